"""Before a study's first run: the FMU loads, and a run on a reused instance equals a run on a fresh one.

fmusa reuses one FMU instance per worker, so every run but a worker's first starts from what the instance
was brought back to. Real exports get that wrong in many ways: after ``fmi2Reset`` a Dymola 2022x FMU
restarts its state at 0 instead of its start value, a 20-sim 4.6 FMU outputs zeros, an Amesim 15 FMU
returns fmi2Error. Every run would then be ``ok`` and wrong, and the answer would change with the number
of workers. So, before the first batch, :func:`check_reuse` runs point A on a fresh instance, then point
B and point A again on the same instance, brought back between runs by ``fmi2Reset``; every output the
metrics read must be identical. Where it is not (or the reset fails), the same is tried with a state
snapshot taken right after instantiation (``fmi2SetFMUstate``, where the FMU can get and set its state),
and else every run gets a new instance (its library loaded anew, as ``fmpy.simulate_fmu`` does). If even
that does not reproduce the fresh run, the FMU's runs depend on something fmusa cannot reset, and the
study is refused.

The check also loads the FMU once before anything is written: a binary that cannot load (a missing
library or symbol, the wrong platform) stops the study at once with the loader's reason and the fix
(:class:`FMULoadError`). An FMU other than our own is checked in a child process, so that a crash costs
the check, not the study. Verdicts are cached per FMU digest and run set-up (:func:`cache_dir`).
"""
from __future__ import annotations

import hashlib
import json
import math
import re
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from fmusa.errors import FmusaError
from fmusa.files import ENV_CACHE, atomic_write, cache_dir  # noqa: F401 - ENV_CACHE: its users import it here
from fmusa.fmi.info import FMUError, read_fmu_info, select_interface
from fmusa.runs.spec import PlanSpec, plan_for, release_plan, runner_for

#: Bumped when the check changes what it decides, so that older cached verdicts are not used.
_CHECK_VERSION = 1


class FMULoadError(FmusaError, RuntimeError):
    """The FMU's binary cannot be loaded or instantiated on this machine (a missing library or symbol, the
    wrong platform, an instantiation the FMU refuses); the message holds the loader's reason and the fix.

    Fix: what the message says after "Fix:": install the library the binary needs, re-export the FMU for
    this platform (or with its C sources, which fmusa builds), or export or download a damaged FMU again.
    Nothing was written: an earlier runs.csv in ``--out`` is where it was."""

    exit_code = 1


class FMUReuseError(FmusaError, RuntimeError):
    """Runs of the FMU are not reproducible even on a new instance with its library loaded anew: its
    results depend on something fmusa cannot reset (state kept in its process, a nondeterministic
    solver), so no run of it could be trusted.

    Fix: ask the FMU's exporter for an export whose runs depend only on their parameters (no global state
    in its binary, a deterministic solver); the message names the output and time where two runs of the
    same point differed."""

    exit_code = 1


@dataclass
class ReuseVerdict:
    """How the study's runs are made (``mode``: reset | snapshot | fresh), why, and what it costs."""
    mode: str
    why: str
    #: one entry per way tried: mode, whether it reproduced the fresh run, what differed, its cost
    tried: list[dict] = field(default_factory=list)
    #: wall time of bringing the instance back before a run in the chosen mode, in ms (None: not measured)
    restore_ms: float | None = None
    #: the check's wall time, in s, with loading the FMU (which its runs here then use); 0 when cached
    check_s: float = 0.0
    cached: bool = False
    #: where the check ran: "this process" or "a child process"
    where: str = "this process"

    def as_dict(self) -> dict:
        return asdict(self)


