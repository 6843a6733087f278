"""The worker side of the supervised pool (:mod:`fmusa.runs.pool`): what runs in each worker process.

This module imports only the standard library at its top, so that a worker started by ``spawn`` or
``forkserver`` (Windows and macOS, or ``execution.start_method``) loads no more than a run needs: the spec
and the model description arrive pickled (:func:`main` unpickles them once it has set itself up), and
:mod:`fmusa.runs.spec` brings numpy, fmpy and the FMI layer. A worker loads its FMU and tells the parent
"ready" before it is given a run, so its start-up is never charged to a run's time limit.
"""
from __future__ import annotations

import os
import pickle
import sys
import threading

PR_SET_PDEATHSIG = 1          # linux/prctl.h

#: The start methods a pool can use (each platform offers some of them; see fmusa.runs.pool).
START_METHODS = ("spawn", "forkserver", "fork")

#: the parent's ends of the pipes of the workers started before this one: a forked worker closes its
#: copies at once, so that a worker never keeps a sibling's parent-death pipe open (see :func:`main`)
PARENT_ENDS: list = []


def _kernel_death_signal() -> None:
    """Linux's fast path: the kernel kills this process with SIGKILL when its parent thread ends
    (``prctl(PR_SET_PDEATHSIG)``). Anything that goes wrong here (not Linux, no libc by that name, a ctypes
    that refuses ``CDLL(None)`` as Windows' does with TypeError) leaves the pipe watch alone in charge."""
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes
        import signal
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    except Exception:  # noqa: BLE001 - any failure: the pipe watch still ends the worker
        pass


def watch_parent(death) -> None:
    """End this process as soon as its parent dies, however it dies (``kill -9`` too), on every platform:
    ``death`` is the reading end of a pipe whose only writing end the parent holds and never writes to, so
    reading it returns (EOF) exactly when the parent is gone. A worker deep in an FMU call or blocked on its
    own pipe would otherwise live on. No ``getppid``: under forkserver the parent is the fork server."""
    _kernel_death_signal()

    def watch() -> None:
        try:
            death.recv_bytes()
        except BaseException:  # noqa: BLE001 - EOF (the parent is gone) or a broken pipe: the same
            pass
        os._exit(1)

    threading.Thread(target=watch, name="fmusa-parent-watch", daemon=True).start()


def main(conn, death, started, payload: bytes) -> None:
    """A pool worker. ``payload`` (pickled by the parent): (the PlanSpec, the parent's FMU info for the
    spec's unpacked FMU or None), or for the lean path ("lean", the plan of :mod:`fmusa.fmi.lean`, scale,
    offset, that first payload pickled, for an FMU the lean path cannot load). The worker loads the FMU,
    says ``("ready", pid)``, then receives chunks (run ids, study values) and sends back RunBatches (lean:
    LeanBatches, which the parent turns into RunBatches), one message per chunk (more for a chunk that
    takes longer than half a second). Before each run it counts up ``started`` and stamps its
    start time, so the parent knows which run crashed or hangs, and since when. ``None`` ends it."""
    import faulthandler
    import signal

    for end in PARENT_ENDS:        # forked: the copies of earlier workers' parent-side pipe ends
        try:
            end.close()
        except Exception:  # noqa: BLE001 - already closed
            pass
    PARENT_ENDS.clear()
    watch_parent(death)
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # the parent decides when to stop
    faulthandler.disable()   # a crashing FMU is reported by the parent, not by a Python stack dump
    # numpy's OpenBLAS starts a thread per core at import, ~0.1 s of CPU of a spawned worker's start, for
    # nothing: a worker's numpy reduces small arrays, and the pool runs one worker per core already (set
    # before the payload is unpickled: the fmpy path's spec brings numpy)
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    job = pickle.loads(payload)
    lean_chunks = job[0] == "lean"
    if lean_chunks:          # ("lean", plan, scale, offset, the fmpy payload): ctypes only, when it loads
        _, plan, scale, offset, fallback = job
        fmu = _lean_fmu(plan)
        if fmu is not None:
            _serve_lean(conn, started, fmu, scale, offset)
            return
        job = pickle.loads(fallback)     # the FMU as fmpy loads it: runs and errors are then fmpy's
    _serve(conn, started, *job, lean_chunks=lean_chunks)


def _lean_fmu(plan: dict):
    """The FMU loaded and instantiated on ctypes alone (:mod:`fmusa.fmi.lean`), or None when that fails in
    any way: the fmpy path then loads it, and the runs fail, if they must, with fmpy's reasons."""
    try:
        from fmusa.fmi.lean import LeanFMU
        return LeanFMU(plan)
    except Exception:  # noqa: BLE001 - fmpy's path says why
        return None


def _serve_chunks(conn, answer) -> None:
    """Say "ready", then answer chunk after chunk (run ids, study values) until the parent sends None or goes."""
    conn.send(("ready", os.getpid()))
    while True:
        try:
            msg = conn.recv()
        except (EOFError, OSError):
            return
        if msg is None:
            return
        conn.send(answer(*msg))


def _serve_lean(conn, started, fmu, scale, offset) -> None:
    """The lean worker's loop: chunks (run ids, study values as array('d')) in, LeanBatches out."""
    from fmusa.runs.lean import run_rows

    _serve_chunks(conn, lambda ids, values: run_rows(fmu, ids, values, scale, offset, started, emit=conn.send))


def _serve(conn, started, spec, info, lean_chunks: bool = False) -> None:
    """The fmpy path's loop: chunks in, RunBatches out (chunks as a lean worker gets them: made arrays)."""
    if info is not None:     # the parent's reading of the model description: not parsed again here
        from fmusa.fmi.info import adopt_fmu_info
        adopt_fmu_info(info)
    from fmusa.runs.spec import plan_for, run_batch

    try:                     # load and instantiate now, before the first run is timed
        plan_for(spec)
    except Exception:  # noqa: BLE001 - run_batch fails each run with the reason
        pass
    if lean_chunks:
        import numpy as np

    def answer(ids, values):
        if lean_chunks:
            ids = np.asarray(ids, dtype=np.int64)
            values = np.frombuffer(values, dtype=float).reshape(len(ids), len(spec.varied))
        return run_batch(spec, ids, values, started, emit=conn.send)

    _serve_chunks(conn, answer)
