"""A population from several specimens: mean, between-specimen spread, each specimen's estimate shrunk
towards the mean, and the range a new specimen will fall in.

Biomechanics papers report a parameter over specimens (k1 = mean ± SD) and how a new specimen will behave.
Each specimen's estimate has its own standard error (its fit), and specimens differ beyond that; the
random-effects model y_i = μ + u_i + e_i (u_i ~ N(0, τ²) between specimens, e_i ~ N(0, s_i²) within) is
fitted with the Paule–Mandel estimator of τ² (the generalised Q statistic set to its expectation;
DerSimonian–Laird's closed form overstates τ when the standard errors differ by orders of magnitude, as
those of a slow and a fast test do: on the shear data it gave a τ above the plain SD of the estimates); each specimen's estimate shrinks towards μ by B_i = s_i²/(s_i² + τ²) (its best linear unbiased
prediction); a new specimen falls within μ ± t_{k−2} √(τ² + SE(μ)²) with 95 % (Higgins, Thompson &
Spiegelhalter 2009). :func:`leave_one_out` checks that range on the specimens themselves.
"""
from __future__ import annotations

import math
from typing import Mapping, Sequence

import numpy as np
from scipy import stats

__all__ = ["random_effects", "leave_one_out", "population_of_diagnoses", "summary_text", "MIN_SPECIMENS"]

#: a between-specimen spread and a prediction range need at least this many specimens (t on k − 2 dof)
MIN_SPECIMENS = 3


def random_effects(estimates: Sequence[float], ses: Sequence[float], names: Sequence[str] | None = None,
                   level: float = 0.95) -> dict:
    """Random-effects fit (Paule–Mandel τ²) of per-specimen estimates with their standard errors.

    Keys: k, mean, mean_se, mean_ci, tau (between-specimen SD), sd (plain SD of the estimates), i2 (share
    of the spread that is between specimens), q, q_p (Cochran's Q test of no spread), prediction (the range
    of a new specimen), specimens (name, estimate, se, shrunk, shrinkage B_i). With fewer than
    MIN_SPECIMENS estimates the spread and the prediction are NaN and ``note`` says why."""
    y = np.asarray(estimates, float)
    s = np.asarray(ses, float)
    names = list(names) if names is not None else [str(i + 1) for i in range(len(y))]
    ok = np.isfinite(y) & np.isfinite(s) & (s > 0)
    y, s, names = y[ok], s[ok], [n for n, o in zip(names, ok) if o]
    k = len(y)
    nan = float("nan")
    if k == 0:
        return {"k": 0, "mean": nan, "mean_se": nan, "mean_ci": [nan, nan], "tau": nan, "sd": nan, "i2": nan,
                "q": nan, "q_p": nan, "prediction": [nan, nan], "specimens": [],
                "note": "no specimen with a finite estimate and standard error"}
    w = 1.0 / s ** 2
    mu_fe = float(np.sum(w * y) / np.sum(w))
    q = float(np.sum(w * (y - mu_fe) ** 2))
    tau2 = _paule_mandel(y, s) if k > 1 else 0.0
    ws = 1.0 / (s ** 2 + tau2)
    mu = float(np.sum(ws * y) / np.sum(ws))
    se_mu = float(math.sqrt(1.0 / np.sum(ws)))
    z = stats.norm.ppf(0.5 + level / 2)
    out = {"k": k, "mean": mu, "mean_se": se_mu, "mean_ci": [mu - z * se_mu, mu + z * se_mu],
           "tau": math.sqrt(tau2), "sd": float(np.std(y, ddof=1)) if k > 1 else nan,
           "i2": max(0.0, (q - (k - 1)) / q) if k > 1 and q > 0 else 0.0,
           "q": q, "q_p": float(stats.chi2.sf(q, k - 1)) if k > 1 else nan}
    if k >= MIN_SPECIMENS:
        half = stats.t.ppf(0.5 + level / 2, k - 2) * math.sqrt(tau2 + se_mu ** 2)
        out["prediction"] = [mu - half, mu + half]
    else:
        out["prediction"] = [nan, nan]
        out["note"] = f"{k} specimen(s): the range of a new specimen needs at least {MIN_SPECIMENS}"
    B = s ** 2 / (s ** 2 + tau2)
    out["specimens"] = [{"name": n, "estimate": float(yi), "se": float(si), "shrunk": float(bi * mu + (1 - bi) * yi),
                         "shrinkage": float(bi)} for n, yi, si, bi in zip(names, y, s, B)]
    return out


