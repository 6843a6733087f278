"""The search in rounds (search.parallel, fmusa.analysis.search.search_in_rounds): the sequential search's
answer, in fewer rounds of runs as the points per round rise.

First on the closed-form boundary of test_warm_start (exact lattice answers, the guard's warnings, the
warm start, one parameter), then on studies: the paper study on our FMU, the one-parameter spring study
(tests/fmus/me_spring) and the paper study on the stand-in FMU tests/fmus/slow_pullout (its closed form
recomputed here, independently of the C), which also resumes a round cut short.
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import pandas as pd
import pytest

from fmusa.analysis.roi import Region
from fmusa.analysis.search import nested_binary_search, search_in_rounds
from fmusa.api import parse_study
from fmusa.pipeline.sweep import run_study

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fmus.me_spring.build import build_spring_fmu  # noqa: E402
from fmus.slow_pullout.build import build_pullout_fmu  # noqa: E402
from test_warm_start import REGION, model  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PAPER_TEXT = (ROOT / "studies" / "paper.yaml").read_text(encoding="utf-8")
PAPER_C, PAPER_D, PAPER_D_HAND = 822067.2607421875, 381.4697265625, 488.28125


def _rounds_of(evaluate):
    """evaluate_many() over a one-point evaluate(), recording each round's size."""
    sizes: list[int] = []

    def many(points):
        sizes.append(len(points))
        return [evaluate(p) for p in points]
    return many, sizes


@pytest.mark.parametrize("notch", [False, True])
def test_rounds_give_the_sequential_answer_and_fall_as_workers_rise(notch):
    seq = nested_binary_search(model(notch), REGION, ["y"], 1e-3, 1e-3, 20)
    rounds = []
    for workers in (1, 2, 4, 16):
        ev = model(notch)
        many, sizes = _rounds_of(ev)
        par = search_in_rounds(many, REGION, ["y"], workers, 1e-3, 1e-3, 20)
        # the same lattice: the same answer at every level, the same stop and the same warnings
        assert par.optimum == seq.optimum
        assert [(lv.outer, lv.inner, lv.changed) for lv in par.levels] == \
               [(lv.outer, lv.inner, lv.changed) for lv in seq.levels]
        assert par.stop_reason == seq.stop_reason and par.binding == seq.binding
        # notch: every level below d = 5000 fails its guard (at points above the last cut's cell when the
        # guard ran with it, not exactly the sequential x * (1.5^(1/3), 1.5^(2/3), 1.5))
        assert [w.split(" but not at ")[0] for w in par.warnings] == \
               [w.split(" but not at ")[0] for w in seq.warnings]
        assert max(sizes) <= workers and par.rounds.rounds == len(sizes)
        assert par.evaluations == par.rounds.runs == len(ev.calls) == sum(sizes)
        assert par.rounds.sequential_runs == seq.evaluations      # what the sequential search took
        rounds.append(par.rounds.rounds)
    assert all(a > b for a, b in zip(rounds, rounds[1:])), rounds
    assert rounds[-1] <= 20 < seq.evaluations


def test_warm_start_in_rounds_guards_once():
    seq = nested_binary_search(model(True), REGION, ["y"], 1e-3, 1e-3, 20, warm_start=True)
    many, sizes = _rounds_of(model(True))
    par = search_in_rounds(many, REGION, ["y"], 8, warm_start=True)
    assert par.optimum["d"] == seq.optimum["d"]
    assert abs(par.optimum["c"] - seq.optimum["c"]) <= 1e-3 * seq.optimum["c"]
    assert len(par.warnings) == 1 and f"d = {par.optimum['d']:g}" in par.warnings[0]
    assert par.warm_start and max(sizes) <= 8


def test_one_parameter_in_rounds():
    region = Region("c", None, (390625.0, 9765625.0), None, "manual")
    seq = nested_binary_search(model(), region, ["y"], 1e-3)
    many, sizes = _rounds_of(model())
    par = search_in_rounds(many, region, ["y"], 4)
    assert par.optimum == seq.optimum and par.levels[0].outer is None and "one parameter" in par.stop_reason
    assert par.rounds.rounds == len(sizes) < seq.evaluations and par.rounds.sequential_runs == seq.evaluations
    many, _ = _rounds_of(model())
    none = search_in_rounds(many, Region("c", None, (1e5, 5e5), None, "manual"), ["y"], 4)
    assert none.optimum is None and "no feasible c" in none.stop_reason
    with pytest.raises(ValueError, match="at least 1 worker"):
        search_in_rounds(many, region, ["y"], 0)


