"""Supervised worker processes (local or on a Dask worker): a crash or a hang costs one run, never the study."""
from __future__ import annotations

import shutil
from dataclasses import replace
from pathlib import Path
from typing import Sequence


from fmusa.runs.spec import PlanSpec, RunResult, run_chunk


def _signal_name(num: int) -> str:
    import signal
    try:
        return f"{signal.Signals(num).name}, signal {num}"
    except ValueError:
        return f"signal {num}"


def _worker_main(conn, spec: PlanSpec) -> None:
    """A pool worker: receive chunks, send back one result per run as soon as it is done."""
    import faulthandler
    import signal
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # the parent decides when to stop
    faulthandler.disable()   # a crashing FMU is reported by the parent, not by a Python stack dump
    while True:
        try:
            msg = conn.recv()
        except EOFError:
            return
        if msg is None:
            return
        for item in msg:
            conn.send(run_chunk(spec, [item])[0])


class _Worker:
    """One supervised worker process and the items it has been given but not answered yet."""

    def __init__(self, ctx, spec: PlanSpec) -> None:
        self.conn, child = ctx.Pipe()
        self.proc = ctx.Process(target=_worker_main, args=(child, spec), daemon=True)
        self.proc.start()
        child.close()
        self.pending: list[tuple[int, tuple[float, ...]]] = []
        self.since = 0.0           # when the current run started (last answer or hand-out)

    def give(self, items: list, now: float) -> None:
        self.pending = list(items)
        self.since = now
        self.conn.send(items)

    def kill(self) -> None:
        try:
            self.proc.kill()
        except Exception:
            pass
        self.proc.join(1.0)
        self.conn.close()


class WorkerPool:
    """Local worker processes supervised run by run.

    A run that crashes its worker (segfault, abort) or exceeds ``timeout_s`` is recorded as failed with
    the reason, the worker is replaced, the rest of its chunk is handed out again and the study goes on.
    """

    def __init__(self, spec: PlanSpec, workers: int, timeout_s: float | None) -> None:
        import multiprocessing as mp
        self.ctx = mp.get_context("fork")
        self.spec = spec
        self.n = workers
        self.timeout_s = timeout_s
        self.workers: list[_Worker] = []

    def _start_worker(self) -> _Worker:
        """A new worker process. Inside a daemonic process (a Dask worker, by default) multiprocessing
        refuses to start children; ours are daemonic themselves and exit on the closed pipe when their
        parent dies, so the refusal is lifted while one starts."""
        import multiprocessing as mp
        config = mp.current_process()._config
        daemon = config.get("daemon")
        if not daemon:
            return _Worker(self.ctx, self.spec)
        config["daemon"] = False
        try:
            return _Worker(self.ctx, self.spec)
        finally:
            config["daemon"] = daemon

    def close(self) -> None:
        for w in self.workers:
            try:
                w.conn.send(None)
            except Exception:
                pass
        for w in self.workers:
            w.proc.join(0.5)
            if w.proc.is_alive():
                w.kill()
        self.workers = []

    def map(self, items: list, take, chunk: int) -> None:
        import time
        from multiprocessing.connection import wait

        queue = [items[i:i + chunk] for i in range(0, len(items), chunk)]
        while len(self.workers) < min(self.n, len(queue)):
            self.workers.append(self._start_worker())
        for w in self.workers:
            if queue:
                w.give(queue.pop(0), time.monotonic())
        while any(w.pending for w in self.workers):
            busy = {w.conn: w for w in self.workers if w.pending}
            ready = wait(list(busy), timeout=0.05 if self.timeout_s else None)
            now = time.monotonic()
            for conn in ready:
                w = busy[conn]
                try:
                    res = conn.recv()
                except (EOFError, OSError):
                    code = w.proc.exitcode
                    w.proc.join(1.0)
                    code = w.proc.exitcode if code is None else code
                    reason = (f"the FMU crashed the worker process ({_signal_name(-code)})" if code and code < 0
                              else f"the worker process exited with code {code}")
                    self._replace(w, reason, take, now)
                    continue
                w.pending.pop(0)
                w.since = now
                take([res])
                if not w.pending and queue:
                    w.give(queue.pop(0), now)
            if self.timeout_s:
                for w in list(self.workers):
                    if w.pending and now - w.since > self.timeout_s:
                        if w.conn.poll():      # an answer arrived after wait(): read it next round
                            continue
                        self._replace(w, f"timed out after {self.timeout_s:g} s (the FMU hangs or is too slow; "
                                         f"if only slow, raise execution.timeout_s and rerun without --resume)",
                                      take, now)
            # workers replaced without a chunk left to finish pick up queued chunks
            for w in self.workers:
                if not w.pending and queue:
                    w.give(queue.pop(0), now)

    def _replace(self, w: _Worker, reason: str, take, now: float) -> None:
        run_id, values = w.pending[0]
        rest = w.pending[1:]
        w.kill()
        take([RunResult(run_id, tuple(values), None, "failed", reason, now - w.since)])
        nw = self._start_worker()
        self.workers[self.workers.index(w)] = nw
        if rest:
            nw.give(rest, now)


_DASK_POOLS: dict = {}


def _dask_pool(spec: PlanSpec, timeout_s: float | None) -> WorkerPool:
    """This Dask worker thread's supervised pool (one worker process) for ``spec``, made once. The FMU is
    unpacked once per Dask worker process, so that supervised processes that crash leave no copy behind."""
    import atexit
    import threading

    key = (spec, timeout_s, threading.get_ident())
    pool = _DASK_POOLS.get(key)
    if pool is not None:
        return pool
    local = _DASK_POOLS.get(("unzipped", spec))
    if local is None:
        local = spec
        if Path(spec.fmu_path).is_file():
            import fmpy
            unzipdir = fmpy.extract(spec.fmu_path)
            atexit.register(shutil.rmtree, unzipdir, ignore_errors=True)
            local = replace(spec, fmu_path=unzipdir)
        _DASK_POOLS[("unzipped", spec)] = local
    pool = WorkerPool(local, 1, timeout_s)
    atexit.register(pool.close)
    _DASK_POOLS[key] = pool
    return pool


def run_chunk_supervised(spec: PlanSpec, chunk: Sequence[tuple[int, tuple[float, ...]]],
                         timeout_s: float | None) -> list[RunResult]:
    """A Dask task: run ``chunk`` in a supervised process of this Dask worker, as the local pool does. A run
    that crashes that process, hangs past ``timeout_s`` or fails is recorded as failed with its reason; the
    process is replaced and the chunk goes on, so the Dask worker itself never dies with the FMU."""
    pool = _dask_pool(spec, timeout_s)
    out: list[RunResult] = []
    pool.map(list(chunk), out.extend, max(1, len(chunk)))
    return out


