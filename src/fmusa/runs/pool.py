"""Supervised worker processes (local or on a Dask worker): a crash or a hang costs one run, never the study.

The workers are started with the platform's default start method (``fork`` on Linux up to Python 3.13,
``spawn`` on Windows and macOS, ``forkserver`` on Linux from 3.14), or the one ``execution.start_method``
or ``$FMUSA_START_METHOD`` names (:func:`resolve_start_method`); the results are the same under each.
Whatever the method, a worker loads its FMU before it says "ready" and is given its first run only then, so
its start-up is never charged to a run's time limit (a run's time counts from the moment the worker starts
it); workers are reused for run after run, a spare worker is started as soon as one has had to be replaced
(so that the next replacement is ready before it is needed), and the worker side is the lean module
:mod:`fmusa.runs.worker`, handed the spec and the parent's reading of the model description.

A worker that uses more memory than ``execution.worker_max_memory_mb``, or has made
``execution.worker_max_runs`` runs, is replaced by a fresh one; a run whose worker died (a crash, the
memory limit, the system's out-of-memory killer) is tried once more on a fresh worker before it is
recorded as failed (``execution.retries``). A run that hangs past ``timeout_s`` is not tried again.
"""
from __future__ import annotations

import os
import pickle
import shutil
import sys
import threading
import time
from array import array
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from fmusa.errors import UsageError
from fmusa.fmi.archive import extract_fmu, remove_folder
from fmusa.runs import worker as _worker_side
from fmusa.runs.lean import LeanBatch
from fmusa.runs.spec import LeanView, PlanSpec, RunBatch, as_arrays, from_lean, lean_view
from fmusa.runs.timelimit import timeout_reason

START_METHODS = _worker_side.START_METHODS
#: The environment variable that picks the start method when the study does not.
ENV_START_METHOD = "FMUSA_START_METHOD"
#: The start methods whose workers take the lean path (:mod:`fmusa.fmi.lean`: ctypes, no numpy or fmpy)
#: where it covers the runs: a spawned worker imports everything itself, a forked one (fork, forkserver,
#: whose server has imported numpy and fmpy once) has it already.
LEAN_METHODS = ("spawn",)
#: Set to 0 to give every worker the fmpy path (to compare the two; the results are the same).
ENV_LEAN = "FMUSA_LEAN_WORKERS"
#: Seconds a new worker may take to load its FMU and say "ready" (a model description of 200k variables
#: takes seconds; a worker that takes longer is counted as one that could not start).
STARTUP_LIMIT_S = 600.0
#: Workers that die one after another before any is ready: past this, the runs fail with the reason.
START_FAILURES = 3
#: Seconds between two looks at the workers' memory (with ``worker_max_memory_mb`` set).
MEMORY_POLL_S = 0.2
#: Most runs in one chunk with ``worker_max_memory_mb`` set (the memory is also looked at between chunks).
MEMORY_CHUNK = 4

#: Windows exception codes (NTSTATUS) a process ends with when native code crashes it.
WINDOWS_CRASHES = {
    0xC0000005: "access violation", 0xC0000006: "in-page error", 0xC000001D: "illegal instruction",
    0xC0000025: "non-continuable exception", 0xC000008C: "array bounds exceeded",
    0xC000008E: "floating-point division by zero", 0xC0000090: "floating-point invalid operation",
    0xC0000094: "integer division by zero", 0xC0000095: "integer overflow", 0xC0000096: "privileged instruction",
    0xC00000FD: "stack overflow", 0xC0000017: "out of memory", 0xC0000374: "heap corruption",
    0xC0000409: "stack buffer overrun (fast fail, e.g. abort)", 0xC0000420: "assertion failure",
    0x80000003: "breakpoint",
}


@dataclass(frozen=True)
class PoolOptions:
    """How the pool starts and keeps its workers (the ``execution:`` keys of the same names)."""
    start_method: str | None = None          # None: $FMUSA_START_METHOD, else the platform's default
    worker_max_runs: int | None = None       # replace a worker after this many runs (None: never)
    worker_max_memory_mb: float | None = None  # replace a worker past this resident memory (None: never)
    retries: int = 1                         # tries more of a run whose worker died, each on a fresh worker


