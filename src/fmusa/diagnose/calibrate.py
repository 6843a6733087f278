"""Calibration: fit one model (the baseline, or the baseline plus effects) to measured tests through the FMU.

The FMU is run only through :class:`fmusa.fmi.plans.DrivenPlan`, driven by the experiments' measured drive
through the variables a :class:`~fmusa.diagnose.interface.ModelInterface` names. :func:`calibrate` is a
multi-start bounded least squares of the response channel on all experiments jointly; :func:`heldout_rmse`
scores a fit on data it did not see; :func:`fit_candidate` does both for one candidate (a worker's job);
:func:`unify_equivalent` scores candidates that are the same equations as one model.
"""
from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, field, replace
from typing import Callable, Sequence

import numpy as np
from scipy import optimize, stats

from fmusa.diagnose.effects import (DAMPING, EQUIVALENT_BY_CONSTRUCTION, STIFFNESS, Param, Scales, constant_rate,
                                    data_scales, equivalent_intervals, equivalent_parameters, model_parameters,
                                    with_bounds)
from fmusa.diagnose.interface import ModelInterface
from fmusa.diagnose.models import resolve
from fmusa.diagnose.intervals import interval_report

__all__ = ["Fit", "ModelRunner", "Lane", "calibrate", "nested_p_value", "can_be_significant", "MIN_EXPERIMENTS_LEFT_OUT", "heldout_masks", "heldout_folds",
           "pooled_heldout", "heldout_rmse", "unify_equivalent", "fit_candidate", "make_runner"]


@dataclass
class Fit:
    """One calibrated model: parameters with 95 % intervals and its scores."""
    effect: str
    params: dict[str, float]
    ci95: dict[str, tuple[float, float]]
    rss: float
    n: int
    k: int
    rmse: float
    heldout_rmse: float = float("nan")
    predictions: list[np.ndarray] = field(default_factory=list)
    starts_tried: int = 0
    nfev: int = 0
    #: per held-out fold: the training cost of the refit, the held-out squared error and point count
    heldout_folds: list[dict] = field(default_factory=list)
    #: set when this fit is another candidate's, mapped (EQUIVALENT_BY_CONSTRUCTION): that candidate's name
    mapped_from: str | None = None
    #: with mapped_from: what this candidate's own optimiser found (params, rmse, heldout_rmse)
    own: dict | None = None
    #: parameters where the optimiser stopped at a bound: name, value, which bound
    at_bounds: list[dict] = field(default_factory=list)
    #: parameters held (not fitted), with their values and why
    held: dict = field(default_factory=dict)
    #: FMU runs this fit made, by stage ("fit": the starts and the final prediction; "heldout": the refits)
    runs: dict[str, int] = field(default_factory=dict)
    #: the least-squares cost each start reached, in the order tried
    start_costs: list[float] = field(default_factory=list)
    #: taken from a cache of an earlier diagnosis (its runs were spent then, not now)
    cached: bool = False
    #: how ci95 was made (:func:`intervals.interval_report`): method, phi, n_eff, and the Gauss–Newton intervals
    intervals: dict = field(default_factory=dict)
    #: rounds of FMU runs waited for one after another, by stage (a round: one run, or one Jacobian's columns
    #: or several held-out refits' runs at once on several FMU instances): the fit's wall time on a slow FMU
    rounds: dict[str, int] = field(default_factory=dict)
    #: why the held-out refits were not made (a fit that cannot be significant: :func:`can_be_significant`)
    heldout_skipped: str = ""
    #: wall seconds the fit took (its held-out refits included): the chain submits its costliest steps first
    seconds: float = 0.0

    @property
    def aic(self) -> float:
        return self.n * math.log(self.rss / self.n) + 2 * self.k

    @property
    def bic(self) -> float:
        return self.n * math.log(self.rss / self.n) + self.k * math.log(self.n)


def nested_p_value(base: Fit, ext: Fit) -> float:
    """F test of the extra parameters of a nested model (white-noise assumption)."""
    dk = ext.k - base.k
    dof = ext.n - ext.k
    if dk <= 0 or dof <= 0 or ext.rss <= 0:
        return 1.0
    F = max(base.rss - ext.rss, 0.0) / dk / (ext.rss / dof)
    return float(stats.f.sf(F, dk, dof))


def can_be_significant(ext: Fit, base: Fit, delta_bic: float, p_value: float) -> str:
    """Empty when ``ext`` passes the two in-sample tests of significance against ``base`` (ΔBIC below
    ``delta_bic``, nested F test's p below ``p_value``), else why not: a fit that fails either cannot be
    significant whatever its held-out score (:func:`rank.rank_candidates` needs all three)."""
    d_bic, p = ext.bic - base.bic, nested_p_value(base, ext)
    if d_bic < delta_bic and p < p_value:
        return ""
    return (f"cannot be significant against the model it extends (ΔBIC {d_bic:.3g}, needs < {delta_bic:g}; "
            f"p {p:.3g}, needs < {p_value:g}): its held-out score would not change that")


# ---------------------------------------------------------------------- simulation

