"""FMI 3.0 FMUs behind the FMI 2.0 face the runner and the plans speak (through fmpy's FMU3Slave / FMU3Model).

:class:`FMI3Instance` wraps fmpy's FMI 3 instance and offers the calls :class:`~fmusa.fmi.runner.FMURunner`
and :mod:`fmusa.fmi.plans` make on an FMI 2 instance, with the same arguments: ``setReal``/``getReal`` …,
``setupExperiment`` → ``enterInitializationMode`` → ``exitInitializationMode``, ``doStep``, ``reset`` and the
prepared ctypes calls ``fmi2SetReal(component, vrs, n, values)`` …. So FMI 3 FMUs run through the same
public interface (``FMURunner.run``/``run_final``, ``RunPlan``, ``DrivenPlan``) with a few branches there.

The value references those calls carry are the *scalar indices* of :func:`fmusa.fmi.info.scalar_variables`:
an array element ``x[2]`` is one scalar, and setting it sets the whole array ``x`` (FMI 3.0 sets arrays
whole) from the values this instance knows: the declared start values, then what was set since the last
reset. Getting it reads the whole array and picks the element.

Why the FMI 2 face rather than a second runner: the studies, checks and plans stay one code path, and an
FMI 3 FMU is checked and run exactly as an FMI 2 one is.
"""
from __future__ import annotations

from typing import Callable, Iterable, Sequence

import numpy as np

from fmusa.fmi.info import FMUInfo, ScalarVariable

#: fmpy's setter/getter suffix for each FMI 3.0 type fmusa uses (an enumeration is an Int64).
_CALL_TYPE = {"Float64": "Float64", "Float32": "Float32", "Int8": "Int8", "UInt8": "UInt8", "Int16": "Int16",
              "UInt16": "UInt16", "Int32": "Int32", "UInt32": "UInt32", "Int64": "Int64", "UInt64": "UInt64",
              "Boolean": "Boolean", "Enumeration": "Int64"}


def _python_value(sv: ScalarVariable, text) -> object:
    """A declared start (a string) as the Python value of ``sv``'s type."""
    if sv.type == "Real":
        return float(text)
    if sv.type == "Boolean":
        return str(text).strip().lower() in ("true", "1")
    return int(float(text))


def _zero(sv: ScalarVariable) -> object:
    return 0.0 if sv.type == "Real" else (False if sv.type == "Boolean" else 0)


