"""The fit workers are kept from one stage of a diagnosis to the next (and from one unit of a study to the
next): spawning one costs about 2 s of CPU. Kept only while the environment they were spawned with holds, and
a run budget lent to them counts for the diagnosis that lent it."""
from __future__ import annotations

import os
import time
from concurrent.futures.process import BrokenProcessPool

import pytest

from fmusa.diagnose import budget as rb
from fmusa.diagnose import fitcache


def _pid() -> int:
    return os.getpid()


def _take(n: int) -> int:
    """Take n runs from the worker's budget (as an FMU runner does) and say which process did."""
    rb.take({}, "fit", n)
    return os.getpid()


def test_workers_are_kept_between_calls_and_replaced_when_the_environment_changes(monkeypatch, tmp_path):
    first = set(fitcache.map_in_pool(_pid, [()] * 6, 2))
    again = set(fitcache.map_in_pool(_pid, [()] * 6, 2))
    assert os.getpid() not in first
    assert again <= first, (first, again)        # the same processes, not new ones
    monkeypatch.setenv("FMUSA_TEST_POOL_ENV", "changed")
    changed = set(fitcache.map_in_pool(_pid, [()] * 6, 2))
    assert not changed & first, (first, changed)  # spawned again: they must see the new environment
    monkeypatch.chdir(tmp_path)
    moved = set(fitcache.map_in_pool(_pid, [()] * 6, 2))
    assert not moved & changed, (changed, moved)  # and a new working directory (relative paths)
    fitcache._drop_pool()


def _square_or_die(i: int, die: int) -> int:
    """i squared, or the worker's process ends (as an FMU that crashes ends it) when i is ``die``."""
    if i == die:
        time.sleep(0.5)            # the others are done first
        os._exit(3)
    return i * i


def test_each_in_pool_gives_each_result_when_done_and_what_was_done_when_a_worker_died():
    assert dict(fitcache.each_in_pool(_square_or_die, [(i, -1) for i in range(5)], 2)) == {i: i * i for i in range(5)}
    got = {}
    with pytest.raises(BrokenProcessPool, match="worker process died"):
        for i, r in fitcache.each_in_pool(_square_or_die, [(i, 4) for i in range(5)], 2):
            got[i] = r
    assert got == {i: i * i for i in range(4)}       # every call done before the crash, none after
    assert fitcache._POOL is None                      # the broken pool is dropped
    assert dict(fitcache.each_in_pool(_square_or_die, [(2, -1), (3, -1)], 2)) == {0: 4, 1: 9}   # a new one
    fitcache._drop_pool()


def test_a_lent_budget_counts_the_workers_runs_and_gives_them_back():
    a, b = rb.RunBudget(), rb.RunBudget(100)
    with fitcache._pool_in_use(2, 0) as (pool, _):
        _lend_to(pool, a, b)
    fitcache._drop_pool()


def _lend_to(pool, a, b) -> None:
    with pool.lent(a):
        [f.result() for f in [pool.ex.submit(_take, 3) for _ in range(4)]]
    with pool.lent(b):
        [f.result() for f in [pool.ex.submit(_take, 5) for _ in range(2)]]
    assert (a.used, b.used) == (12, 10)
    with pool.lent(b):       # b's limit holds in the workers: 10 used, 95 more would pass 100
        fut = pool.ex.submit(_take, 95)
        try:
            fut.result()
            raised = False
        except rb.BudgetExhausted:
            raised = True
    assert raised
    assert b.used == 10


def test_kept_workers_end_when_idle_and_not_while_a_call_waits(monkeypatch):
    """The kept pool ends IDLE_S after its last call (its processes exit), never during a call, however long
    the call; a call after that starts a new pool."""
    monkeypatch.setattr(fitcache, "IDLE_S", 0.5)
    fitcache._drop_pool()
    assert fitcache.map_in_pool(_square_or_die, [(i, -1) for i in range(3)], 2) == [0, 1, 4]
    pool = fitcache._POOL
    procs = list(pool.ex._processes.values())
    assert procs and all(p.is_alive() for p in procs)
    with fitcache._pool_in_use(2, 0) as (same, _):       # in use for longer than IDLE_S: kept
        assert same is pool
        time.sleep(1.0)
        assert fitcache._POOL is pool and pool.ex.submit(_square_or_die, 5, -1).result() == 25
    deadline = time.monotonic() + 10.0
    while fitcache._POOL is not None and time.monotonic() < deadline:
        time.sleep(0.1)
    assert fitcache._POOL is None
    while any(p.is_alive() for p in procs) and time.monotonic() < deadline:   # the timer's shutdown joins them
        time.sleep(0.1)
    assert not any(p.is_alive() for p in procs)
    assert fitcache.map_in_pool(_square_or_die, [(2, -1), (3, -1)], 2) == [4, 9]   # a new pool
    assert fitcache._POOL is not pool
    fitcache._drop_pool()


def test_a_script_without_a_main_guard_is_told_so_not_that_the_fmu_crashed(tmp_path):
    """Spawned workers import the main module: an unguarded script starts the fits again in each, which
    Python stops before the fit begins. The error must name that, not blame the FMU."""
    import subprocess
    import sys
    from pathlib import Path

    script = tmp_path / "unguarded.py"
    script.write_text(
        "from fmusa.diagnose.fitcache import run_fits\n"
        "jobs = [('model.fmu', name, 'force', [], 1, None) for name in ('none', 'backlash_gap')]\n"
        "print('RESULT', run_fits(jobs, 2, None, 'key', False))\n")
    src = str(Path(__file__).resolve().parents[1] / "src")
    env = {**os.environ, "PYTHONPATH": src + os.pathsep + os.environ.get("PYTHONPATH", "")}
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=240)
    line = [ln for ln in out.stdout.splitlines() if ln.startswith("RESULT")]
    assert line, (out.stdout[-2000:], out.stderr[-2000:])
    assert line[0].count('if __name__ == "__main__":') == 2, line[0]
    assert "crashes in this fit" not in line[0]
