"""A chain of effects (issue 22): after the first effect is named, each remaining candidate is tried on top of
it, while a further effect is significant and matters. Two effects hidden together must both be named, in
whichever order the tool finds them, with the gain of each step and the final model's parameters.

The data come from tests/effects_reference.py (independent of the FMU), with two effects at once.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import effects_reference as er  # noqa: E402

from fmusa.diagnose.measured import Experiment, downsample  # noqa: E402


def _experiment(params: dict, knots_t, knots_u, n: int, noise: float, seed: int, points: int) -> Experiment:
    t = np.linspace(0.0, float(knots_t[-1]), n)
    F = er.simulate(params, "displacement", knots_t, knots_u, t)
    F = F + np.random.default_rng(seed).normal(0.0, noise, t.size)
    y = np.interp(t, knots_t, knots_u)
    return downsample(Experiment(name="two", path=Path("two.csv"), drive="displacement", t=t, displacement=y,
                                 force=F), points)


def _check_chain(d: dict, want: set[str], truth: dict, rel: float) -> None:
    chain = [s["effect"] for s in d["chain"]]
    assert set(chain) == want and len(chain) == len(want), chain
    assert d["final"]["effects"] == chain
    for s in d["chain"]:   # every step gains on fitted and held-out data
        assert s["gain"]["rmse_ratio"] < 0.9 and s["gain"]["heldout_rmse_ratio"] < 0.9, s
    got = {k: v["value"] for k, v in d["final"]["params"].items()}
    for k, v in truth.items():
        if k in got and v != 0:
            assert got[k] == pytest.approx(v, rel=rel), (k, got[k], v)


def test_toe_and_failure_are_both_named(fmu_path):
    """A pull to failure with a toe: slack (0.15 mm) then the damaged interface (onset 1 mm past the slack,
    residual 150 N), one ramp at 0.01 mm/s, 0.1 N noise: the chain names interface_damage and backlash_gap."""
    from fmusa.diagnose.run import diagnose

    truth = {"c_y": 5.46e5, "dmg_y0": 1.0e-3, "dmg_rate": 5000.0, "dmg_F_res": 150.0, "gap": 1.5e-4}
    e = _experiment({**truth, "d_y": 0.0}, [0.0, 180.0], [0.0, 1.8e-3], 361, 0.1, 1, 180)
    d = diagnose([e], "displacement", fmu_path=fmu_path, workers=2, max_starts=3, chain=2,
                 candidates=("interface_damage", "backlash_gap", "nonlinear_stiffness"))
    _check_chain(d, {"interface_damage", "backlash_gap"}, truth, 0.05)


def test_offset_and_bend_are_both_named(fmu_path):
    """A stiffening bend and a force offset under load-unload (1.2 mm at 1.2 mm/s): the chain names both."""
    from fmusa.diagnose.run import diagnose

    truth = {"c_y": 2.0e5, "d_y": 150.0, "nl_ratio": 2.5, "nl_y_b": 5e-4, "F_offset": 25.0}
    e = _experiment(truth, [0.0, 1.0, 2.0], [0.0, 1.2e-3, 0.0], 201, 0.5, 2, 150)
    d = diagnose([e], "displacement", fmu_path=fmu_path, workers=2, max_starts=3, chain=2,
                 candidates=("nonlinear_stiffness", "sensor_offset", "backlash_gap"))
    _check_chain(d, {"nonlinear_stiffness", "sensor_offset"}, truth, 0.15)
