"""What an FMU declares, read without loading it, and the load-time checks (version, interface, binary, variable roles)."""
from __future__ import annotations

import difflib
import hashlib
import os
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Iterable

from fmusa.errors import FmusaError

#: The FMI versions fmusa runs (an FMI 1.0 FMU is refused with how to export it again).
SUPPORTED_FMI_VERSIONS = ("2.0", "3.0")
FMU_NAME = "ScrewVertebra.fmu"
ENV_FMU = "FMUSA_FMU"
Value = float | int | bool


def default_fmu_path() -> Path:
    """The ScrewVertebra FMU a study or a runner uses when none is named.

    In this order: ``$FMUSA_FMU`` when set; ``dist/ScrewVertebra.fmu`` under the current directory (a
    checkout, or any directory an installed fmusa is run from); ``dist/ScrewVertebra.fmu`` in a directory
    above this file (the repository of an editable install, run from elsewhere). Raises
    :class:`FMUNotFoundError` naming each place and how to build the FMU (``make fmu``).
    """
    env = os.environ.get(ENV_FMU)
    if env:
        path = Path(env).expanduser().resolve()
        if not path.exists():
            raise FMUNotFoundError(f"${ENV_FMU} is set to {env}, which does not exist; point it at an FMU, "
                                   f"or unset it to use dist/{FMU_NAME} (built with `make fmu`)")
        check_fmu_path(path, f"${ENV_FMU} ({env})")
        return path
    local = Path.cwd() / "dist" / FMU_NAME
    if local.is_file():
        return local
    here = Path(__file__).resolve()
    for parent in here.parents:
        candidate = parent / "dist" / FMU_NAME
        if candidate.is_file():
            return candidate
    raise FMUNotFoundError(
        f"no FMU given and the default one is missing: ${ENV_FMU} is not set and {local} does not exist; "
        f"build it with `make fmu` in the fmusa repository, run from the directory that holds "
        f"dist/{FMU_NAME}, or set {ENV_FMU} to the FMU's path")


# ---------------------------------------------------------------------- what an FMU holds, checks, compiling
#: The interfaces fmusa runs (FMI 2.0 and 3.0), in order of preference for ``interface: auto``.
INTERFACES = ("co-simulation", "model-exchange")
#: Values of ``fmu_options.interface``.
INTERFACE_CHOICES = ("auto",) + INTERFACES
#: fmpy's solvers for model exchange FMUs.
SOLVERS = ("CVode", "Euler")
_FMPY_TYPE = {"co-simulation": "CoSimulation", "model-exchange": "ModelExchange"}
_SHORT = {"co-simulation": "CS", "model-exchange": "ME"}


class FMUError(FmusaError, ValueError):
    """An FMU fmusa cannot run as asked: neither FMI 2.0 nor 3.0, the requested interface missing, no binary for
    this platform and no sources to build one, an unreadable model description, an unknown variable
    name or a value of the wrong type for a variable.

    Fix: ``fmusa inspect FMU`` shows what the FMU declares. Export it again as FMI 2.0 with the interface you
    ask for and a binary for this platform (or its C sources), or correct the variable name or value the
    message names (it lists the closest names).
    """


class FMUNotFoundError(FmusaError, FileNotFoundError):
    """The FMU file is missing (a ``FileNotFoundError`` too, as it was before fmusa had its own errors).

    Fix: give the right path to the ``.fmu`` file; for the built ScrewVertebra FMU run ``make fmu`` (it writes
    ``dist/ScrewVertebra.fmu``) or point ``$FMUSA_FMU`` at it.
    """

    exit_code = 1


class FMUCompileError(FmusaError, RuntimeError):
    """Building an FMU's binary from its C sources failed; the message names the FMU and holds the
    compiler's output.

    Fix: read the compiler output in the message. Install a C compiler (and CMake, for fmpy's build template),
    or export the FMU again with a binary for this platform (``fmusa inspect FMU`` shows the binaries it has).
    """

    exit_code = 1


class FMURunError(FmusaError, RuntimeError):
    """A run the FMU rejected (an FMI call returned Error or Fatal, or its outputs were not finite); the
    message names the phase of the run, the parameters set and the FMU's log.

    Fix: read the FMU's log in the message: the parameters may be outside the range the model is meant for (a
    zero mass, a negative stiffness), or the solver settings too tight. In a study the run is recorded as
    failed with this reason and the study goes on.
    """

    exit_code = 1


class FMUTimeLimitError(FMURunError):
    """A run stopped at a communication point because it passed its runner's ``deadline``: the caller that
    set the deadline words the reason (which limit, and how to raise it).

    Fix: if the FMU is only slow, raise the limit the message names (``execution.timeout_s`` in a study) and
    rerun without ``--resume``; if it hangs, check the parameters of that run.
    """


