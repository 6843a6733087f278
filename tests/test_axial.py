"""Axial pullout: the real FMU against the exact closed form (tests/reference.py).

Scenario of the paper's study, shortened: F_max = 411 N ramped over t_ramp = 50 ms, stop 0.2 s,
communication step 1 ms, thresholds eps_v_eq = 5e-8 m/s, eps_a_eq = 5e-9 m/s^2 (defaults).
With the interaction point at the CG (default) and no lateral load the axial motion decouples
exactly into m y'' + d_y y' + c_y y = F_pull(t).

Criteria: |y - y_exact| <= 1e-6 * max|y_exact| and the same for v_y at every communication point;
y_max and v_y_max within 1e-6 relative of the exact maxima; t_eq within 1e-6 s (or both -1).
Where t_eq is ill-conditioned (a lobe of |v_y| or |a_y| peaks within 1e-3 of its threshold, which
no double-precision solver resolves: eps_a = 5e-9 m/s^2 is 4e-15 of F_max/m) the FMU's t_eq must
be the exact one for some thresholds within (1 +- 1e-3) x eps instead.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from accuracy import record, worst
from fmu_run import FmuRunner, comm_grid
from reference import DEFAULTS, Axial

M = DEFAULTS["m"]
F_MAX, T_RAMP, STOP, STEP = 411.0, 0.05, 0.2, 1e-3
EPS_V, EPS_A = DEFAULTS["eps_v_eq"], DEFAULTS["eps_a_eq"]
REL, T_EQ_ABS = 1e-6, 1e-6
# t_eq is discontinuous where a lobe of |v_y| or |a_y| just touches its threshold; there the FMU's
# answer is accepted if it is exact for thresholds within this relative distance (see _t_eq_ok)
DELTA_EPS = 1e-3

OUTPUTS = ["y", "v_y", "y_max", "v_y_max", "t_eq"]
# intermediate communication points at which the running monitors are checked as well
CHECK_TIMES = (0.02, 0.05, 0.051, 0.08, 0.12)


def _cases():
    cases = []
    for i in range(3, 8):
        for j in range(2, 7):
            cases.append((f"grid-c25^{i}-d25^{j}", 25.0**i, 25.0**j))
    cases.append(("optimum", 823224.0, 488.0))
    cases.append(("undamped-c8.2e5", 8.2e5, 0.0))
    cases.append(("nospring-d488", 0.0, 488.0))
    rng = np.random.default_rng(20240607)
    lc = rng.uniform(math.log(1e3), math.log(6.1e9), 50)
    ld = rng.uniform(math.log(1.0), math.log(2.44e8), 50)
    for k, (a, b) in enumerate(zip(lc, ld)):
        c, d = math.exp(a), math.exp(b)
        cases.append((f"random{k:02d}-c{c:.4g}-d{d:.4g}", c, d))
    return cases


CASES = _cases()


@pytest.fixture(scope="module")
def runner(fmu_path):
    r = FmuRunner(fmu_path)
    yield r
    r.close()


def _t_eq_ok(got, ax, T, t_eq_exact):
    """t_eq within T_EQ_ABS of the exact one; or, when the exact t_eq is ill-conditioned (a lobe
    of |v_y| or |a_y| peaks within DELTA_EPS of its threshold, so that t_eq jumps by a half-period
    under a relative change of DELTA_EPS in the thresholds), the exact t_eq of some thresholds
    within (1 +- DELTA_EPS) eps.  Returns (ok, explanation)."""
    if t_eq_exact < 0:
        if got == -1.0:
            return True, ""
    elif abs(got - t_eq_exact) <= T_EQ_ABS:
        return True, ""
    lo = ax.monitors(T, EPS_V * (1 + DELTA_EPS), EPS_A * (1 + DELTA_EPS))["t_eq"]
    hi = ax.monitors(T, EPS_V * (1 - DELTA_EPS), EPS_A * (1 - DELTA_EPS))["t_eq"]
    window = f"exact t_eq for eps x (1 +- {DELTA_EPS:g}): [{lo!r}, {hi!r}]"
    if got == -1.0:
        return hi == -1.0, window
    if lo == -1.0:
        return False, window
    return (lo - T_EQ_ABS <= got and (hi == -1.0 or got <= hi + T_EQ_ABS)), window


def _check_monitors(name, got, ref, ax, T):
    assert abs(got["y_max"] - ref["y_max"]) <= REL * ref["y_max"], (
        f"{name}: y_max {got['y_max']!r} vs exact {ref['y_max']!r} "
        f"(rel {got['y_max'] / ref['y_max'] - 1:.3e})")
    assert abs(got["v_y_max"] - ref["v_y_max"]) <= REL * ref["v_y_max"], (
        f"{name}: v_y_max {got['v_y_max']!r} vs exact {ref['v_y_max']!r} "
        f"(rel {got['v_y_max'] / ref['v_y_max'] - 1:.3e})")
    ok, window = _t_eq_ok(got["t_eq"], ax, T, ref["t_eq"])
    assert ok, (f"{name}: t_eq {got['t_eq']!r} vs exact {ref['t_eq']!r} "
                f"(diff {got['t_eq'] - ref['t_eq']:.3e} s); {window}")


@pytest.mark.parametrize("name,c,d", CASES, ids=[c[0] for c in CASES])
def test_axial_pullout_vs_closed_form(runner, name, c, d):
    t = comm_grid(STOP, STEP)
    ax = Axial(M, c, d, F_MAX, T_RAMP)
    exact = np.array([ax.eval(ti) for ti in t])
    mon = ax.monitors(STOP, EPS_V, EPS_A)
    out = runner.simulate({"c_y": c, "d_y": d, "F_max": F_MAX, "t_ramp": T_RAMP}, t, OUTPUTS)

    ey = np.max(np.abs(out["y"] - exact[:, 0]))
    ev = np.max(np.abs(out["v_y"] - exact[:, 1]))
    ky = int(np.argmax(np.abs(out["y"] - exact[:, 0])))
    kv = int(np.argmax(np.abs(out["v_y"] - exact[:, 1])))
    assert ey <= REL * mon["y_max"], (
        f"{name}: max |y - exact| = {ey:.3e} = {ey / mon['y_max']:.3e} x peak at t = {t[ky]:.3f}")
    assert ev <= REL * mon["v_y_max"], (
        f"{name}: max |v_y - exact| = {ev:.3e} = {ev / mon['v_y_max']:.3e} x peak "
        f"at t = {t[kv]:.3f}")

    _check_monitors(name, {k: out[k][-1] for k in ("y_max", "v_y_max", "t_eq")}, mon, ax, STOP)
    _record(name, ey / mon["y_max"], ev / mon["v_y_max"], {k: out[k][-1] for k in ("y_max", "v_y_max", "t_eq")},
            mon, ax, STOP)
    for tc in CHECK_TIMES:
        k = int(round(tc / STEP))
        ref_k = ax.monitors(t[k], EPS_V, EPS_A)
        got_k = {kk: out[kk][k] for kk in ("y_max", "v_y_max", "t_eq")}
        _check_monitors(f"{name} at t = {t[k]:g}", got_k, ref_k, ax, t[k])


#: The worst errors of the exact axial path (issue 10 keeps them): the state at the communication points
#: against its peak, the monitors relative, t_eq absolute where it is well conditioned.
WORST = {"y/peak": 1e-12, "v_y/peak": 1e-10, "y_max rel": 1e-10, "v_y_max rel": 1e-10, "t_eq s": 1e-9}


def _well_conditioned_t_eq(ax, T, t_eq):
    lo = ax.monitors(T, EPS_V * (1 + DELTA_EPS), EPS_A * (1 + DELTA_EPS))["t_eq"]
    hi = ax.monitors(T, EPS_V * (1 - DELTA_EPS), EPS_A * (1 - DELTA_EPS))["t_eq"]
    return t_eq >= 0 and lo >= 0 and hi >= 0 and hi - lo <= T_EQ_ABS


def _record(name, ey_rel, ev_rel, got, mon, ax, T):
    errs = {"y/peak": ey_rel, "v_y/peak": ev_rel,
            "y_max rel": abs(got["y_max"] / mon["y_max"] - 1.0),
            "v_y_max rel": abs(got["v_y_max"] / mon["v_y_max"] - 1.0)}
    if _well_conditioned_t_eq(ax, T, mon["t_eq"]):
        errs["t_eq s"] = abs(got["t_eq"] - mon["t_eq"])
    record("axial pullout vs closed form", name, unit="s", **errs)


def test_axial_worst_errors_are_kept():
    """The worst errors over the cases above (run first, in file order) stay at the exact path's level."""
    w = worst("axial pullout vs closed form")
    if not w:
        pytest.skip("no axial case ran in this session (selected out)")
    bad = {k: v for k, v in w.items() if v[0] > WORST[k]}
    assert not bad, f"worst errors above {WORST}: {bad}"


