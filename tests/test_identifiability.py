"""Which effect a test protocol can identify, and what `fmusa diagnose` says where it cannot.

Real protocols differ: one rate or several, with or without a hold, with or without unloading
(``effects_reference.PROTOCOLS``). From the physics of fmu/MODEL.md, :func:`expected` states for every
effect and protocol (displacement drive) whether the effect is identifiable there, or which look-alike
hides it and which test would separate them. The FMU runs of :data:`CHECKED` (a representative set of
cells, within the CI budget) require that the tool names the effect where it is identifiable, and says
"cannot tell, because ..." with the separating test where it is not. ``coulomb_friction`` and
``yield_softening`` are the same equations (``EQUIVALENT_BY_CONSTRUCTION``): where identifiable, they are
named together, "coulomb_friction ≡ yield_softening". The table is written to out/identifiability.md (and
is the one in the README).
"""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import effects_reference as er  # noqa: E402

from fmusa.diagnose.effects import CANDIDATES, EQUIVALENT_BY_CONSTRUCTION, equivalent_parameters  # noqa: E402
from fmusa.diagnose.measured import Experiment, downsample  # noqa: E402
from fmusa.diagnose.rank import GROUP_SEP, group_members  # noqa: E402
from fmusa.diagnose.run import diagnose  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DRIVE = "displacement"
#: the candidates of the FMU runs (the look-alikes of each other; fewer candidates keep the runs short)
RUN_CANDIDATES = ("coulomb_friction", "yield_softening", "viscoelastic_relaxation", "nonlinear_stiffness")


def equivalents(effect: str) -> set[str]:
    """The effect and those that are the same equations."""
    out = {effect}
    for pair in EQUIVALENT_BY_CONSTRUCTION:
        if effect in pair:
            out |= set(pair)
    return out


def expected(effect: str, protocol: str) -> dict:
    """Identifiable here (named), or the look-alike that hides it, why, and the word its separating test
    must contain. From the physics of fmu/MODEL.md, displacement drive:

    * friction: on constant-rate ramps a rate-independent force equals a viscous one d_y*v, and a reversal at
      the same rate flips both; only a hold (friction keeps its force) or a second rate separates them;
    * yield softening and a softening nonlinear stiffness bend the loading curve alike; only unloading
      (elastic retraces, yield leaves a set) separates them;
    * a Maxwell branch at one rate without a hold is a smooth softening (or, with a short time constant, a
      damping): a hold (relaxation) or a second rate separates it;
    * a force bias on one ramp equals a damping force; a hold or an unloading separates them;
    * slack (a zero-force band from zero) shows on every loading from rest.
    """
    several, hold, unload = er.PROTOCOLS[protocol]
    if effect == "coulomb_friction":
        ok, hider, word, why = hold or several, "damping d_y (baseline) or a Maxwell branch", "hold", \
            "friction on constant-rate ramps equals a viscous force"
    elif effect == "yield_softening":
        ok, hider, word, why = unload, "nonlinear_stiffness", "unload", "yield and an elastic bend load alike"
    elif effect == "nonlinear_stiffness":
        ok, hider, word, why = unload, "yield_softening", "unload", "yield and an elastic bend load alike"
    elif effect == "viscoelastic_relaxation":
        ok, hider, word, why = hold or several, "nonlinear_stiffness, or friction / damping", "hold", \
            "at one rate without a hold relaxation is a smooth softening"
    elif effect == "sensor_offset":
        ok, hider, word, why = hold or several or unload, "damping d_y (baseline)", "hold", \
            "a force bias on one ramp equals a damping force"
    elif effect == "backlash_gap":
        ok, hider, word, why = True, None, None, ""
    else:
        raise ValueError(effect)
    return {"identifiable": ok, "named": equivalents(effect) if ok else None, "look_alike": None if ok else hider,
            "separating_word": None if ok else word, "why": None if ok else why}


#: (effect, protocol, seed): the cells run through the FMU (about 15 s each on two cores).
CHECKED = [
    ("coulomb_friction", "load-hold-unload", 1),
    ("coulomb_friction", "ramp", 1),
    ("coulomb_friction", "load-unload", 1),
    ("coulomb_friction", "load-unload, 2 rates", 1),
    ("viscoelastic_relaxation", "ramp", 2),
    ("viscoelastic_relaxation", "ramp-hold", 2),
    ("yield_softening", "ramp-hold", 3),
    ("nonlinear_stiffness", "load-unload", 4),
]


