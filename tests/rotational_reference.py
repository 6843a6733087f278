"""Independent reference of an interface element attached to a rotational model (tests/rotor_fmu.py: an inertia J
on a torsion spring k and damper b, torque input ``tau``, angle output ``phi``), and synthetic measured tests made
with it: angle in deg, torque in N·m, as a torsion test machine writes them.

With the element between the inertia and the ground (s = phi, v = phi', its torque T_el entering ``tau`` with
the sign -1) and a measured torque drive T(t):

    J phi'' = T(t) - k phi - b phi' - T_el(phi, phi', element states)

T_el and its states are the equations of fmu/MODEL.md as tests/effects_reference.py writes them (the element is
unit-agnostic: c_y in N·m/rad, gap in rad, fric_F in N·m, …); scipy only, none of fmusa's code and none of the
coupling master's. Integrated by scipy LSODA at rtol 1e-10, piecewise between the drive's knots.
"""
from __future__ import annotations

import math

import numpy as np
import pandas as pd

import attached_reference as ar
from rotor_fmu import B as DAMPER, J as INERTIA, K as SPRING

#: The element's baseline (in parallel with the model's spring-damper) and the hidden effects at this model's
#: scale (angles ~4 deg, torques ~2 N·m), in SI (rad, N·m).
BASE = {"c_y": 10.0, "d_y": 0.05}
CASES = {
    "none": {},
    "backlash_gap": {"gap": 0.01},                               # 0.573 deg
    "coulomb_friction": {"fric_F": 0.3, "fric_x": 2.0e-3},       # 0.3 N·m after 0.115 deg of pre-slip
}
DEG = math.pi / 180.0


def protocol(peak: float = 2.0, ramp: float = 0.5, hold: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """A torque drive [N·m]: load to ``peak`` over ``ramp``, hold, unload to -peak/2, hold, back to 0."""
    t = np.cumsum([0.0, ramp, hold, 1.5 * ramp, hold, 0.5 * ramp, hold])
    u = np.array([0.0, peak, peak, -0.5 * peak, -0.5 * peak, 0.0, 0.0])
    return t, u


def simulate(element: dict, knots_t, knots_u, t_out, rtol: float = 1e-10) -> np.ndarray:
    """The angle phi [rad] at ``t_out`` under the torque drive through the knots, with the element's parameters
    (catalogue names): the attached reference's integration (tests/attached_reference.py) with the rotor's inertia,
    spring and damper."""
    return ar.simulate_on(element, knots_t, knots_u, t_out, INERTIA, SPRING, DAMPER, 0.0, rtol, atol_ve=1e-10)


def synthesize(effect: str, rate_hz: float = 40.0, noise_deg: float = 0.01, seed: int = 0,
               **protocol_kw) -> tuple[pd.DataFrame, dict]:
    """A measured test of the case ``effect``: columns ``t_s``, ``angle_deg`` (white noise of ``noise_deg``) and
    ``torque_Nm`` (the drive; every knot is a sample at 40 Hz, so the drive the samples give is the one the reference ran); and the element's true parameters (SI)."""
    truth = {**BASE, **CASES[effect]}
    kt, ku = protocol(**protocol_kw)
    t = np.arange(0.0, kt[-1] + 1e-9, 1.0 / rate_hz)
    phi = simulate(truth, kt, ku, t) / DEG
    phi = phi + np.random.default_rng(seed).normal(0.0, noise_deg, phi.size)
    return pd.DataFrame({"t_s": t, "angle_deg": phi, "torque_Nm": np.interp(t, kt, ku)}), truth
