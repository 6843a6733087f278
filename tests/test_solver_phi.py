"""Unit test of the solver's phi functions (fmu/solver.c: solver_phi), independent of the FMU.

solver.c is compiled on its own into a temporary shared library and solver_phi is called through
ctypes. The reference is computed with mpmath at 50 digits from the identity

    expm([[A, I, 0, 0],       first block row = [phi_0(A), phi_1(A), phi_2(A), phi_3(A)],
          [0, 0, I, 0],
          [0, 0, 0, I],       phi_0 = exp, phi_k(z) = (e^z - sum_{j<k} z^j/j!) / z^k,
          [0, 0, 0, 0]])

(test_reference_* checks that identity against independent closed forms, so the reference is proven
before it judges the solver). The matrix entries are the exact doubles the solver gets.

Criteria (not to be loosened; a failure is a solver problem to report):
- every case: per column j of every phi_k, max_i |P_ij - R_ij| <= 1e-11 * max_i |R_ij|
  (the column max is floored at DBL_MIN: a column below the double range is correct when it is
  rounded to that range);
- the stiff 2x2 cases h*[[0, 1], [-c/m, -d/m]] (the axial pullout's Jacobian): the action on e1 and
  e2 (the columns) component-wise, |P_ij - R_ij| <= 1e-10 |R_ij| wherever |R_ij| > 1e-8 max_i |R_ij|.
"""
from __future__ import annotations

import ctypes
import itertools
import math
import subprocess
from pathlib import Path

import mpmath as mp
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SOLVER_C = ROOT / "fmu" / "solver.c"
NMAX = 12
DPS = 50
DBL_MIN = 2.2250738585072014e-308

COL_TOL = 1e-11          # max-norm error per column, relative to the column's max
COMP_TOL = 1e-10         # component-wise relative error (stiff 2x2 cases)
COMP_FLOOR = 1e-8        # ... for components above this fraction of their column's max

M_SCREW = 2.9e-4
C_VALUES = (0.0, 15625.0, 823224.0, 6.1e9)
D_VALUES = (0.0, 1.0, 488.0, 2.44e8)
H_VALUES = (1e-9, 1e-4, 1.0, 12.0)


# ---------------------------------------------------------------------------------------------- the library

def _build(tmp_path_factory, *flags: str):
    out = tmp_path_factory.mktemp("libsolver") / "libsolver.so"
    subprocess.run(["gcc", "-std=c99", "-O2", "-fPIC", "-shared", *flags, "-I", str(ROOT / "fmu"), "-o", str(out),
                    str(SOLVER_C), "-lm"], check=True)
    lib = ctypes.CDLL(str(out))
    dp = ctypes.POINTER(ctypes.c_double)
    lib.solver_phi.argtypes = [ctypes.c_int, dp, dp, dp, dp, dp]
    lib.solver_phi.restype = None
    lib.solver_phi_apply.argtypes = [ctypes.c_int, dp, dp, dp, dp, dp, dp]
    lib.solver_phi_apply.restype = None
    return lib


@pytest.fixture(scope="module")
def libsolver(tmp_path_factory):
    """solver.c as the FMU builds it: on x86-64 Linux its matrix kernels in an AVX/FMA clone chosen at load."""
    return _build(tmp_path_factory)


@pytest.fixture(scope="module")
def libsolver_baseline(tmp_path_factory):
    """The same without the clones: the baseline code every x86-64 machine runs (and win64, macOS)."""
    return _build(tmp_path_factory, "-DSOLVER_NO_CLONES")


