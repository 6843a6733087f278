"""modelica/ScrewVertebra.mo declares exactly the FMU's public variables.

The Modelica source is parsed with a real Modelica grammar (the ANTLR parser of modelica-builder); any
syntax error fails. Its public component declarations are compared, variable by variable, with the
modelDescription.xml that fmu/generate.py derives from fmu/variables.csv: names (arrays expanded to
``tab_y[1]``...), type, causality, variability, unit, start value of parameters and inputs, and
description. Protected declarations are Modelica internals and are ignored.

Mapping rules (those of a Modelica tool exporting an FMU):
- ``parameter`` -> parameter; ``final parameter`` with a binding -> calculatedParameter (variability
  fixed); ``input``/``output`` -> input/output, continuous for Real unless ``discrete``, discrete for
  Integer and Boolean; anything else public (a plain variable, a constant) is not in the contract.
- The start value of a parameter is its binding (else its ``start``), that of an input its ``start``.
- Entry k of an array ``a[n] "text"`` is the FMU variable ``a[k]`` with description ``"text k"``.
"""
from __future__ import annotations

import itertools
import math
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from antlr4 import CommonTokenStream, InputStream, Token
from antlr4.error.ErrorListener import ErrorListener
from antlr4.tree.Tree import TerminalNode
from modelica_builder.modelica_parser import modelicaLexer, modelicaParser as P

ROOT = Path(__file__).resolve().parents[1]
MO_FILE = ROOT / "modelica" / "ScrewVertebra.mo"
GENERATE = ROOT / "fmu" / "generate.py"
MODEL_NAME = "ScrewVertebra"
TYPES = ("Real", "Integer", "Boolean")
# Type attributes compared besides unit and start whenever either side declares them.
EXTRA_ATTRIBUTES = ("quantity", "displayUnit", "min", "max", "nominal")


class ModelicaError(Exception):
    """A syntax error, or a construct this contract check cannot interpret."""


@dataclass
class Var:
    """One scalar variable, as declared in Modelica or in modelDescription.xml."""
    name: str
    type: str
    causality: str
    variability: str
    description: str
    unit: str | None = None
    start: float | int | bool | None = None
    attributes: dict[str, object] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------------
# Parsing


class _RaisingListener(ErrorListener):
    def __init__(self, source: str):
        super().__init__()
        self.source = source

    def syntaxError(self, recognizer, offendingSymbol, line, column, msg, e):  # noqa: N802 (ANTLR API)
        raise ModelicaError(f"{self.source}:{line}:{column}: syntax error: {msg}")


def parse_modelica(text: str, source: str = "<string>") -> P.Stored_definitionContext:
    """Parse tree of a Modelica file; raises ModelicaError on any lexer or parser error."""
    lexer = modelicaLexer(InputStream(text))
    lexer.removeErrorListeners()
    lexer.addErrorListener(_RaisingListener(source))
    parser = P(CommonTokenStream(lexer))
    parser.removeErrorListeners()
    parser.addErrorListener(_RaisingListener(source))
    tree = parser.stored_definition()
    # The grammar's start rule does not end in EOF: text it cannot continue with would be left over.
    token = parser.getCurrentToken()
    if token.type != Token.EOF:
        raise ModelicaError(f"{source}:{token.line}:{token.column}: syntax error: "
                            f"unexpected {token.text!r} after the last class definition")
    return tree


# --------------------------------------------------------------------------------------------------
# Constant expressions (bindings, modifiers, array sizes)

_ESCAPES = {"'": "'", '"': '"', "?": "?", "\\": "\\", "a": "\a", "b": "\b", "f": "\f", "n": "\n",
            "r": "\r", "t": "\t", "v": "\v"}
_FUNCTIONS = {
    "zeros": lambda *n: _filled(0, n), "ones": lambda *n: _filled(1, n), "fill": lambda v, *n: _filled(v, n),
    "sqrt": math.sqrt, "sin": math.sin, "cos": math.cos, "tan": math.tan, "asin": math.asin,
    "acos": math.acos, "atan": math.atan, "atan2": math.atan2, "exp": math.exp, "log": math.log,
    "log10": math.log10, "abs": abs, "min": min, "max": max, "integer": math.floor,
}


def _filled(value, dims):
    if not dims:
        return value
    return [_filled(value, dims[1:]) for _ in range(int(dims[0]))]


def modelica_string(token: TerminalNode) -> str:
    return re.sub(r"\\(.)", lambda m: _ESCAPES[m.group(1)], token.getText()[1:-1], flags=re.S)


