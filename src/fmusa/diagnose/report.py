"""report.md of ``fmusa diagnose``: the data, the named effect and why, parameters, ranking, residuals, caveats.

It takes the dict returned by :func:`fmusa.diagnose.run.diagnose` (with its in-memory fits, key ``_fits``),
the experiments it was computed from and the figures :func:`fmusa.diagnose.figures.write_figures` drew.
Every number is read from the dict or computed from the predictions it holds; nothing here runs the FMU.

Units are the ones a reader of a mechanical test expects: displacement in mm, force in N, time in s,
stiffness in N/mm, damping in N·s/mm. Residuals are model − measured, in the response channel: N when the
test imposed the displacement, mm when it imposed the force. A rotational interface (``data.motion``) reads
angle in deg, torque in N·m, stiffness in N·m/rad, damping in N·m·s/rad (:mod:`fmusa.diagnose.motion`).

    from fmusa.diagnose.run import diagnose
    from fmusa.diagnose.figures import write_figures
    from fmusa.diagnose.report import write_report
    diag = diagnose(experiments, "displacement")
    write_report(diag, experiments, out, write_figures(diag, experiments, out))
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from fmusa.diagnose.effects import BASELINE, EFFECT_MEANING, PARAM_MEANING, STIFFNESS, in_motion
from fmusa.diagnose.runs_report import budget_notice, runs_section
from fmusa.diagnose.views import (by_loading_direction, delta_text, experiment_motion, final_label, final_name,
                                  final_residuals, natural, p_text, ratio_text, residual_series, response_channel,
                                  structure_text, channel_units)
from fmusa.diagnose import motion as mo
from fmusa.format import fmt, md_code, md_text
from fmusa.files import atomic_write

__all__ = ["write_report", "EFFECT_MEANING", "PARAM_MEANING", "CAPTIONS"]


def _table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    """A markdown table (pipes in cells escaped)."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(str(x).replace("|", "\\|") for x in r) + " |")
    return "\n".join(lines)


# ============================================================================ report
CAPTIONS = {
    "fit_time.png": "Measured response against time for each experiment (grey points) with the calibrated "
                    "baseline (dashed) and the final model (solid: the baseline with every effect of the chain); each panel's title gives both RMSEs.",
    "loops.png": "Force against displacement: the measured points and the loops the baseline and the final model trace. A loop "
                 "in the data that the baseline's line does not open is hysteresis (friction, viscosity, yield).",
    "residuals.png": "Residuals (model − measured) of the baseline (top) and of the final model (bottom) "
                     "against time, displacement, velocity and loading direction; black: binned means ± sd. "
                     "A binned mean that follows an axis is an effect of that quantity the model lacks.",
    "ranking.png": "Every candidate against the baseline: held-out and fitted RMSE ratios, ΔBIC and the p of "
                   "the nested F test, with the significance thresholds (dashed purple); the named effect "
                   "in red (★), other significant candidates in orange.",
}


def _ci(name: str, value: float, ci) -> str:
    v, u = natural(name, value)
    s = fmt(v, 4)
    if ci is not None and len(ci) == 2:
        lo, hi = natural(name, ci[0])[0], natural(name, ci[1])[0]
        s += f" [{fmt(lo, 3)}, {fmt(hi, 3)}]"
    return s


def fmu_name(diag: Mapping, name: str) -> str:
    """The FMU variable a fitted parameter is, as the user's FMU names it (``element.NAME`` for a parameter of the
    attached interface element); the catalogue's name where the diagnosis has no mapping."""
    model = diag.get("model") or {}
    var = (model.get("variables") or {}).get(name, name)
    return f"element.{var}" if (model.get("where") or {}).get(name) == "element" else var


def _summary_params(summary: Mapping) -> tuple[dict, dict]:
    return dict(summary.get("params") or {}), dict(summary.get("ci95") or {})


