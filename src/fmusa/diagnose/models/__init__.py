"""Built-in model descriptions: how a diagnosis drives an FMU it knows without a study file.

Each ``<modelName>.yaml`` here holds the ``model``, ``baseline`` and ``effects`` sections of a diagnosis
study file (:mod:`fmusa.diagnose.study`) for the FMU whose modelDescription.xml has that ``modelName``. When
``fmusa diagnose`` gets no study file, the description is chosen by the FMU's model name; an FMU without one
is refused before anything runs, with the way to write a study file for it.
"""
from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

from fmusa.diagnose.effects import DiagnoseError
from fmusa.diagnose.interface import ModelInterface
from fmusa.diagnose.study import builtin_names, builtin_path

__all__ = ["builtin_names", "builtin_path", "builtin_description", "description_for", "resolve"]

@lru_cache(maxsize=None)
def builtin_description(name: str) -> ModelInterface:
    """The built-in description ``name`` (read once)."""
    from fmusa.diagnose.study import parse_description
    from fmusa.study.loader import read_study_text

    path = builtin_path(name)
    if path is None:
        raise DiagnoseError(f"no built-in model description {name!r} (built-in: {', '.join(builtin_names())})")
    return parse_description(read_study_text(path), str(path), name=name)


def description_for(fmu_path: str | os.PathLike) -> ModelInterface:
    """The built-in description of the FMU's model, chosen by its modelName; a clear error when it has none."""
    from fmusa.fmi.info import read_fmu_info

    model = read_fmu_info(fmu_path).model_name
    if builtin_path(model) is None:
        raise DiagnoseError(
            f"{fmu_path}: fmusa has no description of how to drive the model {model!r} (built-in: "
            f"{', '.join(builtin_names())}): which input takes the measured drive, which output is compared with "
            f"the response, which parameters are the baseline and where the candidate effects go. Write them "
            f"into a diagnosis study file and run `fmusa diagnose STUDY.yaml` (see the docs page \"Diagnosing "
            f"your own model\")")
    return builtin_description(model)


def resolve(interface: ModelInterface | None, fmu_path: str | os.PathLike | None = None) -> ModelInterface:
    """``interface``, or when None the built-in description of the FMU (the default FMU when none is named)."""
    if interface is not None:
        return interface
    if fmu_path is None:
        from fmusa.fmi.info import default_fmu_path

        fmu_path = default_fmu_path()
    return description_for(fmu_path)
