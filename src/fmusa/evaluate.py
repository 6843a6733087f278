"""Run FMI 2.0 FMUs: the one module of fmusa that talks to an FMU (through fmpy).

An :class:`FMURunner` extracts the FMU once, instantiates it once and then runs it as often as
needed: every run is ``reset`` → set parameters → ``setupExperiment`` → initialisation →
``doStep`` … → read outputs. Reusing the instance avoids the unzip/load/instantiate cost that
``fmpy.simulate_fmu`` pays on every call, which matters for studies of thousands of runs.

Co-simulation FMUs integrate themselves. Model exchange FMUs are integrated by fmpy's solver (CVode or
Euler, ``fmpy.simulate_fmu`` on the reused instance). :func:`read_fmu_info` reads what an FMU declares
(FMI version, interfaces, binaries, sources, variables) without loading it; :func:`variable_problem`
and :func:`select_interface` are the load-time checks; an FMU without a binary for this platform but
with C sources is built by :func:`compile_sources` / :func:`prepare_fmu`.

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
from dataclasses import dataclass, replace
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


# ---------------------------------------------------------------------- what an FMU holds, checks, compiling
#: The FMI 2.0 interfaces fmusa runs, in order of preference for ``interface: auto``.
INTERFACES = ("co-simulation", "model-exchange")
#: Values of ``fmu_options.interface``.
INTERFACE_CHOICES = ("auto",) + INTERFACES
#: fmpy's solvers for model exchange FMUs.
SOLVERS = ("CVode", "Euler")
_FMPY_TYPE = {"co-simulation": "CoSimulation", "model-exchange": "ModelExchange"}
_SHORT = {"co-simulation": "CS", "model-exchange": "ME"}


class FMUError(ValueError):
    """An FMU fmusa cannot run as asked: not FMI 2.0, the requested interface missing, no binary for
    this platform and no sources to build one, or an unreadable model description."""


class FMUCompileError(RuntimeError):
    """Building an FMU's binary from its C sources failed; the message names the FMU and holds the
    compiler's output."""


def host_platform() -> str:
    """The FMI 2.0 platform directory of this machine (``linux64`` on Linux x86-64)."""
    import fmpy
    return fmpy.platform


def _an(word: str) -> str:
    return f"an {word}" if word[:1].lower() in "aeiou" else f"a {word}"


def _archive_names(path: Path) -> list[str]:
    if path.is_dir():
        return [p.relative_to(path).as_posix() for p in path.rglob("*") if p.is_file()]
    import zipfile
    try:
        with zipfile.ZipFile(path) as zf:
            return [n for n in zf.namelist() if not n.endswith("/")]
    except zipfile.BadZipFile:
        raise FMUError(f"{path}: not an FMU (not a ZIP archive)") from None


def _root_attributes(path: Path) -> dict[str, str]:
    """Attributes of <fmiModelDescription> (fmiVersion, modelName…), read without fmpy, so that an
    FMI 1 or FMI 3 FMU is recognised before anything tries to parse it as FMI 2."""
    import xml.etree.ElementTree as ET
    import zipfile
    try:
        if path.is_dir():
            data = (path / "modelDescription.xml").read_bytes()
        else:
            with zipfile.ZipFile(path) as zf:
                data = zf.read("modelDescription.xml")
    except (OSError, KeyError):
        raise FMUError(f"{path}: not an FMU (no modelDescription.xml)") from None
    try:
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        raise FMUError(f"{path}: modelDescription.xml is not well-formed XML ({exc})") from None
    return dict(root.attrib)


@dataclass(frozen=True, eq=False)
class FMUInfo:
    """What an FMU declares and contains, read from its model description and its file list (no binary
    is loaded). Made by :func:`read_fmu_info`."""
    path: Path
    fmi_version: str
    model_name: str
    description: str
    generation_tool: str
    guid: str
    interfaces: dict            # interface ("co-simulation"/"model-exchange") -> model identifier
    binaries: dict              # platform directory -> list of files in it
    source_files: tuple         # the files listed under <SourceFiles>
    has_sources: bool           # the archive has sources/*.c (or .cpp)
    default_experiment: dict    # start_time, stop_time, tolerance, step_size (those declared)
    variables: tuple            # fmpy ModelVariable objects, in model-description order
    n_states: int
    n_event_indicators: int
    model_description: object   # the fmpy ModelDescription
    warnings: tuple = ()        # e.g. fmpy's schema validation problems (the FMU is still read)

    @property
    def platforms(self) -> list[str]:
        """Platforms with a binary (``linux64``, ``win64``, ``darwin64``…)."""
        return sorted(p for p, files in self.binaries.items() if files)

    def variable(self, name: str):
        return self._by_name.get(name)

    @property
    def _by_name(self) -> dict:
        d = self.__dict__.get("_names")
        if d is None:
            d = {v.name: v for v in self.variables}
            object.__setattr__(self, "_names", d)
        return d

    def binary_name(self, interface: str) -> str:
        import fmpy
        return f"{self.interfaces[interface]}{fmpy.sharedLibraryExtension}"

    def has_binary(self, interface: str, platform: str | None = None) -> bool:
        """Whether the shared library of ``interface`` is there for ``platform`` (default: this machine)."""
        platform = platform or host_platform()
        return self.binary_name(interface) in self.binaries.get(platform, [])

    @property
    def can_compile(self) -> bool:
        return self.has_sources and bool(self.source_files)


