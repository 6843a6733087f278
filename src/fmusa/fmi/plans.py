"""Repeated runs of one FMU instance with prepared ctypes calls: RunPlan (fixed scenario) and DrivenPlan (a sampled drive).

The plans drive an :class:`~fmusa.fmi.runner.FMURunner` through its public methods only (``ready``,
``lookup``, ``coerce``, ``instance``, ``phase``, ``fail``, ``reject``, ``mark_done``), so the runner can
change how it keeps its instance without breaking them.
"""
from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from fmpy.fmi1 import FMICallException

from fmusa.fmi.info import FMUError, FMUTimeLimitError, Value
from fmusa.fmi.runner import READABLE, FMURunner, communication_points

#: Causalities a plan reads through ``fmi2GetReal`` (inputs are set, not read, by a co-simulation plan).
_PLAN_READABLE = ("output", "parameter", "calculatedParameter", "local")
#: Causalities a study parameter may have: a parameter, or an input held at the study's value over the run.
VARIED = ("parameter", "input")


# ---------------------------------------------------------------------- many runs, fast
def _step_calls(s) -> tuple:
    """fmi2SetReal, fmi2SetRealInputDerivatives, fmi2DoStep and fmi2GetReal of an fmpy instance: its ctypes
    functions themselves, which return the status for the caller to check, where fmpy keeps them as this
    version does and logs no calls (its wrapper, two Python calls and a check each, was a quarter of a driven run
    of our FMU); else fmpy's methods, which raise on an error themselves."""
    names = ("fmi2SetReal", "fmi2SetRealInputDerivatives", "fmi2DoStep", "fmi2GetReal")
    raw = getattr(s, "_functions", None)
    if getattr(s, "fmiCallLogger", None) is None and isinstance(raw, dict) and all(n in raw for n in names):
        return tuple(raw[n] for n in names)
    return tuple(getattr(s, n) for n in names)


