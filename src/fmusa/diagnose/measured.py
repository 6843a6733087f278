"""Measured experiments: CSV files read, checked and converted to SI, ready for ``fmusa diagnose``.

One CSV file is one experiment. The test imposed one channel (the *drive*: force or displacement)
and measured the other (the *response*); the model is driven by the drive and predicts the
response. Several experiments are fitted jointly, so every file goes through the same checks here,
once, before any FMU runs.

Default format: columns ``time, displacement, force`` in s, m, N. A :class:`ColumnSpec` maps other
column names, converts units (mm, kN, …), flips signs, and derives time from a constant drive rate
when the file has no time column.

Every error is a :class:`MeasuredDataError` whose message names the file, the line (1-based, the
header is line 1), the column and the fix, e.g.::

    runs/a.csv:17: column 'Fx' (force): 'n/a' is not a number; fix or delete the row
    runs/a.csv:1: column 'force' (force) not in the header; the file has columns: t, disp, Fx.
    Map it with --force-column NAME (ColumnSpec.force)

Example::

    from fmusa.diagnose.measured import ColumnSpec, load_experiment, downsample
    spec = ColumnSpec(displacement="disp_x_mm", displacement_unit="mm", force="Fx_N", rate="1 mm/s")
    exp = downsample(load_experiment("H1_C67_Ant_1_mm_s.csv", "displacement", spec), 2000)
    exp.t, exp.drive_signal, exp.response_signal     # s, m, N
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
import pandas as pd

from fmusa.diagnose.motion import ANGLE_UNITS, MOTIONS, ROTATION, ROTATION_RATE_UNITS, TORQUE_UNITS, TRANSLATION
from fmusa.errors import FmusaError

__all__ = [
    "MeasuredDataError", "ColumnSpec", "Experiment", "load_experiment", "load_experiments",
    "downsample", "parse_rate", "DRIVES", "ROLES", "LENGTH_UNITS", "FORCE_UNITS", "TIME_UNITS",
    "RATE_UNITS", "MIN_ROWS", "OPTIONS", "DELIMITERS", "DECIMALS", "sniff_dialect", "Blocks",
]
__all__ += ["ANGLE_UNITS", "TORQUE_UNITS", "ROTATION_RATE_UNITS", "unit_table", "infer_motion"]   # rotation

#: What a test may impose.
DRIVES = ("force", "displacement")
#: The channels of an experiment, in file-check order.
ROLES = ("time", "displacement", "force")
#: Fewer data rows than this cannot constrain a dynamic model.
MIN_ROWS = 10

#: Unit -> factor to SI, per quantity. µ may be written u, µ (micro sign) or μ (Greek mu).
LENGTH_UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6, "\u00b5m": 1e-6, "\u03bcm": 1e-6}
FORCE_UNITS = {"N": 1.0, "kN": 1e3, "mN": 1e-3, "lbf": 4.4482216152605}
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "min": 60.0}
#: Drive rates: displacement rates for a displacement drive, force rates for a force drive.
RATE_UNITS = {
    "displacement": {"m/s": 1.0, "mm/s": 1e-3, "mm/min": 1e-3 / 60.0, "um/s": 1e-6,
                     "\u00b5m/s": 1e-6, "\u03bcm/s": 1e-6},
    "force": {"N/s": 1.0, "kN/s": 1e3, "N/min": 1.0 / 60.0, "kN/min": 1e3 / 60.0},
}
_UNITS = {"time": TIME_UNITS, "displacement": LENGTH_UNITS, "force": FORCE_UNITS}
_QUANTITY = {"time": "time", "displacement": "length", "force": "force"}
#: A rotational interface (``model: motion: rotation``): the displacement channel is an angle (SI rad), the force
#: channel a torque (SI N·m); the code's role names stay displacement and force.
_ROT_UNITS = {"time": TIME_UNITS, "displacement": ANGLE_UNITS, "force": TORQUE_UNITS}
_ROT_QUANTITY = {"time": "time", "displacement": "angle", "force": "torque"}
_SI = {"time": "s", "displacement": "m", "force": "N"}

#: The ``fmusa diagnose`` options that set each ColumnSpec field; error messages name them.
OPTIONS = {
    "time": "--time-column", "displacement": "--displacement-column", "force": "--force-column",
    "time_unit": "--time-unit", "displacement_unit": "--displacement-unit",
    "force_unit": "--force-unit", "rate": "--rate", "delimiter": "--delimiter", "decimal": "--decimal",
}
#: Field delimiters a file may use (detected when none is given): the spreadsheet exports' four.
DELIMITERS = {",": "comma", ";": "semicolon", "\t": "tab", "|": "bar"}
#: Decimal marks: the point, or the comma of European spreadsheets (detected when none is given).
DECIMALS = (".", ",")


class MeasuredDataError(FmusaError, ValueError):
    """A measured-data file or column specification that cannot be used. The message is
    ``file:line: column 'name' (role): what is wrong; how to fix it``.

    Fix: go to the file and line named; map the column with ``--time-column``, ``--displacement-column`` or
    ``--force-column``, convert its unit with ``--time-unit``, ``--displacement-unit`` or ``--force-unit``, or
    remove the bad rows (NaN, time that does not increase).
    """


# ============================================================================ units
def unit_table(role: str, motion: str = TRANSLATION) -> Mapping[str, float]:
    """Unit -> factor to SI of channel ``role`` (time, displacement, force) of a ``motion`` interface."""
    return (_ROT_UNITS if motion == ROTATION else _UNITS)[role]


def infer_motion(units: Mapping[str, str | None], rate: str | None = None) -> str | None:
    """``rotation`` when a declared unit (displacement or force, or the rate's) is rotational only, ``translation``
    when one is translational only, None when the units say nothing (SI defaults); a mix raises."""
    rot, tra = [], []
    for role in ("displacement", "force"):
        u = (units.get(role) or "").strip()
        if u in _ROT_UNITS[role] and u not in _UNITS[role]:
            rot.append(f"{role} in {u}")
        elif u in _UNITS[role] and u not in _ROT_UNITS[role] and u not in ("m", "N"):
            tra.append(f"{role} in {u}")
    m = _RATE.match(str(rate)) if rate else None
    if m:
        if any(m.group(2) in t for t in ROTATION_RATE_UNITS.values()):
            rot.append(f"rate {rate}")
        elif any(m.group(2) in t for t in RATE_UNITS.values()):
            tra.append(f"rate {rate}")
    if rot and tra:
        raise MeasuredDataError(f"ColumnSpec: {', '.join(rot)} are rotational and {', '.join(tra)} translational "
                                f"units; an interface is one or the other: give angle (rad, deg, mrad) and torque "
                                f"(N·m, N·mm, kN·m) units, or length and force units")
    return ROTATION if rot else TRANSLATION if tra else None


_ADJ = {TRANSLATION: "translational", ROTATION: "rotational"}


def _a(word: str) -> str:
    return ("an " if word[0] in "aeiou" else "a ") + word


def _unit_error(role: str, unit: str, where: str, motion: str = TRANSLATION) -> MeasuredDataError:
    units, quantity = (_ROT_UNITS, _ROT_QUANTITY) if motion == ROTATION else (_UNITS, _QUANTITY)
    accepted = ", ".join(units[role])
    if role != "time":
        other_units, other_q, other_m = ((_UNITS, _QUANTITY, TRANSLATION) if motion == ROTATION
                                         else (_ROT_UNITS, _ROT_QUANTITY, ROTATION))
        if unit in other_units[role]:
            return MeasuredDataError(
                f"{where}{role} unit: '{unit}' is {_a(other_q[role])} unit, but the interface is {_ADJ[motion]}; accepted {quantity[role]} units: {accepted} "
                f"({OPTIONS[role + '_unit']}, ColumnSpec.{role}_unit), or declare the interface's motion as "
                f"{other_m} (model: motion: {other_m} in the study file, ColumnSpec.motion)")
    other = [q for r, q in quantity.items() if r != role and unit in units[r]]
    if any(unit in table for table in RATE_UNITS.values()):
        other.append("rate")
    what = (f"'{unit}' is {_a(other[0])} unit, not {_a(quantity[role])} unit" if other
            else f"unknown unit '{unit}'")
    return MeasuredDataError(
        f"{where}{role} unit: {what}; accepted {quantity[role]} units: {accepted} "
        f"({OPTIONS[role + '_unit']}, ColumnSpec.{role}_unit)")


def unit_scale(role: str, unit: str, where: str = "", motion: str = TRANSLATION) -> float:
    """SI factor of ``unit`` for channel ``role``; rejects unknown and wrong-dimension units."""
    try:
        return unit_table(role, motion)[unit.strip()]
    except (KeyError, AttributeError):
        raise _unit_error(role, str(unit), where, motion) from None


_RATE = re.compile(r"^\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(\S+)\s*$")


def parse_rate(text: str, motion: str = TRANSLATION) -> tuple[float, str, str]:
    """``"10 mm/s"`` -> ``(0.01, "mm/s", "displacement")``: the rate in SI (m/s or N/s; rad/s or N·m/s for a
    ``rotation`` interface), its unit and the drive it belongs to. Raises :class:`MeasuredDataError` naming the
    accepted units."""
    tables = ROTATION_RATE_UNITS if motion == ROTATION else RATE_UNITS
    accepted = "; ".join(f"{d}: {', '.join(u)}" for d, u in tables.items())
    m = _RATE.match(str(text))
    if not m:
        raise MeasuredDataError(
            f"rate '{text}': expected a number and a unit, e.g. '10 mm/s' ({OPTIONS['rate']}, "
            f"ColumnSpec.rate); accepted units: {accepted}")
    value, unit = float(m.group(1)), m.group(2)
    for drive, table in tables.items():
        if unit in table:
            if not (value > 0 and math.isfinite(value)):
                raise MeasuredDataError(
                    f"rate '{text}': must be positive and finite (the direction comes from the "
                    f"data) ({OPTIONS['rate']}, ColumnSpec.rate)")
            return value * table[unit], unit, drive
    raise MeasuredDataError(
        f"rate '{text}': unknown rate unit '{unit}'; accepted units: {accepted} "
        f"({OPTIONS['rate']}, ColumnSpec.rate)")


# ============================================================================ dataclasses
@dataclass(frozen=True)
class ColumnSpec:
    """How to read one CSV format: column names, their units, sign flips, and an optional rate.

    ``rate`` (e.g. ``"10 mm/s"``, or ``"50 N/s"`` for a force drive) is for files without a time
    column: the test then ran the drive at this constant rate, and time is derived from it. This
    assumes uniform sampling: Δt = |least-squares slope of the drive against the sample index| /
    rate, and t = Δt·i. The least-squares slope, not end minus start, so that noise at the ends does
    not bias Δt. A drive that does not move one way on the whole (net slope ≈ 0) is rejected. With a
    rate the time column is not read, and a file that has one is an error (say which to use).

    Units are checked here, so a wrong unit fails before any file is read.
    """
    time: str = "time"
    displacement: str = "displacement"
    force: str = "force"
    time_unit: str = "s"
    displacement_unit: str = "m"
    force_unit: str = "N"
    flip_displacement: bool = False
    flip_force: bool = False
    rate: str | None = None
    #: the field delimiter (one of :data:`DELIMITERS`); None: detected from the file
    delimiter: str | None = None
    #: the decimal mark, "." or ","; None: detected from the file
    decimal: str | None = None
    #: ``translation`` (lengths and forces) or ``rotation`` (angles and torques: rad, deg, mrad; N·m, N·mm, kN·m);
    #: None: as the units say (translation when they say nothing)
    motion: str | None = None

    def __post_init__(self) -> None:
        if self.motion is not None and self.motion not in MOTIONS:
            raise MeasuredDataError(f"ColumnSpec: motion {self.motion!r} is not one of {', '.join(MOTIONS)}")
        if self.motion is None:
            found = infer_motion({r: getattr(self, r + "_unit") for r in ("displacement", "force")}, self.rate)
            object.__setattr__(self, "motion", found or TRANSLATION)
        if self.motion == ROTATION:   # the default units are the SI ones of the motion: rad and N·m
            for role, si in (("displacement", "rad"), ("force", "N·m")):
                if getattr(self, role + "_unit") == _SI[role]:
                    object.__setattr__(self, role + "_unit", si)
        if self.delimiter is not None and self.delimiter not in DELIMITERS:
            raise MeasuredDataError(f"ColumnSpec: delimiter {self.delimiter!r} is not one of "
                                    f"{', '.join(map(repr, DELIMITERS))} ({OPTIONS['delimiter']}, "
                                    f"ColumnSpec.delimiter; leave it out to detect it)")
        if self.decimal is not None and self.decimal not in DECIMALS:
            raise MeasuredDataError(f"ColumnSpec: decimal mark {self.decimal!r} is not '.' or ',' "
                                    f"({OPTIONS['decimal']}, ColumnSpec.decimal; leave it out to detect it)")
        if self.delimiter is not None and self.delimiter == self.decimal:
            raise MeasuredDataError(f"ColumnSpec: the delimiter and the decimal mark are both "
                                    f"{self.delimiter!r}; a file with decimal commas separates fields with ';'")
        for role in ROLES:
            unit_scale(role, getattr(self, role + "_unit"), "ColumnSpec: ", self.motion)
            name = getattr(self, role)
            if not isinstance(name, str) or not name.strip():
                raise MeasuredDataError(
                    f"ColumnSpec: {role} column name {name!r} is empty; give the column's header "
                    f"({OPTIONS[role]}, ColumnSpec.{role})")
        used = [self.displacement, self.force] + ([] if self.rate else [self.time])
        if len(set(used)) != len(used):
            raise MeasuredDataError(
                f"ColumnSpec: time, displacement and force columns must differ, got "
                f"{self.time!r}, {self.displacement!r}, {self.force!r}")
        if self.rate is not None:
            parse_rate(self.rate, self.motion)

    def column(self, role: str) -> str:
        """The header name of channel ``role``."""
        return getattr(self, role).strip()

    def unit(self, role: str) -> str:
        """The file's unit of channel ``role``."""
        return getattr(self, role + "_unit").strip()

    def scale(self, role: str) -> float:
        """Factor from the file's unit of ``role`` to SI."""
        return unit_scale(role, self.unit(role), motion=self.motion)

    @property
    def rate_si(self) -> tuple[float, str, str] | None:
        """:func:`parse_rate` of ``rate``, or None."""
        return None if self.rate is None else parse_rate(self.rate, self.motion)


def _frozen(a) -> np.ndarray:
    out = np.array(a, dtype=float)  # a copy: the caller's array stays writable and independent
    out.flags.writeable = False
    return out


@dataclass(frozen=True, eq=False)
class Experiment:
    """One measured experiment in SI units: t [s], displacement [m], force [N] (read-only arrays).

    ``drive`` is the channel the test imposed; the model is driven by :attr:`drive_signal` and
    predicts :attr:`response_signal`. ``meta`` records how the file was read (rows, units, rate,
    whether time was derived, the zero shifts, downsampling) so results can say what was fitted.
    """
    name: str
    path: Path
    drive: str
    t: np.ndarray
    displacement: np.ndarray
    force: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.drive not in DRIVES:
            raise MeasuredDataError(f"{self.name}: drive {self.drive!r} must be one of "
                                    f"{', '.join(DRIVES)} (--drive)")
        arrays = {k: _frozen(getattr(self, k)) for k in ("t", "displacement", "force")}
        n = {k: a.shape for k, a in arrays.items()}
        if any(a.ndim != 1 for a in arrays.values()) or len(set(n.values())) != 1:
            raise MeasuredDataError(f"{self.name}: t, displacement and force must be 1-D arrays "
                                    f"of one length, got shapes {n}")
        for k, a in arrays.items():
            object.__setattr__(self, k, a)
        object.__setattr__(self, "path", Path(self.path))
        object.__setattr__(self, "meta", dict(self.meta))

    @property
    def response(self) -> str:
        """The channel the model predicts: the one not imposed."""
        return "displacement" if self.drive == "force" else "force"

    @property
    def drive_signal(self) -> np.ndarray:
        """The imposed channel in SI (m or N)."""
        return getattr(self, self.drive)

    @property
    def response_signal(self) -> np.ndarray:
        """The measured channel the model must reproduce, in SI (N or m)."""
        return getattr(self, self.response)

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.t.size)

    @property
    def duration(self) -> float:
        """t[-1] - t[0] in s."""
        return float(self.t[-1] - self.t[0])

    def to_frame(self) -> pd.DataFrame:
        """The samples as a DataFrame with columns time, displacement, force (SI)."""
        return pd.DataFrame({"time": self.t, "displacement": self.displacement,
                             "force": self.force})


