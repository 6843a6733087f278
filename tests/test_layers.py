"""The package's layers, checked on the source: who may import whom, no cycles, no private names across
modules.

Every import counts, at module level or inside a function, absolute or relative: a function-level import
against the layer order is the same dependency, only deferred. The rules are the table LAYERS; the
checker is plain ``ast`` (nothing is imported), and :func:`test_checker_catches_planted_violations` makes
sure it still finds what it is meant to find.
"""
from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Sequence

SRC = Path(__file__).resolve().parents[1] / "src"
ROOT = "fmusa"

#: (layer, its modules, the layers it may import besides itself). A module entry covers the module and,
#: for a package, everything under it; the root package ``fmusa`` (its __init__) covers itself only.
#: The stack base → fmi → runs → study → analysis → pipeline → report → applications → top, and
#: diagnose: a vertical on base, fmi, runs and cosim (the coupling master, on base and fmi) that only
#: applications and the top use.
_STACK = ("base", "fmi", "runs", "study", "analysis", "pipeline", "report")
LAYERS: tuple[tuple[str, tuple[str, ...], tuple[str, ...]], ...] = (
    ("base", ("fmusa.errors", "fmusa.format", "fmusa.files", "fmusa.figure_check"), ()),
    ("fmi", ("fmusa.fmi",), _STACK[:1]),
    ("runs", ("fmusa.runs",), _STACK[:2]),
    ("study", ("fmusa.study",), _STACK[:3]),
    ("analysis", ("fmusa.analysis",), _STACK[:4]),
    ("pipeline", ("fmusa.pipeline",), _STACK[:5]),
    ("report", ("fmusa.report",), _STACK[:6]),
    ("cosim", ("fmusa.cosim",), ("base", "fmi")),
    ("diagnose", ("fmusa.diagnose",), ("base", "fmi", "runs", "cosim")),
    ("applications", ("fmusa.applications",), _STACK + ("cosim", "diagnose")),
    ("top", ("fmusa", "fmusa.api", "fmusa.cli", "fmusa.bench"), _STACK + ("cosim", "diagnose", "applications")),
)


@dataclass(frozen=True)
class Import:
    """One imported module (the longest known module the statement names) and the names taken from it."""
    source: str
    target: str
    line: int
    names: tuple[str, ...]


def find_modules(src: Path, root: str) -> dict[str, Path]:
    """Dotted module name -> file, for every .py file of package ``root`` under ``src``."""
    out = {}
    for f in sorted((src / root).rglob("*.py")):
        parts = f.relative_to(src).with_suffix("").parts
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = f
    return out


def _known(name: str, modules: Mapping[str, Path]) -> str | None:
    while name and name not in modules:
        name = name.rpartition(".")[0]
    return name or None


def imports_of(name: str, path: Path, modules: Mapping[str, Path]) -> list[Import]:
    """Every import of package modules in ``path`` (module ``name``), at any depth of the syntax tree."""
    is_pkg = path.name == "__init__.py"
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                target = _known(alias.name, modules)
                if target:
                    out.append(Import(name, target, node.lineno, ()))
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = name.split(".") if is_pkg else name.split(".")[:-1]
                parts = parts[:len(parts) - (node.level - 1)]
                base = ".".join(parts + ([base] if base else []))
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                if sub in modules:             # `from pkg import submodule`
                    out.append(Import(name, sub, node.lineno, ()))
                else:
                    target = _known(base, modules)
                    if target:
                        out.append(Import(name, target, node.lineno, (alias.name,)))
    return out


def layer_of(module: str, layers: Sequence[tuple[str, tuple[str, ...], tuple[str, ...]]], root: str) -> str | None:
    """The layer whose most specific entry covers ``module``; None when no entry does."""
    best, best_len = None, -1
    for layer, prefixes, _ in layers:
        for p in prefixes:
            covers = module == p or (p != root and module.startswith(p + "."))
            if covers and len(p) > best_len:
                best, best_len = layer, len(p)
    return best


