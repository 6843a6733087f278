"""The me-grid coupling scheme (fmusa.cosim.grid: fixed-step Radau IIA on the output grid) against references
that share no code with it: the matrix exponential of a linear system, and scipy's LSODA on the equations
written out in tests/test_cosim.py; and its cost against the adaptive me-implicit scheme on the same run
(FMU calls, which do not depend on the machine's load)."""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
from scipy.linalg import expm

from fmusa.cosim import Coupling, simulate_coupled
from fmusa.cosim.grid import GridIntegrationError, integrate_on_grid

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("FMUSA_SHARED_DIR") or ROOT.parent / "shared")
OM = SHARED / "vendor-fmus" / "OM1193_Mass_Damper.fmu"
ELEMENT = ROOT / "dist" / "InterfaceElement.fmu"

#: a force drive through knots (time s, force N), sampled at 40 Hz: a kink at every knot, which are samples
KNOTS_T = np.array([0.0, 0.5, 1.0, 1.75, 2.25, 2.5, 3.0])
KNOTS_F = np.array([0.0, 900.0, 900.0, -450.0, -450.0, 0.0, 0.0])


def oscillator(m: float, c: float, d: float):
    return lambda t, x: np.array([x[1], (np.interp(t, KNOTS_T, KNOTS_F) - c * x[0] - d * x[1]) / m])


def exact_oscillator(m: float, c: float, d: float, times: np.ndarray) -> np.ndarray:
    """x at the times, stepped exactly by the matrix exponential (state augmented with the drive and its
    slope, constant on each piece between the knots, which are among the times)."""
    A = np.array([[0, 1, 0, 0], [-c / m, -d / m, 1 / m, 0], [0, 0, 0, 1], [0, 0, 0, 0]], float)
    y = np.zeros(4)
    out = [0.0]
    for a, b in zip(times[:-1], times[1:]):
        y[2] = np.interp(a, KNOTS_T, KNOTS_F)
        y[3] = (np.interp(b, KNOTS_T, KNOTS_F) - y[2]) / (b - a)
        y = expm(A * (b - a)) @ y
        out.append(y[0])
    return np.array(out)


def test_grid_integrator_against_matrix_exponential():
    """Mass_Damper's equations with a linear element (m 1 kg, c 1.5e4 N/m, d 30 N s/m: 20 Hz, lightly damped) at
    40 Hz samples: the error falls with the tolerance and stays far below it; the drive's kinks cost no
    rejected steps beyond the first interval's."""
    f = oscillator(1.0, 1.5e4, 30.0)
    times = np.arange(0.0, 3.0 + 1e-9, 0.025)
    exact = exact_oscillator(1.0, 1.5e4, 30.0, times)
    errors = {}
    for rtol in (1e-3, 1e-4, 1e-5):
        got = [0.0]
        _, _, st = integrate_on_grid(f, np.zeros(2), times, rtol, np.full(2, 1e-3),
                                     on_step=lambda t, x: got.append(x[0]) and False)
        errors[rtol] = float(np.max(np.abs(np.array(got) - exact)) / np.ptp(exact))
        assert st.jacobians == 1 and st.steps >= len(times) - 1
    assert errors[1e-3] < 1e-4 and errors[1e-4] < 1e-5 and errors[1e-5] < 1e-6, errors
    assert errors[1e-5] < errors[1e-4] < errors[1e-3]


def test_grid_integrator_stiff_start_and_limit():
    """A stiff layer at the start (eigenvalues -1e6 and -1 1/s) is resolved by cutting only the first steps; a
    right-hand side that cannot be evaluated past a time is refused with the interval named, not returned."""
    lam = np.array([-1e6, -1.0])
    f = lambda t, x: lam * (x - np.array([1.0, 2.0]))     # noqa: E731
    times = np.linspace(0.0, 1.0, 11)
    t, x, st = integrate_on_grid(f, np.zeros(2), times, 1e-6, np.full(2, 1e-3))
    assert t == 1.0 and abs(x[0] - 1.0) < 1e-9 and abs(x[1] - 2 * (1 - math.exp(-1.0))) < 1e-6
    assert st.steps < 200, st
    with pytest.raises(GridIntegrationError, match=r"could not meet rtol .* t = "):
        integrate_on_grid(lambda t, x: np.array([np.nan if t > 0.55 else 1.0]), np.zeros(1), times, 1e-6,
                          np.ones(1))


@pytest.fixture(scope="module")
def om() -> Path:
    if not ELEMENT.is_file():
        pytest.fail("dist/InterfaceElement.fmu is missing: run `make fmu`")
    if not OM.is_file():
        pytest.skip(f"{OM} is not there (the shared vendor FMUs; set FMUSA_SHARED_DIR)")
    return OM


