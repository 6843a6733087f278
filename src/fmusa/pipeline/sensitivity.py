"""Global sensitivity analysis of a study: Morris screening and Sobol indices (SALib).

The paper's own future work: which of the 12 force-element parameters (and the screw's mass properties)
drive the response of a combined load case. :func:`run_sensitivity` is the ``sensitivity`` stage of
:func:`fmusa.sweep.run_study`:

1. The SALib problem comes from ``stage.parameters``: a ``uniform`` parameter is sampled within its
   bounds as is, a ``loguniform`` one uniformly in log10 space and transformed back (so SALib sees
   log10 values, the FMU the physical ones).
2. Morris trajectories (``num_levels`` 4) and a Sobol sample (``calc_second_order=False``,
   N·(k + 2) runs) are drawn with ``stage.seed``.
3. Every sample runs through :class:`fmusa.evaluate.Evaluator` (in-process, process pool or Dask, as the
   study's runner: workers, scheduler, isolation, timeout) on its own :class:`~fmusa.evaluate.PlanSpec`
   (the runner's, with the sensitivity parameters' FMU variables varied instead of the study
   parameters; ``study.fixed``, the scenario's inputs and ``fmu_options`` as in the study) and is written as it
   completes to ``out/sensitivity_runs.csv`` by a :class:`~fmusa.runstore.RunStore`; a resumed study
   simulates only the samples not in that file.
4. SALib analyses every metric of ``stage.outputs``. SALib needs a value for every sample: a metric
   with a failed run (or a NaN value) is not analysed, and the summary names the failing parameter sets
   (``errors``, ``failed_runs``); rows are never dropped silently.
5. Accuracy check: ``accuracy_samples`` (20) of the samples are run again with ``rtol = 1e-9`` (stored
   in ``out/sensitivity_accuracy.csv``, resumed the same way) and the largest differences of every
   metric are reported.

Only metric arrays are kept (no time series): memory is one small row per run.

Example::

    from fmusa.study import load_study
    from fmusa.sweep import run_study
    r = run_study(load_study("studies/six_dof.yaml"), "out/six_dof")
    r.sensitivity["summary"]["sobol"]["x_final"]["c_x"]      # {'S1': ..., 'ST': ...}
"""
from __future__ import annotations

import dataclasses
import math
import textwrap
import time
import warnings
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import pandas as pd

from fmusa.runs.evaluator import Evaluator
from fmusa.runs.spec import PlanSpec, RunResult
from fmusa.fmi.info import default_fmu_path
from fmusa.runs.store import RunStore
from fmusa.runs.progress import progress_bar

__all__ = ["run_sensitivity", "plot_sensitivity", "salib_problem", "draw_samples", "to_physical",
           "sensitivity_spec", "REFERENCE_RTOL", "MORRIS_LEVELS"]

#: Solver tolerance of the accuracy check's reference runs.
REFERENCE_RTOL = 1e-9
#: Levels of the Morris grid.
MORRIS_LEVELS = 4
RUNS_FILE = "sensitivity_runs.csv"
ACCURACY_FILE = "sensitivity_accuracy.csv"
#: Parameter sets named per failing metric in its error message; ``failed_runs`` lists up to
#: ``_MAX_FAILED_LISTED`` (every failed run stays in sensitivity_runs.csv).
_SHOW = 5
_MAX_FAILED_LISTED = 50


# ---------------------------------------------------------------------------- problem and samples
def salib_problem(stage) -> dict:
    """The SALib problem of ``stage``: bounds in the sampled space (log10 for ``loguniform``)."""
    names, bounds = [], []
    for p in stage.parameters.values():
        lo, hi = map(float, p.bounds)
        if p.distribution == "loguniform":
            lo, hi = math.log10(lo), math.log10(hi)
        names.append(p.name)
        bounds.append([lo, hi])
    return {"num_vars": len(names), "names": names, "bounds": bounds}


def to_physical(stage, X: np.ndarray) -> np.ndarray:
    """Sampled-space values (rows of SALib's X) → the physical values the FMU gets."""
    X = np.asarray(X, dtype=float)
    out = X.copy()
    for j, p in enumerate(stage.parameters.values()):
        if p.distribution == "loguniform":
            out[:, j] = np.power(10.0, X[:, j])
            lo, hi = map(float, p.bounds)
            out[:, j] = np.clip(out[:, j], lo, hi)   # 10**log10(hi) may be hi·(1 + 1 ulp)
    return out


