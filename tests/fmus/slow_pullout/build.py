"""Build the slow stand-in FMU of pullout.c (the paper's axial pullout in closed form, sleeping ``sleep_s``
seconds of wall time per fmi2DoStep) as a real .fmu file: ``build_pullout_fmu(dest)`` writes
``dest/SlowPullout.fmu`` (Co-Simulation, the binary compiled by gcc for this machine; the C source is
included under sources/). Used by tests/test_search_rounds.py and by ``make bench`` (paper_study_wall_s_slow_fmu).
"""
from __future__ import annotations

import os
import platform
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
SOURCE = HERE / "pullout.c"
GUID = "{0d7c3e52-9b7a-4c61-8f0e-2a4b6c8d1e35}"
IDENTIFIER = "pullout"
HEADERS = ("fmi2Functions.h", "fmi2FunctionTypes.h", "fmi2TypesPlatform.h")

#: (name, causality, unit, start, description); value references in this order (pullout.c's enum)
VARIABLES = [
    ("c_y", "parameter", "N/m", 823224.0, "Interface stiffness along the screw axis y"),
    ("d_y", "parameter", "N.s/m", 488.0, "Interface damping along y"),
    ("F_max", "parameter", "N", 411.0, "Pullout force after the ramp"),
    ("t_ramp", "parameter", "s", 10.0, "Duration of the linear force ramp from 0 to F_max"),
    ("eps_v_eq", "parameter", "m/s", 5e-8, "Equilibrium threshold on |v_y|"),
    ("eps_a_eq", "parameter", "m/s2", 5e-9, "Equilibrium threshold on |a_y|"),
    ("sleep_s", "parameter", "s", 0.5, "Wall time each fmi2DoStep sleeps (the cost of a vendor FMU's run)"),
    ("y_max", "output", "m", None, "max |y| over [0, t]"),
    ("y_mean", "output", "m", None, "time average of y over [0, t]"),
    ("v_y_max", "output", "m/s", None, "max |v_y| over [0, t]"),
    ("v_y_mean", "output", "m/s", None, "time average of |v_y| over [0, t]"),
    ("t_eq", "output", "s", None, "time since which |v_y| <= eps_v_eq and |a_y| <= eps_a_eq; -1 while not at rest"),
]
UNITS = {"N/m": 'kg="1" s="-2"', "N.s/m": 'kg="1" s="-1"', "N": 'kg="1" m="1" s="-2"', "s": 's="1"',
         "m/s": 'm="1" s="-1"', "m/s2": 'm="1" s="-2"', "m": 'm="1"'}


def model_description() -> str:
    units = "\n".join(f'    <Unit name="{u}"><BaseUnit {b}/></Unit>' for u, b in UNITS.items())
    rows, outputs = [], []
    for vr, (name, causality, unit, start, desc) in enumerate(VARIABLES):
        if causality == "parameter":
            attrs, real = 'causality="parameter" variability="fixed" initial="exact"', f'<Real unit="{unit}" start="{start!r}"/>'
        else:
            attrs, real = 'causality="output" variability="continuous"', f'<Real unit="{unit}"/>'
            outputs.append(vr + 1)
        rows.append(f'    <ScalarVariable name="{name}" valueReference="{vr}" description="{desc.replace("<", "&lt;")}" '
                    f'{attrs}>{real}</ScalarVariable>')
    out = "\n".join(f'      <Unknown index="{i}"/>' for i in outputs)
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="2.0" modelName="SlowPullout" guid="{GUID}"
  description="The paper's axial pullout in closed form, sleeping sleep_s per doStep (fmusa bench/test FMU)"
  generationTool="fmusa tests/fmus/slow_pullout/build.py" variableNamingConvention="flat" numberOfEventIndicators="0">
  <CoSimulation modelIdentifier="{IDENTIFIER}" canHandleVariableCommunicationStepSize="true"
    canNotUseMemoryManagementFunctions="true">
    <SourceFiles>
      <File name="pullout.c"/>
    </SourceFiles>
  </CoSimulation>
  <UnitDefinitions>
{units}
  </UnitDefinitions>
  <DefaultExperiment startTime="0" stopTime="12"/>
  <ModelVariables>
{chr(10).join(rows)}
  </ModelVariables>
  <ModelStructure>
    <Outputs>
{out}
    </Outputs>
    <InitialUnknowns>
{out}
    </InitialUnknowns>
  </ModelStructure>
</fmiModelDescription>
"""


def _fmpy_headers() -> Path:
    import fmpy
    return Path(fmpy.__file__).parent / "c-code"


def _platform() -> tuple[str, str]:
    """(FMI binaries folder, shared library suffix) of this machine."""
    if sys.platform.startswith("win"):
        return "win64", ".dll"
    if sys.platform == "darwin":
        return "darwin64", ".dylib"
    return ("linux64" if platform.machine() in ("x86_64", "AMD64", "aarch64") else "linux32"), ".so"


def build_pullout_fmu(dest: Path) -> Path:
    """Write ``dest/SlowPullout.fmu`` and return its path (needs a C compiler: $CC, else gcc)."""
    dest = Path(dest)
    tree = dest / "SlowPullout.build"
    shutil.rmtree(tree, ignore_errors=True)
    tree.mkdir(parents=True)
    (tree / "modelDescription.xml").write_text(model_description(), encoding="utf-8")
    folder, suffix = _platform()
    so = tree / "binaries" / folder / f"{IDENTIFIER}{suffix}"
    so.parent.mkdir(parents=True)
    cmd = [os.environ.get("CC", "gcc"), "-std=c99", "-O2", "-fPIC", "-shared", "-Wall", "-Wextra",
           f"-I{_fmpy_headers()}", str(SOURCE), "-o", str(so), "-lm"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"compiling {SOURCE} failed:\n{' '.join(cmd)}\n{proc.stdout}{proc.stderr}")
    (tree / "sources").mkdir()
    shutil.copy(SOURCE, tree / "sources" / SOURCE.name)
    for h in HEADERS:
        shutil.copy(_fmpy_headers() / h, tree / "sources" / h)
    fmu = dest / "SlowPullout.fmu"
    with zipfile.ZipFile(fmu, "w", zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(tree.rglob("*")):
            if path.is_file():
                zf.write(path, path.relative_to(tree).as_posix())
    shutil.rmtree(tree, ignore_errors=True)
    return fmu


if __name__ == "__main__":  # pragma: no cover - manual use: python tests/fmus/slow_pullout/build.py DIR
    print(build_pullout_fmu(Path(sys.argv[1] if len(sys.argv) > 1 else ".")))
