"""Hostile and careless input, part 3: names from an FMU archive that lead outside its folder, a model
description padded to gigabytes, an archive of very many members, FMU paths that are devices, FIFOs or
folders, huge integers and recursive aliases in a study file, CSV dialects and duplicate headers, FMU and
data-file text that would be Markdown or HTML in a report, and a study that names files elsewhere.

Each test builds the input as a hostile or careless user would (archives from the built FMU, rewritten
byte by byte where zipfile cannot write them) and asserts a clear error, in bounded time and memory, with
nothing written outside the folders fmusa owns.
"""
from __future__ import annotations

import os
import re
import struct
import subprocess
import sys
import time
import zipfile
import zlib
from pathlib import Path

import numpy as np
import pytest

from fmusa.api import parse_study
from fmusa.fmi.archive import extract_fmu
from fmusa.fmi.build import compile_sources, prepare_fmu
from fmusa.fmi.info import FMUError, default_fmu_path, read_fmu_info
from fmusa.study.schema import StudyError
from test_faults import SMALL, fmusa_cli

HOSTILE = "<script>alert(1)</script> | a `tick` [x](javascript:alert(1))"


# ----------------------------------------------------------------------------------------------- helpers
def write_zip(path: Path, members: list[tuple[str, bytes, int, int, int]]) -> Path:
    """A ZIP file of ``members`` (name, data as stored, CRC-32, uncompressed size, method 0 or 8), written
    byte by byte: zipfile cannot write a member whose compressed stream is given."""
    local, central = bytearray(), bytearray()
    for name, data, crc, size, method in members:
        n = name.encode()
        central += struct.pack("<4s4H2H3L5HLL", b"PK\x01\x02", 20, 20, 0, method, 0, 33, crc, len(data), size,
                               len(n), 0, 0, 0, 0, 0, len(local)) + n
        local += struct.pack("<4s5H3L2H", b"PK\x03\x04", 20, 0, method, 0, 33, crc, len(data), size, len(n), 0)
        local += n + data
    n = len(members)
    end = b""
    if n > 0xFFFF:          # ZIP64: the count in its own record, found through a locator
        at = len(local) + len(central)
        end = (struct.pack("<4sQ2H2L4Q", b"PK\x06\x06", 44, 45, 45, 0, 0, n, n, len(central), len(local))
               + struct.pack("<4sLQL", b"PK\x06\x07", 0, at, 1))
        n = 0xFFFF
    end += struct.pack("<4s4H2LH", b"PK\x05\x06", 0, 0, n, n, len(central), len(local), 0)
    path.write_bytes(bytes(local + central + end))
    return path


def deflated(name: str, data: bytes) -> tuple[str, bytes, int, int, int]:
    c = zlib.compressobj(6, zlib.DEFLATED, -15)
    return name, c.compress(data) + c.flush(), zlib.crc32(data), len(data), 8


def built_members(drop_binaries: bool = False, description: bytes | None = None) -> list:
    with zipfile.ZipFile(default_fmu_path()) as z:
        out = []
        for i in z.infolist():
            if i.is_dir() or (drop_binaries and i.filename.startswith("binaries/")):
                continue
            data = z.read(i)
            if i.filename == "modelDescription.xml" and description is not None:
                data = description
            out.append(deflated(i.filename, data))
    return out


def description(edit) -> bytes:
    with zipfile.ZipFile(default_fmu_path()) as z:
        return edit(z.read("modelDescription.xml").decode()).encode()


