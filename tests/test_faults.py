"""Fault matrix: input that must not hang, exhaust memory or fill the disk, outputs that cannot be written, runs
that take too long, a study killed mid-run and a Dask scheduler that is not there.

Each test reproduces one fault as a careless or hostile input would and asserts the behaviour: a clear error
that names the input and the fix, within a bounded time, with what was on disk still there. The real FMU and
the real ``fmusa`` command are used; the archives are the built FMU rewritten by the tests.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import pytest

from fmusa.api import load_study, parse_study, run_study
from fmusa.fmi.archive import ENV_MAX_BYTES, OWNER_FILE, PREFIX, extract_fmu, remove_orphans
from fmusa.fmi.info import FMUError, default_fmu_path, read_fmu_info
from fmusa.errors import UsageError
from fmusa.files import OutputError
from fmusa.study.schema import StudyError
from slow_study import SLOW   # the study of the time-limit tests

ROOT = Path(__file__).resolve().parents[1]

SMALL = """\
name: small
fmu: default
parameters:
  c: {variable: c_y, unit: N/m}
fixed: {F_max: 411, t_ramp: 10}
scenario: {stop_time: 12}
metrics:
  max_y: {output: y_max, unit: m}
constraints:
  - {name: translation, metric: max_y, max: 5.0e-4}
stages:
  grid: {values: {c: [4.0e5, 1.0e6]}}
"""


def fmusa_cli(*args: str, cwd: Path | None = None, timeout: float = 120,
              env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fmusa.cli", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout, env=None if env is None else {**os.environ, **env})


# ----------------------------------------------------------------------------------------------- study files
def test_yaml_alias_bomb_is_refused_quickly(tmp_path):
    levels = ["  a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    for prev, cur in zip("abcdefgh", "bcdefghi"):
        levels.append(f"  {cur}: &{cur} [" + ", ".join([f"*{prev}"] * 10) + "]")   # 10^9 values in all
    f = tmp_path / "bomb.yaml"
    f.write_text(SMALL + "paper:\n" + "\n".join(levels) + "\n")
    t0 = time.perf_counter()
    with pytest.raises(StudyError, match=r"bomb.yaml:\d+: 'paper' expands to more than 100000 values"):
        load_study(f)
    assert time.perf_counter() - t0 < 5.0


@pytest.mark.parametrize("exponents, message", [
    ("[0, 100000]", r"25\^100000 is not a finite, nonzero double; narrow the range"),
    ("[-100000, 0]", r"25\^-100000 is not a finite, nonzero double"),
])
def test_grid_exponents_out_of_range_are_refused(exponents, message):
    text = SMALL.replace("grid: {values: {c: [4.0e5, 1.0e6]}}", f"grid: {{base: 25, exponents: {{c: {exponents}}}}}")
    with pytest.raises(StudyError, match=r"s.yaml:\d+: key 'c' in 'stages.grid.exponents': " + message):
        parse_study(text, "s.yaml")


def test_grid_with_too_many_points_is_refused():
    text = SMALL.replace("parameters:\n  c: {variable: c_y, unit: N/m}\n",
                         "parameters:\n  c: {variable: c_y, unit: N/m}\n  d: {variable: d_y, unit: N.s/m}\n")
    text = text.replace("grid: {values: {c: [4.0e5, 1.0e6]}}", "grid: {base: 2, exponents: {c: [0, 1000], d: [0, 1000]}}")
    with pytest.raises(StudyError, match=r"'stages.grid' has 1002001 points, more than 1000000"):
        parse_study(text, "s.yaml")


def test_a_device_or_a_huge_file_is_not_read_as_a_study(tmp_path):
    with pytest.raises(StudyError, match=r"/dev/zero:1: not a regular file"):
        load_study("/dev/zero")
    big = tmp_path / "big.yaml"
    with open(big, "wb") as f:
        f.write(b"#" * 2_000_001)
    with pytest.raises(StudyError, match=r"big.yaml:1: larger than 1000000 bytes"):
        load_study(big)
    binary = tmp_path / "bin.yaml"
    binary.write_bytes(b"name: x\n\xff\xfe")
    with pytest.raises(StudyError, match=r"bin.yaml:1: not UTF-8 text"):
        load_study(binary)


# ----------------------------------------------------------------------------------------------- FMU archives
def rewrite_fmu(src: Path, dst: Path, extra: dict[str, bytes] | None = None,
                compression: int = zipfile.ZIP_DEFLATED) -> Path:
    """The built FMU copied member by member into ``dst``, plus ``extra`` members (name -> bytes)."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", compression) as zout:
        for info in zin.infolist():
            zout.writestr(info.filename, zin.read(info.filename))
        for name, data in (extra or {}).items():
            zout.writestr(zipfile.ZipInfo(name), data)
    return dst


