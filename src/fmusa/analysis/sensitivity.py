"""Global sensitivity indices from samples (SALib): the problem, the samples, Morris and Sobol analyses.

Arrays in, arrays and tables out: the runs themselves are made by :mod:`fmusa.pipeline.sensitivity`. A
``loguniform`` parameter is sampled uniformly in log10 space (SALib sees log10 values, the FMU the
physical ones).
"""
from __future__ import annotations

import math
import warnings

import numpy as np

#: Levels of the Morris grid.
MORRIS_LEVELS = 4


def salib_problem(stage) -> dict:
    """The SALib problem of ``stage``: bounds in the sampled space (log10 for ``loguniform``)."""
    names, bounds = [], []
    for p in stage.parameters.values():
        lo, hi = map(float, p.bounds)
        if p.distribution == "loguniform":
            lo, hi = math.log10(lo), math.log10(hi)
        names.append(p.name)
        bounds.append([lo, hi])
    return {"num_vars": len(names), "names": names, "bounds": bounds}


def to_physical(stage, X: np.ndarray) -> np.ndarray:
    """Sampled-space values (rows of SALib's X) → the physical values the FMU gets."""
    X = np.asarray(X, dtype=float)
    out = X.copy()
    for j, p in enumerate(stage.parameters.values()):
        if p.distribution == "loguniform":
            out[:, j] = np.power(10.0, X[:, j])
            lo, hi = map(float, p.bounds)
            out[:, j] = np.clip(out[:, j], lo, hi)   # 10**log10(hi) may be hi·(1 + 1 ulp)
    return out


def draw_samples(stage, method: str, problem: dict | None = None, n: int | None = None) -> np.ndarray:
    """SALib's sample (sampled space) for ``method``: Morris trajectories or the Sobol sample
    (``calc_second_order=False``, N·(k + 2) rows). ``n`` overrides ``stage.n`` /
    ``stage.morris_trajectories``."""
    problem = problem or salib_problem(stage)
    if method == "morris":
        from SALib.sample import morris as morris_sample
        return morris_sample.sample(problem, int(n or stage.morris_trajectories), num_levels=MORRIS_LEVELS,
                                    seed=stage.seed)
    if method == "sobol":
        from SALib.sample import sobol as sobol_sample
        with warnings.catch_warnings():   # N not a power of 2: SALib warns, the sample is still valid
            warnings.filterwarnings("ignore", message=".*Convergence properties of the Sobol.*")
            warnings.filterwarnings("ignore", message=".*balance properties of Sobol.*")
            return sobol_sample.sample(problem, int(n or stage.n), calc_second_order=False, seed=stage.seed)
    raise ValueError(f"unknown sensitivity method {method!r}; use morris or sobol")


def _nan_to_none(x):
    x = float(x)
    return x if math.isfinite(x) else None


def analyse_morris(problem, X, Y, metric_names, seed):
    from SALib.analyze import morris as morris_analyze
    out, rows = {}, []
    for j, metric in enumerate(metric_names):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            res = morris_analyze.analyze(problem, X, Y[:, j], num_levels=MORRIS_LEVELS, seed=seed)
        out[metric] = {}
        for i, name in enumerate(problem["names"]):
            d = {"mu_star": _nan_to_none(res["mu_star"][i]), "sigma": _nan_to_none(res["sigma"][i]),
                 "mu_star_conf": _nan_to_none(res["mu_star_conf"][i]), "mu": _nan_to_none(res["mu"][i])}
            out[metric][name] = d
            rows.append({"metric": metric, "parameter": name, **d})
    return out, rows


def analyse_sobol(problem, Y, metric_names, seed):
    from SALib.analyze import sobol as sobol_analyze
    out, rows = {}, []
    for j, metric in enumerate(metric_names):
        y = Y[:, j]
        if not np.ptp(y) > 0:
            # a constant output: no variance to apportion (SALib would divide by zero)
            res = {k: np.zeros(problem["num_vars"]) for k in ("S1", "S1_conf", "ST", "ST_conf")}
        else:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                res = sobol_analyze.analyze(problem, y, calc_second_order=False, seed=seed)
        out[metric] = {}
        for i, name in enumerate(problem["names"]):
            d = {k: _nan_to_none(res[k][i]) for k in ("S1", "S1_conf", "ST", "ST_conf")}
            out[metric][name] = d
            rows.append({"metric": metric, "parameter": name, **d})
    return out, rows

