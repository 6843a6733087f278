"""``fmusa diagnose``: calibrate a model and candidate effects through an FMU against measured tests.

A vertical of its own (it uses only fmusa.errors/format, fmusa.fmi and fmusa.runs), one module per job:
``measured`` (CSV files to checked SI experiments), ``effects`` (the candidates, their parameters and
bounds), ``interface`` (which FMU variables impose the drive and give the response), ``calibrate``
(least squares through the FMU, held-out scores), ``fitcache`` (fits in parallel, cached), ``rank``
(significance, winner, look-alikes), ``residuals`` (structure or noise), ``run`` (the whole diagnosis and
diagnosis.json), ``views`` (numbers shared by) ``figures`` and ``report`` (report.md).
"""
