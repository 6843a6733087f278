"""Figures of ``fmusa diagnose``: ``<out>/figures/fit_time.png``, ``loops.png``, ``residuals.png``, ``ranking.png``.

They take the dict returned by :func:`fmusa.diagnose.run.diagnose` (with its in-memory fits, key ``_fits``)
and the experiments it was computed from. Nothing here runs the FMU: every curve is a prediction the
diagnosis already made. Units are the ones a reader of a mechanical test expects (mm, N, s); residuals are
model − measured in the response channel.
"""
from __future__ import annotations

import math
import textwrap
from pathlib import Path
from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402

from fmusa.diagnose import residuals as rs  # noqa: E402
from fmusa.diagnose.views import (by_loading_direction, experiment_motion, extended_name, final_label, final_name, fit_predictions,  # noqa: E402
                                  p_text, residual_series, response_channel, channel_units)
from fmusa.diagnose.motion import channel_word, motion_of
from fmusa.format import fmt  # noqa: E402
from fmusa.figure_check import MAX_HEIGHT_IN, MAX_WIDTH_IN  # noqa: E402
from fmusa.files import save_figure  # noqa: E402

__all__ = ["write_figures", "fig_fit_time", "fig_loops", "fig_residuals", "fig_ranking", "MAX_PANELS"]

DPI = 130
MAX_PANELS = 5                 # experiments drawn one per panel (with the summary, 3 rows of 2); the rest summarised
PAGE_W, PAGE_H = MAX_WIDTH_IN, MAX_HEIGHT_IN      # a journal page's text area [in]: every figure fits in it
DATA_COLOR = "0.35"
BASE_COLOR = "#1f77b4"
EXT_COLOR = "#d62728"
OTHER_COLOR = "#8c8c8c"
SIG_COLOR = "#ff9f40"
#: a candidate the checks kept from being named: the protocol cannot identify it, or a parameter beyond the test
SCREENED_COLOR = "#c9b3e0"
THRESH_COLOR = "#7b2cbf"

plt.rcParams.update({"font.size": 10, "axes.titlesize": 10.5, "axes.labelsize": 10, "legend.fontsize": 8.5,
                     "xtick.labelsize": 9, "ytick.labelsize": 9})


def _runner_up(diag: Mapping) -> str | None:
    """When no effect is named: the best-ranked candidate, drawn for comparison."""
    if extended_name(diag) != "none":
        return None
    ranking = diag.get("ranking") or []
    return ranking[0]["effect"] if ranking else None


def _models(diag: Mapping, experiments: Sequence) -> list[tuple[str, str, str, list[np.ndarray]]]:
    """(key, label, colour, predictions) of the curves to draw: baseline, extended or best candidate."""
    out = []
    base = fit_predictions(diag, "none", experiments)
    if base is not None:
        out.append(("none", "baseline (eq. 1)", BASE_COLOR, base))
    eff = final_name(diag)
    if eff != "none":
        ext = fit_predictions(diag, eff, experiments)
        if ext is not None:
            out.append((eff, f"final: {final_label(diag)}", EXT_COLOR, ext))
    else:
        ru = _runner_up(diag)
        pr = fit_predictions(diag, ru, experiments) if ru else None
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
    """Root-mean-square difference of two series."""
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


# ============================================================================ figures
def _save(fig, path: Path) -> Path:
    return save_figure(fig, path, dpi=DPI)     # written whole or not at all, checked in the tests


def _grid(n_panels: int, height: float = 3.0, top: float = 0.9):
    """One panel alone, else two per row, on a page's width; rows shrink to keep the figure on one page
    (``top``: room for the title and the legend above the panels)."""
    cols = 1 if n_panels == 1 else 2
    rows = math.ceil(n_panels / cols)
    row_h = min(height, (PAGE_H - top) / rows)
    # one panel alone is drawn at the page's width too, so the figure's title and legend fit above it
    fig, axes = plt.subplots(rows, cols, figsize=(PAGE_W, row_h * rows + top), squeeze=False)
    flat = list(axes.ravel())
    for ax in flat[n_panels:]:
        ax.set_visible(False)
    return fig, flat[:n_panels]


