"""Run the real ScrewVertebra FMU through fmpy's low-level FMI 2.0 co-simulation API.

No mocks: ``FMU2Slave`` is instantiated once per ``FmuRunner``; every case is
reset() -> parameters set by value reference -> setupExperiment -> enter/exitInitializationMode
-> inputs (setReal, optionally setRealInputDerivatives) -> doStep over the communication grid ->
getReal of the outputs at every communication point.

The FMU's log messages are captured (formatted by fmpy's native logger proxy, which ctypes needs
to receive the variadic arguments).  That proxy keeps one process-wide target, so ``close()``
points it back at fmpy's console logger.
"""

from __future__ import annotations

import math
import shutil
import tempfile
from ctypes import byref
from pathlib import Path

import numpy as np
from fmpy import calloc, extract, free, read_model_description
from fmpy.fmi1 import FMICallException, printLogMessage
from fmpy.fmi2 import (
    FMU2Slave,
    fmi2CallbackAllocateMemoryTYPE,
    fmi2CallbackFreeMemoryTYPE,
    fmi2CallbackFunctions,
    fmi2CallbackLoggerTYPE,
)
from fmpy.logging import addLoggerProxy

FMI2_OK, FMI2_WARNING, FMI2_DISCARD, FMI2_ERROR, FMI2_FATAL = 0, 1, 2, 3, 4

_DEFAULT_LOGGER = fmi2CallbackLoggerTYPE(printLogMessage)

__all__ = ["FmuRunner", "FMICallException", "FMI2_ERROR", "FMI2_OK", "comm_grid"]


class FmuRunner:
    """One instance of the FMU, reusable for many cases."""

    def __init__(self, fmu_path, logging_on: bool = True, instance_name: str = "sv_test"):
        # a private copy: a rebuild of dist/ during the session cannot swap the binary under us
        self._tmp = Path(tempfile.mkdtemp(prefix="fmu_run_"))
        copy = self._tmp / Path(fmu_path).name
        shutil.copyfile(fmu_path, copy)
        self.md = read_model_description(str(copy))
        self.unzipdir = extract(str(copy), unzipdir=str(self._tmp / "unzipped"))
        self.vars = {v.name: v for v in self.md.modelVariables}
        self.messages: list[tuple[int, str, str]] = []
        self._py_logger = fmi2CallbackLoggerTYPE(self._log)
        self.callbacks = fmi2CallbackFunctions()
        self.callbacks.logger = self._py_logger
        self.callbacks.allocateMemory = fmi2CallbackAllocateMemoryTYPE(calloc)
        self.callbacks.freeMemory = fmi2CallbackFreeMemoryTYPE(free)
        addLoggerProxy(byref(self.callbacks))
        self.fmu = FMU2Slave(guid=self.md.guid, unzipDirectory=self.unzipdir,
                             modelIdentifier=self.md.coSimulation.modelIdentifier,
                             instanceName=instance_name)
        self.fmu.instantiate(callbacks=self.callbacks, loggingOn=logging_on)
        self._closed = False

    # -- logging ------------------------------------------------------------------------------
    def _log(self, env, instance_name, status, category, message):
        self.messages.append((int(status), (category or b"").decode("utf-8", "replace"),
                              (message or b"").decode("utf-8", "replace")))

    def clear_log(self):
        self.messages.clear()

    def log_text(self, min_status: int = 0) -> str:
        return "\n".join(f"[{s}] {c}: {m}" for s, c, m in self.messages if s >= min_status)

    # -- variables ----------------------------------------------------------------------------
    def vr(self, name: str) -> int:
        try:
            return self.vars[name].valueReference
        except KeyError:
            raise KeyError(f"the FMU has no variable {name!r}") from None

    def set_values(self, values: dict):
        """Set variables by name with the setter matching their declared type."""
        reals, ints, bools = {}, {}, {}
        for name, val in values.items():
            t = self.vars[name].type if name in self.vars else None
            if t is None:
                raise KeyError(f"the FMU has no variable {name!r}")
            if t == "Real":
                reals[self.vr(name)] = float(val)
            elif t in ("Integer", "Enumeration"):
                ints[self.vr(name)] = int(val)
            elif t == "Boolean":
                bools[self.vr(name)] = bool(val)
            else:
                raise TypeError(f"{name}: unsupported type {t}")
        if ints:
            self.fmu.setInteger(list(ints), list(ints.values()))
        if bools:
            self.fmu.setBoolean(list(bools), list(bools.values()))
        if reals:
            self.fmu.setReal(list(reals), list(reals.values()))

    def get_reals(self, names) -> list[float]:
        return self.fmu.getReal([self.vr(n) for n in names])

    # -- a case -------------------------------------------------------------------------------
    def start(self, params: dict, stop_time: float | None = None, inputs: dict | None = None):
        """reset, set parameters (and inputs), initialise. FMICallException propagates."""
        self.fmu.reset()
        self.clear_log()
        if params:
            self.set_values(params)
        if inputs:
            self.set_values(inputs)
        self.fmu.setupExperiment(startTime=0.0, stopTime=stop_time)
        self.fmu.enterInitializationMode()
        self.fmu.exitInitializationMode()

    def simulate(self, params: dict, t_grid, outputs, inputs: dict | None = None,
                 input_fn=None) -> dict:
        """Run one case on the communication grid t_grid (t_grid[0] = 0).

        inputs: constant input values (set before initialisation and kept).
        input_fn(t_k) -> (values: dict, derivatives: dict) called before every doStep from t_k;
        the derivatives are set with setRealInputDerivatives (order 1).
        Returns {name: array over t_grid} (outputs read at every communication point, before the
        inputs of the next step are set) plus 't'."""
        t_grid = np.asarray(t_grid, dtype=float)
        outputs = list(outputs)
        vrs_out = [self.vr(n) for n in outputs]
        res = np.empty((len(outputs), t_grid.size))
        self.start(params, stop_time=float(t_grid[-1]), inputs=inputs)
        res[:, 0] = self.fmu.getReal(vrs_out)
        for k in range(t_grid.size - 1):
            t0, t1 = float(t_grid[k]), float(t_grid[k + 1])
            if input_fn is not None:
                vals, ders = input_fn(t0)
                if vals:
                    self.set_values(vals)
                if ders:
                    names = list(ders)
                    self.fmu.setRealInputDerivatives([self.vr(n) for n in names], [1] * len(names),
                                                     [float(ders[n]) for n in names])
            self.fmu.doStep(currentCommunicationPoint=t0, communicationStepSize=t1 - t0)
            res[:, k + 1] = self.fmu.getReal(vrs_out)
        self.fmu.terminate()
        out = {n: res[i] for i, n in enumerate(outputs)}
        out["t"] = t_grid
        return out

    def close(self):
        if self._closed:
            return
        self._closed = True
        try:
            self.fmu.freeInstance()
        finally:
            restore = fmi2CallbackFunctions()
            restore.logger = _DEFAULT_LOGGER
            addLoggerProxy(byref(restore))
            shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def comm_grid(stop: float, step: float) -> np.ndarray:
    """Communication points k*step (not accumulated), the last one exactly stop."""
    n = int(math.floor(stop / step + 0.5))
    t = np.arange(n + 1) * step
    t[-1] = stop
    return t
