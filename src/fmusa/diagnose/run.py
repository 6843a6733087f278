"""Diagnose a model against measured tests: calibrate, rank the candidate effects, measure the gain.

The stages are plain functions: :func:`calibrate` fits one model (the baseline spring-damper or the
baseline plus one effect) to one or more experiments by bounded least squares through the FMU driven
by the measured drive; :func:`diagnose` fits every candidate, scores it on held-out data and by
information criteria, and names the effect only when its gain is significant. The FMU is run only
through :class:`fmusa.evaluate.DrivenPlan`.
"""
from __future__ import annotations

import math
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy import optimize, stats

CANDIDATES = ("nonlinear_stiffness", "viscoelastic_relaxation", "coulomb_friction", "yield_softening",
              "backlash_gap", "sensor_offset")

# Which measurement tells two candidates apart when the data could not.
SEPARATING_TESTS = {
    frozenset({"nonlinear_stiffness", "yield_softening"}):
        "unload after the peak: an elastic curve retraces loading, yielding leaves a permanent set",
    frozenset({"nonlinear_stiffness", "backlash_gap"}):
        "load through zero in both directions: slack gives a zero-force band, a toe region does not",
    frozenset({"nonlinear_stiffness", "viscoelastic_relaxation"}):
        "test at several rates or hold the displacement: only the Maxwell branch depends on rate and relaxes",
    frozenset({"viscoelastic_relaxation", "coulomb_friction"}):
        "hold the displacement: a Maxwell branch relaxes, friction holds its force; or change the rate",
    frozenset({"viscoelastic_relaxation", "yield_softening"}):
        "hold the displacement and test at several rates: relaxation is rate dependent, yield is not",
    frozenset({"coulomb_friction", "yield_softening"}):
        "unload and reload: friction opens a loop of constant width from the first motion, yield only past "
        "the yield force",
    frozenset({"coulomb_friction", "sensor_offset"}):
        "reverse the motion: friction changes sign with the velocity, a sensor offset does not",
    frozenset({"backlash_gap", "sensor_offset"}):
        "read the channels at rest before loading and load through zero",
    frozenset({"backlash_gap", "yield_softening"}):
        "unload to zero and reload: slack shows at every reloading, a yield set only after yielding",
    frozenset({"sensor_offset", "nonlinear_stiffness"}):
        "read the channels at rest before loading (zero load must read zero)",
    frozenset({"sensor_offset", "viscoelastic_relaxation"}):
        "hold the displacement long enough for relaxation to finish, then unload to zero",
    frozenset({"sensor_offset", "yield_softening"}):
        "unload to zero: a yield set remains in displacement, an offset stays constant in the channel",
    frozenset({"backlash_gap", "viscoelastic_relaxation"}):
        "hold the displacement: relaxation shows, slack does not",
    frozenset({"backlash_gap", "coulomb_friction"}):
        "reverse the motion at a load well above zero: friction drops by twice its force, slack does not",
}

FMU_SETTINGS = {
    "displacement": ({"mode": 2, "use_y_in": True}, "y_in", "F_meas"),
    "force": ({"mode": 1, "F_max": 0.0}, "F_ext_y", "y_meas"),
}

UNITS = {"c_y": "N/m", "d_y": "N.s/m", "gap": "m", "nl_ratio": "1", "nl_y_b": "m", "yield_ratio": "1",
         "yield_F": "N", "fric_F": "N", "ve_k": "N/m", "ve_tau": "s", "F_offset": "N", "y_offset": "m"}

MAIN_PARAMETER = {"nonlinear_stiffness": "nl_ratio", "viscoelastic_relaxation": "ve_tau",
                  "coulomb_friction": "fric_F", "yield_softening": "yield_F", "backlash_gap": "gap",
                  "sensor_offset": None}   # F_offset or y_offset, by drive


class DiagnoseError(ValueError):
    """Bad input to the diagnosis: names what is wrong and the fix."""


