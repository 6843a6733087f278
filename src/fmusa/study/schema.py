"""The study file: one YAML file describes a whole study, validated at load into dataclasses.

A study names the FMU, maps the study's parameters onto FMU variables, fixes the scenario (end time,
inputs), defines the metrics read from the FMU's outputs and the constraints on them, and lists the
stages to run (grid → roi → search → regression, and/or a global sensitivity analysis).

Everything that can be checked without the FMU is checked here, once, at load time, so that a long
study never dies halfway on a typo. Every error is a :class:`StudyError` whose message names the
file, the line, the key and the fix, e.g.::

    studies/paper.yaml:14: key 'stop_tme' is not allowed in 'scenario'; did you mean 'stop_time'?
    (allowed: stop_time, step, inputs, description)

Whether the FMU variables exist is checked later, against the FMU itself
(:func:`fmusa.study.plan.check_fmu`); ``Study.lines`` keeps the line of every FMU reference for those
messages.

Example::

    from fmusa import load_study
    study = load_study("studies/paper.yaml")
    study.stages["grid"].points()        # {'c': array([1.5625e4, ...]), 'd': array([625., ...])}
    study.constraints[0].satisfied(4e-4)
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np

from fmusa.errors import FmusaError
from fmusa.runs.metrics import REDUCTIONS, SAMPLED_REDUCTIONS, MetricRule, reduce_series

__all__ = [
    "StudyError", "Study", "Parameter", "Scenario", "Metric", "Constraint", "GridStage", "RoiStage",
    "SearchStage", "RegressionStage", "SensitivityStage", "SensitivityParameter", "Execution", "FixedValue",
    "FMUOptions", "INTERFACES", "SOLVERS", "STAGE_NAMES", "REDUCTIONS", "SAMPLED_REDUCTIONS", "METHODS",
    "DISTRIBUTIONS",
]

#: Stage names, in the order they are normally run.
STAGE_NAMES = ("grid", "roi", "search", "regression", "sensitivity")
# REDUCTIONS (how a metric reduces the sampled values of its output) and SAMPLED_REDUCTIONS (those whose
# value sits at one sample: what ``scenario.refine_peaks`` refines) come from fmusa.runs.metrics, which
# applies them.
#: Global sensitivity methods.
METHODS = ("morris", "sobol")
#: Distributions of sensitivity parameters.
DISTRIBUTIONS = ("uniform", "loguniform")
#: FMI 2.0 interfaces a study may ask for (``fmu_options.interface``).
INTERFACES = ("auto", "co-simulation", "model-exchange")
#: fmpy's solvers for model exchange FMUs (``fmu_options.solver``).
SOLVERS = ("CVode", "Euler")

#: What a study, parameter or metric name may look like (a Python identifier).
IDENTIFIER = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class StudyError(FmusaError, ValueError):
    """An invalid study file. The message is ``file:line: what is wrong; how to fix it``."""


# ============================================================================ dataclasses
@dataclass(frozen=True)
class Parameter:
    """A study parameter (e.g. the paper's c) and the FMU variable it sets (c_y).

    The study may work in other units than the FMU; ``scale``/``offset`` convert, so reports and
    figures use the study's unit while the FMU always gets SI values.
    """
    name: str
    variable: str
    unit: str = ""
    scale: float = 1.0
    offset: float = 0.0
    description: str = ""

    def to_fmu(self, x):
        """FMU value of study value ``x`` (scalar or array): ``scale * x + offset``."""
        return self.scale * x + self.offset

    def from_fmu(self, v):
        """Study value of FMU value ``v``: the inverse of :meth:`to_fmu`."""
        return (v - self.offset) / self.scale


@dataclass(frozen=True)
class FixedValue:
    """A ``fixed`` FMU parameter written in the study's own unit (``fixed: {c_y: {value: 823.2, unit: N/mm,
    scale: 1000}}``): FMU value = ``scale`` × ``value`` + ``offset``, the conversion of a study parameter.
    The report shows the study's value and unit; the FMU gets :meth:`to_fmu`."""
    name: str
    value: float
    unit: str = ""
    scale: float = 1.0
    offset: float = 0.0
    description: str = ""

    def to_fmu(self) -> float:
        return self.scale * self.value + self.offset


