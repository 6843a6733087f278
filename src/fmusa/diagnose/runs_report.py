"""The report's section on the FMU runs a diagnosis made: by stage, against its budget, and what the budget
left out (rendered from diagnosis.json's ``runs``; nothing runs here)."""
from __future__ import annotations

from typing import Mapping

__all__ = ["runs_section", "budget_notice"]


def _row(stage: str, r: Mapping) -> list[str]:
    note = ("reused from an earlier diagnosis (not counted now)" if r.get("cached")
            else "left out: the run budget ended" if r.get("left_out")
            else "failed" if r.get("failed")
            else "no held-out refits: it cannot be the chain's next step" if r.get("heldout_skipped") else "")
    return [stage, str(r.get("fit", 0)), str(r.get("heldout", 0)), str(r.get("total", 0)), note]


#: what each check after the fits is, as its row of the table names it
CHECKS = {"averaging": ("check: block averaging", "the fitted models at every original sample of the averaged tests")}


def _check_row(name: str, r: Mapping) -> list[str]:
    label, what = CHECKS.get(name, (f"check: {name}", ""))
    note = ("reused from an earlier diagnosis (not counted now)" if r.get("cached")
            else f"not made: {r['not_made']}" if r.get("not_made") else what)
    return [label, "", "", str(r.get("total", 0)), note]


def runs_section(diag: Mapping) -> str:
    """## FMU runs: one row per fit (the baseline, each candidate, each candidate of the chain's steps)."""
    runs = diag.get("runs")
    if not runs:
        return ""
    rows = [_row("baseline", runs["baseline"])]
    rows += [_row(f"`{n}`", r) for n, r in runs.get("candidates", {}).items()]
    rows += [_row(f"chain: `{n}`", r) for n, r in runs.get("chain", {}).items()]
    rows += [_check_row(n, r) for n, r in (runs.get("checks") or {}).items()]
    head = ["fit", "runs of the fit", "runs of the held-out refits", "total", ""]
    table = "| " + " | ".join(head) + " |\n|" + "---|" * len(head) + "\n"
    table += "".join("| " + " | ".join(r) + " |\n" for r in rows)
    budget = runs.get("budget")
    out = (f"## FMU runs\n\n{runs['total']} FMU runs (one run: one experiment simulated once)"
           + (f", of a budget of {budget}" if budget else ", no budget set") + ".\n\n")
    if runs.get("left_out"):
        out += ("The run budget ended before these fits were done, so they are left out and the verdict is "
                "among the fits that were done: " + ", ".join(f"`{n}`" for n in runs["left_out"])
                + ". Allow more runs (`--max-runs`) to include them; the fits done are kept and reused.\n\n")
    return out + table


def budget_notice(diag: Mapping) -> str:
    """At the top of the report when the run budget ended: the verdict covers only the fits that were done."""
    runs = diag.get("runs") or {}
    if not runs.get("left_out"):
        return ""
    return (f"**The run budget ({runs['budget']} FMU runs) ended before every fit was done.** Left out: "
            + ", ".join(f"`{n}`" for n in runs["left_out"])
            + ". The verdict below is among the candidates that were fitted only; a left-out candidate may "
              "fit better. See *FMU runs*.\n")
