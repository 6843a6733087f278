"""The paper's study as an application of the generic pipeline: what it adds after the study's stages.

Enabled by the study's ``paper:`` block. The paper chose its region of interest by hand; with the block's
``roi`` and an automatic region, the same search is run a second time inside the paper's region, so the
report can set both optima next to the paper's printed one.
"""
from __future__ import annotations

from fmusa.analysis.regression import fit_by_level
from fmusa.analysis.roi import Region
from fmusa.analysis.search import nested_binary_search
from fmusa.pipeline.sweep import StudyRunner, SweepResult, search_summary

PAPER_SEARCH_STAGE = "search_paper_roi"


class PaperExtension:
    """The paper's extra FMU work: the search inside the paper's hand-chosen region."""
    name = "paper"

    def __init__(self, block: dict) -> None:
        self.block = block

    def after_stages(self, result: SweepResult, runner: StudyRunner) -> None:
        study, summary = result.study, result.summary
        part: dict = {}
        result.extra[self.name] = part
        stage, roi = study.stages.get("search"), study.stages.get("roi")
        paper_roi = self.block.get("roi")
        if not paper_roi or stage is None or result.region is None or getattr(roi, "manual", None):
            return
        inner, outer = stage.inner, stage.outer
        region = Region(inner, outer, tuple(map(float, paper_roi[inner])), tuple(map(float, paper_roi[outer])),
                        "paper (by hand)")
        response = list(stage.response)
        search = nested_binary_search(lambda p: runner.evaluate_one(p, PAPER_SEARCH_STAGE), region, response,
                                      stage.inner_rtol, stage.response_rtol, stage.max_outer, stage.response_atol)
        part.update(region=region, search=search)
        summary["paper_roi_search"] = search_summary(search)
        reg = study.stages.get("regression")
        if reg is not None:
            runs = runner.store.frame()
            pp = runs[runs["stage"] == PAPER_SEARCH_STAGE]
            summary["regression_paper_roi"] = fit_by_level(pp, reg.x, list(reg.y), reg.by, reg.degree)
