"""The shear application's prediction bands of a held-out rate: the split conformal quantile (a closed form),
and the discrepancy across units (exchangeable specimens: the pooled share inside is the nominal level)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from fmusa.applications.shear_c67.prediction import add_population_bands, conformal_half_width


def test_conformal_half_width_is_the_rank_of_the_level():
    """⌈0.95 (n + 1)⌉-th smallest |error|: 19 errors 1..19 give 19, 39 give 38; too few errors give no band."""
    assert conformal_half_width(np.arange(1, 20)) == 19.0
    assert conformal_half_width(-np.arange(1, 40)) == 38.0
    assert math.isinf(conformal_half_width(np.arange(1, 10)))
    assert conformal_half_width(np.arange(1, 101), level=0.5) == 51.0


def _unit(rng, scale: float, peak: float, n: int = 50, within: float = 0.0) -> list[dict]:
    pred = np.linspace(0.0, peak, n)
    meas = pred + rng.normal(0.0, scale * peak, n)
    return [{"rate_mm_s": 100.0, "trained_on": [1.0, 10.0], "prediction_N": pred.tolist(), "measured_N": meas.tolist(),
             "predicted_peak_N": peak, "peak_N": float(np.max(np.abs(meas))), "within_half_width_N": within}]


def test_population_band_is_the_other_units_relative_quantile():
    """Unit A's band is the 95 % quantile of the other units' errors relative to their predicted peak, times
    A's predicted peak, or the within-unit half-width when that is larger; a rate predicted from other rates is
    another population."""
    rng = np.random.default_rng(1)
    bands = {"A": _unit(rng, 0.02, 200.0), "B": _unit(rng, 0.02, 300.0), "C": _unit(rng, 0.05, 100.0, within=40.0)}
    bands["D"] = [dict(_unit(rng, 0.5, 100.0)[0], rate_mm_s=1.0, trained_on=[10.0, 100.0])]
    rel = [np.abs(np.subtract(b[0]["measured_N"], b[0]["prediction_N"])) / b[0]["predicted_peak_N"] for b in
           (bands["B"], bands["C"])]
    want = conformal_half_width(np.concatenate(rel)) * 200.0
    add_population_bands(bands)
    a = bands["A"][0]
    assert a["population_units"] == 2 and a["population_half_width_N"] == pytest.approx(want)
    assert a["half_width_N"] == pytest.approx(want) and a["half_width_rel_peak"] == pytest.approx(want / a["peak_N"])
    err = np.abs(np.subtract(a["measured_N"], a["prediction_N"]))
    assert a["share_inside"] == pytest.approx(float(np.mean(err <= want)))
    assert bands["C"][0]["half_width_N"] == 40.0 > bands["C"][0]["population_half_width_N"]
    assert bands["D"][0]["population_units"] == 0 and bands["D"][0]["half_width_N"] == 0.0


def test_population_band_covers_exchangeable_units():
    """40 units whose relative errors come from one distribution (peaks 80-330 N, heavy tails): pooled over
    the units, 93-97 % of the samples fall inside the nominal 95 % band."""
    rng = np.random.default_rng(7)
    bands = {}
    for i in range(40):
        peak = float(rng.uniform(80.0, 330.0))
        pred = np.linspace(0.0, peak, 60)
        meas = pred + peak * 0.03 * rng.standard_t(4, pred.size)
        bands[f"U{i}"] = [{"rate_mm_s": 10.0, "trained_on": [1.0, 100.0], "prediction_N": pred.tolist(),
                           "measured_N": meas.tolist(), "predicted_peak_N": peak, "peak_N": peak,
                           "within_half_width_N": 0.0}]
    add_population_bands(bands)
    pooled = np.mean([b[0]["share_inside"] for b in bands.values()])
    assert 0.93 <= pooled <= 0.97, pooled
