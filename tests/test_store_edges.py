"""The run store's edges: a header reordered by hand, runs.csv removed during a sweep, the folder's lock held
until the report is written, a row torn inside a multi-line quoted message.

The FMU is a closed form (tests/formula_fmu.py): y = F / k, refused (fmi2Error, a message of two lines) at
k > 900, so a study has failed runs with messages.
"""
from __future__ import annotations

import json
import shutil

import numpy as np
import pandas as pd
import pytest

from formula_fmu import build_formula_fmu
from fmusa.api import parse_study, run_study
from fmusa.files import OutputError
from fmusa.pipeline.sweep import run_study as run_stages
from fmusa.runs.store import RunStore, StoreBusyError


@pytest.fixture(scope="module")
def fmu(tmp_path_factory):
    return build_formula_fmu(tmp_path_factory.mktemp("spring"), "Spring", {"k": 1.0, "F": 10.0},
                             {"y": "F / k"}, refuse="k > 900", refuse_message="k too large\\nsee the manual")


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("FMUSA_CACHE_DIR", str(tmp_path / "cache"))


def study(fmu, ks, fs=(10.0, 20.0)):
    return parse_study(f"""\
name: spring
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
  grid: {{values: {{k: {list(ks)}, F: {list(fs)}}}}}
execution: {{workers: 1}}
""")


def sweep(s, out, **kw):
    return run_study(s, out, figures=False, progress=False, **kw)


def test_reordered_columns_are_read_by_name_on_resume(fmu, tmp_path):
    out = tmp_path / "out"
    sweep(study(fmu, [10, 100]), out)
    df = pd.read_csv(out / "runs.csv")
    df[list(reversed(df.columns))].to_csv(out / "runs.csv", index=False)    # reordered by hand
    res = sweep(study(fmu, [10, 100, 1000]), out, resume=True)
    fresh = sweep(study(fmu, [10, 100, 1000]), tmp_path / "fresh")
    assert res.summary["runs"] == fresh.summary["runs"] == 6
    assert res.summary["grid"]["feasible"] == fresh.summary["grid"]["feasible"]
    again = pd.read_csv(out / "runs.csv")
    assert list(again.columns) == list(pd.read_csv(tmp_path / "fresh" / "runs.csv").columns)
    a, b = (x.sort_values(["k", "F"])[["k", "F", "y"]].to_numpy() for x in (again, pd.read_csv(tmp_path / "fresh" / "runs.csv")))
    np.testing.assert_array_equal(a, b)
    assert set(zip(again["k"], again["F"])) <= {(k, f) for k in (10, 100, 1000) for f in (10, 20)}


def test_an_unknown_column_refuses_to_resume(fmu, tmp_path):
    out = tmp_path / "out"
    sweep(study(fmu, [10]), out)
    df = pd.read_csv(out / "runs.csv")
    df["note"] = "mine"
    df.to_csv(out / "runs.csv", index=False)
    with pytest.raises(Exception, match="columns note are not the study's"):
        sweep(study(fmu, [10]), out, resume=True)


def test_runs_csv_removed_during_the_study_is_an_error(fmu, tmp_path):
    out = tmp_path / "out"

    class Remove:
        name = "remove"

        def after_stages(self, result, runner):
            shutil.rmtree(out)
            runner.evaluate([{"k": 50.0, "F": 10.0}], "extra")      # a run after the folder went

    with pytest.raises(OutputError, match="deleted, moved or replaced"):
        run_stages(study(fmu, [10]), out, progress=False, extensions=[Remove()])
    assert not (out / "summary.json").exists()


def test_the_lock_is_held_until_the_report_is_written(fmu, tmp_path):
    out = tmp_path / "out"
    s = study(fmu, [10])
    res = run_stages(s, out, progress=False, hold_lock=True)
    with pytest.raises(StoreBusyError, match="another fmusa study"):
        RunStore(out / "runs.csv", ["k", "F"], ["y"], s.constraints, resume=True)
    res.release()
    RunStore(out / "runs.csv", ["k", "F"], ["y"], s.constraints).close()
    sweep(s, tmp_path / "api")        # the API releases it after the report: a second study may start
    sweep(s, tmp_path / "api", resume=True)


def test_messages_on_one_line_and_a_torn_multiline_row_resumes(fmu, tmp_path):
    out = tmp_path / "out"
    sweep(study(fmu, [10, 1000]), out)
    text = (out / "runs.csv").read_text(encoding="utf-8")
    assert "k too large | see the manual" in text and len(text.splitlines()) == 5      # header + 4 runs
    # a file of an older version: the message spans two lines, and a kill tore the last row inside it
    lines = text.splitlines(keepends=True)
    torn = "".join(lines[:-1]) + lines[-1].replace(" | ", "\n").split("\n")[0] + "\n"
    (out / "runs.csv").write_text(torn.replace(" | ", "\r\n"), encoding="utf-8")
    res = sweep(study(fmu, [10, 1000]), out, resume=True)
    assert res.summary["runs"] == 4 and res.summary["simulated_this_session"] == 1
    assert res.summary["failed"] == 2
