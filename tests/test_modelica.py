"""The generated modelDescription.xml and variables.h agree with an independent reading of the Modelica model.

fmu/generate.py derives the FMU's variable contract from the public declarations of
modelica/ScrewVertebra.mo (modelica-builder's ANTLR grammar, its own evaluator of the bindings, its own
rules). Here the same file is read a second way, with pymoca's parser and flattener (another grammar,
another tree, another evaluator), the mapping rules below are applied again, and every public variable
is compared with what the generator wrote: name and value reference (the 1-based declaration order,
arrays expanded), type, causality, variability, initial, unit, start value and description. A wrong rule
in the generator, or in its XML or C writer, fails here; the tests below also prove that the comparison
reports each kind of disagreement, and that the rules hold for declarations the model does not (yet) have.

Mapping rules (those of a Modelica tool exporting an FMU):

- ``parameter`` -> parameter (initial exact); ``final parameter`` with a binding -> calculatedParameter
  (initial calculated); both of variability fixed. ``input``/``output`` -> input/output, continuous for
  Real unless ``discrete``, discrete for Integer and Boolean. Anything else public (a plain variable, a
  constant) is not in the contract: it is read here as causality local, and the generator refuses it.
- The start value of a parameter is its binding (else its ``start``), that of an input its ``start``.
  The XML gives the others none; variables.h gives an output its ``start`` where declared, else 0.
- Entry k of an array ``a[n] "text"`` is the FMU variable ``a[k]`` with description ``"text k"``
  (``a[i,j]``, ``"text i,j"`` for a matrix).
"""
from __future__ import annotations

import itertools
import math
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import pytest
from pymoca import ast, parser, tree

import contract

ROOT = Path(__file__).resolve().parents[1]
MO_FILE = ROOT / "modelica" / "ScrewVertebra.mo"
MODEL = "ScrewVertebra"
# pymoca 0.12 keeps the type prefixes as the joined text of the grammar rule ("discreteoutput"): split it.
PREFIX_WORDS = re.compile(r"discrete|parameter|constant|input|output|flow|stream")
FUNCTIONS = {"sin": math.sin, "cos": math.cos, "tan": math.tan, "asin": math.asin, "acos": math.acos,
             "atan": math.atan, "atan2": math.atan2, "exp": math.exp, "log": math.log, "sqrt": math.sqrt,
             "abs": abs, "min": min, "max": max,
             "zeros": lambda *n: _filled(0, n), "ones": lambda *n: _filled(1, n), "fill": lambda v, *n: _filled(v, n)}
BINARY = {"+": lambda a, b: a + b, "-": lambda a, b: a - b, "*": lambda a, b: a * b, "/": lambda a, b: a / b,
          "^": lambda a, b: a ** b, "and": lambda a, b: a and b, "or": lambda a, b: a or b,
          "<": lambda a, b: a < b, "<=": lambda a, b: a <= b, ">": lambda a, b: a > b, ">=": lambda a, b: a >= b,
          "==": lambda a, b: a == b, "<>": lambda a, b: a != b}
CAUSALITY_KINDS = {"parameter": "CAUS_PARAMETER", "calculatedParameter": "CAUS_CALCULATED",
                   "input": "CAUS_INPUT", "output": "CAUS_OUTPUT", "local": "CAUS_LOCAL"}


@dataclass(frozen=True)
class Var:
    """One scalar variable: as the Modelica model declares it (read by pymoca), or as the XML has it."""
    vr: int
    name: str
    type: str
    causality: str
    variability: str
    initial: str | None
    unit: str | None
    start: bool | int | float | None     # in the XML's terms: parameters and inputs only
    description: str
    declared_start: bool | int | float | None = None   # any declared start (variables.h of an output)


# --------------------------------------------------------------------------------------------------
# The Modelica model read by pymoca


def _filled(value, dims):
    return value if not dims else [_filled(value, dims[1:]) for _ in range(int(dims[0]))]


def _none(node) -> bool:
    return node is None or isinstance(node, ast.Primary) and node.value is None


