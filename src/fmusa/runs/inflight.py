"""The runs a study is making in its own process, on disk while they run (``<runs file>.running``).

A run made in the study's process (our own FMU in a small batch, :mod:`fmusa.runs.timelimit`) that crashes
or exits inside the FMU takes the study down with it, and a resume would make it again and crash again.
So before a chunk of such runs starts, its run ids and values are written to the marker, and it is emptied
when their results are stored. A resume that finds the marker not empty knows which runs were under way when
the process ended: one run is recorded as failed with that reason (never made again by a resume); several
are made again in supervised workers, where a crash costs one run, not the study.

The marker is a memory-mapped file (a shared mapping: what is written reaches the file when the process
ends, however it ends), so noting a chunk costs no system call: a search makes its runs one at a time, and
a write and a truncate per run would cost more than a cheap run. No fsync: the marker has to outlive the
process, not the machine. Layout: ``FMUSA-RUNNING`` (16 bytes), then int64 n, k, stage length, the stage
(64 bytes), the n run ids (int64) and the n × k values (float64), little-endian.
"""
from __future__ import annotations

import mmap
import os
from pathlib import Path
from typing import Sequence

import numpy as np

#: The message of a run that was under way when the study's process ended.
CRASH_REASON = ("the study's process ended during this run in an earlier session (the FMU crashed or exited "
                "inside it, or the process was killed), so it is recorded as failed and a resume does not make "
                "it again; rerun without --resume (or delete its line from the runs file) to try it again")

_MAGIC = b"FMUSA-RUNNING\0\0\0"
_HEAD = 16 + 3 * 8 + 64          # magic, n, k, stage length, stage


class InFlight:
    """The marker file of one runs file: :meth:`begin` a chunk, :meth:`end` it, :meth:`pending` on resume."""

    def __init__(self, runs_path: str | os.PathLike) -> None:
        self.path = Path(str(runs_path) + ".running")
        self._fh = None
        self._mm: mmap.mmap | None = None
        #: the stage of the runs about to be made (the label they are stored under)
        self.stage = ""

    def _map(self, size: int) -> mmap.mmap:
        """The mapping, at least ``size`` bytes (the file grows by doubling; made on first use)."""
        if self._mm is not None and len(self._mm) >= size:
            return self._mm
        cap = max(65536, 1 << (size - 1).bit_length())
        if self._fh is None:
            self._fh = open(self.path, "w+b")
        if self._mm is not None:
            self._mm.close()
        self._fh.truncate(cap)
        self._mm = mmap.mmap(self._fh.fileno(), cap)
        self._mm[:16] = _MAGIC
        return self._mm

    def begin(self, ids: Sequence[int], values) -> None:
        """The chunk ``ids`` (study values ``values``, one row per run) is about to run in this process."""
        ids = np.asarray(ids, dtype="<i8").ravel()
        vals = np.asarray(values, dtype="<f8").reshape(len(ids), -1)
        n, k = vals.shape
        mm = self._map(_HEAD + 8 * n * (k + 1))
        stage = self.stage.encode("utf-8")[:64]
        mm[_HEAD:_HEAD + 8 * n] = ids.tobytes()
        mm[_HEAD + 8 * n:_HEAD + 8 * n * (k + 1)] = vals.tobytes()
        mm[40:40 + len(stage)] = stage
        mm[24:40] = np.array([k, len(stage)], dtype="<i8").tobytes()
        mm[16:24] = n.to_bytes(8, "little")               # last: the chunk is complete

    def end(self) -> None:
        """The chunk's results are stored: nothing is under way."""
        if self._mm is not None:
            self._mm[16:24] = bytes(8)

    def pending(self) -> tuple[str, list[tuple[int, tuple[float, ...]]]]:
        """(stage, [(run id, values)]) of the chunk that was under way when a process ended; empty when none
        (or when the file is not a marker)."""
        try:
            raw = self.path.read_bytes()
        except OSError:
            return "", []
        if len(raw) < _HEAD or raw[:16] != _MAGIC:
            return "", []
        n, k, ls = (int(x) for x in np.frombuffer(raw[16:40], dtype="<i8"))
        if n <= 0 or not 0 <= ls <= 64 or len(raw) < _HEAD + 8 * n * (k + 1):
            return "", []
        stage = raw[40:40 + ls].decode("utf-8", "replace")
        ids = np.frombuffer(raw[_HEAD:_HEAD + 8 * n], dtype="<i8").tolist()
        vals = np.frombuffer(raw[_HEAD + 8 * n:_HEAD + 8 * n * (k + 1)], dtype="<f8").reshape(n, k).tolist()
        return stage, [(int(i), tuple(v)) for i, v in zip(ids, vals)]

    def close(self, remove: bool = True) -> None:
        """Close the marker (``remove``: and delete it, once every run is stored)."""
        if self._mm is not None:      # no msync: the shared mapping reaches the file anyway
            self._mm.close()
            self._mm = None
        if self._fh is not None:
            self._fh.close()
            self._fh = None
        if remove:
            try:
                self.path.unlink()
            except OSError:
                pass


def recover(marker: InFlight, store, evaluator) -> dict | None:
    """On resume: the runs ``marker`` says were under way when the study's process ended and ``store`` does
    not hold. One is stored as failed (:data:`CRASH_REASON`); several are made again now in supervised
    workers (``evaluator.map_batches(..., supervised=True)``), where the one that crashes fails alone. The
    marker is emptied. Returns what was done (for summary.json), or None when nothing was under way."""
    stage, runs = marker.pending()
    runs = [(i, v) for i, v in runs if len(v) == len(store.params) and store.get(v) is None]
    marker.end()
    if not runs:
        return None
    stage = stage or "grid"
    if len(runs) == 1:
        rid, values = runs[0]
        store.add(rid, stage, values, None, "failed", CRASH_REASON, 0.0)
        return {"runs": 1, "stage": stage, "failed": [dict(zip(store.params, values))], "how": "recorded as failed"}
    ids = np.array([i for i, _ in runs], dtype=np.int64)
    values = np.array([v for _, v in runs], dtype=float)
    store.next_id = max(store.next_id, int(ids.max()) + 1)
    evaluator.map_batches((ids, values), lambda b: store.add_batch(stage, b), supervised=True)
    return {"runs": len(runs), "stage": stage, "how": "made again in supervised workers"}


def track_in_flight(store, evaluator, resume: bool) -> dict | None:
    """Give ``evaluator`` the marker of ``store``'s runs file; on ``resume`` first :func:`recover` the runs
    an earlier session left under way, else forget its marker. Returns what :func:`recover` did."""
    marker = InFlight(store.path)
    done = recover(marker, store, evaluator) if resume else None
    if not resume:
        marker.close(remove=True)
    evaluator.marker = marker
    return done