@pytest.fixture(scope="module", params=["matrix", "ladder", "ladder-baseline"])
def solver_phi(request, libsolver, libsolver_baseline):
    """phi_0..3(A) as the solver computes them: "matrix" doubles all four matrices (solver_phi, the steps
    with dense samples); "ladder" applies the squaring ladder to vectors (solver_phi_apply, the steps
    without), here to every unit vector, so that the same criteria judge its columns; "ladder-baseline" the
    same with the kernels every x86-64 machine has (no AVX/FMA clone)."""
    lib = libsolver_baseline if request.param == "ladder-baseline" else libsolver
    dp = ctypes.POINTER(ctypes.c_double)

    def phi(A: np.ndarray) -> list[np.ndarray]:
        A = np.ascontiguousarray(A, dtype=np.float64)
        n = A.shape[0]
        assert A.shape == (n, n) and 1 <= n <= NMAX
        # NaN-filled outputs: every entry must be written
        P = [np.full((n, n), np.nan) for _ in range(4)]
        if request.param == "matrix":
            lib.solver_phi(n, A.ctypes.data_as(dp), *[p.ctypes.data_as(dp) for p in P])
            return P
        for j in range(n):
            e = np.zeros(n)
            e[j] = 1.0
            cols = [np.full(n, np.nan) for _ in range(4)]
            lib.solver_phi_apply(n, A.ctypes.data_as(dp), e.ctypes.data_as(dp), *[c.ctypes.data_as(dp) for c in cols])
            for k in range(4):
                P[k][:, j] = cols[k]
        return P

    return phi


# ---------------------------------------------------------------------------------------------- references

def phi_reference(A: np.ndarray, dps: int = DPS) -> list[mp.matrix]:
    """phi_0..phi_3 of the double matrix A from mpmath's expm of the augmented block matrix."""
    n = A.shape[0]
    with mp.workdps(dps):
        M = mp.zeros(4 * n, 4 * n)
        for i in range(n):
            for j in range(n):
                M[i, j] = mp.mpf(float(A[i, j]))
        for b in range(3):
            for i in range(n):
                M[b * n + i, (b + 1) * n + i] = 1
        E = mp.expm(M)
        return [E[0:n, k * n:(k + 1) * n] for k in range(4)]


def phi_scalar(k: int, z) -> mp.mpf:
    """phi_k(z) for a scalar (real or complex) z at the current precision: series near 0, else closed form."""
    if abs(z) < 1:
        s, term, j = 0, mp.mpf(1) / mp.factorial(k), 0
        while abs(term) > mp.eps * 1e-5:
            s += term
            j += 1
            term = term * z / (j + k)
        return s
    return (mp.exp(z) - sum(z ** j / mp.factorial(j) for j in range(k))) / z ** k


def phi_eigen(A: np.ndarray, dps: int = 100) -> list[mp.matrix]:
    """phi_k(A) = V diag(phi_k(lambda)) V^-1 for a diagonalizable A (an independent reference)."""
    n = A.shape[0]
    with mp.workdps(dps):
        M = mp.matrix([[mp.mpf(float(x)) for x in row] for row in A])
        ev, V = mp.eig(M)
        Vi = mp.inverse(V)
        out = []
        for k in range(4):
            P = V * mp.diag([phi_scalar(k, lam) for lam in ev]) * Vi
            out.append(mp.matrix([[mp.re(P[i, j]) for j in range(n)] for i in range(n)]))
        return out


def phi_nilpotent(N: np.ndarray) -> list[mp.matrix]:
    """phi_k(N) = sum_j N^j / (j+k)! exactly (N nilpotent: the series ends at j = n-1)."""
    n = N.shape[0]
    with mp.workdps(DPS):
        M = mp.matrix([[mp.mpf(float(x)) for x in row] for row in N])
        powers = [mp.eye(n)]
        for _ in range(n):
            powers.append(powers[-1] * M)
        assert all(x == 0 for x in powers[n])
        return [sum((powers[j] / mp.factorial(j + k) for j in range(1, n)), powers[0] / mp.factorial(k))
                for k in range(4)]


# ---------------------------------------------------------------------------------------------- criteria

