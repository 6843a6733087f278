"""The study file's key reference, generated from the dataclasses of ``fmusa.study.schema``.

Each section of the YAML file is one dataclass; its fields are the keys, its type annotations the types,
its defaults the defaults, and the ``:param key:`` entries of its docstring the text. Two checks keep the
page and the loader together, and fail the docs build (and tests/test_docs.py) when they part:

- every key of a section is a documented field and every documented entry a field;
- the loader itself is asked which keys it allows in each section (a study with one unknown key there is
  parsed, and the "(allowed: ...)" of its StudyError is read), and that list must be the documented one.
"""
from __future__ import annotations

import copy
import dataclasses
import re
from dataclasses import MISSING
from typing import Callable

import yaml

from fmusa.study import schema

#: (YAML section, dataclass, fields that are not YAML keys, how the section is written in the file)
SECTIONS: list[tuple[str, type, frozenset[str], str]] = [
    ("", schema.Study, frozenset({"path", "lines", "fixed_units"}), "The top level of the file."),
    ("parameters.<name>", schema.Parameter, frozenset({"name"}),
     "One study parameter; `<name>` is an identifier (e.g. `c`)."),
    ("fixed.<name>", schema.FixedValue, frozenset({"name"}),
     "A `fixed` value written with its unit (a plain `fixed.<name>: number` is in the FMU's unit)."),
    ("scenario", schema.Scenario, frozenset(), "What one run simulates."),
    ("metrics.<name>", schema.Metric, frozenset({"name"}),
     "One metric; `<name>` is an identifier and must not also be a parameter name."),
    ("constraints[i]", schema.Constraint, frozenset(), "One item of the `constraints` list."),
    ("stages.grid", schema.GridStage, frozenset(), "The coarse initial grid."),
    ("stages.roi", schema.RoiStage, frozenset(), "The region of interest."),
    ("stages.search", schema.SearchStage, frozenset(), "The nested binary search."),
    ("stages.regression", schema.RegressionStage, frozenset({"source"}), "Polynomial fits (the paper's eq. 3)."),
    ("stages.sensitivity", schema.SensitivityStage, frozenset(), "Global sensitivity analysis."),
    ("stages.sensitivity.parameters.<name>", schema.SensitivityParameter, frozenset({"name"}),
     "One input of the sensitivity analysis."),
    ("stages.sensitivity.pce", schema.PCEOptions, frozenset(),
     "How the polynomial chaos method (`methods: [pce]`) grows its design."),
    ("fmu_options", schema.FMUOptions, frozenset(), "How the FMU runs."),
    ("execution", schema.Execution, frozenset(), "Where the runs execute."),
]

#: A study with every section, valid without an FMU: the loader is probed with one unknown key added to it.
PROBE_STUDY: dict = {
    "name": "probe",
    "parameters": {"c": {"variable": "c_y"}},
    "fixed": {"F_max": 411, "t_ramp": {"value": 10}},
    "scenario": {"stop_time": 12},
    "metrics": {"max_y": {"output": "y_max"}},
    "constraints": [{"name": "translation", "metric": "max_y", "max": 5.0e-4}],
    "stages": {
        "grid": {"base": 25, "exponents": {"c": [3, 5]}},
        "roi": {},
        "search": {"inner": "c"},
        "regression": {"x": "c", "y": ["max_y"], "degree": 1},
        "sensitivity": {"methods": ["morris"], "outputs": ["max_y"],
                        "parameters": {"mass": {"variable": "m", "bounds": [1.0e-4, 1.0e-3]}},
                        "pce": {"max_runs": 400}},
    },
    "fmu_options": {"interface": "auto"},
    "execution": {"workers": 1},
}

PROBE_KEY = "zz_not_a_key"


class DocsDriftError(RuntimeError):
    """The generated reference and the code disagree: the message names the class, the key and the fix."""


def param_entries(cls: type) -> dict[str, str]:
    """The ``:param key: text`` entries of ``cls``'s docstring, continuation lines joined."""
    out: dict[str, str] = {}
    key = None
    for line in (cls.__doc__ or "").splitlines():
        m = re.match(r"\s*:param (\w+):\s*(.*)$", line)
        if m:
            key = m.group(1)
            out[key] = m.group(2).strip()
        elif key is not None and line.strip() and not line.strip().startswith(":"):
            out[key] += " " + line.strip()
        else:
            key = None
    return out


