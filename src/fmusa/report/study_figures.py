"""Which figures a study gets, drawn from its result: one per stage that ran.

- grid: per metric, a line plot over the one parameter (1-D), a heat map over the two (2-D), or one panel
  per parameter (3 or more); thresholds of the metric's constraints and the region of interest drawn in;
- search: per constrained metric, its values at the search's runs against the inner parameter, with the
  threshold, the optimum and the regression's fits when they are fitted over the same parameters; and
  the search path (outer levels against the smallest feasible inner value) for a nested search;
- regression: its points and fits, when the search figures did not already show them.

Titles, axis labels and captions come from the study's descriptions and units.
"""
from __future__ import annotations

from typing import Callable, Mapping

from fmusa.format import fmt
from fmusa.files import OutputError
from fmusa.report import figures as F
from fmusa.report.context import ReportContext, get
from fmusa.report.sections import figures_list_section, level_binding, search_outer

Title = Callable[[str], str] | None


def thresholds(ctx: ReportContext, metric: str) -> list[F.Threshold]:
    return [F.Threshold(v, label) for v, label in ctx.thresholds(metric)]


def metric_title(ctx: ReportContext, metric: str) -> str:
    return ctx.describe(metric)


def region_frames(ctx: ReportContext) -> list[F.RegionFrame]:
    reg = ctx.result.region
    if reg is None or reg.outer is None:
        return []
    return [F.RegionFrame(reg, f"{reg.source} region of interest")]


# ============================================================================ grid
def grid_figure(ctx: ReportContext, metric: str, title: Title = None) -> tuple[str, str] | None:
    """The grid figure of ``metric`` and its caption; ``title(metric)`` overrides the metric's description."""
    title = title or (lambda m: metric_title(ctx, m))
    params = list(ctx.study.parameters)
    name = f"grid_{metric}.png"
    path = ctx.figdir / name
    th = thresholds(ctx, metric)
    cons = "; ".join(t.label for t in th)
    if len(params) == 1:
        return _grid_line(ctx, metric, params[0], path, title, th, cons)
    if len(params) == 2 and ctx.inner and ctx.outer:
        frames = region_frames(ctx)
        F.grid_heatmap(ctx.runs, metric, path, inner=ctx.inner, outer=ctx.outer, inner_label=ctx.label(ctx.inner),
                       outer_label=ctx.label(ctx.outer), inner_unit=ctx.u(ctx.inner), outer_unit=ctx.u(ctx.outer),
                       metric_unit=ctx.u(metric), title=title(metric), regions=frames, thresholds=th,
                       ok_column=ctx.ok_column(metric) if th else None)
        cap = (f"{ctx.named(metric)} on the {ctx.inner} × {ctx.outer} grid"
               + ("; solid red frame: the region of interest the search used" if frames else "")
               + (f"; hatched cells violate {cons}" if th else "") + ".")
        return name, cap
    F.scatter_panels(ctx.runs, params, metric, path, param_labels={p: ctx.label(p) for p in params},
                     metric_label=ctx.label(metric), title=title(metric), thresholds=th)
    return name, (f"{ctx.named(metric)} of the grid runs against each parameter"
                  + (f"; dashed: {cons}" if th else "") + ".")


def _grid_line(ctx: ReportContext, metric: str, param: str, path, title: Title, th, cons: str):
    reg = ctx.result.region
    shade = None
    if reg is not None and reg.inner == param:
        shade = (reg.inner_range[0], reg.inner_range[1], f"{reg.source} region of interest: {param} ∈ "
                 f"[{fmt(reg.inner_range[0])}, {fmt(reg.inner_range[1])}] {ctx.u(param)}".rstrip())
    opt = get(ctx.summary, "optimum")
    row = ctx.result.search.row if ctx.result.search is not None else None
    star = None
    if opt and param in opt and row and row.get(metric) is not None:
        star = (float(opt[param]), float(row[metric]), f"optimum {param} = {fmt(opt[param], 7)} {ctx.u(param)}")
    F.line_plot(ctx.runs, param, metric, path, param_label=ctx.label(param), metric_label=ctx.label(metric),
                title=title(metric), thresholds=th, shade=shade, optimum=star,
                ok_column=ctx.ok_column(metric) if th else None)
    cap = (f"{ctx.named(metric)} against {param}: the grid runs joined by a line"
           + ("; points: the runs of later stages" if (ctx.runs["stage"] != "grid").any() else "")
           + (f"; dashed: {cons}" if th else "") + ("; shaded: the region of interest" if shade else "")
           + ("; star: the optimum" if star else "") + ".")
    return path.name, cap


# ============================================================================ search
def fits_for(ctx: ReportContext, metric: str) -> Mapping | None:
    """The regression's fits of ``metric`` when they are over the search's parameters (x = inner, by =
    outer), so that they can be drawn over the search's runs."""
    stage = ctx.study.stages.get("regression")
    reg = ctx.summary.get("regression") or {}
    if stage is None or metric not in reg or getattr(stage, "x", None) != ctx.inner:
        return None
    if getattr(stage, "by", None) != search_outer(ctx):
        return None
    return reg[metric]