def text_of(node) -> str:
    """Source text of a parse-tree node with the original spacing."""
    return node.start.getInputStream().getText(node.start.start, node.stop.stop)


def evaluate(node, env: dict[str, object]):
    """Value of a constant expression; names resolve through env (earlier public parameters)."""
    if isinstance(node, P.ExpressionContext):
        if node.simple_expression() is not None:
            return evaluate(node.simple_expression(), env)
        exprs = node.expression()  # if c1 then e1 elseif c2 then e2 ... else e
        for cond, value in zip(exprs[0:-1:2], exprs[1:-1:2]):
            if evaluate(cond, env):
                return evaluate(value, env)
        return evaluate(exprs[-1], env)
    if isinstance(node, P.Simple_expressionContext):
        parts = node.logical_expression()
        if len(parts) != 1:
            raise ModelicaError(f"range expression {node.getText()!r} is not a value")
        return evaluate(parts[0], env)
    if isinstance(node, P.Logical_expressionContext):
        values = [evaluate(t, env) for t in node.logical_term()]
        return values[0] if len(values) == 1 else any(values)
    if isinstance(node, P.Logical_termContext):
        values = [evaluate(f, env) for f in node.logical_factor()]
        return values[0] if len(values) == 1 else all(values)
    if isinstance(node, P.Logical_factorContext):
        value = evaluate(node.relation(), env)
        return (not value) if node.getChild(0).getText() == "not" else value
    if isinstance(node, P.RelationContext):
        sides = [evaluate(a, env) for a in node.arithmetic_expression()]
        if len(sides) == 1:
            return sides[0]
        ops = {"<": float.__lt__, "<=": float.__le__, ">": float.__gt__, ">=": float.__ge__,
               "==": float.__eq__, "<>": float.__ne__}
        return ops[node.rel_op().getText()](float(sides[0]), float(sides[1]))
    if isinstance(node, P.Arithmetic_expressionContext):
        result, sign = None, "+"
        for child in node.getChildren():
            if isinstance(child, P.Add_opContext):
                sign = child.getText().lstrip(".")
                continue
            value = evaluate(child, env)
            if result is None:
                result = -value if sign == "-" else value
            else:
                result = result - value if sign == "-" else result + value
        return result
    if isinstance(node, P.TermContext):
        children = list(node.getChildren())
        result = evaluate(children[0], env)
        for op, operand in zip(children[1::2], children[2::2]):
            value = evaluate(operand, env)
            result = result * value if op.getText().lstrip(".") == "*" else result / value
        return result
    if isinstance(node, P.FactorContext):
        base, *power = [evaluate(p, env) for p in node.primary()]
        return base ** power[0] if power else base
    if isinstance(node, P.PrimaryContext):
        return _evaluate_primary(node, env)
    raise ModelicaError(f"cannot evaluate {node.getText()!r}")


def _evaluate_primary(node: P.PrimaryContext, env: dict[str, object]):
    first = node.getChild(0)
    if node.UNSIGNED_NUMBER() is not None:
        text = node.getText()
        return float(text) if re.search(r"[.eE]", text) else int(text)
    if node.STRING() is not None:
        return modelica_string(node.STRING())
    if first.getText() in ("true", "false") and node.getChildCount() == 1:
        return first.getText() == "true"
    if node.function_call_args() is not None:
        name = first.getText()
        if name not in _FUNCTIONS:
            raise ModelicaError(f"function {name!r} in {node.getText()!r} is not evaluated by this check")
        args = node.function_call_args().function_arguments()
        return _FUNCTIONS[name](*(_arguments(args, env) if args is not None else []))
    if node.component_reference() is not None:
        ref = node.component_reference()
        if ref.array_subscripts() or ref.getText() not in env:
            raise ModelicaError(f"{ref.getText()!r} is not a known public parameter")
        return env[ref.getText()]
    if first.getText() == "(":
        items = node.output_expression_list().expression()
        if len(items) != 1:
            raise ModelicaError(f"tuple {node.getText()!r} is not a value")
        return evaluate(items[0], env)
    if first.getText() == "{":
        return _arguments(node.function_arguments(), env)
    raise ModelicaError(f"cannot evaluate {node.getText()!r}")


def _arguments(node: P.Function_argumentsContext, env: dict[str, object]) -> list:
    values = []
    while node is not None:
        if node.named_arguments() is not None or node.for_indices() is not None:
            raise ModelicaError(f"named arguments or iterators in {node.getText()!r} are not evaluated")
        argument = node.function_argument()
        if argument.expression() is None:
            raise ModelicaError(f"function argument {argument.getText()!r} is not a value")
        values.append(evaluate(argument.expression(), env))
        node = node.function_arguments()
    return values


