"""The coupling master (fmusa.cosim): a model FMU and the interface element FMU run together.

Every coupled run is checked against scipy's solve_ivp on the same equations written out here (the model's
equations of motion and the element's, from modelica/InterfaceElement.mo), which shares no code with the
master or the FMUs:

- OpenModelica 1.19's Mass_Damper (../shared/vendor-fmus/OM1193_Mass_Damper.fmu; ME and CS, no FMU state): a
  mass on a spring and a damper, force input f, output y (the mass's displacement from the spring's rest when
  spring.s_rel0 = 0.5: m y'' = f - c y - d y'). It exports no velocity output: the rate is its state
  damper.v_rel, which counts the other way (velocity_sign = -1).
- A body FMU built here (tests/fmus/cosim_body) as model exchange, as co-simulation with
  canGetAndSetFMUstate and as co-simulation without it, at the paper's interface stiffness (8.2e5 N/m,
  488 N s/m on 0.29 g).
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from cosim_fmus import build_body
from fmusa.cosim import Coupling, CouplingError, CouplingTimeLimitError, check_coupling, simulate_coupled

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("FMUSA_SHARED_DIR") or ROOT.parent / "shared")
OM = SHARED / "vendor-fmus" / "OM1193_Mass_Damper.fmu"
ELEMENT = ROOT / "dist" / "InterfaceElement.fmu"

ELEMENT_DEFAULTS = dict(c=823224.0, d=488.0, gap=0.0, nl_ratio=1.0, nl_y_b=5e-4, yield_ratio=1.0, yield_F=100.0,
                        fric_F=0.0, fric_x=1e-5, ve_k=0.0, ve_tau=1.0, smooth_w=1e-6, dmg_rate=0.0, dmg_y0=5e-4,
                        dmg_F_res=0.0)


def _S(u, w):
    return max(u, 0.0) + w * math.log1p(math.exp(-abs(u) / w))


def _sigma(u, w):
    return math.exp(-max(-u, 0.0) / w) / (1 + math.exp(-abs(u) / w))


def element_reference(s: float, v: float, z, p: dict) -> tuple[float, list[float]]:
    """The element's force and the rates of its states (z_y, z_f, F_ve, kappa), written out from the Modelica."""
    z_y, z_f, F_ve, kappa = z
    w, c = p["smooth_w"], p["c"]
    if p["gap"] > 0:
        s_e = _S(s - p["gap"], w) - _S(-s - p["gap"], w)
        v_e = (_sigma(s - p["gap"], w) + _sigma(-s - p["gap"], w)) * v
    else:
        s_e, v_e = s, v
    yield_on = p["yield_ratio"] != 1
    F_su = p["yield_ratio"] * c * s_e + (1 - p["yield_ratio"]) * p["yield_F"] * z_y if yield_on else c * s_e
    if p["nl_ratio"] != 1:
        F_su += (p["nl_ratio"] - 1) * c * (_S(s_e - p["nl_y_b"], w) - _S(-s_e - p["nl_y_b"], w))
    dz_y = v_e / (p["yield_F"] / c) * (1 - (z_y ** 4 if z_y * v_e > 0 else 0)) if yield_on else 0.0
    dz_f = v / p["fric_x"] * (1 - (z_f ** 4 if z_f * v > 0 else 0)) if p["fric_F"] > 0 else 0.0
    dkappa = ((abs(v_e) if s_e * v_e > 0 else 0) * _sigma(abs(s_e) - kappa, w)) if p["dmg_rate"] > 0 else 0.0
    if p["dmg_rate"] > 0:
        past = _S(kappa - p["dmg_y0"], w)
        dmg = 1 - math.exp(-p["dmg_rate"] * past)
        F_s = (1 - dmg) * F_su + dmg * p["dmg_F_res"] * s_e / (p["dmg_y0"] + past)
    else:
        F_s = F_su
    dF_ve = p["ve_k"] * v - F_ve / p["ve_tau"] if p["ve_k"] > 0 else 0.0
    F = F_s + p["d"] * v + (p["fric_F"] * z_f if p["fric_F"] > 0 else 0) + (F_ve if p["ve_k"] > 0 else 0)
    return F, [dz_y, dz_f, dF_ve, dkappa]