def draw_samples(stage, method: str, problem: dict | None = None, n: int | None = None) -> np.ndarray:
    """SALib's sample (sampled space) for ``method``: Morris trajectories or the Sobol sample
    (``calc_second_order=False``, N·(k + 2) rows). ``n`` overrides ``stage.n`` /
    ``stage.morris_trajectories``."""
    problem = problem or salib_problem(stage)
    if method == "morris":
        from SALib.sample import morris as morris_sample
        return morris_sample.sample(problem, int(n or stage.morris_trajectories), num_levels=MORRIS_LEVELS,
                                    seed=stage.seed)
    if method == "sobol":
        from SALib.sample import sobol as sobol_sample
        with warnings.catch_warnings():   # N not a power of 2: SALib warns, the sample is still valid
            warnings.filterwarnings("ignore", message=".*Convergence properties of the Sobol.*")
            warnings.filterwarnings("ignore", message=".*balance properties of Sobol.*")
            return sobol_sample.sample(problem, int(n or stage.n), calc_second_order=False, seed=stage.seed)
    raise ValueError(f"unknown sensitivity method {method!r}; use morris or sobol")


def sensitivity_spec(study, stage, base: PlanSpec | None = None, fmu_path: str | Path | None = None,
                     fixed_override: Mapping[str, Any] | None = None, **changes) -> PlanSpec:
    """The PlanSpec of the sensitivity runs: the sensitivity parameters' FMU variables are varied
    (physical values, no scaling), ``study.fixed`` (updated with ``fixed_override``) and the scenario's
    inputs are set, the study's metrics are computed.

    ``base`` is the study runner's spec (``StudyRunner.spec``): its FMU path (the FMU as prepared for this
    machine), inputs, outputs, metric rules and how the FMU runs (``fmu_options``) are kept. Without it
    they come from ``study``. ``changes`` replace further fields (e.g. ``relative_tolerance``)."""
    if base is None:
        from fmusa.study.plan import study_plan_spec
        base = study_plan_spec(study, fmu_path or (study.fmu if study.fmu else default_fmu_path()))
    elif fmu_path is not None:
        changes.setdefault("fmu_path", str(fmu_path))
    fixed = dict(study.fixed)
    fixed.update(fixed_override or {})
    k = len(stage.parameters)
    return dataclasses.replace(
        base,
        varied=tuple(p.variable for p in stage.parameters.values()),
        scale=(1.0,) * k,
        offset=(0.0,) * k,
        fixed=tuple(fixed.items()),
        **changes,
    )


def _evaluator(spec: PlanSpec, runner, study, **overrides) -> Evaluator:
    """An Evaluator for ``spec`` that runs like the study runner's (workers, scheduler, isolation of a
    third-party FMU in supervised workers, per-run timeout)."""
    ev = getattr(runner, "evaluator", None)
    kw = {"workers": getattr(ev, "workers", None) or study.execution.workers,
          "scheduler": getattr(ev, "scheduler", None) or study.execution.scheduler,
          "isolate": getattr(ev, "isolate", study.fmu is not None),
          "timeout_s": getattr(ev, "timeout_s", study.execution.timeout_s)}
    kw.update(overrides)
    return Evaluator(spec, **kw)


# ---------------------------------------------------------------------------- evaluation
def _keys(P: np.ndarray) -> list[tuple[float, ...]]:
    return [RunStore.key(row) for row in P.tolist()]


def evaluate_keys(store: RunStore, evaluator: Evaluator, keys: Sequence[tuple[float, ...]], stage_label: str,
                  progress=None) -> int:
    """Simulate the keys the store does not have (each distinct key once); returns how many ran."""
    todo: dict[tuple, int] = {}
    for k in keys:
        if k not in todo and store.get(k) is None:
            todo[k] = store.new_id()
    if not todo:
        return 0
    items = [(rid, k) for k, rid in todo.items()]

    def keep(r: RunResult) -> None:
        store.add(r.run_id, stage_label, r.values, r.metrics, r.status, r.message, r.seconds)

    bar = None
    if progress:
        bar = progress_bar(len(items), f"sensitivity ({stage_label})", True)
    try:
        evaluator.map(items, on_result=keep, progress=bar)
    finally:
        if bar is not None:
            bar.close()
    return len(items)


