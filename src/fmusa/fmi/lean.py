"""A co-simulation FMI 2.0 FMU run on ctypes and the standard library only: the pool's lean worker path.

A worker started by ``spawn`` pays for every module it imports, and a crash-heavy study starts one worker
per crash: numpy and fmpy are ~0.2 s of CPU of each start. :class:`LeanFMU` makes the runs a
:class:`~fmusa.fmi.plans.RunPlan` makes for the common case (FMI 2.0 co-simulation, fixed-step
``fmi2DoStep``, values set and Real outputs read by value reference) with the same calls in the same order
and the same error messages, so that its outputs are bit for bit fmpy's. What it covers is decided in the
parent by :func:`fmusa.fmi.plans.lean_plan` (which gives None for anything else: fmpy runs those), and
everything it needs comes from there as plain data: the library's path (fmpy's lookup: ``binaries/<platform>/
<modelIdentifier>`` + ``.so``, ``.dll`` or ``.dylib``), fmpy's logger proxy library, the value references.
Every call is cdecl (``CDLL``/``CFUNCTYPE``), as fmpy makes them on Linux, macOS and Windows.
"""
from __future__ import annotations

import ctypes
import math
import os
import sys
from array import array
from collections import deque
from ctypes import (CFUNCTYPE, POINTER, Structure, byref, c_char_p, c_double, c_int, c_size_t, c_uint,
                    c_void_p)

_STATUS = ("OK", "Warning", "Discard", "Error", "Fatal", "Pending")
_CALL_LABELS = ("ok", "warning", "discard", "error", "fatal", "pending")     # fmpy's, in its exception
FMI2_COSIMULATION = 1

LOGGER = CFUNCTYPE(None, c_void_p, c_char_p, c_int, c_char_p, c_char_p)
ALLOCATE = CFUNCTYPE(c_void_p, c_size_t, c_size_t)
FREE = CFUNCTYPE(None, c_void_p)
STEP_FINISHED = CFUNCTYPE(None, c_void_p, c_int)


class Callbacks(Structure):
    """fmi2CallbackFunctions (fmi2FunctionTypes.h), as fmpy declares it."""
    _fields_ = [("logger", LOGGER), ("allocateMemory", ALLOCATE), ("freeMemory", FREE),
                ("stepFinished", STEP_FINISHED), ("componentEnvironment", c_void_p)]


_VR = POINTER(c_uint)
#: name -> (restype, argtypes) of the calls made here (fmpy's declarations)
_SIGNATURES = {
    "fmi2Instantiate": (c_void_p, [c_char_p, c_int, c_char_p, c_char_p, POINTER(Callbacks), c_int, c_int]),
    "fmi2FreeInstance": (None, [c_void_p]),
    "fmi2SetDebugLogging": (c_int, [c_void_p, c_int, c_size_t, POINTER(c_char_p)]),
    "fmi2SetupExperiment": (c_int, [c_void_p, c_int, c_double, c_double, c_int, c_double]),
    "fmi2EnterInitializationMode": (c_int, [c_void_p]),
    "fmi2ExitInitializationMode": (c_int, [c_void_p]),
    "fmi2Reset": (c_int, [c_void_p]),
    "fmi2SetReal": (c_int, [c_void_p, _VR, c_size_t, POINTER(c_double)]),
    "fmi2SetInteger": (c_int, [c_void_p, _VR, c_size_t, POINTER(c_int)]),
    "fmi2SetBoolean": (c_int, [c_void_p, _VR, c_size_t, POINTER(c_int)]),
    "fmi2GetReal": (c_int, [c_void_p, _VR, c_size_t, POINTER(c_double)]),
    "fmi2DoStep": (c_int, [c_void_p, c_double, c_double, c_int]),
    "fmi2GetFMUstate": (c_int, [c_void_p, POINTER(c_void_p)]),
    "fmi2SetFMUstate": (c_int, [c_void_p, c_void_p]),
    "fmi2FreeFMUstate": (c_int, [c_void_p, POINTER(c_void_p)]),
}
_SETTERS = {"Real": ("fmi2SetReal", c_double), "Integer": ("fmi2SetInteger", c_int),
            "Boolean": ("fmi2SetBoolean", c_int)}


