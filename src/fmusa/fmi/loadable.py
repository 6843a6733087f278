"""Whether an FMU's binary for this machine loads, asked of a child process.

``fmusa inspect`` says plainly whether an FMU can run here. A binary that is there may still not load (a
library it needs is missing, such as JModelica's ``libgfortran.so.3``; a binary for another platform; a
damaged file), so listing the platform directory is not enough. The binary is loaded in a child process,
so that a crash or a hang while loading costs the question, not the command.
"""
from __future__ import annotations

import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from fmusa.fmi.archive import extract_fmu
from fmusa.fmi.info import FMUInfo

#: seconds a child may take to load a binary before the answer is "it hangs while loading"
LOAD_TIMEOUT_S = 60.0

_CHILD = ("import ctypes, os, sys\n"
          "d = os.path.dirname(sys.argv[1])\n"
          "if hasattr(os, 'add_dll_directory'): os.add_dll_directory(d)\n"
          "ctypes.CDLL(sys.argv[1])\n")


@dataclass(frozen=True)
class LoadAnswer:
    """``loads``: the binary loaded in a child process; ``reason``: the loader's words when it did not."""
    interface: str
    platform: str
    loads: bool
    reason: str = ""


def binary_loads(info: FMUInfo, interface: str) -> LoadAnswer | None:
    """Load ``interface``'s binary for this machine in a child process; None when there is none to load."""
    if interface not in info.interfaces or not info.has_binary(interface):
        return None
    platform = info.host_platform
    if Path(info.path).is_dir():
        folder, made = Path(info.path), False
    else:
        folder, made = extract_fmu(info.path, to_run=True), True
    try:
        lib = folder / "binaries" / platform / info.binary_name(interface)
        try:
            proc = subprocess.run([sys.executable, "-c", _CHILD, str(lib)], capture_output=True, text=True,
                                  encoding="utf-8", errors="replace", timeout=LOAD_TIMEOUT_S,
                                  stdin=subprocess.DEVNULL)
        except subprocess.TimeoutExpired:
            return LoadAnswer(interface, platform, False, f"loading it did not finish within {LOAD_TIMEOUT_S:g} s")
        if proc.returncode == 0:
            return LoadAnswer(interface, platform, True)
        lines = [ln.strip() for ln in proc.stderr.splitlines() if ln.strip()]
        if proc.returncode < 0 or not lines:
            return LoadAnswer(interface, platform, False,
                              f"the process loading it ended with code {proc.returncode} (it crashed)")
        last = lines[-1]
        reason = last.split(": ", 1)[1] if last.startswith(("OSError", "FileNotFoundError")) else last
        return LoadAnswer(interface, platform, False, reason.replace(str(folder), "<fmu>"))
    finally:
        if made:
            shutil.rmtree(folder, ignore_errors=True)
