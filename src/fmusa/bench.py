"""Benchmark one FMU evaluation: ``python -m fmusa.bench --out out/bench/bench.json``.

Measures the paper's 411 N pullout at the paper's optimum (the FMU defaults c = 823224 N/m,
d = 488 N·s/m, t_ramp = 10 s, stop at 12 s) as a study runs it: the instance is reused (reset, set
parameters, setupExperiment, initialisation, ONE doStep 0 → 12 s, read the monitors y_max, v_y_max,
t_eq). Compares with ``fmpy.simulate_fmu`` on the same FMU file, which extracts, loads and
instantiates it on every call. Keys are merged into an existing JSON file.

With ``--sobol-runs`` (default 10000; 0 skips it) it also measures a Sobol study of the 6-DOF load case
(studies/six_dof.yaml: its 16 sensitivity parameters, N chosen so that N·(k + 2) ≈ the run count, no
second-order indices) run by :func:`fmusa.sensitivity.run_sensitivity` through the Evaluator's process
pool on all cores, with its RunStore and the SALib analysis: ``sobol_runs``, ``sobol_wall_s``,
``sobol_runs_per_s`` and ``sobol_peak_rss_mb`` (parent: VmHWM, largest worker: ``ru_maxrss``), the same for
``--sobol-small-runs`` (2500) to show how memory scales with the number of runs (each in a fresh
process, so that the peaks are its own), and ``sobol_profile``: where a run's time goes.

``paper_study_rounds`` counts the rounds (batches of runs waited for one after another) and runs of the paper
study with ``search.parallel`` at 1, 2 and 16 points per round against the sequential search;
``paper_study_wall_s_slow_fmu`` times it on a stand-in FMU that sleeps 0.5 s per run (16 local workers),
next to ``paper_study_wall_s_slow_fmu_sequential`` (``--slow-fmu-workers``, ``--no-slow-fmu-sequential``).

With ``--pipeline-runs`` (default 40000; 0 skips it) it measures the pipeline's own cost on cheap runs (the
6-DOF Sobol study with the screw at rest: FMU runs of ~0.02 ms): ``pipeline_overhead_ms_per_run`` (CPU per
run around the FMU, worker and parent), ``pipeline_worker_python_ms_per_run``,
``pipeline_parent_cpu_ms_per_run`` and ``pipeline_parent_rss_kb_per_run`` (peak RSS growth per run between
studies of a quarter of the runs and all of them), with the load average at the time.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from fmusa.fmi.runner import FMURunner
from fmusa.fmi.plans import RunPlan
from fmusa.fmi.info import default_fmu_path

MONITORS = ["y_max", "v_y_max", "t_eq"]
#: Paper optimum and load case, set explicitly (they equal the FMU defaults).
PARAMS = {"c_y": 823224.0, "d_y": 488.0, "F_max": 411.0, "t_ramp": 10.0}
STOP_TIME = 12.0


def _percentile(xs, q):
    return float(np.percentile(np.asarray(xs), q))


def bench_runner(fmu_path: Path, runs: int, warmup: int) -> tuple[list[float], dict[str, float]]:
    """A study's inner loop: one prepared RunPlan, instance reused (reset, set, initialise, one
    doStep, read)."""
    times = []
    with FMURunner(fmu_path) as fmu:
        varied = list(PARAMS)
        plan = RunPlan(fmu, varied, {}, MONITORS, STOP_TIME, None)
        values = [PARAMS[k] for k in varied]
        for _ in range(warmup):
            row = plan(values)[-1]
        for _ in range(runs):
            t0 = time.perf_counter()
            row = plan(values)[-1]
            times.append((time.perf_counter() - t0) * 1e3)
    return times, dict(zip(MONITORS, map(float, row)))


def bench_simulate_fmu(fmu_path: Path, runs: int) -> tuple[list[float], dict[str, float]]:
    import fmpy

    times = []
    kwargs = dict(start_values=dict(PARAMS), stop_time=STOP_TIME, output=MONITORS,
                  output_interval=STOP_TIME)
    fmpy.simulate_fmu(str(fmu_path), **kwargs)  # warm-up (imports, page cache)
    for _ in range(runs):
        t0 = time.perf_counter()
        res = fmpy.simulate_fmu(str(fmu_path), **kwargs)
        times.append((time.perf_counter() - t0) * 1e3)
    final = {name: float(res[name][-1]) for name in MONITORS}
    return times, final


def _rel_diff(a: float, b: float) -> float:
    scale = max(abs(a), abs(b))
    return 0.0 if scale == 0 else abs(a - b) / scale


# ---------------------------------------------------------------------------- what one run cannot beat
#: doStep over an interval so short that there is nothing to integrate: the cost of calling the FMU at all.
FLOOR_STOP = 1e-9
REPO = Path(__file__).resolve().parents[2]


def _load() -> float | None:
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else None


def bench_fmu_limits(fmu_path: Path, runs: int = 2000, warmup: int = 50) -> dict:
    """The axial pullout against its floor, interleaved so that both see the same machine load:
    ``fmu_run_ms_median`` of a whole run (reset, set, initialise, one doStep 0 -> 12 s, read the monitors)
    against ``fmu_floor_ms``, the same call sequence with a doStep of ``FLOOR_STOP`` s; the doStep alone
    (``axial_dostep_us_median``) against the floor's doStep (``floor_dostep_us_median``)."""
    values = [PARAMS[k] for k in PARAMS]
    run, floor, step, floor_step = [], [], [], []
    load_before = _load()
    with FMURunner(fmu_path) as fmu:
        plans = {stop: RunPlan(fmu, list(PARAMS), {}, MONITORS, stop, None) for stop in (STOP_TIME, FLOOR_STOP)}
        for _ in range(warmup):
            for plan in plans.values():
                plan(values)
        for _ in range(runs):
            for stop, acc in ((STOP_TIME, run), (FLOOR_STOP, floor)):
                t0 = time.perf_counter()
                plans[stop](values)
                acc.append(time.perf_counter() - t0)
        for _ in range(runs):
            for stop, acc in ((STOP_TIME, step), (FLOOR_STOP, floor_step)):
                plan = plans[stop]
                plan.start(values)
                s = plan.runner.instance
                t0 = time.perf_counter()
                s.fmi2DoStep(s.component, 0.0, stop, 1)
                acc.append(time.perf_counter() - t0)
                plan.read()
                plan.runner.mark_done()
    return {"fmu_run_ms_median_interleaved": statistics.median(run) * 1e3,
            "fmu_floor_ms": statistics.median(floor) * 1e3,
            "fmu_floor_stop_s": FLOOR_STOP,
            "axial_dostep_us_median": statistics.median(step) * 1e6,
            "floor_dostep_us_median": statistics.median(floor_step) * 1e6,
            "limits_runs": runs,
            "limits_loadavg_1min": [load_before, _load()]}


def bench_closed_form_c(repeats: int = 400) -> dict:
    """The axial pullout in C without fmpy (fmu/bench/closed_form.c, compiled here with the FMU's flags):
    ``closed_form_us_median``, the closed-form solution (matrix exponential per load piece, extrema and
    rest by root finding) of the paper's case, and ``model_c_run_us_median``, the FMU's model layer
    (parameters, initialisation, one step to 12 s, outputs) called directly."""
    import shutil

    src, inc = REPO / "fmu" / "bench" / "closed_form.c", REPO / "build" / "fmu" / "sources"
    if not (src.exists() and (inc / "variables.h").exists() and (inc / "sv_generated.c").exists()
            and shutil.which("gcc")):
        return {"closed_form_note": "not measured: needs gcc, fmu/bench/closed_form.c and `make fmu`"}
    with tempfile.TemporaryDirectory(prefix="fmusa-bench-cf-") as tmp:
        exe = Path(tmp) / "closed_form"
        subprocess.run(["gcc", "-std=c99", "-O3", "-D_POSIX_C_SOURCE=199309L", f"-I{inc}", "-o", str(exe),
                        str(src), str(REPO / "fmu" / "model.c"), str(inc / "sv_generated.c"), "-lm"],
                       check=True, capture_output=True)
        load = _load()
        proc = subprocess.run([str(exe), str(PARAMS["c_y"]), str(PARAMS["d_y"]), str(PARAMS["F_max"]),
                               str(PARAMS["t_ramp"]), str(STOP_TIME), str(repeats)],
                              check=True, capture_output=True, text=True)
    res = json.loads(proc.stdout)
    return {"closed_form_us_median": res["closed_form_us_median"], "closed_form_us_min": res["closed_form_us_min"],
            "model_c_run_us_median": res["model_run_us_median"], "model_c_run_us_min": res["model_run_us_min"],
            "closed_form_monitors": dict(zip(MONITORS, res["closed_form_monitors"])),
            "closed_form_loadavg_1min": [load, _load()]}