def host_platform(fmi_version: str = "2.0") -> str:
    """The platform directory of this machine for an FMU of ``fmi_version``: FMI 2.0's ``linux64``,
    FMI 3.0's platform tuple ``x86_64-linux`` (on Linux x86-64)."""
    import fmpy
    return fmpy.platform_tuple if str(fmi_version).startswith("3") else fmpy.platform


def host_platforms() -> tuple[str, str]:
    """This machine's platform directories of both FMI versions (``linux64``, ``x86_64-linux``)."""
    return host_platform("2.0"), host_platform("3.0")


def _an(word: str) -> str:
    return f"an {word}" if word[:1].lower() in "aeiou" else f"a {word}"


def member_problem(name: str) -> str | None:
    """Why a member name cannot be unpacked inside the extraction folder, or None."""
    if "\\" in name:
        return "contains a backslash (FMI requires forward slashes)"
    if "\0" in name:
        return "contains a NUL character"
    if name.startswith("/") or (len(name) > 1 and name[1] == ":"):
        return "is an absolute path"
    if ".." in PurePosixPath(name).parts:
        return "leads out of the archive's folder ('..')"
    return None


def identifier_problem(identifier: str) -> str | None:
    """Why a ``modelIdentifier`` cannot name the FMU's library file inside ``binaries/<platform>/``, or None:
    it is a file name (FMI: a C identifier), never a path."""
    if not identifier or identifier.strip() != identifier:
        return "is empty or has leading or trailing blanks"
    if any(ch in identifier for ch in "/\\:\0") or identifier in (".", ".."):
        return "is a path, not a file name (FMI requires a C identifier such as My_Model)"
    return None


def inside(root: str | os.PathLike, name: str) -> bool:
    """Whether ``root/name`` resolves (symbolic links followed) to ``root`` or below: the check of every name
    that an FMU supplies before fmusa reads, writes, compiles or loads a file by it."""
    if member_problem(name):
        return False
    base = Path(root).resolve()
    try:
        (base / name).resolve().relative_to(base)
    except (ValueError, OSError, RuntimeError):
        return False
    return True


#: Largest total of unpacked bytes (FMUSA_MAX_FMU_BYTES overrides it), applied to every member read, the
#: model description first: models with large tables or resources stay far below it, and a runaway
#: archive cannot fill the disk or the memory.
MAX_FMU_BYTES = 2 * 1024 ** 3
ENV_MAX_BYTES = "FMUSA_MAX_FMU_BYTES"
#: Most members (files and folders) an FMU may have (FMUSA_MAX_FMU_MEMBERS overrides it): exports hold a
#: few hundred; reading the archive's directory costs memory and time per member.
MAX_FMU_MEMBERS = 100_000
ENV_MAX_MEMBERS = "FMUSA_MAX_FMU_MEMBERS"
_CHUNK = 1 << 20


def _env_limit(name: str, default: int, example: str, what: str) -> int:
    text = os.environ.get(name, "").strip()
    if not text:
        return default
    try:
        value = int(float(text))
    except (ValueError, OverflowError):
        raise FMUError(f"{name}={text!r} is not {what}; set e.g. {name}={example} or unset it") from None
    if value <= 0:
        raise FMUError(f"{name}={text!r} must be positive; unset it for the default ({default})")
    return value


def max_fmu_bytes() -> int:
    """The unpacking limit in bytes: ``$FMUSA_MAX_FMU_BYTES`` or :data:`MAX_FMU_BYTES`."""
    return _env_limit(ENV_MAX_BYTES, MAX_FMU_BYTES, "4e9", "a number of bytes")


def max_fmu_members() -> int:
    """The most members an FMU may have: ``$FMUSA_MAX_FMU_MEMBERS`` or :data:`MAX_FMU_MEMBERS`."""
    return _env_limit(ENV_MAX_MEMBERS, MAX_FMU_MEMBERS, "200000", "a number of members")


def check_fmu_path(path: Path, label: str | None = None) -> None:
    """Refuse, before anything opens it, a path that is neither a regular file nor an FMU folder: a device
    (``/dev/zero`` reads forever), a FIFO (blocks), a socket, or a folder without a model description."""
    what = label or str(path)
    if not path.exists():
        raise FMUNotFoundError(f"FMU not found: {what}")
    if path.is_dir():
        if not (path / "modelDescription.xml").is_file():
            raise FMUError(f"{what}: a folder without a modelDescription.xml file, so not an extracted FMU; "
                           f"give the .fmu file or the folder an FMU was unpacked into")
        return
    if not path.is_file():
        raise FMUError(f"{what}: not a regular file (a device, a FIFO or a socket); give the .fmu file")


