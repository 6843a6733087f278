"""A diagnosis counts its FMU runs by stage and stays within the budget it is given.

The count is checked from outside fmusa: the real FMU rebuilt from its own sources with every
initialisation logged to a file (fmusa.fmi.instrument), run by the diagnosis's worker processes; the
lines in that file are the runs the FMU saw, whatever fmusa's counter says.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import effects_reference as er  # noqa: E402

from fmusa.diagnose.calibrate import ModelRunner  # noqa: E402
from fmusa.diagnose.effects import DiagnoseError  # noqa: E402
from fmusa.diagnose.measured import Experiment, downsample  # noqa: E402
from fmusa.diagnose.report import write_report  # noqa: E402
from fmusa.diagnose.run import diagnose  # noqa: E402
from fmusa.fmi.instrument import count_logged_runs, instrumented_copy  # noqa: E402

CANDIDATES = ("sensor_offset", "backlash_gap")


@pytest.fixture(scope="module")
def logged_fmu(fmu_path, tmp_path_factory):
    """The ScrewVertebra FMU, rebuilt so that every run appends a line to its log."""
    root = tmp_path_factory.mktemp("logged")
    log = root / "runs.log"
    return instrumented_copy(fmu_path, root / "fmu", log), log


@pytest.fixture(scope="module")
def experiment():
    df, _ = er.synthesize("sensor_offset", "force", seed=7)
    e = Experiment(name="offset", path=Path("offset.csv"), drive="force", t=df.time.values,
                   displacement=df.displacement.values, force=df.force.values)
    return downsample(e, 40)


@pytest.fixture(scope="module")
def counted(logged_fmu, experiment):
    """A whole diagnosis (two candidates, a chain of two) on the logged FMU in two worker processes, and the
    runs the FMU logged."""
    fmu, log = logged_fmu
    log.unlink(missing_ok=True)
    d = diagnose([experiment], "force", fmu_path=fmu, candidates=CANDIDATES, workers=2, max_starts=1, chain=2)
    return d, count_logged_runs(log)


def _stage_total(runs: dict) -> int:
    fits = [runs["baseline"], *runs["candidates"].values(), *runs["chain"].values(), *runs["checks"].values()]
    return sum(f["total"] for f in fits if not f.get("cached"))


def test_runs_counted_by_stage_match_the_runs_the_fmu_saw(counted, experiment, tmp_path):
    d, seen = counted
    runs = d["runs"]
    assert seen > 50 and runs["chain"], "the chain must have run for its runs to be checked"
    assert runs["total"] == seen == runs["counted_by_fits"] == _stage_total(runs)
    # the test is block means: the averaging check ran the final model and the baseline once each at its samples
    assert runs["checks"]["averaging"]["total"] == 2 == d["averaging"]["runs"] and d["averaging"]["made"]
    assert set(runs["candidates"]) == set(CANDIDATES) and runs["budget"] is None and not runs["left_out"]
    for r in [runs["baseline"], *runs["candidates"].values()]:
        assert r["fit"] > 0 and r["heldout"] > 0 and r["total"] == r["fit"] + r["heldout"]
    write_report(d, [experiment], tmp_path, [])
    text = (tmp_path / "report.md").read_text(encoding="utf-8")
    assert "## FMU runs" in text and f"{seen} FMU runs" in text and "run budget" not in text


def test_a_budget_bounds_the_runs_and_names_what_it_left_out(logged_fmu, counted, experiment, tmp_path):
    fmu, log = logged_fmu
    full, _ = counted
    base_runs = full["runs"]["baseline"]["total"]
    budget = base_runs + 10        # the baseline fits; the first candidate runs out
    log.unlink()
    d = diagnose([experiment], "force", fmu_path=fmu, candidates=CANDIDATES, workers=1, max_starts=1, chain=2,
                 max_runs=budget)
    runs = d["runs"]
    assert count_logged_runs(log) == runs["total"] <= budget
    assert runs["total"] >= budget - 5        # a Jacobian round that would pass the budget is not started
    assert runs["budget_ended"] and set(runs["left_out"]) == set(CANDIDATES)
    # what it did is right: the baseline is the same fit as without a budget, and nothing is named from
    # candidates it did not fit
    assert d["baseline"]["params"] == full["baseline"]["params"]
    assert d["effect"] == "none" and d["ranking"] == []
    assert all(r["left_out"] for r in runs["candidates"].values()) and not runs["chain"]
    # (its baseline may have made a few runs fewer than the unbudgeted one: the process already knew whether the
    # FMU's sensitivities pay, and did not time them again)
    assert runs["baseline"]["total"] <= base_runs
    # (the block averaging's check takes what the budget has left, if anything)
    checks = sum(r["total"] for r in runs["checks"].values())
    assert sum(r["total"] for r in runs["candidates"].values()) == runs["total"] - runs["baseline"]["total"] - checks
    write_report(d, [experiment], tmp_path, [])
    text = (tmp_path / "report.md").read_text(encoding="utf-8")
    assert f"The run budget ({budget} FMU runs) ended" in text and "`sensor_offset`" in text
    # too small for the baseline: refused, saying so
    log.unlink()
    with pytest.raises(DiagnoseError, match="run budget of 5 FMU runs ended before the baseline"):
        diagnose([experiment], "force", fmu_path=fmu, candidates=CANDIDATES, workers=1, max_runs=5)
    assert count_logged_runs(log) == 5


def test_a_jacobian_round_in_parallel_is_the_same_as_one_run_after_another(fmu_path, experiment):
    """The columns of a finite-difference Jacobian run on several FMU instances at once give the same
    numbers as on one."""
    from fmusa.diagnose.calibrate import Residuals, parameter_bounds, response_scale
    from fmusa.diagnose.effects import data_scales, model_parameters

    sc = data_scales([experiment])
    params = model_parameters("backlash_gap", "force", sc)
    lo, hi = parameter_bounds(params)
    x = np.array([p.to_x(p.starts[0]) for p in params])
    jacs = []
    for lanes in (1, 3):
        model = ModelRunner(fmu_path, "force", [p.name for p in params], parallel=lanes)
        model.has_sensitivities = False   # the finite differences, not the FMU's forward sensitivities
        try:
            fn = Residuals(model, params, [experiment], [np.ones(len(experiment.t), bool)],
                           response_scale("force", sc), lo, hi)
            jacs.append(fn.jac(x))
            assert model.runs == {"fit": 1 + len(params)}
        finally:
            model.close()
    assert np.array_equal(jacs[0], jacs[1])
    assert np.all(np.isfinite(jacs[0])) and np.linalg.matrix_rank(jacs[0]) == len(params)


def test_a_chain_fit_that_cannot_be_significant_makes_no_heldout_runs(counted):
    """The chain's additions that fail the in-sample tests against the model so far (or its physics check)
    cannot be its next step, so they make no held-out refits; the others make them. Every fit states its
    rounds, and the diagnosis the rounds it waited for one after another (its depth)."""
    from fmusa.diagnose.calibrate import Fit, can_be_significant
    from fmusa.diagnose.rank import Thresholds

    d, _ = counted
    runs, th = d["runs"], Thresholds()
    assert runs["chain"]
    for name, r in runs["chain"].items():
        assert (r["heldout"] == 0) == bool(r.get("heldout_skipped")), (name, r)
    skipped = [n for n, r in runs["chain"].items() if r.get("heldout_skipped")]
    assert skipped, "the offset data leave no significant second effect: its held-out refits must be skipped"
    # the named chain never holds a skipped fit, and what was skipped fails the in-sample tests or physics
    assert not set(skipped) & {s["model"] for s in d["chain"][1:]}
    first = d["extended"]
    base = Fit(effect="", params={}, ci95={}, rss=first["rmse"] ** 2 * first["n"], n=first["n"], k=first["k"],
               rmse=first["rmse"])
    assert can_be_significant(base, base, th.delta_bic, th.p_value)      # no gain: cannot be significant
    from fmusa.diagnose.runs_report import runs_section

    assert "no held-out refits: it cannot be the chain's next step" in runs_section(d)
    # with one FMU instance per fit, each run is its own round; the depth is the longest fit of the first round
    # plus the longest of each chain step
    assert all(r["rounds"] == r["total"] for r in [runs["baseline"], *runs["candidates"].values()])
    first_round = max(r["rounds"] for r in [runs["baseline"], *runs["candidates"].values()])
    # (and the checks after the fits, one after another)
    checks = sum(r["rounds"] for r in runs["checks"].values())
    assert runs["depth"] == first_round + max(r["rounds"] for r in runs["chain"].values()) + checks


def test_heldout_refits_at_once_are_the_same_as_one_after_another(fmu_path, experiment):
    """The held-out refits run at once on several FMU instances give the same folds as one after another,
    with the same runs, in fewer rounds."""
    from fmusa.diagnose.calibrate import calibrate, heldout_folds
    from fmusa.diagnose.effects import data_scales, model_parameters

    sc = data_scales([experiment])
    names = [p.name for p in model_parameters("sensor_offset", "force", sc)]
    fit, out = None, []
    for lanes in (1, 4):
        model = ModelRunner(fmu_path, "force", names, parallel=lanes)
        model.has_sensitivities = False   # the finite differences, not the FMU's forward sensitivities
        try:
            if fit is None:
                fit = calibrate(model, "sensor_offset", "force", [experiment], sc, max_starts=1)
            model.runs, model.rounds = {}, {}
            out.append((heldout_folds(model, fit, "force", [experiment], sc), dict(model.runs), dict(model.rounds)))
        finally:
            model.close()
    (one, runs1, rounds1), (four, runs4, rounds4) = out
    assert one == four and len(one) == 4
    assert runs1 == runs4 and rounds1["heldout"] == runs1["heldout"]
    assert rounds4["heldout"] < runs4["heldout"] / 2