def _six_dof_samples(samples: int, fmu_path: Path | None, seed: int):
    """The 6-DOF study's first ``samples`` Sobol points (physical values), the in-process RunPlan that runs
    them, and a reader of the solver's internal step count (``n_steps``) after a run."""
    import dataclasses

    from fmpy.fmi2 import fmi2Integer, fmi2ValueReference

    from fmusa.analysis.sensitivity import draw_samples, to_physical
    from fmusa.pipeline.sensitivity import sensitivity_spec
    from fmusa.runs.spec import plan_for

    study, stage = _six_dof()
    stage = dataclasses.replace(stage, seed=seed)
    spec = sensitivity_spec(study, stage, fmu_path=fmu_path)
    P = to_physical(stage, draw_samples(stage, "sobol", n=max(1, samples // (len(stage.parameters) + 2) + 1)))
    plan = plan_for(spec)
    inst = plan.runner.instance
    vr = (fmi2ValueReference * 1)(plan.runner.variables["n_steps"].valueReference)
    val = (fmi2Integer * 1)()

    def n_steps() -> int:
        inst.fmi2GetInteger(inst.component, vr, 1, val)
        return int(val[0])

    return spec, P[:samples], plan, n_steps


def bench_six_dof_runs(samples: int = 200, fmu_path: Path | None = None, seed: int = 1) -> dict:
    """Whole runs (reset, set, initialise, one doStep, read) of the 6-DOF study at the Sobol samples of
    :func:`profile_six_dof` (same seed, same points): ``six_dof_run_ms_median`` and the solver's internal
    steps ``six_dof_steps_median``."""
    spec, P, plan, n_steps = _six_dof_samples(samples, fmu_path, seed)
    plan(list(P[0]))
    load_before = _load()
    times, steps = [], []
    for row in P:
        t0 = time.perf_counter()
        plan(list(row))
        times.append(time.perf_counter() - t0)
        steps.append(n_steps())
    return {"six_dof_run_ms_median": statistics.median(times) * 1e3,
            "six_dof_run_ms_mean": float(np.mean(times) * 1e3),
            "six_dof_run_ms_p90": _percentile(times, 90) * 1e3,
            "six_dof_steps_median": float(np.median(steps)),
            "six_dof_steps_mean": float(np.mean(steps)),
            "six_dof_samples": len(P),
            "six_dof_loadavg_1min": [load_before, _load()]}


def limits_note(res: dict) -> str:
    """Each figure next to its limit, as a ratio."""
    parts = []
    if "fmu_floor_ms" in res:
        parts.append(f"axial run {res['fmu_run_ms_median_interleaved']:.4f} ms = "
                     f"{res['fmu_run_ms_median_interleaved'] / res['fmu_floor_ms']:.2f} x the floor "
                     f"{res['fmu_floor_ms']:.4f} ms (target <= 1.5)")
        parts.append(f"axial doStep {res['axial_dostep_us_median']:.2f} us = "
                     f"{res['axial_dostep_us_median'] / res['floor_dostep_us_median']:.2f} x the floor's doStep "
                     f"{res['floor_dostep_us_median']:.2f} us (target <= 20 us)")
    if "closed_form_us_median" in res:
        parts.append(f"in C: model run {res['model_c_run_us_median']:.2f} us = "
                     f"{res['model_c_run_us_median'] / res['closed_form_us_median']:.2f} x the closed form "
                     f"{res['closed_form_us_median']:.2f} us")
    if "six_dof_run_ms_median" in res and "fmu_floor_ms" in res:
        parts.append(f"6-DOF run {res['six_dof_run_ms_median']:.4f} ms = "
                     f"{res['six_dof_run_ms_median'] / res['fmu_floor_ms']:.2f} x the floor "
                     f"({res['six_dof_steps_median']:.0f} internal steps, median)")
    if "paper_study_wall_s" in res:
        part = f"paper study {res['paper_study_wall_s']:.3f} s (target <= 0.1 s)"
        if "fmu_floor_ms" in res and res.get("paper_study_runs"):
            floor = res["paper_study_runs"] * res["fmu_floor_ms"] * 1e-3
            part += (f" = {res['paper_study_wall_s'] / floor:.1f} x its {res['paper_study_runs']} runs at the floor "
                     f"({floor:.4f} s)")
        parts.append(part)
    if "sobol_runs_per_s" in res and "fmu_floor_ms" in res:
        cores = (res.get("sobol_detail") or {}).get("workers") or os.cpu_count() or 1
        ceiling = cores / (res["fmu_floor_ms"] * 1e-3)
        parts.append(f"Sobol {res['sobol_runs_per_s']:.0f} runs/s (target >= {SOBOL_TARGET_RUNS_PER_S:.0f}) = "
                     f"{res['sobol_runs_per_s'] / ceiling:.3f} x the floor's {ceiling:.0f} runs/s on {cores} cores"
                     + (f", {res['sobol_runs_per_s'] / res['pipeline_runs_per_s_cheap']:.2f} x the pipeline's "
                        f"{res['pipeline_runs_per_s_cheap']:.0f} runs/s with an FMU at rest"
                        if res.get("pipeline_runs_per_s_cheap") else ""))
    return "; ".join(parts)


# ---------------------------------------------------------------------------- Sobol study throughput
SIX_DOF = Path(__file__).resolve().parents[2] / "studies" / "six_dof.yaml"
#: What the Sobol study of the 6-DOF case should reach on this 2-core machine.
SOBOL_TARGET_RUNS_PER_S = 2000.0


def _six_dof(study_path: Path | None = None):
    from fmusa.study.loader import load_study
    study = load_study(study_path or SIX_DOF)
    return study, study.stages["sensitivity"]


def _rusage(who: str):
    """``resource.getrusage`` (POSIX), or None where there is no ``resource`` module (Windows)."""
    try:
        import resource
    except ImportError:
        return None
    return resource.getrusage(getattr(resource, who))


def _maxrss_mb(ru) -> float:
    """``ru_maxrss`` in MB: kilobytes on Linux, bytes on macOS."""
    return ru.ru_maxrss / (1024 * 1024 if sys.platform == "darwin" else 1024)


def _peak_rss_mb() -> float:
    """This process's peak resident memory: on Linux VmHWM, which execve resets (``ru_maxrss`` keeps the
    peak of the process that started this one, e.g. the whole benchmark's); elsewhere ``ru_maxrss``
    (macOS) or psutil's peak working set (Windows)."""
    try:
        for line in Path("/proc/self/status").read_text(encoding="utf-8").splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    ru = _rusage("RUSAGE_SELF")
    if ru is not None:
        return _maxrss_mb(ru)
    import psutil
    mem = psutil.Process().memory_info()
    return getattr(mem, "peak_wset", mem.rss) / (1024 * 1024)


def _children_peak_rss_mb() -> float | None:
    """The largest peak resident memory of this process's ended children (POSIX ``RUSAGE_CHILDREN``), or
    None where the system does not keep it (Windows)."""
    ru = _rusage("RUSAGE_CHILDREN")
    return None if ru is None else _maxrss_mb(ru)


def _mb_text(mb: float | None) -> str:
    return "n/a (not kept on this system)" if mb is None else f"{mb:.0f} MB"


def _cpu_s() -> tuple[float, float]:
    """(CPU seconds of this process, of its ended children): resource on POSIX, psutil elsewhere."""
    me, kids = _rusage("RUSAGE_SELF"), _rusage("RUSAGE_CHILDREN")
    if me is not None and kids is not None:
        return me.ru_utime + me.ru_stime, kids.ru_utime + kids.ru_stime
    import psutil
    t = psutil.Process().cpu_times()
    return t.user + t.system, getattr(t, "children_user", 0.0) + getattr(t, "children_system", 0.0)


def cheap_six_dof(study):
    """The 6-DOF study with the screw at rest (no pull, no lateral load): the same 16 parameters, 7
    metrics, RunStore and pool, but an FMU run of ~0.02 ms, so the pipeline's own cost shows."""
    import dataclasses
    return dataclasses.replace(study, fixed={**study.fixed, "F_max": 0.0},
                               scenario=dataclasses.replace(study.scenario, inputs={}))


#: The recorded Saltelli reference of the 6-DOF study's total indices (N = 4096: 73,728 runs, written by
#: :func:`six_dof_saltelli_reference`); the polynomial chaos is held to it.
SALTELLI_REFERENCE = Path(__file__).resolve().parents[2] / "tests" / "data" / "six_dof_saltelli_4096.json"
#: What the polynomial chaos must do on the 6-DOF study: max |ΔST| against the reference, in at most these runs.
PCE_MAX_DST, PCE_MAX_RUNS = 0.02, 400


def six_dof_saltelli_reference(n: int = 4096, workers: int | None = None, fmu: Path | None = None,
                               out: Path = SALTELLI_REFERENCE) -> dict:
    """Saltelli's indices of the 6-DOF study at base sample ``n`` (n·18 runs; N = 4096 takes minutes on two
    cores), written to ``out``: the reference :func:`bench_pce_six_dof` compares with."""
    import dataclasses
    from types import SimpleNamespace

    from fmusa.pipeline.sensitivity import run_sensitivity

    study, stage = _six_dof()
    if fmu:
        study = dataclasses.replace(study, fmu=Path(fmu))
    stage = dataclasses.replace(stage, methods=["sobol"], n=n)
    runner = SimpleNamespace(evaluator=SimpleNamespace(workers=workers or os.cpu_count(), scheduler=None), simulated=0)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="fmusa-bench-saltelli-") as tmp:
        res = run_sensitivity(study, stage, Path(tmp), runner, progress=False, resume=False, accuracy_samples=0)
    s = res["summary"]
    ref = {"n": n, "runs": int(s["runs"]), "failed": int(s["failed"]), "rtol": study.fixed.get("rtol"),
           "sobol": s["sobol"], "wall_s": time.perf_counter() - t0}
    Path(out).write_text(json.dumps(ref, indent=1) + "\n", encoding="utf-8")
    return ref


def bench_pce_six_dof(max_runs: int = PCE_MAX_RUNS, workers: int | None = None, fmu: Path | None = None,
                      reference: Path = SALTELLI_REFERENCE) -> dict:
    """The polynomial chaos method on the 6-DOF study (all 16 inputs, all 7 outputs, budget ``max_runs``,
    target 1e-3, rounds of 100 runs) against the recorded Saltelli reference: the runs it used, max |ΔST|
    over every output and input (target ≤ PCE_MAX_DST), where it is, and the reference's own 95 %
    half-width there."""
    import dataclasses
    from types import SimpleNamespace

    from fmusa.pipeline.sensitivity import run_sensitivity
    from fmusa.study.schema import PCEOptions

    ref = json.loads(Path(reference).read_text(encoding="utf-8"))
    study, stage = _six_dof()
    if fmu:
        study = dataclasses.replace(study, fmu=Path(fmu))
    stage = dataclasses.replace(stage, methods=["pce"], pce=PCEOptions(max_runs=max_runs, target_error=1e-3, batch=100))
    runner = SimpleNamespace(evaluator=SimpleNamespace(workers=workers or os.cpu_count(), scheduler=None), simulated=0)
    load_before = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    cpu0, t0 = time.process_time(), time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="fmusa-bench-pce-") as tmp:
        res = run_sensitivity(study, stage, Path(tmp), runner, progress=False, resume=False, accuracy_samples=0)
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    s = res["summary"]
    val = s["pce_validation"]
    worst, where, per_metric = 0.0, "", {}
    for metric, table in s["pce"].items():
        d, p = max((abs(table[p]["ST"] - ref["sobol"][metric][p]["ST"]), p) for p in table)
        per_metric[metric] = {"max_abs_dST": d, "at": p, "validation_error": val["metrics"][metric]["loo_error"],
                              "trusted": val["metrics"][metric]["trusted"], "degree": val["metrics"][metric]["degree"],
                              "reference_ST_conf": ref["sobol"][metric][p]["ST_conf"]}
        if d > worst:
            worst, where = d, f"{metric} / {p}"
    return {"pce_six_dof_runs": val["runs"], "pce_six_dof_max_abs_dST": worst, "pce_six_dof_worst": where,
            "pce_six_dof_target": {"max_abs_dST": PCE_MAX_DST, "runs": PCE_MAX_RUNS},
            "pce_six_dof_target_met": bool(worst <= PCE_MAX_DST and val["runs"] <= PCE_MAX_RUNS),
            "pce_six_dof_per_metric": per_metric, "pce_six_dof_reached": val["reached"],
            "pce_six_dof_rounds": [(r["runs"], r["worst"]) for r in val["rounds"]],
            "pce_six_dof_wall_s": wall, "pce_six_dof_parent_cpu_s": cpu,
            "pce_six_dof_reference": {"n": ref["n"], "runs": ref["runs"],
                                      "max_ST_conf": max(d["ST_conf"] for t in ref["sobol"].values() for d in t.values())},
            "pce_six_dof_loadavg_1min": [load_before, os.getloadavg()[0] if hasattr(os, "getloadavg") else None]}


def sobol_child(runs: int, workers: int, study_path: str | None = None, fmu: str | None = None,
                cheap: bool = False) -> dict:
    """One Sobol study of about ``runs`` runs, in THIS process (call it in a fresh one): wall time,
    throughput and peak resident memory of this process and of its largest worker. ``cheap``: the screw
    at rest (:func:`cheap_six_dof`), to measure the pipeline rather than the FMU."""
    import dataclasses
    from types import SimpleNamespace

    from fmusa.pipeline.sensitivity import run_sensitivity

    study, stage = _six_dof(Path(study_path) if study_path else None)
    if fmu:
        study = dataclasses.replace(study, fmu=Path(fmu))
    if cheap:
        study = cheap_six_dof(study)
    k = len(stage.parameters)
    n = max(1, round(runs / (k + 2)))
    stage = dataclasses.replace(stage, methods=["sobol"], n=n)
    runner = SimpleNamespace(evaluator=SimpleNamespace(workers=workers, scheduler=None), simulated=0)
    import SALib.analyze.sobol  # noqa: F401 - imported before the clocks start: a one-off cost, not per run
    import SALib.sample.sobol  # noqa: F401
    rss_before = _peak_rss_mb()
    load_before = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    cpu_before = _cpu_s()[0]
    with tempfile.TemporaryDirectory(prefix="fmusa-bench-sobol-") as tmp:
        t0 = time.perf_counter()
        res = run_sensitivity(study, stage, Path(tmp), runner, progress=False, resume=False, accuracy_samples=0)
        wall = time.perf_counter() - t0
        rss_study = _peak_rss_mb()         # the study's peak, before the benchmark reads runs.csv back
        import pandas as pd
        secs = pd.read_csv(Path(tmp) / "sensitivity_runs.csv", usecols=["seconds"], encoding="utf-8")["seconds"].to_numpy()
    s = res["summary"]
    ev = s["eval_wall_s"]
    cpu_me, cpu_workers = _cpu_s()
    cpu_parent = cpu_me - cpu_before
    return {
        "runs": int(s["runs"]), "n": n, "k": k, "workers": workers, "failed": int(s["failed"]),
        "wall_s": ev, "wall_s_with_analysis": wall, "runs_per_s": s["runs"] / ev,
        "peak_rss_mb": {
            "parent": rss_study,
            "parent_before_study": rss_before,
            "largest_worker": _children_peak_rss_mb(),
        },
        "worker_s_per_run": {"mean_ms": float(secs.mean() * 1e3), "median_ms": float(np.median(secs) * 1e3),
                             "p90_ms": float(np.percentile(secs, 90) * 1e3),
                             "max_ms": float(secs.max() * 1e3), "sum_s": float(secs.sum())},
        "pool_utilisation": float(secs.sum() / (ev * workers)),
        # CPU time does not depend on what else the machine runs: what the study costs on idle cores
        "cpu_s": {"workers": cpu_workers, "parent": cpu_parent},
        "worker_cpu_ms_per_run": cpu_workers / max(1, s["runs"]) * 1e3,
        "parent_cpu_ms_per_run": cpu_parent / max(1, s["runs"]) * 1e3,
        "runs_per_s_on_idle_cores": workers / (cpu_workers / max(1, s["runs"])) if cpu_workers > 0 else None,
        "loadavg_1min_after": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        "loadavg_1min_before": load_before,
    }


def bench_sobol(runs: int, workers: int, fmu_path: Path | None = None, cheap: bool = False) -> dict:
    """:func:`sobol_child` in a fresh interpreter, so that ru_maxrss is this study's own peak."""
    code = ("import json, sys; from fmusa.bench import sobol_child; "
            f"print('@@' + json.dumps(sobol_child({int(runs)}, {int(workers)}, None, "
            f"{str(fmu_path) if fmu_path else None!r}, {bool(cheap)!r})))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, encoding="utf-8",
                          errors="replace")
    if proc.returncode != 0:
        raise RuntimeError(f"Sobol benchmark ({runs} runs) failed:\n{proc.stderr[-4000:]}")
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("@@")][-1]
    return json.loads(line[2:])


