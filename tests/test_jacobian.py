"""The Jacobian columns the FMU writes in closed form (fmu/model.c: jacobian_columns, the translations, their
rates and the Cardan rates of the force-driven model) equal the complex-step derivative of the same right-hand
side, which is exact to rounding: at 2000 random states with angles up to 1 rad, interaction point and centre of
gravity off the axis, tilted principal axes and random loads (tests/jacobian/jacobian_check.c, compiled here
against the model's own sources). Criterion: every entry within 1e-12 of its column's largest entry."""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

from accuracy import record

ROOT = Path(__file__).resolve().parents[1]


def test_closed_form_columns_equal_the_complex_step(tmp_path, fmu_path):
    if not shutil.which("gcc"):
        pytest.skip("needs gcc")
    exe = tmp_path / "jacobian_check"
    # fmu/ first: the model's sources; build/fmu/sources only for the generated variables.h
    subprocess.run(["gcc", "-std=c99", "-O2", "-I", str(ROOT / "fmu"), "-I", str(ROOT / "build" / "fmu" / "sources"),
                    "-o", str(exe), str(ROOT / "tests" / "jacobian" / "jacobian_check.c"), str(ROOT / "fmu" / "solver.c"),
                    "-lm"], check=True)
    out = subprocess.run([str(exe), "2000", "7"], capture_output=True, text=True, check=True).stdout.split()
    worst, columns = float(out[0]), int(out[1])
    record("Jacobian columns closed form vs complex step", "2000 states", **{"entry/column max": worst})
    assert columns == 2000 * 9
    assert worst <= 1e-12, f"closed-form Jacobian columns differ from the complex step by {worst:.3e} x column max"
