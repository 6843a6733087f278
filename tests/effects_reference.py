"""Independent scipy reference of the axial interface with the effects of ``fmu/MODEL.md``
("Effects beyond eq. 1"), and a generator of synthetic load-hold-unload data with one hidden effect.

Written from ``fmu/MODEL.md`` only, never from ``fmu/*.c``: an error in the FMU cannot hide itself
in data produced here.  numpy / scipy / pandas only.

Model (notation of MODEL.md; w = smooth_w, S(u) = w ln(1 + e^{u/w}), sigma(u) = S'(u), H(x) = [x > 0]):

* backlash:   y_e = S(y - gap) - S(-y - gap),  v_e = (sigma(y - gap) + sigma(-y - gap)) v
              (gap = 0: y_e = y, v_e = v exactly)
* spring:     F_s = k_lin + (nl_ratio - 1) c [S(y_e - nl_y_b) - S(-y_e - nl_y_b)],
              k_lin = yield_ratio c y_e + (1 - yield_ratio) yield_F z_y
              (yield_ratio = 1: k_lin = c y_e)
* yield:      z_y' = (v_e / y_Y) (1 - H(z_y v_e) z_y^4),  y_Y = yield_F / c
* friction:   F_f = fric_F z_f,  z_f' = (v / fric_x) (1 - H(z_f v) z_f^4)
* Maxwell:    F_ve' = ve_k v - F_ve / ve_tau
* damage:     kappa' = max(0, sgn(y_e) v_e) sigma(|y_e| - kappa)  (the largest |y_e| reached),
              D = 1 - exp(-dmg_rate S(kappa - dmg_y0)),
              F_s <- (1 - D) F_s + D dmg_F_res y_e / (dmg_y0 + S(kappa - dmg_y0))
* total:      F_y = F_s + d v + F_f + F_ve

Drive modes
* ``"displacement"``: y(t) piecewise linear through knots (v constant between knots, y'' = 0), states
  (z_y, z_f, F_ve); predicted measurement F_meas = F_y + F_offset.  At a knot time the output is the
  left limit (velocity of the segment that ends there; v = 0 at t = 0), which is what a
  co-simulation reads at the end of a communication step.  With damage a fourth state kappa.
* ``"force"``: F(t) piecewise linear through knots, m y'' = F(t) - F_y, states
  (y, v, z_y, z_f, F_ve); predicted measurement y_meas = y + y_offset.

Integration: scipy LSODA (default) or Radau, both with the analytic Jacobian, rtol 1e-10 and per-state
absolute tolerances, integrated piecewise between the knots of the drive (its kinks are never stepped
over; every segment restarts exactly from the end state of the previous one), max_step 0.01 s so that
the softplus corners (width w = 1 um) inside a segment are resolved.  The problem is stiff (an
eigenvalue near -d/m ~ -1e6 1/s; friction adds a pre-sliding stiffness fric_F/fric_x).  LSODA is
the default because Radau can stall when friction sticks in a force-driven hold: the velocity decays
to round-off, its sign flips, H(z_f v) switches the Jacobian entry dz_f'/dv between ~0 and 1/fric_x
and Radau's simplified Newton iteration stops converging.  Self-convergence (rtol 1e-12,
max_step 1e-3) of the defaults: <= 1.2e-9 of the peak over 6 random cases per effect and drive;
a force-driven case takes ~0.1 s, a displacement-driven one ~0.02 s.

Generator ranges (``draw_case``) and why
* baseline c_y log-uniform [1e5, 4e5] N/m, d_y uniform [50, 500] N s/m, m = 0.00029 kg.
* protocol: ramp 0 -> peak over T_load in [0.5, 2] s, hold T_hold in [1, 3] s, ramp to 0 over
  T_load, hold T_hold / 2; peak 0.8-1.5 mm (displacement drive) or 150-300 N (force drive); 100 Hz.
  "peak force" / "peak displacement" below mean the linear (effect-free) peak response:
  F_lin = c y_peak (displacement drive), y_lin = F_peak / c (force drive).
* backlash_gap: gap = (0.1-0.3) y_lin or y_peak.
* nonlinear_stiffness: nl_ratio in [0.4, 0.7] or [1.5, 3] (either branch with probability 1/2),
  nl_y_b = (0.2-0.5) peak displacement.
* yield_softening: yield_ratio [0.1, 0.5], yield_F = (0.3-0.6) linear peak force.
* coulomb_friction: fric_F = (0.05-0.15) linear peak force, fric_x default (1e-5 m).
* viscoelastic_relaxation: ve_k = (0.3-1.0) c_y, ve_tau = (0.2-1.0) T_hold.
* interface_damage: displacement drive: dmg_y0 = (0.35-0.55) y_peak, dmg_rate = (1.5-3) / (y_peak -
  dmg_y0) (the force drops past a peak), dmg_F_res = (0.15-0.35) c dmg_y0; force drive: dmg_y0 =
  (0.3-0.5) y_lin, dmg_rate = (0.2-0.35) / y_lin, dmg_F_res = (0.2-0.5) F_peak (the softened curve
  still rises to the peak force, whose largest value is at y = 1/dmg_rate + dmg_F_res/c_y).
* sensor_offset: F_offset (displacement drive) or y_offset (force drive) = +-(0.03-0.1) of the
  linear peak response.
The ranges of the brief were kept.  Visibility was measured by fitting the effect-free model (best
c_y, d_y, by linear least squares in displacement drive and by least squares on the exact linear
response in force drive) to the clean data of 40 random cases per effect and drive: the misfit RMS
in units of the noise sigma (0.5 % of the peak) is, smallest over the 40 / median:
  displacement drive: gap 6.1/15, nonlinear 5.2/8.8, yield 23/40, friction 5.0/9.9,
                      viscoelastic 5.4/18, offset 3.5/8.5 (largest residual >= 6.3 sigma);
  force drive:        gap 9.5/19, nonlinear 4.7/9.2, yield 21/47, friction 6.5/17,
                      viscoelastic 9.1/24, offset 3.5/8.5.
So no range had to be narrowed (``tests/test_effects_reference.py::test_every_effect_is_visible``
keeps this honest: RMS > 2 sigma and a residual > 5 sigma on every draw it checks).  Notes: with
Coulomb friction on constant-speed ramps a larger damping mimics the friction on the ramps, but not
in the holds, where the friction force sticks and the damping force vanishes (that is where the
effect shows); in force drive d_y is nearly unidentifiable (d/c <= 5 ms against ramps of 0.5-2 s)
and the visible part of each effect is its displacement signature (shift by the gap, creep in the
hold, residual set, ...).  The smallest effect is a 3 % sensor offset (6 sigma at the unloaded
ends, partly absorbed by c_y).  Visible against the baseline does not mean distinguishable from
every other effect: e.g. softening nonlinear stiffness and yield look alike on the loading ramp
and differ on unloading only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp
from scipy.integrate._ivp.radau import Radau
from scipy.special import expit

__all__ = ["DEFAULTS", "DRIVES", "EFFECTS", "MAIN_PARAMETER", "Protocol", "simulate", "make_protocol",
           "main_parameter",
           "draw_case", "synthesize", "synthesize_protocol", "full_params", "PROTOCOLS"]

#: MODEL.md / modelica/ScrewVertebra.mo defaults of every parameter used here (effects off; checked against
#: the contract by tests/test_effects_reference.py).
DEFAULTS = {
    "m": 0.00029, "c_y": 823224.0, "d_y": 488.0,
    "gap": 0.0, "nl_ratio": 1.0, "nl_y_b": 0.0005, "yield_ratio": 1.0, "yield_F": 100.0,
    "fric_F": 0.0, "fric_x": 1e-5, "ve_k": 0.0, "ve_tau": 1.0, "F_offset": 0.0, "y_offset": 0.0,
    "smooth_w": 1e-6, "dmg_rate": 0.0, "dmg_y0": 0.0005, "dmg_F_res": 0.0,
}

EFFECTS = ("none", "backlash_gap", "nonlinear_stiffness", "yield_softening", "coulomb_friction",
           "viscoelastic_relaxation", "sensor_offset", "interface_damage")

#: main parameter of every effect (sensor_offset: depends on the drive, see ``main_parameter``)
MAIN_PARAMETER = {"none": None, "backlash_gap": "gap", "nonlinear_stiffness": "nl_ratio",
                  "yield_softening": "yield_F", "coulomb_friction": "fric_F",
                  "viscoelastic_relaxation": "ve_tau", "interface_damage": "dmg_F_res",
                  "sensor_offset": {"displacement": "F_offset", "force": "y_offset"}}

DRIVES = ("displacement", "force")
SAMPLE_RATE = 100.0


def main_parameter(effect: str, drive: str):
    mp = MAIN_PARAMETER[effect]
    return mp[drive] if isinstance(mp, dict) else mp


def full_params(params: dict) -> dict:
    unknown = set(params) - set(DEFAULTS)
    if unknown:
        raise KeyError(f"unknown parameters {sorted(unknown)}")
    p = dict(DEFAULTS)
    p.update({k: float(v) for k, v in params.items()})
    return p


class _Radau(Radau):
    """Radau with Hairer's Newton tolerance (0.03 of the error scale) instead of scipy's
    sqrt(rtol)-based one, which at rtol 1e-10 sits near round-off and makes Newton stall."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.newton_tol = 0.03


