"""FMI 3.0 FMUs, co-simulation and model exchange, through the same runner, plans and studies as FMI 2.0.

Our own FMU is tests/fmus/fmi3_decay (Decay3, built here with gcc against fmpy's FMI 3 headers):
x_i' = u - k_i x_i, z = s·w x, with array parameters k[2], x0[2], w[2,2], array outputs x[2], z[2] and a
scalar input u (s = ±10^scale_exp, a Boolean and an Int32 parameter; n_steps an Int32 output), so x_i(t) = u/k_i + (x0_i - u/k_i) exp(-k_i t). Its co-simulation steps with the exact
exponential (the closed form to rounding); model exchange is integrated by fmpy's CVode.

The real export is ../shared/vendor-fmus/MapleSim2024_CoupledClutches_FMI3.fmu (CS + ME, array output
``outputs`` of 4 elements): a study written as a user would, and each ok run compared with a run of
fmpy's own ``simulate_fmu`` on a fresh instance (CS: 1e-9 relative; ME: within the solver's tolerance).
"""
from __future__ import annotations

import math
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import fmpy
from fmusa.api import run_study
from fmusa.fmi.info import FMUError, FMURunError, read_fmu_info, variable_problem
from fmusa.fmi.plans import DrivenPlan, RunPlan
from fmusa.fmi.runner import FMURunner
from fmusa.study.loader import load_study

SRC = Path(__file__).resolve().parent / "fmus" / "fmi3_decay"
FMI_HEADERS = Path(fmpy.__file__).resolve().parent / "c-code"
SHARED = Path(os.environ.get("FMUSA_SHARED_DIR") or Path(__file__).resolve().parents[1].parent / "shared")
CLUTCHES = SHARED / "vendor-fmus" / "MapleSim2024_CoupledClutches_FMI3.fmu"

K, X0, W = [1.0, 2.0], [1.0, -0.5], [[1.0, 0.0], [0.0, 1.0]]   # the model description's start values


def x_exact(t, u: float, k: float, x0: float):
    """x(t) of x' = u - k x, x(0) = x0."""
    return u / k + (x0 - u / k) * np.exp(-k * np.asarray(t, dtype=float))


