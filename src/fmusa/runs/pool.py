"""Supervised worker processes (local or on a Dask worker): a crash or a hang costs one run, never the study."""
from __future__ import annotations

import os
import shutil
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np

from fmusa.fmi.archive import extract_fmu
from fmusa.runs.spec import PlanSpec, RunBatch, as_arrays, run_batch
from fmusa.runs.timelimit import timeout_reason

PR_SET_PDEATHSIG = 1          # linux/prctl.h


def _signal_name(num: int) -> str:
    import signal
    try:
        return f"{signal.Signals(num).name}, signal {num}"
    except ValueError:
        return f"signal {num}"


def _die_with_parent(parent: int) -> None:
    """End this worker as soon as its parent ``parent`` dies, however it dies (``kill -9`` too): a worker
    blocked on its pipe (its siblings hold the other end open) or deep in an FMU call would otherwise live
    on. On Linux the kernel sends SIGKILL (``prctl(PR_SET_PDEATHSIG)``); elsewhere, and as a backstop, a
    thread checks twice a second that the parent is still there."""
    import ctypes
    import signal
    import time

    try:
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    except (OSError, AttributeError):      # not Linux: the thread alone
        pass
    if os.getppid() != parent:             # the parent died before the request took effect
        os._exit(1)

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, name="fmusa-parent-watch", daemon=True).start()


