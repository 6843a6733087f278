"""The real shear tests (data/shear-c67) against the authors' own analysis, an independent one; and the
shear report on other specimens of the same data set says what those data show, not what H1–H3 showed."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

import numpy as np

from fmusa.applications.shear_c67 import bilinear
from fmusa.applications.shear_c67 import data as shear_c67
from fmusa.applications.shear_c67.study import fit_bilinear_per_test, run_shear_diagnosis
from fmusa.diagnose.run import diagnose

ROOT = Path(__file__).resolve().parents[1]
#: The repository's copy of the data (specimens H1–H3 and H10–H21, copied unchanged; H4–H9 are never used).
SHEAR = ROOT / "data" / "shear-c67"


def test_two_phase_fit_matches_the_authors_breakpoint_analysis(fmu_path):
    """At 1 and 10 mm/s (hundreds of samples per test) our continuous bilinear fit through the FMU must
    agree with the authors' two-line fit: second stiffness within 3 %, first within 10 %, breakpoint
    within 0.1 mm; the two-line fit as the authors did it within 1 %, 2 % and 0.02 mm."""
    tests = shear_c67.list_tests(SHEAR)
    pick = tests[((tests.specimen == "H1") & (tests.direction == "Ant") & (tests.rate_mm_s == 1))
                 | ((tests.specimen == "H2") & (tests.direction == "Pos") & (tests.rate_mm_s == 10))]
    assert len(pick) == 2
    ours = fit_bilinear_per_test(pick, str(fmu_path), max_points=300)
    cmp_ = ours.merge(shear_c67.authors_bilinear(SHEAR), on=["specimen", "direction", "rate_mm_s"])
    for _, r in cmp_.iterrows():
        # fmusa's two-phase model through the FMU (from the unloaded start, 300 block means)
        assert abs(r.model_k2_N_mm / r.stiffness_2 - 1) < 0.03, r.to_dict()
        assert abs(r.model_k1_N_mm / r.stiffness_1 - 1) < 0.10, r.to_dict()
        assert abs(r.model_bp_mm - r.breakpoint_mm) < 0.1, r.to_dict()
        # the chain's model (issue 22): the bend with the first phase's start free (a force offset, the
        # authors' free intercept), through the FMU: first stiffness within 5 %, second within 2 %
        assert abs(r.toe_k1_N_mm / r.stiffness_1 - 1) < 0.05, r.to_dict()
        assert abs(r.toe_k2_N_mm / r.stiffness_2 - 1) < 0.02, r.to_dict()
        # the authors' method redone: two continuous lines, free intercept, every sample
        assert abs(r.k2_N_mm / r.stiffness_2 - 1) < 0.01, r.to_dict()
        assert abs(r.k1_N_mm / r.stiffness_1 - 1) < 0.02, r.to_dict()
        assert abs(r.bp_mm - r.breakpoint_mm) < 0.02, r.to_dict()
        assert r.rmse_N < 0.6 * r.linear_rmse_N      # the bend is real: a line fits far worse


def test_two_lines_recover_a_known_curve():
    """Two continuous lines with a free intercept (a toe: the force starts at -20 N) and 1 N noise, bending
    up or down (k1 > k2), loaded anteriorly and posteriorly, with 30 (a 100 mm/s record) and 2000 samples:
    stiffnesses within 2 %, breakpoint within 0.02 mm, reported in the raw frame (dF/dx > 0, Pos breakpoint
    negative)."""
    rng = np.random.default_rng(4)
    for n, sign, k1, k2 in [(n, sign, k1, k2) for n in (30, 2000) for sign in (1.0, -1.0)
                            for k1, k2 in ((90.0, 230.0), (400.0, 150.0))]:   # stiffening and softening bends
        u = np.linspace(0.03, 1.6, n)
        f = -20.0 + k1 * u + (k2 - k1) * np.maximum(u - 0.6, 0.0) + rng.normal(0, 1.0, n)
        out = bilinear.fit_two_lines(sign * u, sign * f)
        assert out["k1_N_mm"] == pytest.approx(k1, rel=0.02), (n, sign, out)
        assert out["k2_N_mm"] == pytest.approx(k2, rel=0.02), (n, sign, out)
        assert out["bp_mm"] == pytest.approx(sign * 0.6, abs=0.02), (n, sign, out)
        assert out["intercept_1_N"] == pytest.approx(sign * -20.0, abs=2.0)


def test_through_the_unloaded_start_the_first_stiffness_is_off():
    """Why the FMU's two-phase model differs from the authors on k1: a spring that starts unloaded must pass
    through the first sample, so a toe (force lagging the displacement) bends its first line. The free
    intercept recovers k1; a line forced through the start does not."""
    u = np.linspace(0.0, 1.5, 400)
    f = np.where(u < 0.6, -15.0 + 100.0 * u, -15.0 + 60.0 + 250.0 * (u - 0.6))
    f = np.maximum(f, 0.0)                               # the toe: no force until 0.15 mm
    free = bilinear.fit_two_lines(u, f)
    X = np.c_[u - u[0], np.maximum(u - free["bp_mm"], 0.0)]
    through, *_ = np.linalg.lstsq(X, f - f[0], rcond=None)
    assert abs(free["k1_N_mm"] / 100.0 - 1) < abs(through[0] / 100.0 - 1)
    assert abs(through[0] / 100.0 - 1) > 0.05


def test_at_100_mm_s_the_damping_takes_the_first_phase_so_the_model_holds_it_at_0(fmu_path):
    """Issue 11, item 2. At 100 mm/s the drive is still accelerating through the first phase (H1 and H3
    anterior pass it at 0.43 and 0.49 of the record's mean rate), so a damping d_y fitted per test makes
    d_y*v rise like a spring force and takes the first phase: c_y 14–15 N/mm against the authors' 94–102.
    fmusa's two-phase model is compared with d_y held at 0; its k1 is then the continuous two-line least
    squares through the unloaded start (recomputed here without the FMU) and near the authors' (measured
    138.7 vs 102.2 and 95.8 vs 93.6 N/mm). At 10 mm/s the drive is steady and the damping takes nothing.
    The report says so."""
    from fmusa.applications.shear_c67.report import _bilinear_section
    from fmusa.applications.shear_c67.study import summarize

    tests = shear_c67.list_tests(SHEAR)
    pick = tests[tests.specimen.isin(["H1", "H3"]) & (tests.direction == "Ant") & tests.rate_mm_s.isin([10.0, 100.0])]
    assert len(pick) == 4
    ours = fit_bilinear_per_test(pick, str(fmu_path), max_points=300)
    cmp_ = ours.merge(shear_c67.authors_bilinear(SHEAR), on=["specimen", "direction", "rate_mm_s"])
    for (_, r), (_, row) in zip(cmp_.iterrows(), pick.iterrows()):
        exp = shear_c67.load_test(row, max_points=300)
        u, f = 1000.0 * exp.displacement, exp.force          # anterior: loading is positive

        def through(b: float) -> tuple[float, np.ndarray]:
            X = np.c_[u, np.maximum(u - b, 0.0)]
            beta, *_ = np.linalg.lstsq(X, f, rcond=None)
            e = f - X @ beta
            return float(e @ e), beta
        b = min(np.linspace(0.02, 0.98, 961) * u.max(), key=lambda bb: through(bb)[0])
        assert r.model_k1_N_mm == pytest.approx(through(b)[1][0], rel=0.02), r.to_dict()
        if r.rate_mm_s == 100:
            assert r.phase1_rate_ratio < 0.6, r.to_dict()
            assert r.damped_share > 0.5 and r.damped_k1_N_mm < 0.25 * r.stiffness_1, r.to_dict()
            assert r.damped_rmse_N < r.model_rmse_N                    # the least squares prefer it
            assert abs(r.model_k1_N_mm / r.stiffness_1 - 1) < 0.4, r.to_dict()
        else:
            assert r.phase1_rate_ratio > 0.75, r.to_dict()
            assert r.damped_share < 0.1, r.to_dict()
            assert r.damped_k1_N_mm == pytest.approx(r.model_k1_N_mm, rel=0.05), r.to_dict()
    text = "\n".join(_bilinear_section(summarize({}, cmp_, {}), cmp_))
    assert "interface damping d_y held at 0" in text
    assert ("At 100 mm/s the damping force d_y·v then carries more than half of the model's force at its "
            "breakpoint in 2 of 2 tests") in text
    assert "in those tests the drive is still accelerating through the first phase" in text
    assert "At 10 mm/s the damping force" not in text
    assert "| H1 Ant | 100 | tuning |" in text and "(k1 with d_y fitted)" in text


def test_split_of_specimens_is_fixed():
    assert bilinear.TUNING == ("H1", "H2", "H3", "H10", "H11", "H12", "H13", "H14")
    assert bilinear.split(["H21", "H2", "H15", "H10"]) == {"tuning": ["H2", "H10"], "held_out": ["H21", "H15"]}


@pytest.mark.skipif(not (SHEAR / "H21").is_dir(), reason="data/shear-c67 without H15–H21")
def test_two_lines_match_the_authors_on_held_out_specimens():
    """Issue 11: median |Δk1| <= 5 % and |Δk2| <= 2 % per rate on the specimens the breakpoint rule was not
    chosen on (H15–H21), and on the tuning ones (H1–H3, H10–H14). Measured (2026-11-30): held out k1 0.02 /
    0.18 / 1.06 %, k2 0.00 % at 1 / 10 / 100 mm/s; tuning k1 0.02 / 0.08 / 1.92 %, k2 0.00 %."""
    from fmusa.applications.shear_c67.study import summarize

    tests = shear_c67.list_tests(SHEAR)
    ours = fit_bilinear_per_test(tests, None, 300)
    assert ours["model_k1_N_mm"].isna().all()            # no FMU asked for
    cmp_ = ours.merge(shear_c67.authors_bilinear(SHEAR), on=["specimen", "direction", "rate_mm_s"], how="left")
    assert cmp_["stiffness_1"].notna().all()
    s = summarize({}, cmp_, {})
    parts = s["bilinear_by_split"]
    assert parts["held_out"]["specimens"] == [f"H{k}" for k in range(15, 22)]
    assert set(parts["tuning"]["specimens"]) == set(bilinear.TUNING)
    for part in ("held_out", "tuning"):
        assert set(parts[part]["by_rate"]) == {"1", "10", "100"}
        for rate, v in parts[part]["by_rate"].items():
            assert v["k1_rel_diff_median"] <= 0.05, (part, rate, v)
            assert v["k2_rel_diff_median"] <= 0.02, (part, rate, v)
            assert v["breakpoint_abs_diff_median_mm"] <= 0.05, (part, rate, v)


def test_monotonic_real_tests_name_a_stiffening_bend(fmu_path):
    """H2 anterior, three rates jointly: the curve bends upwards (stiffens). Without unloading, yield and
    an elastic bend look alike only when the bend softens; a stiffening bend is one yield cannot make, so
    yield must not be called a look-alike here."""
    tests = shear_c67.list_tests(SHEAR)
    g = tests[(tests.specimen == "H2") & (tests.direction == "Ant")]
    exps = [shear_c67.load_test(r, max_points=150) for _, r in g.iterrows()]
    d = diagnose(exps, "displacement", fmu_path=fmu_path, workers=2, max_starts=4,
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


def _copy_specimen(dst: Path, specimen: str, direction: str) -> None:
    """One specimen's tests of one direction from the repository's copy, with its rows of the two tables."""
    folder = f"H{int(specimen[1:]):02d}"
    (dst / folder).mkdir(parents=True, exist_ok=True)
    for p in (SHEAR / folder).glob(f"{specimen}_C67_{direction}_*_mm_s.csv"):
        shutil.copy(p, dst / folder / p.name)
    for table in ("test_info.csv", "specimen_info.csv"):
        df = pd.read_csv(SHEAR / table)
        keep = df[df["ID"] == specimen]
        if "direction" in keep:
            keep = keep[keep["direction"] == direction]
        out = dst / table
        keep.to_csv(out, mode="a" if out.exists() else "w", header=not out.exists(), index=False)


def test_report_on_other_specimens_names_them(fmu_path, tmp_path):
    """H10 anterior and H11 posterior (three rates each, few samples, two candidates): the report names
    those specimens, directions, rates and counts, and nothing of H1–H3 or of the other tests of the
    repository's copy."""
    data = tmp_path / "shear"
    _copy_specimen(data, "H10", "Ant")
    _copy_specimen(data, "H11", "Pos")
    out = tmp_path / "out"
    # two workers: the units side by side, each in a worker with its fits one after another
    s = run_shear_diagnosis(out, data, fmu_path=str(fmu_path), max_points=60, workers=2, max_starts=2,
                            candidates=("nonlinear_stiffness", "sensor_offset"))
    assert list(s["groups"]) == ["H10_Ant", "H11_Pos"]
    # the same diagnosis as the unit's own, run here with its fits one after another
    from fmusa.applications.shear_c67 import data as shear_c67
    from fmusa.diagnose.run import run_diagnosis

    tests = shear_c67.list_tests(data)
    exps = [shear_c67.load_test(r, max_points=60) for _, r in tests[tests.specimen == "H11"].iterrows()]
    alone = run_diagnosis(exps, "displacement", tmp_path / "alone", fmu_path=str(fmu_path), workers=1, max_starts=2,
                          candidates=("nonlinear_stiffness", "sensor_offset"), progress=False)
    unit = json.loads((out / "H11_Pos" / "diagnosis.json").read_text())
    # (not the run count: a process times the FMU's sensitivities once, two counted runs, and this one may have)
    assert unit["effect"] == alone["effect"]
    assert [r["effect"] for r in unit["ranking"]] == [r["effect"] for r in alone["ranking"]]
    for name, v in alone["baseline"]["params"].items():
        assert unit["baseline"]["params"][name] == pytest.approx(v, rel=1e-12), name
    assert s["data"]["specimens"] == ["H10", "H11"] and s["data"]["tests"] == 6
    assert json.loads((out / "summary.json").read_text())["data"]["specimens"] == ["H10", "H11"]
    text = (out / "report.md").read_text()
    assert f"# Diagnosis of the C6/C7 shear tests ({data})" in text
    assert "Measured data (specimens H10 and H11, anterior and posterior shear at 1, 10 and 100 mm/s" in text
    assert "block-averaged to at most 60 samples" in text
    assert "three rates fitted jointly" in text and "fitted to the other two" in text
    assert "e.g. `H10_Ant/report.md`" in text
    assert "ranking of both candidates" in text and "over the two units" in text
    assert "All 6 tests load monotonically" in text
    assert "| H10 Ant | 100 |" in text and "| H11 Pos | 1 |" in text
    specimens = set(re.findall(r"\bH\d+\b", text))
    assert specimens == {"H10", "H11"}, specimens
    for stale in ("H1–H3", "six units", "18 tests", "six candidates", "PROVENANCE.md", "at most 300 samples"):
        assert stale not in text, stale


