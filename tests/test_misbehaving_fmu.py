"""A vendor FMU that crashes, hangs, returns NaN or fmi2Error: the run is recorded as failed with its reason,
the study goes on and nothing already computed is lost.

The FMU is ``tests/fmus/misbehave`` (a quasi-static spring y = F/k that misbehaves while k lies in a band),
built here with gcc against fmpy's FMI 2 headers and zipped into an .fmu.
"""
from __future__ import annotations

import faulthandler
import json
import shutil
import signal
import subprocess
import tempfile
import time
import zipfile
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import fmpy
from fmusa.study.loader import load_study
from fmusa.api import run_study

SRC = Path(__file__).resolve().parent / "fmus" / "misbehave"
FMI_HEADERS = Path(fmpy.__file__).resolve().parent / "c-code"

F = 411.0
# ten grid values of k; the fault band [2.5e6, 5.5e6] holds two of them, in the middle of the grid
K = [1e5, 2e5, 5e5, 1e6, 3e6, 5e6, 7e6, 1e7, 2e7, 5e7]
BAND = (2.5e6, 5.5e6)
FAULTY = [k for k in K if BAND[0] <= k <= BAND[1]]
HEALTHY = [k for k in K if k not in FAULTY]
TIMEOUT_S = 2

CRASH, HANG, NAN, ERROR = 1, 2, 3, 4


