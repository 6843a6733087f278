"""Prediction bands checked on a rate the fit did not see: fit a unit's model to two of its rates, predict
the third with a 95 % band, and count the share of the third's samples inside.

The band of a new measurement is the prediction ± the quantile × √(g Cov gᵀ + γ₀) (:func:`fmusa.diagnose.
intervals.prediction_band`): Cov the parameters' covariance from the two training rates (the AR(1) sandwich
where their residuals are autocorrelated, :func:`~fmusa.diagnose.intervals.interval_report`), g the
prediction's sensitivity to the parameters, γ₀ the training residuals' variance. The model is the two-phase
elastic curve with damping (``nonlinear_stiffness``, d_y fitted): the rate enters through d_y alone, so a
share far below 95 % says the unit's rate dependence is not a damping force.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from fmusa.diagnose.calibrate import ModelRunner, calibrate
from fmusa.diagnose.effects import data_scales, model_parameters
from fmusa.diagnose.intervals import interval_report, prediction_band

__all__ = ["held_out_rate_bands", "BAND_EFFECT"]

#: the model whose bands are checked
BAND_EFFECT = "nonlinear_stiffness"


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


def held_out_rate_bands(experiments: Sequence, fmu: str, max_starts: int = 4, effect: str = BAND_EFFECT) -> list[dict]:
    """For each experiment (a rate) of a unit with at least three: fit ``effect`` to the others, predict it
    with a 95 % band; per rate the share of its samples inside, the band's median half-width (N), the
    held-out RMSE (N) and the interval method of the training fit."""
    exps = list(experiments)
    if len(exps) < 3:
        return []
    out = []
    sc_all = data_scales(exps)
    names = [p.name for p in model_parameters(effect, "displacement", sc_all)]
    model = ModelRunner(fmu, "displacement", names)
    try:
        for i, new in enumerate(exps):
            train = [e for j, e in enumerate(exps) if j != i]
            sc = data_scales(train)
            params = model_parameters(effect, "displacement", sc)
            fit = calibrate(model, effect, "displacement", train, sc, max_starts=max_starts)
            x = np.array([p.to_x(min(max(fit.params[p.name], p.lower), p.upper)) for p in params])

            def on(es):
                return lambda xx: np.concatenate(model.predict([p.from_x(v) for p, v in zip(params, xx)], es))
            pred, J = _jacobian(on(train), x)
            r = pred - np.concatenate([e.response_signal for e in train])
            rep = interval_report(J, r, x, [len(e.t) for e in train])
            y0, lo, hi = prediction_band(on([new]), x, rep["cov"], rep["gamma0"], quantile=rep["quantile"])
            meas = np.asarray(new.response_signal, float)
            out.append({"experiment": new.name, "rate_mm_s": float(new.meta.get("rate_mm_s", float("nan"))),
                        "share_inside": float(np.mean((lo <= meas) & (meas <= hi))),
                        "half_width_median_N": float(np.median(hi - y0)),
                        "heldout_rmse_N": float(np.sqrt(np.mean((y0 - meas) ** 2))),
                        "train_rmse_N": fit.rmse, "method": rep["method"], "phi": rep["phi_used"],
                        "points": int(len(meas))})
    finally:
        model.close()
    return out