def resolve_start_method(requested: str | None = None) -> str:
    """The start method of the workers: ``requested`` (``execution.start_method``), else
    ``$FMUSA_START_METHOD``, else the one the program set with ``multiprocessing.set_start_method``, else the
    platform's default. A name that is not a start method, or not one this platform has, is a UsageError
    naming where it came from and the choices."""
    import multiprocessing as mp

    where, method = "execution.start_method", requested
    if method is None:
        env = os.environ.get(ENV_START_METHOD, "").strip()
        if env:
            where, method = f"${ENV_START_METHOD}", env
    available = mp.get_all_start_methods()
    if method is None:
        chosen = mp.get_start_method(allow_none=True)
        return chosen if chosen in available else available[0]
    if method not in START_METHODS:
        raise UsageError(f"{where} = {method!r} is not a start method; use one of {', '.join(START_METHODS)} "
                         f"(or leave it out for this platform's default, {available[0]})")
    if method not in available:
        raise UsageError(f"{where} = {method!r} is not available on this platform ({sys.platform}); use one of "
                         f"{', '.join(available)}")
    return method


def _signal_name(num: int) -> str:
    import signal
    try:
        return f"{signal.Signals(num).name}, signal {num}"
    except ValueError:
        return f"signal {num}"


def exit_reason(code: int | None) -> str:
    """Why a worker process ended, told from its exit code: a signal (POSIX, a negative code) or a Windows
    exception code (0xC0000005 and the like) is a crash; anything else an exit with that code."""
    if code is None:
        return "the worker process ended without an exit code"
    if code < 0:
        if -code == 9:
            return (f"the worker process was killed ({_signal_name(-code)}: by the system's out-of-memory "
                    f"killer, or from outside)")
        return f"the FMU crashed the worker process ({_signal_name(-code)})"
    status = code & 0xFFFFFFFF
    if status in WINDOWS_CRASHES:
        return f"the FMU crashed the worker process ({WINDOWS_CRASHES[status]}, exception code 0x{status:08X})"
    if status >= 0xC0000000:
        return f"the FMU crashed the worker process (exception code 0x{status:08X})"
    return f"the worker process exited with code {code}"


#: Model descriptions with more variables than this go to spawned workers with only the variables a run
#: uses: pickling 200k fmpy variables costs more than parsing them.
LEAN_ABOVE = 2000


def _lean_info(info, spec: PlanSpec):
    """``info`` for a worker that makes ``spec``'s runs: a co-simulation FMU's description with only the
    variables those runs set or read (a model exchange FMU's whole description goes: fmpy's solver reads
    it). Runs look variables up by name only, and the parent has checked every name already."""
    import copy
    import dataclasses

    from fmusa.fmi.info import select_interface
    from fmusa.runs.timelimit import WALL_BUDGET

    if len(info.variables) <= LEAN_ABOVE or select_interface(info, spec.interface) != "co-simulation":
        return info
    keep = (set(spec.varied) | {n for n, _ in spec.fixed} | {n for n, _ in spec.inputs} | set(spec.outputs)
            | {WALL_BUDGET})
    md = copy.copy(info.model_description)
    md.modelVariables = [v for v in md.modelVariables if v.name in keep]
    for attr in ("outputs", "derivatives", "initialUnknowns"):
        unknowns = getattr(md, attr, None)
        if unknowns:
            setattr(md, attr, [u for u in unknowns if getattr(u.variable, "name", None) in keep])
    return dataclasses.replace(info, variables=tuple(md.modelVariables), model_description=md)


_START_LOCK = threading.Lock()


def start_process(proc, method: str) -> None:
    """Start ``proc`` without running the program's main module again in it: ``spawn`` and ``forkserver``
    re-import ``__main__`` (for the ``fmusa`` command, the whole CLI and what it imports) in every child,
    and a worker's target and arguments never refer to it."""
    if method == "fork":
        proc.start()
        return
    from multiprocessing import spawn

    with _START_LOCK:
        full = spawn.get_preparation_data

        def lean(name):
            data = full(name)
            data.pop("init_main_from_name", None)
            data.pop("init_main_from_path", None)
            return data

        spawn.get_preparation_data = lean
        try:
            proc.start()
        finally:
            spawn.get_preparation_data = full


