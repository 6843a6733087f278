"""An attached diagnosis runs like every diagnosis: its fits in the worker pool (spawned processes), each fit
saved and reused by a rerun (no coupled run the second time), and its report and console speak in the user's
FMU's names: the element's parameters as ``element.NAME``, not the effect catalogue's names.

The model is OpenModelica's Mass_Damper export (../shared/vendor-fmus/OM1193_Mass_Damper.fmu, or
$FMUSA_SHARED_DIR/vendor-fmus) with the interface element attached at its force input; the measured test is
made by tests/attached_reference.py (scipy on the equations written out, no code of the coupling master).
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import attached_reference as ar  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("FMUSA_SHARED_DIR") or ROOT.parent / "shared")
OM = SHARED / "vendor-fmus" / "OM1193_Mass_Damper.fmu"
ELEMENT = ROOT / "dist" / "InterfaceElement.fmu"

pytestmark = [pytest.mark.skipif(not ELEMENT.is_file(), reason="dist/InterfaceElement.fmu is not built (make fmu)"),
              pytest.mark.skipif(not OM.is_file(), reason=f"{OM} is not there (set FMUSA_SHARED_DIR)")]


def short_study(tmp: Path, effect: str = "backlash_gap", measured: bool = True) -> Path:
    """A short force test (load to 900 N in 0.2 s, unload to -450 N, 1.2 s at 40 Hz) with the effect hidden, and
    its study file: the effect the one candidate, one start (``measured=False``: a file of zeros, for checks
    that read no data)."""
    csv = tmp / "test.csv"
    if measured:
        ar.synthesize(effect, ramp=0.2, hold=0.2)[0].to_csv(csv, index=False)
    else:
        csv.write_text("time,displacement,force\n0,0,0\n0.025,0,1\n0.05,0,2\n", encoding="utf-8")
    f = tmp / "study.yaml"
    f.write_text(f"""name: mass_damper
fmu: {OM}
model:
  drives:
    force: {{input: f, response: y}}
  fixed: {{spring.s_rel0: {ar.S_REL0}}}
baseline:
  stiffness: {{variable: c, bounds: [1.0e3, 2.0e4]}}
  damping: {{variable: d, bounds: [0.0, 200.0]}}
effects:
  where: attached
  element: {ELEMENT}
  force_input: f
  displacement_output: y
  velocity_output: mass.v
  candidates: [{effect}]
tests:
  drive: force
  files: [{csv}]
diagnosis:
  starts: 1
  chain: 1
""")
    return f


def test_parameters_are_named_as_the_fmus_name_them(tmp_path):
    """Which FMU each fitted parameter is set on, and the name the report and the console give it."""
    from fmusa.diagnose.report import fmu_name
    from fmusa.diagnose.run import parameter_homes
    from fmusa.diagnose.study import load_diagnosis_study

    st = load_diagnosis_study(short_study(tmp_path, measured=False))
    names = ["c_y", "d_y", "gap"]
    homes = parameter_homes(str(OM), st.interface, names)
    assert homes == {"c_y": "element", "d_y": "element", "gap": "element"}
    diag = {"model": {"variables": {n: st.interface.variable(n) for n in names}, "where": homes}}
    assert [fmu_name(diag, n) for n in names] == ["element.c", "element.d", "element.gap"]
    # a parameter of the model itself keeps the model's name; without a mapping, the name given
    diag["model"]["variables"]["c_y"], diag["model"]["where"]["c_y"] = "spring.c", "model"
    assert fmu_name(diag, "c_y") == "spring.c" and fmu_name({}, "c_y") == "c_y"


@pytest.mark.slow   # two fits of ~100 coupled runs each
def test_attached_diagnosis_in_the_pool_resumed_and_named(tmp_path, capsys):
    from fmusa.cli import main

    study = short_study(tmp_path)
    out = tmp_path / "out"
    assert main(["diagnose", str(study), "--out", str(out), "--workers", "2"]) == 0
    first = capsys.readouterr().out
    import json
    d1 = json.loads((out / "diagnosis.json").read_text(encoding="utf-8"))
    assert d1["effect"] == "backlash_gap", d1["effect"]
    assert d1["runs"]["total"] > 0 and d1["coupling"]["scheme"] == "me-grid"
    # the user's names: the element's parameters, never the catalogue's (c_y, d_y, gap) alone
    report = (out / "report.md").read_text(encoding="utf-8")
    for name in ("element.c", "element.d", "element.gap"):
        assert f"`{name}`" in report, name
    for name in ("c_y", "d_y", "`gap`"):
        assert name not in report, name
    assert "element.gap = " in first and "gap = " not in first.replace("element.gap = ", ""), first
    # the rerun takes every fit from DIR/fits: no coupled run, the same answer
    assert main(["diagnose", str(study), "--out", str(out), "--workers", "2"]) == 0
    d2 = json.loads((out / "diagnosis.json").read_text(encoding="utf-8"))
    assert d2["runs"]["total"] == 0, d2["runs"]
    assert d2["extended"]["params"] == d1["extended"]["params"]


def test_coupled_run_past_its_time_limit_fails_as_a_run(tmp_path):
    """A coupled run that passes its time limit is a failed run (a RuntimeError the fit backs off from, naming
    the limit), as a sweep's run past its limit is; not a hung diagnosis."""
    from fmusa.diagnose.attached import COUPLED_MAX_WALL_S, CoupledRunner
    from fmusa.diagnose.measured import Experiment
    from fmusa.diagnose.study import load_diagnosis_study

    st = load_diagnosis_study(short_study(tmp_path, measured=False))
    runner = CoupledRunner(str(OM), "force", ["c_y", "d_y"], {}, interface=st.interface, max_wall_s=1e-6)
    assert COUPLED_MAX_WALL_S > 0 and CoupledRunner.__init__.__defaults__[-1] == COUPLED_MAX_WALL_S
    import numpy as np
    t = np.arange(0.0, 1.0, 0.025)
    e = Experiment(name="t", path=tmp_path / "t.csv", drive="force", t=t, displacement=0 * t, force=100 * t)
    with pytest.raises(RuntimeError, match="time limit"):
        runner.predict([5e3, 20.0], [e])


