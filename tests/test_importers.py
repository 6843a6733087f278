"""dist/ScrewVertebra.fmu in importers that are not fmpy, each compared with fmpy on the same archive.

- libcosim (Open Simulation Platform, PyPI libcosimpy), which loads the FMU with its own FMI Library:
  the paper's 12 s pullout at (c_y, d_y) = (823224, 488) and the 6-DOF load case of studies/six_dof.yaml.
- tests/importer/fmi2_import.c, a minimal C importer (dlopen/LoadLibrary, fmi2 functions looked up by
  name, one doStep to the stop time), compiled with gcc and run on the linux64 binary, and compiled
  with mingw-w64 and run under wine on the win64 DLL inside the FMU.
- FMU Manipulation Toolbox (`fmutool -check`) finds the FMU compliant with FMI 2.0.
- The win64 DLL imports only Windows system DLLs and exports the FMI 2.0 co-simulation API.

Criterion: every compared value within 1e-12 relative of fmpy's (a velocity relative to the case's peak
v_y_max, see _scale). libcosim and the linux64 C importer run fmpy's binary and are bit-identical; the
win64 DLL, built against the Windows C runtime's libm, was measured within 4e-14 on the 6-DOF case.
The binaries are whatever the current fmu/*.c build (`make fmu`), so the comparison holds whatever the
solver does. A test skips, naming what to install, only where a tool is missing (CI's .ci/run installs
gcc-mingw-w64-x86-64 and wine; `pip install -e '.[test]'` installs libcosimpy and fmutool).

The wine prefix is created once and kept (its first start takes several seconds): $FMUSA_WINEPREFIX,
else <tmp>/fmusa-wineprefix-<uid>.
"""
from __future__ import annotations

import os
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import zipfile
from pathlib import Path

import pytest
import yaml
from fmpy import extract, read_model_description

from fmusa import FMURunner

ROOT = Path(__file__).resolve().parents[1]
IMPORTER_C = ROOT / "tests" / "importer" / "fmi2_import.c"
MODEL = "ScrewVertebra"
REL = 1e-12
MINGW_CC = "x86_64-w64-mingw32-gcc"
MINGW_OBJDUMP = "x86_64-w64-mingw32-objdump"
INSTALL_CROSS = "apt-get install gcc-mingw-w64-x86-64"
INSTALL_WINE = "apt-get install wine wine64"

# Imports the win64 DLL may have: Windows system DLLs only (no libgcc_s, libwinpthread, ...).
ALLOWED_DLLS = {"kernel32.dll", "msvcrt.dll", "ucrtbase.dll"}
ALLOWED_DLL_PREFIXES = ("api-ms-win-",)

FMI2_CS_FUNCTIONS = """fmi2GetTypesPlatform fmi2GetVersion fmi2SetDebugLogging fmi2Instantiate fmi2FreeInstance
fmi2SetupExperiment fmi2EnterInitializationMode fmi2ExitInitializationMode fmi2Terminate fmi2Reset fmi2GetReal
fmi2GetInteger fmi2GetBoolean fmi2GetString fmi2SetReal fmi2SetInteger fmi2SetBoolean fmi2SetString
fmi2GetFMUstate fmi2SetFMUstate fmi2FreeFMUstate fmi2SerializedFMUstateSize fmi2SerializeFMUstate
fmi2DeSerializeFMUstate fmi2GetDirectionalDerivative fmi2SetRealInputDerivatives fmi2GetRealOutputDerivatives
fmi2DoStep fmi2CancelStep fmi2GetStatus fmi2GetRealStatus fmi2GetIntegerStatus fmi2GetBooleanStatus
fmi2GetStringStatus""".split()


def _six_dof_case() -> dict:
    study = yaml.safe_load((ROOT / "studies" / "six_dof.yaml").read_text())
    return dict(params={k: float(v) for k, v in study["fixed"].items()},
                inputs={k: float(v) for k, v in study["scenario"]["inputs"].items()},
                stop=float(study["scenario"]["stop_time"]),
                outputs=["x", "y", "z", "alpha", "beta", "gamma", "v_x", "v_y", "v_z", "y_max", "v_y_max"])


CASES = {
    # the paper's pullout: 411 N ramped over 10 s (the FMU's defaults), one doStep to 12 s
    "pullout": dict(params={"c_y": 823224.0, "d_y": 488.0}, inputs={}, stop=12.0,
                    outputs=["y", "y_max", "v_y_max", "t_eq"]),
    # studies/six_dof.yaml: 411 N pull over 50 ms, lateral forces and an axial torque, to 0.1 s
    "six_dof": _six_dof_case(),
}


