"""The figures of any study, drawn from data already computed (runs, regions, search levels, fits).

Every function takes plain data plus a target path, writes one PNG with matplotlib's Agg backend and returns
the path; none runs an FMU. Labels, titles and units are arguments (the report builds them from the study's
own descriptions and units), so nothing here knows which model is studied.

Conventions: log axes only where the positive values span decades (:func:`spans_decades`), thresholds as
lines, regions of interest as frames (solid: the region the search used; other frames as the caller asks).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping, Sequence

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib import colors as mcolors  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch, Rectangle  # noqa: E402

from fmusa.format import fmt
from fmusa.files import save_figure

__all__ = [
    "fmt", "RegionFrame", "Threshold", "grid_heatmap", "line_plot", "scatter_panels", "search_metric",
    "search_path", "regression_plot", "sensitivity_figures", "index_tables", "level_colors", "spans_decades",
    "log_ticks", "save", "unit_suffix", "lower_first", "search_points", "readable", "readable_formatter",
    "series_styles", "SERIES_COLORS", "MARKERS", "PAGE_WIDTH", "AUTO_COLOR", "OTHER_COLOR", "OPT_COLOR", "THRESH_COLOR",
]

DPI = 130
#: a journal page's text width, in inches: a figure this wide prints at its own font sizes
PAGE_WIDTH = 7.0
AUTO_COLOR = "#d62728"      # the region the search used: solid red
OTHER_COLOR = "#1f1fff"     # a second region (e.g. one chosen by hand): dashed blue
OPT_COLOR = "#d62728"
MARK_COLOR = "black"
THRESH_COLOR = "#7b2cbf"
#: positive values spanning at least this many decades get a log axis
LOG_DECADES = 1.5
MARKERS = ["o", "s", "^", "D", "v", "P", "X", "<", ">", "h", "p", "*"]

plt.rcParams.update({
    "font.size": 10, "axes.titlesize": 11, "axes.labelsize": 10, "legend.fontsize": 8.5,
    "xtick.labelsize": 9, "ytick.labelsize": 9, "axes.grid": False,
})


@dataclass(frozen=True)
class RegionFrame:
    """A region drawn as a frame: ``region`` has inner/outer ranges; ``label`` names it in the legend."""
    region: object
    label: str
    color: str = AUTO_COLOR
    style: str = "-"
    inset: float = 0.0


@dataclass(frozen=True)
class Threshold:
    """A bound of a constraint, drawn as a line (on the colour bar of a heat map)."""
    value: float
    label: str


# ============================================================================ helpers
def lower_first(text: str) -> str:
    """"Spring stiffness (c)" -> "spring stiffness (c)" to follow other words (not "FMU ...")."""
    return text[:1].lower() + text[1:] if text[1:2].islower() else text


def unit_suffix(u: str) -> str:
    return f" [{u}]" if u else ""


def save(fig, path: str | Path) -> Path:
    """Written whole or not at all (a full disk leaves the earlier figure, never half of one), and checked in
    the tests (:func:`fmusa.files.save_figure`)."""
    return save_figure(fig, path, dpi=DPI)


_SUPERSCRIPT = str.maketrans("-0123456789", "⁻⁰¹²³⁴⁵⁶⁷⁸⁹")


def readable(x: float, sig: int = 3, strip: bool = True) -> str:
    """A number as a figure prints it: plain from 0.001 up to 100000 (``0.186``, ``1000``, ``15625``), else
    ``1.86×10⁻⁵`` (never ``1.86e-5`` or ``1.00e3``); ``sig`` significant digits, ``strip`` drops the mantissa's
    trailing zeros (tick labels) or keeps them (table cells, which then line up)."""
    try:
        x = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not math.isfinite(x):
        return "–" if math.isnan(x) else ("∞" if x > 0 else "−∞")
    if x == 0:
        return "0"
    e = int(math.floor(math.log10(abs(x))))
    if 1e-3 <= abs(x) < 1e5:
        text = f"{x:.{max(0, sig - 1 - e)}f}"
        if strip and "." in text:
            text = text.rstrip("0").rstrip(".")
        return text.replace("-", "−")
    m = x / 10 ** e
    if round(abs(m), sig - 1) >= 10:
        e, m = e + 1, m / 10
    ms = f"{m:.{max(sig - 1, 0)}f}"
    if strip and "." in ms:
        ms = ms.rstrip("0").rstrip(".")
    return f"{ms}×10{str(e).translate(_SUPERSCRIPT)}".replace("-", "−", 1) if x < 0 else \
        f"{ms}×10{str(e).translate(_SUPERSCRIPT)}"


def readable_formatter(sig: int = 3) -> matplotlib.ticker.Formatter:
    """Tick labels through :func:`readable` (a linear axis; log axes keep matplotlib's 10ⁿ)."""
    return matplotlib.ticker.FuncFormatter(lambda v, _pos: readable(v, sig))


def spans_decades(values, decades: float = LOG_DECADES) -> bool:
    """Whether the positive finite ``values`` are all positive and span at least ``decades`` decades:
    only then does a log axis show them better than a linear one."""
    a = np.asarray(pd.to_numeric(pd.Series(np.ravel(values)), errors="coerce"), float)
    a = a[np.isfinite(a)]
    if a.size < 2 or (a <= 0).any():
        return False
    return bool(a.max() / a.min() >= 10 ** decades)


#: a qualitative palette (matplotlib's tab10) whose colours stay apart in print
SERIES_COLORS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f",
                 "#bcbd22", "#17becf")


