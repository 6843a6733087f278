"""The cases the second Modelica tool and the FMU both run (tests/test_second_tool.py).

Kept apart from the test so that a case can be run by hand: `python tests/second_tool/cases.py NAME` (in the
project's venv) prints the case file the runner reads.

Parameter values: the paper's pullout is the FMU's defaults; the 6-DOF load case is studies/six_dof.yaml's (411 N
ramped over 50 ms, lateral forces 20 N and -10 N, 5 N mm about the screw axis, 0.1 s), and "six-dof-large-angles"
tests/test_six_dof.py's case (b) (soft rotations, angles of 0.1-0.2 rad, the interaction point off the centre of
gravity and the axis, a lateral force and three torques); each effect runs in both drive modes with values inside the ranges of
tests/effects_reference.py's generator (draw_case), scaled to these load cases:
* mode 1 (force-driven): 200 N ramped over 1 s, held to 2 s, unloaded over 1 s, 1 s at rest (the loop shows
  hysteresis, creep and residual set); linear peak displacement y_lin = 200 N / c_y = 0.24 mm;
* mode 2 (motion-driven): y = v_pull t at 0.5 mm/s for 1 s (0.5 mm, 411 N for the linear spring).
"""
from __future__ import annotations

import json
import math
import sys
from typing import Any

#: the outputs compared in every case
BASE_OUTPUTS = ("y", "v_y", "F_y", "F_pull")
SIX_DOF_OUTPUTS = ("x", "y", "z", "alpha", "beta", "gamma", "v_x", "v_y", "v_z", "w_alpha", "w_beta", "w_gamma",
                   "F_y", "F_pull")

FORCE_LOAD = dict(mode=1, F_max=200.0, t_ramp=1.0, unload=True, t_unload=2.0)
MOTION_LOAD = dict(mode=2, v_pull=5e-4)

#: a stiffening table (tests/test_motion_mode.py's): beyond 3e-4 m it extrapolates with 1.8e6 N/m
TABLE = {"tab_n": 4, "tab_y[1]": 0.0, "tab_y[2]": 1e-4, "tab_y[3]": 2e-4, "tab_y[4]": 3e-4,
         "tab_F[1]": 0.0, "tab_F[2]": 40.0, "tab_F[3]": 120.0, "tab_F[4]": 300.0}

#: effect -> (parameters in mode 1, parameters in mode 2, the effect's own outputs)
EFFECTS: dict[str, tuple[dict[str, Any], dict[str, Any], tuple[str, ...]]] = {
    "gap": (dict(gap=5e-5), dict(gap=1e-4), ()),
    "nonlinear": (dict(nl_ratio=2.0, nl_y_b=1e-4), dict(nl_ratio=0.5, nl_y_b=2e-4), ()),
    "yield": (dict(yield_ratio=0.3, yield_F=100.0), dict(yield_ratio=0.3, yield_F=150.0), ()),
    "friction": (dict(fric_F=20.0, fric_x=1e-5), dict(fric_F=40.0, fric_x=1e-5), ("F_fric",)),
    "viscoelastic": (dict(ve_k=4e5, ve_tau=0.5), dict(ve_k=4e5, ve_tau=0.3), ("F_ve",)),
    "offset": (dict(F_offset=10.0, y_offset=2e-5), dict(F_offset=20.0, y_offset=1e-5), ("F_meas", "y_meas")),
    "table": (dict(TABLE), dict(TABLE), ()),
    "damage": (dict(dmg_rate=1200.0, dmg_y0=1e-4, dmg_F_res=60.0),
               dict(dmg_rate=7300.0, dmg_y0=2.25e-4, dmg_F_res=46.0), ("dmg_D",)),
}


def comm_points(stop: float, step: float) -> list[float]:
    """k*step for k = 0..n, the last one exactly stop (tests/fmu_run.py's comm_grid)."""
    n = int(math.floor(stop / step + 0.5))
    return [k * step for k in range(n)] + [stop]


def cases() -> dict[str, dict[str, Any]]:
    """name -> {params, inputs, stop, step, outputs}."""
    out: dict[str, dict[str, Any]] = {
        "paper-pullout": dict(params={}, inputs={}, stop=12.0, step=0.05, outputs=BASE_OUTPUTS),
        "six-dof": dict(params=dict(F_max=411.0, t_ramp=0.05),
                        inputs=dict(F_ext_x=20.0, F_ext_z=-10.0, T_ext_y=0.005),
                        stop=0.1, step=1e-3, outputs=SIX_DOF_OUTPUTS),
        "six-dof-large-angles": dict(params=dict(F_max=1.0, t_ramp=0.01, c_alpha=0.05, c_beta=0.02,
                                                 c_gamma=0.05,
                                                 d_alpha=1e-4, d_beta=1e-4, d_gamma=1e-4, rI_x=0.0005, rI_y=-0.012),
                                     inputs=dict(F_ext_x=0.5, T_ext_x=0.005, T_ext_y=0.004, T_ext_z=-0.004),
                                     stop=0.05, step=5e-4, outputs=SIX_DOF_OUTPUTS),
    }
    for effect, (force, motion, own) in EFFECTS.items():
        out[f"{effect}-force"] = dict(params={**FORCE_LOAD, **force}, inputs={}, stop=4.0, step=0.02,
                                      outputs=BASE_OUTPUTS + own)
        out[f"{effect}-motion"] = dict(params={**MOTION_LOAD, **motion}, inputs={}, stop=1.0, step=0.01,
                                       outputs=BASE_OUTPUTS + own)
    return out


if __name__ == "__main__":
    print(json.dumps(cases()[sys.argv[1]], indent=1))