# ------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def fmu_copy(fmu_path, tmp_path_factory):
    """A private copy of the FMU (a rebuild of dist/ cannot swap it under the tests), extracted."""
    d = tmp_path_factory.mktemp("importers")
    copy = d / f"{MODEL}.fmu"
    shutil.copyfile(fmu_path, copy)
    unzipped = Path(extract(str(copy), unzipdir=str(d / "unzipped")))
    md = read_model_description(str(copy))
    return dict(path=copy, dir=unzipped, md=md, vars={v.name: v for v in md.modelVariables})


@pytest.fixture(scope="module")
def fmpy_results(fmu_copy):
    """fmpy's final values for every case (fmusa.FMURunner: FMU2Slave, one doStep)."""
    out = {}
    with FMURunner(fmu_copy["path"]) as fmu:
        for name, case in CASES.items():
            out[name] = fmu.run_final(case["params"], case["stop"], case["outputs"], inputs=case["inputs"] or None)
    return out


def _scale(k: str, ref: dict) -> float:
    """The magnitude a difference in output k is relative to, besides the values themselves: a
    velocity's is the case's peak axial velocity v_y_max. At the end of the 6-DOF case the screw is at
    rest and its velocities have decayed to ~1e-40..1e-75 m/s, noise of the last ulp of the
    equilibrium's libm-dependent digits (the win64 DLL uses the Windows C runtime's sin/cos/exp)."""
    if k.startswith("v_") and k != "v_y_max" and "v_y_max" in ref:
        return abs(ref["v_y_max"])
    return 0.0


def _compare(name: str, importer: str, got: dict, ref: dict, against: str = "fmpy") -> float:
    """Assert every output within REL of the reference's; return the largest relative difference."""
    worst, bad = 0.0, []
    for k, r in ref.items():
        g = got[k]
        scale = max(abs(r), abs(g), _scale(k, ref))
        rel = 0.0 if g == r else abs(g - r) / scale
        worst = max(worst, rel)
        if not rel <= REL:
            bad.append(f"{k}: {importer} {g!r}, {against} {r!r} (relative {rel:.3g})")
    print(f"{importer} vs {against}, {name}: largest relative difference {worst:.3g}")
    assert not bad, f"{importer} differs from {against} on {name} by more than {REL:g}:\n" + "\n".join(bad)
    return worst


# ------------------------------------------------------------------------------------------ libcosim
def _libcosim_run(fmu_file: Path, md_vars: dict, case: dict) -> dict:
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
    from libcosimpy.CosimObserver import CosimObserver
    from libcosimpy.CosimSlave import CosimLocalSlave

    log_output_level(CosimLogLevel.WARNING)
    stop_ns = round(case["stop"] * 1e9)           # libcosim's time is integer nanoseconds
    assert stop_ns / 1e9 == case["stop"]
    execution = CosimExecution.from_step_size(stop_ns)   # one step: one doStep from 0 to the stop time
    slave = CosimLocalSlave(fmu_path=str(fmu_file), instance_name="sv")
    index = execution.add_local_slave(slave)
    observer = CosimObserver.create_last_value()
    assert execution.add_observer(observer)
    for name, value in {**case["params"], **case["inputs"]}.items():
        v = md_vars[name]
        if v.type == "Real":
            ok = execution.real_initial_value(index, v.valueReference, float(value))
        elif v.type == "Integer":
            ok = execution.integer_initial_value(index, v.valueReference, int(value))
        else:
            ok = execution.boolean_initial_value(index, v.valueReference, bool(value))
        assert ok, f"libcosim rejected the initial value of {name}"
    assert execution.step(1), "libcosim's step failed"
    status = execution.status()
    assert status.current_time == stop_ns, status
    vrs = [md_vars[n].valueReference for n in case["outputs"]]
    values = observer.last_real_values(index, vrs)
    return dict(zip(case["outputs"], map(float, values)))


@pytest.mark.parametrize("name", list(CASES))
def test_libcosim_matches_fmpy(name, fmu_copy, fmpy_results):
    pytest.importorskip("libcosimpy", reason="libcosimpy is not installed (pip install -e '.[test]')")
    got = _libcosim_run(fmu_copy["path"], fmu_copy["vars"], CASES[name])
    _compare(name, "libcosim", got, fmpy_results[name])


