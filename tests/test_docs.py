"""Every example in the README and the docs pages runs, so a change that breaks one fails CI.

The fenced blocks of README.md and docs/*.md are read in page order and run as a user would, from the
repository root with the built FMU:

- ``sh``: each command line (``\\`` continuations joined, comments kept) runs in bash;
- ``python``: the block runs as a script in a fresh interpreter;
- ``console``: each ``$ command`` runs and its output must be the lines shown under it (timings such as
  ``0.91 s`` and the temporary folder are normalised);
- ``yaml`` after ``<!-- docs-test: file PATH -->`` is written to PATH (a later block uses it); any other
  yaml block must parse;
- ``text`` after ``<!-- docs-test: output-of-previous -->`` must be what the previous python block printed;
- a block after ``<!-- docs-test: make -->`` lists make targets: each is checked with ``make -n``, since
  ``make test`` inside the tests (or ``make sweep``, which the same ``fmusa sweep`` line shows) would run
  twice what CI runs anyway;
- a block after ``<!-- docs-test: skip REASON -->`` cannot run here (another host, a batch system, wine):
  its syntax is checked, and the list of such blocks is pinned in ``SKIPPED`` so a new one is a visible edit.

Every ``out/`` path in a command or script is moved into a temporary folder, and ``.venv/bin/`` is the bin
folder of the interpreter running the tests. A command that appears on several pages runs once.
"""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
FMU = ROOT / "dist" / "ScrewVertebra.fmu"
BIN = Path(sys.executable).parent
PAGES = [ROOT / "README.md"] + sorted((ROOT / "docs").glob("*.md")) + sorted((ROOT / "docs" / "_partials").glob("*.md"))

#: (page, first line of the block) of every block that is not run, with the reason given on the page.
SKIPPED = {
    ("getting-started.md", ".venv/bin/fmusa sweep studies/six_dof.yaml --out out/six_dof --scheduler tcp://127.0.0.1:8786"),
    ("clusters.md", ".venv/bin/dask scheduler --port 8786                                     # on host1"),
    ("clusters.md", "# cluster.py: python cluster.py, then fmusa sweep ... --scheduler <the address it prints>"),
    ("other-tools.md", "unzip -o dist/ScrewVertebra.fmu -d out/sv"),
    ("diagnosing-own-model.md", ".venv/bin/fmusa diagnose my_study.yaml --out out/my_diagnosis"),
}

DIRECTIVE = re.compile(r"<!--\s*docs-test:\s*(\S+)\s*(.*?)\s*-->")
TIMING = re.compile(r"\b\d+(?:\.\d+)? s\b")


@dataclass
class Block:
    page: str
    line: int
    lang: str
    text: str
    directive: str = ""
    arg: str = ""

    @property
    def where(self) -> str:
        return f"{self.page}:{self.line}"


def blocks(path: Path) -> list[Block]:
    """The fenced blocks of a page, each with the docs-test directive on the line before it."""
    lines = path.read_text(encoding="utf-8").splitlines()
    out: list[Block] = []
    i = 0
    while i < len(lines):
        m = re.match(r"^```(\w*)\s*$", lines[i])
        if not m:
            i += 1
            continue
        start = i
        j = i + 1
        while j < len(lines) and lines[j] != "```":
            j += 1
        prev = next((lines[k] for k in range(start - 1, -1, -1) if lines[k].strip()), "")
        d = DIRECTIVE.search(prev)
        out.append(Block(path.name, start + 1, m.group(1), "\n".join(lines[start + 1:j]),
                         d.group(1) if d else "", d.group(2) if d else ""))
        i = j + 1
    return out


def commands(text: str) -> list[str]:
    """Shell command lines of a block, continuation lines joined; comment-only lines dropped."""
    out, cur = [], ""
    for line in text.splitlines():
        if cur:
            cur += " " + line.strip()
        elif line.strip() and not line.lstrip().startswith("#"):
            cur = line.strip()
        if cur.endswith("\\"):
            cur = cur[:-1].rstrip()
            continue
        if cur:
            out.append(re.sub(r"\s{2,}#\s.*$", "", cur))    # a trailing comment (two spaces, then #)
        cur = ""
    return out


