"""The paper's report: the generic sections with the paper's columns, rows and titles, its figures ("cf. paper
Fig. N") and its own sections on the ramp time and the deviations.

:func:`paper_sections` is what ``api.run_study`` passes to :func:`fmusa.report.markdown.write_report` when the
study has a ``paper:`` block. Everything is rendered from the result: the paper block (reference values),
``result.extra["paper"]`` (the second search, the physics runs, the time series) and the runs.
"""
from __future__ import annotations

import inspect
import math
import re
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from fmusa.applications.paper import figures as PF
from fmusa.applications.paper.deviations import deviations_section, ramp_section
from fmusa.applications.paper.physics import PaperScenario
from fmusa.format import fmt
from fmusa.files import OutputError
from fmusa.report import figures as F
from fmusa.report import sections as S
from fmusa.report.context import ReportContext, Section, get, pct
from fmusa.report.study_figures import fits_for, path_annotations
from fmusa.report.sections import figures_list_section

__all__ = ["paper_sections", "PaperView", "paper_view"]

#: units of the paper's fixed FMU values (the study writes them as plain numbers)
FIXED_UNITS = {"F_max": "N", "t_ramp": "s", "eps_v_eq": "m/s", "eps_a_eq": "m/s²"}
GRID_TITLES = {
    "max_y": "Maximum screw translation max(y) (cf. paper Fig. 5)",
    "mean_y": "Average screw translation (cf. paper Fig. 6)",
    "max_v": "Maximum screw velocity max(ẏ) (cf. paper Fig. 7)",
    "mean_v": "Average screw velocity (cf. paper Fig. 8)",
    "t_eq": "Time of reaching the static equilibrium (cf. paper Fig. 9)",
}
SEARCH_FIGURES = (("max_y", 10, "ε_y"), ("max_v", 11, "ε_ẏ"))


@dataclass
class PaperView:
    """What the paper's sections read: the ``paper:`` block, the extension's results, the scenario."""
    block: dict
    part: dict = field(default_factory=dict)
    sc: PaperScenario | None = None
    F: float | None = None
    t_ramp: float | None = None
    eps_y: float | None = None
    eps_v: float | None = None

    @property
    def region(self):
        return self.part.get("region")

    @property
    def search(self):
        return self.part.get("search")

    @property
    def physics(self):
        return self.part.get("physics")

    def optimum(self, inner: str, outer: str) -> dict | None:
        popt = self.block.get("optimum")
        if isinstance(popt, Mapping) and "c" in popt and "d" in popt:
            return {inner: float(popt["c"]), outer: float(popt["d"])}
        return None


def _float(x) -> float | None:
    try:
        return float(x)
    except (TypeError, ValueError):
        return None


def paper_view(ctx: ReportContext) -> PaperView:
    st = ctx.study
    th = {c.metric: float(c.max) for c in st.constraints if c.max is not None}
    part = ctx.result.extra.get("paper") or {}
    return PaperView(dict(st.paper or {}), part, part.get("scenario"), _float(st.fixed.get("F_max")),
                     _float(st.fixed.get("t_ramp")), th.get("max_y"), th.get("max_v"))


def _sig_opt(m: str) -> int:
    return 6 if m == "t_eq" else 5


def _sig_path(m: str) -> int:
    return 7 if m == "t_eq" else 5


# ============================================================================ what was run
def what_was_run(ctx: ReportContext) -> str:
    pv = paper_view(ctx)
    rows = S.what_was_run_rows(ctx, FIXED_UNITS)
    keys = [k for k, _ in rows]
    if pv.F is not None:
        ramp = fmt(pv.t_ramp) if pv.t_ramp is not None else "?"
        rows.insert(keys.index("scenario") + 1,
                    ("pullout force F", f"{fmt(pv.F)} N, linear ramp from 0 over t_ramp = {ramp} s, then held"))
    phys_s = pv.part.get("physics_wall_s")
    if phys_s is not None and "wall time" in keys and ctx.summary.get("wall_s") is not None:
        keys = [k for k, _ in rows]
        i = keys.index("wall time")      # the stages' time; the report's physics runs apart
        n_phys = getattr(pv.physics, "runs", 0)
        rows[i] = ("wall time", S.wall_time_text(ctx, ctx.summary["wall_s"] - phys_s)
                   + f" (and {phys_s:.2f} s for the {n_phys} runs of the ramp and end-time section)")
    cpu = pv.block.get("cpu_s_per_run")
    if cpu and "wall time" in keys:
        runs = ctx.runs
        n = int(ctx.summary.get("runs", len(runs)))
        per = float(runs["seconds"].mean()) if len(runs) and "seconds" in runs else math.nan
        i = [k for k, _ in rows].index("wall time")
        rows[i] = ("wall time", rows[i][1] + f". The paper reports {cpu:g} s per run: {n} runs would have taken "
                   f"{n * float(cpu) / 60:.0f} min of CPU time there"
                   + (f", {float(cpu) / per:,.0f} times our time per run" if math.isfinite(per) and per > 0 else ""))
    return S.what_was_run_section(ctx, rows)


