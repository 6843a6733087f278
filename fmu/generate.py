#!/usr/bin/env python3
"""Generate modelDescription.xml and variables.h from the public declarations of a Modelica model
(modelica/ScrewVertebra.mo, modelica/InterfaceElement.mo).

The Modelica model is the single source of the FMU's public variable contract: names, types,
causalities, variabilities, units, start values and descriptions are read from its public component
declarations, and the C code (variables.h) and the XML are both derived from them. Protected
declarations, functions and the equation and algorithm sections are Modelica internals and are never
looked at. The file is parsed with a real Modelica grammar (modelica-builder's ANTLR parser, in the
``fmu`` extra), so a syntax error fails the build; tests/test_modelica.py checks the result against an
independent reading of the same file (pymoca's parser and flattener).

Mapping rules (those of a Modelica tool exporting an FMU):

- ``parameter`` -> parameter; ``final parameter`` with a binding -> calculatedParameter (variability
  fixed); ``input``/``output`` -> input/output, continuous for Real unless ``discrete``, discrete for
  Integer and Boolean. Anything else public (a plain variable, a constant) is refused: the FMU has no
  local variables, so such a declaration belongs in the protected section.
- The start value of a parameter is its binding (else its ``start``), that of an input its ``start``,
  that of an output its ``start`` where declared. A binding that is an expression (``atan2(0.28,
  0.96)``, ``2e-3/60``) is evaluated to a number; names in it resolve to earlier public parameters.
- Entry k of an array ``a[n] "text"`` is the FMU variable ``a[k]`` with description ``"text k"``.
- Value references are the 1-based positions of the scalar variables in declaration order (arrays
  expanded in index order), so an array's entries have consecutive value references.
"""
from __future__ import annotations

import csv
import io
import itertools
import math
import re
import sys
import uuid
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

from antlr4 import CommonTokenStream, InputStream, Token
from antlr4.error.ErrorListener import ErrorListener
from antlr4.tree.Tree import TerminalNode
from modelica_builder.modelica_parser import modelicaLexer, modelicaParser as P

HERE = Path(__file__).resolve().parent
MO_FILE = HERE.parent / "modelica" / "ScrewVertebra.mo"
MODEL_NAME = "ScrewVertebra"
SOURCES = ["fmi2.c", "model.c", "solver.c", "sv_generated.c"]
#: What each model's FMU offers beyond its variables: its C sources, the interfaces (a model exchange FMU
#: exports its states, the public outputs whose der() the equations use, and their derivatives), FMU state
#: support, the default experiment.
FMUS = {
    "ScrewVertebra": dict(sources=SOURCES, model_exchange=False, fmu_state=False, experiment=("0", "12", "0.01")),
    "InterfaceElement": dict(sources=["fmi2.c", "element.c", "el_generated.c"], model_exchange=True,
                             fmu_state=True, experiment=("0", "1", "0.001")),
}
#: Forward sensitivities the FMU computes beside its states (fmu/codegen.py generates their equations, fmu/solver.c
#: integrates them): up to ``parameters`` Real parameters, each selected by its value reference in the Integer
#: parameter ``sens_p[k]`` (0: none), and the derivative of each named output by each of them, the output
#: ``sens_<output>[k]``. The variables follow the model's own, so its value references are unchanged.
SENSITIVITIES = {"ScrewVertebra": dict(parameters=8, outputs=("F_meas", "y_meas"))}
TYPES = ("Real", "Integer", "Boolean")
# The type attributes a public declaration may set (others, such as min or fixed, are not carried to the XML).
ATTRIBUTES = ("unit", "start")

# SI base-unit exponents (kg, m, s, rad) of every unit the model may use.
UNITS = {
    "1": {},
    "kg": {"kg": 1},
    "m": {"m": 1},
    "s": {"s": 1},
    "rad": {"rad": 1},
    "1/m": {"m": -1},
    "m/s": {"m": 1, "s": -1},
    "m/s2": {"m": 1, "s": -2},
    "rad/s": {"rad": 1, "s": -1},
    "N": {"kg": 1, "m": 1, "s": -2},
    "N.m": {"kg": 1, "m": 2, "s": -2},
    "kg.m2": {"kg": 1, "m": 2},
    "N/m": {"kg": 1, "s": -2},
    "N.s/m": {"kg": 1, "s": -1},
    "N.m/rad": {"kg": 1, "m": 2, "s": -2, "rad": -1},
    "N.m.s/rad": {"kg": 1, "m": 2, "s": -1, "rad": -1},
}


