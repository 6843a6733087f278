"""The generic report of studies that are not the paper's, on FMUs built here that are not ours.

- a two-parameter study (stiffness and damping of tests/fmus/me_spring, a mass on a spring-damper under a
  ramped force, compiled here) through grid, region of interest, nested search, regression and a Morris
  screening: report.md speaks in the study's own words (none of the paper's), and every stage that ran has
  a figure and a results table;
- a one-parameter study (tests/fmus/misbehave, a static spring that fails on purpose for stiffnesses in a
  band): a line plot over the parameter, a results section, and the failed runs listed with their reason;
- a regression fitted on the grid runs of a study without search still gets its section and figure.
"""
from __future__ import annotations

import json
import re
import shutil
import struct
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

import fmpy
from fmusa.api import parse_study, run_study
from fmusa.format import fmt

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from fmus.me_spring.build import build_spring_fmu  # noqa: E402

BANNED = ("screw", "paper", "pullout", "vertebra")
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------------------------------------- FMUs
@pytest.fixture(scope="module")
def spring_fmu(tmp_path_factory) -> Path:
    if shutil.which("gcc") is None:
        pytest.skip("gcc is needed to build the spring test FMU")
    return build_spring_fmu(tmp_path_factory.mktemp("spring"), "SpringBoth", ("co-simulation", "model-exchange"))


