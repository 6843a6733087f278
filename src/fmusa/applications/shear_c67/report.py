"""Figures and report.md of the shear-c67 diagnosis (`make diagnose`): what the tool finds against the
authors' two-phase analysis, and what the rate dependence across the tested rates shows.

Every sentence is built from the summary of the data it was given (:func:`~fmusa.applications.shear_c67.
study.summarize`): the specimens, directions, rates and counts are read from it, and each conclusion is
stated only when the numbers support it, with its alternative when they do not.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import pandas as pd

from fmusa.applications.shear_c67.data import DIRECTION_NAMES
from fmusa.diagnose.rank import Thresholds
from fmusa.diagnose.views import natural
from fmusa.files import atomic_write, save_figure

__all__ = ["write_figures", "write_report", "RATE_COLORS"]

#: Colours of the rates, slowest first.
RATE_COLORS = ("tab:blue", "tab:orange", "tab:red", "tab:green", "tab:purple", "tab:brown")
#: The medians that count as agreeing closely with the authors (issue 11: |Δk1| <= 5 %, |Δk2| <= 2 %).
CLOSE = {"k1_rel_diff_median": 0.05, "k2_rel_diff_median": 0.02, "breakpoint_abs_diff_median_mm": 0.1}
#: A record with fewer samples than this is short (the rate's derived time base rests on few points).
SHORT_RECORD = 100
#: Rate trends within this factor count as weak; peak displacements within it as the same.
WEAK_FACTOR = 1.5
SAME_DISPLACEMENT = 1.05

_WORDS = {1: "one", 2: "two", 3: "three", 4: "four", 5: "five", 6: "six", 7: "seven", 8: "eight", 9: "nine",
          10: "ten", 11: "eleven", 12: "twelve"}


def _rate_colors(rates) -> dict[float, str]:
    """One colour per rate, slowest first (1, 10, 100 mm/s: blue, orange, red)."""
    return {r: RATE_COLORS[i % len(RATE_COLORS)] for i, r in enumerate(sorted(set(float(x) for x in rates)))}


def _save(fig, path: Path) -> Path:
    return save_figure(fig, path, dpi=110)


def _fig_bilinear(cmp_: pd.DataFrame, path: Path) -> Path:
    """Our k1, k2 and breakpoint against the authors', per test: colour by rate, marker by direction."""
    import matplotlib.pyplot as plt

    colors = _rate_colors(cmp_["rate_mm_s"])
    fig, axes = plt.subplots(1, 3, figsize=(7.2, 3.4), layout="constrained")
    for ax, ours, theirs, label in ((axes[0], "k1_N_mm", "stiffness_1", "k below the breakpoint [N/mm]"),
                                    (axes[1], "k2_N_mm", "stiffness_2", "k past the breakpoint [N/mm]"),
                                    (axes[2], "bp_mm", "breakpoint_mm", "breakpoint [mm]")):
        for rate, g in cmp_.groupby("rate_mm_s"):
            for direction, marker in (("Ant", "o"), ("Pos", "s")):
                h = g[g["direction"] == direction]
                if h.empty:
                    continue
                ax.scatter(h[theirs], h[ours], color=colors[float(rate)], marker=marker, s=30,
                           label=f"{rate:g} mm/s, {DIRECTION_NAMES.get(direction, direction)}")
        lo = float(np.nanmin(np.r_[cmp_[ours], cmp_[theirs]]))
        hi = float(np.nanmax(np.r_[cmp_[ours], cmp_[theirs]]))
        pad = 0.05 * (hi - lo)
        ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], "k--", lw=1, label="equal")
        ax.set_xlabel(f"authors: {label}")
        ax.set_ylabel(f"fmusa: {label}")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=min(4, len(labels)), frameon=False)
    fig.suptitle("Two-phase fit per test (two continuous lines, free intercept) against the authors' analysis",
                 fontsize=9)
    return _save(fig, path)


def _fig_rates(cmp_: pd.DataFrame, path: Path) -> Path:
    """Stiffness past the breakpoint (ours, the authors') and secant stiffness against the rate, per unit:
    one colour and marker per specimen (distinct for any count), solid anterior, dashed posterior."""
    import matplotlib.pyplot as plt

    from fmusa.report.figures import series_styles

    specimens = sorted(cmp_["specimen"].unique(), key=lambda s: (len(str(s)), str(s)))     # H2 before H10
    style = dict(zip(specimens, series_styles(len(specimens))))
    rows = -(-cmp_.groupby(["specimen", "direction"]).ngroups // 5)          # legend rows (5 columns)
    fig, axes = plt.subplots(1, 3, figsize=(7.2, 2.9 + 0.17 * rows), sharey=True, layout="constrained")
    units = sorted(cmp_.groupby(["specimen", "direction"]), key=lambda kv: (specimens.index(kv[0][0]), kv[0][1]))
    for (spec, direction), g in units:
        g = g.sort_values("rate_mm_s")
        color, marker = style[spec]
        line = "-" if direction == "Ant" else "--"
        face = color if direction == "Ant" else "white"
        kw = dict(color=color, marker=marker, markerfacecolor=face, markersize=5.5, linewidth=1.2, linestyle=line,
                  label=f"{spec} {DIRECTION_NAMES.get(direction, direction)}")
        axes[0].plot(g["rate_mm_s"], g["k2_N_mm"], **kw)
        axes[1].plot(g["rate_mm_s"], g["stiffness_2"], **kw)
        axes[2].plot(g["rate_mm_s"], g["peak_load_N"] / g["peak_disp_mm"], **kw)
    for ax, title in zip(axes, ("fmusa:\nstiffness past the breakpoint", "authors:\nstiffness past the breakpoint",
                                "secant stiffness at the peak\n(peak load / peak displacement)")):
        ax.set_xscale("log")
        ax.set_xlabel("shear rate [mm/s]")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3, which="both")
    axes[0].set_ylabel("stiffness [N/mm]")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside lower center", ncol=min(5, max(1, len(labels))), frameon=False,
               title="unit (filled, solid: anterior; open, dashed: posterior)", title_fontsize=8)
    return _save(fig, path)


