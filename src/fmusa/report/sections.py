"""The generic sections of report.md: what any study's stages found, in the study's own words.

Each ``*_section(ctx, ...)`` renders one section from the result (summary, runs, region, search) and returns
markdown, "" when its stage did not run. Their keyword arguments let an application add columns, rows or a
paragraph without copying the section (its own ReportSection calls them). Nothing here names a model:
labels come from the study's descriptions and units.
"""
from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np
import pandas as pd

from fmusa.format import fmt, md_code, md_text
from fmusa.files import OutputError
from fmusa.report import figures as F
from fmusa.report.context import ReportContext, figure_markdown, get, ok_mark, table, yes

Sig = Callable[[str], int]
Row = Sequence[object]


def _sig5(metric: str) -> int:
    return 5


def _sig3(metric: str) -> int:
    return 3


# ============================================================================ title, what was run
def title_section(ctx: ReportContext) -> str:
    st = ctx.study
    text = f"# Report: study `{st.name}`\n"
    if st.description:
        text += "\n" + st.description.strip() + "\n"
    return text


def _fixed_text(ctx: ReportContext, units: Mapping[str, str]) -> str:
    st = ctx.study
    mapped = getattr(st, "fixed_units", None) or {}

    def one(k, v) -> str:
        if k in mapped:   # written in the study's unit: show it, and what the FMU gets
            fv = mapped[k]
            return f"{k} = {fv.value:g}{(' ' + fv.unit) if fv.unit else ''} (FMU value {v:g})"
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            return f"{k} = {v:g}{(' ' + units[k]) if k in units else ''}"
        return f"{k} = {v}"
    return ", ".join(one(k, v) for k, v in st.fixed.items())


def _constraint_rows(ctx: ReportContext) -> list[tuple[str, str]]:
    rows = []
    for c in ctx.study.constraints:
        bound = []
        if c.max is not None:
            bound.append(f"{c.metric} ≤ {fmt(c.max)} {ctx.u(c.metric)}")
        if c.min is not None:
            bound.append(f"{c.metric} ≥ {fmt(c.min)} {ctx.u(c.metric)}")
        if c.required:
            bound.append(f"{c.metric} exists")
        rows.append((f"constraint `{c.name}`", " and ".join(bound) + (f" ({c.description})" if c.description else "")))
    return rows


def _fmu_text(ctx: ReportContext) -> str:
    """The FMU's path, model name and description; the FMU's own text escaped (it is someone else's)."""
    from fmusa.errors import FmusaError
    from fmusa.fmi.info import default_fmu_path, read_fmu_info
    st = ctx.study
    try:
        path = st.fmu or default_fmu_path()
    except (FileNotFoundError, FmusaError):
        return "`(not found)`"
    try:
        info = read_fmu_info(path)
    except (OSError, FmusaError):
        return md_code(path)
    about = md_text(info.model_name) + (f": {md_text(info.description)}" if info.description else "")
    return f"{md_code(path)} ({about})"


def _runs_rows(ctx: ReportContext) -> list[tuple[str, str]]:
    s, runs = ctx.summary, ctx.runs
    n = int(s.get("runs", len(runs)))
    rc = s.get("run_counts") or {"runs": n, "simulated_now": s.get("simulated_this_session"), "failed": s.get("failed")}
    counts = ", ".join(f"{k}: {v}" for k, v in runs["stage"].value_counts().items()) if len(runs) else ""
    rows = [("runs", f"{rc['runs']} ({rc.get('simulated_now', '–')} simulated in this session)"),
            ("in runs.csv", f"{n} ({counts})" if counts else str(n))]
    if rc.get("sensitivity"):
        rows.append(("in sensitivity_runs.csv", f"{rc['sensitivity']} (see the sensitivity section)"))
    if rc.get("sensitivity_reference"):
        rows.append(("sensitivity reference runs", f"{rc['sensitivity_reference']} (its accuracy check)"))
    rows.append(("failed runs", str(rc.get("failed", "–"))))
    return rows


def wall_time_text(ctx: ReportContext, wall: float | None = None) -> str:
    """"x s for the whole study; y ms per FMU run on average" ("" without a wall time); ``wall`` replaces
    summary["wall_s"] (e.g. without an application's own runs)."""
    wall, runs = (ctx.summary.get("wall_s") if wall is None else wall), ctx.runs
    if wall is None:
        return ""
    per = float(runs["seconds"].mean()) if len(runs) and "seconds" in runs else math.nan
    txt = f"{wall:.2f} s for the whole study (all stages)"
    if math.isfinite(per):
        txt += f"; {per * 1e3:.3f} ms per FMU run on average"
    return txt


