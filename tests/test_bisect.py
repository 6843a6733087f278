"""fmusa.analysis.bisect, the package's one bisection: smallest feasible value of a monotone predicate
(cold and warm-started) and the crossing of a monotone function, on closed-form functions (no FMU)."""
from __future__ import annotations

import math

import pytest

from fmusa.analysis.bisect import Boundary, crossing, narrow_enough, smallest_feasible, smallest_feasible_from

BOUNDARY = 411.0 / 5e-4          # c with F / c = eps_y: 822000


def counted(f):
    """f with a list of the points it was called at."""
    calls: list[float] = []

    def g(x: float):
        calls.append(x)
        return f(x)
    g.calls = calls
    return g


def feasible_c(c: float) -> bool:
    return 411.0 / c <= 5e-4


@pytest.mark.parametrize("midpoint", ["linear", "geometric"])
def test_smallest_feasible_brackets_the_boundary_within_rtol(midpoint):
    test = counted(feasible_c)
    b = smallest_feasible(test, 1e5, 1e7, rtol=1e-4, midpoint=midpoint)
    assert b.status == "bracketed"
    assert b.below < BOUNDARY <= b.value and narrow_enough(b.below, b.value, 1e-4)
    assert (b.result, b.below_result) == (True, False)
    assert b.evaluations == len(test.calls) == len(set(test.calls))      # no point twice
    assert test.calls[:2] == [1e7, 1e5]                                  # hi first, then lo


def test_module_docstring_example():
    b = smallest_feasible(lambda c: 411.0 / c <= 5e-4, 1e5, 1e7, rtol=1e-4)
    assert b.status == "bracketed" and 822000 <= b.value <= 822000 * (1 + 1e-4) and b.evaluations == 19
    assert smallest_feasible_from(lambda c: 411.0 / c <= 5e-4, 822050.0, 1e5, 1e7, rtol=1e-4).evaluations == 2
    assert crossing(lambda t: t * t, 2.0, 0.0, 4.0, rtol=1e-9) == pytest.approx(math.sqrt(2), rel=1e-9)


def test_linear_midpoints_and_stop_rule_are_the_papers():
    """The default search's lattice: (lo + hi) / 2 until hi - lo <= rtol·hi, from the region's bounds."""
    test = counted(feasible_c)
    b = smallest_feasible(test, 390625.0, 9765625.0, rtol=1e-3, at_lo=False, at_hi=True)
    assert b.value == 822067.2607421875 and b.evaluations == 14     # + 2 ends + 3 guard = 19 a level
    lo, hi = 390625.0, 9765625.0
    for x in test.calls:
        assert x == 0.5 * (lo + hi)
        lo, hi = (lo, x) if feasible_c(x) else (x, hi)


def test_ends_given_or_failing():
    test = counted(feasible_c)
    b = smallest_feasible(test, 1e5, 5e5)                   # nothing feasible: lo is never run
    assert (b.status, b.value, b.below, b.evaluations, test.calls) == ("infeasible_at_hi", None, 5e5, 1, [5e5])
    b = smallest_feasible(feasible_c, 1e6, 1e7)
    assert (b.status, b.value, b.below, b.evaluations) == ("feasible_at_lo", 1e6, None, 2)
    b = smallest_feasible(feasible_c, 1e6, 1e7, at_lo=True, at_hi=True)
    assert b.evaluations == 0 and b.status == "feasible_at_lo"
    # results may be rows: `feasible` reads the verdict
    b = smallest_feasible(lambda c: {"c": c, "ok": feasible_c(c)}, 1e5, 1e7, feasible=lambda r: r["ok"])
    assert b.result == {"c": b.value, "ok": True} and b.below_result["ok"] is False
    with pytest.raises(ValueError, match="empty"):
        smallest_feasible(feasible_c, 2.0, 1.0)
    with pytest.raises(ValueError, match="lo > 0"):
        smallest_feasible(feasible_c, 0.0, 1.0, midpoint="geometric")


def test_bisection_ends_when_floats_run_out():
    b = smallest_feasible(lambda x: x >= 0.0, -1.0, 0.0, rtol=0.0)   # rtol·max(|lo|, |hi|) -> 0
    assert b.status == "bracketed" and b.value == 0.0 and b.evaluations < 1200


@pytest.mark.parametrize("guess, most", [
    (BOUNDARY, 2),                  # the boundary has not moved: the guess and guess·(1 - rtol)
    (BOUNDARY * 1.0005, 2),         # within rtol above
    (BOUNDARY * (1 - 5e-4), 2),     # within rtol below: guess·(1 + rtol) is feasible
    (BOUNDARY * 2.0, 18),           # moved by a factor 2: grow the bracket downwards, then bisect
    (BOUNDARY / 2.0, 18),
    (2e5, 20),
    (9e6, 20),
])
def test_warm_start_finds_the_same_boundary(guess, most):
    test = counted(feasible_c)
    b = smallest_feasible_from(test, guess, 1e5, 1e7, rtol=1e-3)
    assert b.status == "bracketed" and b.below < BOUNDARY <= b.value
    assert b.value <= BOUNDARY * (1 + 1e-3)
    assert b.evaluations == len(test.calls) == len(set(test.calls)) <= most
    cold = smallest_feasible(feasible_c, 1e5, 1e7, rtol=1e-3)
    assert abs(b.value - cold.value) <= 1e-3 * cold.value


def test_warm_start_at_the_bracket_ends():
    b = smallest_feasible_from(feasible_c, 5e6, 1e6, 1e7)        # feasible down to lo
    assert (b.status, b.value) == ("feasible_at_lo", 1e6) and b.evaluations <= 6
    b = smallest_feasible_from(feasible_c, 2e5, 1e5, 5e5)        # infeasible up to hi
    assert (b.status, b.value, b.below) == ("infeasible_at_hi", None, 5e5) and b.evaluations <= 6
    b = smallest_feasible_from(feasible_c, 1e9, 1e5, 1e7)        # a guess outside is clipped to the bracket
    assert b.status == "bracketed" and b.below < BOUNDARY <= b.value
    with pytest.raises(ValueError, match="growth"):
        smallest_feasible_from(feasible_c, 1e6, 1e5, 1e7, growth=1.0)


def test_crossing_of_a_monotone_function():
    assert crossing(lambda x: x ** 3, 8.0, 0.0, 10.0, rtol=1e-10) == pytest.approx(2.0, rel=1e-9)
    # decreasing, geometric midpoints over decades: F / c = eps at c = F / eps
    x = crossing(lambda c: 411.0 / c, 5e-4, 1e3, 1e11, rtol=1e-8, midpoint="geometric")
    assert x == pytest.approx(BOUNDARY, rel=1e-8)
    assert crossing(lambda x: x, 5.0, 0.0, 1.0) is None              # not bracketed
    assert crossing(lambda x: math.nan, 0.5, 0.0, 1.0) is None       # not finite at the ends
    assert crossing(lambda x: x, 0.0, 0.0, 1.0) == 0.0               # at the lower end
    assert crossing(lambda x: -x, -0.25, 0.0, 1.0, increasing=False) == pytest.approx(0.25, rel=1e-5)


def test_boundary_is_plain_data():
    b = Boundary(1.0, True, 0.5, False, 3, "bracketed")
    assert (b.value, b.below, b.evaluations) == (1.0, 0.5, 3)
