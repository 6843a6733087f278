"""The command line and the public API around it: user errors are one line, bugs keep their traceback,
``--help`` and ``inspect`` import little, and ``import fmusa`` gives the README's names."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import fmusa
from fmusa.cli import main
from fmusa.errors import FmusaError, UsageError

HEAVY = ("numpy", "pandas", "scipy", "matplotlib", "fmpy", "yaml")


def _python(code: str, cwd: Path | None = None, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                          timeout=120, cwd=cwd, env=env)


def _crash_inspect(exc: str) -> subprocess.CompletedProcess:
    """`fmusa inspect` whose command function raises ``exc``."""
    return _python(f"""
        import sys
        import fmusa.cli as cli
        from fmusa.errors import FmusaError

        def boom(args):
            raise {exc}

        cli.cmd_inspect = boom
        sys.exit(cli.main(["inspect", "some.fmu"]))
    """)


def test_a_user_error_is_one_line_and_exit_2():
    r = _crash_inspect('FmusaError("some.fmu: not an FMU; export it again")')
    assert r.returncode == 2
    assert r.stderr == "fmusa inspect: some.fmu: not an FMU; export it again\n"
    assert r.stdout == ""


def test_a_bug_shows_its_traceback():
    """Not an FmusaError (a ValueError from a bug, say): the traceback, not a user-error line."""
    r = _crash_inspect('ValueError("an index went wrong")')
    assert r.returncode != 0
    assert "Traceback (most recent call last)" in r.stderr
    assert "ValueError: an index went wrong" in r.stderr
    assert "fmusa inspect: an index went wrong" not in r.stderr


def test_user_errors_keep_their_builtin_bases():
    """Older code catching ValueError / RuntimeError / FileNotFoundError still catches them."""
    from fmusa.diagnose.effects import DiagnoseError
    from fmusa.diagnose.measured import MeasuredDataError
    from fmusa.fmi.info import FMUCompileError, FMUError, FMUNotFoundError, FMURunError
    from fmusa.study.schema import StudyError

    for cls, base in ((StudyError, ValueError), (FMUError, ValueError), (FMUCompileError, RuntimeError),
                      (FMURunError, RuntimeError), (FMUNotFoundError, FileNotFoundError),
                      (DiagnoseError, ValueError), (MeasuredDataError, ValueError), (UsageError, ValueError)):
        assert issubclass(cls, FmusaError) and issubclass(cls, base), cls


def test_runner_errors_are_user_errors(fmu_path):
    from fmusa.fmi.info import FMUError

    with fmusa.FMURunner(fmu_path) as fmu:
        with pytest.raises(FMUError, match=r"unknown parameter 'c_yy'.*closest names: c_y"):
            fmu.run({"c_yy": 1.0}, stop_time=0.1, step=None, outputs=["y"])
        with pytest.raises(FMUError, match="cannot parse 'abc'"):
            fmu.parse_value("c_y", "abc")
        with pytest.raises(UsageError, match="stop_time must be a positive"):
            fmu.run({}, stop_time=-1.0, step=None, outputs=["y"])


def test_options_out_of_range_are_usage_errors(capsys):
    with pytest.raises(SystemExit) as e:
        main(["sweep", "studies/paper.yaml", "--out", "x", "--workers", "0"])
    assert e.value.code == 2 and "--workers: must be >= 1, got 0" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        main(["pullout", "--out", "x", "--stop-time", "-1"])
    assert e.value.code == 2 and "--stop-time: must be a positive finite number" in capsys.readouterr().err


def _loaded_after(code: str) -> set[str]:
    """The heavy libraries loaded once ``code`` has run in a fresh interpreter."""
    r = _python(textwrap.dedent(code) + f"\nimport sys\nprint('loaded:' + ','.join(m for m in {HEAVY!r} "
                                        f"if m in sys.modules))")
    assert r.returncode == 0, r.stderr
    return set(filter(None, r.stdout.rsplit("loaded:", 1)[1].strip().split(",")))


def test_import_fmusa_is_cheap():
    assert _loaded_after("import fmusa") == set()


def test_help_imports_no_heavy_library():
    """`fmusa --help` (and each subcommand's parser but diagnose's) needs only argparse."""
    assert _loaded_after("""
        import contextlib, io
        from fmusa.cli import main
        for argv in (["--help"], ["inspect", "--help"], ["sweep", "--help"], ["pullout", "--help"]):
            with contextlib.redirect_stdout(io.StringIO()):
                try:
                    main(argv)
                except SystemExit:
                    pass
    """) == set()


def test_inspect_imports_neither_pandas_nor_scipy_nor_matplotlib(fmu_path):
    loaded = _loaded_after(f"""
        import contextlib, io
        from fmusa.cli import main
        with contextlib.redirect_stdout(io.StringIO()):
            assert main(["inspect", {str(fmu_path)!r}]) == 0
    """)
    assert loaded <= {"fmpy", "numpy"}, loaded    # fmpy imports numpy itself


def test_diagnose_help_lists_the_candidates(capsys):
    from fmusa.diagnose.effects import CANDIDATES

    with pytest.raises(SystemExit):
        main(["diagnose", "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert all(c in out for c in CANDIDATES)


def test_public_api_names():
    """The names the README's Python examples use, each the object of its defining module."""
    from fmusa.api import load_study, run_study, write_report
    from fmusa.fmi.info import read_fmu_info
    from fmusa.fmi.runner import FMURunner

    assert fmusa.load_study is load_study and fmusa.run_study is run_study
    assert fmusa.FMURunner is FMURunner and fmusa.read_fmu_info is read_fmu_info
    assert fmusa.write_report is write_report and fmusa.FmusaError is FmusaError
    assert isinstance(fmusa.__version__, str)
    for name in fmusa.__all__:
        assert getattr(fmusa, name) is not None, name
    with pytest.raises(AttributeError):
        fmusa.no_such_name
    # fmusa.diagnose is the subpackage and, called, the diagnosis
    from fmusa.diagnose import measured

    assert fmusa.diagnose.measured is measured and callable(fmusa.diagnose)


