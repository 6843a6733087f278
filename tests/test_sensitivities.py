"""The FMU's forward sensitivities (sens_p[k] selects a parameter, sens_<output>[k] is the output's derivative by it)
against paths that do not share their code, and the diagnosis's least-squares Jacobian taken from them.

- The axial spring-damper under the ramp load: d y / d c_y and d y / d d_y against the derivatives of the exact
  closed form (tests/reference.py, differentiated in 40-digit arithmetic), d y / d F_max = y / F_max.
- Every effect, force- and motion-driven: against central differences of fresh fmpy runs of the FMU without
  sensitivities (rtol 1e-10); the states of a run with sensitivities are bit for bit those of one without.
- A bad selection is refused, naming sens_p[k].
- Calibration: with the sensitivities, one FMU run per residual evaluation gives the Jacobian too (no run for
  it), and the fit lands where the finite-difference fit does.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fmpy import read_model_description, simulate_fmu

from reference import MP, Axial

STOP = 2.0
T = np.linspace(0.0, STOP, 81)

#: per effect, parameters of a clearly active effect (force drive peaks near 1.3 mm at c_y = 2e5 N/m)
EFFECTS = {
    "none": {},
    "nonlinear_stiffness": {"nl_ratio": 2.5, "nl_y_b": 4e-4},
    "coulomb_friction": {"fric_F": 25.0, "fric_x": 5e-5},
    "yield_softening": {"yield_ratio": 0.3, "yield_F": 120.0},
    "viscoelastic_relaxation": {"ve_k": 1e5, "ve_tau": 0.3},
    "backlash_gap": {"gap": 1e-4},
    "interface_damage": {"dmg_y0": 4e-4, "dmg_rate": 3000.0, "dmg_F_res": 50.0},
    "sensor_offset": {},
}
#: the cases `make test` runs (the rest run in `make slow`)
QUICK = {("nonlinear_stiffness", "force"), ("coulomb_friction", "displacement")}


def _vrs(fmu) -> dict[str, int]:
    return {v.name: v.valueReference for v in read_model_description(str(fmu)).modelVariables}


def test_axial_sensitivities_match_the_closed_form(fmu_path):
    m, c, d, F, tr = 0.00029, 823224.0, 488.0, 411.0, 0.05
    vr = _vrs(fmu_path)
    res = simulate_fmu(str(fmu_path), stop_time=0.2, output_interval=2e-3,
                       start_values={"c_y": c, "d_y": d, "F_max": F, "t_ramp": tr, "sens_p[1]": vr["c_y"],
                                     "sens_p[2]": vr["d_y"], "sens_p[3]": vr["F_max"]},
                       output=["y_meas", "sens_y_meas[1]", "sens_y_meas[2]", "sens_y_meas[3]"])
    t = res["time"]

    def y(cc, dd):
        ax = Axial(m, cc, dd, F, tr)
        return [ax.eval_mp(float(ti))[0] for ti in t]

    h = MP.mpf("1e-15")
    c_, d_ = MP.mpf(c), MP.mpf(d)
    exact = {
        "c_y": [float((a - b) / (2 * h * c_)) for a, b in zip(y(c_ * (1 + h), d_), y(c_ * (1 - h), d_))],
        "d_y": [float((a - b) / (2 * h * d_)) for a, b in zip(y(c_, d_ * (1 + h)), y(c_, d_ * (1 - h)))],
        "F_max": [float(v) / F for v in y(c_, d_)],
    }
    # measured: 9e-11, 8e-9 and 1.4e-14 of the largest sensitivity (F_max's, exact but for rounding: the solver takes
    # the sensitivity equations' rate by a forward difference)
    for k, (name, tol) in enumerate((("c_y", 1e-8), ("d_y", 1e-6), ("F_max", 1e-12)), start=1):
        ex = np.array(exact[name])
        err = np.max(np.abs(res[f"sens_y_meas[{k}]"] - ex)) / np.max(np.abs(ex))
        assert err <= tol, f"d y / d {name}: {err:.2e} of its largest value off the closed form"
    assert np.max(np.abs(ex)) > 0


def _drive(drive: str):
    """The FMU's own drives (fmpy holds an input constant over a communication step): force-driven, the load
    ramped to 250 N over 0.5 s, held, unloaded from 1 s; motion-driven, a pull at 1.5 mm/s."""
    if drive == "force":
        return {"mode": 1, "F_max": 250.0, "t_ramp": 0.5, "unload": True, "t_unload": 1.0}, "y_meas"
    return {"mode": 2, "use_y_in": False, "v_pull": 1.5e-3}, "F_meas"


def _run(fmu, values: dict, sets: dict, outputs: list[str], rtol: float) -> dict:
    return simulate_fmu(str(fmu), stop_time=STOP, output_interval=T[1] - T[0], output=outputs,
                        start_values={**sets, "monitors": False, "rtol": rtol, **values})


@pytest.mark.parametrize("effect,drive", [
    pytest.param(e, dr, marks=() if (e, dr) in QUICK else pytest.mark.slow)
    for e in EFFECTS for dr in ("force", "displacement")])
def test_sensitivities_match_central_differences_of_fresh_runs(fmu_path, effect, drive):
    sets, out = _drive(drive)
    params = {"c_y": 2e5, "d_y": 100.0, **EFFECTS[effect]}
    if effect == "sensor_offset":
        params["y_offset" if drive == "force" else "F_offset"] = 1e-5 if drive == "force" else 5.0
    names = list(params)
    vr = _vrs(fmu_path)
    select = {f"sens_p[{k + 1}]": vr[n] for k, n in enumerate(names)}
    sens = _run(fmu_path, {**params, **select}, sets, [out] + [f"sens_{out}[{k + 1}]" for k in range(len(names))],
                1e-8)
    plain = _run(fmu_path, params, sets, [out], 1e-8)
    if effect not in ("none", "sensor_offset"):   # the full variant both times: the states see no sensitivities
        assert np.array_equal(sens[out], plain[out])
    for k, n in enumerate(names):
        h = 1e-4 * abs(params[n])
        up = _run(fmu_path, {**params, n: params[n] + h}, sets, [out], 1e-10)[out]
        down = _run(fmu_path, {**params, n: params[n] - h}, sets, [out], 1e-10)[out]
        fd = (up - down) / (2 * h)
        scale = np.max(np.abs(fd))
        # a parameter that moves the output by less than 1e-6 of its size would make the check vacuous
        assert scale * abs(params[n]) > 1e-6 * np.max(np.abs(plain[out])), f"{n} does not move {out}"
        err = np.max(np.abs(sens[f"sens_{out}[{k + 1}]"] - fd)) / scale
        # measured worst: 1e-5 (nl_y_b at its rounded corner: the central difference's own error)
        assert err <= 1e-4, f"{effect}, {drive}: d {out} / d {n} is {err:.2e} of its largest value off"


@pytest.mark.parametrize("name,second,expected", [
    ("mode", None, "Real parameter"), ("rtol", None, "not a solver setting"), ("F_meas", None, "Real parameter"),
    ("c_y", "c_y", "same parameter")])
def test_a_selection_that_cannot_be_differentiated_is_refused(fmu_path, name, second, expected):
    messages: list[str] = []
    vr = _vrs(fmu_path)

    def logger(component, instance, status, category, message):
        messages.append(message.decode() if isinstance(message, bytes) else str(message))

    start = {"sens_p[2]": vr[name]} if second is None else {"sens_p[1]": vr[name], "sens_p[2]": vr[second]}
    with pytest.raises(Exception):
        simulate_fmu(str(fmu_path), stop_time=0.1, start_values=start, logger=logger)
    assert any("sens_p[2]" in m and expected in m for m in messages), messages


@pytest.mark.parametrize("value", [-1e-3, 0.5, float("nan")])
def test_a_sensitivity_tolerance_out_of_range_is_refused(fmu_path, value):
    messages: list[str] = []

    def logger(component, instance, status, category, message):
        messages.append(message.decode() if isinstance(message, bytes) else str(message))

    with pytest.raises(Exception):
        simulate_fmu(str(fmu_path), stop_time=0.1, start_values={"sens_rtol": value}, logger=logger)
    assert any("sens_rtol" in m and "between 1e-14 and 0.1" in m for m in messages), messages
    vr = _vrs(fmu_path)     # the last variable: the value references before it are those the FMU had without it
    assert vr["sens_rtol"] == max(vr.values())


def test_calibration_takes_its_jacobian_from_the_sensitivities(fmu_path):
    from fmusa.diagnose.calibrate import ModelRunner, calibrate
    from fmusa.diagnose.effects import data_scales
    from fmusa.diagnose.measured import Experiment

    t = np.linspace(0.0, 2.0, 41)
    F = np.interp(t, [0.0, 0.8, 1.2, 2.0], [0.0, 250.0, 250.0, 0.0])
    truth = {"c_y": 2e5, "d_y": 100.0, "nl_ratio": 2.5, "nl_y_b": 4e-4}
    gen = ModelRunner(fmu_path, "force", list(truth))
    try:
        drive = Experiment(name="drive", path=Path("drive.csv"), drive="force", t=t, displacement=0 * t, force=F)
        y = gen.predict(list(truth.values()), [drive])[0]
    finally:
        gen.close()
    exp = Experiment(name="synthetic", path=Path("synthetic.csv"), drive="force", t=t, displacement=y, force=F)
    sc = data_scales([exp])
    fits = {}
    for exact in (True, False):
        model = ModelRunner(fmu_path, "force", list(truth))
        try:
            assert model.has_sensitivities
            model.has_sensitivities = exact
            model._sens_pays = True   # not the timed choice (a force drive's sensitivities cost more than they save)
            fit = calibrate(model, "nonlinear_stiffness", "force", [exp], sc, max_starts=1, max_nfev=25,
                            start={"c_y": 1.5e5, "d_y": 150.0, "nl_ratio": 2.0, "nl_y_b": 3e-4})
            fits[exact] = (fit, dict(model.runs))
        finally:
            model.close()
    (ex, runs_ex), (fd, runs_fd) = fits[True], fits[False]
    # one run per residual evaluation (the Jacobian comes with it) and the final prediction
    assert runs_ex["fit"] == ex.nfev + 1
    assert runs_fd["fit"] > runs_ex["fit"]
    for n, v in truth.items():   # from a start near the truth, both land on it (the rounded corner at nl_y_b too)
        assert ex.params[n] == pytest.approx(v, rel=1e-3), (n, ex.params, fd.params)
        assert fd.params[n] == pytest.approx(v, rel=1e-3), (n, ex.params, fd.params)


def test_an_fmu_without_sensitivities_keeps_the_finite_differences():
    from fmusa.diagnose.calibrate import sensitivity_outputs

    element = Path(__file__).resolve().parents[1] / "dist" / "InterfaceElement.fmu"
    if not element.exists():
        pytest.skip("dist/InterfaceElement.fmu is not built (make fmu)")
    md = read_model_description(str(element))
    outputs = [v.name for v in md.modelVariables if v.causality == "output"]
    params = [v.name for v in md.modelVariables if v.causality == "parameter" and v.type == "Real"][:2]
    assert outputs and params and sensitivity_outputs(md, outputs[0], params) == []


def test_the_sensitivity_outputs_are_found_in_the_model_description(fmu_path):
    from fmusa.diagnose.calibrate import sensitivity_outputs

    md = read_model_description(str(fmu_path))
    assert sensitivity_outputs(md, "F_meas", ["c_y", "d_y"]) == ["sens_F_meas[1]", "sens_F_meas[2]"]
    # more parameters than the FMU offers sensitivities for: the first eight (the others by differences)
    assert sensitivity_outputs(md, "y_meas", ["c_y"] * 9) == [f"sens_y_meas[{k}]" for k in range(1, 9)]
    assert sensitivity_outputs(md, "y_meas", ["c_y", "no_such"]) == []    # a parameter the FMU lacks
    assert sensitivity_outputs(md, "F_pull", ["c_y"]) == []             # an output without them



def test_a_model_with_more_parameters_than_sensitivities_differences_the_rest(fmu_path):
    """Nine parameters (a stiffening, interface damage and a Maxwell branch under a prescribed motion, a chain
    step of a real shear unit): eight columns of the Jacobian from the run's sensitivities, the ninth from one
    more run, where nine finite-difference runs were taken before (a third of that unit's runs). Every column
    agrees with forward differences of fresh runs; the runs are counted."""
    from fmusa.diagnose.calibrate import ModelRunner, Residuals, parameter_bounds, response_scale
    from fmusa.diagnose.effects import data_scales, model_parameters
    from fmusa.diagnose.measured import Experiment

    t = np.linspace(0.0, 1.3, 60)
    y = np.interp(t, [0.0, 1.0, 1.3], [0.0, 1.2e-3, 1.2e-3])
    exp = Experiment(name="synthetic", path=Path("synthetic.csv"), drive="displacement", t=t, displacement=y,
                     force=150.0 * y / 1.2e-3)
    sc = data_scales([exp])
    effect = "nonlinear_stiffness+interface_damage+viscoelastic_relaxation"
    params = model_parameters(effect, "displacement", sc)
    assert len(params) == 9
    lo, hi = parameter_bounds(params)
    x = lo + 0.37 * (hi - lo)
    jacobians, runs = {}, {}
    # the sensitivities (the ninth by the optimiser's differences), the optimiser's differences (a step of 1e-4 on
    # its scale: a fifth of nl_y_b), and differences at a step of 1e-7 as the reference
    for mode, rel_step in (("exact", 1e-4), ("fd", 1e-4), ("reference", 1e-7)):
        model = ModelRunner(fmu_path, "displacement", [p.name for p in params])
        try:
            assert model.has_sensitivities and len(model._sens_outputs) == 8
            model.has_sensitivities = mode == "exact"
            fn = Residuals(model, params, [exp], [np.ones(len(t), bool)], response_scale("displacement", sc), lo, hi,
                           rel_step=rel_step)
            fn(x)
            jacobians[mode] = fn.jac(x)
            runs[mode] = model.runs["fit"]
        finally:
            model.close()
    assert runs["exact"] == 2 and runs["fd"] == 1 + 9, runs    # one run with sensitivities and one difference
    ex, ref = jacobians["exact"], jacobians["reference"]
    for j, p in enumerate(params[:8]):
        err = np.max(np.abs(ex[:, j] - ref[:, j])) / np.max(np.abs(ref[:, j]))
        # measured: 7.6e-9 (d_y) to 1.1e-2 (nl_y_b, the rounded corner), at the sensitivities' tolerance of 1e-3
        assert err <= 3e-2, f"d r / d {p.name}: {err:.2e} of its largest value off the reference differences"
    np.testing.assert_array_equal(ex[:, 8], jacobians["fd"][:, 8])      # the ninth: the optimiser's differences
    assert np.max(np.abs(ex[:, 8] - ref[:, 8])) <= 1e-3 * np.max(np.abs(ref[:, 8]))


def _damage_case():
    """Interface damage under a damper a million times stiffer than the mass (d/m ~ 2e8 1/s), a point an
    optimiser reached in an identifiability cell: the damping's sensitivity misses its tolerance at every sub-step
    of the smallest size. Its sub-step shrank until t + k == t, and the suite hung in one fmi2DoStep."""
    from fmusa.diagnose.measured import Experiment

    t = np.concatenate([np.arange(0.0, 1.77, 0.045), np.arange(1.805, 7.8, 0.08)])
    F = np.interp(t, [0.0, 1.768, 4.593, 6.361], [0.0, 287.0, 287.0, 0.0])
    names = ["c_y", "d_y", "dmg_y0", "dmg_rate", "dmg_F_res"]
    values = [134278.225, 68947.509, 6.488859670560038e-4, 1386.99, 57.408]
    exp = Experiment(name="synthetic", path=Path("synthetic.csv"), drive="force", t=t, displacement=1e-3 * t / 7.8,
                     force=F)
    return names, values, exp


def test_a_column_the_polynomial_scheme_could_not_follow_is_followed_with_the_states(fmu_path):
    """The case above: stepped alone, with the states' motion a polynomial in time, the damping's column missed its
    tolerance at every sub-step of the smallest size (2.6 s a run against 6.5 ms without sensitivities, and finite
    differences were taken); stepped together with the states (the doubled system, fmu/solver.c
    sens_substep_aug) it follows at the sub-step the others take. The states are those of a run without
    sensitivities, every column agrees with central differences of fresh runs, and the timed choice keeps the
    sensitivities for the FMU."""
    from fmusa.diagnose import calibrate
    from fmusa.diagnose.calibrate import ModelRunner

    names, values, exp = _damage_case()
    model = ModelRunner(fmu_path, "force", names)
    try:
        assert model.has_sensitivities
        preds, jacs = model.predict_with_jacobian(values, [exp])
        plain = model.predict(values, [exp])[0]
        np.testing.assert_array_equal(preds[0], plain)
        for j, (n, v) in enumerate(zip(names, values)):
            h = 1e-5 * abs(v)
            fd = (model.predict([*values[:j], v + h, *values[j + 1:]], [exp])[0]
                  - model.predict([*values[:j], v - h, *values[j + 1:]], [exp])[0]) / (2 * h)
            err = np.max(np.abs(jacs[0][:, j] - fd)) / np.max(np.abs(fd))
            # measured: 3e-7 (c_y) to 1e-5 (d_y), at the sensitivities' tolerance of 1e-3
            assert err <= 1e-3, f"d F / d {n}: {err:.2e} of its largest value off central differences"
        calibrate._SENS_PAYS.clear()           # the process's answer for this FMU and drive: not from another test
        assert model.sensitivities_pay(values, [exp]) is True
        assert list(calibrate._SENS_PAYS.values()) == [True]
    finally:
        model.close()


def test_a_failing_run_with_sensitivities_falls_back_to_finite_differences(fmu_path):
    from fmusa.diagnose.calibrate import ModelRunner, Residuals, model_parameters
    from fmusa.diagnose.effects import data_scales
    from fmusa.fmi.info import FMURunError

    class Failing(ModelRunner):
        def predict_with_jacobian(self, values, experiments):
            raise FMURunError("the sensitivities failed")

    names, values, exp = _damage_case()
    values[1] = 100.0
    model = Failing(fmu_path, "force", names)
    try:
        params = [p for p in model_parameters("interface_damage", "force", data_scales([exp])) if p.name in names]
        assert [p.name for p in params] == names
        x = np.array([p.to_x(v) for p, v in zip(params, values)])
        res = Residuals(model, params, [exp], [np.ones(len(exp.t), bool)], 1.0, np.full(len(x), -np.inf),
                        np.full(len(x), np.inf))
        assert res.exact
        f = res(x)
        assert not res.exact and model._sens_pays is False       # finite differences from here on
        plain = model.predict([p.from_x(xi) for p, xi in zip(params, x)], [exp])[0]   # log scale round trip
        np.testing.assert_array_equal(f, plain - exp.response_signal)
        J = res.jac(x)
        assert J.shape == (len(f), len(x)) and np.any(J != 0.0)
    finally:
        model.close()


def test_sensitivities_follow_an_input_that_jumps_at_every_communication_point(fmu_path):
    """fmpy holds an input constant over a communication step, so a force given as an input jumps at every
    communication point. The solver starts a step's columns from the columns' last sub-step where it can
    (fmu/solver.c sens_from_history), which holds only where the inputs go on continuously (fmu/model.c clears it
    at a jump). A slow, lightly damped oscillator (m = 1 kg, c_y = 2e3 N/m) rings after every jump, so the mass's
    column, whose equations carry the force itself (d v'/d m = -(F - F_I)/m^2), and the damping's matter. At the
    diagnosis's tolerance (sens_rtol = 1e-3), against central differences of fresh runs with the same input."""
    names = {"c_y": 2e3, "d_y": 10.0, "m": 1.0, "nl_ratio": 2.5, "nl_y_b": 5e-3}
    vr = _vrs(fmu_path)
    t = np.linspace(0.0, STOP, 41)
    signal = np.array(list(zip(t, np.interp(t, [0.0, 0.5, 1.0, 1.5], [0.0, 25.0, 25.0, 0.0]))),
                      dtype=[("time", np.float64), ("F_ext_y", np.float64)])

    def run(values: dict, outputs: list[str], rtol: float) -> dict:
        return simulate_fmu(str(fmu_path), stop_time=STOP, output_interval=T[1] - T[0], output=outputs,
                            input=signal, start_values={"mode": 1, "F_max": 0.0, "monitors": False, "rtol": rtol,
                                                        **values})

    select = {f"sens_p[{k + 1}]": vr[n] for k, n in enumerate(names)}
    sens = run({**names, **select, "sens_rtol": 1e-3},
               ["y_meas"] + [f"sens_y_meas[{k + 1}]" for k in range(len(names))], 1e-8)
    for k, (n, v) in enumerate(names.items()):
        h = 1e-4 * abs(v)
        fd = (run({**names, n: v + h}, ["y_meas"], 1e-10)["y_meas"]
              - run({**names, n: v - h}, ["y_meas"], 1e-10)["y_meas"]) / (2 * h)
        scale = np.max(np.abs(fd))
        assert scale * abs(v) > 1e-3 * np.max(np.abs(sens["y_meas"])), f"{n} does not move y"
        err = np.max(np.abs(sens[f"sens_y_meas[{k + 1}]"] - fd)) / scale
        # measured: 3.3e-6 (nl_y_b) to 3.2e-3 (d_y); m 1.1e-3 (the solver before sens_from_history: 3.1e-3, 1.1e-3)
        assert err <= 1e-2, f"d y / d {n}: {err:.2e} of its largest value off central differences"