def _initialise(r: FMURunner, fixed_calls: list, vr_varied, val_varied, values: Sequence[float],
                input_calls: list, start: float, stop: float) -> None:
    """Set the prepared parameters and inputs of one run on a ready instance and initialise it (the part
    RunPlan and DrivenPlan share; the phases name where a failure happened)."""
    s = r.instance
    # fmpy's order: the experiment first, then the values (some exports drop values set before it)
    r.phase = "while setting up the experiment"
    if r.setup_tolerance is None:
        s.fmi2SetupExperiment(s.component, 0, 0.0, start, 1, stop)
    else:
        s.fmi2SetupExperiment(s.component, 1, r.setup_tolerance, start, 1, stop)
    r.phase = "while setting parameters"
    for fn, vr, val in fixed_calls:
        getattr(s, fn)(s.component, vr, len(vr), val)
    for i, x in enumerate(values):
        val_varied[i] = x
    if len(vr_varied):
        s.fmi2SetReal(s.component, vr_varied, len(val_varied), val_varied)
    for fn, vr, val in input_calls:
        getattr(s, fn)(s.component, vr, len(vr), val)
    r.phase = "during initialisation"
    s.fmi2EnterInitializationMode(s.component)
    s.fmi2ExitInitializationMode(s.component)


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

        runner.check_time(stop_time, step)
        runner.validate(fixed, list(outputs), inputs)
        self.runner = runner
        self.varied = list(varied)
        self.fixed = dict(fixed)
        self.inputs = dict(inputs or {})
        self.outputs = list(outputs)
        self.stop_time = float(stop_time)
        self.times = communication_points(self.stop_time, step)
        # a study parameter is a parameter, or an input held at its value (set before initialisation; an FMI
        # co-simulation or model exchange FMU keeps an input's value until it is set again)
        vs = [runner.lookup(n, VARIED, "parameter") for n in self.varied]
        for v in vs:
            if v.type != "Real":
                raise FMUError(f"study parameter {v.name!r} is a {v.type}; only Real parameters can be varied")
            if v.causality == "parameter" and v.variability not in ("fixed", "tunable"):
                raise FMUError(f"parameter {v.name!r} has variability {v.variability!r} and cannot be set")
        self._fixed_calls = self._prepared_sets(runner, self.fixed, ("parameter",), "parameter")
        self._input_calls = self._prepared_sets(runner, self.inputs, ("input",), "input")
        if runner.is_model_exchange:
            # fmpy's solver runs the FMU: start values by name, the same for every run but the varied ones
            self._base_values = {n: runner.coerce(runner.variables[n], x)
                                 for n, x in {**self.fixed, **self.inputs}.items()}
            for n in self.outputs:
                runner.lookup(n, READABLE, "output")
            return
        self._vr_varied = (fmi2ValueReference * len(vs))(*[v.valueReference for v in vs])
        self._val_varied = (fmi2Real * len(vs))()
        outs = [runner.lookup(n, _PLAN_READABLE, "output") for n in self.outputs]
        if all(o.type == "Real" for o in outs):
            self._vr_out = (fmi2ValueReference * len(outs))(*[o.valueReference for o in outs])
            self._val_out = (fmi2Real * len(outs))()
            self._read = self._read_real
        else:
            self._read = runner.reader(self.outputs)

    @staticmethod
    def _prepared_sets(runner: FMURunner, values: Mapping[str, Value], allowed, role) -> list:
        """(setter name, vr array, value array) per type, built once."""
        from fmpy.fmi2 import fmi2Boolean, fmi2Integer, fmi2Real, fmi2ValueReference

        groups = runner.by_type(values, allowed, role)
        ctype = {"Real": ("fmi2SetReal", fmi2Real), "Integer": ("fmi2SetInteger", fmi2Integer),
                 "Enumeration": ("fmi2SetInteger", fmi2Integer), "Boolean": ("fmi2SetBoolean", fmi2Boolean)}
        calls = []
        for typ, (vrs, vals) in groups.items():
            fn, ct = ctype[typ]
            calls.append((fn, (fmi2ValueReference * len(vrs))(*vrs), (ct * len(vals))(*vals)))
        return calls

    def start(self, values: Sequence[float]) -> None:
        """Reset the instance and take a co-simulation run up to the end of its initialisation, the varied
        parameters at ``values``: the first part of :meth:`__call__`, for timing the parts of a run (the
        caller steps ``instance.fmi2DoStep`` and calls :meth:`read`). Errors are the FMU's, unwrapped."""
        if self.runner.is_model_exchange:
            raise FMUError("start() prepares a co-simulation run; fmpy's solver runs a model exchange FMU whole")
        self.runner.ready()
        _initialise(self.runner, self._fixed_calls, self._vr_varied, self._val_varied, values,
                    self._input_calls, 0.0, self.stop_time)

    def read(self) -> list[float]:
        """The outputs at the instance's current time (co-simulation)."""
        return self._read()

    def _read_real(self) -> list[float]:
        s = self.runner.instance
        s.fmi2GetReal(s.component, self._vr_out, len(self._val_out), self._val_out)
        return list(self._val_out)

    def __call__(self, values: Sequence[float]) -> np.ndarray:
        r = self.runner
        if r.is_model_exchange:
            return self._call_me(values)
        r.ready()
        s = r.instance
        n = len(self.times)
        data = np.empty((n, len(self.outputs)))
        t = 0.0
        deadline, late = r.deadline, False   # a time limit: stop at the first communication point past it
        try:
            _initialise(r, self._fixed_calls, self._vr_varied, self._val_varied, values, self._input_calls,
                        0.0, self.stop_time)
            data[0] = self._read()
            for k in range(1, n):
                t_next = self.times[k]
                r.phase = f"in the communication step from t = {t:.10g} s to {t_next:.10g} s"
                s.fmi2DoStep(s.component, t, t_next - t, 1)
                t = t_next
                data[k] = self._read()
                if deadline is not None and k < n - 1 and time.monotonic() > deadline:
                    late = True
                    break
        except Exception as exc:
            raise r.fail(exc, {**self.fixed, **dict(zip(self.varied, values))}) from exc
        if late:
            raise r.reject(f"stopped at t = {t:.10g} s of {self.stop_time:.10g} s: past its time limit",
                           FMUTimeLimitError)
        r.mark_done()
        if not np.isfinite(data[-1]).all():
            params = dict(zip(self.varied, values))
            bad = [n for n, x in zip(self.outputs, data[-1]) if not math.isfinite(x)]
            raise r.reject(f"non-finite output {', '.join(bad)} at t = {t:.10g} s; parameters {params}")
        return data

    def _call_me(self, values: Sequence[float]) -> np.ndarray:
        """A model exchange run: fmpy's solver on the runner's reused instance."""
        r = self.runner
        params = dict(zip(self.varied, (float(x) for x in values)))
        data = r.run_me({**self._base_values, **params}, self.times, self.outputs, {**self.fixed, **params})
        if not np.all(np.isfinite(data[-1])):
            bad = [n for n, x in zip(self.outputs, data[-1]) if not math.isfinite(x)]
            raise r.reject(f"non-finite output {', '.join(bad)} at t = {self.times[-1]:.10g} s; "
                           f"parameters {params}")
        return data


