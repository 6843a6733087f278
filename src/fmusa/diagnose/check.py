"""The model description checked against the FMU before anything runs: every variable it names exists and
can play its part (the drive and the interface force are inputs, the response and the interface motion are
outputs, baseline and effect parameters can be set).

A diagnosis runs dozens of fits; a variable the FMU lacks must stop it at once, not after the first fits.
:func:`check_description` reads only the modelDescription.xml of each FMU and raises one
:class:`~fmusa.diagnose.effects.DiagnoseError` that lists every problem and how to export the model so that it
has what is missing (Simpack, Dymola, OpenModelica).
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

from fmusa.diagnose.effects import BASELINE, Scales, DiagnoseError, model_parameters
from fmusa.diagnose.interface import ModelInterface

__all__ = ["check_description", "description_problems", "EXPORT_HINTS"]

#: How to give an exported FMU what a diagnosis needs, per tool and per kind of variable.
EXPORT_HINTS = {
    "input": (
        "an FMU input is a top-level input connector of the exported model: in Dymola and OpenModelica add a "
        "RealInput at the top level (e.g. `Modelica.Blocks.Interfaces.RealInput f` connected to a "
        "Modelica.Mechanics.Translational.Sources.Force, or a Rotational.Sources.Torque for a torque) and export "
        "again (Dymola: Simulation > Translate > FMU; OpenModelica: File > Export > FMU, or "
        "buildModelFMU(Model, version=\"2.0\", fmuType=\"me_cs\")); in Simpack, define a u-input (Model Setup > "
        "Inputs) that drives a Force Element of type 93 (Input Force) or a prescribed motion, and list it as an "
        "input in the FMU export (File > Export > FMU)"),
    "output": (
        "an FMU output is a top-level output connector: in Dymola and OpenModelica add a RealOutput at the top "
        "level set from the quantity (e.g. `y = mass.s` through a Translational.Sensors.PositionSensor, a "
        "relative displacement through a RelPositionSensor and its velocity through a RelSpeedSensor); in "
        "Simpack, define a y-output (Model Setup > Outputs) of the sensor and list it in the FMU export"),
    "parameter": (
        "a settable FMU parameter is a top-level `parameter Real` of the exported model (Dymola and "
        "OpenModelica export top-level parameters; a parameter computed from others is a calculatedParameter and "
        "cannot be set — make the one it is computed from top level); in Simpack, a SubVar listed as a parameter "
        "in the FMU export"),
}


def _problem(info, name: str, role: str) -> str | None:
    """Why ``name`` cannot play ``role``: as :func:`fmusa.fmi.info.variable_problem`, an output must be declared
    one (causality output); ``state`` is a Real output or a state the tool exported (a local variable)."""
    from fmusa.fmi.info import variable_problem

    if role == "state":
        return variable_problem(info, name, "output")
    if role == "output":
        v = info.variable(name)
        if v is not None and (v.causality or "local") != "output":
            return (f"{name!r} is {'an' if (v.causality or 'local')[0] in 'aeiou' else 'a'} {v.causality or 'local'} "
                    f"variable, not an output")
    return variable_problem(info, name, role)


def description_problems(fmu_path: str | os.PathLike, interface: ModelInterface, drive: str,
                         candidates: Sequence[str]) -> list[tuple[str, str, str]]:
    """(what it is for, the problem, the kind of variable it needs) for every variable that cannot play its part."""
    from fmusa.fmi.info import read_fmu_info

    info = read_fmu_info(fmu_path)
    out: list[tuple[str, str, str]] = []

    def need(info_, name: str | None, role: str, what: str) -> None:
        if not name:
            return
        p = _problem(info_, name, role)
        if p:
            out.append((what, p, role))

    interface.check_drive(drive)
    need(info, interface.input_name(drive), "input", f"the {drive} drive")
    resp = "force" if drive == "displacement" else "displacement"
    need(info, interface.output_name(drive), "output", f"the measured {resp} (the response)")
    settings = interface.settings(drive, 1e-6)
    for name in settings:
        need(info, name, "parameter", f"a setting of the {drive} drive")
    sc = Scales(y_pk=1.0, F_pk=1.0, v_pk=1.0, c0=1.0, t_min=1.0, t_max=1.0, dt_min=0.1)
    names = dict.fromkeys(p.name for c in ("none", *candidates) for p in model_parameters(c, drive, sc))
    att = interface.attached
    if att is None:
        for n in names:
            role = "the baseline" if n in BASELINE else "a candidate effect"
            need(info, interface.variable(n), "parameter", f"{role} ({n})")
        return out
    need(info, att.force_input, "input", "the interface force of the attached element")
    need(info, att.displacement_output, "output", "the interface's relative displacement")
    need(info, att.velocity_output, "state", "the interface's relative velocity")
    if not Path(att.element_fmu).exists():
        out.append(("the interface element", f"{att.element_fmu} does not exist (build it with `make fmu`, or give "
                                             f"effects.element)", "file"))
        return out
    element = read_fmu_info(att.element_fmu)
    for n in names:
        var = interface.variable(n)
        target = element if element.variable(var) is not None or info.variable(var) is None else info
        need(target, var, "parameter", f"{'the baseline' if n in BASELINE else 'a candidate effect'} ({n})")
    return out


def check_description(fmu_path: str | os.PathLike, interface: ModelInterface, drive: str,
                      candidates: Sequence[str]) -> None:
    """Raise one DiagnoseError naming every variable the FMU lacks for this diagnosis and how to export it."""
    problems = description_problems(fmu_path, interface, drive, candidates)
    if not problems:
        return
    lines = [f"- for {what}: {p}" for what, p, _ in problems]
    kinds = dict.fromkeys(("output" if k == "state" else k) for _, _, k in problems)
    kinds = [k for k in kinds if k in EXPORT_HINTS]
    how = [f"How to export it: {EXPORT_HINTS[k]}." for k in kinds]
    raise DiagnoseError(
        f"{fmu_path}: the FMU does not have what the description of {interface.name} names; nothing was run:\n"
        + "\n".join(lines) + "\n" + "\n".join(how)
        + "\nOr describe this FMU's own variables in a diagnosis study file (model.drives, baseline, effects) "
          "and run `fmusa diagnose STUDY.yaml`.")
