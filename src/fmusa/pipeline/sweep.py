"""A study from its dataclasses to runs.csv and summary.json: every stage that runs the FMU.

Stages run in the order of the study file: grid → roi → search → regression → sensitivity. Every run goes
through one RunStore, so a point asked for twice is simulated once and an interrupted study resumes where
it stopped. Applications (the paper's study, say) add their own FMU work after the stages through
:class:`StudyExtension`; figures and report.md are drawn afterwards by :mod:`fmusa.report` from the result.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Mapping, Protocol, Sequence

import numpy as np
import pandas as pd

from fmusa.runs.evaluator import Evaluator
from fmusa.fmi.info import FMUCompileError, default_fmu_path
from fmusa.fmi.build import prepare_fmu
from fmusa.analysis.regression import fit_by_level
from fmusa.analysis.roi import Region, automatic_region, floor_region, grid_findings, inert_parameters, manual_region
from fmusa.runs.inflight import track_in_flight
from fmusa.runs.store import RunStore
from fmusa.runs.timelimit import own_fmu
from fmusa.analysis.search import SearchResult, edge_notes, nested_binary_search, search_in_rounds
from fmusa.files import atomic_write, move_aside, writable_folder
from fmusa.study.schema import Study, StudyError
from fmusa.runs.progress import progress_bar
from fmusa.pipeline.sampling_check import sampling_summary
from fmusa.pipeline.solver_check import accuracy_verdict, implausible_runs, solver_summary
from fmusa.study.plan import check_fmu, grid_points, reset_check_points, run_fingerprint, study_plan_spec
from fmusa.runs.preflight import preflight


#: What an earlier study in the same ``--out`` leaves besides its runs: moved aside with them by a fresh start.
EARLIER_OUTPUTS = ("report.md", "summary.json", "figures", "sensitivity_morris.csv", "sensitivity_sobol.csv")


@dataclass
class SweepResult:
    study: Study
    out: Path
    runs: pd.DataFrame
    summary: dict
    region: Region | None = None
    search: SearchResult | None = None
    sensitivity: dict | None = None
    #: results of study extensions, by extension name (plain data the report renders)
    extra: dict = field(default_factory=dict)
    #: releases the lock on ``out`` held for the report (run_study's ``hold_lock``); a no-op otherwise
    release: Callable[[], None] = field(default=lambda: None, repr=False)


class StudyExtension(Protocol):
    """FMU work an application adds after the study's stages (e.g. a second search inside a region chosen
    by hand), writing plain data into ``result.extra[name]`` and ``result.summary``."""
    name: str

    def after_stages(self, result: SweepResult, runner: "StudyRunner") -> None: ...


class StudyRunner:
    """Evaluates study points through the store (cache, resume) and the evaluator (pool, cluster)."""

    def __init__(self, study: Study, out: Path, resume: bool, workers: int | None, scheduler: str | None,
                 progress: bool = True, retry_failed: bool = False) -> None:
        self.study = study
        #: --resume --retry-failed: the stored failed runs are run again (sensitivity stages follow it too)
        self.retry_failed = retry_failed
        fmu_path = Path(study.fmu) if study.fmu else default_fmu_path()
        errors = check_fmu(study, fmu_path)
        if errors:
            n = len(errors)
            raise StudyError(f"{study.path}: the study does not fit the FMU {fmu_path} ({n} problem"
                             f"{'s' if n > 1 else ''}):\n  " + "\n  ".join(errors))
        opts = study.fmu_options
        try:   # an FMU without a binary for this machine is built from its sources, once, before any run
            run_path = prepare_fmu(fmu_path, opts.interface, workdir=Path(out) / ".fmu")
        except FMUCompileError as exc:
            raise FMUCompileError(f"{study.path}: {exc}") from None
        self.params = list(study.parameters)
        self.metrics = list(study.metrics)
        spec = study_plan_spec(study, run_path)
        #: what besides the parameters decides a run: a resumed study reuses stored runs only while it holds
        self.fingerprint = run_fingerprint(study, fmu_path)
        # any FMU but our own (by its digest) runs in supervised workers: a crash or hang then costs one run
        own = own_fmu(fmu_path)
        self.evaluator = Evaluator(spec, workers=workers or study.execution.workers,
                                   scheduler=scheduler or study.execution.scheduler,
                                   isolate=study.fmu is not None or not own,
                                   timeout_s=study.execution.timeout_s, pool=study.execution.pool_options(),
                                   own=own)
        try:   # a scheduler that cannot be reached fails here, before an earlier runs.csv is moved aside
            self.evaluator.connect()
            # the FMU loaded once, and how its runs must be made to equal runs on a fresh instance, before
            # anything is written (a binary that cannot load stops the study here, nothing moved aside)
            a, b = reset_check_points(study, spec)
            self.reuse = preflight(self.evaluator.check_spec(), a, b, isolate=self.evaluator.supervised_only,
                                   timeout_s=study.execution.timeout_s, digest=str(self.fingerprint.get("fmu")),
                                   start_method=study.execution.start_method, name=str(fmu_path))
            self.evaluator.set_reuse(self.reuse.mode)
            self.spec = replace(spec, reuse=self.reuse.mode)
            self.store = RunStore(out / "runs.csv", self.params, self.metrics, study.constraints, resume=resume,
                                  fingerprint=self.fingerprint, retry_failed=retry_failed)
            if self.store.previous is not None:     # the earlier study's report and figures go with its runs
                tag = self.store.previous.stem.rpartition(".")[2]           # previous-<n>
                move_aside(out, EARLIER_OUTPUTS, tag)
            #: runs under way when an earlier session's process ended: failed, or made again supervised
            self.recovered = track_in_flight(self.store, self.evaluator, resume)
        except BaseException:
            self.evaluator.close()
            raise
        self.progress = progress
        #: batches that simulated at least one new run: the study's wall time for an FMU that costs seconds
        self.rounds = 0
        self.simulated = 0
        #: points asked for (a repeated point counts again; the store simulates it once)
        self.asked = 0
        #: values of the study parameters a stage does not vary (the first grid point)
        self.defaults: dict[str, float] = {}

    def close(self, keep_lock: bool = False) -> None:
        """Stop the workers and close runs.csv; ``keep_lock``: the folder stays locked for this study until
        ``self.store.release()`` (its report is still to be written)."""
        self.evaluator.close()
        if self.evaluator.marker is not None:
            self.evaluator.marker.close()
        self.store.close(keep_lock=keep_lock)

    def evaluate(self, points: list[dict[str, float]], stage: str) -> list[dict]:
        """Rows for ``points`` (study parameter name → value), simulating only the new ones."""
        keys = [tuple(float(p[name]) for name in self.params) for p in points]
        self.asked += len(keys)
        todo: dict[tuple, int] = {}
        for k in keys:
            if self.store.get(k) is None and k not in todo:
                todo[k] = self.store.new_id()
        if todo:
            if self.evaluator.marker is not None:     # the label a run under way at a crash is stored under
                self.evaluator.marker.stage = stage
            bar = progress_bar(len(todo), stage, self.progress)
            items = [(rid, k) for k, rid in todo.items()]
            # results arrive as blocks (arrays) and go to runs.csv as one write each
            self.evaluator.map_batches(items, lambda batch: self.store.add_batch(stage, batch), progress=bar)
            self.simulated += len(items)
            self.rounds += 1
            if bar is not None:
                bar.close()
        return [self.store.get(k) for k in keys]

    def evaluate_one(self, point: dict[str, float], stage: str) -> dict:
        return self.evaluate_many([point], stage)[0]

    def evaluate_many(self, points: list[dict[str, float]], stage: str) -> list[dict]:
        """Rows for ``points`` run together (one round); parameters a point does not set keep the first
        grid value."""
        full = [dict(p) for p in points]
        for f in full:
            for name in self.params:
                f.setdefault(name, self.defaults[name])
        return self.evaluate(full, stage)

    def parallel_workers(self) -> int:
        """Points that run at once: the Dask cluster's threads, else the local workers."""
        return self.evaluator.parallel_workers()

    def search(self, region: Region, stage, tag: str, hints: Sequence[float] = (),
               warm_start: bool | None = None) -> SearchResult:
        """The search stage ``stage`` (a SearchStage) inside ``region``, its runs tagged ``tag``: in rounds
        of the study's workers (``parallel``), else the sequential search, one point at a time.
        ``warm_start`` None: the stage's."""
        response = list(stage.response)      # default: the constrained metrics (study.py)
        warm = stage.warm_start if warm_start is None else warm_start
        par = getattr(stage, "parallel", False)
        if par is False:
            return nested_binary_search(lambda p: self.evaluate_one(p, tag), region, response, stage.inner_rtol,
                                        stage.response_rtol, stage.max_outer, stage.response_atol,
                                        warm_start=warm)
        workers = self.parallel_workers() if par == "auto" or par is True else int(par)
        return search_in_rounds(lambda pts: self.evaluate_many(pts, tag), region, response, workers,
                                stage.inner_rtol, stage.response_rtol, stage.max_outer, stage.response_atol,
                                warm_start=warm, hints=hints)


