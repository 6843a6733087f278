"""The coupling master: a user's FMU and the interface element FMU run as one system.

The model gives the interface's relative displacement ``s`` and its rate ``v`` (outputs); the element turns
them into the force or torque ``F`` it carries; the model takes ``force_sign * F`` at its force input (added to
the drive when the drive uses the same input). Interfaces are stiff (8.2e5 N/m on a 0.29 g screw: 5e4 rad/s),
so an explicit exchange at a fixed step goes unstable or wrong without a sound. Four schemes, chosen by what
the model's FMU can do (``auto``: the first that applies):

- ``me-grid``: both FMUs as model exchange, their states one ODE integrated by fixed-step Radau IIA that lands
  on every output time (:mod:`fmusa.cosim.grid`: RADAU5's error estimate against ``rtol`` at every step, a
  failing step cut in two, one Jacobian reused); time events end a segment. For FMUs without event indicators
  (state events need the next scheme). The hot path calls the FMUs through ctypes directly.
- ``me-implicit``: both FMUs as model exchange, their states one ODE integrated implicitly (scipy's Radau,
  error controlled on every state); inputs set before each derivative call; step ends, time events and
  state events (event indicators, located on the dense output) handled as FMI 2.0 asks.
- ``cs-iterate``: co-simulation where the model can get and set its state: each macro step is repeated from
  the saved states until the exchanged force converges (secant iteration on the interface residual: a
  converged step is the implicit coupling, stable at any stiffness), then the whole run is repeated at half
  the step and the two compared.
- ``cs-halving``: co-simulation without state rollback: an explicit exchange (the model steps with the last
  force, the element with the model's new motion), the run repeated at half the step until two runs agree
  within ``coupling_tol``; a run that does not converge within ``max_halvings`` raises :class:`CouplingError`
  (or warns with ``strict=False``, and the result says ``converged=False``).

The result says which scheme ran, how many FMU calls it made and the wall and CPU time (all runs of the
verification included).
"""
from __future__ import annotations

import math
import os
import shutil
import threading
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import pandas as pd

from fmusa.errors import FmusaError
from fmusa.fmi.info import FMUError, FMUNotFoundError, read_fmu_info, variable_problem

ELEMENT_NAME = "InterfaceElement.fmu"
ENV_ELEMENT = "FMUSA_ELEMENT_FMU"
#: The element FMU's interface: inputs (displacement, rate), output (force or torque).
ELEMENT_S, ELEMENT_V, ELEMENT_F = "s", "v", "F"
SCHEMES = ("auto", "me-grid", "me-implicit", "cs-iterate", "cs-halving")


class CouplingError(FmusaError, RuntimeError):
    """A coupled run that cannot be made or did not converge: the message names the variable, the FMU or the
    measured disagreement.

    Fix: export the variable the message names with the causality it asks for (the interface force as an
    input, the displacement and its rate as outputs); when the run did not converge, export the model with
    Model Exchange or with canGetAndSetFMUstate, or give a smaller first step.
    """

    exit_code = 1


class CouplingTimeLimitError(CouplingError):
    """A coupled run stopped at its time limit (``max_wall_s``).

    Fix: raise ``max_wall_s``, or make the run cheaper (a Model Exchange export, a smaller first step for the
    co-simulation schemes).
    """


def default_element_fmu() -> Path:
    """The interface element FMU: ``$FMUSA_ELEMENT_FMU``, else ``dist/InterfaceElement.fmu`` under the
    current directory or a directory above this file (built by ``make fmu``)."""
    env = os.environ.get(ENV_ELEMENT)
    if env:
        path = Path(env).expanduser().resolve()
        if not path.exists():
            raise FMUNotFoundError(f"${ENV_ELEMENT} is set to {env}, which does not exist; point it at the "
                                   f"element FMU, or unset it to use dist/{ELEMENT_NAME} (`make fmu`)")
        return path
    for base in [Path.cwd(), *Path(__file__).resolve().parents]:
        candidate = base / "dist" / ELEMENT_NAME
        if candidate.is_file():
            return candidate
    raise FMUNotFoundError(f"the interface element FMU dist/{ELEMENT_NAME} is missing: build it with `make fmu` "
                           f"in the fmusa repository, or set {ENV_ELEMENT} to its path")


@dataclass(frozen=True)
class Coupling:
    """A coupled system, as data: which model, which element, and which variables meet at the interface."""
    model_fmu: Path                  # the user's FMU
    element_fmu: Path | None = None  # ours (None: default_element_fmu())
    force_input: str = ""            # model input that takes the interface force/torque
    displacement_output: str = ""    # model output: the interface's relative displacement/angle
    velocity_output: str = ""        # model output (or state): its rate
    force_sign: float = -1.0         # model input = force_sign * element F (+ the drive on the same input)
    scheme: str = "auto"             # "auto" | "me-implicit" | "cs-iterate" | "cs-halving"
    velocity_sign: float = 1.0       # rate = velocity_sign * velocity_output (an export whose rate variable
                                     # counts the other way round)

    def element(self) -> Path:
        return Path(self.element_fmu) if self.element_fmu is not None else default_element_fmu()


@dataclass
class CoupledResult:
    """A coupled run: the outputs at the output times, the scheme that ran and what it cost."""
    frame: pd.DataFrame              # time, the outputs asked for, and 'F' (the element's force/torque)
    scheme: str
    calls: int                       # FMU function calls, both FMUs, every run of the verification
    wall_s: float
    cpu_s: float
    step: float | None = None        # the macro step of the accepted run (CS schemes)
    runs: int = 1                    # coupled runs made (the halving verification repeats them)
    converged: bool = True
    difference: float | None = None  # CS schemes: relative difference between the last two runs
    iterations: int = 0              # cs-iterate: force iterations in all, accepted run
    notes: list[str] = field(default_factory=list)


# ---------------------------------------------------------------------------------------------- checks

def _capabilities(info) -> dict:
    md = info.model_description
    cs, me = md.coSimulation, md.modelExchange
    return dict(cs=cs is not None, me=me is not None,
                cs_state=bool(cs is not None and cs.canGetAndSetFMUstate),
                cs_interp=bool(cs is not None and cs.canInterpolateInputs))


