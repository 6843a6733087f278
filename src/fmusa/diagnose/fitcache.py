"""Running the candidates' fits: in parallel worker processes, each saved as it completes and reused.

A diagnosis is six or more independent fits of a few minutes each; :func:`run_fits` runs them in a pool
(one failing candidate does not sink the others), and with a cache folder writes every fit to
``<cache>/<candidate>.json`` as soon as it is done, so a rerun on the same data (same :func:`data_key`)
computes only what is missing.

An FMU that crashes a worker process (a segfault, an abort) breaks the whole pool; the fits finished stay,
and the ones not finished run again, each in a process of its own, so that only the candidate whose fit
crashes its own process fails (:func:`crash_message`). With one worker the fits run in this process, where
such a crash ends the diagnosis.
"""
from __future__ import annotations

import contextlib
import hashlib
import json
import multiprocessing as mp
import os
import threading
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from fmusa.diagnose import budget as rb
from fmusa.diagnose.calibrate import Fit, fit_candidate
from fmusa.diagnose.interface import ModelInterface
from fmusa.files import atomic_write

__all__ = ["FitJob", "data_key", "fit_to_json", "fit_from_json", "run_fits", "map_in_pool", "close_workers"]

#: (fmu path, candidate, drive, experiments, max_starts, interface[, parallel, agree, start, gate]): the
#: arguments of fit_candidate.
FitJob = tuple


def _fit_job(args: FitJob) -> Fit | rb.LeftOut | str:
    """A candidate's fit, what it spent when the run budget ended, or the reason it failed (one bad
    candidate must not sink the others)."""
    try:
        return fit_candidate(*args)
    except rb.BudgetExhausted as exc:
        return rb.LeftOut(args[1], dict(getattr(exc, "runs", {}) or {}))
    except Exception as exc:  # noqa: BLE001 - reported per candidate in diagnosis.json
        return FailedFit(f"{type(exc).__name__}: {exc}", getattr(exc, "runs", None))


class FailedFit(str):
    """Why a fit failed (a str, as diagnosis.json states it), with the FMU runs it spent before."""
    runs: dict

    def __new__(cls, reason: str, runs: dict | None = None) -> "FailedFit":
        obj = super().__new__(cls, reason)
        obj.runs = dict(runs or {})
        return obj

    def __reduce__(self):
        return (FailedFit, (str(self), self.runs))


def _start_worker(limit: int | None, value, started=None) -> None:
    """A fit worker: Ctrl-C left to the parent, the diagnosis's run budget shared, and (``started``) the
    jobs it starts marked where the parent can read them after the worker died."""
    global _STARTED
    _ignore_sigint()
    if value is not None:
        rb.install(limit, value)
    _STARTED = started


#: in a fit worker: one flag per job of its pool, set when the worker starts that job (None: not tracked)
_STARTED = None


def _tracked_job(index: int, args: FitJob) -> Fit | rb.LeftOut | str:
    """:func:`_fit_job`, marked as started first: when a worker dies, the jobs started and not finished are
    the ones that may have crashed it (the pool itself does not say which job its dead process held)."""
    if _STARTED is not None:
        _STARTED[index] = 1
    return _fit_job(args)