def series_styles(n: int) -> list[tuple[str, str]]:
    """(colour, marker) for ``n`` series, every pair distinct for any ``n`` up to 60 (10 colours and 12
    markers cycle together, so series 0 and 10 share a colour but not a marker); beyond that, pairs repeat
    and the caller must add a line style."""
    return [(SERIES_COLORS[i % len(SERIES_COLORS)], MARKERS[i % len(MARKERS)]) for i in range(n)]


def level_colors(levels: Sequence[float], cmap: str = "viridis") -> dict[float, tuple]:
    """One colour per outer-parameter level, ordered (small values dark, large values bright)."""
    lv = sorted({float(x) for x in levels})
    cm = plt.get_cmap(cmap)
    if len(lv) == 1:
        return {lv[0]: cm(0.3)}
    return {x: cm(p) for x, p in zip(lv, np.linspace(0.0, 0.9, len(lv)))}


def log_ticks(ax, axis: str = "x") -> None:
    """Labelled ticks at 1, 2, 4, 6, 8 × 10^k on a log axis that spans little more than a decade
    (matplotlib would label only the powers of ten)."""
    lo, hi = (ax.get_xlim() if axis == "x" else ax.get_ylim())
    if lo <= 0 or hi / lo > 300:
        return
    ticks = [m * 10 ** k for k in range(int(math.floor(math.log10(lo))), int(math.ceil(math.log10(hi))) + 1)
             for m in (1, 2, 5) if lo <= m * 10 ** k <= hi]
    a = ax.xaxis if axis == "x" else ax.yaxis
    a.set_major_locator(matplotlib.ticker.FixedLocator(ticks))
    a.set_major_formatter(matplotlib.ticker.FixedFormatter([readable(t) for t in ticks]))
    a.set_minor_formatter(matplotlib.ticker.NullFormatter())


def _range_text(frame: RegionFrame, inner: str, outer: str, inner_unit: str, outer_unit: str) -> str:
    r = frame.region
    return (f"{frame.label}: {inner} ∈ [{readable(r.inner_range[0])}, {readable(r.inner_range[1])}] {inner_unit}, "
            f"{outer} ∈ [{readable(r.outer_range[0])}, {readable(r.outer_range[1])}] {outer_unit}")


# ============================================================================ 2-D grid: heat map
def _index_position(axis: np.ndarray, value: float, log: bool) -> float:
    """Fractional cell index of ``value`` on a sorted categorical axis (below the axis: its lower edge)."""
    if value < axis[0] * (1 - 1e-9) or (log and value <= 0):
        return -0.5
    if value > axis[-1] * (1 + 1e-9):
        return len(axis) - 0.5
    if len(axis) == 1:
        return 0.0
    scale = np.log10 if log else (lambda v: np.asarray(v, float))
    return float(np.interp(scale(value), scale(axis), np.arange(len(axis))))


def _frame(ax, xs, zs, frame: RegionFrame, logx: bool, logz: bool) -> None:
    r = frame.region
    x_lo, z_lo = r.inner_range[0], r.outer_range[0]
    x0 = _index_position(xs, x_lo, logx) - (0.5 if x_lo >= xs[0] * (1 - 1e-9) and (x_lo > 0 or not logx) else 0)
    x1 = _index_position(xs, r.inner_range[1], logx) + 0.5
    z0 = _index_position(zs, z_lo, logz) - (0.5 if z_lo >= zs[0] * (1 - 1e-9) and (z_lo > 0 or not logz) else 0)
    z1 = _index_position(zs, r.outer_range[1], logz) + 0.5
    x0, x1 = max(x0, -0.5), min(x1, len(xs) - 0.5)
    z0, z1 = max(z0, -0.5), min(z1, len(zs) - 0.5)
    inset = frame.inset
    xy, w, h = (x0 + inset, z0 + inset), x1 - x0 - 2 * inset, z1 - z0 - 2 * inset
    ax.add_patch(Rectangle(xy, w, h, fill=False, edgecolor="white", linewidth=5.5, zorder=5))
    ax.add_patch(Rectangle(xy, w, h, fill=False, edgecolor=frame.color, linewidth=3.0, linestyle=frame.style,
                           zorder=5.5))


def _grid_matrix(runs: pd.DataFrame, metric: str, inner: str, outer: str, ok_column: str | None,
                 shift: float):
    """Axes, values, violated-constraint and failed-run masks of the grid runs, [outer index, inner index]."""
    grid = runs[runs["stage"] == "grid"]
    xs, zs = np.sort(grid[inner].unique()), np.sort(grid[outer].unique())
    val = np.full((len(zs), len(xs)), np.nan)
    bad = np.zeros_like(val, dtype=bool)
    failed = np.zeros_like(val, dtype=bool)
    for _, r in grid.iterrows():
        i, j = int(np.searchsorted(zs, r[outer])), int(np.searchsorted(xs, r[inner]))
        if r["status"] != "ok":
            failed[i, j] = True
            continue
        val[i, j] = float(r[metric]) - shift
        if ok_column and ok_column in r and not bool(r[ok_column]):
            bad[i, j] = True
    return xs, zs, val, bad, failed