@dataclass(frozen=True)
class Scenario:
    """What one run simulates: the end time, the communication step and constant inputs.

    ``step`` None means one ``doStep`` from 0 to ``stop_time``; the FMU's monitors (y_max, t_eq, …)
    are updated on every internal step, so their final values are exact without sampling. With a
    ``step`` the outputs are sampled every ``step`` s, and a peak or a settling time taken from the
    samples is off by up to ~step²/8·|y''| or one step; ``refine_peaks`` then re-runs each run with
    ``refine_factor`` times finer steps around those samples (see :mod:`fmusa.runs.refine`).
    """
    stop_time: float
    step: float | None = None
    inputs: dict[str, float] = field(default_factory=dict)
    description: str = ""
    refine_peaks: bool = False
    refine_factor: int = 10


@dataclass(frozen=True)
class Metric:
    """A scalar result of one run, computed from an FMU output.

    ``reduce`` turns the sampled output into one number (``final`` needs no sampling). A reduced
    raw value below ``missing_below`` means "none" (NaN): e.g. ``t_eq = -1`` means never at rest.
    The reported metric is ``scale * raw + offset`` (unit conversion).
    """
    name: str
    output: str
    reduce: str = "final"
    unit: str = ""
    scale: float = 1.0
    offset: float = 0.0
    missing_below: float | None = None
    description: str = ""
    settle_tol: float | None = None

    def compute(self, samples, times=None) -> float:
        """The metric from the output's samples (a scalar counts as one sample) at ``times`` (default:
        equally spaced; ``settle`` needs them).

        The same reduction the runs use (:func:`fmusa.runs.metrics.reduce_series`): ``mean`` and
        ``mean_abs`` are time means (trapezoid rule over ``times``), then ``missing_below`` (on the raw
        FMU value), then ``scale``/``offset``.
        """
        a = np.atleast_1d(np.asarray(samples, dtype=float))
        if a.size == 0:
            return math.nan
        if times is None:
            if self.reduce == "settle":
                raise ValueError(f"metric {self.name!r} (reduce: settle) needs the sample times")
            t = np.arange(a.size, dtype=float)
        else:
            t = np.atleast_1d(np.asarray(times, dtype=float))
            if t.shape != a.shape:
                raise ValueError(f"metric {self.name!r}: {a.size} samples but {t.size} times")
        rule = MetricRule(self.name, 0, self.reduce, self.scale, self.offset, self.missing_below,
                          self.settle_tol)
        return float(reduce_series(t, a[:, None], [rule])[0])


@dataclass(frozen=True)
class Constraint:
    """A condition on a metric that a feasible parameter set must meet (Table 2 of the paper).

    Bounds are inclusive (``min <= value <= max``). ``required`` means the metric must exist
    (not NaN), e.g. "the screw reaches equilibrium".
    """
    name: str
    metric: str
    max: float | None = None
    min: float | None = None
    required: bool = False
    description: str = ""

    def satisfied(self, value: float) -> bool:
        """Whether ``value`` meets the constraint. NaN fails every constraint (each one has a
        bound or is required)."""
        value = float(value)
        if math.isnan(value):
            return False
        if self.max is not None and not value <= self.max:
            return False
        if self.min is not None and not value >= self.min:
            return False
        return True


