"""Residual statistics against known truths: hand-computed formulas, white noise (false-alarm rate, uniform
p-values), a sine and a drift of known size, AR(1) noise. Nothing here compares the code with its own output."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import signal, stats

from fmusa.diagnose.residuals import MIN_PERIODS, autocorrelation, binned_residuals, by_direction, ljung_box, residual_structure, runs_test


# ---------------------------------------------------------------------------------------------- by hand

def test_autocorrelation_by_hand():
    # deviations of 1, 2, 3, 4 about 2.5: -1.5 -0.5 0.5 1.5, sum of squares 5
    # lag 1: (0.75 - 0.25 + 0.75) / 5 = 0.25; lag 2: (-0.75 - 0.75) / 5 = -0.3
    np.testing.assert_allclose(autocorrelation([1.0, 2.0, 3.0, 4.0], 2), [1.0, 0.25, -0.3], atol=1e-15)


@pytest.mark.parametrize("r, q, p", [
    # n = 4, h = 2: Q = 4*6*(0.25^2/3 + 0.3^2/2) = 0.5 + 1.08; chi2(2) survival is exp(-Q/2)
    ([1.0, 2.0, 3.0, 4.0], 1.58, np.exp(-0.79)),
    # rho_1 = -3/4, rho_2 = 2/4: Q = 24*(0.5625/3 + 0.25/2) = 7.5
    ([1.0, -1.0, 1.0, -1.0], 7.5, np.exp(-3.75)),
])
def test_ljung_box_by_hand(r, q, p):
    q_, p_, h = ljung_box(np.array(r), lags=2)
    assert h == 2
    assert q_ == pytest.approx(q, rel=1e-12)
    assert p_ == pytest.approx(p, rel=1e-12)


def test_ljung_box_segments_sum_q_and_degrees_of_freedom():
    a, b = [1.0, 2.0, 3.0, 4.0], [1.0, -1.0, 1.0, -1.0]
    q, p, h = ljung_box(np.array(a + b), lags=2, segments=[np.arange(4), np.arange(4, 8)])
    assert h == 4
    assert q == pytest.approx(1.58 + 7.5, rel=1e-12)
    assert p == pytest.approx(stats.chi2.sf(9.08, 4), rel=1e-12)


def test_runs_test_alternating_and_blocked():
    # n1 = n2 = 10: E = 2*10*10/20 + 1 = 11, Var = 2*10*10*(200 - 20)/(20^2 * 19) = 36000/7600
    sd = np.sqrt(36000 / 7600)
    alt = np.tile([1.0, -1.0], 10)
    runs, z, p = runs_test(alt)
    assert runs == 20
    assert z == pytest.approx((9 - 0.5) / sd, rel=1e-12)      # 3.91: far too many sign changes
    assert p == pytest.approx(2 * stats.norm.sf((9 - 0.5) / sd), rel=1e-9)
    runs, z, _ = runs_test(np.r_[np.ones(10), -np.ones(10)])
    assert runs == 2
    assert z == pytest.approx(-(9 - 0.5) / sd, rel=1e-12)     # far too few
    runs, _, _ = runs_test(np.r_[np.ones(10), -np.ones(10)] + 5.0, center="median")
    assert runs == 2


# ---------------------------------------------------------------------------------------------- white noise

def test_white_noise_false_alarm_rate_and_uniform_p_values():
    """200 seeds: structured at alpha = 0.05 about 5 % of the time (Bonferroni over four tests keeps it at or
    below alpha); Ljung–Box p-values uniform. Measured over 1000 seeds: 5.7 % at alpha 0.05."""
    rates = {0.05: 0, 0.01: 0}
    lb_p, osc = [], 0
    t = np.arange(400) * 0.01
    for seed in range(200):
        r = np.random.default_rng(seed).normal(0.0, 2.0, len(t))
        out = residual_structure(t, r, alpha=0.05)
        rates[0.05] += out["structured"]
        rates[0.01] += min(v for v in out["p_values"].values()) < 0.01 / 4
        osc += out["oscillation"] is not None
        lb_p.append(out["ljung_box_p"])
        if not out["structured"]:
            assert out["description"] == "white: no structure beyond noise"
    assert 0.015 <= rates[0.05] / 200 <= 0.10, rates
    assert rates[0.01] / 200 <= 0.035, rates
    assert osc <= 4
    assert stats.kstest(lb_p, "uniform").pvalue > 0.01


def test_white_noise_uneven_sampling():
    rng = np.random.default_rng(7)
    hits = 0
    for _ in range(40):
        t = np.sort(rng.uniform(0.0, 4.0, 300))
        hits += residual_structure(t, rng.normal(size=300), alpha=0.05)["structured"]
    assert hits <= 6                                   # binomial(40, 0.05): P(> 6) < 0.5 %


def test_noise_rms_of_white_noise():
    r = np.random.default_rng(3).normal(0.0, 1.5, 5000)
    out = residual_structure(np.arange(5000) * 1e-3, r)
    assert out["noise_rms"] == pytest.approx(1.5, rel=0.05)
    assert out["rms"] == pytest.approx(1.5, rel=0.05)


# ---------------------------------------------------------------------------------------------- structure

@pytest.mark.parametrize("uneven", [False, True])
def test_sine_found_with_its_frequency_and_amplitude(uneven):
    """A 12.3 Hz, 0.8 N rig oscillation in 0.5 N noise over 10 s; 5 seeds. Measured: frequency error
    < 0.03 %, amplitude error < 5 %."""
    f0, a0, sigma = 12.3, 0.8, 0.5
    share = (a0 ** 2 / 2) / (a0 ** 2 / 2 + sigma ** 2)
    for seed in range(5):
        rng = np.random.default_rng(100 + seed)
        t = np.arange(2000) * 0.005
        if uneven:
            t = t + rng.uniform(-0.002, 0.002, len(t))      # jittered clock: Lomb–Scargle path
        r = a0 * np.sin(2 * np.pi * f0 * t + rng.uniform(0, 2 * np.pi)) + rng.normal(0.0, sigma, len(t))
        out = residual_structure(t, r, unit="N")
        osc = out["oscillation"]
        assert out["structured"] and osc is not None
        assert osc["frequency_hz"] == pytest.approx(f0, rel=0.02)
        assert osc["amplitude"] == pytest.approx(a0, rel=0.10)
        assert osc["share_of_variance"] == pytest.approx(share, abs=0.05)
        assert out["noise_rms"] == pytest.approx(sigma, rel=0.10)
        assert out["drift"] is None
        assert "12.3 Hz" in out["description"] and "N" in out["description"]


def test_drift_found_with_its_slope():
    """0.3 N/s over 10 s in 0.5 N noise; 10 seeds. Measured: slope error < 4 %."""
    t = np.arange(1000) * 0.01
    for seed in range(10):
        r = 1.0 + 0.3 * t + np.random.default_rng(200 + seed).normal(0.0, 0.5, len(t))
        out = residual_structure(t, r, unit="N")
        d = out["drift"]
        assert out["structured"] and d is not None
        assert d["slope_per_s"] == pytest.approx(0.3, rel=0.10)
        assert d["total_change"] == pytest.approx(0.3 * t[-1], rel=0.10)
        assert out["oscillation"] is None
        assert "drift of +" in out["description"]


def test_sine_and_drift_together():
    rng = np.random.default_rng(11)
    t = np.arange(3000) * 0.002
    r = -0.5 * t + 0.4 * np.cos(2 * np.pi * 31.0 * t) + rng.normal(0.0, 0.3, len(t))
    out = residual_structure(t, r)
    assert out["oscillation"]["frequency_hz"] == pytest.approx(31.0, rel=0.02)
    assert out["oscillation"]["amplitude"] == pytest.approx(0.4, rel=0.10)
    assert out["drift"]["slope_per_s"] == pytest.approx(-0.5, rel=0.10)


def test_ar1_noise_is_structured():
    """AR(1) with phi = 0.8: correlated, no line and no trend. Always flagged; lag-1 autocorrelation ~ phi."""
    for seed in range(20):
        e = np.random.default_rng(300 + seed).normal(size=600)
        x = signal.lfilter([1.0], [1.0, -0.8], e)
        out = residual_structure(np.arange(600) * 0.01, x)
        assert out["structured"]
        assert out["lag1_autocorrelation"] == pytest.approx(0.8, abs=0.1)
        assert out["description"].startswith("structured")


def test_segments_keep_joins_out():
    """Three experiments of white noise with different offsets: white when told the experiments apart,
    structured when run together as one record."""
    rng = np.random.default_rng(5)
    sizes = [150, 200, 250]
    t = np.arange(sum(sizes)) * 0.01
    r = rng.normal(size=sum(sizes)) + np.repeat([0.0, 5.0, -3.0], sizes)
    segs = np.split(np.arange(len(r)), np.cumsum(sizes)[:-1])
    assert not residual_structure(t, r, segments=segs)["structured"]
    assert residual_structure(t, r)["structured"]


def test_segments_in_any_order_and_not_covering_everything():
    """Experiments listed last-first, samples 0..49 in none of them (say, a discarded settling phase that holds
    a 100 N spike): the drift of 0.4 per s inside each experiment is still found, the spike plays no part."""
    rng = np.random.default_rng(21)
    t = np.arange(1050) * 0.01
    r = rng.normal(0.0, 0.3, len(t))
    r[:50] = 100.0
    a, b = np.arange(50, 550), np.arange(550, 1050)
    r[a] += 0.4 * (t[a] - t[a][0])
    r[b] += 0.4 * (t[b] - t[b][0]) - 7.0
    out = residual_structure(t, r, segments=[b, a])
    assert out["n"] == 1000 and out["n_segments"] == 2
    assert out["drift"]["slope_per_s"] == pytest.approx(0.4, rel=0.10)
    assert out["drift"]["total_change"] == pytest.approx(0.4 * 4.99, rel=0.10)
    assert "over an experiment" in out["description"]


def test_too_short_to_test():
    out = residual_structure([0.0, 1.0], [0.3, -0.2])
    assert not out["structured"] and out["description"].startswith("too few samples")


def test_oscillation_across_experiments_with_different_phases():
    rng = np.random.default_rng(9)
    sizes = [800, 1000, 1200]
    t = np.concatenate([np.arange(m) * 0.004 for m in sizes])
    r = np.concatenate([0.6 * np.sin(2 * np.pi * 7.5 * np.arange(m) * 0.004 + rng.uniform(0, 6))
                        + 3.0 * j + rng.normal(0.0, 0.5, m) for j, m in enumerate(sizes)])
    segs = np.split(np.arange(len(r)), np.cumsum(sizes)[:-1])
    osc = residual_structure(t, r, segments=segs)["oscillation"]
    assert osc["frequency_hz"] == pytest.approx(7.5, rel=0.02)
    assert osc["amplitude"] == pytest.approx(0.6, rel=0.10)


# ---------------------------------------------------------------------------------------------- edges (issue 11)

def _stack(sizes, dt, make):
    """Experiments of the given sizes, each starting at t = 0 (as the shear tests do); make(j, tt) -> r."""
    t = np.concatenate([np.arange(m) * dt for m in sizes])
    r = np.concatenate([make(j, np.arange(m) * dt) for j, m in enumerate(sizes)])
    return t, r, np.split(np.arange(len(r)), np.cumsum(sizes)[:-1])


def _room(r, segs, which=None):
    """Mean square of r about each experiment's own mean, over the experiments ``which`` (all by default)."""
    which = range(len(segs)) if which is None else which
    x = np.concatenate([r[segs[j]] - r[segs[j]].mean() for j in which])
    return float(np.mean(x ** 2))


