"""Load-time checks of a study against its FMU, before any run, and FMUs that must be compiled first.

Every problem is reported at once, in one message naming the study file, each with the line of the
study that causes it and the closest names the FMU does have. FMI 1.0 / 3.0 FMUs are refused with a
message that says fmusa needs FMI 2.0. An FMU with C sources and no binary for this machine is built
before the study starts, and gives the results of the shipped binary.
"""
from __future__ import annotations

import re
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from fmusa.fmi.info import FMUCompileError, FMUError, read_fmu_info, variable_problem
from fmusa.fmi.runner import FMURunner
from fmusa.fmi.build import prepare_fmu
from fmusa.study.schema import StudyError
from fmusa.study.loader import parse_study
from fmusa.api import run_study
from fmusa.pipeline.sweep import StudyRunner
from fmusa.study.plan import check_fmu

from fmus.me_spring.build import build_spring_fmu



def _study_text(fmu: str = "default", parameters: str | None = None, fixed: str = "F_max: 411",
                metrics: str | None = None, options: str = "", inputs: str = "") -> str:
    parameters = parameters or "  c: {variable: c_y, unit: N/m}\n  d: {variable: d_y}\n"
    metrics = metrics or "  max_y: {output: y_max}\n  t_eq: {output: t_eq, missing_below: 0}\n"
    return (f"name: checks\n"
            f"fmu: {fmu}\n"
            + (f"fmu_options:\n{options}" if options else "")
            + f"parameters:\n{parameters}"
            f"fixed:\n  {fixed}\n"
            f"scenario:\n  stop_time: 12\n" + (f"  inputs:\n{inputs}" if inputs else "")
            + f"metrics:\n{metrics}"
            f"stages:\n  grid:\n    values: {{c: [8.0e5, 1.0e6], d: [488]}}\n")


def _write(tmp_path: Path, text: str, name: str = "study.yaml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _line_of(text: str, needle: str) -> int:
    return next(i for i, line in enumerate(text.splitlines(), 1) if needle in line)


def _runner_error(study, tmp_path) -> str:
    with pytest.raises(ValueError) as info:
        StudyRunner(study, tmp_path / "out", resume=False, workers=1, scheduler=None, progress=False)
    return str(info.value)


# ---------------------------------------------------------------------------- variables
def test_all_mapping_problems_are_reported_together_with_lines_and_closest_names(fmu_path, tmp_path):
    text = _study_text(
        parameters=("  c: {variable: c_yy, unit: N/m}\n"      # no such variable
                    "  d: {variable: v_y}\n"                   # an output
                    "  inertia: {variable: I_1}\n"),           # a calculatedParameter
        metrics="  max_y: {output: y_maxx}\n  t_eq: {output: t_eq}\n")   # no such output
    text = text.replace("values: {c: [8.0e5, 1.0e6], d: [488]}",
                        "values: {c: [8.0e5], d: [488], inertia: [1.0e-8]}")
    path = _write(tmp_path, text)
    study = parse_study(text, path)
    msg = _runner_error(study, tmp_path)
    head = msg.splitlines()[0]
    assert str(path) in head and "does not fit the FMU" in head and "(4 problems)" in head
    lines = msg.splitlines()[1:]
    assert len(lines) == 4
    by_var = {k: next(l for l in lines if k in l) for k in ("c_yy", "v_y", "I_1", "y_maxx")}
    # each problem points at its line in the study file
    for key, line in by_var.items():
        assert line.strip().startswith(f"{path}:{_line_of(text, key)}:"), line
    assert "no variable 'c_yy'" in by_var["c_yy"] and "closest parameter names: c_y" in by_var["c_yy"]
    assert "parameter 'c'" in by_var["c_yy"]
    assert "'v_y' is an output variable" in by_var["v_y"] and "cannot be set" in by_var["v_y"]
    assert "calculatedParameter" in by_var["I_1"] and "cannot be set" in by_var["I_1"]
    assert "computed from" in by_var["I_1"]
    assert "no variable 'y_maxx'" in by_var["y_maxx"] and "closest output names: y_max" in by_var["y_maxx"]
    assert "metric 'max_y'" in by_var["y_maxx"]
    # check_fmu itself returns the same list, and nothing ran: no output directory was made
    assert len(check_fmu(study, fmu_path)) == 4
    assert not (tmp_path / "out" / "runs.csv").exists()


def test_fixed_inputs_and_constants_are_checked(tmp_path):
    fmu = build_spring_fmu(tmp_path, "SpringME")
    text = (f"name: spring\nfmu: {fmu}\n"
            "parameters:\n  c: {variable: c}\n  g: {variable: g}\n"
            "fixed:\n  F_mx: 3\n  F_ext: 1\n"
            "scenario:\n  stop_time: 3\n  inputs:\n    t_ramp: 2\n"
            "metrics:\n  max_y: {output: y, reduce: max}\n"
            "stages:\n  grid:\n    values: {c: [100], g: [9.81]}\n")
    path = _write(tmp_path, text)
    errors = check_fmu(parse_study(text, path), fmu)
    assert len(errors) == 4, errors
    joined = "\n".join(errors)
    assert f"{path}:{_line_of(text, 'g: {variable: g}')}: parameter 'g' (variable: g): 'g' is a constant" in joined
    assert "cannot be set" in joined
    assert f"{path}:{_line_of(text, 'F_mx')}: fixed 'F_mx': SpringME has no variable 'F_mx'; closest " \
           f"parameter names: F_max" in joined
    assert "'F_ext' is an input, not a parameter; set it under scenario.inputs" in joined
    assert "'t_ramp' is a parameter, not an input; set it under fixed" in joined


def test_variable_problem_roles(fmu_path):
    info = read_fmu_info(fmu_path)
    assert variable_problem(info, "c_y", "varied") is None
    assert variable_problem(info, "mode", "parameter") is None            # an Integer, set once
    assert "must be Real" in variable_problem(info, "mode", "varied")
    assert variable_problem(info, "F_ext_y", "input") is None
    assert variable_problem(info, "F_ext_y", "varied") is None              # a study parameter may be an input
    assert variable_problem(info, "y_max", "output") is None
    assert variable_problem(info, "I_1", "output") is None                 # a calculatedParameter can be read
    assert "an input, not a parameter" in variable_problem(info, "F_ext_y", "parameter")


# ---------------------------------------------------------------------------- FMI version and interface
def _with_version(src: Path, dest: Path, version: str) -> Path:
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dest, "w", zipfile.ZIP_DEFLATED) as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "modelDescription.xml":
                data = data.replace(b'fmiVersion="2.0"', f'fmiVersion="{version}"'.encode(), 1)
            zout.writestr(item, data)
    return dest


