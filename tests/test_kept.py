"""The build keeps each point's system for the update (``sapgo.adjust._kept_systems``):
the update back-solves from it instead of linearising the point again, with the same numbers
to the last bit; where the systems would not fit, or the update needs more (self-calibration,
robust weights), it linearises as before."""

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

import sapgo
from sapgo.formats.bal import import_bal
from test_inmemory import assert_same, results

DATA = Path(__file__).parent / "data"

CASES = {
    "gauss-newton": dict(),
    "levenberg-marquardt": dict(method="levenberg-marquardt"),
    "free network": dict(datum="free"),
    "snooping": dict(snooping=True),
    "self-calibration": dict(calibrate=("f", "k1"), max_iterations=30),
    "robust": dict(robust="cauchy", max_iterations=30),
}
#: cases whose updates never read kept systems (self-calibration: the step moves the border,
#: the update needs the rays' partials; robust weights: the update works them out again;
#: neither keeps them)
LINEARISED = {"self-calibration", "robust"}


def _count_kept(monkeypatch):
    """Count the update calls that were given kept systems, and those that were not."""
    module = sys.modules["sapgo.adjust"]
    seen = {"kept": 0, "linearised": 0}
    real = module.update_points_parallel

    def spy(*args):
        seen["kept" if len(args[-2]) else "linearised"] += 1   # (keep_pt: rows or none)
        return real(*args)

    monkeypatch.setattr(module, "update_points_parallel", spy)
    return seen


@pytest.mark.parametrize("case", list(CASES))
def test_update_from_kept_systems_equals_linearising_again(p1_block, tmp_path, monkeypatch,
                                                          case):
    module = sys.modules["sapgo.adjust"]
    again = tmp_path / "again.h5"
    shutil.copy(p1_block, again)
    opts = sapgo.Options(progress=False, **CASES[case])
    seen = _count_kept(monkeypatch)
    a = sapgo.adjust(p1_block, opts)
    assert (seen["kept"] == 0) == (case in LINEARISED), seen
    monkeypatch.setattr(module, "KEPT_SYSTEMS_BYTES", 0)   # (nothing fits: as before)
    seen.update(kept=0, linearised=0)
    b = sapgo.adjust(again, opts)
    assert seen["kept"] == 0 and seen["linearised"] > 0
    assert a.iterations == b.iterations and a.sigma0 == b.sigma0
    assert_same(results(p1_block), results(again))


@pytest.mark.parametrize("name, intrinsics", [("dubrovnik-3-7", "fixed"),
                                              ("problem-49-7776", "adjusted")])
def test_bal_problem_with_kept_systems_equals_linearising_again(tmp_path, monkeypatch, name,
                                                                intrinsics):
    """A BAL problem (points behind cameras allowed, Levenberg-Marquardt, a free network;
    9 parameters a photo with its intrinsics)."""
    module = sys.modules["sapgo.adjust"]
    paths = [tmp_path / "a.h5", tmp_path / "b.h5"]
    for p in paths:
        import_bal(DATA / f"{name}-pre.txt.gz", p, intrinsics=intrinsics)
    seen = _count_kept(monkeypatch)
    opts = sapgo.Options(progress=False, max_iterations=30)
    a = sapgo.adjust(paths[0], opts)
    assert seen["kept"] > 0
    monkeypatch.setattr(module, "KEPT_SYSTEMS_BYTES", 0)
    b = sapgo.adjust(paths[1], opts)
    assert a.iterations == b.iterations and a.sigma0 == b.sigma0
    for x, y in zip(results(paths[0])[:2], results(paths[1])[:2]):
        for k in x:
            np.testing.assert_array_equal(x[k], y[k], err_msg=k)


def test_systems_kept_only_within_the_budget(p1_block, monkeypatch):
    """The systems take 8 (18 a point + 3 npar an observation) bytes: kept up to
    KEPT_SYSTEMS_BYTES and a sixteenth of --memory, never for robust estimation or
    self-calibration."""
    from sapgo.adjust import _kept_systems
    from sapgo.project import Project

    module = sys.modules["sapgo.adjust"]

    class Blk:
        npar = 6
        n_border = 0

    class Calibrating(Blk):
        n_border = 7

    with Project(p1_block) as p:
        size = 8 * (18 * p.n_points + 18 * p.n_observations)
        kept = _kept_systems(p, Blk, sapgo.Options())
        assert kept[0].shape == (p.n_points, 18) and kept[1].shape == (p.n_observations, 6, 3)
        assert _kept_systems(p, Blk, sapgo.Options(robust="huber")) is None
        assert _kept_systems(p, Calibrating, sapgo.Options()) is None
        monkeypatch.setattr(module, "KEPT_SYSTEMS_BYTES", size)
        assert _kept_systems(p, Blk, sapgo.Options()) is not None
        monkeypatch.setattr(module, "KEPT_SYSTEMS_BYTES", size - 1)
        assert _kept_systems(p, Blk, sapgo.Options()) is None
        monkeypatch.setattr(module, "KEPT_SYSTEMS_BYTES", 1 << 40)   # (the budget's 16th)
        monkeypatch.setattr(module, "DEFAULT_CORE_BUDGET", 16 * size)
        assert _kept_systems(p, Blk, sapgo.Options()) is not None
        monkeypatch.setattr(module, "DEFAULT_CORE_BUDGET", 16 * size - 16)
        assert _kept_systems(p, Blk, sapgo.Options()) is None
