"""The worst errors the physics suites measure, kept for the end of the run (conftest prints them).

A suite records each case's errors with :func:`record`; its last test asserts the suite's own bounds on
:func:`worst`, and ``pytest_terminal_summary`` in conftest.py prints every suite's worst errors, so that a
run shows the accuracy it proved, not only that it passed.
"""
from __future__ import annotations

from collections import defaultdict

#: suite -> error name -> (worst value, case)
_WORST: dict[str, dict[str, tuple[float, str]]] = defaultdict(dict)
_UNITS: dict[tuple[str, str], str] = {}


def record(suite: str, case: str, unit: str = "", **errors: float) -> None:
    for name, value in errors.items():
        value = float(value)
        _UNITS[(suite, name)] = unit if name.startswith("t_") else ""
        old = _WORST[suite].get(name)
        if old is None or value > old[0]:
            _WORST[suite][name] = (value, case)


def worst(suite: str) -> dict[str, tuple[float, str]]:
    return dict(_WORST.get(suite, {}))


def summary_lines() -> list[str]:
    lines = []
    for suite, errs in sorted(_WORST.items()):
        parts = [f"{name} {value:.2e}{_UNITS.get((suite, name), '') and ' ' + _UNITS[(suite, name)]} ({case})"
                 for name, (value, case) in errs.items()]
        lines.append(f"{suite}: " + "; ".join(parts))
    return lines