def _data_section(diag: Mapping, experiments: Sequence) -> str:
    data = diag["data"]
    resp, unit, f = response_channel(diag)
    cu = channel_units(diag)
    rows = []
    for e, de in zip(experiments, data.get("experiments") or [{}] * len(experiments)):
        t = np.asarray(e.t, float)
        v = np.gradient(np.asarray(e.displacement, float), t) if len(t) > 1 else np.zeros(1)
        src = e.meta.get("downsampled_from") if isinstance(e.meta, Mapping) else None
        pts = f"{e.n}" + (f" (block means of {src} rows)" if src else "")
        meta = e.meta if isinstance(e.meta, Mapping) else {}
        cols = ", ".join(md_text(c) for c in (meta.get("columns") or {}).values() if c)   # the file's text
        dialect = (f"; delimiter {md_code(meta['delimiter'])}, decimal {md_code(meta['decimal'])}"
                   if meta.get("delimiter") else "")
        rows.append([md_text(e.name), md_code(e.path) + (f" (columns {cols}{dialect})" if cols else ""), pts,
                     fmt(e.duration, 4),
                     fmt(float(np.max(np.abs(e.displacement))) * cu["displacement"][1]),
                     fmt(float(np.max(np.abs(e.force))) * cu["force"][1]),
                     fmt(float(np.max(np.abs(v))) * cu["velocity"][1])])
    out = "## Data\n\n"
    out += (f"{len(experiments)} experiment{'s, fitted jointly' if len(experiments) != 1 else ''}; "
            f"the test imposed the **{mo.channel_word(data['drive'])}**, the model is driven by it and predicts the "
            f"**{mo.channel_word(data['response'])}** ({unit}). {data['points']} points in all.\n\n")
    if mo.current() == mo.ROTATION:
        out += ("The interface is rotational: the angle is stored in rad and the torque in N·m (diagnosis.json), "
                "shown here in deg and N·m; stiffnesses in N·m/rad, dampings in N·m·s/rad.\n\n")
    out += _table(["experiment", "file", "points", "duration [s]",
                   f"peak |{mo.channel_word('displacement')}| [{cu['displacement'][0]}]",
                   f"peak |{mo.channel_word('force')}| [{cu['force'][0]}]",
                   f"peak |{mo.channel_word('velocity')}| [{cu['velocity'][0]}]"], rows) + "\n\n"
    out += (f"Held-out error: {data.get('heldout', '–')}. Each fold is left out, the model is refitted on the "
            f"rest, and the refit predicts the left-out points; the held-out RMSE pools the squared errors "
            f"of all folds.\n")
    return out


def _named_text(diag: Mapping) -> str:
    """The named effect: what it means, its gain over the baseline and its main parameter."""
    eff, gain = diag["effect"], diag.get("gain") or {}
    resp, unit, f = response_channel(diag)
    base, ext = diag.get("baseline") or {}, diag.get("extended") or {}
    motion = mo.motion_of(diag)
    meaning = " — or, the same equations, ".join(in_motion(EFFECT_MEANING.get(m, ""), motion) for m in eff.split(" ≡ "))
    out = (f"**Effect: `{eff}`**: {meaning}.\n\n"
           f"Adding it to the baseline lowers the RMSE of the {resp} on the fitted data from "
           f"{fmt(base.get('rmse', float('nan')) * f)} {unit} to {fmt(ext.get('rmse', float('nan')) * f)} "
           f"{unit} (ratio {ratio_text(gain.get('rmse_ratio'))}) and on held-out data from "
           f"{fmt(base.get('heldout_rmse', float('nan')) * f)} {unit} to "
           f"{fmt(ext.get('heldout_rmse', float('nan')) * f)} {unit} "
           f"(ratio {ratio_text(gain.get('heldout_rmse_ratio'))}); ΔAIC = {delta_text(gain.get('delta_aic'))}, "
           f"ΔBIC = {delta_text(gain.get('delta_bic'))}, p = {p_text(gain.get('p_value'))} (F test of the extra "
           f"parameters).\n\n")
    mp = diag.get("main_parameter")
    ep = diag.get("effect_params") or {}
    if mp and mp in ep:
        v, u = natural(mp, ep[mp]["value"])
        lo, hi = (natural(mp, c)[0] for c in ep[mp]["ci95"])
        out += (f"Main parameter: {fmu_name(diag, mp)} ({in_motion(PARAM_MEANING.get(mp, ''), motion)}) = {fmt(v, 4)} {u} "
                f"(95 % interval {fmt(lo)} to {fmt(hi)} {u}).\n\n")
    return out


