"""Global sensitivity analysis of a study: Morris screening and Sobol indices (SALib).

Which inputs drive which outputs, over whole ranges rather than around one point. :func:`run_sensitivity`
is the ``sensitivity`` stage of :func:`fmusa.pipeline.sweep.run_study`; the samples and the SALib analyses
are :mod:`fmusa.analysis.sensitivity`, the figures :mod:`fmusa.report.sensitivity_figures`:

1. The SALib problem comes from ``stage.parameters``: a ``uniform`` parameter is sampled within its
   bounds as is, a ``loguniform`` one uniformly in log10 space and transformed back (so SALib sees
   log10 values, the FMU the physical ones).
2. Morris trajectories (``num_levels`` 4) and a Sobol sample (``calc_second_order=False``,
   N·(k + 2) runs) are drawn with ``stage.seed``.
3. Every sample runs through :class:`fmusa.runs.evaluator.Evaluator` (in-process, process pool or Dask, as the
   study's runner: workers, scheduler, isolation, timeout) on its own :class:`~fmusa.runs.spec.PlanSpec`
   (the runner's, with the sensitivity parameters' FMU variables varied instead of the study
   parameters; ``study.fixed``, the scenario's inputs and ``fmu_options`` as in the study) and is written as it
   completes to ``out/sensitivity_runs.csv`` by a :class:`~fmusa.runs.store.RunStore`; a resumed study
   simulates only the samples not in that file.
4. SALib analyses every metric of ``stage.outputs``. SALib needs a value for every sample: a metric
   with a failed run (or a NaN value) is not analysed, and the summary names the failing parameter sets
   (``errors``, ``failed_runs``); rows are never dropped silently.
5. Accuracy check: ``accuracy_samples`` (20) of the samples are run again with ``rtol = 1e-9`` (stored
   in ``out/sensitivity_accuracy.csv``, resumed the same way) and the largest differences of every
   metric are reported.

Only metric arrays are kept (no time series): memory is one small row per run. Workers get the samples in
chunks and send back one RunBatch (arrays) per chunk; the store keeps arrays and writes runs.csv in blocks.

Example::

    import fmusa
    r = fmusa.run_study(fmusa.load_study("studies/six_dof.yaml"), "out/six_dof")
    r.sensitivity["summary"]["sobol"]["x_final"]["c_x"]      # {'S1': ..., 'ST': ...}
"""
from __future__ import annotations

import dataclasses
import time
import warnings
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import pandas as pd

from fmusa.files import atomic_path
from fmusa.runs.evaluator import Evaluator
from fmusa.runs.spec import PlanSpec
from fmusa.fmi.info import default_fmu_path
from fmusa.runs.inflight import track_in_flight
from fmusa.runs.store import RunStore
from fmusa.runs.progress import progress_bar
from fmusa.analysis.sensitivity import MORRIS_LEVELS, analyse_morris, analyse_sobol, draw_samples, salib_problem, to_physical

__all__ = ["run_sensitivity",
           "sensitivity_spec", "REFERENCE_RTOL"]

#: Solver tolerance of the accuracy check's reference runs.
REFERENCE_RTOL = 1e-9
RUNS_FILE = "sensitivity_runs.csv"
ACCURACY_FILE = "sensitivity_accuracy.csv"
#: Parameter sets named per failing metric in its error message; ``failed_runs`` lists up to
#: ``_MAX_FAILED_LISTED`` (every failed run stays in sensitivity_runs.csv).
_SHOW = 5
_MAX_FAILED_LISTED = 50


# ---------------------------------------------------------------------------- problem and samples


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
          "timeout_s": getattr(ev, "timeout_s", study.execution.timeout_s),
          "pool": getattr(ev, "pool_options", None) or study.execution.pool_options(),
          "own": getattr(ev, "own", None)}
    kw.update(overrides)
    return Evaluator(spec, **kw)


def stage_fingerprint(runner, spec: PlanSpec, names: Sequence[str]) -> dict | None:
    """What decides the runs of ``spec`` (the sensitivity parameters' variables, not the study's; the
    reference runs' tolerance), with the FMU digest of the study runner's fingerprint; None for a runner
    without one (its stores are not checked)."""
    base = getattr(runner, "fingerprint", None)
    if base is None:
        return None
    from fmusa.study.plan import spec_fingerprint

    return spec_fingerprint(spec, names, base.get("fmu", ""))


# ---------------------------------------------------------------------------- evaluation
def _keys(P: np.ndarray) -> np.ndarray:
    """The samples' parameter values as the store keys them: a float array, one row per sample."""
    return np.ascontiguousarray(P, dtype=float)


