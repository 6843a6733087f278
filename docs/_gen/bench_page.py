"""The last measurement of ``make bench`` as a section of the Benchmarks page.

Every timing the pages refer to is a key of out/bench/bench.json; this renders that file's numbers with the
machine, the load and the time they were measured, so the site states no timing that no run produced.
"""
from __future__ import annotations

import json
from pathlib import Path


def _number(v: float) -> str:
    if isinstance(v, bool):
        return str(v).lower()
    if isinstance(v, int):
        return f"{v:,}"
    a = abs(v)
    if a == 0:
        return "0"
    if a >= 100:
        return f"{v:,.0f}"
    if a >= 0.01:
        return f"{v:.3g}"
    return f"{v:.2e}"


def scalars(data: dict) -> dict[str, float]:
    """The top-level numbers of bench.json (nested detail stays in the file)."""
    return {k: v for k, v in data.items() if isinstance(v, (int, float)) and not isinstance(v, bool)}


def render(path: Path) -> str:
    """A markdown section: the numbers of ``path``, or how to get them when it does not exist."""
    head = "## The last measurement\n\n"
    if not path.is_file():
        return head + ("No measurement: `out/bench/bench.json` did not exist when this site was built. Run "
                       "`make bench`, then `make docs`, to list it here.\n")
    data = json.loads(path.read_text(encoding="utf-8"))
    m = data.get("machine", {})
    load = m.get("loadavg_1min")
    lines = [head, f"Measured by `make bench` at {data.get('timestamp', 'an unknown time')} on "
             f"{m.get('platform', 'an unknown platform')}, {m.get('processor', '?')}, {m.get('cpu_count', '?')} "
             f"logical CPUs, Python {m.get('python', '?')}, fmpy {m.get('fmpy', '?')}"
             + (f"; 1-minute load average {load:.2f} at the start (a load above the CPU count inflates every "
                "wall-clock time)" if isinstance(load, (int, float)) else "") + ".", ""]
    if data.get("limits_note"):
        lines += [f"Limits: {data['limits_note']}", ""]
    lines += ["| key | value |", "|---|---|"]
    lines += [f"| `{k}` | {_number(v)} |" for k, v in sorted(scalars(data).items())]
    return "\n".join(lines) + "\n"