def _colour_norm(val: np.ndarray):
    """(shown values, norm, log?, signed?): a log colour scale over |value| where the values span decades."""
    finite = val[np.isfinite(val)]
    signed = bool((finite < 0).any())
    shown = np.abs(val) if signed else val.copy()
    if spans_decades(shown[np.isfinite(shown) & (shown > 0)]) and not (finite == 0).any():
        pos = shown[np.isfinite(shown) & (shown > 0)]
        return shown, mcolors.LogNorm(vmin=float(pos.min()), vmax=float(pos.max())), True, signed
    shown = val.copy()
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    if hi <= lo:
        lo, hi = lo - (abs(lo) or 1.0) * 0.5, hi + (abs(hi) or 1.0) * 0.5
    return shown, mcolors.Normalize(lo, hi), False, False


def cell_digits(val: np.ndarray, log: bool) -> int:
    """Significant digits that tell the cells apart: 3, more when the values differ little relative to
    their size (10.0078 next to 10.65 on a linear scale), at most 6."""
    finite = val[np.isfinite(val)]
    if log or finite.size < 2 or finite.max() == finite.min():
        return 3
    ratio = float(np.abs(finite).max() / (finite.max() - finite.min()))
    return int(min(6, 3 + max(0, math.ceil(math.log10(ratio)))))


def _annotate_cells(ax, val, shown, failed, bad, cmap, norm, missing_label: str, sig: int = 3) -> None:
    for i in range(val.shape[0]):
        for j in range(val.shape[1]):
            v = val[i, j]
            if failed[i, j]:
                txt, color = "run\nfailed", "black"
            elif not np.isfinite(v):
                txt, color = missing_label, "#444444"
            else:
                txt = readable(v, sig, strip=False)
                rgba = cmap(norm(shown[i, j]))
                lum = 0.299 * rgba[0] + 0.587 * rgba[1] + 0.114 * rgba[2]
                color = "black" if lum > 0.5 else "white"
            ax.text(j, i, txt, ha="center", va="center", fontsize=9, color=color, zorder=6,
                    fontweight="bold" if not np.isfinite(v) else "normal")
            if bad[i, j]:
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, hatch="///", linewidth=0,
                                       edgecolor=(1, 1, 1, 0.55), zorder=4))


def grid_heatmap(runs: pd.DataFrame, metric: str, path: str | Path, *, inner: str, outer: str,
                 inner_label: str, outer_label: str, inner_unit: str = "", outer_unit: str = "",
                 metric_unit: str = "", title: str = "", regions: Sequence[RegionFrame] = (),
                 thresholds: Sequence[Threshold] = (), ok_column: str | None = None, shift: float = 0.0,
                 shift_label: str = "", missing_label: str = "no value") -> Path:
    """Heat map of ``metric`` over the 2-D grid (stage "grid"): one cell per grid value, every cell
    annotated, a log colour scale only where the values span decades; missing values marked
    ``missing_label``; cells failing ``ok_column`` hatched; ``thresholds`` marked on the colour bar;
    ``regions`` framed. With ``shift`` the cells show ``metric − shift``."""
    xs, zs, val, bad, failed = _grid_matrix(runs, metric, inner, outer, ok_column, shift)
    shown, norm, log, signed = _colour_norm(val)
    fig, ax = plt.subplots(figsize=(PAGE_WIDTH, 5.6))
    cmap = plt.get_cmap("viridis").with_extremes(bad="#d9d9d9")
    ok = np.isfinite(shown) & ((shown > 0) if log else True)
    im = ax.imshow(np.ma.masked_where(~ok, shown), origin="lower", cmap=cmap, norm=norm, aspect="auto")
    _annotate_cells(ax, val, shown, failed, bad, cmap, norm, missing_label, cell_digits(val, log))
    ax.set_xticks(range(len(xs)), [readable(x, 3) for x in xs])
    ax.set_yticks(range(len(zs)), [readable(z, 3) for z in zs])
    ax.set_xlabel(f"{inner_label} (grid values)")
    ax.set_ylabel(f"{outer_label} (grid values)")
    ax.set_title(title or metric)
    cb = fig.colorbar(im, ax=ax, pad=0.02)
    name = shift_label or metric
    cb.set_label(f"{'|' + name + '|' if signed else name}{unit_suffix(metric_unit)}"
                 + (" (log scale)" if log else ""))
    handles = []
    for th in thresholds:
        if norm.vmin <= th.value <= norm.vmax:
            cb.ax.axhline(th.value, color=THRESH_COLOR, linewidth=2.5)
            where = "purple line on the colour bar"
        else:
            where = f"beyond the colour bar: every cell is {'below' if th.value > norm.vmax else 'above'} it"
        handles.append(Line2D([], [], color=THRESH_COLOR, linewidth=2.5, label=f"{th.label} ({where})"))
    if ok_column is not None and bad.any():
        handles.append(Patch(facecolor="#777777", edgecolor="white", hatch="///",
                             label="hatched: this metric's constraint is violated"))
    logx, logz = spans_decades(xs), spans_decades(zs)
    for fr in regions:
        _frame(ax, xs, zs, fr, logx, logz)
        handles.append(Line2D([], [], color=fr.color, linewidth=3, linestyle=fr.style,
                              label=_range_text(fr, inner, outer, inner_unit, outer_unit)))
    if signed:
        handles.append(Patch(facecolor="white", edgecolor="#999999",
                             label=f"colour: |{metric}| (the cells show the signed value)"))
    if np.isnan(val).any() and not failed.all():
        handles.append(Patch(facecolor="#d9d9d9", edgecolor="#999999", label=f"grey: {missing_label}"))
    if handles:
        ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=1, frameon=False)
    return save(fig, path)