def _collect(store: RunStore, keys: Sequence[tuple], metrics: Sequence[str]) -> tuple[np.ndarray, list[dict]]:
    """Metric matrix (samples × metrics; NaN where a run failed) and the failed rows."""
    Y = np.full((len(keys), len(metrics)), np.nan)
    failed: dict[tuple, dict] = {}
    for i, k in enumerate(keys):
        row = store.get(k)
        if row is None:  # pragma: no cover - evaluate_keys ran every key
            raise RuntimeError(f"sample {k} was not evaluated")
        if row["status"] != "ok":
            failed.setdefault(k, row)
            continue
        Y[i] = [float(row[m]) for m in metrics]
    return Y, list(failed.values())


def _resume_flag(runner, resume: bool | None) -> bool:
    """Resume when asked, else when the study's runner resumes: ``runner.resume`` if it has one,
    otherwise whether its RunStore reopened runs.csv for appending (StudyRunner(resume=True) on an
    existing output directory)."""
    if resume is not None:
        return bool(resume)
    flag = getattr(runner, "resume", None)
    if flag is not None:
        return bool(flag)
    fh = getattr(getattr(runner, "store", None), "_fh", None)
    return bool(fh is not None and getattr(fh, "mode", "w").startswith("a"))


def _reason(message: str, limit: int = 400) -> str:
    """The gist of a failed run's message: its first line and the FMU's log (the parameter list the
    message repeats is left out; the caller prints the parameter set)."""
    parts = [p.strip() for p in str(message).split(" | ")]
    head = parts[0] if parts else ""
    log = [p for p in parts[1:] if p and not p.startswith(("parameters set:", "FMU log:"))]
    text = head + (" — " + " ".join(log) if log else "")
    return text if len(text) <= limit else text[:limit - 1] + "…"


def _param_text(names: Sequence[str], key: Sequence[float]) -> str:
    return "{" + ", ".join(f"{n}={v:.6g}" for n, v in zip(names, key)) + "}"


# ---------------------------------------------------------------------------- analysis
def _nan_to_none(x):
    x = float(x)
    return x if math.isfinite(x) else None


def _analyse_morris(problem, X, Y, metric_names, seed):
    from SALib.analyze import morris as morris_analyze
    out, rows = {}, []
    for j, metric in enumerate(metric_names):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            res = morris_analyze.analyze(problem, X, Y[:, j], num_levels=MORRIS_LEVELS, seed=seed)
        out[metric] = {}
        for i, name in enumerate(problem["names"]):
            d = {"mu_star": _nan_to_none(res["mu_star"][i]), "sigma": _nan_to_none(res["sigma"][i]),
                 "mu_star_conf": _nan_to_none(res["mu_star_conf"][i]), "mu": _nan_to_none(res["mu"][i])}
            out[metric][name] = d
            rows.append({"metric": metric, "parameter": name, **d})
    return out, rows


def _analyse_sobol(problem, Y, metric_names, seed):
    from SALib.analyze import sobol as sobol_analyze
    out, rows = {}, []
    for j, metric in enumerate(metric_names):
        y = Y[:, j]
        if not np.ptp(y) > 0:
            # a constant output: no variance to apportion (SALib would divide by zero)
            res = {k: np.zeros(problem["num_vars"]) for k in ("S1", "S1_conf", "ST", "ST_conf")}
        else:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                res = sobol_analyze.analyze(problem, y, calc_second_order=False, seed=seed)
        out[metric] = {}
        for i, name in enumerate(problem["names"]):
            d = {k: _nan_to_none(res[k][i]) for k in ("S1", "S1_conf", "ST", "ST_conf")}
            out[metric][name] = d
            rows.append({"metric": metric, "parameter": name, **d})
    return out, rows


