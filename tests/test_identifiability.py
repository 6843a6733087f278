"""Which effect a test protocol can identify, and what `fmusa diagnose` says where it cannot.

Real protocols differ: one rate or several, with or without a hold, with or without unloading
(``effects_reference.PROTOCOLS``). From the physics of fmu/MODEL.md, :func:`expected` states for every
effect and protocol whether the effect is identifiable there, or which look-alike hides it and which test
would separate them. Every cell of that table is run through the FMU (:data:`CELLS`: the 6 x 8 cells of the
displacement drive, those whose answer depends on the specimen twice (:func:`_split`: a softening or a
stiffening curve, an offset along or against the load), and the force drive for one protocol per effect plus
a ramp): the tool must name the effect where it is identifiable, and say "cannot tell, because ..." with the
separating test where it is not. ``coulomb_friction`` and
``yield_softening`` are the same equations (``EQUIVALENT_BY_CONSTRUCTION``): where identifiable, they are
named together, "coulomb_friction ≡ yield_softening".

Each cell is its own synthetic specimen (a seed per cell, :func:`seed_for`), 0.5 % noise, at most
:data:`POINTS` block means per test and :data:`STARTS` least-squares starts; the candidates of a cell are all
six less those :data:`LEFT_OUT` names, each with the physical reason it cannot be the look-alike. The cells
run two at a time (one process each), each with its fit cache; the equivalent pair's test reruns from its cache.
The cells of :data:`CI` (:func:`_in_ci`: 43 of the 60, about 2.5 minutes on two cores) run on every
``make test``, those of :data:`SLOW` only with ``--run-slow`` (``make identifiability``, about 3.5 minutes).
The table (with which cells ran where) is written to out/identifiability.md with what the tool
said in every cell that ran, and is the one in the README (:func:`test_readme_has_the_table`).
"""
from __future__ import annotations

import json
import multiprocessing as mp
import re
import sys
import time
import zlib
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import effects_reference as er  # noqa: E402

from fmusa.diagnose.calibrate import Fit, pooled_heldout, unify_equivalent  # noqa: E402
from fmusa.diagnose.effects import CANDIDATES, EQUIVALENT_BY_CONSTRUCTION, equivalent_parameters  # noqa: E402
from fmusa.diagnose.measured import Experiment, downsample  # noqa: E402
from fmusa.diagnose.rank import GROUP_SEP, group_members  # noqa: E402
from fmusa.diagnose.run import diagnose  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: block means per test and least-squares starts: small specimens keep a cell at a few seconds; 4 starts still
#: try both branches of the nonlinear stiffness (softening, stiffening) and 2 of the friction's pre-slips
POINTS, STARTS = 100, 4

#: Candidates a row leaves out, with the reason: one of an equivalent pair when the other is fitted (the same
#: equations give the same fit), and effects that bend the curve the other way from the start (they cannot
#: be the look-alike). The look-alikes of :func:`expected` and the separating tests' pairs stay in.
LEFT_OUT = {
    "coulomb_friction": {
        "backlash_gap": "slack gives no force near zero, friction a stiff pre-slip: opposite curvature from the start"},
    "yield_softening": {
        "backlash_gap": "slack gives no force near zero, yield the full stiffness c_y: opposite curvature from the "
                        "start"},
    "nonlinear_stiffness": {
        "coulomb_friction": "the same equations as yield_softening (EQUIVALENT_BY_CONSTRUCTION), which is fitted"},
    "viscoelastic_relaxation": {
        "yield_softening": "the same equations as coulomb_friction (EQUIVALENT_BY_CONSTRUCTION), which is fitted",
        "backlash_gap": "slack gives no force near zero, a Maxwell branch adds stiffness from the first motion"},
    "backlash_gap": {
        "coulomb_friction": "friction adds a stiff pre-slip from the first motion, slack no force at all",
        "yield_softening": "yield starts at the full stiffness c_y, slack at none",
        "viscoelastic_relaxation": "a Maxwell branch adds stiffness from the first motion, slack no force at all"},
    "sensor_offset": {
        "yield_softening": "the same equations as coulomb_friction (EQUIVALENT_BY_CONSTRUCTION), which is fitted"},
    "interface_damage": {
        "coulomb_friction": "the same equations as yield_softening (EQUIVALENT_BY_CONSTRUCTION), which is fitted",
        "backlash_gap": "slack gives no force near zero, damage starts with the full stiffness c_y"},
}