# ------------------------------------------------------------------------------------------ loading
def load_problem(fmu: str, exc: BaseException) -> str:
    """The loader's reason why ``fmu`` cannot be loaded or instantiated here, with the fix."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    lib = re.search(r"([\w.+-]+\.(?:so(?:\.\d+)*|dll|dylib)): cannot open shared object file", text)
    if lib:
        fix = (f"the binary needs the library {lib.group(1)}, which this machine does not have: install it "
               f"(on Debian/Ubuntu: apt-file search {lib.group(1)} names the package), or re-export the FMU "
               f"with its runtime linked statically or with its C sources, which fmusa can build")
    elif "undefined symbol" in text:
        fix = ("the binary needs a symbol that no loaded library provides: re-export the FMU against this "
               "platform's libraries, or with its C sources")
    elif re.search(r"file too short|cannot read file data|truncated", text, re.I):
        fix = "the binary is damaged or truncated: export or download the FMU again"
    elif re.search(r"wrong ELF class|invalid ELF header|not a valid Win32|mach-o", text, re.I):
        fix = "the binary is for another platform: re-export the FMU for this one, or with its C sources"
    elif "instantiate" in text.lower():
        fix = ("fmi2Instantiate failed: the FMU's log above says why (a licence, a resource file, a GUID "
               "that does not match its model description)")
    else:
        fix = "check that the FMU was exported for this platform, or re-export it with its C sources"
    return f"{fmu}: the FMU cannot be loaded on this machine: {text}. Fix: {fix}"


def _is_load_failure(exc: BaseException) -> bool:
    """Whether ``exc``, raised while an FMU was loaded or instantiated, says the binary cannot be loaded here
    (fmpy raises a plain Exception for a library that does not load; an FMUError for a missing binary), as
    opposed to a mistake in the input, which is raised as it is."""
    return not (isinstance(exc, FmusaError) and not isinstance(exc, FMUError))


# ------------------------------------------------------------------------------------------ the check
def _difference(first: np.ndarray, again: np.ndarray, outputs: Sequence[str], times: np.ndarray) -> str:
    """Where run ``again`` differs most from run ``first`` (the same point), in words."""
    if first.shape != again.shape:
        return f"the runs have {len(first)} and {len(again)} samples"
    diff = np.abs(first - again)
    diff[np.isnan(first) & np.isnan(again)] = 0.0
    diff[np.isnan(diff)] = np.inf
    i, j = np.unravel_index(int(np.argmax(diff)), diff.shape)
    return (f"{outputs[j]} = {first[i, j]:.10g} on a fresh instance, {again[i, j]:.10g} on the reused one "
            f"(t = {times[i]:.6g} s)")


def _run_sequence(spec: PlanSpec, mode: str, a: Sequence[float], b: Sequence[float], shared: bool,
                  budget: _Budget) -> dict:
    """Point ``a`` on a fresh instance, then ``b`` and ``a`` again on the same instance brought back by
    ``mode``; the entry of :attr:`ReuseVerdict.tried` (with the two runs of ``a`` under private keys).
    ``shared``: the instance is this process's RunPlan for ``spec`` (:func:`~fmusa.runs.spec.plan_for`),
    which the study's runs here then go on using, so the check costs its runs and nothing else."""
    from fmusa.fmi.plans import RunPlan

    entry: dict = {"mode": mode, "reproduced": False, "detail": "", "restore_ms": None}
    if shared and mode == spec.reuse:
        try:
            plan = plan_for(spec)
        except Exception as exc:
            if not _is_load_failure(exc):
                raise
            raise FMULoadError(load_problem(spec.fmu_path, exc)) from None
        if plan.runner.is_fresh:
            return _sequence(entry, plan, a, b, spec, mode, False, budget)
        release_plan(spec)          # used before: the check needs a fresh instance
        return _run_sequence(spec, mode, a, b, shared, budget)
    try:
        runner = runner_for(replace(spec, reuse=mode))
    except Exception as exc:
        if not _is_load_failure(exc):
            raise
        if mode == "reset":
            raise FMULoadError(load_problem(spec.fmu_path, exc)) from None
        entry["detail"] = f"could not be instantiated: {' '.join(str(exc).split())[:300]}"
        return entry
    try:
        plan = RunPlan(runner, spec.varied, dict(spec.fixed), spec.outputs, spec.stop_time, spec.step,
                       dict(spec.inputs))
    except BaseException:
        runner.close()
        raise
    return _sequence(entry, plan, a, b, spec, mode, True, budget)


@dataclass
class _Budget:
    """The time limit of each run of the check (the study's ``execution.timeout_s``), and a call made as each
    run starts (a child process tells its parent, which stops it when a run outlasts the limit)."""
    timeout_s: float | None = None
    on_run: Callable[[], None] | None = None


def _timed(plan, point, budget: _Budget):
    """``plan(point)`` stopped at its first communication point past the limit (a single doStep is bounded
    by the FMU's own budget, which the study's spec sets, or by the parent of the check's process)."""
    if budget.on_run is not None:
        budget.on_run()
    if budget.timeout_s is None:
        return plan(point)
    plan.runner.deadline = time.monotonic() + budget.timeout_s
    try:
        return plan(point)
    finally:
        plan.runner.deadline = None


