"""Issue 18, row 3: a full disk. One line naming the file and the free space, a non-zero exit, every file
written before intact and valid (no half-written summary.json or figure, no temporary file left), and
``--resume`` after space was freed completes with the same runs as a study that never ran out.

On a small tmpfs when this process may mount one (root on Linux, as here and in CI); else skipped, and the
same faults are injected as an ENOSPC from the writer (not a mock of the FMU or fmpy).
"""
from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from fmusa.api import parse_study, run_study
from fmusa.files import DiskFullError, atomic_write

STUDY = """\
name: disk
fmu: default
parameters:
  c: {variable: c_y, unit: N/m}
  d: {variable: d_y, unit: N.s/m}
fixed: {F_max: 411, t_ramp: 10}
scenario: {stop_time: 2.0}
metrics:
  max_y: {output: y_max, unit: m}
  max_v: {output: v_y_max, unit: m/s}
constraints:
  - {name: translation, metric: max_y, max: 5.0e-4}
stages:
  grid: {values: {c: [%s], d: [200, 400, 800]}}
"""


def _study_text(n_c: int) -> str:
    return STUDY % ", ".join(f"{4e5 * 1.01 ** i:.6g}" for i in range(n_c))


def _cli(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "fmusa.cli", *args], capture_output=True, text=True,
                          timeout=timeout)


@pytest.fixture
def tmpfs(tmp_path):
    """A 16 kB tmpfs (resized with ``resize(kb)``), or a skip when it cannot be mounted."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    if not sys.platform.startswith("linux") or shutil.which("mount") is None:
        pytest.skip("needs Linux mount for a small tmpfs (the injected-ENOSPC tests cover the rest)")
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=16k", "tmpfs", str(mnt)], capture_output=True,
                          text=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({proc.stderr.strip() or proc.returncode}); the "
                    f"injected-ENOSPC tests cover the rest")

    def resize(kb: int) -> None:
        subprocess.run(["mount", "-o", f"remount,size={kb}k", str(mnt)], check=True)

    try:
        yield mnt, resize
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def _runs(path: Path) -> pd.DataFrame:
    return pd.read_csv(path).drop(columns=["seconds"]).sort_values(["c", "d"]).reset_index(drop=True)


def _valid_outputs(out: Path) -> None:
    """Every file fmusa left is whole: JSON parses, PNGs end with IEND, no temporary file."""
    assert not [p.name for p in out.rglob("*") if ".tmp-" in p.name]
    for p in out.rglob("*.json"):
        json.loads(p.read_text(encoding="utf-8"))
    for p in out.rglob("*.png"):
        assert p.read_bytes()[-8:-4] == b"IEND", p


def _one_line(proc: subprocess.CompletedProcess, file: str) -> str:
    err = proc.stderr.strip()
    assert proc.returncode == 1, (proc.returncode, err)
    assert len(err.splitlines()) == 1 and "Traceback" not in err, err
    assert f"{file}: cannot be written: the disk is full (" in err and " free on its file system)" in err, err
    assert "free some space and rerun with --resume" in err
    return err


def test_a_full_disk_while_writing_runs_csv(tmp_path, tmpfs):
    mnt, resize = tmpfs
    study = tmp_path / "s.yaml"
    study.write_text(_study_text(100), encoding="utf-8")     # 300 runs, ~30 kB of runs.csv
    proc = _cli("sweep", str(study), "--out", str(mnt / "out"), "--quiet", "--no-figures")
    _one_line(proc, "runs.csv")
    _valid_outputs(mnt / "out")
    kept = (mnt / "out" / "runs.csv").read_text(encoding="utf-8")
    assert 0 < kept.count("\n") < 301
    resize(4096)          # space freed: --resume completes, with the runs a study with room makes
    proc = _cli("sweep", str(study), "--out", str(mnt / "out"), "--quiet", "--no-figures", "--resume")
    assert proc.returncode == 0, proc.stderr
    clean = tmp_path / "clean"
    run_study(parse_study(_study_text(100), study), clean, figures=False, progress=False)
    a, b = _runs(mnt / "out" / "runs.csv"), _runs(clean / "runs.csv")
    pd.testing.assert_frame_equal(a.drop(columns=["run_id"]), b.drop(columns=["run_id"]))
    sa = json.loads((mnt / "out" / "summary.json").read_text(encoding="utf-8"))
    sb = json.loads((clean / "summary.json").read_text(encoding="utf-8"))
    assert sa["grid"] == sb["grid"] and sa["runs"] == sb["runs"] == 300


def test_a_full_disk_while_writing_figures(tmp_path, tmpfs):
    mnt, resize = tmpfs
    resize(64)            # runs.csv and summary.json fit, the figures do not
    study = tmp_path / "s.yaml"
    study.write_text(_study_text(4), encoding="utf-8")
    proc = _cli("sweep", str(study), "--out", str(mnt / "out"), "--quiet")
    err = _one_line(proc, ".png")
    assert "runs.csv and summary.json in" in err and "are complete" in err
    _valid_outputs(mnt / "out")
    summary = json.loads((mnt / "out" / "summary.json").read_text(encoding="utf-8"))
    assert summary["runs"] == 12
    resize(8192)
    proc = _cli("sweep", str(study), "--out", str(mnt / "out"), "--quiet", "--resume")
    assert proc.returncode == 0, proc.stderr
    assert "(0 simulated now, 0 failed)" in proc.stdout
    assert (mnt / "out" / "report.md").exists()
    _valid_outputs(mnt / "out")


# ------------------------------------------------------------------ injected ENOSPC (any platform)
def _enospc_after(monkeypatch, module, name: str, target: str):
    """``module.name`` raising ENOSPC once a path ending with ``target`` is involved."""
    real = getattr(module, name)

    def failing(*args, **kw):
        if any(str(a).endswith(target) or f"{target}.tmp-" in str(a) for a in args):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(*args, **kw)

    monkeypatch.setattr(module, name, failing)


def test_an_injected_enospc_on_summary_json_keeps_the_earlier_file(tmp_path, monkeypatch):
    import fmusa.files as files

    study = parse_study(_study_text(2), tmp_path / "s.yaml")
    out = tmp_path / "out"
    run_study(study, out, figures=False, progress=False)
    before = (out / "summary.json").read_bytes()
    _enospc_after(monkeypatch, files, "_fsync", ".json")
    with pytest.raises(DiskFullError, match=r"summary.json: cannot be written: the disk is full \(.* free on "
                                            r"its file system\); free some space and rerun with --resume"):
        run_study(study, out, resume=True, figures=False, progress=False)
    assert (out / "summary.json").read_bytes() == before      # the earlier one, whole
    _valid_outputs(out)
    monkeypatch.undo()
    again = run_study(study, out, resume=True, figures=False, progress=False)
    assert again.summary["simulated_this_session"] == 0 and again.summary["runs"] == 6


def test_an_injected_enospc_in_an_image_writer_is_one_error(tmp_path, monkeypatch):
    """A writer (PIL under matplotlib) that raises its own error from the ENOSPC: still the disk's error."""
    def pil_like(*args, **kw):
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError as exc:
            raise RuntimeError("encoder error -2 when writing image file") from exc

    target = tmp_path / "f.png"
    atomic_write(target, b"old")
    with pytest.raises(DiskFullError, match=r"f.png: cannot be written: the disk is full"):
        from fmusa.files import atomic_path
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            pil_like()
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["f.png"]