def _assert_possible(out, r, segs):
    """Every statement fits in the residual: A^2/2 <= the variance about the experiments' means, a ramp's
    variance (total change^2 / 12) <= that variance, shares in [0, 1]."""
    room = _room(r, segs)
    osc, drift = out["oscillation"], out["drift"]
    if osc is not None:
        assert osc["amplitude"] ** 2 / 2 <= room * (1 + 1e-9)
        assert 0.0 <= osc["share_of_variance"] <= 1.0
    if drift is not None:
        assert 0.0 <= drift["share_of_variance"] <= 1.0
        assert drift["total_change"] ** 2 / 12 <= 1.05 * room


def test_oscillation_in_segments_of_25_to_500_samples():
    """A 5 Hz, 0.8 N oscillation in 0.3 N noise, experiments of 25–500 samples at 250 Hz (0.1–2 s), each with
    its own phase and offset: frequency and amplitude found, within what the residual holds."""
    rng = np.random.default_rng(3)
    sizes = [25, 500, 44, 300, 120, 25]
    t, r, segs = _stack(sizes, 0.004, lambda j, tt: 0.8 * np.sin(2 * np.pi * 5.0 * tt + rng.uniform(0, 6))
                        + rng.normal(0, 5.0) + rng.normal(0.0, 0.3, len(tt)))
    out = residual_structure(t, r, segments=segs, unit="N")
    osc = out["oscillation"]
    assert osc is not None and osc["frequency_hz"] == pytest.approx(5.0, rel=0.02)
    assert osc["amplitude"] == pytest.approx(0.8, rel=0.10)
    # 25 samples (0.1 s) hold half a period of 5 Hz: only the experiments holding three periods (>= 0.6 s) carry it
    assert osc["experiments"] == 2
    _assert_possible(out, r, segs)


