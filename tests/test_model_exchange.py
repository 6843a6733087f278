"""Model exchange FMUs run through fmpy's solver, with the solver and tolerances set in the study.

The FMU is not ours: tests/fmus/me_spring/spring.c, a mass on a spring-damper under a ramped force,
m y'' + d y' + c y = F_max·min(t/t_ramp, 1) (+ F_ext), built by gcc into real .fmu files (model exchange
only; co-simulation and model exchange; model exchange with sources and no binary). Its grid results are
checked against the closed-form solution and against the ScrewVertebra FMU, whose axial motion obeys the
same equation (fmu/MODEL.md).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.linalg import expm

from fmusa.fmi.runner import FMURunner
from fmusa.runs.spec import PlanSpec, run_chunk
from fmusa.fmi.plans import RunPlan
from fmusa.fmi.info import read_fmu_info
from fmusa.runs.metrics import MetricRule
from fmusa.study.loader import parse_study
from fmusa.api import run_study

from fmus.me_spring.build import build_spring_fmu

C_GRID = [100.0, 400.0, 1600.0]
D_GRID = [5.0, 20.0, 200.0]
M, F_MAX, T_RAMP, STOP, STEP = 1.0, 10.0, 1.0, 3.0, 0.001


@pytest.fixture(scope="module")
def fmus(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("spring_fmus")
    return {
        "me": build_spring_fmu(d, "SpringME", ("model-exchange",)),
        "both": build_spring_fmu(d, "SpringBoth", ("co-simulation", "model-exchange")),
        "me_sources": build_spring_fmu(d, "SpringSrc", ("model-exchange",), binary=False, sources=True),
    }


def closed_form(c: float, d: float, times, m: float = M, f_max: float = F_MAX,
                t_ramp: float = T_RAMP, f_ext: float = 0.0) -> np.ndarray:
    """y(t) of m y'' + d y' + c y = F_max·min(t/t_ramp, 1) + F_ext, y(0) = y'(0) = 0, at ``times`` (ascending):
    the exact flow of the linear system in the state (y, v, t, 1), matrix exponentials from one time to
    the next, split at t_ramp."""
    a = {1: np.array([[0, 1, 0, 0], [-c / m, -d / m, f_max / (t_ramp * m), f_ext / m], [0, 0, 0, 1],
                      [0, 0, 0, 0]]),
         2: np.array([[0, 1, 0, 0], [-c / m, -d / m, 0, (f_max + f_ext) / m], [0, 0, 0, 1], [0, 0, 0, 0]])}
    cache: dict = {}

    def flow(piece: int, dt: float) -> np.ndarray:
        key = (piece, round(dt, 13))
        if key not in cache:
            cache[key] = expm(a[piece] * dt)
        return cache[key]

    x = np.array([0.0, 0.0, 0.0, 1.0])
    t_prev, out = 0.0, []
    for t in np.asarray(times, dtype=float):
        if t_prev < t_ramp < t:
            x = flow(2, t - t_ramp) @ (flow(1, t_ramp - t_prev) @ x)
        elif t <= t_ramp:
            x = flow(1, t - t_prev) @ x
        else:
            x = flow(2, t - t_prev) @ x
        out.append(x[0])
        t_prev = t
    return np.array(out)


def _times(stop: float = STOP, step: float = STEP) -> np.ndarray:
    n = math.ceil(stop / step - 1e-9)
    t = np.arange(n + 1) * step
    t[-1] = stop
    return t


def _study(fmu: str, options: str, fixed: str = "F_max: 10\nt_ramp: 1", extra_metrics: str = "") -> str:
    """A study of the (c, d) grid; ``options`` and ``fixed`` are 'key: value' lines."""
    def block(text: str) -> str:
        return "\n".join("  " + line for line in text.splitlines())
    return (f"name: spring\n"
            f"fmu: {fmu}\n"
            f"fmu_options:\n{block(options)}\n"
            f"parameters:\n"
            f"  c: {{variable: c, unit: N/m}}\n"
            f"  d: {{variable: d, unit: N·s/m}}\n"
            f"fixed:\n{block(fixed)}\n"
            f"scenario:\n"
            f"  stop_time: {STOP}\n"
            f"  step: {STEP}\n"
            f"metrics:\n"
            f"  max_y: {{output: y, reduce: max, unit: m}}\n"
            f"  y_end: {{output: y, unit: m}}\n"
            f"  max_v: {{output: v, reduce: max_abs, unit: m/s}}\n{extra_metrics}"
            f"stages:\n"
            f"  grid:\n"
            f"    values: {{c: {C_GRID}, d: {D_GRID}}}\n"
            f"execution:\n"
            f"  workers: 2\n")


def _grid(out: Path) -> pd.DataFrame:
    runs = pd.read_csv(out / "runs.csv")
    assert (runs["status"] == "ok").all(), runs[["c", "d", "status", "message"]]
    return runs.sort_values(["c", "d"]).reset_index(drop=True)


@pytest.fixture(scope="module")
def me_grid(fmus, tmp_path_factory):
    """The (c, d) grid of the model exchange FMU with CVode at rtol 1e-8, through the whole study pipeline."""
    tmp = tmp_path_factory.mktemp("me_study")
    path = tmp / "spring_me.yaml"
    path.write_text(_study(str(fmus["me"]), "interface: model-exchange\nsolver: CVode\n"
                                            "relative_tolerance: 1.0e-8"))
    from fmusa.study.loader import load_study
    study = load_study(path)
    assert study.fmu_options.interface == "model-exchange" and study.fmu_options.solver == "CVode"
    assert study.fmu_options.relative_tolerance == 1e-8
    run_study(study, tmp / "out", figures=False, progress=False)
    return _grid(tmp / "out"), tmp / "out"


def test_model_exchange_grid_matches_the_closed_form(me_grid):
    grid, out = me_grid
    assert len(grid) == len(C_GRID) * len(D_GRID)
    t = _times()
    for row in grid.itertuples():
        y = closed_form(row.c, row.d, t)
        v = np.gradient(y, t)
        assert row.max_y == pytest.approx(y.max(), rel=1e-5), (row.c, row.d)
        assert row.y_end == pytest.approx(y[-1], rel=1e-5), (row.c, row.d)
        assert row.max_v == pytest.approx(np.abs(v).max(), rel=2e-2)    # finite differences of y
    summary = json.loads((out / "summary.json").read_text())
    assert summary["failed"] == 0 and summary["runs"] == 9


def test_model_exchange_grid_matches_our_fmu(me_grid, fmu_path, tmp_path):
    """ScrewVertebra's axial motion obeys the same equation: m ÿ + d_y ẏ + c_y y = F_pull(t)."""
    grid, _ = me_grid
    text = _study("default", "interface: auto", fixed="F_max: 10\nt_ramp: 1\nm: 1\nrtol: 1.0e-10")
    text = text.replace("variable: c,", "variable: c_y,").replace("variable: d,", "variable: d_y,")
    text = text.replace("output: v,", "output: v_y,")
    study = parse_study(text, tmp_path / "screw.yaml")
    run_study(study, tmp_path / "out", figures=False, progress=False)
    ours = _grid(tmp_path / "out")
    np.testing.assert_allclose(grid["max_y"], ours["max_y"], rtol=1e-5)
    np.testing.assert_allclose(grid["y_end"], ours["y_end"], rtol=1e-5)


