"""The paper's nested binary search for the smallest parameters that meet every constraint.

Outer loop: the outer parameter (damping d) is halved from the top of the region of interest. Inner loop:
bisection of the inner parameter (stiffness c) between the region's bounds for its smallest feasible value
(:func:`fmusa.analysis.bisect.smallest_feasible`). Stop rule (the paper's): a feasible pair has been found
and the response did not change for two consecutive pairs; or no feasible inner value exists at the next
outer value. Guards: the bracket must change sign (infeasible at the bottom, feasible at the top), and a
few points above the found value are checked to be feasible too; otherwise the boundary is not monotone
and the result says so.

``warm_start`` (fewer FMU runs, for FMUs that cost seconds per run): every outer level after the first
starts from the previous level's answer x (:func:`fmusa.analysis.bisect.smallest_feasible_from`): x and
x·(1 − inner_rtol) are run first, and when they bracket the boundary the level costs 2 runs; otherwise the
bracket grows geometrically from x towards the boundary (within the region) and is bisected. The
monotonicity guard then runs once, at the final answer only (3 runs instead of 3 per level): a boundary
that is not monotone at another outer level goes unnoticed there (the default search guards every level),
and a bracket grown across an infeasible gap may stop at its upper edge. For a monotone boundary the
answer lies within ``inner_rtol`` of the default search's, but not on the same bisection lattice. The
paper's study: 66 runs asked (64 simulated) instead of 227 (225), c within 4.5e-4 of the default, same d.

One parameter (``region.outer`` None): one bisection of the inner parameter inside the region, guard
included; the result has ``outer`` None, ``optimum`` {inner: value} and a single level whose ``outer`` is
None.

:func:`search_in_rounds` (``search.parallel``, for FMUs that cost seconds per run, where the wall time is
the number of rounds of runs waited for, not the runs): the same search, asking for up to ``workers``
points per round. Every level walks the sequential bisection's own lattice and infers verdicts from
monotonicity, so for a monotone boundary it lands on the sequential answer at every level (the same stop,
the same optimum); a level predicted by another level's answer costs the two ends of its cell, the others
are k-sectioned, and independent levels share rounds. The paper's study on 16 workers: 15 rounds instead
of 357 (224 runs instead of 381); ``result.rounds`` says what it cost and what the sequential search takes.
With one worker (one point per round) the walk on the lattice usually costs far fewer runs than the
sequential bisection, since a level predicted by its neighbour costs the two ends of a cell (paper study: 95
runs instead of 227); against the sequential warm start it can cost a few runs more or fewer, because the
warm start leaves the lattice while the walk stays on it.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np

from fmusa.analysis.bisect import (FEASIBLE_AT_LO, INFEASIBLE_AT_HI, Boundary, narrow_enough, smallest_feasible,
                                   smallest_feasible_from)
from fmusa.analysis.roi import Region

Evaluate = Callable[[dict[str, float]], dict]

#: growth of the warm start's bracket per run (see smallest_feasible_from): 8 reaches a boundary that
#: moved by a factor 2 from a 1e-3 step in 3 runs, and costs 3 more bisection steps than a tight bracket
WARM_GROWTH = 8.0


@dataclass
class Level:
    """One outer value of the search (``outer`` None in a one-parameter search)."""
    outer: float | None
    inner: float | None                  # smallest feasible inner value at this outer value
    row: dict | None                     # the run at (inner, outer)
    below: dict | None                   # the last infeasible run below it (for the binding constraint)
    evaluations: int
    changed: bool | None = None          # did the response change against the previous level?
    note: str = ""


@dataclass
class Rounds:
    """What a search in rounds cost: ``rounds`` (batches waited for), ``runs`` (points asked), and what
    the sequential search would have taken for the same answers (one point per round)."""
    workers: int
    rounds: int = 0
    runs: int = 0
    speculative: int = 0                 # points asked for levels past the stop (or never needed)
    sequential_runs: int = 0             # = the sequential search's rounds
    largest_round: int = 0

    def as_dict(self) -> dict:
        return {"workers": self.workers, "rounds": self.rounds, "runs": self.runs,
                "speculative_runs": self.speculative, "sequential_rounds": self.sequential_runs,
                "sequential_runs": self.sequential_runs, "largest_round": self.largest_round}


@dataclass
class SearchResult:
    """The search's answer. ``optimum`` is {inner: x, outer: z}, or {inner: x} when ``outer`` is None;
    None when no feasible point was found. ``evaluations`` counts every evaluate call (levels + guard);
    the RunStore simulates a repeated point once."""
    inner: str
    outer: str | None
    optimum: dict[str, float] | None
    row: dict | None
    binding: list[str]
    levels: list[Level]
    stop_reason: str
    warnings: list[str] = field(default_factory=list)
    warm_start: bool = False
    evaluations: int = 0
    #: the cost in rounds of a search in rounds (:func:`search_in_rounds`); None for the sequential one
    rounds: Rounds | None = None


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


def edge_notes(result: "SearchResult", region: Region, rtol: float) -> list[str]:
    """Where the optimum sits at an edge of the range searched, in words (empty when it lies inside): the
    inner value at the region's top (no boundary found below it), at its bottom (the boundary lies below),
    or the outer value at the top of its range because the first halving already had no feasible inner
    value (the search stopped at its first level)."""
    opt = result.optimum
    if not opt:
        return []
    out = []
    lo, hi = region.inner_range
    x = opt[result.inner]
    if x >= hi * (1 - rtol) and hi > lo:
        out.append(f"{result.inner} = {x:.6g} is the top of the range searched ([{lo:.6g}, {hi:.6g}]): the "
                   f"constraints are met there but the search found no boundary inside the range; widen the "
                   f"grid of {result.inner} above {hi:.6g}, or check that the constraints are met at larger "
                   f"{result.inner} (the search assumes they are)")
    elif x <= lo:
        out.append(f"{result.inner} = {x:.6g} is the bottom of the range searched ([{lo:.6g}, {hi:.6g}]): the "
                   f"boundary lies below it")
    if result.outer is not None and region.outer_range is not None:
        z = opt[result.outer]
        found = [lv for lv in result.levels if lv.inner is not None]
        if z >= region.outer_range[1] and len(found) == 1:
            out.append(f"{result.outer} = {z:.6g} is the top of the range searched ([{region.outer_range[0]:.6g}, "
                       f"{region.outer_range[1]:.6g}]): the search stopped at its first level ({result.stop_reason}), "
                       f"so this is the edge of the range, not a boundary found inside it")
    return out


def _point(inner: str, outer: str | None, x: float, z: float | None) -> dict[str, float]:
    return {inner: x} if outer is None else {inner: x, outer: z}


def _at(outer: str | None, z: float | None) -> str:
    """Prefix of a warning about one level: '<outer> = z: ' (nothing in one dimension)."""
    return "" if outer is None else f"{outer} = {z:g}: "


def check_monotone(evaluate: Evaluate, inner: str, outer: str | None, z: float | None, x: float,
                   warnings: list[str]) -> int:
    """The monotonicity guard: 3 points in (x, 1.5·x] must be feasible too, else a warning says the
    boundary is not monotone. Returns the number of evaluations."""
    n = 0
    for xg in np.geomspace(x, x * 1.5, 4)[1:]:
        n += 1
        top = evaluate(_point(inner, outer, float(xg), z))
        if not _feasible(top):
            failed = [k[3:] for k, v in top.items() if k.startswith("ok_") and not v]
            warnings.append(f"{_at(outer, z)}the constraint boundary in {inner} is not monotone: feasible "
                            f"at {x:.6g} but not at {xg:.6g} ({', '.join(failed) or top.get('status')})")
            break
    return n


def _level(b: Boundary, z: float | None, inner: str, outer: str | None, lo: float, hi: float,
           n: int, warnings: list[str]) -> Level:
    """A Level from a bisection's Boundary (warning when the boundary lies below the region)."""
    if b.status == FEASIBLE_AT_LO:
        warnings.append(f"{_at(outer, z)}already feasible at the region's lower bound {inner} = {lo:g}; "
                        f"the boundary lies below the region (lower its {inner} bound)")
        return Level(z, lo, b.result, None, n, note="feasible at lower bound")
    if b.status == INFEASIBLE_AT_HI:
        return Level(z, None, None, b.below_result, n, note=f"no feasible {inner} up to {hi:g}")
    return Level(z, b.value, b.result, b.below_result, n)