def data_key(experiments: Sequence, drive: str, max_starts: int, fmu: str,
             interface: ModelInterface | None = None, agree: int = 0) -> str:
    """Identity of a diagnosis input: cached fits are reused only for the same data, drive, FMU and
    interface (the FMU's built-in description adds nothing, so caches written before descriptions existed
    stay valid; a description's name is not part of it)."""
    from dataclasses import replace

    from fmusa.diagnose.models import resolve

    h = hashlib.sha256()
    # v2: friction fits fric_x too; v3: held-out folds kept; v4: damping start from the data, the damping held
    # at a constant rate, bounds hit recorded; v5: intervals for correlated residuals; v6: intervals from the
    # column-scaled Jacobian (a parameter in large units no longer gets a zero-width interval)
    h.update(f"{drive}|{max_starts}|v6".encode())
    if interface is not None:
        try:
            default = replace(resolve(None, fmu), name="")
        except Exception:  # noqa: BLE001 - an FMU without a built-in description: the interface is hashed
            default = None
        if replace(interface, name="") != default:
            h.update(repr(replace(interface, name="")).encode())
    h.update(b"|chain-start")     # the chain's fits start from the model so far
    h.update(b"|tol1e-6|chain-starts2")    # stopping tolerances 1e-6; the chain's generic starts capped
    if agree:       # starts stopped once they agree: another fit than all of them
        h.update(f"|agree{agree}".encode())
    h.update(Path(fmu).read_bytes() if Path(fmu).is_file() else str(fmu).encode())
    for e in experiments:
        for a in (e.t, e.displacement, e.force):
            h.update(np.ascontiguousarray(a, dtype=float).tobytes())
    return h.hexdigest()[:16]


def fit_to_json(f: Fit, key: str) -> dict:
    """A fit as the cache stores it, tagged with the key of its input."""
    return {"key": key, "effect": f.effect, "params": f.params, "ci95": {k: list(v) for k, v in f.ci95.items()},
            "rss": f.rss, "n": f.n, "k": f.k, "rmse": f.rmse, "heldout_rmse": f.heldout_rmse,
            "predictions": [p.tolist() for p in f.predictions], "starts_tried": f.starts_tried, "nfev": f.nfev,
            "heldout_folds": list(f.heldout_folds), "at_bounds": list(f.at_bounds), "held": dict(f.held),
            "runs": dict(f.runs), "start_costs": list(f.start_costs), "rounds": dict(f.rounds),
            "heldout_skipped": f.heldout_skipped, "seconds": f.seconds,
            "intervals": {k: ({n: list(v) for n, v in x.items()} if k == "gauss_newton" else x)
                          for k, x in f.intervals.items()}}


def fit_from_json(d: dict) -> Fit:
    """A cached fit back in memory."""
    return Fit(effect=d["effect"], params=d["params"], ci95={k: tuple(v) for k, v in d["ci95"].items()},
               rss=d["rss"], n=d["n"], k=d["k"], rmse=d["rmse"], heldout_rmse=d["heldout_rmse"],
               predictions=[np.array(p) for p in d["predictions"]], starts_tried=d["starts_tried"],
               nfev=d["nfev"], heldout_folds=list(d.get("heldout_folds") or []),
               at_bounds=list(d.get("at_bounds") or []), held=dict(d.get("held") or {}),
               runs=dict(d.get("runs") or {}), start_costs=list(d.get("start_costs") or []),
               rounds=dict(d.get("rounds") or {}), heldout_skipped=str(d.get("heldout_skipped") or ""),
               seconds=float(d.get("seconds") or 0.0),
               intervals={k: ({n: tuple(v) for n, v in x.items()} if k == "gauss_newton" else x)
                          for k, x in (d.get("intervals") or {}).items()})


def _cached(cache_dir: Path | None, name: str, key: str) -> Fit | None:
    """The cached fit of a candidate when it was computed from the same input, else None."""
    path = cache_dir / f"{name}.json" if cache_dir else None
    if path is None or not path.exists():
        return None
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
        return fit_from_json(d) if d.get("key") == key else None
    except (ValueError, KeyError):
        return None


def _save(cache_dir: Path, name: str, fit: Fit, key: str) -> None:
    """Write a fit atomically, so an interrupted run leaves no half-written cache file."""
    atomic_write(cache_dir / f"{name}.json", json.dumps(fit_to_json(fit, key)))