def _fig_population(pop: dict, path: Path) -> Path | None:
    """A forest plot per direction and rate: each specimen's k1 with its 95 % interval, the population mean with
    its interval and the range of a new specimen (random effects), and the authors' k1 marked where leaving that
    specimen out put it outside the range predicted from the others."""
    import matplotlib.pyplot as plt

    cells = pop.get("cells") or {}
    if not cells:
        return None
    directions = list(dict.fromkeys(c["direction"] for c in cells.values()))
    rates = sorted({c["rate_mm_s"] for c in cells.values()})
    n_spec = max(len(c["fit"]["specimens"]) for c in cells.values())
    fig, axes = plt.subplots(len(directions), len(rates), figsize=(7.2, 1.6 + 0.24 * n_spec * len(directions)),
                             layout="constrained", sharey="row", squeeze=False)
    for i, direction in enumerate(directions):
        for j, rate in enumerate(rates):
            ax = axes[i][j]
            cell = next((c for c in cells.values() if c["direction"] == direction and c["rate_mm_s"] == rate), None)
            ax.set_title(f"{DIRECTION_NAMES.get(direction, direction)}, {rate:g} mm/s")
            if cell is None:
                ax.set_axis_off()
                continue
            fit = cell["fit"]
            specs = fit["specimens"]
            y = np.arange(len(specs))[::-1]
            lo, hi = fit["prediction"]
            ax.axvspan(lo, hi, color="tab:blue", alpha=0.12, lw=0, label="a new specimen, 95 %")
            ax.axvspan(*fit["mean_ci"], color="tab:blue", alpha=0.35, lw=0, label="population mean, 95 %")
            est = np.array([s["estimate"] for s in specs])
            se = np.array([s["se"] for s in specs])
            ax.errorbar(est, y, xerr=1.96 * se, fmt="o", ms=3, color="k", elinewidth=1, capsize=1.5,
                        label="specimen's k1 (two lines), 95 %")
            loo = {r["name"]: r for r in cell.get("leave_one_out", {}).get("rows", [])}
            for s, yy in zip(specs, y):
                rng = loo.get(s["name"], {}).get("checked_range")
                if rng:
                    ax.plot(rng, [yy - 0.3, yy - 0.3], color="tab:gray", lw=0.8, alpha=0.5,
                            label="range from the others, widened by its test's error")
            out = [(s["name"], yy) for s, yy in zip(specs, y) if s["name"] in loo and not loo[s["name"]]["inside"]]
            if out:
                ax.scatter([loo[n]["reference"] for n, _ in out], [yy for _, yy in out], marker="x", s=30,
                           color="tab:red", zorder=3, label="authors' k1 outside the range from the others")
            ax.set_yticks(y, [s["name"] for s in specs])
            ax.set_xlabel("k1 [N/mm]")
            ax.grid(alpha=0.3, axis="x")
    handles, labels = {}, {}
    for ax in np.ravel(axes):
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    fig.legend(list(handles.values()), list(handles), loc="outside lower center", ncol=2, frameon=False)
    fig.suptitle("k1 over the specimens: random effects (Paule–Mandel) and leave one specimen out", fontsize=9)
    return _save(fig, path)


def write_figures(summary: dict, cmp_: pd.DataFrame, out: Path) -> list[Path]:
    """figures/bilinear_vs_authors.png (our two-phase fit against the authors'),
    figures/rate_dependence.png (stiffness against rate per unit) and figures/population_k1.png (k1 over the
    specimens, where the data have enough of them)."""
    import matplotlib
    matplotlib.use("Agg")

    figdir = out / "figures"
    figdir.mkdir(parents=True, exist_ok=True)
    import matplotlib.pyplot as plt

    # three panels across a page's width: the fonts a journal prints at that size
    with plt.rc_context({"font.size": 8, "axes.labelsize": 8, "axes.titlesize": 8.5, "xtick.labelsize": 7.5,
                         "ytick.labelsize": 7.5, "legend.fontsize": 7.5}):
        figs = [_fig_bilinear(cmp_, figdir / "bilinear_vs_authors.png"),
                _fig_rates(cmp_, figdir / "rate_dependence.png"),
                _fig_population(summary.get("population_k1") or {}, figdir / "population_k1.png")]
    return [f for f in figs if f is not None]


def _f(x, fmt=".3g") -> str:
    try:
        return format(float(x), fmt)
    except (TypeError, ValueError):
        return "n/a"


def _word(n: int) -> str:
    """A count as a word up to twelve (as the report's prose writes it), else as digits."""
    return _WORDS.get(int(n), str(int(n)))


def _and(items: Sequence[str]) -> str:
    """'a', 'a and b', 'a, b and c'."""
    items = list(items)
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " and " + items[-1] if items else ""


def _rates(rates: Iterable) -> str:
    """'1, 10 and 100 mm/s'."""
    return _and([f"{float(r):g}" for r in rates]) + " mm/s"


def _specimens(names: Sequence[str]) -> str:
    """'specimen H10', 'specimens H1–H3', 'specimens H1–H3 and H10–H12': runs of three or more
    consecutive numbers as a range."""
    nums = sorted(int(n[1:]) for n in names)
    parts, run = [], [nums[0]] if nums else []
    for k in nums[1:] + [None]:
        if k is not None and k == run[-1] + 1:
            run.append(k)
            continue
        parts += [f"H{run[0]}–H{run[-1]}"] if len(run) >= 3 else [f"H{x}" for x in run]
        run = [k]
    return ("specimen " if len(nums) == 1 else "specimens ") + _and(parts)