def value_of(node, env: dict[str, object]):
    """Value of a constant pymoca expression; names resolve to earlier public parameters."""
    if isinstance(node, ast.Primary):
        return node.value
    if isinstance(node, ast.Array):
        return [value_of(v, env) for v in node.values]
    if isinstance(node, ast.ComponentRef):
        if node.child or any(i is not None for group in node.indices for i in group) or node.name not in env:
            raise ValueError(f"{node} is not a known public parameter")
        return env[node.name]
    if isinstance(node, ast.IfExpression):
        for condition, expression in zip(node.conditions, node.expressions):
            if value_of(condition, env):
                return value_of(expression, env)
        return value_of(node.expressions[-1], env)
    if isinstance(node, ast.Expression):
        op = str(node.operator)
        args = [value_of(o, env) for o in node.operands]
        if op in BINARY and len(args) == 2:
            return BINARY[op](*args)
        if op == "-" and len(args) == 1:
            return -args[0]
        if op == "not" and len(args) == 1:
            return not args[0]
        if op in FUNCTIONS:
            return FUNCTIONS[op](*args)
    raise ValueError(f"cannot evaluate {node!r}")


def _entries(value, dims: list[int]) -> list:
    """Per array entry (row major); a scalar applies to every entry (``each``)."""
    if not dims:
        return [value]
    if not isinstance(value, list):
        return [value] * math.prod(dims)
    assert len(value) == dims[0], (value, dims)
    return [v for item in value for v in _entries(item, dims[1:])]


def pymoca_model(text: str, model: str = MODEL) -> tuple[str, list[Var]]:
    """(the model's description, its public scalar variables in declaration order), read by pymoca."""
    flat = tree.flatten(parser.parse(text), ast.ComponentRef(name=model))
    cls = flat.classes[model]
    env: dict[str, object] = {}
    out: list[Var] = []
    for symbol in cls.symbols.values():             # declaration order
        if symbol.visibility != ast.Visibility.PUBLIC:
            continue
        prefixes = PREFIX_WORDS.findall("".join(symbol.prefixes))
        type_name = str(symbol.type)
        binding = None if _none(symbol.value) else symbol.value
        start = None if _none(symbol.start) else symbol.start
        if "parameter" in prefixes:
            calculated = symbol.final and binding is not None
            causality, initial = ("calculatedParameter", "calculated") if calculated else ("parameter", "exact")
            variability = "fixed"
        elif "input" in prefixes or "output" in prefixes:
            causality = "input" if "input" in prefixes else "output"
            variability = "continuous" if type_name == "Real" and "discrete" not in prefixes else "discrete"
            initial = None
        else:
            causality, variability, initial = "local", "constant" if "constant" in prefixes else "continuous", None
        dims = [int(value_of(d, env)) for group in symbol.dimensions for d in group if not _none(d)]
        if "parameter" in prefixes and binding is not None:
            env[symbol.name] = value_of(binding, env)
        xml_start = (binding if binding is not None else start) if causality == "parameter" \
            else start if causality == "input" else None
        n = math.prod(dims) if dims else 1
        xml_starts = _entries(value_of(xml_start, env), dims) if xml_start is not None else [None] * n
        declared = _entries(value_of(start, env), dims) if start is not None else [None] * n
        units = _entries(value_of(symbol.unit, env), dims) if not _none(symbol.unit) else [None] * n
        indices = [",".join(map(str, i)) for i in itertools.product(*(range(1, k + 1) for k in dims))]
        for k, index in enumerate(indices):
            out.append(Var(vr=len(out) + 1, name=f"{symbol.name}[{index}]" if dims else symbol.name,
                           type=type_name, causality=causality, variability=variability, initial=initial,
                           unit=units[k], start=xml_starts[k],
                           description=f"{symbol.comment} {index}" if dims else symbol.comment,
                           declared_start=declared[k]))
    return cls.comment, out


# --------------------------------------------------------------------------------------------------
# What the generator wrote