def _distinct(P: np.ndarray) -> np.ndarray:
    """Indices of the first occurrence of every distinct row of ``P`` (as the store keys rows: -0.0 is
    0.0), in order. Rows whose 64-bit hashes all differ are distinct; only otherwise are they compared."""
    P = np.asarray(P, dtype=float)
    n = len(P)
    if not n:
        return np.empty(0, dtype=np.int64)
    mix = np.random.default_rng(1).integers(1, 2**63, size=P.shape[1], dtype=np.uint64) | np.uint64(1)
    h = np.empty(n, dtype=np.uint64)
    for a in range(0, n, 4096):                 # a slice at a time: no second copy of the samples
        x = ((P[a:a + 4096] + 0.0).view(np.uint64) * mix).sum(axis=1, dtype=np.uint64)
        x ^= x >> np.uint64(31)
        x *= np.uint64(0x9E3779B97F4A7C15)
        h[a:a + 4096] = x ^ (x >> np.uint64(29))
    if len(np.unique(h)) == n:
        return np.arange(n)
    Q = np.ascontiguousarray(P) + 0.0
    _, first = np.unique(Q.view(np.dtype((np.void, Q.dtype.itemsize * Q.shape[1]))).ravel(), return_index=True)
    return np.sort(first)


def _first_rows(rows: np.ndarray) -> np.ndarray:
    """Indices of the first occurrence of every distinct stored row in ``rows`` (store rows, -1 for none;
    the store keys a parameter set to one row), in order."""
    rows = np.asarray(rows)
    _, first = np.unique(rows, return_index=True)
    first = np.sort(first)
    return first[rows[first] >= 0]


def evaluate_keys(store: RunStore, evaluator: Evaluator, keys, stage_label: str, progress=None) -> int:
    """Simulate the keys (parameter sets, one per row) the store does not have, each distinct key once;
    the results go to the store in blocks as they arrive. Returns how many ran."""
    P = np.asarray(keys, dtype=float).reshape(len(keys), len(store.params))
    missing = np.flatnonzero(store.rows_of(P) < 0)
    if not len(missing):
        return 0
    todo = P if len(missing) == len(P) else P[missing]
    distinct = _distinct(todo)
    if len(distinct) < len(todo):
        todo = todo[distinct]
    if getattr(evaluator, "marker", None) is not None:    # the label a run under way at a crash is stored under
        evaluator.marker.stage = stage_label
    ids = store.new_ids(len(todo))
    store.reserve(len(todo))

    bar = None
    if progress:
        bar = progress_bar(len(todo), f"sensitivity ({stage_label})", True)
    try:
        evaluator.map_batches((ids, todo), lambda b: store.add_batch(stage_label, b), progress=bar)
    finally:
        if bar is not None:
            bar.close()
    return len(todo)


def _collect(store: RunStore, keys, metrics: Sequence[str]) -> tuple[np.ndarray, list[dict]]:
    """Metric matrix (samples × metrics; NaN where a run failed) and the failed rows."""
    P = np.asarray(keys, dtype=float).reshape(len(keys), len(store.params))
    rows = store.rows_of(P)
    if (rows < 0).any():  # pragma: no cover - evaluate_keys ran every key
        raise RuntimeError(f"sample {tuple(P[np.flatnonzero(rows < 0)[0]])} was not evaluated")
    cols = [store.metrics.index(m) for m in metrics]
    Y = store.metric_matrix(rows)[:, cols]
    ok = store.ok(rows)
    Y[~ok] = np.nan
    bad = np.flatnonzero(~ok)
    failed_rows = list(dict.fromkeys(rows[bad].tolist()))
    return Y, [store.record(r) for r in failed_rows]


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


