"""Chains that are physically possible: a fitted effect's parameters against the test that produced them, and
an effect the protocol cannot identify (the physics of test_identifiability's table) not added."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

from fmusa.diagnose.measured import Experiment  # noqa: E402
from fmusa.diagnose.plausibility import (IDENTIFYING_FEATURES, Support, implausible, support_of,  # noqa: E402
                                         unidentifiable)


def _ramp(travel_mm: float, peak_n: float, seconds: float, n: int = 145) -> Experiment:
    t = np.linspace(0.0, seconds, n)
    y = np.linspace(0.0, travel_mm * 1e-3, n)
    return Experiment(name="ramp", path=Path("ramp.csv"), drive="displacement", t=t, displacement=y,
                      force=np.linspace(0.0, peak_n, n))


def test_support_reads_travel_peak_length_and_sampling():
    s = support_of([_ramp(1.45, 274.0, 0.145), _ramp(1.0, 300.0, 1.45)])
    assert s.travel == pytest.approx(1.45e-3) and s.peak_force == pytest.approx(300.0)
    assert s.longest == pytest.approx(1.45) and s.dt_min == pytest.approx(0.145 / 144)


def test_the_issue_cases_are_implausible():
    """The three chains of the report: pre-slip beyond the travel, residual force above the peak, a relaxation
    time ten times the test's length; each named with the parameter and the test that would support it."""
    s = Support(travel=1.45e-3, peak_force=274.0, longest=0.137, dt_min=1e-3)
    fric = implausible("nonlinear_stiffness+coulomb_friction", {"fric_x": 2.84e-3, "fric_F": 50.0}, s)
    assert [b["parameter"] for b in fric] == ["fric_x"] and "travel" in fric[0]["why"]
    dmg = implausible("interface_damage", {"dmg_F_res": 328.0, "dmg_y0": 0.5e-3}, s)
    assert [b["parameter"] for b in dmg] == ["dmg_F_res"] and "peak" in dmg[0]["why"]
    ve = implausible("a+viscoelastic_relaxation", {"ve_tau": 1.37, "ve_k": 1e5}, s)
    assert [b["parameter"] for b in ve] == ["ve_tau"] and "hold" in ve[0]["test"]
    # within what the test supports: nothing to say
    ok = {"fric_x": 0.1e-3, "fric_F": 50.0, "dmg_F_res": 100.0, "dmg_y0": 0.5e-3, "ve_tau": 0.05}
    assert implausible("coulomb_friction+interface_damage+viscoelastic_relaxation", ok, s) == []
    # too fast to resolve: shorter than 3 samples
    assert implausible("viscoelastic_relaxation", {"ve_tau": 2e-3}, s)[0]["parameter"] == "ve_tau"


def test_protocol_table_agrees_with_the_identifiability_table():
    """IDENTIFYING_FEATURES against test_identifiability.expected, for every protocol of the table (displacement
    drive): the same physics stated once in the code and once in the test."""
    import effects_reference as er
    from test_identifiability import Cell, expected

    for effect in IDENTIFYING_FEATURES:
        for protocol, (several, hold, unload) in er.PROTOCOLS.items():
            feats = {"several_rates": several, "hold": hold, "unloading": unload}
            want = expected(Cell(effect, protocol))["identifiable"]
            got = unidentifiable(effect, feats) is None
            assert got == want, (effect, protocol)
    why = unidentifiable("viscoelastic_relaxation", {"several_rates": False, "hold": False, "unloading": False})
    assert why["reason"].startswith("cannot tell") and "hold" in why["separating_test"]
    assert unidentifiable("viscoelastic_relaxation", {"several_rates": False}, drive="force") is None


def _fit(effect: str, params: dict, rss: float, preds: np.ndarray):
    from fmusa.diagnose.calibrate import Fit

    n = preds.size
    return Fit(effect=effect, params=params, ci95={k: (v, v) for k, v in params.items()}, rss=rss, n=n,
               k=len(params), rmse=float(np.sqrt(rss / n)), heldout_rmse=float(np.sqrt(rss / n)) * 1.1,
               predictions=[preds])