def what_was_run_rows(ctx: ReportContext, fixed_units: Mapping[str, str] | None = None) -> list[tuple[str, str]]:
    """The rows of "What was run" (item, value); ``fixed_units`` gives units to fixed FMU values that the
    study writes without one."""
    st = ctx.study
    rows = [("study file", md_code(st.path)), ("FMU", _fmu_text(ctx)),
            ("study parameters", ", ".join(f"{n} → FMU {md_code(p.variable)} [{md_text(p.unit)}]"
                                           for n, p in st.parameters.items()))]
    if st.fixed:
        rows.append(("fixed parameters", _fixed_text(ctx, fixed_units or {})))
    sc = st.scenario
    rows.append(("scenario", sc.description or "–"))
    step = "one doStep to the end" if sc.step is None else f"communication step {sc.step:g} s"
    rows.append(("end time", f"{fmt(sc.stop_time)} s ({step})"))
    if sc.inputs:
        rows.append(("inputs", ", ".join(f"{k} = {v:g}" for k, v in sc.inputs.items())))
    rows += _constraint_rows(ctx)
    rows.append(("stages", ", ".join(st.stages)))
    rows += _runs_rows(ctx)
    wall = wall_time_text(ctx)
    if wall:
        rows.append(("wall time", wall))
    return rows


def what_was_run_section(ctx: ReportContext, rows: Sequence[Row] | None = None) -> str:
    rows = what_was_run_rows(ctx) if rows is None else rows
    return "## What was run\n\n" + table(["item", "value"], rows) + "\n"


# ============================================================================ results: grid
def results_heading(ctx: ReportContext) -> str:
    return "## Results\n\n"


def grid_runs(ctx: ReportContext) -> pd.DataFrame:
    runs = ctx.runs
    if not len(runs) or "stage" not in runs:
        return runs
    return runs[(runs["stage"] == "grid") & (runs["status"] == "ok")]


def _at(g: pd.DataFrame, i, names: Sequence[str]) -> str:
    return ", ".join(f"{n} = {fmt(g.at[i, n])}" for n in names)


def _extreme_rows(ctx: ReportContext, g: pd.DataFrame, names: Sequence[str], sig: Sig,
                  extra_columns: Sequence[tuple[str, Callable[[str], str]]]) -> list[Row]:
    rows = []
    for m in ctx.study.metrics:
        col = g[m].astype(float)
        if not col.notna().any():
            continue
        i_max, i_min = col.idxmax(), col.idxmin()
        rows.append((m, f"{ctx.v(col[i_max], m, sig(m))} at {_at(g, i_max, names)}",
                     f"{ctx.v(col[i_min], m, sig(m))} at {_at(g, i_min, names)}",
                     *(fn(m) for _, fn in extra_columns), int(col.isna().sum())))
    return rows


def best_grid_point(ctx: ReportContext, g: pd.DataFrame) -> str:
    """The feasible grid point with the smallest value of the first axis (ties: of the next), which is
    what a search for the smallest feasible parameters refines; "" without constraints."""
    if not ctx.study.constraints or "feasible" not in g:
        return ""
    feas = g[g["feasible"].astype(bool)]
    axes = [n for n in (ctx.inner, ctx.outer) if n] + [n for n in ctx.study.parameters if n not in (ctx.inner, ctx.outer)]
    if not len(feas):
        return "No grid point meets every constraint.\n"
    best = feas.sort_values(axes).iloc[0]
    where = ", ".join(f"{n} = {fmt(best[n], 5)} {ctx.u(n)}".rstrip() for n in axes)
    vals = ", ".join(f"{m} = {fmt(best[m], 5)} {ctx.u(m)}".rstrip() for m in ctx.constrained_metrics())
    return f"Smallest feasible {axes[0]} on the grid: {where} ({vals}).\n"


def grid_section(ctx: ReportContext, heading: str = "### Grid", sig: Sig = _sig3,
                 extra_columns: Sequence[tuple[str, Callable[[str], str]]] = (), note: str = "") -> str:
    """The grid's runs: its axes, how many meet every constraint, the best point, each metric's extremes;
    ``extra_columns`` (title, metric → text) go before the last column."""
    g = grid_runs(ctx)
    if not len(g) or not ctx.stage_ran("grid"):
        return ""
    names = [n for n in ctx.study.parameters if n in g]
    axes = " × ".join(f"{n} ∈ {{{', '.join(fmt(x) for x in sorted(g[n].unique()))}}} {ctx.u(n)}".rstrip()
                      for n in names)
    n_feas = int(g["feasible"].astype(bool).sum()) if "feasible" in g else len(g)   # no constraints: all
    failed = int((ctx.runs["stage"] == "grid").sum()) - len(g)
    out = f"{heading}\n\n"
    out += (f"{len(g)} runs on the grid {axes}; {n_feas} of them meet every constraint"
            + (f"; {failed} more failed (see Failed runs)" if failed else "") + ".\n\n")
    out += table(["metric", "largest (ours)", "smallest (ours)", *(t for t, _ in extra_columns), "cells without a value"],
                 _extreme_rows(ctx, g, names, sig, extra_columns)) + "\n"
    best = best_grid_point(ctx, g)
    if best:
        out += "\n" + best
    found = (ctx.result.summary or {}).get("grid") or {}
    for info in (found.get("inert_parameters") or {}).values():     # not a reason to widen the grid
        out += f"\n**A parameter that does nothing.** {info['message']}.\n"
    if found.get("infeasible"):
        out += f"\n**No feasible grid point.** {found['infeasible']}.\n"
    return out + note


