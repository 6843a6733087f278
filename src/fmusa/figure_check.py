"""What can be checked on a figure before it is saved: axis labels with units, series told apart, nothing cut.

:func:`fmusa.files.save_figure` (every figure fmusa writes goes through it) runs :func:`figure_problems`
when ``$FMUSA_CHECK_FIGURES`` names a file, and appends one JSON line per figure there (its path and its
problems): the tests run the commands that draw figures with it set and require no problems. A user never
sees this; the check only reads the figure.
"""
from __future__ import annotations

import json
import os
import re
from pathlib import Path

ENV = "FMUSA_CHECK_FIGURES"
#: a journal page's text area, in inches (a wider figure is scaled down, and its text with it)
MAX_WIDTH_IN, MAX_HEIGHT_IN = 7.5, 9.5

#: an axis label states its unit: "[N/mm]", "[-]", or it is a count, rank, ratio or index (no unit)
UNIT = re.compile(r"\[[^\]]+\]|\((?:[^()]*/[^()]*|s|m|N|mm|Hz|rad|%)\)|\b(?:count|number|runs|rank|ratio|index|"
                  r"indices|fraction|share|μ\*|σ|S1|ST|effect|candidate|parameter|level|specimen|unit|cell|"
                  r"protocol|experiment|test)s?\b", re.I)


def _style(handle) -> tuple:
    """What tells a legend entry apart on the page: colour, marker, line style, fill."""
    from matplotlib import colors as mcolors
    from matplotlib.collections import Collection
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    def rgb(c) -> tuple:
        try:
            return tuple(round(v, 3) for v in mcolors.to_rgba(c))
        except (TypeError, ValueError):
            return (str(c),)
    if isinstance(handle, Line2D):
        return ("line", rgb(handle.get_color()), str(handle.get_marker()), str(handle.get_linestyle()),
                rgb(handle.get_markerfacecolor()))
    if isinstance(handle, Collection):
        fc, ec = handle.get_facecolor(), handle.get_edgecolor()
        paths = handle.get_paths()
        shape = tuple(map(tuple, paths[0].vertices.round(2))) if len(paths) else ()
        return ("points", rgb(fc[0]) if len(fc) else (), rgb(ec[0]) if len(ec) else (), hash(shape))
    if isinstance(handle, Patch):
        return ("patch", rgb(handle.get_facecolor()), rgb(handle.get_edgecolor()), str(handle.get_hatch()),
                str(handle.get_linestyle()))
    return (type(handle).__name__, id(handle))


def _alike(legend, name: str) -> list[str]:
    """Entries of ``legend`` that a reader cannot tell apart (same colour, marker, line style and fill)."""
    if legend is None:
        return []
    out, seen = [], {}
    for handle, text in zip(legend.legend_handles, [t.get_text() for t in legend.get_texts()]):
        if handle is None:
            continue
        style = _style(handle)
        if style in seen and seen[style] != text:
            out.append(f"{name}: legend entries {seen[style]!r} and {text!r} are drawn alike")
        seen.setdefault(style, text)
    return out


def _has_data(ax) -> bool:
    return bool(ax.lines or ax.collections or ax.images or ax.patches or ax.containers)


def _is_colorbar(ax) -> bool:
    return ax.get_label() == "<colorbar>" or hasattr(ax, "_colorbar")


def figure_problems(fig, tight: bool = True) -> list[str]:
    """What a reader of ``fig`` could not tell: an axis without a label or a unit, two legend entries drawn
    alike, error bars that leave the axes, text cut by the figure's edge (``tight``: saved with
    bbox_inches="tight", which keeps every text)."""
    problems: list[str] = []
    w, h = fig.get_size_inches()
    if w > MAX_WIDTH_IN + 1e-9 or h > MAX_HEIGHT_IN + 1e-9:
        problems.append(f"{w:.1f} × {h:.1f} in: larger than a page ({MAX_WIDTH_IN} × {MAX_HEIGHT_IN} in); it "
                        f"would print its text at {min(MAX_WIDTH_IN / w, MAX_HEIGHT_IN / h):.0%} of its size")
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    for k, ax in enumerate(fig.axes):
        if not ax.get_visible() or not ax.axison or _is_colorbar(ax) or not _has_data(ax):
            continue
        name = f"axes {k + 1}" + (f" ({ax.get_title()!r})" if ax.get_title() else "")
        for axis, label, shared in (("x", ax.get_xlabel(), ax.get_shared_x_axes()),
                                    ("y", ax.get_ylabel(), ax.get_shared_y_axes())):
            if not label.strip():
                siblings = [a for a in shared.get_siblings(ax) if a is not ax]
                ticks = [t.get_text() for t in (ax.get_xticklabels() if axis == "x" else ax.get_yticklabels())]
                if any((a.get_xlabel() if axis == "x" else a.get_ylabel()).strip() for a in siblings):
                    continue               # a shared axis labelled on its neighbour
                if not any(t.strip() for t in ticks):
                    continue               # no tick labels either: an axis that carries no values
                problems.append(f"{name}: the {axis} axis has no label")
            elif not UNIT.search(label):
                problems.append(f"{name}: the {axis} axis label {label!r} states no unit (write it as [unit])")
        problems += _alike(ax.get_legend(), name)
        x0, x1 = sorted(ax.get_xlim())
        y0, y1 = sorted(ax.get_ylim())
        for container in ax.containers:
            lines = getattr(container, "lines", None)
            if not lines or len(lines) < 3:
                continue
            for coll in lines[2]:          # the bars of an errorbar container
                for seg in coll.get_segments():
                    for x, y in seg:
                        if not (x0 - 1e-9 * abs(x1 - x0) <= x <= x1 + 1e-9 * abs(x1 - x0)
                                and y0 - 1e-9 * abs(y1 - y0) <= y <= y1 + 1e-9 * abs(y1 - y0)):
                            problems.append(f"{name}: an error bar leaves the axes (cut at its limits)")
                            break
                    else:
                        continue
                    break
    for n, legend in enumerate(fig.legends):
        problems += _alike(legend, f"figure legend {n + 1}")
    if not tight:
        box = fig.bbox
        ticks = {id(t) for ax in fig.axes for t in ax.get_xticklabels(which="both") + ax.get_yticklabels(which="both")}
        texts = [t for t in fig.findobj(lambda a: hasattr(a, "get_text") and hasattr(a, "get_window_extent"))
                 if t.get_visible() and str(t.get_text()).strip() and id(t) not in ticks]
        for t in texts:
            try:
                e = t.get_window_extent(renderer)
            except (RuntimeError, ValueError):
                continue
            if e.x0 < box.x0 - 1 or e.x1 > box.x1 + 1 or e.y0 < box.y0 - 1 or e.y1 > box.y1 + 1:
                problems.append(f"text {str(t.get_text())[:40]!r} is cut by the figure's edge")
    return list(dict.fromkeys(problems))


def record(fig, path: str | os.PathLike, tight: bool = True) -> None:
    """Append ``path`` and its problems to the file named by ``$FMUSA_CHECK_FIGURES`` (nothing when unset)."""
    log = os.environ.get(ENV)
    if not log:
        return
    w, h = fig.get_size_inches()
    entry = {"path": str(path), "size_in": [round(float(w), 2), round(float(h), 2)],
             "problems": figure_problems(fig, tight)}
    with open(Path(log), "a", encoding="utf-8") as f:
        f.write(json.dumps(entry) + "\n")