def bisect_inner(evaluate: Evaluate, inner: str, outer: str | None, z: float | None, lo: float, hi: float,
                 rtol: float, warnings: list[str], guard: bool = True) -> Level:
    """Smallest feasible inner value in [lo, hi] at outer value z, by bisection: both bounds first (so
    that the level's run count is the paper's), then the guard (``guard``) at the answer."""
    def run(x: float) -> dict:
        return evaluate(_point(inner, outer, x, z))

    r_lo, r_hi = run(lo), run(hi)
    b = smallest_feasible(run, lo, hi, rtol, feasible=_feasible, at_lo=r_lo, at_hi=r_hi)
    if _feasible(r_lo):      # already feasible at the bottom: reported whatever the top says
        b = Boundary(lo, r_lo, None, None, 0, FEASIBLE_AT_LO)
    elif b.status == INFEASIBLE_AT_HI:
        b.below_result = r_lo
    level = _level(b, z, inner, outer, lo, hi, 2 + b.evaluations, warnings)
    if guard and b.status == "bracketed":
        level.evaluations += check_monotone(evaluate, inner, outer, z, b.value, warnings)
    return level


def warm_inner(evaluate: Evaluate, inner: str, outer: str | None, z: float | None, guess: float, lo: float,
               hi: float, rtol: float, warnings: list[str], growth: float = WARM_GROWTH) -> Level:
    """Smallest feasible inner value in [lo, hi] at outer value z, started from ``guess`` (the previous
    level's answer); no guard (the warm search runs it once, at the end)."""
    def run(x: float) -> dict:
        return evaluate(_point(inner, outer, x, z))

    b = smallest_feasible_from(run, guess, lo, hi, rtol, feasible=_feasible, growth=growth)
    return _level(b, z, inner, outer, lo, hi, b.evaluations, warnings)


