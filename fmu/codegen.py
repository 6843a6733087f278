#!/usr/bin/env python3
"""Translate the model's equations in modelica/ScrewVertebra.mo into the C the FMU's solver calls.

The Modelica is the one source of the equations. pymoca parses and flattens it into a CasADi DAE
(residuals in the states, their derivatives, the algebraic variables, parameters, inputs and time);
this script makes the DAE explicit (block lower triangular order, every block solved symbolically, the
drive constraint of the motion-driven mode differentiated to the acceleration), builds the right-hand
side, its exact Jacobian and time derivative, the outputs and the load's kinks, and lets CasADi write
them as C (``Function.generate``). The FMU's solver (fmu/solver.c) and FMI layer stay hand-written and
see the model only through ``sv_model.h``, written here too.

Variants: the structural parameter ``mode`` (1 force-driven, 2 motion-driven) and, for speed, a "core"
variant of the force-driven one with the effects beyond eq. 1 switched off at their defaults
(:data:`CORE_OFF`). The
core force-driven variant is checked here to have the axial block the exact stepper of the solver
assumes (linear, constant coefficients), so that the solver's shortcut is the model's structure.

Run: ``python fmu/codegen.py OUTDIR`` (``make fmu`` does, into build/fmu/sources).
"""
from __future__ import annotations

import math
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import casadi as ca
import pymoca.parser
from pymoca import ast
from pymoca.backends.casadi.generator import generate

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from generate import SENSITIVITIES  # noqa: E402  (the one statement of the FMU's sensitivity variables)

MO_FILE = HERE.parent / "modelica" / "ScrewVertebra.mo"
MODEL = "ScrewVertebra"

#: The FMU's solver states, in its order: the six coordinates, their rates, the states of the effects.
STATES = ("x", "y", "z", "alpha", "beta", "gamma", "v_x", "v_y", "v_z", "w_alpha", "w_beta", "w_gamma",
          "z_y", "z_f", "F_ve", "kappa")
#: The monitored position and velocity (the solver's closed-form monitors and exact axial steps).
POSITION, VELOCITY = "y", "v_y"
#: Variables the FMU's solver computes itself (the monitors, its step count) and the Modelica-only
#: helpers they need: every equation that mentions one is left out of the generated code.
SOLVER_OWNED = ("y_max", "v_y_max", "y_mean", "v_y_mean", "t_eq", "n_steps",
                "y_hold", "v_hold", "at_rest", "y_int", "v_abs_int", "t_rest")
#: The parameters that switch the effects beyond eq. 1 (and the table) off at their defaults; the core
#: variants are the model with these fixed to the defaults.
CORE_OFF = ("tab_n", "gap", "yield_ratio", "nl_ratio", "fric_F", "ve_k", "dmg_rate")
#: Structural parameter: one variant per value.
MODES = {"force": 1, "motion": 2}
#: The modes with a core variant besides the full one: the force-driven pullout of the paper's study and the
#: Sobol studies (speed; the exact axial steps). A motion-driven run takes the full variant: a core one would
#: add a fifth of the generated code, and its compile time, for runs that are rarely many.
CORE_MODES = ("force",)
#: Identity operators of Modelica (they tell a tool about events and smoothness, not about values).
IDENTITY_CALLS = {"smooth": 1, "noEvent": 0}
#: Functions pymoca's CasADi backend lacks, folded where their arguments are numbers (parameter defaults).
FOLDED_CALLS = {"atan2": math.atan2}
PREFIX = "sv_"


@dataclass(frozen=True)
class Spec:
    """One model the generator translates: its file, the solver's states in order, the variables the FMU
    computes itself, and its variants (ScrewVertebra: force/motion modes and core variants; a model without
    modes has one variant, ``full``)."""
    model: str
    mo_file: Path
    states: tuple[str, ...]
    prefix: str
    solver_owned: tuple[str, ...] = ()
    modes: dict = field(default_factory=dict)
    core_off: tuple[str, ...] = ()
    core_modes: tuple[str, ...] = ()
    position: str | None = None
    velocity: str | None = None


#: ScrewVertebra: the 6-DOF screw with its solver's monitors, modes and core variants.
SCREW = Spec(MODEL, MO_FILE, STATES, PREFIX, SOLVER_OWNED, MODES, CORE_OFF, CORE_MODES, POSITION, VELOCITY)
#: InterfaceElement: the 1-DOF interface force element (its states are those of the effects' history).
ELEMENT = Spec("InterfaceElement", HERE.parent / "modelica" / "InterfaceElement.mo",
               ("z_y", "z_f", "F_ve", "kappa"), "el_")
SPECS = {s.model: s for s in (SCREW, ELEMENT)}


def spec_for(path: Path | None) -> Spec:
    """The spec of a Modelica file: that of the known model the file declares."""
    if path is None:
        return SCREW
    text = Path(path).read_text(encoding="utf-8")
    for spec in SPECS.values():
        if re.search(rf"^\s*model\s+{spec.model}\b", text, re.M):
            return spec
    sys.exit(f"{path}: declares none of the models the generator knows ({', '.join(SPECS)})")