@dataclass(frozen=True)
class Param:
    """One fitted parameter: bounds and starts in natural units, optimised on a log or linear scale."""
    name: str
    lower: float
    upper: float
    starts: tuple[float, ...]
    log: bool = False

    def to_x(self, value: float) -> float:
        return math.log(value) if self.log else value

    def from_x(self, x: float) -> float:
        return math.exp(x) if self.log else x


@dataclass(frozen=True)
class Scales:
    """Sizes of the data that set bounds and starts: peak displacement and force, secant stiffness, times."""
    y_pk: float
    F_pk: float
    v_pk: float
    c0: float
    t_min: float
    t_max: float
    dt_min: float


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

    @property
    def aic(self) -> float:
        return self.n * math.log(self.rss / self.n) + 2 * self.k

    @property
    def bic(self) -> float:
        return self.n * math.log(self.rss / self.n) + self.k * math.log(self.n)


# ---------------------------------------------------------------------- the data's scales

def data_scales(experiments: Sequence) -> Scales:
    """Bounds and starts come from these, so a test in mm and kN fits as well as one in m and N."""
    y_pk = max(float(np.max(np.abs(e.displacement))) for e in experiments)
    F_pk = max(float(np.max(np.abs(e.force))) for e in experiments)
    v_pk = max(float(np.max(np.abs(np.diff(e.displacement) / np.diff(e.t)))) for e in experiments)
    if not (y_pk > 0 and F_pk > 0):
        raise DiagnoseError("the data have no displacement or no force: nothing to calibrate")
    # secant stiffness from a least-squares line through the origin over all experiments
    ys = np.concatenate([e.displacement for e in experiments])
    Fs = np.concatenate([e.force for e in experiments])
    c0 = abs(float(np.dot(ys, Fs) / np.dot(ys, ys)))
    durations = [float(e.t[-1] - e.t[0]) for e in experiments]
    dt_min = min(float(np.min(np.diff(e.t))) for e in experiments)
    return Scales(y_pk=y_pk, F_pk=F_pk, v_pk=v_pk, c0=c0 if c0 > 0 else F_pk / y_pk,
                  t_min=min(durations), t_max=max(durations), dt_min=dt_min)


def model_parameters(effect: str, drive: str, sc: Scales) -> list[Param]:
    """The fitted parameters of the baseline (c_y, d_y) plus those of one effect, with data-scaled bounds."""
    if "+" in effect:   # several effects at once, e.g. "nonlinear_stiffness+viscoelastic_relaxation"
        parts = effect.split("+")
        out = model_parameters(parts[0], drive, sc)
        for part in parts[1:]:
            out += model_parameters(part, drive, sc)[2:]
        return out
    c0, y_pk, F_pk = sc.c0, sc.y_pk, sc.F_pk
    d_max = 2.0 * F_pk / sc.v_pk
    base = [Param("c_y", c0 / 100, c0 * 100, (c0,), log=True),
            Param("d_y", 0.0, d_max, (0.001 * d_max,))]
    if effect == "none":
        return base
    if effect == "backlash_gap":
        return base + [Param("gap", 0.0, 0.9 * y_pk, (0.05 * y_pk, 0.2 * y_pk, 0.4 * y_pk))]
    if effect == "nonlinear_stiffness":
        return base + [Param("nl_ratio", 0.05, 20.0, (0.5, 2.0), log=True),
                       Param("nl_y_b", 0.02 * y_pk, 0.98 * y_pk, (0.25 * y_pk, 0.5 * y_pk, 0.75 * y_pk))]
    if effect == "yield_softening":
        return base + [Param("yield_ratio", 0.0, 0.99, (0.3,)),
                       Param("yield_F", 0.05 * F_pk, 1.5 * F_pk, (0.3 * F_pk, 0.6 * F_pk, 0.9 * F_pk),
                             log=True)]
    if effect == "coulomb_friction":
        return base + [Param("fric_F", 0.0, 0.5 * F_pk, (0.02 * F_pk, 0.1 * F_pk, 0.3 * F_pk))]
    if effect == "viscoelastic_relaxation":
        tau_lo, tau_hi = max(sc.dt_min, 1e-4 * sc.t_max), 10.0 * sc.t_max
        taus = tuple(min(max(f * sc.t_max, tau_lo), tau_hi) for f in (0.03, 0.3))
        if sc.t_max > 30 * sc.t_min:   # several rates: a start at the short tests' time scale too
            taus = taus + (min(max(0.3 * sc.t_min, tau_lo), tau_hi),)
        return base + [Param("ve_k", 0.0, 20.0 * c0, (0.3 * c0, 1.0 * c0)),
                       Param("ve_tau", tau_lo, tau_hi, taus, log=True)]
    if effect == "sensor_offset":
        if drive == "displacement":
            return base + [Param("F_offset", -0.5 * F_pk, 0.5 * F_pk, (0.0,))]
        return base + [Param("y_offset", -0.5 * y_pk, 0.5 * y_pk, (0.0,))]
    raise DiagnoseError(f"unknown effect {effect!r}; use one of none, {', '.join(CANDIDATES)}")


