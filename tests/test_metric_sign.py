"""A metric is reduce(scale × output) + offset: a negative scale flips the axis before the reduction.

The oscillator of tests/fmus/faulty moves from x0 = 0.5 m down past its rest position (load F = -200 N,
k = 100 N/m); with ``scale: -1000`` (m to mm along the flipped axis) ``max`` is its deepest point as a
positive number of mm, compared with the closed form at the same samples.
"""
from __future__ import annotations

import numpy as np
import pytest

from faulty_fmu import build_faulty, closed_form
from fmusa.api import run_study
from fmusa.study.loader import load_study


def test_negative_scale_flips_the_axis_before_the_reduction(tmp_path, monkeypatch):
    monkeypatch.setenv("FMUSA_CACHE_DIR", str(tmp_path / "cache"))
    fmu = build_faulty(tmp_path, me=False)
    study = tmp_path / "study.yaml"
    study.write_text(f"""\
name: sign
fmu: {fmu}
parameters:
  k: {{variable: k, unit: N/m}}
fixed:
  F: -200
scenario: {{stop_time: 2, step: 0.01}}
metrics:
  down_max: {{output: x, reduce: max, scale: -1000, unit: mm}}
  down_min: {{output: x, reduce: min, scale: -1000, unit: mm}}
  down_abs: {{output: x, reduce: max_abs, scale: -1000, unit: mm}}
  up_max: {{output: x, reduce: max, scale: 1000, unit: mm}}
stages:
  grid: {{values: {{k: [100]}}}}
execution: {{workers: 1}}
""", encoding="utf-8")
    res = run_study(load_study(study), tmp_path / "out", figures=False, progress=False)
    row = res.runs.iloc[0]
    x, _ = closed_form(np.arange(201) * 0.01, k=100.0, F=-200.0)
    assert x.min() < -3                                     # it does go down, well past 0
    assert row["down_max"] == pytest.approx(-1000 * x.min(), rel=1e-5)     # the deepest point, positive
    assert row["down_min"] == pytest.approx(-1000 * x.max(), rel=1e-5)     # -500 mm: the start
    assert row["down_abs"] == pytest.approx(1000 * np.abs(x).max(), rel=1e-5) and row["down_abs"] > 0
    assert row["up_max"] == pytest.approx(1000 * x.max(), rel=1e-5)
