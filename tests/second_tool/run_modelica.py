"""A second Modelica tool simulates modelica/ScrewVertebra.mo: the pure-Python `modelica` package.

Runs INSIDE the environment that `make modelica-venv` creates (Python >= 3.12, modelica[sim] pinned in
tests/second_tool/requirements.txt), never in the project's venv: tests/test_second_tool.py starts it in a subprocess per case and
compares what it writes with the FMU. Nothing here imports fmusa, fmpy or the FMU's code, so an error in
fmu/codegen.py, CasADi or fmu/solver.c cannot hide in this tool's answer.

Usage: python run_modelica.py CASE.json OUT.json

CASE.json: {"mo": path of the .mo, "params": {name: value}, "inputs": {name: constant value},
"times": [communication points, from 0], "tolerance": relative tolerance, "absolute": absolute tolerance,
"outputs": [names], "method": SciPy's integrator, default Radau}. Parameters named like the FMU's
variables (tab_y[3] for the table's entries).
OUT.json: {"t": [...], name: [...] for each output, "states": [...], "events": n, "transformations": [what
each changed], "timing": {...}}.

The model is simulated exactly as written, with the case's parameters set as modifiers of an extends
clause (plain Modelica: `model SecondToolCase extends ScrewVertebra(c_y = ..., mode = 2); end ...`, so
structural parameters such as mode are known when the package flattens the if-equations). After
flattening, the package needs these transformations of the flat model, each for a construct it cannot
take yet; none changes what an equation says:

T1 parameter bindings: a subscripted parameter array in a parameter's binding (tab_F[2] in tab_s1 =
   (tab_F[2] - tab_F[1])/...) is left as an array subscript by the package's flattener, whose code
   generator then stops with "array equations are not supported yet"; in equations the same flattener
   already writes the scalar tab_F[2]. T1 does that renaming in bindings too (Subscript(tab_F, 2) ->
   the flat scalar tab_F[2], which holds the same value). And an array modifier (tab_y = {0, 1e-4, ...},
   how a case sets the table) binds every flat element tab_y[k] to the whole array literal; T1 binds
   tab_y[k] to the literal's k-th entry, which is what the modifier means.
T2 inputs: the package has no input channel (an input is a known it never sets; a modifier binding it
   becomes an equation with no unknown left). The cases here hold every input constant, so each
   top-level input becomes a parameter bound to that constant (0 where the case sets none: the
   inputs' start value, which the FMU also starts from and keeps).
T3 n_steps = 0: a discrete Integer defined by a continuous equation; the package defines a discrete
   variable only in a when-clause ("no unknown left for equation `n_steps = 0`"). n_steps is the FMU
   solver's step count (0 in a Modelica tool, the .mo says so); it is removed.
T4 the t_eq monitor: `when {initial(), at_rest} then t_rest = time;` has a vector of conditions (and a
   Boolean, not a relation); the package's event generator takes one relation only ("a when-condition
   has to be a relation"). t_rest, its when-clause and t_eq (the FMU solver's monitor, not compared)
   are removed; at_rest is then read by nothing and goes too (its relations would only add events).
T5 the y_mean and v_y_mean monitors: `y_mean = if time > 0 then y_int/time else y`. The relation
   time > 0 sits at zero at the start; the package fires it as an event at t = 0 and latches it true
   there, so the model divides by time = 0 (ZeroDivisionError in the Jacobian, before any step).
   y_mean, v_y_mean and their integrals y_int, v_abs_int (the FMU solver's monitors) are removed.
T6 the y_max and v_y_max monitors: `when y*v_y < 0 then y_hold = ...` (and v_y*a_y < 0). At rest both
   products are exactly 0 at t = 0, and so is `time < 0` of the load; the package hands every
   when-condition and relation to SciPy's event location, whose root bracketing fails on an indicator
   that is 0 at both ends of the first step ("no crossing could be located at t = 0 -- 'y * v_y < 0',
   'v_y * a_y < 0', 'time < 0' sit at zero"). Without the two when-clauses only `time < 0` is left at
   zero and the run goes through. y_max, v_y_max, y_hold and v_hold (the FMU solver's monitors) are
   removed.

So every monitor is the FMU solver's alone and none is compared; everything else is simulated as written.
"""
from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
from modelica import ir
from modelica.ir.flat import FlatModel, FlatVariable
from modelica.lang import parse
from modelica.sim import causalize, flatten, simulate

