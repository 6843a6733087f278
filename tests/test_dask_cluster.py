"""A study on a real Dask cluster: ``dask scheduler`` and ``dask worker`` started as separate processes, as a
cluster user starts them (the CLI entry points beside this Python), and ``fmusa sweep --scheduler``.

The results must be the local ones, every run must keep to ``execution.timeout_s`` on the Dask workers too,
and a Dask worker killed mid-study (``kill -9``) must cost nothing: its task is rescheduled, the runs on disk
stay, the study completes and the worker's supervised FMU process dies with it. Every process started here
is torn down by the fixtures, whatever a test does.
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from slow_study import SLOW as SLOW_STUDY

pytest.importorskip("dask")
distributed = pytest.importorskip("distributed")
psutil = pytest.importorskip("psutil")

from fmusa.fmi.archive import OWNER_FILE, PREFIX   # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DASK = Path(sys.executable).with_name("dask")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _gone(procs, within: float) -> list:
    """The processes of ``procs`` still alive (zombies count as gone) after waiting up to ``within`` s."""
    t_end = time.monotonic() + within
    while True:
        alive = []
        for p in procs:
            try:       # is_running: not a process that took over the PID since
                if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                    alive.append(p)
            except psutil.NoSuchProcess:
                pass
        if not alive or time.monotonic() > t_end:
            return alive
        time.sleep(0.05)


class Cluster:
    """A scheduler and ``n`` workers (``--nworkers 1 --nthreads 1`` each), their temporary files in ``tmp``."""

    def __init__(self, root: Path, n: int = 2) -> None:
        if not DASK.exists():
            pytest.skip(f"no dask command beside {sys.executable}")
        self.root = root
        self.tmp = root / "tmp"
        self.tmp.mkdir(parents=True)
        self.env = {**os.environ, "TMPDIR": str(self.tmp)}
        self.address = f"tcp://127.0.0.1:{_free_port()}"
        self.procs: list[subprocess.Popen] = []
        self._seen: list = []            # every process of the cluster ever seen (for the teardown)
        port = self.address.rsplit(":", 1)[1]
        self._start("scheduler", [str(DASK), "scheduler", "--host", "127.0.0.1", "--port", port, "--no-dashboard"])
        for i in range(n):
            self._start(f"worker{i}", [str(DASK), "worker", self.address, "--nworkers", "1", "--nthreads", "1",
                                       "--no-dashboard", "--memory-limit", "0", "--name", f"w{i}",
                                       "--local-directory", str(root / f"w{i}")])
        with distributed.Client(self.address, timeout=30) as client:
            client.wait_for_workers(n, timeout=60)

    def _start(self, name: str, cmd: list[str]) -> None:
        log = open(self.root / f"{name}.log", "wb")
        self.procs.append(subprocess.Popen(cmd, env=self.env, stdout=log, stderr=subprocess.STDOUT,
                                           start_new_session=True))
        log.close()

    def worker_pids(self) -> dict[str, int]:
        """Dask worker address -> PID of the process that runs its tasks (the nanny's child)."""
        with distributed.Client(self.address, timeout=30) as client:
            return client.run(os.getpid)

    def remember(self) -> None:
        for p in self.procs:
            try:
                self._seen += [psutil.Process(p.pid)] + psutil.Process(p.pid).children(recursive=True)
            except psutil.NoSuchProcess:
                pass

    def close(self) -> None:
        """Workers first (SIGTERM: a graceful close), then the scheduler; anything left is killed."""
        self.remember()
        for p in reversed(self.procs):
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
                try:
                    p.wait(15)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait(5)
        for p in _gone(self._seen, 5):
            p.kill()


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    c = Cluster(tmp_path_factory.mktemp("dask"))
    try:
        yield c
    finally:
        c.close()
    # a Dask worker that closes removes the FMUs it unpacked (the supervised pools' atexit hook)
    assert sorted(p.name for p in c.tmp.glob(PREFIX + "*")) == []


@pytest.fixture(scope="module")
def fmu(tmp_path_factory) -> Path:
    """A copy of the built FMU for the local and the Dask runs alike (`make fmu` may replace the original)."""
    from fmusa.fmi.info import default_fmu_path
    return Path(shutil.copy(default_fmu_path(), tmp_path_factory.mktemp("fmu") / "ScrewVertebra.fmu"))


def sweep(fmu: Path, *args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    """``fmusa sweep ARGS`` of ``fmu`` (``fmu: default`` in the studies, through $FMUSA_FMU)."""
    return subprocess.run([sys.executable, "-m", "fmusa.cli", "sweep", *args, "--quiet", "--no-figures"],
                          capture_output=True, text=True, timeout=timeout, cwd=ROOT,
                          env={**os.environ, "FMUSA_FMU": str(fmu)})


def _rows(out: Path):
    """runs.csv without what differs from one execution to the next (run ids, order, seconds), sorted."""
    import pandas as pd
    runs = pd.read_csv(out / "runs.csv", keep_default_na=False, na_values=[""])
    assert runs["run_id"].is_unique
    runs = runs.drop(columns=["run_id", "seconds"])
    return runs.sort_values(list(runs.columns)).reset_index(drop=True)


def _lines(path: Path) -> list[str]:
    """The complete data lines of runs.csv, as written (a line cut short is not one)."""
    return [ln for ln in (path.read_bytes().decode().split("\r\n")[1:-1] if path.exists() else []) if ln]


def test_the_paper_study_on_dask_gives_the_local_result(cluster, fmu, tmp_path):
    local = sweep(fmu, "studies/paper.yaml", "--out", str(tmp_path / "local"))
    assert local.returncode == 0, local.stderr
    workers = cluster.worker_pids()
    t0 = time.monotonic()
    dask = sweep(fmu, "studies/paper.yaml", "--out", str(tmp_path / "dask"), "--scheduler", cluster.address)
    wall = time.monotonic() - t0
    assert dask.returncode == 0, dask.stderr
    a = json.loads((tmp_path / "local" / "summary.json").read_text())
    b = json.loads((tmp_path / "dask" / "summary.json").read_text())
    assert b["optimum"] == a["optimum"] and b["binding_constraint"] == a["binding_constraint"]
    assert b["runs"] == a["runs"] and b["failed"] == a["failed"] == 0
    import pandas as pd
    pd.testing.assert_frame_equal(_rows(tmp_path / "dask"), _rows(tmp_path / "local"))   # every metric, exactly
    # the FMU ran on the Dask workers: each unpacked it once, in its own temporary folder
    owners = {int((d / OWNER_FILE).read_text()) for d in cluster.tmp.glob(PREFIX + "*")}
    assert owners == set(workers.values()), (owners, workers)
    assert cluster.worker_pids() == workers                                  # no worker restarted
    print(f"paper study on Dask: {b['runs']} runs in {wall:.1f} s")


#: The time-limit study of test_faults.py (slow_study.py) with two slow runs and two fast ones, on the
#: cluster's workers.
SLOW = SLOW_STUDY.replace("[1.0e-5, 1.0e-9]", "[1.0e-5, 1.0e-9, 2.0e-5, 2.0e-9]").replace("workers: 1, ", "")


def test_on_dask_each_run_keeps_to_timeout_s(cluster, fmu, tmp_path):
    """Two runs of minutes each and two fast ones: each slow run is stopped after its own timeout_s on the
    Dask worker (its supervised process is replaced), the fast ones are exact, the Dask workers survive."""
    study = tmp_path / "slow.yaml"
    study.write_text(SLOW)
    workers = cluster.worker_pids()
    t0 = time.monotonic()
    r = sweep(fmu, str(study), "--out", str(tmp_path / "out"), "--scheduler", cluster.address)
    wall = time.monotonic() - t0
    assert r.returncode == 0, r.stderr
    import pandas as pd
    runs = pd.read_csv(tmp_path / "out" / "runs.csv", keep_default_na=False, na_values=[""]).set_index("h")
    for h in (1e-9, 2e-9):
        assert runs.loc[h, "status"] == "failed"
        assert runs.loc[h, "message"].startswith("timed out after 1 s (execution.timeout_s; its worker process "
                                                 "was stopped)"), runs.loc[h, "message"]
        assert 1.0 <= runs.loc[h, "seconds"] < 2.0
    assert (runs.loc[[1e-5, 2e-5], "status"] == "ok").all()
    assert wall < 15, f"the study took {wall:.1f} s"
    assert cluster.worker_pids() == workers


#: 40 runs of ~0.1 s each (the 6-DOF case with h_max = 1e-5 s): 20 Dask tasks of two runs, a few seconds.
KILLED = """\
name: killed
fmu: default
parameters:
  c: {variable: c_y, unit: N/m}
fixed: {F_max: 411, t_ramp: 0.05, h_max: 1.0e-5}
scenario: {stop_time: 0.1, inputs: {F_ext_x: 20}}
metrics:
  max_y: {output: y_max, unit: m}
  x_final: {output: x, unit: m}
stages:
  grid: {base: 1.1, exponents: {c: [130, 169]}}
"""


def test_a_dask_worker_killed_mid_study_loses_nothing(fmu, tmp_path):
    c = Cluster(tmp_path / "cluster")
    try:
        study = tmp_path / "killed.yaml"
        study.write_text(KILLED)
        out = tmp_path / "out"
        with distributed.Client(c.address, timeout=30) as client:
            address, pid = next(iter(client.run(os.getpid).items()))
            victim = psutil.Process(pid)
            proc = subprocess.Popen([sys.executable, "-m", "fmusa.cli", "sweep", str(study), "--out", str(out),
                                     "--quiet", "--no-figures", "--scheduler", c.address],
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                                    env={**os.environ, "FMUSA_FMU": str(fmu)})
            try:
                t_end = time.monotonic() + 60
                while True:    # mid-study: results on disk, a task on the victim, its FMU process up
                    children = victim.children(recursive=True)
                    busy = client.processing([address]).get(address)
                    if children and busy and len(_lines(out / "runs.csv")) >= 4:
                        break
                    assert proc.poll() is None, f"the study ended before a worker was killed: {proc.stderr.read()}"
                    assert time.monotonic() < t_end, "no Dask worker started a task within 60 s"
                    time.sleep(0.02)
                c.remember()
                victim.kill()
                t_kill = time.monotonic()
                on_disk = _lines(out / "runs.csv")
                assert not _gone(children, 5), "the killed Dask worker's FMU process outlived it"
                print(f"{len(children)} supervised process(es) gone {time.monotonic() - t_kill:.2f} s after the "
                      f"Dask worker's kill -9 in task(s) {list(busy)}; {len(on_disk)} of 40 runs were on disk")
                stdout, stderr = proc.communicate(timeout=90)
            finally:
                if proc.poll() is None:
                    proc.kill()
                    proc.communicate()
        assert proc.returncode == 0, stderr
        assert "40 runs (40 simulated now, 0 failed)" in stdout, stdout     # the lost task was run again
        final = _lines(out / "runs.csv")
        assert len(final) == 40 and all(",ok,," in ln for ln in final)
        assert set(on_disk) <= set(final)                                    # what was on disk is still there
        assert 4 <= len(on_disk) < 40
    finally:
        c.close()


def test_the_search_in_rounds_on_dask(cluster, fmu, tmp_path):
    """studies/paper.yaml with search.parallel: auto on the cluster: as many points per round as its
    threads (2), the sequential search's optimum level by level, fewer rounds than at 1 point per round."""
    text = (ROOT / "studies" / "paper.yaml").read_text(encoding="utf-8")
    summaries = {}
    for name, par, args in (("seq", "false", ()), ("one", "1", ()), ("dask", "auto", ("--scheduler", cluster.address))):
        study = tmp_path / f"{name}.yaml"
        study.write_text(text.replace("    parallel: false", f"    parallel: {par}"), encoding="utf-8")
        t0 = time.monotonic()
        r = sweep(fmu, str(study), "--out", str(tmp_path / name), *args)
        assert r.returncode == 0, r.stderr
        summaries[name] = json.loads((tmp_path / name / "summary.json").read_text())
        summaries[name]["wall"] = time.monotonic() - t0
    seq, one, dask = summaries["seq"], summaries["one"], summaries["dask"]
    assert dask["optimum"] == one["optimum"] == seq["optimum"]
    for key in ("search", "paper_roi_search"):
        assert [(lv["outer"], lv["inner"]) for lv in dask[key]["levels"]] == \
               [(lv["outer"], lv["inner"]) for lv in seq[key]["levels"]]
        assert dask[key]["parallel"]["workers"] == 2 and dask[key]["parallel"]["largest_round"] == 2
        assert dask[key]["parallel"]["sequential_rounds"] == seq[key]["evaluations"]
    assert seq["rounds"] > one["rounds"] > dask["rounds"], (seq["rounds"], one["rounds"], dask["rounds"])
    assert dask["failed"] == 0
    print(f"paper study in rounds on Dask (2 threads): {dask['rounds']} rounds, {dask['runs']} runs, "
          f"{dask['wall']:.1f} s; locally at 1 point per round {one['rounds']}, sequential {seq['rounds']}")


@pytest.mark.slow
def test_a_lost_scheduler_is_an_interruption_and_resume_gives_the_local_numbers(fmu, tmp_path):
    """The Dask scheduler killed mid-study: no run is stored as failed, the study stops with exit 1 and says
    to resume; ``--resume`` on a new cluster completes it with the numbers of a local run, exactly."""
    study = tmp_path / "lost.yaml"
    study.write_text(KILLED)
    out = tmp_path / "out"
    c = Cluster(tmp_path / "cluster")
    try:
        proc = subprocess.Popen([sys.executable, "-m", "fmusa.cli", "sweep", str(study), "--out", str(out),
                                 "--quiet", "--no-figures", "--scheduler", c.address],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT,
                                env={**os.environ, "FMUSA_FMU": str(fmu)})
        try:
            t_end = time.monotonic() + 60
            while len(_lines(out / "runs.csv")) < 4:       # mid-study: results on disk
                assert proc.poll() is None, f"the study ended before the scheduler was killed: {proc.stderr.read()}"
                assert time.monotonic() < t_end, "no results within 60 s"
                time.sleep(0.02)
            c.remember()
            c.procs[0].kill()                               # the scheduler
            stdout, stderr = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
    finally:
        c.close()
    assert proc.returncode == 1, (stdout, stderr)
    assert "connection to the Dask scheduler" in stderr and "--resume" in stderr, stderr
    kept = _lines(out / "runs.csv")
    assert 4 <= len(kept) < 40 and all(",ok,," in ln for ln in kept), kept      # nothing stored as failed
    c2 = Cluster(tmp_path / "cluster2")
    try:
        r = sweep(fmu, str(study), "--out", str(out), "--resume", "--scheduler", c2.address)
    finally:
        c2.close()
    assert r.returncode == 0, r.stderr
    local = sweep(fmu, str(study), "--out", str(tmp_path / "local"))
    assert local.returncode == 0, local.stderr
    import pandas as pd
    pd.testing.assert_frame_equal(_rows(out), _rows(tmp_path / "local"))
