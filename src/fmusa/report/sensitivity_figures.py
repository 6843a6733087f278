"""Figures of a global sensitivity analysis: Morris μ*–σ and Sobol S1/ST bars, from the results it is given."""
from __future__ import annotations

import math
import textwrap
from pathlib import Path
from typing import Mapping

import numpy as np

from fmusa.analysis.sensitivity import MORRIS_LEVELS
from fmusa.files import atomic_path


def _tables(result: Mapping) -> tuple[dict, dict]:
    """(summary, meta) from run_sensitivity's result or from its summary (e.g. summary.json)."""
    summary = result.get("summary", result)
    return summary, summary.get("meta", {})


def _unit(meta: Mapping, metric: str) -> str:
    u = meta.get("metrics", {}).get(metric, {}).get("unit", "")
    return u or "–"


def plot_sensitivity(result: Mapping, figdir: str | Path) -> list[Path]:
    """``sensitivity_morris.png`` (μ* against σ per metric, points labelled with the parameter) and
    ``sensitivity_sobol.png`` (S1 and ST per parameter per metric with their 95 % confidence
    intervals) in ``figdir``. ``result`` is run_sensitivity's result or its summary."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary, meta = _tables(result)
    figdir = Path(figdir)
    figdir.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []

    def grid(n):
        ncols = 2 if n > 1 else 1
        return math.ceil(n / ncols), ncols

    morris = summary.get("morris") or {}
    if morris:
        metrics = list(morris)
        nr, nc = grid(len(metrics))
        fig, axes = plt.subplots(nr, nc, figsize=(6.4 * nc, 4.6 * nr), squeeze=False)
        for ax, metric in zip(axes.flat, metrics):
            tab = morris[metric]
            names = list(tab)
            mu = np.array([tab[n]["mu_star"] or 0.0 for n in names])
            sg = np.array([tab[n]["sigma"] or 0.0 for n in names])
            ci = np.array([tab[n]["mu_star_conf"] or 0.0 for n in names])
            ax.errorbar(mu, sg, xerr=ci, fmt="o", ms=5, color="C0", ecolor="0.6", elinewidth=1, capsize=2)
            top = max(float(mu.max()), float(sg.max()), 1e-300)
            ax.plot([0, top * 1.2], [0, top * 1.2], ls="--", lw=0.8, color="0.5", label="σ = μ*")
            thresh = 0.03 * top
            minor = []
            for n, x, y in zip(names, mu, sg):
                if x >= thresh or y >= thresh:
                    ax.annotate(n, (x, y), xytext=(4, 4), textcoords="offset points", fontsize=8.5,
                                color="C3")
                else:
                    minor.append(n)
            u = _unit(meta, metric)
            desc = meta.get("metrics", {}).get(metric, {}).get("description", "")
            title = f"{metric}" + (f": {desc}" if desc else "")
            if minor:
                title += "\n" + textwrap.fill("< 3 % of the largest: " + ", ".join(minor), 95)
            ax.set_title(title, fontsize=9)
            ax.set_xlabel(f"μ* (mean |elementary effect|) [{u}]")
            ax.set_ylabel(f"σ (std. of elementary effects) [{u}]")
            ax.set_xlim(left=0, right=1.25 * top)      # same scale on both axes: σ/μ* is the slope
            ax.set_ylim(bottom=0, top=1.25 * top)
            ax.ticklabel_format(style="sci", scilimits=(-3, 3), axis="both")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, loc="upper left")
        for ax in axes.flat[len(metrics):]:
            ax.set_visible(False)
        levels = meta.get("morris_levels", MORRIS_LEVELS)
        step = f"{levels / (2 * (levels - 1)):.3g}" if isinstance(levels, int) and levels > 1 else "Δ"
        fig.suptitle(f"Morris screening ({meta.get('morris_trajectories', '?')} trajectories, {levels} levels): "
                     f"change of the metric per step of {step} × the input's range (log10 range for "
                     f"log-uniform inputs); bars: 95 % CI of μ*", fontsize=10)
        fig.tight_layout(rect=(0, 0, 1, 0.97))
        p = figdir / "sensitivity_morris.png"
        try:
            with atomic_path(p) as tmp:
                fig.savefig(tmp, dpi=130)
        finally:
            plt.close(fig)
        paths.append(p)

    sobol = summary.get("sobol") or {}
    if sobol:
        metrics = list(sobol)
        nr, nc = grid(len(metrics))
        fig, axes = plt.subplots(nr, nc, figsize=(7.2 * nc, 3.6 * nr), squeeze=False)
        for ax, metric in zip(axes.flat, metrics):
            tab = sobol[metric]
            names = list(tab)
            xs = np.arange(len(names))

            def col(k):
                return np.array([tab[n][k] if tab[n][k] is not None else np.nan for n in names])
            w = 0.38
            ax.bar(xs - w / 2, col("S1"), w, yerr=col("S1_conf"), capsize=2, color="C0", label="S1 (first order)",
                   error_kw={"elinewidth": 0.8})
            ax.bar(xs + w / 2, col("ST"), w, yerr=col("ST_conf"), capsize=2, color="C1", label="ST (total)",
                   error_kw={"elinewidth": 0.8})
            ax.axhline(0, color="k", lw=0.6)
            ax.set_xticks(xs)
            ax.set_xticklabels(names, rotation=60, ha="right", fontsize=8)
            n_force = sum(1 for n in names if n[:2] in ("c_", "d_"))
            if 0 < n_force < len(names):   # force-element parameters | mass properties
                ax.axvline(n_force - 0.5, color="0.6", lw=0.8, ls=":")
            ax.set_ylabel("Sobol index [–] (share of variance)")
            u = _unit(meta, metric)
            desc = meta.get("metrics", {}).get(metric, {}).get("description", "")
            ax.set_title(f"{metric} [{u}]" + (f": {desc}" if desc else ""), fontsize=9.5)
            hi = np.nanmax(np.concatenate([col("ST") + np.nan_to_num(col("ST_conf")), [1.0]]))
            lo = np.nanmin(np.concatenate([col("S1") - np.nan_to_num(col("S1_conf")), [0.0]]))
            ax.set_ylim(max(lo - 0.05, -0.3), min(hi + 0.05, 1.5))
            ax.grid(axis="y", alpha=0.3)
            ax.legend(fontsize=7, loc="upper right")
        for ax in axes.flat[len(metrics):]:
            ax.set_visible(False)
        samples = (summary.get("samples") or {}).get("sobol", "?")
        fig.suptitle(f"Sobol indices (N = {meta.get('n', '?')}, {samples} runs, no second order; "
                     f"bars: 95 % confidence intervals)", fontsize=10)
        fig.tight_layout(rect=(0, 0, 1, 0.97))
        p = figdir / "sensitivity_sobol.png"
        try:
            with atomic_path(p) as tmp:
                fig.savefig(tmp, dpi=130)
        finally:
            plt.close(fig)
        paths.append(p)
    return paths