def _worker_main(conn, spec: PlanSpec, started, parent: int) -> None:
    """A pool worker: receive chunks (run ids, study values), send back their results as RunBatches, one
    message per chunk (more for a chunk that takes longer than half a second). Before each run it counts
    up ``started`` and stamps its start time, so the parent knows which run crashed or hangs. It dies with
    its parent process ``parent``."""
    import faulthandler
    import signal
    _die_with_parent(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # the parent decides when to stop
    faulthandler.disable()   # a crashing FMU is reported by the parent, not by a Python stack dump
    while True:
        try:
            msg = conn.recv()
        except EOFError:
            return
        if msg is None:
            return
        ids, values = msg
        conn.send(run_batch(spec, ids, values, started, emit=conn.send))


class _Worker:
    """One supervised worker process and the runs it has been given but not answered yet."""

    def __init__(self, ctx, spec: PlanSpec) -> None:
        self.conn, child = ctx.Pipe()
        #: [runs started, time.monotonic() when the last one started], written by the worker
        self.started = ctx.RawArray("d", 2)
        self.proc = ctx.Process(target=_worker_main, args=(child, spec, self.started, os.getpid()), daemon=True)
        self.proc.start()
        child.close()
        self.ids = np.empty(0, dtype=np.int64)     # runs given, not answered (in the order they run)
        self.values = np.empty((0, len(spec.varied)))
        self.answered = 0          # runs this process has answered
        self.given_at = 0.0        # when the current chunk was handed out

    @property
    def pending(self) -> int:
        return len(self.ids)

    def give(self, ids: np.ndarray, values: np.ndarray, now: float) -> None:
        self.ids, self.values = ids, values
        self.given_at = now
        self.conn.send((ids, values))

    def answer(self, n: int) -> None:
        self.ids, self.values = self.ids[n:], self.values[n:]
        if not len(self.ids):      # views no longer needed: let the caller's arrays go
            self.ids, self.values = self.ids.copy(), self.values.copy()
        self.answered += n

    def current(self) -> tuple[int, float]:
        """(index in the pending runs of the run in progress, when it started); index 0 and the hand-out
        time when no run of the pending ones has started."""
        count, since = int(self.started[0]), float(self.started[1])
        k = count - 1 - self.answered
        if not 0 <= k < len(self.ids):
            return 0, self.given_at
        return k, max(since, self.given_at)

    def kill(self) -> None:
        try:
            self.proc.kill()
        except Exception:
            pass
        self.proc.join(1.0)
        self.conn.close()


class _Chunks:
    """The runs not handed out yet, handed out in chunks of at most ``most`` runs and at most
    1/``parts`` of what is left (guided self-scheduling)."""

    def __init__(self, ids: np.ndarray, values: np.ndarray, most: int, parts: int) -> None:
        self.ids, self.values, self.most, self.parts = ids, values, max(1, most), max(1, parts)
        self.pos = 0

    def __bool__(self) -> bool:
        return self.pos < len(self.ids)

    def popleft(self) -> tuple[np.ndarray, np.ndarray]:
        left = len(self.ids) - self.pos
        size = max(1, min(self.most, -(-left // self.parts)))
        a, self.pos = self.pos, self.pos + size
        return self.ids[a:self.pos], self.values[a:self.pos]


class WorkerPool:
    """Local worker processes supervised run by run.

    Workers get chunks of runs and answer with one RunBatch per chunk (arrays, not an object per run).
    A run that crashes its worker (segfault, abort) or exceeds ``timeout_s`` is recorded as failed with
    the reason, the worker is replaced, the rest of its chunk (including runs done but not yet answered)
    is handed out again and the study goes on.
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
        refuses to start children; ours are daemonic themselves and die with their parent
        (:func:`_die_with_parent`), so the refusal is lifted while one starts."""
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

    def map(self, items, take, chunk: int) -> None:
        """Run ``items`` (a list of (run id, values), or the pair of arrays run ids, values) in chunks of at
        most ``chunk`` runs; ``take`` gets every RunBatch as it arrives. Chunks shrink as the runs left
        do (a worker gets at most 1/(2·workers) of them), so the workers finish together."""
        import time
        from multiprocessing.connection import wait

        ids, values = as_arrays(items)
        if not len(ids):
            return
        values = values.reshape(len(ids), len(self.spec.varied))
        queue = _Chunks(ids, values, chunk, 2 * self.n)
        for j, w in enumerate(self.workers):
            if not w.proc.is_alive():   # died while idle (killed from outside): it held no run, none is lost
                w.kill()
                self.workers[j] = self._start_worker()
        while len(self.workers) < min(self.n, len(ids)):
            self.workers.append(self._start_worker())
        for w in self.workers:
            if queue:
                w.give(*queue.popleft(), time.monotonic())
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
                w.answer(len(res))
                take(res)
                if not w.pending and queue:
                    w.give(*queue.popleft(), now)
            if self.timeout_s:
                for w in list(self.workers):
                    if w.pending and now - w.current()[1] > self.timeout_s:
                        if w.conn.poll():      # an answer arrived after wait(): read it next round
                            continue
                        self._replace(w, timeout_reason(self.timeout_s, "its worker process was stopped"),
                                      take, now)
            # workers replaced without a chunk left to finish pick up queued chunks
            for w in self.workers:
                if not w.pending and queue:
                    w.give(*queue.popleft(), now)

    def _replace(self, w: _Worker, reason: str, take, now: float) -> None:
        """``w`` crashed or hangs in its current run: that run fails with ``reason``; the others it was
        given and has not answered go to a new worker."""
        k, since = w.current()
        w.kill()
        take(RunBatch.failed(w.ids[k:k + 1], w.values[k:k + 1], len(self.spec.rules), reason, now - since))
        rest_ids = np.concatenate([w.ids[:k], w.ids[k + 1:]])
        rest_vals = np.concatenate([w.values[:k], w.values[k + 1:]])
        nw = self._start_worker()
        self.workers[self.workers.index(w)] = nw
        if len(rest_ids):
            nw.give(rest_ids, rest_vals, now)


#: (spec, timeout_s, thread id) -> this Dask worker's supervised pools, the one used last at the end
_DASK_POOLS: dict[tuple, WorkerPool] = {}
#: spec -> (the spec on the FMU unpacked once in this Dask worker, that folder or None)
_DASK_FMUS: dict[PlanSpec, tuple[PlanSpec, str | None]] = {}
#: pools a Dask worker thread keeps: a long-lived Dask worker that runs study after study closes the oldest
#: (its process and, once no pool uses it, its unpacked FMU) instead of keeping one per study forever
DASK_KEEP = 4
_DASK_EXIT: list[bool] = []        # the exit hook registered (once per process)
_DASK_LOCK = threading.Lock()      # a Dask worker's threads share the pools and unpacked FMUs


def _close_dask_pools() -> None:
    """At the Dask worker's exit: every pool's process, every unpacked FMU."""
    for pool in _DASK_POOLS.values():
        pool.close()
    _DASK_POOLS.clear()
    for _, folder in _DASK_FMUS.values():
        if folder:
            shutil.rmtree(folder, ignore_errors=True)
    _DASK_FMUS.clear()


def _dask_pool(spec: PlanSpec, timeout_s: float | None) -> WorkerPool:
    """This Dask worker thread's supervised pool (one worker process) for ``spec``, made once and kept among
    the thread's last :data:`DASK_KEEP`. The FMU is unpacked once per Dask worker process, so that supervised
    processes that crash leave no copy behind."""
    import atexit

    thread = threading.get_ident()
    key = (spec, timeout_s, thread)
    with _DASK_LOCK:
        if not _DASK_EXIT:
            atexit.register(_close_dask_pools)
            _DASK_EXIT.append(True)
        pool = _DASK_POOLS.pop(key, None)
        if pool is None:
            if spec not in _DASK_FMUS:
                folder = str(extract_fmu(spec.fmu_path, to_run=True)) if Path(spec.fmu_path).is_file() else None
                _DASK_FMUS[spec] = (spec if folder is None else replace(spec, fmu_path=folder), folder)
            pool = WorkerPool(_DASK_FMUS[spec][0], 1, timeout_s)
        _DASK_POOLS[key] = pool
        mine = [k for k in _DASK_POOLS if k[2] == thread]   # this thread uses none of them now but ``pool``
        for old in mine[:-DASK_KEEP]:
            _DASK_POOLS.pop(old).close()
        used = {k[0] for k in _DASK_POOLS}
        for other in [k for k in _DASK_FMUS if k not in used]:
            folder = _DASK_FMUS.pop(other)[1]
            if folder:
                shutil.rmtree(folder, ignore_errors=True)
    return pool


def run_chunk_supervised(spec: PlanSpec, chunk, timeout_s: float | None) -> RunBatch:
    """A Dask task: run ``chunk`` in a supervised process of this Dask worker, as the local pool does. A run
    that crashes that process, hangs past ``timeout_s`` or fails is recorded as failed with its reason; the
    process is replaced and the chunk goes on, so the Dask worker itself never dies with the FMU."""
    pool = _dask_pool(spec, timeout_s)
    out: list[RunBatch] = []
    ids, values = as_arrays(chunk)
    pool.map((ids, values), out.append, max(1, len(ids)))
    return RunBatch.concat(out)