class Cell(NamedTuple):
    """One cell of the table: an effect hidden in a specimen tested under a protocol, in a drive mode.
    ``variant`` splits a cell whose answer depends on the specimen (the sign of a sensor offset)."""
    effect: str
    protocol: str
    drive: str = "displacement"
    variant: str = ""

    @property
    def id(self) -> str:
        return "|".join(x for x in self if x)


def equivalents(effect: str) -> set[str]:
    """The effect and those that are the same equations."""
    out = {effect}
    for pair in EQUIVALENT_BY_CONSTRUCTION:
        if effect in pair:
            out |= set(pair)
    return out


def expected(cell: Cell) -> dict:
    """Identifiable here (named), or the look-alike that hides it, why, and the words one of which its
    separating test must contain. From the physics of fmu/MODEL.md, displacement drive:

    * friction (the generator's: a pre-slip of 10 um, a sharp corner): on loading alone (no unloading) it is a
      bend of the curve, which an elastic nonlinear stiffness gives too; with an unloading at one rate and no
      hold, it is a force that flips at the reversal like the damping force d_y*v; so it needs an unloading and
      a hold or a second rate (on a plain ramp both look-alikes hide it);
    * yield softening (at 30-60 % of the peak, a long elastic unloading) and a softening nonlinear stiffness
      bend the loading curve alike; only unloading (elastic retraces, yield leaves a set) separates them; a
      stiffening curve has no such look-alike;
    * a Maxwell branch at one rate without a hold is a smooth softening (or, with a short time constant, a
      damping): a hold (relaxation) or a second rate separates it;
    * a force bias on one ramp equals a damping force d_y*v when it has the sign of the velocity (d_y >= 0
      cannot give the other sign); a hold, an unloading or a second rate separates them;
    * slack (a zero-force band from zero) shows on every loading from rest; but a soft toe (a stiffening
      nonlinear stiffness, at most 20 times stiffer past its breakpoint: its bound) gives at most c_y*gap/20 in
      the band, within the noise when the slack is small (below about 1/8 of the peak at 0.5 % noise), and
      then the two are named together; loading through zero in both directions separates them.

    * interface damage (the generator's: onset at 35-55 % of the peak displacement, the force dropping past a
      peak towards a residual): no other candidate lowers the force while the displacement grows (yield and a
      bend keep a stiffness >= 0, friction and a Maxwell branch add force), so the drop names it under every
      protocol; where the test unloads, the secant unloading (no set, no jump) confirms it.

    Force drive (the cells run): every effect is identifiable under load-hold-unload (each shows in the
    displacement it adds: a shift by the gap, creep in the hold, a set after unloading, ...); on a force ramp
    yield and an elastic bend give the same loading curve y(F), and unloading separates them."""
    several, hold, unload = er.PROTOCOLS[cell.protocol]
    effect = cell.effect
    if cell.drive == "force":
        if cell.protocol == "load-hold-unload":
            ok, hider, words = True, None, ()
        elif effect == "interface_damage":
            raise ValueError(f"no physics stated for {cell}")
        elif effect in ("yield_softening", "nonlinear_stiffness") and not unload:
            other = "nonlinear_stiffness" if effect == "yield_softening" else "yield_softening"
            ok, hider, words = False, other, ("unload",)
        else:
            raise ValueError(f"no physics stated for {cell}")
    elif effect == "coulomb_friction":
        ok = unload and (hold or several)
        if not unload and not (hold or several):
            hider, words = "damping d_y (baseline), a Maxwell branch or an elastic bend", ("hold", "unload")
        elif not unload:
            hider, words = "nonlinear_stiffness", ("unload",)
        else:
            hider, words = "damping d_y (baseline) or a Maxwell branch", ("hold",)
    elif effect == "yield_softening":
        ok, hider, words = unload, "nonlinear_stiffness", ("unload",)
    elif effect == "nonlinear_stiffness":
        ok, hider, words = unload or cell.variant == "stiffening", "yield_softening", ("unload",)
    elif effect == "viscoelastic_relaxation":
        ok, hider, words = hold or several, "nonlinear_stiffness, or friction / damping", ("hold",)
    elif effect == "sensor_offset":
        along = cell.variant != "against the load"
        ok, hider, words = hold or several or unload or not along, "damping d_y (baseline)", ("hold",)
    elif effect in ("backlash_gap", "interface_damage"):
        ok, hider, words = True, None, ()
    else:
        raise ValueError(effect)
    # a look-alike that may fit within the noise, named with the effect then, and the separating test's words
    with_ = ("nonlinear_stiffness", ("through zero",)) if effect == "backlash_gap" else None
    return {"identifiable": ok, "named": equivalents(effect) if ok else None, "look_alike": None if ok else hider,
            "separating_words": () if ok else words, "or_named_with": with_}


