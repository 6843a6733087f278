"""The paper's study as an application of the generic pipeline: what it adds after the study's stages.

Enabled by the study's ``paper:`` block. The paper chose its region of interest by hand; with the block's
``roi`` and an automatic region, the same search is run a second time inside the paper's region, so the
report can set both optima next to the paper's printed one. For the report (``report=True``) it also runs
the physics of the ramp and end times (:mod:`fmusa.applications.paper.physics`) and samples the pullout at
our optimum, so that the report itself only renders data.

Everything lands in ``result.extra["paper"]``: ``region``, ``search`` (the second search), ``physics``
(:class:`~fmusa.applications.paper.physics.PaperPhysics`), ``time_series`` and ``notes``.
"""
from __future__ import annotations

import time

from fmusa.analysis.regression import fit_by_level
from fmusa.analysis.roi import Region
from fmusa.applications.paper.physics import PaperScenario, compute_physics, optimum_time_series
from fmusa.pipeline.sweep import StudyRunner, SweepResult, search_summary

PAPER_SEARCH_STAGE = "search_paper_roi"


class PaperExtension:
    """The paper's extra FMU work: the search inside the paper's hand-chosen region, and (for the report)
    the ramp/end-time physics and the time series at the optimum."""
    name = "paper"

    def __init__(self, block: dict, report: bool = True) -> None:
        self.block = block
        self.report = report

    def after_stages(self, result: SweepResult, runner: StudyRunner) -> None:
        part: dict = {"notes": []}
        result.extra[self.name] = part
        self.search_paper_region(result, runner, part)
        if self.report:
            t0 = time.perf_counter()
            self.physics(result, runner, part)
            part["physics_wall_s"] = time.perf_counter() - t0

    def search_paper_region(self, result: SweepResult, runner: StudyRunner, part: dict) -> None:
        """The nested search again, inside the paper's region (``paper.roi``), when ours is automatic."""
        study, summary = result.study, result.summary
        stage, roi = study.stages.get("search"), study.stages.get("roi")
        paper_roi = self.block.get("roi")
        if not paper_roi or stage is None or result.region is None or getattr(roi, "manual", None):
            return
        inner, outer = stage.inner, getattr(stage, "outer", None)
        if outer is None or inner not in paper_roi or outer not in paper_roi:
            return
        region = Region(inner, outer, tuple(map(float, paper_roi[inner])), tuple(map(float, paper_roi[outer])),
                        "paper (by hand)")
        # the same search (sequential, or in rounds: then predicted by our search's answer, which lies
        # on the same lattice when the inner ranges agree)
        hints = [result.search.optimum[inner]] if result.search is not None and result.search.optimum else []
        search = runner.search(region, stage, PAPER_SEARCH_STAGE, hints=hints, warm_start=False)
        part.update(region=region, search=search)
        summary["paper_roi_search"] = search_summary(search)
        reg = study.stages.get("regression")
        if reg is not None:
            runs = runner.store.frame()
            pp = runs[runs["stage"] == PAPER_SEARCH_STAGE]
            summary["regression_paper_roi"] = fit_by_level(pp, reg.x, list(reg.y), reg.by, reg.degree)

    def physics(self, result: SweepResult, runner: StudyRunner, part: dict) -> None:
        """The ramp/end-time runs and the time series at our optimum (for the report only)."""
        search = result.search
        if search is None or search.optimum is None:
            return
        sc = PaperScenario.of(result.study, search.inner, getattr(search, "outer", None))
        if sc is not None:
            part["scenario"] = sc
            try:
                part["physics"] = compute_physics(result.study, runner.spec, sc, search.optimum, result.region,
                                                  runner.store.frame(), self.block)
            except Exception as exc:  # noqa: BLE001 - the extra runs must not cost the study
                part["notes"].append(f"The ramp/end-time runs failed: {type(exc).__name__}: {exc}")
        t_eq = float((search.row or {}).get("t_eq", float("nan")))
        t_ramp = result.study.fixed.get("t_ramp")
        try:
            part["time_series"] = optimum_time_series(result.study, runner.spec, search.optimum, t_eq,
                                                      float(t_ramp) if t_ramp is not None else None)
        except Exception as exc:  # noqa: BLE001 - an FMU without these outputs: no figure, say so
            part["notes"].append(f"The time-series figure was skipped: {type(exc).__name__}: {exc}")
