"""The figures of a study: equivalents of the paper's Figures 5-13 and a few more.

Every function takes the pieces of a :class:`fmusa.sweep.SweepResult` it needs (the runs table, the
regions, the search levels, ...) plus a target path, writes one PNG with matplotlib's Agg backend and
returns the path. No function runs the FMU except :func:`time_series`'s caller, which hands in the
sampled trajectory.

Conventions: the study's units on every axis, log axes where values span decades, thresholds as
horizontal lines, the automatic region of interest framed solid and the paper's hand-picked region
dashed.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Callable, Mapping, Sequence

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402,F401
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib import colors as mcolors  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402
from matplotlib.patches import Patch, Rectangle  # noqa: E402
from fmusa.format import fmt

__all__ = [
    "fmt", "grid_heatmap", "search_metric", "search_t_eq", "search_path", "time_series",
    "ramp_time", "sensitivity_figures", "level_colors",
]

DPI = 130
AUTO_COLOR = "#d62728"      # automatic region of interest: solid red
PAPER_COLOR = "#1f1fff"     # the paper's region (the paper frames its region in blue): dashed
OPT_COLOR = "#d62728"
PAPER_OPT_COLOR = "black"
THRESH_COLOR = "#7b2cbf"    # the paper draws its thresholds in purple

plt.rcParams.update({
    "font.size": 10,
    "axes.titlesize": 11,
    "axes.labelsize": 10,
    "legend.fontsize": 8.5,
    "xtick.labelsize": 9,
    "ytick.labelsize": 9,
    "axes.grid": False,
})


# ============================================================================ formatting


def _unit(u: str) -> str:
    return f" [{u}]" if u else ""


def _save(fig, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return path


def level_colors(levels: Sequence[float], cmap: str = "viridis") -> dict[float, tuple]:
    """One colour per outer-parameter level, ordered on a log scale (small d dark, large d bright)."""
    lv = sorted({float(x) for x in levels})
    cm = plt.get_cmap(cmap)
    if len(lv) == 1:
        return {lv[0]: cm(0.3)}
    pos = np.linspace(0.0, 0.9, len(lv))
    return {x: cm(p) for x, p in zip(lv, pos)}


_MARKERS = ["o", "s", "^", "D", "v", "P", "X", "<", ">", "h", "p", "*"]


def _log_ticks(ax, axis: str = "x") -> None:
    """Labelled ticks at 1, 2, 4, 6, 8 × 10^k within the current limits of a log axis that spans little
    more than a decade (matplotlib would label only the powers of ten)."""
    lo, hi = (ax.get_xlim() if axis == "x" else ax.get_ylim())
    if lo <= 0 or hi / lo > 300:
        return
    ticks = [m * 10 ** k for k in range(int(math.floor(math.log10(lo))), int(math.ceil(math.log10(hi))) + 1)
             for m in (1, 2, 4, 6, 8) if lo <= m * 10 ** k <= hi]
    a = ax.xaxis if axis == "x" else ax.yaxis
    a.set_major_locator(matplotlib.ticker.FixedLocator(ticks))
    a.set_major_formatter(matplotlib.ticker.FixedFormatter([fmt(t) for t in ticks]))
    a.set_minor_formatter(matplotlib.ticker.NullFormatter())


# ============================================================================ Figures 5-9: grid heat maps
def _index_position(axis: np.ndarray, value: float) -> float:
    """Fractional cell index of ``value`` on a sorted, log-spaced categorical axis (0 or below the axis:
    the lower edge)."""
    if value <= 0 or value < axis[0] * (1 - 1e-9):
        return -0.5
    if value > axis[-1] * (1 + 1e-9):
        return len(axis) - 0.5
    return float(np.interp(math.log10(value), np.log10(axis), np.arange(len(axis))))


def _frame(ax, xs, zs, x_range, z_range, color, style, inset, label):
    x0 = _index_position(xs, x_range[0]) - (0.5 if x_range[0] > 0 and x_range[0] >= xs[0] * (1 - 1e-9) else 0)
    x1 = _index_position(xs, x_range[1]) + 0.5
    z0 = _index_position(zs, z_range[0]) - (0.5 if z_range[0] > 0 and z_range[0] >= zs[0] * (1 - 1e-9) else 0)
    z1 = _index_position(zs, z_range[1]) + 0.5
    x0, x1 = max(x0, -0.5), min(x1, len(xs) - 0.5)
    z0, z1 = max(z0, -0.5), min(z1, len(zs) - 0.5)
    xy, w, h = (x0 + inset, z0 + inset), x1 - x0 - 2 * inset, z1 - z0 - 2 * inset
    ax.add_patch(Rectangle(xy, w, h, fill=False, edgecolor="white", linewidth=5.5, zorder=5))
    rect = Rectangle(xy, w, h, fill=False, edgecolor=color, linewidth=3.0, linestyle=style, zorder=5.5,
                     label=label)
    ax.add_patch(rect)
    return rect


def grid_heatmap(runs: pd.DataFrame, metric: str, path: str | Path, *, inner: str = "c", outer: str = "d",
                 inner_unit: str = "N/m", outer_unit: str = "N·s/m", metric_unit: str = "",
                 title: str = "", region=None, paper_region=None, threshold: float | None = None,
                 ok_column: str | None = None, shift: float = 0.0, shift_label: str = "",
                 missing_label: str = "no rest") -> Path:
    """Heat map of ``metric`` over the grid (stage "grid"): categorical log-spaced axes, log colour
    scale, every cell annotated; NaN cells marked ``missing_label``; the automatic region framed
    solid, the paper's dashed; cells failing ``ok_column`` hatched and ``threshold`` marked on the
    colour bar. With ``shift`` the cells show ``metric − shift`` (e.g. t_eq − t_ramp)."""
    grid = runs[runs["stage"] == "grid"]
    xs = np.sort(grid[inner].unique())
    zs = np.sort(grid[outer].unique())
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
    signed = bool((val[np.isfinite(val)] < 0).any())
    shown = np.abs(val) if signed else val.copy()     # a signed metric is coloured by its magnitude
    positive = shown[np.isfinite(shown) & (shown > 0)]
    fig, ax = plt.subplots(figsize=(8.6, 6.4))
    cmap = plt.get_cmap("viridis").with_extremes(bad="#d9d9d9")
    if positive.size:
        vmin, vmax = float(positive.min()), float(positive.max())
        if vmax <= vmin:
            vmin, vmax = vmin / 2, vmax * 2
        norm = mcolors.LogNorm(vmin=vmin, vmax=vmax)
    else:
        norm = mcolors.Normalize(0, 1)
    masked = np.ma.masked_where(~(np.isfinite(shown) & (shown > 0)), shown)
    im = ax.imshow(masked, origin="lower", cmap=cmap, norm=norm, aspect="auto")
    for i in range(len(zs)):
        for j in range(len(xs)):
            v = val[i, j]
            if failed[i, j]:
                txt, color = "run\nfailed", "black"
            elif not np.isfinite(v):
                txt, color = missing_label, "#444444"
            else:
                txt = fmt(v, 3, strip=False, plain_min=1.0)
                rgba = cmap(norm(abs(v))) if abs(v) > 0 else (0.85, 0.85, 0.85, 1)
                lum = 0.299 * rgba[0] + 0.587 * rgba[1] + 0.114 * rgba[2]
                color = "black" if lum > 0.5 else "white"
            ax.text(j, i, txt, ha="center", va="center", fontsize=9, color=color, zorder=6,
                    fontweight="bold" if not np.isfinite(v) else "normal")
            if bad[i, j]:
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, hatch="///", linewidth=0,
                                       edgecolor=(1, 1, 1, 0.55), zorder=4))
    ax.set_xticks(range(len(xs)), [fmt(x, strip=False) for x in xs])
    ax.set_yticks(range(len(zs)), [fmt(z, strip=False) for z in zs])
    ax.set_xlabel(f"stiffness {inner}{_unit(inner_unit)} (grid values, log-spaced)")
    ax.set_ylabel(f"damping {outer}{_unit(outer_unit)} (grid values, log-spaced)")
    ax.set_title(title or metric)
    cb = fig.colorbar(im, ax=ax, pad=0.02)
    name = shift_label or metric
    cb.set_label(f"{'|' + name + '|' if signed else name}{_unit(metric_unit)} (log scale)")
    handles = []
    if threshold is not None and positive.size:
        if norm.vmin <= threshold <= norm.vmax:
            cb.ax.axhline(threshold, color=THRESH_COLOR, linewidth=2.5)
        handles.append(Line2D([], [], color=THRESH_COLOR, linewidth=2.5,
                              label=f"threshold {fmt(threshold)} {metric_unit} (purple line on the colour bar)"))
    if ok_column is not None and bad.any():
        handles.append(Patch(facecolor="#777777", edgecolor="white", hatch="///",
                             label="hatched: this metric's constraint is violated"))
    if region is not None:
        _frame(ax, xs, zs, region.inner_range, region.outer_range, AUTO_COLOR, "-", 0.0, None)
        handles.append(Line2D([], [], color=AUTO_COLOR, linewidth=3,
                              label=f"automatic region: {inner} ∈ [{fmt(region.inner_range[0])}, "
                                    f"{fmt(region.inner_range[1])}] {inner_unit}, {outer} ∈ "
                                    f"[{fmt(region.outer_range[0])}, {fmt(region.outer_range[1])}] {outer_unit}"))
    if paper_region is not None:
        _frame(ax, xs, zs, paper_region.inner_range, paper_region.outer_range, PAPER_COLOR, "--", 0.07, None)
        handles.append(Line2D([], [], color=PAPER_COLOR, linewidth=3, linestyle="--",
                              label=f"paper's region (by hand): {inner} ∈ [{fmt(paper_region.inner_range[0])}, "
                                    f"{fmt(paper_region.inner_range[1])}] {inner_unit}, {outer} ∈ "
                                    f"[{fmt(paper_region.outer_range[0])}, {fmt(paper_region.outer_range[1])}] "
                                    f"{outer_unit}"))
    if signed:
        handles.append(Patch(facecolor="white", edgecolor="#999999",
                             label=f"colour: |{metric}| (the cells show the signed value)"))
    if np.isnan(val).any() and not failed.all():
        handles.append(Patch(facecolor="#d9d9d9", edgecolor="#999999", label=f"grey: {missing_label}"))
    if handles:
        ax.legend(handles=handles, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=1, frameon=False)
    return _save(fig, path)


# ============================================================================ Figures 10-11: search points
def _search_points(runs: pd.DataFrame, levels: Sequence[dict], inner: str, outer: str,
                   inner_range: tuple[float, float] | None, stages: Sequence[str]) -> pd.DataFrame:
    """The runs the search made: at its outer levels, inner within the region (grid runs that the
    search reused count too)."""
    outs = {float(lv["outer"]) for lv in levels}
    pts = runs[runs[outer].astype(float).isin(outs) & (runs["status"] == "ok")]
    pts = pts[pts["stage"].isin(list(stages) + ["grid"])]
    if inner_range is not None:
        lo, hi = inner_range
        pts = pts[(pts[inner] >= lo * (1 - 1e-12)) & (pts[inner] <= hi * (1 + 1e-12))]
    return pts


def search_metric(runs: pd.DataFrame, levels: Sequence[dict], fits: Mapping[str, dict] | None, metric: str,
                  path: str | Path, *, inner: str = "c", outer: str = "d", inner_unit: str = "N/m",
                  outer_unit: str = "N·s/m", metric_unit: str = "", threshold: float | None = None,
                  threshold_label: str = "", optimum: Mapping[str, float] | None = None,
                  paper_optimum: Mapping[str, float] | None = None, inner_range=None,
                  reference: Callable[[np.ndarray], np.ndarray] | None = None, reference_label: str = "",
                  title: str = "", stages: Sequence[str] = ("search",), zoom: float = 0.05) -> Path:
    """``metric`` of the search points against the inner parameter (log x), one colour per outer
    level, the cubic fits per level (coefficients in increasing order), the threshold, the optimum;
    right panel: the same within ±``zoom`` of the optimum."""
    pts = _search_points(runs, levels, inner, outer, inner_range, stages)
    lv_values = sorted({float(lv["outer"]) for lv in levels}, reverse=True)
    cols = level_colors(lv_values)
    fig, (ax, az) = plt.subplots(1, 2, figsize=(13.5, 5.6), gridspec_kw={"width_ratios": [1.35, 1]})
    opt_row = None
    if optimum is not None:
        m = pts[np.isclose(pts[inner], optimum[inner], rtol=1e-12) & np.isclose(pts[outer], optimum[outer],
                                                                                 rtol=1e-12)]
        if len(m):
            opt_row = m.iloc[0]
    for k, z in enumerate(lv_values):
        g = pts[np.isclose(pts[outer], z, rtol=1e-12)].sort_values(inner)
        mk = _MARKERS[k % len(_MARKERS)]
        for a in (ax, az):
            a.scatter(g[inner], g[metric], s=34 if a is ax else 46, marker=mk, color=cols[z], alpha=0.55,
                      edgecolors="none", zorder=3, label=f"{outer} = {fmt(z, 6)}" if a is ax else None)
        fit = (fits or {}).get(f"{z:.10g}")
        if fit and fit.get("coefficients"):
            lo, hi = fit.get("x_range", [g[inner].min(), g[inner].max()])
            xx = np.geomspace(lo, hi, 400)
            yy = np.polynomial.polynomial.polyval(xx, fit["coefficients"])
            for a in (ax, az):
                a.plot(xx, yy, color=cols[z], linewidth=1.0, alpha=0.7, zorder=2)
    if reference is not None and len(pts):
        xx = np.geomspace(pts[inner].min(), pts[inner].max(), 400)
        for a in (ax, az):
            a.plot(xx, reference(xx), color="black", linestyle=":", linewidth=1.4, zorder=4,
                   label=reference_label if a is ax else None)
    if threshold is not None:
        for a in (ax, az):
            a.axhline(threshold, color=THRESH_COLOR, linewidth=2, zorder=1,
                      label=(threshold_label or f"threshold {fmt(threshold)}{_unit(metric_unit)}") if a is ax
                      else None)
    if opt_row is not None:
        for a in (ax, az):
            a.scatter([opt_row[inner]], [opt_row[metric]], marker="*", s=320, color=OPT_COLOR, edgecolors="black",
                      linewidths=0.8, zorder=7,
                      label=(f"optimum {inner} = {fmt(optimum[inner], 7)} {inner_unit}, {outer} = {fmt(optimum[outer], 5)} {outer_unit}"
                             if a is ax else None))
    if paper_optimum is not None and inner in paper_optimum:
        for a in (ax, az):
            a.axvline(paper_optimum[inner], color=PAPER_OPT_COLOR, linestyle="--", linewidth=1.2, zorder=1,
                      label=f"paper's optimum {inner} = {fmt(paper_optimum[inner], 6)} {inner_unit}" if a is ax else None)
    ax.set_xscale("log")
    # linear y: the cubic fits of eq. 3 change sign over a decade of c, which a log axis would hide
    vals = pts[metric].to_numpy(float)
    vals = vals[np.isfinite(vals)]
    if vals.size:
        top = max(float(vals.max()), threshold or 0.0)
        ax.set_ylim(-0.08 * top, 1.12 * top)
    ax.axhline(0.0, color="gray", linewidth=0.6)
    ax.ticklabel_format(axis="y", style="sci", scilimits=(-3, 4), useMathText=True)
    _log_ticks(ax, "x")
    ax.set_xlabel(f"stiffness {inner}{_unit(inner_unit)} (log)")
    ax.set_ylabel(f"{metric}{_unit(metric_unit)}")
    ax.set_title(title or f"{metric} of the search points")
    ax.grid(True, which="both", alpha=0.25)
    # zoom panel
    center = optimum[inner] if optimum is not None else (float(np.median(pts[inner])) if len(pts) else 1.0)
    lo, hi = center * (1 - zoom), center * (1 + zoom)
    near = pts[(pts[inner] >= lo) & (pts[inner] <= hi)]
    az.set_xlim(lo, hi)
    ys = [float(v) for v in near[metric] if np.isfinite(v)]
    if threshold is not None:
        ys.append(threshold)
    if reference is not None:
        ys.extend(list(reference(np.array([lo, hi]))))
    if ys:
        span = max(ys) - min(ys) or abs(max(ys)) * 0.1 or 1.0
        az.set_ylim(min(ys) - 0.08 * span, max(ys) + 0.08 * span)
    az.set_xlabel(f"stiffness {inner}{_unit(inner_unit)} (linear, ±{zoom:.0%} of the optimum)")
    az.set_ylabel(f"{metric}{_unit(metric_unit)}")
    az.set_title(f"zoom: {len(near)} search points near the boundary")
    az.grid(True, alpha=0.25)
    az.ticklabel_format(axis="both", style="sci", scilimits=(-3, 4), useMathText=True)
    handles, labels = ax.get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=4, frameon=False,
               title=f"search levels of {outer} [{outer_unit}] (one colour and marker each; "
                     f"thin lines: cubic fits of eq. 3 per level)", title_fontsize=9)
    fig.tight_layout()
    return _save(fig, path)


# ============================================================================ Figures 12-13: t_eq
def search_t_eq(runs: pd.DataFrame, levels: Sequence[dict], path: str | Path, *, inner: str = "c",
                outer: str = "d", inner_unit: str = "N/m", outer_unit: str = "N·s/m", metric: str = "t_eq",
                shift: float = 0.0, optimum: Mapping[str, float] | None = None,
                paper_optimum: Mapping[str, float] | None = None, paper_t_eq: float | None = None,
                inner_range=None, stages: Sequence[str] = ("search",)) -> Path:
    """The time to equilibrium of the search points against the inner (left) and the outer (right)
    parameter, log axes. With ``shift`` (the ramp time) the y axis is ``t_eq − shift``, the time the
    screw needs to come to rest after the load stops rising."""
    pts = _search_points(runs, levels, inner, outer, inner_range, stages)
    lv_values = sorted({float(lv["outer"]) for lv in levels}, reverse=True)
    cols = level_colors(lv_values)
    y = pts[metric].astype(float) - shift
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(13, 5.4), sharey=True)
    finite = y[np.isfinite(y) & (y > 0)]
    top = float(finite.max()) * 2.5 if len(finite) else 1.0
    for k, z in enumerate(lv_values):
        sel = np.isclose(pts[outer], z, rtol=1e-12)
        g, gy = pts[sel], y[sel]
        ok = np.isfinite(gy) & (gy > 0)
        mk = _MARKERS[k % len(_MARKERS)]
        a1.scatter(g.loc[ok, inner], gy[ok], marker=mk, s=34, color=cols[z], alpha=0.6, edgecolors="none",
                   label=f"{outer} = {fmt(z, 6)}")
        a2.scatter(g.loc[ok, outer], gy[ok], marker=mk, s=34, color=cols[z], alpha=0.6, edgecolors="none")
        if (~ok).any():
            a1.scatter(g.loc[~ok, inner], np.full((~ok).sum(), top), marker="^", s=40, facecolors="none",
                       edgecolors=cols[z], alpha=0.8)
            a2.scatter(g.loc[~ok, outer], np.full((~ok).sum(), top), marker="^", s=40, facecolors="none",
                       edgecolors=cols[z], alpha=0.8)
    n_missing = int((~(np.isfinite(y) & (y > 0))).sum())
    if n_missing:
        a1.scatter([], [], marker="^", facecolors="none", edgecolors="gray",
                   label=f"never at rest before the end ({n_missing} runs, drawn at the top)")
    if optimum is not None:
        m = pts[np.isclose(pts[inner], optimum[inner], rtol=1e-12) & np.isclose(pts[outer], optimum[outer],
                                                                                 rtol=1e-12)]
        if len(m):
            yo = float(m.iloc[0][metric]) - shift
            for a, xv in ((a1, optimum[inner]), (a2, optimum[outer])):
                a.scatter([xv], [yo], marker="*", s=320, color=OPT_COLOR, edgecolors="black", linewidths=0.8,
                          zorder=7, label=(f"our optimum: {metric} = {fmt(yo + shift, 7)} s" if a is a1 else None))
    if paper_optimum is not None and paper_t_eq is not None:
        # the paper's t_eq is plotted as reported (it is not measured after a ramp of length `shift`)
        for a, key in ((a1, inner), (a2, outer)):
            if key in paper_optimum:
                a.scatter([paper_optimum[key]], [paper_t_eq], marker="X", s=110, color="black", zorder=7,
                          label=(f"paper: {metric} = {paper_t_eq:g} s at {inner} = {fmt(paper_optimum[inner], 6)},"
                                 f" {outer} = {fmt(paper_optimum[outer], 4)} (its reported value; "
                                 f"not after a ramp)" if a is a1 else None))
    ylabel = (f"{metric} − {fmt(shift, 4)} s  [s]  (time after the ramp end)" if shift else f"{metric} [s]")
    for a, name, unit in ((a1, inner, inner_unit), (a2, outer, outer_unit)):
        a.set_xscale("log")
        a.set_yscale("log")
        a.grid(True, which="both", alpha=0.25)
        a.set_xlabel(f"{'stiffness' if a is a1 else 'damping'} {name}{_unit(unit)}")
    _log_ticks(a1, "x")
    a1.set_ylabel(ylabel)
    a1.set_title(f"time to equilibrium against {inner}")
    a2.set_title(f"time to equilibrium against {outer}")
    handles, labels = a1.get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=4, frameon=False)
    fig.tight_layout()
    return _save(fig, path)


# ============================================================================ search path
def search_path(searches: Sequence[tuple[str, Sequence[dict], Mapping[str, float] | None, str]], path: str | Path,
                *, inner: str = "c", outer: str = "d", inner_unit: str = "N/m", outer_unit: str = "N·s/m",
                paper_optimum: Mapping[str, float] | None = None,
                reference: tuple[float, str] | None = None,
                annotations: Sequence[tuple[float, float, str]] = ()) -> Path:
    """The outer levels of each search (``(label, levels, optimum, color)``) against the smallest
    feasible inner value found there; the stop point starred, levels without a feasible value marked
    at the bottom; the paper's optimum as a cross; ``annotations`` (outer, inner, text) label points."""
    fig, ax = plt.subplots(figsize=(9.5, 5.8))
    all_c = []
    for label, levels, opt, color in searches:
        all_c += [float(lv["inner"]) for lv in levels if lv.get("inner") is not None]
    lo_c = min(all_c) if all_c else 1.0
    hi_c = max(all_c) if all_c else 1.0
    for n, (label, levels, opt, color) in enumerate(searches):
        zs = np.array([float(lv["outer"]) for lv in levels])
        cs = np.array([float(lv["inner"]) if lv.get("inner") is not None else np.nan for lv in levels])
        ok = np.isfinite(cs)
        ax.plot(zs[ok], cs[ok], "-o", color=color, alpha=0.8, markersize=7 - 2 * n, linewidth=1.8 - 0.6 * n,
                label=f"{label}: {len(levels)} levels, {sum(int(lv.get('evaluations', 0)) for lv in levels)} runs")
        if (~ok).any():
            ax.scatter(zs[~ok], np.full((~ok).sum(), lo_c - 0.05 * (hi_c - lo_c)), marker="v", s=60, color=color,
                       label=f"{label}: no feasible {inner} in the region")
        if len(zs):
            ax.annotate(f"start ({label})", (zs[0], cs[0] if ok[0] else lo_c), textcoords="offset points",
                        xytext=(0, 10 + 14 * n), ha="center", fontsize=8.5, color=color)
        if opt is not None:
            ax.scatter([opt[outer]], [opt[inner]], marker="*", s=380 - 120 * n, color=color, edgecolors="black",
                       zorder=6, label=f"{label}: stop point {inner} = {fmt(opt[inner], 7)} {inner_unit}, "
                                       f"{outer} = {fmt(opt[outer], 5)} {outer_unit}")
    if paper_optimum is not None:
        ax.scatter([paper_optimum[outer]], [paper_optimum[inner]], marker="x", s=90, linewidths=2.2, color="black",
                   zorder=7, label=f"paper's optimum {inner} = {fmt(paper_optimum[inner], 6)} {inner_unit}, "
                                   f"{outer} = {fmt(paper_optimum[outer], 4)} {outer_unit}")
    if reference is not None:
        ax.axhline(reference[0], color=THRESH_COLOR, linestyle=":", linewidth=1.5, label=reference[1], zorder=1)
    for z, c, text in annotations:
        ax.annotate(text, (z, c), textcoords="offset points", xytext=(-10, 0), ha="right", va="center",
                    fontsize=8.5, arrowprops={"arrowstyle": "-", "color": "gray", "lw": 0.6})
    ax.set_xscale("log")
    ax.ticklabel_format(axis="y", style="sci", scilimits=(-3, 4), useMathText=True)
    ax.set_ylim(lo_c - 0.12 * (hi_c - lo_c) - 0.02 * lo_c, hi_c + 0.12 * (hi_c - lo_c) + 0.02 * hi_c)
    ax.grid(True, which="both", alpha=0.25)
    ax.set_xlabel(f"damping {outer}{_unit(outer_unit)} (log; the search halves it from the region's top, "
                  f"right to left)")
    ax.set_ylabel(f"smallest feasible stiffness {inner}{_unit(inner_unit)}")
    ax.set_title(f"Nested binary search: the {outer} levels and the smallest feasible {inner} at each")
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=1, frameon=False)
    return _save(fig, path)


