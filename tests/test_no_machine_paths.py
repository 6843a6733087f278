"""No file of the repository names a path that exists on one machine only.

A path such as the shared folder on the machine the project was developed on means nothing to a user
(the README used to send readers to one). Tests find the shared folder as the repository's parent's
``shared/``; documentation cites the paper instead of a folder holding it.
"""
from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Written in pieces so that this file does not match itself.
_ROOTS = ["work", "root", "home", "tmp", "Users", "mnt", "scratch"]
MACHINE_PATH = re.compile(r"(?<![\w.~-])/(?:" + "|".join(_ROOTS) + r")/[\w.$-]|\b[A-Z]:\\\\?(?:Users|Documents and Settings)\\\\?")
BINARY_SUFFIXES = {".png", ".jpg", ".fmu", ".so", ".dll", ".zip", ".gz", ".pdf"}


def tracked_files() -> list[Path]:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout (or no git): the tracked files cannot be listed")
    out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    return [ROOT / p for p in out.decode("utf-8").split("\0") if p]


def test_no_machine_path_in_tracked_files() -> None:
    hits = []
    for path in tracked_files():
        if path.suffix.lower() in BINARY_SUFFIXES or not path.is_file():
            continue
        data = path.read_bytes()
        if b"\0" in data[:4096]:
            continue
        for n, line in enumerate(data.decode("utf-8", errors="replace").splitlines(), start=1):
            if MACHINE_PATH.search(line):
                hits.append(f"{path.relative_to(ROOT).as_posix()}:{n}: {line.strip()[:120]}")
    assert not hits, ("paths on one machine in the repository (use a relative path, the repository's parent's "
                      "shared/, or cite the source):\n" + "\n".join(hits))


@pytest.mark.parametrize("line, bad", [
    ("see /" + "work/shared/paper/ for the paper", True),    # in pieces, so that this file passes itself
    ("cd /" + "root/x", True),
    ("C:" + "\\Users\\me\\fmusa", True),
    ("out/paper/runs.csv and docs/notes/", False),
    ("https://example.org/home/page", False),
    ("--remote-python /path/to/fmusa/.venv/bin/python", False),
])
def test_the_pattern(line: str, bad: bool) -> None:
    """The check finds what it is for (a test that cannot fail is no test) and spares relative paths."""
    assert bool(MACHINE_PATH.search(line)) is bad


#: a test that builds the shared folder's path from the repository's location
SHARED_PATH = re.compile(r"""(?:parents\[\d\]|parent|ROOT\.parent)\s*/\s*["']shared["']""")


def shared_path_problems(text: str) -> list[int]:
    """Lines that build ``../shared`` without ``$FMUSA_SHARED_DIR`` beside them (CI, or a git worktree
    elsewhere, lays the shared folder where the environment variable says)."""
    return [n for n, line in enumerate(text.splitlines(), 1)
            if SHARED_PATH.search(line) and "FMUSA_SHARED_DIR" not in line]


def test_tests_find_the_shared_folder_through_the_environment() -> None:
    hits = []
    for path in (ROOT / "tests").rglob("*.py"):
        text = path.read_text(encoding="utf-8")
        hits += [f"{path.relative_to(ROOT).as_posix()}:{n}" for n in shared_path_problems(text)]
    assert not hits, ("tests that ignore $FMUSA_SHARED_DIR (write "
                      "`Path(os.environ.get(\"FMUSA_SHARED_DIR\") or ROOT.parent / \"shared\")`):\n" + "\n".join(hits))


def test_the_shared_path_pattern() -> None:
    # in pieces, so that this file passes itself
    assert shared_path_problems('OM = ROOT.parent / "' + 'shared" / "vendor-fmus"') == [1]
    assert shared_path_problems("x = Path(__file__).resolve().parents[2] / '" + "shared'") == [1]
    assert shared_path_problems('S = Path(os.environ.get("FMUSA_SHARED_DIR") or ROOT.parent / "shared")') == []