@pytest.fixture(scope="module")
def faulty_fmu(tmp_path_factory) -> Path:
    """tests/fmus/misbehave compiled with gcc: y = F/k, failing with fmi2Error while k is in a band."""
    if shutil.which("gcc") is None:
        pytest.skip("gcc is needed to build the misbehaving test FMU")
    root = tmp_path_factory.mktemp("faulty")
    tree = root / "tree"
    (tree / "binaries" / "linux64").mkdir(parents=True)
    shutil.copy(HERE / "fmus" / "misbehave" / "modelDescription.xml", tree / "modelDescription.xml")
    cmd = ["gcc", "-std=c99", "-O1", "-shared", "-fPIC", "-I", str(Path(fmpy.__file__).parent / "c-code"),
           str(HERE / "fmus" / "misbehave" / "misbehave.c"), "-o", str(tree / "binaries" / "linux64" / "Misbehave.so"),
           "-lm"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    fmu = root / "Misbehave.fmu"
    with zipfile.ZipFile(fmu, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted(tree.rglob("*")):
            if f.is_file():
                z.write(f, f.relative_to(tree).as_posix())
    return fmu


# ---------------------------------------------------------------------------------------------- studies
OSCILLATOR = """\
name: oscillator
description: A mass on a spring-damper under a ramped force; the smallest stiffness and damping that keep
  it close and slow.
fmu: {fmu}
fmu_options: {{interface: co-simulation}}
parameters:
  c: {{variable: c, unit: N/m, description: Spring stiffness}}
  d: {{variable: d, unit: N·s/m, description: Damping coefficient}}
fixed: {{F_max: 10, t_ramp: 1, m: 1}}
scenario:
  stop_time: 3
  step: 0.01
  description: The force rises from 0 to 10 N over 1 s and is then held until 3 s.
metrics:
  max_y: {{output: y, reduce: max, unit: m, description: Largest displacement}}
  max_v: {{output: v, reduce: max_abs, unit: m/s, description: Largest speed}}
  y_end: {{output: y, unit: m, description: Displacement at the end}}
constraints:
  - {{name: reach, metric: max_y, max: 0.05, description: the mass stays within 5 cm}}
  - {{name: speed, metric: max_v, max: 0.08, description: the mass moves slower than 8 cm/s}}
stages:
  grid:
    values: {{c: [50, 100, 200, 400, 800, 1600], d: [1, 4, 16, 64]}}
{stages}execution: {{workers: 2}}
"""
SEARCH_STAGES = """\
  roi: {}
  search: {inner: c, outer: d, inner_rtol: 1.0e-3, response_rtol: 1.0e-3, max_outer: 8}
  regression: {x: c, y: [max_y], by: d, degree: 2}
  sensitivity:
    methods: [morris]
    morris_trajectories: 4
    outputs: [max_y, max_v]
    parameters:
      c: {variable: c, bounds: [100, 1000]}
      d: {variable: d, bounds: [1, 50]}
"""
GRID_REGRESSION = """\
  regression: {x: c, y: [max_y, y_end], by: d, degree: 2}
"""
STIFFNESS = """\
name: stiffness
description: A static spring under a load; the smallest stiffness that keeps the deflection small.
fmu: {fmu}
parameters:
  k: {{variable: k, unit: N/m, description: Spring stiffness}}
fixed: {{F: 411, fault: 1, fault_kind: 4, fault_lo: 2.5e6, fault_hi: 5.5e6}}
scenario:
  stop_time: 1
metrics:
  y_max: {{output: y_peak, unit: m, description: Largest deflection}}
constraints:
  - {{name: deflection, metric: y_max, max: 5.0e-4}}
stages:
  grid:
    values: {{k: [1.0e5, 2.0e5, 5.0e5, 1.0e6, 3.0e6, 5.0e6, 7.0e6, 1.0e7, 2.0e7, 5.0e7]}}
  roi: {{}}
  search: {{inner: k}}
execution: {{workers: 2, timeout_s: 5}}
"""


def _run(tmp_path: Path, name: str, text: str):
    path = tmp_path / f"{name}.yaml"
    path.write_text(text, encoding="utf-8")
    out = tmp_path / "out"
    result = run_study(parse_study(text, path), out, figures=True, progress=False)
    return result, out, (out / "report.md").read_text(encoding="utf-8")


def _figures(text: str) -> list[str]:
    return re.findall(r"!\[[^\]]*\]\(figures/([^)\s]+)\)", text)


def _caption(text: str, name: str) -> str:
    m = re.search(rf"\*{re.escape(name)}\*: (.*)", text)
    assert m, f"no caption for {name}"
    return m.group(1)


def _section(text: str, heading: str) -> str:
    """The text under ``heading`` up to the next heading of the same or a higher level."""
    level = heading.split(" ")[0]
    start = text.index(heading + "\n")
    rest = text[start + len(heading):]
    m = re.search(rf"\n#{{1,{len(level)}}} ", rest)
    return rest[: m.start()] if m else rest


def _has_table(section: str) -> bool:
    return bool(re.search(r"^\|.*\|\n\|(---\|)+\n\|", section, flags=re.M))


def _check_pngs(out: Path, names: list[str]) -> None:
    for n in names:
        head = (out / "figures" / n).read_bytes()[:24]
        assert head[:8] == PNG_SIGNATURE, n
        w, h = struct.unpack(">II", head[16:24])
        assert w >= 600 and h >= 400, (n, w, h)


# ---------------------------------------------------------------------------------------------- tests
@pytest.fixture(scope="module")
def oscillator(spring_fmu, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("oscillator")
    return _run(tmp, "oscillator", OSCILLATOR.format(fmu=spring_fmu, stages=SEARCH_STAGES))


def test_two_parameter_report_speaks_the_study_s_language(oscillator):
    result, out, text = oscillator
    for word in BANNED:
        assert word not in text.lower(), f"report.md mentions {word!r}"
    for word in BANNED:       # the figures' captions and file names too
        assert not any(word in n.lower() for n in result.summary["figures"]), word
    assert "## Results\n" in text and "### Grid\n" in text
    # titles from the study's descriptions, not from the metrics' names
    assert _caption(text, "grid_max_y.png").startswith("Largest displacement (max_y)")
    assert _caption(text, "search_max_v.png").startswith("Largest speed (max_v)")


def test_every_stage_that_ran_has_a_figure_and_a_results_table(oscillator):
    result, out, text = oscillator
    figs = _figures(text)
    assert set(figs) == {p.split("/", 1)[1] for p in result.summary["figures"]}
    _check_pngs(out, figs)
    metrics, constrained = ["max_y", "max_v", "y_end"], ["max_y", "max_v"]
    expected = {
        "grid": ("### Grid", [f"grid_{m}.png" for m in metrics]),
        "roi": ("### Region of interest", ["grid_max_y.png"]),            # the region framed on the grid maps
        "search": ("### Search path", [f"search_{m}.png" for m in constrained] + ["search_path.png"]),
        "regression": ("### Regression", ["search_max_y.png"]),           # its fits over the search's runs
        "sensitivity": ("## Global sensitivity analysis", ["sensitivity_morris.png"]),
    }
    assert set(expected) == set(result.study.stages)
    for stage, (heading, names) in expected.items():
        section = _section(text, next(line for line in text.splitlines() if line.startswith(heading)))
        assert _has_table(section), f"{stage}: no results table under {heading}"
        assert set(names) <= set(figs), f"{stage}: missing figures {set(names) - set(figs)}"
    assert _has_table(_section(text, "### Optimum"))
    assert "region of interest" in _caption(text, "grid_max_y.png")
    assert "regression's fits" in _caption(text, "search_max_y.png")
    # what each stage found: feasible count, best point, optimum, binding constraint, stop reason, run counts
    grid = _section(text, "### Grid")
    assert re.search(r"24 runs on the grid .*; \d+ of them meet every constraint", grid)
    assert "Smallest feasible c on the grid: c = " in grid
    opt = result.summary["optimum"]
    assert f"| search (automatic region) | {fmt(opt['c'], 7)} | {fmt(opt['d'], 6)} |" in text
    assert "binding constraint(s)" in text and ", ".join(result.summary["binding_constraint"]) in text
    assert "Stop rule of the search: " in text
    assert "FMU runs per stage" in text
    assert "## Sampling of the outputs" in text          # step 0.01 s: peaks taken from samples


def test_one_parameter_study_gets_a_line_plot_and_lists_its_failed_runs(faulty_fmu, tmp_path):
    result, out, text = _run(tmp_path, "stiffness", STIFFNESS.format(fmu=faulty_fmu))
    for word in BANNED:
        assert word not in text.lower(), word
    figs = _figures(text)
    _check_pngs(out, figs)
    assert "grid_y_max.png" in figs and "search_y_max.png" in figs
    assert "against k" in _caption(text, "grid_y_max.png")
    results = _section(text, "## Results")
    for heading in ("### Grid", "### Region of interest", "### Optimum", "### Search path", "### Failed runs"):
        assert heading in results, heading
        assert _has_table(_section(text, heading)), heading
    assert result.summary["optimum"]["k"] == pytest.approx(411 / 5e-4, rel=2e-3)
    failed = _section(text, "### Failed runs")
    assert "2 runs failed" in failed
    for k in ("3e6", "5e6"):
        row = next(line for line in failed.splitlines() if line.startswith(f"| grid | {k} |"))
        assert "deliberate failure" in row and "fmi2DoStep returned Error" in row
    assert json.loads((out / "summary.json").read_text())["failed"] == 2


def test_regression_on_the_grid_runs_without_search(spring_fmu, tmp_path):
    result, out, text = _run(tmp_path, "grid_fit", OSCILLATOR.format(fmu=spring_fmu, stages=GRID_REGRESSION))
    section = _section(text, next(line for line in text.splitlines() if line.startswith("### Regression")))
    assert _has_table(section) and "the grid runs" in section
    figs = _figures(text)
    assert {"regression_max_y.png", "regression_y_end.png"} <= set(figs)
    _check_pngs(out, figs)
    assert "### Optimum" not in text and "search_path.png" not in figs
