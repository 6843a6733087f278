"""The whole diagnosis: calibrate the baseline and every candidate, rank them, describe what is left.

:func:`diagnose` fits every candidate (:mod:`~fmusa.diagnose.fitcache`, :mod:`~fmusa.diagnose.calibrate`),
ranks them on held-out data and by information criteria (:mod:`~fmusa.diagnose.rank`), names the effect
only when its gain is significant, and tests the residuals before and after for structure
(:mod:`~fmusa.diagnose.residuals`). :func:`run_diagnosis` is ``fmusa diagnose``: the same, written to a
folder as diagnosis.json, figures and report.md.

    from fmusa.diagnose.run import diagnose
    diag = diagnose(experiments, "displacement")     # experiments: fmusa.diagnose.measured.Experiment
"""
from __future__ import annotations

import functools
import inspect
import json
import math
import os
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fmusa.diagnose import motion as mo
from fmusa.diagnose import residuals as rs
from fmusa.diagnose.budget import LeftOut, RunBudget
from fmusa.diagnose.calibrate import AGREE_DBIC, MIN_EXPERIMENTS_LEFT_OUT, Fit, unify_equivalent
from fmusa.diagnose.effects import (BASELINE_LOOK_ALIKES, CANDIDATES, DAMPING, STIFFNESS, UNITS, DiagnoseError,
                                    data_scales, equivalent_by_construction, equivalent_parameters,
                                    main_parameter, model_parameters)
from fmusa.diagnose.fitcache import data_key, run_fits
from fmusa.diagnose.interface import ModelInterface
from fmusa.diagnose.plausibility import implausible, support_of, unidentifiable
from fmusa.diagnose.rank import (Thresholds, choose_effect, group_members,
                                 indistinguishable, nested_p_value, protocol_features, rank_candidates)
from fmusa.diagnose.units import check_units, model_scale
from fmusa.diagnose.views import structure_text
from fmusa.files import atomic_write

__all__ = ["diagnose", "response_range", "write_json", "run_diagnosis", "run_study_diagnosis"]


def _check_input(experiments: Sequence, drive: str, candidates: Sequence[str], interface: ModelInterface) -> None:
    """Refuse a bad drive, an unknown candidate or no data before any FMU runs."""
    interface.check_drive(drive)
    for c in candidates:
        if c not in CANDIDATES:
            raise DiagnoseError(f"unknown candidate {c!r}; use any of {', '.join(CANDIDATES)}")
    if not experiments:
        raise DiagnoseError("no experiments given")


def _structure(fit: Fit, experiments: Sequence, drive: str) -> dict:
    """The residual structure of a fit over all experiments, each tested as its own segment."""
    segments, offset = [], 0
    for e in experiments:
        segments.append(np.arange(offset, offset + len(e.t)))
        offset += len(e.t)
    t_all = np.concatenate([e.t for e in experiments])
    r = np.concatenate([pr - e.response_signal for pr, e in zip(fit.predictions, experiments)])
    meas = np.concatenate([np.asarray(e.response_signal, float) for e in experiments])
    if mo.current() == mo.ROTATION:   # a rotational interface: along the angle in deg or the torque in N·m
        return _structure_rotation(fit, experiments, drive, t_all, r, meas, segments)
    # where a misfit is: along the drive channel, in mm or N
    if drive == "displacement":
        x, x_unit, x_name, resp = np.concatenate([e.displacement for e in experiments]) * 1e3, "mm", \
            "displacement", "force"
    else:
        x, x_unit, x_name, resp = np.concatenate([e.force for e in experiments]), "N", "force", "displacement"
    # a time axis derived from a nominal rate is made up: structure is searched along the nominal drive path
    # (rate x time, mm or N) and stated per mm or N of the drive, never as a frequency
    derived = all(e.meta.get("time_derived") and e.meta.get("rate_si") for e in experiments)
    if derived:
        f_drive = 1e3 if drive == "displacement" else 1.0
        t_all = np.concatenate([(np.asarray(e.t, float) - e.t[0]) * float(e.meta["rate_si"]) * f_drive
                                for e in experiments])
    st = rs.residual_structure(t_all, r, segments=segments, unit="N" if drive == "displacement" else "m",
                               x=x, x_unit=x_unit, x_name=x_name, measured=meas, response=resp)
    st["axis"] = ({"name": x_name, "unit": x_unit, "derived_time": True} if derived else
                  {"name": "time", "unit": "s", "derived_time": False})
    unit, f = ("N", 1.0) if drive == "displacement" else ("mm", 1e3)
    st["description"] = structure_text(st, unit, f)
    return st


def _structure_rotation(fit: Fit, experiments: Sequence, drive: str, t_all, r, meas, segments) -> dict:
    """:func:`_structure` of a rotational interface: the drive axis and the response in deg and N·m."""
    resp = "force" if drive == "displacement" else "displacement"
    (xu, xf), (unit, f) = (mo.ROTATION_NATURAL[mo.channel_unit(c, mo.ROTATION)] for c in (drive, resp))
    x = np.concatenate([np.asarray(getattr(e, drive), float) for e in experiments]) * xf
    derived = all(e.meta.get("time_derived") and e.meta.get("rate_si") for e in experiments)
    if derived:
        t_all = np.concatenate([(np.asarray(e.t, float) - e.t[0]) * float(e.meta["rate_si"]) * xf
                                for e in experiments])
    st = rs.residual_structure(t_all, r, segments=segments, unit=mo.channel_unit(resp, mo.ROTATION), x=x,
                               x_unit=xu, x_name=mo.channel_word(drive, mo.ROTATION), measured=meas,
                               response=mo.channel_word(resp, mo.ROTATION))
    st["axis"] = ({"name": mo.channel_word(drive, mo.ROTATION), "unit": xu, "derived_time": True} if derived else
                  {"name": "time", "unit": "s", "derived_time": False})
    st["description"] = structure_text(st, unit, f)
    return st


