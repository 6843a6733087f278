"""The model the FMU's solver receives (the C generated from modelica/ScrewVertebra.mo by fmu/codegen.py) is
right, and so is its exact Jacobian, checked against paths that share no code with it:

- the right-hand side against the NumPy reference of MODEL.md (tests/reference.py: a 6x6 linear solve of the
  Newton-Euler equations) at random 6-DOF states, angles up to 1.2 rad, interaction point and centre of
  gravity off the axis, tilted principal axes, random stiffnesses, damping and loads;
- the Jacobian and the time derivative against Richardson-extrapolated central differences of that reference;
- with every effect beyond eq. 1 on, the Jacobian's columns against central differences of the generated
  right-hand side itself (CasADi's symbolic derivatives against its function values);
- the exact axial steps of the solver read the oscillator's coefficients off the Jacobian (solver.c,
  linear_piece): in the core force-driven variant (Solver.lin2) those entries are exactly c_y/m and d_y/m,
  whatever the state and the time, and nothing else feeds the axial rows.

The probe (tests/jacobian/model_probe.c) is compiled here against the FMU's own build sources."""
from __future__ import annotations

import ctypes
import shutil
import subprocess
import xml.etree.ElementTree as ET
import zlib
import zipfile
from pathlib import Path

import numpy as np
import pytest

import reference as ref
from accuracy import record

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ROOT / "build" / "fmu" / "sources"
NX = 16
STATES = ("x", "y", "z", "alpha", "beta", "gamma", "v_x", "v_y", "v_z", "w_alpha", "w_beta", "w_gamma")


class Probe:
    def __init__(self, lib: ctypes.CDLL, vrs: dict[str, int], starts: dict[str, float]) -> None:
        self.lib, self.vrs, self.starts = lib, vrs, starts
        self.n_vr = lib.probe_n_vr()

    def init(self, **params: float) -> None:
        v = np.zeros(self.n_vr)
        for name, val in {**self.starts, **params}.items():
            v[self.vrs[name]] = val
        msg = ctypes.create_string_buffer(512)
        if self.lib.probe_init(v.ctypes.data_as(ctypes.c_void_p), msg, 512):
            raise RuntimeError(msg.value.decode())

    def lin(self, t: float, x: np.ndarray):
        x = np.ascontiguousarray(x, dtype=float)
        du, J, Ft = np.zeros(NX), np.zeros(NX * NX), np.zeros(NX)
        msg = ctypes.create_string_buffer(512)
        ptr = lambda a: a.ctypes.data_as(ctypes.c_void_p)  # noqa: E731
        if self.lib.probe_lin(ctypes.c_double(t), ptr(x), ptr(du), ptr(J), ptr(Ft), msg, 512):
            raise RuntimeError(msg.value.decode())
        return du, J.reshape(NX, NX), Ft

    def rhs(self, t: float, x: np.ndarray) -> np.ndarray:
        return self.lin(t, x)[0]


@pytest.fixture(scope="module")
def probe(tmp_path_factory, fmu_path) -> Probe:
    if not shutil.which("gcc"):
        pytest.skip("needs gcc")
    if not (SOURCES / "sv_generated.c").exists():
        pytest.skip("build/fmu/sources has no generated model: run make fmu")
    out = tmp_path_factory.mktemp("probe") / "model_probe.so"
    # -O0: the generated model compiles in seconds instead of tens (the arithmetic is the same IEEE double)
    subprocess.run(["gcc", "-std=c99", "-O0", "-shared", "-fPIC", "-I", str(SOURCES), "-o", str(out),
                    str(ROOT / "tests" / "jacobian" / "model_probe.c"), str(SOURCES / "solver.c"),
                    str(SOURCES / "sv_generated.c"), "-lm"], check=True)
    lib = ctypes.CDLL(str(out))
    lib.probe_lin.argtypes = [ctypes.c_double] + [ctypes.c_void_p] * 4 + [ctypes.c_char_p, ctypes.c_int]
    lib.probe_init.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_int]
    with zipfile.ZipFile(fmu_path) as z:
        md = ET.fromstring(z.read("modelDescription.xml"))
    vrs, starts = {}, {}
    for sv in md.iter("ScalarVariable"):
        vrs[sv.get("name")] = int(sv.get("valueReference"))
        typ = next(iter(sv))
        if sv.get("causality") in ("parameter", "input") and typ.get("start") is not None:
            s = typ.get("start")
            starts[sv.get("name")] = 1.0 if s == "true" else 0.0 if s == "false" else float(s)
    return Probe(lib, vrs, starts)