def xml_model(text: str) -> tuple[ET.Element, list[Var]]:
    """(the root element, the ScalarVariables in document order) of a modelDescription.xml."""
    root = ET.fromstring(text)
    out = []
    for sv in root.iter("ScalarVariable"):
        typed = next(iter(sv))
        start = typed.get("start")
        if start is not None:
            parse = {"Real": float, "Integer": int, "Boolean": {"true": True, "false": False}.__getitem__}
            start = parse[typed.tag](start)
        out.append(Var(vr=int(sv.get("valueReference")), name=sv.get("name"), type=typed.tag,
                       causality=sv.get("causality", "local"), variability=sv.get("variability", "continuous"),
                       initial=sv.get("initial"), unit=typed.get("unit"), start=start,
                       description=sv.get("description", "")))
    return root, out


def _same(a, b) -> bool:
    """Equal and of the same kind (True is not 1; an Integer start is an int)."""
    if isinstance(a, bool) or isinstance(b, bool) or a is None or b is None:
        return a is b
    return type(a) is type(b) and a == b if isinstance(a, int) and isinstance(b, int) else float(a) == float(b)


def compare(modelica: list[Var], xml: list[Var]) -> list[str]:
    """Every disagreement, one message each (empty: they agree)."""
    mo, gen = {v.name: v for v in modelica}, {v.name: v for v in xml}
    problems = [f"{n}: only in Modelica ({mo[n].causality})" for n in mo if n not in gen]
    problems += [f"{n}: only in the XML ({gen[n].causality})" for n in gen if n not in mo]
    common = [n for n in mo if n in gen]
    if [n for n in gen if n in mo] != common:
        problems.append("the XML lists the variables in another order than the Modelica declarations")
    for name in common:
        a, b = mo[name], gen[name]
        for what in ("vr", "type", "causality", "variability", "initial", "unit", "description"):
            if getattr(a, what) != getattr(b, what):
                problems.append(f"{name}: {what} differs: Modelica {getattr(a, what)!r}, XML {getattr(b, what)!r}")
        start = float(a.start) if a.type == "Real" and isinstance(a.start, int) and not isinstance(a.start, bool) \
            else a.start
        if a.type == b.type and not _same(start, b.start):
            problems.append(f"{name}: start differs: Modelica {start!r}, XML {b.start!r}")
    return problems


def compare_header(modelica: list[Var], header: str, guid: str) -> list[str]:
    """Every disagreement of variables.h with the Modelica reading (and with the XML's GUID)."""
    problems = []
    if f'#define MODEL_GUID "{guid}"' not in header:
        problems.append("MODEL_GUID is not the XML's guid")
    if f"#define N_VR {len(modelica) + 1}\n" not in header:
        problems.append("N_VR is not the number of variables + 1")
    defines = {m[1]: int(m[2]) for m in re.finditer(r"^#define VR_(\w+) (\d+)$", header, flags=re.M)}
    rows = re.findall(r'^    X\("([^"]+)", (\d+), TYPE_(\w+), (CAUS_\w+), ([^)]+)\) \\$', header, flags=re.M)
    if [r[0] for r in rows] != [v.name for v in modelica]:
        problems.append("the X table does not list the Modelica variables in declaration order")
    expected_defines = {re.sub(r"\W", "_", v.name).rstrip("_"): v.vr for v in modelica}
    if defines != expected_defines:
        problems.append(f"VR_ defines differ: {sorted(set(defines.items()) ^ set(expected_defines.items()))}")
    by_name = {v.name: v for v in modelica}
    for name, vr, type_name, kind, start in rows:
        v = by_name.get(name)
        if v is None:
            continue
        value = v.start if v.causality in ("parameter", "input") else \
            v.declared_start if v.causality == "output" else None
        got = (int(vr), type_name, kind, float(start))
        want = (v.vr, v.type.upper(), CAUSALITY_KINDS.get(v.causality), float(value or 0))
        if got != want:
            problems.append(f"{name}: variables.h has {got}, the Modelica model says {want}")
    return problems