@pytest.fixture(scope="session")
def decay3(tmp_path_factory) -> Path:
    """tests/fmus/fmi3_decay built with gcc and zipped as Decay3.fmu (binaries/<FMI 3 platform tuple>/)."""
    if shutil.which("gcc") is None:
        pytest.skip("gcc is needed to build the FMI 3.0 test FMU")
    if sys.platform.startswith("win"):
        pytest.skip("the test builds a shared library with gcc -shared -fPIC (Linux/macOS)")
    root = tmp_path_factory.mktemp("decay3")
    tree = root / "tree"
    bindir = tree / "binaries" / fmpy.platform_tuple
    bindir.mkdir(parents=True)
    shutil.copy(SRC / "modelDescription.xml", tree / "modelDescription.xml")
    lib = bindir / f"Decay3{fmpy.sharedLibraryExtension}"
    cmd = ["gcc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-O1", "-shared", "-fPIC", "-I", str(FMI_HEADERS),
           str(SRC / "decay3.c"), "-o", str(lib), "-lm"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.fail(f"building the FMI 3.0 test FMU failed:\n{' '.join(cmd)}\n{proc.stdout}\n{proc.stderr}")
    fmu = root / "Decay3.fmu"
    with zipfile.ZipFile(fmu, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted(tree.rglob("*")):
            if f.is_file():
                z.write(f, f.relative_to(tree).as_posix())
    return fmu


# ---------------------------------------------------------------------- what fmusa reads
def test_array_variables_are_element_scalars(decay3):
    info = read_fmu_info(decay3)
    assert info.is_fmi3 and info.fmi_version == "3.0"
    assert set(info.interfaces) == {"co-simulation", "model-exchange"}
    assert info.platforms == [fmpy.platform_tuple] and info.has_binary("co-simulation")
    names = [v.name for v in info.variables]
    assert names == ["time", "k[1]", "k[2]", "x0[1]", "x0[2]", "w[1,1]", "w[1,2]", "w[2,1]", "w[2,2]", "u",
                     "x[1]", "x[2]", "der(x)[1]", "der(x)[2]", "z[1]", "z[2]", "negate", "scale_exp", "t_terminate",
                     "n_steps"]
    w21 = info.variable("w[2,1]")
    assert (w21.type, w21.fmi3_type, w21.vr, w21.index, w21.size, w21.shape) == ("Real", "Float64", 3, 2, 4, (2, 2))
    assert info.variable("x0[2]").start == "-0.5"
    assert [v.name for v in info.declared_variables] == ["time", "k", "x0", "w", "u", "x", "der(x)", "z", "negate",
                                                         "scale_exp", "t_terminate", "n_steps"]
    assert [(info.variable(n).type, info.variable(n).fmi3_type) for n in ("negate", "scale_exp")] == \
        [("Boolean", "Boolean"), ("Integer", "Int32")]
    # roles: an element is a parameter/output like a scalar; an array's name tells how to address it
    assert variable_problem(info, "k[2]", "varied") is None
    assert variable_problem(info, "u", "varied") is None
    assert variable_problem(info, "z[2]", "output") is None
    msg = variable_problem(info, "w", "varied")
    assert "'w' is an array of 2×2 elements" in msg and "w[1,1] … w[2,2]" in msg
    assert "no variable 'k[3]'" in variable_problem(info, "k[3]", "varied")


def test_inspect_shows_the_fmi3_platform_and_the_arrays(decay3):
    exe = Path(sys.executable).parent / "fmusa"
    import os
    proc = subprocess.run([str(exe), "inspect", str(decay3)], capture_output=True, text=True,
                          env={**os.environ, "COLUMNS": "400"})
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    assert f"runs here           yes: FMI 3.0, co-simulation and model exchange; the {fmpy.platform_tuple} binary loads" \
        in out or f"runs here           yes: FMI 3.0, co-simulation; the {fmpy.platform_tuple} binary loads" in out, out
    assert "w (2×2, parameter): w[1,1] … w[2,2]" in out and "z (2, output): z[1] … z[2]" in out
    assert "20 scalars" in out and "in 12 variables, 6 of them arrays" in out
    rows = {line.split()[0]: line.split() for line in out.splitlines() if line.startswith(("w[", "u ", "x0["))}
    assert rows["w[2,2]"][1:4] == ["parameter", "tunable", "Float64"] and rows["x0[2]"][-3] == "-0.5"


# ---------------------------------------------------------------------- runs against the closed form
@pytest.mark.parametrize("interface, rtol", [("co-simulation", 1e-13), ("model-exchange", 1e-5)])
def test_runs_match_the_closed_form_and_a_fresh_fmpy_instance(decay3, interface, rtol):
    times = np.linspace(0.0, 2.0, 201)
    u, k2, x01 = 0.7, 3.0, 2.5
    with FMURunner(decay3, interface=interface, relative_tolerance=1e-9 if interface == "model-exchange"
                   else None) as r:
        # the second run leaves w[1,2] at its start: what the first run set must not outlive the reset
        first = r.run({"k[2]": k2, "x0[1]": x01, "w[1,2]": 5.0}, 2.0, 0.01, ["x[1]", "x[2]", "z[1]", "z[2]"],
                      inputs={"u": u})
        second = r.run({"k[2]": k2}, 2.0, 0.01, ["x[1]", "z[1]"], inputs={"u": u})
        final = r.run_final({"k[2]": k2, "x0[1]": x01, "w[1,2]": 5.0}, 2.0, ["z[1]"], inputs={"u": u})
    x1 = x_exact(times, u, K[0], x01)
    x2 = x_exact(times, u, k2, X0[1])
    np.testing.assert_allclose(first["time"], times, rtol=0, atol=1e-12)
    np.testing.assert_allclose(first["x[1]"], x1, rtol=rtol, atol=0)
    np.testing.assert_allclose(first["x[2]"], x2, rtol=rtol, atol=1e-12)
    np.testing.assert_allclose(first["z[1]"], x1 + 5.0 * x2, rtol=rtol, atol=1e-12)
    np.testing.assert_allclose(first["z[2]"], x2, rtol=rtol, atol=1e-12)
    np.testing.assert_allclose(second["x[1]"], x_exact(times, u, K[0], X0[0]), rtol=rtol, atol=0)
    np.testing.assert_allclose(second["z[1]"], second["x[1]"], rtol=1e-15, atol=0)     # w[1,2] back at 0
    assert final["z[1]"] == pytest.approx(x1[-1] + 5.0 * x2[-1], rel=rtol)

    # fmpy on a fresh instance, arrays set whole as fmpy takes them
    fmi_type = "CoSimulation" if interface == "co-simulation" else "ModelExchange"
    res = fmpy.simulate_fmu(str(decay3), fmi_type=fmi_type, stop_time=2.0, output_interval=0.01,
                            relative_tolerance=1e-9 if interface == "model-exchange" else None,
                            start_values={"k": [K[0], k2], "x0": [x01, X0[1]], "w": [1.0, 5.0, 0.0, 1.0], "u": u},
                            output=["x", "z"])
    np.testing.assert_allclose(first["z[1]"], res["z"][:, 0], rtol=1e-9 if interface == "co-simulation" else 1e-6,
                               atol=1e-12)


def test_run_plan_reuses_the_instance_and_an_error_is_the_fmus(decay3):
    with FMURunner(decay3) as r:
        plan = RunPlan(r, ["k[1]", "u"], {"w[2,1]": 2.0}, ["z[2]", "x[1]"], 1.0, 0.25)
        a = plan([2.0, 1.0])
        b = plan([0.5, -1.0])
        again = plan([2.0, 1.0])
        np.testing.assert_array_equal(a, again)
        t = plan.times
        for (k1, u), data in (((2.0, 1.0), a), ((0.5, -1.0), b)):
            x1 = x_exact(t, u, k1, X0[0])
            np.testing.assert_allclose(data[:, 1], x1, rtol=1e-13)
            np.testing.assert_allclose(data[:, 0], 2.0 * x1 + x_exact(t, u, K[1], X0[1]), rtol=1e-13, atol=1e-14)
        with pytest.raises(FMURunError, match=r"(?s)fmi3ExitInitializationMode returned Error.*FMU log:.*"
                                              r"k\[1\] and k\[2\] must be positive"):
            plan([-1.0, 0.0])
        np.testing.assert_array_equal(plan([2.0, 1.0]), a)     # and the next run is right again
        with pytest.raises(FMUError, match=r"unknown parameter 'k\[3\]'"):
            RunPlan(r, ["k[3]"], {}, ["x[1]"], 1.0, 0.5)


def test_an_fmu_that_asks_to_terminate_fails_the_run_with_the_time(decay3):
    with FMURunner(decay3) as r:
        plan = RunPlan(r, ["t_terminate"], {}, ["x[1]"], 1.0, 0.25)
        with pytest.raises(FMURunError, match=r"asked to terminate the simulation in fmi3DoStep at t = 0\.5 s "
                                              r"\(step from 0\.25 s\)"):
            plan([0.5])
        np.testing.assert_allclose(plan([2.0])[:, 0], x_exact(plan.times, 0.0, K[0], X0[0]), rtol=1e-13)


def test_a_driven_plan_runs_an_fmi3_co_simulation(decay3):
    """DrivenPlan holds each sample of the drive over its interval (FMI 3.0 has no input derivatives)."""
    t = np.array([0.0, 0.3, 0.5, 1.2])
    u = np.array([1.0, -2.0, 0.5, 0.0])
    with FMURunner(decay3) as r:
        assert not DrivenPlan(r, [], {}, "u", ["x[1]"]).interpolates
        data = DrivenPlan(r, ["k[1]"], {}, "u", ["x[1]"])([1.5], t, u)
    x, expect = X0[0], [X0[0]]
    for i in range(1, len(t)):
        x = float(x_exact(t[i] - t[i - 1], u[i - 1], 1.5, x))
        expect.append(x)
    np.testing.assert_allclose(data[:, 0], expect, rtol=1e-13)


@pytest.mark.parametrize("interface", ["co-simulation", "model-exchange"])
def test_boolean_and_integer_variables_are_set_and_read(decay3, interface):
    with FMURunner(decay3, interface=interface) as r:
        plan = RunPlan(r, ["k[1]"], {"negate": "true", "scale_exp": -2}, ["z[1]", "n_steps", "x[1]"], 1.0, 0.25)
        data = plan([3.0])
        plain = r.run_final({"k[1]": 3.0}, 1.0, ["z[1]", "n_steps"])      # back at the starts: false, 0
    x1 = x_exact(plan.times, 0.0, 3.0, X0[0])
    np.testing.assert_allclose(data[:, 2], x1, rtol=1e-13 if interface == "co-simulation" else 1e-5)
    np.testing.assert_allclose(data[:, 0], -1e-2 * data[:, 2], rtol=1e-14)
    # fmi3DoStep calls since the reset (model exchange makes none)
    steps = [0, 1, 2, 3, 4] if interface == "co-simulation" else [0] * 5
    assert data[:, 1].tolist() == steps
    assert plain["z[1]"] == pytest.approx(float(x1[-1]), rel=1e-13 if interface == "co-simulation" else 1e-5)
    assert plain["n_steps"] == (1 if interface == "co-simulation" else 0)
    with FMURunner(decay3, interface=interface) as r, pytest.raises(FMUError, match=r"scale_exp is an Integer"):
        r.run_final({"scale_exp": 1.5}, 1.0, ["z[1]"])


def test_a_study_holds_an_fmi3_input_under_scenario_inputs(tmp_path, decay3):
    text = f"""\
name: decay3_inputs
fmu: {decay3.as_posix()}
parameters:
  k1: {{variable: "k[1]"}}
fixed:
  scale_exp: 1
scenario:
  stop_time: 1.0
  step: 0.1
  inputs:
    u: 0.25
metrics:
  z1_end: {{output: "z[1]", reduce: final}}
  steps: {{output: n_steps, reduce: final}}
stages:
  grid:
    values:
      k1: [0.5, 2.0]
execution:
  workers: 1
"""
    path = tmp_path / "inputs.yaml"
    path.write_text(text, encoding="utf-8")
    run_study(load_study(path), tmp_path / "out", figures=False, progress=False)
    runs = pd.read_csv(tmp_path / "out" / "runs.csv")
    assert (runs["status"] == "ok").all(), runs[["status", "message"]]
    for _, r in runs.iterrows():
        assert r["z1_end"] == pytest.approx(10.0 * float(x_exact(1.0, 0.25, r["k1"], X0[0])), rel=1e-13)
        assert r["steps"] == 10


# ---------------------------------------------------------------------- a study of our FMI 3.0 FMU
def _decay_study(directory: Path, fmu: Path, interface: str) -> Path:
    options = ("  interface: co-simulation\n" if interface == "co-simulation" else
               "  interface: model-exchange\n  relative_tolerance: 1.0e-9\n")
    text = f"""\
name: decay3_{interface.replace('-', '_')}
fmu: {fmu.as_posix()}
fmu_options:
{options}parameters:
  k2: {{variable: "k[2]", unit: 1/s}}
  coupling: {{variable: "w[1,2]"}}
  drive: {{variable: u}}
fixed:
  "x0[1]": 2.0
scenario:
  stop_time: 1.5
  step: 0.05
metrics:
  x2_end: {{output: "x[2]", reduce: final}}
  z1_end: {{output: "z[1]", reduce: final}}
  z1_max: {{output: "z[1]", reduce: max}}
stages:
  grid:
    values:
      k2: [0.5, 4.0]
      coupling: [0.0, -3.0]
      drive: [0.0, 1.0]
execution:
  workers: 1
"""
    path = directory / f"decay3_{interface}.yaml"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize("interface, rtol", [("co-simulation", 1e-12), ("model-exchange", 1e-5)])
def test_a_study_of_array_elements_and_an_input_matches_the_closed_form(tmp_path, decay3, interface, rtol):
    run_study(load_study(_decay_study(tmp_path, decay3, interface)), tmp_path / "out", figures=False,
              progress=False)
    runs = pd.read_csv(tmp_path / "out" / "runs.csv")
    assert len(runs) == 8 and (runs["status"] == "ok").all(), runs[["status", "message"]]
    t = np.linspace(0.0, 1.5, 31)
    for _, r in runs.iterrows():
        x1 = x_exact(t, r["drive"], K[0], 2.0)
        x2 = x_exact(t, r["drive"], r["k2"], X0[1])
        z1 = x1 + r["coupling"] * x2
        assert r["x2_end"] == pytest.approx(x2[-1], rel=rtol, abs=1e-12)
        assert r["z1_end"] == pytest.approx(z1[-1], rel=rtol, abs=1e-12)
        assert r["z1_max"] == pytest.approx(z1.max(), rel=rtol, abs=1e-12)


# ---------------------------------------------------------------------- the MapleSim 2024 FMI 3.0 export
needs_clutches = pytest.mark.skipif(not CLUTCHES.is_file(),
                                    reason=f"the shared vendor FMU {CLUTCHES.name} is not next to the repository "
                                           f"(../shared/vendor-fmus/)")

CLUTCH_STUDY = """\
name: clutches_{tag}
description: MapleSim 2024's CoupledClutches (FMI 3.0); its array output 'outputs' addressed element-wise
fmu: {fmu}
fmu_options:
  interface: {interface}
parameters:
  freq: {{variable: freqHz, unit: Hz}}
  t2: {{variable: T2, unit: s}}
  drive: {{variable: RI1}}
scenario:
  stop_time: 1.5
  step: 0.01
metrics:
  w1_end: {{output: "outputs[1]", reduce: final}}
  w2_max: {{output: "outputs[2]", reduce: max}}
  w3_end: {{output: "outputs[3]", reduce: final}}
  w4_end: {{output: "outputs[4]", reduce: final}}
stages:
  grid:
    values:
      freq: [0.1, 0.3]
      t2: [0.3, 0.6]
      drive: [0.0, 2.0]
execution:
  workers: 1
"""


@needs_clutches
@pytest.mark.parametrize("interface, rtol", [("co-simulation", 1e-9), ("model-exchange", 1e-5)])
def test_maplesim_fmi3_study_equals_fresh_fmpy_runs(tmp_path, interface, rtol):
    path = tmp_path / f"clutches_{interface}.yaml"
    path.write_text(CLUTCH_STUDY.format(tag=interface.replace("-", "_"), fmu=CLUTCHES.as_posix(),
                                        interface=interface), encoding="utf-8")
    out = tmp_path / "out"
    exe = Path(sys.executable).parent / "fmusa"
    proc = subprocess.run([str(exe), "sweep", str(path), "--out", str(out)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    runs = pd.read_csv(out / "runs.csv")
    assert len(runs) == 8 and (runs["status"] == "ok").all(), runs[["status", "message"]]
    report = (out / "report.md").read_text(encoding="utf-8")
    assert "drive → FMU `RI1`" in report and "| w1_end |" in report and (out / "summary.json").is_file()
    fmi_type = "CoSimulation" if interface == "co-simulation" else "ModelExchange"
    moved = []
    for _, r in runs.iterrows():
        res = fmpy.simulate_fmu(str(CLUTCHES), fmi_type=fmi_type, stop_time=1.5, output_interval=0.01,
                                start_values={"freqHz": r["freq"], "T2": r["t2"], "RI1": r["drive"]},
                                output=["outputs"], record_events=False)
        o = np.asarray(res["outputs"], dtype=float)
        expect = {"w1_end": o[-1, 0], "w2_max": o[:, 1].max(), "w3_end": o[-1, 2], "w4_end": o[-1, 3]}
        for name, value in expect.items():
            scale = max(abs(value), 1e-3 * np.abs(o).max())
            assert abs(r[name] - value) <= rtol * scale, (interface, name, r[name], value)
        moved.append(r["w1_end"])
    assert np.ptp(moved) > 1e-3          # the study parameters reach the FMU (the answers differ)


def test_morris_on_array_elements_and_an_input(tmp_path, decay3):
    """A sensitivity stage whose parameters are array elements and an input: every run is the closed form,
    and z's coupling w[1,2] has no effect on x[2] (mu* exactly 0)."""
    text = f"""\
name: decay3_morris
fmu: {decay3.as_posix()}
parameters:
  k2: {{variable: "k[2]"}}
scenario:
  stop_time: 1.5
  step: 0.05
metrics:
  x2_end: {{output: "x[2]", reduce: final}}
  z1_end: {{output: "z[1]", reduce: final}}
stages:
  grid:
    values:
      k2: [1.0]
  sensitivity:
    methods: [morris]
    morris_trajectories: 4
    seed: 1
    outputs: [x2_end, z1_end]
    parameters:
      k2: {{variable: "k[2]", bounds: [0.5, 4.0]}}
      drive: {{variable: u, bounds: [-1.0, 1.0]}}
      w12: {{variable: "w[1,2]", bounds: [0.0, 2.0]}}
execution:
  workers: 1
"""
    path = tmp_path / "morris.yaml"
    path.write_text(text, encoding="utf-8")
    result = run_study(load_study(path), tmp_path / "out", figures=False, progress=False)
    runs = pd.read_csv(tmp_path / "out" / "sensitivity_runs.csv")
    assert len(runs) >= 16 and (runs["status"] == "ok").all(), runs[["status", "message"]]
    for _, r in runs.iterrows():
        x1 = float(x_exact(1.5, r["drive"], K[0], X0[0]))
        x2 = float(x_exact(1.5, r["drive"], r["k2"], X0[1]))
        assert r["x2_end"] == pytest.approx(x2, rel=1e-12, abs=1e-15)
        assert r["z1_end"] == pytest.approx(x1 + r["w12"] * x2, rel=1e-12, abs=1e-15)
    morris = result.summary["sensitivity"]["morris"]
    assert morris["x2_end"]["w12"]["mu_star"] == 0.0
    assert morris["x2_end"]["drive"]["mu_star"] > 0.1 and morris["z1_end"]["w12"]["mu_star"] > 0.1