# ============================================================================ results: region of interest
def quoted(text: str) -> str:
    """``text`` as a markdown block quote."""
    return "\n".join("> " + line if line else ">" for line in text.strip().splitlines())


def roi_rules(inner: str, outer: str | None) -> str:
    """The rules of :func:`fmusa.analysis.roi.automatic_region`, in the study's parameter names."""
    if outer is None:
        return (f"Rule: the region's {inner}-range is [the largest grid {inner} below the smallest feasible grid "
                f"{inner}, that smallest feasible grid {inner}] (0 when no grid value lies below), over the grid "
                f"runs where the other parameters have the values the search keeps.")
    return (f"Rules, with x_min(z) the smallest grid {inner} that meets every constraint at {outer} = z:\n\n"
            f"1. The region's {inner}-range is [the largest grid {inner} below min_z x_min(z), min_z x_min(z)]: "
            f"the grid neighbours that bracket the smallest feasible {inner} (0 when no grid value lies below).\n"
            f"2. The region's {outer}-range is [z_lo, z_hi]: z_hi is the largest grid {outer} at which x_min(z) "
            f"still equals the overall smallest feasible {inner}; z_lo is 0 when the smallest grid {outer} is "
            f"feasible there, else the grid neighbour below the smallest feasible {outer}.")


def region_row(label: str, region, notes: str) -> tuple:
    row = [label, f"[{fmt(region.inner_range[0])}, {fmt(region.inner_range[1])}]"]
    if region.outer is not None and region.outer_range is not None:
        row.append(f"[{fmt(region.outer_range[0])}, {fmt(region.outer_range[1])}]")
    return (*row, notes)


def roi_section(ctx: ReportContext, extra_rows: Sequence[Row] = (), rules: str | None = None) -> str:
    """The region of interest the search used, with the rules it was computed by (``rules``: markdown in
    their place)."""
    reg = ctx.result.region
    if reg is None:
        return ""
    head = [f"{reg.inner} [{ctx.u(reg.inner)}]"] + ([f"{reg.outer} [{ctx.u(reg.outer)}]"] if reg.outer else [])
    rows = [region_row(f"ours ({reg.source})", reg, "; ".join(reg.notes) or "–"), *extra_rows]
    if reg.source == "manual":
        intro = "The region is given in the study file (`stages.roi.manual`).\n\n"
    else:
        rules = rules if rules is not None else quoted(roi_rules(reg.inner, reg.outer))
        intro = "Our region is computed from the grid (`fmusa/analysis/roi.py`):\n\n" + rules + "\n\n"
    return "### Region of interest\n\n" + intro + table(["region", *head, "notes"], rows) + "\n"


# ============================================================================ results: optimum, binding
def search_outer(ctx: ReportContext) -> str | None:
    s = ctx.result.search
    return getattr(s, "outer", ctx.outer) if s is not None else ctx.outer


def optimum_row(ctx: ReportContext, label: str, opt: Mapping, row: Mapping | None, binding: str,
                extra: Sequence[str] = (), sig: Sig = _sig5) -> tuple:
    inner, outer = ctx.inner, search_outer(ctx)
    cells = [label, fmt(opt[inner], 7)] + ([fmt(opt[outer], 6)] if outer else [])
    return (*cells, *extra, *(fmt(row.get(m), sig(m)) if row else "–" for m in ctx.response_metrics()), binding)


def optimum_section(ctx: ReportContext, label: str | None = None, sig: Sig = _sig5,
                    extra_columns: Sequence[tuple[str, Callable[[Mapping], str]]] = (),
                    extra_rows: Sequence[Row] = (), stop_label: str = "the search") -> str:
    """The search's optimum and its response; ``extra_columns`` (title, optimum → text) follow the
    parameters, ``extra_rows`` (complete rows) follow the search's own row."""
    res = ctx.result
    if res.search is None:
        return ""
    inner, outer = ctx.inner, search_outer(ctx)
    ms = ctx.response_metrics()
    label = label or (f"search ({res.region.source} region)" if res.region is not None else "search")
    header = ["", f"{inner} [{ctx.u(inner)}]", *([f"{outer} [{ctx.u(outer)}]"] if outer else []),
              *(t for t, _ in extra_columns), *(f"{m} [{ctx.u(m)}]" for m in ms), "binding constraint(s)"]
    opt = res.search.optimum
    if opt is not None:
        rows = [optimum_row(ctx, label, opt, res.search.row, ", ".join(res.search.binding) or "–",
                            [fn(opt) for _, fn in extra_columns], sig)]
    else:
        rows = [(label, "none found", *([""] if outer else []), *("" for _ in extra_columns), *("" for _ in ms),
                 res.search.stop_reason)]
    out = "### Optimum\n\n" + table(header, [*rows, *extra_rows]) + "\n"
    if opt is not None:
        out += f"\nStop rule of {stop_label}: {res.search.stop_reason}.\n"
        for w in res.search.warnings:
            out += f"\n- warning: {w}\n"
    if opt is not None:
        for note in res.summary.get("optimum_at_edge") or []:
            out += f"\n- note: {note}\n"
        for note in (res.summary.get("optimum_free") or {}).values():
            out += f"\n- note: {note}\n"
    acc = res.summary.get("accuracy")
    if opt is not None and acc:
        out += (f"\n**This optimum is unreliable**: the accuracy checks (sections on sampling and on the FMU's "
                f"steps) moved the constrained metric(s) {', '.join(acc['metrics'])}, on which every run's "
                f"feasibility rests:\n\n" + "".join(f"- {w}\n" for w in acc["warnings"]))
    return out