def test_public_diagnose_is_the_diagnosis(monkeypatch):
    import fmusa.diagnose.run as dg

    seen = {}
    monkeypatch.setattr(dg, "diagnose", lambda *a, **k: seen.update(args=a, kw=k) or "diagnosis")
    assert fmusa.diagnose(["e"], "displacement", workers=1) == "diagnosis"
    assert seen == {"args": (["e"], "displacement"), "kw": {"workers": 1}}


def test_default_fmu_path(tmp_path, monkeypatch):
    """$FMUSA_FMU, else ./dist/ScrewVertebra.fmu under the working directory (an installed fmusa), else a
    clear error naming both and `make fmu`."""
    from fmusa.fmi import info
    from fmusa.fmi.info import FMUNotFoundError, default_fmu_path

    monkeypatch.delenv("FMUSA_FMU", raising=False)
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(info, "__file__", str(tmp_path / "site-packages" / "fmusa" / "fmi" / "info.py"))
    with pytest.raises(FMUNotFoundError) as e:
        default_fmu_path()
    msg = str(e.value)
    assert "FMUSA_FMU" in msg and str(tmp_path / "dist" / "ScrewVertebra.fmu") in msg and "make fmu" in msg
    assert e.value.exit_code == 1 and isinstance(e.value, FileNotFoundError)
    (tmp_path / "dist").mkdir()
    (tmp_path / "dist" / "ScrewVertebra.fmu").write_bytes(b"")
    assert default_fmu_path() == tmp_path / "dist" / "ScrewVertebra.fmu"
    other = tmp_path / "other.fmu"
    monkeypatch.setenv("FMUSA_FMU", str(other))
    with pytest.raises(FMUNotFoundError, match="FMUSA_FMU is set to .*other.fmu, which does not exist"):
        default_fmu_path()
    other.write_bytes(b"")
    assert default_fmu_path() == other


def test_inspect_of_a_missing_fmu_exits_1(tmp_path):
    r = subprocess.run([sys.executable, "-m", "fmusa.cli", "inspect", str(tmp_path / "none.fmu")],
                       capture_output=True, text=True, timeout=120, env={**os.environ})
    assert r.returncode == 1 and r.stderr.startswith("fmusa inspect: FMU not found")
    assert "Traceback" not in r.stderr


def test_a_stray_warning_is_one_line_without_a_source_path(capsys, monkeypatch):
    """A library's warning while a command runs (a SALib or numpy RuntimeWarning) reads as one line naming the
    library, not a source path and line number."""
    import warnings

    import fmusa.cli as cli

    def warn(args):
        warnings.warn_explicit("invalid value encountered in divide", RuntimeWarning,
                               "/some/venv/lib/python3.11/site-packages/SALib/analyze/morris.py", 345)
        return 0
    parser = cli.build_parser("inspect")
    parser._subparsers._group_actions[0].choices["inspect"].set_defaults(func=warn)
    monkeypatch.setattr(cli, "build_parser", lambda command=None: parser)
    assert cli.main(["inspect", "x.fmu"]) == 0
    err = capsys.readouterr().err
    assert err.strip() == ("fmusa inspect: warning: invalid value encountered in divide (RuntimeWarning from "
                           "SALib)"), err
    assert "site-packages" not in err and "morris.py" not in err
