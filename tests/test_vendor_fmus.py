"""Third-party FMUs through a study file alone: the same (c, d) optimum as our own FMU.

Two FMUs that are not built from our model code, made by exporters installed from PyPI:

- AxialScrew (tests/fmus/thirdparty/axial_screw.py), exported by pythonfmu: an independent
  implementation of the axial pullout with its own integrator, names such as ``screw.bushing.c[2]``,
  ``'F pull'`` and ``der(screw.y_mm)``, and millimetre units (N/mm, N·s/mm, mm, mm/s, N·mm, g);
- PulloutContainer, made by fmpy's container exporter around dist/ScrewVertebra.fmu: our model under
  hierarchical, quoted and der() names (``screw.monitor.'|v| max'``, ``der(screw.y)``), in SI units.

Each runs its committed study file (studies/vendor_pythonfmu.yaml, studies/vendor_container.yaml; only
the ``fmu:`` line is replaced by the FMU built here) through grid, region of interest and nested search.
The same study is then mapped onto our own FMU (our names, the unit factors the two FMUs declare in
their model descriptions) and must give the same optimum: c within the search's inner_rtol and the same
d level of the outer halving.

Run as a script, ``python tests/test_vendor_fmus.py build/vendor`` builds both FMUs where the committed
study files look for them.
"""
from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "tests" / "fmus" / "thirdparty" / "axial_screw.py"
STUDIES = {"pythonfmu": ROOT / "studies" / "vendor_pythonfmu.yaml",
           "container": ROOT / "studies" / "vendor_container.yaml"}

# Vendor FMU variable -> our ScrewVertebra variable (the unit factors come from the model descriptions).
AXIAL_NAMES = {
    "screw.bushing.c[2]": "c_y",
    "screw.bushing.d[2]": "d_y",
    "'F pull'": "F_max",
    "t_ramp": "t_ramp",
    "screw.mass": "m",
    "screw.y_mm": "y",
    "der(screw.y_mm)": "v_y",
    "screw.bushing.W": None,          # no counterpart in our FMU: the metric is dropped
}
CONTAINER_PARAMETERS = {
    "'F pull'": "F_max",
    "pull.t_ramp": "t_ramp",
    "screw.m": "m",
    "screw.bushing.c[2]": "c_y",
    "screw.bushing.d[2]": "d_y",
    "screw.monitor.eps_v_eq": "eps_v_eq",
    "screw.monitor.eps_a_eq": "eps_a_eq",
}
CONTAINER_OUTPUTS = {
    "screw.y": "y",
    "der(screw.y)": "v_y",
    "der(screw.y,2)": "a_y",
    "screw.monitor.y_max": "y_max",
    "screw.monitor.'|v| max'": "v_y_max",
    "screw.monitor.t_eq": "t_eq",
}
CONTAINER_NAMES = {**CONTAINER_PARAMETERS, **CONTAINER_OUTPUTS}
CONTAINER_STEP = 0.002   # s, the container's fixed internal step: it steps ScrewVertebra every 2 ms


# ---------------------------------------------------------------------------------------------- builders

def build_axial_screw(dest: Path) -> Path:
    """Export AxialScrew with pythonfmu's command line, in a separate process (the builder imports the
    script, and the FMU must later import its own copy from its resources)."""
    dest.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run([sys.executable, "-m", "pythonfmu", "build", "-f", str(SCRIPT), "-d", str(dest)],
                          capture_output=True, text=True, cwd=dest)
    fmu = dest / "AxialScrew.fmu"
    if proc.returncode != 0 or not fmu.is_file():
        raise RuntimeError(f"pythonfmu build failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}")
    return fmu