def _unit(key: str) -> str:
    return key.replace("_", " ")


def _param_text(name: str, v: dict) -> str:
    """A fitted parameter in the units of the data (mm, N/mm, N, s; ratios bare), as the unit reports."""
    value, unit = natural(name, v["value"])
    return f"{name} = {_f(value, '.4g')}{' ' + unit if unit else ''}"


def _ci_text(name: str, v: dict) -> str:
    """' [lo, hi]' of a parameter's 95 % interval in the units of the data ('' without one)."""
    ci = v.get("ci95") if isinstance(v, dict) else None
    if not ci or len(ci) != 2:
        return ""
    return f" [{_f(natural(name, ci[0])[0], '.3g')}, {_f(natural(name, ci[1])[0], '.3g')}]"


def _population_section(summary: dict) -> list[str]:
    """The population of k1 over the specimens per direction and rate, and the leave-one-out check."""
    pop = summary.get("population_k1") or {}
    cells = pop.get("cells") or {}
    if not cells:
        return []
    L = ["## The population: k1 over the specimens\n",
         f"Each specimen's k1 (two lines, free intercept) with its standard error, combined by {pop['method']}. "
         "τ is the spread between specimens beyond each test's own uncertainty; the shrinkage is how far a "
         "specimen's estimate moves towards the mean (0: its own test decides, 1: the population does). "
         "Leave one out: the range of a new specimen predicted from the other specimens, and whether the "
         "left-out specimen's k1 of the authors' analysis falls inside it, widened by that test's own standard "
         "error (their k1 is a fit to the same test, so it carries the test's error as well as the "
         "specimen's).\n",
         "| direction | rate [mm/s] | specimens | mean k1 [N/mm] | τ between specimens [N/mm] | SD of the "
         "estimates [N/mm] | a new specimen, 95 % [N/mm] | largest shrinkage | authors' k1 inside (left out) |",
         "|---|---|---|---|---|---|---|---|---|"]
    for c in cells.values():
        f, loo = c["fit"], c["leave_one_out"]
        miss = [r["name"] for r in loo["rows"] if not r["inside"]]
        L.append(f"| {DIRECTION_NAMES.get(c['direction'], c['direction'])} | {c['rate_mm_s']:g} | {f['k']} | "
                 f"{_f(f['mean'], '.4g')} ± {_f(f['mean_se'], '.2g')} | {_f(f['tau'], '.3g')} | {_f(f['sd'], '.3g')} | "
                 f"{_f(f['prediction'][0], '.3g')} to {_f(f['prediction'][1], '.3g')} | "
                 f"{_f(max(s['shrinkage'] for s in f['specimens']), '.2f')} | {loo['inside']} of {loo['tested']}"
                 + (f" (outside: {', '.join(miss)})" if miss else "") + " |")
    L.append("")
    units = summary.get("population_units") or {}
    for d, params in units.items():
        c = params.get("c_y")
        if not c or not c.get("k"):
            continue
        lo, hi = c["prediction"]
        L.append(f"The diagnosed units' final models, {DIRECTION_NAMES.get(d, d)}: stiffness c {_f(c['mean'] / 1e3, '.4g')} "
                 f"± {_f(c['tau'] / 1e3, '.3g')} N/mm between specimens over {c['k']} specimens"
                 + (f", a new specimen {_f(lo / 1e3, '.3g')} to {_f(hi / 1e3, '.3g')} N/mm" if math.isfinite(lo)
                    else f" ({c.get('note', '')})")
                 + "; per specimen (estimate → shrunk, shrinkage): "
                 + ", ".join(f"{x['name']} {_f(x['estimate'] / 1e3, '.4g')} → {_f(x['shrunk'] / 1e3, '.4g')} "
                             f"({_f(x['shrinkage'], '.2f')})" for x in c["specimens"]) + ".\n")
    L.append(f"In all, the authors' k1 of {pop['inside']} of {pop['tested']} left-out specimen tests "
             f"({100 * pop['share']:.0f} %) falls inside the range predicted from the other specimens, widened by its test's own error (nominal 95 %).\n")
    return L


