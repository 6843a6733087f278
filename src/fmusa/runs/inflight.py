"""The runs a study is making in its own process, on disk while they run (``<runs file>.running``).

A run made in the study's process (our own FMU in a small batch, :mod:`fmusa.runs.timelimit`) that crashes
or exits inside the FMU takes the study down with it, and a resume would make it again and crash again.
So before a chunk of such runs starts, its run ids and values are written to the marker, and it is emptied
when their results are stored. A resume that finds the marker not empty knows which runs were under way when
the process ended: one run is recorded as failed with that reason (never made again by a resume); several
are made again in supervised workers, where a crash costs one run, not the study.

The marker is written without fsync: it has to outlive the process, not the machine, and a chunk of cheap
runs must not wait for the disk. Standard library only (no pandas): a chunk is a few writes.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

#: The message of a run that was under way when the study's process ended.
CRASH_REASON = ("the study's process ended during this run in an earlier session (the FMU crashed or exited "
                "inside it, or the process was killed), so it is recorded as failed and a resume does not make "
                "it again; rerun without --resume (or delete its line from the runs file) to try it again")


class InFlight:
    """The marker file of one runs file: :meth:`begin` a chunk, :meth:`end` it, :meth:`pending` on resume."""

    def __init__(self, runs_path: str | os.PathLike) -> None:
        self.path = Path(str(runs_path) + ".running")
        self._fd: int | None = None
        #: the stage of the runs about to be made (the label they are stored under)
        self.stage = ""

    def _open(self) -> int:
        if self._fd is None:
            self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT | getattr(os, "O_BINARY", 0), 0o666)
        return self._fd

    def begin(self, ids: Sequence[int], values) -> None:
        """The chunk ``ids`` (study values ``values``, one row per run) is about to run in this process."""
        lines = [self.stage] + [f"{int(i)}," + ",".join(repr(float(v)) for v in row)
                                for i, row in zip(ids, values)]
        data = ("\n".join(lines) + "\n").encode("utf-8")
        fd = self._open()
        os.lseek(fd, 0, os.SEEK_SET)
        os.write(fd, data)
        os.ftruncate(fd, len(data))

    def end(self) -> None:
        """The chunk's results are stored: nothing is under way."""
        if self._fd is not None:
            os.ftruncate(self._fd, 0)

    def pending(self) -> tuple[str, list[tuple[int, tuple[float, ...]]]]:
        """(stage, [(run id, values)]) of the chunk that was under way when a process ended; empty when none
        (a line cut short by the end is left out)."""
        try:
            text = self.path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError):
            return "", []
        if not text.endswith("\n"):
            text = text[:text.rfind("\n") + 1]
        lines = text.split("\n")[:-1]
        if not lines:
            return "", []
        runs = []
        for line in lines[1:]:
            try:
                head, *vals = line.split(",")
                runs.append((int(head), tuple(float(v) for v in vals)))
            except ValueError:
                continue
        return lines[0], runs

    def close(self, remove: bool = True) -> None:
        """Close the marker (``remove``: and delete it, once every run is stored)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
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
    import numpy as np

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