def main_parameter(effect: str, drive: str) -> str | None:
    if effect == "sensor_offset":
        return "F_offset" if drive == "displacement" else "y_offset"
    return MAIN_PARAMETER.get(effect)


# ---------------------------------------------------------------------- simulation

class ModelRunner:
    """The FMU of one candidate, driven by the experiments' measured drive."""

    def __init__(self, fmu_path: str | os.PathLike, drive: str, names: Sequence[str],
                 fixed: dict | None = None, rtol: float = 1e-5) -> None:
        from fmusa.fmi.plans import DrivenPlan
        from fmusa.fmi.runner import FMURunner

        settings, self.input_name, self.output = FMU_SETTINGS[drive]
        self.runner = FMURunner(fmu_path, instance_name="diagnose")
        self.plan = DrivenPlan(self.runner, list(names), {**settings, "rtol": rtol, "monitors": False, **(fixed or {})},
                               self.input_name, [self.output])

    def predict(self, values: Sequence[float], experiments: Sequence) -> list[np.ndarray]:
        return [self.plan(values, e.t, e.drive_signal)[:, 0] for e in experiments]

    def close(self) -> None:
        self.runner.close()


# ---------------------------------------------------------------------- calibration

def _residual_fn(model: ModelRunner, params: list[Param], experiments: Sequence, masks, scale: float):
    def fn(x: np.ndarray) -> np.ndarray:
        values = [p.from_x(xi) for p, xi in zip(params, x)]
        try:
            preds = model.predict(values, experiments)
        except RuntimeError:
            return np.full(sum(int(m.sum()) for m in masks), 1e3)
        return np.concatenate([(pr - e.response_signal)[m] / scale
                               for pr, e, m in zip(preds, experiments, masks)])
    return fn


def _starts(params: list[Param], max_starts: int) -> list[np.ndarray]:
    """Combinations of the per-parameter starts (the effect's own, the baseline's single one)."""
    grids = [[p.to_x(s) for s in p.starts] for p in params]
    combos: list[list[float]] = [[]]
    for g in grids:
        combos = [c + [x] for c in combos for x in g]
    return [np.array(c) for c in combos[:max_starts]]


def _bounds(params: list[Param]) -> tuple[np.ndarray, np.ndarray]:
    return (np.array([p.to_x(p.lower) for p in params]), np.array([p.to_x(p.upper) for p in params]))


def _least_squares(fn, x0, lo, hi, max_nfev: int):
    x0 = np.clip(x0, lo + 1e-12 * (hi - lo), hi - 1e-12 * (hi - lo))
    return optimize.least_squares(fn, x0, bounds=(lo, hi), method="trf", x_scale="jac",
                                  diff_step=1e-4, max_nfev=max_nfev, xtol=1e-10, ftol=1e-10)