def candidates(cell: Cell) -> tuple[str, ...]:
    """The candidates fitted in a cell: all six less the row's LEFT_OUT (displacement drive; the force drive,
    whose physics the reasons were not stated for, fits all six)."""
    out = LEFT_OUT.get(cell.effect, {}) if cell.drive == "displacement" else {}
    return tuple(c for c in CANDIDATES if c not in out)


#: specimens a variant asks for: the sign of a sensor offset, the branch of a nonlinear stiffness
VARIANTS = {
    ("sensor_offset", "along the load"): lambda p: p["F_offset"] > 0,
    ("sensor_offset", "against the load"): lambda p: p["F_offset"] < 0,
    ("nonlinear_stiffness", "softening"): lambda p: p["nl_ratio"] < 1,
    ("nonlinear_stiffness", "stiffening"): lambda p: p["nl_ratio"] > 1,
}


def seed_for(cell: Cell) -> int:
    """A specimen per cell (a seed from its name); for a variant the first seed from there whose specimen
    is of that kind (the specimens load in the positive direction)."""
    seed = zlib.crc32(f"{cell.effect}|{cell.protocol}|{cell.drive}|{cell.variant}".encode()) % 10_000
    if cell.variant:
        wanted = VARIANTS[(cell.effect, cell.variant)]
        while not wanted(er.draw_case(cell.effect, cell.drive, np.random.default_rng(seed))[0]):
            seed += 1
    return seed


def _experiments(cell: Cell, seed: int) -> tuple[list[Experiment], dict]:
    frames, truth = er.synthesize_protocol(cell.effect, cell.drive, seed, cell.protocol)
    exps = [downsample(Experiment(name=f"rate{i}", path=Path(f"rate{i}.csv"), drive=cell.drive, t=df.time.values,
                                  displacement=df.displacement.values, force=df.force.values), POINTS)
            for i, df in enumerate(frames)]
    return exps, truth


#: the force-drive protocols run (one per effect, and the ramp that hides yield behind an elastic bend)
FORCE_CELLS = [Cell(e, "load-hold-unload", "force") for e in CANDIDATES] + [Cell("yield_softening", "ramp", "force")]


def _split(effect: str, protocol: str) -> list[Cell]:
    """The cells of one (effect, protocol): two where the answer depends on the specimen."""
    unload = er.PROTOCOLS[protocol][2]
    if effect == "sensor_offset" and protocol == "ramp":
        return [Cell(effect, protocol, variant=v) for v in ("along the load", "against the load")]
    if effect == "nonlinear_stiffness" and not unload:
        return [Cell(effect, protocol, variant=v) for v in ("softening", "stiffening")]
    return [Cell(effect, protocol)]