class DrivenPlan:
    """Repeated runs of a co-simulation FMU driven by a sampled signal (the measured drive of a test).

    The drive is taken as piecewise linear between its samples: at each sample the input gets its value
    and, when the FMU can interpolate inputs, its slope on the coming interval
    (``fmi2SetRealInputDerivatives``), so the FMU integrates the signal the test imposed rather than a
    staircase. ``__call__(values, t, u)`` returns the outputs at every sample time, one row each.
    """

    def __init__(self, runner: FMURunner, varied: Sequence[str], fixed: Mapping[str, Value],
                 input_name: str, outputs: Sequence[str]) -> None:
        from fmpy.fmi2 import fmi2Integer, fmi2Real, fmi2ValueReference

        if runner.is_model_exchange:
            raise FMUError(f"{runner.fmu_path}: a drive from measured data needs a co-simulation FMU "
                           f"(this one offers model exchange only)")
        runner.validate(fixed, list(outputs), {input_name: 0.0})
        self.runner = runner
        self.varied = list(varied)
        self.fixed = dict(fixed)
        self.outputs = list(outputs)
        self.input_name = input_name
        vs = [runner.lookup(n, ("parameter",), "parameter") for n in self.varied]
        for v in vs:
            if v.type != "Real":
                raise FMUError(f"parameter {v.name!r} is a {v.type}; only Real parameters can be fitted")
        inp = runner.lookup(input_name, ("input",), "input")
        if inp.type != "Real":
            raise FMUError(f"input {input_name!r} is a {inp.type}; the drive must be a Real input")
        cs = runner.model_description.coSimulation
        self.interpolates = bool(getattr(cs, "canInterpolateInputs", False))
        self._fixed_calls = RunPlan._prepared_sets(runner, self.fixed, ("parameter",), "parameter")
        self._vr_varied = (fmi2ValueReference * len(vs))(*[v.valueReference for v in vs])
        self._val_varied = (fmi2Real * len(vs))()
        self._vr_in = (fmi2ValueReference * 1)(inp.valueReference)
        self._val_in = (fmi2Real * 1)()
        self._order = (fmi2Integer * 1)(1)
        outs = [runner.lookup(n, _PLAN_READABLE, "output") for n in self.outputs]
        if any(o.type != "Real" for o in outs):
            raise FMUError("driven runs read Real outputs only")
        self._vr_out = (fmi2ValueReference * len(outs))(*[o.valueReference for o in outs])
        self._val_out = (fmi2Real * len(outs))()

    def __call__(self, values: Sequence[float], t: np.ndarray, u: np.ndarray) -> np.ndarray:
        r = self.runner
        t = np.asarray(t, dtype=float)
        u = np.asarray(u, dtype=float)
        if t.ndim != 1 or t.shape != u.shape or len(t) < 2 or not np.all(np.diff(t) > 0):
            raise ValueError("the drive needs matching 1-D arrays t, u of at least 2 samples with t increasing")
        r.ready()
        s = r.instance
        params = dict(zip(self.varied, (float(x) for x in values)))
        slopes = np.diff(u) / np.diff(t)
        n_out = len(self.outputs)
        data = np.empty((len(t), n_out))
        vr_out, val_out, vr_in, val_in, order = self._vr_out, self._val_out, self._vr_in, self._val_in, self._order
        ti = float(t[0])
        k = 0
        try:
            val_in[0] = u[0]
            _initialise(r, self._fixed_calls, self._vr_varied, self._val_varied, values,
                        [("fmi2SetReal", vr_in, val_in)], ti, float(t[-1]))
            s.fmi2GetReal(s.component, vr_out, n_out, val_out)
            data[0] = val_out
            set_real, set_der, do_step, get_real = _step_calls(s)
            comp = s.component
            interpolates = self.interpolates
            for k in range(1, len(t)):
                val_in[0] = u[k - 1]
                st = set_real(comp, vr_in, 1, val_in)
                if st > 1:
                    raise FMICallException(function="fmi2SetReal", status=st)
                if interpolates:
                    val_in[0] = slopes[k - 1]
                    st = set_der(comp, vr_in, 1, order, val_in)
                    if st > 1:
                        raise FMICallException(function="fmi2SetRealInputDerivatives", status=st)
                t_next = float(t[k])
                st = do_step(comp, ti, t_next - ti, 1)
                if st > 1:
                    raise FMICallException(function="fmi2DoStep", status=st)
                ti = t_next
                st = get_real(comp, vr_out, n_out, val_out)
                if st > 1:
                    raise FMICallException(function="fmi2GetReal", status=st)
                data[k] = val_out
        except Exception as exc:
            if k:       # named here, not before every step: formatting it cost a tenth of a fast run
                r.phase = f"in the communication step from t = {t[k - 1]:.10g} s to {t[k]:.10g} s"
            raise r.fail(exc, {**self.fixed, **params}) from exc
        r.mark_done()
        if not np.all(np.isfinite(data)):
            raise r.reject(f"non-finite output with parameters {params}")
        return data