# ---------------------------------------------------------------------------- accuracy check
def accuracy_check(study, stage, spec: PlanSpec, store: RunStore, keys: Sequence[tuple], out: Path,
                   metrics: Sequence[str], runner, resume: bool, samples: int = 20,
                   reference_rtol: float = REFERENCE_RTOL) -> tuple[dict, int]:
    """Re-run ``samples`` of the (successful) samples with the solver tolerance ``reference_rtol`` and
    compare every metric: (report, runs simulated).

    The tolerance is the FMU parameter ``rtol`` when the study fixes it (our FMU), and the experiment
    tolerance (``fmi2SetupExperiment``, or the model exchange solver's) in any case; our FMU takes the
    smaller of the two."""
    ok_keys = [k for k in dict.fromkeys(keys) if (store.get(k) or {}).get("status") == "ok"]
    study_rtol = dict(study.fixed).get("rtol")
    exp_tol = getattr(spec, "relative_tolerance", None)
    report: dict[str, Any] = {"reference_rtol": reference_rtol,
                              "study_rtol": float(study_rtol) if study_rtol is not None else None,
                              "study_experiment_tolerance": exp_tol,
                              "samples": 0}
    if not ok_keys or samples <= 0:
        report["note"] = "no successful sample to check"
        return report, 0
    if any(p.variable == "rtol" for p in stage.parameters.values()):
        report["note"] = "rtol is a sensitivity parameter; no accuracy check"
        return report, 0
    rng = np.random.default_rng(stage.seed)
    pick = sorted(rng.choice(len(ok_keys), size=min(samples, len(ok_keys)), replace=False).tolist())
    chosen = [ok_keys[i] for i in pick]
    override = {"rtol": reference_rtol} if study_rtol is not None else {}
    changes = {}
    if "relative_tolerance" in PlanSpec.__dataclass_fields__:
        changes["relative_tolerance"] = min(reference_rtol, exp_tol) if exp_tol else reference_rtol
    ref_spec = dataclasses.replace(spec, fixed=tuple({**dict(spec.fixed), **override}.items()), **changes)
    report["reference_via"] = (["fixed rtol"] if override else []) + (
        ["experiment tolerance"] if changes else [])
    ref_store = RunStore(out / ACCURACY_FILE, list(stage.parameters), list(metrics), resume=resume)
    t0 = time.perf_counter()
    timeout = getattr(getattr(runner, "evaluator", None), "timeout_s", study.execution.timeout_s)
    try:   # a reference run costs ~100 study runs: a longer per-run limit
        with _evaluator(ref_spec, runner, study, pool_threshold=4,
                        timeout_s=None if timeout is None else 100 * timeout) as ev:
            simulated = evaluate_keys(ref_store, ev, chosen, f"rtol={reference_rtol:g}")
    finally:
        ref_store.close()
    names = list(stage.parameters)
    per_metric: dict[str, dict] = {}
    failed_ref = []
    A = np.array([[float(store.get(k)[m]) for m in metrics] for k in chosen])
    B = np.full_like(A, np.nan)
    for i, k in enumerate(chosen):
        row = ref_store.get(k)
        if row["status"] == "ok":
            B[i] = [float(row[m]) for m in metrics]
        else:
            failed_ref.append({"parameters": dict(zip(names, k)), "message": row["message"]})
    for j, m in enumerate(metrics):
        a, b = A[:, j], B[:, j]
        good = np.isfinite(a) & np.isfinite(b)
        if not good.any():
            per_metric[m] = {"max_rel_diff": None, "note": "no sample with both values"}
            continue
        diff = np.abs(a - b)
        denom = np.maximum(np.abs(b), np.finfo(float).tiny)
        rel = np.where(good, diff / denom, -np.inf)
        i_max = int(np.argmax(rel))
        spread = float(np.ptp(b[good]))
        per_metric[m] = {
            "max_rel_diff": float(rel[i_max]),
            "max_abs_diff": float(np.max(np.where(good, diff, -np.inf))),
            "max_diff_over_range": (float(np.max(diff[good])) / spread) if spread > 0 else None,
            "worst_sample": _param_text(names, chosen[i_max]),
        }
    report.update(samples=len(chosen), simulated=simulated, wall_s=time.perf_counter() - t0,
                  metrics=per_metric,
                  max_rel_diff=max((v["max_rel_diff"] for v in per_metric.values()
                                    if v.get("max_rel_diff") is not None), default=None),
                  failed_reference_runs=failed_ref)
    return report, simulated


