"""Effects attached to an FMU that cannot be edited: OpenModelica's Mass_Damper export
(../shared/vendor-fmus/OM1193_Mass_Damper.fmu) coupled at its force input ``f`` to the interface element FMU.

The measured tests come from tests/attached_reference.py (scipy on the same equations written out; none of the
coupling master's code). Mass_Damper has one input, so the force drive is the one drive it can take (the
measured force and the element's force meet at ``f``). The diagnosis must name the hidden effect, recover
its parameters within 5 % and gain on data it did not see.
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import attached_reference as ar  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("FMUSA_SHARED_DIR") or ROOT.parent / "shared")
OM = SHARED / "vendor-fmus" / "OM1193_Mass_Damper.fmu"
ELEMENT = ROOT / "dist" / "InterfaceElement.fmu"

pytestmark = [pytest.mark.skipif(not ELEMENT.is_file(), reason="dist/InterfaceElement.fmu is not built (make fmu)"),
              pytest.mark.skipif(not OM.is_file(), reason=f"{OM} is not there (the shared vendor exports; "
                                                          "set FMUSA_SHARED_DIR)")]

#: the effect whose coupled run is checked in `make test` (the others with --run-slow)
CI_EFFECTS = ("backlash_gap",)
#: Each attached diagnosis is hundreds of coupled runs of 1.5-3 s CPU each (the master integrates the two FMUs
#: as one implicit system in Python): every one runs with --run-slow only, with the hidden effect among three
#: candidates (itself and two that mimic it on this protocol) and one start per model.
RIVALS = {"backlash_gap": ("nonlinear_stiffness", "coulomb_friction"),
          "coulomb_friction": ("yield_softening", "viscoelastic_relaxation"),
          "yield_softening": ("nonlinear_stiffness", "interface_damage"),
          "nonlinear_stiffness": ("backlash_gap", "yield_softening"),
          "viscoelastic_relaxation": ("coulomb_friction", "nonlinear_stiffness"),
          "interface_damage": ("yield_softening", "nonlinear_stiffness")}
#: The measured tests of each case (keywords of ar.protocol(), one test file each; default the one protocol). The
#: expected 95 % half-widths at the truth (Gauss-Newton, noise 2e-4 m, every 40 Hz sample) on the one protocol:
#: fric_x ±14 %, dmg_F_res ±27 %, dmg_rate ±16 %, every other parameter ≤ 2.5 % (but d_y). So friction gets a
#: slow small cycle beside it (its pre-slip shows at each reversal: 80 N of force, 2 samples at 900 N in 0.5 s,
#: 27 at 120 N in 3 s): fric_x ±2.4 %, fric_F ±1.1 %; and damage a test to a higher peak (the interface
#: further past its onset, towards its residual force): dmg_F_res ±2.0 %, dmg_rate ±1.8 %, dmg_y0 ±2.2 %.
PROTOCOLS = {"coulomb_friction": ({}, {"peak": 120.0, "ramp": 3.0, "hold": 0.1}),
             "interface_damage": ({}, {"peak": 1500.0, "hold": 0.25})}


def write_study(tmp: Path, effect: str, candidates: list[str] | None = None, starts: int = 2,
                points: int | None = None) -> Path:
    """The study of the case ``effect``: its tests (PROTOCOLS, each with its own noise), every sample fitted
    unless ``points`` is given. Not block-averaged: the mass rings at 19.5 Hz after each kink of the drive (about
    1 mm), which a mean of two 40 Hz samples cancels and the model at the block's mean time does not; to 100
    points (blocks of 2) the noise-free data are 1.2-2.3 times the noise away from the true model's response, and
    the fit trades that for damping (d_y +58 to +440 %) and the effect's parameters (fric_F -25 %)."""
    csvs, longest = [], 0
    for i, kw in enumerate(PROTOCOLS.get(effect, ({},))):
        df, _ = ar.synthesize(effect, seed=i, **kw)
        csvs.append(tmp / f"{effect}_{i}.csv")
        df.to_csv(csvs[-1], index=False)
        longest = max(longest, len(df))
    points = points or longest
    cands = f"  candidates: [{', '.join(candidates)}]\n" if candidates else ""
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
{cands}tests:
  drive: force
  files: [{', '.join(str(c) for c in csvs)}]
  max_points: {points}
diagnosis:
  starts: {starts}
  chain: 1
""")
    return f


@pytest.mark.slow   # about 8 s: fmpy at a 0.2 ms output interval
def test_reference_equations_are_the_export():
    """The reference's Mass_Damper (no element) against the FMU itself under the same force drive (fmpy's
    CVode): the equations written out are the export's."""
    from fmpy import simulate_fmu

    kt, ku = ar.protocol()
    t = np.arange(0.0, kt[-1] + 1e-9, 2e-4)    # fmpy samples the input per output interval: a fine one
    y_ref = ar.simulate({"c_y": 1e-9, "d_y": 0.0}, kt, ku, t)
    assert np.ptp(y_ref) > 0.05
    inp = np.array(list(zip(kt, ku)), dtype=[("time", float), ("f", float)])
    r = simulate_fmu(str(OM), fmi_type="ModelExchange", stop_time=kt[-1], output=["y"], output_interval=2e-4,
                     input=inp, relative_tolerance=1e-8, start_values={"spring.s_rel0": ar.S_REL0})
    y_fmu = np.interp(t, r["time"], r["y"])
    # 5e-5 m of 0.14 m: what is left is fmpy's sampling of the input (2.4e-4 m at a 1 ms interval)
    assert np.max(np.abs(y_fmu - y_ref)) < 5e-4 * np.ptp(y_ref)