def _runnable(info, interface: str) -> bool:
    from fmusa.fmi.info import binary_problem
    return interface in info.interfaces and binary_problem(info, interface) is None


def choose_scheme(model_info, element_info, requested: str = "auto") -> str:
    """The scheme a coupling runs: ``requested``, or the first of me-implicit, cs-iterate, cs-halving that
    both FMUs support. Raises :class:`CouplingError` naming what is missing."""
    if requested not in SCHEMES:
        raise CouplingError(f"unknown coupling scheme {requested!r}; use one of {', '.join(SCHEMES)}")
    m = _capabilities(model_info)
    e = _capabilities(element_info)
    me = _runnable(model_info, "model-exchange") and _runnable(element_info, "model-exchange")
    no_indicators = me and not (model_info.model_description.numberOfEventIndicators
                                or element_info.model_description.numberOfEventIndicators)
    can = {"me-grid": no_indicators, "me-implicit": me,
           "cs-iterate": _runnable(model_info, "co-simulation") and m["cs_state"]
           and _runnable(element_info, "co-simulation") and e["cs_state"],
           "cs-halving": _runnable(model_info, "co-simulation") and _runnable(element_info, "co-simulation")}
    if requested == "auto":
        for s in SCHEMES[1:]:
            if can[s]:
                return s
        raise CouplingError(f"{model_info.path}: {model_info.model_name} can be coupled neither as model exchange "
                            f"nor as co-simulation on this machine (no binary for this platform and no sources); "
                            f"export it with a binary for this platform")
    if not can[requested]:
        why = {"me-grid": "both FMUs need a model exchange interface with a binary (or sources) for this platform "
                          "and no event indicators (state events need me-implicit, which locates them)",
               "me-implicit": "both FMUs need a model exchange interface with a binary (or sources) for this "
                              "platform; export the model with Model Exchange",
               "cs-iterate": "both FMUs need co-simulation with canGetAndSetFMUstate = true; export the model "
                             "with FMU state support (Dymola: 'Include code for getting/setting the FMU state'),"
                             " or use me-implicit or cs-halving",
               "cs-halving": "both FMUs need co-simulation with a binary (or sources) for this platform"}[requested]
        raise CouplingError(f"scheme {requested} cannot run with {model_info.model_name}: {why}")
    return requested


def check_coupling(coupling: Coupling) -> None:
    """Before any run: both FMUs can be read, the model's force input is an input, its displacement and
    rate are readable (an output, or a state the tool exported), the element is the element, and a scheme
    applies. Raises :class:`CouplingError` naming what is missing and how to export it."""
    checked_coupling(coupling)


def checked_coupling(coupling: Coupling):
    """:func:`check_coupling`, returning what it read: (the model's FMUInfo, the element's, the scheme)."""
    try:
        minfo = read_fmu_info(coupling.model_fmu)
        einfo = read_fmu_info(coupling.element())
    except FMUError as exc:
        raise CouplingError(str(exc)) from exc
    if minfo.is_fmi3:
        raise CouplingError(f"{coupling.model_fmu}: the coupling master runs FMI 2.0 FMUs; export "
                            f"{minfo.model_name} as FMI 2.0")
    problems = []
    export = ("export the model with the interface {what} as {kind} (Dymola: a RealInput/RealOutput connector at "
              "the top level; OpenModelica: a top-level input/output; Simpack: an u-/y-vector entry)")
    for name, role, what in ((coupling.force_input, "input", "force or torque"),
                             (coupling.displacement_output, "output", "relative displacement or angle")):
        if not name:
            problems.append(f"no {role} named for the interface {what}")
            continue
        p = variable_problem(minfo, name, role)
        if p:
            problems.append(f"{p}; {export.format(what=what, kind=f'an {role}')}")
    v = minfo.variable(coupling.velocity_output) if coupling.velocity_output else None
    if not coupling.velocity_output:
        problems.append("no variable named for the interface's rate (velocity_output)")
    elif v is None:
        p = variable_problem(minfo, coupling.velocity_output, "output")
        problems.append(f"{p}; {export.format(what='rate', kind='an output')} (a state the tool exports, "
                        f"such as damper.v_rel, also works)")
    elif v.causality not in ("output", "local") or v.type != "Real":
        problems.append(f"{coupling.velocity_output!r} is {v.causality or 'local'} {v.type}: the interface's "
                        f"rate must be a Real output or a state")
    for name, role in ((ELEMENT_S, "input"), (ELEMENT_V, "input"), (ELEMENT_F, "output")):
        p = variable_problem(einfo, name, role)
        if p:
            problems.append(f"element FMU {coupling.element()}: {p}; it must be the interface element "
                            f"(dist/{ELEMENT_NAME}, `make fmu`)")
    if not math.isfinite(coupling.force_sign) or coupling.force_sign == 0:
        problems.append(f"force_sign = {coupling.force_sign}: use -1 (the input pushes the model the way "
                        f"positive s goes) or +1")
    if problems:
        raise CouplingError(f"{coupling.model_fmu}: cannot couple {minfo.model_name} with the element: "
                            + "; ".join(problems))
    scheme = choose_scheme(minfo, einfo, coupling.scheme)
    return minfo, einfo, scheme


# ---------------------------------------------------------------------------------------------- FMUs

_UNPACKED: dict[tuple, Path] = {}
_UNPACK_ROOT: list[Path] = []
_UNPACK_LOCK = threading.Lock()


