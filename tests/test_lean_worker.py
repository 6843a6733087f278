"""The pool's lean worker path (issue 19): spawned workers run FMI 2.0 co-simulation FMUs on ctypes alone
(fmusa.fmi.lean), and every output is bit for bit what the fmpy path (RunPlan) gives, every error message
word for word, in each reuse mode: on our FMU, on the vendor exports of ../shared/vendor-fmus (those that
load here) and on the faulty C FMUs. What the lean path does not cover goes to fmpy."""
from __future__ import annotations

import json
import subprocess
import sys
from array import array
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from faulty_fmu import build_faulty  # noqa: E402
from fresh_runs import VENDOR  # noqa: E402

from fmusa.fmi.archive import extract_fmu  # noqa: E402
from fmusa.fmi.info import read_fmu_info  # noqa: E402
from fmusa.fmi.lean import LeanFMU  # noqa: E402
from fmusa.runs.metrics import MetricRule  # noqa: E402
from fmusa.runs.pool import PoolOptions, WorkerPool  # noqa: E402
from fmusa.runs.spec import PlanSpec, lean_view, plan_for, release_plan  # noqa: E402


def _message(exc: BaseException) -> str:
    return str(exc).strip().replace("\n", " | ")


def spec_on(folder: Path, varied, outputs, stop_time: float, step, fixed=(), inputs=(), reuse="reset",
            **kw) -> PlanSpec:
    rules = tuple(MetricRule(f"m{i}", i, "final") for i in range(len(outputs)))
    return PlanSpec(str(folder), tuple(varied), (1.0,) * len(varied), (0.0,) * len(varied), tuple(fixed),
                    tuple(inputs), tuple(outputs), stop_time, step, rules, reuse=reuse, **kw)


def fmpy_runs(spec: PlanSpec, rows) -> list:
    """Each row's outputs (bytes of the float64 array) or error message, from the fmpy path's RunPlan."""
    plan = plan_for(spec)
    out = []
    try:
        for r in rows:
            try:
                out.append(plan(list(r)).tobytes())
            except Exception as exc:  # noqa: BLE001 - compared with the lean path's
                out.append(_message(exc))
    finally:
        release_plan(spec)
    return out


def lean_runs(spec: PlanSpec, rows) -> list:
    view = lean_view(spec, read_fmu_info(spec.fmu_path))
    assert view is not None, "the lean path should cover this spec"
    fmu = LeanFMU(view.plan)
    out = []
    try:
        for r in rows:
            a = array("d")
            try:
                fmu.run(list(r), a)
                out.append(a.tobytes())
            except Exception as exc:  # noqa: BLE001 - compared with fmpy's
                out.append(_message(exc))
    finally:
        fmu.close()
    return out


def assert_same(spec: PlanSpec, rows) -> list:
    """The lean path's runs of ``rows`` equal the fmpy path's bit for bit (messages word for word)."""
    ref, lean = fmpy_runs(spec, rows), lean_runs(spec, rows)
    for i, (a, b) in enumerate(zip(ref, lean)):
        assert type(a) is type(b) and a == b, f"run {i} ({rows[i]}): fmpy {a!r:.300} != lean {b!r:.300}"
    assert len(ref) == len(rows)
    return ref


@pytest.fixture(scope="module")
def screw(tmp_path_factory, fmu_path) -> Path:
    return extract_fmu(fmu_path, tmp_path_factory.mktemp("screw") / "fmu", to_run=True)


@pytest.mark.parametrize("reuse", ["reset", "fresh"])   # no FMU state to snapshot: the faulty FMU has one
def test_our_fmu_sampled_and_one_step_bit_for_bit(screw, reuse):
    outs = ("y", "v_y", "y_max", "F_pull")
    rows = [(8e5, 500.0), (2e6, 900.0), (8e5, 500.0)]
    fixed = (("F_max", 411), ("t_ramp", 1.0), ("monitors", True))
    ref = assert_same(spec_on(screw, ("c_y", "d_y"), outs, 1.2, 0.05, fixed, reuse=reuse), rows)
    data = np.frombuffer(ref[0], dtype=float).reshape(-1, len(outs))
    assert data.shape == (25, 4) and np.ptp(data[:, 0]) > 0          # a run that moves: not a trivial match
    assert ref[0] == ref[2] and ref[0] != ref[1]
    assert_same(spec_on(screw, ("c_y",), outs, 0.5, None, fixed, reuse=reuse, subsample=1), rows[:2])


def test_our_fmu_subsampled_rows_and_an_input(screw):
    spec = spec_on(screw, ("c_y",), ("y", "y_max"), 1.0, 0.01, (("t_ramp", 1.0),), subsample=7)
    view = lean_view(spec, read_fmu_info(spec.fmu_path))
    assert view.plan["keep"][-1] == 100 and len(view.times) == len(view.plan["keep"])
    lean = LeanFMU(view.plan)
    a = array("d")
    lean.run([8e5], a)
    lean.close()
    full = fmpy_runs(replace(spec, subsample=1), [(8e5,)])[0]
    np.testing.assert_array_equal(np.frombuffer(full).reshape(-1, 2)[view.plan["keep"]],
                                  np.frombuffer(a.tobytes()).reshape(-1, 2))