def comment_entries(cls: type) -> dict[str, str]:
    """``#: text`` comments right above a field in the class body (the Sphinx convention for attributes),
    for fields that have no ``:param`` entry."""
    import inspect
    out: dict[str, str] = {}
    pending: list[str] = []
    for line in inspect.getsource(cls).splitlines():
        stripped = line.strip()
        if stripped.startswith("#:"):
            pending.append(stripped[2:].strip())
            continue
        m = re.match(r"(\w+)\s*:", stripped)
        if m and pending:
            out[m.group(1)] = " ".join(pending)
        pending = []
    return out


def entries(cls: type) -> dict[str, str]:
    """The text of each documented field: its ``:param`` entry, else its ``#:`` comment."""
    return {**comment_entries(cls), **param_entries(cls)}


def intro(cls: type) -> str:
    """The docstring's prose, without its ``:param`` entries."""
    text = (cls.__doc__ or "").split(":param", 1)[0]
    lines = [ln.strip() for ln in text.strip().splitlines()]
    paras, cur = [], []
    for ln in lines:
        if ln:
            cur.append(ln)
        elif cur:
            paras.append(" ".join(cur))
            cur = []
    if cur:
        paras.append(" ".join(cur))
    return "\n\n".join(paras)


def keys_of(cls: type, excluded: frozenset[str]) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if f.name not in excluded]


_TYPE_WORDS = [("dict", "mapping"), ("float", "number"), ("int", "integer"), ("bool", "true/false"),
               ("str", "string"), ("None", "null"), ("Path", "path"), ("object", "stage")]


def yaml_type(annotation: object) -> str:
    """A field's annotation in the words of a YAML file (``float | None`` -> ``number or null``)."""
    text = str(annotation).replace("tuple[float, float]", "[lo, hi]").replace("tuple[int, int]", "[lo, hi]")
    for a, b in _TYPE_WORDS:
        text = re.sub(rf"\b{a}\b", b, text)
    text = re.sub(r"\b(" + "|".join(c.__name__ for _, c, _, _ in SECTIONS) + r")\b", "mapping", text)
    return text.replace(" | ", " or ")


def markdown(text: str) -> str:
    """Docstring markup (reST literals and roles) as Markdown."""
    text = re.sub(r":(?:func|meth|class|mod|attr|data):`~?([^`]+)`", r"`\1`", text)
    return text.replace("``", "`")


def _default(f: dataclasses.Field) -> str | None:
    if f.default is not MISSING:
        value = f.default
    elif f.default_factory is not MISSING:      # type: ignore[misc]
        value = f.default_factory()             # type: ignore[misc]
    else:
        return None
    if value is None:
        return "null"
    if dataclasses.is_dataclass(value):
        return "the defaults of its keys"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return f'"{value}"' if value == "" else value
    return yaml.safe_dump(value, default_flow_style=True).strip().removesuffix("...").strip()


def keys_the_loader_allows(parse: Callable[[str], object], error: type[Exception], study: dict, node: dict,
                           section: str, hint: str) -> list[str]:
    """The keys a loader allows in one section: ``node`` (a mapping inside ``study``) gets an unknown key,
    ``parse`` reads the study, and the "(allowed: ...)" of its ``error`` is returned. ``hint`` names what to
    update when the loader does not answer that way."""
    node[PROBE_KEY] = 1
    where = section or "top level"
    try:
        parse(yaml.safe_dump(study, sort_keys=False))
    except error as exc:
        m = re.search(r"key '" + PROBE_KEY + r"' is not allowed.*\(allowed: ([^)]*)\)", str(exc))
        if m:
            return [k.strip() for k in m.group(1).split(",")]
        raise DocsDriftError(f"the loader did not reject an unknown key in '{where}' as expected: {exc}; "
                             f"{hint}") from None
    raise DocsDriftError(f"the loader accepted the unknown key {PROBE_KEY!r} in '{where}'")


