"""The path that shares no code with fmusa's runs: ``fmpy.simulate_fmu`` on a fresh instance, reduced here.

Tests of FMUs from real tools compare each ``ok`` run of runs.csv with this: a new FMU instance per run
(fmpy unpacks, loads and instantiates the FMU anew), fmpy's own call order, the same start values, the
metric reduced with plain numpy.
"""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Mapping

import fmpy
import numpy as np
import pandas as pd
import yaml

#: ../shared beside the repository, or $FMUSA_SHARED_DIR (a git worktree elsewhere)
SHARED = Path(os.environ.get("FMUSA_SHARED_DIR") or Path(__file__).resolve().parents[1].parent / "shared")
VENDOR = SHARED / "vendor-fmus"


def fresh_metrics(fmu: str | Path, start_values: Mapping[str, float], metrics: Mapping[str, tuple[str, str]],
                  stop_time: float, step: float | None, fmi_type: str | None = None,
                  relative_tolerance: float | None = None) -> dict[str, float]:
    """metric -> value of one run on a fresh instance; ``metrics``: metric -> (output, reduce)."""
    outputs = sorted({o for o, _ in metrics.values()})
    res = fmpy.simulate_fmu(str(fmu), start_time=0.0, stop_time=stop_time, start_values=dict(start_values),
                            output=outputs, output_interval=step if step else stop_time, fmi_type=fmi_type,
                            relative_tolerance=relative_tolerance)
    out = {}
    for name, (output, reduce) in metrics.items():
        x = np.asarray(res[output], dtype=float)
        out[name] = {"final": lambda: x[-1], "max": lambda: x.max(), "min": lambda: x.min(),
                     "max_abs": lambda: np.abs(x).max()}[reduce]()
    return out


def study_metrics(study_file: Path) -> dict[str, tuple[str, str]]:
    data = yaml.safe_load(study_file.read_text(encoding="utf-8"))
    return {k: (v["output"], v.get("reduce", "final")) for k, v in data["metrics"].items()}


def largest_difference(runs: pd.DataFrame, study_file: Path, fmu: Path, fmi_type: str | None = None,
                       relative_tolerance: float | None = None) -> tuple[float, int]:
    """The largest relative difference between an ``ok`` run of ``runs`` and a fresh fmpy run at the same
    point (parameters and fixed values of ``study_file``), and the number of runs compared."""
    data = yaml.safe_load(study_file.read_text(encoding="utf-8"))
    metrics = study_metrics(study_file)
    fixed = dict(data.get("fixed") or {})
    params = {k: v["variable"] for k, v in data["parameters"].items()}
    sc = data["scenario"]
    worst, n = 0.0, 0
    for _, row in runs[runs["status"] == "ok"].iterrows():
        start = {**fixed, **{var: float(row[p]) for p, var in params.items()}}
        ref = fresh_metrics(fmu, start, metrics, float(sc["stop_time"]), sc.get("step"), fmi_type,
                            relative_tolerance)
        for m, x in ref.items():
            y = float(row[m])
            if math.isnan(x) and math.isnan(y):
                continue
            worst = max(worst, abs(y - x) / max(abs(x), 1e-300))
        n += 1
    return worst, n