def _binding(level: Level) -> list[str]:
    if level.below is None:
        return []
    return [k[3:] for k, v in level.below.items() if k.startswith("ok_") and not v]


def _one_parameter(evaluate: Evaluate, region: Region, rtol: float) -> SearchResult:
    """The search over the inner parameter alone: one bisection inside the region's inner range."""
    inner = region.inner
    x_lo, x_hi = region.inner_range
    warnings: list[str] = []
    level = bisect_inner(evaluate, inner, None, None, x_lo, x_hi, rtol, warnings)
    if level.inner is None:
        stop = f"no feasible {inner} in [{x_lo:g}, {x_hi:g}]: the region holds no feasible value"
        return SearchResult(inner, None, None, None, [], [level], stop, warnings, False, level.evaluations)
    stop = f"bisection of {inner} in [{x_lo:g}, {x_hi:g}] to a relative width of {rtol:g} (one parameter)"
    return SearchResult(inner, None, {inner: level.inner}, level.row, _binding(level), [level], stop, warnings,
                        False, level.evaluations)


def nested_binary_search(evaluate: Evaluate, region: Region, response: Sequence[str], inner_rtol: float = 1e-3,
                         response_rtol: float = 1e-3, max_outer: int = 20,
                         response_atol: Mapping[str, float] | None = None, *,
                         warm_start: bool = False) -> SearchResult:
    """The smallest feasible (inner, outer) pair of ``region``; see the module docstring. ``evaluate``
    takes {inner: x, outer: z} (or {inner: x} without an outer parameter) and returns the run's row."""
    if region.outer is None:
        return _one_parameter(evaluate, region, inner_rtol)
    inner, outer = region.inner, region.outer
    x_lo, x_hi = region.inner_range
    z_top = region.outer_range[1]
    warnings: list[str] = []
    levels: list[Level] = []
    stop = f"reached max_outer = {max_outer} halvings of {outer}"
    unchanged_run = 0
    for k in range(max_outer + 1):
        z = z_top / 2 ** k
        feasible_levels = [lv for lv in levels if lv.inner is not None]
        if warm_start and feasible_levels:
            level = warm_inner(evaluate, inner, outer, z, feasible_levels[-1].inner, x_lo, x_hi, inner_rtol,
                               warnings)
        else:
            level = bisect_inner(evaluate, inner, outer, z, x_lo, x_hi, inner_rtol, warnings, guard=not warm_start)
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
    evaluations = sum(lv.evaluations for lv in levels)
    found = [lv for lv in levels if lv.inner is not None]
    if not found:
        return SearchResult(inner, outer, None, None, [], levels, stop, warnings, warm_start, evaluations)
    # The answer is the first pair of the final unchanged run: below it the outer parameter no longer
    # changes the response (the paper: "parameters smaller than presented here ... did not indicate any
    # significant change"). Without such a run, the smallest feasible outer value reached.
    best = found[-1]
    if unchanged_run >= 2:
        best = found[-unchanged_run]
    if warm_start and best.below is not None:      # the guard, once, at the answer
        evaluations += check_monotone(evaluate, inner, outer, best.outer, best.inner, warnings)
    return SearchResult(inner, outer, {inner: best.inner, outer: best.outer}, best.row, _binding(best), levels,
                        stop, warnings, warm_start, evaluations)


