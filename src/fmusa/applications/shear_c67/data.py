"""The C6/C7 shear tests of ``luidias/ShearND_C67`` (e.g. ``data/shear-c67``): find, load, the authors' fits.

Measured data, not simulated (see ``PROVENANCE.md`` in the data folder): functional spinal units sheared
anteriorly (``Ant``) and posteriorly (``Pos``) at constant rates under displacement control. The
files have no time column; the rate is in the file name (``H1_C67_Ant_10_mm_s.csv``), so time is
derived from it (:class:`fmusa.diagnose.measured.ColumnSpec`, ``rate``). Shear acts along x: the drive
is ``disp_x_mm`` and the response ``Fx_N``. The ``Pos`` tests have negative displacement and force
(anterior is positive); they are kept signed unless ``flip_pos`` is asked for.

This module knows the data set's file names, columns and the authors' table; it knows nothing of FMUs.
The data folder is always an argument (any copy, any subset of specimens): nothing is found relative to
the installed package.

Example::

    from fmusa.applications.shear_c67 import data as shear_c67
    tests = shear_c67.list_tests("data/shear-c67")   # one row per file: specimen, direction, rate_mm_s, path
    exp = shear_c67.load_test(tests.iloc[0])          # an Experiment in SI, time from the rate
    fits = shear_c67.authors_bilinear("data/shear-c67")   # the authors' two-phase linear fits [N/mm]
"""
from __future__ import annotations

import os
import re
from dataclasses import replace
from pathlib import Path
from typing import Mapping

import numpy as np
import pandas as pd

from fmusa.diagnose.measured import ColumnSpec, Experiment, MeasuredDataError, downsample, load_experiment

__all__ = ["DEFAULT_DATA", "DRIVE", "data_root", "list_tests", "parse_name", "column_spec", "load_test",
           "load_raw", "authors_bilinear", "DIRECTION_NAMES"]

#: Where `fmusa diagnose-shear` looks by default: relative to the current directory (the repository root).
DEFAULT_DATA = Path("data") / "shear-c67"
#: The tests ran under displacement control.
DRIVE = "displacement"

#: The file names' direction codes in words.
DIRECTION_NAMES = {"Ant": "anterior", "Pos": "posterior"}

_NAME = re.compile(r"^(H\d+)_C67_(Ant|Pos)_(\d+(?:\.\d+)?)_mm_s$")


def data_root(root: str | os.PathLike) -> Path:
    """The data folder, checked: a missing one is named with where it was looked for and the fix."""
    root = Path(root)
    if not root.is_dir():
        where = "" if root.is_absolute() else f" (relative to the current directory {Path.cwd()})"
        raise MeasuredDataError(f"{root}: shear-c67 data folder not found{where}; pass the folder holding "
                                f"H01/…, test_info.csv with --data FOLDER (root= in Python), or run from the "
                                f"repository root, where it is {DEFAULT_DATA}")
    return root


def parse_name(path) -> tuple[str, str, float]:
    """``.../H1_C67_Pos_10_mm_s.csv`` -> ``("H1", "Pos", 10.0)``: specimen, direction, rate [mm/s]."""
    m = _NAME.match(Path(path).stem)
    if not m:
        raise MeasuredDataError(f"{path}: not a shear-c67 test file name; expected "
                                f"H<k>_C67_<Ant|Pos>_<rate>_mm_s.csv (the rate gives the time)")
    return m.group(1), m.group(2), float(m.group(3))


def list_tests(root: str | os.PathLike) -> pd.DataFrame:
    """One row per test file: specimen, direction (Ant/Pos), rate_mm_s, name (file stem), path;
    sorted by specimen, direction, rate."""
    root = data_root(root)
    rows = []
    for p in sorted(root.glob("H*/H*_C67_*_mm_s.csv")):
        specimen, direction, rate = parse_name(p)
        rows.append({"specimen": specimen, "direction": direction, "rate_mm_s": rate,
                     "name": p.stem, "path": p})
    if not rows:
        raise MeasuredDataError(f"{root}: no test files H*/H<k>_C67_<Ant|Pos>_<rate>_mm_s.csv")
    df = pd.DataFrame(rows)
    df["_k"] = df["specimen"].str[1:].astype(int)
    return (df.sort_values(["_k", "direction", "rate_mm_s"]).drop(columns="_k")
            .reset_index(drop=True))