def check_section(cls: type, excluded: frozenset[str], section: str, allowed: list[str] | None, where: str,
                  fix: str) -> None:
    """Raise :class:`DocsDriftError` when the docstring of ``cls``, its fields and the keys the loader
    ``allowed`` disagree (``where`` names the class, ``fix`` where a non-key field is listed)."""
    fields = [f.name for f in keys_of(cls, excluded)]
    docs = entries(cls)
    missing = [k for k in fields if k not in docs]
    if missing:
        raise DocsDriftError(f"{where}: field(s) {', '.join(missing)} have no ':param <key>: text' entry in the "
                             f"class docstring (nor a '#: text' comment above the field); add one (the "
                             f"reference page is made from it)")
    extra = [k for k in param_entries(cls) if k not in fields]
    if extra:
        raise DocsDriftError(f"{where}: docstring entries {', '.join(extra)} are not fields; remove them")
    if allowed is not None and sorted(allowed) != sorted(fields):
        raise DocsDriftError(f"{where}: the loader allows {sorted(allowed)} in '{section or 'top level'}' but "
                             f"the dataclass has {sorted(fields)}; give the dataclass (and its docstring) "
                             f"the loader's keys, or list a non-key field in {fix}")


def loader_keys(section: str) -> list[str]:
    """The keys the study loader allows in ``section``."""
    from fmusa.api import parse_study
    from fmusa.study.schema import StudyError
    study = copy.deepcopy(PROBE_STUDY)
    parts = [p for p in re.split(r"\.|\[i\]", section) if p]
    node: object = study
    for part in parts:
        if part == "<name>":
            node = next(iter(node.values()))        # type: ignore[union-attr]
        else:
            node = node[part]                       # type: ignore[index]
        if isinstance(node, list):
            node = node[0]
    if section == "fixed.<name>":
        node = study["fixed"]["t_ramp"]
    return keys_the_loader_allows(parse_study, StudyError, study, node, section,  # type: ignore[arg-type]
                                  "update docs/_gen/study_keys.py's PROBE_STUDY")


def check(section: str, cls: type, excluded: frozenset[str]) -> None:
    """Raise :class:`DocsDriftError` when the docstring, the fields and the loader disagree."""
    check_section(cls, excluded, section, loader_keys(section), f"fmusa.study.schema.{cls.__name__}",
                  "docs/_gen/study_keys.py SECTIONS")


def render() -> str:
    """The whole reference page (Markdown)."""
    out = ["# Study file keys", "",
           "Generated by `make docs` from the dataclasses of `fmusa.study.schema` (their fields, types, defaults "
           "and docstrings) and checked against the keys the loader accepts, so it cannot drift from "
           "`fmusa.load_study`. [Writing a study](../study-file.md) shows a whole file.", "",
           "**required** marks a key without a default; every other key shows its default. A key written with no "
           "value (null) takes its default. Numbers may be written `1e5` or `1.0e5`; relative paths resolve "
           "against the directory of the YAML file.", ""]
    for section, cls, excluded, what in SECTIONS:
        check(section, cls, excluded)
        title = f"`{section}`" if section else "Top level"
        prose = "" if cls is schema.Study else markdown(intro(cls))   # Study's docstring is about the Python object
        out += [f"## {title}", "", what, "", prose, "",
                "| key | type | default | meaning |", "|---|---|---|---|"]
        docs = entries(cls)
        for f in keys_of(cls, excluded):
            text = docs[f.name]
            default = _default(f)
            m = re.match(r"(\*\*required\*\*|\[(\[\]|\{\}|[^\]]*)\])\s*(.*)$", text)
            if m:
                default = "**required**" if m.group(1) == "**required**" else m.group(2)
                text = m.group(3)
            if default is None:
                default = "**required**"
            elif default != "**required**":
                default = default if default.startswith("`") or " " in default else f"`{default}`"
            text = markdown(text).replace("\\|", "|").replace("|", "\\|")
            default = markdown(default)
            out.append(f"| `{f.name}` | {yaml_type(f.type)} | {default} | {text} |")
        out.append("")
    return "\n".join(out)
