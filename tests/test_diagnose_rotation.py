"""A rotational interface: effects attached to a torque-driven FMU we did not write as the user's model
(tests/rotor_fmu.py: an inertia on a torsion spring-damper, torque input ``tau``, angle output ``phi``), measured
tests in deg and N·m (tests/rotational_reference.py: scipy on the same equations written out, none of the
coupling master's code), declared in the study file with ``model: motion: rotation``.

The diagnosis must read the angle in deg and the torque in N·m (converted to rad and N·m), name the hidden
effect, recover its parameters within 5 %, and write rotational units (deg, N·m, N·m/rad) in report.md,
diagnosis.json and the figures, never N or mm.
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import rotational_reference as rr  # noqa: E402
from rotor_fmu import build_rotor  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
ELEMENT = ROOT / "dist" / "InterfaceElement.fmu"

pytestmark = pytest.mark.skipif(not ELEMENT.is_file(), reason="dist/InterfaceElement.fmu is not built (make fmu)")


@pytest.fixture(scope="module")
def rotor(tmp_path_factory) -> Path:
    return build_rotor(tmp_path_factory.mktemp("rotor"))


def write_study(tmp: Path, fmu: Path, effect: str, candidates: list[str] | None = None, starts: int = 1,
                motion: str | None = "rotation", units: str = "{time: s, displacement: deg, force: N·m}") -> Path:
    """The study of the case ``effect``: one test (angle in deg, torque in N·m) at 40 Hz, every sample fitted."""
    df, _ = rr.synthesize(effect)
    csv = tmp / f"{effect}.csv"
    df.to_csv(csv, index=False)
    cands = f"  candidates: [{', '.join(candidates)}]\n" if candidates else ""
    mot = f"  motion: {motion}\n" if motion else ""
    f = tmp / "study.yaml"
    f.write_text(f"""name: rotor
fmu: {fmu}
model:
{mot}  drives:
    force: {{input: tau, response: phi}}
baseline:
  stiffness: {{variable: c, bounds: [1.0, 100.0]}}
  damping: {{variable: d, bounds: [0.0, 1.0]}}
effects:
  where: attached
  element: {ELEMENT}
  force_input: tau
  displacement_output: phi
  velocity_output: w
{cands}tests:
  drive: force
  files: [{csv}]
  columns: {{time: t_s, displacement: angle_deg, force: torque_Nm}}
  units: {units}
  max_points: {len(df)}
diagnosis:
  starts: {starts}
  chain: 1
