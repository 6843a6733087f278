"""Metrics from sampled outputs (an FMU without monitors): the sampling bound the report states, and
``scenario.refine_peaks``, measured on the third-party AxialScrew FMU (pythonfmu) against the exact
monitors of our own FMU (max |y|, max |v|) and against much finer sampling (settling time)."""
from __future__ import annotations

import re

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from fmusa.fmi.runner import FMURunner
from fmusa.runs.metrics import MetricRule, reduce_series
from fmusa.runs.refine import refine_intervals, refined_times
from fmusa.study.schema import Metric, StudyError
from fmusa.study.loader import parse_study
from fmusa.api import run_study

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_vendor_fmus import build_axial_screw  # noqa: E402

STEP = 0.001
C = [20, 26, 33, 41, 50, 60]          # N/m: lightly damped, 16-28 ms period, 16-28 samples per period
D = [0.005, 0.01, 0.02, 0.03]         # N·s/m


@pytest.fixture(scope="module")
def axial(tmp_path_factory) -> Path:
    return build_axial_screw(tmp_path_factory.mktemp("axial"))


def study_text(fmu: Path, refine: bool, c=C, d=D, stop=0.1) -> str:
    return f"""\
name: sampled
fmu: {fmu}
parameters:
  c: {{variable: "screw.bushing.c[2]", unit: N/m, scale: 1.0e-3}}
  d: {{variable: "screw.bushing.d[2]", unit: N·s/m, scale: 1.0e-3}}
fixed:
  "'F pull'": 411
  t_ramp: 0.004
  screw.mass: 0.29
scenario:
  stop_time: {stop}
  step: {STEP}
  refine_peaks: {str(refine).lower()}
metrics:
  max_y: {{output: screw.y_mm, reduce: max_abs, scale: 1.0e-3, unit: m}}
  max_v: {{output: "der(screw.y_mm)", reduce: max_abs, scale: 1.0e-3, unit: m/s}}
  t_set: {{output: "der(screw.y_mm)", reduce: settle, settle_tol: 1.0, unit: s}}
stages:
  grid:
    values: {{c: {list(c)}, d: {list(d)}}}
execution: {{workers: 1}}
"""


def monitors(runs) -> np.ndarray:
    """max |y| and max |v| of every run from our FMU's monitors (updated on every internal solver step,
    rtol 1e-10): the exact peaks the sampled ones are compared with."""
    out = []
    with FMURunner() as fmu:
        for c, d in zip(runs["c"], runs["d"]):
            f = fmu.run_final({"c_y": c, "d_y": d, "m": 2.9e-4, "F_max": 411.0, "t_ramp": 0.004, "rtol": 1e-10},
                              0.1, ["y_max", "v_y_max"])
            out.append((f["y_max"], f["v_y_max"]))
    return np.array(out)


def test_refine_peaks_cuts_the_peak_error_against_exact_monitors(axial, tmp_path, fmu_path):
    coarse = run_study(parse_study(study_text(axial, False), tmp_path / "a.yaml"), tmp_path / "coarse",
                       figures=False, progress=False).runs.sort_values(["c", "d"])
    fine = run_study(parse_study(study_text(axial, True), tmp_path / "b.yaml"), tmp_path / "fine",
                     figures=False, progress=False).runs.sort_values(["c", "d"])
    assert (coarse["status"] == "ok").all() and (fine["status"] == "ok").all() and len(fine) == len(C) * len(D)
    exact = monitors(fine)
    err = {}
    for name, runs in (("coarse", coarse), ("fine", fine)):
        got = runs[["max_y", "max_v"]].to_numpy()
        err[name] = np.abs(got - exact) / exact
        assert (got <= exact * (1 + 1e-7)).all()       # a sampled peak can only be low
    worst_c, worst_f = err["coarse"].max(axis=0), err["fine"].max(axis=0)
    print(f"\nlargest relative peak error (max_y, max_v): every {STEP:g} s {worst_c}, refined 10x {worst_f}")
    assert (worst_c > 3e-3).all()                      # sampling every ms misses the peaks by > 0.3 %
    assert (worst_f < worst_c / 30).all()              # 10x finer around the peak: ~100x smaller
    assert (err["fine"] <= err["coarse"] + 1e-9).all()  # never worse, run by run
    # the refinement re-samples the peaks only: a metric that does not sit at a sample is unchanged
    assert np.array_equal(coarse["t_set"].isna(), fine["t_set"].isna())


