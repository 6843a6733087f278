"""Intervals whose coverage is measured: synthetic tests with AR(1) noise of known φ and known parameters;
nominal 95 % intervals must cover the truth in 90–98 % of replicates, where the Gauss–Newton intervals
(white noise) fall far short. A closed-form response tests the interval method itself (fast, many
replicates); the FMU's two-phase curve tests it through calibrate (slow, 200 replicates per φ too).

`make test` runs one φ of each kind (200 replicates of the closed form, about 2 s); the full study
(φ = 0, 0.5, 0.8, 0.9, 0.95, 200 replicates each, both methods side by side, and through the FMU) is
``@pytest.mark.slow`` and writes out/coverage.md and out/coverage_fmu.md.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy import optimize

from fmusa.diagnose.intervals import AR1_SANDWICH, GAUSS_NEWTON, interval_report, prediction_band, sandwich_covariance

ROOT = Path(__file__).resolve().parents[1]
TRUTH = np.array([100.0, 30.0, np.log(0.15)])
Y = np.linspace(0.0, 1.0, 300)


def closed_form(theta: np.ndarray, y: np.ndarray = Y) -> np.ndarray:
    """A stiffening-then-linear force: c y + A (1 − exp(−y/b)), b on a log scale (as the optimiser sees it)."""
    c, a, b = theta[0], theta[1], np.exp(theta[2])
    return c * y + a * (1.0 - np.exp(-y / b))


def ar1_noise(n: int, phi: float, sd: float, rng: np.random.Generator) -> np.ndarray:
    """Stationary AR(1) noise of marginal SD ``sd``."""
    from scipy.signal import lfilter

    e = rng.normal(size=n)
    e[1:] *= np.sqrt(1 - phi ** 2)                 # e[0] already has the stationary variance
    return lfilter([1.0], [1.0, -phi], e) * sd


def coverage(phi: float, replicates: int, seed: int) -> dict:
    """Share of replicates whose 95 % interval covers each true parameter: the chosen (AR(1) sandwich or
    Gauss–Newton where the residuals are white) and Gauss–Newton."""
    rng = np.random.default_rng(seed)
    hit_ch = np.zeros(3)
    hit_gn = np.zeros(3)
    methods = set()
    for _ in range(replicates):
        F = closed_form(TRUTH) + ar1_noise(len(Y), phi, 2.0, rng)
        res = optimize.least_squares(lambda th: closed_form(th) - F, TRUTH * 1.1, method="trf")
        rep = interval_report(res.jac, res.fun, res.x)
        hit_ch += (rep["lower"] <= TRUTH) & (TRUTH <= rep["upper"])
        lo, hi = rep["gauss_newton"]
        hit_gn += (lo <= TRUTH) & (TRUTH <= hi)
        methods.add(rep["method"])
    return {"chosen": hit_ch / replicates, "gauss_newton": hit_gn / replicates, "methods": methods}


def test_coverage_at_strong_autocorrelation():
    """φ = 0.9: the intervals cover 90–98 %; Gauss–Newton's cover under 60 % (measured: about 30 %)."""
    c = coverage(0.9, 200, seed=11)
    assert np.all((c["chosen"] >= 0.90) & (c["chosen"] <= 0.98)), c
    assert np.all(c["gauss_newton"] < 0.6), c
    assert AR1_SANDWICH in c["methods"]


def test_white_noise_keeps_gauss_newton_width():
    """φ = 0: the sandwich is no wider than needed (within 15 % of Gauss–Newton on average) and both cover."""
    rng = np.random.default_rng(3)
    ratios = []
    for _ in range(50):
        F = closed_form(TRUTH) + rng.normal(0, 2.0, len(Y))
        res = optimize.least_squares(lambda th: closed_form(th) - F, TRUTH * 1.1, method="trf")
        rep = interval_report(res.jac, res.fun, res.x)
        lo, hi = rep["gauss_newton"]
        ratios.append((rep["upper"] - rep["lower"]) / (hi - lo))
    assert 0.95 <= float(np.mean(ratios)) <= 1.15