# ---------------------------------------------------------------- the search in rounds (search.parallel)

EvaluateMany = Callable[[list[dict[str, float]]], list[dict]]


@functools.lru_cache(maxsize=4096)
def _guard_points(x: float) -> tuple[float, ...]:
    return tuple(float(v) for v in np.geomspace(x, x * 1.5, 4)[1:])


def guard_points(x: float) -> list[float]:
    """The monotonicity guard's points above an answer x: 3 in (x, 1.5·x] (the floats of
    :func:`check_monotone`)."""
    return list(_guard_points(float(x)))


def _guard_warning(outer: str | None, z: float | None, inner: str, x: float, xg: float, top: dict) -> str:
    failed = [k[3:] for k, v in top.items() if k.startswith("ok_") and not v]
    return (f"{_at(outer, z)}the constraint boundary in {inner} is not monotone: feasible "
            f"at {x:.6g} but not at {xg:.6g} ({', '.join(failed) or top.get('status')})")


class _Walk:
    """One outer level of the search in rounds: the bisection of [lo, hi] on the sequential search's own
    lattice (midpoints of midpoints, the same floats), walked from whatever runs this level has.

    A midpoint's verdict is its run's, or inferred from monotonicity (feasible when a feasible run lies at
    or below it, infeasible when an infeasible one lies at or above it), as the bisection assumes; a
    midpoint neither run nor inferred is the level's frontier. So any set of runs that brackets the
    boundary finishes the level on the lattice cell the sequential bisection ends in: two runs (the cell's
    ends) when another level predicts it, else k runs per round cutting the frontier into k + 1 parts."""

    def __init__(self, z: float | None, lo: float, hi: float, rtol: float) -> None:
        self.z, self.lo, self.hi, self.rtol = z, lo, hi, rtol
        self.known: dict[float, dict] = {}     # the bisection's runs (bounds, lattice points)
        self.guards: dict[float, dict] = {}    # the guard's runs: never used to infer a verdict
        self.asked = 0                      # points this level asked for
        self.bracket_guard: list[float] = []
        self._walks: dict[float | None, tuple[str, float, float]] = {}    # walk() by hypothesis, until a run
        self._answered: bool | None = None
        self._min_feasible = math.inf          # the smallest feasible run and the largest infeasible one
        self._max_infeasible = -math.inf

    def add(self, x: float, row: dict, guard: bool) -> None:
        """A run of this level (``guard``: one of the guard's)."""
        (self.guards if guard else self.known)[x] = row
        self.asked += 1
        if not guard:
            self._walks.clear()
            self._answered = None
            if _feasible(row):
                self._min_feasible = min(self._min_feasible, x)
            else:
                self._max_infeasible = max(self._max_infeasible, x)

    def verdict(self, x: float) -> bool | None:
        r = self.known.get(x)
        if r is not None:
            return _feasible(r)
        if self._min_feasible <= x:
            return True
        if self._max_infeasible >= x:
            return False
        return None

    def walk(self, hypothesis: float | None = None) -> tuple[str, float, float]:
        """("feasible_at_lo" | "infeasible_at_hi" | "open" | "cell", a, b): the state of the bisection.
        With ``hypothesis`` p, a midpoint without verdict counts as feasible iff it is >= p."""
        if hypothesis not in self._walks:
            self._walks[hypothesis] = self._walk(hypothesis)
        return self._walks[hypothesis]

    def _walk(self, hypothesis: float | None) -> tuple[str, float, float]:
        r_lo, r_hi = self.known.get(self.lo), self.known.get(self.hi)
        if r_lo is not None and _feasible(r_lo):
            return FEASIBLE_AT_LO, self.lo, self.lo
        if r_hi is not None and not _feasible(r_hi):
            return INFEASIBLE_AT_HI, self.hi, self.hi
        a, b = self.lo, self.hi
        while not narrow_enough(a, b, self.rtol):
            m = 0.5 * (a + b)
            if not a < m < b:
                break
            f = self.verdict(m)
            if f is None:
                if hypothesis is None:
                    return "open", a, b
                f = m >= hypothesis
            if f:
                b = m
            else:
                a = m
        return "cell", a, b

    def _cell_needs(self, a: float, b: float) -> list[float]:
        """Runs that the cell [a, b] still needs: its answer b, and an infeasible run in [a, b)."""
        need = [] if b in self.known else [b]
        if not any(a <= k < b and not _feasible(r) for k, r in self.known.items()):
            need.append(a)
        return need

    def answered(self) -> bool:
        if self._answered is None:
            state, a, b = self.walk()
            self._answered = (state in (FEASIBLE_AT_LO, INFEASIBLE_AT_HI)
                              or (state == "cell" and not self._cell_needs(a, b)))
        return self._answered

    def answer(self) -> float | None:
        """The level's smallest feasible inner value (lo when feasible there), once answered."""
        state, a, b = self.walk()
        return None if state == INFEASIBLE_AT_HI else (self.lo if state == FEASIBLE_AT_LO else b)

    def guard_set(self) -> list[float] | None:
        """The guard's points of an answered, bracketed level, once run: the exact ones above the answer
        when run, else the ones run with the last cut (all in (x, 1.5·x]); None while neither is run."""
        state, _, x = self.walk()
        exact = guard_points(x)
        if all(g in self.guards for g in exact):
            return exact
        g = self.bracket_guard
        if g and all(v in self.guards for v in g) and all(x < v <= 1.5 * x for v in g):
            return g
        return None

    def _bfs(self, a: float, b: float, budget: int) -> tuple[list[float], bool]:
        """k-section of the frontier [a, b]: the unknown midpoints of the next m bisection steps (all of
        them: 2^m - 1 at most, so that the cell after the round is certain), m as large as ``budget``
        allows; and whether the level is then sure to be done."""
        best: list[float] = []
        final = False
        m = 1
        while True:
            layer_pts: list[float] = []
            cells = [(a, b)]
            open_after = False
            for depth in range(m):
                nxt = []
                for ca, cb in cells:
                    if narrow_enough(ca, cb, self.rtol):
                        continue
                    mid = 0.5 * (ca + cb)
                    if not ca < mid < cb:
                        continue
                    f = self.verdict(mid)
                    if f is None:
                        layer_pts.append(mid)
                        nxt += [(ca, mid), (mid, cb)]
                    else:
                        nxt.append((ca, mid) if f else (mid, cb))
                cells = nxt
            open_after = any(not narrow_enough(ca, cb, self.rtol) and ca < 0.5 * (ca + cb) < cb
                             for ca, cb in cells)
            if len(layer_pts) > budget or (best and len(layer_pts) == len(best)):
                break
            best, final = layer_pts, not open_after
            if final:
                break
            m += 1
        return best, final

    def requests(self, budget: int, predictions: Sequence[float], guard: bool) -> list[tuple[float, bool]]:
        """The points this level asks for in a round of at most ``budget`` points, as (value, is a guard
        point): the cell's ends under a prediction (another level's answer) with its guard, or the
        k-section of its frontier; bounds first for a level that knows nothing."""
        return [(float(x), g) for x, g in self._requests(budget, predictions, guard)][:budget]

    def _requests(self, budget: int, predictions: Sequence[float], guard: bool) -> list[tuple[float, bool]]:
        if budget <= 0:
            return []
        state, a, b = self.walk()
        if state in (FEASIBLE_AT_LO, INFEASIBLE_AT_HI):
            return []
        if state == "cell":
            need = [(x, False) for x in self._cell_needs(a, b)]
            if not need and guard and self.guard_set() is None:
                need = [(g, True) for g in guard_points(b) if g not in self.guards]
            return need
        for p in predictions:
            if a < p <= b:
                ps, pa, pb = self.walk(hypothesis=p)
                if ps == "cell" and pb == p:
                    pts = [(x, False) for x in self._cell_needs(pa, pb)]
                    if guard:
                        pts += [(g, True) for g in guard_points(pb) if g not in self.guards]
                    return pts
        pts: list[tuple[float, bool]] = []
        if not self.known:          # a level that knows nothing: the region's bounds first (as the paper)
            pts = [(self.lo, False), (self.hi, False)][:budget]
        cut, final = self._bfs(a, b, budget - len(pts))
        if final and guard and 0 < b < 1.5 * a:
            # the last cut: the guard goes with it, at 3 points above the frontier (so in (x, 1.5·x] for
            # whichever x in it the cut picks)
            cut3, final3 = self._bfs(a, b, budget - len(pts) - 3)
            if final3 and cut3:
                self.bracket_guard = [float(v) for v in np.geomspace(b, 1.5 * a, 4)[1:]]
                return (pts + [(x, False) for x in cut3]
                        + [(g, True) for g in self.bracket_guard if g not in self.guards])
        return pts + [(x, False) for x in cut]

    def level(self, inner: str, outer: str | None, warnings: list[str], guard: bool) -> Level:
        """The Level of an answered walk (the guard's warning too, when ``guard``)."""
        state, a, b = self.walk()
        n = self.asked
        if state == FEASIBLE_AT_LO:
            warnings.append(f"{_at(outer, self.z)}already feasible at the region's lower bound {inner} = "
                            f"{self.lo:g}; the boundary lies below the region (lower its {inner} bound)")
            return Level(self.z, self.lo, self.known[self.lo], None, n, note="feasible at lower bound")
        if state == INFEASIBLE_AT_HI:
            below = self.known.get(self.lo, self.known[self.hi])
            return Level(self.z, None, None, below, n, note=f"no feasible {inner} up to {self.hi:g}")
        below_x = max(k for k, r in self.known.items() if a <= k < b and not _feasible(r))
        if guard:
            self.check_guard(inner, outer, b, warnings)
        return Level(self.z, b, self.known[b], self.known[below_x], n)

    def guard_count(self) -> int:
        """Guard runs the sequential search makes here: up to and with the first infeasible one."""
        for i, xg in enumerate(self.guard_set() or [], 1):
            if not _feasible(self.guards[xg]):
                return i
        return 3

    def check_guard(self, inner: str, outer: str | None, x: float, warnings: list[str]) -> None:
        for xg in self.guard_set() or []:
            if not _feasible(self.guards[xg]):
                warnings.append(_guard_warning(outer, self.z, inner, x, xg, self.guards[xg]))
                break


