"""The study file's ``paper:`` block: the paper's printed reference values, checked at load.

The block is reference data for the report (it changes no run). Known keys and their shapes::

    paper:
      thresholds: {eps_y: 5.0e-4, eps_v: 5.0e-5, ...}        # names -> numbers (Table 2)
      roi: {c: [390625, 9765625], d: [0, 15625]}           # parameter -> [lo, hi], the hand-chosen region
      optimum: {c: 823224, d: 488, t_eq: 0.07674}          # names -> numbers
      regression: {metric: max_y, x: c, r: .., s: .., t: .., u: ..}   # eq. 3 as printed
      grid_extremes: {max_y: {value: 2.63e-2, c: 1.56e4, d: 6.25e2}, ...}
      t_eq_at_c_1562499_d_7813: 0.07908                    # a number
      cpu_s_per_run: 5                                     # a number

:func:`validate_paper_block` is the validator ``fmusa.api.load_study`` hands to the loader; every error
names ``file:line``, the key and what is allowed.
"""
from __future__ import annotations

import difflib
from typing import Callable, Mapping

from fmusa.study.schema import StudyError

__all__ = ["PAPER_KEYS", "REGRESSION_KEYS", "validate_paper_block"]

LineOf = Callable[[str], str]

PAPER_KEYS = ("thresholds", "roi", "optimum", "regression", "grid_extremes", "t_eq_at_c_1562499_d_7813",
              "cpu_s_per_run")
REGRESSION_KEYS = ("metric", "x", "r", "s", "t", "u")


def _number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _unknown(where: str, key, allowed, line_of: LineOf) -> StudyError:
    close = difflib.get_close_matches(str(key), list(allowed), n=1, cutoff=0.6)
    hint = f"; did you mean '{close[0]}'?" if close else ""
    return StudyError(f"{line_of(f'{where}.{key}')}: key '{key}' is not allowed in '{where}'{hint} "
                      f"(allowed: {', '.join(allowed)})")


def _mapping(value, where: str, line_of: LineOf, example: str) -> Mapping:
    if not isinstance(value, Mapping):
        raise StudyError(f"{line_of(where)}: key '{where.rsplit('.', 1)[-1]}' in '{where.rsplit('.', 1)[0]}' must "
                         f"be a mapping, got {value!r}; e.g. {example}")
    return value


def _numbers(value, where: str, line_of: LineOf, example: str) -> None:
    for k, v in _mapping(value, where, line_of, example).items():
        if not _number(v):
            raise StudyError(f"{line_of(f'{where}.{k}')}: key '{k}' in '{where}' must be a number, got {v!r}; "
                             f"e.g. {example}")


def _roi(value, line_of: LineOf) -> None:
    for k, v in _mapping(value, "paper.roi", line_of, "roi: {c: [390625, 9765625], d: [0, 15625]}").items():
        if not (isinstance(v, list) and len(v) == 2 and all(_number(x) for x in v) and v[0] <= v[1]):
            raise StudyError(f"{line_of(f'paper.roi.{k}')}: key '{k}' in 'paper.roi' must be [lo, hi] with "
                             f"lo <= hi, got {v!r}; e.g. {k}: [390625, 9765625]")


def _regression(value, line_of: LineOf) -> None:
    m = _mapping(value, "paper.regression", line_of, "regression: {metric: max_y, x: c, r: 0.002, s: -3e-9, ...}")
    for k, v in m.items():
        if k not in REGRESSION_KEYS:
            raise _unknown("paper.regression", k, REGRESSION_KEYS, line_of)
        if k in ("metric", "x") and not isinstance(v, str):
            raise StudyError(f"{line_of(f'paper.regression.{k}')}: key '{k}' in 'paper.regression' must be a "
                             f"name, got {v!r}")
        if k not in ("metric", "x") and not _number(v):
            raise StudyError(f"{line_of(f'paper.regression.{k}')}: key '{k}' in 'paper.regression' must be a "
                             f"number, got {v!r}")


def _grid_extremes(value, line_of: LineOf) -> None:
    m = _mapping(value, "paper.grid_extremes", line_of, "grid_extremes: {max_y: {value: 2.63e-2, c: 1.56e4, d: 625}}")
    for metric, ext in m.items():
        where = f"paper.grid_extremes.{metric}"
        _numbers(ext, where, line_of, f"{metric}: {{value: 2.63e-2, c: 1.56e4, d: 625}}")
        if "value" not in ext:
            raise StudyError(f"{line_of(where)}: key 'value' is missing in '{where}'; add it, e.g. value: 2.63e-2")


def validate_paper_block(block: dict, line_of: LineOf) -> None:
    """Raise :class:`StudyError` (``file:line: ...``) unless ``block`` has the shape above."""
    for key, value in block.items():
        if key not in PAPER_KEYS:
            raise _unknown("paper", key, PAPER_KEYS, line_of)
        where = f"paper.{key}"
        if key in ("thresholds", "optimum"):
            _numbers(value, where, line_of, f"{key}: {{eps_y: 5.0e-4}}" if key == "thresholds" else
                     "optimum: {c: 823224, d: 488}")
        elif key == "roi":
            _roi(value, line_of)
        elif key == "regression":
            _regression(value, line_of)
        elif key == "grid_extremes":
            _grid_extremes(value, line_of)
        elif not _number(value) or value < 0:
            raise StudyError(f"{line_of(where)}: key '{key}' in 'paper' must be a number >= 0, got {value!r}")
