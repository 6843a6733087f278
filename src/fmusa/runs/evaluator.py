"""Batches of runs in this process, on supervised local workers, or on a Dask cluster."""
from __future__ import annotations

import os
import shutil
from dataclasses import replace
from pathlib import Path
from typing import Sequence

from fmusa.errors import FmusaError
from fmusa.fmi.archive import extract_fmu, remove_folder
from fmusa.fmi.build import compile_sources
from fmusa.fmi.info import read_fmu_info, select_interface
from fmusa.runs.pool import ENV_START_METHOD, PoolOptions, WorkerPool, resolve_start_method, run_chunk_supervised
from fmusa.runs.scheduler import connect_scheduler
from fmusa.runs.spec import PlanSpec, RunBatch, RunResult, as_arrays, release_plan, run_batch
from fmusa.runs.inflight import InFlight
from fmusa.runs.timelimit import in_process_fixed, own_fmu

class SchedulerLostError(FmusaError, RuntimeError):
    """The connection to the Dask scheduler was lost mid-study (the scheduler stopped, or the network went):
    an interruption, like Ctrl-C. The runs finished before are in runs.csv; the runs under way are not stored
    as failed.

    Fix: start the scheduler (and its workers) again and rerun the same command with ``--resume``: only the
    runs not in runs.csv are made."""

    exit_code = 1


def _cancelled(exc: BaseException) -> bool:
    from concurrent.futures import CancelledError
    import asyncio
    return isinstance(exc, (CancelledError, asyncio.CancelledError))