def _bands_section(summary: dict) -> list[str]:
    """Each rate predicted from the unit's other rates with a 95 % band: the share of its samples inside, the
    half-width against the peak force, and the AR(1) band beside it."""
    bands = {k: v for k, v in (summary.get("prediction_bands") or {}).items() if v}
    if not bands:
        return []
    rows = [r for rs in bands.values() for r in rs]
    L = ["## Prediction bands: each rate predicted from the other rates\n",
         "The two-phase elastic curve with damping, fitted to two rates of a unit, predicts the third with a "
         f"95 % band: {rows[0]['method']}. A share near 95 % is a band that holds; a share far below says the model "
         "does not carry over to that rate as it did elsewhere. Beside it, the band from the parameters' AR(1) "
         "sandwich covariance and the residual variance.\n",
         "| unit | predicted rate [mm/s] | from [mm/s] | samples inside the 95 % band | half-width [N] (of the peak) "
         "| within the unit / across units [N] | held-out RMSE [N] | AR(1) band: inside, median half-width [N] |",
         "|---|---|---|---|---|---|---|---|"]
    for key, rs in bands.items():
        for r in rs:
            L.append(f"| {_unit(key)} | {r['rate_mm_s']:g} | {', '.join(f'{x:g}' for x in r.get('trained_on') or [])} | "
                     f"{100 * r['share_inside']:.0f} % | {_f(r['half_width_N'], '.3g')} "
                     f"({100 * r['half_width_rel_peak']:.0f} %) | {_f(r['within_half_width_N'], '.3g')} / "
                     f"{_f(r.get('population_half_width_N', float('nan')), '.3g')} | {_f(r['heldout_rmse_N'], '.3g')} | "
                     f"{100 * r['ar1_share_inside']:.0f} %, {_f(r['ar1_half_width_median_N'], '.3g')} |")
    L.append("")
    share = np.array([r["share_inside"] for r in rows])
    rel = np.array([r["half_width_rel_peak"] for r in rows])
    ar1 = np.array([r["ar1_share_inside"] for r in rows])
    L.append(f"Over the {len(rows)} predicted rates: median share inside {100 * float(np.median(share)):.0f} % "
             f"({int(np.sum(share >= 0.9))} of {len(rows)} at 90 % or more; all samples pooled "
             f"{100 * float(np.average(share, weights=[r['points'] for r in rows])):.0f} %), median half-width "
             f"{100 * float(np.median(rel)):.0f} % of the peak force. The AR(1) band: median share "
             f"{100 * float(np.median(ar1)):.0f} % ({int(np.sum(ar1 >= 0.9))} of {len(rows)} at 90 % or more), "
             f"median half-width {_f(float(np.median([r['ar1_half_width_median_N'] for r in rows])), '.3g')} N.\n")
    parts = []
    for label, sh, hw in (("within the unit", "within_share_inside", "within_half_width_N"),
                          ("across the units", "population_share_inside", "population_half_width_N")):
        ok = [r for r in rows if math.isfinite(r.get(hw, float("nan")))]
        if ok:
            x = np.array([r[sh] for r in ok])
            parts.append(f"{label} alone, {int(np.sum(x >= 0.9))} of {len(ok)} rates at 90 % or more (pooled "
                         f"{100 * float(np.average(x, weights=[r['points'] for r in ok])):.0f} %), median half-width "
                         f"{100 * float(np.median([r[hw] / r['peak_N'] for r in ok])):.0f} % of the peak")
    if parts:
        L.append("Each term of the band alone: " + "; ".join(parts) + ".\n")
    for rate in sorted({r["rate_mm_s"] for r in rows}):
        at = [r for r in rows if r["rate_mm_s"] == rate]
        L.append(f"- {rate:g} mm/s predicted from the other rates: median share inside "
                 f"{100 * float(np.median([r['share_inside'] for r in at])):.0f} % over {len(at)} units, median "
                 f"half-width {100 * float(np.median([r['half_width_rel_peak'] for r in at])):.0f} % of the peak.")
    L.append("")
    return L


def _tests_per_unit(summary: dict) -> int | None:
    """The number of tests (rates) of every unit when all have the same, else None."""
    counts = {g["tests"] for g in summary["groups"].values()}
    return counts.pop() if len(counts) == 1 else None


# ============================================================================ report sections
def _intro(summary: dict) -> list[str]:
    d = summary["data"]
    root = d.get("root", "")
    dirs = _and([DIRECTION_NAMES.get(x, x) for x in d.get("directions", [])])
    prov = f"; see {d['provenance']}" if d.get("provenance") else ""
    return [f"# Diagnosis of the C6/C7 shear tests ({root})\n",
            f"Measured data ({_specimens(d['specimens'])}, {dirs} shear at {_rates(d['rates_mm_s'])} under "
            f"displacement control{prov}). The spinal unit is seen as one bushing along the shear axis: the FMU's "
            f"axial degree of freedom is the shear displacement disp_x, which drives the model, and the model "
            f"predicts Fx. Time is derived from the nominal rate (uniform sampling assumed); each record is "
            f"block-averaged to at most {d['max_points']} samples and its displacement shifted to start at 0 "
            f"(the model starts at rest).\n"] + _diagnosed_text(d)


def _diagnosed_text(d: dict) -> list[str]:
    """Which specimens went through the FMU diagnosis, when not all of them did."""
    chosen = d.get("diagnosed_specimens")
    if not chosen or len(chosen) == len(d.get("specimens", [])):
        return []
    first = "the first specimen" if len(chosen) == 1 else f"the first {_word(len(chosen))}"
    return [f"Diagnosed through the FMU: {_specimens(chosen)} ({d.get('diagnosed_tests', 'n/a')} tests; {first} of "
            f"the {_word(len(d['specimens']))} specimens; `--all` diagnoses every one). The two-phase comparison "
            f"with the authors and the rate table cover all {d['tests']} tests.\n"]


def _units_heading(k: int | None) -> list[str]:
    """The section title and how the held-out score was cut, from the number of tests per unit."""
    if k is None:
        return ["## What the tool finds per specimen and direction (all rates of a unit fitted jointly)\n",
                "Held-out score: each rate predicted by the model fitted to the unit's other rates (a unit with "
                "one test: 4 contiguous blocks in time, each predicted from the rest).\n"]
    if k == 1:
        return ["## What the tool finds per specimen and direction (one test per unit)\n",
                "Held-out score: 4 contiguous blocks in time of each test, each predicted by the model fitted "
                "to the rest.\n"]
    if k == 2:   # diagnose keeps both rates in every training set (calibrate.heldout_masks)
        return ["## What the tool finds per specimen and direction (two rates fitted jointly)\n",
                "Held-out score: 4 contiguous blocks in time of both tests, each predicted by the model fitted "
                "to the rest of both.\n"]
    return [f"## What the tool finds per specimen and direction ({_word(k)} rates fitted jointly)\n",
            f"Held-out score: each rate predicted by the model fitted to the other {_word(k - 1)}.\n"]


