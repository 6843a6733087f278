"""Fault matrix of `fmusa diagnose`: input whose answer must not be taken at face value.

Each test reproduces one fault as a user would meet it and asserts the behaviour (issue 13, item 9):

* a unit mistake (a file in mm or kN read as m or N) is fitted as well as the right unit, only 1000 times
  off, so the diagnosis warns, in the command's output, diagnosis.json and report.md, naming the likely unit
  and the option that fixes it, and does not warn on the real shear data or the synthetic tests;
* on data the baseline itself generated (noise-free or nearly), every extra parameter passes the statistical
  tests by fitting round-off: the diagnosis must name no effect, in both drive modes, including the reported
  cases (a 400 N monotonic ramp at 0.25 mm/s; baseline ramps that named a nonlinear stiffness);
* an effect that is real but smaller than the physical floor is not named, one above it is.

The real FMU and the real ``fmusa`` command are used; the data come from tests/effects_reference.py (an
independent scipy implementation of fmu/MODEL.md) and from data/shear-c67.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import effects_reference as er  # noqa: E402

from fmusa.diagnose.effects import CANDIDATES  # noqa: E402
from fmusa.diagnose.measured import ColumnSpec, Experiment, downsample, load_experiment  # noqa: E402
from fmusa.diagnose.report import write_report  # noqa: E402
from fmusa.diagnose.run import diagnose  # noqa: E402
from fmusa.diagnose.units import check_units, model_scale  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHEAR = ROOT / "data" / "shear-c67"


def fmusa_cli(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fmusa.cli", *args], capture_output=True, text=True,
                          timeout=timeout)


def _exp(df: pd.DataFrame, drive: str, name: str = "test") -> Experiment:
    return Experiment(name=name, path=Path(f"{name}.csv"), drive=drive, t=df.time.values,
                      displacement=df.displacement.values, force=df.force.values)


# ----------------------------------------------------------------------------------------------- units
def test_displacement_in_mm_read_as_m_is_named(tmp_path, fmu_path):
    """A shear test (mm, N) run as the README shows it but without --displacement-unit mm: a 1 mm peak is read
    as 1 m. The command warns before the fits, names mm and the option, and says so in diagnosis.json and
    report.md; with the option the same file gives no warning."""
    csv = SHEAR / "H01" / "H1_C67_Ant_10_mm_s.csv"
    common = ["--drive", "displacement", "--displacement-column", "disp_x_mm", "--force-column", "Fx_N",
              "--rate", "10 mm/s", "--fmu", str(fmu_path), "--candidates", "sensor_offset", "--starts", "1",
              "--max-points", "60", "--workers", "1"]
    out = tmp_path / "wrong"
    r = fmusa_cli("diagnose", str(csv), "--out", str(out), *common)
    assert r.returncode == 0, r.stderr
    warning = next(ln for ln in r.stdout.splitlines() if ln.startswith("warning: units"))
    assert "likely in mm, not m" in warning and "--displacement-unit mm" in warning, warning
    assert r.stdout.index("warning: units") < r.stdout.index("fitted")       # before the fits, not after
    d = json.loads((out / "diagnosis.json").read_text())
    [w] = d["warnings"]
    assert w["fix"] == "--displacement-unit mm" and w["likely_units"] == {"displacement": "mm"}
    assert "displacement" in w["outside"]
    peak_as_read = float(pd.read_csv(csv)["disp_x_mm"].abs().max())        # the number in the file, taken as m
    assert d["units"]["experiments"][0]["magnitudes"]["displacement"] == pytest.approx(
        peak_as_read - float(pd.read_csv(csv)["disp_x_mm"].iloc[0]), rel=0.05)   # zeroed drive
    assert d["units"]["experiments"][0]["magnitudes"]["displacement"] > d["units"]["ranges"]["displacement"][1]
    report = (out / "report.md").read_text()
    assert "## Warnings" in report and "--displacement-unit mm" in report

    ok = tmp_path / "right"
    r = fmusa_cli("diagnose", str(csv), "--out", str(ok), "--displacement-unit", "mm", *common)
    assert r.returncode == 0, r.stderr
    assert "warning" not in r.stdout
    d = json.loads((ok / "diagnosis.json").read_text())
    assert d["warnings"] == [] and "## Warnings" not in (ok / "report.md").read_text()


def test_force_in_kn_read_as_n_is_named(tmp_path, fmu_path):
    """A test written in kN, read with the default unit (N): the stiffness it implies is 1000 times too low for
    the FMU; the check names kN and --force-unit kN (nothing is fitted)."""
    df = pd.read_csv(SHEAR / "H01" / "H1_C67_Ant_1_mm_s.csv", usecols=["disp_x_mm", "Fx_N"])
    csv = tmp_path / "kN.csv"
    pd.DataFrame({"displacement": df.disp_x_mm * 1e-3, "force": df.Fx_N * 1e-3}).to_csv(csv, index=False)
    e = load_experiment(csv, "displacement", ColumnSpec(rate="1 mm/s"))
    [w] = check_units([e], model_scale(fmu_path))["warnings"]
    assert w["fix"] == "--force-unit kN" and "likely in kN, not N" in w["message"], w["message"]
    e = load_experiment(csv, "displacement", ColumnSpec(rate="1 mm/s", force_unit="kN"))
    assert check_units([e], model_scale(fmu_path))["warnings"] == []


def test_no_units_warning_on_the_shear_data_or_the_synthetic_tests(fmu_path):
    """Every test of data/shear-c67 as the shear application reads it (mm, N), and the synthetic specimens of
    every effect, drive and protocol the diagnose tests use: plausible, no warning."""
    from fmusa.applications.shear_c67 import data as shear_c67

    scale = model_scale(fmu_path)
    tests = shear_c67.list_tests(SHEAR)
    exps = [shear_c67.load_test(row, max_points=300) for _, row in tests.iterrows()]
    assert len(exps) == len(tests) >= 90
    assert check_units(exps, scale)["warnings"] == []
    count = 0
    for drive in er.DRIVES:
        for effect in er.EFFECTS:
            for k, protocol in enumerate(er.PROTOCOLS):
                frames, _ = er.synthesize_protocol(effect, drive, 100 * k + 7, protocol)
                rep = check_units([_exp(f, drive, f"r{i}") for i, f in enumerate(frames)], scale)
                assert rep["warnings"] == [], (drive, effect, protocol, rep["warnings"])
                count += 1
    assert count == 2 * len(er.EFFECTS) * 8 == 2 * 8 * 8


# ----------------------------------------------------------------------------------------------- effect size
def _names_nothing(d: dict) -> None:
    """No effect named; whatever passed the statistical tests changed the prediction by less than the floor."""
    info = [(r["effect"], r["statistically_significant"], f"{r['effect_size']['size']:.3g}",
             f"{r['effect_size']['floor']:.3g}") for r in d["ranking"]]
    assert d["effect"] == "none", info
    assert d["gain"]["rmse_ratio"] == 1.0
    for r in d["ranking"]:
        if r["statistically_significant"]:
            assert r["effect_size"]["size"] <= r["effect_size"]["floor"], info


def test_baseline_ramp_of_the_report_names_nothing(tmp_path, fmu_path):
    """The reported case: a 400 N monotonic ramp, c = 8e5 N/m, d = 500 N·s/m, 0.25 mm/s (0.5 mm in 2 s, the
    damper's 0.125 N from the start), noise-free, as a CSV through the command: it named an effect (a
    0.12 N sensor offset); it must name none."""
    c, d_, rate = 8e5, 500.0, 0.25e-3
    T = 400.0 / c / rate
    t = np.arange(0, int(round(T * 100)) + 1) / 100
    kt, ku = np.array([0.0, T]), np.array([0.0, 400.0 / c])
    force = er.simulate({"c_y": c, "d_y": d_}, "displacement", kt, ku, t)
    assert force[-1] == pytest.approx(400.0 + d_ * rate) and force[1] == pytest.approx(c * rate * 0.01 + d_ * rate)
    csv = tmp_path / "ramp.csv"
    pd.DataFrame({"time": t, "displacement": np.interp(t, kt, ku), "force": force}).to_csv(csv, index=False)
    out = tmp_path / "out"
    r = fmusa_cli("diagnose", str(csv), "--drive", "displacement", "--out", str(out), "--fmu", str(fmu_path),
                  "--workers", "2")
    assert r.returncode == 0, r.stderr
    assert "effect: none" in r.stdout and "warning" not in r.stdout
    d = json.loads((out / "diagnosis.json").read_text())
    _names_nothing(d)
    assert {r["effect"] for r in d["ranking"]} == set(CANDIDATES)
    assert d["baseline"]["params"]["c_y"] == pytest.approx(c, rel=1e-3)


@pytest.mark.parametrize("drive,protocol,noise", [
    ("displacement", "ramp", 0.0),               # named nonlinear_stiffness (nl_ratio ~1) before
    ("displacement", "ramps, 2 rates", 0.0),     # named sensor_offset (-0.0 N) before
    ("force", "ramp", 0.0),                      # named nonlinear_stiffness before
    ("force", "ramps, 2 rates", 0.0),            # named sensor_offset (0.0 m) before
    # tiny noise: controls, which named nothing before too (22 s together: --run-slow)
    pytest.param("displacement", "load-hold-unload", 1e-5, marks=pytest.mark.slow),
    pytest.param("force", "load-hold-unload", 1e-5, marks=pytest.mark.slow),
])
def test_data_of_the_baseline_name_nothing(drive, protocol, noise, fmu_path):
    """Tests generated by the baseline itself (effects_reference, no effect), noise-free or with 1e-5 of the
    peak: nothing is missing, so nothing may be named, whatever the statistics say."""
    frames, truth = er.synthesize_protocol("none", drive, 1, protocol, noise_rel=noise)
    exps = [downsample(_exp(f, drive, f"rate{i}"), 150) for i, f in enumerate(frames)]
    d = diagnose(exps, drive, fmu_path=fmu_path, workers=2)
    _names_nothing(d)
    assert d["warnings"] == []


def _offset_test(offset: float, fmu_path):
    """A load-hold-unload test (1 mm at 1 mm/s, hold 2 s, back, hold 1 s) of c = 3e5 N/m, d = 200 N·s/m with a
    force bias ``offset``, noise 1e-5 of the peak (0.003 N), diagnosed with the offset as candidate."""
    kt = np.array([0.0, 1.0, 3.0, 4.0, 5.0])
    ku = np.array([0.0, 1e-3, 1e-3, 0.0, 0.0])
    t = np.arange(0, 501) / 100
    clean = er.simulate({"c_y": 3e5, "d_y": 200.0, "F_offset": offset}, "displacement", kt, ku, t)
    rng = np.random.default_rng(5)
    force = clean + rng.normal(0.0, 1e-5 * np.max(np.abs(clean)), t.size)
    e = downsample(Experiment(name="offset", path=Path("offset.csv"), drive="displacement", t=t,
                              displacement=np.interp(t, kt, ku), force=force), 150)
    return diagnose([e], "displacement", fmu_path=fmu_path, workers=1, candidates=("sensor_offset",),
                    max_starts=2), e


def test_an_effect_below_the_floor_is_not_named_one_above_is(tmp_path, fmu_path):
    """A real force bias of 0.9 N on a 300 N test (0.3 % of the range, 300 times the noise) passes every
    statistical test but is below the floor (1 % of the force range, 3 N): not named, and the report says why.
    A bias of 15 N (5 %) is named, with its value. At the end of the test the specimen rests at zero, where the
    baseline predicts exactly 0 N, so the change the offset makes there is the bias itself."""
    small, e = _offset_test(0.9, fmu_path)
    [row] = small["ranking"]
    size = row["effect_size"]
    assert row["statistically_significant"] and not row["significant"], row
    assert small["effect"] == "none"
    assert 0.8 * 0.9 <= size["size"] <= 1.5 * 0.9
    assert size["floor"] == pytest.approx(0.01 * (np.max(e.force) - np.min(e.force)))
    assert size["size"] < size["floor"]
    text = write_report(small, [e], tmp_path, []).read_text()
    assert "does not matter physically" in text and "change of the prediction" in text

    big, _ = _offset_test(15.0, fmu_path)
    [row] = big["ranking"]
    assert big["effect"] == "sensor_offset" and row["significant"], row
    assert row["effect_size"]["size"] > row["effect_size"]["floor"]
    assert 0.8 * 15.0 <= row["effect_size"]["size"] <= 1.5 * 15.0
    assert big["effect_params"]["F_offset"]["value"] == pytest.approx(15.0, rel=0.05)
