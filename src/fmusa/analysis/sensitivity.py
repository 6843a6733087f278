"""Global sensitivity indices from samples (SALib): the problem, the samples, Morris and Sobol analyses.

Arrays in, arrays and tables out: the runs themselves are made by :mod:`fmusa.pipeline.sensitivity`. A
``loguniform`` parameter is sampled uniformly in log10 space (SALib sees log10 values, the FMU the
physical ones).
"""
from __future__ import annotations

import math
import warnings

import numpy as np
from typing import Mapping

#: Levels of the Morris grid.
MORRIS_LEVELS = 4


def _quantile_space(p) -> bool:
    """SALib samples this input as a quantile in [0, 1] (its distribution's inverse CDF gives the value)."""
    return p.distribution not in ("uniform", "loguniform")


def salib_problem(stage) -> dict:
    """The SALib problem of ``stage``: bounds in the sampled space (log10 for ``loguniform``, the quantile
    [0, 1] for ``normal``, ``truncnormal`` and ``lognormal``)."""
    names, bounds = [], []
    for p in stage.parameters.values():
        if _quantile_space(p):
            lo, hi = 0.0, 1.0
        else:
            lo, hi = map(float, p.bounds)
            if p.distribution == "loguniform":
                lo, hi = math.log10(lo), math.log10(hi)
        names.append(p.name)
        bounds.append([lo, hi])
    return {"num_vars": len(names), "names": names, "bounds": bounds}


def sampled_marginal(p) -> tuple[str, tuple[float, ...]]:
    """The distribution of one input in its sampled space, where the polynomial chaos is fitted:
    ``uniform`` (lo, hi) for uniform and (log10 lo, log10 hi) for log-uniform inputs, ``normal`` (mean,
    std) for normal inputs and (mean, std) of ln x for log-normal ones, ``truncnormal`` (mean, std, lo,
    hi)."""
    if p.distribution == "uniform":
        return "uniform", tuple(map(float, p.bounds))
    if p.distribution == "loguniform":
        return "uniform", tuple(math.log10(float(b)) for b in p.bounds)
    if p.distribution == "normal":
        return "normal", (float(p.mean), float(p.std))
    if p.distribution == "truncnormal":
        return "truncnormal", (float(p.mean), float(p.std), *map(float, p.bounds))
    if p.distribution == "lognormal":
        s2 = math.log1p((float(p.std) / float(p.mean)) ** 2)
        return "normal", (math.log(float(p.mean)) - s2 / 2, math.sqrt(s2))
    raise ValueError(f"unknown distribution {p.distribution!r}")


def sampled_marginals(stage) -> list[tuple[str, tuple[float, ...]]]:
    return [sampled_marginal(p) for p in stage.parameters.values()]


def physical_from_sampled(stage, Z: np.ndarray) -> np.ndarray:
    """Sampled-space values (see :func:`sampled_marginal`) → the physical values the FMU gets."""
    Z = np.asarray(Z, dtype=float)
    out = Z.copy()
    for j, p in enumerate(stage.parameters.values()):
        if p.distribution == "loguniform":
            lo, hi = map(float, p.bounds)
            out[:, j] = np.clip(np.power(10.0, Z[:, j]), lo, hi)   # 10**log10(hi) may be hi·(1 + 1 ulp)
        elif p.distribution == "lognormal":
            out[:, j] = np.exp(Z[:, j])
    return out


def to_physical(stage, X: np.ndarray, method: str = "sobol") -> np.ndarray:
    """Sampled-space values (rows of SALib's X) → the physical values the FMU gets. A quantile-space input
    goes through its inverse CDF; for Morris its levels are the quantiles (i + ½)/levels (the grid's ends
    would be the distribution's infinite tails)."""
    from fmusa.analysis.pce import sampled_from_unit
    X = np.asarray(X, dtype=float)
    Z = X.copy()
    for j, p in enumerate(stage.parameters.values()):
        if _quantile_space(p):
            q = X[:, j]
            if method == "morris":
                q = (q * (MORRIS_LEVELS - 1) + 0.5) / MORRIS_LEVELS
            Z[:, j] = sampled_from_unit(q.reshape(-1, 1), [sampled_marginal(p)])[:, 0]
    return physical_from_sampled(stage, Z)


