"""Whether block averaging biased a diagnosis: the fitted model run once at every original sample.

A test longer than ``max_points`` samples is fitted as block means (:func:`fmusa.diagnose.measured.downsample`),
the model run at each block's mean time under the block's mean drive. That is the block's mean response only
where the response is close to a straight line within a block. Where it is not (a mass ringing at 19.5 Hz
after each kink of a force drive sampled at 40 Hz, averaged in blocks of 2), the data's block means and the
model at the block times differ even when the model is the truth, and the fit takes the difference for
physics (damping, friction). The fit's residuals cannot show it: the fit has absorbed it.

:func:`check_averaging` runs the fitted model (the final one and the baseline) once per averaged test at the
original samples under the original drive (kept in ``meta['blocks']``), averages that response in the same
blocks, and compares it with the fit's own prediction at the block times: their difference ``b`` is the bias the
averaging puts into the data, seen through the model. Against the fit's residual RMSE ``s`` (the noise as the
fit sees it), ``z = ||b|| / s`` bounds how far the bias can move any fitted parameter, or any combination of
them, in its standard errors (least squares moves the estimate by the projection of ``b`` onto the model's
sensitivities, whose length is at most ``||b||``; a standard error is ``s`` along the same direction). A
warning is given when ``z`` > :data:`MAX_SHIFT_SE`: a parameter may then be off by more than one standard error
(its 95 % interval would cover the truth about 83 % of the time, or less, not 95 %). The bound is the worst
case (the bias all along one parameter's sensitivity); it is what can be checked with one run per test, with no
Jacobian. One block far off (``|b| > s``) is enough, as is a small bias on many blocks.

    from fmusa.diagnose.averaging import check_averaging
    check = check_averaging(fmu, "force", interface, {"baseline": base, "final": final}, experiments)
    check["warnings"]       # [] or one warning naming the tests, the bias against the residuals and the fix
"""
from __future__ import annotations

import hashlib
import json
import math
import time
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np

from fmusa.diagnose.interface import ModelInterface
from fmusa.diagnose.measured import Blocks, Experiment

__all__ = ["MAX_SHIFT_SE", "averaged", "original_experiment", "bias_of", "check_averaging", "averaging_warning"]

#: The check warns when block averaging could move a fitted parameter by more than this many of its standard
#: errors (z = ||bias|| / residual RMSE; see the module's text).
MAX_SHIFT_SE = 1.0
#: A test is named in the warning when its own share reaches this many standard errors (the largest always).
NAME_SHIFT_SE = 0.5


def averaged(e) -> bool:
    """Whether an experiment is block means with its original samples kept (``meta['blocks']``)."""
    return isinstance(getattr(e, "meta", {}).get("blocks"), Blocks)


def original_experiment(e: Experiment) -> Experiment:
    """The experiment at its original samples: the original time and drive; the response is not kept (zeros)."""
    b: Blocks = e.meta["blocks"]
    zero = np.zeros(b.n)
    chans = {"displacement": zero, "force": zero, e.drive: b.drive}
    meta = {k: v for k, v in e.meta.items() if k != "blocks"}
    return Experiment(name=e.name, path=e.path, drive=e.drive, t=b.t, displacement=chans["displacement"],
                      force=chans["force"], meta=dict(meta, downsampled_from=None, block=None))


def bias_of(e: Experiment, at_samples: np.ndarray, at_blocks: np.ndarray, rmse: float) -> dict:
    """The bias of one averaged test under one model: the block means of the model's response at every original
    sample (``at_samples``) less its response at the block times (``at_blocks``), against the fit's residual
    RMSE: its RMS and largest block in RMSEs, and z = ||bias|| / RMSE, the most it can move a parameter in
    standard errors."""
    b: Blocks = e.meta["blocks"]
    diff = b.mean(at_samples) - np.asarray(at_blocks, float)
    s = float(rmse) if rmse and math.isfinite(rmse) and rmse > 0 else float("nan")
    norm = float(np.sqrt(np.sum(diff ** 2)))
    worst = int(np.argmax(np.abs(diff)))
    return {"experiment": e.name, "samples": b.n, "points": int(e.n), "block": int(np.max(b.sizes)),
            "bias_rms": float(np.sqrt(np.mean(diff ** 2))), "bias_max": float(abs(diff[worst])),
            "bias_max_t": float(e.t[worst]), "rmse": s, "rms_ratio": float(np.sqrt(np.mean(diff ** 2))) / s,
            "max_ratio": float(abs(diff[worst])) / s, "shift_se": norm / s}


def _fingerprint(experiments: Sequence, key: str) -> str:
    """The cache key of the check: the diagnosis's data key and the averaged tests' original samples."""
    h = hashlib.sha256(key.encode())
    for e in experiments:
        b = e.meta["blocks"]
        for a in (b.t, b.drive, b.starts, b.weights()):
            h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def _load_cache(path: Path | None, key: str) -> dict:
    if path is None or not path.is_file():
        return {}
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
    except ValueError:
        return {}
    return d.get("models", {}) if d.get("key") == key else {}


