"""Fault matrix: input that must not hang, exhaust memory or fill the disk, and outputs that cannot be written.

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


def fmusa_cli(*args: str, cwd: Path | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fmusa.cli", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=timeout)


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


def test_extraction_folders_of_killed_processes_are_removed(tmp_path):
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True).stdout.strip()
    orphan = Path(tempfile.mkdtemp(prefix=PREFIX))
    (orphan / OWNER_FILE).write_text(dead)
    mine = Path(tempfile.mkdtemp(prefix=PREFIX))
    (mine / OWNER_FILE).write_text(str(os.getpid()))
    try:
        removed = remove_orphans()
        assert orphan in removed and not orphan.exists()
        assert mine.exists()
    finally:
        shutil.rmtree(orphan, ignore_errors=True)
        shutil.rmtree(mine, ignore_errors=True)


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


def test_an_fmu_whose_binary_does_not_load_fails_its_runs_with_the_cause(tmp_path):
    bad = tmp_path / "Short.fmu"
    with zipfile.ZipFile(default_fmu_path()) as zin, zipfile.ZipFile(bad, "w") as zout:
        for info in zin.infolist():
            data = zin.read(info.filename)
            zout.writestr(info.filename, data[:100] if info.filename.endswith(".so") else data)
    text = SMALL.replace("fmu: default", f"fmu: {bad}") + "  roi: {}\n  search: {inner: c}\n"
    study = parse_study(text, tmp_path / "s.yaml")
    with pytest.raises(StudyError, match=r"all 2 grid runs failed, so there is no region of interest; the first "
                                         r"says: the FMU could not be loaded or instantiated: .*ScrewVertebra.so"):
        run_study(study, tmp_path / "out", figures=False, progress=False)
    import pandas as pd
    runs = pd.read_csv(tmp_path / "out" / "runs.csv")
    assert (runs["status"] == "failed").all() and len(runs) == 2
    assert runs["message"].str.contains("could not be loaded or instantiated").all()
    assert not runs["message"].str.contains("worker exited").any()


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