def search_figure(ctx: ReportContext, metric: str, title: str = "", **extra) -> tuple[str, str]:
    """``metric`` of the search's runs against the inner parameter (and its caption)."""
    res, inner, outer = ctx.result, ctx.inner, search_outer(ctx)
    name = f"search_{metric}.png"
    fits = fits_for(ctx, metric)
    F.search_metric(ctx.runs, get(ctx.summary, "search", "levels", default=[]), fits, metric, ctx.figdir / name,
                    inner=inner, outer=outer, inner_label=ctx.label(inner), metric_label=ctx.label(metric),
                    inner_unit=ctx.u(inner), outer_unit=ctx.u(outer) if outer else "",
                    thresholds=thresholds(ctx, metric), optimum=res.search.optimum,
                    inner_range=res.region.inner_range if res.region is not None else None,
                    title=title or f"{ctx.describe(metric)} at the search's runs", **extra)
    per = f", one colour per {outer} level" if outer else ""
    cap = (f"{ctx.named(metric)} of every run of the search against {inner}{per}"
           + (", with the regression's fits per level" if fits else "")
           + (", the constraint's bounds" if ctx.thresholds(metric) else "")
           + " and the optimum; right: zoom to ±5 % of the optimum.")
    return name, cap


def path_annotations(ctx: ReportContext, levels, why: Callable[[str], str] = lambda b: "") -> list:
    """Levels where another constraint decides than at the optimum: (outer, inner, "<name> binds")."""
    opt, res = ctx.result.search.optimum, ctx.result
    inner, outer = ctx.inner, search_outer(ctx)
    rng = res.region.inner_range if res.region is not None else None
    final = level_binding(ctx, next((lv for lv in levels if lv.get("inner") == opt[inner]
                                     and lv.get("outer") == opt[outer]), {}), ["search"], rng)
    notes = []
    for lv in levels:
        b = level_binding(ctx, lv, ["search"], rng)
        if lv.get("inner") is not None and b not in ("–", final):
            notes.append((float(lv["outer"]), float(lv["inner"]), f"{b} binds{why(b)}"))
    return notes


def search_path_figure(ctx: ReportContext) -> tuple[str, str] | None:
    res, inner, outer = ctx.result, ctx.inner, search_outer(ctx)
    if outer is None or res.search.optimum is None:
        return None
    levels = get(ctx.summary, "search", "levels", default=[])
    src = res.region.source if res.region is not None else "search"
    name = "search_path.png"
    F.search_path([(f"{src} region", levels, res.search.optimum, F.AUTO_COLOR)], ctx.figdir / name, inner=inner,
                  outer=outer, inner_label=ctx.label(inner), outer_label=ctx.label(outer), inner_unit=ctx.u(inner),
                  outer_unit=ctx.u(outer), annotations=path_annotations(ctx, levels),
                  inner_range=res.region.inner_range if res.region is not None else None)
    return name, (f"Search path: each {outer} level visited by the nested binary search and the smallest "
                  f"feasible {inner} found there; star: where the search stopped; labelled levels: where "
                  f"another constraint than at the optimum decides.")


# ============================================================================ regression
def regression_figures(ctx: ReportContext) -> list[tuple[str, str]]:
    """One figure per fitted metric whose fits no search figure shows."""
    stage, reg = ctx.study.stages.get("regression"), ctx.summary.get("regression") or {}
    if stage is None or not reg:
        return []
    src = ctx.summary.get("regression_source") or ("search" if ctx.result.search is not None else "grid")
    pts = ctx.runs[ctx.runs["stage"] == src] if len(ctx.runs) else ctx.runs
    out = []
    for m, fits in reg.items():
        if ctx.result.search is not None and m in ctx.constrained_metrics() and fits_for(ctx, m) is not None:
            continue
        name = f"regression_{m}.png"
        F.regression_plot(pts, fits, stage.x, m, stage.by, ctx.figdir / name, x_label=ctx.label(stage.x),
                          metric_label=ctx.label(m), by_unit=ctx.u(stage.by) if stage.by else "",
                          title=f"{ctx.describe(m)}: degree-{stage.degree} fit over {stage.x}", degree=stage.degree)
        per = f", one per {stage.by} level" if stage.by else ""
        out.append((name, f"{ctx.named(m)} of the {src} runs against {stage.x} with the fitted "
                          f"degree-{stage.degree} polynomials{per}."))
    return out


# ============================================================================ all of them
def draw_study_figures(ctx: ReportContext) -> None:
    """Every generic figure of the stages that ran, added to ``ctx.figures``; a figure that cannot be
    drawn leaves a note instead of stopping the report."""
    steps = []
    if ctx.stage_ran("grid"):
        steps += [lambda m=m: grid_figure(ctx, m) for m in ctx.study.metrics]
    if ctx.result.search is not None and ctx.result.search.optimum is not None:
        steps += [lambda m=m: search_figure(ctx, m) for m in ctx.constrained_metrics()]
        steps.append(lambda: search_path_figure(ctx))
    steps.append(lambda: regression_figures(ctx))
    for step in steps:
        try:
            made = step()
        except OutputError:   # a full disk or a folder that cannot be written: the study's error, not a note
            raise
        except Exception as exc:  # noqa: BLE001 - one figure must not cost the report
            ctx.notes.append(f"A figure could not be drawn: {type(exc).__name__}: {exc}")
            continue
        for fig in ([made] if isinstance(made, tuple) else made or []):
            ctx.add_figure(*fig)


def figures_section(ctx: ReportContext) -> str:
    """Draw the study's figures, then list them under "## Figures"."""
    draw_study_figures(ctx)
    return figures_list_section(ctx)