# ------------------------------------------------------------------------------------------ fmutool
def test_fmutool_check_finds_the_fmu_compliant(fmu_copy):
    pytest.importorskip("fmu_manipulation_toolbox",
                        reason="fmu-manipulation-toolbox is not installed (pip install -e '.[test]')")
    fmutool = Path(sys.executable).with_name("fmutool")
    cmd = [str(fmutool)] if fmutool.exists() else [sys.executable, "-m", "fmu_manipulation_toolbox.cli.fmutool"]
    proc = subprocess.run(cmd + ["-input", str(fmu_copy["path"]), "-check"],
                          capture_output=True, text=True, timeout=120)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    assert "This FMU seems to be compliant with FMI-2.0." in out, out
    assert "No semantic error against the FMI-2 standard." in out, out
    problems = [ln for ln in out.splitlines() if ln.lstrip().startswith(("ERROR", "WARNING", "CRITICAL"))]
    assert not problems, out


# ------------------------------------------------------------------------------------------ C importer
def _importer_args(fmu_copy, case) -> list[str]:
    """SET... -- GET... for fmi2_import; Reals passed as their IEEE bits (exact under any C runtime)."""
    args = []
    for name, value in {**case["params"], **case["inputs"]}.items():
        v = fmu_copy["vars"][name]
        if v.type == "Real":
            args.append(f"r:{v.valueReference}=x{struct.unpack('<Q', struct.pack('<d', float(value)))[0]:016x}")
        elif v.type == "Integer":
            args.append(f"i:{v.valueReference}={int(value)}")
        else:
            args.append(f"b:{v.valueReference}={int(bool(value))}")
    return args + ["--"] + [str(fmu_copy["vars"][n].valueReference) for n in case["outputs"]]


def _run_importer(cmd: list[str], fmu_copy, case, env=None, timeout=120) -> dict:
    stop_bits = struct.unpack("<Q", struct.pack("<d", case["stop"]))[0]
    full = cmd + [fmu_copy["md"].guid, f"x{stop_bits:016x}"] + _importer_args(fmu_copy, case)
    # files, not pipes: wine's wineserver outlives the run (3 s) and would hold a pipe open that long
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.run(full, stdout=out, stderr=err, timeout=timeout, env=env)
        out.seek(0), err.seek(0)
        stdout, stderr = out.read(), err.read()
    assert proc.returncode == 0, f"{' '.join(full)}\nexit {proc.returncode}\n{stdout}\n{stderr}"
    by_vr = {}
    for line in stdout.splitlines():
        vr, bits, _ = line.split()
        by_vr[int(vr)] = struct.unpack("<d", struct.pack("<Q", int(bits, 16)))[0]
    return {n: by_vr[fmu_copy["vars"][n].valueReference] for n in case["outputs"]}