def column_spec(rate_mm_s: float, flip: bool = False) -> ColumnSpec:
    """How a shear file reads: drive disp_x_mm [mm], response Fx_N [N], time from the rate."""
    return ColumnSpec(displacement="disp_x_mm", displacement_unit="mm", force="Fx_N",
                      force_unit="N", rate=f"{rate_mm_s:g} mm/s", flip_displacement=flip,
                      flip_force=flip)


def load_test(path_or_row: str | Path | Mapping, max_points: int | None = 1000,
              zero_drive: bool = True, flip_pos: bool = False) -> Experiment:
    """One test as an :class:`Experiment` (SI, displacement-driven, time derived from the rate).

    ``path_or_row``: a file path or a row of :func:`list_tests`. ``max_points`` (None: all samples)
    block-averages the 1 mm/s records, which have up to ~4300 samples. ``flip_pos`` negates
    displacement and force of Pos tests so that every test loads in the positive direction.
    ``meta`` gains specimen, direction and rate_mm_s.
    """
    path = Path(path_or_row["path"] if isinstance(path_or_row, (Mapping, pd.Series))
                else path_or_row)
    specimen, direction, rate = parse_name(path)
    exp = load_experiment(path, DRIVE, column_spec(rate, flip_pos and direction == "Pos"),
                          zero_drive=zero_drive)
    exp = replace(exp, meta=dict(exp.meta, specimen=specimen, direction=direction, rate_mm_s=rate))
    return exp if max_points is None else downsample(exp, max_points)


def load_raw(path_or_row: str | Path | Mapping) -> tuple[np.ndarray, np.ndarray]:
    """(disp_x [mm], Fx [N]) of one test as recorded: every sample, signed, not shifted, not averaged (the
    frame of the authors' analysis in test_info.csv)."""
    path = Path(path_or_row["path"] if isinstance(path_or_row, (Mapping, pd.Series)) else path_or_row)
    parse_name(path)
    try:
        df = pd.read_csv(path, usecols=["disp_x_mm", "Fx_N"], encoding="utf-8")
    except ValueError as e:
        raise MeasuredDataError(f"{path}: {e}; expected the columns disp_x_mm and Fx_N") from None
    df = df.dropna()
    return df["disp_x_mm"].to_numpy(float), df["Fx_N"].to_numpy(float)


_BILINEAR = {
    "ID": "specimen", "direction": "direction", "disp_rate_mm_s": "rate_mm_s",
    "stiffness_1": "stiffness_1", "stiffness_2": "stiffness_2", "breakpoint_mm": "breakpoint_mm",
    "intercept_1": "intercept_1", "intercept_2": "intercept_2", "calculated_R2_1": "r2_1",
    "calculated_R2_2": "r2_2", "calculated_R2_3": "r2_3", "peakLoad_N": "peak_load_N",
    "peakDisp_mm": "peak_disp_mm",
}


def authors_bilinear(root: str | os.PathLike) -> pd.DataFrame:
    """The authors' two-phase linear fit of Fx against disp_x per test, from test_info.csv.

    Columns: specimen, direction, rate_mm_s, stiffness_1, stiffness_2 [N/mm] (below / above the
    breakpoint), breakpoint_mm, intercept_1, intercept_2 [N], r2_1, r2_2, r2_3 (the file's
    calculated_R2_1..3, as given), peak_load_N, peak_disp_mm. The fits are on the raw signed data
    (not zeroed): Pos tests have positive stiffness, negative breakpoint; peaks are magnitudes.
    """
    path = data_root(root) / "test_info.csv"
    if not path.is_file():
        raise MeasuredDataError(f"{path}: file not found; it comes with the shear-c67 data")
    df = pd.read_csv(path, encoding="utf-8")
    missing = [c for c in _BILINEAR if c not in df.columns]
    if missing:
        raise MeasuredDataError(f"{path}:1: columns {', '.join(missing)} not in the header; "
                                f"expected the original test_info.csv")
    out = df[list(_BILINEAR)].rename(columns=_BILINEAR)
    out["rate_mm_s"] = out["rate_mm_s"].astype(float)
    return out.reset_index(drop=True)