def worker_memory_mb(pid: int) -> float:
    """The memory process ``pid`` holds alone, in MB: its unique set size (what it would free by ending,
    e.g. a leaking FMU's allocations), its resident size where the system cannot tell, 0 when gone. A worker
    forked from a large study process shares that process's pages; its resident size counts them, and a
    fresh worker would seem over a memory limit before its first run."""
    try:
        import psutil
        proc = psutil.Process(pid)
    except Exception:  # noqa: BLE001 - gone, or no psutil: nothing to act on
        return 0.0
    try:
        return proc.memory_full_info().uss / 1e6
    except Exception:  # noqa: BLE001 - not allowed or not offered here: the resident size
        try:
            return proc.memory_info().rss / 1e6
        except Exception:  # noqa: BLE001
            return 0.0


class _Worker:
    """One supervised worker process and the runs it has been given but not answered yet."""

    def __init__(self, ctx, method: str, payload: bytes, n_varied: int, lean: bool = False) -> None:
        #: the worker takes chunks as plain data (a lean worker unpickles no numpy array)
        self.lean = lean
        self.conn, child = ctx.Pipe()
        #: the worker watches the other end: it reads EOF when this process, the only writer, is gone
        death_r, self.death = ctx.Pipe(duplex=False)
        #: [runs started, time.monotonic() when the last one started], written by the worker
        self.started = ctx.RawArray("d", 2)
        self.proc = ctx.Process(target=_worker_side.main, args=(child, death_r, self.started, payload),
                                daemon=True, name="fmusa-worker")
        ends = _worker_side.PARENT_ENDS
        ends.extend((self.conn, self.death))     # a forked child closes its copies of these at once
        try:
            start_process(self.proc, method)
        except BaseException:
            self._forget()
            raise
        child.close()
        death_r.close()
        self.born = time.monotonic()
        self.ready = False
        self.ids = np.empty(0, dtype=np.int64)     # runs given, not answered (in the order they run)
        self.values = np.empty((0, n_varied))
        self.sent = False          # the pending runs were sent (a worker not ready yet gets them on ready)
        self.answered = 0          # runs this process has answered
        self.given_at = 0.0        # when the current chunk was sent

    @property
    def pending(self) -> int:
        return len(self.ids)

    def give(self, ids: np.ndarray, values: np.ndarray, now: float) -> None:
        self.ids, self.values, self.sent = ids, values, False
        if self.ready:
            self._send(now)

    def _send(self, now: float) -> None:
        self.given_at = now
        self.sent = True
        if self.lean:
            values = array("d")
            values.frombytes(np.ascontiguousarray(self.values, dtype=float).tobytes())
            self.conn.send((self.ids.tolist(), values))
        else:
            self.conn.send((self.ids, self.values))

    def on_ready(self, now: float) -> None:
        self.ready = True
        if self.pending and not self.sent:
            self._send(now)

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

    def memory_mb(self) -> float:
        """The memory the worker alone holds, in MB (0 when it cannot be read): see :func:`worker_memory_mb`."""
        return worker_memory_mb(self.proc.pid)

    def _forget(self) -> None:
        ends = _worker_side.PARENT_ENDS
        for end in (self.conn, self.death):
            if end in ends:
                ends.remove(end)

    def stop(self) -> None:
        """Ask the worker to end after what it is doing (it has nothing pending)."""
        try:
            self.conn.send(None)
        except Exception:  # noqa: BLE001 - already gone
            pass

    def kill(self) -> None:
        try:
            self.proc.kill()
        except Exception:  # noqa: BLE001
            pass
        self.proc.join(1.0)
        self.close()

    def close(self) -> None:
        self._forget()
        for end in (self.conn, self.death):
            try:
                end.close()
            except Exception:  # noqa: BLE001
                pass