def _unpacked(info, interface: str, fresh: bool = False) -> Path:
    """The FMU unpacked (built from its sources where it has no binary for this platform) for running, once per
    process and version of the file: a coupled run makes fresh instances every time, and a fresh copy of the
    binary per run costs time and leaves every copy loaded in the process. ``fresh``: a new copy all the same,
    for a binary whose instances share state through the loaded library. Removed when the process ends."""
    import atexit
    import tempfile

    from fmusa.fmi.archive import extract_fmu
    from fmusa.fmi.build import prepare_fmu

    src = Path(info.path).resolve()
    st = src.stat()
    key = (str(src), st.st_mtime_ns, st.st_size, interface)
    with _UNPACK_LOCK:
        hit = _UNPACKED.get(key)
        if hit is not None and hit.exists() and not fresh:
            return hit
        if not _UNPACK_ROOT:
            root = Path(tempfile.mkdtemp(prefix="fmusa-cosim-"))
            atexit.register(shutil.rmtree, root, True)
            _UNPACK_ROOT.append(root)
        work = Path(tempfile.mkdtemp(dir=_UNPACK_ROOT[0]))
        path = prepare_fmu(info.path, interface, work)
        unzip = Path(path) if Path(path).is_dir() else Path(extract_fmu(path, work / "unpacked", to_run=True))
        if not fresh:
            _UNPACKED[key] = unzip
            _hold_loaded(unzip, info.interfaces.get(interface, ""))
        return unzip


_HELD: list = []


def _hold_loaded(unzip: Path, identifier: str) -> None:
    """Keep the unpacked binary loaded for the rest of the process. fmpy unloads a binary when its instance is
    freed, and a coupled run frees its instances: a binary that makes a thread-local key each time it is loaded
    and never deletes it (OpenModelica's runtime does: pthread_key_create) runs out of keys after about a
    thousand runs and then writes into another library's slot (measured: the interpreter's own, a segfault).
    Loaded once and kept, its initialisation runs once."""
    import ctypes

    from fmpy import platform, sharedLibraryExtension

    lib = Path(unzip) / "binaries" / platform / f"{identifier}{sharedLibraryExtension}"
    if identifier and lib.is_file():
        try:
            _HELD.append(ctypes.CDLL(str(lib)))
        except OSError:       # fmpy will say why it cannot load it
            pass


class _Fmu:
    """One FMI 2.0 instance (ME or CS) through fmpy, counting the calls made to it."""

    def __init__(self, info, interface: str, name: str, fresh: bool = False) -> None:
        from fmpy.fmi2 import FMU2Model, FMU2Slave

        unzip = _unpacked(info, interface, fresh)
        md = info.model_description
        cls = FMU2Model if interface == "model-exchange" else FMU2Slave
        self.fmu = cls(guid=md.guid, unzipDirectory=str(unzip), modelIdentifier=info.interfaces[interface],
                       instanceName=name)
        self.info = info
        self.name = name
        self.calls = 0
        self.vars = {v.name: v for v in md.modelVariables}
        self.nx = md.numberOfContinuousStates if interface == "model-exchange" else 0
        self.nz = md.numberOfEventIndicators if interface == "model-exchange" else 0
        self.fmu.instantiate()
        self.calls += 1
        self.instantiated = True

    def call(self, fn: str, *args):
        self.calls += 1
        try:
            return getattr(self.fmu, fn)(*args)
        except Exception as exc:  # fmpy raises on an error status: say which FMU and call
            raise CouplingError(f"{self.info.model_name} ({self.name}): {fn} failed: {exc}") from exc

    def vr(self, names: Sequence[str]) -> list[int]:
        return [self.vars[n].valueReference for n in names]

    def set_values(self, values: dict) -> None:
        by_type: dict[str, tuple[list, list]] = {}
        for n, x in values.items():
            v = self.vars.get(n)
            if v is None:
                raise CouplingError(f"{self.info.model_name} has no variable {n!r}")
            vrs, xs = by_type.setdefault(v.type, ([], []))
            vrs.append(v.valueReference)
            xs.append(x)
        for t, (vrs, xs) in by_type.items():
            if t == "Real":
                self.call("setReal", vrs, [float(x) for x in xs])
            elif t in ("Integer", "Enumeration"):
                self.call("setInteger", vrs, [int(x) for x in xs])
            elif t == "Boolean":
                self.call("setBoolean", vrs, [bool(x) for x in xs])
            else:
                raise CouplingError(f"{self.info.model_name}: cannot set {t} variables")

    def real(self, vrs: list[int]) -> list[float]:
        return self.call("getReal", vrs)

    def free(self) -> None:
        if self.instantiated:
            try:
                self.fmu.terminate()
            except Exception:
                pass
            try:
                self.fmu.freeInstance()
            except Exception:
                pass
            self.instantiated = False


class _Direct:
    """The FMI functions of the model exchange hot path called straight through ctypes, with buffers made once:
    fmpy's wrappers build new arrays and look the function up on every call, which is most of a coupled run's
    time. Counts its calls into the FMU's count; an error status raises :class:`CouplingError`."""

    def __init__(self, fmu: _Fmu) -> None:
        from ctypes import POINTER, c_double, c_int, c_size_t, c_uint, c_void_p

        self.fmu = fmu
        self.component = fmu.fmu.component
        dll = fmu.fmu.dll
        pd_, pu = POINTER(c_double), POINTER(c_uint)
        sig = {"fmi2SetTime": [c_void_p, c_double], "fmi2SetContinuousStates": [c_void_p, pd_, c_size_t],
               "fmi2GetDerivatives": [c_void_p, pd_, c_size_t], "fmi2GetReal": [c_void_p, pu, c_size_t, pd_],
               "fmi2SetReal": [c_void_p, pu, c_size_t, pd_]}
        self.fn = {}
        for name, argtypes in sig.items():
            f = dll[name]            # a new function object: fmpy's own keeps its settings
            f.argtypes, f.restype = argtypes, c_int
            self.fn[name] = f
        n = max(fmu.nx, 1)
        self.x, self.dx = (c_double * n)(), (c_double * n)()
        self.x_np = np.frombuffer(self.x, dtype=float)
        self.dx_np = np.frombuffer(self.dx, dtype=float)
        self._c_double, self._c_uint = c_double, c_uint

    def _check(self, name: str, status: int) -> None:
        if status > 1:   # fmi2Warning is fine, fmi2Discard and worse are not
            raise CouplingError(f"{self.fmu.info.model_name} ({self.fmu.name}): {name} returned status {status}")

    def refs(self, vrs: Sequence[int]):
        """A value-reference buffer and a value buffer for get_real/set_real."""
        return (self._c_uint * len(vrs))(*vrs), (self._c_double * len(vrs))()

    def set_time(self, t: float) -> None:
        self.fmu.calls += 1
        self._check("fmi2SetTime", self.fn["fmi2SetTime"](self.component, t))

    def set_states(self, x: np.ndarray) -> None:
        self.fmu.calls += 1
        self.x_np[:x.size] = x
        self._check("fmi2SetContinuousStates", self.fn["fmi2SetContinuousStates"](self.component, self.x, x.size))

    def derivatives(self, out: np.ndarray) -> None:
        self.fmu.calls += 1
        n = out.size
        self._check("fmi2GetDerivatives", self.fn["fmi2GetDerivatives"](self.component, self.dx, n))
        out[:] = self.dx_np[:n]

    def get_real(self, buffers) -> None:
        vr, val = buffers
        self.fmu.calls += 1
        self._check("fmi2GetReal", self.fn["fmi2GetReal"](self.component, vr, len(vr), val))

    def set_real(self, buffers) -> None:
        vr, val = buffers
        self.fmu.calls += 1
        self._check("fmi2SetReal", self.fn["fmi2SetReal"](self.component, vr, len(vr), val))


