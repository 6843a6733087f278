"""The generic diagnosis core holds none of ScrewVertebra's variable names: they live in its model description
(src/fmusa/diagnose/models/ScrewVertebra.yaml, a data file, and studies/diagnose_screw_vertebra.yaml) and in
the effect catalogue (fmusa.diagnose.effects: the effects' parameters, as data). Checked on the source: every
string in the code (docstrings and comments aside) and every identifier of the core's modules."""
from __future__ import annotations

import ast
import re
from pathlib import Path

import yaml

SRC = Path(__file__).resolve().parents[1] / "src" / "fmusa" / "diagnose"
#: the effect catalogue: the modules of the diagnosis that name the catalogue's parameters, as data: the
#: effects and their parameters, and each effect's physical-support rules (plausibility.py)
CATALOGUE = {"effects.py", "plausibility.py"}
#: ScrewVertebra's variables that a diagnosis sets or reads (its tolerance parameter ``rtol`` is also the
#: solver's generic keyword, so it is checked in the description only), and the effects' parameters
SCREW_VERTEBRA = ("c_y", "d_y", "mode", "y_in", "use_y_in", "F_ext_y", "F_meas", "y_meas", "F_pull", "F_max",
                  "L_screw", "smooth_w", "monitors")
EFFECT_PARAMETERS = ("gap", "nl_ratio", "nl_y_b", "yield_ratio", "yield_F", "fric_F", "fric_x", "ve_k", "ve_tau",
                     "dmg_rate", "dmg_y0", "dmg_F_res", "F_offset", "y_offset")
NAMES = re.compile(r"(?<![\w.])(" + "|".join(SCREW_VERTEBRA + EFFECT_PARAMETERS) + r")(?![\w])")


def _docstrings(tree: ast.AST) -> set[int]:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                out.add(id(first.value))
    return out


def names_in_code(path: Path) -> list[str]:
    """Each ScrewVertebra or effect-parameter name in a string or identifier of the module (file:line: name)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    docs = _docstrings(tree)
    hits = []
    for node in ast.walk(tree):
        text = None
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs:
            text = node.value
        elif isinstance(node, ast.Name):
            text = node.id
        elif isinstance(node, ast.Attribute):
            text = node.attr
        elif isinstance(node, ast.arg):
            text = node.arg
        if text:
            hits += [f"{path.name}:{node.lineno}: {m}" for m in NAMES.findall(text)]
    return hits


def core_modules() -> list[Path]:
    return [p for p in sorted(SRC.rglob("*.py")) if p.name not in CATALOGUE]


def test_generic_core_holds_no_screw_vertebra_names():
    hits = [h for p in core_modules() for h in names_in_code(p)]
    assert not hits, "ScrewVertebra's names in the generic diagnosis core (move them into its model " \
                     "description or the effect catalogue):\n" + "\n".join(hits)


def test_the_check_finds_a_planted_name(tmp_path):
    """The checker itself: a name in a string or an argument is found, one in a docstring is not."""
    f = tmp_path / "m.py"
    f.write_text('"""Uses c_y."""\ndef f(y_in=1):\n    """d_y."""\n    return {"gap": 1, "note": "set mode 2"}\n')
    assert sorted(names_in_code(f)) == ["m.py:2: y_in", "m.py:4: gap", "m.py:4: mode"]


def test_the_names_are_in_the_description():
    """ScrewVertebra's names the core lacks are in its description (so the check above tests a move, not a loss)."""
    d = yaml.safe_load((SRC / "models" / "ScrewVertebra.yaml").read_text(encoding="utf-8"))
    text = repr(d)
    for name in ("c_y", "d_y", "mode", "y_in", "use_y_in", "F_ext_y", "F_meas", "y_meas", "F_max", "L_screw",
                 "smooth_w", "monitors", "rtol"):
        assert name in text, name