def check_sample_size(stage, method: str, n: int | None = None) -> list[str]:
    """Refuse (UsageError) a sample over the cap before anything is allocated; the notes for a sample
    the study file would have refused (the Python API lets it through): below the smallest useful size,
    or a Saltelli n that is not a power of 2."""
    from fmusa.errors import UsageError
    from fmusa.study.schema import (ENV_MAX_SENSITIVITY_RUNS, max_sensitivity_runs, nearest_powers_of_two,
                                    smallest_sobol_n)
    k = len(stage.parameters)
    cap = max_sensitivity_runs()
    notes = []
    if method == "sobol":
        n = int(n or stage.n)
        runs = n * (k + 2)
        if n < 1 or runs > cap:
            raise UsageError(f"sensitivity n = {n} asks for n·(k + 2) = {runs:,} Sobol runs with {k} inputs; the "
                             f"cap is {cap:,} runs ({ENV_MAX_SENSITIVITY_RUNS} raises it); lower n or use "
                             f"method pce")
        least = smallest_sobol_n(k)
        if n < least:
            notes.append(f"sobol: n = {n} is below the smallest useful n for {k} inputs ({least}): the "
                         f"indices are not resolved at this n")
        lo, hi = nearest_powers_of_two(n)
        if lo != n:
            notes.append(f"sobol: n = {n} is not a power of 2, so Saltelli's sample (a Sobol sequence) loses "
                         f"its balance and convergence properties; n = {lo} or {hi} would keep them")
    elif method == "morris":
        r = int(n or stage.morris_trajectories)
        if r < 1 or r * (k + 1) > cap:
            raise UsageError(f"sensitivity morris_trajectories = {r} asks for {r * (k + 1):,} runs; the cap is "
                             f"{cap:,} runs ({ENV_MAX_SENSITIVITY_RUNS} raises it)")
    elif method == "pce":
        if stage.pce.max_runs > cap:
            raise UsageError(f"sensitivity pce.max_runs = {stage.pce.max_runs:,} is over the cap of {cap:,} "
                             f"runs ({ENV_MAX_SENSITIVITY_RUNS} raises it)")
    return notes


def draw_samples(stage, method: str, problem: dict | None = None, n: int | None = None,
                 messages: list[str] | None = None) -> np.ndarray:
    """SALib's sample (sampled space) for ``method``: Morris trajectories or the Sobol sample
    (``calc_second_order=False``, N·(k + 2) rows). ``n`` overrides ``stage.n`` /
    ``stage.morris_trajectories``. SALib's warnings become lines of ``messages`` (the study's own notes),
    not Python warnings."""
    problem = problem or salib_problem(stage)
    notes = check_sample_size(stage, method, n)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if method == "morris":
            from SALib.sample import morris as morris_sample
            X = morris_sample.sample(problem, int(n or stage.morris_trajectories), num_levels=MORRIS_LEVELS,
                                     seed=stage.seed)
        elif method == "sobol":
            from SALib.sample import sobol as sobol_sample
            X = sobol_sample.sample(problem, int(n or stage.n), calc_second_order=False, seed=stage.seed)
        else:
            raise ValueError(f"unknown sensitivity method {method!r}; use morris or sobol")
    if messages is not None:
        messages.extend(notes)
        for w in caught:
            text = " ".join(str(w.message).split())
            if "power of 2" in text or "balance properties" in text or "Convergence properties" in text:
                continue    # said by check_sample_size in the study's words
            messages.append(f"{method}: SALib: {text}")
    return X


def _nan_to_none(x):
    x = float(x)
    return x if math.isfinite(x) else None


def _salib_notes(caught, where: str, notes: list[str] | None) -> None:
    """SALib's warnings as the study's notes (one line each, no source path)."""
    if notes is None:
        return
    for w in caught:
        text = " ".join(str(w.message).split())
        line = f"{where}: SALib: {text}"
        if line not in notes:
            notes.append(line)


def analyse_morris(problem, X, Y, metric_names, seed, notes: list[str] | None = None):
    """SALib's Morris analysis of every metric (a column of ``Y``); SALib's warnings go to ``notes``."""
    from SALib.analyze import morris as morris_analyze
    out, rows = {}, []
    for j, metric in enumerate(metric_names):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            res = morris_analyze.analyze(problem, X, Y[:, j], num_levels=MORRIS_LEVELS, seed=seed)
        _salib_notes(caught, f"morris: {metric}", notes)
        out[metric] = {}
        for i, name in enumerate(problem["names"]):
            d = {"mu_star": _nan_to_none(res["mu_star"][i]), "sigma": _nan_to_none(res["sigma"][i]),
                 "mu_star_conf": _nan_to_none(res["mu_star_conf"][i]), "mu": _nan_to_none(res["mu"][i])}
            out[metric][name] = d
            rows.append({"metric": metric, "parameter": name, **d})
    return out, rows


def analyse_sobol(problem, Y, metric_names, seed, notes: list[str] | None = None):
    """SALib's Sobol analysis of every metric (a column of ``Y``); an index outside [0, 1] beyond its
    interval is not reported (None), and said in ``notes``."""
    from SALib.analyze import sobol as sobol_analyze
    out, rows = {}, []
    for j, metric in enumerate(metric_names):
        y = Y[:, j]
        if not np.ptp(y) > 0:
            # a constant output: no variance to apportion (SALib would divide by zero)
            res = {k: np.zeros(problem["num_vars"]) for k in ("S1", "S1_conf", "ST", "ST_conf")}
        else:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                res = sobol_analyze.analyze(problem, y, calc_second_order=False, seed=seed)
            _salib_notes(caught, f"sobol: {metric}", notes)
        out[metric] = {}
        for i, name in enumerate(problem["names"]):
            d = {k: _nan_to_none(res[k][i]) for k in ("S1", "S1_conf", "ST", "ST_conf")}
            bad = impossible_indices({name: d})
            if bad:     # no index is outside [0, 1]: not a number to print
                if notes is not None:
                    notes.extend(f"sobol: {metric}: {b}" for b in bad)
                for k in ("S1", "ST"):
                    if impossible_indices({name: {k: d[k], f"{k}_conf": d[f"{k}_conf"]}}):
                        d[k] = d[f"{k}_conf"] = None
            out[metric][name] = d
            rows.append({"metric": metric, "parameter": name, **d})
    return out, rows



