"""The region of interest, derived from the grid by stated rules (the paper picked it by hand).

Rules, for an inner parameter x (searched for its smallest feasible value, the paper's stiffness c) and an
outer parameter z (halved from the region's top, the paper's damping d):

1. x_min(z) is the smallest grid x that meets every constraint at z. The region's x-range is
   [largest grid x below min_z x_min(z), min_z x_min(z)]: the grid neighbours that bracket the smallest
   feasible x (0 when no grid value lies below).
2. The region's z-range is [z_lo, z_hi], where z_hi is the largest grid z at which x_min(z) still equals
   the overall smallest feasible x (beyond it the outer parameter starts to cost inner parameter), and z_lo is
   0 when the smallest grid z is feasible there (the boundary may lie below the grid, as the paper's d = 0),
   else the grid neighbour below the smallest feasible z.

With one parameter (a search with ``inner`` only, ``outer`` None) only rule 1 applies, over the grid runs at
the point the search runs at (the other study parameters at ``at``, their first grid values): the region
is an inner range alone (``outer`` and ``outer_range`` None).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
import pandas as pd

from fmusa.study.schema import StudyError


@dataclass(frozen=True)
class Region:
    """The box the search works in; ``outer`` and ``outer_range`` are None for a one-parameter search."""
    inner: str
    outer: str | None
    inner_range: tuple[float, float]
    outer_range: tuple[float, float] | None
    source: str                        # "automatic" or "manual"
    notes: tuple[str, ...] = ()

    def as_dict(self) -> dict:
        """{inner: [lo, hi], outer: [lo, hi], source, notes} (no outer key in one dimension)."""
        out: dict = {self.inner: list(self.inner_range)}
        if self.outer is not None:
            out[self.outer] = list(self.outer_range)
        return {**out, "source": self.source, "notes": list(self.notes)}


def _at_point(grid: pd.DataFrame, at: Mapping[str, float] | None) -> pd.DataFrame:
    """The grid rows whose other parameters equal ``at`` (all rows when ``at`` is empty)."""
    if not at:
        return grid
    keep = np.ones(len(grid), dtype=bool)
    for name, value in at.items():
        keep &= np.isclose(grid[name].to_numpy(dtype=float), float(value), rtol=1e-12, atol=0.0)
    return grid[keep]


def feasibility_matrix(grid: pd.DataFrame, inner: str, outer: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Grid axes (sorted) and a boolean matrix feasible[outer index, inner index]."""
    xs = np.sort(grid[inner].unique())
    zs = np.sort(grid[outer].unique())
    feas = np.zeros((len(zs), len(xs)), dtype=bool)
    for _, row in grid.iterrows():
        i = np.searchsorted(zs, row[outer])
        j = np.searchsorted(xs, row[inner])
        feas[i, j] = bool(row["feasible"]) and row["status"] == "ok"
    return xs, zs, feas


def automatic_region(grid: pd.DataFrame, inner: str, outer: str | None = None,
                     at: Mapping[str, float] | None = None, constraints: Sequence = (),
                     params: Sequence[str] | None = None) -> Region:
    """The region by the module's rules from the grid runs at ``at`` (the study parameters the search does
    not vary; None: every run); ``outer`` None gives the inner range alone (rule 1). ``constraints`` and
    ``params`` (the study's) make the error of a grid without a feasible point say which constraints fail,
    by how much, and along which parameter widening could help (:func:`infeasible_message`)."""
    whole = grid
    grid = _at_point(grid, at)
    axes = [n for n in (inner, outer) if n]
    if at and not len(grid):
        raise StudyError(f"no grid run at {_where(at)}, where the region is found: set stages.roi.at to grid "
                         f"values of {', '.join(at)}")

    def why() -> str:
        text = (infeasible_message(grid, constraints, list(params or axes)) if constraints else
                f"no grid point meets every constraint: widen the grid of {' and '.join(axes)} or relax the "
                f"constraints (see runs.csv, columns ok_*)")
        return text + _feasible_elsewhere(whole, grid, at)
    if len(grid) and "status" in grid and (grid["status"] != "ok").all():
        first = grid["message"].iloc[0] if "message" in grid else ""
        raise StudyError(f"all {len(grid)} grid runs failed, so there is no region of interest; the first "
                         f"says: {first} (every run's reason is in runs.csv, column message)")
    if outer is None:
        return _inner_only(grid, inner, why)
    xs, zs, feas = feasibility_matrix(grid, inner, outer)
    if not feas.any():
        raise StudyError(why())
    notes = []
    x_min = np.array([xs[np.argmax(row)] if row.any() else np.inf for row in feas])
    best = x_min.min()
    j_best = int(np.searchsorted(xs, best))
    x_lo = float(xs[j_best - 1]) if j_best > 0 else 0.0
    if j_best == 0:
        notes.append(f"the smallest grid {inner} is already feasible: the boundary may lie below the grid")
    flat = np.where(x_min == best)[0]
    i_hi = int(flat.max())
    z_hi = float(zs[i_hi])
    i_lo = int(flat.min())
    z_lo = 0.0 if i_lo == 0 else float(zs[i_lo - 1])
    if len(flat) != i_hi - i_lo + 1:
        notes.append(f"the {outer} values where {inner} = {best:g} is feasible are not contiguous: "
                     f"{', '.join(f'{zs[i]:g}' for i in flat)}")
    return Region(inner, outer, (x_lo, float(best)), (z_lo, z_hi), "automatic", tuple(notes))