def reference(m: float, k: float, b: float, element: dict, drive, times: np.ndarray, x0: float = 0.0):
    """m x'' = drive(t) - F_element(x, x') - k x - b x', by scipy's LSODA at rtol 1e-10: (x, F) at the times."""
    p = {**ELEMENT_DEFAULTS, **element}

    def rhs(t, y):
        F, dz = element_reference(y[0], y[1], y[2:], p)
        return [y[1], (drive(t) - F - k * y[0] - b * y[1]) / m, *dz]

    sol = solve_ivp(rhs, (0, times[-1]), [x0, 0, 0, 0, 0, 0], t_eval=times, method="LSODA", rtol=1e-10,
                    atol=[1e-14, 1e-12, 1e-12, 1e-12, 1e-10, 1e-14], max_step=(times[1] - times[0]))
    assert sol.success
    F = np.array([element_reference(sol.y[0, i], sol.y[1, i], sol.y[2:, i], p)[0] for i in range(len(times))])
    return sol.y[0], F


def linear_reference(m: float, k: float, b: float, c: float, d: float, knots: list[tuple[float, float]],
                     times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The linear element in closed form: m x'' = f(t) - (c + k) x - (d + b) x' with f piecewise affine through
    ``knots`` (time, force; constant after the last), stepped exactly by the matrix exponential of the system
    augmented with f and f' (f'' = 0 on each piece). Returns (x, F = c x + d x') at the times."""
    from scipy.linalg import expm
    A = np.array([[0, 1, 0, 0], [-(c + k) / m, -(d + b) / m, 1 / m, 0], [0, 0, 0, 1], [0, 0, 0, 0]], float)
    kt = [t for t, _ in knots]
    grid = np.union1d(times, [t for t in kt if 0 < t < times[-1]])

    def slope(t):
        for (t0, f0), (t1, f1) in zip(knots[:-1], knots[1:]):
            if t0 <= t < t1:
                return (f1 - f0) / (t1 - t0)
        return 0.0

    y = np.array([0.0, 0.0, float(np.interp(0.0, kt, [f for _, f in knots])), slope(0.0)])
    out = {0.0: y[:2].copy()}
    for t0, t1 in zip(grid[:-1], grid[1:]):
        y[3] = slope(t0)
        y = expm(A * (t1 - t0)) @ y
        out[t1] = y[:2].copy()
    xv = np.array([out[t] for t in times])
    return xv[:, 0], c * xv[:, 0] + d * xv[:, 1]


def _rel(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a) - np.asarray(b))) / np.max(np.abs(b)))


# ---------------------------------------------------------------------------------------------- fixtures

@pytest.fixture(scope="module")
def element() -> Path:
    if not ELEMENT.is_file():
        pytest.fail("dist/InterfaceElement.fmu is missing: run `make fmu`")
    return ELEMENT


@pytest.fixture(scope="module")
def om() -> Path:
    if not OM.is_file():
        pytest.skip(f"{OM} is not there (the shared vendor FMUs)")
    return OM


@pytest.fixture(scope="module")
def bodies(tmp_path_factory) -> dict[str, Path]:
    """The body FMU as model exchange, CS with FMU state, CS without (built once per module)."""
    out = {}
    for name, interfaces, state in (("me", ("model-exchange",), False), ("cs-state", ("co-simulation",), True),
                                    ("cs-plain", ("co-simulation",), False)):
        out[name] = build_body(tmp_path_factory.mktemp(name), interfaces, state)
    return out


OM_PARAMS = {"mass.m": 1.0, "spring.c": 100.0, "damper.d": 1.0, "spring.s_rel0": 0.5}
OM_T = 0.5
OM_TIMES = np.linspace(0.0, OM_T, 51)


def om_drive(t: float) -> float:
    return 150.0 * math.sin(2 * math.pi * 2.0 * t)


SOFT = {"c": 1e4, "d": 20.0, "smooth_w": 1e-4}
#: each effect at the scale of the soft interface's motion (|s| up to ~1.4e-2 m)
EFFECTS = {"linear": {}, "gap": {"gap": 2e-3}, "nonlinear": {"nl_ratio": 3.0, "nl_y_b": 4e-3},
           "yield": {"yield_ratio": 0.2, "yield_F": 40.0}, "friction": {"fric_F": 20.0, "fric_x": 1e-3},
           "maxwell": {"ve_k": 5e3, "ve_tau": 0.05}, "damage": {"dmg_rate": 300.0, "dmg_y0": 4e-3, "dmg_F_res": 20.0},
           "offset": {"F_offset": 5.0, "y_offset": 1e-3}}
FAST_EFFECTS = ("linear",)


def om_coupling(element: Path, om: Path, scheme: str) -> Coupling:
    return Coupling(om, element, force_input="f", displacement_output="y", velocity_output="damper.v_rel",
                    velocity_sign=-1.0, scheme=scheme)


# ---------------------------------------------------------------------------------------------- tests

@pytest.mark.parametrize("effect", [pytest.param(e, marks=() if e in FAST_EFFECTS else pytest.mark.slow)
                                    for e in EFFECTS])
def test_openmodelica_model_exchange_with_each_effect(element, om, effect):
    """OM1193 Mass_Damper (ME) + the element, me-implicit, against scipy on the equations written out here."""
    params = {**SOFT, **EFFECTS[effect]}
    r = simulate_coupled(om_coupling(element, om, "me-implicit"), OM_PARAMS, params, OM_T, OM_TIMES,
                         ["y", "element.F_meas", "element.s_meas"], model_inputs=lambda t: {"f": om_drive(t)})
    x, F = reference(1.0, 100.0, 1.0, params, om_drive, OM_TIMES)
    assert r.scheme == "me-implicit" and r.calls > 0 and r.wall_s > 0
    assert _rel(r.frame["y"], x) < 1e-4, f"{effect}: y differs from scipy by {_rel(r.frame['y'], x):.3g}"
    assert _rel(r.frame["F"], F) < 1e-4, f"{effect}: F differs from scipy by {_rel(r.frame['F'], F):.3g}"
    assert np.allclose(r.frame["element.F_meas"], r.frame["F"] + params.get("F_offset", 0.0), rtol=0, atol=1e-9)
    assert np.allclose(r.frame["element.s_meas"], r.frame["y"] + params.get("y_offset", 0.0), rtol=0, atol=1e-12)
    if effect != "linear":   # the effect changes the response by far more than the tolerance
        x0, _ = reference(1.0, 100.0, 1.0, SOFT, om_drive, OM_TIMES)
        assert effect == "offset" or _rel(x0, x) > 1e-2


STIFF_BODY = {"m": 2.9e-4, "k": 100.0, "b": 0.01}
PAPER = {"c": 8.2e5, "d": 488.0}
STIFF_T = 0.05
STIFF_TIMES = np.linspace(0.0, STIFF_T, 26)


def ramp(t: float) -> float:
    return 100.0 * min(t / 0.02, 1.0)


@pytest.mark.parametrize("kind, scheme", [("me", "me-grid"), ("cs-state", "cs-iterate")])
def test_paper_stiffness_holds(element, bodies, kind, scheme):
    """The paper's interface (8.2e5 N/m, 488 N s/m on 0.29 g: eigenvalues -1.7e3 and -1.7e6 1/s) on the body FMU
    as ME (implicit) and as CS with FMU state (iteration with rollback, verified by halving): scipy's answer."""
    cp = Coupling(bodies[kind], element, "f", "x", "v", scheme="auto")
    r = simulate_coupled(cp, STIFF_BODY, PAPER, STIFF_T, STIFF_TIMES, ["x"], model_inputs=lambda t: {"f": ramp(t)},
                         step=2.5e-4)
    assert r.scheme == scheme     # auto picks what the FMU allows
    x, F = linear_reference(2.9e-4, 100.0, 0.01, PAPER["c"], PAPER["d"], [(0.0, 0.0), (0.02, 100.0)], STIFF_TIMES)
    tol = 1e-4 if scheme == "me-grid" else 1e-3
    assert _rel(r.frame["x"], x) < tol and _rel(r.frame["F"], F) < tol, (r.notes, _rel(r.frame["x"], x))
    if scheme == "cs-iterate":
        assert r.converged and r.difference <= 1e-3 and r.iterations > 0