class ModelicaError(Exception):
    """A syntax error, or a public declaration this generator cannot map to the FMU's contract."""


@dataclass(frozen=True)
class Variable:
    """One scalar variable of the FMU, with its attributes as modelDescription.xml writes them."""
    vr: int
    name: str
    type: str
    causality: str
    variability: str
    initial: str        # "" where the XML leaves it out
    start: str          # "" where the model declares none
    unit: str           # "" for none
    description: str


@dataclass(frozen=True)
class Model:
    """The model's description string and its public scalar variables in value-reference order (for a model
    exchange FMU, the derivatives of its states after them)."""
    description: str
    variables: list[Variable]
    name: str = MODEL_NAME
    states: tuple[str, ...] = ()    # model exchange: the continuous states, in the order of <Derivatives>


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
    """The value of a Modelica string literal (quotes removed, escapes resolved)."""
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
            raise ModelicaError(f"function {name!r} in {node.getText()!r} is not evaluated by fmu/generate.py")
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
    """The class specifier of model ``name`` (a model, closed by ``end name``)."""
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
    """Elements of the public sections (the leading one and those after 'public'); equation and
    algorithm sections are other children of the composition and never looked at."""
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


def _scalar_values(value, dims: list[int], what: str) -> list:
    """The value of each array entry, in index order (row major)."""
    if not dims:
        return [value]
    if not isinstance(value, list) or len(value) != dims[0]:
        raise ModelicaError(f"{what}: {value!r} does not have size {dims[0]}")
    return [v for item in value for v in _scalar_values(item, dims[1:], what)]


def format_start(type_name: str, value: object, what: str) -> str:
    """A start value as modelDescription.xml writes it (shortest repr of a Real: 823224, 5e-08)."""
    if type_name == "Boolean":
        if not isinstance(value, bool):
            raise ModelicaError(f"{what}: {value!r} is not a Boolean")
        return "true" if value else "false"
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ModelicaError(f"{what}: {value!r} is not a number")
    if type_name == "Integer":
        if not isinstance(value, int):
            raise ModelicaError(f"{what}: {value!r} is not an Integer")
        return str(value)
    if not math.isfinite(value):
        raise ModelicaError(f"{what}: {value!r} is not finite")
    text = repr(float(value))
    return text[:-2] if text.endswith(".0") else text


def _causality(prefixes: list[str], final: bool, has_binding: bool, type_name: str, name: str) -> tuple[str, str]:
    """(causality, variability) of a public declaration, by the rules of the module docstring."""
    if "parameter" in prefixes:
        return ("calculatedParameter" if final and has_binding else "parameter"), "fixed"
    causality = next((p for p in prefixes if p in ("input", "output")), None)
    if causality is None or set(prefixes) - {"input", "output", "discrete"}:
        raise ModelicaError(f"public {' '.join(prefixes + [type_name])} {name}: not a parameter, input or output "
                            "(the FMU has no local variables: declare it protected)")
    continuous = type_name == "Real" and "discrete" not in prefixes
    return causality, "continuous" if continuous else "discrete"


def state_names(spec: P.Long_class_specifierContext) -> set[str]:
    """The variables whose der() the equation sections use: the model's continuous states."""
    names: set[str] = set()
    for child in spec.composition().getChildren():
        if isinstance(child, P.Equation_sectionContext):
            names |= set(re.findall(r"\bder\(\s*(\w+)\s*\)", text_of(child)))
    return names


