"""The FMI 2.0 contract of dist/ScrewVertebra.fmu, checked with the real FMU through real fmpy (no mocks).

- fmpy's validator finds no problem; the archive holds the model description, the linux64 binary and
  the sources listed in <SourceFiles> with every header they include; the binary needs only libc/libm.
- The sources in the archive rebuild (fmpy.build.build_platform_binary: cmake + gcc) into a binary
  that reproduces the shipped one on the 411 N pullout to 1e-12.
- A second importer, fmpy's container FMU, runs ScrewVertebra as a component and gives the same
  results as simulating it directly; a fixed-step master (doStep(n*h, h)) gets across a load kink that
  its rounded step ends miss by a few ulps.
- The FMI state machine and argument checks: every illegal call returns fmi2Error, is logged with a
  message naming the call or the variable, and fmi2Reset makes the instance usable again.
- The calculated parameters I_1..I_3 are the solid-cylinder moments.
- modelDescription.xml and variables.h are what fmu/generate.py makes from modelica/ScrewVertebra.mo.
"""
from __future__ import annotations

import math
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
import zipfile
from ctypes import byref
from pathlib import Path

import numpy as np
import pytest
from fmpy import calloc, extract, free, read_model_description, simulate_fmu
from fmpy.fmi1 import FMICallException, printLogMessage
from fmpy.fmi2 import (
    FMU2Slave,
    fmi2CallbackAllocateMemoryTYPE,
    fmi2CallbackFreeMemoryTYPE,
    fmi2CallbackFunctions,
    fmi2CallbackLoggerTYPE,
    fmi2LastSuccessfulTime,
)
from fmpy.logging import addLoggerProxy
from fmpy.validation import validate_fmu

import contract

ROOT = Path(__file__).resolve().parents[1]
MODEL = "ScrewVertebra"
SO_PATH = f"binaries/linux64/{MODEL}.so"
FMI2_OK, FMI2_ERROR = 0, 3

# The only shared libraries the binary may need (plus the kernel's vDSO that ldd lists).
ALLOWED_LIBS = {"libc.so.6", "libm.so.6", "ld-linux-x86-64.so.2", "linux-vdso.so.1"}

# The FMI 2.0 co-simulation API every binary must export.
FMI2_CS_FUNCTIONS = """fmi2GetTypesPlatform fmi2GetVersion fmi2SetDebugLogging fmi2Instantiate fmi2FreeInstance
fmi2SetupExperiment fmi2EnterInitializationMode fmi2ExitInitializationMode fmi2Terminate fmi2Reset fmi2GetReal
fmi2GetInteger fmi2GetBoolean fmi2GetString fmi2SetReal fmi2SetInteger fmi2SetBoolean fmi2SetString
fmi2GetFMUstate fmi2SetFMUstate fmi2FreeFMUstate fmi2SerializedFMUstateSize fmi2SerializeFMUstate
fmi2DeSerializeFMUstate fmi2GetDirectionalDerivative fmi2SetRealInputDerivatives fmi2GetRealOutputDerivatives
fmi2DoStep fmi2CancelStep fmi2GetStatus fmi2GetRealStatus fmi2GetIntegerStatus fmi2GetBooleanStatus
fmi2GetStringStatus""".split()

# The paper's pullout, shortened: 411 N ramped over 50 ms, one communication step to 0.2 s.
PULLOUT = {"F_max": 411.0, "t_ramp": 0.05}
PULLOUT_STOP = 0.2
PULLOUT_OUTPUTS = ("y_max", "v_y_max", "t_eq")


# ---------------------------------------------------------------------------------------------- fixtures

@pytest.fixture(scope="module")
def fmu(fmu_path, tmp_path_factory) -> Path:
    """A private copy of dist/ScrewVertebra.fmu (conftest's fmu_path runs `make fmu` when it is
    missing), so that a rebuild of dist/ during the session cannot mix two versions in this module."""
    copy = tmp_path_factory.mktemp("fmu") / f"{MODEL}.fmu"
    shutil.copyfile(fmu_path, copy)
    return copy