def _sequence(entry: dict, plan, a, b, spec: PlanSpec, mode: str, close: bool, budget: _Budget) -> dict:
    runner = plan.runner
    try:
        try:
            first = _timed(plan, a, budget)
        except Exception as exc:
            entry["detail"] = f"the first run failed on a fresh instance: {' '.join(str(exc).split())[:300]}"
            entry["first_failed"] = True
            return entry
        costs = []
        t_runs = time.perf_counter()
        for point in (b, a):
            t0 = time.perf_counter()
            try:
                runner.restore()
            except Exception as exc:
                entry["detail"] = (f"bringing the instance back failed ({mode}): "
                                   f"{' '.join(str(exc).split())[:300]}")
                return entry
            costs.append(time.perf_counter() - t0)
            try:
                again = _timed(plan, point, budget)
            except Exception as exc:
                if point is a:
                    entry["detail"] = (f"the run that worked on a fresh instance failed on the reused one: "
                                       f"{' '.join(str(exc).split())[:300]}")
                    return entry
        entry["restore_ms"] = 1e3 * min(costs)
        # the check's own cost: the two runs after the first and bringing the instance back before each
        entry["extra_ms"] = 1e3 * (time.perf_counter() - t_runs)
        if np.array_equal(first, again, equal_nan=True):
            entry["reproduced"] = True
            entry["detail"] = "every output equal at every sample"
        else:
            entry["detail"] = _difference(first, again, list(spec.outputs), plan.times)
        entry["_first"] = first
        return entry
    finally:
        if close:
            runner.close()


def _can_snapshot(spec: PlanSpec) -> bool:
    try:
        info = read_fmu_info(spec.fmu_path)
        iface = select_interface(info, spec.interface)
    except FmusaError:
        return False
    md = info.model_description
    part = md.coSimulation if iface == "co-simulation" else md.modelExchange
    return bool(getattr(part, "canGetAndSetFMUstate", False))


def check_reuse(spec: PlanSpec, a: Sequence[float], b: Sequence[float], shared: bool = False,
                timeout_s: float | None = None, on_run: Callable[[], None] | None = None) -> ReuseVerdict:
    """The way runs of ``spec`` must be made so that each equals a run on a fresh instance, found by running
    point ``a`` fresh, then ``b`` and ``a`` again on the same instance (FMU values of ``spec.varied``), in
    this process. Raises :class:`FMULoadError` when the FMU cannot be loaded, :class:`FMUReuseError` when
    not even a new instance reproduces a fresh run."""
    t0 = time.perf_counter()
    a, b = [float(x) for x in a], [float(x) for x in b]
    budget = _Budget(timeout_s, on_run)
    tried = []
    spec = replace(spec, reuse="reset")
    reset = _run_sequence(spec, "reset", a, b, shared, budget)
    tried.append(reset)
    if reset.get("first_failed") and b != a:      # point a does not run: check with b first instead
        reset = _run_sequence(spec, "reset", b, a, shared, budget)
        tried.append(reset)
    if reset.get("first_failed"):
        return _verdict("fresh", "the check's points fail on a fresh instance too, so the reset could not "
                        "be checked; every run gets a new instance (always right, costs an instantiation)",
                        tried, None, t0)
    if reset["reproduced"]:
        return _verdict("reset", "fmi2Reset restores the state of a fresh instance: the rerun of the first "
                        "point after another point equals its run on a fresh instance", tried,
                        reset["restore_ms"], t0)
    if shared:
        release_plan(spec)      # runs here will use another way: no instance left behind
    first_a, second = (a, b) if reset is tried[0] else (b, a)
    problem = f"after fmi2Reset {reset['detail']}"
    if _can_snapshot(spec):
        snap = _run_sequence(spec, "snapshot", first_a, second, False, budget)
        tried.append(snap)
        if snap["reproduced"]:
            return _verdict("snapshot", f"{problem}; a state snapshot taken right after instantiation "
                            f"(fmi2SetFMUstate) restores it", tried, snap["restore_ms"], t0)
        problem += f"; fmi2SetFMUstate to a snapshot: {snap['detail']}"
    fresh = _run_sequence(spec, "fresh", first_a, second, False, budget)
    tried.append(fresh)
    if not fresh["reproduced"]:
        raise FMUReuseError(
            f"{spec.fmu_path}: runs of this FMU are not reproducible: {problem}; and even on a new instance, "
            f"its library loaded anew, {fresh['detail']}. Its results depend on something fmusa cannot reset "
            f"(state kept in its process, a nondeterministic solver): ask its exporter, or run each point in "
            f"a process of its own")
    if "_first" in reset and "_first" in fresh and not np.array_equal(reset["_first"], fresh["_first"],
                                                                      equal_nan=True):
        raise FMUReuseError(f"{spec.fmu_path}: two fresh instances of this FMU give different results for "
                            f"the same point: its results depend on something fmusa cannot reset")
    return _verdict("fresh", f"{problem}; every run gets a new instance", tried, fresh["restore_ms"], t0)


