"""Metrics of one run from its outputs, and the constraints on them.

A metric reduces one FMU output over the run (the final value of a monitor the FMU keeps, or the max,
mean, … of the sampled output) in study units: metric = reduce(scale × output) + offset. A negative scale
flips the axis before the reduction, so ``max`` then takes the FMU's most negative sample and ``max_abs``
stays positive. Pure numpy: no FMU here.
"""
from __future__ import annotations

import math

from dataclasses import dataclass, replace
from typing import Iterable, Mapping, Sequence

import numpy as np

REDUCTIONS = ("final", "max", "min", "max_abs", "mean", "mean_abs", "settle")
#: Reductions whose value sits at one sample (a peak, a settling time): sampling can miss the true value,
#: and ``scenario.refine_peaks`` resolves them on a finer grid around that sample.
PEAK_REDUCTIONS = ("max", "min", "max_abs")
SAMPLED_REDUCTIONS = PEAK_REDUCTIONS + ("settle",)


@dataclass(frozen=True)
class MetricRule:
    """How one metric comes out of the sampled outputs; picklable, so workers can apply it."""
    name: str
    column: int             # index of the output in the sampled array
    reduce: str
    scale: float = 1.0
    offset: float = 0.0
    missing_below: float | None = None
    settle_tol: float | None = None      # ``settle``: the band |x| <= settle_tol (FMU units)

    @property
    def raw_reduce(self) -> str:
        """The reduction on the FMU's own values that gives the metric's sample: ``max`` of scale × x is
        ``min`` of x when the scale is negative."""
        return raw_reduction(self.reduce, self.scale)

    @property
    def factor(self) -> float:
        """What the raw reduced value is multiplied by: |scale| for the reductions of |x|."""
        return abs(self.scale) if self.reduce in ("max_abs", "mean_abs") else self.scale


def raw_reduction(reduce: str, scale: float) -> str:
    """The reduction of the FMU's values equal to ``reduce`` of scale × values (max and min swap places
    for a negative ``scale``)."""
    if scale < 0 and reduce in ("max", "min"):
        return "min" if reduce == "max" else "max"
    return reduce


def settle_index(x: np.ndarray, tol: float) -> int | None:
    """Index of the first sample from which |x| <= tol holds to the end; None when the last sample is
    outside the band (not settled)."""
    out = np.abs(np.asarray(x, dtype=float)) > tol
    if out[-1] or not np.all(np.isfinite(x)):
        return None
    bad = np.flatnonzero(out)
    return 0 if bad.size == 0 else int(bad[-1]) + 1


def peak_index(x: np.ndarray, reduce: str) -> int:
    """Index of the sample a peak reduction (max, min, max_abs) takes its value from."""
    x = np.asarray(x, dtype=float)
    return int(np.argmax(x) if reduce == "max" else np.argmin(x) if reduce == "min" else np.argmax(np.abs(x)))


def _time_mean(t: np.ndarray, x: np.ndarray) -> float:
    if len(t) < 2 or t[-1] <= t[0]:
        return float(x[-1])
    return float(np.trapezoid(x, t) / (t[-1] - t[0]))


def reduce_series(t: np.ndarray, values: np.ndarray, rules: Sequence[MetricRule]) -> np.ndarray:
    """Metric values of one run. ``values`` has one row per communication point (the last row is the
    end of the run) and one column per output."""
    out = np.empty(len(rules))
    for k, r in enumerate(rules):
        x = values[:, r.column]
        how = r.raw_reduce
        if how == "final":
            v = float(x[-1])
        elif how == "max":
            v = float(np.max(x))
        elif how == "min":
            v = float(np.min(x))
        elif how == "max_abs":
            v = float(np.max(np.abs(x)))
        elif how == "mean":
            v = _time_mean(t, x)
        elif how == "mean_abs":
            v = _time_mean(t, np.abs(x))
        elif how == "settle":   # the time since which |x| <= settle_tol, on the samples
            i = settle_index(x, r.settle_tol)
            v = float("nan") if i is None else float(t[i])
        else:  # pragma: no cover - the study loader rejects other names
            raise ValueError(f"unknown reduction {r.reduce!r}; use one of {', '.join(REDUCTIONS)}")
        if r.missing_below is not None and v < r.missing_below:
            v = float("nan")
        out[k] = r.factor * v + r.offset
    return out


def reduce_batch(t: np.ndarray, data: np.ndarray, rules: Sequence[MetricRule]) -> np.ndarray:
    """:func:`reduce_series` of many runs sampled at the same times ``t``: ``data`` has one block per run
    (runs × samples × outputs); one row of metrics per run. The order-free reductions (final, max, min,
    max_abs) and the mapping to study units are done with numpy over the batch, the others run by run, so
    every value equals :func:`reduce_series`'s bit for bit."""
    data = np.asarray(data, dtype=float)
    n = data.shape[0]
    out = np.empty((n, len(rules)))
    for k, r in enumerate(rules):
        x = data[:, :, r.column]
        how = r.raw_reduce
        if how == "final":
            v = x[:, -1].copy()
        elif how == "max":
            v = np.max(x, axis=1)
        elif how == "min":
            v = np.min(x, axis=1)
        elif how == "max_abs":
            v = np.max(np.abs(x), axis=1)
        else:   # time means and settling times: run by run, on each run's own block as reduce_series
            v = np.array([reduce_series(t, data[i], [replace(r, scale=1.0, offset=0.0, missing_below=None)])[0]
                          for i in range(n)], dtype=float)
        if r.missing_below is not None:
            v = np.where(v < r.missing_below, np.nan, v)
        out[:, k] = r.factor * v + r.offset
    return out


def metric_rules(metrics: Iterable, outputs: list[str]) -> list[MetricRule]:
    """Rules for the study's metrics, given the order of the outputs the FMU is asked for."""
    index = {name: i for i, name in enumerate(outputs)}
    return [MetricRule(m.name, index[m.output], m.reduce, m.scale, m.offset, m.missing_below,
                       getattr(m, "settle_tol", None)) for m in metrics]


def constraint_holds(c, x: float) -> bool:
    """Whether one run's metric value ``x`` passes constraint ``c``: :func:`constraint_table` for one run."""
    if math.isnan(x):
        return not (c.required or c.max is not None or c.min is not None)
    return (c.max is None or x <= c.max) and (c.min is None or x >= c.min)


def constraint_table(values: Mapping[str, np.ndarray], constraints: Iterable) -> dict[str, np.ndarray]:
    """Pass/fail of every constraint for every run (columns ``ok_<name>``) and ``feasible``."""
    table: dict[str, np.ndarray] = {}
    feasible = None
    for c in constraints:
        x = np.asarray(values[c.metric], dtype=float)
        ok = np.ones(x.shape, dtype=bool)
        if c.required or c.max is not None or c.min is not None:
            ok &= ~np.isnan(x)
        if c.max is not None:
            ok &= np.where(np.isnan(x), False, x <= c.max)
        if c.min is not None:
            ok &= np.where(np.isnan(x), False, x >= c.min)
        table[f"ok_{c.name}"] = ok
        feasible = ok if feasible is None else feasible & ok
    if feasible is not None:
        table["feasible"] = feasible
    return table
