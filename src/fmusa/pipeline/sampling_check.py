"""After the stages: how much the output sampling moves the metrics taken from samples, measured on a few runs.

A study whose metrics take a peak or a settling time from outputs sampled every ``scenario.step`` gets
``summary["sampling"]``: the step, the refinement factor, and per checked run and metric the sampled value,
the bound h²/8·|y''| (one interval for a settling time) and the value from a re-run sampled 100 times finer
(:func:`fmusa.runs.refine.sampling_check`). The report renders it; it runs no FMU itself.
"""
from __future__ import annotations

import math
from typing import Mapping

import numpy as np
import pandas as pd

from fmusa.fmi.plans import RunPlan
from fmusa.runs.metrics import SAMPLED_REDUCTIONS
from fmusa.runs.refine import sampling_check
from fmusa.runs.spec import PlanSpec, runner_for

__all__ = ["sampling_summary", "check_points"]


def check_points(names: list[str], runs: pd.DataFrame, optimum: Mapping | None, max_runs: int) -> list[dict]:
    """The optimum (when the search found one) and runs spread evenly over the successful ones."""
    ok = runs[runs["status"] == "ok"] if len(runs) and "status" in runs else runs.iloc[0:0]
    picks: list[dict] = []
    if optimum and all(n in optimum for n in names):
        picks.append({n: float(optimum[n]) for n in names})
    if not len(ok):
        return picks
    for i in np.unique(np.linspace(0, len(ok) - 1, max_runs).round().astype(int)):
        pt = {n: float(ok.iloc[i][n]) for n in names}
        if pt not in picks and len(picks) < max_runs:
            picks.append(pt)
    return picks


def _checks_at(spec: PlanSpec, plan: RunPlan, study, pt: dict, notes: list[str]) -> list[dict]:
    values = [study.parameters[n].to_fmu(pt[n]) for n in pt]
    try:
        rows = sampling_check(spec, plan, values)
    except Exception as exc:  # noqa: BLE001 - a failed run is reported, not fatal
        notes.append(f"Sampling check at {pt}: the run failed: {str(exc).splitlines()[0][:200]}")
        return []
    out = []
    for r in rows:
        if math.isnan(r["value"]) and math.isnan(r["reference"]):
            continue   # e.g. a settling time where the run does not settle: nothing sampled
        within = r["error"] <= r["bound"] * (1 + 1e-9) + 1e-300 if math.isfinite(r["bound"]) else None
        out.append({**r, "point": dict(pt), "within_bound": within})
    return out


def sampling_summary(study, runs: pd.DataFrame, optimum: Mapping | None, spec: PlanSpec,
                     max_runs: int = 5) -> dict | None:
    """``summary["sampling"]`` for a study with sampled peak or settling metrics (None otherwise)."""
    sc = study.scenario
    sampled = [m for m in study.metrics.values() if m.reduce in SAMPLED_REDUCTIONS]
    if sc.step is None or not sampled or not len(runs) or "status" not in runs:
        return None
    picks = check_points(list(study.parameters), runs, optimum, max_runs)
    if not picks:
        return None
    f = sc.refine_factor if sc.refine_peaks else 1
    out = {"step": sc.step, "refine_factor": f if sc.refine_peaks else None, "interval_at_peaks": sc.step / f,
           "largest_relative_difference": math.nan, "checks": [], "notes": []}
    try:
        runner = runner_for(spec)
    except Exception as exc:  # noqa: BLE001 - the study's results stand without the measurement
        out["notes"].append(f"The sampling check could not load the FMU: {type(exc).__name__}: {exc}")
        return out
    try:
        plan = RunPlan(runner, spec.varied, dict(spec.fixed), spec.outputs, spec.stop_time, spec.step,
                       dict(spec.inputs))
        for pt in picks:
            out["checks"] += _checks_at(spec, plan, study, pt, out["notes"])
    finally:
        runner.close()
    out["largest_relative_difference"] = max((c["error"] / abs(c["reference"]) for c in out["checks"]
                                              if c["reference"]), default=math.nan)
    return out