LONG_CASES = [("optimum", 823224.0, 488.0), ("grid-c25^7-d25^2", 25.0**7, 25.0**2),
              ("grid-c25^4-d25^3", 25.0**4, 25.0**3),
              # far past the paper's range: the hold rings at 1e9-1e11 rad/s for 1e9-1e11 half-periods, taken in
              # closed form (once: 20 s for one doStep and a velocity peak 4000x too high at c = 1e20)
              ("stiff-c1e16", 1e16, 488.0), ("stiff-c1e20", 1e20, 488.0)]


@pytest.mark.parametrize("name,c,d", LONG_CASES, ids=[c[0] for c in LONG_CASES])
def test_axial_default_scenario_single_step(runner, name, c, d):
    """The defaults' scenario (t_ramp = 10 s), one communication step 0 -> 12 s; only the
    monitors are compared."""
    stop = 12.0
    t_ramp = DEFAULTS["t_ramp"]
    assert t_ramp == 10.0
    ax = Axial(M, c, d, DEFAULTS["F_max"], t_ramp)
    mon = ax.monitors(stop, EPS_V, EPS_A)
    out = runner.simulate({"c_y": c, "d_y": d}, np.array([0.0, stop]), ["y_max", "v_y_max", "t_eq"])
    _check_monitors(name, {k: out[k][-1] for k in ("y_max", "v_y_max", "t_eq")}, mon, ax, stop)