class FMI3Instance:
    """An instantiated FMI 3.0 FMU (``fmu``: fmpy's FMU3Slave or FMU3Model) with an FMI 2.0 face.

    ``log(env, instance_name, status, category, message)`` receives the FMU's log messages (the FMI 2
    logger's arguments). ``setupExperiment`` only records the tolerance and times: FMI 3.0 passes them to
    ``fmi3EnterInitializationMode``; a tolerance left undefined is the default experiment's, as fmpy does.
    """

    def __init__(self, info: FMUInfo, unzipdir: str, interface: str, instance_name: str,
                 log: Callable, debug_categories: Sequence[str] = ()) -> None:
        from fmpy.fmi3 import FMU3Model, FMU3Slave

        md = info.model_description
        self.info = info
        self.is_model_exchange = interface == "model-exchange"
        cls = FMU3Model if self.is_model_exchange else FMU3Slave
        self.fmu = cls(guid=md.instantiationToken or md.guid, unzipDirectory=str(unzipdir),
                       modelIdentifier=info.interfaces[interface], instanceName=instance_name)
        self._scalars: list[ScalarVariable] = list(info.variables)
        self._arrays: dict[int, list] = {}          # vr -> the array's values as this instance knows them
        self._starts: dict[int, list] = {}
        for sv in self._scalars:
            if sv.index is not None:
                self._starts.setdefault(sv.vr, [None] * sv.size)[sv.index] = (
                    _zero(sv) if sv.start is None else _python_value(sv, sv.start))
        self._plans: dict[tuple, list] = {}
        self._fast: dict[tuple, tuple] = {}          # (id of a ctypes vr array, n) -> (the array, its plan)
        self._step_out = None
        self._experiment = (None, 0.0, None)
        self._default_tolerance = info.default_experiment.get("tolerance")

        def logger(env, status, category, message) -> None:
            log(env, None, status, category, message)
        kwargs = {"loggingOn": bool(debug_categories), "logMessage": logger}
        self.fmu.instantiate(**kwargs)
        if debug_categories:
            self.fmu.setDebugLogging(True, list(debug_categories))
        self._restart()
        #: FMI 2's component handle; the prepared calls pass it back and this instance ignores it.
        self.component = None

    # ------------------------------------------------------------------ life cycle
    def _restart(self) -> None:
        self._arrays = {vr: list(vals) for vr, vals in self._starts.items()}

    def reset(self) -> None:
        """fmi3Reset: the FMU's variables are back at their start values, and so are the arrays known here."""
        self.fmu.reset()
        self._restart()

    def freeInstance(self) -> None:
        self.fmu.freeInstance()

    def terminate(self) -> None:
        self.fmu.terminate()

    # FMU state snapshots under FMI 2's names (FMI 3.0 spells them ...FMUState); the values known here
    # go with the snapshot, so a restored state sets arrays from what they were when it was taken
    def getFMUstate(self):
        return self.fmu.getFMUState(), {vr: list(v) for vr, v in self._arrays.items()}

    def setFMUstate(self, state) -> None:
        fmu_state, arrays = state
        self.fmu.setFMUState(fmu_state)
        self._arrays = {vr: list(v) for vr, v in arrays.items()}

    def freeFMUstate(self, state) -> None:
        self.fmu.freeFMUState(state[0])

    def setDebugLogging(self, on: bool, categories: Sequence[str]) -> None:
        self.fmu.setDebugLogging(on, list(categories))

    def setupExperiment(self, tolerance: float | None = None, startTime: float = 0.0,
                        stopTime: float | None = None) -> None:
        self._experiment = (tolerance, float(startTime), stopTime)

    def enterInitializationMode(self) -> None:
        tol, start, stop = self._experiment
        self.fmu.enterInitializationMode(tolerance=self._default_tolerance if tol is None else tol,
                                         startTime=start, stopTime=stop)

    def exitInitializationMode(self) -> None:
        self.fmu.exitInitializationMode()

    def doStep(self, currentCommunicationPoint: float, communicationStepSize: float,
               noSetFMUStatePriorToCurrentPoint: bool = True) -> None:
        """fmi3DoStep; an FMU that asks to end the simulation ends the run (a RuntimeError naming the time)."""
        out = self._step_out        # fmi3DoStep's four results, allocated once (a call per communication point)
        if out is None:
            from ctypes import byref

            from fmpy.fmi3 import fmi3Boolean, fmi3Float64
            vals = (fmi3Boolean(), fmi3Boolean(), fmi3Boolean(), fmi3Float64())
            out = self._step_out = (vals, tuple(byref(v) for v in vals))
        self.fmu.fmi3DoStep(self.fmu.component, currentCommunicationPoint, communicationStepSize,
                            bool(noSetFMUStatePriorToCurrentPoint), *out[1])
        if out[0][1].value:
            raise RuntimeError(f"the FMU asked to terminate the simulation in fmi3DoStep at t = "
                               f"{out[0][3].value:.10g} s (step from {currentCommunicationPoint:.10g} s)")

    # ------------------------------------------------------------------ values by scalar index
    def _plan(self, refs: tuple) -> list:
        """How to read the scalars ``refs``, built once per tuple of refs: per FMI 3 type, (fmpy's ctypes
        getter ``fmi3Get<Type>``, the value references as a ctypes array, the number of values, a ctypes
        buffer for them, [(position in refs, offset in the buffer)]). A read then costs one ctypes call per
        type, no allocation (it runs at every communication point)."""
        plan = self._plans.get(refs)
        if plan is not None:
            return plan
        import fmpy.fmi3 as f3

        groups: dict[str, tuple[list, dict, list]] = {}
        for pos, ref in enumerate(refs):
            sv = self._scalars[ref]
            vrs, offsets, picks = groups.setdefault(_CALL_TYPE[sv.fmi3_type], ([], {}, []))
            if sv.vr not in offsets:
                offsets[sv.vr] = sum(self._scalars_size(v) for v in vrs)
                vrs.append(sv.vr)
            picks.append((pos, offsets[sv.vr] + (sv.index or 0)))
        plan = []
        for typ, (vrs, _, picks) in groups.items():
            n = sum(self._scalars_size(v) for v in vrs)
            plan.append((getattr(self.fmu, "fmi3Get" + typ), (f3.fmi3ValueReference * len(vrs))(*vrs), n,
                         (getattr(f3, "fmi3" + typ) * n)(), picks))
        self._plans[refs] = plan
        return plan

    def _scalars_size(self, vr: int) -> int:
        arr = self._starts.get(vr)
        return 1 if arr is None else len(arr)

    def get(self, refs: Iterable[int]) -> list:
        """The values of the scalars ``refs`` (any types), in order."""
        refs = tuple(int(r) for r in refs)
        out: list = [None] * len(refs)
        component = self.fmu.component
        for getter, vrs, n, buf, picks in self._plan(refs):
            getter(component, vrs, len(vrs), buf, n)
            for pos, off in picks:
                out[pos] = buf[off]
        return out

    def set(self, refs: Iterable[int], values: Iterable) -> None:
        """Set the scalars ``refs`` to ``values``: scalars of one type in one call, an array whole."""
        groups: dict[str, tuple[list, list]] = {}
        touched: dict[int, str] = {}
        for ref, value in zip(refs, values):
            sv = self._scalars[int(ref)]
            typ = _CALL_TYPE[sv.fmi3_type]
            if sv.index is None:
                vrs, vals = groups.setdefault(typ, ([], []))
                vrs.append(sv.vr)
                vals.append(value)
            else:
                self._arrays[sv.vr][sv.index] = value
                touched[sv.vr] = typ
        for typ, (vrs, vals) in groups.items():
            getattr(self.fmu, "set" + typ)(vrs, vals)
        for vr, typ in touched.items():
            getattr(self.fmu, "set" + typ)([vr], list(self._arrays[vr]))

    # the FMI 2 names the runner calls
    def setReal(self, vrs, values) -> None:
        self.set(vrs, [float(x) for x in values])

    def setInteger(self, vrs, values) -> None:
        self.set(vrs, [int(x) for x in values])

    def setBoolean(self, vrs, values) -> None:
        self.set(vrs, [bool(x) for x in values])

    def getReal(self, vrs) -> list:
        return [float(x) for x in self.get(vrs)]

    def getInteger(self, vrs) -> list:
        return [int(x) for x in self.get(vrs)]

    def getBoolean(self, vrs) -> list:
        return [bool(x) for x in self.get(vrs)]

    # the prepared ctypes calls of the plans (fmusa.fmi.plans), same arguments as fmpy's FMI 2 functions
    def fmi2SetReal(self, component, vr, nvr, value) -> int:
        self.set([vr[i] for i in range(nvr)], [float(value[i]) for i in range(nvr)])
        return 0

    def fmi2SetInteger(self, component, vr, nvr, value) -> int:
        self.set([vr[i] for i in range(nvr)], [int(value[i]) for i in range(nvr)])
        return 0

    def fmi2SetBoolean(self, component, vr, nvr, value) -> int:
        self.set([vr[i] for i in range(nvr)], [bool(value[i]) for i in range(nvr)])
        return 0

    def fmi2GetReal(self, component, vr, nvr, value) -> int:
        # a plan reads through the same ctypes array every time: its read plan is found by the array's id
        key = (id(vr), nvr)
        fast = self._fast.get(key)
        if fast is None or fast[0] is not vr:
            fast = (vr, self._plan(tuple(int(vr[k]) for k in range(nvr))))
            self._fast[key] = fast
        comp = self.fmu.component
        for getter, vrs, n, buf, picks in fast[1]:
            getter(comp, vrs, len(vrs), buf, n)
            for pos, off in picks:
                value[pos] = buf[off]
        return 0

    def fmi2SetupExperiment(self, component, toleranceDefined, tolerance, startTime, stopTimeDefined,
                            stopTime) -> int:
        self.setupExperiment(float(tolerance) if toleranceDefined else None, startTime,
                             float(stopTime) if stopTimeDefined else None)
        return 0

    def fmi2EnterInitializationMode(self, component) -> int:
        self.enterInitializationMode()
        return 0

    def fmi2ExitInitializationMode(self, component) -> int:
        self.exitInitializationMode()
        return 0

    def fmi2DoStep(self, component, t, h, no_set_state_prior) -> int:
        self.doStep(t, h, bool(no_set_state_prior))
        return 0

    def fmi2SetRealInputDerivatives(self, component, vr, nvr, order, value) -> int:
        raise RuntimeError("FMI 3.0 co-simulation has no input derivatives (fmi2SetRealInputDerivatives)")


