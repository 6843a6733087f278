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


# ------------------------------------------------------------------ diagnosis and sensitivity figures
def _synthetic_diagnosis(n_experiments: int, drive: str = "displacement"):
    """A diagnosis as fmusa.diagnose.run.diagnose returns it (its fits' predictions, the ranking, the
    thresholds), with friction-like experiments: enough for its figures, no FMU run."""
    from types import SimpleNamespace

    from fmusa.diagnose import measured as fm
    exps, base, ext = [], [], []
    for i in range(n_experiments):
        rate = (1.0, 10.0, 100.0)[i % 3]
        t = np.linspace(0.0, 2.0 / rate * 4, 150)
        y = 0.5e-3 * np.sin(np.pi * t * rate / 4) * (1 if i % 2 == 0 else -1)
        v = np.gradient(y, t)
        F = 4.0e5 * y + 20.0 * np.tanh(v / 1e-4) + np.random.default_rng(i).normal(0, 2.0, len(t))
        exps.append(fm.Experiment(name=f"H{i + 1} shear {rate:g} mm/s", path=f"synthetic/{i}.csv", drive=drive,
                                  t=t, displacement=y, force=F))
        base.append(4.0e5 * y)
        ext.append(4.0e5 * y + 19.0 * np.tanh(v / 1e-4))
    ranking = [{"effect": "coulomb_friction", "heldout_rmse_ratio": 0.12, "rmse_ratio": 0.11, "delta_bic": -812.0,
                "p_value": 1e-120, "significant": True},
               {"effect": "viscous_damping", "heldout_rmse_ratio": 0.7, "rmse_ratio": 0.66, "delta_bic": -95.0,
                "p_value": 1e-12, "significant": True},
               {"effect": "sensor_offset", "heldout_rmse_ratio": 0.98, "rmse_ratio": 0.97, "delta_bic": 3.2,
                "p_value": 0.4, "significant": False},
               {"effect": "bilinear_stiffness", "heldout_rmse_ratio": 1.02, "rmse_ratio": 0.99, "delta_bic": 6.0,
                "p_value": 0.8, "significant": False}]
    diag = {"data": {"drive": drive}, "effect": "coulomb_friction",
            "final": {"effects": ["coulomb_friction"], "model": "coulomb_friction"}, "ranking": ranking,
            "thresholds": {"delta_bic": -10.0, "heldout_ratio": 0.9, "p_value": 0.01},
            "_fits": {"none": SimpleNamespace(predictions=base), "coulomb_friction": SimpleNamespace(predictions=ext)}}
    return diag, exps


def _synthetic_sensitivity(n_metrics: int, n_params: int = 7) -> dict:
    """A sensitivity summary as run_sensitivity writes it (Morris and Sobol tables), no FMU run."""
    rng = np.random.default_rng(3)
    params = [f"p{k}" for k in range(n_params)]
    metrics = {f"out{m}": {"unit": ("m", "N", "m/s", "s")[m % 4], "description": f"output number {m}"}
               for m in range(n_metrics)}
    morris, sobol = {}, {}
    for m, metric in enumerate(metrics):
        scale = 10.0 ** (m - 3)
        mu = rng.uniform(0, 1, n_params) * scale
        morris[metric] = {p: {"mu_star": float(u), "sigma": float(u * rng.uniform(0.2, 1.2)),
                              "mu_star_conf": float(u * 0.2)} for p, u in zip(params, mu)}
        s1 = rng.dirichlet(np.ones(n_params)) * 0.9
        sobol[metric] = {p: {"S1": float(a), "S1_conf": 0.05, "ST": float(a * 1.1), "ST_conf": 0.06}
                         for p, a in zip(params, s1)}
    morris["out_flat"] = {p: {"mu_star": 0.0, "sigma": 0.0, "mu_star_conf": 0.0} for p in params}
    return {"morris": morris, "sobol": sobol, "samples": {"sobol": 64 * (n_params + 2)},
            "meta": {"metrics": {**metrics, "out_flat": {"unit": "m"}}, "n": 64, "morris_trajectories": 10,
                     "morris_levels": 4}}


def _draw_and_check(tmp_path, monkeypatch, diagnoses: tuple, outputs: tuple) -> dict:
    """Draw the diagnosis figures of ``diagnoses`` experiments and the sensitivity figures of ``outputs``
    outputs (each with one more that no input moves) under the check; {file name: size [in]} per drawing."""
    from fmusa.diagnose.figures import write_figures
    from fmusa.report.sensitivity_figures import plot_sensitivity

    log = tmp_path / "figures.jsonl"
    monkeypatch.setenv(ENV, str(log))
    for n in diagnoses:
        write_figures(*_synthetic_diagnosis(n), tmp_path / f"diag{n}")
    for n in outputs:
        plot_sensitivity(_synthetic_sensitivity(n), tmp_path / f"sens{n}" / "figures")
    entries = [json.loads(line) for line in log.read_text(encoding="utf-8").splitlines()]
    bad = {e["path"]: (e["size_in"], e["problems"]) for e in entries if e["problems"]}
    assert not bad, bad
    return {str(Path(e["path"]).relative_to(tmp_path)): e["size_in"] for e in entries}


def test_the_diagnosis_and_sensitivity_figures_pass_the_check(tmp_path, monkeypatch):
    """The diagnosis figures of more experiments than are drawn one per panel (the summary panel too) and
    the sensitivity figures of one output (and one no input moves) fit a page and pass the check; drawn from synthetic results,
    without an FMU."""
    sizes = _draw_and_check(tmp_path, monkeypatch, (6,), (1,))
    assert set(sizes) == {f"diag6/figures/{n}.png" for n in ("fit_time", "loops", "residuals", "ranking")} | \
        {f"sens1/figures/sensitivity_{m}.png" for m in ("morris", "sobol")}, sizes


@pytest.mark.slow
def test_one_experiment_and_many_outputs_fit_a_page(tmp_path, monkeypatch):
    """One experiment (one panel, drawn at a page's width), 7 outputs (4 rows of panels on one page), and 17 outputs: split into pages
    of at most 8 panels (name.png, name_2.png, …), each within 7.5 × 9.5 in."""
    sizes = _draw_and_check(tmp_path, monkeypatch, (1,), (7, 17))
    assert {f"sens17/figures/sensitivity_{m}{p}.png" for m in ("morris", "sobol") for p in ("", "_2", "_3")} \
        <= set(sizes), sizes
    assert all(w <= 7.5 and h <= 9.5 for w, h in sizes.values()), sizes
