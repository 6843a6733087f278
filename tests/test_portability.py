"""fmusa where its users work (issue 19): the pool under every start method, a Windows-like Python (no fork,
no register_at_fork, no fcntl, spawn by default), a console and locale that cannot encode what FMUs say,
portable locks and process checks, crash codes of every platform.

The Windows simulation is a ``sitecustomize`` on ``PYTHONPATH`` in a fresh interpreter (and so in every
worker it spawns); the locale test runs the ``fmusa`` command under ``LC_ALL=C PYTHONUTF8=0`` with a C FMU
(tests/fmus/leaky) whose error messages hold Ü, ≥, · and Δ.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from c_fmus import build_leaky  # noqa: E402

from fmusa.errors import UsageError  # noqa: E402
from fmusa.runs.pool import WINDOWS_CRASHES, exit_reason, resolve_start_method  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "studies" / "paper.yaml"
SRC = ROOT / "src"

WINDOWS_LIKE = '''\
"""A Windows-like Python on Linux (tests/test_portability.py): no fork, no register_at_fork, no fcntl;
spawn is the only start method and the default."""
import os
import sys

for _name in ("fork", "forkpty", "register_at_fork"):
    if hasattr(os, _name):
        delattr(os, _name)
sys.modules["fcntl"] = None          # `import fcntl` raises ImportError, as on Windows

# msvcrt.locking as Windows has it (a region lock; EACCES, a PermissionError, when another process holds
# it), made of POSIX record locks; after subprocess, which takes an importable msvcrt for Windows
import subprocess  # noqa: F401
import types as _types

_msvcrt = _types.ModuleType("msvcrt")
_msvcrt.LK_UNLCK, _msvcrt.LK_LOCK, _msvcrt.LK_NBLCK = 0, 1, 2


def _locking(fd, mode, nbytes):
    try:
        os.lockf(fd, os.F_ULOCK if mode == 0 else os.F_TLOCK, nbytes)
    except OSError as exc:
        raise PermissionError(13, "Permission denied") from exc


_msvcrt.locking = _locking
sys.modules["msvcrt"] = _msvcrt

import multiprocessing
import multiprocessing.context as _ctx

multiprocessing.set_start_method("spawn", force=True)
for _name in ("fork", "forkserver"):        # get_context("fork") raises ValueError, as on Windows
    _ctx._concrete_contexts.pop(_name, None)
_ctx.DefaultContext.get_all_start_methods = lambda self: ["spawn"]
multiprocessing.get_all_start_methods = lambda: ["spawn"]
'''

#: run inside the simulated interpreter: a study in this process, the same through the pool, both resumed
SIMULATED_STUDY = '''\
import json, os, sys
from pathlib import Path
assert not hasattr(os, "fork") and not hasattr(os, "register_at_fork"), "the simulation did not load"
try:
    import fcntl  # noqa: F401
    raise SystemExit("fcntl is importable: the simulation did not load")
except ImportError:
    pass
import fmusa
from fmusa.study.loader import parse_study
from fmusa.api import run_study
from fmusa.runs.pool import resolve_start_method

text, fmu, out = sys.argv[1], sys.argv[2], Path(sys.argv[3])
res = {"start_method": resolve_start_method()}
for kind in ("in_process", "pool"):
    t = text if kind == "in_process" else text.replace("fmu: default", f"fmu: {fmu}", 1)
    study = parse_study(t, out / f"{kind}.yaml")
    first = run_study(study, out / kind, workers=2, figures=False, progress=False)
    again = run_study(study, out / kind, workers=2, resume=True, figures=False, progress=False)
    res[kind] = {"simulated": first.summary["simulated_this_session"],
                 "resumed_simulated": again.summary["simulated_this_session"], "runs": len(again.runs)}
print("@@" + json.dumps(res))
'''


def _env(**extra: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("FMUSA_START_METHOD", "PYTHONPATH")}
    env.update(extra)
    return env


def _small_paper_text() -> str:
    """studies/paper.yaml with a 3 x 3 grid and nothing after it (seconds, not minutes)."""
    text = PAPER.read_text(encoding="utf-8")
    start, end = text.index("stages:"), text.index("execution:")
    return text[:start] + "stages:\n  grid:\n    base: 25\n    exponents: {c: [3, 5], d: [2, 4]}\n\n" \
        + text[end:]


# ---------------------------------------------------------------------------------------- start methods
def test_start_method_comes_from_the_study_then_the_environment_then_the_platform(monkeypatch):
    import multiprocessing as mp
    monkeypatch.delenv("FMUSA_START_METHOD", raising=False)
    default = resolve_start_method()
    assert default in mp.get_all_start_methods()
    assert resolve_start_method("spawn") == "spawn"
    monkeypatch.setenv("FMUSA_START_METHOD", "spawn")
    assert resolve_start_method() == "spawn"
    monkeypatch.setenv("FMUSA_START_METHOD", "vfork")
    with pytest.raises(UsageError, match=r"\$FMUSA_START_METHOD = 'vfork' is not a start method; use one of "
                                         r"spawn, forkserver, fork"):
        resolve_start_method()
    with pytest.raises(UsageError, match=r"execution.start_method = 'thread'"):
        resolve_start_method("thread")


def test_study_file_takes_a_start_method_and_refuses_a_wrong_one(tmp_path):
    from fmusa.study.loader import parse_study
    from fmusa.study.schema import StudyError
    text = _small_paper_text()
    good = text.replace("  timeout_s: 60", "  timeout_s: 60\n  start_method: spawn\n  worker_max_runs: 50\n"
                                           "  worker_max_memory_mb: 800\n  retries: 0")
    ex = parse_study(good, tmp_path / "s.yaml").execution
    assert (ex.start_method, ex.worker_max_runs, ex.worker_max_memory_mb, ex.retries) == ("spawn", 50, 800.0, 0)
    assert ex.pool_options().start_method == "spawn"
    with pytest.raises(StudyError, match=r"unknown start method 'spwan'.*spawn"):
        parse_study(text.replace("  timeout_s: 60", "  timeout_s: 60\n  start_method: spwan"), tmp_path / "s.yaml")


def test_exit_codes_of_every_platform_are_named():
    assert exit_reason(-11) == "the FMU crashed the worker process (SIGSEGV, signal 11)"
    assert "out-of-memory" in exit_reason(-9)
    # Windows reports an access violation as the exit code 3221225477 (0xC0000005), not as a signal
    assert exit_reason(3221225477) == ("the FMU crashed the worker process (access violation, exception code "
                                       "0xC0000005)")
    assert "stack overflow" in exit_reason(0xC00000FD)
    assert exit_reason(0xC0001234).startswith("the FMU crashed the worker process (exception code 0xC0001234")
    assert exit_reason(3) == "the worker process exited with code 3"
    assert all(c >= 0x80000000 for c in WINDOWS_CRASHES)


# ---------------------------------------------------------------------------------------- locks, processes
def test_a_second_study_in_the_same_folder_is_refused_naming_the_first(tmp_path):
    from fmusa.runs.store import RunStore, StoreBusyError
    a = RunStore(tmp_path / "runs.csv", ["c"], ["y"])
    try:
        code = ("import sys; from fmusa.runs.store import RunStore\n"
                "try:\n    RunStore(sys.argv[1], ['c'], ['y'])\nexcept Exception as e:\n    print(e)")
        r = subprocess.run([sys.executable, "-c", code, str(tmp_path / "runs.csv")], capture_output=True,
                           text=True, encoding="utf-8", timeout=60)
        assert f"another fmusa study (pid {os.getpid()}) is writing to this folder" in r.stdout, r.stdout + r.stderr
    finally:
        a.close()
    RunStore(tmp_path / "runs.csv", ["c"], ["y"]).close()      # released: the folder is free again
    assert StoreBusyError


def test_a_file_system_that_cannot_lock_is_named_not_blamed_on_another_study(tmp_path, monkeypatch):
    """NFS without lockd, some SMB mounts: flock fails with ENOLCK (or EOPNOTSUPP); that is not a busy folder."""
    import errno
    import fcntl
    from fmusa.runs.store import RunStore, StoreBusyError

    def refuse(fh, how):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", refuse)
    with pytest.raises(StoreBusyError) as info:
        RunStore(tmp_path / "runs.csv", ["c"], ["y"])
    msg = str(info.value)
    assert "cannot lock files (No locks available)" in msg and "another fmusa study" not in msg
    assert "local disk" in msg


def test_extraction_folders_are_claimed_and_judged_without_fcntl(tmp_path):
    """The extraction folders' owner lock in a Windows-like interpreter (msvcrt.locking): a folder claimed by
    a live process is kept, one whose owner file nobody holds is removed."""
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(WINDOWS_LIKE, encoding="utf-8")
    code = ("import os, sys; from pathlib import Path; import fmusa.fmi.archive as a; a.GRACE_S = 0\n"
            "root = Path(sys.argv[1]); live, stale = root / 'fmusa-fmu-live', root / 'fmusa-fmu-stale'\n"
            "live.mkdir(); stale.mkdir(); (stale / a.OWNER_FILE).write_text('1')\n"
            "import subprocess; c = subprocess.Popen([sys.executable, '-c', 'import sys, time; import "
            "fmusa.fmi.archive as a; a.claim_folder(sys.argv[1]); print(1, flush=True); time.sleep(60)', "
            "str(live)], stdout=subprocess.PIPE)\n"
            "c.stdout.readline(); print(sorted(p.name for p in a.remove_orphans(root)), live.exists()); c.kill()")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True,
                       encoding="utf-8", timeout=120, env=_env(PYTHONPATH=f"{site}{os.pathsep}{SRC}"))
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["['fmusa-fmu-stale']", "True"]


def test_no_fork_hook_or_fcntl_is_needed_to_import_and_lock(tmp_path):
    """The constructs that broke on Windows at import or at the first store, in a Windows-like interpreter."""
    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(WINDOWS_LIKE, encoding="utf-8")
    code = ("import os, multiprocessing as mp; assert not hasattr(os, 'register_at_fork')\n"
            "import fmusa.runs.store as s, fmusa.runs.pool as p, fmusa.cli\n"
            "st = s.RunStore(os.path.join(os.sys.argv[1], 'runs.csv'), ['c'], ['y']); st.close()\n"
            "print(p.resolve_start_method(), mp.get_all_start_methods())")
    r = subprocess.run([sys.executable, "-c", code, str(tmp_path)], capture_output=True, text=True,
                       encoding="utf-8", timeout=120, env=_env(PYTHONPATH=f"{site}{os.pathsep}{SRC}"))
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == ["spawn", "['spawn']"]


# ---------------------------------------------------------------------------------------- Windows-like
def test_a_study_runs_and_resumes_in_a_windows_like_python(tmp_path, fmu_path):
    """No fork, no register_at_fork, no fcntl, spawn only: a study in process and one through the pool of
    spawned workers (the study names its FMU, so every run is supervised), each resumed with nothing run
    again; the results equal this interpreter's (fork or the platform default) bit for bit."""
    from fmusa.study.loader import parse_study
    from fmusa.api import run_study

    site = tmp_path / "site"
    site.mkdir()
    (site / "sitecustomize.py").write_text(WINDOWS_LIKE, encoding="utf-8")
    text = _small_paper_text()
    out = tmp_path / "sim"
    out.mkdir()
    # A temporary folder of its own: its extraction folders are locked with the simulated msvcrt (POSIX
    # record locks), which another fmusa on this machine, locking with flock, cannot see.
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    r = subprocess.run([sys.executable, "-c", SIMULATED_STUDY, text, str(fmu_path), str(out)],
                       capture_output=True, text=True, encoding="utf-8", timeout=600, cwd=str(ROOT),
                       env=_env(PYTHONPATH=f"{site}{os.pathsep}{SRC}", FMUSA_FMU=str(fmu_path), TMPDIR=str(tmp),
                                TEMP=str(tmp), TMP=str(tmp)))
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    res = json.loads(r.stdout.split("@@")[-1])
    assert res["start_method"] == "spawn"
    for kind in ("in_process", "pool"):
        assert res[kind]["simulated"] == res[kind]["runs"] == 9, res
        assert res[kind]["resumed_simulated"] == 0, res
    here = run_study(parse_study(text, tmp_path / "here.yaml"), tmp_path / "here", figures=False,
                     progress=False).runs
    cols = ["c", "d", "max_y", "mean_y", "max_v", "mean_v", "t_eq", "feasible", "status"]
    ref = here.sort_values(["c", "d"]).reset_index(drop=True)[cols]
    for kind in ("in_process", "pool"):
        got = pd.read_csv(out / kind / "runs.csv", encoding="utf-8").sort_values(["c", "d"]).reset_index(drop=True)
        pd.testing.assert_frame_equal(ref, got[cols], check_exact=True, check_dtype=False)