def _zip_member_count(path: Path) -> int | None:
    """The number of members the ZIP file's end-of-directory record declares (read before zipfile builds
    an object per member), or None when the record is not found (zipfile then says why)."""
    import struct
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            size = f.tell()
            f.seek(max(0, size - (1 << 16) - 22))
            tail = f.read()
            at = tail.rfind(b"PK\x05\x06")
            if at < 0 or len(tail) < at + 22:
                return None
            count = struct.unpack("<H", tail[at + 10:at + 12])[0]
            loc = tail.rfind(b"PK\x06\x07", 0, at)            # ZIP64: the count is in its own record
            if count == 0xFFFF and loc >= 0 and len(tail) >= loc + 20:
                f.seek(struct.unpack("<Q", tail[loc + 8:loc + 16])[0])
                rec = f.read(56)
                if rec[:4] == b"PK\x06\x06" and len(rec) >= 40:
                    count = struct.unpack("<Q", rec[32:40])[0]
            return count
    except OSError:
        return None


def _too_many(path: Path, count: int, limit: int) -> FMUError:
    return FMUError(f"{path}: has {count} members, more than the limit of {limit} (FMUs hold a few hundred); "
                    f"if this FMU really needs them, raise the limit with {ENV_MAX_MEMBERS}")


def open_fmu_zip(path: Path) -> zipfile.ZipFile:
    """The FMU file ``path`` as an open ZipFile, its member count checked against :func:`max_fmu_members`
    before its directory is read. Raises :class:`FMUError`."""
    check_fmu_path(path)
    limit = max_fmu_members()
    count = _zip_member_count(path)
    if count is not None and count > limit:
        raise _too_many(path, count, limit)
    try:
        zf = zipfile.ZipFile(path)
    except zipfile.BadZipFile:
        raise FMUError(f"{path}: not an FMU (not a ZIP archive); export the FMU again") from None
    except OSError as exc:
        raise FMUError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if len(zf.infolist()) > limit:
        zf.close()
        raise _too_many(path, count or 0, limit)
    return zf


def _archive_names(path: Path) -> list[str]:
    """The files of an FMU folder or archive; a member that would unpack outside its folder is refused
    here, when the FMU is first read, not halfway through a study."""
    limit = max_fmu_members()
    if path.is_dir():
        names = []
        for p in path.rglob("*"):
            if len(names) >= limit:
                raise _too_many(path, len(names) + 1, limit)
            if p.is_file():
                names.append(p.relative_to(path).as_posix())
        return names
    with open_fmu_zip(path) as zf:
        names = zf.namelist()
    for n in names:
        problem = member_problem(n)
        if problem:
            raise FMUError(f"{path}: member '{n}' {problem}; the archive is not a valid FMU (export it again)")
    return [n for n in names if not n.endswith("/")]


def read_member(path: Path, name: str, limit: int | None = None) -> bytes | None:
    """The bytes of member ``name`` of the FMU file or folder ``path`` (None when it has none), read in
    bounded memory: more than ``limit`` bytes (default :func:`max_fmu_bytes`) is an FMUError, found from
    the archive's directory before a byte is unpacked, and counted while reading (directories can lie)."""
    limit = max_fmu_bytes() if limit is None else limit
    too_big = (f"{path}: {name} is larger than the limit of {limit} bytes; if the FMU really needs it, "
               f"raise the limit with {ENV_MAX_BYTES}")
    if path.is_dir():
        f = path / name
        if not f.exists():
            return None
        if not f.is_file() or not inside(path, name):
            raise FMUError(f"{path}: {name} is not a regular file inside the FMU folder")
        if f.stat().st_size > limit:
            raise FMUError(too_big)
        with open(f, "rb") as fh:
            data = fh.read(limit + 1)
    else:
        with open_fmu_zip(path) as zf:
            try:
                info = zf.getinfo(name)
            except KeyError:
                return None
            if info.file_size > limit:
                raise FMUError(too_big + f" (it unpacks to {info.file_size} bytes)")
            try:
                with zf.open(info) as src:
                    data = src.read(limit + 1)
            except (zlib.error, zipfile.BadZipFile, EOFError) as exc:
                raise FMUError(f"{path}: member '{name}' is damaged ({type(exc).__name__}: {exc}); the "
                               f"archive is corrupt: export or download the FMU again") from None
    if len(data) > limit:
        raise FMUError(too_big)
    return data