def _none_text(diag: Mapping) -> str:
    """No effect named: whether the baseline suffices, the best candidate's numbers, the baseline's RMSE."""
    resp, unit, f = response_channel(diag)
    base = diag.get("baseline") or {}
    ranking = diag.get("ranking") or []
    base_st = (diag.get("residuals") or {}).get("baseline") or {}
    th = diag.get("thresholds") or {}
    small = [r for r in ranking if r.get("statistically_significant") and not r.get("significant")]
    if small:
        def one(r):
            es = r["effect_size"]
            return (f"`{r['effect']}` changes the prediction by {fmt(es['size'] * f)} {unit} (on at least "
                    f"{th.get('effect_points', 3)} samples), below the floor of {fmt(es['floor'] * f)} {unit}")
        out = ("**Effect: `none`**: what the candidates add is too small to matter. Passing the statistical "
               "tests is not enough: " + "; ".join(one(r) for r in small)
               + f" (the larger of {fmt(th.get('effect_noise', 3))} × the noise and "
                 f"{fmt(100 * th.get('effect_range', 0.01))} % of the measured range of the {resp}), so "
               + ("it does not matter physically and is not named" if len(small) == 1 else
                  "they do not matter physically and are not named") + ".\n\n")
    elif base_st.get("structured"):
        out = ("**Effect: `none`**: no candidate's gain passes all three tests. This does not mean the "
               "baseline explains the data: its residuals are structured (see below), but no single "
               "candidate effect removes that structure convincingly enough on held-out data.\n\n")
    else:
        out = (f"**Effect: `none`**: {in_motion(EFFECT_MEANING['none'], mo.motion_of(diag))}; "
               "no candidate's gain passes all three tests.\n\n")
    if ranking:
        crit = ranking[0]
        out += (f"The best-ranked candidate, `{crit['effect']}`, reaches an RMSE ratio of "
                f"{ratio_text(crit.get('rmse_ratio'))} on the fitted data and "
                f"{ratio_text(crit.get('heldout_rmse_ratio'))} on held-out data, "
                f"ΔAIC = {delta_text(crit.get('delta_aic'))}, ΔBIC = {delta_text(crit.get('delta_bic'))}, "
                f"p = {p_text(crit.get('p_value'))}.\n\n")
    return out + (f"The baseline's RMSE is {fmt(base.get('rmse', float('nan')) * f)} {unit} on the fitted data "
                  f"and {fmt(base.get('heldout_rmse', float('nan')) * f)} {unit} on held-out data.\n\n")


def _criteria_text(eff: str, crit: Mapping, th: Mapping, unit: str = "N", f: float = 1.0) -> str:
    """The three significance tests and the effect size of the named (or best-ranked) candidate, and the
    tie margins."""
    checks = [
        ("held-out RMSE ratio", ratio_text(crit.get("heldout_rmse_ratio")), f"< {fmt(th['heldout_ratio'])}",
         crit.get("heldout_rmse_ratio", float("nan")) < th["heldout_ratio"]),
        ("ΔBIC", delta_text(crit.get("delta_bic")), f"< {fmt(th['delta_bic'])}",
         crit.get("delta_bic", float("nan")) < th["delta_bic"]),
        ("p (nested F test)", p_text(crit.get("p_value")), f"< {fmt(th['p_value'])}",
         crit.get("p_value", float("nan")) < th["p_value"]),
    ]
    size = crit.get("effect_size") or {}
    if size:
        checks.append((f"change of the prediction (on ≥ {th.get('effect_points', 3)} samples) [{unit}]",
                       fmt(size.get("size", float("nan")) * f),
                       f"> {fmt(size.get('floor', float('nan')) * f)} (the larger of {fmt(th.get('effect_noise'))} × "
                       f"noise {fmt(size.get('noise', float('nan')) * f)} and {fmt(100 * th.get('effect_range', 0))} % "
                       f"of the range {fmt(size.get('response_range', float('nan')) * f)})",
                       bool(size.get("matters"))))
    who = f"`{eff}`" if eff != "none" else f"`{crit.get('effect', '–')}` (best-ranked)"
    out = (f"An effect is named only when its gain is significant on all three statistical counts and it "
           f"matters: the extended model must change the prediction by more than the noise and a physical "
           f"floor somewhere on the data; for {who}:\n\n")
    out += _table(["criterion", "value", "required", "met"],
                  [[a, b, c, "yes" if d else "no"] for a, b, c, d in checks]) + "\n\n"
    return out + (f"ΔAIC = {delta_text(crit.get('delta_aic'))} is reported for comparison; it does not decide. "
                  f"A candidate counts as indistinguishable from the winner when it is significant too, its "
                  f"held-out RMSE is within a factor {fmt(th.get('tie_heldout'))} of the winner's and its BIC "
                  f"within {fmt(th.get('tie_bic'))}.\n")


def _verdict_section(diag: Mapping) -> str:
    eff = diag["effect"]
    th = diag.get("thresholds") or {}
    ranking = diag.get("ranking") or []
    if eff != "none":
        row = next((r for r in ranking if r["effect"] == diag.get("lead")), {})
        out, crit = _named_text(diag), {**(diag.get("gain") or {}), "effect_size": row.get("effect_size")}
    else:
        out, crit = _none_text(diag), (ranking[0] if ranking else {})
    out = "## The effect\n\n" + out
    _, unit, f = response_channel(diag)
    return out + _criteria_text(eff, crit, th, unit, f) if th and crit else out


def _final_summary(diag: Mapping) -> dict:
    """The final model's parameters and intervals (the chain's last step, else the named effect's)."""
    final = diag.get("final") or {}
    if final.get("params"):
        return {"params": {n: v["value"] for n, v in final["params"].items()},
                "ci95": {n: v["ci95"] for n, v in final["params"].items()},
                "intervals": final.get("intervals") or {}, "gauss_newton": final.get("gauss_newton") or {}}
    ext = dict(diag.get("extended") or {})
    if ext:
        ext["gauss_newton"] = (ext.get("intervals") or {}).get("gauss_newton") or {}
        return ext
    return dict(diag.get("extended") or {})