def column_errors(P: np.ndarray, R: mp.matrix) -> list[float]:
    """Per column: max_i |P_ij - R_ij| / max(max_i |R_ij|, DBL_MIN)."""
    n = P.shape[0]
    errs = []
    with mp.workdps(DPS):
        for j in range(n):
            scale = max(max(abs(R[i, j]) for i in range(n)), DBL_MIN)
            errs.append(float(max(abs(mp.mpf(float(P[i, j])) - R[i, j]) for i in range(n)) / scale))
    return errs


def component_errors(P: np.ndarray, R: mp.matrix) -> float:
    """Worst |P_ij - R_ij| / |R_ij| over the components above COMP_FLOOR of their column's max."""
    n = P.shape[0]
    worst = 0.0
    with mp.workdps(DPS):
        for j in range(n):
            scale = max(abs(R[i, j]) for i in range(n))
            for i in range(n):
                r = R[i, j]
                if abs(r) > COMP_FLOOR * scale and abs(r) > 1e10 * DBL_MIN:
                    worst = max(worst, float(abs(mp.mpf(float(P[i, j])) - r) / abs(r)))
    return worst


def sensitivity(A: np.ndarray, R: list[mp.matrix], seed: int = 0) -> float:
    """How much the exact phi's move, in the column criterion, when A's entries move by one ulp (for
    the failure report: what no double-precision algorithm can avoid)."""
    rng = np.random.default_rng(seed)
    Ap = np.nextafter(A, np.where(rng.random(A.shape) < 0.5, np.inf, -np.inf))
    Rp = phi_reference(Ap)
    n = A.shape[0]
    worst = 0.0
    with mp.workdps(DPS):
        for k in range(4):
            for j in range(n):
                scale = max(max(abs(R[k][i, j]) for i in range(n)), DBL_MIN)
                worst = max(worst, float(max(abs(Rp[k][i, j] - R[k][i, j]) for i in range(n)) / scale))
    return worst


def check(P: list[np.ndarray], R: list[mp.matrix], A: np.ndarray, componentwise: bool) -> None:
    for k in range(4):
        assert np.all(np.isfinite(P[k])), f"phi_{k} has non-finite entries:\n{P[k]}"
    col = [max(column_errors(P[k], R[k])) for k in range(4)]
    comp = [component_errors(P[k], R[k]) for k in range(4)] if componentwise else [0.0] * 4
    if max(col) <= COL_TOL and max(comp) <= COMP_TOL:
        return
    lines = [f"column errors (tol {COL_TOL:g}): " + ", ".join(f"phi_{k} {e:.2e}" for k, e in enumerate(col))]
    if componentwise:
        lines.append(f"component errors (tol {COMP_TOL:g}): "
                     + ", ".join(f"phi_{k} {e:.2e}" for k, e in enumerate(comp)))
    for k in range(4):
        if col[k] > COL_TOL or comp[k] > COMP_TOL:
            lines.append(f"phi_{k} solver    {P[k].tolist()}")
            lines.append(f"phi_{k} reference {[[mp.nstr(R[k][i, j], 17) for j in range(A.shape[0])] for i in range(A.shape[0])]}")
    lines.append(f"(exact phi's change under 1-ulp perturbations of A, same column measure: {sensitivity(A, R):.1e})")
    pytest.fail("\n".join(lines))


# ---------------------------------------------------------------------------------------------- the reference itself

@pytest.mark.parametrize("z", [0.0, 1e-9, -3.5e-5, 0.3, -1.0, 2.5, -40.0, -1e6, -1e13])
def test_reference_identity_scalar(z):
    """1x1: the augmented-matrix expm gives the closed forms phi_k(z)."""
    R = phi_reference(np.array([[z]]))
    with mp.workdps(DPS + 20):
        for k in range(4):
            exact = phi_scalar(k, mp.mpf(z))
            assert abs(R[k][0, 0] - exact) <= mp.mpf(10) ** (-40) * max(abs(exact), 1), (k, R[k][0, 0], exact)