def _ignore_sigint() -> None:
    """A fit worker leaves Ctrl-C to the parent (which stops it), instead of printing a traceback."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def _sigint_ignored():
    """SIGINT ignored in this process while the block starts workers: a spawned worker inherits that, so
    a Ctrl-C during its start-up (before :func:`_ignore_sigint`) cannot print its traceback."""
    import signal

    try:
        old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    except ValueError:      # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def _kill_workers(ex: ProcessPoolExecutor) -> None:
    """Stop the executor's processes at once: its shutdown would wait for the running fits (seconds)."""
    procs = list((getattr(ex, "_processes", None) or {}).values())
    ex.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        try:
            p.kill()
        except (OSError, AttributeError):
            pass
    for p in procs:
        try:
            p.join(2)
        except (OSError, AttributeError, AssertionError):
            pass
    queue = getattr(ex, "_call_queue", None)      # its feeder thread would be waited for at exit
    if queue is not None:
        try:
            queue.cancel_join_thread()
        except (OSError, AttributeError, ValueError):
            pass


def run_fits(jobs: list[FitJob], workers: int, cache_dir: Path | None, key: str,
             progress: bool, budget: rb.RunBudget | None = None) -> dict[str, Fit | rb.LeftOut | str]:
    """Every job's fit (or what it spent when the run budget ended, or the reason it failed), taken from
    the cache when it is there, and saved as soon as it is done. ``budget`` counts (and bounds) the runs
    of every worker."""
    results: dict[str, Fit | rb.LeftOut | str] = {}
    todo = []
    for job in jobs:
        hit = _cached(cache_dir, job[1], key)
        if hit is None:
            todo.append(job)
        else:
            hit.cached = True
            results[job[1]] = hit

    def keep(name: str, r: Fit | str) -> None:
        results[name] = r
        if cache_dir is not None and isinstance(r, Fit):
            _save(cache_dir, name, r, key)
        if progress:
            what = (f"rmse {r.rmse:.4g}, held-out {r.heldout_rmse:.4g}" if isinstance(r, Fit)
                    else "left out: the run budget ended" if isinstance(r, rb.LeftOut) else f"failed: {r}")
            print(f"  fitted {name}: {what}", flush=True)

    # with workers, even one fit runs on them: in this process an FMU that crashes would end the diagnosis (a
    # unit's last fit left after its side-by-side run broke did)
    if workers > 1 and todo:
        _supervised(todo, workers, budget, keep)
    else:
        old = rb.set_current(budget) if budget is not None else None
        try:
            for j in todo:
                keep(j[1], _fit_job(j))
        finally:
            if budget is not None:
                rb.set_current(old)
    return results


#: times a job may crash its worker process before it is reported failed (the second crash is on a process
#: of its own, so it is the job's and not a neighbour's)
CRASHES = 2


def _new_pool(n: int, budget: rb.RunBudget | None, started) -> ProcessPoolExecutor:
    """A spawn pool of ``n`` fit workers sharing the run budget (one counter across every pool made)."""
    limit, value = budget.shared() if budget is not None else (None, None)
    return ProcessPoolExecutor(n, mp_context=mp.get_context("spawn"), initializer=_start_worker,
                               initargs=(limit, value, started))


class _SharedPool:
    """The fit workers kept from one :func:`run_fits` to the next (a diagnosis calls it once per stage, a
    shear study once per stage of each of its 30 units): a spawned worker costs about 2 s of CPU to start
    (the interpreter, numpy, scipy, fmpy) and decides once whether to take an FMU's sensitivities
    (``calibrate._SENS_PAYS``).

    The run budget passes to workers only at their start, so the pool has a counter and a limit of its own,
    lent to each call's budget (:meth:`lent`); the started flags (which job a dead worker may have held) are
    slots numbered across calls. Kept only while the environment is the one its workers were spawned with."""

    SLOTS = 1 << 14

    def __init__(self, workers: int) -> None:
        ctx = mp.get_context("spawn")
        self.workers, self.env = workers, _environment()
        self.count, self.limit = ctx.Value("q", 0), ctx.Value("q", -1)
        self.started = ctx.Array("b", self.SLOTS, lock=False)
        self.next = 0
        self.users = 0                         # calls using the pool now (under _POOL_LOCK)
        self.timer: threading.Timer | None = None
        self.ex = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_start_worker,
                                      initargs=(self.limit, self.count, self.started))

    def slots(self, n: int) -> int | None:
        """The first of ``n`` new started flags, or None when the pool has run out of them."""
        if self.next + n > self.SLOTS:
            return None
        first, self.next = self.next, self.next + n
        return first

    @contextlib.contextmanager
    def lent(self, budget: rb.RunBudget | None):
        """The pool's counter and limit set to ``budget``'s for the block, and its count given back after."""
        self.limit.value = -1 if budget is None or budget.limit is None else int(budget.limit)
        self.count.value = budget.used if budget is not None else 0
        try:
            yield
        finally:
            if budget is not None:
                budget.set_used(self.count.value)


