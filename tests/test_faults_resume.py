"""Issue 18, rows 1 and 2: a resumed study reuses a stored run only while everything that decides it is
unchanged, in every stage that keeps runs (the grid's runs.csv and the sensitivity stage's file), and a
record of what made the runs that cannot be read refuses the resume instead of being rewritten.

The real built FMU; each change is made alone to a study that ran, and ``--resume`` must be refused with a
message that names the change.
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from fmusa.api import parse_study, run_study
from fmusa.errors import UsageError

BASE = """\
name: fp
fmu: default
parameters:
  c: {variable: c_y, unit: N/m, scale: 1.0, offset: 0.0}
fixed: {F_max: 411, t_ramp: 10}
scenario: {stop_time: 2.0, step: 0.5}
metrics:
  max_y: {output: y_max, unit: m}
constraints:
  - {name: translation, metric: max_y, max: 5.0e-4}
stages:
  grid: {values: {c: [4.0e5, 1.0e6]}}
"""

SENS = """\
name: fps
fmu: default
parameters:
  c: {variable: c_y, unit: N/m}
fixed: {F_max: 411, t_ramp: 10}
scenario: {stop_time: 2.0}
metrics:
  max_y: {output: y_max, unit: m}
stages:
  grid: {values: {c: [4.0e5]}}
  sensitivity:
    methods: [morris]
    morris_trajectories: 4
    seed: 1
    outputs: [max_y]
    parameters:
      p: {variable: cg_y, bounds: [-0.008, -0.006], distribution: uniform, unit: m}
"""


def _run(tmp_path: Path, text: str, out: Path, resume: bool = False):
    return run_study(parse_study(text, tmp_path / "s.yaml"), out, resume=resume, figures=False, progress=False)


@pytest.mark.parametrize("old, new, named", [
    ("variable: c_y, unit: N/m, scale: 1.0", "variable: c_x, unit: N/m, scale: 1.0", "parameters.c"),
    ("scale: 1.0, offset: 0.0", "scale: 2.0, offset: 0.0", "parameters.c"),
    ("scale: 1.0, offset: 0.0", "scale: 1.0, offset: 1.0", "parameters.c"),
    ("fixed: {F_max: 411, t_ramp: 10}", "fixed: {F_max: 300, t_ramp: 10}", "fixed.F_max"),
    ("fixed: {F_max: 411, t_ramp: 10}", "fixed: {F_max: 411, t_ramp: 10, d_y: 500}", "fixed.d_y"),
    ("stop_time: 2.0, step: 0.5", "stop_time: 3.0, step: 0.5", "scenario.stop_time"),
    ("stop_time: 2.0, step: 0.5", "stop_time: 2.0, step: 0.25", "scenario.step"),
    ("stop_time: 2.0, step: 0.5}", "stop_time: 2.0, step: 0.5, inputs: {y_in: 0.001}}", "scenario.inputs"),
    ("max_y: {output: y_max, unit: m}", "max_y: {output: v_y_max, unit: m}", "metrics.max_y"),
    ("max_y: {output: y_max, unit: m}", "max_y: {output: y_max, unit: mm, scale: 1000}", "metrics.max_y"),
    ("stages:", "fmu_options: {relative_tolerance: 1.0e-6}\nstages:", "fmu_options"),
])
def test_resume_is_refused_when_anything_that_decides_a_run_changed(tmp_path, old, new, named):
    out = tmp_path / "out"
    _run(tmp_path, BASE, out)
    assert BASE.count(old) == 1
    changed = BASE.replace(old, new)
    if "y_in" in new:     # an input needs the FMU to read it: use_y_in
        changed = changed.replace("t_ramp: 10}", "t_ramp: 10, use_y_in: true}")
        named = "fixed.use_y_in"
    before = (out / "runs.csv").read_bytes(), (out / "runs.csv.study.json").read_bytes()
    with pytest.raises(UsageError, match=rf"cannot resume: the study changed .*{named.replace('.', '[.]')}.*"
                                         r"metrics would be stale; run without --resume"):
        _run(tmp_path, changed, out, resume=True)
    assert ((out / "runs.csv").read_bytes(), (out / "runs.csv.study.json").read_bytes()) == before
    # the unchanged study still resumes, simulating nothing
    again = _run(tmp_path, BASE, out, resume=True)
    assert again.summary["simulated_this_session"] == 0


def test_resume_is_refused_when_the_fmu_changed(tmp_path, fmu_path):
    own = tmp_path / "ScrewVertebra.fmu"
    shutil.copyfile(fmu_path, own)
    text = BASE.replace("fmu: default", f"fmu: {own.as_posix()}")
    out = tmp_path / "out"
    _run(tmp_path, text, out)
    with open(own, "ab") as fh:       # the same FMU rebuilt: other bytes (a zip comment past its end)
        fh.write(b"\0")
    with pytest.raises(UsageError, match=r"cannot resume: the study changed .*fmu: changed"):
        _run(tmp_path, text, out, resume=True)


def test_a_sensitivity_parameters_variable_is_in_its_fingerprint(tmp_path):
    """Row 1: the sensitivity stage keeps its runs under its own parameters' variables (cg_y → rI_y)."""
    out = tmp_path / "out"
    first = _run(tmp_path, SENS, out)
    assert first.sensitivity["summary"]["simulated"] > 0
    stored = json.loads((out / "sensitivity_runs.csv.study.json").read_text(encoding="utf-8"))
    assert stored["parameters"] == {"p": ["cg_y", 1.0, 0.0]}
    again = _run(tmp_path, SENS, out, resume=True)
    assert again.summary["simulated_this_session"] == 0
    with pytest.raises(UsageError, match=r"sensitivity_runs.csv: cannot resume: the study changed since these runs were made "
                                         r"\(parameters.p: \['cg_y', 1.0, 0.0\] → \['rI_y', 1.0, 0.0\]\)"):
        _run(tmp_path, SENS.replace("variable: cg_y", "variable: rI_y"), out, resume=True)


@pytest.mark.parametrize("damage", ["torn", "missing", "not an object"])
def test_a_fingerprint_that_cannot_be_read_refuses_resume_and_is_kept(tmp_path, damage):
    """Row 2: a torn record and a changed F_max: refused, and the record is never rewritten as the new one."""
    out = tmp_path / "out"
    _run(tmp_path, BASE, out)
    meta = out / "runs.csv.study.json"
    text = meta.read_text(encoding="utf-8")
    if damage == "torn":
        meta.write_text(text[:len(text) // 2], encoding="utf-8")
    elif damage == "missing":
        meta.unlink()
    else:
        meta.write_text("[1, 2]", encoding="utf-8")
    left = meta.read_bytes() if meta.exists() else None
    runs = (out / "runs.csv").read_bytes()
    changed = BASE.replace("F_max: 411", "F_max: 300")
    for text_ in (changed, BASE):
        with pytest.raises(UsageError, match=r"runs.csv: cannot resume: runs.csv.study.json"
                                             r"(, the record of what made these runs .* is missing| cannot be "
                                             r"read \(.*; it was cut short or edited\))"):
            _run(tmp_path, text_, out, resume=True)
        assert (meta.read_bytes() if meta.exists() else None) == left
        assert (out / "runs.csv").read_bytes() == runs
    # without --resume the study starts afresh, the old runs kept aside
    fresh = _run(tmp_path, changed, out)
    assert fresh.summary["simulated_this_session"] == 2
    assert (out / "runs.previous-1.csv").read_bytes() == runs