# ---------------------------------------------------------------------------- the stage
def run_sensitivity(study, stage, out: str | Path, runner, progress: bool = True, resume: bool | None = None,
                    accuracy_samples: int = 20) -> dict:
    """Morris screening and/or Sobol indices of ``stage.outputs`` over ``stage.parameters``.

    ``runner`` is the study's :class:`fmusa.sweep.StudyRunner` (its evaluator's ``workers`` and
    ``scheduler`` are used; its ``simulated`` counter is increased). ``resume`` None follows the runner
    (see :func:`_resume_flag`). Returns ``{"summary": {...}, "morris": DataFrame, "sobol": DataFrame}``;
    the summary has, per method, ``{metric: {parameter: {mu_star, sigma, mu_star_conf, mu}}}`` (Morris)
    or ``{S1, S1_conf, ST, ST_conf}`` (Sobol), and ``runs``, ``failed``, ``simulated``, ``wall_s``,
    ``runs_per_s``, ``accuracy_check``, ``errors``, ``failed_runs``, ``meta``.
    """
    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    resume = _resume_flag(runner, resume)
    names = list(stage.parameters)
    metrics = list(study.metrics)          # the store keeps every metric; SALib analyses stage.outputs
    outputs = list(stage.outputs)
    problem = salib_problem(stage)
    ev_workers = getattr(getattr(runner, "evaluator", None), "workers", None) or study.execution.workers
    ev_scheduler = getattr(getattr(runner, "evaluator", None), "scheduler", None) or study.execution.scheduler
    spec = sensitivity_spec(study, stage, base=getattr(runner, "spec", None))

    X: dict[str, np.ndarray] = {}
    keys: dict[str, list[tuple]] = {}
    for method in stage.methods:
        X[method] = draw_samples(stage, method, problem)
        keys[method] = _keys(to_physical(stage, X[method]))

    store = RunStore(out / RUNS_FILE, names, metrics, resume=resume)
    simulated = 0
    try:
        t_eval = time.perf_counter()
        with _evaluator(spec, runner, study) as evaluator:
            for method in stage.methods:
                simulated += evaluate_keys(store, evaluator, keys[method], method, progress)
        eval_wall = time.perf_counter() - t_eval

        summary: dict[str, Any] = {}
        frames: dict[str, pd.DataFrame] = {}
        errors: dict[str, dict[str, str]] = {}
        failed_all: dict[tuple, dict] = {}
        out_idx = [metrics.index(m) for m in outputs]
        for method in stage.methods:
            Y, failed = _collect(store, keys[method], metrics)
            for row in failed:
                failed_all.setdefault(RunStore.key([row[n] for n in names]), row)
            Y = Y[:, out_idx]
            bad = ~np.isfinite(Y)
            good_cols = [j for j in range(len(outputs)) if not bad[:, j].any()]
            for j in range(len(outputs)):
                if bad[:, j].any():
                    rows = np.flatnonzero(bad[:, j])
                    distinct = list(dict.fromkeys(keys[method][i] for i in rows))
                    shown = []
                    for k in distinct[:_SHOW]:
                        rec = store.get(k)
                        why = _reason(rec["message"]) if rec["status"] != "ok" else f"{outputs[j]} is NaN"
                        shown.append(f"{_param_text(names, k)}: {why}")
                    msg = (f"{method}: {len(rows)} of {len(Y)} samples ({len(distinct)} distinct parameter "
                           f"sets) have no value for metric '{outputs[j]}' (failed runs or NaN), and SALib "
                           f"needs every sample, so the {method} indices of '{outputs[j]}' are not "
                           f"computed. Failing parameter sets"
                           f"{' (first ' + str(_SHOW) + ')' if len(distinct) > _SHOW else ''}: "
                           + "; ".join(shown))
                    errors.setdefault(method, {})[outputs[j]] = msg
                    warnings.warn(msg, RuntimeWarning, stacklevel=2)
            ok_names = [outputs[j] for j in good_cols]
            Yg = Y[:, good_cols]
            if method == "morris":
                summary[method], rows = _analyse_morris(problem, X[method], Yg, ok_names, stage.seed)
                cols = ["metric", "parameter", "mu_star", "sigma", "mu_star_conf", "mu"]
            else:
                summary[method], rows = _analyse_sobol(problem, Yg, ok_names, stage.seed)
                cols = ["metric", "parameter", "S1", "S1_conf", "ST", "ST_conf"]
            frames[method] = pd.DataFrame(rows, columns=cols)
            frames[method].to_csv(out / f"sensitivity_{method}.csv", index=False)

        all_keys = list(dict.fromkeys(k for m in stage.methods for k in keys[m]))
        acc, acc_sim = accuracy_check(study, stage, spec, store, all_keys, out, metrics, runner, resume,
                                      samples=accuracy_samples)
    finally:
        store.close()
    if hasattr(runner, "simulated"):
        runner.simulated += simulated + acc_sim

    failed_list = [{"parameters": {n: float(r[n]) for n in names}, "message": _reason(r["message"], 1000)}
                   for r in list(failed_all.values())[:_MAX_FAILED_LISTED]]
    summary.update(
        runs=len(all_keys),
        samples={m: int(len(keys[m])) for m in stage.methods},
        failed=len(failed_all),
        failed_runs=failed_list,
        errors=errors,
        simulated=simulated,
        eval_wall_s=eval_wall,
        runs_per_s=(simulated / eval_wall) if simulated and eval_wall > 0 else None,
        wall_s=time.perf_counter() - t0,
        accuracy_check=acc,
        workers=ev_workers or None,
        scheduler=ev_scheduler,
        resumed=resume,
        meta={
            "n": stage.n, "morris_trajectories": stage.morris_trajectories, "morris_levels": MORRIS_LEVELS,
            "seed": stage.seed, "calc_second_order": False,
            "fixed": {k: v for k, v in study.fixed.items()},
            "inputs": dict(study.scenario.inputs), "stop_time": study.scenario.stop_time,
            "metrics": {m: {"unit": study.metrics[m].unit, "description": study.metrics[m].description,
                            "output": study.metrics[m].output, "reduce": study.metrics[m].reduce}
                        for m in outputs},
            "parameters": {p.name: {"variable": p.variable, "unit": p.unit, "distribution": p.distribution,
                                    "bounds": [float(b) for b in p.bounds]}
                           for p in stage.parameters.values()},
        },
    )
    result = {"summary": summary}
    for m in ("morris", "sobol"):
        result[m] = frames.get(m, pd.DataFrame())
    return result


