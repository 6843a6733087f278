"""Eq. (3) of the paper: a cubic y = r + s x + t x^2 + u x^3 in the stiffness, fitted to a metric per
damping level, with R². The fit is done on x / x_scale for conditioning and the coefficients are given
back in raw units so they can stand next to the paper's r, s, t, u."""
from __future__ import annotations

import numpy as np
import pandas as pd


def fit_polynomial(x: np.ndarray, y: np.ndarray, degree: int = 3) -> dict:
    """Least-squares polynomial; coefficients in increasing order (r, s, t, u for degree 3)."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    n = len(x)
    if n < degree + 1:
        return {"n": int(n), "coefficients": None, "r2": None,
                "note": f"{n} points cannot determine a degree-{degree} polynomial"}
    scale = float(np.max(np.abs(x))) or 1.0
    c_scaled = np.polynomial.polynomial.polyfit(x / scale, y, degree)
    coef = [float(c / scale ** k) for k, c in enumerate(c_scaled)]
    fit = np.polynomial.polynomial.polyval(x / scale, c_scaled)
    ss_res = float(np.sum((y - fit) ** 2))
    ss_tot = float(np.sum((y - y.mean()) ** 2))
    r2 = 1.0 - ss_res / ss_tot if ss_tot > 0 else (1.0 if ss_res == 0 else 0.0)
    return {"n": int(n), "coefficients": coef, "r2": r2, "x_range": [float(x.min()), float(x.max())]}


def fit_by_level(runs: pd.DataFrame, x: str, ys: list[str], by: str | None, degree: int = 3) -> dict:
    """{metric: {level: fit}} over the successful runs in ``runs``; level "all" when ``by`` is None."""
    ok = (runs["status"] == "ok").to_numpy()
    X = runs[x].to_numpy(dtype=float)[ok]
    if by is None:
        groups = [("all", np.ones(len(X), dtype=bool))]
    else:   # the levels in increasing order, as groupby's (a level that is NaN has no group)
        B = runs[by].to_numpy(dtype=float)[ok]
        groups = [(f"{float(level):.10g}", B == level) for level in np.unique(B[~np.isnan(B)])]
    out: dict = {}
    for y in ys:
        Y = runs[y].to_numpy(dtype=float)[ok]
        out[y] = {level: fit_polynomial(X[sel], Y[sel], degree) for level, sel in groups}
    return out
