"""What every section of a report works from, and how an application adds its own sections.

:class:`ReportContext` wraps a finished :class:`fmusa.pipeline.sweep.SweepResult` with the labels the report
derives from the study (descriptions, units, thresholds) and collects the figures and notes sections add.
:class:`ReportSection` is the protocol an application implements to add a section (or replace a generic
one): a ``key``, a ``placement`` and a ``render(ctx)`` that returns markdown and may draw figures from the
data it is given; it never runs an FMU.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Protocol, Sequence

import pandas as pd

from fmusa.format import fmt

__all__ = ["ReportContext", "ReportSection", "Section", "num", "pct", "table", "get", "yes", "ok_mark",
           "figure_markdown"]


class ReportSection(Protocol):
    """A section of report.md.

    ``key`` names it; ``placement`` says where it goes: ``"replace"`` (the generic section of the same key),
    ``"before:<key>"`` or ``"after:<key>"``. Keys with a dot (``results.grid``) are sub-sections: they are
    joined under their parent (``results``), whose own text is only written when a sub-section has text.
    ``render`` returns markdown ("" for nothing) and may add figures with :meth:`ReportContext.add_figure`.
    """
    key: str
    placement: str

    def render(self, ctx: "ReportContext") -> str: ...


@dataclass(frozen=True)
class Section:
    """A :class:`ReportSection` from a function."""
    key: str
    fn: Callable[["ReportContext"], str]
    placement: str = "replace"

    def render(self, ctx: "ReportContext") -> str:
        return self.fn(ctx)


# ============================================================================ small formatting helpers
def num(x, sig: int = 3, unit: str = "") -> str:
    s = fmt(x, sig)
    return f"{s} {unit}" if unit and s != "–" else s


def pct(a: float, b: float) -> str:
    """Relative difference of a against b in percent."""
    if b == 0 or not (math.isfinite(a) and math.isfinite(b)):
        return "–"
    return f"{(a - b) / b * 100:+.2f} %"


def table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(str(x).replace("|", "\\|") for x in r) + " |")
    return "\n".join(lines)


def yes(x) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "–"
    return "yes" if bool(x) else "no"


def ok_mark(x) -> str:
    return "✓" if bool(x) else "✗"


def get(d: Mapping | None, *keys, default=None):
    """``d[k1][k2]...`` or ``default`` when any level is missing."""
    for k in keys:
        if not isinstance(d, Mapping) or k not in d:
            return default
        d = d[k]
    return d


def figure_markdown(name: str, caption: str) -> str:
    return f"![{name}](figures/{name})\n\n*{name}*: {caption}\n\n"


# ============================================================================ the context
@dataclass
class ReportContext:
    """A finished study as the report sees it; ``figures`` ((file name, caption) in drawing order) and
    ``notes`` grow while the sections render."""
    result: Any
    figdir: Path
    figures: list = field(default_factory=list)
    notes: list = field(default_factory=list)
    #: the study's two main axes: the search's inner and outer parameters, else the first two parameters
    inner: str | None = None
    outer: str | None = None

    def __post_init__(self) -> None:
        st = self.study
        search = st.stages.get("search")
        region = self.result.region
        names = list(st.parameters)
        if region is not None:
            self.inner, self.outer = region.inner, region.outer
        elif search is not None:
            self.inner, self.outer = search.inner, getattr(search, "outer", None)
        elif names:
            self.inner = names[0]
            self.outer = names[1] if len(names) >= 2 else None

    # ---------------------------------------------------------------- the result
    @property
    def study(self):
        return self.result.study

    @property
    def summary(self) -> dict:
        return self.result.summary

    @property
    def runs(self) -> pd.DataFrame:
        runs = self.result.runs
        return runs if runs is not None else pd.DataFrame()

    def stage_ran(self, name: str) -> bool:
        """Whether stage ``name`` ran (it is in the study and left its mark in the summary or the runs)."""
        if name not in self.study.stages:
            return False
        if name == "grid":
            return bool(len(self.runs)) and "stage" in self.runs and bool((self.runs["stage"] == "grid").any())
        key = {"roi": "roi", "search": "search", "regression": "regression", "sensitivity": "sensitivity"}
        return self.summary.get(key.get(name, name)) is not None

    # ---------------------------------------------------------------- labels from the study
    def u(self, name: str) -> str:
        """The unit of a parameter or metric ("" when none)."""
        st = self.study
        item = st.parameters.get(name) or st.metrics.get(name)
        return getattr(item, "unit", "") or ""

    def v(self, x, name: str, sig: int = 3) -> str:
        return num(x, sig, self.u(name))

    def describe(self, name: str) -> str:
        """A parameter's or metric's description from the study, else its name."""
        st = self.study
        item = st.parameters.get(name) or st.metrics.get(name)
        return (getattr(item, "description", "") or "").strip() or name

    def named(self, name: str) -> str:
        """Description and name, ``Spring stiffness (c)``; the name alone when it has no description (never
        ``Q (Q)``)."""
        desc = self.describe(name)
        return name if desc.strip().lower() == name.lower() else f"{desc} ({name})"

    def label(self, name: str) -> str:
        """Axis label: description, name and unit, e.g. ``Spring stiffness (c) [N/m]``."""
        unit = self.u(name)
        text = self.named(name)
        return f"{text} [{unit}]" if unit else text

    # ---------------------------------------------------------------- constraints
    def constraints_on(self, metric: str) -> list:
        return [c for c in self.study.constraints if c.metric == metric]

    def constrained_metrics(self) -> list[str]:
        return list(dict.fromkeys(c.metric for c in self.study.constraints))

    def thresholds(self, metric: str) -> list[tuple[float, str]]:
        """(bound, label) of every bound the constraints set on ``metric``."""
        out = []
        for c in self.constraints_on(metric):
            for bound, sign in ((c.max, "≤"), (c.min, "≥")):
                if bound is not None:
                    out.append((float(bound), f"{c.name}: {metric} {sign} {fmt(bound)} {self.u(metric)}".rstrip()))
        return out

    def ok_column(self, metric: str) -> str | None:
        cons = self.constraints_on(metric)
        return f"ok_{cons[0].name}" if cons else None

    def response_metrics(self) -> list[str]:
        """The search's response metrics (``stages.search.response``; by default the constrained ones)."""
        search = self.study.stages.get("search")
        response = list(getattr(search, "response", None) or [])
        return response or self.constrained_metrics() or list(self.study.metrics)[:3]

    # ---------------------------------------------------------------- figures
    def add_figure(self, name: str, caption: str) -> None:
        self.figures.append((name, caption))