@pytest.mark.parametrize("version", ["1.0", "4.0"])
def test_fmi_1_and_unknown_versions_are_rejected_with_a_clear_message(fmu_path, tmp_path, version):
    """FMI 1.0 (and a version fmusa does not know) is refused; FMI 3.0 runs (tests/test_fmi3.py)."""
    fake = _with_version(fmu_path, tmp_path / f"ScrewVertebra_fmi{version[0]}.fmu", version)
    text = _study_text(fmu=fake.name)
    path = _write(tmp_path, text)
    study = parse_study(text, path)
    msg = _runner_error(study, tmp_path)
    assert str(path) in msg
    assert f"{path}:{_line_of(text, 'fmu:')}:" in msg
    assert f"is an FMI {version} FMU" in msg and "fmusa needs FMI 2.0" in msg
    with pytest.raises(FMUError, match=rf"FMI {re.escape(version)} FMU.*needs FMI 2\.0"):
        FMURunner(fake)


def test_interface_options_are_checked_against_the_fmu(fmu_path, tmp_path):
    # ScrewVertebra is co-simulation only: model exchange is not there, and a solver makes no sense
    text = _study_text(options="  interface: model-exchange\n")
    path = _write(tmp_path, text)
    errors = check_fmu(parse_study(text, path), fmu_path)
    assert len(errors) == 1
    assert errors[0].startswith(f"{path}:{_line_of(text, 'interface:')}:")
    assert "implements only co-simulation" in errors[0] and "interface: co-simulation or auto" in errors[0]

    text = _study_text(options="  solver: CVode\n  relative_tolerance: 1.0e-8\n")
    path = _write(tmp_path, text)
    errors = check_fmu(parse_study(text, path), fmu_path)
    assert len(errors) == 1 and f"{path}:{_line_of(text, 'solver:')}:" in errors[0]
    assert "applies to model exchange only" in errors[0] and "co-simulation" in errors[0]

    with pytest.raises(FMUError, match="implements only co-simulation"):
        FMURunner(fmu_path, interface="model-exchange")