#: per process, whether an FMU's Jacobians come from its sensitivities, by FMU, drive, input and output: the first
#: runner decides (:meth:`ModelRunner.sensitivities_pay`), the others of the process take its answer.
_SENS_PAYS: dict[tuple, bool] = {}
#: a run with sensitivities that costs more than this many times the 1 + k runs of forward differences is not
#: taken (measured on the force-driven stiffening test at every candidate's starts: 0.6-1.1 times; ScrewVertebra's
#: sensitivities before their columns stepped together: up to 40 times)
SENS_TOO_SLOW = 10.0
#: the local error tolerance of the forward sensitivities (the FMU's parameter ``sens_rtol``, where it has one): a
#: least-squares Jacobian steers the steps and sizes the intervals, for which three digits are plenty; at the states'
#: rtol (1e-5) the sensitivities' sub-steps made a run cost 15-90 plain ones (force-driven stiffening test, every
#: candidate at its starts); at 1e-3, with the columns stepped together and each step's start taken from the last
#: sub-step, 1.5-3 (k = 2-5). The Jacobian stays within 4e-4 of central differences of fresh runs there, but the
#: damping's column under backlash, 0.22 % (fmu/MODEL.md)
SENS_RTOL = 1e-3
SENS_RTOL_VARIABLE = "sens_rtol"