def test_auto_prefers_co_simulation_and_model_exchange_can_be_chosen(fmus):
    info = read_fmu_info(fmus["both"])
    assert list(info.interfaces) == ["co-simulation", "model-exchange"]
    t = _times()
    y_ref = closed_form(400.0, 20.0, t)
    with FMURunner(fmus["both"]) as cs:
        assert cs.interface == "co-simulation"
        y_cs = cs.run({"c": 400.0, "d": 20.0}, STOP, STEP, ["y"])["y"].to_numpy()
    with FMURunner(fmus["both"], interface="model-exchange", relative_tolerance=1e-9) as me:
        assert me.interface == "model-exchange"
        y_me = me.run({"c": 400.0, "d": 20.0}, STOP, STEP, ["y"])["y"].to_numpy()
        final = me.run_final({"c": 400.0, "d": 20.0}, STOP, ["y", "y_static"])
    scale = np.abs(y_ref).max()
    assert np.abs(y_cs - y_ref).max() < 1e-8 * scale      # the FMU's own RK4
    assert np.abs(y_me - y_ref).max() < 1e-6 * scale      # fmpy's CVode
    assert final["y"] == pytest.approx(y_ref[-1], rel=1e-6)
    assert final["y_static"] == pytest.approx(F_MAX / 400.0)


def test_co_simulation_never_needs_fmpys_solver(fmus, fmu_path, monkeypatch):
    import fmpy
    import fmpy.simulation

    def refuse(*a, **k):
        raise AssertionError("fmpy.simulate_fmu must not run a co-simulation FMU")
    monkeypatch.setattr(fmpy, "simulate_fmu", refuse)
    monkeypatch.setattr(fmpy.simulation, "simulate_fmu", refuse)
    with FMURunner(fmus["both"]) as cs:
        assert cs.run_final({"c": 400.0}, STOP, ["y"])["y"] == pytest.approx(0.025, rel=1e-6)
        plan = RunPlan(cs, ["c", "d"], {"F_max": 10.0}, ["y"], STOP, None)
        assert plan([400.0, 20.0])[-1, 0] == pytest.approx(0.025, rel=1e-6)
    with FMURunner(fmu_path, relative_tolerance=1e-8) as ours:     # tolerance -> fmi2SetupExperiment
        assert ours.interface == "co-simulation"
        plan = RunPlan(ours, ["c_y", "d_y"], {}, ["y_max"], 12.0, None)
        assert plan([823224.0, 488.0])[-1, 0] == pytest.approx(411 / 823224.0, rel=1e-3)
    with pytest.raises(ValueError, match="model exchange only"):
        FMURunner(fmus["both"], solver="CVode")


