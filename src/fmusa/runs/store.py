"""runs.csv: every run of a study, one row each, written as results arrive.

The key of a run is its study parameter values, so any stage that asks for a point already run (in this
session or, with ``resume``, in an interrupted one) gets the stored row instead of a new simulation.

The rows are kept as arrays (parameters, metrics, constraint flags, status, seconds; the message of a
failed run only), not as a Python object per run, and a batch of results is written as one block
(:meth:`RunStore.add_batch`): the same bytes as row by row (:meth:`RunStore.add`), one write and one
flush. A block cut short by a kill leaves a partial last line; resuming drops it (the run is made again).
"""
from __future__ import annotations

import csv
import errno
import json
import math
import os
import struct
import weakref
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import pandas as pd

from fmusa.errors import UsageError
from fmusa.files import OutputError, atomic_write, try_lock, write_error
from fmusa.runs.metrics import constraint_holds, constraint_table

FLOAT = "%.17g"   # round-trips a double exactly, so reloaded keys match new ones


def _quote(text: str) -> str:
    """A text field as the csv module writes it (excel dialect, minimal quoting)."""
    if any(c in text for c in ',"\r\n'):
        return '"' + text.replace('"', '""') + '"'
    return text


def _num(x: float) -> str:
    return "" if math.isnan(x) else FLOAT % x


def one_line(text: str) -> str:
    """A message as runs.csv stores it: on one line (a line break becomes " | "), so that a row cut short
    by a kill is always its file's last line, which resuming drops."""
    if "\n" not in text and "\r" not in text:
        return text
    return " | ".join(part.strip() for part in text.replace("\r\n", "\n").replace("\r", "\n").split("\n")
                      if part.strip())


def _complete_records(data: bytes) -> int:
    """The length of ``data`` (csv bytes) up to the end of its last complete record: a line break outside
    quotes (a quoted field may span lines, as messages stored by older versions do)."""
    if b'"' not in data:                          # no quoted field: the last line break ends the last record
        return data.rfind(b"\n") + 1
    last_ok = 0
    pos, inside = 0, False
    for line in data.split(b"\n")[:-1]:           # every line ended by a break
        pos += len(line) + 1
        if line.count(b'"') % 2:
            inside = not inside
        if not inside:
            last_ok = pos
    return last_ok


class StoreBusyError(UsageError):
    """Another process writes the same runs file.

    Fix: wait for the other ``fmusa sweep`` on the same ``--out`` folder to finish (or stop it), or give this
    one another ``--out``.
    """


_try_lock = try_lock    # fmusa.files: the extraction folders of fmusa.fmi.archive use it too


#: errnos of a lock that another process holds (rather than one the file system refuses)
_HELD = {errno.EAGAIN, errno.EACCES, getattr(errno, "EWOULDBLOCK", errno.EAGAIN)}


def _lock_folder(path: Path):
    """An exclusive lock on ``<runs file>.lock`` for as long as the store is open: two studies writing the
    same runs.csv would interleave their rows. Released by the system when the process dies."""
    lock = path.with_name(path.name + ".lock")
    fh = open(lock, "a+", encoding="utf-8")
    try:
        _try_lock(fh)
    except OSError as exc:
        held = isinstance(exc, BlockingIOError) or exc.errno in _HELD
        try:
            fh.seek(0)
            owner = fh.read().strip() if held else ""
        except OSError:        # Windows: the holder's locked byte cannot be read
            owner = ""
        fh.close()
        if not held:
            raise StoreBusyError(f"{lock}: the file system of this folder cannot lock files "
                                 f"({exc.strerror or exc}), so fmusa cannot keep two studies from writing "
                                 f"the same runs.csv; give --out a folder on a local disk") from None
        raise StoreBusyError(f"{path}: another fmusa study ({owner or 'another process'}) is writing to this "
                             f"folder; wait for it to finish, or give this study another --out") from None
    fh.seek(0)
    fh.truncate()
    fh.write(f"pid {os.getpid()}")
    fh.flush()
    _LOCKS.add(fh)
    return fh