def _description_bytes(path: Path) -> bytes:
    """The bytes of the FMU's modelDescription.xml (read once, bounded: the root check and the parse both
    use them)."""
    data = read_member(path, "modelDescription.xml")
    if data is None:
        raise FMUError(f"{path}: not an FMU (no modelDescription.xml)")
    return data


def _root_attributes(path: Path, data: bytes) -> dict[str, str]:
    """Attributes of <fmiModelDescription> (fmiVersion, modelName…), read without fmpy, so that an
    FMI 1 or FMI 3 FMU is recognised before anything tries to parse it as FMI 2."""
    import xml.etree.ElementTree as ET
    try:
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        raise FMUError(f"{path}: modelDescription.xml is not well-formed XML ({exc})") from None
    return dict(root.attrib)


@dataclass(frozen=True, eq=False)
class FMUInfo:
    """What an FMU declares and contains, read from its model description and its file list (no binary
    is loaded). Made by :func:`read_fmu_info`."""
    path: Path
    fmi_version: str
    model_name: str
    description: str
    generation_tool: str
    guid: str
    interfaces: dict            # interface ("co-simulation"/"model-exchange") -> model identifier
    binaries: dict              # platform directory -> list of files in it
    source_files: tuple         # the files listed under <SourceFiles>
    has_sources: bool           # the archive has sources/*.c (or .cpp)
    default_experiment: dict    # start_time, stop_time, tolerance, step_size (those declared)
    variables: tuple            # fmpy ModelVariable objects, in model-description order
    n_states: int
    n_event_indicators: int
    model_description: object   # the fmpy ModelDescription
    warnings: tuple = ()        # e.g. fmpy's schema validation problems (the FMU is still read)
    #: The variables as declared (FMI 3.0: fmpy's, arrays whole); ``variables`` holds what a study can
    #: address, an FMI 3.0 array as one element variable per element (``name[i]``, ``name[i,j]``).
    declared: tuple = ()
    #: Names from the archive that would lead outside its folder (a modelIdentifier that is a path, a source
    #: file with '..'): such an FMU is shown by ``inspect`` and refused by everything that runs or builds it.
    unsafe: tuple = ()

    @property
    def is_fmi3(self) -> bool:
        return str(self.fmi_version).startswith("3")

    @property
    def declared_variables(self) -> tuple:
        """The variables as the model description declares them (arrays whole), for ``inspect``."""
        return self.declared or self.variables

    @property
    def host_platform(self) -> str:
        """This machine's binary directory for this FMU's FMI version."""
        return host_platform(self.fmi_version)

    @property
    def platforms(self) -> list[str]:
        """Platforms with a binary (``linux64``, ``win64``, ``darwin64``…)."""
        return sorted(p for p, files in self.binaries.items() if files)

    def variable(self, name: str):
        return self._by_name.get(name)

    @property
    def _by_name(self) -> dict:
        d = self.__dict__.get("_names")
        if d is None:
            d = {v.name: v for v in self.variables}
            object.__setattr__(self, "_names", d)
        return d

    def binary_name(self, interface: str) -> str:
        import fmpy
        return f"{self.interfaces[interface]}{fmpy.sharedLibraryExtension}"

    def has_binary(self, interface: str, platform: str | None = None) -> bool:
        """Whether the shared library of ``interface`` is there for ``platform`` (default: this machine)."""
        platform = platform or self.host_platform
        return self.binary_name(interface) in self.binaries.get(platform, [])

    @property
    def can_compile(self) -> bool:
        """Whether fmusa can build a binary from the sources (FMI 2.0 only: it builds with FMI 2 headers)."""
        return self.has_sources and bool(self.source_files) and not self.is_fmi3


#: read_fmu_info's answers for FMU files, keyed by (path, size, modification time): a study reads the same
#: FMU several times (checks, preparation, runners), and parsing its description costs ~10 ms each time.
_INFO_CACHE: dict[tuple, "FMUInfo"] = {}


def read_fmu_info(path: str | os.PathLike, require_fmi2: bool = True) -> FMUInfo:
    """Read what ``path`` (an ``.fmu`` file or an extracted FMU directory) declares and contains.

    Raises :class:`FMUError` when it is not an FMU, or (``require_fmi2``) neither an FMI 2.0 nor an FMI 3.0
    FMU (the name is older than fmusa's FMI 3.0 support: FMI 1.0 is refused). fmpy's
    schema validation problems do not stop the reading: they are kept in ``warnings``. An FMU file read
    before is not parsed again while its size and modification time are the same.
    """
    path = Path(path)
    check_fmu_path(path)          # a device, a FIFO: refused before anything opens it
    key = None
    if _ADOPTED and path.is_dir():
        adopted = _adopted(path)
        if adopted is not None and (adopted.fmi_version == "2.0" or not require_fmi2):
            return adopted
    if path.is_file():
        st = path.stat()
        key = (str(path.resolve()), st.st_size, st.st_mtime_ns, require_fmi2)
        if key in _INFO_CACHE:
            return _INFO_CACHE[key]
    info = _read_fmu_info(path, require_fmi2)
    if key is not None:
        _INFO_CACHE[key] = info
    return info


