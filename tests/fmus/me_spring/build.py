"""Build the test FMU of spring.c (a mass on a spring-damper under a ramped force) as a real .fmu file.

``build_spring_fmu(dest, interfaces=("model-exchange",))`` writes ``dest/<name>.fmu`` with a
``modelDescription.xml`` that declares the requested FMI 2.0 interfaces, the linux64 binary compiled by
gcc (unless ``binary=False``) and, with ``sources=True``, the C sources listed under ``<SourceFiles>``.
The FMI 2 headers come from the installed fmpy. Used by tests/test_model_exchange.py, test_inspect.py and
test_fmu_checks.py.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import zipfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
SOURCE = HERE / "spring.c"
GUID = "{5b0d2a6e-3c1f-4f7e-9a51-0c5e1f2a7b3d}"
IDENTIFIER = "spring"
HEADERS = ("fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h")

_VARIABLES = """\
  <UnitDefinitions>
    <Unit name="N"><BaseUnit kg="1" m="1" s="-2"/></Unit>
    <Unit name="N/m"><BaseUnit kg="1" s="-2"/></Unit>
    <Unit name="N.s/m"><BaseUnit kg="1" s="-1"/></Unit>
    <Unit name="kg"><BaseUnit kg="1"/></Unit>
    <Unit name="m"><BaseUnit m="1"/></Unit>
    <Unit name="m/s"><BaseUnit m="1" s="-1"/></Unit>
    <Unit name="m/s2"><BaseUnit m="1" s="-2"/></Unit>
    <Unit name="s"><BaseUnit s="1"/></Unit>
  </UnitDefinitions>
  <DefaultExperiment startTime="0" stopTime="3" tolerance="1e-6"/>
  <ModelVariables>
    <!-- 1 --><ScalarVariable name="c" valueReference="0" causality="parameter" variability="fixed" initial="exact" description="Spring stiffness"><Real unit="N/m" start="400"/></ScalarVariable>
    <!-- 2 --><ScalarVariable name="d" valueReference="1" causality="parameter" variability="fixed" initial="exact" description="Damping coefficient"><Real unit="N.s/m" start="20"/></ScalarVariable>
    <!-- 3 --><ScalarVariable name="m" valueReference="2" causality="parameter" variability="fixed" initial="exact" description="Mass"><Real unit="kg" start="1"/></ScalarVariable>
    <!-- 4 --><ScalarVariable name="F_max" valueReference="3" causality="parameter" variability="tunable" initial="exact" description="Force at the end of the ramp and after it"><Real unit="N" start="10"/></ScalarVariable>
    <!-- 5 --><ScalarVariable name="t_ramp" valueReference="4" causality="parameter" variability="fixed" initial="exact" description="Duration of the linear force ramp from 0 to F_max"><Real unit="s" start="1"/></ScalarVariable>
    <!-- 6 --><ScalarVariable name="y_static" valueReference="5" causality="calculatedParameter" variability="fixed" initial="calculated" description="Static displacement F_max / c"><Real unit="m"/></ScalarVariable>
    <!-- 7 --><ScalarVariable name="y" valueReference="6" causality="output" variability="continuous" initial="calculated" description="Displacement of the mass"><Real unit="m"/></ScalarVariable>
    <!-- 8 --><ScalarVariable name="v" valueReference="7" causality="output" variability="continuous" initial="calculated" description="Velocity of the mass"><Real unit="m/s" derivative="7"/></ScalarVariable>
    <!-- 9 --><ScalarVariable name="a" valueReference="8" causality="output" variability="continuous" initial="calculated" description="Acceleration of the mass"><Real unit="m/s2" derivative="8"/></ScalarVariable>
    <!-- 10 --><ScalarVariable name="F" valueReference="9" causality="output" variability="continuous" initial="calculated" description="Applied force F_max*min(t/t_ramp, 1) + F_ext"><Real unit="N"/></ScalarVariable>
    <!-- 11 --><ScalarVariable name="F_ext" valueReference="10" causality="input" variability="continuous" description="Extra constant force"><Real unit="N" start="0"/></ScalarVariable>
    <!-- 12 --><ScalarVariable name="h_cs" valueReference="11" causality="parameter" variability="fixed" initial="exact" description="Largest RK4 sub-step of the co-simulation interface"><Real unit="s" start="1e-4"/></ScalarVariable>
    <!-- 13 --><ScalarVariable name="g" valueReference="12" causality="local" variability="constant" initial="exact" description="Gravity (unused; a constant)"><Real unit="m/s2" start="9.81"/></ScalarVariable>
  </ModelVariables>
  <ModelStructure>
    <Outputs>
      <Unknown index="7"/>
      <Unknown index="8"/>
      <Unknown index="9"/>
      <Unknown index="10"/>
    </Outputs>
    <Derivatives>
      <Unknown index="8"/>
      <Unknown index="9"/>
    </Derivatives>
    <InitialUnknowns>
      <Unknown index="6"/>
      <Unknown index="7"/>
      <Unknown index="8"/>
      <Unknown index="9"/>
      <Unknown index="10"/>
    </InitialUnknowns>
  </ModelStructure>