# --------------------------------------------------------------------------------------------------
# Public declarations of the Modelica model


def find_model(tree: P.Stored_definitionContext, name: str = MODEL_NAME) -> P.Long_class_specifierContext:
    for definition in tree.class_definition():
        spec = definition.class_specifier().long_class_specifier()
        if spec is not None and spec.IDENT(0).getText() == name:
            if definition.class_prefixes().getText() != "model":
                raise ModelicaError(f"{name} is a {definition.class_prefixes().getText()}, not a model")
            if spec.IDENT(1).getText() != name:
                raise ModelicaError(f"model {name} ends with 'end {spec.IDENT(1).getText()}'")
            return spec
    raise ModelicaError(f"no model {name} in the file")


def public_elements(spec: P.Long_class_specifierContext) -> list[P.ElementContext]:
    """Elements of the public sections (the leading one and those after 'public')."""
    elements, public = [], True
    for child in spec.composition().getChildren():
        if isinstance(child, TerminalNode):
            if child.getText() in ("public", "protected"):
                public = child.getText() == "public"
        elif isinstance(child, P.Element_listContext) and public:
            elements.extend(child.element())
    return elements


def _modifiers(declaration: P.DeclarationContext):
    """(binding expression or None, {attribute: (each, expression)})."""
    modification = declaration.modification()
    if modification is None:
        return None, {}
    attributes = {}
    class_modification = modification.class_modification()
    if class_modification is not None and class_modification.argument_list() is not None:
        for argument in class_modification.argument_list().argument():
            item = argument.element_modification_or_replaceable()
            if item is None or item.element_modification() is None:
                raise ModelicaError(f"{declaration.IDENT().getText()}: redeclaration {argument.getText()!r}")
            each = any(isinstance(c, TerminalNode) and c.getText() == "each" for c in item.getChildren())
            em = item.element_modification()
            sub = em.modification()
            if sub is None or sub.class_modification() is not None or sub.expression() is None:
                raise ModelicaError(f"{declaration.IDENT().getText()}: modifier {em.getText()!r} is not "
                                    "'attribute = value'")
            attributes[em.name().getText()] = (each, sub.expression())
    return modification.expression(), attributes


def _scalar_values(value, dims: list[int], what: str):
    """The value of each array entry, in index order (row major)."""
    if not dims:
        return [value]
    if not isinstance(value, list) or len(value) != dims[0]:
        raise ModelicaError(f"{what}: {value!r} does not have size {dims[0]}")
    return [v for item in value for v in _scalar_values(item, dims[1:], what)]


def modelica_variables(text: str, source: str = "<string>") -> dict[str, Var]:
    """The public scalar variables of the model, as an FMU exporter would list them."""
    spec = find_model(parse_modelica(text, source))
    env: dict[str, object] = {}
    variables: dict[str, Var] = {}
    for element in public_elements(spec):
        clause = element.component_clause()
        if element.import_clause() is not None or element.class_definition() is not None:
            continue  # not a variable
        if clause is None:
            raise ModelicaError(f"public element {text_of(element)!r} is not supported (extends, replaceable, ...)")
        flags = {c.getText() for c in element.getChildren() if isinstance(c, TerminalNode)}
        if flags & {"redeclare", "inner", "outer", "replaceable"}:
            raise ModelicaError(f"public element {text_of(element)!r}: {sorted(flags)} is not supported")
        final = "final" in flags
        prefixes = [c.getText() for c in clause.type_prefix().getChildren()]
        type_name = clause.type_specifier().getText()
        for component in clause.component_list().component_declaration():
            declaration = component.declaration()
            name = declaration.IDENT().getText()
            if type_name not in TYPES:
                raise ModelicaError(f"{name}: type {type_name!r} is not one of {TYPES}")
            if component.condition_attribute() is not None:
                raise ModelicaError(f"{name}: conditional components are not supported")
            dims = []
            for subscripts in (clause.array_subscripts(), declaration.array_subscripts()):
                if subscripts is not None:
                    dims += [int(evaluate(s.expression(), env)) for s in subscripts.subscript()]
            binding, attributes = _modifiers(declaration)
            description = "".join(modelica_string(s) for s in component.comment().string_comment().STRING())

            if "parameter" in prefixes:
                causality = "calculatedParameter" if final and binding is not None else "parameter"
                variability = "fixed"
            elif "constant" in prefixes:
                causality, variability = "local", "constant"
            else:
                causality = next((p for p in prefixes if p in ("input", "output")), "local")
                continuous = type_name == "Real" and "discrete" not in prefixes
                variability = "continuous" if continuous else "discrete"

            # Values of the whole array (or scalar), then per entry.
            start_expr = binding if causality in ("parameter", "calculatedParameter") and binding is not None \
                else attributes.get("start", (False, None))[1]
            start_value = evaluate(start_expr, env) if start_expr is not None else None
            if causality in ("parameter", "calculatedParameter", "local") and binding is not None:
                env[name] = evaluate(binding, env)
            entries = [list(i) for i in itertools.product(*(range(1, n + 1) for n in dims))]
            starts = _scalar_values(start_value, dims, f"{name} start") if start_value is not None \
                else [None] * len(entries)
            attribute_values = {}
            for attribute, (each, expression) in attributes.items():
                if attribute in ("start", "fixed"):
                    continue
                value = evaluate(expression, env)
                if dims and not each and not isinstance(value, list):
                    raise ModelicaError(f"{name}: scalar modifier {attribute} of an array needs 'each'")
                attribute_values[attribute] = [value] * len(entries) if each or not dims \
                    else _scalar_values(value, dims, f"{name} {attribute}")
            for k, index in enumerate(entries):
                scalar = f"{name}[{','.join(map(str, index))}]" if dims else name
                values = {a: v[k] for a, v in attribute_values.items()}
                unit = values.pop("unit", None)
                variables[scalar] = Var(
                    name=scalar, type=type_name, causality=causality, variability=variability,
                    description=f"{description} {','.join(map(str, index))}" if dims else description,
                    unit=unit, start=starts[k], attributes=values)
    return variables


