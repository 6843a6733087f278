"""The diagnosis study file: which FMU, which measured tests, how the tests drive the FMU and where the
candidate effects go, validated into dataclasses with file:line errors (the YAML machinery of
:mod:`fmusa.study.loader`, as for the sweep's study file).

    from fmusa.diagnose.study import load_diagnosis_study
    st = load_diagnosis_study("studies/diagnose_screw_vertebra.yaml")
    st.interface          # the ModelInterface the fits use
    st.experiments()      # the measured tests, checked and in SI

A study's ``model``, ``baseline`` and ``effects`` sections are the model description
(:class:`~fmusa.diagnose.interface.ModelInterface`); a built-in description (``model: <name>``) is a file of
:mod:`fmusa.diagnose.models` with these three sections. Nothing here runs an FMU: the study is checked
against the FMU's modelDescription.xml by :mod:`fmusa.diagnose.check`.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Mapping

from yaml.nodes import MappingNode, Node, ScalarNode

from fmusa.diagnose.effects import CANDIDATES, DAMPING, STIFFNESS, Scales, model_parameters
from fmusa.diagnose.interface import DRIVES, WHERE, AttachedElement, ModelInterface
from fmusa.diagnose.measured import (FORCE_UNITS, LENGTH_UNITS, ColumnSpec, MeasuredDataError, TIME_UNITS,
                                     unit_table)
from fmusa.diagnose.motion import ANGLE_UNITS, MOTIONS, ROTATION, TORQUE_UNITS, TRANSLATION
from fmusa.study.loader import YamlMap, YamlParser, compose_yaml, read_study_text
from fmusa.study.schema import StudyError

__all__ = ["DriveSection", "ModelSection", "BaselineParameter", "EffectsSection", "TestsSection",
           "DiagnosisOptions", "DiagnosisStudy", "parse_diagnosis_study", "load_diagnosis_study",
           "parse_description", "BASELINE_ROLES", "TOP_KEYS", "ELEMENT_BASELINE", "BUILTIN_DIR", "builtin_names",
           "builtin_path"]

#: The study's names of the baseline's two parameters -> their names in the effect catalogue.
BASELINE_ROLES = {"stiffness": STIFFNESS, "damping": DAMPING}
#: The interface element FMU's own baseline parameters (the eq. 1 spring-damper c, d).
ELEMENT_BASELINE = {"stiffness": "c", "damping": "d"}
TOP_KEYS = ("name", "description", "fmu", "model", "baseline", "effects", "tests", "diagnosis")
_UNITS = {"displacement": LENGTH_UNITS, "force": FORCE_UNITS}
#: the units a study may give a channel whose motion is not declared: translation's, then rotation's
_ANY_UNITS = {"displacement": {**LENGTH_UNITS, **ANGLE_UNITS}, "force": {**FORCE_UNITS, **TORQUE_UNITS}}


#: The built-in model descriptions (:mod:`fmusa.diagnose.models`): ``<modelName>.yaml``.
BUILTIN_DIR = Path(__file__).resolve().parent / "models"


def builtin_names() -> list[str]:
    """The model names that have a built-in description."""
    return sorted(p.stem for p in BUILTIN_DIR.glob("*.yaml"))


def builtin_path(name: str) -> Path | None:
    """The file of the built-in description ``name``, or None."""
    return BUILTIN_DIR / f"{name}.yaml" if name in builtin_names() else None


# ============================================================================ schema
@dataclass(frozen=True)
class DriveSection:
    """How one drive reaches the FMU (``model.drives.displacement`` or ``model.drives.force``).

    :param input: the FMU input (causality input) that receives the measured drive channel, e.g. ``x_machine``.
    :param input_unit: the unit the FMU input expects (a length unit for a displacement drive, a force unit for a force drive); default SI (m, N).
    :param response: the FMU output (causality output) compared with the measured response channel.
    :param response_unit: the unit of that output (a force unit under a displacement drive, a length unit under a force drive); default SI.
    :param set: FMU variables set in every run of this drive, e.g. a switch that selects it: ``{drive_mode: 2}``.
    """
    input: str
    response: str
    input_unit: str = ""
    response_unit: str = ""
    set: Mapping[str, object] = field(default_factory=dict)


@dataclass(frozen=True)
class ModelSection:
    """How the measured tests drive the FMU (``model``), or the name of a built-in description (``model: ScrewVertebra``).

    :param drives: per drive (``displacement``, ``force``) a DriveSection; a test can use only the drives listed.
    :param fixed: FMU parameters set in every run, e.g. ``{mass.m: 0.5}``.
    :param tolerance_parameter: an FMU parameter that receives the solver's relative tolerance (the FMU's own solver), or null.
    :param scale: FMU parameters whose start values give the model's scale for the units check: ``stiffness`` [N/m], ``length`` [m], ``resolution`` [m], ``force`` [N].
    :param motion: ``translation`` (displacement and force) or ``rotation`` (the interface's displacement is an angle, its force a torque: units rad, deg, mrad and N·m, N·mm, kN·m, SI rad and N·m); default: as the units of ``tests`` say, else translation.
    """
    drives: Mapping[str, DriveSection]
    fixed: Mapping[str, object] = field(default_factory=dict)
    tolerance_parameter: str | None = None
    scale: Mapping[str, str] = field(default_factory=dict)
    motion: str | None = None


@dataclass(frozen=True)
class BaselineParameter:
    """One parameter of the baseline spring-damper (``baseline.stiffness``, ``baseline.damping``); a plain string is its ``variable``.

    :param variable: the FMU variable (a parameter) that carries it: of the model FMU when the effects are ``inside``, of the element FMU when ``attached`` (default there: the element's ``c`` and ``d``).
    :param bounds: [lower, upper] in SI (N/m, N·s/m) in place of the bounds scaled to the data.
    """
    variable: str
    bounds: tuple[float, float] | None = None


@dataclass(frozen=True)
class EffectsSection:
    """Where the candidate effects go (``effects``).

    :param where: ``inside``: the effects are parameters of the FMU itself; ``attached``: they are parameters of an interface element FMU coupled to the model.
    :param candidates: the effects to try (default: every one of the catalogue; attached: all but sensor_offset, which an element cannot add to the model's outputs).
    :param parameters: catalogue parameter -> FMU variable, where the FMU names it differently (``inside``).
    :param bounds: catalogue parameter -> [lower, upper] in SI, in place of the bounds scaled to the data.
    :param element: ``attached``: the interface element FMU (default ``dist/InterfaceElement.fmu``).
    :param force_input: ``attached``: the model FMU's input that takes the interface force (or torque).
    :param displacement_output: ``attached``: the model FMU's output that gives the interface's relative displacement (or angle).
    :param velocity_output: ``attached``: the model FMU's output that gives the interface's relative velocity.
    :param force_sign: ``attached``: the factor the element's force is multiplied by before it enters ``force_input`` (-1: the element pulls back).
    """
    where: str = "inside"
    candidates: tuple[str, ...] = CANDIDATES
    parameters: Mapping[str, str] = field(default_factory=dict)
    bounds: Mapping[str, tuple[float, float]] = field(default_factory=dict)
    element: Path | None = None
    force_input: str | None = None
    displacement_output: str | None = None
    velocity_output: str | None = None
    force_sign: float = -1.0


@dataclass(frozen=True)
class TestsSection:
    """The measured tests (``tests``): one CSV file per test, all read the same way and fitted jointly.

    :param drive: the channel the tests imposed (``displacement`` or ``force``); the model is driven by it and predicts the other.
    :param files: the CSV files (relative paths start at the study file's directory); an item ``{file: a.csv, rate: 10 mm/s}`` gives a file its own drive rate.
    :param columns: the header names of the channels: ``{time: t, displacement: disp, force: Fx}`` (default time, displacement, force).
    :param units: the units of the channels: ``{time: s, displacement: mm, force: N}`` (default s, m, N); of a rotational interface ``{displacement: deg, force: N·m}`` (angle: rad, deg, mrad; torque: N·m, N*m, Nm, N·mm, kN·m; default rad, N·m).
    :param rate: the constant drive rate (``10 mm/s``; rotational ``5 deg/s`` or ``2 N·m/s``) for files without a time column, else null.
    :param flip: channels whose sign is flipped: a list of ``displacement``, ``force``.
    :param zero_drive: shift the drive to start at 0, where the model is at rest.
    :param max_points: block-average each test to at most this many samples for the fit.
    """
    drive: str
    files: tuple[Path, ...]
    columns: Mapping[str, str] = field(default_factory=dict)
    units: Mapping[str, str] = field(default_factory=dict)
    #: how each file is read (the columns and units, with the file's own rate)
    specs: tuple[ColumnSpec, ...] = ()
    rate: str | None = None
    flip: tuple[str, ...] = ()
    zero_drive: bool = True
    max_points: int = 300


@dataclass(frozen=True)
class DiagnosisOptions:
    """How the diagnosis runs (``diagnosis``).

    :param starts: least-squares starts per model.
    :param workers: processes (null: all cores).
    :param chain: the most effects named one on top of the other (1: one effect only).
    """
    starts: int = 6
    workers: int | None = None
    chain: int = 3


@dataclass(frozen=True)
class DiagnosisStudy:
    """A diagnosis study file. ``interface`` is the model description its ``model``, ``baseline`` and
    ``effects`` make (what the fits use).

    :param name: the study's name (an identifier).
    :param description: free text.
    :param fmu: the model FMU (relative paths start at the study file's directory), or ``default`` for dist/ScrewVertebra.fmu.
    :param model: how the tests drive the FMU (ModelSection), or the name of a built-in description.
    :param baseline: the baseline spring-damper: ``stiffness`` and ``damping``, each a BaselineParameter.
    :param effects: where the candidate effects go (EffectsSection).
    :param tests: the measured tests (TestsSection).
    :param diagnosis: how the diagnosis runs (DiagnosisOptions).
    """
    name: str
    tests: TestsSection
    interface: ModelInterface
    description: str = ""
    fmu: Path | None = None
    model: ModelSection | str | None = None
    baseline: Mapping[str, BaselineParameter] = field(default_factory=dict)
    effects: EffectsSection = EffectsSection()
    diagnosis: DiagnosisOptions = DiagnosisOptions()
    path: Path | None = None
    lines: Mapping[str, int] = field(default_factory=dict)

    def experiments(self) -> list:
        """The measured tests, read, checked and converted to SI (errors name file, line and column)."""
        from fmusa.diagnose.measured import load_experiments

        return load_experiments(self.tests.files, self.tests.drive, list(self.tests.specs),
                                zero_drive=self.tests.zero_drive, max_points=self.tests.max_points)


# ============================================================================ parsing
def _where(key: str, where: str) -> str:
    return f"key '{key}' in '{where}'" if where else f"key '{key}' at the top level"


def _path(p: YamlParser, node: Node, key: str, where: str, base_dir: Path, hint: str) -> Path:
    text = p.string(node, key, where, hint)
    path = Path(os.path.expanduser(text))
    path = (path if path.is_absolute() else base_dir / path).resolve()
    if not path.exists():
        raise p.error(node, f"{_where(key, where)}: {path} does not exist; give the path of the file (relative "
                            f"paths start at the study file's directory)")
    return path


def _variable(p: YamlParser, node: Node, key: str, where: str, hint: str) -> str:
    """An FMU variable name (any string: FMU names may hold dots and brackets)."""
    v = p.string(node, key, where, hint)
    p.mark(f"{where}.{key}" if where else key, node)
    return v.strip()


def _values(p: YamlParser, node: Node | None, key: str, where: str) -> dict[str, object]:
    """A mapping FMU variable -> plain value (number, true/false)."""
    if node is None:
        return {}
    m = p.mapping(node, f"{where}.{key}" if where else key, key)
    out = {}
    for k, kn, vn in m.entries():
        v = p.scalar(vn) if isinstance(vn, ScalarNode) else None
        if isinstance(v, bool) or isinstance(v, (int, float)):
            out[k] = v
        else:
            raise p.error(vn, f"{_where(k, m.where)} must be a number or true/false, got {p.describe(vn)}; "
                              f"e.g. {k}: 1")
        p.mark(f"{m.where}.{k}", kn)
    return out


def _unit(p: YamlParser, m: YamlMap, key: str, table: Mapping[str, float],
          shown: Mapping[str, float] | None = None, motion: str | None = None) -> str:
    """A unit of ``table``; the error lists ``shown`` (default the table) and, for a unit of the other motion, says
    which motion the study declares."""
    n = m.opt(key)
    if n is None:
        return ""
    shown = shown or table
    u = p.string(n, key, m.where, f"{key}: {next(iter(shown))}").strip()
    if u not in table:
        other = ROTATION if motion == TRANSLATION else TRANSLATION
        if motion is not None and key in _UNITS and u in unit_table(key, other):
            raise p.error(n, f"{_where(key, m.where)}: {u!r} is a {other} unit, but the study declares "
                             f"model.motion: {motion} (allowed: {', '.join(shown)}); give a {motion} unit or "
                             f"declare motion: {other}")
        raise p.error(n, f"{_where(key, m.where)}: unknown unit {u!r} (allowed: {', '.join(shown)})")
    return u


def _tables(motion: str | None) -> dict:
    """The units a study may give the displacement and force channels: the motion's, or both when undeclared."""
    if motion is None:
        return _ANY_UNITS
    return {r: unit_table(r, motion) for r in ("displacement", "force")}


def _parse_drive(p: YamlParser, node: Node, drive: str, where: str, motion: str | None = None) -> DriveSection:
    w = f"{where}.{drive}"
    hint = "{input: x_machine, response: F_sensor}"
    m = p.mapping(node, w, drive)
    m.allow(("input", "input_unit", "response", "response_unit", "set"))
    response_channel = "force" if drive == "displacement" else "displacement"
    return DriveSection(
        input=_variable(p, m.need("input", f"input: NAME  (the FMU input that takes the measured {drive})"),
                        "input", w, "input: x_machine"),
        response=_variable(p, m.need("response", f"response: NAME  (the FMU output compared with the "
                                                 f"measured {response_channel})"), "response", w, hint),
        input_unit=_unit(p, m, "input_unit", _tables(motion)[drive], motion=motion),
        response_unit=_unit(p, m, "response_unit", _tables(motion)[response_channel], motion=motion),
        set=_values(p, m.opt("set"), "set", w))


def _parse_model(p: YamlParser, node: Node) -> ModelSection:
    m = p.mapping(node, "model", "model")
    m.allow(("drives", "fixed", "tolerance_parameter", "scale", "motion"))
    motion = None if m.opt("motion") is None else p.choice(m.opt("motion"), "motion", "model", MOTIONS,
                                                           "motion of the interface")
    dn = m.need("drives", "drives: {displacement: {input: x_machine, response: F_sensor}}")
    dm = p.mapping(dn, "model.drives", "drives")
    dm.allow(DRIVES)
    if not dm.items:
        raise p.error(dn, "key 'drives' in 'model' must name at least one drive (displacement, force) with its "
                          "FMU input and response output")
    drives = {d: _parse_drive(p, vn, d, "model.drives", motion) for d, _, vn in dm.entries()}
    tol = m.opt("tolerance_parameter")
    scale = {}
    if m.opt("scale") is not None:
        if motion == ROTATION:
            raise p.error(m.key_node("scale"), "key 'scale' in 'model': the units check's scale (stiffness N/m, "
                                               "length m, force N) is for a translational interface; remove it")
        sm = p.mapping(m.opt("scale"), "model.scale", "scale")
        sm.allow(("stiffness", "length", "resolution", "force"))
        scale = {k: _variable(p, vn, k, "model.scale", f"{k}: NAME") for k, _, vn in sm.entries()}
    return ModelSection(drives=drives, fixed=_values(p, m.opt("fixed"), "fixed", "model"),
                        tolerance_parameter=None if tol is None else _variable(p, tol, "tolerance_parameter",
                                                                                 "model", "tolerance_parameter: tol"),
                        scale=scale, motion=motion)


def _bounds(p: YamlParser, node: Node, key: str, where: str) -> tuple[float, float]:
    lo, hi = p.pair(node, key, where, "[1.0e3, 1.0e7]", lambda n, k, w, h: p.number(n, k, w, h))
    if not lo < hi:
        raise p.error(node, f"{_where(key, where)}: lower bound {lo:g} must be below the upper {hi:g}")
    return lo, hi


def _parse_baseline(p: YamlParser, node: Node | None, where_effects: str) -> dict[str, BaselineParameter]:
    if node is None:
        if where_effects == "attached":
            return {r: BaselineParameter(v) for r, v in ELEMENT_BASELINE.items()}
        raise StudyError(f"{p.label}:1: key 'baseline' is missing at the top level; name the FMU parameters of "
                         f"the baseline spring-damper, e.g. baseline: {{stiffness: spring.c, damping: damper.d}}")
    m = p.mapping(node, "baseline", "baseline")
    m.allow(tuple(BASELINE_ROLES))
    out = {}
    for role in BASELINE_ROLES:
        vn = m.opt(role)
        if vn is None:
            if where_effects == "attached":
                out[role] = BaselineParameter(ELEMENT_BASELINE[role])
                continue
            m.need(role, f"{role}: NAME  (the FMU parameter of the baseline's {role})")
            raise p.error(m.key_node(role), f"key '{role}' in 'baseline' is empty; name the FMU parameter")
        if isinstance(vn, MappingNode):
            bm = p.mapping(vn, f"baseline.{role}", role)
            bm.allow(("variable", "bounds"))
            var = _variable(p, bm.need("variable", "variable: NAME"), "variable", f"baseline.{role}", "variable: spring.c")
            b = bm.opt("bounds")
            out[role] = BaselineParameter(var, None if b is None else _bounds(p, b, "bounds", f"baseline.{role}"))
        else:
            out[role] = BaselineParameter(_variable(p, vn, role, "baseline", f"{role}: spring.c"))
    return out


def _parse_effects(p: YamlParser, node: Node | None, base_dir: Path) -> EffectsSection:
    if node is None:
        return EffectsSection()
    m = p.mapping(node, "effects", "effects")
    m.allow(("where", "candidates", "parameters", "bounds", "element", "force_input", "displacement_output",
             "velocity_output", "force_sign"))
    where = "inside" if m.opt("where") is None else p.choice(m.opt("where"), "where", "effects", WHERE,
                                                             "place of the effects")
    cands: tuple[str, ...] = CANDIDATES
    if m.opt("candidates") is not None:
        pool = {c: c for c in CANDIDATES}
        cands = tuple(p.names_in(m.opt("candidates"), "candidates", "effects", pool, "effect",
                                 "[coulomb_friction, backlash_gap]"))
    params = _catalogue_entries(p, m.opt("parameters"), "parameters", "; map catalogue names to FMU variables",
                                lambda vn, k, where: _variable(p, vn, k, where, f"{k}: NAME"))
    bounds = _catalogue_entries(p, m.opt("bounds"), "bounds", "",
                                lambda vn, k, where: _bounds(p, vn, k, where))
    attached_keys = ("element", "force_input", "displacement_output", "velocity_output", "force_sign")
    if where == "inside":
        for k in attached_keys:
            if k in m:
                raise p.error(m.key_node(k), f"key '{k}' in 'effects' applies to where: attached only; remove it "
                                             f"or set where: attached")
        return EffectsSection(where=where, candidates=cands, parameters=params, bounds=bounds)
    if "sensor_offset" in cands:
        if m.opt("candidates") is not None:
            raise p.error(m.opt("candidates"), "key 'candidates' in 'effects': sensor_offset cannot be attached: the "
                                               "measured channels are your model's outputs, which the element does "
                                               "not offset; remove it")
        cands = tuple(c for c in cands if c != "sensor_offset")
    if params:
        raise p.error(m.key_node("parameters"), "key 'parameters' in 'effects' maps effect parameters to the "
                                                "model FMU's variables (where: inside); attached effects are the "
                                                "element FMU's parameters: remove it")
    element = None
    if m.opt("element") is not None:
        element = _path(p, m.opt("element"), "element", "effects", base_dir, "element: InterfaceElement.fmu")
    names = {k: _variable(p, m.need(k, f"{k}: NAME  (the model FMU's {what})"), k, "effects", f"{k}: NAME")
             for k, what in (("force_input", "input that takes the interface force"),
                             ("displacement_output", "output of the interface's relative displacement"),
                             ("velocity_output", "output of the interface's relative velocity"))}
    sign = m.num("force_sign", -1.0, "force_sign: -1", nonzero=True)
    return EffectsSection(where=where, candidates=cands, bounds=bounds, element=element, force_sign=sign, **names)



def _catalogue_entries(p, node, key: str, hint: str, read) -> dict:
    """``effects.<key>``: a mapping keyed by the effect catalogue's parameter names, each value read by ``read``."""
    out: dict = {}
    if node is None:
        return out
    where = f"effects.{key}"
    known = _catalogue_names()
    for k, kn, vn in p.mapping(node, where, key).entries():
        if k not in known:
            raise p.error(kn, f"key '{k}' in '{where}' is not a parameter of the effect catalogue "
                              f"(known: {', '.join(sorted(known))}){hint}")
        out[k] = read(vn, k, where)
    return out

def _catalogue_names() -> set[str]:
    """Every parameter name of the effect catalogue (any drive)."""
    sc = Scales(y_pk=1.0, F_pk=1.0, v_pk=1.0, c0=1.0, t_min=1.0, t_max=1.0, dt_min=0.1)
    return {p.name for c in ("none",) + CANDIDATES for d in DRIVES for p in model_parameters(c, d, sc)}


def _parse_tests(p: YamlParser, node: Node | None, base_dir: Path, motion: str | None = None) -> TestsSection | None:
    if node is None:
        return None
    m = p.mapping(node, "tests", "tests")
    m.allow(("drive", "files", "columns", "units", "rate", "flip", "zero_drive", "max_points"))
    dnode = m.need("drive", "drive: displacement")
    drive = p.choice(dnode, "drive", "tests", DRIVES, "drive")
    p.mark("tests.drive", dnode)
    fn = m.need("files", "files: [test1.csv, test2.csv]")
    items = p.sequence(fn, "files", "tests", "[test1.csv, test2.csv]")
    if not items:
        raise p.error(fn, "key 'files' in 'tests' must list at least one CSV file")
    files, rates = [], []
    for n in items:   # a path, or {file: path, rate: 10 mm/s} for a file of its own rate
        if isinstance(n, MappingNode):
            fm = p.mapping(n, "tests.files", "files")
            fm.allow(("file", "rate"))
            files.append(_path(p, fm.need("file", "file: test1.csv"), "file", "tests.files", base_dir,
                               "file: test1.csv"))
            r = fm.opt("rate")
            rates.append(None if r is None else str(p.scalar(r)))
        else:
            files.append(_path(p, n, "files", "tests", base_dir, "files: [test1.csv]"))
            rates.append(None)
    kw: dict = {}
    columns, units = {}, {}
    if m.opt("columns") is not None:
        cm = p.mapping(m.opt("columns"), "tests.columns", "columns")
        cm.allow(("time", "displacement", "force"))
        columns = {k: p.string(vn, k, "tests.columns", f"{k}: NAME") for k, _, vn in cm.entries()}
        kw.update(columns)
    if m.opt("units") is not None:
        um = p.mapping(m.opt("units"), "tests.units", "units")
        um.allow(("time", "displacement", "force"))
        tables = {"time": TIME_UNITS, **_tables(motion)}
        units = {k: _unit(p, um, k, tables[k], motion=motion) for k in um.keys()}
        kw.update({f"{k}_unit": u for k, u in units.items()})
    rate = m.opt("rate")
    if rate is not None:
        kw["rate"] = str(p.scalar(rate)) if isinstance(rate, ScalarNode) else p.string(rate, "rate", "tests", "10 mm/s")
    flip: tuple[str, ...] = ()
    if m.opt("flip") is not None:
        flip = tuple(p.names_in(m.opt("flip"), "flip", "tests", {"displacement": 1, "force": 1}, "channel",
                                "[force]"))
        kw.update({f"flip_{c}": True for c in flip})
    kw["motion"] = motion
    try:
        spec = ColumnSpec(**kw)
        specs = tuple(spec if r is None else ColumnSpec(**{**kw, "rate": r}) for r in rates)
        for k, u in units.items():   # a unit written out must be of the motion (ColumnSpec maps only its defaults)
            if k != "time" and u not in unit_table(k, spec.motion):
                from fmusa.diagnose.measured import unit_scale
                unit_scale(k, u, "ColumnSpec: ", spec.motion)
    except MeasuredDataError as exc:
        raise p.error(m.node, f"in 'tests': {exc}") from None
    zero = m.opt("zero_drive")
    return TestsSection(drive=drive, files=tuple(files), columns=columns, units=units, specs=specs, rate=kw.get("rate"), flip=flip,
                        zero_drive=True if zero is None else p.boolean(zero, "zero_drive", "tests", "zero_drive: true"),
                        max_points=m.int_("max_points", 300, "max_points: 300", minimum=10))


def _parse_options(p: YamlParser, node: Node | None) -> DiagnosisOptions:
    if node is None:
        return DiagnosisOptions()
    m = p.mapping(node, "diagnosis", "diagnosis")
    m.allow(("starts", "workers", "chain"))
    return DiagnosisOptions(starts=m.int_("starts", 6, "starts: 6", minimum=1),
                            workers=m.int_("workers", None, "workers: 2", minimum=1),
                            chain=m.int_("chain", 3, "chain: 3", minimum=1))


def _interface(name: str, model: ModelSection, baseline: Mapping[str, BaselineParameter],
               effects: EffectsSection, element_default: Path | None, motion: str | None = None) -> ModelInterface:
    """The model description the fits use (``motion``: the interface's, default the model section's)."""
    d = model.drives
    motion = motion or model.motion or TRANSLATION
    scale = {}
    for drive, sec in d.items():
        resp = "force" if drive == "displacement" else "displacement"
        if sec.input_unit:
            scale.setdefault("in", {})[drive] = unit_table(drive, motion)[sec.input_unit]
        if sec.response_unit:
            scale.setdefault("out", {})[drive] = unit_table(resp, motion)[sec.response_unit]
    names = {BASELINE_ROLES[r]: b.variable for r, b in baseline.items()}
    names.update(effects.parameters)
    bounds = {BASELINE_ROLES[r]: b.bounds for r, b in baseline.items() if b.bounds}
    bounds.update(effects.bounds)
    attached = None
    if effects.where == "attached":
        attached = AttachedElement(element_fmu=effects.element or element_default or Path("dist/InterfaceElement.fmu"),
                                   force_input=effects.force_input, displacement_output=effects.displacement_output,
                                   velocity_output=effects.velocity_output, force_sign=effects.force_sign)
    return ModelInterface(
        displacement_input=d["displacement"].input if "displacement" in d else None,
        force_output=d["displacement"].response if "displacement" in d else None,
        force_input=d["force"].input if "force" in d else None,
        displacement_output=d["force"].response if "force" in d else None,
        drive_parameters={k: dict(v.set) for k, v in d.items() if v.set},
        tolerance_parameter=model.tolerance_parameter, fixed_parameters=dict(model.fixed),
        parameter_names={k: v for k, v in names.items() if k != v}, scale_variables=dict(model.scale),
        input_scale=scale.get("in", {}), output_scale=scale.get("out", {}),
        bounds=bounds, candidates=tuple(effects.candidates), attached=attached, name=name,
        **({"motion": motion} if motion != TRANSLATION else {}))


def _description(p: YamlParser, top: YamlMap, base_dir: Path, name: str) -> tuple[ModelInterface, EffectsSection,
                                                                                 ModelSection | str, dict]:
    """The model description of the study: its own model/baseline/effects sections, or a built-in one."""
    mnode = top.need("model", "model: {drives: {displacement: {input: x_machine, response: F_sensor}}}")
    if isinstance(mnode, ScalarNode):
        ref = p.string(mnode, "model", "", "model: ScrewVertebra")
        path = builtin_path(ref)
        if path is None:
            raise p.error(mnode, f"key 'model' at the top level: no built-in model description {ref!r} (built-in: "
                                 f"{', '.join(builtin_names())}); write the model section out instead: "
                                 f"model: {{drives: {{...}}}}")
        if "baseline" in top:
            raise p.error(top.key_node("baseline"), f"key 'baseline' at the top level: the built-in description "
                                                    f"{ref!r} sets it; remove it, or write the model section out")
        base = parse_description(read_study_text(path), str(path))
        eff_node = top.opt("effects")
        if eff_node is not None:   # only the candidates and their bounds may be narrowed
            em = p.mapping(eff_node, "effects", "effects")
            em.allow(("candidates", "bounds"))
            sub = _parse_effects(p, eff_node, base_dir)
            return (replace(base, candidates=sub.candidates, bounds={**base.bounds, **sub.bounds}, name=name), sub,
                    ref, {})
        return (replace(base, name=name), EffectsSection(where="attached" if base.attached else "inside",
                                                         candidates=base.candidates or CANDIDATES), ref, {})
    model = _parse_model(p, mnode)
    effects = _parse_effects(p, top.opt("effects"), base_dir)
    baseline = _parse_baseline(p, top.opt("baseline"), effects.where)
    return _interface(name, model, baseline, effects, None), effects, model, baseline


def parse_description(text: str, label: str, name: str | None = None) -> ModelInterface:
    """A model description file (the ``model``, ``baseline`` and ``effects`` sections of a study, and ``name``)."""
    p = YamlParser(label)
    root = compose_yaml(text, label)
    if root is None:
        raise StudyError(f"{label}:1: the model description is empty")
    top = p.mapping(root, "")
    top.allow(("name", "description", "model", "baseline", "effects"))
    nm = name or (p.string(top.opt("name"), "name", "", "name: ScrewVertebra") if top.opt("name") else "model")
    model = _parse_model(p, top.need("model", "model: {drives: {...}}"))
    effects = _parse_effects(p, top.opt("effects"), Path(label).parent)
    baseline = _parse_baseline(p, top.opt("baseline"), effects.where)
    return _interface(nm, model, baseline, effects, None)


def parse_diagnosis_study(text: str, path: str | os.PathLike = "<string>") -> DiagnosisStudy:
    """Parse and validate a diagnosis study from YAML ``text`` (``path`` for messages and relative paths)."""
    label = str(path)
    p = YamlParser(label)
    if label == "<string>":
        base_dir, study_path = Path.cwd(), None
    else:
        study_path = Path(path).expanduser().resolve()
        base_dir = study_path.parent
    root = compose_yaml(text, label)
    if root is None:
        raise StudyError(f"{label}:1: the study file is empty; it needs at least the keys name, model and tests")
    top = p.mapping(root, "")
    top.allow(TOP_KEYS)
    name = p.ident(top.need("name", "name: my_model"), "name", "", "name: my_model", "study name")
    fmu = None
    if top.opt("fmu") is not None:
        text_fmu = p.string(top.opt("fmu"), "fmu", "", "fmu: model.fmu")
        p.mark("fmu", top.opt("fmu"))
        if text_fmu != "default":
            fmu = _path(p, top.opt("fmu"), "fmu", "", base_dir, "fmu: model.fmu")
    interface, effects, model, baseline = _description(p, top, base_dir, name)
    declared = model.motion if isinstance(model, ModelSection) else interface.motion
    tests = _parse_tests(p, top.opt("tests"), base_dir, declared)
    if tests is not None and isinstance(model, ModelSection):
        motion = declared or tests.specs[0].motion   # undeclared: as the tests' units say
        for drive, sec in model.drives.items():
            resp = "force" if drive == "displacement" else "displacement"
            for key, role in (("input_unit", drive), ("response_unit", resp)):
                u = getattr(sec, key)
                if u and u not in unit_table(role, motion):
                    raise StudyError(f"{label}:{_line_of(top, 'model')}: key '{key}' in 'model.drives.{drive}' is "
                                     f"{u!r}, a unit of the other motion than the tests' ({motion}: "
                                     f"{', '.join(unit_table(role, motion))}); declare model.motion or give the "
                                     f"units of one motion")
        if motion != (interface.motion or TRANSLATION):
            interface = _interface(name, model, baseline, effects, None, motion)
    if tests is None:
        raise p.error(root, "key 'tests' is missing at the top level; add the measured tests, e.g. "
                            "tests: {drive: displacement, files: [test1.csv]}")
    if tests.drive not in interface.drives():
        can = ", ".join(interface.drives()) or "none"
        raise StudyError(f"{label}:{p.lines.get('tests.drive', _line_of(top, 'tests'))}: key 'drive' in 'tests' is "
                         f"{tests.drive!r}, but the model description gives no FMU input and response for a "
                         f"{tests.drive} drive (it has: {can}); add model.drives.{tests.drive}")
    return DiagnosisStudy(name=name, description=top.text("description"), fmu=fmu, interface=interface,
                          model=model, baseline=baseline, effects=effects, tests=tests, diagnosis=_parse_options(p, top.opt("diagnosis")),
                          path=study_path, lines=dict(p.lines))


def _line_of(top: YamlMap, key: str) -> int:
    return top.key_node(key).start_mark.line + 1


def load_diagnosis_study(path: str | os.PathLike) -> DiagnosisStudy:
    """Load and validate the diagnosis study file ``path``. Raises :class:`StudyError` (a ValueError)."""
    return parse_diagnosis_study(read_study_text(path), path)
