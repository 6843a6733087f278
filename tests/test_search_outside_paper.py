"""The region of interest and the search on problems unlike the paper's, each against its closed form.

One C FMU (tests/formula_fmu.py) holds four closed forms, constant in time:
- ``y_load = load`` at dplin >= 500, else ``0.01 load`` (feasible only at dplin = 1000 of the grid [10, 100,
  1000]; the region is found at roi.at, default the first grid value);
- ``y_p = 1000 / pP``, which pT does not move (an outer parameter with no effect);
- ``q = htc·air / (htc + air)``, rising in both (a heat exchanger: feasible only at the top of the range);
- ``y_k = 1 / k``, refused (fmi2Error) at k <= 0;
- ``y_cd = 1/c + 1/(1 + d)``: a paper-like boundary c(d), for the search in rounds and the regression.
"""
from __future__ import annotations

import json
import math

import pytest

from formula_fmu import build_formula_fmu
from fmusa.api import parse_study, run_study
from fmusa.study.schema import StudyError

PARAMS = {"k": 1.0, "dplin": 10.0, "load": 1.0, "pP": 1.0, "pT": 1.0, "htc": 100.0, "air": 100.0,
          "c": 1.0, "d": 1.0}
OUTPUTS = {"y_k": "1.0 / k", "y_load": "load * (dplin >= 500 ? 1.0 : 0.01)", "y_p": "1000.0 / pP",
           "q": "htc * air / (htc + air)", "y_cd": "1.0 / c + 1.0 / (1.0 + d)"}


@pytest.fixture(scope="module")
def fmu(tmp_path_factory):
    return build_formula_fmu(tmp_path_factory.mktemp("shapes"), "Shapes", PARAMS, OUTPUTS, refuse="k <= 0",
                             refuse_message="k must be > 0")


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("FMUSA_CACHE_DIR", str(tmp_path / "cache"))


def study(fmu, params: list[str], metric: str, constraint: str, stages: str):
    text = f"""\
name: shapes
fmu: {fmu}
parameters:
{"".join(f"  {p}: {{variable: {p}}}{chr(10)}" for p in params)}scenario: {{stop_time: 1, step: 0.5}}
metrics:
  {metric}: {{output: {metric}, reduce: final}}
constraints:
  - {constraint}
stages:
{stages}execution: {{workers: 1}}
"""
    return parse_study(text)


def sweep(s, tmp_path):
    run_study(s, tmp_path / "out", figures=False, progress=False)
    return json.loads((tmp_path / "out" / "summary.json").read_text())


def test_region_found_at_roi_at_and_the_message_names_the_feasible_points(fmu, tmp_path):
    stages = ("  grid: {values: {dplin: [10, 100, 1000], load: [1, 2, 4, 8, 16]}}\n  roi:\n"
              "  search: {inner: load, inner_rtol: 1.0e-3}\n")
    with pytest.raises(StudyError) as err:
        sweep(study(fmu, ["dplin", "load"], "y_load", "{name: enough, metric: y_load, min: 5}", stages), tmp_path)
    msg = str(err.value)
    assert "2 of the 15 grid points meet every constraint" in msg and "dplin = 1000: 2" in msg
    assert "roi: {at: {dplin: 1000}}" in msg
    at = stages.replace("  roi:\n", "  roi: {at: {dplin: 1000}}\n")
    s = sweep(study(fmu, ["dplin", "load"], "y_load", "{name: enough, metric: y_load, min: 5}", at),
              tmp_path / "at")
    assert s["optimum"]["load"] == pytest.approx(5.0, rel=1.1e-3) and s["optimum"]["load"] >= 5.0
    with pytest.raises(StudyError, match="not one of its grid values"):
        study(fmu, ["dplin", "load"], "y_load", "{name: enough, metric: y_load, min: 5}",
              at.replace("dplin: 1000}", "dplin: 500}"))


def test_optimum_names_a_parameter_that_moves_no_constraint(fmu, tmp_path):
    stages = ("  grid: {values: {pP: [10, 50, 200, 800], pT: [1, 2.5, 5, 10]}}\n  roi:\n"
              "  search: {inner: pP, outer: pT, inner_rtol: 1.0e-3}\n")
    s = sweep(study(fmu, ["pP", "pT"], "y_p", "{name: cap, metric: y_p, max: 10}", stages), tmp_path)
    assert s["optimum"]["pP"] == pytest.approx(100.0, rel=1.1e-3)
    assert list(s["optimum_free"]) == ["pT"] and "moves none of the constrained metrics" in s["optimum_free"]["pT"]


def test_an_optimum_at_the_top_of_the_range_says_so(fmu, tmp_path):
    """q = htc·air/(htc + air) >= 80 needs both large: on the grid htc = 100 at air = 400, htc = 200 at
    air = 200, none at air = 100. The region is htc in [50, 100] (the grid bracket), air in [200, 400]; at
    air = 400 the boundary is htc = 80·400/320 = 100, the region's top, and the first halving (air = 200
    needs htc >= 133) has none: the optimum is the corner of the range, and says so."""
    stages = ("  grid: {values: {htc: [50, 100, 200], air: [100, 200, 400]}}\n  roi:\n"
              "  search: {inner: htc, outer: air, inner_rtol: 1.0e-3}\n")
    s = sweep(study(fmu, ["htc", "air"], "q", "{name: duty, metric: q, min: 80}", stages), tmp_path)
    assert s["optimum"] == {"htc": 100.0, "air": 400.0}
    notes = " ".join(s["optimum_at_edge"])
    assert "htc = 100 is the top of the range searched" in notes and "widen the grid of htc above 100" in notes
    assert "air = 400 is the top of the range searched" in notes and "first level" in notes


def test_a_bound_at_zero_gets_an_absolute_floor(fmu, tmp_path):
    """1/k <= 1 holds at every grid k: the region is [0, 10] by rule 1; the search starts at the floor
    inner_rtol × 10 = 0.01 (never at 0, which the FMU refuses) and lands on k = 1."""
    stages = "  grid: {values: {k: [10, 100, 1000]}}\n  roi:\n  search: {inner: k, inner_rtol: 1.0e-3}\n"
    s = sweep(study(fmu, ["k"], "y_k", "{name: cap, metric: y_k, max: 1}", stages), tmp_path)
    assert s["roi"]["k"] == [pytest.approx(0.01), 10.0]
    assert 1.0 <= s["optimum"]["k"] <= 1.0 + 1.1e-3
    assert s["stage_runs"]["search"]["asked"] < 30 and s["failed"] == 0
    assert not math.isclose(s["optimum"]["k"], 0.0, abs_tol=1e-6)


def test_regression_levels_are_the_search_path(fmu, tmp_path):
    """A search in rounds of 4 also asks for levels past its stop; the regression by the outer parameter fits
    the levels on the search's path only."""
    stages = ("  grid: {values: {c: [1, 4, 16, 64], d: [1, 4, 16, 64]}}\n  roi:\n"
              "  search: {inner: c, outer: d, inner_rtol: 1.0e-3, parallel: 4}\n"
              "  regression: {x: c, y: [y_cd], by: d, degree: 1}\n")
    s = sweep(study(fmu, ["c", "d"], "y_cd", "{name: cap, metric: y_cd, max: 0.5}", stages), tmp_path)
    path = {f"{lv['outer']:.10g}" for lv in s["search"]["levels"]}
    assert s["search"]["parallel"]["speculative_runs"] > 0
    assert set(s["regression"]["y_cd"]) <= path, (set(s["regression"]["y_cd"]), path)
