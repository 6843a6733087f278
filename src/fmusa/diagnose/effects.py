"""The candidate effects: their parameters, bounds scaled to the data, and what tells them apart.

Everything here is knowledge about the effects of fmu/MODEL.md ("Effects beyond eq. 1"), independent of
how a model is run or fitted: the names of the fitted parameters (the baseline spring-damper ``c_y``,
``d_y`` plus those of one effect), their units, bounds and starts taken from the size of the data
(:func:`data_scales`), and the test that separates two effects the data could not.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Mapping, Sequence

import numpy as np

from fmusa.errors import FmusaError

__all__ = ["CANDIDATES", "STIFFNESS", "DAMPING", "BASELINE", "PARAM_MEANING", "EFFECT_MEANING", "SEPARATING_TESTS", "UNITS", "ROTATION_UNITS", "MAIN_PARAMETER", "DiagnoseError", "Param", "Scales",
           "data_scales", "with_bounds", "constant_rate", "model_parameters", "main_parameter", "separating_test", "EQUIVALENT_BY_CONSTRUCTION",
           "equivalent_by_construction", "equivalent_parameters", "equivalent_intervals", "BASELINE_LOOK_ALIKES"]

#: The baseline every candidate extends: the eq. 1 spring-damper, its two parameters under the catalogue's
#: names. A model description (:class:`fmusa.diagnose.interface.ModelInterface`) binds each catalogue name to
#: the FMU variable that carries it (its ``parameter_names``), so these names never have to be the FMU's.
STIFFNESS = "c_y"
DAMPING = "d_y"
BASELINE = (STIFFNESS, DAMPING)

CANDIDATES = ("nonlinear_stiffness", "viscoelastic_relaxation", "coulomb_friction", "yield_softening",
              "backlash_gap", "sensor_offset", "interface_damage")

# Which measurement tells two candidates apart when the data could not.
SEPARATING_TESTS = {
    frozenset({"nonlinear_stiffness", "yield_softening"}):
        "unload after the peak: an elastic curve retraces loading, yielding leaves a permanent set",
    frozenset({"nonlinear_stiffness", "coulomb_friction"}):
        "unload after the peak: an elastic curve retraces loading, friction opens a loop (on loading alone, "
        "friction after its pre-slip is a bend of the curve)",
    frozenset({"nonlinear_stiffness", "backlash_gap"}):
        "load through zero in both directions: slack gives a zero-force band, a toe region does not",
    frozenset({"nonlinear_stiffness", "viscoelastic_relaxation"}):
        "test at several rates or hold the displacement: only the Maxwell branch depends on rate and relaxes",
    frozenset({"viscoelastic_relaxation", "coulomb_friction"}):
        "hold the displacement: a Maxwell branch relaxes, friction holds its force; or change the rate",
    frozenset({"viscoelastic_relaxation", "yield_softening"}):
        "hold the displacement and test at several rates: relaxation is rate dependent, yield is not",
    frozenset({"coulomb_friction", "yield_softening"}):
        "none on the axial force-displacement channel: the two are the same equations (see "
        "EQUIVALENT_BY_CONSTRUCTION); only a look inside the interface (sliding marks on the thread against "
        "crushed bone, e.g. by micro-CT after the test) tells them apart",
    frozenset({"coulomb_friction", "sensor_offset"}):
        "reverse the motion: friction changes sign with the velocity, a sensor offset does not",
    frozenset({"backlash_gap", "sensor_offset"}):
        "read the channels at rest before loading and load through zero",
    frozenset({"backlash_gap", "yield_softening"}):
        "unload to zero and reload: slack shows at every reloading, a yield set only after yielding",
    frozenset({"sensor_offset", "nonlinear_stiffness"}):
        "read the channels at rest before loading (zero load must read zero)",
    frozenset({"sensor_offset", "viscoelastic_relaxation"}):
        "hold the displacement long enough for relaxation to finish, then unload to zero",
    frozenset({"sensor_offset", "yield_softening"}):
        "unload to zero: a yield set remains in displacement, an offset stays constant in the channel",
    frozenset({"backlash_gap", "viscoelastic_relaxation"}):
        "hold the displacement: relaxation shows, slack does not",
    frozenset({"interface_damage", "yield_softening"}):
        "unload after the peak: a damaged interface unloads on the secant to the origin (no permanent set), "
        "a yielded one with its elastic stiffness and keeps a set; on loading alone both soften past a force",
    frozenset({"interface_damage", "coulomb_friction"}):
        "unload after the peak: friction drops by twice its force at the reversal and opens a loop, a damaged "
        "interface unloads on the secant to the origin without a jump",
    frozenset({"interface_damage", "nonlinear_stiffness"}):
        "unload after the peak and reload: a bend retraces loading, damage unloads on a lower secant and "
        "reloads on it up to the largest displacement reached",
    frozenset({"interface_damage", "viscoelastic_relaxation"}):
        "hold the displacement or test at a second rate: relaxation depends on time, damage on the largest "
        "displacement reached",
    frozenset({"interface_damage", "backlash_gap"}):
        "unload to zero and reload: slack shows at every reloading from zero, damage only lowers the secant",
    frozenset({"interface_damage", "sensor_offset"}):
        "read the channels at rest before loading, and unload: a damaged interface carries no force at zero",
    frozenset({"backlash_gap", "coulomb_friction"}):
        "reverse the motion at a load well above zero: friction drops by twice its force, slack does not",
}

# ---------------------------------------------------------------------- equivalent effects

# Two candidates that are the same equations under another parametrisation: no data of this channel can
# tell them apart, whatever the protocol. Spring c' beside a Bouc-Wen friction (fric_F, fric_x) is a spring
# c beside nothing that yields at yield_F with post-yield stiffness yield_ratio*c (MODEL.md, both with
# n = 4): F = r c y + (1 - r) F_Y z, z' = v/(F_Y/c) (1 - H(zv) z^4) is F = c' y + F_f z, z' = v/x_f (...)
# exactly when c' = r c, F_f = (1 - r) F_Y, x_f = F_Y / c (and back: c = c' + F_f/x_f,
# r = c'/c, F_Y = F_f + c' x_f). Spring || Jenkins element (spring in series with a slider) is bilinear
# kinematic hardening.
EQUIVALENT_BY_CONSTRUCTION = {
    frozenset({"coulomb_friction", "yield_softening"}): {
        "mapping": "c_y' = yield_ratio*c_y, fric_F = (1 - yield_ratio)*yield_F, fric_x = yield_F/c_y "
                   "(back: c_y = c_y' + fric_F/fric_x, yield_ratio = c_y'/c_y, yield_F = fric_F + c_y'*fric_x)",
        "readings": {
            "coulomb_friction": "the thread slides in the bone against a friction force fric_F after a "
                                "pre-slip of fric_x, beside an elastic interface c_y that recovers fully",
            "yield_softening": "the interface itself yields at yield_F (stiffness c_y before, yield_ratio*c_y "
                               "after) with kinematic hardening: the yield surface moves with the load, so a "
                               "reversal yields again after 2*yield_F*(1 - yield_ratio) of force",
        },
        "why": "spring beside a Jenkins element (spring in series with a slider) is bilinear kinematic "
               "hardening: the same force for every displacement history, so for every protocol",
    },
}

# Candidates the baseline (c_y, d_y) mimics under a protocol that lacks a feature, and what separates them.
BASELINE_LOOK_ALIKES = {
    "coulomb_friction": {
        "missing": ("hold", "several_rates"), "drive": "displacement",
        "why": "during a constant-rate ramp a rate-independent friction force fric_F equals a viscous one "
               "d_y*v (d_y = fric_F/v), and at a reversal at the same rate both jump by twice their value",
        "separating_test": "hold the displacement (friction keeps its force, damping drops to zero) or "
                           "load at a second rate (damping scales with the rate, friction does not)",
    },
    "viscoelastic_relaxation": {
        "missing": ("hold", "several_rates"), "drive": "displacement",
        "why": "at one constant rate a Maxwell branch with a short time constant adds a constant force "
               "ve_k*ve_tau*v, which a larger damping d_y reproduces",
        "separating_test": "hold the displacement (the branch relaxes over ve_tau) or load at a second rate",
    },
    "sensor_offset": {
        "missing": ("hold", "several_rates", "unloading"), "drive": "displacement",
        "why": "on a single constant-rate ramp a constant force bias equals a damping force d_y*v",
        "separating_test": "hold or unload (the damping force vanishes or reverses, a bias stays)",
    },
}


def equivalent_by_construction(a: str, b: str) -> dict | None:
    """The entry of EQUIVALENT_BY_CONSTRUCTION for the pair, or None when they are different models."""
    return EQUIVALENT_BY_CONSTRUCTION.get(frozenset({a, b}))


def equivalent_parameters(effect: str, params: dict, other: str) -> dict | None:
    """The parameters of ``other`` that give exactly the same model as ``effect`` with ``params``."""
    if {effect, other} != {"coulomb_friction", "yield_softening"}:
        return None
    c, d = params["c_y"], params["d_y"]
    if effect == "yield_softening":
        r, F_Y = params["yield_ratio"], params["yield_F"]
        return {"c_y": r * c, "d_y": d, "fric_F": (1 - r) * F_Y, "fric_x": F_Y / c}
    c1, F_f, x_f = c, params["fric_F"], params["fric_x"]
    c_tot = c1 + F_f / x_f
    return {"c_y": c_tot, "d_y": d, "yield_ratio": c1 / c_tot, "yield_F": F_f + c1 * x_f}


def equivalent_intervals(effect: str, params: dict, ci95: dict, other: str) -> dict | None:
    """The 95 % intervals of ``other``'s parameters, mapped from ``effect``'s: the mapping of
    EQUIVALENT_BY_CONSTRUCTION is monotone in each parameter over positive values, so the image of the box
    of intervals lies within the box spanned by the images of its corners (a conservative interval)."""
    if equivalent_parameters(effect, params, other) is None:
        return None
    names = [n for n in params if n in ci95]
    corners = []
    for bits in range(2 ** len(names)):
        p = dict(params)
        for i, n in enumerate(names):
            p[n] = ci95[n][(bits >> i) & 1]
        corners.append(equivalent_parameters(effect, p, other))
    return {k: (min(c[k] for c in corners), max(c[k] for c in corners)) for k in corners[0]}


#: What each fitted parameter means (the report's tables).
PARAM_MEANING = {
    "c_y": "stiffness c (eq. 1)",
    "d_y": "damping d (eq. 1)",
    "gap": "slack: no force within ±gap",
    "nl_ratio": "stiffness past the breakpoint / c",
    "nl_y_b": "breakpoint displacement of the stiffness",
    "yield_ratio": "stiffness after yield / c",
    "yield_F": "yield force",
    "fric_F": "Coulomb friction force",
    "fric_x": "pre-slip displacement of the friction (stiffness fric_F/fric_x before it slides)",
    "ve_k": "stiffness of the Maxwell branch",
    "ve_tau": "relaxation time of the Maxwell branch",
    "F_offset": "bias of the force channel",
    "y_offset": "bias of the displacement channel",
    "dmg_y0": "onset displacement of the interface damage (largest displacement reached)",
    "dmg_rate": "softening rate of the damage per displacement past the onset",
    "dmg_F_res": "residual force of the failed interface (friction plateau)",
}

def in_motion(text: str, motion: str | None) -> str:
    """A catalogue text (:data:`PARAM_MEANING`, :data:`EFFECT_MEANING`) in the words of the interface's motion:
    under rotation an angle and a torque where translation has a displacement and a force."""
    if motion != "rotation":       # motion.ROTATION (motion reads the catalogue's units from here)
        return text
    for a, b in (("force–displacement", "torque–angle"), ("displacements", "angles"), ("displacement", "angle"),
                 ("forces", "torques"), ("force", "torque")):
        text = text.replace(a, b)
    return text


#: What each effect means physically (fmu/MODEL.md, "Effects beyond eq. 1").
EFFECT_MEANING = {
    "none": "the baseline spring–damper (eq. 1) explains the data within their noise",
    "nonlinear_stiffness": "the force–displacement curve bends (stiffness changes past a breakpoint) and is "
                           "elastic: unloading retraces loading",
    "viscoelastic_relaxation": "a Maxwell branch (spring in series with a dashpot): force relaxes at held "
                               "displacement, displacement creeps at held force, stiffness rises with rate",
    "coulomb_friction": "a rate-independent force opposing the motion: a hysteresis loop of constant width",
    "yield_softening": "the interface yields (threads stripping bone): lower stiffness past a yield force and "
                       "a permanent set after unloading",
    "backlash_gap": "slack: no force until the displacement passes a gap",
    "sensor_offset": "a constant bias in the measured channel",
    "interface_damage": "the interface fails: past an onset displacement its strength drops towards a residual "
                        "(friction) force, and it unloads and reloads on the secant to the origin",
}

UNITS = {"c_y": "N/m", "d_y": "N.s/m", "gap": "m", "nl_ratio": "1", "nl_y_b": "m", "yield_ratio": "1",
         "yield_F": "N", "fric_F": "N", "fric_x": "m", "ve_k": "N/m", "ve_tau": "s", "F_offset": "N", "y_offset": "m",
         "dmg_y0": "m", "dmg_rate": "1/m", "dmg_F_res": "N"}
#: The same parameters' SI units when the interface is rotational (``model: motion: rotation``): an angle for a
#: displacement, a torque for a force (:mod:`fmusa.diagnose.motion`).
ROTATION_UNITS = {"c_y": "N·m/rad", "d_y": "N·m·s/rad", "gap": "rad", "nl_ratio": "1", "nl_y_b": "rad",
                  "yield_ratio": "1", "yield_F": "N·m", "fric_F": "N·m", "fric_x": "rad", "ve_k": "N·m/rad",
                  "ve_tau": "s", "F_offset": "N·m", "y_offset": "rad", "dmg_y0": "rad", "dmg_rate": "1/rad",
                  "dmg_F_res": "N·m"}

MAIN_PARAMETER = {"nonlinear_stiffness": "nl_ratio", "viscoelastic_relaxation": "ve_tau",
                  "coulomb_friction": "fric_F", "yield_softening": "yield_F", "backlash_gap": "gap",
                  "sensor_offset": None,   # F_offset or y_offset, by drive
                  "interface_damage": "dmg_F_res"}


class DiagnoseError(FmusaError, ValueError):
    """Bad input to the diagnosis: names what is wrong and the fix.

    Fix: change the argument the message names (an effect name, a drive ``displacement`` or ``force``, an
    option out of range) as it says.
    """


@dataclass(frozen=True)
class Param:
    """One fitted parameter: bounds and starts in natural units, optimised on a log or linear scale."""
    name: str
    lower: float
    upper: float
    starts: tuple[float, ...]
    log: bool = False

    def to_x(self, value: float) -> float:
        """Natural value -> optimiser coordinate."""
        return math.log(value) if self.log else value

    def from_x(self, x: float) -> float:
        """Optimiser coordinate -> natural value."""
        return math.exp(x) if self.log else x


@dataclass(frozen=True)
class Scales:
    """Sizes of the data that set bounds and starts: peak displacement and force, secant stiffness, times."""
    y_pk: float
    F_pk: float
    v_pk: float
    c0: float
    t_min: float
    t_max: float
    dt_min: float
    #: the damping the rate content of the data asks for: the least-squares d of F - c0 y on v, in [0, d_max]
    d0: float = 0.0
    #: bounds a model description or study file sets in place of the data-scaled ones: name -> (lower, upper)
    bounds: Mapping[str, tuple[float, float]] = field(default_factory=dict)


def with_bounds(sc: Scales, bounds: Mapping[str, tuple[float, float]] | None) -> Scales:
    """The scales with the given bounds in place of the data-scaled ones (their starts clipped into them)."""
    return replace(sc, bounds=dict(bounds)) if bounds else sc


def data_scales(experiments: Sequence) -> Scales:
    """Bounds and starts come from these, so a test in mm and kN fits as well as one in m and N."""
    y_pk = max(float(np.max(np.abs(e.displacement))) for e in experiments)
    F_pk = max(float(np.max(np.abs(e.force))) for e in experiments)
    v_pk = max(float(np.max(np.abs(np.diff(e.displacement) / np.diff(e.t)))) for e in experiments)
    if not (y_pk > 0 and F_pk > 0):
        raise DiagnoseError("the data have no displacement or no force: nothing to calibrate")
    # secant stiffness from a least-squares line through the origin over all experiments
    ys = np.concatenate([e.displacement for e in experiments])
    Fs = np.concatenate([e.force for e in experiments])
    c0 = abs(float(np.dot(ys, Fs) / np.dot(ys, ys)))
    durations = [float(e.t[-1] - e.t[0]) for e in experiments]
    dt_min = min(float(np.min(np.diff(e.t))) for e in experiments)
    c0 = c0 if c0 > 0 else F_pk / y_pk
    # damping from the rate content: what of the force the secant spring leaves, projected on the velocity
    vs = np.concatenate([np.gradient(e.displacement, e.t) for e in experiments])
    vv = float(np.dot(vs, vs))
    d0 = float(np.dot(Fs - c0 * ys, vs) / vv) if vv > 0 else 0.0
    d0 = min(max(d0, 0.0), 2.0 * F_pk / v_pk) if math.isfinite(d0) else 0.0
    return Scales(y_pk=y_pk, F_pk=F_pk, v_pk=v_pk, c0=c0, t_min=min(durations), t_max=max(durations),
                  dt_min=dt_min, d0=d0)


def constant_rate(experiments: Sequence, tol: float = 0.05) -> dict | None:
    """Whether every test drives at one constant rate (one direction, the same rate in all): then the damping
    force d_y*v is a constant, which no fit can tell from an offset or a friction force. Returns the rate
    (SI, of the drive channel) and why, or None when the rate varies (a hold, an unloading, a second rate)."""
    rates = []
    for e in experiments:
        u = np.asarray(e.drive_signal, float)
        du = np.diff(u) / np.diff(e.t)
        if du.size < 3:
            return None
        med = float(np.median(du))
        if med == 0 or float(np.mean(np.abs(du - med) <= tol * abs(med))) < 0.9:
            return None
        rates.append(med)
    if not rates or max(rates) - min(rates) > tol * max(abs(r) for r in rates):
        return None
    return {"rate": float(np.median(rates)),
            "why": "the drive has one constant rate, so the damping force d_y*v is a constant that no fit can "
                   "tell from a force offset (or a friction force): d_y is held at 0",
            "identifying_test": "a test at a second rate (the damping force scales with it) or a hold (it "
                                "vanishes)"}


def model_parameters(effect: str, drive: str, sc: Scales) -> list[Param]:
    """The fitted parameters of the baseline (c_y, d_y) plus those of one effect, with data-scaled bounds
    (or the bounds ``sc.bounds`` sets, the starts clipped into them)."""
    params = _catalogue_parameters(effect, drive, sc)
    if not sc.bounds:
        return params
    out = []
    for p in params:
        if p.name in sc.bounds:
            lo, hi = sc.bounds[p.name]
            starts = tuple(dict.fromkeys(min(max(s, lo), hi) for s in p.starts))
            p = replace(p, lower=lo, upper=hi, starts=starts, log=p.log and lo > 0)
        out.append(p)
    return out


def _catalogue_parameters(effect: str, drive: str, sc: Scales) -> list[Param]:
    """The catalogue's parameters of a model with data-scaled bounds."""
    if "+" in effect:   # several effects at once, e.g. "nonlinear_stiffness+viscoelastic_relaxation"
        parts = effect.split("+")
        out = _catalogue_parameters(parts[0], drive, sc)
        for part in parts[1:]:
            out += _catalogue_parameters(part, drive, sc)[2:]
        return out
    c0, y_pk, F_pk = sc.c0, sc.y_pk, sc.F_pk
    d_max = 2.0 * F_pk / sc.v_pk
    # starts: the secant stiffness of the data, the damping its rate content asks for (at least a trace)
    base = [Param("c_y", c0 / 100, c0 * 100, (c0,), log=True),
            Param("d_y", 0.0, d_max, (min(max(sc.d0, 0.001 * d_max), d_max),))]
    if effect == "none":
        return base
    if effect == "backlash_gap":
        return base + [Param("gap", 0.0, 0.9 * y_pk, (0.05 * y_pk, 0.2 * y_pk, 0.4 * y_pk))]
    if effect == "nonlinear_stiffness":
        return base + [Param("nl_ratio", 0.05, 20.0, (0.5, 2.0), log=True),
                       Param("nl_y_b", 0.02 * y_pk, 0.98 * y_pk, (0.25 * y_pk, 0.5 * y_pk, 0.75 * y_pk))]
    if effect == "yield_softening":
        return base + [Param("yield_ratio", 0.0, 0.99, (0.3,)),
                       Param("yield_F", 0.05 * F_pk, 1.5 * F_pk, (0.3 * F_pk, 0.6 * F_pk, 0.9 * F_pk),
                             log=True)]
    if effect == "coulomb_friction":
        # the pre-slip is fitted too: with it fixed, friction is a subset of its equivalent
        # (yield_softening, EQUIVALENT_BY_CONSTRUCTION) and fits worse than it for no physical reason
        # bounds cover the image of yield_softening's (fric_F = (1 - yield_ratio)*yield_F, fric_x =
        # yield_F/c_y), starts both a stiff pre-slip (Coulomb-like) and a long one (yield-like)
        return base + [Param("fric_F", 0.0, 1.5 * F_pk, (0.05 * F_pk, 0.3 * F_pk)),
                       Param("fric_x", 1e-4 * y_pk, 2.0 * y_pk, (0.01 * y_pk, 0.1 * y_pk, 0.4 * y_pk), log=True)]
    if effect == "viscoelastic_relaxation":
        tau_lo, tau_hi = max(sc.dt_min, 1e-4 * sc.t_max), 10.0 * sc.t_max
        taus = tuple(min(max(f * sc.t_max, tau_lo), tau_hi) for f in (0.03, 0.3))
        if sc.t_max > 30 * sc.t_min:   # several rates: a start at the short tests' time scale too
            taus = taus + (min(max(0.3 * sc.t_min, tau_lo), tau_hi),)
        return base + [Param("ve_k", 0.0, 20.0 * c0, (0.3 * c0, 1.0 * c0)),
                       Param("ve_tau", tau_lo, tau_hi, taus, log=True)]
    if effect == "interface_damage":
        # onset within the data, softening over 0.3 to 10 times the span past it, residual up to the peak.
        # Under a force drive a residual below the applied force lets the failed interface run away (the
        # screw of a force-driven ScrewVertebra to 0.48 m against 0.25 mm measured, from both starts of
        # dmg_y0): no least-squares step comes back from there, so a start that carries the peak follows
        res = (0.2 * F_pk, F_pk) if drive == "force" else (0.2 * F_pk,)
        return base + [Param("dmg_y0", 0.05 * y_pk, 0.95 * y_pk, (0.3 * y_pk, 0.6 * y_pk), log=True),
                       Param("dmg_rate", 0.1 / y_pk, 100.0 / y_pk, (3.0 / y_pk,), log=True),
                       Param("dmg_F_res", 0.0, 1.2 * F_pk, res)]
    if effect == "sensor_offset":
        if drive == "displacement":
            return base + [Param("F_offset", -0.5 * F_pk, 0.5 * F_pk, (0.0,))]
        return base + [Param("y_offset", -0.5 * y_pk, 0.5 * y_pk, (0.0,))]
    raise DiagnoseError(f"unknown effect {effect!r}; use one of none, {', '.join(CANDIDATES)}")


def main_parameter(effect: str, drive: str) -> str | None:
    """The parameter that sizes an effect (the sensor offset's depends on which channel is measured)."""
    if effect == "sensor_offset":
        return "F_offset" if drive == "displacement" else "y_offset"
    return MAIN_PARAMETER.get(effect)


def separating_test(a: str, b: str) -> str:
    """The measurement that would tell ``a`` from ``b`` (a generic rich protocol for pairs not listed)."""
    return SEPARATING_TESTS.get(frozenset({a, b}), "a test that loads, holds and unloads at several rates")