def check_averaging(fmu: str, drive: str, interface: ModelInterface, fits: Mapping, experiments: Sequence,
                    budget=None, cache_dir=None, key: str = "") -> dict:
    """The averaging check of the fitted models ``fits`` (label -> :class:`~fmusa.diagnose.calibrate.Fit`, the
    final model first) on every averaged test of ``experiments``: one run per model and averaged test, at the
    original samples (plus, with effects attached, the coupled runner's one reuse check), taken from ``budget``.

    Returns ``{"made", "why", "tests", "models": {label: {"params", "shift_se", "tests": [bias_of ...]}},
    "runs", "rounds", "cached", "wall_s", "cpu_s", "threshold_se", "warnings"}``; ``made`` False (and ``why``)
    when no test was averaged, when the run budget ended or a run failed (no warning then). With ``cache_dir``
    the result is kept in ``averaging.json`` and reused by a rerun on the same data and parameters."""
    from fmusa.diagnose import budget as rb
    from fmusa.diagnose.calibrate import make_runner

    avg = [e for e in experiments if averaged(e)]
    out = {"made": False, "why": "", "tests": [e.name for e in avg], "models": {}, "runs": 0, "rounds": 0,
           "cached": False, "wall_s": 0.0, "cpu_s": 0.0, "threshold_se": MAX_SHIFT_SE, "warnings": []}
    if not avg:
        out["why"] = "no test was block-averaged (every sample fitted)"
        return out
    path = Path(cache_dir) / "averaging.json" if cache_dir else None
    fkey = _fingerprint(avg, key)
    cached = _load_cache(path, fkey)
    index = {e.name: i for i, e in enumerate(experiments)}
    w0, c0 = time.perf_counter(), time.process_time()
    old = rb.set_current(budget) if budget is not None else None
    reuse = None
    try:
        for label, fit in fits.items():
            params = {k: float(v) for k, v in fit.params.items()}
            hit = cached.get(label)
            if hit and hit.get("params") == params:
                out["models"][label] = hit
                out["cached"] = True
                continue
            runner = make_runner(fmu, drive, list(params), {}, interface)
            runner.stage = "check"
            if reuse is not None:       # the coupled runs' reuse check: once per process and FMU binaries
                runner.reuse, runner.fresh_binary = reuse
            try:
                at_samples = runner.predict(list(params.values()), [original_experiment(e) for e in avg])
                preds = list(getattr(fit, "predictions", None) or [])
                if len(preds) != len(experiments) or any(len(preds[index[e.name]]) != e.n for e in avg):
                    at_blocks = runner.predict(list(params.values()), avg)
                else:
                    at_blocks = [preds[index[e.name]] for e in avg]
            finally:
                out["runs"] += sum(runner.runs.values())
                out["rounds"] += sum((getattr(runner, "rounds", None) or runner.runs).values())
                if getattr(runner, "reuse", ""):
                    reuse = (runner.reuse, runner.fresh_binary)
                runner.close()
            tests = [bias_of(e, s, b, fit.rmse) for e, s, b in zip(avg, at_samples, at_blocks)]
            out["models"][label] = {"params": params, "rmse": float(fit.rmse),
                                    "shift_se": float(math.sqrt(sum(r["shift_se"] ** 2 for r in tests))),
                                    "tests": tests}
        out["made"] = True
    except rb.BudgetExhausted:
        out["why"] = "the run budget ended before the check's runs (allow more runs: --max-runs)"
    except RuntimeError as exc:       # a failed run: the fits stand, the check says why it was not made
        out["why"] = f"a run at the original samples failed: {exc}"
    finally:
        if budget is not None:
            rb.set_current(old)
    out["wall_s"] = time.perf_counter() - w0
    out["cpu_s"] = time.process_time() - c0
    if out["made"] and path is not None and out["runs"]:
        from fmusa.files import atomic_write

        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, json.dumps({"key": fkey, "models": out["models"]}))
    if out["made"]:
        w = averaging_warning(out, drive)
        out["warnings"] = [w] if w else []
    return out


def _size(v: float, drive: str) -> str:
    """A response difference in the report's units: N under a displacement drive, mm under a force drive."""
    return f"{v:.3g} N" if drive == "displacement" else f"{v * 1e3:.3g} mm"


def averaging_warning(check: Mapping, drive: str) -> dict | None:
    """The warning of a check where a model's z passed :data:`MAX_SHIFT_SE` (None when none did): the tests that
    carry it, the bias against the residuals, how far it can move a parameter, and the fix (every sample
    fitted: max_points at least the tests' sample count)."""
    bad = {lab: m for lab, m in check["models"].items() if m["shift_se"] > check.get("threshold_se", MAX_SHIFT_SE)}
    if not bad:
        return None
    lead_label, lead = next(iter(bad.items()))
    rows = sorted(lead["tests"], key=lambda r: -r["shift_se"])
    named = [r for r in rows if r["shift_se"] >= NAME_SHIFT_SE] or rows[:1]
    parts = []
    for r in named:
        parts.append(f"'{r['experiment']}' ({r['samples']} samples fitted as {r['points']} block means of up to "
                     f"{r['block']}): the block means of the model's response at every sample differ from its "
                     f"response at the block times by {r['max_ratio']:.2g} x the residual RMSE at most "
                     f"({_size(r['bias_max'], drive)} at t = {r['bias_max_t']:.3g} s; RMS {r['rms_ratio']:.2g} x, "
                     f"residual RMSE {_size(r['rmse'], drive)})")
    models = "; ".join(f"of the {lab} by up to {m['shift_se']:.2g}" for lab, m in bad.items())
    n = max(r["samples"] for r in named)
    text = (f"block averaging: the response is not close to a straight line within the blocks of "
            f"{'test' if len(named) == 1 else 'tests'} " + "; ".join(parts) + ". The data's block means and the "
            f"model at the block times differ even where the model is right, and the fit takes the difference for "
            f"physics: it can move a fitted parameter {models} standard errors (the check's limit is "
            f"{check.get('threshold_se', MAX_SHIFT_SE):g}). Fit every sample: max_points at least {n} "
            f"(`max_points: {n}` under `tests:` in the study file, or `--max-points {n}`).")
    return {"kind": "averaging", "message": text, "fix": f"--max-points {n}", "max_points": n,
            "experiments": [r["experiment"] for r in named],
            "shift_se": {lab: m["shift_se"] for lab, m in bad.items()}}