# ============================================================================ results next to the paper
def results_heading(ctx: ReportContext) -> str:
    return "## Results next to the paper\n\n"


def grid(ctx: ReportContext) -> str:
    pext = get(paper_view(ctx).block, "grid_extremes", default={}) or {}
    inner, outer = ctx.inner, ctx.outer

    def extreme(m: str) -> str:
        p = pext.get(m)
        if not isinstance(p, Mapping):
            return "–"
        return (f"{ctx.v(p['value'], m)} at {inner} = {fmt(p.get(inner, p.get('c')))}, "
                f"{outer} = {fmt(p.get(outer, p.get('d')))}")
    note = ("\nA missing t_eq means the screw was not at rest (|ẏ| ≤ ε_ẏeq and |ÿ| ≤ ε_ÿeq) at the end of the "
            "run.\n") if "t_eq" in ctx.study.metrics else ""
    return S.grid_section(ctx, "### Grid (cf. paper Figs. 5-9)", lambda m: 7 if m == "t_eq" else 3,
                          [("paper's extreme", extreme)], note)


def roi_rules_quote() -> str:
    """The two rules as fmusa.analysis.roi states them (in the paper's c and d): its "Rules," paragraph
    and the numbered ones after it."""
    from fmusa.analysis import roi as roi_mod

    doc = inspect.getdoc(roi_mod) or ""
    if "Rules," not in doc:
        return S.quoted(doc)
    paras = ("Rules," + doc.split("Rules,", 1)[1]).split("\n\n")
    keep = [paras[0]]
    for para in paras[1:]:
        if not re.match(r"\d+\.", para):
            break
        keep.append(para)
    return S.quoted("\n\n".join(keep))


def roi(ctx: ReportContext) -> str:
    preg = paper_view(ctx).region
    rows = [S.region_row("paper (by hand)", preg, "chosen by hand in the paper from Figs. 5-9")] if preg else []
    return S.roi_section(ctx, rows, roi_rules_quote())


def optimum(ctx: ReportContext) -> str:
    pv, inner = paper_view(ctx), ctx.inner
    popt = pv.block.get("optimum") or {}
    paper_c = float(popt["c"]) if "c" in popt else None
    vs = [(f"{inner} vs paper", lambda opt: pct(opt[inner], paper_c) if paper_c else "–")]
    rows = []
    ps = pv.search
    if ps is not None and ps.optimum is not None:
        rows.append(S.optimum_row(ctx, "ours, inside the paper's region", ps.optimum, ps.row,
                                  ", ".join(ps.binding) or "–", [vs[0][1](ps.optimum)], _sig_opt))
    if popt:
        eps_y = get(pv.block, "thresholds", "eps_y")
        known = {"max_y": f"{fmt(eps_y)} (Sec. 3)" if eps_y is not None else "–",
                 "t_eq": fmt(popt.get("t_eq"), 5) if "t_eq" in popt else "–"}
        rows.append(("paper", fmt(popt.get("c"), 7), fmt(popt.get("d"), 6), "",
                     *(known.get(m, "–") for m in ctx.response_metrics()), "translation (Sec. 3)"))
    return S.optimum_section(ctx, "ours, automatic region", _sig_opt, vs, rows, "the automatic-region search")