MODEL = "ScrewVertebra"
CASE_MODEL = "SecondToolCase"
TABLE_ARRAYS = ("tab_y", "tab_F")
TABLE_SIZE = 16
#: T3-T6: the variables removed, with every equation and when-clause that names one of them
REMOVED_BY: dict[str, frozenset[str]] = {
    "T3": frozenset({"n_steps"}),
    "T4": frozenset({"t_rest", "t_eq", "at_rest"}),
    "T5": frozenset({"y_mean", "v_y_mean", "y_int", "v_abs_int"}),
    "T6": frozenset({"y_max", "v_y_max", "y_hold", "v_hold"}),
}
REMOVED = frozenset().union(*REMOVED_BY.values())


# ------------------------------------------------------------------------------------------ parameters
def modelica_literal(value: Any) -> str:
    """A Python value as a Modelica literal (bool before int: True is an int in Python)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, (list, tuple)):
        return "{" + ", ".join(modelica_literal(v) for v in value) + "}"
    x = float(value)
    if not math.isfinite(x):
        raise ValueError(f"not a finite number: {value!r}")
    return repr(x)


def modifiers(params: dict[str, Any]) -> str:
    """The extends clause's modifiers: scalars by name, table entries tab_y[k] as whole arrays."""
    tables = {name: [0.0] * TABLE_SIZE for name in TABLE_ARRAYS}
    touched: set[str] = set()
    parts = []
    for name, value in params.items():
        base, _, rest = name.partition("[")
        if base in tables and rest:
            tables[base][int(rest.rstrip("]")) - 1] = float(value)
            touched.add(base)
        else:
            parts.append(f"{name} = {modelica_literal(value)}")
    parts += [f"{name} = {modelica_literal(tables[name])}" for name in TABLE_ARRAYS if name in touched]
    return ", ".join(parts)


def case_source(mo_text: str, params: dict[str, Any]) -> str:
    """The .mo file unchanged, plus a model that extends ScrewVertebra with the case's parameters."""
    return f"{mo_text}\n\nmodel {CASE_MODEL}\n  extends {MODEL}({modifiers(params)});\nend {CASE_MODEL};\n"


# ------------------------------------------------------------------------------------------ transformations
def map_expr(node: Any, fn: Callable[[Any], Any | None]) -> Any:
    """Rebuild an IR expression bottom-up, replacing each node where fn returns one (None: keep)."""
    if isinstance(node, tuple):
        return tuple(map_expr(n, fn) for n in node)
    if dataclasses.is_dataclass(node) and not isinstance(node, type):
        changes = {}
        for f in dataclasses.fields(node):
            if f.name == "span":
                continue
            old = getattr(node, f.name)
            new = map_expr(old, fn)
            if new is not old:
                changes[f.name] = new
        if changes:
            node = dataclasses.replace(node, **changes)
        out = fn(node)
        return node if out is None else out
    return node


def _scalar_subscript(node: Any) -> Any | None:
    """T1: tab_F[2] as an array subscript -> the flat scalar named tab_F[2]."""
    if (isinstance(node, ir.Subscript) and isinstance(node.base, ir.Ref)
            and all(isinstance(i, ir.IntLiteral) for i in node.indices)):
        return ir.Ref((node.base.name + "[" + ",".join(str(i.value) for i in node.indices) + "]",))
    return None


def _array_entry(name: str, binding: Any) -> Any:
    """T1: the flat element a[k] bound to a whole array literal {e1, e2, ...} -> e_k."""
    base, _, rest = name.partition("[")
    if isinstance(binding, ir.Array) and rest.endswith("]") and rest[:-1].isdigit():
        k = int(rest[:-1])
        if not 1 <= k <= len(binding.elements):
            raise ValueError(f"{name}: the array literal has {len(binding.elements)} entries")
        return binding.elements[k - 1]
    return binding


def _names(node: Any) -> set[str]:
    """Every variable name an IR node (expression, equation, when-clause) reads or assigns."""
    found: set[str] = set()

    def visit(n: Any) -> None:
        if isinstance(n, ir.Ref):
            found.add(n.name)
        return None

    map_expr(node, visit)
    return found