# ============================================================================ time series at the optimum
def time_series(df: pd.DataFrame, path: str | Path, *, eps_y: float | None = None, eps_v: float | None = None,
                t_eq: float | None = None, t_ramp: float | None = None, title: str = "",
                zoom: pd.DataFrame | None = None, eps_v_eq: float | None = None,
                eps_a_eq: float | None = None) -> Path:
    """Force, displacement (mm), velocity (mm/s) of one run, thresholds and t_eq marked; with ``zoom``
    (a finer sampled run) a fourth panel shows |v_y| on a log axis around the ramp end and t_eq."""
    n = 4 if zoom is not None else 3
    fig, axes = plt.subplots(n, 1, figsize=(12, 2.5 * n + 0.6))
    t = df["time"].to_numpy()
    a0, a1, a2 = axes[0], axes[1], axes[2]
    a0.plot(t, df["F_pull"], color="black")
    a0.set_ylabel("pullout force\nF_pull [N]")
    a1.plot(t, df["y"] * 1e3, color="tab:blue", label="y")
    if eps_y is not None:
        a1.axhline(eps_y * 1e3, color=THRESH_COLOR, linestyle="--", label=f"ε_y = {fmt(eps_y * 1e3)} mm")
    a1.set_ylabel("displacement\ny [mm]")
    a2.plot(t, df["v_y"] * 1e3, color="tab:orange", label="ẏ")
    if eps_v is not None:
        a2.axhline(eps_v * 1e3, color=THRESH_COLOR, linestyle="--", label=f"ε_ẏ = {fmt(eps_v * 1e3)} mm/s")
    a2.set_ylabel("velocity\nẏ [mm/s]")
    for a in (a0, a1, a2):
        a.set_xlim(t[0], t[-1])
        a.grid(True, alpha=0.3)
        a.set_xlabel("time t [s]")
        if t_ramp is not None:
            a.axvline(t_ramp, color="gray", linestyle=":", linewidth=1.2,
                      label=f"ramp end t_ramp = {t_ramp:g} s" if a is a0 else None)
        if t_eq is not None and math.isfinite(t_eq):
            a.axvline(t_eq, color="tab:green", linewidth=1.5,
                      label=f"at rest from t_eq = {t_eq:.6g} s" if a is a0 else None)
    for a in (a0, a1, a2):
        a.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), frameon=False)
    a2.set_ylim(bottom=min(-0.05 * (eps_v or 0) * 1e3, float(np.nanmin(df["v_y"])) * 1.1e3))
    if zoom is not None:
        a3 = axes[3]
        v = np.abs(zoom["v_y"].to_numpy())
        a3.semilogy(zoom["time"], np.where(v > 0, v, np.nan) * 1e3, color="tab:orange", label="|ẏ| [mm/s]")
        if eps_v is not None:
            a3.axhline(eps_v * 1e3, color=THRESH_COLOR, linestyle="--", label=f"ε_ẏ = {fmt(eps_v * 1e3)} mm/s")
        if eps_v_eq is not None:
            a3.axhline(eps_v_eq * 1e3, color="tab:orange", linestyle=":", linewidth=1.5,
                       label=f"ε_ẏeq = {fmt(eps_v_eq * 1e3)} mm/s (rest threshold on |ẏ|)")
        lows = [x for x in (eps_v_eq, eps_a_eq) if x]
        if "a_y" in zoom:
            acc = np.abs(zoom["a_y"].to_numpy())
            a3.semilogy(zoom["time"], np.where(acc > 0, acc, np.nan) * 1e3, color="tab:brown",
                        label="|ÿ| [mm/s²]")
            if eps_a_eq is not None:
                a3.axhline(eps_a_eq * 1e3, color="tab:brown", linestyle=":", linewidth=1.5,
                           label=f"ε_ÿeq = {fmt(eps_a_eq * 1e3)} mm/s² (rest threshold on |ÿ|)")
        if t_ramp is not None:
            a3.axvline(t_ramp, color="gray", linestyle=":", linewidth=1.2)
        if t_eq is not None and math.isfinite(t_eq):
            a3.axvline(t_eq, color="tab:green", linewidth=1.5, label=f"t_eq = {t_eq:.6g} s")
        a3.set_xlim(zoom["time"].iloc[0], zoom["time"].iloc[-1])
        lo = (min(lows) if lows else np.nanmin(v[v > 0])) * 1e3 / 30
        hi = max([(eps_v or 0) * 1e3 * 5] + ([float(np.nanmax(np.abs(zoom["a_y"]))) * 1e3 * 2]
                                            if "a_y" in zoom else []))
        a3.set_ylim(lo, hi)
        a3.set_xlabel("time t [s] (zoom on the ramp end, sampled every 0.5 ms)")
        a3.set_ylabel("|ẏ| [mm/s], |ÿ| [mm/s²]\n(log)")
        a3.grid(True, which="both", alpha=0.3)
        a3.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), frameon=False)
    fig.suptitle(title)
    fig.tight_layout()
    return _save(fig, path)


