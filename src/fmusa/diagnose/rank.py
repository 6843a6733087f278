"""Ranking: which candidate's gain over the baseline is significant, which ones the data cannot tell apart.

A candidate is significant when it passes three tests against the baseline (ΔBIC, held-out RMSE ratio,
nested F test: :class:`Thresholds`); the winner is the best significant one. Candidates close to it, and
look-alikes the test protocol cannot separate from it (no unloading, no hold, a single rate), are named
with the measurement that would separate them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy import stats

from fmusa.diagnose.calibrate import Fit
from fmusa.diagnose.effects import separating_test

__all__ = ["Thresholds", "nested_p_value", "rank_candidates", "choose_effect", "PROTOCOL_FEATURES",
           "protocol_features", "protocol_blind_spots", "indistinguishable"]


@dataclass(frozen=True)
class Thresholds:
    """What counts as a significant gain over the baseline. BIC's penalty keeps noise from winning;
    the held-out ratio demands that the gain carries over to data the fit did not see."""
    delta_bic: float = -10.0
    heldout_ratio: float = 0.9
    p_value: float = 1e-3
    tie_bic: float = 10.0
    tie_heldout: float = 1.1


def nested_p_value(base: Fit, ext: Fit) -> float:
    """F test of the extra parameters of a nested model (white-noise assumption)."""
    dk = ext.k - base.k
    dof = ext.n - ext.k
    if dk <= 0 or dof <= 0 or ext.rss <= 0:
        return 1.0
    F = max(base.rss - ext.rss, 0.0) / dk / (ext.rss / dof)
    return float(stats.f.sf(F, dk, dof))


def rank_candidates(base: Fit, fits: dict[str, Fit], th: Thresholds = Thresholds()) -> list[dict]:
    """Every candidate with its scores, best first: significant ones first, then by held-out error
    (prediction on unseen data separates look-alike families better than the in-sample BIC does)."""
    rows = []
    for name, f in fits.items():
        p = nested_p_value(base, f)
        h_ratio = f.heldout_rmse / base.heldout_rmse if base.heldout_rmse > 0 else float("nan")
        d_bic = f.bic - base.bic
        significant = bool(d_bic < th.delta_bic and h_ratio < th.heldout_ratio and p < th.p_value)
        rows.append({"effect": name, "significant": significant, "rmse": f.rmse,
                     "heldout_rmse": f.heldout_rmse, "rmse_ratio": f.rmse / base.rmse,
                     "heldout_rmse_ratio": h_ratio, "aic": f.aic, "bic": f.bic,
                     "delta_aic": f.aic - base.aic, "delta_bic": d_bic, "p_value": p, "k": f.k,
                     "params": dict(f.params)})
    rows.sort(key=lambda r: (not r["significant"], r["heldout_rmse"], r["bic"]))
    return rows


def choose_effect(ranking: list[dict], th: Thresholds = Thresholds()) -> tuple[str, list[str]]:
    """The winner (or none) and the significant candidates the data cannot tell from it."""
    sig = [r for r in ranking if r["significant"]]
    if not sig:
        return "none", []
    win = sig[0]
    ties = [r["effect"] for r in sig[1:]
            if r["heldout_rmse"] < th.tie_heldout * win["heldout_rmse"] and r["bic"] - win["bic"] < th.tie_bic]
    return win["effect"], ties


# ---------------------------------------------------------------------- what the protocol can show

# Features of a test protocol that separate look-alike effects, and the pairs each one separates.
PROTOCOL_FEATURES = {
    "unloading": (frozenset({"nonlinear_stiffness", "yield_softening"}),
                  frozenset({"coulomb_friction", "sensor_offset"}),
                  frozenset({"coulomb_friction", "yield_softening"})),
    "hold": (frozenset({"viscoelastic_relaxation", "coulomb_friction"}),),
    "several_rates_or_hold": (frozenset({"viscoelastic_relaxation", "nonlinear_stiffness"}),
                              frozenset({"viscoelastic_relaxation", "yield_softening"})),
}


def protocol_features(experiments: Sequence) -> dict:
    """What the tests did: unload after the peak, hold still, run at several rates."""
    unloading = hold = False
    rates = []
    for e in experiments:
        u = np.abs(np.asarray(e.drive_signal, float))
        pk = float(np.max(u))
        k = int(np.argmax(u))
        if pk > 0 and float(np.min(u[k:])) < 0.7 * pk:
            unloading = True
        du = np.abs(np.diff(e.drive_signal)) / np.diff(e.t)
        rate = float(np.median(du[du > 0.1 * np.max(du)])) if np.max(du) > 0 else 0.0
        rates.append(rate)
        still = du < 0.02 * np.max(du) if np.max(du) > 0 else np.ones_like(du, bool)
        if float(np.sum(np.diff(e.t)[still])) > 0.1 * float(e.t[-1] - e.t[0]):
            hold = True
    rates = [r for r in rates if r > 0]
    several = bool(rates) and max(rates) > 3.0 * min(rates)
    return {"unloading": unloading, "hold": hold, "several_rates": several,
            "several_rates_or_hold": several or hold}


def protocol_blind_spots(effect: str, features: dict) -> list[dict]:
    """The candidates this protocol cannot separate from ``effect``, whatever the scores say."""
    out = []
    for feat, pairs in PROTOCOL_FEATURES.items():
        if features.get(feat):
            continue
        for pair in pairs:
            if effect in pair:
                other = next(iter(pair - {effect}))
                out.append({"effect": other, "missing": feat, "separating_test": separating_test(effect, other)})
    return out


def indistinguishable(effect: str, ties: Sequence[str], ranking: list[dict], features: dict) -> list[dict]:
    """The candidates the data cannot tell from ``effect``: ties on the scores, then look-alikes the
    protocol cannot separate, each with the reason and the test that would separate them."""
    out = [{"effect": t, "reason": "scores within the tie margins", "separating_test": separating_test(effect, t)}
           for t in ties]
    if effect == "none":
        return out
    significant = {r["effect"] for r in ranking if r["significant"]}
    for b in protocol_blind_spots(effect, features):
        # only a look-alike that explains the data too: one that fails here was told apart after all
        if b["effect"] not in ties and b["effect"] in significant:
            out.append({"effect": b["effect"], "reason": f"the tests have no {b['missing'].replace('_', ' ')}",
                        "separating_test": b["separating_test"]})
    return out
