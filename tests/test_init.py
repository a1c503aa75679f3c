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


def _convergent(tmp_path, seed=3):
    """A close-range block: 10 photos on a ring 30 m around a 10 m box of 60 points, looking
    at it 40 degrees down (tilts far from vertical), 12 full control points on the box's
    corners and edges; returned with true approximations (ref) and with none (per: photos
    at the origin, points at 0)."""
    from conftest import read_records, rewrite
    from sapgo.frames import opk_of
    from sapgo.geometry import camera_array, project

    rng = np.random.default_rng(seed)
    base = tmp_path / "base.h5"
    sapgo.generate_block(base, strips=2, photos_per_strip=3, control_points=4, progress=False)
    rec = read_records(base)
    cams = rec["cameras"][:1].copy()
    cams["focal_length"], cams["format_x"], cams["format_y"] = 24.0, 36.0, 24.0
    cams["sigma_image"] = 0.002
    cams[["k1", "k2", "k3", "p1", "p2"]] = 0.0
    n_ph = 10
    ring = np.linspace(0, 2 * np.pi, n_ph, endpoint=False) + 0.1
    centres = np.column_stack([30 * np.cos(ring), 30 * np.sin(ring),
                               25 * np.tan(np.radians(40)) * np.ones(n_ph)])
    eo = np.zeros((n_ph, 6))
    for i, c in enumerate(centres):
        w = c / np.linalg.norm(c)                       # backwards: away from the box
        u = np.cross([0.0, 0.0, 1.0], w)
        u /= np.linalg.norm(u)
        v = np.cross(w, u)
        eo[i, :3] = opk_of(np.array([u, v, w])[None])[0]
        eo[i, 3:] = c
    pts = rng.uniform(-5, 5, (60, 3))
    face = rng.integers(0, 3, 60)
    pts[np.arange(60), face] = np.sign(pts[np.arange(60), face]) * 5.0
    st = np.zeros(n_ph, rec["stations"].dtype)
    st["id"], st["camera"], st["strip"], st["eo"] = np.arange(1, n_ph + 1), 0, -1, eo
    row = camera_array(cams)[0]
    obs = []
    for j, x in enumerate(pts):
        for s in range(n_ph):
            xy = np.array(project(eo[s], x, row))
            if (eo[s, 3:] - x) @ (eo[s, 3:] / np.linalg.norm(eo[s, 3:])) > 20 and \
                    (np.abs(xy) < [17, 11]).all():
                obs.append((j, s, *(xy + rng.normal(0, 0.002, 2))))
    ob = np.zeros(len(obs), rec["observations"].dtype)
    o = np.array(obs)
    ob["point"], ob["station"] = o[:, 0].astype(np.int64), o[:, 1].astype(np.int64)
    ob["x"], ob["y"], ob["sigma"] = o[:, 2], o[:, 3], 0.0
    pt = np.zeros(60, rec["points"].dtype)
    pt["id"] = np.arange(100, 160)
    pt["xyz"] = pts
    ctrl = np.argsort(-np.abs(pts).sum(axis=1))[:12]   # near the corners
    pt["kind"][ctrl] = 1
    pt["control"][ctrl] = pts[ctrl]
    pt["control_sigma"][ctrl] = 0.001
    out = {"cameras": cams, "stations": st, "points": pt, "observations": ob,
           "station_priors": rec["station_priors"][:0], "truth": None}
    ref = tmp_path / "ref.h5"
    rewrite(ref, out)
    st_p = st.copy()
    st_p["eo"] = 0.0
    pt_p = pt.copy()
    pt_p["xyz"] = 0.0
    per = tmp_path / "per.h5"
    rewrite(per, dict(out, stations=st_p, points=pt_p))
    return ref, per


def test_init_resects_a_convergent_block_into_the_adjustment(tmp_path, capsys):
    """A convergent block, its photos 40 degrees off the vertical and with no starting
    values at all: auto picks the resection start, every photo is placed, and the adjustment
    from it equals the one from the true values."""
    ref, per = _convergent(tmp_path)
    code, out, err = run_cli(capsys, "init", per)
    assert code == 0 and "placed 10 of 10 photos" in out and "resection start" in out, err
    s_ref = sapgo.adjust(ref, sapgo.Options(progress=False))
    s = sapgo.adjust(per, sapgo.Options(progress=False))
    assert s.converged and s.sigma0 == pytest.approx(s_ref.sigma0, rel=1e-9)
    a, b = _adjusted(ref), _adjusted(per)
    np.testing.assert_allclose(b[3][np.argsort(b[2])], a[3][np.argsort(a[2])], rtol=0,
                               atol=1e-6)
