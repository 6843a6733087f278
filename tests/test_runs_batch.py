"""Runs in batches (fmusa.runs): a batch gives the same values as run by run, runs.csv written in blocks
has the bytes written row by row, a resumed store drops a block cut short by a kill, and the Sobol indices
of a study run in blocks through the worker pool equal those of the same samples run one by one."""
from __future__ import annotations

import dataclasses
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from fmusa.analysis.sensitivity import analyse_sobol, draw_samples, salib_problem, to_physical
from fmusa.pipeline.sensitivity import run_sensitivity, sensitivity_spec
from fmusa.runs.evaluator import Evaluator
from fmusa.runs.spec import RunBatch, as_arrays, run_batch, run_chunk
from fmusa.runs.store import RunStore
from fmusa.study.loader import load_study

ROOT = Path(__file__).resolve().parents[1]
SUBSET = ["c_x", "c_z", "d_x", "d_beta"]


@pytest.fixture(scope="module")
def six_dof(fmu_path):
    study = dataclasses.replace(load_study(ROOT / "studies" / "six_dof.yaml"), fmu=fmu_path)
    full = study.stages["sensitivity"]
    stage = dataclasses.replace(full, parameters={k: full.parameters[k] for k in SUBSET}, methods=["sobol"],
                                n=16, seed=5)
    return study, stage


def _samples(stage) -> np.ndarray:
    return to_physical(stage, draw_samples(stage, "sobol"))


def test_a_batch_gives_the_values_of_runs_one_by_one(six_dof):
    study, stage = six_dof
    spec = sensitivity_spec(study, stage)
    P = _samples(stage)[:40].copy()
    P[7, SUBSET.index("d_beta")] = -1.0            # rejected by the FMU: a failed run inside the batch
    items = [(100 + i, tuple(row)) for i, row in enumerate(P.tolist())]
    one_by_one = [run_chunk(spec, [it])[0] for it in items]
    batch = run_batch(spec, *as_arrays(items))
    assert batch.run_ids.tolist() == [it[0] for it in items]
    assert batch.ok.tolist() == [r.status == "ok" for r in one_by_one] and not batch.ok[7]
    for i, r in enumerate(one_by_one):
        if r.status == "ok":
            assert batch.metrics[i].tobytes() == r.metrics.tobytes()        # bit for bit
        else:
            assert np.isnan(batch.metrics[i]).all() and batch.messages[i] == r.message
    # the pool: chunks to workers, RunBatches back, in any order
    with Evaluator(spec, workers=2, pool_threshold=1, timeout_s=60) as ev:
        got = []
        ev.map_batches(items, got.append)
    pooled = RunBatch.concat(got)
    order = np.argsort(pooled.run_ids)
    assert pooled.run_ids[order].tolist() == batch.run_ids.tolist()
    assert pooled.metrics[order].tobytes() == batch.metrics.tobytes()
    assert pooled.ok[order].tolist() == batch.ok.tolist()


def _batch(n: int, seed: int = 0) -> RunBatch:
    rng = np.random.default_rng(seed)
    values = rng.lognormal(size=(n, 2)) * np.array([1e6, 1e2])
    metrics = rng.normal(size=(n, 3))
    metrics[3, 1] = np.nan                       # a metric without value in a run that worked
    metrics[5, 0] = -0.0
    ok = np.ones(n, bool)
    ok[[2, 9]] = False
    msgs = {2: 'FMU said: "no", bad k, see\nlog', 9: "plain failure"}
    return RunBatch(np.arange(n, dtype=np.int64) + 10, values, np.where(ok[:, None], metrics, np.nan), ok,
                    rng.uniform(size=n) * 1e-3, msgs)


CONSTRAINTS = [SimpleNamespace(name="small", metric="m0", max=0.5, min=None, required=True),
               SimpleNamespace(name="pos", metric="m2", max=None, min=0.0, required=False)]


