"""The paper's nested binary search for the smallest parameters that meet every constraint.

Outer loop: the outer parameter (damping d) is halved from the top of the region of interest. Inner loop:
bisection of the inner parameter (stiffness c) between the region's bounds for its smallest feasible value.
Stop rule (the paper's): a feasible pair has been found and the response did not change for two
consecutive pairs; or no feasible inner value exists at the next outer value. Guards: the bracket must
change sign (infeasible at the bottom, feasible at the top), and a few points above the found value are
checked to be feasible too; otherwise the boundary is not monotone and the result says so.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np

from fmusa.analysis.roi import Region

Evaluate = Callable[[dict[str, float]], dict]


@dataclass
class Level:
    outer: float
    inner: float | None                  # smallest feasible inner value at this outer value
    row: dict | None                     # the run at (inner, outer)
    below: dict | None                   # the last infeasible run below it (for the binding constraint)
    evaluations: int
    changed: bool | None = None          # did the response change against the previous level?
    note: str = ""


@dataclass
class SearchResult:
    inner: str
    outer: str
    optimum: dict[str, float] | None
    row: dict | None
    binding: list[str]
    levels: list[Level]
    stop_reason: str
    warnings: list[str] = field(default_factory=list)


def _feasible(row: dict) -> bool:
    return bool(row.get("feasible")) and row.get("status") == "ok"


def _changed(a: dict, b: dict, metrics: Sequence[str], rtol: float,
             atol: Mapping[str, float] | None = None) -> bool:
    """Whether any response metric differs between runs ``a`` and ``b``: by more than ``rtol`` relative
    and more than its ``atol`` floor (so that a metric that is 0 up to round-off does not count as
    changed), or exists in one run only."""
    atol = atol or {}
    for m in metrics:
        x, y = float(a[m]), float(b[m])
        if math.isnan(x) != math.isnan(y):
            return True
        if not math.isnan(x) and abs(x - y) > max(rtol * max(abs(x), abs(y), 1e-300), atol.get(m, 0.0)):
            return True
    return False


def bisect_inner(evaluate: Evaluate, inner: str, outer: str, z: float, lo: float, hi: float,
                 rtol: float, warnings: list[str]) -> Level:
    """Smallest feasible inner value in [lo, hi] at outer value z, by bisection."""
    n = 0

    def run(x: float) -> dict:
        nonlocal n
        n += 1
        return evaluate({inner: x, outer: z})

    r_lo, r_hi = run(lo), run(hi)
    if _feasible(r_lo):
        warnings.append(f"{outer} = {z:g}: already feasible at the region's lower bound {inner} = {lo:g}; "
                        f"the boundary lies below the region (lower its {inner} bound)")
        return Level(z, lo, r_lo, None, n, note="feasible at lower bound")
    if not _feasible(r_hi):
        return Level(z, None, None, r_lo, n, note=f"no feasible {inner} up to {hi:g}")
    below = r_lo
    while hi - lo > rtol * hi:
        mid = 0.5 * (lo + hi)
        r = run(mid)
        if _feasible(r):
            hi, r_hi = mid, r
        else:
            lo, below = mid, r
    # monotonicity guard: points above the boundary must stay feasible
    for x in np.geomspace(hi, hi * 1.5, 4)[1:]:
        top = run(float(x))
        if not _feasible(top):
            failed = [k[3:] for k, v in top.items() if k.startswith("ok_") and not v]
            warnings.append(f"{outer} = {z:g}: the constraint boundary in {inner} is not monotone: feasible "
                            f"at {hi:.6g} but not at {x:.6g} ({', '.join(failed) or top.get('status')})")
            break
    return Level(z, hi, r_hi, below, n)


def nested_binary_search(evaluate: Evaluate, region: Region, response: Sequence[str], inner_rtol: float = 1e-3,
                         response_rtol: float = 1e-3, max_outer: int = 20,
                         response_atol: Mapping[str, float] | None = None) -> SearchResult:
    inner, outer = region.inner, region.outer
    x_lo, x_hi = region.inner_range
    z_top = region.outer_range[1]
    warnings: list[str] = []
    levels: list[Level] = []
    stop = f"reached max_outer = {max_outer} halvings of {outer}"
    unchanged_run = 0
    for k in range(max_outer + 1):
        z = z_top / 2 ** k
        level = bisect_inner(evaluate, inner, outer, z, x_lo, x_hi, inner_rtol, warnings)
        feasible_levels = [lv for lv in levels if lv.inner is not None]
        if level.inner is None:
            levels.append(level)
            stop = (f"no feasible {inner} in [{x_lo:g}, {x_hi:g}] at {outer} = {z:g}"
                    + ("" if feasible_levels else ": the region holds no feasible pair"))
            break
        if feasible_levels:
            level.changed = _changed(level.row, feasible_levels[-1].row, response, response_rtol, response_atol)
            unchanged_run = 0 if level.changed else unchanged_run + 1
        levels.append(level)
        if unchanged_run >= 2:
            floors = ", ".join(f"{m} {a:g}" for m, a in (response_atol or {}).items() if a > 0)
            stop = (f"the response ({', '.join(response)}) changed by less than {response_rtol:g} (relative)"
                    + (f" or less than its absolute floor ({floors})" if floors else "")
                    + " for two consecutive pairs")
            break
    found = [lv for lv in levels if lv.inner is not None]
    if not found:
        return SearchResult(inner, outer, None, None, [], levels, stop, warnings)
    # The answer is the first pair of the final unchanged run: below it the outer parameter no longer
    # changes the response (the paper: "parameters smaller than presented here ... did not indicate any
    # significant change"). Without such a run, the smallest feasible outer value reached.
    best = found[-1]
    if unchanged_run >= 2:
        best = found[-unchanged_run]
    binding = []
    if best.below is not None:
        binding = [k[3:] for k, v in best.below.items() if k.startswith("ok_") and not v]
    return SearchResult(inner, outer, {inner: best.inner, outer: best.outer}, best.row, binding, levels, stop,
                        warnings)