def read_fmu_info(path: str | os.PathLike, require_fmi2: bool = True) -> FMUInfo:
    """Read what ``path`` (an ``.fmu`` file or an extracted FMU directory) declares and contains.

    Raises :class:`FMUError` when it is not an FMU, or (``require_fmi2``) not an FMI 2.0 FMU. fmpy's
    schema validation problems do not stop the reading: they are kept in ``warnings``.
    """
    import fmpy

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"FMU not found: {path}")
    names = _archive_names(path)
    attrs = _root_attributes(path)
    version = attrs.get("fmiVersion", "?")
    model = attrs.get("modelName", path.stem)
    if require_fmi2 and version != "2.0":
        major = version.split(".")[0]
        raise FMUError(f"{path}: {model} is an FMI {version} FMU (fmiVersion=\"{version}\" in its "
                       f"modelDescription.xml); fmusa needs FMI 2.0. Export the model again as an FMI "
                       f"2.0 co-simulation or model exchange FMU"
                       + (" (FMI 1.0 FMUs cannot be converted)" if major == "1" else
                          " (most tools that export FMI 3.0 can also export FMI 2.0)" if major == "3" else ""))
    warnings: list[str] = []
    try:
        md = fmpy.read_model_description(str(path), validate=True)
    except Exception as exc:  # schema or consistency problems: read it anyway, keep the problems
        try:
            md = fmpy.read_model_description(str(path), validate=False)
        except Exception as exc2:
            raise FMUError(f"{path}: cannot read modelDescription.xml: {exc2}") from None
        warnings.append(f"fmpy's validation of modelDescription.xml failed: {str(exc).strip()}")
    interfaces = {}
    if getattr(md, "coSimulation", None) is not None:
        interfaces["co-simulation"] = md.coSimulation.modelIdentifier
    if getattr(md, "modelExchange", None) is not None:
        interfaces["model-exchange"] = md.modelExchange.modelIdentifier
    binaries: dict[str, list[str]] = {}
    for n in names:
        parts = n.split("/")
        if len(parts) == 3 and parts[0] == "binaries":
            binaries.setdefault(parts[1], []).append(parts[2])
    has_sources = any(n.startswith("sources/") and n.rsplit(".", 1)[-1] in ("c", "cc", "cpp", "cxx")
                      for n in names)
    source_files: list[str] = []
    for bc in getattr(md, "buildConfigurations", None) or []:
        for sfs in bc.sourceFileSets:
            source_files += [f for f in sfs.sourceFiles if f not in source_files]
    de = md.defaultExperiment
    experiment = {}
    if de is not None:
        for key, attr in (("start_time", "startTime"), ("stop_time", "stopTime"),
                          ("tolerance", "tolerance"), ("step_size", "stepSize")):
            val = getattr(de, attr, None)
            if val is not None:
                try:
                    experiment[key] = float(val)
                except ValueError:
                    experiment[key] = val
    return FMUInfo(path=path, fmi_version=md.fmiVersion, model_name=md.modelName or model,
                   description=md.description or "", generation_tool=md.generationTool or "",
                   guid=md.guid or "", interfaces=interfaces, binaries=binaries,
                   source_files=tuple(source_files), has_sources=has_sources,
                   default_experiment=experiment, variables=tuple(md.modelVariables),
                   n_states=int(md.numberOfContinuousStates or 0),
                   n_event_indicators=int(md.numberOfEventIndicators or 0),
                   model_description=md, warnings=tuple(warnings))


def select_interface(info: FMUInfo, requested: str = "auto") -> str:
    """The interface a study runs: co-simulation when the FMU has it (``auto``), else model exchange;
    or the one ``requested``. Raises :class:`FMUError` when the FMU does not implement it."""
    have = list(info.interfaces)
    if not have:
        raise FMUError(f"{info.path}: {info.model_name} declares neither <CoSimulation> nor "
                       f"<ModelExchange> in its modelDescription.xml")
    if requested in (None, "auto"):
        return "co-simulation" if "co-simulation" in have else "model-exchange"
    if requested not in INTERFACES:
        raise FMUError(f"unknown interface {requested!r}; use one of {', '.join(INTERFACE_CHOICES)}")
    if requested not in have:
        other = have[0]
        raise FMUError(f"interface {requested} was asked for, but {info.model_name} implements only "
                       f"{other} ({_SHORT[other]}); set interface: {other} or auto"
                       + ("" if other == "model-exchange" else
                          " (a co-simulation FMU brings its own solver)"))
    return requested


