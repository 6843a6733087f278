"""The FMU variables a diagnosis drives and reads, so that the calibration knows no model by name.

A diagnosis imposes the measured drive (displacement or force) on the FMU and compares one of its
outputs with the measured response. Which variables do that is a property of the FMU, not of the
method: a :class:`ModelInterface` names them. It is data, read from a diagnosis study file (its
``model``, ``baseline`` and ``effects`` sections, :mod:`fmusa.diagnose.study`) or from a built-in model
description (:mod:`fmusa.diagnose.models`, chosen by the FMU's model name when no study names one).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

from fmusa.diagnose.effects import DiagnoseError
from fmusa.fmi.info import Value

__all__ = ["ModelInterface", "AttachedElement", "DRIVES", "WHERE"]

#: What a test may impose (the measured channel that drives the model).
DRIVES = ("displacement", "force")
#: Where the candidate effects go: parameters of the FMU itself, or an element FMU coupled at an interface.
WHERE = ("inside", "attached")


@dataclass(frozen=True)
class AttachedElement:
    """An interface element coupled to the model FMU (``effects: where: attached``).

    The element FMU takes the model's interface motion (``displacement_output``, ``velocity_output``) and
    returns its force, which enters the model at ``force_input`` multiplied by ``force_sign``.
    ``drive_input`` is the model input that takes the measured drive when the model has one of its own
    (else None: the drive reaches the model through the element's far end, see the docs)."""
    element_fmu: Path
    force_input: str
    displacement_output: str
    velocity_output: str
    force_sign: float = -1.0
    scheme: str = "auto"


@dataclass(frozen=True)
class ModelInterface:
    """How a diagnosis drives an FMU and reads its response.

    Under a displacement drive the FMU follows ``displacement_input`` (its slope goes in through
    ``fmi2SetRealInputDerivatives``), once the Boolean ``follow_input`` (if any) is set; under a
    force drive ``force_input`` is the load. ``force_output`` and ``displacement_output`` are the
    *measured* channels. ``mode_variable`` (optional) selects the drive with ``mode_values``;
    ``drive_parameters`` are further parameters set per drive, ``tolerance_parameter`` receives the
    solver's relative tolerance, ``fixed_parameters`` are set in every run, and ``parameter_names`` maps a
    fitted parameter of the effect catalogue (:mod:`fmusa.diagnose.effects`) to its FMU variable where the
    two differ. ``input_scale`` / ``output_scale`` per drive convert units: the FMU input is the SI value
    divided by its factor, the SI response is the FMU output times its factor (1 when absent).
    ``scale_variables`` names the parameters whose start values give the FMU's scale for the units check
    (:mod:`fmusa.diagnose.units`: ``stiffness`` [N/m], ``length`` [m], ``resolution`` [m], ``force`` [N]);
    a quantity left out is not checked. ``bounds`` replace the data-scaled bounds of fitted parameters
    (catalogue names). ``candidates``: the effects this model can carry (None: every one of the catalogue).
    ``attached``: the element the effects live in when they are not parameters of the FMU itself.
    """
    mode_variable: str | None = None
    mode_values: Mapping[str, int] = field(default_factory=dict)
    displacement_input: str | None = None
    follow_input: str | None = None
    force_input: str | None = None
    force_output: str | None = None
    displacement_output: str | None = None
    drive_parameters: Mapping[str, Mapping[str, Value]] = field(default_factory=dict)
    tolerance_parameter: str | None = None
    fixed_parameters: Mapping[str, Value] = field(default_factory=dict)
    parameter_names: Mapping[str, str] = field(default_factory=dict)
    scale_variables: Mapping[str, str] = field(default_factory=dict)
    input_scale: Mapping[str, float] = field(default_factory=dict)
    output_scale: Mapping[str, float] = field(default_factory=dict)
    bounds: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    candidates: tuple[str, ...] | None = None
    attached: AttachedElement | None = None
    #: what the description is called in messages (the FMU's model name or the study's)
    name: str = "model"
    #: None (translation: displacement and force, m and N) or ``rotation`` (an angle and a torque, rad and N·m):
    #: the units the report, the console and the figures write (:mod:`fmusa.diagnose.motion`); not in the repr,
    #: which keys the fit cache: the fits are the same numbers either way
    motion: str | None = field(default=None, repr=False)

    def drives(self) -> tuple[str, ...]:
        """The drives this model can impose: those with an input for the drive and an output for the response."""
        out = []
        for d in DRIVES:
            if self.input_name(d, check=False) and self.output_name(d, check=False):
                if self.mode_variable is None or d in self.mode_values:
                    out.append(d)
        return tuple(out)

    def check_drive(self, drive: str) -> None:
        """Refuse a drive this interface cannot impose, naming the ones it can."""
        if drive not in DRIVES:
            raise DiagnoseError(f"--drive {drive!r}: use 'force' or 'displacement'")
        if drive not in self.drives():
            can = " or ".join(repr(d) for d in self.drives()) or "none"
            raise DiagnoseError(f"--drive {drive!r}: the description of {self.name} gives no FMU input for a "
                                f"{drive} drive and output for its response (it can impose: {can}); add "
                                f"model.drives.{drive} (input and response) to the study file")

    def input_name(self, drive: str, check: bool = True) -> str | None:
        """The FMU input the measured drive is fed into."""
        name = self.displacement_input if drive == "displacement" else self.force_input
        if check and not name:
            self.check_drive(drive)
        return name

    def output_name(self, drive: str, check: bool = True) -> str | None:
        """The FMU output compared with the measured response (the channel the drive does not impose)."""
        name = self.force_output if drive == "displacement" else self.displacement_output
        if check and not name:
            self.check_drive(drive)
        return name

    def settings(self, drive: str, rtol: float) -> dict[str, Value]:
        """The fixed parameters of a driven run: mode, input switch, per-drive and common settings."""
        self.check_drive(drive)
        out: dict[str, Value] = {}
        if self.mode_variable:
            out[self.mode_variable] = self.mode_values[drive]
        if drive == "displacement" and self.follow_input:
            out[self.follow_input] = True
        out.update(self.drive_parameters.get(drive, {}))
        if self.tolerance_parameter:
            out[self.tolerance_parameter] = rtol
        out.update(self.fixed_parameters)
        return out

    def variable(self, parameter: str) -> str:
        """The FMU variable of a fitted parameter."""
        return self.parameter_names.get(parameter, parameter)