@pytest.mark.parametrize("c,d,h", [(15625.0, 2.44e8, 1.0), (6.1e9, 1.0, 1.0), (823224.0, 0.0, 12.0),
                                   (823224.0, 488.0, 1e-4), (6.1e9, 2.44e8, 12.0)])
def test_reference_identity_stiff(c, d, h):
    """2x2 stiff: the augmented-matrix expm agrees with the eigen-decomposition at 100 digits."""
    A = h * np.array([[0.0, 1.0], [-c / M_SCREW, -d / M_SCREW]])
    R, E = phi_reference(A), phi_eigen(A)
    with mp.workdps(DPS):
        for k in range(4):
            for j in range(2):
                scale = max(abs(E[k][i, j]) for i in range(2))
                for i in range(2):
                    assert abs(R[k][i, j] - E[k][i, j]) <= mp.mpf(10) ** (-25) * scale, (k, i, j)


# ---------------------------------------------------------------------------------------------- the solver

STIFF_CASES = list(itertools.product(C_VALUES, D_VALUES, H_VALUES))


@pytest.mark.parametrize("c,d,h", STIFF_CASES, ids=[f"c={c:g}-d={d:g}-h={h:g}" for c, d, h in STIFF_CASES])
def test_phi_axial_2x2(solver_phi, c, d, h):
    """The criterion is the one the integrator needs: the error of phi_k acting on physical states,
    measured in the element's natural units (position, velocity / w with w = sqrt(c/m), or d/m when
    c = 0), relative to the propagated state. Entries that are tiny because the state's units differ
    (phi_0[v, v] ~ 1e-17 when a velocity hardly survives a stiff step) do not count on their own.
    The error is normwise (relative to the largest entry of the balanced phi_k): a velocity a stiff step
    reduces to 1e-9 of itself needs no 1e-11 relative accuracy of what is left of it.
    The tolerance grows with the oscillation phase covered by the step, w_d h rad: a phase of 5e7 rad
    is known to ~5e7 ulp, whatever the method (the failure message prints that sensitivity)."""
    A = h * np.array([[0.0, 1.0], [-c / M_SCREW, -d / M_SCREW]])
    w = np.sqrt(c / M_SCREW) if c > 0 else max(d / M_SCREW, 1.0)
    S = np.diag([1.0, w])
    Si = np.diag([1.0, 1.0 / w])
    P = [Si @ Pk @ S for Pk in solver_phi(A)]
    R0 = phi_reference(A)
    with mp.workdps(DPS):
        Sm, Sim = mp.matrix(S.tolist()), mp.matrix(Si.tolist())
        R = [Sim * Rk * Sm for Rk in R0]
    disc = (d / M_SCREW) ** 2 - 4 * c / M_SCREW
    phase = 0.5 * np.sqrt(-disc) * h if disc < 0 else 0.0
    tol = COL_TOL + 8 * np.finfo(float).eps * phase
    # phi_0 propagates a state: its error counts against the state it acts on (norm 1 in balanced
    # units), not against what is left of it after a step that damps it by e^-300
    col = [normwise_error(P[k], R[k], floor=1.0 if k == 0 else 0.0) for k in range(4)]
    assert max(col) <= tol, (f"balanced normwise errors {[f'{e:.2e}' for e in col]} > tol {tol:.2e} "
                             f"(phase {phase:.3g} rad; 1-ulp sensitivity {sensitivity(A, R0):.1e})")


def normwise_error(P: np.ndarray, R: mp.matrix, floor: float = 0.0) -> float:
    """max_ij |P_ij - R_ij| / max(max_ij |R_ij|, floor): the relative error of a matrix function."""
    n = P.shape[0]
    with mp.workdps(DPS):
        scale = max(max(abs(R[i, j]) for i in range(n) for j in range(n)), DBL_MIN, floor)
        return float(max(abs(mp.mpf(float(P[i, j])) - R[i, j]) for i in range(n) for j in range(n)) / scale)