#: FMU folders read by another process (a pool's parent): folder -> (its modelDescription.xml's size and
#: modification time, the FMUInfo)
_ADOPTED: dict[str, tuple[tuple[int, int], "FMUInfo"]] = {}


def _stamp(folder: Path) -> tuple[int, int]:
    st = (folder / "modelDescription.xml").stat()
    return st.st_size, st.st_mtime_ns


def adopt_fmu_info(info: "FMUInfo") -> None:
    """Take ``info`` (what another process read from the unpacked FMU folder ``info.path``) as
    :func:`read_fmu_info`'s answer for that folder while its modelDescription.xml keeps its size and
    modification time: a worker process started by spawn then parses no description (seconds for one of
    200k variables)."""
    try:
        _ADOPTED[str(Path(info.path).resolve())] = (_stamp(Path(info.path)), info)
    except OSError:
        pass


def _adopted(folder: Path) -> "FMUInfo | None":
    hit = _ADOPTED.get(str(folder.resolve()))
    try:
        return hit[1] if hit is not None and hit[0] == _stamp(folder) else None
    except OSError:
        return None


#: Parsed model descriptions by the SHA-256 of their modelDescription.xml: an FMU unpacked for a study has
#: the description of the archive read just before, and validating it again costs ~10 ms.
_DESCRIPTIONS: dict[bytes, tuple] = {}


def _bounded_copy(path: Path, raw: bytes) -> "io.BytesIO":
    """An in-memory FMU of the description bytes ``raw`` already read (bounded) and, for FMI 3.0, the
    bounded ``sources/buildDescription.xml``: what fmpy parses, so that it never reads the archive itself."""
    import io
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        zf.writestr("modelDescription.xml", raw)
        build = read_member(path, "sources/buildDescription.xml")
        if build is not None:
            zf.writestr("sources/buildDescription.xml", build)
    buf.seek(0)
    return buf


def _parse_description(path: Path, raw: bytes) -> tuple:
    """(fmpy's model description of ``path``, the problems its validation found), parsed once per content
    ``raw`` (the bytes of its modelDescription.xml)."""
    import fmpy

    digest = hashlib.sha256(raw).digest()
    if digest in _DESCRIPTIONS:
        return _DESCRIPTIONS[digest]
    warnings: list[str] = []
    try:
        md = fmpy.read_model_description(_bounded_copy(path, raw), validate=True)
    except FMUError:
        raise
    except Exception as exc:  # schema or consistency problems: read it anyway, keep the problems
        try:
            md = fmpy.read_model_description(_bounded_copy(path, raw), validate=False)
        except Exception as exc2:
            raise FMUError(f"{path}: cannot read modelDescription.xml: {exc2}") from None
        warnings.append(f"fmpy's validation of modelDescription.xml failed: {str(exc).strip()}")
    if len(_DESCRIPTIONS) >= 16:
        _DESCRIPTIONS.pop(next(iter(_DESCRIPTIONS)))
    _DESCRIPTIONS[digest] = (md, warnings)
    return md, warnings


