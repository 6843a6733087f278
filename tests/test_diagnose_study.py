"""The diagnosis study file: validated into dataclasses with file:line errors, and checked against the FMU's
modelDescription.xml before any run (a vendor FMU without the variables stops at once, naming what is missing
and how to export it). No fit runs here: every test is a load or a check of a real FMU's description."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from fmusa.diagnose.effects import DiagnoseError
from fmusa.diagnose.models import builtin_description, resolve
from fmusa.diagnose.study import load_diagnosis_study
from fmusa.study.schema import StudyError

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("FMUSA_SHARED_DIR") or ROOT.parent / "shared")
VENDOR = SHARED / "vendor-fmus"
OM = VENDOR / "OM1193_Mass_Damper.fmu"
DYMOLA = VENDOR / "Dymola2023x_SpringFrictionPendulum1D.fmu"
CSV = ROOT / "data/shear-c67/H01/H1_C67_Ant_10_mm_s.csv"
#: The shared vendor exports are beside the repository (../shared) or at $FMUSA_SHARED_DIR; a clone elsewhere
#: skips the tests that read them, saying where it looked.
needs_exports = pytest.mark.skipif(not (OM.is_file() and DYMOLA.is_file()),
                                   reason=f"the shared vendor exports are not at {VENDOR} (set FMUSA_SHARED_DIR)")


def _csv(tmp_path: Path) -> Path:
    """A measured test of the default format (time, displacement, force in s, m, N)."""
    f = tmp_path / "t.csv"
    f.write_text("time,displacement,force\n" + "".join(f"{0.1 * i},{1e-4 * i},{10.0 * i}\n" for i in range(20)))
    return f


def test_screw_vertebra_study_is_the_builtin_description(fmu_path):
    st = load_diagnosis_study(ROOT / "studies/diagnose_screw_vertebra.yaml")
    from dataclasses import replace

    assert replace(st.interface, name="") == replace(builtin_description("ScrewVertebra"), name="")
    assert resolve(None, fmu_path) == builtin_description("ScrewVertebra")
    assert st.tests.drive == "displacement" and [s.rate for s in st.tests.specs] == ["1 mm/s", "10 mm/s", "100 mm/s"]
    exps = st.experiments()
    assert [e.name for e in exps] == ["H1_C67_Ant_1_mm_s", "H1_C67_Ant_10_mm_s", "H1_C67_Ant_100_mm_s"]
    assert max(len(e.t) for e in exps) <= 300
    # the same fits as `fmusa diagnose FILES --drive displacement ...` (their cache keys are the same: a rerun
    # of either reuses the other's fits)
    from fmusa.diagnose.fitcache import data_key

    assert data_key(exps, "displacement", 6, str(fmu_path), st.interface) == \
        data_key(exps, "displacement", 6, str(fmu_path))


def _om_study(tmp_path: Path, body: str) -> Path:
    f = tmp_path / "study.yaml"
    f.write_text(f"name: om\nfmu: {OM}\n" + body + f"tests:\n  drive: force\n  files: [{_csv(tmp_path)}]\n")
    return f


@needs_exports
@pytest.mark.parametrize("body, line, words", [
    ("model: {drives: {force: {input: f}}}\n", 3, "key 'response' is missing"),
    ("model: {drives: {forse: {input: f, response: y}}}\n", 3, "did you mean 'force'"),
    ("model: {drives: {force: {input: f, response: y, response_unit: kN}}}\nbaseline: {stiffness: spring.c, "
     "damping: damper.d}\n", 3, "unknown unit 'kN'"),
    ("model: {drives: {force: {input: f, response: y}}}\nbaseline: {stiffness: spring.c}\n", 4,
     "key 'damping' is missing"),
    ("model: {drives: {force: {input: f, response: y}}}\nbaseline: {stiffness: spring.c, damping: damper.d}\n"
     "effects: {candidates: [coulomb_friktion]}\n", 5, "did you mean 'coulomb_friction'"),
    ("model: {drives: {displacement: {input: f, response: y}}}\nbaseline: {stiffness: spring.c, damping: d}\n",
     6, "gives no FMU input and response for a force drive"),
    ("model: {drives: {force: {input: f, response: y}}}\nbaseline: {stiffness: spring.c, damping: damper.d}\n"
     "effects: {where: inside, force_input: f}\n", 5, "applies to where: attached only"),
    ("model: Spring\n", 3, "no built-in model description 'Spring'"),
])
def test_bad_study_names_file_line_and_fix(tmp_path, body, line, words):
    f = _om_study(tmp_path, body)
    with pytest.raises(StudyError) as e:
        load_diagnosis_study(f)
    assert f"{f}:{line}:" in str(e.value) and words in str(e.value), str(e.value)


@needs_exports
def test_vendor_fmu_with_the_flags_is_refused_before_any_fit(tmp_path, capsys):
    """`fmusa diagnose --fmu <a Dymola export>` used to fit every candidate for 47 s, then fail on 'mode': now it
    stops before any fit, saying that the FMU has no description and how to write one."""
    from fmusa.cli import main

    out = tmp_path / "out"
    code = main(["diagnose", str(_csv(tmp_path)), "--drive", "displacement", "--out", str(out), "--fmu", str(DYMOLA)])
    err = capsys.readouterr().err
    assert code == 2
    assert "no description of how to drive the model 'SpringFrictionPendulum1D'" in err and \
        "fmusa diagnose STUDY.yaml" in err, err
    assert not (out / "fits").exists()


@needs_exports
def test_study_against_the_fmu_names_every_missing_variable_and_the_export(tmp_path):
    """A study whose names the FMU lacks: one error listing each, how to export it, and nothing run."""
    from fmusa.diagnose.run import run_study_diagnosis

    f = _om_study(tmp_path, "model: {drives: {force: {input: F_ext, response: spring.s_rel}}}\n"
                            "baseline: {stiffness: spring.c, damping: damper.d}\n"
                            "effects: {candidates: [backlash_gap]}\n")
    st = load_diagnosis_study(f)
    with pytest.raises(DiagnoseError) as e:
        run_study_diagnosis(st, tmp_path / "out", workers=1, progress=False)
    msg = str(e.value)
    assert "nothing was run" in msg
    assert "for the force drive: Mass_Damper has no variable 'F_ext'" in msg
    assert "for the measured displacement (the response): 'spring.s_rel' is a local variable, not an output" in msg
    assert "for a candidate effect (gap): Mass_Damper has no variable 'gap'" in msg
    assert "Dymola" in msg and "OpenModelica" in msg and "Simpack" in msg
    assert "for the baseline" not in msg    # its parameters are settable: not named
    assert not (tmp_path / "out").exists()


def test_an_fmu_that_has_everything_passes_the_check(tmp_path, fmu_path):
    from fmusa.diagnose.check import description_problems

    st = load_diagnosis_study(ROOT / "studies/diagnose_screw_vertebra.yaml")
    assert description_problems(fmu_path, st.interface, "displacement", st.interface.candidates) == []
    assert description_problems(fmu_path, st.interface, "force", st.interface.candidates) == []


def test_cli_study_mode_refuses_the_flags_it_sets(tmp_path, capsys):
    from fmusa.cli import main

    code = main(["diagnose", str(ROOT / "studies/diagnose_screw_vertebra.yaml"), "--out", str(tmp_path),
                 "--drive", "force"])
    assert code == 2 and "--drive: the study file" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


@needs_exports
def test_units_of_the_fmu_are_converted(tmp_path):
    """input_unit and response_unit reach the runner as factors to and from SI."""
    f = _om_study(tmp_path, "model: {drives: {force: {input: f, input_unit: kN, response: y, response_unit: mm}}}\n"
                            "baseline: {stiffness: spring.c, damping: damper.d}\n")
    st = load_diagnosis_study(f)
    assert st.interface.input_scale == {"force": 1e3} and st.interface.output_scale == {"force": 1e-3}


def test_key_reference_agrees_with_the_loader():
    """docs/_gen/diagnosis_keys.py: every key documented, every entry a key, the loader's keys the documented ones."""
    sys.path.insert(0, str(ROOT / "docs" / "_gen"))
    try:
        import diagnosis_keys
    finally:
        sys.path.pop(0)
    page = diagnosis_keys.render()
    for section, cls, excluded, _ in diagnosis_keys.SECTIONS:
        for f in diagnosis_keys.keys_of(cls, excluded):
            assert f"| `{f.name}` |" in page