class FMICallError(Exception):
    """An FMI call returned more than fmi2Warning (fmpy's FMICallException: the same rule, the same name)."""

    def __init__(self, function: str, status: int) -> None:
        label = _CALL_LABELS[status] if 0 <= status < len(_CALL_LABELS) else "illegal return code"
        super().__init__(f"{function} failed with status {status} ({label}).")
        self.function = function
        self.status = status


class LeanRunError(Exception):
    """A run the FMU rejected or whose result is unusable; the message is FMURunner's, word for word."""


def status_label(status: int) -> str:
    """An fmi2Status by name ("Error"), as fmusa's messages give it (also FMURunner's: one spelling)."""
    return _STATUS[status] if 0 <= status < len(_STATUS) else f"status {status}"


def failure_head(function: str | None, status: int | None, exc: BaseException, what: str) -> str:
    """The first line's cause of a failed run: the FMI call and its status, or the exception."""
    if function is not None:
        return f"{function} returned {status_label(status)} {what}"
    return f"{type(exc).__name__}: {exc} {what}"


def failure_text(model_name: str, head: str, params, messages) -> str:
    """A failed run's message (FMURunner's and the lean worker's alike): the cause, the parameters set and
    the FMU's log."""
    log = "\n".join(f"  [{st}] {cat}: {msg}" for st, cat, msg in messages)
    changed = ", ".join(f"{k}={v!r}" for k, v in params.items()) or "none (FMU defaults)"
    return f"{model_name}: {head}\nparameters set: {changed}\nFMU log:\n{log if log else '  (no messages)'}"


def _c_runtime():
    """(calloc, free, freeLibrary) as fmpy takes them: the C library's, ``dlclose`` / ``FreeLibrary``."""
    if sys.platform.startswith("win"):
        crt = ctypes.cdll.msvcrt
        calloc, free, free_library = crt.calloc, crt.free, ctypes.windll.kernel32.FreeLibrary
    else:
        libc = ctypes.CDLL(None)
        calloc, free, free_library = libc.calloc, libc.free, libc.dlclose
    calloc.argtypes, calloc.restype = [c_size_t, c_size_t], c_void_p
    free.argtypes, free.restype = [c_void_p], None
    free_library.argtypes = [c_void_p]
    return calloc, free, free_library


