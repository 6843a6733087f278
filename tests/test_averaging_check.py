"""The block averaging's check (fmusa.diagnose.averaging): a fit to block means is biased where the response is not
close to a straight line within a block, and the diagnosis says so, naming the test, the size and the fix.

On real FMUs: OpenModelica's Mass_Damper export (../shared/vendor-fmus/OM1193_Mass_Damper.fmu) with the interface
element attached, whose mass rings at 19.5 Hz after each kink of a force drive sampled at 40 Hz (the tests of
tests/attached_reference.py, averaged in blocks of 2: the fit takes the difference for damping, d_y +58 %); and
ScrewVertebra on a shear test of data/shear-c67 (1 mm/s, blocks of 6), close to a straight line within its blocks.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import attached_reference as ar  # noqa: E402

from fmusa.diagnose.averaging import MAX_SHIFT_SE, check_averaging  # noqa: E402
from fmusa.diagnose.calibrate import Fit, make_runner  # noqa: E402
from fmusa.diagnose.measured import Blocks, Experiment, downsample  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def test_blocks_give_back_the_block_means():
    """What downsample keeps (meta['blocks']) averages any signal at the original samples into the experiment's
    samples, also when an experiment is averaged twice (blocks of blocks, unequal weights)."""
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.5, 1.5, 1003))
    e = Experiment(name="a", path=Path("a.csv"), drive="displacement", t=t, displacement=rng.normal(size=t.size),
                   force=rng.normal(size=t.size))
    assert "blocks" not in downsample(e, 2000).meta          # not averaged: nothing kept
    once = downsample(e, 100)
    twice = downsample(once, 37)
    for d in (once, twice):
        b = d.meta["blocks"]
        assert isinstance(b, Blocks) and b.n == 1003 and d.meta["downsampled_from"] == 1003
        assert np.array_equal(b.t, t) and np.array_equal(b.drive, e.displacement)
        np.testing.assert_allclose(b.mean(t), d.t, rtol=1e-14)
        np.testing.assert_allclose(b.mean(e.displacement), d.displacement, atol=1e-14)
        np.testing.assert_allclose(b.mean(e.force), d.force, atol=1e-14)
        assert b.sizes.sum() == 1003 and b.sizes[0] == b.sizes[-1] == 1     # the end samples as they are


# ---------------------------------------------------------------------------------------- ringing: Mass_Damper
def _mass_damper_study(tmp_path: Path, points: int | None):
    import test_diagnose_attached as tda

    if not (tda.ELEMENT.is_file() and tda.OM.is_file()):
        pytest.skip("dist/InterfaceElement.fmu or the OpenModelica Mass_Damper export is not there")
    from fmusa.diagnose.study import load_diagnosis_study

    return tda, load_diagnosis_study(tda.write_study(tmp_path, "backlash_gap", points=points))


def _fit_at(fmu, drive, interface, params: dict, experiments, effect: str) -> Fit:
    """The model at ``params`` as a fit: its predictions at the experiments' samples and its residual RMSE."""
    runner = make_runner(str(fmu), drive, list(params), {}, interface)
    preds = runner.predict(list(params.values()), experiments)
    rss = float(sum(np.sum((p - e.response_signal) ** 2) for p, e in zip(preds, experiments)))
    n = sum(e.n for e in experiments)
    return Fit(effect=effect, params=dict(params), ci95={}, rss=rss, n=n, k=len(params), rmse=float(np.sqrt(rss / n)),
               predictions=preds)


