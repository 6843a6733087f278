"""Build tests/fmus/faulty (a damped oscillator that breaks FMI 2.0 the ways real exports do) into an .fmu.

One binary per fault (``-DFAULT_...``, see faulty.c), its model description written here, so that a test
can also make the description ambiguous (two variables of one name, two names sharing a value reference)
or link the binary against a library that is then removed (a binary that cannot load).

The closed form of the oscillator (``closed_form``) is what a correct run must give.
"""
from __future__ import annotations

import math
import shutil
import subprocess
import zipfile
from pathlib import Path

import fmpy
import numpy as np

SRC = Path(__file__).resolve().parent / "fmus" / "faulty" / "faulty.c"
FMI_HEADERS = Path(fmpy.__file__).resolve().parent / "c-code"

#: (name, value reference, causality, variability, start, description)
VARIABLES = [
    ("m", 0, "parameter", "fixed", 1.0, "mass (kg)"),
    ("k", 1, "parameter", "tunable", 100.0, "stiffness (N/m)"),
    ("d", 2, "parameter", "tunable", 2.0, "damping (N s/m)"),
    ("F", 3, "parameter", "tunable", 10.0, "constant load (N)"),
    ("x0", 4, "parameter", "fixed", 0.5, "initial position (m)"),
    ("h_max", 5, "parameter", "tunable", 1e-3, "longest internal step (s)"),
    ("u", 6, "input", "continuous", 0.0, "load added to F (N)"),
    ("x", 7, "output", "continuous", None, "position (m)"),
    ("v", 8, "output", "continuous", None, "velocity (m/s)"),
    ("x_peak", 9, "output", "continuous", None, "largest |x| so far (m)"),
    ("tolerance_seen", 12, "local", "continuous", None, "the tolerance fmi2SetupExperiment was given (-1: none)"),
]
FAULTS = ("none", "reset_zero", "reset_zeros", "reset_error", "drop_early", "euler")


