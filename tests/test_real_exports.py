"""FMUs that break FMI 2.0 the ways real exports do: every ``ok`` run equals a run on a fresh instance.

Each fault is compiled into tests/fmus/faulty (a damped oscillator m x'' + d x' + k x = F, x(0) = x0 = 0.5)
by tests/faulty_fmu.py: a reset that restarts the state at 0 (Dymola 2022x), outputs that read 0 after a
reset (20-sim 4.6), a reset that returns fmi2Error (Amesim 15), parameters dropped when set before
fmi2SetupExperiment (20-sim 4.6), explicit Euler at the communication step (OpenModelica CS), two variables
of one name, two names sharing a value reference, a binary that needs a library the machine lacks. The
reference is the oscillator's closed form and fmpy on a fresh instance (tests/fresh_runs.py).
"""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from faulty_fmu import build_faulty, closed_form
from fresh_runs import largest_difference
from fmusa.api import run_study
from fmusa.study.loader import load_study
from fmusa.study.schema import StudyError

K = [50.0, 100.0, 200.0, 400.0]


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    """Each test checks its FMU afresh (a verdict cached by an earlier test would hide the check)."""
    monkeypatch.setenv("FMUSA_CACHE_DIR", str(tmp_path / "cache"))


def write_study(directory: Path, fmu: Path, *, workers: int = 2, k=K, extra: str = "", step: float = 0.01,
                parameters: str = "  k: {variable: k, unit: N/m}\n", fixed: str = "  F: 10\n",
                interface: str | None = None) -> Path:
    opts = f"fmu_options:\n  interface: {interface}\n" if interface else ""
    text = f"""\
name: faulty
fmu: {fmu}
parameters:
{parameters}fixed:
{fixed}scenario:
  stop_time: 2
  step: {step}
metrics:
  x_end: {{output: x, reduce: final, unit: m}}
  x_peak: {{output: x_peak, reduce: final, unit: m}}
  v_max: {{output: v, reduce: max, unit: m/s}}
stages:
  grid:
    values:
      k: [{", ".join(repr(x) for x in k)}]
execution:
  workers: {workers}
{opts}{extra}"""
    path = directory / f"study_{fmu.stem}.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def closed_metrics(k: float, x0: float = 0.5, F: float = 10.0) -> dict[str, float]:
    t = np.arange(201) * 0.01
    x, v = closed_form(t, k=k, F=F, x0=x0)
    return {"x_end": float(x[-1]), "v_max": float(v.max())}


def sweep(study: Path, out: Path, workers: int | None = None):
    return run_study(load_study(study), out, workers=workers, figures=False, progress=False)


@pytest.mark.parametrize("fault, with_state, mode", [
    ("reset_zero", False, "fresh"),      # Dymola 2022x: the state restarts at 0 after fmi2Reset
    ("reset_zero", True, "snapshot"),    # ... but it can get and set its state
    ("reset_zeros", False, "fresh"),     # 20-sim 4.6: outputs read 0 after fmi2Reset
    ("reset_error", False, "fresh"),     # Amesim 15: fmi2Reset returns fmi2Error
    ("none", False, "reset"),
])
def test_a_broken_reset_is_found_and_every_run_equals_a_fresh_instance(tmp_path, fault, with_state, mode):
    fmu = build_faulty(tmp_path, fault, with_state=with_state)
    study = write_study(tmp_path, fmu)
    answers = []
    for workers in (1, 2):
        res = sweep(study, tmp_path / f"out{workers}", workers=workers)
        reuse = res.summary["fmu_runs"]
        assert reuse["mode"] == mode, reuse
        if mode != "reset":
            assert "after fmi2Reset" in reuse["why"], reuse["why"]
        ok = res.runs[res.runs["status"] == "ok"]
        assert len(ok) == len(K)
        for _, row in ok.iterrows():        # the closed form, x0 = 0.5 in every run
            ref = closed_metrics(row["k"])
            assert row["x_end"] == pytest.approx(ref["x_end"], rel=1e-5, abs=1e-7)
            assert row["v_max"] == pytest.approx(ref["v_max"], rel=1e-6)
        answers.append(ok.sort_values("k")[["x_end", "x_peak", "v_max"]].to_numpy())
        worst, n = largest_difference(res.runs, study, fmu)
        assert n == len(K) and worst <= 1e-9, worst
    np.testing.assert_array_equal(answers[0], answers[1])    # the answer does not depend on --workers
    with open(tmp_path / "out2" / "summary.json", encoding="utf-8") as fh:
        assert json.load(fh)["fmu_runs"]["mode"] == mode