def build_container(screw_fmu: Path, dest: Path) -> Path:
    """Wrap ``screw_fmu`` (our ScrewVertebra) in fmpy's container FMU under the names above."""
    from fmpy import read_model_description
    from fmpy.container_fmu.cli import create_container_fmu
    from fmpy.container_fmu.config import Component, Configuration
    from fmpy.model_description import (CoSimulation, DefaultExperiment, ModelDescription, ModelVariable,
                                        Unknown)

    md = read_model_description(str(screw_fmu))
    comp_vars = {v.name: v for v in md.modelVariables}
    component = Component(name="screw", filename=Path(screw_fmu), modelDescription=md)
    # The container numbers its variables in this order; the first must be the independent time.
    variables = [ModelVariable(type="Real", variability="continuous", causality="independent", name="time")]
    mappings = {}
    for names, kind in ((CONTAINER_PARAMETERS, "parameter"), (CONTAINER_OUTPUTS, "output")):
        for name, target in names.items():
            src = comp_vars[target]
            if kind == "parameter":
                v = ModelVariable(type="Real", variability="fixed", causality="parameter", initial="exact",
                                  name=name, start=src.start)
            else:
                v = ModelVariable(type="Real", variability="continuous", causality="output",
                                  initial="calculated", name=name)
            v.unit = src.unit
            v.description = f"{target} of {md.modelName}: {src.description}"
            variables.append(v)
            mappings[v] = [(component, src)]
    outputs = [v for v in variables if v.causality == "output"]
    container_md = ModelDescription(
        fmiVersion="2.0", modelName="PulloutContainer",
        instantiationToken="{" + str(uuid.uuid5(uuid.NAMESPACE_URL, "fmusa/PulloutContainer")) + "}",
        description="fmpy container FMU around ScrewVertebra, with renamed variables",
        defaultExperiment=DefaultExperiment(stopTime="0.6", stepSize=str(CONTAINER_STEP)),
        coSimulation=CoSimulation(fixedInternalStepSize=CONTAINER_STEP),
        modelVariables=variables)
    container_md.variableNamingConvention = "structured"
    container_md.unitDefinitions = md.unitDefinitions
    container_md.outputs = [Unknown(variable=v) for v in outputs]
    container_md.initialUnknowns = [Unknown(variable=v) for v in outputs]
    config = Configuration(parallelDoStep=False, modelDescription=container_md, components=[component],
                           connections=[], variableMappings=mappings)
    dest.mkdir(parents=True, exist_ok=True)
    work = dest / "container_build"
    work.mkdir(exist_ok=True)
    fmu = dest / "PulloutContainer.fmu"
    create_container_fmu(config, work, fmu)
    shutil.rmtree(work, ignore_errors=True)
    return fmu


# ---------------------------------------------------------------------------------------------- studies

def vendor_study_text(kind: str, fmu: Path) -> str:
    """The committed study file with its ``fmu:`` line pointing at ``fmu``."""
    text = STUDIES[kind].read_text(encoding="utf-8")
    new, n = re.subn(r"(?m)^fmu:.*$", lambda _: f"fmu: {json.dumps(str(fmu))}", text)
    assert n == 1, f"{STUDIES[kind]}: expected one top-level 'fmu:' line"
    return new


def unit_factors(fmu) -> dict[str, float]:
    """Variable name -> factor to SI (value_SI = factor * value), from the model description's units."""
    from fmpy import read_model_description

    md = read_model_description(str(fmu))
    units = {u.name: (float(u.baseUnit.factor) if u.baseUnit is not None and u.baseUnit.factor is not None
                      else 1.0) for u in md.unitDefinitions}
    return {v.name: units.get(v.unit, 1.0) for v in md.modelVariables}


def reference_study_text(vendor_text: str, names: dict[str, str | None], vendor_fmu: Path,
                         our_fmu: Path) -> str:
    """The vendor study mapped onto our own FMU (``fmu: default``): our variable names, and scales that
    absorb the unit factors the two FMUs declare, so the study's values and metrics mean the same."""
    f_vendor, f_ours = unit_factors(vendor_fmu), unit_factors(our_fmu)
    doc = yaml.safe_load(vendor_text)
    doc["name"] = doc["name"] + "_ours"
    doc["fmu"] = "default"

    def to_ours(var: str) -> float:   # one vendor unit in our unit
        return f_vendor[var] / f_ours[names[var]]

    for p in doc["parameters"].values():
        var = p["variable"]
        p["scale"] = float(p.get("scale", 1.0)) * to_ours(var)
        p["offset"] = float(p.get("offset", 0.0)) * to_ours(var)
        p["variable"] = names[var]
    doc["fixed"] = {names[k]: (v if isinstance(v, bool) else float(v) * to_ours(k))
                    for k, v in doc.get("fixed", {}).items()}
    metrics = {}
    for name, m in doc["metrics"].items():
        var = m["output"]
        if names[var] is None:
            continue
        m["scale"] = float(m.get("scale", 1.0)) / to_ours(var)
        m["output"] = names[var]
        metrics[name] = m
    doc["metrics"] = metrics
    return yaml.safe_dump(doc, sort_keys=False, allow_unicode=True)


