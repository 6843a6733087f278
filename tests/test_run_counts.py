"""One count of runs everywhere: the console line, the report's runs row and summary.json's run_counts agree
with the files on disk (runs.csv, sensitivity_runs.csv, the sensitivity reference runs), on a first run and
on a resume; every stage that simulated something reports its rounds.

The FMU is a closed form (tests/formula_fmu.py): y = F / k, cheap, so a grid, a search and a small Morris
sensitivity stage take a few seconds.
"""
from __future__ import annotations

import json
import re

import pandas as pd
import pytest

from formula_fmu import build_formula_fmu
from fmusa.cli import main


def test_console_report_and_summary_count_the_same_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("FMUSA_CACHE_DIR", str(tmp_path / "cache"))
    fmu = build_formula_fmu(tmp_path, "Spring", {"k": 1.0, "F": 10.0}, {"y": "F / k"})
    study = tmp_path / "counts.yaml"
    study.write_text(f"""\
name: counts
fmu: {fmu}
parameters:
  k: {{variable: k}}
  F: {{variable: F}}
scenario: {{stop_time: 1, step: 0.5}}
metrics:
  y: {{output: y, reduce: final}}
constraints:
  - {{name: small, metric: y, max: 0.5}}
stages:
  grid: {{values: {{k: [10, 100, 1000], F: [10, 20]}}}}
  roi:
  search: {{inner: k, inner_rtol: 1.0e-2}}
  sensitivity:
    methods: [morris]
    morris_trajectories: 4
    seed: 1
    outputs: [y]
    parameters:
      k: {{variable: k, bounds: [10, 1000], distribution: loguniform}}
      F: {{variable: F, bounds: [5, 20]}}
execution: {{workers: 1}}
""", encoding="utf-8")
    out = tmp_path / "out"
    for args in ([], ["--resume", "--no-figures"]):     # the report once: its figures cost most of the time
        assert main(["sweep", str(study), "--out", str(out), "--quiet", *args]) == 0
        console = capsys.readouterr().out
        s = json.loads((out / "summary.json").read_text())
        rc = s["run_counts"]
        on_disk = (len(pd.read_csv(out / "runs.csv")) + len(pd.read_csv(out / "sensitivity_runs.csv"))
                   + rc["sensitivity_reference"])
        assert rc["runs"] == on_disk == rc["runs_csv"] + rc["sensitivity"] + rc["sensitivity_reference"]
        assert rc["simulated_now"] <= rc["runs"]
        m = re.search(r"counts: (\d+) runs \((\d+) simulated now, (\d+) failed\)", console)
        assert m and (int(m[1]), int(m[2]), int(m[3])) == (rc["runs"], rc["simulated_now"], rc["failed"])
        if not args:
            report = (out / "report.md").read_text(encoding="utf-8")
            assert f"| runs | {rc['runs']} ({rc['simulated_now']} simulated in this session) |" in report
        for stage, v in s["stage_runs"].items():
            assert (v["rounds"] > 0) == (v["simulated"] > 0), (stage, v)
            assert v["simulated"] <= v["asked"]
        assert sum(v["simulated"] for v in s["stage_runs"].values()) == rc["simulated_now"]
    assert rc["simulated_now"] == 0           # the resume made nothing again
