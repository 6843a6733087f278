"""Applications of the generic engine: the paper's study (``paper:`` block) and the C6/C7 shear data set.

:func:`extensions_for` is how a study file switches an application on: each top-level block it names
maps to the extension that adds that application's FMU work after the pipeline's stages.
"""
from __future__ import annotations


def extensions_for(study) -> list:
    """The pipeline extensions the study's application blocks ask for."""
    out = []
    if study.paper:
        from fmusa.applications.paper.extension import PaperExtension
        out.append(PaperExtension(study.paper))
    return out
