"""Prediction bands checked on a rate the fit did not see: fit a unit's model to two of its rates, predict
the third with a 95 % band, and count the share of the third's samples inside.

Why not the parameters' covariance: the residuals of a fitted shear curve are a smooth misfit of the model's
shape (lag-1 autocorrelation φ near 1), not noise, so the parameters' uncertainty is not what a new rate
costs; an AR(1) sandwich band (the prediction ± the quantile × √(g Cov gᵀ + γ₀),
:func:`fmusa.diagnose.intervals.prediction_band`) is either very wide (a few effective samples, a Student
quantile on as few degrees of freedom) or misses a rate the model does not carry over to. What a new rate costs
is the model's discrepancy when it carries over from one rate to another, and it is measured twice:

* within the unit (:func:`held_out_rate_bands`): each training rate is fitted alone and predicts the other;
  the split conformal 95 % quantile of those cross-rate errors (:func:`conformal_half_width`);
* across the units (:func:`add_population_bands`): the other units' errors when the same rate is predicted
  from the same two rates, relative to their predicted peak force, as a 95 % quantile scaled by this unit's
  predicted peak. The units (specimens) are exchangeable where the rates of one unit are not: a fast rate can
  behave unlike the two slower ones it is extrapolated from, which the within-unit errors cannot see.

The band is the prediction of the model fitted to both training rates ± the larger of the two half-widths.
The model is the two-phase elastic curve with damping (``nonlinear_stiffness``, d_y fitted): the rate enters
through d_y alone. The AR(1) band is computed beside it, for comparison (``ar1_*``).
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from fmusa.diagnose.calibrate import ModelRunner, calibrate
from fmusa.diagnose.run import AGREE_STARTS
from fmusa.diagnose.effects import data_scales, model_parameters
from fmusa.diagnose.intervals import interval_report, prediction_band

__all__ = ["held_out_rate_bands", "add_population_bands", "conformal_half_width", "BAND_EFFECT", "BAND_METHOD",
           "LEVEL"]

#: the model whose bands are checked
BAND_EFFECT = "nonlinear_stiffness"
#: the band's level
LEVEL = 0.95
#: the band's method, as the report names it
BAND_METHOD = ("the prediction of the model fitted to the two other rates ± the larger of two 95 % quantiles of "
               "the model's discrepancy on a rate it was not fitted to: within the unit (each training rate fitted "
               "alone, predicting the other) and across the other units (the same rate predicted from the same two, "
               "relative to the predicted peak force)")


def _jacobian(fn, x: np.ndarray, step: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """(f(x), forward-difference Jacobian of f at x) on the optimiser's scale."""
    y0 = fn(x)
    J = np.empty((y0.size, x.size))
    for j in range(x.size):
        h = step * max(1.0, abs(x[j]))
        xj = x.copy()
        xj[j] += h
        J[:, j] = (fn(xj) - y0) / h
    return y0, J


def conformal_half_width(errors: np.ndarray, level: float = 0.95) -> float:
    """The split conformal half-width of ``errors`` (absolute prediction errors on data the fit did not see):
    the ⌈level (n + 1)⌉-th smallest; infinite when there are too few errors for that level."""
    e = np.sort(np.abs(np.asarray(errors, float)))
    rank = math.ceil(level * (e.size + 1))
    return float(e[rank - 1]) if 0 < rank <= e.size else float("inf")


def _set_band(row: dict, half: float, abs_err: np.ndarray) -> None:
    """The band's half-width (N, and relative to the measured peak) and the share of samples inside it."""
    row.update(half_width_N=half, half_width_rel_peak=half / row["peak_N"] if row["peak_N"] > 0 else float("nan"),
               share_inside=float(np.mean(abs_err <= half)), method=BAND_METHOD)


