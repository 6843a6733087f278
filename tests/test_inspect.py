"""`fmusa inspect FMU`: what an FMU offers, and a readable table of its variables (or CSV)."""
from __future__ import annotations

import csv
import io
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from fmusa.cli import main

import contract as fmu_contract
from fmus.me_spring.build import build_spring_fmu

#: ../shared beside the repository, or $FMUSA_SHARED_DIR
SHARED = Path(os.environ.get("FMUSA_SHARED_DIR") or Path(__file__).resolve().parents[2] / "shared")


@pytest.fixture(scope="module")
def contract() -> list[dict[str, str]]:
    """The FMU's variable contract (read from the Modelica source by fmu/generate.py), one row per
    scalar variable: the counts inspect must report."""
    rows = [{"name": v.name, "causality": v.causality} for v in fmu_contract.variables()]
    assert len(rows) >= 118 and len({r["name"] for r in rows}) == len(rows)      # not vacuous
    return rows


def _count(rows: list[dict[str, str]], causality: str) -> int:
    return sum(r["causality"] == causality for r in rows)


def _inspect(capsys, *args: str) -> tuple[int, str, str]:
    code = main(["inspect", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def _header(out: str) -> dict[str, str]:
    head = out.split("\n\n", 1)[0]
    rows = {}
    for line in head.splitlines():
        if line[:1] != " ":
            key, _, value = line.partition("  ")
            rows[key.strip()] = value.strip()
    return rows


def _table(out: str) -> list[list[str]]:
    """Rows of the variable table split on its column starts (taken from the dashes line)."""
    lines = out.split("\n\n", 1)[1].splitlines()
    dashes = lines[1]
    starts = [i for i, ch in enumerate(dashes) if ch == "-" and (i == 0 or dashes[i - 1] == " ")]
    bounds = list(zip(starts, starts[1:] + [None]))
    return [[line[a:b].strip() for a, b in bounds] for line in lines[2:] if line and not line.startswith("(")]


@pytest.fixture(scope="module")
def spring(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("inspect_fmus")
    return {"me": build_spring_fmu(d, "SpringME"),
            "both": build_spring_fmu(d, "SpringBoth", ("co-simulation", "model-exchange")),
            "sources": build_spring_fmu(d, "SpringSrc", binary=False, sources=True)}


def test_inspect_our_fmu(capsys, fmu_path, monkeypatch, contract):
    monkeypatch.setenv("COLUMNS", "120")
    code, out, _ = _inspect(capsys, fmu_path)
    assert code == 0
    head = _header(out)
    assert head["FMI version"] == "2.0"
    assert head["model name"] == "ScrewVertebra"
    assert head["interfaces"] == "co-simulation (CS), model identifier ScrewVertebra"
    assert head["binaries"].startswith("linux64")
    assert head["runs here"] == "yes: FMI 2.0, co-simulation; the linux64 binary loads"
    assert head["sources"] == "4 files listed under <SourceFiles> (fmi2.c, model.c, solver.c, sv_generated.c)"
    assert head["default experiment"] == "start 0 s, stop 12 s, step 0.01 s"
    counts = {c: _count(contract, c) for c in ("parameter", "calculatedParameter", "input", "output")}
    assert counts["calculatedParameter"] == 3 and counts["input"] == 7
    assert head["variables"] == (f"{len(contract)} ({counts['parameter']} parameter, "
                                 f"{counts['calculatedParameter']} calculatedParameter, {counts['input']} input, "
                                 f"{counts['output']} output)")
    rows = {r[0]: r for r in _table(out)}
    assert len(rows) == len(contract)
    assert {name: r[1] for name, r in rows.items()} == {r["name"]: r["causality"] for r in contract}
    assert rows["c_y"][:6] == ["c_y", "parameter", "fixed", "Real", "N/m", "823224"]
    assert rows["c_y"][6].startswith("Interface stiffness along the screw")
    assert rows["I_1"][1:4] == ["calculatedParameter", "fixed", "Real"] and rows["I_1"][5] == ""
    assert rows["mode"][3] == "Integer"
    assert rows["y_max"][1:3] == ["output", "continuous"]
    assert rows["phi_inertia"][5] == "0.2837941092"          # long starts shortened to 10 digits
    # every line fits the terminal; long descriptions are cut with an ellipsis
    assert max(len(line) for line in out.split("\n\n", 1)[1].splitlines()) <= 120
    assert any(r[6].endswith("…") for r in rows.values())


def test_inspect_filters_by_causality_and_name(capsys, fmu_path, contract):
    code, out, _ = _inspect(capsys, fmu_path, "--causality", "input")
    assert code == 0
    names = [r[0] for r in _table(out)]
    assert names == ["F_ext_x", "F_ext_y", "F_ext_z", "T_ext_x", "T_ext_y", "T_ext_z", "y_in"]
    assert f"(7 of {len(contract)} variables)" in out
    code, out, _ = _inspect(capsys, fmu_path, "--causality", "output,calculatedParameter", "--name", "*_max")
    assert sorted(r[0] for r in _table(out)) == ["v_y_max", "y_max"]
    code, out, _ = _inspect(capsys, fmu_path, "--causality", "parameter", "--name", "d_*")
    assert sorted(r[0] for r in _table(out)) == sorted(["d_x", "d_y", "d_z", "d_alpha", "d_beta", "d_gamma"])
    code, out, _ = _inspect(capsys, fmu_path, "--name", "SCREW")       # a plain word: anywhere, any case
    assert sorted(r[0] for r in _table(out)) == ["D_screw", "L_screw"]
    code, out, _ = _inspect(capsys, fmu_path, "--causality", "input", "--name", "nothing")
    assert code == 0 and "no variables match causality input and name 'nothing'" in out


def test_inspect_unknown_causality_is_an_error(capsys, fmu_path):
    code, out, err = _inspect(capsys, fmu_path, "--causality", "outpt")
    assert code == 2 and "unknown causality 'outpt'; did you mean output?" in err


def test_inspect_csv(capsys, fmu_path, contract):
    code, out, _ = _inspect(capsys, fmu_path, "--csv")
    assert code == 0
    rows = list(csv.DictReader(io.StringIO(out)))
    assert [r["name"] for r in rows] == [r["name"] for r in contract]
    assert list(rows[0]) == ["name", "causality", "variability", "type", "unit", "start", "description"]
    c_y = next(r for r in rows if r["name"] == "c_y")
    assert c_y["unit"] == "N/m" and float(c_y["start"]) == 823224
    assert c_y["description"] == "Interface stiffness along the screw axis y (eq. 1)"      # not truncated
    code, out, _ = _inspect(capsys, fmu_path, "--csv", "--causality", "calculatedParameter")
    assert [r["name"] for r in csv.DictReader(io.StringIO(out))] == ["I_1", "I_2", "I_3"]


def test_inspect_model_exchange_fmu(capsys, spring):
    code, out, _ = _inspect(capsys, spring["me"])
    assert code == 0
    head = _header(out)
    assert head["interfaces"] == "model exchange (ME), model identifier spring"
    assert head["ME states / events"] == "2 continuous states, 0 event indicators"
    assert head["sources"] == "none"
    assert head["default experiment"] == "start 0 s, stop 3 s, tolerance 1e-06"
    rows = {r[0]: r for r in _table(out)}
    assert rows["F_max"][:6] == ["F_max", "parameter", "tunable", "Real", "N", "10"]
    assert rows["y_static"][1] == "calculatedParameter"
    assert rows["g"][1:3] == ["local", "constant"]
    assert rows["F_ext"][1] == "input"
    code, out, _ = _inspect(capsys, spring["both"])
    assert _header(out)["interfaces"] == ("co-simulation (CS), model identifier spring, "
                                          "model exchange (ME), model identifier spring")


def test_inspect_sources_only_fmu(capsys, spring):
    code, out, _ = _inspect(capsys, spring["sources"])
    head = _header(out)
    assert head["binaries"] == "none"
    assert head["sources"] == "1 file listed under <SourceFiles> (spring.c)"
    assert head["runs here"].startswith("once built: no linux64 binary; fmusa builds one from the C sources")


def test_inspect_full_and_narrow_terminal(capsys, fmu_path, monkeypatch):
    monkeypatch.setenv("COLUMNS", "100")
    _, out, _ = _inspect(capsys, fmu_path)
    table = out.split("\n\n", 1)[1].splitlines()
    assert all(len(line) <= 100 for line in table)
    assert "Interface stiffness along the screw axis y (eq. 1)" not in out
    _, out, _ = _inspect(capsys, fmu_path, "--full")
    assert "Interface stiffness along the screw axis y (eq. 1)" in out


def test_inspect_rejects_fmi1_with_a_clear_message(capsys, fmu_path, tmp_path):
    fake = tmp_path / "Fmi1.fmu"
    with zipfile.ZipFile(fmu_path) as zin, zipfile.ZipFile(fake, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename == "modelDescription.xml":
                data = data.replace(b'fmiVersion="2.0"', b'fmiVersion="1.0"', 1)
            zout.writestr(item, data)
    code, out, err = _inspect(capsys, fake)
    assert code == 2
    assert "is an FMI 1.0 FMU" in err and "fmusa needs FMI 2.0 or 3.0" in err
    code, out, err = _inspect(capsys, tmp_path / "missing.fmu")
    assert code == 1 and "FMU not found" in err


def test_inspect_command_line(fmu_path):
    """The installed `fmusa` entry point, piped into a pager that stops early, exits cleanly."""
    exe = Path(sys.executable).parent / "fmusa"
    proc = subprocess.run(f"'{exe}' inspect '{fmu_path}' | head -n 3", shell=True, capture_output=True,
                          text=True)
    assert proc.stdout.splitlines()[1].split() == ["FMI", "version", "2.0"]
    assert "Traceback" not in proc.stderr


def _rewritten(fmu: Path, target: Path, edit) -> Path:
    """A copy of ``fmu`` whose modelDescription.xml is passed through ``edit`` (bytes -> bytes)."""
    with zipfile.ZipFile(fmu) as zin, zipfile.ZipFile(target, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            zout.writestr(item, edit(data) if item.filename == "modelDescription.xml" else data)
    return target


def test_inspect_says_a_binary_that_cannot_load_cannot_run(capsys, fmu_path, tmp_path):
    """A binary that is there but does not load (here: the linux64 directory holds a file that is no shared
    library, as a damaged export would) is "runs here: no", with the loader's reason and the fix; the real
    JModelica export, whose binary needs libgfortran.so.3, says that library."""
    bad = tmp_path / "Damaged.fmu"
    with zipfile.ZipFile(fmu_path) as zin, zipfile.ZipFile(bad, "w") as zout:
        for item in zin.infolist():
            data = zin.read(item.filename)
            if item.filename.startswith("binaries/linux64/"):
                data = b"not an ELF file"
            zout.writestr(item, data)
    code, out, _ = _inspect(capsys, bad)
    assert code == 0
    runs = _header(out)["runs here"]
    assert runs.startswith("no: the linux64 binary does not load: ") and "Fix:" in runs, runs
    jm = SHARED / "vendor-fmus" / "JModelica115_ControlledTemperature.fmu"
    if jm.is_file():
        code, out, _ = _inspect(capsys, jm)
        runs = _header(out)["runs here"]
        assert runs.startswith("no: the linux64 binary does not load") and "libgfortran.so.3" in runs, runs


def test_inspect_sources_are_summarised(capsys, tmp_path, monkeypatch):
    """An export with many sources (OpenModelica lists about 65) gets a count and three names, not a line of
    every file; --full lists them all."""
    om = SHARED / "vendor-fmus" / "OM1193_Mass_Damper.fmu"
    if not om.is_file():
        pytest.skip(f"{om} is not there")
    monkeypatch.setenv("COLUMNS", "300")
    code, out, _ = _inspect(capsys, om)
    line = _header(out)["sources"]
    n = int(line.split()[0])
    assert n > 20 and line.count(",") == 3 and "…" in line and "--full lists them" in line   # 3 names, then …
    code, out, _ = _inspect(capsys, om, "--full")
    assert _header(out)["sources"].count(",") == n - 1


def test_inspect_says_no_parameters_and_a_study_says_why(capsys, fmu_path, tmp_path):
    """An FMU without parameters: inspect says so, and a study that varies one is refused saying the FMU has
    none (not only "no variable 'c_y'" with the closest names of other variables)."""
    from fmusa.fmi.info import read_fmu_info, variable_problem

    none = _rewritten(fmu_path, tmp_path / "NoParameters.fmu",
                      lambda d: d.replace(b'causality="parameter"', b'causality="local"'))
    code, out, _ = _inspect(capsys, none, "--full")
    assert code == 0 and "; no parameters: a study can set only its inputs" in _header(out)["variables"]
    info = read_fmu_info(none)
    msg = variable_problem(info, "c_y", "parameter")
    assert "ScrewVertebra has no settable parameters at all" in msg, msg
    msg = variable_problem(info, "k_missing", "parameter")
    assert "has no variable 'k_missing'; ScrewVertebra has no parameters at all" in msg, msg
    # varied: the inputs count (the FMU has seven), so no such sentence there
    assert "at all" not in (variable_problem(info, "c_y", "varied") or "")


def test_inspect_says_an_fmi1_fmu_cannot_run(capsys, fmu_path, tmp_path):
    """An FMI 1.0 FMU fmpy can read is shown, with "runs here: no" and why, not a note at the end."""
    import fmusa.cli as cli

    class Info:          # what the reader gives for an FMI 1.0 export: the version is all that matters here
        fmi_version = "1.0"
    runs = cli._runs_here(Info(), "X.fmu: X is an FMI 1.0 FMU")
    assert runs.startswith("no: FMI 1.0; fmusa runs FMI 2.0 and 3.0 FMUs"), runs