# ---------------------------------------------------------------------------- accuracy check
def accuracy_check(study, stage, spec: PlanSpec, store: RunStore, keys: Sequence[tuple], out: Path,
                   metrics: Sequence[str], runner, resume: bool, samples: int = 20,
                   reference_rtol: float = REFERENCE_RTOL) -> tuple[dict, int]:
    """Re-run ``samples`` of the (successful) samples with the solver tolerance ``reference_rtol`` and
    compare every metric: (report, runs simulated).

    The tolerance is the FMU parameter ``rtol`` when the study fixes it (our FMU), and the experiment
    tolerance (``fmi2SetupExperiment``, or the model exchange solver's) in any case; our FMU takes the
    smaller of the two."""
    P = np.asarray(keys, dtype=float).reshape(len(keys), len(store.params))
    rows = store.rows_of(P)
    first = _first_rows(rows)
    ok_keys = first[store.ok(rows[first])]          # indices in P of the distinct samples that worked
    study_rtol = dict(study.fixed).get("rtol")
    exp_tol = getattr(spec, "relative_tolerance", None)
    report: dict[str, Any] = {"reference_rtol": reference_rtol,
                              "study_rtol": float(study_rtol) if study_rtol is not None else None,
                              "study_experiment_tolerance": exp_tol,
                              "samples": 0}
    if not len(ok_keys) or samples <= 0:
        report["note"] = "no successful sample to check"
        return report, 0
    if any(p.variable == "rtol" for p in stage.parameters.values()):
        report["note"] = "rtol is a sensitivity parameter; no accuracy check"
        return report, 0
    rng = np.random.default_rng(stage.seed)
    pick = sorted(rng.choice(len(ok_keys), size=min(samples, len(ok_keys)), replace=False).tolist())
    chosen = [RunStore.key(P[ok_keys[i]]) for i in pick]
    override = {"rtol": reference_rtol} if study_rtol is not None else {}
    changes = {}
    if "relative_tolerance" in PlanSpec.__dataclass_fields__:
        changes["relative_tolerance"] = min(reference_rtol, exp_tol) if exp_tol else reference_rtol
    ref_spec = dataclasses.replace(spec, fixed=tuple({**dict(spec.fixed), **override}.items()), **changes)
    report["reference_via"] = (["fixed rtol"] if override else []) + (
        ["experiment tolerance"] if changes else [])
    ref_store = RunStore(out / ACCURACY_FILE, list(stage.parameters), list(metrics), resume=resume,
                         fingerprint=stage_fingerprint(runner, ref_spec, list(stage.parameters)))
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

    ``runner`` is the study's :class:`fmusa.pipeline.sweep.StudyRunner` (its evaluator's ``workers`` and
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
        sample = draw_samples(stage, method, problem)
        keys[method] = _keys(to_physical(stage, sample))
        if method == "morris":      # the Sobol analysis needs the outputs only: no second copy of its sample
            X[method] = sample
        del sample

    fingerprint = stage_fingerprint(runner, spec, names)
    store = RunStore(out / RUNS_FILE, names, metrics, resume=resume, fingerprint=fingerprint,
                     retry_failed=bool(getattr(runner, "retry_failed", False)))
    simulated = batches = 0      # batches: rounds of new runs (the study's count of rounds)
    try:
        t_eval = time.perf_counter()
        with _evaluator(spec, runner, study) as evaluator:
            recovered = track_in_flight(store, evaluator, resume)    # runs a crashed session left under way
            try:
                for method in stage.methods:
                    made = evaluate_keys(store, evaluator, keys[method], method, progress)
                    simulated += made
                    batches += made > 0
            finally:
                evaluator.marker.close()
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
                    distinct = list(dict.fromkeys(RunStore.key(keys[method][i]) for i in rows))
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
                summary[method], rows = analyse_morris(problem, X[method], Yg, ok_names, stage.seed)
                cols = ["metric", "parameter", "mu_star", "sigma", "mu_star_conf", "mu"]
            else:
                summary[method], rows = analyse_sobol(problem, Yg, ok_names, stage.seed)
                cols = ["metric", "parameter", "S1", "S1_conf", "ST", "ST_conf"]
            frames[method] = pd.DataFrame(rows, columns=cols)
            with atomic_path(out / f"sensitivity_{method}.csv") as tmp:
                frames[method].to_csv(tmp, index=False, encoding="utf-8")

        all_keys = keys[stage.methods[0]] if len(stage.methods) == 1 else np.concatenate(
            [keys[m] for m in stage.methods])
        first = _first_rows(store.rows_of(all_keys))
        if len(first) < len(all_keys):
            all_keys = all_keys[first]
        acc, acc_sim = accuracy_check(study, stage, spec, store, all_keys, out, metrics, runner, resume,
                                      samples=accuracy_samples)
    finally:
        store.close()
    if hasattr(runner, "simulated"):
        runner.simulated += simulated + acc_sim
    if hasattr(runner, "rounds"):
        runner.rounds += batches + (acc_sim > 0)
    if hasattr(runner, "asked"):    # every sample point (repeated ones count again) and the reference runs
        runner.asked += sum(len(keys[m]) for m in stage.methods) + acc_sim

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
        **({"recovered_runs": recovered} if recovered else {}),
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


