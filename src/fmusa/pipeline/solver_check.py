"""After the stages: how far the FMU's own integration moves the metrics, measured on a few runs.

A co-simulation FMU integrates with its own solver between communication points, and some exports do so
crudely: OpenModelica's CS export takes one explicit Euler step per communication step, and at stiff points
of a grid it blows up while every run is ``ok``. So, like the sampling check, a few points (the optimum and
runs spread over the successful ones) are run again with the communication step halved, the tolerance
tightened tenfold, and, where the FMU also offers model exchange, through model exchange with fmpy's CVode
at a tight tolerance. Every metric that moves by more than the study's tolerance (``search.response_rtol``
and ``response_atol``, else 1e-3 relative) is flagged, with the advice that fits: a smaller
``scenario.step``, or ``fmu_options.interface: model-exchange``.

The runs go through :class:`~fmusa.runs.evaluator.Evaluator`, supervised as the study's own runs are, so an
FMU that crashes here costs the check, not the study. The report renders ``summary["fmu_steps"]``.
"""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Mapping

import numpy as np
import pandas as pd

from fmusa.errors import FmusaError
from fmusa.fmi.info import read_fmu_info, select_interface
from fmusa.fmi.runner import experiment_tolerance
from fmusa.pipeline.sampling_check import check_points
from fmusa.runs.evaluator import Evaluator
from fmusa.runs.spec import PlanSpec, RunBatch, release_plan

__all__ = ["solver_summary", "implausible_runs", "accuracy_verdict"]

#: fmpy's CVode tolerance when neither the study nor the FMU gives one.
_FMPY_CVODE_RTOL = 1e-5
#: What a co-simulation check tightens tenfold when neither the study nor the FMU gives a tolerance.
_CS_BASE_RTOL = 1e-4


def _variants(spec: PlanSpec, interface: str, info) -> list[tuple[str, PlanSpec, str]]:
    """(label, spec, advice when it moves a metric) of each rerun."""
    out = []
    half = spec.stop_time / 2 if spec.step is None else spec.step / 2
    # read at every halved step: a peak the study's sampling misses between two samples moves the metric too
    out.append(("communication step halved", replace(spec, step=half),
                "the FMU's result depends on the communication step: make scenario.step smaller until the "
                "metrics stop moving"))
    tol = spec.relative_tolerance or experiment_tolerance(info.model_description) or (
        _FMPY_CVODE_RTOL if interface == "model-exchange" else _CS_BASE_RTOL)
    out.append((f"tolerance {tol / 10:g} (tightened tenfold)", replace(spec, relative_tolerance=tol / 10),
                "the FMU's result depends on its solver tolerance: set fmu_options.relative_tolerance "
                "smaller (or the FMU's own tolerance parameter) until the metrics stop moving"))
    if interface == "co-simulation" and "model-exchange" in info.interfaces:
        rtol = min(tol / 100, 1e-6)
        out.append((f"model exchange (fmpy CVode, rtol {rtol:g})",
                    replace(spec, interface="model-exchange", solver=None, step_size=None, relative_tolerance=rtol),
                    "the FMU's own co-simulation solver disagrees with its model equations integrated "
                    "accurately: run it through fmu_options.interface: model-exchange, or a smaller "
                    "scenario.step"))
    return out


def _run(spec: PlanSpec, values: np.ndarray, workers: int, isolate: bool, timeout_s, scheduler=None) -> RunBatch:
    """The points ``values`` (study values) run on ``spec``, as many at a time as there are points and workers
    (one round for an FMU that costs seconds per run)."""
    batches: list[RunBatch] = []
    ev = Evaluator(spec, workers=max(1, min(workers, len(values))), scheduler=scheduler, isolate=isolate,
                   timeout_s=timeout_s)
    try:
        ev.map_batches((np.arange(len(values), dtype=np.int64), values), batches.append)
    finally:
        ev.close()
        release_plan(spec)
    return RunBatch.concat(batches)


def _tolerances(study) -> tuple[float, dict[str, float]]:
    s = study.stages.get("search")
    if s is None:
        return 1e-3, {}
    return float(s.response_rtol), dict(s.response_atol or {})