# ============================================================================ reading
def _where(path, first: int, last: int | None = None) -> str:
    return f"{path}:{first}" if last is None or last == first else f"{path}:{first}-{last}"


def _label(spec: ColumnSpec, role: str, drive: str) -> str:
    tag = role + (", the drive" if role == drive else "")
    return f"column '{spec.column(role)}' ({tag})"


_DECIMAL_COMMA = re.compile(r"^[-+]?\d*,\d+(?:[eE][-+]?\d+)?$")
_DECIMAL_POINT = re.compile(r"^[-+]?\d*\.\d+(?:[eE][-+]?\d+)?$")


def _first_lines(path: Path, n: int = 50) -> list[str]:
    """Up to ``n`` non-blank lines from the start of the file (at most 1 MB read)."""
    try:
        with open(path, "rb") as f:
            head = f.read(1 << 20)
    except OSError:
        return []
    text = head.decode("utf-8-sig", errors="replace")
    lines = text.splitlines()
    if len(head) == 1 << 20 and lines:
        lines = lines[:-1]          # the last may be cut
    return [ln for ln in lines if ln.strip()][:n]


def sniff_dialect(path: Path, spec: ColumnSpec) -> tuple[str, str, list[str]]:
    """(delimiter, decimal mark, what was detected) of CSV file ``path``: those of ``spec`` when given, else
    detected from its first lines: the delimiter that splits the header and every line into the same
    number (> 1) of fields, the most fields winning; the decimal comma when cells read like ``1,5`` and none
    like ``1.5``. A file that fits neither is read with ',' and '.', and the checks after say what fails."""
    lines = _first_lines(path)
    found = []
    delim = spec.delimiter
    if delim is None:
        best = (1, ",")
        for cand in DELIMITERS:
            counts = {ln.count(cand) for ln in lines}
            if lines and len(counts) == 1 and counts.pop() + 1 > best[0]:
                best = (lines[0].count(cand) + 1, cand)
        delim = best[1]
        found.append(f"delimiter {delim!r} ({DELIMITERS[delim]})")
    dec = spec.decimal
    if dec is None:
        cells = [c.strip().strip('"') for ln in lines[1:] for c in ln.split(delim)]
        comma = delim != "," and any(_DECIMAL_COMMA.match(c) for c in cells)
        dec = "," if comma and not any(_DECIMAL_POINT.match(c) for c in cells) else "."
        found.append(f"decimal mark {dec!r}")
    return delim, dec, found


