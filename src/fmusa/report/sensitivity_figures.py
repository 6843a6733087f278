"""Figures of a global sensitivity analysis, from the results they are given: Morris μ*–σ, Sobol S1/ST bars
(Saltelli's scheme or the polynomial chaos) with their 95 % intervals, and the polynomial chaos' validation
(each run against its leave-one-out prediction)."""
from __future__ import annotations

import math
import textwrap
from pathlib import Path
from typing import Mapping

import numpy as np

from fmusa.analysis.sensitivity import MORRIS_LEVELS
from fmusa.figure_check import MAX_HEIGHT_IN, MAX_WIDTH_IN
from fmusa.files import save_figure

#: Width and height of one panel [in], and the resolution: a page (7.5 in wide) holds two panels side by side.
PANEL_W, PANEL_H, DPI = 3.7, 3.0, 130
#: At most this many rows of panels on one figure; more outputs go on further pages (name_2.png, …).
MAX_ROWS = 4


def _tables(result: Mapping) -> tuple[dict, dict]:
    """(summary, meta) from run_sensitivity's result or from its summary (e.g. summary.json)."""
    summary = result.get("summary", result)
    return summary, summary.get("meta", {})


def _unit(meta: Mapping, metric: str) -> str:
    u = meta.get("metrics", {}).get(metric, {}).get("unit", "")
    return u or "–"


def _grid(n: int) -> tuple[int, int]:
    """Rows and columns of ``n`` panels (at most 2 × MAX_ROWS, one page): one panel alone, else two per row."""
    ncols = 1 if n == 1 else 2
    return math.ceil(n / ncols), ncols


def _size(nr: int, nc: int, row_extra: float = 0.0, top: float = 0.5) -> tuple[float, float]:
    """Figure size [in] of ``nr`` × ``nc`` panels within a page: rows shrink to fit its height."""
    row = min(PANEL_H + row_extra, (MAX_HEIGHT_IN - top) / nr)
    width = PANEL_W * nc + 0.1 if nc > 1 else PANEL_W * 1.4
    return min(width, MAX_WIDTH_IN), row * nr + top


def _pages(items: list, path: Path) -> list[tuple[list, Path]]:
    """``items`` split into pages of at most 2 × MAX_ROWS panels: the first page is ``path``, the next
    ``<stem>_2<suffix>``, …, so that every figure fits a journal page."""
    per = 2 * MAX_ROWS
    chunks = [items[i:i + per] for i in range(0, len(items), per)] or [[]]
    return [(c, path if k == 0 else path.with_name(f"{path.stem}_{k + 1}{path.suffix}"))
            for k, c in enumerate(chunks)]


def _save(fig, path: Path) -> Path:
    return save_figure(fig, path, tight=False, dpi=DPI)   # written whole, checked in the tests (figure_check)


def _suptitle(fig, text: str, fontsize: float = 9.5) -> None:
    """A figure title wrapped to the figure's width."""
    chars = int(fig.get_figwidth() * 72 / (0.55 * fontsize))
    fig.suptitle(textwrap.fill(text, chars), fontsize=fontsize)


def _title(meta: Mapping, metric: str, with_unit: bool = True) -> str:
    desc = meta.get("metrics", {}).get(metric, {}).get("description", "")
    head = f"{metric} [{_unit(meta, metric)}]" if with_unit else metric
    return textwrap.shorten(head + (f": {desc}" if desc else ""), 80, placeholder="…")


def _morris_figure(morris: Mapping, meta: Mapping, path: Path) -> list[Path]:
    return [_morris_page(morris, metrics, meta, p) for metrics, p in _pages(list(morris), path)]