#: the lock files this process holds: a forked worker closes its copies at once, so that it cannot keep a
#: lock alive after this process dies (one hook for all of them, registered once, where fork exists)
_LOCKS: "weakref.WeakSet" = weakref.WeakSet()
if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=lambda: [fh.close() for fh in list(_LOCKS)])


def _numbers(path: Path, df: pd.DataFrame, columns: Sequence[str]) -> np.ndarray:
    """The columns as floats; a cell that is not a number (an edited or damaged file) is an error that
    names its line and column, never a silent string or NaN."""
    out = np.empty((len(df), len(columns)))
    for j, c in enumerate(columns):
        col = df[c]
        x = pd.to_numeric(col, errors="coerce")
        bad = x.isna() & col.notna() & (col.astype(str).str.strip() != "")
        if bad.any():
            k = int(np.flatnonzero(bad.to_numpy())[0])
            raise UsageError(f"{path}:{k + 2}: column '{c}' holds {str(col.iloc[k])!r}, not a number; fix or "
                             f"delete that line (a deleted run is simply run again with --resume)")
        out[:, j] = x.to_numpy(float)
    return out


def _changes(old, new, key: str = "") -> list[str]:
    """Every entry that differs between two fingerprints, as ``key.sub: old → new`` (the FMU: ``changed``)."""
    if old == new:
        return []
    if isinstance(old, dict) and isinstance(new, dict):
        out = []
        for k in sorted(set(old) | set(new), key=str):
            out += _changes(old.get(k), new.get(k), f"{key}.{k}" if key else str(k))
        return out
    if key == "fmu":
        return ["fmu: changed (another FMU, or the same one rebuilt)"]
    return [f"{key}: {old!r} → {new!r}"]


def _check_fingerprint(path: Path, meta: Path, fingerprint: dict | None) -> None:
    """Refuse to resume when what decides a run (FMU, parameters' variables and units, fixed values,
    scenario, metrics, options) has changed since the stored runs were made: their metrics would be stale.
    A fingerprint that is missing or cannot be read (cut short by a kill) refuses too: nothing says what
    made the runs."""
    if fingerprint is None:
        return
    fix = (f"run without --resume (the old runs are kept as {path.stem}.previous-<n>{path.suffix}) or use "
           f"another --out")
    if not meta.exists():
        raise UsageError(f"{path}: cannot resume: {meta.name}, the record of what made these runs (FMU, "
                         f"parameters, scenario, metrics), is missing, so they may be stale; {fix}")
    try:
        old = json.loads(meta.read_text(encoding="utf-8"))
        if not isinstance(old, dict):
            raise ValueError("not a JSON object")
    except (OSError, ValueError) as exc:
        raise UsageError(f"{path}: cannot resume: {meta.name} cannot be read ({exc}; it was cut short or "
                         f"edited), so nothing says what made these runs; {fix}") from None
    new = json.loads(json.dumps(fingerprint))         # the same JSON form as stored
    changed = _changes(old, new)
    if changed:
        raise UsageError(f"{path}: cannot resume: the study changed since these runs were made ("
                         + "; ".join(changed[:6]) + ("; …" if len(changed) > 6 else "")
                         + f"), so their metrics would be stale; {fix}")


def _keep_previous(path: Path) -> Path:
    """Move an earlier study's runs file aside (``runs.previous-<n>.csv``) instead of emptying it: a new
    study that then fails to start (a scheduler that cannot be reached, say) has cost nothing."""
    n = 1
    while (target := path.with_name(f"{path.stem}.previous-{n}{path.suffix}")).exists():
        n += 1
    path.replace(target)
    return target


_M64 = (1 << 64) - 1


