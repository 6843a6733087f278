"""A diagnosed extended model of a vendor export, written as SSP by the diagnosis and replayed by libcosim.

OpenModelica's Mass_Damper export (../shared/vendor-fmus/OM1193_Mass_Damper.fmu, or $FMUSA_SHARED_DIR) gives the
mass's position ``y`` as an output, but its velocity ``mass.v`` is a state, not an output, and an SSP connection
starts at an output: as exported, the diagnosis says why it writes no archive (tests/test_diagnose_attached.py).
The model a user re-exports for coupling has the velocity as an output too (OpenModelica: a top-level
``output Real v = mass.v;``). That re-export is made here from the vendor file itself, in a temporary folder:
the same binary and sources, its modelDescription.xml declaring the state ``mass.v`` an output (listed under
ModelStructure/Outputs) — nothing else changes, fmi2GetReal returns the same number.

The measured force enters the model at ``f``, the input the element's force also takes; an SSP input takes one
connection, so the replay carries no drive. It is a release instead: the spring's unstretched length set
off by 5 cm (``spring.s_rel0``), the mass swings through the element's gap and settles. libcosim runs the OM
export's co-simulation interface (explicit Euler at the communication step, PROVENANCE.md) at a fixed step:
first order, so the tolerance is stated at a step and the error must halve with the step.
"""
from __future__ import annotations

import os
import re
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("FMUSA_SHARED_DIR") or ROOT.parent / "shared")
OM = SHARED / "vendor-fmus" / "OM1193_Mass_Damper.fmu"
ELEMENT = ROOT / "dist" / "InterfaceElement.fmu"

pytestmark = [pytest.mark.skipif(not ELEMENT.is_file(), reason="dist/InterfaceElement.fmu is not built (make fmu)"),
              pytest.mark.skipif(not OM.is_file(), reason=f"{OM} is not there (set FMUSA_SHARED_DIR)")]

#: the diagnosed element (the backlash case of tests/attached_reference.py) and the release
ELEMENT_PARAMS = {"c": 5.0e3, "d": 20.0, "gap": 0.02}
MODEL_PARAMS = {"spring.s_rel0": 0.45}     # the model's spring pulls to y = 0.05 m; starts at y = 0
T = 0.5
TIMES = np.linspace(0.0, T, 51)


def with_velocity_output(src: Path, dest: Path) -> Path:
    """The export with the state ``mass.v`` declared an output (modelDescription.xml only)."""
    with zipfile.ZipFile(src) as z:
        files = {n: z.read(n) for n in z.namelist()}
    xml = files["modelDescription.xml"].decode("utf-8")
    blocks = re.findall(r"<ScalarVariable\b", xml)
    start = xml.index('name="mass.v"')
    index = xml[:start].count("<ScalarVariable") + 0     # 1-based index: the block opened just before the name
    assert 0 < index <= len(blocks)
    head = xml.rindex("<ScalarVariable", 0, start)
    xml = xml[:head] + '<ScalarVariable causality="output"' + xml[head + len("<ScalarVariable"):]
    xml = xml.replace("<Outputs>", f'<Outputs>\n      <Unknown index="{index}" />', 1)
    files["modelDescription.xml"] = xml.encode("utf-8")
    with zipfile.ZipFile(dest, "w", zipfile.ZIP_DEFLATED) as z:
        for n, data in files.items():
            z.writestr(n, data)
    return dest


def run_libcosim(folder: Path, step: float) -> np.ndarray:
    """The model's y at TIMES, run by libcosim from the unpacked archive at a fixed step."""
    pytest.importorskip("libcosimpy")
    from libcosimpy.CosimExecution import CosimExecution
    from libcosimpy.CosimLogging import CosimLogLevel, log_output_level
    from libcosimpy.CosimObserver import CosimObserver
    log_output_level(CosimLogLevel.ERROR)
    ex = CosimExecution.from_ssp_file(str(folder), step_size=int(round(step * 1e9)))
    name = lambda s: s.decode() if isinstance(s, bytes) else s   # noqa: E731
    slaves = {name(s.name): s.index for s in ex.slave_infos()}
    obs = CosimObserver.create_last_value()
    ex.add_observer(obs)
    ref = {name(v.name): v.reference for v in ex.slave_variables(slaves["model"])}["y"]
    out = [0.0]
    for t in TIMES[1:]:
        assert ex.simulate_until(int(round(t * 1e9)))
        out.append(obs.last_real_values(slaves["model"], [ref])[0])
    return np.array(out)


