"""Sobol indices from a sparse polynomial chaos expansion (OpenTURNS), for FMUs whose runs are expensive.

Arrays in, arrays and dicts out: the runs themselves are made by :mod:`fmusa.pipeline.sensitivity`.

The expansion is fitted in the *sampled space* of every input (log10 of a log-uniform input, ln of a
log-normal one, the value itself otherwise; Sobol indices do not change under a one-to-one transform of one
input), on a design drawn from the unit cube (a scrambled Sobol sequence, or one Latin hypercube per batch)
and mapped through each input's quantile function:

1. the candidate basis: OpenTURNS' orthonormal polynomials of each input's distribution (Legendre for a
   uniform one, Hermite for a normal one, Stieltjes for a truncated normal one) under a hyperbolic
   truncation (q = 0.5: few interactions of high degree);
2. the sparse basis: LARS, the step chosen by the corrected leave-one-out error, for every total degree
   from 1 up, keeping the degree with the smallest error (stopping when two degrees in a row do worse);
3. the validation error: the relative leave-one-out error of the final least-squares fit on the selected
   basis, multiplied by the correction for its size (Chapelle et al.; Blatman and Sudret 2011), so that a
   basis nearly as large as the design is not believed;
4. S1 and ST from the coefficients (orthonormal basis: each term's variance is its coefficient squared);
5. intervals: the design resampled with replacement and the coefficients of the selected basis fitted
   again (the bootstrap of Marelli and Sudret's bootstrap PCE); the 2.5 and 97.5 percentiles.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np

__all__ = ["PCEFit", "fit_pce", "pce_indices", "unit_design", "sampled_from_unit", "ot_marginal",
           "bootstrap_indices", "TRUNCATION_Q"]

#: Hyperbolic truncation of the candidate basis (1 = total degree; smaller keeps fewer interactions).
TRUNCATION_Q = 0.5
#: Degrees tried past the best one before the search stops.
PATIENCE = 4
#: Largest candidate basis tried (terms): beyond it LARS costs more than the runs it saves.
MAX_CANDIDATES = 1000


@dataclass
class PCEFit:
    """A fitted sparse expansion of one output: its selected terms (multi-indices), coefficients, the
    design matrix of those terms at the design points, the validation error and the degree."""
    multi_indices: np.ndarray        # terms × inputs, degrees of each input in each term
    coefficients: np.ndarray         # terms
    psi: np.ndarray                  # design points × terms
    loo_error: float                 # relative leave-one-out error, corrected for the basis size
    degree: int
    candidates: int                  # size of the candidate basis at that degree
    mean: float
    variance: float
    loo_predictions: np.ndarray      # design points: the prediction of each point by the fit without it


# ---------------------------------------------------------------------------- distributions and design
def ot_marginal(kind: str, args: Sequence[float]):
    """The OpenTURNS distribution of one input in its sampled space: ``uniform`` (lo, hi), ``normal``
    (mean, std), ``truncnormal`` (mean, std, lo, hi)."""
    import openturns as ot
    if kind == "uniform":
        return ot.Uniform(float(args[0]), float(args[1]))
    if kind == "normal":
        return ot.Normal(float(args[0]), float(args[1]))
    if kind == "truncnormal":
        return ot.TruncatedNormal(float(args[0]), float(args[1]), float(args[2]), float(args[3]))
    raise ValueError(f"unknown sampled-space distribution {kind!r}")


def sampled_from_unit(U: np.ndarray, marginals: Sequence[tuple[str, Sequence[float]]]) -> np.ndarray:
    """Points of the unit cube → the sampled space, through each input's quantile function."""
    from scipy import stats
    U = np.clip(np.asarray(U, dtype=float), 1e-12, 1 - 1e-12)
    Z = np.empty_like(U)
    for j, (kind, a) in enumerate(marginals):
        if kind == "uniform":
            Z[:, j] = a[0] + U[:, j] * (a[1] - a[0])
        elif kind == "normal":
            Z[:, j] = stats.norm.ppf(U[:, j], loc=a[0], scale=a[1])
        elif kind == "truncnormal":
            lo, hi = (a[2] - a[0]) / a[1], (a[3] - a[0]) / a[1]
            Z[:, j] = np.clip(stats.truncnorm.ppf(U[:, j], lo, hi, loc=a[0], scale=a[1]), a[2], a[3])
        else:
            raise ValueError(f"unknown sampled-space distribution {kind!r}")
    return Z


