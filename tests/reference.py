"""Independent reference solutions for the ScrewVertebra FMU tests.

Written from ``fmu/MODEL.md`` and the variable contract (the public declarations of
``modelica/ScrewVertebra.mo``, read by ``fmu/generate.py``) only (never from the C code):

* the axial pullout problem  m y'' + d y' + c y = F(t), y(0) = y'(0) = 0, with the ramp load
  F = F_max t / t_ramp (t < t_ramp), F_max afterwards, solved exactly in multiple precision
  (``axial_closed_form``) together with its exact monitors y_max, v_y_max and t_eq
  (``axial_monitors``);
* the full six-degree-of-freedom Newton-Euler equations in numpy (``six_dof_rhs``) and a tight
  Radau integration of them from rest (``six_dof_radau``).

Axial closed form
-----------------
With the eigenvalues l1, l2 of m s^2 + d s + c and the phi functions
phi_0(z) = e^z, phi_k(z) = (phi_{k-1}(z) - 1/(k-1)!)/z = sum_j z^j/(j+k)!, the response to the unit
ramp input u(t) = t is

    Y(t) = t^2/m DD[phi_2(l t)],  Y'(t) = t/m DD[phi_1(l t)],  Y''(t) = 1/m DD[phi_0(l t)],

where DD[f(l)] = (f(l1) - f(l2))/(l1 - l2) is the divided difference over the two eigenvalues
(= Im f(l1)/omega for a complex pair, = d f/d l for a double eigenvalue).  The ramp load is the
superposition of two ramps: y(t) = k (Y(t) - Y(t - t_ramp) H(t - t_ramp)), k = F_max/t_ramp.
The phi functions are evaluated by their series for |z| < 1 and by the recursion otherwise, and
the working precision grows with the cancellation of the divided difference, so the formula is
exact to far below double precision for all of c in {0} U [1e3, 6.1e9], d in {0} U [1, 2.44e8]
(over-, under- and critically damped, c = 0, d = 0, both zero).

Axial monitors
--------------
Extrema and threshold crossings are located on the monotone pieces of each signal.  The pieces are
delimited by the zeros of the next derivative, which are known in closed form: in each phase
(ramp: tau = t, after the ramp: tau = t - t_ramp) a, the jerk, and (after the ramp) v have the form
DD[f(l) e^{l tau}] for an explicit f, whose zeros are tau = ln(f2/f1)/(l1 - l2) (real),
tau = -f'(l)/f(l) (double) or the arithmetic sequence tau_n = (n pi - arg f(l1))/omega (complex).
After the ramp v and a are pure transients, so their values at consecutive breakpoints shrink by
the constant factor exp(sigma pi/omega): the last breakpoint above a threshold follows from a
logarithm, which keeps cases with 1e5 oscillations exact and fast.  Crossings are then refined by
Brent's method on a bracket in which the signal is monotone (one root guaranteed).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mpmath
import numpy as np
from scipy.integrate import Radau, solve_ivp
from scipy.optimize import brentq

import contract

# A private multiple-precision context: never touch mpmath's global one.
MP = mpmath.MPContext()
MP.dps = 40
BASE_DPS = 40
MAX_DPS = 2000

# --------------------------------------------------------------------------------------------
# Defaults (the contract)
# --------------------------------------------------------------------------------------------
def read_defaults() -> dict:
    """Start values of all parameters of the contract (Real -> float, Integer -> int,
    Boolean -> bool); calculated parameters (I_1, I_2, I_3) are derived as in MODEL.md."""
    out = {}
    for v in contract.variables():
        if v.causality != "parameter":
            continue
        if v.type == "Real":
            out[v.name] = float(v.start)
        elif v.type == "Integer":
            out[v.name] = int(v.start)
        elif v.type == "Boolean":
            out[v.name] = v.start == "true"
        else:  # pragma: no cover - no strings in the contract
            out[v.name] = v.start
    return out


DEFAULTS = read_defaults()


def inertia_moments(p: dict) -> tuple:
    """Principal moments of a solid cylinder (MODEL.md): I1 = I3 = m(3r^2+L^2)/12, I2 = m r^2/2."""
    m, L, r = p["m"], p["L_screw"], p["D_screw"] / 2.0
    i1 = m * (3.0 * r * r + L * L) / 12.0
    return i1, m * r * r / 2.0, i1


# --------------------------------------------------------------------------------------------
# Axial closed form in multiple precision
# --------------------------------------------------------------------------------------------
_FACT = [1, 1, 2, 6, 24, 120]


def _phis(z, kmax):
    """[phi_0(z), ..., phi_kmax(z)] (z real or complex mp number), no cancellation."""
    if abs(z) < 1:
        # series of phi_kmax, then the stable upward recursion phi_{k-1} = z phi_k + 1/(k-1)!
        tol = MP.mpf(10) ** (-MP.dps - 5)
        term = MP.mpf(1) / _FACT[kmax]
        s = term
        j = 0
        while True:
            j += 1
            term = term * z / (j + kmax)
            s += term
            if abs(term) < tol:
                break
        out = [None] * (kmax + 1)
        out[kmax] = s
        for k in range(kmax, 0, -1):
            out[k - 1] = z * out[k] + MP.mpf(1) / _FACT[k - 1]
        return out
    out = [MP.exp(z)]
    for k in range(1, kmax + 1):
        out.append((out[-1] - MP.mpf(1) / _FACT[k - 1]) / z)
    return out


def _dphis(z, kmax):
    """[phi_0'(z), ..., phi_kmax'(z)] (needed only for a double eigenvalue)."""
    if abs(z) < 1:
        tol = MP.mpf(10) ** (-MP.dps - 5)
        out = []
        for k in range(kmax + 1):
            # phi_k'(z) = sum_{j>=1} j z^{j-1}/(j+k)!
            zp = MP.mpf(1)  # z^{j-1}
            fac = MP.factorial(k + 1)  # (j+k)! for j = 1
            s = MP.mpf(1) / fac
            j = 1
            while True:
                j += 1
                zp = zp * z
                fac = fac * (j + k)
                term = j * zp / fac
                s += term
                if abs(term) < tol and j > 3:
                    break
            out.append(s)
        return out
    ph = _phis(z, kmax)
    out = [ph[0]]
    for k in range(1, kmax + 1):
        out.append((ph[k - 1] - k * ph[k]) / z)
    return out


@dataclass
class _Seq:
    """Breakpoints tau_n = start + n*step, n = 0..count-1 (step None: at most one point)."""

    start: object = None
    step: object = None
    count: int = 0

    def __len__(self):
        return self.count

    def __getitem__(self, n):
        if n < 0 or n >= self.count:
            raise IndexError(n)
        return self.start if self.step is None else self.start + n * self.step


class Axial:
    """Exact solution of m y'' + d y' + c y = F(t) with the two-ramp load."""

    def __init__(self, m, c, d, F_max, t_ramp):
        if not (m > 0 and c >= 0 and d >= 0 and t_ramp > 0):
            raise ValueError("need m > 0, c >= 0, d >= 0, t_ramp > 0")
        self.m_f, self.c_f, self.d_f = float(m), float(c), float(d)
        self.F_f, self.tr_f = float(F_max), float(t_ramp)
        with MP.workdps(120):  # exact discriminant of the double inputs (< 160 bits)
            m_, c_, d_ = MP.mpf(m), MP.mpf(c), MP.mpf(d)
            self.m, self.c, self.d = m_, c_, d_
            self.tr = MP.mpf(t_ramp)
            self.k = MP.mpf(F_max) / self.tr
            disc = d_ * d_ - 4 * m_ * c_
            if disc > 0:
                s = MP.sqrt(disc)
                self.kind = "real"
                self.l1 = -2 * c_ / (d_ + s)  # slow eigenvalue, free of cancellation
                self.l2 = (-d_ - s) / (2 * m_)
                self.dl = abs(self.l1 - self.l2)
            elif disc < 0:
                self.kind = "complex"
                self.sigma = -d_ / (2 * m_)
                self.omega = MP.sqrt(-disc) / (2 * m_)
                self.l1 = MP.mpc(self.sigma, self.omega)
                self.l2 = MP.mpc(self.sigma, -self.omega)
                self.dl = 2 * self.omega
            else:
                self.kind = "double"
                self.l1 = self.l2 = -d_ / (2 * m_)
                self.dl = MP.mpf(0)

    # -- precision management ----------------------------------------------------------------
    def _dps(self, t):
        extra = 0
        if self.kind != "double" and t > 0:
            x = float(self.dl * t)
            if x < 1.0:
                extra = int(math.ceil(-math.log10(x))) + 2 if x > 0 else 0
        return min(BASE_DPS + extra, MAX_DPS)

    # -- unit ramp response --------------------------------------------------------------------
    def _unit_ramp(self, t, nder=2):
        """(Y, Y', Y'') of the unit ramp input at t >= 0 (mp)."""
        if t == 0:
            return (MP.mpf(0),) * (nder + 1)
        m = self.m
        if self.kind == "double":
            z = self.l1 * t
            dp = _dphis(z, 2)
            dd = [t * dp[2], t * dp[1], t * dp[0]]  # DD -> d/dl of phi_k(l t)
        elif self.kind == "complex":
            ph = _phis(self.l1 * t, 2)
            dd = [MP.im(ph[2]) / self.omega, MP.im(ph[1]) / self.omega,
                  MP.im(ph[0]) / self.omega]
        else:
            p1 = _phis(self.l1 * t, 2)
            p2 = _phis(self.l2 * t, 2)
            den = self.l1 - self.l2
            dd = [(p1[2] - p2[2]) / den, (p1[1] - p2[1]) / den, (p1[0] - p2[0]) / den]
        return (t * t / m * dd[0], t / m * dd[1], dd[2] / m)[: nder + 1]

    def eval_mp(self, t):
        """(y, v, a) at time t (mp or float), in mp."""
        t = MP.mpf(t)
        if t <= 0:
            return MP.mpf(0), MP.mpf(0), MP.mpf(0)
        tau = t - self.tr
        d_min = t if tau <= 0 else min(t, tau)
        with MP.workdps(self._dps(d_min)):
            y1 = self._unit_ramp(t)
            if tau > 0:
                y2 = self._unit_ramp(tau)
                return tuple(self.k * (a - b) for a, b in zip(y1, y2))
            return tuple(self.k * a for a in y1)

    def eval(self, t):
        return tuple(float(x) for x in self.eval_mp(t))

    # -- breakpoints --------------------------------------------------------------------------
    def _f(self, which, lam):
        """(f(l), f'(l)) for the phase functions, see module docstring."""
        tr = self.tr
        if which == "one":
            return MP.mpf(1), MP.mpf(0)
        if which == "lam":
            return lam, MP.mpf(1)
        ph = _phis(lam * tr, 1)
        dph = _dphis(lam * tr, 1) if self.kind == "double" else (None, None)
        E = ph[0]
        W = lam * tr * ph[1]  # e^{l tr} - 1 without cancellation
        if which == "W":
            return W, tr * E
        if which == "lamW":
            return lam * W, W + lam * tr * E
        if which == "W/lam":
            return tr * ph[1], (tr * tr * dph[1] if dph[1] is not None else None)
        raise ValueError(which)

    def _zeros(self, which, length):
        """Zeros in (0, length) of DD[f(l) e^{l tau}] as a _Seq."""
        with MP.workdps(60):
            if self.kind == "complex":
                f1, _ = self._f(which, self.l1)
                if f1 == 0:
                    return _Seq()
                step = MP.pi / self.omega
                start = -MP.arg(f1) / self.omega
                # smallest n with start + n step > 0
                n0 = int(MP.floor(-start / step)) + 1
                start = start + n0 * step
                while start - step > 0:
                    start -= step
                if start >= length:
                    return _Seq()
                count = int(MP.floor((length - start) / step)) + 1
                if start + (count - 1) * step >= length:
                    count -= 1
                return _Seq(start, step, count)
            if self.kind == "real":
                f1, _ = self._f(which, self.l1)
                f2, _ = self._f(which, self.l2)
                if f1 == 0 or f2 == 0:
                    return _Seq()
                r = f2 / f1
                if r <= 0:
                    return _Seq()
                tau = MP.log(r) / (self.l1 - self.l2)
            else:
                f, fp = self._f(which, self.l1)
                if f == 0:
                    return _Seq()
                tau = -fp / f
            if 0 < tau < length:
                return _Seq(tau, None, 1)
            return _Seq()

    # -- monitors -----------------------------------------------------------------------------
    def _sig(self, idx, t):
        return self.eval_mp(t)[idx]

    def _root(self, idx, target, a, b):
        """Root of s_idx(t) = target in [a, b] where s_idx is monotone with a sign change."""
        fa = float(self._sig(idx, a) - target)
        fb = float(self._sig(idx, b) - target)
        a_f, b_f = float(a), float(b)
        if fa == 0:
            return a_f
        if fb == 0:
            return b_f
        g = lambda t: float(self._sig(idx, t) - target)  # noqa: E731
        # guard against the rounding of the bracket to doubles
        if g(a_f) * g(b_f) > 0:
            return 0.5 * (a_f + b_f)
        return brentq(g, a_f, b_f, xtol=1e-300, rtol=4 * np.finfo(float).eps, maxiter=500)

    def _last_violation(self, idx, eps, T):
        """sup{t in [0, T]: |s_idx(t)| > eps} (None if never); s_idx = v (1) or a (2)."""
        tr = self.tr
        T = MP.mpf(T)
        if T > tr:
            length = T - tr
            bp = self._zeros("W" if idx == 1 else "lamW", length)
            if bp.step is not None and bp.count > 2:
                # pure transient: |s| at the breakpoints decays geometrically
                E0 = abs(self._sig(idx, tr + bp[0]))
                nstar = None
                if E0 > eps:
                    if self.sigma == 0:
                        nstar = bp.count - 1
                    else:
                        rate = -self.sigma * bp.step
                        nstar = min(int(MP.floor(MP.log(E0 / eps) / rate)), bp.count - 1)
                        nstar = max(nstar, 0)
                        while nstar > 0 and abs(self._sig(idx, tr + bp[nstar])) <= eps:
                            nstar -= 1
                        while (nstar + 1 < bp.count
                               and abs(self._sig(idx, tr + bp[nstar + 1])) > eps):
                            nstar += 1
                if nstar is not None:
                    p = tr + bp[nstar]
                    q = tr + bp[nstar + 1] if nstar + 1 < bp.count else T
                    pieces = [(p, q)]
                else:
                    pieces = [(tr, tr + bp[0])]
            else:
                pts = [tr] + [tr + bp[i] for i in range(len(bp))] + [T]
                pieces = list(zip(pts[:-1], pts[1:]))
            res = self._walk(idx, eps, reversed(pieces))
            if res is not None:
                return res
            t_end = tr
        else:
            t_end = T
        # ramp phase [0, t_end] (|s(t_end)| <= eps is known here), walked backwards piece by piece
        bp = self._zeros("one" if idx == 1 else "lam", t_end)
        first = len(bp) - 1  # index of the last breakpoint that can start a violating piece
        if bp.step is not None and len(bp) > 2:
            # s = K + transient, |transient| at the breakpoints shrinks geometrically: beyond the
            # last n with E_n > eps - |K| every breakpoint (and so every piece) is within eps
            K = self.k / self.c if idx == 1 else MP.mpf(0)
            thr = eps - abs(K)
            E0 = abs(self._sig(idx, bp[0]) - K)
            if thr > 0 and self.sigma < 0:
                if E0 <= thr:
                    first = -1
                else:
                    n_env = int(MP.floor(MP.log(E0 / thr) / (-self.sigma * bp.step)))
                    first = min(first, n_env + 1)

        def ramp_pieces():
            hi = t_end if first == len(bp) - 1 else bp[first + 1]
            for i in range(first, -1, -1):
                lo = bp[i]
                yield (lo, hi)
                hi = lo
                if first - i > 10**6:
                    raise RuntimeError("ramp-phase walk too long")
            yield (MP.mpf(0), hi)

        return self._walk(idx, eps, ramp_pieces())

    def _walk(self, idx, eps, pieces):
        for p, q in pieces:
            sq = self._sig(idx, q)
            if abs(sq) > eps:
                return float(q)
            sp = self._sig(idx, p)
            if abs(sp) > eps:
                target = eps if sp > 0 else -eps
                return self._root(idx, target, p, q)
        return None

    def monitors(self, T, eps_v=5e-8, eps_a=5e-9):
        tr = self.tr
        T_ = MP.mpf(T)
        te = min(tr, T_)
        # y: nondecreasing on the ramp (v = k * unit-step response >= 0); afterwards extrema at
        # the zeros of v, whose |y - y_static| shrink, so the first two suffice.
        ty = [te, T_]
        tv = [te, T_]
        bpa = self._zeros("one", te)
        tv += [bpa[i] for i in range(min(2, len(bpa)))]
        if T_ > tr:
            bpv = self._zeros("W/lam", T_ - tr)
            ty += [tr + bpv[i] for i in range(min(2, len(bpv)))]
            bpa = self._zeros("W", T_ - tr)
            tv += [tr + bpa[i] for i in range(min(2, len(bpa)))]
        y_max = max(abs(self.eval_mp(t)[0]) for t in ty)
        v_max = max(abs(self.eval_mp(t)[1]) for t in tv)
        _, vT, aT = self.eval_mp(T_)
        if abs(vT) > eps_v or abs(aT) > eps_a:
            t_eq = -1.0
        else:
            lv = self._last_violation(1, MP.mpf(eps_v), T_)
            la = self._last_violation(2, MP.mpf(eps_a), T_)
            t_eq = max([x for x in (lv, la) if x is not None], default=0.0)
        return {"y_max": float(y_max), "v_y_max": float(v_max), "t_eq": float(t_eq)}