def parse_model(text: str, source: str = "<string>", model_name: str = MODEL_NAME) -> Model:
    """The model's description and public scalar variables, as the FMU exports them."""
    spec = find_model(parse_modelica(text, source), model_name)
    model_description = "".join(modelica_string(s) for s in spec.string_comment().STRING())
    env: dict[str, object] = {}
    variables: list[Variable] = []
    for element in public_elements(spec):
        clause = element.component_clause()
        if element.import_clause() is not None or element.class_definition() is not None:
            continue  # not a variable
        if clause is None:
            raise ModelicaError(f"public element {text_of(element)!r} is not supported (extends, replaceable, ...)")
        flags = {c.getText() for c in element.getChildren() if isinstance(c, TerminalNode)}
        if flags & {"redeclare", "inner", "outer", "replaceable"}:
            raise ModelicaError(f"public element {text_of(element)!r}: {sorted(flags)} is not supported")
        prefixes = [c.getText() for c in clause.type_prefix().getChildren()]
        type_name = clause.type_specifier().getText()
        for component in clause.component_list().component_declaration():
            declaration = component.declaration()
            name = declaration.IDENT().getText()
            if type_name not in TYPES:
                raise ModelicaError(f"{name}: type {type_name!r} is not one of {TYPES}")
            if component.condition_attribute() is not None:
                raise ModelicaError(f"{name}: conditional components are not supported")
            dims: list[int] = []
            for subscripts in (clause.array_subscripts(), declaration.array_subscripts()):
                if subscripts is not None:
                    dims += [int(evaluate(s.expression(), env)) for s in subscripts.subscript()]
            binding, attributes = _modifiers(declaration)
            unsupported = sorted(set(attributes) - set(ATTRIBUTES))
            if unsupported:
                raise ModelicaError(f"{name}: attributes {unsupported} are not carried to the FMU (only {ATTRIBUTES})")
            description = "".join(modelica_string(s) for s in component.comment().string_comment().STRING())
            causality, variability = _causality(prefixes, "final" in flags, binding is not None, type_name, name)
            entries = [list(i) for i in itertools.product(*(range(1, n + 1) for n in dims))]

            def per_entry(each: bool, value: object, what: str) -> list:
                """The value of each entry: a scalar of an array applies to all with 'each'."""
                return [value] * len(entries) if each or not dims else _scalar_values(value, dims, f"{name} {what}")

            # Bindings of parameters are values (later bindings may use them); a calculated parameter has
            # no start in the XML, a parameter its binding (else its start), an input or output its start.
            if causality in ("parameter", "calculatedParameter") and binding is not None:
                env[name] = evaluate(binding, env)
            starts: list = [None] * len(entries)
            if causality == "parameter" and binding is not None:
                starts = per_entry(False, env[name], "binding")
            elif causality != "calculatedParameter" and "start" in attributes:
                each, expression = attributes["start"]
                starts = per_entry(each, evaluate(expression, env), "start")
            elif causality in ("parameter", "input"):
                raise ModelicaError(f"{name}: the {causality} needs a start value (a binding or start=...)")
            starts = ["" if s is None else format_start(type_name, s, f"{name} start") for s in starts]
            units = [""] * len(entries)
            if "unit" in attributes:
                each, expression = attributes["unit"]
                units = per_entry(each, evaluate(expression, env), "unit")
                for unit in units:
                    if unit not in UNITS:
                        raise ModelicaError(f"{name}: unit {unit!r} is not in UNITS of fmu/generate.py")
            for k, index in enumerate(entries):
                suffix = ",".join(map(str, index))
                variables.append(Variable(
                    vr=len(variables) + 1, name=f"{name}[{suffix}]" if dims else name, type=type_name,
                    causality=causality, variability=variability,
                    initial={"parameter": "exact", "calculatedParameter": "calculated"}.get(causality, ""),
                    start=starts[k], unit=units[k], description=f"{description} {suffix}" if dims else description))
    if not FMUS.get(model_name, {}).get("model_exchange"):
        return Model(model_description, variables + sensitivity_variables(model_name, variables), model_name)
    # model exchange: the states are public Real outputs (in declaration order); their derivatives follow
    states = state_names(spec)
    declared = {v.name: v for v in variables}
    hidden = sorted(s for s in states if s not in declared or declared[s].causality != "output")
    if hidden:
        raise ModelicaError(f"the states {hidden} must be public outputs for the model exchange FMU")
    ordered = tuple(v.name for v in variables if v.name in states)
    for s in ordered:
        variables.append(Variable(vr=len(variables) + 1, name=f"der({s})", type="Real", causality="local",
                                  variability="continuous", initial="", start="", unit="",
                                  description=f"Rate of {s}"))
    return Model(model_description, variables, model_name, ordered)