def test_a_rejected_value_says_what_fmpy_says(screw):
    # c_y < 0 is refused by the FMU's own checks (fmi2Error, its log naming why), then the next run works
    rows = [(-1.0,), (8e5,), (-2.0,), (8e5,)]
    ref = assert_same(spec_on(screw, ("c_y",), ("y", "y_max"), 0.3, 0.1), rows)
    assert isinstance(ref[0], str) and "c_y = -1 is invalid" in ref[0] and isinstance(ref[1], bytes)


@pytest.mark.parametrize("fault,with_state", [("none", False), ("none", True), ("reset_zero", True),
                                              ("reset_zeros", False), ("reset_error", False),
                                              ("drop_early", False), ("euler", False)])
def test_faulty_fmus_in_each_reuse_mode(tmp_path, fault, with_state):
    fmu = build_faulty(tmp_path, fault, with_state=with_state, me=False, tolerance=1e-7)
    folder = extract_fmu(fmu, tmp_path / "x", to_run=True)
    rows = [(100.0, 2.0), (400.0, 1.0), (100.0, 2.0)]
    for reuse in ("reset", "fresh") + (("snapshot",) if with_state else ()):
        spec = spec_on(folder, ("k", "d"), ("x", "v", "x_peak", "tolerance_seen"), 1.0, 0.1,
                       (("F", 10.0),), (("u", 1.5),), reuse=reuse)
        ref = assert_same(spec, rows)
        if reuse == "fresh" or fault == "none":
            assert ref[0] == ref[2]
        assert np.frombuffer(ref[1])[-1] == 1e-7          # the default experiment's tolerance, set up as fmpy does


VENDOR_CS = {
    # file, parameter, values, outputs, stop, step
    "Dymola2023x_SpringFrictionPendulum1D.fmu": ("spring.c", [5.0, 20.0, 5.0], ["mass.s", "mass.v"], 1.0, 0.01),
    "20sim464_TorsionBar.fmu": ("Controller.PID.kp", [1.0, 4.0, 1.0], ["LoadDiskRev", "MotorDiskRev"], 0.2, 0.01),
    "MapleSim2024_CoupledClutches_CS.fmu": ("freqHz", [0.1, 0.4, 0.1], ["outputs[1]", "outputs[2]"], 0.5, 0.01),
    "OM1193_Mass_Damper.fmu": ("spring.c", [1e3, 3e4, 1e3], ["y"], 1.0, 0.01),
    "JModelica115_ControlledTemperature.fmu": (None, [0.0], [], 1.0, 0.1),
}


@pytest.mark.skipif(not VENDOR.is_dir(), reason=f"the shared vendor FMUs are not at {VENDOR}")
@pytest.mark.parametrize("name", list(VENDOR_CS))
def test_vendor_exports_bit_for_bit(tmp_path, name):
    parameter, values, outputs, stop, step = VENDOR_CS[name]
    folder = extract_fmu(VENDOR / name, tmp_path / "x", to_run=True)
    info = read_fmu_info(folder)
    if parameter is None:       # JModelica 1.15: its binary needs libgfortran.so.3
        try:
            plan_for(spec_on(folder, (), (), stop, step))
        except Exception as exc:  # noqa: BLE001 - the expected load failure
            pytest.skip(f"{name} does not load here: {str(exc)[:160]}")
        pytest.fail(f"{name} loads here now: give it a case")
    for reuse in ("reset", "fresh"):
        spec = spec_on(folder, (parameter,), tuple(outputs), stop, step, reuse=reuse,
                       interface="co-simulation" if "model-exchange" in info.interfaces else "auto")
        ref = assert_same(spec, [(v,) for v in values])
        assert ref[0] != ref[1]


def test_what_the_lean_path_does_not_cover_goes_to_fmpy(tmp_path, screw):
    base = spec_on(screw, ("c_y",), ("y",), 0.2, 0.1)
    info = read_fmu_info(screw)
    assert lean_view(base, info) is not None
    assert lean_view(replace(base, outputs=("n_steps",)), info) is None         # an Integer output
    assert lean_view(replace(base, refine_factor=10), info) is None             # refined peaks re-run the FMU
    assert lean_view(replace(base, fixed=(("c_y", np.float64(1.0)),)), info) is None   # not plain data
    assert lean_view(replace(base, fixed=(("no_such", 1.0),)), info) is None    # fmpy's path says why
    me = build_faulty(tmp_path, "none", me=True, name="MeOnly")
    me_dir = extract_fmu(me, tmp_path / "me", to_run=True)
    me_spec = spec_on(me_dir, ("k",), ("x",), 0.2, 0.1, interface="model-exchange")
    assert lean_view(me_spec, read_fmu_info(me_dir)) is None
    fmi3 = VENDOR / "MapleSim2024_CoupledClutches_FMI3.fmu"
    if fmi3.is_file():
        d = extract_fmu(fmi3, tmp_path / "fmi3", to_run=True)
        assert lean_view(spec_on(d, ("freqHz",), ("outputs[1]",), 0.1, 0.05), read_fmu_info(d)) is None


