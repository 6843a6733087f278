"""The coupled system as an SSP 1.0 archive that other tools run (FMPy, libcosim, OMSimulator, Simpack…).

The archive holds SystemStructure.ssd (SSP 1.0: the system with the model and the element as components, their
connectors, the three connections of the interface with the signs as linear transformations, the default
experiment), both FMUs under resources/, and each component's parameter values as an SSV file bound to it
(resources/<component>.ssv). The drive of a test is not part of the system: a tool running the archive applies
its own (or the model's built-in load case). The SSD is checked against the SSP 1.0 schema that FMPy ships.
"""
from __future__ import annotations

import math
import shutil
import zipfile
from pathlib import Path
from xml.sax.saxutils import quoteattr

from fmusa.cosim.master import ELEMENT_F, ELEMENT_S, ELEMENT_V, Coupling, CouplingError, checked_coupling

NS_SSD = "http://ssp-standard.org/SSP1/SystemStructureDescription"
NS_SSC = "http://ssp-standard.org/SSP1/SystemStructureCommon"
NS_SSV = "http://ssp-standard.org/SSP1/SystemStructureParameterValues"
FMU_TYPE = "application/x-fmu-sharedlibrary"
MODEL, ELEMENT = "model", "element"


def _number(x: float) -> str:
    if not math.isfinite(float(x)):
        raise CouplingError(f"parameter value {x!r} is not finite: an SSP archive carries finite numbers only")
    return repr(float(x))


def parameter_values(name: str, values: dict[str, float], types: dict[str, str]) -> str:
    """An SSV file: the parameter values of one component."""
    rows = []
    for k, x in values.items():
        t = types.get(k, "Real")
        if t == "Boolean":
            rows.append(f'    <ssv:Parameter name={quoteattr(k)}><ssv:Boolean value="{"true" if x else "false"}"/>'
                        f'</ssv:Parameter>')
        elif t in ("Integer", "Enumeration"):
            rows.append(f'    <ssv:Parameter name={quoteattr(k)}><ssv:Integer value="{int(x)}"/></ssv:Parameter>')
        else:
            rows.append(f'    <ssv:Parameter name={quoteattr(k)}><ssv:Real value="{_number(x)}"/></ssv:Parameter>')
    return (f'<?xml version="1.0" encoding="UTF-8"?>\n'
            f'<ssv:ParameterSet xmlns:ssv="{NS_SSV}" xmlns:ssc="{NS_SSC}" version="1.0" name={quoteattr(name)}>\n'
            f'  <ssv:Parameters>\n' + "\n".join(rows) + '\n  </ssv:Parameters>\n</ssv:ParameterSet>\n')


def _connector(name: str, kind: str) -> str:
    return f'          <ssd:Connector name={quoteattr(name)} kind="{kind}"><ssc:Real/></ssd:Connector>'


def _connection(start: tuple[str, str], end: tuple[str, str], factor: float) -> str:
    inner = "" if factor == 1.0 else f'\n        <ssc:LinearTransformation factor="{_number(factor)}" offset="0"/>\n      '
    return (f'      <ssd:Connection startElement="{start[0]}" startConnector={quoteattr(start[1])} '
            f'endElement="{end[0]}" endConnector={quoteattr(end[1])}>{inner}</ssd:Connection>')