@pytest.mark.parametrize("member, why", [
    ("/etc/fmusa-evil", "is an absolute path"),
    ("resources/../../fmusa-evil", r"leads out of the archive's folder \('..'\)"),
    ("resources\\evil", "contains a backslash"),
])
def test_members_that_leave_the_folder_are_refused_when_the_fmu_is_read(tmp_path, member, why):
    fmu = rewrite_fmu(default_fmu_path(), tmp_path / "Evil.fmu", {member: b"x"})
    with pytest.raises(FMUError, match=f"Evil.fmu: member '{member.replace(chr(92), chr(92) * 2)}' {why}"):
        read_fmu_info(fmu)
    before = set(Path(tempfile.gettempdir()).glob(PREFIX + "*"))
    with pytest.raises(FMUError, match=why):
        extract_fmu(fmu)
    assert set(Path(tempfile.gettempdir()).glob(PREFIX + "*")) <= before      # nothing new left behind
    assert not Path("/etc/fmusa-evil").exists() and not (tmp_path.parent / "fmusa-evil").exists()


def test_a_damaged_member_is_named(tmp_path):
    fmu = rewrite_fmu(default_fmu_path(), tmp_path / "Damaged.fmu")
    with zipfile.ZipFile(fmu) as z:
        info = next(i for i in z.infolist() if i.filename.endswith(".so"))
    data = bytearray(fmu.read_bytes())
    header = info.header_offset
    name_len = int.from_bytes(data[header + 26:header + 28], "little")
    extra_len = int.from_bytes(data[header + 28:header + 30], "little")
    start = header + 30 + name_len + extra_len
    for k in range(start + 100, start + 400):          # scramble the compressed bytes of the binary
        data[k] ^= 0x5A
    fmu.write_bytes(bytes(data))
    with pytest.raises(FMUError, match=rf"Damaged.fmu: member '{info.filename}' is damaged .*export or download"):
        extract_fmu(fmu, tmp_path / "x")


def test_unpacking_is_bounded(tmp_path, monkeypatch):
    fmu = rewrite_fmu(default_fmu_path(), tmp_path / "Big.fmu", {"resources/big.bin": b"\0" * 3_000_000})
    monkeypatch.setenv(ENV_MAX_BYTES, "2000000")
    before = set(Path(tempfile.gettempdir()).glob(PREFIX + "*"))
    with pytest.raises(FMUError, match=r"Big.fmu: unpacks to \d+ bytes, more than the limit of 2000000; .*"
                                       + ENV_MAX_BYTES):
        extract_fmu(fmu)
    assert set(Path(tempfile.gettempdir()).glob(PREFIX + "*")) <= before
    monkeypatch.setenv(ENV_MAX_BYTES, "a lot")
    with pytest.raises(FMUError, match=f"{ENV_MAX_BYTES}='a lot' is not a number of bytes"):
        extract_fmu(fmu)


#: A process that claims an extraction folder (argv[1]) and then writes into its owner file a process id that
#: means nothing here: what a fmusa in another container, or on another host sharing the temporary folder,
#: leaves. It prints "ready" and sleeps until killed.
CLAIMER = ("import sys, time; from fmusa.fmi.archive import claim_folder, OWNER_FILE, _HELD\n"
           "claim_folder(sys.argv[1]); fh = _HELD[sys.argv[1]]; fh.seek(0); fh.truncate(); fh.write(sys.argv[2])\n"
           "fh.flush(); print('ready', flush=True); time.sleep(600)")