def _verdict(mode: str, why: str, tried: list[dict], restore_ms: float | None, t0: float) -> ReuseVerdict:
    public = [{k: v for k, v in e.items() if not k.startswith("_") and k != "first_failed"} for e in tried]
    return ReuseVerdict(mode, why, public, restore_ms, time.perf_counter() - t0)


# ------------------------------------------------------------------------------------------ isolated
def _child(conn, spec: PlanSpec, a, b, timeout_s) -> None:
    try:
        conn.send(("ok", check_reuse(spec, a, b, timeout_s=timeout_s, on_run=lambda: conn.send(("run",)))))
    except FmusaError as exc:
        conn.send(("error", type(exc).__name__, str(exc)))
    except BaseException as exc:     # noqa: BLE001 - anything else is reported, not lost
        conn.send(("bug", type(exc).__name__, str(exc)))
    finally:
        conn.close()


def _isolated_once(spec: PlanSpec, a, b, timeout_s: float | None, start_method: str | None
                   ) -> tuple[object, int, float]:
    """One run of :func:`check_reuse` in a child process: (what it sent last, or "timeout" or None for a
    crash; how many of its runs had started; the limit in force when it stopped)."""
    import multiprocessing as mp

    from fmusa.runs.pool import resolve_start_method, start_process

    method = resolve_start_method(start_method)
    ctx = mp.get_context(method)
    recv, send = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(send, spec, list(a), list(b), timeout_s), name="fmusa-preflight",
                       daemon=True)
    start_process(proc, method)     # spawn, forkserver: without running the program's main module again
    send.close()
    # the process's start and the FMU's loading, then each run within the study's limit of a run: a run
    # that hangs in one doStep is stopped here, with the whole check
    first_limit, run_limit = 60.0, (1.1 * timeout_s + 0.5 if timeout_s else 600.0)
    msg, limit, started = None, first_limit, 0
    try:
        while True:
            if not recv.poll(limit):
                msg = "timeout"
                break
            try:
                msg = recv.recv()
            except EOFError:
                msg = None
                break
            if msg != ("run",):
                break
            started += 1
            limit = run_limit
    finally:
        if proc.is_alive():
            proc.kill()
        proc.join(5)
        recv.close()
    if msg is None:
        from fmusa.runs.pool import exit_reason
        msg = ("crash", exit_reason(proc.exitcode))
    return msg, started, limit


def check_reuse_isolated(spec: PlanSpec, a: Sequence[float], b: Sequence[float],
                         timeout_s: float | None, start_method: str | None = None) -> ReuseVerdict:
    """:func:`check_reuse` in a child process: an FMU that crashes or hangs costs the check, not the study.
    When one of the check's two points outlasts the time limit of a run, the check is made again with the
    other point alone (its rerun after itself still shows a state the reset does not restore); a check that
    crashes or hangs again gives ``fresh`` (always right) and says why."""
    t0 = time.perf_counter()
    msg, started, limit = _isolated_once(spec, a, b, timeout_s, start_method)
    if msg == "timeout" and started in (1, 2) and list(a) != list(b):
        other = list(b) if started == 1 else list(a)        # the first run is a, the second b
        msg, started, limit = _isolated_once(spec, other, other, timeout_s, start_method)
    if isinstance(msg, tuple) and msg[0] == "ok":
        verdict = msg[1]
        verdict.where = "a child process"
        verdict.check_s = time.perf_counter() - t0
        return verdict
    if isinstance(msg, tuple) and msg[0] == "error":
        cls = {"FMULoadError": FMULoadError, "FMUReuseError": FMUReuseError}.get(msg[1], FMULoadError)
        raise cls(msg[2])
    if isinstance(msg, tuple) and msg[0] == "bug":
        raise RuntimeError(f"the reset check failed in its process: {msg[1]}: {msg[2]}")
    if msg == "timeout":
        why = (f"a run of the reset check did not finish within {limit:g} s" if started else
               f"the FMU did not load within {limit:g} s")
    else:
        why = f"during the reset check {msg[1]}"
    return ReuseVerdict("fresh", f"{why}; every run gets a new instance (always right, costs an instantiation)",
                        [], None, time.perf_counter() - t0, where="a child process")