#: The crash-heavy study of :func:`bench_start_methods`: runs whose every one segfaults its worker.
CRASH_RUNS = 100


def _child(code: str, env: dict, what: str) -> dict:
    """Run ``code`` (which prints ``@@`` + JSON) in a fresh interpreter with ``env``; its JSON."""
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, encoding="utf-8",
                          errors="replace", env=env, cwd=str(REPO))
    if proc.returncode != 0:
        raise RuntimeError(f"{what} failed:\n{proc.stderr[-4000:]}")
    return json.loads([ln for ln in proc.stdout.splitlines() if ln.startswith("@@")][-1][2:])


def paper_study_child() -> dict:
    """The paper's study once (no figures), in THIS process: its wall time."""
    from fmusa.study.loader import load_study
    from fmusa.api import run_study

    study = load_study(REPO / "studies" / "paper.yaml")
    with tempfile.TemporaryDirectory(prefix="fmusa-bench-paper-") as tmp:
        t0 = time.perf_counter()
        res = run_study(study, tmp, figures=False, progress=False)
        return {"wall_s": time.perf_counter() - t0, "runs": res.summary["runs"]}


def crash_study_child(fmu: str, runs: int, workers: int) -> dict:
    """A study of ``runs`` runs of tests/fmus/misbehave that each segfault their worker, in THIS process:
    its wall time, how many runs failed (all of them, each on a fresh worker) and the CPU seconds of the
    workers and of this process."""
    import dataclasses
    from fmusa.study.loader import parse_study
    from fmusa.api import run_study

    ks = np.geomspace(3e6, 5e6, runs)
    text = (f"name: crash_heavy\nfmu: {fmu}\nparameters:\n  k: {{variable: k, unit: N/m}}\nfixed:\n  F: 411.0\n"
            f"  fault: 1\n  fault_kind: 1\n  fault_lo: 1.0\n  fault_hi: 1.0e9\nscenario:\n  stop_time: 1\n"
            f"  step: 0.5\nmetrics:\n  y_max: {{output: y_peak, reduce: final, unit: m}}\nstages:\n  grid:\n"
            f"    values:\n      k: [{', '.join(repr(float(k)) for k in ks)}]\nexecution:\n  workers: {workers}\n")
    with tempfile.TemporaryDirectory(prefix="fmusa-bench-crash-") as tmp:
        study = parse_study(text, Path(tmp) / "crash.yaml")
        cpu0 = _cpu_s()
        t0 = time.perf_counter()
        res = run_study(study, Path(tmp) / "out", figures=False, progress=False)
        wall = time.perf_counter() - t0
        cpu1 = _cpu_s()
        # CPU does not depend on what else the machine runs: the workers' (ended children) and this process's
        return {"wall_s": wall, "runs": res.summary["runs"], "failed": res.summary["failed"],
                "cpu_s_workers": cpu1[1] - cpu0[1], "cpu_s_parent": cpu1[0] - cpu0[0]}


def _misbehave_fmu(folder: Path) -> Path | None:
    """tests/fmus/misbehave built with gcc and zipped, or None without gcc or the sources (not Linux)."""
    import shutil
    import zipfile
    import fmpy

    src = REPO / "tests" / "fmus" / "misbehave"
    if not (src.is_dir() and shutil.which("gcc") and sys.platform.startswith("linux")):
        return None
    tree = folder / "tree"
    (tree / "binaries" / "linux64").mkdir(parents=True)
    shutil.copy(src / "modelDescription.xml", tree / "modelDescription.xml")
    subprocess.run(["gcc", "-std=c99", "-O1", "-shared", "-fPIC", "-I", str(Path(fmpy.__file__).parent / "c-code"),
                    str(src / "misbehave.c"), "-o", str(tree / "binaries" / "linux64" / "Misbehave.so"), "-lm"],
                   check=True, capture_output=True)
    fmu = folder / "Misbehave.fmu"
    with zipfile.ZipFile(fmu, "w", zipfile.ZIP_DEFLATED) as z:
        for f in sorted(tree.rglob("*")):
            if f.is_file():
                z.write(f, f.relative_to(tree).as_posix())
    return fmu


