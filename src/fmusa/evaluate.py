"""Run FMI 2.0 co-simulation FMUs: the one module of fmusa that talks to an FMU (through fmpy).

An :class:`FMURunner` extracts the FMU once, instantiates it once and then runs it as often as
needed: every run is ``reset`` → set parameters → ``setupExperiment`` → initialisation →
``doStep`` … → read outputs. Reusing the instance avoids the unzip/load/instantiate cost that
``fmpy.simulate_fmu`` pays on every call, which matters for studies of thousands of runs.

Example::

    from fmusa.evaluate import FMURunner
    with FMURunner() as fmu:
        df = fmu.run({"c_y": 8e5, "d_y": 500}, stop_time=12, step=0.01, outputs=["y", "v_y"])
        final = fmu.run_final({"c_y": 8e5}, stop_time=12, outputs=["y_max", "t_eq"])
"""
from __future__ import annotations

import difflib
import math
import os
import shutil
from collections import deque
from dataclasses import dataclass
from ctypes import byref
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np
import pandas as pd

from .metrics import MetricRule, reduce_series

FMU_NAME = "ScrewVertebra.fmu"
ENV_FMU = "FMUSA_FMU"

#: Outputs of the paper's pullout experiment, in the order they are written.
PULLOUT_OUTPUTS = ["y", "v_y", "a_y", "F_y", "F_pull", "y_max", "v_y_max", "t_eq"]

_STATUS = ["OK", "Warning", "Discard", "Error", "Fatal", "Pending"]

Value = float | int | bool


def default_fmu_path() -> Path:
    """The ScrewVertebra FMU: ``$FMUSA_FMU`` if set, else ``dist/ScrewVertebra.fmu`` in the first
    directory above this file that has one (the repository root for an editable install)."""
    env = os.environ.get(ENV_FMU)
    if env:
        return Path(env).expanduser().resolve()
    here = Path(__file__).resolve()
    for parent in here.parents:
        candidate = parent / "dist" / FMU_NAME
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(
        f"cannot find dist/{FMU_NAME} in any directory above {here.parent}; "
        f"build it with `make fmu` or set {ENV_FMU} to the FMU's path")


def _label(status: int) -> str:
    return _STATUS[status] if 0 <= status < len(_STATUS) else f"status {status}"