def run_study(study: Study, out: str | Path, resume: bool = False, workers: int | None = None,
              scheduler: str | None = None, progress: bool = True,
              extensions: Sequence[StudyExtension] = (), retry_failed: bool = False,
              hold_lock: bool = False) -> SweepResult:
    """Run every stage of ``study`` into ``out`` (runs.csv as runs finish, summary.json at the end) and
    then each extension's ``after_stages``. Draws nothing: :func:`fmusa.report.markdown.write_report`
    renders the result. ``hold_lock``: a study that ends well keeps ``out`` locked against another study
    until ``result.release()`` (called once its report is written)."""


    out = writable_folder(out, "output folder (--out)")
    t0 = time.perf_counter()
    runner = StudyRunner(study, out, resume, workers, scheduler, progress, retry_failed=retry_failed)
    summary: dict[str, Any] = {"study": study.name, "study_file": str(study.path),
                               "fmu_runs": runner.reuse.as_dict()}
    result = SweepResult(study, out, pd.DataFrame(), summary)
    ended_well = False
    try:
        stage_times: dict[str, float] = {}
        stage_runs: dict[str, dict[str, int]] = {}     # FMU runs each stage asked for / simulated
        grid_df = None
        runner.defaults = {}
        for name, stage in study.stages.items():
            ts = time.perf_counter()
            asked0, simulated0, rounds0 = runner.asked, runner.simulated, runner.rounds
            if name == "grid":
                pts = grid_points(study)
                runner.defaults = dict(pts[0])
                runner.evaluate(pts, "grid")
                grid_df = runner.store.frame("grid")
                # values orders of magnitude beyond the rest (a solver that blew up) are not results: the
                # region of interest is found without them (summary["implausible"] lists them)
                bad = {i["run"] for i in implausible_runs(grid_df, runner.metrics)}
                if bad:
                    grid_df = grid_df.copy()
                    grid_df.loc[grid_df["run_id"].isin(bad), "status"] = "implausible"
                summary["grid"] = {"points": len(pts), "axes": {k: [float(x) for x in v]
                                                                for k, v in stage.points().items()},
                                   **grid_findings(grid_df, _grid_axes(study), list(study.metrics),
                                                   study.constraints)}
            elif name == "roi":
                search_stage = study.stages.get("search")
                if search_stage is None:
                    raise StudyError(f"{study.path}: stages.roi needs stages.search (the region spans its inner and outer parameters)")
                inner, outer = search_stage.inner, search_stage.outer      # outer None: an inner range
                runner.defaults.update(stage.at or {})     # where the search holds the other parameters
                if stage.manual:
                    result.region = manual_region(stage.manual, inner, outer)
                else:
                    if grid_df is None:
                        raise StudyError(f"{study.path}: an automatic region of interest needs stages.grid "
                                         f"before stages.roi (or give roi.manual)")
                    # the grid runs where the search will run: the other parameters at roi.at, else at
                    # their first grid values
                    at = {k: v for k, v in runner.defaults.items() if k not in (inner, outer)}
                    result.region = automatic_region(grid_df, inner, outer, at, study.constraints,
                                                     list(study.parameters))
                summary["roi"] = result.region.as_dict()
            elif name == "search":
                if result.region is None:
                    raise StudyError(f"{study.path}: stages.search needs stages.roi before it")
                result.region = floor_region(result.region, stage.inner_rtol)
                summary["roi"] = result.region.as_dict()
                result.search = runner.search(result.region, stage, "search")
                summary["optimum"] = result.search.optimum      # {inner: x} when the search has no outer
                summary["binding_constraint"] = result.search.binding
                summary["search"] = search_summary(result.search)
                if result.search.optimum:
                    notes = edge_notes(result.search, result.region, stage.inner_rtol)
                    free = _free_in_optimum(study, grid_df, result.search.optimum)
                    if notes:
                        summary["optimum_at_edge"] = notes
                    if free:
                        summary["optimum_free"] = free
            elif name == "regression":
                # the search's runs, or the grid's in a study without search (the loader decides: source)
                runs = runner.store.frame()
                pts = runs[runs["stage"] == stage.source]
                if stage.source == "search" and result.search is not None and stage.by is not None \
                        and stage.by == result.search.outer:
                    # the levels on the search's path only: a search in rounds also asks for levels past
                    # its stop (speculative points), which are no level of its answer
                    path = [lv.outer for lv in result.search.levels]
                    pts = pts[np.isin(pts[stage.by].to_numpy(dtype=float), np.asarray(path, dtype=float))]
                if not len(pts):
                    raise StudyError(f"{study.path}: stages.regression fits the {stage.source} runs, but there "
                                     f"are none; run the {stage.source} stage before the regression")
                summary["regression"] = fit_by_level(pts, stage.x, list(stage.y), stage.by, stage.degree)
                summary["regression_source"] = stage.source
            elif name == "sensitivity":
                from fmusa.pipeline.sensitivity import run_sensitivity
                result.sensitivity = run_sensitivity(study, stage, out, runner, progress=progress)
                summary["sensitivity"] = result.sensitivity["summary"]
            stage_times[name] = time.perf_counter() - ts
            stage_runs[name] = _stage_runs(runner, asked0, simulated0, rounds0)
        for ext in extensions:
            ts = time.perf_counter()
            asked0, simulated0, rounds0 = runner.asked, runner.simulated, runner.rounds
            ext.after_stages(result, runner)
            stage_times[ext.name] = time.perf_counter() - ts
            stage_runs[ext.name] = _stage_runs(runner, asked0, simulated0, rounds0)
        if runner.recovered:
            summary["recovered_runs"] = runner.recovered
        sampling = sampling_summary(study, runner.store.frame(), summary.get("optimum"), runner.spec)
        if sampling is not None:     # how the output sampling moves peaks and settling times
            summary["sampling"] = sampling
        runs = runner.store.frame()
        check_steps = study.execution.check_fmu_steps
        if check_steps is None:       # auto: every FMU but our own (its tests hold its solver to closed forms)
            check_steps = runner.evaluator.isolate
        if check_steps:               # how the FMU's own integration moves the metrics
            ts = time.perf_counter()
            steps = solver_summary(study, runs, summary.get("optimum"), runner.evaluator.local_spec(),
                                   isolate=runner.evaluator.isolate, workers=runner.evaluator.workers,
                                   scheduler=runner.evaluator.scheduler, sampling=summary.get("sampling"))
            if steps is not None:
                steps["wall_s"] = time.perf_counter() - ts
                summary["fmu_steps"] = steps
        accuracy = accuracy_verdict(study, summary.get("sampling"), summary.get("fmu_steps"))
        if accuracy is not None:     # a constrained metric moved when checked finer: the optimum rests on it
            summary["accuracy"] = accuracy
        if summary.get("optimum"):
            summary["optimum_reliable"] = accuracy is None
        implausible = implausible_runs(runs, runner.metrics)
        if implausible:
            summary["implausible"] = implausible
        result.runs = runs
        summary["runs"] = int(len(runs))
        summary["simulated_this_session"] = int(runner.simulated)
        summary["failed"] = int((runs["status"] != "ok").sum()) if len(runs) else 0
        summary["stage_wall_s"] = stage_times
        summary["stage_runs"] = stage_runs
        summary["rounds"] = int(runner.rounds)
        summary["run_counts"] = run_counts(summary)
        summary["wall_s"] = time.perf_counter() - t0
        runner.store.check_present()      # runs.csv still where it was written (its folder not removed)
        write_summary(result)
        ended_well = True
    finally:
        runner.close(keep_lock=hold_lock and ended_well)
    result.release = runner.store.release if hold_lock else _nothing
    return result


