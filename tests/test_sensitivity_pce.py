"""Sensitivity from a surrogate (method pce) and what the indices do not know, on an FMU of test functions
whose Sobol indices have closed forms (tests/fmus/testfunc: Ishigami, Sobol's G, a linear sum), built here
with gcc and run through the real fmpy. The studies are written as a user writes them."""
from __future__ import annotations

import json
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from fmusa.pipeline.sensitivity import run_sensitivity
from fmusa.study.loader import parse_study
from testfunc_fmu import build_testfunc, g_indices, ishigami_indices, study_text

PI = float(np.pi)


@pytest.fixture(scope="module")
def fmu(tmp_path_factory):
    return build_testfunc(tmp_path_factory.mktemp("testfunc"))


def _run(fmu, tmp_path, output, k, lo, hi, methods, extra="", fixed=None, resume=False, name="s"):
    text = study_text(fmu, output, k, lo, hi, methods, extra, fixed)
    study = parse_study(text, tmp_path / f"{name}.yaml")
    runner = SimpleNamespace(evaluator=SimpleNamespace(workers=1, scheduler=None), simulated=0)
    res = run_sensitivity(study, study.stages["sensitivity"], tmp_path / name, runner, progress=False,
                          resume=resume, accuracy_samples=0)
    return res, runner


def _err(table, s1, st, names):
    return max(max(abs(table[n]["S1"] - a), abs(table[n]["ST"] - b)) for n, a, b in zip(names, s1, st))


def test_pce_on_ishigami_is_within_001_of_the_closed_form_in_at_most_150_runs_and_resumes(fmu, tmp_path):
    res, runner = _run(fmu, tmp_path, "ishigami", 3, -PI, PI, "[pce]", "    pce: {max_runs: 150, batch: 32}")
    s = res["summary"]
    S1, ST = ishigami_indices()
    val = s["pce_validation"]
    assert val["reached"] and val["metrics"]["y"]["trusted"] and val["metrics"]["y"]["loo_error"] <= 1e-3
    assert val["runs"] <= 150 and s["samples"]["pce"] == val["runs"] == s["runs"] == s["simulated"] == runner.simulated
    assert _err(s["pce"]["y"], S1, ST, ["x1", "x2", "x3"]) < 0.01
    assert all(d["ST_lo"] <= d["ST"] <= d["ST_hi"] for d in s["pce"]["y"].values())
    # the runs are the design: Ishigami of the stored inputs, computed here, is the stored output
    runs = pd.read_csv(tmp_path / "s" / "sensitivity_runs.csv")
    x1, x2, x3 = (runs[f"x{i}"].to_numpy() for i in (1, 2, 3))
    np.testing.assert_allclose(runs["y"], np.sin(x1) + 7 * np.sin(x2) ** 2 + 0.1 * x3 ** 4 * np.sin(x1),
                               rtol=1e-12, atol=1e-12)
    assert len(runs) == val["runs"] and (runs["stage"] == "pce").all()
    # the validation points: leave-one-out predictions of every run
    pts = pd.read_csv(tmp_path / "s" / "sensitivity_pce_validation.csv")
    assert len(pts) == val["runs"]
    # resumed: the same rounds, nothing simulated, the same indices
    res2, runner2 = _run(fmu, tmp_path, "ishigami", 3, -PI, PI, "[pce]", "    pce: {max_runs: 150, batch: 32}",
                         resume=True)
    assert res2["summary"]["simulated"] == 0 and runner2.simulated == 0
    assert res2["summary"]["pce"] == s["pce"]


