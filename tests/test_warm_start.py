"""The warm-started nested search (search.warm_start): the same optimum as the paper's search, within
inner_rtol, in far fewer FMU runs; first on a closed-form boundary, then on the paper's study."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

from fmusa.analysis.roi import Region
from fmusa.analysis.search import nested_binary_search
from fmusa.pipeline.sweep import run_study
from fmusa.study.loader import load_study

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "studies" / "paper.yaml"
#: the default (paper-faithful) search of studies/paper.yaml: its optimum and FMU runs
PAPER_C, PAPER_D, PAPER_SEARCH_RUNS = 822067.2607421875, 381.4697265625, 225
REGION = Region("c", "d", (390625.0, 9765625.0), (0.0, 390625.0), "manual")


def boundary(d: float) -> float:
    """Smallest feasible c at damping d: grows with d, flat (8e5) below d ~ 1e4."""
    return 8e5 * (1.0 + (d / 2e5) ** 2)


def model(notch: bool = False):
    """evaluate() of a closed-form study: feasible iff c >= boundary(d) (``notch``: and, for d < 5000, where
    the boundary no longer moves, not within (1.1, 1.2)·boundary: a non-monotone boundary); y = 411 / c."""
    calls: list[dict] = []

    def evaluate(p: dict[str, float]) -> dict:
        calls.append(dict(p))
        c, b = p["c"], boundary(p.get("d", 0.0))
        ok = c >= b and not (notch and p.get("d", 0.0) < 5000 and 1.1 * b < c < 1.2 * b)
        return {**p, "y": 411.0 / c, "ok_size": ok, "feasible": ok, "status": "ok"}
    evaluate.calls = calls
    return evaluate


def test_warm_start_reaches_the_default_optimum_in_fewer_runs():
    cold_ev, warm_ev = model(), model()
    cold = nested_binary_search(cold_ev, REGION, ["y"], 1e-3, 1e-3, 20)
    warm = nested_binary_search(warm_ev, REGION, ["y"], 1e-3, 1e-3, 20, warm_start=True)
    assert warm.optimum["d"] == cold.optimum["d"]
    assert abs(warm.optimum["c"] - cold.optimum["c"]) <= 1e-3 * cold.optimum["c"]
    assert boundary(warm.optimum["d"]) <= warm.optimum["c"] <= boundary(warm.optimum["d"]) * (1 + 1e-3)
    assert cold.evaluations == len(cold_ev.calls) and warm.evaluations == len(warm_ev.calls)
    assert warm.evaluations < 0.6 * cold.evaluations         # 93 against 168: the boundary moves at 7 levels
    assert warm.warm_start and not cold.warm_start and warm.warnings == [] == cold.warnings
    assert warm.binding == ["size"] and warm.stop_reason == cold.stop_reason
    # levels whose boundary did not move cost 2 runs; the guard runs once, at the end (3 runs)
    assert min(lv.evaluations for lv in warm.levels[1:]) == 2
    assert warm.evaluations == sum(lv.evaluations for lv in warm.levels) + 3


def test_warm_start_checks_monotonicity_once_at_the_answer():
    cold = nested_binary_search(model(notch=True), REGION, ["y"], 1e-3, 1e-3, 20)
    warm = nested_binary_search(model(notch=True), REGION, ["y"], 1e-3, 1e-3, 20, warm_start=True)
    assert len(cold.warnings) == sum(lv.outer < 5000 for lv in cold.levels) >= 2   # every level is guarded
    assert len(warm.warnings) == 1 and "not monotone" in warm.warnings[0]
    assert f"d = {warm.optimum['d']:g}" in warm.warnings[0]


def test_one_parameter_search_is_one_bisection():
    region = Region("c", None, (390625.0, 9765625.0), None, "manual")
    ev = model()
    res = nested_binary_search(ev, region, ["y"], 1e-3)
    assert set(res.optimum) == {"c"} and res.outer is None
    assert 8e5 <= res.optimum["c"] <= 8e5 * (1 + 1e-3)
    assert len(res.levels) == 1 and res.levels[0].outer is None and res.levels[0].changed is None
    assert all(set(p) == {"c"} for p in ev.calls) and res.evaluations == len(ev.calls) == 19
    assert "one parameter" in res.stop_reason and res.binding == ["size"]
    none = nested_binary_search(ev, Region("c", None, (1e5, 5e5), None, "manual"), ["y"])
    assert none.optimum is None and "no feasible c" in none.stop_reason


def test_paper_study_warm_start(tmp_path, fmu_path):
    """studies/paper.yaml's stages with search.warm_start: the default search's optimum within inner_rtol,
    at most 80 search runs (225 without)."""
    study = load_study(PAPER)
    stage = study.stages["search"]
    assert stage.warm_start is False                   # the paper-faithful search stays the default
    study = dataclasses.replace(study, stages={**study.stages,
                                               "search": dataclasses.replace(stage, warm_start=True)})
    result = run_study(study, tmp_path, progress=False)
    s = json.loads((tmp_path / "summary.json").read_text())
    c, d = s["optimum"]["c"], s["optimum"]["d"]
    assert abs(c - PAPER_C) <= stage.inner_rtol * PAPER_C
    assert d == PAPER_D                                # the same level of the halving of d
    runs = s["stage_runs"]["search"]
    assert runs["simulated"] <= runs["asked"] == result.search.evaluations <= 80
    assert s["search"]["warm_start"] is True and s["search"]["warnings"] == []
    assert s["binding_constraint"] == ["translation", "velocity"]
    assert c >= 411 / 5e-4                            # feasible side of max(y) = F / c <= eps_y