class _Axial:
    """Constitutive part of the axial interface (shared by both drive modes)."""

    def __init__(self, p: dict):
        self.p = p
        self.c, self.d, self.m = p["c_y"], p["d_y"], p["m"]
        self.w = p["smooth_w"]
        self.gap = p["gap"]
        self.has_gap = p["gap"] != 0.0
        self.has_nl = p["nl_ratio"] != 1.0
        self.has_yield = p["yield_ratio"] != 1.0
        self.has_fric = p["fric_F"] != 0.0
        self.has_ve = p["ve_k"] != 0.0
        self.y_Y = p["yield_F"] / self.c
        self.has_dmg = p["dmg_rate"] != 0.0

    def S(self, u):
        return self.w * np.logaddexp(0.0, u / self.w)

    def sig(self, u):
        return expit(u / self.w)

    def elastic(self, y, v):
        if not self.has_gap:
            return y, v
        g = self.gap
        return (self.S(y - g) - self.S(-y - g), (self.sig(y - g) + self.sig(-y - g)) * v)

    def spring(self, ye, zy):
        p, c = self.p, self.c
        if self.has_yield:
            F = p["yield_ratio"] * c * ye + (1.0 - p["yield_ratio"]) * p["yield_F"] * zy
        else:
            F = c * ye
        if self.has_nl:
            yb = p["nl_y_b"]
            F = F + (p["nl_ratio"] - 1.0) * c * (self.S(ye - yb) - self.S(-ye - yb))
        return F

    def damaged(self, ye, Fs, kappa):
        """(1 - D) F_s + D F_res y_e / (y0 + S(kappa - y0)) and D, of the largest |y_e| reached."""
        if not self.has_dmg:
            return Fs, 0.0 * Fs
        p = self.p
        past = self.S(kappa - p["dmg_y0"])
        D = 1.0 - np.exp(-p["dmg_rate"] * past)
        return (1.0 - D) * Fs + D * p["dmg_F_res"] * ye / (p["dmg_y0"] + past), D

    def kappa_rate(self, y, v, kappa):
        if not self.has_dmg:
            return 0.0 * v
        ye, ve = self.elastic(y, v)
        sv = np.where(ye >= 0.0, ve, -ve)
        return np.where(sv > 0.0, sv, 0.0) * self.sig(np.abs(ye) - kappa)

    def total(self, y, v, zy, zf, Fve, kappa=0.0):
        ye, _ = self.elastic(y, v)
        Fs, _ = self.damaged(ye, self.spring(ye, zy), kappa)
        return Fs + self.d * v + self.p["fric_F"] * zf + Fve

    def jacobian_force(self, y, v, zy, zf, Fve):
        """Analytic Jacobian of the force-drive right-hand side (states y, v, z_y, z_f, F_ve)."""
        p, c, w = self.p, self.c, self.w
        J = np.zeros((5, 5))
        if self.has_gap:
            g = self.gap
            s1, s2 = self.sig(y - g), self.sig(-y - g)
            sg = s1 + s2
            dve_dy = (s1 * (1.0 - s1) - s2 * (1.0 - s2)) / w * v
        else:
            sg, dve_dy = 1.0, 0.0
        ye, ve = self.elastic(y, v)
        yr = p["yield_ratio"] if self.has_yield else 1.0
        dFs_dye = yr * c
        if self.has_nl:
            yb = p["nl_y_b"]
            dFs_dye += (p["nl_ratio"] - 1.0) * c * (self.sig(ye - yb) + self.sig(-ye - yb))
        J[0, 1] = 1.0
        J[1, 0] = -dFs_dye * sg / self.m
        J[1, 1] = -self.d / self.m
        J[1, 2] = -((1.0 - yr) * p["yield_F"] if self.has_yield else 0.0) / self.m
        J[1, 3] = -p["fric_F"] / self.m
        J[1, 4] = -1.0 / self.m
        if self.has_yield:
            h = 1.0 if zy * ve > 0.0 else 0.0
            f = 1.0 - h * zy ** 4
            J[2, 0] = dve_dy / self.y_Y * f
            J[2, 1] = sg / self.y_Y * f
            J[2, 2] = -(ve / self.y_Y) * h * 4.0 * zy ** 3
        if self.has_fric:
            fx = p["fric_x"]
            h = 1.0 if zf * v > 0.0 else 0.0
            J[3, 1] = (1.0 - h * zf ** 4) / fx
            J[3, 3] = -(v / fx) * h * 4.0 * zf ** 3
        if self.has_ve:
            J[4, 1] = p["ve_k"]
            J[4, 4] = -1.0 / p["ve_tau"]
        return J

    def jacobian_force_damage(self, y, v, zy, zf, Fve, kappa):
        """The force-drive Jacobian with damage (states y, v, z_y, z_f, F_ve, kappa): the undamaged one
        with the spring's row scaled by 1 - D and the entries of kappa."""
        p, w, m = self.p, self.w, self.m
        J = np.zeros((6, 6))
        J[:5, :5] = self.jacobian_force(y, v, zy, zf, Fve)
        ye, ve = self.elastic(y, v)
        if self.has_gap:
            g = self.gap
            s1, s2 = self.sig(y - g), self.sig(-y - g)
            sg = s1 + s2
            dve_dy = (s1 * (1.0 - s1) - s2 * (1.0 - s2)) / w * v
        else:
            sg, dve_dy = 1.0, 0.0
        y0, r, Fr = p["dmg_y0"], p["dmg_rate"], p["dmg_F_res"]
        P = self.S(kappa - y0)
        sp = self.sig(kappa - y0)
        E = math.exp(-r * P)
        D = 1.0 - E
        Fs = self.spring(ye, zy)
        J[1, 0] = (1.0 - D) * J[1, 0] - D * Fr * sg / ((y0 + P) * m)
        J[1, 2] = (1.0 - D) * J[1, 2]
        dF_dk = r * E * sp * (-Fs + Fr * ye / (y0 + P)) - D * Fr * ye * sp / (y0 + P) ** 2
        J[1, 5] = -dF_dk / m
        sgn = 1.0 if ye >= 0.0 else -1.0
        sv = sgn * ve
        if sv > 0.0:
            q = self.sig(abs(ye) - kappa)
            dq = q * (1.0 - q) / w
            J[5, 0] = sgn * dve_dy * q + sv * dq * sgn * sg
            J[5, 1] = sgn * sg * q
            J[5, 5] = -sv * dq
        return J

    def jacobian_disp(self, y, v, zy, zf, Fve):
        """Analytic Jacobian of the displacement-drive right-hand side (z_y, z_f, F_ve)."""
        J = np.zeros((3, 3))
        if self.has_yield:
            _, ve = self.elastic(y, v)
            h = 1.0 if zy * ve > 0.0 else 0.0
            J[0, 0] = -(ve / self.y_Y) * h * 4.0 * zy ** 3
        if self.has_fric:
            h = 1.0 if zf * v > 0.0 else 0.0
            J[1, 1] = -(v / self.p["fric_x"]) * h * 4.0 * zf ** 3
        if self.has_ve:
            J[2, 2] = -1.0 / self.p["ve_tau"]
        return J

    def internal_rates(self, y, v, zy, zf, Fve):
        """(z_y', z_f', F_ve')"""
        p = self.p
        dzy = dzf = dFve = 0.0 * v
        if self.has_yield:
            _, ve = self.elastic(y, v)
            dzy = (ve / self.y_Y) * (1.0 - np.where(zy * ve > 0.0, 1.0, 0.0) * zy ** 4)
        if self.has_fric:
            dzf = (v / p["fric_x"]) * (1.0 - np.where(zf * v > 0.0, 1.0, 0.0) * zf ** 4)
        if self.has_ve:
            dFve = p["ve_k"] * v - Fve / p["ve_tau"]
        return dzy, dzf, dFve