def _where(at: Mapping[str, float]) -> str:
    return ", ".join(f"{k} = {_num(v)}" for k, v in at.items())


def _feasible_elsewhere(whole: pd.DataFrame, here: pd.DataFrame, at: Mapping[str, float] | None) -> str:
    """The grid's feasible points at other values of the parameters held at ``at`` (the region is found
    at ``at`` only), and how to find the region there: "" when there are none."""
    if not at or "feasible" not in whole:
        return ""
    ok = whole[whole["feasible"].astype(bool) & ((whole["status"] == "ok") if "status" in whole else True)]
    if not len(ok) or len(ok) == int((here["feasible"].astype(bool)).sum()):
        return ""
    names = list(at)
    combos = ok.groupby(names, sort=True).size()
    listed = "; ".join(f"{_where(dict(zip(names, key if isinstance(key, tuple) else (key,))))}: {n}"
                       for key, n in combos.items())
    first = combos.index[0]
    first = dict(zip(names, first if isinstance(first, tuple) else (first,)))
    return (f". The region is found at {_where(at)} (stages.roi.at, else the first grid values of the "
            f"parameters the search does not vary), but {len(ok)} of the {len(whole)} grid points meet every constraint at other values "
            f"({listed}): set stages.roi.at to one of them, e.g. roi: {{at: {{"
            + ", ".join(f"{k}: {_num(v)}" for k, v in first.items()) + "}}")


def _inner_only(grid: pd.DataFrame, inner: str, why=None) -> Region:
    """Rule 1 in one dimension: the grid neighbours that bracket the smallest feasible grid value."""
    xs = np.sort(grid[inner].unique())
    ok = (grid["feasible"].astype(bool) & (grid["status"] == "ok")).to_numpy()
    feasible_xs = np.sort(grid.loc[ok, inner].unique())
    if not len(feasible_xs):
        raise StudyError(why())
    best = float(feasible_xs[0])
    j_best = int(np.searchsorted(xs, best))
    notes = []
    x_lo = float(xs[j_best - 1]) if j_best > 0 else 0.0
    if j_best == 0:
        notes.append(f"the smallest grid {inner} is already feasible: the boundary may lie below the grid")
    above = xs[xs > best]
    infeasible_above = sorted(set(map(float, above)) - set(map(float, feasible_xs)))
    if infeasible_above:
        notes.append(f"{inner} is not feasible at every grid value above {best:g} (not at "
                     f"{', '.join(f'{x:g}' for x in infeasible_above)}): the boundary may not be monotone")
    return Region(inner, None, (x_lo, best), None, "automatic", tuple(notes))


def manual_region(manual: Mapping[str, Sequence[float]], inner: str, outer: str | None = None) -> Region:
    """The region given by hand (``stages.roi.manual``): parameter -> [lo, hi]."""
    outer_range = None if outer is None else tuple(map(float, manual[outer]))
    return Region(inner, outer, tuple(map(float, manual[inner])), outer_range, "manual")


def grid_findings(grid: pd.DataFrame, axes: Sequence[str], metrics: Sequence[str],
                  constraints: Sequence = ()) -> dict:
    """What the grid found, for summary.json: how many runs meet every constraint, how many failed, and the
    feasible point with the smallest value of ``axes[0]`` (ties: of the next axis), the point a search for
    the smallest feasible parameters refines (None when no run is feasible). Also the parameters that
    change no metric (``inert_parameters``, :func:`inert_parameters`) and, when no run is feasible, why
    (``infeasible``, :func:`infeasible_message`)."""
    ok = grid[grid["status"] == "ok"] if "status" in grid else grid
    feasible = ok[ok["feasible"].astype(bool)] if "feasible" in ok else ok
    out: dict = {"feasible": int(len(feasible)), "failed": int(len(grid) - len(ok)), "best": None}
    if len(feasible) and axes:
        best = feasible.sort_values(list(axes)).iloc[0]
        out["best"] = {**{a: float(best[a]) for a in axes}, **{m: float(best[m]) for m in metrics if m in best}}
    inert = inert_parameters(grid, axes, metrics)
    if inert:
        out["inert_parameters"] = inert
    if constraints and len(ok) and not len(feasible):
        out["infeasible"] = infeasible_message(grid, constraints, axes)
    return out