def binding(ctx: ReportContext) -> str:
    pv, res, inner = paper_view(ctx), ctx.result, ctx.inner
    sc = pv.sc
    if sc is None or res.search is None or res.search.optimum is None:
        return S.binding_section(ctx)
    F_, T = sc.F, sc.t_ramp
    text = (f"\nBoth threshold constraints bind at once because, for a screw that follows the force "
            f"quasi-statically, max(y) = F/{inner} and max(ẏ) = F/({inner}·t_ramp): they reach ε_y and ε_ẏ "
            f"at {inner} = F/ε_y = {fmt(F_ / sc.eps_y, 6)} {ctx.u(inner)} and {inner} = F/(ε_ẏ·t_ramp) = "
            f"{fmt(F_ / (sc.eps_v * T), 6)} {ctx.u(inner)}, the same value for t_ramp = {fmt(T)} s. Our "
            f"optimum {fmt(res.search.optimum[inner], 7)} {ctx.u(inner)} lies "
            f"{pct(res.search.optimum[inner], F_ / sc.eps_y)} above it (the bisection tolerance is "
            f"{ctx.study.stages['search'].inner_rtol:g} relative).\n")
    return S.binding_section(ctx, text)


def search(ctx: ReportContext) -> str:
    pv = paper_view(ctx)
    extra = ""
    if pv.search is not None and pv.region is not None:
        extra = (f"\nInside the paper's region ({ctx.outer} halved from {fmt(pv.region.outer_range[1])} "
                 f"{ctx.u(ctx.outer)}):\n\n")
        extra += S.search_table(ctx, get(ctx.summary, "paper_roi_search", "levels", default=[]),
                                ["search_paper_roi"], pv.region.inner_range, _sig_path) + "\n"
        extra += f"\nStop: {pv.search.stop_reason}.\n"
    return S.search_section(ctx, _sig_path, extra)


def _cubic_of_hyperbola(F_: float, lo: float, hi: float) -> tuple[list[float], float]:
    """Coefficients (increasing powers) and R² of a cubic least-squares fit of F/x over [lo, hi]."""
    xx = np.linspace(lo, hi, 400)
    c = np.polynomial.polynomial.polyfit(xx / hi, F_ / xx, 3)
    c = [v / hi ** k for k, v in enumerate(c)]
    yy = np.polynomial.polynomial.polyval(xx, c)
    r2 = 1 - np.sum((F_ / xx - yy) ** 2) / np.sum((F_ / xx - np.mean(F_ / xx)) ** 2)
    return c, float(r2)


def _regression_rows(ctx: ReportContext, pv: PaperView, x: str):
    pr = get(pv.block, "regression", default={}) or {}

    def rows(m: str) -> list:
        out = []
        if pr.get("metric") == m:
            out.append(("**paper**", "–", fmt(pr.get("r")), fmt(pr.get("s")), fmt(pr.get("t"), 4),
                        fmt(pr.get("u")), "–", "Fig. 10 (one curve)"))
        if m == "max_y" and pv.F is not None:
            for lo, hi in ((3.90625e5, 1.6e6), (6e5, 9e5)):
                c, r2 = _cubic_of_hyperbola(pv.F, lo, hi)
                out.append((f"*cubic fit of F/{x}*", "400", *(fmt(v, 4) for v in c), f"{r2:.4f}",
                            f"[{fmt(lo)}, {fmt(hi)}]"))
        return out
    return rows


def _median_r2(fits) -> float:
    vals = [f["r2"] for f in (fits or {}).values() if f.get("r2") is not None]
    return float(np.median(vals)) if vals else math.nan