class RunStore:
    def __init__(self, path: str | os.PathLike, params: Sequence[str], metrics: Sequence[str],
                 constraints: Iterable = (), resume: bool = False, fingerprint: dict | None = None,
                 retry_failed: bool = False) -> None:
        self.path = Path(path)
        self.params = list(params)
        self.metrics = list(metrics)
        self.constraints = list(constraints)
        self.flags = [f"ok_{c.name}" for c in self.constraints] + (["feasible"] if self.constraints else [])
        self.columns = (["run_id", "stage"] + self.params + self.metrics + self.flags
                        + ["status", "message", "seconds"])
        # key -> row: by a 64-bit hash of the parameter values (an int per run, not a tuple or bytes), the
        # rare key whose hash another key already has by its bytes
        self._index: dict[int, int] = {}
        self._spill: dict[bytes, int] = {}
        self._mix = np.random.default_rng(0x5EED).integers(1, 2**63, size=max(1, len(self.params)),
                                                            dtype=np.uint64) | np.uint64(1)
        self._mix_py = self._mix.tolist()          # the same hash in plain Python, for one key at a time
        self._pack = struct.Struct(f"={len(self.params)}d")
        self._unpack = struct.Struct(f"={len(self.params)}Q")
        self._n = 0
        self._alloc(1024)
        self._stages: list[str] = []
        self._stage_code: dict[str, int] = {}
        self._statuses: list[str] = ["ok", "failed"]
        self._messages: dict[int, str] = {}       # row -> message (failed runs, mostly)
        self.next_id = 0
        self._num_fmt = ",".join([FLOAT] * (len(self.params) + len(self.metrics)))
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._lock = _lock_folder(self.path)
        #: where the runs of an earlier study went when this one started afresh (nothing is deleted)
        self.previous: Path | None = None
        self.retried = 0
        #: what, besides the parameters, decided the stored runs (``<runs file>.study.json``)
        self.fingerprint = fingerprint
        meta = self.path.with_name(self.path.name + ".study.json")
        if resume and self.path.exists() and self.path.stat().st_size > 0:
            _check_fingerprint(self.path, meta, fingerprint)     # a matching record is not rewritten
        self._reordered = False
        if resume and self.path.exists() and self.path.stat().st_size > 0 and self._load():
            if self._reordered:    # columns in another order (edited by hand): read by name, written in ours
                header = ",".join(_quote(c) for c in self.columns) + "\r\n"
                self._guard(lambda: atomic_write(self.path, header + self._block(slice(0, self._n))))
            self._fh = open(self.path, "a", newline="", encoding="utf-8")
            #: failed runs of the resumed study set aside to be run again (``retry_failed``)
            self.retried = self._forget_failed() if retry_failed else 0
        else:
            if self.path.exists() and self.path.stat().st_size > 0:
                self.previous = _keep_previous(self.path)
                if meta.exists():
                    meta.replace(self.previous.with_name(self.previous.name + ".study.json"))
            if fingerprint is not None:   # before the first run: a runs file never lacks its record
                atomic_write(meta, json.dumps(fingerprint, indent=1, sort_keys=True))

            def start():
                fh = open(self.path, "w", newline="", encoding="utf-8")
                csv.writer(fh).writerow(self.columns)
                fh.flush()
                return fh
            self._fh = self._guard(start)
        self._writer = csv.writer(self._fh)

    # ------------------------------------------------------------------ arrays
    def _alloc(self, cap: int) -> None:
        p, m, f = len(self.params), len(self.metrics), len(self.flags)
        old = getattr(self, "_ids", None)
        new = {"_ids": np.empty(cap, np.int64), "_stage": np.empty(cap, np.int32),
               "_P": np.empty((cap, p)), "_M": np.empty((cap, m)), "_F": np.empty((cap, f), bool),
               "_status": np.empty(cap, np.int8), "_secs": np.empty(cap), "_live": np.zeros(cap, bool)}
        for name, arr in new.items():
            if old is not None:
                arr[:self._n] = getattr(self, name)[:self._n]
            setattr(self, name, arr)
        self._cap = cap

    def reserve(self, n: int) -> None:
        """Make room for ``n`` more runs at once (arrays of the right size, not doubled as rows come)."""
        if self._n + n > self._cap:
            self._alloc(self._n + n)

    def _reserve(self, n: int) -> int:
        """Room for ``n`` more rows; the first new row."""
        if self._n + n > self._cap:
            self._alloc(max(2 * self._cap, self._n + n))
        i = self._n
        self._n += n
        return i

    def _code(self, table: list[str], codes: dict | None, value: str) -> int:
        if codes is not None:
            c = codes.get(value)
            if c is None:
                c = codes[value] = len(table)
                table.append(value)
            return c
        if value not in table:
            table.append(value)
        return table.index(value)

    def _bits(self, P: np.ndarray) -> np.ndarray:
        """The parameter values as the key compares them: their bits, -0.0 as 0.0."""
        P = np.ascontiguousarray(np.asarray(P, dtype=float).reshape(-1, len(self.params))) + 0.0
        return P.view(np.uint64)

    def _hashes(self, U: np.ndarray) -> list[int]:
        h = (U * self._mix).sum(axis=1, dtype=np.uint64)       # arithmetic modulo 2**64
        h ^= h >> np.uint64(31)
        h *= np.uint64(0x9E3779B97F4A7C15)
        h ^= h >> np.uint64(29)
        return h.tolist()

    def _key_hash(self, raw: bytes) -> int:
        """:meth:`_hashes` of one key's bytes (``self._pack`` of its values + 0.0), in plain Python."""
        h = 0
        for b, m in zip(self._unpack.unpack(raw), self._mix_py):
            h += b * m
        h &= _M64
        h ^= h >> 31
        h = (h * 0x9E3779B97F4A7C15) & _M64
        return h ^ (h >> 29)

    def _insert(self, start: int, n: int) -> None:
        if n == 1:   # one run (a search's): the same index entry without numpy's fixed costs
            raw = self._pack.pack(*[v + 0.0 for v in self._P[start].tolist()])
            h = self._key_hash(raw)
            old = self._index.get(h)
            if old is None:
                self._index[h] = start
            elif (self._P[old] + 0.0).tobytes() == raw:
                self._live[old] = False
                self._index[h] = start
            else:
                prev = self._spill.get(raw)
                if prev is not None:
                    self._live[prev] = False
                self._spill[raw] = start
            self._live[start] = True
            return
        U = self._bits(self._P[start:start + n])
        index = self._index
        self._live[start:start + n] = True      # first: a key repeated within the block leaves its last row
        for j, h in enumerate(self._hashes(U)):
            row = start + j
            old = index.get(h)
            if old is None:
                index[h] = row
                continue
            if np.array_equal(self._bits(self._P[old])[0], U[j]):     # the same key again: the new row
                self._live[old] = False
                index[h] = row
            else:                                                   # another key with this hash
                k = U[j].tobytes()
                prev = self._spill.get(k)
                if prev is not None:
                    self._live[prev] = False
                self._spill[k] = row

    def _load(self) -> bool:
        with open(self.path, "r+b") as fh:   # a block cut short by a kill: drop its partial last record
            data = fh.read()
            pos = _complete_records(data)
            if pos < len(data):
                fh.truncate(pos)
        if pos == 0:                           # not even the header survived: start afresh
            return False
        try:
            df = pd.read_csv(self.path, keep_default_na=True, encoding="utf-8",
                             dtype={"stage": str, "status": str, "message": str})
        except (pd.errors.ParserError, ValueError) as exc:
            raise UsageError(f"{self.path}: cannot resume: the file cannot be read as runs.csv "
                             f"({' '.join(str(exc).split())}); fix the line it names, or start afresh without "
                             f"--resume") from None
        missing = [c for c in self.columns if c not in df.columns]
        if missing:
            raise UsageError(f"{self.path}: cannot resume: columns {', '.join(missing)} are missing "
                             f"(the study changed?); start afresh without --resume or use another --out")
        extra = [c for c in df.columns if c not in self.columns]
        if extra:
            raise UsageError(f"{self.path}: cannot resume: columns {', '.join(map(str, extra))} are not the "
                             f"study's (runs.csv was edited, or the study changed); remove them, or start "
                             f"afresh without --resume")
        self._reordered = list(df.columns) != self.columns
        n = len(df)
        i = self._reserve(n)
        self._ids[i:i + n] = _numbers(self.path, df, ["run_id"]).astype(np.int64)[:, 0]
        self._P[i:i + n] = _numbers(self.path, df, self.params)
        self._M[i:i + n] = _numbers(self.path, df, self.metrics)
        self._secs[i:i + n] = _numbers(self.path, df, ["seconds"])[:, 0]
        codes: dict[str, int] = {}
        self._stage[i:i + n] = [self._code(self._stages, codes, str(s)) for s in df["stage"].tolist()]
        status = df["status"].fillna("").astype(str).tolist()
        self._status[i:i + n] = [self._code(self._statuses, None, s) for s in status]
        for j, msg in enumerate(df["message"].tolist()):
            if isinstance(msg, str) and msg:
                self._messages[i + j] = msg
        self._stage_code = {s: c for c, s in enumerate(self._stages)}
        if self.flags:   # never read back: recomputed from the metrics under today's constraints
            self._F[i:i + n] = self._flag_rows(self._M[i:i + n], self._status[i:i + n] == 0)
        self._insert(i, n)
        self.next_id = int(df["run_id"].max()) + 1 if n else 0
        return True

    def _forget_failed(self) -> int:
        """Take the stored failed runs out of the lookup, so that a resumed study runs them again (their
        lines stay in runs.csv; a new row for the same parameters supersedes an old one on every later
        load). Returns how many."""
        rows = np.flatnonzero(self._live[:self._n] & (self._status[:self._n] != self._statuses.index("ok")))
        if not len(rows):
            return 0
        U = self._bits(self._P[rows])
        for row, h, u in zip(rows.tolist(), self._hashes(U), U):
            if self._index.get(h) == row:
                del self._index[h]
            else:
                self._spill.pop(u.tobytes(), None)
        self._live[rows] = False
        return len(rows)

    # ------------------------------------------------------------------ lookups
    @staticmethod
    def key(values: Sequence[float]) -> tuple[float, ...]:
        return tuple(float(v) for v in values)

    def rows_of(self, P) -> np.ndarray:
        """Row of every parameter set in ``P`` (one per row), -1 where the store has none."""
        P = np.asarray(P, dtype=float).reshape(-1, len(self.params))
        get = self._index.get
        out = np.empty(len(P), dtype=np.int64)
        for a in range(0, len(P), 4096):         # a slice at a time: no key object for every row at once
            u = self._bits(P[a:a + 4096])
            rows = np.array([get(h, -1) for h in self._hashes(u)], dtype=np.int64)
            found = rows >= 0
            same = np.zeros(len(u), dtype=bool)
            if found.any():
                same[found] = (self._bits(self._P[rows[found]]) == u[found]).all(axis=1)
            rows[~same] = -1
            if self._spill:                               # no row, or another key's: the spilled keys
                for j in np.flatnonzero(~same).tolist():
                    rows[j] = self._spill.get(u[j].tobytes(), -1)
            out[a:a + 4096] = rows
        return out

    def row_of(self, values: Sequence[float]) -> int:
        """:meth:`rows_of` for one parameter set, in plain Python: a search asks for one point at a time, and
        numpy's fixed cost per call would be most of a cheap run's."""
        raw = self._pack.pack(*[float(v) + 0.0 for v in values])     # + 0.0: -0.0 is the key 0.0
        row = self._index.get(self._key_hash(raw), -1)
        if row >= 0 and (self._P[row] + 0.0).tobytes() == raw:
            return row
        return self._spill.get(raw, -1) if self._spill else -1

    def __contains__(self, values) -> bool:
        return self.row_of(values) >= 0

    def __len__(self) -> int:
        return len(self._index) + len(self._spill)

    def _record(self, i: int) -> dict:
        rec: dict = {"run_id": int(self._ids[i]), "stage": self._stages[self._stage[i]]}
        rec.update(zip(self.params, self._P[i].tolist()))
        rec.update(zip(self.metrics, self._M[i].tolist()))
        rec.update(zip(self.flags, self._F[i].tolist()))
        rec.update(status=self._statuses[self._status[i]], message=self._messages.get(i, ""),
                   seconds=float(self._secs[i]))
        return rec

    def get(self, values: Sequence[float]) -> dict | None:
        i = self.row_of(values)
        return None if i < 0 else self._record(i)

    def metric_matrix(self, rows: np.ndarray) -> np.ndarray:
        """Metrics of the store's ``rows`` (NaN where a run failed)."""
        return self._M[rows]

    def ok(self, rows: np.ndarray) -> np.ndarray:
        """Whether the runs on ``rows`` worked (status ok)."""
        return self._status[rows] == self._statuses.index("ok")

    def record(self, row: int) -> dict:
        """The stored row ``row`` (from :meth:`rows_of`) as a dict, one entry per column."""
        return self._record(int(row))

    def new_ids(self, n: int) -> np.ndarray:
        """``n`` new run ids."""
        ids = np.arange(self.next_id, self.next_id + n, dtype=np.int64)
        self.next_id += n
        return ids

    def new_id(self) -> int:
        i = self.next_id
        self.next_id += 1
        return i

    # ------------------------------------------------------------------ adding rows
    def _flag_rows(self, M: np.ndarray, ok: np.ndarray) -> np.ndarray:
        if len(M) == 1 and self.constraints:   # one run: the flags of constraint_table, in plain Python
            row = dict(zip(self.metrics, M[0].tolist()))
            flags = [bool(ok[0]) and constraint_holds(c, row[c.metric]) for c in self.constraints]
            return np.array([flags + [all(flags)]], dtype=bool)
        table = constraint_table({k: M[:, j] for j, k in enumerate(self.metrics)}, self.constraints)
        F = np.empty((len(M), len(self.flags)), bool)
        for j, name in enumerate(self.flags):
            F[:, j] = table[name] & ok
        return F

    def add(self, run_id: int, stage: str, values: Sequence[float], metrics: np.ndarray | None,
            status: str, message: str, seconds: float) -> dict:
        """One run: stored, written as one row of runs.csv and flushed."""
        i = self._reserve(1)
        self._ids[i] = run_id
        self._stage[i] = self._code(self._stages, self._stage_code, stage)
        self._P[i] = [float(v) for v in values]
        self._M[i] = metrics if metrics is not None else np.nan
        self._status[i] = self._code(self._statuses, None, status)
        if self.flags:
            self._F[i] = self._flag_rows(self._M[i:i + 1], np.array([status == "ok"]))[0]
        self._secs[i] = float(seconds)
        if message:
            self._messages[i] = one_line(message)
        self._insert(i, 1)
        rec = self._record(i)
        self._guard(lambda: (self._writer.writerow([self._fmt(rec[c]) for c in self.columns]), self._fh.flush()))
        return rec

    def add_batch(self, stage: str, batch) -> None:
        """A :class:`~fmusa.runs.spec.RunBatch` of results: stored and written as one block of rows (the
        bytes :meth:`add` writes for them one by one), one write, one flush."""
        n = len(batch)
        if not n:
            return
        i = self._reserve(n)
        sl = slice(i, i + n)
        ok = np.asarray(batch.ok, dtype=bool)
        self._ids[sl] = batch.run_ids
        self._stage[sl] = self._code(self._stages, self._stage_code, stage)
        self._P[sl] = np.asarray(batch.values, dtype=float).reshape(n, len(self.params))
        M = np.array(batch.metrics, dtype=float).reshape(n, len(self.metrics))
        M[~ok] = np.nan
        self._M[sl] = M
        ok_code, failed_code = self._statuses.index("ok"), self._statuses.index("failed")
        self._status[sl] = np.where(ok, ok_code, failed_code)
        if self.flags:
            self._F[sl] = self._flag_rows(M, ok)
        self._secs[sl] = batch.seconds
        for j, msg in batch.messages.items():
            if msg:
                self._messages[i + j] = one_line(msg)
        self._insert(i, n)
        text = self._block(sl)
        self._guard(lambda: (self._fh.write(text), self._fh.flush()))

    def _guard(self, write):
        """``write()``, with an OSError (a full disk) as one line naming runs.csv and the free space; the
        rows before are intact (a partial last line is dropped on resume). Then :meth:`check_present`."""
        try:
            out = write()
        except OSError as exc:
            raise write_error(self.path, exc, kept=f"the runs before are kept in {self.path.name}") from None
        self.check_present()
        return out

    def check_present(self) -> None:
        """An :class:`~fmusa.files.OutputError` when runs.csv is no longer the file this store writes (its
        folder deleted or moved, the file replaced during the study): the rows would go nowhere."""
        fh = getattr(self, "_fh", None)
        if fh is None or fh.closed:
            return
        try:
            mine, there = os.fstat(fh.fileno()), os.stat(self.path)
            same = (mine.st_ino, mine.st_dev) == (there.st_ino, there.st_dev)
        except OSError:
            same = False
        if not same:
            raise OutputError(f"{self.path}: runs.csv was deleted, moved or replaced while the study ran "
                              f"(its folder removed?), so the runs since then are lost; nothing more is "
                              f"written. Run the study again (with --resume if runs.csv is back)")

    def _block(self, sl: slice) -> str:
        """The rows ``sl`` as csv text, as the csv module writes them row by row."""
        ids = self._ids[sl].tolist()
        nums = np.hstack([self._P[sl], self._M[sl]]).tolist()
        flags = [",".join("True" if f else "False" for f in row) + "," for row in self._F[sl].tolist()] \
            if self.flags else None
        stage_text = [_quote(s) for s in self._stages]
        status_text = [_quote(s) for s in self._statuses]
        stages, status, secs = self._stage[sl].tolist(), self._status[sl].tolist(), self._secs[sl].tolist()
        fmt, msgs, first = self._num_fmt, self._messages, sl.start
        lines = []
        for j, rid in enumerate(ids):
            num = fmt % tuple(nums[j])
            if "nan" in num:
                num = ",".join(map(_num, nums[j]))
            msg = msgs.get(first + j)
            lines.append(f"{rid},{stage_text[stages[j]]},{num},{flags[j] if flags else ''}"
                         f"{status_text[status[j]]},{_quote(msg) if msg else ''},{_num(secs[j])}\r\n")
        return "".join(lines)

    @staticmethod
    def _fmt(x):
        if isinstance(x, (bool, np.bool_)):
            return "True" if x else "False"
        if isinstance(x, float):
            return "" if math.isnan(x) else FLOAT % x
        return x

    def frame(self, stage: str | None = None) -> pd.DataFrame:
        rows = np.flatnonzero(self._live[:self._n])
        if stage is not None:
            code = self._stage_code.get(stage)
            rows = rows[self._stage[rows] == code] if code is not None else rows[:0]
        if not len(rows):
            return pd.DataFrame([], columns=self.columns).reset_index(drop=True)
        rows = rows[np.argsort(self._ids[rows], kind="stable")]
        cols: dict = {"run_id": self._ids[rows], "stage": np.array(self._stages, dtype=object)[self._stage[rows]]}
        cols.update(zip(self.params, self._P[rows].T))
        cols.update(zip(self.metrics, self._M[rows].T))
        cols.update(zip(self.flags, self._F[rows].T))
        cols["status"] = np.array(self._statuses, dtype=object)[self._status[rows]]
        cols["message"] = np.array([self._messages.get(i, "") for i in rows.tolist()], dtype=object)
        cols["seconds"] = self._secs[rows]
        return pd.DataFrame(cols, columns=self.columns)

    def close(self, keep_lock: bool = False) -> None:
        """Close runs.csv; release the folder's lock unless ``keep_lock`` (the report is still to be
        written into the folder: :meth:`release`)."""
        if not self._fh.closed:
            try:
                self._fh.close()
            except OSError:     # the rows a full disk refused: already reported by the write that failed
                pass
        if not keep_lock:
            self.release()

    def release(self) -> None:
        """Release the lock on the folder's runs file (closing the lock file releases it)."""
        if self._lock is not None:
            self._lock.close()
            self._lock = None