def run(text: str, path: Path, out: Path):
    from fmusa.study.loader import load_study
    from fmusa.api import run_study

    path.write_text(text, encoding="utf-8")
    t0 = time.perf_counter()
    result = run_study(load_study(path), out, figures=False, progress=False)
    wall = time.perf_counter() - t0
    summary = json.loads((out / "summary.json").read_text())
    runs = pd.read_csv(out / "runs.csv")
    return result, summary, runs, wall


# ---------------------------------------------------------------------------------------------- fixtures

@pytest.fixture(scope="session")
def axial_fmu(tmp_path_factory) -> Path:
    return build_axial_screw(tmp_path_factory.mktemp("pythonfmu"))


@pytest.fixture(scope="session")
def container_fmu(tmp_path_factory, fmu_path) -> Path:
    return build_container(fmu_path, tmp_path_factory.mktemp("container"))


@pytest.fixture(scope="module")
def pair(tmp_path_factory, axial_fmu, container_fmu, fmu_path):
    """Run a vendor study and the same study on our FMU; cached per kind."""
    cache: dict = {}

    def get(kind: str):
        if kind not in cache:
            vendor = axial_fmu if kind == "pythonfmu" else container_fmu
            names = AXIAL_NAMES if kind == "pythonfmu" else CONTAINER_NAMES
            tmp = tmp_path_factory.mktemp(kind)
            text = vendor_study_text(kind, vendor)
            v = run(text, tmp / f"vendor_{kind}.yaml", tmp / "vendor")
            o = run(reference_study_text(text, names, vendor, fmu_path), tmp / f"ours_{kind}.yaml", tmp / "ours")
            cache[kind] = (v, o)
        return cache[kind]
    return get


# ---------------------------------------------------------------------------------------------- the FMUs

def test_pythonfmu_export_is_a_valid_third_party_fmu(axial_fmu):
    from fmpy import read_model_description
    from fmpy.validation import validate_fmu

    assert validate_fmu(str(axial_fmu)) == []
    md = read_model_description(str(axial_fmu))
    assert md.generationTool.startswith("PythonFMU")
    assert md.coSimulation.modelIdentifier == "AxialScrew" and md.modelExchange is None
    v = {x.name: x for x in md.modelVariables}
    assert set(AXIAL_NAMES) <= set(v)
    assert {n: v[n].unit for n in AXIAL_NAMES} == {
        "screw.bushing.c[2]": "N/mm", "screw.bushing.d[2]": "N.s/mm", "'F pull'": "N", "t_ramp": "s",
        "screw.mass": "g", "screw.y_mm": "mm", "der(screw.y_mm)": "mm/s", "screw.bushing.W": "N.mm"}
    f = unit_factors(axial_fmu)
    assert (f["screw.bushing.c[2]"], f["screw.y_mm"], f["screw.bushing.W"], f["screw.mass"]) == (1e3, 1e-3, 1e-3, 1e-3)


def test_pythonfmu_fmu_solves_the_axial_pullout(axial_fmu):
    """Against the closed-form quasi-static pullout: y = F/c at rest, y' = F/(c t_ramp) on the ramp."""
    from fmusa.fmi.runner import FMURunner

    c, d = 822.0, 0.5                          # N/mm, N·s/mm: overdamped, d/c = 0.6 ms
    with FMURunner(axial_fmu) as fmu:
        df = fmu.run({"screw.bushing.c[2]": c, "screw.bushing.d[2]": d, "'F pull'": 411.0, "t_ramp": 0.5},
                     stop_time=0.6, step=0.002, outputs=["screw.y_mm", "der(screw.y_mm)", "screw.bushing.W"])
    assert len(df) == 301 and df["time"].iloc[-1] == 0.6
    assert df["screw.y_mm"].iloc[-1] == pytest.approx(411 / c, rel=1e-12)
    assert df["screw.bushing.W"].iloc[-1] == pytest.approx(411 ** 2 / (2 * c), rel=1e-12)
    ramp = df[(df["time"] > 0.1) & (df["time"] <= 0.5)]
    assert np.allclose(ramp["der(screw.y_mm)"], 411 / (c * 0.5), rtol=1e-9)
    assert abs(df["der(screw.y_mm)"].iloc[-1]) < 1e-9


