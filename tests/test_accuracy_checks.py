"""A peak between two output samples: the accuracy checks after the stages find it and say so.

tests/formula_fmu.py builds a C FMU whose output is y(t) = (0.1 t + exp(-((t - 0.505)/0.002)²)) / p:
a pulse 4 ms wide at t = 0.505 s, between the samples every 10 ms (where it reads below 0.002 / p). The
study bounds y_max <= 0.5 and searches the smallest feasible p: on the samples the optimum is p ≈ 0.2
(y_max = 0.1/p at t = 1), while the true peak (1 + 0.0505)/p needs p >= 2.1. The checks read finer than the
study's sampling (the sampling check throughout the run, the halved-step check at every halved step), so
both see the true peak; the console warns and summary.json marks the optimum unreliable.
"""
from __future__ import annotations

import json

import pytest

from formula_fmu import build_formula_fmu
from fmusa.cli import main

PULSE = "(0.1 * t + exp(-pow((t - 0.505) / 0.002, 2))) / p"


def true_peak(p: float) -> float:
    return (1 + 0.1 * 0.505) / p


def test_a_peak_between_samples_makes_the_optimum_unreliable(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("FMUSA_CACHE_DIR", str(tmp_path / "cache"))
    fmu = build_formula_fmu(tmp_path, "Pulse", {"p": 1.0}, {"y": PULSE})
    study = tmp_path / "pulse.yaml"
    study.write_text(f"""\
name: pulse
fmu: {fmu}
parameters:
  p: {{variable: p}}
scenario: {{stop_time: 1, step: 0.01}}
metrics:
  y_max: {{output: y, reduce: max}}
constraints:
  - {{name: cap, metric: y_max, max: 0.5}}
stages:
  grid: {{values: {{p: [0.04, 0.16, 0.64, 2.56, 10.24]}}}}
  roi:
  search: {{inner: p, inner_rtol: 1.0e-2}}
execution: {{workers: 1}}
""", encoding="utf-8")
    assert main(["sweep", str(study), "--out", str(tmp_path / "out"), "--no-figures", "--quiet"]) == 0
    out, err = capsys.readouterr()
    s = json.loads((tmp_path / "out" / "summary.json").read_text())
    p = s["optimum"]["p"]
    assert p == pytest.approx(0.2, rel=0.02)               # what the samples say
    assert true_peak(p) > 10 * 0.5                          # the real peak is ten times the bound
    assert s["optimum_reliable"] is False and s["accuracy"]["metrics"] == ["y_max"]
    assert "(unreliable" in out and "warning: the accuracy checks moved the constrained metric y_max" in err
    # the sampling check's reference and the halved step both see the true peak (closed form)
    at_opt = [c for c in s["sampling"]["checks"] if c["point"] == {"p": p}]
    assert at_opt and at_opt[0]["reference"] == pytest.approx(true_peak(p), rel=1e-3)
    halved = [c for c in s["fmu_steps"]["checks"] if c["point"] == {"p": p} and c["variant"].startswith("comm")]
    assert halved[0]["flagged"] and halved[0]["variant_value"] == pytest.approx(true_peak(p), rel=1e-9)