def bench_start_methods(methods: tuple[str, ...] = ("fork", "spawn"), sobol_runs: int = 10000,
                        workers: int | None = None) -> dict:
    """The same studies with the pool's workers started by each of ``methods`` ($FMUSA_START_METHOD), each
    in a fresh interpreter: the paper's study, the 6-DOF Sobol study of ``sobol_runs`` runs and a
    crash-heavy study (:data:`CRASH_RUNS` runs, each segfaulting its worker). Issue 19's targets: spawn
    within 1.5x of fork on the first two, within 5x on the third (``start_method_ratios``)."""
    import multiprocessing as mp

    workers = workers or os.cpu_count() or 1
    out: dict = {"start_methods": {}, "start_methods_workers": workers, "start_methods_loadavg_1min": [_load()]}
    with tempfile.TemporaryDirectory(prefix="fmusa-bench-sm-") as tmp:
        crash_fmu = _misbehave_fmu(Path(tmp))
        for m in methods:
            if m not in mp.get_all_start_methods():
                out["start_methods"][m] = {"note": f"not available on {sys.platform}"}
                continue
            env = {**os.environ, "FMUSA_START_METHOD": m}
            row = {"paper_study_wall_s": _child("import json; from fmusa.bench import paper_study_child; "
                                                "print('@@' + json.dumps(paper_study_child()))", env,
                                                f"the paper study under {m}")["wall_s"]}
            if sobol_runs > 0:
                sob = _child(f"import json; from fmusa.bench import sobol_child; "
                             f"print('@@' + json.dumps(sobol_child({int(sobol_runs)}, {int(workers)})))", env,
                             f"the Sobol study under {m}")
                row.update(sobol_wall_s=sob["wall_s"], sobol_runs=sob["runs"], sobol_runs_per_s=sob["runs_per_s"])
            if crash_fmu is not None:
                cr = _child(f"import json; from fmusa.bench import crash_study_child; print('@@' + json.dumps("
                            f"crash_study_child({str(crash_fmu)!r}, {CRASH_RUNS}, {int(workers)})))", env,
                            f"the crash-heavy study under {m}")
                row.update(crash_study_wall_s=cr["wall_s"], crash_study_failed=cr["failed"],
                           crash_study_cpu_s_workers=cr["cpu_s_workers"], crash_study_cpu_s_parent=cr["cpu_s_parent"])
            out["start_methods"][m] = row
            out["start_methods_loadavg_1min"].append(_load())
    base = out["start_methods"].get("fork", {})
    out["start_method_ratios"] = {
        m: {k: row[k] / base[k] for k in ("paper_study_wall_s", "sobol_wall_s", "crash_study_wall_s")
            if k in row and base.get(k)}
        for m, row in out["start_methods"].items() if m != "fork"}
    return out


def profile_six_dof(samples: int = 100, fmu_path: Path | None = None, seed: int = 1) -> dict:
    """Where one run of the 6-DOF Sobol study spends its time, in-process on ``samples`` of the
    study's Sobol points: the FMU's parts (reset + set + initialisation, the doStep that integrates,
    reading outputs), the Python around it (run_chunk of the same run minus those parts) and the
    solver's internal steps. (What a pooled run costs on top, IPC and the parent's RunStore, comes from
    the pooled benchmark: ``pooled_overhead_ms_per_run``.)"""
    from fmusa.runs.spec import run_batch

    spec, P, plan, n_steps = _six_dof_samples(samples, fmu_path, seed)
    r = plan.runner
    failed: list[str] = []
    t_setup, t_step, t_read, steps, cpu_step, t_full, cpu_full = [], [], [], [], [], [], []
    plan(list(P[0]))                                     # warm; leaves the instance ready for reset
    for j, row in enumerate(P):
        # 1) the run by hand, timed in parts (what RunPlan.__call__ does)
        t0 = time.perf_counter()
        plan.start(row)                                  # reset, set parameters, initialise
        s = r.instance
        t1 = time.perf_counter()
        c1 = time.process_time()
        s.fmi2DoStep(s.component, 0.0, plan.stop_time, 1)
        cpu_step.append(time.process_time() - c1)
        t2 = time.perf_counter()
        plan.read()
        t3 = time.perf_counter()
        steps.append(n_steps())
        t_setup.append(t1 - t0)
        t_step.append(t2 - t1)
        t_read.append(t3 - t2)
        r.mark_done()
    # 2) the same runs as a worker does them (run_batch: RunPlan, metrics reduced over the batch)
    t0, c0 = time.perf_counter(), time.process_time()
    res = run_batch(spec, np.arange(len(P)), P)
    t_full.append((time.perf_counter() - t0) / len(P))
    cpu_full.append((time.process_time() - c0) / len(P))
    failed.extend(m[:300] for m in res.messages.values())
    steps = np.asarray(steps, dtype=float)
    step_s = np.asarray(t_step)
    full = float(np.mean(t_full))
    fmu_parts = float(np.mean(t_setup) + np.mean(step_s) + np.mean(t_read))
    cores = os.cpu_count() or 1
    return {
        "samples": len(P),
        "rtol": dict(spec.fixed).get("rtol"),
        "ms_per_run_in_process": full * 1e3,
        "cpu_ms_per_run_in_process": float(np.mean(cpu_full) * 1e3),
        "fmu_setup_ms": float(np.mean(t_setup) * 1e3),
        "fmu_dostep_ms": float(np.mean(step_s) * 1e3),
        "fmu_dostep_ms_median": float(np.median(step_s) * 1e3),
        "fmu_dostep_ms_p90": float(np.percentile(step_s, 90) * 1e3),
        "fmu_dostep_ms_max": float(step_s.max() * 1e3),
        "fmu_dostep_cpu_ms": float(np.mean(cpu_step) * 1e3),
        "fmu_read_ms": float(np.mean(t_read) * 1e3),
        "python_overhead_ms": (full - fmu_parts) * 1e3,
        "python_overhead_note": ("run_batch of the samples per run minus the same runs' FMU calls timed by "
                                 "hand (reset/set/initialise + doStep + read): RunPlan, metrics; noisy with "
                                 "runs of this length, see pipeline_worker_python_ms_per_run (cheap runs)"),
        "fmu_integration_share": float(np.mean(step_s) / full) if full > 0 else None,
        "solver_steps_mean": float(steps.mean()),
        "solver_steps_median": float(np.median(steps)),
        "solver_steps_max": float(steps.max()),
        "solver_us_per_step": float(step_s.sum() / steps.sum() * 1e6),
        "failed": failed,
        "ceiling_runs_per_s_all_cores_fmu_only": cores / float(np.mean(step_s)),
        "ceiling_runs_per_s_all_cores_without_integration": cores / max(full - float(np.mean(step_s)), 1e-9),
        "loadavg_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
    }


