"""Issue 18 rows 9 and 10, issue 17 "parameters that do nothing": messages that say what is wrong.

A constraint whose metric is NaN in every run is named with that fact (widening cannot help); a name that is
not ASCII says that names are ASCII; a study parameter that changes none of the metrics is said to do nothing,
with its likely causes, in summary.json and the report, and never drawn into a "widen the grid" advice; the
"no grid point meets every constraint" error names the failing constraints, by how much they fail, and
recommends widening only along a parameter that moves the failing metric towards its bound.

The real FMU, and a C FMU built here (tests/fmus/misbehave: with ``fault: 0`` it ignores ``fault_lo``).
"""
from __future__ import annotations

import json
import re

import pytest

from fmusa.api import parse_study, run_study
from fmusa.study.schema import StudyError
from test_misbehaving_fmu import misbehave_fmu  # noqa: F401 - the fixture: the C FMU built with gcc

STUDY = """\
name: msg
fmu: default
parameters:
  c: {variable: c_y, unit: N/m}
  d: {variable: d_y, unit: N.s/m}
fixed: {F_max: 411, t_ramp: 10}
scenario: {stop_time: 12}
metrics:
  max_y: {output: y_max, unit: m}
  t_eq: {output: t_eq, unit: s, missing_below: 0}
constraints:
  - {name: translation, metric: max_y, max: %s}
stages:
  grid: {values: {c: [4.0e5, 8.0e5], d: [300, 600]}}
  roi: {}
  search: {inner: c, outer: d}
"""


def _run(tmp_path, text: str, **kw):
    return run_study(parse_study(text, tmp_path / "s.yaml"), tmp_path / "out", progress=False, **kw)


def test_a_constraint_on_a_metric_that_is_nan_everywhere_is_named(tmp_path):
    """Row 9: t_eq is NaN in every run (not at rest by 12 s: missing_below turns -1 into NaN)."""
    text = STUDY % "5.0e-4"
    text = text.replace("scenario: {stop_time: 12}", "scenario: {stop_time: 0.5}")
    text = text.replace("  - {name: translation, metric: max_y, max: 5.0e-4}",
                        "  - {name: translation, metric: max_y, max: 5.0e-4}\n"
                        "  - {name: at_rest, metric: t_eq, required: true, max: 20}")
    with pytest.raises(StudyError) as info:
        _run(tmp_path, text, figures=False)
    msg = str(info.value)
    assert re.search(r"constraint 'at_rest' \(t_eq <= 20\): t_eq is NaN in every one of the 4 grid runs that "
                     r"worked \(no run gives it a value\), so no grid can meet it", msg), msg
    assert "widen the grid" not in msg
    assert "A wider grid cannot help while 'at_rest' has no value in any run" in msg


def test_the_failing_constraint_says_by_how_much_and_where_to_widen(tmp_path):
    """max_y falls with c: a bound below the grid's smallest max_y is named with its nearest value, and the
    advice is to widen c upwards (the stiffer, the smaller max_y), not d downwards."""
    with pytest.raises(StudyError) as info:
        _run(tmp_path, STUDY % "1.0e-5", figures=False)
    msg = str(info.value)
    m = re.search(r"constraint 'translation' \(max_y <= 1e-05\) is met by none of the 4 grid runs: nearest "
                  r"max_y = ([0-9.e-]+) at c = 8e\+05, d = (300|600), ([0-9.e-]+) past its bound \(([0-9.e+]+) % "
                  r"past it\)", msg)
    assert m, msg
    nearest = float(m.group(1))
    assert nearest == pytest.approx(411 / 8e5, rel=0.05)          # the static deflection F/c, at rest
    assert float(m.group(3)) == pytest.approx(nearest - 1e-5, rel=1e-3)
    assert "widen the grid of c above 8e+05" in msg
    assert "grid of d" not in msg                                  # d does not bring max_y nearer (static)