def unit_design(n: int, dim: int, design: str, seed: int, batch: int) -> np.ndarray:
    """The first ``n`` points of the experimental design in the unit cube, the same for the same arguments
    (a resumed study draws them again): a scrambled Sobol sequence (extensible: every batch continues
    it), or one Latin hypercube of ``batch`` points per batch (each batch its own seed)."""
    from scipy.stats import qmc
    if n <= 0:
        return np.empty((0, dim))
    if design == "sobol":
        with warnings.catch_warnings():   # balance holds at powers of two only; the design needs none
            warnings.simplefilter("ignore", UserWarning)
            return qmc.Sobol(dim, scramble=True, seed=seed).random(n)
    if design == "lhs":
        parts, done, b = [], 0, 0
        while done < n:
            size = batch
            parts.append(qmc.LatinHypercube(dim, seed=np.random.default_rng([seed, b])).random(size))
            done += size
            b += 1
        return np.concatenate(parts)[:n]
    raise ValueError(f"unknown design {design!r}; use sobol or lhs")


# ---------------------------------------------------------------------------- the fit
def _basis(marginals):
    import openturns as ot
    dists = [ot_marginal(k, a) for k, a in marginals]
    dim = len(dists)
    enum = ot.HyperbolicAnisotropicEnumerateFunction(dim, TRUNCATION_Q)
    factories = [ot.StandardDistributionPolynomialFactory(d) for d in dists]
    basis = ot.OrthogonalProductPolynomialFactory(factories, enum)
    joint = (ot.JointDistribution if hasattr(ot, "JointDistribution") else ot.ComposedDistribution)(dists)
    return basis, enum, joint