def _check_outputs(outputs: Sequence[str], model: _Fmu, element: _Fmu) -> list[tuple[str, _Fmu, int]]:
    """Where each requested output is read: the model's variable, or the element's as ``element.NAME``."""
    out = []
    for name in outputs:
        if name in model.vars:
            out.append((name, model, model.vars[name].valueReference))
        elif name.startswith("element.") and name[8:] in element.vars:
            out.append((name, element, element.vars[name[8:]].valueReference))
        else:
            raise CouplingError(f"output {name!r} is neither a variable of {model.info.model_name} nor an "
                                f"element variable (write element.NAME, e.g. element.F_fric)")
    return out


class _Interface:
    """The variables that meet at the interface, as value references."""

    def __init__(self, coupling: Coupling, model: _Fmu, element: _Fmu) -> None:
        self.c = coupling
        self.f = model.vars[coupling.force_input].valueReference
        self.s = model.vars[coupling.displacement_output].valueReference
        self.v = model.vars[coupling.velocity_output].valueReference
        self.es, self.ev, self.eF = element.vr([ELEMENT_S, ELEMENT_V, ELEMENT_F])


def _drive(model_inputs, t: float, force_input: str) -> tuple[dict, float]:
    """The drive at t: the model's other inputs, and the part of the force input the drive itself gives."""
    if model_inputs is None:
        return {}, 0.0
    u = dict(model_inputs(t))
    return u, float(u.pop(force_input, 0.0))


def _start(fmu: _Fmu, params: dict, rtol: float, stop_time: float, inputs: dict) -> None:
    fmu.call("setupExperiment", rtol, 0.0, stop_time)
    fmu.set_values(params)
    fmu.call("enterInitializationMode")
    if inputs:
        fmu.set_values(inputs)
    fmu.call("exitInitializationMode")


# ---------------------------------------------------------------------------------------------- ME

def _event_iteration(fmu: _Fmu) -> float:
    """fmi2NewDiscreteStates until no new step is needed; the next time event (inf: none)."""
    for _ in range(1000):
        need, term, _, _, next_def, next_t = fmu.call("newDiscreteStates")
        if term:
            raise CouplingError(f"{fmu.info.model_name} asked to terminate the simulation during an event")
        if not need:
            return next_t if next_def else math.inf
    raise CouplingError(f"{fmu.info.model_name}: the event iteration did not end after 1000 iterations")


def _over_time(deadline: float | None, t: float) -> None:
    """Raise when a coupled run has used its time limit (max_wall_s of simulate_coupled)."""
    if deadline is not None and time.perf_counter() > deadline:
        raise CouplingTimeLimitError(f"the coupled run passed its time limit (max_wall_s) at t = {t:.9g}; "
                                     f"raise max_wall_s, or give the CS schemes a smaller first step")