def _morris_page(morris: Mapping, metrics: list, meta: Mapping, path: Path) -> Path:
    import matplotlib.pyplot as plt
    nr, nc = _grid(len(metrics))
    fig, axes = plt.subplots(nr, nc, figsize=_size(nr, nc, 0.5, 0.6), squeeze=False, layout="constrained")
    for ax, metric in zip(axes.flat, metrics):
        tab = morris[metric]
        names = list(tab)
        mu = np.array([tab[n]["mu_star"] or 0.0 for n in names])
        sg = np.array([tab[n]["sigma"] or 0.0 for n in names])
        ci = np.array([tab[n]["mu_star_conf"] or 0.0 for n in names])
        u = _unit(meta, metric)
        top = max(float(np.max(mu + ci)), float(sg.max()))
        if not top > 0:      # no input moves this output: say so, no axis of nothing
            ax.text(0.5, 0.5, "no input changes this output\n(every elementary effect is 0)", ha="center",
                    va="center", transform=ax.transAxes, fontsize=9)
            ax.set_xlim(0, 1)
            ax.set_ylim(0, 1)
            ax.set_xticks([])
            ax.set_yticks([])
        else:
            ax.errorbar(mu, sg, xerr=ci, fmt="o", ms=5, color="C0", ecolor="0.55", elinewidth=1, capsize=2,
                        label="μ* with its 95 % interval")
            ax.plot([0, top * 1.15], [0, top * 1.15], ls="--", lw=0.8, color="0.5", label="σ = μ*")
            minor = []
            for n, x, y in zip(names, mu, sg):
                if x >= 0.03 * top or y >= 0.03 * top:
                    ax.annotate(n, (x, y), xytext=(4, 4), textcoords="offset points", fontsize=8, color="C3")
                else:
                    minor.append(n)
            if minor:
                ax.text(0.98, 0.02, textwrap.fill("< 3 % of the largest: " + ", ".join(minor), 50),
                        transform=ax.transAxes, ha="right", va="bottom", fontsize=7, color="0.35")
            ax.set_xlim(0, 1.15 * top)          # every error bar inside; same scale on both axes
            ax.set_ylim(0, 1.15 * top)
            ax.ticklabel_format(style="sci", scilimits=(-3, 3), axis="both")
            ax.legend(fontsize=7, loc="upper left")
        ax.set_title(_title(meta, metric, False), fontsize=9)
        ax.set_xlabel(f"μ* (mean |elementary effect|) [{u}]", fontsize=8.5)
        ax.set_ylabel(f"σ of elementary effects [{u}]", fontsize=8.5)
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(metrics):]:
        ax.set_visible(False)
    levels = meta.get("morris_levels", MORRIS_LEVELS)
    step = f"{levels / (2 * (levels - 1)):.3g}" if isinstance(levels, int) and levels > 1 else "Δ"
    _suptitle(fig, f"Morris screening ({meta.get('morris_trajectories', '?')} trajectories, {levels} levels): change "
                   f"of the output per step of {step} × the input's range (log10 range for log-uniform inputs, "
                   f"quantile range for normal ones)")
    return _save(fig, path)


def _index_columns(tab: Mapping, names, method: str):
    """Values and (lower, upper) error-bar lengths of S1 and ST: Saltelli's ± half-widths, the polynomial
    chaos' bootstrap percentiles."""
    def col(k):
        return np.array([tab[n].get(k) if tab[n].get(k) is not None else np.nan for n in names], dtype=float)
    out = {}
    for k in ("S1", "ST"):
        v = col(k)
        if method == "pce":
            lo, hi = col(f"{k}_lo"), col(f"{k}_hi")
            err = np.vstack([np.clip(v - lo, 0, None), np.clip(hi - v, 0, None)])
        else:
            h = np.nan_to_num(col(f"{k}_conf"))
            err = np.vstack([h, h])
        out[k] = (v, err)
    return out


def _indices_figure(table: Mapping, meta: Mapping, path: Path, title: str, method: str,
                    notes: Mapping | None = None) -> list[Path]:
    return [_indices_page(table, metrics, meta, p, title, method, notes) for metrics, p in _pages(list(table), path)]


def _indices_page(table: Mapping, metrics: list, meta: Mapping, path: Path, title: str, method: str,
                  notes: Mapping | None = None) -> Path:
    import matplotlib.pyplot as plt
    nr, nc = _grid(len(metrics))
    fig, axes = plt.subplots(nr, nc, figsize=_size(nr, nc, 0.0, 0.6), squeeze=False, layout="constrained")
    for ax, metric in zip(axes.flat, metrics):
        tab = table[metric]
        names = list(tab)
        xs = np.arange(len(names))
        cols = _index_columns(tab, names, method)
        w = 0.38
        for (k, (v, err)), dx, color, label in zip(cols.items(), (-w / 2, w / 2), ("C0", "C1"),
                                                    ("S1 (first order)", "ST (total)")):
            ax.bar(xs + dx, v, w, yerr=err, capsize=1.5, color=color, label=label,
                   error_kw={"elinewidth": 0.8, "ecolor": "0.2"})
        ax.axhline(0, color="k", lw=0.6)
        ax.set_xticks(xs)
        ax.set_xticklabels(names, rotation=60 if len(names) > 6 else 0, ha="right" if len(names) > 6 else "center",
                           fontsize=7.5)
        ax.set_ylabel("share of variance [–]", fontsize=8.5)
        ax.set_xlabel("input parameter", fontsize=8)
        t = _title(meta, metric)
        note = (notes or {}).get(metric)
        if note:
            t += f"\n{note}"
        ax.set_title(t, fontsize=8.5, color="C3" if note and "not trusted" in note else "k")
        tops = [np.nanmax(v + e[1]) if np.isfinite(v).any() else 1.0 for v, e in cols.values()]
        lows = [np.nanmin(v - e[0]) if np.isfinite(v).any() else 0.0 for v, e in cols.values()]
        ax.set_ylim(min(min(lows) - 0.05, -0.05), max(max(tops) + 0.05, 1.05))
        ax.grid(axis="y", alpha=0.3)
        ax.legend(fontsize=7, loc="upper right")
    for ax in axes.flat[len(metrics):]:
        ax.set_visible(False)
    _suptitle(fig, title)
    return _save(fig, path)