def _units_section(summary: dict) -> list[str]:
    groups = summary["groups"]
    n = len(groups)
    L = _units_heading(_tests_per_unit(summary))
    L.append("| unit | final model (first effect named) | held-out RMSE ratio of the first | ΔBIC of the first | "
             "final model's effect parameters [95 %] | cannot be told from | left in the residuals of the final model |")
    L.append("|---|---|---|---|---|---|---|")
    for k, g in groups.items():
        fin = g.get("final") or {}
        ps = "; ".join(_param_text(nm, v) + _ci_text(nm, v) for nm, v in (fin.get("params") or g["effect_params"]).items())
        model = " + ".join(fin.get("effects") or []) or g["effect"]
        L.append(f"| {_unit(k)} | **{model}** | {_f(g['gain']['heldout_rmse_ratio'])} | "
                 f"{_f(g['gain']['delta_bic'], '.1f')} | {ps or '–'} | {', '.join(g['indistinguishable']) or '–'} | "
                 f"{g['leftover'] or '–'} |")
    L.append("")
    methods = sorted({(g.get("final") or {}).get("interval_method") for g in groups.values()} - {None})
    if methods:
        L.append(f"Intervals: {'; '.join(methods)} (the method of each unit is in its report).\n")
    removed = [(k, r) for k, g in groups.items() for r in g.get("chain_removed") or []]
    if removed:
        L.append("Steps of the chains the checks removed (a parameter the test cannot support, an effect the "
                 "protocol cannot identify, or an optimiser failure):\n")
        for k, r in removed:
            L.append(f"- {_unit(k)}, step {r['step']}, `{r['effect']}`: {r['reason']}.")
        L.append("")
    refitted = [(k, r) for k, g in groups.items() for r in g.get("chain_refitted") or []]
    if refitted:
        L.append("Steps of the chains kept after a refit (the first fit was worse than the model it extends):\n")
        for k, r in refitted:
            L.append(f"- {_unit(k)}, step {r['step']}, `{r['effect']}`: {r['text']}.")
        L.append("")
    n_cand = max(len(g["ranking"]) for g in groups.values())
    cands = {1: "the one candidate", 2: "both candidates"}.get(n_cand, f"all {_word(n_cand)} candidates")
    L.append(f"Every group's own report (figures, ranking of {cands}, residual tests) is in its folder, e.g. "
             f"`{next(iter(groups))}/report.md`.\n")
    counts = pd.Series([g["effect"] for g in groups.values()]).value_counts()
    L.append("Effects named: " + ", ".join(f"{e} ({c} of {n})" for e, c in counts.items()) + ".\n")
    ratios: dict[str, list[float]] = {}
    for g in groups.values():
        for r in g["ranking"]:
            ratios.setdefault(r["effect"], []).append(r["heldout_rmse_ratio"])
    over = "in the one unit" if n == 1 else f"over the {_word(n)} units"
    L.append(f"Median held-out RMSE ratio of each candidate against the baseline {over}: " +
             ", ".join(f"{e} {np.nanmedian(v):.3f}"
                       for e, v in sorted(ratios.items(), key=lambda kv: np.nanmedian(kv[1]))) + ".\n")
    L.append(_protocol_paragraph(summary))
    return L


def _bend_text(groups: dict) -> str:
    """What the named elastic bend says about yield, which monotonic loading cannot tell from a softening bend."""
    ratios = [g["effect_params"]["nl_ratio"]["value"] for g in groups.values()
              if g["effect"] == "nonlinear_stiffness"]
    if not ratios:
        return "is not named. "
    yield_sig = sum(any(r["effect"] == "yield_softening" and r["significant"] for r in g["ranking"])
                    for g in groups.values())
    stiffen = sum(r > 1.0 for r in ratios)
    span = f"nl_ratio {min(ratios):.2f}–{max(ratios):.2f}"
    if stiffen == len(ratios) and not yield_sig:
        return (f"stiffens in {stiffen} of {len(ratios)} units where it is named ({span}): a yield cannot produce "
                f"that, and its fit indeed gains nothing, so these data rule yield out; what they cannot rule out "
                f"is a softening stage beyond the peak, which only a test to failure or an unloading would show. ")
    out = (f"stiffens in {stiffen} and softens in {len(ratios) - stiffen} of the {len(ratios)} units where it is "
           f"named ({span}): a yield can produce only the softening bends, and these tests cannot tell those "
           f"from an elastic softening")
    if yield_sig:
        out += f"; `yield_softening` itself is significant in {yield_sig} of {len(groups)} units"
    return out + ". "


def _relaxation_text(summary: dict) -> str:
    groups = summary["groups"]
    several = sum(g["protocol"]["several_rates"] for g in groups.values())
    if not several:
        return ("Relaxation needs a hold or several rates, and these tests have neither: it cannot be told "
                "from an elastic bend here.")
    k = _tests_per_unit(summary)
    if several == len(groups):
        return f"Relaxation needs a hold or several rates: here the {_word(k)} rates." if k else \
            "Relaxation needs a hold or several rates: here the several rates of each unit."
    return f"Relaxation needs a hold or several rates: here the several rates of {several} of {len(groups)} units."


def _protocol_paragraph(summary: dict) -> str:
    """What the protocol (unloading, holds, rates: read from the tests) can and cannot separate."""
    groups = summary["groups"]
    n_tests = (summary["data"].get("diagnosed_tests") or summary["data"].get("tests")
               or sum(g["tests"] for g in groups.values()))
    unload = sum(g["protocol"]["unloading"] for g in groups.values())
    hold = sum(g["protocol"]["hold"] for g in groups.values())
    head = "**What these tests can and cannot tell.** "
    if unload or hold:
        return (head + f"{unload} of {len(groups)} units unload after the peak and {hold} hold the displacement. "
                "Unloading separates a softening elastic bend from a yielding interface (an elastic curve retraces, "
                "a yield leaves a permanent set) and a reversal separates friction from a sensor offset; where the "
                "tests lack them, each unit's report names the look-alikes they cannot separate. "
                + _relaxation_text(summary) + "\n")
    tests = (f"All {n_tests} tests load monotonically to the peak and stop" if n_tests != 1
             else "The one test loads monotonically to the peak and stops")
    return (head + tests + ": there is no hold and no unloading. A *softening* elastic bend and a yielding "
            "interface (`yield_softening`) give the same loading curve, and only unloading separates them (an "
            "elastic curve retraces, a yield leaves a permanent set). Here the bend " + _bend_text(groups)
            + "Friction and a sensor offset add the same constant force during monotonic loading; a reversal "
            "separates them. " + _relaxation_text(summary) + "\n")