def test_co_simulation_without_state_halves_until_converged(element, om):
    """OM1193 as co-simulation (no FMU state; its CS interface integrates with explicit Euler at the
    communication step): the explicit exchange is repeated at half the step until two runs agree, and the
    accepted run is scipy's answer within the measured difference (first order: error ~ difference)."""
    params = {"c": 1e3, "d": 20.0}
    times = np.linspace(0.0, 1.0, 21)
    drive = lambda t: 100.0 * min(t / 0.5, 1.0)      # noqa: E731
    r = simulate_coupled(om_coupling(element, om, "cs-halving"), OM_PARAMS, params, 1.0, times, ["y"],
                         model_inputs=lambda t: {"f": drive(t)}, coupling_tol=2e-3)
    x, F = linear_reference(1.0, 100.0, 1.0, params["c"], params["d"], [(0.0, 0.0), (0.5, 100.0)], times)
    assert r.scheme == "cs-halving" and r.converged and r.runs >= 2
    assert _rel(r.frame["y"], x) < 2 * r.difference + 1e-4 and _rel(r.frame["y"], x) < 5e-3


def test_explicit_exchange_at_paper_stiffness_refuses(element, bodies):
    """No FMU state and a stiff interface: the explicit exchange does not converge by halving, and the master
    says so instead of returning a number (or, strict=False, warns and marks the result)."""
    cp = Coupling(bodies["cs-plain"], element, "f", "x", "v")
    kw = dict(model_params=STIFF_BODY, element_params=PAPER, stop_time=0.01, output_times=np.linspace(0, 0.01, 6),
              outputs=["x"], model_inputs=lambda t: {"f": ramp(t)}, max_halvings=2)
    with pytest.raises(CouplingError, match="did not converge.*Model Exchange"):
        simulate_coupled(cp, **kw)
    with pytest.warns(UserWarning, match="did not converge"):
        r = simulate_coupled(cp, strict=False, **kw)
    assert r.scheme == "cs-halving" and not r.converged
    with pytest.raises(CouplingTimeLimitError, match="time limit"):
        simulate_coupled(cp, **{**kw, "max_halvings": 12}, max_wall_s=0.05)