def test_fmu_options_are_validated_with_file_and_line():
    base = _study_text()

    def err(options: str) -> str:
        text = base.replace("parameters:", f"fmu_options:\n{options}parameters:", 1)
        with pytest.raises(StudyError) as info:
            parse_study(text, "s.yaml")
        return str(info.value)

    assert re.match(r"s\.yaml:4: .*unknown interface 'model_exchnge'; did you mean 'model-exchange'",
                    err("  interface: model_exchnge\n"))
    assert re.match(r"s\.yaml:4: .*unknown solver 'CVod'; did you mean 'CVode'", err("  solver: CVod\n"))
    assert re.match(r"s\.yaml:4: .*relative_tolerance.* must be > 0", err("  relative_tolerance: -1\n"))
    assert re.match(r"s\.yaml:4: .*relative_tolerance.* must be < 1", err("  relative_tolerance: 2\n"))
    assert re.match(r"s\.yaml:5: key 'solver' in 'fmu_options' applies to model exchange only",
                    err("  interface: co-simulation\n  solver: Euler\n"))
    assert re.match(r"s\.yaml:4: key 'step_sise' is not allowed in 'fmu_options'; did you mean 'step_size'",
                    err("  step_sise: 0.1\n"))
    text = base.replace("stop_time: 12", "stop_time: 12\n  step: 0.01").replace(
        "parameters:", "fmu_options:\n  solver: Euler\n  step_size: 0.003\nparameters:", 1)
    with pytest.raises(StudyError, match=r"s\.yaml:5: .*must divide scenario.step .*step_size: 0.0025"):
        parse_study(text, "s.yaml")
    # aliases and case are accepted
    s = parse_study(base.replace("parameters:", "fmu_options:\n  interface: ME\n  solver: cvode\n"
                                                "parameters:", 1), "s.yaml")
    assert (s.fmu_options.interface, s.fmu_options.solver) == ("model-exchange", "CVode")
    assert parse_study(base, "s.yaml").fmu_options.interface == "auto"


def test_no_binary_and_no_sources_is_an_error(fmu_path, tmp_path):
    bare = tmp_path / "Bare.fmu"
    with zipfile.ZipFile(fmu_path) as zin, zipfile.ZipFile(bare, "w") as zout:
        for item in zin.infolist():
            if not item.filename.startswith(("binaries/", "sources/")):
                zout.writestr(item, zin.read(item.filename))
    text = _study_text(fmu=bare.name)
    path = _write(tmp_path, text)
    msg = _runner_error(parse_study(text, path), tmp_path)
    assert "no linux64 binary" in msg and "no C sources" in msg
    with pytest.raises(FMUError, match="no linux64 binary"):
        FMURunner(bare)


# ---------------------------------------------------------------------------- compiling from sources
def _sources_only(fmu_path: Path, dest: Path, patch: bytes | None = None) -> Path:
    """Our FMU without binaries/ (optionally with a line added to model.c)."""
    with zipfile.ZipFile(fmu_path) as zin, zipfile.ZipFile(dest, "w", zipfile.ZIP_DEFLATED) as zout:
        for item in zin.infolist():
            if item.filename.startswith("binaries/"):
                continue
            data = zin.read(item.filename)
            if patch is not None and item.filename == "sources/model.c":
                data += patch
            zout.writestr(item, data)
    return dest


def test_sources_only_fmu_is_compiled_before_the_study_and_matches_the_binary(tmp_path):
    """A study of an FMU that ships C sources only: built once before the study, in the study's folder, its runs
    those of the same FMU's binary, the build reused. On the spring test FMU: ScrewVertebra's own sources (about 30 s
    to compile) are rebuilt and checked against the shipped binary in tests/test_fmu_contract.py."""
    src = build_spring_fmu(tmp_path, "SpringSrc", binary=False, sources=True)
    binary = build_spring_fmu(tmp_path, "SpringBin", binary=True, sources=False)
    info = read_fmu_info(src)
    assert info.platforms == [] and info.can_compile
    results = {}
    for name, fmu in (("binary", binary), ("sources", src)):
        text = (f"name: spring\nfmu: {fmu}\nparameters:\n  c: {{variable: c}}\nscenario:\n  stop_time: 3\n"
                "metrics:\n  y_end: {output: y}\n  max_y: {output: y, reduce: max}\n"
                "stages:\n  grid:\n    values: {c: [100, 400, 1600]}\n")
        study = parse_study(text, tmp_path / f"{name}.yaml")
        run_study(study, tmp_path / name, figures=False, progress=False)
        runs = pd.read_csv(tmp_path / name / "runs.csv")
        assert (runs["status"] == "ok").all(), runs["message"]
        results[name] = runs.sort_values("c").reset_index(drop=True)
    built = list((tmp_path / "sources" / ".fmu").glob("SpringSrc-*/binaries/linux64/spring.so"))
    assert len(built) == 1
    assert not (tmp_path / "binary" / ".fmu").exists()           # the shipped binary is used as it is
    assert results["binary"]["y_end"].to_numpy() == pytest.approx([0.1, 0.025, 0.00625], rel=1e-3)   # F / c
    for col in ("y_end", "max_y"):
        np.testing.assert_allclose(results["sources"][col], results["binary"][col], rtol=1e-9, err_msg=col)
    # a second preparation reuses the build
    again = prepare_fmu(src, workdir=tmp_path / "sources" / ".fmu")
    assert again == built[0].parents[2]