def sequential_evaluations(level: Level, lo: float, hi: float, rtol: float, guard: int = 3) -> int:
    """The runs the sequential search (:func:`bisect_inner`) asks for at a level with this answer, for a
    monotone boundary: both bounds, the bisection's steps to the answer's cell, ``guard`` guard runs."""
    if level.inner is None or level.note:
        return 2
    a, b, n = lo, hi, 0
    while not narrow_enough(a, b, rtol):
        m = 0.5 * (a + b)
        if not a < m < b:
            break
        n += 1
        if m >= level.inner:
            b = m
        else:
            a = m
    return 2 + n + guard


def search_in_rounds(evaluate_many: EvaluateMany, region: Region, response: Sequence[str], workers: int,
                     inner_rtol: float = 1e-3, response_rtol: float = 1e-3, max_outer: int = 20,
                     response_atol: Mapping[str, float] | None = None, *, warm_start: bool = False,
                     hints: Sequence[float] = ()) -> SearchResult:
    """:func:`nested_binary_search` in rounds of up to ``workers`` points run together (see
    :class:`_Walk`): ``evaluate_many`` takes a list of points and returns their rows. Outer levels are
    bracketed in the same round; a level predicted by another's answer (or by ``hints``, e.g. the answer
    of an earlier search on the same inner range) costs the two ends of that answer's lattice cell, run
    with its guard. The stop rule, the answer and the guard are the sequential search's: for a monotone
    boundary the same pair, on the same lattice. ``warm_start``: the guard once, at the answer."""
    if workers < 1:
        raise ValueError(f"a search in rounds needs at least 1 worker, got {workers}")
    inner, outer = region.inner, region.outer
    x_lo, x_hi = region.inner_range
    n_levels = 1 if outer is None else max_outer + 1
    z_top = None if outer is None else region.outer_range[1]
    walks: list[_Walk] = []
    per_level_guard = not warm_start
    cost = Rounds(workers)

    def walk(k: int) -> _Walk:
        while len(walks) <= k:
            z = None if outer is None else z_top / 2 ** len(walks)
            walks.append(_Walk(z, x_lo, x_hi, inner_rtol))
        return walks[k]

    def decide() -> tuple[int | None, int, str]:
        """(first level not answered yet or None when the stop is decided, levels in the result, stop)."""
        prev, unchanged = None, 0
        for k in range(n_levels):
            w = walk(k)
            if not w.answered():
                return k, k, ""
            x = w.answer()
            if x is None:
                return None, k + 1, "infeasible"
            if outer is None:
                return None, 1, "one"
            if prev is not None:
                changed = _changed(w.known[x], prev, response, response_rtol, response_atol)
                unchanged = 0 if changed else unchanged + 1
            prev = w.known[x]
            if unchanged >= 2:
                return None, k + 1, "unchanged"
        return None, n_levels, "max"

    while True:
        first, n_result, how = decide()
        todo: list[tuple[int, float, bool]] = []
        if first is None:      # the stop is decided: the guards the answer needs
            res_walks = walks[:n_result]
            if per_level_guard:
                need = [w for w in res_walks if w.answer() is not None and w.walk()[0] == "cell"]
            else:
                found = [w for w in res_walks if w.answer() is not None]
                need = []
                if found:
                    best = _best_index(res_walks, how)
                    if res_walks[best].walk()[0] == "cell":
                        need = [res_walks[best]]
            budget = workers
            for w in need:
                if w.guard_set() is None:
                    pts = [g for g in guard_points(w.answer()) if g not in w.guards][:budget]
                    todo += [(walks.index(w), g, True) for g in pts]
                    budget -= len(pts)
                if budget <= 0:
                    break
            if not todo:
                break
        else:
            todo = _plan_round(walks, walk, first, n_levels, workers, hints, per_level_guard)
            if not todo:
                raise RuntimeError("search in rounds: no point to run and no decision (a bug)")
        points = [_point(inner, outer, x, walks[k].z) for k, x, _ in todo]
        rows = evaluate_many(points)
        cost.rounds += 1
        cost.runs += len(points)
        cost.largest_round = max(cost.largest_round, len(points))
        for (k, x, is_guard), row in zip(todo, rows):
            walks[k].add(x, row, is_guard)

    res_walks = walks[:n_result]
    cost.speculative = sum(w.asked for w in walks[n_result:])
    warnings: list[str] = []
    levels: list[Level] = []
    prev = None
    for w in res_walks:
        lv = w.level(inner, outer, warnings, per_level_guard)
        if lv.inner is not None and prev is not None:
            lv.changed = _changed(lv.row, prev.row, response, response_rtol, response_atol)
        if lv.inner is not None:
            prev = lv
        levels.append(lv)
    cost.sequential_runs = sum(sequential_evaluations(lv, x_lo, x_hi, inner_rtol, w.guard_count())
                               for lv, w in zip(levels, res_walks))
    found = [lv for lv in levels if lv.inner is not None]
    if outer is None:
        lv = levels[0]
        if lv.inner is None:
            stop = f"no feasible {inner} in [{x_lo:g}, {x_hi:g}]: the region holds no feasible value"
            res = SearchResult(inner, None, None, None, [], levels, stop, warnings, False, cost.runs)
        else:
            stop = (f"bisection of {inner} in [{x_lo:g}, {x_hi:g}] to a relative width of {inner_rtol:g} "
                    f"(one parameter)")
            res = SearchResult(inner, None, {inner: lv.inner}, lv.row, _binding(lv), levels, stop, warnings,
                               False, cost.runs)
        res.rounds = cost
        return res
    if how == "infeasible":
        z = levels[-1].outer
        stop = (f"no feasible {inner} in [{x_lo:g}, {x_hi:g}] at {outer} = {z:g}"
                + ("" if found else ": the region holds no feasible pair"))
    elif how == "unchanged":
        floors = ", ".join(f"{m} {a:g}" for m, a in (response_atol or {}).items() if a > 0)
        stop = (f"the response ({', '.join(response)}) changed by less than {response_rtol:g} (relative)"
                + (f" or less than its absolute floor ({floors})" if floors else "")
                + " for two consecutive pairs")
    else:
        stop = f"reached max_outer = {max_outer} halvings of {outer}"
    if not found:
        res = SearchResult(inner, outer, None, None, [], levels, stop, warnings, warm_start, cost.runs)
        res.rounds = cost
        return res
    best = levels[_best_index(res_walks, how)]
    if not per_level_guard and best.below is not None:
        walks[levels.index(best)].check_guard(inner, outer, best.inner, warnings)
    res = SearchResult(inner, outer, {inner: best.inner, outer: best.outer}, best.row, _binding(best), levels,
                       stop, warnings, warm_start, cost.runs)
    res.rounds = cost
    return res