def test_refine_peaks_resolves_the_settling_time(axial, tmp_path):
    """t_set (|v| <= 1 mm/s from then on) is one interval late at most; refined, one tenth of it. The
    reference is the same FMU sampled 100 times finer (every 10 µs)."""
    c, d = [45.0], [0.1, 0.15, 0.2]
    runs = {}
    for name, refine in (("coarse", False), ("fine", True)):
        st = parse_study(study_text(axial, refine, c, d), tmp_path / f"{name}.yaml")
        runs[name] = run_study(st, tmp_path / name, figures=False, progress=False).runs.sort_values("d")
    rule = [MetricRule("t_set", 0, "settle", settle_tol=1.0)]
    ref = []
    with FMURunner(axial) as fmu:
        for dd in d:
            df = fmu.run({"screw.bushing.c[2]": 0.045, "screw.bushing.d[2]": dd * 1e-3, "'F pull'": 411.0,
                          "t_ramp": 0.004, "screw.mass": 0.29}, 0.1, STEP / 100, ["der(screw.y_mm)"])
            ref.append(reduce_series(df["time"].to_numpy(), df[["der(screw.y_mm)"]].to_numpy(), rule)[0])
    ref = np.array(ref)
    assert np.isfinite(ref).all() and (ref < 0.09).all()
    late_c = runs["coarse"]["t_set"].to_numpy() - ref
    late_f = runs["fine"]["t_set"].to_numpy() - ref
    print(f"\nt_set late by: every {STEP:g} s {late_c}, refined 10x {late_f}")
    res = STEP / 100                                  # the reference's own resolution
    assert ((late_c >= -res) & (late_c <= STEP + 1e-9)).all()
    assert ((late_f >= -res) & (late_f <= STEP / 10 + 1e-9)).all()
    assert late_c.max() > STEP / 10                   # the coarse error is really larger than the refined bound


def test_report_states_and_measures_the_sampling_effect(axial, tmp_path):
    study = parse_study(study_text(axial, True, [26, 50], [0.01, 0.2]), tmp_path / "r.yaml")
    run_study(study, tmp_path / "out", figures=True, progress=False)
    text = (tmp_path / "out" / "report.md").read_text(encoding="utf-8")
    assert "## Sampling of the outputs" in text
    assert "h = 0.001 s" in text and "h²/8·|y''|" in text and "± 0.0001 s" in text
    assert "refine_peaks` (factor 10)" in text
    s = json.loads((tmp_path / "out" / "summary.json").read_text())["sampling"]
    assert s["step"] == STEP and s["refine_factor"] == 10 and s["interval_at_peaks"] == pytest.approx(1e-4)
    checks = [c for c in s["checks"] if c["reference"] is not None and c["value"] is not None]
    assert {c["metric"] for c in checks} == {"max_y", "max_v", "t_set"}
    # the measured difference to a 100x finer re-run stays inside the stated bound, and is small
    assert all(c["within_bound"] for c in checks), checks
    peaks = [c for c in checks if c["metric"] != "t_set"]
    assert max(c["error"] / c["reference"] for c in peaks) < 1e-4
    assert all(c["error"] <= 1e-4 + 1e-12 for c in checks if c["metric"] == "t_set")


def test_a_late_excursion_between_samples_is_refined():
    """A decaying oscillation whose last return above the band falls between two samples inside it: the
    settling time from the samples is early by more than one interval; refinement finds the hump (where |x|
    is concave) and the refined settling time lies within the refined interval of a 1000x finer one."""
    from fmusa.runs.refine import hidden_excursions
    from fmusa.runs.metrics import settle_index
    w, zeta, tol = 2 * np.pi * 43.0, 0.05, 0.15

    def x(t):
        return np.exp(-zeta * w * t) * np.cos(w * t)

    fine = np.linspace(0.0, 0.2, 200_001)
    t_true = fine[settle_index(x(fine), tol)]
    t = np.arange(0.0, 0.2 + 1e-12, 0.002)                 # 11.6 samples a period: a hump falls between samples
    k = settle_index(x(t), tol)
    assert t_true - t[k] > 0.002                           # the plain samples settle too early
    rules = [MetricRule("s", 0, "settle", settle_tol=tol)]
    intervals = refine_intervals(t, x(t)[:, None], rules)
    assert set(hidden_excursions(t, x(t), tol, k)) <= set(intervals)
    g = refined_times(t, intervals, 10)
    t_ref = g[settle_index(x(g), tol)]
    assert abs(t_ref - t_true) <= 0.0002 + 1e-12, (t_ref, t_true)
    # a monotone decay inside the band has no hump: nothing after the settling sample is refined
    d = np.exp(-t / 0.01)
    kd = settle_index(d, 0.5)
    assert hidden_excursions(t, d, 0.5, kd) == []