@pytest.mark.parametrize("h", [1.0, 12.0])
def test_phi_keeps_slow_mode(solver_phi, h):
    """c = 15625, d = 2.44e8: eigenvalues ~-8.4e11 h and ~-6.4e-5 h. The slow one must survive in phi_0
    and phi_1 with its relative accuracy: the dominant eigenvalue mu of the computed P0 gives
    log(mu) = lambda_slow, and of the computed P1 gives 1 - mu = 1 - phi_1(lambda_slow)."""
    c, d = 15625.0, 2.44e8
    A = h * np.array([[0.0, 1.0], [-c / M_SCREW, -d / M_SCREW]])
    P = solver_phi(A)
    with mp.workdps(60):
        a, b = -mp.mpf(float(A[1, 0])), -mp.mpf(float(A[1, 1]))          # A = [[0, h], [-a, -b]] (h exact)
        lam = (-b + mp.sqrt(b * b - 4 * a * mp.mpf(float(A[0, 1])))) / 2  # the slow eigenvalue
        assert -1e-3 < lam < 0

        def dominant(Pk):
            p = [[mp.mpf(float(x)) for x in row] for row in Pk]
            tr, det = p[0][0] + p[1][1], p[0][0] * p[1][1] - p[0][1] * p[1][0]
            return tr / 2 + mp.sqrt(tr * tr / 4 - det)

        lam_from_p0 = mp.log(dominant(P[0]))
        gap_p1 = 1 - dominant(P[1])
        exact_gap_p1 = 1 - phi_scalar(1, lam)
        err0 = float(abs(lam_from_p0 - lam) / abs(lam))
        err1 = float(abs(gap_p1 - exact_gap_p1) / abs(exact_gap_p1))
    assert err0 <= 1e-9 and err1 <= 1e-9, (
        f"slow eigenvalue {mp.nstr(lam, 17)}: relative error {err0:.2e} from phi_0, {err1:.2e} from phi_1")


def _random(n: int, scale: float, seed: int) -> np.ndarray:
    return np.random.default_rng(seed).standard_normal((n, n)) * scale / math.sqrt(n)


def _badly_scaled(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    D = 2.0 ** rng.integers(-20, 21, n)
    return D[:, None] * (rng.standard_normal((n, n)) * 2 / math.sqrt(n)) / D[None, :]


GENERAL_CASES = {
    "random-6x6-norm~2": lambda: _random(6, 1.0, 1),
    "random-6x6-norm~8": lambda: _random(6, 4.0, 2),
    "random-12x12-norm~3": lambda: _random(12, 1.0, 3),
    "random-12x12-norm~15": lambda: _random(12, 4.0, 4),
    "random-6x6-badly-scaled-2^±20": lambda: _badly_scaled(6, 5),
}


@pytest.mark.parametrize("name", list(GENERAL_CASES))
def test_phi_general(solver_phi, name):
    A = GENERAL_CASES[name]()
    check(solver_phi(A), phi_reference(A), A, componentwise=False)


@pytest.mark.parametrize("n", [2, 6, 12])
def test_phi_nilpotent(solver_phi, n):
    N = np.triu(np.random.default_rng(10 + n).standard_normal((n, n)) * 2.0, 1)
    R = phi_nilpotent(N)
    check(solver_phi(N), R, N, componentwise=False)
    # the two references agree on it
    with mp.workdps(DPS):
        for Rk, Sk in zip(R, phi_reference(N)):
            assert mp.mnorm(Rk - Sk, 1) <= mp.mpf(10) ** (-40) * mp.mnorm(Rk, 1)


@pytest.mark.parametrize("n", [1, 5, 12])
def test_phi_zero_matrix(solver_phi, n):
    P = solver_phi(np.zeros((n, n)))
    for k in range(4):
        assert np.array_equal(P[k], np.eye(n) / math.factorial(k)), (k, P[k])
