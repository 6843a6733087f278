"""Run FMI 2.0 and 3.0 FMUs: the one module of fmusa that talks to an FMU (through fmpy; an FMI 3.0 FMU through
:class:`fmusa.fmi.fmi3.FMI3Instance`, which gives fmpy's FMI 3 instance the FMI 2 calls used here).

An :class:`FMURunner` extracts the FMU once, instantiates it once and then runs it as often as
needed, in fmpy's call order: ``setupExperiment`` (with the default experiment's tolerance unless one is
given) → set parameters → initialisation → ``doStep`` … → read outputs. Between runs the instance is
brought back to the state it had right after instantiation as :attr:`FMURunner.reuse` says: ``reset``
(``fmi2Reset``), ``snapshot`` (``fmi2SetFMUstate`` to a state taken right after instantiation) or
``fresh`` (a new instance, its library loaded anew, as ``fmpy.simulate_fmu`` makes every run). Which one
an FMU needs is found by :mod:`fmusa.runs.preflight`, since real exports break ``fmi2Reset`` in many
ways. Reusing the instance avoids the unzip/load/instantiate cost that ``fmpy.simulate_fmu`` pays on
every call, which matters for studies of thousands of runs.

A runner used directly (:meth:`FMURunner.run`, :meth:`FMURunner.run_final`) checks the way it brings the
instance back the first time it reuses it, as a study's pre-flight check does: its first run (on a fresh
instance) is made again after the second run on the same instance, and must give the same numbers. Where it
does not, the runner moves on to a state snapshot, else to a new instance per run, warns
(:class:`FMUReuseWarning`), and makes the second run again that way. The verdict is cached per FMU digest and
set-up (in :func:`fmusa.files.cache_dir`), so the check costs one run once.

Co-simulation FMUs integrate themselves. Model exchange FMUs are integrated by fmpy's solver (CVode or
Euler, ``fmpy.simulate_fmu`` on the reused instance). What an FMU declares and the load-time checks are
in :mod:`fmusa.fmi.info`; building a binary from an FMU's sources in :mod:`fmusa.fmi.build`; prepared
repeated runs (:class:`~fmusa.fmi.plans.RunPlan`, :class:`~fmusa.fmi.plans.DrivenPlan`) in
:mod:`fmusa.fmi.plans`, which drive the runner only through its public methods (:meth:`FMURunner.ready`,
:meth:`FMURunner.lookup`, :attr:`FMURunner.instance`, :meth:`FMURunner.fail` …).

Errors: an unknown variable, a value of the wrong type or an FMU that cannot run as asked raise
:class:`~fmusa.fmi.info.FMUError` (a ``ValueError``); a run the FMU rejects raises
:class:`~fmusa.fmi.info.FMURunError` (a ``RuntimeError``) with the FMU's log.

Example::

    from fmusa import FMURunner
    with FMURunner() as fmu:
        df = fmu.run({"c_y": 8e5, "d_y": 500}, stop_time=12, step=0.01, outputs=["y", "v_y"])
        final = fmu.run_final({"c_y": 8e5}, stop_time=12, outputs=["y_max", "t_eq"])
"""
from __future__ import annotations

import difflib
import itertools
import math
import os
import shutil
from collections import deque
from ctypes import byref
from pathlib import Path
from typing import Callable, Iterable, Mapping, Sequence

import numpy as np
from fmusa.errors import UsageError
from fmusa.files import atomic_write, cache_dir
from fmusa.fmi.archive import extract_fmu, new_folder, remove_folder
from fmusa.fmi.build import compile_sources, file_digest
from fmusa.fmi.lean import failure_head, failure_text, status_label
from fmusa.fmi.info import (SOLVERS, FMUError, FMUNotFoundError, FMURunError, Value, binary_problem,
                            default_fmu_path, read_fmu_info, select_interface)

#: The causalities a variable may have to be read as an output (time, the independent variable, is
#: always returned and cannot be asked for).
READABLE = ("output", "parameter", "calculatedParameter", "local", "input")

#: How a runner brings its instance back to the state right after instantiation between two runs.
REUSE_MODES = ("reset", "snapshot", "fresh")

#: Bumped when the runner's reuse check changes what it decides, so that older cached verdicts are not used.
_REUSE_CHECK_VERSION = 1

#: Verdicts of the reuse check this process has made or read: cache key -> (mode, why).
_REUSE_VERDICTS: dict[str, tuple[str, str]] = {}


class FMUReuseWarning(UserWarning):
    """The FMU does not come back to its state after instantiation the way asked (``fmi2Reset`` leaves a
    state or outputs behind): the runner now brings it back another way (a state snapshot, or a new
    instance per run), which is always right and may cost more per run."""


#: The range of an fmi2Integer (a C int).
INT_MIN, INT_MAX = -2**31, 2**31 - 1


