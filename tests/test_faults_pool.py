"""Workers that stay healthy (issue 18, rows 4 and 6): a leaking FMU is recycled under a memory limit or
after a number of runs, a run whose worker died is tried once more on a fresh worker, and a run's time
limit counts from the run's start, not from a worker's start-up, however long the FMU takes to load.

The FMU is tests/fmus/leaky (a spring y = F/k, so every healthy run has the closed form F/k): it leaks
``leak_mb`` MB per fmi2DoStep and, with ``crash_above_mb``, aborts once its process has leaked more.
"""
from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from c_fmus import build_leaky  # noqa: E402

from fmusa.api import run_study  # noqa: E402
from fmusa.study.loader import parse_study  # noqa: E402

F = 411.0


@pytest.fixture(scope="module")
def leaky_so(tmp_path_factory) -> Path:
    """The leaky FMU's binary, built once for the module."""
    root = tmp_path_factory.mktemp("leaky")
    fmu = build_leaky(root)
    return root / "tree" / "binaries" / "linux64" / "Leaky.so"


@pytest.fixture
def leaky(tmp_path, leaky_so) -> Path:
    return build_leaky(tmp_path / "fmu", binary=leaky_so)


def study_text(fmu: Path, ks, fixed: str = "", execution: str = "", step: str = "null", stop: float = 1.0) -> str:
    return f"""\
name: leaky_pool
fmu: {fmu}
parameters:
  k: {{variable: k, unit: N/m}}
fixed:
  F: {F!r}
{fixed}
scenario:
  stop_time: {stop}
  step: {step}
metrics:
  y_max: {{output: y_peak, reduce: final, unit: m}}
stages:
  grid:
    values:
      k: [{", ".join(repr(float(k)) for k in ks)}]
execution:
  workers: 2
  timeout_s: 30
{execution}
"""


def run(tmp_path: Path, text: str, name: str = "out"):
    study = parse_study(text, tmp_path / f"{name}.yaml")
    result = run_study(study, tmp_path / name, figures=False, progress=False)
    runs = pd.read_csv(tmp_path / name / "runs.csv", encoding="utf-8", keep_default_na=False, na_values=[""])
    return result, runs


def exact(runs: pd.DataFrame) -> None:
    ok = runs[runs["status"] == "ok"]
    np.testing.assert_allclose(ok["y_max"].to_numpy(float), F / ok["k"].to_numpy(float), rtol=1e-12, atol=0)


class PeakWorkerMemory:
    """The largest memory any child process of this one holds alone (unique set size, the measure of
    execution.worker_max_memory_mb), looked at every 20 ms (psutil)."""

    def __init__(self) -> None:
        import psutil
        self.me, self.peak_mb, self._stop = psutil.Process(), 0.0, threading.Event()
        self._thread = threading.Thread(target=self._watch, daemon=True)

    def _watch(self) -> None:
        while not self._stop.is_set():
            for child in self.me.children(recursive=True):
                try:
                    self.peak_mb = max(self.peak_mb, child.memory_full_info().uss / 1e6)
                except Exception:  # noqa: BLE001 - it ended meanwhile
                    pass
            time.sleep(0.02)

    def __enter__(self) -> "PeakWorkerMemory":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


