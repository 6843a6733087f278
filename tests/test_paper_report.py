"""`make sweep` after the refactor: the paper's study gives the same optimum, region, section headings and
figures as before it (tests/data/paper_report_baseline.json, recorded by `make sweep` on commit 3365d44), and
every number of the paper's own sections is still computed (none typed in), now from the paper extension's
runs rather than by the report."""
from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from fmusa.api import load_study, run_study

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "studies" / "paper.yaml"
BASELINE = json.loads((ROOT / "tests" / "data" / "paper_report_baseline.json").read_text())


@pytest.fixture(scope="module")
def sweep(tmp_path_factory, fmu_path):
    """What `make sweep` does: `fmusa sweep studies/paper.yaml --out out/paper`."""
    out = tmp_path_factory.mktemp("sweep") / "paper"
    result = run_study(load_study(PAPER), out, figures=True, progress=False)
    summary = json.loads((out / "summary.json").read_text())
    return result, summary, (out / "report.md").read_text(encoding="utf-8")


def test_same_optimum_and_region(sweep):
    _, s, _ = sweep
    assert s["optimum"] == BASELINE["optimum"]
    assert {k: s["roi"][k] for k in BASELINE["roi"]} == BASELINE["roi"]
    assert s["binding_constraint"] == BASELINE["binding_constraint"]
    assert s["paper_roi_search"]["optimum"] == BASELINE["paper_roi_optimum"]
    assert s["runs"] == BASELINE["runs"]


def test_same_section_headings_and_figures(sweep):
    _, s, text = sweep
    headings = [line for line in text.splitlines() if line.startswith("#")]
    assert headings == BASELINE["headings"]
    assert s["figures"] == BASELINE["figures"]
    refs = re.findall(r"!\[[^\]]*\]\(([^)\s]+)\)", text)
    assert sorted(set(refs)) == sorted(BASELINE["figures"])


def test_the_paper_sections_are_computed_from_runs(sweep):
    result, _, text = sweep
    paper = result.extra["paper"]
    ph = paper["physics"]
    assert ph.runs > 500 and f"({ph.runs} extra runs in all)" in text
    # the ramp that reproduces the paper's t_eq = 0.07674 s, found by bisection on the FMU
    Tq = ph.checks["T_for_t_eq"]
    assert 0.03 < Tq < 0.1 and f"t_ramp = {Tq * 1e3:.4g} ms (bisection on the FMU)" in text
    assert ph.checks["at_T_for_t_eq"]["t_eq"] == pytest.approx(0.07674, rel=1e-3)
    # the velocity threshold at the paper's optimum is met from t_ramp = F/(c·eps_v) on
    assert ph.checks["T_for_eps_v"] == pytest.approx(411 / (823224 * 5e-5), rel=1e-3)
    # the smallest feasible c over the ramp time follows the quasi-static max(F/eps_y, F/(eps_v·t_ramp))
    for row in ph.ramp_curve:
        bound = max(411 / 5e-4, 411 / (5e-5 * row["t_ramp"]))
        assert row["c_min"] == pytest.approx(bound, rel=1e-2), row      # dynamic overshoot for short ramps
    ts = paper["time_series"]
    assert {"y", "v_y", "F_pull"} <= set(ts["df"].columns) and ts["zoom"] is not None


def test_the_report_runs_no_fmu(sweep, monkeypatch, tmp_path):
    """Rendering the finished result again writes the same report without opening any FMU."""
    from fmusa.api import write_report
    from fmusa.fmi import runner as runner_mod

    result, _, text = sweep

    def refuse(*args, **kwargs):
        raise AssertionError("the report opened an FMU")

    monkeypatch.setattr(runner_mod.FMURunner, "__init__", refuse)
    result.out = tmp_path
    write_report(result)
    again = (tmp_path / "report.md").read_text(encoding="utf-8")
    assert [l for l in again.splitlines() if l.startswith("#")] == BASELINE["headings"]
    assert again.replace(str(tmp_path), "OUT") == text.replace(str(tmp_path), "OUT")
