"""A screw pulled to failure (issue 22): the interface fails past a peak and the force drops to a friction
plateau. `fmusa diagnose` must name the failure (interface_damage), tell it from friction and yield, never fit
the force of a constant-rate ramp to the damping, and describe what is left without calling a peak an
oscillation.

The curve is made by tests/effects_reference.py (independent of the FMU): a displacement ramp at 0.01 mm/s to
1.8 mm, stiffness 546 N/mm, damage from 1.0 mm (peak 546 N there), softening 5 /mm, residual 150 N, Gaussian
noise of 0.1 N as in the public push-in curve of the issue. One file has a time column, the other has none and
gets its time from ``--rate '0.01 mm/s'`` (ColumnSpec.rate): the two give the same time axis, so one diagnosis
stands for both.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import effects_reference as er  # noqa: E402

from fmusa.diagnose.measured import ColumnSpec, Experiment, downsample, load_experiment  # noqa: E402
from fmusa.diagnose.rank import group_members  # noqa: E402

RATE = 1e-5           # 0.01 mm/s
Y_END = 1.8e-3
TRUTH = {"c_y": 5.46e5, "d_y": 0.0, "dmg_y0": 1.0e-3, "dmg_rate": 5000.0, "dmg_F_res": 150.0}
NOISE = 0.1


def pull_curve(seed: int = 0) -> pd.DataFrame:
    """time [s], displacement [mm], force [N] of the synthetic pull to failure."""
    T = Y_END / RATE
    t = np.linspace(0.0, T, 361)
    F = er.simulate(TRUTH, "displacement", [0.0, T], [0.0, Y_END], t)
    F = F + np.random.default_rng(seed).normal(0.0, NOISE, t.size)
    return pd.DataFrame({"time": t, "displacement": 1e3 * RATE * t, "force": F})


def test_time_from_the_rate_is_the_time_column(tmp_path):
    """Without a time column, --rate '0.01 mm/s' gives the same time axis as the column (uniform sampling)."""
    df = pull_curve()
    with_t, without_t = tmp_path / "with.csv", tmp_path / "without.csv"
    df.to_csv(with_t, index=False)
    df.drop(columns="time").to_csv(without_t, index=False)
    a = load_experiment(with_t, "displacement", ColumnSpec(displacement_unit="mm"))
    b = load_experiment(without_t, "displacement", ColumnSpec(displacement_unit="mm", rate="0.01 mm/s"))
    np.testing.assert_allclose(b.t, a.t, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(b.force, a.force)


@pytest.fixture(scope="module")
def failure_diagnosis(fmu_path, tmp_path_factory):
    from fmusa.diagnose.run import run_diagnosis

    df = pull_curve()
    csv = tmp_path_factory.mktemp("pull") / "pull.csv"
    df.drop(columns="time").to_csv(csv, index=False)
    e = load_experiment(csv, "displacement", ColumnSpec(displacement_unit="mm", rate="0.01 mm/s"))
    e = downsample(Experiment(name="pull", path=csv, drive="displacement", t=e.t, displacement=e.displacement,
                              force=e.force), 180)
    out = tmp_path_factory.mktemp("pull_out")
    d = run_diagnosis([e], "displacement", out, fmu_path=fmu_path, workers=2, max_starts=3, progress=False,
                      candidates=("interface_damage", "coulomb_friction", "yield_softening"))
    return d, (out / "report.md").read_text(encoding="utf-8")


def test_failure_is_named_and_told_from_friction_and_yield(failure_diagnosis):
    d, report = failure_diagnosis
    assert group_members(d["effect"]) == ["interface_damage"], d["effect"]
    p = {k: v["value"] for k, v in d["effect_params"].items()}
    assert p["dmg_y0"] == pytest.approx(TRUTH["dmg_y0"], rel=0.05)
    assert p["dmg_F_res"] == pytest.approx(TRUTH["dmg_F_res"], rel=0.05)
    assert p["dmg_rate"] == pytest.approx(TRUTH["dmg_rate"], rel=0.10)
    # friction and yield cannot drop the force while the displacement grows: told apart, not look-alikes
    named_alike = {i["effect"] for i in d["indistinguishable"]}
    assert not named_alike & {"coulomb_friction", "yield_softening"}, d["indistinguishable"]
    assert "Effect: `interface_damage`" in report or "`interface_damage`" in report.split("\n## ")[1]


def test_constant_rate_never_fits_the_force_to_the_damping(failure_diagnosis):
    """One constant rate: d_y*v is a constant, so d_y is held at 0 and the report says which test identifies
    it; the baseline is then the secant line, never a constant force carried by the damping."""
    d, report = failure_diagnosis
    base = d["baseline"]
    assert base["params"]["d_y"] == 0.0 and "d_y" in base["held"]
    assert "second rate" in base["held"]["d_y"]["identifying_test"]
    assert d["straight_line"]["baseline_not_worse"]
    assert base["params"]["c_y"] == pytest.approx(d["straight_line"]["c_y"], rel=1e-3)
    assert "`d_y` held at 0" in report and "second rate" in report


def test_no_oscillation_in_a_peak_and_a_drop(failure_diagnosis):
    """The baseline misses the peak and the drop: a region of misfit with where and how much, no wave."""
    d, report = failure_diagnosis
    st = d["residuals"]["baseline"]
    assert st["structured"] and st["oscillation"] is None
    assert st["misfit"] is not None and st["misfit"]["x_start"] < st["misfit"]["x_end"]
    assert "Hz" not in st["description"] and " mm " in st["description"] + " "
    assert d["residuals"]["extended"]["oscillation"] is None


def test_a_candidate_fit_worse_than_the_baseline_is_refitted_from_it(fmu_path):
    """A candidate contains the baseline (its effect off), so a fit of it worse than the baseline's is the
    optimiser's failure (as the force-driven damage fit was when every start let the interface run away): it
    is refitted from the baseline's optimum, its runs counted with the first fit's, and the report says so."""
    import zlib

    from fmusa.diagnose.calibrate import Fit, fit_candidate
    from fmusa.diagnose.fitcache import FailedFit
    from fmusa.diagnose.models import resolve
    from fmusa.diagnose.report import _ranking_section
    from fmusa.diagnose.run import _refit_worse_than_baseline

    df, _ = er.synthesize("nonlinear_stiffness", "force",
                          seed=zlib.crc32(b"nonlinear_stiffness/force") % 10_000)
    e = downsample(Experiment("s", Path("s.csv"), "force", df.time.values, df.displacement.values,
                              df.force.values), 120)
    interface = resolve(None, str(fmu_path))
    base = fit_candidate(str(fmu_path), "none", "force", [e], 2, interface)
    # a first fit that stalled far off (its numbers as a stalled fit reports them)
    stalled = Fit(effect="backlash_gap", params={"c_y": base.params["c_y"], "d_y": base.params["d_y"], "gap": 1e-4},
                  ci95={}, rss=1e3 * base.rss, n=base.n, k=3, rmse=base.rmse * 31.6, starts_tried=1,
                  runs={"fit": 7}, rounds={"fit": 7})
    results = {"none": base, "backlash_gap": stalled, "sensor_offset": FailedFit("an FMU error", {"fit": 3})}
    notes = _refit_worse_than_baseline(results, base, str(fmu_path), "force", [e], 2, interface, 1, None)
    refit = results["backlash_gap"]
    assert isinstance(refit, Fit) and refit.rss <= base.rss * (1 + 1e-6), refit
    assert refit.runs["fit"] > 7 and refit.runs.get("heldout", 0) > 0     # both fits' runs, and its held-out score
    assert "worse than the baseline" in notes["backlash_gap"]["text"]
    assert isinstance(results["sensor_offset"], FailedFit)                 # a failed fit is left as it is
    text = _ranking_section({"ranking": [], "refitted": notes, "failed": {"sensor_offset": "an FMU error"},
                             "effect": "none", "data": {"response": "displacement", "drive": "force"}})
    assert "`backlash_gap`: its first fit" in text and "- `sensor_offset`: an FMU error" in text
