"""AxialScrew: a third-party FMU of the screw's axial pullout, exported with pythonfmu.

It is written independently of fmusa's own ScrewVertebra model (fmu/*.c): the same physics, the axial
spring-damper of the screw-vertebra interface under a ramped pull,

    m y'' + d y' + c y = F(t),   F(t) = F_pull * min(t / t_ramp, 1),   y(0) = y'(0) = 0,

but its own integrator, its own variable names (hierarchical and quoted, as Modelica tools write them)
and its own units (millimetres and grams, as CAD-based multibody tools often use):

=====================  ==========  =========  ==========================================
variable               causality   unit       meaning
=====================  ==========  =========  ==========================================
screw.mass             parameter   g          screw mass (0.29 g)
screw.bushing.c[2]     parameter   N/mm       axial stiffness of the interface (index 2: y)
screw.bushing.d[2]     parameter   N.s/mm     axial damping of the interface
'F pull'               parameter   N          pull force after the ramp
t_ramp                 parameter   s          ramp time 0 -> 'F pull'
screw.y_mm             output      mm         axial displacement y
der(screw.y_mm)        output      mm/s       axial velocity y'
screw.bushing.W        output      N.mm       energy stored in the axial spring, c y^2 / 2
=====================  ==========  =========  ==========================================

There are no monitors (max |y|, ...): an importer samples the outputs at its communication points.

Integrator: the state (y, y', F, F') obeys a linear, time-invariant ODE on each piece of the load
(ramp, hold), so one communication step is advanced exactly by the matrix exponential of the 4x4
augmented system (scipy.linalg.expm), split at t = t_ramp. The step matrices are cached per step size.

Build:  pythonfmu build -f axial_screw.py   (the class must be declared as ``class X(Fmi2Slave):``,
which pythonfmu's runtime looks for by regular expression). The FMU's binary runs the class in the Python
interpreter of the process that loads it (it resolves the CPython API from the host process), so it
runs under fmpy in any Python with numpy and scipy; it cannot run in a non-Python importer.
"""
from __future__ import annotations

import math
from xml.etree.ElementTree import Element, SubElement

import numpy as np
from scipy.linalg import expm

from pythonfmu import Fmi2Causality, Fmi2Slave, Fmi2Variability, Real
from pythonfmu.default_experiment import DefaultExperiment

# FMI 2.0 unit definitions: name -> SI exponents and factor (value_SI = factor * value).
UNITS = {
    "g": ({"kg": 1}, 1e-3),
    "N/mm": ({"kg": 1, "s": -2}, 1e3),
    "N.s/mm": ({"kg": 1, "s": -1}, 1e3),
    "N": ({"kg": 1, "m": 1, "s": -2}, 1.0),
    "s": ({"s": 1}, 1.0),
    "mm": ({"m": 1}, 1e-3),
    "mm/s": ({"m": 1, "s": -1}, 1e-3),
    "N.mm": ({"kg": 1, "m": 2, "s": -2}, 1e-3),
}


