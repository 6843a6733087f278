"""Ranking: which candidate's gain over the baseline is significant, which ones the data cannot tell apart.

A candidate is significant when it passes three statistical tests against the baseline (ΔBIC, held-out
RMSE ratio, nested F test: :class:`Thresholds`) and it matters: its prediction differs from the baseline's
by more than the noise and more than a physical floor (a fraction of the measured range) somewhere on the
data (:func:`effect_size`). Significance alone is not enough: on noise-free data any extra parameter passes
the statistical tests by fitting round-off. The winner is the best significant one. Candidates close to it,
and look-alikes the test protocol cannot separate from it (no unloading, no hold, a single rate), are named
with the measurement that would separate them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from fmusa.diagnose.calibrate import Fit, nested_p_value
from fmusa.diagnose.effects import BASELINE_LOOK_ALIKES, equivalent_by_construction, separating_test

__all__ = ["Thresholds", "nested_p_value", "effect_size", "rank_candidates", "choose_effect", "PROTOCOL_FEATURES",
           "protocol_features", "protocol_blind_spots", "indistinguishable", "equivalent_by_fit", "GROUP_SEP",
           "group_members"]

#: joins the names of candidates the data cannot decide between: "coulomb_friction ≡ yield_softening"
GROUP_SEP = " ≡ "
#: a look-alike whose RMSE and held-out RMSE are both this many times the named effect's is told apart
#: (10: a Maxwell branch that a load-unload test fits 8x better than friction, or a bend 3.7x worse than
#: yield on ramp-holds, stay look-alikes whose separating test is named; a failure curve leaves friction and
#: yield ~2000x behind)
TOLD_APART = 10.0


@dataclass(frozen=True)
class Thresholds:
    """What counts as a significant gain over the baseline. BIC's penalty keeps noise from winning;
    the held-out ratio demands that the gain carries over to data the fit did not see."""
    delta_bic: float = -10.0
    heldout_ratio: float = 0.9
    p_value: float = 1e-3
    tie_bic: float = 10.0
    tie_heldout: float = 1.1
    same_prediction: float = 0.5   # two fits whose predictions differ by less than this x noise are one
    # the minimum effect size: the extended model's prediction must differ from the baseline's by more than
    # effect_noise x the noise (the smallest residual RMSE of the fits) and more than effect_range x the range
    # of the measured response, on at least effect_points samples (one sample can be a start-up or
    # block-average artefact)
    effect_noise: float = 3.0
    effect_range: float = 0.01
    effect_points: int = 3


def group_members(effect: str) -> list[str]:
    """The candidates a (possibly grouped) name stands for: "a ≡ b" -> [a, b]."""
    return effect.split(GROUP_SEP)


def equivalent_by_fit(a: Fit, b: Fit, th: Thresholds = Thresholds()) -> dict | None:
    """Whether two fits predict the same data within the noise: the RMS of the difference of their
    predictions against the noise estimated from the residuals (the smaller RMSE of the two). Returns
    the numbers when they agree, else None."""
    if not a.predictions or not b.predictions or len(a.predictions) != len(b.predictions):
        return None
    diff = np.concatenate([pa - pb for pa, pb in zip(a.predictions, b.predictions)])
    rms = float(np.sqrt(np.mean(diff ** 2)))
    noise = min(a.rmse, b.rmse)
    if noise > 0 and rms < th.same_prediction * noise:
        return {"prediction_rms_difference": rms, "noise": noise}
    return None


def effect_size(base: Fit, ext: Fit, response_range: float, noise: float | None = None,
                th: Thresholds = Thresholds()) -> dict:
    """How much the extended model changes the prediction, against what would matter.

    ``size`` is the ``th.effect_points``-th largest |extended − baseline| over all samples of the all-data
    fits (so the change holds on that many samples, not on one); ``floor`` is the larger of
    ``th.effect_noise`` × ``noise`` (the noise the data leave: the smallest residual RMSE of the models
    fitted, by default the extended model's) and ``th.effect_range`` × ``response_range`` (the range of the
    measured response: below a fraction of it an effect is physically negligible). ``matters`` when
    ``size`` exceeds ``floor``."""
    noise = ext.rmse if noise is None else noise
    if not base.predictions or len(base.predictions) != len(ext.predictions):
        return {"size": float("nan"), "floor": float("nan"), "noise": noise, "matters": False}
    diff = np.abs(np.concatenate([pe - pb for pe, pb in zip(ext.predictions, base.predictions)]))
    k = min(max(int(th.effect_points), 1), diff.size)
    size = float(np.partition(diff, diff.size - k)[diff.size - k])
    noise_floor, range_floor = th.effect_noise * noise, th.effect_range * response_range
    floor = max(noise_floor, range_floor)
    return {"size": size, "floor": floor, "noise": noise, "noise_floor": noise_floor,
            "range_floor": range_floor, "response_range": response_range, "matters": bool(size > floor)}


def rank_candidates(base: Fit, fits: dict[str, Fit], th: Thresholds = Thresholds(),
                    response_range: float | None = None) -> list[dict]:
    """Every candidate with its scores, best first: significant ones first, then by held-out error
    (prediction on unseen data separates look-alike families better than the in-sample BIC does); the
    winner of :func:`choose_effect` (BIC decides within the held-out tie margin) is put first.

    ``significant`` needs the three statistical tests (``statistically_significant``) and an effect that
    matters (:func:`effect_size`, against ``response_range``, without it the range of the baseline's
    predictions, and the noise of the data: the smallest RMSE of all the fits)."""
    if response_range is None:
        pooled = np.concatenate(base.predictions) if base.predictions else np.zeros(1)
        response_range = float(np.max(pooled) - np.min(pooled))
    noise = min([base.rmse] + [f.rmse for f in fits.values()])
    rows = []
    for name, f in fits.items():
        p = nested_p_value(base, f)
        h_ratio = f.heldout_rmse / base.heldout_rmse if base.heldout_rmse > 0 else float("nan")
        d_bic = f.bic - base.bic
        stat = bool(d_bic < th.delta_bic and h_ratio < th.heldout_ratio and p < th.p_value)
        size = effect_size(base, f, response_range, noise, th)
        rows.append({"effect": name, "significant": stat and size["matters"], "statistically_significant": stat,
                     "effect_size": size, "rmse": f.rmse,
                     "heldout_rmse": f.heldout_rmse, "rmse_ratio": f.rmse / base.rmse,
                     "heldout_rmse_ratio": h_ratio, "aic": f.aic, "bic": f.bic,
                     "delta_aic": f.aic - base.aic, "delta_bic": d_bic, "p_value": p, "k": f.k,
                     "params": dict(f.params)})
    # the name last: equal scores (an equivalent pair) in the same order whatever order the fits came in
    rows.sort(key=lambda r: (not r["significant"], r["heldout_rmse"], r["bic"], r["effect"]))
    sig = [r for r in rows if r["significant"]]
    if sig:   # the winner first (choose_effect)
        win = _winner(sig, th)
        rows.remove(win)
        rows.insert(0, win)
    return rows


def _winner(sig: list[dict], th: Thresholds) -> dict:
    """The best of the significant rows: the lowest held-out error, or, among those within the tie margin of
    the lowest (held-out error cannot decide between them), the lowest BIC."""
    best = min(r["heldout_rmse"] for r in sig)
    close = [r for r in sig if r["heldout_rmse"] <= th.tie_heldout * best]
    return min(close, key=lambda r: (r["bic"], r["heldout_rmse"]))


def choose_effect(ranking: list[dict], th: Thresholds = Thresholds(),
                  fits: dict[str, Fit] | None = None) -> tuple[str, list[str]]:
    """The winner (or none) and the significant candidates the data cannot tell from it.

    The winner has the lowest held-out error, or, among the significant candidates within the tie margin
    of the lowest (``th.tie_heldout``), the lowest BIC. It is a group "a ≡ b" when candidates are the same
    equations (equivalent by construction, whatever their scores) or, given the ``fits``, significant ones
    whose best fits predict the same data within the noise and whose BICs are within ``th.tie_bic``
    (equivalent by fit): the data cannot decide between them, so both are named."""
    sig = [r for r in ranking if r["significant"]]
    if not sig:
        return "none", []
    win = _winner(sig, th)
    group = [win["effect"]]
    for r in [x for x in ranking if x is not win]:
        if equivalent_by_construction(win["effect"], r["effect"]):
            group.append(r["effect"])
        elif (fits and r["significant"] and win["effect"] in fits and r["effect"] in fits
              and abs(r["bic"] - win["bic"]) < th.tie_bic     # else BIC prefers one of them: the data decide
              and equivalent_by_fit(fits[win["effect"]], fits[r["effect"]], th)):
            group.append(r["effect"])
    ties = [r["effect"] for r in sig if r is not win and r["effect"] not in group
            and r["heldout_rmse"] < th.tie_heldout * win["heldout_rmse"] and r["bic"] - win["bic"] < th.tie_bic]
    # a group is named in a fixed order (alphabetical), whichever member ranked first
    return GROUP_SEP.join(sorted(group)), ties


# ---------------------------------------------------------------------- what the protocol can show

# Features of a test protocol that separate look-alike effects, and the pairs each one separates.
PROTOCOL_FEATURES = {
    "unloading": (frozenset({"nonlinear_stiffness", "yield_softening"}),
                  frozenset({"nonlinear_stiffness", "coulomb_friction"}),   # friction is yield (same equations)
                  frozenset({"coulomb_friction", "sensor_offset"}),
                  frozenset({"interface_damage", "yield_softening"}),
                  frozenset({"interface_damage", "coulomb_friction"}),
                  frozenset({"interface_damage", "nonlinear_stiffness"})),
    "several_rates_or_hold": (frozenset({"viscoelastic_relaxation", "nonlinear_stiffness"}),
                              frozenset({"viscoelastic_relaxation", "yield_softening"}),
                              frozenset({"viscoelastic_relaxation", "coulomb_friction"})),
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


def baseline_look_alikes(features: dict, candidates: Sequence[str], drive: str | None = None) -> list[dict]:
    """Candidates that the baseline's damping mimics under this protocol (e.g. friction on constant-rate
    ramps without a hold): a `none` here means "cannot tell", not "absent"."""
    out = []
    for name, la in BASELINE_LOOK_ALIKES.items():
        if name not in candidates or any(features.get(m) for m in la["missing"]):
            continue
        if drive not in (None, la["drive"]):
            continue
        out.append({"effect": name, "reason": f"cannot tell, because {la['why']}",
                    "separating_test": la["separating_test"]})
    return out


def indistinguishable(effect: str, ties: Sequence[str], ranking: list[dict], features: dict,
                      fits: dict[str, Fit] | None = None, drive: str | None = None) -> list[dict]:
    """The candidates the data cannot tell from ``effect``: equivalent ones named together in a group
    (with the physical reading of each), ties on the scores, then look-alikes the protocol cannot
    separate, each with the reason and the test that would separate them."""
    out = []
    members = group_members(effect)
    lead = next((r["effect"] for r in ranking if r["effect"] in members), members[0])
    for b in members:
        if b == lead:
            continue
        same = [a for a in [lead] + members if a != b and equivalent_by_construction(a, b)]
        if same:
            eq = equivalent_by_construction(same[0], b)
            out.append({"effect": b, "of": same[0], "equivalent": "by construction",
                        "reason": f"cannot tell, because the two are the same equations ({eq['why']}; "
                                  f"{eq['mapping']})",
                        "readings": dict(eq["readings"]), "separating_test": separating_test(same[0], b)})
            continue
        num = equivalent_by_fit(fits[lead], fits[b]) if fits and lead in fits and b in fits else None
        why = (f"their best fits predict the data within the noise (RMS difference "
               f"{num['prediction_rms_difference']:.3g} against noise {num['noise']:.3g})"
               if num else "their best fits predict the data within the noise")
        out.append({"effect": b, "of": lead, "equivalent": "by fit", "reason": f"cannot tell, because {why}",
                    "separating_test": separating_test(lead, b)})
    for t in ties:
        # a tie the protocol cannot resolve says why: the phase the tests lack
        blind = next((b for m in members for b in protocol_blind_spots(m, features) if b["effect"] == t), None)
        if blind:
            out.append({"effect": t, "reason": f"cannot tell, because the tests have no "
                                               f"{blind['missing'].replace('_', ' ')} (scores within the tie margins)",
                        "separating_test": blind["separating_test"]})
        else:
            out.append({"effect": t, "reason": "scores within the tie margins",
                        "separating_test": separating_test(lead, t)})
    if effect == "none":
        return out + baseline_look_alikes(features, [r["effect"] for r in ranking], drive)
    # a look-alike counts when it explains the data too: significant, or as good in-sample (BIC) as the
    # named one (its held-out score can suffer from what the protocol lacks: an extrapolation into a
    # phase the training blocks did not show)
    bic = {r["effect"]: r["bic"] for r in ranking}
    th = Thresholds()
    lead_row = next((r for r in ranking if r["effect"] == lead), None)

    def told_apart(r: dict) -> bool:
        # a look-alike the data left far behind (RMSE and held-out RMSE both TOLD_APART x the named one's) was
        # told apart by the data after all, whatever the protocol lacks (e.g. a drop of the force past a peak,
        # which neither yield nor friction can give)
        return bool(lead_row and r["rmse"] > TOLD_APART * lead_row["rmse"]
                    and r["heldout_rmse"] > TOLD_APART * lead_row["heldout_rmse"])
    explains = {r["effect"] for r in ranking
                if not told_apart(r) and (
                    r["significant"] or ((r.get("effect_size") or {}).get("matters", True)
                                         and r["delta_bic"] < th.delta_bic and lead in bic
                                         and r["bic"] - bic[lead] < th.tie_bic))}
    seen = set(members) | set(ties)
    for m in members:
        for b in protocol_blind_spots(m, features):
            # only a look-alike that explains the data too: one that fails here was told apart after all
            if b["effect"] not in seen and b["effect"] in explains:
                seen.add(b["effect"])
                out.append({"effect": b["effect"], "reason": f"cannot tell, because the tests have no "
                                                                f"{b['missing'].replace('_', ' ')}",
                            "separating_test": b["separating_test"]})
    return out