# ============================================================================ 1-D: a line plot
def _set_scales(ax, x, y, xlog: bool | None, ylog: bool | None) -> tuple[bool, bool]:
    xlog = spans_decades(x) if xlog is None else xlog
    ylog = spans_decades(y) if ylog is None else ylog
    if xlog:
        ax.set_xscale("log")
    if ylog:
        ax.set_yscale("log")
    return xlog, ylog


def line_plot(runs: pd.DataFrame, param: str, metric: str, path: str | Path, *, param_label: str,
              metric_label: str, title: str = "", thresholds: Sequence[Threshold] = (),
              shade: tuple[float, float, str] | None = None, optimum: tuple[float, float, str] | None = None,
              ok_column: str | None = None, xlog: bool | None = None, ylog: bool | None = None) -> Path:
    """``metric`` against the one study parameter: the grid runs joined by a line, the other stages' runs
    as points, runs that violate the metric's constraint hollow, failed runs as crosses on the axis,
    ``thresholds`` as horizontal lines, ``shade`` (lo, hi, label) as a band, ``optimum`` (x, y, label)
    starred."""
    ok = runs[runs["status"] == "ok"].sort_values(param)
    fig, ax = plt.subplots(figsize=(PAGE_WIDTH, 4.4))
    grid = ok[ok["stage"] == "grid"]
    ax.plot(grid[param], grid[metric], "-o", color="tab:blue", markersize=6, zorder=3, label="grid runs")
    other = ok[ok["stage"] != "grid"]
    if len(other):
        ax.scatter(other[param], other[metric], s=22, color="tab:orange", zorder=4, label="runs of later stages")
    if ok_column is not None and ok_column in ok:
        bad = ok[~ok[ok_column].astype(bool)]
        if len(bad):
            ax.scatter(bad[param], bad[metric], s=70, facecolors="none", edgecolors="black", zorder=5,
                       label="violates the constraint on this metric")
    xlog, _ = _set_scales(ax, ok[param], ok[metric], xlog, ylog)
    for th in thresholds:
        ax.axhline(th.value, color=THRESH_COLOR, linestyle="--", linewidth=1.8, label=th.label, zorder=2)
    if shade is not None:
        ax.axvspan(max(shade[0], ok[param].min() if xlog and shade[0] <= 0 else shade[0]), shade[1],
                   color="tab:red", alpha=0.12, label=shade[2], zorder=1)
    if optimum is not None:
        ax.scatter([optimum[0]], [optimum[1]], marker="*", s=300, color=OPT_COLOR, edgecolors="black",
                   zorder=7, label=optimum[2])
    failed = runs[runs["status"] != "ok"]
    if len(failed):
        ax.scatter(failed[param], np.zeros(len(failed)), marker="x", s=60, color="black", zorder=6,
                   transform=ax.get_xaxis_transform(), clip_on=False, label=f"failed runs ({len(failed)})")
    ax.set_xlabel(param_label)
    ax.set_ylabel(metric_label)
    ax.set_title(title or metric)
    ax.grid(True, which="both", alpha=0.25)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, frameon=False)
    return save(fig, path)


def scatter_panels(runs: pd.DataFrame, params: Sequence[str], metric: str, path: str | Path, *,
                   param_labels: Mapping[str, str], metric_label: str, title: str = "",
                   thresholds: Sequence[Threshold] = ()) -> Path:
    """``metric`` of the grid runs against each of three or more parameters, one panel each (a heat
    map would hide the other parameters)."""
    ok = runs[(runs["status"] == "ok") & (runs["stage"] == "grid")]
    n = len(params)
    fig, axes = plt.subplots(1, n, figsize=(PAGE_WIDTH, min(3.4, PAGE_WIDTH / n + 0.8)), sharey=True, squeeze=False)
    for ax, p in zip(axes[0], params):
        ax.scatter(ok[p], ok[metric], s=18, alpha=0.7)
        _set_scales(ax, ok[p], ok[metric], None, None)
        for th in thresholds:
            ax.axhline(th.value, color=THRESH_COLOR, linestyle="--", linewidth=1.5,
                       label=th.label if ax is axes[0][0] else None)
        ax.set_xlabel(param_labels.get(p, p))
        ax.grid(True, which="both", alpha=0.25)
    axes[0][0].set_ylabel(metric_label)
    if thresholds:
        axes[0][0].legend(loc="best", frameon=False)
    fig.suptitle(title or metric)
    fig.tight_layout()
    return save(fig, path)


# ============================================================================ search points
def search_points(runs: pd.DataFrame, levels: Sequence[dict], inner: str, outer: str | None,
                  inner_range: tuple[float, float] | None, stages: Sequence[str]) -> pd.DataFrame:
    """The runs the search made: at its outer levels, inner within the region (grid runs that the
    search reused count too)."""
    pts = runs[(runs["status"] == "ok") & runs["stage"].isin(list(stages) + ["grid"])]
    if outer is not None:
        outs = {float(lv["outer"]) for lv in levels if lv.get("outer") is not None}
        pts = pts[pts[outer].astype(float).isin(outs)]
    else:
        pts = pts[pts["stage"].isin(list(stages))]
    if inner_range is not None:
        lo, hi = inner_range
        pts = pts[(pts[inner] >= lo * (1 - 1e-12)) & (pts[inner] <= hi * (1 + 1e-12))]
    return pts