def _read_fmu_info(path: Path, require_fmi2: bool) -> FMUInfo:

    names = _archive_names(path)
    raw = _description_bytes(path)
    attrs = _root_attributes(path, raw)
    version = attrs.get("fmiVersion", "?")
    model = attrs.get("modelName", path.stem)
    major = version.split(".")[0]
    if require_fmi2 and version != "2.0" and major != "3":
        raise FMUError(f"{path}: {model} is an FMI {version} FMU (fmiVersion=\"{version}\" in its "
                       f"modelDescription.xml); fmusa needs FMI 2.0 or 3.0. Export the model again as an FMI "
                       f"2.0 or 3.0 co-simulation or model exchange FMU"
                       + (" (FMI 1.0 FMUs cannot be converted)" if major == "1" else ""))
    md, warnings = _parse_description(path, raw)
    interfaces = {}
    if getattr(md, "coSimulation", None) is not None:
        interfaces["co-simulation"] = md.coSimulation.modelIdentifier
    if getattr(md, "modelExchange", None) is not None:
        interfaces["model-exchange"] = md.modelExchange.modelIdentifier
    binaries: dict[str, list[str]] = {}
    for n in names:
        parts = n.split("/")
        if len(parts) == 3 and parts[0] == "binaries":
            binaries.setdefault(parts[1], []).append(parts[2])
    has_sources = any(n.startswith("sources/") and n.rsplit(".", 1)[-1] in ("c", "cc", "cpp", "cxx")
                      for n in names)
    source_files: list[str] = []
    for bc in getattr(md, "buildConfigurations", None) or []:
        for sfs in bc.sourceFileSets:
            source_files += [f for f in sfs.sourceFiles if f not in source_files]
    unsafe = [f"modelIdentifier {ident!r} of {iface} {why}" for iface, ident in interfaces.items()
              for why in [identifier_problem(ident)] if why]
    unsafe += [f"source file {f!r} (under <SourceFiles>) leads outside sources/" for f in source_files
               if member_problem(f) or (path.is_dir() and not inside(path / "sources", f))]
    if path.is_dir():     # an FMU folder: a link in it that leads away
        unsafe += [f"file {n!r} is a link that leads outside the FMU folder" for n in names if not inside(path, n)]
    de = md.defaultExperiment
    experiment = {}
    if de is not None:
        for key, attr in (("start_time", "startTime"), ("stop_time", "stopTime"),
                          ("tolerance", "tolerance"), ("step_size", "stepSize")):
            val = getattr(de, attr, None)
            if val is not None:
                try:
                    experiment[key] = float(val)
                except ValueError:
                    experiment[key] = val
    declared: tuple = ()
    variables = tuple(md.modelVariables)
    if str(md.fmiVersion).startswith("3"):
        declared, variables = variables, tuple(scalar_variables(md))
    return FMUInfo(path=path, fmi_version=md.fmiVersion, model_name=md.modelName or model,
                   description=md.description or "", generation_tool=md.generationTool or "",
                   guid=md.guid or "", interfaces=interfaces, binaries=binaries,
                   source_files=tuple(source_files), has_sources=has_sources,
                   default_experiment=experiment, variables=variables, declared=declared,
                   n_states=int(md.numberOfContinuousStates or 0),
                   n_event_indicators=int(md.numberOfEventIndicators or 0),
                   model_description=md, warnings=tuple(warnings), unsafe=tuple(unsafe))


# ---------------------------------------------------------------------- FMI 3.0 variables, element-wise
#: FMI 3.0 types fmusa sets and reads, as the FMI 2.0 kind the rest of fmusa knows them by.
FMI3_KIND = {"Float64": "Real", "Float32": "Real", "Int8": "Integer", "UInt8": "Integer", "Int16": "Integer",
             "UInt16": "Integer", "Int32": "Integer", "UInt32": "Integer", "Int64": "Integer",
             "UInt64": "Integer", "Boolean": "Boolean", "Enumeration": "Enumeration"}


@dataclass(frozen=True, eq=False)
class ScalarVariable:
    """One scalar of an FMI 3.0 FMU: a scalar variable, or one element of an array variable, named as
    Modelica and FMI 2.0's scalarised names do (``x[2]``, ``m[1,3]``, 1-based, row-major like FMI 3.0's
    serialisation). It reads like fmpy's FMI 2 ``ModelVariable`` (``type`` is the FMI 2 kind ``Real``,
    ``Integer``…), so the checks and runs written for FMI 2.0 apply unchanged; ``valueReference`` is its
    index among the FMU's scalars (what :class:`fmusa.fmi.fmi3.FMI3Instance` translates), ``vr`` the FMU's."""
    name: str
    type: str                   # FMI 2 kind (Real, Integer, Boolean, Enumeration) or the FMI 3 type name
    fmi3_type: str              # Float64, Int32, …
    causality: str | None
    variability: str | None
    initial: str | None
    valueReference: int         # the scalar's index (see the class docstring)
    vr: int                     # the FMU's value reference of the (array) variable
    index: int | None           # the element's flat, 0-based index in its array; None for a scalar
    size: int                   # number of elements of the variable (1 for a scalar)
    shape: tuple
    start: object
    description: str | None
    unit: str | None
    declaredType: object
    base: object                # fmpy's ModelVariable

    @property
    def array_name(self) -> str:
        return self.base.name

    def __getattr__(self, name: str):
        """fmpy's other attributes of the declared variable (``nominal``, ``min``, ``derivative`` …)."""
        if name.startswith("__") or name == "base":
            raise AttributeError(name)
        return getattr(self.base, name)


def _split_start(start, size: int) -> list | None:
    """An array variable's start as a list of ``size`` strings (None when it declares none)."""
    if start is None:
        return None
    items = start.split() if isinstance(start, str) else list(start)
    return items if len(items) == size else None