BODY_STUDY = """name: body
fmu: {fmu}
model:
  drives:
    force: {{input: f, response: x}}
baseline:
  stiffness: {{variable: c, bounds: [1.0e2, 1.0e5]}}
  damping: {{variable: d, bounds: [0.0, 100.0]}}
effects:
  where: attached
  element: {element}
  force_input: f
  displacement_output: x
  velocity_output: v
  candidates: [backlash_gap]
tests:
  drive: force
  files: [{csv}]
"""


@pytest.mark.parametrize("flawed", [False, True])
def test_reuse_check_of_the_coupled_runs(tmp_path, flawed):
    """The first coupled run of a runner is made twice on new instances of the binaries loaded once (the reuse
    check, as FMURunner's): a clean export passes and keeps the loaded binary; an export whose instances share
    a static counter (tests/fmus/cosim_body built with -DWITH_GLOBAL: each new instance starts 1 mm further) is
    caught, and from then on every run loads a fresh copy, so that every run gives the first run's numbers."""
    import numpy as np

    from cosim_fmus import build_body
    from fmusa.diagnose.attached import CoupledRunner
    from fmusa.diagnose.measured import Experiment
    from fmusa.diagnose.study import load_diagnosis_study

    fmu = build_body(tmp_path, ("model-exchange",), False, global_state=flawed)
    csv = tmp_path / "t.csv"
    csv.write_text("time,displacement,force\n0,0,0\n0.025,0,1\n0.05,0,2\n", encoding="utf-8")
    (tmp_path / "s.yaml").write_text(BODY_STUDY.format(fmu=fmu, element=ELEMENT, csv=csv), encoding="utf-8")
    st = load_diagnosis_study(tmp_path / "s.yaml")
    runner = CoupledRunner(str(fmu), "force", ["c_y", "d_y"], {}, interface=st.interface)
    # fmpy unloads a binary when its last instance is freed, which resets a library's static state; a process
    # where something else keeps the library loaded (here: this test, as another instance or a host would)
    # carries it over from run to run
    import ctypes

    from fmusa.cosim.master import _unpacked
    from fmusa.fmi.info import read_fmu_info
    held = ctypes.CDLL(str(_unpacked(read_fmu_info(fmu), "model-exchange") / "binaries" / "linux64" / "body.so"))
    t = np.linspace(0.0, 0.2, 21)
    e = Experiment(name="t", path=csv, drive="force", t=t, displacement=0 * t, force=10 * t)
    first = runner.predict([1e3, 5.0], [e])[0]
    assert runner.reuse and runner.fresh_binary is flawed, runner.reuse
    assert runner.runs["fit"] == 2                    # the check's run is counted
    for _ in range(2):
        assert np.array_equal(runner.predict([1e3, 5.0], [e])[0], first)
    assert held is not None