def _confidence(res, params: list[Param], n: int) -> dict[str, tuple[float, float]]:
    """95 % intervals from the Gauss-Newton covariance, on the optimiser's scale (so log-scaled ones are
    asymmetric), clipped to the bounds. Residual autocorrelation makes them too narrow: see the report."""
    k = len(params)
    dof = max(n - k, 1)
    s2 = 2.0 * res.cost / dof
    J = res.jac
    try:
        cov = np.linalg.pinv(J.T @ J) * s2
        se = np.sqrt(np.clip(np.diag(cov), 0, None))
    except np.linalg.LinAlgError:
        se = np.full(k, np.inf)
    q = stats.t.ppf(0.975, dof)
    out = {}
    for p, x, e in zip(params, res.x, se):
        lo_x, hi_x = max(x - q * e, p.to_x(p.lower)), min(x + q * e, p.to_x(p.upper))
        lo_v = p.from_x(lo_x) if math.isfinite(lo_x) else p.lower
        hi_v = p.from_x(hi_x) if math.isfinite(hi_x) else p.upper
        out[p.name] = (max(lo_v, p.lower), min(hi_v, p.upper))
    return out


def calibrate(model: ModelRunner, effect: str, drive: str, experiments: Sequence, sc: Scales,
              max_starts: int = 6, max_nfev: int = 60) -> Fit:
    """Multi-start bounded least squares of the response channel on all experiments jointly."""
    params = model_parameters(effect, drive, sc)
    scale = sc.F_pk if drive == "displacement" else sc.y_pk
    masks = [np.ones(len(e.t), bool) for e in experiments]
    fn = _residual_fn(model, params, experiments, masks, scale)
    lo, hi = _bounds(params)
    best, nfev, starts = None, 0, _starts(params, max_starts)
    for x0 in starts:
        res = _least_squares(fn, x0, lo, hi, max_nfev)
        nfev += res.nfev
        if best is None or res.cost < best.cost:
            best = res
    n = sum(len(e.t) for e in experiments)
    values = [p.from_x(x) for p, x in zip(params, best.x)]
    preds = model.predict(values, experiments)
    rss = float(sum(np.sum((pr - e.response_signal) ** 2) for pr, e in zip(preds, experiments)))
    return Fit(effect=effect, params={p.name: v for p, v in zip(params, values)},
               ci95=_confidence(best, params, n), rss=rss, n=n, k=len(params), rmse=math.sqrt(rss / n),
               predictions=preds, starts_tried=len(starts), nfev=nfev)


def heldout_masks(experiments: Sequence, blocks: int = 4) -> list[list[np.ndarray]]:
    """Folds of held-out points: whole experiments when there are several, else contiguous blocks."""
    if len(experiments) > 1:
        return [[np.full(len(e.t), i == j) for j, e in enumerate(experiments)] for i in range(len(experiments))]
    n = len(experiments[0].t)
    edges = np.linspace(0, n, blocks + 1).astype(int)
    folds = []
    for b in range(blocks):
        m = np.zeros(n, bool)
        m[edges[b]:edges[b + 1]] = True
        folds.append([m])
    return folds


def heldout_rmse(model: ModelRunner, fit: Fit, drive: str, experiments: Sequence, sc: Scales,
                 max_nfev: int = 40) -> float:
    """Prediction error on data the fit did not see: refit without each fold, predict the fold.

    Each refit starts from the all-data optimum (one start, to keep the cost at a few fits); the
    score is the prediction error of the training-only optimum on the held-out points."""
    params = model_parameters(fit.effect, drive, sc)
    scale = sc.F_pk if drive == "displacement" else sc.y_pk
    lo, hi = _bounds(params)
    x_full = np.array([p.to_x(min(max(fit.params[p.name], p.lower), p.upper)) for p in params])
    sq, count = 0.0, 0
    for held in heldout_masks(experiments):
        train = [~m for m in held]
        fn = _residual_fn(model, params, experiments, train, scale)
        res = _least_squares(fn, x_full, lo, hi, max_nfev)
        values = [p.from_x(x) for p, x in zip(params, res.x)]
        preds = model.predict(values, experiments)
        for pr, e, m in zip(preds, experiments, held):
            sq += float(np.sum((pr - e.response_signal)[m] ** 2))
            count += int(m.sum())
    return math.sqrt(sq / count)


