"""The FMU's equations come from the Modelica source and from nowhere else.

- Regeneration: fmu/codegen.py run now on modelica/ScrewVertebra.mo gives, byte for byte, the generated C the
  FMU was built from (build/fmu/sources) and that it carries in its sources/ (so another tool rebuilding the
  binary from the FMU compiles the same model). An edit of the Modelica without `make fmu` fails here.
- The hand-written C holds no equation of the model: outside the validation of the parameters, fmu/model.c
  reads no parameter of the model (only the solver's settings, the structural mode and the monitors it fills),
  fmu/solver.c includes nothing of the model (it sees it through solver.h), and neither it nor fmu/fmi2.c
  uses a variable of the model but the tolerance.
- The generator refuses what it cannot make explicit, naming it (a nonlinear algebraic loop, an unbalanced
  model)."""
from __future__ import annotations

import re
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CODEGEN = ROOT / "fmu" / "codegen.py"
MO = ROOT / "modelica" / "ScrewVertebra.mo"
GENERATED = ("sv_generated.c", "sv_generated.h", "sv_model.h")
#: What fmu/model.c may read besides the parameters' validation: the solver's settings, the structural mode,
#: the monitors and counters the solver fills.
SOLVER_SIDE = {"mode", "rtol", "sens_rtol", "h_max", "monitors", "max_steps", "max_wall_s", "eps_v_eq", "eps_a_eq",
               "a_y", "y_max", "v_y_max", "y_mean", "v_y_mean", "t_eq", "n_steps",
               # the forward sensitivities' selection and outputs (VR_sens_##name##_1: the generated outputs' names)
               "sens_p_1", "sens_"}


def run_codegen(out: Path, mo: Path | None = None) -> subprocess.CompletedProcess:
    code = ("import sys; sys.path.insert(0, sys.argv[1]); import codegen; from pathlib import Path; "
            "info = codegen.build(Path(sys.argv[3])); codegen.write(Path(sys.argv[2]), info)")
    return subprocess.run([sys.executable, "-c", code, str(CODEGEN.parent), str(out), str(mo or MO)],
                          capture_output=True, text=True)


def test_generated_c_is_what_the_fmu_was_built_from(tmp_path, fmu_path):
    pytest.importorskip("pymoca")
    pytest.importorskip("casadi")
    proc = run_codegen(tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    with zipfile.ZipFile(fmu_path) as z:
        names = set(z.namelist())
        for name in GENERATED:
            fresh = (tmp_path / name).read_bytes()
            built = (ROOT / "build" / "fmu" / "sources" / name).read_bytes()
            assert fresh == built, f"{name}: the Modelica changed since the FMU was built: run `make fmu`"
            assert f"sources/{name}" in names, f"the FMU does not carry sources/{name}"
            assert z.read(f"sources/{name}") == fresh, f"sources/{name} in {fmu_path.name} is not the generated one"


def _without_comments(c: str) -> str:
    return re.sub(r"//[^\n]*", "", re.sub(r"/\*.*?\*/", "", c, flags=re.S))


def _parameters() -> set[str]:
    text = (ROOT / "build" / "fmu" / "sources" / "sv_model.h").read_text(encoding="utf-8")
    block = text[text.index("#define SV_PARAMETERS(X)"):]
    block = block[:block.index("\n\n")]
    return set(re.findall(r"X\(\d+, (\w+)\)", block))


def test_hand_written_c_holds_no_equation(fmu_path):
    params = _parameters()
    assert {"c_y", "d_y", "m", "F_max", "gap", "tab_y_1"} <= params
    model = _without_comments((ROOT / "fmu" / "model.c").read_text(encoding="utf-8"))
    start, end = model.index("int model_validate("), model.index("typedef int (*sv_fn)")
    glue = model[:start] + model[end:]
    read = set(re.findall(r"\bV\((\w+)\)", glue)) | set(re.findall(r"\bVR_(\w+)", glue))
    assert read - {"name"} <= SOLVER_SIDE, f"fmu/model.c reads {sorted(read - SOLVER_SIDE - {'name'})} outside " \
                                           "the validation: an equation written by hand?"
    for other in ("solver.c", "fmi2.c", "solver.h", "model.h"):
        text = _without_comments((ROOT / "fmu" / other).read_text(encoding="utf-8"))
        used = {m for m in re.findall(r"\bVR_(\w+)", text)} | {m for m in re.findall(r"\bV\((\w+)\)", text)}
        assert used <= {"rtol"}, f"fmu/{other} uses the model's variables {sorted(used)}"
    # the solver sees the model only through its interface (solver.h): no header of the model
    solver = (ROOT / "fmu" / "solver.c").read_text(encoding="utf-8")
    assert set(re.findall(r'#include "([^"]+)"', solver)) == {"solver.h"}


def _edited(tmp_path: Path, old: str, new: str) -> Path:
    text = MO.read_text(encoding="utf-8")
    assert old in text
    out = tmp_path / "Edited.mo"
    out.write_text(text.replace(old, new, 1), encoding="utf-8")
    return out


@pytest.mark.parametrize("old, new, says", [
    ("  F_x = c_x*x + d_x*v_x;", "  F_x = c_x*x + d_x*v_x*F_x^2;", "not linear"),
    ("  F_meas = F_pull + F_offset;\n", "", "equations for"),
])
def test_generator_refuses_what_it_cannot_make_explicit(tmp_path, old, new, says):
    pytest.importorskip("pymoca")
    proc = run_codegen(tmp_path / "out", _edited(tmp_path, old, new))
    assert proc.returncode != 0
    assert says in proc.stderr + proc.stdout, proc.stderr[-1500:]