def _pool_batches(spec: PlanSpec, values: np.ndarray, method: str, lean: bool, monkeypatch) -> tuple:
    monkeypatch.setenv("FMUSA_LEAN_WORKERS", "1" if lean else "0")
    pool = WorkerPool(spec, 1, 30.0, PoolOptions(start_method=method, retries=0))
    got = []
    try:
        pool.map((np.arange(len(values)), values), got.append, len(values))
        assert (pool.lean is not None) == (lean and method == "spawn")
    finally:
        pool.close()
    from fmusa.runs.spec import RunBatch
    b = RunBatch.concat(got)
    order = np.argsort(b.run_ids)
    msgs = {int(b.run_ids[i]): m for i, m in b.messages.items()}
    return b.run_ids[order], b.metrics[order], b.ok[order], msgs


@pytest.fixture(scope="module")
def misbehave(tmp_path_factory) -> Path:
    """tests/fmus/misbehave unpacked (a spring y = F/k that misbehaves for k in [fault_lo, fault_hi])."""
    from fmusa.bench import _misbehave_fmu
    tmp = tmp_path_factory.mktemp("misbehave")
    fmu = _misbehave_fmu(tmp)
    if fmu is None:
        pytest.skip("needs gcc and Linux to build tests/fmus/misbehave")
    return extract_fmu(fmu, tmp / "x", to_run=True)


def misbehave_spec(folder: Path, kind: int) -> PlanSpec:
    return spec_on(folder, ("k",), ("y", "y_peak"), 1.0, 0.5,
                   (("F", 411.0), ("fault", 1.0), ("fault_kind", kind), ("fault_lo", 2.5e6), ("fault_hi", 4.5e6)))


@pytest.mark.parametrize("kind", [3, 4])     # NaN outputs, fmi2Error from fmi2DoStep
def test_misbehaving_runs_say_what_fmpy_says(misbehave, kind):
    ref = assert_same(misbehave_spec(misbehave, kind), [(1e6,), (3e6,), (5e6,), (4e6,), (1e6,)])
    assert [type(r) for r in ref] == [bytes, str, bytes, str, bytes]
    assert ("non-finite output y, y_peak" if kind == 3 else "fmi2DoStep returned Error") in ref[1]


def test_spawned_pool_lean_equals_fmpy_around_segfaults(misbehave, monkeypatch):
    """Through a spawned pool whose workers take the lean path, with runs that segfault their worker: the
    same metrics, failures and messages as workers on the fmpy path (forked, where fork exists)."""
    import multiprocessing as mp
    ks = np.array([[1e6], [3e6], [5e6], [4e6], [6e6]])
    spec = misbehave_spec(misbehave, 1)
    ids, m_lean, ok_lean, msg_lean = _pool_batches(spec, ks, "spawn", True, monkeypatch)
    ref = "fork" if "fork" in mp.get_all_start_methods() else "spawn"
    _, m_fmpy, ok_fmpy, msg_fmpy = _pool_batches(spec, ks, ref, False, monkeypatch)
    assert ok_lean.tolist() == ok_fmpy.tolist() == [True, False, True, False, True]
    np.testing.assert_array_equal(m_lean, m_fmpy)
    assert msg_lean == msg_fmpy and "SIGSEGV" in msg_lean[1] and "SIGSEGV" in msg_lean[3]
    np.testing.assert_array_equal(m_lean[ok_lean, 0], 411.0 / ks[ok_lean, 0])


def test_a_lean_worker_imports_neither_numpy_nor_fmpy(screw):
    spec = spec_on(screw, ("c_y",), ("y",), 0.2, 0.1)
    plan = lean_view(spec, read_fmu_info(screw)).plan
    code = ("import json, sys; from array import array\n"
            "from fmusa.fmi.lean import LeanFMU; from fmusa.runs.lean import run_rows\n"
            f"fmu = LeanFMU(json.loads({json.dumps(json.dumps(plan))}))\n"
            "b = run_rows(fmu, [0, 1], array('d', [8e5, 9e5]), (1.0,), (0.0,))\n"
            "assert not b.messages, b.messages\n"
            "print(json.dumps([len(b.data), sorted(m for m in ('numpy', 'fmpy', 'pandas') if m in sys.modules)]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert json.loads(out.stdout) == [2 * 3, []]