def _environment() -> int:
    """What spawned workers inherited from this process that can change between calls: its environment, its
    working directory (a relative path means what it means here) and its module search path."""
    try:
        cwd = os.getcwd()
    except OSError:        # the directory is gone: a new pool would start elsewhere anyway
        cwd = None
    import sys

    return hash((tuple(sorted(os.environ.items())), cwd, tuple(sys.path)))


_POOL: _SharedPool | None = None
_POOL_LOCK = threading.RLock()
#: seconds the kept workers wait idle for the next call before they end (a notebook's diagnoses minutes apart keep
#: them; a session left open does not keep two interpreters with numpy, scipy and an FMU loaded for hours)
IDLE_S = 300.0


@contextlib.contextmanager
def _pool_in_use(workers: int, jobs: int) -> Iterator[tuple[_SharedPool, int]]:
    """The kept pool (a new one when there is none, it has another size or environment, or no started flags
    left) and the first started flag of ``jobs`` jobs, held in use for the block: the idle timer, cancelled
    while it runs, starts again when the last user leaves."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is not None and (_POOL.workers != workers or _POOL.env != _environment()
                                  or _POOL.next + jobs > _POOL.SLOTS):
            _drop_pool()
        if _POOL is None:
            _POOL = _SharedPool(workers)
        pool = _POOL
        pool.users += 1
        if pool.timer is not None:
            pool.timer.cancel()
            pool.timer = None
        first = pool.slots(jobs)
    try:
        yield pool, first
    finally:
        with _POOL_LOCK:
            pool.users -= 1
            if pool.users == 0 and _POOL is pool and IDLE_S > 0:
                pool.timer = threading.Timer(IDLE_S, _drop_if_idle, args=(pool,))
                pool.timer.daemon = True
                pool.timer.start()


def _drop_if_idle(pool: _SharedPool) -> None:
    """The idle timer's end: the pool ends unless a call took it up meanwhile (or it was replaced)."""
    with _POOL_LOCK:
        if _POOL is pool and pool.users == 0:
            _drop_pool()


def _drop_pool(kill: bool = False) -> None:
    """Shut the kept pool down (``kill``: at once, as for a broken pool or an interrupt)."""
    global _POOL
    with _POOL_LOCK:
        pool, _POOL = _POOL, None
        if pool is not None and pool.timer is not None:
            pool.timer.cancel()
            pool.timer = None
    if pool is None:
        return
    if kill:
        _kill_workers(pool.ex)
    else:
        pool.ex.shutdown(wait=True)


def close_workers() -> None:
    """End the kept fit workers (they stay alive from one diagnosis to the next): a benchmark's diagnosis then
    starts them as a new user's first one does, and their CPU time reaches this process's children's."""
    _drop_pool()


def map_in_pool(fn, calls: Sequence[tuple], workers: int) -> list:
    """``fn(*args)`` for every args of ``calls``, in the kept pool of fit workers when ``workers`` > 1 and
    there are several (the stages of a study that follow its diagnoses, unit by unit), in this process
    otherwise; the results in the order of ``calls``. ``fn`` must be a module-level function (it is pickled).
    An exception of a call is raised here; a worker that dies breaks the pool, which is dropped, and raises
    BrokenProcessPool (nothing here supervises: these calls run FMUs a diagnosis has run already)."""
    if workers <= 1 or len(calls) <= 1:
        return [fn(*args) for args in calls]
    with _pool_in_use(workers, 0) as (pool, _):
        try:
            with pool.lent(None), _sigint_ignored():
                futs = [pool.ex.submit(fn, *args) for args in calls]
            return [f.result() for f in futs]
        except BaseException:
            _drop_pool(kill=True)
            raise