class FMURunner:
    """One extracted, instantiated FMI 2.0 co-simulation FMU, run again and again.

    Parameters
    ----------
    fmu_path:
        The ``.fmu`` file (default: :func:`default_fmu_path`).
    instance_name:
        Name passed to ``fmi2Instantiate`` (appears in the FMU's log messages).
    debug_logging:
        Log categories to switch on with ``fmi2SetDebugLogging`` (e.g. ``["logAll"]``); by default
        only the error and warning categories the model description declares.
    """

    def __init__(self, fmu_path: str | os.PathLike | None = None, instance_name: str = "fmusa",
                 debug_logging: Iterable[str] | None = None) -> None:
        import fmpy

        self.fmu_path = Path(fmu_path) if fmu_path is not None else default_fmu_path()
        if not self.fmu_path.exists():
            raise FileNotFoundError(f"FMU not found: {self.fmu_path}")
        self.instance_name = instance_name
        self._owns_unzipdir = self.fmu_path.is_file()
        self.unzipdir = (Path(fmpy.extract(str(self.fmu_path))) if self._owns_unzipdir
                         else self.fmu_path)
        self.model_description = fmpy.read_model_description(str(self.unzipdir))
        md = self.model_description
        if md.fmiVersion != "2.0" or md.coSimulation is None:
            self._cleanup_dir()
            raise ValueError(f"{self.fmu_path}: not an FMI 2.0 co-simulation FMU")
        self.variables = {v.name: v for v in md.modelVariables}
        self.messages: deque[tuple[str, str, str]] = deque(maxlen=500)
        cats = [c.name for c in getattr(md, "logCategories", [])]
        if debug_logging is None:
            debug_logging = [c for c in cats if c in ("logStatusError", "logStatusWarning")]
        self._debug_logging = list(debug_logging)
        self._slave = None
        self._state = "closed"
        self._phase = ""
        self._instantiate()

    # ------------------------------------------------------------------ instance management
    def _instantiate(self) -> None:
        from fmpy.fmi2 import (FMU2Slave, fmi2CallbackAllocateMemoryTYPE, fmi2CallbackFreeMemoryTYPE,
                               fmi2CallbackFunctions, fmi2CallbackLoggerTYPE)
        from fmpy import calloc, free

        md = self.model_description
        slave = FMU2Slave(guid=md.guid, unzipDirectory=str(self.unzipdir),
                          modelIdentifier=md.coSimulation.modelIdentifier,
                          instanceName=self.instance_name)
        callbacks = fmi2CallbackFunctions()
        # Keep references to the ctypes callbacks: they must outlive the instance.
        self._logger_cb = fmi2CallbackLoggerTYPE(self._log_message)
        callbacks.logger = self._logger_cb
        callbacks.allocateMemory = fmi2CallbackAllocateMemoryTYPE(calloc)
        callbacks.freeMemory = fmi2CallbackFreeMemoryTYPE(free)
        try:  # native proxy that formats printf-style messages before calling our logger
            from fmpy.logging import addLoggerProxy
            addLoggerProxy(byref(callbacks))
        except Exception:  # pragma: no cover - only on platforms without the proxy library
            pass
        self._callbacks = callbacks
        slave.instantiate(callbacks=callbacks, loggingOn=bool(self._debug_logging))
        self._slave = slave
        if self._debug_logging:
            slave.setDebugLogging(True, self._debug_logging)
        self._state = "instantiated"

    def _free(self) -> None:
        if self._slave is not None:
            try:
                self._slave.freeInstance()
            except Exception:
                pass
        self._slave = None
        self._state = "closed"

    def _log_message(self, env, instance_name, status, category, message) -> None:
        def text(b):
            return b.decode("utf-8", "replace") if b else ""
        self.messages.append((_label(status), text(category), text(message)))

    def close(self) -> None:
        """Free the FMU instance and delete the extracted files."""
        self._free()
        self._cleanup_dir()

    def _cleanup_dir(self) -> None:
        if self._owns_unzipdir and self.unzipdir is not None:
            shutil.rmtree(self.unzipdir, ignore_errors=True)
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
                out[name] = self._coerce(v, v.start)
        return out

    def _lookup(self, name: str, allowed: tuple[str, ...], role: str):
        v = self.variables.get(name)
        if v is None:
            pool = [n for n, x in self.variables.items() if x.causality in allowed] or list(self.variables)
            close = difflib.get_close_matches(name, pool, n=5, cutoff=0.5)
            if not close:
                close = difflib.get_close_matches(name, list(self.variables), n=5, cutoff=0.5)
            hint = (f"; closest names: {', '.join(close)}" if close
                    else f"; known {role}s: {', '.join(pool)}")
            raise ValueError(f"unknown {role} {name!r} in {self.model_description.modelName}{hint}")
        if v.causality not in allowed:
            raise ValueError(f"{name!r} is a{'n' if v.causality[0] in 'aeiou' else ''} "
                             f"{v.causality} variable, not a{'n' if role[0] in 'aeiou' else ''} {role} "
                             f"(allowed causality: {', '.join(allowed)})")
        return v

    @staticmethod
    def _coerce(v, value) -> Value:
        if v.type == "Real":
            return float(value)
        if v.type in ("Integer", "Enumeration"):
            if isinstance(value, str):
                value = float(value)
            if isinstance(value, float):
                if not value.is_integer():
                    raise ValueError(f"{v.name} is an Integer; got {value!r}")
                value = int(value)
            return int(value)
        if v.type == "Boolean":
            if isinstance(value, str):
                s = value.strip().lower()
                if s in ("true", "1", "yes", "on"):
                    return True
                if s in ("false", "0", "no", "off"):
                    return False
                raise ValueError(f"{v.name} is a Boolean; got {value!r}")
            return bool(value)
        raise ValueError(f"{v.name}: variables of type {v.type} are not supported")

    def parse_value(self, name: str, text: str) -> Value:
        """Convert a command-line string to the type of parameter or input ``name``."""
        v = self._lookup(name, ("parameter", "input"), "parameter")
        try:
            return self._coerce(v, text)
        except ValueError as exc:
            if str(exc).startswith(v.name):
                raise
            raise ValueError(f"{name} is a {v.type}; cannot parse {text!r}") from None

    def _set(self, values: Mapping[str, Value], allowed: tuple[str, ...], role: str) -> None:
        groups: dict[str, tuple[list[int], list]] = {}
        for name, value in values.items():
            v = self._lookup(name, allowed, role)
            try:
                val = self._coerce(v, value)
            except TypeError:
                raise ValueError(f"{name} is a {v.type}; got {value!r}") from None
            if v.type == "Real" and not math.isfinite(val):
                raise ValueError(f"{name} must be finite, got {val!r}")
            vrs, vals = groups.setdefault(v.type, ([], []))
            vrs.append(v.valueReference)
            vals.append(val)
        s = self._slave
        for typ, (vrs, vals) in groups.items():
            if typ == "Real":
                s.setReal(vrs, vals)
            elif typ == "Boolean":
                s.setBoolean(vrs, vals)
            else:
                s.setInteger(vrs, vals)

    def _reader(self, outputs: list[str]):
        """A function returning the current values of ``outputs`` as a list of floats."""
        by_type: dict[str, tuple[list[int], list[int]]] = {}
        for i, name in enumerate(outputs):
            v = self._lookup(name, ("output", "parameter", "calculatedParameter", "local",
                                    "input", "independent"), "output")
            if v.causality == "independent":
                raise ValueError(f"{name!r} is the independent variable; `time` is always returned")
            idx, vrs = by_type.setdefault(v.type, ([], []))
            idx.append(i)
            vrs.append(v.valueReference)
        s = self._slave
        getters = {"Real": s.getReal, "Integer": s.getInteger, "Enumeration": s.getInteger,
                   "Boolean": s.getBoolean}
        plan = []
        for typ, (idx, vrs) in by_type.items():
            if typ not in getters:
                raise ValueError(f"outputs of type {typ} are not supported")
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
    def _fail(self, exc: Exception, what: str, params: Mapping[str, Value]) -> RuntimeError:
        from fmpy.fmi1 import FMICallException

        if isinstance(exc, FMICallException):
            head = f"{exc.function} returned {_label(exc.status)} {what}"
            if exc.status >= 4:  # fmi2Fatal: the instance must not be used again
                self._free()
            else:
                self._state = "failed"
        else:
            head = f"{type(exc).__name__}: {exc} {what}"
            self._state = "failed"
        log = "\n".join(f"  [{st}] {cat}: {msg}" for st, cat, msg in self.messages)
        changed = ", ".join(f"{k}={v!r}" for k, v in params.items()) or "none (FMU defaults)"
        return RuntimeError(f"{self.model_description.modelName}: {head}\n"
                            f"parameters set: {changed}\n"
                            f"FMU log:\n{log if log else '  (no messages)'}")

    def _start(self, params: Mapping[str, Value], stop_time: float,
               inputs: Mapping[str, float] | None) -> None:
        if self._slave is None:
            self._instantiate()
        elif self._state != "instantiated":
            try:
                self._slave.reset()
            except Exception:  # a failed instance that cannot be reset: start afresh
                self._free()
                self._instantiate()
        self._state = "running"
        self.messages.clear()
        self._phase = "while setting parameters"
        self._set(params, ("parameter",), "parameter")
        if inputs:
            self._set(inputs, ("input",), "input")
        self._phase = "during initialisation"
        self._slave.setupExperiment(startTime=0.0, stopTime=float(stop_time))
        self._slave.enterInitializationMode()
        self._slave.exitInitializationMode()
        self._phase = "after initialisation"

    @staticmethod
    def _check_time(stop_time: float, step: float | None) -> None:
        if not (math.isfinite(stop_time) and stop_time > 0):
            raise ValueError(f"stop_time must be a positive finite number, got {stop_time!r}")
        if step is not None and not (math.isfinite(step) and step > 0):
            raise ValueError(f"step must be a positive finite number or None, got {step!r}")

    def _validate(self, params, outputs, inputs) -> None:
        for name in params:
            self._lookup(name, ("parameter",), "parameter")
        for name in inputs or {}:
            self._lookup(name, ("input",), "input")
        if isinstance(outputs, str):
            raise TypeError("outputs must be a list of names, not a string")

    def run(self, params: Mapping[str, Value], stop_time: float, step: float | None,
            outputs: list[str], inputs: Mapping[str, float] | None = None) -> pd.DataFrame:
        """Simulate from 0 to ``stop_time`` and return the outputs at the communication points.

        ``params`` are set after ``fmi2Reset`` (all others keep their start values), ``inputs`` are
        held constant. ``step`` is the communication step (the last step is shortened to end at
        ``stop_time``); ``None`` makes one single ``doStep`` and returns the start and end rows.
        The result has a ``time`` column followed by ``outputs``.
        """
        self._check_time(stop_time, step)
        self._validate(params, outputs, inputs)
        outputs = list(outputs)
        if step is None:
            times = np.array([0.0, float(stop_time)])
        else:
            n = max(1, math.ceil(stop_time / step - 1e-9))
            times = np.arange(n + 1, dtype=float) * step
            times[-1] = stop_time
        data = np.empty((len(times), len(outputs)))
        t = 0.0
        try:
            self._start(params, stop_time, inputs)
            read = self._reader(outputs)
            data[0] = read()
            do_step = self._slave.doStep
            for k in range(1, len(times)):
                t_next = times[k]
                self._phase = f"in the communication step from t = {t:.10g} s to {t_next:.10g} s"
                do_step(t, t_next - t)
                t = t_next
                data[k] = read()
        except ValueError:
            raise
        except Exception as exc:
            raise self._fail(exc, self._phase, params) from exc
        self._state = "done"
        df = pd.DataFrame(data, columns=outputs)
        df.insert(0, "time", times)
        return df

    def run_final(self, params: Mapping[str, Value], stop_time: float, outputs: list[str],
                  inputs: Mapping[str, float] | None = None) -> dict[str, float]:
        """One ``doStep`` from 0 to ``stop_time``; the final values of ``outputs``."""
        self._check_time(stop_time, None)
        self._validate(params, outputs, inputs)
        outputs = list(outputs)
        try:
            self._start(params, stop_time, inputs)
            read = self._reader(outputs)
            self._phase = f"in the communication step from t = 0 s to {stop_time:.10g} s"
            self._slave.doStep(0.0, float(stop_time))
            row = read()
        except ValueError:
            raise
        except Exception as exc:
            raise self._fail(exc, self._phase, params) from exc
        self._state = "done"
        return dict(zip(outputs, row))