def test_a_leaking_fmu_is_recycled_under_the_memory_limit_and_every_run_succeeds(tmp_path, leaky):
    """32 MB per fmi2DoStep, 48 runs on two workers: unrecycled, a worker would reach ~24 x 32 = 770 MB on
    top of its own ~60 MB. With worker_max_memory_mb: 300 no worker goes far past 300 MB, and every run
    gives its closed form, however large the process it was forked from (the limit is on the memory the
    worker holds alone: the test suite's own process is several hundred MB by the time this test runs)."""
    ks = np.geomspace(1e5, 1e8, 48)
    text = study_text(leaky, ks, fixed="  leak_mb: 32", execution="  worker_max_memory_mb: 300")
    ballast = np.ones(200_000_000 // 8)        # 200 MB touched in this process: a forked worker's resident size
    with PeakWorkerMemory() as mem:
        result, runs = run(tmp_path, text)
    del ballast
    assert len(runs) == 48 and (runs["status"] == "ok").all(), runs[runs["status"] != "ok"][["k", "message"]]
    exact(runs)
    # the limit, plus at most a chunk of MEMORY_CHUNK = 4 runs (128 MB) between two looks
    assert 300 < mem.peak_mb < 300 + 4 * 32 + 60, f"peak worker memory {mem.peak_mb:.0f} MB"


def test_a_run_that_crashes_a_worn_worker_is_retried_on_a_fresh_one(tmp_path, leaky):
    """The FMU aborts once its process has leaked more than 100 MB (8 MB a run: the 13th run of a worker):
    that run works on a fresh worker. With the default one retry every run succeeds; with retries: 0 the
    runs that met a worn worker fail, naming the crash."""
    ks = np.geomspace(1e5, 1e8, 40)
    fixed = "  leak_mb: 8\n  crash_above_mb: 100"
    result, runs = run(tmp_path, study_text(leaky, ks, fixed=fixed))
    assert (runs["status"] == "ok").all(), runs[runs["status"] != "ok"][["k", "message"]]
    exact(runs)

    _, runs0 = run(tmp_path, study_text(leaky, ks, fixed=fixed, execution="  retries: 0"), name="no_retry")
    failed = runs0[runs0["status"] == "failed"]
    assert len(failed) >= 2, runs0[["k", "status"]]
    assert all("the FMU crashed the worker process (SIGABRT" in m for m in failed["message"]), failed["message"]
    exact(runs0)


def test_a_run_that_crashes_a_fresh_worker_is_not_tried_again(tmp_path, leaky):
    """A run that crashes even a fresh worker (here every run: it leaks past the limit on its own) has had
    its fresh worker: it fails at once, with the crash named, and costs exactly one worker."""
    from fmusa.runs.evaluator import Evaluator
    from fmusa.study.plan import study_plan_spec

    ks = np.array([1e5, 2e5, 5e5, 1e6, 2e6])
    study = parse_study(study_text(leaky, ks, fixed="  leak_mb: 8\n  crash_above_mb: 4"), tmp_path / "s.yaml")
    got: list = []
    with Evaluator(study_plan_spec(study, leaky), workers=1, isolate=True) as ev:
        ev.map_batches((np.arange(5), ks.reshape(-1, 1)), got.append)
        assert ev._pool.replaced == 5
    results = [r for b in got for r in b.results()]
    assert sorted(r.run_id for r in results) == list(range(5))
    assert all(r.status == "failed" and r.message == "the FMU crashed the worker process (SIGABRT, signal 6)"
               for r in results), [r.message for r in results]


def test_worker_max_runs_recycles_workers_without_changing_results(tmp_path, leaky):
    from fmusa.runs.evaluator import Evaluator
    from fmusa.runs.pool import PoolOptions
    from fmusa.study.plan import study_plan_spec

    ks = np.geomspace(1e5, 1e8, 23)
    study = parse_study(study_text(leaky, ks, fixed="  leak_mb: 1"), tmp_path / "s.yaml")
    spec = study_plan_spec(study, leaky)
    got: list = []
    with Evaluator(spec, workers=1, isolate=True, pool=PoolOptions(worker_max_runs=5)) as ev:
        ev.map_batches((np.arange(23), ks.reshape(-1, 1)), got.append)
        pool = ev._pool
        assert pool.replaced == 4, (pool.started, pool.replaced)      # runs 1-5, 6-10, …, 21-23: 5 workers
    ids = np.concatenate([b.run_ids for b in got])
    y = np.concatenate([b.metrics[:, 0] for b in got])
    assert sorted(ids.tolist()) == list(range(23))
    np.testing.assert_allclose(y, F / ks[ids], rtol=1e-12, atol=0)


@pytest.mark.parametrize("method", ["fork", "spawn"])
def test_a_slow_loading_fmu_does_not_use_up_the_first_runs_time_limit(tmp_path, leaky_so, method):
    """A model description of 20k variables takes seconds to parse; with timeout_s: 0.5 every run (a few
    microseconds of work) must still succeed: a worker says "ready" only once its FMU is loaded, and a
    run's time counts from its start. Spawned workers get the parent's parse, with only the variables a
    run uses, instead of parsing again."""
    import multiprocessing as mp
    if method not in mp.get_all_start_methods():
        pytest.skip(f"no {method} here")
    fmu = build_leaky(tmp_path / "fmu", extra=20_000, binary=leaky_so)
    ks = np.geomspace(1e5, 1e8, 12)
    text = study_text(fmu, ks, execution=f"  start_method: {method}").replace("timeout_s: 30", "timeout_s: 0.5")
    t0 = time.monotonic()
    result, runs = run(tmp_path, text)
    assert (runs["status"] == "ok").all(), runs[runs["status"] != "ok"][["k", "message"]].to_string()
    exact(runs)
    assert time.monotonic() - t0 < 120


def test_a_large_description_goes_to_spawned_workers_with_the_variables_runs_use(tmp_path, leaky_so):
    from fmusa.fmi.info import read_fmu_info
    from fmusa.runs.pool import _lean_info
    from fmusa.study.plan import study_plan_spec

    fmu = build_leaky(tmp_path / "fmu", extra=3000, binary=leaky_so)
    study = parse_study(study_text(fmu, [1e6]), tmp_path / "s.yaml")
    spec = study_plan_spec(study, fmu)
    info = read_fmu_info(fmu)
    lean = _lean_info(info, spec)
    assert len(info.variables) == 3008
    assert {v.name for v in lean.variables} == {"k", "F", "y_peak"} | set(spec.outputs)
    assert lean.variable("k") is not None and lean.variable("p_7") is None
    assert info.variable("p_7") is not None         # the parent's own reading is untouched


def test_resume_with_retry_failed_reruns_only_the_failed_runs(tmp_path, leaky):
    """A finished study with runs that failed on worn workers (retries: 0): --resume keeps them failed,
    --resume --retry-failed runs exactly those again (on fresh workers they work) and keeps the rest."""
    ks = np.geomspace(1e5, 1e8, 40)
    text = study_text(leaky, ks, fixed="  leak_mb: 8\n  crash_above_mb: 100", execution="  retries: 0")
    study = parse_study(text, tmp_path / "s.yaml")
    first = run_study(study, tmp_path / "out", figures=False, progress=False)
    n_failed = int((first.runs["status"] == "failed").sum())
    assert n_failed >= 2
    again = run_study(study, tmp_path / "out", resume=True, figures=False, progress=False)
    assert again.summary["simulated_this_session"] == 0 and (again.runs["status"] == "failed").sum() == n_failed
    fixed = run_study(study, tmp_path / "out", resume=True, retry_failed=True, figures=False, progress=False)
    assert fixed.summary["simulated_this_session"] == n_failed
    assert len(fixed.runs) == 40 and (fixed.runs["status"] == "ok").all()
    exact(fixed.runs)
    ok_before = first.runs[first.runs["status"] == "ok"].set_index("k")["y_max"]
    pd.testing.assert_series_equal(fixed.runs.set_index("k").loc[ok_before.index, "y_max"], ok_before)
    # a later plain resume sees the new rows, not the old failed lines still in runs.csv
    last = run_study(study, tmp_path / "out", resume=True, figures=False, progress=False)
    assert last.summary["simulated_this_session"] == 0 and (last.runs["status"] == "ok").all()


def test_retry_failed_without_resume_is_refused(tmp_path):
    from fmusa.cli import main
    assert main(["sweep", str(tmp_path / "none.yaml"), "--out", str(tmp_path / "o"), "--retry-failed"]) == 2


def test_workers_that_die_before_they_are_ready_fail_the_runs_instead_of_looping(tmp_path):
    """An FMU whose library ends any process that loads it (exit code 3): no worker ever says "ready";
    after three in a row every run fails with the reason, and the study ends."""
    from fmusa.runs.evaluator import Evaluator
    from fmusa.study.plan import study_plan_spec

    fmu = build_leaky(tmp_path / "fmu", defines=("LEAKY_EXIT_ON_LOAD",))
    ks = np.geomspace(1e5, 1e8, 6)
    study = parse_study(study_text(fmu, ks), tmp_path / "s.yaml")
    got: list = []
    t0 = time.monotonic()
    with Evaluator(study_plan_spec(study, fmu), workers=2, isolate=True) as ev:
        ev.map_batches((np.arange(6), ks.reshape(-1, 1)), got.append)
    results = [r for b in got for r in b.results()]
    assert sorted(r.run_id for r in results) == list(range(6))
    import re
    assert all(r.status == "failed" and re.fullmatch(
        r"no worker process could load the FMU \(the worker process exited with code 3, [34] times in a row\)",
        r.message) for r in results), [r.message for r in results]
    assert time.monotonic() - t0 < 60