def _cycles(edges: Mapping[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    for start in sorted(edges):
        if start in index:
            continue
        work = [(start, iter(sorted(edges[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on.add(start)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(edges.get(w, ())))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop()
                        on.discard(w)
                        comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        out.append(sorted(comp))
    return out


def check(src: Path, root: str, layers: Sequence[tuple[str, tuple[str, ...], tuple[str, ...]]]) -> list[str]:
    """Every violation in package ``root`` under ``src``: an import against ``layers``, a module no layer
    covers, an import cycle between modules, a name starting with "_" imported from another module."""
    modules = find_modules(src, root)
    allowed = {layer: set(may) | {layer} for layer, _, may in layers}
    problems: list[str] = []
    edges: dict[str, set[str]] = {m: set() for m in modules}
    for m, path in modules.items():
        here = layer_of(m, layers, root)
        rel = path.relative_to(src)
        if here is None:
            problems.append(f"{rel}: module {m} is in no layer; add it to LAYERS")
            continue
        for imp in imports_of(m, path, modules):
            if imp.target == m:
                continue
            there = layer_of(imp.target, layers, root)
            if there is not None and there not in allowed[here]:
                problems.append(f"{rel}:{imp.line}: layer {here} ({m}) imports {imp.target} of layer {there}")
            private = [n for n in imp.names if n.startswith("_") and not (n.startswith("__") and n.endswith("__"))]
            if private:
                problems.append(f"{rel}:{imp.line}: {m} imports private {', '.join(private)} from {imp.target}")
            if not m.startswith(imp.target + "."):   # a package's own parents are imported first anyway
                edges[m].add(imp.target)
    for comp in _cycles(edges):
        problems.append(f"import cycle: {' <-> '.join(comp)}")
    return problems


def test_layers_cycles_and_private_imports() -> None:
    problems = check(SRC, ROOT, LAYERS)
    assert not problems, "\n".join(problems)


def test_every_layer_entry_exists() -> None:
    """A renamed or removed module must leave LAYERS too, or the table silently stops checking it."""
    modules = find_modules(SRC, ROOT)
    missing = [p for _, prefixes, _ in LAYERS for p in prefixes
               if p not in modules and not any(m.startswith(p + ".") for m in modules)]
    assert not missing, f"LAYERS names modules that do not exist: {missing}"


# ---------------------------------------------------------------------------- the checker itself
def _write(root: Path, files: Mapping[str, str]) -> None:
    for rel, text in files.items():
        f = root / rel
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text(text)


_TOY_LAYERS = (
    ("low", ("toy.low",), ()),
    ("high", ("toy.high",), ("low",)),
    ("top", ("toy",), ("low", "high")),
)
_CLEAN = {
    "toy/__init__.py": "",
    "toy/low/__init__.py": "",
    "toy/low/a.py": "X = 1\n_HIDDEN = 2\n",
    "toy/low/b.py": "from .a import X\n",
    "toy/high/__init__.py": "",
    "toy/high/c.py": ("from toy.low.a import X\nfrom toy.low import b\n\n"
                      "def f():\n    from ..low import a\n    return a\n"),
}


def test_checker_passes_a_clean_package(tmp_path: Path) -> None:
    _write(tmp_path, _CLEAN)
    assert check(tmp_path, "toy", _TOY_LAYERS) == []


def _problems(tmp_path: Path, extra: Mapping[str, str]) -> list[str]:
    _write(tmp_path, {**_CLEAN, **extra})
    return check(tmp_path, "toy", _TOY_LAYERS)


def test_checker_catches_an_upward_import_inside_a_function(tmp_path: Path) -> None:
    probs = _problems(tmp_path, {"toy/low/b.py": "def g():\n    from toy.high import c\n    return c\n"})
    assert any("layer low (toy.low.b) imports toy.high.c of layer high" in p for p in probs), probs


def test_checker_catches_a_relative_upward_import(tmp_path: Path) -> None:
    probs = _problems(tmp_path, {"toy/low/b.py": "from ..high.c import f\n"})
    assert any("imports toy.high.c of layer high" in p for p in probs), probs


def test_checker_catches_an_import_of_the_top_package(tmp_path: Path) -> None:
    probs = _problems(tmp_path, {"toy/low/b.py": "import toy\n"})
    assert any("layer low (toy.low.b) imports toy of layer top" in p for p in probs), probs


def test_checker_catches_a_cycle(tmp_path: Path) -> None:
    probs = _problems(tmp_path, {"toy/low/a.py": "X = 1\n\ndef f():\n    from toy.low.b import X\n    return X\n"})
    assert "import cycle: toy.low.a <-> toy.low.b" in probs, probs


def test_checker_catches_a_private_import(tmp_path: Path) -> None:
    probs = _problems(tmp_path, {"toy/high/d.py": "from toy.low.a import _HIDDEN\n"})
    assert any("toy.high.d imports private _HIDDEN from toy.low.a" in p for p in probs), probs


def test_checker_catches_a_module_in_no_layer(tmp_path: Path) -> None:
    probs = _problems(tmp_path, {"toy/loose.py": ""})
    assert any("module toy.loose is in no layer" in p for p in probs), probs
