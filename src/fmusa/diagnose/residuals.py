"""Residual statistics for `fmusa diagnose`: tell structure from white noise, and describe the structure.

A good fit leaves residuals that look like white noise: no autocorrelation (Ljung–Box), signs that change as
often as chance says (Wald–Wolfowitz runs test), no spectral line and no trend. When the residuals are not
white, the user wants to know what is left in them in physical terms: an oscillation of the test rig (its
frequency and amplitude) or a drift (its slope and total change). Pure numpy/scipy, no plotting, no FMU.

Several experiments are handled as separate segments: every statistic is computed within an experiment and
pooled, so the jump from the end of one experiment to the start of the next never counts as structure.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import pandas as pd
from scipy import optimize, signal, special, stats

OVERSAMPLE = 5          # frequency grid points per independent frequency 1/T: the peak is found to < 0.1/T
LOCAL_WINDOW = 25       # independent frequencies each side of a peak that estimate the local continuum
LOCAL_GAP = 2           # ... leaving out this many each side of the peak (its main lobe)
HOLD_FRACTION = 0.02    # |v| below this fraction of max |v| counts as a hold
MIN_PERIODS = 3.0       # an experiment says something about a period only when it holds this many of them:
#                         over a shorter stretch a free-phase sinusoid is indistinguishable from an offset, a
#                         slope, a bend or a single bump, and its fitted amplitude is meaningless (it can be
#                         100x the rms)
RECUR_PARTS = 3         # an oscillation must recur: fitted alone in each third of the samples that hold it, its
RECUR_SHARE = 0.3       # amplitude is at least this share of the whole fit's in every third (a bump is not)
MIN_SAMPLES = 8         # ... and when it has at least this many samples


# ---------------------------------------------------------------------------------------------- segments

def _segments(n: int, segments: Sequence[np.ndarray] | None) -> list[np.ndarray]:
    """Index arrays, one per experiment; the whole record when ``segments`` is None."""
    if segments is None:
        return [np.arange(n)]
    out = [np.asarray(s, dtype=int).ravel() for s in segments]
    out = [s for s in out if len(s)]
    if not out:
        raise ValueError("segments: every segment is empty")
    for s in out:
        if s.min() < 0 or s.max() >= n:
            raise ValueError(f"segments: index out of range 0..{n - 1}")
    return out


# ---------------------------------------------------------------------------------------------- classic tests

def autocorrelation(r: np.ndarray, max_lag: int, *, segments: Sequence[np.ndarray] | None = None) -> np.ndarray:
    """Sample autocorrelation at lags 0..max_lag (lag 0 is 1), the usual biased estimator
    sum (x_t - m)(x_{t+k} - m) / sum (x_t - m)^2. With ``segments`` each experiment is centred on its own
    mean and only pairs within one experiment are counted, so joins between experiments do not correlate."""
    r = np.asarray(r, float).ravel()
    max_lag = int(max_lag)
    if max_lag < 0:
        raise ValueError("max_lag must be >= 0")
    num = np.zeros(max_lag + 1)
    den = 0.0
    for idx in _segments(len(r), segments):
        x = r[idx] - r[idx].mean()
        den += float(x @ x)
        for k in range(min(max_lag, len(x) - 1) + 1):
            num[k] += float(x[:len(x) - k] @ x[k:])
    if den == 0.0:
        out = np.zeros(max_lag + 1)
        out[0] = 1.0
        return out
    return num / den


def _default_lags(n: int) -> int:
    return min(20, n // 5)


def ljung_box(r: np.ndarray, lags: int | None = None, *,
              segments: Sequence[np.ndarray] | None = None) -> tuple[float, float, int]:
    """Ljung–Box Q = n (n + 2) sum_{k=1..h} rho_k^2 / (n - k), chi-square with h degrees of freedom under
    white noise; returns (Q, p_value, lags_used). Default h = min(20, n // 5). With ``segments``, Q is
    computed per experiment (its own n and lags) and summed, and so are the degrees of freedom; lags_used is
    then that sum. Experiments too short for one lag are left out."""
    r = np.asarray(r, float).ravel()
    q_total, df_total = 0.0, 0
    for idx in _segments(len(r), segments):
        n = len(idx)
        h = _default_lags(n) if lags is None else min(int(lags), n - 1)
        if h < 1:
            continue
        rho = autocorrelation(r[idx], h)[1:]
        k = np.arange(1, h + 1)
        q_total += float(n * (n + 2) * np.sum(rho ** 2 / (n - k)))
        df_total += h
    if df_total == 0:
        return float("nan"), float("nan"), 0
    return q_total, float(stats.chi2.sf(q_total, df_total)), df_total


def runs_test(r: np.ndarray, center: float | str = 0.0, *,
              segments: Sequence[np.ndarray] | None = None) -> tuple[int, float, float]:
    """Wald–Wolfowitz runs test on the signs of r - center (center 0, or "median"); values equal to the
    center are dropped. Returns (n_runs, z, two-sided p). z > 0: more sign changes than chance (alternation),
    z < 0: fewer (long stretches on one side, i.e. a systematic error). Normal approximation with a continuity
    correction of 1/2. With ``segments`` runs are counted per experiment, expectations and variances summed."""
    r = np.asarray(r, float).ravel()
    runs, mean, var = 0, 0.0, 0.0
    for idx in _segments(len(r), segments):
        x = r[idx]
        c = float(np.median(x)) if center == "median" else float(center)
        s = np.sign(x - c)
        s = s[s != 0]
        if len(s) == 0:
            continue
        n1, n2 = int(np.sum(s > 0)), int(np.sum(s < 0))
        n = n1 + n2
        runs += 1 + int(np.count_nonzero(s[1:] != s[:-1]))
        mean += 2.0 * n1 * n2 / n + 1.0
        if n > 1:
            var += 2.0 * n1 * n2 * (2.0 * n1 * n2 - n) / (n * n * (n - 1.0))
    if var <= 0:
        return runs, float("nan"), float("nan")
    dev = runs - mean
    z = np.sign(dev) * max(abs(dev) - 0.5, 0.0) / np.sqrt(var)
    return runs, float(z), float(2.0 * stats.norm.sf(abs(z)))


# ---------------------------------------------------------------------------------------------- components

def _design(t: np.ndarray, segs: list[np.ndarray], freq: float | None,
            active: Sequence[bool] | None = None) -> tuple[np.ndarray, int]:
    """Columns: one intercept per experiment, a common slope in time (about each experiment's mean time), and
    when ``freq`` is given a cosine and sine per experiment (common frequency, phase free per experiment:
    experiments start at arbitrary phases of a rig oscillation). ``active`` (one flag per experiment) leaves
    the cosine and sine of an experiment at zero where it cannot hold the period (see _eligible): there a
    free-phase sinusoid would be offset, slope and curvature with a huge amplitude. Returns (X, column of
    the slope)."""
    k = len(segs)
    ncol = k + 1 + (2 * k if freq is not None else 0)
    X = np.zeros((sum(len(s) for s in segs), ncol))     # rows: the experiments stacked in order
    start = 0
    for j, idx in enumerate(segs):
        tt = t[idx]
        rr = slice(start, start + len(idx))
        X[rr, j] = 1.0
        X[rr, k] = tt - tt.mean()
        if freq is not None and (active is None or active[j]):
            X[rr, k + 1 + 2 * j] = np.cos(2 * np.pi * freq * tt)
            X[rr, k + 2 + 2 * j] = np.sin(2 * np.pi * freq * tt)
        start += len(idx)
    return X, k


def _fit(t: np.ndarray, r: np.ndarray, segs: list[np.ndarray], freq: float | None,
         active: Sequence[bool] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares of the stacked experiments on _design; returns (X, coefficients, residual)."""
    X, _ = _design(t, segs, freq, active)
    y = np.concatenate([r[idx] for idx in segs])
    beta, *_ = np.linalg.lstsq(X, y, rcond=None)
    return X, beta, y - X @ beta


def _duration(t: np.ndarray, idx: np.ndarray) -> float:
    """Time an experiment covers: its span plus one (median) sample step."""
    if len(idx) < 2:
        return 0.0
    tt = t[idx]
    return float(tt[-1] - tt[0] + np.median(np.diff(tt)))


def _band(t: np.ndarray, idx: np.ndarray) -> tuple[float, float]:
    """(lowest, highest) frequency an experiment can say anything about: at least MIN_PERIODS periods in it,
    at most its Nyquist frequency; (inf, 0) for one shorter than MIN_SAMPLES."""
    if len(idx) < MIN_SAMPLES:
        return float("inf"), 0.0
    return MIN_PERIODS / _duration(t, idx), 0.5 / float(np.median(np.diff(t[idx])))


def _eligible(t: np.ndarray, segs: list[np.ndarray], freq: float) -> list[bool]:
    """Which experiments hold at least MIN_PERIODS periods of ``freq`` (and resolve it)."""
    out = []
    for idx in segs:
        lo, hi = _band(t, idx)
        out.append(bool(lo * (1 - 1e-9) <= freq <= hi * (1 + 1e-9)))
    return out


def _is_uniform(t: np.ndarray) -> bool:
    """Uniform up to timestamp rounding: a 1e-3 dt jitter shifts phases by < 0.2 degree even at Nyquist."""
    dt = np.diff(t)
    return bool(np.all(np.abs(dt - np.median(dt)) <= 1e-3 * np.median(dt)))


LS_BUDGET = 3e7         # samples x frequencies the direct Lomb–Scargle may spend before resampling instead


def _lomb_scargle(t: np.ndarray, x: np.ndarray, freqs: np.ndarray, block: int | None = None) -> np.ndarray:
    """Classical Lomb–Scargle power of centred x, 0.5 [Re(Z)^2 / C2 + Im(Z)^2 / S2] in the Press–Rybicki
    complex form, on an equally spaced frequency grid. The exponentials of a block of frequencies come from
    one exp and a running product (a multiply instead of an exp per entry); scipy.signal.lombscargle takes
    seconds for a few thousand samples."""
    out = np.empty(len(freqs))
    n = len(x)
    block = block or int(np.clip(2_000_000 // max(n, 1), 16, 512))   # <= 32 MB of exponentials at a time
    df = float(freqs[1] - freqs[0]) if len(freqs) > 1 else 0.0
    step = np.exp(2j * np.pi * df * t)
    for a in range(0, len(freqs), block):
        m = min(block, len(freqs) - a)
        e = np.empty((m, n), complex)
        e[0] = np.exp(2j * np.pi * freqs[a] * t)
        for j in range(1, m):
            np.multiply(e[j - 1], step, out=e[j])
        y = np.einsum("ij,j->i", e, x)    # not e @ x: BLAS threads for a mixed-type product stall under load
        w2 = np.einsum("ij,ij->i", e, e)
        aw = np.abs(w2)
        rot = np.where(aw > 1e-9 * n, np.sqrt(np.conj(w2) / np.where(aw > 0, aw, 1.0)), 1.0)  # e^{-i w tau}
        z = y * rot
        c2 = np.maximum(0.5 * (n + aw), 1e-300)
        s2 = np.maximum(0.5 * (n - aw), 1e-300)
        out[a:a + m] = 0.5 * (z.real ** 2 / c2 + z.imag ** 2 / s2)
    return out


def _periodogram(t: np.ndarray, x: np.ndarray, freqs: np.ndarray) -> np.ndarray:
    """Periodogram of centred x on the equally spaced grid ``freqs``, scaled so that P / variance is about
    exponential with mean 1 at each frequency under Gaussian white noise: |sum x e^{-i w t}|^2 / n on uniform
    samples (chirp-z transform, exact at any grid), Lomb–Scargle on uneven ones. When the direct Lomb–Scargle
    would cost more than LS_BUDGET, uneven samples are linearly interpolated onto their median step first."""
    if not _is_uniform(t) and len(x) * len(freqs) <= LS_BUDGET:
        return _lomb_scargle(t, x, freqs)
    dt = float(np.median(np.diff(t)))
    if not _is_uniform(t):
        tu = np.arange(t[0], t[-1] + 0.5 * dt, dt)
        x = np.interp(tu, t, x)
        x = x - x.mean()
    if len(freqs) == 1:
        return np.array([abs(np.exp(-2j * np.pi * freqs[0] * dt * np.arange(len(x))) @ x) ** 2 / len(x)])
    spec = signal.zoom_fft(x, [freqs[0], freqs[-1]], m=len(freqs), fs=1.0 / dt, endpoint=True)
    return np.abs(spec) ** 2 / len(x)


def _oscillation(t: np.ndarray, r: np.ndarray, segs: list[np.ndarray]) -> dict | None:
    """Strongest spectral line of the per-experiment detrended residual and its p-value, searched only where
    it can be told from an offset and a drift: an experiment takes part at frequency f when it holds at least
    MIN_PERIODS periods (and f is below its Nyquist frequency), so experiments of different lengths cover
    different bands and periods longer than every experiment / MIN_PERIODS are not searched at all (None).
    The pooled power Z(f) = sum over the K(f) taking part of P_s(f) / var_s is Gamma(K(f)) under white noise;
    the peak is the frequency least likely under it. Two tests must both pass, the p-value is the larger:
    Z_max against white noise scanned over the band (Baluev's false-alarm probability), and Z_max rescaled by
    the local continuum (median of Z around the peak), so that the red spectrum of correlated noise is not
    taken for a line."""
    bands = [_band(t, idx) for idx in segs]
    f_lo = min(b[0] for b in bands)
    f_hi = max(b[1] for b in bands)
    if not np.isfinite(f_lo) or f_hi <= f_lo:
        return None
    t_max = max(_duration(t, idx) for idx, b in zip(segs, bands) if np.isfinite(b[0]))
    df = 1.0 / (OVERSAMPLE * t_max)
    freqs = np.arange(f_lo, f_hi + 0.5 * df, df)
    if len(freqs) < 3:
        return None
    _, _, e = _fit(t, r, segs, None)              # detrended per experiment, common slope
    z = np.zeros(len(freqs))
    kk = np.zeros(len(freqs), int)
    start = 0
    for idx, (lo, hi) in zip(segs, bands):
        x = e[start:start + len(idx)]
        start += len(idx)
        if not np.isfinite(lo):
            continue
        var = float(np.mean((x - x.mean()) ** 2))
        if var <= 0:
            continue
        use = (freqs >= lo * (1 - 1e-9)) & (freqs <= hi * (1 + 1e-9))
        if np.count_nonzero(use) == 0:
            continue
        sub = freqs[use]
        z[use] += _periodogram(t[idx], x - x.mean(), sub) / var
        kk[use] += 1
    if not np.any(kk > 0):
        return None
    score = np.full(len(freqs), np.inf)           # -log P(Gamma(K) > Z): the least likely peak under noise
    on = kk > 0
    score[on] = stats.gamma.logsf(z[on], kk[on])
    i = int(np.argmin(score))
    k = int(kk[i])
    var_t = max(float(np.var(t[idx])) for idx, b in zip(segs, bands) if np.isfinite(b[0]))
    w_band = (freqs[-1] - freqs[0]) * np.sqrt(4 * np.pi * var_t)
    zn = np.where(on, z / stats.gamma.median(np.maximum(kk, 1)), np.nan)   # about 1 per frequency under noise
    lo_i, hi_i = max(0, i - LOCAL_WINDOW * OVERSAMPLE), min(len(z), i + LOCAL_WINDOW * OVERSAMPLE + 1)
    window = np.r_[zn[lo_i:max(lo_i, i - LOCAL_GAP * OVERSAMPLE)], zn[min(hi_i, i + LOCAL_GAP * OVERSAMPLE + 1):hi_i]]
    window = window[np.isfinite(window)]
    level = float(np.median(window)) if len(window) >= 10 else 1.0

    def p_max(zz: float) -> float:
        # Baluev (2008): false-alarm probability of the highest peak of a periodogram scanned over a band,
        # from the rate of upcrossings of level zz (W zz^(K-1/2) e^-zz / Gamma(K)) plus the single-frequency
        # tail; oversampled scans make Fisher's count of independent frequencies too optimistic.
        if zz <= 0:
            return 1.0
        tau = np.exp(np.log(w_band) + (k - 0.5) * np.log(zz) - zz - special.gammaln(k))
        return float(min(1.0, -np.expm1(np.log1p(-stats.gamma.sf(zz, k)) - tau)))
    p = max(p_max(z[i]), p_max(z[i] / max(level, 1e-300)))

    active = _eligible(t, segs, float(freqs[i]))

    def sse(f: float) -> float:
        return float(np.sum(_fit(t, r, segs, f, active)[2] ** 2))
    f_best = float(freqs[i])
    if 0 < i < len(freqs) - 1:
        res = optimize.minimize_scalar(sse, bounds=(freqs[i - 1], freqs[i + 1]), method="bounded",
                                       options={"xatol": 1e-4 * df})
        if res.fun <= sse(f_best):
            f_best = float(res.x)
    return {"frequency_hz": f_best, "p_value": p, "peak_power": float(z[i]), "continuum": level,
            "active": active, "experiments": k}


def _recurs(tt: np.ndarray, centred: np.ndarray, rows: np.ndarray, freq: float, amp: float) -> bool:
    """Whether a wave at ``freq`` of amplitude ``amp`` is in every part of the record, not one bump: a sinusoid
    with an offset fitted to each of RECUR_PARTS consecutive parts of the samples that hold it must reach
    RECUR_SHARE of the amplitude in each (a peak and a drop of a test, read as a wave, live in one part)."""
    idx = np.flatnonzero(rows)
    if len(idx) < RECUR_PARTS * MIN_SAMPLES or amp <= 0:
        return False
    for part in np.array_split(idx, RECUR_PARTS):
        w = 2 * np.pi * freq * tt[part]
        X = np.column_stack([np.ones(len(part)), np.cos(w), np.sin(w)])
        b, *_ = np.linalg.lstsq(X, centred[part], rcond=None)
        if float(np.hypot(b[1], b[2])) < RECUR_SHARE * amp:
            return False
    return True


def misfit_region(r: np.ndarray, segs: list[np.ndarray], x: np.ndarray, t: np.ndarray, noise: float,
                  measured: np.ndarray | None = None) -> dict | None:
    """The stretch where the model misses the data systematically: the contiguous run, within one experiment,
    of one sign of the smoothed residual (moving mean over about 1/20 of the experiment) around its largest
    value, where it exceeds 3 x the noise of the mean (and 10 % of that largest value). Returns where (x and
    t at its ends), how much (the 10th percentile and the largest |smoothed residual| there), its sign (+1: the
    model above the data) and, given the measured response, whether that falls across the region."""
    best = None
    for j, idx in enumerate(segs):
        n = len(idx)
        if n < MIN_SAMPLES:
            continue
        w = max(3, n // 20)
        sm = np.convolve(r[idx], np.ones(w) / w, mode="same")
        edge = np.convolve(np.ones(n), np.ones(w) / w, mode="same")
        sm = sm / edge
        k = int(np.argmax(np.abs(sm)))
        if best is None or abs(sm[k]) > abs(best[2][best[3]]):
            best = (j, idx, sm, k, w)
    if best is None:
        return None
    j, idx, sm, k, w = best
    peak = abs(float(sm[k]))
    thr = max(3.0 * noise / np.sqrt(w), 0.1 * peak)
    if not (peak > thr):
        return None
    sign = 1.0 if sm[k] > 0 else -1.0
    on = (sign * sm) > thr
    a = b = k
    while a > 0 and on[a - 1]:
        a -= 1
    while b < len(sm) - 1 and on[b + 1]:
        b += 1
    sizes = np.abs(sm[a:b + 1])
    out = {"experiment": int(j), "sign": int(sign), "x_start": float(x[idx[a]]), "x_end": float(x[idx[b]]),
           "t_start": float(t[idx[a]]), "t_end": float(t[idx[b]]), "size_low": float(np.percentile(sizes, 10)),
           "size_high": float(np.max(sizes)), "samples": int(b - a + 1), "share_of_samples": float((b - a + 1) / len(idx)),
           "response_falls": None}
    if measured is not None and b > a:
        out["response_falls"] = bool(abs(measured[idx[b]]) < abs(measured[idx[a]]) - 2 * noise)
    return out


def longest_period(t: np.ndarray, segs: list[np.ndarray]) -> float:
    """The longest period the oscillation search looks at (s): the longest experiment / MIN_PERIODS; NaN when
    no experiment has MIN_SAMPLES samples. Longer periods cannot be told from an offset and a drift."""
    lows = [_band(t, idx)[0] for idx in segs]
    lows = [x for x in lows if np.isfinite(x)]
    return 1.0 / min(lows) if lows else float("nan")


def _hac_slope_p(X: np.ndarray, e: np.ndarray, col: int, slope: float,
                 segs: list[np.ndarray]) -> tuple[float, float]:
    """Standard error and two-sided p of the slope coefficient, with a Newey–West (Bartlett) long-run variance
    whose bandwidth follows Andrews' AR(1) plug-in rule: a trend test that correlated noise does not fool the
    way ordinary least-squares errors would. Lags are taken within experiments only."""
    others = np.delete(X, col, axis=1)
    g, *_ = np.linalg.lstsq(others, X[:, col], rcond=None)
    xt = X[:, col] - others @ g                   # the slope regressor with everything else projected out
    sxx = float(xt @ xt)
    if sxx <= 0:
        return float("nan"), float("nan")
    u = xt * e
    bounds = np.cumsum([0] + [len(s) for s in segs])
    pieces = [u[a:b] for a, b in zip(bounds[:-1], bounds[1:])]
    num = sum(float(p[1:] @ p[:-1]) for p in pieces if len(p) > 1)
    den = sum(float(p[:-1] @ p[:-1]) for p in pieces if len(p) > 1)
    rho = float(np.clip(num / den, -0.97, 0.97)) if den > 0 else 0.0
    alpha1 = 4 * rho ** 2 / ((1 - rho) ** 2 * (1 + rho) ** 2)
    n = len(u)
    lag = int(min(np.floor(1.1447 * (alpha1 * n) ** (1 / 3)), max(len(p) for p in pieces) - 1))
    omega = float(u @ u)
    for ell in range(1, lag + 1):
        w = 1.0 - ell / (lag + 1)
        omega += 2 * w * sum(float(p[ell:] @ p[:-ell]) for p in pieces if len(p) > ell)
    dof = n - X.shape[1]
    if dof < 2:
        return float("nan"), float("nan")
    se = float(np.sqrt(max(omega, 0.0) * n / dof) / sxx)
    if se <= 0:
        return se, 0.0 if slope != 0 else 1.0
    return se, float(2 * stats.t.sf(abs(slope) / se, dof))


def _robust_noise_rms(pieces: list[np.ndarray]) -> float:
    """rms of the white part: first differences of white noise have variance 2 sigma^2, and a slow structure
    barely changes them; a MAD (1.4826 MAD = sigma for a Gaussian) shrugs off outliers."""
    diffs = [np.diff(p) for p in pieces if len(p) > 1]
    d = np.concatenate(diffs) if diffs else np.zeros(0)
    if len(d) == 0:
        return float("nan")
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0))


def _fmt(x: float) -> str:
    return f"{x:.3g}"


def _describe(out: dict, unit: str, n_segments: int) -> str:
    """One sentence in plain words for the report and the terminal."""
    u = f" {unit}" if unit else ""
    if not any(np.isfinite(p) for p in out["p_values"].values()):
        return "too few samples to tell structure from noise"
    if not out["structured"]:
        return "white: no structure beyond noise"
    parts = []
    osc, drift = out["oscillation"], out["drift"]
    if osc is not None:
        parts.append(f"an oscillation at {_fmt(osc['frequency_hz'])} Hz of amplitude {_fmt(osc['amplitude'])}{u} "
                     f"({100 * osc['share_of_variance']:.0f} % of the residual variance)")
    if drift is not None:
        over = "over the test" if n_segments == 1 else "over an experiment (mean duration)"
        parts.append(f"a drift of {drift['total_change']:+.3g}{u} {over} "
                     f"({_fmt(drift['slope_per_s'])}{u}/s, {100 * drift['share_of_variance']:.0f} % of the "
                     f"residual variance)")
    mis = out.get("misfit")
    if mis is not None:
        where = "above" if mis["sign"] > 0 else "below"
        xu = f" {out.get('x_unit')}" if out.get("x_unit") else ""
        text = (f"the model is {_fmt(mis['size_low'])}–{_fmt(mis['size_high'])}{u} {where} the data from "
                f"{_fmt(mis['x_start'])}{xu} to {_fmt(mis['x_end'])}{xu} of {out.get('x_name', 'displacement')}"
                + (f" (experiment {mis['experiment'] + 1})" if n_segments > 1 else ""))
        if mis.get("response_falls"):
            text += f", where the measured {out.get('response', 'response')} falls"
        mis_text = text
    else:
        mis_text = None
    if not parts:
        rho = out["lag1_autocorrelation"]
        if out["runs_z"] < 0 or rho > 0:
            kind = (f"slowly varying systematic error (lag-1 autocorrelation {rho:.2f}, "
                    f"runs test z = {out['runs_z']:.1f})")
        else:
            kind = f"residuals that alternate more than noise does (lag-1 autocorrelation {rho:.2f})"
        lp = out.get("longest_period_s", float("nan"))
        if np.isfinite(lp):
            parts.append(f"{kind}, but no single drift or oscillation with a period up to {_fmt(lp)} s (longer "
                         f"periods cannot be told from an offset and a drift: an experiment must hold "
                         f"{MIN_PERIODS:g} of them)")
        else:
            parts.append(f"{kind}, but no single drift; whether it oscillates cannot be told (segments too "
                         f"short: fewer than {MIN_SAMPLES} samples each)")
    if mis_text:
        parts.insert(0, mis_text)
    return "structured: " + "; ".join(parts)


def residual_structure(t: np.ndarray, r: np.ndarray, *, segments: Sequence[np.ndarray] | None = None,
                       alpha: float = 0.01, unit: str = "", x: np.ndarray | None = None, x_unit: str = "",
                       x_name: str = "displacement", measured: np.ndarray | None = None,
                       response: str = "response") -> dict:
    """Is anything left in the residuals r(t) beyond white noise, and if so what?

    Four tests, each at alpha / 4 so that white noise is called structured with probability at most alpha:
    Ljung–Box (autocorrelation), runs (sign changes about 0), a spectral line (Lomb–Scargle / periodogram
    peak against white noise and against the local continuum) and a linear drift in time (slope with a
    Newey–West error). A line found is fitted jointly with the drift (frequency refined by least squares,
    phase free per experiment) and described by its frequency, amplitude and share of the variance; the drift
    by its slope and change over the test. ``segments`` (index arrays, one per experiment) keeps every
    statistic within an experiment; each experiment gets its own mean. ``unit`` only labels the description.

    The mean (a bias) is reported but is not structure: a constant offset passes as white.

    Oscillations are searched only at periods that every experiment taking part holds at least MIN_PERIODS
    times (experiments of different lengths cover different bands); the amplitude is that of the sinusoid
    whose mean square is the fitted wave's, never more than the residual of those experiments can hold
    (A^2/2 <= their variance), and each share of variance is what the component explains (nested least
    squares), so it is between 0 and 1.

    Keys: structured, description, n, n_segments, alpha, alpha_per_test, mean, rms, noise_rms,
    lag1_autocorrelation, ljung_box_q, ljung_box_df, ljung_box_p, runs, runs_z, runs_p, p_values (the four
    tests), oscillation (None or frequency_hz, amplitude, share_of_variance, p_value, experiments, samples),
    drift (None or slope_per_s, slope_se, total_change, share_of_variance, p_value), longest_period_s (the
    longest period searched, NaN when none can be), misfit (None or the region of systematic misfit of
    :func:`misfit_region` along ``x``, the drive channel in ``x_unit``: a structure that is no oscillation,
    e.g. a trend or a single bump, is described by where the model misses the data and by how much)."""
    t = np.asarray(t, float).ravel()
    r = np.asarray(r, float).ravel()
    if t.shape != r.shape:
        raise ValueError(f"t and r differ in length ({len(t)} != {len(r)})")
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(r))):
        raise ValueError("t and r must be finite")
    segs = _segments(len(r), segments)
    for j, idx in enumerate(segs):
        if np.any(np.diff(t[idx]) <= 0):
            raise ValueError(f"segment {j}: time must increase")
    n = int(sum(len(s) for s in segs))
    a_each = alpha / 4.0

    q, p_lb, df_lb = ljung_box(r, segments=segs)
    n_runs, z_runs, p_runs = runs_test(r, segments=segs)
    lag1 = float(autocorrelation(r, 1, segments=segs)[1]) if n > 1 else float("nan")

    osc = _oscillation(t, r, segs)
    p_osc = osc["p_value"] if osc is not None else float("nan")
    freq = osc["frequency_hz"] if osc is not None and p_osc < a_each else None
    active = osc["active"] if freq is not None else None
    k = len(segs)
    y = np.concatenate([r[idx] for idx in segs])
    bounds = np.cumsum([0] + [len(s) for s in segs])
    centred = np.concatenate([y[a:b] - y[a:b].mean() for a, b in zip(bounds[:-1], bounds[1:])])
    var_total = float(np.mean(centred ** 2)) if n else float("nan")
    sse_total = float(centred @ centred)
    oscillation = None
    if freq is not None:
        X, beta, e = _fit(t, r, segs, freq, active)
        _, _, e0 = _fit(t, r, segs, None)          # the same without the oscillation: what it explains
        rows = np.concatenate([np.full(b - a, bool(on)) for a, b, on in zip(bounds[:-1], bounds[1:], active)])
        wave = (X[:, k + 1:] @ beta[k + 1:])[rows]
        # Amplitude of the sinusoid whose mean square is the fitted wave's, over the experiments that hold
        # it; it cannot exceed what those experiments' residual holds: A^2 / 2 <= their variance. A fit that
        # would needs the offsets and the drift to cancel it: degenerate, and not reported.
        ms_wave = float(np.mean(wave ** 2))
        ms_room = float(np.mean(centred[rows] ** 2))
        if ms_wave <= 1.05 * ms_room and _recurs(np.concatenate([t[i] for i in segs]), centred, rows, freq, float(np.sqrt(2.0 * ms_wave))):
            amp = float(np.sqrt(2.0 * min(ms_wave, ms_room)))
            explained = max(0.0, float(e0 @ e0) - float(e @ e))
            oscillation = {"frequency_hz": freq, "amplitude": amp,
                           "share_of_variance": float(min(1.0, explained / sse_total)) if sse_total > 0
                           else float("nan"),
                           "p_value": p_osc, "experiments": int(sum(active)),
                           "samples": int(np.count_nonzero(rows))}
        else:
            freq, active = None, None
    X, beta, e = _fit(t, r, segs, freq, active)
    slope = float(beta[k])
    if var_total <= (1e-12 * float(np.max(np.abs(y)))) ** 2:      # constant per experiment: nothing to test
        slope_se, p_drift = float("nan"), float("nan")
    else:
        slope_se, p_drift = _hac_slope_p(X, e, k, slope, segs)
    drift = None
    if np.isfinite(p_drift) and p_drift < a_each:
        span = float(np.mean([t[idx[-1]] - t[idx[0]] for idx in segs]))
        keep = [c for c in range(X.shape[1]) if c != k]
        b1, *_ = np.linalg.lstsq(X[:, keep], y, rcond=None)
        e1 = y - X[:, keep] @ b1                    # the same without the drift: what it explains
        explained = max(0.0, float(e1 @ e1) - float(e @ e))
        drift = {"slope_per_s": slope, "slope_se": slope_se, "total_change": slope * span,
                 "share_of_variance": float(min(1.0, explained / sse_total)) if sse_total > 0 else float("nan"),
                 "p_value": p_drift}

    p_values = {"ljung_box": p_lb, "runs": p_runs, "oscillation": p_osc, "drift": p_drift}
    finite = [p for p in p_values.values() if np.isfinite(p)]
    out = {
        "structured": bool(finite and min(finite) < a_each),
        "n": n, "n_segments": k, "alpha": float(alpha), "alpha_per_test": a_each,
        "mean": float(np.mean(y)) if n else float("nan"),
        "rms": float(np.sqrt(np.mean(y ** 2))) if n else float("nan"),
        "noise_rms": _robust_noise_rms([e[a:b] for a, b in zip(bounds[:-1], bounds[1:])]),
        "lag1_autocorrelation": lag1,
        "ljung_box_q": q, "ljung_box_df": df_lb, "ljung_box_p": p_lb,
        "runs": n_runs, "runs_z": z_runs, "runs_p": p_runs,
        "p_values": p_values, "oscillation": oscillation, "drift": drift,
        "longest_period_s": longest_period(t, segs),
        "misfit": None, "x_unit": x_unit, "x_name": x_name, "response": response,
    }
    if out["structured"] and oscillation is None:
        xx = np.asarray(x, float).ravel() if x is not None else t
        if x is None:
            out.update(x_unit="s", x_name="time")
        out["misfit"] = misfit_region(r, segs, xx, t, max(out["noise_rms"], 1e-300),
                                      None if measured is None else np.asarray(measured, float).ravel())
    out["description"] = _describe(out, unit, k)
    return out


# ---------------------------------------------------------------------------------------------- for plots

def binned_residuals(x: np.ndarray, r: np.ndarray, bins: int | np.ndarray = 12) -> pd.DataFrame:
    """Mean and scatter of the residual in bins of x (displacement, velocity, force): a mean that moves with x
    is a missing effect of x (a bent stiffness curve, rate dependence). Equal-width bins over the range of x
    (or the given edges); columns low, high, center, mean, std (ddof 1), count; empty bins have NaN."""
    x = np.asarray(x, float).ravel()
    r = np.asarray(r, float).ravel()
    if x.shape != r.shape:
        raise ValueError(f"x and r differ in length ({len(x)} != {len(r)})")
    ok = np.isfinite(x) & np.isfinite(r)
    x, r = x[ok], r[ok]
    if np.ndim(bins) == 0:
        lo, hi = (float(x.min()), float(x.max())) if len(x) else (0.0, 1.0)
        if hi <= lo:
            lo, hi = lo - 0.5, hi + 0.5
        edges = np.linspace(lo, hi, int(bins) + 1)
    else:
        edges = np.asarray(bins, float)
    which = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    inside = (x >= edges[0]) & (x <= edges[-1])
    rows = []
    for b in range(len(edges) - 1):
        v = r[inside & (which == b)]
        rows.append({"low": edges[b], "high": edges[b + 1], "center": 0.5 * (edges[b] + edges[b + 1]),
                     "mean": float(v.mean()) if len(v) else float("nan"),
                     "std": float(v.std(ddof=1)) if len(v) > 1 else float("nan"),
                     "count": int(len(v))})
    return pd.DataFrame(rows, columns=["low", "high", "center", "mean", "std", "count"])


def by_direction(v: np.ndarray, r: np.ndarray, hold_fraction: float = HOLD_FRACTION) -> dict:
    """Residual while loading (v > 0), unloading (v < 0) and holding (|v| <= hold_fraction * max |v|):
    a mean that flips sign with the direction is hysteresis (friction, viscosity) the model lacks.
    {direction: {mean, rms, count}}; NaN for a direction with no samples."""
    v = np.asarray(v, float).ravel()
    r = np.asarray(r, float).ravel()
    if v.shape != r.shape:
        raise ValueError(f"v and r differ in length ({len(v)} != {len(r)})")
    ok = np.isfinite(v) & np.isfinite(r)
    v, r = v[ok], r[ok]
    thr = hold_fraction * (float(np.max(np.abs(v))) if len(v) else 0.0)
    masks = {"loading": v > thr, "unloading": v < -thr, "hold": np.abs(v) <= thr}
    out = {}
    for name, m in masks.items():
        x = r[m]
        out[name] = {"mean": float(x.mean()) if len(x) else float("nan"),
                     "rms": float(np.sqrt(np.mean(x ** 2))) if len(x) else float("nan"),
                     "count": int(len(x))}
    return out
