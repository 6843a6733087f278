"""Motion-driven mode (mode = 2, the paper's Section 2.3) of the real FMU.

y(t) is prescribed, F_pull is the reaction of the drive: F_pull = c_y y + d_y v_y + m a_y along the
imposed motion when nothing else moves (MODEL.md).  Checked to 1e-9 relative along the motion:
* y = v_pull t (default 2 mm/min), a_y = 0;
* use_y_in: y = y_in + y_in' (t - t_k) inside every communication step, with y_in set by setReal
  and y_in' by setRealInputDerivatives before each step;
* a stiffening force-displacement table (tab_n = 4): F_pull = F_tab(y) + d_y v_y, with linear
  extrapolation beyond the last point.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from fmu_run import FmuRunner, comm_grid
from reference import DEFAULTS, _Radau

REL = 1e-9
M = DEFAULTS["m"]
OUTS = ["y", "v_y", "a_y", "F_pull", "F_y", "x", "z", "alpha", "beta", "gamma", "v_x", "v_z",
        "w_alpha", "w_beta", "w_gamma"]
OTHERS = ["x", "z", "alpha", "beta", "gamma", "v_x", "v_z", "w_alpha", "w_beta", "w_gamma"]

# a stiffening, monotone table (N against m); beyond 3e-4 m it extrapolates with 1.8e6 N/m
TAB_Y = [0.0, 1e-4, 2e-4, 3e-4]
TAB_F = [0.0, 40.0, 120.0, 300.0]


def f_tab(y):
    y = np.asarray(y, dtype=float)
    ty, tf = np.array(TAB_Y), np.array(TAB_F)
    out = np.interp(y, ty, tf)
    lo, hi = y < ty[0], y > ty[-1]
    out = np.where(lo, tf[0] + (y - ty[0]) * (tf[1] - tf[0]) / (ty[1] - ty[0]), out)
    out = np.where(hi, tf[-1] + (y - ty[-1]) * (tf[-1] - tf[-2]) / (ty[-1] - ty[-2]), out)
    return out


def table_params():
    p = {"tab_n": len(TAB_Y)}
    for i, (yy, ff) in enumerate(zip(TAB_Y, TAB_F), start=1):
        p[f"tab_y[{i}]"] = yy
        p[f"tab_F[{i}]"] = ff
    return p


@pytest.fixture(scope="module")
def runner(fmu_path):
    r = FmuRunner(fmu_path)
    yield r
    r.close()


def _rel_err(got, want):
    scale = np.max(np.abs(want))
    assert scale > 0
    return np.max(np.abs(np.asarray(got) - want)) / scale


def _assert_others_zero(out):
    for k in OTHERS:
        assert np.all(out[k] == 0.0), (
            f"{k} moved in the axial motion: max {np.max(np.abs(out[k])):.3e}")


@pytest.mark.parametrize("c,d", [(DEFAULTS["c_y"], DEFAULTS["d_y"]), (25.0**5, 25.0**3),
                                 (25.0**7, 25.0**6)],
                         ids=["defaults", "c25^5-d25^3", "c25^7-d25^6"])
def test_constant_velocity_pull(runner, c, d):
    v_pull = DEFAULTS["v_pull"]
    assert v_pull == pytest.approx(2e-3 / 60, rel=1e-15)
    t = comm_grid(12.0, 0.25)
    out = runner.simulate({"mode": 2, "c_y": c, "d_y": d}, t, OUTS)
    y_ref = v_pull * t
    assert _rel_err(out["y"], y_ref) <= REL
    assert _rel_err(out["v_y"], np.full_like(t, v_pull)) <= REL
    assert np.all(np.abs(out["a_y"]) <= 1e-12), np.max(np.abs(out["a_y"]))
    F_ref = c * y_ref + d * v_pull
    assert _rel_err(out["F_pull"], F_ref) <= REL
    # the reaction from the FMU's own kinematics, and the element force (eq. 1 sign)
    F_own = c * out["y"] + d * out["v_y"] + M * out["a_y"]
    assert _rel_err(out["F_pull"], F_own) <= REL
    assert _rel_err(out["F_y"], c * out["y"] + d * out["v_y"]) <= REL
    _assert_others_zero(out)


def test_constant_velocity_pull_fine_grid_start(runner):
    """The first communication points: the drive starts at full speed from t = 0."""
    v_pull = DEFAULTS["v_pull"]
    t = comm_grid(0.01, 1e-4)
    out = runner.simulate({"mode": 2}, t, OUTS)
    c, d = DEFAULTS["c_y"], DEFAULTS["d_y"]
    assert _rel_err(out["y"], v_pull * t) <= REL
    assert _rel_err(out["F_pull"][1:], c * v_pull * t[1:] + d * v_pull) <= REL


def _input_fn(kind):
    A, f = 1e-4, 5.0
    w = 2 * math.pi * f

    def sine(tk):
        return {"y_in": A * math.sin(w * tk)}, {"y_in": A * w * math.cos(w * tk)}

    def quad(tk):
        # y = 1e-3 t + 5e-3 t^2, its derivative handed over as the input derivative
        return {"y_in": 1e-3 * tk + 5e-3 * tk * tk}, {"y_in": 1e-3 + 1e-2 * tk}

    def no_derivative(tk):
        return {"y_in": A * math.sin(w * tk)}, {}

    return {"sine": sine, "quadratic": quad, "no-derivative": no_derivative}[kind]


@pytest.mark.parametrize("kind", ["sine", "quadratic", "no-derivative"])
def test_follow_input_with_derivative(runner, kind):
    """use_y_in: inside each step y = y_in + y_in' (t - t_k); read at t_{k+1} before the next
    input is set, so y = y_k + y_k' h, v_y = y_k', a_y = 0 and F_pull = c_y y + d_y v_y."""
    fn = _input_fn(kind)
    t = comm_grid(0.2, 1e-3)
    out = runner.simulate({"mode": 2, "use_y_in": True}, t, OUTS, input_fn=fn)
    yk = np.array([fn(tk)[0]["y_in"] for tk in t[:-1]])
    vk = np.array([fn(tk)[1].get("y_in", 0.0) for tk in t[:-1]])
    y_exp = yk + vk * np.diff(t)
    c, d = DEFAULTS["c_y"], DEFAULTS["d_y"]
    assert _rel_err(out["y"][1:], y_exp) <= REL
    if np.any(vk):
        assert _rel_err(out["v_y"][1:], vk) <= REL
    else:
        assert np.all(out["v_y"][1:] == 0.0)
    assert np.all(np.abs(out["a_y"][1:]) <= 1e-12)
    F_exp = c * y_exp + d * vk
    assert _rel_err(out["F_pull"][1:], F_exp) <= REL
    F_own = c * out["y"] + d * out["v_y"] + M * out["a_y"]
    assert _rel_err(out["F_pull"][1:], F_own[1:]) <= REL
    _assert_others_zero(out)


def test_table_reaction_along_the_motion(runner):
    """tab_n = 4 stiffening table, constant-velocity pull through all segments and beyond the
    last point (linear extrapolation): F_pull = F_tab(y) + d_y v_y."""
    v_pull = DEFAULTS["v_pull"]
    d = DEFAULTS["d_y"]
    t = comm_grid(12.0, 0.1)
    out = runner.simulate(dict(table_params(), mode=2), t, OUTS)
    y_ref = v_pull * t
    assert y_ref[-1] > TAB_Y[-1]  # the extrapolation is exercised
    assert _rel_err(out["y"], y_ref) <= REL
    F_ref = f_tab(y_ref) + d * v_pull
    assert _rel_err(out["F_pull"], F_ref) <= REL
    assert _rel_err(out["F_y"], f_tab(out["y"]) + d * out["v_y"]) <= REL
    _assert_others_zero(out)


def test_table_force_driven_vs_radau(runner):
    """Force-driven pull (mode 1) on the table: m y'' + d_y y' + F_tab(y) = F(t), against scipy's
    Radau (the table's kinks need no special treatment: the right-hand side is Lipschitz)."""
    F_max, t_ramp, stop = 200.0, 0.05, 0.2
    d = DEFAULTS["d_y"]
    t = comm_grid(stop, 1e-3)

    def rhs(tt, s):
        F = F_max * min(tt / t_ramp, 1.0)
        return [s[1], (F - d * s[1] - float(f_tab(s[0]))) / M]

    segs = []
    s0 = [0.0, 0.0]
    for a, b in ((0.0, t_ramp), (t_ramp, stop)):
        sol = solve_ivp(rhs, (a, b), s0, method=_Radau, rtol=1e-11, atol=[1e-17, 1e-14],
                        dense_output=True)
        assert sol.success
        segs.append(sol)
        s0 = sol.y[:, -1]
    ref = np.where(t <= t_ramp, segs[0].sol(np.minimum(t, t_ramp)),
                   segs[1].sol(np.maximum(t, t_ramp)))
    out = runner.simulate(dict(table_params(), F_max=F_max, t_ramp=t_ramp, rtol=1e-10), t, OUTS)
    assert np.max(ref[0]) > TAB_Y[2]  # several table segments are crossed
    assert _rel_err(out["y"], ref[0]) <= 1e-6
    assert _rel_err(out["v_y"], ref[1]) <= 1e-6
