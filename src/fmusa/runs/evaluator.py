"""Batches of runs in this process, on supervised local workers, or on a Dask cluster."""
from __future__ import annotations

import os
import shutil
from dataclasses import replace
from pathlib import Path
from typing import Sequence

from fmusa.fmi.archive import extract_fmu
from fmusa.fmi.build import compile_sources
from fmusa.fmi.info import read_fmu_info, select_interface
from fmusa.runs.pool import WorkerPool, run_chunk_supervised
from fmusa.runs.spec import PlanSpec, RunBatch, RunResult, as_arrays, release_plan, run_batch


class Evaluator:
    """Runs batches of parameter sets in this process, on supervised local workers, or on a Dask
    cluster, and hands every result to ``on_result`` as soon as it is known (so it reaches disk early).

    Small batches of a trusted FMU (our own) run in-process: workers pay ~0.1 s to start and to load the
    FMU, more than a few hundred runs of the built FMU cost. Any other FMU always runs in workers, so a
    crash or a hang costs one run, never the study.
    """

    def __init__(self, spec: PlanSpec, workers: int | None = None, scheduler: str | None = None,
                 pool_threshold: int = 400, isolate: bool = False, timeout_s: float | None = 60.0) -> None:
        self.spec = spec
        self.workers = workers or os.cpu_count() or 1
        self.scheduler = scheduler
        self.pool_threshold = pool_threshold
        self.isolate = isolate
        self.timeout_s = timeout_s
        self._pool: WorkerPool | None = None
        self._client = None
        self._unzipdir: str | None = None
        self._local: PlanSpec | None = None     # the spec on the unpacked FMU, made once

    def _local_spec(self) -> PlanSpec:
        """The spec with the FMU unpacked once, here, for this process and its workers: workers that
        crash or are killed cannot clean up a copy of their own."""
        if self._local is not None:
            return self._local
        if self._unzipdir is None and Path(self.spec.fmu_path).is_file():
            self._unzipdir = str(extract_fmu(self.spec.fmu_path))
            try:   # sources but no binary for this machine: build once here, not in every worker
                info = read_fmu_info(self._unzipdir)
                iface = select_interface(info, self.spec.interface)
                if not info.has_binary(iface) and info.can_compile:
                    compile_sources(self._unzipdir, info, iface)
            except Exception:
                shutil.rmtree(self._unzipdir, ignore_errors=True)
                self._unzipdir = None
                raise
        self._local = self.spec if self._unzipdir is None else replace(self.spec, fmu_path=self._unzipdir)
        return self._local

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool = None
        if self._unzipdir is not None:
            release_plan(self._local_spec())
            shutil.rmtree(self._unzipdir, ignore_errors=True)
            self._unzipdir = None
            self._local = None
        if self._client is not None:
            self._client.close()
            self._client = None

    def __enter__(self) -> "Evaluator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

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

    def map_batches(self, items, on_batch, progress=None) -> None:
        """Evaluate ``items`` (a list of (run id, study values), or the pair of arrays run ids, values):
        ``on_batch`` gets the results as RunBatches (arrays, one row per run) as they arrive, and
        ``progress`` (a tqdm bar or None) is advanced by each batch."""
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
            from dask.distributed import Client, as_completed

            if self._client is None:
                self._client = Client(self.scheduler)
            n = max(1, sum(self._client.nthreads().values()))
            # each task runs its chunk in a supervised process on its Dask worker (crash, hang, error: a
            # failed run, never a dead worker); a task Dask itself loses fails its runs with the reason
            futures, chunks = [], {}
            size = self._chunk_size(len(ids), n)
            for i in range(0, len(ids), size):
                c = (ids[i:i + size], values[i:i + size])
                fut = self._client.submit(run_chunk_supervised, self.spec, c, self.timeout_s, pure=False)
                futures.append(fut)
                chunks[fut.key] = c
            for fut in as_completed(futures):
                try:
                    batch = fut.result()
                except Exception as exc:  # noqa: BLE001 - e.g. KilledWorker: record, go on
                    reason = f"the Dask task failed: {type(exc).__name__}: {str(exc).strip()}"[:2000]
                    batch = RunBatch.failed(*chunks[fut.key], n_metrics, reason)
                take(batch)
        elif self.isolate or (self.workers > 1 and len(ids) >= self.pool_threshold):
            if self._pool is None:
                self._pool = WorkerPool(self._local_spec(), self.workers, self.timeout_s)
            self._pool.map((ids, values), take, max(self._chunk_size(len(ids), self.workers), 200))
        else:
            spec = self._local_spec()
            size = self._chunk_size(len(ids), 1)
            for i in range(0, len(ids), size):
                take(run_batch(spec, ids[i:i + size], values[i:i + size]))
