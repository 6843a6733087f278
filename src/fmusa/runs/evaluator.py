"""Batches of runs in this process, on supervised local workers, or on a Dask cluster."""
from __future__ import annotations

import os
import shutil
from dataclasses import replace
from pathlib import Path
from typing import Sequence

from fmusa.fmi.build import compile_sources
from fmusa.fmi.info import read_fmu_info, select_interface
from fmusa.runs.pool import WorkerPool, run_chunk_supervised
from fmusa.runs.spec import PlanSpec, RunResult, release_plan, run_chunk


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

    def _local_spec(self) -> PlanSpec:
        """The spec with the FMU unpacked once, here, for this process and its workers: workers that
        crash or are killed cannot clean up a copy of their own."""
        if self._unzipdir is None and Path(self.spec.fmu_path).is_file():
            import fmpy
            self._unzipdir = fmpy.extract(self.spec.fmu_path)
            try:   # sources but no binary for this machine: build once here, not in every worker
                info = read_fmu_info(self._unzipdir)
                iface = select_interface(info, self.spec.interface)
                if not info.has_binary(iface) and info.can_compile:
                    compile_sources(self._unzipdir, info, iface)
            except Exception:
                shutil.rmtree(self._unzipdir, ignore_errors=True)
                self._unzipdir = None
                raise
        if self._unzipdir is None:
            return self.spec
        return replace(self.spec, fmu_path=self._unzipdir)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool = None
        if self._unzipdir is not None:
            release_plan(self._local_spec())
            shutil.rmtree(self._unzipdir, ignore_errors=True)
            self._unzipdir = None
        if self._client is not None:
            self._client.close()
            self._client = None

    def __enter__(self) -> "Evaluator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _chunks(self, items: list, n_parallel: int) -> list[list]:
        size = max(1, min(200, len(items) // (n_parallel * 8) or 1))
        return [items[i:i + size] for i in range(0, len(items), size)]

    def map(self, items: Sequence[tuple[int, tuple[float, ...]]], on_result=None, progress=None) -> list[RunResult]:
        """Evaluate ``items`` (run id, study values); results in completion order."""
        items = list(items)
        results: list[RunResult] = []

        def take(batch: list[RunResult]) -> None:
            results.extend(batch)
            if on_result is not None:
                for r in batch:
                    on_result(r)
            if progress is not None:
                progress.update(len(batch))

        if not items:
            return results
        if self.scheduler:
            from dask.distributed import Client, as_completed

            if self._client is None:
                self._client = Client(self.scheduler)
            n = max(1, sum(self._client.nthreads().values()))
            # each task runs its chunk in a supervised process on its Dask worker (crash, hang, error: a
            # failed run, never a dead worker); a task Dask itself loses fails its runs with the reason
            futures, chunks = [], {}
            for c in self._chunks(items, n):
                fut = self._client.submit(run_chunk_supervised, self.spec, c, self.timeout_s, pure=False)
                futures.append(fut)
                chunks[fut.key] = c
            for fut in as_completed(futures):
                try:
                    batch = fut.result()
                except Exception as exc:  # noqa: BLE001 - e.g. KilledWorker: record, go on
                    reason = f"the Dask task failed: {type(exc).__name__}: {str(exc).strip()}"[:2000]
                    batch = [RunResult(rid, tuple(v), None, "failed", reason, 0.0) for rid, v in chunks[fut.key]]
                take(batch)
        elif self.isolate or (self.workers > 1 and len(items) >= self.pool_threshold):
            if self._pool is None:
                self._pool = WorkerPool(self._local_spec(), self.workers, self.timeout_s)
            size = max(1, min(200, len(items) // (self.workers * 8) or 1))
            self._pool.map(items, take, size)
        else:
            spec = self._local_spec()
            for c in self._chunks(items, 1):
                take(run_chunk(spec, c))
        return results
