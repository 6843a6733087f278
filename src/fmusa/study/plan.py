"""How a study becomes runs: the grid's points, the PlanSpec of every run, and the FMU checked against the study before any run."""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Sequence

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
    errors += ambiguity_problems(study, info)
    return errors


def _uses(study: Study) -> list[tuple[str, str, str, object]]:
    """(study key, what, FMU variable, value) of every variable the study names; value ``None`` for one
    the study varies or reads, the fixed value or input value otherwise."""
    out: list[tuple[str, str, str, object]] = []
    for p in study.parameters.values():
        out.append((f"parameters.{p.name}.variable", f"study parameter '{p.name}'", p.variable, None))
    sens = study.stages.get("sensitivity")
    for sp in (getattr(sens, "parameters", None) or {}).values():
        out.append((f"stages.sensitivity.parameters.{sp.name}.variable", f"sensitivity parameter '{sp.name}'",
                    sp.variable, None))
    for name, value in study.fixed.items():
        out.append((f"fixed.{name}", f"fixed '{name}'", name, value))
    for name, value in study.scenario.inputs.items():
        out.append((f"scenario.inputs.{name}", f"scenario.inputs '{name}'", name, value))
    for m in study.metrics.values():
        out.append((f"metrics.{m.name}.output", f"metric '{m.name}'", m.output, "read"))
    return out


def ambiguity_problems(study: Study, info) -> list[str]:
    """What in the FMU's model description makes the study ambiguous: a variable it names that the
    description declares twice (a set or a read would reach only one of them), or two names it sets that
    share a value reference (FMI 2.0 aliases: one value, so two different values cannot both hold)."""
    errors: list[str] = []
    by_name: dict[str, list] = {}
    for v in info.variables:
        by_name.setdefault(v.name, []).append(v)
    uses = _uses(study)
    seen: set[str] = set()
    for key, what, name, _ in uses:
        twins = by_name.get(name, [])
        if len(twins) > 1 and name not in seen:
            seen.add(name)
            each = "; ".join(f"value reference {v.valueReference}, causality {v.causality}"
                             + (f", {v.description!r}" if v.description else "") for v in twins)
            errors.append(f"{study.line(key)}: {what}: the FMU declares {len(twins)} variables named {name!r} "
                          f"({each}): fmusa cannot tell which one is meant, and a value set or read would "
                          f"reach only one of them; ask the FMU's exporter for unique names")
    setters: dict[tuple, list[tuple[str, str, str, object]]] = {}
    for use in uses:
        key, what, name, value = use
        if isinstance(value, str) and value == "read":
            continue
        v = info.variable(name)
        if v is None or len(by_name.get(name, [])) > 1:
            continue
        setters.setdefault((v.type, v.valueReference), []).append(use)
    for (typ, vr), group in setters.items():
        names = {u[2] for u in group}
        if len(names) < 2:
            continue
        varied = [u for u in group if u[3] is None]
        values = {repr(u[3]) for u in group if u[3] is not None}
        if varied or len(values) > 1:
            listed = " and ".join(f"{u[1]} ({u[2]}{'' if u[3] is None else f' = {u[3]!r}'})" for u in group)
            errors.append(f"{study.line(group[0][0])}: {listed} are one FMU variable: they share value "
                          f"reference {vr} ({typ}; FMI 2.0 aliases), so one value would silently override "
                          f"the other; set only one of them")
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


def reset_check_points(study: Study, spec: PlanSpec) -> tuple[list[float], list[float]]:
    """Two points (FMU values of ``spec.varied``) for the FMU's reset check (:mod:`fmusa.runs.preflight`):
    the grid's first and last points, as far apart as the study goes; without a grid, the study
    parameters' start values, twice (the check then still finds a state that a reset does not restore)."""
    scale, offset = np.asarray(spec.scale, dtype=float), np.asarray(spec.offset, dtype=float)
    if "grid" in study.stages and study.parameters:
        pts = grid_points(study)
        names = list(study.parameters)
        first = np.array([pts[0][n] for n in names]) * scale + offset
        last = np.array([pts[-1][n] for n in names]) * scale + offset
        return first.tolist(), last.tolist()
    from fmusa.fmi.info import read_fmu_info
    info = read_fmu_info(spec.fmu_path)
    start = []
    for name in spec.varied:
        v = info.variable(name)
        try:
            start.append(float(v.start) if v is not None and v.start is not None else 0.0)
        except (TypeError, ValueError):
            start.append(0.0)
    return start, start