def test_an_implausible_first_effect_is_not_named():
    """Two candidates both fit far better than the baseline; friction's pre-slip (2.84 mm) is beyond the test's
    travel (1.45 mm): it is listed last, not significant, with why, and the other one is named."""
    from fmusa.diagnose.rank import Thresholds, choose_effect
    from fmusa.diagnose.run import _screened_ranking   # noqa: PLC2701 - the screening itself, without FMU runs

    e = _ramp(1.45, 274.0, 1.45)
    meas = np.asarray(e.force, float)
    base = _fit("none", {"c_y": 1.9e5, "d_y": 0.0}, 400.0 * meas.size, meas + 20.0)
    fric = _fit("coulomb_friction", {"c_y": 1e5, "d_y": 0.0, "fric_F": 60.0, "fric_x": 2.84e-3}, 0.5 * meas.size,
                meas + 0.5)
    bend = _fit("nonlinear_stiffness", {"c_y": 1e5, "d_y": 0.0, "nl_ratio": 2.0, "nl_y_b": 0.5e-3},
                1.0 * meas.size, meas + 1.0)
    ranking, removed = _screened_ranking(base, {"coulomb_friction": fric, "nonlinear_stiffness": bend},
                                         Thresholds(), [e])
    assert ranking[-1]["effect"] == "coulomb_friction" and not ranking[-1]["significant"]
    assert ranking[-1]["implausible"][0]["parameter"] == "fric_x"
    # a ramp at one rate cannot identify friction either: both checks are listed
    assert {(r["effect"], r["check"]) for r in removed} == {("coulomb_friction", "physics"),
                                                            ("coulomb_friction", "protocol")}
    assert choose_effect(ranking, Thresholds())[0] == "nonlinear_stiffness"


def test_chain_does_not_add_what_the_protocol_cannot_identify():
    """On one ramp at one rate, a Maxwell branch and friction cannot be identified: the chain lists them as
    "cannot tell" with the test that would, and adds nothing (no fit is run for them)."""
    from fmusa.diagnose.rank import Thresholds
    from fmusa.diagnose.run import effect_chain

    e = _ramp(1.45, 274.0, 1.45)
    meas = np.asarray(e.force, float)
    base = _fit("none", {"c_y": 1.9e5, "d_y": 0.0}, 400.0 * meas.size, meas + 20.0)
    ext = _fit("nonlinear_stiffness", {"c_y": 1e5, "d_y": 0.0, "nl_ratio": 2.0, "nl_y_b": 0.5e-3}, meas.size,
               meas + 1.0)
    removed: list = []
    steps = effect_chain(base, ext, "nonlinear_stiffness", ["nonlinear_stiffness"], "nonlinear_stiffness",
                         ("viscoelastic_relaxation", "coulomb_friction"), [e], "displacement", "no.fmu", 2, None,
                         1, None, "k", False, Thresholds(), 3, removed=removed)
    assert [s["effect"] for s in steps] == ["nonlinear_stiffness"]
    assert {r["effect"] for r in removed} == {"viscoelastic_relaxation", "coulomb_friction"}
    assert all(r["check"] == "protocol" and r["reason"].startswith("cannot tell") and r["separating_test"]
               for r in removed)


def test_the_first_effect_too_is_checked_against_the_protocol():
    """On one ramp at one rate a Maxwell branch cannot be identified: as the first effect it is listed last, not
    significant, removed at step 1 with why and the test that would tell, and listed as "cannot tell"; the bend
    is named. Friction, unidentifiable under load-unload at one rate, stays when its equivalent (yield, the same
    equations) is identifiable there."""
    from fmusa.diagnose.rank import Thresholds, choose_effect
    from fmusa.diagnose.run import _first_unidentifiable, _screened_ranking, _with_cannot_tell_first  # noqa: PLC2701

    e = _ramp(1.45, 274.0, 1.45)
    meas = np.asarray(e.force, float)
    base = _fit("none", {"c_y": 1.9e5, "d_y": 0.0}, 400.0 * meas.size, meas + 20.0)
    ve = _fit("viscoelastic_relaxation", {"c_y": 1e5, "d_y": 0.0, "ve_k": 1e5, "ve_tau": 0.1}, 0.5 * meas.size,
              meas + 0.5)
    bend = _fit("nonlinear_stiffness", {"c_y": 1e5, "d_y": 0.0, "nl_ratio": 2.0, "nl_y_b": 0.5e-3},
                1.0 * meas.size, meas + 1.0)
    ranking, removed = _screened_ranking(base, {"viscoelastic_relaxation": ve, "nonlinear_stiffness": bend},
                                         Thresholds(), [e], "displacement")
    assert ranking[-1]["effect"] == "viscoelastic_relaxation" and not ranking[-1]["significant"]
    assert ranking[-1]["unidentifiable"]["reason"].startswith("cannot tell")
    assert [(r["step"], r["effect"], r["check"]) for r in removed] == [(1, "viscoelastic_relaxation", "protocol")]
    assert "hold" in removed[0]["separating_test"]
    assert choose_effect(ranking, Thresholds())[0] == "nonlinear_stiffness"
    listed = _with_cannot_tell_first([], removed)
    assert [i["effect"] for i in listed] == ["viscoelastic_relaxation"] and listed[0]["reason"].startswith("cannot")
    assert _with_cannot_tell_first(listed, removed) == listed          # not listed twice
    # under a force drive the table does not apply: nothing removed
    assert not _screened_ranking(base, {"viscoelastic_relaxation": ve}, Thresholds(), [e], "force")[1]
    one_rate_unload = {"unloading": True, "hold": False, "several_rates": False}
    fits = {"coulomb_friction": ve, "yield_softening": ve, "viscoelastic_relaxation": ve}
    assert set(_first_unidentifiable(fits, one_rate_unload, "displacement")) == {"viscoelastic_relaxation"}
    assert set(_first_unidentifiable({"coulomb_friction": ve}, one_rate_unload, "displacement")) == {"coulomb_friction"}