def binary_problem(info: FMUInfo, interface: str) -> str | None:
    """Why ``interface`` cannot run on this machine (no binary and no sources), or None."""
    if info.has_binary(interface) or info.can_compile:
        return None
    plat = host_platform()
    have = ", ".join(info.platforms) or "none"
    src = ("it has no C sources (sources/ and <SourceFiles>) to build one from" if not info.has_sources
           else "its sources/ are not listed under <SourceFiles> in modelDescription.xml, so they "
                "cannot be built")
    return (f"{info.model_name} has no {plat} binary for {interface} "
            f"(binaries/{plat}/{info.binary_name(interface)}; platforms with binaries: {have}), and "
            f"{src}; export the FMU for {plat}, or with source code")


def closest_names(name: str, pool: Iterable[str], n: int = 5) -> list[str]:
    """Names in ``pool`` closest to ``name`` (difflib), best first; case-insensitive as a fallback."""
    pool = list(pool)
    close = difflib.get_close_matches(name, pool, n=n, cutoff=0.4)
    if not close:
        lower = {p.lower(): p for p in pool}
        close = [lower[c] for c in difflib.get_close_matches(name.lower(), list(lower), n=n, cutoff=0.4)]
    return close


#: Variable types fmusa can set and read.
_TYPES = ("Real", "Integer", "Enumeration", "Boolean")


def variable_problem(info: FMUInfo, name: str, role: str) -> str | None:
    """Why FMU variable ``name`` cannot play ``role``, or None when it can.

    ``role`` is ``"varied"`` (a study parameter: a settable Real parameter), ``"parameter"`` (set once per
    run: a settable parameter of any supported type), ``"input"`` or ``"output"`` (read after the run).
    The message lists the closest names the FMU does have.
    """
    vs = info.variables
    v = info.variable(name)
    if role in ("varied", "parameter"):
        pool = [x.name for x in vs if x.causality == "parameter" and x.variability in ("fixed", "tunable")]
        wider = pool
        what = "parameter"
    elif role == "input":
        pool = [x.name for x in vs if x.causality == "input"]
        wider = pool
        what = "input"
    else:
        pool = [x.name for x in vs if x.causality == "output"]
        wider = [x.name for x in vs if x.causality != "independent"]
        what = "output"

    def hint(prefix: str = "closest") -> str:
        others = [n for n in pool if n != name]
        close = closest_names(name, others)
        if not close and v is None:
            close = closest_names(name, [n for n in wider if n != name])
            if close:
                return f"; closest names: {', '.join(close)}"
        if close:
            return f"; {prefix} {what} names: {', '.join(close)}"
        if v is not None:
            return ""
        if others:
            more = f" … ({len(others)} in all)" if len(others) > 12 else ""
            return f"; its {what}s are: {', '.join(others[:12])}{more}"
        return f"; it has no {what}s"

    if v is None:
        return f"{info.model_name} has no variable {name!r}{hint()}"
    causality, variability = v.causality or "local", v.variability or "continuous"
    if v.type not in _TYPES:
        return f"{name!r} is of type {v.type}; fmusa sets and reads only Real, Integer, Boolean and Enumeration"
    if role in ("varied", "parameter"):
        if causality == "calculatedParameter":
            deps = None
            for u in getattr(info.model_description, "initialUnknowns", None) or []:
                if u.variable is v and u.dependencies:
                    deps = [d.name for d in u.dependencies]
            source = (f" ({', '.join(deps)})" if deps else
                      f" (its description: {v.description!r})" if v.description else "")
            return (f"{name!r} is a calculatedParameter: the FMU computes it from other parameters, so it "
                    f"cannot be set; set the parameters it is computed from{source} instead")
        if variability == "constant":
            return (f"{name!r} is a constant (variability constant, causality {causality}): its value is "
                    f"fixed in the FMU and cannot be set{hint('settable')}")
        if causality == "input":
            return f"{name!r} is an input, not a parameter; set it under scenario.inputs instead"
        if causality != "parameter":
            return (f"{name!r} is {_an(causality)} variable (causality {causality}), not a parameter, and "
                    f"cannot be set{hint('settable')}")
        if variability not in ("fixed", "tunable"):
            return (f"{name!r} has variability {variability}; only fixed or tunable parameters can be "
                    f"set{hint('settable')}")
        if role == "varied" and v.type != "Real":
            return (f"{name!r} is {_an(v.type)} parameter; a study parameter must be Real (set "
                    f"{v.type} parameters under fixed)")
        return None
    if role == "input":
        if causality == "input":
            return None
        if causality == "parameter":
            return f"{name!r} is a parameter, not an input; set it under fixed instead"
        return f"{name!r} is {_an(causality)} variable (causality {causality}), not an input{hint()}"
    if causality == "independent":
        return f"{name!r} is the independent variable (time); metrics read outputs"
    return None