def test_parameters_set_before_setup_experiment_are_kept(tmp_path):
    """20-sim 4.6 drops values set before fmi2SetupExperiment: fmusa sets them after it, as fmpy does."""
    fmu = build_faulty(tmp_path, "drop_early")
    res = sweep(write_study(tmp_path, fmu), tmp_path / "out")
    ok = res.runs[res.runs["status"] == "ok"].sort_values("k")
    assert len(ok) == len(K)
    for _, row in ok.iterrows():
        assert row["x_end"] == pytest.approx(closed_metrics(row["k"])["x_end"], rel=1e-5, abs=1e-7)
    assert ok["x_end"].nunique() == len(K)      # k was not ignored


def test_the_default_experiments_tolerance_reaches_setup_experiment(tmp_path):
    fmu = build_faulty(tmp_path, tolerance=1e-4)
    metric = "  tol: {output: tolerance_seen, reduce: final}\n"
    study = write_study(tmp_path, fmu, workers=1)
    text = study.read_text(encoding="utf-8").replace("stages:", "  tol: {output: tolerance_seen, reduce: final}\nstages:", 1)
    study.write_text(text, encoding="utf-8")
    res = sweep(study, tmp_path / "out")
    assert (res.runs["tol"] == 1e-4).all(), res.runs["tol"]
    text = text.replace("execution:", "fmu_options:\n  relative_tolerance: 1.0e-7\nexecution:")
    study.write_text(text, encoding="utf-8")
    res = sweep(study, tmp_path / "out2")
    assert (res.runs["tol"] == 1e-7).all()
    assert metric


def test_an_fmu_without_a_default_tolerance_gets_none(tmp_path):
    fmu = build_faulty(tmp_path)
    study = write_study(tmp_path, fmu, workers=1)
    text = study.read_text(encoding="utf-8").replace("stages:", "  tol: {output: tolerance_seen, reduce: final}\nstages:", 1)
    study.write_text(text, encoding="utf-8")
    res = sweep(study, tmp_path / "out")
    assert (res.runs["tol"] == -1).all()


def test_duplicate_variable_names_are_refused_naming_both(tmp_path):
    fmu = build_faulty(tmp_path, duplicate=True)
    with pytest.raises(StudyError) as err:
        sweep(write_study(tmp_path, fmu), tmp_path / "out")
    msg = str(err.value)
    assert "2 variables named 'k'" in msg and "value reference 1" in msg and "value reference 10" in msg
    assert not (tmp_path / "out" / "runs.csv").exists()


def test_a_fixed_value_and_a_study_parameter_on_one_value_reference_are_refused(tmp_path):
    fmu = build_faulty(tmp_path, alias=True)
    study = write_study(tmp_path, fmu, parameters="  k: {variable: k, unit: N/m}\n  load: {variable: load, unit: N}\n",
                        fixed="  F: 300\n", k=K)
    text = study.read_text(encoding="utf-8").replace("      k: [", "      load: [5.0, 20.0]\n      k: [")
    study.write_text(text, encoding="utf-8")
    with pytest.raises(StudyError) as err:
        sweep(study, tmp_path / "out")
    msg = str(err.value)
    assert "study parameter 'load' (load)" in msg and "fixed 'F' (F = 300)" in msg and "value reference 3" in msg