def test_a_parameter_that_does_nothing_is_said_to_do_nothing(tmp_path):
    """Issue 17: t_unload with unload off changes nothing; summary.json and the report say so, and the
    infeasible grid's message gives no advice to widen it."""
    text = (STUDY % "1.0e-5").replace("d: {variable: d_y, unit: N.s/m}", "u: {variable: t_unload, unit: s}")
    text = text.replace("d: [300, 600]", "u: [20, 30, 40]").replace("search: {inner: c, outer: d}",
                                                                   "search: {inner: c, outer: u}")
    no_search = text.replace("  roi: {}\n  search: {inner: c, outer: u}\n", "")
    result = _run(tmp_path, no_search)
    grid = result.summary["grid"]
    inert = grid["inert_parameters"]
    assert list(inert) == ["u"], inert
    assert inert["u"]["values"] == 3
    assert "parameter 'u' changes none of the metrics (max_y, t_eq) across its 3 grid values" in inert["u"]["message"]
    assert "drop values set before fmi2SetupExperiment" in inert["u"]["message"]
    assert "structural parameter" in inert["u"]["message"]
    assert "wrong variable" in inert["u"]["message"]
    assert "no grid point meets every constraint" in grid["infeasible"]
    assert "widen the grid of c above" in grid["infeasible"] and "grid of u" not in grid["infeasible"]
    on_disk = json.loads((tmp_path / "out" / "summary.json").read_text(encoding="utf-8"))
    assert on_disk["grid"]["inert_parameters"] == inert
    report = (tmp_path / "out" / "report.md").read_text(encoding="utf-8")
    assert "**A parameter that does nothing.** parameter 'u' changes none of the metrics" in report
    assert "**No feasible grid point.**" in report
    with pytest.raises(StudyError, match=r"Note: parameter 'u' changes none of the metrics"):
        _run(tmp_path, text, figures=False)
    # c does something: never called inert
    assert "c" not in inert


def test_a_c_fmu_that_ignores_a_parameter(tmp_path, misbehave_fmu):  # noqa: F811
    """The misbehaving C FMU with fault 0 ignores fault_lo: named as doing nothing; and when the bound
    cannot be met, no advice to widen along fault_lo (only along k, which moves y_peak)."""
    text = f"""\
name: ignored
fmu: {misbehave_fmu.as_posix()}
parameters:
  k: {{variable: k, unit: N/m}}
  lo: {{variable: fault_lo, unit: N/m}}
fixed: {{F: 411, fault: 0}}
scenario: {{stop_time: 1}}
metrics:
  y: {{output: y_peak, unit: m}}
constraints:
  - {{name: small, metric: y, max: 1.0e-6}}
stages:
  grid: {{values: {{k: [1.0e6, 2.0e6], lo: [1, 10, 100]}}}}
  roi: {{}}
  search: {{inner: k, outer: lo}}
"""
    with pytest.raises(StudyError) as info:
        _run(tmp_path, text, figures=False)
    msg = str(info.value)
    assert "nearest y = 0.0002055 at k = 2e+06" in msg, msg            # y = F/k
    assert "widen the grid of k above 2e+06" in msg and "grid of lo" not in msg
    assert "Note: parameter 'lo' changes none of the metrics (y) across its 3 grid values" in msg


@pytest.mark.parametrize("name, says", [
    ("κ", r"'κ' has the non-ASCII character 'κ'; names are ASCII only: letters A-Z and a-z, digits and '_'"),
    ("c_é", r"'c_é' has the non-ASCII character 'é'; names are ASCII only"),
    ("2c", r"'2c' is not an identifier; use ASCII letters \(A-Z, a-z\), digits and '_' \(not starting with a "
           r"digit\)"),
])
def test_a_name_that_is_not_ascii_says_names_are_ascii(name, says):
    """Row 10: κ is a letter (str.isidentifier), but only ASCII is taken, and the message says so."""
    text = (STUDY % "5e-4").replace("  c: {variable: c_y", f"  {name}: {{variable: c_y").replace(
        "{c: [4.0e5", f"{{{name}: [4.0e5").replace("inner: c", f"inner: {name}")
    with pytest.raises(StudyError, match=says):
        parse_study(text, "s.yaml")
