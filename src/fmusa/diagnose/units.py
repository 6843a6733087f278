"""Units sanity: do the magnitudes of the measured tests fit the scale of the FMU they are fitted through?

A fit never notices a wrong unit: its bounds and starts are scaled to the data (:func:`effects.data_scales`),
so a test in mm read as m is fitted as well as the right one, only 1000 times off (a 500 mm peak for a screw).
:func:`check_units` compares what the data imply (the peak displacement, the peak force and the secant
stiffness force / displacement) with plausible ranges taken from the FMU's own scale (:class:`ModelScale`:
the start values the model description names in its ``scale``: a stiffness, a length of the part, a
smoothing width and a nominal load). When a quantity is outside
its range, it tries the other units of each channel (the declared unit of the file replaced by another
length or force unit) and names the one that brings every quantity into range, with the option that fixes
it (``--displacement-unit mm``, ``ColumnSpec.displacement_unit``). Nothing is fitted or run.

Plausible ranges (factors of :data:`RANGES`): stiffness within a factor 100 of the FMU's, peak displacement
from 10 smoothing widths (below that the model's rounded corners are all there is) up to the length of the
part, peak force below 100 times the nominal load. A unit mistake is a factor 1000 (mm for m, kN for N) or
more, so it leaves these ranges, while a real specimen a factor 10 softer or stiffer than the model's
default stays inside.

    from fmusa.diagnose.units import check_units, model_scale
    report = check_units(experiments, model_scale("dist/ScrewVertebra.fmu"))
    report["warnings"]     # [] or one message per problem, naming the likely unit and the option
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from fmusa.diagnose.interface import ModelInterface
from fmusa.diagnose.measured import FORCE_UNITS, LENGTH_UNITS, OPTIONS

__all__ = ["ModelScale", "RANGES", "model_scale", "implied_magnitudes", "check_units"]

#: How far from the FMU's scale a quantity may be and still be plausible.
RANGES = {"stiffness_factor": 100.0, "resolution_factor": 10.0, "force_factor": 100.0}

#: Units tried as the likely one (lbf is within a factor 5 of N: no magnitude check can tell it).
_TRY = {"displacement": ("m", "cm", "mm", "um"), "force": ("N", "kN", "mN")}
_SI = {"displacement": LENGTH_UNITS, "force": FORCE_UNITS}


@dataclass(frozen=True)
class ModelScale:
    """The FMU's own scale, from the start values of its parameters (None: not known, not checked)."""
    stiffness: float | None = None    # N/m
    length: float | None = None       # m: no displacement larger than this is plausible
    resolution: float | None = None   # m: the smallest displacement the model resolves
    force: float | None = None        # N: the nominal load
    variables: Mapping[str, str] = field(default_factory=dict)   # quantity -> FMU variable it came from

    def ranges(self) -> dict[str, tuple[float, float]]:
        """Plausible (low, high) per quantity: stiffness [N/m], peak displacement [m], peak force [N]."""
        out = {}
        if self.length or self.resolution:
            out["displacement"] = (RANGES["resolution_factor"] * (self.resolution or 0.0), self.length or math.inf)
        if self.force:
            out["force"] = (0.0, RANGES["force_factor"] * self.force)
        if self.stiffness:
            f = RANGES["stiffness_factor"]
            out["stiffness"] = (self.stiffness / f, self.stiffness * f)
        return out


def model_scale(fmu_path: str | os.PathLike, interface: ModelInterface | None = None) -> ModelScale:
    """The scale of the FMU: the start values of the variables ``interface.scale_variables`` names
    (missing or non-positive ones are left out, and their checks with them)."""
    from fmusa.diagnose.models import resolve
    from fmusa.fmi.info import read_fmu_info

    interface = resolve(interface, fmu_path)
    info = read_fmu_info(fmu_path)
    values, used = {}, {}
    for quantity, name in interface.scale_variables.items():
        v = info.variable(name)
        try:
            x = float(v.start) if v is not None and v.start is not None else float("nan")
        except (TypeError, ValueError):
            x = float("nan")
        if math.isfinite(x) and x > 0:
            values[quantity], used[quantity] = x, name
    return ModelScale(**values, variables=used)


def implied_magnitudes(e) -> dict[str, float]:
    """What one experiment implies in SI: peak |displacement|, peak |force| and the secant stiffness (the
    least-squares line through the origin, as the fit's bounds use it)."""
    y, F = np.asarray(e.displacement, float), np.asarray(e.force, float)
    yy = float(np.dot(y, y))
    return {"displacement": float(np.max(np.abs(y))), "force": float(np.max(np.abs(F))),
            "stiffness": abs(float(np.dot(y, F))) / yy if yy > 0 else float("nan")}


def _problems(m: Mapping[str, float], ranges: Mapping[str, tuple[float, float]]) -> list[str]:
    """The quantities outside their plausible range."""
    return [q for q, (lo, hi) in ranges.items() if math.isfinite(m[q]) and not lo <= m[q] <= hi]


def _declared(e, role: str) -> str:
    units = (e.meta or {}).get("units") or {}
    u = units.get(role)
    return u if u in _SI[role] else ("m" if role == "displacement" else "N")