def test_refined_grid_and_intervals():
    t = np.arange(6) * 0.1
    x = np.array([[0.0, 5.0], [1.0, 3.0], [3.0, 2.0], [2.0, 0.5], [1.0, 0.1], [0.5, 0.05]])
    rules = [MetricRule("p", 0, "max"), MetricRule("s", 1, "settle", settle_tol=0.6)]
    assert refine_intervals(t, x, rules) == [1, 2]           # around the peak sample 2; settled from sample 3
    g = refined_times(t, [1, 2], 4)
    assert len(g) == 6 + 2 * 3 and np.all(np.diff(g) > 0)
    np.testing.assert_allclose(g[1:10], [0.1, 0.125, 0.15, 0.175, 0.2, 0.225, 0.25, 0.275, 0.3])
    v = reduce_series(t, x, rules)
    assert v[0] == 3.0 and v[1] == pytest.approx(0.3)


def test_time_mean_of_unevenly_sampled_signal_is_one_value():
    """A study metric and a worker's reduction are one implementation: the time mean (trapezoid rule) of
    t² on [0, 1], sampled unevenly, is 1/3 up to the trapezoid error; a plain mean of the samples is not."""
    t = np.concatenate([np.linspace(0.0, 0.5, 400, endpoint=False), np.linspace(0.5, 1.0, 41)])
    x = t ** 2
    h = np.diff(t)
    trapezoid_error = float(np.sum(h ** 3) / 6)      # (b - a) h² f''/12 with f'' = 2, interval by interval
    mean = Metric("m", "y", reduce="mean")
    assert mean.compute(x, t) == pytest.approx(1 / 3 + trapezoid_error, rel=1e-12)
    assert abs(mean.compute(x, t) - 1 / 3) < 1e-4 < abs(x.mean() - 1 / 3)
    rules = [MetricRule("m", 0, "mean"), MetricRule("a", 1, "mean_abs", scale=2.0, offset=1.0)]
    both = reduce_series(t, np.column_stack([x, -x]), rules)
    assert both[0] == mean.compute(x, t)
    assert both[1] == Metric("a", "y", reduce="mean_abs", scale=2.0, offset=1.0).compute(-x, t)
    # every reduction: the study's metric gives what the worker gives
    for reduce in ("final", "max", "min", "max_abs", "mean", "mean_abs"):
        m = Metric("m", "y", reduce=reduce, scale=3.0, offset=-1.0, missing_below=-0.5)
        worker = reduce_series(t, np.sin(7 * t)[:, None], [MetricRule("m", 0, reduce, 3.0, -1.0, -0.5)])[0]
        np.testing.assert_equal(m.compute(np.sin(7 * t), t), worker, err_msg=reduce)   # min: NaN (missing)
    settle = Metric("s", "y", reduce="settle", settle_tol=0.01)
    assert settle.compute(np.exp(-10 * t), t) == pytest.approx(t[np.argmax(np.exp(-10 * t) <= 0.01)])
    with pytest.raises(ValueError, match="needs the sample times"):
        settle.compute(np.exp(-10 * t))


def test_refine_peaks_is_validated_at_load(tmp_path):
    base = study_text(Path("/nonexistent.fmu"), True).replace("fmu: /nonexistent.fmu\n", "")
    with pytest.raises(StudyError, match=r"bad\.yaml:12: key 'refine_peaks' in 'scenario' refines sampled outputs, "
                                         r"but step is null"):
        parse_study(base.replace(f"  step: {STEP}\n", "  step: null\n"), "bad.yaml")
    no_peak = base.split("metrics:")[0] + "metrics:\n  y_end: {output: screw.y_mm}\nstages:" + base.split("stages:")[1]
    with pytest.raises(StudyError, match=r"bad\.yaml:12: key 'refine_peaks' in 'scenario': no metric takes a peak"):
        parse_study(no_peak, "bad.yaml")
    with pytest.raises(StudyError, match=r"refine_factor' in 'scenario' must be ≥ 2"):
        parse_study(base.replace("  refine_peaks: true\n", "  refine_peaks: true\n  refine_factor: 1\n"), "bad.yaml")
    with pytest.raises(StudyError, match=r"'settle' .* needs the band; add settle_tol") as err:
        parse_study(base.replace(", settle_tol: 1.0", ""), "bad.yaml")
    # no number whatever the output's unit (the paper's velocity threshold is no band for a displacement in mm)
    assert "FMU's unit of der(screw.y_mm)" in str(err.value) and not re.search(r"settle_tol: \d", str(err.value))
    with pytest.raises(StudyError, match=r"settle_tol' in 'metrics.max_y' applies to reduce: settle only"):
        parse_study(base.replace("reduce: max_abs, scale: 1.0e-3, unit: m}", "reduce: max_abs, settle_tol: 1, unit: m}"),
                    "bad.yaml")