def _level_groups(pts: pd.DataFrame, levels: Sequence[dict], outer: str | None):
    """(outer value or None, its points, colour, marker) for each outer level, largest first."""
    if outer is None:
        return [(None, pts.sort_values(pts.columns[0]), "tab:blue", "o")]
    lv_values = sorted({float(lv["outer"]) for lv in levels if lv.get("outer") is not None}, reverse=True)
    cols = level_colors(lv_values)
    return [(z, pts[np.isclose(pts[outer], z, rtol=1e-12)], cols[z], MARKERS[k % len(MARKERS)])
            for k, z in enumerate(lv_values)]


def _draw_fits(axes, fits, z, x_lo, x_hi, color, log: bool, label: str | None = None) -> None:
    """The fitted polynomial of level ``z`` ("all" when None) over its x range; ``label`` on the first axis."""
    fit = (fits or {}).get("all" if z is None else f"{z:.10g}")
    if not fit or not fit.get("coefficients"):
        return
    lo, hi = fit.get("x_range", [x_lo, x_hi])
    xx = np.geomspace(lo, hi, 400) if log and lo > 0 else np.linspace(lo, hi, 400)
    yy = np.polynomial.polynomial.polyval(xx, fit["coefficients"])
    for k, a in enumerate(axes):
        a.plot(xx, yy, color=color, linewidth=1.0, alpha=0.7, zorder=2, label=label if k == 0 else None)


def _zoom_panel(az, pts, inner, metric, center, zoom, thresholds, reference, inner_label, metric_label):
    """The right panel of :func:`search_metric`: the runs within ±``zoom`` of ``center``."""
    lo, hi = center * (1 - zoom), center * (1 + zoom)
    near = pts[(pts[inner] >= lo) & (pts[inner] <= hi)]
    az.set_xlim(lo, hi)
    ys = [float(v) for v in near[metric] if np.isfinite(v)] + [th.value for th in thresholds]
    if reference is not None:
        ys.extend(list(reference(np.array([lo, hi]))))
    if ys:
        span = max(ys) - min(ys) or abs(max(ys)) * 0.1 or 1.0
        az.set_ylim(min(ys) - 0.08 * span, max(ys) + 0.08 * span)
    az.set_xlabel(f"{inner_label}, ±{zoom:.0%} of the optimum")
    az.set_ylabel(metric_label)
    az.set_title(f"zoom: {len(near)} points near the boundary", fontsize=10)
    az.grid(True, alpha=0.25)
    az.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(4))
    az.xaxis.set_major_formatter(readable_formatter(4))
    az.ticklabel_format(axis="y", style="sci", scilimits=(-3, 4), useMathText=True)


def _optimum_row(pts, inner, outer, optimum):
    if optimum is None:
        return None
    sel = np.isclose(pts[inner], optimum[inner], rtol=1e-12)
    if outer is not None:
        sel &= np.isclose(pts[outer], optimum[outer], rtol=1e-12)
    return pts[sel].iloc[0] if sel.any() else None


def _main_axes(ax, values, thresholds: Sequence[Threshold], xlog: bool, inner_label: str, metric_label: str,
               title: str, with_zero: bool) -> None:
    """Scales, limits and labels of the left panel of :func:`search_metric`; ``with_zero`` keeps y = 0 in
    view (fitted polynomials may change sign, which a log axis or a tight range would hide)."""
    if xlog:
        ax.set_xscale("log")
    vals = np.asarray(values, float)
    vals = vals[np.isfinite(vals)]
    bounds = [th.value for th in thresholds]
    if vals.size:
        top = max([float(vals.max())] + bounds + ([0.0] if with_zero else []))
        bottom = min([float(vals.min())] + bounds + ([0.0] if with_zero else []))
        pad = (top - bottom) or abs(top) or 1.0
        ax.set_ylim(bottom - 0.08 * pad, top + 0.12 * pad)
    if with_zero:
        ax.axhline(0.0, color="gray", linewidth=0.6)
    ax.ticklabel_format(axis="y", style="sci", scilimits=(-3, 4), useMathText=True)
    if xlog:
        log_ticks(ax, "x")
    ax.set_xlabel(f"{inner_label}{' (log)' if xlog else ''}")
    ax.set_ylabel(metric_label)
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="both", alpha=0.25)