def _params_section(diag: Mapping) -> str:
    base_p, base_ci = _summary_params(diag.get("baseline") or {})
    ext_p, ext_ci = _summary_params(_final_summary(diag))
    names = list(base_p) + [n for n in ext_p if n not in base_p]
    rows = []
    for n in names:
        unit = natural(n, 0.0)[1] or "–"
        b = _ci(n, base_p[n], base_ci.get(n)) if n in base_p else "–"
        x = _ci(n, ext_p[n], ext_ci.get(n)) if n in ext_p else "–"
        rows.append([f"`{fmu_name(diag, n)}`", in_motion(PARAM_MEANING.get(n, ""), mo.motion_of(diag)),
                     unit, b, x])
    eff = diag["effect"]
    out = "## Parameters\n\n"
    shown = (("baseline", diag.get("baseline") or {}),) + ((("final model", _final_summary(diag)),)
                                                          if diag["effect"] != "none" else ())
    how = "; ".join(f"{label}: {_interval_method(s)}" for label, s in shown)
    out += (f"Values with their 95 % confidence intervals in brackets ({how}; see the caveats). "
            f"Final model: {final_label(diag)}" if eff != "none" else
            f"Values with their 95 % confidence intervals in brackets ({how}; see the caveats). "
            "No effect is named, so the final model is the baseline")
    out += ".\n\n" + _table(["parameter", "meaning", "unit", "baseline", "final model"], rows) + "\n"
    gn = (_final_summary(diag).get("gauss_newton") or {})
    if gn and "sandwich" in _interval_method(_final_summary(diag)):
        out += ("\nThe Gauss–Newton intervals of the final model, which assume white residuals and are too narrow "
                "here: " + ", ".join(f"`{fmu_name(diag, n)}` {_ci(n, ext_p[n], v)}" for n, v in gn.items() if n in ext_p)
                + ".\n")
    return out


def _interval_method(summary: Mapping) -> str:
    """How a fit's intervals were made, in words (with φ and the effective sample size of the residuals)."""
    iv = summary.get("intervals") or {}
    m = iv.get("method")
    if not m:
        return "Gauss–Newton covariance"
    if "sandwich" in m:
        return (f"{m}, lag-1 autocorrelation φ = {iv.get('phi_used', float('nan')):.2f}, about "
                f"{max(iv.get('n_eff', float('nan')), 1):.0f} effective samples")
    return m


def _change_text(r: Mapping, f: float) -> str:
    """A ranking row's effect size against its floor."""
    es = r.get("effect_size") or {}
    if not es:
        return "–"
    return f"{fmt(es.get('size', float('nan')) * f)} ({fmt(es.get('floor', float('nan')) * f)})"


def _screened_text(row: Mapping, diag: Mapping) -> str:
    """Why a candidate was kept from being named by the checks: the protocol cannot identify it, or a parameter
    the tests cannot support (" (…)"; empty when neither)."""
    why = (["the protocol cannot identify it"] if row.get("unidentifiable") else []) + \
          [f"`{fmu_name(diag, b['parameter'])}` beyond the test" for b in row.get("implausible") or []]
    return f" ({'; '.join(why)})" if why else ""


def _ranking_section(diag: Mapping) -> str:
    resp, unit, f = response_channel(diag)
    rows = []
    for i, r in enumerate(diag.get("ranking") or [], 1):
        eparams = [(k, v) for k, v in (r.get("params") or {}).items() if k not in BASELINE]
        ptxt = ", ".join(f"{fmu_name(diag, k)} = {fmt(natural(k, v)[0])}{(' ' + natural(k, v)[1]) if natural(k, v)[1] else ''}"
                         for k, v in eparams) or "–"
        rows.append([i, f"`{r['effect']}`" + (" ★" if r["effect"] in diag["effect"].split(" ≡ ") else ""),
                     "yes" if r.get("significant") else "no" + _screened_text(r, diag), r.get("k", "–"),
                     fmt(r.get("rmse", float("nan")) * f), fmt(r.get("heldout_rmse", float("nan")) * f),
                     ratio_text(r.get("rmse_ratio")), ratio_text(r.get("heldout_rmse_ratio")),
                     delta_text(r.get("delta_aic")), delta_text(r.get("delta_bic")), p_text(r.get("p_value")), ptxt,
                     _change_text(r, f)])
    out = "## Ranking\n\n"
    out += ("Every candidate fitted as the baseline plus that one effect, best first (significant candidates "
            "first, then by held-out RMSE). Ratios and differences are against the baseline "
            f"(RMSE {fmt((diag.get('baseline') or {}).get('rmse', float('nan')) * f)} {unit}, held-out "
            f"{fmt((diag.get('baseline') or {}).get('heldout_rmse', float('nan')) * f)} {unit}); "
            "k counts the fitted parameters; ★ marks the named effect. The change of the prediction is how "
            "much the candidate moves the prediction away from the baseline's (on at least "
            f"{(diag.get('thresholds') or {}).get('effect_points', 3)} samples), against the floor it must exceed "
            "to matter.\n\n")
    out += _table(["#", "candidate", "significant", "k", f"RMSE [{unit}]", f"held-out RMSE [{unit}]",
                   "RMSE ratio", "held-out ratio", "ΔAIC", "ΔBIC", "p", "effect parameters",
                   f"change of the prediction [{unit}] (floor)"], rows) + "\n"
    refitted = diag.get("refitted") or {}
    for name, note in refitted.items():
        out += f"`{name}`: {note['text']}.\n\n"
    failed = diag.get("failed") or {}
    if failed:
        out += ("Candidates that could not be fitted (not ranked, so the verdict is among the others):\n\n"
                + "".join(f"- `{n}`: {why}\n" for n, why in failed.items()) + "\n")
    return out