@pytest.fixture(scope="module")
def md(fmu):
    return read_model_description(str(fmu))


@pytest.fixture(scope="module")
def vrs(md) -> dict[str, int]:
    return {v.name: v.valueReference for v in md.modelVariables}


@pytest.fixture(scope="module")
def unzipdir(fmu, tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("unzipped")
    extract(str(fmu), unzipdir=str(d))
    return d


# Keeps fmpy's default console logger alive for restoring it (see LogCapture.close).
_DEFAULT_LOGGER = fmi2CallbackLoggerTYPE(printLogMessage)


class LogCapture:
    """fmi2CallbackFunctions whose logger records (status, category, message) with the message
    formatted. The formatting goes through fmpy's native proxy (ctypes cannot receive the variadic
    arguments); that proxy keeps one process-wide target, which close() points back at fmpy's
    console logger."""

    def __init__(self):
        self.messages: list[tuple[int, str, str]] = []
        self._py_logger = fmi2CallbackLoggerTYPE(self._log)
        self.callbacks = fmi2CallbackFunctions()
        self.callbacks.logger = self._py_logger
        self.callbacks.allocateMemory = fmi2CallbackAllocateMemoryTYPE(calloc)
        self.callbacks.freeMemory = fmi2CallbackFreeMemoryTYPE(free)
        addLoggerProxy(byref(self.callbacks))

    def _log(self, env, instance_name, status, category, message):
        self.messages.append((status, (category or b"").decode(), (message or b"").decode()))

    def errors(self) -> list[str]:
        return [m for s, _, m in self.messages if s >= FMI2_ERROR]

    def close(self):
        restore = fmi2CallbackFunctions()
        restore.logger = _DEFAULT_LOGGER
        addLoggerProxy(byref(restore))


@pytest.fixture(scope="module")
def log():
    capture = LogCapture()
    yield capture
    capture.close()


def new_slave(unzipdir: Path, md, log: LogCapture | None = None, guid: str | None = None,
              name: str = "sv") -> FMU2Slave:
    slave = FMU2Slave(guid=guid or md.guid, unzipDirectory=str(unzipdir),
                      modelIdentifier=md.coSimulation.modelIdentifier, instanceName=name)
    slave.instantiate(callbacks=log.callbacks if log else None)
    return slave


def run_pullout(slave: FMU2Slave, vrs) -> dict[str, float]:
    """From a freshly instantiated (or reset) slave: the 411 N pullout in one doStep."""
    slave.setupExperiment(startTime=0.0, stopTime=PULLOUT_STOP)
    slave.enterInitializationMode()
    slave.setReal([vrs[k] for k in PULLOUT], list(PULLOUT.values()))
    slave.exitInitializationMode()
    slave.doStep(currentCommunicationPoint=0.0, communicationStepSize=PULLOUT_STOP)
    out = dict(zip(PULLOUT_OUTPUTS, slave.getReal([vrs[k] for k in PULLOUT_OUTPUTS])))
    out["n_steps"] = slave.getInteger([vrs["n_steps"]])[0]
    return out


@pytest.fixture(scope="module")
def shipped_pullout(unzipdir, md, vrs) -> dict[str, float]:
    slave = new_slave(unzipdir, md)
    try:
        result = run_pullout(slave, vrs)
        slave.terminate()
    finally:
        slave.freeInstance()
    # the case must be a real one: the screw moved and came to rest within the run
    assert result["y_max"] > 0 and result["v_y_max"] > 0 and 0 < result["t_eq"] < PULLOUT_STOP, result
    return result


def rel_diff(a: float, b: float) -> float:
    return abs(a - b) / max(abs(a), abs(b)) if a != b else 0.0


# ---------------------------------------------------------------------------------------------- archive

def test_validate_fmu(fmu):
    problems = validate_fmu(str(fmu))
    assert problems == [], "\n".join(problems)


def _quoted_includes(text: str) -> list[str]:
    return re.findall(r'^\s*#\s*include\s*"([^"]+)"', text, flags=re.MULTILINE)


def test_archive_contents(fmu):
    with zipfile.ZipFile(fmu) as z:
        names = set(z.namelist())
        assert "modelDescription.xml" in names
        assert SO_PATH in names
        root = ET.fromstring(z.read("modelDescription.xml"))
        listed = [f.get("name") for f in root.findall("./CoSimulation/SourceFiles/File")]
        assert listed, "<SourceFiles> lists no file"
        missing = [f for f in listed if f"sources/{f}" not in names]
        assert not missing, f"<SourceFiles> entries missing under sources/: {missing}"
        # every header a listed source includes, transitively, must be under sources/
        seen, todo, absent = set(), list(listed), []
        while todo:
            f = todo.pop()
            if f in seen:
                continue
            seen.add(f)
            if f"sources/{f}" not in names:
                absent.append(f)
                continue
            todo.extend(_quoted_includes(z.read(f"sources/{f}").decode()))
        assert not absent, f'headers included with #include "..." but not under sources/: {sorted(absent)}'
        assert {"fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h"} <= seen, sorted(seen)


def test_binary_dependencies(unzipdir):
    so = unzipdir / SO_PATH
    dyn = subprocess.run(["readelf", "-d", "-W", str(so)], check=True, capture_output=True, text=True).stdout
    needed = re.findall(r"\(NEEDED\)\s+Shared library: \[([^\]]+)\]", dyn)
    assert needed, dyn
    assert set(needed) <= ALLOWED_LIBS, f"NEEDED entries beyond libc/libm: {sorted(set(needed) - ALLOWED_LIBS)}"
    # the loader's view: the transitive closure too
    ldd = subprocess.run(["ldd", str(so)], check=True, capture_output=True, text=True).stdout
    loaded = []
    for line in ldd.splitlines():
        assert "not found" not in line, ldd
        first = line.split()[0]
        loaded.append(Path(first).name)
    assert set(loaded) <= ALLOWED_LIBS, f"ldd lists libraries beyond libc/libm: {ldd}"
    # and it exports the whole FMI 2.0 co-simulation API
    syms = subprocess.run(["readelf", "--dyn-syms", "-W", str(so)], check=True, capture_output=True,
                          text=True).stdout
    exported = {m.group(1) for m in re.finditer(r"\sFUNC\s+GLOBAL\s+DEFAULT\s+\d+\s+(\w+)", syms)}
    assert not set(FMI2_CS_FUNCTIONS) - exported, sorted(set(FMI2_CS_FUNCTIONS) - exported)


# ---------------------------------------------------------------------------------------------- rebuild

def test_rebuild_from_sources(fmu, md, vrs, shipped_pullout, tmp_path):
    from fmpy.build import build_platform_binary

    rebuilt = tmp_path / "rebuilt"
    with zipfile.ZipFile(fmu) as z:
        z.extractall(rebuilt)
    shutil.rmtree(rebuilt / "binaries")
    build_dir = tmp_path / "cmake-build"
    build_dir.mkdir()
    build_platform_binary(rebuilt.resolve(), build_dir=build_dir)   # cmake + the system's C compiler
    so = rebuilt / SO_PATH
    assert so.is_file(), f"no {SO_PATH} after build_platform_binary"

    slave = new_slave(rebuilt, md, name="rebuilt")
    try:
        assert Path(slave.dll._name).resolve() == so.resolve()   # the rebuilt binary, not the shipped one
        result = run_pullout(slave, vrs)
        slave.terminate()
    finally:
        slave.freeInstance()
    diffs = {k: rel_diff(result[k], shipped_pullout[k]) for k in PULLOUT_OUTPUTS}
    assert max(diffs.values()) <= 1e-12, (
        f"rebuilt vs shipped: relative differences {diffs}\nrebuilt {result}\nshipped {shipped_pullout}")


# ---------------------------------------------------------------------------------------------- container

CONTAINER_PARAMS = {"c_y": 500000.0, "d_y": 300.0, "t_ramp": 0.05}
CONTAINER_OUTPUTS = ["y", "v_y", "y_max", "t_eq"]
# With 0.005 the container's fixed steps doStep(n*h, h) leave the component 4e-18 s short of the load
# kink at t_ramp = 0.05 (see test_fixed_step_master_across_a_load_kink): the importer's way of stepping.
CONTAINER_DT = 0.005
CONTAINER_STOP = 0.2


def test_container_fmu(fmu, md, tmp_path):
    from fmpy.container_fmu.cli import create_container_fmu
    from fmpy.container_fmu.config import Component, Configuration
    from fmpy.model_description import CoSimulation, DefaultExperiment, ModelDescription, ModelVariable

    comp_vars = {v.name: v for v in md.modelVariables}
    component = Component(name="screw", filename=fmu, modelDescription=md)
    # The container numbers its variables in this order; the first must be the independent time.
    variables = [ModelVariable(type="Real", variability="continuous", causality="independent", name="time")]
    mappings = {}
    for name in CONTAINER_PARAMS:
        v = ModelVariable(type="Real", variability="fixed", causality="parameter", initial="exact", name=name,
                          start=comp_vars[name].start)
        variables.append(v)
        mappings[v] = [(component, comp_vars[name])]
    for name in CONTAINER_OUTPUTS:
        v = ModelVariable(type="Real", variability="continuous", causality="output", initial="calculated",
                          name=name)
        variables.append(v)
        mappings[v] = [(component, comp_vars[name])]
    container_md = ModelDescription(
        fmiVersion="2.0", modelName="ScrewVertebraContainer",
        instantiationToken="{5c1e3b0a-0d7e-4b8e-9a51-6f0c2a7d9e11}",
        defaultExperiment=DefaultExperiment(stopTime=str(CONTAINER_STOP), stepSize=str(CONTAINER_DT)),
        coSimulation=CoSimulation(fixedInternalStepSize=CONTAINER_DT),
        modelVariables=variables)
    config = Configuration(parallelDoStep=False, modelDescription=container_md, components=[component],
                           connections=[], variableMappings=mappings)
    work = tmp_path / "container"
    work.mkdir()
    container = tmp_path / "ScrewVertebraContainer.fmu"
    create_container_fmu(config, work, container)

    common = dict(stop_time=CONTAINER_STOP, output_interval=CONTAINER_DT, start_values=CONTAINER_PARAMS,
                  output=CONTAINER_OUTPUTS)
    via_container = simulate_fmu(str(container), **common)
    direct = simulate_fmu(str(fmu), **common)

    assert len(via_container) == len(direct) == round(CONTAINER_STOP / CONTAINER_DT) + 1
    np.testing.assert_allclose(via_container["time"], direct["time"], rtol=1e-12, atol=0)
    # the parameters reached the component: the static deflection is F_max / c_y, not the default's
    f_max = float(comp_vars["F_max"].start)
    assert via_container["y"][-1] == pytest.approx(f_max / CONTAINER_PARAMS["c_y"], rel=1e-6)
    assert via_container["t_eq"][-1] > 0

    # The two runs end their steps at times a few ulps apart (fmpy: time + (next - time); container:
    # n*h + h), so the solver's internal steps differ slightly and agreement is to the solver's
    # tolerance: relative to each signal's range, and pointwise for the time t_eq.
    report = {}
    for name in CONTAINER_OUTPUTS:
        a, b = via_container[name], direct[name]
        scale = np.max(np.abs(b))
        assert scale > 0, name
        report[name] = float(np.max(np.abs(a - b)) / scale)
    a, b = via_container["t_eq"], direct["t_eq"]
    report["t_eq pointwise"] = max(rel_diff(float(x), float(y)) for x, y in zip(a, b))
    assert max(report.values()) <= 1e-9, f"container vs direct, relative differences: {report}"


def test_fixed_step_master_across_a_load_kink(unzipdir, md, vrs, log):
    """The usual fixed-step master calls doStep(n*h, h), so the FMU's own time after step n-1 is
    (n-1)*h + h, which can fall a few ulps short of n*h: 0.045 + 0.005 = 0.049999999999999996, just
    before the kink at t_ramp = 0.05 (fmpy's container FMU steps this way). Every step must be taken
    (a communication point within rounding of the FMU's time is the same point), and the result must
    match stepping to exactly representable ends."""
    h, n = 0.005, 20
    results = []
    for fixed_master in (True, False):
        slave = new_slave(unzipdir, md, log, name="kink")
        try:
            slave.setupExperiment(startTime=0.0, stopTime=n * h)
            slave.enterInitializationMode()
            slave.setReal([vrs["t_ramp"]], [0.05])
            slave.exitInitializationMode()
            del log.messages[:]
            t = 0.0
            for i in range(n):
                cp = i * h if fixed_master else t
                step = h if fixed_master else (i + 1) * h - t
                try:
                    slave.doStep(currentCommunicationPoint=cp, communicationStepSize=step)
                except FMICallException as e:
                    pytest.fail(f"doStep({cp!r}, {step!r}) failed: {e}; log: {log.errors()}")
                t = (i + 1) * h
            results.append(slave.getReal([vrs["y"], vrs["y_max"], vrs["t_eq"]]))
            slave.terminate()
        finally:
            slave.freeInstance()
    (y_a, ymax_a, teq_a), (y_b, ymax_b, teq_b) = results
    assert teq_a > 0 and teq_b > 0
    assert rel_diff(y_a, y_b) <= 1e-9 and rel_diff(ymax_a, ymax_b) <= 1e-9 and abs(teq_a - teq_b) <= 1e-9


# ---------------------------------------------------------------------------------------------- state machine

def _offending_calls():
    """name -> (offending action(slave, vrs), regexes the logged error must match)."""

    def do_step_before_init(s, vrs):
        s.doStep(currentCommunicationPoint=0.0, communicationStepSize=0.1)

    def set_output(s, vrs):
        s.setupExperiment(startTime=0.0)
        s.enterInitializationMode()
        s.exitInitializationMode()
        s.setReal([vrs["y"]], [1e-3])

    def set_calculated_parameter(s, vrs):
        s.setReal([vrs["I_1"]], [1e-9])

    def set_parameter_after_init(s, vrs):
        s.setupExperiment(startTime=0.0)
        s.enterInitializationMode()
        s.exitInitializationMode()
        s.setReal([vrs["c_y"]], [1e5])

    def wrong_communication_point(s, vrs):
        s.setupExperiment(startTime=0.0)
        s.enterInitializationMode()
        s.exitInitializationMode()
        s.doStep(currentCommunicationPoint=0.0, communicationStepSize=0.01)
        s.doStep(currentCommunicationPoint=0.5, communicationStepSize=0.01)

    def negative_step(s, vrs):
        s.setupExperiment(startTime=0.0)
        s.enterInitializationMode()
        s.exitInitializationMode()
        s.doStep(currentCommunicationPoint=0.0, communicationStepSize=-0.01)

    return {
        "doStep-before-initialization": (do_step_before_init, [r"fmi2DoStep"]),
        "setReal-on-output-y": (set_output, [r"fmi2SetReal", r"(?<![\w\[])y(?![\w\[])"]),
        "setReal-on-calculatedParameter-I_1": (set_calculated_parameter, [r"fmi2SetReal", r"\bI_1\b"]),
        "setReal-on-parameter-after-exitInitializationMode": (set_parameter_after_init,
                                                              [r"fmi2SetReal", r"\bc_y\b"]),
        "doStep-wrong-currentCommunicationPoint": (wrong_communication_point,
                                                   [r"fmi2DoStep", r"currentCommunicationPoint"]),
        "doStep-negative-step": (negative_step, [r"fmi2DoStep", r"communicationStepSize"]),
    }


OFFENDING = _offending_calls()


@pytest.mark.parametrize("case", list(OFFENDING))
def test_illegal_call_is_an_error_logged_and_reset_recovers(case, unzipdir, md, vrs, log, shipped_pullout):
    action, patterns = OFFENDING[case]
    slave = new_slave(unzipdir, md, log, name=f"sv-{case}")
    try:
        del log.messages[:]
        with pytest.raises(FMICallException) as info:
            action(slave, vrs)
        assert info.value.status == FMI2_ERROR, f"{info.value} (expected fmi2Error)"
        errors = log.errors()
        assert errors, f"no error was logged; messages: {log.messages}"
        assert any(all(re.search(p, m) for p in patterns) for m in errors), (
            f"no logged error matches {patterns}: {errors}")
        # the offending call changed nothing it should not have
        if case == "setReal-on-parameter-after-exitInitializationMode":
            assert slave.getReal([vrs["c_y"]])[0] == float(md_start(md, "c_y"))
        if case == "setReal-on-output-y":
            assert slave.getReal([vrs["y"]])[0] == 0.0

        # fmi2Reset brings the instance back: the normal case reproduces a fresh instance bit for bit
        assert slave.reset() == FMI2_OK
        del log.messages[:]
        result = run_pullout(slave, vrs)
        assert log.errors() == [], log.messages
        assert result == shipped_pullout, f"after reset {result} != fresh instance {shipped_pullout}"
        slave.terminate()
    finally:
        slave.freeInstance()


def md_start(md, name):
    return next(v.start for v in md.modelVariables if v.name == name)


def test_wrong_guid_is_refused(unzipdir, md, log):
    wrong = "{00000000-0000-0000-0000-000000000000}"
    assert wrong != md.guid
    slave = FMU2Slave(guid=wrong, unzipDirectory=str(unzipdir), modelIdentifier=MODEL, instanceName="bad-guid")
    try:
        del log.messages[:]
        with pytest.raises(Exception, match="Failed to instantiate"):
            slave.instantiate(callbacks=log.callbacks)
        assert slave.component is None      # fmi2Instantiate returned NULL
        assert any("fmi2Instantiate" in m and "GUID" in m and wrong in m for m in log.errors()), log.messages
    finally:
        slave.freeLibrary()


def test_last_successful_time(unzipdir, md, vrs, log):
    slave = new_slave(unzipdir, md, log, name="status")
    try:
        slave.setupExperiment(startTime=0.0, stopTime=1.0)
        slave.enterInitializationMode()
        slave.setReal([vrs["t_ramp"]], [0.05])
        slave.exitInitializationMode()
        assert slave.getRealStatus(fmi2LastSuccessfulTime) == 0.0
        slave.doStep(currentCommunicationPoint=0.0, communicationStepSize=0.05)
        slave.doStep(currentCommunicationPoint=0.05, communicationStepSize=0.05)
        assert slave.getRealStatus(fmi2LastSuccessfulTime) == pytest.approx(0.1, rel=1e-15)
        # a refused step does not move it
        with pytest.raises(FMICallException):
            slave.doStep(currentCommunicationPoint=0.3, communicationStepSize=0.05)
        assert slave.getRealStatus(fmi2LastSuccessfulTime) == pytest.approx(0.1, rel=1e-15)
        slave.reset()
    finally:
        slave.freeInstance()


# ---------------------------------------------------------------------------------------------- inertia

@pytest.mark.parametrize("params", [{}, {"m": 1.0e-3, "L_screw": 0.03, "D_screw": 0.005}],
                         ids=["Table1", "custom"])
def test_calculated_inertia_is_solid_cylinder(params, unzipdir, md, vrs):
    slave = new_slave(unzipdir, md, name="inertia")
    try:
        slave.setupExperiment(startTime=0.0)
        slave.enterInitializationMode()
        if params:
            slave.setReal([vrs[k] for k in params], list(params.values()))
        slave.exitInitializationMode()
        i1, i2, i3 = slave.getReal([vrs["I_1"], vrs["I_2"], vrs["I_3"]])
        m, length, diameter = slave.getReal([vrs["m"], vrs["L_screw"], vrs["D_screw"]])
        slave.terminate()
    finally:
        slave.freeInstance()
    for k, v in params.items():
        assert {"m": m, "L_screw": length, "D_screw": diameter}[k] == v
    r = diameter / 2
    transverse = m * (3 * r ** 2 + length ** 2) / 12
    axial = m * r ** 2 / 2
    assert math.isclose(i1, transverse, rel_tol=1e-14), (i1, transverse)
    assert math.isclose(i2, axial, rel_tol=1e-14), (i2, axial)
    assert math.isclose(i3, transverse, rel_tol=1e-14), (i3, transverse)


# ---------------------------------------------------------------------------------------------- single source

def test_model_description_is_generated_from_the_modelica_source(fmu, tmp_path):
    names = [v.name for v in contract.variables()]
    assert len(names) >= 118                                                   # not vacuous
    with zipfile.ZipFile(fmu) as z:
        shipped_xml = z.read("modelDescription.xml")
        shipped_header = z.read("sources/variables.h")
    root = ET.fromstring(shipped_xml)
    xml_names = [sv.get("name") for sv in root.findall("./ModelVariables/ScalarVariable")]
    assert xml_names == names
    vrs = [int(sv.get("valueReference")) for sv in root.findall("./ModelVariables/ScalarVariable")]
    assert vrs == list(range(1, len(names) + 1))
    # and the generator, run now on the Modelica source, reproduces the shipped files byte for byte
    subprocess.run([sys.executable, str(ROOT / "fmu" / "generate.py"), str(tmp_path)], check=True)
    assert (tmp_path / "modelDescription.xml").read_bytes() == shipped_xml, \
        "dist FMU's modelDescription.xml differs from fmu/generate.py's output: stale FMU? (make fmu)"
    assert (tmp_path / "sources" / "variables.h").read_bytes() == shipped_header


def test_c_code_uses_only_value_references_of_the_contract(fmu):
    """Every VR_<name> (and V(<name>), model.c's shorthand for mi->v[VR_<name>]) in the C sources the FMU
    ships is a variable of variables.h (an unknown one also fails the compile, this names it), and the
    arrays the C code indexes as VR_tab_y_1 + k have consecutive value references."""
    with zipfile.ZipFile(fmu) as z:
        header = z.read("sources/variables.h").decode()
        code = {n: z.read(n).decode() for n in z.namelist()
                if n.startswith("sources/") and n.endswith((".c", ".h")) and n != "sources/variables.h"}
    defined = {m[1]: int(m[2]) for m in re.finditer(r"^#define VR_(\w+) (\d+)$", header, flags=re.M)}
    assert len(defined) == len(contract.variables())
    used: dict[str, set[str]] = {}
    for name, text in code.items():
        text = re.sub(r"/\*.*?\*/|//[^\n]*", "", text, flags=re.S)          # not in comments
        for ref in re.findall(r"\bVR_(\w+)", text) + re.findall(r"\bV\((\w+)\)", text):
            used.setdefault(ref, set()).add(name)
    used.pop("name", None)                                  # the macro's own parameter: #define V(name) ... VR_##name
    used.pop("sens_", None)     # VR_sens_##name##_1: the sensitivity outputs of each name in SV_SENS_OUTPUTS
    assert {"c_y", "tab_y_1", "t_eq", "rtol"} <= set(used)                    # not vacuous
    unknown = {ref: sorted(files) for ref, files in used.items() if ref not in defined}
    assert not unknown, f"value references the C code uses that variables.h does not define: {unknown}"
    for v in contract.variables():
        m = re.fullmatch(r"(\w+)\[(\d+)\]", v.name)
        if m:
            assert v.vr == defined[f"{m[1]}_1"] + int(m[2]) - 1, f"{v.name}: not consecutive with {m[1]}[1]"
