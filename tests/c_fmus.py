"""Small C FMUs for the tests, built with gcc against fmpy's FMI 2 headers and zipped as .fmu files.

``leaky_fmu`` builds tests/fmus/leaky (a spring y = F/k that leaks ``leak_mb`` MB per fmi2DoStep and fails
with a non-ASCII message while fail_lo <= k <= fail_hi), optionally with ``extra`` more parameters in its
model description (a description of 200k variables, as some exported models have).
"""
from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

import fmpy

HERE = Path(__file__).resolve().parent
LEAKY = HERE / "fmus" / "leaky"
FMI_HEADERS = Path(fmpy.__file__).resolve().parent / "c-code"

_VARIABLES = [   # name, value reference, causality, start, description
    ("k", 0, "parameter", "1e6", "Spring stiffness"),
    ("F", 1, "parameter", "411", "Static load"),
    ("leak_mb", 2, "parameter", "0", "MB leaked (allocated, touched, never freed) by every fmi2DoStep"),
    ("fail_lo", 3, "parameter", "0", "Lower end of the k band in which fmi2DoStep fails"),
    ("fail_hi", 4, "parameter", "-1", "Upper end of the k band in which fmi2DoStep fails"),
    ("y", 5, "output", None, "Displacement y = F/k"),
    ("y_peak", 6, "output", None, "Largest |y| over the run"),
    ("crash_above_mb", 7, "parameter", "0", "fmi2DoStep aborts once the process has leaked more (0: never)"),
]


def leaky_description(extra: int = 0) -> str:
    """The model description of the leaky FMU, with ``extra`` unused parameters ``p_1`` … after its own."""
    rows = []
    for name, vr, causality, start, desc in _VARIABLES:
        if causality == "parameter":
            rows.append(f'<ScalarVariable name="{name}" valueReference="{vr}" description="{desc}" '
                        f'causality="parameter" variability="tunable" initial="exact"><Real start="{start}"/>'
                        f'</ScalarVariable>')
        else:
            rows.append(f'<ScalarVariable name="{name}" valueReference="{vr}" description="{desc}" '
                        f'causality="output" variability="continuous" initial="calculated"><Real/></ScalarVariable>')
    rows += [f'<ScalarVariable name="p_{i}" valueReference="{1000 + i}" causality="parameter" '
             f'variability="tunable" initial="exact"><Real start="0"/></ScalarVariable>' for i in range(1, extra + 1)]
    out_index = [i + 1 for i, v in enumerate(_VARIABLES) if v[2] == "output"]
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="2.0" modelName="Leaky" guid="{{8a0c5e1d-3f2b-4c6a-9d7e-leaky0000000}}"
  description="Spring y = F/k that leaks memory and fails with a non-ASCII message (a test fixture of fmusa)"
  generationTool="hand-written (tests/fmus/leaky)" variableNamingConvention="flat" numberOfEventIndicators="0">
  <CoSimulation modelIdentifier="Leaky" canHandleVariableCommunicationStepSize="true"
    canNotUseMemoryManagementFunctions="true" canGetAndSetFMUstate="false" canSerializeFMUstate="false"/>
  <LogCategories><Category name="logStatusError"/></LogCategories>
  <DefaultExperiment startTime="0" stopTime="1" stepSize="0.5"/>
  <ModelVariables>
{chr(10).join(rows)}
  </ModelVariables>
  <ModelStructure>
    <Outputs>{"".join(f'<Unknown index="{i}"/>' for i in out_index)}</Outputs>
    <InitialUnknowns>{"".join(f'<Unknown index="{i}"/>' for i in out_index)}</InitialUnknowns>
  </ModelStructure>
</fmiModelDescription>
"""


def compile_linux64(source: Path, so: Path, defines: tuple[str, ...] = (), what: str = "test FMU") -> None:
    """A test FMU's C file built as its linux64 binary (skipped off Linux or without gcc, failed with gcc's words)."""
    if not sys.platform.startswith("linux"):
        pytest.skip("the test FMUs are built as linux64 binaries")
    if shutil.which("gcc") is None:
        pytest.skip(f"gcc is needed to build the {what} {source}")
    so.parent.mkdir(parents=True, exist_ok=True)
    cmd = ["gcc", "-std=c99", "-Wall", "-O1", "-shared", "-fPIC", *(f"-D{d}" for d in defines), "-I",
           str(FMI_HEADERS), str(source), "-o", str(so), "-lm"]
    proc = subprocess.run(cmd, capture_output=True, text=True, encoding="utf-8", errors="replace")
    if proc.returncode != 0:
        pytest.fail(f"building the {what} failed:\n{' '.join(cmd)}\n{proc.stdout}\n{proc.stderr}")


def zip_tree(tree: Path, fmu: Path) -> Path:
    """An FMU's unpacked tree zipped as ``fmu``."""
    with zipfile.ZipFile(fmu, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted(tree.rglob("*")):
            if f.is_file():
                z.write(f, f.relative_to(tree).as_posix())
    return fmu


def build_leaky(root: Path, extra: int = 0, binary: Path | None = None, defines: tuple[str, ...] = ()) -> Path:
    """tests/fmus/leaky built (or ``binary`` reused; ``defines`` for gcc -D) and zipped as ``root``/Leaky.fmu."""
    tree = root / "tree"
    so = tree / "binaries" / "linux64" / "Leaky.so"
    if binary is not None:
        if not sys.platform.startswith("linux"):
            pytest.skip("the test FMUs are built as linux64 binaries")
        so.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(binary, so)
    else:
        compile_linux64(LEAKY / "leaky.c", so, defines, "leaky FMU")
    (tree / "modelDescription.xml").write_text(leaky_description(extra), encoding="utf-8")
    return zip_tree(tree, root / "Leaky.fmu")