def profile_pipeline(samples: int = 4000, fmu_path: Path | None = None, repeats: int = 3) -> dict:
    """The worker's Python per run on cheap runs (:func:`cheap_six_dof`), in this process: ``run_batch``
    of ``samples`` Sobol points per run minus the same runs' FMU calls timed by hand (reset, parameters,
    initialisation, doStep, read through fmpy); the best of ``repeats`` of each, as the machine is shared."""
    from fmusa.runs.spec import plan_for, run_batch
    from fmusa.analysis.sensitivity import draw_samples, to_physical
    from fmusa.pipeline.sensitivity import sensitivity_spec

    study, stage = _six_dof()
    spec = sensitivity_spec(cheap_six_dof(study), stage, fmu_path=fmu_path)
    P = to_physical(stage, draw_samples(stage, "sobol", n=samples // (len(stage.parameters) + 2) + 1))[:samples]
    plan = plan_for(spec)
    rows = P.tolist()
    plan(rows[0])
    ids = np.arange(len(P))
    t_fmu, t_batch = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for row in rows:
            plan.start(row)
            s = plan.runner.instance
            s.fmi2DoStep(s.component, 0.0, plan.stop_time, 1)
            plan.read()
            plan.runner.mark_done()
        t_fmu.append((time.perf_counter() - t0) / len(P))
        t0 = time.perf_counter()
        b = run_batch(spec, ids, P)
        t_batch.append((time.perf_counter() - t0) / len(P))
    fmu, batch = min(t_fmu), min(t_batch)
    return {"samples": len(P), "failed": int((~b.ok).sum()), "fmu_ms_per_run": fmu * 1e3,
            "run_batch_ms_per_run": batch * 1e3, "worker_python_ms_per_run": (batch - fmu) * 1e3,
            "loadavg_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}


def bench_pipeline(workers: int, runs: int = 40000, small_runs: int = 10000, fmu_path: Path | None = None) -> dict:
    """What the pipeline itself costs per run, on cheap runs (the 6-DOF study with the screw at rest,
    :func:`cheap_six_dof`: the same 16 parameters, 7 metrics, pool, RunStore and SALib analysis, an FMU run
    of ~0.02 ms): the worker's Python (:func:`profile_pipeline`), the worker's and the parent's CPU time per
    run of a pooled Sobol study of ``runs`` runs (``pipeline_overhead_ms_per_run``: both, without the FMU's
    own calls), and the parent's peak RSS growth per run between studies of ``small_runs`` and ``runs``."""
    prof = profile_pipeline(fmu_path=fmu_path)
    big = bench_sobol(runs, workers, fmu_path, cheap=True)
    small = bench_sobol(small_runs, workers, fmu_path, cheap=True)
    fmu = prof["fmu_ms_per_run"]
    worker = big["worker_cpu_ms_per_run"] - fmu
    rss = ((big["peak_rss_mb"]["parent"] - small["peak_rss_mb"]["parent"]) * 1024
           / max(1, big["runs"] - small["runs"]))
    return {
        "pipeline_overhead_ms_per_run": worker + big["parent_cpu_ms_per_run"],
        "pipeline_worker_python_ms_per_run": prof["worker_python_ms_per_run"],
        "pipeline_worker_cpu_ms_per_run_without_fmu": worker,
        "pipeline_parent_cpu_ms_per_run": big["parent_cpu_ms_per_run"],
        "pipeline_parent_rss_kb_per_run": rss,
        "pipeline_runs_per_s_cheap": big["runs_per_s"],
        "pipeline_loadavg_1min": [prof["loadavg_1min"], big["loadavg_1min_before"], big["loadavg_1min_after"],
                                  small["loadavg_1min_before"], small["loadavg_1min_after"]],
        "pipeline_detail": {"profile": prof, "pooled": big, "pooled_small": small,
                            "note": "CPU times per run; overhead = worker CPU - the FMU's calls + parent CPU "
                                    "(store, pool, sampling, SALib analysis); FMU run ~0.02 ms"},
    }


def bench_paper_study(repeats: int = 5) -> dict:
    """The paper's study, all three stages (grid, region of interest, search; regression too), no figures:
    the median wall time of fresh runs into an empty directory."""
    from fmusa.study.loader import load_study
    from fmusa.api import run_study

    from fmusa.runs.preflight import ENV_CACHE, forget_verdicts

    study_file = Path(__file__).resolve().parents[2] / "studies" / "paper.yaml"
    study = load_study(study_file)
    walls, runs, checks, steps, extra = [], 0, [], [], []
    old_cache = os.environ.get(ENV_CACHE)
    try:
        for _ in range(repeats):
            with tempfile.TemporaryDirectory(prefix="fmusa-bench-paper-") as tmp:
                os.environ[ENV_CACHE] = os.path.join(tmp, "cache")      # the reset check made, not cached
                forget_verdicts()
                t0 = time.perf_counter()
                res = run_study(study, os.path.join(tmp, "out"), figures=False, progress=False)
                walls.append(time.perf_counter() - t0)
                runs = res.summary["runs"]
                checks.append(res.summary["fmu_runs"]["check_s"])
                extra.append(sum(t.get("extra_ms") or 0.0 for t in res.summary["fmu_runs"]["tried"]))
                steps.append((res.summary.get("fmu_steps") or {}).get("wall_s", 0.0))
    finally:
        if old_cache is None:
            os.environ.pop(ENV_CACHE, None)
        else:
            os.environ[ENV_CACHE] = old_cache
    out = {"paper_study_wall_s": statistics.median(walls), "paper_study_wall_s_all": walls,
           # issue 17: the reset check before the first batch, and the FMU step check after the stages
           "paper_reset_check_s": statistics.median(checks), "paper_reset_verdict": res.summary["fmu_runs"]["mode"],
           # of it, the check's own runs (the FMU's loading and first run are the study's anyway)
           "paper_reset_check_extra_ms": statistics.median(extra),
           "paper_fmu_step_check_s": statistics.median(steps),
           "paper_study_loadavg_1min": _load(),
           "paper_study_runs": runs, "paper_study_target_s": 2.0,
           "paper_study_optimum": res.summary.get("optimum"),
           # FMU runs of the automatic-region search (a vendor FMU costs seconds per run: runs are the cost)
           "paper_search_runs": res.summary["stage_runs"]["search"]["simulated"]}
    out.update(bench_paper_search_warm(study, res.summary["optimum"]))
    return out


def bench_paper_search_warm(study=None, default_optimum: dict | None = None) -> dict:
    """The paper's stages with ``search.warm_start``: FMU runs of the search (``paper_search_runs_warm``,
    target <= 80 against ``paper_search_runs``), its optimum and the relative difference of each parameter
    from the default search's (target <= inner_rtol)."""
    import dataclasses

    from fmusa.pipeline.sweep import run_study as run_stages
    from fmusa.study.loader import load_study

    if study is None:
        study = load_study(Path(__file__).resolve().parents[2] / "studies" / "paper.yaml")
    stage = study.stages["search"]
    warm = dataclasses.replace(study, stages={**study.stages,
                                              "search": dataclasses.replace(stage, warm_start=True)})
    with tempfile.TemporaryDirectory(prefix="fmusa-bench-warm-") as tmp:
        if default_optimum is None:
            default_optimum = run_stages(study, Path(tmp) / "default", progress=False).summary["optimum"]
        res = run_stages(warm, Path(tmp) / "warm", progress=False)
    opt = res.summary["optimum"]
    rel = {k: abs(opt[k] - v) / abs(v) for k, v in default_optimum.items()} if opt else None
    return {"paper_search_runs_warm": res.summary["stage_runs"]["search"]["simulated"],
            "paper_search_runs_warm_asked": res.summary["stage_runs"]["search"]["asked"],
            "paper_search_runs_warm_target": 80,
            "paper_search_optimum_warm": opt,
            "paper_search_optimum_warm_rel_diff": rel,
            "paper_search_warm_within_inner_rtol": bool(rel) and max(rel.values()) <= stage.inner_rtol}


def _paper_text() -> str:
    return (Path(__file__).resolve().parents[2] / "studies" / "paper.yaml").read_text(encoding="utf-8")


def _paper_variant(parallel: str, workers: int | None = None, fmu: Path | None = None,
                   sleep_s: float | None = None):
    """studies/paper.yaml with ``search.parallel`` set (``"false"``, ``"auto"`` or a number), optionally on
    another FMU (``fmu``, with ScrewVertebra's variable names; ``sleep_s`` set in ``fixed``) and
    ``execution.workers``."""
    from fmusa.api import parse_study

    text = _paper_text()
    assert "    parallel: false" in text and "fmu: default" in text and "  workers: null " in text
    text = text.replace("    parallel: false", f"    parallel: {parallel}")
    if fmu is not None:
        text = text.replace("fmu: default", f"fmu: {fmu.as_posix()}")
    if sleep_s is not None:
        text = text.replace("fixed:\n", f"fixed:\n  sleep_s: {sleep_s!r}\n", 1)
    if workers is not None:
        text = text.replace("  workers: null ", f"  workers: {workers} ")
    return parse_study(text, Path(__file__).resolve().parents[2] / "studies" / "paper.yaml")


def _rounds_entry(summary: dict) -> dict:
    """Rounds and runs per stage of a finished study (stages that ran the FMU)."""
    stages = {k: v for k, v in summary["stage_runs"].items() if v.get("asked")}
    out = {"rounds": summary["rounds"], "runs": summary["runs"], "stages": stages,
           "optimum": summary.get("optimum")}
    for key in ("search", "paper_roi_search"):
        par = (summary.get(key) or {}).get("parallel")
        if par:
            out[f"{key}_sequential_rounds"] = par["sequential_rounds"]
    return out


def bench_paper_study_rounds(workers: tuple[int, ...] = (1, 2, 16)) -> dict:
    """``paper_study_rounds``: the paper study (our FMU, figures off) with ``search.parallel`` at 1, 2 and 16
    points per round, next to the sequential search of studies/paper.yaml: rounds (batches of runs waited
    for one after another: the wall time of an FMU that costs seconds per run) and runs, per stage."""
    from fmusa.api import run_study

    out: dict = {}
    for w in ("false", *workers):
        study = _paper_variant(str(w))
        with tempfile.TemporaryDirectory(prefix="fmusa-bench-rounds-") as tmp:
            res = run_study(study, tmp, figures=False, progress=False)
        out["sequential" if w == "false" else str(w)] = _rounds_entry(res.summary)
    return {"paper_study_rounds": out, "paper_study_rounds_target_16": 20,
            "paper_study_rounds_16_within_target": out.get("16", {}).get("rounds", 10 ** 9) <= 20,
            "paper_study_runs_target_16": 2 * out["sequential"]["runs"]}


def bench_paper_study_slow_fmu(workers: tuple[int, ...] = (16,), sequential: bool = True,
                               sleep_s: float = 0.5) -> dict:
    """``paper_study_wall_s_slow_fmu``: the paper study on a stand-in FMU that sleeps ``sleep_s`` of wall
    time per run and returns the closed-form axial pullout (tests/fmus/slow_pullout, built here with the C
    compiler), with ``search.parallel: auto`` on 16 local workers (sleeping needs no cores), next to the
    sequential search (``sequential``; one run at a time, ~runs x sleep_s). Other worker counts go into
    ``paper_study_slow_fmu``."""
    from fmusa.api import run_study

    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests" / "fmus" / "slow_pullout"))
    try:
        from build import build_pullout_fmu
    finally:
        sys.path.pop(0)
    detail: dict = {}
    with tempfile.TemporaryDirectory(prefix="fmusa-bench-slow-") as tmp:
        fmu = build_pullout_fmu(Path(tmp))
        runs_list = [("auto", w) for w in workers] + ([("false", 1)] if sequential else [])
        for par, w in runs_list:
            study = _paper_variant(par, w, fmu, sleep_s)
            t0 = time.perf_counter()
            res = run_study(study, Path(tmp) / f"out-{par}-{w}", figures=False, progress=False)
            entry = _rounds_entry(res.summary)
            entry["wall_s"] = time.perf_counter() - t0
            detail["sequential" if par == "false" else str(w)] = entry
            print(f"paper study, stand-in FMU at {sleep_s} s per run, "
                  f"{'sequential search' if par == 'false' else f'{w} workers'}: {entry['wall_s']:.1f} s, "
                  f"{entry['rounds']} rounds, {entry['runs']} runs")
    out = {"paper_study_slow_fmu": detail, "paper_study_slow_fmu_sleep_s": sleep_s,
           "paper_study_wall_s_slow_fmu_target_s": 15.0}
    if "16" in detail:
        out["paper_study_wall_s_slow_fmu"] = detail["16"]["wall_s"]
    if "sequential" in detail:
        out["paper_study_wall_s_slow_fmu_sequential"] = detail["sequential"]["wall_s"]
    return out


def bench_diagnose(fmu_path: Path, workers: int | None = None) -> dict:
    """`fmusa diagnose`: one FMU run on a measured drive (300 samples) with the baseline and with the most
    expensive effect, and the wall time of a whole diagnosis (six candidates, held-out refits) of one real
    spinal unit (H2 anterior, three rates, 528 samples) with a cold cache."""
    import numpy as np

    from fmusa.applications.shear_c67 import data as shear_c67
    from fmusa.diagnose.calibrate import ModelRunner
    from fmusa.diagnose.run import diagnose

    t = np.linspace(0.0, 6.0, 300)
    y = np.interp(t, [0, 1.5, 3.5, 5.0, 6.0], [0, 1.2e-3, 1.2e-3, 0, 0])
    F = np.interp(t, [0, 1.5, 3.5, 5.0, 6.0], [0, 250.0, 250.0, 0, 0])
    out = {}
    cases = {"displacement_baseline": ("displacement", ["c_y", "d_y"], [2e5, 100.0], y),
             "force_friction": ("force", ["c_y", "d_y", "fric_F"], [2e5, 100.0, 25.0], F)}
    for name, (drive, names, values, u) in cases.items():
        model = ModelRunner(fmu_path, drive, names)
        try:
            model.plan(values, t, u)
            times = []
            for _ in range(20):
                t0 = time.perf_counter()
                model.plan(values, t, u)
                times.append(time.perf_counter() - t0)
        finally:
            model.close()
        out[f"diagnose_run_ms_{name}"] = 1e3 * statistics.median(times)
    tests = shear_c67.list_tests(shear_c67.DEFAULT_DATA)   # make bench runs from the repository root
    g = tests[(tests.specimen == "H2") & (tests.direction == "Ant")]
    exps = [shear_c67.load_test(r, max_points=300) for _, r in g.iterrows()]
    t0 = time.perf_counter()
    d = diagnose(exps, "displacement", fmu_path=fmu_path, workers=workers)
    out["diagnose_shear_unit_wall_s"] = time.perf_counter() - t0
    out["diagnose_shear_unit_points"] = int(sum(len(e.t) for e in exps))
    out["diagnose_shear_unit_effect"] = d["effect"]
    return out


def _synthetic_force_test():
    """The force-driven synthetic test with a hidden stiffening (tests/effects_reference.py, the seed the
    identifiability tests use), 200 samples; None where the tests folder is not there."""
    import zlib

    tests_dir = Path(__file__).resolve().parents[2] / "tests"
    if not (tests_dir / "effects_reference.py").is_file():
        return None
    sys.path.insert(0, str(tests_dir))
    try:
        import effects_reference as er
    finally:
        sys.path.remove(str(tests_dir))
    from fmusa.diagnose.measured import Experiment, downsample

    effect, drive = "nonlinear_stiffness", "force"
    df, _ = er.synthesize(effect, drive, seed=zlib.crc32(f"{effect}/{drive}".encode()) % 10_000)
    return downsample(Experiment(name="stiffening-force", path=Path("stiffening-force.csv"), drive=drive,
                                 t=df.time.values, displacement=df.displacement.values,
                                 force=df.force.values), 200)


def _timed_diagnosis(exps, drive: str, fmu, workers: int) -> dict:
    """One whole diagnosis (every candidate, the chain, cold cache, its fit workers started for it, as a new
    user's first): wall and CPU seconds (this process and its worker processes), its FMU runs by its own count,
    and its verdict."""
    from fmusa.diagnose.fitcache import close_workers
    from fmusa.diagnose.run import diagnose

    close_workers()
    c0, k0 = _cpu_s()
    t0 = time.perf_counter()
    d = diagnose(exps, drive, fmu_path=fmu, workers=workers)
    wall = time.perf_counter() - t0
    close_workers()            # kept workers' CPU is counted once they have ended
    c1, k1 = _cpu_s()
    return {"wall_s": wall, "cpu_s": (c1 - c0) + (k1 - k0), "runs": d["runs"]["total"], "workers": workers,
            "runs_counted_by_fits": d["runs"]["counted_by_fits"], "depth": d["runs"]["depth"], "effect": d["effect"], "chain": [s["effect"] for s in d["chain"]],
            "runs_by_stage": {"baseline": d["runs"]["baseline"]["total"],
                              **{n: r["total"] for n, r in d["runs"]["candidates"].items()},
                              **{f"chain:{n}": r["total"] for n, r in d["runs"]["chain"].items()}},
            "rounds_by_stage": {"baseline": d["runs"]["baseline"].get("rounds"),
                                **{n: r.get("rounds") for n, r in d["runs"]["candidates"].items()},
                                **{f"chain:{n}": r.get("rounds") for n, r in d["runs"]["chain"].items()}},
            "loadavg_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}


#: issue targets of a whole diagnosis of one test (two cores; the slow stand-in on 16 workers)
DIAGNOSE_TARGETS = {"diagnose_runs_target": 1000, "diagnose_force_stiffening_wall_s_target": 30.0,
                    "diagnose_h01_anterior_10mm_s_wall_s_target": 10.0, "diagnose_slow_fmu_wall_s_target": 600.0,
                    "diagnose_shear_all_wall_s_target": 300.0}


def bench_diagnose_shear_all(fmu_path: Path, workers: int | None = None) -> dict:
    """`fmusa diagnose-shear --all` as a user runs it: every unit of data/shear-c67 diagnosed, the rate
    dependence, the prediction bands, the two-line fits and the report, with the fit workers started anew (a
    new user's first run); wall and CPU seconds (this process's and its workers'), the units and their effects."""
    from fmusa.applications.shear_c67 import data as shear_c67
    from fmusa.applications.shear_c67.study import run_shear_diagnosis
    from fmusa.diagnose.fitcache import close_workers

    close_workers()
    with tempfile.TemporaryDirectory(prefix="fmusa-bench-shear-") as tmp:
        c0, k0 = _cpu_s()
        t0 = time.perf_counter()
        s = run_shear_diagnosis(Path(tmp) / "out", shear_c67.DEFAULT_DATA, fmu_path=str(fmu_path), workers=workers,
                                diagnosed=None)
        wall = time.perf_counter() - t0
        close_workers()               # their CPU reaches this process's children's
        c1, k1 = _cpu_s()
        used = (c1 - c0) + (k1 - k0)
    effects = {k: g["effect"] for k, g in s["groups"].items()}
    print(f"diagnose-shear --all: {len(effects)} units in {wall:.0f} s wall, {used:.0f} s CPU")
    return {"diagnose_shear_all_wall_s": wall, "diagnose_shear_all_cpu_s": used, "diagnose_shear_all_units": len(effects),
            "diagnose_shear_all_effects": effects, "diagnose_shear_all_workers": workers or os.cpu_count() or 1,
            "diagnose_shear_all_loadavg_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None}


def bench_diagnose_runs(fmu_path: Path, workers: int | None = None, slow_workers: int = 16,
                        delay_s: float = 0.2, shear_all: bool = True) -> dict:
    """What one diagnosis of one test costs, in FMU runs, CPU and wall seconds: the force-driven synthetic
    test with a hidden stiffening and H01 anterior at 10 mm/s, on all cores; and the force-driven test on
    a stand-in for a slow export (the FMU rebuilt to sleep ``delay_s`` a run, :mod:`fmusa.fmi.instrument`)
    with ``slow_workers`` workers, whose own log of its runs checks the diagnosis's count; and with
    ``shear_all`` `fmusa diagnose-shear --all` (:func:`bench_diagnose_shear_all`, about five minutes)."""
    import tempfile

    from fmusa.applications.shear_c67 import data as shear_c67
    from fmusa.fmi.instrument import count_logged_runs, instrumented_copy

    workers = workers or os.cpu_count() or 1
    out: dict = {}
    force = _synthetic_force_test()
    if force is not None:
        out["diagnose_force_stiffening"] = _timed_diagnosis([force], "force", fmu_path, workers)
    tests = shear_c67.list_tests(shear_c67.DEFAULT_DATA)
    row = tests[(tests.specimen == "H1") & (tests.direction == "Ant") & (tests.rate_mm_s == 10)]
    if len(row):
        exps = [shear_c67.load_test(row.iloc[0], max_points=300)]
        out["diagnose_h01_anterior_10mm_s"] = _timed_diagnosis(exps, "displacement", fmu_path, workers)
    else:
        out["diagnose_h01_anterior_10mm_s"] = {"skipped": f"no test H1 Ant 10 mm/s in {shear_c67.DEFAULT_DATA}"}
    if force is not None and slow_workers > 0:
        with tempfile.TemporaryDirectory(prefix="fmusa-bench-slow-") as tmp:
            log = Path(tmp) / "runs.log"
            try:
                slow = instrumented_copy(fmu_path, Path(tmp) / "fmu", log, delay_s)
            except Exception as exc:  # noqa: BLE001 - no compiler here: say so in bench.json
                out["diagnose_slow_fmu"] = {"skipped": f"{type(exc).__name__}: {exc}"}
            else:
                r = _timed_diagnosis([force], "force", slow, slow_workers)
                r.update(delay_s_per_run=delay_s, runs_logged_by_fmu=count_logged_runs(log))
                out["diagnose_slow_fmu"] = r
    out_all = bench_diagnose_shear_all(fmu_path, workers) if shear_all else {}
    flat = {}
    for k, r in out.items():
        if "wall_s" in r:
            print(f"{k}: {r['runs']} FMU runs in {r['depth']} rounds, {r['wall_s']:.1f} s wall, {r['cpu_s']:.1f} s "
                  f"CPU on {r['workers']} workers (load {r['loadavg_1min']}); effect {r['effect']}, chain {r['chain']}")
            # the figures the benchmark page lists (it shows the top-level numbers; the detail stays nested)
            flat.update({f"{k}_runs": r["runs"], f"{k}_depth": r["depth"], f"{k}_wall_s": r["wall_s"],
                         f"{k}_cpu_s": r["cpu_s"]})
    return {**out, **flat, **out_all, **DIAGNOSE_TARGETS}


def bench_attached_run(runs: int = 10, effect: str = "nonlinear_stiffness") -> dict:
    """What one run of an attached diagnosis costs: OpenModelica's Mass_Damper export (the shared vendor FMUs)
    with our InterfaceElement FMU coupled at its force input by the diagnosis's own runner (the me-grid scheme),
    on a force ramp-hold-unload of 4 s sampled at 40 Hz, the element carrying ``effect``; beside it, one run of the
    export alone through fmpy. Skipped, saying why, where the vendor FMUs or the element FMU are not there."""
    import numpy as np

    from fmusa.diagnose.calibrate import make_runner
    from fmusa.diagnose.effects import data_scales, model_parameters
    from fmusa.diagnose.measured import Experiment
    from fmusa.diagnose.study import load_diagnosis_study

    shared = Path(os.environ.get("FMUSA_SHARED_DIR") or Path.cwd().resolve().parent / "shared")
    om, element = shared / "vendor-fmus" / "OM1193_Mass_Damper.fmu", Path("dist/InterfaceElement.fmu").resolve()
    missing = [str(p) for p in (om, element) if not p.is_file()]
    if missing:
        return {"attached_run": {"skipped": f"not found: {', '.join(missing)} (set FMUSA_SHARED_DIR; make fmu)"}}
    t = np.arange(0.0, 4.0 + 1e-9, 1.0 / 40.0)
    F = np.interp(t, [0.0, 1.5, 2.5, 4.0], [0.0, 150.0, 150.0, 0.0])
    y = F / 1.5e4
    with tempfile.TemporaryDirectory(prefix="fmusa-bench-attached-") as tmp:
        csv = Path(tmp) / "ramp.csv"
        csv.write_text("time,displacement,force\n" + "".join(f"{a!r},{b!r},{c!r}\n" for a, b, c in zip(t, y, F)),
                       encoding="utf-8")
        study = Path(tmp) / "study.yaml"
        study.write_text(f"""name: mass_damper
fmu: {om}
model:
  drives:
    force: {{input: f, response: y}}
  fixed: {{spring.s_rel0: 0.5}}
baseline:
  stiffness: {{variable: c, bounds: [1.0e3, 2.0e4]}}
  damping: {{variable: d, bounds: [0.0, 200.0]}}
effects:
  where: attached
  element: {element}
  force_input: f
  displacement_output: y
  velocity_output: mass.v
tests:
  drive: force
  files: [{csv}]
""", encoding="utf-8")
        st = load_diagnosis_study(study)
        exp = Experiment(name="ramp", path=csv, drive="force", t=t, displacement=y, force=F)
        params = {p.name: p.starts[0] for p in model_parameters(effect, "force", data_scales([exp]))}
        runner = make_runner(str(om), "force", list(params), {}, st.interface)
        try:
            runner.predict(list(params.values()), [exp])            # loads both FMUs: not timed
            wall, cpu = [], []
            for _ in range(runs):
                w0, c0 = time.perf_counter(), time.process_time()
                runner.predict(list(params.values()), [exp])
                wall.append(time.perf_counter() - w0)
                cpu.append(time.process_time() - c0)
            scheme = getattr(getattr(runner, "last", None), "scheme", None)
        finally:
            runner.close()
    import fmpy

    alone = []
    for _ in range(3):
        w0 = time.perf_counter()
        fmpy.simulate_fmu(str(om), stop_time=4.0, output_interval=1.0 / 40.0, start_values={"spring.s_rel0": 0.5})
        alone.append(time.perf_counter() - w0)
    return {"attached_run": {"effect": effect, "samples": int(t.size), "scheme": scheme, "runs": runs,
                             "parameters": params},
            "attached_run_ms": 1e3 * statistics.median(wall), "attached_run_cpu_ms": 1e3 * statistics.median(cpu),
            "attached_export_alone_fmpy_ms": 1e3 * statistics.median(alone)}


def bench_fmi3(runs: int = 20, fmu_path: Path | None = None) -> dict:
    """An FMI 3.0 FMU through fmusa (fmusa.fmi.fmi3): MapleSim 2024's CoupledClutches from the shared vendor FMUs
    (``../shared/vendor-fmus/`` next to the repository), co-simulation and model exchange, 1.5 s sampled every
    10 ms: a prepared RunPlan's run on the reused instance against fmpy's ``simulate_fmu`` on a fresh one, and
    the largest relative difference of the four array elements between them. Empty when the FMU is missing."""
    import fmpy

    path = fmu_path or (Path(__file__).resolve().parents[2].parent / "shared" / "vendor-fmus"
                        / "MapleSim2024_CoupledClutches_FMI3.fmu")
    if not path.is_file():
        return {}
    outputs = [f"outputs[{i}]" for i in range(1, 5)]
    out: dict = {}
    for iface, key in (("co-simulation", "cs"), ("model-exchange", "me")):
        with FMURunner(path, interface=iface) as r:
            plan = RunPlan(r, ["freqHz", "T2"], {}, outputs, 1.5, 0.01)
            plan([0.2, 0.4])
            times, worst = [], 0.0
            for i in range(runs):
                vals = [0.1 + 0.2 * i / max(1, runs - 1), 0.3 + 0.3 * (i % 3) / 2]
                t0 = time.perf_counter()
                data = plan(vals)
                times.append((time.perf_counter() - t0) * 1e3)
                if i < 3:   # fresh-instance fmpy runs cost ~0.1 s each: a few suffice for the difference
                    t1 = time.perf_counter()
                    res = fmpy.simulate_fmu(str(path), fmi_type="CoSimulation" if key == "cs" else "ModelExchange",
                                            stop_time=1.5, output_interval=0.01, record_events=False,
                                            start_values={"freqHz": vals[0], "T2": vals[1]}, output=["outputs"])
                    out.setdefault(f"fmi3_clutches_{key}_fmpy_fresh_ms", (time.perf_counter() - t1) * 1e3)
                    ref = np.asarray(res["outputs"], dtype=float)
                    scale = np.maximum(np.abs(ref), 1e-3 * np.abs(ref).max())
                    worst = max(worst, float(np.max(np.abs(data - ref) / scale)))
        out[f"fmi3_clutches_{key}_run_ms_median"] = statistics.median(times)
        out[f"fmi3_clutches_{key}_max_rel_diff_vs_fresh_fmpy"] = worst
    return out


def _print_start_methods(sm: dict) -> None:
    for m, row in sm["start_methods"].items():
        print(f"start method {m}: " + ", ".join(f"{k} {v:.2f}" if isinstance(v, float) else f"{k} {v}"
                                                 for k, v in row.items()))
    for m, r in sm["start_method_ratios"].items():
        print(f"{m} / fork: " + ", ".join(f"{k} {v:.2f}x" for k, v in r.items()))


def _machine() -> dict:
    """The machine a figure was measured on, and its load then."""
    import fmpy

    return {"cpu_count": os.cpu_count(), "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(), "python": sys.version.split()[0],
            "fmpy": fmpy.__version__, "loadavg_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
            "timestamp": datetime.now(timezone.utc).isoformat(timespec="seconds")}


def _merge_into(path: Path, result: dict) -> None:
    """Merge ``result`` into the JSON file ``path`` (kept keys of earlier runs), written whole by rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    merged = {}
    if path.exists():
        try:
            merged = json.loads(path.read_text(encoding="utf-8"))
        except json.JSONDecodeError:
            merged = {}
    merged.update(result)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(merged, indent=2) + "\n", encoding="utf-8")
    tmp.replace(path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fmusa.bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/bench/bench.json"))
    ap.add_argument("--fmu", type=Path, default=None)
    ap.add_argument("--runs", type=int, default=300, help="timed reused-instance runs (>= 200)")
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--fmpy-runs", type=int, default=15, help="timed fmpy.simulate_fmu runs (>= 10)")
    ap.add_argument("--sobol-runs", type=int, default=10000,
                    help="runs of the 6-DOF Sobol study (N·(k+2) ≈ this; 0 skips the Sobol measurements)")
    ap.add_argument("--sobol-small-runs", type=int, default=2500,
                    help="runs of the second, smaller Sobol study (memory against run count; 0 skips it)")
    ap.add_argument("--pipeline-runs", type=int, default=40000,
                    help="runs of the cheap Sobol study that measures the pipeline's own cost (0 skips it)")
    ap.add_argument("--workers", type=int, default=None, help="pool workers (default: all cores)")
    ap.add_argument("--no-pce", dest="pce", action="store_false",
                    help="skip the polynomial chaos on the 6-DOF study against the Saltelli reference")
    ap.add_argument("--saltelli-reference", action="store_true",
                    help="first recompute the 6-DOF Saltelli reference (N = 4096, 73,728 runs) it is compared with")
    ap.add_argument("--no-diagnose", dest="diagnose", action="store_false",
                    help="skip the timings of `fmusa diagnose`")
    ap.add_argument("--no-diagnose-runs", dest="diagnose_runs", action="store_false",
                    help="skip the FMU runs, CPU and wall time of whole diagnoses (minutes)")
    ap.add_argument("--only-diagnose-runs", action="store_true",
                    help="measure only the whole diagnoses and merge them into --out")
    ap.add_argument("--only-diagnose", action="store_true",
                    help="measure only the diagnosis keys (driven runs, the shear unit, the whole diagnoses) and "
                         "merge them into --out")
    ap.add_argument("--slow-fmu-workers", default="16",
                    help="worker counts of the paper study on the slow stand-in FMU, e.g. 1,2,4,16 (0 skips it)")
    ap.add_argument("--no-slow-fmu-sequential", dest="slow_sequential", action="store_false",
                    help="skip the sequential search on the slow FMU (~190 s)")
    ap.add_argument("--start-methods", default="fork,spawn", metavar="LIST",
                    help="start methods to compare on the paper, Sobol and crash-heavy studies (empty: skip)")
    ap.add_argument("--only-start-methods", action="store_true",
                    help="measure only the start-method comparison and merge it into --out")
    args = ap.parse_args(argv)
    fmu_path = (args.fmu or default_fmu_path()).resolve()
    methods = tuple(m.strip() for m in args.start_methods.split(",") if m.strip())
    if args.only_diagnose_runs or args.only_diagnose:
        res = {**bench_diagnose(fmu_path, args.workers), **bench_attached_run()} if args.only_diagnose else {}
        _merge_into(args.out, {**res, **bench_diagnose_runs(fmu_path, args.workers),
                               "diagnose_runs_machine": _machine()})
        return 0
    if args.only_start_methods:
        sm = bench_start_methods(methods, args.sobol_runs, args.workers)
        _print_start_methods(sm)
        _merge_into(args.out, sm)
        return 0

    import fmpy

    t_runner, final = bench_runner(fmu_path, args.runs, args.warmup)
    t_fmpy, final_fmpy = bench_simulate_fmu(fmu_path, args.fmpy_runs)
    med = statistics.median(t_runner)
    med_fmpy = statistics.median(t_fmpy)
    diffs = {k: _rel_diff(final[k], final_fmpy[k]) for k in MONITORS}

    result = {
        "fmu": str(fmu_path),
        "case": {"params": PARAMS, "stop_time": STOP_TIME, "do_steps": 1, "outputs": MONITORS},
        "fmu_run_ms_median": med,
        "fmu_run_ms_p90": _percentile(t_runner, 90),
        "fmu_run_ms_min": min(t_runner),
        "fmu_runs": len(t_runner),
        "monitors": final,
        "fmpy_simulate_fmu_ms_median": med_fmpy,
        "fmpy_simulate_fmu_runs": len(t_fmpy),
        "fmpy_simulate_fmu_monitors": final_fmpy,
        "speedup_vs_fmpy_simulate_fmu": med_fmpy / med,
        "monitors_max_rel_diff_vs_fmpy": max(diffs.values()),
        "monitors_rel_diff_vs_fmpy": diffs,
        "machine": _machine(),
        "timestamp": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }

    result.update(bench_paper_study())
    result.update(bench_paper_study_rounds())
    slow_workers = tuple(int(w) for w in args.slow_fmu_workers.split(",") if int(w) > 0)
    if slow_workers or args.slow_sequential:
        result.update(bench_paper_study_slow_fmu(slow_workers, args.slow_sequential))
    result.update(bench_fmu_limits(fmu_path))
    result.update(bench_closed_form_c())
    result.update(bench_six_dof_runs(fmu_path=args.fmu))
    result.update(bench_fmi3())      # FMI 3.0 (MapleSim's CoupledClutches), when ../shared is there
    if args.diagnose_runs:
        result.update(bench_diagnose_runs(fmu_path, args.workers))
    if args.diagnose:
        result.update(bench_diagnose(fmu_path, args.workers))
        result.update(bench_attached_run())   # when ../shared's vendor FMUs are there
        print(f"diagnose: one driven run {result['diagnose_run_ms_displacement_baseline']:.2f} ms (baseline, "
              f"300 samples), {result['diagnose_run_ms_force_friction']:.2f} ms (force drive, friction); a "
              f"real unit, 6 candidates: {result['diagnose_shear_unit_wall_s']:.1f} s")

    if args.saltelli_reference:
        ref = six_dof_saltelli_reference(workers=args.workers, fmu=args.fmu)
        print(f"Saltelli reference: {ref['runs']} runs in {ref['wall_s']:.0f} s -> {SALTELLI_REFERENCE}")
    if args.pce:
        pce = bench_pce_six_dof(workers=args.workers, fmu=args.fmu)
        result.update(pce)
        print(f"pce 6-DOF: {pce['pce_six_dof_runs']} runs, max |dST| {pce['pce_six_dof_max_abs_dST']:.4f} at "
              f"{pce['pce_six_dof_worst']} against Saltelli at N = {pce['pce_six_dof_reference']['n']} (target "
              f"<= {PCE_MAX_DST} in <= {PCE_MAX_RUNS} runs); {pce['pce_six_dof_wall_s']:.0f} s wall")

    pipe = None
    if args.pipeline_runs > 0:
        workers = args.workers or os.cpu_count() or 1
        pipe = bench_pipeline(workers, args.pipeline_runs, max(1, args.pipeline_runs // 4), args.fmu)
        result.update(pipe)
        print(f"pipeline (cheap runs): {pipe['pipeline_overhead_ms_per_run']:.3f} ms CPU per run around the FMU "
              f"(worker Python {pipe['pipeline_worker_python_ms_per_run']:.3f} ms, parent "
              f"{pipe['pipeline_parent_cpu_ms_per_run']:.3f} ms), {pipe['pipeline_runs_per_s_cheap']:.0f} runs/s, "
              f"parent RSS {pipe['pipeline_parent_rss_kb_per_run']:.2f} KB per run; load "
              f"{pipe['pipeline_loadavg_1min']}")

    if args.sobol_runs > 0:
        workers = args.workers or os.cpu_count() or 1
        big = bench_sobol(args.sobol_runs, workers, args.fmu)
        print(f"Sobol 6-DOF: {big['runs']} runs in {big['wall_s']:.1f} s = {big['runs_per_s']:.1f} runs/s on "
              f"{workers} workers; peak RSS parent {big['peak_rss_mb']['parent']:.0f} MB, largest worker "
              f"{_mb_text(big['peak_rss_mb']['largest_worker'])}")
        result.update({
            "sobol_runs": big["runs"],
            "sobol_wall_s": big["wall_s"],
            "sobol_runs_per_s": big["runs_per_s"],
            "sobol_peak_rss_mb": big["peak_rss_mb"],
            "sobol_target_runs_per_s": SOBOL_TARGET_RUNS_PER_S,
            "sobol_target_met": big["runs_per_s"] >= SOBOL_TARGET_RUNS_PER_S,
            "sobol_detail": big,
        })
        if args.sobol_small_runs > 0:
            small = bench_sobol(args.sobol_small_runs, workers, args.fmu)
            print(f"Sobol 6-DOF: {small['runs']} runs in {small['wall_s']:.1f} s = {small['runs_per_s']:.1f} "
                  f"runs/s; peak RSS parent {small['peak_rss_mb']['parent']:.0f} MB, largest worker "
                  f"{_mb_text(small['peak_rss_mb']['largest_worker'])}")
            result.update({
                "sobol_small_runs": small["runs"],
                "sobol_small_wall_s": small["wall_s"],
                "sobol_small_runs_per_s": small["runs_per_s"],
                "sobol_small_peak_rss_mb": small["peak_rss_mb"],
                "sobol_small_detail": small,
                "sobol_parent_rss_kb_per_extra_run": (
                    (big["peak_rss_mb"]["parent"] - small["peak_rss_mb"]["parent"]) * 1024
                    / max(1, big["runs"] - small["runs"])),
            })
        # where each millisecond goes, whether or not the target is met
        prof = profile_six_dof(fmu_path=args.fmu)
        prof["pool_utilisation"] = big["pool_utilisation"]
        prof["pooled_worker_ms_per_run_mean"] = big["worker_s_per_run"]["mean_ms"]
        prof["pooled_overhead_ms_per_run"] = (big["wall_s"] * workers / big["runs"] * 1e3
                                              - big["worker_s_per_run"]["mean_ms"])
        # where each millisecond goes, per run: the FMU's integration, the worker's Python (on cheap
        # runs, where it is not lost in the FMU's spread), the parent (CPU: store, pool, analysis)
        prof["worker_python_ms_per_run"] = (pipe["pipeline_worker_python_ms_per_run"] if pipe
                                            else prof["python_overhead_ms"])
        prof["parent_cpu_ms_per_run"] = big["parent_cpu_ms_per_run"]
        prof["worker_cpu_ms_per_run"] = big["worker_cpu_ms_per_run"]
        prof["loadavg_1min_study"] = [big["loadavg_1min_before"], big["loadavg_1min_after"]]
        prof["why"] = (f"target {SOBOL_TARGET_RUNS_PER_S:.0f} runs/s on {workers} cores needs "
                       f"<= {workers / SOBOL_TARGET_RUNS_PER_S * 1e3:.2f} ms per run; the FMU's integration "
                       f"(one doStep) alone takes {prof['fmu_dostep_ms']:.2f} ms per run on average "
                       f"({prof['solver_steps_mean']:.0f} internal solver steps at "
                       f"{prof['solver_us_per_step']:.0f} us each); reset, parameters, initialisation "
                       f"and reading {prof['fmu_setup_ms'] + prof['fmu_read_ms']:.3f} ms, Python around the "
                       f"FMU in the worker {prof['worker_python_ms_per_run']:.3f} ms, the parent "
                       f"{prof['parent_cpu_ms_per_run']:.3f} ms CPU per run (pool wall time not spent in "
                       f"runs: {max(0.0, prof['pooled_overhead_ms_per_run']):.2f} ms per run)")
        result["sobol_profile"] = prof
        print(("Sobol target met: " if result["sobol_target_met"] else "Sobol target missed: ") + prof["why"])

    if methods:
        sm = bench_start_methods(methods, args.sobol_runs, args.workers)
        _print_start_methods(sm)
        result.update(sm)

    result["limits_note"] = limits_note(result)
    print("limits: " + result["limits_note"])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    merged = {}
    if args.out.exists():
        try:
            merged = json.loads(args.out.read_text(encoding="utf-8"))
        except json.JSONDecodeError:
            merged = {}
    merged.update(result)
    tmp = args.out.with_suffix(args.out.suffix + ".tmp")
    tmp.write_text(json.dumps(merged, indent=2) + "\n", encoding="utf-8")
    tmp.replace(args.out)

    print(f"reused instance: median {med:.3f} ms, p90 {result['fmu_run_ms_p90']:.3f} ms "
          f"over {len(t_runner)} runs")
    print(f"fmpy.simulate_fmu: median {med_fmpy:.3f} ms over {len(t_fmpy)} runs "
          f"-> speedup {result['speedup_vs_fmpy_simulate_fmu']:.1f}x")
    print(f"monitors {final}; max rel. diff vs simulate_fmu {result['monitors_max_rel_diff_vs_fmpy']:.3g}")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
