"""Self-checks of the independent references in tests/reference.py (no FMU involved).

They keep the references honest: the closed form is checked against the ODE itself, its initial
conditions, elementary special-case formulas and scipy's Radau; the monitors against dense
sampling; the 6-DOF equations against kinematic identities, energy and momentum conservation and
the exact axial decoupling.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from reference import (
    SIX_DOF_NAMES,
    _Radau,
    Axial,
    axial_closed_form,
    axial_monitors,
    cardan_G,
    cardan_Gdot,
    cardan_R,
    make_params,
    six_dof_energy,
    six_dof_momentum,
    six_dof_radau,
    six_dof_rhs,
    skew,
)

M = 2.9e-4
F_MAX, T_RAMP = 411.0, 0.05


def _F(t, F_max=F_MAX, t_ramp=T_RAMP):
    return F_max * np.minimum(np.asarray(t) / t_ramp, 1.0)


# ------------------------------------------------------------------------------- axial closed form
EXTREME_CASES = [
    (823224.0, 488.0),  # paper optimum, overdamped
    (6.1e9, 1.0),  # stiffest, almost undamped: 1e5 oscillations in 0.2 s
    (6.1e9, 2.44e8),  # eigenvalues -25 and -8.4e11
    (1e3, 2.44e8),  # eigenvalues -4.1e-6 and -8.4e11
    (1e3, 1.0),
    (25.0**7, 25.0**2),
    (8.2e5, 0.0),  # undamped
    (0.0, 488.0),  # no spring
    (0.0, 0.0),  # free mass
    (1e6, 2.0 * math.sqrt(M * 1e6)),  # (nearly) critical in double precision
]


@pytest.mark.parametrize("c,d", EXTREME_CASES, ids=[f"c{c:.4g}-d{d:.4g}" for c, d in EXTREME_CASES])
def test_closed_form_satisfies_ode(c, d):
    """m a + d v + c y = F(t) at every point, each term being exact to ~1e-13 of the largest."""
    t = np.concatenate([np.linspace(0.0, 0.2, 201), [1e-9, 0.05 - 1e-12, 0.05 + 1e-12, 0.0501]])
    y, v, a = axial_closed_form(M, c, d, F_MAX, T_RAMP, t)
    res = M * a + d * v + c * y - _F(t)
    scale = np.maximum.reduce([np.abs(M * a), np.abs(d * v), np.abs(c * y), _F(t)]) + 1e-300
    ok = np.abs(res) <= 1e-12 * np.maximum(scale, 1e-3 * F_MAX)
    assert np.all(ok), np.max(np.abs(res) / scale)


@pytest.mark.parametrize("c,d", EXTREME_CASES, ids=[f"c{c:.4g}-d{d:.4g}" for c, d in EXTREME_CASES])
def test_closed_form_initial_conditions(c, d):
    """From rest: y ~ k t^3/(6m), v ~ k t^2/(2m), a ~ k t/m for t -> 0 (k = F_max/t_ramp)."""
    k = F_MAX / T_RAMP
    ax = Axial(M, c, d, F_MAX, T_RAMP)
    # far below every time scale of the case (the fastest is m/d, 1/sqrt(c/m))
    t = 1e-6 * min(M / d if d else 1.0, math.sqrt(M / c) if c else 1.0, 1.0)
    y, v, a = ax.eval(t)
    assert y == pytest.approx(k * t**3 / (6 * M), rel=1e-5)
    assert v == pytest.approx(k * t**2 / (2 * M), rel=1e-5)
    assert a == pytest.approx(k * t / M, rel=1e-5)
    assert ax.eval(0.0) == (0.0, 0.0, 0.0)


def test_closed_form_elementary_special_cases():
    t = np.linspace(0.0, 0.2, 401)
    k = F_MAX / T_RAMP
    # free mass: y = k t^3/(6m) on the ramp, then the superposition of two cubic ramps
    y, v, a = axial_closed_form(M, 0.0, 0.0, F_MAX, T_RAMP, t)
    tau = np.maximum(t - T_RAMP, 0.0)
    np.testing.assert_allclose(y, k * (t**3 - tau**3) / (6 * M), rtol=1e-13)
    np.testing.assert_allclose(v, k * (t**2 - tau**2) / (2 * M), rtol=1e-13)
    # undamped: y = k/c (t - sin(w t)/w) - same for the second ramp
    c = 8.2e5
    w = math.sqrt(c / M)
    y, v, a = axial_closed_form(M, c, 0.0, F_MAX, T_RAMP, t)

    def Yu(s):
        s = np.maximum(s, 0.0)
        return (s - np.sin(w * s) / w) / c

    np.testing.assert_allclose(y, k * (Yu(t) - Yu(t - T_RAMP)), rtol=1e-9, atol=1e-12 * np.max(y))
    # no spring: y = k/d (t^2/2 - (m/d) t + (m/d)^2 (1 - e^{-d t/m}))
    d = 488.0
    mu = M / d

    def Yd(s):
        s = np.maximum(s, 0.0)
        return (s * s / 2 - mu * s + mu * mu * (-np.expm1(-s / mu))) / d

    y, v, a = axial_closed_form(M, 0.0, d, F_MAX, T_RAMP, t)
    np.testing.assert_allclose(y, k * (Yd(t) - Yd(t - T_RAMP)), rtol=1e-9, atol=1e-14 * np.max(y))


def test_closed_form_exact_double_root_is_continuous():
    """m = 1/4, c = d = 1 is exactly critical in binary; neighbours on both sides agree."""
    t = np.linspace(0.0, 3.0, 31)
    y0, v0, a0 = axial_closed_form(0.25, 1.0, 1.0, 1.0, 1.0, t)
    assert Axial(0.25, 1.0, 1.0, 1.0, 1.0).kind == "double"
    for dd in (1.0 + 1e-12, 1.0 - 1e-12):
        y1, v1, a1 = axial_closed_form(0.25, 1.0, dd, 1.0, 1.0, t)
        np.testing.assert_allclose(y1, y0, rtol=1e-10, atol=1e-16)
        np.testing.assert_allclose(v1, v0, rtol=1e-10, atol=1e-16)
    # and the double-root formula itself against the ODE: y = t - 1 + (1 + t) e^{-2t} ... (ramp)
    # unit ramp response of 1/4 y'' + y' + y = t: Y = t - 1 + e^{-2t}(1 + t)
    Y = lambda s: np.where(s > 0, s - 1 + np.exp(-2 * s) * (1 + s), 0.0)  # noqa: E731
    np.testing.assert_allclose(y0, Y(t) - Y(t - 1.0), rtol=1e-12, atol=1e-15)


MODERATE_CASES = [(823224.0, 488.0), (1e4, 0.5), (1e5, 20.0), (4e4, 2 * math.sqrt(M * 4e4)),
                  (2e5, 2.0), (1e3, 1.0), (0.0, 10.0)]


def _ivp_axial(c, d, T, rtol=1e-11, method="Radau", F_max=F_MAX, t_ramp=T_RAMP):
    """scipy's integration of the axial ODE (split at the ramp's kink).

    atol = rtol x the peak of each state (taken from the closed form: only a scale); a smaller
    atol sits below the round-off noise of a screw at rest (411 N against 411 N) and makes the
    step size collapse."""
    mon = axial_monitors(M, c, d, F_max, t_ramp, T)
    atol = [rtol * mon["y_max"], rtol * mon["v_y_max"]]

    def f(t, s):
        return [s[1], (_F(t, F_max, t_ramp) - d * s[1] - c * s[0]) / M]

    def jac(t, s):
        return [[0.0, 1.0], [-c / M, -d / M]]

    out = []
    s0 = [0.0, 0.0]
    for a, b in ((0.0, t_ramp), (t_ramp, T)):
        kw = {"jac": jac} if method != "DOP853" else {}
        sol = solve_ivp(f, (a, b), s0, method=method, rtol=rtol, atol=atol, dense_output=True,
                        **kw)
        assert sol.success
        out.append(sol)
        s0 = sol.y[:, -1]
    return out


@pytest.mark.parametrize("c,d", MODERATE_CASES,
                         ids=[f"c{c:.4g}-d{d:.4g}" for c, d in MODERATE_CASES])
def test_closed_form_vs_scipy_radau(c, d):
    T = 0.2
    segs = _ivp_axial(c, d, T, method=_Radau)
    t = np.linspace(0.0, T, 201)
    y, v, a = axial_closed_form(M, c, d, F_MAX, T_RAMP, t)
    num = np.where(t <= T_RAMP, segs[0].sol(np.minimum(t, T_RAMP)),
                   segs[1].sol(np.maximum(t, T_RAMP)))
    assert np.max(np.abs(num[0] - y)) <= 1e-8 * np.max(np.abs(y))
    assert np.max(np.abs(num[1] - v)) <= 1e-8 * np.max(np.abs(v))


# ------------------------------------------------------------------------------------- monitors
def _propagate(c, d, T, n, F_max=F_MAX, t_ramp=T_RAMP):
    """(t, y, v, a) on a uniform grid of n points by exact linear propagation with the matrix
    exponential (scipy.linalg.expm), independent of the phi/divided-difference formulas.

    For c > 0 the state is the deviation from the particular solution of each phase
    (k (t/c - d/c^2) on the ramp, F_max/c after it), so that a = -(d u' + c u)/m carries no
    cancellation against the 411 N load (eps_a = 5e-9 m/s^2 is 4e-15 of F_max/m)."""
    from scipy.linalg import expm

    t = np.linspace(0.0, T, n)
    dt = t[1] - t[0]
    k = F_max / t_ramp
    y, v, a = np.zeros(n), np.zeros(n), np.zeros(n)
    if c > 0:
        A = np.array([[0.0, 1.0], [-c / M, -d / M]])
        # the ramp phase, from u(0) = k d / c^2, u'(0) = -k / c
        i_r = int(np.searchsorted(t, t_ramp, side="right"))  # samples with t < = t_ramp
        x = np.array([k * d / c**2, -k / c])
        P = expm(A * dt)
        us = np.empty((n, 2))
        for i in range(min(i_r, n)):
            if i:
                x = P @ x
            us[i] = x
        x_r = expm(A * t_ramp) @ np.array([k * d / c**2, -k / c])  # state at t_ramp exactly
        # the phase after the ramp: u = y - F_max/c, continuous y and v at t_ramp
        y_r = x_r[0] + k * (t_ramp / c - d / c**2)
        v_r = x_r[1] + k / c
        x = np.array([y_r - F_max / c, v_r])
        if i_r < n:
            x = expm(A * (t[i_r] - t_ramp)) @ x
            for i in range(i_r, n):
                if i > i_r:
                    x = P @ x
                us[i] = x
        ramp = t <= t_ramp
        y = np.where(ramp, us[:, 0] + k * (t / c - d / c**2), us[:, 0] + F_max / c)
        v = np.where(ramp, us[:, 1] + k / c, us[:, 1])
        a = -(d * us[:, 1] + c * us[:, 0]) / M
    else:
        # c = 0: augmented linear system in (y, v, t, 1) with F = k min(t, t_ramp)
        def sys(post):
            B = np.zeros((4, 4))
            B[0, 1] = 1.0
            B[1, 1] = -d / M
            if post:
                B[1, 3] = F_max / M
            else:
                B[1, 2] = k / M
            B[2, 3] = 1.0
            return B

        x = np.array([0.0, 0.0, 0.0, 1.0])
        Pr, Pp = expm(sys(False) * dt), expm(sys(True) * dt)
        xs = np.empty((n, 4))
        for i in range(n):
            if i:
                if t[i] <= t_ramp:
                    x = Pr @ x
                else:
                    if t[i - 1] < t_ramp:
                        x = expm(sys(True) * (t[i] - t_ramp)) @ (
                            expm(sys(False) * (t_ramp - t[i - 1])) @ x)
                    else:
                        x = Pp @ x
            xs[i] = x
        y, v = xs[:, 0], xs[:, 1]
        a = (_F(t, F_max, t_ramp) - d * v) / M
    return t, y, v, a


def _local_max(c, d, t0, y0, v0, t1, n=4001, F_max=F_MAX, t_ramp=T_RAMP):
    """max |y| and max |v| on [t0, t1] from the state (y0, v0) at t0: expm propagation of the
    augmented system (y, v, t, 1) on a grid of n points (the ramp's kink is a grid point)."""
    from scipy.linalg import expm

    k = F_max / t_ramp

    def B(post):
        b = np.zeros((4, 4))
        b[0, 1] = 1.0
        b[1, 0] = -c / M
        b[1, 1] = -d / M
        if post:
            b[1, 3] = F_max / M
        else:
            b[1, 2] = k / M
        b[2, 3] = 1.0
        return b

    ts = np.linspace(t0, t1, n)
    h = ts[1] - ts[0]
    P = {False: expm(B(False) * h), True: expm(B(True) * h)}
    x = np.array([y0, v0, t0, 1.0])
    ym, vm = abs(y0), abs(v0)
    for ta, tb in zip(ts[:-1], ts[1:]):
        if ta < t_ramp < tb:  # split the step at the kink
            x = expm(B(True) * (tb - t_ramp)) @ (expm(B(False) * (t_ramp - ta)) @ x)
        else:
            x = P[ta >= t_ramp] @ x
        ym, vm = max(ym, abs(x[0])), max(vm, abs(x[1]))
    return ym, vm


def _dense_monitors(c, d, T, eps_v=5e-8, eps_a=5e-9, n=100001):
    """Monitors by brute force on a uniform grid of n samples; the sampled maxima are polished by
    resampling finely between the neighbours of the best sample."""
    t, y, v, a = _propagate(c, d, T, n)
    dt = t[1] - t[0]
    res = {}
    for key, sig, k in (("y_max", y, 0), ("v_y_max", v, 1)):
        i = int(np.argmax(np.abs(sig)))
        best = abs(sig[i])
        j = max(i - 1, 0)
        loc = _local_max(c, d, t[j], y[j], v[j], min(T, t[j] + 2 * dt))
        res[key] = max(best, loc[k])
    bad = (np.abs(v) > eps_v) | (np.abs(a) > eps_a)
    if bad[-1]:
        res["t_eq"] = -1.0
    else:
        res["t_eq"] = t[np.nonzero(bad)[0][-1]] if bad.any() else 0.0
    return res, dt


MONITOR_CASES = [(823224.0, 488.0, 0.2), (1e4, 0.5, 0.2), (1e5, 20.0, 0.2),
                 (4e4, 2 * math.sqrt(M * 4e4), 0.2), (2e5, 0.02, 0.1), (1e3, 1.0, 0.2),
                 (3e5, 3.0, 0.2), (8.2e5, 0.0, 0.07), (0.0, 488.0, 0.2)]


@pytest.mark.parametrize("c,d,T", MONITOR_CASES,
                         ids=[f"c{c:.4g}-d{d:.4g}" for c, d, _ in MONITOR_CASES])
def test_monitors_vs_dense_sampling(c, d, T):
    ref = axial_monitors(M, c, d, F_MAX, T_RAMP, T)
    brute, dt = _dense_monitors(c, d, T)
    assert ref["y_max"] == pytest.approx(brute["y_max"], rel=1e-8)
    assert ref["v_y_max"] == pytest.approx(brute["v_y_max"], rel=1e-8)
    if brute["t_eq"] < 0:
        assert ref["t_eq"] == -1.0
    else:
        # the exact crossing lies within one sampling interval after the last bad sample
        assert brute["t_eq"] - 1e-12 <= ref["t_eq"] <= brute["t_eq"] + dt + 1e-12


def test_monitors_short_horizon_and_intermediate_times():
    """T inside the ramp and just after it; t_eq = -1 while the screw moves."""
    for T in (0.01, 0.05, 0.06, 0.1):
        ref = axial_monitors(M, 823224.0, 488.0, F_MAX, T_RAMP, T)
        brute, dt = _dense_monitors(823224.0, 488.0, T, n=50001)
        assert ref["y_max"] == pytest.approx(brute["y_max"], rel=1e-8)
        assert ref["v_y_max"] == pytest.approx(brute["v_y_max"], rel=1e-8)
        if brute["t_eq"] < 0:
            assert ref["t_eq"] == -1.0
        else:
            assert brute["t_eq"] - 1e-12 <= ref["t_eq"] <= brute["t_eq"] + dt + 1e-12


STIFF_MONITOR_CASES = [(6.1e9, 1.0), (25.0**7, 25.0**2), (6.1e9, 2.44e8), (1e3, 2.44e8),
                       (5e8, 30.0)]


@pytest.mark.parametrize("c,d", STIFF_MONITOR_CASES,
                         ids=[f"c{c:.4g}-d{d:.4g}" for c, d in STIFF_MONITOR_CASES])
def test_monitors_locally_in_stiff_and_oscillating_cases(c, d):
    """Where brute force over [0, T] is impossible (1e5 oscillations, time scales of 1e-12 s):
    exact samples around the located extrema and around t_eq confirm them locally."""
    T, eps_v, eps_a = 0.2, 5e-8, 5e-9
    ax = Axial(M, c, d, F_MAX, T_RAMP)
    ref = ax.monitors(T, eps_v, eps_a)
    period = float(2 * math.pi / ax.omega) if ax.kind == "complex" else 1e-3
    # no sample around the ramp end or at T exceeds the maxima
    win = np.concatenate([T_RAMP + np.linspace(0.0, 3 * period, 601), np.linspace(0.0, T_RAMP, 201),
                          [T]])
    win = win[win <= T]
    vals = np.array([ax.eval(t) for t in win])
    assert np.max(np.abs(vals[:, 0])) <= ref["y_max"] * (1 + 1e-12)
    assert np.max(np.abs(vals[:, 1])) <= ref["v_y_max"] * (1 + 1e-12)
    if ref["t_eq"] > 0:
        te = ref["t_eq"]
        after = np.array([ax.eval(t) for t in te + np.linspace(1e-13, 4 * period, 801)
                          if t <= T])
        assert np.all(np.abs(after[:, 1]) <= eps_v) and np.all(np.abs(after[:, 2]) <= eps_a)
        y, v, a = ax.eval(te)
        assert abs(abs(v) - eps_v) <= 1e-9 * eps_v or abs(abs(a) - eps_a) <= 1e-9 * eps_a
        before = np.array([ax.eval(t) for t in te - np.linspace(1e-3, 1.0, 50) * period * 0.5])
        assert np.any((np.abs(before[:, 1]) > eps_v) | (np.abs(before[:, 2]) > eps_a))


def test_monitors_undamped_never_at_rest():
    assert axial_monitors(M, 8.2e5, 0.0, F_MAX, T_RAMP, 0.2)["t_eq"] == -1.0
    assert axial_monitors(M, 6.1e9, 0.0, F_MAX, T_RAMP, 0.2)["t_eq"] == -1.0


def test_axial_reference_speed():
    """77 cases x 201 points plus monitors stay fast (the axial FMU test relies on it)."""
    import time

    t0 = time.perf_counter()
    t = np.linspace(0.0, 0.2, 201)
    for c in (25.0**3, 25.0**5, 25.0**7):
        for d in (25.0**2, 25.0**4, 25.0**6):
            axial_closed_form(M, c, d, F_MAX, T_RAMP, t)
            axial_monitors(M, c, d, F_MAX, T_RAMP, 0.2)
    # ~0.1 s per case on an idle 2-core machine; generous for a loaded one
    assert time.perf_counter() - t0 < 9 * 3.0


# ------------------------------------------------------------------------------------------ 6 DOF
def test_cardan_kinematics():
    """R^T dR/dt = skew(G theta') and dG/dt = G' (central differences)."""
    rng = np.random.default_rng(1)
    for _ in range(5):
        th = rng.uniform(-1.0, 1.0, 3)
        thd = rng.uniform(-3.0, 3.0, 3)
        h = 1e-6
        Rd = (cardan_R(*(th + h * thd)) - cardan_R(*(th - h * thd))) / (2 * h)
        W = cardan_R(*th).T @ Rd
        np.testing.assert_allclose(W, skew(cardan_G(th[1], th[2]) @ thd), atol=1e-8)
        Gd = (cardan_G(*(th + h * thd)[1:]) - cardan_G(*(th - h * thd)[1:])) / (2 * h)
        np.testing.assert_allclose(Gd, cardan_Gdot(th[1], th[2], thd[1], thd[2]), atol=1e-8)


def test_six_dof_axial_decoupling_matches_closed_form():
    p = make_params(t_ramp=0.01)
    t = np.linspace(0.0, 0.05, 101)
    ref = six_dof_radau(p, None, t)
    y, v, a = axial_closed_form(p["m"], p["c_y"], p["d_y"], p["F_max"], p["t_ramp"], t)
    assert np.max(np.abs(ref["y"] - y)) <= 1e-9 * np.max(np.abs(y))
    assert np.max(np.abs(ref["v_y"] - v)) <= 1e-9 * np.max(np.abs(v))
    assert np.max(np.abs(ref["a_y"] - a)) <= 1e-8 * np.max(np.abs(a))
    for k in SIX_DOF_NAMES:
        if k not in ("y", "v_y"):
            assert np.all(ref[k] == 0.0), k


def _coupled_params(**kw):
    # interaction point off the CG and off the axis: all six coordinates couple
    return make_params(rI_x=0.0005, rI_y=-0.012, rI_z=-0.0003, **kw)


def test_six_dof_energy_conservation():
    p = _coupled_params(F_max=0.0, d_x=0.0, d_y=0.0, d_z=0.0, d_alpha=0.0, d_beta=0.0,
                        d_gamma=0.0, c_alpha=0.5, c_beta=0.2, c_gamma=0.4, c_x=1e5, c_y=2e5,
                        c_z=1.5e5)
    s0 = np.array([2e-5, -1e-5, 1.5e-5, 0.3, -0.2, 0.25, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    t = np.linspace(0.0, 1e-3, 21)
    ref = six_dof_radau(p, None, t, state0=s0)
    E0 = six_dof_energy(s0, p)
    E = [six_dof_energy([ref[k][i] for k in SIX_DOF_NAMES], p) for i in range(t.size)]
    assert np.max(np.abs(np.array(E) - E0)) <= 1e-8 * E0
    # it really moved, in all coordinates
    for k in SIX_DOF_NAMES:
        assert np.ptp(ref[k]) > 0.1 * np.max(np.abs(ref[k])), k


def test_six_dof_momentum_of_the_free_screw():
    """No interface, no loads: linear and angular momentum (about the V origin) are constant;
    this checks the gyroscopic term, G and G' beyond energy."""
    zero = {k: 0.0 for k in ("c_x", "c_y", "c_z", "c_alpha", "c_beta", "c_gamma", "d_x", "d_y",
                             "d_z", "d_alpha", "d_beta", "d_gamma")}
    p = _coupled_params(F_max=0.0, **zero)
    s0 = np.array([0.0, 0.0, 0.0, 0.2, -0.3, 0.1, 0.01, -0.02, 0.015, 40.0, -25.0, 60.0])
    t = np.linspace(0.0, 0.01, 21)
    ref = six_dof_radau(p, None, t, state0=s0, method="DOP853")
    P0, L0 = six_dof_momentum(s0, p)
    E0 = six_dof_energy(s0, p)
    for i in range(t.size):
        s = [ref[k][i] for k in SIX_DOF_NAMES]
        P, L = six_dof_momentum(s, p)
        np.testing.assert_allclose(P, P0, rtol=0, atol=1e-9 * np.linalg.norm(P0))
        np.testing.assert_allclose(L, L0, rtol=0, atol=1e-9 * np.linalg.norm(L0))
        assert six_dof_energy(s, p) == pytest.approx(E0, rel=1e-9)
    assert np.ptp(ref["beta"]) > 0.1


def test_six_dof_rest_stays_exactly_zero():
    p = make_params(F_max=0.0)
    assert np.all(six_dof_rhs(0.3, np.zeros(12), p, None) == 0.0)


def test_six_dof_radau_and_dop853_agree_on_the_lightly_damped_case():
    p = make_params(F_max=411.0, t_ramp=0.005, d_x=0.5, d_y=0.5, d_z=0.5, d_alpha=1e-5,
                    d_beta=1e-5, d_gamma=1e-5, rI_y=-0.009)
    loads = {"F_ext": [3.0, 0.0, 2.0], "T_ext": [0.002, 0.003, -0.002]}
    t = np.linspace(0.0, 0.001, 21)
    r1 = six_dof_radau(p, loads, t)
    r2 = six_dof_radau(p, loads, t, method="DOP853", rtol=1e-12)
    for k in SIX_DOF_NAMES:
        assert np.max(np.abs(r1[k] - r2[k])) <= 1e-8 * np.max(np.abs(r2[k])), k


def test_six_dof_small_torque_statics():
    """A small pure torque about each axis on the default screw (P at the CG): the linear static
    answer theta_k = T_k / c_k (Cardan angles ~ small rotation vector)."""
    p = make_params(F_max=0.0)
    for k, name in enumerate(("alpha", "beta", "gamma")):
        T = np.zeros(3)
        T[k] = 1e-6 * p[("c_alpha", "c_beta", "c_gamma")[k]]
        ref = six_dof_radau(p, {"T_ext": T}, np.array([0.0, 0.2]), rtol=1e-8, atol_rel=1e-8)
        assert ref[name][-1] == pytest.approx(1e-6, rel=1e-4), name
