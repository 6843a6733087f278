"""Figures and report.md of the shear-c67 diagnosis (`make diagnose`): what the tool finds against the
authors' two-phase analysis, and what the rate dependence across 1, 10 and 100 mm/s shows."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

RATE_COLORS = {1.0: "tab:blue", 10.0: "tab:orange", 100.0: "tab:red"}


def write_figures(summary: dict, cmp_: pd.DataFrame, out: Path) -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figdir = out / "figures"
    figdir.mkdir(parents=True, exist_ok=True)
    paths = []

    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    for ax, ours, theirs, label in ((axes[0], "k1_N_mm", "stiffness_1", "stiffness below the breakpoint [N/mm]"),
                                    (axes[1], "k2_N_mm", "stiffness_2", "stiffness past the breakpoint [N/mm]"),
                                    (axes[2], "bp_mm", "breakpoint_mm", "breakpoint [mm]")):
        for rate, g in cmp_.groupby("rate_mm_s"):
            for direction, marker in (("Ant", "o"), ("Pos", "s")):
                h = g[g["direction"] == direction]
                ax.scatter(h[theirs], h[ours], c=RATE_COLORS.get(rate, "k"), marker=marker, s=36,
                           label=f"{rate:g} mm/s, {direction}")
        lo = float(np.nanmin(np.r_[cmp_[ours], cmp_[theirs]]))
        hi = float(np.nanmax(np.r_[cmp_[ours], cmp_[theirs]]))
        pad = 0.05 * (hi - lo)
        ax.plot([lo - pad, hi + pad], [lo - pad, hi + pad], "k--", lw=1, label="equal")
        ax.set_xlabel(f"authors: {label}")
        ax.set_ylabel(f"fmusa: {label}")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, loc="upper left")
    fig.suptitle("Two-phase fit per test: fmusa (FMU, continuous bilinear) against the authors' breakpoint analysis")
    fig.tight_layout()
    p = figdir / "bilinear_vs_authors.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)

    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2))
    for (spec, direction), g in cmp_.groupby(["specimen", "direction"]):
        g = g.sort_values("rate_mm_s")
        style = "-" if direction == "Ant" else "--"
        axes[0].plot(g["rate_mm_s"], g["k2_N_mm"], style, marker="o", label=f"{spec} {direction}")
        axes[1].plot(g["rate_mm_s"], g["stiffness_2"], style, marker="s", label=f"{spec} {direction}")
        axes[2].plot(g["rate_mm_s"], g["peak_load_N"] / g["peak_disp_mm"], style, marker="^",
                     label=f"{spec} {direction}")
    for ax, title in zip(axes, ("fmusa: stiffness past the breakpoint", "authors: stiffness_2",
                                "secant stiffness at the peak\n(peak load / peak displacement)")):
        ax.set_xscale("log")
        ax.set_xlabel("shear rate [mm/s]")
        ax.set_ylabel("stiffness [N/mm]")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3, which="both")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    p = figdir / "rate_dependence.png"
    fig.savefig(p, dpi=110)
    plt.close(fig)
    paths.append(p)
    return paths


def _f(x, fmt=".3g") -> str:
    try:
        return format(float(x), fmt)
    except (TypeError, ValueError):
        return "n/a"


def _param_text(name: str, v: dict) -> str:
    """A fitted parameter in the units of the data (mm, N/mm, N, s; ratios bare), as the unit reports."""
    from fmusa.diagnose.report import natural

    value, unit = natural(name, v["value"])
    return f"{name} = {_f(value, '.4g')}{' ' + unit if unit else ''}"


def write_report(summary: dict, cmp_: pd.DataFrame, groups: dict, out: Path, figs: list[Path]) -> Path:
    L: list[str] = []
    L.append("# Diagnosis of the C6/C7 shear tests (data/shear-c67)\n")
    L.append("Measured data (specimens H1–H3, anterior and posterior shear at 1, 10 and 100 mm/s under "
             "displacement control; see data/shear-c67/PROVENANCE.md). The spinal unit is seen as one "
             "bushing along the shear axis: the FMU's axial degree of freedom is the shear displacement "
             "disp_x, which drives the model, and the model predicts Fx. Time is derived from the nominal "
             "rate (uniform sampling assumed); each record is block-averaged to at most 300 samples and "
             "its displacement shifted to start at 0 (the model starts at rest).\n")
    L.append("## What the tool finds per specimen and direction (three rates fitted jointly)\n")
    L.append("Held-out score: each rate predicted by the model fitted to the other two.\n")
    L.append("| unit | effect named | held-out RMSE ratio | ΔBIC | effect parameters | cannot be told from | left in the residuals |")
    L.append("|---|---|---|---|---|---|---|")
    for k, g in summary["groups"].items():
        ps = "; ".join(_param_text(n, v) for n, v in g["effect_params"].items())
        L.append(f"| {k.replace('_', ' ')} | **{g['effect']}** | {_f(g['gain']['heldout_rmse_ratio'])} | "
                 f"{_f(g['gain']['delta_bic'], '.1f')} | {ps or '–'} | {', '.join(g['indistinguishable']) or '–'} | "
                 f"{g['leftover'] or '–'} |")
    L.append("")
    L.append("Every group's own report (figures, ranking of all six candidates, residual tests) is in "
             "its folder, e.g. `H1_Ant/report.md`.\n")
    counts = pd.Series([g["effect"] for g in summary["groups"].values()]).value_counts()
    L.append("Effects named: " + ", ".join(f"{e} ({n} of {len(summary['groups'])})" for e, n in counts.items()) + ".\n")
    sig_rank = {}
    for g in summary["groups"].values():
        for r in g["ranking"]:
            sig_rank.setdefault(r["effect"], []).append(r["heldout_rmse_ratio"])
    L.append("Median held-out RMSE ratio of each candidate against the baseline over the six units: " +
             ", ".join(f"{e} {np.nanmedian(v):.3f}" for e, v in sorted(sig_rank.items(), key=lambda kv: np.nanmedian(kv[1]))) + ".\n")
    ratios = [g["effect_params"]["nl_ratio"]["value"] for g in summary["groups"].values()
              if g["effect"] == "nonlinear_stiffness"]
    stiffen = sum(r > 1.0 for r in ratios)
    L.append("**What these tests can and cannot tell.** All 18 tests load monotonically to the peak and stop: "
             "there is no hold and no unloading. A *softening* elastic bend and a yielding interface "
             "(`yield_softening`) give the same loading curve, and only unloading separates them (an elastic "
             "curve retraces, a yield leaves a permanent set). Here the bend "
             + (f"stiffens in {stiffen} of {len(ratios)} units where it is named (nl_ratio "
                f"{min(ratios):.2f}–{max(ratios):.2f}): a yield cannot produce that, and its fit indeed gains "
                f"nothing, so these data rule yield out; what they cannot rule out is a softening stage beyond "
                f"the peak, which only a test to failure or an unloading would show. "
                if ratios else "is not named. ")
             + "Friction and a sensor offset add the same constant force during monotonic loading; a reversal "
             "separates them. Relaxation needs a hold or several rates: here the three rates.\n")
    L.append("## Two-phase fit per test against the authors' breakpoint analysis\n")
    b = summary["bilinear"]
    L.append(f"fmusa fits the continuous bilinear elastic model (stiffness c_y up to the breakpoint, "
             f"nl_ratio·c_y past it) to each test through the FMU; the authors fit two straight lines with "
             f"free intercepts. Median |relative difference|: first stiffness {100 * b['k1_rel_diff_median']:.1f} %, "
             f"second stiffness {100 * b['k2_rel_diff_median']:.1f} %; median |breakpoint difference| "
             f"{b['breakpoint_abs_diff_median_mm']:.3f} mm (breakpoints compared in the raw displacement frame).\n")
    L.append("By rate (median |relative difference| of k1 and k2, median |breakpoint difference|, median samples):\n")
    L.append("| rate [mm/s] | k1 | k2 | breakpoint [mm] | samples |")
    L.append("|---|---|---|---|---|")
    for rate, v in summary["bilinear_by_rate"].items():
        L.append(f"| {rate} | {100 * v['k1_rel_diff_median']:.1f} % | {100 * v['k2_rel_diff_median']:.1f} % | "
                 f"{v['breakpoint_abs_diff_median_mm']:.3f} | {v['points_median']:.0f} |")
    L.append("")
    L.append("At 1 and 10 mm/s the two analyses agree closely. At 100 mm/s the records hold only 25–44 samples "
             "and start with a toe (force lagging the displacement); the authors' lines with free intercepts "
             "absorb it, while fmusa's continuous curve through the unloaded start cannot, and puts a soft "
             "first phase there instead, so k1 and the breakpoint differ most at that rate.\n")
    L.append("| test | rate [mm/s] | authors k1 / k2 [N/mm] | fmusa k1 / k2 [N/mm] | authors breakpoint [mm] | fmusa breakpoint [mm] | fmusa RMSE [N] (linear) |")
    L.append("|---|---|---|---|---|---|---|")
    for _, r in cmp_.iterrows():
        L.append(f"| {r['specimen']} {r['direction']} | {r['rate_mm_s']:g} | {_f(r['stiffness_1'], '.1f')} / "
                 f"{_f(r['stiffness_2'], '.1f')} | {_f(r['k1_N_mm'], '.1f')} / {_f(r['k2_N_mm'], '.1f')} | "
                 f"{_f(r['breakpoint_mm'], '.3f')} | {_f(r['bp_mm'], '.3f')} | {_f(r['rmse_N'], '.2f')} "
                 f"({_f(r['linear_rmse_N'], '.2f')}) |")
    L.append("")
    L.append("## Rate dependence (1 → 10 → 100 mm/s)\n")
    rt = pd.DataFrame(summary["rate"])
    L.append("| unit | fmusa k2(100)/k2(1) | authors k2(100)/k2(1) | peak load(100)/(1) | linear stiffness(100)/(1) |")
    L.append("|---|---|---|---|---|")
    for _, r in rt.iterrows():
        L.append(f"| {r['specimen']} {r['direction']} | {_f(r['k2_ratio_100_1_ours'])} | "
                 f"{_f(r['k2_ratio_100_1_authors'])} | {_f(r['peak_ratio_100_1'])} | {_f(r['linear_k_ratio_100_1'])} |")
    L.append("")
    rm = summary.get("rate_models", {})
    if rm:
        L.append("Direct test: a Maxwell branch added to the two-phase elastic curve, fitted to all three rates "
                 "of a unit, each rate predicted from the other two:\n")
        L.append("| unit | held-out RMSE two-phase [N] | + Maxwell [N] | ratio | ΔBIC | ve_k [N/mm] | ve_tau [s] |")
        L.append("|---|---|---|---|---|---|---|")
        for k, v in rm.items():
            m = v["two_phase_maxwell"]
            L.append(f"| {k.replace('_', ' ')} | {_f(v['two_phase']['heldout_rmse'])} | {_f(m['heldout_rmse'])} | "
                     f"{_f(v['heldout_ratio'])} | {_f(v['delta_bic'], '.1f')} | {_f(m['ve_k_N_mm'])} | {_f(m['ve_tau_s'])} |")
        L.append("")
        better = [k for k, v in rm.items() if v["heldout_ratio"] < 0.9 and v["delta_bic"] < -10]
        L.append(f"The Maxwell branch improves the prediction of an unseen rate significantly (held-out ratio "
                 f"< 0.9 and ΔBIC < -10) in {len(better)} of {len(rm)} units"
                 + (f" ({', '.join(b.replace('_', ' ') for b in better)})" if better else "") + ".\n")
    up = int((rt["k2_ratio_100_1_ours"] > 1.0).sum())
    n_better = len(better) if rm else 0
    L.append(f"**What the rates show.** Over a 100-fold increase of the rate the stiffness past the breakpoint "
             f"rises in {up} of {len(rt)} units, by a median factor {rt['k2_ratio_100_1_ours'].median():.2f} "
             f"(authors' analysis: {rt['k2_ratio_100_1_authors'].median():.2f}); the peak load changes by a median "
             f"factor {rt['peak_ratio_100_1'].median():.2f}, but the tests stop at different displacements, so the "
             f"peak loads are not like for like. A rate-dependent (viscoelastic) interface would show as a "
             f"Maxwell branch that predicts an unseen rate; it does so in {n_better} of {len(rt)} units. The rate "
             f"dependence in these tests is therefore weak (stiffness past the breakpoint "
             f"{rt['k2_ratio_100_1_ours'].min():.2f}–{rt['k2_ratio_100_1_ours'].max():.2f}× over two decades of "
             f"rate) and a single Maxwell branch does not capture it in most units: a rate-independent two-phase "
             f"elastic bushing is an adequate model for shear rates of 1–100 mm/s here, with the caveat that the 100 mm/s records are short (25–44 "
             f"samples) and their time base is derived from the nominal rate.\n")
    for p in figs:
        L.append(f"![{p.stem}](figures/{p.name})\n")
    path = out / "report.md"
    path.write_text("\n".join(L))
    return path