def _plan_round(walks: list[_Walk], walk: Callable[[int], _Walk], first: int, n_levels: int, workers: int,
                hints: Sequence[float], guard: bool) -> list[tuple[int, float, bool]]:
    """The points of the next round, (level, inner value), at most ``workers``: levels in order from the
    first one not answered, each taking what it needs (a predicted level 2 + 3 guard points, an answered
    one its guard), a level without prediction a share of the round for its k-section; up to
    ``max(2, workers // 4)`` levels past the first (levels past the stop rule are speculative)."""
    todo: list[tuple[int, float, bool]] = []
    budget = workers
    lookahead = max(2, workers // 4)
    for k in range(first, min(n_levels, first + lookahead + 1)):
        if budget <= 0:
            break
        w = walk(k)
        if w.answered() and not (guard and w.answer() is not None and w.walk()[0] == "cell"
                                 and w.guard_set() is None):
            continue
        preds = _predictions(walks, k) + [float(h) for h in hints]
        _, a, b = w.walk()
        share = budget
        if not w.answered() and not any(a < p <= b for p in preds):
            # no prediction: the first such level takes most of the round, the next ones what is left
            share = budget if k == first and workers < 6 else max(3, (2 * budget) // 3)
        pts = w.requests(min(share, budget), preds, guard)
        todo += [(k, x, g) for x, g in pts]
        budget -= len(pts)
    return todo


def _best_index(walks: list[_Walk], how: str) -> int:
    """Index of the answer among the result's levels: the first of the final unchanged run (two
    levels back from the last), else the last feasible level."""
    feasible = [i for i, w in enumerate(walks) if w.answer() is not None]
    if how == "unchanged":
        return feasible[-2]
    return feasible[-1]


def _predictions(walks: list[_Walk], k: int) -> list[float]:
    """Answers of other answered levels, nearest first (lower levels before higher at equal distance)."""
    out = []
    for j in sorted(range(len(walks)), key=lambda j: (abs(j - k), j > k)):
        if j != k and walks[j].answered() and walks[j].answer() is not None and walks[j].answer() not in out:
            out.append(walks[j].answer())
    return out
