"""A one-parameter study (grid → roi → search over one parameter) on an FMU that is not ours, against its
closed-form answer; and a regression without a search stage, which fits the grid runs.

The FMU is tests/fmus/me_spring/spring.c (co-simulation, its own RK4), built by gcc in the test: a mass on
a spring-damper, m y'' + d y' + c y = F(t), under a force ramped to F_max in t_ramp = 0.1 ms, i.e. a step
(the ramp lowers the peak by ~(ω t_ramp)²/24 ≈ 2e-7, relative). The study varies the damping d alone
(c = 400 N/m, m = 1 kg, F_max = 10 N) and bounds the peak displacement by 10 % overshoot:
max y <= 1.1 F/c. The step response of the underdamped oscillator peaks at

    max y = F/c · (1 + exp(-π ζ / sqrt(1 - ζ²))),   ζ = d / (2 sqrt(c m)),

which decreases in d, so the smallest feasible damping is where the overshoot is 0.1:

    ζ* = -ln 0.1 / sqrt(π² + ln² 0.1) = 0.59116,   d* = 2 ζ* sqrt(c m) = 23.6462 N·s/m.

Outputs are sampled every 1 ms: the sampled peak is low by at most |y''| Δt²/8 ≈ 1.3e-7 m, which moves d*
by ~1e-5 (relative), far inside the search's inner_rtol = 1e-3.
"""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import pandas as pd
import pytest

from fmusa.pipeline.sweep import run_study
from fmusa.study.loader import parse_study

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fmus.me_spring.build import build_spring_fmu  # noqa: E402

C, M, F_MAX = 400.0, 1.0, 10.0
OVERSHOOT = 0.1
Y_MAX = (1 + OVERSHOOT) * F_MAX / C
GRID_D = [2.0, 8.0, 32.0, 128.0]


def zeta_for_overshoot(os_: float) -> float:
    ln = math.log(os_)
    return -ln / math.sqrt(math.pi ** 2 + ln ** 2)


D_STAR = 2 * zeta_for_overshoot(OVERSHOOT) * math.sqrt(C * M)


def peak(d: float) -> float:
    """Closed-form max y of the underdamped step response."""
    z = d / (2 * math.sqrt(C * M))
    return F_MAX / C * (1 + math.exp(-math.pi * z / math.sqrt(1 - z * z)))


def study_text(fmu: Path, stages: str) -> str:
    return f"""\
name: overshoot
description: One parameter, the damping of a spring-mass under a step force; max y <= 1.1 F/c.
fmu: {fmu}
parameters:
  d: {{variable: d, unit: N·s/m}}
fixed: {{c: {C}, m: {M}, F_max: {F_MAX}, t_ramp: 1.0e-4}}
scenario: {{stop_time: 2, step: 1.0e-3}}
metrics:
  max_y: {{output: y, reduce: max, unit: m}}
constraints:
  - {{name: overshoot, metric: max_y, max: {Y_MAX!r}}}
stages:
{stages}execution: {{workers: 1}}
"""


@pytest.fixture(scope="module")
def spring_fmu(tmp_path_factory) -> Path:
    return build_spring_fmu(tmp_path_factory.mktemp("spring_1d"), "SpringCS", ("co-simulation",))


def test_one_parameter_study_lands_on_the_closed_form(spring_fmu, tmp_path):
    stages = (f"  grid: {{values: {{d: {GRID_D}}}}}\n"
              f"  roi:\n"
              f"  search: {{inner: d, inner_rtol: 1.0e-3}}\n")
    study = parse_study(study_text(spring_fmu, stages), tmp_path / "overshoot.yaml")
    assert study.stages["search"].outer is None
    t0 = time.perf_counter()
    result = run_study(study, tmp_path / "out", progress=False)
    wall = time.perf_counter() - t0
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    # roi, rule 1 alone: the grid neighbours that bracket the smallest feasible grid d (32 > d* > 8)
    assert s["roi"] == {"d": [8.0, 32.0], "source": "automatic", "notes": []}
    assert set(s["optimum"]) == {"d"}
    # the grid's own findings: feasible count and the smallest feasible grid d (the closed form decides)
    grid_feasible = [x for x in GRID_D if x >= 2 * math.sqrt(C * M) or peak(x) <= 1.1 * F_MAX / C]
    assert s["grid"]["feasible"] == len(grid_feasible) and s["grid"]["failed"] == 0
    assert s["grid"]["best"]["d"] == min(grid_feasible) == 32.0
    d = s["optimum"]["d"]
    assert D_STAR <= d <= D_STAR * (1 + 1e-3), (d, D_STAR)            # the feasible side, within inner_rtol
    assert s["search"]["outer"] is None and len(s["search"]["levels"]) == 1
    assert s["search"]["levels"][0]["outer"] is None and s["search"]["warnings"] == []
    assert s["binding_constraint"] == ["overshoot"]
    assert s["stage_runs"]["search"]["asked"] == result.search.evaluations <= 16
    # every run agrees with the closed-form peak; the last infeasible run lies just below d*
    runs = pd.read_csv(tmp_path / "out" / "runs.csv")
    assert (runs["status"] == "ok").all()
    for row in runs.itertuples():
        if row.d < 2 * math.sqrt(C * M):         # underdamped: the closed-form peak
            assert row.max_y == pytest.approx(peak(row.d), rel=2e-5), row.d
        else:                                    # overdamped: creeps up to F/c, not reached by t = 2 s
            assert row.max_y <= F_MAX / C
    below = runs.loc[~runs["feasible"].astype(bool), "d"].max()
    assert D_STAR * (1 - 1e-3) <= below < D_STAR
    print(f"one-parameter study: d = {d:.6g} vs closed form {D_STAR:.6g} (rel. {(d - D_STAR) / D_STAR:.2e}), "
          f"{len(runs)} runs, {wall:.2f} s")


def test_regression_without_search_fits_the_grid(spring_fmu, tmp_path):
    stages = (f"  grid: {{values: {{d: {GRID_D}}}}}\n"
              f"  regression: {{x: d, y: [max_y], degree: 2}}\n")
    study = parse_study(study_text(spring_fmu, stages), tmp_path / "fit.yaml")
    assert study.stages["regression"].source == "grid"
    run_study(study, tmp_path / "out", progress=False)
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert s["regression_source"] == "grid"
    fit = s["regression"]["max_y"]["all"]
    assert fit["n"] == len(GRID_D) and len(fit["coefficients"]) == 3 and fit["r2"] > 0.5
    assert fit["x_range"] == [min(GRID_D), max(GRID_D)]