def fit_candidate(fmu_path: str, effect: str, drive: str, experiments: Sequence,
                  max_starts: int = 6) -> Fit:
    """Calibrate one model and score it on held-out data (runs in a worker process)."""
    sc = data_scales(experiments)
    names = [p.name for p in model_parameters(effect, drive, sc)]
    model = ModelRunner(fmu_path, drive, names)
    try:
        fit = calibrate(model, effect, drive, experiments, sc, max_starts=max_starts)
        fit.heldout_rmse = heldout_rmse(model, fit, drive, experiments, sc)
    finally:
        model.close()
    return fit


# ---------------------------------------------------------------------- ranking

@dataclass(frozen=True)
class Thresholds:
    """What counts as a significant gain over the baseline. BIC's penalty keeps noise from winning;
    the held-out ratio demands that the gain carries over to data the fit did not see."""
    delta_bic: float = -10.0
    heldout_ratio: float = 0.9
    p_value: float = 1e-3
    tie_bic: float = 10.0
    tie_heldout: float = 1.1


def nested_p_value(base: Fit, ext: Fit) -> float:
    """F test of the extra parameters of a nested model (white-noise assumption)."""
    dk = ext.k - base.k
    dof = ext.n - ext.k
    if dk <= 0 or dof <= 0 or ext.rss <= 0:
        return 1.0
    F = max(base.rss - ext.rss, 0.0) / dk / (ext.rss / dof)
    return float(stats.f.sf(F, dk, dof))


def rank_candidates(base: Fit, fits: dict[str, Fit], th: Thresholds = Thresholds()) -> list[dict]:
    """Every candidate with its scores, best first: significant ones first, then by held-out error
    (prediction on unseen data separates look-alike families better than the in-sample BIC does)."""
    rows = []
    for name, f in fits.items():
        p = nested_p_value(base, f)
        h_ratio = f.heldout_rmse / base.heldout_rmse if base.heldout_rmse > 0 else float("nan")
        d_bic = f.bic - base.bic
        significant = bool(d_bic < th.delta_bic and h_ratio < th.heldout_ratio and p < th.p_value)
        rows.append({"effect": name, "significant": significant, "rmse": f.rmse,
                     "heldout_rmse": f.heldout_rmse, "rmse_ratio": f.rmse / base.rmse,
                     "heldout_rmse_ratio": h_ratio, "aic": f.aic, "bic": f.bic,
                     "delta_aic": f.aic - base.aic, "delta_bic": d_bic, "p_value": p, "k": f.k,
                     "params": dict(f.params)})
    rows.sort(key=lambda r: (not r["significant"], r["heldout_rmse"], r["bic"]))
    return rows


def choose_effect(ranking: list[dict], th: Thresholds = Thresholds()) -> tuple[str, list[str]]:
    """The winner (or none) and the significant candidates the data cannot tell from it."""
    sig = [r for r in ranking if r["significant"]]
    if not sig:
        return "none", []
    win = sig[0]
    ties = [r["effect"] for r in sig[1:]
            if r["heldout_rmse"] < th.tie_heldout * win["heldout_rmse"] and r["bic"] - win["bic"] < th.tie_bic]
    return win["effect"], ties


def separating_test(a: str, b: str) -> str:
    return SEPARATING_TESTS.get(frozenset({a, b}), "a test that loads, holds and unloads at several rates")


# ---------------------------------------------------------------------- what the protocol can show

# Features of a test protocol that separate look-alike effects, and the pairs each one separates.
PROTOCOL_FEATURES = {
    "unloading": (frozenset({"nonlinear_stiffness", "yield_softening"}),
                  frozenset({"coulomb_friction", "sensor_offset"}),
                  frozenset({"coulomb_friction", "yield_softening"})),
    "hold": (frozenset({"viscoelastic_relaxation", "coulomb_friction"}),),
    "several_rates_or_hold": (frozenset({"viscoelastic_relaxation", "nonlinear_stiffness"}),
                              frozenset({"viscoelastic_relaxation", "yield_softening"})),
}