def test_extraction_folders_are_owned_by_a_lock_not_a_process_id(tmp_path, monkeypatch):
    """A folder whose owner is alive is kept although its recorded process id is dead here (another PID
    namespace); once the owner is killed, its folder is removed; a folder of this process is never judged."""
    from fmusa.fmi import archive
    monkeypatch.setattr(archive, "GRACE_S", 0.0)
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    live = tmp_path / f"{PREFIX}live"
    live.mkdir()
    owner = subprocess.Popen([sys.executable, "-c", CLAIMER, str(live), dead], stdout=subprocess.PIPE, text=True)
    try:
        assert owner.stdout.readline().strip() == "ready"
        assert (live / OWNER_FILE).read_text() == dead                 # the id says: dead
        mine = tmp_path / f"{PREFIX}mine"
        mine.mkdir()
        archive.claim_folder(mine)
        stale = tmp_path / f"{PREFIX}stale"                            # an owner file nobody holds
        stale.mkdir()
        (stale / OWNER_FILE).write_text(str(os.getpid()))              # ... with a live id
        assert remove_orphans(tmp_path) == [stale]
        assert live.exists() and mine.exists() and not stale.exists()
    finally:
        owner.kill()
        owner.wait()
    assert remove_orphans(tmp_path) == [live]                          # killed: its lock is free
    assert mine.exists()
    archive.remove_folder(mine)
    assert not mine.exists()


def test_a_new_extraction_folder_is_not_judged_while_it_is_made(tmp_path):
    from fmusa.fmi import archive
    young = tmp_path / f"{PREFIX}young"
    young.mkdir()
    (young / OWNER_FILE).write_text("")          # created, not yet locked by its maker
    assert archive.remove_orphans(tmp_path) == [] and young.exists()


# ----------------------------------------------------------------------------------------------- outputs
def test_a_file_given_as_out_is_refused_before_any_run(tmp_path):
    study = tmp_path / "s.yaml"
    study.write_text(SMALL)
    target = tmp_path / "afile"
    target.write_text("keep me")
    r = fmusa_cli("sweep", str(study), "--out", str(target), "--quiet")
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert f"output folder (--out) {target}: is a file, not a folder" in r.stderr
    assert target.read_text() == "keep me"


def test_an_out_folder_that_cannot_be_made_is_refused(tmp_path):
    study = tmp_path / "s.yaml"
    study.write_text(SMALL)
    (tmp_path / "blocker").write_text("")
    r = fmusa_cli("sweep", str(study), "--out", str(tmp_path / "blocker" / "out"), "--quiet")
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and "cannot be written" in r.stderr


def test_figures_that_cannot_be_written_keep_runs_and_summary(tmp_path):
    study = parse_study(SMALL, tmp_path / "s.yaml")
    out = tmp_path / "out"
    out.mkdir()
    (out / "figures").write_text("not a folder")
    with pytest.raises(OutputError, match=r"figures folder .*: is a file, not a folder.*runs.csv and "
                                          r"summary.json in .* are complete"):
        run_study(study, out, progress=False)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"] == 2
    assert len((out / "runs.csv").read_text().strip().splitlines()) == 3


# ----------------------------------------------------------------------------------------------- the run store
def test_a_rerun_without_resume_keeps_the_earlier_runs(tmp_path):
    study = parse_study(SMALL, tmp_path / "s.yaml")
    out = tmp_path / "out"
    run_study(study, out, figures=False, progress=False)
    first = (out / "runs.csv").read_text()
    study2 = parse_study(SMALL.replace("[4.0e5, 1.0e6]", "[5.0e5, 2.0e6, 3.0e6]"), tmp_path / "s.yaml")
    run_study(study2, out, figures=False, progress=False)
    assert (out / "runs.previous-1.csv").read_text() == first          # moved aside, not emptied
    assert len((out / "runs.csv").read_text().strip().splitlines()) == 4
    run_study(study, out, figures=False, progress=False)
    assert (out / "runs.previous-2.csv").exists()