def _split_table(part: dict) -> list[str]:
    L = ["| rate [mm/s] | tests | median \\|Δk1\\| | median \\|Δk2\\| | median \\|Δbreakpoint\\| [mm] | samples |",
         "|---|---|---|---|---|---|"]
    for rate, v in part["by_rate"].items():
        L.append(f"| {rate} | {v['tests']} | {100 * v['k1_rel_diff_median']:.2f} % | "
                 f"{100 * v['k2_rel_diff_median']:.2f} % | {v['breakpoint_abs_diff_median_mm']:.4f} | "
                 f"{v['points_min']}–{v['points_max']} |")
    return L + [""]


def _agreement_text(by_rate: dict) -> str:
    """Where the two-line fit agrees with the authors (the CLOSE medians)."""
    if not by_rate:
        return ""
    close = [r for r, v in by_rate.items() if all(v[k] < lim for k, lim in CLOSE.items())]
    crit = (f"(medians: first stiffness within {100 * CLOSE['k1_rel_diff_median']:.0f} %, second within "
            f"{100 * CLOSE['k2_rel_diff_median']:.0f} %, breakpoint within "
            f"{CLOSE['breakpoint_abs_diff_median_mm']:g} mm)")
    if not close:
        return f"At no rate do the two analyses agree closely {crit}.\n"
    others = [r for r in by_rate if r not in close]
    return (f"At {_rates(close)} the two analyses agree closely {crit}"
            + (f"; at {_rates(others)} they do not" if others else "") + ".\n")


#: A first phase passed at a mean rate below this fraction of the whole record's: the drive is still
#: accelerating through it.
ACCELERATING = 0.8


def _model_text(by_rate: dict) -> str:
    """fmusa's two-phase model through the FMU against the authors, where it was fitted: why its k1 differs,
    and what the damping would do to it (the model is compared with d_y held at 0)."""
    rows = {r: v for r, v in by_rate.items() if v.get("model_tests")}
    if not rows:
        return ""
    n = sum(v["model_tests"] for v in rows.values())
    per = ", ".join(f"{100 * v['model_k1_rel_diff_median']:.1f} % at {r} mm/s" for r, v in rows.items())
    per2 = ", ".join(f"{100 * v['model_k2_rel_diff_median']:.1f} %" for v in rows.values())
    lower = sum(v["model_k1_diff_median_sign"] < 0 for v in rows.values())
    out = (f"fmusa's own two-phase elastic model through the FMU (fitted to {n} tests, block-averaged, interface "
           f"damping d_y held at 0) is not the authors' analysis: it is a spring that starts unloaded at the "
           f"first sample, so its first phase cannot take the free intercept with which the authors' first line "
           f"absorbs a toe at the start of a record, and its breakpoint is wherever its own least squares put it. "
           f"Its median |Δk1| against the authors is {per} (|Δk2| {per2}), its k1 lower at {lower} of {len(rows)} "
           f"rates; on the same tests the two lines with a free intercept give the medians above.")
    toe = {r: v for r, v in rows.items() if v.get("toe_k1_rel_diff_median") is not None}
    if toe:
        t1 = ", ".join(f"{100 * v['toe_k1_rel_diff_median']:.2f} % at {r} mm/s" for r, v in toe.items())
        t2 = ", ".join(f"{100 * v['toe_k2_rel_diff_median']:.2f} %" for v in toe.values())
        out += (f" The chain's model (issue 22: the bend with a force offset that frees the first phase's start, "
                f"d_y held at 0, started at the authors' rule) gives a median |Δk1| of {t1} (|Δk2| {t2}).")
    return out + _damping_text(rows, by_rate) + "\n"


def _damping_text(rows: dict, by_rate: dict) -> str:
    """Why d_y is held at 0: where the damping, fitted too, takes the first phase, and what in the records
    lets it (the drive still accelerating through the first phase)."""
    rows = {r: v for r, v in rows.items() if v.get("damped_tests")}
    if not rows:
        return ""
    per = ", ".join(f"{100 * v['damped_k1_rel_diff_median']:.1f} %" for v in rows.values())
    out = f" With d_y fitted as well the median |Δk1| is {per} at the same rates"
    taken = {r: v for r, v in rows.items() if v.get("damping_carried")}
    if not taken:
        return out + ", and in no test does the damping carry half of the model's force at its breakpoint."
    out += ". "
    accelerating = False
    for r, v in taken.items():
        c = v["damping_carried"]
        out += (f"At {r} mm/s the damping force d_y·v then carries more than half of the model's force at its "
                f"breakpoint in {v['damping_carries']} of {v['damped_tests']} tests "
                f"(d_y {_range(c['d_N_s_mm'], '.3f')} N·s/mm; c_y {_range(c['k1_N_mm'], '.1f')} N/mm against "
                f"the authors' {_range(c['authors_k1_N_mm'], '.1f')} N/mm; median RMSE "
                f"{c['damped_rmse_median_N']:.2f} N against {c['model_rmse_median_N']:.2f} N with d_y held at 0)")
        ratio = c["phase1_rate_ratio_median"]
        if ratio < ACCELERATING:
            accelerating = True
            whole = ", ".join(f"{w['phase1_rate_ratio_median']:.2f} at {q} mm/s" for q, w in by_rate.items())
            out += (f": in those tests the drive is still accelerating through the first phase, passing it at a "
                    f"median {ratio:.2f} of its mean rate over the whole record (time from uniform sampling; "
                    f"median of all tests {whole})")
        out += ". "
    if accelerating:
        out += ("So d_y·v rises with the displacement as a spring force would, and the least squares give it the "
                "first phase. ")
    return out + ("The authors' stiffness is the slope of the whole force against the displacement; with damping "
                  "in the model c_y is only part of that slope wherever the velocity changes along the phase, so "
                  "the comparison holds d_y at 0.")


