"""The study file format (fmusa.study): the two shipped studies load, and bad input fails with a
message that names the file, the line, the key and the fix.

No FMU is run here: whether FMU variables exist is checked against the built FMU's modelDescription.xml
(the variable contract fmu/generate.py derives from modelica/ScrewVertebra.mo; read from the FMU, so that
these tests need no Modelica parser).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from fmusa.study.schema import Constraint, GridStage, Metric, Parameter, RegressionStage, RoiStage, SearchStage, SensitivityStage, Study, StudyError
from fmusa.study.loader import load_study, parse_study

from contract import fmu_variables

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "studies" / "paper.yaml"
SIX_DOF = ROOT / "studies" / "six_dof.yaml"
BAD = "studies/bad.yaml"          # the file name the bad-input tests report


def _line_of(text: str, marker: str) -> int:
    """1-based line of the first occurrence of ``marker`` in ``text``."""
    idx = text.index(marker)
    return text.count("\n", 0, idx) + 1


def _edit(text: str, old: str, new: str) -> str:
    assert text.count(old) == 1, f"{old!r} occurs {text.count(old)} times"
    return text.replace(old, new)


def _fails(text: str, line: int, *words: str) -> str:
    with pytest.raises(StudyError) as info:
        parse_study(text, BAD)
    msg = str(info.value)
    assert msg.startswith(f"{BAD}:{line}: "), msg
    for w in words:
        assert w in msg, f"{w!r} not in {msg!r}"
    return msg


# ============================================================================ the shipped studies
def test_paper_study_loads():
    s = load_study(PAPER)
    assert isinstance(s, Study)
    assert s.name == "paper" and s.path == PAPER and s.fmu is None
    assert s.parameters["c"] == Parameter("c", "c_y", "N/m", 1.0, 0.0, "Axial interface stiffness c_F")
    assert s.parameters["d"].variable == "d_y"
    assert s.fixed == {"F_max": 411, "t_ramp": 10, "eps_v_eq": 5e-8, "eps_a_eq": 5e-9}
    assert (s.scenario.stop_time, s.scenario.step, s.scenario.inputs) == (12.0, None, {})
    assert list(s.metrics) == ["max_y", "mean_y", "max_v", "mean_v", "t_eq"]
    assert s.metrics["mean_y"].output == "y_mean" and s.metrics["mean_v"].output == "v_y_mean"
    assert all(m.reduce == "final" for m in s.metrics.values())
    assert s.metrics["t_eq"].missing_below == 0
    assert [(c.name, c.metric, c.max, c.required) for c in s.constraints] == [
        ("translation", "max_y", 5e-4, False), ("velocity", "max_v", 5e-5, False),
        ("equilibrium", "t_eq", None, True)]
    assert list(s.stages) == ["grid", "roi", "search", "regression"]
    grid = s.stages["grid"]
    assert isinstance(grid, GridStage) and grid.base == 25 and grid.exponents == {"c": (3, 7), "d": (2, 6)}
    pts = grid.points()
    np.testing.assert_array_equal(pts["c"], [25.0 ** k for k in range(3, 8)])
    np.testing.assert_array_equal(pts["d"], [25.0 ** k for k in range(2, 7)])
    assert s.stages["roi"] == RoiStage(manual=None)
    assert s.stages["search"] == SearchStage("c", "d", 1e-3, 1e-3, 20, ["max_y", "max_v", "t_eq"], {},
                                             parallel=False)     # the paper's sequential search
    assert s.stages["regression"] == RegressionStage("c", ["max_y", "max_v"], "d", 3)
    assert (s.execution.workers, s.execution.scheduler, s.execution.timeout_s) == (None, None, 60.0)
    assert s.paper["optimum"] == {"c": 823224, "d": 488, "t_eq": 0.07674}
    # the paper prints the region's bounds to 3 digits (3.91e5, 9.77e6; 0, 1.56e4)
    assert s.paper["roi"]["c"] == pytest.approx([3.91e5, 9.77e6], rel=2e-3)
    assert s.paper["roi"]["d"] == pytest.approx([0, 1.56e4], rel=2e-3)
    assert s.paper["regression"]["u"] == -5.4e-22 and s.paper["cpu_s_per_run"] == 5
    # The ramp argument of the comments: both thresholds bind at the same stiffness.
    F, t_ramp = s.fixed["F_max"], s.fixed["t_ramp"]
    c_y, c_v = F / s.constraints[0].max, F / (s.constraints[1].max * t_ramp)
    assert c_y == pytest.approx(822000) and c_v == pytest.approx(822000)


def test_six_dof_study_loads(fmu_path):
    s = load_study(SIX_DOF)
    assert s.name == "six_dof" and "grid" not in s.stages
    assert s.fixed == {"F_max": 411, "t_ramp": 0.05, "rtol": 1e-3}
    assert s.scenario.stop_time == 0.1
    assert s.scenario.inputs == {"F_ext_x": 20.0, "F_ext_z": -10.0, "T_ext_y": 0.005}
    sens = s.stages["sensitivity"]
    assert isinstance(sens, SensitivityStage)
    assert (sens.methods, sens.n, sens.seed) == (["morris", "sobol"], 1024, 1)
    assert sens.outputs == list(s.metrics)
    assert s.metrics["x_final"].output == "x" and s.metrics["gamma_final"].output == "gamma"
    start = {n: float(r["start"]) for n, r in fmu_variables(fmu_path).items() if r["type"] == "Real" and r["start"]}
    elements = [f"{k}_{a}" for k in "cd" for a in ("x", "y", "z", "alpha", "beta", "gamma")]
    mass = ["m", "cg_y", "L_screw", "D_screw"]
    assert list(sens.parameters) == elements + mass
    for name in elements:
        p = sens.parameters[name]
        assert p.distribution == "loguniform"
        assert p.bounds == pytest.approx((start[name] / 10, start[name] * 10))
    for name in mass:
        p = sens.parameters[name]
        lo, hi = sorted((start[name] * 0.8, start[name] * 1.2))
        assert p.distribution == "uniform" and p.bounds == pytest.approx((lo, hi))


@pytest.mark.parametrize("path", [PAPER, SIX_DOF], ids=["paper", "six_dof"])
def test_studies_use_only_fmu_variables(path, fmu_path):
    """Every FMU name a study refers to is in the variable contract, with the right causality.
    y_mean and v_y_mean are outputs still to be added to the FMU; they may be missing for now."""
    s = load_study(path)
    var = fmu_variables(fmu_path)
    pending = {"y_mean", "v_y_mean"} - set(var)
    params = [p.variable for p in s.parameters.values()] + list(s.fixed)
    if "sensitivity" in s.stages:
        params += [p.variable for p in s.stages["sensitivity"].parameters.values()]
    for name in params:
        assert var[name]["causality"] == "parameter", name
    for name in s.scenario.inputs:
        assert var[name]["causality"] == "input", name
    for m in s.metrics.values():
        assert m.output in pending or var[m.output]["causality"] == "output", m.output


# ============================================================================ helpers of the dataclasses
def test_parameter_unit_conversion():
    p = Parameter("c", "c_y", "kN/m", scale=1000.0, offset=0.0)
    assert p.to_fmu(823.224) == pytest.approx(823224)
    assert p.from_fmu(p.to_fmu(1.5)) == pytest.approx(1.5)
    np.testing.assert_allclose(p.to_fmu(np.array([1.0, 2.0])), [1000.0, 2000.0])


def test_constraint_satisfied():
    bound = Constraint("translation", "max_y", max=5e-4)
    assert bound.satisfied(5e-4) and bound.satisfied(1e-5) and not bound.satisfied(6e-4)
    assert not bound.satisfied(math.nan)
    both = Constraint("band", "x", max=2.0, min=1.0)
    assert both.satisfied(1.0) and not both.satisfied(0.5) and not both.satisfied(2.5)
    required = Constraint("equilibrium", "t_eq", required=True)
    assert required.satisfied(0.07674) and not required.satisfied(math.nan)


def test_metric_compute():
    t_eq = Metric("t_eq", "t_eq", missing_below=0)
    assert math.isnan(t_eq.compute(-1.0)) and t_eq.compute(0.07674) == 0.07674
    mm = Metric("max_y_mm", "y", reduce="max_abs", scale=1000.0)
    assert mm.compute([0.0, -2e-4, 1e-4]) == pytest.approx(0.2)
    assert Metric("m", "y", reduce="mean").compute([1.0, 2.0, 3.0]) == 2.0
    assert Metric("m", "y").compute([1.0, 2.0, 3.0]) == 3.0


def test_fmu_values_merge_fixed_and_parameters():
    s = load_study(PAPER)
    v = s.fmu_values({"c": 823224, "d": 488})
    assert v["c_y"] == 823224 and v["d_y"] == 488 and v["F_max"] == 411 and v["t_ramp"] == 10


# ============================================================================ good input, small
MINIMAL = """\
name: tiny
parameters:
  c: {variable: c_y}
