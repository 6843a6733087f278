"""The Python API's FMURunner checks the way it brings its instance back, as a study's pre-flight check does.

Its first run (on a fresh instance) is made again after the second one on the same instance; where they
differ (20-sim 4.6's outputs read 0 after fmi2Reset; a Dymola 2022x-like reset that restarts the state at 0,
built from tests/fmus/faulty), the runner moves on to a state snapshot or a new instance per run, warns, and
every run it returns equals a run of fmpy on a fresh instance (or the oscillator's closed form). The verdict is
cached per FMU digest: a second runner does not check again.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import fmpy
import numpy as np
import pytest

from faulty_fmu import build_faulty, closed_form
from fmusa.fmi.runner import FMURunner, FMUReuseWarning

SHARED = Path(os.environ.get("FMUSA_SHARED_DIR") or Path(__file__).resolve().parents[2] / "shared")
TORSION_BAR = SHARED / "vendor-fmus" / "20sim464_TorsionBar.fmu"


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("FMUSA_CACHE_DIR", str(tmp_path / "cache"))


def _runs(fmu: Path, points: list[dict], **run) -> tuple[list, list[str], FMURunner]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with FMURunner(fmu) as r:
            out = [r.run(p, **run) for p in points]
            mode = r.reuse
    return out, [str(w.message) for w in caught if issubclass(w.category, FMUReuseWarning)], mode


def test_torsion_bar_runs_after_the_first_equal_fresh_fmpy_runs():
    if not TORSION_BAR.exists():
        pytest.skip("the shared vendor FMUs are not here")
    outputs = ["LoadDiskRev", "MotorDiskRev"]
    runs, warned, mode = _runs(TORSION_BAR, [{}, {}, {}], stop_time=1.0, step=0.1, outputs=outputs)
    ref = fmpy.simulate_fmu(str(TORSION_BAR), stop_time=1.0, output_interval=0.1, output=outputs)
    for df in runs:
        for name in outputs:
            np.testing.assert_allclose(df[name].to_numpy(), ref[name], rtol=0, atol=1e-12)
    assert abs(runs[1]["MotorDiskRev"].iloc[-1]) > 1       # the broken reset gave 0 here
    assert mode == "fresh" and len(warned) == 1 and "fmi2Reset" in warned[0] and "0 instead of" in warned[0]
    # the verdict is cached per FMU digest: a new runner uses it at once, without checking again
    runs2, warned2, mode2 = _runs(TORSION_BAR, [{}, {}], stop_time=1.0, step=0.1, outputs=outputs)
    assert mode2 == "fresh" and warned2 == []
    np.testing.assert_allclose(runs2[1]["MotorDiskRev"].to_numpy(), ref["MotorDiskRev"], atol=1e-12)


@pytest.mark.parametrize("with_state,mode", [(False, "fresh"), (True, "snapshot")])
def test_reset_that_restarts_the_state_at_zero(tmp_path, with_state, mode):
    """Dymola 2022x-like: after fmi2Reset x(0) = 0 instead of 0.5. Every run equals the closed form."""
    fmu = build_faulty(tmp_path, "reset_zero", with_state=with_state, me=False)
    ks = [100.0, 200.0, 100.0, 400.0]
    runs, warned, got = _runs(fmu, [{"k": k} for k in ks], stop_time=2.0, step=0.01, outputs=["x", "v"])
    t = runs[0]["time"].to_numpy()
    for k, df in zip(ks, runs):
        x, v = closed_form(t, k=k)
        assert df["x"].iloc[0] == pytest.approx(0.5)
        np.testing.assert_allclose(df["x"].to_numpy(), x, atol=2e-3)
        np.testing.assert_allclose(df["v"].to_numpy(), v, atol=2e-2)
    assert got == mode and len(warned) == 1


def test_a_reset_that_works_is_kept_and_checked_once(tmp_path):
    fmu = build_faulty(tmp_path, "none", me=False)
    runs, warned, mode = _runs(fmu, [{"k": 100.0}, {"k": 300.0}, {"k": 100.0}], stop_time=1.0, step=0.01,
                               outputs=["x"])
    assert mode == "reset" and warned == []
    np.testing.assert_array_equal(runs[0]["x"].to_numpy(), runs[2]["x"].to_numpy())
    assert list((tmp_path / "cache").glob("runner-reuse-*.json"))
