"""Invalid parameters are rejected with fmi2Error and a logged message naming the parameter.

Each case uses a fresh instance of the real FMU (fmpy FMU2Slave, logging on, the FMU's log
captured through fmpy's native logger proxy).  The error may come from the setter (setReal /
setInteger) or, at the latest, from fmi2ExitInitializationMode; either way the call must return
fmi2Error (fmpy raises FMICallException with that status), the log must name the parameter, and
the process must survive (afterwards the instance is freed and a fresh one simulates normally).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from fmu_run import FMI2_ERROR, FMICallException, FmuRunner

NAN = math.nan

CASES = {
    "m=0": ({"m": 0.0}, "m"),
    "m=-1": ({"m": -1.0}, "m"),
    "m=nan": ({"m": NAN}, "m"),
    "c_y<0": ({"c_y": -1.0}, "c_y"),
    "d_x=nan": ({"d_x": NAN}, "d_x"),
    "d_alpha<0": ({"d_alpha": -0.01}, "d_alpha"),
    "t_ramp=0": ({"t_ramp": 0.0}, "t_ramp"),
    "t_ramp<0": ({"t_ramp": -1.0}, "t_ramp"),
    "tab_y-not-increasing": ({"tab_n": 3, "tab_y[1]": 0.0, "tab_y[2]": 2e-4, "tab_y[3]": 1e-4,
                              "tab_F[1]": 0.0, "tab_F[2]": 50.0, "tab_F[3]": 100.0}, "tab_y"),
    "tab_y-repeated": ({"tab_n": 3, "tab_y[1]": 0.0, "tab_y[2]": 1e-4, "tab_y[3]": 1e-4,
                        "tab_F[1]": 0.0, "tab_F[2]": 50.0, "tab_F[3]": 100.0}, "tab_y"),
    "tab_n=1": ({"tab_n": 1}, "tab_n"),
    "tab_n=17": ({"tab_n": 17}, "tab_n"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_bad_parameter_is_rejected(fmu_path, name):
    params, pname = CASES[name]
    r = FmuRunner(fmu_path, logging_on=True)
    try:
        stage = "set"
        err = None
        try:
            r.fmu.reset()
            r.clear_log()
            r.set_values(params)
            stage = "setupExperiment"
            r.fmu.setupExperiment(startTime=0.0, stopTime=1.0)
            stage = "enterInitializationMode"
            r.fmu.enterInitializationMode()
            stage = "exitInitializationMode"
            r.fmu.exitInitializationMode()
        except FMICallException as e:
            err = e
        assert err is not None, (f"{name}: accepted through exitInitializationMode; log:\n"
                                 f"{r.log_text()}")
        assert err.status == FMI2_ERROR, (
            f"{name}: {err.function} returned status {err.status} at {stage}")
        assert stage in ("set", "exitInitializationMode"), f"{name}: rejected only at {stage}"
        errors = [m for s, _, m in r.messages if s >= FMI2_ERROR]
        assert errors, f"{name}: no error message logged; log:\n{r.log_text()}"
        assert any(pname in m for m in errors), (
            f"{name}: no logged error names {pname!r}; errors: {errors}")
    finally:
        r.close()


def test_fmu_still_works_after_the_rejections(fmu_path):
    """The process survived all of the above; a fresh instance simulates normally, and so does
    a reset() instance after a rejected initialisation."""
    with FmuRunner(fmu_path) as r:
        with pytest.raises(FMICallException):
            r.start({"m": -1.0}, stop_time=0.1)
        out = r.simulate({"F_max": 411.0, "t_ramp": 0.05}, np.linspace(0.0, 0.1, 11),
                         ["y", "y_max"])
        assert out["y"][-1] == pytest.approx(411.0 / 823224.0, rel=1e-3)