def _pce_validation_figure(points, validation: Mapping, meta: Mapping, path: Path) -> Path:
    import matplotlib.pyplot as plt
    metrics = [m for m in validation.get("metrics", {}) if (points["metric"] == m).any()]
    n = len(metrics)
    ncols = min(n, 3) if n > 1 else 1
    nrows = math.ceil(n / ncols)
    side = min(3.3, (MAX_WIDTH_IN - 0.4) / ncols, (MAX_HEIGHT_IN - 0.8) / nrows)     # square panels on a page
    fig, axes = plt.subplots(nrows, ncols, figsize=(max(side * ncols + 0.4, 4.6), side * nrows + 0.8),
                             squeeze=False, layout="constrained")
    for ax, metric in zip(axes.flat, metrics):
        d = points[points["metric"] == metric]
        v = validation["metrics"][metric]
        y, p = d["value"].to_numpy(float), d["loo_prediction"].to_numpy(float)
        ok = v.get("trusted", True)
        ax.plot(y, p, "o", ms=3, color="C0" if ok else "C3", alpha=0.7)
        lo, hi = float(np.nanmin([y.min(), p.min()])), float(np.nanmax([y.max(), p.max()]))
        pad = 0.05 * (hi - lo or 1.0)
        ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], color="0.4", lw=0.8, ls="--")
        ax.set_xlim(lo - pad, hi + pad)
        ax.set_ylim(lo - pad, hi + pad)
        ax.set_aspect("equal")
        u = _unit(meta, metric)
        ax.set_xlabel(f"run [{u}]", fontsize=8)
        ax.set_ylabel(f"leave-one-out prediction [{u}]", fontsize=8)
        ax.ticklabel_format(style="sci", scilimits=(-3, 3), axis="both")
        ax.tick_params(labelsize=7)
        ax.set_title(f"{metric}: error {v['loo_error']:.2g} (target {v.get('target_error', '?'):g})"
                     + ("" if ok else "\nnot trusted: use method sobol"), fontsize=8.5,
                     color="k" if ok else "C3")
        ax.grid(alpha=0.3)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    _suptitle(fig, f"Polynomial chaos validation: each of the {validation.get('runs', '?')} runs against the "
                   f"expansion fitted without it (on the dashed line: predicted exactly)", 9)
    return _save(fig, path)


def plot_sensitivity(result: Mapping, figdir: str | Path) -> list[Path]:
    """``sensitivity_morris.png`` (μ* against σ per metric), ``sensitivity_sobol.png`` (S1 and ST per
    parameter per metric with their 95 % intervals), and for the polynomial chaos ``sensitivity_pce.png``
    (its indices with their bootstrap intervals) and ``sensitivity_pce_validation.png`` (runs against
    leave-one-out predictions; needs ``result["pce_points"]``) in ``figdir``. ``result`` is
    run_sensitivity's result or its summary."""
    import matplotlib
    matplotlib.use("Agg")

    summary, meta = _tables(result)
    figdir = Path(figdir)
    figdir.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []
    if summary.get("morris"):
        paths.extend(_morris_figure(summary["morris"], meta, figdir / "sensitivity_morris.png"))
    if summary.get("sobol"):
        samples = (summary.get("samples") or {}).get("sobol", "?")
        paths.extend(_indices_figure(summary["sobol"], meta, figdir / "sensitivity_sobol.png",
                                     f"Sobol indices by Saltelli's scheme (n = {meta.get('n', '?')}, {samples} runs, "
                                     f"no second order); bars: 95 % confidence intervals", "sobol"))
    if summary.get("pce"):
        val = summary.get("pce_validation") or {}
        notes = {m: (f"validation error {v['loo_error']:.2g}" + ("" if v.get("trusted", True) else ": not trusted"))
                 for m, v in (val.get("metrics") or {}).items()}
        paths.extend(_indices_figure(summary["pce"], meta, figdir / "sensitivity_pce.png",
                                     f"Sobol indices from a sparse polynomial chaos ({val.get('runs', '?')} runs); "
                                     f"bars: 95 % bootstrap intervals over the design", "pce", notes))
        points = result.get("pce_points") if isinstance(result, Mapping) else None
        if points is not None and len(points):
            paths.append(_pce_validation_figure(points, val, meta, figdir / "sensitivity_pce_validation.png"))
    return paths