def test_two_studies_cannot_write_the_same_runs_file(tmp_path):
    from fmusa.runs.store import RunStore, StoreBusyError

    study = tmp_path / "s.yaml"
    study.write_text(SMALL)
    out = tmp_path / "out"
    holder = RunStore(out / "runs.csv", ["c"], ["max_y"])
    try:
        with pytest.raises(StoreBusyError, match=rf"runs.csv: another fmusa study \(pid {os.getpid()}\) is "
                                                 r"writing to this folder; .* another --out"):
            RunStore(out / "runs.csv", ["c"], ["max_y"])
        r = fmusa_cli("sweep", str(study), "--out", str(out), "--quiet")
        assert r.returncode == 2 and "Traceback" not in r.stderr
        assert "is writing to this folder" in r.stderr
    finally:
        holder.close()
    RunStore(out / "runs.csv", ["c"], ["max_y"], resume=True).close()     # free again once closed


def test_an_fmu_whose_binary_does_not_load_stops_the_study_before_any_run(tmp_path):
    """Issue 17: the FMU is loaded once before the first batch; a binary that cannot load stops the study
    at once with the loader's reason and the fix, and no runs.csv is written."""
    from fmusa.runs.preflight import FMULoadError

    bad = tmp_path / "Short.fmu"
    with zipfile.ZipFile(default_fmu_path()) as zin, zipfile.ZipFile(bad, "w") as zout:
        for info in zin.infolist():
            data = zin.read(info.filename)
            zout.writestr(info.filename, data[:100] if info.filename.endswith(".so") else data)
    text = SMALL.replace("fmu: default", f"fmu: {bad}") + "  roi: {}\n  search: {inner: c}\n"
    study = parse_study(text, tmp_path / "s.yaml")
    with pytest.raises(FMULoadError, match=r"Short.fmu: the FMU cannot be loaded on this machine: .*ScrewVertebra.so"
                                           r".*Fix: the binary is damaged"):
        run_study(study, tmp_path / "out", figures=False, progress=False)
    assert not (tmp_path / "out" / "runs.csv").exists()


def _paper_text() -> str:
    text = (ROOT / "studies" / "paper.yaml").read_text()
    return text[:text.index("\npaper:")] + "\n"


def test_resume_refuses_runs_made_under_another_scenario(tmp_path):
    out = tmp_path / "out"
    run_study(parse_study(_paper_text(), tmp_path / "p.yaml"), out, figures=False, progress=False)
    changed = parse_study(_paper_text().replace("F_max: 411", "F_max: 200"), tmp_path / "p.yaml")
    with pytest.raises(UsageError, match=r"cannot resume: the study changed since these runs were made "
                                         r"\(fixed.F_max: 411 → 200\), so their metrics would be stale"):
        run_study(changed, out, resume=True, figures=False, progress=False)
    fresh = run_study(changed, out, figures=False, progress=False)        # the old runs are kept aside
    assert (out / "runs.previous-1.csv").exists()
    assert fresh.summary["optimum"]["c"] == pytest.approx(200 / 5e-4, rel=1e-3)


def test_resume_after_new_thresholds_recomputes_feasibility(tmp_path):
    out = tmp_path / "out"
    run_study(parse_study(_paper_text(), tmp_path / "p.yaml"), out, figures=False, progress=False)
    doubled = _paper_text().replace("max: 5.0e-4", "max: 1.0e-3").replace("max: 5.0e-5", "max: 1.0e-4")
    resumed = run_study(parse_study(doubled, tmp_path / "p.yaml"), out, resume=True, figures=False, progress=False)
    fresh = run_study(parse_study(doubled, tmp_path / "p.yaml"), tmp_path / "fresh", figures=False, progress=False)
    assert resumed.summary["optimum"] == fresh.summary["optimum"]
    assert resumed.summary["optimum"]["c"] == pytest.approx(411 / 1e-3, rel=1e-3)
    assert resumed.summary["simulated_this_session"] < fresh.summary["simulated_this_session"]


