"""Every figure fmusa writes is checked before it is saved (fmusa.figure_check through fmusa.files.save_figure):
axis labels with units, series a reader can tell apart, error bars inside the axes, nothing cut, a size that
fits a journal page. The checker is tested on figures made to fail it, then run on the figures of the paper's
study, a pullout and the shear data's figures."""
from __future__ import annotations

import json
import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
import pytest  # noqa: E402

from fmusa.figure_check import ENV, figure_problems  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def test_the_checker_finds_what_it_checks():
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot([1, 2], [3, 4], "o-", color="C0", label="H4 anterior")
    ax.plot([1, 2], [4, 5], "o-", color="C0", label="H9 anterior")       # the same colour and marker
    ax.errorbar([1.5], [4.0], yerr=[9.0], fmt="none")                    # leaves the axes
    ax.set_ylim(2, 6)
    ax.set_xlabel("shear rate")                                          # no unit
    ax.legend()
    problems = figure_problems(fig)
    plt.close(fig)
    assert any("x axis label 'shear rate' states no unit" in p for p in problems), problems
    assert any("the y axis has no label" in p for p in problems), problems
    assert any("'H4 anterior' and 'H9 anterior' are drawn alike" in p for p in problems), problems
    assert any("error bar leaves the axes" in p for p in problems), problems
    fig, ax = plt.subplots(figsize=(13.5, 5.6))
    ax.plot([1, 2], [1, 2])
    ax.set_xlabel("c [N/m]")
    ax.set_ylabel("max_y [m]")
    fig.text(0.99, 0.5, "a note far too long to fit on the right of this figure")
    problems = figure_problems(fig, tight=False)
    plt.close(fig)
    assert any("larger than a page" in p for p in problems) and any("cut by the figure's edge" in p for p in problems)
    fig, ax = plt.subplots(figsize=(6, 4))
    for i, (c, m) in enumerate(__import__("fmusa.report.figures", fromlist=["x"]).series_styles(12)):
        ax.plot([0, 1], [i, i + 1], marker=m, color=c, label=f"unit {i}")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("y [mm]")
    ax.legend()
    assert figure_problems(fig) == []
    plt.close(fig)


def _shear_table(units: int) -> pd.DataFrame:
    """A comparison table of ``units`` specimens × 2 directions × 3 rates, as the shear report draws it."""
    rows = []
    for s in range(1, units + 1):
        for d in ("Ant", "Pos"):
            for r in (1.0, 10.0, 100.0):
                k = 100.0 + 10 * s + r / 10
                rows.append({"specimen": f"H{s}", "direction": d, "rate_mm_s": r, "k1_N_mm": k / 2,
                             "stiffness_1": k / 2 * 1.01, "k2_N_mm": k, "stiffness_2": k * 0.99, "bp_mm": 0.5,
                             "breakpoint_mm": 0.51, "peak_load_N": 300.0, "peak_disp_mm": 300.0 / k * 1.2})
    return pd.DataFrame(rows)


def _problems(log: Path) -> tuple[set[str], dict]:
    entries = [json.loads(line) for line in log.read_text(encoding="utf-8").splitlines()]
    return ({Path(e["path"]).name for e in entries},
            {Path(e["path"]).name: e["problems"] for e in entries if e["problems"]})


#: a small generic study (no application block): grid heat maps, the search and its path, the regression
SMALL = """\
name: small
fmu: default
parameters:
  c: {variable: c_y, unit: N/m, description: Axial interface stiffness}
  d: {variable: d_y, unit: N·s/m, description: Axial interface damping}
fixed: {F_max: 411, t_ramp: 10}
scenario: {stop_time: 12}
metrics:
  max_y: {output: y_max, unit: m, description: Largest displacement}
  max_v: {output: v_y_max, unit: m/s}            # no description: captions say max_v, not 'max_v (max_v)'
constraints:
  - {name: translation, metric: max_y, max: 5.0e-4}
  - {name: velocity, metric: max_v, max: 5.0e-5}
stages:
  grid: {values: {c: [1.0e5, 1.0e6, 1.0e7], d: [100, 1.0e4]}}
  roi: {manual: {c: [1.0e5, 1.0e7], d: [100, 1.0e4]}}
  search: {inner: c, outer: d, inner_rtol: 5.0e-2, response_rtol: 5.0e-2, max_outer: 2}
"""


def test_the_figures_of_a_study_a_pullout_and_the_shear_data_pass_the_check(tmp_path, monkeypatch, fmu_path):
    """A small study (heat maps, search, search path), a pullout and the shear data's figures with 12
    specimens (more units than one colour cycle) pass the check."""
    import fmusa
    from fmusa.applications.shear_c67 import report as shear_report
    from fmusa.cli import main

    log = tmp_path / "figures.jsonl"
    monkeypatch.setenv(ENV, str(log))
    from fmusa.api import parse_study
    fmusa.run_study(parse_study(SMALL, tmp_path / "small.yaml"), tmp_path / "small", progress=False)
    assert main(["pullout", "--out", str(tmp_path / "pullout")]) == 0
    shear_report.write_figures({}, _shear_table(12), tmp_path / "shear")
    report = (tmp_path / "small" / "report.md").read_text(encoding="utf-8")
    assert "max_v" in report and not re.search(r"\b(\w+) \(\1\)", report), re.findall(r"\b(\w+) \(\1\)", report)
    names, bad = _problems(log)
    assert {"grid_max_y.png", "search_path.png", "search_max_y.png", "pullout.png", "rate_dependence.png",
            "bilinear_vs_authors.png"} <= names, names
    assert not bad, bad


@pytest.mark.slow
def test_every_figure_of_the_paper_study_passes_the_check(tmp_path, monkeypatch, fmu_path):
    """The paper's study with every figure (its application's too: time series, ramp time)."""
    import fmusa

    log = tmp_path / "figures.jsonl"
    monkeypatch.setenv(ENV, str(log))
    fmusa.run_study(fmusa.load_study(ROOT / "studies" / "paper.yaml"), tmp_path / "paper", progress=False)
    names, bad = _problems(log)
    assert {"grid_max_y.png", "search_path.png", "search_max_y.png", "optimum_time_series.png",
            "ramp_time.png"} <= names, names
    assert not bad, bad
