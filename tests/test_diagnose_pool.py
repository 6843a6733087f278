"""The diagnosis's pool of fit workers survives an FMU that crashes: one candidate fails, naming itself.

A real crash, nothing mocked: tests/fmus/crash (any model description's variables, abort() as its first
run starts) is built with the ScrewVertebra model description and fitted as one candidate next to two
candidates on the real FMU, in a pool of two worker processes. Its crash breaks the pool; the candidates
that did not crash must still get the fits a run without it gives.
"""
from __future__ import annotations

import re
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import effects_reference as er  # noqa: E402
from c_fmus import compile_linux64, zip_tree  # noqa: E402


from fmusa.diagnose.budget import RunBudget  # noqa: E402
from fmusa.diagnose.calibrate import Fit  # noqa: E402
from fmusa.diagnose.fitcache import run_fits  # noqa: E402
from fmusa.diagnose.measured import Experiment, downsample  # noqa: E402
from fmusa.diagnose.models import resolve  # noqa: E402

CRASH_C = Path(__file__).resolve().parent / "fmus" / "crash" / "crash.c"


def build_crash_fmu(root: Path, description_from: Path, defines: tuple[str, ...] = ()) -> Path:
    """tests/fmus/crash with the model description of ``description_from`` (its sources left out), zipped as
    ``root``/Crash.fmu."""
    tree = root / "tree"
    compile_linux64(CRASH_C, tree / "binaries" / "linux64" / "Crash.so", defines, "crash FMU")
    with zipfile.ZipFile(description_from) as z:
        xml = z.read("modelDescription.xml").decode("utf-8")
    xml = re.sub(r'modelIdentifier="[^"]*"', 'modelIdentifier="Crash"', xml)
    xml = re.sub(r"\s*<SourceFiles>.*?</SourceFiles>", "", xml, flags=re.S)
    (tree / "modelDescription.xml").write_text(xml, encoding="utf-8")
    return zip_tree(tree, root / "Crash.fmu")


@pytest.fixture(scope="module")
def experiment():
    df, _ = er.synthesize("sensor_offset", "force", seed=7)
    e = Experiment(name="offset", path=Path("offset.csv"), drive="force", t=df.time.values,
                   displacement=df.displacement.values, force=df.force.values)
    return downsample(e, 30)


def assert_same_fit(a: Fit, b: Fit) -> None:
    """The same fit but for its run counts: the first fit of each process spends two runs on the choice of the
    Jacobian's method (:meth:`ModelRunner.sensitivities_pay`)."""
    for k in ("effect", "n", "k", "starts_tried", "at_bounds", "heldout_skipped"):
        assert getattr(a, k) == getattr(b, k), k
    assert a.params.keys() == b.params.keys()
    pairs = {"params": (list(a.params.values()), list(b.params.values())), "rss": (a.rss, b.rss),
             "rmse": (a.rmse, b.rmse), "heldout_rmse": (a.heldout_rmse, b.heldout_rmse),
             "predictions": (np.concatenate(a.predictions), np.concatenate(b.predictions))}
    for k, (x, y) in pairs.items():
        np.testing.assert_allclose(x, y, rtol=1e-6, atol=0, err_msg=k)


def _job(fmu: Path, name: str, experiment, interface) -> tuple:
    return (str(fmu), name, "force", [experiment], 1, interface, 1, 0)


def test_a_crashing_candidate_fails_alone_and_the_others_keep_their_fits(fmu_path, experiment, tmp_path):
    crash = build_crash_fmu(tmp_path, fmu_path)
    interface = resolve(None, str(fmu_path))
    good = [_job(fmu_path, name, experiment, interface) for name in ("none", "sensor_offset")]
    bad = _job(crash, "backlash_gap", experiment, interface)

    budget = RunBudget()
    t0 = time.monotonic()
    got = run_fits([good[0], bad, good[1]], 2, tmp_path / "cache", "k", False, budget)
    took = time.monotonic() - t0
    alone = run_fits(good, 1, None, "k", False)

    assert took < 120, f"the supervised pool took {took:.1f} s"
    for name in ("none", "sensor_offset"):
        assert isinstance(got[name], Fit), got[name]
        assert_same_fit(got[name], alone[name])
        assert (tmp_path / "cache" / f"{name}.json").is_file()     # saved as it finished
    why = got["backlash_gap"]
    assert isinstance(why, str) and not isinstance(why, Fit)
    assert "'backlash_gap'" in why and "SIGABRT" in why and "exit code -6" in why, why
    assert f"fmusa inspect {crash}" in why and "leave backlash_gap out" in why and "--candidates" in why, why
    assert "BrokenProcessPool" not in why
    # the run budget is one counter across the fresh pools: every run of the good fits, the crashed fit's
    # first run (twice: it crashed its first process, then one of its own), and the runs a good fit had
    # made when the crash stopped its process (it ran again, whole, in a process of its own)
    spent = sum(sum(got[name].runs.values()) for name in ("none", "sensor_offset"))
    assert spent + 2 <= budget.used <= 2 * spent + 2, (budget.used, spent)
    print(f"\nsupervised pool with one crashing candidate: {took:.1f} s\nmessage: {why}")


def test_a_segfault_is_named_too(fmu_path, experiment, tmp_path):
    """SIGSEGV, the other crash exports die of; two candidates only, so the pool breaks on the first try."""
    crash = build_crash_fmu(tmp_path, fmu_path, ("CRASH_SEGV",))
    interface = resolve(None, str(fmu_path))
    got = run_fits([_job(crash, "backlash_gap", experiment, interface),
                    _job(crash, "sensor_offset", experiment, interface)], 2, None, "k", False)
    for name in ("backlash_gap", "sensor_offset"):
        assert "SIGSEGV" in got[name] and "exit code -11" in got[name] and repr(name) in got[name], got