def test_fmurunner_builds_a_sources_only_fmu_itself(tmp_path):
    """FMURunner compiles a sources-only FMU on its own (no study around it). A small FMU of ours, not
    ScrewVertebra (whose sources the test above and tests/test_fmu_contract.py compile already, ~40 s each)."""
    src = build_spring_fmu(tmp_path, "SpringSrc", binary=False, sources=True)
    shipped = build_spring_fmu(tmp_path, "SpringBin", binary=True, sources=False)
    assert read_fmu_info(src).platforms == []
    with FMURunner(src) as built, FMURunner(shipped) as binary:
        a = built.run_final({"c": 400.0}, 3.0, ["y"])
        b = binary.run_final({"c": 400.0}, 3.0, ["y"])
        unzipdir = built.unzipdir
    assert a["y"] == pytest.approx(0.025, rel=1e-4)                    # the spring's static deflection
    assert a == pytest.approx(b, rel=1e-12)
    assert not unzipdir.exists()        # the extracted, compiled copy is removed on close


def test_a_failing_build_names_the_fmu_and_shows_the_compiler_output(fmu_path, tmp_path):
    broken = _sources_only(fmu_path, tmp_path / "Broken.fmu", patch=b"\nthis is not C;\n")
    text = _study_text(fmu=broken.name)
    path = _write(tmp_path, text)
    with pytest.raises(FMUCompileError) as info:
        StudyRunner(parse_study(text, path), tmp_path / "out", resume=False, workers=1, scheduler=None,
                    progress=False)
    msg = str(info.value)
    assert str(path) in msg and "ScrewVertebra" in msg and str(broken) in msg
    assert "building one from its C sources" in msg and "model.c" in msg
    assert "error" in msg.lower()                                 # the compiler's own words
    assert "this is not C" in msg or "unknown type name" in msg


def test_check_runs_without_loading_the_binary(tmp_path):
    """check_fmu reads the model description only: a sources-only FMU is checked before it is built."""
    fmu = build_spring_fmu(tmp_path, "SpringSrc", binary=False, sources=True)
    text = (f"name: spring\nfmu: {fmu}\n"
            "parameters:\n  c: {variable: cc}\n"
            "scenario:\n  stop_time: 3\n"
            "metrics:\n  max_y: {output: y, reduce: max}\n"
            "stages:\n  grid:\n    values: {c: [100]}\n")
    path = _write(tmp_path, text)
    msg = _runner_error(parse_study(text, path), tmp_path)
    assert "no variable 'cc'; closest parameter names: c" in msg
    assert not (tmp_path / "out" / ".fmu").exists()              # nothing was compiled


def test_build_without_cmake_falls_back_to_the_c_compiler(tmp_path, monkeypatch):
    fmu = build_spring_fmu(tmp_path, "SpringSrc", binary=False, sources=True)
    which = shutil.which
    monkeypatch.setattr(shutil, "which", lambda name, *a, **k: None if name == "cmake" else which(name, *a, **k))
    built = prepare_fmu(fmu, workdir=tmp_path / "build")
    assert (built / "binaries" / "linux64" / "spring.so").is_file()
    with FMURunner(built) as me:
        assert me.interface == "model-exchange"
        assert me.run_final({"c": 400.0}, 3.0, ["y"])["y"] == pytest.approx(0.025, rel=1e-4)
    assert (built / "binaries" / "linux64" / "spring.so").is_file()   # a directory is used in place


# ---------------------------------------------------------------------------- a driven run that fails
def test_a_driven_run_that_fails_names_the_step_the_call_and_the_fmus_words(fmu_path):
    """A measured drive through ScrewVertebra with a work budget of five internal steps: the run stops in its
    first communication step that needs more. The error names that step, fmi2DoStep and its status, and the
    FMU's own message; the instance is usable for the next run (which then succeeds)."""
    from fmusa.fmi.info import FMURunError
    from fmusa.fmi.plans import DrivenPlan

    t = np.linspace(0.0, 1.0, 21)
    y = np.interp(t, [0.0, 0.5, 1.0], [0.0, 1e-3, 1e-3])
    with FMURunner(fmu_path) as r:
        fixed = {"mode": 2.0, "use_y_in": 1.0, "max_steps": 5.0}
        plan = DrivenPlan(r, ["c_y", "d_y"], fixed, "y_in", ["F_meas"])
        with pytest.raises(FMURunError) as info:
            plan([2e5, 100.0], t, y)
        msg = str(info.value)
        assert re.search(r"in the communication step from t = [0-9.e-]+ s to [0-9.e-]+ s", msg), msg
        assert "fmi2DoStep" in msg and "work budget used up" in msg, msg
        ok = DrivenPlan(r, ["c_y", "d_y"], {"mode": 2.0, "use_y_in": 1.0}, "y_in", ["F_meas"])([2e5, 100.0], t, y)
    assert np.all(np.isfinite(ok)) and ok[-1, 0] == pytest.approx(2e5 * 1e-3, rel=0.05)