def _tail(text: str, n: int = 4000) -> str:
    text = text.strip()
    return text if len(text) <= n else "…" + text[-n:]


def compile_sources(unzipdir: str | os.PathLike, info: FMUInfo | None = None,
                    interface: str | None = None) -> Path:
    """Build the binary for this platform from the C sources of the extracted FMU ``unzipdir`` and put it
    in ``unzipdir/binaries/<platform>/``, as ``fmpy.build.build_platform_binary`` does (CMake with fmpy's
    build template; plain ``cc`` when CMake is missing). Returns the binary's path.

    Raises :class:`FMUCompileError` with the compiler's output when the build fails.
    """
    import subprocess
    import tempfile

    import fmpy

    unzipdir = Path(unzipdir).resolve()
    info = info or read_fmu_info(unzipdir)
    interface = interface or select_interface(info)
    plat = host_platform()
    target = unzipdir / "binaries" / plat / info.binary_name(interface)
    label = f"{info.model_name} ({info.path})"
    if not info.can_compile:
        raise FMUCompileError(f"{label}: no {plat} binary and no C sources listed under <SourceFiles>")
    log: list[str] = []

    def run(cmd: list[str], cwd=None) -> bool:
        log.append("$ " + " ".join(cmd))
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, cwd=cwd, timeout=600)
        except (OSError, subprocess.TimeoutExpired) as exc:
            log.append(str(exc))
            return False
        log.append((proc.stdout + proc.stderr).strip())
        return proc.returncode == 0

    c_code = Path(fmpy.__file__).parent / "c-code"
    ok = False
    if shutil.which("cmake"):
        from fmpy.build import create_cmake_settings
        with tempfile.TemporaryDirectory(prefix="fmusa-build-") as build_dir:
            try:
                create_cmake_settings(unzipdir, build_dir)
            except Exception as exc:
                raise FMUCompileError(f"{label}: cannot set up the build of its sources: {exc}") from None
            ok = (run(["cmake", "-S", str(c_code), "-B", build_dir])
                  and run(["cmake", "--build", build_dir, "--target", "install", "--config", "Release"]))
    else:
        cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
        if cc is None:
            raise FMUCompileError(f"{label}: has no {plat} binary, and neither cmake nor a C compiler (cc, "
                                  f"gcc) was found to build one from its sources; install gcc (and cmake)")
        srcs = [str(unzipdir / "sources" / f) for f in info.source_files]
        target.parent.mkdir(parents=True, exist_ok=True)
        ok = run([cc, "-shared", "-fPIC", "-O2", f"-I{unzipdir / 'sources'}", f"-I{c_code}", *srcs,
                  "-o", str(target), "-lm"])
    if not ok or not target.is_file():
        if ok:
            log.append(f"the build finished but did not produce {target.relative_to(unzipdir)}")
        # the failing step (the configure chatter of a step that worked is left out)
        failed = log[-2:] if len(log) >= 2 and log[-2].startswith("$ ") else log[-1:]
        raise FMUCompileError(f"{label}: has no {plat} binary, and building one from its C sources "
                              f"({', '.join(info.source_files)}) failed. Compiler output:\n"
                              + _tail("\n".join(x for x in failed if x)))
    return target


def _file_digest(path: Path) -> str:
    import hashlib
    h = hashlib.sha256()
    if path.is_dir():
        for p in sorted(path.rglob("*")):
            if p.is_file():
                h.update(p.relative_to(path).as_posix().encode())
                h.update(p.read_bytes())
    else:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()[:12]


def prepare_fmu(fmu_path: str | os.PathLike, interface: str = "auto",
                workdir: str | os.PathLike | None = None) -> Path:
    """A path FMURunner can run on this machine: ``fmu_path`` itself when it has a binary for this platform,
    else an extracted copy in ``workdir`` (default: a new temporary directory) with the binary built from
    the FMU's sources. A copy built earlier for the same FMU content is reused.

    Raises :class:`FMUError` (not FMI 2.0, interface missing, neither binary nor sources) or
    :class:`FMUCompileError`.
    """
    import tempfile

    import fmpy

    fmu_path = Path(fmu_path)
    info = read_fmu_info(fmu_path)
    iface = select_interface(info, interface)
    if info.has_binary(iface):
        return fmu_path
    problem = binary_problem(info, iface)
    if problem:
        raise FMUError(f"{fmu_path}: {problem}")
    root = Path(workdir) if workdir is not None else Path(tempfile.mkdtemp(prefix="fmusa-fmu-"))
    root.mkdir(parents=True, exist_ok=True)
    dest = root / f"{fmu_path.stem}-{_file_digest(fmu_path)}"
    if (dest / "binaries" / host_platform() / info.binary_name(iface)).is_file():
        return dest
    tmp = Path(tempfile.mkdtemp(prefix=".build-", dir=root))
    try:
        if fmu_path.is_dir():
            shutil.copytree(fmu_path, tmp, dirs_exist_ok=True)
        else:
            fmpy.extract(str(fmu_path), str(tmp))
        compile_sources(tmp, info, iface)
        shutil.rmtree(dest, ignore_errors=True)
        tmp.rename(dest)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return dest


