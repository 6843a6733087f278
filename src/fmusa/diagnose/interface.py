"""The FMU variables a diagnosis drives and reads, so that the calibration knows no model by name.

A diagnosis imposes the measured drive (displacement or force) on the FMU and compares one of its
outputs with the measured response. Which variables do that is a property of the FMU, not of the
method: :class:`ModelInterface` names them, and :data:`SCREW_VERTEBRA` is the one place that holds
the names of this repository's FMU (the public declarations of ``modelica/ScrewVertebra.mo``). Pass another interface to
:func:`fmusa.diagnose.run.diagnose` to diagnose an FMU with other variable names.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping

from fmusa.diagnose.effects import DiagnoseError
from fmusa.fmi.info import Value

__all__ = ["ModelInterface", "SCREW_VERTEBRA", "DRIVES"]

#: What a test may impose (the measured channel that drives the model).
DRIVES = ("displacement", "force")


@dataclass(frozen=True)
class ModelInterface:
    """How a diagnosis drives an FMU and reads its response.

    ``mode_variable`` selects the drive, ``mode_values`` gives its value per drive. Under a
    displacement drive the FMU follows ``displacement_input`` (its slope goes in through
    ``fmi2SetRealInputDerivatives``), once the Boolean ``follow_input`` (if any) is set; under a
    force drive ``force_input`` is the load. ``force_output`` and ``displacement_output`` are the
    *measured* channels (with the sensor offsets). ``drive_parameters`` are further parameters set per
    drive (e.g. a built-in load ramp switched off), ``tolerance_parameter`` receives the solver's
    relative tolerance, ``fixed_parameters`` are set in every run, and ``parameter_names`` maps a
    fitted parameter (``c_y``, ``gap``, …, see :mod:`fmusa.diagnose.effects`) to its FMU variable
    where the two differ. ``scale_variables`` names the parameters whose start values give the FMU's
    scale for the units check (:mod:`fmusa.diagnose.units`: ``stiffness`` [N/m], ``length`` [m],
    ``resolution`` [m], ``force`` [N]); a quantity left out is not checked.
    """
    mode_variable: str
    mode_values: Mapping[str, int]
    displacement_input: str
    follow_input: str | None
    force_input: str
    force_output: str
    displacement_output: str
    drive_parameters: Mapping[str, Mapping[str, Value]] = field(default_factory=dict)
    tolerance_parameter: str | None = None
    fixed_parameters: Mapping[str, Value] = field(default_factory=dict)
    parameter_names: Mapping[str, str] = field(default_factory=dict)
    scale_variables: Mapping[str, str] = field(default_factory=dict)

    def check_drive(self, drive: str) -> None:
        """Refuse a drive this interface cannot impose, naming the ones it can."""
        if drive not in DRIVES or drive not in self.mode_values:
            raise DiagnoseError(f"--drive {drive!r}: use 'force' or 'displacement'")

    def input_name(self, drive: str) -> str:
        """The FMU input the measured drive is fed into."""
        return self.displacement_input if drive == "displacement" else self.force_input

    def output_name(self, drive: str) -> str:
        """The FMU output compared with the measured response (the channel the drive does not impose)."""
        return self.force_output if drive == "displacement" else self.displacement_output

    def settings(self, drive: str, rtol: float) -> dict[str, Value]:
        """The fixed parameters of a driven run: mode, input switch, per-drive and common settings."""
        self.check_drive(drive)
        out: dict[str, Value] = {self.mode_variable: self.mode_values[drive]}
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


#: The ScrewVertebra FMU of this repository (modelica/ScrewVertebra.mo): mode 2 follows the input y_in (with
#: its derivative) when use_y_in is true; mode 1 applies F_ext_y on top of a ramp to F_max, set to 0.
SCREW_VERTEBRA = ModelInterface(
    mode_variable="mode",
    mode_values={"displacement": 2, "force": 1},
    displacement_input="y_in",
    follow_input="use_y_in",
    force_input="F_ext_y",
    force_output="F_meas",
    displacement_output="y_meas",
    drive_parameters={"force": {"F_max": 0.0}},
    tolerance_parameter="rtol",
    fixed_parameters={"monitors": False},
    scale_variables={"stiffness": "c_y", "length": "L_screw", "resolution": "smooth_w", "force": "F_max"},
)