def test_runs_csv_in_blocks_has_the_bytes_of_row_by_row(tmp_path):
    b = _batch(12)
    blocks = RunStore(tmp_path / "blocks.csv", ["c", "d"], ["m0", "m1", "m2"], CONSTRAINTS)
    rows = RunStore(tmp_path / "rows.csv", ["c", "d"], ["m0", "m1", "m2"], CONSTRAINTS)
    blocks.add_batch("sobol", RunBatch(b.run_ids[:5], b.values[:5], b.metrics[:5], b.ok[:5], b.seconds[:5],
                                       {i: m for i, m in b.messages.items() if i < 5}))
    blocks.add_batch("sobol", RunBatch(b.run_ids[5:], b.values[5:], b.metrics[5:], b.ok[5:], b.seconds[5:],
                                       {i - 5: m for i, m in b.messages.items() if i >= 5}))
    for r in b.results():
        rows.add(r.run_id, "sobol", r.values, r.metrics, r.status, r.message, r.seconds)
    blocks.close()
    rows.close()
    assert (tmp_path / "blocks.csv").read_bytes() == (tmp_path / "rows.csv").read_bytes()
    pd.testing.assert_frame_equal(blocks.frame(), rows.frame())
    assert blocks.get(b.values[0]) == rows.get(b.values[0]) and blocks.get(b.values[0])["status"] == "ok"
    assert blocks.get(b.values[2])["message"] == b.messages[2].replace("\n", " | ")   # stored on one line
    back = pd.read_csv(tmp_path / "blocks.csv")
    assert back[["c", "d"]].to_numpy().tobytes() == b.values.tobytes()
    ok = b.ok
    assert np.array_equal(back[["m0", "m1", "m2"]].to_numpy()[ok], b.metrics[ok], equal_nan=True)


def test_resume_after_a_block_cut_short(tmp_path):
    b = _batch(12, seed=1)
    path = tmp_path / "runs.csv"
    store = RunStore(path, ["c", "d"], ["m0", "m1", "m2"], CONSTRAINTS)
    store.add_batch("grid", RunBatch(b.run_ids[:8], b.values[:8], b.metrics[:8], b.ok[:8], b.seconds[:8],
                                     {i: m for i, m in b.messages.items() if i < 8}))
    store.close()
    full = path.read_bytes()
    lines = full.split(b"\r\n")
    cut = len(b"\r\n".join(lines[:7])) + 2 + len(lines[7]) // 2      # in the middle of the 7th run's row
    path.write_bytes(full[:cut])

    resumed = RunStore(path, ["c", "d"], ["m0", "m1", "m2"], CONSTRAINTS, resume=True)
    assert len(resumed) == 6 and resumed.next_id == b.run_ids[5] + 1
    assert resumed.get(b.values[6]) is None and resumed.get(b.values[5]) is not None
    assert resumed.get(b.values[2])["status"] == "failed"
    todo = [i for i in range(12) if resumed.get(b.values[i]) is None]
    assert todo == list(range(6, 12))
    rest = RunBatch(b.run_ids[6:], b.values[6:], b.metrics[6:], b.ok[6:], b.seconds[6:],
                    {i - 6: m for i, m in b.messages.items() if i >= 6})
    resumed.add_batch("grid", rest)
    resumed.close()

    ref = RunStore(tmp_path / "ref.csv", ["c", "d"], ["m0", "m1", "m2"], CONSTRAINTS)
    ref.add_batch("grid", b)
    ref.close()
    assert path.read_bytes() == (tmp_path / "ref.csv").read_bytes()
    again = RunStore(path, ["c", "d"], ["m0", "m1", "m2"], CONSTRAINTS, resume=True)
    pd.testing.assert_frame_equal(again.frame(), ref.frame(), check_exact=True)
    again.close()


def test_sobol_indices_of_runs_in_blocks_equal_those_of_runs_one_by_one(six_dof, tmp_path):
    study, stage = six_dof
    runner = SimpleNamespace(evaluator=SimpleNamespace(workers=2, scheduler=None, isolate=True, timeout_s=60),
                             simulated=0)
    res = run_sensitivity(study, stage, tmp_path, runner, progress=False, resume=False, accuracy_samples=0)
    s = res["summary"]
    assert s["failed"] == 0 and s["errors"] == {}
    spec = sensitivity_spec(study, stage)
    P = _samples(stage)
    outputs = list(stage.outputs)
    rules = {r.name: k for k, r in enumerate(spec.rules)}
    Y = np.array([run_chunk(spec, [(i, tuple(row))])[0].metrics for i, row in enumerate(P.tolist())])
    Y = Y[:, [rules[m] for m in outputs]]
    ref, _ = analyse_sobol(salib_problem(stage), Y, outputs, stage.seed)
    assert s["sobol"] == ref


