"""The sensitivity stage's study keys: sample sizes refused below the smallest useful one, off powers of two
and over the cap (before anything is allocated), the distributions and the pce options, each with file:line,
the key and the fix."""
from __future__ import annotations

import time
import tracemalloc
from pathlib import Path

import pytest

from fmusa.study.loader import parse_study
from fmusa.study.schema import MAX_SENSITIVITY_RUNS, StudyError

ROOT = Path(__file__).resolve().parents[1]
SIX_TEXT = (ROOT / "studies" / "six_dof.yaml").read_text()
BAD = "studies/bad.yaml"
N_LINE = "    n: 1024 "
M_LINE = "      m:       {variable: m,       bounds: [0.000232, 0.000348], distribution: uniform, unit: kg}"


def _edit(old: str, new: str) -> str:
    assert old in SIX_TEXT, old
    return SIX_TEXT.replace(old, new, 1)


def _line_of(text: str, marker: str) -> int:
    return next(i for i, line in enumerate(text.splitlines(), 1) if marker in line)


def _fails(text: str, marker: str, *words: str) -> str:
    with pytest.raises(StudyError) as info:
        parse_study(text, BAD)
    msg = str(info.value)
    assert msg.startswith(f"{BAD}:{_line_of(text, marker)}: "), msg
    for w in words:
        assert w in msg, f"{w!r} not in {msg!r}"
    return msg


CASES = [
    # n: 1 would give an Ishigami S1 of 3.08 ± 8.7e-16: refused, naming the smallest useful n for 16 inputs
    ("n of one", N_LINE, "    n: 1 ", "n: 1 ", ["key 'n' in 'stages.sensitivity'", "too small for 16 inputs",
                                                "smallest useful n is 64 (1152 runs)"]),
    ("n below the smallest", N_LINE, "    n: 32 ", "n: 32", ["smallest useful n is 64"]),
    ("n not a power of two", N_LINE, "    n: 1000 ", "n: 1000", ["not a power of 2", "use n: 512 or n: 1024"]),
    ("n of 1e9", N_LINE, "    n: 1000000000 ", "n: 1000000000",
     ["18,000,000,000 Sobol runs", "cap of 1,000,000", "FMUSA_MAX_SENSITIVITY_RUNS"]),
    ("n of 5e7", N_LINE, "    n: 50000000 ", "n: 50000000", ["cap of 1,000,000", "method pce"]),
    ("morris trajectories too few", "  morris_trajectories: 20", "  morris_trajectories: 2", "morris_trajectories: 2",
     ["key 'morris_trajectories' in 'stages.sensitivity' must be ≥ 4"]),
    ("morris over the cap", "  morris_trajectories: 20", "  morris_trajectories: 100000", "morris_trajectories:",
     ["1,700,000 runs", "cap of 1,000,000", "FMUSA_MAX_SENSITIVITY_RUNS"]),
    ("normal with bounds", M_LINE, "      m: {variable: m, bounds: [1, 2], distribution: normal, mean: 3.0e-4, std: 2.0e-5}",
     "m: {variable: m", ["key 'bounds' in 'stages.sensitivity.parameters.m'", "has no bounds",
                         "distribution: truncnormal"]),
    ("normal without std", M_LINE, "      m: {variable: m, distribution: normal, mean: 3.0e-4}", "m: {variable: m",
     ["key 'std' is missing in 'stages.sensitivity.parameters.m'"]),
    ("lognormal mean not positive", M_LINE, "      m: {variable: m, distribution: lognormal, mean: -1, std: 1}",
     "m: {variable: m", ["key 'mean' in 'stages.sensitivity.parameters.m' must be > 0"]),
    ("truncnormal without bounds", M_LINE, "      m: {variable: m, distribution: truncnormal, mean: 3.0e-4, std: 2.0e-5}",
     "m: {variable: m", ["key 'bounds' is missing in 'stages.sensitivity.parameters.m'"]),
    ("truncnormal bounds in the far tail", M_LINE,
     "      m: {variable: m, distribution: truncnormal, mean: 0, std: 1, bounds: [50, 60]}", "m: {variable: m",
     ["holds almost none of the normal"]),
    ("mean for a uniform input", M_LINE, "      m: {variable: m, bounds: [1, 2], mean: 1.5}", "m: {variable: m",
     ["key 'mean' in 'stages.sensitivity.parameters.m' is for a normal"]),
    ("pce budget below a batch", N_LINE, "    n: 1024\n    pce: {max_runs: 40}", "pce:",
     ["key 'max_runs' in 'stages.sensitivity.pce'", "less than one batch (64 runs)"]),
    ("pce target not a share", N_LINE, "    n: 1024\n    pce: {target_error: 2}", "pce:",
     ["key 'target_error' in 'stages.sensitivity.pce' must be below 1"]),
    ("pce unknown design", N_LINE, "    n: 1024\n    pce: {design: halton}", "pce:",
     ["key 'design' in 'stages.sensitivity.pce'", "unknown design 'halton'", "allowed: sobol, lhs"]),
    ("pce over the cap", N_LINE, "    n: 1024\n    pce: {max_runs: 2000000}", "pce:",
     ["cap of 1,000,000", "FMUSA_MAX_SENSITIVITY_RUNS"]),
]


