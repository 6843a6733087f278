"""Figures and report of ``fmusa diagnose``: ``<out>/figures/*.png`` and ``<out>/report.md``.

Both take the dict returned by :func:`fmusa.diagnose.diagnose` (with its in-memory fits, key ``_fits``) and
the experiments it was computed from. Nothing here runs the FMU: every curve is a prediction the diagnosis
already made, every number in the report is read from the dict or computed from those predictions.

Units are the ones a reader of a mechanical test expects: displacement in mm, force in N, time in s,
stiffness in N/mm, damping in N·s/mm. Residuals are model − measured, in the response channel: N when the
test imposed the displacement, mm when it imposed the force.

    from fmusa.diagnose import diagnose
    from fmusa.diagnose_report import write_figures, write_report
    diag = diagnose(experiments, "displacement")
    figs = write_figures(diag, experiments, out)
    write_report(diag, experiments, out, figs)
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402

from fmusa.diagnose import residuals as rs  # noqa: E402
from fmusa.format import fmt  # noqa: E402

__all__ = ["write_figures", "write_report", "natural", "param_label", "MAX_PANELS", "EFFECT_MEANING"]

DPI = 130
MAX_PANELS = 6                 # experiments drawn one per panel; the rest are summarised
DATA_COLOR = "0.35"
BASE_COLOR = "#1f77b4"
EXT_COLOR = "#d62728"
OTHER_COLOR = "#8c8c8c"
SIG_COLOR = "#ff9f40"
THRESH_COLOR = "#7b2cbf"

#: SI unit -> (natural unit, factor SI -> natural)
NATURAL_UNITS = {"N/m": ("N/mm", 1e-3), "N.s/m": ("N·s/mm", 1e-3), "m": ("mm", 1e3), "N": ("N", 1.0),
                 "s": ("s", 1.0), "1": ("", 1.0), "": ("", 1.0)}

#: Fallback SI units (fmusa.diagnose.UNITS is used when importable).
_SI_UNITS = {"c_y": "N/m", "d_y": "N.s/m", "gap": "m", "nl_ratio": "1", "nl_y_b": "m", "yield_ratio": "1",
             "yield_F": "N", "fric_F": "N", "ve_k": "N/m", "ve_tau": "s", "F_offset": "N", "y_offset": "m"}

PARAM_MEANING = {
    "c_y": "stiffness c (eq. 1)",
    "d_y": "damping d (eq. 1)",
    "gap": "slack: no force within ±gap",
    "nl_ratio": "stiffness past the breakpoint / c",
    "nl_y_b": "breakpoint displacement of the stiffness",
    "yield_ratio": "stiffness after yield / c",
    "yield_F": "yield force",
    "fric_F": "Coulomb friction force",
    "ve_k": "stiffness of the Maxwell branch",
    "ve_tau": "relaxation time of the Maxwell branch",
    "F_offset": "bias of the force channel",
    "y_offset": "bias of the displacement channel",
}

#: What each effect means physically (fmu/MODEL.md, "Effects beyond eq. 1").
EFFECT_MEANING = {
    "none": "the baseline spring–damper (eq. 1) explains the data within their noise",
    "nonlinear_stiffness": "the force–displacement curve bends (stiffness changes past a breakpoint) and is "
                           "elastic: unloading retraces loading",
    "viscoelastic_relaxation": "a Maxwell branch (spring in series with a dashpot): force relaxes at held "
                               "displacement, displacement creeps at held force, stiffness rises with rate",
    "coulomb_friction": "a rate-independent force opposing the motion: a hysteresis loop of constant width",
    "yield_softening": "the interface yields (threads stripping bone): lower stiffness past a yield force and "
                       "a permanent set after unloading",
    "backlash_gap": "slack: no force until the displacement passes a gap",
    "sensor_offset": "a constant bias in the measured channel",
}

plt.rcParams.update({"font.size": 10, "axes.titlesize": 10.5, "axes.labelsize": 10, "legend.fontsize": 8.5,
                     "xtick.labelsize": 9, "ytick.labelsize": 9})


# ============================================================================ units and numbers
def _si_unit(name: str) -> str:
    try:
        from fmusa.diagnose.run import UNITS
        return UNITS.get(name, _SI_UNITS.get(name, ""))
    except Exception:   # pragma: no cover - diagnose always importable in the package
        return _SI_UNITS.get(name, "")


def natural(name: str, value: float) -> tuple[float, str]:
    """A parameter value in natural units: (value, unit), e.g. c_y 3.7e5 N/m -> (370, 'N/mm')."""
    unit, f = NATURAL_UNITS.get(_si_unit(name), (_si_unit(name), 1.0))
    return float(value) * f, unit


def param_label(name: str) -> str:
    unit = natural(name, 0.0)[1]
    return f"{name} [{unit}]" if unit else name


def _p(x) -> str:
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


def _delta(x) -> str:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return "–"
    if not math.isfinite(x):
        return fmt(x)
    return f"{x:+.1f}" if abs(x) < 1e5 else f"{x:+.3g}"


def _table(header: Sequence[str], rows: Sequence[Sequence]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(str(x).replace("|", "\\|") for x in r) + " |")
    return "\n".join(lines)


def _response(diag: Mapping) -> tuple[str, str, float]:
    """(response channel, its natural unit, factor SI -> natural)."""
    drive = diag["data"]["drive"]
    return ("force", "N", 1.0) if drive == "displacement" else ("displacement", "mm", 1e3)


# ============================================================================ pieces of the diagnosis
def _fits(diag: Mapping) -> dict:
    return dict(diag.get("_fits") or {})


def _predictions(diag: Mapping, name: str | None, experiments: Sequence) -> list[np.ndarray] | None:
    fit = _fits(diag).get(name) if name else None
    preds = getattr(fit, "predictions", None)
    if not preds or len(preds) != len(experiments):
        return None
    return [np.asarray(p, float) for p in preds]


def _extended_name(diag: Mapping) -> str:
    return diag.get("effect", "none")


def _runner_up(diag: Mapping) -> str | None:
    """When no effect is named: the best-ranked candidate, drawn for comparison."""
    if _extended_name(diag) != "none":
        return None
    ranking = diag.get("ranking") or []
    return ranking[0]["effect"] if ranking else None


def _models(diag: Mapping, experiments: Sequence) -> list[tuple[str, str, str, list[np.ndarray]]]:
    """(key, label, colour, predictions) of the curves to draw: baseline, extended or best candidate."""
    out = []
    base = _predictions(diag, "none", experiments)
    if base is not None:
        out.append(("none", "baseline (eq. 1)", BASE_COLOR, base))
    eff = _extended_name(diag)
    if eff != "none":
        ext = _predictions(diag, eff, experiments)
        if ext is not None:
            out.append((eff, f"extended: + {eff}", EXT_COLOR, ext))
    else:
        ru = _runner_up(diag)
        pr = _predictions(diag, ru, experiments) if ru else None
        if pr is not None:
            out.append((ru, f"best candidate {ru} (not significant)", OTHER_COLOR, pr))
    return out


def _shown(experiments: Sequence) -> list[int]:
    """Indices of the experiments drawn one per panel: all up to MAX_PANELS, else spread over the list."""
    n = len(experiments)
    if n <= MAX_PANELS:
        return list(range(n))
    return sorted({int(round(i)) for i in np.linspace(0, n - 1, MAX_PANELS)})


def _rmse(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


def _motion(diag: Mapping, experiments: Sequence) -> list[tuple[np.ndarray, np.ndarray]]:
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


def _direction(experiments: Sequence, motion, resid: list[np.ndarray]) -> dict:
    """Residual by loading direction, pooled over experiments (fmusa.residuals.by_direction per experiment).
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


