"""The study pipeline end to end on the real FMU: the paper's study, resume after a kill, Dask."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from fmusa.study.loader import load_study, parse_study
from fmusa.api import run_study

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "studies" / "paper.yaml"


@pytest.fixture(scope="module")
def paper_run(tmp_path_factory, fmu_path):
    out = tmp_path_factory.mktemp("paper")
    return run_study(load_study(PAPER), out, figures=False, progress=False), out


def test_paper_study_finds_the_papers_stiffness(paper_run):
    result, out = paper_run
    s = json.loads((out / "summary.json").read_text())
    for key in ("roi", "optimum", "binding_constraint", "regression", "runs", "failed", "wall_s"):
        assert key in s, key
    c, d = s["optimum"]["c"], s["optimum"]["d"]
    # max(y) <= eps_y makes c ~ F / eps_y = 822000 N/m; the paper reports 823224 N/m
    assert abs(c - 823224) / 823224 < 0.005
    assert abs(c - 411 / 5e-4) / (411 / 5e-4) < 2e-3
    assert "translation" in s["binding_constraint"]
    # the automatic region brackets the boundary by the grid neighbours 25^4 and 25^5, as the paper's
    assert s["roi"]["c"] == [25.0 ** 4, 25.0 ** 5]
    # inside the paper's hand-picked region the search lands on its halving lattice: 488 = 15625 / 2^5
    d_paper = s["paper_roi_search"]["optimum"]["d"]
    k = np.log2(15625 / d_paper)
    assert abs(k - round(k)) < 1e-12 and d_paper == pytest.approx(488.28125)
    # d of the automatic region lies on its own halving lattice
    k = np.log2(s["roi"]["d"][1] / d)
    assert abs(k - round(k)) < 1e-12
    assert s["failed"] == 0
    # the paper-faithful search (no warm start) is the default: its exact lattice point and run count
    assert (c, d) == (822067.2607421875, 381.4697265625) and s["search"]["warm_start"] is False
    assert s["stage_runs"]["grid"] == {"asked": 25, "simulated": 25, "rounds": 1}
    # 2 level-0 ends are grid points; one point per round (parallel: false)
    assert s["stage_runs"]["search"] == {"asked": 227, "simulated": 225, "rounds": 225}
    assert s["stage_runs"]["search"]["asked"] == s["search"]["evaluations"]
    assert sum(r["simulated"] for r in s["stage_runs"].values()) == s["runs"]
    assert s["regression_source"] == "search"


def test_runs_csv_has_one_row_per_run_with_constraints(paper_run):
    result, out = paper_run
    runs = pd.read_csv(out / "runs.csv")
    assert len(runs) == json.loads((out / "summary.json").read_text())["runs"]
    assert runs["run_id"].is_unique
    assert set(runs["stage"]) >= {"grid", "search"}
    assert (runs["stage"] == "grid").sum() == 25
    for col in ("c", "d", "max_y", "mean_y", "max_v", "mean_v", "t_eq", "ok_translation", "ok_velocity",
                "ok_equilibrium", "feasible", "status"):
        assert col in runs.columns, col
    # constraint columns agree with the thresholds of Table 2
    ok = runs["status"] == "ok"
    assert ((runs.loc[ok, "max_y"] <= 5e-4) == runs.loc[ok, "ok_translation"]).all()
    assert ((runs.loc[ok, "max_v"] <= 5e-5) == runs.loc[ok, "ok_velocity"]).all()
    # quasi-static physics of the grid: max(y) = F/c wherever the element is overdamped and settles
    # (time constant d/c well inside the 2 s after the ramp); the rest lags behind F/c
    grid = runs[runs["stage"] == "grid"]
    quasi = (grid["d"] > 3 * np.sqrt(grid["c"] * 2.9e-4)) & (grid["d"] / grid["c"] < 0.05)
    assert quasi.sum() >= 8
    assert np.allclose(grid.loc[quasi, "max_y"], 411 / grid.loc[quasi, "c"], rtol=1e-6)
    assert (grid["max_y"] <= 411 / grid["c"] * (1 + 1e-9) + (grid["d"] < 2 * np.sqrt(grid["c"] * 2.9e-4))).all()


def _slow_study_text() -> str:
    """The paper study on a fine grid with sampled outputs: long enough to kill mid-way."""
    text = PAPER.read_text()
    cs = ", ".join(f"{x:.6g}" for x in np.geomspace(1e5, 1e7, 24))
    ds = ", ".join(f"{x:.6g}" for x in np.geomspace(50, 5e4, 24))
    start = text.index("stages:")
    end = text.index("execution:")
    stages = f"stages:\n  grid:\n    values:\n      c: [{cs}]\n      d: [{ds}]\n\n"
    text = text[:start] + stages + text[end:]
    return text.replace("step: null ", "step: 0.02 ")


def test_kill_and_resume_equals_uninterrupted(tmp_path, fmu_path):
    study_file = tmp_path / "slow.yaml"
    study_file.write_text(_slow_study_text())
    study = load_study(study_file)
    assert study.scenario.step == 0.02
    ref = run_study(study, tmp_path / "ref", figures=False, progress=False).runs

    out = tmp_path / "killed"
    cmd = [sys.executable, "-m", "fmusa.cli", "sweep", str(study_file), "--out", str(out), "--no-figures",
           "--quiet", "--workers", "2"]
    proc = subprocess.Popen(cmd, cwd=ROOT, start_new_session=True)
    runs_csv = out / "runs.csv"
    deadline = time.time() + 60
    while time.time() < deadline:
        if runs_csv.exists() and sum(1 for _ in open(runs_csv)) > 60:
            break
        time.sleep(0.02)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    partial = pd.read_csv(runs_csv)
    assert 0 < len(partial) < len(ref), "the kill must land in the middle of the sweep"

    resumed = run_study(study, out, resume=True, figures=False, progress=False)
    assert resumed.summary["simulated_this_session"] == len(ref) - len(partial)
    a = ref.sort_values(["c", "d"]).reset_index(drop=True)
    b = resumed.runs.sort_values(["c", "d"]).reset_index(drop=True)
    assert len(a) == len(b) == 24 * 24
    cols = ["c", "d", "max_y", "mean_y", "max_v", "mean_v", "t_eq", "feasible", "status"]
    pd.testing.assert_frame_equal(a[cols], b[cols], check_exact=True)


def test_dask_local_cluster_gives_identical_results(tmp_path, fmu_path):
    distributed = pytest.importorskip("distributed")
    text = PAPER.read_text()
    start, end = text.index("stages:"), text.index("execution:")
    text = text[:start] + "stages:\n  grid:\n    base: 25\n    exponents: {c: [3, 7], d: [2, 6]}\n\n" + text[end:]
    study = parse_study(text, ROOT / "studies" / "dask_check.yaml")
    local = run_study(study, tmp_path / "local", workers=1, figures=False, progress=False).runs
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        remote = run_study(study, tmp_path / "dask", scheduler=cluster.scheduler_address, figures=False,
                           progress=False).runs
    cols = ["c", "d", "max_y", "mean_y", "max_v", "mean_v", "t_eq", "feasible"]
    a = local.sort_values(["c", "d"]).reset_index(drop=True)[cols]
    b = remote.sort_values(["c", "d"]).reset_index(drop=True)[cols]
    pd.testing.assert_frame_equal(a, b, check_exact=True)