def binding_section(ctx: ReportContext, explanation: str = "") -> str:
    """Which constraints fail just below the optimum (the search's last infeasible point there)."""
    res = ctx.result
    if res.search is None or res.search.optimum is None:
        return ""
    inner, outer = ctx.inner, search_outer(ctx)
    opt = res.search.optimum
    best = next((lv for lv in res.search.levels if lv.inner is not None and lv.row is not None
                 and lv.inner == opt[inner] and (outer is None or lv.outer == opt[outer])), None)
    out = "### Binding constraint\n\n"
    if best is None or best.below is None:
        return out + "No infeasible run below the optimum was recorded.\n" + explanation
    b, r = best.below, best.row
    items = []
    for c in ctx.study.constraints:
        bound = f" vs {fmt(c.max)}" if c.max is not None else (f" vs ≥ {fmt(c.min)}" if c.min is not None else "")
        items.append(f"`{c.name}` {ok_mark(b.get(f'ok_{c.name}'))} ({c.metric} = {fmt(b.get(c.metric), 5)} "
                     f"{ctx.u(c.metric)}{bound})")
    out += (f"Just below the optimum, at {inner} = {fmt(b[inner], 7)} {ctx.u(inner)} (the last infeasible "
            f"bisection point, {(r[inner] - b[inner]) / r[inner] * 100:.3f} % lower), the constraints read: "
            + "; ".join(items) + ".\n")
    return out + explanation


# ============================================================================ results: search path
def level_binding(ctx: ReportContext, level: Mapping, stages: Sequence[str], inner_range) -> str:
    """Which constraints fail at the largest infeasible inner value below the level's result."""
    runs, inner, outer = ctx.runs, ctx.inner, search_outer(ctx)
    if level.get("inner") is None or not len(runs):
        return "–"
    sel = (runs[inner] < float(level["inner"])) & runs["stage"].isin(list(stages) + ["grid"])
    if inner_range is not None:
        sel &= runs[inner] >= inner_range[0] * (1 - 1e-12)
    if outer is not None and level.get("outer") is not None:
        sel &= np.isclose(runs[outer].astype(float), float(level["outer"]), rtol=1e-12)
    g = runs[sel]
    g = g[~g["feasible"].astype(bool)]
    if not len(g):
        return "–"
    b = g.loc[g[inner].idxmax()]
    return ", ".join(c.name for c in ctx.study.constraints if not bool(b.get(f"ok_{c.name}", True))) or "–"


def _rel_changes(prev: Mapping | None, cur: Mapping | None, metrics: Sequence[str]) -> str:
    if not prev or not cur:
        return "–"
    best, name = -1.0, ""
    for m in metrics:
        a, b = prev.get(m), cur.get(m)
        if a is None or b is None:
            continue
        a, b = float(a), float(b)
        if math.isnan(a) != math.isnan(b):
            return f"{m}: value ↔ none"
        if math.isnan(a):
            continue
        r = abs(a - b) / max(abs(a), abs(b), 1e-300)
        if r > best:
            best, name = r, m
    return f"{best:.2e} ({name})" if best >= 0 else "–"


def search_table(ctx: ReportContext, levels: Sequence[dict], stages: Sequence[str], inner_range,
                 sig: Sig = _sig5) -> str:
    """One row per outer level of a search (one row in all for a search without outer parameter)."""
    inner, outer = ctx.inner, search_outer(ctx)
    metrics = ctx.response_metrics()
    rows, prev = [], None
    for k, lv in enumerate(levels):
        resp = lv.get("response") or {}
        outer_cell = [fmt(lv.get("outer"), 6)] if outer else []
        rows.append((k, *outer_cell, fmt(lv["inner"], 7) if lv.get("inner") is not None else "none",
                     *(fmt(resp.get(m), sig(m)) if resp else "–" for m in metrics),
                     lv.get("evaluations", "–"),
                     {None: "–", True: "yes", False: "no"}.get(lv.get("changed"), str(lv.get("changed"))),
                     _rel_changes(prev, resp, metrics) if prev else "–",
                     level_binding(ctx, lv, stages, inner_range), lv.get("note") or ""))
        if resp and lv.get("inner") is not None:
            prev = resp
    return table(["#", *([f"{outer} [{ctx.u(outer)}]"] if outer else []), f"smallest {inner} [{ctx.u(inner)}]",
                  *(f"{m} [{ctx.u(m)}]" for m in metrics), "evaluations", "changed?",
                  "largest relative change vs previous", "fails just below", "note"], rows)