# ============================================================================ ramp-time dependence
def ramp_time(table: pd.DataFrame, path: str | Path, *, F: float, eps_y: float, eps_v: float,
              ours: float | None = None, paper: float | None = None, inner: str = "c",
              inner_unit: str = "N/m", outer_label: str = "", at: float = 10.0) -> Path:
    """The smallest feasible stiffness against the ramp time (columns t_ramp, c_min), next to the two
    quasi-static bounds F/ε_y and F/(ε_ẏ·t_ramp)."""
    fig, ax = plt.subplots(figsize=(9.5, 5.6))
    T = table["t_ramp"].to_numpy(float)
    tt = np.geomspace(T.min(), T.max(), 300)
    ax.plot(T, table["c_min"], "o", color="black", markersize=7, zorder=3,
            label=f"smallest feasible {inner} (FMU, bisection{outer_label})")
    ax.plot(tt, np.full_like(tt, F / eps_y), color="tab:blue", linestyle="--", linewidth=2, zorder=4,
            label=f"translation bound F/ε_y = {fmt(F / eps_y, 6)} {inner_unit}")
    ax.plot(tt, F / (eps_v * tt), color="tab:orange", linestyle="--", linewidth=2, zorder=4,
            label="velocity bound F/(ε_ẏ·t_ramp)")
    ax.axvline(eps_y / eps_v, color="gray", linestyle=":", linewidth=1.2,
               label=f"t_ramp = ε_y/ε_ẏ = {fmt(eps_y / eps_v)} s: both bind")
    if ours is not None:
        ax.scatter([at], [ours], marker="*", s=220, color=OPT_COLOR, edgecolors="black", zorder=6,
                   label=f"our optimum {inner} = {fmt(ours, 7)} {inner_unit} (t_ramp = {fmt(at)} s)")
    if paper is not None:
        ax.scatter([at], [paper], marker="x", s=90, linewidths=2.2, color="black", zorder=7,
                   label=f"paper's {inner} = {fmt(paper, 6)} {inner_unit} (drawn at t_ramp = {fmt(at)} s)")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.25)
    ax.set_xlabel("ramp time t_ramp [s] (F rises linearly from 0 to F_max; end = t_ramp + 2 s)")
    ax.set_ylabel(f"smallest feasible stiffness {inner}{_unit(inner_unit)}")
    ax.set_title("Which constraint binds depends on the ramp time")
    ax.legend(loc="upper right", frameon=True)
    return _save(fig, path)