"""


def model_description(name: str, interfaces, sources: bool, fmi_version: str = "2.0") -> str:
    files = ("\n    <SourceFiles>\n      <File name=\"spring.c\"/>\n    </SourceFiles>\n  " if sources else "")
    parts = []
    if "model-exchange" in interfaces:
        parts.append(f'  <ModelExchange modelIdentifier="{IDENTIFIER}" completedIntegratorStepNotNeeded="true" '
                     f'canNotUseMemoryManagementFunctions="true">{files}</ModelExchange>')
    if "co-simulation" in interfaces:
        parts.append(f'  <CoSimulation modelIdentifier="{IDENTIFIER}" canHandleVariableCommunicationStepSize="true" '
                     f'canNotUseMemoryManagementFunctions="true">{files}</CoSimulation>')
    if not parts:
        raise ValueError("at least one interface")
    return (f'<?xml version="1.0" encoding="UTF-8"?>\n'
            f'<fmiModelDescription fmiVersion="{fmi_version}" modelName="{name}" guid="{GUID}" '
            f'description="Mass on a spring-damper under a ramped force (fmusa test FMU)" '
            f'generationTool="fmusa tests/fmus/me_spring/build.py" variableNamingConvention="flat" '
            f'numberOfEventIndicators="0">\n'
            + "\n".join(parts) + "\n"
            + _VARIABLES
            + "</fmiModelDescription>\n")


def _fmpy_headers() -> Path:
    import fmpy
    return Path(fmpy.__file__).parent / "c-code"


def compile_binary(out_so: Path) -> Path:
    out_so.parent.mkdir(parents=True, exist_ok=True)
    cmd = [os.environ.get("CC", "gcc"), "-std=c99", "-O2", "-fPIC", "-shared", "-Wall",
           f"-I{_fmpy_headers()}", str(SOURCE), "-o", str(out_so), "-lm"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"compiling {SOURCE} failed:\n{' '.join(cmd)}\n{proc.stdout}{proc.stderr}")
    return out_so


def build_spring_fmu(dest: Path, name: str = "SpringME", interfaces=("model-exchange",),
                     binary: bool = True, sources: bool = False, fmi_version: str = "2.0") -> Path:
    """Write ``dest/<name>.fmu`` and return its path."""
    dest = Path(dest)
    tree = dest / f"{name}.build"
    shutil.rmtree(tree, ignore_errors=True)
    tree.mkdir(parents=True)
    (tree / "modelDescription.xml").write_text(model_description(name, interfaces, sources, fmi_version))
    if binary:
        compile_binary(tree / "binaries" / "linux64" / f"{IDENTIFIER}.so")
    if sources:
        (tree / "sources").mkdir()
        shutil.copy(SOURCE, tree / "sources" / "spring.c")
        for h in HEADERS:
            shutil.copy(_fmpy_headers() / h, tree / "sources" / h)
    fmu = dest / f"{name}.fmu"
    with zipfile.ZipFile(fmu, "w", zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(tree.rglob("*")):
            if path.is_file():
                zf.write(path, path.relative_to(tree).as_posix())
    shutil.rmtree(tree, ignore_errors=True)
    return fmu


if __name__ == "__main__":  # pragma: no cover - manual use: python tests/fmus/me_spring/build.py DIR
    import sys
    out = Path(sys.argv[1] if len(sys.argv) > 1 else ".")
    print(build_spring_fmu(out))
    print(build_spring_fmu(out, "SpringBoth", ("co-simulation", "model-exchange")))