def test_a_damaged_cell_in_runs_csv_cannot_change_the_answer(tmp_path):
    import pandas as pd

    out = tmp_path / "out"
    study = parse_study(_paper_text(), tmp_path / "p.yaml")
    ref = run_study(study, out, figures=False, progress=False).summary["optimum"]
    lines = (out / "runs.csv").read_text().splitlines(keepends=True)
    header = lines[0].rstrip("\r\n").split(",")
    cells = lines[5].rstrip("\r\n").split(",")
    cells[header.index("feasible")] = "garbage"          # a flag is never read back: recomputed
    lines[5] = ",".join(cells) + "\r\n"
    (out / "runs.csv").write_text("".join(lines))
    again = run_study(study, out, resume=True, figures=False, progress=False)
    assert again.summary["optimum"] == ref and again.summary["simulated_this_session"] == 0
    cells[header.index("max_y")] = "1.2.3"               # a metric is: an error that names line and column
    lines[5] = ",".join(cells) + "\r\n"
    (out / "runs.csv").write_text("".join(lines))
    with pytest.raises(UsageError, match=r"runs.csv:6: column 'max_y' holds '1.2.3', not a number; fix or "
                                         r"delete that line"):
        run_study(study, out, resume=True, figures=False, progress=False)
    assert len(pd.read_csv(out / "runs.csv")) == len(lines) - 1          # nothing was lost


# ----------------------------------------------------------------------------------------------- time limits


@pytest.mark.parametrize("params,inputs", [
    ({"c_y": 1e28, "d_y": 488}, {}),                                   # the axial pullout, 12 s: 9 s once
    ({"c_y": 1e40, "d_y": 488}, {}),                                   # more than 300 s once
    ({"c_y": 1e40, "F_max": 411, "t_ramp": 0.05, "rI_y": -0.009}, {"F_ext_x": 20.0}),   # 6-DOF, stiff axis
    ({"c_x": 1e40, "rI_y": -0.009}, {"F_ext_x": 20.0}),                # 6-DOF, stiff lateral element
    ({"c_y": 1e300, "d_y": 488}, {}),                                  # beyond what doubles can integrate
])
def test_the_fmu_never_spins_on_extreme_stiffness(fmu_path, params, inputs):
    """What once made one fmi2DoStep spin for minutes either finishes within seconds or ends in a clear error."""
    from fmusa.fmi.info import FMURunError
    from fmusa.fmi.runner import FMURunner

    stop = 12.0 if not inputs else 0.1
    with FMURunner(fmu_path) as fmu:
        t0 = time.monotonic()
        try:
            out = fmu.run_final(params, stop_time=stop, inputs=inputs, outputs=["y_max", "n_steps"])
            assert out["n_steps"] < 1e6
        except FMURunError as exc:
            assert "not finite" in str(exc) or "work budget" in str(exc), str(exc)
        assert time.monotonic() - t0 < 10.0


def test_the_fmus_step_budget_ends_a_run_with_the_reason(fmu_path):
    """max_steps: a run that needs more internal steps than allowed stops with fmi2Error naming the budget."""
    from fmusa.fmi.info import FMURunError
    from fmusa.fmi.runner import FMURunner

    with FMURunner(fmu_path) as fmu:
        params = {"F_max": 411, "t_ramp": 0.05, "h_max": 1e-6, "max_steps": 1000}
        t0 = time.monotonic()
        with pytest.raises(FMURunError, match=r"work budget used up: 1000 internal steps \(max_steps\) took the "
                                              r"solution only from t = 0 to [0-9.e-]+ s of the step to 0\.1 s "
                                              r".*raise max_steps"):
            fmu.run_final(params, stop_time=0.1, inputs={"F_ext_x": 20.0}, outputs=["y_max"])
        assert time.monotonic() - t0 < 5.0
        # the same run within its budget
        ok = fmu.run_final({**params, "max_steps": 200000}, stop_time=0.1, inputs={"F_ext_x": 20.0},
                           outputs=["y_max", "n_steps"])
        assert 1e5 <= ok["n_steps"] <= 200000