# ----------------------------------------------------------------------------------------------- parse

def _mentions(node, names: set[str]) -> bool:
    """Whether an AST node refers to one of the names anywhere inside."""
    if isinstance(node, ast.ComponentRef):
        if node.name in names:
            return True
        return any(_mentions(c, names) for c in node.child)
    if isinstance(node, ast.Node):
        return any(_mentions(v, names) for v in vars(node).values())
    if isinstance(node, (list, tuple)):
        return any(_mentions(v, names) for v in node)
    if isinstance(node, dict):
        return any(_mentions(v, names) for v in node.values())
    return False


def _strip_identity(node):
    """smooth(n, e) and noEvent(e) -> e, everywhere below node (in place where possible)."""
    if isinstance(node, ast.Expression) and isinstance(node.operator, ast.ComponentRef) \
            and node.operator.name in IDENTITY_CALLS and not node.operator.child:
        return _strip_identity(node.operands[IDENTITY_CALLS[node.operator.name]])
    if isinstance(node, ast.Expression) and isinstance(node.operator, ast.ComponentRef) \
            and node.operator.name in FOLDED_CALLS and not node.operator.child:
        args = [_strip_identity(a) for a in node.operands]
        if all(isinstance(a, ast.Primary) and isinstance(a.value, (int, float)) for a in args):
            return ast.Primary(value=FOLDED_CALLS[node.operator.name](*[float(a.value) for a in args]))
    if isinstance(node, ast.Node):
        for k, v in vars(node).items():
            if k not in ("parent", "scope"):   # references up the tree, not children
                setattr(node, k, _strip_identity(v))
        return node
    if isinstance(node, list):
        return [_strip_identity(v) for v in node]
    return node


def _is_assert(eq) -> bool:
    if isinstance(eq, ast.Function):
        return eq.name == "assert"
    left = getattr(eq, "left", None)
    return isinstance(left, ast.Expression) and isinstance(left.operator, ast.ComponentRef) \
        and left.operator.name == "assert"


def parse_model(path: Path = MO_FILE, spec: Spec = SCREW) -> ast.Tree:
    """The Modelica source as a pymoca tree, reduced to what the generated code computes: no asserts (the
    FMU validates its parameters in C), no monitors (the solver's), no initial section (the FMU starts at
    rest), smooth()/noEvent() read as their argument."""
    tree = pymoca.parser.parse(path.read_text(encoding="utf-8"))
    if tree is None:
        sys.exit(f"{path}: pymoca could not parse the Modelica source")
    cls = tree.classes.get(spec.model)
    if cls is None:
        sys.exit(f"{path}: no model {spec.model}")
    owned = set(spec.solver_owned)
    missing = owned - set(cls.symbols)
    if missing:
        sys.exit(f"{path}: SOLVER_OWNED of {__file__} names {sorted(missing)}, which the model does not declare")
    kept = []
    for eq in cls.equations:
        if isinstance(eq, ast.WhenEquation) or _is_assert(eq) or _mentions(eq, owned):
            continue
        kept.append(_strip_identity(eq))
    cls.equations = kept
    cls.initial_equations = []
    cls.initial_statements = []
    for name in owned:
        del cls.symbols[name]
    for sym in cls.symbols.values():
        sym.class_modification = _strip_identity(sym.class_modification)
    return tree


# ----------------------------------------------------------------------------------------------- DAE

