"""Metrics taken from sampled outputs: how much the sampling can move them, and how to refine it.

An FMU without monitors (a vendor export) gives its outputs only at the communication points, every
``scenario.step`` = h seconds. A peak (``reduce: max``, ``min``, ``max_abs``) is then the largest *sample*,
not the largest value: the true peak at t* lies within h/2 of the nearest sample, so for a smooth peak the
sampled one is low by at most |y''|/2·(h/2)² = **h²/8·|y''|**. A settling time (``reduce: settle``) is the
first sample inside the band: up to **one interval h** late, unless a return outside the band hides
between two later samples (refinement looks for those too: :func:`hidden_excursions`). Means and final
values are not affected this way (a mean is a trapezoid integral, a final value is sampled exactly).

``scenario.refine_peaks`` resolves both: after each run, the intervals next to the peak sample and the one
before the settling sample are re-run with ``refine_factor`` (f) times finer communication steps (one
more run of the FMU with a non-uniform grid of communication points; a model exchange FMU, or one that
cannot change its step, is re-run with the finer step throughout). The bound then shrinks by f², the
settling time's resolution by f. :func:`sampling_check` measures both against a run sampled much finer
throughout (the bound holds only for the peak the samples show, not for a narrower one between two samples
elsewhere), for the report.
"""
from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from fmusa.runs.metrics import PEAK_REDUCTIONS, SAMPLED_REDUCTIONS, MetricRule, peak_index, reduce_series, settle_index

__all__ = ["refine_intervals", "hidden_excursions", "refined_times", "refine_run", "peak_curvature", "sampling_check"]


def refine_intervals(t: np.ndarray, data: np.ndarray, rules: Sequence[MetricRule]) -> list[int]:
    """Indices i of the sampling intervals [t[i], t[i+1]] that can hold a true peak or settling time the
    samples missed: the two intervals next to each peak sample, the one before each settling sample."""
    n = len(t)
    out: set[int] = set()
    for r in rules:
        x = data[:, r.column]
        if r.reduce in PEAK_REDUCTIONS:
            k = peak_index(x, r.raw_reduce)
            out.update(i for i in (k - 1, k) if 0 <= i < n - 1)
        elif r.reduce == "settle":
            k = settle_index(x, r.settle_tol)
            if k is not None and k > 0:
                out.add(k - 1)
            if k is not None:
                out.update(hidden_excursions(t, x, r.settle_tol, k))
    return sorted(out)


#: how much the sampled curvature is trusted: a hump between two samples is judged with twice its estimate
CURVATURE_MARGIN = 2.0


def hidden_excursions(t: np.ndarray, x: np.ndarray, tol: float, start: int) -> list[int]:
    """Intervals from sample ``start`` on that can hide a return outside the band |x| <= tol between two
    samples inside it: where |x| is concave, a hump between samples rises above their chord by at most
    |x''|·h²/8 (|x''| from the second differences, with a margin). Refining only the interval before the
    settling sample would miss such a late excursion, and the settling time with it."""
    t = np.asarray(t, dtype=float)
    a = np.abs(np.asarray(x, dtype=float))
    n = len(t)
    if n < 3 or start >= n - 1:
        return []
    h = np.diff(t)
    slope = np.diff(a) / h
    concave = np.zeros(n)
    concave[1:-1] = np.maximum(-2.0 * np.diff(slope) / (h[:-1] + h[1:]), 0.0)   # -a'' where a is concave
    bend = np.maximum(concave[:-1], concave[1:])                                  # per interval, both ends
    rise = CURVATURE_MARGIN * bend * h ** 2 / 8.0
    top = np.maximum(a[:-1], a[1:]) + rise
    idx = np.flatnonzero(top > tol)
    return [int(i) for i in idx if i >= start]


def refined_times(t: np.ndarray, intervals: Sequence[int], factor: int) -> np.ndarray:
    """The sampling times ``t`` with each interval in ``intervals`` split into ``factor`` equal steps."""
    pieces = [np.asarray(t, dtype=float)]
    inner = np.arange(1, factor) / factor
    for i in intervals:
        a, b = float(t[i]), float(t[i + 1])
        pieces.append(a + (b - a) * inner)
    return np.sort(np.concatenate(pieces))


def _variable_steps(runner) -> bool:
    """Whether the FMU takes communication steps of changing length (co-simulation with
    canHandleVariableCommunicationStepSize); otherwise refinement re-runs with the fine step throughout."""
    if runner.is_model_exchange:
        return False
    cs = getattr(runner.model_description, "coSimulation", None)
    return bool(getattr(cs, "canHandleVariableCommunicationStepSize", False))


_FINE_PLANS: dict = {}


def _fine_plan(spec, plan, factor: int, throughout: bool = False):
    """The RunPlan of the finer re-runs on ``plan``'s FMU instance, made once per spec and factor. ``uniform``
    says whether it samples at step/factor throughout (always so with ``throughout``; else only for an FMU
    that cannot vary its step, and its ``times`` are set per run)."""
    key = (spec, factor, id(plan.runner), throughout)
    fp = _FINE_PLANS.get(key)
    if fp is None or fp.runner is not plan.runner:
        from fmusa.fmi.plans import RunPlan
        uniform = throughout or not _variable_steps(plan.runner)
        step = max(spec.step / factor, spec.stop_time / 5e4) if uniform else None
        fp = RunPlan(plan.runner, spec.varied, dict(spec.fixed), spec.outputs, spec.stop_time, step,
                     dict(spec.inputs))
        fp.uniform = uniform
        _FINE_PLANS[key] = fp
    return fp