def test_solver_and_tolerance_are_used(fmus):
    t = _times()
    y_ref = closed_form(1600.0, 2.0, t)     # lightly damped: 40 rad/s oscillation, hard for loose tolerances
    err = {}
    for rtol in (1e-3, 1e-10):
        with FMURunner(fmus["me"], relative_tolerance=rtol) as me:
            y = me.run({"c": 1600.0, "d": 2.0}, STOP, STEP, ["y"])["y"].to_numpy()
        err[rtol] = np.abs(y - y_ref).max() / np.abs(y_ref).max()
    # CVode's global error over ~19 periods grows to a few hundred times rtol
    assert err[1e-10] < 1e-6 and err[1e-3] > 1e3 * err[1e-10]
    # Euler: a first-order fixed step, sampled every 0.01 s on every 100th step of 1e-4 s
    with FMURunner(fmus["me"], solver="Euler", step_size=1e-4) as me:
        df = me.run({"c": 400.0, "d": 20.0}, 1.5, 0.01, ["y"])
    y_ref = closed_form(400.0, 20.0, df["time"].to_numpy())
    assert len(df) == 151
    e = np.abs(df["y"].to_numpy() - y_ref).max() / np.abs(y_ref).max()
    assert 1e-6 < e < 1e-2


def test_euler_through_the_study(fmus, tmp_path):
    """fmpy's Euler takes one step per output point: the study samples every 10th step of 1e-4 s."""
    text = _study(str(fmus["me"]), "interface: model-exchange\nsolver: Euler\nstep_size: 1.0e-4")
    text = text.replace(f"stop_time: {STOP}", "stop_time: 0.5").replace(f"step: {STEP}", "step: 0.001")
    text = text.replace(f"values: {{c: {C_GRID}, d: {D_GRID}}}", "values: {c: [400.0], d: [20.0, 200.0]}")
    text = text.replace("F_max: 10\n  t_ramp: 1", "F_max: 10\n  t_ramp: 0.2")
    study = parse_study(text, tmp_path / "euler.yaml")
    assert study.fmu_options.solver == "Euler" and study.fmu_options.step_size == 1e-4
    run_study(study, tmp_path / "out", figures=False, progress=False)
    grid = _grid(tmp_path / "out")
    t = _times(0.5, 0.001)
    for row in grid.itertuples():
        y = closed_form(row.c, row.d, t, t_ramp=0.2)
        assert row.max_y == pytest.approx(y.max(), rel=1e-2)
        assert row.max_y != pytest.approx(y.max(), rel=1e-7)     # first order: visibly not CVode


def test_inputs_and_fixed_parameters_reach_the_model_exchange_fmu(fmus):
    with FMURunner(fmus["me"], relative_tolerance=1e-9) as me:
        plan = RunPlan(me, ["c"], {"d": 200.0, "F_max": 10.0, "t_ramp": 0.5}, ["y", "F"], STOP, 0.01,
                       {"F_ext": 5.0})
        data = plan([400.0])
        assert plan.times[-1] == STOP and data.shape == (len(plan.times), 2)
        y_ref = closed_form(400.0, 200.0, plan.times, t_ramp=0.5, f_ext=5.0)
        np.testing.assert_allclose(data[:, 0], y_ref, rtol=1e-5, atol=1e-9)
        assert data[-1, 1] == pytest.approx(15.0)
        # the instance is reused: reset between runs, the next run starts from the FMU's defaults + these
        again = plan([400.0])
        np.testing.assert_array_equal(again, data)


def test_a_failing_model_exchange_run_is_recorded_and_the_next_one_runs(fmus):
    rule = MetricRule("y_end", 0, "final")
    spec = PlanSpec(fmu_path=str(fmus["me"]), varied=("c", "m"), scale=(1.0, 1.0), offset=(0.0, 0.0),
                    fixed=(("F_max", 10.0),), inputs=(), outputs=("y",), stop_time=STOP, step=None,
                    rules=(rule,), interface="model-exchange", solver="CVode", relative_tolerance=1e-9)
    res = run_chunk(spec, [(0, (400.0, 1.0)), (1, (400.0, 0.0)), (2, (400.0, 1.0))])
    assert [r.status for r in res] == ["ok", "failed", "ok"]
    assert "m must be > 0" in res[1].message and "SpringME" in res[1].message
    assert res[0].metrics[0] == res[2].metrics[0] == pytest.approx(closed_form(400.0, 20.0, [STOP])[0], rel=1e-6)


def test_model_exchange_fmu_without_binary_is_compiled_from_its_sources(fmus, me_grid, tmp_path):
    info = read_fmu_info(fmus["me_sources"])
    assert info.platforms == [] and info.can_compile and info.source_files == ("spring.c",)
    text = _study(str(fmus["me_sources"]), "interface: model-exchange\nrelative_tolerance: 1.0e-8")
    study = parse_study(text, tmp_path / "src.yaml")
    run_study(study, tmp_path / "out", figures=False, progress=False)
    built = list((tmp_path / "out" / ".fmu").glob("SpringSrc-*/binaries/linux64/spring.so"))
    assert len(built) == 1
    grid, _ = me_grid
    np.testing.assert_allclose(_grid(tmp_path / "out")["max_y"], grid["max_y"], rtol=1e-9)
