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
    ("other-tools.md", "from fmpy import extract"),
    ("diagnosing-own-model.md", ".venv/bin/fmusa diagnose my_study.yaml --out out/my_diagnosis"),
    ("element-fmu.md", "from pathlib import Path"),
    ("element-fmu.md", "from fmusa.cosim.ssp import write_ssp"),
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



def _gen_module(name: str):
    """A docs/_gen module loaded from its file: tests/ has a module of the same name (reference.py), and a
    plain import would return whichever sys.modules holds first."""
    import importlib.util
    sys.path.insert(0, str(ROOT / "docs" / "_gen"))
    try:
        spec = importlib.util.spec_from_file_location(f"_docs_gen_{name}", ROOT / "docs" / "_gen" / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.pop(0)

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


# ---------------------------------------------------------------------- the pages as a user's manual

#: every page a user reads: the README, the hand-written pages, their partials and the committed generated ones
MANUAL = PAGES + sorted((ROOT / "docs" / "reference").glob("*.md"))
#: development history, which belongs in CHANGELOG.md and the git log, not in the manual
HISTORY = re.compile(r"(?i)\bissues? #?\d+|\bthis branch\b|\bon the branch\b|\bbranch `|docs/notes|\bnotes?/"
                     r"|folded notes|\bhelpers?'s? notes|\bmeasured on this\b|\bbusy machine\b|\bshared machine\b")
#: a timing stated as measured ("about 35 s", "took 3 min"): it must be a key of `make bench` instead
MEASURED_TIME = re.compile(r"(?i)\b(?:about|approximately|roughly|takes?|took|~)\s*~?\d[\d.,–-]*\s?"
                           r"(?:s|ms|µs|min|minutes|hours?)\b")


def _prose(text: str) -> str:
    """A page without its fenced blocks and inline code (commands and messages are checked by running them)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def test_no_page_holds_development_history() -> None:
    """The manual says what fmusa does; no page names an issue, a branch or a development note, and the
    folder of notes is gone. The checker is checked too (a test that cannot fail is a defect)."""
    assert not (ROOT / "docs" / "notes").exists(), "docs/notes/ is development history: CHANGELOG.md and git log"
    for bad in ("as issue 22 asked", "numbers measured on this branch", "see docs/notes/x.md", "<!-- folded notes"):
        assert HISTORY.search(bad), bad
    for page in MANUAL:
        for n, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
            m = HISTORY.search(line)
            assert not m, f"{page.relative_to(ROOT)}:{n}: {m.group(0)!r} is development history: {line.strip()}"


def test_no_page_states_a_timing_that_no_run_wrote() -> None:
    """Wall times depend on the machine: a page names the `make bench` key that measures one (the
    Benchmarks page lists the last measurement and its machine), never "about 35 s"."""
    for bad in ("about 35 s for this file", "it takes about 13 minutes", "took 3 min"):
        assert MEASURED_TIME.search(bad), bad
    for page in MANUAL:
        for n, line in enumerate(_prose(page.read_text(encoding="utf-8")).splitlines(), 1):
            m = MEASURED_TIME.search(line)
            assert not m, f"{page.relative_to(ROOT)}: {m.group(0)!r}: name the `make bench` key instead: {line.strip()}"


def test_generated_pages_are_current() -> None:
    """The committed reference pages and the identifiability table equal what the code and the tests give
    now (so the README's links show current pages on the repository page)."""
    reference = _gen_module("reference")
    assert not reference.stale(), f"stale generated pages {reference.stale()}: run `{reference.REWRITE}`"
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    for page in reference.PAGES:
        assert page in readme, f"README.md does not link {page}"


def test_pages_state_the_fmi_versions_fmusa_runs() -> None:
    """No page or help text contradicts the FMI versions fmusa runs (fmusa.fmi.info.SUPPORTED_FMI_VERSIONS),
    and those are what the reader does: an FMI 3.0 export is read, an FMI 1.0 one refused."""
    from fmusa.cli import build_parser
    from fmusa.fmi.info import SUPPORTED_FMI_VERSIONS, FMUError, read_fmu_info

    supported = set(SUPPORTED_FMI_VERSIONS)
    texts = {p.relative_to(ROOT).as_posix(): " ".join(p.read_text(encoding="utf-8").split()) for p in MANUAL}
    texts["fmusa --help"] = " ".join(build_parser().format_help().split())
    for where, text in texts.items():
        for m in re.finditer(r"(?i)\bonly FMI (\d\.\d)", text):
            assert {m.group(1)} == supported, f"{where}: {m.group(0)!r}, but fmusa runs FMI {supported}"
        for m in re.finditer(r"(?i)\bFMI (\d\.\d)(?: or (\d\.\d))? FMUs? (?:is|are) refused", text):
            said = {v for v in m.groups() if v}
            assert not said & supported, f"{where}: {m.group(0)!r}, but fmusa runs FMI {sorted(supported)}"
        for m in re.finditer(r"(?i)\b(?:another|any) FMI (\d\.\d)(?: or (\d\.\d))? FMU", text):
            said = {v for v in m.groups() if v}
            assert said == supported, f"{where}: {m.group(0)!r}, but fmusa runs FMI {sorted(supported)}"
    assert " or ".join(SUPPORTED_FMI_VERSIONS) in texts["fmusa --help"]
    fmi3 = Path(os.environ.get("FMUSA_SHARED_DIR") or ROOT.parent / "shared") / "vendor-fmus" / "MapleSim2024_CoupledClutches_FMI3.fmu"
    if fmi3.is_file():
        assert read_fmu_info(fmi3).fmi_version == "3.0"
    if FMU.is_file():
        fake = Path(os.environ.get("TMPDIR", "/tmp")) / f"fmusa-docs-fmi1-{os.getpid()}.fmu"
        import zipfile
        try:
            with zipfile.ZipFile(FMU) as zin, zipfile.ZipFile(fake, "w") as zout:
                for item in zin.infolist():
                    data = zin.read(item.filename)
                    if item.filename == "modelDescription.xml":
                        data = data.replace(b'fmiVersion="2.0"', b'fmiVersion="1.0"', 1)
                    zout.writestr(item, data)
            with pytest.raises(FMUError, match="FMI 1.0"):
                read_fmu_info(fake)
        finally:
            fake.unlink(missing_ok=True)


def test_help_texts_state_the_parsers_defaults() -> None:
    """Every "(default X)" in `fmusa … --help` is the option's real default, and no help text states a
    timing (which depends on the machine)."""
    from fmusa.cli import COMMANDS, build_parser

    parser = build_parser()
    subs = next(a for a in parser._actions if isinstance(a, type(parser._subparsers._group_actions[0])))
    checked = 0
    for name in COMMANDS:
        for action in subs.choices[name]._actions:
            text = action.help or ""
            assert not MEASURED_TIME.search(text) and "minutes" not in text, f"fmusa {name} {action.dest}: {text}"
            m = re.search(r"\(default:? ([^,;)]+)", text)
            if m and re.fullmatch(r"-?\d+(?:\.\d+)?(?:e-?\d+)?", m.group(1).strip()):
                assert float(m.group(1)) == float(action.default), f"fmusa {name} {action.dest}: {text}"
                checked += 1
    assert checked >= 5


def test_readme_states_the_optimum_the_paper_study_prints() -> None:
    """The README's optimum is fmusa's, the one `make sweep` prints (the paper-study page's example, which
    test_examples_of_page_run runs and compares), and the paper's own is named as the paper's."""
    readme = " ".join((ROOT / "README.md").read_text(encoding="utf-8").split())
    page = next(b for b in blocks(ROOT / "docs" / "paper-study.md") if b.directive == "output-of-previous")
    printed = re.search(r"c = (\d+) N/m, d = ([\d.]+) N·s/m", page.text)
    assert printed, page.text
    assert f"c = {printed.group(1)} N/m, d = {printed.group(2)} N·s/m" in readme
    assert not re.search(r"reproduces the paper's search \(optimum c = 823224", readme)
    runs = re.search(r"^(\d+) FMU runs$", page.text, re.M).group(1)
    paper = " ".join((ROOT / "docs" / "paper-study.md").read_text(encoding="utf-8").split())
    clusters = " ".join((ROOT / "docs" / "clusters.md").read_text(encoding="utf-8").split())
    assert f"finds c = {printed.group(1)} N/m, d = {printed.group(2)} N·s/m in {runs} FMU runs" in paper
    assert f"c = {printed.group(1)}" in clusters and f"d = {printed.group(2)} N·s/m, {runs} runs" in clusters


def test_the_benchmarks_page_lists_a_measurement_with_its_machine(tmp_path) -> None:
    """The Benchmarks page gets out/bench/bench.json's numbers with the machine, the load and the time they
    were measured at (docs/_gen/bench_page.py, run by the docs build); without the file it says how to get one."""
    import json as _json
    sys.path.insert(0, str(ROOT / "docs" / "_gen"))
    try:
        import bench_page
    finally:
        sys.path.pop(0)
    assert "No measurement" in bench_page.render(tmp_path / "missing.json")
    data = {"fmu_run_ms_median": 0.912, "paper_study_wall_s": 0.31, "diagnose_shear_unit_wall_s": 211.0,
            "timestamp": "2026-12-02T17:00:00+00:00", "limits_note": "fmu 0.9 ms (limit 2 ms)",
            "machine": {"cpu_count": 2, "platform": "Linux-6.1", "processor": "x86_64", "python": "3.11.7",
                        "fmpy": "0.3.32", "loadavg_1min": 9.5}}
    (tmp_path / "bench.json").write_text(_json.dumps(data), encoding="utf-8")
    page = bench_page.render(tmp_path / "bench.json")
    assert "2026-12-02T17:00:00+00:00 on Linux-6.1, x86_64, 2 logical CPUs" in page and "load average 9.50" in page
    assert "| `diagnose_shear_unit_wall_s` | 211 |" in page and "| `fmu_run_ms_median` | 0.912 |" in page
    for page_file in MANUAL:        # every bench key a page names is one `make bench` writes
        for key in re.findall(r"`((?:fmu|paper|sobol|six_dof|diagnose|pipeline|bench)_[a-z0-9_]+)`",
                              page_file.read_text(encoding="utf-8")):
            if key.endswith(("_s", "_ms", "_per_s", "_median")) or key.startswith("bench_"):
                src = (ROOT / "src" / "fmusa" / "bench.py").read_text(encoding="utf-8")
                assert key in src or key.removeprefix("bench_") in src, f"{page_file.name}: `{key}` is no bench key"


def test_the_key_pages_fail_when_docs_fields_and_loader_part() -> None:
    """The check both key pages run (study_keys.check_section) fails on each kind of drift: an undocumented
    field, a docstring entry without a field, a loader that allows other keys (a check that cannot fail
    would let the pages drift silently)."""
    import dataclasses
    study_keys = _gen_module("study_keys")

    @dataclasses.dataclass
    class Documented:
        """A section.

        :param a: the first key.
        :param b: the second key.
        """
        a: int = 1
        b: int = 2

    study_keys.check_section(Documented, frozenset(), "s", ["a", "b"], "Documented", "SECTIONS")
    with pytest.raises(study_keys.DocsDriftError, match="allows"):
        study_keys.check_section(Documented, frozenset(), "s", ["a", "b", "c"], "Documented", "SECTIONS")
    with pytest.raises(study_keys.DocsDriftError, match="are not fields"):
        study_keys.check_section(Documented, frozenset({"b"}), "s", ["a"], "Documented", "SECTIONS")

    @dataclasses.dataclass
    class Undocumented:
        """A section.

        :param a: the first key.
        """
        a: int = 1
        b: int = 2

    with pytest.raises(study_keys.DocsDriftError, match="b have no"):
        study_keys.check_section(Undocumented, frozenset(), "s", ["a", "b"], "Undocumented", "SECTIONS")