def _segments(knots_t, knots_u):
    kt = np.asarray(knots_t, dtype=float)
    ku = np.asarray(knots_u, dtype=float)
    if kt.ndim != 1 or kt.shape != ku.shape or kt.size < 2:
        raise ValueError("knots_t and knots_u: 1-D, same length >= 2")
    if kt[0] != 0.0 or np.any(np.diff(kt) <= 0.0):
        raise ValueError("knots_t must start at 0 and increase strictly")
    return kt, ku, np.diff(ku) / np.diff(kt)


def simulate(params: dict, drive: str, knots_t, knots_u, t_out, *, rtol: float = 1e-10,
             max_step: float = 0.01, method: str = "LSODA", return_states: bool = False):
    """Predicted measured channel at the times t_out (within [0, knots_t[-1]]).

    params: FMU names in SI (c_y, d_y, m and the effect parameters; missing ones at the MODEL.md
    defaults).  drive "displacement": knots_u are displacements y [m], returns F_meas [N];
    drive "force": knots_u are forces F [N], returns y_meas [m].
    method: "LSODA" (default) or "Radau" (scipy's Radau with Hairer's Newton tolerance); a force drive
    with damage always takes Radau.
    With return_states, also returns a dict of the states (and v, F_y) at t_out."""
    if method not in ("LSODA", "Radau"):
        raise ValueError("method: LSODA or Radau")
    if drive not in DRIVES:
        raise ValueError(f"drive must be one of {DRIVES}")
    p = full_params(params)
    ax = _Axial(p)
    kt, ku, slopes = _segments(knots_t, knots_u)
    if ax.has_dmg and drive == "force":
        # LSODA takes ~1e5 steps on a damaging ramp (it measured 375 000 on a 2 s ramp against Radau's 718)
        method = "Radau"
    t_out = np.asarray(t_out, dtype=float)
    if t_out.ndim != 1 or np.any(t_out < 0.0) or np.any(t_out > kt[-1] * (1 + 1e-12)):
        raise ValueError("t_out must lie within [0, knots_t[-1]]")
    n_st = (3 if drive == "displacement" else 5) + (1 if ax.has_dmg else 0)   # kappa last, with damage
    states = np.zeros((n_st, t_out.size))
    vel = np.zeros(t_out.size)  # displacement drive: left-limit drive velocity at t_out

    if drive == "displacement":
        scale_F = max(ax.c * np.max(np.abs(ku)), 1.0)
        atol = np.array([1e-11, 1e-11, 1e-11 * scale_F] + ([1e-12] if ax.has_dmg else []))
    else:
        y_scale = max(np.max(np.abs(ku)) / ax.c, 1e-9)
        # v: an absolute floor well above round-off (1e-9 y_scale per second): a tighter one lets
        # the sign of a vanishing velocity in a hold chatter, which switches H(z v) and stalls
        # Radau when friction sticks
        atol = np.array([1e-11 * y_scale, 1e-9 * y_scale, 1e-10, 1e-10,
                         1e-10 * max(np.max(np.abs(ku)), 1.0)] + ([1e-11 * y_scale] if ax.has_dmg else []))

    s = np.zeros(n_st)
    # t = 0: all states at rest, v = 0
    sel0 = t_out == 0.0
    for i in range(kt.size - 1):
        a, b, u0, k = kt[i], kt[i + 1], ku[i], slopes[i]
        if drive == "displacement":
            def fun(t, x, a=a, u0=u0, k=k):
                y = u0 + k * (t - a)
                rates = list(ax.internal_rates(y, k, x[0], x[1], x[2]))
                if ax.has_dmg:
                    rates.append(ax.kappa_rate(y, k, x[3]))
                return np.array(rates, dtype=float)

            def jac(t, x, a=a, u0=u0, k=k):
                return ax.jacobian_disp(u0 + k * (t - a), k, x[0], x[1], x[2])
        else:
            def fun(t, x, a=a, u0=u0, k=k):
                y, v, zy, zf, Fve = x[:5]
                kappa = x[5] if ax.has_dmg else 0.0
                F = u0 + k * (t - a)
                acc = (F - ax.total(y, v, zy, zf, Fve, kappa)) / ax.m
                dzy, dzf, dFve = ax.internal_rates(y, v, zy, zf, Fve)
                rates = [v, acc, dzy, dzf, dFve] + ([ax.kappa_rate(y, v, kappa)] if ax.has_dmg else [])
                return np.array(rates, dtype=float)

            def jac(t, x):
                return ax.jacobian_force_damage(*x) if ax.has_dmg else ax.jacobian_force(*x)
        sel = (t_out > a) & (t_out <= b)
        if i == kt.size - 2:
            sel |= (t_out > b)  # rounding at the very end
        te = np.clip(t_out[sel], a, b)
        if ax.has_dmg and drive == "displacement":   # kappa's entry by LSODA's finite differences
            jac = None
        if drive == "displacement" and not (ax.has_yield or ax.has_fric or ax.has_ve or ax.has_dmg):
            # no internal state is active: nothing to integrate
            xs = np.zeros((n_st, te.size))
            s_end = s
        else:
            sol = solve_ivp(fun, (a, b), s, method=_Radau if method == "Radau" else "LSODA",
                            rtol=rtol, atol=atol, jac=jac,
                            max_step=min(max_step, b - a), dense_output=te.size > 0)
            if not sol.success:
                raise RuntimeError(f"Radau failed on [{a}, {b}]: {sol.message}")
            xs = sol.sol(te) if te.size else np.zeros((n_st, 0))
            # the dense output at the very end point equals the step end; keep it exact
            xs[:, te == b] = sol.y[:, -1:]
            s_end = sol.y[:, -1].copy()
        states[:, sel] = xs
        vel[sel] = k
        s = s_end
    vel[sel0] = 0.0

    if drive == "displacement":
        y = np.interp(t_out, kt, ku)
        zy, zf, Fve = states[:3]
        v = vel
    else:
        y, v, zy, zf, Fve = states[:5]
    kappa = states[-1] if ax.has_dmg else np.zeros_like(y)
    Fy = ax.total(y, v, zy, zf, Fve, kappa)
    out = Fy + p["F_offset"] if drive == "displacement" else y + p["y_offset"]
    if return_states:
        ye, _ = ax.elastic(y, v)
        _, D = ax.damaged(ye, ax.spring(ye, zy), kappa)
        return out, {"y": y, "v": v, "z_y": zy, "z_f": zf, "F_ve": Fve, "F_y": Fy,
                     "F_fric": p["fric_F"] * zf, "kappa": kappa, "dmg_D": D}
    return out