def random_case(rng: np.random.Generator) -> tuple[dict, dict, np.ndarray, float]:
    params = dict(c_x=10 ** rng.uniform(3, 8), c_y=10 ** rng.uniform(3, 8), c_z=10 ** rng.uniform(3, 8),
                  d_x=10 ** rng.uniform(0, 4), d_y=10 ** rng.uniform(0, 4), d_z=10 ** rng.uniform(0, 4),
                  c_alpha=10 ** rng.uniform(-1, 2), c_beta=10 ** rng.uniform(-1, 2), c_gamma=10 ** rng.uniform(-1, 2),
                  d_alpha=10 ** rng.uniform(-4, -1), d_beta=10 ** rng.uniform(-4, -1), d_gamma=10 ** rng.uniform(-4, -1),
                  rI_x=rng.uniform(-2e-3, 2e-3), rI_y=rng.uniform(-1e-2, 0), rI_z=rng.uniform(-2e-3, 2e-3),
                  cg_x=rng.uniform(-1e-3, 1e-3), cg_z=rng.uniform(-1e-3, 1e-3),
                  phi_inertia=rng.uniform(-1, 1), F_max=rng.uniform(10, 500))
    loads = dict(F_ext=rng.normal(0, 10, 3), T_ext=rng.normal(0, 0.01, 3))
    x = np.zeros(NX)
    x[0:3] = rng.normal(0, 1e-4, 3)
    x[3:6] = rng.uniform(-1.2, 1.2, 3)
    x[6:9] = rng.normal(0, 1e-2, 3)
    x[9:12] = rng.normal(0, 1.0, 3)
    t = float(rng.uniform(0.1, 9.9))   # inside the ramp, away from its kinks
    return params, loads, x, t


def fmu_inputs(loads: dict) -> dict:
    F, T = loads["F_ext"], loads["T_ext"]
    return dict(F_ext_x=F[0], F_ext_y=F[1], F_ext_z=F[2], T_ext_x=T[0], T_ext_y=T[1], T_ext_z=T[2])


