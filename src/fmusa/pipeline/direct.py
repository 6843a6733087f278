"""FMU runs outside the run store, on the study's prepared FMU: checks and applications that need a run's
whole trajectory or a changed scenario (a finer sampling, another end time) rather than a row of runs.csv.
"""
from __future__ import annotations

from fmusa.fmi.runner import FMURunner
from fmusa.runs.spec import PlanSpec


def open_runner(spec: PlanSpec) -> FMURunner:
    """An FMURunner on ``spec``'s FMU (already prepared by the pipeline: built from its sources when it had
    no binary for this machine), run with the study's ``fmu_options``. Close it (or use ``with``)."""
    return FMURunner(spec.fmu_path, interface=spec.interface, solver=spec.solver,
                     relative_tolerance=spec.relative_tolerance, step_size=spec.step_size)
