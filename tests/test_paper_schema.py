"""The study file's `paper:` block is checked at load (fmusa.api.load_study): unknown keys and wrong shapes
are errors that name the file, the line, the key and what is allowed; the plain loader keeps it as data."""
from __future__ import annotations

from pathlib import Path

import pytest

from fmusa.api import load_study, parse_study
from fmusa.applications.paper.schema import PAPER_KEYS
from fmusa.study import loader
from fmusa.study.schema import StudyError

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "studies" / "paper.yaml"
TEXT = PAPER.read_text(encoding="utf-8")


def _line(text: str, fragment: str) -> int:
    return next(i for i, line in enumerate(text.splitlines(), 1) if fragment in line)


def test_the_paper_study_loads_with_its_block():
    s = load_study(PAPER)
    assert set(s.paper) == set(PAPER_KEYS)
    assert s.paper["optimum"] == {"c": 823224, "d": 488, "t_eq": 0.07674}


def test_an_unknown_key_names_file_line_key_and_the_allowed_keys(tmp_path):
    text = TEXT.replace("  cpu_s_per_run: 5", "  cpu_s_per_run: 5\n  cpu_per_run: 5")
    path = tmp_path / "paper.yaml"
    path.write_text(text)
    with pytest.raises(StudyError) as exc:
        load_study(path)
    msg = str(exc.value)
    assert msg.startswith(f"{path}:{_line(text, 'cpu_per_run')}: key 'cpu_per_run' is not allowed in 'paper'")
    assert "did you mean 'cpu_s_per_run'?" in msg
    assert "(allowed: " + ", ".join(PAPER_KEYS) + ")" in msg
    assert loader.load_study(path).paper["cpu_per_run"] == 5      # the plain loader takes any block


@pytest.mark.parametrize("old, new, fragment, expected", [
    ("    x: c\n    r: 0.002", "    x: c\n    q: 0.002", "q: 0.002",
     "key 'q' is not allowed in 'paper.regression' (allowed: metric, x, r, s, t, u)"),
    ("    d: [0, 15625]", "    d: [15625]", "d: [15625]", "key 'd' in 'paper.roi' must be [lo, hi]"),
    ("  optimum: {c: 823224, d: 488, t_eq: 0.07674}", "  optimum: {c: 823224, d: fast, t_eq: 0.07674}",
     "optimum:", "key 'd' in 'paper.optimum' must be a number"),
    ("  cpu_s_per_run: 5", "  cpu_s_per_run: five", "cpu_s_per_run", "key 'cpu_s_per_run' in 'paper' must be a number"),
    ("    max_v: {value: 1.60e-2, c: 1.56e4, d: 1.56e4}", "    max_v: {c: 1.56e4, d: 1.56e4}", "max_v: {c:",
     "key 'value' is missing in 'paper.grid_extremes.max_v'"),
])
def test_a_wrong_shape_names_its_line(tmp_path, old, new, fragment, expected):
    assert old in TEXT
    text = TEXT.replace(old, new)
    with pytest.raises(StudyError) as exc:
        parse_study(text, tmp_path / "p.yaml")
    msg = str(exc.value)
    assert msg.startswith(f"{tmp_path / 'p.yaml'}:{_line(text, fragment)}: "), msg
    assert expected in msg, msg