# --------------------------------------------------------------------------------------------------
# The FMU's modelDescription.xml


def fmu_variables(model_description: Path) -> dict[str, Var]:
    variables = {}
    for sv in ET.parse(model_description).getroot().iter("ScalarVariable"):
        typed = next(iter(sv))
        start = typed.get("start")
        if start is not None:
            start = {"Real": float, "Integer": int, "Boolean": lambda s: s == "true"}.get(typed.tag, str)(start)
        variables[sv.get("name")] = Var(
            name=sv.get("name"), type=typed.tag, causality=sv.get("causality", "local"),
            variability=sv.get("variability", "continuous"), description=sv.get("description", ""),
            unit=typed.get("unit"), start=start,
            attributes={a: typed.get(a) for a in EXTRA_ATTRIBUTES if typed.get(a) is not None})
    return variables


# --------------------------------------------------------------------------------------------------
# Comparison


def _same_value(a, b) -> bool:
    if isinstance(a, bool) or isinstance(b, bool) or a is None or b is None:
        return a is b or a == b and type(a) is type(b)
    try:
        return math.isclose(float(a), float(b), rel_tol=1e-12, abs_tol=0.0)
    except (TypeError, ValueError):
        return str(a) == str(b)


def compare(modelica: dict[str, Var], fmu: dict[str, Var]) -> list[str]:
    """Every disagreement between the two variable sets, one message each (empty: they agree)."""
    problems = [f"{n}: only in Modelica ({modelica[n].causality})" for n in modelica if n not in fmu]
    problems += [f"{n}: only in the FMU ({fmu[n].causality})" for n in fmu if n not in modelica]
    for name in (n for n in fmu if n in modelica):
        mo, xml = modelica[name], fmu[name]

        def differs(what, a, b):
            problems.append(f"{name}: {what} differs: Modelica {a!r}, FMU {b!r}")

        for what in ("type", "causality", "variability", "description"):
            if getattr(mo, what) != getattr(xml, what):
                differs(what, getattr(mo, what), getattr(xml, what))
        if (mo.unit or None) != (xml.unit or None):
            differs("unit", mo.unit, xml.unit)
        if xml.causality in ("parameter", "input"):
            mo_start = mo.start
            if mo.type == "Real" and isinstance(mo_start, int) and not isinstance(mo_start, bool):
                mo_start = float(mo_start)
            integer_ok = mo.type != "Integer" or (type(mo_start) is int)
            if not integer_ok or not _same_value(mo_start, xml.start):
                differs("start", mo_start, xml.start)
        for attribute in EXTRA_ATTRIBUTES:
            a, b = mo.attributes.get(attribute), xml.attributes.get(attribute)
            if (a is not None or b is not None) and not _same_value(a, b):
                differs(attribute, a, b)
    return problems


# --------------------------------------------------------------------------------------------------
# Tests


