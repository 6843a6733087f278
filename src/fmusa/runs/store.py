"""runs.csv: every run of a study, one row each, written as results arrive.

The key of a run is its study parameter values, so any stage that asks for a point already run (in this
session or, with ``resume``, in an interrupted one) gets the stored row instead of a new simulation.
"""
from __future__ import annotations

import csv
import math
import os
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import pandas as pd

from fmusa.errors import UsageError
from fmusa.runs.metrics import constraint_table

FLOAT = "%.17g"   # round-trips a double exactly, so reloaded keys match new ones


class RunStore:
    def __init__(self, path: str | os.PathLike, params: Sequence[str], metrics: Sequence[str],
                 constraints: Iterable = (), resume: bool = False) -> None:
        self.path = Path(path)
        self.params = list(params)
        self.metrics = list(metrics)
        self.constraints = list(constraints)
        self.columns = (["run_id", "stage"] + self.params + self.metrics
                        + [f"ok_{c.name}" for c in self.constraints]
                        + (["feasible"] if self.constraints else []) + ["status", "message", "seconds"])
        self.rows: dict[tuple[float, ...], dict] = {}
        self.next_id = 0
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if resume and self.path.exists() and self.path.stat().st_size > 0:
            self._load()
            self._fh = open(self.path, "a", newline="")
        else:
            self._fh = open(self.path, "w", newline="")
            csv.writer(self._fh).writerow(self.columns)
            self._fh.flush()
        self._writer = csv.writer(self._fh)

    def _load(self) -> None:
        df = pd.read_csv(self.path, keep_default_na=True)
        missing = [c for c in self.columns if c not in df.columns]
        if missing:
            raise UsageError(f"{self.path}: cannot resume: columns {', '.join(missing)} are missing "
                             f"(the study changed?); start afresh without --resume or use another --out")
        for rec in df.to_dict("records"):
            if not isinstance(rec.get("message"), str):
                rec["message"] = ""
            self.rows[self.key([rec[p] for p in self.params])] = rec
        self.next_id = int(df["run_id"].max()) + 1 if len(df) else 0

    @staticmethod
    def key(values: Sequence[float]) -> tuple[float, ...]:
        return tuple(float(v) for v in values)

    def get(self, values: Sequence[float]) -> dict | None:
        return self.rows.get(self.key(values))

    def new_id(self) -> int:
        i = self.next_id
        self.next_id += 1
        return i

    def add(self, run_id: int, stage: str, values: Sequence[float], metrics: np.ndarray | None,
            status: str, message: str, seconds: float) -> dict:
        rec: dict = {"run_id": run_id, "stage": stage}
        rec.update(zip(self.params, map(float, values)))
        mvals = metrics if metrics is not None else np.full(len(self.metrics), np.nan)
        rec.update(zip(self.metrics, map(float, mvals)))
        if self.constraints:
            table = constraint_table({k: np.array([rec[k]]) for k in self.metrics}, self.constraints)
            for k, v in table.items():
                rec[k] = bool(v[0]) and status == "ok"
        rec.update(status=status, message=message, seconds=float(seconds))
        self.rows[self.key(values)] = rec
        self._writer.writerow([self._fmt(rec[c]) for c in self.columns])
        self._fh.flush()
        return rec

    @staticmethod
    def _fmt(x):
        if isinstance(x, (bool, np.bool_)):
            return "True" if x else "False"
        if isinstance(x, float):
            return "" if math.isnan(x) else FLOAT % x
        return x

    def frame(self, stage: str | None = None) -> pd.DataFrame:
        df = pd.DataFrame(list(self.rows.values()), columns=self.columns)
        if stage is not None:
            df = df[df["stage"] == stage]
        return df.sort_values("run_id").reset_index(drop=True)

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()