def search_metric(runs: pd.DataFrame, levels: Sequence[dict], fits: Mapping[str, dict] | None, metric: str,
                  path: str | Path, *, inner: str, outer: str | None, inner_label: str, metric_label: str,
                  inner_unit: str = "", outer_unit: str = "", thresholds: Sequence[Threshold] = (),
                  optimum: Mapping[str, float] | None = None, markers: Sequence[tuple[float, str]] = (),
                  inner_range=None, reference: Callable[[np.ndarray], np.ndarray] | None = None,
                  reference_label: str = "", title: str = "", stages: Sequence[str] = ("search",),
                  zoom: float = 0.05, xlog: bool | None = None, fit_label: str = "fitted polynomials",
                  ) -> Path:
    """``metric`` of the search points against the inner parameter, one colour per outer level, the
    regression ``fits`` per level (coefficients in increasing order), ``thresholds``, the optimum and
    vertical ``markers`` (x, label); right panel: the same within ±``zoom`` of the optimum."""
    pts = search_points(runs, levels, inner, outer, inner_range, stages)
    fig, (ax, az) = plt.subplots(1, 2, figsize=(PAGE_WIDTH, 3.9), gridspec_kw={"width_ratios": [1.35, 1]})
    xlog = spans_decades(pts[inner]) if xlog is None else xlog
    for z, g, color, mk in _level_groups(pts, levels, outer):
        g = g.sort_values(inner)
        for a in (ax, az):
            a.scatter(g[inner], g[metric], s=34 if a is ax else 46, marker=mk, color=color, alpha=0.55,
                      edgecolors="none", zorder=3,
                      label=(f"{outer} = {fmt(z, 6)}" if z is not None else "search runs") if a is ax else None)
        if len(g):
            _draw_fits((ax, az), fits, z, g[inner].min(), g[inner].max(), color, xlog,
                       fit_label if z is None else None)
    if reference is not None and len(pts):
        xx = np.geomspace(pts[inner].min(), pts[inner].max(), 400)
        for a in (ax, az):
            a.plot(xx, reference(xx), color="black", linestyle=":", linewidth=1.4, zorder=4,
                   label=reference_label if a is ax else None)
    for th in thresholds:
        for a in (ax, az):
            a.axhline(th.value, color=THRESH_COLOR, linewidth=2, zorder=1, label=th.label if a is ax else None)
    opt_row = _optimum_row(pts, inner, outer, optimum)
    if opt_row is not None:
        where = f"{inner} = {fmt(optimum[inner], 7)} {inner_unit}" + (
            f", {outer} = {fmt(optimum[outer], 5)} {outer_unit}" if outer is not None else "")
        for a in (ax, az):
            a.scatter([opt_row[inner]], [opt_row[metric]], marker="*", s=320, color=OPT_COLOR, edgecolors="black",
                      linewidths=0.8, zorder=7, label=f"optimum {where}" if a is ax else None)
    for x, label in markers:
        for a in (ax, az):
            a.axvline(x, color=MARK_COLOR, linestyle="--", linewidth=1.2, zorder=1, label=label if a is ax else None)
    with_zero = bool(fits) or not len(pts) or bool((pts[metric] <= 0).any())
    _main_axes(ax, pts[metric], thresholds, xlog, inner_label, metric_label,
               title or f"{metric} of the search points", with_zero)
    center = optimum[inner] if optimum is not None else (float(np.median(pts[inner])) if len(pts) else 1.0)
    _zoom_panel(az, pts, inner, metric, center, zoom, thresholds, reference, f"{inner}{unit_suffix(inner_unit)}",
                metric_label)
    handles, labels = ax.get_legend_handles_labels()
    fitted = f"; thin lines: {fit_label} per level" if fits else ""
    legend_title = (f"search levels of {outer}{unit_suffix(outer_unit)} (one colour and marker each{fitted})"
                    if outer is not None else None)
    fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=3, frameon=False,
               title=legend_title, title_fontsize=8.5, fontsize=8)
    fig.tight_layout()
    return save(fig, path)


# ============================================================================ search path
def _path_limits(searches) -> tuple[float, float]:
    all_c = [float(lv["inner"]) for _, levels, _, _ in searches for lv in levels if lv.get("inner") is not None]
    return (min(all_c), max(all_c)) if all_c else (1.0, 1.0)