@pytest.mark.slow   # about 20 s of expansion fits (a minute on a loaded machine): make slow
def test_pce_on_a_smooth_g_function_is_within_001_and_on_a_kinked_one_warns(fmu, tmp_path):
    smooth = (4.5, 9.0, 99.0, 99.0)
    fixed = {f"a{i + 1}": a for i, a in enumerate(smooth)}
    res, _ = _run(fmu, tmp_path, "gfun", 4, 0.0, 1.0, "[pce]", "    pce: {max_runs: 150, target_error: 0.003, batch: 50}",
                  fixed, name="smooth")
    s = res["summary"]
    S1, ST = g_indices(smooth)
    assert s["pce_validation"]["runs"] <= 150 and s["pce_validation"]["metrics"]["y"]["trusted"]
    assert _err(s["pce"]["y"], S1, ST, ["x1", "x2", "x3", "x4"]) < 0.01
    assert not any("cannot be trusted" in m for m in s["messages"])

    kinked = (0.0, 0.5, 3.0, 9.0, 99.0, 99.0)
    fixed = {f"a{i + 1}": a for i, a in enumerate(kinked)}
    res, _ = _run(fmu, tmp_path, "gfun", 6, 0.0, 1.0, "[pce]", "    pce: {max_runs: 150, target_error: 0.003, batch: 50}",
                  fixed, name="kinked")
    s = res["summary"]
    v = s["pce_validation"]
    assert v["runs"] == 150 and not v["reached"] and not v["metrics"]["y"]["trusted"]
    assert v["metrics"]["y"]["loo_error"] > 0.003
    msg = next(m for m in s["messages"] if "cannot be trusted" in m)
    assert "use method sobol" in msg and "kink" in msg
    S1, ST = g_indices(kinked)    # the warning is deserved: the indices are off by more than 0.01
    assert _err(s["pce"]["y"], S1, ST, [f"x{i}" for i in range(1, 7)]) > 0.01


def test_pce_with_normal_truncnormal_and_lognormal_inputs(fmu, tmp_path):
    # linear = x1 + 2 x2 + 3 x3: Var = var1 + 4 var2 + 9 var3, S1 = ST = c_i² var_i / Var
    text = study_text(fmu, "linear", 3, 0.0, 1.0, "[pce]", "    pce: {max_runs: 200, target_error: 0.0001}")
    text = text.replace("      x1: {variable: x1, bounds: [0.0, 1.0]}",
                        "      x1: {variable: x1, distribution: normal, mean: 1.0, std: 0.3}")
    text = text.replace("      x2: {variable: x2, bounds: [0.0, 1.0]}",
                        "      x2: {variable: x2, distribution: truncnormal, mean: 0.0, std: 1.0, bounds: [-0.5, 2.0]}")
    text = text.replace("      x3: {variable: x3, bounds: [0.0, 1.0]}",
                        "      x3: {variable: x3, distribution: lognormal, mean: 0.5, std: 0.1}")
    study = parse_study(text, tmp_path / "lin.yaml")
    runner = SimpleNamespace(evaluator=SimpleNamespace(workers=1, scheduler=None), simulated=0)
    res = run_sensitivity(study, study.stages["sensitivity"], tmp_path / "lin", runner, progress=False,
                          resume=False, accuracy_samples=0)
    s = res["summary"]
    tn = stats.truncnorm(-0.5, 2.0)
    var = np.array([0.3 ** 2, 4 * tn.var(), 9 * 0.1 ** 2])
    S = var / var.sum()
    assert _err(s["pce"]["y"], S, S, ["x1", "x2", "x3"]) < 0.01
    # the FMU got values of the named distributions (a test that does not share the sampling code)
    runs = pd.read_csv(tmp_path / "lin" / "sensitivity_runs.csv")
    assert stats.kstest(runs["x1"], stats.norm(1.0, 0.3).cdf).pvalue > 0.01
    assert stats.kstest(runs["x2"], tn.cdf).pvalue > 0.01 and runs["x2"].between(-0.5, 2.0).all()
    s2 = np.log1p((0.1 / 0.5) ** 2)
    assert stats.kstest(runs["x3"], stats.lognorm(np.sqrt(s2), scale=0.5 * np.exp(-s2 / 2)).cdf).pvalue > 0.01