# ----------------------------------------------------------------------------------------------- names
def test_a_model_identifier_that_is_a_path_is_refused_and_inspect_says_so(tmp_path):
    escaped = f"../../../../../..{tmp_path}/ESCAPED"
    md = description(lambda t: t.replace('modelIdentifier="ScrewVertebra"', f'modelIdentifier="{escaped}"'))
    fmu = write_zip(tmp_path / "Escape.fmu", built_members(drop_binaries=True, description=md))
    info = read_fmu_info(fmu)
    assert info.unsafe and "is a path, not a file name" in info.unsafe[0]
    from fmusa.fmi.runner import FMURunner
    for attempt in (lambda: FMURunner(fmu), lambda: prepare_fmu(fmu, workdir=tmp_path / "w")):
        with pytest.raises(FMUError, match=r"Escape.fmu: refused: modelIdentifier '.*ESCAPED' of co-simulation "
                                           r"is a path"):
            attempt()
    folder = extract_fmu(fmu, tmp_path / "x")                     # unpacked as asked, never built
    with pytest.raises(FMUError, match="refused to build"):
        compile_sources(folder, info, "co-simulation")
    assert not list(tmp_path.glob("ESCAPED*")) and not list(Path("/").glob("ESCAPED*"))
    r = fmusa_cli("inspect", str(fmu))
    assert r.returncode == 0 and "Traceback" not in r.stderr
    flat = " ".join(r.stdout.split())                              # the table wraps long values
    assert re.search(r"UNSAFE modelIdentifier '.*ESCAPED' .*refuses to build or run", flat), r.stdout


def test_a_source_file_outside_sources_is_never_compiled(tmp_path):
    outside = tmp_path / "outside.c"
    outside.write_text("#error FIRST_LINE_OF_A_FILE_OUTSIDE\n")
    md = description(lambda t: t.replace('<File name="fmi2.c"/>', '<File name="fmi2.c"/><File name="../../outside.c"/>'))
    fmu = write_zip(tmp_path / "Src.fmu", built_members(drop_binaries=True, description=md))
    info = read_fmu_info(fmu)
    assert any("'../../outside.c'" in u and "leads outside sources/" in u for u in info.unsafe)
    folder = extract_fmu(fmu, tmp_path / "a" / "b")             # sources/../../outside.c is tmp_path/outside.c
    with pytest.raises(FMUError) as exc:
        compile_sources(folder, info, "co-simulation")
    assert "source files outside sources/ ('../../outside.c')" in str(exc.value)
    assert "FIRST_LINE" not in str(exc.value)
    with pytest.raises(FMUError, match="refused: .*source file '../../outside.c'"):
        prepare_fmu(fmu, workdir=tmp_path / "w")


# ----------------------------------------------------------------------------------------------- sizes
def repeated_crc(crc: int, block: bytes, n: int) -> int:
    """``zlib.crc32`` of ``block`` repeated ``n`` times after ``crc``, without reading 4 GB: the CRC is affine
    in its start value, x -> L·x ⊕ c over GF(2), so L's 32 columns are read off 33 CRCs of the block and
    applied ``n`` times."""
    c = zlib.crc32(block, 0)
    cols = [zlib.crc32(block, 1 << j) ^ c for j in range(32)]
    for _ in range(n):
        y, j = c, 0
        while crc:
            if crc & 1:
                y ^= cols[j]
            crc >>= 1
            j += 1
        crc = y
    return crc


def test_repeated_crc_is_the_crc_of_the_repeated_bytes():
    block = bytes(range(256)) * 7
    assert repeated_crc(12345, block, 5) == zlib.crc32(block * 5, 12345)


def padded_description_fmu(path: Path, pad: int = 4000 << 20) -> Path:
    """The built FMU with its modelDescription.xml followed by ``pad`` spaces (well-formed XML still): one
    deflate block of 1 MiB of spaces, repeated, compresses 4 GB into 4 MB; the CRC is computed for real."""
    md = description(lambda t: t)
    c = zlib.compressobj(9, zlib.DEFLATED, -15)
    head = c.compress(md) + c.flush(zlib.Z_FULL_FLUSH)
    mib = b" " * (1 << 20)
    block = c.compress(mib) + c.flush(zlib.Z_FULL_FLUSH)     # the same bytes for every MiB after a full flush
    tail = c.flush(zlib.Z_FINISH)
    n = pad >> 20
    crc = repeated_crc(zlib.crc32(md), mib, n)
    big = ("modelDescription.xml", head + block * n + tail, crc, len(md) + (n << 20), 8)
    members = [m for m in built_members() if m[0] != "modelDescription.xml"]
    return write_zip(path, [big] + members)