def _fit_summary(f: Fit) -> dict:
    """A fit as diagnosis.json states it (no predictions)."""
    out = {"params": dict(f.params), "ci95": {k: list(v) for k, v in f.ci95.items()},
           "units": {k: mo.si_unit(k) for k in f.params}, "rmse": f.rmse, "heldout_rmse": f.heldout_rmse,
           "aic": f.aic, "bic": f.bic, "k": f.k, "n": f.n}
    if f.mapped_from:
        out.update(mapped_from=f.mapped_from, own=f.own)
    out["at_bounds"] = [dict(b, unit=mo.si_unit(b["name"])) for b in f.at_bounds]
    out["held"] = dict(f.held)
    out["intervals"] = {k: ({n: list(v) for n, v in x.items()} if k == "gauss_newton" else x)
                        for k, x in f.intervals.items()}
    return out


#: the most effects a chain names (the first and up to two on top of it)
MAX_CHAIN = 3

#: a fit stops trying starts once this many reached its best cost
AGREE_STARTS = 2

#: the chain's fits try at most this many generic starts after their first (the model so far at its optimum)
CHAIN_STARTS = 2


def effect_chain(base: Fit, ext: Fit, lead: str, members: Sequence[str], effect: str, candidates: Sequence[str],
                 experiments: Sequence, drive: str, fmu: str, max_starts: int, interface: ModelInterface,
                 workers: int, cache_dir, key: str, progress: bool, th: Thresholds, chain: int,
                 budget: RunBudget | None = None, agree: int = 0, runs: dict | None = None,
                 removed: list | None = None, singles: dict | None = None) -> list[dict]:
    """After the first effect, each remaining candidate on top of the model so far, while the best addition
    passes the same tests as the first (significant against the model so far: ΔBIC, held-out ratio, F test)
    and matters (:func:`rank.effect_size`). Each step: the effect, its gain over the model before it (fitted
    and held-out RMSE ratios, ΔBIC, p), the parameters left at a bound and the fit. Candidates equivalent to
    a named one are not tried (the same equations add nothing).

    An addition is not made when the protocol cannot identify it (:func:`plausibility.unidentifiable`) or
    when its model has a parameter the tests cannot support (:func:`plausibility.implausible`); an addition
    that fits worse than the model it extends is an optimiser failure and is refitted from that model's
    optimum, and dropped when it stays worse. Each of these is appended to ``removed`` with the reason.
    ``runs``: filled with each step's fits (candidate name -> Fit or LeftOut; a refit under its own name), for
    the run count; when the run budget ends within a step, the chain stops there.

    To spend fewer runs, each fit tries its first start (the model so far at its optimum, the added effect's own
    parameters at their optimum alone, from ``singles``, the candidates' fits) and at most
    :data:`CHAIN_STARTS` generic ones, and an addition that fails the in-sample tests against the model so
    far or the physics check gets no held-out refits (:func:`calibrate.fit_candidate`'s ``gate``): neither
    can be the next step whatever its held-out score."""
    runs = {} if runs is None else runs
    if effect == "none":
        return []
    removed = [] if removed is None else removed
    steps = [{"effect": lead, "model": lead, "gain": _gain(base, ext, lead), "rmse": ext.rmse,
              "heldout_rmse": ext.heldout_rmse, "at_bounds": list(ext.at_bounds), "fit": ext}]
    named = set(members)
    current, name = ext, lead
    rr = response_range(experiments)
    features = protocol_features(experiments)
    support = support_of(experiments)
    while len(steps) < chain:
        rest = [c for c in candidates if c not in named
                and not any(equivalent_by_construction(c, m) for m in named)]
        for c in list(rest):
            why = unidentifiable(c, features, drive)
            if why:
                removed.append({"step": len(steps) + 1, "effect": c, "model": f"{name}+{c}", "check": "protocol",
                                "reason": why["reason"], "separating_test": why["separating_test"]})
                rest.remove(c)
        if not rest:
            break
        # first start: the model so far at its optimum, the added effect at its own first start; no held-out
        # refits for an addition that cannot be significant against the model so far
        gate, lanes, starts = _gate(current, th), jacobian_lanes(workers, len(rest)), min(max_starts, CHAIN_STARTS)
        # the costliest first (by its fit alone): the pool's last job is then a short one
        cost = {c: getattr((singles or {}).get(c), "seconds", 0.0) for c in rest}
        jobs = [(fmu, f"{name}+{c}", drive, list(experiments), starts, interface, lanes, agree,
                 _chain_start(current, (singles or {}).get(c)), gate) for c in sorted(rest, key=lambda c: -cost[c])]
        results = run_fits(jobs, workers, Path(cache_dir) if cache_dir else None, key, progress, budget)
        runs.update(results)
        if any(isinstance(r, LeftOut) for r in results.values()):
            break       # a step is chosen among all its candidates or not at all
        combos = {c: results[f"{name}+{c}"] for c in rest if isinstance(results.get(f"{name}+{c}"), Fit)}
        rescued, ended = {}, False
        for c in list(combos):
            if worse_than(combos[c], current):       # nested: never worse at its optimum
                worse = combos[c]
                # the refit tries the starts the fit did not (its first one was the model so far's optimum
                # already): none left, and it would make the same runs again to the same end
                if worse.starts_tried < 1 + starts:
                    refit = _refit_from(fmu, f"{name}+{c}", drive, experiments, starts, interface, current, gate,
                                        jacobian_lanes(workers, 1), budget, skip=worse.starts_tried, agree=agree)
                    runs[f"{name}+{c} (refit)"] = refit
                    if isinstance(refit, LeftOut):
                        ended = True
                        break
                    combos[c] = refit
                if worse_than(combos[c], current):
                    removed.append({"step": len(steps) + 1, "effect": c, "model": f"{name}+{c}",
                                    "check": "optimiser",
                                    "reason": f"the fit (RMSE {worse.rmse:.4g}) is worse than the model it extends "
                                              f"(RMSE {current.rmse:.4g}), also refitted from that model's optimum "
                                              f"(RMSE {combos[c].rmse:.4g}): an optimiser failure"})
                    del combos[c]
                elif combos[c] is not worse:      # rescued by its refit: said wherever the step is shown
                    rescued[c] = refit_note(worse, combos[c], current)
        if ended:
            break       # the run budget ended within the step: no step chosen among part of its candidates
        for c in list(combos):
            bad = implausible(f"{name}+{c}", combos[c].params, support)
            if bad:
                removed.append({"step": len(steps) + 1, "effect": c, "model": f"{name}+{c}", "check": "physics",
                                "reason": "; ".join(b["why"] for b in bad),
                                "separating_test": "; ".join(b["test"] for b in bad), "parameters": bad})
                del combos[c]
        if not combos:
            break
        ranking = rank_candidates(current, combos, th, rr)
        nxt, _ = choose_effect(ranking, th, combos)
        if nxt == "none":
            break
        pick = group_members(nxt)[0]
        fit = combos[pick]
        name = f"{name}+{pick}"
        steps.append({"effect": pick, "model": name, "gain": _gain(current, fit, pick), "rmse": fit.rmse,
                      "heldout_rmse": fit.heldout_rmse, "at_bounds": list(fit.at_bounds), "fit": fit,
                      "tried": sorted(combos), **({"refit": rescued[pick]} if pick in rescued else {})})
        named |= set(group_members(nxt))
        current = fit
    return steps