def transform(flat: FlatModel, inputs: dict[str, float]) -> tuple[FlatModel, list[str]]:
    """T1-T6 of the module docstring; returns the flat model and a log of what each changed."""
    log: list[str] = []
    variables: list[FlatVariable] = []
    unknown_inputs = set(inputs) - {v.name for v in flat.variables if v.causality == "input"}
    if unknown_inputs:
        raise KeyError(f"not inputs of {MODEL}: {sorted(unknown_inputs)}")
    drop = REMOVED
    for v in flat.variables:
        if v.name in drop:
            continue
        if v.is_constant and v.binding is not None:                                     # T1
            binding = _array_entry(v.name, v.binding)
            binding = map_expr(binding, _scalar_subscript)
            if binding != v.binding:
                log.append(f"T1 {v.name}: subscripts in the binding as flat scalars")
                v = dataclasses.replace(v, binding=binding)
        if v.causality == "input":                                                      # T2
            value = float(inputs.get(v.name, 0.0))
            log.append(f"T2 input {v.name} -> parameter = {value!r}")
            v = dataclasses.replace(v, variability="parameter", causality="none",
                                    binding=ir.RealLiteral(value))
        variables.append(v)
    # T3-T6: an equation or when-clause naming a removed variable goes. Were one of them to define a kept
    # variable, the model would lose an equation and causalize() would refuse it as unbalanced.
    def removed_by(node: Any) -> str | None:
        names = _names(node)
        return next((tag for tag, group in REMOVED_BY.items() if names & group), None)

    def kept_of(nodes: list, what: str) -> list:
        out = []
        for node in nodes:
            tag = removed_by(node)
            if tag:
                log.append(f"{tag} removed the {what} of {sorted(_names(node) & REMOVED)}")
            else:
                out.append(node)
        return out

    equations = kept_of(flat.equations, "equation")
    whens = kept_of(flat.whens, "when-clause")
    kept = {v.name for v in variables}
    for a in flat.asserts:
        missing = _names(a) & drop
        if missing:
            raise RuntimeError(f"an assert reads the removed {sorted(missing)}")
    assert not (drop & kept)
    return dataclasses.replace(flat, variables=tuple(variables), equations=tuple(equations),
                               whens=tuple(whens)), log


# ------------------------------------------------------------------------------------------ a case
def run(case: dict[str, Any]) -> dict[str, Any]:
    """Flatten, transform, causalize and simulate one case; the outputs at the communication points."""
    clock = {}
    t0 = time.perf_counter()
    mo_text = Path(case["mo"]).read_text(encoding="utf-8")
    flat = flatten([parse(case_source(mo_text, case.get("params", {})))], CASE_MODEL)
    flat, log = transform(flat, case.get("inputs", {}))
    system = causalize(flat)
    clock["compile_s"] = time.perf_counter() - t0
    grid = np.asarray(case["times"], dtype=float)
    if grid[0] != 0.0 or np.any(np.diff(grid) <= 0):
        raise ValueError("times must start at 0 and increase")
    t1 = time.perf_counter()
    result = simulate(system, stop=float(grid[-1]), times=grid, tolerance=float(case["tolerance"]),
                      absolute=float(case["absolute"]), method=case.get("method", "Radau"))
    clock["simulate_s"] = time.perf_counter() - t1
    # The requested times are merged into the solver's steps: pick each one (its last sample, the value
    # after an event at that instant, as the FMU reads it at the end of a communication step).
    idx = np.searchsorted(result.time, grid, side="right") - 1
    if np.any(idx < 0) or not np.allclose(result.time[idx], grid, rtol=0, atol=1e-12):
        raise RuntimeError("the result misses communication points")
    out: dict[str, Any] = {"t": grid.tolist()}
    for name in case["outputs"]:
        out[name] = np.asarray(result[name])[idx].tolist()
    out["states"] = list(system.states)
    out["events"] = len(result.events)
    out["transformations"] = log
    out["timing"] = clock
    return out


def main(argv: list[str]) -> int:
    """python run_modelica.py CASE.json OUT.json"""
    if len(argv) != 3:
        print(main.__doc__, file=sys.stderr)
        return 2
    case = json.loads(Path(argv[1]).read_text(encoding="utf-8"))
    Path(argv[2]).write_text(json.dumps(run(case)), encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
