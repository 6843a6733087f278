"""Unpacking an FMU archive safely: bounded in size and member count, kept inside its folder, and cleaned
up even after a kill.

An FMU is a ZIP file from someone else. ``fmpy.extract`` trusts it: a member of a gigabyte lands in /tmp
whatever the model needs, and a damaged member fails with a bare ``zlib.error``. Here every member is
checked before anything is written (no absolute path, no ``..``, no backslash or drive letter), the bytes
actually written are counted against a limit (the sizes in the ZIP's directory can lie), and a damaged
archive is reported with the member's name. Each extraction folder is named ``fmusa-fmu-*`` and holds a
lock file that its process keeps locked while it lives (the system releases the lock however the process
dies): a later extraction removes the folders whose lock nobody holds. A process id alone would not do:
another container, or another host sharing the temporary folder, sees other processes under the same ids.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import time
import zipfile
import zlib
from pathlib import Path

from fmusa.files import try_lock
from fmusa.fmi.info import (ENV_MAX_BYTES, MAX_FMU_BYTES, FMUError, host_platforms, max_fmu_bytes,  # noqa: F401
                            inside, member_problem, open_fmu_zip)

PREFIX = "fmusa-fmu-"
#: The lock file of an extraction folder (it also names the owner's process id, for people).
OWNER_FILE = ".fmusa-owner"
#: An owner file still empty (its owner writes its process id only once it holds the lock) and younger
#: than this is not judged: its folder may be being made right now.
GRACE_S = 2.0
_CHUNK = 1 << 20
#: folder -> the open, locked owner file of each extraction folder this process made
_HELD: dict[str, object] = {}


def claim_folder(folder: str | os.PathLike) -> None:
    """Make ``folder`` this process's: lock its owner file for as long as the process lives (or until
    :func:`remove_folder`). A file system that cannot lock leaves the folder unclaimed, so never removed
    by another process (harmless: a folder kept)."""
    fh = open(Path(folder) / OWNER_FILE, "a+", encoding="utf-8")
    try:
        try_lock(fh)
    except OSError:
        fh.close()
        return
    fh.seek(0)
    fh.truncate()
    fh.write(str(os.getpid()))
    fh.flush()
    _HELD[str(Path(folder))] = fh


def new_folder() -> Path:
    """A new, claimed ``fmusa-fmu-*`` folder in the temporary folder."""
    remove_orphans()
    folder = Path(tempfile.mkdtemp(prefix=PREFIX))
    claim_folder(folder)
    return folder


def remove_folder(folder: str | os.PathLike | None) -> None:
    """Release and delete an extraction folder of this process (Windows cannot delete a file held open)."""
    if folder is None:
        return
    fh = _HELD.pop(str(Path(folder)), None)
    if fh is not None:
        fh.close()
    shutil.rmtree(folder, ignore_errors=True)


def _owner_gone(lock: Path) -> bool:
    """Whether nobody holds the lock of ``lock`` (an owner file): the process that made its folder ended.
    A lock that cannot be taken for another reason (a file system without locks) means "keep"."""
    try:
        fh = open(lock, "r+", encoding="utf-8")
    except OSError:
        return False
    try:
        if not fh.read(32).strip() and time.time() - lock.stat().st_mtime < GRACE_S:
            return False        # not locked yet by its maker, perhaps
        fh.seek(0)
        try_lock(fh)            # (on Windows the read above already fails when the byte is locked)
    except OSError:
        return False
    finally:
        fh.close()          # releases the lock just taken
    return True


def remove_orphans(root: str | os.PathLike | None = None) -> list[Path]:
    """Remove the extraction folders under ``root`` (the temp folder) whose owner's lock is free: their
    process has ended, wherever it ran. Folders without an owner file are not judged."""
    for name, fh in list(_HELD.items()):       # folders of this process deleted without remove_folder
        if not Path(name).exists():
            _HELD.pop(name, None)
            fh.close()
    removed = []
    base = Path(root or tempfile.gettempdir())
    for d in base.glob(PREFIX + "*"):
        if str(d) in _HELD:
            continue
        if _owner_gone(d / OWNER_FILE):
            shutil.rmtree(d, ignore_errors=True)
            removed.append(d)
    return removed


def extract_fmu(fmu: str | os.PathLike, dest: str | os.PathLike | None = None,
                max_bytes: int | None = None, to_run: bool = False) -> Path:
    """Unpack ``fmu`` into ``dest`` (a new ``fmusa-fmu-*`` temp folder when None) and return the folder.

    ``to_run``: only what running it here needs (the model description, ``resources/``, this platform's
    ``binaries/``, and ``sources/`` when that binary is missing): files and folders cost milliseconds each
    on some disks, and the other platforms' binaries, the sources and the documentation are most of an
    FMU's members.

    Raises :class:`FMUError` naming the archive, the member and the fix for: a file that is not a ZIP
    archive, a member whose path would leave the folder, more than ``max_bytes`` unpacked bytes, and a
    damaged member. Nothing is left behind on error when the folder was made here."""
    path = Path(fmu)
    limit = max_fmu_bytes() if max_bytes is None else int(max_bytes)
    made_here = dest is None
    if made_here:
        folder = new_folder()
    else:
        folder = Path(dest)
        folder.mkdir(parents=True, exist_ok=True)
    try:
        _unpack(path, folder, limit, to_run)
    except BaseException:
        if made_here:
            remove_folder(folder)
        raise
    return folder


def _needed_to_run(names: list[str]) -> set[str]:
    """The members a run of the FMU on this machine needs (see :func:`extract_fmu`)."""
    here = tuple(f"binaries/{p}/" for p in host_platforms())   # FMI 2.0's linux64, FMI 3.0's x86_64-linux
    has_binary = any(n.startswith(here) and not n.endswith("/") for n in names)
    keep = ("resources/",) + here + (() if has_binary else ("sources/",))
    return {n for n in names if n == "modelDescription.xml" or n.startswith(keep)}


def _unpack(path: Path, folder: Path, limit: int, to_run: bool = False) -> None:
    zf = open_fmu_zip(path)     # a regular file, not too many members
    with zf:
        infos = zf.infolist()
        for info in infos:
            problem = member_problem(info.filename)
            if problem:
                raise FMUError(f"{path}: member '{info.filename}' {problem}; the archive is not a valid FMU "
                               f"(export it again)")
        if to_run:
            needed = _needed_to_run([i.filename for i in infos])
            infos = [i for i in infos if i.filename in needed]
        declared = sum(i.file_size for i in infos)
        if declared > limit:
            raise FMUError(f"{path}: unpacks to {declared} bytes, more than the limit of {limit}; if the "
                           f"FMU really needs it, raise the limit with {ENV_MAX_BYTES}")
        written = 0
        for info in infos:
            if not inside(folder, info.filename):     # a link already in ``dest`` that leads away
                raise FMUError(f"{path}: member '{info.filename}' would be written outside {folder}; unpack "
                               f"into an empty folder")
            target = folder / info.filename
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            try:
                with zf.open(info) as src, open(target, "wb") as out:
                    while True:
                        block = src.read(_CHUNK)
                        if not block:
                            break
                        written += len(block)
                        if written > limit:
                            raise FMUError(f"{path}: unpacks to more than the limit of {limit} bytes (member "
                                           f"'{info.filename}' is larger than the archive declares); raise "
                                           f"the limit with {ENV_MAX_BYTES} only if you trust this FMU")
                        out.write(block)
            except (zlib.error, zipfile.BadZipFile, EOFError) as exc:
                raise FMUError(f"{path}: member '{info.filename}' is damaged ({type(exc).__name__}: {exc}); "
                               f"the archive is corrupt: export or download the FMU again") from None