def protocol_features(experiments: Sequence) -> dict:
    """What the tests did: unload after the peak, hold still, run at several rates."""
    unloading = hold = False
    rates = []
    for e in experiments:
        u = np.abs(np.asarray(e.drive_signal, float))
        pk = float(np.max(u))
        k = int(np.argmax(u))
        if pk > 0 and float(np.min(u[k:])) < 0.7 * pk:
            unloading = True
        du = np.abs(np.diff(e.drive_signal)) / np.diff(e.t)
        rate = float(np.median(du[du > 0.1 * np.max(du)])) if np.max(du) > 0 else 0.0
        rates.append(rate)
        still = du < 0.02 * np.max(du) if np.max(du) > 0 else np.ones_like(du, bool)
        if float(np.sum(np.diff(e.t)[still])) > 0.1 * float(e.t[-1] - e.t[0]):
            hold = True
    rates = [r for r in rates if r > 0]
    several = bool(rates) and max(rates) > 3.0 * min(rates)
    return {"unloading": unloading, "hold": hold, "several_rates": several,
            "several_rates_or_hold": several or hold}


def protocol_blind_spots(effect: str, features: dict) -> list[dict]:
    """The candidates this protocol cannot separate from ``effect``, whatever the scores say."""
    out = []
    for feat, pairs in PROTOCOL_FEATURES.items():
        if features.get(feat):
            continue
        for pair in pairs:
            if effect in pair:
                other = next(iter(pair - {effect}))
                out.append({"effect": other, "missing": feat, "separating_test": separating_test(effect, other)})
    return out


# ---------------------------------------------------------------------- the whole diagnosis

def _fit_job(args) -> Fit | str:
    """A candidate's fit, or the reason it failed (one bad candidate must not sink the others)."""
    try:
        return fit_candidate(*args)
    except Exception as exc:  # noqa: BLE001 - reported per candidate in diagnosis.json
        return f"{type(exc).__name__}: {exc}"


def data_key(experiments: Sequence, drive: str, max_starts: int, fmu: str) -> str:
    """Identity of a diagnosis input: cached fits are reused only for the same data, drive and FMU."""
    import hashlib

    h = hashlib.sha256()
    h.update(f"{drive}|{max_starts}|v1".encode())
    h.update(Path(fmu).read_bytes() if Path(fmu).is_file() else str(fmu).encode())
    for e in experiments:
        for a in (e.t, e.displacement, e.force):
            h.update(np.ascontiguousarray(a, dtype=float).tobytes())
    return h.hexdigest()[:16]


def _fit_to_json(f: Fit, key: str) -> dict:
    return {"key": key, "effect": f.effect, "params": f.params, "ci95": {k: list(v) for k, v in f.ci95.items()},
            "rss": f.rss, "n": f.n, "k": f.k, "rmse": f.rmse, "heldout_rmse": f.heldout_rmse,
            "predictions": [p.tolist() for p in f.predictions], "starts_tried": f.starts_tried, "nfev": f.nfev}


def _fit_from_json(d: dict) -> Fit:
    return Fit(effect=d["effect"], params=d["params"], ci95={k: tuple(v) for k, v in d["ci95"].items()},
               rss=d["rss"], n=d["n"], k=d["k"], rmse=d["rmse"], heldout_rmse=d["heldout_rmse"],
               predictions=[np.array(p) for p in d["predictions"]], starts_tried=d["starts_tried"],
               nfev=d["nfev"])