@dataclass(frozen=True)
class GridStage:
    """The initial coarse grid (paper, Section 2.4): powers of a base, or explicit values."""
    base: float | None = None
    exponents: dict[str, tuple[int, int]] = field(default_factory=dict)
    values: dict[str, list[float]] = field(default_factory=dict)

    def points(self) -> dict[str, np.ndarray]:
        """Grid values per parameter, sorted ascending: ``base**k`` for k = lo..hi (inclusive), or
        the explicit values. Parameters with exponents come first, in file order."""
        out: dict[str, np.ndarray] = {}
        for name, (lo, hi) in self.exponents.items():
            out[name] = np.sort(np.array([float(self.base) ** k for k in range(lo, hi + 1)]))
        for name, vals in self.values.items():
            out[name] = np.sort(np.array(vals, dtype=float))
        return out


@dataclass(frozen=True)
class RoiStage:
    """The region of interest. ``manual`` (parameter -> (lo, hi)) overrides the region computed
    from the grid; the paper chose its region by hand. Spanned by the search's ``inner`` and ``outer``
    parameters, or by ``inner`` alone (an inner range) when the search has no ``outer``."""
    manual: dict[str, tuple[float, float]] | None = None


@dataclass(frozen=True)
class SearchStage:
    """The nested binary search (paper, Section 3): for each ``outer`` value, halved from the
    region's upper bound, bisect ``inner`` for its smallest feasible value; stop when the response
    no longer changes. Without ``outer`` (None): one bisection of ``inner`` inside the region.

    ``response`` are the metrics compared between outer levels (default: the constrained ones). A
    metric counts as changed when it moved by more than ``response_rtol`` (relative) and more than its
    ``response_atol`` (absolute, in the metric's unit; 0 when not given): without the floor a metric
    that is 0 up to round-off (a final velocity at rest) would always count as changed.

    ``warm_start`` brackets each outer level from the previous level's answer instead of the whole
    region (fewer FMU runs; the answer stays within ``inner_rtol``; see :mod:`fmusa.analysis.search`);
    off by default, the paper's search.

    ``parallel`` runs the search in rounds of points run together (:func:`fmusa.analysis.search.
    search_in_rounds`): ``"auto"`` (the default) as many points per round as the study has workers (local
    processes or the Dask cluster's threads), an integer that many, ``False`` the sequential search, one
    point at a time (the paper's; studies/paper.yaml keeps it). The answer is the sequential search's for
    a monotone boundary."""
    inner: str
    outer: str | None = None
    inner_rtol: float = 1e-3
    response_rtol: float = 1e-3
    max_outer: int = 20
    response: list[str] = field(default_factory=list)
    response_atol: dict[str, float] = field(default_factory=dict)
    warm_start: bool = False
    parallel: str | int | bool = "auto"


@dataclass(frozen=True)
class RegressionStage:
    """Polynomial fits of metrics over one parameter (the paper's eq. 3, a cubic in c), one fit
    per value of ``by`` if given. ``source`` names the runs fitted, set by the loader: ``"search"``
    when the study has a search stage (the paper's fits), else ``"grid"``."""
    x: str
    y: list[str]
    by: str | None = None
    degree: int = 3
    source: str = "search"


@dataclass(frozen=True)
class SensitivityParameter:
    """An input of the global sensitivity analysis, sampled within ``bounds``."""
    name: str
    variable: str
    bounds: tuple[float, float]
    distribution: str = "uniform"
    unit: str = ""


@dataclass(frozen=True)
class SensitivityStage:
    """Global sensitivity analysis (Morris screening, Sobol indices) of ``outputs`` (metric
    names) to ``parameters``. ``n`` is the Sobol base sample size."""
    methods: list[str] = field(default_factory=lambda: list(METHODS))
    n: int = 1024
    morris_trajectories: int = 20
    seed: int = 1
    outputs: list[str] = field(default_factory=list)
    parameters: dict[str, SensitivityParameter] = field(default_factory=dict)