def _run_me(coupling, minfo, einfo, model_params, element_params, stop_time, output_times, outputs, model_inputs,
            rtol, deadline: float | None = None, fresh: bool = False) -> tuple[pd.DataFrame, int, dict]:
    from ctypes import c_double
    from scipy.integrate import Radau

    m = _Fmu(minfo, "model-exchange", "model", fresh)
    e = _Fmu(einfo, "model-exchange", "element", fresh)
    try:
        itf = _Interface(coupling, m, e)
        where = _check_outputs(outputs, m, e)
        u0, f0 = _drive(model_inputs, 0.0, coupling.force_input)
        _start(m, model_params, rtol, stop_time, {**u0, coupling.force_input: f0})
        _start(e, element_params, rtol, stop_time, {})
        t_ev = min(_event_iteration(m), _event_iteration(e))
        m.call("enterContinuousTimeMode")
        e.call("enterContinuousTimeMode")
        nm, ne = m.nx, e.nx
        n = nm + ne
        xm, xe, dm, de = (c_double * max(nm, 1))(), (c_double * max(ne, 1))(), (c_double * max(nm, 1))(), \
            (c_double * max(ne, 1))()
        zm, ze = (c_double * max(m.nz, 1))(), (c_double * max(e.nz, 1))()

        def evaluate(t: float, x: np.ndarray) -> float:
            """Both FMUs at (t, x), the interface closed; returns F."""
            m.call("setTime", t)
            e.call("setTime", t)
            if nm:
                xm[:nm] = x[:nm]
                m.call("setContinuousStates", xm, nm)
            if ne:
                xe[:ne] = x[nm:]
                e.call("setContinuousStates", xe, ne)
            u, fd = _drive(model_inputs, t, coupling.force_input)
            if u:
                m.set_values(u)
            s, v = m.real([itf.s, itf.v])
            e.call("setReal", [itf.es, itf.ev], [s, coupling.velocity_sign * v])
            F = e.real([itf.eF])[0]
            m.call("setReal", [itf.f], [fd + coupling.force_sign * F])
            return F

        def rhs(t, x):
            evaluate(t, x)
            out = np.empty(n)
            if nm:
                m.call("getDerivatives", dm, nm)
                out[:nm] = dm[:nm]
            if ne:
                e.call("getDerivatives", de, ne)
                out[nm:] = de[:ne]
            if not np.all(np.isfinite(out)):
                raise CouplingError(f"the coupled derivatives are not finite at t = {t:.9g}")
            return out

        def states() -> np.ndarray:
            x = np.empty(n)
            if nm:
                m.call("getContinuousStates", xm, nm)
                x[:nm] = xm[:nm]
            if ne:
                e.call("getContinuousStates", xe, ne)
                x[nm:] = xe[:ne]
            return x

        def indicators(t, x) -> np.ndarray:
            evaluate(t, x)
            z = []
            if m.nz:
                m.call("getEventIndicators", zm, m.nz)
                z += list(zm[:m.nz])
            if e.nz:
                e.call("getEventIndicators", ze, e.nz)
                z += list(ze[:e.nz])
            return np.array(z)

        rows: list[list[float]] = []
        times = np.asarray(output_times, dtype=float)
        k = 0

        def record(t_hi: float, interp) -> None:
            nonlocal k
            while k < len(times) and times[k] <= t_hi + 1e-12 * max(1.0, abs(t_hi)):
                x = interp(times[k])
                F = evaluate(times[k], x)
                rows.append([times[k]] + [fmu.real([vr])[0] for _, fmu, vr in where] + [F])
                k += 1

        def event_mode() -> float:
            m.call("enterEventMode")
            e.call("enterEventMode")
            nxt = min(_event_iteration(m), _event_iteration(e))
            m.call("enterContinuousTimeMode")
            e.call("enterContinuousTimeMode")
            return nxt

        x = states()
        t = 0.0
        record(0.0, lambda _t: x)
        scale = np.maximum(np.abs(x), 1.0)
        atol = rtol * 1e-3 * scale
        steps = 0
        while t < stop_time * (1 - 1e-14):
            t_bound = min(stop_time, t_ev)
            solver = Radau(rhs, t, x, t_bound, rtol=rtol, atol=atol)
            z_old = indicators(t, x) if (m.nz or e.nz) else None
            event_at = None
            while solver.status == "running":
                msg = solver.step()
                steps += 1
                _over_time(deadline, solver.t)
                if solver.status == "failed":
                    raise CouplingError(f"the implicit integration of the coupled system failed at t = "
                                        f"{solver.t:.9g}: {msg}")
                dense = solver.dense_output()
                t_lo, t_hi = solver.t_old, solver.t
                if z_old is not None:
                    z_new = indicators(t_hi, solver.y)
                    crossed = np.sign(z_new) != np.sign(z_old)
                    if np.any(crossed):
                        a, b = t_lo, t_hi
                        for _ in range(60):   # bisection on the dense output: the first indicator to cross
                            mid = 0.5 * (a + b)
                            zc = indicators(mid, dense(mid))
                            if np.any(np.sign(zc[crossed]) != np.sign(z_old[crossed])):
                                b = mid
                            else:
                                a = mid
                        event_at = b
                        record(b, dense)
                        x = dense(b)
                        t = b
                        break
                    z_old = z_new
                record(t_hi, dense)
                evaluate(t_hi, solver.y)
                step_m = m.call("completedIntegratorStep", 1)
                step_e = e.call("completedIntegratorStep", 1)
                if step_m[1] or step_e[1]:
                    raise CouplingError(f"an FMU asked to terminate the simulation at t = {t_hi:.9g}")
                if step_m[0] or step_e[0]:
                    event_at = t_hi
                    x, t = solver.y.copy(), t_hi
                    break
                x, t = solver.y.copy(), t_hi
            if event_at is not None or (t >= t_ev * (1 - 1e-14) and math.isfinite(t_ev)):
                evaluate(t, x)
                t_next = event_mode()
                x = states()
                t_ev = t_next if t_next > t else math.inf
        record(stop_time, lambda _t: x)
        cols = ["time", *outputs, "F"]
        frame = pd.DataFrame(rows, columns=cols)
        return frame, m.calls + e.calls, {"steps": steps}
    finally:
        m.free()
        e.free()


