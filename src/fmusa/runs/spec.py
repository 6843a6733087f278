"""What a worker needs to make runs (PlanSpec), what it gives back (RunResult for one run, RunBatch for many, as
arrays), and a batch of runs in this process (run_batch; run_chunk gives RunResults)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from fmusa.fmi.info import Value
from fmusa.fmi.plans import RunPlan
from fmusa.fmi.runner import FMURunner
from fmusa.runs.metrics import MetricRule, reduce_batch, reduce_series


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
    # how an instance returns to its state right after instantiation between runs (fmusa.runs.preflight
    # finds which one the FMU needs): reset | snapshot | fresh
    reuse: str = "reset"
    # metrics from every ``subsample``-th communication point only (and the last): a run with a finer
    # communication step read at the study's own sampling (fmusa.pipeline.solver_check)
    subsample: int = 1


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


def runner_for(spec: PlanSpec) -> FMURunner:
    """A new FMURunner on ``spec``'s FMU with the study's ``fmu_options``: for the runs a plan makes, and for
    runs outside the run store (a finer sampling, another scenario). Close it (or use ``with``)."""
    return FMURunner(spec.fmu_path, interface=spec.interface, solver=spec.solver,
                     relative_tolerance=spec.relative_tolerance, step_size=spec.step_size, reuse=spec.reuse,
                     check_reuse=False)      # the study's pre-flight check chose spec.reuse


#: The last spec plan_for was asked for and its plan: hashing a spec (every field) costs more than a cheap run.
_LAST_PLAN: list = [None, None]


def plan_for(spec: PlanSpec) -> RunPlan:
    """The calling process's RunPlan for ``spec``: one FMU instance per process and spec, reused."""
    if spec is _LAST_PLAN[0]:
        return _LAST_PLAN[1]
    plan = _WORKER_PLANS.get(spec)
    if plan is None:
        runner = runner_for(spec)
        plan = RunPlan(runner, spec.varied, dict(spec.fixed), spec.outputs, spec.stop_time, spec.step,
                       dict(spec.inputs))
        _WORKER_PLANS[spec] = plan
    _LAST_PLAN[:] = [spec, plan]
    return plan


def release_plan(spec: PlanSpec) -> None:
    """Forget this process's RunPlan for ``spec`` and free its FMU instance (before its files are deleted)."""
    plan = _WORKER_PLANS.pop(spec, None)
    if _LAST_PLAN[0] is not None and _LAST_PLAN[0] == spec:
        _LAST_PLAN[:] = [None, None]
    if plan is not None:
        plan.runner.close()


@dataclass
class RunBatch:
    """Many runs as arrays, one row each: what a worker sends back for a chunk (one message, not one
    object per run). ``metrics`` is NaN on the rows of failed runs; ``messages`` holds the reasons of the
    failed runs only, by row."""
    run_ids: np.ndarray                      # int64 (n,)
    values: np.ndarray                       # float (n, k): study values
    metrics: np.ndarray                      # float (n, m)
    ok: np.ndarray                           # bool (n,)
    seconds: np.ndarray                      # float (n,)
    messages: dict[int, str]

    def __len__(self) -> int:
        return len(self.run_ids)

    @classmethod
    def failed(cls, run_ids, values, n_metrics: int, reason: str, seconds: float = 0.0) -> "RunBatch":
        """Every run of ``run_ids``/``values`` failed with ``reason``."""
        ids = np.asarray(run_ids, dtype=np.int64).reshape(-1)
        n = len(ids)
        vals = np.asarray(values, dtype=float).reshape(n, -1)
        return cls(ids, vals, np.full((n, n_metrics), np.nan), np.zeros(n, bool), np.full(n, float(seconds)),
                   {i: reason for i in range(n)})

    @classmethod
    def from_results(cls, results: Sequence[RunResult], n_metrics: int, n_values: int) -> "RunBatch":
        n = len(results)
        M = np.full((n, n_metrics), np.nan)
        for i, r in enumerate(results):
            if r.metrics is not None:
                M[i] = r.metrics
        return cls(np.array([r.run_id for r in results], dtype=np.int64),
                   np.array([r.values for r in results], dtype=float).reshape(n, n_values), M,
                   np.array([r.status == "ok" for r in results], dtype=bool),
                   np.array([r.seconds for r in results], dtype=float),
                   {i: r.message for i, r in enumerate(results) if r.status != "ok"})

    @classmethod
    def concat(cls, batches: Sequence["RunBatch"]) -> "RunBatch":
        batches = [b for b in batches if len(b)]
        if len(batches) == 1:
            return batches[0]
        if not batches:
            return cls(np.empty(0, np.int64), np.empty((0, 0)), np.empty((0, 0)), np.empty(0, bool),
                       np.empty(0), {})
        msgs, off = {}, 0
        for b in batches:
            msgs.update({off + i: m for i, m in b.messages.items()})
            off += len(b)
        return cls(np.concatenate([b.run_ids for b in batches]), np.concatenate([b.values for b in batches]),
                   np.concatenate([b.metrics for b in batches]), np.concatenate([b.ok for b in batches]),
                   np.concatenate([b.seconds for b in batches]), msgs)

    def results(self) -> list[RunResult]:
        """One RunResult per run (study values as tuples of floats, metrics rows for the runs that worked)."""
        out = []
        for i, (rid, vals, ok, sec) in enumerate(zip(self.run_ids.tolist(), self.values.tolist(),
                                                     self.ok.tolist(), self.seconds.tolist())):
            if ok:
                out.append(RunResult(rid, tuple(vals), self.metrics[i].copy(), "ok", "", sec))
            else:
                out.append(RunResult(rid, tuple(vals), None, "failed", self.messages.get(i, ""), sec))
        return out


