"""How a study becomes runs: the grid's points, the PlanSpec of every run, and the FMU checked against the study before any run."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from fmusa.fmi.build import file_digest
from fmusa.runs.metrics import metric_rules
from fmusa.runs.spec import PlanSpec
from fmusa.study.schema import Study, StudyError


def check_fmu(study: Study, fmu_path: Path) -> list[str]:
    """Everything the study asks of the FMU, checked on its model description before any run (nothing is
    loaded, so an FMU that still has to be compiled from its sources is checked too).

    FMI version 2.0 or 3.0; the interface ``fmu_options`` asks for (and a binary for this machine, or sources
    to build one); every study, fixed and sensitivity parameter a settable parameter (causality parameter,
    variability fixed or tunable; study parameters Real, or a Real input held at the study's value; a fixed
    value of the variable's type); FMI 3.0 arrays addressed element-wise (``name[i]``); every
    scenario input an input; every metric's
    output a variable that can be read. Returns all problems, each ``file:line: what; closest names``.
    """
    from fmusa.fmi.info import FMUError, binary_problem, read_fmu_info, select_interface, variable_problem
    from fmusa.fmi.runner import FMURunner

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
    for name, value in study.fixed.items():
        check(f"fixed.{name}", f"fixed '{name}'", name, "parameter")
        v = info.variable(name)
        if v is not None and not variable_problem(info, name, "parameter"):
            try:     # the value fits the variable's type (an Integer: whole, 32 bits), before any run
                FMURunner.coerce(v, value)
            except FMUError as exc:
                errors.append(f"{study.line(f'fixed.{name}')}: fixed '{name}': {exc}")
    for name in study.scenario.inputs:
        check(f"scenario.inputs.{name}", f"scenario.inputs '{name}'", name, "input")
    for m in study.metrics.values():
        check(f"metrics.{m.name}.output", f"metric '{m.name}' (output: {m.output})", m.output, "output")
    sens = study.stages.get("sensitivity")
    for sp in (getattr(sens, "parameters", None) or {}).values():
        check(f"stages.sensitivity.parameters.{sp.name}.variable",
              f"sensitivity parameter '{sp.name}' (variable: {sp.variable})", sp.variable, "varied")
    return errors


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
        raise StudyError(f"{study.path}: stages.grid gives no values for {', '.join(missing)}")
    mesh = np.meshgrid(*[axes[n] for n in names], indexing="ij")
    return [dict(zip(names, map(float, vals))) for vals in zip(*[m.ravel() for m in mesh])]



def run_fingerprint(study: Study, fmu_path: str | Path) -> dict:
    """Everything besides the study parameters that decides a run's metrics: the FMU's content, the fixed
    values, the scenario, how each metric is read, how the FMU runs. A resumed study may reuse a stored run
    only while this is unchanged. Constraints are not in it: feasibility is recomputed from the metrics."""
    path = Path(fmu_path)
    return {
        "fmu": file_digest(path) if path.is_file() else str(path.resolve()),
        "parameters": {n: [p.variable, float(p.scale), float(p.offset)] for n, p in study.parameters.items()},
        "fixed": {k: (v if isinstance(v, (bool, int, str)) else float(v)) for k, v in study.fixed.items()},
        "scenario": {"stop_time": float(study.scenario.stop_time), "step": study.scenario.step,
                     "inputs": {k: float(v) for k, v in study.scenario.inputs.items()},
                     "refine_peaks": bool(study.scenario.refine_peaks),
                     "refine_factor": int(study.scenario.refine_factor)},
        "metrics": {m.name: [m.output, m.reduce, float(m.scale), float(m.offset), m.missing_below, m.settle_tol]
                    for m in study.metrics.values()},
        "fmu_options": [study.fmu_options.interface, study.fmu_options.solver,
                        study.fmu_options.relative_tolerance, study.fmu_options.step_size],
    }
