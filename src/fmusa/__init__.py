"""fmusa: run an FMI 2.0 co-simulation FMU many times to find a-priori unknown model parameters.

The package is built around the ScrewVertebra FMU (dist/ScrewVertebra.fmu) of Kramer & Bauer's
screw-vertebra pullout model. Only :mod:`fmusa.evaluate` talks to FMUs.
"""

__version__ = "0.1.0"
