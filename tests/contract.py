"""The FMU's variable contract for the tests: what fmu/generate.py reads from modelica/ScrewVertebra.mo.

fmu/generate.py is a build script, not part of the package (an installed fmusa has no fmu/ folder), so
the tests load it from the repository; the Modelica parser it needs is in the ``fmu`` extra. A test run
where that is not installed (``.ci/pythons``) reads a built FMU's modelDescription.xml instead
(:func:`fmu_variables`).
"""
from __future__ import annotations

import functools
import importlib.util
import sys
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]
GENERATE = ROOT / "fmu" / "generate.py"


@functools.cache
def generator() -> ModuleType:
    """fmu/generate.py as a module (registered, so its dataclasses resolve their own module)."""
    spec = importlib.util.spec_from_file_location("fmusa_fmu_generate", GENERATE)
    module = importlib.util.module_from_spec(spec)          # type: ignore[arg-type]
    sys.modules[spec.name] = module                          # type: ignore[union-attr]
    spec.loader.exec_module(module)                          # type: ignore[union-attr]
    return module


@functools.cache
def variables() -> tuple:
    """The FMU's scalar variables (fmu/generate.py's ``Variable``) in value-reference order."""
    return tuple(generator().read_model().variables)


def fmu_variables(fmu: Path) -> dict[str, dict[str, str]]:
    """name -> the attributes of its ScalarVariable (plus ``type``, ``unit``, ``start``) in an FMU's
    modelDescription.xml, in value-reference order; standard library only."""
    with zipfile.ZipFile(fmu) as z:
        root = ET.fromstring(z.read("modelDescription.xml"))
    out = {}
    for sv in root.iter("ScalarVariable"):
        typed = next(iter(sv))
        out[sv.get("name")] = {**sv.attrib, "type": typed.tag, "unit": typed.get("unit", ""),
                               "start": typed.get("start", "")}
    return out
