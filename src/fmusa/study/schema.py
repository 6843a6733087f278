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
    "DISTRIBUTIONS", "PCEOptions", "DESIGNS", "MAX_SENSITIVITY_RUNS", "ENV_MAX_SENSITIVITY_RUNS",
    "max_sensitivity_runs", "smallest_sobol_n", "nearest_powers_of_two", "MIN_SOBOL_N", "MIN_MORRIS_TRAJECTORIES",
]

#: Stage names, in the order they are normally run.
STAGE_NAMES = ("grid", "roi", "search", "regression", "sensitivity")
# REDUCTIONS (how a metric reduces the sampled values of its output) and SAMPLED_REDUCTIONS (those whose
# value sits at one sample: what ``scenario.refine_peaks`` refines) come from fmusa.runs.metrics, which
# applies them.
#: Global sensitivity methods.
METHODS = ("morris", "sobol", "pce")
#: Distributions of sensitivity parameters.
DISTRIBUTIONS = ("uniform", "loguniform", "normal", "truncnormal", "lognormal")
#: Experimental designs of the polynomial chaos method.
DESIGNS = ("sobol", "lhs")
#: Most runs one sensitivity method may ask for (Saltelli's n·(k + 2), Morris' r·(k + 1), the pce budget):
#: like the grid's cap, far beyond a study on a few cores, and small enough that the samples themselves are
#: never what exhausts memory. ``FMUSA_MAX_SENSITIVITY_RUNS`` raises it.
MAX_SENSITIVITY_RUNS = 1_000_000
ENV_MAX_SENSITIVITY_RUNS = "FMUSA_MAX_SENSITIVITY_RUNS"
#: The smallest Saltelli base sample size and Morris trajectory count whose indices are worth reporting.
MIN_SOBOL_N = 64
MIN_MORRIS_TRAJECTORIES = 4


def max_sensitivity_runs() -> int:
    """The cap on one sensitivity method's runs: ``$FMUSA_MAX_SENSITIVITY_RUNS`` or
    :data:`MAX_SENSITIVITY_RUNS`."""
    import os
    raw = os.environ.get(ENV_MAX_SENSITIVITY_RUNS, "").strip()
    try:
        return max(1, int(raw)) if raw else MAX_SENSITIVITY_RUNS
    except ValueError:
        return MAX_SENSITIVITY_RUNS


def smallest_sobol_n(k: int) -> int:
    """The smallest useful Saltelli base sample for ``k`` inputs: a power of 2, at least MIN_SOBOL_N and
    4·k (below it the bootstrap intervals of the indices are wider than the indices' range)."""
    need = max(MIN_SOBOL_N, 4 * k)
    return 1 << (need - 1).bit_length()


def nearest_powers_of_two(n: int) -> tuple[int, int]:
    """The powers of 2 just below and above ``n`` (n ≥ 1)."""
    lo = 1 << (int(n).bit_length() - 1)
    return lo, (lo if lo == n else lo * 2)


#: FMI 2.0 interfaces a study may ask for (``fmu_options.interface``).
INTERFACES = ("auto", "co-simulation", "model-exchange")
#: fmpy's solvers for model exchange FMUs (``fmu_options.solver``).
SOLVERS = ("CVode", "Euler")

#: What a study, parameter or metric name may look like (a Python identifier).
IDENTIFIER = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


class StudyError(FmusaError, ValueError):
    """An invalid study file. The message is ``file:line: what is wrong; how to fix it``.

    Fix: go to the file and line the message names and make the change it says (the closest allowed key or
    name is suggested). The keys are listed on the site's *Study file keys* page.
    """