def paper_study(parallel: str, fmu: Path | None = None, sleep_s: float | None = None, workers: int | None = None):
    """studies/paper.yaml with search.parallel set, optionally on another FMU (ScrewVertebra's names)."""
    text = PAPER_TEXT.replace("    parallel: false", f"    parallel: {parallel}")
    if fmu is not None:
        text = text.replace("fmu: default", f"fmu: {fmu.as_posix()}")
    if sleep_s is not None:
        text = text.replace("fixed:\n", f"fixed:\n  sleep_s: {sleep_s!r}\n", 1)
    if workers is not None:
        text = text.replace("  workers: null ", f"  workers: {workers} ")
    return parse_study(text, ROOT / "studies" / "paper.yaml")


def test_paper_study_in_rounds(tmp_path, fmu_path):
    """The whole paper study (grid, search, the paper's own region): the sequential optimum at 1, 2 and 16
    points per round, rounds falling to <= 20 at 16, runs <= 2 x the sequential 381."""
    from fmusa.api import run_study as run_with_extensions
    seq = run_with_extensions(paper_study("false"), tmp_path / "seq", figures=False, progress=False).summary
    assert (seq["rounds"], seq["runs"]) == (357, 381)
    total = []
    for w in (1, 2, 16):
        s = run_with_extensions(paper_study(str(w)), tmp_path / str(w), figures=False, progress=False).summary
        assert s["optimum"] == {"c": PAPER_C, "d": PAPER_D} == seq["optimum"]
        assert s["paper_roi_search"]["optimum"] == {"c": PAPER_C, "d": PAPER_D_HAND}
        for key in ("search", "paper_roi_search"):       # level by level the sequential answers and responses
            metrics = ("max_y", "mean_y", "max_v", "mean_v", "t_eq")     # (run ids and seconds differ)
            assert [(lv["outer"], lv["inner"], *(lv["response"][m] for m in metrics)) for lv in s[key]["levels"]] \
                == [(lv["outer"], lv["inner"], *(lv["response"][m] for m in metrics)) for lv in seq[key]["levels"]]
            par = s[key]["parallel"]
            assert par["workers"] == w and par["largest_round"] <= w
            assert par["sequential_rounds"] == seq[key]["evaluations"]      # 227 and 133
        assert s["stage_runs"]["search"]["rounds"] <= s["search"]["parallel"]["rounds"]
        assert s["rounds"] == sum(v["rounds"] for v in s["stage_runs"].values())
        total.append(s["rounds"])
    assert total[0] > total[1] > total[2] and total[2] <= 20, total
    assert s["runs"] <= 2 * seq["runs"]


@pytest.fixture(scope="module")
def pullout_fmu(tmp_path_factory) -> Path:
    return build_pullout_fmu(tmp_path_factory.mktemp("pullout"))


def closed_form(c: float, d: float, F: float = 411.0, tr: float = 10.0, T: float = 12.0,
                eps_v: float = 5e-8, eps_a: float = 5e-9) -> dict[str, float]:
    """The stand-in's pullout d y' + c y = F min(t / tr, 1), at T (see tests/fmus/slow_pullout/pullout.c)."""
    tau, A, ys = d / c, F / (c * tr), F / c
    q = -math.expm1(-tr / tau)
    y_r, v_r = A * (tr - tau * q), A * q
    e = math.exp(-(T - tr) / tau)
    y = ys - (ys - y_r) * e
    iy = A * (tr ** 2 / 2 - tau * tr + tau ** 2 * q) + ys * (T - tr) + (ys - y_r) * tau * math.expm1(-(T - tr) / tau)
    lim = min(eps_v, eps_a * tau)
    rest = tr + tau * math.log(v_r / lim) if v_r > lim else tr
    return {"max_y": y, "mean_y": iy / T, "max_v": v_r, "mean_v": y / T, "t_eq": rest if rest <= T else math.nan}


