"""The FMU runs of a diagnosis: counted, and bounded by a budget the user sets.

A run is one simulation of one experiment (initialise the FMU, step through the measured drive). Every run of
a diagnosis passes :meth:`RunBudget.take` first, in whichever process it happens: the budget is one counter
shared by the parent and its worker processes, so the total never exceeds the limit however the fits are
spread. A fit that reaches the limit stops (:class:`BudgetExhausted`) and is reported as left out
(:class:`LeftOut`, with the runs it spent), never as a result.
"""
from __future__ import annotations

import multiprocessing as mp
from dataclasses import dataclass, field

__all__ = ["BudgetExhausted", "RunBudget", "LeftOut", "install", "current"]


class BudgetExhausted(Exception):
    """The run budget of the diagnosis ended before this run (not a RuntimeError: a failed simulation is
    one, and the least-squares loop backs off from those instead of stopping)."""


class RunBudget:
    """A run counter shared across processes, with an optional limit.

    Made in the parent (``RunBudget(limit)``) and handed to worker processes at their start
    (:meth:`shared`, :func:`install`): a synchronized value passes only by inheritance, not by pickling."""

    def __init__(self, limit=None, _value=None) -> None:
        # ``limit`` may be a shared value too (-1: none): a worker of a pool kept across diagnoses
        # (:mod:`fitcache`) reads the limit of the diagnosis it works for at each run
        if isinstance(limit, int) and limit < 1:
            raise ValueError(f"the run budget must be at least 1, got {limit}")
        self._limit = limit
        self._value = _value if _value is not None else mp.get_context("spawn").Value("q", 0)

    @property
    def limit(self) -> int | None:
        if self._limit is None or isinstance(self._limit, int):
            return self._limit
        v = int(self._limit.value)
        return None if v < 0 else v

    @property
    def used(self) -> int:
        """Runs taken so far, by every process."""
        return int(self._value.value)

    @property
    def exhausted(self) -> bool:
        return self.limit is not None and self.used >= self.limit

    def take(self, n: int = 1) -> None:
        """Count ``n`` runs about to start, or raise BudgetExhausted when they would pass the limit."""
        with self._value.get_lock():
            limit = self.limit
            if limit is not None and self._value.value + n > limit:
                raise BudgetExhausted(f"the run budget of {limit} FMU runs ended")
            self._value.value += n

    def set_used(self, n: int) -> None:
        """Set the count (a pool's counter lent to this budget gives its count back, :mod:`fitcache`)."""
        self._value.value = int(n)

    def shared(self) -> tuple:
        """What a worker process needs to share this counter (for :func:`install`, as initializer args)."""
        return (self.limit, self._value)


#: the budget of this process (set in the parent by the diagnosis, in a worker by its initializer)
_CURRENT: RunBudget | None = None


def install(limit: int | None, value) -> None:
    """Make the shared counter this process's budget (a worker process's initializer)."""
    global _CURRENT
    _CURRENT = RunBudget(limit, value)


def current() -> RunBudget | None:
    """This process's budget, or None when nothing counts (a fit run on its own)."""
    return _CURRENT


def set_current(budget: RunBudget | None) -> RunBudget | None:
    """Make ``budget`` this process's budget; returns the one it replaces."""
    global _CURRENT
    old, _CURRENT = _CURRENT, budget
    return old


def take(runs: dict[str, int], stage: str, n: int) -> None:
    """Take ``n`` runs from this process's budget (BudgetExhausted when it has ended) and count them in
    ``runs`` under ``stage``: the one bookkeeping of the FMU runners and the coupled runner."""
    b = current()
    if b is not None:
        b.take(n)
    runs[stage] = runs.get(stage, 0) + n


@dataclass
class LeftOut:
    """A fit the budget ended: its name and the runs it had spent (by stage) when it stopped."""
    effect: str
    runs: dict[str, int] = field(default_factory=dict)
    reason: str = "the run budget ended"

    def summary(self) -> dict:
        return {"effect": self.effect, "runs": dict(self.runs), "reason": self.reason}