# ============================================================================ dataclasses
@dataclass(frozen=True)
class Parameter:
    """A study parameter (e.g. the paper's c) and the FMU variable it sets (c_y).

    The study may work in other units than the FMU; ``scale``/``offset`` convert, so reports and
    figures use the study's unit while the FMU always gets SI values.

    :param variable: **required** The FMU variable, any string (e.g. ``c_y``, ``body.c``, ``tab_y[1]``).
    :param unit: The study's unit, used in reports and figures.
    :param scale: Nonzero; FMU value = ``scale`` × study value + ``offset`` (unit conversion).
    :param offset: Added after ``scale``.
    :param description: Free text for the report.
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
    The report shows the study's value and unit; the FMU gets :meth:`to_fmu`.

    :param value: **required** A number in the study's unit.
    :param unit: The study's unit, shown in the report. A label only: the conversion is ``scale`` and
        ``offset`` (``fmusa inspect`` shows the FMU's own unit).
    :param scale: Nonzero; FMU value = ``scale`` × ``value`` + ``offset``; e.g.
        ``c_y: {value: 823.2, unit: N/mm, scale: 1000}`` sets ``c_y`` = 823200 N/m.
    :param offset: E.g. ``T: {value: 37, unit: degC, offset: 273.15}`` sets 310.15 K.
    :param description: Free text for the report.
    """
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

    :param stop_time: **required** The end time in s, > 0.
    :param step: Communication step (the output interval) in s, > 0. With null there is a single ``doStep``
        to ``stop_time``; the FMU's monitors make this exact.
    :param inputs: FMU inputs held constant: name → number.
    :param description: Free text.
    :param refine_peaks: With true, every run whose metrics take a peak (``max``, ``min``, ``max_abs``) or a
        settling time (``settle``) from the samples is re-run once with ``refine_factor`` times finer
        communication steps in the sampling intervals next to those samples (a model exchange FMU, or one that
        cannot vary its communication step, is re-run with the finer step throughout). Needs a ``step`` and
        such a metric.
    :param refine_factor: Integer ≥ 2; only with ``refine_peaks: true``.
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
    The reported metric is the reduction of ``scale`` × output, plus ``offset`` (unit conversion): a negative
    scale flips the axis before the reduction, so ``max`` takes the FMU's most negative sample and ``max_abs``
    stays positive.

    :param output: **required** The FMU output variable (any variable except the independent one).
    :param reduce: One of ``final``, ``max``, ``min``, ``max_abs``, ``mean``, ``mean_abs``, ``settle``, over the
        sampled output. ``settle`` is the time since which |output| ≤ ``settle_tol`` has held (the first
        such sample; NaN when the last sample is outside the band): a time to equilibrium for an FMU without a
        ``t_eq`` monitor.
    :param unit: The metric's unit, for reports.
    :param scale: Nonzero; metric = reduce(``scale`` × output) + ``offset``.
    :param offset: Added after ``scale``.
    :param missing_below: A reduced raw FMU value below this means "none" (NaN). For example ``t_eq = -1``
        means the screw never came to rest.
    :param description: Free text for the report.
    :param settle_tol: > 0, the band of ``settle``, in the FMU's unit of the output; required with ``settle``
        and allowed only there.
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
        ``mean_abs`` are time means (trapezoid rule over ``times``) of scale × output (a negative scale
        flips max and min), then ``missing_below`` (on the raw FMU value of the reduction), then ``offset``.
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

    :param name: **required** An identifier that is unique among the constraints.
    :param metric: **required** The name of a metric.
    :param max: Inclusive upper bound.
    :param min: Inclusive lower bound (≤ ``max``).
    :param required: With true, the metric must exist (not NaN). A NaN fails every constraint. Each item
        needs a bound or ``required: true``.
    :param description: Free text for the report.
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
    """The initial coarse grid (paper, Section 2.4): powers of a base, or explicit values.

    :param base: Required with ``exponents``; > 0 and not 1.
    :param exponents: Parameter → [lo, hi], an inclusive integer range with lo ≤ hi. The grid values are
        base^lo … base^hi.
    :param values: Parameter → an explicit list of values. Each parameter takes exactly one of ``exponents``
        and ``values``, and the grid must give values for every study parameter.
    """
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
    parameters, or by ``inner`` alone (an inner range) when the search has no ``outer``.

    :param manual: Parameter → [lo, hi], which overrides the region computed from the grid. Without
        ``manual``, a ``grid`` stage must come first. A ``search`` stage is also required: its ``inner`` and
        ``outer`` parameters span the region. Without ``outer``, the region is a range of ``inner`` alone: the
        grid neighbours that bracket its smallest feasible grid value (rule 1 of ``fmusa/analysis/roi.py``),
        taken at the other study parameters' first grid values (or at ``at``).
    :param at: Study parameter → value: where the study parameters that the search does not vary are held,
        both for the region computed from the grid and for the search's runs (default: each one's first grid
        value). Each value must be one of the parameter's grid values when the region is computed from the
        grid. Use it when the constraints are met only at other values of those parameters; the error of a
        grid without a feasible point there names the values where grid points are feasible.
    """
    manual: dict[str, tuple[float, float]] | None = None
    at: dict[str, float] | None = None


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
    a monotone boundary.

    :param inner: **required** The study parameter whose smallest feasible value is bisected. A ``roi`` stage
        must come first; with ``roi.manual``, both parameters need a range there.
    :param outer: The study parameter halved from the region's upper bound (≠ ``inner``). Without it the
        search is one bisection of ``inner`` inside the region; ``summary.json`` then has
        ``optimum: {inner: value}`` and a single search level whose ``outer`` is null.
    :param inner_rtol: > 0, the relative bracket width that ends the inner bisection.
    :param response_rtol: > 0, the relative change in the response that counts as "a change".
    :param max_outer: Integer ≥ 1, the most outer levels.
    :param response: [the constrained metrics] The metric names compared between consecutive outer levels
        (the search's stop rule); e.g. ``[max_y, max_v, t_eq]``.
    :param response_atol: [0] ≥ 0, an absolute floor in the metric's unit: a metric changed only if it moved by
        more than ``response_rtol`` relative *and* more than its floor. One number for every response metric,
        or metric → number (only metrics in ``response``). Without a floor a metric that is 0 up to round-off
        (a final velocity at rest, 1e-19 … 1e-150 m/s) counts as changed at every level, and the search runs
        to ``max_outer``; e.g. ``response_atol: {v_end: 5.0e-8}``.
    :param warm_start: True brackets each outer level from the previous level's answer x: x and
        x·(1 − ``inner_rtol``) are run first (2 runs when the boundary has not moved), else the bracket grows
        geometrically from x and is bisected; the monotonicity check runs once, at the final answer. Fewer FMU
        runs (the paper's study: 64 instead of 225) for an optimum within ``inner_rtol`` of the default
        search's. Needs ``outer``. ``summary.json`` gives each stage's runs under ``stage_runs`` (``asked``,
        ``simulated``).
    :param parallel: [auto] ``auto``, an integer ≥ 1 or ``false``: the points run together in one round of the
        search (``auto``: the study's workers, or the Dask cluster's threads); ``false`` is the paper's
        sequential search. The answer is the sequential search's for a monotone boundary.
    """
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
    when the study has a search stage (the paper's fits), else ``"grid"``.

    :param x: **required** A study parameter. The fits use the runs of the ``search`` stage, which must come
        before the regression; in a study without ``search``, the runs of the ``grid`` stage, which must then
        come first and give at least ``degree`` + 1 values of ``x``. ``summary.json`` names the runs fitted
        under ``regression_source`` (``search`` or ``grid``).
    :param y: **required** A list of metric names.
    :param by: A study parameter (≠ ``x``); one fit is made for each of its values.
    :param degree: Integer ≥ 1, the degree of the polynomial.
    """
    x: str
    y: list[str]
    by: str | None = None
    degree: int = 3
    source: str = "search"


@dataclass(frozen=True)
class SensitivityParameter:
    """An input of the global sensitivity analysis and its distribution.

    :param variable: **required** The FMU variable. It is varied by only one parameter and is not in
        ``fixed``.
    :param bounds: The range, lo < hi, written [lo, hi]: needed for ``uniform``, ``loguniform`` (lo > 0)
        and ``truncnormal`` (where the normal is cut); not allowed for ``normal`` and ``lognormal``.
    :param distribution: ``uniform`` (within ``bounds``), ``loguniform`` (uniform in log10 within
        ``bounds``), ``normal`` (``mean``, ``std``), ``truncnormal`` (a normal of ``mean``, ``std`` cut to
        ``bounds``) or ``lognormal`` (a positive value whose logarithm is normal; ``mean`` and ``std`` are
        those of the value itself).
    :param mean: The mean of a ``normal``, ``truncnormal`` (before the cut) or ``lognormal`` input.
    :param std: Its standard deviation, > 0.
    :param unit: The parameter's unit, for reports.
    """
    name: str
    variable: str
    bounds: tuple[float, float] | None = None
    distribution: str = "uniform"
    unit: str = ""
    mean: float | None = None
    std: float | None = None


@dataclass(frozen=True)
class PCEOptions:
    """How the ``pce`` method grows its experimental design: a batch of ``batch`` runs per round on the
    workers, a sparse polynomial chaos expansion fitted after each, until the leave-one-out error of every
    output is at most ``target_error`` or ``max_runs`` have run.

    :param target_error: The relative leave-one-out error to reach (a share of the output's variance the
        expansion fails to predict), in (0, 1).
    :param max_runs: The run budget, an integer ≥ ``batch``.
    :param batch: Runs per round; null takes max(16, 4 × the number of inputs).
    :param design: ``sobol`` (a scrambled Sobol sequence, each batch continues it) or ``lhs`` (one Latin
        hypercube per batch).
    :param max_degree: The highest total degree of the expansion, an integer ≥ 1.
    :param bootstrap: Resamples of the design for the intervals of the indices, an integer ≥ 20.
    """
    target_error: float = 1e-3
    max_runs: int = 400
    batch: int | None = None
    design: str = "sobol"
    max_degree: int = 20
    bootstrap: int = 200

    def batch_size(self, k: int) -> int:
        """Runs per round for ``k`` inputs."""
        return int(self.batch) if self.batch else max(16, 4 * k)


@dataclass(frozen=True)
class SensitivityStage:
    """Global sensitivity analysis (Morris screening, Sobol indices by Saltelli's scheme or from a
    polynomial chaos expansion) of ``outputs`` (metric names) to ``parameters``.

    :param methods: A subset of ``morris``, ``sobol`` (Saltelli's scheme: n·(k + 2) runs for k inputs),
        ``pce`` (a sparse polynomial chaos expansion, for expensive runs: see ``pce``).
    :param n: The Sobol base sample size: a power of 2, at least the smallest useful one (64, and 4 × the
        number of inputs rounded up to a power of 2); n·(k + 2) at most 1,000,000 runs
        (``FMUSA_MAX_SENSITIVITY_RUNS`` raises the cap).
    :param morris_trajectories: Integer ≥ 4 (the smallest for which μ* has an interval worth the name).
    :param seed: Integer ≥ 0, the seed of the samples.
    :param outputs: **required** A list of metric names.
    :param parameters: **required** Name → ``{variable, distribution, bounds or mean and std, unit}``. Each
        name is an identifier and must not also be a metric name.
    :param pce: The ``pce`` method's options: ``{target_error, max_runs, batch, design, max_degree,
        bootstrap}``.
    """
    methods: list[str] = field(default_factory=lambda: ["morris", "sobol"])
    n: int = 1024
    morris_trajectories: int = 20
    seed: int = 1
    outputs: list[str] = field(default_factory=list)
    parameters: dict[str, SensitivityParameter] = field(default_factory=dict)
    pce: PCEOptions = field(default_factory=PCEOptions)


@dataclass(frozen=True)
class Execution:
    """Where the runs execute: local worker processes (None = all cores) or a Dask scheduler.

    :param workers: The number of local worker processes, an integer ≥ 1; null uses all cores.
    :param scheduler: The address of a Dask scheduler, e.g. ``tcp://127.0.0.1:8786`` (``--scheduler``
        overrides it). Each Dask task runs its runs in a supervised process on its Dask worker, as the local
        pool does: a run that segfaults, hangs past ``timeout_s``, returns NaN or fmi2Error is recorded as
        failed with its reason, the process is replaced, and the Dask worker itself survives. A Dask worker
        killed from outside costs nothing: Dask gives its task to another worker. A task Dask gives up on (its
        worker died more than ``distributed.scheduler.allowed-failures`` = 3 times) records its runs as
        failed with Dask's reason; the study goes on.
    :param timeout_s: The wall-clock limit per run in s, > 0, wherever the run is made.
    :param check_fmu_steps: [auto] ``auto``, ``true`` or ``false``: after the stages, rerun a few points with the
        communication step halved, the tolerance tightened tenfold and (where the FMU has it) through model
        exchange, and flag the metrics that move by more than the study's tolerance
        (:mod:`fmusa.pipeline.solver_check`). ``auto`` checks every FMU but this repository's own
        ScrewVertebra, whose solver its tests hold to closed forms and an independent stiff solver.
    """
    workers: int | None = None
    scheduler: str | None = None
    timeout_s: float = 60.0
    check_fmu_steps: bool | None = None
    #: spawn | forkserver | fork; None: $FMUSA_START_METHOD, else the platform's default
    start_method: str | None = None
    #: a worker is replaced by a fresh one after this many runs (None: never)
    worker_max_runs: int | None = None
    #: a worker is replaced once the memory it holds alone (its unique set size) passes this many MB (None:
    #: never); its run in progress is retried
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

    :param interface: ``auto``, ``co-simulation`` or ``model-exchange`` (``CS`` and ``ME`` are accepted too).
        ``auto`` runs co-simulation when the FMU has it, else model exchange.
    :param solver: Model exchange only: fmpy's ``CVode`` (the default) or ``Euler``. An error with
        co-simulation, which integrates with the FMU's own solver.
    :param relative_tolerance: > 0 and < 1. Model exchange: CVode's relative tolerance (null: the FMU's
        default experiment, else 1e-5). Co-simulation: passed to the FMU as the tolerance of
        ``fmi2SetupExperiment``.
    :param step_size: s, > 0, model exchange only: Euler's fixed step, or the longest step CVode may take. It
        must divide ``scenario.step`` into whole steps. Null: Euler steps at ``scenario.step``, split to at
        most ``stop_time``/1000; CVode chooses its own steps.
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

    :param name: **required** An identifier (letters, digits, ``_``); names the study and its outputs.
    :param description: [""] Free text.
    :param fmu: [``default``] ``default`` (or absent) is the built ``dist/ScrewVertebra.fmu`` (or
        ``$FMUSA_FMU``); otherwise the path to an ``.fmu`` file, relative to the YAML file. The file must exist.
    :param fmu_options: [defaults of ``fmu_options``] How the FMU runs: its interface and, for model exchange,
        fmpy's solver.
    :param parameters: **required** At least one study parameter. They map onto FMU variables and are what the
        grid, RoI, search and regression work on.
    :param fixed: [{}] FMU parameters set on every run: name → number or true/false (in the FMU's unit), or
        name → ``{value, unit, scale, offset, description}`` to write the value in the study's own unit. It
        must not set the variable of a study or sensitivity parameter.
    :param scenario: **required** What one run simulates.
    :param metrics: **required** At least one. Maps a metric name to how it is computed from an FMU output.
    :param constraints: [[]] A list of conditions on metrics (Equation 2 and Table 2 of the paper).
    :param stages: **required** At least one. An ordered mapping whose keys come from ``grid``, ``roi``,
        ``search``, ``regression``, ``sensitivity``; the stages run in file order.
    :param execution: [defaults of ``execution``] Where the runs execute.
    :param paper: [{}] Reference values quoted in the paper, for the report (the paper application checks
        this block's own keys); not used by the computation.
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