# ---------------------------------------------------------------------- the lean worker's plan
class _Declared:
    """What FMURunner's checks read (its variables and model description), without an instance: the
    lean plan is checked as a RunPlan is, in the parent, where no FMU is loaded."""
    lookup = FMURunner.lookup
    by_type = FMURunner.by_type
    validate = FMURunner.validate
    coerce = staticmethod(FMURunner.coerce)

    def __init__(self, info) -> None:
        self.variables = {v.name: v for v in info.variables}
        self.model_description = info.model_description


#: The types of the values a lean plan carries as they are (plain data: a worker unpickles no numpy).
_PLAIN = (float, int, bool, str)


def lean_plan(fmu_dir: str, info, varied: Sequence[str], fixed: Sequence[tuple[str, Value]],
              inputs: Sequence[tuple[str, float]], outputs: Sequence[str], stop_time: float, step: float | None,
              *, interface: str = "auto", solver: str | None = None, relative_tolerance: float | None = None,
              step_size: float | None = None, reuse: str = "reset", keep: Sequence[int] | None = None
              ) -> dict | None:
    """The plain data :class:`fmusa.fmi.lean.LeanFMU` needs to make a RunPlan's runs of the FMU unpacked in
    ``fmu_dir`` (``info``: its FMUInfo) without fmpy or numpy, or None when the lean path does not cover
    them: anything but an FMI 2.0 co-simulation FMU with its binary for this platform in place, an output
    that is not a Real, a value not of a plain type, or a set-up FMURunner or RunPlan would refuse (they run
    then, and say why). ``keep``: the communication points whose rows a run sends back (None: all)."""
    import inspect

    import fmpy
    from fmpy.fmi2 import FMU2Slave

    from fmusa.fmi.info import select_interface
    from fmusa.fmi.runner import REUSE_MODES, experiment_tolerance

    try:
        if info.is_fmi3 or select_interface(info, interface) != "co-simulation":
            return None
        if solver is not None or step_size is not None or reuse not in REUSE_MODES:
            return None
        if relative_tolerance is not None and not (math.isfinite(relative_tolerance) and relative_tolerance > 0):
            return None
        folder = Path(fmu_dir)
        model_id = info.interfaces["co-simulation"]
        library = folder / "binaries" / fmpy.platform / (model_id + fmpy.sharedLibraryExtension)
        if not (folder.is_absolute() and folder.is_dir() and library.is_file()):
            return None
        if any(type(x) not in _PLAIN for _, x in fixed) or any(type(x) not in _PLAIN for _, x in inputs):
            return None
        d = _Declared(info)
        FMURunner.check_time(stop_time, step)
        fixed_d, inputs_d = dict(fixed), dict(inputs)
        d.validate(fixed_d, list(outputs), inputs_d)
        vs = [d.lookup(n, VARIED, "parameter") for n in varied]
        if any(v.type != "Real" or (v.causality == "parameter" and v.variability not in ("fixed", "tunable"))
               for v in vs):
            return None
        outs = [d.lookup(n, _PLAN_READABLE, "output") for n in outputs]
        if any(o.type != "Real" for o in outs):
            return None
        calls = []
        for values, allowed, role in ((fixed_d, ("parameter",), "parameter"), (inputs_d, ("input",), "input")):
            groups = d.by_type(values, allowed, role)
            if any(t not in ("Real", "Integer", "Enumeration", "Boolean") for t in groups):
                return None
            calls.append([("Integer" if t == "Enumeration" else t, list(vrs),
                           [bool(x) if t == "Boolean" else x for x in vals]) for t, (vrs, vals) in groups.items()])
    except Exception:  # noqa: BLE001 - whatever the checks refuse: the fmpy path runs, and says why
        return None
    md = info.model_description
    tol = relative_tolerance if relative_tolerance is not None else experiment_tolerance(md)
    cats = [c.name for c in getattr(md, "logCategories", [])]
    proxy = Path(fmpy.__file__).parent / "logging" / fmpy.platform / ("logging" + fmpy.sharedLibraryExtension)
    times = communication_points(float(stop_time), step)
    return {
        "library": str(library),
        "required": sorted(n for n, _ in inspect.getmembers(FMU2Slave) if n.startswith("fmi2")),
        "logger_proxy": str(proxy),
        "model_name": str(md.modelName),
        "instance_name": "fmusa",
        "guid": str(md.guid),
        "resource_uri": Path(fmu_dir, "resources").as_uri(),     # fmpy's; fmu_dir is absolute
        "tolerance": None if tol is None else float(tol),
        "debug_logging": [c for c in cats if c in ("logStatusError", "logStatusWarning")],
        "reuse": reuse,
        "varied": list(varied),
        "varied_vrs": [int(v.valueReference) for v in vs],
        "fixed": [(k, x) for k, x in fixed],
        "fixed_calls": calls[0],
        "input_calls": calls[1],
        "outputs": list(outputs),
        "output_vrs": [int(o.valueReference) for o in outs],
        "times": times.tolist(),
        "keep": None if keep is None else [int(i) for i in keep],
    }
