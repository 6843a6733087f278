"""The report's sections on how the FMU was run: its reset check, its own integration, implausible values.

Rendered from ``summary["fmu_runs"]`` (:mod:`fmusa.runs.preflight`), ``summary["fmu_steps"]`` and
``summary["implausible"]`` (:mod:`fmusa.pipeline.solver_check`); nothing here runs an FMU.
"""
from __future__ import annotations

from typing import Mapping

from fmusa.format import fmt
from fmusa.report.context import ReportContext, table

_MODES = {
    "reset": "one instance per worker, brought back by `fmi2Reset` before each run",
    "snapshot": "one instance per worker, brought back before each run to a state snapshot taken right "
                "after instantiation (`fmi2SetFMUstate`)",
    "fresh": "a new instance for every run, its library loaded anew (as `fmpy.simulate_fmu` does)",
}


def fmu_runs_section(ctx: ReportContext) -> str:
    """How each run was made so that it equals a run on a fresh instance, why, and what it cost."""
    r = ctx.summary.get("fmu_runs")
    if not isinstance(r, Mapping) or r.get("mode") not in _MODES:
        return ""
    out = ("## How the FMU's runs were made\n\n"
           f"Runs were made on {_MODES[r['mode']]}. Why: {r.get('why', '')}. ")
    if r.get("restore_ms") is not None:
        out += f"Bringing the instance back cost {fmt(r['restore_ms'], 3)} ms per run. "
    if r.get("cached"):
        out += "The verdict comes from fmusa's cache (the same FMU and run set-up checked before). "
    elif r.get("check_s") is not None:
        out += f"The check ran in {r.get('where', 'this process')} and took {fmt(r['check_s'], 3)} s. "
    rows = [(t.get("mode"), "yes" if t.get("reproduced") else "no", t.get("detail", ""),
             fmt(t["restore_ms"], 3) if t.get("restore_ms") is not None else "–") for t in r.get("tried") or []]
    if rows:
        out += ("Before the first batch, the first point was run on a fresh instance, then another point and "
                "the first again on the same instance, brought back each way tried:\n\n"
                + table(["way", "reproduced the fresh run?", "what was seen", "cost per run [ms]"], rows))
    return out + "\n"


def fmu_steps_section(ctx: ReportContext) -> str:
    """How far the FMU's own integration moves the metrics, and values no run could plausibly give."""
    s = ctx.summary.get("fmu_steps")
    implausible = ctx.summary.get("implausible") or []
    if not isinstance(s, Mapping) and not implausible:
        return ""
    out = "## The FMU's own integration\n\n"
    if isinstance(s, Mapping):
        ctx.notes.extend(s.get("notes") or [])
        atol = s.get("atol") or {}
        out += (f"A few points were run again with the communication step halved (read at the study's own "
                f"sampling), the tolerance tightened tenfold and, where the FMU offers it, through model "
                f"exchange. A metric that moved by more than {fmt(s.get('tolerance'), 3)} relative"
                + (" (and more than its `response_atol`)" if atol else "") + " is flagged. ")
        flagged = s.get("flagged") or []
        if flagged:
            out += (f"**Flagged: {', '.join(f'`{m}`' for m in flagged)}** — the study's values of "
                    f"{'these metrics' if len(flagged) > 1 else 'this metric'} depend on how the FMU "
                    f"integrates, not only on the parameters. What to do:\n\n"
                    + "".join(f"- {a}\n" for a in s.get("advice") or []) + "\n")
        else:
            out += "No metric moved that far. "
        largest = s.get("largest_relative") or {}
        if largest:
            out += ("\n\n" + table(["metric", "largest relative move"],
                                   [(m, fmt(v, 3)) for m, v in largest.items()]) + "\n")
        rows = [(", ".join(f"{k} = {fmt(v, 5)}" for k, v in (c.get("point") or {}).items()), c.get("variant"),
                 c.get("metric") or "–", fmt(c.get("value"), 6), fmt(c.get("variant_value"), 6),
                 fmt(c.get("relative"), 2), c.get("note") or "") for c in s.get("checks") or [] if c.get("flagged")]
        if rows:
            out += "\n" + table(["point", "rerun", "metric", "as run", "rerun value", "relative move", "note"],
                                rows[:30]) + "\n"
    if implausible:
        out += (f"\n**{len(implausible)} value{'s' if len(implausible) > 1 else ''} not plausible**: orders of "
                f"magnitude beyond the rest of the study's runs (a solver that blew up reports them as `ok`). "
                f"They are not results: do not read them as the model's response; the check above says "
                f"which rerun moves them.\n\n"
                + table(["run", "metric", "value", "upper quartile of the runs", "limit"],
                        [(i.get("run"), i.get("metric"), fmt(i.get("value"), 4), fmt(i.get("typical_upper"), 4),
                          fmt(i.get("limit"), 4)) for i in implausible[:30]]) + "\n")
    return out + "\n"