def _duplicate_headers(path: Path, header: list[str]) -> None:
    """Two columns of one name: refused, naming both (which one is meant cannot be known)."""
    first: dict[str, int] = {}
    for i, name in enumerate(header, start=1):
        if name in first:
            raise MeasuredDataError(f"{path}:1: columns {first[name]} and {i} are both headed '{name}'; rename "
                                    f"one of them (fmusa cannot know which one is meant)")
        first[name] = i


def _read_table(path: Path, spec: ColumnSpec) -> pd.DataFrame:
    """The file as strings, one DataFrame row per line after the header (blank lines kept, so the
    row index maps to line = index + 2); trailing blank lines dropped. ``spec`` has its dialect."""
    if not path.exists():
        raise MeasuredDataError(f"{path}: file not found; check the path")
    if not path.is_file():
        raise MeasuredDataError(f"{path}: not a file; give a CSV file")
    try:
        df = pd.read_csv(path, sep=spec.delimiter, dtype=str, keep_default_na=False,
                         skip_blank_lines=False, encoding="utf-8-sig")
    except pd.errors.EmptyDataError:
        raise MeasuredDataError(f"{path}:1: file is empty; expected a header line and data rows "
                                f"(CSV with columns {spec.column('time')}, "
                                f"{spec.column('displacement')}, {spec.column('force')})") from None
    except pd.errors.ParserError as exc:
        m = re.search(r"Expected (\d+) fields in line (\d+), saw (\d+)", str(exc))
        if m:
            raise MeasuredDataError(f"{path}:{m.group(2)}: {m.group(3)} fields, the header has "
                                    f"{m.group(1)}; every row needs as many fields as the header "
                                    f"(a stray '{spec.delimiter}'?)") from None
        raise MeasuredDataError(f"{path}: not a readable CSV file ({str(exc).strip()}); every row "
                                f"needs as many fields as the header") from None
    except UnicodeDecodeError as exc:
        raise MeasuredDataError(f"{path}: not a text file ({exc.reason} at byte {exc.start}); "
                                f"save it as UTF-8 CSV") from None
    except OSError as exc:
        raise MeasuredDataError(f"{path}: cannot be read ({exc.strerror or exc}); check the "
                                f"file's permissions") from None
    import csv
    lines = _first_lines(path, 1)
    header = next(csv.reader(lines, delimiter=spec.delimiter), []) if lines else []
    _duplicate_headers(path, [h.strip() for h in header])
    df.columns = [str(c).strip() for c in df.columns]
    blank = df.apply(lambda col: col.isna() | (col.astype(str).str.strip() == "")).all(axis=1)
    keep = len(df)
    while keep > 0 and blank.iloc[keep - 1]:
        keep -= 1
    return df.iloc[:keep]