def test_statements_unresolved_order_and_morris_sobol_disagreement_on_ishigami(fmu, tmp_path):
    # Known: ST(x1) = 0.558 > ST(x2) = 0.442, while Morris' μ* of x2 is exactly 7.875 (every step of sin² at
    # the 4 levels changes it by 0.75·7 over 2/3 of the range) and μ* of x1 averages 7.70: Morris ranks x2
    # first, Sobol x1. At n = 64 Saltelli's intervals of ST(x1) and ST(x2) overlap; the chaos' do not.
    res, _ = _run(fmu, tmp_path, "ishigami", 3, -PI, PI, "[morris, sobol, pce]",
                  "    n: 64\n    morris_trajectories: 20\n    pce: {max_runs: 150, batch: 32}")
    s = res["summary"]
    sob, mor, pce = s["sobol"]["y"], s["morris"]["y"], s["pce"]["y"]
    assert sob["x1"]["ST"] - sob["x1"]["ST_conf"] <= sob["x2"]["ST"] + sob["x2"]["ST_conf"]
    st = s["statements"]
    assert any("the order of x1 and x2 is not resolved at n = 64" in t for t in st["sobol"]["y"])
    assert "pce" not in st or not any("x1 and x2" in t for t in st["pce"].get("y", []))
    assert mor["x2"]["mu_star"] == pytest.approx(7 * 0.75 / (2 / 3)) and mor["x2"]["mu_star"] > mor["x1"]["mu_star"]
    assert pce["x1"]["ST"] > pce["x2"]["ST"]
    dis = st["morris-vs-pce"]["y"]
    assert any("Morris ranks x2 above x1 (μ*)" in t and "ranks x1 above x2" in t for t in dis)
    # every table has its intervals
    assert all(set(d) >= {"ST", "ST_conf"} for d in sob.values())
    assert all(set(d) >= {"ST_lo", "ST_hi", "S1_lo", "S1_hi"} for d in pce.values())
    table = pd.read_csv(tmp_path / "s" / "sensitivity_pce.csv")
    assert {"S1_lo", "S1_hi", "ST_lo", "ST_hi"} <= set(table.columns)


def test_a_tiny_or_odd_n_from_the_api_is_said_in_the_studys_words_and_gives_no_impossible_index(fmu, tmp_path):
    text = study_text(fmu, "ishigami", 3, -PI, PI, "[sobol]", "    n: 64")
    study = parse_study(text, tmp_path / "i.yaml")
    import dataclasses
    for n, words in ((1, "below the smallest useful n for 3 inputs (64)"), (96, "n = 96 is not a power of 2")):
        stage = dataclasses.replace(study.stages["sensitivity"], n=n)
        runner = SimpleNamespace(evaluator=SimpleNamespace(workers=1, scheduler=None), simulated=0)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = run_sensitivity(study, stage, tmp_path / f"n{n}", runner, progress=False, resume=False,
                                  accuracy_samples=0)
        assert not [w for w in caught if "SALib" in str(w.filename) or "scipy" in str(w.filename)], \
            [f"{w.filename}: {w.message}" for w in caught]
        s = res["summary"]
        assert any(words in m for m in s["messages"]), s["messages"]
        for d in s["sobol"]["y"].values():
            for k in ("S1", "ST"):
                if d[k] is not None:     # an index is in [0, 1] within its interval, or not reported
                    assert -d[f"{k}_conf"] - 1e-9 <= d[k] <= 1 + d[f"{k}_conf"] + 1e-9
        json.dumps(s, default=str)


@pytest.mark.slow   # 16-dimensional expansions: minutes on a loaded machine (make slow; make bench runs all outputs)
def test_pce_on_the_six_dof_study_agrees_with_saltelli_at_n_4096_for_three_outputs(fmu_path, tmp_path):
    # The cheap version of `make bench`'s check (all 7 outputs, <= 400 runs): the three outputs one input
    # owns, all 16 inputs, <= 160 runs, against the recorded Saltelli reference (N = 4096, 73,728 runs).
    import dataclasses
    from fmusa.study.loader import load_study
    from fmusa.study.schema import PCEOptions
    ref = json.loads((Path(__file__).parent / "data" / "six_dof_saltelli_4096.json").read_text())
    study = dataclasses.replace(load_study(Path(__file__).parents[1] / "studies" / "six_dof.yaml"), fmu=fmu_path)
    outputs = ["x_final", "z_final", "gamma_final"]
    stage = dataclasses.replace(study.stages["sensitivity"], methods=["pce"], outputs=outputs,
                                pce=PCEOptions(max_runs=160, batch=64, target_error=1e-3))
    runner = SimpleNamespace(evaluator=SimpleNamespace(workers=2, scheduler=None), simulated=0)
    res = run_sensitivity(study, stage, tmp_path, runner, progress=False, resume=False, accuracy_samples=0)
    s = res["summary"]
    assert s["pce_validation"]["runs"] <= 160 and all(v["trusted"] for v in s["pce_validation"]["metrics"].values())
    worst = max(abs(s["pce"][m][p]["ST"] - ref["sobol"][m][p]["ST"]) for m in outputs for p in s["pce"][m])
    assert worst <= 0.02, worst
