"""Shared fixtures: the real built FMU (built with `make fmu` when missing)."""
from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FMU = ROOT / "dist" / "ScrewVertebra.fmu"


@pytest.fixture(scope="session")
def fmu_path() -> Path:
    if not FMU.exists():
        proc = subprocess.run(["make", "fmu"], cwd=ROOT, capture_output=True, text=True)
        if proc.returncode != 0:
            pytest.fail(f"`make fmu` failed:\n{proc.stdout}\n{proc.stderr}")
    return FMU