# --------------------------------------------------------------------------------------------------
# Fixtures


@pytest.fixture(scope="module")
def mo_text() -> str:
    return MO_FILE.read_text(encoding="utf-8")


@pytest.fixture(scope="module")
def generated(tmp_path_factory) -> tuple[str, str]:
    """(modelDescription.xml, variables.h) as the build makes them: fmu/generate.py run as a script."""
    out = tmp_path_factory.mktemp("fmu")
    subprocess.run([sys.executable, str(contract.GENERATE), str(out)], check=True, cwd=ROOT)
    return (out / "modelDescription.xml").read_text(encoding="utf-8"), \
        (out / "sources" / "variables.h").read_text(encoding="utf-8")


def with_sensitivities(modelica: list[Var], model: str = MODEL) -> list[Var]:
    """The model's variables and after them those of its forward sensitivities, as the generator's
    SENSITIVITIES states them (k = 1..K): Integer parameters sens_p[k] (start 0), then per named output the Real
    outputs sens_<output>[k], then their tolerance sens_rtol (start 0), value references continuing the model's."""
    facts = contract.generator().SENSITIVITIES.get(model)
    units = {v.name: v.unit for v in modelica}
    if not facts or not any(name in units for name in facts["outputs"]):
        return modelica
    out = list(modelica)
    k_max = facts["parameters"]
    for k in range(1, k_max + 1):
        out.append(Var(vr=len(out) + 1, name=f"sens_p[{k}]", type="Integer", causality="parameter",
                       variability="fixed", initial="exact", unit=None, start=0, declared_start=0,
                       description=f"Forward sensitivity {k}: the value reference of the Real parameter to "
                                   f"differentiate the outputs sens_<output>[{k}] by (0: none; every one 0 costs "
                                   f"nothing)"))
    for name in facts["outputs"]:
        for k in range(1, k_max + 1):
            out.append(Var(vr=len(out) + 1, name=f"sens_{name}[{k}]", type="Real", causality="output",
                           variability="continuous", initial=None, unit=None, start=None,
                           description=f"Forward sensitivity of {name} by the parameter sens_p[{k}] selects: d {name} "
                                       f"/ d parameter, in {units[name] or '1'} per the parameter's unit (0 when "
                                       f"sens_p[{k}] = 0)"))
    out.append(Var(vr=len(out) + 1, name="sens_rtol", type="Real", causality="parameter", variability="fixed",
                   initial="exact", unit=None, start=0, declared_start=0,
                   description="Relative local error tolerance of the forward sensitivities (0: rtol); a "
                               "least-squares Jacobian needs a few digits, not the states' accuracy"))
    return out


@pytest.fixture(scope="module")
def mo_vars(mo_text) -> list[Var]:
    return with_sensitivities(pymoca_model(mo_text)[1])


def generate(text: str) -> tuple[str, str]:
    """(modelDescription.xml, variables.h) that fmu/generate.py makes from a Modelica text."""
    g = contract.generator()
    model = g.parse_model(text)
    guid = g.guid(model)
    return g.model_description(model, guid), g.c_header(model, guid)


def agreement(text: str, xml: str, header: str) -> list[str]:
    """Every disagreement of the generated files with pymoca's reading of the Modelica text."""
    description, modelica = pymoca_model(text)
    modelica = with_sensitivities(modelica)
    root, xml_vars = xml_model(xml)
    problems = compare(modelica, xml_vars)
    if root.get("description") != description:
        problems.append(f"model description differs: Modelica {description!r}, XML {root.get('description')!r}")
    problems += compare_header(modelica, header, root.get("guid"))
    return problems


# --------------------------------------------------------------------------------------------------
# The shipped model


def test_generated_files_agree_with_pymocas_reading(mo_text, generated, mo_vars):
    names = [v.name for v in mo_vars]
    assert {"m", "I_1", "phi_inertia", "tab_y[16]", "F_ext_x", "y", "n_steps", "dmg_D"} <= set(names)  # not vacuous
    assert {v.causality for v in mo_vars} == {"parameter", "calculatedParameter", "input", "output"}
    problems = agreement(mo_text, *generated)
    assert not problems, "fmu/generate.py's output disagrees with pymoca's reading:\n" + "\n".join(problems)