def _run_me_grid(coupling, minfo, einfo, model_params, element_params, stop_time, output_times, outputs,
                 model_inputs, rtol, deadline: float | None = None,
                 fresh: bool = False) -> tuple[pd.DataFrame, int, dict]:
    """Both FMUs as model exchange, their states one ODE integrated by fixed-step Radau IIA on the output grid
    (:mod:`fmusa.cosim.grid`); time events end a segment; no event indicators (:func:`choose_scheme`)."""
    from fmusa.cosim.grid import integrate_on_grid

    m = _Fmu(minfo, "model-exchange", "model", fresh)
    e = _Fmu(einfo, "model-exchange", "element", fresh)
    try:
        itf = _Interface(coupling, m, e)
        where = _check_outputs(outputs, m, e)
        u0, f0 = _drive(model_inputs, 0.0, coupling.force_input)
        _start(m, model_params, rtol, stop_time, {**u0, coupling.force_input: f0})
        _start(e, element_params, rtol, stop_time, {})
        t_ev = min(_event_iteration(m), _event_iteration(e))
        m.call("enterContinuousTimeMode")
        e.call("enterContinuousTimeMode")
        dm, de = _Direct(m), _Direct(e)
        nm, ne = m.nx, e.nx
        n = nm + ne
        motion, element_in, element_out = dm.refs([itf.s, itf.v]), de.refs([itf.es, itf.ev]), de.refs([itf.eF])
        force = dm.refs([itf.f])
        drive_refs: dict[tuple, tuple] = {}
        reads = [(name, dm if fmu is m else de, (dm if fmu is m else de).refs([vr])) for name, fmu, vr in where]
        sv, fs = coupling.velocity_sign, coupling.force_sign
        out = np.empty(n)
        last = {"F": 0.0}

        # the hot path: raw ctypes functions and buffers bound to locals, the calls counted per evaluation
        cm, ce = dm.component, de.component
        m_time, e_time = dm.fn["fmi2SetTime"], de.fn["fmi2SetTime"]
        m_states, e_states = dm.fn["fmi2SetContinuousStates"], de.fn["fmi2SetContinuousStates"]
        m_get, m_set, e_get, e_set = dm.fn["fmi2GetReal"], dm.fn["fmi2SetReal"], de.fn["fmi2GetReal"], de.fn["fmi2SetReal"]
        m_der, e_der = dm.fn["fmi2GetDerivatives"], de.fn["fmi2GetDerivatives"]
        (mo_vr, mo_val), (ei_vr, ei_val) = motion, element_in
        (eo_vr, eo_val), (f_vr, f_val) = element_out, force
        xm_np, xe_np, dxm_np, dxe_np = dm.x_np[:nm], de.x_np[:ne], dm.dx_np[:nm], de.dx_np[:ne]
        per_eval_m, per_eval_e = 4 + bool(nm), 3 + bool(ne)

        def fail(what: str, t: float) -> None:
            raise CouplingError(f"{what} returned an error status at t = {t:.9g} in the coupled run")

        def evaluate(t: float, x: np.ndarray) -> None:
            """Both FMUs at (t, x), the interface closed."""
            st = m_time(cm, t) | e_time(ce, t)
            if nm:
                xm_np[:] = x[:nm]
                st |= m_states(cm, dm.x, nm)
            if ne:
                xe_np[:] = x[nm:]
                st |= e_states(ce, de.x, ne)
            u, fd = _drive(model_inputs, t, coupling.force_input)
            if u:
                key = tuple(u)
                if key not in drive_refs:
                    drive_refs[key] = dm.refs(m.vr(list(u)))
                vr, val = drive_refs[key]
                val[:] = [float(u[k]) for k in key]
                st |= m_set(cm, vr, len(vr), val)
                m.calls += 1
            st |= m_get(cm, mo_vr, 2, mo_val)
            ei_val[0], ei_val[1] = mo_val[0], sv * mo_val[1]
            st |= e_set(ce, ei_vr, 2, ei_val)
            st |= e_get(ce, eo_vr, 1, eo_val)
            F = eo_val[0]
            f_val[0] = fd + fs * F
            st |= m_set(cm, f_vr, 1, f_val)
            m.calls += per_eval_m - 1
            e.calls += per_eval_e - 1
            if st > 1:     # fmi2Warning (1) is fine; any worse status is named by the slow path
                fail("an FMU", t)
            last["F"] = F

        def rhs(t: float, x: np.ndarray) -> np.ndarray:
            evaluate(t, x)
            st = 0
            if nm:
                st |= m_der(cm, dm.dx, nm)
                out[:nm] = dxm_np
            if ne:
                st |= e_der(ce, de.dx, ne)
                out[nm:] = dxe_np
            m.calls += bool(nm)
            e.calls += bool(ne)
            if st > 1:
                fail("fmi2GetDerivatives", t)
            if not np.all(np.isfinite(out)):
                raise CouplingError(f"the coupled derivatives are not finite at t = {t:.9g}")
            return out.copy()

        def states() -> np.ndarray:
            from ctypes import c_double
            x = np.empty(n)
            for fmu, lo, k in ((m, 0, nm), (e, nm, ne)):
                if k:
                    buf = (c_double * k)()
                    fmu.call("getContinuousStates", buf, k)
                    x[lo:lo + k] = buf[:k]
            return x

        def nominals() -> np.ndarray:
            from ctypes import c_double
            x = np.ones(n)
            for fmu, lo, k in ((m, 0, nm), (e, nm, ne)):
                if k:
                    buf = (c_double * k)()
                    fmu.call("getNominalsOfContinuousStates", buf, k)
                    x[lo:lo + k] = np.abs(buf[:k])
            return x

        times = np.asarray(output_times, dtype=float)
        rows: list[list[float]] = []
        k_out = 0

        def record(t: float) -> None:
            """The outputs at t, when t is an output time (the FMUs were last evaluated at t)."""
            nonlocal k_out
            while k_out < len(times) and times[k_out] <= t + 1e-12 * max(1.0, abs(t)):
                if abs(times[k_out] - t) <= 1e-12 * max(1.0, abs(t)):
                    row = [t]
                    for _, d, buf in reads:
                        d.get_real(buf)
                        row.append(buf[1][0])
                    rows.append(row + [last["F"]])
                k_out += 1

        asked = {"event": False}

        def on_step(t: float, x: np.ndarray) -> bool:
            record(t)
            step_m = m.call("completedIntegratorStep", 1)
            step_e = e.call("completedIntegratorStep", 1)
            if step_m[1] or step_e[1]:
                raise CouplingError(f"an FMU asked to terminate the simulation at t = {t:.9g}")
            asked["event"] = bool(step_m[0] or step_e[0])
            return asked["event"]

        x = states()
        floor = 1e-3 * nominals()
        t = 0.0
        evaluate(0.0, x)
        record(0.0)
        totals = {"steps": 0, "rejected": 0, "rhs": 0, "jacobians": 0, "max_substeps": 1, "worst_error": 0.0}
        while t < stop_time * (1 - 1e-14):
            t_end = min(stop_time, t_ev)
            grid = np.union1d([t, t_end], times[(times > t) & (times < t_end)])
            t, x, st = integrate_on_grid(rhs, x, grid, rtol, floor, on_step=on_step,
                                         check=lambda tt: _over_time(deadline, tt))
            for key in ("steps", "rejected", "rhs", "jacobians"):
                totals[key] += getattr(st, key)
            totals["max_substeps"] = max(totals["max_substeps"], st.max_substeps)
            totals["worst_error"] = max(totals["worst_error"], st.worst_error)
            if asked["event"] or (math.isfinite(t_ev) and t >= t_ev * (1 - 1e-14)):
                evaluate(t, x)
                m.call("enterEventMode")
                e.call("enterEventMode")
                nxt = min(_event_iteration(m), _event_iteration(e))
                m.call("enterContinuousTimeMode")
                e.call("enterContinuousTimeMode")
                x = states()
                t_ev = nxt if nxt > t else math.inf
                asked["event"] = False
        frame = pd.DataFrame(rows, columns=["time", *outputs, "F"])
        return frame, m.calls + e.calls, totals
    finally:
        m.free()
        e.free()


