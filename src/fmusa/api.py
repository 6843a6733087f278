"""The public entry points a user calls: a study from its file to runs, summary, figures and report.

Composes the layers (pipeline, then the report) with the applications the study enables; the CLI's
``sweep`` and the README's Python examples go through :func:`run_study`.
"""
from __future__ import annotations

import time
from pathlib import Path

from fmusa.applications import extensions_for
from fmusa.pipeline.sweep import SweepResult, run_study as run_stages, write_summary
from fmusa.report.markdown import write_report
from fmusa.study.schema import Study


def run_study(study: Study, out: str | Path, resume: bool = False, workers: int | None = None,
              scheduler: str | None = None, figures: bool = True, progress: bool = True) -> SweepResult:
    """Every stage of ``study`` into ``out``: runs.csv and summary.json first, then (``figures``) the
    figures and report.md, drawn from the result without running the FMU again."""
    t0 = time.perf_counter()
    result = run_stages(study, out, resume=resume, workers=workers, scheduler=scheduler, progress=progress,
                        extensions=extensions_for(study))
    if figures:
        write_report(result)
        result.summary["wall_s_with_report"] = time.perf_counter() - t0
        write_summary(result)
    return result
