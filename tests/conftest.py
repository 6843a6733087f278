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


def pytest_terminal_summary(terminalreporter):
    """The worst errors the physics suites measured in this run (tests/accuracy.py)."""
    from accuracy import summary_lines

    lines = summary_lines()
    if lines:
        terminalreporter.section("accuracy: worst errors measured")
        for line in lines:
            terminalreporter.write_line(line)


def pytest_addoption(parser):
    parser.addoption("--run-slow", action="store_true", default=False,
                     help="also run the tests marked slow (e.g. the identifiability cells kept out of `make test`)")


def pytest_configure(config):
    config.addinivalue_line("markers", "slow: a long test that runs only with --run-slow (not in `make test`)")


def pytest_collection_modifyitems(config, items):
    if config.getoption("--run-slow"):
        return
    skip = pytest.mark.skip(reason="slow: run with --run-slow")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