def _residual_statistics(cols: list, unit: str, f: float) -> list[list]:
    """One table row per statistic of the residual tests, one column per model."""
    def g(st, k):
        return (st or {}).get(k, float("nan"))

    def row(label, fn):
        return [label] + [fn(st) for _, st in cols]
    return [
        row(f"rms [{unit}]", lambda st: fmt(g(st, "rms") * f)),
        row(f"mean [{unit}]", lambda st: fmt(g(st, "mean") * f)),
        row(f"rms of the white part [{unit}]", lambda st: fmt(g(st, "noise_rms") * f)),
        row("lag-1 autocorrelation", lambda st: f"{g(st, 'lag1_autocorrelation'):.3f}"),
        row("Ljung–Box Q (df), p", lambda st: f"{fmt(g(st, 'ljung_box_q'))} ({g(st, 'ljung_box_df')}), "
                                              f"p = {p_text(g(st, 'ljung_box_p'))}"),
        row("runs test z, p", lambda st: f"{g(st, 'runs_z'):.2f}, p = {p_text(g(st, 'runs_p'))}"),
        row("spectral line p", lambda st: p_text(((st or {}).get("p_values") or {}).get("oscillation", float("nan")))),
        row("drift p", lambda st: p_text(((st or {}).get("p_values") or {}).get("drift", float("nan")))),
        row("structured", lambda st: "yes" if (st or {}).get("structured") else "no"),
    ]


def _direction_text(diag: Mapping, experiments: Sequence, unit: str, f: float) -> str:
    """The residual by loading direction of the baseline and the extended model ('' without predictions)."""
    eff = final_name(diag)
    motion = experiment_motion(diag, experiments)
    drows = []
    for key, label in [("none", "baseline")] + ([(eff, f"final ({final_label(diag)})")] if eff != "none" else []):
        r = residual_series(diag, experiments, key)
        if r is None:
            continue
        d = by_loading_direction(experiments, motion, r)
        drows.append([label] + [f"{fmt(d[k]['mean'] * f)} ± {fmt(d[k]['rms'] * f)} (n = {d[k]['count']})"
                                for k in ("loading", "hold", "unloading")])
    if not drows:
        return ""
    return (f"\nResidual by loading direction, mean ± rms [{unit}] (loading: moving away from zero in the "
            "direction the test was loaded; hold: speed below 2 % of the experiment's peak; tests loaded in "
            "the negative direction enter with their residual's sign flipped, so that effects odd in the "
            "motion add up across directions). A mean that flips sign between loading and "
            "unloading is hysteresis the model lacks; a mean in the holds is relaxation or creep.\n\n"
            + _table(["model", "loading", "hold", "unloading"], drows) + "\n")


def _leftover_text(diag: Mapping, unit: str, f: float) -> str:
    """What is left in the residuals of the final model, and what it may be."""
    eff = diag["effect"]
    st = final_residuals(diag)
    model = f"final model ({final_label(diag)})" if eff != "none" else "baseline"
    if not (diag.get("leftover") or (st and st.get("structured"))):
        return f"Nothing: the residuals of the {model} pass all four tests as white noise.\n"
    out = f"Structure remains in the residuals of the {model}: {structure_text(st, unit, f).removeprefix('structured: ')}."
    osc, drift = (st or {}).get("oscillation"), (st or {}).get("drift")
    axis = (st or {}).get("axis") or {}
    if osc and axis.get("derived_time"):
        out += (f" The waviness (p = {p_text(osc.get('p_value'))}) is not part of any candidate. The test's time "
                f"axis was derived from a nominal rate, so it was searched along the {axis.get('name')}, and it is "
                f"a feature of the {axis.get('name')} (a periodic roughness, a thread or a lead screw), not a "
                "frequency: nothing here says how fast the rig moved.")
    elif osc:
        out += (f" The oscillation (p = {p_text(osc.get('p_value'))}) is not part of any candidate: a resonance of "
                "the test rig or a periodic disturbance.")
    if drift:
        out += (f" The drift (p = {p_text(drift.get('p_value'))}) may be a sensor drift, temperature, or a slow "
                "effect none of the candidates has.")
    if not osc and not drift:
        out += (" It is neither an oscillation (none recurs over three periods or more) nor a drift: a "
                "systematic error the candidates do not describe, or a further effect.")
    return out + "\n"