def _missing_columns(path: Path, df: pd.DataFrame, spec: ColumnSpec, roles: list[str]) -> None:
    missing = [r for r in roles if spec.column(r) not in df.columns]
    if not missing:
        return
    have = ", ".join(df.columns) or "(none)"
    names = ", ".join(f"'{spec.column(r)}' ({r})" for r in missing)
    how = "; ".join(f"{r}: {OPTIONS[r]} NAME (ColumnSpec.{r})" for r in missing)
    hint = ""
    if len(df.columns) == 1 and any(d in df.columns[0] for d in ";\t|"):
        hint = (" The header is one field: the file seems to use another delimiter than "
                f"'{spec.delimiter}'; give it with {OPTIONS['delimiter']} (ColumnSpec.delimiter).")
    if "time" in missing and spec.rate is None:
        how += (f"; or, for a file without time at a constant drive rate, {OPTIONS['rate']} "
                f"'10 mm/s' (ColumnSpec.rate)")
    raise MeasuredDataError(f"{path}:1: column{'s' if len(missing) > 1 else ''} {names} not in "
                            f"the header; the file has columns: {have}. Map "
                            f"{'them' if len(missing) > 1 else 'it'} with {how}.{hint}")


def _numeric(path: Path, df: pd.DataFrame, spec: ColumnSpec, roles: list[str],
             drive: str) -> dict[str, np.ndarray]:
    """Each column as floats; the first bad cell (by line, over all columns) is an error."""
    values: dict[str, np.ndarray] = {}
    first: tuple[int, str, int] | None = None  # (row, role, count of bad cells in that column)
    for role in roles:
        raw = df[spec.column(role)]
        text = raw.fillna("").astype(str).str.strip()
        if spec.decimal == ",":
            text = text.str.replace(",", ".", regex=False)
        num = pd.to_numeric(text, errors="coerce").to_numpy(dtype=float)
        bad = np.flatnonzero(~np.isfinite(num))
        values[role] = num
        if bad.size and (first is None or bad[0] < first[0]):
            first = (int(bad[0]), role, int(bad.size))
    if first is None:
        return values
    row, role, count = first
    cell = df[spec.column(role)].iloc[row]
    cell = "" if not isinstance(cell, str) else cell.strip()
    num = values[role][row]
    if cell == "":
        what, fix = "empty cell", "fill it or delete the row"
    elif math.isnan(num) and cell.lower() in ("nan", "-nan", "na", "n/a", "null", "none", "#n/a"):
        what, fix = f"'{cell}' is NaN", "fill it or delete the row"
    elif math.isinf(num):
        what, fix = f"'{cell}' is infinite", "fix or delete the row"
    else:
        what, fix = f"'{cell}' is not a number", "fix or delete the row"
        if re.fullmatch(r"[-+]?\d+,\d+", cell):
            fix = (f"write decimals with '.', not ','; if the file writes decimal commas throughout, give "
                   f"{OPTIONS['decimal']} ',' (ColumnSpec.decimal), with another delimiter than ','")
    more = f" ({count - 1} more bad cell{'s' if count > 2 else ''} in this column)" if count > 1 else ""
    raise MeasuredDataError(f"{_where(path, row + 2)}: {_label(spec, role, drive)}: {what}; "
                            f"{fix}{more}")


