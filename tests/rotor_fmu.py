"""A rotational FMU that fmusa did not write as the user's model: an inertia J on a torsion spring k and a
torsional damper b, driven by a torque input ``tau``, with outputs the angle ``phi`` [rad] and the angular
velocity ``w`` [rad/s]:

    J phi'' = tau - k phi - b phi',   phi(0) = phi0, phi'(0) = 0

The binary is tests/fmus/cosim_body/body.c (a hand-written FMI 2.0 export that shares no code with fmusa: its
variables are value references only), compiled with fmi2GetFMUstate/fmi2SetFMUstate and the start values below, and exported, as
OpenModelica and Dymola export a model, for Model Exchange and for Co-Simulation (RK4 on fine fixed
sub-steps); the model description names its variables as a rotational Modelica model would
(``Rotational.Sources.Torque`` at ``tau``) and declares their units (rad, rad/s, N.m, kg.m2).
"""
from __future__ import annotations

from pathlib import Path

from c_fmus import compile_linux64, zip_tree

HERE = Path(__file__).resolve().parent
BODY = HERE / "fmus" / "cosim_body" / "body.c"

#: the export's start values: J [kg·m²], k [N·m/rad], b [N·m·s/rad]
J, K, B = 0.01, 20.0, 0.05


def rotor_description() -> str:
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="2.0" modelName="Rotor" guid="{{6d1e0f7a-2c3b-4e5f-9a8b-rotor00000001}}"
  description="Inertia on a torsion spring and damper, driven by a torque (a test fixture of fmusa)"
  generationTool="hand-written (tests/fmus/cosim_body, rotational names)" variableNamingConvention="structured"
  numberOfEventIndicators="0">
  <ModelExchange modelIdentifier="body" canNotUseMemoryManagementFunctions="true" completedIntegratorStepNotNeeded="true"/>
  <CoSimulation modelIdentifier="body" canHandleVariableCommunicationStepSize="true" canInterpolateInputs="true"
    canNotUseMemoryManagementFunctions="true" canGetAndSetFMUstate="true" canSerializeFMUstate="false"/>
  <UnitDefinitions>
    <Unit name="rad"/><Unit name="rad/s"><BaseUnit s="-1"/></Unit><Unit name="rad/s2"><BaseUnit s="-2"/></Unit>
    <Unit name="N.m"><BaseUnit kg="1" m="2" s="-2"/></Unit><Unit name="kg.m2"><BaseUnit kg="1" m="2"/></Unit>
    <Unit name="N.m/rad"><BaseUnit kg="1" m="2" s="-2"/></Unit><Unit name="N.m.s/rad"><BaseUnit kg="1" m="2" s="-1"/></Unit>
  </UnitDefinitions>
  <DefaultExperiment startTime="0" stopTime="3"/>
  <ModelVariables>
    <ScalarVariable name="inertia.J" valueReference="0" causality="parameter" variability="fixed" initial="exact"><Real unit="kg.m2" start="{J}"/></ScalarVariable>
    <ScalarVariable name="spring.c" valueReference="1" causality="parameter" variability="fixed" initial="exact"><Real unit="N.m/rad" start="{K}"/></ScalarVariable>
    <ScalarVariable name="damper.d" valueReference="2" causality="parameter" variability="fixed" initial="exact"><Real unit="N.m.s/rad" start="{B}"/></ScalarVariable>
    <ScalarVariable name="phi_start" valueReference="3" causality="parameter" variability="fixed" initial="exact"><Real unit="rad" start="0"/></ScalarVariable>
    <ScalarVariable name="tau" valueReference="4" causality="input" variability="continuous"><Real unit="N.m" start="0"/></ScalarVariable>
    <ScalarVariable name="phi" valueReference="5" causality="output" variability="continuous" initial="calculated"><Real unit="rad"/></ScalarVariable>
    <ScalarVariable name="w" valueReference="6" causality="output" variability="continuous" initial="calculated"><Real unit="rad/s" derivative="6"/></ScalarVariable>
    <ScalarVariable name="a" valueReference="7" causality="local" variability="continuous" initial="calculated"><Real unit="rad/s2" derivative="7"/></ScalarVariable>
  </ModelVariables>
  <ModelStructure>
    <Outputs><Unknown index="6"/><Unknown index="7"/></Outputs>
    <Derivatives><Unknown index="7"/><Unknown index="8"/></Derivatives>
    <InitialUnknowns><Unknown index="6"/><Unknown index="7"/><Unknown index="8"/></InitialUnknowns>
  </ModelStructure>
</fmiModelDescription>
"""


def build_rotor(root: Path) -> Path:
    """body.c built (with its FMU state) and zipped with the rotational description as root/Rotor.fmu."""
    tree = root / "tree"
    compile_linux64(BODY, tree / "binaries" / "linux64" / "body.so",
                    ("WITH_STATE", f"START_M={J!r}", f"START_K={K!r}", f"START_B={B!r}"), "rotor FMU")
    (tree / "modelDescription.xml").write_text(rotor_description(), encoding="utf-8")
    return zip_tree(tree, root / "Rotor.fmu")
