"""A study parameter that maps to an FMU input (causality input), held at its value over the run.

The FMU is tests/fmus/me_spring (gcc-built, FMI 2.0, co-simulation and model exchange): a mass on a
spring-damper whose load ``F_ext`` is an input. With the ramped force off (``F_max: 0``) the load is a step
of ``F_ext`` at t = 0, and y(t) has the closed form of the damped oscillator's step response. The study
varies the load and the stiffness; every run must equal the closed form on both interfaces (co-simulation:
RK4 sub-steps of 1e-4 s; model exchange: CVode at rtol 1e-8). The FMI 3.0 case is in tests/test_fmi3.py.
"""
from __future__ import annotations

import math
from pathlib import Path

import pandas as pd
import pytest

from fmus.me_spring.build import build_spring_fmu
from fmusa.api import run_study
from fmusa.fmi.info import read_fmu_info, variable_problem
from fmusa.study.loader import load_study
from fmusa.study.schema import StudyError

M, STOP, STEP = 1.0, 2.0, 0.01
LOADS = [5.0, 20.0, -7.5]
STIFF = [100.0, 400.0]
DAMP = 8.0


def step_response(load: float, c: float, d: float, t: float, m: float = M) -> float:
    """y(t) of m y'' + d y' + c y = load, y(0) = y'(0) = 0 (underdamped: d² < 4 m c)."""
    zeta = d / (2 * math.sqrt(c * m))
    wn = math.sqrt(c / m)
    wd = wn * math.sqrt(1 - zeta ** 2)
    assert zeta < 1
    return load / c * (1 - math.exp(-zeta * wn * t) * (math.cos(wd * t) + zeta / math.sqrt(1 - zeta ** 2)
                                                        * math.sin(wd * t)))


def peak(load: float, c: float, d: float, m: float = M) -> float:
    """The largest |y| over [0, STOP]: the first overshoot, at t = pi / wd (inside STOP for these grids)."""
    wd = math.sqrt(c / m) * math.sqrt(1 - (d / (2 * math.sqrt(c * m))) ** 2)
    assert math.pi / wd < STOP
    return abs(step_response(load, c, d, math.pi / wd))


@pytest.fixture(scope="module")
def spring(tmp_path_factory) -> Path:
    return build_spring_fmu(tmp_path_factory.mktemp("input_fmu"), "SpringInput",
                            ("co-simulation", "model-exchange"))


def write_study(directory: Path, fmu: Path, interface: str, inputs: str = "") -> Path:
    """The study a user writes: the load (an input) and the stiffness varied, the ramp switched off."""
    options = ("  interface: co-simulation\n" if interface == "co-simulation" else
               "  interface: model-exchange\n  solver: CVode\n  relative_tolerance: 1.0e-8\n")
    text = f"""\
name: load_input
fmu: {fmu.as_posix()}
fmu_options:
{options}parameters:
  load: {{variable: F_ext, unit: N}}
  c: {{variable: c, unit: N/m}}
fixed:
  F_max: 0
  d: {DAMP}
scenario:
  stop_time: {STOP}
  step: {STEP}
{inputs}metrics:
  y_end: {{output: y, reduce: final, unit: m}}
  y_peak: {{output: y, reduce: max_abs, unit: m}}
  F_end: {{output: F, reduce: final, unit: N}}
stages:
  grid:
    values:
      load: {LOADS}
      c: {STIFF}
execution:
  workers: 1
"""
    path = directory / f"load_{interface}.yaml"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize("interface, rtol, peak_rtol", [("co-simulation", 1e-9, 2e-3),
                                                        ("model-exchange", 2e-5, 2e-3)])
def test_an_input_as_study_parameter_is_held_over_the_run(tmp_path, spring, interface, rtol, peak_rtol):
    study = load_study(write_study(tmp_path, spring, interface))
    run_study(study, tmp_path / "out", figures=False, progress=False)
    runs = pd.read_csv(tmp_path / "out" / "runs.csv")
    assert len(runs) == len(LOADS) * len(STIFF)
    assert (runs["status"] == "ok").all(), runs[["load", "c", "status", "message"]]
    for _, r in runs.iterrows():
        # the input is what the FMU saw at the end (F = F_max*ramp + F_ext, F_max = 0): held, not reset
        assert r["F_end"] == pytest.approx(r["load"], rel=1e-15, abs=0)
        assert r["y_end"] == pytest.approx(step_response(r["load"], r["c"], DAMP, STOP), rel=rtol, abs=0)
        # the peak is sampled every STEP: within what the sampling can miss of the first overshoot
        assert r["y_peak"] == pytest.approx(peak(r["load"], r["c"], DAMP), rel=peak_rtol)
    # the load moves the answer (a study whose input were dropped would give y = 0 everywhere)
    assert runs["y_end"].abs().min() > 1e-3


def test_an_input_is_a_valid_study_parameter_but_not_a_fixed_value(spring):
    info = read_fmu_info(spring)
    assert variable_problem(info, "F_ext", "varied") is None
    assert "is an input, not a parameter" in variable_problem(info, "F_ext", "parameter")
    # an output is neither
    assert "not a parameter" in variable_problem(info, "y", "varied")


def test_an_input_both_varied_and_held_in_scenario_inputs_is_refused(tmp_path, spring):
    path = write_study(tmp_path, spring, "co-simulation", inputs="  inputs:\n    F_ext: 3\n")
    with pytest.raises(StudyError, match=r"'F_ext' in 'scenario.inputs' is the FMU input of study parameter "
                                         r"'load'.*remove it from 'scenario.inputs'") as err:
        load_study(path)
    line = next(i for i, s in enumerate(path.read_text(encoding="utf-8").splitlines(), 1) if "F_ext: 3" in s)
    assert f"{path.name}:{line}:" in str(err.value)


def test_the_closed_form_is_the_fmus_answer_on_a_fresh_fmpy_instance(spring):
    """The reference itself checked on an independent path: fmpy's simulate_fmu, a fresh instance."""
    import fmpy
    res = fmpy.simulate_fmu(str(spring), fmi_type="CoSimulation", stop_time=STOP, output_interval=STEP,
                            start_values={"F_ext": 20.0, "c": 400.0, "d": DAMP, "F_max": 0.0}, output=["y"])
    assert float(res["y"][-1]) == pytest.approx(step_response(20.0, 400.0, DAMP, STOP), rel=1e-9)


@pytest.mark.parametrize("interface", ["co-simulation", "model-exchange"])
def test_the_runner_takes_an_input_among_the_parameters_of_a_run(spring, interface):
    """FMURunner.run/run_final set an input named among ``params`` as RunPlan does (re-runs of a study's
    points outside the plan, e.g. a finer sampling, pass the study parameters that way)."""
    from fmusa.fmi.runner import FMURunner
    rtol = 1e-9 if interface == "co-simulation" else 2e-4     # ME: CVode at the FMU's default 1e-6
    with FMURunner(spring, interface=interface) as r:
        final = r.run_final({"F_ext": 7.0, "F_max": 0.0, "c": 400.0, "d": DAMP}, STOP, ["F", "y"])
        df = r.run({"F_ext": -3.0, "F_max": 0.0, "c": 100.0, "d": DAMP}, STOP, STEP, ["F", "y"])
    assert final["F"] == 7.0
    assert final["y"] == pytest.approx(step_response(7.0, 400.0, DAMP, STOP), rel=rtol)
    assert (df["F"] == -3.0).all()
    assert df["y"].iloc[-1] == pytest.approx(step_response(-3.0, 100.0, DAMP, STOP), rel=rtol)
