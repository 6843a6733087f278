"""Residual statements in the units the test has: where time was derived from a nominal rate, a periodic
misfit is a waviness along the drive (mm of displacement), never a frequency or a resonance; and the console,
diagnosis.json and the report print one text for it."""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from fmusa.diagnose.calibrate import Fit
from fmusa.diagnose.measured import Experiment


def _experiments(derived: bool) -> tuple[list[Experiment], Fit]:
    """Two ramps to 3 mm at 0.01 and 0.1 mm/s (time from the rate when ``derived``) whose residual is a
    waviness of 0.30 mm period along the displacement, 2 N, with 0.2 N noise."""
    rng = np.random.default_rng(4)
    exps, preds = [], []
    for rate in (1e-5, 1e-4):
        y = np.linspace(0.0, 3e-3, 600)
        t = y / rate
        F = 1e5 * y + rng.normal(0.0, 0.2, y.size)
        meta = {"time_derived": True, "rate_si": rate} if derived else {}
        exps.append(Experiment(name=f"{rate}", path=Path("x.csv"), drive="displacement", t=t, displacement=y,
                               force=F, meta=meta))
        preds.append(F + 2.0 * np.sin(2 * np.pi * y / 0.30e-3))
    rss = float(sum(np.sum((p - e.force) ** 2) for p, e in zip(preds, exps)))
    fit = Fit(effect="none", params={"c_y": 1e5}, ci95={}, rss=rss, n=1200, k=1, rmse=float(np.sqrt(rss / 1200)),
              predictions=preds)
    return exps, fit


def test_derived_time_gives_a_waviness_in_mm():
    from fmusa.diagnose.run import _structure
    from fmusa.diagnose.views import structure_text

    exps, fit = _experiments(derived=True)
    st = _structure(fit, exps, "displacement")
    assert st["axis"]["derived_time"] and st["axis"]["unit"] == "mm"
    text = st["description"]
    m = re.search(r"waviness with a period of ([0-9.]+) mm of displacement", text)
    assert m, text
    assert float(m.group(1)) == pytest.approx(0.30, rel=0.03)
    assert "Hz" not in text and "resonance" not in text
    assert text == structure_text(st, "N", 1.0)        # one text for console, json and report


def test_measured_time_keeps_the_frequency():
    """Two rates with a real time axis: the same waviness is at two frequencies, one per rate; the text is in
    Hz (an oscillation in time) or, when none recurs jointly, no period in mm is invented."""
    from fmusa.diagnose.run import _structure

    exps, fit = _experiments(derived=False)
    st = _structure(fit, exps, "displacement")
    assert not st["axis"]["derived_time"]
    assert "mm of displacement" not in st["description"].split("from")[0]