# ---------------------------------------------------------------------------- figures
def _tables(result: Mapping) -> tuple[dict, dict]:
    """(summary, meta) from run_sensitivity's result or from its summary (e.g. summary.json)."""
    summary = result.get("summary", result)
    return summary, summary.get("meta", {})


def _unit(meta: Mapping, metric: str) -> str:
    u = meta.get("metrics", {}).get(metric, {}).get("unit", "")
    return u or "–"


def plot_sensitivity(result: Mapping, figdir: str | Path) -> list[Path]:
    """``sensitivity_morris.png`` (μ* against σ per metric, points labelled with the parameter) and
    ``sensitivity_sobol.png`` (S1 and ST per parameter per metric with their 95 % confidence
    intervals) in ``figdir``. ``result`` is run_sensitivity's result or its summary."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary, meta = _tables(result)
    figdir = Path(figdir)
    figdir.mkdir(parents=True, exist_ok=True)
    paths: list[Path] = []

    def grid(n):
        ncols = 2 if n > 1 else 1
        return math.ceil(n / ncols), ncols

    morris = summary.get("morris") or {}
    if morris:
        metrics = list(morris)
        nr, nc = grid(len(metrics))
        fig, axes = plt.subplots(nr, nc, figsize=(6.4 * nc, 4.6 * nr), squeeze=False)
        for ax, metric in zip(axes.flat, metrics):
            tab = morris[metric]
            names = list(tab)
            mu = np.array([tab[n]["mu_star"] or 0.0 for n in names])
            sg = np.array([tab[n]["sigma"] or 0.0 for n in names])
            ci = np.array([tab[n]["mu_star_conf"] or 0.0 for n in names])
            ax.errorbar(mu, sg, xerr=ci, fmt="o", ms=5, color="C0", ecolor="0.6", elinewidth=1, capsize=2)
            top = max(float(mu.max()), float(sg.max()), 1e-300)
            ax.plot([0, top * 1.2], [0, top * 1.2], ls="--", lw=0.8, color="0.5", label="σ = μ*")
            thresh = 0.03 * top
            minor = []
            for n, x, y in zip(names, mu, sg):
                if x >= thresh or y >= thresh:
                    ax.annotate(n, (x, y), xytext=(4, 4), textcoords="offset points", fontsize=8.5,
                                color="C3")
                else:
                    minor.append(n)
            u = _unit(meta, metric)
            desc = meta.get("metrics", {}).get(metric, {}).get("description", "")
            title = f"{metric}" + (f": {desc}" if desc else "")
            if minor:
                title += "\n" + textwrap.fill("< 3 % of the largest: " + ", ".join(minor), 95)
            ax.set_title(title, fontsize=9)
            ax.set_xlabel(f"μ* (mean |elementary effect|) [{u}]")
            ax.set_ylabel(f"σ (std. of elementary effects) [{u}]")
            ax.set_xlim(left=0, right=1.25 * top)      # same scale on both axes: σ/μ* is the slope
            ax.set_ylim(bottom=0, top=1.25 * top)
            ax.ticklabel_format(style="sci", scilimits=(-3, 3), axis="both")
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7, loc="upper left")
        for ax in axes.flat[len(metrics):]:
            ax.set_visible(False)
        levels = meta.get("morris_levels", MORRIS_LEVELS)
        step = f"{levels / (2 * (levels - 1)):.3g}" if isinstance(levels, int) and levels > 1 else "Δ"
        fig.suptitle(f"Morris screening ({meta.get('morris_trajectories', '?')} trajectories, {levels} levels): "
                     f"change of the metric per step of {step} × the input's range (log10 range for "
                     f"log-uniform inputs); bars: 95 % CI of μ*", fontsize=10)
        fig.tight_layout(rect=(0, 0, 1, 0.97))
        p = figdir / "sensitivity_morris.png"
        fig.savefig(p, dpi=130)
        plt.close(fig)
        paths.append(p)

    sobol = summary.get("sobol") or {}
    if sobol:
        metrics = list(sobol)
        nr, nc = grid(len(metrics))
        fig, axes = plt.subplots(nr, nc, figsize=(7.2 * nc, 3.6 * nr), squeeze=False)
        for ax, metric in zip(axes.flat, metrics):
            tab = sobol[metric]
            names = list(tab)
            xs = np.arange(len(names))

            def col(k):
                return np.array([tab[n][k] if tab[n][k] is not None else np.nan for n in names])
            w = 0.38
            ax.bar(xs - w / 2, col("S1"), w, yerr=col("S1_conf"), capsize=2, color="C0", label="S1 (first order)",
                   error_kw={"elinewidth": 0.8})
            ax.bar(xs + w / 2, col("ST"), w, yerr=col("ST_conf"), capsize=2, color="C1", label="ST (total)",
                   error_kw={"elinewidth": 0.8})
            ax.axhline(0, color="k", lw=0.6)
            ax.set_xticks(xs)
            ax.set_xticklabels(names, rotation=60, ha="right", fontsize=8)
            n_force = sum(1 for n in names if n[:2] in ("c_", "d_"))
            if 0 < n_force < len(names):   # force-element parameters | mass properties
                ax.axvline(n_force - 0.5, color="0.6", lw=0.8, ls=":")
            ax.set_ylabel("Sobol index [–] (share of variance)")
            u = _unit(meta, metric)
            desc = meta.get("metrics", {}).get(metric, {}).get("description", "")
            ax.set_title(f"{metric} [{u}]" + (f": {desc}" if desc else ""), fontsize=9.5)
            hi = np.nanmax(np.concatenate([col("ST") + np.nan_to_num(col("ST_conf")), [1.0]]))
            lo = np.nanmin(np.concatenate([col("S1") - np.nan_to_num(col("S1_conf")), [0.0]]))
            ax.set_ylim(max(lo - 0.05, -0.3), min(hi + 0.05, 1.5))
            ax.grid(axis="y", alpha=0.3)
            ax.legend(fontsize=7, loc="upper right")
        for ax in axes.flat[len(metrics):]:
            ax.set_visible(False)
        samples = (summary.get("samples") or {}).get("sobol", "?")
        fig.suptitle(f"Sobol indices (N = {meta.get('n', '?')}, {samples} runs, no second order; "
                     f"bars: 95 % confidence intervals)", fontsize=10)
        fig.tight_layout(rect=(0, 0, 1, 0.97))
        p = figdir / "sensitivity_sobol.png"
        fig.savefig(p, dpi=130)
        plt.close(fig)
        paths.append(p)
    return paths