def communication_points(stop_time: float, step: float | None) -> np.ndarray:
    """The communication points of a run from 0 to ``stop_time``: every ``step`` s, the last step shortened
    to end at ``stop_time``; ``[0, stop_time]`` for ``step`` None (one single ``doStep``)."""
    if step is None:
        return np.array([0.0, float(stop_time)])
    n = max(1, math.ceil(stop_time / step - 1e-9))
    times = np.arange(n + 1, dtype=float) * step
    times[-1] = stop_time
    return times



#: componentEnvironment -> the logger of the live instance that was given it (see _logger_router)
_LOGGERS: dict[int, Callable] = {}
_LOG_KEYS = itertools.count(1)
_ROUTER: list = []   # the one ctypes callback, created on first use (fmpy is imported lazily)


def _register_logger(log: Callable) -> int:
    key = next(_LOG_KEYS)
    _LOGGERS[key] = log
    return key


def _route_log_message(env, instance_name, status, category, message) -> None:
    log = _LOGGERS.get(env or 0)
    if log is None:   # an instance fmusa did not make (plain fmpy in the same process): fmpy's own printer
        from fmpy.fmi1 import printLogMessage
        printLogMessage(env, instance_name, status, category, message)
    else:
        log(env, instance_name, status, category, message)


def _logger_router(logger_type):
    """The process-wide logger callback: never freed, so the native proxy can never call a dead one."""
    if not _ROUTER:
        _ROUTER.append(logger_type(_route_log_message))
    return _ROUTER[0]

