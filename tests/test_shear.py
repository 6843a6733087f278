"""The real shear tests (data/shear-c67) against the authors' own analysis, an independent one."""
from __future__ import annotations

from fmusa.diagnose import run as dg
from fmusa.applications.shear_c67 import data as shear_c67
from fmusa.applications.shear_c67.study import fit_bilinear_per_test


def test_two_phase_fit_matches_the_authors_breakpoint_analysis(fmu_path):
    """At 1 and 10 mm/s (hundreds of samples per test) our continuous bilinear fit through the FMU must
    agree with the authors' two-line fit: second stiffness within 3 %, first within 10 %, breakpoint
    within 0.1 mm."""
    tests = shear_c67.list_tests()
    pick = tests[((tests.specimen == "H1") & (tests.direction == "Ant") & (tests.rate_mm_s == 1))
                 | ((tests.specimen == "H2") & (tests.direction == "Pos") & (tests.rate_mm_s == 10))]
    assert len(pick) == 2
    ours = fit_bilinear_per_test(pick, str(fmu_path), max_points=300)
    cmp_ = ours.merge(shear_c67.authors_bilinear(), on=["specimen", "direction", "rate_mm_s"])
    for _, r in cmp_.iterrows():
        assert abs(r.k2_N_mm / r.stiffness_2 - 1) < 0.03, r.to_dict()
        assert abs(r.k1_N_mm / r.stiffness_1 - 1) < 0.10, r.to_dict()
        assert abs(r.bp_mm - r.breakpoint_mm) < 0.1, r.to_dict()
        assert r.rmse_N < 0.5 * r.linear_rmse_N      # the bend is real: a line fits far worse


def test_monotonic_real_tests_name_a_stiffening_bend(fmu_path):
    """H2 anterior, three rates jointly: the curve bends upwards (stiffens). Without unloading, yield and
    an elastic bend look alike only when the bend softens; a stiffening bend is one yield cannot make, so
    yield must not be called a look-alike here."""
    tests = shear_c67.list_tests()
    g = tests[(tests.specimen == "H2") & (tests.direction == "Ant")]
    exps = [shear_c67.load_test(r, max_points=150) for _, r in g.iterrows()]
    d = dg.diagnose(exps, "displacement", fmu_path=fmu_path, workers=2, max_starts=4,
                    candidates=("nonlinear_stiffness", "yield_softening", "sensor_offset"))
    assert d["protocol"] == {"unloading": False, "hold": False, "several_rates": True,
                             "several_rates_or_hold": True}
    assert d["effect"] == "nonlinear_stiffness"
    assert d["gain"]["heldout_rmse_ratio"] < 0.7
    assert d["effect_params"]["nl_ratio"]["value"] > 1.2
    assert not any(i["effect"] == "yield_softening" for i in d["indistinguishable"])
    assert not next(r for r in d["ranking"] if r["effect"] == "yield_softening")["significant"]
    assert d["residuals"]["extended"]["structured"]        # real data: structure is left, and it is said
    assert d["leftover"]