class Dae:
    """The flattened model in SX: residuals res(t, x, xd, z, p, u) = 0, parameter values and bindings."""

    def __init__(self, tree: ast.Tree, spec: Spec = SCREW) -> None:
        self.spec = spec
        self.states = STATES = spec.states
        finals = {n for n, sym in tree.classes[spec.model].symbols.items() if sym.final}
        model = generate(tree, spec.model)
        self.model = model
        names = lambda vs: [v.symbol.name() for v in vs]  # noqa: E731
        state_names = names(model.states)
        if sorted(state_names) != sorted(STATES):
            sys.exit(f"the model's states are {sorted(state_names)}, STATES of {__file__} says {sorted(STATES)}")
        order = [state_names.index(n) for n in STATES]
        self.x_mx = [model.states[i].symbol for i in order]
        self.xd_mx = [model.der_states[i].symbol for i in order]
        self.z_names = names(model.alg_states)
        self.z_mx = [v.symbol for v in model.alg_states]
        self.u_names = names(model.inputs)
        self.u_mx = [v.symbol for v in model.inputs]
        self.outputs = list(model.outputs)
        # parameters: those with a literal value are the FMU's (set by the user); those bound to an
        # expression of others are derived (computed once per initialisation)
        self.p_names, self.p_mx, self.p_default = [], [], {}
        self.d_names, self.d_mx, self.d_expr = [], [], []
        for v in model.parameters:
            val, name, n = v.value, v.symbol.name(), v.symbol.numel()
            if (isinstance(val, ca.MX) and not val.is_constant()) or name in finals:
                val = ca.MX(val)
                if n != 1:
                    sys.exit(f"derived parameter {name} is an array: write it as scalars")
                self.d_names.append(name)
                self.d_mx.append(v.symbol)
                self.d_expr.append(val)
                continue
            if isinstance(val, ca.MX):
                val = ca.evalf(val)
            vals = ca.DM(val).full().ravel().tolist()
            if len(vals) == 1:
                vals = vals * n
            self.p_mx.append(v.symbol)
            for k in range(n):
                entry = f"{name}[{k + 1}]" if n > 1 else name
                self.p_names.append(entry)
                self.p_default[entry] = float(vals[k])
        self.t_mx = model.time
        res = ca.vertcat(*model.equations)
        # one SX function, expanded: if-expressions become if_else_zero, functions are inlined
        args = [self.t_mx, ca.vertcat(*self.x_mx), ca.vertcat(*self.xd_mx), ca.vertcat(*self.z_mx),
                ca.vertcat(*self.p_mx), ca.vertcat(*self.d_mx), ca.vertcat(*self.u_mx)]
        f = ca.Function("res", args, [res]).expand()
        dexpr = ca.Function("derived", [ca.vertcat(*self.p_mx), ca.vertcat(*self.d_mx)],
                            [ca.vertcat(*self.d_expr)]).expand()
        self.t = ca.SX.sym("t")
        self.x = ca.SX.sym("x", len(STATES))
        self.xd = ca.SX.sym("xd", len(STATES))
        self.z = ca.SX.sym("z", len(self.z_mx))
        self.p = ca.SX.sym("p", len(self.p_names))
        self.d = ca.SX.sym("d", len(self.d_mx))
        self.u = ca.SX.sym("u", len(self.u_mx))
        self.ud = ca.SX.sym("ud", len(self.u_mx))
        self.res = f(self.t, self.x, self.xd, self.z, self.p, self.d, self.u)
        # derived parameters in terms of the FMU's parameters alone (they may refer to each other)
        dd = dexpr(self.p, self.d)
        for _ in range(len(self.d_mx) + 1):
            nxt = ca.substitute(dd, self.d, dd)
            if not ca.depends_on(nxt, self.d):
                dd = nxt
                break
            dd = nxt
        else:
            sys.exit("the derived parameters refer to each other in a cycle")
        self.derived = dd

    def fix(self, values: dict[str, float]) -> "ca.SX":
        """The residuals with some FMU parameters fixed (a variant)."""
        psub = ca.vertcat(*[ca.SX(values[n]) if n in values else self.p[i] for i, n in enumerate(self.p_names)])
        dsub = ca.substitute(self.derived, self.p, psub)
        return ca.substitute(self.res, ca.vertcat(self.p, self.d), ca.vertcat(psub, dsub))


# ----------------------------------------------------------------------------------------------- solve

def _total_derivative(e, dae: Dae, known_xd: dict[int, "ca.SX"]):
    """d/dt of e(t, x, u) along the model: the states' rates where an explicit equation gives them
    (der(q) = qd), the unknown der symbol otherwise; inputs vary linearly within a communication step."""
    de = ca.jacobian(e, dae.t)
    for i in range(len(dae.states)):
        if ca.depends_on(e, dae.x[i]):
            rate = known_xd.get(i, dae.xd[i])
            de = de + ca.jacobian(e, dae.x[i]) * rate
    for i in range(dae.u.numel()):
        if ca.depends_on(e, dae.u[i]):
            de = de + ca.jacobian(e, dae.u[i]) * dae.ud[i]
    return de