def each_in_pool(fn, calls: Sequence[tuple], workers: int) -> Iterator[tuple[int, Any]]:
    """:func:`map_in_pool`'s calls in the kept pool, each ``(index, result)`` as soon as it is done (a caller
    that says, and keeps, what finished). An exception of a call is raised here. A worker that dies breaks the
    pool: it is dropped, the calls done before are yielded, and BrokenProcessPool is raised for the caller to
    run the others its own way (one of them crashed its process)."""
    given: set[int] = set()
    with _pool_in_use(workers, 0) as (pool, _):
        with pool.lent(None), _sigint_ignored():
            futs = {pool.ex.submit(fn, *args): i for i, args in enumerate(calls)}
        try:
            for fut in as_completed(futs):
                if isinstance(fut.exception(), BrokenProcessPool):
                    break
                given.add(futs[fut])
                yield futs[fut], fut.result()
            else:
                return
        except BaseException:
            _drop_pool(kill=True)
            raise
    done = [(i, f) for f, i in futs.items()
            if i not in given and f.done() and not isinstance(f.exception(), BrokenProcessPool)]
    _drop_pool(kill=True)
    for i, f in done:
        yield i, f.result()
    raise BrokenProcessPool("a worker process died (an FMU that crashed?): the calls not done did not run")


def _supervised(todo: list[FitJob], workers: int, budget: rb.RunBudget | None, keep) -> None:
    """The jobs in the kept pool of ``workers`` processes (:class:`_SharedPool`); when a process dies (an FMU
    that crashes), the fits finished stay, and the jobs not finished run again, each in a process of its own
    (so a second crash is the job's own: it fails with the reason, the others get their fits)."""
    broken = False
    with _pool_in_use(workers, len(todo)) as (pool, first), pool.lent(budget):
        ex, started = pool.ex, pool.started
        try:
            with _sigint_ignored():    # the workers start with Ctrl-C ignored (kept across their exec)
                futs = {ex.submit(_tracked_job, first + i, j): i for i, j in enumerate(todo)}
            for fut in as_completed(futs):
                if isinstance(fut.exception(), BrokenProcessPool):
                    broken = True
                    break
                keep(todo[futs[fut]][1], _outcome(fut))
        except BaseException:     # Ctrl-C, SIGTERM: stop the fits now (the saved ones stay), not after them
            _drop_pool(kill=True)
            raise
        if not broken:
            return
    # the pool is broken: every future not finished holds BrokenProcessPool; those done before the break
    # hold their fits
    done = set()
    for fut, i in futs.items():
        if fut.done() and not isinstance(fut.exception(), BrokenProcessPool):
            keep(todo[i][1], _outcome(fut))
            done.add(i)
    _drop_pool(kill=True)
    left = [i for i in range(len(todo)) if i not in done]
    crashes = {i: 1 for i in left if started[first + i]}   # running when a process died: each may be the cause
    _one_per_process([todo[i] for i in left], [crashes.get(i, 0) for i in left], workers, budget, keep)


def _outcome(fut) -> Fit | rb.LeftOut | str:
    """A finished future's fit, or why it failed (an exception the fit itself did not catch)."""
    try:
        return fut.result()
    except Exception as exc:  # noqa: BLE001 - reported per candidate
        return FailedFit(f"{type(exc).__name__}: {exc}")


