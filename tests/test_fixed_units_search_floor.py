"""``fixed:`` values written in the study's own unit, and the search's absolute floor on "the response
changed", on the real FMU."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from fmusa.study.loader import parse_study
from fmusa.api import run_study
from fmusa.pipeline.sweep import StudyRunner
from fmusa.study.plan import check_fmu

ROOT = Path(__file__).resolve().parents[1]
PAPER_TEXT = (ROOT / "studies" / "paper.yaml").read_text()


def _edit(text: str, old: str, new: str) -> str:
    assert text.count(old) == 1, old
    return text.replace(old, new)


def _grid_only(text: str) -> str:
    start, end = text.index("stages:"), text.index("execution:")
    return text[:start] + "stages:\n  grid:\n    values: {c: [2.0e5, 8.0e5, 3.0e6], d: [50, 500, 5000]}\n\n" + text[end:]


def test_fixed_values_in_other_units_give_the_same_runs(tmp_path, fmu_path):
    """F_max in kN, t_ramp in ms and eps_v_eq in mm/s, converted by scale: the FMU sees the SI values (up to
    the rounding of 1000 × 0.411, which the adaptive solver turns into ~1e-12 relative), so every metric
    equals the SI study's."""
    si = _grid_only(PAPER_TEXT)
    mm = _edit(si, "  F_max: 411 ", "  F_max: {value: 0.411, unit: kN, scale: 1000} ")
    mm = _edit(mm, "  t_ramp: 10 ", "  t_ramp: {value: 10000, unit: ms, scale: 1.0e-3} ")
    mm = _edit(mm, "  eps_v_eq: 5.0e-8 ", "  eps_v_eq: {value: 5.0e-5, unit: mm/s, scale: 1.0e-3} ")
    a = run_study(parse_study(si, tmp_path / "si.yaml"), tmp_path / "si", figures=False, progress=False).runs
    study = parse_study(mm, tmp_path / "mm.yaml")
    assert study.fixed_units["F_max"].unit == "kN"
    b = run_study(study, tmp_path / "mm", figures=False, progress=False).runs
    cols = ["c", "d", "max_y", "max_v", "t_eq", "feasible"]
    pd.testing.assert_frame_equal(a.sort_values(["c", "d"])[cols].reset_index(drop=True),
                                  b.sort_values(["c", "d"])[cols].reset_index(drop=True), check_exact=False,
                                  rtol=1e-9, atol=0)
    # the grid really depends on the converted values: a wrong factor changes max_y = F/c
    assert b["max_y"].max() > 1e-3
    wrong = _edit(mm, "scale: 1000} ", "scale: 100} ")
    c = run_study(parse_study(wrong, tmp_path / "wrong.yaml"), tmp_path / "wrong", figures=False,
                  progress=False).runs
    assert not (c.sort_values(["c", "d"])["max_y"].to_numpy() == b.sort_values(["c", "d"])["max_y"].to_numpy()).any()


def test_fixed_with_a_unit_is_checked_against_the_fmu(tmp_path, fmu_path):
    text = _edit(PAPER_TEXT, "  F_max: 411 ", "  F_mx: {value: 0.411, unit: kN, scale: 1000} ")
    study = parse_study(text, tmp_path / "bad.yaml")
    line = text[:text.index("  F_mx:")].count("\n") + 1
    errors = check_fmu(study, fmu_path)
    assert len(errors) == 1 and errors[0].startswith(f"{tmp_path / 'bad.yaml'}:{line}: fixed 'F_mx'"), errors
    assert "closest parameter names: F_max" in errors[0]
    with pytest.raises(ValueError, match="F_mx"):
        StudyRunner(study, tmp_path / "out", False, 1, None, progress=False)


def _v_end_search(atol: str) -> dict:
    """The paper's search with the final velocity v_y(12 s) among the response metrics. At rest it is 0 up
    to round-off (1e-19 ... 1e-150 here), so its relative change between levels is O(1) at every level."""
    text = _edit(PAPER_TEXT, "metrics:\n", "metrics:\n  v_end:\n    output: v_y\n    reduce: final\n    unit: m/s\n")
    text = _edit(text, "    max_outer: 20\n", "    max_outer: 20\n    response: [max_y, max_v, v_end]\n" + atol)
    text = text.replace("  regression:", "  regression_off:").split("  regression_off:")[0] + "\nexecution:\n  workers: 1\n"
    return parse_study(text, ROOT / "studies" / "v_end.yaml")


def test_without_a_floor_a_metric_at_round_off_counts_as_changed_at_every_level():
    """The analysis alone (no FMU): a response metric that is 0 up to round-off, as a final velocity at rest
    is in an FMU that integrates with a step-size control, differs relatively by O(1) between any two levels.
    Without a floor the search halves the outer parameter to max_outer; with one it stops."""
    from fmusa.analysis.roi import Region
    from fmusa.analysis.search import nested_binary_search

    rng = np.random.default_rng(5)

    def evaluate(p):     # feasible above c = 822000 at every d; v_end: round-off of random size and sign
        feasible = p["c"] >= 822000.0
        return {"c": p["c"], "d": p["d"], "status": "ok", "feasible": feasible, "ok_translation": feasible,
                "max_y": 411 / p["c"], "v_end": float(rng.choice([-1, 1]) * 10.0 ** rng.uniform(-150, -19))}

    region = Region("c", "d", (390625.0, 9765625.0), (0.0, 390625.0), "manual")
    r = nested_binary_search(evaluate, region, ["max_y", "v_end"], 1e-3, 1e-3, 20)
    assert r.stop_reason.startswith("reached max_outer = 20")
    assert all(lv.changed for lv in r.levels[1:])
    r = nested_binary_search(evaluate, region, ["max_y", "v_end"], 1e-3, 1e-3, 20, {"v_end": 5e-8})
    assert "absolute floor (v_end 5e-08)" in r.stop_reason and len(r.levels) == 3


def test_search_response_floor_lets_a_metric_at_zero_settle(tmp_path, fmu_path):
    # The FMU's exact axial solution (one step per load piece) ends at rest with v_y(12 s) = 0 exactly or
    # round-off below 1e-18: with the paper's eps_v_eq as the floor of v_end, the search stops once max_y
    # and max_v settle (the case without a floor is the test above: the FMU no longer produces it)
    study = _v_end_search("    response_atol: {v_end: 5.0e-8}\n")
    r = run_study(study, tmp_path / "floor", figures=False, progress=False)
    s = r.summary["search"]
    assert s["stop_reason"].startswith("the response (max_y, max_v, v_end) changed by less than 0.001")
    assert "absolute floor (v_end 5e-08)" in s["stop_reason"]
    assert [lv["changed"] for lv in s["levels"]][-2:] == [False, False]
    assert r.summary["optimum"]["c"] == pytest.approx(411 / 5e-4, rel=2e-3)
    assert r.summary["optimum"]["d"] == pytest.approx(390625 / 2 ** 3)
    # the floor is absolute: v_end stays below it between the last levels
    last = [lv["response"]["v_end"] for lv in s["levels"][-3:]]
    assert max(abs(x) for x in last) < 5e-8