def scalar_variables(md) -> list[ScalarVariable]:
    """The scalars of FMI 3.0 model description ``md``: each scalar variable, and each element of each
    array variable (``name[i]``, ``name[i,j]``…, 1-based, row-major)."""
    import itertools
    out: list[ScalarVariable] = []
    for v in md.modelVariables:
        shape = tuple(int(n) for n in (v.shape or ()))
        kind = FMI3_KIND.get(v.type, v.type)
        common = dict(type=kind, fmi3_type=v.type, causality=v.causality, variability=v.variability,
                      initial=v.initial, vr=v.valueReference, description=v.description,
                      unit=getattr(v, "unit", None), declaredType=getattr(v, "declaredType", None), base=v,
                      shape=shape)
        if not shape:
            out.append(ScalarVariable(name=v.name, valueReference=len(out), index=None, size=1,
                                      start=v.start, **common))
            continue
        size = 1
        for n in shape:
            size *= n
        starts = _split_start(v.start, size)
        for flat, idx in enumerate(itertools.product(*[range(1, n + 1) for n in shape])):
            out.append(ScalarVariable(name=f"{v.name}[{','.join(map(str, idx))}]", valueReference=len(out),
                                      index=flat, size=size, start=None if starts is None else starts[flat],
                                      **common))
    return out


def array_hint(info: FMUInfo, name: str) -> str | None:
    """For the name of an FMI 3.0 array variable: how to address its elements; else None."""
    for v in info.declared:
        if v.name == name and v.shape:
            dims = "×".join(map(str, v.shape))
            first = "1" if len(v.shape) == 1 else ",".join("1" * len(v.shape))
            last = ",".join(map(str, v.shape))
            return (f"{name!r} is an array of {dims} elements; address one element as {name}[{first}] … "
                    f"{name}[{last}] (1-based)")
    return None


def select_interface(info: FMUInfo, requested: str = "auto") -> str:
    """The interface a study runs: co-simulation when the FMU has it (``auto``), else model exchange;
    or the one ``requested``. Raises :class:`FMUError` when the FMU does not implement it."""
    have = list(info.interfaces)
    if info.unsafe:
        raise FMUError(f"{info.path}: refused: {'; '.join(info.unsafe)}; fmusa uses no name from an FMU that "
                       f"leads outside the folder it is unpacked into. The FMU is broken or hostile: export it "
                       f"again (or ask its author)")
    if not have:
        raise FMUError(f"{info.path}: {info.model_name} declares neither <CoSimulation> nor "
                       f"<ModelExchange> in its modelDescription.xml")
    if requested in (None, "auto"):
        return "co-simulation" if "co-simulation" in have else "model-exchange"
    if requested not in INTERFACES:
        raise FMUError(f"unknown interface {requested!r}; use one of {', '.join(INTERFACE_CHOICES)}")
    if requested not in have:
        other = have[0]
        raise FMUError(f"interface {requested} was asked for, but {info.model_name} implements only "
                       f"{other} ({_SHORT[other]}); set interface: {other} or auto"
                       + ("" if other == "model-exchange" else
                          " (a co-simulation FMU brings its own solver)"))
    return requested


def binary_problem(info: FMUInfo, interface: str) -> str | None:
    """Why ``interface`` cannot run on this machine (no binary and no sources), or None."""
    if info.has_binary(interface) or info.can_compile:
        return None
    plat = info.host_platform
    if info.is_fmi3 and info.has_sources:
        return (f"{info.model_name} has no {plat} binary for {interface} "
                f"(binaries/{plat}/{info.binary_name(interface)}); fmusa builds binaries from the sources of "
                f"FMI 2.0 FMUs only: export the FMI 3.0 FMU with a {plat} binary")
    have = ", ".join(info.platforms) or "none"
    src = ("it has no C sources (sources/ and <SourceFiles>) to build one from" if not info.has_sources
           else "its sources/ are not listed under <SourceFiles> in modelDescription.xml, so they "
                "cannot be built")
    return (f"{info.model_name} has no {plat} binary for {interface} "
            f"(binaries/{plat}/{info.binary_name(interface)}; platforms with binaries: {have}), and "
            f"{src}; export the FMU for {plat}, or with source code")


def closest_names(name: str, pool: Iterable[str], n: int = 5) -> list[str]:
    """Names in ``pool`` closest to ``name`` (difflib), best first; case-insensitive as a fallback."""
    pool = list(pool)
    close = difflib.get_close_matches(name, pool, n=n, cutoff=0.4)
    if not close:
        lower = {p.lower(): p for p in pool}
        close = [lower[c] for c in difflib.get_close_matches(name.lower(), list(lower), n=n, cutoff=0.4)]
    return close


