"""The paper's force-driven pullout scenario on the ScrewVertebra FMU."""
from __future__ import annotations

import os
from typing import Mapping

import pandas as pd

from fmusa.fmi.info import Value
from fmusa.fmi.runner import FMURunner


PULLOUT_OUTPUTS = ["y", "v_y", "a_y", "F_y", "F_pull", "y_max", "v_y_max", "t_eq"]


def pullout(params: Mapping[str, Value] | None = None, stop_time: float = 12.0, step: float | None = 0.01,
            outputs: list[str] | None = None, runner: FMURunner | None = None,
            fmu_path: str | os.PathLike | None = None) -> pd.DataFrame:
    """The paper's force-driven pullout: F_pull ramps from 0 to F_max = 411 N over t_ramp = 10 s and
    is then held, simulated to 12 s with 0.01 s communication steps. ``params`` override the FMU's
    defaults (the paper's optimum c = 823224 N/m, d = 488 N·s/m)."""
    params = dict(params or {})
    outputs = list(outputs or PULLOUT_OUTPUTS)
    if runner is not None:
        return runner.run(params, stop_time, step, outputs)
    with FMURunner(fmu_path) as fmu:
        return fmu.run(params, stop_time, step, outputs)