def test_an_injected_enospc_on_runs_csv_keeps_the_rows_before(tmp_path, monkeypatch):
    from fmusa.runs import store as store_mod

    study = parse_study(_study_text(2), tmp_path / "s.yaml")
    out = tmp_path / "out"
    real = store_mod.RunStore._block

    class FullFile:
        """runs.csv on a disk that takes half of the next block, then is full."""
        def __init__(self, fh):
            self.fh, self.closed = fh, False

        def write(self, text):
            self.fh.write(text[:len(text) // 2])
            self.fh.flush()
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

        def flush(self):
            self.fh.flush()

        def close(self):
            self.fh.close()
            self.closed = True

    def block_then_full(self, sl):
        if not isinstance(self._fh, FullFile):
            self._fh = FullFile(self._fh)
        return real(self, sl)

    monkeypatch.setattr(store_mod.RunStore, "_block", block_then_full)
    with pytest.raises(DiskFullError, match=r"runs.csv: cannot be written: the disk is full \(.* free on its "
                                            r"file system\); the runs before are kept in runs.csv; free some "
                                            r"space and rerun with --resume"):
        run_study(study, out, figures=False, progress=False)
    monkeypatch.undo()
    again = run_study(study, out, resume=True, figures=False, progress=False)
    clean = run_study(study, tmp_path / "clean", figures=False, progress=False)
    a, b = _runs(out / "runs.csv"), _runs(tmp_path / "clean" / "runs.csv")
    pd.testing.assert_frame_equal(a.drop(columns=["run_id"]), b.drop(columns=["run_id"]))
    assert again.summary["grid"] == clean.summary["grid"]
