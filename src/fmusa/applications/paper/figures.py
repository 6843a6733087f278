"""The paper's own figures: time to equilibrium of the search points (its Figs. 12-13), the pullout at the
optimum over time, and the smallest feasible stiffness against the ramp time.

Drawn from data the paper extension computed (:mod:`fmusa.applications.paper.physics`); the generic figures
(heat maps, search points, search path) come from :mod:`fmusa.report.figures` with the paper's titles.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from fmusa.report.figures import (MARKERS, OPT_COLOR, PAGE_WIDTH, THRESH_COLOR, fmt, level_colors, log_ticks, save,
                                  search_points, unit_suffix)

import matplotlib.pyplot as plt  # noqa: E402 - after fmusa.report.figures chose the Agg backend

PAPER_COLOR = "#1f1fff"     # the paper's region (the paper frames its region in blue): dashed


def search_t_eq(runs: pd.DataFrame, levels: Sequence[dict], path: str | Path, *, inner: str = "c",
                outer: str = "d", inner_unit: str = "N/m", outer_unit: str = "N·s/m", metric: str = "t_eq",
                shift: float = 0.0, optimum: Mapping[str, float] | None = None,
                paper_optimum: Mapping[str, float] | None = None, paper_t_eq: float | None = None,
                inner_range=None, stages: Sequence[str] = ("search",)) -> Path:
    """The time to equilibrium of the search points against the inner (left) and the outer (right)
    parameter, log axes. With ``shift`` (the ramp time) the y axis is ``t_eq − shift``, the time the
    screw needs to come to rest after the load stops rising."""
    pts = search_points(runs, levels, inner, outer, inner_range, stages)
    lv_values = sorted({float(lv["outer"]) for lv in levels}, reverse=True)
    cols = level_colors(lv_values)
    y = pts[metric].astype(float) - shift
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(PAGE_WIDTH, 3.8), sharey=True)
    finite = y[np.isfinite(y) & (y > 0)]
    top = float(finite.max()) * 2.5 if len(finite) else 1.0
    for k, z in enumerate(lv_values):
        sel = np.isclose(pts[outer], z, rtol=1e-12)
        g, gy = pts[sel], y[sel]
        ok = np.isfinite(gy) & (gy > 0)
        mk = MARKERS[k % len(MARKERS)]
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
        a.set_xlabel(f"{'stiffness' if a is a1 else 'damping'} {name}{unit_suffix(unit)}")
    log_ticks(a1, "x")
    a1.set_ylabel(ylabel)
    a1.set_title(f"time to equilibrium against {inner}")
    a2.set_title(f"time to equilibrium against {outer}")
    handles, labels = a1.get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=4, frameon=False)
    fig.tight_layout()
    return save(fig, path)


def _zoom_panel(a3, zoom: pd.DataFrame, eps_v, eps_v_eq, eps_a_eq, t_ramp, t_eq) -> None:
    """|ẏ| and |ÿ| around the ramp end on a log axis, with the rest thresholds."""
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
    a3.legend(loc="upper center", bbox_to_anchor=(0.5, -0.32), fontsize=7.5, frameon=False, ncol=2)


def time_series(df: pd.DataFrame, path: str | Path, *, eps_y: float | None = None, eps_v: float | None = None,
                t_eq: float | None = None, t_ramp: float | None = None, title: str = "",
                zoom: pd.DataFrame | None = None, eps_v_eq: float | None = None,
                eps_a_eq: float | None = None) -> Path:
    """Force, displacement (mm), velocity (mm/s) of one run, thresholds and t_eq marked; with ``zoom``
    (a finer sampled run) a fourth panel shows |v_y| on a log axis around the ramp end and t_eq."""
    n = 4 if zoom is not None else 3
    fig, axes = plt.subplots(n, 1, figsize=(PAGE_WIDTH, 1.9 * n + 0.6))
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
    for a, where in ((a0, "upper left"), (a1, "upper left"), (a2, "center left")):
        a.legend(loc=where, fontsize=8, framealpha=0.9)
    a2.set_ylim(bottom=min(-0.05 * (eps_v or 0) * 1e3, float(np.nanmin(df["v_y"])) * 1.1e3))
    if zoom is not None:
        _zoom_panel(axes[3], zoom, eps_v, eps_v_eq, eps_a_eq, t_ramp, t_eq)
    fig.suptitle(title)
    fig.tight_layout()
    return save(fig, path)


def ramp_time(table: pd.DataFrame, path: str | Path, *, F: float, eps_y: float, eps_v: float,
              ours: float | None = None, paper: float | None = None, inner: str = "c",
              inner_unit: str = "N/m", outer_label: str = "", at: float = 10.0) -> Path:
    """The smallest feasible stiffness against the ramp time (columns t_ramp, c_min), next to the two
    quasi-static bounds F/ε_y and F/(ε_ẏ·t_ramp)."""
    fig, ax = plt.subplots(figsize=(PAGE_WIDTH, 4.4))
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
    ax.set_ylabel(f"smallest feasible stiffness {inner}{unit_suffix(inner_unit)}")
    ax.set_title("Which constraint binds depends on the ramp time")
    ax.legend(loc="upper right", frameon=True)
    return save(fig, path)