def grid_points(study: Study) -> list[dict[str, float]]:
    axes = study.stages["grid"].points()
    names = list(study.parameters)
    missing = [n for n in names if n not in axes]
    if missing:
        raise StudyError(f"{study.path}: stages.grid gives no values for {', '.join(missing)}")
    mesh = np.meshgrid(*[axes[n] for n in names], indexing="ij")
    return [dict(zip(names, map(float, vals))) for vals in zip(*[m.ravel() for m in mesh])]


def _plain(v):
    """A fixed value, input or option as JSON keeps it (floats as floats, so 300 and 300.0 compare equal)."""
    if isinstance(v, (bool, str)) or v is None:
        return v
    if isinstance(v, int):
        return v
    try:
        return float(v)
    except (TypeError, ValueError):
        return repr(v)


def _flipped(rule) -> list[str]:
    """A mark in the fingerprint of a metric whose negative scale flips the axis before its reduction (runs
    stored when the scale was applied after it do not match)."""
    return ["scaled, then reduced"] if rule.scale < 0 and rule.reduce in ("max", "min", "max_abs",
                                                                            "mean_abs") else []


def spec_fingerprint(spec: PlanSpec, names: Sequence[str], fmu: str) -> dict:
    """Everything of ``spec`` that decides a run's metrics, keyed so that a change reads in the study's
    words: ``fmu`` (the digest ``fmu``), ``parameters`` (study name → [FMU variable, scale, offset]),
    ``fixed``, ``scenario``, ``metrics`` (name → [output, reduce, scale, offset, missing_below,
    settle_tol]), ``fmu_options``; every other field of the spec (one added later, say) under ``other``,
    so that nothing that decides a run is left out. The spec's FMU path is not in it (the digest is)."""
    # ``reuse`` (how an instance is brought back between runs) decides nothing: the reset check makes every
    # way it picks give the run of a fresh instance
    known = {"fmu_path", "varied", "scale", "offset", "fixed", "inputs", "outputs", "stop_time", "step",
             "rules", "interface", "solver", "relative_tolerance", "step_size", "refine_factor", "reuse"}
    fp: dict = {
        "fmu": fmu,
        "parameters": {n: [v, float(a), float(b)] for n, v, a, b in zip(names, spec.varied, spec.scale,
                                                                          spec.offset)},
        "fixed": {k: _plain(v) for k, v in spec.fixed},
        "scenario": {"stop_time": float(spec.stop_time), "step": _plain(spec.step),
                     "inputs": {k: _plain(v) for k, v in spec.inputs},
                     "refine_factor": _plain(spec.refine_factor)},
        "metrics": {r.name: [spec.outputs[r.column], r.reduce, float(r.scale), float(r.offset),
                             _plain(r.missing_below), _plain(r.settle_tol)] + _flipped(r) for r in spec.rules},
        "fmu_options": [spec.interface, spec.solver, _plain(spec.relative_tolerance), _plain(spec.step_size)],
    }
    other = {f.name: _plain(getattr(spec, f.name)) for f in dataclasses.fields(spec) if f.name not in known}
    if other:
        fp["other"] = other
    return fp


def fmu_digest(fmu_path: str | Path) -> str:
    """The FMU's content digest (a folder: its resolved path)."""
    path = Path(fmu_path)
    return file_digest(path) if path.is_file() else str(path.resolve())


def run_fingerprint(study: Study, fmu_path: str | Path) -> dict:
    """Everything besides the study parameters' values that decides a run's metrics (see
    :func:`spec_fingerprint`): a resumed study may reuse a stored run only while this is unchanged.
    Constraints are not in it: feasibility is recomputed from the metrics."""
    return spec_fingerprint(study_plan_spec(study, fmu_path), list(study.parameters), fmu_digest(fmu_path))
