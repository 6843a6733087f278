"""Many runs of a study's FMU: what they are (``spec``), where they run (``evaluator``: in this process,
supervised local workers in ``pool``, or Dask), what a run gives (``metrics``, ``refine`` for sampled
peaks), where results go (``store``: runs.csv) and the ``progress`` bar. Built on :mod:`fmusa.fmi`; knows no
study file.
"""