def _residuals(diag: Mapping, experiments: Sequence, key: str) -> list[np.ndarray] | None:
    """model − measured per experiment, in SI."""
    pr = _predictions(diag, key, experiments)
    if pr is None:
        return None
    return [p - np.asarray(e.response_signal, float) for p, e in zip(pr, experiments)]


# ============================================================================ figures
def _save(fig, path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return path


def _grid(n_panels: int, width: float = 5.2, height: float = 3.3):
    cols = 1 if n_panels == 1 else 2 if n_panels <= 4 else 3
    rows = math.ceil(n_panels / cols)
    # one panel alone is drawn wider, so the figure's title and legend fit above it
    fig, axes = plt.subplots(rows, cols, figsize=(max(width * cols, 8.0), height * rows), squeeze=False)
    flat = list(axes.ravel())
    for ax in flat[n_panels:]:
        ax.set_visible(False)
    return fig, flat[:n_panels]


def _top_legend(fig, ax, ncol: int) -> None:
    """One legend for all panels, under the title, so that no panel's data hide behind it."""
    h = fig.get_figheight()
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.3 / h))
    if ax is not None:
        handles, labels = ax.get_legend_handles_labels()
        fig.legend(handles, labels, loc="upper center", ncol=ncol, frameon=False, fontsize=9,
                   bbox_to_anchor=(0.5, 1 - 0.28 / h))


def _short(name: str, n: int = 38) -> str:
    return name if len(name) <= n else name[:n - 1] + "…"


def _not_shown_note(fig, experiments: Sequence, shown: list[int]) -> None:
    rest = len(experiments) - len(shown)
    if rest > 0:
        fig.text(0.5, -0.01, f"{len(shown)} of {len(experiments)} experiments drawn; the RMSE of all "
                 f"{len(experiments)} is in the last panel of fit_time.png and in report.md",
                 ha="center", va="top", fontsize=9, style="italic")


def fig_fit_time(diag: Mapping, experiments: Sequence, path: Path) -> Path:
    """Measured response vs time per experiment with the baseline and the extended model."""
    resp, unit, f = _response(diag)
    models = _models(diag, experiments)
    shown = _shown(experiments)
    summary = len(experiments) > len(shown)
    fig, axes = _grid(len(shown) + (1 if summary else 0))
    for ax, i in zip(axes, shown):
        e = experiments[i]
        t = np.asarray(e.t, float)
        meas = np.asarray(e.response_signal, float)
        ms = 2.5 if len(t) > 400 else 3.5
        ax.plot(t, meas * f, ".", color=DATA_COLOR, ms=ms, alpha=0.6, label="measured", zorder=4)
        parts = []
        for key, label, color, preds in models:
            ls = "--" if key == "none" else "-"
            ax.plot(t, preds[i] * f, ls, color=color, lw=1.6, label=label, zorder=3 if key != "none" else 2)
            parts.append(f"{'baseline' if key == 'none' else key} {fmt(_rmse(preds[i], meas) * f)}")
        ax.set_title(_short(e.name) + ("\nRMSE [" + unit + "]: " + ", ".join(parts) if parts else ""),
                     fontsize=9.5)
        ax.set_xlabel("time [s]")
        ax.set_ylabel(f"{resp} [{unit}]")
        ax.grid(alpha=0.3)
    if summary:
        ax = axes[-1]
        x = np.arange(len(experiments))
        width = 0.8 / max(len(models), 1)
        for j, (key, label, color, preds) in enumerate(models):
            vals = [_rmse(p, e.response_signal) * f for p, e in zip(preds, experiments)]
            ax.bar(x + (j - (len(models) - 1) / 2) * width, vals, width, color=color, label=label)
        ax.set_xticks(x)
        ax.set_xticklabels([_short(e.name, 18) for e in experiments], rotation=60, ha="right", fontsize=7)
        ax.set_ylabel(f"RMSE of {resp} [{unit}]")
        ax.set_title(f"all {len(experiments)} experiments", fontsize=9.5)
        vals_all = [v for *_, preds in models for v in (_rmse(p, e.response_signal) for p, e in
                                                         zip(preds, experiments)) if v > 0]
        if vals_all and max(vals_all) / min(vals_all) > 30:
            ax.set_yscale("log")
        ax.grid(alpha=0.3, axis="y")
    drive = diag["data"]["drive"]
    fig.suptitle(f"{resp.capitalize()} response to the imposed {drive}: data, baseline and "
                 f"{'extended model' if _extended_name(diag) != 'none' else 'no extension (effect: none)'}",
                 fontsize=11)
    _top_legend(fig, axes[0] if axes else None, len(models) + 1)
    return _save(fig, path)


