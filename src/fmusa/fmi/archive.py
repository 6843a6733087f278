"""Unpacking an FMU archive safely: bounded in size, kept inside its folder, and cleaned up even after a kill.

An FMU is a ZIP file from someone else. ``fmpy.extract`` trusts it: a member of a gigabyte lands in /tmp
whatever the model needs, and a damaged member fails with a bare ``zlib.error``. Here every member is
checked before anything is written (no absolute path, no ``..``, no backslash or drive letter), the bytes
actually written are counted against a limit (the sizes in the ZIP's directory can lie), and a damaged
archive is reported with the member's name. Each extraction folder is named ``fmusa-fmu-*`` and holds
the PID of the process that made it, so that a later extraction removes the folders of processes that
were killed before they could clean up.
"""
from __future__ import annotations

import os
import shutil
import tempfile
import zipfile
import zlib
from pathlib import Path

from fmusa.fmi.info import FMUError, host_platforms, member_problem

#: Largest total of unpacked bytes (FMUSA_MAX_FMU_BYTES overrides it): models with large tables or
#: resources stay far below it, and a runaway archive cannot fill the disk.
MAX_FMU_BYTES = 2 * 1024 ** 3
ENV_MAX_BYTES = "FMUSA_MAX_FMU_BYTES"
PREFIX = "fmusa-fmu-"
OWNER_FILE = ".fmusa-owner"
_CHUNK = 1 << 20


def max_fmu_bytes() -> int:
    """The unpacking limit in bytes: ``$FMUSA_MAX_FMU_BYTES`` or :data:`MAX_FMU_BYTES`."""
    text = os.environ.get(ENV_MAX_BYTES, "").strip()
    if not text:
        return MAX_FMU_BYTES
    try:
        value = int(float(text))
    except ValueError:
        raise FMUError(f"{ENV_MAX_BYTES}={text!r} is not a number of bytes; set e.g. "
                       f"{ENV_MAX_BYTES}=4e9 or unset it") from None
    if value <= 0:
        raise FMUError(f"{ENV_MAX_BYTES}={text!r} must be positive; unset it for the default "
                       f"({MAX_FMU_BYTES} bytes)")
    return value


def _pid_alive(pid: int) -> bool:
    """Whether process ``pid`` still runs, through psutil on every platform (``os.kill(pid, 0)`` would send
    Ctrl+C on Windows, and a dead pid there raises an error instead of saying so). Without psutil: on POSIX
    the signal-0 probe, elsewhere "alive" (a folder kept is harmless, one removed under a live study is not)."""
    try:
        import psutil
    except ImportError:
        psutil = None
    if psutil is not None:
        try:
            return psutil.pid_exists(pid) and psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
        except psutil.NoSuchProcess:
            return False
        except Exception:  # noqa: BLE001 - access denied and the like: it exists
            return True
    if os.name != "posix":
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_orphans(root: str | os.PathLike | None = None) -> list[Path]:
    """Remove the extraction folders under ``root`` (the temp folder) whose owning process has died."""
    removed = []
    base = Path(root or tempfile.gettempdir())
    for d in base.glob(PREFIX + "*"):
        try:
            pid = int((d / OWNER_FILE).read_text(encoding="utf-8").strip())
        except (OSError, ValueError):
            continue       # not (yet) ours to judge: a folder being created has no owner file for a moment
        if pid != os.getpid() and not _pid_alive(pid):
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
        remove_orphans()
        folder = Path(tempfile.mkdtemp(prefix=PREFIX))
        (folder / OWNER_FILE).write_text(str(os.getpid()), encoding="utf-8")
    else:
        folder = Path(dest)
        folder.mkdir(parents=True, exist_ok=True)
    try:
        _unpack(path, folder, limit, to_run)
    except BaseException:
        if made_here:
            shutil.rmtree(folder, ignore_errors=True)
        raise
    return folder


def _needed_to_run(names: list[str]) -> set[str]:
    """The members a run of the FMU on this machine needs (see :func:`extract_fmu`)."""
    here = tuple(f"binaries/{p}/" for p in host_platforms())   # FMI 2.0's linux64, FMI 3.0's x86_64-linux
    has_binary = any(n.startswith(here) and not n.endswith("/") for n in names)
    keep = ("resources/",) + here + (() if has_binary else ("sources/",))
    return {n for n in names if n == "modelDescription.xml" or n.startswith(keep)}


def _unpack(path: Path, folder: Path, limit: int, to_run: bool = False) -> None:
    try:
        zf = zipfile.ZipFile(path)
    except zipfile.BadZipFile:
        raise FMUError(f"{path}: not an FMU (not a ZIP archive); export the FMU again") from None
    except FileNotFoundError:
        raise FMUError(f"{path}: FMU file not found; check the path") from None
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
