"""Issue 18, rows 2 and 8: files written whole, and a fresh study that moves the earlier study's report and
figures aside with its runs (no old figure next to the new study's).
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from fmusa.api import parse_study, run_study
from fmusa.files import atomic_path, atomic_write

TWO = """\
name: first
fmu: default
parameters:
  c: {variable: c_y, unit: N/m}
fixed: {F_max: 411, t_ramp: 10}
scenario: {stop_time: 2.0}
metrics:
  max_y: {output: y_max, unit: m}
  max_v: {output: v_y_max, unit: m/s}
stages:
  grid: {values: {c: [4.0e5, 1.0e6, 2.0e6]}}
"""
ONE = TWO.replace("name: first", "name: second").replace("  max_v: {output: v_y_max, unit: m/s}\n", "")


def test_a_fresh_study_moves_the_earlier_report_and_figures_aside(tmp_path):
    out = tmp_path / "out"
    first = run_study(parse_study(TWO, tmp_path / "a.yaml"), out, progress=False)
    old_figures = sorted(p.name for p in (out / "figures").iterdir())
    assert len(old_figures) == 2
    old_report = (out / "report.md").read_text(encoding="utf-8")
    study = tmp_path / "b.yaml"
    study.write_text(ONE, encoding="utf-8")
    r = subprocess.run([sys.executable, "-m", "fmusa.cli", "sweep", str(study), "--out", str(out), "--quiet"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "note: this study started afresh; the earlier runs are kept in" in r.stderr
    assert "figures.previous-1" in r.stderr and "report.previous-1.md" in r.stderr
    new_figures = sorted(p.name for p in (out / "figures").iterdir())
    assert new_figures == ["grid_max_y.png"]                    # the new study's only
    assert sorted(p.name for p in (out / "figures.previous-1").iterdir()) == old_figures
    assert (out / "report.previous-1.md").read_text(encoding="utf-8") == old_report
    assert json.loads((out / "summary.previous-1.json").read_text(encoding="utf-8"))["study"] == "first"
    assert json.loads((out / "summary.json").read_text(encoding="utf-8"))["study"] == "second"
    assert (out / "runs.previous-1.csv").exists() and (out / "runs.previous-1.csv.study.json").exists()
    assert first.summary["runs"] == 3
    # a resume moves nothing
    r = subprocess.run([sys.executable, "-m", "fmusa.cli", "sweep", str(study), "--out", str(out), "--quiet",
                        "--resume"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and "started afresh" not in r.stderr, r.stderr
    assert not (out / "figures.previous-2").exists()


def test_an_atomic_write_that_fails_leaves_the_earlier_file_and_no_temporary(tmp_path):
    target = tmp_path / "summary.json"
    atomic_write(target, '{"a": 1}')
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text('{"a": ', encoding="utf-8")       # half written, then the writer fails
            raise RuntimeError("killed")
    assert json.loads(target.read_text(encoding="utf-8")) == {"a": 1}
    assert [p.name for p in tmp_path.iterdir()] == ["summary.json"]
    if os.name == "posix":        # the umask's mode, not mkstemp's 0600
        mask = os.umask(0)
        os.umask(mask)
        assert target.stat().st_mode & 0o777 == 0o666 & ~mask


def test_every_whole_file_writer_goes_through_the_atomic_writer():
    """No whole-file writer bypasses fmusa.files (write_text, savefig or to_csv on the final path)."""
    src = Path(__file__).resolve().parents[1] / "src" / "fmusa"
    bad = []
    for f in sorted(src.rglob("*.py")):
        if f.name in ("bench.py", "files.py", "archive.py"):     # bench output; the writer; FMU unpacking
            continue
        for i, line in enumerate(f.read_text(encoding="utf-8").splitlines(), 1):
            code = line.split("#")[0]
            if (".write_text(" in code or ".savefig(" in code and "savefig(tmp" not in code
                    or ".to_csv(" in code and "to_csv(tmp" not in code):
                bad.append(f"{f.relative_to(src)}:{i}: {line.strip()}")
    assert not bad, "\n".join(bad)