def _residual_section(diag: Mapping, experiments: Sequence) -> str:
    resp, unit, f = response_channel(diag)
    res = diag.get("residuals") or {}
    eff = diag["effect"]
    cols = [("baseline", res.get("baseline"))]
    if eff != "none":
        cols.append((f"final ({final_label(diag)})", final_residuals(diag)))
    alpha = (cols[0][1] or {}).get("alpha", float("nan"))
    out = "## Residuals before and after\n\n"
    out += (f"Residual = model − measured {resp}. Four tests tell structure from white noise, each at "
            f"α/4 = {fmt(alpha / 4 if math.isfinite(alpha) else float('nan'))} (α = {fmt(alpha)} overall): "
            "Ljung–Box (autocorrelation), the runs test on the signs (z < 0: long stretches on one side), a "
            "spectral line and a linear drift. Several experiments are tested each on its own and pooled.\n\n")
    out += _table(["statistic"] + [c for c, _ in cols], _residual_statistics(cols, unit, f)) + "\n\n"
    for label, st in cols:
        out += f"- {label}: {structure_text(st, unit, f)}.\n"
    out += _direction_text(diag, experiments, unit, f)
    return out + "\n### What is left\n\n" + _leftover_text(diag, unit, f)


def _ties_section(diag: Mapping) -> str:
    ties = diag.get("indistinguishable") or []
    out = "## Candidates the data cannot tell apart\n\n"
    if not ties:
        if diag["effect"] == "none":
            return out + "None: no candidate is significant.\n"
        return out + (f"None: no other significant candidate comes close to `{diag['effect']}` on held-out error "
                      "and BIC.\n")
    out += (f"These candidates explain the data about as well as `{diag['effect']}`; the data cannot decide "
            "between them. The test that would:\n\n")
    ranking = {r["effect"]: r for r in diag.get("ranking") or []}
    for t in ties:
        r = ranking.get(t["effect"], {})
        out += (f"- `{t['effect']}` (held-out ratio {ratio_text(r.get('heldout_rmse_ratio'))}, ΔBIC "
                f"{delta_text(r.get('delta_bic'))}): {t['separating_test']}.")
        if t.get("reason", "").startswith("cannot tell"):
            out += f" {t['reason'][0].upper()}{t['reason'][1:]}."
        g = (diag.get("group") or {}).get(t["effect"]) or {}
        if g.get("mapped_from"):
            own = g.get("own") or {}
            _, unit, f = response_channel(diag)
            out += (f" Scored as one model with `{g['mapped_from']}`: its parameters are the ones of "
                    f"`{g['mapped_from']}`'s better fit, mapped; in each held-out fold the refit with the lower "
                    f"training cost counts for both (its own optimiser reached RMSE "
                    f"{fmt(own.get('rmse', float('nan')) * f)} {unit}, held-out "
                    f"{fmt(own.get('heldout_rmse', float('nan')) * f)} {unit}).")
        for name, reading in (t.get("readings") or {}).items():
            out += f"\n  - read as `{name}`: {reading}."
        out += "\n"
    return out