@dataclass
class Protocol:
    """A load-hold-unload protocol: piecewise-linear drive through (knots_t, knots_u)."""
    drive: str
    peak: float
    T_load: float
    T_hold: float
    knots_t: np.ndarray = field(repr=False)
    knots_u: np.ndarray = field(repr=False)
    t_out: np.ndarray = field(repr=False)

    @property
    def t_end(self) -> float:
        return float(self.knots_t[-1])

    def drive_at(self, t):
        return np.interp(t, self.knots_t, self.knots_u)


def make_protocol(drive: str, rng: np.random.Generator, *, peak: float | None = None,
                  T_load: float | None = None, T_hold: float | None = None,
                  rate: float = SAMPLE_RATE, hold: bool = True, unload: bool = True) -> Protocol:
    """Load-hold-unload: 0 -> peak over T_load, hold T_hold, peak -> 0 over T_load, hold T_hold/2.

    Random (uniform) unless given: peak 0.8-1.5 mm (displacement drive) or 150-300 N (force
    drive), T_load in [0.5, 2] s, T_hold in [1, 3] s.  t_out: samples k/rate up to the end.
    Without ``hold`` no phase holds still (the ramps meet at the peak, the test ends at zero); without
    ``unload`` the test ends at the peak (after its hold, if any).  The random draws are the same
    whatever the options, so one seed gives the same case under every protocol."""
    if drive not in DRIVES:
        raise ValueError(f"drive must be one of {DRIVES}")
    if peak is None:
        peak = rng.uniform(0.8e-3, 1.5e-3) if drive == "displacement" else rng.uniform(150, 300)
    if T_load is None:
        T_load = rng.uniform(0.5, 2.0)
    if T_hold is None:
        T_hold = rng.uniform(1.0, 3.0)
    knots_t, knots_u = [0.0, T_load], [0.0, peak]
    if hold:
        knots_t.append(knots_t[-1] + T_hold)
        knots_u.append(peak)
    if unload:
        knots_t.append(knots_t[-1] + T_load)
        knots_u.append(0.0)
        if hold:
            knots_t.append(knots_t[-1] + T_hold / 2.0)
            knots_u.append(0.0)
    knots_t, knots_u = np.array(knots_t), np.array(knots_u)
    t4 = float(knots_t[-1])
    n = int(math.floor(t4 * rate + 1e-9))
    t_out = np.arange(n + 1) / rate
    return Protocol(drive, float(peak), float(T_load), float(T_hold), knots_t, knots_u, t_out)


