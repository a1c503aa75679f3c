"""``sapgo init``: starting values from the control alone reach the adjustment of the
unperturbed block."""

import shutil

import h5py
import numpy as np
import pytest
from conftest import assert_one_line_error, digest, run_cli

import sapgo
from sapgo.project import KIND_CHECK, KIND_PASS, Project


def _blocks(tmp_path, preset):
    """The preset (its check points made pass points: only the control places the block)
    and a copy whose photos are moved by up to 500 m and turned by up to 20 degrees and
    whose points have no approximations (all at 0, 0, 0)."""
    ref = tmp_path / "ref.h5"
    sapgo.generate_block(ref, preset=preset, progress=False)
    with h5py.File(ref, "r+") as f:
        pt = f["points"][...]
        pt["kind"][pt["kind"] == KIND_CHECK] = KIND_PASS
        f["points"][...] = pt
    per = tmp_path / "per.h5"
    shutil.copy(ref, per)
    rng = np.random.default_rng(7)
    with h5py.File(per, "r+") as f:
        st = f["stations"][...]
        st["eo"][:, :3] += np.radians(rng.uniform(-20, 20, (len(st), 3)))
        st["eo"][:, 3:] += rng.uniform(-500, 500, (len(st), 3))
        f["stations"][...] = st
        pt = f["points"][...]
        pt["xyz"] = 0.0
        f["points"][...] = pt
    return ref, per


def _adjusted(path):
    with Project(path) as p:
        st, pt = p.read("stations"), p.read("points")
        return (st["id"], st["eo"] + p.solution("station_corr"), pt["id"],
                pt["xyz"] + p.solution("point_corr"))


@pytest.mark.parametrize("preset", ["sapgo-p-3", "sapgo-mfl-1"])
def test_init_then_adjust_reaches_the_unperturbed_solution(tmp_path, capsys, preset):
    """SAPGO-P-3 (full control every few photos along the strip boundaries) and SAPGO-MFL-1
    (horizontal and vertical control apart, six cameras): photos 500 m and 20 degrees off,
    no point approximations; init, then adjust: the unperturbed block's adjustment."""
    ref, per = _blocks(tmp_path, preset)
    with Project(per) as p:
        n = p.n_stations
    code, out, err = run_cli(capsys, "init", per)
    assert code == 0 and f"placed {n} of {n} photos" in out, err
    with Project(per) as p:
        assert p.history()[-1]["command"] == "init"
    s_ref = sapgo.adjust(ref, sapgo.Options(progress=False))
    s = sapgo.adjust(per, sapgo.Options(progress=False))
    assert s.converged and s.sigma0 == pytest.approx(s_ref.sigma0, rel=1e-9)
    ia, ea, pa, xa = _adjusted(ref)
    ib, eb, pb, xb = _adjusted(per)
    assert (ia == ib).all() and (pa == pb).all()
    d = eb - ea
    d[:, :3] = (d[:, :3] + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(d[:, :3]).max() < 1e-9 and np.abs(d[:, 3:]).max() < 1e-5
    assert np.abs(xb - xa).max() < 1e-5


def test_init_replaces_a_solution_and_needs_control(small_block, tmp_path, capsys):
    sapgo.adjust(small_block, sapgo.Options(progress=False))
    with Project(small_block) as p:
        assert p.has_solution
    code, out, err = run_cli(capsys, "init", small_block)
    assert code == 0, err
    with Project(small_block) as p:
        assert not p.has_solution   # (its corrections referred to the old approximations)
    assert not small_block.with_name(small_block.name + ".work").exists()
    assert sapgo.adjust(small_block, sapgo.Options(progress=False)).converged
    # without control: one line, the project unchanged
    with h5py.File(small_block, "r+") as f:
        pt = f["points"][...]
        pt["kind"] = KIND_PASS
        f["points"][...] = pt
    before = digest(small_block)
    code, out, err = run_cli(capsys, "init", small_block)
    assert_one_line_error(code, err, "2 control or check points", "found 0")
    assert digest(small_block) == before