def sensitivity_variables(model_name: str, variables: list[Variable]) -> list[Variable]:
    """The variables of the forward sensitivities (SENSITIVITIES) after the model's own: the selecting parameters
    sens_p[k], then per output the derivatives sens_<output>[k], then their tolerance sens_rtol."""
    facts = SENSITIVITIES.get(model_name)
    if not facts:
        return []
    declared = {v.name: v for v in variables}
    if not any(name in declared for name in facts["outputs"]):
        return []   # a model of that name without those outputs (a test's minimal one): nothing to differentiate
    k_max = facts["parameters"]
    out: list[Variable] = []
    for k in range(1, k_max + 1):
        out.append(Variable(
            vr=len(variables) + len(out) + 1, name=f"sens_p[{k}]", type="Integer", causality="parameter",
            variability="fixed", initial="exact", start="0", unit="",
            description=f"Forward sensitivity {k}: the value reference of the Real parameter to differentiate the "
                        f"outputs sens_<output>[{k}] by (0: none; every one 0 costs nothing)"))
    for name in facts["outputs"]:
        if name not in declared or declared[name].causality != "output" or declared[name].type != "Real":
            raise ModelicaError(f"SENSITIVITIES of fmu/generate.py names {name!r}, which is not a Real output")
        for k in range(1, k_max + 1):
            out.append(Variable(
                vr=len(variables) + len(out) + 1, name=f"sens_{name}[{k}]", type="Real", causality="output",
                variability="continuous", initial="", start="", unit="",
                description=f"Forward sensitivity of {name} by the parameter sens_p[{k}] selects: d {name} / d "
                            f"parameter, in {declared[name].unit or '1'} per the parameter's unit (0 when "
                            f"sens_p[{k}] = 0)"))
    out.append(Variable(
        vr=len(variables) + len(out) + 1, name="sens_rtol", type="Real", causality="parameter", variability="fixed",
        initial="exact", start="0", unit="",
        description="Relative local error tolerance of the forward sensitivities (0: rtol); a least-squares "
                    "Jacobian needs a few digits, not the states' accuracy"))
    return out


def read_model(path: Path = MO_FILE) -> Model:
    """The FMU's contract read from a Modelica file (by default modelica/ScrewVertebra.mo; the model is the
    one of FMUS the file declares)."""
    text = path.read_text(encoding="utf-8")
    declared = [m for m in FMUS if re.search(rf"^\s*model\s+{m}\b", text, re.M)]
    return parse_model(text, str(path), declared[0] if declared else MODEL_NAME)


# --------------------------------------------------------------------------------------------------
# The generated files


def c_name(name: str) -> str:
    """The C identifier part of a variable name: tab_y[3] -> tab_y_3."""
    return name.replace("[", "_").replace("]", "").replace(",", "_").replace("(", "_").replace(")", "")


def contract_text(model: Model) -> str:
    """The contract as CSV text, one row per variable: what the GUID is a hash of."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["model", model.name, model.description])
    fields = ["name", "type", "causality", "variability", "initial", "start", "unit", "description"]
    writer.writerow(fields)
    for v in model.variables:
        writer.writerow([getattr(v, f) for f in fields])
    return out.getvalue()


def guid(model: Model) -> str:
    """A hash of the contract, so an unchanged contract keeps its GUID across builds (and edits of the
    equations or the protected part)."""
    return str(uuid.uuid5(uuid.NAMESPACE_URL, contract_text(model)))


def xml_scalar(v: Variable, derivative_of: int | None = None) -> str:
    attrs = [f"name={quoteattr(v.name)}", f"valueReference=\"{v.vr}\"",
             f"description={quoteattr(v.description)}", f"causality=\"{v.causality}\"",
             f"variability=\"{v.variability}\""]
    if v.initial and v.causality != "input":
        attrs.append(f"initial=\"{v.initial}\"")
    inner = []
    if v.unit:
        inner.append(f"unit=\"{v.unit}\"")
    if v.causality in ("parameter", "input"):
        inner.append(f"start=\"{v.start}\"")
    if derivative_of is not None:
        inner.append(f"derivative=\"{derivative_of}\"")
    return (f"    <ScalarVariable {' '.join(attrs)}>\n"
            f"      <{v.type} {' '.join(inner)}/>\n    </ScalarVariable>")


def model_description(model: Model, guid: str) -> str:
    """modelDescription.xml of the co-simulation FMU."""
    rows = model.variables
    units = sorted({r.unit for r in rows if r.unit})
    unit_xml = []
    for u in units:
        exps = " ".join(f"{k}=\"{v}\"" for k, v in UNITS[u].items())
        unit_xml.append(f"    <Unit name=\"{u}\"><BaseUnit {exps}/></Unit>")
    facts = FMUS[model.name]
    name = model.name
    outputs = [r for r in rows if r.causality == "output"]
    derivatives = [r for r in rows if r.name.startswith("der(")]
    initial = [r for r in rows if r.causality in ("output", "calculatedParameter")] + derivatives
    sources = "\n".join(f"        <File name=\"{s}\"/>" for s in facts["sources"])
    state = "true" if facts["fmu_state"] else "false"
    me = ""
    if facts["model_exchange"]:
        me = f"""
  <ModelExchange modelIdentifier="{name}" completedIntegratorStepNotNeeded="true"
    canBeInstantiatedOnlyOncePerProcess="false" canNotUseMemoryManagementFunctions="true"
    canGetAndSetFMUstate="{state}" canSerializeFMUstate="false">
    <SourceFiles>
{sources}
    </SourceFiles>
  </ModelExchange>"""
    by_name = {r.name: r.vr for r in rows}
    derivative = {r.name: by_name[r.name[4:-1]] for r in derivatives}
    structure = ""
    if derivatives:
        structure = ("\n    <Derivatives>\n"
                     + "\n".join(f'      <Unknown index="{r.vr}"/>' for r in derivatives)
                     + "\n    </Derivatives>")
    start, stop, step = facts["experiment"]
    return f"""<?xml version="1.0" encoding="UTF-8"?>
