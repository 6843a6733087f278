"""The coupled system written as an SSP 1.0 archive (fmusa.cosim.ssp) and run by a tool that is not fmusa's
master: libcosim (libcosimpy, fixed-step co-simulation, which applies the SSD's parameter bindings and the
connections' linear transformations). Its run reproduces fmusa's prediction (me-implicit) to first order in
its step. (FMPy 0.3.32's SSP runner does not apply an SSD's linear transformations, so it cannot run a
coupling whose force enters the model with a sign; the archive is read and schema-validated by FMPy's reader.)
"""
from __future__ import annotations

import os
import zipfile
from pathlib import Path

import numpy as np
import pytest

from cosim_fmus import build_body
from fmusa.cosim import Coupling, CouplingError, simulate_coupled
from fmusa.cosim.ssp import validate_ssd, write_ssp

ROOT = Path(__file__).resolve().parents[1]
ELEMENT = ROOT / "dist" / "InterfaceElement.fmu"
SHARED = Path(os.environ.get("FMUSA_SHARED_DIR") or ROOT.parent / "shared")
OM = SHARED / "vendor-fmus" / "OM1193_Mass_Damper.fmu"
MODEL = {"m": 1.0, "k": 100.0, "b": 1.0, "x0": 0.01}
ELEMENT_PARAMS = {"c": 1e4, "d": 20.0, "yield_ratio": 0.2, "yield_F": 40.0}
T = 0.3
TIMES = np.linspace(0.0, T, 31)


def run_libcosim(folder: Path, step: float) -> np.ndarray:
    """The model's x at TIMES, run by libcosim from the unpacked archive at a fixed step."""
    pytest.importorskip("libcosimpy")
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimObserver import CosimObserver
    from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
    log_output_level(CosimLogLevel.ERROR)
    ex = CosimExecution.from_ssp_file(str(folder), step_size=int(round(step * 1e9)))
    name = lambda s: s.decode() if isinstance(s, bytes) else s   # noqa: E731
    slaves = {name(s.name): s.index for s in ex.slave_infos()}
    obs = CosimObserver.create_last_value()
    ex.add_observer(obs)
    ref = {name(v.name): v.reference for v in ex.slave_variables(slaves["model"])}["x"]
    out = [MODEL["x0"]]
    for t in TIMES[1:]:
        assert ex.simulate_until(int(round(t * 1e9)))
        out.append(obs.last_real_values(slaves["model"], [ref])[0])
    return np.array(out)


@pytest.fixture(scope="module")
def system(tmp_path_factory):
    if not ELEMENT.is_file():
        pytest.fail("dist/InterfaceElement.fmu is missing: run `make fmu`")
    root = tmp_path_factory.mktemp("ssp")
    body = build_body(root, ("model-exchange", "co-simulation"), False)
    coupling = Coupling(body, ELEMENT, "f", "x", "v")
    archive = write_ssp(root / "Coupled.ssp", coupling, MODEL, ELEMENT_PARAMS, T)
    folder = root / "unpacked"
    with zipfile.ZipFile(archive) as z:
        z.extractall(folder)
    return coupling, archive, folder


def test_archive_is_valid_ssp(system):
    coupling, archive, folder = system
    names = zipfile.ZipFile(archive).namelist()
    assert set(names) == {"SystemStructure.ssd", "resources/Body.fmu", "resources/InterfaceElement.fmu",
                          "resources/model.ssv", "resources/element.ssv"}
    ssd = (folder / "SystemStructure.ssd").read_text(encoding="utf-8")
    assert validate_ssd(ssd) == []
    assert validate_ssd((folder / "resources" / "element.ssv").read_text(encoding="utf-8"),
                        "SystemStructureParameterValues.xsd") == []
    from fmpy.ssp.ssd import read_ssd                       # a second reader, validating as it reads
    sd = read_ssd(str(archive), validate=True)
    components = {e.name: e for e in sd.system.elements}
    assert set(components) == {"model", "element"}
    bound = {p.name: p.value for b in components["element"].parameterBindings for s in b.parameterValues
             for p in s.parameters}
    assert {k: float(v) for k, v in bound.items()} == ELEMENT_PARAMS
    # the validator can fail: a connection without its end is refused
    assert validate_ssd(ssd.replace('endConnector="f"', "")) != []


def test_libcosim_reproduces_fmusas_prediction(system):
    """libcosim's fixed-step run of the archive against fmusa's me-grid prediction: relative error (to the
    largest |x|) below 1 % at a 1e-4 s step, about halving with the step (first order)."""
    coupling, _, folder = system
    pred = simulate_coupled(coupling, MODEL, ELEMENT_PARAMS, T, TIMES, ["x"])
    assert pred.scheme == "me-grid"
    x = pred.frame["x"].to_numpy()
    errors = {}
    for step in (2e-4, 1e-4):
        got = run_libcosim(folder, step)
        errors[step] = float(np.max(np.abs(got - x)) / np.max(np.abs(x)))
    assert errors[1e-4] < 1e-2, errors
    assert 1.5 < errors[2e-4] / errors[1e-4] < 2.5, errors
    # the parameters in the archive are the ones that ran: without yield the prediction is far off
    linear = simulate_coupled(coupling, MODEL, {"c": 1e4, "d": 20.0}, T, TIMES, ["x"]).frame["x"].to_numpy()
    assert np.max(np.abs(linear - x)) / np.max(np.abs(x)) > 10 * errors[1e-4]


def test_archive_needs_the_motion_as_outputs(tmp_path):
    """OM1193 exports its rate only as a state (damper.v_rel): an SSP connection must start at an output."""
    if not OM.is_file():
        pytest.skip("the shared vendor FMUs are not there")
    coupling = Coupling(OM, ELEMENT, "f", "y", "damper.v_rel", velocity_sign=-1.0)
    with pytest.raises(CouplingError, match="damper.v_rel.*not an output"):
        write_ssp(tmp_path / "x.ssp", coupling, {}, {}, 1.0)