def _derive_time(path: Path, spec: ColumnSpec, drive: str, x: np.ndarray,
                 last_line: int) -> tuple[np.ndarray, float]:
    """Time from a constant drive rate and uniform sampling: Δt = |LS slope per sample| / rate."""
    rate, unit, rate_drive = spec.rate_si
    if rate_drive != drive:
        units = ", ".join((ROTATION_RATE_UNITS if spec.motion == ROTATION else RATE_UNITS)[drive])
        raise MeasuredDataError(
            f"{path}: rate '{spec.rate}' is a {rate_drive} rate but the drive is {drive}; give a "
            f"{drive} rate ({units}) with {OPTIONS['rate']}, or check --drive")
    i = np.arange(x.size, dtype=float)
    ic = i - i.mean()
    slope = float(np.dot(ic, x - x.mean()) / np.dot(ic, ic))  # SI units per sample
    travel, span = abs(slope) * (x.size - 1), float(x.max() - x.min())
    if travel < 0.5 * span:
        raise MeasuredDataError(
            f"{_where(path, 2, last_line)}: {_label(spec, drive, drive)}: time is derived from "
            f"the rate {spec.rate}, which needs a drive that moves one way at that rate, but its "
            f"straight-line trend covers only {travel / span:.0%} of its range (it goes back and "
            f"forth); give a time column ({OPTIONS['time']}) instead of {OPTIONS['rate']}")
    dt = abs(slope) / rate
    return dt * i, dt



