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
                     at: Mapping[str, float] | None = None) -> Region:
    """The region by the module's rules from the grid runs at ``at`` (the study parameters the search does
    not vary; None: every run); ``outer`` None gives the inner range alone (rule 1)."""
    grid = _at_point(grid, at)
    if len(grid) and "status" in grid and (grid["status"] != "ok").all():
        first = grid["message"].iloc[0] if "message" in grid else ""
        raise StudyError(f"all {len(grid)} grid runs failed, so there is no region of interest; the first "
                         f"says: {first} (every run's reason is in runs.csv, column message)")
    if outer is None:
        return _inner_only(grid, inner)
    xs, zs, feas = feasibility_matrix(grid, inner, outer)
    if not feas.any():
        raise StudyError(f"no grid point meets every constraint: widen the grid of {inner} and {outer} "
                         f"or relax the constraints (see runs.csv, columns ok_*)")
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


def _inner_only(grid: pd.DataFrame, inner: str) -> Region:
    """Rule 1 in one dimension: the grid neighbours that bracket the smallest feasible grid value."""
    xs = np.sort(grid[inner].unique())
    ok = (grid["feasible"].astype(bool) & (grid["status"] == "ok")).to_numpy()
    feasible_xs = np.sort(grid.loc[ok, inner].unique())
    if not len(feasible_xs):
        raise StudyError(f"no grid point meets every constraint: widen the grid of {inner} or relax the "
                         f"constraints (see runs.csv, columns ok_*)")
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


def grid_findings(grid: pd.DataFrame, axes: Sequence[str], metrics: Sequence[str]) -> dict:
    """What the grid found, for summary.json: how many runs meet every constraint, how many failed, and the
    feasible point with the smallest value of ``axes[0]`` (ties: of the next axis), the point a search for
    the smallest feasible parameters refines (None when no run is feasible)."""
    ok = grid[grid["status"] == "ok"] if "status" in grid else grid
    feasible = ok[ok["feasible"].astype(bool)] if "feasible" in ok else ok
    out: dict = {"feasible": int(len(feasible)), "failed": int(len(grid) - len(ok)), "best": None}
    if len(feasible) and axes:
        best = feasible.sort_values(list(axes)).iloc[0]
        out["best"] = {**{a: float(best[a]) for a in axes}, **{m: float(best[m]) for m in metrics if m in best}}
    return out