@pytest.mark.slow   # libcosim at 1e-4 s and 2e-4 s steps: about 10 s
def test_diagnosed_vendor_model_replayed_by_libcosim(tmp_path):
    """write_extended_ssp (what the diagnosis writes) of the re-exported model with the diagnosed element; libcosim's
    run against fmusa's prediction (me-grid): within 2 % of the motion's range at a 1e-4 s step, the error about
    halving with the step (first order), and far from the model without the gap."""
    from fmusa.cosim import simulate_coupled
    from fmusa.diagnose.attached import coupling_of
    from fmusa.diagnose.run import write_extended_ssp
    from fmusa.diagnose.study import load_diagnosis_study
    from test_diagnose_attached_runs import short_study

    pytest.importorskip("libcosimpy")
    fmu = with_velocity_output(OM, tmp_path / "Mass_Damper.fmu")
    study = short_study(tmp_path, measured=False).read_text(encoding="utf-8").replace(str(OM), str(fmu))
    (tmp_path / "study.yaml").write_text(study, encoding="utf-8")
    st = load_diagnosis_study(tmp_path / "study.yaml")
    diagnosed = {"c_y": ELEMENT_PARAMS["c"], "d_y": ELEMENT_PARAMS["d"], "gap": ELEMENT_PARAMS["gap"]}
    out = write_extended_ssp(tmp_path / "extended.ssp", str(fmu), st.interface, "force", diagnosed, T, "mass_damper")
    assert out["written"], out
    assert out["element_parameters"] == ELEMENT_PARAMS
    folder = tmp_path / "unpacked"
    with zipfile.ZipFile(tmp_path / "extended.ssp") as z:
        z.extractall(folder)
    # the release: the archive's model parameters plus the changed spring length, in the archive and in fmusa
    ssv = folder / "resources" / "model.ssv"
    text = ssv.read_text(encoding="utf-8")
    text = re.sub(r'(name="spring.s_rel0"><ssv:Real value=")[^"]*', r"\g<1>0.45", text)
    assert "0.45" in text
    ssv.write_text(text, encoding="utf-8")
    coupling = coupling_of(str(fmu), st.interface)
    model = {**out["model_parameters"], **MODEL_PARAMS}
    pred = simulate_coupled(coupling, model, ELEMENT_PARAMS, T, TIMES, ["y"]).frame["y"].to_numpy()
    # it settles where the model's spring (1e4 N/m, towards 0.05 m) and the element's past its gap balance
    rest = (1e4 * 0.05 + ELEMENT_PARAMS["c"] * ELEMENT_PARAMS["gap"]) / (1e4 + ELEMENT_PARAMS["c"])
    assert abs(pred[-1] - rest) < 2e-3, (pred[-1], rest)
    span = np.ptp(pred)
    errors = {}
    for step in (2e-4, 1e-4):
        got = run_libcosim(folder, step)
        errors[step] = float(np.max(np.abs(got - pred)) / span)
    print(f"libcosim against fmusa, relative to the range: {errors}")
    assert errors[1e-4] < 2e-2, errors
    assert 1.5 < errors[2e-4] / errors[1e-4] < 2.5, errors
    linear = simulate_coupled(coupling, model, {"c": 5.0e3, "d": 20.0}, T, TIMES, ["y"]).frame["y"].to_numpy()
    assert np.max(np.abs(linear - pred)) / span > 10 * errors[1e-4]
