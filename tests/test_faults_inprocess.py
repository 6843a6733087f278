"""Issue 18, row 5: runs in the study's own process only for this repository's own FMU, recognised by its
content (the digest of the FMU ``make fmu`` built), never by a variable it declares; and a run under way
when the study's process died is known on resume (a marker written before it started) and failed with
that reason, or made again in supervised workers, so that a resume never repeats the crash.

The real FMU, the gcc-built misbehaving FMU (a segfault in doStep), real processes and ``kill -9``.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import zipfile

import pandas as pd
import pytest

from fmusa.api import parse_study, run_study
from fmusa.runs.inflight import CRASH_REASON, InFlight
from fmusa.runs.timelimit import own_fmu
from test_misbehaving_fmu import misbehave_fmu, quiet_worker_crashes  # noqa: F401 - fixtures

SEGFAULT = """\
name: crash
fmu: default
parameters:
  k: {variable: k, unit: N/m}
fixed: {F: 411, fault: 1, fault_kind: 1, fault_lo: 2.5e6, fault_hi: 5.5e6}
scenario: {stop_time: 1}
metrics:
  y: {output: y_peak, unit: m}
execution: {timeout_s: 10}
stages:
  grid: {values: {k: [1.0e6, 3.0e6, 5.0e6, 7.0e6]}}
"""


def _cli(*args: str, env: dict | None = None, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fmusa.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env={**os.environ, **(env or {})})


def test_own_fmu_is_known_by_its_content_not_its_variables(tmp_path, fmu_path, misbehave_fmu):  # noqa: F811
    copy = tmp_path / "copy.fmu"
    shutil.copyfile(fmu_path, copy)
    assert own_fmu(fmu_path) and own_fmu(copy)
    assert not own_fmu(misbehave_fmu)
    # our FMU with one byte of its model description changed (the same variables, max_wall_s included)
    other = tmp_path / "other.fmu"
    with zipfile.ZipFile(fmu_path) as zin, zipfile.ZipFile(other, "w", zipfile.ZIP_DEFLATED) as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "modelDescription.xml":
                data = data.replace(b'generationTool="fmusa', b'generationTool="Fmusa')
            zout.writestr(item, data)
    assert b"max_wall_s" in zipfile.ZipFile(other).read("modelDescription.xml")
    assert not own_fmu(other)
    assert not own_fmu(tmp_path)            # a folder, not a built FMU


def test_a_third_party_fmu_behind_fmu_default_never_runs_in_process(tmp_path, misbehave_fmu):  # noqa: F811
    """$FMUSA_FMU with `fmu: default` once ran a third-party FMU in the study's process: its segfault ended
    the study (rc 139). Now its runs are supervised: the crashing ones fail, the study completes."""
    study = tmp_path / "s.yaml"
    study.write_text(SEGFAULT, encoding="utf-8")
    out = tmp_path / "out"
    r = _cli("sweep", str(study), "--out", str(out), "--quiet", "--no-figures", "--workers", "1",
             env={"FMUSA_FMU": str(misbehave_fmu)})
    assert r.returncode == 0, (r.returncode, r.stderr)
    runs = pd.read_csv(out / "runs.csv").set_index("k").sort_index()
    assert list(runs["status"]) == ["ok", "failed", "failed", "ok"]
    assert runs.loc[3e6, "message"].startswith("the FMU crashed the worker process (SIGSEGV")
    assert runs.loc[1e6, "y"] == pytest.approx(411 / 1e6, rel=1e-12)


BIG = """\
name: big
fmu: default
parameters:
  c: {variable: c_y, unit: N/m}
fixed: {F_max: 411, t_ramp: 10}
scenario: {stop_time: 2.0}
metrics:
  max_y: {output: y_max, unit: m}
stages:
  grid: {base: 1.01, exponents: {c: [1200, 1999]}}
"""     # 800 runs of ~1 ms, in chunks of 100


def test_a_chunk_under_way_when_the_study_was_killed_is_made_again_supervised(tmp_path):
    """kill -9 of a study making its runs in its own process (--workers 1): the marker names the chunk
    under way; the resume makes those runs in supervised workers, then goes on here."""
    study = tmp_path / "big.yaml"
    study.write_text(BIG, encoding="utf-8")
    out = tmp_path / "out"
    args = ["sweep", str(study), "--out", str(out), "--quiet", "--no-figures", "--workers", "1"]
    marker = InFlight(out / "runs.csv")
    for attempt in range(3):       # a kill between two chunks finds nothing under way: try again
        proc = subprocess.Popen([sys.executable, "-m", "fmusa.cli", *args], stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL)
        t_end = time.monotonic() + 60
        while not (out / "runs.csv").exists() or (out / "runs.csv").read_bytes().count(b"\n") < 150:
            assert proc.poll() is None and time.monotonic() < t_end, "the study ended before it was killed"
            time.sleep(0.005)
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
        stage, pending = marker.pending()
        if pending:
            break
        shutil.rmtree(out)
    assert stage == "grid" and len(pending) > 1
    kept = pd.read_csv(out / "runs.csv")
    assert not set(kept["run_id"]) & {i for i, _ in pending}       # the chunk under way was not stored
    r = _cli(*args, "--resume")
    assert r.returncode == 0, r.stderr
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert summary["recovered_runs"] == {"runs": len(pending), "stage": "grid",
                                         "how": "made again in supervised workers"}
    runs = pd.read_csv(out / "runs.csv")
    assert len(runs) == 800 and (runs["status"] == "ok").all() and runs["c"].is_unique
    assert not marker.path.exists()                                 # nothing under way once it finished


def test_a_run_under_way_when_the_process_died_is_failed_on_resume_and_never_made_again(tmp_path):
    """One run under way when the process ended (a segfault of an in-process run leaves exactly this on
    disk): the resume records it as failed with that reason and makes it neither then nor later."""
    text = BIG.replace("grid: {base: 1.01, exponents: {c: [1200, 1699]}}", "grid: {values: {c: [1.0e6, 2.0e6]}}")
    study = parse_study(text, tmp_path / "s.yaml")
    out = tmp_path / "out"
    run_study(study, out, figures=False, progress=False)
    marker = InFlight(out / "runs.csv")
    marker.stage = "grid"
    marker.begin([7], [[3.0e6]])
    marker.close(remove=False)
    wider = parse_study(text.replace("[1.0e6, 2.0e6]", "[1.0e6, 2.0e6, 3.0e6]"), tmp_path / "s.yaml")
    r1 = run_study(wider, out, resume=True, figures=False, progress=False)
    assert r1.summary["simulated_this_session"] == 0
    assert r1.summary["recovered_runs"]["how"] == "recorded as failed"
    row = r1.runs.set_index("c").loc[3.0e6]
    assert row["status"] == "failed" and row["message"] == CRASH_REASON and row["run_id"] == 7
    r2 = run_study(wider, out, resume=True, figures=False, progress=False)
    assert r2.summary["simulated_this_session"] == 0 and "recovered_runs" not in r2.summary
    assert r2.runs.set_index("c").loc[3.0e6, "status"] == "failed"