def test_sandwich_matches_the_closed_form_variance_of_a_mean():
    """The sandwich of a constant (J = 1) with AR(1) residuals of known φ is the variance of the mean of an
    AR(1) series: γ₀/n · (1 + 2 Σ (1 − h/n) φ^h)."""
    n, phi = 400, 0.8
    rng = np.random.default_rng(5)
    r = ar1_noise(n, phi, 1.0, rng)
    r -= r.mean()
    cov, info = sandwich_covariance(np.ones((n, 1)), r, phi=phi)
    g0 = float(r @ r) / (n - 1 * (1 + phi) / (1 - phi))
    h = np.arange(1, n)
    want = g0 / n * (1 + 2 * np.sum((1 - h / n) * phi ** h))
    assert cov[0, 0] == pytest.approx(want, rel=1e-6)
    assert info["n_eff"] == pytest.approx(n * (1 - phi) / (1 + phi))


def test_prediction_band_of_a_line_is_the_textbook_one():
    """A straight line's band with a known covariance: √(x² var(k) + σ²) × 1.96."""
    x = np.linspace(0, 1, 11)
    cov = np.array([[4.0]])
    y0, lo, hi = prediction_band(lambda th: th[0] * x, np.array([2.0]), cov, noise_var=1.0)
    assert np.allclose(y0, 2 * x)
    assert np.allclose(hi - y0, 1.959963984540054 * np.sqrt(4 * x ** 2 + 1.0), rtol=1e-4)


@pytest.mark.slow
def test_coverage_study_side_by_side():
    """The full study: 200 replicates per φ, the chosen intervals in 90–98 % everywhere, Gauss–Newton beside;
    the table goes to out/coverage.md."""
    rows = []
    for i, phi in enumerate((0.0, 0.5, 0.8, 0.9, 0.95)):
        c = coverage(phi, 200, seed=100 + i)
        rows.append((phi, c))
        assert np.all((c["chosen"] >= 0.90) & (c["chosen"] <= 0.98)), (phi, c)
    out = ROOT / "out"
    out.mkdir(exist_ok=True)
    lines = ["| φ | intervals of fmusa: c, A, b | Gauss–Newton: c, A, b |", "|---|---|---|"]
    for phi, c in rows:
        lines.append(f"| {phi:g} | " + ", ".join(f"{x:.3f}" for x in c["chosen"]) + " | "
                     + ", ".join(f"{x:.3f}" for x in c["gauss_newton"]) + " |")
    (out / "coverage.md").write_text("\n".join(lines) + "\n")


#: replicates through the FMU per φ (each a calibration of the two-phase curve: 0.15-0.5 s)
FMU_REPLICATES = 200