def _run_fits(jobs: list, workers: int, cache_dir: Path | None, key: str, progress: bool) -> dict:
    """Every job's fit, taken from the cache when it is there, and saved as soon as it is done."""
    import json

    results: dict[str, Fit | str] = {}
    todo = []
    for job in jobs:
        path = cache_dir / f"{job[1]}.json" if cache_dir else None
        if path is not None and path.exists():
            try:
                d = json.loads(path.read_text())
                if d.get("key") == key:
                    results[job[1]] = _fit_from_json(d)
                    continue
            except (ValueError, KeyError):
                pass
        todo.append(job)

    def keep(name: str, r) -> None:
        results[name] = r
        if cache_dir is not None and isinstance(r, Fit):
            cache_dir.mkdir(parents=True, exist_ok=True)
            tmp = cache_dir / f"{name}.json.tmp"
            tmp.write_text(json.dumps(_fit_to_json(r, key)))
            tmp.replace(cache_dir / f"{name}.json")
        if progress:
            what = f"rmse {r.rmse:.4g}, held-out {r.heldout_rmse:.4g}" if isinstance(r, Fit) else f"failed: {r}"
            print(f"  fitted {name}: {what}", flush=True)

    if workers > 1 and len(todo) > 1:
        import multiprocessing as mp
        from concurrent.futures import as_completed

        with ProcessPoolExecutor(min(workers, len(todo)), mp_context=mp.get_context("spawn")) as ex:
            futs = {ex.submit(_fit_job, j): j[1] for j in todo}
            for fut in as_completed(futs):
                try:
                    r = fut.result()
                except Exception as exc:  # a worker that died (e.g. the FMU crashed the process)
                    r = f"{type(exc).__name__}: {exc}"
                keep(futs[fut], r)
    else:
        for j in todo:
            keep(j[1], _fit_job(j))
    return results


def diagnose(experiments: Sequence, drive: str, fmu_path: str | os.PathLike | None = None,
             candidates: Sequence[str] = CANDIDATES, workers: int | None = None,
             max_starts: int = 6, thresholds: Thresholds = Thresholds(), progress: bool = False,
             cache_dir: str | os.PathLike | None = None) -> dict:
    """Calibrate the baseline and every candidate, rank them, and describe what is left.

    Returns a dict with the keys of diagnosis.json plus the fits (``_fits``) for the figures. With
    ``cache_dir`` each fit is saved as it completes and reused by a rerun on the same data, so an
    interrupted diagnosis loses nothing already computed."""
    from fmusa.fmi.info import default_fmu_path
    from fmusa.diagnose import residuals as rs

    if drive not in FMU_SETTINGS:
        raise DiagnoseError(f"--drive {drive!r}: use 'force' or 'displacement'")
    for c in candidates:
        if c not in CANDIDATES:
            raise DiagnoseError(f"unknown candidate {c!r}; use any of {', '.join(CANDIDATES)}")
    if not experiments:
        raise DiagnoseError("no experiments given")
    fmu = str(fmu_path or default_fmu_path())
    sc = data_scales(experiments)
    if not Path(fmu).exists():
        raise DiagnoseError(f"FMU not found: {fmu}; build it with `make fmu` or pass --fmu")
    jobs = [(fmu, name, drive, list(experiments), max_starts) for name in ("none", *candidates)]
    workers = workers or min(len(jobs), os.cpu_count() or 1)
    key = data_key(experiments, drive, max_starts, fmu)
    results = _run_fits(jobs, workers, Path(cache_dir) if cache_dir else None, key, progress)
    base = results["none"]
    if not isinstance(base, Fit):
        raise RuntimeError(f"the baseline could not be fitted: {base}")
    fits = {n: r for n, r in results.items() if n != "none" and isinstance(r, Fit)}
    failed = {n: r for n, r in results.items() if not isinstance(r, Fit)}
    ranking = rank_candidates(base, fits, thresholds)
    effect, ties = choose_effect(ranking, thresholds)
    ext = fits[effect] if effect != "none" else base
    segments, offset = [], 0
    for e in experiments:
        segments.append(np.arange(offset, offset + len(e.t)))
        offset += len(e.t)
    t_all = np.concatenate([e.t for e in experiments])

    def structure(fit: Fit) -> dict:
        r = np.concatenate([pr - e.response_signal for pr, e in zip(fit.predictions, experiments)])
        return rs.residual_structure(t_all, r, segments=segments, unit="N" if drive == "displacement" else "m")

    res_base, res_ext = structure(base), structure(ext)
    features = protocol_features(experiments)
    indist = [{"effect": t, "reason": "scores within the tie margins",
               "separating_test": separating_test(effect, t)} for t in ties]
    if effect != "none":
        significant = {r["effect"] for r in ranking if r["significant"]}
        for b in protocol_blind_spots(effect, features):
            # only a look-alike that explains the data too: one that fails here was told apart after all
            if b["effect"] not in ties and b["effect"] in significant:
                indist.append({"effect": b["effect"],
                               "reason": f"the tests have no {b['missing'].replace('_', ' ')}",
                               "separating_test": b["separating_test"]})
    main = main_parameter(effect, drive) if effect != "none" else None
    eff_names = [p.name for p in model_parameters(effect, drive, sc)][2:] if effect != "none" else []
    out = {
        "effect": effect,
        "main_parameter": main,
        "effect_params": {n: {"value": ext.params[n], "ci95": list(ext.ci95[n]), "unit": UNITS.get(n, "")}
                          for n in eff_names},
        "baseline": _fit_summary(base),
        "extended": _fit_summary(ext),
        "gain": {"rmse_ratio": ext.rmse / base.rmse,
                 "heldout_rmse_ratio": ext.heldout_rmse / base.heldout_rmse,
                 "delta_aic": ext.aic - base.aic, "delta_bic": ext.bic - base.bic,
                 "p_value": nested_p_value(base, ext) if effect != "none" else 1.0},
        "ranking": ranking,
        "failed": failed,
        "indistinguishable": indist,
        "protocol": features,
        "residuals": {"baseline": res_base, "extended": res_ext},
        "leftover": res_ext.get("description", "") if res_ext.get("structured") else "",
        "data": {"drive": drive, "response": "force" if drive == "displacement" else "displacement",
                 "experiments": [{"name": e.name, "points": len(e.t), "duration_s": float(e.t[-1] - e.t[0])}
                                 for e in experiments],
                 "points": int(sum(len(e.t) for e in experiments)),
                 "heldout": "whole experiments (leave one out)" if len(experiments) > 1
                            else "4 contiguous blocks in time (leave one out)"},
        "thresholds": {"delta_bic": thresholds.delta_bic, "heldout_ratio": thresholds.heldout_ratio,
                       "p_value": thresholds.p_value, "tie_bic": thresholds.tie_bic,
                       "tie_heldout": thresholds.tie_heldout},
        "_fits": {"none": base, **fits},
    }
    return out


