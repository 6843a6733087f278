"""The committed pages that are made from the code: written by ``make reference``, checked by the tests.

They are committed (not only made during ``make docs``) so that the README's links to them work on the
repository page. ``tests/test_docs.py`` and the docs build fail when one differs from what the code gives
now, with the command that rewrites it:

- docs/reference/study-keys.md: the study file's keys, from ``fmusa.study.schema`` (checked against the loader);
- docs/reference/model.md: the ScrewVertebra model, from fmu/MODEL.md and the Modelica source;
- docs/reference/troubleshooting.md: every FmusaError subclass, found by introspection, with its fix;
- the identifiability table in docs/diagnosing.md (between ``<!-- generated: identifiability … -->`` and
  ``<!-- end generated -->``), from tests/test_identifiability.py, the tests that check every cell.

``python docs/_gen/reference.py`` writes them; ``--check`` lists the stale ones and exits with 1.
"""
from __future__ import annotations

import re
import sys
from pathlib import Path
from typing import Callable

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
for _p in (HERE, ROOT / "tests"):
    if str(_p) not in sys.path:
        sys.path.insert(0, str(_p))

import errors_page  # noqa: E402
import model_page  # noqa: E402
import study_keys  # noqa: E402

REWRITE = "make reference"
BLOCK = re.compile(r"(<!-- generated: (?P<name>[\w-]+) \(make reference\) -->\n)(?P<body>.*?)(<!-- end generated -->)",
                   re.S)


def identifiability_block() -> str:
    """The identifiability table of tests/test_identifiability.py, with how many cells each mark stands for."""
    import test_identifiability as ti
    return (f"✓: {len(ti.CI)} cells run by every `make test`; ○: {len(ti.SLOW)} more with `--run-slow`.\n\n"
            + ti.tables())


#: whole pages: path relative to the repository -> the function that renders it
PAGES: dict[str, Callable[[], str]] = {
    "docs/reference/study-keys.md": study_keys.render,
    "docs/reference/model.md": model_page.render,
    "docs/reference/troubleshooting.md": errors_page.render,
}
#: generated blocks inside a hand-written page: block name -> (page, renderer)
BLOCKS: dict[str, tuple[str, Callable[[], str]]] = {
    "identifiability": ("docs/diagnosing.md", identifiability_block),
}


def _with_blocks(text: str, page: str) -> str:
    def fill(m: re.Match) -> str:
        name = m.group("name")
        if name not in BLOCKS or BLOCKS[name][0] != page:
            raise RuntimeError(f"{page}: unknown generated block {name!r}")
        return m.group(1) + BLOCKS[name][1]().rstrip("\n") + "\n" + m.group(4)
    return BLOCK.sub(fill, text)


def expected() -> dict[str, str]:
    """Every generated file's text as the code gives it now (path relative to the repository -> text)."""
    out = {path: render().rstrip("\n") + "\n" for path, render in PAGES.items()}
    for page in sorted({p for p, _ in BLOCKS.values()}):
        text = (ROOT / page).read_text(encoding="utf-8")
        names = {m.group("name") for m in BLOCK.finditer(text)}
        missing = {n for n, (p, _) in BLOCKS.items() if p == page} - names
        if missing:
            raise RuntimeError(f"{page}: the generated block(s) {sorted(missing)} are missing")
        out[page] = _with_blocks(text, page)
    return out


def stale() -> list[str]:
    """The generated files whose committed text differs from what the code gives now."""
    return [p for p, text in expected().items()
            if not (ROOT / p).is_file() or (ROOT / p).read_text(encoding="utf-8") != text]


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if "--check" in argv:
        bad = stale()
        for p in bad:
            print(f"{p} is stale: run `{REWRITE}`")
        return 1 if bad else 0
    for p, text in expected().items():
        path = ROOT / p
        path.parent.mkdir(parents=True, exist_ok=True)
        if not path.is_file() or path.read_text(encoding="utf-8") != text:
            path.write_text(text, encoding="utf-8")
            print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
