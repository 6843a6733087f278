"""An FMU without a binary for this machine, built from its C sources (once per FMU content)."""
from __future__ import annotations

import os
import shutil
from pathlib import Path

from fmusa.fmi.archive import extract_fmu, new_folder
from fmusa.fmi.info import (FMUCompileError, FMUError, FMUInfo, binary_problem, host_platform, identifier_problem,
                            inside, read_fmu_info, select_interface)


def _tail(text: str, n: int = 4000) -> str:
    text = text.strip()
    return text if len(text) <= n else "…" + text[-n:]


def compile_sources(unzipdir: str | os.PathLike, info: FMUInfo | None = None,
                    interface: str | None = None) -> Path:
    """Build the binary for this platform from the C sources of the extracted FMU ``unzipdir`` and put it
    in ``unzipdir/binaries/<platform>/``, as ``fmpy.build.build_platform_binary`` does (CMake with fmpy's
    build template; plain ``cc`` when CMake is missing). Returns the binary's path.

    Raises :class:`FMUCompileError` with the compiler's output when the build fails.
    """
    import subprocess
    import tempfile

    import fmpy

    unzipdir = Path(unzipdir).resolve()
    info = info or read_fmu_info(unzipdir)
    interface = interface or select_interface(info)
    plat = host_platform()
    target = unzipdir / "binaries" / plat / info.binary_name(interface)
    label = f"{info.model_name} ({info.path})"
    if not info.can_compile:
        raise FMUCompileError(f"{label}: no {plat} binary and no C sources listed under <SourceFiles>")
    # every name the FMU supplies stays inside the folder: the library written, the sources compiled
    why = identifier_problem(info.interfaces[interface])
    outside = [f for f in info.source_files if not inside(unzipdir / "sources", f)]
    if why or outside or not inside(unzipdir, target.relative_to(unzipdir).as_posix()):
        raise FMUError(f"{label}: refused to build: "
                       + (f"modelIdentifier {info.interfaces[interface]!r} {why}" if why else
                          f"source files outside sources/ ({', '.join(map(repr, outside))})" if outside else
                          f"binaries/{plat} leads outside {unzipdir}")
                       + "; the FMU is broken or hostile")
    log: list[str] = []

    def run(cmd: list[str], cwd=None) -> bool:
        log.append("$ " + " ".join(cmd))
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, encoding="utf-8", errors="replace", cwd=cwd,
                                  timeout=600)
        except (OSError, subprocess.TimeoutExpired) as exc:
            log.append(str(exc))
            return False
        log.append((proc.stdout + proc.stderr).strip())
        return proc.returncode == 0

    c_code = Path(fmpy.__file__).parent / "c-code"
    ok = False
    if shutil.which("cmake"):
        from fmpy.build import create_cmake_settings
        with tempfile.TemporaryDirectory(prefix="fmusa-build-") as build_dir:
            try:
                create_cmake_settings(unzipdir, build_dir)
            except Exception as exc:
                raise FMUCompileError(f"{label}: cannot set up the build of its sources: {exc}") from None
            ok = (run(["cmake", "-S", str(c_code), "-B", build_dir])
                  and run(["cmake", "--build", build_dir, "--target", "install", "--config", "Release"]))
    else:
        cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
        if cc is None:
            raise FMUCompileError(f"{label}: has no {plat} binary, and neither cmake nor a C compiler (cc, "
                                  f"gcc) was found to build one from its sources; install gcc (and cmake)")
        srcs = [str(unzipdir / "sources" / f) for f in info.source_files]
        target.parent.mkdir(parents=True, exist_ok=True)
        ok = run([cc, "-shared", "-fPIC", "-O2", f"-I{unzipdir / 'sources'}", f"-I{c_code}", *srcs,
                  "-o", str(target), "-lm"])
    if not ok or not target.is_file():
        if ok:
            log.append(f"the build finished but did not produce {target.relative_to(unzipdir)}")
        # the failing step (the configure chatter of a step that worked is left out)
        failed = log[-2:] if len(log) >= 2 and log[-2].startswith("$ ") else log[-1:]
        raise FMUCompileError(f"{label}: has no {plat} binary, and building one from its C sources "
                              f"({', '.join(info.source_files)}) failed. Compiler output:\n"
                              + _tail("\n".join(x for x in failed if x)))
    return target


def file_digest(path: Path) -> str:
    import hashlib
    h = hashlib.sha256()
    if path.is_dir():
        for p in sorted(path.rglob("*")):
            if p.is_file():
                h.update(p.relative_to(path).as_posix().encode())
                h.update(p.read_bytes())
    else:
        with open(path, "rb") as f:
            for block in iter(lambda: f.read(1 << 20), b""):
                h.update(block)
    return h.hexdigest()[:12]


def prepare_fmu(fmu_path: str | os.PathLike, interface: str = "auto",
                workdir: str | os.PathLike | None = None) -> Path:
    """A path FMURunner can run on this machine: ``fmu_path`` itself when it has a binary for this platform,
    else an extracted copy in ``workdir`` (default: a new temporary directory) with the binary built from
    the FMU's sources. A copy built earlier for the same FMU content is reused.

    Raises :class:`FMUError` (not FMI 2.0, interface missing, neither binary nor sources) or
    :class:`FMUCompileError`.
    """
    import tempfile

    fmu_path = Path(fmu_path)
    info = read_fmu_info(fmu_path)
    iface = select_interface(info, interface)
    if info.has_binary(iface):
        return fmu_path
    problem = binary_problem(info, iface)
    if problem:
        raise FMUError(f"{fmu_path}: {problem}")
    root = Path(workdir) if workdir is not None else new_folder()
    root.mkdir(parents=True, exist_ok=True)
    dest = root / f"{fmu_path.stem}-{file_digest(fmu_path)}"
    if (dest / "binaries" / host_platform() / info.binary_name(iface)).is_file():
        return dest
    tmp = Path(tempfile.mkdtemp(prefix=".build-", dir=root))
    try:
        if fmu_path.is_dir():
            shutil.copytree(fmu_path, tmp, dirs_exist_ok=True)
        else:
            extract_fmu(fmu_path, tmp)
        compile_sources(tmp, info, iface)
        shutil.rmtree(dest, ignore_errors=True)
        tmp.rename(dest)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return dest