def _suptitle(fig, text: str, fontsize: float = 11) -> int:
    """The figure's title wrapped to its width; the number of lines."""
    lines = textwrap.wrap(text, int(fig.get_figwidth() * 72 / (0.56 * fontsize)))
    fig.suptitle("\n".join(lines), fontsize=fontsize, y=1 - 0.08 / fig.get_figheight(), va="top")
    return len(lines)


def _top_legend(fig, ax, ncol: int, title_lines: int = 1, handles=None, bottom: float = 0.0,
                legend_h: float = 0.3) -> None:
    """One legend for all panels, under the title, so that no panel's data hide behind it (``legend_h``,
    ``bottom``: the room it takes and the room kept under the panels [in]; tight_layout makes the title's)."""
    h = fig.get_figheight()
    below = (0.1 + 0.21 * title_lines) / h
    fig.tight_layout(rect=(0, bottom / h, 1, 1 - legend_h / h))
    if handles is None and ax is not None:
        handles = ax.get_legend_handles_labels()[0]
    if handles:
        fig.legend(handles=handles, loc="upper center", ncol=ncol, frameon=False, fontsize=8.5,
                   bbox_to_anchor=(0.5, 1 - below))


def _short(name: str, n: int = 38) -> str:
    return name if len(name) <= n else name[:n - 1] + "…"


def _not_shown_note(fig, experiments: Sequence, shown: list[int]) -> None:
    rest = len(experiments) - len(shown)
    if rest > 0:
        fig.text(0.5, 0.12 / fig.get_figheight(), f"{len(shown)} of {len(experiments)} experiments drawn; the "
                 f"RMSE of all {len(experiments)}: fit_time.png (last panel) and report.md",
                 ha="center", va="bottom", fontsize=9, style="italic")


def fig_fit_time(diag: Mapping, experiments: Sequence, path: Path) -> Path:
    """Measured response vs time per experiment with the baseline and the extended model."""
    resp, unit, f = response_channel(diag)
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
            # a chain's name ("a+b") is too long for a panel's title: the legend says what "final" is
            name = "baseline" if key == "none" else "final" if "+" in key else key
            parts.append(f"{name} {fmt(_rmse(preds[i], meas) * f)}")
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
        ax.set_xlabel("experiment")
        ax.set_title(f"all {len(experiments)} experiments", fontsize=9.5)
        vals_all = [v for *_, preds in models for v in (_rmse(p, e.response_signal) for p, e in
                                                         zip(preds, experiments)) if v > 0]
        if vals_all and max(vals_all) / min(vals_all) > 30:
            ax.set_yscale("log")
        ax.grid(alpha=0.3, axis="y")
    drive = channel_word(diag["data"]["drive"], motion_of(diag))
    lines = _suptitle(fig, f"{resp.capitalize()} response to the imposed {drive}: data, baseline and "
                      f"{'final model (' + final_label(diag) + ')' if extended_name(diag) != 'none' else 'no extension (effect: none)'}")
    _top_legend(fig, axes[0] if axes else None, len(models) + 1, lines)
    return _save(fig, path)