def _read_runs(out: Path):
    import pandas as pd
    return pd.read_csv(out / "runs.csv", keep_default_na=False, na_values=[""]).set_index("h")


def _extraction_folders(tmp: Path) -> list[str]:
    return sorted(p.name for p in tmp.glob(PREFIX + "*"))


def _sweep_with_tmp(tmp_path: Path, text: str, **env: str):
    """``fmusa sweep`` of the study ``text`` with its temporary files in ``tmp_path/tmp``: (result, wall s,
    out folder, tmp folder)."""
    tmp = tmp_path / "tmp"
    tmp.mkdir(exist_ok=True)
    study = tmp_path / "s.yaml"
    study.write_text(text)
    out = tmp_path / "out"
    t0 = time.monotonic()
    r = fmusa_cli("sweep", str(study), "--out", str(out), "--quiet", "--no-figures", env={"TMPDIR": str(tmp), **env})
    return r, time.monotonic() - t0, out, tmp


@pytest.mark.parametrize("scenario", ["one doStep", "sampled"])
def test_a_slow_run_in_process_stops_at_timeout_s(tmp_path, scenario):
    """Our FMU in a small batch runs in this process (no worker start-up), yet every run keeps to timeout_s:
    fmusa sets the FMU's max_wall_s to it, and a sampled run also stops at its first communication point
    past it."""
    text = SLOW
    if scenario == "sampled":   # 500 doSteps of ~0.2 s each at h_max = 1e-8: no single one reaches 1 s
        text = SLOW.replace("stop_time: 0.1,", "stop_time: 0.1, step: 0.0002,").replace("1.0e-9]", "1.0e-8]")
    r, wall, out, tmp = _sweep_with_tmp(tmp_path, text)
    assert r.returncode == 0, r.stderr
    runs = _read_runs(out)
    slow = runs.loc[1e-9 if scenario == "one doStep" else 1e-8]
    assert slow["status"] == "failed"
    assert slow["message"].startswith("timed out after 1 s (execution.timeout_s; ")
    assert "raise execution.timeout_s and rerun without --resume" in slow["message"]
    assert "worker process" not in slow["message"]                      # in this process, not in a worker
    if scenario == "one doStep":
        assert "through its parameter max_wall_s, which fmusa sets to execution.timeout_s" in slow["message"]
        assert "work budget used up: 1 s of computing (max_wall_s)" in slow["message"]
    assert 1.0 <= slow["seconds"] < 2.5, slow["seconds"]
    assert runs.loc[1e-5, "status"] == "ok" and runs.loc[1e-5, "max_y"] > 0
    assert wall < 10, f"the study took {wall:.1f} s"
    assert _extraction_folders(tmp) == []


@pytest.mark.parametrize("own, expect", [
    (0.3, "work budget used up: 0.3 s of computing (max_wall_s)"),   # the study's budget, within timeout_s
    (0, "timed out after 1 s (execution.timeout_s; its worker process was stopped)"),   # none: supervised
])
def test_a_budget_the_study_sets_itself_is_kept_and_never_outlasts_timeout_s(tmp_path, own, expect):
    r, wall, out, tmp = _sweep_with_tmp(tmp_path, SLOW.replace("max_steps: 2000000000}",
                                                               f"max_steps: 2000000000, max_wall_s: {own}}}"))
    assert r.returncode == 0, r.stderr
    slow = _read_runs(out).loc[1e-9]
    assert slow["status"] == "failed" and expect in slow["message"], slow["message"]
    if own:      # the FMU's own words: the study's max_wall_s is the one to raise, not timeout_s
        assert "timed out" not in slow["message"] and slow["seconds"] < 1.0
    assert wall < 10 and _extraction_folders(tmp) == []