@pytest.mark.slow
def test_coverage_through_the_fmu(fmu_path):
    """The FMU's two-phase curve (nonlinear_stiffness, d_y held at 0) at known parameters, AR(1) noise of 2 % of
    the peak at φ = 0, 0.5, 0.8, 0.9, 0.95, FMU_REPLICATES replicates each, calibrated by
    fmusa.diagnose.calibrate: its intervals (ci95) cover the truth of every parameter in 90–98 % of the
    replicates, Gauss–Newton's beside (far less where φ > 0). About 4 min; the table goes to out/coverage_fmu.md."""
    from fmusa.diagnose.calibrate import ModelRunner, calibrate
    from fmusa.diagnose.effects import data_scales
    from fmusa.diagnose.measured import Experiment

    t = np.linspace(0.0, 1.0, 200)
    y = 1e-3 * t
    truth = {"c_y": 2.0e5, "nl_ratio": 2.5, "nl_y_b": 0.4e-3}
    model = ModelRunner(fmu_path, "displacement", list(truth), fixed={"d_y": 0.0})
    rows = []
    try:
        clean = model.predict(list(truth.values()), [Experiment("c", Path("c.csv"), "displacement", t, y,
                                                                np.zeros_like(t))])[0]
        sd = 0.02 * float(np.max(np.abs(clean)))
        for phi in (0.0, 0.5, 0.8, 0.9, 0.95):
            rng = np.random.default_rng(int(round(phi * 100)) + 7)
            hits = {k: 0 for k in truth}
            hits_gn = {k: 0 for k in truth}
            for _ in range(FMU_REPLICATES):
                exp = Experiment("s", Path("s.csv"), "displacement", t, y, clean + ar1_noise(len(t), phi, sd, rng))
                fit = calibrate(model, "nonlinear_stiffness", "displacement", [exp], data_scales([exp]),
                                max_starts=2, held=("d_y",))
                for k, v in truth.items():
                    lo, hi = fit.ci95[k]
                    hits[k] += lo <= v <= hi
                    lo, hi = fit.intervals["gauss_newton"][k]
                    hits_gn[k] += lo <= v <= hi
            rows.append((phi, {k: v / FMU_REPLICATES for k, v in hits.items()},
                         {k: v / FMU_REPLICATES for k, v in hits_gn.items()}))
    finally:
        model.close()
    out = ROOT / "out"
    out.mkdir(exist_ok=True)
    lines = [f"Through the FMU, {FMU_REPLICATES} replicates per φ:", "",
             "| φ | intervals of fmusa: c_y, nl_ratio, nl_y_b | Gauss–Newton: c_y, nl_ratio, nl_y_b |", "|---|---|---|"]
    for phi, share, share_gn in rows:
        lines.append(f"| {phi:g} | " + ", ".join(f"{share[k]:.3f}" for k in truth) + " | "
                     + ", ".join(f"{share_gn[k]:.3f}" for k in truth) + " |")
    (out / "coverage_fmu.md").write_text("\n".join(lines) + "\n")
    for phi, share, share_gn in rows:
        assert all(0.90 <= share[k] <= 0.98 for k in truth), (phi, share, share_gn)
        if phi >= 0.5:
            assert all(share_gn[k] < share[k] for k in truth), (phi, share, share_gn)


def test_a_parameter_in_large_units_keeps_its_variance():
    """A stiffness in N/m (column 1e-6 per unit) beside a log parameter (column ~1): JᵀJ's condition number
    (~1e16) made a pseudo-inverse drop the stiffness's direction, a zero-width 95 % interval. The covariance is
    the exact (JᵀJ)⁻¹σ² (a closed form: the columns are orthogonal), and a parameter the data do not determine
    (two identical columns) gets an infinite variance and an unbounded band, never a zero one."""
    from fmusa.diagnose.intervals import gauss_newton_covariance

    n = 200
    t = np.linspace(-1.0, 1.0, n)
    J = np.column_stack([1e-6 * t, np.ones(n)])           # orthogonal columns
    r = np.random.default_rng(3).normal(0.0, 0.1, n)
    s2 = float(r @ r) / (n - 2)
    cov = gauss_newton_covariance(J, r)
    assert cov[0, 0] == pytest.approx(s2 / float(J[:, 0] @ J[:, 0]), rel=1e-9)
    assert cov[1, 1] == pytest.approx(s2 / n, rel=1e-9)
    rep = interval_report(J, r, np.array([6.2e4, 0.0]))
    assert rep["upper"][0] - rep["lower"][0] > 1e4            # about ±2.7e4 N/m, not ±0
    same = np.column_stack([t, t, np.ones(n)])
    cov = gauss_newton_covariance(same, r)
    assert np.isinf(cov[0, 0]) and np.isinf(cov[1, 1])
    assert cov[2, 2] == pytest.approx(float(r @ r) / (n - 3) / n, rel=1e-9)   # the intercept stays determined
    y0, lo, hi = prediction_band(lambda th: th[0] * t + th[2], np.zeros(3), cov, noise_var=0.01)
    assert np.all(np.isinf(hi))
