"""The study file's YAML, validated into the dataclasses of fmusa.study.schema: every error names file:line:key and the fix."""
from __future__ import annotations

import difflib
import math
import os
import re
from pathlib import Path
from typing import Callable, Mapping, Sequence

import yaml
from yaml.constructor import ConstructorError, SafeConstructor
from yaml.nodes import MappingNode, Node, ScalarNode, SequenceNode


from fmusa.runs.worker import START_METHODS
from fmusa.study.schema import (
    Constraint, DISTRIBUTIONS, Execution, FMUOptions, FixedValue, GridStage, INTERFACES, METHODS, Metric, Parameter, REDUCTIONS, RegressionStage, RoiStage, SAMPLED_REDUCTIONS, SOLVERS, STAGE_NAMES, Scenario, SearchStage, SensitivityParameter, SensitivityStage, Study, StudyError, IDENTIFIER,
)

# ============================================================================ YAML plumbing
class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads ``1e5`` and ``1.0e5`` as floats (YAML 1.1, and so plain
    PyYAML, reads them as strings; YAML 1.2 and every user reads them as numbers)."""


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^(?:[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+"
               r"|[-+]?\.[0-9_]+[eE][-+]?[0-9]+)$"),
    list("-+0123456789."))

_NULL = "tag:yaml.org,2002:null"
#: Largest integer a study file may hold: beyond it no count, size or value of a study makes sense, and
#: converting it to a float overflows.
MAX_INT = 10 ** 18
MAX_INT_DIGITS = 18
#: Deepest nesting of lists and mappings: a study file nests four or five levels.
MAX_DEPTH = 100
#: Most values a free-form block may expand to (aliases included); the paper's block has about 40.
MAX_PLAIN_VALUES = 100_000


def _line(node: Node) -> int:
    return node.start_mark.line + 1


def _in(where: str) -> str:
    return f"in '{where}'" if where else "at the top level"


def _key(key: str, where: str) -> str:
    return f"key '{key}' {_in(where)}"


def _suggest(word: str, pool) -> str:
    close = difflib.get_close_matches(word, list(pool), n=1, cutoff=0.6)
    return f"; did you mean '{close[0]}'?" if close else ""


def _fmt_list(names) -> str:
    names = list(names)
    return ", ".join(names) if names else "none"


class _Parser:
    """Walks the composed node tree; knows the file label for messages."""

    def __init__(self, label: str) -> None:
        self.label = label
        self._constructor = SafeConstructor()
        self.lines: dict[str, int] = {}   # study key -> line, for the checks against the FMU
        self.plain_nodes = 0              # values built by plain(), bounded by MAX_PLAIN_VALUES

    def mark(self, key: str, node: Node) -> None:
        self.lines.setdefault(key, _line(node))

    # ---------------------------------------------------------------- errors
    def error(self, node: Node | None, msg: str) -> StudyError:
        line = _line(node) if node is not None else 1
        return StudyError(f"{self.label}:{line}: {msg}")

    # ---------------------------------------------------------------- plain values
    def scalar(self, node: ScalarNode):
        try:
            v = self._constructor.construct_object(node, deep=True)
        except ConstructorError as exc:
            raise self.error(node, f"cannot read the value {node.value!r}: {exc.problem}; "
                                   f"write a plain number, string, true/false or null") from None
        except (ValueError, OverflowError) as exc:     # e.g. more digits than Python converts
            raise self.error(node, f"cannot read the value {node.value[:40]!r}…: {exc}; write a number of "
                                   f"at most {MAX_INT_DIGITS} digits") from None
        if isinstance(v, int) and not isinstance(v, bool) and abs(v) > MAX_INT:
            raise self.error(node, f"the integer {node.value[:20]}… ({len(str(abs(v)))} digits) is larger than "
                                   f"any value a study uses (at most {MAX_INT:.0e}); check the number, and write large "
                                   f"physical values in floating point (e.g. 1.0e20)")
        return v

    def describe(self, node: Node) -> str:
        """'a list', 'a mapping', 'the string 'x'', 'the number 3', 'null', 'true'..."""
        if isinstance(node, MappingNode):
            return "a mapping"
        if isinstance(node, SequenceNode):
            return "a list"
        v = self.scalar(node)
        if v is None:
            return "null (empty)"
        if isinstance(v, bool):
            return f"the boolean {str(v).lower()}"
        if isinstance(v, (int, float)):
            return f"the number {v!r}"
        if isinstance(v, str):
            return f"the string {v!r}"
        return f"{type(v).__name__} {v!r}"

    def plain(self, node: Node, where: str):
        """Free-form value (the ``paper`` section): plain Python, duplicate keys rejected. Counts the
        values it builds, so that YAML aliases that expand exponentially (an alias bomb) stop early."""
        self.plain_nodes += 1
        if self.plain_nodes > MAX_PLAIN_VALUES:
            raise self.error(node, f"'{where.split('.')[0] or where}' expands to more than {MAX_PLAIN_VALUES} "
                                   f"values (YAML aliases that repeat each other?); write the block out "
                                   f"without nested aliases")
        if isinstance(node, MappingNode):
            self.flatten(node)
            out: dict = {}
            lines: dict = {}
            for k, v in node.value:
                key = self.plain(k, where)
                try:
                    hash(key)
                except TypeError:
                    raise self.error(k, f"a key {_in(where)} must be a plain value, not "
                                        f"{self.describe(k)}") from None
                if key in out:
                    raise self.error(k, f"key '{key}' appears twice {_in(where)} (first at line "
                                        f"{lines[key]}); remove one of them")
                lines[key] = _line(k)
                self.mark(f"{where}.{key}" if where else str(key), k)   # for a block validator's messages
                out[key] = self.plain(v, f"{where}.{key}" if where else str(key))
            return out
        if isinstance(node, SequenceNode):
            return [self.plain(v, f"{where}[{i}]") for i, v in enumerate(node.value)]
        return self.scalar(node)

    def flatten(self, node: MappingNode) -> None:
        """Apply YAML merge keys (``<<: *anchor``) in place."""
        try:
            self._constructor.flatten_mapping(node)
        except ConstructorError as exc:
            line = (exc.problem_mark or node.start_mark).line + 1
            raise StudyError(f"{self.label}:{line}: bad merge key '<<': {exc.problem}; merge a "
                             f"mapping anchor (<<: *name)") from None

    def is_null(self, node: Node) -> bool:
        return isinstance(node, ScalarNode) and node.tag == _NULL

    # ---------------------------------------------------------------- typed values
    def mapping(self, node: Node, where: str, key: str | None = None,
                owner: Node | None = None) -> "_Map":
        """``node`` as a :class:`_Map`; ``owner`` is its key node (missing keys are reported there)."""
        if not isinstance(node, MappingNode):
            what = _key(key, where.rpartition(".")[0]) if key else f"'{where}'" if where else "the study"
            raise self.error(node, f"{what} must be a mapping (indented 'name: value' lines), got "
                                   f"{self.describe(node)}; write it as a mapping")
        return _Map(self, node, where, owner)

    def sequence(self, node: Node, key: str, where: str, hint: str) -> list[Node]:
        if not isinstance(node, SequenceNode):
            raise self.error(node, f"{_key(key, where)} must be a list, got {self.describe(node)}; "
                                   f"write it as a list, e.g. {hint}")
        return list(node.value)

    def string(self, node: Node, key: str, where: str, hint: str, nonempty: bool = True) -> str:
        v = self.scalar(node) if isinstance(node, ScalarNode) else None
        if not isinstance(node, ScalarNode) or not isinstance(v, str):
            raise self.error(node, f"{_key(key, where)} must be a string, got {self.describe(node)}; "
                                   f"e.g. {hint} (quote it if it looks like a number or true/false)")
        if nonempty and not v.strip():
            raise self.error(node, f"{_key(key, where)} must not be empty; e.g. {hint}")
        return v

    def ident(self, node: Node, key: str, where: str, hint: str, what: str = "name") -> str:
        v = self.string(node, key, where, hint)
        if not IDENTIFIER.match(v):
            wide = next((ch for ch in v if ord(ch) > 127), None)
            if wide is not None:     # a letter to Python, but names are ASCII (columns, keys, other tools)
                raise self.error(node, f"{_key(key, where)}: {what} {v!r} has the non-ASCII character "
                                       f"{wide!r}; names are ASCII only: letters A-Z and a-z, digits and '_' "
                                       f"(not starting with a digit), e.g. {hint}")
            raise self.error(node, f"{_key(key, where)}: {what} {v!r} is not an identifier; use ASCII "
                                   f"letters (A-Z, a-z), digits and '_' (not starting with a digit), e.g. {hint}")
        return v

    def number(self, node: Node, key: str, where: str, hint: str, *, positive: bool = False,
               nonzero: bool = False) -> float:
        v = self.scalar(node) if isinstance(node, ScalarNode) else None
        if (not isinstance(node, ScalarNode) or isinstance(v, bool)
                or not isinstance(v, (int, float))):
            extra = ""
            if isinstance(v, str):
                extra = " (remove the quotes or units)"
            raise self.error(node, f"{_key(key, where)} must be a number, got {self.describe(node)}"
                                   f"{extra}; e.g. {hint}")
        v = float(v)
        if not math.isfinite(v):
            raise self.error(node, f"{_key(key, where)} must be finite, got {v}; e.g. {hint}")
        if positive and v <= 0:
            raise self.error(node, f"{_key(key, where)} must be > 0, got {v:g}; e.g. {hint}")
        if nonzero and v == 0:
            raise self.error(node, f"{_key(key, where)} must not be 0; e.g. {hint}")
        return v

    def integer(self, node: Node, key: str, where: str, hint: str, minimum: int | None = None) -> int:
        v = self.scalar(node) if isinstance(node, ScalarNode) else None
        if not isinstance(node, ScalarNode) or isinstance(v, bool) or not isinstance(v, int):
            raise self.error(node, f"{_key(key, where)} must be an integer, got "
                                   f"{self.describe(node)}; e.g. {hint}")
        if minimum is not None and v < minimum:
            raise self.error(node, f"{_key(key, where)} must be ≥ {minimum}, got {v}; e.g. {hint}")
        return v

    def boolean(self, node: Node, key: str, where: str, hint: str) -> bool:
        v = self.scalar(node) if isinstance(node, ScalarNode) else None
        if not isinstance(v, bool):
            raise self.error(node, f"{_key(key, where)} must be true or false, got "
                                   f"{self.describe(node)}; e.g. {hint}")
        return v

    def choice(self, node: Node, key: str, where: str, allowed, what: str) -> str:
        v = self.string(node, key, where, f"{key}: {allowed[0]}")
        if v not in allowed:
            raise self.error(node, f"{_key(key, where)}: unknown {what} {v!r}{_suggest(v, allowed)} "
                                   f"(allowed: {_fmt_list(allowed)})")
        return v

    def name_in(self, node: Node, key: str, where: str, pool: Mapping, what: str, hint: str) -> str:
        """A reference to a study parameter or a metric, checked against ``pool``."""
        v = self.string(node, key, where, hint)
        if v not in pool:
            raise self.error(node, f"{_key(key, where)} names an unknown {what} {v!r}"
                                   f"{_suggest(v, pool)} (known {what}s: {_fmt_list(pool)}); "
                                   f"use one of them or define it")
        return v

    def names_in(self, node: Node, key: str, where: str, pool: Mapping, what: str,
                 hint: str) -> list[str]:
        items = self.sequence(node, key, where, hint)
        if not items:
            raise self.error(node, f"{_key(key, where)} must list at least one {what}; e.g. {hint}")
        out: list[str] = []
        for item in items:
            v = self.name_in(item, key, where, pool, what, hint)
            if v in out:
                raise self.error(item, f"{_key(key, where)} lists {what} {v!r} twice; remove one")
            out.append(v)
        return out

    def pair(self, node: Node, key: str, where: str, hint: str, conv: Callable) -> tuple:
        items = self.sequence(node, key, where, hint)
        if len(items) != 2:
            raise self.error(node, f"{_key(key, where)} must be a pair [lo, hi], got {len(items)} "
                                   f"value(s); e.g. {hint}")
        return tuple(conv(item, key, where, hint) for item in items)


class _Map:
    """A YAML mapping with its key nodes (for line numbers); rejects duplicate and unknown keys."""

    def __init__(self, p: _Parser, node: MappingNode, where: str, owner: Node | None = None) -> None:
        p.flatten(node)   # support '<<: *anchor' merges
        self.p, self.node, self.where = p, node, where
        self.owner = owner if owner is not None else node
        self.items: dict[str, tuple[Node, Node]] = {}
        for k, v in node.value:
            kv = p.scalar(k) if isinstance(k, ScalarNode) else None
            if not isinstance(kv, str):
                raise p.error(k, f"keys {_in(where)} must be names, got {p.describe(k)}; "
                                 f"quote the key if it is a name that looks like a number or boolean")
            if kv in self.items:
                raise p.error(k, f"key '{kv}' appears twice {_in(where)} (first at line "
                                 f"{_line(self.items[kv][0])}); remove or rename one of them")
            self.items[kv] = (k, v)

    def __contains__(self, key: str) -> bool:
        return key in self.items

    def keys(self) -> list[str]:
        return list(self.items)

    def sub(self, key: str) -> str:
        return f"{self.where}.{key}" if self.where else key

    def allow(self, allowed) -> None:
        for key, (knode, _) in self.items.items():
            if key not in allowed:
                raise self.p.error(knode, f"key '{key}' is not allowed {_in(self.where)}"
                                          f"{_suggest(key, allowed)} (allowed: {_fmt_list(allowed)})")

    def need(self, key: str, hint: str) -> Node:
        if key not in self.items:
            raise self.p.error(self.owner, f"key '{key}' is missing {_in(self.where)}; add it, "
                                          f"e.g. {hint}")
        return self.items[key][1]

    def opt(self, key: str) -> Node | None:
        """The value node, or None when absent or null (then the default applies)."""
        if key not in self.items:
            return None
        v = self.items[key][1]
        return None if self.p.is_null(v) else v

    def key_node(self, key: str) -> Node:
        return self.items[key][0]

    def entries(self):
        """(key, key node, value node) in file order."""
        return [(k, kn, vn) for k, (kn, vn) in self.items.items()]

    # shorthands --------------------------------------------------------------
    def text(self, key: str, default: str = "") -> str:
        n = self.opt(key)
        return default if n is None else self.p.string(n, key, self.where, f'{key}: "..."',
                                                       nonempty=False)

    def num(self, key: str, default, hint: str, **kw):
        n = self.opt(key)
        return default if n is None else self.p.number(n, key, self.where, hint, **kw)

    def int_(self, key: str, default, hint: str, minimum: int | None = None):
        n = self.opt(key)
        return default if n is None else self.p.integer(n, key, self.where, hint, minimum)


# ============================================================================ sections
_TOP_KEYS = ("name", "description", "fmu", "fmu_options", "parameters", "fixed", "scenario", "metrics",
             "constraints", "stages", "execution", "paper")


def _parse_parameters(p: _Parser, top: _Map) -> dict[str, Parameter]:
    node = top.need("parameters", "parameters: {c: {variable: c_y, unit: N/m}}")
    m = p.mapping(node, "parameters", "parameters", top.key_node("parameters"))
    if not m.items:
        raise p.error(node, "key 'parameters' at the top level must define at least one study "
                            "parameter; e.g. parameters: {c: {variable: c_y, unit: N/m}}")
    out: dict[str, Parameter] = {}
    seen: dict[str, str] = {}
    for name, knode, vnode in m.entries():
        p.ident(knode, name, "parameters", "c: {variable: c_y}", "parameter name")
        where = f"parameters.{name}"
        pm = p.mapping(vnode, where, name, knode)
        pm.allow(("variable", "unit", "scale", "offset", "description"))
        var = p.string(pm.need("variable", "variable: c_y"), "variable", where, "variable: c_y")
        p.mark(f"{where}.variable", pm.items["variable"][1])
        if var in seen:
            raise p.error(pm.items["variable"][1],
                          f"key 'variable' {_in(where)}: FMU variable {var!r} is already set by "
                          f"parameter '{seen[var]}'; map each FMU variable to one parameter")
        seen[var] = name
        out[name] = Parameter(
            name=name, variable=var, unit=pm.text("unit"),
            scale=pm.num("scale", 1.0, "scale: 1.0", nonzero=True),
            offset=pm.num("offset", 0.0, "offset: 0.0"),
            description=pm.text("description"))
    return out


def _parse_fixed(p: _Parser, top: _Map) -> tuple[dict[str, float | int | bool], dict[str, FixedValue]]:
    """``fixed``: name -> number or true/false (the FMU's unit), or name -> ``{value, unit, scale, offset,
    description}`` (the study's unit, converted like a study parameter). Returns the FMU values and the
    entries written with units."""
    node = top.opt("fixed")
    if node is None:
        return {}, {}
    m = p.mapping(node, "fixed", "fixed")
    out: dict[str, float | int | bool] = {}
    units: dict[str, FixedValue] = {}
    for name, knode, vnode in m.entries():
        p.mark(f"fixed.{name}", knode)
        if isinstance(vnode, MappingNode):
            w = f"fixed.{name}"
            fm = p.mapping(vnode, w, name, knode)
            fm.allow(("value", "unit", "scale", "offset", "description"))
            hint = f"{name}: {{value: 823.2, unit: N/mm, scale: 1000}}"
            value = p.number(fm.need("value", "value: 823.2  (in the study's unit; FMU value = scale × "
                                              "value + offset)"), "value", w, "value: 823.2")
            fv = FixedValue(name=name, value=value, unit=fm.text("unit"),
                            scale=fm.num("scale", 1.0, "scale: 1000  (e.g. N/mm -> N/m)", nonzero=True),
                            offset=fm.num("offset", 0.0, "offset: 0.0"), description=fm.text("description"))
            fmu_value = fv.to_fmu()
            if not math.isfinite(fmu_value):
                raise p.error(vnode, f"key '{name}' in 'fixed': scale × value + offset is not finite "
                                     f"({fv.scale:g} × {fv.value:g} + {fv.offset:g}); check the numbers, "
                                     f"e.g. {hint}")
            out[name] = fmu_value
            units[name] = fv
            continue
        v = p.scalar(vnode) if isinstance(vnode, ScalarNode) else None
        if isinstance(v, bool):
            out[name] = v
            continue
        if isinstance(v, int):
            out[name] = v
            continue
        out[name] = p.number(vnode, name, "fixed", f"{name}: 411  (a number, true/false, or "
                                                   f"{{value: 0.411, unit: kN, scale: 1000}})")
    return out, units


def _parse_scenario(p: _Parser, top: _Map) -> Scenario:
    node = top.need("scenario", "scenario: {stop_time: 12}")
    m = p.mapping(node, "scenario", "scenario", top.key_node("scenario"))
    m.allow(("stop_time", "step", "inputs", "description", "refine_peaks", "refine_factor"))
    stop = p.number(m.need("stop_time", "stop_time: 12  (simulation end time in s, > 0)"),
                    "stop_time", "scenario", "stop_time: 12  (simulation end time in s)",
                    positive=True)
    step = m.num("step", None, "step: 0.01  (communication step in s), or null for one doStep",
                 positive=True)
    if step is not None and step > stop:
        raise p.error(m.items["step"][1], f"key 'step' in 'scenario' ({step:g} s) is longer than "
                                          f"stop_time ({stop:g} s); use a smaller step or null")
    inputs: dict[str, float] = {}
    inode = m.opt("inputs")
    if inode is not None:
        im = p.mapping(inode, "scenario.inputs", "inputs")
        for name, knode, vnode in im.entries():
            p.mark(f"scenario.inputs.{name}", knode)
            inputs[name] = p.number(vnode, name, "scenario.inputs", f"{name}: 20")
    refine = False
    rnode = m.opt("refine_peaks")
    if rnode is not None:
        refine = p.boolean(rnode, "refine_peaks", "scenario", "refine_peaks: true")
        p.mark("scenario.refine_peaks", rnode)
        if refine and step is None:
            raise p.error(rnode, "key 'refine_peaks' in 'scenario' refines sampled outputs, but step is null "
                                 "(one doStep, no samples); set step: 0.01 (the output interval) or remove "
                                 "refine_peaks")
    factor = m.int_("refine_factor", 10, "refine_factor: 10", minimum=2)
    if "refine_factor" in m and m.opt("refine_factor") is not None and not refine:
        raise p.error(m.items["refine_factor"][1], "key 'refine_factor' in 'scenario' has no effect without "
                                                   "refine_peaks: true; add it or remove refine_factor")
    return Scenario(stop_time=stop, step=step, inputs=inputs, description=m.text("description"),
                    refine_peaks=refine, refine_factor=factor)


def _parse_metrics(p: _Parser, top: _Map, parameters: Mapping) -> dict[str, Metric]:
    node = top.need("metrics", "metrics: {max_y: {output: y_max}}")
    m = p.mapping(node, "metrics", "metrics")
    if not m.items:
        raise p.error(node, "key 'metrics' at the top level must define at least one metric; "
                            "e.g. metrics: {max_y: {output: y_max}}")
    out: dict[str, Metric] = {}
    for name, knode, vnode in m.entries():
        p.ident(knode, name, "metrics", "max_y: {output: y_max}", "metric name")
        if name in parameters:
            raise p.error(knode, f"key '{name}' in 'metrics': '{name}' is already a study parameter; "
                                 f"rename the metric (parameters and metrics share result tables)")
        where = f"metrics.{name}"
        mm = p.mapping(vnode, where, name, knode)
        mm.allow(("output", "reduce", "unit", "scale", "offset", "missing_below", "settle_tol", "description"))
        output = p.string(mm.need("output", "output: y_max  (an FMU output variable)"), "output",
                          where, "output: y_max")
        p.mark(f"{where}.output", mm.items["output"][1])
        rnode = mm.opt("reduce")
        reduce = "final" if rnode is None else p.choice(rnode, "reduce", where, REDUCTIONS,
                                                        "reduction")
        # no number is suggested: a band depends on the output's unit and size, which the loader cannot know
        band = (f"settle_tol: BAND, the largest |{output}| that counts as settled, in the FMU's unit of {output} "
                f"(`fmusa inspect` shows it; e.g. a hundredth of its peak)")
        tol = mm.num("settle_tol", None, band, positive=True)
        if reduce == "settle" and tol is None:
            raise p.error(mm.items["reduce"][1], f"{_key('reduce', where)}: 'settle' (the time since which "
                                                 f"|{output}| stays within a band) needs the band; add {band}")
        if tol is not None and reduce != "settle":
            raise p.error(mm.items["settle_tol"][1], f"{_key('settle_tol', where)} applies to reduce: settle "
                                                     f"only, but the reduction is '{reduce}'; remove it or "
                                                     f"set reduce: settle")
        out[name] = Metric(
            name=name, output=output, reduce=reduce, unit=mm.text("unit"),
            scale=mm.num("scale", 1.0, "scale: 1000  (e.g. m -> mm)", nonzero=True),
            offset=mm.num("offset", 0.0, "offset: 0.0"),
            missing_below=mm.num("missing_below", None, "missing_below: 0"),
            description=mm.text("description"), settle_tol=tol)
    return out


def _parse_constraints(p: _Parser, top: _Map, metrics: Mapping) -> list[Constraint]:
    node = top.opt("constraints")
    if node is None:
        return []
    items = p.sequence(node, "constraints", "", "constraints: [{name: translation, metric: max_y, "
                                                "max: 5.0e-4}]")
    out: list[Constraint] = []
    first: dict[str, Node] = {}
    for i, item in enumerate(items):
        where = f"constraints[{i}]"
        cm = p.mapping(item, where)
        cm.allow(("name", "metric", "max", "min", "required", "description"))
        nnode = cm.need("name", "name: translation")
        name = p.ident(nnode, "name", where, "name: translation", "constraint name")
        if name in first:
            raise p.error(nnode, f"key 'name' {_in(where)}: constraint name {name!r} is already used "
                                 f"at line {_line(first[name])}; give each constraint its own name")
        first[name] = nnode
        metric = p.name_in(cm.need("metric", "metric: max_y"), "metric", where, metrics, "metric",
                           "metric: max_y")
        hi = cm.num("max", None, "max: 5.0e-4")
        lo = cm.num("min", None, "min: 0.0")
        rnode = cm.opt("required")
        required = False if rnode is None else p.boolean(rnode, "required", where, "required: true")
        if hi is None and lo is None and not required:
            raise p.error(item, f"constraint '{name}' {_in(where)} checks nothing; add a key 'max', "
                                f"a key 'min' or 'required: true'")
        if hi is not None and lo is not None and lo > hi:
            raise p.error(cm.items["min"][1], f"key 'min' {_in(where)} ({lo:g}) is above key 'max' "
                                              f"({hi:g}); swap them")
        out.append(Constraint(name=name, metric=metric, max=hi, min=lo, required=required,
                              description=cm.text("description")))
    return out


def _parse_grid(p: _Parser, m: _Map, where: str, parameters: Mapping) -> GridStage:
    m.allow(("base", "exponents", "values"))
    exponents: dict[str, tuple[int, int]] = {}
    values: dict[str, list[float]] = {}
    enode = m.opt("exponents")
    if enode is not None:
        ew = f"{where}.exponents"
        em = p.mapping(enode, ew, "exponents")
        for name, knode, vnode in em.entries():
            p.name_in(knode, name, ew, parameters, "study parameter", "c: [3, 7]")
            lo, hi = p.pair(vnode, name, ew, f"{name}: [3, 7]", p.integer)
            if lo > hi:
                raise p.error(vnode, f"{_key(name, ew)} must be a range [lo, hi] with lo ≤ hi, got "
                                     f"[{lo}, {hi}]; swap them: {name}: [{hi}, {lo}]")
            exponents[name] = (lo, hi)
    vnode_all = m.opt("values")
    if vnode_all is not None:
        vw = f"{where}.values"
        vm = p.mapping(vnode_all, vw, "values")
        for name, knode, vnode in vm.entries():
            p.name_in(knode, name, vw, parameters, "study parameter", "c: [1.0e5, 1.0e6]")
            if name in exponents:
                raise p.error(knode, f"{_key(name, vw)}: parameter '{name}' also has exponents in "
                                     f"'{where}'; keep exactly one of exponents / values")
            items = p.sequence(vnode, name, vw, f"{name}: [1.0e5, 1.0e6]")
            if not items:
                raise p.error(vnode, f"{_key(name, vw)} must list at least one value; e.g. "
                                     f"{name}: [1.0e5, 1.0e6]")
            vals = [p.number(it, name, vw, f"{name}: [1.0e5, 1.0e6]") for it in items]
            if len(set(vals)) != len(vals):
                raise p.error(vnode, f"{_key(name, vw)} lists a value twice; remove duplicates")
            values[name] = vals
    if not exponents and not values:
        raise p.error(m.owner, "key 'grid' in 'stages' defines no grid points; add 'exponents' "
                               "(with 'base') or 'values', e.g. base: 25, exponents: {c: [3, 7]}")
    base = m.num("base", None, "base: 25", positive=True)
    if exponents and base is None:
        raise p.error(m.owner, f"key 'base' is missing {_in(where)}; exponents need it, add it, "
                              f"e.g. base: 25")
    if exponents and base == 1.0:
        raise p.error(m.items["base"][1], f"{_key('base', where)} must not be 1 (every power would "
                                          f"be 1); e.g. base: 25")
    _check_grid_size(p, m, where, base, exponents, values)
    return GridStage(base=base, exponents=exponents, values=values)


#: Most points a grid may have: far beyond any study run on a few cores, and small enough that the
#: grid itself (its points, runs.csv) is never what exhausts time or memory.
MAX_GRID_POINTS = 1_000_000


def _check_grid_size(p: _Parser, m: _Map, where: str, base: float | None, exponents: Mapping,
                     values: Mapping) -> None:
    """Every power of the base a finite double, and the whole grid at most MAX_GRID_POINTS points."""
    total = 1
    for name, (lo, hi) in exponents.items():
        node = m.items["exponents"][1]
        for k in (lo, hi):
            try:
                x = float(base) ** k
            except OverflowError:
                x = math.inf
            if not math.isfinite(x) or x == 0.0:
                raise p.error(node, f"{_key(name, where + '.exponents')}: {base:g}^{k} is not a finite, "
                                    f"nonzero double; narrow the range of exponents [{lo}, {hi}]")
        total *= hi - lo + 1
    for vals in values.values():
        total *= len(vals)
    if total > MAX_GRID_POINTS:
        raise p.error(m.owner, f"'{where}' has {total} points, more than {MAX_GRID_POINTS}; use fewer "
                               f"exponents or values (a coarse grid, then the region of interest and the "
                               f"search, is the method)")


def _parse_roi(p: _Parser, m: _Map, where: str, parameters: Mapping) -> RoiStage:
    m.allow(("manual", "at"))
    at = None
    anode = m.opt("at")
    if anode is not None and not p.is_null(anode):
        aw = f"{where}.at"
        am = p.mapping(anode, aw, "at")
        at = {}
        for name, knode, vnode in am.entries():
            p.name_in(knode, name, aw, parameters, "study parameter", "load: 10")
            at[name] = p.number(vnode, name, aw, f"{name}: 10")
        if not at:
            at = None
    node = m.opt("manual")
    if node is None:
        return RoiStage(manual=None, at=at)
    mw = f"{where}.manual"
    mm = p.mapping(node, mw, "manual")
    manual: dict[str, tuple[float, float]] = {}
    for name, knode, vnode in mm.entries():
        p.name_in(knode, name, mw, parameters, "study parameter", "c: [3.91e5, 9.77e6]")
        lo, hi = p.pair(vnode, name, mw, f"{name}: [3.91e5, 9.77e6]", p.number)
        if lo > hi:
            raise p.error(vnode, f"{_key(name, mw)} must be [lo, hi] with lo ≤ hi, got "
                                 f"[{lo:g}, {hi:g}]; swap them")
        manual[name] = (lo, hi)
    if not manual:
        raise p.error(node, f"{_key('manual', where)} is empty; give [lo, hi] per parameter, "
                            f"e.g. manual: {{c: [3.91e5, 9.77e6]}}, or null for the automatic region")
    return RoiStage(manual=manual, at=at)


def _parse_search(p: _Parser, m: _Map, where: str, parameters: Mapping, metrics: Mapping,
                  constraints: Sequence[Constraint]) -> SearchStage:
    m.allow(("inner", "outer", "inner_rtol", "response_rtol", "response_atol", "response", "max_outer",
             "warm_start", "parallel"))
    inner = p.name_in(m.need("inner", "inner: c"), "inner", where, parameters, "study parameter",
                      "inner: c")
    onode = m.opt("outer")       # optional: without it, one bisection of 'inner' inside the region
    outer = None
    if onode is not None:
        outer = p.name_in(onode, "outer", where, parameters, "study parameter", "outer: d")
        if outer == inner:
            raise p.error(onode, f"{_key('outer', where)} is the same parameter as 'inner' ({inner!r}); "
                                 f"search two different parameters, or remove 'outer' to search '{inner}' alone")
    wnode = m.opt("warm_start")
    warm_start = False if wnode is None else p.boolean(wnode, "warm_start", where, "warm_start: true")
    if warm_start and outer is None:
        raise p.error(wnode, f"{_key('warm_start', where)}: a warm start brackets each outer level from the "
                             f"previous level's answer, but the search has no 'outer' parameter (one "
                             f"bisection); remove warm_start or add outer")
    parallel = _parse_parallel(p, m.opt("parallel"), where)
    rnode = m.opt("response")
    if rnode is not None:
        response = p.names_in(rnode, "response", where, metrics, "metric", "response: [max_y, max_v, t_eq]")
    else:   # the constrained metrics, in constraint order
        response = list(dict.fromkeys(c.metric for c in constraints))
    atol: dict[str, float] = {}
    anode = m.opt("response_atol")
    if anode is not None:
        hint = ("response_atol: 1.0e-9  (one floor for every response metric, in its unit) or "
                "response_atol: {v_end: 1.0e-9}")
        if isinstance(anode, MappingNode):
            aw = f"{where}.response_atol"
            am = p.mapping(anode, aw, "response_atol")
            for name, knode, vnode in am.entries():
                if name not in response:
                    shown = _fmt_list(response)
                    raise p.error(knode, f"{_key(name, aw)}: '{name}' is not a response metric of the search "
                                         f"(response: {shown}){_suggest(name, response)}; give floors for "
                                         f"those metrics only, or add '{name}' to 'response'")
                atol[name] = p.number(vnode, name, aw, f"{name}: 1.0e-9  (in the metric's unit, ≥ 0)")
                if atol[name] < 0:
                    raise p.error(vnode, f"{_key(name, aw)} must be ≥ 0, got {atol[name]:g}; e.g. "
                                         f"{name}: 1.0e-9")
        else:
            value = p.number(anode, "response_atol", where, hint)
            if value < 0:
                raise p.error(anode, f"{_key('response_atol', where)} must be ≥ 0, got {value:g}; e.g. {hint}")
            atol = {name: value for name in response}
    return SearchStage(
        inner=inner, outer=outer,
        inner_rtol=m.num("inner_rtol", 1e-3, "inner_rtol: 1.0e-3", positive=True),
        response_rtol=m.num("response_rtol", 1e-3, "response_rtol: 1.0e-3", positive=True),
        max_outer=m.int_("max_outer", 20, "max_outer: 20", minimum=1),
        response=response, response_atol=atol, warm_start=warm_start, parallel=parallel)


def _parse_parallel(p: _Parser, node: Node | None, where: str) -> str | int | bool:
    """search.parallel: auto (default; also true), false (the sequential search) or a number of points
    per round (an integer ≥ 1)."""
    if node is None:
        return "auto"
    hint = "parallel: auto  (points per round = the study's workers), parallel: false (one point at a time) or parallel: 16"
    v = p.scalar(node) if isinstance(node, ScalarNode) else None
    if v is True or v == "auto":
        return "auto"
    if v is False:
        return False
    if isinstance(v, int) and not isinstance(v, bool):
        if v < 1:
            raise p.error(node, f"{_key('parallel', where)} must be ≥ 1 points per round, got {v}; e.g. {hint}")
        return v
    raise p.error(node, f"{_key('parallel', where)} must be auto, false or an integer, got "
                        f"{p.describe(node)}; e.g. {hint}")


def _parse_regression(p: _Parser, m: _Map, where: str, parameters: Mapping,
                      metrics: Mapping, before: Mapping[str, object] | None = None,
                      has_search: bool = True) -> RegressionStage:
    """The regression fits the search's runs when the study has a search stage, else the grid's; that
    stage must come first (stages run in file order), so that the fit is never silently empty."""
    m.allow(("x", "y", "by", "degree"))
    before = {} if before is None else before
    source = "search" if has_search else "grid"
    if source not in before:
        what = ("the study has a 'search' stage, whose runs it fits, but it comes after 'regression'; "
                "move 'regression' below 'search'" if has_search else
                "without a 'search' stage it fits the grid runs, but no 'grid' stage comes before it; add "
                "a 'grid' stage above it (or a 'search')")
        raise p.error(m.owner, f"key 'regression' in 'stages' has no runs to fit: {what}")
    x = p.name_in(m.need("x", "x: c"), "x", where, parameters, "study parameter", "x: c")
    y = p.names_in(m.need("y", "y: [max_y, max_v]"), "y", where, metrics, "metric",
                   "y: [max_y, max_v]")
    by = None
    bnode = m.opt("by")
    if bnode is not None:
        by = p.name_in(bnode, "by", where, parameters, "study parameter", "by: d")
        if by == x:
            raise p.error(bnode, f"{_key('by', where)} is the same parameter as 'x' ({x!r}); use "
                                 f"another parameter or null")
    degree = m.int_("degree", 3, "degree: 3", minimum=1)
    if source == "grid":
        xs = before["grid"].points().get(x)
        if xs is not None and len(xs) < degree + 1:
            raise p.error(m.owner, f"key 'regression' in 'stages' fits the grid runs (there is no 'search' "
                                   f"stage), but the grid has {len(xs)} value(s) of '{x}', too few for a "
                                   f"degree-{degree} polynomial; give the grid at least {degree + 1} values of "
                                   f"'{x}' or lower 'degree'")
    return RegressionStage(x=x, y=y, by=by, degree=degree, source=source)


def _parse_sensitivity(p: _Parser, m: _Map, where: str, metrics: Mapping,
                       fixed: Mapping) -> SensitivityStage:
    m.allow(("methods", "n", "morris_trajectories", "seed", "outputs", "parameters"))
    methods = list(METHODS)
    mnode = m.opt("methods")
    if mnode is not None:
        items = p.sequence(mnode, "methods", where, "methods: [morris, sobol]")
        if not items:
            raise p.error(mnode, f"{_key('methods', where)} is empty; e.g. methods: [morris, sobol]")
        methods = []
        for it in items:
            v = p.choice(it, "methods", where, METHODS, "method")
            if v in methods:
                raise p.error(it, f"{_key('methods', where)} lists {v!r} twice; remove one")
            methods.append(v)
    outputs = p.names_in(m.need("outputs", "outputs: [max_y, max_v]"), "outputs", where, metrics,
                         "metric", "outputs: [max_y, max_v]")
    pw = f"{where}.parameters"
    pnode = m.need("parameters", "parameters: {c_x: {variable: c_x, bounds: [1.0e5, 1.0e7]}}")
    pm = p.mapping(pnode, pw, "parameters")
    if not pm.items:
        raise p.error(pnode, f"{_key('parameters', where)} is empty; e.g. parameters: "
                             f"{{c_x: {{variable: c_x, bounds: [1.0e5, 1.0e7]}}}}")
    params: dict[str, SensitivityParameter] = {}
    seen: dict[str, str] = {}
    for name, knode, vnode in pm.entries():
        p.ident(knode, name, pw, "c_x: {variable: c_x, bounds: [1.0e5, 1.0e7]}", "parameter name")
        if name in metrics:
            raise p.error(knode, f"{_key(name, pw)}: '{name}' is already a metric; rename the "
                                 f"parameter (parameters and metrics share result tables)")
        w = f"{pw}.{name}"
        sm = p.mapping(vnode, w, name, knode)
        sm.allow(("variable", "bounds", "distribution", "unit"))
        varnode = sm.need("variable", f"variable: {name}")
        var = p.string(varnode, "variable", w, f"variable: {name}")
        p.mark(f"{w}.variable", varnode)
        if var in seen:
            raise p.error(varnode, f"{_key('variable', w)}: FMU variable {var!r} is already varied by "
                                   f"'{seen[var]}'; vary each FMU variable once")
        if var in fixed:
            raise p.error(varnode, f"{_key('variable', w)}: FMU variable {var!r} is also in 'fixed', "
                                   f"which would override the sample; remove it from 'fixed'")
        seen[var] = name
        dnode = sm.opt("distribution")
        dist = "uniform" if dnode is None else p.choice(dnode, "distribution", w, DISTRIBUTIONS,
                                                        "distribution")
        bnode = sm.need("bounds", "bounds: [1.0e5, 1.0e7]")
        lo, hi = p.pair(bnode, "bounds", w, "bounds: [1.0e5, 1.0e7]", p.number)
        if not lo < hi:
            raise p.error(bnode, f"{_key('bounds', w)} must be [lo, hi] with lo < hi, got "
                                 f"[{lo:g}, {hi:g}]; "
                                 + ("swap them" if lo > hi else "widen the range"))
        if dist == "loguniform" and lo <= 0:
            raise p.error(bnode, f"{_key('bounds', w)}: a loguniform distribution needs lo > 0, got "
                                 f"[{lo:g}, {hi:g}]; use a positive lower bound or distribution: "
                                 f"uniform")
        params[name] = SensitivityParameter(name=name, variable=var, bounds=(lo, hi),
                                            distribution=dist, unit=sm.text("unit"))
    return SensitivityStage(
        methods=methods,
        n=m.int_("n", 1024, "n: 1024", minimum=1),
        morris_trajectories=m.int_("morris_trajectories", 20, "morris_trajectories: 20", minimum=2),
        seed=m.int_("seed", 1, "seed: 1", minimum=0),
        outputs=outputs, parameters=params)


def _parse_stages(p: _Parser, top: _Map, parameters: Mapping, metrics: Mapping,
                  fixed: Mapping, constraints: Sequence[Constraint] = ()) -> dict[str, object]:
    node = top.need("stages", "stages: {sensitivity: {...}}  (one or more of: "
                              + ", ".join(STAGE_NAMES) + ")")
    m = p.mapping(node, "stages", "stages")
    m.allow(STAGE_NAMES)
    if not m.items:
        raise p.error(node, f"key 'stages' at the top level is empty; add at least one of: "
                            f"{_fmt_list(STAGE_NAMES)}")
    out: dict[str, object] = {}
    for name, knode, vnode in m.entries():
        where = f"stages.{name}"
        if p.is_null(vnode):   # e.g. 'roi:' with nothing under it: all defaults
            sm = _Map(p, MappingNode("tag:yaml.org,2002:map", [], vnode.start_mark, vnode.end_mark),
                      where, knode)
        else:
            sm = p.mapping(vnode, where, name, knode)
        if name == "grid":
            out[name] = _parse_grid(p, sm, where, parameters)
        elif name == "roi":
            stage = _parse_roi(p, sm, where, parameters)
            if stage.manual is None and "grid" not in out:
                raise p.error(knode, "key 'roi' in 'stages': without 'manual' the region is computed "
                                     "from the grid, but no 'grid' stage comes before it; add a "
                                     "'grid' stage above it or give roi: {manual: {...}}")
            out[name] = stage
        elif name == "search":
            if "roi" not in out:
                raise p.error(knode, "key 'search' in 'stages': the search needs a region of "
                                     "interest, but no 'roi' stage comes before it; add 'roi:' "
                                     "above 'search'")
            stage = _parse_search(p, sm, where, parameters, metrics, constraints)
            for q in (stage.inner, stage.outer):
                if q is not None and q in (out["roi"].at or {}):
                    raise p.error(knode, f"key 'search' in 'stages' varies '{q}', so 'stages.roi.at' cannot "
                                         f"hold it; remove {q} from 'at'")
            manual = out["roi"].manual
            if manual is not None:
                for q in (stage.inner, stage.outer):
                    if q is not None and q not in manual:
                        raise p.error(knode, f"key 'search' in 'stages' varies '{q}', but "
                                             f"'stages.roi.manual' gives no range for it; add "
                                             f"{q}: [lo, hi] there")
            out[name] = stage
        elif name == "regression":
            out[name] = _parse_regression(p, sm, where, parameters, metrics, out, "search" in m)
        elif name == "sensitivity":
            out[name] = _parse_sensitivity(p, sm, where, metrics, fixed)
    if "grid" in out:
        grid = out["grid"]
        roi = out.get("roi")
        if roi is not None and roi.at and roi.manual is None:
            axes = grid.points()
            for q, v in roi.at.items():
                if q in axes and not any(math.isclose(v, g, rel_tol=1e-12) for g in axes[q]):
                    raise p.error(m.key_node("roi"), f"'stages.roi.at' holds {q} = {v:g}, which is not one of "
                                                     f"its grid values ({', '.join(f'{g:g}' for g in axes[q])}): "
                                                     f"the region is found from the grid runs there; pick one")
        missing = [q for q in parameters if q not in grid.exponents and q not in grid.values]
        if missing:
            raise p.error(m.key_node("grid"),
                          f"key 'grid' in 'stages' gives no values for study parameter(s) "
                          f"{', '.join(missing)}; add {missing[0]}: [lo, hi] under 'exponents' or "
                          f"{missing[0]}: [...] under 'values'")
    if "roi" in out and "search" not in out:
        raise p.error(m.key_node("roi"), "key 'roi' in 'stages': the region of interest is "
                                         "spanned by the search's inner (and outer) parameters, but "
                                         "there is no 'search' stage; add one after 'roi' or remove "
                                         "'roi'")
    return out


def _parse_execution(p: _Parser, top: _Map) -> Execution:
    node = top.opt("execution")
    if node is None:
        return Execution()
    m = p.mapping(node, "execution", "execution")
    m.allow(("workers", "scheduler", "timeout_s", "check_fmu_steps", "start_method", "worker_max_runs",
             "worker_max_memory_mb", "retries"))
    snode = m.opt("scheduler")
    scheduler = None if snode is None else p.string(snode, "scheduler", "execution",
                                                    "scheduler: tcp://127.0.0.1:8786")
    cnode = m.opt("check_fmu_steps")      # auto (None): every FMU but our own
    check_steps = None
    if cnode is not None and not (isinstance(cnode.value, str) and cnode.value.strip().lower() == "auto"):
        check_steps = p.boolean(cnode, "check_fmu_steps", "execution", "check_fmu_steps: auto  (or true, false)")
    mnode = m.opt("start_method")
    start_method = None if mnode is None else p.choice(mnode, "start_method", "execution", START_METHODS,
                                                       "start method")
    return Execution(
        workers=m.int_("workers", None, "workers: 4  (or null for all cores)", minimum=1),
        scheduler=scheduler,
        timeout_s=m.num("timeout_s", 60.0, "timeout_s: 60", positive=True),
        check_fmu_steps=check_steps,
        start_method=start_method,
        worker_max_runs=m.int_("worker_max_runs", None, "worker_max_runs: 1000  (or null: never)", minimum=1),
        worker_max_memory_mb=m.num("worker_max_memory_mb", None, "worker_max_memory_mb: 2000  (or null: no limit)",
                                   positive=True),
        retries=m.int_("retries", 1, "retries: 1  (0: a run whose worker died fails at once)", minimum=0))


_INTERFACE_ALIASES = {"auto": "auto", "cosimulation": "co-simulation", "cs": "co-simulation",
                      "modelexchange": "model-exchange", "me": "model-exchange"}


def _parse_fmu_options(p: _Parser, top: _Map, scenario: Scenario) -> FMUOptions:
    node = top.opt("fmu_options")
    if node is None:
        return FMUOptions()
    w = "fmu_options"
    m = p.mapping(node, w, "fmu_options")
    m.allow(("interface", "solver", "relative_tolerance", "step_size"))
    for key, knode, _ in m.entries():
        p.mark(f"{w}.{key}", knode)
    interface = "auto"
    inode = m.opt("interface")
    if inode is not None:
        text = p.string(inode, "interface", w, "interface: model-exchange")
        interface = _INTERFACE_ALIASES.get(re.sub(r"[\s_-]", "", text.lower()))
        if interface is None:
            raise p.error(inode, f"{_key('interface', w)}: unknown interface {text!r}"
                                 f"{_suggest(text, INTERFACES)} (allowed: {_fmt_list(INTERFACES)}; auto runs "
                                 f"co-simulation when the FMU has it, else model exchange)")
    solver = None
    snode = m.opt("solver")
    if snode is not None:
        text = p.string(snode, "solver", w, "solver: CVode")
        solver = {s.lower(): s for s in SOLVERS}.get(text.lower())
        if solver is None:
            raise p.error(snode, f"{_key('solver', w)}: unknown solver {text!r}{_suggest(text, SOLVERS)} "
                                 f"(allowed: {_fmt_list(SOLVERS)}, fmpy's solvers for model exchange FMUs)")
    rtol = m.num("relative_tolerance", None, "relative_tolerance: 1.0e-6", positive=True)
    if rtol is not None and rtol >= 1:
        raise p.error(m.items["relative_tolerance"][1],
                      f"{_key('relative_tolerance', w)} must be < 1 (a relative tolerance), got {rtol:g}; "
                      f"e.g. relative_tolerance: 1.0e-6")
    step_size = m.num("step_size", None, "step_size: 1.0e-3  (s)", positive=True)
    if interface == "co-simulation":
        for key, val in (("solver", solver), ("step_size", step_size)):
            if val is not None:
                raise p.error(m.items[key][1],
                              f"{_key(key, w)} applies to model exchange only: a co-simulation FMU integrates "
                              f"with its own solver; remove '{key}' or set interface: model-exchange")
    if step_size is not None:
        snode = m.items["step_size"][1]
        if step_size > scenario.stop_time:
            raise p.error(snode, f"{_key('step_size', w)} ({step_size:g} s) is longer than scenario.stop_time "
                                 f"({scenario.stop_time:g} s); use a smaller step_size or null")
        if scenario.step is not None:
            k = scenario.step / step_size
            if abs(k - round(k)) > 1e-9 * max(1.0, k) or round(k) < 1:
                good = scenario.step / max(1, math.ceil(k))
                raise p.error(snode, f"{_key('step_size', w)} ({step_size:g} s) must divide scenario.step "
                                     f"({scenario.step:g} s) into whole steps, so that the outputs are sampled "
                                     f"on solver steps; e.g. step_size: {good:.6g}")
    return FMUOptions(interface=interface, solver=solver, relative_tolerance=rtol, step_size=step_size)


def _parse_fmu(p: _Parser, top: _Map, base_dir: Path) -> Path | None:
    node = top.opt("fmu")
    if node is None:
        return None
    text = p.string(node, "fmu", "", "fmu: default  (or a path to an .fmu file)")
    p.mark("fmu", node)
    if text == "default":
        return None
    path = Path(os.path.expanduser(text))
    if not path.is_absolute():
        path = base_dir / path
    path = path.resolve()
    if not path.exists():
        raise p.error(node, f"key 'fmu' at the top level: {path} does not exist; give the path to "
                            f"the .fmu file (relative paths start at the study file's directory) "
                            f"or 'default' for the built ScrewVertebra FMU")
    if not path.is_file() and not (path.is_dir() and (path / "modelDescription.xml").is_file()):
        raise p.error(node, f"key 'fmu' at the top level: {path} is not a regular file (a device, a FIFO, or a "
                            f"folder without modelDescription.xml); give the path to the .fmu file")
    return path


def files_outside(study: Study) -> list[str]:
    """The files a study names outside its own folder (an absolute path, ``..``, a link that leads away), as
    notes to print: fmusa reads them as asked, and says so, since a study file may come from someone else."""
    if study.fmu is None or study.path is None:
        return []
    folder = Path(study.path).resolve().parent
    try:
        Path(study.fmu).resolve().relative_to(folder)
        return []
    except ValueError:
        return [f"{study.path}:{study.lines.get('fmu', 1)}: the study reads the FMU {study.fmu}, outside the "
                f"study file's folder {folder}"]


def _check_conflicts(p: _Parser, top: _Map, parameters: Mapping[str, Parameter], fixed: Mapping,
                     scenario: Scenario) -> None:
    fixed_map = p.mapping(top.items["fixed"][1], "fixed") if top.opt("fixed") is not None else None
    for prm in parameters.values():
        if prm.variable in fixed and fixed_map is not None:
            raise p.error(fixed_map.key_node(prm.variable),
                          f"key '{prm.variable}' in 'fixed' is the FMU variable of study parameter "
                          f"'{prm.name}', which sets it on every run; remove it from 'fixed'")
    if scenario.inputs:
        for prm in parameters.values():
            if prm.variable in scenario.inputs:
                raise StudyError(f"{p.label}:{p.lines.get(f'scenario.inputs.{prm.variable}', '?')}: key "
                                 f"'{prm.variable}' in 'scenario.inputs' is the FMU input of study parameter "
                                 f"'{prm.name}', which holds it at the parameter's value on every run; "
                                 f"remove it from 'scenario.inputs'")
    if fixed_map is not None:
        for name in scenario.inputs:
            if name in fixed:
                raise p.error(fixed_map.key_node(name),
                              f"key '{name}' in 'fixed' is also in 'scenario.inputs'; an FMU "
                              f"variable is either a parameter or an input, keep it in one place")


def _parse(p: _Parser, root: Node | None, base_dir: Path, path: Path | None,
           blocks: Mapping[str, BlockValidator] | None = None) -> Study:
    if root is None:
        raise p.error(None, "the study file is empty; it needs at least the keys name, parameters, "
                            "scenario, metrics and stages")
    top = p.mapping(root, "")
    top.allow(_TOP_KEYS)
    name = p.ident(top.need("name", "name: paper"), "name", "", "name: paper", "study name")
    description = top.text("description")
    fmu = _parse_fmu(p, top, base_dir)
    parameters = _parse_parameters(p, top)
    fixed, fixed_units = _parse_fixed(p, top)
    scenario = _parse_scenario(p, top)
    _check_conflicts(p, top, parameters, fixed, scenario)
    metrics = _parse_metrics(p, top, parameters)
    if scenario.refine_peaks and not any(m.reduce in SAMPLED_REDUCTIONS for m in metrics.values()):
        raise StudyError(f"{p.label}:{p.lines['scenario.refine_peaks']}: key 'refine_peaks' in 'scenario': no "
                         f"metric takes a peak or a settling time from the samples (reduce: "
                         f"{', '.join(SAMPLED_REDUCTIONS)}), so there is nothing to refine; remove "
                         f"refine_peaks")
    constraints = _parse_constraints(p, top, metrics)
    stages = _parse_stages(p, top, parameters, metrics, fixed, constraints)
    execution = _parse_execution(p, top)
    fmu_options = _parse_fmu_options(p, top, scenario)
    paper_node = top.opt("paper")
    paper: dict = {}
    if paper_node is not None:
        if not isinstance(paper_node, MappingNode):
            raise p.error(paper_node, f"key 'paper' at the top level must be a mapping, got "
                                      f"{p.describe(paper_node)}; e.g. paper: {{optimum: {{c: 823224}}}}")
        paper = p.plain(paper_node, "paper")
        if blocks and "paper" in blocks:    # an application's schema of its block (fmusa.api.load_study)
            blocks["paper"](paper, lambda key: f"{p.label}:{p.lines.get(key, _line(paper_node))}")
    return Study(name=name, description=description, path=path, fmu=fmu, parameters=parameters,
                 fixed=fixed, scenario=scenario, metrics=metrics, constraints=constraints,
                 stages=stages, execution=execution, paper=paper, fmu_options=fmu_options,
                 fixed_units=fixed_units, lines=dict(p.lines))


def _check_depth(p: _Parser, text: str) -> None:
    """Refuse nesting deeper than MAX_DEPTH from the parser's events (it does not recurse; composing the
    tree does, and would die of a RecursionError)."""
    depth = 0
    for ev in yaml.parse(text, Loader=_Loader):
        if isinstance(ev, (yaml.SequenceStartEvent, yaml.MappingStartEvent)):
            depth += 1
            if depth > MAX_DEPTH:
                raise StudyError(f"{p.label}:{ev.start_mark.line + 1}: lists or mappings nested more than "
                                 f"{MAX_DEPTH} levels deep; a study file nests a few levels")
        elif isinstance(ev, (yaml.SequenceEndEvent, yaml.MappingEndEvent)):
            depth -= 1


def _check_graph(p: _Parser, root: Node | None) -> None:
    """Refuse a node that contains itself (a recursive alias, ``x: &r {y: *r}``) and nesting deeper than
    MAX_DEPTH, before anything walks the tree recursively; each node is visited once (aliases are shared)."""
    if root is None:
        return
    done: set[int] = set()
    path: set[int] = set()
    stack: list[tuple[Node, int, bool]] = [(root, 0, False)]
    while stack:
        node, depth, leaving = stack.pop()
        if leaving:
            path.discard(id(node))
            done.add(id(node))
            continue
        if id(node) in done or isinstance(node, ScalarNode):
            continue
        if depth > MAX_DEPTH:
            raise p.error(node, f"lists or mappings nested more than {MAX_DEPTH} levels deep; a study file "
                                f"nests a few levels")
        path.add(id(node))
        stack.append((node, depth, True))
        children = ([c for kv in node.value for c in kv] if isinstance(node, MappingNode) else list(node.value))
        for child in children:
            if id(child) in path:
                raise p.error(node, f"a YAML alias refers to the list or mapping it is in (anchor at line "
                                    f"{_line(child)}), which would repeat it forever; write the values out")
            stack.append((child, depth + 1, False))


# ============================================================================ entry points
#: Validates a free-form top-level block (``paper``) once it is read: called with the block as plain Python
#: and ``line_of(key)`` -> ``"file:line"`` of a dotted key (``"paper.roi.c"``); raises StudyError.
BlockValidator = Callable[[dict, Callable[[str], str]], None]


def parse_study(text: str, path: str | os.PathLike = "<string>",
                blocks: Mapping[str, BlockValidator] | None = None) -> Study:
    """Parse and validate a study from YAML ``text``.

    ``path`` is used in error messages and, unless it is ``"<string>"``, as the study file: relative
    paths in the study then resolve against its directory (otherwise against the current one).
    Raises :class:`StudyError`.
    """
    label = str(path)
    p = _Parser(label)
    if label == "<string>":
        base_dir, study_path = Path.cwd(), None
    else:
        study_path = Path(path).expanduser().resolve()
        base_dir = study_path.parent
    try:
        _check_depth(p, text)
        root = yaml.compose(text, Loader=_Loader)
        _check_graph(p, root)
    except RecursionError:
        raise StudyError(f"{label}:1: lists or mappings nested too deeply; a study file nests a few "
                         f"levels") from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = mark.line + 1 if mark is not None else 1
        problem = " ".join(x for x in (exc.context, exc.problem) if x)
        raise StudyError(f"{label}:{line}: invalid YAML: {problem}; fix the syntax (indentation, "
                         f"':' after each key, matching quotes and brackets)") from None
    except yaml.YAMLError as exc:
        raise StudyError(f"{label}:1: invalid YAML: {exc}") from None
    return _parse(p, root, base_dir, study_path, blocks)


#: Largest study file read: study files are a few kilobytes; this stops a wrong path (a device, a
#: data file) from being read until memory runs out.
MAX_STUDY_BYTES = 1_000_000


def load_study(path: str | os.PathLike, blocks: Mapping[str, BlockValidator] | None = None) -> Study:
    """Load and validate the study file ``path``. Raises :class:`StudyError` (a ValueError)."""
    file = Path(path)
    try:
        if not file.is_file():
            if not file.exists():
                raise StudyError(f"{path}:1: study file not found; check the path")
            raise StudyError(f"{path}:1: not a regular file (a folder or a device); give the study's YAML file")
        with open(file, "rb") as f:
            data = f.read(MAX_STUDY_BYTES + 1)
    except OSError as exc:
        raise StudyError(f"{path}:1: cannot read the study file: {exc.strerror}") from None
    if len(data) > MAX_STUDY_BYTES:
        raise StudyError(f"{path}:1: larger than {MAX_STUDY_BYTES} bytes, which no study file is; check that "
                         f"this is the study's YAML file")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise StudyError(f"{path}:1: not UTF-8 text (byte {exc.start}); save the study file as UTF-8") from None
    return parse_study(text, path, blocks)