class FMURunner:
    """One extracted, instantiated FMI 2.0 or 3.0 FMU, run again and again (FMI 3.0 arrays element-wise, ``x[2]``).

    Co-simulation FMUs integrate themselves (``fmi2DoStep``); model exchange FMUs are integrated by
    fmpy's solver (CVode or Euler) through ``fmpy.simulate_fmu``, on the same reused instance. An FMU
    without a binary for this platform but with C sources is built from them first.

    Parameters
    ----------
    fmu_path:
        The ``.fmu`` file or an extracted FMU directory (default: :func:`default_fmu_path`).
    instance_name:
        Name passed to ``fmi2Instantiate`` (appears in the FMU's log messages).
    debug_logging:
        Log categories to switch on with ``fmi2SetDebugLogging`` (e.g. ``["logAll"]``); by default
        only the error and warning categories the model description declares.
    interface:
        ``"auto"`` (co-simulation when the FMU has it, else model exchange), ``"co-simulation"`` or
        ``"model-exchange"``.
    solver, relative_tolerance, step_size:
        Model exchange only: fmpy's solver (``"CVode"``, the default, or ``"Euler"``), CVode's relative
        tolerance (default: the FMU's default experiment, else 1e-5) and the integration step (Euler's
        fixed step; for CVode the longest step). For a co-simulation FMU ``relative_tolerance`` is passed
        to ``fmi2SetupExperiment`` (default: the default experiment's tolerance, as fmpy does; undefined
        when it declares none); ``solver`` and ``step_size`` are errors.
    reuse:
        How the instance returns to its state right after instantiation between runs (:data:`REUSE_MODES`).
    check_reuse:
        Check ``reuse`` the first time the instance is reused by :meth:`run` or :meth:`run_final` (the first
        run made again after the second must give the same numbers; see the module's docstring) and move on
        to a way that works when it does not. Off only where the caller has checked it (a study's runs).
    """

    def __init__(self, fmu_path: str | os.PathLike | None = None, instance_name: str = "fmusa",
                 debug_logging: Iterable[str] | None = None, *, interface: str = "auto",
                 solver: str | None = None, relative_tolerance: float | None = None,
                 step_size: float | None = None, reuse: str = "reset", check_reuse: bool = True) -> None:
        if reuse not in REUSE_MODES:
            raise UsageError(f"unknown reuse mode {reuse!r}; use one of {', '.join(REUSE_MODES)}")
        self.reuse = reuse
        #: Why runs are brought back as :attr:`reuse` says: "" before the check, else its verdict.
        self.reuse_why = ""
        self._check_reuse = check_reuse and reuse != "fresh"
        self._first_run: tuple | None = None      # (how, args, result) of the first run on a fresh instance
        self._snapshot = None
        self.fmu_path = Path(fmu_path) if fmu_path is not None else default_fmu_path()
        if not self.fmu_path.exists():
            raise FMUNotFoundError(f"FMU not found: {self.fmu_path}")
        self.instance_name = instance_name
        self._owns_unzipdir = False
        self.unzipdir = None
        self._instance = None
        info = read_fmu_info(self.fmu_path)              # FMI 2.0 or 3.0? (FMUError otherwise)
        self.interface = select_interface(info, interface)
        if solver is not None and solver not in SOLVERS:
            raise UsageError(f"unknown solver {solver!r}; use one of {', '.join(SOLVERS)}")
        if self.interface == "co-simulation" and (solver is not None or step_size is not None):
            raise UsageError(f"{info.model_name} runs as a co-simulation FMU, which integrates with its own "
                             f"solver: solver and step_size apply to model exchange only")
        for name, x in (("relative_tolerance", relative_tolerance), ("step_size", step_size)):
            if x is not None and not (math.isfinite(x) and x > 0):
                raise UsageError(f"{name} must be a positive finite number, got {x!r}")
        self.solver = solver or "CVode"
        self.relative_tolerance = None if relative_tolerance is None else float(relative_tolerance)
        self.step_size = None if step_size is None else float(step_size)
        needs_build = not info.has_binary(self.interface)
        if needs_build:
            problem = binary_problem(info, self.interface)
            if problem:
                raise FMUError(f"{self.fmu_path}: {problem}")
        if self.fmu_path.is_file():
            self._owns_unzipdir = True
            self.unzipdir = extract_fmu(self.fmu_path, to_run=True)
        elif needs_build:   # never write into the user's directory: build in a copy
            self._owns_unzipdir = True
            self.unzipdir = new_folder()
            shutil.copytree(self.fmu_path, self.unzipdir, dirs_exist_ok=True)
        else:
            self.unzipdir = self.fmu_path
        try:
            if needs_build:
                compile_sources(self.unzipdir, info, self.interface)
            self.info = info
            self.model_description = info.model_description
        except BaseException:
            self._cleanup_dir()
            raise
        md = self.model_description
        self.variables = {v.name: v for v in info.variables}   # FMI 3.0: scalars, arrays element-wise
        #: the tolerance passed to fmi2SetupExperiment: the one asked for, else the default experiment's
        self.setup_tolerance = self.relative_tolerance
        if self.setup_tolerance is None:
            self.setup_tolerance = experiment_tolerance(md)
        self.messages: deque[tuple[str, str, str]] = deque(maxlen=500)
        cats = [c.name for c in getattr(md, "logCategories", [])]
        if debug_logging is None:
            debug_logging = [c for c in cats if c in ("logStatusError", "logStatusWarning")]
        self._debug_logging = list(debug_logging)
        self._state = "closed"
        if self._check_reuse:
            self._apply_cached_verdict()
        #: Where the current run is (e.g. "during initialisation"): named by :meth:`fail`'s message.
        self.phase = ""
        #: ``time.monotonic()`` after which a co-simulation RunPlan run stops at its next communication point
        #: (FMUTimeLimitError); None: no limit. Set per run by whoever limits the run's time.
        self.deadline: float | None = None
        try:
            self._instantiate()
        except BaseException:
            self._cleanup_dir()
            raise

    @property
    def is_model_exchange(self) -> bool:
        return self.interface == "model-exchange"

    @property
    def is_fresh(self) -> bool:
        """Whether the instance is as instantiated, no run made on it yet."""
        return self._instance is not None and self._state == "instantiated"

    @property
    def instance(self):
        """The fmpy instance (``FMU2Slave`` for co-simulation, ``FMU2Model`` for model exchange) that
        :class:`~fmusa.fmi.plans.RunPlan` calls through ctypes; None after :meth:`close` or a fatal error
        (:meth:`ready` instantiates afresh)."""
        return self._instance

    # ------------------------------------------------------------------ instance management
    def _instantiate(self) -> None:
        from fmpy.fmi2 import (FMU2Model, FMU2Slave, fmi2CallbackAllocateMemoryTYPE,
                               fmi2CallbackFreeMemoryTYPE, fmi2CallbackFunctions, fmi2CallbackLoggerTYPE)
        from fmpy import calloc, free

        if self.info.is_fmi3:   # fmpy's FMU3Slave/FMU3Model behind the FMI 2 calls (fmusa.fmi.fmi3)
            from fmusa.fmi.fmi3 import FMI3Instance
            self._instance = FMI3Instance(self.info, str(self.unzipdir), self.interface, self.instance_name,
                                          self._log_message, self._debug_logging)
            self._state = "instantiated"
            return
        md = self.model_description
        cls = FMU2Model if self.is_model_exchange else FMU2Slave
        cwd = os.getcwd()
        try:
            slave = cls(guid=md.guid, unzipDirectory=str(self.unzipdir),
                        modelIdentifier=self.info.interfaces[self.interface],
                        instanceName=self.instance_name)
        finally:   # fmpy changes into the binary's folder to load it and stays there when loading fails
            if os.getcwd() != cwd:
                os.chdir(cwd)
        callbacks = fmi2CallbackFunctions()
        # fmpy's native proxy keeps ONE logger for the whole process (the last one given to it): every
        # instance logs through a router that lives as long as the process and finds the instance's own
        # logger by its componentEnvironment, so a freed runner leaves no dangling callback behind (a later
        # plain fmpy instance crashed on its first log message) and two live runners keep their messages apart.
        self._log_key = _register_logger(self._log_message)
        callbacks.componentEnvironment = self._log_key
        callbacks.logger = _logger_router(fmi2CallbackLoggerTYPE)
        callbacks.allocateMemory = fmi2CallbackAllocateMemoryTYPE(calloc)
        callbacks.freeMemory = fmi2CallbackFreeMemoryTYPE(free)
        try:  # native proxy that formats printf-style messages before calling our logger
            from fmpy.logging import addLoggerProxy
            addLoggerProxy(byref(callbacks))
        except Exception:  # pragma: no cover - only on platforms without the proxy library
            pass
        self._callbacks = callbacks
        slave.instantiate(callbacks=callbacks, loggingOn=bool(self._debug_logging))
        self._instance = slave
        if self._debug_logging:
            slave.setDebugLogging(True, self._debug_logging)
        if self.reuse == "snapshot":
            self._snapshot = slave.getFMUstate()
        self._state = "instantiated"

    def _free(self) -> None:
        if self._instance is not None:
            if self._snapshot is not None:
                try:
                    self._instance.freeFMUstate(self._snapshot)
                except Exception:
                    pass
            try:
                self._instance.freeInstance()
            except Exception:
                pass
        self._instance = None
        self._snapshot = None
        self._state = "closed"
        _LOGGERS.pop(getattr(self, "_log_key", None), None)

    def _log_message(self, env, instance_name, status, category, message) -> None:
        def text(b):
            return b.decode("utf-8", "replace") if b else ""
        self.messages.append((status_label(status), text(category), text(message)))

    def close(self) -> None:
        """Free the FMU instance and delete the extracted files."""
        self._free()
        self._cleanup_dir()

    def _cleanup_dir(self) -> None:
        if self._owns_unzipdir and self.unzipdir is not None:
            remove_folder(self.unzipdir)   # releases its lock first (Windows)
            self.unzipdir = None

    def __enter__(self) -> "FMURunner":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:  # best effort; prefer close() / with
        try:
            self.close()
        except Exception:
            pass

    # ------------------------------------------------------------------ variables
    def names(self, causality: str | None = None) -> list[str]:
        """Variable names, optionally only those of one causality (parameter, input, output…)."""
        return [n for n, v in self.variables.items() if causality is None or v.causality == causality]

    def start_values(self, causality: str = "parameter") -> dict[str, Value]:
        """The start values the model description declares for variables of ``causality``."""
        out: dict[str, Value] = {}
        for name in self.names(causality):
            v = self.variables[name]
            if v.start is not None:
                out[name] = self.coerce(v, v.start)
        return out

    def lookup(self, name: str, allowed: tuple[str, ...], role: str):
        """The fmpy ModelVariable ``name``, which must have one of the causalities ``allowed`` to play
        ``role`` (parameter, input, output); an :class:`FMUError` naming the closest names otherwise."""
        v = self.variables.get(name)
        if v is None:
            pool = [n for n, x in self.variables.items() if x.causality in allowed] or list(self.variables)
            close = difflib.get_close_matches(name, pool, n=5, cutoff=0.5)
            if not close:
                close = difflib.get_close_matches(name, list(self.variables), n=5, cutoff=0.5)
            hint = (f"; closest names: {', '.join(close)}" if close
                    else f"; known {role}s: {', '.join(pool)}")
            raise FMUError(f"unknown {role} {name!r} in {self.model_description.modelName}{hint}")
        if v.causality not in allowed:
            raise FMUError(f"{name!r} is a{'n' if v.causality[0] in 'aeiou' else ''} "
                           f"{v.causality} variable, not a{'n' if role[0] in 'aeiou' else ''} {role} "
                           f"(allowed causality: {', '.join(allowed)})")
        return v

    @staticmethod
    def coerce(v, value) -> Value:
        """``value`` (a number or a string) as the type of variable ``v``; :class:`FMUError` when it does
        not fit (1.5 for an Integer, "maybe" for a Boolean, "abc" for a Real)."""
        try:
            if v.type == "Real":
                return float(value)
            if v.type in ("Integer", "Enumeration"):
                if isinstance(value, str):
                    value = float(value)
                if isinstance(value, float):
                    if not value.is_integer():
                        raise FMUError(f"{v.name} is an Integer; got {value!r}")
                    value = int(value)
                if not INT_MIN <= int(value) <= INT_MAX:    # fmi2Integer is 32 bits: ctypes would wrap it
                    raise FMUError(f"{v.name} is an Integer (32 bits); {value!r} is out of its range: give a value "
                                   f"from {INT_MIN} to {INT_MAX}")
                return int(value)
            if v.type == "Boolean":
                if isinstance(value, str):
                    s = value.strip().lower()
                    if s in ("true", "1", "yes", "on"):
                        return True
                    if s in ("false", "0", "no", "off"):
                        return False
                    raise FMUError(f"{v.name} is a Boolean; got {value!r}")
                return bool(value)
        except (TypeError, ValueError) as exc:
            if isinstance(exc, FMUError):
                raise
            how = "cannot parse" if isinstance(value, str) else "got"
            raise FMUError(f"{v.name} is a {v.type}; {how} {value!r}") from None
        raise FMUError(f"{v.name}: variables of type {v.type} are not supported")

    def parse_value(self, name: str, text: str) -> Value:
        """Convert a command-line string to the type of parameter or input ``name``."""
        return self.coerce(self.lookup(name, ("parameter", "input"), "parameter"), text)

    def by_type(self, values: Mapping[str, Value], allowed: tuple[str, ...], role: str
                ) -> dict[str, tuple[list[int], list]]:
        """``values`` (name → value) checked and converted, grouped by FMI type: type → (value references,
        values), the shape of the fmi2Set* calls. A Real must be finite."""
        groups: dict[str, tuple[list[int], list]] = {}
        for name, value in values.items():
            v = self.lookup(name, allowed, role)
            val = self.coerce(v, value)
            if v.type == "Real" and not math.isfinite(val):
                raise FMUError(f"{name} must be finite, got {val!r}")
            vrs, vals = groups.setdefault(v.type, ([], []))
            vrs.append(v.valueReference)
            vals.append(val)
        return groups

    def _set(self, values: Mapping[str, Value], allowed: tuple[str, ...], role: str) -> None:
        s = self._instance
        for typ, (vrs, vals) in self.by_type(values, allowed, role).items():
            if typ == "Real":
                s.setReal(vrs, vals)
            elif typ == "Boolean":
                s.setBoolean(vrs, vals)
            else:
                s.setInteger(vrs, vals)

    def reader(self, outputs: list[str]):
        """A function returning the current values of ``outputs`` as a list of floats (built once, called
        at every communication point)."""
        by_type: dict[str, tuple[list[int], list[int]]] = {}
        for i, name in enumerate(outputs):
            v = self.lookup(name, READABLE + ("independent",), "output")
            if v.causality == "independent":
                raise FMUError(f"{name!r} is the independent variable; `time` is always returned")
            idx, vrs = by_type.setdefault(v.type, ([], []))
            idx.append(i)
            vrs.append(v.valueReference)
        s = self._instance
        getters = {"Real": s.getReal, "Integer": s.getInteger, "Enumeration": s.getInteger,
                   "Boolean": s.getBoolean}
        plan = []
        for typ, (idx, vrs) in by_type.items():
            if typ not in getters:
                raise FMUError(f"outputs of type {typ} are not supported")
            plan.append((getters[typ], idx, vrs))
        n = len(outputs)

        def read() -> list[float]:
            row = [0.0] * n
            for get, idx, vrs in plan:
                for i, x in zip(idx, get(vrs)):
                    row[i] = float(x)
            return row
        return read

    # ------------------------------------------------------------------ running
    def fail(self, exc: Exception, params: Mapping[str, Value], what: str | None = None) -> FMURunError:
        """The error to raise for ``exc``, which ended a run with ``params`` set, ``what`` (default: the
        current :attr:`phase`): names the FMI call and its status, the parameters and the FMU's log. The
        instance is marked failed (reset before the next run), or freed after fmi2Fatal."""
        from fmpy.fmi1 import FMICallException

        what = self.phase if what is None else what
        call = isinstance(exc, FMICallException)
        head = failure_head(exc.function if call else None, exc.status if call else None, exc, what)
        if call and exc.status >= 4:  # fmi2Fatal: the instance must not be used again
            self._free()
        else:
            self._state = "failed"
        return FMURunError(failure_text(self.model_description.modelName, head, params, self.messages))

    def reject(self, message: str, error: type[FMURunError] = FMURunError) -> FMURunError:
        """The error (an ``error``) to raise for a run whose result is unusable (e.g. non-finite outputs) or
        that was stopped; the instance is reset before the next run."""
        self._state = "failed"
        return error(f"{self.model_description.modelName}: {message}")

    def mark_done(self) -> None:
        """Record that the current run ended normally (the next :meth:`ready` resets the instance)."""
        self._state = "done"

    def restore(self) -> None:
        """Bring the instance back to its state right after instantiation as :attr:`reuse` says
        (``fmi2Reset``, ``fmi2SetFMUstate`` to the snapshot, or a new instance); the FMU's error is
        raised, not hidden, so that :mod:`fmusa.runs.preflight` can tell a reset that fails."""
        if self._instance is None or self.reuse == "fresh":
            self._free()
            self._instantiate()
        elif self.reuse == "snapshot":
            self._instance.setFMUstate(self._snapshot)
        else:
            self._instance.reset()
        self._state = "instantiated"

    def ready(self) -> None:
        """An instance in the state right after instantiation, for a new run: the last run's brought back
        as :attr:`reuse` says, or a new one (after a fatal error, or when bringing it back fails)."""
        if self._instance is None:
            self._instantiate()
        elif self._state != "instantiated":
            try:
                self.restore()
            except Exception:  # a failed instance that cannot be brought back: start afresh
                self._free()
                self._instantiate()
        self._state = "running"
        self.messages.clear()

    def _start(self, params: Mapping[str, Value], stop_time: float,
               inputs: Mapping[str, float] | None) -> None:
        self.ready()
        inst = self._instance
        self.phase = "while setting up the experiment"
        inst.setupExperiment(tolerance=self.setup_tolerance, startTime=0.0, stopTime=float(stop_time))
        self.phase = "while setting parameters"
        self._set(params, ("parameter", "input"), "parameter")   # a study parameter may be an input
        if inputs:
            self._set(inputs, ("input",), "input")
        self.phase = "during initialisation"
        inst.enterInitializationMode()
        inst.exitInitializationMode()
        self.phase = "after initialisation"

    def _me_intervals(self, times: np.ndarray) -> tuple[float, float | None]:
        """(fmpy output_interval, fmpy step_size) for a model exchange run sampled at ``times``.

        fmpy's loop integrates from one output point to the next (Euler: one step each), so the output
        interval is the integration step: ``step_size`` when set, else the sampling step (CVode) or
        the sampling step divided into steps of at most stop_time/1000 (Euler)."""
        stop = float(times[-1])
        sample = float(times[1] - times[0]) if len(times) > 2 else stop
        if self.step_size is not None:
            h = min(self.step_size, stop)
        elif self.solver == "Euler":
            h = sample / math.ceil(sample / (stop / 1000) - 1e-9)
        else:
            h = sample
        return h, (h if self.solver == "Euler" else None)

    def run_me(self, values: Mapping[str, Value], times: np.ndarray, outputs: list[str],
               params: Mapping[str, Value]) -> np.ndarray:
        """One model exchange run with fmpy's solver on the reused instance; the outputs at ``times``.

        ``values`` are the start values (parameters and constant inputs) set after ``fmi2Reset``;
        ``params`` are the parameters the error message names if the run fails."""
        from fmpy import simulate_fmu

        self.ready()
        interval, step_size = self._me_intervals(times)
        self.phase = (f"in fmpy's {self.solver} integration of the model exchange FMU "
                       f"from t = 0 to {times[-1]:.10g} s")
        start, recorded, instance = dict(values), list(outputs), self._instance
        if self.info.is_fmi3:   # fmpy sets and records FMI 3.0 arrays whole: elements gathered, picked out
            from fmusa.fmi.fmi3 import me_columns, me_outputs, me_start_values
            start, recorded, instance = me_start_values(self.info, start), me_outputs(self.info, outputs), instance.fmu
        try:
            res = simulate_fmu(str(self.unzipdir), validate=True, start_time=0.0, stop_time=float(times[-1]),
                               solver=self.solver, step_size=step_size,
                               relative_tolerance=self.relative_tolerance, output_interval=interval,
                               record_events=True, fmi_type="ModelExchange", start_values=start,
                               output=recorded, model_description=self.model_description,
                               fmu_instance=instance)
            if self.info.is_fmi3:
                res = me_columns(self.info, res, outputs)
        except Exception as exc:
            raise self.fail(exc, params) from exc
        self._state = "done"
        return _sample_at(res, times, outputs)

    @staticmethod
    def check_time(stop_time: float, step: float | None) -> None:
        """A :class:`~fmusa.errors.UsageError` unless ``stop_time`` and ``step`` (or None) are positive
        and finite."""
        if not (math.isfinite(stop_time) and stop_time > 0):
            raise UsageError(f"stop_time must be a positive finite number, got {stop_time!r}")
        if step is not None and not (math.isfinite(step) and step > 0):
            raise UsageError(f"step must be a positive finite number or None, got {step!r}")

    def validate(self, params: Mapping[str, Value], outputs: Sequence[str],
                 inputs: Mapping[str, float] | None) -> None:
        """Check the names of a run's parameters and inputs before it starts (:class:`FMUError`)."""
        for name in params:
            self.lookup(name, ("parameter", "input"), "parameter")   # (a study parameter may be an input)
        for name in inputs or {}:
            self.lookup(name, ("input",), "input")
        if isinstance(outputs, str):
            raise TypeError("outputs must be a list of names, not a string")

    def run(self, params: Mapping[str, Value], stop_time: float, step: float | None,
            outputs: list[str], inputs: Mapping[str, float] | None = None) -> pd.DataFrame:
        """Simulate from 0 to ``stop_time`` and return the outputs at the communication points.

        ``params`` are set on an instance in its state right after instantiation (all others keep their
        start values; the way back there is checked, see :attr:`reuse`), ``inputs`` are held constant.
        ``step`` is the communication step (the last step is shortened to end at ``stop_time``); ``None``
        makes one single ``doStep`` and returns the start and end rows. The result has a ``time`` column
        followed by ``outputs``.
        """
        return self._checked(self._run, (params, stop_time, step, outputs, inputs))

    def _run(self, params: Mapping[str, Value], stop_time: float, step: float | None,
             outputs: list[str], inputs: Mapping[str, float] | None = None) -> pd.DataFrame:
        import pandas as pd   # here: a pool worker (RunPlan runs) never needs pandas, ~0.4 s of its start-up
        self.check_time(stop_time, step)
        self.validate(params, outputs, inputs)
        outputs = list(outputs)
        times = communication_points(stop_time, step)
        if self.is_model_exchange:
            for name in outputs:
                self.lookup(name, READABLE, "output")
            values = {n: self.coerce(self.variables[n], x) for n, x in {**params, **(inputs or {})}.items()}
            data = self.run_me(values, times, outputs, params)
            df = pd.DataFrame(data, columns=outputs)
            df.insert(0, "time", times)
            return df
        data = np.empty((len(times), len(outputs)))
        t = 0.0
        try:
            self._start(params, stop_time, inputs)
            read = self.reader(outputs)
            data[0] = read()
            do_step = self._instance.doStep
            for k in range(1, len(times)):
                t_next = times[k]
                self.phase = f"in the communication step from t = {t:.10g} s to {t_next:.10g} s"
                do_step(t, t_next - t)
                t = t_next
                data[k] = read()
        except FMUError:
            raise
        except Exception as exc:
            raise self.fail(exc, params) from exc
        self._state = "done"
        df = pd.DataFrame(data, columns=outputs)
        df.insert(0, "time", times)
        return df

    def run_final(self, params: Mapping[str, Value], stop_time: float, outputs: list[str],
                  inputs: Mapping[str, float] | None = None) -> dict[str, float]:
        """One ``doStep`` from 0 to ``stop_time``; the final values of ``outputs``."""
        return self._checked(self._run_final, (params, stop_time, outputs, inputs))

    def _run_final(self, params: Mapping[str, Value], stop_time: float, outputs: list[str],
                   inputs: Mapping[str, float] | None = None) -> dict[str, float]:
        self.check_time(stop_time, None)
        self.validate(params, outputs, inputs)
        outputs = list(outputs)
        if self.is_model_exchange:
            df = self._run(params, stop_time, None, outputs, inputs)
            return {name: float(df[name].iloc[-1]) for name in outputs}
        try:
            self._start(params, stop_time, inputs)
            read = self.reader(outputs)
            self.phase = f"in the communication step from t = 0 s to {stop_time:.10g} s"
            self._instance.doStep(0.0, float(stop_time))
            row = read()
        except FMUError:
            raise
        except Exception as exc:
            raise self.fail(exc, params) from exc
        self._state = "done"
        return dict(zip(outputs, row))

    # ------------------------------------------------------------------ the reuse check
    def _reuse_key(self) -> str:
        import hashlib
        import json
        what = [_REUSE_CHECK_VERSION, file_digest(self.fmu_path), self.interface, self.solver,
                self.relative_tolerance, self.step_size, self.reuse]
        return hashlib.sha256(json.dumps(what).encode("utf-8")).hexdigest()[:32]

    def _apply_cached_verdict(self) -> None:
        """Take the verdict of an earlier check of this FMU and set-up (this process's, else the cache's)."""
        import json
        key = self._reuse_key()
        self._key = key
        hit = _REUSE_VERDICTS.get(key)
        if hit is None:
            try:
                data = json.loads((cache_dir() / f"runner-reuse-{key}.json").read_text(encoding="utf-8"))
                hit = (str(data["mode"]), str(data["why"]))
            except (OSError, ValueError, KeyError, TypeError):
                return
            if hit[0] not in REUSE_MODES:
                return
            _REUSE_VERDICTS[key] = hit
        self.reuse, self.reuse_why = hit
        self._check_reuse = False

    def _store_verdict(self, mode: str, why: str) -> None:
        import json
        self.reuse, self.reuse_why, self._check_reuse = mode, why, False
        _REUSE_VERDICTS[self._key] = (mode, why)
        try:
            atomic_write(cache_dir() / f"runner-reuse-{self._key}.json", json.dumps({"mode": mode, "why": why}))
        except OSError:     # a cache that cannot be written costs the check next time, nothing else
            pass

    def _checked(self, how, args: tuple):
        """``how(*args)`` (a run), with the way the instance is brought back checked the first time it is
        reused: the first run, made on a fresh instance, is made again after this one and must be equal."""
        if not self._check_reuse:
            return how(*args)
        if self._first_run is None:
            if not (self.is_fresh or self._instance is None):
                self._free()        # the first run failed: the check needs a run on a fresh instance
            result = how(*args)
            self._first_run = (how, args, result)
            return result
        result = how(*args)
        problem = self._rerun_differs(self.reuse)
        if problem is None:
            self._store_verdict(self.reuse, f"the first run made again on the reused instance ({self.reuse}) "
                                f"equals its run on a fresh instance")
            return result
        problem = f"after {_REUSE_CALLS[self.reuse]} {problem}"
        asked = self.reuse
        if asked == "reset" and self._can_snapshot():
            self._start_over("snapshot")
            result = how(*args)                 # the second run, then the first again, as before
            snap = self._rerun_differs("snapshot")
            if snap is None:
                self._moved_on("snapshot", asked, problem)
                return result
            problem += f"; after fmi2SetFMUstate to a snapshot {snap}"
        self._start_over("fresh")
        result = how(*args)
        fresh = self._rerun_differs("fresh")
        if fresh is not None:
            raise FMURunError(f"{self.model_description.modelName}: runs of this FMU are not reproducible: "
                              f"{problem}; and even on a new instance {fresh}. Its results depend on something "
                              f"that cannot be reset (state kept in its process, a nondeterministic solver)")
        self._moved_on("fresh", asked, problem)
        return result

    def _rerun_differs(self, mode: str) -> str | None:
        """None when the first run, made again now on the instance brought back by ``mode``, equals its run on
        a fresh instance; else what differs."""
        how, args, first = self._first_run
        try:
            again = how(*args)
        except Exception as exc:
            return f"the first run, which worked on a fresh instance, failed: {' '.join(str(exc).split())[:300]}"
        a, b = _as_array(first), _as_array(again)
        if a.shape == b.shape and np.array_equal(a, b, equal_nan=True):
            return None
        if a.shape != b.shape:
            return f"the first run made again has {b.shape[0]} samples instead of {a.shape[0]}"
        diff = np.abs(a - b)
        diff[np.isnan(diff)] = np.inf
        i = int(np.argmax(diff))
        names = _result_names(first)
        where = np.unravel_index(i, a.shape)
        name = names[where[-1]] if names else "an output"
        return (f"the first run made again gives {name} = {b.flat[i]:.10g} instead of {a.flat[i]:.10g} "
                f"on a fresh instance")

    def _can_snapshot(self) -> bool:
        md = self.model_description
        part = md.coSimulation if self.interface == "co-simulation" else md.modelExchange
        return bool(getattr(part, "canGetAndSetFMUstate", False)) and not self.info.is_fmi3

    def _start_over(self, mode: str) -> None:
        """A new instance brought back by ``mode`` from now on, its first run made again on it (fresh)."""
        self._free()
        self.reuse = mode
        how, args, _ = self._first_run
        how(*args)

    def _moved_on(self, mode: str, asked: str, problem: str) -> None:
        """Record that runs are now brought back by ``mode`` and warn."""
        import warnings
        why = (f"{problem}: every run {'gets a new instance' if mode == 'fresh' else 'starts from a state snapshot taken right after instantiation'} "
               f"instead of {_REUSE_CALLS[asked]}")
        self._store_verdict(mode, why)
        warnings.warn(f"{self.fmu_path}: {why}. This run was made again that way; the runner's first run "
                      f"was on a fresh instance.", FMUReuseWarning, stacklevel=4)