def _fit_summary(f: Fit) -> dict:
    return {"params": dict(f.params), "ci95": {k: list(v) for k, v in f.ci95.items()},
            "units": {k: UNITS.get(k, "") for k in f.params}, "rmse": f.rmse, "heldout_rmse": f.heldout_rmse,
            "aic": f.aic, "bic": f.bic, "k": f.k, "n": f.n}


def write_json(diag: dict, path: str | os.PathLike) -> None:
    """diagnosis.json: everything but the in-memory fits."""
    import json

    def clean(x):
        if isinstance(x, dict):
            return {k: clean(v) for k, v in x.items() if not k.startswith("_")}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        if isinstance(x, (np.floating, float)):
            return float(x) if math.isfinite(x) else None
        if isinstance(x, (np.integer,)):
            return int(x)
        if isinstance(x, np.bool_):
            return bool(x)
        return x
    Path(path).write_text(json.dumps(clean(diag), indent=2))


def run_diagnosis(experiments: Sequence, drive: str, out_dir: str | os.PathLike, **kw) -> dict:
    """diagnose, then DIR/diagnosis.json, DIR/figures/ and DIR/report.md; fits are cached in DIR/fits."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    diag = diagnose(experiments, drive, cache_dir=out / "fits", progress=kw.pop("progress", True), **kw)
    write_json(diag, out / "diagnosis.json")
    try:
        from fmusa.diagnose import report as diagnose_report
    except ImportError:  # pragma: no cover - the report module is part of the package
        return diag
    figs = diagnose_report.write_figures(diag, experiments, out)
    diagnose_report.write_report(diag, experiments, out, figs)
    return diag