@pytest.mark.parametrize("effect", [e if e in CI_EFFECTS else pytest.param(e, marks=pytest.mark.slow)
                                    for e in ar.CASES])
def test_coupled_run_is_the_reference(tmp_path, effect):
    """One coupled run (the master, the element FMU, the OM export) at the true parameters against the reference."""
    from fmusa.diagnose.calibrate import make_runner
    from fmusa.diagnose.study import load_diagnosis_study

    st = load_diagnosis_study(write_study(tmp_path, effect, points=1000))   # not block-averaged: the drive exact
    exp = st.experiments()[0]
    truth = {**ar.BASE, **ar.CASES[effect]}
    runner = make_runner(str(OM), "force", list(truth), {}, st.interface)
    pred = runner.predict(list(truth.values()), [exp])[0]
    ref = ar.simulate(truth, *ar.protocol(), exp.t)
    err = np.max(np.abs(pred - ref)) / np.ptp(ref)
    # the coupled runs' tolerance (COUPLED_RTOL 1e-4, me-grid): measured at most 5e-6 of the range
    assert runner.last.scheme == "me-grid"
    assert err < 1e-5, (effect, err, runner.last.scheme)


@pytest.mark.slow
@pytest.mark.parametrize("effect", list(RIVALS))
def test_attached_effect_is_named(tmp_path, effect):
    """The hidden effect named among the candidates, its parameters within 5 %, and a gain on held-out data."""
    from fmusa.diagnose.run import run_study_diagnosis
    from fmusa.diagnose.study import load_diagnosis_study

    st = load_diagnosis_study(write_study(tmp_path, effect, candidates=[effect, *RIVALS[effect]], starts=1))
    d = run_study_diagnosis(st, tmp_path / "out", workers=2, progress=False)
    assert effect in d["effect"].split(" ≡ "), (d["effect"], [(r["effect"], r["significant"]) for r in d["ranking"]])
    # the effect's parameters and the stiffness within 5 %; the damping shows only in the ringing after the drive's
    # kinks, a few samples at 40 Hz (expected 95 % half-width of d_y 17-70 % on these tests), so it is not checked
    truth = {**ar.CASES[effect], "c_y": ar.BASE["c_y"]}
    fit = d["_fits"][effect].params
    for k, v in truth.items():
        assert abs(fit[k] - v) <= 0.05 * abs(v), (k, fit[k], v)
    assert d["gain"]["heldout_rmse_ratio"] < 0.5
    assert (tmp_path / "out" / "diagnosis.json").is_file()
    assert d["coupling"]["scheme"] == "me-grid"
    # a test the diagnosis never saw (another peak and other durations): the extended model predicts it better
    ratio = heldout_gain(st, d, effect)
    assert ratio < 0.5, ratio


def heldout_gain(st, d: dict, effect: str) -> float:
    """RMSE of the extended model over the baseline's on a new test of the hidden effect (peak 600 N, slower)."""
    from fmusa.diagnose.calibrate import make_runner
    from fmusa.diagnose.measured import Experiment

    df, _ = ar.synthesize(effect, seed=7, peak=600.0, ramp=1.0, hold=0.25)
    e = Experiment(name="heldout", path=Path("heldout.csv"), drive="force", t=df.time.values,
                   displacement=df.displacement.values, force=df.force.values)
    rmse = {}
    for key in ("baseline", "extended"):
        params = d[key]["params"]
        runner = make_runner(str(OM), "force", list(params), {}, st.interface)
        pred = runner.predict(list(params.values()), [e])[0]
        rmse[key] = float(np.sqrt(np.mean((pred - e.displacement) ** 2)))
    return rmse["extended"] / rmse["baseline"]


def test_extended_model_as_ssp_or_why_not(tmp_path):
    """The diagnosis writes the extended model as SSP next to diagnosis.json; Mass_Damper's velocity is a state,
    not an output, and an SSP connection starts at an output: the diagnosis says so instead of a file."""
    from fmusa.diagnose.run import write_extended_ssp
    from fmusa.diagnose.study import load_diagnosis_study

    st = load_diagnosis_study(write_study(tmp_path, "backlash_gap"))
    params = {**ar.BASE, **ar.CASES["backlash_gap"]}
    out = write_extended_ssp(tmp_path / "extended.ssp", str(OM), st.interface, "force", params, 3.0, "mass_damper")
    assert out["written"] is False and "'mass.v' is not an output" in out["why"], out
    assert not (tmp_path / "extended.ssp").exists()