def explicit_ode(dae: Dae, res, nominal: dict[str, float]):
    """Solve res = 0 for (xd, z): returns xd(t, x, p, d, u, ud), z(...) as SX, and the drive (the
    prescribed states and their rates, for the motion-driven mode). Blocks of the block lower triangular
    form are solved one after another; each must be affine in its unknowns (checked) and is solved by
    Gaussian elimination whose pivots are chosen at a nominal point, preferring constant coefficients."""
    nx = len(dae.states)
    w = ca.vertcat(dae.xd, dae.z)
    eqs = [res[i] for i in range(res.numel())]
    # kinematic equations der(q) = expression without unknowns
    known_xd: dict[int, ca.SX] = {}
    for e in eqs:
        for i in range(nx):
            if ca.depends_on(e, dae.xd[i]):
                a = ca.jacobian(e, dae.xd[i])
                rest = ca.substitute(e, dae.xd[i], ca.SX(0))
                if a.is_constant() and not ca.depends_on(ca.vertcat(a, rest), w):
                    known_xd[i] = -rest / a
    # constraints on states alone (the drive y = y_drive): differentiate until an unknown appears
    drive = []
    for k, e in enumerate(eqs):
        if ca.depends_on(e, w):
            continue
        chain = [e]
        g = e
        for _ in range(3):
            g = _total_derivative(g, dae, known_xd)
            # a derivative given by a kinematic equation is replaced by it
            g = ca.substitute(g, ca.vertcat(*[dae.xd[i] for i in known_xd]),
                              ca.vertcat(*[known_xd[i] for i in known_xd])) if known_xd else g
            if ca.depends_on(g, w):
                break
            chain.append(g)
        else:
            sys.exit("a constraint on the states does not reach the unknowns after three derivatives")
        eqs[k] = g
        drive.append(chain)
    res = ca.vertcat(*eqs)
    n = res.numel()
    if n != w.numel():
        sys.exit(f"the model has {n} equations for {w.numel()} unknowns (states' rates and algebraic variables)")
    sp = ca.jacobian(res, w).sparsity()
    nb, rowperm, colperm, rowblock, colblock, _, _ = sp.btf()
    sol: dict[int, ca.SX] = {}
    for b in range(nb):
        rows = [rowperm[i] for i in range(rowblock[b], rowblock[b + 1])]
        cols = [colperm[i] for i in range(colblock[b], colblock[b + 1])]
        if len(rows) != len(cols):
            sys.exit(f"the equations are structurally singular: {len(rows)} equations for the unknowns "
                     f"{[_unknown_name(dae, j) for j in cols]}")
        known = [j for j in sol]
        r = ca.vertcat(*[res[i] for i in rows])
        if known:
            r = ca.substitute(r, ca.vertcat(*[w[j] for j in known]), ca.vertcat(*[sol[j] for j in known]))
        wb = ca.vertcat(*[w[j] for j in cols])
        A = ca.jacobian(r, wb)
        if ca.depends_on(A, wb):
            names = [_unknown_name(dae, j) for j in cols]
            sys.exit(f"the equations for {names} are not linear in them: the generator solves only linear blocks")
        rhs = -ca.substitute(r, wb, ca.SX.zeros(wb.numel()))
        x = _solve_block(A, rhs, dae, sol, w, nominal)
        for jj, j in enumerate(cols):
            sol[j] = x[jj]
    xd = ca.vertcat(*[sol[i] for i in range(nx)])
    z = ca.vertcat(*[sol[nx + i] for i in range(dae.z.numel())])
    return xd, z, drive, known_xd


def _unknown_name(dae: Dae, j: int) -> str:
    nx = len(dae.states)
    return f"der({dae.states[j]})" if j < nx else dae.z_names[j - nx]


def _solve_block(A, b, dae: Dae, sol, w, nominal):
    """x with A x = b by Gaussian elimination, pivots chosen once: a constant coefficient where there is
    one, else the largest at the nominal point."""
    n = A.shape[0]
    if n == 1:
        return [b[0] / A[0, 0]]
    A = [[A[i, j] for j in range(n)] for i in range(n)]
    b = [b[i] for i in range(n)]
    # nominal values of the block's coefficients
    At = ca.vertcat(*[ca.vertcat(*row) for row in A])
    known = list(sol)
    if known:
        At = ca.substitute(At, ca.vertcat(*[w[j] for j in known]), ca.vertcat(*[sol[j] for j in known]))
    f = ca.Function("a", [dae.t, dae.x, dae.p, dae.d], [At])
    num = f(nominal["t"], nominal["x"], nominal["p"], nominal["d"]).full().ravel()
    val = [[num[i * n + j] for j in range(n)] for i in range(n)]
    rows, cols = list(range(n)), list(range(n))
    order = []
    for _ in range(n):
        best = None
        for i in rows:
            for j in cols:
                a = A[i][j]
                if a.is_zero():
                    continue
                score = (1 if a.is_constant() else 0, abs(val[i][j]))
                if score[1] == 0 and not a.is_constant():
                    continue
                if best is None or score > best[0]:
                    best = (score, i, j)
        if best is None:
            sys.exit("a linear block of the model is singular at the nominal point")
        _, pi, pj = best
        rows.remove(pi)
        cols.remove(pj)
        order.append((pi, pj))
        piv = A[pi][pj]
        for i in rows:
            if A[i][pj].is_zero():
                continue
            fac = A[i][pj] / piv
            for j in cols:
                A[i][j] = A[i][j] - fac * A[pi][j]
            b[i] = b[i] - fac * b[pi]
            # numerical values for the next pivot choice
            vf = val[i][pj] / val[pi][pj] if val[pi][pj] != 0 else 0.0
            for j in cols:
                val[i][j] -= vf * val[pi][j]
            A[i][pj] = ca.SX(0)
    x = [None] * n
    for pi, pj in reversed(order):
        s = b[pi]
        for j in range(n):
            if j != pj and x[j] is not None and not A[pi][j].is_zero():
                s = s - A[pi][j] * x[j]
        x[pj] = s / A[pi][pj]
    return x


# ----------------------------------------------------------------------------------------------- kinks