def test_missing_data_folder_is_named_with_the_fix(tmp_path):
    """`fmusa diagnose-shear` run outside the repository: the error names the folder, where it looked, and
    --data; nothing is written."""
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "fmusa.cli", "diagnose-shear", "--out", str(out)], cwd=tmp_path,
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert "data/shear-c67: shear-c67 data folder not found" in r.stderr
    assert str(tmp_path) in r.stderr and "--data FOLDER" in r.stderr
    assert not out.exists()


def test_report_states_only_what_one_rate_can_show(tmp_path):
    """A unit tested at one rate with a softening bend: the report says one test per unit, held-out blocks,
    that the protocol cannot tell yield from the bend, and that rates say nothing here (no FMU needed)."""
    from fmusa.applications.shear_c67.report import write_report
    from fmusa.applications.shear_c67.study import summarize

    ranking = [{"effect": "nonlinear_stiffness", "significant": True, "heldout_rmse_ratio": 0.5, "delta_bic": -40.0,
                "rmse_ratio": 0.5},
               {"effect": "yield_softening", "significant": True, "heldout_rmse_ratio": 0.55, "delta_bic": -35.0,
                "rmse_ratio": 0.52}]
    diag = {"effect": "nonlinear_stiffness", "indistinguishable": [{"effect": "yield_softening"}],
            "gain": {"heldout_rmse_ratio": 0.5, "delta_bic": -40.0},
            "effect_params": {"nl_ratio": {"value": 0.6}, "nl_y_b": {"value": 4e-4}},
            "baseline": {"params": {"c_y": 2e5}}, "ranking": ranking, "leftover": "",
            "data": {"experiments": [{"name": "H12_C67_Ant_10_mm_s"}],
                     "heldout": "4 contiguous blocks in time (leave one out)"},
            "protocol": {"unloading": False, "hold": False, "several_rates": False, "several_rates_or_hold": False}}
    cmp_ = pd.DataFrame([{"specimen": "H12", "direction": "Ant", "rate_mm_s": 10.0, "k1_N_mm": 200.0,
                          "k2_N_mm": 120.0, "bp_mm": 0.4, "rmse_N": 2.0, "linear_rmse_N": 9.0,
                          "linear_k_N_mm": 150.0, "peak_N": 150.0, "points": 180, "stiffness_1": 205.0,
                          "stiffness_2": 121.0, "breakpoint_mm": 0.41, "peak_load_N": 150.0, "peak_disp_mm": 1.0}])
    data = {"root": "elsewhere/shear", "provenance": None, "specimens": ["H12"], "directions": ["Ant"],
            "rates_mm_s": [10.0], "tests": 1, "max_points": 300}
    text = write_report(summarize({"H12_Ant": diag}, cmp_, data), cmp_, tmp_path, []).read_text()
    assert "Measured data (specimen H12, anterior shear at 10 mm/s under displacement control)." in text
    assert "(one test per unit)" in text and "4 contiguous blocks in time" in text
    assert "The one test loads monotonically to the peak and stops" in text
    assert "softens in 1 of the 1 units" in text and "`yield_softening` itself is significant in 1 of 1" in text
    assert "these tests have neither" in text
    assert "Every unit was tested at one rate only" in text
    assert "At 10 mm/s the two analyses agree closely" in text
    assert set(re.findall(r"\bH\d+\b", text)) == {"H12"}
    for stale in ("three rates", "100 mm/s", "posterior", "Maxwell branch improves"):
        assert stale not in text, stale