def pullout(params: Mapping[str, Value] | None = None, stop_time: float = 12.0, step: float | None = 0.01,
            outputs: list[str] | None = None, runner: FMURunner | None = None,
            fmu_path: str | os.PathLike | None = None) -> pd.DataFrame:
    """The paper's force-driven pullout: F_pull ramps from 0 to F_max = 411 N over t_ramp = 10 s and
    is then held, simulated to 12 s with 0.01 s communication steps. ``params`` override the FMU's
    defaults (the paper's optimum c = 823224 N/m, d = 488 N·s/m)."""
    params = dict(params or {})
    outputs = list(outputs or PULLOUT_OUTPUTS)
    if runner is not None:
        return runner.run(params, stop_time, step, outputs)
    with FMURunner(fmu_path) as fmu:
        return fmu.run(params, stop_time, step, outputs)


# ---------------------------------------------------------------------- many runs, fast
class RunPlan:
    """Repeated runs of one FMU in which only some Real parameters change.

    Everything that does not change from run to run (value references, ctypes arrays, the fixed
    parameters and inputs) is prepared once; a run then costs reset, a few ctypes calls and the
    simulation itself. ``__call__`` returns the sampled outputs (one row per communication point).
    """

    def __init__(self, runner: FMURunner, varied: Sequence[str], fixed: Mapping[str, Value],
                 outputs: Sequence[str], stop_time: float, step: float | None,
                 inputs: Mapping[str, float] | None = None) -> None:
        from fmpy.fmi2 import fmi2Real, fmi2ValueReference

        runner._check_time(stop_time, step)
        runner._validate(fixed, list(outputs), inputs)
        self.runner = runner
        self.varied = list(varied)
        self.fixed = dict(fixed)
        self.inputs = dict(inputs or {})
        self.outputs = list(outputs)
        self.stop_time = float(stop_time)
        if step is None:
            self.times = np.array([0.0, self.stop_time])
        else:
            n = max(1, math.ceil(stop_time / step - 1e-9))
            self.times = np.arange(n + 1, dtype=float) * step
            self.times[-1] = stop_time
        vs = [runner._lookup(n, ("parameter",), "parameter") for n in self.varied]
        for v in vs:
            if v.type != "Real":
                raise ValueError(f"study parameter {v.name!r} is a {v.type}; only Real parameters can be varied")
            if v.variability not in ("fixed", "tunable"):
                raise ValueError(f"parameter {v.name!r} has variability {v.variability!r} and cannot be set")
        self._fixed_calls = self._prepared_sets(runner, self.fixed, ("parameter",), "parameter")
        self._input_calls = self._prepared_sets(runner, self.inputs, ("input",), "input")
        self._vr_varied = (fmi2ValueReference * len(vs))(*[v.valueReference for v in vs])
        self._val_varied = (fmi2Real * len(vs))()
        outs = [runner._lookup(n, ("output", "parameter", "calculatedParameter", "local"), "output")
                for n in self.outputs]
        if all(o.type == "Real" for o in outs):
            self._vr_out = (fmi2ValueReference * len(outs))(*[o.valueReference for o in outs])
            self._val_out = (fmi2Real * len(outs))()
            self._read = self._read_real
        else:
            self._read = runner._reader(self.outputs)

    @staticmethod
    def _prepared_sets(runner: FMURunner, values: Mapping[str, Value], allowed, role) -> list:
        """(setter name, vr array, value array) per type, built once."""
        from fmpy.fmi2 import fmi2Boolean, fmi2Integer, fmi2Real, fmi2ValueReference

        groups: dict[str, tuple[list[int], list]] = {}
        for name, value in values.items():
            v = runner._lookup(name, allowed, role)
            val = runner._coerce(v, value)
            if v.type == "Real" and not math.isfinite(val):
                raise ValueError(f"{name} must be finite, got {val!r}")
            vrs, vals = groups.setdefault(v.type, ([], []))
            vrs.append(v.valueReference)
            vals.append(val)
        ctype = {"Real": ("fmi2SetReal", fmi2Real), "Integer": ("fmi2SetInteger", fmi2Integer),
                 "Enumeration": ("fmi2SetInteger", fmi2Integer), "Boolean": ("fmi2SetBoolean", fmi2Boolean)}
        calls = []
        for typ, (vrs, vals) in groups.items():
            fn, ct = ctype[typ]
            calls.append((fn, (fmi2ValueReference * len(vrs))(*vrs), (ct * len(vals))(*vals)))
        return calls

    def _read_real(self) -> list[float]:
        s = self.runner._slave
        s.fmi2GetReal(s.component, self._vr_out, len(self._val_out), self._val_out)
        return list(self._val_out)

    def __call__(self, values: Sequence[float]) -> np.ndarray:
        r = self.runner
        if r._slave is None or r._state != "instantiated":
            if r._slave is None:
                r._instantiate()
            else:
                try:
                    r._slave.reset()
                except Exception:
                    r._free()
                    r._instantiate()
        s = r._slave
        r._state = "running"
        r.messages.clear()
        params = dict(zip(self.varied, values))
        data = np.empty((len(self.times), len(self.outputs)))
        t = 0.0
        try:
            r._phase = "while setting parameters"
            for fn, vr, val in self._fixed_calls:
                getattr(s, fn)(s.component, vr, len(vr), val)
            for i, x in enumerate(values):
                self._val_varied[i] = x
            s.fmi2SetReal(s.component, self._vr_varied, len(self._val_varied), self._val_varied)
            for fn, vr, val in self._input_calls:
                getattr(s, fn)(s.component, vr, len(vr), val)
            r._phase = "during initialisation"
            s.fmi2SetupExperiment(s.component, 0, 0.0, 0.0, 1, self.stop_time)
            s.fmi2EnterInitializationMode(s.component)
            s.fmi2ExitInitializationMode(s.component)
            data[0] = self._read()
            for k in range(1, len(self.times)):
                t_next = self.times[k]
                r._phase = f"in the communication step from t = {t:.10g} s to {t_next:.10g} s"
                s.fmi2DoStep(s.component, t, t_next - t, 1)
                t = t_next
                data[k] = self._read()
        except Exception as exc:
            raise r._fail(exc, r._phase, {**self.fixed, **params}) from exc
        r._state = "done"
        if not np.all(np.isfinite(data[-1])):
            bad = [n for n, x in zip(self.outputs, data[-1]) if not math.isfinite(x)]
            r._state = "failed"
            raise RuntimeError(f"{r.model_description.modelName}: non-finite output {', '.join(bad)} at "
                               f"t = {t:.10g} s; parameters {params}")
        return data