#: How each reuse mode brings the instance back, in words.
_REUSE_CALLS = {"reset": "fmi2Reset", "snapshot": "fmi2SetFMUstate to a snapshot", "fresh": "a new instance"}


def _as_array(result) -> np.ndarray:
    if isinstance(result, dict):
        return np.asarray(list(result.values()), dtype=float)
    return np.asarray(result.to_numpy(), dtype=float)


def _result_names(result) -> list[str]:
    return list(result) if isinstance(result, dict) else list(result.columns)


def experiment_tolerance(md) -> float | None:
    """The default experiment's tolerance of model description ``md`` (what fmpy passes to
    fmi2SetupExperiment when none is asked for), or None when it declares none or a value that is not a
    positive number."""
    exp = getattr(md, "defaultExperiment", None)
    tol = getattr(exp, "tolerance", None) if exp is not None else None
    try:
        tol = float(tol) if tol is not None else None
    except (TypeError, ValueError):
        return None
    return tol if tol is not None and math.isfinite(tol) and tol > 0 else None


def _sample_at(res, times: np.ndarray, outputs: Sequence[str]) -> np.ndarray:
    """Rows of fmpy's result ``res`` at ``times``: the last sample at each time (after an event at that
    instant), linear interpolation where no sample falls on it."""
    t = np.asarray(res["time"], dtype=float)
    cols = np.column_stack([np.asarray(res[name], dtype=float) for name in outputs]) if len(outputs) \
        else np.empty((len(t), 0))
    tol = 1e-9 * max(1.0, abs(float(times[-1])))
    idx = np.searchsorted(t, np.asarray(times) + tol, side="right") - 1
    out = np.empty((len(times), len(outputs)))
    for k, (T, i) in enumerate(zip(times, idx)):
        if i >= 0 and abs(t[i] - T) <= tol:
            out[k] = cols[i]
        else:
            for j in range(len(outputs)):
                out[k, j] = np.interp(T, t, cols[:, j])
    return out