@pytest.fixture(scope="session")
def misbehave_fmu(tmp_path_factory) -> Path:
    """tests/fmus/misbehave built with gcc and zipped as Misbehave.fmu."""
    if shutil.which("gcc") is None:
        pytest.skip("gcc is needed to build the misbehaving test FMU")
    root = tmp_path_factory.mktemp("misbehave")
    tree = root / "tree"
    (tree / "binaries" / "linux64").mkdir(parents=True)
    shutil.copy(SRC / "modelDescription.xml", tree / "modelDescription.xml")
    so = tree / "binaries" / "linux64" / "Misbehave.so"
    cmd = ["gcc", "-std=c99", "-Wall", "-Wextra", "-O1", "-shared", "-fPIC",
           "-I", str(FMI_HEADERS), str(SRC / "misbehave.c"), "-o", str(so), "-lm"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.fail(f"building the misbehaving FMU failed:\n{' '.join(cmd)}\n{proc.stdout}\n{proc.stderr}")
    fmu = root / "Misbehave.fmu"
    with zipfile.ZipFile(fmu, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted(tree.rglob("*")):
            if f.is_file():
                z.write(f, f.relative_to(tree).as_posix())
    from fmpy.validation import validate_fmu
    assert validate_fmu(str(fmu)) == [], validate_fmu(str(fmu))
    return fmu


@pytest.fixture(autouse=True)
def quiet_worker_crashes(request):
    """The forked workers inherit pytest's faulthandler, which would print a traceback of pytest's stack
    ("Fatal Python error: Segmentation fault") for every deliberate crash. Off while a test runs."""
    was_enabled = faulthandler.is_enabled()
    faulthandler.disable()
    try:
        yield
    finally:
        if was_enabled:
            try:  # pytest's own file descriptor for it (private; if it moves, faulthandler just stays off)
                from _pytest.faulthandler import fault_handler_stderr_fd_key
                faulthandler.enable(file=request.config.stash[fault_handler_stderr_fd_key])
            except Exception:
                pass


@pytest.fixture(autouse=True)
def extract_dir(tmp_path, monkeypatch) -> Path:
    """fmpy extracts the FMU into tempfile's directory, in the parent and in every (forked) worker: keep
    those directories under this test's tmp_path instead of /tmp."""
    d = tmp_path / "extracted"
    d.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(d))
    return d


def write_study(directory: Path, fmu: Path, kind: int, workers: int = 2) -> Path:
    text = f"""\
name: misbehave_{kind}
fmu: {fmu}
parameters:
  k: {{variable: k, unit: N/m}}
fixed:
  F: {F!r}
  fault: 1
  fault_kind: {kind}
  fault_lo: {BAND[0]!r}
  fault_hi: {BAND[1]!r}
scenario:
  stop_time: 1
  step: 0.5
metrics:
  y_max: {{output: y_peak, reduce: final, unit: m}}
stages:
  grid:
    values:
      k: [{", ".join(repr(k) for k in K)}]
execution:
  workers: {workers}
  timeout_s: {TIMEOUT_S}
"""
    path = directory / f"misbehave_{kind}.yaml"
    path.write_text(text)
    return path


def run(tmp_path: Path, fmu: Path, kind: int, workers: int = 2, out: Path | None = None,
        resume: bool = False):
    path = write_study(tmp_path, fmu, kind, workers)
    out = out or tmp_path / "out"
    t0 = time.monotonic()
    result = run_study(load_study(path), out, resume=resume, figures=False, progress=False)
    return result, out, time.monotonic() - t0


def check_runs(out: Path, kind: int) -> pd.DataFrame:
    """runs.csv on disk: every grid point once, the faulty ones failed with their reason, the rest exact."""
    runs = pd.read_csv(out / "runs.csv", keep_default_na=False, na_values=[""])
    assert runs["run_id"].is_unique
    assert sorted(runs["k"]) == sorted(K)
    assert (runs["stage"] == "grid").all()
    by_k = runs.set_index("k")

    for k in FAULTY:
        row = by_k.loc[k]
        msg = str(row["message"])
        assert row["status"] == "failed", (k, row.to_dict())
        assert np.isnan(row["y_max"]), (k, row.to_dict())
        if kind == CRASH:
            assert "crash" in msg and f"signal {int(signal.SIGSEGV)}" in msg, msg
        elif kind == HANG:
            assert "timed out" in msg and f"{TIMEOUT_S} s" in msg, msg
        elif kind == NAN:
            assert "non-finite" in msg and "y_peak" in msg, msg
        elif kind == ERROR:
            assert "fmi2DoStep returned Error" in msg, msg
            assert f"deliberate failure at k = {k:.17g}" in msg, msg

    healthy = by_k.loc[HEALTHY]
    assert (healthy["status"] == "ok").all(), healthy[["status", "message"]]
    k = np.asarray(HEALTHY)
    np.testing.assert_allclose(healthy["y_max"].to_numpy(float), F / k, rtol=1e-12, atol=0)
    return runs


@pytest.mark.parametrize("kind", [CRASH, HANG, NAN, ERROR], ids=["segfault", "hang", "nan", "fmi2Error"])
def test_faulty_runs_fail_with_their_reason_and_the_study_goes_on(tmp_path, misbehave_fmu, kind):
    result, out, wall = run(tmp_path, misbehave_fmu, kind)
    check_runs(out, kind)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"] == len(K)
    assert summary["failed"] == len(FAULTY)
    assert summary["simulated_this_session"] == len(K)
    # the in-memory result agrees with the file
    assert len(result.runs) == len(K)
    assert (result.runs["status"] == "failed").sum() == len(FAULTY)
    if kind == HANG:
        # two hangs, each ended by the 2 s timeout; at worst one after the other
        assert wall < 10, f"the hang study took {wall:.1f} s"


@pytest.mark.parametrize("kind", [CRASH, HANG], ids=["segfault", "hang"])
def test_a_single_worker_is_replaced_and_finishes_the_grid(tmp_path, misbehave_fmu, kind):
    """With one worker every run after a fault needs the replacement worker."""
    result, out, wall = run(tmp_path, misbehave_fmu, kind, workers=1)
    runs = check_runs(out, kind)
    # healthy points after the faulty ones in the grid were computed after the worker died
    after = [k for k in HEALTHY if k > max(FAULTY)]
    assert after and (runs.set_index("k").loc[after, "status"] == "ok").all()
    if kind == HANG:
        assert wall < 10, f"the hang study took {wall:.1f} s"


def test_resume_after_crashes_simulates_nothing_again(tmp_path, misbehave_fmu):
    result1, out, _ = run(tmp_path, misbehave_fmu, CRASH)
    before = (out / "runs.csv").read_bytes()
    check_runs(out, CRASH)

    result2, out2, _ = run(tmp_path, misbehave_fmu, CRASH, out=out, resume=True)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["simulated_this_session"] == 0
    assert summary["runs"] == len(K) and summary["failed"] == len(FAULTY)
    assert (out / "runs.csv").read_bytes() == before          # no row added, none rewritten
    pd.testing.assert_frame_equal(result1.runs, result2.runs, check_dtype=False)


@pytest.mark.parametrize("kind", [CRASH, ERROR], ids=["segfault", "fmi2Error"])
def test_workers_leave_no_extracted_fmu_behind(tmp_path, misbehave_fmu, extract_dir, kind):
    run(tmp_path, misbehave_fmu, kind)
    assert sorted(p.name for p in extract_dir.iterdir()) == []


# ---------------------------------------------------------------------------------------------- on Dask
@pytest.fixture(scope="module")
def dask_cluster():
    """A Dask LocalCluster of two worker processes (daemonic, as Dask makes them by default)."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        yield cluster


@pytest.mark.parametrize("kind", [CRASH, HANG, NAN, ERROR], ids=["segfault", "hang", "nan", "fmi2Error"])
def test_on_dask_faulty_runs_fail_with_their_reason_and_the_study_goes_on(tmp_path, misbehave_fmu, dask_cluster,
                                                                         kind):
    """The same studies on a Dask cluster: each task runs its runs in a supervised process on its Dask
    worker, so a segfault or a hang costs that run (with its reason), never the Dask worker or the study."""
    path = write_study(tmp_path, misbehave_fmu, kind)
    out = tmp_path / "out"
    workers_before = set(dask_cluster.scheduler_info["workers"])
    t0 = time.monotonic()
    result = run_study(load_study(path), out, scheduler=dask_cluster.scheduler_address, figures=False,
                       progress=False)
    wall = time.monotonic() - t0
    check_runs(out, kind)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"] == len(K) and summary["failed"] == len(FAULTY)
    assert summary["simulated_this_session"] == len(K)
    assert (result.runs["status"] == "failed").sum() == len(FAULTY)
    # the Dask workers survived: the same two, no restart by the nanny
    assert set(dask_cluster.scheduler_info["workers"]) == workers_before and len(workers_before) == 2
    if kind == HANG:
        assert wall < 10, f"the hang study took {wall:.1f} s"