@pytest.mark.parametrize("old,new,marker,words", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_bad_sensitivity_keys_name_file_line_key_and_fix(old, new, marker, words):
    _fails(_edit(old, new), marker, *words)


def test_huge_n_is_refused_before_any_allocation():
    text = _edit(N_LINE, "    n: 1000000000 ")
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(StudyError):
            parse_study(text, BAD)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert time.perf_counter() - t0 < 5 and peak < 50e6, peak


def test_the_cap_is_raised_by_the_environment(monkeypatch):
    text = _edit(N_LINE, "    n: 65536 ")         # 65536 · 18 = 1,179,648 runs
    with pytest.raises(StudyError, match="cap of 1,000,000"):
        parse_study(text, BAD)
    monkeypatch.setenv("FMUSA_MAX_SENSITIVITY_RUNS", "2000000")
    assert parse_study(text, BAD).stages["sensitivity"].n == 65536
    assert MAX_SENSITIVITY_RUNS == 1_000_000


def test_distributions_and_pce_options_load():
    text = _edit(M_LINE, "      m: {variable: m, distribution: normal, mean: 2.9e-4, std: 2.0e-5, unit: kg}")
    text = text.replace("      cg_y:    {variable: cg_y,    bounds: [-0.008436, -0.005624], distribution: uniform, unit: m}",
                        "      cg_y: {variable: cg_y, distribution: truncnormal, mean: -0.00703, std: 0.001, "
                        "bounds: [-0.008436, -0.005624]}")
    text = text.replace("      L_screw: {variable: L_screw, bounds: [0.0136, 0.0204],     distribution: uniform, unit: m}",
                        "      L_screw: {variable: L_screw, distribution: lognormal, mean: 0.017, std: 0.001}")
    text = text.replace("methods: [morris, sobol]", "methods: [pce]").replace(
        N_LINE, "    n: 1024\n    pce: {target_error: 0.002, max_runs: 300, batch: 50, design: lhs}")
    st = parse_study(text, BAD).stages["sensitivity"]
    m, cg, L = st.parameters["m"], st.parameters["cg_y"], st.parameters["L_screw"]
    assert (m.distribution, m.mean, m.std, m.bounds) == ("normal", 2.9e-4, 2.0e-5, None)
    assert cg.distribution == "truncnormal" and cg.bounds == (-0.008436, -0.005624)
    assert L.distribution == "lognormal" and L.mean == 0.017
    assert st.methods == ["pce"]
    assert (st.pce.target_error, st.pce.max_runs, st.pce.batch, st.pce.design) == (0.002, 300, 50, "lhs")
    assert st.pce.batch_size(16) == 50


def test_huge_n_through_the_python_api_is_refused_before_any_allocation(fmu_path, tmp_path):
    import dataclasses
    from types import SimpleNamespace

    from fmusa.errors import UsageError
    from fmusa.pipeline.sensitivity import run_sensitivity
    study = dataclasses.replace(parse_study(SIX_TEXT, ROOT / "studies" / "six_dof.yaml"), fmu=fmu_path)
    runner = SimpleNamespace(evaluator=SimpleNamespace(workers=1, scheduler=None), simulated=0)
    for n in (10 ** 9, 5 * 10 ** 7):
        stage = dataclasses.replace(study.stages["sensitivity"], methods=["sobol"], n=n)
        tracemalloc.start()
        try:
            with pytest.raises(UsageError, match="FMUSA_MAX_SENSITIVITY_RUNS"):
                run_sensitivity(study, stage, tmp_path / str(n), runner, progress=False, resume=False,
                                accuracy_samples=0)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 50e6 and runner.simulated == 0