# ---------------------------------------------------------------------- batches, pools, clusters
@dataclass(frozen=True)
class PlanSpec:
    """Everything a worker needs to build its RunPlan: plain data, picklable, hashable."""
    fmu_path: str
    varied: tuple[str, ...]                  # FMU variables
    scale: tuple[float, ...]                 # FMU value = scale * study value + offset
    offset: tuple[float, ...]
    fixed: tuple[tuple[str, Value], ...]
    inputs: tuple[tuple[str, float], ...]
    outputs: tuple[str, ...]
    stop_time: float
    step: float | None
    rules: tuple[MetricRule, ...]


@dataclass
class RunResult:
    run_id: int
    values: tuple[float, ...]                # study values
    metrics: np.ndarray | None               # one per rule; None when the run failed
    status: str                              # "ok" | "failed"
    message: str
    seconds: float


_WORKER_PLANS: dict[PlanSpec, RunPlan] = {}


def _plan_for(spec: PlanSpec) -> RunPlan:
    """The calling process's RunPlan for ``spec``: one FMU instance per process and spec, reused."""
    plan = _WORKER_PLANS.get(spec)
    if plan is None:
        runner = FMURunner(spec.fmu_path)
        plan = RunPlan(runner, spec.varied, dict(spec.fixed), spec.outputs, spec.stop_time, spec.step,
                       dict(spec.inputs))
        _WORKER_PLANS[spec] = plan
    return plan