def closed_form(t: np.ndarray, m: float = 1.0, k: float = 100.0, d: float = 2.0, F: float = 10.0,
                x0: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """x(t), v(t) of m x'' + d x' + k x = F, x(0) = x0, v(0) = 0 (underdamped)."""
    xs = F / k
    w0 = math.sqrt(k / m)
    zeta = d / (2 * math.sqrt(k * m))
    assert zeta < 1, "closed_form covers the underdamped case"
    wd = w0 * math.sqrt(1 - zeta ** 2)
    a = x0 - xs
    b = zeta * w0 * a / wd
    e = np.exp(-zeta * w0 * t)
    x = xs + e * (a * np.cos(wd * t) + b * np.sin(wd * t))
    v = e * ((-zeta * w0 * a + wd * b) * np.cos(wd * t) + (-zeta * w0 * b - wd * a) * np.sin(wd * t))
    return x, v


def _xml(name: str, with_state: bool, me: bool, duplicate: bool, alias: bool, tolerance: float | None) -> str:
    rows = list(VARIABLES)
    if duplicate:     # a second variable named "k" (another value reference): an exporter's bug
        rows.append(("k", 10, "parameter", "tunable", 100.0, "stiffness, again"))
    if alias:         # "load" shares F's value reference: an FMI 2.0 alias
        rows.append(("load", 3, "parameter", "tunable", 10.0, "alias of F"))
    lines = []
    outputs = []
    for i, (vname, vr, causality, variability, start, desc) in enumerate(rows, start=1):
        attrs = f'name="{vname}" valueReference="{vr}" causality="{causality}" variability="{variability}"'
        if causality == "parameter":
            attrs += ' initial="exact"'
        real = f'<Real start="{start!r}"/>' if start is not None else "<Real/>"
        lines.append(f'    <ScalarVariable {attrs} description="{desc}">{real}</ScalarVariable>')
        if causality == "output":
            outputs.append(i)
    state_attrs = ' canGetAndSetFMUstate="true"' if with_state else ""
    me_xml = f'  <ModelExchange modelIdentifier="{name}"{state_attrs}/>\n' if me else ""
    tol = f' tolerance="{tolerance!r}"' if tolerance is not None else ""
    der = ""
    initial = list(outputs)
    if me:   # x and v are the states; der(x) = v, der(v) is a local
        n = len(rows)
        lines.append(f'    <ScalarVariable name="der(v)" valueReference="11" causality="local" '
                     f'variability="continuous"><Real derivative="{outputs[1]}"/></ScalarVariable>')
        lines.append(f'    <ScalarVariable name="der(x)" valueReference="8" causality="local" '
                     f'variability="continuous"><Real derivative="{outputs[0]}"/></ScalarVariable>')
        der = (f'    <Derivatives>\n      <Unknown index="{n + 2}"/>\n      <Unknown index="{n + 1}"/>\n'
               f'    </Derivatives>\n')
        initial += [n + 1, n + 2]
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="2.0" modelName="{name}" guid="{{fa017e00-0000-4000-8000-000000000017}}"
    generationTool="fmusa tests (faulty.c)" variableNamingConvention="flat" numberOfEventIndicators="0">
  <CoSimulation modelIdentifier="{name}" canHandleVariableCommunicationStepSize="true"{state_attrs}/>
{me_xml}  <LogCategories>
    <Category name="logStatusError"/>
    <Category name="logAll"/>
  </LogCategories>
  <DefaultExperiment startTime="0" stopTime="2"{tol}/>
  <ModelVariables>
{chr(10).join(lines)}
  </ModelVariables>
  <ModelStructure>
    <Outputs>
{chr(10).join(f'      <Unknown index="{i}"/>' for i in outputs)}
    </Outputs>
{der}    <InitialUnknowns>
{chr(10).join(f'      <Unknown index="{i}"/>' for i in sorted(initial))}
    </InitialUnknowns>
  </ModelStructure>
</fmiModelDescription>
"""


def build_faulty(dest: Path, fault: str = "none", *, with_state: bool = False, me: bool = True,
                 duplicate: bool = False, alias: bool = False, missing_library: bool = False,
                 log_text: str | None = None, tolerance: float | None = None, name: str = "Faulty") -> Path:
    """``dest``/<name>.fmu with the fault ``fault`` (one of :data:`FAULTS`) compiled in."""
    if fault not in FAULTS:
        raise ValueError(f"unknown fault {fault!r}")
    if shutil.which("gcc") is None:
        import pytest
        pytest.skip("gcc is needed to build the faulty test FMU")
    tree = dest / f"{name}.tree"
    so_dir = tree / "binaries" / fmpy.platform
    so_dir.mkdir(parents=True, exist_ok=True)
    (tree / "modelDescription.xml").write_text(_xml(name, with_state, me, duplicate, alias, tolerance),
                                               encoding="utf-8")
    defines = [] if fault == "none" else [f"-DFAULT_{fault.upper()}"]
    if with_state:
        defines.append("-DWITH_STATE")
    if log_text is not None:
        defines.append(f'-DLOG_TEXT="{log_text}"')
    extra: list[str] = []
    if missing_library:    # linked against a library that is gone when the FMU is loaded
        lib_dir = dest / f"{name}.lib"
        lib_dir.mkdir(exist_ok=True)
        stub = lib_dir / "stub.c"
        stub.write_text("int fmusa_missing_dependency(void) { return 1; }\n", encoding="utf-8")
        lib = lib_dir / "libfmusa_missing_dep.so"
        subprocess.run(["gcc", "-shared", "-fPIC", "-o", str(lib), str(stub)], check=True)
        extra = [f"-L{lib_dir}", "-Wl,--no-as-needed", "-lfmusa_missing_dep", "-Wl,--as-needed"]
    so = so_dir / f"{name}{fmpy.sharedLibraryExtension}"
    cmd = ["gcc", "-std=c99", "-Wall", "-Wextra", "-O2", "-shared", "-fPIC", "-I", str(FMI_HEADERS), *defines,
           str(SRC), "-o", str(so), *extra, "-lm"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"building the faulty FMU failed:\n{' '.join(cmd)}\n{proc.stdout}\n{proc.stderr}")
    if missing_library:
        shutil.rmtree(dest / f"{name}.lib")
    fmu = dest / f"{name}.fmu"
    with zipfile.ZipFile(fmu, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted(tree.rglob("*")):
            if f.is_file():
                z.write(f, f.relative_to(tree).as_posix())
    shutil.rmtree(tree)
    return fmu
