"""Applications of the generic engine: the paper's study (``paper:`` block) and the C6/C7 shear data set.

A study file switches an application on with a top-level block. For each block this module names what the
application adds: the block's schema (checked at load, :func:`study_blocks`), the FMU work after the
pipeline's stages (:func:`extensions_for`) and the report's sections (:func:`report_sections_for`).
"""
from __future__ import annotations


def study_blocks() -> dict:
    """Validators of the application blocks a study file may hold, by top-level key (for the loader)."""
    from fmusa.applications.paper.schema import validate_paper_block
    return {"paper": validate_paper_block}


def extensions_for(study, report: bool = True) -> list:
    """The pipeline extensions the study's application blocks ask for; ``report`` False skips the FMU
    work that only the report needs."""
    out = []
    if study.paper:
        from fmusa.applications.paper.extension import PaperExtension
        out.append(PaperExtension(study.paper, report=report))
    return out


def report_sections_for(study) -> list:
    """The report sections the study's application blocks add (see fmusa.report.context.ReportSection)."""
    if study.paper:
        from fmusa.applications.paper.report import paper_sections
        return paper_sections()
    return []