class FMURunner:
    """One extracted, instantiated FMI 2.0 FMU, run again and again.

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
        to ``fmi2SetupExperiment``; ``solver`` and ``step_size`` are errors.
    """

    def __init__(self, fmu_path: str | os.PathLike | None = None, instance_name: str = "fmusa",
                 debug_logging: Iterable[str] | None = None, *, interface: str = "auto",
                 solver: str | None = None, relative_tolerance: float | None = None,
                 step_size: float | None = None) -> None:
        import fmpy

        self.fmu_path = Path(fmu_path) if fmu_path is not None else default_fmu_path()
        if not self.fmu_path.exists():
            raise FileNotFoundError(f"FMU not found: {self.fmu_path}")
        self.instance_name = instance_name
        self._owns_unzipdir = False
        self.unzipdir = None
        self._slave = None
        info = read_fmu_info(self.fmu_path)              # FMI 2.0? (FMUError otherwise)
        self.interface = select_interface(info, interface)
        if solver is not None and solver not in SOLVERS:
            raise ValueError(f"unknown solver {solver!r}; use one of {', '.join(SOLVERS)}")
        if self.interface == "co-simulation" and (solver is not None or step_size is not None):
            raise ValueError(f"{info.model_name} runs as a co-simulation FMU, which integrates with its own "
                             f"solver: solver and step_size apply to model exchange only")
        for name, x in (("relative_tolerance", relative_tolerance), ("step_size", step_size)):
            if x is not None and not (math.isfinite(x) and x > 0):
                raise ValueError(f"{name} must be a positive finite number, got {x!r}")
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
            self.unzipdir = Path(fmpy.extract(str(self.fmu_path)))
        elif needs_build:   # never write into the user's directory: build in a copy
            import tempfile
            self._owns_unzipdir = True
            self.unzipdir = Path(tempfile.mkdtemp(prefix="fmusa-fmu-"))
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
        self.variables = {v.name: v for v in md.modelVariables}
        self.messages: deque[tuple[str, str, str]] = deque(maxlen=500)
        cats = [c.name for c in getattr(md, "logCategories", [])]
        if debug_logging is None:
            debug_logging = [c for c in cats if c in ("logStatusError", "logStatusWarning")]
        self._debug_logging = list(debug_logging)
        self._state = "closed"
        self._phase = ""
        try:
            self._instantiate()
        except BaseException:
            self._cleanup_dir()
            raise

    @property
    def is_model_exchange(self) -> bool:
        return self.interface == "model-exchange"

    # ------------------------------------------------------------------ instance management
    def _instantiate(self) -> None:
        from fmpy.fmi2 import (FMU2Model, FMU2Slave, fmi2CallbackAllocateMemoryTYPE,
                               fmi2CallbackFreeMemoryTYPE, fmi2CallbackFunctions, fmi2CallbackLoggerTYPE)
        from fmpy import calloc, free

        md = self.model_description
        cls = FMU2Model if self.is_model_exchange else FMU2Slave
        slave = cls(guid=md.guid, unzipDirectory=str(self.unzipdir),
                    modelIdentifier=self.info.interfaces[self.interface],
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

    def _ready(self) -> None:
        """An instance in the instantiated state: reset the last run's, or instantiate afresh."""
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

    def _start(self, params: Mapping[str, Value], stop_time: float,
               inputs: Mapping[str, float] | None) -> None:
        self._ready()
        self._phase = "while setting parameters"
        self._set(params, ("parameter",), "parameter")
        if inputs:
            self._set(inputs, ("input",), "input")
        self._phase = "during initialisation"
        self._slave.setupExperiment(tolerance=self.relative_tolerance, startTime=0.0, stopTime=float(stop_time))
        self._slave.enterInitializationMode()
        self._slave.exitInitializationMode()
        self._phase = "after initialisation"

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

    def _run_me(self, values: Mapping[str, Value], times: np.ndarray, outputs: list[str],
                params: Mapping[str, Value]) -> np.ndarray:
        """One model exchange run with fmpy's solver on the reused instance; the outputs at ``times``.

        ``values`` are the start values (parameters and constant inputs) set after ``fmi2Reset``."""
        from fmpy import simulate_fmu

        self._ready()
        interval, step_size = self._me_intervals(times)
        self._phase = (f"in fmpy's {self.solver} integration of the model exchange FMU "
                       f"from t = 0 to {times[-1]:.10g} s")
        try:
            res = simulate_fmu(str(self.unzipdir), validate=True, start_time=0.0, stop_time=float(times[-1]),
                               solver=self.solver, step_size=step_size,
                               relative_tolerance=self.relative_tolerance, output_interval=interval,
                               record_events=True, fmi_type="ModelExchange", start_values=dict(values),
                               output=list(outputs), model_description=self.model_description,
                               fmu_instance=self._slave)
        except Exception as exc:
            raise self._fail(exc, self._phase, params) from exc
        self._state = "done"
        return _sample_at(res, times, outputs)

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
        if self.is_model_exchange:
            for name in outputs:
                self._lookup(name, ("output", "parameter", "calculatedParameter", "local", "input"), "output")
            values = {n: self._coerce(self.variables[n], x) for n, x in {**params, **(inputs or {})}.items()}
            data = self._run_me(values, times, outputs, params)
            df = pd.DataFrame(data, columns=outputs)
            df.insert(0, "time", times)
            return df
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
        if self.is_model_exchange:
            df = self.run(params, stop_time, None, outputs, inputs)
            return {name: float(df[name].iloc[-1]) for name in outputs}
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
def _initialise(r: FMURunner, fixed_calls: list, vr_varied, val_varied, values: Sequence[float],
                input_calls: list, start: float, stop: float) -> None:
    """Set the prepared parameters and inputs of one run on a ready instance and initialise it (the part
    RunPlan and DrivenPlan share; the phases name where a failure happened)."""
    s = r._slave
    r._phase = "while setting parameters"
    for fn, vr, val in fixed_calls:
        getattr(s, fn)(s.component, vr, len(vr), val)
    for i, x in enumerate(values):
        val_varied[i] = x
    if len(vr_varied):
        s.fmi2SetReal(s.component, vr_varied, len(val_varied), val_varied)
    for fn, vr, val in input_calls:
        getattr(s, fn)(s.component, vr, len(vr), val)
    r._phase = "during initialisation"
    if r.relative_tolerance is None:
        s.fmi2SetupExperiment(s.component, 0, 0.0, start, 1, stop)
    else:
        s.fmi2SetupExperiment(s.component, 1, r.relative_tolerance, start, 1, stop)
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
        if runner.is_model_exchange:
            # fmpy's solver runs the FMU: start values by name, the same for every run but the varied ones
            self._base_values = {n: runner._coerce(runner.variables[n], x)
                                 for n, x in {**self.fixed, **self.inputs}.items()}
            for n in self.outputs:
                runner._lookup(n, ("output", "parameter", "calculatedParameter", "local", "input"), "output")
            return
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
        if r.is_model_exchange:
            return self._call_me(values)
        r._ready()
        s = r._slave
        params = dict(zip(self.varied, values))
        data = np.empty((len(self.times), len(self.outputs)))
        t = 0.0
        try:
            _initialise(r, self._fixed_calls, self._vr_varied, self._val_varied, values, self._input_calls,
                        0.0, self.stop_time)
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


    def _call_me(self, values: Sequence[float]) -> np.ndarray:
        """A model exchange run: fmpy's solver on the runner's reused instance."""
        r = self.runner
        params = dict(zip(self.varied, (float(x) for x in values)))
        data = r._run_me({**self._base_values, **params}, self.times, self.outputs, {**self.fixed, **params})
        if not np.all(np.isfinite(data[-1])):
            bad = [n for n, x in zip(self.outputs, data[-1]) if not math.isfinite(x)]
            r._state = "failed"
            raise RuntimeError(f"{r.model_description.modelName}: non-finite output {', '.join(bad)} at "
                               f"t = {self.times[-1]:.10g} s; parameters {params}")
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
            raise ValueError(f"{runner.fmu_path}: a drive from measured data needs a co-simulation FMU "
                             f"(this one offers model exchange only)")
        runner._validate(fixed, list(outputs), {input_name: 0.0})
        self.runner = runner
        self.varied = list(varied)
        self.fixed = dict(fixed)
        self.outputs = list(outputs)
        self.input_name = input_name
        vs = [runner._lookup(n, ("parameter",), "parameter") for n in self.varied]
        for v in vs:
            if v.type != "Real":
                raise ValueError(f"parameter {v.name!r} is a {v.type}; only Real parameters can be fitted")
        inp = runner._lookup(input_name, ("input",), "input")
        if inp.type != "Real":
            raise ValueError(f"input {input_name!r} is a {inp.type}; the drive must be a Real input")
        cs = runner.model_description.coSimulation
        self.interpolates = bool(getattr(cs, "canInterpolateInputs", False))
        self._fixed_calls = RunPlan._prepared_sets(runner, self.fixed, ("parameter",), "parameter")
        self._vr_varied = (fmi2ValueReference * len(vs))(*[v.valueReference for v in vs])
        self._val_varied = (fmi2Real * len(vs))()
        self._vr_in = (fmi2ValueReference * 1)(inp.valueReference)
        self._val_in = (fmi2Real * 1)()
        self._order = (fmi2Integer * 1)(1)
        outs = [runner._lookup(n, ("output", "parameter", "calculatedParameter", "local"), "output")
                for n in self.outputs]
        if any(o.type != "Real" for o in outs):
            raise ValueError("driven runs read Real outputs only")
        self._vr_out = (fmi2ValueReference * len(outs))(*[o.valueReference for o in outs])
        self._val_out = (fmi2Real * len(outs))()

    def __call__(self, values: Sequence[float], t: np.ndarray, u: np.ndarray) -> np.ndarray:
        r = self.runner
        t = np.asarray(t, dtype=float)
        u = np.asarray(u, dtype=float)
        if t.ndim != 1 or t.shape != u.shape or len(t) < 2 or not np.all(np.diff(t) > 0):
            raise ValueError("the drive needs matching 1-D arrays t, u of at least 2 samples with t increasing")
        r._ready()
        s = r._slave
        params = dict(zip(self.varied, (float(x) for x in values)))
        slopes = np.diff(u) / np.diff(t)
        n_out = len(self.outputs)
        data = np.empty((len(t), n_out))
        vr_out, val_out, vr_in, val_in, order = self._vr_out, self._val_out, self._vr_in, self._val_in, self._order
        ti = float(t[0])
        try:
            val_in[0] = u[0]
            _initialise(r, self._fixed_calls, self._vr_varied, self._val_varied, values,
                        [("fmi2SetReal", vr_in, val_in)], ti, float(t[-1]))
            s.fmi2GetReal(s.component, vr_out, n_out, val_out)
            data[0] = val_out
            set_real, set_der, do_step, get_real = (s.fmi2SetReal, s.fmi2SetRealInputDerivatives,
                                                   s.fmi2DoStep, s.fmi2GetReal)
            comp = s.component
            for k in range(1, len(t)):
                val_in[0] = u[k - 1]
                set_real(comp, vr_in, 1, val_in)
                if self.interpolates:
                    val_in[0] = slopes[k - 1]
                    set_der(comp, vr_in, 1, order, val_in)
                t_next = float(t[k])
                r._phase = f"in the communication step from t = {ti:.10g} s to {t_next:.10g} s"
                do_step(comp, ti, t_next - ti, 1)
                ti = t_next
                get_real(comp, vr_out, n_out, val_out)
                data[k] = val_out
        except Exception as exc:
            raise r._fail(exc, r._phase, {**self.fixed, **params}) from exc
        r._state = "done"
        if not np.all(np.isfinite(data)):
            r._state = "failed"
            raise RuntimeError(f"{r.model_description.modelName}: non-finite output with parameters {params}")
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
    # how the FMU runs (fmu_options of the study); the defaults are a co-simulation FMU's own solver
    interface: str = "auto"                  # auto | co-simulation | model-exchange
    solver: str | None = None                # model exchange: CVode (None) or Euler
    relative_tolerance: float | None = None
    step_size: float | None = None
    # scenario.refine_peaks: peaks and settling times re-sampled this many times finer (fmusa.sampling)
    refine_factor: int | None = None


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
        runner = FMURunner(spec.fmu_path, interface=spec.interface, solver=spec.solver,
                           relative_tolerance=spec.relative_tolerance, step_size=spec.step_size)
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
            if spec.refine_factor and type(plan) is RunPlan:
                from .sampling import refine_run
                metrics = refine_run(spec, plan, fmu_values, data, metrics)
            out.append(RunResult(run_id, tuple(values), metrics, "ok", "", time.perf_counter() - t0))
        except Exception as exc:  # the FMU's own error: record it, keep going
            msg = str(exc).strip().replace("\n", " | ")
            out.append(RunResult(run_id, tuple(values), None, "failed", msg[:2000], time.perf_counter() - t0))
    return out


def _signal_name(num: int) -> str:
    import signal
    try:
        return f"{signal.Signals(num).name}, signal {num}"
    except ValueError:
        return f"signal {num}"


def _worker_main(conn, spec: PlanSpec) -> None:
    """A pool worker: receive chunks, send back one result per run as soon as it is done."""
    import faulthandler
    import signal
    signal.signal(signal.SIGINT, signal.SIG_IGN)   # the parent decides when to stop
    faulthandler.disable()   # a crashing FMU is reported by the parent, not by a Python stack dump
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

    def _start_worker(self) -> _Worker:
        """A new worker process. Inside a daemonic process (a Dask worker, by default) multiprocessing
        refuses to start children; ours are daemonic themselves and exit on the closed pipe when their
        parent dies, so the refusal is lifted while one starts."""
        import multiprocessing as mp
        config = mp.current_process()._config
        daemon = config.get("daemon")
        if not daemon:
            return _Worker(self.ctx, self.spec)
        config["daemon"] = False
        try:
            return _Worker(self.ctx, self.spec)
        finally:
            config["daemon"] = daemon

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
            self.workers.append(self._start_worker())
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
                    reason = (f"the FMU crashed the worker process ({_signal_name(-code)})" if code and code < 0
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
                        if w.conn.poll():      # an answer arrived after wait(): read it next round
                            continue
                        self._replace(w, f"timed out after {self.timeout_s:g} s (the FMU hangs or is too slow; "
                                         f"if only slow, raise execution.timeout_s and rerun without --resume)",
                                      take, now)
            # workers replaced without a chunk left to finish pick up queued chunks
            for w in self.workers:
                if not w.pending and queue:
                    w.give(queue.pop(0), now)

    def _replace(self, w: _Worker, reason: str, take, now: float) -> None:
        run_id, values = w.pending[0]
        rest = w.pending[1:]
        w.kill()
        take([RunResult(run_id, tuple(values), None, "failed", reason, now - w.since)])
        nw = self._start_worker()
        self.workers[self.workers.index(w)] = nw
        if rest:
            nw.give(rest, now)


_DASK_POOLS: dict = {}


def _dask_pool(spec: PlanSpec, timeout_s: float | None) -> WorkerPool:
    """This Dask worker thread's supervised pool (one worker process) for ``spec``, made once. The FMU is
    unpacked once per Dask worker process, so that supervised processes that crash leave no copy behind."""
    import atexit
    import threading

    key = (spec, timeout_s, threading.get_ident())
    pool = _DASK_POOLS.get(key)
    if pool is not None:
        return pool
    local = _DASK_POOLS.get(("unzipped", spec))
    if local is None:
        local = spec
        if Path(spec.fmu_path).is_file():
            import fmpy
            unzipdir = fmpy.extract(spec.fmu_path)
            atexit.register(shutil.rmtree, unzipdir, ignore_errors=True)
            local = replace(spec, fmu_path=unzipdir)
        _DASK_POOLS[("unzipped", spec)] = local
    pool = WorkerPool(local, 1, timeout_s)
    atexit.register(pool.close)
    _DASK_POOLS[key] = pool
    return pool


def run_chunk_supervised(spec: PlanSpec, chunk: Sequence[tuple[int, tuple[float, ...]]],
                         timeout_s: float | None) -> list[RunResult]:
    """A Dask task: run ``chunk`` in a supervised process of this Dask worker, as the local pool does. A run
    that crashes that process, hangs past ``timeout_s`` or fails is recorded as failed with its reason; the
    process is replaced and the chunk goes on, so the Dask worker itself never dies with the FMU."""
    pool = _dask_pool(spec, timeout_s)
    out: list[RunResult] = []
    pool.map(list(chunk), out.extend, max(1, len(chunk)))
    return out


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
        self._unzipdir: str | None = None

    def _local_spec(self) -> PlanSpec:
        """The spec with the FMU unpacked once, here, for this process and its workers: workers that
        crash or are killed cannot clean up a copy of their own."""
        if self._unzipdir is None and Path(self.spec.fmu_path).is_file():
            import fmpy
            self._unzipdir = fmpy.extract(self.spec.fmu_path)
            try:   # sources but no binary for this machine: build once here, not in every worker
                info = read_fmu_info(self._unzipdir)
                iface = select_interface(info, self.spec.interface)
                if not info.has_binary(iface) and info.can_compile:
                    compile_sources(self._unzipdir, info, iface)
            except Exception:
                shutil.rmtree(self._unzipdir, ignore_errors=True)
                self._unzipdir = None
                raise
        if self._unzipdir is None:
            return self.spec
        return replace(self.spec, fmu_path=self._unzipdir)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.close()
            self._pool = None
        if self._unzipdir is not None:
            plan = _WORKER_PLANS.pop(self._local_spec(), None)
            if plan is not None:
                plan.runner.close()
            shutil.rmtree(self._unzipdir, ignore_errors=True)
            self._unzipdir = None
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
            # each task runs its chunk in a supervised process on its Dask worker (crash, hang, error: a
            # failed run, never a dead worker); a task Dask itself loses fails its runs with the reason
            futures, chunks = [], {}
            for c in self._chunks(items, n):
                fut = self._client.submit(run_chunk_supervised, self.spec, c, self.timeout_s, pure=False)
                futures.append(fut)
                chunks[fut.key] = c
            for fut in as_completed(futures):
                try:
                    batch = fut.result()
                except Exception as exc:  # noqa: BLE001 - e.g. KilledWorker: record, go on
                    reason = f"the Dask task failed: {type(exc).__name__}: {str(exc).strip()}"[:2000]
                    batch = [RunResult(rid, tuple(v), None, "failed", reason, 0.0) for rid, v in chunks[fut.key]]
                take(batch)
        elif self.isolate or (self.workers > 1 and len(items) >= self.pool_threshold):
            if self._pool is None:
                self._pool = WorkerPool(self._local_spec(), self.workers, self.timeout_s)
            size = max(1, min(200, len(items) // (self.workers * 8) or 1))
            self._pool.map(items, take, size)
        else:
            spec = self._local_spec()
            for c in self._chunks(items, 1):
                take(run_chunk(spec, c))
        return results