# ---------------------------------------------------------------------- model exchange through fmpy
def me_start_values(info: FMUInfo, values: dict) -> dict:
    """fmpy's ``start_values`` for FMI 3.0: element values (``x[2]``) gathered into whole arrays, the other
    elements at their declared starts."""
    out: dict = {}
    arrays: dict[str, list] = {}
    for name, value in values.items():
        sv = info.variable(name)
        if sv is None or sv.index is None:
            out[name] = value
            continue
        arr = arrays.get(sv.array_name)
        if arr is None:
            arr = [None] * sv.size
            for other in info.variables:
                if other.index is not None and other.vr == sv.vr:
                    arr[other.index] = _zero(other) if other.start is None else _python_value(other, other.start)
            arrays[sv.array_name] = arr
        arr[sv.index] = value
    out.update(arrays)
    return out


def me_outputs(info: FMUInfo, outputs: Sequence[str]) -> list[str]:
    """The variable names fmpy records for ``outputs`` (an element's array, once)."""
    names: list[str] = []
    for name in outputs:
        sv = info.variable(name)
        base = sv.array_name if sv is not None and sv.index is not None else name
        if base not in names:
            names.append(base)
    return names


def me_columns(info: FMUInfo, res, outputs: Sequence[str]) -> dict:
    """fmpy's result ``res`` as columns by scalar name: ``time`` and each of ``outputs`` (an element of an
    array column picked out)."""
    cols = {"time": np.asarray(res["time"], dtype=float)}
    for name in outputs:
        sv = info.variable(name)
        if sv is not None and sv.index is not None:
            arr = np.asarray(res[sv.array_name], dtype=float).reshape(len(cols["time"]), -1)
            cols[name] = arr[:, sv.index]
        else:
            cols[name] = np.asarray(res[name], dtype=float)
    return cols