def test_a_description_padded_to_4_gb_is_refused_fast_in_bounded_memory(tmp_path):
    fmu = padded_description_fmu(tmp_path / "Padded.fmu")
    assert fmu.stat().st_size < 10 << 20
    with zipfile.ZipFile(fmu) as z:                                     # a valid archive: 4.2 GB unpacked
        assert z.getinfo("modelDescription.xml").file_size > 4e9
        with z.open("modelDescription.xml") as f:
            assert f.read(5) == b"<?xml"
    t0 = time.process_time()
    with pytest.raises(FMUError, match=r"Padded.fmu: modelDescription.xml is larger than the limit of \d+ bytes"
                                       r".*FMUSA_MAX_FMU_BYTES .*unpacks to 4\d{9} bytes"):
        read_fmu_info(fmu)
    with pytest.raises(FMUError, match="more than the limit"):
        extract_fmu(fmu, tmp_path / "x")
    assert time.process_time() - t0 < 2.0
    if sys.platform.startswith("linux"):       # the command, its address space capped far below 4 GB
        code = ("import resource, sys; resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30)); "
                "from fmusa.cli import main; sys.exit(main(['inspect', sys.argv[1]]))")
        r = subprocess.run([sys.executable, "-c", code, str(fmu)], capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert "larger than the limit" in r.stderr


def test_an_archive_of_very_many_members_is_refused_before_its_directory_is_read(tmp_path):
    empty = [(f"resources/f{i}", b"", 0, 0, 0) for i in range(100_001)]
    fmu = write_zip(tmp_path / "Many.fmu", built_members() + empty)
    t0 = time.process_time()
    with pytest.raises(FMUError, match=r"Many.fmu: has 1000\d\d members, more than the limit of 100000 .*"
                                       r"FMUSA_MAX_FMU_MEMBERS"):
        read_fmu_info(fmu)
    with pytest.raises(FMUError, match="more than the limit of 100000"):
        extract_fmu(fmu, tmp_path / "x")
    assert time.process_time() - t0 < 1.0
    assert not (tmp_path / "x" / "resources").exists()


# ----------------------------------------------------------------------------------------------- paths
@pytest.fixture
def not_files(tmp_path):
    fifo = tmp_path / "pipe.fmu"
    os.mkfifo(fifo)
    folder = tmp_path / "folder.fmu"
    folder.mkdir()
    return {"device": Path("/dev/zero"), "FIFO": fifo, "folder": folder}


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="FIFOs are POSIX")
@pytest.mark.parametrize("kind", ["device", "FIFO", "folder"])
def test_a_path_that_is_not_a_regular_file_is_refused_as_an_fmu_everywhere(tmp_path, not_files, kind, monkeypatch):
    path = not_files[kind]
    why = "not a regular file" if kind != "folder" else "a folder without a modelDescription.xml"
    with pytest.raises(FMUError, match=why):                                    # the API
        read_fmu_info(path)
    with pytest.raises(FMUError, match=why):
        extract_fmu(path, tmp_path / "x")
    from fmusa.fmi.runner import FMURunner                                      # --fmu
    with pytest.raises(FMUError, match=why):
        FMURunner(path)
    with pytest.raises(StudyError, match=r"s.yaml:2: key 'fmu' at the top level: .* is not a regular file"):
        parse_study(SMALL.replace("fmu: default", f"fmu: {path}"), tmp_path / "s.yaml")   # fmu: in a study
    monkeypatch.setenv("FMUSA_FMU", str(path))                                  # $FMUSA_FMU
    with pytest.raises(FMUError, match=r"\$FMUSA_FMU .*" + why):
        default_fmu_path()
    r = fmusa_cli("inspect", str(path), timeout=60)                             # inspect
    assert r.returncode != 0 and "Traceback" not in r.stderr and why in r.stderr, r.stderr


# ----------------------------------------------------------------------------------------------- study files
BIG = "1" * 401


