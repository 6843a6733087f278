"""Output files: folders checked before any work is done (so that a wrong ``--out`` costs nothing), and
whole files written atomically (a kill or a full disk never leaves half a file where a good one was).

Base layer: standard library and :mod:`fmusa.errors` only.
"""
from __future__ import annotations

import contextlib
import errno
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Iterator

from fmusa.errors import FmusaError

__all__ = ["OutputError", "DiskFullError", "writable_folder", "atomic_path", "atomic_write", "write_error",
           "free_space", "move_aside", "cache_dir", "ENV_CACHE"]

#: Environment variable naming the folder of fmusa's caches (default: the platform's user cache folder).
ENV_CACHE = "FMUSA_CACHE_DIR"


def cache_dir() -> Path:
    """fmusa's cache folder: ``$FMUSA_CACHE_DIR``, else the platform's user cache folder."""
    env = os.environ.get(ENV_CACHE)
    if env:
        return Path(env).expanduser()
    if sys.platform == "win32":
        base = Path(os.environ.get("LOCALAPPDATA") or Path.home() / "AppData" / "Local")
        return base / "fmusa" / "cache"
    if sys.platform == "darwin":
        return Path.home() / "Library" / "Caches" / "fmusa"
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "fmusa"


class OutputError(FmusaError, OSError):
    """An output folder that cannot be made or written: the message names it and the fix.

    Fix: choose an ``--out`` folder you can write (not a file, not read-only, on a disk with space), or make
    the named folder writable, then rerun (a study with ``--resume`` keeps the runs already in ``runs.csv``).
    """
    exit_code = 2


class DiskFullError(OutputError):
    """A file that could not be written because its disk (or quota) is full: names the file and the free
    space. Exit code 1: the input was right, the machine could not take the output.

    Fix: free space on the file system the message names (or point ``--out`` at another one), then rerun
    the same command with ``--resume``: every file written before is intact, and the runs already in
    runs.csv are not made again."""
    exit_code = 1


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
        if exc.errno in _FULL:
            raise write_error(folder, exc) from None
        reason = exc.strerror or type(exc).__name__
        raise OutputError(f"{what} {folder}: cannot be written ({reason}); choose a folder you can write "
                          f"to, or fix its permissions") from None
    return folder


#: this process's umask, read once (setting it is the only way to read it)
_UMASK = os.umask(0)
os.umask(_UMASK)

#: errno values of a full disk or an exhausted quota
_FULL = {errno.ENOSPC, getattr(errno, "EDQUOT", errno.ENOSPC), errno.EFBIG}


def free_space(path: str | os.PathLike) -> str:
    """The free space of the file system that holds ``path`` (or its nearest existing parent), as text."""
    p = Path(path)
    while not p.exists() and p != p.parent:
        p = p.parent
    try:
        free = shutil.disk_usage(p).free
    except OSError:
        return "unknown free space"
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if free >= size:
            return f"{free / size:.1f} {unit} free"
    return f"{free} bytes free"


def write_error(path: str | os.PathLike, exc: OSError, kept: str = "") -> OutputError:
    """The one-line error of a file that could not be written: a full disk names the free space and the
    fix (free space, then ``--resume``); anything else its reason. ``kept``: what is still intact."""
    tail = f"; {kept}" if kept else ""
    if exc.errno in _FULL:
        return DiskFullError(f"{path}: cannot be written: the disk is full ({free_space(path)} on its file "
                             f"system){tail}; free some space and rerun with --resume")
    reason = exc.strerror or str(exc) or type(exc).__name__
    return OutputError(f"{path}: cannot be written ({reason}){tail}; check the folder's permissions and space")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """A temporary path in ``path``'s folder (same suffix, so a writer that goes by it, such as
    ``savefig``, picks the same format) that becomes ``path`` when the block ends without error: flushed
    and fsynced first, then renamed over ``path``. On any error the temporary file is removed and
    ``path`` is left as it was; an OSError (a full disk, say) becomes :class:`OutputError` naming ``path``.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.tmp-", suffix=path.suffix)
        os.close(fd)
    except OSError as exc:
        raise write_error(path, exc) from None
    tmp = Path(tmp_name)
    try:
        try:
            os.chmod(tmp, 0o666 & ~_UMASK)     # mkstemp's 0600 would make every output private
            yield tmp
            _fsync(tmp)
            os.replace(tmp, path)
        except OSError as exc:
            raise write_error(path, exc) from None
        except Exception as exc:   # a writer that wrapped the OSError of a full disk (an image library)
            cause = exc.__cause__ or exc.__context__
            if isinstance(cause, OSError) and cause.errno in _FULL:
                raise write_error(path, cause) from None
            raise
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()


def save_figure(fig, path: str | os.PathLike, tight: bool = True, **savefig) -> Path:
    """Write a matplotlib figure whole (see :func:`atomic_path`) and close it; every figure fmusa makes goes
    through here, so that the tests can check each one (:mod:`fmusa.figure_check`, ``$FMUSA_CHECK_FIGURES``)."""
    import matplotlib.pyplot as plt

    from fmusa.figure_check import record

    path = Path(path)
    try:
        record(fig, path, tight)
        with atomic_path(path) as tmp:
            fig.savefig(tmp, **({"bbox_inches": "tight"} if tight else {}), **savefig)
    finally:
        plt.close(fig)
    return path


def atomic_write(path: str | os.PathLike, data: str | bytes, encoding: str = "utf-8",
                 errors: str = "strict") -> Path:
    """Write ``data`` to ``path`` whole or not at all (see :func:`atomic_path`). Returns ``path``.
    ``errors``: how text that UTF-8 cannot encode is written (``surrogateescape``: a file name read under
    an ASCII locale goes back as the bytes it was)."""
    path = Path(path)
    raw = data.encode(encoding, errors) if isinstance(data, str) else data
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            fh.write(raw)
    return path


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDWR | getattr(os, "O_BINARY", 0))     # Windows' fsync needs write access
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def move_aside(folder: str | os.PathLike, names: tuple[str, ...], tag: str) -> list[Path]:
    """Move the files and folders ``names`` of ``folder`` that exist to ``<stem>.<tag><suffix>`` (e.g.
    report.md → report.previous-2.md, figures → figures.previous-2), so that an earlier study's outputs
    are kept beside its runs rather than mixed with a new study's. Returns the new paths."""
    folder = Path(folder)
    moved = []
    for name in names:
        src = folder / name
        if not src.exists():
            continue
        stem, suffix = (src.stem, src.suffix) if src.is_file() else (src.name, "")
        target = folder / f"{stem}.{tag}{suffix}"
        n = 1
        while target.exists():       # never over an earlier copy
            n += 1
            target = folder / f"{stem}.{tag}.{n}{suffix}"
        try:
            os.replace(src, target)
        except OSError as exc:
            raise write_error(target, exc) from None
        moved.append(target)
    return moved


def try_lock(fh) -> None:
    """Lock the open file ``fh`` for this process alone, without waiting: ``fcntl.flock`` on POSIX,
    ``msvcrt.locking`` (its first byte) on Windows. BlockingIOError when another process holds it; any
    other OSError when the file system cannot lock files at all. The system releases it when the process
    dies, however it dies."""
    try:
        import fcntl
    except ImportError:
        fcntl = None
    if fcntl is not None:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return
    import msvcrt
    fh.seek(0)
    try:
        msvcrt.locking(fh.fileno(), msvcrt.LK_NBLCK, 1)
    except PermissionError as exc:     # Windows: the region is locked by another process
        raise BlockingIOError(exc.errno, str(exc)) from None