def test_period_longer_than_every_segment_is_not_reported():
    """The degenerate case of issue 11: short experiments (25–44 samples, 0.25–0.44 s) of a slow wave
    (0.86 Hz, period 1.2 s, 3–5 times an experiment) with offsets. A free-phase sinusoid of that period over
    one experiment is an offset, a slope and a bend: no oscillation may be stated, no amplitude beyond the
    residual, and the description says which periods were looked at."""
    for seed in range(5):
        rng = np.random.default_rng(seed)
        sizes = list(rng.integers(25, 45, 6))
        t, r, segs = _stack(sizes, 0.01, lambda j, tt: 4.0 * np.sin(2 * np.pi * 0.86 * tt + rng.uniform(0, 6))
                            + rng.normal(0, 3.0) + rng.normal(0.0, 0.5, len(tt)))
        out = residual_structure(t, r, segments=segs, unit="N")
        osc = out["oscillation"]
        assert osc is None or osc["frequency_hz"] >= MIN_PERIODS / (0.01 * max(sizes)) * (1 - 1e-6)
        _assert_possible(out, r, segs)
        assert out["longest_period_s"] == pytest.approx(0.01 * max(sizes) / MIN_PERIODS)
        assert out["structured"]                      # the slow wave is structure (Ljung–Box, runs) ...
        assert " Hz" not in out["description"] and "period up to" in out["description"]   # ... but no line