class _Chunks:
    """The runs not handed out yet, handed out in chunks of at most ``most`` runs and at most
    1/``parts`` of what is left (guided self-scheduling)."""

    def __init__(self, ids: np.ndarray, values: np.ndarray, most: int, parts: int) -> None:
        self.ids, self.values, self.most, self.parts = ids, values, max(1, most), max(1, parts)
        self.pos = 0

    def __bool__(self) -> bool:
        return self.pos < len(self.ids)

    def popleft(self, most: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        left = len(self.ids) - self.pos
        size = max(1, min(self.most, -(-left // self.parts), most or self.most))
        a, self.pos = self.pos, self.pos + size
        return self.ids[a:self.pos], self.values[a:self.pos]

    def drain(self) -> tuple[np.ndarray, np.ndarray]:
        a, self.pos = self.pos, len(self.ids)
        return self.ids[a:], self.values[a:]


class WorkerPool:
    """Local worker processes supervised run by run.

    Workers get chunks of runs and answer with one RunBatch per chunk (arrays, not an object per run).
    A run that crashes its worker (segfault, abort, an access violation) is tried once more on a fresh
    worker and then recorded as failed with the reason; a run that exceeds ``timeout_s`` is recorded as
    failed at once. The worker is replaced, the rest of its chunk (including runs done but not yet
    answered) is handed out again and the study goes on.
    """

    def __init__(self, spec: PlanSpec, workers: int, timeout_s: float | None,
                 options: PoolOptions | None = None) -> None:
        import multiprocessing as mp
        self.options = options or PoolOptions()
        self.method = resolve_start_method(self.options.start_method)
        self.ctx = mp.get_context(self.method)
        if self.method == "forkserver":   # the server imports what a run needs once; its children have it
            self.ctx.set_forkserver_preload(["fmusa.runs.worker", "fmusa.runs.spec"])
        self.spec = spec
        self.n = workers
        self.timeout_s = timeout_s
        self.workers: list[_Worker] = []
        self.spare: _Worker | None = None
        self._retiring: list[_Worker] = []
        self._tries: dict[int, int] = {}      # run id -> times it was tried again after its worker died
        self._start_failures = 0
        self._last_exit = ""
        self._payload: bytes | None = None
        #: the lean path's plan and what turns its answers into RunBatches (None: the fmpy path)
        self.lean: LeanView | None = None
        #: workers started, and the replacements among them (crashes, time limits, recycling), for the record
        self.started = 0
        self.replaced = 0

    def _worker_payload(self) -> bytes:
        """The pickled (spec, FMU info) every worker gets: the parent's reading of the unpacked FMU's model
        description goes along (spawn, forkserver) or is inherited (fork), so no worker parses it again."""
        if self._payload is None:
            info = None
            path = Path(self.spec.fmu_path)
            if path.is_dir():
                from fmusa.fmi.info import adopt_fmu_info, read_fmu_info
                try:
                    info = read_fmu_info(path)
                    adopt_fmu_info(info)      # forked workers inherit it; this process reads it again so
                except Exception:  # noqa: BLE001 - the workers report the problem, run by run
                    info = None
            if (info is not None and self.method in LEAN_METHODS
                    and os.environ.get(ENV_LEAN, "").strip() not in ("0", "no", "false")):
                self.lean = lean_view(self.spec, info)
            if info is not None and self.method != "fork":
                info = _lean_info(info, self.spec)
            self._payload = pickle.dumps((self.spec, None if self.method == "fork" else info),
                                         protocol=pickle.HIGHEST_PROTOCOL)
            if self.lean is not None:
                self._payload = pickle.dumps(("lean", self.lean.plan, tuple(self.spec.scale),
                                              tuple(self.spec.offset), self._payload),
                                             protocol=pickle.HIGHEST_PROTOCOL)
        return self._payload

    def _start_worker(self) -> _Worker:
        """A new worker process. Inside a daemonic process (a Dask worker, by default) multiprocessing
        refuses to start children; ours are daemonic themselves and die with their parent
        (:mod:`fmusa.runs.worker`), so the refusal is lifted while one starts."""
        import multiprocessing as mp
        payload = self._worker_payload()
        self.started += 1
        config = mp.current_process()._config
        daemon = config.get("daemon")
        if not daemon:
            return _Worker(self.ctx, self.method, payload, len(self.spec.varied), self.lean is not None)
        config["daemon"] = False
        try:
            return _Worker(self.ctx, self.method, payload, len(self.spec.varied), self.lean is not None)
        finally:
            config["daemon"] = daemon

    def _fresh(self) -> _Worker:
        """A worker that has made no run: the spare (started earlier, often ready already), else a new one;
        a new spare is started in its place, so that the next replacement is ready before it is needed."""
        self.replaced += 1
        w, self.spare = self.spare, None
        if w is None or not w.proc.is_alive():
            if w is not None:
                w.kill()
            w = self._start_worker()
        self.spare = self._start_worker()
        return w

    def close(self) -> None:
        everyone = self.workers + self._retiring + ([self.spare] if self.spare else [])
        for w in everyone:
            w.stop()
        for w in everyone:
            w.proc.join(0.5)
            if w.proc.is_alive():
                w.kill()
            else:
                w.close()
        self.workers, self._retiring, self.spare = [], [], None

    def _chunk_limit(self, w: _Worker) -> int | None:
        """Most runs ``w`` may be given at once: what is left of its ``worker_max_runs``, and
        :data:`MEMORY_CHUNK` with a memory limit (its memory is looked at between chunks and every
        :data:`MEMORY_POLL_S`, so a leak can overshoot the limit by at most a few runs' worth)."""
        most = self.options.worker_max_runs
        left = None if not most else max(1, most - w.answered)
        if self.options.worker_max_memory_mb:
            left = MEMORY_CHUNK if left is None else min(left, MEMORY_CHUNK)
        return left

    def map(self, items, take, chunk: int) -> None:
        """Run ``items`` (a list of (run id, values), or the pair of arrays run ids, values) in chunks of at
        most ``chunk`` runs; ``take`` gets every RunBatch as it arrives. Chunks shrink as the runs left
        do (a worker gets at most 1/(2·workers) of them), so the workers finish together."""
        from multiprocessing.connection import wait

        ids, values = as_arrays(items)
        if not len(ids):
            return
        values = values.reshape(len(ids), len(self.spec.varied))
        queue = _Chunks(ids, values, chunk, 2 * self.n)
        self._tries = {}
        for j, w in enumerate(self.workers):
            if not w.proc.is_alive():   # died while idle (killed from outside): it held no run, none is lost
                w.kill()
                self.workers[j] = self._start_worker()
        while len(self.workers) < min(self.n, len(ids)):
            self.workers.append(self._start_worker())
        if self.options.worker_max_runs and self.spare is None:
            self.spare = self._start_worker()
        now = time.monotonic()
        for w in self.workers:
            if queue:
                w.give(*queue.popleft(self._chunk_limit(w)), now)
        limit_mb = self.options.worker_max_memory_mb
        next_memory = now + MEMORY_POLL_S
        while any(w.pending for w in self.workers):
            watched = {w.conn: w for w in self.workers if w.pending or not w.ready}
            if self.spare is not None and not self.spare.ready:
                watched[self.spare.conn] = self.spare
            polling = bool(self.timeout_s or limit_mb or any(not w.ready for w in watched.values()))
            ready = wait(list(watched), timeout=0.05 if polling else None)
            now = time.monotonic()
            for conn in ready:
                w = watched[conn]
                try:
                    res = conn.recv()
                except (EOFError, OSError):
                    w.proc.join(1.0)
                    reason = exit_reason(w.proc.exitcode)
                    if not w.ready:
                        self._not_started(w, reason, take, queue)
                    else:
                        self._replace(w, reason, take, now, retry=True)
                    continue
                if isinstance(res, tuple):        # ("ready", pid)
                    self._start_failures = 0
                    w.on_ready(now)
                    continue
                if isinstance(res, LeanBatch):    # the lean path's answer: the metrics are reduced here
                    res = from_lean(self.spec, self.lean, res, w.values[:len(res)])
                w.answer(len(res))
                take(res)
                if not w.pending:
                    if self._worn_out(w, limit_mb):
                        w = self._retire(w)
                    if queue:
                        w.give(*queue.popleft(self._chunk_limit(w)), now)
            if self.timeout_s:
                for w in list(self.workers):
                    if w.pending and w.sent and now - w.current()[1] > self.timeout_s:
                        if w.conn.poll():      # an answer arrived after wait(): read it next round
                            continue
                        self._replace(w, timeout_reason(self.timeout_s, "its worker process was stopped"),
                                      take, now, retry=False)
            if limit_mb and now >= next_memory:
                next_memory = now + MEMORY_POLL_S
                for w in list(self.workers):
                    if w.ready and w.pending and (mb := w.memory_mb()) > limit_mb:
                        self._replace(w, self._memory_reason(mb), take, now, retry=True)
            for w in list(self.workers):      # workers that could not start (and took their runs back)
                if not w.ready and now - w.born > STARTUP_LIMIT_S:
                    w.kill()
                    self._not_started(w, f"the worker process did not load the FMU within {STARTUP_LIMIT_S:g} s",
                                      take, queue)
            # workers replaced without a chunk left to finish pick up queued chunks
            for w in self.workers:
                if not w.pending and queue:
                    w.give(*queue.popleft(self._chunk_limit(w)), now)
        self._reap()

    def _memory_reason(self, mb: float) -> str:
        return (f"its worker process used {mb:.0f} MB, more than execution.worker_max_memory_mb = "
                f"{self.options.worker_max_memory_mb:g} (the FMU may leak memory); the worker was replaced")

    def _worn_out(self, w: _Worker, limit_mb: float | None) -> bool:
        most = self.options.worker_max_runs
        return bool((most and w.answered >= most) or (limit_mb and w.memory_mb() > limit_mb))

    def _retire(self, w: _Worker) -> _Worker:
        """``w`` (nothing pending) has made its runs or grown too large: it ends once it reads its stop,
        a fresh worker takes its place."""
        w.stop()
        self._retiring.append(w)
        nw = self._fresh()
        self.workers[self.workers.index(w)] = nw
        self._reap()
        return nw

    def _reap(self) -> None:
        for w in list(self._retiring):
            if not w.proc.is_alive():
                w.proc.join(0)
                w.close()
                self._retiring.remove(w)

    def _not_started(self, w: _Worker, reason: str, take, queue: _Chunks) -> None:
        """``w`` died (or hung) before it was ready: start another; after :data:`START_FAILURES` in a row,
        every run it held and every run left fails with the reason (no worker can load the FMU)."""
        self._start_failures += 1
        w.kill()
        if w is self.spare:
            self.spare = None
            if self._start_failures < START_FAILURES:
                self.spare = self._start_worker()
            return
        j = self.workers.index(w)
        if self._start_failures >= START_FAILURES:
            why = f"no worker process could load the FMU ({reason}, {self._start_failures} times in a row)"
            rest = queue.drain()
            for ids, vals in ((w.ids, w.values), rest):
                if len(ids):
                    take(RunBatch.failed(ids, vals, len(self.spec.rules), why))
            self.workers.pop(j)
            if not self.workers:
                self.workers.append(self._start_worker())
                self._start_failures = START_FAILURES - 1
            return
        nw = self._start_worker()
        self.workers[j] = nw
        if w.pending:
            nw.give(w.ids, w.values, time.monotonic())

    def _replace(self, w: _Worker, reason: str, take, now: float, retry: bool) -> None:
        """``w`` crashed, hangs or grew too large in its current run: that run fails with ``reason`` (or, when
        ``retry``, it was not the worker's first run and it has been tried again fewer than
        ``options.retries`` times, goes first to the fresh worker); the others it was given and has not
        answered go to the fresh worker too. A run that was its worker's first has had its fresh worker."""
        k, since = w.current()
        fresh = int(w.started[0]) <= 1      # the run was this worker's first: a retry would repeat it exactly
        w.kill()
        run = int(w.ids[k]) if len(w.ids) else None
        rest_ids = np.concatenate([w.ids[k:k + 1], w.ids[:k], w.ids[k + 1:]])
        rest_vals = np.concatenate([w.values[k:k + 1], w.values[:k], w.values[k + 1:]])
        tries = self._tries.get(run, 0) if run is not None else 0
        if run is not None and not (retry and not fresh and tries < self.options.retries):
            again = f" (the same on a fresh worker, tried {tries + 1} times)" if tries else ""
            take(RunBatch.failed(rest_ids[:1], rest_vals[:1], len(self.spec.rules), reason + again, now - since))
            rest_ids, rest_vals = rest_ids[1:], rest_vals[1:]
        elif run is not None:
            self._tries[run] = tries + 1
        nw = self._fresh()
        self.workers[self.workers.index(w)] = nw
        if len(rest_ids):
            nw.give(rest_ids, rest_vals, now)


#: (spec, timeout_s, pool options, thread id) -> this Dask worker's supervised pools, the one used last at the end
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
            remove_folder(folder)
    _DASK_FMUS.clear()


def _dask_options(options: PoolOptions | None) -> PoolOptions:
    """The pool options of a Dask worker: a Dask worker runs threads (its event loop, its executor), and
    forking a threaded process can deadlock the child (Python 3.12+ warns of it), so where the platform's
    default is fork and nothing was chosen, its supervised processes come from a fork server instead."""
    import multiprocessing as mp

    options = options or PoolOptions()
    if (options.start_method is None and not os.environ.get(ENV_START_METHOD, "").strip()
            and resolve_start_method() == "fork" and "forkserver" in mp.get_all_start_methods()):
        options = replace(options, start_method="forkserver")
    return options


def _dask_pool(spec: PlanSpec, timeout_s: float | None, options: PoolOptions | None = None) -> WorkerPool:
    """This Dask worker thread's supervised pool (one worker process) for ``spec``, made once and kept among
    the thread's last :data:`DASK_KEEP`. The FMU is unpacked once per Dask worker process, so that supervised
    processes that crash leave no copy behind."""
    import atexit

    thread = threading.get_ident()
    options = _dask_options(options)
    key = (spec, timeout_s, options, thread)
    with _DASK_LOCK:
        if not _DASK_EXIT:
            atexit.register(_close_dask_pools)
            _DASK_EXIT.append(True)
        pool = _DASK_POOLS.pop(key, None)
        if pool is None:
            if spec not in _DASK_FMUS:
                folder = str(extract_fmu(spec.fmu_path, to_run=True)) if Path(spec.fmu_path).is_file() else None
                _DASK_FMUS[spec] = (spec if folder is None else replace(spec, fmu_path=folder), folder)
            pool = WorkerPool(_DASK_FMUS[spec][0], 1, timeout_s, options)
        _DASK_POOLS[key] = pool
        mine = [k for k in _DASK_POOLS if k[-1] == thread]   # this thread uses none of them now but ``pool``
        for old in mine[:-DASK_KEEP]:
            _DASK_POOLS.pop(old).close()
        used = {k[0] for k in _DASK_POOLS}
        for other in [k for k in _DASK_FMUS if k not in used]:
            folder = _DASK_FMUS.pop(other)[1]
            if folder:
                remove_folder(folder)
    return pool


def run_chunk_supervised(spec: PlanSpec, chunk, timeout_s: float | None,
                         options: PoolOptions | None = None) -> RunBatch:
    """A Dask task: run ``chunk`` in a supervised process of this Dask worker, as the local pool does. A run
    that crashes that process, hangs past ``timeout_s`` or fails is recorded as failed with its reason; the
    process is replaced and the chunk goes on, so the Dask worker itself never dies with the FMU."""
    pool = _dask_pool(spec, timeout_s, options)
    out: list[RunBatch] = []
    ids, values = as_arrays(chunk)
    pool.map((ids, values), out.append, max(1, len(ids)))
    return RunBatch.concat(out)


