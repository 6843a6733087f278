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
sensitivities, whose length is at most ``||b||``; a standard error is ``s`` along the same direction).

When ``z`` is at most :data:`MAX_SHIFT_SE`, no parameter can move by more than one standard error, and that is all
the check costs: one run per model and averaged test. When it is more (one block far off, ``|b| > s``, is enough,
as is a small bias on many blocks), the bound is the worst case (the bias all along one parameter's sensitivity),
so the check finds how far each parameter moves, to first order: ``dx = J+ b`` with the Jacobian of the fit at its
optimum (:func:`parameter_shifts`: k more runs, or one with the FMU's sensitivities), in the standard errors of
the fit's own 95 % intervals. A warning is given when a parameter moves by more than :data:`MAX_SHIFT_SE` standard
error: its 95 % interval then covers the value every sample would give about 83 % of the time or less, not 95 %.

Measured against fits to every sample (the first-order shift is 75-87 % of the difference of the two fits):
Mass_Damper (attached) in blocks of 2, the damping 31.7 against 22.3 N·s/m, the check +7.0 (1.7 standard errors);
ScrewVertebra's synthetic backlash under a force drive at the default 300 points (blocks of 3), the damping 158
against 188 N·s/m, the check -26 (4.4), and 351 against 416, -51 (3.6); its friction under a displacement drive,
the pre-slip 11.5 against 9.9 µm, +1.3 (5.4). No warning: its damage (0.3 standard errors at most), a shear test of
data/shear-c67 at 1 mm/s in blocks of 6 (z <= 0.3).

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

from fmusa.diagnose import motion as mo
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
    original samples (plus, with effects attached, the coupled runner's one reuse check), and where the bound z
    passes :data:`MAX_SHIFT_SE` the Jacobian of :func:`parameter_shifts`; every run taken from ``budget``.

    Returns ``{"made", "why", "tests", "models": {label: {"params", "rmse", "shift_se" (z), "tests": [bias_of ...],
    "parameters" (parameter_shifts, or None), "max_shift_se"}},
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
            held = {k: params[k] for k in (getattr(fit, "held", None) or {}) if k in params}
            free = {k: v for k, v in params.items() if k not in held}
            runner = make_runner(fmu, drive, list(free), held, interface)
            runner.stage = "check"
            if reuse is not None:       # the coupled runs' reuse check: once per process and FMU binaries
                runner.reuse, runner.fresh_binary = reuse
            try:
                at_samples = runner.predict(list(free.values()), [original_experiment(e) for e in avg])
                preds = list(getattr(fit, "predictions", None) or [])
                if len(preds) != len(experiments) or any(len(preds[index[e.name]]) != e.n for e in avg):
                    at_blocks = runner.predict(list(free.values()), avg)
                else:
                    at_blocks = [preds[index[e.name]] for e in avg]
                tests = [bias_of(e, a, b, fit.rmse) for e, a, b in zip(avg, at_samples, at_blocks)]
                z = float(math.sqrt(sum(r["shift_se"] ** 2 for r in tests)))
                shifts = None
                if z > MAX_SHIFT_SE:      # the bound allows a shift past the limit: how far each parameter moves
                    bias = {e.name: e.meta["blocks"].mean(a) - np.asarray(b, float)
                            for e, a, b in zip(avg, at_samples, at_blocks)}
                    try:
                        shifts = parameter_shifts(runner, fit, free, drive, interface, experiments, bias)
                    except (rb.BudgetExhausted, KeyboardInterrupt):
                        raise
                    except Exception:  # noqa: BLE001 - a Jacobian that cannot be had: the bound z stands alone
                        shifts = None
            finally:
                out["runs"] += sum(runner.runs.values())
                out["rounds"] += sum((getattr(runner, "rounds", None) or runner.runs).values())
                if getattr(runner, "reuse", ""):
                    reuse = (runner.reuse, runner.fresh_binary)
                runner.close()
            out["models"][label] = {"params": params, "rmse": float(fit.rmse), "shift_se": z, "tests": tests,
                                    "parameters": shifts,
                                    "max_shift_se": (max((abs(v["shift_se"]) for v in shifts.values()), default=0.0)
                                                     if shifts is not None else z)}
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


def parameter_shifts(runner, fit, free: dict, drive: str, interface: ModelInterface, experiments: Sequence,
                     bias: Mapping[str, np.ndarray]) -> dict | None:
    """How far the averaging's bias moves each fitted parameter, to first order: least squares moves the optimum
    by ``dx = J+ b`` (J the Jacobian of the scaled residuals on the optimiser's scale at the fit, the same finite
    differences as the fit's, k runs or one with the FMU's sensitivities; b the bias, 0 on tests not averaged).
    Per parameter: its value, the shift in its units and relative, and the shift in standard errors: those of
    the fit's 95 % interval on the side it moves to (interval / 1.96), or Gauss-Newton's where that is not finite.
    None when the fit's model cannot be rebuilt (its parameters are not the catalogue's)."""
    from fmusa.diagnose.calibrate import Residuals, parameter_bounds, response_scale
    from fmusa.diagnose.effects import data_scales, model_parameters, with_bounds

    sc = with_bounds(data_scales(experiments), interface.bounds)
    try:
        params = [p for p in model_parameters(fit.effect, drive, sc) if p.name in free]
    except Exception:  # noqa: BLE001 - a fit of no catalogue model: the bound z stands alone
        return None
    if [p.name for p in params] != list(free):
        return None
    lo, hi = parameter_bounds(params)
    scale = response_scale(drive, sc)
    fn = Residuals(runner, params, list(experiments), [np.ones(e.n, bool) for e in experiments], scale, lo, hi)
    x = np.array([p.to_x(min(max(free[p.name], p.lower), p.upper)) for p in params])
    preds = list(getattr(fit, "predictions", None) or [])
    if len(preds) == len(experiments) and all(len(pr) == e.n for pr, e in zip(preds, experiments)):
        fn._last = (x.copy(), fn._scaled(preds))     # the fit's residuals at x: the differences need no run for them
    J = fn.jac(x)
    b = np.concatenate([bias.get(e.name, np.zeros(e.n)) for e in experiments]) / scale
    if J.shape[0] != b.size or not np.all(np.isfinite(J)):
        return None
    dx = np.linalg.lstsq(J, b, rcond=None)[0]
    s_x = float(fit.rmse) / scale
    cov = np.linalg.pinv(J.T @ J) * s_x ** 2
    out = {}
    for j, p in enumerate(params):
        v = free[p.name]
        target = p.from_x(x[j] + dx[j])
        moved = target - v
        lo_ci, hi_ci = (getattr(fit, "ci95", None) or {}).get(p.name, (float("nan"), float("nan")))
        side = (hi_ci - v) if moved > 0 else (v - lo_ci)
        se_gn = math.sqrt(max(cov[j, j], 0.0))
        se = side / 1.96 if math.isfinite(side) and side > 0 else float("nan")
        shift_gn = dx[j] / se_gn if se_gn > 0 else float("inf") * np.sign(dx[j])
        on_element = (getattr(runner, "on_element", None) or {}).get(p.name)
        out[p.name] = {"fmu_name": f"element.{interface.variable(p.name)}" if on_element else interface.variable(p.name),
                       "value": float(v), "shift": float(moved),
                       # a first-order shift past a bound is no value the parameter can take: said so
                       "beyond": "lower" if target < p.lower else "upper" if target > p.upper else "",
                       "relative": float(moved / v) if v else float("nan"),
                       "shift_se": float(moved / se) if math.isfinite(se) else float(shift_gn),
                       "shift_se_gauss_newton": float(shift_gn)}
    return out


def _size(v: float, drive: str) -> str:
    """A response difference in the report's units: N under a displacement drive, mm under a force drive (of a
    rotational interface N·m and deg)."""
    role = "force" if drive == "displacement" else "displacement"
    shown = mo.natural_unit(mo.channel_unit(role))
    if shown is not None:
        return f"{v * shown[1]:.3g} {shown[0]}"
    return f"{v:.3g} N" if drive == "displacement" else f"{v * 1e3:.3g} mm"


def _moves(m: Mapping) -> str:
    """The parameters a model's bias moves by half a standard error or more (the largest three), e.g.
    "element.d by +45 % (2.1 standard errors)"; '' when the shifts are not known."""
    shifts = m.get("parameters") or {}
    rows = sorted(shifts.values(), key=lambda r: -abs(r["shift_se"]))
    rows = [r for r in rows if abs(r["shift_se"]) >= NAME_SHIFT_SE][:3]

    def how(r):
        size = (f"{r['relative'] * 100:+.2g} %" if r["value"] and math.isfinite(r["relative"])
                else f"{r['shift']:+.3g}")
        return f"{size}, past its {r['beyond']} bound: to that bound at most" if r.get("beyond") else size
    return ", ".join(f"{r['fmu_name']} by {how(r)} ({r['shift_se']:+.2g} standard errors)" for r in rows)


def averaging_warning(check: Mapping, drive: str) -> dict | None:
    """The warning of a check where the averaging moves a fitted parameter by more than :data:`MAX_SHIFT_SE`
    standard errors (to first order; the bound z where the shifts are not known), None when it moves none that
    far: the tests that carry the bias, its size against the residuals, the parameters it moves and how far, and
    the fix (every sample fitted: max_points at least the tests' sample count)."""
    limit = check.get("threshold_se", MAX_SHIFT_SE)
    bad = {lab: m for lab, m in check["models"].items() if m.get("max_shift_se", m["shift_se"]) > limit}
    if not bad:
        return None
    lead = next(iter(bad.values()))
    rows = sorted(lead["tests"], key=lambda r: -r["shift_se"])
    named = [r for r in rows if r["shift_se"] >= NAME_SHIFT_SE] or rows[:1]
    parts = []
    for r in named:
        parts.append(f"'{r['experiment']}' ({r['samples']} samples fitted as {r['points']} block means of up to "
                     f"{r['block']}): the model at every sample, averaged in the same blocks, differs from the model at "
                     f"the block times by up to {r['max_ratio']:.2g} x the residual RMSE ({_size(r['bias_max'], drive)} "
                     f"at t = {r['bias_max_t']:.3g} s; RMS {r['rms_ratio']:.2g} x; residual RMSE "
                     f"{_size(r['rmse'], drive)})")
    models = []
    for lab, m in bad.items():
        moves = _moves(m)
        models.append(f"the {lab}: {moves}" if moves else
                      f"the {lab}: a parameter by up to {m['shift_se']:.2g} standard errors (a bound)")
    n = max(r["samples"] for r in named)
    text = (f"block averaging: the response is not close to a straight line within the blocks of "
            f"{'test' if len(named) == 1 else 'tests'} " + "; ".join(parts) + ". The data's block means and the "
            f"model at the block times differ even where the model is right, and the fit takes the difference for "
            f"physics; to first order it moves " + "; ".join(models) + f" (the check's limit: {limit:g} standard "
            f"error). Fit every sample: max_points at least {n} (`max_points: {n}` under `tests:` in the study file, "
            f"or `--max-points {n}`).")
    return {"kind": "averaging", "message": text, "fix": f"--max-points {n}", "max_points": n,
            "experiments": [r["experiment"] for r in named],
            "shift_se": {lab: m.get("max_shift_se", m["shift_se"]) for lab, m in bad.items()}}