#: Variable types fmusa can set and read.
_TYPES = ("Real", "Integer", "Enumeration", "Boolean")


def variable_problem(info: FMUInfo, name: str, role: str) -> str | None:
    """Why FMU variable ``name`` cannot play ``role``, or None when it can.

    ``role`` is ``"varied"`` (a study parameter: a settable Real parameter, or a Real input held at the
    study's value over the run), ``"parameter"`` (set once per
    run: a settable parameter of any supported type), ``"input"`` or ``"output"`` (read after the run).
    The message lists the closest names the FMU does have.
    """
    vs = info.variables
    v = info.variable(name)
    if v is None and info.is_fmi3:
        hint_ = array_hint(info, name)
        if hint_:
            return hint_
    if role in ("varied", "parameter"):
        pool = [x.name for x in vs if x.causality == "parameter" and x.variability in ("fixed", "tunable")]
        if role == "varied":
            pool += [x.name for x in vs if x.causality == "input"]
        wider = pool
        what = "parameter"
    elif role == "input":
        pool = [x.name for x in vs if x.causality == "input"]
        wider = pool
        what = "input"
    else:
        pool = [x.name for x in vs if x.causality == "output"]
        wider = [x.name for x in vs if x.causality != "independent"]
        what = "output"

    def hint(prefix: str = "closest") -> str:
        others = [n for n in pool if n != name]
        if not others:     # an FMU without any: said first, whether or not the name exists
            kinds = f"{what}s or inputs" if role == "varied" else f"{what}s"
            text = f"; {info.model_name} has no {prefix + ' ' if prefix == 'settable' else ''}{kinds} at all"
            close = closest_names(name, [n for n in wider if n != name]) if v is None else []
            return text + (f" (closest names among its other variables: {', '.join(close)})" if close else "")
        close = closest_names(name, others)
        if not close and v is None:
            close = closest_names(name, [n for n in wider if n != name])
            if close:
                return f"; closest names: {', '.join(close)}"
        if close:
            return f"; {prefix} {what} names: {', '.join(close)}"
        if v is not None:
            return ""
        more = f" … ({len(others)} in all)" if len(others) > 12 else ""
        return f"; its {what}s are: {', '.join(others[:12])}{more}"

    if v is None:
        return f"{info.model_name} has no variable {name!r}{hint()}"
    causality, variability = v.causality or "local", v.variability or "continuous"
    if v.type not in _TYPES:
        return f"{name!r} is of type {v.type}; fmusa sets and reads only Real, Integer, Boolean and Enumeration"
    if role == "varied" and causality == "input":   # held at the study's value over the run
        if v.type != "Real":
            return (f"{name!r} is {_an(v.type)} input; a study parameter must be Real (hold {v.type} inputs "
                    f"under scenario.inputs)")
        return None
    if role in ("varied", "parameter"):
        if causality == "calculatedParameter":
            deps = None
            for u in getattr(info.model_description, "initialUnknowns", None) or []:
                if u.variable is v and u.dependencies:
                    deps = [d.name for d in u.dependencies]
            source = (f" ({', '.join(deps)})" if deps else
                      f" (its description: {v.description!r})" if v.description else "")
            return (f"{name!r} is a calculatedParameter: the FMU computes it from other parameters, so it "
                    f"cannot be set; set the parameters it is computed from{source} instead")
        if variability == "constant":
            return (f"{name!r} is a constant (variability constant, causality {causality}): its value is "
                    f"fixed in the FMU and cannot be set{hint('settable')}")
        if causality == "input":
            return f"{name!r} is an input, not a parameter; set it under scenario.inputs instead"
        if causality != "parameter":
            return (f"{name!r} is {_an(causality)} variable (causality {causality}), not a parameter, and "
                    f"cannot be set{hint('settable')}")
        if variability not in ("fixed", "tunable"):
            return (f"{name!r} has variability {variability}; only fixed or tunable parameters can be "
                    f"set{hint('settable')}")
        if role == "varied" and v.type != "Real":
            return (f"{name!r} is {_an(v.type)} parameter; a study parameter must be Real (set "
                    f"{v.type} parameters under fixed)")
        return None
    if role == "input":
        if causality == "input":
            return None
        if causality == "parameter":
            return f"{name!r} is a parameter, not an input; set it under fixed instead"
        return f"{name!r} is {_an(causality)} variable (causality {causality}), not an input{hint()}"
    if causality == "independent":
        return f"{name!r} is the independent variable (time); metrics read outputs"
    return None