def _stored(runs: pd.DataFrame, names: list[str], values: np.ndarray, metrics: list[str]) -> RunBatch | None:
    """The study's own runs at ``values`` (each one ``ok`` in ``runs``), as the reference: they are what the
    study reported, and the reset check made them equal to runs on a fresh instance."""
    rows = []
    ok = runs[runs["status"] == "ok"] if "status" in runs else runs.iloc[0:0]
    for v in values:
        hit = ok
        for n, x in zip(names, v):
            hit = hit[hit[n].to_numpy(dtype=float) == float(x)]
        if not len(hit):
            return None
        rows.append(hit.iloc[0])
    n = len(rows)
    M = np.array([[float(r[m]) for m in metrics] for r in rows], dtype=float).reshape(n, len(metrics))
    return RunBatch(np.arange(n, dtype=np.int64), np.asarray(values, dtype=float), M, np.ones(n, bool),
                    np.zeros(n), {})


def _sampling_allowance(sampling: Mapping | None) -> dict[str, tuple[dict, float]]:
    """metric -> ({point key: sampling bound}, largest bound relative to its value), from the sampling check:
    how far a sampled peak may move when read at the halved step without being wrong."""
    out: dict[str, tuple[dict, float]] = {}
    for c in (sampling or {}).get("checks", []):
        b = c.get("bound")
        if b is None or not math.isfinite(b):
            continue
        at, rel = out.setdefault(c["metric"], ({}, 0.0))
        at[tuple(sorted(c["point"].items()))] = float(b)
        if c.get("value"):
            out[c["metric"]] = (at, max(rel, float(b) / abs(float(c["value"]))))
    return out


def solver_summary(study, runs: pd.DataFrame, optimum: Mapping | None, spec: PlanSpec, isolate: bool,
                   max_runs: int = 3, workers: int = 1, scheduler: str | None = None,
                   sampling: Mapping | None = None) -> dict | None:
    """``summary["fmu_steps"]``: each checked point, rerun each way, and how far each metric moved. ``spec``
    is best the study evaluator's :meth:`~fmusa.runs.evaluator.Evaluator.local_spec` (the FMU unpacked
    once). The halved step is read at every halved step, so a peak the study's samples miss moves its
    metric; a sampled peak that moves by no more than the sampling check's bound (``sampling``, the
    sampling summary: h²/8·|y''|, how low a smooth peak's sample may lie) is not flagged for it."""
    names = list(study.parameters)
    picks = check_points(names, runs, optimum, max_runs) if names else []
    if not picks:
        return None
    try:
        info = read_fmu_info(spec.fmu_path)
        interface = select_interface(info, spec.interface)
    except FmusaError as exc:
        return {"checks": [], "notes": [f"the FMU could not be read for the check: {exc}"], "flagged": []}
    rtol, atol = _tolerances(study)
    metrics = [r.name for r in spec.rules]
    values = np.array([[pt[n] for n in names] for pt in picks], dtype=float)
    timeout = study.execution.timeout_s
    out: dict = {"tolerance": rtol, "atol": atol, "interface": interface, "points": picks, "checks": [],
                 "notes": [], "flagged": [], "advice": [], "largest_relative": {}}
    base = _stored(runs, names, values, metrics)
    try:
        if base is None:
            base = _run(spec, values, workers, isolate, timeout, scheduler)
    except Exception as exc:  # noqa: BLE001 - the study's results stand without the measurement
        out["notes"].append(f"the check's reference runs failed: {type(exc).__name__}: {exc}")
        return out
    order = np.argsort(base.run_ids)
    allowance = _sampling_allowance(sampling)
    for label, vspec, advice in _variants(spec, interface, info):
        halved = vspec.step is not None and spec.step is not None and vspec.step < spec.step
        try:
            var = _run(vspec, values, workers, isolate, timeout, scheduler)
        except Exception as exc:  # noqa: BLE001
            out["notes"].append(f"{label}: the runs could not be made: {type(exc).__name__}: {exc}")
            continue
        vorder = np.argsort(var.run_ids)
        moved_here = False
        for i, pt in enumerate(picks):
            bi, vi = order[i], vorder[i]
            if not base.ok[bi]:
                continue
            if not var.ok[vi]:
                out["checks"].append({"point": pt, "variant": label, "metric": None, "value": None,
                                      "variant_value": None, "relative": None, "flagged": True,
                                      "note": f"the run failed: {var.messages.get(vi, '')[:300]}"})
                moved_here = True
                continue
            for j, m in enumerate(metrics):
                x, y = float(base.metrics[bi, j]), float(var.metrics[vi, j])
                if math.isnan(x) and math.isnan(y):
                    continue
                diff = abs(y - x) if math.isfinite(x) and math.isfinite(y) else math.inf
                rel = diff / abs(x) if x and math.isfinite(x) else (0.0 if diff == 0 else math.inf)
                allowed = atol.get(m, 0.0)
                if halved and m in allowance:      # a smooth peak's sample may move by its sampling bound
                    at, rel_bound = allowance[m]
                    allowed = max(allowed, at.get(tuple(sorted(pt.items())), rel_bound * abs(x)))
                flagged = bool(diff > rtol * abs(x) and diff > allowed)
                out["checks"].append({"point": pt, "variant": label, "metric": m, "value": x, "variant_value": y,
                                      "relative": rel, "flagged": flagged})
                out["largest_relative"][m] = max(out["largest_relative"].get(m, 0.0), rel)
                if flagged:
                    moved_here = True
                    if m not in out["flagged"]:
                        out["flagged"].append(m)
        if moved_here:
            out["advice"].append(f"{label}: {advice}")
    return out