def test_two_aliases_fixed_to_different_values_are_refused_and_equal_values_are_not(tmp_path):
    fmu = build_faulty(tmp_path, alias=True)
    with pytest.raises(StudyError, match="share value reference 3"):
        sweep(write_study(tmp_path, fmu, fixed="  F: 10\n  load: 20\n"), tmp_path / "out")
    res = sweep(write_study(tmp_path, fmu, fixed="  F: 20\n  load: 20\n", workers=1), tmp_path / "out2")
    assert (res.runs["status"] == "ok").all()
    ok = res.runs.sort_values("k")
    assert ok["x_end"].iloc[0] == pytest.approx(closed_metrics(50.0, F=20.0)["x_end"], rel=1e-5, abs=1e-7)


def test_euler_at_the_communication_step_is_flagged_with_the_fix(tmp_path):
    """OpenModelica's CS export: one explicit Euler step per communication step. At stiff points it blows
    up while every run is ok: the rerun with half the step and through model exchange move the metrics,
    the blown-up values are flagged as implausible, and the advice names scenario.step and the interface."""
    fmu = build_faulty(tmp_path, "euler")
    k = [10.0, 20.0, 40.0, 80.0, 90000.0]       # h*omega = 3 at the last: |1 + 3i|^200 ~ 1e100
    res = sweep(write_study(tmp_path, fmu, k=k), tmp_path / "out")
    steps = res.summary["fmu_steps"]
    assert set(steps["flagged"]) >= {"x_end", "v_max"}, steps
    advice = " ".join(steps["advice"])
    assert "scenario.step" in advice and "interface: model-exchange" in advice
    implausible = res.summary["implausible"]
    assert {i["metric"] for i in implausible} >= {"x_peak"}
    stiff = res.runs.loc[res.runs["k"] == 90000.0, "x_peak"].iloc[0]
    assert stiff > 1e50 and all(i["value"] > 1e50 for i in implausible)


def test_an_accurate_fmu_is_not_flagged(tmp_path):
    fmu = build_faulty(tmp_path)
    res = sweep(write_study(tmp_path, fmu), tmp_path / "out")
    steps = res.summary["fmu_steps"]
    assert steps["flagged"] == [] and steps["advice"] == []
    assert len(steps["checks"]) >= 3 * 3 and "implausible" not in res.summary
    # CVode at rtol 1e-6 against RK4 (the halved step, read at every halved step, also moves the sampled peak
    # v_max, within its sampling bound)
    assert max(c["relative"] for c in steps["checks"] if not c["variant"].startswith("communication")) < 1e-3


def test_a_binary_that_cannot_load_stops_the_study_at_once(tmp_path):
    fmu = build_faulty(tmp_path, missing_library=True)
    study = write_study(tmp_path, fmu)
    out = tmp_path / "out"
    out.mkdir()
    (out / "runs.csv").write_text("earlier runs\n", encoding="utf-8")
    proc = subprocess.run([sys.executable, "-m", "fmusa.cli", "sweep", str(study), "--out", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "libfmusa_missing_dep.so" in lines[0] and "cannot be loaded" in lines[0] and "Fix:" in lines[0]
    assert (out / "runs.csv").read_text(encoding="utf-8") == "earlier runs\n"      # nothing moved aside
    assert not list(out.glob("runs.previous*"))


def test_the_verdict_is_cached_per_fmu(tmp_path):
    fmu = build_faulty(tmp_path, "reset_zero")
    study = write_study(tmp_path, fmu, workers=1)
    first = sweep(study, tmp_path / "a").summary["fmu_runs"]
    again = sweep(study, tmp_path / "b").summary["fmu_runs"]
    assert not first["cached"] and first["check_s"] > 0
    assert again["cached"] and again["check_s"] == 0 and again["mode"] == first["mode"] == "fresh"