<fmiModelDescription fmiVersion="2.0" modelName="{name}" guid="{{{guid}}}"
  description={quoteattr(model.description)}
  generationTool="fmusa fmu/generate.py" variableNamingConvention="structured" numberOfEventIndicators="0">{me}
  <CoSimulation modelIdentifier="{name}" canHandleVariableCommunicationStepSize="true"
    canInterpolateInputs="true" maxOutputDerivativeOrder="0" canBeInstantiatedOnlyOncePerProcess="false"
    canNotUseMemoryManagementFunctions="true" canGetAndSetFMUstate="{state}" canSerializeFMUstate="false">
    <SourceFiles>
{sources}
    </SourceFiles>
  </CoSimulation>
  <UnitDefinitions>
{chr(10).join(unit_xml)}
  </UnitDefinitions>
  <LogCategories>
    <Category name="logStatusError" description="Errors: bad parameters, failed steps"/>
    <Category name="logStatusWarning" description="Warnings"/>
    <Category name="logAll" description="Everything, including solver statistics"/>
  </LogCategories>
  <DefaultExperiment startTime="{start}" stopTime="{stop}" stepSize="{step}"/>
  <ModelVariables>
{chr(10).join(xml_scalar(r, derivative.get(r.name)) for r in rows)}
  </ModelVariables>
  <ModelStructure>
    <Outputs>
{chr(10).join(f'      <Unknown index="{r.vr}"/>' for r in outputs)}
    </Outputs>{structure}
    <InitialUnknowns>
{chr(10).join(f'      <Unknown index="{r.vr}"/>' for r in initial)}
    </InitialUnknowns>
  </ModelStructure>
</fmiModelDescription>
"""


def c_header(model: Model, guid: str) -> str:
    """variables.h: the value references and the variable table the C code is compiled with."""
    rows = model.variables
    lines = [f"/* Generated by fmu/generate.py from modelica/{model.name}.mo: do not edit. */",
             "#ifndef VARIABLES_H", "#define VARIABLES_H", "",
             f"#define MODEL_GUID \"{{{guid}}}\"", f"#define N_VR {len(rows) + 1}", ""]
    for r in rows:
        lines.append(f"#define VR_{c_name(r.name)} {r.vr}")
    lines += ["", "/* X(name, vr, type, causality, start) for every variable */", "#define VARIABLES(X) \\"]
    kinds = {"parameter": "CAUS_PARAMETER", "calculatedParameter": "CAUS_CALCULATED",
             "input": "CAUS_INPUT", "output": "CAUS_OUTPUT", "local": "CAUS_LOCAL"}
    for r in rows:
        start = r.start or "0"
        if r.type == "Boolean":
            start = "1" if start == "true" else "0"
        lines.append(f"    X(\"{r.name}\", {r.vr}, TYPE_{r.type.upper()}, {kinds[r.causality]}, {start}) \\")
    lines += ["", "#endif", ""]
    return "\n".join(lines)


def write(out: Path, model: Model) -> None:
    """modelDescription.xml into out, variables.h into out/sources."""
    g = guid(model)
    (out / "sources").mkdir(parents=True, exist_ok=True)
    (out / "modelDescription.xml").write_text(model_description(model, g), encoding="utf-8")
    (out / "sources" / "variables.h").write_text(c_header(model, g), encoding="utf-8")


def main(argv: list[str] | None = None) -> None:
    """generate.py [OUT [MODEL.mo]]: OUT defaults to build/fmu, MODEL.mo to modelica/ScrewVertebra.mo."""
    args = sys.argv[1:] if argv is None else argv
    out = Path(args[0]) if args else HERE.parent / "build" / "fmu"
    source = Path(args[1]) if len(args) > 1 else MO_FILE
    try:
        model = read_model(source)
    except ModelicaError as e:
        sys.exit(f"fmu/generate.py: {source}: {e}")
    write(out, model)


if __name__ == "__main__":
    main()
