"""The authors' two-phase analysis of a shear test, redone: a continuous two-line least-squares fit of the raw
force Fx [N] against the raw displacement disp_x [mm], every sample, free intercept. No FMU.

Why not the FMU: fmusa's two-phase elastic model (``nonlinear_stiffness``) is a spring that starts unloaded
at the first sample, so its first line must pass through the start of the record; the authors' first line
has a free intercept (test_info.csv ``intercept_1``, often −5 to −50 N: a toe at the start of the record).
On H1–H3 and H10–H14 forcing the line through the unloaded start makes the median |Δk1| 4–10 % per rate;
with a free intercept it is 0.02–2 %. Block averaging to 300 samples changes k1 by 0.2 % at most.

The least-squares error as a function of the breakpoint has several local minima in many tests (a toe, a
late softening near the peak). The authors' breakpoints are the *first* local minimum from the start of
the loading, not always the global one (H2 Ant 100 mm/s: 0.38 mm, local; the global one is at 0.98 mm).
:data:`GRID` (interior breakpoints scanned, evenly spaced over the loaded range) was chosen on the
:data:`TUNING` specimens: mean |Δk1| 6 % with 10 points against 6–12 % with 8, 15, 20, 30 points or the
global minimum. :data:`HELD_OUT` did not enter that choice.
"""
from __future__ import annotations

from typing import Iterable

import numpy as np
from scipy import optimize

from fmusa.diagnose.intervals import sandwich_covariance

__all__ = ["GRID", "TUNING", "split_of", "fit_two_lines", "fit_line"]

#: Interior breakpoints scanned for the first local minimum of the squared error (then refined between its
#: neighbours).
GRID = 10
#: The specimens the breakpoint rule was chosen on; every other specimen of the data set is held out.
TUNING = ("H1", "H2", "H3", "H10", "H11", "H12", "H13", "H14")


def split_of(specimen: str) -> str:
    """'tuning' for a specimen the fit was tuned on, else 'held_out'."""
    return "tuning" if specimen in TUNING else "held_out"


def split(specimens: Iterable[str]) -> dict:
    """{'tuning': [...], 'held_out': [...]} of the given specimens, in their order."""
    names = list(dict.fromkeys(specimens))
    return {"tuning": [s for s in names if split_of(s) == "tuning"],
            "held_out": [s for s in names if split_of(s) == "held_out"]}


def _sse(u: np.ndarray, f: np.ndarray, b: float) -> tuple[float, np.ndarray]:
    X = np.c_[np.ones_like(u), u, np.maximum(u - b, 0.0)]
    beta, *_ = np.linalg.lstsq(X, f, rcond=None)
    e = f - X @ beta
    return float(e @ e), beta


def fit_line(x_mm: np.ndarray, f_n: np.ndarray) -> dict:
    """Straight line with intercept: k_N_mm, intercept_N, rmse_N."""
    x, f = np.asarray(x_mm, float), np.asarray(f_n, float)
    X = np.c_[np.ones_like(x), x]
    beta, *_ = np.linalg.lstsq(X, f, rcond=None)
    e = f - X @ beta
    return {"k_N_mm": float(beta[1]), "intercept_N": float(beta[0]), "rmse_N": float(np.sqrt(np.mean(e ** 2)))}


def fit_two_lines(x_mm: np.ndarray, f_n: np.ndarray, grid: int = GRID) -> dict:
    """Continuous two-line fit F = i1 + k1 x up to the breakpoint, i2 + k2 x past it (i2 = i1 + (k1 − k2) bp),
    in the raw frame: stiffnesses dF/dx [N/mm] (positive for Pos tests too, as the authors give them),
    breakpoint in raw displacement [mm]. The loading direction is that of the record (last minus first
    displacement). Keys k1_N_mm, k2_N_mm, bp_mm, intercept_1_N, intercept_2_N, rmse_N, points, k1_se_N_mm (the
    standard error of k1 at that breakpoint, AR(1) sandwich: :mod:`fmusa.diagnose.intervals`), and
    bp_global_mm (the breakpoint of the smallest squared error on the same grid, refined: not used)."""
    x, f = np.asarray(x_mm, float).ravel(), np.asarray(f_n, float).ravel()
    if x.shape != f.shape or len(x) < 4:
        raise ValueError(f"two-line fit: need >= 4 paired samples (got {len(x)} and {len(f)})")
    s = 1.0 if x[-1] >= x[0] else -1.0
    u = s * x                                   # the loading coordinate: grows during the test
    bs = np.linspace(u.min(), u.max(), int(grid) + 2)[1:-1]
    v = np.array([_sse(u, f, b)[0] for b in bs])
    first = next(j for j in range(len(v)) if (j == 0 or v[j] <= v[j - 1]) and (j == len(v) - 1 or v[j] <= v[j + 1]))
    lo, hi = bs[max(first - 1, 0)], bs[min(first + 1, len(bs) - 1)]
    b = float(bs[first])
    if hi > lo:
        res = optimize.minimize_scalar(lambda bb: _sse(u, f, bb)[0], bounds=(lo, hi), method="bounded",
                                       options={"xatol": 1e-7 * max(1.0, float(np.ptp(u)))})
        if res.fun <= v[first]:
            b = float(res.x)
    g = int(np.argmin(v))                         # the global minimum, for comparison only
    b_glob = float(bs[g])
    lo_g, hi_g = bs[max(g - 1, 0)], bs[min(g + 1, len(bs) - 1)]
    if hi_g > lo_g:
        res = optimize.minimize_scalar(lambda bb: _sse(u, f, bb)[0], bounds=(lo_g, hi_g), method="bounded")
        if res.fun <= v[g]:
            b_glob = float(res.x)
    sse, beta = _sse(u, f, b)
    k1, k2 = s * beta[1], s * (beta[1] + beta[2])          # dF/dx in the raw frame
    # the standard error of k1 at this breakpoint, for correlated residuals (AR(1) sandwich): the samples of
    # a record are far from independent
    X = np.c_[np.ones_like(u), u, np.maximum(u - b, 0.0)]
    cov, _ = sandwich_covariance(X, f - X @ beta)
    k1_se = float(np.sqrt(max(cov[1, 1], 0.0)))
    i1 = float(beta[0])
    bp = s * b
    return {"k1_N_mm": float(k1), "k2_N_mm": float(k2), "bp_mm": float(bp), "intercept_1_N": i1,
            "intercept_2_N": float(i1 + (k1 - k2) * bp), "rmse_N": float(np.sqrt(sse / len(u))),
            "bp_global_mm": float(s * b_glob), "points": int(len(u)), "k1_se_N_mm": k1_se}
