"""Output folders checked before any work is done, so that a wrong ``--out`` costs nothing.

Base layer: standard library and :mod:`fmusa.errors` only.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path

from fmusa.errors import FmusaError

__all__ = ["OutputError", "writable_folder"]


class OutputError(FmusaError, OSError):
    """An output folder that cannot be made or written: the message names it and the fix.

    Fix: choose an ``--out`` folder you can write (not a file, not read-only, on a disk with space), or make
    the named folder writable, then rerun (a study with ``--resume`` keeps the runs already in ``runs.csv``).
    """
    exit_code = 2


def writable_folder(path: str | os.PathLike, what: str = "output folder") -> Path:
    """``path`` as a folder that exists and can be written (made when missing). Raises OutputError."""
    folder = Path(path)
    if folder.exists() and not folder.is_dir():
        raise OutputError(f"{what} {folder}: is a file, not a folder; give a folder (it is made when missing)")
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".fmusa-write-test-"):
            pass
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise OutputError(f"{what} {folder}: cannot be written ({reason}); choose a folder you can write "
                          f"to, or fix its permissions") from None
    return folder