def stage_runs_text(ctx: ReportContext) -> str:
    """"FMU runs per stage" from summary["stage_runs"] ({stage: count or {asked, simulated}}); "" without."""
    sr = ctx.summary.get("stage_runs")
    if not isinstance(sr, Mapping) or not sr:
        return ""
    parts = []
    for stage, v in sr.items():
        if isinstance(v, Mapping) and not any(v.values()):
            continue          # a stage that runs nothing (roi, regression)
        if isinstance(v, Mapping):
            asked, sim, rounds = v.get("asked"), v.get("simulated"), v.get("rounds")
            text = (f"{stage}: {asked} asked, {sim} simulated" if asked is not None else
                    f"{stage}: " + ", ".join(f"{k} {x}" for k, x in v.items() if k != "rounds"))
            if rounds is not None and sim:
                text += f" in {rounds} round{'s' if rounds != 1 else ''} of new runs"
            parts.append(text)
        else:
            parts.append(f"{stage}: {v}")
    return ("\nFMU runs per stage (points asked for, a point asked twice counted twice; simulated: the new "
            "runs, the rest were already stored; rounds: batches of new runs waited for one after another, "
            "the wall time of an FMU that costs seconds per run): "
            + "; ".join(parts) + ".\n" + rounds_text(ctx.summary))


def rounds_text(summary: Mapping) -> str:
    """How a search in rounds (search.parallel) compares with the sequential search; "" without one."""
    out = []
    for key, what in (("search", "The search"), ("paper_roi_search", "The search in the paper's region")):
        par = (summary.get(key) or {}).get("parallel") if isinstance(summary.get(key), Mapping) else None
        if not par:
            continue
        out.append(f"{what} asked for {par['runs']} points in {par['rounds']} rounds of up to {par['workers']} "
                   f"({par['speculative_runs']} for levels past the stop; a point already stored is not run "
                   f"again); the sequential search asks for {par['sequential_rounds']} points, one per round, "
                   f"for the same answers.")
    return ("\n" + " ".join(out) + "\n") if out else ""


def search_section(ctx: ReportContext, sig: Sig = _sig5, extra: str = "") -> str:
    """The search level by level: the smallest feasible inner value at each outer level, the response, the
    stop test and which constraint fails just below; ``extra`` follows the stop reason."""
    res = ctx.result
    if res.search is None:
        return ""
    stage, outer = ctx.study.stages["search"], search_outer(ctx)
    floors = ", ".join(f"{m}: {a:g} {ctx.u(m)}".rstrip() for m, a in stage.response_atol.items() if a > 0)
    region = res.region
    if region is not None and outer and region.outer_range:
        halved = f" ({outer} halved from {fmt(region.outer_range[1])} {ctx.u(outer)})"
    elif region is not None:
        halved = (f" (one bisection of {ctx.inner} in [{fmt(region.inner_range[0])}, {fmt(region.inner_range[1])}] "
                  f"{ctx.u(ctx.inner)})")
    else:
        halved = ""
    out = "### Search path\n\n"
    out += (f"{(region.source if region is not None else 'search').capitalize()} region{halved}. "
            f"'changed?' is the search's own test (any response metric differs by more than "
            f"{stage.response_rtol:g} relative from the previous feasible level"
            + (f" and by more than its absolute floor ({floors})" if floors else "") + "); "
            f"'fails just below' names the constraints violated at the largest infeasible {ctx.inner} "
            f"the bisection tried at that level.\n\n")
    out += search_table(ctx, get(ctx.summary, "search", "levels", default=[]), ["search"],
                        region.inner_range if region is not None else None, sig) + "\n"
    out += f"\nStop: {res.search.stop_reason}.\n"
    return out + stage_runs_text(ctx) + extra


# ============================================================================ results: regression
def _fit_rows(fits: Mapping[str, dict], names: Sequence[str]) -> list[Row]:
    rows = []
    n = len(names)
    for level, fit in sorted(fits.items(), key=lambda kv: -float(kv[0]) if kv[0] != "all" else 0):
        lab = fmt(float(level), 6) if level != "all" else level
        co = fit.get("coefficients")
        if co is None:
            rows.append((lab, fit.get("n"), *("–" for _ in range(n + 1)), fit.get("note", "")))
            continue
        xr = fit.get("x_range", [math.nan, math.nan])
        rows.append((lab, fit["n"], *(fmt(c, 4) for c in co[:n]), f"{fit['r2']:.4f}", f"[{fmt(xr[0])}, {fmt(xr[1])}]"))
    return rows


def regression_source_text(ctx: ReportContext) -> str:
    src = ctx.summary.get("regression_source") or ("search" if ctx.summary.get("search") else "grid")
    return f"the {src} runs"


