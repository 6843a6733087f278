"""The Sobol indices of studies/six_dof.yaml on a smaller sample, as the sensitivity stage computes them.

Shared by tests/test_six_dof_sobol.py and by the command that wrote its baseline
(``python tests/six_dof_sobol.py --fmu OLD.fmu --out tests/data/six_dof_sobol_baseline.json``).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import tempfile
from pathlib import Path
from types import SimpleNamespace

ROOT = Path(__file__).resolve().parents[1]
#: Sobol base sample: N * (16 + 2) = 2304 runs
N = 128


def six_dof_sobol(fmu: Path, n: int = N, workers: int = 1) -> dict:
    """S1, S1_conf, ST, ST_conf per metric and parameter, and the run count."""
    from fmusa.pipeline.sensitivity import run_sensitivity
    from fmusa.study.loader import load_study

    study = load_study(ROOT / "studies" / "six_dof.yaml")
    study = dataclasses.replace(study, fmu=Path(fmu))
    stage = dataclasses.replace(study.stages["sensitivity"], methods=["sobol"], n=n)
    runner = SimpleNamespace(evaluator=SimpleNamespace(workers=workers, scheduler=None), simulated=0)
    with tempfile.TemporaryDirectory(prefix="fmusa-sobol-") as tmp:
        res = run_sensitivity(study, stage, Path(tmp), runner, progress=False, resume=False, accuracy_samples=0)
    s = res["summary"]
    return {"n": n, "runs": int(s["runs"]), "failed": int(s["failed"]), "rtol": study.fixed.get("rtol"),
            "sobol": s["sobol"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fmu", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--note", default="")
    args = ap.parse_args(argv)
    res = six_dof_sobol(args.fmu, workers=2)
    res["note"] = args.note
    args.out.write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