def _cell(effect: str, protocol: str) -> str:
    e = expected(effect, protocol)
    checked = " ✓" if any(c[0] == effect and c[1] == protocol for c in CHECKED) else ""
    if e["identifiable"]:
        names = sorted(e["named"])
        return ("named" if len(names) == 1 else "named as " + GROUP_SEP.join(f"`{n}`" for n in names)) + checked
    return f"cannot tell: {e['look_alike']} ({e['separating_word']} separates)" + checked


def table() -> str:
    """The identifiability table (markdown): effect x protocol, displacement drive."""
    protos = list(er.PROTOCOLS)
    lines = ["| effect | " + " | ".join(protos) + " |", "|---|" + "---|" * len(protos)]
    for eff in CANDIDATES:
        lines.append(f"| `{eff}` | " + " | ".join(_cell(eff, p) for p in protos) + " |")
    return "\n".join(lines) + "\n"


def test_identifiability_table_is_written():
    """The table covers every candidate and protocol and is written for the README."""
    text = table()
    assert text.count("\n") == 2 + len(CANDIDATES)
    for p in er.PROTOCOLS:
        assert p in text
    out = ROOT / "out"
    out.mkdir(exist_ok=True)
    (out / "identifiability.md").write_text(
        "Identifiability (displacement drive; ✓ = checked by an FMU run in tests/test_identifiability.py, the "
        "other cells from the physics):\n\n" + text)
    print("\n" + text)


def test_protocols_have_their_features():
    """The synthetic protocols have what their names say, as the diagnosis detects it."""
    from fmusa.diagnose.rank import protocol_features

    for name, (several, hold, unload) in er.PROTOCOLS.items():
        frames, _ = er.synthesize_protocol("none", DRIVE, 5, name)
        exps = [Experiment(name=f"r{i}", path=Path("x.csv"), drive=DRIVE, t=df.time.values,
                           displacement=df.displacement.values, force=df.force.values) for i, df in enumerate(frames)]
        f = protocol_features(exps)
        assert (f["several_rates"], f["hold"], f["unloading"]) == (several, hold, unload), name


def test_friction_and_yield_are_the_same_equations():
    """The mapping of EQUIVALENT_BY_CONSTRUCTION gives the same force for any history (scipy reference),
    and maps back."""
    import numpy as np

    fr = {"c_y": 2e5, "d_y": 300.0, "fric_F": 20.0, "fric_x": 2e-5}
    yi = equivalent_parameters("coulomb_friction", fr, "yield_softening")
    back = equivalent_parameters("yield_softening", yi, "coulomb_friction")
    assert all(abs(back[k] - fr[k]) <= 1e-12 * abs(fr[k]) for k in fr)
    kt = np.array([0.0, 1.0, 1.5, 2.5, 3.0, 4.0])
    ku = np.array([0.0, 1e-3, 0.4e-3, 0.9e-3, -0.5e-3, 0.2e-3])
    t = np.linspace(0, 4, 801)
    a = er.simulate(fr, DRIVE, kt, ku, t)
    b = er.simulate(yi, DRIVE, kt, ku, t)
    assert np.max(np.abs(a - b)) < 1e-6 * np.max(np.abs(a))


def _experiments(effect: str, protocol: str, seed: int):
    frames, truth = er.synthesize_protocol(effect, DRIVE, seed, protocol)
    exps = [downsample(Experiment(name=f"rate{i}", path=Path(f"rate{i}.csv"), drive=DRIVE, t=df.time.values,
                                  displacement=df.displacement.values, force=df.force.values), 150)
            for i, df in enumerate(frames)]
    return exps, truth


@pytest.mark.parametrize("effect,protocol,seed", CHECKED, ids=[f"{c[0]}|{c[1]}" for c in CHECKED])
def test_named_where_identifiable_else_cannot_tell(effect, protocol, seed, fmu_path):
    exps, truth = _experiments(effect, protocol, seed)
    d = diagnose(exps, DRIVE, fmu_path=fmu_path, workers=2, candidates=RUN_CANDIDATES)
    e = expected(effect, protocol)
    members = set(group_members(d["effect"]))
    scores = {r["effect"]: (r["significant"], round(r["heldout_rmse_ratio"], 3)) for r in d["ranking"]}
    info = f"named {d['effect']!r}; ranking {scores}; indistinguishable {d['indistinguishable']}"
    if e["identifiable"]:
        assert members == e["named"] & (set(RUN_CANDIDATES) | {effect}), info
        return
    # not identifiable: never named alone without a word; the tool says "cannot tell, because ..." and gives
    # a separating test of the expected kind, naming the hidden effect among the look-alikes
    cannot = [i for i in d["indistinguishable"] if i["reason"].startswith("cannot tell, because")]
    assert cannot, info
    assert effect in members | {i["effect"] for i in cannot}, info
    assert any(e["separating_word"] in i["separating_test"] for i in cannot), info