@pytest.mark.parametrize("edit, line", [
    (lambda t: t + f"execution: {{timeout_s: {BIG}}}\n", 13),
    (lambda t: t + f"execution: {{workers: {BIG}}}\n", 13),
    (lambda t: t.replace("F_max: 411", f"F_max: {BIG}"), 5),
    (lambda t: t.replace("max: 5.0e-4", f"max: {BIG}"), 10),
    (lambda t: t.replace("grid: {values: {c: [4.0e5, 1.0e6]}}", f"grid: {{base: {BIG}, exponents: {{c: [0, 2]}}}}"), 12),
], ids=["timeout_s", "workers", "fixed", "constraint max", "grid base"])
def test_a_401_digit_integer_is_a_study_error_with_its_line(edit, line):
    with pytest.raises(StudyError, match=rf"^s.yaml:{line}: the integer 1+… \(401 digits\) is larger than"):
        parse_study(edit(SMALL), "s.yaml")


@pytest.mark.parametrize("text, line, match", [
    (SMALL + "paper: &r {x: *r}\n", 13, "a YAML alias refers to the list or mapping it is in"),
    (SMALL.replace("fixed: {F_max: 411, t_ramp: 10}", "fixed: &r {F_max: 411, t: [*r]}"), 5, "alias refers"),
    (SMALL + "paper: " + "[" * 3000 + "]" * 3000 + "\n", 13, "nested more than 100 levels deep"),
], ids=["paper", "fixed", "deep"])
def test_a_recursive_alias_is_a_study_error_with_its_line(text, line, match):
    with pytest.raises(StudyError, match=rf"^s.yaml:{line}: .*{match}"):
        parse_study(text, "s.yaml")


def test_a_study_that_names_a_file_elsewhere_reads_it_and_says_so(tmp_path):
    from fmusa.study.loader import files_outside
    fmu = default_fmu_path()
    here = tmp_path / "study"
    here.mkdir()
    (here / "m.fmu").symlink_to(fmu)
    inside = parse_study(SMALL.replace("fmu: default", "fmu: m.fmu"), here / "s.yaml")
    assert inside.fmu == fmu.resolve() or inside.fmu == (here / "m.fmu").resolve()
    elsewhere = parse_study(SMALL.replace("fmu: default", f"fmu: {fmu}"), here / "s.yaml")
    notes = files_outside(elsewhere)
    assert len(notes) == 1 and re.search(rf"s.yaml:2: the study reads the FMU {re.escape(str(fmu))}, outside", notes[0])
    up = parse_study(SMALL.replace("fmu: default", f"fmu: {os.path.relpath(fmu, here)}"), here / "s.yaml")
    assert up.fmu == fmu.resolve() and files_outside(up)          # relative, from the study's folder
    local = here / "own.fmu"
    local.write_bytes(fmu.read_bytes())
    assert files_outside(parse_study(SMALL.replace("fmu: default", "fmu: own.fmu"), here / "s.yaml")) == []


# ----------------------------------------------------------------------------------------------- CSV
def _csv(path: Path, header: str, sep: str, decimal: str) -> Path:
    t = np.linspace(0.0, 2.0, 41)
    rows = [header] + [sep.join(f"{v:.6g}".replace(".", decimal) for v in (a, 1e-3 * a, 50.0 * a + 0.25))
                       for a in t]
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")
    return path


@pytest.mark.parametrize("sep, decimal", [(";", ","), ("\t", ","), ("|", "."), (";", ".")])
def test_csv_dialects_are_detected_and_read_as_the_plain_file(tmp_path, sep, decimal):
    from fmusa.diagnose.measured import ColumnSpec, load_experiment
    plain = load_experiment(_csv(tmp_path / "plain.csv", "time,displacement,force", ",", "."), "displacement")
    other = _csv(tmp_path / "other.csv", sep.join(("time", "displacement", "force")), sep, decimal)
    e = load_experiment(other, "displacement")
    assert e.meta["delimiter"] == sep and e.meta["decimal"] == decimal
    assert e.meta["detected"][0].startswith(f"delimiter {sep!r}") and e.meta["detected"][1] == f"decimal mark {decimal!r}"
    for ch in ("t", "displacement", "force"):
        np.testing.assert_array_equal(getattr(e, ch), getattr(plain, ch))
    given = load_experiment(other, "displacement", ColumnSpec(delimiter=sep, decimal=decimal))
    assert given.meta["detected"] == [] and np.array_equal(given.force, plain.force)