def system_structure(coupling: Coupling, model_source: str, element_source: str, stop_time: float,
                     name: str = "CoupledSystem") -> str:
    """SystemStructure.ssd of the coupled system."""
    c = coupling
    model = [_connector(c.force_input, "input"), _connector(c.displacement_output, "output"),
             _connector(c.velocity_output, "output")]   # an output, or a state the tool exported
    element = [_connector(ELEMENT_S, "input"), _connector(ELEMENT_V, "input"), _connector(ELEMENT_F, "output")]
    connections = [_connection((MODEL, c.displacement_output), (ELEMENT, ELEMENT_S), 1.0),
                   _connection((MODEL, c.velocity_output), (ELEMENT, ELEMENT_V), c.velocity_sign),
                   _connection((ELEMENT, ELEMENT_F), (MODEL, c.force_input), c.force_sign)]

    def component(cname: str, source: str, connectors: list[str]) -> str:
        return (f'      <ssd:Component name="{cname}" type="{FMU_TYPE}" source={quoteattr(source)}>\n'
                f'        <ssd:Connectors>\n' + "\n".join(connectors) + '\n        </ssd:Connectors>\n'
                f'        <ssd:ParameterBindings>\n'
                f'          <ssd:ParameterBinding type="application/x-ssp-parameter-set" '
                f'source="resources/{cname}.ssv"/>\n'
                f'        </ssd:ParameterBindings>\n      </ssd:Component>')

    return (f'<?xml version="1.0" encoding="UTF-8"?>\n'
            f'<ssd:SystemStructureDescription xmlns:ssd="{NS_SSD}" xmlns:ssc="{NS_SSC}" xmlns:ssv="{NS_SSV}"\n'
            f'  version="1.0" name={quoteattr(name)} generationTool="fmusa">\n'
            f'  <ssd:System name={quoteattr(name)} description="A model coupled with fmusa\'s interface element: '
            f'the model gives the interface motion, the element the force">\n'
            f'    <ssd:Elements>\n'
            f'{component(MODEL, model_source, model)}\n{component(ELEMENT, element_source, element)}\n'
            f'    </ssd:Elements>\n'
            f'    <ssd:Connections>\n' + "\n".join(connections) + '\n    </ssd:Connections>\n'
            f'  </ssd:System>\n'
            f'  <ssd:DefaultExperiment startTime="0" stopTime="{_number(stop_time)}"/>\n'
            f'</ssd:SystemStructureDescription>\n')


def validate_ssd(text: str, schema_file: str = "SystemStructureDescription.xsd") -> list[str]:
    """Problems of an SSD (or, with the SSV schema, an SSV) against the SSP 1.0 schema FMPy ships; empty when
    it is valid."""
    import os

    import fmpy.ssp
    from lxml import etree
    schema_dir = os.path.join(os.path.dirname(fmpy.ssp.__file__), "schema")
    schema = etree.XMLSchema(file=os.path.join(schema_dir, schema_file))
    root = etree.fromstring(text.encode("utf-8"))
    if schema.validate(root):
        return []
    return [f"line {e.line}: {e.message}" for e in schema.error_log]


def write_ssp(path: str | Path, coupling: Coupling, model_params: dict[str, float],
              element_params: dict[str, float], stop_time: float, name: str = "CoupledSystem") -> Path:
    """Write the coupled system with these parameter values as an SSP 1.0 archive at ``path``. Raises
    :class:`CouplingError` when the coupling does not check or the SSD does not validate."""
    minfo, einfo, _ = checked_coupling(coupling)
    for name in (coupling.displacement_output, coupling.velocity_output):
        v = minfo.variable(name)
        if v is None or v.causality != "output":
            raise CouplingError(f"{minfo.model_name}: {name!r} is not an output, and an SSP connection starts at an "
                                f"output; export the interface's displacement and rate as outputs of the model")
    path = Path(path)
    model_source = f"resources/{Path(coupling.model_fmu).name}"
    element_source = f"resources/{coupling.element().name}"
    if model_source == element_source:
        raise CouplingError(f"the model FMU and the element FMU are both named {Path(model_source).name}; rename one")
    ssd = system_structure(coupling, model_source, element_source, stop_time, name)
    problems = validate_ssd(ssd)
    if problems:
        raise CouplingError("the SystemStructure.ssd fmusa wrote does not validate against SSP 1.0: "
                            + "; ".join(problems[:5]))
    types_m = {x.name: x.type for x in minfo.variables}
    types_e = {x.name: x.type for x in einfo.variables}
    ssv = {MODEL: parameter_values(MODEL, model_params, types_m),
           ELEMENT: parameter_values(ELEMENT, element_params, types_e)}
    for cname, text in ssv.items():
        problems = validate_ssd(text, "SystemStructureParameterValues.xsd")
        if problems:
            raise CouplingError(f"the {cname}.ssv fmusa wrote does not validate against SSP 1.0: "
                                + "; ".join(problems[:5]))
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
        z.writestr("SystemStructure.ssd", ssd)
        z.write(coupling.model_fmu, model_source)
        z.write(coupling.element(), element_source)
        for cname, text in ssv.items():
            z.writestr(f"resources/{cname}.ssv", text)
    shutil.move(tmp, path)
    return path