class ModelRunner:
    """The FMU of one candidate, driven by the experiments' measured drive.

    Every run is counted by stage (:attr:`runs`; the caller sets :attr:`stage`) and taken from this process's
    run budget (:mod:`fmusa.diagnose.budget`). With ``parallel`` > 1, :meth:`predict_many` runs its points as
    one round on that many instances of the FMU in threads (the FMU's C code runs outside the interpreter
    lock; an FMU that declares canBeInstantiatedOnlyOncePerProcess gets one instance)."""

    def __init__(self, fmu_path: str | os.PathLike, drive: str, names: Sequence[str],
                 fixed: dict | None = None, rtol: float = 1e-5,
                 interface: ModelInterface | None = None, parallel: int = 1) -> None:
        interface = resolve(interface, fmu_path)
        self._args = (fmu_path, drive, list(names), dict(fixed or {}), rtol, interface)
        self.input_name = interface.input_name(drive)
        self.output = interface.output_name(drive)
        # SI -> the FMU's units of the input, the FMU's units of the output -> SI
        self.in_scale = float(interface.input_scale.get(drive, 1.0))
        self.out_scale = float(interface.output_scale.get(drive, 1.0))
        self.runner, self.plan = self._open()
        cs = self.runner.model_description.coSimulation
        # an FMU that allows one instance per process gets one: its rounds run one point after another
        once = bool(getattr(cs, "canBeInstantiatedOnlyOncePerProcess", False))
        self.parallel = 1 if once else max(1, int(parallel))
        self._extra: list[tuple] = []
        #: FMU runs made, by stage ("fit", "heldout", ...), one per experiment simulated
        self.runs: dict[str, int] = {}
        #: rounds waited for one after another, by stage (:attr:`Fit.rounds`)
        self.rounds: dict[str, int] = {}
        self.stage = "fit"
        self._sens_outputs = sensitivity_outputs(self.runner.model_description, self.output,
                                                 [interface.variable(n) for n in names])
        self._sens: tuple | None = None
        #: the FMU gives the response's derivatives by the fitted parameters in the same run
        #: (:meth:`predict_with_jacobian`)
        self.has_sensitivities = bool(self._sens_outputs)
        self._sens_pays: bool | None = None
        import threading

        self._lock = threading.Lock()

    def _open(self) -> tuple:
        """One more instance of the FMU with its driven plan."""
        from fmusa.fmi.plans import DrivenPlan
        from fmusa.fmi.runner import FMURunner

        fmu_path, drive, names, fixed, rtol, interface = self._args
        settings = interface.settings(drive, rtol)
        runner = FMURunner(fmu_path, instance_name="diagnose")
        try:
            plan = DrivenPlan(runner, [interface.variable(n) for n in names], {**settings, **fixed},
                              self.input_name, [self.output])
        except Exception:
            runner.close()
            raise
        return runner, plan

    def _count(self, n: int, rounds: int = 1) -> None:
        from fmusa.diagnose.budget import take

        with self._lock:      # the held-out refits count from several threads at once
            take(self.runs, self.stage, n)
            if rounds:
                self.rounds[self.stage] = self.rounds.get(self.stage, 0) + rounds

    def _simulate(self, plan, values: Sequence[float], experiments: Sequence) -> list[np.ndarray]:
        if self.in_scale == 1.0 and self.out_scale == 1.0:
            return [plan(values, e.t, e.drive_signal)[:, 0] for e in experiments]
        return [plan(values, e.t, np.asarray(e.drive_signal) / self.in_scale)[:, 0] * self.out_scale
                for e in experiments]

    def predict(self, values: Sequence[float], experiments: Sequence) -> list[np.ndarray]:
        """The response channel of every experiment under the given parameter values."""
        self._count(len(experiments))
        return self._simulate(self.plan, values, experiments)

    def sensitivities_pay(self, values: Sequence[float], experiments: Sequence) -> bool:
        """Whether the Jacobians come from the FMU's forward sensitivities (one run) rather than forward
        differences (1 + k runs): yes, unless a run with them fails or costs far more than the differences' runs
        (timed once per runner, one run of each kind at ``values``, both counted). The choice is otherwise not
        a race of timings: on a busy machine a close one would go either way, and the fit's last digits with
        it, from one diagnosis of the same data to the next."""
        key = (str(self._args[0]), self._args[1], self.input_name, self.output)
        if self._sens_pays is None and key in _SENS_PAYS:
            self._sens_pays = _SENS_PAYS[key]
        if self._sens_pays is None:
            try:
                t0 = time.perf_counter()
                self.predict(values, experiments[:1])
                t1 = time.perf_counter()
                self.predict_with_jacobian(values, experiments[:1])  # opens the instance too
            except RuntimeError:
                # a failed run (the FMU says why; the residuals will say so too): finite differences are no worse
                # (not remembered for the FMU: a failed run says nothing of what the sensitivities cost)
                self._sens_pays = False
                return False
            if time.perf_counter() - t1 > SENS_TOO_SLOW * (1 + len(self._sens_outputs)) * (t1 - t0) + 0.05:
                # far slower even with the instance's opening (seen: 2.6 s against 6.5 ms plain, a column whose
                # sub-steps all sat at the smallest size): not remembered for the FMU either, since such a column
                # is a matter of this point
                self._sens_pays = False
                return False
            self._sens_pays = _SENS_PAYS[key] = True
        return self._sens_pays

    def predict_with_jacobian(self, values: Sequence[float], experiments: Sequence) -> tuple[list, list]:
        """:meth:`predict` and, from the same run, the derivatives of each experiment's response by the fitted
        parameters in natural units (samples x parameters), from the FMU's forward sensitivities (one run per
        experiment, as :meth:`predict`): by the first of them, as many as the FMU offers sensitivities for
        (:func:`sensitivity_outputs`). Only when :attr:`has_sensitivities`."""
        if self._sens is None:
            from fmusa.fmi.plans import DrivenPlan
            from fmusa.fmi.runner import FMURunner

            fmu_path, drive, names, fixed, rtol, interface = self._args
            md_vars = {v.name: v for v in self.runner.model_description.modelVariables}
            select = {f"sens_p[{k + 1}]": md_vars[interface.variable(n)].valueReference
                      for k, n in enumerate(names[:len(self._sens_outputs)])}
            if SENS_RTOL_VARIABLE in md_vars:   # the Jacobian to a few digits, not to the states' rtol
                select[SENS_RTOL_VARIABLE] = max(rtol, SENS_RTOL)
            runner = FMURunner(fmu_path, instance_name="diagnose")
            try:
                plan = DrivenPlan(runner, [interface.variable(n) for n in names],
                                  {**interface.settings(drive, rtol), **fixed, **select}, self.input_name,
                                  [self.output] + self._sens_outputs)
            except Exception:
                runner.close()
                raise
            self._sens = (runner, plan)
        self._count(len(experiments))
        plan = self._sens[1]
        preds, jacs = [], []
        for e in experiments:
            u = np.asarray(e.drive_signal)
            data = plan(values, e.t, u if self.in_scale == 1.0 else u / self.in_scale)
            if self.out_scale != 1.0:
                data = data * self.out_scale
            preds.append(data[:, 0])
            jacs.append(data[:, 1:])
        return preds, jacs

    def predict_many(self, points: Sequence[Sequence[float]], experiments: Sequence) -> list:
        """:meth:`predict` at every point, as one round on up to ``parallel`` FMU instances: per point the
        predictions, or the RuntimeError its simulation raised."""
        self._count(len(points) * len(experiments), -(-len(points) // max(1, self.parallel)))
        return self._round(self._plans(min(self.parallel, len(points))), points, experiments)

    def _plans(self, n: int) -> list:
        """The driven plans of ``n`` instances of the FMU (opened when first needed)."""
        while len(self._extra) < n - 1:
            self._extra.append(self._open())
        return [self.plan] + [p for _, p in self._extra[:max(0, n - 1)]]

    def _round(self, plans: list, points: Sequence[Sequence[float]], experiments: Sequence) -> list:
        def run(plan, pts):
            out = []
            for v in pts:
                try:
                    out.append(self._simulate(plan, v, experiments))
                except RuntimeError as exc:
                    out.append(exc)
            return out

        lanes = min(len(plans), len(points))
        if lanes <= 1:
            return run(plans[0], points)
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(lanes) as ex:
            parts = list(ex.map(run, plans[:lanes], [list(points[i::lanes]) for i in range(lanes)]))
        out: list = [None] * len(points)
        for i, part in enumerate(parts):
            out[i::lanes] = part
        return out

    def lanes(self, n: int) -> list["Lane"]:
        """This runner's instances shared out among ``n`` fits run at once in threads (the held-out refits):
        each lane one instance or more, its runs counted here, its rounds on its own (:attr:`Lane.rounds`)."""
        n = max(1, min(n, self.parallel))
        plans = self._plans(self.parallel)
        return [Lane(self, plans[i::n]) for i in range(n)]

    def close(self) -> None:
        for runner, _ in self._extra:
            runner.close()
        if self._sens is not None:
            self._sens[0].close()
        self.runner.close()


def sensitivity_outputs(model_description, output: str, parameters: Sequence[str]) -> list[str]:
    """The FMU's outputs of the derivatives of ``output`` by ``parameters``, when it declares forward
    sensitivities (Integer parameters ``sens_p[k]`` selecting a Real parameter by value reference, Real
    outputs ``sens_<output>[k]``, k = 1, 2, ...): one for each of the first parameters, as many as it offers
    (a model with more parameters takes the others' columns by finite differences); [] when it offers none."""
    md_vars = {v.name: v for v in model_description.modelVariables}
    if any(md_vars.get(p) is None or md_vars[p].type != "Real" for p in parameters):
        return []
    out = []
    for k in range(1, len(parameters) + 1):
        sel, der = md_vars.get(f"sens_p[{k}]"), md_vars.get(f"sens_{output}[{k}]")
        if sel is None or der is None or sel.type != "Integer" or sel.causality != "parameter" \
                or der.type != "Real" or der.causality != "output":
            break
        out.append(der.name)
    return out


class Lane:
    """Some of a :class:`ModelRunner`'s FMU instances, for one of several fits run at once: runs as the runner's
    (counted there, under its stage), rounds counted here, since the lanes' rounds overlap. Finite-difference
    Jacobians only."""

    has_sensitivities = False

    def __init__(self, owner: ModelRunner, plans: list) -> None:
        self.owner, self.plans, self.parallel, self.rounds = owner, plans, len(plans), 0

    def predict(self, values: Sequence[float], experiments: Sequence) -> list[np.ndarray]:
        self.owner._count(len(experiments), 0)
        self.rounds += 1
        return self.owner._simulate(self.plans[0], values, experiments)

    def predict_many(self, points: Sequence[Sequence[float]], experiments: Sequence) -> list:
        self.owner._count(len(points) * len(experiments), 0)
        self.rounds += -(-len(points) // self.parallel)
        return self.owner._round(self.plans, points, experiments)


# ---------------------------------------------------------------------- calibration

def response_scale(drive: str, sc: Scales) -> float:
    """Residuals are divided by the peak of the response channel, so the optimiser sees numbers near 1."""
    return sc.F_pk if drive == "displacement" else sc.y_pk


class Residuals:
    """The scaled residuals of the masked points as a function of the optimiser's coordinates, and their
    finite-difference Jacobian with all its columns as one round on the workers
    (:meth:`ModelRunner.predict_many`) instead of one run after another.

    A failed simulation gives large residuals, so the optimiser backs off instead of stopping. The
    Jacobian is the forward difference scipy's ``least_squares`` takes with ``diff_step``: a relative step,
    turned back where it would leave the bounds, from the residuals at x (the last evaluation, which the
    trust-region loop always made just before asking for the Jacobian there)."""

    def __init__(self, model: ModelRunner, params: list[Param], experiments: Sequence, masks, scale: float,
                 lo: np.ndarray, hi: np.ndarray, rel_step: float = 1e-4) -> None:
        self.model, self.params, self.experiments, self.masks, self.scale = model, params, experiments, masks, scale
        self.lo, self.hi, self.rel_step = lo, hi, rel_step
        self._last: tuple[np.ndarray, np.ndarray] | None = None
        #: the Jacobian comes with the residuals from one run (the FMU's forward sensitivities)
        self.exact = bool(getattr(model, "has_sensitivities", False))
        self._last_jac: tuple[np.ndarray, np.ndarray] | None = None

    def decide(self, x: np.ndarray) -> None:
        """Keep the sensitivities only where a run with them costs less than the finite differences' runs
        (:meth:`ModelRunner.sensitivities_pay`, timed once per runner)."""
        if self.exact and hasattr(self.model, "sensitivities_pay"):
            self.exact = self.model.sensitivities_pay(self._values(x), self.experiments)

    def _values(self, x: np.ndarray) -> list[float]:
        return [p.from_x(xi) for p, xi in zip(self.params, x)]

    def _scaled(self, preds) -> np.ndarray:
        n = sum(int(m.sum()) for m in self.masks)
        if isinstance(preds, RuntimeError):
            return np.full(n, 1e3)
        r = np.concatenate([(pr - e.response_signal)[m] / self.scale
                            for pr, e, m in zip(preds, self.experiments, self.masks)])
        # an output that is not a finite number, or a thousand times the measured peak, is a failed
        # simulation too (the FMU did not say so); left in, it would blow up the Jacobian
        return r if np.all(np.abs(r) <= 1e3) else np.full(n, 1e3)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        if self.exact:
            return self._with_jacobian(np.array(x, float))
        try:
            preds = self.model.predict(self._values(x), self.experiments)
        except RuntimeError as exc:
            preds = exc
        f = self._scaled(preds)
        self._last = (np.array(x, float), f)
        return f

    def _with_jacobian(self, x: np.ndarray) -> np.ndarray:
        """The residuals and their Jacobian on the optimiser's scale from one run with the FMU's forward
        sensitivities: d r / d x_j = (d prediction / d p_j) (d p_j / d x_j) / scale on the masked points, d p / d x
        = p for a log-scaled parameter. A failed run gives the large constant residuals and a zero Jacobian."""
        values = self._values(x)
        try:
            preds, jacs = self.model.predict_with_jacobian(values, self.experiments)
        except RuntimeError:
            # the sensitivities' failure or the simulation's: a run without them tells which. If it succeeds,
            # this fit takes finite differences from here on (a wrong or empty Jacobian would stall it)
            self.exact = False
            if hasattr(self.model, "_sens_pays"):
                self.model._sens_pays = False
            return self(x)
        f = self._scaled(preds)
        failed = jacs is None or bool(np.all(f == 1e3))
        if failed:
            J = np.zeros((len(f), len(x)))
        else:
            m = jacs[0].shape[1]
            dpdx = np.array([v if p.log else 1.0 for p, v in zip(self.params[:m], values[:m])])
            J = np.concatenate([jac[mk] for jac, mk in zip(jacs, self.masks)]) * (dpdx / self.scale)
            if not np.all(np.isfinite(J)):
                J = np.zeros((len(f), m))
            if m < len(x):      # more parameters than the FMU has sensitivities for: the rest by differences
                J = np.hstack([J, self._differences(x, f, range(m, len(x)))])
        self._last = (x, f)
        self._last_jac = (x, J)
        return f

    def jac(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, float)
        if self.exact and (self._last_jac is None or not np.array_equal(self._last_jac[0], x)):
            self._with_jacobian(x.copy())          # may fall back to finite differences (self.exact False)
        if self.exact:
            return self._last_jac[1]
        f0 = self._last[1] if self._last is not None and np.array_equal(self._last[0], x) else self(x)
        return self._differences(x, f0, range(len(x)))

    def _differences(self, x: np.ndarray, f0: np.ndarray, columns: Sequence[int]) -> np.ndarray:
        """The Jacobian's ``columns`` by forward differences from the residuals ``f0`` at x, as one round."""
        h = self.rel_step * np.where(x >= 0, 1.0, -1.0) * np.maximum(1.0, np.abs(x))
        out = (x + h < self.lo) | (x + h > self.hi)
        h[out] *= -1
        points, steps = [], []
        for j in columns:
            xj = x.copy()
            xj[j] = x[j] + h[j]
            steps.append(xj[j] - x[j])
            points.append(self._values(xj))
        preds = self.model.predict_many(points, self.experiments)
        J = np.empty((len(f0), len(steps)))
        for j, (pr, dx) in enumerate(zip(preds, steps)):
            J[:, j] = (self._scaled(pr) - f0) / dx
        return J


def _starts(params: list[Param], max_starts: int) -> list[np.ndarray]:
    """Combinations of the per-parameter starts (the effect's own, the baseline's single one)."""
    grids = [[p.to_x(s) for s in p.starts] for p in params]
    combos: list[list[float]] = [[]]
    for g in grids:
        combos = [c + [x] for c in combos for x in g]
    return [np.array(c) for c in combos[:max_starts]]


def parameter_bounds(params: list[Param]) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds on the optimiser's scale."""
    return (np.array([p.to_x(p.lower) for p in params]), np.array([p.to_x(p.upper) for p in params]))


#: the trust-region loop's stopping tolerances on the cost and the step (scipy's ftol, xtol)
FTOL = XTOL = 1e-6
#: the same for the held-out refits, which start at the all-data optimum: their score is a held-out error compared
#: at 0.9x and 1.1x of another's, and at 1e-6 a refit crawling along a direction its fold does not pin down (a
#: damping that goes to 0 on a log scale) spent its 40 evaluations there: on the force-driven stiffening test
#: 230 runs of held-out refits instead of 434, the verdict and every identifiability cell unchanged
HELDOUT_TOL = 1e-4


def _least_squares(fn: Residuals, x0, lo, hi, max_nfev: int, tol: float | None = None) -> optimize.OptimizeResult:
    """One bounded trust-region fit from x0 (nudged inside the bounds, which trf requires)."""
    x0 = np.clip(x0, lo + 1e-12 * (hi - lo), hi - 1e-12 * (hi - lo))
    fn.decide(x0)
    # the FMU's forward sensitivities: the Jacobian of the run that gave the residuals; otherwise, on one FMU
    # instance, scipy's own forward differences (the same runs, one after another)
    jac = fn.jac if fn.exact or fn.model.parallel > 1 else "2-point"
    return optimize.least_squares(fn, x0, jac=jac, bounds=(lo, hi), method="trf", x_scale="jac",
                                  diff_step=fn.rel_step, max_nfev=max_nfev, xtol=tol or XTOL, ftol=tol or FTOL)


def _to_natural(p: Param, lo_x: float, hi_x: float) -> tuple[float, float]:
    """An interval on the optimiser's scale in natural units, clipped to the bounds."""
    lo_x, hi_x = max(lo_x, p.to_x(p.lower)), min(hi_x, p.to_x(p.upper))
    lo_v = p.from_x(lo_x) if math.isfinite(lo_x) else p.lower
    hi_v = p.from_x(hi_x) if math.isfinite(hi_x) else p.upper
    return (max(lo_v, p.lower), min(hi_v, p.upper))


def _confidence(res, params: list[Param], n: int, lengths: Sequence[int] | None = None) -> tuple[dict, dict]:
    """95 % intervals on the optimiser's scale (so log-scaled ones are asymmetric), clipped to the bounds:
    the AR(1) sandwich where the residuals are autocorrelated, Gauss–Newton where they are not
    (:func:`intervals.interval_report`); and how they were made (method, φ, effective n, the Gauss–Newton
    intervals beside)."""
    try:
        rep = interval_report(res.jac, res.fun, res.x, lengths)
    except (np.linalg.LinAlgError, ValueError):
        inf = {p.name: (p.lower, p.upper) for p in params}
        return inf, {"method": "none (the covariance could not be computed)", "gauss_newton": inf}
    ci = {p.name: _to_natural(p, lo, hi) for p, lo, hi in zip(params, rep["lower"], rep["upper"])}
    gn = {p.name: _to_natural(p, lo, hi) for p, lo, hi in zip(params, *rep["gauss_newton"])}
    return ci, {"method": rep["method"], "phi": rep["phi"], "phi_used": rep["phi_used"], "n_eff": rep["n_eff"],
                "p_value": rep["p_value"], "gauss_newton": gn}


#: two starts agree when their residual sums of squares differ by at most this in BIC units (n ln(rss1/rss2)):
#: a tenth of what the ranking's tie threshold and significance tests could notice
AGREE_DBIC = 0.1


def calibrate(model: ModelRunner, effect: str, drive: str, experiments: Sequence, sc: Scales,
              max_starts: int = 6, max_nfev: int = 60, held: Sequence[str] = (),
              start: dict | None = None, agree: int = 0, skip: int = 0) -> Fit:
    """Multi-start bounded least squares of the response channel on all experiments jointly.

    ``held``: parameters of the model that are not fitted; ``model`` must have been built without them
    (their values in its ``fixed``), and the fit's params, intervals and k leave them out. ``start``: a first
    start in natural units (e.g. from a direct fit of the data), tried before the generic ones. ``agree``:
    stop trying starts once that many have reached the best cost so far (within :data:`AGREE_DBIC`); 0 tries
    them all. ``skip``: leave out that many starts from the front (those an earlier fit tried), but never all."""
    params = [p for p in model_parameters(effect, drive, sc) if p.name not in held]
    scale = response_scale(drive, sc)
    masks = [np.ones(len(e.t), bool) for e in experiments]
    lo, hi = parameter_bounds(params)
    fn = Residuals(model, params, experiments, masks, scale, lo, hi)
    best, nfev, starts = None, 0, _starts(params, max_starts)
    if start:
        starts = [np.array([p.to_x(min(max(float(start.get(p.name, p.starts[0])), p.lower), p.upper))
                            for p in params])] + starts
    starts = starts[min(skip, len(starts) - 1):]
    model.stage = "fit"
    n_points = sum(len(e.t) for e in experiments)
    costs: list[float] = []
    for x0 in starts:
        res = _least_squares(fn, x0, lo, hi, max_nfev)
        nfev += res.nfev
        costs.append(float(res.cost))
        if best is None or res.cost < best.cost:
            best = res
        if agree and sum(n_points * math.log(max(c, 1e-300) / max(best.cost, 1e-300)) <= AGREE_DBIC
                         for c in costs) >= agree:
            break
    n = sum(len(e.t) for e in experiments)
    ci, how = _confidence(best, params, n, [len(e.t) for e in experiments])
    values = [p.from_x(x) for p, x in zip(params, best.x)]
    preds = model.predict(values, experiments)
    rss = float(sum(np.sum((pr - e.response_signal) ** 2) for pr, e in zip(preds, experiments)))
    return Fit(effect=effect, params={p.name: v for p, v in zip(params, values)},
               ci95=ci, rss=rss, n=n, k=len(params), rmse=math.sqrt(rss / n), intervals=how,
               predictions=preds, starts_tried=len(costs), nfev=nfev, at_bounds=at_bounds(params, best.x, lo, hi),
               start_costs=costs)


def at_bounds(params: list[Param], x: np.ndarray, lo: np.ndarray, hi: np.ndarray, rel: float = 1e-6) -> list[dict]:
    """The parameters the optimiser left at a bound (within ``rel`` of the range on its scale): a fit that
    stops there did not find an optimum inside the range, which the report says. A lower bound of 0 on an
    effect size (an effect switched off) counts too."""
    out = []
    for p, xi, a, b in zip(params, x, lo, hi):
        span = max(b - a, 1e-300)
        if xi - a <= rel * span or b - xi <= rel * span:
            which = "lower" if xi - a <= rel * span else "upper"
            out.append({"name": p.name, "value": p.from_x(xi), "bound": which,
                        "limit": p.lower if which == "lower" else p.upper})
    return out


#: whole experiments are left out in turn only when every training set still holds at least two of them
MIN_EXPERIMENTS_LEFT_OUT = 3


def heldout_masks(experiments: Sequence, blocks: int = 4) -> list[list[np.ndarray]]:
    """Folds of held-out points: whole experiments (leave one out) when there are three or more, else
    ``blocks`` contiguous blocks in time of every experiment (fold b leaves out block b of each).

    With two experiments, leaving one out would fit a single one: the contrast the second adds (a second
    rate: damping scales with it, friction does not) would be missing from every training set, so no
    held-out score could show an effect that only the contrast identifies."""
    if len(experiments) >= MIN_EXPERIMENTS_LEFT_OUT:
        return [[np.full(len(e.t), i == j) for j, e in enumerate(experiments)] for i in range(len(experiments))]
    folds = []
    for b in range(blocks):
        fold = []
        for e in experiments:
            n = len(e.t)
            edges = np.linspace(0, n, blocks + 1).astype(int)
            m = np.zeros(n, bool)
            m[edges[b]:edges[b + 1]] = True
            fold.append(m)
        folds.append(fold)
    return folds


def heldout_folds(model: ModelRunner, fit: Fit, drive: str, experiments: Sequence, sc: Scales,
                  max_nfev: int = 40, held: Sequence[str] = ()) -> list[dict]:
    """Refit without each fold and predict it: per fold, the training cost of the refit (the least-squares
    cost on the scaled residuals of the training points), the squared error on the held-out points and
    their count.

    Each refit starts from the all-data optimum (one start, to keep the cost at a few fits); ``held`` as in
    :func:`calibrate`. With several FMU instances (``model.parallel`` > 1) the refits run at once in threads,
    the instances shared out among them (:meth:`ModelRunner.lanes`): a slow FMU waits for the slowest refit,
    not for all of them one after another. Each refit is the same computation whichever lane runs it."""
    params = [p for p in model_parameters(fit.effect, drive, sc) if p.name not in held]
    scale = response_scale(drive, sc)
    lo, hi = parameter_bounds(params)
    x_full = np.array([p.to_x(min(max(fit.params[p.name], p.lower), p.upper)) for p in params])
    model.stage = "heldout"
    masks = heldout_masks(experiments)

    def refit(runner, held_out) -> dict:
        fn = Residuals(runner, params, experiments, [~m for m in held_out], scale, lo, hi)
        res = _least_squares(fn, x_full, lo, hi, max_nfev, HELDOUT_TOL)
        preds = runner.predict([p.from_x(x) for p, x in zip(params, res.x)], experiments)
        sq, count = 0.0, 0
        for pr, e, m in zip(preds, experiments, held_out):
            sq += float(np.sum((pr - e.response_signal)[m] ** 2))
            count += int(m.sum())
        return {"train_cost": float(res.cost), "sq": sq, "count": count}

    # one after another: one instance, a coupled runner, or an FMU whose Jacobian is one run already
    if model.parallel <= 1 or not hasattr(model, "lanes") or len(masks) < 2 \
            or getattr(model, "has_sensitivities", False):
        return [refit(model, m) for m in masks]
    from concurrent.futures import ThreadPoolExecutor

    lanes = model.lanes(len(masks))

    def run_lane(i: int) -> list[dict]:
        return [refit(lanes[i], m) for m in masks[i::len(lanes)]]

    with ThreadPoolExecutor(len(lanes)) as ex:
        parts = list(ex.map(run_lane, range(len(lanes))))
    with model._lock:
        model.rounds["heldout"] = model.rounds.get("heldout", 0) + max(lane.rounds for lane in lanes)
    folds: list = [None] * len(masks)
    for i, part in enumerate(parts):
        folds[i::len(lanes)] = part
    return folds


def pooled_heldout(folds: Sequence[dict]) -> float:
    """The held-out RMSE of the folds: the squared errors of all folds pooled."""
    count = sum(f["count"] for f in folds)
    return math.sqrt(sum(f["sq"] for f in folds) / count) if count else float("nan")


def heldout_rmse(model: ModelRunner, fit: Fit, drive: str, experiments: Sequence, sc: Scales,
                 max_nfev: int = 40) -> float:
    """Prediction error on data the fit did not see: refit without each fold, predict the fold; the
    score is the prediction error of the training-only optimum on the held-out points."""
    return pooled_heldout(heldout_folds(model, fit, drive, experiments, sc, max_nfev))


def unify_equivalent(fits: dict[str, Fit]) -> dict[str, Fit]:
    """Score candidates that are the same equations (EQUIVALENT_BY_CONSTRUCTION) as one model.

    Each member's optimiser finds its own optimum, and the two drift apart (a local minimum in one
    parametrisation, a held-out refit that stalls in the other), though the model is the same. So the member
    with the lower all-data cost keeps its fit, the other gets it mapped into its own parameters
    (:func:`effects.equivalent_parameters`, intervals by :func:`effects.equivalent_intervals`), with the same
    predictions and residuals; and in each held-out fold the refit with the lower *training* cost (never the
    held-out error) gives the held-out error of both. What the other's own optimiser found stays in ``own``."""
    out = dict(fits)
    for pair in EQUIVALENT_BY_CONSTRUCTION:
        a, b = sorted(pair)
        if not (isinstance(fits.get(a), Fit) and isinstance(fits.get(b), Fit)):
            continue
        fa, fb = fits[a], fits[b]
        best, other = (fa, fb) if fa.rss <= fb.rss else (fb, fa)
        folds = list(best.heldout_folds)
        if len(best.heldout_folds) == len(other.heldout_folds) and folds:
            folds = [x if x["train_cost"] <= y["train_cost"] else y
                     for x, y in zip(best.heldout_folds, other.heldout_folds)]
        held = pooled_heldout(folds) if folds else min(best.heldout_rmse, other.heldout_rmse)
        out[best.effect] = replace(best, heldout_rmse=held, heldout_folds=folds,
                                   own={"params": dict(best.params), "rmse": best.rmse,
                                        "heldout_rmse": best.heldout_rmse, "heldout_folds": list(best.heldout_folds)})
        out[other.effect] = replace(
            best, effect=other.effect, k=other.k, heldout_rmse=held, heldout_folds=folds,
            params=equivalent_parameters(best.effect, best.params, other.effect),
            ci95=equivalent_intervals(best.effect, best.params, best.ci95, other.effect),
            mapped_from=best.effect,
            own={"params": dict(other.params), "rmse": other.rmse, "heldout_rmse": other.heldout_rmse,
                 "heldout_folds": list(other.heldout_folds)})
    return out


def fit_candidate(fmu_path: str, effect: str, drive: str, experiments: Sequence,
                  max_starts: int = 6, interface: ModelInterface | None = None, parallel: int = 1,
                  agree: int = 0, start: dict | None = None, gate: dict | None = None, skip: int = 0) -> Fit:
    """Calibrate one model and score it on held-out data (runs in a worker process).

    Under a drive of one constant rate (:func:`effects.constant_rate`) the damping is held at 0: its
    force d*v is a constant there, which the fit would trade against the stiffness (a baseline fitted a
    constant 150 N through d*v with the stiffness -> 0). ``parallel``: FMU instances for the rounds of a
    Jacobian; ``agree``, ``start``, ``skip``: as in :func:`calibrate`. ``gate``: the model this one extends (``rss``, ``n``,
    ``k``) and the thresholds (``delta_bic``, ``p_value``), and with ``physics`` the check of its parameters against
    what the tests support: when the fit cannot be significant against that model (:func:`can_be_significant`)
    or is implausible (:func:`plausibility.implausible`), and so cannot be chosen whatever its held-out score,
    its held-out refits are not made (``heldout_skipped`` says why, the held-out RMSE is NaN). The fit's ``runs`` counts its FMU runs by stage; when
    the run budget ends, :class:`~fmusa.diagnose.budget.BudgetExhausted` carries them out in ``runs``."""
    from fmusa.diagnose.budget import BudgetExhausted

    interface = resolve(interface, fmu_path)
    sc = with_bounds(data_scales(experiments), interface.bounds)
    const = constant_rate(experiments) if drive == "displacement" else None
    fixed = {DAMPING: 0.0} if const else {}
    names = [p.name for p in model_parameters(effect, drive, sc) if p.name not in fixed]
    model = make_runner(fmu_path, drive, names, fixed, interface, parallel=parallel)
    t0 = time.perf_counter()
    try:
        fit = calibrate(model, effect, drive, experiments, sc, max_starts=max_starts, held=tuple(fixed),
                        agree=agree, start=start, skip=skip)
        if gate:
            fit.heldout_skipped = _gated(fit, effect, gate, {**fit.params, **fixed}, experiments)
        if not fit.heldout_skipped:
            fit.heldout_folds = heldout_folds(model, fit, drive, experiments, sc, held=tuple(fixed))
            fit.heldout_rmse = pooled_heldout(fit.heldout_folds)
        fit.runs = dict(model.runs)
        fit.rounds = dict(getattr(model, "rounds", {}) or {})
        fit.seconds = time.perf_counter() - t0
    except Exception as exc:   # the runs spent go with the error (BudgetExhausted, or a fit that failed)
        exc.runs = dict(model.runs)
        raise
    finally:
        model.close()
    if const:
        fit.params = {STIFFNESS: fit.params[STIFFNESS], DAMPING: 0.0,
                      **{k: v for k, v in fit.params.items() if k != STIFFNESS}}
        fit.ci95 = {STIFFNESS: fit.ci95[STIFFNESS], DAMPING: (0.0, 0.0),
                    **{k: v for k, v in fit.ci95.items() if k != STIFFNESS}}
        fit.held = {DAMPING: {"value": 0.0, "why": const["why"], "identifying_test": const["identifying_test"]}}
    return fit


def _gated(fit: Fit, effect: str, gate: dict, params: dict, experiments: Sequence) -> str:
    """Why a fit's held-out refits are not worth their runs (see :func:`fit_candidate`), or empty."""
    base = Fit(effect="", params={}, ci95={}, rss=gate["rss"], n=gate["n"], k=gate["k"], rmse=0.0)
    why = can_be_significant(fit, base, gate["delta_bic"], gate["p_value"])
    if why or not gate.get("physics"):
        return why
    from fmusa.diagnose.plausibility import implausible, support_of

    bad = implausible(effect, params, support_of(experiments))
    return ("implausible: " + "; ".join(b["why"] for b in bad)) if bad else ""


def make_runner(fmu_path: str, drive: str, names: Sequence[str], fixed: dict, interface: ModelInterface,
                parallel: int = 1):
    """The runner of one candidate: the FMU alone (effects inside it), or coupled to the interface element
    (effects attached, :mod:`fmusa.diagnose.attached`). ``fixed`` in catalogue names."""
    if interface.attached is not None:
        from fmusa.diagnose.attached import CoupledRunner

        return CoupledRunner(fmu_path, drive, names, fixed, interface=interface)
    return ModelRunner(fmu_path, drive, names, fixed={interface.variable(k): v for k, v in fixed.items()},
                       interface=interface, parallel=parallel)