#: Why a study parameter may change no metric at all.
INERT_CAUSES = ("the FMU ignores it: it may drop values set before fmi2SetupExperiment (some exporters do), "
                "it may be the wrong variable (one that no metric's output depends on), or a structural "
                "parameter the FMU reads only when it is instantiated; check it with `fmusa inspect` and a "
                "run of the FMU at two of its values")


def inert_parameters(grid: pd.DataFrame, params: Sequence[str], metrics: Sequence[str]) -> dict[str, dict]:
    """The study parameters whose grid values change none of ``metrics`` (nor whether a run works), with
    the other parameters held: {name: {"values": n, "message": ...}}. A parameter with one grid value, or
    whose values never meet at equal other values, is not judged. Equal means NaN for NaN, else within a
    relative 1e-12 (round-off)."""
    out: dict[str, dict] = {}
    if not len(grid):
        return out
    metrics = [m for m in metrics if m in grid]
    M = grid[metrics].to_numpy(dtype=float) if metrics else np.empty((len(grid), 0))
    ok = (grid["status"] == "ok").to_numpy() if "status" in grid else np.ones(len(grid), bool)
    P = grid[list(params)].to_numpy(dtype=float)
    for j, p in enumerate(params):
        values = np.unique(P[:, j])
        if len(values) < 2:
            continue
        others = np.delete(P, j, axis=1)
        if others.shape[1]:
            _, first, group = np.unique(others, axis=0, return_index=True, return_inverse=True)
            group = group.ravel()
        else:
            first, group = np.zeros(1, dtype=np.int64), np.zeros(len(P), dtype=np.int64)
        pairs = np.unique(np.column_stack([group, P[:, j]]), axis=0)
        if not (np.bincount(pairs[:, 0].astype(np.int64)) > 1).any():
            continue              # no two of its values at the same other values: not judged
        ref = first[group]
        a, b = M, M[ref]
        same = (np.isnan(a) & np.isnan(b)) | (np.abs(a - b) <= 1e-12 * np.maximum(np.abs(a), np.abs(b)))
        if same.all() and (ok == ok[ref]).all():
            out[p] = {"values": int(len(values)),
                      "message": f"parameter '{p}' changes none of the metrics ({', '.join(metrics)}) across its "
                                 f"{len(values)} grid values ({_num(values[0])} … {_num(values[-1])}): "
                                 f"{INERT_CAUSES}"}
    return out


def _num(x: float) -> str:
    return f"{float(x):.4g}"


def _bound_text(c) -> str:
    parts = ([f"{c.metric} <= {_num(c.max)}"] if c.max is not None else []) + (
        [f"{c.metric} >= {_num(c.min)}"] if c.min is not None else [])
    return " and ".join(parts) or f"{c.metric} has a value"


def _excess(c, v: np.ndarray) -> np.ndarray:
    """How far each value is past the constraint's bounds (0 inside; NaN for no value)."""
    v = np.asarray(v, dtype=float)
    e = np.zeros_like(v)
    if c.max is not None:
        e = np.maximum(e, v - c.max)
    if c.min is not None:
        e = np.maximum(e, c.min - v)
    return np.where(np.isnan(v), np.nan, e)