def _caveats_section(diag: Mapping) -> str:
    res = diag.get("residuals") or {}
    structured = [k for k in ("baseline", "extended") if ((final_residuals(diag) if k == "extended" else res.get(k))
                                                          or {}).get("structured")]
    out = "## Caveats\n\n"
    iv = _final_summary(diag).get("intervals") or {}
    if "sandwich" in (iv.get("method") or ""):
        out += (f"- The 95 % intervals of the final model account for the autocorrelation of its residuals: the "
                f"residuals of each experiment are taken as an AR(1) process (lag-1 autocorrelation "
                f"{iv.get('phi_used', float('nan')):.2f} after its small-sample correction), the covariance is the "
                f"sandwich (JᵀJ)⁻¹JᵀΣJ(JᵀJ)⁻¹ and the quantile a t on about {max(iv.get('n_eff', 1), 1):.0f} "
                "effective samples. On synthetic tests with AR(1) noise (φ 0 to 0.95) such intervals cover the "
                "true parameters in 90–98 % of cases, where Gauss–Newton intervals, which assume white residuals, "
                "are too narrow (they cover about 80 % at φ = 0.5 and 25 % at φ = 0.95); a misfit that is no AR(1) process (a "
                "systematic bend the model lacks) is covered only as far as it looks like one.")
    elif iv.get("method"):
        out += ("- The 95 % intervals of the final model are Gauss–Newton intervals, which assume white residuals: "
                "its residuals show no positive lag-1 autocorrelation (with it they would be too narrow, and the "
                "AR(1) sandwich would be used).")
    else:
        out += ("- The 95 % intervals come from the Gauss–Newton covariance and assume white, independent "
                "residuals of constant variance.")
    out += "\n"
    out += ("- The p of the nested F test and the BIC make the same white-noise assumption; with structured "
            "residuals they overstate the evidence. The held-out ratio does not rely on it.\n")
    out += ("- The held-out refits start from the all-data optimum (one start each), so they are not fully "
            "independent of the held-out points: the held-out error is, if anything, optimistic, equally for "
            "every candidate.\n")
    if diag["data"].get("heldout", "").startswith("4 contiguous"):
        out += ("- Held-out blocks are stretches of the tests the fit saw the rest of: a prediction into a "
                "stretch the fit did not see, not a new test.\n")
    out += ("- Every candidate of the ranking is one effect added to the baseline, and the named effect is the "
            "single one that explains most; further effects are tried on top of it in the chain (see Chain of "
            "effects), one at a time, the best addition first.\n")
    if structured and "extended" not in structured:
        out += "- The baseline's residuals were structured; the extension removed that structure.\n"
    return out


def _warnings_section(diag: Mapping) -> str:
    """What may be wrong with the input itself (e.g. a unit), before any result is read ('' when nothing)."""
    ws = diag.get("warnings") or []
    if not ws:
        return ""
    out = "## Warnings\n\n"
    for w in ws:
        out += f"- {w['message']}\n"
    if any(w.get("kind", "units") == "units" for w in ws):
        out += ("\nThe fit adapts its bounds to the data, so it cannot notice a wrong unit: the results below are "
                "for the data as read.\n")
    if any(w.get("kind") == "averaging" for w in ws):
        out += ("\nThe residuals cannot show a bias from block averaging (the fit has absorbed it): it was found by "
                "running the fitted model at every original sample of the averaged tests and averaging that in the "
                "same blocks. The results below are for the block means.\n")
    return out


def _chain_section(diag: Mapping) -> str:
    """The chain of effects: each step's gain over the model before it and where its fit stopped at a bound,
    and every addition the checks removed, with why."""
    steps = diag.get("chain") or []
    removed = diag.get("chain_removed") or []
    if not steps and not removed:
        return ""
    _, unit, f = response_channel(diag)
    rows = []
    for i, s in enumerate(steps, 1):
        g = s["gain"]
        bounds = ", ".join(f"`{fmu_name(diag, b['name'])}` ({b['bound']})" for b in s.get("at_bounds") or []) or "none"
        rows.append([f"#{i}" + (" (refitted)" if s.get("refit") else ""), f"`{s['effect']}`",
                     f"{fmt(s['rmse'] * f)}", f"{fmt(s['heldout_rmse'] * f)}",
                     ratio_text(g.get("rmse_ratio")), ratio_text(g.get("heldout_rmse_ratio")),
                     delta_text(g.get("delta_bic")), p_text(g.get("p_value")), bounds])
    out = "## Chain of effects\n\n"
    if len(steps) == 1:
        out += (f"After `{steps[0]['effect']}`, every remaining candidate was tried on top of it: none passed the "
                f"tests and the checks (significant, mattering and physically possible against the model with "
                f"`{steps[0]['effect']}`), so the chain stops at one effect.\n\n")
    elif steps:
        out += ("After the first effect, every remaining candidate was tried on top of the model so far; the best "
                "addition was kept while it passed the same tests as the first (significant and mattering) and "
                "the checks (an effect the protocol can identify, parameters the tests support, a fit not worse "
                "than the step before). Gains are against the model of the step before (the first against the "
                "baseline). The headline, the parameters, the residuals and the figures are the final model's: "
                f"{final_label(diag)}.\n\n")
    if steps:
        out += _table(["step", "effect", f"RMSE [{unit}]", f"held-out RMSE [{unit}]", "RMSE ratio",
                       "held-out ratio", "ΔBIC", "p", "at a bound"], rows) + "\n"
    for i, s in enumerate(steps, 1):
        if s.get("refit"):
            out += f"Step {i} (`{s['effect']}`) was refitted: {s['refit']['text']}.\n\n"
    if removed:
        labels = {"physics": "a parameter the tests cannot support", "protocol": "the protocol cannot identify it",
                  "optimiser": "an optimiser failure"}
        out += "\nRemoved by the checks (not added to the model):\n\n"
        for r in removed:
            out += (f"- step {r['step']}, `{r['effect']}` ({labels.get(r['check'], r['check'])}): {r['reason']}"
                    + (f". The test that would tell: {r['separating_test']}" if r.get("separating_test") else "")
                    + ".\n")
    return out