# ---------------------------------------------------------------------------- what the indices do not know
#: Inputs below this share of the largest index are left out of the statements on the order.
ORDER_FLOOR = 0.05
#: How many of the largest indices the statements on the order look at.
ORDER_TOP = 5


def index_intervals(method: str, table: Mapping) -> dict[str, tuple[float, float, float]]:
    """{parameter: (value, lo, hi)} of the index a method ranks by: Morris μ* ± its 95 % half-width, Sobol
    ST ± its half-width, pce ST with its bootstrap interval. Parameters without a value are left out."""
    out = {}
    for name, d in table.items():
        if method == "morris":
            v, h = d.get("mu_star"), d.get("mu_star_conf") or 0.0
            if v is not None:
                out[name] = (v, v - h, v + h)
        elif method == "sobol":
            v, h = d.get("ST"), d.get("ST_conf") or 0.0
            if v is not None:
                out[name] = (v, v - h, v + h)
        elif d.get("ST") is not None:
            out[name] = (d["ST"], d.get("ST_lo", d["ST"]), d.get("ST_hi", d["ST"]))
    return out


def ranked(method: str, table: Mapping) -> list[tuple[str, float, float, float]]:
    """The inputs that matter, largest index first: (name, value, lo, hi) of the ORDER_TOP largest with a
    value of at least ORDER_FLOOR × the largest."""
    iv = index_intervals(method, table)
    if not iv:
        return []
    top = max(v for v, _, _ in iv.values())
    rows = sorted(((n, *t) for n, t in iv.items()), key=lambda r: -r[1])
    return [r for r in rows if top > 0 and r[1] >= ORDER_FLOOR * top][:ORDER_TOP]


def unresolved_orders(method: str, table: Mapping, size_text: str) -> list[str]:
    """"the order of A and B is not resolved at this n" for every two neighbours in the ranking whose
    intervals overlap."""
    rows = ranked(method, table)
    index = {"morris": "μ*", "sobol": "ST", "pce": "ST"}[method]
    out = []
    for (a, va, la, ha), (b, vb, lb, hb) in zip(rows, rows[1:]):
        if la <= hb:
            out.append(f"the order of {a} and {b} is not resolved at {size_text} ({index} {va:.3g} "
                       f"[{la:.3g}, {ha:.3g}] and {vb:.3g} [{lb:.3g}, {hb:.3g}] overlap)")
    return out


def ranking_disagreements(morris: Mapping, other: Mapping, other_method: str) -> list[str]:
    """Where Morris (μ*) and a variance-based method (ST) put two of the inputs that matter in opposite
    order, saying whether each order is resolved by its intervals."""
    mi = index_intervals("morris", morris)
    oi = index_intervals(other_method, other)
    names = [r[0] for r in ranked("morris", morris)[:3]] + [r[0] for r in ranked(other_method, other)[:3]]
    names = [n for n in dict.fromkeys(names) if n in mi and n in oi]
    label = {"sobol": "Sobol (ST)", "pce": "the polynomial chaos (ST)"}[other_method]
    out = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            dm = mi[a][0] - mi[b][0]
            do = oi[a][0] - oi[b][0]
            if dm * do >= 0:
                continue
            first, second = (a, b) if dm > 0 else (b, a)
            sure_m = mi[first][1] > mi[second][2]
            sure_o = oi[second][1] > oi[first][2]
            how = ("both orders are resolved by their intervals" if sure_m and sure_o else
                   "within their intervals (not resolved)" if not (sure_m or sure_o) else
                   f"resolved by {'Morris' if sure_m else label}'s intervals only")
            out.append(f"Morris ranks {first} above {second} (μ*), {label} ranks {second} above {first}: "
                       f"{how}. Morris measures mean effects along one-at-a-time steps, ST shares of variance; "
                       f"they may rank differently when an input acts through interactions or a small part "
                       f"of its range")
    return out


def impossible_indices(table: Mapping) -> list[str]:
    """Sobol indices outside [0, 1] beyond their interval: an estimate with no meaning (a sample too
    small, or an output dominated by noise)."""
    out = []
    for name, d in table.items():
        for k in ("S1", "ST"):
            v, h = d.get(k), d.get(f"{k}_conf") or 0.0
            if v is not None and not (-h - 1e-9 <= v <= 1 + h + 1e-9):
                out.append(f"{k} of {name} = {v:.3g} ± {h:.2g} is outside [0, 1]: no index is; not reported")
    return out