def as_arrays(chunk) -> tuple[np.ndarray, np.ndarray]:
    """(run ids, study values) of a chunk given as [(run id, values), ...] or as the pair of arrays."""
    if isinstance(chunk, tuple) and len(chunk) == 2 and isinstance(chunk[0], np.ndarray):
        return chunk
    chunk = list(chunk)
    ids = np.fromiter((c[0] for c in chunk), dtype=np.int64, count=len(chunk))
    vals = np.array([tuple(c[1]) for c in chunk], dtype=float)
    return ids, (vals.reshape(len(chunk), -1) if len(chunk) else np.empty((0, 0)))


def _message(exc: BaseException) -> str:
    return str(exc).strip().replace("\n", " | ")[:2000]


def run_batch(spec: PlanSpec, ids: np.ndarray, values: np.ndarray, started=None, emit=None,
              emit_every_s: float = 0.5, timeout_s: float | None = None, budget: str | None = None) -> RunBatch:
    """Run many parameter sets (``ids``, study ``values`` one row each) in this process; a failing run is
    recorded with its reason and the rest go on. The metrics are reduced with numpy over the whole batch
    (:func:`~fmusa.runs.metrics.reduce_batch`, the same values as run by run).

    ``started`` (a shared ``[count, time]`` array, for the supervising parent): before each run its count
    goes up by one and its time is set to ``time.monotonic()``, so the parent can tell which run crashed
    or hangs. ``emit``: called with the runs done so far every ``emit_every_s`` seconds (their results
    reach the parent and disk early); the runs after the last emit are returned.

    ``timeout_s``: the time limit of a run made here, unsupervised (:mod:`fmusa.runs.timelimit`): each run
    stops at its first communication point past it, and a run stopped that way or by the FMU parameter
    ``budget`` (which the caller set to ``timeout_s``) fails with the reason naming execution.timeout_s."""
    try:
        plan = plan_for(spec)
    except Exception as exc:    # an FMU that does not load or instantiate: every run says why, no dead worker
        reason = " | ".join(str(exc).strip().splitlines()) or type(exc).__name__
        return RunBatch.failed(ids, values, len(spec.rules),
                               f"the FMU could not be loaded or instantiated: {reason}"[:2000])
    n = len(ids)
    values = np.asarray(values, dtype=float).reshape(n, len(spec.varied))
    # FMU value = scale * study value + offset, elementwise as run by run
    fmu = (values * np.asarray(spec.scale, dtype=float) + np.asarray(spec.offset, dtype=float)).tolist()
    refine = bool(spec.refine_factor) and type(plan) is RunPlan
    limited = timeout_s is not None and type(plan) is RunPlan
    try:
        return _run_rows(spec, plan, ids, values, fmu, refine, started, emit, emit_every_s,
                         timeout_s if limited else None, budget)
    finally:
        if limited:
            plan.runner.deadline = None


