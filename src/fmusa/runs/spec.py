"""What a worker needs to make runs (PlanSpec), what it gives back (RunResult), and a chunk of runs in this process."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from fmusa.fmi.info import Value
from fmusa.fmi.plans import RunPlan
from fmusa.fmi.runner import FMURunner
from fmusa.runs.metrics import MetricRule, reduce_series


# ---------------------------------------------------------------------- batches, pools, clusters
@dataclass(frozen=True)
class PlanSpec:
    """Everything a worker needs to build its RunPlan: plain data, picklable, hashable."""
    fmu_path: str
    varied: tuple[str, ...]                  # FMU variables
    scale: tuple[float, ...]                 # FMU value = scale * study value + offset
    offset: tuple[float, ...]
    fixed: tuple[tuple[str, Value], ...]
    inputs: tuple[tuple[str, float], ...]
    outputs: tuple[str, ...]
    stop_time: float
    step: float | None
    rules: tuple[MetricRule, ...]
    # how the FMU runs (fmu_options of the study); the defaults are a co-simulation FMU's own solver
    interface: str = "auto"                  # auto | co-simulation | model-exchange
    solver: str | None = None                # model exchange: CVode (None) or Euler
    relative_tolerance: float | None = None
    step_size: float | None = None
    # scenario.refine_peaks: peaks and settling times re-sampled this many times finer (fmusa.runs.refine)
    refine_factor: int | None = None


@dataclass
class RunResult:
    run_id: int
    values: tuple[float, ...]                # study values
    metrics: np.ndarray | None               # one per rule; None when the run failed
    status: str                              # "ok" | "failed"
    message: str
    seconds: float


#: This process's RunPlans, one per spec (each holds an instantiated FMU).
_WORKER_PLANS: dict[PlanSpec, RunPlan] = {}


def plan_for(spec: PlanSpec) -> RunPlan:
    """The calling process's RunPlan for ``spec``: one FMU instance per process and spec, reused."""
    plan = _WORKER_PLANS.get(spec)
    if plan is None:
        runner = FMURunner(spec.fmu_path, interface=spec.interface, solver=spec.solver,
                           relative_tolerance=spec.relative_tolerance, step_size=spec.step_size)
        plan = RunPlan(runner, spec.varied, dict(spec.fixed), spec.outputs, spec.stop_time, spec.step,
                       dict(spec.inputs))
        _WORKER_PLANS[spec] = plan
    return plan


def release_plan(spec: PlanSpec) -> None:
    """Forget this process's RunPlan for ``spec`` and free its FMU instance (before its files are deleted)."""
    plan = _WORKER_PLANS.pop(spec, None)
    if plan is not None:
        plan.runner.close()


def run_chunk(spec: PlanSpec, chunk: Sequence[tuple[int, tuple[float, ...]]]) -> list[RunResult]:
    """Run a chunk of parameter sets; a failing run is recorded with its reason and the rest go on."""
    import time

    plan = plan_for(spec)
    out = []
    for run_id, values in chunk:
        t0 = time.perf_counter()
        fmu_values = [s * x + o for s, x, o in zip(spec.scale, values, spec.offset)]
        try:
            data = plan(fmu_values)
            metrics = reduce_series(plan.times, data, spec.rules)
            if spec.refine_factor and type(plan) is RunPlan:
                from fmusa.runs.refine import refine_run
                metrics = refine_run(spec, plan, fmu_values, data, metrics)
            out.append(RunResult(run_id, tuple(values), metrics, "ok", "", time.perf_counter() - t0))
        except Exception as exc:  # the FMU's own error: record it, keep going
            msg = str(exc).strip().replace("\n", " | ")
            out.append(RunResult(run_id, tuple(values), None, "failed", msg[:2000], time.perf_counter() - t0))
    return out