def test_ringing_mass_damper_in_blocks_of_two_is_warned_about(tmp_path):
    """The hidden backlash at the true parameters, its test (121 samples at 40 Hz) averaged to 62 points: the model
    run at every sample and averaged in the same blocks is 4 residual RMSEs away from the model at the block times
    after the drive's kinks, which can move a parameter by several standard errors: the warning names the test,
    the size against the residuals, and the fix. Three coupled runs (one of them the coupled runner's reuse check)."""
    from fmusa.diagnose.report import _warnings_section
    from fmusa.diagnose.runs_report import runs_section
    from fmusa.diagnose.run import run_count
    from fmusa.diagnose.budget import RunBudget

    tda, st = _mass_damper_study(tmp_path, 100)
    exps = st.experiments()
    assert exps[0].n == 62 and exps[0].meta["downsampled_from"] == 121 and exps[0].meta["block"] == 2
    truth = {**ar.BASE, **ar.CASES["backlash_gap"]}
    fit = _fit_at(tda.OM, "force", st.interface, truth, exps, "backlash_gap")
    budget = RunBudget(None)
    check = check_averaging(str(tda.OM), "force", st.interface, {"final model (backlash_gap)": fit}, exps, budget)
    # the run at the samples, the coupled runner's reuse check, and (the bound passed) the 3 columns of a Jacobian
    assert check["made"] and check["runs"] == budget.used == 5, check
    m = check["models"]["final model (backlash_gap)"]
    row = m["tests"][0]
    # measured: RMS 0.73 x the residual RMSE, 3.9 x at the worst block (t = 2.54 s, after the unloading's kink)
    assert row["max_ratio"] > 2.0 and row["rms_ratio"] > 0.4 and row["shift_se"] > 3 * MAX_SHIFT_SE, row
    # the damping takes it (the fit to these block means: d_y +58 %, every sample +12 %)
    d = m["parameters"]["d_y"]
    assert d["fmu_name"] == "element.d" and d["relative"] > 0.1 and d["shift_se"] > MAX_SHIFT_SE, m["parameters"]
    assert m["max_shift_se"] == max(abs(p["shift_se"]) for p in m["parameters"].values()) <= row["shift_se"]
    (w,) = check["warnings"]
    assert w["kind"] == "averaging" and w["experiments"] == ["backlash_gap_0"] and w["max_points"] == 121
    for text in ("'backlash_gap_0'", "121 samples", "x the residual RMSE", "element.d by +",
                 "standard errors", "`max_points: 121`", "`--max-points 121`"):
        assert text in w["message"], (text, w["message"])
    # the report's warnings and the run count's row
    section = _warnings_section({"warnings": [w]})
    assert "'backlash_gap_0'" in section and "wrong unit" not in section and "block averaging" in section
    base = Fit(effect="none", params={}, ci95={}, rss=1.0, n=1, k=1, rmse=1.0, runs={"fit": 10}, rounds={"fit": 10})
    runs = run_count({"none": base}, {}, budget, check)
    assert runs["checks"]["averaging"]["total"] == 5 and runs["counted_by_fits"] == 15
    assert "| check: block averaging |  |  | 5 |" in runs_section({"runs": runs})

    # every sample fitted: nothing averaged, nothing to check, no run, no warning
    (tmp_path / "all").mkdir()
    _, st_all = _mass_damper_study(tmp_path / "all", None)
    exps_all = st_all.experiments()
    assert exps_all[0].n == 121 and "blocks" not in exps_all[0].meta
    check_all = check_averaging(str(tda.OM), "force", st_all.interface, {"final model (backlash_gap)": fit}, exps_all)
    assert not check_all["made"] and check_all["runs"] == 0 and check_all["warnings"] == []
    assert "no test was block-averaged" in check_all["why"]


# ---------------------------------------------------------------------------------------- near-linear: shear
def test_shear_test_close_to_a_line_within_its_blocks_is_not_warned_about(fmu_path):
    """ScrewVertebra fitted to a 1 mm/s shear test (1522 samples averaged to 256, blocks of 6), the baseline and
    the interface damage (the most curved of the catalogue's fits there): the block means of the model at every
    sample are the model at the block times to a few hundredths of the residual RMSE; no warning. Measured:
    z = 0 (baseline: a line), 0.12 (damage)."""
    from fmusa.applications.shear_c67.data import list_tests, load_test
    from fmusa.diagnose.calibrate import calibrate
    from fmusa.diagnose.effects import data_scales, model_parameters
    from fmusa.diagnose.models import resolve

    tests = list_tests(ROOT / "data" / "shear-c67")
    row = tests[(tests.specimen == "H1") & (tests.direction == "Ant") & (tests.rate_mm_s == 1.0)].iloc[0]
    e = load_test(row, max_points=300)
    assert e.meta["downsampled_from"] == 1522 and e.n == 256
    interface = resolve(None, str(fmu_path))
    sc = data_scales([e])
    fits = {}
    for effect in ("interface_damage", "none"):
        names = [p.name for p in model_parameters(effect, "displacement", sc)]
        model = make_runner(str(fmu_path), "displacement", names, {}, interface)
        try:
            fits[effect] = calibrate(model, effect, "displacement", [e], sc, max_starts=1, max_nfev=30)
        finally:
            model.close()
    assert fits["interface_damage"].rmse < 0.8 * fits["none"].rmse      # a curved fit, not the line again
    check = check_averaging(str(fmu_path), "displacement", interface,
                            {"final model (interface_damage)": fits["interface_damage"], "baseline": fits["none"]}, [e])
    assert check["made"] and check["runs"] == 2 and check["warnings"] == []
    for label, m in check["models"].items():
        (r,) = m["tests"]
        assert m["shift_se"] < 0.5 * MAX_SHIFT_SE and r["max_ratio"] < 0.3, (label, r)
        assert m["parameters"] is None          # below the bound: no Jacobian, one run per model