def _regression_footer(ctx: ReportContext, pv: PaperView, x: str) -> str:
    pr = get(pv.block, "regression", default={}) or {}
    popt = get(pv.block, "optimum", "c")
    if pv.F is None or pr.get("metric") != "max_y" or not popt or ctx.result.region is None:
        return ""
    co = [float(pr[k]) for k in ("r", "s", "t", "u")]
    val = float(np.polynomial.polynomial.polyval(float(popt), co))
    rng = ctx.result.region.inner_range
    return (f"max(y) = F/{x} in the quasi-static limit is a hyperbola, so a cubic fits it only approximately "
            f"over a decade of {x}: our per-level fits span the whole region [{fmt(rng[0])}, "
            f"{fmt(rng[1])}] {ctx.u(x)} (the bisection starts at its bounds) and reach "
            f"R² ≈ {_median_r2(ctx.summary['regression'].get('max_y')):.2f}. The paper's printed coefficients have "
            f"the magnitudes of a cubic through F/{x} over about [{fmt(3.90625e5)}, {fmt(1.6e6)}] {ctx.u(x)} (rows "
            f"in italics), but evaluated at the paper's optimum {x} = {fmt(float(popt), 6)} they give "
            f"{fmt(val, 3)} m, not ε_y = {fmt(pv.eps_y)} m (F/{x} = {fmt(pv.F / float(popt), 4)} m): "
            f"with r ≈ 0.002 printed to one digit (±5e-4 m) and the terms cancelling, the printed cubic "
            f"cannot be evaluated to the precision of the threshold.\n")


def regression(ctx: ReportContext) -> str:
    if not ctx.summary.get("regression"):
        return ""
    pv = paper_view(ctx)
    x = getattr(ctx.study.stages.get("regression"), "x", ctx.inner)
    fitted_on = ("the automatic-region search" if ctx.summary.get("regression_source", "search") == "search"
                 else None)
    return S.regression_section(ctx, "### Regression (eq. 3: y = r + s·x + t·x² + u·x³)", ("r", "s", "t", "u"),
                                fitted_on, _regression_rows(ctx, pv, x), _regression_footer(ctx, pv, x))


# ============================================================================ figures
def _scenario_text(ctx: ReportContext, pv: PaperView) -> str:
    parts = [f"F = {fmt(pv.F)} N"] if pv.F is not None else []
    if pv.t_ramp is not None:
        parts.append(f"ramp {fmt(pv.t_ramp)} s")
    parts.append(f"end {fmt(ctx.study.scenario.stop_time)} s")
    return ", ".join(parts)


def grid_figure(ctx: ReportContext, pv: PaperView, m: str) -> tuple[str, str]:
    st, res, inner, outer = ctx.study, ctx.result, ctx.inner, ctx.outer
    shift = pv.t_ramp if (m == "t_eq" and pv.t_ramp) else 0.0
    title = GRID_TITLES.get(m, st.metrics[m].description or m)
    name = f"grid_{m}.png"
    frames = [F.RegionFrame(res.region, "automatic region")] if res.region is not None else []
    if pv.region is not None:
        frames.append(F.RegionFrame(pv.region, "paper's region (by hand)", PF.PAPER_COLOR, "--", 0.07))
    th = ctx.thresholds(m) if m in ("max_y", "max_v") else []
    F.grid_heatmap(ctx.runs, m, ctx.figdir / name, inner=inner, outer=outer, inner_label=ctx.label(inner),
                   outer_label=ctx.label(outer), inner_unit=ctx.u(inner), outer_unit=ctx.u(outer),
                   metric_unit=ctx.u(m), title=f"{title}\n{_scenario_text(ctx, pv)}", regions=frames,
                   thresholds=[F.Threshold(v, f"threshold {fmt(v)} {ctx.u(m)}") for v, _ in th[:1]],
                   ok_column=ctx.ok_column(m) if th else None, shift=shift,
                   shift_label=f"{m} − t_ramp" if shift else "", missing_label="no rest")
    cap = (f"{title} on the {inner} × {outer} grid"
           + ("; solid red frame: our automatic region of interest" if res.region is not None else "")
           + ("; dashed blue: the paper's region" if pv.region is not None else ""))
    if th:
        cap += f"; hatched cells violate {m} ≤ {fmt(th[0][0])} {ctx.u(m)}"
    if shift:
        cap += (f". Cells show t_eq − t_ramp (the time after the ramp end at {fmt(shift)} s; t_eq itself is "
                f"measured from t = 0); grey 'no rest': not at rest before the end at {fmt(st.scenario.stop_time)} s")
    return name, cap + "."


def _reference(pv: PaperView, m: str, inner: str):
    if pv.F is not None and m == "max_y":
        return (lambda x, F_=pv.F: F_ / x), f"quasi-static F/{inner} (F = {fmt(pv.F)} N)"
    if pv.F is not None and pv.t_ramp and m == "max_v":
        return ((lambda x, F_=pv.F, T=pv.t_ramp: F_ / (x * T)),
                f"quasi-static ramp velocity F/({inner}·t_ramp), t_ramp = {fmt(pv.t_ramp)} s")
    return None, ""