def _range(lo_hi, fmt: str) -> str:
    lo, hi = lo_hi
    return f"{lo:{fmt}}" if f"{lo:{fmt}}" == f"{hi:{fmt}}" else f"{lo:{fmt}}–{hi:{fmt}}"


def _first_minimum_text(m: dict) -> str:
    """In how many tests the first local minimum is not the global one, and which one the authors took."""
    n = m.get("global_elsewhere")
    if n is None:
        return ""
    if n == 0:
        return "In every test it is also the global minimum. "
    k = m.get("authors_at_first", 0)
    return (f"In {n} test{'s' if n != 1 else ''} the global minimum lies more than 0.05 mm away; the authors' "
            f"breakpoint is nearer the first minimum in {k} of {'them' if n != 1 else 'it'}. ")


def _bilinear_section(summary: dict, cmp_: pd.DataFrame) -> list[str]:
    L = ["## Two-phase fit per test against the authors' breakpoint analysis\n"]
    b = summary["bilinear"]
    m = summary.get("bilinear_method", {})
    L.append(f"The comparison uses a direct least-squares fit, not the FMU: two continuous straight lines of the "
             f"raw force Fx against the raw displacement disp_x, every sample, free intercept, which is the "
             f"authors' method; the breakpoint is the {m.get('breakpoint_rule', 'least-squares one')}. "
             + _first_minimum_text(m) + f"Over all {len(cmp_)} tests: median "
             f"|relative difference| of the first stiffness {100 * b['k1_rel_diff_median']:.2f} %, of the second "
             f"{100 * b['k2_rel_diff_median']:.2f} %, median |breakpoint difference| "
             f"{b['breakpoint_abs_diff_median_mm']:.4f} mm (raw displacement frame).\n")
    parts = summary.get("bilinear_by_split", {})
    here = [f"{_specimens(parts['tuning']['specimens'])} {'are' if len(parts['tuning']['specimens']) > 1 else 'is'} "
            f"among those it was chosen on (tuning)"] if "tuning" in parts else []
    here += [f"{_specimens(parts['held_out']['specimens'])} {'were' if len(parts['held_out']['specimens']) > 1 else 'was'} "
             f"not used to choose it (held out)"] if "held_out" in parts else []
    if here:
        L.append("The breakpoint rule was chosen on a fixed set of specimens of the data set: " + "; ".join(here)
                 + ".\n")
    names = {"held_out": "Held-out specimens", "tuning": "Tuning specimens"}
    for key in ("held_out", "tuning"):
        if key in parts:
            L.append(f"**{names[key]}**: {_specimens(parts[key]['specimens'])}.\n")
            L += _split_table(parts[key])
    if "held_out" not in parts:
        L.append("None of these specimens was held out from choosing the breakpoint rule: the numbers above show "
                 "the fit on data it was tuned on.\n")
    L.append(_agreement_text(summary["bilinear_by_rate"]))
    L.append(_model_text(summary["bilinear_by_rate"]))
    L.append("| test | rate [mm/s] | split | authors k1 / k2 [N/mm] | two-line k1 / k2 [N/mm] | FMU model k1 / k2 "
             "[N/mm] (k1 with d_y fitted) | authors breakpoint [mm] | two-line breakpoint [mm] | RMSE [N] (linear) |")
    L.append("|---|---|---|---|---|---|---|---|---|")
    for _, r in cmp_.iterrows():
        mk = (f"{_f(r.get('model_k1_N_mm'), '.1f')} / {_f(r.get('model_k2_N_mm'), '.1f')}"
              if pd.notna(r.get("model_k1_N_mm", np.nan)) else "–")
        if pd.notna(r.get("damped_k1_N_mm", np.nan)):
            mk += f" ({_f(r['damped_k1_N_mm'], '.1f')})"
        L.append(f"| {r['specimen']} {r['direction']} | {r['rate_mm_s']:g} | {str(r.get('split', '')).replace('_', ' ')} | "
                 f"{_f(r['stiffness_1'], '.1f')} / {_f(r['stiffness_2'], '.1f')} | {_f(r['k1_N_mm'], '.1f')} / "
                 f"{_f(r['k2_N_mm'], '.1f')} | {mk} | {_f(r['breakpoint_mm'], '.3f')} | {_f(r['bp_mm'], '.3f')} | "
                 f"{_f(r['rmse_N'], '.2f')} ({_f(r['linear_rmse_N'], '.2f')}) |")
    L.append("")
    return L


def _span(rt: pd.DataFrame) -> tuple[str, str] | None:
    """(slowest, fastest) rate text when every unit spans the same rates, else None."""
    pairs = set(zip(rt["rate_low_mm_s"], rt["rate_high_mm_s"]))
    if len(pairs) != 1:
        return None
    lo, hi = pairs.pop()
    return f"{lo:g}", f"{hi:g}"