def implausible_runs(runs: pd.DataFrame, metrics: list[str], decades: float = 6.0) -> list[dict]:
    """Successful runs whose value of a metric lies orders of magnitude beyond the rest (an FMU whose solver
    blew up reports a travel of 1e23 mm as ``ok``): more than ``decades`` decades above the upper quartile
    of that metric's magnitudes, with the interquartile spread of the magnitudes added, so that a metric
    that spans decades over the grid by design (y = F/c) is not flagged. An infinite value is flagged too."""
    if not len(runs) or "status" not in runs:
        return []
    ok = runs[runs["status"] == "ok"]
    ids = ok["run_id"].to_numpy() if "run_id" in ok else ok.index.to_numpy()
    out = []
    for m in metrics:
        if m not in ok:
            continue
        v = ok[m].to_numpy(dtype=float)
        x = np.abs(v)
        good = x[np.isfinite(x) & (x > 0)]
        if len(good) < 4:
            continue
        lg = np.log10(good)
        q1, q3 = np.percentile(lg, [25, 75])
        limit = q3 + (q3 - q1) + decades
        with np.errstate(divide="ignore", invalid="ignore"):
            bad = np.isinf(v) | (np.isfinite(v) & (x > 0) & (np.log10(np.where(x > 0, x, 1.0)) > limit))
        for k in np.flatnonzero(bad):
            out.append({"run": int(ids[k]), "metric": m, "value": float(v[k]), "typical_upper": float(10 ** q3),
                        "limit": float(10 ** limit)})
    return out


def accuracy_verdict(study, sampling: Mapping | None, steps: Mapping | None) -> dict | None:
    """``summary["accuracy"]`` when a check after the stages moved a metric a constraint reads: the sampling
    check (a run sampled much finer gives another value, beyond the sampling bound and the study's
    tolerance) or the FMU step check (a flagged metric). ``{"reliable": False, "metrics": [...],
    "warnings": [...]}``: the feasibility of every run, and so the optimum, rests on those metrics. None
    when no constrained metric moved."""
    constrained = {c.metric for c in study.constraints}
    rtol, atol = _tolerances(study)
    warnings: list[str] = []
    metrics: list[str] = []
    for c in (sampling or {}).get("checks", []):
        m = c["metric"]
        if m not in constrained or c.get("within_bound") is not False:
            continue
        err, ref = float(c["error"]), float(c["reference"])
        if not (err > rtol * abs(ref) and err > atol.get(m, 0.0)):
            continue
        pt = ", ".join(f"{k} = {v:.6g}" for k, v in c["point"].items())
        warnings.append(f"metric '{m}' at {pt}: {c['value']:.6g} from samples every {c['step'] / c['factor']:g} s, "
                        f"{ref:.6g} from a run sampled {100:g} times finer (sampling bound {c['bound']:.3g}): "
                        f"the peak lies between samples; make scenario.step smaller or set scenario.refine_peaks")
        if m not in metrics:
            metrics.append(m)
    for c in (steps or {}).get("checks", []):
        m = c.get("metric")
        if not c.get("flagged") or (m is not None and m not in constrained):
            continue
        pt = ", ".join(f"{k} = {v:.6g}" for k, v in c["point"].items())
        if m is None:
            warnings.append(f"at {pt}, {c['variant']}: {c.get('note', 'the run failed')}")
            continue
        warnings.append(f"metric '{m}' at {pt}: {c['value']:.6g}, with the {c['variant']} {c['variant_value']:.6g} "
                        f"({100 * c['relative']:.3g} %, beyond the study's tolerance {rtol:g})")
        if m not in metrics:
            metrics.append(m)
    if not warnings:
        return None
    return {"reliable": False, "metrics": metrics, "warnings": warnings}
