"""`diagnose-shear` with an FMU that crashes in one candidate's region: the units side by side lose their worker,
the units left run one after another on supervised workers, the candidate that crashes is named as failed in every
unit, and the study ends with its report.

Before fitcache.run_fits kept a single fit on the workers, a unit whose side-by-side run had left one fit to do
ran it in the main process, and the crash ended the study. A real crash, nothing mocked: ScrewVertebra rebuilt from its own sources with fmi2ExitInitializationMode wrapped
so that a run with interface damage switched on (dmg_rate > 0) calls abort(), as an export that dies in one region
of its parameters does. The verdict of each unit is the one of the whole study on the real FMU (H1 anterior and
posterior: no effect beyond eq. 1, tests/test_shear_c67.py and `make bench`'s `diagnose_shear_all_effects`).
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "data" / "shear-c67"
SV = ROOT / "dist" / "ScrewVertebra.fmu"

_WRAPPER = """
#include <stdlib.h>
fmi2Status fmi2ExitInitializationMode(fmi2Component comp)
{
    const fmi2ValueReference vr = %(vr)d;
    fmi2Real rate = 0.0;
    if (fmi2GetReal(comp, &vr, 1, &rate) == fmi2OK && rate > 0.0) abort();   /* dies where damage is on */
    return inner_exit_initialization_mode(comp);
}
"""

# slow (`make slow`): 40 s, half of it building the FMU from its sources
pytestmark = [pytest.mark.slow,
              pytest.mark.skipif(not SV.exists(), reason="needs dist/ScrewVertebra.fmu (make fmu)"),
              pytest.mark.skipif(os.name == "nt" or shutil.which("cc") is None, reason="needs a C compiler")]


def crashing_copy(dest: Path) -> Path:
    """ScrewVertebra, extracted into ``dest`` and rebuilt at -O1 with the wrapper above (the way
    fmusa.fmi.instrument rebuilds an FMU that logs its runs)."""
    from fmpy import read_model_description

    from fmusa.fmi.archive import extract_fmu
    from fmusa.fmi.instrument import _DEFINITION, _compile_quickly

    extract_fmu(SV, dest)
    shutil.rmtree(dest / "binaries")
    vr = {v.name: v.valueReference for v in read_model_description(str(SV)).modelVariables}["dmg_rate"]
    src = dest / "sources" / "fmi2.c"
    text = src.read_text(encoding="utf-8")
    assert _DEFINITION.search(text), "fmi2.c no longer defines fmi2ExitInitializationMode"
    text = _DEFINITION.sub(lambda m: f"static fmi2Status inner_exit_initialization_mode(fmi2Component "
                                     f"{m.group(1)}) {{", text, count=1)
    src.write_text(text + _WRAPPER % {"vr": vr}, encoding="utf-8")
    _compile_quickly(shutil.which("cc"), dest)
    return dest


def test_a_unit_whose_fmu_crashes_ends_the_side_by_side_run_and_the_study_still_ends(tmp_path):
    fmu = crashing_copy(tmp_path / "crashing")
    out = tmp_path / "out"
    code = ("from fmusa.applications.shear_c67.study import run_shear_diagnosis\n"
            "if __name__ == '__main__':\n"
            f"    run_shear_diagnosis({str(out)!r}, {str(DATA)!r}, fmu_path={str(fmu)!r}, specimens=['H1'],\n"
            "                        diagnosed=1, workers=2,\n"
            "                        candidates=('nonlinear_stiffness', 'interface_damage'))\n")
    script = tmp_path / "run.py"
    script.write_text(code, encoding="utf-8")
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    # the side-by-side run broke (a unit's worker died) and the units went on one after another
    assert "units left one after another" in proc.stdout, proc.stdout[-3000:]
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert (out / "report.md").is_file()
    for unit in ("H1_Ant", "H1_Pos"):
        d = json.loads((out / unit / "diagnosis.json").read_text(encoding="utf-8"))
        assert "crashes in this fit" in d["failed"].get("interface_damage", ""), (unit, d["failed"])
        assert d["runs"]["candidates"]["interface_damage"].get("failed"), unit
        assert "nonlinear_stiffness" in [r["effect"] for r in d["ranking"]], unit
        assert d["effect"] == "none", (unit, d["effect"])
    # every stage after the diagnoses ran for both units (their rate dependence and prediction bands)
    for stage in ("groups", "rate_models", "prediction_bands"):
        assert set(summary[stage]) == {"H1_Ant", "H1_Pos"}, stage