def time_kinks(exprs, dae: Dae) -> list:
    """The times at which a condition on time switches (the load's ramp starts and ends): every
    comparison in the expressions whose sides differ by an affine function of time alone, as an
    expression of the parameters. The solver never steps across one."""
    seen: set[int] = set()
    out: list = []
    keys: set[str] = set()
    stack = [exprs[i] for i in range(exprs.numel())]
    other = ca.vertcat(dae.x, dae.u, dae.ud)
    while stack:
        e = stack.pop()
        h = e.element_hash()
        if h in seen:
            continue
        seen.add(h)
        if e.is_op(ca.OP_LT) or e.is_op(ca.OP_LE):
            g = e.dep(0) - e.dep(1)
            if ca.depends_on(g, dae.t) and not ca.depends_on(g, other):
                slope = ca.jacobian(g, dae.t)
                if ca.depends_on(slope, ca.vertcat(dae.t, other)):
                    sys.exit("a condition on time is not affine in time: the solver cannot locate its switch")
                at = -ca.substitute(g, dae.t, ca.SX(0)) / slope
                key = str(at)
                if key not in keys:
                    keys.add(key)
                    out.append(at)
        for i in range(e.n_dep()):
            stack.append(e.dep(i))
    return sorted(out, key=str)


# ----------------------------------------------------------------------------------------------- variants

class Variant:
    """One explicit model: the right-hand side, its linearisation and the outputs, as SX."""

    def __init__(self, dae: Dae, name: str, fixed: dict[str, float], nominal: dict) -> None:
        self.name = name
        self.fixed = fixed
        res = dae.fix(fixed)
        xd, z, drive, _ = explicit_ode(dae, res, nominal)
        self.xd = xd
        self.J = ca.jacobian(xd, dae.x)
        self.Ft = ca.jacobian(xd, dae.t) + ca.mtimes(ca.jacobian(xd, dae.u), dae.ud)
        # outputs: every model output that is not a state, from the solved algebraic variables
        zs = {n: z[i] for i, n in enumerate(dae.z_names)}
        self.out_names = [n for n in dae.outputs if n not in dae.states]
        missing = [n for n in self.out_names if n not in zs]
        if missing:
            sys.exit(f"outputs {missing} are neither states nor algebraic variables of the model")
        self.out = ca.vertcat(*[zs[n] for n in self.out_names])
        self.drive = drive
        self.zs = zs

    def functions(self, dae: Dae) -> list:
        ins = [dae.t, dae.x, dae.p, dae.d, dae.u, dae.ud]
        names = ["t", "x", "p", "d", "u", "ud"]
        # every output dense: the C reads whole vectors (CasADi writes only the structural non-zeros of a
        # sparse one)
        f_rhs = ca.Function(f"{dae.spec.prefix}{self.name}_rhs", ins, [ca.densify(self.xd)], names, ["xd"])
        # J transposed: CasADi writes a dense matrix by columns, the solver reads J by rows
        f_lin = ca.Function(f"{dae.spec.prefix}{self.name}_lin", ins, [ca.densify(self.xd), ca.densify(self.J.T), ca.densify(self.Ft)],
                            names, ["xd", "J", "Ft"])
        f_out = ca.Function(f"{dae.spec.prefix}{self.name}_out", ins, [ca.densify(self.out)], names, ["out"])
        return [f_rhs, f_lin, f_out]


#: columns of the sensitivity functions that take several at once (fmu/model.c calls them per batch): the columns
#: of one call share the model's Jacobian and rates, unused ones cost as much as used ones, and each batch column
#: adds as much generated code; four of the diagnosis's two to seven.
SENS_BATCH = 4