CELLS = [c for e in CANDIDATES for p in er.PROTOCOLS for c in _split(e, p)] + FORCE_CELLS
def _one_rate(cell: Cell) -> list[Cell]:
    """The cells of the same effect under the protocol without the second rate."""
    p = cell.protocol.replace(", 2 rates", "").replace("ramps", "ramp")
    return [c for c in CELLS if (c.effect, c.protocol, c.drive) == (cell.effect, p, cell.drive)]


def _in_ci(cell: Cell) -> bool:
    """Run on every `make test` (about 1.5 minutes on two cores): in the displacement drive every "cannot
    tell" cell, every effect on the ramp and under load-unload at one rate, and at two rates every cell whose
    answer the second rate changes (friction under load-unload, the Maxwell branch, the offset on ramps, the
    bend); in the force drive the ramp that hides yield and the load-hold-unload of the effects whose fits
    are cheapest there (yield, the Maxwell branch). The others run with --run-slow (`make
    identifiability`): the holds of effects named without them, Coulomb friction where it repeats yield
    (the same Bouc-Wen equations, so the same statements), and the force drive's nonlinear stiffness,
    friction, offset and slack (the costliest fits, 16-30 s each)."""
    if cell.drive == "force":
        return cell.protocol == "ramp" or cell.effect in ("yield_softening", "viscoelastic_relaxation")
    if cell.effect == "interface_damage" and cell.protocol not in ("ramp", "load-unload"):
        return False   # the drop names it on a ramp; a hold adds nothing to tell it by (--run-slow)
    if not expected(cell)["identifiable"]:
        return cell.effect != "coulomb_friction" or cell.protocol == "load-unload, 2 rates"
    if ", 2 rates" not in cell.protocol:
        return cell.protocol in ("ramp", "load-unload")
    return any(not expected(c)["identifiable"] for c in _one_rate(cell))


CI = [c for c in CELLS if _in_ci(c)]
SLOW = [c for c in CELLS if c not in CI]


def run_cell(cell: Cell, fmu: str, cache_root: str) -> dict:
    """Diagnose one cell (in a worker process): what the tool named, what it could not tell, in how long."""
    seed = seed_for(cell)
    exps, truth = _experiments(cell, seed)
    t0 = time.perf_counter()
    d = diagnose(exps, cell.drive, fmu_path=fmu, workers=1, candidates=candidates(cell), max_starts=STARTS, chain=1,
                 cache_dir=Path(cache_root) / re.sub(r"[^A-Za-z0-9]+", "_", cell.id))
    return {"cell": list(cell), "seed": seed, "seconds": time.perf_counter() - t0, "effect": d["effect"],
            "indistinguishable": [{k: i[k] for k in ("effect", "reason", "separating_test")}
                                  for i in d["indistinguishable"]],
            "ranking": [{"effect": r["effect"], "significant": r["significant"],
                         "heldout_rmse_ratio": r["heldout_rmse_ratio"], "delta_bic": r["delta_bic"]}
                        for r in d["ranking"]],
            # the units check's warnings (the block averaging's check may warn on these blocks of 3-4 samples: it
            # concerns the parameters' values, not which effect is named, and is kept apart)
            "warnings": [w["message"] for w in d["warnings"] if w.get("kind", "units") == "units"],
            "averaging_warnings": [w["message"] for w in d["warnings"] if w.get("kind") == "averaging"],
            "group_own": {m: g.get("own", {}).get("heldout_rmse") for m, g in d["group"].items()},
            "baseline_heldout": d["baseline"]["heldout_rmse"]}


def _run_cells(cells: list[Cell], fmu: Path, cache_root: Path) -> dict[Cell, dict]:
    """Every cell, two at a time (the slowest first, so that the last ones finish together)."""
    order = sorted(cells, key=lambda c: (c.drive != "force", ", 2 rates" not in c.protocol))
    with ProcessPoolExecutor(2, mp_context=mp.get_context("spawn")) as ex:
        futs = {c: ex.submit(run_cell, c, str(fmu), str(cache_root)) for c in order}
        return {c: f.result() for c, f in futs.items()}