def _nothing() -> None:
    """No lock to release."""


def _free_in_optimum(study: Study, grid: pd.DataFrame | None, optimum: Mapping[str, float]) -> dict[str, str]:
    """The parameters of ``optimum`` that move none of the constrained metrics across the grid: their
    value there is only where the search held them or stopped (any other value does as well)."""
    constrained = sorted({c.metric for c in study.constraints})
    if grid is None or not constrained:
        return {}
    inert = inert_parameters(grid, list(study.parameters), constrained)
    return {p: (f"{p} moves none of the constrained metrics ({', '.join(constrained)}) across its grid: its "
                f"value in the optimum ({optimum[p]:.6g}) is only where the search held or stopped it, and any "
                f"value in its range meets the constraints as well")
            for p in optimum if p in inert}


def run_counts(summary: Mapping) -> dict[str, int]:
    """The study's one count of runs (docs: "Runs and how they are counted"): ``runs``, every distinct
    parameter set the FMU was run at and stored (runs.csv, sensitivity_runs.csv and the sensitivity stage's
    reference runs); of them ``simulated_now`` in this session and ``failed``; and the parts. The checks
    after the stages (reset, sampling, FMU steps) are not runs of the study and are not counted."""
    sens = summary.get("sensitivity") or {}
    reference = int(((sens.get("accuracy_check") or {}).get("samples")) or 0)
    parts = {"runs_csv": int(summary.get("runs", 0)), "sensitivity": int(sens.get("runs", 0) or 0),
             "sensitivity_reference": reference}
    return {"runs": sum(parts.values()), "simulated_now": int(summary.get("simulated_this_session", 0)),
            "failed": int(summary.get("failed", 0)) + int(sens.get("failed", 0) or 0), **parts}