@pytest.mark.slow   # about 4 s CPU: me-implicit's run and the reference's
def test_me_grid_cheaper_than_me_implicit_same_answer(om):
    """The same coupled run (Mass_Damper + a gap element, 40 Hz samples over 3 s) by both model exchange schemes:
    the matrix exponential cannot follow a gap, so both against scipy's LSODA at rtol 1e-10 on the equations
    written out (tests/attached_reference.py); me-grid at rtol 1e-4 within 1e-5 of the range, with fewer than
    half the FMU calls of me-implicit at rtol 1e-6."""
    import attached_reference as ar
    truth = {**ar.BASE, **ar.CASES["backlash_gap"]}
    element = {{"c_y": "c", "d_y": "d"}.get(k, k): v for k, v in truth.items()}
    kt, ku = ar.protocol()
    t = np.arange(0.0, kt[-1] + 1e-9, 0.025)
    ref = ar.simulate(truth, kt, ku, t)
    drive = lambda time: {"f": float(np.interp(time, kt, ku))}     # noqa: E731
    calls = {}
    for scheme, rtol in (("me-grid", 1e-4), ("me-implicit", 1e-6)):
        cp = Coupling(om, ELEMENT, force_input="f", displacement_output="y", velocity_output="mass.v",
                      scheme=scheme)
        r = simulate_coupled(cp, {"spring.s_rel0": ar.S_REL0}, element, float(t[-1]), t, ["y"], model_inputs=drive,
                             rtol=rtol)
        err = float(np.max(np.abs(r.frame["y"].to_numpy() - ref)) / np.ptp(ref))
        assert r.scheme == scheme and err < (1e-5 if scheme == "me-grid" else 1e-6), (scheme, err, r.notes)
        calls[scheme] = r.calls
    assert calls["me-grid"] < 0.5 * calls["me-implicit"], calls


def test_event_indicators_choose_me_implicit(tmp_path):
    """A model exchange export with an event indicator (the body FMU of tests/fmus/cosim_body built with one: its
    displacement, crossed at every swing through rest): auto runs the adaptive me-implicit, which locates state
    events, and gets the closed form of the free swing; me-grid, which does not locate them, is refused."""
    from cosim_fmus import build_body
    from fmusa.cosim import CouplingError, check_coupling

    if not ELEMENT.is_file():
        pytest.fail("dist/InterfaceElement.fmu is missing: run `make fmu`")
    fmu = build_body(tmp_path, ("model-exchange",), False, indicators=True)
    body, element = {"m": 1.0, "k": 100.0, "b": 1.0, "x0": 0.01}, {"c": 1e4, "d": 20.0}
    times = np.linspace(0.0, 0.2, 41)
    r = simulate_coupled(Coupling(fmu, ELEMENT, "f", "x", "v"), body, element, 0.2, times, ["x"])
    A = np.array([[0.0, 1.0], [-(1e4 + 100.0), -(20.0 + 1.0)]])
    exact = np.array([(expm(A * t) @ [0.01, 0.0])[0] for t in times])
    assert r.scheme == "me-implicit"
    assert np.sum(np.diff(np.sign(exact)) != 0) >= 3          # it swings through rest: the indicator crosses
    assert np.max(np.abs(r.frame["x"].to_numpy() - exact)) < 1e-4 * 0.01
    with pytest.raises(CouplingError, match="event indicators"):
        check_coupling(Coupling(fmu, ELEMENT, "f", "x", "v", scheme="me-grid"))


def test_model_binary_stays_loaded_between_coupled_runs(om):
    """Coupled runs load each FMU's binary once per process and keep it: OpenModelica's runtime makes a
    thread-local key each time its library is loaded (and never deletes it), so loading it anew for every run
    ran out of keys after about a thousand runs and crashed the process. After a run the export's binary is
    still mapped, and more runs map no other copy."""
    import sys
    if not sys.platform.startswith("linux"):
        pytest.skip("reads /proc/self/maps")
    cp = Coupling(om, ELEMENT, force_input="f", displacement_output="y", velocity_output="mass.v", scheme="me-grid")
    times = np.linspace(0.0, 0.05, 3)

    def run_and_map() -> set[str]:
        simulate_coupled(cp, {"spring.s_rel0": 0.5}, {"c": 1e3, "d": 1.0}, 0.05, times, ["y"],
                         model_inputs=lambda t: {"f": 1.0})
        maps = Path("/proc/self/maps").read_text()
        return {line.split()[-1] for line in maps.splitlines() if line.endswith("Mass_Damper.so")}

    first = run_and_map()
    assert first, "the export's binary was unloaded after the run"
    assert run_and_map() == first and run_and_map() == first