def test_an_fmu_without_a_time_budget_never_runs_unsupervised(tmp_path):
    """`fmu: default` pointed ($FMUSA_FMU) at an FMU without max_wall_s (ours, with the parameter renamed):
    even a batch of four runs goes to a supervised worker, which is stopped after timeout_s, run by run."""
    fmu = tmp_path / "NoBudget.fmu"
    with zipfile.ZipFile(default_fmu_path()) as zin, zipfile.ZipFile(fmu, "w", zipfile.ZIP_DEFLATED) as zout:
        for info in zin.infolist():
            data = zin.read(info.filename)
            if info.filename == "modelDescription.xml":
                assert b'name="max_wall_s"' in data
                data = data.replace(b'name="max_wall_s"', b'name="wall_budget_s"')
            zout.writestr(info.filename, data)
    text = SLOW.replace("[1.0e-5, 1.0e-9]", "[1.0e-5, 1.0e-9, 2.0e-5, 2.0e-9]")
    r, wall, out, tmp = _sweep_with_tmp(tmp_path, text, FMUSA_FMU=str(fmu))
    assert r.returncode == 0, r.stderr
    runs = _read_runs(out)
    for h in (1e-9, 2e-9):          # each slow run its own 1 s, one worker after the other
        row = runs.loc[h]
        assert row["status"] == "failed", row.to_dict()
        assert row["message"].startswith("timed out after 1 s (execution.timeout_s; its worker process was "
                                         "stopped): the FMU hangs or is too slow"), row["message"]
        assert 1.0 <= row["seconds"] < 2.0
    assert (runs.loc[[1e-5, 2e-5], "status"] == "ok").all()
    assert wall < 12, f"the study took {wall:.1f} s"
    assert _extraction_folders(tmp) == []


def test_a_budget_past_the_integer_range_is_refused_before_any_run(tmp_path):
    """`raise max_steps`, taken literally: 1e12 does not fit an fmi2Integer, which would wrap it silently into a
    negative number; the study is refused, naming the line and the range."""
    study = parse_study(SLOW.replace("max_steps: 2000000000", "max_steps: 1.0e12"), tmp_path / "s.yaml")
    with pytest.raises(StudyError, match=r"s.yaml:5: fixed 'max_steps': max_steps is an Integer \(32 bits\); "
                                         r"1000000000000 is out of its range: give a value from -2147483648 to "
                                         r"2147483647"):
        run_study(study, tmp_path / "out", figures=False, progress=False)
    assert not (tmp_path / "out" / "runs.csv").exists()


# ----------------------------------------------------------------------------------------------- kill -9
#: 500 runs of the 6-DOF case (~10 ms each): a batch large enough for the worker pool, over a few seconds.
BIG = """\
name: big
fmu: default
parameters:
  c: {variable: c_y, unit: N/m}
fixed: {F_max: 411, t_ramp: 0.05, rtol: 1.0e-3, h_max: 1.0e-4}
scenario: {stop_time: 0.1, inputs: {F_ext_x: 20}}
metrics:
  max_y: {output: y_max, unit: m}
stages:
  grid: {base: 1.01, exponents: {c: [1200, 1699]}}
"""


def _data_lines(path: Path) -> list[str]:
    """The complete data lines of a runs.csv (a line a kill cut short is not one)."""
    text = path.read_bytes().decode() if path.exists() else ""      # as written: rows end in \r\n
    lines = text.split("\r\n")
    return [ln for ln in lines[1:-1] if ln]


def _alive(procs) -> list:
    import psutil
    out = []
    for p in procs:
        try:       # is_running: not a process that took over the PID since
            if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                out.append(p)
        except psutil.NoSuchProcess:
            pass
    return out


