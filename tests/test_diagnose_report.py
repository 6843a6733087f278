"""Figures and report of `fmusa diagnose` (fmusa.diagnose.figures, fmusa.diagnose.report) on a small real diagnosis.

The diagnosis runs the real pipeline (FMU, calibration, held-out refits, ranking, residual statistics) on
a short synthetic load-hold-unload test from tests/effects_reference.py, with two candidates and two starts
so that it costs a few seconds.
"""
from __future__ import annotations

import re
import struct
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from effects_reference import synthesize  # noqa: E402

from fmusa.diagnose import measured as fm  # noqa: E402
from fmusa.diagnose import views  # noqa: E402
from fmusa.diagnose.figures import write_figures  # noqa: E402
from fmusa.diagnose.report import write_report  # noqa: E402
from fmusa.diagnose.run import diagnose  # noqa: E402
from fmusa.format import fmt  # noqa: E402

FIGURES = ("fit_time.png", "loops.png", "residuals.png", "ranking.png")


def _diagnose(fmu_path, effect: str, drive: str, seed: int):
    df, truth = synthesize(effect, drive, seed)
    e = fm.Experiment(name=f"{effect}_{drive}_{seed}", path=f"synthetic/{effect}_{seed}.csv", drive=drive,
                      t=df["time"].to_numpy(), displacement=df["displacement"].to_numpy(),
                      force=df["force"].to_numpy())
    e = fm.downsample(e, 120)
    diag = diagnose([e], drive, fmu_path=fmu_path, candidates=("sensor_offset", "coulomb_friction"),
                       workers=1, max_starts=2)
    return diag, [e], truth


@pytest.fixture(scope="module")
def friction(fmu_path, tmp_path_factory):
    diag, exps, truth = _diagnose(fmu_path, "coulomb_friction", "displacement", 1)
    out = tmp_path_factory.mktemp("diag_friction")
    figs = write_figures(diag, exps, out)
    report = write_report(diag, exps, out, figs)
    return diag, exps, out, figs, report


def _png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n", f"{path.name} is not a PNG"
    assert head[12:16] == b"IHDR"
    return struct.unpack(">II", head[16:24])


def _check_figures(out: Path, figs) -> None:
    assert [Path(p).name for p in figs] == list(FIGURES)
    for name in FIGURES:
        p = out / "figures" / name
        assert p.exists(), name
        w, h = _png_size(p)
        assert 400 <= w <= 4000 and 250 <= h <= 4000, (name, w, h)
        assert p.stat().st_size > 15_000, f"{name} is suspiciously small ({p.stat().st_size} bytes)"


def test_files_exist_and_figures_are_sane_pngs(friction):
    diag, exps, out, figs, report = friction
    assert report == out / "report.md" and report.exists()
    _check_figures(out, figs)


def test_report_contains_the_numbers_of_the_diagnosis(friction):
    diag, exps, out, figs, report = friction
    text = report.read_text()
    assert diag["effect"] == "coulomb_friction"          # the friction is strong: the pipeline names it
    assert f"# Diagnosis: `{diag['effect']}`" in text
    gain = diag["gain"]
    assert f"(ratio {views.ratio_text(gain['rmse_ratio'])})" in text
    assert f"(ratio {views.ratio_text(gain['heldout_rmse_ratio'])})" in text
    assert f"ΔBIC = {views.delta_text(gain['delta_bic'])}" in text
    assert f"ΔAIC = {views.delta_text(gain['delta_aic'])}" in text
    # the ranking table: one row per candidate with its own ratios, in ranking order
    rows = [ln for ln in text.splitlines() if re.match(r"^\| \d+ \| `", ln)]
    assert len(rows) == len(diag["ranking"]) == 2
    for i, (r, ln) in enumerate(zip(diag["ranking"], rows), 1):
        cells = [c.strip() for c in ln.strip("|").split("|")]
        assert cells[0] == str(i)
        assert cells[1].startswith(f"`{r['effect']}`")
        assert cells[2] == ("yes" if r["significant"] else "no")
        assert cells[6] == views.ratio_text(r["rmse_ratio"])
        assert cells[7] == views.ratio_text(r["heldout_rmse_ratio"])
        assert cells[9] == views.delta_text(r["delta_bic"])
    # parameters in natural units with their intervals: the friction force in N, the stiffness in N/mm
    fric = diag["effect_params"]["fric_F"]
    assert f"fric_F (Coulomb friction force) = {fmt(fric['value'], 4)} N" in text
    c = diag["extended"]["params"]["c_y"]
    assert fmt(c * 1e-3, 4) in text and "N/mm" in text
    # residual diagnosis before / after with the statistics asked for
    for word in ("Ljung–Box", "runs test", "lag-1 autocorrelation", "Residuals before and after",
                 "Candidates the data cannot tell apart", "Caveats", "assume white", "too narrow"):
        assert word in text, word
    assert f"{diag['residuals']['baseline']['lag1_autocorrelation']:.3f}" in text
    assert "held-out refits start from the all-data optimum" in text
    for name in FIGURES:
        assert f"(figures/{name})" in text


def test_natural_units():
    assert views.natural("c_y", 3.7e5) == (pytest.approx(370.0), "N/mm")
    assert views.natural("gap", 2e-4) == (pytest.approx(0.2), "mm")
    assert views.natural("fric_F", 12.0) == (12.0, "N")
    assert views.natural("ve_tau", 0.5) == (0.5, "s")
    assert views.natural("nl_ratio", 2.0) == (2.0, "")


def test_report_without_effect(fmu_path, tmp_path):
    """Clean data without an effect: the report says none, gives the best candidate's numbers, and the
    figures still draw (no 'after' row)."""
    diag, exps, truth = _diagnose(fmu_path, "none", "force", 3)
    figs = write_figures(diag, exps, tmp_path)
    report = write_report(diag, exps, tmp_path, figs)
    _check_figures(tmp_path, figs)
    text = report.read_text()
    assert f"# Diagnosis: `{diag['effect']}`" in text
    if diag["effect"] == "none":
        best = diag["ranking"][0]
        assert f"The best-ranked candidate, `{best['effect']}`" in text
        assert views.ratio_text(best["heldout_rmse_ratio"]) in text
    assert "[mm]" in text                                  # force drive: residuals and RMSE in mm