# ---------------------------------------------------------------------------------------------- CS

def _cs_grid(stop_time: float, step: float, output_times: np.ndarray) -> np.ndarray:
    n = max(1, int(math.ceil(stop_time / step - 1e-9)))
    grid = np.union1d(np.linspace(0.0, stop_time, n + 1), np.asarray(output_times, dtype=float))
    return grid[(grid >= 0) & (grid <= stop_time)]


def _run_cs(coupling, minfo, einfo, model_params, element_params, stop_time, output_times, outputs, model_inputs,
            rtol, step: float, iterate: bool, max_iter: int = 30,
            deadline: float | None = None, fresh: bool = False) -> tuple[pd.DataFrame, int, dict]:
    m = _Fmu(minfo, "co-simulation", "model", fresh)
    e = _Fmu(einfo, "co-simulation", "element", fresh)
    try:
        itf = _Interface(coupling, m, e)
        where = _check_outputs(outputs, m, e)
        interp_m = _capabilities(minfo)["cs_interp"]
        interp_e = _capabilities(einfo)["cs_interp"]
        u0, f0 = _drive(model_inputs, 0.0, coupling.force_input)
        _start(m, model_params, rtol, stop_time, {**u0, coupling.force_input: f0})
        _start(e, element_params, rtol, stop_time, {})
        sv = coupling.velocity_sign
        s_n, v_n = m.real([itf.s, itf.v])
        v_n *= sv
        e.call("setReal", [itf.es, itf.ev], [s_n, v_n])
        F_n = e.real([itf.eF])[0]
        m.call("setReal", [itf.f], [f0 + coupling.force_sign * F_n])
        times = np.asarray(output_times, dtype=float)
        grid = _cs_grid(stop_time, step, times)
        rows = []

        def record(t):
            if np.any(np.isclose(times, t, rtol=0, atol=1e-12 * max(1.0, t))):
                rows.append([t] + [fmu.real([vr])[0] for _, fmu, vr in where] + [F_n])

        record(0.0)
        F_scale = max(abs(F_n), 1e-12)
        iterations = 0

        def macro(t: float, h: float, F_k: float, drive_now, drive_next) -> tuple[float, float, float]:
            """One macro step with the force going from F_n to F_k over it: the element's F at t + h."""
            u, fd = drive_now
            u1, fd1 = drive_next
            if u:
                m.set_values(u)
            # the interface force over the step: explicit, held at F_n; iterated, affine from F_n to the iterate
            # F_k where the model interpolates its inputs (second order), else held at F_k (first order); the
            # drive, where the model interpolates, affine from its value at t to that at t + h
            if iterate and interp_m:
                f_start = fd + coupling.force_sign * F_n
                f_rate = (fd1 + coupling.force_sign * F_k - f_start) / h
            else:
                f_start = fd + coupling.force_sign * F_k
                f_rate = (fd1 - fd) / h
            m.call("setReal", [itf.f], [f_start])
            if interp_m:
                m.call("setRealInputDerivatives", [itf.f], [1], [f_rate])
                if u:
                    vrs = m.vr(list(u))
                    m.call("setRealInputDerivatives", vrs, [1] * len(vrs),
                           [(u1[n] - u[n]) / h for n in u])
            m.call("doStep", t, h, 0 if iterate else 1)
            s1, v1 = m.real([itf.s, itf.v])
            v1 *= sv
            if not (math.isfinite(s1) and math.isfinite(v1)):
                raise CouplingError(f"the coupled run diverged at t = {t + h:.9g} (step {h:.3g} s)")
            if interp_e:
                e.call("setReal", [itf.es, itf.ev], [s_n, v_n])
                e.call("setRealInputDerivatives", [itf.es, itf.ev], [1, 1], [(s1 - s_n) / h, (v1 - v_n) / h])
            else:
                e.call("setReal", [itf.es, itf.ev], [s1, v1])
            e.call("doStep", t, h, 0 if iterate else 1)
            e.call("setReal", [itf.es, itf.ev], [s1, v1])   # F at t + h with the motion at t + h
            if interp_e:
                e.call("setRealInputDerivatives", [itf.es, itf.ev], [1, 1], [0.0, 0.0])
            F1 = e.real([itf.eF])[0]
            if not (math.isfinite(F1) and math.isfinite(s1) and math.isfinite(v1)):
                raise CouplingError(f"the coupled run diverged at t = {t + h:.9g} (step {h:.3g} s)")
            return F1, s1, v1

        F_prev = F_n
        for t, t1 in zip(grid[:-1], grid[1:]):
            _over_time(deadline, t)
            h = t1 - t
            dn, dn1 = _drive(model_inputs, t, coupling.force_input), _drive(model_inputs, t1, coupling.force_input)
            if iterate:
                sm, se = m.call("getFMUState"), e.call("getFMUState")
                # secant iteration on the residual r(F) = element force(model motion under F) - F: the first
                # guess extrapolates the force, the second perturbs it (a fixed-point step would overshoot by
                # the interface's stiffness), then secant steps
                F_k = F_n + (F_n - F_prev)
                hist: list[tuple[float, float]] = []
                r = math.inf
                for it in range(max_iter):
                    F1, s1, v1 = macro(t, h, F_k, dn, dn1)
                    iterations += 1
                    r = F1 - F_k
                    F_scale = max(F_scale, abs(F1))
                    if abs(r) <= 10 * rtol * F_scale:
                        break
                    hist.append((F_k, r))
                    if len(hist) >= 2 and hist[-1][1] != hist[-2][1]:
                        (Fa, ra), (Fb, rb) = hist[-2], hist[-1]
                        F_k = Fb - rb * (Fb - Fa) / (rb - ra)
                    else:
                        F_k = F_k + 1e-3 * max(abs(r), 1e-9 * F_scale)
                    m.call("setFMUState", sm)
                    e.call("setFMUState", se)
                else:
                    raise CouplingError(f"the interface force did not converge in {max_iter} iterations at "
                                        f"t = {t1:.9g} (residual {r:.3g}); use a smaller step or me-implicit")
                m.call("freeFMUState", sm)
                e.call("freeFMUState", se)
            else:
                F1, s1, v1 = macro(t, h, F_n, dn, dn1)
            F_prev, F_n, s_n, v_n = F_n, F1, s1, v1
            F_scale = max(F_scale, abs(F_n))
            m.call("setReal", [itf.f], [dn1[1] + coupling.force_sign * F_n])
            if interp_m:
                m.call("setRealInputDerivatives", [itf.f], [1], [0.0])
            record(t1)
        frame = pd.DataFrame(rows, columns=["time", *outputs, "F"])
        return frame, m.calls + e.calls, {"iterations": iterations, "steps": len(grid) - 1}
    finally:
        m.free()
        e.free()