def test_kill_9_of_a_sweep_takes_its_workers_along_and_resume_completes(tmp_path):
    psutil = pytest.importorskip("psutil")
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    study = tmp_path / "big.yaml"
    study.write_text(BIG)
    out = tmp_path / "out"
    args = [sys.executable, "-m", "fmusa.cli", "sweep", str(study), "--out", str(out), "--quiet", "--no-figures",
            "--workers", "2"]
    fmu = shutil.copy(default_fmu_path(), tmp_path / "ScrewVertebra.fmu")   # the same FMU for the resume
    env = {**os.environ, "TMPDIR": str(tmp), "FMUSA_FMU": str(fmu)}
    proc = subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    workers: list = []
    try:
        sweep = psutil.Process(proc.pid)
        t_end = time.monotonic() + 60
        while True:      # mid-run: both workers started and the first results on disk
            workers = sweep.children(recursive=True)
            if len(workers) >= 2 and len(_data_lines(out / "runs.csv")) >= 10:
                break
            assert proc.poll() is None, f"the study ended before it could be killed: {proc.stderr.read()}"
            assert time.monotonic() < t_end, "the study did not start its workers within 60 s"
            time.sleep(0.02)
        proc.kill()
        proc.wait(10)
        t_kill = time.monotonic()
        while _alive(workers) and time.monotonic() - t_kill < 5:
            time.sleep(0.05)
        left = _alive(workers)
        assert not left, f"workers {[p.pid for p in left]} outlived the killed study"
        print(f"{len(workers)} workers gone {time.monotonic() - t_kill:.2f} s after kill -9")
    finally:       # no stray process, whatever failed
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        for p in _alive(workers):
            p.kill()
        proc.stderr.close()
    on_disk = _data_lines(out / "runs.csv")
    assert 10 <= len(on_disk) < 500
    assert _extraction_folders(tmp)          # the killed study could not remove its own

    r = fmusa_cli("sweep", str(study), "--out", str(out), "--resume", "--quiet", "--no-figures", "--workers", "2",
                  env={"TMPDIR": str(tmp), "FMUSA_FMU": str(fmu)})
    assert r.returncode == 0, r.stderr
    final = _data_lines(out / "runs.csv")
    assert final[:len(on_disk)] == on_disk                 # the runs on disk are still there, unchanged
    assert len(final) == 500 and all(",ok,," in ln for ln in final)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"] == 500 and summary["simulated_this_session"] == 500 - len(on_disk)
    assert _extraction_folders(tmp) == []                  # the resumed study removed the killed one's folder


# ----------------------------------------------------------------------------------------------- Dask
@pytest.mark.parametrize("address, message", [
    ("tcp://127.0.0.1:1", r"cannot reach the Dask scheduler at tcp://127.0.0.1:1 \(--scheduler, or "
                          r"execution.scheduler in the study file\): Connection refused; start it there "
                          r"\(`dask scheduler`, .*\), correct the address, or leave the scheduler out"),
    ("127.0.0.1", r"'127.0.0.1' \(--scheduler, or execution.scheduler in the study file\) is not a Dask "
                  r"scheduler address \(.*port.*\); write it as tcp://HOST:PORT"),
    ("web server", r"cannot reach the Dask scheduler at ADDRESS .*: it accepts connections but does not answer "
                   r"as a Dask scheduler within 5 s; is it a Dask scheduler\? \(its port is 8786 by default; "
                   r"8787 is its dashboard\); start it there"),
])
def test_an_unreachable_scheduler_is_one_clear_line_and_costs_nothing(tmp_path, address, message):
    import http.server
    import re
    import threading

    server = None
    if address == "web server":     # a mistake: the dashboard's port (or any web server) for the scheduler's
        server = http.server.HTTPServer(("127.0.0.1", 0), http.server.BaseHTTPRequestHandler)
        threading.Thread(target=server.serve_forever, daemon=True).start()
        address = f"tcp://127.0.0.1:{server.server_address[1]}"
        message = message.replace("ADDRESS", address)
    try:
        study = tmp_path / "s.yaml"
        study.write_text(SMALL)
        out = tmp_path / "out"
        assert fmusa_cli("sweep", str(study), "--out", str(out), "--quiet", "--no-figures").returncode == 0
        before = {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()}
        t0 = time.monotonic()
        r = fmusa_cli("sweep", str(study), "--out", str(out), "--quiet", "--no-figures", "--scheduler", address)
        wall = time.monotonic() - t0
    finally:
        if server is not None:
            server.shutdown()
            server.server_close()
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    error = r.stderr.strip().splitlines()
    assert len(error) == 1 and error[0].startswith("fmusa sweep: ") and re.search(message, error[0]), r.stderr
    assert wall < 10, f"the error took {wall:.1f} s"
    assert {p.name: p.read_bytes() for p in out.iterdir() if p.is_file()} == before    # byte for byte
