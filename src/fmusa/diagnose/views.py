"""What the figures and the report of ``fmusa diagnose`` show, computed once for both.

Natural units (mm, N, s, N/mm, N·s/mm) for the SI values of the diagnosis, the response channel, the
predictions and residuals of a fit per experiment, the motion of each experiment and its residuals by
loading direction, and how p-values, ratios and differences are written. Nothing here draws or writes.
"""
from __future__ import annotations

import math
from typing import Mapping, Sequence

import numpy as np

from fmusa.diagnose import residuals as rs
from fmusa.diagnose import motion as mo
from fmusa.diagnose.effects import UNITS
from fmusa.format import fmt

__all__ = ["NATURAL_UNITS", "natural", "channel_units", "param_label", "p_text", "ratio_text", "delta_text", "response_channel",
           "fit_predictions", "extended_name", "final_name", "final_label", "final_residuals", "structure_text", "residual_series", "experiment_motion", "by_loading_direction"]

#: SI unit -> (natural unit, factor SI -> natural)
NATURAL_UNITS = {"N/m": ("N/mm", 1e-3), "N.s/m": ("N·s/mm", 1e-3), "m": ("mm", 1e3), "N": ("N", 1.0), "1/m": ("1/mm", 1e-3),
                 "s": ("s", 1.0), "1": ("", 1.0), "": ("", 1.0)}


# ============================================================================ units and numbers
def _si_unit(name: str) -> str:
    return UNITS.get(name, "")


def natural(name: str, value: float, motion: str | None = None) -> tuple[float, str]:
    """A parameter value in natural units: (value, unit), e.g. c_y 3.7e5 N/m -> (370, 'N/mm'); of a rotational
    interface (``motion``, default :func:`fmusa.diagnose.motion.current`) e.g. gap 0.01 rad -> (0.573, 'deg')."""
    rot = mo.natural_unit(mo.si_unit(name, motion), motion)
    if rot is not None:
        return float(value) * rot[1], rot[0]
    unit, f = NATURAL_UNITS.get(_si_unit(name), (_si_unit(name), 1.0))
    return float(value) * f, unit


def channel_units(diag: Mapping) -> dict[str, tuple[str, float]]:
    """(natural unit, factor SI -> natural) of the displacement, force and velocity channels of a diagnosis:
    mm, N, mm/s; of a rotational interface deg, N·m, deg/s."""
    if mo.motion_of(diag) == mo.ROTATION:
        return {r: mo.ROTATION_NATURAL[mo.channel_unit(r, mo.ROTATION)]
                for r in ("displacement", "force", "velocity")}
    return {"displacement": ("mm", 1e3), "force": ("N", 1.0), "velocity": ("mm/s", 1e3)}


def param_label(name: str) -> str:
    """An axis label: the name and its natural unit in brackets."""
    unit = natural(name, 0.0)[1]
    return f"{name} [{unit}]" if unit else name


def p_text(x) -> str:
    """A p-value: plain above 1e-3, else mantissa-exponent; values below 1e-300 as '< 1e-300'."""
    try:
        x = float(x)
    except (TypeError, ValueError):
        return "–"
    if math.isnan(x):
        return "–"
    if x < 1e-300:
        return "< 1e-300"
    return f"{x:.3f}" if x >= 1e-3 else fmt(x, 2)


def ratio_text(x) -> str:
    """How the report writes an RMSE ratio (4 significant digits)."""
    return fmt(x, 4)


def delta_text(x) -> str:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return "–"
    if not math.isfinite(x):
        return fmt(x)
    return f"{x:+.1f}" if abs(x) < 1e5 else f"{x:+.3g}"


def response_channel(diag: Mapping) -> tuple[str, str, float]:
    """(response channel, its natural unit, factor SI -> natural); of a rotational interface the channel's
    word (torque, angle) and unit (N·m, deg)."""
    drive = diag["data"]["drive"]
    if mo.motion_of(diag) == mo.ROTATION:
        resp = "force" if drive == "displacement" else "displacement"
        return (mo.channel_word(resp, mo.ROTATION), *channel_units(diag)[resp])
    return ("force", "N", 1.0) if drive == "displacement" else ("displacement", "mm", 1e3)