def _one_per_process(jobs: list[FitJob], crashes: list[int], workers: int, budget: rb.RunBudget | None,
                     keep) -> None:
    """Each job in a pool of one process of its own, at most ``workers`` at a time: a process that dies
    was fitting that job and no other. A job that crashes its process again (``crashes`` counts the times it
    may have before) is reported failed, naming the candidate, how the process ended and what to do."""
    from concurrent.futures import FIRST_COMPLETED, wait

    queue = list(zip(jobs, crashes))
    running: dict = {}       # future -> (job, crashes so far, its executor, its process)
    try:
        while queue or running:
            while queue and len(running) < workers:
                job, n = queue.pop(0)
                started = mp.get_context("spawn").Array("b", 1, lock=False)
                ex = _new_pool(1, budget, started)
                with _sigint_ignored():
                    fut = ex.submit(_tracked_job, 0, job)
                procs = list((getattr(ex, "_processes", None) or {}).values())
                running[fut] = (job, n, ex, procs[0] if procs else None, started)
            finished, _ = wait(list(running), return_when=FIRST_COMPLETED)
            for fut in finished:
                job, n, ex, proc, started = running.pop(fut)
                if not isinstance(fut.exception(), BrokenProcessPool):
                    ex.shutdown(wait=True)
                    keep(job[1], _outcome(fut))
                    continue
                code = _exit_code(proc)
                _kill_workers(ex)
                if not started[0]:       # died before the fit began: the process, not the FMU, failed
                    keep(job[1], FailedFit(start_failure_message(job, code)))
                elif n + 1 < CRASHES:
                    queue.append((job, n + 1))
                else:
                    keep(job[1], FailedFit(crash_message(job, code, n + 1)))
    except BaseException:     # Ctrl-C, SIGTERM: stop every fit now
        for _, _, ex, _, _ in running.values():
            _kill_workers(ex)
        raise


def _exit_code(proc, wait_s: float = 5.0) -> int | None:
    """How the pool's process ended. Its executor's own thread reaps it too: when that thread's waitpid wins,
    ours fails (ECHILD) and reads None until the winner stores the code, so this asks again for a while."""
    import time

    if proc is None:
        return None
    end = time.monotonic() + wait_s
    proc.join(wait_s)
    while True:
        code = proc.exitcode
        if code is not None or time.monotonic() > end:
            return code
        time.sleep(0.02)


def start_failure_message(job: FitJob, code: int | None) -> str:
    """Why a candidate's fit failed when its worker process died before it began the fit: not the FMU. The
    usual cause is a script that starts a diagnosis without guarding its entry point: fit workers are spawned
    (a fresh interpreter that imports the script's main module), as every process is on Windows, and an
    unguarded script starts the diagnosis again inside each worker, which Python stops."""
    from fmusa.runs.pool import exit_reason

    return (f"the worker process for candidate {str(job[1])!r} ended before it began the fit "
            f"({exit_reason(code)}): the FMU was not run. Fit workers are started by "
            f"'spawn' (a fresh Python that imports your main module), so a script that runs a diagnosis must "
            f"guard it: put the call under `if __name__ == \"__main__\":`, or run with one worker "
            f"(workers=1, --workers 1). The worker's own error is printed above in this output")


def crash_message(job: FitJob, code: int | None, times: int) -> str:
    """Why a candidate's fit failed when its FMU killed the worker process: the candidate, the FMU, how the
    process ended, and the ways on. Not "run it with one worker to see the FMU's log": the messages the FMU
    logs through fmusa are kept in memory and die with the process, and in fmusa's own process (one worker)
    the crash ends the whole diagnosis; what the FMU prints itself reaches the terminal from a worker too."""
    from fmusa.runs.pool import exit_reason

    fmu, name = job[0], str(job[1])
    added = name.split("+")[-1]       # a chain's fit is named model-so-far+added-effect
    return (f"the FMU process died while fitting candidate {name!r}, {times} times (the last in a process of "
            f"its own, so it is this candidate's fit): {exit_reason(code)}, exit code {code}; the other "
            f"candidates are not affected. The FMU {fmu} crashes in this fit: check it "
            f"with `fmusa inspect {fmu}` and with the tool that exported it (what the FMU printed before it "
            f"died is above in this output), or leave {added} out of the candidates (--candidates, or "
            f"effects: candidates in a diagnosis study file)")