def _u(rng, lo, hi):
    return float(rng.uniform(lo, hi))


def draw_case(effect: str, drive: str, rng: np.random.Generator, *, hold: bool = True, unload: bool = True):
    """(params, protocol, main_parameter_name) of one random case with the given hidden effect."""
    if effect not in EFFECTS:
        raise ValueError(f"effect must be one of {EFFECTS}")
    proto = make_protocol(drive, rng, hold=hold, unload=unload)
    c = float(math.exp(rng.uniform(math.log(1e5), math.log(4e5))))
    d = _u(rng, 50.0, 500.0)
    params = {"c_y": c, "d_y": d, "m": DEFAULTS["m"]}
    if drive == "displacement":
        y_pk = proto.peak                 # peak displacement
        F_pk = c * proto.peak             # linear peak force
    else:
        F_pk = proto.peak
        y_pk = proto.peak / c             # linear peak displacement
    if effect == "backlash_gap":
        params["gap"] = _u(rng, 0.1, 0.3) * y_pk
    elif effect == "nonlinear_stiffness":
        params["nl_ratio"] = _u(rng, 0.4, 0.7) if rng.random() < 0.5 else _u(rng, 1.5, 3.0)
        params["nl_y_b"] = _u(rng, 0.2, 0.5) * y_pk
    elif effect == "yield_softening":
        params["yield_ratio"] = _u(rng, 0.1, 0.5)
        params["yield_F"] = _u(rng, 0.3, 0.6) * F_pk
    elif effect == "coulomb_friction":
        params["fric_F"] = _u(rng, 0.05, 0.15) * F_pk
    elif effect == "viscoelastic_relaxation":
        params["ve_k"] = _u(rng, 0.3, 1.0) * c
        params["ve_tau"] = _u(rng, 0.2, 1.0) * proto.T_hold
    elif effect == "interface_damage":
        if drive == "displacement":
            # onset before the peak, softening past it that drops the force towards the residual
            params["dmg_y0"] = _u(rng, 0.35, 0.55) * y_pk
            params["dmg_rate"] = _u(rng, 1.5, 3.0) / (y_pk - params["dmg_y0"])
            params["dmg_F_res"] = _u(rng, 0.15, 0.35) * c * params["dmg_y0"]
        else:
            # under a force drive the softened curve must still rise to the peak force (else the screw
            # runs away): its maximum is at y = 1/dmg_rate + dmg_F_res/c, above F_pk for these ranges
            params["dmg_y0"] = _u(rng, 0.3, 0.5) * y_pk
            params["dmg_rate"] = _u(rng, 0.2, 0.35) / y_pk
            params["dmg_F_res"] = _u(rng, 0.2, 0.5) * F_pk
    elif effect == "sensor_offset":
        sign = 1.0 if rng.random() < 0.5 else -1.0
        if drive == "displacement":
            params["F_offset"] = sign * _u(rng, 0.03, 0.1) * F_pk
        else:
            params["y_offset"] = sign * _u(rng, 0.03, 0.1) * y_pk
    return params, proto, main_parameter(effect, drive)


