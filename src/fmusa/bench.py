"""Benchmark one FMU evaluation: ``python -m fmusa.bench --out out/bench/bench.json``.

Measures the paper's 411 N pullout at the paper's optimum (the FMU defaults c = 823224 N/m,
d = 488 N·s/m, t_ramp = 10 s, stop at 12 s) as a study runs it: the instance is reused (reset, set
parameters, setupExperiment, initialisation, ONE doStep 0 → 12 s, read the monitors y_max, v_y_max,
t_eq). Compares with ``fmpy.simulate_fmu`` on the same FMU file, which extracts, loads and
instantiates it on every call. Keys are merged into an existing JSON file.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from .evaluate import FMURunner, RunPlan, default_fmu_path

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


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fmusa.bench", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("out/bench/bench.json"))
    ap.add_argument("--fmu", type=Path, default=None)
    ap.add_argument("--runs", type=int, default=300, help="timed reused-instance runs (>= 200)")
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--fmpy-runs", type=int, default=15, help="timed fmpy.simulate_fmu runs (>= 10)")
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