def fig_loops(diag: Mapping, experiments: Sequence, path: Path) -> Path:
    """Force–displacement loops per experiment: data points, baseline, extended (mm, N)."""
    drive = diag["data"]["drive"]
    (yu, yf), (fu, ff) = (channel_units(diag)[r] for r in ("displacement", "force"))
    yw, fw = (channel_word(r, motion_of(diag)) for r in ("displacement", "force"))
    models = _models(diag, experiments)
    shown = _shown(experiments)
    fig, axes = _grid(len(shown), height=3.2)
    for ax, i in zip(axes, shown):
        e = experiments[i]
        y = np.asarray(e.displacement, float) * yf
        F = np.asarray(e.force, float) * ff
        ms = 2.5 if len(y) > 400 else 3.5
        ax.plot(y, F, ".", color=DATA_COLOR, ms=ms, alpha=0.55, label="measured", zorder=4)
        for key, label, color, preds in models:
            ls = "--" if key == "none" else "-"
            if drive == "displacement":
                xm, ym = y, preds[i] * ff
            else:
                xm, ym = preds[i] * yf, F
            ax.plot(xm, ym, ls, color=color, lw=1.5, label=label, zorder=3 if key != "none" else 2)
        ax.set_title(_short(e.name), fontsize=9.5)
        ax.set_xlabel(f"{yw} [{yu}]")
        ax.set_ylabel(f"{fw} [{fu}]")
        ax.axhline(0, color="0.7", lw=0.6, zorder=0)
        ax.axvline(0, color="0.7", lw=0.6, zorder=0)
        ax.grid(alpha=0.3)
    lines = _suptitle(fig, f"{fw.capitalize()}–{yw} loops ({channel_word(drive, motion_of(diag))} imposed)")
    _top_legend(fig, axes[0] if axes else None, len(models) + 1, lines,
                bottom=0.4 if len(experiments) > len(shown) else 0.0)
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


def _residual_panel(ax, x: np.ndarray, r: np.ndarray, xlabel: str, color: str, ms: float, lim: float,
                    velocity_peaks: list[float] | None = None) -> None:
    """Residuals against one quantity with their binned means ± sd (bins with at least 3 points); against
    the velocity (``velocity_peaks`` given) on an axis that suits the experiments' speeds."""
    ax.plot(x, r, ".", color=color, ms=ms, alpha=0.35, label="residual")
    bins = _velocity_axis(ax, x, velocity_peaks) if velocity_peaks is not None else 12
    b = rs.binned_residuals(x, r, bins)
    b = b[b["count"] >= 3]
    ax.errorbar(b["center"], b["mean"], yerr=b["std"].fillna(0), fmt="o-", color="black", ms=4,
                lw=1.2, capsize=2, label="binned mean ± sd", zorder=4)
    ax.axhline(0, color="0.5", lw=0.8)
    ax.set_xlabel(xlabel)
    ax.set_ylim(-lim, lim)
    ax.grid(alpha=0.3)


def _direction_panel(ax, d: dict, f: float, color: str, lim: float) -> None:
    """Mean ± rms of the residual while loading, holding and unloading."""
    names = ["loading", "hold", "unloading"]
    means = [d[k]["mean"] * f for k in names]
    rmss = [d[k]["rms"] * f for k in names]
    xs = np.arange(3)
    ax.bar(xs, np.nan_to_num(means), 0.6, color=color, alpha=0.75, label="mean")
    ax.errorbar(xs, np.nan_to_num(means), yerr=np.nan_to_num(rmss), fmt="none", ecolor="black", capsize=5,
                lw=1.2, label="± rms")
    ax.set_xticks(xs)
    ax.set_xticklabels([f"{k}\n(n={d[k]['count']})" for k in names], fontsize=8)
    ax.axhline(0, color="0.5", lw=0.8)
    reach = np.nan_to_num(np.abs(means) + np.abs(rmss))
    ax.set_ylim(-max(lim, 1.08 * reach.max()), max(lim, 1.08 * reach.max()))     # every bar inside the axes
    ax.set_xlabel("loading direction (n: number of points)", fontsize=8.5)
    ax.set_title("by loading direction: mean ± rms", fontsize=9)
    ax.grid(alpha=0.3, axis="y")