def _paule_mandel(y: np.ndarray, s: np.ndarray) -> float:
    """τ² at which the generalised Q statistic Σ (y_i − μ(τ²))² / (s_i² + τ²) equals its expectation k − 1
    (0 when even τ² = 0 gives less)."""
    k = len(y)

    def excess(tau2: float) -> float:
        w = 1.0 / (s ** 2 + tau2)
        mu = float(np.sum(w * y) / np.sum(w))
        return float(np.sum(w * (y - mu) ** 2)) - (k - 1)
    if excess(0.0) <= 0:
        return 0.0
    hi = max(float(np.var(y, ddof=1)), 1e-300)
    while excess(hi) > 0:
        hi *= 4.0
    from scipy.optimize import brentq
    return float(brentq(excess, 0.0, hi, xtol=1e-12 * hi))


def leave_one_out(estimates: Sequence[float], ses: Sequence[float], reference: Sequence[float],
                  names: Sequence[str] | None = None, level: float = 0.95,
                  reference_ses: Sequence[float] | None = None) -> dict:
    """Leave each specimen out, predict the range of a new specimen from the rest (:func:`random_effects`)
    and check whether the specimen's ``reference`` value (e.g. the authors' own analysis) falls inside.

    The range of a new specimen is that of its true value. A reference that is itself measured (the authors'
    k1 is a fit to the same test, with the same error as the specimen's own estimate) scatters about the true
    value by its own error too, so with ``reference_ses`` each is checked against the range widened by it:
    μ ± t_{k−2} √(τ² + SE(μ)² + s_ref²) (the left-out test's precision, not its value). Without them the
    reference is taken as exact (a true value, as in a simulation).

    Keys: rows (name, reference, prediction (the new specimen's range), checked_range, inside), inside
    (count), tested (count), share."""
    y = np.asarray(estimates, float)
    s = np.asarray(ses, float)
    ref = np.asarray(reference, float)
    ref_s = np.zeros(len(y)) if reference_ses is None else np.asarray(reference_ses, float)
    names = list(names) if names is not None else [str(i + 1) for i in range(len(y))]
    rows = []
    for i in range(len(y)):
        keep = np.arange(len(y)) != i
        fit = random_effects(y[keep], s[keep], level=level)
        lo, hi = fit["prediction"]
        if not (math.isfinite(lo) and math.isfinite(ref[i])):
            continue
        if ref_s[i] > 0 and math.isfinite(ref_s[i]):
            k = fit["k"]
            half = stats.t.ppf(0.5 + level / 2, k - 2) * math.sqrt(fit["tau"] ** 2 + fit["mean_se"] ** 2
                                                                   + ref_s[i] ** 2)
            checked = [fit["mean"] - half, fit["mean"] + half]
        else:
            checked = [lo, hi]
        rows.append({"name": names[i], "reference": float(ref[i]), "prediction": [lo, hi],
                     "checked_range": checked, "inside": bool(checked[0] <= ref[i] <= checked[1])})
    inside = sum(r["inside"] for r in rows)
    return {"rows": rows, "inside": inside, "tested": len(rows),
            "share": inside / len(rows) if rows else float("nan")}


def summary_text(fit: Mapping, unit: str = "", digits: int = 3) -> str:
    """'mean ± between-specimen SD (k specimens; a new specimen: lo to hi)' in plain words."""
    u = f" {unit}" if unit else ""
    if not fit.get("k"):
        return "no specimen"
    lo, hi = fit["prediction"]
    new = (f"; a new specimen: {lo:.{digits}g} to {hi:.{digits}g}{u}" if math.isfinite(lo) else "")
    return (f"{fit['mean']:.{digits}g}{u} ± {fit['tau']:.{digits}g}{u} between specimens "
            f"({fit['k']} specimens{new})")


def population_of_diagnoses(diags: Mapping[str, Mapping], level: float = 0.95) -> dict:
    """The population of every parameter that the final models of several specimens' diagnoses
    (:func:`fmusa.diagnose.run.diagnose`, one per specimen, keyed by its name) share: :func:`random_effects`
    of the values with standard errors from their 95 % intervals ((upper − lower)/(2 × 1.96); the intervals
    of log-scaled parameters are asymmetric, so this is their average half-width). A parameter is pooled
    only over the specimens whose final model has it; those whose model differs are named."""
    z = stats.norm.ppf(0.5 + level / 2)
    values: dict[str, list] = {}
    for name, d in diags.items():
        final = d.get("final") or {}
        params = final.get("params") or {n: {"value": v, "ci95": (d.get("baseline") or {}).get("ci95", {}).get(n)}
                                         for n, v in ((d.get("baseline") or {}).get("params") or {}).items()}
        for p, v in params.items():
            ci = v.get("ci95")
            if ci is None or len(ci) != 2:
                continue
            values.setdefault(p, []).append((name, float(v["value"]), (float(ci[1]) - float(ci[0])) / (2 * z)))
    out = {}
    for p, rows in values.items():
        fit = random_effects([r[1] for r in rows], [r[2] for r in rows], [r[0] for r in rows], level)
        fit["without"] = [n for n in diags if n not in {r[0] for r in rows}]
        out[p] = fit
    return out