def sensitivity_functions(dae: Dae, v: Variant, outputs: tuple[str, ...], columns: int) -> list:
    """The forward sensitivities of a variant: S' = J S + (df/dp) E for S = dx/dp E in the parameter direction E
    (the unit vector of a selected parameter), and the output sensitivities (dh/dx) S + (dh/dp) E. The derived
    parameters are functions of p in the variant's equations (Dae.fix), so these are total derivatives.
    ``_sens_rhs_all``: S' for ``columns`` columns at once (S and E n x columns and np x columns, column-major: the
    columns share J, which one column at a time cost as much as the states' own step). For a variant whose states
    move freely (not a prescribed motion), ``_sens_lin_all``: the same and, for the solver's exponential step of S,
    its time derivative along the states' own motion, d/dt (J S + f_p E) at fixed S with x' = f and the inputs'
    rates (under a prescribed motion the solver takes it by a difference of two ``_sens_rhs_all``: there that costs
    less, and this is half the generated code); ``_sens_rhs`` and ``_sens_aug``: one column's S', and with it its
    Jacobian by the states at fixed S (row-major) and its explicit time derivative (the inputs' rates): the solver
    steps (x, S) together with them where a ringing x would move S faster than a polynomial in time can follow.
    ``_sens_out``: the outputs' sensitivities of one column."""
    pre, name = dae.spec.prefix, v.name
    S = ca.SX.sym("S", len(dae.states))
    E = ca.SX.sym("E", dae.p.numel())
    Fs = ca.mtimes(v.J, S) + ca.jtimes(v.xd, dae.p, E)
    ins = [dae.t, dae.x, dae.p, dae.d, dae.u, dae.ud, S, E]
    names = ["t", "x", "p", "d", "u", "ud", "S", "E"]
    missing = [o for o in outputs if o not in v.zs]
    if missing:
        sys.exit(f"SENSITIVITIES names {missing}, which are not outputs of the model")
    h = ca.vertcat(*[v.zs[o] for o in outputs])
    dh = ca.mtimes(ca.jacobian(h, dae.x), S) + ca.jtimes(h, dae.p, E)
    SK = ca.SX.sym("SK", len(dae.states), columns)
    EK = ca.SX.sym("EK", dae.p.numel(), columns)
    FsK = ca.mtimes(v.J, SK) + ca.jtimes(v.xd, dae.p, EK)
    insK = [dae.t, dae.x, dae.p, dae.d, dae.u, dae.ud, SK, EK]
    out = [ca.Function(f"{pre}{name}_sens_rhs_all", insK, [ca.densify(FsK)], names, ["Fs"])]
    if not v.drive:
        vK = ca.vec(FsK)
        FtsK = ca.reshape(ca.jtimes(vK, dae.t, ca.SX(1)) + ca.jtimes(vK, dae.u, dae.ud) + ca.jtimes(vK, dae.x, v.xd),
                          FsK.shape)
        out.append(ca.Function(f"{pre}{name}_sens_lin_all", insK, [ca.densify(FsK), ca.densify(FtsK)], names,
                               ["Fs", "Fts"]))
        out.append(ca.Function(f"{pre}{name}_sens_rhs", ins, [ca.densify(Fs)], names, ["Fs"]))
        out.append(ca.Function(f"{pre}{name}_sens_aug", ins,
                               [ca.densify(Fs), ca.densify(ca.jacobian(Fs, dae.x).T),
                                ca.densify(ca.jtimes(Fs, dae.t, ca.SX(1)) + ca.jtimes(Fs, dae.u, dae.ud))],
                               names, ["Fs", "Fsx", "Fst"]))
    out.append(ca.Function(f"{pre}{name}_sens_out", ins, [ca.densify(dh)], names, ["dout"]))
    return out


def drive_sensitivity_function(dae: Dae, variant: Variant, drive):
    """The prescribed states' sensitivities in one direction E: d(x_drive)/dp E (a drive v_pull*time depends
    on v_pull; one that follows an input on nothing)."""
    E = ca.SX.sym("E", dae.p.numel())
    values = drive.call([dae.t, dae.p, dae.d, dae.u, dae.ud])[0]
    dv = ca.jtimes(values, dae.p, E)
    return ca.Function(f"{dae.spec.prefix}{variant.name}_sens_drive", [dae.t, dae.p, dae.d, dae.u, dae.ud, E],
                       [ca.densify(dv)], ["t", "p", "d", "u", "ud", "E"], ["dx_drive"])


def drive_function(dae: Dae, variant: Variant):
    """The prescribed states of the motion-driven mode at time t: each equation of the drive's chain
    (the constraint, then its derivatives) solved for the one state it fixes."""
    fixed_states, values = [], []
    subst_from, subst_to = [], []
    for chain in variant.drive:
        for g in chain:
            if subst_from:
                g = ca.substitute(g, ca.vertcat(*subst_from), ca.vertcat(*subst_to))
            deps = [i for i in range(len(STATES)) if ca.depends_on(g, dae.x[i])]
            if len(deps) != 1:
                sys.exit(f"a drive equation fixes {[STATES[i] for i in deps]}: it must fix one state")
            i = deps[0]
            a = ca.jacobian(g, dae.x[i])
            if ca.depends_on(a, dae.x):
                sys.exit(f"the drive equation for {STATES[i]} is not linear in it")
            val = -ca.substitute(g, dae.x[i], ca.SX(0)) / a
            fixed_states.append(STATES[i])
            values.append(val)
            subst_from.append(dae.x[i])
            subst_to.append(val)
    f = ca.Function(f"{dae.spec.prefix}{variant.name}_drive", [dae.t, dae.p, dae.d, dae.u, dae.ud],
                    [ca.densify(ca.vertcat(*values))], ["t", "p", "d", "u", "ud"], ["x_drive"])
    return f, fixed_states


# ----------------------------------------------------------------------------------------------- checks