def _stage_runs(runner: StudyRunner, asked0: int, simulated0: int, rounds0: int) -> dict[str, int]:
    """A stage's FMU runs: asked for, simulated (the rest were in runs.csv) and rounds (batches waited
    for one after another: the wall time of an FMU that costs seconds per run)."""
    return {"asked": runner.asked - asked0, "simulated": runner.simulated - simulated0,
            "rounds": runner.rounds - rounds0}


def _grid_axes(study: Study) -> list[str]:
    """The study parameters in the order a search refines them: its inner, its outer, then the rest."""
    s = study.stages.get("search")
    first = [n for n in (getattr(s, "inner", None), getattr(s, "outer", None)) if n]
    return first + [n for n in study.parameters if n not in first]


def write_summary(result: SweepResult) -> Path:
    """``<out>/summary.json`` from ``result.summary`` (written before any figure, and again by the report)."""
    path = Path(result.out) / "summary.json"
    atomic_write(path, json.dumps(jsonable(result.summary), indent=2))
    return path


def search_summary(s: SearchResult) -> dict:
    """The search in summary.json; ``outer`` None (and levels with ``outer`` null) for one parameter."""
    return {
        "inner": s.inner,
        "outer": s.outer,
        "optimum": s.optimum,
        "binding_constraint": s.binding,
        "stop_reason": s.stop_reason,
        "warnings": s.warnings,
        "warm_start": s.warm_start,
        "evaluations": s.evaluations,
        # the search in rounds: rounds, runs, and the sequential search's for the same answers
        "parallel": s.rounds.as_dict() if s.rounds is not None else None,
        "levels": [{"outer": lv.outer, "inner": lv.inner, "evaluations": lv.evaluations,
                    "changed": lv.changed, "note": lv.note,
                    "response": ({k: lv.row[k] for k in lv.row if not k.startswith("ok_")} if lv.row else None)}
                   for lv in s.levels],
    }


def jsonable(x):
    if isinstance(x, dict):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return None if not math.isfinite(float(x)) else float(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x