""", encoding="utf-8")
    return f


def test_study_reads_deg_and_newton_metres(tmp_path, rotor):
    """The study loads as rotational (declared, or from the units alone), the angle in deg becomes rad and the
    torque stays N·m; a length or force unit under a rotational interface is refused naming the angle units."""
    from fmusa.diagnose.study import load_diagnosis_study
    from fmusa.study.schema import StudyError

    for motion in ("rotation", None):
        st = load_diagnosis_study(write_study(tmp_path, rotor, "backlash_gap", motion=motion))
        assert st.interface.motion == "rotation" and st.tests.specs[0].motion == "rotation"
        e = st.experiments()[0]
        df, _ = rr.synthesize("backlash_gap")
        assert np.allclose(e.response_signal, np.radians(df.angle_deg.to_numpy()), rtol=1e-12, atol=1e-15)
        assert np.allclose(e.force, df.torque_Nm.to_numpy())
        assert e.meta["motion"] == "rotation" and e.meta["units"]["displacement"] == "deg"
    with pytest.raises(StudyError, match=r"'mm' is a translation unit.*allowed: rad, deg, mrad"):
        load_diagnosis_study(write_study(tmp_path, rotor, "backlash_gap",
                                         units="{time: s, displacement: mm, force: N·m}"))
    with pytest.raises(StudyError, match=r"'N' is a force unit, but the interface is rotational; accepted "
                                         r"torque units: N·m"):
        load_diagnosis_study(write_study(tmp_path, rotor, "backlash_gap", motion=None,
                                         units="{time: s, displacement: deg, force: N}"))


def test_coupled_run_is_the_reference(tmp_path, rotor):
    """One coupled run (the master, the element FMU, the rotor export) at the true parameters, fed the measured
    torque of the study's test, against the scipy reference: within 3e-5 of the angle's range."""
    from fmusa.diagnose.calibrate import make_runner
    from fmusa.diagnose.study import load_diagnosis_study

    for effect in ("backlash_gap", "coulomb_friction"):
        st = load_diagnosis_study(write_study(tmp_path, rotor, effect))
        exp = st.experiments()[0]
        truth = {**rr.BASE, **rr.CASES[effect]}
        runner = make_runner(str(rotor), "force", list(truth), {}, st.interface)
        pred = runner.predict(list(truth.values()), [exp])[0]
        ref = rr.simulate(truth, *rr.protocol(), exp.t)
        err = float(np.max(np.abs(pred - ref)) / np.ptp(ref))
        print(f"{effect}: coupled run against the reference, max error {err:.2g} of the angle's range")
        assert runner.last.scheme == "me-grid"
        # the coupled runs' tolerance (COUPLED_RTOL 1e-4, me-grid): measured 1.0e-5 (gap: at the slack's corners,
        # rounded over smooth_w = 1e-6 rad) and 7.9e-6 (friction) of the range; the noise (0.01 deg) is 1.7e-3 of it
        assert err < 3e-5, (effect, err)


def _no_translation_units(text: str) -> list[str]:
    """Translational units a rotational report must not write (N alone, mm, N/mm, N·s/mm, m/s)."""
    import re
    return re.findall(r"\[(?:N|mm|N/mm|N·s/mm|mm/s|m)\]|\d (?:N|mm|N/mm|N·s/mm)(?=[ ,.;)])", text)


@pytest.mark.slow
@pytest.mark.parametrize("effect, rival", [("backlash_gap", "coulomb_friction"),
                                           ("coulomb_friction", "backlash_gap")])
def test_rotational_effect_is_named(tmp_path, rotor, effect, rival):
    """The hidden effect named against a rival, its parameters and the stiffness within 5 %, in rotational units."""
    from fmusa.diagnose.run import run_study_diagnosis
    from fmusa.diagnose.study import load_diagnosis_study

    st = load_diagnosis_study(write_study(tmp_path, rotor, effect, candidates=[effect, rival]))
    d = run_study_diagnosis(st, tmp_path / "out", workers=1, progress=False)
    assert effect in d["effect"].split(" ≡ "), (d["effect"], [(r["effect"], r["significant"]) for r in d["ranking"]])
    truth = {**rr.CASES[effect], "c_y": rr.BASE["c_y"]}
    fit = d["_fits"][effect].params
    for k, v in truth.items():
        assert abs(fit[k] - v) <= 0.05 * abs(v), (k, fit[k], v)
    js = json.loads((tmp_path / "out" / "diagnosis.json").read_text(encoding="utf-8"))
    assert js["data"]["motion"] == "rotation" and js["data"]["units"] == {"displacement": "rad", "force": "N·m"}
    expected = {"c_y": "N·m/rad", "d_y": "N·m·s/rad", "gap": "rad", "fric_F": "N·m", "fric_x": "rad"}
    assert js["extended"]["units"] == {k: expected[k] for k in fit}
    assert {k: v["unit"] for k, v in js["effect_params"].items()} == {k: expected[k] for k in rr.CASES[effect]}
    report = (tmp_path / "out" / "report.md").read_text(encoding="utf-8")
    assert "peak |angle| [deg]" in report and "peak |torque| [N·m]" in report and "| N·m/rad |" in report
    assert "**angle** (deg)" in report
    assert not _no_translation_units(report), _no_translation_units(report)
    main = {"backlash_gap": "gap", "coulomb_friction": "fric_F"}[effect]
    shown = {"gap": f"{math.degrees(fit['gap']):.4g} deg" if effect == "backlash_gap" else None,
             "fric_F": f"{fit['fric_F']:.4g} N·m" if effect == "coulomb_friction" else None}[main]
    assert f"= {shown}" in report, shown


def test_the_catalogue_speaks_of_torques_and_angles_under_rotation():
    """What the report says an effect and a parameter mean follows the interface's motion."""
    from fmusa.diagnose.effects import EFFECT_MEANING, PARAM_MEANING, in_motion
    from fmusa.diagnose.report import _params_section

    assert in_motion(PARAM_MEANING["fric_F"], "rotation") == "Coulomb friction torque"
    assert in_motion(EFFECT_MEANING["nonlinear_stiffness"], "rotation").startswith("the torque–angle curve bends")
    assert in_motion(PARAM_MEANING["dmg_y0"], "translation") == PARAM_MEANING["dmg_y0"]
    for text in (*PARAM_MEANING.values(), *EFFECT_MEANING.values()):
        rot = in_motion(text, "rotation")
        assert "force" not in rot and "displacement" not in rot, rot
    diag = {"effect": "coulomb_friction", "data": {"motion": "rotation"},
            "baseline": {"params": {"c_y": 20.0}, "ci95": {"c_y": [19.0, 21.0]}},
            "final": {"params": {"c_y": {"value": 20.0, "ci95": [19.0, 21.0]},
                                 "fric_F": {"value": 0.3, "ci95": [0.29, 0.31]}}}}
    text = _params_section(diag)
    assert "Coulomb friction torque" in text and "friction force" not in text