def test_two_parameter_study_on_a_test_fmu(pullout_fmu, tmp_path):
    """The paper study on the stand-in FMU (sleep 0): the closed form at every run, and the search in rounds
    (8 points per round on 2 workers, 4 on 2) gives the sequential optimum in fewer rounds."""
    seq = run_study(paper_study("false", pullout_fmu, 0.0, 2), tmp_path / "seq", progress=False)
    runs = pd.read_csv(tmp_path / "seq" / "runs.csv")
    assert (runs["status"] == "ok").all()
    for row in runs.sample(40, random_state=1).itertuples():
        ref = closed_form(row.c, row.d)
        for m in ("max_y", "mean_y", "max_v", "mean_v"):
            assert getattr(row, m) == pytest.approx(ref[m], rel=1e-9), (m, row.c, row.d)
        assert (math.isnan(ref["t_eq"]) and pd.isna(row.t_eq)) or row.t_eq == pytest.approx(ref["t_eq"], rel=1e-9)
    opt = seq.search.optimum
    # the feasible side of the closed form, within inner_rtol of its boundary: max y = y(T) <= eps_y
    ref = closed_form(opt["c"], opt["d"])
    assert ref["max_y"] <= 5e-4 and ref["max_v"] <= 5e-5 and not math.isnan(ref["t_eq"])
    below = closed_form(opt["c"] * (1 - 1e-3), opt["d"])
    assert below["max_y"] > 5e-4 or below["max_v"] > 5e-5
    rounds = []
    for w in (4, 8):
        res = run_study(paper_study(str(w), pullout_fmu, 0.0, 2), tmp_path / str(w), progress=False)
        assert abs(res.search.optimum["c"] - opt["c"]) <= 1e-3 * opt["c"]
        assert res.search.optimum["d"] == opt["d"]
        rounds.append(res.summary["stage_runs"]["search"]["rounds"])
    assert seq.summary["stage_runs"]["search"]["rounds"] > rounds[0] > rounds[1], rounds


def test_one_parameter_study_in_rounds(tmp_path):
    """The spring study of test_search_1d (one bisection of d): the sequential answer in fewer rounds."""
    from test_search_1d import GRID_D, D_STAR, study_text
    fmu = build_spring_fmu(tmp_path, "SpringCS", ("co-simulation",))
    found, rounds = [], []
    from fmusa.api import run_study as run_with_report
    for par in ("false", "1", "4"):
        stages = (f"  grid: {{values: {{d: {GRID_D}}}}}\n  roi:\n"
                  f"  search: {{inner: d, inner_rtol: 1.0e-3, parallel: {par}}}\n")
        study = parse_study(study_text(fmu, stages), tmp_path / f"o{par}.yaml")
        if par == "4":      # the report says what the rounds cost against the sequential search
            res = run_with_report(study, tmp_path / f"out{par}", progress=False)
            text = (tmp_path / f"out{par}" / "report.md").read_text(encoding="utf-8")
            par_s = res.summary["search"]["parallel"]
            assert (f"The search asked for {par_s['runs']} points in {par_s['rounds']} rounds of up to 4"
                    in text), text
            assert f"the sequential search asks for {par_s['sequential_rounds']} points, one per round" in text
        else:
            res = run_study(study, tmp_path / f"out{par}", progress=False)
        found.append(res.search.optimum["d"])
        rounds.append(res.summary["stage_runs"]["search"]["rounds"])
    assert D_STAR <= found[0] <= D_STAR * (1 + 1e-3)
    assert found[1] == found[2] == found[0]
    assert rounds[0] >= rounds[1] > rounds[2], rounds


