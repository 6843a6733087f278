"""A study from its YAML file to runs.csv, summary.json, figures and report.md.

Stages run in the order of the study file: grid → roi → search → regression → sensitivity. Every run goes
through one RunStore, so a point asked for twice is simulated once and an interrupted study resumes where
it stopped.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from .evaluate import Evaluator, FMUCompileError, PlanSpec, RunResult, default_fmu_path, prepare_fmu
from .metrics import metric_rules
from .regression import fit_by_level
from .roi import Region, automatic_region, manual_region
from .runstore import RunStore
from .search import SearchResult, nested_binary_search
from .study import Study


@dataclass
class SweepResult:
    study: Study
    out: Path
    runs: pd.DataFrame
    summary: dict
    region: Region | None = None
    paper_region: Region | None = None
    search: SearchResult | None = None
    paper_search: SearchResult | None = None
    sensitivity: dict | None = None
    extra: dict = field(default_factory=dict)


def _progress(total: int, desc: str, enabled: bool):
    if not enabled or total < 50:
        return None
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="run", leave=False, mininterval=0.5)


def check_fmu(study: Study, fmu_path: Path) -> list[str]:
    """Everything the study asks of the FMU, checked on its model description before any run (nothing is
    loaded, so an FMU that still has to be compiled from its sources is checked too).

    FMI version 2.0; the interface ``fmu_options`` asks for (and a binary for this machine, or sources to
    build one); every study, fixed and sensitivity parameter a settable parameter (causality parameter,
    variability fixed or tunable; study parameters Real); every scenario input an input; every metric's
    output a variable that can be read. Returns all problems, each ``file:line: what; closest names``.
    """
    from .evaluate import FMUError, binary_problem, read_fmu_info, select_interface, variable_problem

    try:
        info = read_fmu_info(fmu_path)
    except (FMUError, FileNotFoundError) as exc:
        return [f"{study.line('fmu')}: {exc}"]
    errors: list[str] = []
    opts = study.fmu_options
    try:
        interface = select_interface(info, opts.interface)
    except FMUError as exc:
        errors.append(f"{study.line('fmu_options.interface')}: fmu_options.interface: {exc}")
    else:
        if interface == "co-simulation":
            for key, val in (("solver", opts.solver), ("step_size", opts.step_size)):
                if val is not None:
                    errors.append(f"{study.line(f'fmu_options.{key}')}: fmu_options.{key} applies to model "
                                  f"exchange only, but {info.model_name} runs as a co-simulation FMU (its own "
                                  f"solver); remove '{key}'"
                                  + (", or set interface: model-exchange" if "model-exchange" in info.interfaces
                                     else ""))
        problem = binary_problem(info, interface)
        if problem:
            errors.append(f"{study.line('fmu')}: {problem}")

    def check(key: str, what: str, name: str, role: str) -> None:
        problem = variable_problem(info, name, role)
        if problem:
            errors.append(f"{study.line(key)}: {what}: {problem}")

    for p in study.parameters.values():
        check(f"parameters.{p.name}.variable", f"parameter '{p.name}' (variable: {p.variable})", p.variable,
              "varied")
    for name in study.fixed:
        check(f"fixed.{name}", f"fixed '{name}'", name, "parameter")
    for name in study.scenario.inputs:
        check(f"scenario.inputs.{name}", f"scenario.inputs '{name}'", name, "input")
    for m in study.metrics.values():
        check(f"metrics.{m.name}.output", f"metric '{m.name}' (output: {m.output})", m.output, "output")
    sens = study.stages.get("sensitivity")
    for sp in (getattr(sens, "parameters", None) or {}).values():
        check(f"stages.sensitivity.parameters.{sp.name}.variable",
              f"sensitivity parameter '{sp.name}' (variable: {sp.variable})", sp.variable, "varied")
    return errors


class StudyRunner:
    """Evaluates study points through the store (cache, resume) and the evaluator (pool, cluster)."""

    def __init__(self, study: Study, out: Path, resume: bool, workers: int | None, scheduler: str | None,
                 progress: bool = True) -> None:
        self.study = study
        fmu_path = Path(study.fmu) if study.fmu else default_fmu_path()
        errors = check_fmu(study, fmu_path)
        if errors:
            n = len(errors)
            raise ValueError(f"{study.path}: the study does not fit the FMU {fmu_path} ({n} problem"
                             f"{'s' if n > 1 else ''}):\n  " + "\n  ".join(errors))
        opts = study.fmu_options
        try:   # an FMU without a binary for this machine is built from its sources, once, before any run
            run_path = prepare_fmu(fmu_path, opts.interface, workdir=Path(out) / ".fmu")
        except FMUCompileError as exc:
            raise FMUCompileError(f"{study.path}: {exc}") from None
        self.params = list(study.parameters)
        self.metrics = list(study.metrics)
        spec = self.spec = study_plan_spec(study, run_path)
        self.store = RunStore(out / "runs.csv", self.params, self.metrics, study.constraints, resume=resume)
        # any FMU but our own runs in supervised workers: a crash or hang then costs one run
        self.evaluator = Evaluator(spec, workers=workers or study.execution.workers,
                                   scheduler=scheduler or study.execution.scheduler,
                                   isolate=study.fmu is not None, timeout_s=study.execution.timeout_s)
        self.progress = progress
        self.simulated = 0

    def close(self) -> None:
        self.evaluator.close()
        self.store.close()

    def evaluate(self, points: list[dict[str, float]], stage: str) -> list[dict]:
        """Rows for ``points`` (study parameter name → value), simulating only the new ones."""
        keys = [tuple(float(p[name]) for name in self.params) for p in points]
        todo: dict[tuple, int] = {}
        for k in keys:
            if self.store.get(k) is None and k not in todo:
                todo[k] = self.store.new_id()
        if todo:
            bar = _progress(len(todo), stage, self.progress)
            items = [(rid, k) for k, rid in todo.items()]

            def keep(r: RunResult) -> None:
                self.store.add(r.run_id, stage, r.values, r.metrics, r.status, r.message, r.seconds)

            self.evaluator.map(items, on_result=keep, progress=bar)
            self.simulated += len(items)
            if bar is not None:
                bar.close()
        return [self.store.get(k) for k in keys]

    def evaluate_one(self, point: dict[str, float], stage: str) -> dict:
        full = dict(point)
        for name in self.params:          # parameters the stage does not vary keep the first grid value
            full.setdefault(name, self._defaults[name])
        return self.evaluate([full], stage)[0]


def study_plan_spec(study: Study, fmu_path: str | Path) -> PlanSpec:
    """How every run of ``study`` is made: its parameters varied (with their unit mapping), ``fixed`` and
    the scenario's inputs set, its metrics computed, the FMU run with ``fmu_options``. Stages that vary
    other variables (sensitivity) replace ``varied``, ``scale`` and ``offset``."""
    names = list(study.parameters)
    outputs = list(dict.fromkeys(m.output for m in study.metrics.values()))
    opts = study.fmu_options
    return PlanSpec(
        fmu_path=str(fmu_path),
        varied=tuple(study.parameters[p].variable for p in names),
        scale=tuple(float(study.parameters[p].scale) for p in names),
        offset=tuple(float(study.parameters[p].offset) for p in names),
        fixed=tuple(study.fixed.items()),
        inputs=tuple(study.scenario.inputs.items()),
        outputs=tuple(outputs),
        stop_time=float(study.scenario.stop_time),
        step=study.scenario.step,
        rules=tuple(metric_rules(study.metrics.values(), outputs)),
        interface=opts.interface,
        solver=opts.solver,
        relative_tolerance=opts.relative_tolerance,
        step_size=opts.step_size,
        refine_factor=study.scenario.refine_factor if study.scenario.refine_peaks else None,
    )


def grid_points(study: Study) -> list[dict[str, float]]:
    axes = study.stages["grid"].points()
    names = list(study.parameters)
    missing = [n for n in names if n not in axes]
    if missing:
        raise ValueError(f"{study.path}: stages.grid gives no values for {', '.join(missing)}")
    mesh = np.meshgrid(*[axes[n] for n in names], indexing="ij")
    return [dict(zip(names, map(float, vals))) for vals in zip(*[m.ravel() for m in mesh])]


def run_study(study: Study, out: str | Path, resume: bool = False, workers: int | None = None,
              scheduler: str | None = None, figures: bool = True, progress: bool = True) -> SweepResult:


    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    runner = StudyRunner(study, out, resume, workers, scheduler, progress)
    summary: dict[str, Any] = {"study": study.name, "study_file": str(study.path)}
    result = SweepResult(study, out, pd.DataFrame(), summary)
    try:
        stage_times: dict[str, float] = {}
        grid_df = None
        runner._defaults = {}
        for name, stage in study.stages.items():
            ts = time.perf_counter()
            if name == "grid":
                pts = grid_points(study)
                runner._defaults = dict(pts[0])
                runner.evaluate(pts, "grid")
                grid_df = runner.store.frame("grid")
                summary["grid"] = {"points": len(pts), "axes": {k: [float(x) for x in v]
                                                                for k, v in stage.points().items()}}
            elif name == "roi":
                search_stage = study.stages.get("search")
                if search_stage is None:
                    raise ValueError(f"{study.path}: stages.roi needs stages.search (its inner and outer parameters)")
                inner, outer = search_stage.inner, search_stage.outer
                if stage.manual:
                    result.region = manual_region(stage.manual, inner, outer)
                else:
                    if grid_df is None:
                        raise ValueError(f"{study.path}: an automatic region of interest needs stages.grid "
                                         f"before stages.roi (or give roi.manual)")
                    result.region = automatic_region(grid_df, inner, outer)
                summary["roi"] = result.region.as_dict()
                paper_roi = (study.paper or {}).get("roi")
                if paper_roi and not stage.manual:
                    result.paper_region = Region(inner, outer, tuple(map(float, paper_roi[inner])),
                                                 tuple(map(float, paper_roi[outer])), "paper (by hand)")
            elif name == "search":
                if result.region is None:
                    raise ValueError(f"{study.path}: stages.search needs stages.roi before it")
                response = list(stage.response)      # default: the constrained metrics (study.py)

                def ev(point: dict[str, float], tag: str = "search") -> dict:
                    return runner.evaluate_one(point, tag)

                result.search = nested_binary_search(ev, result.region, response, stage.inner_rtol,
                                                     stage.response_rtol, stage.max_outer, stage.response_atol)
                summary["optimum"] = result.search.optimum
                summary["binding_constraint"] = result.search.binding
                summary["search"] = _search_summary(result.search)
                if result.paper_region is not None:
                    result.paper_search = nested_binary_search(
                        lambda p: ev(p, "search_paper_roi"), result.paper_region, response, stage.inner_rtol,
                        stage.response_rtol, stage.max_outer, stage.response_atol)
                    summary["paper_roi_search"] = _search_summary(result.paper_search)
            elif name == "regression":
                runs = runner.store.frame()
                pts = runs[runs["stage"].isin(["search"])]
                summary["regression"] = fit_by_level(pts, stage.x, list(stage.y), stage.by, stage.degree)
                if result.paper_search is not None:
                    pp = runs[runs["stage"] == "search_paper_roi"]
                    summary["regression_paper_roi"] = fit_by_level(pp, stage.x, list(stage.y), stage.by,
                                                                   stage.degree)
            elif name == "sensitivity":
                from .sensitivity import run_sensitivity
                result.sensitivity = run_sensitivity(study, stage, out, runner, progress=progress)
                summary["sensitivity"] = result.sensitivity["summary"]
            stage_times[name] = time.perf_counter() - ts
        runs = runner.store.frame()
        result.runs = runs
        summary["runs"] = int(len(runs))
        summary["simulated_this_session"] = int(runner.simulated)
        summary["failed"] = int((runs["status"] != "ok").sum()) if len(runs) else 0
        summary["stage_wall_s"] = stage_times
        summary["wall_s"] = time.perf_counter() - t0
    finally:
        runner.close()
    if figures:
        from .report import write_report
        write_report(result)
        summary["wall_s_with_report"] = time.perf_counter() - t0
    (out / "summary.json").write_text(json.dumps(_jsonable(summary), indent=2))
    return result


def _search_summary(s: SearchResult) -> dict:
    return {
        "optimum": s.optimum,
        "binding_constraint": s.binding,
        "stop_reason": s.stop_reason,
        "warnings": s.warnings,
        "levels": [{"outer": lv.outer, "inner": lv.inner, "evaluations": lv.evaluations,
                    "changed": lv.changed, "note": lv.note,
                    "response": ({k: lv.row[k] for k in lv.row if not k.startswith("ok_")} if lv.row else None)}
                   for lv in s.levels],
    }


def _jsonable(x):
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return None if not math.isfinite(float(x)) else float(x)
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x