def infeasible_message(grid: pd.DataFrame, constraints: Sequence, params: Sequence[str]) -> str:
    """Why no grid point meets every constraint: each constraint no run meets, with its nearest value and
    how far past the bound it is (or that its metric has no value in any run, which no grid can mend), and
    a wider grid recommended only along a parameter that moves that metric towards its bound (parameters
    that change no metric are named as such)."""
    ok = grid[grid["status"] == "ok"] if "status" in grid else grid
    if not len(ok):
        return "no grid point meets every constraint: every grid run failed (see runs.csv, column message)"
    meta = {"run_id", "stage", "status", "message", "seconds", "feasible"}
    metrics = [m for m in grid.columns if m not in meta and m not in params and not str(m).startswith("ok_")]
    inert = inert_parameters(grid, params, metrics)
    failing = [c for c in constraints if not _holds(ok, c).any()]
    parts, advice, no_value = [], [], []
    for c in failing:
        v = ok[c.metric].to_numpy(dtype=float)
        if np.isnan(v).all():
            no_value.append(c.name)
            parts.append(f"constraint '{c.name}' ({_bound_text(c)}): {c.metric} is NaN in every one of the "
                         f"{len(ok)} grid runs that worked (no run gives it a value), so no grid can meet it; "
                         f"check metric '{c.metric}' (its output, reduce and missing_below) or drop the constraint")
            continue
        e = _excess(c, v)
        i = int(np.nanargmin(e))
        bound = c.max if c.max is not None and v[i] > c.max else c.min
        rel = f" ({100 * e[i] / abs(bound):.3g} % past it)" if bound else ""
        at = ", ".join(f"{p} = {_num(ok[p].iloc[i])}" for p in params if p in ok)
        parts.append(f"constraint '{c.name}' ({_bound_text(c)}) is met by none of the {len(ok)} grid runs: "
                     f"nearest {c.metric} = {_num(v[i])} at {at}, {_num(e[i])} past its bound{rel}")
        advice.append(_widen_advice(ok, c, [p for p in params if p in ok and p not in inert]))
    if not failing:
        parts.append("each constraint is met at some grid point, but no point meets all of them at once: "
                     + "; ".join(f"'{c.name}' at {int(_holds(ok, c).sum())} of {len(ok)}" for c in constraints))
    text = "no grid point meets every constraint: " + "; ".join(parts)
    good = [a for a in advice if a]
    if no_value:      # a grid, however wide, cannot give that metric a value
        text += (f". A wider grid cannot help while {', '.join(repr(n) for n in no_value)} "
                 f"{'has' if len(no_value) == 1 else 'have'} no value in any run")
    elif good:
        text += ". " + "; ".join(good)
    elif failing and any(not np.isnan(ok[c.metric].to_numpy(dtype=float)).all() for c in failing):
        text += (". No study parameter moves the failing metrics towards their bounds across the grid, so a "
                 "wider grid will not help: relax the constraints, or check the model and the metrics")
    for p, info in inert.items():
        text += f". Note: {info['message']}"
    return text + " (see runs.csv, columns ok_*)"


def _holds(ok: pd.DataFrame, c) -> np.ndarray:
    col = f"ok_{c.name}"
    if col in ok:
        return ok[col].astype(bool).to_numpy()
    e = _excess(c, ok[c.metric].to_numpy(dtype=float))
    return np.nan_to_num(e, nan=1.0) <= 0


#: A wider grid is advised along a parameter only when, across its grid, the failing metric comes nearer
#: its bound by at least this fraction of the distance left (else it would take a grid many times wider).
WIDEN_MIN_GAIN = 0.01


def _widen_advice(ok: pd.DataFrame, c, params: Sequence[str]) -> str:
    """Where to widen the grid for constraint ``c``: along each parameter whose best value of the metric
    (over the others) comes nearer the bound towards one end of its grid (by :data:`WIDEN_MIN_GAIN` of
    the distance left, at least), beyond that end; "" for none."""
    e_all = _excess(c, ok[c.metric].to_numpy(dtype=float))
    tips = []
    for p in params:
        x = ok[p].to_numpy(dtype=float)
        xs = np.unique(x)
        if len(xs) < 2:
            continue
        best = np.array([np.nanmin(e_all[x == v]) if np.isfinite(e_all[x == v]).any() else np.nan for v in xs])
        if np.isnan(best[[0, -1]]).any():
            continue
        lo, hi = best[0], best[-1]
        if abs(lo - hi) < WIDEN_MIN_GAIN * min(lo, hi):     # across its whole grid it hardly moves the metric
            continue
        if hi < lo and hi <= np.nanmin(best):
            tips.append(f"widen the grid of {p} above {_num(xs[-1])} (towards its top {c.metric} comes nearer its "
                        f"bound: {_num(lo)} → {_num(hi)} past it)")
        elif lo < hi and lo <= np.nanmin(best):
            tips.append(f"widen the grid of {p} below {_num(xs[0])} (towards its bottom {c.metric} comes nearer "
                        f"its bound: {_num(hi)} → {_num(lo)} past it)")
    if not tips:
        return ""
    return f"For '{c.name}': " + ", or ".join(tips)


def floor_region(region: Region, rtol: float) -> Region:
    """``region`` with an inner lower bound of 0 (the smallest grid value already feasible, or a manual 0)
    raised to an absolute floor, ``rtol`` × its upper bound: a relative stop rule never holds near 0, and
    many FMUs refuse a stiffness or area of 0. A boundary below the floor is reported as lying below it."""
    lo, hi = region.inner_range
    if not (lo <= 0 < hi):
        return region
    floor = rtol * hi
    note = (f"the search starts at {region.inner} = {floor:.6g} (inner_rtol × the region's top), not at "
            f"{lo:g}: a bound found below it is reported as lying below it")
    from dataclasses import replace
    return replace(region, inner_range=(floor, hi), notes=region.notes + (note,))