def run_chunk(spec: PlanSpec, chunk: Sequence[tuple[int, tuple[float, ...]]]) -> list[RunResult]:
    """Run a chunk of parameter sets; a failing run is recorded with its reason and the rest go on."""
    import time

    plan = _plan_for(spec)
    out = []
    for run_id, values in chunk:
        t0 = time.perf_counter()
        fmu_values = [s * x + o for s, x, o in zip(spec.scale, values, spec.offset)]
        try:
            data = plan(fmu_values)
            metrics = reduce_series(plan.times, data, spec.rules)
            out.append(RunResult(run_id, tuple(values), metrics, "ok", "", time.perf_counter() - t0))
        except Exception as exc:  # the FMU's own error: record it, keep going
            msg = str(exc).strip().replace("\n", " | ")
            out.append(RunResult(run_id, tuple(values), None, "failed", msg[:2000], time.perf_counter() - t0))
    return out


def _worker_main(conn, spec: PlanSpec) -> None:
    """A pool worker: receive chunks, send back one result per run as soon as it is done."""
    import signal
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # the parent decides when to stop
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
            self.workers.append(_Worker(self.ctx, self.spec))
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
                    reason = (f"the FMU crashed the worker process (signal {-code})" if code and code < 0
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
                        self._replace(w, f"timed out after {self.timeout_s:g} s (the FMU hangs or is too slow; "
                                         f"raise execution.timeout_s if it is only slow)", take, now)
            # workers replaced without a chunk left to finish pick up queued chunks
            for w in self.workers:
                if not w.pending and queue:
                    w.give(queue.pop(0), now)

    def _replace(self, w: _Worker, reason: str, take, now: float) -> None:
        run_id, values = w.pending[0]
        rest = w.pending[1:]
        w.kill()
        take([RunResult(run_id, tuple(values), None, "failed", reason, now - w.since)])
        nw = _Worker(self.ctx, self.spec)
        self.workers[self.workers.index(w)] = nw
        if rest:
            nw.give(rest, now)


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

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool = None
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
            futures = [self._client.submit(run_chunk, self.spec, c, pure=False)
                       for c in self._chunks(items, n)]
            for fut in as_completed(futures):
                take(fut.result())
        elif self.isolate or (self.workers > 1 and len(items) >= self.pool_threshold):
            if self._pool is None:
                self._pool = WorkerPool(self.spec, self.workers, self.timeout_s)
            size = max(1, min(200, len(items) // (self.workers * 8) or 1))
            self._pool.map(items, take, size)
        else:
            for c in self._chunks(items, 1):
                take(run_chunk(self.spec, c))
        return results
