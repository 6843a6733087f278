"""The public entry points a user calls: a study from its file to runs, summary, figures and report.

Composes the layers (pipeline, then the report) with the applications the study enables; the CLI's
``sweep`` and the README's Python examples go through :func:`load_study` and :func:`run_study`.
"""
from __future__ import annotations

import os
import time
from pathlib import Path

from fmusa.files import OutputError
from fmusa.applications import extensions_for, report_sections_for, study_blocks
from fmusa.pipeline.sweep import SweepResult, run_study as run_stages, write_summary
from fmusa.report import markdown
from fmusa.study import loader
from fmusa.study.schema import Study

__all__ = ["load_study", "parse_study", "run_study", "write_report"]


def load_study(path: str | os.PathLike) -> Study:
    """Load and validate the study file ``path``, application blocks (``paper:``) included."""
    return loader.load_study(path, blocks=study_blocks())


def parse_study(text: str, path: str | os.PathLike = "<string>") -> Study:
    """:func:`load_study` from YAML text (``path`` for messages and relative paths)."""
    return loader.parse_study(text, path, blocks=study_blocks())


def write_report(result: SweepResult) -> Path:
    """figures/*.png and report.md of a finished study, with the sections of the applications it enables
    (the paper's when it has a ``paper:`` block); runs no FMU."""
    return markdown.write_report(result, report_sections_for(result.study))


def run_study(study: Study, out: str | Path, resume: bool = False, workers: int | None = None,
              scheduler: str | None = None, figures: bool = True, progress: bool = True,
              retry_failed: bool = False) -> SweepResult:
    """Every stage of ``study`` into ``out``: runs.csv and summary.json first, then (``figures``) the
    figures and report.md, drawn from the result without running the FMU again."""
    t0 = time.perf_counter()
    # the folder stays locked until the report is written: another study on the same out waits its turn
    result = run_stages(study, out, resume=resume, workers=workers, scheduler=scheduler, progress=progress,
                        extensions=extensions_for(study, report=figures), retry_failed=retry_failed,
                        hold_lock=True)
    try:
        if figures:     # runs.csv and summary.json are on disk already: a report that fails loses neither
            try:
                write_report(result)
            except OutputError as exc:
                raise type(exc)(f"{exc}. runs.csv and summary.json in {result.out} are complete; rerun with "
                                f"--resume once the folder is writable, or with --no-figures") from None
            result.summary["wall_s_with_report"] = time.perf_counter() - t0
            write_summary(result)
    finally:
        result.release()
    return result