def synthesize(effect: str, drive: str, seed: int, noise_rel: float = 0.005):
    """Synthetic measurement with one hidden effect.

    Returns (DataFrame[time, displacement, force] in s, m, N; truth dict).  The drive channel is
    exact; Gaussian noise of noise_rel x max|predicted channel| is added to the predicted channel
    (force in displacement drive, displacement in force drive)."""
    rng = np.random.default_rng(seed)
    params, proto, main = draw_case(effect, drive, rng)
    clean = simulate(params, drive, proto.knots_t, proto.knots_u, proto.t_out)
    sigma = noise_rel * float(np.max(np.abs(clean)))
    noisy = clean + rng.normal(0.0, sigma, clean.size)
    u = proto.drive_at(proto.t_out)
    if drive == "displacement":
        df = pd.DataFrame({"time": proto.t_out, "displacement": u, "force": noisy})
    else:
        df = pd.DataFrame({"time": proto.t_out, "displacement": noisy, "force": u})
    truth = {"effect": effect, "drive": drive, "seed": seed, "params": params,
             "main_parameter": main, "main_value": params.get(main) if main else None,
             "noise_rel": noise_rel, "noise_sigma": sigma, "clean": clean,
             "knots_t": proto.knots_t, "knots_u": proto.knots_u,
             "T_load": proto.T_load, "T_hold": proto.T_hold, "peak": proto.peak}
    return df, truth


