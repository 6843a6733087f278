"""Whether a fitted effect is physically possible in the test that produced it, and whether the protocol
can identify it at all.

An optimiser can lower the residual with parameters no test supports: a friction whose pre-slip is longer
than the whole travel never slides (it acts as an extra spring), a damaged interface whose residual force is
above the measured peak never fails, a relaxation time ten times the test's length never relaxes. Such a
step is not an effect of the specimen; :func:`implausible` says why, with the test that would support it.
:func:`unidentifiable` says when the protocol itself cannot identify an effect (the physics of
``tests/test_identifiability.py``'s table): it is then listed as "cannot tell", not added.

Nothing here runs the FMU: the checks read the fitted parameters and the measured data.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from fmusa.diagnose import motion as mo

__all__ = ["Support", "support_of", "implausible", "unidentifiable", "IDENTIFYING_FEATURES",
           "MIN_SAMPLES_PER_TAU"]

#: a time constant shorter than this many sampling intervals cannot be told from an instantaneous force
MIN_SAMPLES_PER_TAU = 3.0


@dataclass(frozen=True)
class Support:
    """What the tests can show: the largest displacement reached (travel, m), the largest force (N), the
    longest test (s) and the shortest sampling interval (s)."""
    travel: float
    peak_force: float
    longest: float
    dt_min: float


def support_of(experiments: Sequence) -> Support:
    """The travel, peak force, longest duration and finest sampling (the smallest median sampling interval of
    a test) of the measured tests (all SI)."""
    travel = max(float(np.max(np.abs(np.asarray(e.displacement, float)))) for e in experiments)
    peak = max(float(np.max(np.abs(np.asarray(e.force, float)))) for e in experiments)
    longest = max(float(e.t[-1] - e.t[0]) for e in experiments)
    # the median step: the last block of a block-averaged record is shorter, its mean time closer to the one before
    dt = min(float(np.median(np.diff(np.asarray(e.t, float)))) for e in experiments if len(e.t) > 1)
    return Support(travel=travel, peak_force=peak, longest=longest, dt_min=dt)


def _mm(x: float) -> str:
    """A displacement as the messages write it (an angle in deg for a rotational interface)."""
    if mo.current() == mo.ROTATION:
        return f"{x * 180.0 / math.pi:.3g} deg"
    return f"{x * 1e3:.3g} mm"


def _n(x: float) -> str:
    """A force as the messages write it (a torque in N·m for a rotational interface)."""
    return f"{x:.3g} N·m" if mo.current() == mo.ROTATION else f"{x:.3g} N"


def _s(x: float) -> str:
    return f"{x:.3g} s"


def implausible(effect: str, params: Mapping[str, float], support: Support) -> list[dict]:
    """Every parameter of the effects in ``effect`` ("a+b" for a chain) outside what the tests support:
    parameter, value, the limit, why, and the test that would support such a value. Empty when all hold."""
    out = []

    def bad(name: str, why: str, test: str) -> None:
        out.append({"parameter": name, "value": float(params[name]), "why": why, "test": test})

    s = support
    parts = effect.split("+")
    if "coulomb_friction" in parts and params.get("fric_x", 0.0) >= s.travel:
        bad("fric_x", f"the pre-slip fric_x = {_mm(params['fric_x'])} is not within the travel "
                      f"({_mm(s.travel)}): the friction never slides and acts as an extra spring",
            f"a test with a travel well beyond {_mm(params['fric_x'])}")
    if "coulomb_friction" in parts and params.get("fric_F", 0.0) >= s.peak_force:
        bad("fric_F", f"the friction force fric_F = {_n(params['fric_F'])} is not below the peak force "
                      f"({_n(s.peak_force)}): it never slides within the test",
            f"a test loaded beyond {_n(params['fric_F'])}")
    if "interface_damage" in parts:
        if params.get("dmg_F_res", 0.0) >= s.peak_force:
            bad("dmg_F_res", f"the residual force dmg_F_res = {_n(params['dmg_F_res'])} is not below the peak "
                             f"force ({_n(s.peak_force)}): the interface never loses strength in this test",
                "a test loaded past the failure, to a force that drops")
        if params.get("dmg_y0", 0.0) >= s.travel:
            bad("dmg_y0", f"the onset dmg_y0 = {_mm(params['dmg_y0'])} is outside the loaded range "
                          f"(0 to {_mm(s.travel)})", f"a test with a travel beyond {_mm(params['dmg_y0'])}")
    if "viscoelastic_relaxation" in parts:
        tau = params.get("ve_tau", 0.0)
        if tau > s.longest:
            bad("ve_tau", f"the relaxation time ve_tau = {_s(tau)} is longer than the longest test "
                          f"({_s(s.longest)}): the branch never relaxes within the test",
                f"a hold of several times {_s(tau)}")
        elif tau < MIN_SAMPLES_PER_TAU * s.dt_min:
            bad("ve_tau", f"the relaxation time ve_tau = {_s(tau)} is shorter than {MIN_SAMPLES_PER_TAU:g} "
                          f"sampling intervals ({_s(MIN_SAMPLES_PER_TAU * s.dt_min)}): the test cannot resolve it",
                f"sampling faster than {_s(tau / MIN_SAMPLES_PER_TAU)}")
    if "yield_softening" in parts and params.get("yield_F", 0.0) >= s.peak_force:
        bad("yield_F", f"the yield force yield_F = {_n(params['yield_F'])} is not below the peak force "
                       f"({_n(s.peak_force)}): the interface never yields within the test",
            f"a test loaded beyond {_n(params['yield_F'])}")
    if "backlash_gap" in parts and params.get("gap", 0.0) >= s.travel:
        bad("gap", f"the slack gap = {_mm(params['gap'])} is not within the travel ({_mm(s.travel)})",
            f"a test with a travel beyond {_mm(params['gap'])}")
    if "nonlinear_stiffness" in parts and params.get("nl_y_b", 0.0) >= s.travel:
        bad("nl_y_b", f"the breakpoint nl_y_b = {_mm(params['nl_y_b'])} is outside the loaded range "
                      f"(0 to {_mm(s.travel)})", f"a test with a travel beyond {_mm(params['nl_y_b'])}")
    return out


#: Displacement drive: the protocol features an effect needs to be identified at all, as alternatives (any one
#: tuple of features, all of its members present), the look-alike that hides it otherwise and the test that
#: tells (the physics of tests/test_identifiability.py's ``expected``, which checks this table).
IDENTIFYING_FEATURES: dict[str, dict] = {
    "coulomb_friction": {
        "needs": (("unloading", "hold"), ("unloading", "several_rates")),
        "hidden_by": "the damping, a Maxwell branch or an elastic bend",
        "test": "unload after the peak, and hold the displacement or load at a second rate"},
    "yield_softening": {
        "needs": (("unloading",),),
        "hidden_by": "a softening nonlinear stiffness",
        "test": "unload after the peak (elastic retraces, yield leaves a set)"},
    "viscoelastic_relaxation": {
        "needs": (("hold",), ("several_rates",)),
        "hidden_by": "a smooth softening or a damping",
        "test": "hold the displacement (the force relaxes) or load at a second rate"},
}
# not listed: backlash_gap and interface_damage (identifiable under every protocol), a sensor offset (against the
# load it is identifiable on a ramp too: the sign decides, known only after the fit) and a nonlinear stiffness
# (a stiffening one is identifiable everywhere)


def unidentifiable(effect: str, features: Mapping[str, bool], drive: str = "displacement") -> dict | None:
    """None when the protocol (``features`` of :func:`fmusa.diagnose.rank.protocol_features`) can identify
    ``effect`` in this drive; else what it lacks, the look-alike and the test that would tell."""
    row = IDENTIFYING_FEATURES.get(effect)
    if drive != "displacement" or row is None:
        return None
    if any(all(features.get(f) for f in alt) for alt in row["needs"]):
        return None
    missing = ", or ".join(" with ".join(f.replace("_", " ") for f in alt) for alt in row["needs"])
    return {"effect": effect, "missing": missing, "hidden_by": row["hidden_by"], "separating_test": row["test"],
            "reason": f"cannot tell, because the tests have no {missing}: {row['hidden_by']} gives the same "
                      f"response here"}