def test_model_structure_lists_the_outputs_and_initial_unknowns(generated, mo_vars):
    root = ET.fromstring(generated[0])
    outputs = [int(u.get("index")) for u in root.find("ModelStructure/Outputs")]
    initial = [int(u.get("index")) for u in root.find("ModelStructure/InitialUnknowns")]
    assert outputs == [v.vr for v in mo_vars if v.causality == "output"]
    assert initial == [v.vr for v in mo_vars if v.causality in ("output", "calculatedParameter")]


def test_expression_bindings_are_evaluated(generated):
    _, xml_vars = xml_model(generated[0])
    start = {v.name: v.start for v in xml_vars}
    assert start["phi_inertia"] == math.atan2(0.28, 0.96)
    assert start["v_pull"] == 2e-3 / 60
    assert 'name="phi_inertia"' in generated[0] and 'start="0.28379410920832787"' in generated[0]


def test_calculated_inertia_is_the_solid_cylinder(mo_text):
    """The bindings of I_1..I_3, evaluated by pymoca's tree: the moments MODEL.md states."""
    cls = tree.flatten(parser.parse(mo_text), ast.ComponentRef(name=MODEL)).classes[MODEL]
    env: dict[str, object] = {}
    for symbol in cls.symbols.values():
        if symbol.visibility == ast.Visibility.PUBLIC and "parameter" in symbol.prefixes and not _none(symbol.value):
            env[symbol.name] = value_of(symbol.value, env)
    r, length, m = env["D_screw"] / 2, env["L_screw"], env["m"]
    assert math.isclose(env["I_1"], m * (3 * r**2 + length**2) / 12, rel_tol=1e-14)
    assert math.isclose(env["I_3"], env["I_1"], rel_tol=1e-14)
    assert math.isclose(env["I_2"], m * r**2 / 2, rel_tol=1e-14)
    assert math.isclose(math.cos(env["phi_inertia"]), 0.96, rel_tol=1e-14)
    assert math.isclose(math.sin(env["phi_inertia"]), 0.28, rel_tol=1e-14)


# --------------------------------------------------------------------------------------------------
# The comparison reports every kind of disagreement


def _edit_variable(xml: str, name: str, old: str, new: str) -> str:
    block = re.search(rf'    <ScalarVariable name="{re.escape(name)}" .*?</ScalarVariable>\n', xml, flags=re.S)
    assert block is not None and block.group(0).count(old) == 1, (name, old)
    return xml.replace(block.group(0), block.group(0).replace(old, new))


@pytest.mark.parametrize("name, old, new, expected", [
    ("d_x", 'unit="N.s/m"', 'unit="N.m/s"', ["d_x: unit differs: Modelica 'N.s/m', XML 'N.m/s'"]),
    ("y_in", 'causality="input"', 'causality="output"', ["y_in: causality differs: Modelica 'input', XML 'output'"]),
    ("c_beta", 'start="1"', 'start="1.5"', ["c_beta: start differs: Modelica 1.0, XML 1.5"]),
    ("unload", 'start="false"', 'start="true"', ["unload: start differs: Modelica False, XML True"]),
    ("w_beta", '"Rate of beta"', '"Rate of Beta"',
     ["w_beta: description differs: Modelica 'Rate of beta', XML 'Rate of Beta'"]),
    ("n_steps", 'variability="discrete"', 'variability="continuous"',
     ["n_steps: variability differs: Modelica 'discrete', XML 'continuous'"]),
    ("I_2", 'initial="calculated"', 'initial="exact"', ["I_2: initial differs: Modelica 'calculated', XML 'exact'"]),
    ("mode", "<Integer ", "<Real ", ["mode: type differs: Modelica 'Integer', XML 'Real'"]),
    ("F_ext_y", 'unit="N" ', "", ["F_ext_y: unit differs: Modelica 'N', XML None"]),
])
def test_comparison_reports_a_wrong_xml(mo_text, generated, name, old, new, expected):
    assert agreement(mo_text, _edit_variable(generated[0], name, old, new), generated[1]) == expected