class Runner:
    """Runs the blocks of the pages in one temporary folder (shared: a page may use another's output)."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.done: dict[str, str] = {}
        self.env = {**os.environ, "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}", "MPLBACKEND": "Agg",
                    "COLUMNS": "120", "PYTHONIOENCODING": "utf-8"}
        self.env.pop("FMUSA_FMU", None)

    def localise(self, text: str) -> str:
        text = re.sub(r"(?<![\w./-])out/", (self.tmp / "out").as_posix() + "/", text)
        return text.replace(".venv/bin/", BIN.as_posix() + "/")

    def normalise(self, text: str) -> str:
        text = text.replace(self.tmp.as_posix() + "/", "").replace(ROOT.as_posix() + "/", "")
        return "\n".join(TIMING.sub("N s", ln.rstrip()) for ln in text.strip("\n").splitlines())

    def shell(self, cmd: str, where: str, check: bool = True) -> subprocess.CompletedProcess:
        # make (make test above all) never runs from here: it would run the suite inside the suite
        assert not re.match(r"(\S*/)?make\b", cmd), f"{where}: `{cmd}` belongs in a <!-- docs-test: make --> block"
        if cmd in self.done and check:
            return subprocess.CompletedProcess(cmd, 0, self.done[cmd], "")
        t0 = time.perf_counter()
        proc = subprocess.run(["bash", "-c", self.localise(cmd)], cwd=ROOT, env=self.env, capture_output=True,
                              text=True, encoding="utf-8", timeout=600, stdin=subprocess.DEVNULL)
        print(f"{where}: $ {cmd}  [{time.perf_counter() - t0:.1f} s]", flush=True)
        if check:
            assert proc.returncode == 0, f"{where}: `{cmd}` exited with {proc.returncode}:\n{proc.stdout}\n{proc.stderr}"
            self.done[cmd] = proc.stdout
        return proc

    def python(self, code: str, where: str) -> str:
        script = self.tmp / "snippet.py"
        script.write_text(self.localise(code), encoding="utf-8")
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, str(script)], cwd=ROOT, env=self.env, capture_output=True, text=True,
                              encoding="utf-8", timeout=600, stdin=subprocess.DEVNULL)
        print(f"{where}: python block  [{time.perf_counter() - t0:.1f} s]", flush=True)
        assert proc.returncode == 0, f"{where}: the Python block failed:\n{proc.stdout}\n{proc.stderr}"
        return proc.stdout

    def console(self, text: str, where: str) -> None:
        parts = re.split(r"^\$ ", text, flags=re.M)
        for part in parts[1:]:
            cmd, _, expected = part.partition("\n")
            cmd = cmd.split("    #")[0].strip()
            proc = self.shell(cmd, where, check=False)
            got = self.normalise(proc.stdout + proc.stderr)
            assert got == self.normalise(expected), (
                f"{where}: `{cmd}` printed\n{got}\n\ninstead of what the page shows:\n{self.normalise(expected)}")

    def make(self, text: str, where: str) -> None:
        for cmd in commands(text):
            target = re.match(r"make (\S+)", cmd)
            assert target, f"{where}: a make block holds `{cmd}`, which is not `make TARGET`"
            print(f"{where}: make -n {target.group(1)}", flush=True)
            proc = subprocess.run(["make", "-n", target.group(1)], cwd=ROOT, capture_output=True, text=True,
                                  stdin=subprocess.DEVNULL, timeout=120)
            assert proc.returncode == 0, f"{where}: `make -n {target.group(1)}` fails: {proc.stderr}"

    def run(self, b: Block, last_output: str) -> str:
        if b.directive == "skip":
            assert b.arg, f"{b.where}: a skipped block needs its reason: <!-- docs-test: skip REASON -->"
            if b.lang == "python":
                compile(b.text, b.where, "exec")
            elif b.lang in ("sh", "bash"):
                subprocess.run(["bash", "-n"], input=b.text, text=True, check=True)
            return last_output
        if b.directive == "make":
            self.make(b.text, b.where)
        elif b.directive == "file":
            target = self.tmp / b.arg if b.arg.startswith("out/") else None
            assert target is not None, f"{b.where}: docs-test file paths start with out/"
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(b.text + "\n", encoding="utf-8")
        elif b.directive == "output-of-previous":
            assert self.normalise(last_output) == self.normalise(b.text), (
                f"{b.where}: the previous Python block printed\n{last_output}\ninstead of\n{b.text}")
        elif b.directive:
            raise AssertionError(f"{b.where}: unknown docs-test directive {b.directive!r}")
        elif b.lang in ("sh", "bash"):
            for cmd in commands(b.text):
                self.shell(cmd, b.where)
        elif b.lang == "python":
            return self.python(b.text, b.where)
        elif b.lang == "console":
            self.console(b.text, b.where)
        elif b.lang == "yaml" and "--8<--" not in b.text:
            yaml.safe_load(b.text)
        return last_output


@pytest.fixture(scope="module")
def runner(tmp_path_factory: pytest.TempPathFactory) -> Runner:
    if not FMU.is_file():
        pytest.skip(f"{FMU.relative_to(ROOT)} is not built: run `make fmu` first")
    if shutil.which("bash") is None or shutil.which("make") is None:
        pytest.skip("the examples are shell commands: bash and make are needed")
    return Runner(tmp_path_factory.mktemp("docs-examples"))


def test_every_example_block_is_known() -> None:
    """Each block is run, or is one of the pinned skips; and every pinned skip still exists."""
    seen = set()
    for page in PAGES:
        for b in blocks(page):
            if b.directive == "skip":
                first = b.text.splitlines()[0] if b.text else "<none>"
                seen.add((b.page, first))
                assert (b.page, first) in SKIPPED, f"{b.where}: a new skipped block; run it, or add it to SKIPPED"
            assert b.lang or b.directive, f"{b.where}: a fenced block without a language"
    assert seen == SKIPPED, f"pinned skips no longer on the pages: {sorted(SKIPPED - seen)}"


#: Pages whose examples run only with --run-slow (`make slow`), to keep `make test` under 15 minutes: the
#: clusters page starts Dask clusters and sweeps the paper study three times (about 28 s).
SLOW_PAGES = {"clusters.md"}


@pytest.mark.parametrize("page", [pytest.param(p.name, marks=pytest.mark.slow) if p.name in SLOW_PAGES else p.name
                                  for p in PAGES])
def test_examples_of_page_run(runner: Runner, page: str) -> None:
    path = next(p for p in PAGES if p.name == page)
    last = ""
    for b in blocks(path):
        last = runner.run(b, last)


def test_readme_is_a_landing_page() -> None:
    """The README stays short, cites the paper, and links to pages that exist."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 150
    assert "Kramer & Bauer" in text and "Preprints 2022" in text
    for link in re.findall(r"\]\(([^)#]+)(?:#[^)]*)?\)", text):
        if not link.startswith("http"):
            assert (ROOT / link).exists(), f"README.md links to {link}, which does not exist"


def test_generated_reference_agrees_with_the_code() -> None:
    """The study-key page and the loader agree, every error class has its fix, the model page has every
    variable (the same code the docs build runs, without building the site)."""
    sys.path.insert(0, str(ROOT / "docs" / "_gen"))
    try:
        import errors_page
        import model_page
        import study_keys
    finally:
        sys.path.pop(0)
    keys = study_keys.render()
    for section, cls, excluded, _ in study_keys.SECTIONS:
        for f in study_keys.keys_of(cls, excluded):
            assert f"| `{f.name}` |" in keys
    errors = errors_page.render()
    from fmusa.errors import FmusaError
    for cls in errors_page.error_classes():
        assert issubclass(cls, FmusaError) and f"### `{cls.__name__}`" in errors
    model = model_page.render()
    for row in model_page.variable_rows():
        assert f"| `{row.name}` | {row.vr} |" in model