def search_path(searches: Sequence[tuple[str, Sequence[dict], Mapping[str, float] | None, str]], path: str | Path,
                *, inner: str, outer: str, inner_label: str, outer_label: str, inner_unit: str = "",
                outer_unit: str = "", markers: Sequence[tuple[float, float, str]] = (),
                reference: tuple[float, str] | None = None,
                annotations: Sequence[tuple[float, float, str]] = (), xlog: bool | None = None,
                inner_range: tuple[float, float] | None = None) -> Path:
    """The outer levels of each search (``(label, levels, optimum, color)``) against the smallest
    feasible inner value found there; the stop point starred; ``markers`` (outer, inner, label) as crosses;
    ``annotations`` (outer, inner, text). ``inner_range``: the region the search bisected, drawn as two
    dashed lines; a level without a feasible value is drawn above its top (nothing up to it was feasible),
    and when every level found nearly the same value the axis shows the whole region, so the figure says
    where in it they lie (at a bound, say)."""
    fig, ax = plt.subplots(figsize=(PAGE_WIDTH, 4.6))
    lo_c, hi_c = _path_limits(searches)
    none_found = any(lv.get("inner") is None for _, levels, _, _ in searches for lv in levels)
    if inner_range is not None:
        r_lo, r_hi = (float(v) for v in inner_range)
        if none_found or (hi_c - lo_c) < 0.05 * (r_hi - r_lo):
            lo_c, hi_c = min(lo_c, r_lo), max(hi_c, r_hi)
        for k, v in enumerate((r_lo, r_hi)):
            if lo_c <= v <= hi_c:
                ax.axhline(v, color="gray", linestyle="--", linewidth=1.0, zorder=1,
                           label=f"the region's bounds of {inner}: {fmt(r_lo, 4)}, {fmt(r_hi, 4)} {inner_unit}"
                           if k == 0 or not lo_c <= r_lo <= hi_c else None)
    if hi_c <= lo_c:           # one value: a band of ±10 % around it
        lo_c, hi_c = lo_c - 0.1 * abs(lo_c or 1.0), hi_c + 0.1 * abs(hi_c or 1.0)
    top = hi_c + 0.06 * (hi_c - lo_c)          # where "none feasible up to the top" is drawn
    all_z = []
    for n, (label, levels, opt, color) in enumerate(searches):
        zs = np.array([float(lv["outer"]) for lv in levels])
        all_z += list(zs)
        cs = np.array([float(lv["inner"]) if lv.get("inner") is not None else np.nan for lv in levels])
        ok = np.isfinite(cs)
        ax.plot(zs[ok], cs[ok], "-" + MARKERS[n % len(MARKERS)], color=color, alpha=0.8, markersize=7 - 1.5 * n,
                linewidth=1.8 - 0.6 * n,
                label=f"{label}: {len(levels)} levels, {sum(int(lv.get('evaluations', 0)) for lv in levels)} runs")
        if (~ok).any():
            where = (f"up to the region's top {fmt(inner_range[1], 4)} {inner_unit}" if inner_range is not None
                     else "in the region")
            ax.scatter(zs[~ok], np.full((~ok).sum(), top), marker="^", s=70, color=color, edgecolors="black",
                       zorder=6, label=f"{label}: no feasible {inner} {where} (drawn above it)")
        if len(zs):
            ax.annotate(f"start ({label})", (zs[0], cs[0] if ok[0] else top), textcoords="offset points",
                        xytext=(0, 10 + 14 * n), ha="center", fontsize=8.5, color=color)
        if opt is not None:
            ax.scatter([opt[outer]], [opt[inner]], marker="*", s=380 - 120 * n, color=color, edgecolors="black",
                       zorder=6, label=f"{label}: stop point {inner} = {fmt(opt[inner], 7)} {inner_unit}, "
                                       f"{outer} = {fmt(opt[outer], 5)} {outer_unit}")
    for z, c, label in markers:
        ax.scatter([z], [c], marker="x", s=90, linewidths=2.2, color=MARK_COLOR, zorder=7, label=label)
    if reference is not None:
        ax.axhline(reference[0], color=THRESH_COLOR, linestyle=":", linewidth=1.5, label=reference[1], zorder=1)
    for z, c, text in annotations:
        ax.annotate(text, (z, c), textcoords="offset points", xytext=(-10, 0), ha="right", va="center",
                    fontsize=8.5, arrowprops={"arrowstyle": "-", "color": "gray", "lw": 0.6})
    xlog = spans_decades(all_z) if xlog is None else xlog
    if xlog:
        ax.set_xscale("log")
    ax.yaxis.set_major_formatter(readable_formatter())
    ax.set_ylim(lo_c - 0.12 * (hi_c - lo_c), hi_c + 0.16 * (hi_c - lo_c))
    ax.grid(True, which="both", alpha=0.25)
    ax.set_xlabel(f"{outer_label}{' (log)' if xlog else ''}; halved from the region's top, right to left")
    ax.set_ylabel(f"smallest feasible {lower_first(inner_label)}")
    ax.set_title(f"Nested binary search: the {outer} levels and the smallest feasible {inner} at each")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=1, frameon=False)
    return save(fig, path)


# ============================================================================ regression
def regression_plot(points: pd.DataFrame, fits: Mapping[str, dict], x: str, metric: str, by: str | None,
                    path: str | Path, *, x_label: str, metric_label: str, by_unit: str = "", title: str = "",
                    degree: int = 3) -> Path:
    """The points a regression was fitted to (one colour per ``by`` level) and its fitted polynomials."""
    fig, ax = plt.subplots(figsize=(PAGE_WIDTH, 4.4))
    ok = points[points["status"] == "ok"]
    xlog = spans_decades(ok[x])
    groups = [(None, ok)] if by is None else sorted(ok.groupby(by), key=lambda g: -float(g[0]))
    cols = level_colors([float(z) for z, _ in groups]) if by is not None else {}
    for k, (z, g) in enumerate(groups):
        color = cols.get(float(z), "tab:blue") if z is not None else "tab:blue"
        ax.scatter(g[x], g[metric], s=26, marker=MARKERS[k % len(MARKERS)], color=color, alpha=0.6,
                   label=f"{by} = {fmt(z, 6)} {by_unit}".rstrip() if by is not None else "fitted runs")
        _draw_fits([ax], fits, None if z is None else float(z), g[x].min(), g[x].max(), color, xlog)
    if xlog:
        ax.set_xscale("log")
    ax.set_xlabel(x_label)
    ax.set_ylabel(metric_label)
    ax.set_title(title or f"{metric}: degree-{degree} fit over {x}")
    ax.grid(True, which="both", alpha=0.25)
    ax.ticklabel_format(axis="y", style="sci", scilimits=(-3, 4), useMathText=True)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=3, frameon=False,
              title=f"points and degree-{degree} fits", title_fontsize=9)
    return save(fig, path)


# ============================================================================ sensitivity
_INDEX_KEYS = ("mu_star", "sigma", "mu", "S1", "ST")