def richardson(f, x0: float, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Derivative of f at x0 by central differences at h and h/2, extrapolated (error O(h^4)), and a bound
    of its own error: the change from the first estimate plus the rounding of f over the step."""
    f1, f2, f3, f4 = f(x0 + h), f(x0 - h), f(x0 + h / 2), f(x0 - h / 2)
    d1 = (f1 - f2) / (2 * h)
    d2 = (f3 - f4) / h
    mag = np.max(np.abs([f1, f2, f3, f4]), axis=0)
    return (4 * d2 - d1) / 3, np.abs(d2 - d1) + 64 * np.finfo(float).eps * mag / h


def mismatch(J_col: np.ndarray, col: np.ndarray, bound: np.ndarray) -> float:
    """The largest difference between an exact column and its differences beyond the differences' own
    error bound, relative to the column's largest entry."""
    scale = np.max(np.abs(col)) + np.max(np.abs(J_col)) + 1e-300
    return float(np.max(np.maximum(np.abs(J_col - col) - bound, 0.0)) / scale)


def best_mismatch(J_col: np.ndarray, f, x0: float, floor: float) -> float:
    """mismatch() at the best of three step sizes (1e-4 to 1e-2 of the state's scale): differences of a
    function with cancelling terms carry rounding noise that no single step avoids."""
    scale = max(abs(x0), floor)
    return min(mismatch(J_col, *richardson(f, x0, hf * scale)) for hf in (1e-4, 1e-3, 1e-2))


@pytest.mark.parametrize("variant", ["core", "full"])
def test_generated_model_equals_the_numpy_reference(probe, variant):
    """100 random 6-DOF cases per variant: the full variant is selected by a Maxwell branch too weak to
    matter (ve_k = 1e-300 N/m, its force stays 0), so both variants meet the same reference."""
    rng = np.random.default_rng(11 if variant == "core" else 12)
    worst_f = worst_j = worst_t = 0.0
    for _ in range(100):
        params, loads, x, t = random_case(rng)
        extra = {} if variant == "core" else {"ve_k": 1e-300}
        probe.init(**params, **extra, **fmu_inputs(loads))
        du, J, Ft = probe.lin(t, x)
        p = ref.make_params(**params)
        model = ref._Model(p)
        f_ref = lambda s, tt=t: ref.six_dof_rhs(tt, s, p, loads, model)  # noqa: E731
        r = f_ref(x[:12])
        scale = np.max(np.abs(r[6:12])) + 1e-300
        worst_f = max(worst_f, np.max(np.abs(du[:12] - r)) / scale)
        assert np.all(np.abs(du[12:]) <= 1e-250)   # the effects' states stay at rest
        # Jacobian columns of the 12 mechanical states, and the time derivative
        for j in range(12):
            def shifted(v, j=j):
                s = x[:12].copy()
                s[j] = v
                return f_ref(s)

            worst_j = max(worst_j, best_mismatch(J[:12, j], shifted, x[j], 1e-2 if j >= 3 else 1e-5))
        worst_t = max(worst_t, best_mismatch(Ft[:12], lambda tt: ref.six_dof_rhs(tt, x[:12], p, loads, model),
                                             t, 1.0))
    record(f"generated model vs NumPy reference ({variant})", "100 6-DOF states",
           **{"rhs/row max": worst_f, "J column/col max": worst_j, "Ft/max": worst_t})
    assert worst_f <= 1e-10, f"right-hand side differs from the reference by {worst_f:.3e} of its largest entry"
    assert worst_j <= 1e-8, f"Jacobian differs from the reference's differences by {worst_j:.3e}"
    assert worst_t <= 1e-8, f"time derivative differs from the reference's differences by {worst_t:.3e}"


EFFECTS = {
    "gap": dict(gap=3e-5),
    "nonlinear_stiffness": dict(nl_ratio=2.5, nl_y_b=2e-5),
    "yield": dict(yield_ratio=0.2, yield_F=20.0),
    "friction": dict(fric_F=15.0, fric_x=1e-5),
    "maxwell": dict(ve_k=2e5, ve_tau=0.5),
    "damage": dict(dmg_rate=2e4, dmg_y0=2e-5, dmg_F_res=30.0),
    "table": dict(tab_n=4, **{"tab_y[1]": -1e-4, "tab_y[2]": 0.0, "tab_y[3]": 5e-5, "tab_y[4]": 2e-4,
                              "tab_F[1]": -80.0, "tab_F[2]": 0.0, "tab_F[3]": 30.0, "tab_F[4]": 60.0}),
}


@pytest.mark.parametrize("mode", [1, 2])
@pytest.mark.parametrize("effect", sorted(EFFECTS))
def test_effect_jacobian_equals_differences(probe, effect, mode):
    """Each effect on, in both drive modes, at 20 random states: every column of the generated Jacobian
    against Richardson differences of the generated right-hand side (smooth states only: the states are
    drawn away from the corners of max/abs, which the differences would straddle)."""
    rng = np.random.default_rng(zlib.crc32(f"{effect} {mode}".encode()))
    worst = 0.0
    for _ in range(20):
        params, loads, x, t = random_case(rng)
        probe.init(mode=mode, smooth_w=1e-5, **params, **EFFECTS[effect], **fmu_inputs(loads))
        x[1] = rng.uniform(-1.5e-4, 1.5e-4)
        x[7] = rng.normal(0, 1e-2)
        x[12:15] = rng.uniform(-0.9, 0.9, 3) * [1, 1, 50.0]
        x[15] = abs(x[1]) + rng.uniform(0, 5e-5)
        du, J, _ = probe.lin(t, x)
        for j in range(NX):
            def shifted(v, j=j):
                s = x.copy()
                s[j] = v
                return probe.rhs(t, s)

            worst = max(worst, best_mismatch(J[:, j], shifted, x[j], 1e-2 if 3 <= j < 6 or j >= 9 else 1e-6))
    record("generated Jacobian vs differences with an effect", f"{effect}, mode {mode}", **{"column/col max": worst})
    assert worst <= 1e-8, f"{effect} (mode {mode}): the Jacobian differs from differences by {worst:.3e}"


def test_exact_axial_steps_read_c_y_and_d_y_off_the_generated_jacobian(probe):
    """The core force-driven variant is the one the solver takes in exact steps (lin2): the (y, v_y) block of
    its Jacobian is [[0, 1], [-c_y/m, -d_y/m]] at every state and time, the axial motion drives no other state
    (so the active set stays the axial block), and the load enters as F_max/(m t_ramp) in the time derivative."""
    rng = np.random.default_rng(3)
    iy, iv = 1, 7
    for _ in range(50):
        c, d, m = 10 ** rng.uniform(2, 9.8), 10 ** rng.uniform(-2, 8.4), 10 ** rng.uniform(-5, -2)
        probe.init(c_y=c, d_y=d, m=m)
        assert probe.lib.probe_lin2() == 1
        blocks = set()
        for _ in range(5):
            x = np.zeros(NX)
            x[iy], x[iv] = rng.normal(0, 1e-3), rng.normal(0, 1e-2)
            t = float(rng.uniform(0.01, 9.99))
            _, J, Ft = probe.lin(t, x)
            blocks.add((J[iy, iy], J[iy, iv], J[iv, iy], J[iv, iv], Ft[iy], Ft[iv]))
            others = [j for j in range(NX) if j not in (iy, iv)]
            rows_moving = [i for i in others if J[i, iy] != 0.0 or J[i, iv] != 0.0]
            assert rows_moving == [], f"states {rows_moving} are driven by the axial motion in the core variant"
        assert len(blocks) == 1, "the axial block changes with the state or the time"
        (jyy, jyv, jvy, jvv, fty, ftv), = blocks
        assert (jyy, jyv, fty) == (0.0, 1.0, 0.0)
        assert jvy == pytest.approx(-c / m, rel=2e-16 * 4) and jvv == pytest.approx(-d / m, rel=2e-16 * 4)
        assert ftv == pytest.approx(411.0 / (m * 10.0), rel=1e-15)
    # an effect switched on leaves the exact steps
    probe.init(gap=1e-6)
    assert probe.lib.probe_lin2() == 0