def test_container_fmu_renames_our_fmu(container_fmu, fmu_path):
    from fmpy import read_model_description
    from fmpy.validation import validate_fmu

    from fmusa.fmi.runner import FMURunner

    assert validate_fmu(str(container_fmu)) == []
    md = read_model_description(str(container_fmu))
    assert md.coSimulation.modelIdentifier == "container_fmu"
    assert [v.name for v in md.modelVariables] == ["time", *CONTAINER_NAMES]
    params = {"c_y": 5e5, "d_y": 300.0, "t_ramp": 0.5}
    renamed = {k: params[v] for k, v in CONTAINER_PARAMETERS.items() if v in params}
    with FMURunner(container_fmu) as a, FMURunner(fmu_path) as b:
        via = a.run(renamed, 0.6, CONTAINER_STEP, list(CONTAINER_OUTPUTS))
        again = a.run(renamed, 0.6, CONTAINER_STEP, list(CONTAINER_OUTPUTS))    # after fmi2Reset
        direct = b.run(params, 0.6, CONTAINER_STEP, list(CONTAINER_OUTPUTS.values()))
    np.testing.assert_array_equal(via.to_numpy(), again.to_numpy())
    for name, target in CONTAINER_OUTPUTS.items():
        scale = max(np.max(np.abs(direct[target])), 1e-300)
        assert np.max(np.abs(via[name] - direct[target])) <= 1e-9 * scale, name
    assert via["screw.monitor.y_max"].iloc[-1] == pytest.approx(411 / 5e5, rel=1e-9)


def test_committed_study_files_load_with_a_built_fmu(axial_fmu, container_fmu, tmp_path):
    from fmusa.study.loader import parse_study

    for kind, fmu in (("pythonfmu", axial_fmu), ("container", container_fmu)):
        study = parse_study(vendor_study_text(kind, fmu), tmp_path / f"{kind}.yaml")
        assert study.fmu == fmu.resolve()
        assert list(study.stages) == ["grid", "roi", "search"]
        grid = study.stages["grid"].points()
        assert len(grid["c"]) == len(grid["d"]) == 4
        # the grid is 25^3..25^6 N/m and 25^0..25^3 N·s/m, whatever the study's unit
        c_si = np.asarray(grid["c"]) * (1.0 if kind == "pythonfmu" else 1e3)
        assert np.allclose(c_si, 25.0 ** np.arange(3, 7), rtol=1e-12)
    # without a built FMU the committed path is reported, not silently replaced
    missing = STUDIES["pythonfmu"].read_text().replace("../build/vendor/", "../build/no_such_dir/")
    with pytest.raises(ValueError, match="does not exist"):
        parse_study(missing, STUDIES["pythonfmu"])


# ---------------------------------------------------------------------------------------------- studies

@pytest.mark.parametrize("kind", ["pythonfmu", "container"])
def test_vendor_study_runs_completely(pair, kind):
    (vres, vsum, vruns, vwall), (ores, osum, oruns, owall) = pair(kind)
    for s, runs in ((vsum, vruns), (osum, oruns)):
        assert s["failed"] == 0
        assert len(runs) == s["runs"] and runs["run_id"].is_unique
        assert sorted(runs["run_id"]) == list(range(len(runs)))
        assert (runs["status"] == "ok").all(), runs.loc[runs["status"] != "ok", "message"].tolist()
        assert (runs["stage"] == "grid").sum() == 16
        assert set(runs["stage"]) == {"grid", "search"}
        for col in ("max_y", "max_v"):
            assert runs[col].notna().all(), col
        assert s["search"]["warnings"] == []
        assert s["search"]["stop_reason"].startswith("the response")
    print(f"\n{kind}: vendor {vsum['runs']} runs in {vwall:.2f} s, ours {osum['runs']} runs in {owall:.2f} s; "
          f"optimum vendor {vsum['optimum']}, ours {osum['optimum']}")