# ---------------------------------------------------------------------------------------- a C locale
LEAKY_STUDY = """\
name: leaky_words
fmu: {fmu}
parameters:
  k: {{variable: k, unit: N/m}}
fixed:
  F: 411.0
  fail_lo: 2.5e6
  fail_hi: 5.5e6
scenario:
  stop_time: 1
  step: 0.5
metrics:
  y_max: {{output: y_peak, reduce: final, unit: m}}
stages:
  grid:
    values:
      k: [1.0e6, 3.0e6, 5.0e6, 1.0e7]
execution:
  workers: 2
  timeout_s: 30
"""


def test_sweep_resume_and_diagnose_under_a_c_locale(tmp_path, fmu_path):
    """LC_ALL=C, PYTHONUTF8=0: Python's default encoding is ASCII. The FMU's messages (Ü, ≥, ·, Δ) reach
    runs.csv as UTF-8, --resume reads them back, diagnose writes its report with its Δ, and the console
    gets escapes instead of a UnicodeEncodeError."""
    fmu = build_leaky(tmp_path / "leaky")
    study = tmp_path / "leaky.yaml"
    study.write_text(LEAKY_STUDY.format(fmu=fmu), encoding="utf-8")
    env = _env(LC_ALL="C", LANG="C", PYTHONUTF8="0", PYTHONIOENCODING="", PYTHONPATH=str(SRC))
    env.pop("PYTHONIOENCODING")
    probe = subprocess.run([sys.executable, "-c", "import locale; print(locale.getpreferredencoding(False))"],
                           capture_output=True, text=True, env=env)
    if "utf" in probe.stdout.lower():
        pytest.skip(f"this Python coerces the C locale to UTF-8 ({probe.stdout.strip()}); nothing to test")

    def fmusa(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "fmusa.cli", *args], capture_output=True, cwd=str(tmp_path),
                              env=env, timeout=600)

    out = tmp_path / "out"
    r = fmusa("sweep", str(study), "--out", str(out), "--no-figures", "--quiet")
    assert r.returncode == 0, r.stderr.decode("utf-8", "replace")
    runs = pd.read_csv(out / "runs.csv", encoding="utf-8", keep_default_na=False)
    failed = runs[runs["status"] == "failed"]
    assert sorted(failed["k"]) == [3e6, 5e6]
    assert all("Überlast bei k = " in m and "F ≥ k·Δy" in m for m in failed["message"]), failed["message"].tolist()
    ok = runs[runs["status"] == "ok"].set_index("k")
    np.testing.assert_allclose(ok.loc[[1e6, 1e7], "y_max"].to_numpy(float), 411.0 / np.array([1e6, 1e7]), rtol=1e-12)
    before = (out / "runs.csv").read_bytes()

    r = fmusa("sweep", str(study), "--out", str(out), "--no-figures", "--quiet", "--resume")
    assert r.returncode == 0, r.stderr.decode("utf-8", "replace")
    assert b"0 simulated now" in r.stdout, r.stdout
    assert (out / "runs.csv").read_bytes() == before

    # diagnose: a tiny measured test (the model itself at a known stiffness), one candidate, one start
    t = np.linspace(0.0, 2.0, 60)
    d = 1e-3 * np.minimum(t, 1.0)
    force = 8e5 * d + 500.0 * np.gradient(d, t)
    csv = tmp_path / "meßreihe.csv"
    pd.DataFrame({"time": t, "displacement": d, "force": force}).to_csv(csv, index=False, encoding="utf-8")
    dout = tmp_path / "diag"
    t0 = time.monotonic()
    r = fmusa("diagnose", str(csv), "--drive", "displacement", "--out", str(dout), "--fmu", str(fmu_path),
              "--candidates", "sensor_offset", "--starts", "1", "--max-points", "30", "--workers", "1")
    assert r.returncode == 0, r.stderr.decode("utf-8", "replace")
    report = (dout / "report.md").read_text(encoding="utf-8")
    assert len(report) > 200 and "meßreihe" in report, report[:500]
    assert time.monotonic() - t0 < 300


def test_the_cli_prints_what_an_ascii_console_cannot_encode_as_escapes():
    """A result line with Δ, ≥ and Ü on a console in ASCII (LC_ALL=C, where stdout's error handler is
    strict about such characters): printed with escapes, exit code 0, no UnicodeEncodeError."""
    env = _env(LC_ALL="C", LANG="C", PYTHONUTF8="0", PYTHONPATH=str(SRC))
    env.pop("PYTHONIOENCODING", None)
    code = ("import sys\nimport fmusa.cli as c\n"
            "def said(args):\n    print('\\u0394k \\u2265 0 for \\u00dcberlast')\n    return 0\n"
            "c.cmd_sweep = said\n"
            "sys.exit(c.main(['sweep', 'x.yaml', '--out', 'o']))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, env=env, timeout=120)
    assert r.returncode == 0, r.stderr.decode("utf-8", "replace")
    assert r.stdout.decode("ascii").strip() == r"\u0394k \u2265 0 for \xdcberlast"