def _compile(cc: str, out: Path, include: Path, extra=()) -> Path:
    proc = subprocess.run([cc, "-std=c99", "-O2", "-Wall", "-Wextra", f"-I{include}",
                           "-o", str(out), str(IMPORTER_C), *extra], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, f"{cc} failed to compile {IMPORTER_C.name}:\n{proc.stderr}"
    return out


@pytest.fixture(scope="module")
def linux_importer(fmu_copy, tmp_path_factory):
    if shutil.which("gcc") is None:
        pytest.skip("gcc is not installed (apt-get install gcc)")
    # the FMI 2 headers are those the FMU carries in sources/
    return _compile("gcc", tmp_path_factory.mktemp("importer_linux") / "fmi2_import",
                    fmu_copy["dir"] / "sources", ["-ldl"])


@pytest.mark.parametrize("name", list(CASES))
def test_c_importer_on_linux64_matches_fmpy(name, linux_importer, fmu_copy, fmpy_results):
    so = fmu_copy["dir"] / "binaries" / "linux64" / f"{MODEL}.so"
    got = _run_importer([str(linux_importer), str(so)], fmu_copy, CASES[name])
    _compare(name, "C importer (linux64)", got, fmpy_results[name])


# ------------------------------------------------------------------------------------------ win64
def _require_cross_compiler():
    if shutil.which(MINGW_CC) is None:
        pytest.skip(f"{MINGW_CC} is not installed, so `make fmu` builds no win64 binary ({INSTALL_CROSS})")


@pytest.fixture(scope="module")
def win64_dll(fmu_copy) -> Path:
    _require_cross_compiler()
    dll = fmu_copy["dir"] / "binaries" / "win64" / f"{MODEL}.dll"
    assert dll.is_file(), (f"{MINGW_CC} is installed but the FMU has no binaries/win64/{MODEL}.dll: "
                           "rebuild it with `make fmu`")
    return dll


def test_fmu_carries_linux64_and_win64(fmu_copy, win64_dll):
    with zipfile.ZipFile(fmu_copy["path"]) as z:
        names = set(z.namelist())
    assert {f"binaries/linux64/{MODEL}.so", f"binaries/win64/{MODEL}.dll"} <= names


def test_win64_dll_imports_only_system_dlls_and_exports_fmi2(win64_dll):
    if shutil.which(MINGW_OBJDUMP) is None:
        pytest.skip(f"{MINGW_OBJDUMP} is not installed ({INSTALL_CROSS})")
    out = subprocess.run([MINGW_OBJDUMP, "-p", str(win64_dll)], capture_output=True, text=True,
                         check=True, timeout=60).stdout
    imports = {ln.split("DLL Name:")[1].strip().lower() for ln in out.splitlines() if "DLL Name:" in ln}
    assert imports, out
    foreign = {d for d in imports if d not in ALLOWED_DLLS and not d.startswith(ALLOWED_DLL_PREFIXES)}
    assert not foreign, f"the DLL needs more than Windows system DLLs: {sorted(foreign)} (all: {sorted(imports)})"
    # the export table: lines "[ n] name" after "[Ordinal/Name Pointer] Table"
    table = out.split("[Ordinal/Name Pointer] Table", 1)[1] if "[Ordinal/Name Pointer] Table" in out else out
    exported = {ln.split("]", 1)[1].strip() for ln in table.splitlines() if ln.strip().startswith("[")}
    missing = sorted(set(FMI2_CS_FUNCTIONS) - exported)
    assert not missing, f"the DLL does not export {missing}"
    others = sorted(n for n in exported if not n.startswith("fmi2"))
    assert not others, f"the DLL exports more than the fmi2 functions: {others}"


def _wine() -> str | None:
    for name in ("wine", "wine64"):
        if shutil.which(name):
            return shutil.which(name)
    return None


@pytest.fixture(scope="module")
def wine_env():
    wine = _wine()
    if wine is None:
        pytest.skip(f"wine is not installed, so the win64 DLL cannot be run here ({INSTALL_WINE})")
    prefix = os.environ.get("FMUSA_WINEPREFIX") or os.path.join(tempfile.gettempdir(),
                                                                 f"fmusa-wineprefix-{os.getuid()}")
    env = {k: v for k, v in os.environ.items() if k != "DISPLAY"}
    # no debug output, no Mono/Gecko install prompts, no window
    env.update(WINEPREFIX=prefix, WINEDEBUG="-all", WINEDLLOVERRIDES="mscoree,mshtml=")
    state = {"new prefix": not os.path.isdir(prefix)}    # the first run creates it
    return wine, env, state


@pytest.fixture(scope="module")
def windows_importer(fmu_copy, win64_dll, tmp_path_factory):
    # static: the .exe needs no mingw runtime DLL under wine
    return _compile(MINGW_CC, tmp_path_factory.mktemp("importer_win64") / "fmi2_import.exe",
                    fmu_copy["dir"] / "sources", ["-static"])


def _windows_path(p: Path) -> str:
    return "Z:" + str(p.resolve()).replace("/", "\\")    # wine maps / to drive Z:


@pytest.mark.timeout(600)
@pytest.mark.parametrize("name", list(CASES))
def test_win64_dll_under_wine_matches_linux64_and_fmpy(name, windows_importer, wine_env, win64_dll,
                                                       linux_importer, fmu_copy, fmpy_results):
    wine, env, state = wine_env
    first, state["new prefix"] = state["new prefix"], False
    t0 = time.perf_counter()
    got = _run_importer([wine, _windows_path(windows_importer), _windows_path(win64_dll)], fmu_copy,
                        CASES[name], env=env, timeout=540)
    dt = time.perf_counter() - t0
    print(f"wine run ({'new prefix ' if first else ''}{env['WINEPREFIX']}): {dt:.2f} s")
    so = fmu_copy["dir"] / "binaries" / "linux64" / f"{MODEL}.so"
    linux = _run_importer([str(linux_importer), str(so)], fmu_copy, CASES[name])
    _compare(name, "win64 DLL under wine", got, linux, against="linux64 binary (C importer)")
    _compare(name, "win64 DLL under wine", got, fmpy_results[name])
