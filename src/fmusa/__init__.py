"""fmusa: run an FMI 2.0 FMU many times to find a-priori unknown model parameters.

The package is built around the ScrewVertebra FMU (dist/ScrewVertebra.fmu) of Kramer & Bauer's
screw-vertebra pullout model, but runs any FMI 2.0 co-simulation or model exchange FMU. Only
:mod:`fmusa.fmi` talks to FMUs.

The public API, what the README's Python examples use::

    import fmusa
    study = fmusa.load_study("studies/paper.yaml")
    result = fmusa.run_study(study, "out/paper")          # runs.csv, summary.json, figures, report.md
    with fmusa.FMURunner() as fmu:                         # dist/ScrewVertebra.fmu, or $FMUSA_FMU
        df = fmu.run({"c_y": 8e5}, stop_time=12, step=0.01, outputs=["y"])
    info = fmusa.read_fmu_info("dist/ScrewVertebra.fmu")
    diag = fmusa.diagnose(experiments, "displacement")     # experiments: fmusa.diagnose.measured

Each name is imported on first use (PEP 562 ``__getattr__``), so ``import fmusa`` (and with it the
``fmusa`` command's ``--help``) loads neither numpy, pandas, scipy nor fmpy. Errors in the user's input
are :class:`FmusaError` subclasses.
"""
from __future__ import annotations

import importlib as _importlib

from fmusa.errors import FmusaError

__version__ = "0.1.0"

#: Public name -> the module that defines it (imported when the name is first used).
_EXPORTS: dict[str, str] = {
    "load_study": "fmusa.api",
    "run_study": "fmusa.api",
    "write_report": "fmusa.api",
    "FMURunner": "fmusa.fmi.runner",
    "read_fmu_info": "fmusa.fmi.info",
}
__all__ = ["__version__", "FmusaError", "load_study", "run_study", "write_report", "FMURunner", "read_fmu_info",
           "diagnose"]

TYPE_CHECKING = False   # typing.TYPE_CHECKING without importing typing (~14 ms of every spawned worker)
if TYPE_CHECKING:   # for type checkers and IDEs; at run time each comes from __getattr__
    from fmusa.api import load_study, run_study, write_report
    from fmusa.fmi.info import read_fmu_info
    from fmusa.fmi.runner import FMURunner


def __getattr__(name: str) -> object:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'fmusa' has no attribute {name!r}")
    value = getattr(_importlib.import_module(module), name)
    globals()[name] = value          # later look-ups skip __getattr__
    return value


def __dir__() -> list[str]:
    hidden = ("TYPE_CHECKING", "annotations")
    return sorted(set(__all__) | {k for k in globals() if not k.startswith("_") and k not in hidden})


# The subpackage fmusa.diagnose is imported first (it holds only a docstring): importing a subpackage binds it
# as an attribute of its parent, and the function below must be the one that stays bound.
_importlib.import_module("fmusa.diagnose")


def diagnose(experiments_or_study: object, drive: str | None = None, **kwargs: object) -> dict:
    """The diagnosis: ``fmusa.diagnose(experiments, "displacement")`` or ``fmusa.diagnose("study.yaml")``
    (:func:`fmusa.api.diagnose`)."""
    return _importlib.import_module("fmusa.api").diagnose(experiments_or_study, drive, **kwargs)


# `import fmusa.diagnose.run as m` looks `run` up on fmusa.diagnose (this function) and, not finding it there,
# takes the module sys.modules[f"{fmusa.diagnose.__name__}.run"]: the name keeps every such import working.
diagnose.__name__ = "fmusa.diagnose"
