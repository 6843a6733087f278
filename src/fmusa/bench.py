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
``sobol_runs_per_s`` and ``sobol_peak_rss_mb`` (parent and largest worker, ``ru_maxrss``), the same for
``--sobol-small-runs`` (2500) to show how memory scales with the number of runs (each in a fresh
process, so that the peaks are its own), and ``sobol_profile``: where a run's time goes.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import resource
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


# ---------------------------------------------------------------------------- Sobol study throughput
SIX_DOF = Path(__file__).resolve().parents[2] / "studies" / "six_dof.yaml"
#: What the Sobol study of the 6-DOF case should reach on this 2-core machine.
SOBOL_TARGET_RUNS_PER_S = 2000.0


def _six_dof(study_path: Path | None = None):
    from fmusa.study.loader import load_study
    study = load_study(study_path or SIX_DOF)
    return study, study.stages["sensitivity"]


def sobol_child(runs: int, workers: int, study_path: str | None = None, fmu: str | None = None) -> dict:
    """One Sobol study of about ``runs`` runs, in THIS process (call it in a fresh one): wall time,
    throughput and peak resident memory of this process and of its largest worker."""
    import dataclasses
    from types import SimpleNamespace

    from fmusa.pipeline.sensitivity import run_sensitivity

    study, stage = _six_dof(Path(study_path) if study_path else None)
    if fmu:
        study = dataclasses.replace(study, fmu=Path(fmu))
    k = len(stage.parameters)
    n = max(1, round(runs / (k + 2)))
    stage = dataclasses.replace(stage, methods=["sobol"], n=n)
    runner = SimpleNamespace(evaluator=SimpleNamespace(workers=workers, scheduler=None), simulated=0)
    rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    load_before = os.getloadavg()[0] if hasattr(os, "getloadavg") else None
    _r = resource.getrusage(resource.RUSAGE_SELF)
    cpu_before = _r.ru_utime + _r.ru_stime
    with tempfile.TemporaryDirectory(prefix="fmusa-bench-sobol-") as tmp:
        t0 = time.perf_counter()
        res = run_sensitivity(study, stage, Path(tmp), runner, progress=False, resume=False, accuracy_samples=0)
        wall = time.perf_counter() - t0
        import pandas as pd
        secs = pd.read_csv(Path(tmp) / "sensitivity_runs.csv", usecols=["seconds"])["seconds"].to_numpy()
    s = res["summary"]
    ev = s["eval_wall_s"]
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu_workers = kids.ru_utime + kids.ru_stime
    cpu_parent = me.ru_utime + me.ru_stime - cpu_before
    return {
        "runs": int(s["runs"]), "n": n, "k": k, "workers": workers, "failed": int(s["failed"]),
        "wall_s": ev, "wall_s_with_analysis": wall, "runs_per_s": s["runs"] / ev,
        "peak_rss_mb": {
            "parent": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "parent_before_study": rss_before,
            "largest_worker": resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024,
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


def bench_sobol(runs: int, workers: int, fmu_path: Path | None = None) -> dict:
    """:func:`sobol_child` in a fresh interpreter, so that ru_maxrss is this study's own peak."""
    code = ("import json, sys; from fmusa.bench import sobol_child; "
            f"print('@@' + json.dumps(sobol_child({int(runs)}, {int(workers)}, None, "
            f"{str(fmu_path) if fmu_path else None!r})))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(f"Sobol benchmark ({runs} runs) failed:\n{proc.stderr[-4000:]}")
    line = [ln for ln in proc.stdout.splitlines() if ln.startswith("@@")][-1]
    return json.loads(line[2:])


def profile_six_dof(samples: int = 100, fmu_path: Path | None = None, seed: int = 1) -> dict:
    """Where one run of the 6-DOF Sobol study spends its time, in-process on ``samples`` of the
    study's Sobol points: the FMU's parts (reset + set + initialisation, the doStep that integrates,
    reading outputs), the Python around it (run_chunk of the same run minus those parts) and the
    solver's internal steps. (What a pooled run costs on top, IPC and the parent's RunStore, comes from
    the pooled benchmark: ``pooled_overhead_ms_per_run``.)"""
    import dataclasses

    from fmpy.fmi2 import fmi2Integer, fmi2ValueReference

    from fmusa.runs.spec import plan_for, run_chunk
    from fmusa.analysis.sensitivity import draw_samples, to_physical
    from fmusa.pipeline.sensitivity import sensitivity_spec

    study, stage = _six_dof()
    stage = dataclasses.replace(stage, seed=seed)
    spec = sensitivity_spec(study, stage, fmu_path=fmu_path)
    P = to_physical(stage, draw_samples(stage, "sobol", n=max(1, samples // (len(stage.parameters) + 2) + 1)))
    P = P[:samples]
    plan = plan_for(spec)
    r = plan.runner
    vr_steps = (fmi2ValueReference * 1)(r.variables["n_steps"].valueReference)
    steps_val = (fmi2Integer * 1)()
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
        s.fmi2GetInteger(s.component, vr_steps, 1, steps_val)
        steps.append(steps_val[0])
        t_setup.append(t1 - t0)
        t_step.append(t2 - t1)
        t_read.append(t3 - t2)
        r.mark_done()
        # 2) the same run as a worker does it (run_chunk: RunPlan, metrics, RunResult), right after
        t0, c0 = time.perf_counter(), time.process_time()
        res = run_chunk(spec, [(j, tuple(map(float, row)))])
        t_full.append(time.perf_counter() - t0)
        cpu_full.append(time.process_time() - c0)
        if res[0].status != "ok":
            failed.append(res[0].message[:300])
    steps = np.asarray(steps, dtype=float)
    step_s = np.asarray(t_step)
    full = float(np.mean(t_full))
    fmu_parts = float(np.mean(t_setup) + np.mean(step_s) + np.mean(t_read))
    cores = os.cpu_count() or 1
    return {
        "samples": len(P),
        "rtol": dict(study.fixed).get("rtol"),
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
        "python_overhead_note": ("run_chunk of one run minus the same run's FMU calls timed by hand just "
                                 "before (reset/set/initialise + doStep + read): RunPlan, metrics, RunResult"),
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


def bench_paper_study(repeats: int = 5) -> dict:
    """The paper's study, all three stages (grid, region of interest, search; regression too), no figures:
    the median wall time of fresh runs into an empty directory."""
    from fmusa.study.loader import load_study
    from fmusa.api import run_study

    study_file = Path(__file__).resolve().parents[2] / "studies" / "paper.yaml"
    study = load_study(study_file)
    walls, runs = [], 0
    for _ in range(repeats):
        with tempfile.TemporaryDirectory(prefix="fmusa-bench-paper-") as tmp:
            t0 = time.perf_counter()
            res = run_study(study, tmp, figures=False, progress=False)
            walls.append(time.perf_counter() - t0)
            runs = res.summary["runs"]
    out = {"paper_study_wall_s": statistics.median(walls), "paper_study_wall_s_all": walls,
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
    ap.add_argument("--workers", type=int, default=None, help="pool workers (default: all cores)")
    ap.add_argument("--no-diagnose", dest="diagnose", action="store_false",
                    help="skip the timings of `fmusa diagnose`")
    args = ap.parse_args(argv)
    fmu_path = (args.fmu or default_fmu_path()).resolve()

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
        "machine": {
            "cpu_count": os.cpu_count(),
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "python": sys.version.split()[0],
            "fmpy": fmpy.__version__,
            "loadavg_1min": os.getloadavg()[0] if hasattr(os, "getloadavg") else None,
        },
        "timestamp": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }

    result.update(bench_paper_study())
    if args.diagnose:
        result.update(bench_diagnose(fmu_path, args.workers))
        print(f"diagnose: one driven run {result['diagnose_run_ms_displacement_baseline']:.2f} ms (baseline, "
              f"300 samples), {result['diagnose_run_ms_force_friction']:.2f} ms (force drive, friction); a "
              f"real unit, 6 candidates: {result['diagnose_shear_unit_wall_s']:.1f} s")

    if args.sobol_runs > 0:
        workers = args.workers or os.cpu_count() or 1
        big = bench_sobol(args.sobol_runs, workers, args.fmu)
        print(f"Sobol 6-DOF: {big['runs']} runs in {big['wall_s']:.1f} s = {big['runs_per_s']:.1f} runs/s on "
              f"{workers} workers; peak RSS parent {big['peak_rss_mb']['parent']:.0f} MB, largest worker "
              f"{big['peak_rss_mb']['largest_worker']:.0f} MB")
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
                  f"{small['peak_rss_mb']['largest_worker']:.0f} MB")
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
        if not result["sobol_target_met"]:
            prof = profile_six_dof(fmu_path=args.fmu)
            prof["pool_utilisation"] = big["pool_utilisation"]
            prof["pooled_worker_ms_per_run_mean"] = big["worker_s_per_run"]["mean_ms"]
            prof["pooled_overhead_ms_per_run"] = (big["wall_s"] * workers / big["runs"] * 1e3
                                                  - big["worker_s_per_run"]["mean_ms"])
            prof["why"] = (f"target {SOBOL_TARGET_RUNS_PER_S:.0f} runs/s on {workers} cores needs "
                           f"<= {workers / SOBOL_TARGET_RUNS_PER_S * 1e3:.2f} ms per run; the FMU's integration "
                           f"(one doStep) alone takes {prof['fmu_dostep_ms']:.2f} ms per run on average "
                           f"({prof['solver_steps_mean']:.0f} internal solver steps at "
                           f"{prof['solver_us_per_step']:.0f} us each); reset, parameters, initialisation "
                           f"and reading {prof['fmu_setup_ms'] + prof['fmu_read_ms']:.3f} ms, Python around the "
                           f"FMU in the worker {prof['python_overhead_ms']:.3f} ms, pool and parent "
                           f"{max(0.0, prof['pooled_overhead_ms_per_run']):.2f} ms per run")
            result["sobol_profile"] = prof
            print("Sobol target missed: " + prof["why"])

    args.out.parent.mkdir(parents=True, exist_ok=True)
    merged = {}
    if args.out.exists():
        try:
            merged = json.loads(args.out.read_text())
        except json.JSONDecodeError:
            merged = {}
    merged.update(result)
    tmp = args.out.with_suffix(args.out.suffix + ".tmp")
    tmp.write_text(json.dumps(merged, indent=2) + "\n")
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