def _text_name(name: str) -> str:
    """A file name as text: under an ASCII locale (``LC_ALL=C``) Python hands non-ASCII bytes of a name
    over as surrogates, which no report, figure or JSON file can hold; they are read back as UTF-8."""
    return name.encode("utf-8", "surrogateescape").decode("utf-8", "replace")

def load_experiment(path, drive: str, spec: ColumnSpec = ColumnSpec(), zero_drive: bool = True,
                    zero_time: bool = True) -> Experiment:
    """Read, check and convert one CSV file into an :class:`Experiment` (SI units).

    ``zero_drive``: the model starts at rest at zero, so the first drive value is subtracted from
    the drive (``meta['zero_shift']``, SI); the response is left as measured. ``zero_time``: time
    starts at 0, the FMU's start time (``meta['time_shift']``, s). Errors name file, line, column.
    """
    path = Path(path)
    if drive not in DRIVES:
        raise MeasuredDataError(f"{path}: drive {drive!r} must be one of {', '.join(DRIVES)} "
                                f"(--drive): the channel the test imposed")
    delimiter, decimal, detected = sniff_dialect(path, spec) if path.is_file() else (",", ".", [])
    spec = replace(spec, delimiter=delimiter, decimal=decimal)
    df = _read_table(path, spec)
    derived = spec.rate is not None
    roles = [r for r in ROLES if not (derived and r == "time")]
    _missing_columns(path, df, spec, roles)
    if derived and spec.column("time") in df.columns:
        raise MeasuredDataError(
            f"{path}:1: column '{spec.column('time')}' (time) is in the file and a rate "
            f"({spec.rate}) was given; use one: drop {OPTIONS['rate']} to read the time column, "
            f"or delete the column to derive time from the rate")
    n = len(df)
    last = n + 1
    if n < MIN_ROWS:
        raise MeasuredDataError(
            f"{_where(path, 2, last) if n else f'{path}:1'}: {n} data row{'s' if n != 1 else ''}; "
            f"at least {MIN_ROWS} are needed to fit a model (give the whole test record)")
    raw = _numeric(path, df, spec, roles, drive)
    si = {r: raw[r] * spec.scale(r) for r in roles}
    if spec.flip_displacement:
        si["displacement"] = -si["displacement"]
    if spec.flip_force:
        si["force"] = -si["force"]

    x = si[drive]
    span = float(x.max() - x.min())
    if span <= 1e-9 * spec.scale(drive):
        raise MeasuredDataError(
            f"{_where(path, 2, last)}: {_label(spec, drive, drive)}: does not move (range "
            f"{span / spec.scale(drive):.3g} {spec.unit(drive)}, at {raw[drive][0]:g} {spec.unit(drive)}); the model is driven by this column: check "
            f"--drive (which channel did the test impose?) and {OPTIONS[drive]}")

    dt = None
    if derived:
        t, dt = _derive_time(path, spec, drive, x, last)
    else:
        t = si["time"]
        bad = np.flatnonzero(np.diff(t) <= 0)
        if bad.size:
            k = int(bad[0])
            rt = raw["time"]
            raise MeasuredDataError(
                f"{_where(path, k + 3)}: {_label(spec, 'time', drive)}: time {rt[k + 1]:g} "
                f"{spec.unit('time')} is not after {rt[k]:g} {spec.unit('time')} on line {k + 2}; "
                f"time must increase strictly (sort the rows, remove repeated samples, or check "
                f"{OPTIONS['time']})")
    time_shift = float(t[0]) if zero_time else 0.0
    zero_shift = float(x[0]) if zero_drive else 0.0
    si[drive] = x - zero_shift
    meta = {
        "rows": n, "lines": (2, last),
        "columns": {r: (spec.column(r) if r in roles else None) for r in ROLES},
        "units": {r: (spec.unit(r) if r in roles else None) for r in ROLES},
        "flipped": [r for r in ("displacement", "force") if getattr(spec, "flip_" + r)],
        "rate": spec.rate, "rate_si": spec.rate_si[0] if derived else None,
        "time_derived": derived, "dt": dt,
        "zero_drive": zero_drive, "zero_shift": zero_shift,
        "zero_time": zero_time, "time_shift": time_shift,
        "downsampled_from": None, "block": None,
        "delimiter": delimiter, "decimal": decimal, "detected": detected,
    }
    if spec.motion == ROTATION:   # angle in rad, torque in N·m (translation's meta stays as it was)
        meta["motion"] = ROTATION
    return Experiment(name=_text_name(path.stem), path=path, drive=drive, t=t - time_shift,
                      displacement=si["displacement"], force=si["force"], meta=meta)


