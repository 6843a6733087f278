"""The test-function FMU (tests/fmus/testfunc: Ishigami, Sobol's G, a linear sum of x1 ... x8), built with gcc
against fmpy's FMI 2 headers, the closed forms of their Sobol indices, and study files for it as a user
writes them."""
from __future__ import annotations

import math
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from c_fmus import FMI_HEADERS

HERE = Path(__file__).resolve().parent
SOURCE = HERE / "fmus" / "testfunc" / "testfunc.c"
NX = 8


def _description() -> str:
    rows = []
    names = [f"x{i}" for i in range(1, NX + 1)] + [f"a{i}" for i in range(1, NX + 1)] + ["A", "B"]
    starts = ["0"] * (2 * NX) + ["7", "0.1"]
    for vr, (name, start) in enumerate(zip(names, starts)):
        rows.append(f'<ScalarVariable name="{name}" valueReference="{vr}" causality="parameter" '
                    f'variability="tunable" initial="exact"><Real start="{start}"/></ScalarVariable>')
    for vr, name in ((18, "ishigami"), (19, "gfun"), (20, "linear")):
        rows.append(f'<ScalarVariable name="{name}" valueReference="{vr}" causality="output" '
                    f'variability="continuous" initial="calculated"><Real/></ScalarVariable>')
    first_out = len(names) + 1
    outs = "".join(f'<Unknown index="{first_out + i}"/>' for i in range(3))
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="2.0" modelName="TestFunc" guid="{{5b1e9a4c-0d7f-4e2a-8c3b-testfunc0001}}"
  description="Test functions with known Sobol indices (a test fixture of fmusa)"
  generationTool="hand-written (tests/fmus/testfunc)" variableNamingConvention="flat" numberOfEventIndicators="0">
  <CoSimulation modelIdentifier="TestFunc" canHandleVariableCommunicationStepSize="true"
    canNotUseMemoryManagementFunctions="true"/>
  <DefaultExperiment startTime="0" stopTime="1"/>
  <ModelVariables>
{chr(10).join(rows)}
  </ModelVariables>
  <ModelStructure>
    <Outputs>{outs}</Outputs>
    <InitialUnknowns>{outs}</InitialUnknowns>
  </ModelStructure>
</fmiModelDescription>
"""


def build_testfunc(root: Path) -> Path:
    """tests/fmus/testfunc built and zipped as ``root``/TestFunc.fmu."""
    if not sys.platform.startswith("linux"):
        pytest.skip("the test FMUs are built as linux64 binaries")
    if shutil.which("gcc") is None:
        pytest.skip("gcc is needed to build the test FMU tests/fmus/testfunc")
    tree = root / "tree"
    so = tree / "binaries" / "linux64" / "TestFunc.so"
    so.parent.mkdir(parents=True, exist_ok=True)
    cmd = ["gcc", "-std=c99", "-Wall", "-O1", "-shared", "-fPIC", "-I", str(FMI_HEADERS), str(SOURCE), "-o",
           str(so), "-lm"]
    proc = subprocess.run(cmd, capture_output=True, text=True, encoding="utf-8", errors="replace")
    if proc.returncode != 0:
        pytest.fail(f"building the test-function FMU failed:\n{' '.join(cmd)}\n{proc.stdout}\n{proc.stderr}")
    (tree / "modelDescription.xml").write_text(_description(), encoding="utf-8")
    fmu = root / "TestFunc.fmu"
    with zipfile.ZipFile(fmu, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted(tree.rglob("*")):
            if f.is_file():
                z.write(f, f.relative_to(tree).as_posix())
    return fmu


# ---------------------------------------------------------------------------- closed forms
def ishigami_indices(a: float = 7.0, b: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """(S1, ST) of x1, x2, x3 of the Ishigami function, x uniform on [-π, π] (Sobol and Levitan 1999)."""
    pi = math.pi
    v1 = 0.5 * (1 + b * pi ** 4 / 5) ** 2
    v2 = a ** 2 / 8
    v13 = b ** 2 * pi ** 8 * (1 / 18 - 1 / 50)
    v = v1 + v2 + v13
    return np.array([v1, v2, 0.0]) / v, np.array([v1 + v13, v2, v13]) / v


def g_indices(a) -> tuple[np.ndarray, np.ndarray]:
    """(S1, ST) of Sobol's G function with coefficients ``a``, x uniform on [0, 1]."""
    a = np.asarray(a, dtype=float)
    vi = 1 / (3 * (1 + a) ** 2)
    v = np.prod(1 + vi) - 1
    st = np.array([vi[i] * np.prod(np.delete(1 + vi, i)) for i in range(len(a))]) / v
    return vi / v, st


# ---------------------------------------------------------------------------- study files
def study_text(fmu: Path, output: str, k: int, lo: float, hi: float, methods: str, extra: str = "",
               fixed: dict | None = None, workers: int = 2) -> str:
    """A study file over x1 ... xk (uniform on [lo, hi]) of one output of the test-function FMU."""
    params = "\n".join(f"      x{i}: {{variable: x{i}, bounds: [{lo!r}, {hi!r}]}}" for i in range(1, k + 1))
    fixed_text = "".join(f"\n  {n}: {v!r}" for n, v in (fixed or {}).items())
    return f"""name: testfunc
fmu: {fmu}
parameters:
  p: {{variable: x8}}
fixed:
  A: 7{fixed_text}
scenario:
  stop_time: 1
  step: null
metrics:
  y:
    output: {output}
    reduce: final
stages:
  sensitivity:
    methods: {methods}
    seed: 1
    outputs: [y]
{extra}
    parameters:
{params}
execution:
  workers: {workers}
"""
