"""Generated blocks with a random texture of tie points (``--points-per-photo``)."""

import numpy as np
import pytest

import sapgo
from sapgo.geometry import camera_array, project
from sapgo.project import Project

from conftest import assert_one_line_error, run_cli


def _records(path):
    with Project(path) as p:
        return (p.read("points"), p.read("observations"), p.read("truth/points")["xyz"],
                p.read("truth/stations")["eo"], camera_array(p.cameras()))


def test_every_photo_that_holds_a_point_measures_it(tmp_path):
    """Against the obvious reference: each true point projected into every photo; the
    photos whose format (less the 1 mm margin) holds it are exactly its observations, and
    the points on fewer than two photos are left out."""
    path = tmp_path / "t.h5"
    info = sapgo.generate_block(path, strips=3, photos_per_strip=8, points_per_photo=40,
                                control_points=6, sigma_image=0.0, progress=False)
    pts, obs, xyz, eo, cams = _records(path)
    assert info["points"] == len(pts) and info["observations"] == len(obs)
    half = 230.0 / 2 - 1.0
    for j in range(len(pts)):
        seen = []
        for s in range(len(eo)):
            x, y = project(eo[s], xyz[j], cams[0])
            if abs(x) < half and abs(y) < half:
                seen.append((s, x, y))
        o0, n = int(pts["obs_start"][j]), int(pts["n_obs"][j])
        got = obs[o0:o0 + n]
        assert n >= 2 and (got["point"] == j).all()
        assert got["station"].tolist() == [s for s, _, _ in seen]
        np.testing.assert_allclose(np.column_stack([got["x"], got["y"]]),
                                   [(x, y) for _, x, y in seen], atol=1e-9)


def test_density_determinism_and_control(tmp_path):
    """About N points on a photo inside the block, the same file from the same seed, the
    control points asked for."""
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    for path in (a, b):
        info = sapgo.generate_block(path, strips=4, photos_per_strip=30, points_per_photo=60,
                                    control_points=12, progress=False)
    pa, oa, _, _, _ = _records(a)
    pb, ob, _, _, _ = _records(b)
    np.testing.assert_array_equal(pa, pb)
    np.testing.assert_array_equal(oa, ob)
    assert info["control_points"] == 12
    per_photo = np.bincount(oa["station"], minlength=120).reshape(4, 30)
    inner = per_photo[1:-1, 2:-2]   # (the block's edges see fewer)
    assert 0.85 * 60 < inner.mean() < 1.15 * 60
    rays = pa["n_obs"]
    assert rays.min() >= 2 and 2.5 < rays.mean() < 4.5


def test_a_texture_block_adjusts_to_its_truth(tmp_path):
    path = tmp_path / "t.h5"
    sapgo.generate_block(path, strips=3, photos_per_strip=12, points_per_photo=30,
                         control_points=8, progress=False)
    s = sapgo.adjust(path, sapgo.Options(progress=False))
    assert s.converged and 0.9 < s.sigma0 < 1.1
    assert s.truth["points"]["sxy"] < 0.5 and s.truth["points"]["sz"] < 1.0


@pytest.mark.parametrize("args, says", [
    (["--points-per-photo", "3"], "points per photo must be between 4 and 5000, not 3"),
    (["--points-per-photo", "50", "--pattern", "25"],
     "points per photo and the 25-point pattern exclude each other"),
])
def test_bad_points_per_photo_is_one_line(tmp_path, capsys, args, says):
    code, _, err = run_cli(capsys, "generate", tmp_path / "x.h5", *args)
    assert_one_line_error(code, err, says)
    assert not (tmp_path / "x.h5").exists()