def _maxwell_table(summary: dict, th: Thresholds) -> tuple[list[str], list[str]]:
    """The direct test of a Maxwell branch per unit; the units where it predicts an unseen rate better."""
    rm = summary.get("rate_models", {})
    if not rm:
        return [], []
    k = _tests_per_unit(summary)
    how = ("fitted to all rates of a unit, each rate predicted from the others" if k is None else
           "fitted to the one test of a unit, held-out blocks in time" if k == 1 else
           f"fitted to all {_word(k)} rates of a unit, each rate predicted from the other {_word(k - 1)}")
    L = [f"Direct test: a Maxwell branch added to the two-phase elastic curve, {how}:\n",
         "| unit | held-out RMSE two-phase [N] | + Maxwell [N] | ratio | ΔBIC | ve_k [N/mm] | ve_tau [s] |",
         "|---|---|---|---|---|---|---|"]
    for key, v in rm.items():
        m = v["two_phase_maxwell"]
        L.append(f"| {_unit(key)} | {_f(v['two_phase']['heldout_rmse'])} | {_f(m['heldout_rmse'])} | "
                 f"{_f(v['heldout_ratio'])} | {_f(v['delta_bic'], '.1f')} | {_f(m['ve_k_N_mm'])} | {_f(m['ve_tau_s'])} |")
    L.append("")
    better = [key for key, v in rm.items() if v["heldout_ratio"] < th.heldout_ratio and v["delta_bic"] < th.delta_bic]
    L.append(f"The Maxwell branch improves the prediction of an unseen rate significantly (held-out ratio "
             f"< {th.heldout_ratio:g} and ΔBIC < {th.delta_bic:g}) in {len(better)} of {len(rm)} units"
             + (f" ({', '.join(_unit(b) for b in better)})" if better else "") + ".\n")
    return L, better


def _rates_conclusion(summary: dict, rt: pd.DataFrame, n_better: int) -> str:
    """What the rates show, stated as strongly as the numbers allow."""
    span = _span(rt)
    k2 = rt["k2_ratio_ours"]
    up = int((k2 > 1.0).sum())
    n_tested = len(summary.get("rate_models", {})) or len(rt)
    over = f"Over a {float(span[1]) / float(span[0]):g}-fold increase of the rate" if span else \
        "From the slowest to the fastest test of each unit"
    peaks = (", but the tests stop at different displacements, so the peak loads are not like for like"
             if rt["peak_disp_spread"].max() > SAME_DISPLACEMENT else ", the tests stopping at about the same "
             "displacement")
    out = (f"**What the rates show.** {over} the stiffness past the breakpoint rises in {up} of {len(rt)} units, "
           f"by a median factor {k2.median():.2f} (authors' analysis: {rt['k2_ratio_authors'].median():.2f}); the "
           f"peak load changes by a median factor {rt['peak_ratio'].median():.2f}{peaks}. A rate-dependent "
           f"(viscoelastic) interface would show as a Maxwell branch that predicts an unseen rate; it does so in "
           f"{n_better} of the {n_tested} units where it was tested.")
    if span:
        decades = math.log10(float(span[1]) / float(span[0]))
        width = (f"over {_word(round(decades))} decade{'s' if round(decades) != 1 else ''} of rate"
                 if abs(decades - round(decades)) < 1e-9 and decades >= 1 else "over the tested rates")
        rates = f"shear rates of {span[0]}–{span[1]} mm/s"
    else:
        width, rates = "over the tested rates", "the tested shear rates"
    fastest = summary["bilinear_by_rate"].get(span[1] if span else "", {})
    caveat = (f"the {span[1]} mm/s records are short ({fastest['points_min']}–{fastest['points_max']} samples) and "
              f"their time base is derived from the nominal rate" if fastest and
              fastest["points_max"] < SHORT_RECORD else "the time base is derived from the nominal rate")
    trend = f"stiffness past the breakpoint {k2.min():.2f}–{k2.max():.2f}× {width}"
    if 2 * n_better > n_tested:
        return out + (f" The rate dependence here is viscoelastic ({trend}): a Maxwell branch captures it in "
                      f"most units, so a rate-independent bushing is not adequate for {rates}; with the caveat "
                      f"that {caveat}.\n")
    if max(k2.max(), 1 / k2.min()) > WEAK_FACTOR:
        return out + (f" The stiffness does change with the rate ({trend}), but a single Maxwell branch does not "
                      f"capture it in most units: the rate dependence is not of the Maxwell kind, or the records "
                      f"cannot resolve it; with the caveat that {caveat}.\n")
    return out + (f" The rate dependence in these tests is therefore weak ({trend}) and a single Maxwell branch "
                  f"does not capture it in most units: a rate-independent two-phase elastic bushing is an adequate "
                  f"model for {rates} here, with the caveat that {caveat}.\n")


def _rate_section(summary: dict) -> list[str]:
    rates = summary["data"].get("rates_mm_s", [])
    rt = pd.DataFrame(summary["rate"])
    if rt.empty:
        return ["## Rate dependence\n",
                "Every unit was tested at one rate only: these data say nothing about rate dependence.\n"]
    L = [f"## Rate dependence ({' → '.join(f'{r:g}' for r in rates)} mm/s)\n"]
    span = _span(rt)
    hi, lo = (span[1], span[0]) if span else ("fastest", "slowest")
    L.append(f"| unit | fmusa k2({hi})/k2({lo}) | authors k2({hi})/k2({lo}) | peak load({hi})/({lo}) | "
             f"linear stiffness({hi})/({lo}) |")
    L.append("|---|---|---|---|---|")
    for _, r in rt.iterrows():
        L.append(f"| {r['specimen']} {r['direction']} | {_f(r['k2_ratio_ours'])} | {_f(r['k2_ratio_authors'])} | "
                 f"{_f(r['peak_ratio'])} | {_f(r['linear_k_ratio'])} |")
    L.append("")
    table, better = _maxwell_table(summary, Thresholds())
    L += table
    multi = {f"{s}_{d}" for s, d in zip(rt["specimen"], rt["direction"])}
    L.append(_rates_conclusion(summary, rt, sum(b in multi for b in better)))
    return L


def write_report(summary: dict, cmp_: pd.DataFrame, out: Path, figs: list[Path]) -> Path:
    """out/report.md: the data, the diagnosis per unit, the comparison with the authors, the rates."""
    L = (_intro(summary) + _units_section(summary) + _population_section(summary) + _bands_section(summary)
         + _bilinear_section(summary, cmp_)
         + _rate_section(summary))
    for p in figs:
        L.append(f"![{p.stem}](figures/{p.name})\n")
    path = Path(out) / "report.md"
    atomic_write(path, "\n".join(L))
    return path