@pytest.mark.parametrize("kind", ["pythonfmu", "container"])
def test_vendor_optimum_equals_ours(pair, kind):
    (vres, vsum, vruns, _), (ores, osum, oruns, _) = pair(kind)
    study = vres.study
    tol = study.stages["search"].inner_rtol
    # the reference study works in the same study units (its scales absorb the unit factors)
    assert {p: ores.study.parameters[p].unit for p in ("c", "d")} == {p: study.parameters[p].unit for p in ("c", "d")}
    c_v, d_v = vsum["optimum"]["c"], vsum["optimum"]["d"]
    c_o, d_o = osum["optimum"]["c"], osum["optimum"]["d"]
    assert abs(c_v - c_o) <= tol * c_o, (c_v, c_o)
    assert d_v == pytest.approx(d_o, rel=1e-12)            # the same level of the outer halving
    assert vsum["roi"] == osum["roi"]
    assert vsum["binding_constraint"] == osum["binding_constraint"]
    assert [lv["outer"] for lv in vsum["search"]["levels"]] == [lv["outer"] for lv in osum["search"]["levels"]]
    # in SI the boundary is c* = F/eps_y = 822000 N/m, where translation and velocity bind together
    c_si = c_v * (1.0 if kind == "pythonfmu" else 1e3)
    assert abs(c_si - 411 / 5e-4) <= 2 * tol * c_si
    # the grid metrics agree point by point (the same physics; two independent integrators for pythonfmu)
    key = ["c", "d"]
    g = vruns[vruns["stage"] == "grid"].merge(oruns[oruns["stage"] == "grid"], on=key, suffixes=("_v", "_o"))
    assert len(g) == 16
    for m in ("max_y", "max_v"):
        rel = np.abs(g[f"{m}_v"] - g[f"{m}_o"]) / np.abs(g[f"{m}_o"])
        assert rel.max() < 1e-6, (m, float(rel.max()))
    assert (g["feasible_v"] == g["feasible_o"]).all()
    if kind == "container":
        # the same FMU stepped differently (every 2 ms inside the container, one doStep in ours): the
        # monitors agree to the solver's tolerance, and t_eq (located by root finding) to ~1e-4
        both = g["t_eq_v"].notna() & g["t_eq_o"].notna()
        assert (g["t_eq_v"].isna() == g["t_eq_o"].isna()).all()
        assert (np.abs(g.loc[both, "t_eq_v"] - g.loc[both, "t_eq_o"]) <= 1e-3 * g.loc[both, "t_eq_o"]).all()
    else:
        # pythonfmu's energy metric has no counterpart in our FMU and is dropped from the reference
        assert "energy_end" in vres.study.metrics and "energy_end" not in ores.study.metrics


def test_units_convert_through_the_study_file(pair):
    """The two studies convert in opposite directions (SI study on a mm FMU, mm study on an SI FMU),
    and both land on the same stiffness; the pythonfmu energy metric converts N·mm to J."""
    (pres, psum, pruns, _), _ = pair("pythonfmu")
    (cres, csum, cruns, _), _ = pair("container")
    tol = pres.study.stages["search"].inner_rtol
    c_p = psum["optimum"]["c"]                   # N/m
    c_c = csum["optimum"]["c"] * 1e3             # N/mm -> N/m
    assert abs(c_p - c_c) <= tol * c_p
    # max_y in m (pythonfmu study, from mm) and in mm (container study, from m): F/c both
    best = pruns.set_index(["c", "d"]).loc[(c_p, psum["optimum"]["d"])]
    assert best["max_y"] == pytest.approx(411 / c_p, rel=1e-4)
    cbest = cruns.set_index(["c", "d"]).loc[(csum["optimum"]["c"], csum["optimum"]["d"])]
    assert cbest["max_y"] == pytest.approx(411 / csum["optimum"]["c"], rel=1e-4)
    # energy c y^2/2 in the FMU's N·mm, reported in J: F^2/(2c) wherever the screw has come to rest
    rest = pruns[(pruns["d"] / pruns["c"] < 0.01) & (pruns["v_end"].abs() < 1e-9)]
    assert len(rest) >= 10
    assert np.allclose(rest["energy_end"], 411.0 ** 2 / (2 * rest["c"]), rtol=1e-6)


if __name__ == "__main__":   # build both FMUs where the committed study files expect them
    dest = Path(sys.argv[1] if len(sys.argv) > 1 else ROOT / "build" / "vendor").resolve()
    print(build_axial_screw(dest))
    print(build_container(ROOT / "dist" / "ScrewVertebra.fmu", dest))