def test_a_step_rescued_by_its_refit_is_flagged(fmu_path, tmp_path):
    """A chain step whose first fit is worse than the model it extends (here a stalled fit put in the fit cache)
    is refitted from that model's optimum through the FMU; the refit is better, so the step is kept and flagged
    with the three RMSEs, in diagnosis.json's chain and in the report's chain section."""
    import json

    import effects_reference as er

    from fmusa.diagnose.fitcache import fit_to_json
    from fmusa.diagnose.measured import downsample
    from fmusa.diagnose.rank import Thresholds
    from fmusa.diagnose.report import _chain_section   # noqa: PLC2701
    from fmusa.diagnose.run import effect_chain

    truth = {"c_y": 2.0e5, "d_y": 150.0, "nl_ratio": 2.5, "nl_y_b": 5e-4, "F_offset": 25.0}
    kt, ku = [0.0, 1.0, 2.0], [0.0, 1.2e-3, 0.0]
    t = np.linspace(0.0, 2.0, 201)
    F = er.simulate(truth, "displacement", kt, ku, t) + np.random.default_rng(2).normal(0.0, 0.5, t.size)
    e = downsample(Experiment(name="lu", path=Path("lu.csv"), drive="displacement", t=t,
                              displacement=np.interp(t, kt, ku), force=F), 60)
    meas = np.asarray(e.force, float)
    base = _fit("none", {"c_y": 2.0e5, "d_y": 150.0}, 900.0 * meas.size, meas + 30.0)
    # the bend without the offset: 25 N off
    ext = _fit("nonlinear_stiffness", {k: truth[k] for k in ("c_y", "d_y", "nl_ratio", "nl_y_b")},
               625.0 * meas.size, meas - 25.0)
    stalled = _fit("nonlinear_stiffness+sensor_offset", {**ext.params, "F_offset": 0.0}, 2500.0 * meas.size,
                   meas - 50.0)
    (tmp_path / "nonlinear_stiffness+sensor_offset.json").write_text(json.dumps(fit_to_json(stalled, "k")))
    removed: list = []
    steps = effect_chain(base, ext, "nonlinear_stiffness", ["nonlinear_stiffness"], "nonlinear_stiffness",
                         ("sensor_offset",), [e], "displacement", str(fmu_path), 1, None, 1, tmp_path, "k", False,
                         Thresholds(), 2, removed=removed)
    assert [s["effect"] for s in steps] == ["nonlinear_stiffness", "sensor_offset"] and not removed
    note = steps[1]["refit"]
    assert note["first_rmse"] == pytest.approx(50.0) and note["previous_rmse"] == pytest.approx(25.0)
    assert note["refit_rmse"] < 2.0 and steps[1]["fit"].params["F_offset"] == pytest.approx(25.0, rel=0.1)
    assert "refit" not in steps[0]
    diag = {"chain": [{k: v for k, v in s.items() if k != "fit"} for s in steps], "chain_removed": removed,
            "data": {"drive": "displacement", "response": "force"}}
    text = _chain_section(diag)
    assert "#2 (refitted)" in text and "Step 2 (`sensor_offset`) was refitted" in text