class Evaluator:
    """Runs batches of parameter sets in this process, on supervised local workers, or on a Dask
    cluster, and hands every result to ``on_result`` as soon as it is known (so it reaches disk early).

    Small batches of a trusted FMU (our own) run in-process: workers pay ~0.1 s to start and to load the
    FMU, more than a few hundred runs of the built FMU cost. With a time limit (``timeout_s``) that holds
    only for an FMU that can stop a run itself (:mod:`fmusa.runs.timelimit`: its ``max_wall_s``); any
    other FMU runs in supervised workers, as an FMU not our own always does, so a crash or a hang costs
    one run, never the study.
    """

    def __init__(self, spec: PlanSpec, workers: int | None = None, scheduler: str | None = None,
                 pool_threshold: int = 400, isolate: bool = False, timeout_s: float | None = 60.0,
                 pool: PoolOptions | None = None, own: bool | None = None) -> None:
        self.spec = spec
        #: how supervised workers start and are kept (execution.start_method, worker_max_runs, …)
        self.pool_options = pool or PoolOptions()
        if not scheduler:       # a start method this platform lacks is an error now, before anything runs
            resolve_start_method(self.pool_options.start_method)
        self.workers = workers or os.cpu_count() or 1
        self.scheduler = scheduler
        self.pool_threshold = pool_threshold
        self.isolate = isolate
        #: whether the FMU is our own (:func:`fmusa.runs.timelimit.own_fmu` of the FMU as given, before a
        #: build from its sources); None: judged from ``spec.fmu_path``
        self.own = own
        self.timeout_s = timeout_s
        self._pool: WorkerPool | None = None
        self._client = None
        self._unzipdir: str | None = None
        self._local: PlanSpec | None = None     # the spec on the unpacked FMU, made once
        #: (spec, budget parameter set by fmusa) of runs made in this process; False: supervised only
        self._here: tuple[PlanSpec, str | None] | bool | None = None
        #: where the runs made in this process are noted while they run (:mod:`fmusa.runs.inflight`), so that
        #: a resume after a crash that took this process down does not make them here again
        self.marker: InFlight | None = None

    def _local_spec(self) -> PlanSpec:
        """The spec with the FMU unpacked once, here, for this process and its workers: workers that
        crash or are killed cannot clean up a copy of their own."""
        if self._local is not None:
            return self._local
        if self._unzipdir is None and Path(self.spec.fmu_path).is_file():
            self._unzipdir = str(extract_fmu(self.spec.fmu_path, to_run=True))
            try:   # sources but no binary for this machine: build once here, not in every worker
                info = read_fmu_info(self.spec.fmu_path)      # the archive's, read before (cached)
                iface = select_interface(info, self.spec.interface)
                if not info.has_binary(iface) and info.can_compile:
                    compile_sources(self._unzipdir, info, iface)
            except Exception:
                remove_folder(self._unzipdir)
                self._unzipdir = None
                raise
        self._local = self.spec if self._unzipdir is None else replace(self.spec, fmu_path=self._unzipdir)
        return self._local

    def local_spec(self) -> PlanSpec:
        """The spec on the FMU as unpacked here for this study (its ``fmu_path`` a folder): further runs
        of the same FMU (another step, another interface) made from it need no unpacking of their own."""
        return self._local_spec()

    def check_spec(self) -> PlanSpec:
        """The spec the FMU's reset check (:mod:`fmusa.runs.preflight`) runs: the one runs in this process
        are made with when there are such runs (the check's instance is then theirs), else the unpacked FMU's."""
        here = None if self.isolate else self._in_process()
        return here[0] if here else self._local_spec()

    @property
    def supervised_only(self) -> bool:
        """Whether every run of this evaluator is made in supervised workers (an FMU not our own, or one that
        cannot keep a run to ``timeout_s`` by itself): then anything else that runs the FMU must be
        supervised too."""
        return bool(self.isolate or self._in_process() is None)

    def set_reuse(self, mode: str) -> None:
        """Make every later run bring its instance back as ``mode`` says (the reset check's verdict)."""
        if mode == self.spec.reuse:
            return
        self.spec = replace(self.spec, reuse=mode)
        if self._local is not None:
            self._local = replace(self._local, reuse=mode)
        if isinstance(self._here, tuple):
            self._here = (replace(self._here[0], reuse=mode), self._here[1])

    def _in_process(self) -> tuple[PlanSpec, str | None] | None:
        """(the spec runs in this process are made with, the FMU parameter fmusa set in it to keep each run
        within ``timeout_s``, or None when the study sets it), or None when a run here could outlast
        ``timeout_s``: then every run goes to supervised workers."""
        if self._here is None and not (self.own if self.own is not None else own_fmu(self.spec.fmu_path)):
            self._here = False          # not our FMU: a crash or an exit inside it would end this process
        if self._here is None:
            local = self._local_spec()
            self._here = (local, None)
            if self.timeout_s is not None:
                try:
                    limited = in_process_fixed(read_fmu_info(self.spec.fmu_path), self.spec.interface,
                                               local.fixed, local.varied, self.timeout_s)
                except FmusaError:      # an FMU that cannot be read: the workers say why, run by run
                    limited = None
                self._here = False if limited is None else (replace(local, fixed=limited[0]), limited[1])
        return self._here or None

    def connect(self) -> None:
        """Reach the Dask scheduler now (nothing to do for local runs), so that a wrong or dead address is
        an error before anything is written rather than once the study runs."""
        if self.scheduler and self._client is None:
            self._client = connect_scheduler(self.scheduler)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool = None
        if self._unzipdir is not None:
            here = self._here if isinstance(self._here, tuple) else None
            release_plan(self._local_spec())
            if here is not None and here[0] != self._local:
                release_plan(here[0])
            remove_folder(self._unzipdir)
            self._unzipdir = None
            self._local = None
            self._here = None
        if self._client is not None:
            self._client.close()
            self._client = None

    def __enter__(self) -> "Evaluator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _scheduler_lost(self, exc: BaseException) -> bool:
        """Whether a Dask task's error says the scheduler is gone rather than the task failed: fmusa never
        cancels its own futures, so a cancelled one (``scheduler-connection-lost``) is an interruption; so is
        any error while the client is no longer connected."""
        if _cancelled(exc) or "connection-lost" in str(exc) or "CommClosedError" in type(exc).__name__:
            return True
        return getattr(self._client, "status", "running") not in ("running", "newly-created")

    def parallel_workers(self) -> int:
        """How many runs go at once: the Dask cluster's threads (asked for now), else the local workers."""
        if self.scheduler:
            self.connect()
            return max(1, sum(self._client.nthreads().values()))
        return self.workers

    @staticmethod
    def _chunk_size(n: int, n_parallel: int) -> int:
        """Runs per chunk: about 8 chunks per worker (the last ones balance the load), at most 1000 (a worker
        answers at least every half second anyway)."""
        return max(1, min(1000, n // (n_parallel * 8) or 1))

    def map(self, items: Sequence[tuple[int, tuple[float, ...]]], on_result=None, progress=None) -> list[RunResult]:
        """Evaluate ``items`` (run id, study values); results in completion order, each also handed to
        ``on_result`` as soon as it is known."""
        results: list[RunResult] = []

        def take(batch: RunBatch) -> None:
            rs = batch.results()
            results.extend(rs)
            if on_result is not None:
                for r in rs:
                    on_result(r)

        self.map_batches(items, take, progress)
        return results

    def map_batches(self, items, on_batch, progress=None, supervised: bool = False) -> None:
        """Evaluate ``items`` (a list of (run id, study values), or the pair of arrays run ids, values):
        ``on_batch`` gets the results as RunBatches (arrays, one row per run) as they arrive, and
        ``progress`` (a tqdm bar or None) is advanced by each batch. ``supervised``: in supervised
        workers whatever the batch's size (runs that may crash)."""
        ids, values = as_arrays(items)
        if not len(ids):
            return
        values = values.reshape(len(ids), len(self.spec.varied))
        n_metrics = len(self.spec.rules)

        def take(batch: RunBatch) -> None:
            on_batch(batch)
            if progress is not None:
                progress.update(len(batch))

        if self.scheduler:
            from dask.distributed import as_completed

            self.connect()
            n = max(1, sum(self._client.nthreads().values()))
            # each task runs its chunk in a supervised process on its Dask worker (crash, hang, error: a
            # failed run, never a dead worker); a task Dask itself loses fails its runs with the reason
            futures, chunks = [], {}
            # the start method chosen here (study or environment) holds on the Dask workers too; none
            # chosen: each Dask worker's platform default
            opts = self.pool_options
            if opts.start_method is None and os.environ.get(ENV_START_METHOD, "").strip():
                opts = replace(opts, start_method=os.environ[ENV_START_METHOD].strip())
            size = self._chunk_size(len(ids), n)
            for i in range(0, len(ids), size):
                c = (ids[i:i + size], values[i:i + size])
                fut = self._client.submit(run_chunk_supervised, self.spec, c, self.timeout_s, opts, pure=False)
                futures.append(fut)
                chunks[fut.key] = c
            done = 0
            for fut in as_completed(futures):
                try:
                    batch = fut.result()
                except Exception as exc:  # noqa: BLE001 - e.g. KilledWorker: record, go on
                    if self._scheduler_lost(exc):     # not the runs' fault: stop, as Ctrl-C does
                        for f in futures:
                            f.release()
                        raise SchedulerLostError(
                            f"the connection to the Dask scheduler at {self.scheduler} was lost during the study "
                            f"({type(exc).__name__}: {' '.join(str(exc).split())[:300]}); the runs finished before "
                            f"({done} of this batch) are in runs.csv and none was stored as failed: start the "
                            f"scheduler and its workers again, then rerun the same command with --resume") from None
                    reason = f"the Dask task failed: {type(exc).__name__}: {str(exc).strip()}"[:2000]
                    batch = RunBatch.failed(*chunks[fut.key], n_metrics, reason)
                take(batch)
                done += len(batch)
        elif (supervised or self.isolate or (self.workers > 1 and len(ids) >= self.pool_threshold)
              or (here := self._in_process()) is None):
            if self._pool is None:
                self._pool = WorkerPool(self._local_spec(), self.workers, self.timeout_s, self.pool_options)
            # chunks of 200 runs at least keep the pipes quiet; a batch smaller than 200 per worker (a
            # search's round) is spread over all workers
            size = max(self._chunk_size(len(ids), self.workers), min(200, -(-len(ids) // self.workers)))
            self._pool.map((ids, values), take, size)
        else:      # unsupervised: each run kept to timeout_s by the FMU's own budget
            spec, budget = here
            size = self._chunk_size(len(ids), 1)
            marker = self.marker
            for i in range(0, len(ids), size):
                if marker is None:
                    take(run_batch(spec, ids[i:i + size], values[i:i + size], timeout_s=self.timeout_s,
                                   budget=budget))
                    continue
                marker.begin(ids[i:i + size], values[i:i + size])     # left behind only if the process dies
                try:
                    batch = run_batch(spec, ids[i:i + size], values[i:i + size], timeout_s=self.timeout_s,
                                      budget=budget)
                    take(batch)
                finally:     # an exception (Ctrl-C, a full disk) is not a crash: nothing left under way
                    marker.end()
