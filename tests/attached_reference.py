"""Independent reference of an interface element attached to OpenModelica's Mass_Damper export
(``../shared/vendor-fmus/OM1193_Mass_Damper.fmu``), and synthetic measured tests made with it.

The exported model (its ``resources/Mass_Damper_info.json``, and checked against the FMU itself by
tests/test_diagnose_attached.py): a mass m = 1 kg on a spring c = 1e4 N/m (unstretched length 1 m, fixed end at
1 m) and a damper d = 10 N·s/m, the force input ``f`` on the mass, the output ``y`` = the mass's position, which
starts at 0 and rests at 0.5 - spring.s_rel0 (-0.5 m in the export; the tests set s_rel0 = 0.5 m, so that
the mass starts at rest):

    m y'' = f(t) - c (y + 0.5) - d y'

With an interface element attached at ``f`` (the element between the mass and the ground, s = y, v = y', its
force F_el entering ``f`` with the sign -1), a measured force drive F(t) and the element's effect:

    m y'' = F(t) - c (y + 0.5) - d y' - F_el(y, y', element states)

F_el and its states are the equations of fmu/MODEL.md as tests/effects_reference.py writes them (scipy only;
none of fmusa's code and none of the coupling master's). Integrated by scipy LSODA at rtol 1e-10, piecewise
between the drive's knots.
"""
from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

import effects_reference as er

#: Mass_Damper's own parameters (start values of the export), but for the spring's unstretched length, set to
#: 0.5 m (``spring.s_rel0``, a parameter of the export) so that the mass rests at y = 0, where it starts
MASS, SPRING, DAMPER = 1.0, 1.0e4, 10.0
S_REL0 = 0.5
REST = 0.5 - S_REL0          # the spring is unstretched at s_rel = 1 - (y + 0.5) = s_rel0

#: The element's baseline in each case (in parallel with the model's spring-damper), and the effects' sizes
#: at this model's scale (displacements ~0.05 m, forces ~100 N).
BASE = {"c_y": 5.0e3, "d_y": 20.0}
CASES = {
    "none": {},
    "backlash_gap": {"gap": 0.02},
    "coulomb_friction": {"fric_F": 40.0, "fric_x": 2.0e-3},
    "yield_softening": {"yield_ratio": 0.3, "yield_F": 150.0},
    "nonlinear_stiffness": {"nl_ratio": 3.0, "nl_y_b": 0.03},
    "viscoelastic_relaxation": {"ve_k": 4.0e3, "ve_tau": 0.5},
    "interface_damage": {"dmg_y0": 0.03, "dmg_rate": 40.0, "dmg_F_res": 60.0},
}


def protocol(peak: float = 900.0, ramp: float = 0.5, hold: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """A force drive: load to ``peak`` over ``ramp``, hold, unload to -peak/2 (so the
    interface is also loaded the other way), hold, back to 0 (knots: time [s], force [N])."""
    t = np.cumsum([0.0, ramp, hold, 1.5 * ramp, hold, 0.5 * ramp, hold])
    u = np.array([0.0, peak, peak, -0.5 * peak, -0.5 * peak, 0.0, 0.0])
    return t, u


def simulate(element: dict, knots_t, knots_u, t_out, rtol: float = 1e-10) -> np.ndarray:
    """The mass's position y [m] at ``t_out`` under the force drive through the knots, with the element's
    parameters (catalogue names: c_y, d_y and the effect's)."""
    return simulate_on(element, knots_t, knots_u, t_out, MASS, SPRING, DAMPER, REST, rtol)


def simulate_on(element: dict, knots_t, knots_u, t_out, mass: float, spring: float, damper: float,
                rest: float = 0.0, rtol: float = 1e-10, atol_ve: float = 1e-8) -> np.ndarray:
    """The position at ``t_out`` of a mass (or inertia) on a spring and damper (at rest at 0, the spring's rest
    at ``rest``) with the element between it and the ground, under the drive through the knots: the equations
    of the module's text, for any such model (a rotational one in angle and torque). ``atol_ve``: the absolute
    tolerance of the Maxwell branch's force state."""
    p = er.full_params({**element, "m": mass})
    ax = er._Axial(p)
    kt, ku = np.asarray(knots_t, float), np.asarray(knots_u, float)
    t_out = np.asarray(t_out, float)
    x = np.zeros(6)                       # y, v, z_y, z_f, F_ve, kappa: all 0 at the start (y(0) = 0, at rest)
    out = np.zeros(t_out.size)
    atol = np.array([1e-12, 1e-10, 1e-10, 1e-10, atol_ve, 1e-12])
    for i in range(kt.size - 1):
        a, b = kt[i], kt[i + 1]
        k = (ku[i + 1] - ku[i]) / (b - a)

        def fun(t, s, a=a, u0=ku[i], k=k):
            y, v, zy, zf, Fve, kappa = s
            F_el = ax.total(y, v, zy, zf, Fve, kappa)
            acc = (u0 + k * (t - a) - spring * (y - rest) - damper * v - F_el) / mass
            dzy, dzf, dFve = ax.internal_rates(y, v, zy, zf, Fve)
            return [v, acc, dzy, dzf, dFve, ax.kappa_rate(y, v, kappa)]

        sel = (t_out > a) & (t_out <= b)
        sol = solve_ivp(fun, (a, b), x, method="LSODA", rtol=rtol, atol=atol, max_step=min(2e-3, b - a),
                        dense_output=bool(sel.any()))
        if not sol.success:
            raise RuntimeError(f"reference failed on [{a}, {b}]: {sol.message}")
        if sel.any():
            out[sel] = sol.sol(t_out[sel])[0]
        x = sol.y[:, -1].copy()
    return out


def synthesize(effect: str, rate_hz: float = 40.0, noise: float = 2.0e-4, seed: int = 0,
               **protocol_kw) -> tuple[pd.DataFrame, dict]:
    """A measured test (time, displacement = y, force = the drive) of the case ``effect``, with white noise
    of ``noise`` m on the displacement; and the element's true parameters. Every knot of the drive is a
    sample (at 40 Hz), so that the drive the samples give is the drive the reference ran."""
    truth = {**BASE, **CASES[effect]}
    kt, ku = protocol(**protocol_kw)
    t = np.arange(0.0, kt[-1] + 1e-9, 1.0 / rate_hz)
    y = simulate(truth, kt, ku, t)
    y = y + np.random.default_rng(seed).normal(0.0, noise, y.size)
    return pd.DataFrame({"time": t, "displacement": y, "force": np.interp(t, kt, ku)}), truth