@pytest.fixture(scope="module")
def fmu_vars(tmp_path_factory) -> dict[str, Var]:
    out = tmp_path_factory.mktemp("fmu")
    subprocess.run([sys.executable, str(GENERATE), str(out)], check=True, cwd=ROOT)
    return fmu_variables(out / "modelDescription.xml")


@pytest.fixture(scope="module")
def mo_text() -> str:
    return MO_FILE.read_text()


@pytest.fixture(scope="module")
def mo_vars(mo_text) -> dict[str, Var]:
    return modelica_variables(mo_text, str(MO_FILE))


def test_modelica_parses(mo_text):
    spec = find_model(parse_modelica(mo_text, str(MO_FILE)))
    assert spec.IDENT(0).getText() == MODEL_NAME


def test_modelica_declares_the_fmu_variables(mo_vars, fmu_vars):
    assert {"m", "I_1", "tab_y[16]", "F_ext_x", "y", "n_steps"} <= set(fmu_vars)  # not vacuous
    problems = compare(mo_vars, fmu_vars)
    assert not problems, "modelica/ScrewVertebra.mo disagrees with the FMU:\n" + "\n".join(problems)


def test_calculated_inertia_is_the_solid_cylinder(mo_text):
    spec = find_model(parse_modelica(mo_text))
    env: dict[str, object] = {}
    for element in public_elements(spec):
        clause = element.component_clause()
        if clause is None:
            continue
        for component in clause.component_list().component_declaration():
            binding, _ = _modifiers(component.declaration())
            if binding is not None and "parameter" in clause.type_prefix().getText():
                env[component.declaration().IDENT().getText()] = evaluate(binding, env)
    r, length, m = env["D_screw"] / 2, env["L_screw"], env["m"]
    assert math.isclose(env["I_1"], m * (3 * r**2 + length**2) / 12, rel_tol=1e-14)
    assert math.isclose(env["I_3"], env["I_1"], rel_tol=1e-14)
    assert math.isclose(env["I_2"], m * r**2 / 2, rel_tol=1e-14)
    assert math.isclose(math.cos(env["phi_inertia"]), 0.96, rel_tol=1e-14)
    assert math.isclose(math.sin(env["phi_inertia"]), 0.28, rel_tol=1e-14)


def _mutate(text: str, old: str, new: str) -> str:
    assert text.count(old) == 1, f"the mutation target {old!r} must occur exactly once"
    return text.replace(old, new)


@pytest.mark.parametrize("old, new, expected", [
    ('Real d_x(unit="N.s/m")', 'Real d_x(unit="N.m/s")',
     ["d_x: unit differs: Modelica 'N.m/s', FMU 'N.s/m'"]),
    ('"Rate of beta"', '"Rate of Beta"',
     ["w_beta: description differs: Modelica 'Rate of Beta', FMU 'Rate of beta'"]),
    ('c_beta(unit="N.m/rad") = 1 ', 'c_beta(unit="N.m/rad") = 1.5 ',
     ["c_beta: start differs: Modelica 1.5, FMU 1.0"]),
    ('parameter Boolean unload = false', 'parameter Boolean unload = true',
     ["unload: start differs: Modelica True, FMU False"]),
    ('input Real y_in(unit="m", start=0)', 'output Real y_in(unit="m")',
     ["y_in: causality differs: Modelica 'output', FMU 'input'",
      "y_in: start differs: Modelica None, FMU 0.0"]),
    ('final parameter Real I_2', 'parameter Real I_2',
     ["I_2: causality differs: Modelica 'parameter', FMU 'calculatedParameter'"]),
    ('tab_F[16](each unit="N") = zeros(16)', 'tab_F[15](each unit="N") = zeros(15)',
     ["tab_F[16]: only in the FMU (parameter)"]),
    ('  // Inputs\n', '  Real spare "Not in the contract";\n',
     ["spare: only in Modelica (local)"]),
])
def test_comparison_reports_a_mutation(mo_text, fmu_vars, old, new, expected):
    mutated = modelica_variables(_mutate(mo_text, old, new))
    assert compare(mutated, fmu_vars) == expected


def test_protected_declarations_are_ignored(mo_text, fmu_vars):
    mutated = _mutate(mo_text, "\nprotected\n", "\nprotected\n  Real spare \"Internal\";\n")
    assert compare(modelica_variables(mutated), fmu_vars) == []


def test_syntax_error_fails(mo_text):
    with pytest.raises(ModelicaError, match="syntax error"):
        parse_modelica(_mutate(mo_text, "der(x) = v_x;", "der(x) = v_x"))
    with pytest.raises(ModelicaError, match="syntax error"):
        parse_modelica(mo_text + "\nmodel Trailing\n")
