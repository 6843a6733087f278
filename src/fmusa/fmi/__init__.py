"""The FMI layer: the only code of fmusa that talks to an FMU (through fmpy).

``info`` reads what an FMU declares without loading it and holds the load-time checks and the FMU errors;
``build`` builds a missing binary from the FMU's C sources; ``runner`` is :class:`FMURunner`, one
instantiated FMU run again and again; ``plans`` prepares repeated runs on a runner (``RunPlan`` for a
study's scenario, ``DrivenPlan`` for a measured drive). It imports only the base modules.
"""