def test_comparison_reports_a_missing_variable_and_a_wrong_value_reference(mo_text, generated, mo_vars):
    xml, header = generated
    block = re.search(r'    <ScalarVariable name="tab_F\[16\]" .*?</ScalarVariable>\n', xml, flags=re.S).group(0)
    assert agreement(mo_text, xml.replace(block, ""), header) == ["tab_F[16]: only in Modelica (parameter)"]
    vr = {v.name: v.vr for v in mo_vars}
    wrong = _edit_variable(xml, "y", f'valueReference="{vr["y"]}"', f'valueReference="{vr["x"]}"')
    assert agreement(mo_text, wrong, header) == [f"y: vr differs: Modelica {vr['y']}, XML {vr['x']}"]


def test_comparison_reports_a_wrong_header(mo_text, generated, mo_vars):
    xml, header = generated
    vr = {v.name: v.vr for v in mo_vars}
    wrong = header.replace(f'    X("c_y", {vr["c_y"]}, TYPE_REAL, CAUS_PARAMETER, 823224)',
                           f'    X("c_y", {vr["c_y"]}, TYPE_REAL, CAUS_PARAMETER, 823225)')
    assert wrong != header
    assert agreement(mo_text, xml, wrong) == [
        f"c_y: variables.h has ({vr['c_y']}, 'REAL', 'CAUS_PARAMETER', 823225.0), "
        f"the Modelica model says ({vr['c_y']}, 'REAL', 'CAUS_PARAMETER', 823224.0)"]
    wrong = header.replace(f"#define VR_y {vr['y']}\n", f"#define VR_y {vr['x']}\n")
    assert agreement(mo_text, xml, wrong) == [f"VR_ defines differ: [('y', {vr['x']}), ('y', {vr['y']})]"]


# --------------------------------------------------------------------------------------------------
# The rules on declarations the shipped model does not have


def _insert_public(text: str, declarations: str) -> str:
    """The declarations appended to the leading public section (before 'protected')."""
    assert text.count("\nprotected\n") == 1
    return text.replace("\nprotected\n", "\n" + declarations + "\nprotected\n")


def _before_sections(text: str, insert: str) -> str:
    """``insert`` placed before the first equation or algorithm section of the model (not of a function
    before it in the file)."""
    start = text.index("\nmodel ScrewVertebra")
    m = re.compile(r"^(initial )?(equation|algorithm)$", flags=re.M).search(text, start)
    assert m is not None
    return text[:m.start()] + insert + text[m.start():]


@pytest.mark.parametrize("declarations, expected", [
    ('  discrete output Real d_out(unit="m", start=2) "Discrete output";', {"d_out": ("output", "discrete")}),
    ('  output Boolean b_out "Boolean output";\n  output Integer i_out(start=-4) "Integer output";',
     {"b_out": ("output", "discrete"), "i_out": ("output", "discrete")}),
    ('  input Integer i_in(start=3) "Integer input";\n  input Boolean b_in(start=true) "Boolean input";',
     {"i_in": ("input", "discrete"), "b_in": ("input", "discrete")}),
    ('  parameter Real tab2[2, 3](each unit="m") = {{1, 2, 3}, {4, 5, 6.5}} "Two-dimensional table";',
     {"tab2[1,1]": ("parameter", "fixed"), "tab2[2,3]": ("parameter", "fixed")}),
    ('  parameter Real tab3[2](unit={"m", "s"}, start={0.5, 7}) "Array without binding";',
     {"tab3[1]": ("parameter", "fixed"), "tab3[2]": ("parameter", "fixed")}),
    ('  final parameter Real k2(unit="N/m") = 2*c_y + 0.5 "Twice c_y";', {"k2": ("calculatedParameter", "fixed")}),
    ('  final parameter Real k3(unit="N/m", start=4) "Final without binding";', {"k3": ("parameter", "fixed")}),
    ('  parameter Real ang(unit="rad") = if 1 > 2 then 0 else atan2(1, 2) - cos(0.5)^2 "An expression";\n'
     '  parameter Integer n2 = 2*3 - 1 "Integer expression";\n'
     '  parameter Boolean flag = not false and true "Boolean expression";',
     {"ang": ("parameter", "fixed"), "n2": ("parameter", "fixed"), "flag": ("parameter", "fixed")}),
])
def test_rules_hold_beyond_the_shipped_declarations(mo_text, declarations, expected):
    text = _insert_public(mo_text, declarations)
    xml, header = generate(text)
    _, xml_vars = xml_model(xml)
    got = {v.name: (v.causality, v.variability) for v in xml_vars}
    assert {n: got.get(n) for n in expected} == expected
    problems = agreement(text, xml, header)
    assert not problems, "\n".join(problems)


