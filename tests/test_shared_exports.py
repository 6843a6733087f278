"""FMUs exported by real tools (../shared/vendor-fmus, see its PROVENANCE.md), each through a study file
written as a user would: every ``ok`` run equals a run of fmpy on a fresh instance (co-simulation: 1e-9
relative; model exchange: within the solver's tolerance), or the study is refused with the cause named.

The FMUs are read from the shared folder beside the repository, never copied into it; the tests skip when
it is missing. Their known faults: 20-sim 4.6 drops parameters set before fmi2SetupExperiment and outputs
zeros after fmi2Reset; OpenModelica 1.19's CS export steps with explicit Euler at the communication step;
JModelica 1.15's binary needs libgfortran.so.3.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from fresh_runs import VENDOR, largest_difference
from fmusa.api import run_study
from fmusa.runs.preflight import FMULoadError
from fmusa.study.loader import load_study

pytestmark = pytest.mark.skipif(not VENDOR.is_dir(), reason=f"the shared vendor FMUs are not at {VENDOR}")


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("FMUSA_CACHE_DIR", str(tmp_path / "cache"))


def study_file(tmp_path: Path, fmu: str, parameter: str, values: list[float], metrics: dict[str, tuple[str, str]],
               stop_time: float, step: float, interface: str | None = None, fixed: dict | None = None,
               check_steps: bool = True) -> Path:
    lines = [f"name: s_{Path(fmu).stem.lower()}", f"fmu: {VENDOR / fmu}", "parameters:",
             f"  p: {{variable: '{parameter}'}}"]
    if fixed:
        lines += ["fixed:"] + [f"  '{k}': {v!r}" for k, v in fixed.items()]
    lines += ["scenario:", f"  stop_time: {stop_time!r}", f"  step: {step!r}", "metrics:"]
    lines += [f"  {m}: {{output: '{o}', reduce: {r}}}" for m, (o, r) in metrics.items()]
    lines += ["stages:", "  grid:", "    values:", f"      p: [{', '.join(repr(v) for v in values)}]",
              "execution:", "  workers: 2", f"  check_fmu_steps: {str(check_steps).lower()}"]
    if interface:
        lines += ["fmu_options:", f"  interface: {interface}"]
    path = tmp_path / f"{Path(fmu).stem}.yaml"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def sweep(path: Path, out: Path):
    return run_study(load_study(path), out, figures=False, progress=False)


CASES = {
    # file, parameter, values, metrics, stop, step, interface, expected reuse mode
    "dymola_cs": ("Dymola2023x_SpringFrictionPendulum1D.fmu", "spring.c", [5.0, 10.0, 20.0],
                  {"s_end": ("mass.s", "final"), "v_peak": ("mass.v", "max_abs")}, 1.0, 0.01, "co-simulation"),
    "twentysim": ("20sim464_TorsionBar.fmu", "Controller.PID.kp", [1.0, 2.0, 4.0],
                  {"load_end": ("LoadDiskRev", "final"), "motor_max": ("MotorDiskRev", "max")}, 0.5, 0.01, None),
    "maplesim_cs": ("MapleSim2024_CoupledClutches_CS.fmu", "freqHz", [0.1, 0.2, 0.4],
                    {"w1_end": ("outputs[1]", "final"), "w2_max": ("outputs[2]", "max")}, 1.5, 0.01, None),
    "om_cs": ("OM1193_Mass_Damper.fmu", "spring.c", [1e3, 1e4, 3e4],
              {"y_end": ("y", "final"), "y_peak": ("y", "max_abs")}, 1.0, 0.01, "co-simulation"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_every_ok_run_of_a_cs_export_equals_a_fresh_fmpy_run(tmp_path, case):
    fmu, parameter, values, metrics, stop, step, interface = CASES[case]
    # 20-sim's runs cost most: its steps are not checked here (OpenModelica's are, below)
    path = study_file(tmp_path, fmu, parameter, values, metrics, stop, step, interface,
                      check_steps=case != "twentysim")
    res = sweep(path, tmp_path / "out")
    ok = res.runs[res.runs["status"] == "ok"]
    assert len(ok) == len(values), res.runs[["p", "status", "message"]]
    worst, n = largest_difference(res.runs, path, VENDOR / fmu, fmi_type="CoSimulation")
    print(f"{fmu}: reuse {res.summary['fmu_runs']['mode']} ({res.summary['fmu_runs']['why'][:120]}); "
          f"{n} runs, largest difference from a fresh fmpy run {worst:.2e}")
    assert n == len(values) and worst <= 1e-9
    for m in metrics:       # the parameter is not ignored
        if case != "twentysim" or m == "load_end":
            assert ok[m].nunique() > 1, (m, ok[m].tolist())
    with open(tmp_path / "out" / "summary.json", encoding="utf-8") as fh:
        reuse = json.load(fh)["fmu_runs"]
    if case == "twentysim":    # outputs zeros after fmi2Reset, cannot get and set its state
        assert reuse["mode"] == "fresh" and "after fmi2Reset" in reuse["why"], reuse
        assert ok["load_end"].nunique() == len(values)       # kp was not dropped before setupExperiment
    else:                       # these reset cleanly (PROVENANCE.md)
        assert reuse["mode"] == "reset", reuse


def test_openmodelica_cs_euler_is_flagged_and_its_me_interface_agrees_with_fmpy(tmp_path):
    fmu, parameter, values, metrics, stop, step, _ = CASES["om_cs"]
    res = sweep(study_file(tmp_path, fmu, parameter, values + [1e5], metrics, stop, step, "co-simulation"),
                tmp_path / "cs")
    steps = res.summary["fmu_steps"]
    assert steps["flagged"], steps
    assert any("model exchange" in a for a in steps["advice"]), steps["advice"]
    me_path = study_file(tmp_path, fmu, parameter, values, metrics, stop, step, "model-exchange")
    me = sweep(me_path, tmp_path / "me")
    assert (me.runs["status"] == "ok").all()
    worst, n = largest_difference(me.runs, me_path, VENDOR / fmu, fmi_type="ModelExchange", relative_tolerance=1e-6)
    print(f"{fmu} ME: {n} runs, largest difference from a fresh fmpy run {worst:.2e}")
    assert n == len(values) and worst <= 1e-9


@pytest.mark.parametrize("fmu, parameter, metrics", [
    ("MapleSim2024_CoupledClutches_ME.fmu", "freqHz", {"w1_end": ("outputs[1]", "final"), "w2_max": ("outputs[2]", "max")}),
    ("Dymola2023x_SpringFrictionPendulum1D.fmu", "spring.c", {"s_end": ("mass.s", "final"), "v_peak": ("mass.v", "max_abs")}),
])
def test_every_ok_run_of_an_me_export_equals_a_fresh_fmpy_run(tmp_path, fmu, parameter, metrics):
    path = study_file(tmp_path, fmu, parameter, [0.1, 0.2, 0.4] if "Maple" in fmu else [5.0, 10.0, 20.0], metrics,
                      1.0, 0.01, "model-exchange")
    res = sweep(path, tmp_path / "out")
    assert (res.runs["status"] == "ok").all(), res.runs["message"].tolist()
    worst, n = largest_difference(res.runs, path, VENDOR / fmu, fmi_type="ModelExchange")
    print(f"{fmu} ME: reuse {res.summary['fmu_runs']['mode']}; {n} runs, largest difference {worst:.2e}")
    assert n == 3 and worst <= 1e-6      # fmpy's CVode at the FMU's default tolerance, the same calls


def test_jmodelica_binary_that_cannot_load_is_refused_with_the_library_named(tmp_path):
    path = study_file(tmp_path, "JModelica115_ControlledTemperature.fmu", "TAmb", [290.0, 300.0],
                      {"T_end": ("TRes", "final")}, 10.0, 0.1)
    with pytest.raises(FMULoadError) as err:
        sweep(path, tmp_path / "out")
    assert "libgfortran.so.3" in str(err.value) and "Fix:" in str(err.value)
    proc = subprocess.run([str(Path(sys.executable).parent / "fmusa"), "sweep", str(path), "--out", str(tmp_path / "cli")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and "libgfortran.so.3" in proc.stderr and "Traceback" not in proc.stderr