def regression_section(ctx: ReportContext, heading: str | None = None,
                       coefficient_names: Sequence[str] | None = None, fitted_on: str | None = None,
                       extra_rows: Callable[[str], Sequence[Row]] | None = None, footer: str = "") -> str:
    """One table per fitted metric: the polynomial's coefficients (increasing powers), R² and the x range
    of each fit; ``extra_rows(metric)`` adds rows under a metric's fits."""
    reg = ctx.summary.get("regression")
    if not reg:
        return ""
    stage = ctx.study.stages.get("regression")
    x, by, degree = getattr(stage, "x", ctx.inner), getattr(stage, "by", None), getattr(stage, "degree", 3)
    names = list(coefficient_names or [f"a{k}" for k in range(degree + 1)])
    heading = heading or (f"### Regression (degree-{degree} polynomial in {x}: y = "
                          + " + ".join(n + ("" if k == 0 else "·x" if k == 1 else f"·x^{k}") for k, n in enumerate(names)) + ")")
    fitted_on = fitted_on or regression_source_text(ctx)
    out = f"{heading}\n\n"
    for m, fits in reg.items():
        rows = _fit_rows(fits, names) + list(extra_rows(m) if extra_rows else [])
        per = f"one fit per {by} level of {fitted_on}" if by else f"one fit over all of {fitted_on}"
        out += f"**{m}** [{ctx.u(m)}] over {x} [{ctx.u(x)}], {per}:\n\n"
        out += table([f"{by} [{ctx.u(by)}]" if by else "fit", "n", *names, "R²", f"{x} range"], rows) + "\n\n"
    return out + footer


# ============================================================================ results: failed runs
def failed_section(ctx: ReportContext, limit: int = 30) -> str:
    """Every failed run (up to ``limit``) with its stage, parameters and the FMU's reason."""
    runs = ctx.runs
    if not len(runs) or "status" not in runs:
        return ""
    bad = runs[runs["status"] != "ok"]
    if not len(bad):
        return ""
    names = [n for n in ctx.study.parameters if n in bad]
    rows = []
    for _, r in bad.head(limit).iterrows():
        msg = str(r.get("message", "") or "").replace("\n", " ").strip()     # the FMU's log: escaped
        rows.append((r.get("stage", "–"), *(fmt(r[n], 6) for n in names), md_text(r["status"]),
                     md_text((msg[:300] + "…") if len(msg) > 300 else (msg or "–"))))
    out = (f"### Failed runs\n\n{len(bad)} run{'s' if len(bad) > 1 else ''} failed; "
           f"{'the first ' + str(limit) + ' are' if len(bad) > limit else 'each is'} listed with the reason "
           f"recorded in runs.csv (column `message`). The stages went on without them.\n\n")
    return out + table(["stage", *(f"{n} [{ctx.u(n)}]" for n in names), "status", "reason"], rows) + "\n"


# ============================================================================ sampling
def _sampling_rows(ctx: ReportContext, checks: Sequence[Mapping]) -> list[Row]:
    rows = []
    for c in checks:
        m, pt = c.get("metric"), c.get("point") or {}
        ref, val, err, bound = c.get("reference"), c.get("value"), c.get("error"), c.get("bound")
        btxt = (f"h²/8·|y''| = {fmt(bound, 2)}" if c.get("reduce") != "settle" else f"± {fmt(bound, 2)}")
        rows.append((", ".join(f"{n} = {fmt(v, 5)}" for n, v in pt.items()), m, fmt(val, 5),
                     btxt + (f" {ctx.u(m)}" if ctx.u(m) else ""), fmt(ref, 5), fmt(err, 2),
                     fmt(err / abs(ref), 2) if ref and err is not None else "–", yes(c.get("within_bound"))))
    return rows


def _sampling_intro(ctx: ReportContext, s: Mapping, sampled: Sequence) -> str:
    h, f = s.get("step"), s.get("refine_factor")
    h_eff = s.get("interval_at_peaks", h)
    peaks = [m.name for m in sampled if m.reduce != "settle"]
    settles = [m.name for m in sampled if m.reduce == "settle"]
    out = (f"The metrics {', '.join(f'`{m.name}`' for m in sampled)} are taken from outputs sampled every "
           f"h = {h:g} s (`scenario.step`), not from monitors inside the FMU. ")
    if peaks:
        out += (f"A peak ({', '.join(peaks)}) is the largest sample: the true peak lies within h/2 of a "
                f"sample, so for a smooth peak the sampled value is low by at most h²/8·|y''|, with |y''| "
                f"the second derivative at the peak (estimated from the samples around it). ")
    if settles:
        out += (f"A settling time ({', '.join(settles)}) is the first sample inside the band: it is late by "
                f"up to one interval, ± {h_eff:g} s. ")
    if f:
        out += (f"With `refine_peaks` (factor {f}) every run is re-run with {f} times finer communication "
                f"steps in the intervals next to its peak and settling samples, so the interval there is "
                f"{h_eff:g} s: the peak bound shrinks by {f * f}, the settling time's resolution by {f}. ")
    else:
        out += ("`scenario.refine_peaks: true` re-runs every run with finer steps around those samples "
                "(see the README). ")
    return out + ("The table measures it on a few runs: the value as the study computed it, the bound, and the "
                  "value from a re-run sampled 100 times finer still around the same samples (a true peak "
                  "between samples far from the sampled one, as with an oscillation the step does not resolve, "
                  "is missed by both).\n\n")