def _chain_start(current: Fit, single) -> dict:
    """A chain step's first start: the model so far at its optimum; the added effect's own parameters at their
    optimum alone where it was fitted (a generic start of interface damage on top of a stiffening let the
    interface fail and run away, and its refit from the next starts was the diagnosis's longest tail)."""
    own = single.params.items() if isinstance(single, Fit) else ()
    return {**{k: v for k, v in own if k not in current.params}, **current.params}


def worse_than(fit: Fit, nested: Fit) -> bool:
    """Whether a model's fit is worse than that of a model it contains by more than the optimiser's tolerance:
    a higher residual sum of squares by more than :data:`calibrate.AGREE_DBIC` in BIC units (n ln(rss/rss0)),
    the difference below which two starts count as the same optimum."""
    return fit.rss > nested.rss * math.exp(AGREE_DBIC / max(fit.n, 1))


def _refit_worse_than_baseline(results: dict, base: Fit, fmu: str, drive: str, experiments: Sequence,
                               max_starts: int, interface: ModelInterface, workers: int,
                               budget: RunBudget | None, agree: int = 0) -> dict:
    """Every candidate nests the baseline (its effect switched off is the baseline), so a candidate's fit worse
    than the baseline's is an optimiser failure (seen: every start in a region where the FMU's runs fail, the
    fit stopped there after two evaluations). Each such fit is refitted from the baseline's optimum (the starts
    it did not try); of one still worse the better fit is kept, and said so. ``results`` is updated in place
    (the runs of both fits kept together); returns a note for each fit refitted."""
    notes = {}
    for name, first in list(results.items()):
        if name == "none" or not isinstance(first, Fit) or not worse_than(first, base):
            continue
        refit = _refit_from(fmu, name, drive, experiments, max_starts, interface, base, None,
                            jacobian_lanes(workers, 1), budget, skip=first.starts_tried, agree=agree)
        runs = _added(first.runs, getattr(refit, "runs", None) or {})
        if not isinstance(refit, Fit):
            refit.runs = runs               # the run budget ended in the refit
            results[name] = refit
            continue
        still = worse_than(refit, base)
        # still worse: the better of the two stays in the ranking (it cannot be significant there), said so
        kept = (refit if refit.rss < first.rss else first) if still else refit
        kept.runs, kept.rounds = runs, _added(first.rounds, refit.rounds)
        results[name] = kept
        notes[name] = refit_note(first, refit, base, "the baseline") if not still else {
            "first_rmse": first.rmse, "refit_rmse": refit.rmse, "previous_rmse": base.rmse,
            "text": f"its fit (RMSE {first.rmse:.4g}) and its refit from the baseline's optimum "
                    f"(RMSE {refit.rmse:.4g}) are worse than the baseline (RMSE {base.rmse:.4g}), "
                    f"which it contains: the optimiser found no point of this model as good as "
                    f"the baseline; the better of the two is ranked"}
    return notes