# ============================================================================ pieces of the diagnosis
def _fits(diag: Mapping) -> dict:
    """The in-memory fits of the diagnosis (absent once it went through diagnosis.json)."""
    return dict(diag.get("_fits") or {})


def fit_predictions(diag: Mapping, name: str | None, experiments: Sequence) -> list[np.ndarray] | None:
    """A fit's prediction per experiment, or None when the diagnosis does not hold it."""
    fit = _fits(diag).get(name) if name else None
    preds = getattr(fit, "predictions", None)
    if not preds or len(preds) != len(experiments):
        return None
    return [np.asarray(p, float) for p in preds]


def extended_name(diag: Mapping) -> str:
    """The named effect ('none' when there is none)."""
    return diag.get("effect", "none")


def final_name(diag: Mapping) -> str:
    """The key of the final model's fit: the last step of the chain of effects ("a+b"), else the named
    effect ('none' when there is none)."""
    model = (diag.get("final") or {}).get("model")
    return model if model and (model in _fits(diag) or "_fits" not in diag) else extended_name(diag)


def final_label(diag: Mapping) -> str:
    """The final model in words: "baseline + a + b", or "baseline" when no effect is named."""
    effects = (diag.get("final") or {}).get("effects") or []
    if not effects:
        eff = extended_name(diag)
        return "baseline" if eff == "none" else f"baseline + {eff}"
    return "baseline + " + " + ".join(effects)


def final_residuals(diag: Mapping) -> dict | None:
    """The residual structure of the final model (of the chain's last step, else of the named effect's)."""
    res = diag.get("residuals") or {}
    return res.get("final") or res.get("extended")


def residual_series(diag: Mapping, experiments: Sequence, key: str) -> list[np.ndarray] | None:
    """model − measured per experiment, in SI."""
    pr = fit_predictions(diag, key, experiments)
    if pr is None:
        return None
    return [p - np.asarray(e.response_signal, float) for p, e in zip(pr, experiments)]


def experiment_motion(diag: Mapping, experiments: Sequence) -> list[tuple[np.ndarray, np.ndarray]]:
    """(displacement m, velocity m/s) per experiment, from the measured displacement: in displacement drive
    it is the imposed (exact) signal; in force drive it is measured with noise, so its velocity is taken
    from a Savitzky–Golay fit (cubic, about 11 samples) instead of a raw difference."""
    from scipy.signal import savgol_filter

    out = []
    drive = diag["data"]["drive"]
    for e in experiments:
        y = np.asarray(e.displacement, float)
        t = np.asarray(e.t, float)
        if len(t) < 2:
            out.append((y, np.zeros_like(y)))
            continue
        if drive == "force" and len(t) >= 7:
            win = min(11, len(t) - (1 - len(t) % 2))
            win = win if win % 2 else win - 1
            dt = float(np.median(np.diff(t)))
            v = savgol_filter(y, win, min(3, win - 1), deriv=1, delta=dt)
        else:
            v = np.gradient(y, t)
        out.append((y, v))
    return out


def _load_sign(y: np.ndarray) -> float:
    """+1 for a test loaded in the positive direction, −1 for one loaded in the negative direction (the sign
    of the displacement at its largest magnitude)."""
    if len(y) == 0:
        return 1.0
    s = float(np.sign(y[int(np.argmax(np.abs(y)))]))
    return s if s != 0 else 1.0