def search_figure(ctx: ReportContext, pv: PaperView, m: str, fig_no: int, sym: str) -> tuple[str, str]:
    inner, outer, res = ctx.inner, ctx.outer, ctx.result
    popt = pv.optimum(inner, outer)
    ref, ref_label = _reference(pv, m, inner)
    th = ctx.thresholds(m)[:1]
    name = f"search_{m}.png"
    F.search_metric(ctx.runs, get(ctx.summary, "search", "levels", default=[]), fits_for(ctx, m), m,
                    ctx.figdir / name, inner=inner, outer=outer, inner_label=ctx.label(inner),
                    metric_label=f"{m}{F.unit_suffix(ctx.u(m))}", inner_unit=ctx.u(inner), outer_unit=ctx.u(outer),
                    thresholds=[F.Threshold(v, f"{sym} = {fmt(v)} {ctx.u(m)}") for v, _ in th],
                    optimum=res.search.optimum, inner_range=res.region.inner_range, reference=ref,
                    reference_label=ref_label, title=f"{m} of the search points (cf. paper Fig. {fig_no})",
                    markers=[(popt[inner], f"paper's optimum {inner} = {fmt(popt[inner], 6)} {ctx.u(inner)}")]
                    if popt else [], xlog=True, fit_label="cubic fits of eq. 3")
    return name, (f"{m} of every run of the nested binary search (automatic region) against {inner}, one colour "
                  f"per {outer} level, with the cubic fits of eq. 3 per level, the threshold and the optimum; "
                  f"right: zoom to ±5 % of the optimum (cf. paper Fig. {fig_no}).")


def t_eq_figure(ctx: ReportContext, pv: PaperView) -> tuple[str, str]:
    inner, outer, res = ctx.inner, ctx.outer, ctx.result
    name = "search_t_eq.png"
    PF.search_t_eq(ctx.runs, get(ctx.summary, "search", "levels", default=[]), ctx.figdir / name, inner=inner,
                   outer=outer, inner_unit=ctx.u(inner), outer_unit=ctx.u(outer), shift=pv.t_ramp or 0.0,
                   optimum=res.search.optimum, paper_optimum=pv.optimum(inner, outer),
                   paper_t_eq=get(pv.block, "optimum", "t_eq"), inner_range=res.region.inner_range)
    return name, (f"Time to equilibrium of the search points against {inner} and {outer} (cf. paper Figs. 12-13), "
                  f"plotted as t_eq − t_ramp, the time the screw needs to come to rest after the force stops "
                  f"rising; the paper's reported t_eq = {get(pv.block, 'optimum', 't_eq', default='–')} s is drawn "
                  f"as reported.")


def path_figure(ctx: ReportContext, pv: PaperView) -> tuple[str, str]:
    inner, outer, res, s = ctx.inner, ctx.outer, ctx.result, ctx.summary
    levels = get(s, "search", "levels", default=[])
    searches = [("automatic region", levels, res.search.optimum, F.AUTO_COLOR)]
    if pv.search is not None:
        searches.append(("paper's region", get(s, "paper_roi_search", "levels", default=[]), pv.search.optimum,
                         PF.PAPER_COLOR))
    popt = pv.optimum(inner, outer)
    markers = [(popt[outer], popt[inner], f"paper's optimum {inner} = {fmt(popt[inner], 6)} {ctx.u(inner)}, "
                                          f"{outer} = {fmt(popt[outer], 4)} {ctx.u(outer)}")] if popt else []
    ref = ((pv.F / pv.eps_y, f"F/ε_y = {fmt(pv.F / pv.eps_y, 6)} {ctx.u(inner)}")
           if pv.F is not None and pv.eps_y else None)
    stop = fmt(ctx.study.scenario.stop_time)
    notes = path_annotations(ctx, levels, lambda b: f" (not at rest by t = {stop} s)" if b == "equilibrium" else "")
    name = "search_path.png"
    F.search_path(searches, ctx.figdir / name, inner=inner, outer=outer, inner_label=ctx.label(inner),
                  outer_label=ctx.label(outer), inner_unit=ctx.u(inner), outer_unit=ctx.u(outer), markers=markers,
                  reference=ref, annotations=notes, xlog=True)
    return name, (f"Search path: each {outer} level visited by the nested binary search and the smallest feasible "
                  f"{inner} found there, for the automatic and the paper's region; stars: where each search "
                  f"stopped; labelled levels: where another constraint than at the optimum decides.")