@dataclass(frozen=True)
class Execution:
    """Where the runs execute: local worker processes (None = all cores) or a Dask scheduler.

    ``check_fmu_steps``: after the stages, rerun a few points with the communication step halved, the
    tolerance tightened tenfold and (where the FMU has it) through model exchange, and flag the metrics that
    move by more than the study's tolerance (:mod:`fmusa.pipeline.solver_check`). ``None`` (``auto``, the
    default): for every FMU but this repository's own ScrewVertebra, whose solver its tests hold to closed
    forms and an independent stiff solver; ``true`` checks ours too, ``false`` skips those runs.
    """
    workers: int | None = None
    scheduler: str | None = None
    timeout_s: float = 60.0
    check_fmu_steps: bool | None = None
    #: spawn | forkserver | fork; None: $FMUSA_START_METHOD, else the platform's default
    start_method: str | None = None
    #: a worker is replaced by a fresh one after this many runs (None: never)
    worker_max_runs: int | None = None
    #: a worker is replaced past this resident memory in MB (None: never); its run in progress is retried
    worker_max_memory_mb: float | None = None
    #: times a run whose worker died (crash, memory) is tried again on a fresh worker
    retries: int = 1

    def pool_options(self):
        """These settings as the supervised pool takes them (:class:`fmusa.runs.pool.PoolOptions`)."""
        from fmusa.runs.pool import PoolOptions
        return PoolOptions(start_method=self.start_method, worker_max_runs=self.worker_max_runs,
                           worker_max_memory_mb=self.worker_max_memory_mb, retries=self.retries)


@dataclass(frozen=True)
class FMUOptions:
    """How the FMU runs (``fmu_options``).

    ``interface`` ``auto`` runs co-simulation when the FMU has it (the FMU's own solver), else model
    exchange. Model exchange FMUs are integrated by fmpy's ``solver`` (CVode when None, or Euler) with
    ``relative_tolerance`` (CVode) and ``step_size`` (Euler's fixed step; CVode's longest step). For a
    co-simulation FMU, ``relative_tolerance`` is passed to ``fmi2SetupExperiment``.
    """
    interface: str = "auto"
    solver: str | None = None
    relative_tolerance: float | None = None
    step_size: float | None = None


@dataclass(frozen=True)
class Study:
    """A whole study, as loaded from its YAML file.

    ``path`` is the YAML file (absolute; None when parsed from a string without a file name);
    ``fmu`` None means the built ScrewVertebra FMU (:func:`fmusa.fmi.info.default_fmu_path`).
    ``stages`` keeps the file order.
    """
    name: str
    description: str
    path: Path | None
    fmu: Path | None
    parameters: dict[str, Parameter]
    fixed: dict[str, float | int | bool]          # FMU values (converted from the study's units)
    scenario: Scenario
    metrics: dict[str, Metric]
    constraints: list[Constraint]
    stages: dict[str, object]
    execution: Execution
    paper: dict
    fmu_options: FMUOptions = field(default_factory=FMUOptions)
    #: the ``fixed`` entries written as ``{value, unit, scale, offset}``, in the study's units
    fixed_units: dict[str, FixedValue] = field(default_factory=dict)
    #: line of each FMU reference in the study file, for the FMU checks' messages: keys such as
    #: ``fmu``, ``parameters.c.variable``, ``fixed.F_max``, ``scenario.inputs.F_ext``,
    #: ``metrics.max_y.output``, ``stages.sensitivity.parameters.c_x.variable``, ``fmu_options.solver``
    lines: dict = field(default_factory=dict, compare=False, repr=False)

    def line(self, key: str) -> str:
        """``file:line`` of ``key`` (see ``lines``), or ``file`` when unknown, for messages."""
        label = str(self.path) if self.path is not None else "<string>"
        n = self.lines.get(key)
        return f"{label}:{n}" if n else label

    def fmu_values(self, point: Mapping[str, float]) -> dict[str, float | int | bool]:
        """FMU start values for one run: ``fixed`` plus the study parameters in ``point``
        (study name -> study value), converted with each parameter's scale/offset."""
        out: dict[str, float | int | bool] = dict(self.fixed)
        for name, x in point.items():
            p = self.parameters[name]
            out[p.variable] = p.to_fmu(x)
        return out