def axial_closed_form(m, c, d, F_max, t_ramp, t):
    """Exact y(t), v(t), a(t) (float arrays) of m y'' + d y' + c y = F(t) from rest."""
    ax = Axial(m, c, d, F_max, t_ramp)
    t = np.atleast_1d(np.asarray(t, dtype=float))
    out = np.empty((3, t.size))
    for i, ti in enumerate(t):
        out[:, i] = ax.eval(ti)
    return out[0], out[1], out[2]


def axial_monitors(m, c, d, F_max, t_ramp, T, eps_v=5e-8, eps_a=5e-9):
    """Exact y_max, v_y_max over [0, T] and t_eq (see MODEL.md; -1 if not at rest at T)."""
    return Axial(m, c, d, F_max, t_ramp).monitors(T, eps_v, eps_a)


# --------------------------------------------------------------------------------------------
# Six degrees of freedom (MODEL.md, Newton-Euler about the CG)
# --------------------------------------------------------------------------------------------
def rot_x(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def cardan_R(al, be, ga):
    """R = Rx(alpha) Ry(beta) Rz(gamma): screw frame S -> vertebra frame V."""
    return rot_x(al) @ rot_y(be) @ rot_z(ga)


def cardan_G(be, ga):
    """omega (body, in S) = G (alpha', beta', gamma')."""
    cb, sb, cg, sg = math.cos(be), math.sin(be), math.cos(ga), math.sin(ga)
    return np.array([[cb * cg, sg, 0.0], [-cb * sg, cg, 0.0], [sb, 0.0, 1.0]])


def cardan_Gdot(be, ga, bed, gad):
    cb, sb, cg, sg = math.cos(be), math.sin(be), math.cos(ga), math.sin(ga)
    dGdb = np.array([[-sb * cg, 0.0, 0.0], [sb * sg, 0.0, 0.0], [cb, 0.0, 0.0]])
    dGdg = np.array([[-cb * sg, cg, 0.0], [-cb * cg, -sg, 0.0], [0.0, 0.0, 0.0]])
    return dGdb * bed + dGdg * gad


def skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def make_params(**overrides) -> dict:
    p = dict(DEFAULTS)
    for k in overrides:
        if k not in p:
            raise KeyError(f"unknown parameter {k}")
    p.update(overrides)
    return p


def pull_force(t, p):
    """F_pull(t) in force-driven mode (MODEL.md)."""
    F, tr = p["F_max"], p["t_ramp"]
    f = F * t / tr if t < tr else F
    if p.get("unload", False):
        tu = p["t_unload"]
        if t >= tu:
            f = min(f, max(0.0, F * (1.0 - (t - tu) / tr)))
    return f


class _Model:
    """Pre-computed constants of the 6-DOF model."""

    def __init__(self, p):
        self.m = p["m"]
        i1, i2, i3 = inertia_moments(p)
        Q = rot_x(p["phi_inertia"])
        self.IB = Q @ np.diag([i1, i2, i3]) @ Q.T
        cg = np.array([p["cg_x"], p["cg_y"], p["cg_z"]])
        pI = np.array([p["rI_x"], p["rI_y"], p["rI_z"]])
        self.b = cg - pI  # from P to the CG (in S)
        self.h = -cg  # from the CG to H (in S)
        self.skew_b = skew(self.b)
        self.ct = np.array([p["c_x"], p["c_y"], p["c_z"]])
        self.dt = np.array([p["d_x"], p["d_y"], p["d_z"]])
        self.cr = np.array([p["c_alpha"], p["c_beta"], p["c_gamma"]])
        self.dr = np.array([p["d_alpha"], p["d_beta"], p["d_gamma"]])
        self.p = p


def _loads_vec(loads, key):
    if loads is None:
        return np.zeros(3)
    v = loads.get(key)
    return np.zeros(3) if v is None else np.asarray(v, dtype=float)


def _cross(a, b):
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


def six_dof_accel(t, state, params, loads=None, model=None):
    """(r'', theta'') and auxiliary quantities for state = (r, theta, r', theta').

    Newton-Euler about the CG (MODEL.md):
      m r''_G = F_I + F_H,  r''_G = r'' + R(w' x b + w x (w x b)),  w' = G theta'' + G' theta'
      I_B w' + w x I_B w = (-b) x R^T F_I + h x R^T F_H + G^-T Q_I + R^T T_ext
    assembled as one 6x6 linear system in (r'', theta'')."""
    M = model if model is not None else _Model(params)
    s = np.asarray(state, dtype=float)
    r, th, rd, thd = s[0:3], s[3:6], s[6:9], s[9:12]
    al, be, ga = float(th[0]), float(th[1]), float(th[2])
    R = cardan_R(al, be, ga)
    G = cardan_G(be, ga)
    Gd = cardan_Gdot(be, ga, float(thd[1]), float(thd[2]))
    w = G @ thd
    F_I = -(M.ct * r + M.dt * rd)
    Q_I = -(M.cr * th + M.dr * thd)
    tau_I = np.linalg.solve(G.T, Q_I)
    F_pull = pull_force(t, M.p)
    F_H = _loads_vec(loads, "F_ext") + np.array([0.0, F_pull, 0.0])
    T_ext = _loads_vec(loads, "T_ext")
    m, b, h, IB = M.m, M.b, M.h, M.IB
    Gdthd = Gd @ thd
    RT = R.T
    A = np.zeros((6, 6))
    A[0, 0] = A[1, 1] = A[2, 2] = m
    A[0:3, 3:6] = -m * (R @ (M.skew_b @ G))
    A[3:6, 3:6] = IB @ G
    rhs = np.empty(6)
    rhs[0:3] = F_I + F_H + m * (R @ (M.skew_b @ Gdthd - _cross(w, _cross(w, b))))
    rhs[3:6] = (_cross(-b, RT @ F_I) + _cross(h, RT @ F_H) + tau_I + RT @ T_ext
                - _cross(w, IB @ w) - IB @ Gdthd)
    acc = np.linalg.solve(A, rhs)
    return acc, {"F_pull": F_pull, "F_I": F_I, "Q_I": Q_I, "omega": w}


def six_dof_rhs(t, state, params, loads=None, model=None):
    """d/dt (r, theta, r', theta') of MODEL.md (force-driven mode)."""
    acc, _ = six_dof_accel(t, state, params, loads, model)
    s = np.asarray(state, dtype=float)
    return np.concatenate([s[6:12], acc])


def six_dof_energy(state, params):
    """Kinetic + potential energy (conserved with zero damping and no loads)."""
    M = _Model(params)
    s = np.asarray(state, dtype=float)
    r, th, rd, thd = s[0:3], s[3:6], s[6:9], s[9:12]
    R = cardan_R(*th)
    w = cardan_G(th[1], th[2]) @ thd
    vG = rd + R @ np.cross(w, M.b)
    return (0.5 * M.m * vG @ vG + 0.5 * w @ M.IB @ w
            + 0.5 * np.sum(M.ct * r * r) + 0.5 * np.sum(M.cr * th * th))


def six_dof_momentum(state, params):
    """Linear and angular momentum (about the V origin, in V) of the free screw."""
    M = _Model(params)
    s = np.asarray(state, dtype=float)
    r, th, rd, thd = s[0:3], s[3:6], s[6:9], s[9:12]
    R = cardan_R(*th)
    w = cardan_G(th[1], th[2]) @ thd
    rG = r + R @ M.b
    vG = rd + R @ np.cross(w, M.b)
    return M.m * vG, np.cross(rG, M.m * vG) + R @ (M.IB @ w)


class _Radau(Radau):
    """scipy's Radau with Hairer's upper Newton tolerance (0.03 of the error scale).

    scipy ties the Newton tolerance to sqrt(rtol); at rtol = 1e-11 that is 2e-4 of the error
    scale, below the round-off noise of the accelerations of coordinates that have come to
    rest (forces of ~400 N cancel), and the Newton iteration then never converges and the step
    size collapses.  The iteration error stays below the local error tolerance either way."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.newton_tol = 0.03


SIX_DOF_NAMES = ["x", "y", "z", "alpha", "beta", "gamma",
                 "v_x", "v_y", "v_z", "w_alpha", "w_beta", "w_gamma"]


def six_dof_radau(params, loads=None, t_eval=None, state0=None, rtol=1e-11, atol_rel=1e-11,
                  method="Radau"):
    """Integrate the 6-DOF model with Radau (rtol 1e-11, per-state atol 1e-11 x peak).

    The integration is split at the load's kinks (t_ramp, unloading) so the kinks are not
    stepped over.  Returns a dict of arrays at t_eval for SIX_DOF_NAMES plus 'a_y', 'F_pull'.
    method="DOP853" (same tolerances) is much faster for lightly damped, oscillating, non-stiff
    cases; test_reference checks that both agree on such a case."""
    t_eval = np.asarray(t_eval, dtype=float)
    T = float(t_eval[-1])
    model = _Model(params)
    y0 = np.zeros(12) if state0 is None else np.asarray(state0, dtype=float)
    kinks = [params["t_ramp"]]
    if params.get("unload", False):
        kinks += [params["t_unload"], params["t_unload"] + params["t_ramp"]]
    bounds = [0.0] + sorted(k for k in kinks if 0.0 < k < T) + [T]
    fun = lambda t, s: six_dof_rhs(t, s, params, loads, model)  # noqa: E731

    def run(atol, rt, teval):
        s = y0.copy()
        ts, ys = [], []
        for a, b in zip(bounds[:-1], bounds[1:]):
            sol = solve_ivp(fun, (a, b), s, method=_Radau if method == "Radau" else method,
                            rtol=rt, atol=atol,
                            dense_output=teval is not None)
            if not sol.success:
                raise RuntimeError(f"Radau failed: {sol.message}")
            if teval is None:
                ts.append(sol.t)
                ys.append(sol.y)
            else:
                sel = (teval >= a) & (teval <= b) if a == 0.0 else (teval > a) & (teval <= b)
                te = teval[sel]
                ts.append(te)
                ys.append(sol.sol(te) if te.size else np.zeros((12, 0)))
            s = sol.y[:, -1]  # restart exactly from the end of the segment
        return np.concatenate(ts), np.concatenate(ys, axis=1)

    # pass 1: state scales
    _, y1 = run(1e-9, 1e-6, None)
    peak = np.max(np.abs(y1), axis=1)
    # tiny but well above the round-off noise of a state at rest (a smaller atol makes the
    # step size collapse once the motion has decayed to the noise level)
    atol = np.where(peak > 0, atol_rel * peak, 1e-14)
    t, ys = run(atol, rtol, t_eval)
    if t.size != t_eval.size or not np.allclose(t, t_eval, rtol=0, atol=0):
        raise RuntimeError("Radau reference: t_eval not reproduced")
    out = {name: ys[i] for i, name in enumerate(SIX_DOF_NAMES)}
    a_y = np.empty(t.size)
    fp = np.empty(t.size)
    for i in range(t.size):
        acc, aux = six_dof_accel(t[i], ys[:, i], params, loads, model)
        a_y[i] = acc[1]
        fp[i] = aux["F_pull"]
    out["a_y"] = a_y
    out["F_pull"] = fp
    out["t"] = t
    return out
