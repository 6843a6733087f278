"""`make diagnose`: the diagnosis of the real C6/C7 shear tests and its comparison with the authors.

The spinal unit is seen as one bushing along the shear axis: the FMU's axial degree of freedom (y) is
the anteroposterior shear displacement, driven by the measured disp_x, and the model predicts Fx. Per
specimen and direction the three rates (1, 10, 100 mm/s) are diagnosed jointly, so the held-out score
is the prediction of a whole rate from the other two. Per test, the two-phase elastic model
(``nonlinear_stiffness``: stiffness c_y up to the breakpoint, nl_ratio*c_y past it) is fitted alone and
compared with the authors' own breakpoint analysis in test_info.csv.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pandas as pd

from fmusa.diagnose import run as dg
from fmusa.applications.shear_c67 import data as shear_c67


def fit_bilinear_per_test(tests: pd.DataFrame, fmu: str, max_points: int) -> pd.DataFrame:
    """Our two-phase elastic fit of every test, in the authors' units and frame (raw displacement)."""
    rows = []
    # the fitted names do not depend on the data: one extracted FMU per model for all tests
    model = dg.ModelRunner(fmu, "displacement", ["c_y", "d_y", "nl_ratio", "nl_y_b"])
    base = dg.ModelRunner(fmu, "displacement", ["c_y", "d_y"])
    try:
        for _, row in tests.iterrows():
            rows.append(_bilinear_row(row, model, base, max_points))
    finally:
        model.close()
        base.close()
    return pd.DataFrame(rows)


def _bilinear_row(row, model: dg.ModelRunner, base: dg.ModelRunner, max_points: int) -> dict:
    exp = shear_c67.load_test(row, max_points=max_points)
    sc = dg.data_scales([exp])
    fit = dg.calibrate(model, "nonlinear_stiffness", "displacement", [exp], sc, max_starts=6)
    lin = dg.calibrate(base, "none", "displacement", [exp], sc)
    sign = 1.0 if row["direction"] == "Ant" else -1.0
    x0 = float(exp.meta.get("zero_shift", 0.0))
    c1 = fit.params["c_y"] / 1000.0
    return {"specimen": row["specimen"], "direction": row["direction"], "rate_mm_s": row["rate_mm_s"],
            "k1_N_mm": c1, "k2_N_mm": c1 * fit.params["nl_ratio"],
            "bp_mm": 1000.0 * (x0 + sign * fit.params["nl_y_b"]),
            "k1_ci": [v / 1000.0 for v in fit.ci95["c_y"]],
            "rmse_N": fit.rmse, "linear_rmse_N": lin.rmse, "linear_k_N_mm": lin.params["c_y"] / 1000.0,
            "peak_N": float(np.max(np.abs(exp.force))), "points": len(exp.t)}


def rate_dependence(exps, fmu: str, diag: dict) -> dict:
    """Does a Maxwell branch on top of the two-phase curve predict a held-out rate better?

    The single-effect ranking tests the Maxwell branch on a straight line, where the bend of the curve
    dominates the residuals; here it is added to the two-phase elastic model, and each rate is
    predicted by the fit to the other two (leave one rate out)."""
    two = diag["_fits"].get("nonlinear_stiffness") or dg.fit_candidate(fmu, "nonlinear_stiffness",
                                                                        "displacement", exps)
    both = dg.fit_candidate(fmu, "nonlinear_stiffness+viscoelastic_relaxation", "displacement", exps)
    return {"two_phase": {"rmse": two.rmse, "heldout_rmse": two.heldout_rmse, "bic": two.bic},
            "two_phase_maxwell": {"rmse": both.rmse, "heldout_rmse": both.heldout_rmse, "bic": both.bic,
                                  "ve_k_N_mm": both.params["ve_k"] / 1000.0, "ve_tau_s": both.params["ve_tau"],
                                  "c_N_mm": both.params["c_y"] / 1000.0},
            "heldout_ratio": both.heldout_rmse / two.heldout_rmse, "delta_bic": both.bic - two.bic}