def by_loading_direction(experiments: Sequence, motion, resid: list[np.ndarray]) -> dict:
    """Residual by loading direction, pooled over experiments (fmusa.diagnose.residuals.by_direction per experiment).
    Loading = moving away from zero, in the direction the experiment was loaded; a test loaded in the negative
    direction has its velocity and residual signed by −1, so that friction (always opposing the motion) and
    yield (odd in the displacement) show with the same sign in tests of both directions. The hold threshold is
    relative to each experiment's own peak speed, so a slow test is not all 'hold' next to a fast one."""
    acc = {k: [0.0, 0.0, 0] for k in ("loading", "hold", "unloading")}
    for (y, v), r in zip(motion, resid):
        s = _load_sign(y)
        d = rs.by_direction(v * s, r * s)
        for k, st in d.items():
            if st["count"]:
                acc[k][0] += st["mean"] * st["count"]
                acc[k][1] += st["rms"] ** 2 * st["count"]
                acc[k][2] += st["count"]
    return {k: {"mean": (m / c if c else float("nan")), "rms": (math.sqrt(q / c) if c else float("nan")),
                "count": c} for k, (m, q, c) in acc.items()}


# ============================================================================ residual structure in words
def structure_text(st: Mapping | None, unit: str, f: float) -> str:
    """The residual structure in plain words and natural units: the one text the console, diagnosis.json
    and the report print. Where the time axis was derived from a nominal rate (``st['axis']``), the search
    ran along the drive, and a periodic part is a waviness with a period in mm (or N) of the drive, never a
    frequency; a drift is per mm (or N) of the drive."""
    if not st:
        return "not computed"
    if not st.get("structured"):
        return str(st.get("description") or "white: no structure beyond noise")
    axis = st.get("axis") or {"name": "time", "unit": "s", "derived_time": False}
    along = bool(axis.get("derived_time"))
    au = axis.get("unit") or ""
    parts = []
    osc, drift = st.get("oscillation"), st.get("drift")
    mis = st.get("misfit")
    if mis:
        xu = st.get("x_unit") or ""
        parts.append(f"the model is {fmt(mis['size_low'] * f)}–{fmt(mis['size_high'] * f)} {unit} "
                     f"{'above' if mis['sign'] > 0 else 'below'} the data from {fmt(mis['x_start'])} {xu} to "
                     f"{fmt(mis['x_end'])} {xu} of {st.get('x_name') or 'displacement'}"
                     + (f" (experiment {mis['experiment'] + 1})" if st.get("n_segments", 1) > 1 else "")
                     + (f", where the measured {st.get('response') or 'response'} falls"
                        if mis.get("response_falls") else ""))
    if osc and along:
        parts.append(f"a waviness with a period of {fmt(1 / osc['frequency_hz'])} {au} of {axis['name']} "
                     f"and amplitude {fmt(osc['amplitude'] * f)} {unit}, "
                     f"{100 * osc['share_of_variance']:.0f} % of the residual variance")
    elif osc:
        parts.append(f"an oscillation at {fmt(osc['frequency_hz'])} Hz (period {fmt(1 / osc['frequency_hz'])} s) "
                     f"of amplitude {fmt(osc['amplitude'] * f)} {unit}, "
                     f"{100 * osc['share_of_variance']:.0f} % of the residual variance")
    if drift:
        over = "over the test" if st.get("n_segments", 1) == 1 else "over an experiment of mean length"
        per = f"{unit}/{au}" if along else f"{unit}/s"
        parts.append(f"a drift of {drift['total_change'] * f:+.3g} {unit} {over} "
                     f"({fmt(drift['slope_per_s'] * f)} {per}, {100 * drift['share_of_variance']:.0f} % of "
                     f"the residual variance)")
    if not osc and not drift:
        rho, z = st.get("lag1_autocorrelation", float("nan")), st.get("runs_z", float("nan"))
        if (z < 0) or (rho > 0):
            parts.append(f"a slowly varying systematic error (lag-1 autocorrelation {rho:.2f}, runs test "
                         f"z = {z:.1f}), but no single oscillation or drift")
        else:
            parts.append(f"residuals that alternate more than noise does (lag-1 autocorrelation {rho:.2f})")
    return "structured: " + "; ".join(parts)

