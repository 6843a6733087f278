"""The coupled physics against a single model: ScrewVertebra with an axial effect switched on, against
ScrewVertebra split at its axial interface (c_y = d_y = 0, the interface force entering at its input F_ext_y)
coupled with the element FMU carrying c_y, d_y and the effect, at the paper's stiffness.

The split body is ScrewVertebra's own generated sources built here with FMU state support (-DMODEL_FMU_STATE=1,
its model description saying canGetAndSetFMUstate="true"), so the master runs cs-iterate. Force-driven: the
coupled run reproduces the single FMU. Motion-driven (y prescribed): the interface force is the element's under
the prescribed motion, so the element driven alone reproduces ScrewVertebra's F_y.
"""
from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

import fmpy
from fmusa.cosim import Coupling, simulate_coupled
from test_element_fmu import drive_cs

ROOT = Path(__file__).resolve().parents[1]
SV = ROOT / "dist" / "ScrewVertebra.fmu"
ELEMENT = ROOT / "dist" / "InterfaceElement.fmu"
SOURCES = ROOT / "build" / "fmu" / "sources"
PAPER = {"c": 823224.0, "d": 488.0}
YIELD = {"yield_ratio": 0.2, "yield_F": 150.0}


@pytest.fixture(scope="module")
def split_body(tmp_path_factory) -> Path:
    if not sys.platform.startswith("linux") or shutil.which("gcc") is None:
        pytest.skip("the split body is built with gcc as a linux64 binary")
    if not (SOURCES / "sv_generated.c").is_file():
        pytest.fail("build/fmu/sources is missing: run `make fmu`")
    root = tmp_path_factory.mktemp("split")
    tree = root / "tree"
    so = tree / "binaries" / "linux64" / "ScrewVertebra.so"
    so.parent.mkdir(parents=True)
    subprocess.run(["gcc", "-std=c99", "-O2", "-fPIC", "-shared", "-DMODEL_FMU_STATE=1", "-I", str(SOURCES), "-o",
                    str(so)] + [str(SOURCES / f) for f in ("fmi2.c", "model.c", "solver.c", "sv_generated.c")]
                   + ["-lm"], check=True)
    md = (ROOT / "build" / "fmu" / "modelDescription.xml").read_text(encoding="utf-8")
    assert md.count('canGetAndSetFMUstate="false"') == 1
    (tree / "modelDescription.xml").write_text(md.replace('canGetAndSetFMUstate="false"',
                                                          'canGetAndSetFMUstate="true"'), encoding="utf-8")
    fmu = root / "ScrewVertebraBody.fmu"
    with zipfile.ZipFile(fmu, "w") as z:
        for f in sorted(tree.rglob("*")):
            if f.is_file():
                z.write(f, f.relative_to(tree).as_posix())
    return fmu


@pytest.mark.slow
def test_force_driven_split_reproduces_the_single_model(split_body):
    """411 N ramped over 0.05 s, yield on: y and the interface force of the split within 2e-4 (relative to the
    largest) of the single FMU; the cost is in the result (measured: ~1.4e5 FMU calls, ~16 s on a loaded
    machine, against 0.3 s for the single FMU)."""
    load = {"F_max": 411.0, "t_ramp": 0.05, "monitors": False}
    T, times = 0.1, np.linspace(0.0, 0.1, 21)
    single = fmpy.simulate_fmu(str(SV), stop_time=T, output_interval=T / 20, start_values={**load, **YIELD},
                               output=["y", "F_y"])
    cp = Coupling(split_body, ELEMENT, "F_ext_y", "y", "v_y", scheme="auto")
    r = simulate_coupled(cp, {**load, "c_y": 0.0, "d_y": 0.0}, {**PAPER, **YIELD}, T, times, ["y"], step=1e-3)
    assert r.scheme == "cs-iterate" and r.converged
    for mine, theirs in ((r.frame["y"], single["y"]), (r.frame["F"], single["F_y"])):
        assert np.max(np.abs(mine - theirs)) / np.max(np.abs(theirs)) < 2e-4
    assert np.max(np.abs(single["y"])) > 1.5 * 411.0 / PAPER["c"]     # yielded: softer than the linear spring


def test_motion_driven_interface_force_is_the_elements(tmp_path):
    """Motion-driven (y = v_pull t), yield on: ScrewVertebra's F_y equals the element's F under the same motion."""
    v_pull = 0.02
    T, times = 0.1, np.linspace(0.0, 0.1, 101)
    single = fmpy.simulate_fmu(str(SV), stop_time=T, output_interval=T / 100,
                               start_values={"mode": 2, "v_pull": v_pull, "monitors": False, **YIELD},
                               output=["y", "F_y"])
    unzipped = Path(fmpy.extract(str(ELEMENT), str(tmp_path / "el")))
    el = drive_cs(unzipped, {**PAPER, **YIELD}, times, v_pull * times, np.full_like(times, v_pull))
    assert np.max(np.abs(single["y"] - v_pull * times)) < 1e-12
    assert np.max(np.abs(el["F"] - single["F_y"])) / np.max(np.abs(single["F_y"])) < 1e-5
    assert np.max(single["F_y"]) < 0.5 * PAPER["c"] * v_pull * T                 # the yield acted