def test_a_public_section_after_the_protected_one_counts(mo_text):
    text = _before_sections(mo_text, 'public\n  parameter Real late(unit="s") = 1e3 "After protected";\n\n')
    xml, header = generate(text)
    names = [v.name for v in xml_model(xml)[1] if not v.name.startswith("sens_")]   # the sensitivities come last
    assert names[-1] == "late"
    assert agreement(text, xml, header) == []


def test_generator_ignores_protected_declarations_functions_and_equations(mo_text, generated):
    text = mo_text.replace("\nprotected\n", '\nprotected\n  input Real spare_in(unit="furlong", start=1) "Internal";\n'
                           '  parameter Real spare_p = 2 "Internal";\n  output Real spare_out "Internal";\n'
                           '  function spare_f\n    input Real u;\n    output Real v;\n  algorithm\n'
                           '    v := u;\n  end spare_f;\n', 1)
    text = _before_sections(text, "algorithm\n  spare_out := spare_f(spare_p);\n")
    text = text.replace("\nequation\n", "\nequation\n  spare_in = time;\n", 1)
    xml, header = generate(text)
    g = contract.generator()
    # the same variables and GUID: the XML and the header are those of the shipped model
    assert (xml, header) == generated
    assert g.guid(g.parse_model(text)) == g.guid(g.parse_model(mo_text))


def test_generator_refuses_public_variables_outside_the_contract(mo_text):
    g = contract.generator()
    for declaration in ('  Real spare "A plain variable";', '  constant Real spare = 1 "A constant";'):
        text = _insert_public(mo_text, declaration)
        with pytest.raises(g.ModelicaError, match="spare: not a parameter, input or output"):
            g.parse_model(text)
        # and pymoca's reading has it outside the FMU's causalities, so the comparison would report it
        assert next(v for v in pymoca_model(text)[1] if v.name == "spare").causality == "local"
    with pytest.raises(g.ModelicaError, match="unit 'furlong' is not in UNITS"):
        g.parse_model(_insert_public(mo_text, '  parameter Real spare(unit="furlong") = 1 "Unknown unit";'))
    with pytest.raises(g.ModelicaError, match="spare: the input needs a start value"):
        g.parse_model(_insert_public(mo_text, '  input Real spare "No start";'))
    with pytest.raises(g.ModelicaError, match=r"spare: attributes \['min'\] are not carried"):
        g.parse_model(_insert_public(mo_text, '  parameter Real spare(min=0) = 1 "A minimum";'))


def test_syntax_error_fails(mo_text):
    g = contract.generator()
    with pytest.raises(g.ModelicaError, match="syntax error"):
        g.parse_modelica(mo_text.replace('"Mass of the screw (Table 1)";', '"Mass of the screw (Table 1)"', 1))
    with pytest.raises(g.ModelicaError, match="syntax error"):
        g.parse_modelica(mo_text + "\nmodel Trailing\n")