# ============================================================================ sensitivity (optional)
_INDEX_KEYS = ("mu_star", "sigma", "mu", "S1", "ST")


def _tables(obj, trail=()) -> list[tuple[tuple, pd.DataFrame]]:
    """(path, parameter × index table) for every sensitivity index table found in ``obj``: a
    DataFrame with index columns, a SALib-like dict {names, S1, ST, ...}, or {parameter: {S1: ..}}."""
    found = []
    if isinstance(obj, pd.DataFrame):
        cols = [c for c in obj.columns if c in _INDEX_KEYS or c.endswith("_conf")]
        if any(c in _INDEX_KEYS for c in cols):
            df = obj.copy()
            for key in ("parameter", "name", "names"):
                if key in df.columns:
                    df = df.set_index(key)
                    break
            found.append((trail, df[cols].apply(pd.to_numeric, errors="coerce")))
        return found
    if not isinstance(obj, Mapping):
        return found
    names = obj.get("names") or obj.get("parameters")
    if isinstance(names, (list, tuple)) and any(k in obj for k in _INDEX_KEYS):
        data = {}
        for k, v in obj.items():
            if (k in _INDEX_KEYS or str(k).endswith("_conf")) and hasattr(v, "__len__") and len(v) == len(names) \
                    and np.ndim(v) == 1:
                data[k] = pd.to_numeric(pd.Series(list(v)), errors="coerce").to_numpy()
        if data:
            found.append((trail, pd.DataFrame(data, index=list(names))))
            return found
    vals = list(obj.values())
    if vals and all(isinstance(v, Mapping) for v in vals) and \
            all(any(k in v for k in _INDEX_KEYS) for v in vals):
        df = pd.DataFrame({str(p): {k: v.get(k) for k in v if k in _INDEX_KEYS or str(k).endswith("_conf")}
                           for p, v in obj.items()}).T
        found.append((trail, df.apply(pd.to_numeric, errors="coerce")))
        return found
    for k, v in obj.items():
        if len(trail) < 5:
            found += _tables(v, trail + (str(k),))
    return found