def fig_residuals(diag: Mapping, experiments: Sequence, path: Path) -> Path:
    """Residuals (model − measured) of the baseline and the extended model against time, displacement,
    velocity and loading direction, with binned means."""
    resp, unit, f = response_channel(diag)
    eff = final_name(diag)
    rows = [("none", "baseline", BASE_COLOR)]
    if eff != "none":
        rows.append((eff, f"final ({final_label(diag)})", EXT_COLOR))
    data = [(k, lab, col, residual_series(diag, experiments, k)) for k, lab, col in rows]
    data = [d for d in data if d[3] is not None]
    motion = experiment_motion(diag, experiments)
    t = np.concatenate([np.asarray(e.t, float) for e in experiments])
    cu, mot = channel_units(diag), motion_of(diag)
    y_mm = np.concatenate([m[0] for m in motion]) * cu["displacement"][1]
    v_mm = np.concatenate([m[1] for m in motion]) * cu["velocity"][1]
    peaks = [float(np.max(np.abs(m[1]))) * cu["velocity"][1] for m in motion]
    vw, yw = (f"{channel_word(r, mot)} [{cu[r][0]}]" for r in ("velocity", "displacement"))
    vlabel = vw if diag["data"]["drive"] == "displacement" else f"measured {vw} (smoothed)"
    ylabel_disp = yw if diag["data"]["drive"] == "displacement" else f"measured {yw}"
    nblock = max(len(data), 1)       # one 2 × 2 block of panels per model: time, displacement / velocity, direction
    fig, axes = plt.subplots(2 * nblock, 2, figsize=(PAGE_W, min(2 * nblock * 2.45 + 0.9, PAGE_H)), squeeze=False)
    if not data:
        for ax in axes.ravel():
            ax.set_visible(False)
        axes[0, 0].set_visible(True)
        axes[0, 0].text(0.5, 0.5, "no model predictions in the diagnosis", ha="center", va="center")
    ms = 2.0 if len(t) > 1500 else 3.0
    for b, (key, label, color, res) in enumerate(data):
        r = np.concatenate(res) * f
        rms = float(np.sqrt(np.mean(r ** 2)))
        lim = np.nanpercentile(np.abs(r), 99.5) * 1.15 if len(r) else 1.0
        block = [axes[2 * b, 0], axes[2 * b, 1], axes[2 * b + 1, 0], axes[2 * b + 1, 1]]
        for ax, (x, xl) in zip(block, [(t, "time [s]"), (y_mm, ylabel_disp), (v_mm, vlabel)]):
            _residual_panel(ax, x, r, xl, color, ms, lim, peaks if ax is block[2] else None)
            ax.set_ylabel(f"residual [{unit}]")
        block[0].set_title(f"{label}: rms {fmt(rms)} {unit}", fontsize=9.5, loc="left", color=color)
        _direction_panel(block[3], by_loading_direction(experiments, motion, res), f, color, lim)
        block[3].set_ylabel(f"residual [{unit}]")
    sign = "model − measured"
    title = f"Residuals of the {resp} ({sign}), of the baseline and of the final model"
    if eff == "none":
        title = f"Residuals of the {resp} ({sign}) of the baseline (no effect named, so no 'after')"
    lines = _suptitle(fig, title)
    from matplotlib.lines import Line2D
    handles = [Line2D([], [], ls="none", marker=".", color=c, ms=8, label=f"residual, {lab}")
               for _, lab, c, _ in data]
    handles.append(Line2D([], [], marker="o", ms=4, color="black", label="binned mean ± sd (bins with ≥ 3 points)"))
    _top_legend(fig, None, 2, lines, handles=handles, legend_h=0.45)
    return _save(fig, path)


def _label_bar(ax, x: float, y: float, text: str, inside: bool, right: bool) -> None:
    """Value at the tip of a bar: inside it (white) when the bar is long, else just outside."""
    if inside:
        ax.annotate(text, (x, y), xytext=(-4 if right else 4, 0), textcoords="offset points", va="center",
                    ha="right" if right else "left", fontsize=8.5, color="white", fontweight="bold")
    else:
        ax.annotate(text, (x, y), xytext=(4 if right else -4, 0), textcoords="offset points", va="center",
                    ha="left" if right else "right", fontsize=8.5)