OUTCOMES: dict[Cell, dict] = {}


@pytest.fixture(scope="module")
def cache_root(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("identifiability_fits")


@pytest.fixture(scope="module")
def ci_outcomes(fmu_path, cache_root) -> dict[Cell, dict]:
    t0 = time.perf_counter()
    out = _run_cells(CI, fmu_path, cache_root)
    OUTCOMES.update(out)
    print(f"\n{len(CI)} cells in {time.perf_counter() - t0:.0f} s")
    (ROOT / "out").mkdir(exist_ok=True)
    (ROOT / "out" / "identifiability_ci.json").write_text(json.dumps({c.id: o for c, o in out.items()}, indent=1))
    return out


@pytest.fixture(scope="module")
def slow_outcomes(fmu_path, cache_root) -> dict[Cell, dict]:
    out = _run_cells(SLOW, fmu_path, cache_root)
    OUTCOMES.update(out)
    return out


def problems(cell: Cell, outcome: dict) -> list[str]:
    """What the tool said that the physics of the cell contradicts (empty: it agrees)."""
    e = expected(cell)
    members = set(group_members(outcome["effect"]))
    cannot = [i for i in outcome["indistinguishable"] if i["reason"].startswith("cannot tell, because")]
    out = []
    if outcome["warnings"]:
        out.append(f"a units warning on synthetic data in SI: {outcome['warnings']}")
    if e["identifiable"]:
        want = e["named"] & (set(candidates(cell)) | {cell.effect})
        if members == want:
            return out
        other = e["or_named_with"]
        if other and members == want | {other[0]} and any(
                i["effect"] == other[0] and any(w in i["separating_test"] for w in other[1]) for i in cannot):
            return out
        out.append(f"named {outcome['effect']!r}, expected {GROUP_SEP.join(sorted(want))!r}"
                   + (f" (or with {other[0]} and a separating test with {other[1]})" if other else ""))
        return out
    # not identifiable: never named alone without a word; the tool says "cannot tell, because ..." and gives
    # a separating test of the expected kind, naming the hidden effect among the look-alikes
    if not cannot:
        out.append("no 'cannot tell, because ...'")
    if cell.effect not in members | {i["effect"] for i in cannot}:
        out.append(f"{cell.effect} neither named nor among the look-alikes")
    if not any(w in i["separating_test"] for i in cannot for w in e["separating_words"]):
        out.append(f"no separating test with {' or '.join(map(repr, e['separating_words']))}")
    return out


def _info(outcome: dict) -> str:
    scores = {r["effect"]: (r["significant"], round(r["heldout_rmse_ratio"], 3), round(r["delta_bic"], 1))
              for r in outcome["ranking"]}
    return (f"seed {outcome['seed']}: named {outcome['effect']!r}; ranking {scores}; indistinguishable "
            f"{[(i['effect'], i['reason'][:60]) for i in outcome['indistinguishable']]}")


@pytest.mark.parametrize("cell", CI, ids=[c.id for c in CI])
def test_named_where_identifiable_else_cannot_tell(cell, ci_outcomes):
    outcome = ci_outcomes[cell]
    assert not problems(cell, outcome), f"{problems(cell, outcome)}; {_info(outcome)}"


@pytest.mark.slow
@pytest.mark.parametrize("cell", SLOW, ids=[c.id for c in SLOW])
def test_named_where_identifiable_else_cannot_tell_slow(cell, slow_outcomes):
    outcome = slow_outcomes[cell]
    assert not problems(cell, outcome), f"{problems(cell, outcome)}; {_info(outcome)}"


# ---------------------------------------------------------------------- the table

def _mark(cell: Cell) -> str:
    return " ✓" if cell in CI else " ○" if cell in SLOW else ""


def _statement(cell: Cell) -> str:
    e = expected(cell)
    if e["identifiable"]:
        names = sorted(e["named"])
        text = "named" if len(names) == 1 else "named as " + GROUP_SEP.join(f"`{n}`" for n in names)
        return text + (" ¹" if e["or_named_with"] else "")
    return f"cannot tell: {e['look_alike']} ({' or '.join(e['separating_words'])} separates)"


def _cell_text(effect: str, protocol: str, drive: str) -> str:
    cells = [c for c in CELLS if (c.effect, c.protocol, c.drive) == (effect, protocol, drive)]
    if not cells:
        return "–"
    if len(cells) == 1:
        return _statement(cells[0]) + _mark(cells[0])
    return "; ".join(f"{c.variant}: {_statement(c)}{_mark(c)}" for c in cells)


def table(drive: str = "displacement") -> str:
    """The identifiability table (markdown): effect x protocol, for one drive."""
    protos = list(er.PROTOCOLS) if drive == "displacement" else \
        [p for p in er.PROTOCOLS if any(c.drive == drive and c.protocol == p for c in CELLS)]
    lines = ["| effect | " + " | ".join(protos) + " |", "|---|" + "---|" * len(protos)]
    for eff in CANDIDATES:
        lines.append(f"| `{eff}` | " + " | ".join(_cell_text(eff, p, drive) for p in protos) + " |")
    return "\n".join(lines) + "\n"


def tables() -> str:
    """Both tables as the README shows them."""
    return ("Displacement drive:\n\n" + table("displacement") + "\nForce drive (the cells run):\n\n"
            + table("force") + "\n¹ or, when the slack is small against the noise (below about 1/8 of the peak at "
            "0.5 % noise), named together with `nonlinear_stiffness` (a soft toe, at most 20 times stiffer past its "
            "breakpoint, fits within the noise), with the test that separates them: load through zero in both "
            "directions.\n")


def test_every_cell_is_run_and_stated():
    """Every displacement-drive cell is run (in CI or in the slow set), and has a statement; the force drive
    has one protocol per effect."""
    for e in CANDIDATES:
        for p in er.PROTOCOLS:
            run = [c for c in CELLS if (c.effect, c.protocol, c.drive) == (e, p, "displacement")]
            assert run and all(c in CI or c in SLOW for c in run), (e, p)
        assert any(c.effect == e and c.drive == "force" for c in CELLS), e
    assert len(set(CELLS)) == len(CELLS) and not set(CI) & set(SLOW)
    text = tables()
    assert text.count("\n| `") == 2 * len(CANDIDATES)


def test_readme_has_the_table():
    """The documentation shows the table these tests produce: the README, or a page under docs/ (where the
    README's sections are moving)."""
    pages = [ROOT / "README.md"] + sorted((ROOT / "docs").rglob("*.md"))
    texts = [p.read_text(encoding="utf-8") for p in pages if p.is_file()]
    assert any(tables() in t for t in texts), \
        "README.md or docs/: replace the identifiability tables with out/identifiability.md's"


def test_protocols_have_their_features():
    """The synthetic protocols have what their names say, as the diagnosis detects it."""
    from fmusa.diagnose.rank import protocol_features

    for name, (several, hold, unload) in er.PROTOCOLS.items():
        frames, _ = er.synthesize_protocol("none", "displacement", 5, name)
        exps = [Experiment(name=f"r{i}", path=Path("x.csv"), drive="displacement", t=df.time.values,
                           displacement=df.displacement.values, force=df.force.values) for i, df in enumerate(frames)]
        f = protocol_features(exps)
        assert (f["several_rates"], f["hold"], f["unloading"]) == (several, hold, unload), name


def test_friction_and_yield_are_the_same_equations():
    """The mapping of EQUIVALENT_BY_CONSTRUCTION gives the same force for any history (scipy reference),
    and maps back."""
    fr = {"c_y": 2e5, "d_y": 300.0, "fric_F": 20.0, "fric_x": 2e-5}
    yi = equivalent_parameters("coulomb_friction", fr, "yield_softening")
    back = equivalent_parameters("yield_softening", yi, "coulomb_friction")
    assert all(abs(back[k] - fr[k]) <= 1e-12 * abs(fr[k]) for k in fr)
    kt = np.array([0.0, 1.0, 1.5, 2.5, 3.0, 4.0])
    ku = np.array([0.0, 1e-3, 0.4e-3, 0.9e-3, -0.5e-3, 0.2e-3])
    t = np.linspace(0, 4, 801)
    a = er.simulate(fr, "displacement", kt, ku, t)
    b = er.simulate(yi, "displacement", kt, ku, t)
    assert np.max(np.abs(a - b)) < 1e-6 * np.max(np.abs(a))


# ---------------------------------------------------------------------- the equivalent pair, scored as one

def _fit(effect: str, rss: float, held: float, folds: list[tuple[float, float, int]], params: dict) -> Fit:
    return Fit(effect=effect, params=params, ci95={k: (0.9 * v, 1.1 * v) for k, v in params.items()}, rss=rss,
               n=100, k=4, rmse=(rss / 100) ** 0.5, heldout_rmse=held, predictions=[np.zeros(100)],
               heldout_folds=[{"train_cost": c, "sq": s, "count": n} for c, s, n in folds])


def test_equivalent_pair_takes_the_better_fit_and_each_folds_lower_training_cost():
    """The rule itself, on fits made up to tell it from the alternatives: the lower all-data cost wins the
    parameters (mapped into the other's), and in each fold the refit with the lower *training* cost gives the
    held-out error of both, even where the other refit happened to predict the held-out points better."""
    fr = _fit("coulomb_friction", 4.0, 2.95, [(1.0, 100.0, 10), (2.0, 900.0, 10)],
              {"c_y": 2e5, "d_y": 300.0, "fric_F": 20.0, "fric_x": 2e-5})
    yi = _fit("yield_softening", 5.0, 0.55, [(1.5, 1.0, 10), (1.0, 4.0, 10)],
              {"c_y": 1.2e6, "d_y": 300.0, "yield_ratio": 0.2, "yield_F": 25.0})
    u = unify_equivalent({"coulomb_friction": fr, "yield_softening": yi})
    a, b = u["coulomb_friction"], u["yield_softening"]
    # fold 1: friction's refit trained better (1.0 < 1.5): its 100 counts, not yield's 1; fold 2: yield's
    assert a.heldout_rmse == b.heldout_rmse == pytest.approx(((100.0 + 4.0) / 20) ** 0.5)
    assert a.rss == b.rss == 4.0 and b.mapped_from == "coulomb_friction" and a.mapped_from is None
    assert b.params == pytest.approx(equivalent_parameters("coulomb_friction", fr.params, "yield_softening"))
    for k, (lo, hi) in b.ci95.items():
        assert lo <= b.params[k] <= hi, k
    assert b.own["heldout_rmse"] == 0.55 and a.own["heldout_rmse"] == 2.95


def test_equivalent_pair_is_scored_as_one_model(cache_root, fmu_path):
    """Yield under load-unload (seed 2, 150 points: the settings of tests/test_diagnose.py). Written first on a
    ramp-hold, where the two parametrisations' own held-out refits drifted apart (a held-out ratio of 0.58 for
    friction against 0.07 for yield); the protocol check now says a ramp-hold cannot tell either (no unloading),
    so the pair is no longer named there. The diagnosis scores both as one model: the same RMSE,
    BIC and held-out RMSE, the per-fold rule recomputed here from each member's own folds; a rerun from the fit
    cache gives the same; and the mapped parameters give, through the FMU, the same force as the lead's fit."""
    from fmusa.diagnose.calibrate import ModelRunner

    frames, _ = er.synthesize_protocol("yield_softening", "displacement", 2, "load-unload")
    exps = [downsample(Experiment(name="load-unload", path=Path("load-unload.csv"), drive="displacement",
                                  t=f.time.values, displacement=f.displacement.values, force=f.force.values), 150)
            for f in frames]
    cands = ("coulomb_friction", "yield_softening")
    d = diagnose(exps, "displacement", fmu_path=fmu_path, workers=2, candidates=cands, cache_dir=cache_root / "pair")
    rows = {r["effect"]: r for r in d["ranking"]}
    fr, yi = rows["coulomb_friction"], rows["yield_softening"]
    own = {m: g["own"] for m, g in d["group"].items()}
    base = d["baseline"]["heldout_rmse"]
    print(f"\nown held-out ratios: friction {own['coulomb_friction']['heldout_rmse'] / base:.3f}, yield "
          f"{own['yield_softening']['heldout_rmse'] / base:.3f}; shared {fr['heldout_rmse_ratio']:.3f}")
    assert fr["rmse"] == yi["rmse"] and fr["heldout_rmse"] == yi["heldout_rmse"] and fr["bic"] == yi["bic"]
    folds = [x if x["train_cost"] <= y["train_cost"] else y
             for x, y in zip(own["coulomb_friction"]["heldout_folds"], own["yield_softening"]["heldout_folds"])]
    assert fr["heldout_rmse"] == pytest.approx(pooled_heldout(folds), rel=1e-12)
    assert min(own[m]["rmse"] for m in cands) == fr["rmse"]          # the better all-data fit, for both
    assert d["effect"] == "coulomb_friction ≡ yield_softening"
    again = diagnose(exps, "displacement", fmu_path=fmu_path, workers=1, candidates=cands,
                     cache_dir=cache_root / "pair")                   # every fit from the cache
    assert [(r["effect"], r["heldout_rmse"], r["rmse"]) for r in again["ranking"]] == \
        [(r["effect"], r["heldout_rmse"], r["rmse"]) for r in d["ranking"]]
    # the mapped member's parameters predict, through the FMU, what the lead's fit predicts
    lead = d["lead"]
    other = next(m for m in d["group"] if m != lead)
    preds = []
    for params in (d["group"][other]["params"], d["extended"]["params"]):
        runner = ModelRunner(fmu_path, "displacement", list(params))
        try:
            preds.append(runner.predict(list(params.values()), exps))
        finally:
            runner.close()
    peak = max(float(np.max(np.abs(e.force))) for e in exps)
    assert max(float(np.max(np.abs(a - b))) for a, b in zip(*preds)) < 1e-4 * peak


def test_zz_identifiability_table_is_written(ci_outcomes):
    """out/identifiability.md: the tables (✓ run in CI, ○ run with --run-slow) and what the tool said in each
    cell that ran in this session; every cell that ran agreed with its statement (the tests above)."""
    out = ROOT / "out"
    out.mkdir(exist_ok=True)
    lines = ["Identifiability (tests/test_identifiability.py; ✓ = run through the FMU by every `make test`, ○ = "
             "run with `--run-slow`, `make identifiability`):\n", tables(), "\nWhat the tool said (cells run in this "
             "session):\n", "| cell | seed | named | cannot tell (look-alike: separating test) | s | agrees |",
             "|---|---|---|---|---|---|"]
    for cell in CELLS:
        o = OUTCOMES.get(cell)
        if o is None:
            continue
        cannot = "; ".join(f"{i['effect']}: {i['separating_test'][:70]}" for i in o["indistinguishable"]
                           if i["reason"].startswith("cannot tell")) or "–"
        lines.append(f"| {cell.id} | {o['seed']} | `{o['effect']}` | {cannot.replace('|', '/')} | "
                     f"{o['seconds']:.1f} | {'yes' if not problems(cell, o) else 'NO'} |")
    (out / "identifiability.md").write_text("\n".join(lines) + "\n")
    (out / "identifiability.json").write_text(json.dumps({c.id: o for c, o in OUTCOMES.items()}, indent=1))
    print("\n" + tables())
