"""Co-simulation: a user's FMU and fmusa's interface element FMU run together, exchanging force and motion.

``master`` couples the two (:class:`Coupling` is the system as data, :func:`simulate_coupled` runs it with a
scheme that holds at a stiff interface and says which ran and what it cost, :func:`check_coupling` checks the
variables before any run); ``ssp`` writes the coupled system as an SSP 1.0 archive that other tools run.
It sits beside ``runs`` (it imports the base and ``fmi``), below ``diagnose``.
"""
from fmusa.cosim.master import (CoupledResult, Coupling, CouplingError, CouplingTimeLimitError, check_coupling,
                                default_element_fmu, simulate_coupled)

__all__ = ["Coupling", "CoupledResult", "CouplingError", "CouplingTimeLimitError", "check_coupling",
           "default_element_fmu", "simulate_coupled"]