def _ranking_heldout_panel(ax, ranking: list, th: Mapping, ypos: np.ndarray, cols: list) -> None:
    """Held-out ratio (bars) and fitted ratio (markers) against the baseline, log axis."""
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
    ax.set_xlabel("RMSE ratio to the baseline's [–] (log; < 1 is better)")
    ax.set_title(f"held-out prediction error (significant < {fmt(th.get('heldout_ratio'))})")


def _ranking_bic_panel(ax, ranking: list, th: Mapping, ypos: np.ndarray, cols: list) -> None:
    """ΔBIC against the baseline; symlog when some candidate is far past the threshold."""
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
            _label_bar(ax, v, yy, f"{v:+.0f}" if abs(v) >= 10 else f"{v:+.1f}", inside=False, right=v >= 0)
    ax.set_xlabel("ΔBIC vs the baseline [–] (< 0 is better" + (", symlog)" if big else ")"))
    ax.set_title(f"information criterion (significant < {fmt(th.get('delta_bic'))})")


def _ranking_p_panel(ax, ranking: list, th: Mapping, ypos: np.ndarray, cols: list) -> None:
    """−log10 p of the nested F test of the extra parameters."""
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
        _label_bar(ax, v, yy, p_text(pv), inside=False, right=True)
    ax.set_xlabel("−log₁₀ p of the nested F test [–] (larger: stronger)")
    ax.set_title(f"extra parameters' significance (p < {fmt(th.get('p_value'))})")


def fig_ranking(diag: Mapping, path: Path) -> Path:
    """Every candidate's held-out RMSE ratio, ΔBIC and p against the baseline, thresholds, winner."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    ranking = list(diag.get("ranking") or [])
    th = diag.get("thresholds") or {}
    eff = extended_name(diag)
    names = [r["effect"] for r in ranking]
    n = max(len(names), 1)
    # the three criteria stacked on a page's width, each with the candidates' names
    panel_h = min(0.75 + 0.42 * n, (PAGE_H - 1.2) / 3)
    fig, axes = plt.subplots(3, 1, figsize=(PAGE_W, 3 * panel_h + 1.2), sharey=True)
    ypos = np.arange(len(names))[::-1].astype(float)
    cols = [EXT_COLOR if r["effect"] in eff.split(" ≡ ") else SIG_COLOR if r.get("significant")
            else SCREENED_COLOR if r.get("implausible") or r.get("unidentifiable") else OTHER_COLOR for r in ranking]
    _ranking_heldout_panel(axes[0], ranking, th, ypos, cols)
    _ranking_bic_panel(axes[1], ranking, th, ypos, cols)
    _ranking_p_panel(axes[2], ranking, th, ypos, cols)
    axes[0].set_yticks(ypos)
    axes[0].set_ylim(-0.6, len(names) - 0.25)
    for a in axes:
        a.grid(alpha=0.3, axis="x")
        a.set_yticks(ypos)
        a.set_yticklabels([f"{nm} ★" if nm == eff else nm for nm in names], fontsize=8.5)
        a.tick_params(axis="y", labelleft=True)
        a.set_ylabel("candidate effect", fontsize=9)
        a.title.set_fontsize(9.5)
    handles = [Patch(color=EXT_COLOR, label=f"named: {eff} ★" if eff != "none" else "named"),
               Patch(color=SIG_COLOR, label="significant, not named"),
               Patch(color=OTHER_COLOR, label="not significant"),
               *([Patch(color=SCREENED_COLOR, label="removed by the checks (protocol, or beyond the test)")]
                 if SCREENED_COLOR in cols else []),
               Line2D([], [], ls="none", marker="D", color="black", mfc="white", label="fitted-data RMSE ratio"),
               Line2D([], [], ls="--", color=THRESH_COLOR, label="significance threshold")]
    lines = _suptitle(fig, f"Candidate effects against the baseline, best first (effect named: {eff})")
    _top_legend(fig, None, 3, lines, handles=handles, legend_h=0.45)          # the legend takes two rows
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