def sampling_section(ctx: ReportContext) -> str:
    """How the output sampling moves the metrics taken from samples, as the pipeline measured it
    (summary["sampling"], :mod:`fmusa.pipeline.sampling_check`)."""
    from fmusa.runs.metrics import SAMPLED_REDUCTIONS

    s = ctx.summary.get("sampling")
    if not isinstance(s, Mapping) or s.get("step") is None:
        return ""
    ctx.notes.extend(s.get("notes") or [])
    sampled = [m for m in ctx.study.metrics.values() if m.reduce in SAMPLED_REDUCTIONS]
    out = "## Sampling of the outputs\n\n" + _sampling_intro(ctx, s, sampled)
    rows = _sampling_rows(ctx, s.get("checks") or [])
    if rows:
        out += table(["run", "metric", "sampled value", "bound from sampling", "finer re-run", "difference",
                      "relative", "within bound?"], rows) + "\n"
    return out


# ============================================================================ sensitivity
def _sensitivity_rows(summ: Mapping) -> list[Row]:
    rows = []
    for key, label in (("runs", "distinct runs"), ("failed", "failed runs"), ("simulated", "simulated this session"),
                       ("wall_s", "wall time [s]"), ("runs_per_s", "runs per second")):
        if summ.get(key) is not None:
            v = summ[key]
            rows.append((label, fmt(v, 4) if isinstance(v, float) else v))
    for method, n in (summ.get("samples") or {}).items():
        rows.append((f"runs of {method}", n))
    acc = summ.get("accuracy_check")
    if isinstance(acc, Mapping) and acc.get("max_rel_diff") is not None:
        rows.append(("accuracy check: largest relative difference to reference runs", fmt(acc["max_rel_diff"], 3)))
    return rows


def _sensitivity_figures(ctx: ReportContext, sens, summ) -> tuple[list[Path], str]:
    try:
        from fmusa.report.sensitivity_figures import plot_sensitivity
        return list(plot_sensitivity(sens, ctx.figdir)), ""
    except OutputError:     # a full disk: the study's error, not a note
        raise
    except Exception:  # noqa: BLE001 - older/other sensitivity results: our own bar charts
        try:
            return F.sensitivity_figures(summ, ctx.figdir), ""
        except OutputError:
            raise
        except Exception as exc:  # noqa: BLE001
            return [], f"The sensitivity figures could not be drawn ({type(exc).__name__}: {exc}).\n\n"


#: The index each method ranks by, and how its interval is written.
_RANK_INDEX = {"morris": ("mu_star", "μ*"), "sobol": ("ST", "ST"), "pce": ("ST", "ST")}


def _with_interval(method: str, d: Mapping, key: str) -> str:
    """"value [lo, hi]" of one index, its 95 % interval (Saltelli's and Morris' ± half-width, the polynomial
    chaos' bootstrap percentiles)."""
    v = d.get(key)
    if v is None:
        return "–"
    if method == "pce":
        lo, hi = d.get(f"{key}_lo"), d.get(f"{key}_hi")
    else:
        h = d.get(f"{key}_conf")
        lo, hi = (None, None) if h is None else (v - h, v + h)
    return f"{fmt(v, 3)} [{fmt(lo, 3)}, {fmt(hi, 3)}]" if lo is not None else fmt(v, 3)


def _top_inputs(ctx: ReportContext, summ: Mapping) -> list[Row]:
    rows = []
    for method in ("morris", "sobol", "pce"):
        for metric, tab in (summ.get(method) or {}).items():
            if not isinstance(tab, Mapping) or not tab:
                continue
            key, label = _RANK_INDEX[method]
            order = sorted((n for n in tab if tab[n].get(key) is not None), key=lambda n: -tab[n][key])[:4]
            unit = (ctx.u(metric) or "–") if method == "morris" else "–"
            rows.append((method, metric, f"{label} [{unit}]",
                         "; ".join(f"{n} {_with_interval(method, tab[n], key)}" for n in order)))
    return rows


def _pce_rows(summ: Mapping) -> list[Row]:
    val = summ.get("pce_validation") or {}
    rows = []
    for metric, v in (val.get("metrics") or {}).items():
        rows.append((metric, fmt(v.get("loo_error"), 2), fmt(v.get("target_error"), 2), v.get("degree"),
                     v.get("terms"), v.get("runs"), v.get("failed"),
                     v.get("status", "") if v.get("trusted") else "**not trusted**"))
    return rows


