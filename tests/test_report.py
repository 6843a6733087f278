"""The report of the paper's study on the real FMU: report.md, the figures it embeds, summary.json."""
from __future__ import annotations

import json
import re
import struct
from pathlib import Path

import pytest

from fmusa.format import fmt
from fmusa.api import load_study, parse_study, run_study

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "studies" / "paper.yaml"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
EXPECTED = ["grid_max_y.png", "grid_mean_y.png", "grid_max_v.png", "grid_mean_v.png", "grid_t_eq.png",
            "search_max_y.png", "search_max_v.png", "search_t_eq.png", "search_path.png",
            "optimum_time_series.png", "ramp_time.png"]


@pytest.fixture(scope="module")
def paper_report(tmp_path_factory, fmu_path):
    out = tmp_path_factory.mktemp("report")
    result = run_study(load_study(PAPER), out, figures=True, progress=False)
    return result, out


def _png_size(path: Path) -> tuple[int, int]:
    """Width and height from the IHDR chunk; fails unless the file is a PNG."""
    head = path.read_bytes()[:24]
    assert head[:8] == PNG_SIGNATURE, f"{path.name} is not a PNG"
    assert head[12:16] == b"IHDR", f"{path.name}: no IHDR chunk"
    return struct.unpack(">II", head[16:24])


def _referenced(text: str) -> list[str]:
    return re.findall(r"!\[[^\]]*\]\(([^)\s]+)\)", text)


def test_report_mentions_the_optimum_and_the_paper(paper_report):
    result, out = paper_report
    report = out / "report.md"
    assert report.is_file()
    text = report.read_text(encoding="utf-8")
    c, d = result.summary["optimum"]["c"], result.summary["optimum"]["d"]
    assert fmt(c, 7) in text and fmt(d, 6) in text          # our optimum, as the tables write it
    assert "823224" in text and "488" in text                # the paper's optimum next to it
    for heading in ("## What was run", "### Region of interest", "### Optimum", "### Binding constraint",
                    "### Search path", "### Regression", "## Figures",
                    "## How the results depend on the ramp time and the end time", "## Deviations explained"):
        assert heading in text, heading
    # the deviations are computed: the ramp that reproduces the paper's t_eq, and the stiffness F/eps_y
    assert re.search(r"t_ramp = \d+(\.\d+)? ms \(bisection on the FMU\)", text)
    assert "822000 N/m" in text


def test_every_referenced_figure_is_a_real_png(paper_report):
    _, out = paper_report
    text = (out / "report.md").read_text(encoding="utf-8")
    refs = _referenced(text)
    assert {f"figures/{n}" for n in EXPECTED} <= set(refs)
    for ref in refs:
        path = out / ref
        assert path.is_file(), f"report.md references a missing file {ref}"
        assert path.stat().st_size > 20_000, f"{ref} is suspiciously small ({path.stat().st_size} bytes)"
        w, h = _png_size(path)
        assert w >= 600 and h >= 400, f"{ref}: {w}×{h} pixels"


def test_summary_json_parses_and_lists_the_figures(paper_report):
    result, out = paper_report
    s = json.loads((out / "summary.json").read_text())
    assert s["figures"] == result.summary["figures"]
    assert sorted(s["figures"]) == sorted(f"figures/{n}" for n in EXPECTED)
    for f in s["figures"]:
        assert (out / f).is_file(), f
    assert s["optimum"]["c"] == pytest.approx(411 / 5e-4, rel=2e-3)
    assert "wall_s_with_report" in s


def test_report_without_search_stages(tmp_path, fmu_path):
    """A study with only the grid still gets its heat maps and a report, without the search sections."""
    text = PAPER.read_text()
    start, end = text.index("  roi:"), text.index("execution:")
    study = parse_study(text[:start] + "\n" + text[end:], PAPER)
    result = run_study(study, tmp_path, figures=True, progress=False)
    report = (tmp_path / "report.md").read_text(encoding="utf-8")
    assert "## What was run" in report and "### Optimum" not in report
    refs = _referenced(report)
    assert refs and all(r.startswith("figures/grid_") for r in refs)
    for r in refs:
        _png_size(tmp_path / r)
    assert json.loads((tmp_path / "summary.json").read_text())["figures"] == result.summary["figures"]