def _fit_checks_section(diag: Mapping) -> str:
    """What the fits could not decide or where they stopped: a parameter held (the damping under one constant
    rate) and the test that would identify it, the baseline against the straight line through the data, and
    every parameter left at a bound."""
    lines = []
    base = diag.get("baseline") or {}
    for name, h in (base.get("held") or {}).items():
        lines.append(f"- `{name}` held at {fmt(h.get('value', 0.0))}: {h.get('why', '')}. The test that would "
                     f"identify it: {h.get('identifying_test', '')}.")
    line = diag.get("straight_line")
    if line:
        _, unit, f = response_channel(diag)
        c, u = natural(STIFFNESS, line[STIFFNESS])
        verdict = "not worse" if line.get("baseline_not_worse") else "WORSE (a fit that failed: see the caveats)"
        lines.append(f"- The fitted baseline (RMSE {fmt(base.get('rmse', float('nan')) * f)} {unit}) is {verdict} "
                     f"than the straight line through the origin with the secant stiffness {fmt(c)} {u} (RMSE "
                     f"{fmt(line['rmse'] * f)} {unit}).")
    checked = [("baseline", base.get("at_bounds") or [])]
    if diag.get("effect") != "none":
        checked += [(f"step {i} (+ {st['effect']})", st.get("at_bounds") or [])
                    for i, st in enumerate(diag.get("chain") or [], 1)] or \
                   [("extended model", (diag.get("extended") or {}).get("at_bounds") or [])]
    for label, bounds in checked:
        for b in bounds:
            v, u = natural(b["name"], b["value"])
            lim, _ = natural(b["name"], b["limit"])
            lines.append(f"- {label[0].upper()}{label[1:]}: the fit stopped at the {b['bound']} bound of `{fmu_name(diag, b['name'])}` ({fmt(v)} {u}, "
                         f"bound {fmt(lim)} {u}): no optimum inside the range; the value is a limit, not an "
                         f"estimate.")
    return "## Fit checks\n\n" + "\n".join(lines) + "\n" if lines else ""


def _caption(name: str) -> str:
    """A figure's caption, in the words of a rotational interface when it is one."""
    text = CAPTIONS.get(name, "")
    if mo.current() != mo.ROTATION:
        return text
    for a, b in (("Force against displacement", "Torque against angle"), ("displacement", "angle"),
                 ("velocity", "angular velocity"), ("force", "torque")):
        text = text.replace(a, b)
    return text


def write_report(diag: dict, experiments, out_dir: Path, figures: list[Path]) -> Path:
    """``out_dir/report.md``: the data, the named effect and why, parameters with intervals, the ranking, the
    residual diagnosis before and after, look-alike candidates, caveats and the figures."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    experiments = list(experiments)
    eff = diag["effect"]
    title = " + ".join(f"`{e}`" for e in ((diag.get("final") or {}).get("effects") or [eff]))
    if len((diag.get("final") or {}).get("effects") or []) == 1:
        title = f"`{eff}`"
    with mo.use(diag):
        return _write_report(diag, experiments, out_dir, figures, title)


def _write_report(diag: dict, experiments, out_dir: Path, figures: list[Path], title: str) -> Path:
    eff = diag["effect"]
    parts = [f"# Diagnosis: {title}\n\n"
             f"The measured {mo.channel_word(diag['data']['response'])} under imposed "
             f"{mo.channel_word(diag['data']['drive'])} against the "
             f"baseline spring–damper (eq. 1: stiffness c, damping d) and against the baseline plus each "
             f"candidate effect ({len(diag.get('ranking') or [])} candidates); the effect is named only when "
             f"its gain is significant.\n",
             budget_notice(diag), _warnings_section(diag),
             _data_section(diag, experiments), _verdict_section(diag), _params_section(diag), _chain_section(diag), _fit_checks_section(diag),
             _ranking_section(diag), _residual_section(diag, experiments), _ties_section(diag),
             _caveats_section(diag), runs_section(diag)]
    if figures:
        fig_txt = "## Figures\n\n"
        for p in figures:
            p = Path(p)
            try:
                rel = p.relative_to(out_dir)
            except ValueError:
                rel = Path("figures") / p.name
            fig_txt += f"![{p.name}]({rel.as_posix()})\n\n*{p.name}*: {_caption(p.name)}\n\n"
        parts.append(fig_txt)
    parts.append("## Files\n\n- `diagnosis.json`: every number of this report\n- `figures/`: the figures above\n")
    path = out_dir / "report.md"
    # surrogateescape: a file path given under an ASCII locale goes back as the bytes it was
    atomic_write(path, "\n".join(p.rstrip() + "\n" for p in parts if p), errors="surrogateescape")
    return path
