"""Candidate effects attached to an FMU that cannot be edited: the model coupled to the interface element FMU.

With ``effects: where: attached`` the effects are parameters of the element FMU (the eq. 1 spring-damper and
every effect of the catalogue, under the catalogue's names), which :mod:`fmusa.cosim.master` couples to the
model at the interface the description names (the model's force input, its relative displacement and velocity
outputs). :class:`CoupledRunner` is the :class:`~fmusa.diagnose.calibrate.ModelRunner` of that case: the same
``predict``, each experiment one coupled run, the measured drive fed to the model's drive input.
"""
from __future__ import annotations

import os
from typing import Sequence

import numpy as np

from fmusa.diagnose.interface import ModelInterface

__all__ = ["COUPLED_MAX_WALL_S", "COUPLED_RTOL", "CoupledRunner", "coupling_of"]

#: The coupled runs' integration tolerance (the error estimate of fmusa.cosim's me-grid scheme). Measured on
#: OpenModelica's Mass_Damper with each effect attached, against scipy at rtol 1e-10: the response within
#: 5e-6 of its range (the tests' noise is 1.4e-3 of it), at a fifth of the cost of rtol 1e-6.
COUPLED_RTOL = 1e-4
#: A coupled run's time limit [s of wall time], as a sweep's run has one: past it the run fails, and the fit backs
#: off from that point as from any failed run (a stiff corner that asks for ever smaller steps cannot stall it).
COUPLED_MAX_WALL_S = 60.0


def coupling_of(fmu_path: str | os.PathLike, interface: ModelInterface):
    """The :class:`fmusa.cosim.master.Coupling` of the model FMU and the description's element."""
    from fmusa.cosim.master import Coupling

    att = interface.attached
    return Coupling(model_fmu=fmu_path, element_fmu=att.element_fmu, force_input=att.force_input,
                    displacement_output=att.displacement_output, velocity_output=att.velocity_output,
                    force_sign=att.force_sign, scheme=att.scheme)


def set_on_element(element_fmu, interface: ModelInterface, names: Sequence[str]) -> dict[str, bool]:
    """Per fitted parameter: True when it is set on the element FMU (the element has its variable), False when
    on the model (a baseline of the user's own, e.g. ``spring.c``)."""
    from fmusa.fmi.info import read_fmu_info

    element = read_fmu_info(element_fmu)
    return {n: element.variable(interface.variable(n)) is not None for n in names}


class CoupledRunner:
    """The model FMU coupled to the interface element, driven by the experiments' measured drive.

    ``names``: the fitted parameters (catalogue names); each goes to the element when the element has its
    variable, else to the model (a baseline of the user's own, e.g. ``spring.c``). ``fixed``: catalogue name ->
    value, held in every run. The model's drive settings (``interface.settings``) are set on the model."""

    def __init__(self, fmu_path: str | os.PathLike, drive: str, names: Sequence[str], fixed: dict | None = None,
                 rtol: float = COUPLED_RTOL, interface: ModelInterface | None = None,
                 max_wall_s: float = COUPLED_MAX_WALL_S) -> None:
        from fmusa.cosim.master import check_coupling

        if interface is None or interface.attached is None:
            raise ValueError("CoupledRunner needs a description with effects attached")
        self.interface = interface
        self.coupling = coupling_of(fmu_path, interface)
        check_coupling(self.coupling)
        self.on_element = set_on_element(self.coupling.element(), interface, list(names) + list(fixed or {}))
        self.names = list(names)
        self.fixed = dict(fixed or {})
        self.settings = interface.settings(drive, rtol)
        self.input_name = interface.input_name(drive)
        self.output = interface.output_name(drive)
        self.in_scale = float(interface.input_scale.get(drive, 1.0))
        self.out_scale = float(interface.output_scale.get(drive, 1.0))
        self.rtol = rtol
        self.max_wall_s = max_wall_s
        #: the reuse check's verdict ("" before the first run): instances of the FMUs' binaries loaded once per
        #: process give the same run twice, or every run loads fresh copies (:attr:`fresh_binary`)
        self.reuse = ""
        self.fresh_binary = False
        #: the last coupled run's scheme, FMU calls and wall time, for what a coupled run costs
        self.last = None
        #: coupled runs made, by stage ("fit", "heldout", ...), one per experiment simulated; one lane
        self.runs: dict[str, int] = {}
        self.stage = "fit"
        self.parallel = 1

    def _count(self, n: int) -> None:
        from fmusa.diagnose.budget import take

        take(self.runs, self.stage, n)

    def predict_many(self, points: Sequence[Sequence[float]], experiments: Sequence) -> list:
        """:meth:`predict` at every point, one after another: per point the predictions or the RuntimeError."""
        out: list = []
        for v in points:
            try:
                out.append(self.predict(v, experiments))
            except RuntimeError as exc:
                out.append(exc)
        return out

    def parameter_values(self, values: Sequence[float]) -> tuple[dict, dict]:
        """(model FMU's, element FMU's) variable values of one run: the drive's settings and the parameters."""
        return self._params(values)

    def _params(self, values: Sequence[float]) -> tuple[dict, dict]:
        model, element = dict(self.settings), {}
        for n, v in [*zip(self.names, values), *self.fixed.items()]:
            (element if self.on_element[n] else model)[self.interface.variable(n)] = float(v)
        return model, element

    def predict(self, values: Sequence[float], experiments: Sequence) -> list[np.ndarray]:
        """The response channel of every experiment under the given parameter values (one coupled run each)."""
        from fmusa.cosim.master import simulate_coupled

        self._count(len(experiments))
        model, element = self._params(values)
        out = []
        for e in experiments:
            t = np.asarray(e.t, float)
            u = np.asarray(e.drive_signal, float) / self.in_scale
            name = self.input_name

            def drive(time: float, t=t, u=u, name=name) -> dict[str, float]:
                return {name: float(np.interp(time, t, u))}

            def run(fresh: bool, t=t, drive=drive):
                return simulate_coupled(self.coupling, model, element, float(t[-1]), t, [self.output],
                                        model_inputs=drive, rtol=self.rtol, max_wall_s=self.max_wall_s,
                                        fresh_binary=fresh)

            try:
                res = run(self.fresh_binary)
                if not self.reuse:
                    res = self._check_reuse(res, run)
            except Exception as exc:   # the fit backs off from a failed run (calibrate._residual_fn)
                raise RuntimeError(f"coupled run failed: {exc}") from exc
            self.last = res
            out.append(res.frame[self.output].to_numpy(float) * self.out_scale)
        return out

    def _check_reuse(self, first, run):
        """The reuse check of the first coupled run (as FMURunner checks an instance it reuses): the same run
        again on new instances of the binaries this process has loaded must give the same numbers; when it does
        not (an export whose instances share state through its library, which persists while the library stays
        loaded: fmpy unloads it with its last instance, another instance or a host may keep it), every run
        loads fresh copies, and the run is made again that way. Counted as a run."""
        self._count(1)
        again = run(False)
        a, b = first.frame.to_numpy(float), again.frame.to_numpy(float)
        if a.shape == b.shape and np.array_equal(a, b):
            self.reuse = "instances of the binaries loaded once per process give the same run twice"
            return first
        diff = float(np.max(np.abs(a - b))) if a.shape == b.shape else float("inf")
        self.fresh_binary = True
        self.reuse = (f"a second run on new instances of the loaded binaries differed (by {diff:.3g}): every "
                      f"coupled run loads fresh copies of the FMUs' binaries")
        return run(True)

    def close(self) -> None:
        """Nothing held between runs (each coupled run makes and frees its own instances)."""