class LeanFMU:
    """One instantiated FMI 2.0 co-simulation FMU, run again and again as :class:`~fmusa.fmi.runner.FMURunner`
    and :class:`~fmusa.fmi.plans.RunPlan` run it: ``fmi2Instantiate`` → ``fmi2SetupExperiment`` → set values →
    ``fmi2EnterInitializationMode`` → ``fmi2ExitInitializationMode`` → ``fmi2DoStep`` …, the instance brought
    back between runs by ``fmi2Reset``, a state snapshot or a new instance (its library loaded anew), as
    ``plan["reuse"]`` says. ``plan`` is :func:`fmusa.fmi.plans.lean_plan`'s plain data."""

    def __init__(self, plan: dict) -> None:
        self.plan = plan
        self.reuse = plan["reuse"]
        self.model_name = plan["model_name"]
        self.varied = list(plan["varied"])
        self.fixed = dict(plan["fixed"])
        self.times = list(plan["times"])
        #: the communication points whose rows are sent back (None: every one)
        self.keep = None if plan["keep"] is None else frozenset(plan["keep"])
        self.tolerance = plan["tolerance"]
        self.stop_time = float(self.times[-1])
        self.messages: deque = deque(maxlen=500)
        self._calloc, self._free_c, self._free_library = _c_runtime()
        self._proxy = None
        if plan["logger_proxy"] and os.path.isfile(plan["logger_proxy"]):
            try:
                self._proxy = ctypes.cdll.LoadLibrary(plan["logger_proxy"]).addLoggerProxy
                self._proxy.argtypes, self._proxy.restype = [c_void_p], None
            except Exception:  # noqa: BLE001 - as fmpy: no proxy, messages unformatted
                self._proxy = None
        self._cats = [c.encode("utf-8") for c in plan["debug_logging"]]
        self._calls = []
        for typ, vrs, vals in plan["fixed_calls"]:
            fn, ct = _SETTERS[typ]
            self._calls.append((fn, (c_uint * len(vrs))(*vrs), (ct * len(vals))(*vals)))
        self._inputs = []
        for typ, vrs, vals in plan["input_calls"]:
            fn, ct = _SETTERS[typ]
            self._inputs.append((fn, (c_uint * len(vrs))(*vrs), (ct * len(vals))(*vals)))
        self._vr_varied = (c_uint * len(plan["varied_vrs"]))(*plan["varied_vrs"])
        self._val_varied = (c_double * len(plan["varied_vrs"]))()
        self.outputs = list(plan["outputs"])
        self._vr_out = (c_uint * len(plan["output_vrs"]))(*plan["output_vrs"])
        self._val_out = (c_double * len(plan["output_vrs"]))()
        self.dll = None
        self.component = None
        self._snapshot = None
        self._state = "closed"
        self.phase = ""
        self._instantiate()

    # ------------------------------------------------------------------ instance management
    def _load(self) -> None:
        """The library, loaded as fmpy loads it (from its own folder, the working directory given back)."""
        path = self.plan["library"]
        if not os.path.isfile(path):
            raise Exception(f"Cannot find shared library {path}.")
        cwd = os.getcwd()
        os.chdir(os.path.dirname(path))     # some DLLs resolve their dependencies from there
        try:
            dll = ctypes.cdll.LoadLibrary(path)
        except Exception as e:
            raise Exception(f"Failed to load shared library {path}. {e}") from None
        finally:
            os.chdir(cwd)
        for name in self.plan["required"]:       # fmpy loads every FMI 2.0 function: a missing one fails
            getattr(dll, name)
        for name, (res, args) in _SIGNATURES.items():
            f = getattr(dll, name)
            f.restype, f.argtypes = res, args
        self.dll = dll

    def _instantiate(self) -> None:
        self._load()
        dll = self.dll
        cb = Callbacks()
        self._logger_cb = LOGGER(self._log_message)     # referenced: it must outlive the instance
        cb.logger = self._logger_cb
        cb.allocateMemory = ALLOCATE(ctypes.cast(self._calloc, c_void_p).value)
        cb.freeMemory = FREE(ctypes.cast(self._free_c, c_void_p).value)
        if self._proxy is not None:
            try:
                self._proxy(byref(cb))
            except Exception:  # noqa: BLE001 - as fmpy
                pass
        self._callbacks = cb
        p = self.plan
        comp = dll.fmi2Instantiate(p["instance_name"].encode("utf-8"), FMI2_COSIMULATION, p["guid"].encode("utf-8"),
                                   p["resource_uri"].encode("utf-8"), byref(cb), 0, 1 if self._cats else 0)
        if comp is None:
            raise Exception("Failed to instantiate model")
        self.component = comp
        if self._cats:
            cats = (c_char_p * len(self._cats))(*self._cats)
            self._check("fmi2SetDebugLogging", dll.fmi2SetDebugLogging(comp, 1, len(self._cats), cats))
        if self.reuse == "snapshot":
            state = c_void_p()
            self._check("fmi2GetFMUstate", dll.fmi2GetFMUstate(comp, byref(state)))
            self._snapshot = state
        self._state = "instantiated"

    @staticmethod
    def _check(function: str, status: int) -> None:
        if status > 1:
            raise FMICallError(function, status)

    def _free(self) -> None:
        if self.component is not None:
            dll = self.dll
            if self._snapshot is not None:
                try:
                    dll.fmi2FreeFMUstate(self.component, byref(self._snapshot))
                except Exception:  # noqa: BLE001 - as FMURunner
                    pass
            try:
                dll.fmi2FreeInstance(self.component)
                self._free_library(dll._handle)
            except Exception:  # noqa: BLE001 - as FMURunner
                pass
        self.component = None
        self._snapshot = None
        self._state = "closed"

    def close(self) -> None:
        self._free()

    def _log_message(self, env, instance_name, status, category, message) -> None:
        def text(b):
            return b.decode("utf-8", "replace") if b else ""
        self.messages.append((status_label(status), text(category), text(message)))

    def restore(self) -> None:
        """Back to the state right after instantiation (FMURunner.restore)."""
        if self.component is None or self.reuse == "fresh":
            self._free()
            self._instantiate()
        elif self.reuse == "snapshot":
            self._check("fmi2SetFMUstate", self.dll.fmi2SetFMUstate(self.component, self._snapshot))
        else:
            self._check("fmi2Reset", self.dll.fmi2Reset(self.component))
        self._state = "instantiated"

    def ready(self) -> None:
        """An instance as instantiated, for a new run (FMURunner.ready)."""
        if self.component is None:
            self._instantiate()
        elif self._state != "instantiated":
            try:
                self.restore()
            except Exception:  # noqa: BLE001 - a failed instance that cannot be brought back: start afresh
                self._free()
                self._instantiate()
        self._state = "running"
        self.messages.clear()

    # ------------------------------------------------------------------ running
    def _fail(self, exc: BaseException, values) -> LeanRunError:
        """FMURunner.fail's error for ``exc``, which ended the run at ``values``."""
        call = isinstance(exc, FMICallError)
        head = failure_head(exc.function if call else None, exc.status if call else None, exc, self.phase)
        if call and exc.status >= 4:      # fmi2Fatal: the instance must not be used again
            self._free()
        else:
            self._state = "failed"
        params = {**self.fixed, **dict(zip(self.varied, values))}
        return LeanRunError(failure_text(self.model_name, head, params, self.messages))

    def run(self, values: list, out: array) -> None:
        """One run with the varied parameters at ``values`` (FMU units): its outputs at the kept
        communication points are appended to ``out`` (row by row); LeanRunError when it fails."""
        self.ready()
        dll, comp = self.dll, self.component
        check = self._check
        times, keep = self.times, self.keep
        vr_out, val_out, n_out = self._vr_out, self._val_out, len(self._val_out)
        get_real, do_step = dll.fmi2GetReal, dll.fmi2DoStep
        start = len(out)
        t = 0.0
        k = 0
        try:
            self.phase = "while setting up the experiment"
            if self.tolerance is None:
                check("fmi2SetupExperiment", dll.fmi2SetupExperiment(comp, 0, 0.0, 0.0, 1, self.stop_time))
            else:
                check("fmi2SetupExperiment", dll.fmi2SetupExperiment(comp, 1, self.tolerance, 0.0, 1,
                                                                      self.stop_time))
            self.phase = "while setting parameters"
            for fn, vr, val in self._calls:
                check(fn, getattr(dll, fn)(comp, vr, len(vr), val))
            val_varied = self._val_varied
            for i, x in enumerate(values):
                val_varied[i] = x
            if len(val_varied):
                check("fmi2SetReal", dll.fmi2SetReal(comp, self._vr_varied, len(val_varied), val_varied))
            for fn, vr, val in self._inputs:
                check(fn, getattr(dll, fn)(comp, vr, len(vr), val))
            self.phase = "during initialisation"
            check("fmi2EnterInitializationMode", dll.fmi2EnterInitializationMode(comp))
            check("fmi2ExitInitializationMode", dll.fmi2ExitInitializationMode(comp))
            st = get_real(comp, vr_out, n_out, val_out)
            if st > 1:
                raise FMICallError("fmi2GetReal", st)
            if keep is None or 0 in keep:
                out.frombytes(bytes(val_out))
            for k in range(1, len(times)):
                t_next = times[k]
                st = do_step(comp, t, t_next - t, 1)
                if st > 1:
                    self.phase = f"in the communication step from t = {t:.10g} s to {t_next:.10g} s"
                    raise FMICallError("fmi2DoStep", st)
                t = t_next
                st = get_real(comp, vr_out, n_out, val_out)
                if st > 1:
                    self.phase = f"in the communication step from t = {times[k - 1]:.10g} s to {t:.10g} s"
                    raise FMICallError("fmi2GetReal", st)
                if keep is None or k in keep:
                    out.frombytes(bytes(val_out))
        except Exception as exc:
            del out[start:]
            raise self._fail(exc, values) from exc
        self._state = "done"
        last = list(val_out)
        if not all(math.isfinite(x) for x in last):
            del out[start:]
            self._state = "failed"
            bad = [n for n, x in zip(self.outputs, last) if not math.isfinite(x)]
            params = dict(zip(self.varied, values))
            raise LeanRunError(f"{self.model_name}: non-finite output {', '.join(bad)} at t = {t:.10g} s; "
                               f"parameters {params}")