@pytest.mark.parametrize("collide", [False, True])
def test_keys_stay_apart_and_a_key_again_replaces_its_row(tmp_path, monkeypatch, collide):
    if collide:     # every key: one hash, in the batch path and the one-key path alike
        monkeypatch.setattr(RunStore, "_hashes", lambda self, U: [7] * len(U))
        monkeypatch.setattr(RunStore, "_key_hash", lambda self, raw: 7)
    b = _batch(12, seed=2)
    store = RunStore(tmp_path / "runs.csv", ["c", "d"], ["m0", "m1", "m2"])
    store.add_batch("grid", b)
    assert len(store) == 12
    assert store.rows_of(b.values).tolist() == list(range(12))
    assert store.get([-1.0, 2.0]) is None and store.rows_of([[0.0, -0.0]]).tolist() == [-1]
    store.add(99, "grid", [0.0, -0.0], np.array([1.0, 2.0, 3.0]), "ok", "", 0.1)
    assert store.get([-0.0, 0.0])["run_id"] == 99 and len(store) == 13
    store.add(100, "grid", b.values[4], np.array([1.0, 2.0, 3.0]), "ok", "", 0.1)   # a key again: the new row
    assert store.get(b.values[4])["run_id"] == 100 and len(store) == 13
    assert len(store.frame()) == 13
    store.close()
    again = RunStore(tmp_path / "runs.csv", ["c", "d"], ["m0", "m1", "m2"], resume=True)
    assert again.get(b.values[4])["run_id"] == 100 and len(again) == 13
    again.close()


def test_the_one_key_hash_is_the_batch_hash(tmp_path):
    """A search looks keys up one at a time in plain Python (RunStore.row_of, _key_hash), a study's grid in
    batches with numpy (rows_of, _hashes): the two must give every key the same hash and the same row."""
    rng = np.random.default_rng(11)
    P = rng.normal(size=(300, 3)) * 10.0 ** rng.integers(-300, 300, size=(300, 3))
    P[:5] = [[0.0, -0.0, 1.0], [-0.0, 0.0, -0.0], [np.inf, -np.inf, 5e-324], [1.0, 2.0, 3.0], [1.0, 2.0, -3.0]]
    store = RunStore(tmp_path / "runs.csv", ["a", "b", "c"], ["m"])
    batch_hashes = store._hashes(store._bits(P))
    one = [store._key_hash(store._pack.pack(*[float(v) + 0.0 for v in row])) for row in P.tolist()]
    assert one == batch_hashes
    n = len(P)
    store.add_batch("grid", RunBatch(np.arange(150), P[:150], np.ones((150, 1)), np.ones(150, bool), np.zeros(150), {}))
    for i, row in enumerate(P[150:].tolist()):       # one by one: the one-key path of _insert
        store.add(150 + i, "search", row, np.array([1.0]), "ok", "", 0.0)
    assert store.rows_of(P).tolist() == list(range(n))
    assert [store.row_of(row) for row in P.tolist()] == list(range(n))
    assert store.row_of([0.0, 0.0, 1.0]) == 0 and store.row_of([-0.0, -0.0, -0.0]) == 1   # -0.0 is 0.0
    store.close()


def test_the_flags_of_one_run_are_the_table_s():
    """A search's run gets its constraint flags in plain Python (constraint_holds), a grid's from the batch
    table (constraint_table): the same verdict on values at, inside and outside the bounds, NaN and inf."""
    from fmusa.runs.metrics import constraint_holds, constraint_table

    C = SimpleNamespace
    constraints = [C(name="hi", metric="m", max=1.0, min=None, required=False),
                   C(name="lo", metric="m", max=None, min=-1.0, required=False),
                   C(name="band", metric="m", max=1.0, min=-1.0, required=False),
                   C(name="req", metric="m", max=None, min=None, required=True),
                   C(name="free", metric="m", max=None, min=None, required=False)]
    x = np.array([-np.inf, -2.0, -1.0, 0.0, 1.0, np.nextafter(1.0, 2.0), np.inf, np.nan])
    table = constraint_table({"m": x}, constraints)
    for c in constraints:
        assert table[f"ok_{c.name}"].tolist() == [constraint_holds(c, v) for v in x.tolist()], c.name


def test_reductions_over_a_batch_equal_those_run_by_run():
    from fmusa.runs.metrics import REDUCTIONS, MetricRule, reduce_batch, reduce_series

    rng = np.random.default_rng(3)
    t = np.sort(rng.uniform(0, 2, size=41))
    t[0] = 0.0
    data = rng.normal(size=(25, 41, 3)) * np.exp(-3 * t)[None, :, None]
    data[4, :, 1] = -0.0
    data[6, -5:, 2] = 5.0                       # not settled
    rules = [MetricRule(f"{red}_{c}", c, red, scale=s, offset=o, missing_below=mb, settle_tol=0.05)
             for red in REDUCTIONS for c in range(3)
             for s, o, mb in ((1.0, 0.0, None), (-1e3, 2.5, None), (2.0, 0.0, -0.5))]
    batch = reduce_batch(t, data, rules)
    for i in range(len(data)):
        assert batch[i].tobytes() == reduce_series(t, data[i], rules).tobytes()