def add_population_bands(bands: dict[str, list[dict]], level: float = LEVEL) -> None:
    """Each unit's bands (:func:`held_out_rate_bands`, in place) widened to the discrepancy across the other
    units: for a rate predicted from two others, the split conformal quantile of the other units' absolute
    errors in the same prediction (same rate from the same two), each relative to its predicted peak force,
    times this unit's predicted peak (``population_half_width_N``, ``population_share_inside``,
    ``population_units``); the band's half-width is the larger of it and the within-unit one."""
    def config(r: dict) -> tuple:
        return (r["rate_mm_s"], tuple(sorted(r["trained_on"])))

    for key, rows in bands.items():
        for r in rows:
            others = [o for k, rs in bands.items() if k != key for o in rs if config(o) == config(r)]
            rel = [np.abs(np.asarray(o["measured_N"]) - np.asarray(o["prediction_N"])) / o["predicted_peak_N"]
                   for o in others if o["predicted_peak_N"] > 0]
            err = np.abs(np.asarray(r["measured_N"]) - np.asarray(r["prediction_N"]))
            pop = conformal_half_width(np.concatenate(rel), level) * r["predicted_peak_N"] if rel else float("nan")
            r.update(population_half_width_N=pop, population_units=len(rel),
                     population_share_inside=float(np.mean(err <= pop)) if rel else float("nan"))
            _set_band(r, max(r["within_half_width_N"], pop) if rel else r["within_half_width_N"], err)


def _x_of(params, fit) -> np.ndarray:
    return np.array([p.to_x(min(max(fit.params[p.name], p.lower), p.upper)) for p in params])


def held_out_rate_bands(experiments: Sequence, fmu: str, max_starts: int = 4, effect: str = BAND_EFFECT) -> list[dict]:
    """For each experiment (a rate) of a unit with at least three: fit ``effect`` to the others, predict it
    with a 95 % band (:data:`BAND_METHOD`); per rate the share of its samples inside, the band's median
    half-width (N, and relative to the rate's peak force), the held-out RMSE (N), and the same share and
    half-width of the AR(1) sandwich band (``ar1_*``) for comparison."""
    exps = list(experiments)
    if len(exps) < 3:
        return []
    out = []
    names = [p.name for p in model_parameters(effect, "displacement", data_scales(exps))]
    model = ModelRunner(fmu, "displacement", names)
    try:
        # each rate alone, predicting every rate: the cross-rate errors of the discrepancy term
        alone = []
        for e in exps:
            sc = data_scales([e])
            params = model_parameters(effect, "displacement", sc)
            fit = calibrate(model, effect, "displacement", [e], sc, max_starts=max_starts, agree=AGREE_STARTS)
            alone.append(model.predict([p.from_x(v) for p, v in zip(params, _x_of(params, fit))], exps))
        for i, new in enumerate(exps):
            train = [j for j in range(len(exps)) if j != i]
            sc = data_scales([exps[j] for j in train])
            params = model_parameters(effect, "displacement", sc)
            fit = calibrate(model, effect, "displacement", [exps[j] for j in train], sc, max_starts=max_starts,
                            agree=AGREE_STARTS)
            x = _x_of(params, fit)

            def on(es):
                return lambda xx: np.concatenate(model.predict([p.from_x(v) for p, v in zip(params, xx)], es))
            pred, J = _jacobian(on([exps[j] for j in train]), x)
            r = pred - np.concatenate([exps[j].response_signal for j in train])
            rep = interval_report(J, r, x, [len(exps[j].t) for j in train])
            y0, lo, hi = prediction_band(on([new]), x, rep["cov"], rep["gamma0"], quantile=rep["quantile"])
            meas = np.asarray(new.response_signal, float)
            cross = np.concatenate([alone[a][b] - exps[b].response_signal for a in train for b in train if a != b])
            half = conformal_half_width(cross, LEVEL)
            row = {"experiment": new.name, "rate_mm_s": float(new.meta.get("rate_mm_s", float("nan"))),
                   "peak_N": float(np.max(np.abs(meas))), "predicted_peak_N": float(np.max(np.abs(y0))),
                   "heldout_rmse_N": float(np.sqrt(np.mean((y0 - meas) ** 2))), "train_rmse_N": fit.rmse,
                   "within_half_width_N": half, "within_share_inside": float(np.mean(np.abs(meas - y0) <= half)),
                   "within_errors": int(cross.size)}
            _set_band(row, half, np.abs(meas - y0))
            out.append({**row, "ar1_share_inside": float(np.mean((lo <= meas) & (meas <= hi))),
                        "ar1_half_width_median_N": float(np.median(hi - y0)),
                        "ar1_method": rep["method"], "phi": rep["phi_used"], "points": int(len(meas)),
                        "trained_on": [float(exps[j].meta.get("rate_mm_s", float("nan"))) for j in train],
                        "prediction_N": y0.tolist(), "measured_N": meas.tolist()})
    finally:
        model.close()
    return out
