"""Small C FMUs for the coupling tests (tests/fmus/cosim_body/body.c: a body on a soft spring-damper with the
interface force as an input), built with gcc against fmpy's FMI 2 headers in the three kinds of export the
coupling master meets: model exchange, co-simulation with canGetAndSetFMUstate, co-simulation without it."""
from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

import fmpy

HERE = Path(__file__).resolve().parent
BODY = HERE / "fmus" / "cosim_body" / "body.c"
FMI_HEADERS = Path(fmpy.__file__).resolve().parent / "c-code"

_VARIABLES = """
  <ModelVariables>
    <ScalarVariable name="m" valueReference="0" causality="parameter" variability="fixed" initial="exact"><Real start="1"/></ScalarVariable>
    <ScalarVariable name="k" valueReference="1" causality="parameter" variability="fixed" initial="exact"><Real start="100"/></ScalarVariable>
    <ScalarVariable name="b" valueReference="2" causality="parameter" variability="fixed" initial="exact"><Real start="1"/></ScalarVariable>
    <ScalarVariable name="x0" valueReference="3" causality="parameter" variability="fixed" initial="exact"><Real start="0"/></ScalarVariable>
    <ScalarVariable name="f" valueReference="4" causality="input" variability="continuous"><Real start="0"/></ScalarVariable>
    <ScalarVariable name="x" valueReference="5" causality="output" variability="continuous" initial="calculated"><Real/></ScalarVariable>
    <ScalarVariable name="v" valueReference="6" causality="output" variability="continuous" initial="calculated"><Real derivative="6"/></ScalarVariable>
    <ScalarVariable name="a" valueReference="7" causality="local" variability="continuous" initial="calculated"><Real derivative="7"/></ScalarVariable>
  </ModelVariables>
  <ModelStructure>
    <Outputs><Unknown index="6"/><Unknown index="7"/></Outputs>
    <Derivatives><Unknown index="7"/><Unknown index="8"/></Derivatives>
    <InitialUnknowns><Unknown index="6"/><Unknown index="7"/><Unknown index="8"/></InitialUnknowns>
  </ModelStructure>"""


def body_description(interfaces: tuple[str, ...], state: bool, indicators: int = 0) -> str:
    parts = []
    flag = "true" if state else "false"
    if "model-exchange" in interfaces:
        parts.append('  <ModelExchange modelIdentifier="body" canNotUseMemoryManagementFunctions="true" '
                     'completedIntegratorStepNotNeeded="true"/>')
    if "co-simulation" in interfaces:
        parts.append('  <CoSimulation modelIdentifier="body" canHandleVariableCommunicationStepSize="true" '
                     f'canInterpolateInputs="true" canNotUseMemoryManagementFunctions="true" '
                     f'canGetAndSetFMUstate="{flag}" canSerializeFMUstate="false"/>')
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="2.0" modelName="Body" guid="{{2f1c7e3a-9b4d-4c1e-8a2f-cosimbody0001}}"
  generationTool="hand-written (tests/fmus/cosim_body)" variableNamingConvention="flat" numberOfEventIndicators="{indicators}">
{chr(10).join(parts)}
  <DefaultExperiment startTime="0" stopTime="1"/>{_VARIABLES}
</fmiModelDescription>
"""


def build_body(root: Path, interfaces: tuple[str, ...], state: bool, indicators: bool = False,
               global_state: bool = False) -> Path:
    """body.c built (with -DWITH_STATE when ``state``, -DWITH_INDICATOR when ``indicators``: one event indicator,
    -DWITH_GLOBAL when ``global_state``: instances of one loaded binary that do not start alike) and zipped as
    root/Body.fmu declaring ``interfaces``."""
    if not sys.platform.startswith("linux"):
        pytest.skip("the test FMUs are built as linux64 binaries")
    if shutil.which("gcc") is None:
        pytest.skip("gcc is needed to build the test FMU tests/fmus/cosim_body")
    tree = root / "tree"
    so = tree / "binaries" / "linux64" / "body.so"
    so.parent.mkdir(parents=True, exist_ok=True)
    cmd = ["gcc", "-std=c99", "-Wall", "-O2", "-shared", "-fPIC", *(["-DWITH_STATE"] if state else []),
           *(["-DWITH_INDICATOR"] if indicators else []), *(["-DWITH_GLOBAL"] if global_state else []),
           "-I", str(FMI_HEADERS), str(BODY), "-o", str(so), "-lm"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.fail(f"building the body FMU failed:\n{' '.join(cmd)}\n{proc.stderr}")
    (tree / "modelDescription.xml").write_text(body_description(interfaces, state, int(indicators)),
                                               encoding="utf-8")
    fmu = root / "Body.fmu"
    with zipfile.ZipFile(fmu, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted(tree.rglob("*")):
            if f.is_file():
                z.write(f, f.relative_to(tree).as_posix())
    return fmu