scenario:
  stop_time: 1
metrics:
  max_y: {output: y_max}
stages:
  grid:
    values: {c: [3.0e5, 1e5, 2.0E+5]}
"""


def test_minimal_study_defaults_and_number_forms():
    s = parse_study(MINIMAL, BAD)
    assert s.description == "" and s.fmu is None and s.fixed == {} and s.constraints == [] and s.paper == {}
    assert s.metrics["max_y"].reduce == "final"
    # 1e5 is a number (plain PyYAML would read it as a string); points are sorted
    np.testing.assert_array_equal(s.stages["grid"].points()["c"], [1e5, 2e5, 3e5])
    assert s.execution.timeout_s == 60.0 and s.stages["grid"].base is None


def test_relative_fmu_path_resolves_against_the_study_file(tmp_path):
    (tmp_path / "vendor").mkdir()
    fmu = tmp_path / "vendor" / "Screw.fmu"
    fmu.write_bytes(b"")
    sub = tmp_path / "studies"
    sub.mkdir()
    f = sub / "s.yaml"
    f.write_text(MINIMAL.replace("name: tiny\n", "name: tiny\nfmu: ../vendor/Screw.fmu\n"))
    assert load_study(f).fmu == fmu.resolve()
    f.write_text(MINIMAL.replace("name: tiny\n", "name: tiny\nfmu: ../vendor/Missing.fmu\n"))
    with pytest.raises(StudyError, match=r"s\.yaml:2: key 'fmu' .*Missing\.fmu does not exist"):
        load_study(f)


# ============================================================================ bad input
PAPER_TEXT = PAPER.read_text()
SIX_TEXT = SIX_DOF.read_text()

# (id, source text, old, new, marker of the reported line, words the message must contain)
CASES = [
    ("misspelt key", PAPER_TEXT, "  stop_time: 12 ", "  stop_tme: 12 ", "stop_tme:",
     ["key 'stop_tme' is not allowed in 'scenario'", "did you mean 'stop_time'?", "allowed: stop_time"]),
    ("unknown top-level key", PAPER_TEXT, "\nfixed:\n", "\nfixd:\n", "fixd:",
     ["key 'fixd' is not allowed at the top level", "did you mean 'fixed'?"]),
    ("missing metric output", PAPER_TEXT, "    output: y_max            # FMU monitor max |y| over the run (Figure 5)\n",
     "", "  max_y:\n", ["key 'output' is missing in 'metrics.max_y'", "add it", "output: y_max"]),
    ("missing stop_time", MINIMAL, "  stop_time: 1\n", "  step: 0.1\n", "scenario:",
     ["key 'stop_time' is missing in 'scenario'", "stop_time: 12"]),
    ("missing name", MINIMAL, "name: tiny\n", "", "parameters:",
     ["key 'name' is missing at the top level", "name: paper"]),
    ("string for a number", PAPER_TEXT, "  stop_time: 12 ", "  stop_time: 12 s ", "stop_time: 12 s",
     ["key 'stop_time' in 'scenario' must be a number", "'12 s'", "remove the quotes or units"]),
    ("quoted number", MINIMAL, "stop_time: 1", "stop_time: '1'", "stop_time:",
     ["key 'stop_time' in 'scenario' must be a number", "remove the quotes"]),
    ("string for a list", PAPER_TEXT, "    y: [max_y, max_v]", "    y: max_y", "    y: max_y",
     ["key 'y' in 'stages.regression' must be a list", "y: [max_y, max_v]"]),
    ("list for a string", PAPER_TEXT, "    variable: c_y ", "    variable: [c_y] ", "variable: [c_y]",
     ["key 'variable' in 'parameters.c' must be a string", "got a list"]),
    ("mapping expected", MINIMAL, "scenario:\n  stop_time: 1\n", "scenario: 1\n", "scenario: 1",
     ["key 'scenario' at the top level must be a mapping", "the number 1"]),
    ("boolean for an integer", PAPER_TEXT, "    degree: 3", "    degree: true", "degree: true",
     ["key 'degree' in 'stages.regression' must be an integer", "the boolean true"]),
    ("negative stop_time", PAPER_TEXT, "  stop_time: 12 ", "  stop_time: -1 ", "stop_time: -1",
     ["key 'stop_time' in 'scenario' must be > 0", "got -1"]),
    ("infinite stop_time", MINIMAL, "stop_time: 1", "stop_time: .inf", "stop_time:",
     ["key 'stop_time' in 'scenario' must be finite"]),
    ("zero step", PAPER_TEXT, "  step: null ", "  step: 0 ", "  step: 0",
     ["key 'step' in 'scenario' must be > 0"]),
    ("exponents reversed", PAPER_TEXT, "      c: [3, 7]", "      c: [5, 3]", "c: [5, 3]",
     ["key 'c' in 'stages.grid.exponents'", "lo ≤ hi", "got [5, 3]", "swap them: c: [3, 5]"]),
    ("exponent not an integer", PAPER_TEXT, "      d: [2, 6]", "      d: [2, 6.5]", "d: [2, 6.5]",
     ["key 'd' in 'stages.grid.exponents' must be an integer"]),
    ("exponents without base", PAPER_TEXT, "    base: 25\n", "", "  grid:",
     ["key 'base' is missing in 'stages.grid'", "base: 25"]),
    ("grid on an unknown parameter", PAPER_TEXT, "      d: [2, 6]", "      e: [2, 6]", "e: [2, 6]",
     ["key 'e' in 'stages.grid.exponents' names an unknown study parameter 'e'", "known study parameters: c, d"]),
    ("exponents and values", PAPER_TEXT, "      d: [2, 6]  ", "      d: [2, 6]\n    values: {c: [1.0, 2.0]}  ",
     "values: {c:", ["key 'c' in 'stages.grid.values'", "keep exactly one of exponents / values"]),
    ("constraint on unknown metric", PAPER_TEXT, "    metric: max_v\n", "    metric: max_vel\n", "metric: max_vel",
     ["key 'metric' in 'constraints[1]' names an unknown metric 'max_vel'", "did you mean 'max_v'?"]),
    ("constraint without a bound", PAPER_TEXT, "    required: true ", "    required: false ", "  - name: equilibrium",
     ["constraint 'equilibrium'", "add a key 'max', a key 'min' or 'required: true'"]),
    ("min above max", PAPER_TEXT, "    max: 5.0e-4 ", "    max: 5.0e-4\n    min: 1.0e-3 ", "min: 1.0e-3",
     ["key 'min' in 'constraints[0]'", "swap them"]),
    ("duplicate constraint names", PAPER_TEXT, "  - name: velocity", "  - name: translation", "  - name: translation\n    metric: max_v",
     ["key 'name' in 'constraints[1]'", "'translation' is already used at line", "its own name"]),
    ("duplicate parameter names", PAPER_TEXT, "  d:\n    variable: d_y", "  c:\n    variable: d_y", "  c:\n    variable: d_y",
     ["key 'c' appears twice in 'parameters' (first at line", "remove or rename one"]),
    ("two parameters on one variable", PAPER_TEXT, "    variable: d_y", "    variable: c_y", "variable: c_y\n    unit: N·s/m",
     ["key 'variable' in 'parameters.d'", "'c_y' is already set by parameter 'c'"]),
    ("metric named like a parameter", MINIMAL, "  max_y: {output: y_max}", "  c: {output: y_max}", "  c: {output",
     ["key 'c' in 'metrics'", "already a study parameter"]),
    ("fixed sets a study parameter", PAPER_TEXT, "  F_max: 411 ", "  c_y: 1.0e6\n  F_max: 411 ", "c_y: 1.0e6",
     ["key 'c_y' in 'fixed'", "study parameter 'c'", "remove it from 'fixed'"]),
    ("unknown stage name", PAPER_TEXT, "\n  grid:", "\n  gird:", "gird:",
     ["key 'gird' is not allowed in 'stages'", "did you mean 'grid'?", "allowed: grid, roi, search, regression, sensitivity"]),
    ("unknown reduction", PAPER_TEXT, "    reduce: final\n    unit: m\n    description: Maximum screw translation",
     "    reduce: maximum\n    unit: m\n    description: Maximum screw translation", "reduce: maximum",
     ["key 'reduce' in 'metrics.max_y'", "unknown reduction 'maximum'", "did you mean 'max'?"]),
    ("search on unknown parameter", PAPER_TEXT, "    inner: c\n", "    inner: cc\n", "inner: cc",
     ["key 'inner' in 'stages.search'", "unknown study parameter 'cc'", "did you mean 'c'?"]),
    ("search inner equals outer", PAPER_TEXT, "    outer: d\n", "    outer: c\n", "outer: c",
     ["key 'outer' in 'stages.search'", "same parameter as 'inner'"]),
    ("misspelt stage", PAPER_TEXT, "  roi:\n    manual: null", "  roi_x: null", "roi_x",
     ["key 'roi_x' is not allowed in 'stages'", "did you mean 'roi'?"]),
    ("regression on unknown metric", PAPER_TEXT, "    y: [max_y, max_v]", "    y: [max_y, max_w]", "y: [max_y, max_w]",
     ["key 'y' in 'stages.regression'", "unknown metric 'max_w'"]),
    ("negative timeout", PAPER_TEXT, "  timeout_s: 60", "  timeout_s: -5", "timeout_s: -5",
     ["key 'timeout_s' in 'execution' must be > 0"]),
    ("zero workers", PAPER_TEXT, "  workers: null ", "  workers: 0 ", "workers: 0",
     ["key 'workers' in 'execution' must be ≥ 1"]),
    ("paper not a mapping", MINIMAL, "name: tiny\n", "name: tiny\npaper: [1]\n", "paper: [1]",
     ["key 'paper' at the top level must be a mapping"]),
    ("loguniform with lo <= 0", SIX_TEXT, "bounds: [0.1, 10], ", "bounds: [0, 10], ", "bounds: [0, 10]",
     ["key 'bounds' in 'stages.sensitivity.parameters.c_beta'", "loguniform distribution needs lo > 0",
      "distribution: uniform"]),
    ("sensitivity bounds reversed", SIX_TEXT, "bounds: [0.0136, 0.0204]", "bounds: [0.0204, 0.0136]", "bounds: [0.0204",
     ["key 'bounds' in 'stages.sensitivity.parameters.L_screw'", "lo < hi", "swap them"]),
    ("sensitivity bounds not a pair", SIX_TEXT, "c_alpha, bounds: [1, 100], ", "c_alpha, bounds: [1, 10, 100], ",
     "bounds: [1, 10, 100]",
     ["key 'bounds' in 'stages.sensitivity.parameters.c_alpha' must be a pair [lo, hi]"]),
    ("unknown distribution", SIX_TEXT, "distribution: uniform, unit: kg", "distribution: gauss, unit: kg",
     "distribution: gauss", ["key 'distribution' in 'stages.sensitivity.parameters.m'", "unknown distribution 'gauss'",
                             "allowed: uniform, loguniform, normal, truncnormal, lognormal"]),
    ("unknown method", SIX_TEXT, "methods: [morris, sobol]", "methods: [morris, sobole]", "methods:",
     ["key 'methods' in 'stages.sensitivity'", "unknown method 'sobole'", "did you mean 'sobol'?"]),
    ("sensitivity output unknown", SIX_TEXT, "outputs: [max_y, ", "outputs: [y_max, ", "outputs:",
     ["key 'outputs' in 'stages.sensitivity'", "unknown metric 'y_max'", "did you mean 'max_y'?"]),
    ("sensitivity variable twice", SIX_TEXT, "c_z:     {variable: c_z,", "c_z:     {variable: c_x,", "c_z:     {variable: c_x",
     ["key 'variable' in 'stages.sensitivity.parameters.c_z'", "'c_x' is already varied by 'c_x'"]),
    ("sensitivity variable fixed", SIX_TEXT, "  t_ramp: 0.05 ", "  t_ramp: 0.05\n  m: 0.0003 ",
     "m:       {variable: m", ["key 'variable' in 'stages.sensitivity.parameters.m'", "also in 'fixed'"]),
    ("missing sensitivity outputs", SIX_TEXT, "    outputs: [max_y, max_v, x_final, z_final, alpha_final, beta_final, gamma_final]\n",
     "", "  sensitivity:", ["key 'outputs' is missing in 'stages.sensitivity'", "outputs: [max_y, max_v]"]),
    ("misspelt sensitivity key", SIX_TEXT, "    parameters:\n", "    params:\n", "params:",
     ["key 'params' is not allowed in 'stages.sensitivity'", "did you mean 'parameters'?"]),
    ("non-integer n", SIX_TEXT, "    n: 1024 ", "    n: 1024.5 ", "n: 1024.5",
     ["key 'n' in 'stages.sensitivity' must be an integer"]),
    ("name not an identifier", MINIMAL, "name: tiny", "name: my study", "name:",
     ["key 'name' at the top level", "not an identifier"]),
    ("fixed with a unit: misspelt key", PAPER_TEXT, "  F_max: 411 ", "  F_max: {value: 0.411, units: kN, scale: 1000} ",
     "F_max: {", ["key 'units' is not allowed in 'fixed.F_max'", "did you mean 'unit'?",
                  "allowed: value, unit, scale, offset, description"]),
    ("fixed with a unit: no value", PAPER_TEXT, "  F_max: 411 ", "  F_max: {unit: kN, scale: 1000} ", "F_max: {",
     ["key 'value' is missing in 'fixed.F_max'", "value: 823.2"]),
    ("fixed with a unit: zero scale", PAPER_TEXT, "  F_max: 411 ", "  F_max:\n    value: 0.411\n    scale: 0 ",
     "scale: 0", ["key 'scale' in 'fixed.F_max' must not be 0", "scale: 1000"]),
    ("fixed with a unit: value with its unit", PAPER_TEXT, "  F_max: 411 ", "  F_max:\n    value: 0.411 kN ",
     "value: 0.411 kN", ["key 'value' in 'fixed.F_max' must be a number", "'0.411 kN'", "remove the quotes or units"]),
    ("fixed plain value with its unit", PAPER_TEXT, "  F_max: 411 ", "  F_max: 411 N ", "F_max: 411 N",
     ["key 'F_max' in 'fixed' must be a number", "{value: 0.411, unit: kN, scale: 1000}"]),
    ("search response unknown metric", PAPER_TEXT, "    max_outer: 20\n", "    max_outer: 20\n    response: [max_y, v_end]\n",
     "response: [", ["key 'response' in 'stages.search' names an unknown metric 'v_end'", "known metrics: max_y"]),
    ("search response empty", PAPER_TEXT, "    max_outer: 20\n", "    max_outer: 20\n    response: []\n",
     "response: [", ["key 'response' in 'stages.search' must list at least one metric"]),
    ("negative response_atol", PAPER_TEXT, "    max_outer: 20\n", "    max_outer: 20\n    response_atol: -1.0e-9\n",
     "response_atol:", ["key 'response_atol' in 'stages.search' must be ≥ 0", "response_atol: {v_end: 1.0e-9}"]),
    ("response_atol for a metric not in the response", PAPER_TEXT, "    max_outer: 20\n",
     "    max_outer: 20\n    response_atol:\n      mean_y: 1.0e-9\n", "mean_y: 1.0e-9",
     ["key 'mean_y' in 'stages.search.response_atol'", "not a response metric of the search",
      "(response: max_y, max_v, t_eq)", "add 'mean_y' to 'response'"]),
    ("response_atol not a number", PAPER_TEXT, "    max_outer: 20\n",
     "    max_outer: 20\n    response_atol: {t_eq: small}\n", "response_atol:",
     ["key 't_eq' in 'stages.search.response_atol' must be a number", "the string 'small'"]),
]


@pytest.mark.parametrize("text,old,new,marker,words", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_input_names_file_line_key_and_fix(text, old, new, marker, words):
    bad = _edit(text, old, new)
    _fails(bad, _line_of(bad, marker), *words)


def test_fixed_values_convert_from_the_study_unit():
    text = _edit(PAPER_TEXT, "  F_max: 411 ", "  F_max: {value: 0.411, unit: kN, scale: 1000} ")
    text = _edit(text, "  t_ramp: 10 ", "  t_ramp:\n    value: 10000\n    unit: ms\n    scale: 1.0e-3\n"
                                       "    description: ramp time in ms ")
    s = parse_study(text, BAD)
    assert s.fixed["F_max"] == pytest.approx(411.0, rel=1e-15) and s.fixed["t_ramp"] == pytest.approx(10.0, rel=1e-15)
    assert s.fmu_values({"c": 1.0, "d": 2.0})["F_max"] == pytest.approx(411.0, rel=1e-15)
    fv = s.fixed_units["t_ramp"]
    assert (fv.value, fv.unit, fv.scale, fv.offset, fv.description) == (10000, "ms", 1e-3, 0.0, "ramp time in ms")
    assert set(s.fixed_units) == {"F_max", "t_ramp"}          # plain numbers stay in the FMU's unit
    assert s.fixed["eps_v_eq"] == 5e-8 and "eps_v_eq" not in s.fixed_units
    assert s.lines["fixed.t_ramp"] == _line_of(text, "  t_ramp:")   # the FMU checks report this line
    # an offset: a temperature in °C for an FMU in K
    s = parse_study(_edit(MINIMAL, "scenario:", "fixed:\n  T: {value: 37, unit: degC, offset: 273.15}\nscenario:"), BAD)
    assert s.fixed["T"] == pytest.approx(310.15)


def test_search_response_and_floor_defaults():
    s = parse_study(PAPER_TEXT, BAD)
    assert s.stages["search"].response == ["max_y", "max_v", "t_eq"] and s.stages["search"].response_atol == {}
    text = _edit(PAPER_TEXT, "    max_outer: 20\n", "    max_outer: 20\n    response: [max_y, mean_v]\n"
                                                 "    response_atol: 1.0e-12\n")
    stage = parse_study(text, BAD).stages["search"]
    assert stage.response == ["max_y", "mean_v"] and stage.response_atol == {"max_y": 1e-12, "mean_v": 1e-12}
    text = _edit(PAPER_TEXT, "    max_outer: 20\n", "    max_outer: 20\n    response_atol: {t_eq: 1.0e-3}\n")
    assert parse_study(text, BAD).stages["search"].response_atol == {"t_eq": 1e-3}


def test_search_needs_roi_stage():
    bad = _edit(PAPER_TEXT, "  roi:\n    manual: null             # computed from the grid; the paper's hand-chosen "
                            "region is under paper.roi\n", "")
    _fails(bad, _line_of(bad, "  search:"), "key 'search' in 'stages'", "no 'roi' stage comes before it")


def test_automatic_roi_needs_grid():
    roi = "  roi:\n    manual: null             # computed from the grid; the paper's hand-chosen region is under paper.roi\n"
    bad = _edit(_edit(PAPER_TEXT, roi, ""), "  grid:", roi + "  grid:")
    _fails(bad, _line_of(bad, "  roi:"), "key 'roi' in 'stages'", "add a 'grid' stage")


def test_roi_needs_a_search_stage():
    bad = MINIMAL + "  roi:\n    manual: {c: [1.0, 2.0]}\n"
    _fails(bad, _line_of(bad, "  roi:"), "key 'roi' in 'stages'", "no 'search' stage")


def test_grid_must_cover_every_study_parameter():
    bad = _edit(PAPER_TEXT, "      d: [2, 6]  ", "      #")
    _fails(bad, _line_of(bad, "  grid:"), "key 'grid' in 'stages' gives no values for study parameter(s) d",
           "d: [lo, hi]")


def test_manual_roi_must_cover_the_searched_parameters():
    bad = _edit(PAPER_TEXT, "    manual: null ", "    manual: {c: [3.91e5, 9.77e6]} ")
    _fails(bad, _line_of(bad, "  search:"), "key 'search' in 'stages'", "no range for it", "d: [lo, hi]")


ONE_PARAMETER = MINIMAL.replace("  max_y: {output: y_max}\n", "  max_y: {output: y_max}\nconstraints:\n"
                                "  - {name: translation, metric: max_y, max: 5.0e-4}\n")


def test_search_over_one_parameter():
    text = ONE_PARAMETER + "  roi:\n  search: {inner: c}\n"
    stage = parse_study(text, BAD).stages["search"]
    assert stage == SearchStage("c", None, response=["max_y"]) and stage.warm_start is False
    text = ONE_PARAMETER + "  roi: {manual: {c: [1.0e5, 3.0e5]}}\n  search: {inner: c}\n"
    assert parse_study(text, BAD).stages["roi"].manual == {"c": (1e5, 3e5)}


def test_search_warm_start():
    assert parse_study(PAPER_TEXT, BAD).stages["search"].warm_start is False     # the paper's search
    text = _edit(PAPER_TEXT, "    max_outer: 20\n", "    max_outer: 20\n    warm_start: true\n")
    assert parse_study(text, BAD).stages["search"].warm_start is True
    bad = _edit(PAPER_TEXT, "    max_outer: 20\n", "    max_outer: 20\n    warm_start: yes please\n")
    _fails(bad, _line_of(bad, "warm_start:"), "key 'warm_start' in 'stages.search' must be true or false")
    bad = ONE_PARAMETER + "  roi:\n  search: {inner: c, warm_start: true}\n"
    _fails(bad, _line_of(bad, "  search:"), "key 'warm_start' in 'stages.search'", "no 'outer' parameter",
           "remove warm_start or add outer")


def test_regression_source():
    assert parse_study(PAPER_TEXT, BAD).stages["regression"].source == "search"
    text = ONE_PARAMETER + "  regression: {x: c, y: [max_y], degree: 2}\n"
    assert parse_study(text, BAD).stages["regression"] == RegressionStage("c", ["max_y"], None, 2, "grid")
    # too few grid values for the degree
    bad = ONE_PARAMETER + "  regression: {x: c, y: [max_y]}\n"
    _fails(bad, _line_of(bad, "  regression:"), "fits the grid runs", "3 value(s) of 'c'",
           "degree-3 polynomial")
    # nothing to fit: no grid and no search before it
    bad = _edit(ONE_PARAMETER, "  grid:\n    values: {c: [3.0e5, 1e5, 2.0E+5]}\n",
                "  regression: {x: c, y: [max_y], degree: 1}\n  grid:\n    values: {c: [3.0e5, 1e5, 2.0E+5]}\n")
    _fails(bad, _line_of(bad, "  regression:"), "has no runs to fit", "no 'grid' stage comes before it")
    # the search's runs, but the search comes after the regression
    reg = "  regression:                # eq. 3"
    block = PAPER_TEXT[PAPER_TEXT.index(reg):PAPER_TEXT.index("\nexecution:")]
    bad = _edit(_edit(PAPER_TEXT, block, ""), "  search:  ", block.rstrip("\n") + "\n  search:  ")
    _fails(bad, _line_of(bad, "  regression:"), "has no runs to fit", "comes after 'regression'",
           "move 'regression' below 'search'")


def test_duplicate_stage():
    bad = MINIMAL + "  grid:\n    values: {c: [1.0]}\n"
    _fails(bad, _line_of(bad, "  grid:\n    values: {c: [1.0]}"), "key 'grid' appears twice in 'stages'")


def test_yaml_syntax_error_has_a_line():
    bad = _edit(MINIMAL, "  stop_time: 1\n", "  stop_time: [1\n")
    with pytest.raises(StudyError, match=rf"^{BAD}:\d+: invalid YAML"):
        parse_study(bad, BAD)


def test_empty_file():
    _fails("", 1, "empty")


def test_missing_file(tmp_path):
    with pytest.raises(StudyError, match="nope.yaml:1: study file not found"):
        load_study(tmp_path / "nope.yaml")


def test_study_error_is_a_value_error():
    assert issubclass(StudyError, ValueError)