# ------------------------------------------------------------------------------------------ cache
def _cache_key(spec: PlanSpec, digest: str, a, b) -> str:
    what = [_CHECK_VERSION, digest, spec.interface, spec.solver, spec.relative_tolerance, spec.step_size,
            list(spec.varied), [[k, repr(v)] for k, v in spec.fixed], [[k, repr(v)] for k, v in spec.inputs],
            list(spec.outputs), spec.stop_time, spec.step, [repr(float(x)) for x in a],
            [repr(float(x)) for x in b]]
    return hashlib.sha256(json.dumps(what).encode("utf-8")).hexdigest()[:32]


_MEMORY: dict[tuple[str, str], ReuseVerdict] = {}


def forget_verdicts() -> None:
    """Forget the verdicts this process remembers (the files in :func:`cache_dir` stay)."""
    _MEMORY.clear()


def _read_cached(key: str) -> ReuseVerdict | None:
    folder = cache_dir()
    if (str(folder), key) in _MEMORY:
        return _MEMORY[str(folder), key]
    path = folder / f"reuse-{key}.json"
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        verdict = ReuseVerdict(**data)
    except (OSError, ValueError, TypeError):
        return None
    if verdict.mode not in ("reset", "snapshot", "fresh"):
        return None
    _MEMORY[str(folder), key] = verdict
    return verdict


def _write_cached(key: str, verdict: ReuseVerdict) -> None:
    folder = cache_dir()
    _MEMORY[str(folder), key] = verdict
    try:
        atomic_write(folder / f"reuse-{key}.json", json.dumps(verdict.as_dict()))
    except OSError:     # a cache that cannot be written costs the check next time, nothing else
        pass


def preflight(spec: PlanSpec, a: Sequence[float], b: Sequence[float], *, isolate: bool,
              timeout_s: float | None = None, digest: str | None = None, cache: bool = True,
              start_method: str | None = None, name: str | None = None) -> ReuseVerdict:
    """Load the FMU and find how its runs must be made (:func:`check_reuse`), in a child process when
    ``isolate`` (an FMU not our own; else on this process's RunPlan for ``spec``, which its runs here then
    use), the verdict cached under the FMU's ``digest`` and the run set-up. ``name``: the FMU as the user
    gave it, which an error names (``spec.fmu_path`` may be the folder it was unpacked into)."""
    try:
        return _preflight(spec, a, b, isolate, timeout_s, digest, cache, start_method)
    except (FMULoadError, FMUReuseError) as exc:
        if name is None or str(exc).startswith(name):
            raise
        raise type(exc)(f"{name}{str(exc)[len(spec.fmu_path):]}" if str(exc).startswith(spec.fmu_path)
                        else f"{name}: {exc}") from None


def _preflight(spec: PlanSpec, a: Sequence[float], b: Sequence[float], isolate: bool, timeout_s: float | None,
               digest: str | None, cache: bool, start_method: str | None) -> ReuseVerdict:
    key = _cache_key(spec, digest, a, b) if (cache and digest) else None
    if key is not None:
        hit = _read_cached(key)
        if hit is not None:
            _confirm_loads(spec, isolate)
            return replace(hit, cached=True, check_s=0.0)
    verdict = (check_reuse_isolated(spec, a, b, timeout_s, start_method) if isolate
               else check_reuse(spec, a, b, shared=True, timeout_s=timeout_s))
    if key is not None and math.isfinite(verdict.check_s) and verdict.tried:
        _write_cached(key, verdict)
    return verdict


def _confirm_loads(spec: PlanSpec, isolate: bool) -> None:
    """A cached verdict still needs our FMU to load here; an FMU not our own is not loaded in this process
    (its workers say why, run by run; a cached verdict was made by a binary that loaded)."""
    if isolate:
        return
    try:
        runner_for(spec).close()
    except Exception as exc:
        if not _is_load_failure(exc):
            raise
        raise FMULoadError(load_problem(spec.fmu_path, exc)) from None