def test_decimal_commas_read_as_points_are_named_with_the_option(tmp_path):
    from fmusa.diagnose.measured import ColumnSpec, MeasuredDataError, load_experiment
    f = _csv(tmp_path / "eu.csv", "time;displacement;force", ";", ",")
    with pytest.raises(MeasuredDataError, match=r"eu.csv:2: column 'force' \(force\): '0,25' is not a number; write "
                                                r"decimals with '.', not ','; .*give --decimal ','"):
        load_experiment(f, "displacement", ColumnSpec(decimal="."))


def test_duplicate_headers_are_refused_naming_both_columns(tmp_path):
    from fmusa.diagnose.measured import ColumnSpec, MeasuredDataError, load_experiment
    f = tmp_path / "dup.csv"
    f.write_text("time,Fx_N,disp,Fx_N\n" + "".join(f"{i},{i},{i * 1e-3},{2 * i}\n" for i in range(20)))
    with pytest.raises(MeasuredDataError, match=r"dup.csv:1: columns 2 and 4 are both headed 'Fx_N'"):
        load_experiment(f, "displacement", ColumnSpec(displacement="disp", force="Fx_N"))


def test_diagnose_takes_delimiter_and_decimal():
    from fmusa.cli import build_parser
    args = build_parser().parse_args(["diagnose", "a.csv", "--drive", "displacement", "--out", "o",
                                      "--delimiter", "tab", "--decimal", ","])
    assert args.delimiter == "\t" and args.decimal == ","
    with pytest.raises(SystemExit):
        build_parser().parse_args(["diagnose", "a.csv", "--drive", "displacement", "--out", "o", "--delimiter", "x"])


# ----------------------------------------------------------------------------------------------- escaping
_CELL = re.compile(r"(?<!\\)\|")


def _assert_inert(text: str, rows_with: str, cells: int) -> None:
    """No raw HTML, no link, and the row holding ``rows_with`` keeps its ``cells`` cells."""
    assert "<script" not in text and not re.search(r"(?<!\\)\]\(javascript:", text) and "[x](" not in text
    row = next(line for line in text.splitlines() if rows_with in line)
    assert len(_CELL.split(row.strip().strip("|"))) == cells, row


def test_fmu_and_log_text_is_escaped_in_the_report(tmp_path):
    import pandas as pd
    from types import SimpleNamespace
    from fmusa.report import sections as S
    from fmusa.report.context import ReportContext
    md = description(lambda t: re.sub(r'description="Rigid[^"]*"', 'description="' + HOSTILE.replace("<", "&lt;")
                                      .replace(">", "&gt;") + '"', t, count=1))
    fmu = write_zip(tmp_path / "Hostile.fmu", built_members(description=md))
    assert read_fmu_info(fmu).description == HOSTILE
    study = parse_study(SMALL.replace("fmu: default", f"fmu: {fmu}"), tmp_path / "s.yaml")
    runs = pd.DataFrame({"stage": ["grid"], "c": [4e5], "status": ["failed"], "message": [HOSTILE], "seconds": [0.1]})
    result = SimpleNamespace(study=study, runs=runs, summary={"runs": 1, "failed": 1}, out=tmp_path,
                             region=None)
    ctx = ReportContext(result, tmp_path)
    text = S.what_was_run_section(ctx) + S.failed_section(ctx)
    _assert_inert(text, "| FMU |", 2)
    _assert_inert(text, "| failed |", 4)
    assert "&lt;script&gt;alert(1)&lt;/script&gt; &#124; a \\`tick\\` \\[x\\](javascript:alert(1))" in text


def test_a_csv_column_name_is_escaped_in_the_diagnosis_report(tmp_path):
    from fmusa.diagnose.measured import ColumnSpec, load_experiment
    from fmusa.diagnose.report import _data_section
    f = _csv(tmp_path / "col.csv", f"time;displacement;{HOSTILE}", ";", ".")
    e = load_experiment(f, "displacement", ColumnSpec(force=HOSTILE))
    diag = {"data": {"drive": "displacement", "response": "force", "points": e.n}, "drive": "displacement"}
    text = _data_section(diag, [e])
    _assert_inert(text, "col.csv", 7)
    assert "&lt;script&gt;" in text