class AxialScrew(Fmi2Slave):

    author = "fmusa test suite (third-party exporter: pythonfmu)"
    description = ("Axial pullout of a bone screw, m y'' + d y' + c y = F(t), in mm, g and N; "
                   "exact matrix-exponential steps")

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.default_experiment = DefaultExperiment(start_time=0.0, stop_time=0.6, step_size=0.002)
        # parameters, in the FMU's own units
        self.mass_g = 0.29
        self.c_N_per_mm = 822.0
        self.d_Ns_per_mm = 0.5
        self.F_pull = 411.0
        self.t_ramp = 0.5
        # state, SI internally: y [m], v [m/s]
        self.t = 0.0
        self.y = 0.0
        self.v = 0.0
        self._cache: dict = {}
        self._units: dict[str, str] = {}

        def par(name, attr, unit, description):
            self._register(Real(name, causality=Fmi2Causality.parameter, variability=Fmi2Variability.tunable,
                                description=description, getter=lambda: getattr(self, attr),
                                setter=lambda v: setattr(self, attr, float(v))), unit)

        def out(name, fn, unit, description):
            self._register(Real(name, causality=Fmi2Causality.output, variability=Fmi2Variability.continuous,
                                description=description, getter=fn), unit)

        par("screw.mass", "mass_g", "g", "Mass of the screw")
        par("screw.bushing.c[2]", "c_N_per_mm", "N/mm", "Axial stiffness of the screw-bone interface")
        par("screw.bushing.d[2]", "d_Ns_per_mm", "N.s/mm", "Axial damping of the screw-bone interface")
        par("'F pull'", "F_pull", "N", "Pull force at the screw head after the ramp")
        par("t_ramp", "t_ramp", "s", "Duration of the linear force ramp")
        out("screw.y_mm", lambda: 1e3 * self.y, "mm", "Axial displacement of the screw")
        out("der(screw.y_mm)", lambda: 1e3 * self.v, "mm/s", "Axial velocity of the screw")
        out("screw.bushing.W", lambda: 0.5 * self.c_N_per_mm * (1e3 * self.y) ** 2, "N.mm",
            "Energy stored in the axial spring")

    def _register(self, var: Real, unit: str) -> None:
        # explicit getters/setters: the names are FMI names, not Python attribute paths
        self.register_variable(var, nested=False)
        self._units[var.name] = unit

    # ------------------------------------------------------------------ model description: units
    def to_xml(self, model_options=dict()) -> Element:
        """pythonfmu writes no units: add <UnitDefinitions> and each Real's unit attribute (and the
        InitialUnknowns pythonfmu leaves out)."""
        root = super().to_xml(model_options)
        defs = Element("UnitDefinitions")
        for name, (exps, factor) in UNITS.items():
            u = SubElement(defs, "Unit", {"name": name})
            attrs = {k: str(v) for k, v in exps.items()}
            if factor != 1.0:
                attrs["factor"] = repr(factor)
            SubElement(u, "BaseUnit", attrs)
        # FMI 2.0 order: CoSimulation, UnitDefinitions, TypeDefinitions, LogCategories, ...
        index = [i for i, child in enumerate(root) if child.tag == "CoSimulation"][0] + 1
        root.insert(index, defs)
        for sv in root.find("ModelVariables"):
            unit = self._units.get(sv.get("name"))
            if unit:
                sv.find("Real").set("unit", unit)
        # pythonfmu lists the outputs but not the initial unknowns that FMI 2.0 requires with them
        structure = root.find("ModelStructure")
        outputs = structure.find("Outputs")
        if outputs is not None and structure.find("InitialUnknowns") is None:
            initial = SubElement(structure, "InitialUnknowns")
            for unknown in outputs:
                SubElement(initial, "Unknown", {"index": unknown.get("index")})
        return root

    # ------------------------------------------------------------------ simulation
    def setup_experiment(self, start_time, stop_time=None, tolerance=None):
        self.t = float(start_time)

    def exit_initialization_mode(self):
        m = 1e-3 * self.mass_g
        c = 1e3 * self.c_N_per_mm
        d = 1e3 * self.d_Ns_per_mm
        if not (m > 0 and c >= 0 and d >= 0 and self.t_ramp > 0):
            raise ValueError(f"need screw.mass > 0, c >= 0, d >= 0, t_ramp > 0; got m = {self.mass_g} g, "
                             f"c = {self.c_N_per_mm} N/mm, d = {self.d_Ns_per_mm} N.s/mm, "
                             f"t_ramp = {self.t_ramp} s")
        # z = (y, v, F, F'):  y' = v,  v' = (F - c y - d v) / m,  F'' = 0
        self._A = np.array([[0.0, 1.0, 0.0, 0.0],
                            [-c / m, -d / m, 1.0 / m, 0.0],
                            [0.0, 0.0, 0.0, 1.0],
                            [0.0, 0.0, 0.0, 0.0]])
        self._cache = {}
        self.y = 0.0
        self.v = 0.0

    def _load(self, t: float) -> tuple[float, float]:
        """F and F' on the piece of the load that starts at t."""
        if t < self.t_ramp:
            rate = self.F_pull / self.t_ramp
            return rate * t, rate
        return self.F_pull, 0.0

    def _advance(self, t: float, h: float) -> None:
        if h <= 0.0:
            return
        key = round(h, 15)
        phi = self._cache.get(key)
        if phi is None:
            phi = expm(self._A * h)
            if len(self._cache) < 64:
                self._cache[key] = phi
        F, dF = self._load(t)
        z = phi @ np.array([self.y, self.v, F, dF])
        self.y, self.v = float(z[0]), float(z[1])

    def do_step(self, current_time, step_size):
        t0, t1 = float(current_time), float(current_time) + float(step_size)
        # a step end within rounding of the kink counts as the kink
        kink = self.t_ramp
        if t0 < kink < t1 and not math.isclose(t1, kink, rel_tol=1e-12, abs_tol=1e-15):
            self._advance(t0, kink - t0)
            self._advance(kink, t1 - kink)
        else:
            self._advance(t0 if not math.isclose(t0, kink, rel_tol=1e-12, abs_tol=1e-15) else kink,
                          t1 - t0)
        self.t = t1
        return True
