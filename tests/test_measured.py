"""The measured-data input layer (fmusa.diagnose.measured) and the shear-c67 glue: every bad input gives a
MeasuredDataError naming file, line and column; units, derived time, zeroing and downsampling are
exact on synthetic files; the 18 real shear tests load with sensible durations."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fmusa.applications.shear_c67 import data as shear_c67
from fmusa.diagnose.measured import ColumnSpec, Experiment, MeasuredDataError, downsample, load_experiment, load_experiments, parse_rate

#: The repository's copy of the shear data (specimens H1–H3 and H10–H21).
SHEAR = Path(__file__).resolve().parents[1] / "data" / "shear-c67"

N = 20


def write(tmp_path, text: str, name: str = "exp.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


def table(n: int = N, header: str = "time,displacement,force", rows=None) -> str:
    """A well-formed file: t = 0.1 i s, x = 1e-4 i m, F = 5 i N, with rows overridden by line."""
    lines = [header] + [f"{0.1 * i:.6g},{1e-4 * i:.6g},{5.0 * i:.6g}" for i in range(n)]
    for line, text in (rows or {}).items():
        lines[line - 1] = text
    return "\n".join(lines) + "\n"


def raises(path, *parts, drive="displacement", spec=ColumnSpec()):
    with pytest.raises(MeasuredDataError) as info:
        load_experiment(path, drive, spec)
    msg = str(info.value)
    for part in (str(path),) + parts:
        assert part in msg, msg
    return msg


# ============================================================================ errors
def test_missing_file(tmp_path):
    raises(tmp_path / "nope.csv", "file not found")


def test_directory(tmp_path):
    raises(tmp_path, "not a file")


def test_empty_file(tmp_path):
    raises(write(tmp_path, ""), ":1:", "empty")


def test_unreadable_binary(tmp_path):
    p = tmp_path / "bin.csv"
    p.write_bytes(b"time,displacement,force\n\xff\xfe\x00\x81,1,2\n")
    raises(p, "UTF-8")


def test_ragged_row(tmp_path):
    p = write(tmp_path, table(rows={5: "0.3,1,2,99"}))
    raises(p, f"{p}:5:", "4 fields, the header has 3")


def test_missing_column_lists_columns_and_option(tmp_path):
    p = write(tmp_path, table(header="t,displacement,Fx"))
    msg = raises(p, ":1:", "'time' (time)", "'force' (force)", "t, displacement, Fx",
                 "--time-column", "--force-column", "ColumnSpec.force", "--rate")
    assert "'displacement'" not in msg.split("the file has")[0]


def test_semicolon_file_hint(tmp_path):
    """Detected, it reads; read with the comma asked for, the message names --delimiter."""
    p = write(tmp_path, table().replace(",", ";"))
    assert load_experiment(p, "displacement").meta["delimiter"] == ";"
    raises(p, "another delimiter than ','", "--delimiter", spec=ColumnSpec(delimiter=","))


def test_header_only(tmp_path):
    raises(write(tmp_path, "time,displacement,force\n"), ":1:", "0 data rows", "at least 10")


def test_too_few_rows(tmp_path):
    raises(write(tmp_path, table(n=5)), ":2-6:", "5 data rows", "at least 10")


def test_non_numeric_cell(tmp_path):
    p = write(tmp_path, table(rows={7: "0.5,5e-4,abc"}))
    raises(p, f"{p}:7:", "column 'force' (force)", "'abc' is not a number")


def test_decimal_comma_hint(tmp_path):
    p = write(tmp_path, table(header="time;displacement;force").replace(",", ";")
              .replace("0.5;", "0,5;"))
    raises(p, ":7:", "column 'time' (time)", "'0,5'", "'.'", spec=ColumnSpec(delimiter=";"))


def test_nan_cell(tmp_path):
    p = write(tmp_path, table(rows={4: "0.2,NaN,10"}))
    raises(p, f"{p}:4:", "column 'displacement' (displacement, the drive)", "NaN")


def test_empty_cell_first_by_line_and_count(tmp_path):
    p = write(tmp_path, table(rows={9: "0.7,,35", 6: "0.4,4e-4,", 12: "1,1e-3,"}))
    raises(p, f"{p}:6:", "column 'force' (force)", "empty cell", "1 more bad cell")


def test_blank_line_inside(tmp_path):
    p = write(tmp_path, table(rows={8: ""}) + "\n\n")  # trailing blank lines are fine
    raises(p, f"{p}:8:", "column 'time'", "empty cell")


def test_infinite_cell(tmp_path):
    raises(write(tmp_path, table(rows={3: "0.1,inf,5"})), ":3:", "displacement", "infinite")


def test_non_increasing_time(tmp_path):
    p = write(tmp_path, table(rows={11: "0.8,9e-4,45"}))  # line 10 holds t = 0.8
    raises(p, f"{p}:11:", "column 'time' (time)", "0.8 s is not after 0.8 s on line 10",
           "increase strictly")


def test_decreasing_time(tmp_path):
    raises(write(tmp_path, table(rows={15: "0.1,1.3e-3,65"})), ":15:", "column 'time'",
           "on line 14")


def test_drive_does_not_move(tmp_path):
    text = "time,displacement,force\n" + "".join(f"{0.1 * i},0.002,{i}\n" for i in range(N))
    p = write(tmp_path, text)
    raises(p, f"{p}:2-21:", "column 'displacement' (displacement, the drive)", "does not move",
           "--drive")
    load_experiment(p, "force")  # force moves: fine as the drive


def test_drive_moves_below_resolution(tmp_path):
    text = "time,d,force\n" + "".join(f"{0.1 * i},{5 + 1e-13 * i:.17g},{i}\n" for i in range(N))
    raises(write(tmp_path, text), "column 'd'", "does not move",
           spec=ColumnSpec(displacement="d", displacement_unit="mm"))


def test_bad_drive_name(tmp_path):
    raises(write(tmp_path, table()), "--drive", drive="velocity")


@pytest.mark.parametrize("kwargs, parts", [
    ({"force_unit": "kg"}, ["force unit", "unknown unit 'kg'", "N, kN, mN, lbf", "--force-unit"]),
    ({"time_unit": "mm"}, ["time unit", "'mm' is a length unit, not a time unit", "s, ms, min"]),
    ({"displacement_unit": "N"}, ["'N' is a force unit, not a length unit", "m, cm, mm, um"]),
    ({"time_unit": "mm/s"}, ["'mm/s' is a rate unit"]),
    ({"rate": "10 furlong/s"}, ["rate", "mm/s", "N/s", "--rate"]),
    ({"rate": "fast"}, ["'10 mm/s'"]),
    ({"rate": "-1 mm/s"}, ["positive"]),
    ({"force": "x", "displacement": "x"}, ["must differ"]),
    ({"force": " "}, ["force column name"]),
])
def test_bad_spec(kwargs, parts):
    with pytest.raises(MeasuredDataError) as info:
        ColumnSpec(**kwargs)
    for part in parts:
        assert part in str(info.value), str(info.value)


def test_rate_dimension_must_match_drive(tmp_path):
    p = write(tmp_path, "displacement,force\n" + "".join(f"{i},{i}\n" for i in range(N)))
    raises(p, "displacement rate but the drive is force", "N/s", drive="force",
           spec=ColumnSpec(rate="1 mm/s"))


def test_rate_and_time_column_conflict(tmp_path):
    raises(write(tmp_path, table()), ":1:", "column 'time'", "use one",
           spec=ColumnSpec(rate="1 mm/s"))


def test_rate_needs_monotone_drive(tmp_path):
    x = np.concatenate([np.linspace(0, 1, 20), np.linspace(1, 0, 20)[1:]])
    p = write(tmp_path, "displacement,force\n" + "".join(f"{v},{2 * v}\n" for v in x))
    raises(p, ":2-40:", "column 'displacement' (displacement, the drive)", "back and forth",
           "--time-column", spec=ColumnSpec(rate="1 m/s"))


# ============================================================================ conversion
def test_default_format_si(tmp_path):
    exp = load_experiment(write(tmp_path, table()), "displacement", zero_drive=False)
    assert isinstance(exp, Experiment) and exp.name == "exp" and exp.n == N
    np.testing.assert_allclose(exp.t, 0.1 * np.arange(N))
    np.testing.assert_allclose(exp.displacement, 1e-4 * np.arange(N))
    assert exp.drive_signal is exp.displacement and exp.response_signal is exp.force
    assert exp.response == "force"
    with pytest.raises(ValueError):
        exp.t[0] = 1.0  # read-only
    assert exp.meta["rows"] == N and exp.meta["lines"] == (2, N + 1)
    assert exp.meta["time_derived"] is False and exp.meta["zero_shift"] == 0.0


def test_unit_conversion_and_mapping(tmp_path):
    text = "Fx,ms,d_mm,extra\n" + "".join(f"{0.5 * i},{10 * i + 100},{0.2 * i + 3},x\n"
                                           for i in range(N))
    spec = ColumnSpec(time="ms", time_unit="ms", displacement="d_mm", displacement_unit="mm",
                      force="Fx", force_unit="kN", flip_force=True)
    exp = load_experiment(write(tmp_path, text), "force", spec, zero_drive=False, zero_time=False)
    i = np.arange(N)
    np.testing.assert_allclose(exp.t, 1e-3 * (10 * i + 100), rtol=1e-15)
    np.testing.assert_allclose(exp.displacement, 1e-3 * (0.2 * i + 3), rtol=1e-15)
    np.testing.assert_allclose(exp.force, -1e3 * 0.5 * i, rtol=1e-15)
    assert exp.drive_signal is exp.force and exp.response == "displacement"
    assert exp.meta["units"] == {"time": "ms", "displacement": "mm", "force": "kN"}
    assert exp.meta["flipped"] == ["force"]


def test_other_units():
    assert ColumnSpec(force_unit="lbf").scale("force") == pytest.approx(4.4482216152605)
    assert ColumnSpec(displacement_unit="\u00b5m").scale("displacement") == 1e-6
    assert ColumnSpec(displacement_unit="cm").scale("displacement") == 1e-2
    assert ColumnSpec(time_unit="min").scale("time") == 60.0
    assert parse_rate("10 mm/s") == (pytest.approx(0.01), "mm/s", "displacement")
    assert parse_rate("6mm/min")[0] == pytest.approx(1e-4)
    assert parse_rate("2.5e1 um/s")[0] == pytest.approx(2.5e-5)
    assert parse_rate("3 kN/s") == (3000.0, "kN/s", "force")


def test_zero_drive_and_time(tmp_path):
    text = "time,displacement,force\n" + "".join(f"{2 + 0.1 * i},{0.5 + 0.01 * i},{7 + i}\n"
                                                 for i in range(N))
    exp = load_experiment(write(tmp_path, text), "displacement",
                          ColumnSpec(displacement_unit="mm"))
    assert exp.t[0] == 0.0 and exp.meta["time_shift"] == 2.0
    assert exp.displacement[0] == 0.0 and exp.meta["zero_shift"] == pytest.approx(5e-4)
    np.testing.assert_allclose(exp.displacement, 1e-5 * np.arange(N), atol=1e-18)
    np.testing.assert_allclose(exp.force, 7 + np.arange(N))  # the response is left alone


def test_time_from_rate_exact(tmp_path):
    """Noise-free uniform samples at 10 mm/s, dt = 2 ms: 0.02 mm per sample, time exact."""
    n, dt = 200, 2e-3
    x_mm = 0.3 - 10.0 * dt * np.arange(n)  # moving negative, as the Pos tests do
    p = write(tmp_path, "x,F\n" + "".join(f"{v:.17g},{3 * v:.17g}\n" for v in x_mm))
    spec = ColumnSpec(displacement="x", displacement_unit="mm", force="F", rate="10 mm/s")
    exp = load_experiment(p, "displacement", spec)
    np.testing.assert_allclose(exp.t, dt * np.arange(n), rtol=1e-12, atol=1e-15)
    assert exp.meta["time_derived"] and exp.meta["dt"] == pytest.approx(dt, rel=1e-12)
    assert exp.meta["rate_si"] == pytest.approx(0.01) and exp.meta["columns"]["time"] is None


def test_time_from_force_rate(tmp_path):
    p = write(tmp_path, "displacement,force\n" + "".join(f"{1e-5 * i},{0.05 * i}\n"
                                                          for i in range(50)))
    exp = load_experiment(p, "force", ColumnSpec(rate="3 kN/min"))  # 50 N/s, 0.05 N per sample
    assert exp.meta["dt"] == pytest.approx(1e-3, rel=1e-9)


# ============================================================================ downsampling
def test_downsample(tmp_path):
    n = 1002
    i = np.arange(n)
    p = write(tmp_path, "time,displacement,force\n" + "".join(
        f"{0.01 * k},{1e-3 * np.sin(k / 100):.17g},{np.cos(k / 50):.17g}\n" for k in i))
    exp = load_experiment(p, "displacement")
    small = downsample(exp, 102)  # 1000 inner samples in 100 blocks of 10
    assert small.n == 102 and small.meta["block"] == 10 and small.meta["downsampled_from"] == n
    for a, b in ((exp.t, small.t), (exp.displacement, small.displacement),
                 (exp.force, small.force)):
        assert b[0] == a[0] and b[-1] == a[-1]
        assert b[1:-1].mean() == pytest.approx(a[1:-1].mean(), rel=1e-12, abs=1e-15)
        # the time integral (what a fit sees) barely moves
        assert np.trapezoid(b, small.t) == pytest.approx(np.trapezoid(a, exp.t), rel=1e-2,
                                                         abs=1e-9)
    assert np.all(np.diff(small.t) > 0)
    line = load_experiment(write(tmp_path, table(n=1000), "line.csv"), "force")
    thin = downsample(line, 50)  # a linear record stays on its line
    np.testing.assert_allclose(thin.displacement, 1e-3 * thin.t, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(thin.force, 50 * thin.t, rtol=1e-9, atol=1e-12)
    odd = downsample(exp, 97)  # uneven last block
    assert odd.n <= 97 and odd.t[-1] == exp.t[-1] and np.all(np.diff(odd.t) > 0)
    assert downsample(exp, n) is exp  # no-op
    with pytest.raises(MeasuredDataError, match="max_points"):
        downsample(exp, 2)


# ============================================================================ several files
def test_load_experiments_unique_names_and_all_errors(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    p1 = write(tmp_path / "a", table(), "run.csv")
    p2 = write(tmp_path / "b", table(), "run.csv")
    p3 = write(tmp_path, table(), "other.csv")
    exps = load_experiments([p1, p2, p3], "displacement", max_points=12)
    assert [e.name for e in exps] == ["a_run", "b_run", "other"]
    assert all(e.n <= 12 for e in exps)
    with pytest.raises(MeasuredDataError, match="given twice"):
        load_experiments([p1, p1], "displacement")
    bad1 = write(tmp_path, table(rows={4: "x,1,2"}), "bad1.csv")
    bad2 = write(tmp_path, table(n=3), "bad2.csv")
    with pytest.raises(MeasuredDataError) as info:
        load_experiments([p3, bad1, bad2], "displacement")
    msg = str(info.value)
    assert "2 of 3 files" in msg and f"{bad1}:4:" in msg and f"{bad2}:2-4:" in msg
    with pytest.raises(MeasuredDataError, match="no measured-data files"):
        load_experiments([], "force")


# ============================================================================ the real data
def test_shear_tests_load():
    tests = shear_c67.list_tests(SHEAR)
    assert {"H1", "H2", "H3"} <= set(tests.specimen) and not {f"H{k}" for k in range(4, 10)} & set(tests.specimen)
    tests = tests[tests.specimen.isin(["H1", "H2", "H3"])].reset_index(drop=True)   # the folder also holds H10–H21
    assert len(tests) == 18
    assert set(tests.specimen) == {"H1", "H2", "H3"} and set(tests.direction) == {"Ant", "Pos"}
    assert sorted(set(tests.rate_mm_s)) == [1.0, 10.0, 100.0]
    for _, row in tests.iterrows():
        exp = shear_c67.load_test(row, max_points=None)
        assert exp.drive == "displacement" and exp.meta["time_derived"] and exp.t[0] == 0.0
        assert exp.displacement[0] == 0.0 and exp.meta["specimen"] == row.specimen
        travel = abs(exp.displacement[-1]) / (row.rate_mm_s * 1e-3)  # s at the nominal rate
        assert 0.8 * travel < exp.duration < 1.25 * travel, (exp.name, exp.duration, travel)
        sign = 1 if row.direction == "Ant" else -1  # Pos: negative displacement and force
        assert sign * exp.displacement[-1] > 0.5e-3
        assert sign * exp.response_signal[np.argmax(np.abs(exp.force))] > 100
    exp = shear_c67.load_test(tests.path[0])  # H1 Ant 1 mm/s: about 0.9 mm in about 0.9 s
    assert exp.n <= 1000 and exp.meta["downsampled_from"] == 1522
    assert 0.85 < exp.duration < 1.05 and 0.85e-3 < exp.displacement[-1] < 0.95e-3
    flipped = shear_c67.load_test(tests.path[3], flip_pos=True)
    assert flipped.displacement[-1] > 0 and flipped.force.max() > 150


def test_shear_authors_bilinear():
    fits = shear_c67.authors_bilinear(SHEAR)
    assert len(fits) == 6 * shear_c67.list_tests(SHEAR).specimen.nunique()      # one row per test on file
    assert {"specimen", "direction", "rate_mm_s", "stiffness_1", "stiffness_2", "breakpoint_mm",
            "intercept_1", "intercept_2", "r2_1", "peak_load_N", "peak_disp_mm"} <= set(fits)
    row = fits[(fits.specimen == "H1") & (fits.direction == "Ant") & (fits.rate_mm_s == 1)].iloc[0]
    assert row.stiffness_1 == pytest.approx(225.42752) and row.breakpoint_mm == pytest.approx(0.4409,
                                                                                            abs=1e-4)
    # the two phases meet at the breakpoint
    b = fits.breakpoint_mm
    np.testing.assert_allclose(fits.stiffness_1 * b + fits.intercept_1,
                               fits.stiffness_2 * b + fits.intercept_2, atol=1e-3)
    assert (fits[fits.direction == "Pos"].breakpoint_mm < 0).all()


def test_shear_bad_name(tmp_path):
    with pytest.raises(MeasuredDataError, match="H<k>_C67"):
        shear_c67.load_test(write(tmp_path, table(), "whatever.csv"))
    with pytest.raises(MeasuredDataError, match="data folder not found.*--data FOLDER") as info:
        shear_c67.list_tests(tmp_path / "none")
    assert str(tmp_path / "none") in str(info.value)