# ============================================================================ downsampling
@dataclass(frozen=True, eq=False)
class Blocks:
    """The samples a block-averaged experiment was made from, as much of them as the averaging check needs
    (:mod:`fmusa.diagnose.averaging`): the original time and drive (SI, zeroed as the experiment), and which
    samples make each block: ``starts[i]`` the first original sample of block i (blocks are consecutive), and
    ``weight`` each sample's weight in its block's mean (None: equal weights, 1 / the block's size).
    ``experiment.meta['blocks']`` of a downsampled experiment; the response is not kept (the check compares
    the model with itself)."""
    t: np.ndarray
    drive: np.ndarray
    starts: np.ndarray
    weight: np.ndarray | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "t", _frozen(self.t))
        object.__setattr__(self, "drive", _frozen(self.drive))
        starts = np.array(self.starts, dtype=np.int64)
        starts.flags.writeable = False
        object.__setattr__(self, "starts", starts)
        if self.weight is not None:
            object.__setattr__(self, "weight", _frozen(self.weight))

    @property
    def n(self) -> int:
        """Original samples."""
        return int(self.t.size)

    @property
    def sizes(self) -> np.ndarray:
        """Original samples per block."""
        return np.diff(np.append(self.starts, self.n))

    def weights(self) -> np.ndarray:
        """Each original sample's weight in its block's mean (each block's weights sum to 1)."""
        if self.weight is not None:
            return self.weight
        return np.repeat(1.0 / self.sizes, self.sizes)

    def mean(self, values) -> np.ndarray:
        """Block means of ``values`` (one per original sample), as the experiment's samples were made."""
        v = np.asarray(values, float)
        if v.shape != self.t.shape:
            raise ValueError(f"{v.shape[0] if v.ndim else 0} values for {self.n} original samples")
        return np.add.reduceat(v * self.weights(), self.starts)


