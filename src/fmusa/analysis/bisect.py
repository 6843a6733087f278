"""One bisection for the whole package: the smallest feasible value of a monotone predicate on a bracket,
the same started from a guess (warm start), and the crossing of a monotone function with a target.

Every FMU run costs (seconds for a vendor FMU), so these functions never evaluate a point twice and take
results the caller already has (``at_lo``, ``at_hi``). The test may return anything (a run's row, a
bool); ``feasible`` reads the verdict from it (default: ``bool``). Feasibility must be monotone in x:
infeasible below the boundary, feasible above it.

Tolerance: a bracket [lo, hi] is narrow enough when ``hi - lo <= rtol * max(|lo|, |hi|)``; the answer is
its feasible end ``hi``, so it lies at most ``rtol`` (relative) above the true boundary. The midpoint is
``(lo + hi) / 2`` (``midpoint="linear"``) or ``sqrt(lo * hi)`` (``"geometric"``, for brackets spanning
decades; needs lo > 0).

Example::

    from fmusa.analysis.bisect import crossing, smallest_feasible, smallest_feasible_from

    b = smallest_feasible(lambda c: 411.0 / c <= 5e-4, 1e5, 1e7, rtol=1e-4)
    b.status, b.value, b.evaluations   # ('bracketed', 822000.88..., 19): 822000 <= b.value <= 822000 * (1 + 1e-4)
    b = smallest_feasible_from(lambda c: 411.0 / c <= 5e-4, 822050.0, 1e5, 1e7, rtol=1e-4)
    b.evaluations                      # 2: the guess is feasible and guess * (1 - 1e-4) is not
    crossing(lambda t: t * t, 2.0, 0.0, 4.0, rtol=1e-9)     # 1.41421356...

With rows from an FMU run: ``smallest_feasible(lambda c: run({"c": c, "d": 488.0}), lo, hi,
feasible=lambda row: row["feasible"])``; ``b.result`` is the row at ``b.value`` and ``b.below_result``
the row at the last infeasible point (which constraint binds).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Generic, Literal, TypeVar

__all__ = ["Boundary", "smallest_feasible", "smallest_feasible_from", "crossing", "narrow_enough",
           "BRACKETED", "FEASIBLE_AT_LO", "INFEASIBLE_AT_HI"]

R = TypeVar("R")
Midpoint = Literal["linear", "geometric"]

#: Boundary.status values
BRACKETED, FEASIBLE_AT_LO, INFEASIBLE_AT_HI = "bracketed", "feasible_at_lo", "infeasible_at_hi"


@dataclass
class Boundary(Generic[R]):
    """Where a monotone predicate turns feasible.

    ``status``: ``"bracketed"`` (``below`` < boundary <= ``value``, within rtol), ``"feasible_at_lo"``
    (already feasible at the lower bound: ``value`` = lo, ``below`` None; the boundary may lie below the
    bracket) or ``"infeasible_at_hi"`` (no feasible value up to hi: ``value`` None, ``below`` = hi).
    ``evaluations`` counts the calls of the test made here (not the caller's ``at_lo``/``at_hi``)."""
    value: float | None
    result: R | None
    below: float | None
    below_result: R | None
    evaluations: int
    status: str


def narrow_enough(lo: float, hi: float, rtol: float) -> bool:
    """The stop rule of every bisection here: ``hi - lo <= rtol * max(|lo|, |hi|)``."""
    return hi - lo <= rtol * max(abs(lo), abs(hi))


def _mid(lo: float, hi: float, midpoint: Midpoint) -> float:
    if midpoint == "geometric":
        return math.sqrt(lo * hi)
    return 0.5 * (lo + hi)


def smallest_feasible(test: Callable[[float], R], lo: float, hi: float, rtol: float = 1e-3, *,
                      feasible: Callable[[R], bool] = bool, midpoint: Midpoint = "linear",
                      at_lo: R | None = None, at_hi: R | None = None) -> Boundary[R]:
    """Smallest x in [lo, hi] with ``feasible(test(x))``, by bisection to ``rtol``.

    Evaluates hi first (nothing feasible: stop, lo is never run), then lo, unless their results are given
    as ``at_hi`` / ``at_lo``. Stops early when a midpoint no longer moves (floating-point exhaustion)."""
    if not lo <= hi:
        raise ValueError(f"bisection bracket [{lo:g}, {hi:g}] is empty: need lo <= hi")
    if midpoint not in ("linear", "geometric"):
        raise ValueError(f"midpoint must be 'linear' or 'geometric', got {midpoint!r}")
    if midpoint == "geometric" and lo <= 0:
        raise ValueError(f"a geometric midpoint needs lo > 0, got [{lo:g}, {hi:g}]")
    n = 0

    def run(x: float) -> R:
        nonlocal n
        n += 1
        return test(x)

    r_hi = at_hi if at_hi is not None else run(hi)
    if not feasible(r_hi):
        return Boundary(None, None, hi, r_hi, n, INFEASIBLE_AT_HI)
    r_lo = at_lo if at_lo is not None else run(lo)
    if feasible(r_lo):
        return Boundary(lo, r_lo, None, None, n, FEASIBLE_AT_LO)
    while not narrow_enough(lo, hi, rtol):
        mid = _mid(lo, hi, midpoint)
        if not lo < mid < hi:
            break
        r = run(mid)
        if feasible(r):
            hi, r_hi = mid, r
        else:
            lo, r_lo = mid, r
    return Boundary(hi, r_hi, lo, r_lo, n, BRACKETED)


def smallest_feasible_from(test: Callable[[float], R], guess: float, lo: float, hi: float, rtol: float = 1e-3,
                           *, feasible: Callable[[R], bool] = bool, midpoint: Midpoint = "linear",
                           growth: float = 8.0) -> Boundary[R]:
    """:func:`smallest_feasible` in [lo, hi] started from a ``guess`` near the boundary (warm start).

    Tests the guess, then one step of ``rtol * |guess|`` towards the boundary: when the boundary has not
    moved (the guess is feasible, ``guess - rtol·|guess|`` not) that is the answer in 2 evaluations.
    Otherwise the step grows by ``growth`` per evaluation in the needed direction (clipped to [lo, hi])
    until the boundary is bracketed, and the bracket is bisected. Costs about ``2 + log_growth(D / (rtol·x))
    + log2(D·growth / (rtol·x))`` evaluations for a boundary at distance D, against ``log2((hi - lo) /
    (rtol·x))`` for a cold bisection: cheap when the guess is close."""
    if not lo <= hi:
        raise ValueError(f"bisection bracket [{lo:g}, {hi:g}] is empty: need lo <= hi")
    if growth <= 1:
        raise ValueError(f"growth must be > 1, got {growth:g}")
    n = 0

    def run(x: float) -> R:
        nonlocal n
        n += 1
        return test(x)

    def done(b: Boundary[R]) -> Boundary[R]:
        b.evaluations += n
        return b

    x = min(max(float(guess), lo), hi)
    r = run(x)
    step = rtol * abs(x) or rtol * max(abs(lo), abs(hi)) or rtol
    if feasible(r):            # the boundary is at x or below: walk down
        upper, r_upper = x, r
        first = True
        while True:
            if upper <= lo:
                return done(Boundary(lo, r_upper, None, None, 0, FEASIBLE_AT_LO))
            cand = max(lo, x - step)
            rc = run(cand)
            if not feasible(rc):
                # first step: [x - rtol·|x|, x] is rtol narrow by construction (not re-tested in floats)
                if first or narrow_enough(cand, upper, rtol):
                    return done(Boundary(upper, r_upper, cand, rc, 0, BRACKETED))
                return done(smallest_feasible(test, cand, upper, rtol, feasible=feasible, midpoint=midpoint,
                                              at_lo=rc, at_hi=r_upper))
            upper, r_upper, first = cand, rc, False
            step *= growth
    lower, r_lower = x, r     # infeasible at x: the boundary is above, walk up
    while True:
        if lower >= hi:
            return done(Boundary(None, None, hi, r_lower, 0, INFEASIBLE_AT_HI))
        cand = min(hi, x + step)
        rc = run(cand)
        if feasible(rc):
            if narrow_enough(lower, cand, rtol):
                return done(Boundary(cand, rc, lower, r_lower, 0, BRACKETED))
            return done(smallest_feasible(test, lower, cand, rtol, feasible=feasible, midpoint=midpoint,
                                          at_lo=r_lower, at_hi=rc))
        lower, r_lower = cand, rc
        step *= growth


def crossing(f: Callable[[float], float], target: float, lo: float, hi: float, rtol: float = 1e-6, *,
             midpoint: Midpoint = "linear", increasing: bool | None = None) -> float | None:
    """x in [lo, hi] where the monotone ``f`` crosses ``target``: the midpoint of the final bracket, which
    is ``rtol`` narrow. ``increasing`` None takes the direction from f(lo) and f(hi). None when f(lo) or
    f(hi) is not finite or the target is not between them. A NaN inside counts as not yet crossed."""
    f_lo, f_hi = float(f(lo)), float(f(hi))
    if not (math.isfinite(f_lo) and math.isfinite(f_hi)):
        return None
    if increasing is None:
        increasing = f_hi >= f_lo
    if not (f_lo <= target <= f_hi if increasing else f_hi <= target <= f_lo):
        return None

    def crossed(v: float) -> bool:
        return v >= target if increasing else v <= target

    b = smallest_feasible(f, lo, hi, rtol, feasible=crossed, midpoint=midpoint, at_lo=f_lo, at_hi=f_hi)
    if b.status == FEASIBLE_AT_LO:
        return lo
    return _mid(b.below, b.value, midpoint)
