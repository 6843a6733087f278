"""Translation or rotation: the units and words of the interface a diagnosis fits.

The interface element and the fits are unit-agnostic: ``s`` is a displacement or an angle, ``F`` a force or a
torque, and the effect catalogue's parameters (effects.UNITS, effects.ROTATION_UNITS) are the same numbers either
way.
What changes is what the user reads and writes: the units a measured column may be in, the SI unit each value
is held in (m and N, or rad and N·m) and the units the report, the console and the figures show. This module
holds those tables; every other module asks it by the motion's name (``translation``, the default, or
``rotation``).

    from fmusa.diagnose.motion import si_unit, natural_unit, channel_word
    si_unit(STIFFNESS, "rotation")        # 'N·m/rad' (STIFFNESS of fmusa.diagnose.effects)
    natural_unit("rad", "rotation")       # ('deg', 57.29...): the value in rad times the factor
    channel_word("force", "rotation")     # 'torque'
"""
from __future__ import annotations

import contextlib
import contextvars
import math
from typing import Iterator, Mapping

__all__ = ["MOTIONS", "TRANSLATION", "ROTATION", "ANGLE_UNITS", "TORQUE_UNITS", "ROTATION_RATE_UNITS",
           "ROTATION_NATURAL", "motion_of", "si_unit", "natural_unit", "channel_word",
           "channel_unit", "current", "use"]

TRANSLATION, ROTATION = "translation", "rotation"
#: The motions an interface may have (``model: motion:`` in a diagnosis study).
MOTIONS = (TRANSLATION, ROTATION)

_DEG = math.pi / 180.0
#: Angle unit -> factor to rad.
ANGLE_UNITS = {"rad": 1.0, "deg": _DEG, "mrad": 1e-3}
#: Torque unit -> factor to N·m (the middle dot, '*' or nothing between N and m).
TORQUE_UNITS = {"N·m": 1.0, "N*m": 1.0, "Nm": 1.0, "N.m": 1.0, "N·mm": 1e-3, "N*mm": 1e-3, "Nmm": 1e-3,
                "kN·m": 1e3, "kN*m": 1e3, "kNm": 1e3}
#: Drive rates of a rotational test: angle rates for an angle drive, torque rates for a torque drive.
ROTATION_RATE_UNITS = {
    "displacement": {"rad/s": 1.0, "deg/s": _DEG, "mrad/s": 1e-3, "deg/min": _DEG / 60.0},
    "force": {"N·m/s": 1.0, "N*m/s": 1.0, "Nm/s": 1.0, "N.m/s": 1.0},
}

#: SI unit of a rotational value -> (the unit the report shows, factor SI -> shown): angles in degrees, torques
#: and stiffnesses as SI (N·m, N·m/rad, N·m·s/rad: the units rotational stiffness is quoted in).
ROTATION_NATURAL = {"rad": ("deg", 1.0 / _DEG), "rad/s": ("deg/s", 1.0 / _DEG), "1/rad": ("1/rad", 1.0),
                    "N·m": ("N·m", 1.0), "N·m/rad": ("N·m/rad", 1.0), "N·m·s/rad": ("N·m·s/rad", 1.0),
                    "s": ("s", 1.0), "1": ("", 1.0), "": ("", 1.0)}

#: The words of the two channels (the code's role names are translation's).
_WORDS = {ROTATION: {"displacement": "angle", "force": "torque", "velocity": "angular velocity"}}
#: The SI unit of each channel.
_CHANNEL_SI = {TRANSLATION: {"displacement": "m", "force": "N", "velocity": "m/s"},
               ROTATION: {"displacement": "rad", "force": "N·m", "velocity": "rad/s"}}

_CURRENT: contextvars.ContextVar[str] = contextvars.ContextVar("fmusa_motion", default=TRANSLATION)


def motion_of(diag_or_name: Mapping | str | None) -> str:
    """The motion of a diagnosis dict (``data.motion``, absent for translation) or a name (None: translation)."""
    if diag_or_name is None:
        return TRANSLATION
    if isinstance(diag_or_name, str):
        return diag_or_name
    return ((diag_or_name.get("data") or {}).get("motion")) or TRANSLATION


def current() -> str:
    """The motion of what is being written now (:func:`use`), translation unless set."""
    return _CURRENT.get()


@contextlib.contextmanager
def use(motion: str | Mapping | None) -> Iterator[str]:
    """Within the block, values without a motion of their own are in ``motion`` (a name or a diagnosis)."""
    token = _CURRENT.set(motion_of(motion))
    try:
        yield _CURRENT.get()
    finally:
        _CURRENT.reset(token)


def si_unit(name: str, motion: str | None = None) -> str:
    """The SI unit of catalogue parameter ``name`` ('' when it has none)."""
    from fmusa.diagnose.effects import ROTATION_UNITS, UNITS

    table = ROTATION_UNITS if (motion or current()) == ROTATION else UNITS
    return table.get(name, "")


def natural_unit(si: str, motion: str | None = None) -> tuple[str, float] | None:
    """(the unit a rotational SI value is shown in, factor SI -> shown), or None under translation."""
    if (motion or current()) != ROTATION:
        return None
    return ROTATION_NATURAL.get(si, (si, 1.0))


def channel_word(role: str, motion: str | None = None) -> str:
    """'displacement' / 'force' / 'velocity' as the motion says them ('angle', 'torque', 'angular velocity')."""
    return _WORDS.get(motion or current(), {}).get(role, role)


def channel_unit(role: str, motion: str | None = None) -> str:
    """The SI unit of a channel ('m', 'N', 'm/s'; 'rad', 'N·m', 'rad/s')."""
    return _CHANNEL_SI[motion or current()][role]