def _alternatives(m: Mapping[str, float], declared: Mapping[str, str], ranges, c_ref: float | None) -> list[dict]:
    """Other units of the two channels that make every quantity plausible, likeliest first: fewer channels
    changed, then the stiffness nearer the FMU's."""
    out = []
    for ud in _TRY["displacement"]:
        for uf in _TRY["force"]:
            fd = _SI["displacement"][ud] / _SI["displacement"][declared["displacement"]]
            ff = _SI["force"][uf] / _SI["force"][declared["force"]]
            if fd == 1.0 and ff == 1.0:
                continue
            mm = {"displacement": m["displacement"] * fd, "force": m["force"] * ff,
                  "stiffness": m["stiffness"] * ff / fd}
            if _problems(mm, ranges):
                continue
            changed = {r: u for r, u in (("displacement", ud), ("force", uf)) if u != declared[r]}
            dist = abs(math.log(mm["stiffness"] / c_ref)) if c_ref and mm["stiffness"] > 0 else 0.0
            out.append({"units": changed, "magnitudes": mm, "_key": (len(changed), dist)})
    out.sort(key=lambda a: a["_key"])
    return [{k: v for k, v in a.items() if k != "_key"} for a in out]


def _q(quantity: str, x: float) -> str:
    """A magnitude as the message writes it (natural units)."""
    if quantity == "displacement":
        return f"{x * 1e3:.3g} mm"
    if quantity == "force":
        return f"{x:.3g} N"
    return f"{x * 1e-3:.3g} N/mm"


#: the kind of magnitude of each scale quantity, for the message
_QUANTITY = {"stiffness": "stiffness", "length": "displacement", "resolution": "displacement", "force": "force"}
_LABEL = {"displacement": "peak displacement", "force": "peak force", "stiffness": "implied stiffness"}


def _outside(q: str, x: float, lo: float, hi: float) -> str:
    """One quantity out of its range, with the range."""
    if lo > 0 and math.isfinite(hi):
        rng = f"{_q(q, lo)} to {_q(q, hi)}"
    else:
        rng = f"up to {_q(q, hi)}" if math.isfinite(hi) else f"from {_q(q, lo)}"
    return f"{_LABEL[q]} {_q(q, x)} (plausible {rng})"


def _option(role: str, unit: str) -> str:
    return f"{OPTIONS[role + '_unit']} {unit}"


def _message(names: Sequence[str], m: Mapping[str, float], bad: Sequence[str], declared: Mapping[str, str],
             scale: ModelScale, alts: list[dict]) -> tuple[str, str | None, dict | None]:
    """The warning, the option that fixes it (or None) and the likely units."""
    ranges = scale.ranges()
    what = "; ".join(_outside(q, m[q], *ranges[q]) for q in bad)
    src = ", ".join(f"{v} = {_q(_QUANTITY[q], getattr(scale, q))}" for q, v in scale.variables.items())
    who = names[0] if len(names) == 1 else \
        f"{len(names)} experiments ({', '.join(names)}; the numbers are {names[0]}'s)"
    text = (f"units: {who}, read as displacement in {declared['displacement']} and force in "
            f"{declared['force']}: {what}, against the FMU's scale ({src}).")
    if not alts:
        return text + " No other unit of the displacement or force column brings these into range: check the " \
                      "columns and their units.", None, None
    best = alts[0]
    fix = " ".join(_option(r, u) for r, u in best["units"].items())
    likely = " and ".join(f"the {r} column is likely in {u}, not {declared[r]}" for r, u in best["units"].items())
    then = ", ".join(f"{_LABEL[q]} {_q(q, best['magnitudes'][q])}" for q in ("displacement", "force", "stiffness"))
    text += f" {likely[0].upper()}{likely[1:]}: pass {fix} (then {then})."
    others = [" ".join(_option(r, u) for r, u in a["units"].items()) for a in alts[1:3]]
    if others:
        text += f" Also in range, less likely: {'; '.join(others)}."
    return text, fix, dict(best["units"])


def check_units(experiments: Sequence, scale: ModelScale) -> dict:
    """Compare the magnitudes each experiment implies with the FMU's scale.

    Returns ``{"ranges", "experiments": [{name, declared, magnitudes, outside}], "warnings": [{"message",
    "fix", "likely_units", "experiments", "outside"}]}``; experiments with the same problem and fix share
    one warning."""
    ranges = scale.ranges()
    rows, groups = [], {}
    for e in experiments:
        m = implied_magnitudes(e)
        declared = {r: _declared(e, r) for r in ("displacement", "force")}
        bad = _problems(m, ranges)
        rows.append({"name": e.name, "declared": declared, "magnitudes": m, "outside": bad})
        if not bad:
            continue
        alts = _alternatives(m, declared, ranges, scale.stiffness)
        key = (tuple(bad), tuple(sorted(declared.items())), tuple(sorted(alts[0]["units"].items())) if alts else ())
        groups.setdefault(key, []).append((e.name, m, bad, declared, alts))
    warnings = []
    for items in groups.values():
        names = [i[0] for i in items]
        _, m, bad, declared, alts = items[0]
        text, fix, likely = _message(names, m, bad, declared, scale, alts)
        warnings.append({"kind": "units", "message": text, "fix": fix, "likely_units": likely,
                         "experiments": names, "outside": list(bad)})
    return {"ranges": {q: list(v) for q, v in ranges.items()},
            "scale": {q: getattr(scale, q) for q in scale.variables}, "scale_variables": dict(scale.variables),
            "experiments": rows, "warnings": warnings}