def _added(a: dict, b: dict) -> dict:
    """Runs (or rounds) by stage of two fits together."""
    return {k: a.get(k, 0) + b.get(k, 0) for k in {**a, **b}}


def averaging_check(fmu: str, drive: str, interface: ModelInterface, base: Fit, final: Fit, steps: list,
                    experiments: Sequence, budget: RunBudget | None, cache_dir, key: str) -> dict:
    """The block averaging's check (:func:`fmusa.diagnose.averaging.check_averaging`) of the final model and the
    baseline: one run of each per averaged test at its original samples, counted in the diagnosis's runs."""
    from fmusa.diagnose.averaging import check_averaging

    name = "+".join(s["effect"] for s in steps) if steps else ""
    fits = {f"final model ({name})": final, "baseline": base} if name else {"baseline": base}
    return check_averaging(fmu, drive, interface, fits, experiments, budget, cache_dir, key)


def refit_note(first: Fit, refit: Fit, previous: Fit, what: str = "the model it extends") -> dict:
    """A step whose first fit was worse than the model it extends and whose refit from that model's optimum was
    not: the three RMSEs and what it means (the first fit stalled; the kept fit is the refit)."""
    return {"first_rmse": first.rmse, "refit_rmse": refit.rmse, "previous_rmse": previous.rmse,
            "text": f"its first fit (RMSE {first.rmse:.4g}) was worse than {what} (RMSE "
                    f"{previous.rmse:.4g}): an optimiser failure; refitted from that model's optimum (RMSE "
                    f"{refit.rmse:.4g}), the refit is the " + ("step" if what == "the model it extends" else "fit")}


def _gate(current: Fit, th: Thresholds) -> dict:
    """What a fit extending ``current`` must pass for its held-out refits to be worth their runs: the in-sample
    tests against ``current`` (:func:`calibrate.can_be_significant`) and the physics check the chain makes
    (:func:`plausibility.implausible`); a fit failing either is never the chain's next step."""
    return {"rss": current.rss, "n": current.n, "k": current.k, "delta_bic": th.delta_bic, "p_value": th.p_value,
            "physics": True}


