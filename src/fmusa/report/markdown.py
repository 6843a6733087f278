"""report.md and figures/*.png of any finished study, from its result alone (never runs an FMU).

:func:`write_report` renders the generic sections (:data:`GENERIC_SECTIONS`) in order; an application passes
its own :class:`~fmusa.report.context.ReportSection` objects to replace a generic section or to add one
before or after another (``api.run_study`` passes the paper's when the study has a ``paper:`` block).
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

from fmusa.files import atomic_write, writable_folder
from fmusa.report import fmu_sections
from fmusa.report import sections as S
from fmusa.report.context import ReportContext, ReportSection, Section
from fmusa.report.study_figures import figures_section

__all__ = ["write_report", "GENERIC_SECTIONS", "arrange_sections"]

#: The generic sections in report order; ``results.*`` are joined under the ``results`` heading.
GENERIC_SECTIONS: tuple[Section, ...] = (
    Section("title", S.title_section),
    Section("what_was_run", S.what_was_run_section),
    Section("results", S.results_heading),
    Section("results.grid", S.grid_section),
    Section("results.roi", S.roi_section),
    Section("results.optimum", S.optimum_section),
    Section("results.binding", S.binding_section),
    Section("results.search", S.search_section),
    Section("results.regression", S.regression_section),
    Section("results.failed", S.failed_section),
    Section("sampling", S.sampling_section),
    Section("fmu_runs", fmu_sections.fmu_runs_section),
    Section("fmu_steps", fmu_sections.fmu_steps_section),
    Section("figures", figures_section),
    Section("sensitivity", S.sensitivity_section),
    Section("notes", S.notes_section),
    Section("files", S.files_section),
)


def arrange_sections(extra: Sequence[ReportSection] = ()) -> list[ReportSection]:
    """The generic sections with ``extra`` applied by their placement: ``replace`` a section of the same
    key, ``before:<key>`` / ``after:<key>`` another; a section whose anchor is missing goes before notes."""
    order: list[ReportSection] = list(GENERIC_SECTIONS)
    for sec in extra:
        keys = [s.key for s in order]
        how, _, anchor = sec.placement.partition(":")
        if how == "replace" and sec.key in keys:
            order[keys.index(sec.key)] = sec
            continue
        if how in ("before", "after") and anchor in keys:
            i = keys.index(anchor)
            if how == "after":     # after the anchor and its sub-sections
                while i + 1 < len(order) and order[i + 1].key.startswith(anchor + "."):
                    i += 1
                i += 1
            order.insert(i, sec)
            continue
        order.insert(keys.index("notes") if "notes" in keys else len(order), sec)
    return order


def _render(ctx: ReportContext, order: Sequence[ReportSection]) -> list[str]:
    """The top-level parts in order; a parent's sub-sections are joined under it when any has text."""
    parts = []
    for sec in order:
        if "." in sec.key:
            continue
        children = [c for c in order if c.key.startswith(sec.key + ".")]
        if not children:
            parts.append(sec.render(ctx))
            continue
        texts = [t for t in (c.render(ctx) for c in children) if t]
        if texts:
            parts.append(sec.render(ctx) + "\n".join(texts))
    return parts


def write_report(result, sections: Sequence[ReportSection] = ()) -> Path:
    """Write ``<out>/figures/*.png`` and ``<out>/report.md`` for a finished study and set
    ``summary["figures"]`` (paths relative to ``<out>``); ``sections`` are an application's additions
    (see :func:`arrange_sections`). Returns the path of report.md."""
    out = Path(result.out)
    figdir = writable_folder(out / "figures", "figures folder")
    ctx = ReportContext(result, figdir)
    parts = _render(ctx, arrange_sections(sections))
    path = out / "report.md"
    atomic_write(path, "\n".join(p for p in parts if p))
    result.summary["figures"] = [f"figures/{n}" for n in dict.fromkeys(n for n, _ in ctx.figures)]
    return path
