"""An instrumented copy of an FMU that ships its FMI 2 C sources: every run logged to a file, optionally slowed.

The log counts the FMU's runs from the inside (one line per ``fmi2ExitInitializationMode``), so a tool's own
count of the runs it made can be checked against a count it does not keep; the delay turns a fast FMU into
a stand-in for a slow export (seconds a run), to measure what a method costs when runs are expensive.
"""
from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

from fmusa.files import atomic_write
from fmusa.fmi.info import FMUError

__all__ = ["instrumented_copy", "count_logged_runs"]

_DEFINITION = re.compile(r"fmi2Status\s+fmi2ExitInitializationMode\s*\(\s*fmi2Component\s+(\w+)\s*\)\s*\{")

_WRAPPER = """
/* ---- added by fmusa.fmi.instrument: every run logged, and delayed ---- */
#include <stdio.h>
#ifdef _WIN32
#include <windows.h>
#else
#include <time.h>
#endif
fmi2Status fmi2ExitInitializationMode(fmi2Component comp)
{
    FILE *f = fopen(%(log)s, "a");
    if (f) { fputs("run\\n", f); fclose(f); }
    if (%(delay)r > 0.0) {
#ifdef _WIN32
        Sleep((DWORD)(%(delay)r * 1000.0));
#else
        struct timespec ts;
        ts.tv_sec = (time_t)%(delay)r;
        ts.tv_nsec = (long)((%(delay)r - (double)ts.tv_sec) * 1e9);
        nanosleep(&ts, NULL);
#endif
    }
    return fmusa_inner_exit_initialization_mode(comp);
}
"""


def instrumented_copy(fmu: str | os.PathLike, dest: str | os.PathLike, log: str | os.PathLike,
                      delay_s: float = 0.0) -> Path:
    """Build, in the new folder ``dest``, the extracted FMU ``fmu`` rebuilt from its C sources so that every
    run appends a line to ``log`` (and then sleeps ``delay_s``). Returns ``dest``, which FMURunner runs
    as it is. FMUError when the FMU has no FMI 2 C sources with that function."""
    from fmusa.fmi.archive import extract_fmu
    from fmusa.fmi.build import compile_sources

    dest = Path(dest)
    if dest.exists():
        raise FMUError(f"{dest}: already exists; instrument into a new folder")
    extract_fmu(fmu, dest)
    shutil.rmtree(dest / "binaries", ignore_errors=True)
    for src in sorted((dest / "sources").glob("*.c")):
        text = src.read_text(encoding="utf-8", errors="surrogateescape")
        if _DEFINITION.search(text):
            break
    else:
        raise FMUError(f"{fmu}: no C source defines fmi2ExitInitializationMode; only an FMU shipping its "
                       f"FMI 2 sources can be instrumented")
    text = _DEFINITION.sub(lambda m: f"static fmi2Status fmusa_inner_exit_initialization_mode(fmi2Component "
                                     f"{m.group(1)}) {{", text, count=1)
    text = (text + _WRAPPER % {"log": json.dumps(str(Path(log).resolve())), "delay": float(delay_s)})
    guard = "#ifndef _POSIX_C_SOURCE\n#define _POSIX_C_SOURCE 199309L  /* nanosleep under -std=c99 */\n#endif\n"
    atomic_write(src, guard + text, errors="surrogateescape")
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if cc is None or os.name == "nt":
        compile_sources(dest)     # CMake, or whatever builds FMUs here
        return dest
    _compile_quickly(cc, dest)
    return dest


def _compile_quickly(cc: str, dest: Path) -> None:
    """The sources at -O1 with the C compiler (seconds, where CMake's release build of a large generated
    model takes a minute)."""
    import subprocess

    import fmpy

    from fmusa.fmi.info import FMUCompileError, host_platform, read_fmu_info

    info = read_fmu_info(dest)
    target = dest / "binaries" / host_platform() / info.binary_name("co-simulation")
    target.parent.mkdir(parents=True, exist_ok=True)
    srcs = [str(dest / "sources" / f) for f in info.source_files]
    proc = subprocess.run([cc, "-shared", "-fPIC", "-O1", f"-I{dest / 'sources'}",
                           f"-I{Path(fmpy.__file__).parent / 'c-code'}", *srcs, "-o", str(target), "-lm"],
                          capture_output=True, text=True, encoding="utf-8", errors="replace", timeout=600)
    if proc.returncode != 0 or not target.is_file():
        raise FMUCompileError(f"{dest}: building the instrumented FMU failed:\n{proc.stderr[-2000:]}")


def count_logged_runs(log: str | os.PathLike) -> int:
    """The runs an instrumented FMU logged (0 when it logged none)."""
    p = Path(log)
    return sum(1 for line in p.read_text(encoding="utf-8").splitlines() if line == "run") if p.exists() else 0