def jacobian_lanes(workers: int, jobs: int) -> int:
    """FMU instances per fit for the rounds of its Jacobian: the workers left over when there are fewer
    fits running at once than workers (a slow FMU then waits one run per round, not one per column)."""
    return max(1, -(-int(workers) // max(1, int(jobs))))


def _stage_runs(r) -> dict:
    """One fit's runs, as the run count states them (with a fit's rounds: runs waited for one after another)."""
    if isinstance(r, Fit):
        fit, held = r.runs.get("fit", 0), r.runs.get("heldout", 0)
        return {"fit": fit, "heldout": held, "total": fit + held, "rounds": sum(r.rounds.values()),
                **({"heldout_skipped": True} if r.heldout_skipped else {}),
                **({"cached": True} if r.cached else {})}
    if isinstance(r, LeftOut):
        fit, held = r.runs.get("fit", 0), r.runs.get("heldout", 0)
        return {"fit": fit, "heldout": held, "total": fit + held, "left_out": True}
    spent = getattr(r, "runs", None) or {}       # a FailedFit: what it spent before it failed
    fit, held = spent.get("fit", 0), spent.get("heldout", 0)
    return {"fit": fit, "heldout": held, "total": fit + held, "failed": True}


def run_count(results: dict, chain_results: dict, budget: RunBudget, averaging: dict | None = None) -> dict:
    """Every FMU run of the diagnosis by stage (the baseline, each candidate, each step of the chain; per
    fit the runs of its own fit and of its held-out refits; the checks after the fits: the block averaging's,
    :func:`averaging_check`), the total the shared counter saw, the budget, and what the budget left out. Fits
    reused from a cache spent their runs in an earlier diagnosis: they are listed (``cached``) but not in the
    total."""
    stages = {"baseline": _stage_runs(results["none"]),
              "candidates": {n: _stage_runs(r) for n, r in results.items() if n != "none"},
              "chain": {n: _stage_runs(r) for n, r in chain_results.items()},
              "checks": {}}
    if averaging is not None and (averaging.get("tests") or averaging.get("runs")):
        stages["checks"]["averaging"] = {
            "fit": 0, "heldout": 0, "check": int(averaging["runs"]), "total": int(averaging["runs"]),
            "rounds": int(averaging.get("rounds", averaging["runs"])),
            **({"cached": True} if averaging.get("cached") and not averaging["runs"] else {}),
            **({"not_made": averaging["why"]} if not averaging.get("made") else {})}
    by_fits = sum(s["total"] for s in [stages["baseline"], *stages["candidates"].values(),
                                       *stages["chain"].values(), *stages["checks"].values()]
                  if not s.get("cached"))
    left = [n for n, r in {**results, **chain_results}.items() if isinstance(r, LeftOut)]
    return {"total": budget.used, "counted_by_fits": by_fits, "budget": budget.limit,
            "budget_ended": bool(left), "left_out": left, "depth": run_depth(stages), **stages}


def run_depth(stages: dict) -> int:
    """Rounds of FMU runs the diagnosis waited for one after another when every fit of a round has a worker
    of its own: the longest fit of the first round (the baseline and the candidates), plus the longest of
    each step of the chain, plus the chain's refits (made one after another). Times the seconds of one run,
    the least wall time a slow FMU can take however many workers there are."""
    def rounds(r: dict) -> int:
        return 0 if r.get("cached") else int(r.get("rounds", 0))

    depth = max([rounds(stages["baseline"])] + [rounds(r) for r in stages["candidates"].values()])
    depth += sum(rounds(r) for r in (stages.get("checks") or {}).values())     # after the fits, one after another
    steps: dict[int, int] = {}
    for n, r in stages["chain"].items():
        if n.endswith("(refit)"):
            depth += rounds(r)
        else:
            steps[n.count("+")] = max(steps.get(n.count("+"), 0), rounds(r))
    return depth + sum(steps.values())


def _refit_from(fmu: str, model: str, drive: str, experiments: Sequence, max_starts: int,
                interface: ModelInterface, previous: Fit, gate: dict | None = None, parallel: int = 1,
                budget: RunBudget | None = None, skip: int = 0, agree: int = 0) -> Fit | LeftOut:
    """The extended ``model`` fitted again from every start, the first at the optimum of the model it extends,
    less the first ``skip`` (tried already), until ``agree`` starts agree as in the first fit (in this process,
    alone: on ``parallel`` FMU instances, its runs taken from ``budget``; what it spent when that ended)."""
    from fmusa.diagnose import budget as rb
    from fmusa.diagnose.calibrate import fit_candidate

    old = rb.set_current(budget) if budget is not None else None
    try:
        return fit_candidate(fmu, model, drive, list(experiments), max_starts, interface, parallel=parallel,
                             start=dict(previous.params), gate=gate, skip=skip, agree=agree)
    except rb.BudgetExhausted as exc:
        return LeftOut(f"{model} (refit)", dict(getattr(exc, "runs", {}) or {}))
    finally:
        if budget is not None:
            rb.set_current(old)


def _first_unidentifiable(fits: dict, features: dict, drive: str) -> dict:
    """The single effects the protocol cannot identify (:func:`plausibility.unidentifiable`), each with why; an
    effect whose equivalent by construction is identifiable here stays (the same equations, named as a group)."""
    why = {n: unidentifiable(n, features, drive) for n in fits}
    return {n: w for n, w in why.items() if w and not any(
        equivalent_by_construction(n, m) and not why.get(m, unidentifiable(m, features, drive)) for m in fits)}


def _screened_ranking(base: Fit, fits: dict, th: Thresholds, experiments: Sequence,
                      drive: str = "displacement") -> tuple[list[dict], list]:
    """The ranking of the single effects, where a fit with a parameter the tests cannot support
    (:func:`plausibility.implausible`) or an effect the protocol cannot identify
    (:func:`plausibility.unidentifiable`) is listed last, not significant, with why; and those removals
    (the significant ones: those the check kept from being named)."""
    support = support_of(experiments)
    bad = {n: implausible(n, f.params, support) for n, f in fits.items()}
    cannot = _first_unidentifiable(fits, protocol_features(experiments), drive)
    ok = {n: f for n, f in fits.items() if not bad[n] and n not in cannot}
    rr = response_range(experiments)
    ranking = rank_candidates(base, ok, th, rr)
    out = {n: f for n, f in fits.items() if n not in ok}
    removed = []
    for row in rank_candidates(base, out, th, rr) if out else []:
        n, b, w = row["effect"], bad[row["effect"]], cannot.get(row["effect"])
        if row["significant"] and w:
            removed.append({"step": 1, "effect": n, "model": n, "check": "protocol", "reason": w["reason"],
                            "separating_test": w["separating_test"]})
        if row["significant"] and b:
            removed.append({"step": 1, "effect": n, "model": n, "check": "physics",
                            "reason": "; ".join(x["why"] for x in b),
                            "separating_test": "; ".join(x["test"] for x in b), "parameters": b})
        ranking.append(dict(row, significant=False, **({"implausible": b} if b else {}),
                            **({"unidentifiable": w} if w else {})))
    return ranking, removed


def _with_cannot_tell_first(listed: list[dict], removed: Sequence[dict]) -> list[dict]:
    """``listed`` and every first effect the protocol could not identify (removed at step 1), as "cannot tell"
    with the test that would tell, where not listed already."""
    seen = {i["effect"] for i in listed}
    return listed + [{"effect": r["effect"], "reason": r["reason"], "separating_test": r["separating_test"]}
                     for r in removed if r["step"] == 1 and r["check"] == "protocol" and r["effect"] not in seen]


def damping_look_alikes(base: Fit, members: Sequence[str], effect: str) -> list[dict]:
    """With the damping held at 0 (a drive of one constant rate), a named effect that adds a constant force on
    such a ramp (friction, a fast Maxwell branch, a force offset) may be the damping force: say so, with the
    test."""
    if effect == "none" or DAMPING not in base.held:
        return []
    out = []
    for m in members:
        la = BASELINE_LOOK_ALIKES.get(m)
        if la:
            out.append({"effect": f"damping {DAMPING} (held at 0)", "of": m,
                        "reason": f"cannot tell, because {base.held[DAMPING]['why']}; and {la['why']}",
                        "separating_test": la["separating_test"]})
            break
    return out


def straight_line(experiments: Sequence, drive: str) -> dict:
    """The straight line through the origin that fits the response best (the secant stiffness): a fitted
    baseline must never be worse (it holds this line with no damping)."""
    ys = np.concatenate([np.asarray(e.displacement, float) for e in experiments])
    Fs = np.concatenate([np.asarray(e.force, float) for e in experiments])
    if drive == "displacement":
        c = float(np.dot(ys, Fs) / np.dot(ys, ys))
        r = c * ys - Fs
    else:
        c = float(np.dot(Fs, Fs) / np.dot(ys, Fs))
        r = Fs / c - ys
    return {STIFFNESS: c, "rmse": float(np.sqrt(np.mean(r ** 2)))}


def response_range(experiments: Sequence) -> float:
    """The range of the measured response over all experiments (the scale of the physical floor)."""
    r = np.concatenate([np.asarray(e.response_signal, float) for e in experiments])
    return float(np.max(r) - np.min(r))


def _data_summary(experiments: Sequence, drive: str) -> dict:
    """What was fitted: drive, response, experiments and how the held-out folds were cut (and, of a rotational
    interface, its motion and the SI units of its channels)."""
    rot = ({"motion": mo.ROTATION, "units": {r: mo.channel_unit(r, mo.ROTATION) for r in ("displacement", "force")}}
           if mo.current() == mo.ROTATION else {})
    return {**rot, "drive": drive, "response": "force" if drive == "displacement" else "displacement",
            "experiments": [{"name": e.name, "points": len(e.t), "duration_s": float(e.t[-1] - e.t[0])}
                            for e in experiments],
            "points": int(sum(len(e.t) for e in experiments)),
            "heldout": "whole experiments (leave one out)" if len(experiments) >= MIN_EXPERIMENTS_LEFT_OUT
                       else "4 contiguous blocks in time (leave one out)" if len(experiments) == 1
                       else f"4 contiguous blocks in time of each of the {len(experiments)} experiments (leave one "
                            f"out: every training set keeps all experiments)"}


def _gain(base: Fit, ext: Fit, effect: str) -> dict:
    """How much the named effect improves on the baseline (ratios 1 and differences 0 for none)."""
    return {"rmse_ratio": ext.rmse / base.rmse, "heldout_rmse_ratio": ext.heldout_rmse / base.heldout_rmse,
            "delta_aic": ext.aic - base.aic, "delta_bic": ext.bic - base.bic,
            "p_value": nested_p_value(base, ext) if effect != "none" else 1.0}


def _thresholds(th: Thresholds) -> dict:
    return {"delta_bic": th.delta_bic, "heldout_ratio": th.heldout_ratio, "p_value": th.p_value,
            "tie_bic": th.tie_bic, "tie_heldout": th.tie_heldout, "effect_noise": th.effect_noise,
            "effect_range": th.effect_range, "effect_points": th.effect_points}


def _in_motion(fn):
    """``fn`` (:func:`diagnose`) run with the motion of its interface, else of its experiments, as the current one
    (:func:`fmusa.diagnose.motion.use`): the units its results state."""
    sig = inspect.signature(fn)

    @functools.wraps(fn)
    def wrapper(*args, **kw):
        a = sig.bind_partial(*args, **kw).arguments
        iface, exps = a.get("interface"), a.get("experiments") or ()
        motion = getattr(iface, "motion", None) or next(
            (e.meta.get("motion") for e in exps if isinstance(getattr(e, "meta", None), dict)
             and e.meta.get("motion")), None)
        with mo.use(motion):
            return fn(*args, **kw)
    return wrapper


@_in_motion
def diagnose(experiments: Sequence, drive: str, fmu_path: str | os.PathLike | None = None,
             candidates: Sequence[str] | None = None, workers: int | None = None,
             max_starts: int = 6, thresholds: Thresholds = Thresholds(), progress: bool = False,
             cache_dir: str | os.PathLike | None = None, interface: ModelInterface | None = None,
             chain: int = MAX_CHAIN, max_runs: int | None = None,
             agree: int = AGREE_STARTS) -> dict:
    """Calibrate the baseline and every candidate, rank them, and describe what is left.

    Returns a dict with the keys of diagnosis.json plus the fits (``_fits``) for the figures. With
    ``cache_dir`` each fit is saved as it completes and reused by a rerun on the same data, so an
    interrupted diagnosis loses nothing already computed. ``interface`` names the FMU's variables (default:
    the built-in description of the FMU's model, :mod:`fmusa.diagnose.models`); it is checked against the FMU
    before anything runs (:func:`fmusa.diagnose.check.check_description`). ``candidates``: default those of
    the description, else every one of the catalogue. ``chain``: the most effects of the chain
    (:func:`effect_chain`; 1 names one effect only). ``max_runs``: the most FMU runs the
    diagnosis may make (None: no limit); when they end, the candidates not fitted are left out (named in
    ``runs``), and the verdict is among those fitted. ``agree``: a fit stops trying starts once that many
    reached its best cost (0: all starts)."""
    from fmusa.diagnose.check import check_description
    from fmusa.diagnose.models import resolve
    from fmusa.fmi.info import FMURunError, default_fmu_path

    fmu = str(fmu_path or default_fmu_path())
    if not Path(fmu).exists():
        raise DiagnoseError(f"FMU not found: {fmu}; build it with `make fmu` or pass --fmu")
    interface = resolve(interface, fmu)
    if candidates is None:
        candidates = interface.candidates or CANDIDATES
    _check_input(experiments, drive, candidates, interface)
    check_description(fmu, interface, drive, candidates)
    sc = data_scales(experiments)
    units = check_units(experiments, model_scale(fmu, interface))
    if progress:   # before the fits, which take minutes: a wrong unit is worth stopping for
        for w in units["warnings"]:
            print(f"warning: {w['message']}", flush=True)
    names = ("none", *candidates)
    workers = workers or min(len(names), os.cpu_count() or 1)
    jobs = [(fmu, name, drive, list(experiments), max_starts, interface, jacobian_lanes(workers, len(names)),
             agree) for name in names]
    key = data_key(experiments, drive, max_starts, fmu, interface, agree)
    budget = RunBudget(max_runs)
    results = run_fits(jobs, workers, Path(cache_dir) if cache_dir else None, key, progress, budget)
    base = results["none"]
    if isinstance(base, LeftOut):
        raise DiagnoseError(f"the run budget of {max_runs} FMU runs ended before the baseline was fitted "
                            f"({budget.used} runs made); allow more runs (--max-runs)")
    if not isinstance(base, Fit):
        raise FMURunError(f"the baseline could not be fitted: {base}")
    refitted = _refit_worse_than_baseline(results, base, fmu, drive, experiments, max_starts, interface, workers,
                                          budget, agree)
    line = straight_line(experiments, drive)
    line["baseline_not_worse"] = bool(base.rmse <= line["rmse"] * (1 + 1e-3) + 1e-12 * sc.F_pk)
    # the same equations under two parametrisations are scored as one model
    fits = unify_equivalent({n: r for n, r in results.items() if n != "none" and isinstance(r, Fit)})
    ranking, removed = _screened_ranking(base, fits, thresholds, experiments, drive)
    effect, ties = choose_effect(ranking, thresholds, fits)
    members = group_members(effect)
    # a group "a ≡ b" reports the parameters of its best-ranked member; of members that are the same
    # equations, the one whose own fit the others were mapped from
    lead = next((r["effect"] for r in ranking if r["effect"] in members), members[0])
    if lead in fits and fits[lead].mapped_from in members:
        lead = fits[lead].mapped_from
    ext = fits[lead] if effect != "none" else base
    res_base, res_ext = _structure(base, experiments, drive), _structure(ext, experiments, drive)
    chain_results: dict = {}
    steps = effect_chain(base, ext, lead, members, effect, candidates, experiments, drive, fmu, max_starts,
                         interface, workers, cache_dir, key, progress, thresholds, chain, budget, agree,
                         chain_results, removed, fits)
    final = steps[-1]["fit"] if steps else ext
    res_final = _structure(final, experiments, drive) if len(steps) > 1 else res_ext
    averaging = averaging_check(fmu, drive, interface, base, final, steps, experiments, budget, cache_dir, key)
    if progress:
        for w in averaging["warnings"]:
            print(f"warning: {w['message']}", flush=True)
    features = protocol_features(experiments)
    eff_names = [p.name for p in model_parameters(lead, drive, sc)][2:] if effect != "none" else []
    group = {m: {"params": dict(fits[m].params), "main_parameter": main_parameter(m, drive),
                 "from_lead": equivalent_parameters(lead, ext.params, m) if m != lead else None,
                 **({"mapped_from": fits[m].mapped_from} if fits[m].mapped_from else {}),
                 **({"own": fits[m].own} if fits[m].own else {})}
             for m in members if m in fits} if len(members) > 1 else {}
    return {
        "effect": effect,
        "group": group,
        "lead": lead if effect != "none" else None,
        "main_parameter": main_parameter(lead, drive) if effect != "none" else None,
        "effect_params": {n: {"value": ext.params[n], "ci95": list(ext.ci95[n]), "unit": mo.si_unit(n)}
                          for n in eff_names},
        "baseline": _fit_summary(base),
        "straight_line": line,
        "extended": _fit_summary(ext),
        "gain": _gain(base, ext, effect),
        "ranking": ranking,
        "failed": {n: r for n, r in results.items() if isinstance(r, str)},
        "refitted": refitted,
        "runs": run_count(results, chain_results, budget, averaging),
        "indistinguishable": _with_cannot_tell_first(
            indistinguishable(effect, ties, ranking, features, fits, drive) + damping_look_alikes(base, members, effect),
            removed),
        "protocol": features,
        "residuals": {"baseline": res_base, "extended": res_ext, **({"final": res_final} if len(steps) > 1 else {})},
        "leftover": res_final.get("description", "") if res_final.get("structured") else "",
        "chain": [{k: v for k, v in s.items() if k != "fit"} for s in steps],
        "chain_removed": removed,
        "final": {"effects": [s["effect"] for s in steps], "model": steps[-1]["model"] if steps else None,
                  "at_bounds": [dict(b, unit=mo.si_unit(b["name"])) for b in final.at_bounds],
                  "params": {n: {"value": v, "ci95": list(final.ci95.get(n, (v, v))), "unit": mo.si_unit(n)}
                             for n, v in final.params.items()},
                  "intervals": {k: v for k, v in final.intervals.items() if k != "gauss_newton"},
                  "gauss_newton": {n: list(v) for n, v in (final.intervals.get("gauss_newton") or {}).items()},
                  "rmse": final.rmse, "heldout_rmse": final.heldout_rmse} if steps else None,
        "data": _data_summary(experiments, drive),
        # the FMU variable of each fitted parameter (the catalogue's names are the keys above); where the effects
        # went and the model description's name
        "model": {"description": interface.name, "effects": "attached" if interface.attached else "inside",
                  "variables": {n: interface.variable(n) for f in [base, *fits.values()] for n in f.params},
                  **({"where": parameter_homes(fmu, interface, [n for f in [base, *fits.values()] for n in f.params])}
                     if interface.attached else {})},
        "thresholds": _thresholds(thresholds),
        "units": units,
        "warnings": [dict(w) for w in units["warnings"]] + [dict(w) for w in averaging["warnings"]],
        "averaging": {k: v for k, v in averaging.items() if k != "warnings"},
        "_fits": {"none": base, **fits, **({effect: ext} if len(members) > 1 else {}),
                  **({"+".join(s["effect"] for s in steps): final} if len(steps) > 1 else {})},
    }


def _plain(x: Any) -> Any:
    """A JSON-ready copy: no in-memory keys (leading underscore), numpy scalars as Python, NaN as null."""
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items() if not k.startswith("_")}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def parameter_homes(fmu: str, interface: ModelInterface, names: Sequence[str]) -> dict[str, str]:
    """Effects attached: which FMU each fitted parameter is set on ("element" or "model"), for the report."""
    from fmusa.diagnose.attached import coupling_of, set_on_element

    return {n: "element" if on else "model"
            for n, on in set_on_element(coupling_of(fmu, interface).element(), interface, names).items()}


def write_json(diag: dict, path: str | os.PathLike) -> None:
    """diagnosis.json: everything but the in-memory fits."""
    atomic_write(path, json.dumps(_plain(diag), indent=2))


def run_diagnosis(experiments: Sequence, drive: str, out_dir: str | os.PathLike, **kw) -> dict:
    """diagnose, then DIR/diagnosis.json, DIR/figures/ and DIR/report.md; fits are cached in DIR/fits."""
    from fmusa.diagnose.figures import write_figures
    from fmusa.diagnose.report import write_report

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    diag = diagnose(experiments, drive, cache_dir=out / "fits", progress=kw.pop("progress", True), **kw)
    write_json(diag, out / "diagnosis.json")
    figs = write_figures(diag, experiments, out)
    write_report(diag, experiments, out, figs)
    return diag


def run_study_diagnosis(study, out_dir: str | os.PathLike, workers: int | None = None,
                        progress: bool = True, max_runs: int | None = None) -> dict:
    """A diagnosis study file's diagnosis (:class:`fmusa.diagnose.study.DiagnosisStudy`): the study checked
    against its FMU first, then the measured tests read, then :func:`run_diagnosis`."""
    from fmusa.diagnose.check import check_description
    from fmusa.fmi.info import default_fmu_path

    fmu = str(study.fmu or default_fmu_path())
    check_description(fmu, study.interface, study.tests.drive, study.interface.candidates or CANDIDATES)
    experiments = study.experiments()
    opts = study.diagnosis
    diag = run_diagnosis(experiments, study.tests.drive, out_dir, fmu_path=fmu, interface=study.interface,
                         workers=workers or opts.workers, max_starts=opts.starts, chain=opts.chain,
                         progress=progress, max_runs=max_runs)
    if study.interface.attached is not None:
        diag["coupling"] = coupled_cost(fmu, study.interface, study.tests.drive, diag, experiments[0])
        diag["ssp"] = write_extended_ssp(Path(out_dir) / "extended.ssp", fmu, study.interface, study.tests.drive,
                                         diag["extended"]["params"], float(experiments[0].t[-1]), study.name)
        write_json(diag, Path(out_dir) / "diagnosis.json")
    return diag


def write_extended_ssp(path: Path, fmu: str, interface: ModelInterface, drive: str, params: dict,
                       stop_time: float, name: str) -> dict:
    """The extended model (the model FMU, the element FMU with the fitted parameters, their connections) as an
    SSP 1.0 archive next to diagnosis.json; when the coupling cannot be written as SSP (e.g. the interface's
    velocity is a state, not an output), why, in place of the file."""
    from fmusa.cosim.master import CouplingError
    from fmusa.cosim.ssp import write_ssp
    from fmusa.diagnose.attached import CoupledRunner, coupling_of

    runner = CoupledRunner(fmu, drive, list(params), {}, interface=interface)
    model, element = runner.parameter_values(list(params.values()))
    try:
        write_ssp(path, coupling_of(fmu, interface), model, element, stop_time, name=name)
    except CouplingError as exc:
        return {"written": False, "why": str(exc)}
    return {"written": True, "path": path.name, "model_parameters": model, "element_parameters": element}


def coupled_cost(fmu: str, interface: ModelInterface, drive: str, diag: dict, experiment) -> dict:
    """One coupled run of the extended model on the first experiment, for what the diagnosis states about the
    coupling: the scheme the master chose, its FMU calls and its wall and CPU time, and the reuse check's verdict."""
    from fmusa.diagnose.calibrate import make_runner

    params = dict(diag["extended"]["params"])
    runner = make_runner(fmu, drive, list(params), {}, interface)
    runner.predict(list(params.values()), [experiment])
    r = runner.last
    return {"scheme": r.scheme, "calls": int(r.calls), "wall_s": float(r.wall_s), "cpu_s": float(r.cpu_s),
            "notes": list(r.notes), "experiment": experiment.name, "points": len(experiment.t),
            "reuse": runner.reuse}
