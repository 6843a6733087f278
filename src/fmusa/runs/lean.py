"""The lean worker's batches (standard library only): runs made with :class:`fmusa.fmi.lean.LeanFMU`, sent
back as plain lists and ``array.array`` so that a worker started by ``spawn`` never imports numpy. The parent
turns a :class:`LeanBatch` into a :class:`~fmusa.runs.spec.RunBatch` (:func:`fmusa.runs.spec.from_lean`),
reducing the metrics there with the same numpy code as a worker on the fmpy path."""
from __future__ import annotations

import time
from array import array


class LeanBatch:
    """What a lean worker answers for runs of a chunk, in the order they ran: their ids, each one's seconds,
    the reasons of the failed ones (by row) and the outputs of the others, row after row of the kept
    communication points (``array('d')``, runs × rows × outputs)."""
    __slots__ = ("ids", "seconds", "messages", "data")

    def __init__(self, ids: list, seconds: array, messages: dict, data: array) -> None:
        self.ids = ids
        self.seconds = seconds
        self.messages = messages
        self.data = data

    def __len__(self) -> int:
        return len(self.ids)

    def __reduce__(self):
        return (LeanBatch, (self.ids, self.seconds, self.messages, self.data))


def _message(exc: BaseException) -> str:
    return str(exc).strip().replace("\n", " | ")[:2000]


def run_rows(fmu, ids: list, values: array, scale: tuple, offset: tuple, started=None, emit=None,
             emit_every_s: float = 0.5) -> LeanBatch:
    """Run the chunk ``ids`` (study ``values``, one row of ``len(scale)`` each) on ``fmu`` (a LeanFMU), as
    :func:`fmusa.runs.spec.run_batch` does: FMU value = scale * study value + offset (the same two IEEE
    operations as numpy's), ``started`` counted up and stamped before each run, ``emit`` given the runs done
    every ``emit_every_s`` seconds; the runs after the last emit are returned."""
    perf, mono = time.perf_counter, time.monotonic
    k = len(scale)
    n = len(ids)
    lo = 0
    while True:
        deadline = perf() + emit_every_s if emit is not None else None
        secs = array("d")
        data = array("d")
        msgs: dict[int, str] = {}
        i = lo
        while i < n:
            row = [values[i * k + j] * scale[j] + offset[j] for j in range(k)]
            if started is not None:
                started[1] = mono()
                started[0] += 1
            t0 = perf()
            try:
                fmu.run(row, data)
            except Exception as exc:  # noqa: BLE001 - the FMU's own error: record it, keep going
                msgs[i - lo] = _message(exc)
            t1 = perf()
            secs.append(t1 - t0)
            i += 1
            if deadline is not None and t1 > deadline:
                break
        batch = LeanBatch(list(ids[lo:i]), secs, msgs, data)
        if i >= n or emit is None:
            return batch
        emit(batch)
        lo = i