def _loo(psi: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """Least-squares coefficients on ``psi``, the relative leave-one-out error corrected for the basis
    size, T(P, N) = N / (N − P) · (1 + tr((ΨᵀΨ/N)⁻¹) / N), and the leave-one-out predictions; the error is
    inf when the basis is not smaller than the design or is singular."""
    n, p = psi.shape
    var = float(np.var(y))
    coef, *_ = np.linalg.lstsq(psi, y, rcond=None)
    fitted = psi @ coef
    if p >= n or var <= 0:
        return coef, (0.0 if var <= 0 and p < n else math.inf), fitted
    G = psi.T @ psi
    try:
        Ginv = np.linalg.inv(G)
    except np.linalg.LinAlgError:
        return coef, math.inf, fitted
    h = np.einsum("ij,jk,ik->i", psi, Ginv, psi)
    if np.any(h >= 1 - 1e-10):
        return coef, math.inf, fitted
    r = (y - fitted) / (1 - h)
    t = n / (n - p) * (1 + np.trace(Ginv * n) / n)
    return coef, float(np.mean(r ** 2) / var * t), y - r


def _fit_degree(X, y, marginals, degree, basis, enum, joint):
    import openturns as ot
    size = int(enum.getBasisSizeFromTotalDegree(degree)) if hasattr(enum, "getBasisSizeFromTotalDegree") \
        else int(enum.getStrataCumulatedCardinal(degree))
    if size > MAX_CANDIDATES:
        return None, size
    strategy = ot.FixedStrategy(basis, size)
    selection = ot.LeastSquaresMetaModelSelectionFactory(ot.LARS(), ot.CorrectedLeaveOneOut())
    projection = ot.LeastSquaresStrategy(selection)
    algo = ot.FunctionalChaosAlgorithm(ot.Sample(X), ot.Sample(y.reshape(-1, 1)), joint, strategy, projection)
    algo.run()
    res = algo.getResult()
    idx = list(res.getIndices())
    funcs = res.getReducedBasis()
    transform = res.getTransformation()
    Zs = transform(ot.Sample(X))
    psi = np.column_stack([np.asarray(funcs[j](Zs)).ravel() for j in range(len(idx))])
    mi = np.array([list(enum(i)) for i in idx], dtype=int).reshape(len(idx), len(marginals))
    coef, err, pred = _loo(psi, y)
    var = float(np.sum(coef[mi.sum(axis=1) > 0] ** 2))
    mean = float(coef[mi.sum(axis=1) == 0].sum())
    return PCEFit(mi, coef, psi, err, degree, size, mean, var, pred), size


def fit_pce(X: np.ndarray, y: np.ndarray, marginals: Sequence[tuple[str, Sequence[float]]],
            max_degree: int = 20, good_enough: float = 0.0, start_degree: int = 1,
            patience: int = PATIENCE) -> PCEFit:
    """The sparse expansion of ``y`` over the design ``X`` (sampled space), degree chosen by its
    validation error (see the module's docstring); the degrees stop rising once the error is below
    ``good_enough`` (a tenth of the study's target: higher degrees cost time and change no index).
    ``start_degree``: the lowest degree tried (a grown design starts near the degree of the last round)."""
    X = np.asarray(X, dtype=float)
    y = np.asarray(y, dtype=float)
    basis, enum, joint = _basis(marginals)
    best, worse = None, 0
    for degree in range(max(1, min(start_degree, max_degree)), max_degree + 1):
        fit, size = _fit_degree(X, y, marginals, degree, basis, enum, joint)
        if fit is None:
            break
        if best is None or fit.loo_error < best.loo_error:
            best, worse = fit, 0
        else:
            worse += 1
            if worse >= patience:
                break
        if best.loo_error <= good_enough:
            break
    if best is None:   # pragma: no cover - degree 1 of any dimension fits under MAX_CANDIDATES
        raise ValueError("no expansion could be fitted")
    return best


# ---------------------------------------------------------------------------- indices
def pce_indices(multi_indices: np.ndarray, coefficients: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(S1, ST) per input from an orthonormal expansion: the variance of the terms in that input alone,
    and of all terms that contain it, over the variance of all non-constant terms. Zeros for a constant."""
    mi = np.asarray(multi_indices)
    c2 = np.asarray(coefficients, dtype=float) ** 2
    active = mi > 0
    nonconst = active.any(axis=1)
    var = float(c2[nonconst].sum())
    k = mi.shape[1]
    if var <= 0:
        return np.zeros(k), np.zeros(k)
    alone = active.sum(axis=1) == 1
    s1 = np.array([c2[alone & active[:, i]].sum() for i in range(k)]) / var
    st = np.array([c2[active[:, i]].sum() for i in range(k)]) / var
    return s1, st


def bootstrap_indices(fit: PCEFit, y: np.ndarray, resamples: int, seed: int,
                      level: float = 0.95) -> dict[str, np.ndarray]:
    """Percentile intervals of S1 and ST: the design resampled with replacement, the selected basis's
    coefficients fitted again on each resample. Returns S1_lo, S1_hi, ST_lo, ST_hi."""
    y = np.asarray(y, dtype=float)
    n, k = len(y), fit.multi_indices.shape[1]
    rng = np.random.default_rng(seed)
    S1 = np.empty((resamples, k))
    ST = np.empty((resamples, k))
    for b in range(resamples):
        i = rng.integers(0, n, n)
        coef, *_ = np.linalg.lstsq(fit.psi[i], y[i], rcond=None)
        S1[b], ST[b] = pce_indices(fit.multi_indices, coef)
    a = (1 - level) / 2 * 100
    return {"S1_lo": np.percentile(S1, a, axis=0), "S1_hi": np.percentile(S1, 100 - a, axis=0),
            "ST_lo": np.percentile(ST, a, axis=0), "ST_hi": np.percentile(ST, 100 - a, axis=0)}


# ---------------------------------------------------------------------------- one output, one table
def analyse_output(Z: np.ndarray, y: np.ndarray, marginals, names: Sequence[str], max_degree: int,
                   bootstrap: int, seed: int, good_enough: float = 0.0,
                   start_degree: int = 1) -> tuple[dict, dict, np.ndarray]:
    """The expansion of one output: ({parameter: {S1, S1_lo, S1_hi, ST, ST_lo, ST_hi}}, its validation
    {loo_error, degree, terms, candidates, mean, variance}, the leave-one-out predictions)."""
    y = np.asarray(y, dtype=float)
    if not np.ptp(y) > 0:     # a constant output: no variance to share out
        table = {n: {"S1": 0.0, "S1_lo": 0.0, "S1_hi": 0.0, "ST": 0.0, "ST_lo": 0.0, "ST_hi": 0.0} for n in names}
        return table, {"loo_error": 0.0, "degree": 0, "terms": 1, "candidates": 1, "mean": float(y[0]) if len(y)
                       else None, "variance": 0.0}, y.copy()
    fit = fit_pce(Z, y, marginals, max_degree=max_degree, good_enough=good_enough, start_degree=start_degree)
    s1, st = pce_indices(fit.multi_indices, fit.coefficients)
    ci = bootstrap_indices(fit, y, bootstrap, seed)
    table = {}
    for i, n in enumerate(names):
        table[n] = {"S1": float(s1[i]), "S1_lo": float(min(ci["S1_lo"][i], s1[i])),
                    "S1_hi": float(max(ci["S1_hi"][i], s1[i])), "ST": float(st[i]),
                    "ST_lo": float(min(ci["ST_lo"][i], st[i])), "ST_hi": float(max(ci["ST_hi"][i], st[i]))}
    val = {"loo_error": float(fit.loo_error), "degree": int(fit.degree), "terms": int(len(fit.coefficients)),
           "candidates": int(fit.candidates), "mean": fit.mean, "variance": fit.variance}
    return table, val, fit.loo_predictions


def validation_error(Z: np.ndarray, y: np.ndarray, marginals, max_degree: int, good_enough: float = 0.0,
                     start_degree: int = 1) -> tuple[float, int]:
    """The corrected leave-one-out error of the expansion of ``y`` and its degree ((0, 0) for a constant
    output): the check between two rounds, with a shorter search over degrees than the final fit's."""
    y = np.asarray(y, dtype=float)
    if not np.ptp(y) > 0:
        return 0.0, 0
    fit = fit_pce(Z, y, marginals, max_degree=max_degree, good_enough=good_enough, start_degree=start_degree,
                  patience=2)
    return float(fit.loo_error), int(fit.degree)