def _run_rows(spec: PlanSpec, plan, ids, values, fmu, refine: bool, started, emit, emit_every_s: float,
              timeout_s: float | None, budget: str | None) -> RunBatch:
    """The loop of :func:`run_batch` over prepared FMU values ``fmu``, one row per run."""
    import time

    perf, mono = time.perf_counter, time.monotonic
    n = len(ids)
    times, keep = plan.times, None
    if spec.subsample > 1 and not refine:     # refined peaks do not depend on the sampling
        keep = np.unique(np.r_[np.arange(0, len(times), spec.subsample), len(times) - 1])
        times = times[keep]
    if refine:
        from fmusa.runs.refine import refine_run
    if timeout_s is not None:
        from fmusa.runs.timelimit import in_process_reason
    lo = 0
    while True:
        deadline = perf() + emit_every_s if emit is not None else None
        datas: list = []
        okl: list[int] = []
        secs: list[float] = []
        msgs: dict[int, str] = {}
        i = lo
        while i < n:
            if started is not None:
                started[1] = mono()
                started[0] += 1
            t0 = perf()
            if timeout_s is not None:
                plan.runner.deadline = mono() + timeout_s
            try:
                data = plan(fmu[i])
                if keep is not None:
                    data = data[keep]
                if refine:   # re-runs finer around the peaks: run by run, timed and supervised as the run;
                    # then ``datas`` holds the metrics of the runs rather than their outputs
                    datas.append(refine_run(spec, plan, fmu[i], data, reduce_series(plan.times, data, spec.rules)))
                else:
                    datas.append(data)
                okl.append(i - lo)
            except Exception as exc:  # the FMU's own error: record it, keep going
                msgs[i - lo] = _message(exc)
                if timeout_s is not None:
                    late = in_process_reason(exc, perf() - t0, timeout_s, budget, msgs[i - lo])
                    msgs[i - lo] = late[:2000] if late else msgs[i - lo]
            t1 = perf()
            secs.append(t1 - t0)
            i += 1
            if deadline is not None and t1 > deadline:
                break
        m = i - lo
        metrics = np.full((m, len(spec.rules)), np.nan)
        ok = np.zeros(m, dtype=bool)
        if okl:
            ok[okl] = True
            if refine:      # the metrics themselves, already
                metrics[okl] = datas
            elif len(datas) == 1:   # one run (a search's): the same values without numpy's cost per rule
                metrics[okl] = reduce_series(times, datas[0], spec.rules)
            elif len({d.shape for d in datas}) == 1:
                metrics[okl] = reduce_batch(times, np.stack(datas), spec.rules)
            else:  # pragma: no cover - a plan samples every run at the same times
                metrics[okl] = [reduce_series(times, d, spec.rules) for d in datas]
        batch = RunBatch(np.asarray(ids[lo:i], dtype=np.int64), values[lo:i], metrics, ok,
                         np.asarray(secs, dtype=float), msgs)
        if i >= n or emit is None:
            return batch
        emit(batch)
        lo = i


def run_chunk(spec: PlanSpec, chunk: Sequence[tuple[int, tuple[float, ...]]]) -> list[RunResult]:
    """Run a chunk of parameter sets; a failing run is recorded with its reason and the rest go on."""
    ids, vals = as_arrays(chunk)
    return run_batch(spec, ids, vals).results()


# ---------------------------------------------------------------------- the lean worker path
@dataclass(frozen=True)
class LeanView:
    """A lean worker's plan (:func:`fmusa.fmi.plans.lean_plan`) and what the parent needs to turn its
    answers into RunBatches: the sampling times the metrics are reduced on and the outputs per row."""
    plan: dict
    times: np.ndarray
    n_outputs: int


def lean_view(spec: PlanSpec, info) -> LeanView | None:
    """The lean path for ``spec``'s runs (its FMU unpacked, ``info`` read from it), or None where it does not
    cover them (then the worker runs them with fmpy): refined peaks re-run the FMU around each peak."""
    from fmusa.fmi.plans import lean_plan
    from fmusa.fmi.runner import communication_points

    if spec.refine_factor or info is None:
        return None
    times = communication_points(float(spec.stop_time), spec.step)
    keep = None
    if spec.subsample > 1:      # as _run_rows: every subsample-th point and the last
        keep = np.unique(np.r_[np.arange(0, len(times), spec.subsample), len(times) - 1])
        times = times[keep]
    plan = lean_plan(spec.fmu_path, info, spec.varied, spec.fixed, spec.inputs, spec.outputs, spec.stop_time,
                     spec.step, interface=spec.interface, solver=spec.solver,
                     relative_tolerance=spec.relative_tolerance, step_size=spec.step_size, reuse=spec.reuse,
                     keep=None if keep is None else keep.tolist())
    return None if plan is None else LeanView(plan, times, len(spec.outputs))


def from_lean(spec: PlanSpec, view: LeanView, batch, values: np.ndarray) -> RunBatch:
    """The RunBatch of a lean worker's answer ``batch`` (a :class:`fmusa.runs.lean.LeanBatch`) for runs whose
    study values are ``values`` (one row each): the metrics reduced as :func:`_run_rows` reduces them."""
    n = len(batch)
    metrics = np.full((n, len(spec.rules)), np.nan)
    ok = np.ones(n, dtype=bool)
    if batch.messages:
        ok[list(batch.messages)] = False
    okl = np.flatnonzero(ok)
    if len(okl):
        data = np.frombuffer(batch.data, dtype=float).reshape(len(okl), len(view.times), view.n_outputs)
        if len(okl) == 1:
            metrics[okl] = reduce_series(view.times, data[0], spec.rules)
        else:
            metrics[okl] = reduce_batch(view.times, data, spec.rules)
    return RunBatch(np.asarray(batch.ids, dtype=np.int64), np.array(values, dtype=float).reshape(n, -1),
                    metrics, ok, np.frombuffer(batch.seconds, dtype=float).copy(), dict(batch.messages))