def sensitivity_figures(sensitivity, outdir: str | Path) -> list[Path]:
    """Bar charts of every sensitivity index table found in ``sensitivity`` (Morris μ*/σ, Sobol
    S1/ST), one PNG per method, one panel per output. Returns [] when nothing is recognised."""
    tables = _tables(sensitivity)
    seen = set()
    unique = []
    for trail, df in tables:
        key = tuple(t for t in trail if t != "summary")
        if key in seen or df.empty:
            continue
        seen.add(key)
        unique.append((key, df))
    by_method: dict[str, list[tuple[str, pd.DataFrame]]] = {}
    for key, df in unique:
        method = "sobol" if ("S1" in df.columns or "ST" in df.columns) else "morris"
        label = " / ".join(k for k in key if k.lower() not in ("morris", "sobol", "indices")) or method
        by_method.setdefault(method, []).append((label, df))
    paths = []
    for method, items in by_method.items():
        items = items[:12]
        ncol = min(3, len(items))
        nrow = math.ceil(len(items) / ncol)
        nparam = max(len(df) for _, df in items)
        fig, axes = plt.subplots(nrow, ncol, figsize=(5.2 * ncol, max(2.6, 0.28 * nparam + 1.2) * nrow),
                                 squeeze=False)
        for a, (label, df) in zip(axes.ravel(), items):
            if method == "morris":
                main = "mu_star" if "mu_star" in df.columns else df.columns[0]
                d = df.sort_values(main)
                y = np.arange(len(d))
                a.barh(y - 0.2, d[main], height=0.4, color="tab:blue", label="μ* (mean |elementary effect|)",
                       xerr=d.get("mu_star_conf"), error_kw={"elinewidth": 0.8})
                if "sigma" in d.columns:
                    a.barh(y + 0.2, d["sigma"], height=0.4, color="tab:orange", label="σ (interaction/non-linearity)")
            else:
                key = "ST" if "ST" in df.columns else "S1"
                d = df.sort_values(key)
                y = np.arange(len(d))
                if "S1" in d.columns:
                    a.barh(y - 0.2, d["S1"], height=0.4, color="tab:blue", label="S1 (first order)",
                           xerr=d.get("S1_conf"), error_kw={"elinewidth": 0.8})
                if "ST" in d.columns:
                    a.barh(y + 0.2, d["ST"], height=0.4, color="tab:orange", label="ST (total)",
                           xerr=d.get("ST_conf"), error_kw={"elinewidth": 0.8})
            a.set_yticks(y, [str(i) for i in d.index])
            a.set_title(label)
            a.grid(True, axis="x", alpha=0.3)
            a.set_xlabel("index [-]" if method == "sobol" else "elementary effect [output unit per range]")
        for a in axes.ravel()[len(items):]:
            a.set_visible(False)
        h, lab = axes.ravel()[0].get_legend_handles_labels()
        fig.legend(h, lab, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=2, frameon=False)
        fig.suptitle(f"Global sensitivity: {'Morris screening' if method == 'morris' else 'Sobol indices'}")
        fig.tight_layout()
        paths.append(_save(fig, Path(outdir) / f"sensitivity_{method}.png"))
    return paths