def check_core_axial_block(dae: Dae, core: Variant) -> None:
    """The solver takes the axial pullout in exact steps when the core force-driven variant applies
    (Solver.lin2): that needs the (y, v_y) rows to be y' = v_y, v_y' = -k y - g v_y + f(t) with constant
    k, g, f affine in t between kinks, and nothing else in those rows when the rest is at rest. Prove it on
    the generated expressions, so that the shortcut is the model's structure, not an assumption."""
    iy, iv = STATES.index(POSITION), STATES.index(VELOCITY)
    rows = ca.vertcat(core.xd[iy], core.xd[iv])
    J = ca.jacobian(rows, ca.vertcat(dae.x[iy], dae.x[iv]))
    if ca.depends_on(J, ca.vertcat(dae.x[iy], dae.x[iv], dae.t)):
        sys.exit("core variant: the axial block's Jacobian depends on y, v_y or t: the exact axial steps of the "
                 "solver do not hold")
    ft = ca.jacobian(rows, dae.t)
    if ca.depends_on(ca.jacobian(ft, dae.t), dae.t):
        sys.exit("core variant: the axial load is not piecewise affine in time")


# ----------------------------------------------------------------------------------------------- emit

def c_ident(name: str) -> str:
    return name.replace("[", "_").replace("]", "")


def build(path: Path | None = None, spec: Spec | None = None) -> dict:
    """Every generated function and the facts <prefix>model.h states (the spec: by the file's model name)."""
    spec = spec or spec_for(path)
    path = Path(path) if path is not None else spec.mo_file
    tree = parse_model(path, spec)
    dae = Dae(tree, spec)
    PREFIX = spec.prefix
    p_default = [dae.p_default[n] for n in dae.p_names]
    fd = ca.Function(f"{PREFIX}derived", [dae.p], [ca.densify(dae.derived)], ["p"], ["d"])
    # the nominal point at which block pivots are chosen: default parameters, a small displacement
    nominal = dict(t=0.5, x=[1e-4] * len(spec.states), p=p_default, d=fd(p_default).full().ravel().tolist())
    off = {n: dae.p_default[n] for n in spec.core_off}
    variants = []
    for mode_name, mode in spec.modes.items():
        if mode_name in spec.core_modes:
            variants.append(Variant(dae, f"{mode_name}_core", {"mode": mode, **off}, nominal))
        variants.append(Variant(dae, f"{mode_name}_full", {"mode": mode}, nominal))
    if not spec.modes:
        variants.append(Variant(dae, "full", {}, nominal))
    if spec.position:
        check_core_axial_block(dae, variants[0])
    functions = [fd]
    drives = {}
    sens = SENSITIVITIES.get(spec.model)
    for v in variants:
        functions += v.functions(dae)
        if v.drive:
            f, fixed = drive_function(dae, v)
            functions.append(f)
            drives[v.name] = fixed
            if sens:
                functions.append(drive_sensitivity_function(dae, v, f))
        # the sensitivities take the full variants: a core one fixes the effects' parameters
        if sens and v.name.endswith("_full"):
            functions += sensitivity_functions(dae, v, tuple(sens["outputs"]), SENS_BATCH)
    kinks = time_kinks(ca.vertcat(*[v.xd for v in variants]), dae) if spec.modes else []
    if spec.modes:
        fk = ca.Function(f"{PREFIX}kinks", [dae.p, dae.d], [ca.densify(ca.vertcat(*kinks))], ["p", "d"],
                         ["t_kink"])
        functions.append(fk)
    public = {n for n, sym in tree.classes[spec.model].symbols.items() if sym.visibility == ast.Visibility.PUBLIC}
    return dict(dae=dae, variants=variants, functions=functions, drives=drives, n_kinks=len(kinks),
                public=public, sens=sens)