def test_long_period_found_only_in_the_long_segment():
    """Segments of different lengths: a 1 Hz wave in one 5 s experiment (2000 samples) and in six 0.1 s
    ones (25 samples). Only the long one can show it; the amplitude is that experiment's."""
    rng = np.random.default_rng(5)
    sizes = [2000] + [25] * 6
    t, r, segs = _stack(sizes, 0.0025, lambda j, tt: 1.5 * np.sin(2 * np.pi * 1.0 * tt + rng.uniform(0, 6))
                        + rng.normal(0, 4.0) + rng.normal(0.0, 0.4, len(tt)))
    out = residual_structure(t, r, segments=segs, unit="N")
    osc = out["oscillation"]
    assert osc is not None and osc["frequency_hz"] == pytest.approx(1.0, rel=0.02)
    assert osc["experiments"] == 1 and osc["samples"] == 2000
    assert osc["amplitude"] == pytest.approx(1.5, rel=0.10)
    assert osc["amplitude"] ** 2 / 2 <= _room(r, segs, [0])
    _assert_possible(out, r, segs)


def test_white_noise_in_segments_of_25_to_500_samples():
    """No oscillation, no structure: white noise with offsets in experiments of 25–500 samples is called
    structured at about the nominal rate (alpha = 0.01; 60 draws, at most 3 calls), and whatever is said
    is possible."""
    calls = 0
    for seed in range(60):
        rng = np.random.default_rng(100 + seed)
        sizes = list(rng.integers(25, 501, 5))
        t, r, segs = _stack(sizes, 0.01, lambda j, tt: rng.normal(0, 10.0) + rng.normal(0.0, 1.0, len(tt)))
        out = residual_structure(t, r, segments=segs)
        calls += out["structured"]
        _assert_possible(out, r, segs)
    assert calls <= 3


def test_no_impossible_amplitude_on_slow_structure_in_short_segments():
    """Random slow structure (bends, ramps, slow waves of any phase) in experiments of 25–60 samples, as the
    100 mm/s shear tests leave: whatever is stated must fit in the residual (the bug: 931 N at 0.86 Hz on
    a 4 N rms residual)."""
    for seed in range(40):
        rng = np.random.default_rng(1000 + seed)
        sizes = list(rng.integers(25, 61, int(rng.integers(2, 7))))
        def make(j, tt):
            u = tt / tt[-1]
            return (rng.normal(0, 20) + rng.normal(0, 5) * u + rng.normal(0, 5) * u ** 2
                    + rng.normal(0, 3) * np.sin(2 * np.pi * rng.uniform(0.2, 3) * tt + rng.uniform(0, 6))
                    + rng.normal(0, 0.5, len(tt)))
        t, r, segs = _stack(sizes, 0.01, make)
        out = residual_structure(t, r, segments=segs, unit="N")
        _assert_possible(out, r, segs)