def test_generator_script_fails_naming_the_file(mo_text, tmp_path):
    bad = tmp_path / "Bad.mo"
    bad.write_text(_insert_public(mo_text, '  Real spare "A plain variable";'), encoding="utf-8")
    proc = subprocess.run([sys.executable, str(contract.GENERATE), str(tmp_path / "out"), str(bad)],
                          capture_output=True, text=True)
    assert proc.returncode != 0 and f"{bad}: public Real spare: not a parameter" in proc.stderr
    assert not (tmp_path / "out").exists()


def test_pymoca_reading_keeps_the_declared_output_start():
    """t_eq's -1 while not at rest: model.c sets it; variables.h gives an output its start only where declared."""
    text = f"model {MODEL}\n  output Real t(unit=\"s\", start=-1) \"A monitor\";\nequation\n  t = -1;\nend {MODEL};\n"
    xml, header = generate(text)
    assert agreement(text, xml, header) == []
    assert '    X("t", 1, TYPE_REAL, CAUS_OUTPUT, -1) \\' in header and "start=" not in xml.split("<ModelVariables>")[1]


# --------------------------------------------------------------------------------------------------
# The interface element: the same generator on modelica/InterfaceElement.mo, with model exchange

ELEMENT_MO = ROOT / "modelica" / "InterfaceElement.mo"


def test_element_generated_files_agree_with_pymocas_reading(tmp_path):
    """The element's modelDescription.xml and variables.h against pymoca's reading of its Modelica file; the
    model exchange part: one der(x) variable per state (the public outputs whose der() the equations use, in
    declaration order), each with derivative= pointing at its state, listed under <Derivatives> in that order."""
    subprocess.run([sys.executable, str(ROOT / "fmu" / "generate.py"), str(tmp_path), str(ELEMENT_MO)], check=True)
    xml = (tmp_path / "modelDescription.xml").read_text(encoding="utf-8")
    header = (tmp_path / "sources" / "variables.h").read_text(encoding="utf-8")
    text = ELEMENT_MO.read_text(encoding="utf-8")
    description, modelica = pymoca_model(text, "InterfaceElement")
    root, variables = xml_model(xml)
    assert root.get("modelName") == "InterfaceElement" and root.get("description") == description
    public = [v for v in variables if not v.name.startswith("der(")]
    assert compare(modelica, public) == []
    states = [n for n in ("z_y", "z_f", "F_ve", "kappa")]
    flat = tree.flatten(parser.parse(text), ast.ComponentRef(name="InterfaceElement")).classes["InterfaceElement"]
    der_used: set[str] = set()

    def walk(node) -> None:
        if isinstance(node, ast.Expression) and getattr(node.operator, "name", node.operator) == "der":
            der_used.add(node.operands[0].name)
        if isinstance(node, ast.Node):
            for k, v in vars(node).items():
                if k not in ("parent", "scope"):
                    walk(v)
        elif isinstance(node, (list, tuple)):
            for v in node:
                walk(v)

    walk(flat.equations)
    assert der_used == set(states)
    by_name = {v.name: v.vr for v in variables}
    der_rows = [sv for sv in root.iter("ScalarVariable") if sv.get("name").startswith("der(")]
    assert [sv.get("name") for sv in der_rows] == [f"der({s})" for s in states]
    for sv, s in zip(der_rows, states):
        assert next(iter(sv)).get("derivative") == str(by_name[s]) and sv.get("causality") == "local"
    derivs = [int(u.get("index")) for u in root.find("ModelStructure/Derivatives")]
    assert derivs == [by_name[f"der({s})"] for s in states]
    assert root.find("ModelExchange") is not None and root.find("CoSimulation") is not None
    assert root.find("CoSimulation").get("canGetAndSetFMUstate") == "true"
    guid = root.get("guid")
    header_vars = [v for v in modelica]
    problems = compare_header(header_vars + [Var(vr=len(modelica) + i + 1, name=f"der({s})", type="Real",
                                                 causality="local", variability="continuous", initial=None,
                                                 unit=None, start=None, description="", declared_start=None)
                                             for i, s in enumerate(states)], header, guid)
    assert problems == []