def header(info: dict) -> str:
    dae, variants = info["dae"], info["variants"]
    spec = dae.spec
    STATES = spec.states
    P = spec.prefix.upper()
    fns = info["functions"]
    lines = [f"/* Generated by fmu/codegen.py from modelica/{spec.mo_file.name}: do not edit.",
             " * The model as the FMU's solver and FMI layer see it: sizes, the order of the states,",
             f" * parameters, inputs and outputs in the vectors of the generated functions ({spec.prefix}generated.c),",
             " * and which variant applies. */",
             f"#ifndef {P}MODEL_H", f"#define {P}MODEL_H", "", f'#include "{spec.prefix}generated.h"', ""]
    lines += [f"#define SV_NX {len(STATES)}", f"#define SV_NP {len(dae.p_names)}",
              f"#define SV_ND {len(dae.d_names)}", f"#define SV_NU {len(dae.u_names)}",
              f"#define SV_NOUT {len(variants[0].out_names)}", f"#define SV_NKINKS {info['n_kinks']}", ""]
    for i, n in enumerate(STATES):
        lines.append(f"#define SV_IX_{n} {i}")
    if spec.position:
        lines += [f"#define SV_IX_POSITION SV_IX_{spec.position}", f"#define SV_IX_VELOCITY SV_IX_{spec.velocity}", ""]
    def table(macro: str, names: list[str], what: str, into: list[str] | None = None) -> None:
        out = lines if into is None else into
        out.append(f"/* X(index, name) for every {what} */")
        out.append(f"#define {macro}(X) \\")
        for i, n in enumerate(names):
            if n:
                out.append(f"    X({i}, {c_ident(n)}) \\")
        out.append("")
    table("SV_PARAMETERS", dae.p_names, "entry of p (the FMU's parameters)")
    table("SV_DERIVED", dae.d_names, "entry of d (the derived parameters)")
    table("SV_INPUTS", dae.u_names, "entry of u (the inputs; ud holds their time derivatives)")
    outs = variants[0].out_names
    if any(v.out_names != outs for v in variants):
        sys.exit("the variants disagree on the outputs")
    table("SV_OUTPUTS", outs, "entry of out")
    public = info["public"]
    table("SV_STATE_OUTPUTS", [n if n in public else "" for n in STATES], "state that is a variable of the FMU")
    table("SV_CALCULATED", [n if n in public else "" for n in dae.d_names],
          "derived parameter that is a variable of the FMU (calculatedParameter)")
    for i, n in enumerate(dae.p_names):
        lines.append(f"#define SV_P_{c_ident(n)} {i}")
    for i, n in enumerate(dae.d_names):
        lines.append(f"#define SV_D_{c_ident(n)} {i}")
    lines.append("")
    if info.get("sens"):
        sens = info["sens"]
        lines += ["/* Forward sensitivities (fmu/generate.py SENSITIVITIES): parameter directions, outputs */",
                  f"#define SV_NSENS {sens['parameters']}", f"#define SV_NSENS_OUT {len(sens['outputs'])}",
                  f"#define SV_NSENS_BATCH {SENS_BATCH}"]
        table("SV_SENS_OUTPUTS", list(sens["outputs"]), "output with sensitivities (the rows of dout of _sens_out)")
    if spec.modes:
        lines += _mode_lines(info, dae, table)
    sz_arg = max(f.sz_arg() for f in fns)
    sz_res = max(f.sz_res() for f in fns)
    sz_iw = max(f.sz_iw() for f in fns)
    sz_w = max(f.sz_w() for f in fns)
    lines += ["/* The largest work arrays any generated function needs */",
              f"#define SV_SZ_ARG {sz_arg}", f"#define SV_SZ_RES {sz_res}", f"#define SV_SZ_IW {max(sz_iw, 1)}",
              f"#define SV_SZ_W {max(sz_w, 1)}", "", "#endif", ""]
    return "\n".join(lines).replace("SV_", P)


def _mode_lines(info: dict, dae: "Dae", table) -> list[str]:
    """The header's lines on ScrewVertebra's modes, core variants and drive."""
    spec = dae.spec
    lines: list[str] = []
    cond = " && ".join(f"(p)[SV_P_{c_ident(n)}] == {dae.p_default[n]!r}" for n in spec.core_off)
    lines += ["/* The core variants apply: every effect beyond eq. 1 (and the table) is off. */",
              f"#define SV_IS_CORE(p) ({cond})", ""]
    lines.append(f"#define SV_MODE_FORCE {spec.modes['force']}")
    lines.append(f"#define SV_MODE_MOTION {spec.modes['motion']}")
    drives = list(info["drives"].values())
    if any(d != drives[0] for d in drives):
        sys.exit("the motion-driven variants prescribe different states")
    lines.append(f"#define SV_NDRIVE {len(drives[0])}")
    table("SV_DRIVE", drives[0], "state the motion drive prescribes (the output of the _drive functions)", lines)
    return lines


def write(outdir: Path, info: dict) -> list[Path]:
    outdir.mkdir(parents=True, exist_ok=True)
    pre = info["dae"].spec.prefix
    cg = ca.CodeGenerator(f"{pre}generated.c", {"with_header": True, "with_export": False, "verbose": False,
                                             "casadi_int": "int"})
    for f in info["functions"]:
        for i in range(f.n_out()):
            if not f.sparsity_out(i).is_dense():
                sys.exit(f"{f.name()}: output {f.name_out(i)} is sparse; the C reads dense vectors")
        cg.add(f)
    cg.generate(str(outdir) + "/")
    # CasADi's functions take arguments some of them do not use: not a defect of this model
    c = outdir / f"{pre}generated.c"
    c.write_text("#if defined(__GNUC__)\n#pragma GCC diagnostic ignored \"-Wunused-parameter\"\n#endif\n"
                 + c.read_text(encoding="utf-8"), encoding="utf-8")
    (outdir / f"{pre}model.h").write_text(header(info), encoding="utf-8")
    return [outdir / f"{pre}generated.c", outdir / f"{pre}generated.h", outdir / f"{pre}model.h"]


def main() -> None:
    """codegen.py [OUTDIR [MODEL.mo]]: MODEL.mo defaults to modelica/ScrewVertebra.mo."""
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else HERE.parent / "build" / "fmu" / "sources"
    info = build(Path(sys.argv[2]) if len(sys.argv) > 2 else None)
    for p in write(out, info):
        print(f"wrote {p}")


if __name__ == "__main__":
    main()