def _frame_table(obj: pd.DataFrame) -> pd.DataFrame | None:
    cols = [c for c in obj.columns if c in _INDEX_KEYS or str(c).endswith("_conf")]
    if not any(c in _INDEX_KEYS for c in cols):
        return None
    df = obj.copy()
    for key in ("parameter", "name", "names"):
        if key in df.columns:
            df = df.set_index(key)
            break
    return df[cols].apply(pd.to_numeric, errors="coerce")


def _salib_table(obj: Mapping) -> pd.DataFrame | None:
    names = obj.get("names") or obj.get("parameters")
    if not (isinstance(names, (list, tuple)) and any(k in obj for k in _INDEX_KEYS)):
        return None
    data = {k: pd.to_numeric(pd.Series(list(v)), errors="coerce").to_numpy() for k, v in obj.items()
            if (k in _INDEX_KEYS or str(k).endswith("_conf")) and hasattr(v, "__len__")
            and len(v) == len(names) and np.ndim(v) == 1}
    return pd.DataFrame(data, index=list(names)) if data else None


def index_tables(obj, trail=()) -> list[tuple[tuple, pd.DataFrame]]:
    """(path, parameter × index table) for every sensitivity index table found in ``obj``: a
    DataFrame with index columns, a SALib-like dict {names, S1, ST, ...}, or {parameter: {S1: ..}}."""
    if isinstance(obj, pd.DataFrame):
        df = _frame_table(obj)
        return [(trail, df)] if df is not None else []
    if not isinstance(obj, Mapping):
        return []
    df = _salib_table(obj)
    if df is not None:
        return [(trail, df)]
    vals = list(obj.values())
    if vals and all(isinstance(v, Mapping) for v in vals) and all(any(k in v for k in _INDEX_KEYS) for v in vals):
        df = pd.DataFrame({str(p): {k: v.get(k) for k in v if k in _INDEX_KEYS or str(k).endswith("_conf")}
                           for p, v in obj.items()}).T
        return [(trail, df.apply(pd.to_numeric, errors="coerce"))]
    found = []
    for k, v in obj.items():
        if len(trail) < 5:
            found += index_tables(v, trail + (str(k),))
    return found


def _bars(a, df: pd.DataFrame, method: str) -> None:
    if method == "morris":
        main = "mu_star" if "mu_star" in df.columns else df.columns[0]
        d = df.sort_values(main)
        y = np.arange(len(d))
        a.barh(y - 0.2, d[main], height=0.4, color="tab:blue", label="μ* (mean |elementary effect|)",
               xerr=d.get("mu_star_conf"), error_kw={"elinewidth": 0.8})
        if "sigma" in d.columns:
            a.barh(y + 0.2, d["sigma"], height=0.4, color="tab:orange", label="σ (interaction/non-linearity)")
    else:
        d = df.sort_values("ST" if "ST" in df.columns else "S1")
        y = np.arange(len(d))
        for col, dy, color, label in (("S1", -0.2, "tab:blue", "S1 (first order)"),
                                      ("ST", 0.2, "tab:orange", "ST (total)")):
            if col in d.columns:
                a.barh(y + dy, d[col], height=0.4, color=color, label=label, xerr=d.get(f"{col}_conf"),
                       error_kw={"elinewidth": 0.8})
    a.set_yticks(y, [str(i) for i in d.index])
    a.grid(True, axis="x", alpha=0.3)
    a.set_xlabel("index [-]" if method == "sobol" else "elementary effect [output unit per range]")


def _by_method(sensitivity) -> dict[str, list[tuple[str, pd.DataFrame]]]:
    seen, by_method = set(), {}
    for trail, df in index_tables(sensitivity):
        key = tuple(t for t in trail if t != "summary")
        if key in seen or df.empty:
            continue
        seen.add(key)
        method = "sobol" if ("S1" in df.columns or "ST" in df.columns) else "morris"
        label = " / ".join(k for k in key if k.lower() not in ("morris", "sobol", "indices")) or method
        by_method.setdefault(method, []).append((label, df))
    return by_method


def sensitivity_figures(sensitivity, outdir: str | Path) -> list[Path]:
    """Bar charts of every sensitivity index table found in ``sensitivity`` (Morris μ*/σ, Sobol
    S1/ST), one PNG per method, one panel per output. Returns [] when nothing is recognised."""
    paths = []
    for method, items in _by_method(sensitivity).items():
        items = items[:12]
        ncol = min(3, len(items))
        nrow = math.ceil(len(items) / ncol)
        nparam = max(len(df) for _, df in items)
        fig, axes = plt.subplots(nrow, ncol, figsize=(5.2 * ncol, max(2.6, 0.28 * nparam + 1.2) * nrow),
                                 squeeze=False)
        for a, (label, df) in zip(axes.ravel(), items):
            _bars(a, df, method)
            a.set_title(label)
        for a in axes.ravel()[len(items):]:
            a.set_visible(False)
        h, lab = axes.ravel()[0].get_legend_handles_labels()
        fig.legend(h, lab, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=2, frameon=False)
        fig.suptitle(f"Global sensitivity: {'Morris screening' if method == 'morris' else 'Sobol indices'}")
        fig.tight_layout()
        paths.append(save(fig, Path(outdir) / f"sensitivity_{method}.png"))
    return paths
