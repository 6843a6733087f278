"""The time limit of one run (``execution.timeout_s``): where a run may be made so that it keeps to it.

In supervised workers (the local pool, a Dask task) the parent kills the process of a run that has taken
``timeout_s`` (:mod:`fmusa.runs.pool`). A run made in the study's own process cannot be killed without
the study, so it is made there only when the FMU can stop itself: a co-simulation FMU that declares the
settable Real parameter ``max_wall_s`` (the most seconds of computing in one fmi2DoStep, past which
fmi2DoStep returns fmi2Error; our ScrewVertebra does) runs with ``max_wall_s = timeout_s``, and the run
also stops at the first communication point past ``timeout_s``. Any other FMU, or a study that sets
``max_wall_s`` to no limit or a longer one, runs in supervised workers whenever a limit is set.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from fmusa.fmi.info import FMUInfo, FMUTimeLimitError, select_interface

#: The FMU parameter that bounds the wall time of one fmi2DoStep, in s (0: none).
WALL_BUDGET = "max_wall_s"


def timeout_reason(timeout_s: float, how: str, detail: str = "") -> str:
    """The message of a run stopped by ``timeout_s``: the limit and its key, ``how`` it was stopped, the fix."""
    text = (f"timed out after {timeout_s:g} s (execution.timeout_s; {how}): the FMU hangs or is too slow; "
            f"if it is only slow, raise execution.timeout_s and rerun without --resume")
    return f"{text}. {detail}" if detail else text


def wall_budget(info: FMUInfo, interface: str) -> str | None:
    """:data:`WALL_BUDGET` when ``info`` declares it as a settable Real parameter and runs as co-simulation
    (the FMU's own solver: fmpy's solver runs a model exchange FMU, and the budget would not bind), else None."""
    if select_interface(info, interface) != "co-simulation":
        return None
    v = info.variable(WALL_BUDGET)
    if v is None or v.causality != "parameter" or v.variability not in ("fixed", "tunable") or v.type != "Real":
        return None
    return WALL_BUDGET


def in_process_fixed(info: FMUInfo, interface: str, fixed: tuple[tuple[str, Any], ...], varied: tuple[str, ...],
                     timeout_s: float) -> tuple[tuple[tuple[str, Any], ...], str | None] | None:
    """How a run in this process keeps to ``timeout_s``: (the fixed values to run with, the budget parameter
    fmusa set in them or None when the study sets it itself), or None when a run here could outlast
    ``timeout_s`` (no budget parameter, the study varies it, or sets it to 0 or more than ``timeout_s``)."""
    budget = wall_budget(info, interface)
    if budget is None or budget in varied:
        return None
    own = dict(fixed).get(budget)
    if own is None:
        return tuple(fixed) + ((budget, float(timeout_s)),), budget
    if isinstance(own, bool) or not 0 < float(own) <= timeout_s:
        return None
    return tuple(fixed), None


def in_process_reason(exc: BaseException, seconds: float, timeout_s: float, budget: str | None,
                      message: str) -> str | None:
    """The timeout reason of a run in this process that failed with ``exc`` after ``seconds`` (``message``:
    the FMU's own words), or None when it failed for another reason."""
    if isinstance(exc, FMUTimeLimitError):
        return timeout_reason(timeout_s, "the run was stopped at the first communication point past it", message)
    if budget is not None and seconds >= timeout_s:
        return timeout_reason(timeout_s, f"the FMU stopped the run itself through its parameter {budget}, which "
                                         f"fmusa sets to execution.timeout_s", f"The FMU said: {message}")
    return None


#: (resolved path, size, mtime) -> content digest of the FMUs looked at (hashing one costs ~1 ms)
_DIGESTS: dict[tuple[str, int, int], str] = {}


def _digest(path: Path) -> str | None:
    try:
        st = path.stat()
    except OSError:
        return None
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    if key not in _DIGESTS:
        from fmusa.fmi.build import file_digest

        _DIGESTS[key] = file_digest(path)
    return _DIGESTS[key]


def built_fmus() -> list[Path]:
    """This repository's own built FMU (``make fmu``): dist/ScrewVertebra.fmu under the working directory
    and above this package (an editable install), wherever ``$FMUSA_FMU`` points."""
    from fmusa.fmi.info import FMU_NAME

    places = [Path.cwd() / "dist" / FMU_NAME] + [p / "dist" / FMU_NAME for p in Path(__file__).resolve().parents]
    return [p for p in dict.fromkeys(places) if p.is_file()]


def own_fmu(path: str | os.PathLike) -> bool:
    """Whether ``path`` is this repository's own FMU, by its content: the same digest as the FMU ``make
    fmu`` built (a copy of it anywhere counts; an FMU that merely declares our variables, such as
    ``max_wall_s``, does not). Only such an FMU runs in the study's process: any other one may crash or exit
    inside a call, which would end the study."""
    path = Path(path)
    if not path.is_file():
        return False
    mine = _digest(path)
    return mine is not None and any(_digest(p) == mine for p in built_fmus())