# ---------------------------------------------------------------------------------------- end to end
@pytest.mark.slow   # an attached diagnosis: ~2 min
def test_attached_diagnosis_in_blocks_of_two_warns_everywhere(tmp_path, capsys):
    """The whole attached diagnosis (``fmusa diagnose STUDY``) of the backlash at max_points 100: the warning in
    diagnosis.json, on the console and in report.md, its runs in the run count; a rerun reuses the check."""
    from fmusa.cli import main

    tda, _ = _mass_damper_study(tmp_path, 100)
    study = tda.write_study(tmp_path, "backlash_gap", candidates=["backlash_gap"], starts=1, points=100)
    out = tmp_path / "out"
    assert main(["diagnose", str(study), "--out", str(out), "--workers", "1"]) == 0
    console = capsys.readouterr().out
    d = json.loads((out / "diagnosis.json").read_text(encoding="utf-8"))
    ws = [w for w in d["warnings"] if w["kind"] == "averaging"]
    assert len(ws) == 1 and ws[0]["experiments"] == ["backlash_gap_0"], d["warnings"]
    assert f"warning: {ws[0]['message']}" in console
    report = (out / "report.md").read_text(encoding="utf-8")
    assert ws[0]["message"] in report and "check: block averaging" in report
    assert d["runs"]["checks"]["averaging"]["total"] >= 2 and d["averaging"]["made"]
    assert d["runs"]["total"] == d["runs"]["counted_by_fits"]
    assert main(["diagnose", str(study), "--out", str(out), "--workers", "1"]) == 0
    d2 = json.loads((out / "diagnosis.json").read_text(encoding="utf-8"))
    assert d2["runs"]["total"] == 0 and [w["message"] for w in d2["warnings"]] == [w["message"] for w in d["warnings"]]


def test_screw_backlash_under_a_force_drive_in_blocks_of_three(fmu_path):
    """ScrewVertebra with a backlash hidden, force-driven (tests/effects_reference.py, 752 samples): at the default
    max_points (300, blocks of 3) the jump across the gap sits within a block. The check's first-order shift of the
    damping is most of what fitting every sample instead changes (measured -26 against -30 N·s/m, 4.4 standard
    errors)."""
    import effects_reference as er
    from fmusa.diagnose.calibrate import calibrate
    from fmusa.diagnose.effects import data_scales, model_parameters
    from fmusa.diagnose.models import resolve

    df, truth = er.synthesize("backlash_gap", "force", seed=7)
    e = Experiment(name="gap", path=Path("gap.csv"), drive="force", t=df.time.values,
                   displacement=df.displacement.values, force=df.force.values)
    interface = resolve(None, str(fmu_path))
    fits = {}
    for points in (300, None):
        d = downsample(e, points) if points else e
        sc = data_scales([d])
        names = [p.name for p in model_parameters("backlash_gap", "force", sc)]
        model = make_runner(str(fmu_path), "force", names, {}, interface)
        try:
            fits[points] = (d, calibrate(model, "backlash_gap", "force", [d], sc, max_starts=1, start=truth["params"]))
        finally:
            model.close()
    d, fit = fits[300]
    assert d.meta["block"] == 3
    check = check_averaging(str(fmu_path), "force", interface, {"final model (backlash_gap)": fit}, [d])
    m = check["models"]["final model (backlash_gap)"]
    # one run at the samples, one with the FMU's sensitivities for the Jacobian
    assert check["runs"] == 2 and m["shift_se"] > MAX_SHIFT_SE and check["warnings"], m
    shift = m["parameters"]["d_y"]
    actual = fits[None][1].params["d_y"] - fit.params["d_y"]     # every sample less block means
    assert shift["shift_se"] < -2 and shift["shift"] < 0, shift
    assert abs(-shift["shift"] - actual) < 0.3 * abs(actual), (shift, actual)
    assert "'gap' (752 samples" in check["warnings"][0]["message"]


def test_the_warning_never_states_a_value_past_a_bound_nor_a_translational_unit_under_rotation():
    """A first-order shift that would take a parameter past its bound (a residual force below 0) is said to be
    one, and a rotational interface's bias is in N·m and deg, not N and mm."""
    from fmusa.diagnose import motion as mo
    from fmusa.diagnose.averaging import _moves, _size

    m = {"parameters": {"dmg_F_res": {"fmu_name": "dmg_F_res", "value": 10.0, "shift": -14.0, "relative": -1.4,
                                      "shift_se": -3.3, "beyond": "lower"}}}
    assert "past its lower bound" in _moves(m) and "-1.4e+02 %" in _moves(m)
    assert _size(2.0, "displacement") == "2 N" and _size(2e-3, "force") == "2 mm"
    with mo.use(mo.ROTATION):
        assert _size(2.0, "displacement") == "2 N·m"
        assert _size(0.01, "force") == f"{0.01 / (3.141592653589793 / 180):.3g} deg"