def test_very_short_segments_cannot_tell_an_oscillation():
    """Experiments of 6 samples: no period can be searched (longest_period_s NaN, no oscillation); a drift
    across them is still found and the description says an oscillation cannot be told."""
    rng = np.random.default_rng(8)
    sizes = [6] * 40
    t, r, segs = _stack(sizes, 0.01, lambda j, tt: rng.normal(0, 5.0) + 60.0 * tt + rng.normal(0, 0.1, len(tt)))
    out = residual_structure(t, r, segments=segs, unit="N")
    assert out["oscillation"] is None and np.isnan(out["longest_period_s"])
    assert out["drift"] is not None and out["drift"]["slope_per_s"] == pytest.approx(60.0, rel=0.1)
    _assert_possible(out, r, segs)
    t2, r2, segs2 = _stack(sizes, 0.01, lambda j, tt: rng.normal(0, 5.0) + np.r_[1, 1, 1, -1, -1, -1] * 0.5
                           + rng.normal(0, 0.05, len(tt)))
    out2 = residual_structure(t2, r2, segments=segs2)
    assert out2["oscillation"] is None
    if out2["structured"] and out2["drift"] is None:
        assert "cannot be told" in out2["description"]


# ---------------------------------------------------------------------------------------------- for plots

def test_binned_residuals_follow_a_linear_error():
    x = (np.arange(1200) + 0.5) / 1200                 # 100 points placed symmetrically in each of 12 bins
    df = binned_residuals(x, 2.0 * x, bins=12)
    assert list(df.columns) == ["low", "high", "center", "mean", "std", "count"]
    assert df["count"].tolist() == [100] * 12
    np.testing.assert_allclose(df["mean"], 2.0 * df["center"], atol=1e-3)
    empty = binned_residuals(np.array([0.0, 1.0]), np.array([1.0, 3.0]), bins=4)
    assert empty["count"].tolist() == [1, 0, 0, 1] and np.isnan(empty["mean"][1])


def test_by_direction_splits_loading_unloading_hold():
    v = np.r_[np.full(30, 2.0), np.full(20, -1.0), np.full(10, 0.01)]    # 0.01 < 2 % of max |v|
    r = np.r_[np.full(30, 1.0), np.full(20, -3.0), np.full(10, 0.5)]
    out = by_direction(v, r)
    assert out["loading"] == {"mean": 1.0, "rms": 1.0, "count": 30}
    assert out["unloading"] == {"mean": -3.0, "rms": 3.0, "count": 20}
    assert out["hold"] == {"mean": 0.5, "rms": 0.5, "count": 10}


def test_a_single_bump_is_a_region_of_misfit_not_an_oscillation():
    """A peak and a drop the model misses (one bump of 40-120 N between 1.13 and 1.5 mm on a 0-2 mm ramp, in
    0.1 N noise) holds no recurring period: it is described by where and how much, never as a wave."""
    rng = np.random.default_rng(5)
    t = np.linspace(0.0, 200.0, 400)
    x = t / 100.0                                     # mm at 0.01 mm/s
    bump = np.where((x > 1.13) & (x < 1.5), 40.0 + 80.0 * np.sin(np.pi * (x - 1.13) / 0.37) ** 2, 0.0)
    r = bump + rng.normal(0.0, 0.1, len(t))
    measured = 500.0 - np.where(x > 1.13, 300.0 * (x - 1.13), 0.0)
    out = residual_structure(t, r, unit="N", x=x, x_unit="mm", measured=measured, response="force")
    assert out["structured"] and out["oscillation"] is None
    mis = out["misfit"]
    assert mis["sign"] == 1 and mis["x_start"] == pytest.approx(1.13, abs=0.03)
    assert mis["x_end"] == pytest.approx(1.5, abs=0.03)
    assert 10.0 < mis["size_low"] < 70.0 and 100.0 < mis["size_high"] <= 121.0   # edges blurred by the mean
    assert "Hz" not in out["description"] and "above the data from 1.1" in out["description"]
    assert "where the measured force falls" in out["description"]


def test_two_periods_are_not_an_oscillation_three_recurring_are():
    """A wave over two periods of the record is a bend (no oscillation stated); over six it is one."""
    rng = np.random.default_rng(6)
    t = np.linspace(0.0, 10.0, 500)
    for periods, want in ((2.0, False), (6.0, True)):
        r = 5.0 * np.sin(2 * np.pi * periods / 10.0 * t + 0.3) + rng.normal(0.0, 0.5, len(t))
        out = residual_structure(t, r, unit="N")
        assert out["structured"]
        assert (out["oscillation"] is not None) is want, (periods, out["description"])
        if not want:
            assert out["misfit"] is not None and "Hz" not in out["description"]