#: Protocol options of real tests: (several rates, hold, unloading), by name.
PROTOCOLS = {
    "ramp": (False, False, False),
    "ramp-hold": (False, True, False),
    "load-unload": (False, False, True),
    "load-hold-unload": (False, True, True),
    "ramps, 2 rates": (True, False, False),
    "ramp-hold, 2 rates": (True, True, False),
    "load-unload, 2 rates": (True, False, True),
    "load-hold-unload, 2 rates": (True, True, True),
}

#: the second rate of a several-rate protocol: its ramps take T_load / RATE_FACTOR
RATE_FACTOR = 5.0


def synthesize_protocol(effect: str, drive: str, seed: int, protocol: str = "load-hold-unload",
                        noise_rel: float = 0.005):
    """Synthetic tests of one specimen (one hidden effect, one parameter set) under a named protocol
    of ``PROTOCOLS``: one test, or two at rates RATE_FACTOR apart.  The case is the one ``synthesize``
    draws for the same seed (same parameters, peak, T_load, T_hold); only the protocol changes.

    Returns (list of DataFrame[time, displacement, force], truth dict as ``synthesize``, with
    ``protocol``)."""
    several, hold, unload = PROTOCOLS[protocol]
    rng = np.random.default_rng(seed)
    params, proto, main = draw_case(effect, drive, rng, hold=hold, unload=unload)
    protos = [proto]
    if several:
        protos.append(make_protocol(drive, rng, peak=proto.peak, T_load=proto.T_load / RATE_FACTOR,
                                    T_hold=proto.T_hold, hold=hold, unload=unload))
    cleans = [simulate(params, drive, p.knots_t, p.knots_u, p.t_out) for p in protos]
    sigma = noise_rel * max(float(np.max(np.abs(c))) for c in cleans)
    frames = []
    for p, clean in zip(protos, cleans):
        noisy = clean + rng.normal(0.0, sigma, clean.size)
        u = p.drive_at(p.t_out)
        if drive == "displacement":
            frames.append(pd.DataFrame({"time": p.t_out, "displacement": u, "force": noisy}))
        else:
            frames.append(pd.DataFrame({"time": p.t_out, "displacement": noisy, "force": u}))
    truth = {"effect": effect, "drive": drive, "seed": seed, "protocol": protocol, "params": params,
             "main_parameter": main, "main_value": params.get(main) if main else None,
             "noise_rel": noise_rel, "noise_sigma": sigma, "T_load": proto.T_load, "T_hold": proto.T_hold,
             "peak": proto.peak}
    return frames, truth