def _pce_text(summ: Mapping) -> str:
    val = summ.get("pce_validation") or {}
    if not val:
        return ""
    out = (f"Polynomial chaos: a sparse expansion fitted on {val.get('runs')} runs ({val.get('design')} design, "
           f"{len(val.get('rounds') or [])} rounds of up to {val.get('batch')} runs, budget {val.get('max_runs')}), "
           f"{'stopped at its target' if val.get('reached') else 'stopped by its budget, target not reached'}. "
           f"The validation error is the leave-one-out error (corrected for the basis size) as a share of the "
           f"output's variance; above the target the indices may be off by about that share, above 0.01 the "
           f"expansion does not follow the output and its indices are not trusted. Intervals: 95 % bootstrap over the "
           f"design (they do not hold the expansion's own error, which the validation error measures).\n\n")
    rows = _pce_rows(summ)
    if rows:
        out += table(["output", "validation error", "target", "degree", "terms", "runs", "failed", "verdict"],
                     rows) + "\n\n"
    return out


def _statements_text(summ: Mapping) -> str:
    """What the indices do not resolve, and the stage's notes (SALib's warnings among them)."""
    lines = []
    for group, per in (summ.get("statements") or {}).items():
        for metric, items in per.items():
            for it in items:
                lines.append(f"- {group} / {metric}: {it}")
    for m in summ.get("messages") or []:     # SALib's words among them: escaped
        lines.append(f"- {md_text(m)}")
    if not lines:
        return ""
    return "What these indices do not tell:\n\n" + "\n".join(lines) + "\n\n"


def sensitivity_section(ctx: ReportContext) -> str:
    """The global sensitivity analysis: its runs, its figures, the most influential inputs with their
    intervals, the polynomial chaos' validation, and what the indices do not resolve."""
    sens = ctx.result.sensitivity
    if sens is None:
        return ""
    summ = sens.get("summary", sens) if isinstance(sens, Mapping) else {}
    out = "## Global sensitivity analysis\n\n"
    stage = ctx.study.stages.get("sensitivity")
    if stage is not None:
        out += (f"Methods: {', '.join(stage.methods)}; {len(stage.parameters)} inputs; outputs: "
                f"{', '.join(stage.outputs)}.\n\n")
    rows = _sensitivity_rows(summ) if isinstance(summ, Mapping) else []
    if rows:
        out += table(["item", "value"], rows) + "\n\n"
    if isinstance(summ, Mapping):
        out += _pce_text(summ)
    paths, err = _sensitivity_figures(ctx, sens, summ)
    out += err
    captions = {"sensitivity_morris.png": "Morris screening: μ* (mean absolute elementary effect) against σ per output.",
                "sensitivity_sobol.png": "Sobol first-order (S1) and total (ST) indices per output (Saltelli's scheme).",
                "sensitivity_pce.png": "Sobol indices from the polynomial chaos expansion, with bootstrap intervals.",
                "sensitivity_pce_validation.png": "Polynomial chaos validation: runs against leave-one-out predictions."}
    for p in map(Path, paths):
        page = re.fullmatch(r"(.+)_(\d+)(\.png)", p.name)      # a further page of a figure of many outputs
        if page and page[1] + page[3] in captions:
            cap = captions[page[1] + page[3]][:-1] + f" (continued, page {page[2]})."
        else:
            cap = captions.get(p.name, "Sensitivity indices.")
        ctx.add_figure(p.name, cap)
        out += figure_markdown(p.name, cap)
    trows = _top_inputs(ctx, summ) if isinstance(summ, Mapping) else []
    if trows:
        out += "The four most influential inputs per output, with 95 % intervals:\n\n"
        out += table(["method", "output", "index", "largest: value [95 % interval]"], trows) + "\n\n"
    if isinstance(summ, Mapping):
        out += _statements_text(summ)
    for method, per in ((summ.get("errors") if isinstance(summ, Mapping) else None) or {}).items():
        for metric, msg in (per or {}).items():
            out += f"- {method} / {metric}: {msg[:400]}\n"
    if not paths and not trows:
        out += "The sensitivity results hold no index table this report recognises; see summary.json.\n"
    return out


# ============================================================================ notes, files
def figures_list_section(ctx: ReportContext) -> str:
    """"## Figures": every figure drawn so far, with its caption."""
    if not ctx.figures:
        return ""
    return "## Figures\n\n" + "".join(figure_markdown(n, c) for n, c in ctx.figures)


def notes_section(ctx: ReportContext) -> str:
    if not ctx.notes:
        return ""
    return "## Notes\n\n" + "\n".join(f"- {n}" for n in ctx.notes) + "\n"


def files_section(ctx: ReportContext) -> str:
    names = list(dict.fromkeys(n for n, _ in ctx.figures))
    return ("## Files\n\n- `runs.csv`: one row per run (parameters, metrics, constraint flags, status)\n"
            "- `summary.json`: the machine-readable results\n- `figures/`: "
            + ", ".join(f"`{n}`" for n in names) + "\n")