def downsample(exp: Experiment, max_points: int) -> Experiment:
    """At most ``max_points`` samples by block averaging; ``exp`` itself when already that small.

    The first and last samples are kept as they are: the first is the rest state the model starts
    from (drive 0 at t = 0 after zeroing) and the last fixes the end time. The samples between are
    averaged in consecutive blocks of equal size (the last block may be shorter), time included, so
    a linear stretch stays on its line. Averaging, unlike picking every k-th sample, also reduces
    the noise that a piecewise-linear drive would turn into velocity noise.

    The averaged experiment keeps the original time and drive and the blocks (``meta['blocks']``, a
    :class:`Blocks`): averaging is right only where the response is close to a straight line within a block,
    and the diagnosis checks that on the fitted model (:mod:`fmusa.diagnose.averaging`).
    """
    if int(max_points) != max_points or max_points < 3:
        raise MeasuredDataError(f"{exp.name}: max_points {max_points!r} must be an integer >= 3 "
                                f"(first sample, last sample, one block)")
    max_points = int(max_points)
    n = exp.n
    if n <= max_points:
        return exp
    inner = n - 2
    k = -(-inner // (max_points - 2))
    starts = np.arange(1, n - 1, k)
    counts = np.diff(np.append(starts, n - 1))

    def block(a: np.ndarray) -> np.ndarray:
        mid = np.add.reduceat(a[1:-1], starts - 1) / counts
        return np.concatenate(([a[0]], mid, [a[-1]]))

    edges = np.concatenate(([0], starts, [n - 1]))       # each block's first sample, the end ones alone
    before = exp.meta.get("blocks")
    if isinstance(before, Blocks):     # averaged again: the blocks of blocks, in the first samples' terms
        sizes = np.diff(np.append(edges, n))
        w = before.weights() * np.repeat(1.0 / sizes, sizes)[np.repeat(np.arange(n), before.sizes)]
        blocks = Blocks(before.t, before.drive, before.starts[edges], w)
    else:
        blocks = Blocks(exp.t, exp.drive_signal, edges)
    return replace(exp, t=block(exp.t), displacement=block(exp.displacement),
                   force=block(exp.force), meta=dict(exp.meta, downsampled_from=blocks.n, block=int(k), blocks=blocks))


# ============================================================================ several files
def _unique_names(paths: list[Path]) -> list[str]:
    """File stems; stems that repeat get their folder's name in front, then a counter."""
    stems = [p.stem for p in paths]
    names = list(stems)
    for i, p in enumerate(paths):
        if stems.count(p.stem) > 1:
            names[i] = f"{p.parent.name}_{p.stem}" if p.parent.name else p.stem
    seen: dict[str, int] = {}
    out = []
    for name in names:
        seen[name] = seen.get(name, 0) + 1
        out.append(_text_name(name if seen[name] == 1 else f"{name}-{seen[name]}"))
    return out


def load_experiments(paths: Iterable, drive: str,
                     spec: ColumnSpec | Sequence[ColumnSpec] = ColumnSpec(),
                     zero_drive: bool = True, zero_time: bool = True,
                     max_points: int | None = None) -> list[Experiment]:
    """All files, in order, as experiments with unique names (for a joint fit).

    ``spec`` is one ColumnSpec for all files or one per file. Every file is checked before anything
    is raised, so one error lists the problems of all files at once. ``max_points``: see
    :func:`downsample`.
    """
    paths = [Path(p) for p in paths]
    if not paths:
        raise MeasuredDataError("no measured-data files given; pass one or more CSV files")
    specs = [spec] * len(paths) if isinstance(spec, ColumnSpec) else list(spec)
    if len(specs) != len(paths):
        raise MeasuredDataError(f"{len(specs)} column specs for {len(paths)} files; give one spec "
                                f"or one per file")
    seen: dict[Path, Path] = {}
    for p in paths:
        key = p.resolve()
        if key in seen:
            raise MeasuredDataError(f"{p}: given twice (also as {seen[key]}); give each file once")
        seen[key] = p
    out, errors = [], []
    for p, s, name in zip(paths, specs, _unique_names(paths)):
        try:
            exp = load_experiment(p, drive, s, zero_drive=zero_drive, zero_time=zero_time)
        except MeasuredDataError as exc:
            errors.append(str(exc))
            continue
        if name != exp.name:
            exp = replace(exp, name=name)
        out.append(exp if max_points is None else downsample(exp, max_points))
    if errors:
        head = f"{len(errors)} of {len(paths)} files cannot be used:\n" if len(errors) > 1 else ""
        raise MeasuredDataError(head + "\n".join(errors))
    return out
