"""A fixed-step implicit integrator that lands on a given time grid: 3-stage Radau IIA (order 5, L-stable).

Why not an adaptive solver: a coupled run is driven by a measured signal interpolated linearly between its
samples, so the right-hand side has a kink at every sample; an adaptive solver steps across them, rejects and
shrinks. Stepping from sample to sample (each interval cut into equal substeps) keeps the drive affine within
every step, and the step pattern the same from run to run, so a fit's finite-difference Jacobian sees the
model's change and not the step controller's. The error is still controlled: the embedded estimate of Hairer
and Wanner's RADAU5 is taken at every step against ``rtol``, and an interval whose estimate is too large is
repeated with twice the substeps (the next interval starts from the count that passed, and tries half of it
when the estimate was far below the tolerance).

The Newton iteration of the collocation system is the simplified one, with one finite-difference Jacobian
reused over steps and intervals and renewed only when the iteration converges slowly; the LU factors are kept
per step size. At least two iterations are made per step (the first cannot show that it converged).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

S6 = 6 ** 0.5
#: Radau IIA, 3 stages: nodes and coefficients (Hairer & Wanner, Solving ODEs II, table IV.5.6)
C = np.array([(4 - S6) / 10, (4 + S6) / 10, 1.0])
A = np.array([[(88 - 7 * S6) / 360, (296 - 169 * S6) / 1800, (-2 + 3 * S6) / 225],
              [(296 + 169 * S6) / 1800, (88 + 7 * S6) / 360, (-2 - 3 * S6) / 225],
              [(16 - S6) / 36, (16 + S6) / 36, 1 / 9]])
#: the embedded error estimate of RADAU5 (as scipy's Radau writes it)
E = np.array([-13 - 7 * S6, -13 + 7 * S6, -1]) / 3
MU_REAL = 3 + 3 ** (2 / 3) - 3 ** (1 / 3)
NEWTON_MAXITER = 7
MAX_LEVEL = 40          # a step at least a sample interval over 2**40


class GridIntegrationError(RuntimeError):
    """The integration could not meet its tolerance on an interval even with the finest substeps."""


@dataclass
class GridStats:
    steps: int = 0          # accepted substeps
    rejected: int = 0       # steps thrown away and cut in two (error estimate too large, Newton failed)
    rhs: int = 0            # right-hand side evaluations (including the Jacobians')
    jacobians: int = 0
    max_substeps: int = 1   # the finest cut: the smallest step was a sample interval over this
    worst_error: float = 0.0  # the largest accepted error estimate, in units of the tolerance


def _inverse(M: np.ndarray) -> np.ndarray:
    inv = np.linalg.inv(M)
    if not np.all(np.isfinite(inv)):
        raise GridIntegrationError("the Newton matrix of the implicit step is singular")
    return inv


def integrate_on_grid(rhs: Callable[[float, np.ndarray], np.ndarray], x0: np.ndarray, grid: np.ndarray,
                      rtol: float, floor: np.ndarray, on_step: Callable[[float, np.ndarray], bool] | None = None,
                      check: Callable[[float], None] | None = None) -> tuple[float, np.ndarray, GridStats]:
    """Integrate x' = rhs(t, x) from (grid[0], x0) through every point of ``grid``.

    The tolerance per state is ``rtol * max(|x_i|, the largest |x_i| so far, floor_i)``. ``on_step(t, x)`` is
    called at every grid point reached, right after ``rhs`` was last called at that (t, x) (True: stop there, e.g. an FMU asks for an event); ``check(t)`` between
    intervals and every 64 steps tried (a time limit raises there). Returns (the time reached, the state there,
    the statistics)."""
    x = np.array(x0, float)
    n = x.size
    stats = GridStats()
    peak = np.maximum(np.abs(x), np.asarray(floor, float))
    newton_tol = max(10 * np.finfo(float).eps / rtol, min(0.03, rtol ** 0.5))

    def f(t, y):
        stats.rhs += 1
        return rhs(t, y)

    def jacobian(t, y, fy):
        stats.jacobians += 1
        J = np.empty((n, n))
        for j in range(n):
            dy = 1e-7 * max(abs(y[j]), peak[j], 1e-300 ** 0.5)
            yj = y.copy()
            yj[j] += dy
            J[:, j] = (f(t, yj) - fy) / dy
        return J

    t = float(grid[0])
    fx = f(t, x)
    J = jacobian(t, x, fx) if n else np.zeros((0, 0))
    J_fresh = True
    factors: dict[float, tuple] = {}

    def lus(h):
        key = float(h)
        if key not in factors:
            # explicit inverses: the systems are small (3n, n) and solved many times with the same matrix,
            # where scipy's lu_solve costs more in its checks than in the arithmetic
            factors[key] = (_inverse(np.eye(3 * n) - h * np.kron(A, J)), _inverse(MU_REAL / h * np.eye(n) - J))
        return factors[key]

    def step(t, x, fx, h):
        """One Radau IIA step: (x at t + h, error norm) or None when Newton did not converge."""
        lu_full, lu_real = lus(h)
        scale = rtol * np.maximum(np.abs(x), peak)
        Z = np.outer(C * h, fx)        # predictor: the stages on the tangent
        norm_old, rate = None, None
        for k in range(NEWTON_MAXITER):
            F = np.array([f(t + C[i] * h, x + Z[i]) for i in range(3)])
            if not np.all(np.isfinite(F)):
                return None
            dZ = (lu_full @ (h * (A @ F) - Z).ravel()).reshape(3, n)
            dnorm = float(np.max(np.abs(dZ) / scale))
            if norm_old is not None:
                rate = dnorm / norm_old if norm_old > 0 else 0.0
                if rate >= 1 or rate ** (NEWTON_MAXITER - k) / (1 - rate) * dnorm > newton_tol:
                    return None
            Z += dZ
            if dnorm == 0 or (rate is not None and rate / (1 - rate) * dnorm < newton_tol):
                break
            norm_old = dnorm
        else:
            return None
        x_new = x + Z[2]
        ZE = Z.T @ E / h
        err = lu_real @ (fx + ZE)
        scale = rtol * np.maximum(np.maximum(np.abs(x), np.abs(x_new)), peak)
        err_norm = float(np.sqrt(np.mean((err / scale) ** 2)))
        if err_norm > 1:     # the estimate filtered once more, bounded on stiff components (Hairer-Wanner (8.20))
            err = lu_real @ (f(t, x + err) + ZE)
            err_norm = float(np.sqrt(np.mean((err / scale) ** 2)))
        # f at the new point, evaluated last (on_step reads the FMUs there). The last stage's value corrected
        # along the Jacobian would save this evaluation but, with a Jacobian gone stale at a stiff
        # nonlinearity, spoils the error estimate (measured 0.39 of the range wrong on a friction case, rtol 1e-3)
        f_new = f(t + h, x_new)
        return x_new, err_norm, rate, f_new

    level, tries = 0, 0
    for b in grid[1:]:
        b = float(b)
        if check is not None:
            check(t)
        a = t
        width = b - a
        # the interval cut into 2**level equal pieces; a piece whose step fails is cut in two, recursively, so
        # that steps are small only where the solution needs it (a stiff start, a kink of the drive)
        pieces = deque((a + k * width / 2 ** level, a + (k + 1) * width / 2 ** level, level)
                       for k in range(2 ** level))
        last_err = 0.0
        while pieces:
            t0, t1, lv = pieces.popleft()
            tries += 1
            if check is not None and tries % 64 == 0:
                check(t0)
            h = t1 - t0
            res = step(t0, x, fx, h)
            if res is None and not J_fresh:          # a stale Jacobian: renew it, try the step again
                J, J_fresh = jacobian(t0, x, fx), True
                factors.clear()
                res = step(t0, x, fx, h)
            if res is None or res[1] > 1.0:
                stats.rejected += 1
                if lv >= MAX_LEVEL:
                    raise GridIntegrationError(f"the implicit integration could not meet rtol {rtol:g} at "
                                               f"t = {t0:.9g} with a step of {h:.3g} (the sample interval "
                                               f"[{a:.9g}, {b:.9g}] over 2**{MAX_LEVEL})")
                mid = 0.5 * (t0 + t1)
                pieces.appendleft((mid, t1, lv + 1))
                pieces.appendleft((t0, mid, lv + 1))
                continue
            x, last_err, rate, fx = res
            t = t1
            level = lv
            stats.worst_error = max(stats.worst_error, last_err)
            stats.max_substeps = max(stats.max_substeps, 2 ** lv)
            peak = np.maximum(peak, np.abs(x))
            stats.steps += 1
            if rate is not None and rate > 0.3:   # slow convergence: a new Jacobian for the next step
                J, J_fresh = jacobian(t, x, fx), True
                factors.clear()
                f(t, x)                           # the last evaluation is the accepted state again
            else:
                J_fresh = False
        t = b
        if last_err < 0.02 and level > 0:         # the next interval starts from the last piece's cut, or coarser
            level -= 1
        if on_step is not None and on_step(t, x):
            break
    return t, x, stats