def fine_run(spec, plan, fmu_values: Sequence[float], t: np.ndarray, data: np.ndarray,
             rules: Sequence[MetricRule], factor: int, throughout: bool = False
             ) -> tuple[np.ndarray, np.ndarray] | None:
    """Re-run with ``factor`` times finer sampling where ``rules`` take their values (all of the run for an
    FMU that cannot vary its step, or with ``throughout``): (times, outputs), or None when nothing needs
    refining."""
    fp = _fine_plan(spec, plan, factor, throughout)
    if not fp.uniform:
        intervals = refine_intervals(t, data, rules)
        if not intervals:
            return None
        fp.times = refined_times(t, intervals, factor)
    return fp.times, fp(list(fmu_values))


def refine_run(spec, plan, fmu_values: Sequence[float], data: np.ndarray, metrics: np.ndarray) -> np.ndarray:
    """``metrics`` of one run with its peaks and settling times taken from a re-run sampled
    ``spec.refine_factor`` times finer around them (``scenario.refine_peaks``); the other metrics keep their
    values from the run at the study's step."""
    idx = [k for k, r in enumerate(spec.rules) if r.reduce in SAMPLED_REDUCTIONS]
    if not idx or spec.step is None or len(plan.times) < 2:
        return metrics
    rules = [spec.rules[k] for k in idx]
    fine = fine_run(spec, plan, fmu_values, plan.times, data, rules, spec.refine_factor)
    if fine is None:
        return metrics
    redo = reduce_series(fine[0], fine[1], rules)
    out = np.array(metrics, dtype=float)
    out[idx] = redo
    return out


def peak_curvature(t: np.ndarray, x: np.ndarray, reduce: str) -> tuple[float, float]:
    """(|y''| at the peak sample, the local sampling interval h there), from the peak sample and its two
    neighbours (the three samples nearest the end for a peak at the end); h²/8·|y''| bounds how far the
    sampled peak can lie below the true one."""
    t = np.asarray(t, dtype=float)
    x = np.asarray(x, dtype=float)
    if len(t) < 3:
        return math.nan, float(t[-1] - t[0]) if len(t) > 1 else math.nan
    k = peak_index(x, reduce)
    y = np.abs(x) if reduce == "max_abs" else x
    i = min(max(k, 1), len(t) - 2)
    h1, h2 = t[i] - t[i - 1], t[i + 1] - t[i]
    d2 = 2.0 * ((y[i + 1] - y[i]) / h2 - (y[i] - y[i - 1]) / h1) / (h1 + h2)
    return abs(float(d2)), float(max(h1, h2) if 0 < k < len(t) - 1 else (h1 if k == 0 else h2))


def sampling_check(spec, plan, fmu_values: Sequence[float], reference_factor: int = 100) -> list[dict]:
    """For one run as the study makes it (with ``refine_peaks`` if set): every peak or settling metric, its
    sampled value, the sampling bound (h²/8·|y''| for a peak, one interval for a settling time, in the
    metric's unit), and its value from a reference run sampled ``reference_factor`` times finer still
    throughout the run (at most 50,000 samples), so that a peak between two samples far from the sampled one
    is found too. Raises what the FMU raises."""
    data = plan(list(fmu_values))
    t = plan.times
    metrics = reduce_series(t, data, spec.rules)
    grid_t, grid_data = t, data
    factor = 1
    if spec.refine_factor:
        factor = spec.refine_factor
        metrics = refine_run(spec, plan, fmu_values, data, metrics)
        rules = [r for r in spec.rules if r.reduce in SAMPLED_REDUCTIONS]
        fine = fine_run(spec, plan, fmu_values, t, data, rules, factor)
        if fine is not None:
            grid_t, grid_data = fine
    rules = [r for r in spec.rules if r.reduce in SAMPLED_REDUCTIONS]
    ref = fine_run(spec, plan, fmu_values, t, data, rules, factor * reference_factor, throughout=True)
    ref_vals = reduce_series(ref[0], ref[1], rules) if ref is not None else metrics[
        [spec.rules.index(r) for r in rules]]
    out = []
    for r, ref_v in zip(rules, ref_vals):
        k = spec.rules.index(r)
        x = grid_data[:, r.column]
        row = {"metric": r.name, "reduce": r.reduce, "value": float(metrics[k]), "reference": float(ref_v),
               "step": float(spec.step), "factor": factor}
        if r.reduce in PEAK_REDUCTIONS:
            d2, h = peak_curvature(grid_t, x, r.raw_reduce)
            row.update(curvature=d2 * abs(r.scale), h=h, bound=h * h / 8 * d2 * abs(r.scale))
        else:
            k_s = settle_index(x, r.settle_tol)
            h = float(grid_t[k_s] - grid_t[k_s - 1]) if k_s else (0.0 if k_s == 0 else math.nan)
            row.update(curvature=math.nan, h=h, bound=h * abs(r.scale))
        row["error"] = abs(row["value"] - row["reference"])
        out.append(row)
    return out
