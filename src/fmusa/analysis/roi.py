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
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd


@dataclass(frozen=True)
class Region:
    inner: str
    outer: str
    inner_range: tuple[float, float]
    outer_range: tuple[float, float]
    source: str                        # "automatic" or "manual"
    notes: tuple[str, ...] = ()

    def as_dict(self) -> dict:
        return {self.inner: list(self.inner_range), self.outer: list(self.outer_range),
                "source": self.source, "notes": list(self.notes)}


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


def automatic_region(grid: pd.DataFrame, inner: str, outer: str) -> Region:
    xs, zs, feas = feasibility_matrix(grid, inner, outer)
    if not feas.any():
        raise ValueError(f"no grid point meets every constraint: widen the grid of {inner} and {outer} "
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


def manual_region(manual: dict, inner: str, outer: str) -> Region:
    return Region(inner, outer, tuple(map(float, manual[inner])), tuple(map(float, manual[outer])), "manual")