def fig_loops(diag: Mapping, experiments: Sequence, path: Path) -> Path:
    """Force–displacement loops per experiment: data points, baseline, extended (mm, N)."""
    drive = diag["data"]["drive"]
    models = _models(diag, experiments)
    shown = _shown(experiments)
    fig, axes = _grid(len(shown), width=4.6, height=3.8)
    for ax, i in zip(axes, shown):
        e = experiments[i]
        y = np.asarray(e.displacement, float) * 1e3
        F = np.asarray(e.force, float)
        ms = 2.5 if len(y) > 400 else 3.5
        ax.plot(y, F, ".", color=DATA_COLOR, ms=ms, alpha=0.55, label="measured", zorder=4)
        for key, label, color, preds in models:
            ls = "--" if key == "none" else "-"
            if drive == "displacement":
                xm, ym = y, preds[i]
            else:
                xm, ym = preds[i] * 1e3, F
            ax.plot(xm, ym, ls, color=color, lw=1.5, label=label, zorder=3 if key != "none" else 2)
        ax.set_title(_short(e.name), fontsize=9.5)
        ax.set_xlabel("displacement [mm]")
        ax.set_ylabel("force [N]")
        ax.axhline(0, color="0.7", lw=0.6, zorder=0)
        ax.axvline(0, color="0.7", lw=0.6, zorder=0)
        ax.grid(alpha=0.3)
    fig.suptitle(f"Force–displacement loops ({drive} imposed)", fontsize=11)
    _top_legend(fig, axes[0] if axes else None, len(models) + 1)
    _not_shown_note(fig, experiments, shown)
    return _save(fig, path)


def _velocity_axis(ax, v_mm: np.ndarray, peaks: list[float]):
    """Symmetric log axis when the experiments' peak speeds span more than a decade and a half (1, 10,
    100 mm/s tests); returns bin edges that suit the axis."""
    peaks = [p for p in peaks if p > 0]
    lo, hi = float(np.min(v_mm)), float(np.max(v_mm))
    if peaks and max(peaks) / min(peaks) > 30:
        lin = 0.1 * min(peaks)
        ax.set_xscale("symlog", linthresh=lin, linscale=0.5)
        top = max(abs(lo), abs(hi))
        dec = [10.0 ** k for k in range(int(math.ceil(math.log10(lin * 3))), int(math.ceil(math.log10(top))) + 1)
               if 10.0 ** k <= top * 1.05]
        ticks = sorted({0.0, *dec, *(-x for x in dec if -x >= lo * 1.05)} if lo < 0 else {0.0, *dec})
        ax.xaxis.set_major_locator(matplotlib.ticker.FixedLocator(ticks))
        ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda x, _: fmt(x)))
        ax.xaxis.set_minor_locator(matplotlib.ticker.NullLocator())
        def tr(x):
            return np.sign(x) * np.log10(1 + np.abs(x) / lin)
        def inv(u):
            return np.sign(u) * lin * (10 ** np.abs(u) - 1)
        return inv(np.linspace(tr(lo), tr(hi), 17))
    return 12


def fig_residuals(diag: Mapping, experiments: Sequence, path: Path) -> Path:
    """Residuals (model − measured) of the baseline and the extended model against time, displacement,
    velocity and loading direction, with binned means."""
    resp, unit, f = _response(diag)
    eff = _extended_name(diag)
    rows = [("none", "baseline", BASE_COLOR)]
    if eff != "none":
        rows.append((eff, f"extended (+ {eff})", EXT_COLOR))
    data = [(k, lab, col, _residuals(diag, experiments, k)) for k, lab, col in rows]
    data = [d for d in data if d[3] is not None]
    motion = _motion(diag, experiments)
    t = np.concatenate([np.asarray(e.t, float) for e in experiments])
    y_mm = np.concatenate([m[0] for m in motion]) * 1e3
    v_mm = np.concatenate([m[1] for m in motion]) * 1e3
    peaks = [float(np.max(np.abs(m[1]))) * 1e3 for m in motion]
    vlabel = "velocity [mm/s]" if diag["data"]["drive"] == "displacement" else \
        "velocity [mm/s] (smoothed, of the measured displacement)"
    ylabel_disp = "displacement [mm]" if diag["data"]["drive"] == "displacement" else \
        "measured displacement [mm]"
    nrow = max(len(data), 1)
    fig, axes = plt.subplots(nrow, 4, figsize=(17, 3.6 * nrow), squeeze=False,
                             gridspec_kw={"width_ratios": [1.2, 1, 1, 0.75]})
    if not data:
        for ax in axes.ravel():
            ax.set_visible(False)
        axes[0, 0].set_visible(True)
        axes[0, 0].text(0.5, 0.5, "no model predictions in the diagnosis", ha="center", va="center")
    ms = 2.0 if len(t) > 1500 else 3.0
    for row, (key, label, color, res) in enumerate(data):
        r = np.concatenate(res) * f
        rms = float(np.sqrt(np.mean(r ** 2)))
        lim = np.nanpercentile(np.abs(r), 99.5) * 1.15 if len(r) else 1.0
        for col, (x, xl) in enumerate([(t, "time [s]"), (y_mm, ylabel_disp), (v_mm, vlabel)]):
            ax = axes[row, col]
            ax.plot(x, r, ".", color=color, ms=ms, alpha=0.35, label="residual")
            bins = _velocity_axis(ax, v_mm, peaks) if col == 2 else 12
            b = rs.binned_residuals(x, r, bins)
            b = b[b["count"] >= 3]
            ax.errorbar(b["center"], b["mean"], yerr=b["std"].fillna(0), fmt="o-", color="black", ms=4,
                        lw=1.2, capsize=2, label="binned mean ± sd", zorder=4)
            ax.axhline(0, color="0.5", lw=0.8)
            ax.set_xlabel(xl)
            ax.set_ylim(-lim, lim)
            ax.grid(alpha=0.3)
            if col == 0:
                ax.set_ylabel(f"{label}\nresidual [{unit}]")
                ax.set_title(f"{label}: rms {fmt(rms)} {unit}", fontsize=10, loc="left")
        ax = axes[row, 3]
        d = _direction(experiments, motion, res)
        names = ["loading", "hold", "unloading"]
        means = [d[k]["mean"] * f for k in names]
        rmss = [d[k]["rms"] * f for k in names]
        xs = np.arange(3)
        ax.bar(xs, np.nan_to_num(means), 0.6, color=color, alpha=0.75, label="mean")
        ax.errorbar(xs, np.nan_to_num(means), yerr=np.nan_to_num(rmss), fmt="none", ecolor="black", capsize=5,
                    lw=1.2, label="± rms")
        ax.set_xticks(xs)
        ax.set_xticklabels([f"{k}\n(n={d[k]['count']})" for k in names], fontsize=8.5)
        ax.axhline(0, color="0.5", lw=0.8)
        ax.set_ylim(-lim, lim)
        ax.set_title("by loading direction: mean ± rms", fontsize=9.5)
        ax.grid(alpha=0.3, axis="y")
    sign = "model − measured"
    title = f"Residuals of the {resp} ({sign}), before and after the extension"
    if eff == "none":
        title = f"Residuals of the {resp} ({sign}) of the baseline (no effect named, so no 'after')"
    fig.suptitle(title, fontsize=11, x=0.3)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    from matplotlib.lines import Line2D
    handles = [Line2D([], [], ls="none", marker=".", color=c, ms=8, label=f"residual, {lab}")
               for _, lab, c, _ in data]
    handles.append(Line2D([], [], marker="o", ms=4, color="black", label="binned mean ± sd (bins with ≥ 3 points)"))
    fig.legend(handles=handles, loc="upper right", ncol=len(handles), fontsize=8.5, frameon=False,
               bbox_to_anchor=(1.0, 1.005))
    return _save(fig, path)