def test_check_coupling_names_what_is_missing(element, om, bodies):
    good = om_coupling(element, om, "auto")
    check_coupling(good)
    cases = [
        (dict(force_input="force"), "has no variable 'force'.*inputs are: f"),
        (dict(force_input="y"), "'y'.*input"),
        (dict(displacement_output="nothing"), "nothing"),
        (dict(velocity_output=""), "rate"),
        (dict(element_fmu=OM), "element FMU"),
        (dict(scheme="cs-iterate"), "canGetAndSetFMUstate"),
        (dict(scheme="bogus"), "unknown coupling scheme"),
    ]
    for change, pattern in cases:
        with pytest.raises(CouplingError, match=pattern):
            check_coupling(Coupling(**{**good.__dict__, **change}))
    cs_only = Coupling(bodies["cs-plain"], element, "f", "x", "v", scheme="me-implicit")
    with pytest.raises(CouplingError, match="Model Exchange"):
        check_coupling(cs_only)


@pytest.mark.slow
def test_model_exchange_time_event(element, tmp_path):
    """tests/fmus/me_spring (ME; its load F_max*min(t/t_ramp, 1) has a kink at t_ramp that it announces as a
    time event) coupled at its input F_ext: the master stops at the event, runs the event iteration, and the
    coupled response is the closed form across the kink."""
    from fmus.me_spring.build import build_spring_fmu
    fmu = build_spring_fmu(tmp_path, interfaces=("model-exchange",))
    times = np.linspace(0.0, 1.0, 21)
    r = simulate_coupled(Coupling(fmu, element, "F_ext", "y", "v"), {"t_ramp": 0.5}, {"c": 1e3, "d": 5.0}, 1.0,
                         times, ["y"])
    x, F = linear_reference(1.0, 400.0, 20.0, 1e3, 5.0, [(0.0, 0.0), (0.5, 10.0)], times)
    assert r.scheme == "me-grid"     # auto: no event indicators
    assert _rel(r.frame["y"], x) < 1e-4 and _rel(r.frame["F"], F) < 1e-4