def run_shear_diagnosis(out_dir: str | os.PathLike, root=None, fmu_path=None, max_points: int = 300,
                        workers: int | None = None, max_starts: int = 6) -> dict:
    """Diagnose every specimen and direction (three rates jointly), fit the per-test bilinear model,
    compare with the authors, and write out_dir/summary.json, out_dir/report.md and figures."""
    from fmusa.fmi.info import default_fmu_path

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fmu = str(fmu_path or default_fmu_path())
    tests = shear_c67.list_tests(root)
    authors = shear_c67.authors_bilinear(root)
    groups, unit_exps = {}, {}
    for (spec, direction), g in tests.groupby(["specimen", "direction"], sort=False):
        key = f"{spec}_{direction}"
        unit_exps[key] = exps = [shear_c67.load_test(r, max_points=max_points) for _, r in g.iterrows()]
        print(f"{spec} {direction}: {len(exps)} tests", flush=True)
        groups[key] = dg.run_diagnosis(exps, "displacement", out / key, fmu_path=fmu, workers=workers,
                                       max_starts=max_starts)
    rate_models = {}
    for key, diag in groups.items():
        print(f"{key}: rate dependence on top of the two-phase curve", flush=True)
        rate_models[key] = rate_dependence(unit_exps[key], fmu, diag)
    ours = fit_bilinear_per_test(tests, fmu, max_points)
    cmp_ = ours.merge(authors, on=["specimen", "direction", "rate_mm_s"], how="left")
    summary = summarize(groups, cmp_)
    summary["rate_models"] = rate_models
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=_json_default))
    cmp_.drop(columns=["k1_ci"]).to_csv(out / "bilinear_comparison.csv", index=False)
    from fmusa.applications.shear_c67 import report as shear_report
    figs = shear_report.write_figures(summary, cmp_, out)
    shear_report.write_report(summary, cmp_, groups, out, figs)
    return summary


def _json_default(x):
    if isinstance(x, (np.floating,)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    if isinstance(x, Path):
        return str(x)
    raise TypeError(type(x))


def summarize(groups: dict, cmp_: pd.DataFrame) -> dict:
    """The numbers the report states: effects per group, our vs the authors' bilinear, rate trends."""
    eff = {k: {"effect": d["effect"], "indistinguishable": [t["effect"] for t in d["indistinguishable"]],
               "gain": d["gain"], "effect_params": d["effect_params"],
               "baseline_c_N_mm": d["baseline"]["params"]["c_y"] / 1000.0,
               "ranking": [{k2: r[k2] for k2 in ("effect", "significant", "heldout_rmse_ratio", "delta_bic",
                                                  "rmse_ratio")} for r in d["ranking"]],
               "leftover": d["leftover"]}
           for k, d in groups.items()}
    dk1 = (cmp_["k1_N_mm"] - cmp_["stiffness_1"]) / cmp_["stiffness_1"]
    dk2 = (cmp_["k2_N_mm"] - cmp_["stiffness_2"]) / cmp_["stiffness_2"]
    dbp = cmp_["bp_mm"] - cmp_["breakpoint_mm"]
    rate = []
    for (spec, direction), g in cmp_.groupby(["specimen", "direction"]):
        g = g.sort_values("rate_mm_s")
        lo, hi = g.iloc[0], g.iloc[-1]
        rate.append({"specimen": spec, "direction": direction,
                     "k2_ratio_100_1_ours": hi["k2_N_mm"] / lo["k2_N_mm"],
                     "k2_ratio_100_1_authors": hi["stiffness_2"] / lo["stiffness_2"],
                     "peak_ratio_100_1": hi["peak_load_N"] / lo["peak_load_N"],
                     "linear_k_ratio_100_1": hi["linear_k_N_mm"] / lo["linear_k_N_mm"]})
    by_rate = {}
    for r_mm_s, g in cmp_.groupby("rate_mm_s"):
        by_rate[f"{r_mm_s:g}"] = {
            "k1_rel_diff_median": float(np.nanmedian(np.abs((g["k1_N_mm"] - g["stiffness_1"]) / g["stiffness_1"]))),
            "k2_rel_diff_median": float(np.nanmedian(np.abs((g["k2_N_mm"] - g["stiffness_2"]) / g["stiffness_2"]))),
            "breakpoint_abs_diff_median_mm": float(np.nanmedian(np.abs(g["bp_mm"] - g["breakpoint_mm"]))),
            "points_median": float(np.median(g["points"]))}
    return {"groups": eff, "bilinear_by_rate": by_rate,
            "bilinear": {"k1_rel_diff_median": float(np.nanmedian(np.abs(dk1))),
                         "k2_rel_diff_median": float(np.nanmedian(np.abs(dk2))),
                         "breakpoint_abs_diff_median_mm": float(np.nanmedian(np.abs(dbp)))},
            "rate": rate}