def _difference(a: pd.DataFrame, b: pd.DataFrame) -> float:
    """Largest difference of two runs' columns, relative to the column's range in the finer run."""
    worst = 0.0
    for col in a.columns[1:]:
        x, y = a[col].to_numpy(float), b[col].to_numpy(float)
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(y))):
            return math.inf
        scale = max(np.max(np.abs(y)), 1e-300)
        worst = max(worst, float(np.max(np.abs(x - y))) / scale)
    return worst


# ---------------------------------------------------------------------------------------------- run

def simulate_coupled(coupling: Coupling, model_params: dict[str, float], element_params: dict[str, float],
                     stop_time: float, output_times: np.ndarray, outputs: Sequence[str],
                     model_inputs: Callable[[float], dict[str, float]] | None = None,
                     rtol: float = 1e-6, step: float | None = None, coupling_tol: float = 1e-3,
                     max_halvings: int = 10, strict: bool = True, max_wall_s: float | None = None,
                     fresh_binary: bool = False) -> CoupledResult:
    """Run the model and the element together from 0 to ``stop_time``; the outputs (model variables, or
    ``element.NAME``) and the element's force ``F`` at ``output_times``.

    ``model_inputs(t)`` gives the model's other inputs (a drive); a value for the force input itself is added to
    the interface force. ``step`` is the first macro step of the CS schemes (default: the output spacing); they
    halve it until two runs agree within ``coupling_tol`` (relative to each column's largest value).
    ``max_wall_s`` bounds the wall time of the whole (every run of the verification): past it
    :class:`CouplingTimeLimitError`. The FMUs' binaries are loaded once per process and each run makes fresh
    instances; ``fresh_binary`` loads a fresh copy for this run (for a binary whose instances share state).
    """
    if not (stop_time > 0 and math.isfinite(stop_time)):
        raise CouplingError(f"stop_time = {stop_time}: use a positive, finite time")
    times = np.asarray(output_times, dtype=float)
    if times.ndim != 1 or len(times) == 0 or np.any(np.diff(times) <= 0) or times[0] < 0 or times[-1] > stop_time:
        raise CouplingError("output_times must increase strictly, within [0, stop_time]")
    minfo, einfo, scheme = checked_coupling(coupling)
    wall0, cpu0 = time.perf_counter(), time.process_time()
    deadline = wall0 + float(max_wall_s) if max_wall_s else None
    args = (coupling, minfo, einfo, dict(model_params), dict(element_params), float(stop_time), times,
            list(outputs), model_inputs, float(rtol))
    if scheme == "me-grid":
        frame, calls, info = _run_me_grid(*args, deadline, fresh_binary)
        return CoupledResult(frame, scheme, calls, time.perf_counter() - wall0, time.process_time() - cpu0,
                             notes=[f"{info['steps']} Radau IIA steps on the output grid (rtol {rtol:g}; "
                                    f"{info['rejected']} steps cut in two, the smallest a sample "
                                    f"interval / {info['max_substeps']}; {info['rhs']} evaluations, "
                                    f"{info['jacobians']} Jacobians)"])
    if scheme == "me-implicit":
        frame, calls, info = _run_me(*args, deadline, fresh_binary)
        return CoupledResult(frame, scheme, calls, time.perf_counter() - wall0, time.process_time() - cpu0,
                             notes=[f"{info['steps']} implicit steps (Radau, rtol {rtol:g})"])
    iterate = scheme == "cs-iterate"
    h = float(step) if step else float(np.min(np.diff(np.r_[0.0, times[times > 0]]))
                                       if np.any(times > 0) else stop_time / 100)
    calls, runs, prev, diff, info = 0, 0, None, None, {}
    notes = []
    for k in range(max_halvings + 1):
        try:
            frame, c, info = _run_cs(*args, h, iterate, deadline=deadline, fresh=fresh_binary)
        except CouplingError as exc:
            if "diverged" not in str(exc) and "did not converge" not in str(exc):
                raise
            frame, c = None, 0
            notes.append(f"step {h:.3g} s: {exc}")
        calls += c
        runs += 1
        if frame is not None and prev is not None:
            diff = _difference(prev, frame)
            notes.append(f"step {h:.3g} s vs {2 * h:.3g} s: relative difference {diff:.3g}")
            if diff <= coupling_tol:
                return CoupledResult(frame, scheme, calls, time.perf_counter() - wall0,
                                     time.process_time() - cpu0, step=h, runs=runs, difference=diff,
                                     iterations=info.get("iterations", 0), notes=notes)
        prev = frame
        h /= 2
    msg = (f"the coupled {scheme} run did not converge: halving the macro step {max_halvings} times left a "
           f"relative difference of {diff if diff is not None else math.inf:.3g} between the last two runs "
           f"(tolerance {coupling_tol:g}); export the model with Model Exchange (me-implicit) or with "
           f"canGetAndSetFMUstate (cs-iterate), or give a smaller step")
    if strict or prev is None:
        raise CouplingError(msg)
    warnings.warn(msg, stacklevel=2)
    return CoupledResult(prev, scheme, calls, time.perf_counter() - wall0, time.process_time() - cpu0,
                         step=2 * h, runs=runs, converged=False, difference=diff,
                         iterations=info.get("iterations", 0), notes=notes)