def fig_ranking(diag: Mapping, path: Path) -> Path:
    """Every candidate's held-out RMSE ratio, ΔBIC and p against the baseline, thresholds, winner."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    ranking = list(diag.get("ranking") or [])
    th = diag.get("thresholds") or {}
    eff = _extended_name(diag)
    names = [r["effect"] for r in ranking]
    n = max(len(names), 1)
    fig, axes = plt.subplots(1, 3, figsize=(15, max(3.0, 1.4 + 0.5 * n)), sharey=True,
                             gridspec_kw={"width_ratios": [1.25, 1.2, 1]})
    ypos = np.arange(len(names))[::-1].astype(float)
    cols = [EXT_COLOR if r["effect"] == eff else SIG_COLOR if r.get("significant") else OTHER_COLOR
            for r in ranking]

    def label_bar(ax, x, y, text, inside: bool, right: bool):
        """Value at the tip of a bar: inside it (white) when the bar is long, else just outside."""
        if inside:
            ax.annotate(text, (x, y), xytext=(-4 if right else 4, 0), textcoords="offset points", va="center",
                        ha="right" if right else "left", fontsize=8.5, color="white", fontweight="bold")
        else:
            ax.annotate(text, (x, y), xytext=(4 if right else -4, 0), textcoords="offset points", va="center",
                        ha="left" if right else "right", fontsize=8.5)

    # held-out ratio (bars) and fitted ratio (markers), log axis
    ax = axes[0]
    h = np.array([r.get("heldout_rmse_ratio", np.nan) for r in ranking], float)
    fr = np.array([r.get("rmse_ratio", np.nan) for r in ranking], float)
    pos = np.concatenate([h[np.isfinite(h) & (h > 0)], fr[np.isfinite(fr) & (fr > 0)], [1.0]])
    lo = 10 ** math.floor(math.log10(min(pos.min(), th.get("heldout_ratio", 1.0)) * 0.8))
    hi = max(pos.max() * 1.5, 1.5)
    ax.barh(ypos, np.where(np.isfinite(h), h, lo) - lo, left=lo, color=cols, height=0.5)
    ax.plot(fr, ypos, "D", color="black", ms=5, mfc="white", zorder=4)
    ax.set_xscale("log")
    ax.set_xlim(lo, hi)
    ax.axvline(1.0, color="0.3", lw=1)
    if "heldout_ratio" in th:
        ax.axvline(th["heldout_ratio"], color=THRESH_COLOR, ls="--", lw=1.4)
    for yy, v, vf in zip(ypos, h, fr):
        ax.annotate(f"held-out {fmt(v, 3)}, fitted {fmt(vf, 3)}", (lo, yy + 0.27), xytext=(3, 0),
                    textcoords="offset points", va="bottom", ha="left", fontsize=8)
    ticks = [m * 10.0 ** k for k in range(int(math.floor(math.log10(lo))), int(math.ceil(math.log10(hi))) + 1)
             for m in ((1, 2, 5) if hi / lo < 200 else (1,)) if lo <= m * 10.0 ** k <= hi]
    ax.xaxis.set_major_locator(matplotlib.ticker.FixedLocator(ticks))
    ax.xaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda x, _: fmt(x)))
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("RMSE / baseline's RMSE (log; < 1 is better)")
    ax.set_title(f"held-out prediction error (significant < {fmt(th.get('heldout_ratio'))})")
    # ΔBIC
    ax = axes[1]
    dbic = np.array([r.get("delta_bic", np.nan) for r in ranking], float)
    ax.barh(ypos, np.nan_to_num(dbic), color=cols, height=0.6)
    lin = max(10.0, abs(th.get("delta_bic", -10.0)))
    big = np.nanmax(np.abs(dbic), initial=0) > 10 * lin
    if big:
        ax.set_xscale("symlog", linthresh=lin, linscale=0.6)
    left = min(np.nanmin(dbic, initial=0.0), th.get("delta_bic", 0.0))
    right = max(np.nanmax(dbic, initial=0.0), 0.0)
    if big:
        ax.set_xlim(left * 3 if left < 0 else -lin, right * 3 if right > lin else lin)
    else:
        span = right - left
        ax.set_xlim(left - 0.15 * span - 1, right + 0.15 * span + 1)
    ax.axvline(0, color="0.3", lw=1)
    if "delta_bic" in th:
        ax.axvline(th["delta_bic"], color=THRESH_COLOR, ls="--", lw=1.4)
    for yy, v in zip(ypos, dbic):
        if np.isfinite(v):
            label_bar(ax, v, yy, f"{v:+.0f}" if abs(v) >= 10 else f"{v:+.1f}", inside=False, right=v >= 0)
    ax.set_xlabel("ΔBIC vs the baseline (< 0 is better" + (", symlog)" if big else ")"))
    ax.set_title(f"information criterion (significant < {fmt(th.get('delta_bic'))})")
    # nested F test p
    ax = axes[2]
    p = np.array([r.get("p_value", np.nan) for r in ranking], float)
    lp = -np.log10(np.clip(np.nan_to_num(p, nan=1.0), 1e-300, 1.0))
    ax.barh(ypos, lp, color=cols, height=0.6)
    if "p_value" in th:
        ax.axvline(-math.log10(th["p_value"]), color=THRESH_COLOR, ls="--", lw=1.4)
    top = max(np.max(lp, initial=0), -math.log10(th.get("p_value", 0.1)))
    if top > 30:
        ax.set_xscale("symlog", linthresh=3, linscale=0.6)
        ax.set_xlim(0, top * 6)
    else:
        ax.set_xlim(0, top * 1.25 + 0.5)
    for yy, v, pv in zip(ypos, lp, p):
        label_bar(ax, v, yy, _p(pv), inside=False, right=True)
    ax.set_xlabel("−log₁₀ p of the nested F test (larger: stronger)")
    ax.set_title(f"extra parameters' significance (p < {fmt(th.get('p_value'))})")
    axes[0].set_yticks(ypos)
    axes[0].set_yticklabels([f"{nm} ★" if nm == eff else nm for nm in names])
    axes[0].set_ylim(-0.6, len(names) - 0.25)
    for a in axes:
        a.grid(alpha=0.3, axis="x")
    handles = [Patch(color=EXT_COLOR, label=f"named: {eff} ★" if eff != "none" else "named"),
               Patch(color=SIG_COLOR, label="significant, not named"),
               Patch(color=OTHER_COLOR, label="not significant"),
               Line2D([], [], ls="none", marker="D", color="black", mfc="white", label="fitted-data RMSE ratio"),
               Line2D([], [], ls="--", color=THRESH_COLOR, label="significance threshold")]
    fig.suptitle(f"Candidate effects against the baseline, best first (effect named: {eff})", fontsize=11)
    fig.tight_layout(rect=(0, 0.0, 1, 0.93))
    fig.legend(handles=handles, loc="lower center", ncol=5, bbox_to_anchor=(0.5, 0.87 if n > 3 else 0.84),
               fontsize=8.5, frameon=False)
    fig.subplots_adjust(top=0.78 if n <= 3 else 0.84)
    return _save(fig, path)


def write_figures(diag: dict, experiments, out_dir: Path) -> list[Path]:
    """fit_time.png, loops.png, residuals.png and ranking.png in ``out_dir/figures``; their paths."""
    fig_dir = Path(out_dir) / "figures"
    fig_dir.mkdir(parents=True, exist_ok=True)
    experiments = list(experiments)
    return [fig_fit_time(diag, experiments, fig_dir / "fit_time.png"),
            fig_loops(diag, experiments, fig_dir / "loops.png"),
            fig_residuals(diag, experiments, fig_dir / "residuals.png"),
            fig_ranking(diag, fig_dir / "ranking.png")]


# ============================================================================ report
CAPTIONS = {
    "fit_time.png": "Measured response against time for each experiment (grey points) with the calibrated "
                    "baseline (dashed) and the extended model (solid); each panel's title gives both RMSEs.",
    "loops.png": "Force against displacement: the measured points and the loops the two models trace. A loop "
                 "in the data that the baseline's line does not open is hysteresis (friction, viscosity, yield).",
    "residuals.png": "Residuals (model − measured) of the baseline (top) and of the extended model (bottom) "
                     "against time, displacement, velocity and loading direction; black: binned means ± sd. "
                     "A binned mean that follows an axis is an effect of that quantity the model lacks.",
    "ranking.png": "Every candidate against the baseline: held-out and fitted RMSE ratios, ΔBIC and the p of "
                   "the nested F test, with the significance thresholds (dashed purple); the named effect "
                   "in red (★), other significant candidates in orange.",
}


def _ci(name: str, value: float, ci) -> str:
    v, u = natural(name, value)
    s = fmt(v, 4)
    if ci is not None and len(ci) == 2:
        lo, hi = natural(name, ci[0])[0], natural(name, ci[1])[0]
        s += f" [{fmt(lo, 3)}, {fmt(hi, 3)}]"
    return s


def _summary_params(summary: Mapping) -> tuple[dict, dict]:
    return dict(summary.get("params") or {}), dict(summary.get("ci95") or {})


def _describe_structure(st: Mapping | None, unit: str, f: float) -> str:
    """The residual structure in plain words and natural units."""
    if not st:
        return "not computed"
    if not st.get("structured"):
        return str(st.get("description") or "white: no structure beyond noise")
    parts = []
    osc, drift = st.get("oscillation"), st.get("drift")
    if osc:
        parts.append(f"an oscillation at {fmt(osc['frequency_hz'])} Hz (period {fmt(1 / osc['frequency_hz'])} s) "
                     f"of amplitude {fmt(osc['amplitude'] * f)} {unit}, "
                     f"{100 * osc['share_of_variance']:.0f} % of the residual variance")
    if drift:
        over = "over the test" if st.get("n_segments", 1) == 1 else "over an experiment of mean duration"
        parts.append(f"a drift of {drift['total_change'] * f:+.3g} {unit} {over} "
                     f"({fmt(drift['slope_per_s'] * f)} {unit}/s, {100 * drift['share_of_variance']:.0f} % of "
                     f"the residual variance)")
    if not parts:
        rho, z = st.get("lag1_autocorrelation", float("nan")), st.get("runs_z", float("nan"))
        if (z < 0) or (rho > 0):
            parts.append(f"a slowly varying systematic error (lag-1 autocorrelation {rho:.2f}, runs test "
                         f"z = {z:.1f}), but no single oscillation or drift")
        else:
            parts.append(f"residuals that alternate more than noise does (lag-1 autocorrelation {rho:.2f})")
    return "structured: " + "; ".join(parts)


def _data_section(diag: Mapping, experiments: Sequence) -> str:
    data = diag["data"]
    resp, unit, f = _response(diag)
    rows = []
    for e, de in zip(experiments, data.get("experiments") or [{}] * len(experiments)):
        t = np.asarray(e.t, float)
        v = np.gradient(np.asarray(e.displacement, float), t) if len(t) > 1 else np.zeros(1)
        src = e.meta.get("downsampled_from") if isinstance(e.meta, Mapping) else None
        pts = f"{e.n}" + (f" (block means of {src} rows)" if src else "")
        rows.append([e.name, f"`{e.path}`", pts, fmt(e.duration, 4),
                     fmt(float(np.max(np.abs(e.displacement))) * 1e3), fmt(float(np.max(np.abs(e.force)))),
                     fmt(float(np.max(np.abs(v))) * 1e3)])
    out = "## Data\n\n"
    out += (f"{len(experiments)} experiment{'s, fitted jointly' if len(experiments) != 1 else ''}; "
            f"the test imposed the **{data['drive']}**, the model is driven by it and predicts the "
            f"**{data['response']}** ({unit}). {data['points']} points in all.\n\n")
    out += _table(["experiment", "file", "points", "duration [s]", "peak |displacement| [mm]",
                   "peak |force| [N]", "peak |velocity| [mm/s]"], rows) + "\n\n"
    out += (f"Held-out error: {data.get('heldout', '–')}. Each fold is left out, the model is refitted on the "
            f"rest, and the refit predicts the left-out points; the held-out RMSE pools the squared errors "
            f"of all folds.\n")
    return out


def _verdict_section(diag: Mapping) -> str:
    eff = diag["effect"]
    gain = diag.get("gain") or {}
    th = diag.get("thresholds") or {}
    resp, unit, f = _response(diag)
    base, ext = diag.get("baseline") or {}, diag.get("extended") or {}
    ranking = diag.get("ranking") or []
    out = "## The effect\n\n"
    if eff != "none":
        out += (f"**Effect: `{eff}`**: {EFFECT_MEANING.get(eff, '')}.\n\n"
                f"Adding it to the baseline lowers the RMSE of the {resp} on the fitted data from "
                f"{fmt(base.get('rmse', float('nan')) * f)} {unit} to {fmt(ext.get('rmse', float('nan')) * f)} "
                f"{unit} (ratio {ratio_text(gain.get('rmse_ratio'))}) and on held-out data from "
                f"{fmt(base.get('heldout_rmse', float('nan')) * f)} {unit} to "
                f"{fmt(ext.get('heldout_rmse', float('nan')) * f)} {unit} "
                f"(ratio {ratio_text(gain.get('heldout_rmse_ratio'))}); ΔAIC = {_delta(gain.get('delta_aic'))}, "
                f"ΔBIC = {_delta(gain.get('delta_bic'))}, p = {_p(gain.get('p_value'))} (F test of the extra "
                f"parameters).\n\n")
        mp = diag.get("main_parameter")
        ep = diag.get("effect_params") or {}
        if mp and mp in ep:
            v, u = natural(mp, ep[mp]["value"])
            lo, hi = (natural(mp, c)[0] for c in ep[mp]["ci95"])
            out += (f"Main parameter: {mp} ({PARAM_MEANING.get(mp, '')}) = {fmt(v, 4)} {u} "
                    f"(95 % interval {fmt(lo)} to {fmt(hi)} {u}).\n\n")
        crit = gain
    else:
        base_st = (diag.get("residuals") or {}).get("baseline") or {}
        if base_st.get("structured"):
            out += ("**Effect: `none`**: no candidate's gain passes all three tests. This does not mean the "
                    "baseline explains the data: its residuals are structured (see below), but no single "
                    "candidate effect removes that structure convincingly enough on held-out data.\n\n")
        else:
            out += (f"**Effect: `none`**: {EFFECT_MEANING['none']}; no candidate's gain passes all three "
                    "tests.\n\n")
        crit = ranking[0] if ranking else {}
        if ranking:
            out += (f"The best-ranked candidate, `{crit['effect']}`, reaches an RMSE ratio of "
                    f"{ratio_text(crit.get('rmse_ratio'))} on the fitted data and "
                    f"{ratio_text(crit.get('heldout_rmse_ratio'))} on held-out data, "
                    f"ΔAIC = {_delta(crit.get('delta_aic'))}, ΔBIC = {_delta(crit.get('delta_bic'))}, "
                    f"p = {_p(crit.get('p_value'))}.\n\n")
        out += (f"The baseline's RMSE is {fmt(base.get('rmse', float('nan')) * f)} {unit} on the fitted data "
                f"and {fmt(base.get('heldout_rmse', float('nan')) * f)} {unit} on held-out data.\n\n")
    if th and crit:
        checks = [
            ("held-out RMSE ratio", ratio_text(crit.get("heldout_rmse_ratio")), f"< {fmt(th['heldout_ratio'])}",
             crit.get("heldout_rmse_ratio", float("nan")) < th["heldout_ratio"]),
            ("ΔBIC", _delta(crit.get("delta_bic")), f"< {fmt(th['delta_bic'])}",
             crit.get("delta_bic", float("nan")) < th["delta_bic"]),
            ("p (nested F test)", _p(crit.get("p_value")), f"< {fmt(th['p_value'])}",
             crit.get("p_value", float("nan")) < th["p_value"]),
        ]
        who = f"`{eff}`" if eff != "none" else f"`{crit.get('effect', '–')}` (best-ranked)"
        out += (f"An effect is named only when its gain is significant on all three counts; for {who}:\n\n")
        out += _table(["criterion", "value", "required", "met"],
                      [[a, b, c, "yes" if d else "no"] for a, b, c, d in checks]) + "\n\n"
        out += (f"ΔAIC = {_delta(crit.get('delta_aic'))} is reported for comparison; it does not decide. "
                f"A candidate counts as indistinguishable from the winner when it is significant too, its "
                f"held-out RMSE is within a factor {fmt(th.get('tie_heldout'))} of the winner's and its BIC "
                f"within {fmt(th.get('tie_bic'))}.\n")
    return out


def _params_section(diag: Mapping) -> str:
    base_p, base_ci = _summary_params(diag.get("baseline") or {})
    ext_p, ext_ci = _summary_params(diag.get("extended") or {})
    names = list(base_p) + [n for n in ext_p if n not in base_p]
    rows = []
    for n in names:
        unit = natural(n, 0.0)[1] or "–"
        b = _ci(n, base_p[n], base_ci.get(n)) if n in base_p else "–"
        x = _ci(n, ext_p[n], ext_ci.get(n)) if n in ext_p else "–"
        rows.append([f"`{n}`", PARAM_MEANING.get(n, ""), unit, b, x])
    eff = diag["effect"]
    out = "## Parameters\n\n"
    out += (f"Values with their 95 % confidence intervals in brackets (Gauss–Newton covariance; see the caveats). "
            f"Extended model: baseline + `{eff}`" if eff != "none" else
            "Values with their 95 % confidence intervals in brackets (Gauss–Newton covariance; see the caveats). "
            "No effect is named, so the extended model is the baseline")
    out += ".\n\n" + _table(["parameter", "meaning", "unit", "baseline", "extended"], rows) + "\n"
    return out


def _ranking_section(diag: Mapping) -> str:
    resp, unit, f = _response(diag)
    rows = []
    for i, r in enumerate(diag.get("ranking") or [], 1):
        eparams = [(k, v) for k, v in (r.get("params") or {}).items() if k not in ("c_y", "d_y")]
        ptxt = ", ".join(f"{k} = {fmt(natural(k, v)[0])}{(' ' + natural(k, v)[1]) if natural(k, v)[1] else ''}"
                         for k, v in eparams) or "–"
        rows.append([i, f"`{r['effect']}`" + (" ★" if r["effect"] == diag["effect"] else ""),
                     "yes" if r.get("significant") else "no", r.get("k", "–"),
                     fmt(r.get("rmse", float("nan")) * f), fmt(r.get("heldout_rmse", float("nan")) * f),
                     ratio_text(r.get("rmse_ratio")), ratio_text(r.get("heldout_rmse_ratio")),
                     _delta(r.get("delta_aic")), _delta(r.get("delta_bic")), _p(r.get("p_value")), ptxt])
    out = "## Ranking\n\n"
    out += ("Every candidate fitted as the baseline plus that one effect, best first (significant candidates "
            "first, then by held-out RMSE). Ratios and differences are against the baseline "
            f"(RMSE {fmt((diag.get('baseline') or {}).get('rmse', float('nan')) * f)} {unit}, held-out "
            f"{fmt((diag.get('baseline') or {}).get('heldout_rmse', float('nan')) * f)} {unit}); "
            "k counts the fitted parameters; ★ marks the named effect.\n\n")
    out += _table(["#", "candidate", "significant", "k", f"RMSE [{unit}]", f"held-out RMSE [{unit}]",
                   "RMSE ratio", "held-out ratio", "ΔAIC", "ΔBIC", "p", "effect parameters"], rows) + "\n"
    return out


def _residual_section(diag: Mapping, experiments: Sequence) -> str:
    resp, unit, f = _response(diag)
    res = diag.get("residuals") or {}
    eff = diag["effect"]
    cols = [("baseline", res.get("baseline"))]
    if eff != "none":
        cols.append((f"extended (+ {eff})", res.get("extended")))

    def g(st, k):
        return (st or {}).get(k, float("nan"))

    def row(label, fn):
        return [label] + [fn(st) for _, st in cols]
    rows = [
        row(f"rms [{unit}]", lambda st: fmt(g(st, "rms") * f)),
        row(f"mean [{unit}]", lambda st: fmt(g(st, "mean") * f)),
        row(f"rms of the white part [{unit}]", lambda st: fmt(g(st, "noise_rms") * f)),
        row("lag-1 autocorrelation", lambda st: f"{g(st, 'lag1_autocorrelation'):.3f}"),
        row("Ljung–Box Q (df), p", lambda st: f"{fmt(g(st, 'ljung_box_q'))} ({g(st, 'ljung_box_df')}), "
                                              f"p = {_p(g(st, 'ljung_box_p'))}"),
        row("runs test z, p", lambda st: f"{g(st, 'runs_z'):.2f}, p = {_p(g(st, 'runs_p'))}"),
        row("spectral line p", lambda st: _p(((st or {}).get("p_values") or {}).get("oscillation", float("nan")))),
        row("drift p", lambda st: _p(((st or {}).get("p_values") or {}).get("drift", float("nan")))),
        row("structured", lambda st: "yes" if (st or {}).get("structured") else "no"),
    ]
    alpha = g(cols[0][1], "alpha")
    out = "## Residuals before and after\n\n"
    out += (f"Residual = model − measured {resp}. Four tests tell structure from white noise, each at "
            f"α/4 = {fmt(alpha / 4 if math.isfinite(alpha) else float('nan'))} (α = {fmt(alpha)} overall): "
            "Ljung–Box (autocorrelation), the runs test on the signs (z < 0: long stretches on one side), a "
            "spectral line and a linear drift. Several experiments are tested each on its own and pooled.\n\n")
    out += _table(["statistic"] + [c for c, _ in cols], rows) + "\n\n"
    for label, st in cols:
        out += f"- {label}: {_describe_structure(st, unit, f)}.\n"
    # by direction
    motion = _motion(diag, experiments)
    drows = []
    for key, label in [("none", "baseline")] + ([(eff, f"extended (+ {eff})")] if eff != "none" else []):
        r = _residuals(diag, experiments, key)
        if r is None:
            continue
        d = _direction(experiments, motion, r)
        drows.append([label] + [f"{fmt(d[k]['mean'] * f)} ± {fmt(d[k]['rms'] * f)} (n = {d[k]['count']})"
                                for k in ("loading", "hold", "unloading")])
    if drows:
        out += (f"\nResidual by loading direction, mean ± rms [{unit}] (loading: moving away from zero in the "
                "direction the test was loaded; hold: speed below 2 % of the experiment's peak; tests loaded in "
                "the negative direction enter with their residual's sign flipped, so that effects odd in the "
                "motion add up across directions). A mean that flips sign between loading and "
                "unloading is hysteresis the model lacks; a mean in the holds is relaxation or creep.\n\n")
        out += _table(["model", "loading", "hold", "unloading"], drows) + "\n"
    out += "\n### What is left\n\n"
    st = res.get("extended")
    if diag.get("leftover") or (st and st.get("structured")):
        out += (f"Structure remains in the residuals of the {'extended model' if eff != 'none' else 'baseline'}: "
                f"{_describe_structure(st, unit, f)}.")
        osc, drift = (st or {}).get("oscillation"), (st or {}).get("drift")
        if osc:
            out += (f" The oscillation (frequency {fmt(osc['frequency_hz'])} Hz, amplitude "
                    f"{fmt(osc['amplitude'] * f)} {unit}, p = {_p(osc.get('p_value'))}) is not part of any "
                    "candidate: a resonance of the test rig or a periodic disturbance.")
        if drift:
            out += (f" The drift ({fmt(drift['slope_per_s'] * f)} {unit}/s, {drift['total_change'] * f:+.3g} "
                    f"{unit} in all, p = {_p(drift.get('p_value'))}) may be a sensor drift, temperature, or a slow "
                    "effect none of the candidates has.")
        if not osc and not drift:
            out += (" It is neither a single oscillation nor a drift: a systematic error the candidates "
                    "do not describe, or two effects at once.")
        out += "\n"
    else:
        out += (f"Nothing: the residuals of the {'extended model' if eff != 'none' else 'baseline'} pass all four "
                "tests as white noise.\n")
    return out


def _ties_section(diag: Mapping) -> str:
    ties = diag.get("indistinguishable") or []
    out = "## Candidates the data cannot tell apart\n\n"
    if not ties:
        if diag["effect"] == "none":
            return out + "None: no candidate is significant.\n"
        return out + (f"None: no other significant candidate comes close to `{diag['effect']}` on held-out error "
                      "and BIC.\n")
    out += (f"These candidates explain the data about as well as `{diag['effect']}`; the data cannot decide "
            "between them. The test that would:\n\n")
    ranking = {r["effect"]: r for r in diag.get("ranking") or []}
    for t in ties:
        r = ranking.get(t["effect"], {})
        out += (f"- `{t['effect']}` (held-out ratio {ratio_text(r.get('heldout_rmse_ratio'))}, ΔBIC "
                f"{_delta(r.get('delta_bic'))}): {t['separating_test']}.\n")
    return out


def _caveats_section(diag: Mapping) -> str:
    res = diag.get("residuals") or {}
    structured = [k for k in ("baseline", "extended") if (res.get(k) or {}).get("structured")]
    out = "## Caveats\n\n"
    out += ("- The 95 % intervals come from the Gauss–Newton covariance and assume white, independent "
            "residuals of constant variance.")
    if (res.get("extended") or {}).get("structured"):
        rho = res["extended"].get("lag1_autocorrelation", float("nan"))
        n = res["extended"].get("n", 0)
        if math.isfinite(rho) and -1 < rho < 1 and rho > 0:
            n_eff = n * (1 - rho) / (1 + rho)
            out += (f" Here the residuals are structured (lag-1 autocorrelation {rho:.2f}), so the intervals "
                    f"are too narrow: with AR(1) errors {n} points carry the information of about "
                    f"{max(n_eff, 1):.0f}, and the intervals should be about {math.sqrt(n / max(n_eff, 1)):.1f}× "
                    f"wider.")
        else:
            out += " Here the residuals are structured, so the intervals are too narrow."
    else:
        out += (" Structured residuals would make them too narrow; here the residuals of the "
                f"{'extended model' if diag['effect'] != 'none' else 'baseline'} pass as white, so they are "
                "about right.")
    out += "\n"
    out += ("- The p of the nested F test and the BIC make the same white-noise assumption; with structured "
            "residuals they overstate the evidence. The held-out ratio does not rely on it.\n")
    out += ("- The held-out refits start from the all-data optimum (one start each), so they are not fully "
            "independent of the held-out points: the held-out error is, if anything, optimistic, equally for "
            "every candidate.\n")
    if diag["data"].get("heldout", "").startswith("4 contiguous"):
        out += ("- With one experiment, held-out blocks are stretches of the same test: a prediction into a "
                "stretch the fit did not see, not a new test.\n")
    out += ("- Every candidate is one effect added to the baseline; two effects at once are not fitted, and "
            "the named effect is the single one that explains most.\n")
    if structured and "extended" not in structured:
        out += "- The baseline's residuals were structured; the extension removed that structure.\n"
    return out


def write_report(diag: dict, experiments, out_dir: Path, figures: list[Path]) -> Path:
    """``out_dir/report.md``: the data, the named effect and why, parameters with intervals, the ranking, the
    residual diagnosis before and after, look-alike candidates, caveats and the figures."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    experiments = list(experiments)
    eff = diag["effect"]
    parts = [f"# Diagnosis: `{eff}`\n\n"
             f"The measured {diag['data']['response']} under imposed {diag['data']['drive']} against the "
             f"baseline spring–damper (eq. 1: stiffness c, damping d) and against the baseline plus each "
             f"candidate effect ({len(diag.get('ranking') or [])} candidates); the effect is named only when "
             f"its gain is significant.\n",
             _data_section(diag, experiments), _verdict_section(diag), _params_section(diag),
             _ranking_section(diag), _residual_section(diag, experiments), _ties_section(diag),
             _caveats_section(diag)]
    if figures:
        fig_txt = "## Figures\n\n"
        for p in figures:
            p = Path(p)
            try:
                rel = p.relative_to(out_dir)
            except ValueError:
                rel = Path("figures") / p.name
            fig_txt += f"![{p.name}]({rel.as_posix()})\n\n*{p.name}*: {CAPTIONS.get(p.name, '')}\n\n"
        parts.append(fig_txt)
    parts.append("## Files\n\n- `diagnosis.json`: every number of this report\n- `figures/`: the figures above\n")
    path = out_dir / "report.md"
    path.write_text("\n".join(p.rstrip() + "\n" for p in parts))
    return path