def test_a_round_cut_short_resumes(pullout_fmu, tmp_path):
    """runs.csv cut in the middle of a round (as a crash leaves it: whole batches, then nothing): --resume
    runs only what is missing and ends on the same answer, in the same rounds."""
    study = paper_study("8", pullout_fmu, 0.0, 2)
    full = run_study(study, tmp_path / "full", progress=False)
    lines = (tmp_path / "full" / "runs.csv").read_bytes().split(b"\r\n")
    n = full.summary["runs"]
    keep = 25 + 8 * 3 + 5        # the grid, three rounds of 8, and 5 runs of the fourth
    out = tmp_path / "cut"
    out.mkdir()
    (out / "runs.csv").write_bytes(b"\r\n".join(lines[:1 + keep]) + b"\r\n")
    (out / "runs.csv.study.json").write_bytes((tmp_path / "full" / "runs.csv.study.json").read_bytes())
    again = run_study(study, out, resume=True, progress=False)
    assert again.search.optimum == full.search.optimum
    assert again.summary["simulated_this_session"] == n - keep
    assert again.summary["search"]["parallel"]["rounds"] == full.summary["search"]["parallel"]["rounds"]
    assert again.summary["runs"] == n


@pytest.mark.parametrize("value, expected", [(None, "auto"), ("auto", "auto"), ("true", "auto"),
                                             ("false", False), ("16", 16)])
def test_parallel_is_read(value, expected, tmp_path):
    text = PAPER_TEXT.replace("    parallel: false\n", "" if value is None else f"    parallel: {value}\n")
    assert parse_study(text, tmp_path / "p.yaml").stages["search"].parallel == expected


@pytest.mark.parametrize("value, message", [
    ("0", "key 'parallel' in 'stages.search' must be ≥ 1 points per round, got 0"),
    ("fast", "key 'parallel' in 'stages.search' must be auto, false or an integer, got the string 'fast'"),
    ("2.5", "must be auto, false or an integer, got the number 2.5")])
def test_a_bad_parallel_names_its_line_and_the_fix(value, message, tmp_path):
    from fmusa.study.schema import StudyError
    text = PAPER_TEXT.replace("    parallel: false", f"    parallel: {value}")
    with pytest.raises(StudyError) as exc:
        parse_study(text, tmp_path / "p.yaml")
    msg = str(exc.value)
    line = next(i for i, ln in enumerate(text.splitlines(), 1) if ln.startswith("    parallel:"))
    assert msg.startswith(f"{tmp_path / 'p.yaml'}:{line}: ") and message in msg and "e.g. parallel: auto" in msg, msg


def test_random_boundaries_give_the_sequential_answer():
    """Random regions, tolerances and boundaries (flat, growing, a step, wavy in d): for a monotone boundary
    the same optimum as the sequential search at 1, 3 and 16 points per round; with 10 % of the verdicts
    flipped at random (not monotone) the search still ends, within the points it may ask for."""
    rng = __import__("random").Random(3)
    for case in range(60):
        lo = 10 ** rng.uniform(-2, 5)
        hi = lo * 10 ** rng.uniform(0.01, 4)
        z_top, b0 = 10 ** rng.uniform(-1, 5), 10 ** rng.uniform(math.log10(lo) - 0.5, math.log10(hi) + 0.5)
        kind, monotone, rtol = rng.choice(["flat", "grow", "step", "wave"]), case % 3 != 0, rng.choice([1e-3, 1e-2])
        one = case % 5 == 0

        def evaluate(p, kind=kind, monotone=monotone, z_top=z_top, b0=b0, case=case):
            c, z = p["c"], p.get("d", 0.0)
            b = {"flat": b0, "grow": b0 * (1 + (z / z_top) ** 2), "step": b0 * (2 if z > z_top / 8 else 1),
                 "wave": b0 * (1 + 0.5 * math.sin(7.3 * z))}[kind]
            ok = c >= b
            if not monotone:
                ok = ok != (__import__("random").Random(hash((c, z, case))).random() < 0.1)
            return {**p, "y": 1.0 / c, "ok_size": ok, "feasible": ok, "status": "ok"}

        region = Region("c", None if one else "d", (lo, hi), None if one else (0.0, z_top), "manual")
        seq = nested_binary_search(evaluate, region, ["y"], rtol, 1e-3, 20)
        for workers in (1, 3, 16):
            many, sizes = _rounds_of(evaluate)
            par = search_in_rounds(many, region, ["y"], workers, rtol, 1e-3, 20)
            assert max(sizes) <= workers
            if monotone:
                assert par.optimum == seq.optimum, (case, workers)
                assert par.stop_reason == seq.stop_reason and par.rounds.sequential_runs == seq.evaluations