def time_series_figure(ctx: ReportContext, pv: PaperView) -> tuple[str, str] | None:
    ts = pv.part.get("time_series")
    if not ts:
        return None
    if "note" in ts:
        ctx.notes.append(ts["note"])
        return None
    st, opt, inner, outer = ctx.study, ctx.result.search.optimum, ctx.inner, ctx.outer
    name = "optimum_time_series.png"
    PF.time_series(ts["df"], ctx.figdir / name, eps_y=pv.eps_y, eps_v=pv.eps_v, t_eq=ts["t_eq"], t_ramp=pv.t_ramp,
                   zoom=ts["zoom"], eps_v_eq=st.fixed.get("eps_v_eq"), eps_a_eq=st.fixed.get("eps_a_eq"),
                   title=f"Scenario at our optimum {inner} = {fmt(opt[inner], 6)} {ctx.u(inner)}, "
                         f"{outer} = {fmt(opt[outer], 5)} {ctx.u(outer)} (sampled every 0.01 s)")
    return name, ("The pullout at our optimum: force, displacement and velocity against time with the thresholds; "
                  "the bottom panel zooms on the end of the ramp, where |ẏ| and |ÿ| drop below the rest "
                  "thresholds ε_ẏeq and ε_ÿeq; t_eq is when both hold from then on.")


def _figure_steps(ctx: ReportContext, pv: PaperView) -> list:
    res, st = ctx.result, ctx.study
    steps = []
    if ctx.stage_ran("grid") and ctx.inner and ctx.outer:
        steps += [lambda m=m: grid_figure(ctx, pv, m) for m in st.metrics]
    if res.search is not None and res.search.optimum is not None and ctx.inner and ctx.outer:
        steps += [lambda m=m, n=n, s=s: search_figure(ctx, pv, m, n, s) for m, n, s in SEARCH_FIGURES
                  if m in st.metrics]
        if "t_eq" in st.metrics:
            steps.append(lambda: t_eq_figure(ctx, pv))
        steps += [lambda: path_figure(ctx, pv), lambda: time_series_figure(ctx, pv)]
    return steps


def figures(ctx: ReportContext) -> str:
    """The paper's figures (its Figs. 5-13 and the pullout at our optimum), then the list of them."""
    pv = paper_view(ctx)
    for step in _figure_steps(ctx, pv):
        try:
            made = step()
        except OutputError:   # a full disk or a folder that cannot be written: the study's error, not a note
            raise
        except Exception as exc:  # noqa: BLE001 - one figure must not cost the report
            ctx.notes.append(f"A figure could not be drawn: {type(exc).__name__}: {exc}")
            continue
        if made:
            ctx.add_figure(*made)
    ctx.notes.extend(pv.part.get("notes") or [])
    return figures_list_section(ctx)


# ============================================================================ the sections
def _ramp(ctx: ReportContext) -> str:
    pv = paper_view(ctx)
    if pv.physics is None or pv.sc is None:
        return ""
    return ramp_section(ctx, pv.sc, pv.physics, pv.block)


def _deviations(ctx: ReportContext) -> str:
    pv = paper_view(ctx)
    if pv.physics is None or pv.sc is None:
        return ""
    return deviations_section(ctx, pv.sc, pv.physics, pv.block, pv.region, pv.search)


def paper_sections() -> list[Section]:
    """The paper's additions to the generic report (see :class:`fmusa.report.context.ReportSection`)."""
    return [
        Section("what_was_run", what_was_run),
        Section("results", results_heading),
        Section("results.grid", grid),
        Section("results.roi", roi),
        Section("results.optimum", optimum),
        Section("results.binding", binding),
        Section("results.search", search),
        Section("results.regression", regression),
        Section("figures", figures),
        Section("paper_ramp", _ramp, "after:figures"),
        Section("paper_deviations", _deviations, "after:paper_ramp"),
    ]

