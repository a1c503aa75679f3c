"""Generated scenes of SAPGO-MFL (seeds/002 Table 5): counts, band width, adjustment."""

import numpy as np

import sapgo
from conftest import read_records
from sapgo.project import KIND_HORIZONTAL, KIND_VERTICAL, Project


def test_mfl1_preset_counts_band_width_and_adjustment(tmp_path):
    path = tmp_path / "mfl1.h5"
    info = sapgo.generate_block(path, preset="sapgo-mfl-1")
    assert (info["photos"], info["strips"], info["cameras"], info["points"]) == (273, 16, 6,
                                                                                1771)
    with Project(path) as p:
        cams = p.cameras()
        st = p.read("stations")
        pt = p.read("points")
        ob = p.read("observations")
    assert len(np.unique(st["camera"])) == 6 and (cams["k1"] != 0).all()
    assert (cams["sigma_image"] == 0.020).all()
    kinds = dict(zip(*np.unique(pt["kind"], return_counts=True)))
    assert kinds[KIND_HORIZONTAL] == 40 + 85 and kinds[KIND_VERTICAL] == 125
    assert (pt["n_obs"] >= 2).all() and len(ob) == pt["n_obs"].sum()
    # the same seed gives the same file contents
    again = tmp_path / "again.h5"
    sapgo.generate_block(again, preset="sapgo-mfl-1")
    a, b = read_records(path), read_records(again)
    for k in ("cameras", "stations", "points", "observations"):
        assert a[k].tobytes() == b[k].tobytes(), k
    info = sapgo.order_project(path)
    assert info.band_width <= 32  # Table 5: 32
    s = sapgo.adjust(path, sapgo.Options(progress=False))
    assert s.converged and 0.9 < s.sigma0 < 1.1
    assert s.n_cameras == 6
    assert s.truth["points"]["sxy"] < 6.0 and s.truth["points"]["sz"] < 4.0
    sc = s.strip_comparison
    assert len(sc["pairs"]) >= 15 and sc["weighted_average"]["n"] > 300


def test_mfl2_crossing_lines_two_heights_and_band_width(tmp_path):
    path = tmp_path / "mfl2.h5"
    info = sapgo.generate_block(path, preset="sapgo-mfl-2")
    assert (info["photos"], info["cameras"], info["points"]) == (167, 4, 1457)
    with Project(path) as p:
        st = p.read("stations")
    angles = set()
    for s in np.unique(st["strip"]):
        xy = st["eo"][st["strip"] == s, 3:5]
        d = xy[-1] - xy[0]
        angles.add(int(round(np.degrees(np.arctan2(d[1], d[0])) % 180 / 45.0)) * 45 % 180)
    assert angles == {0, 90, 135}  # east-west, north-south and the diagonal line
    heights = np.round(st["eo"][:, 5], -3)
    assert set(heights.tolist()) >= {4000.0, 5000.0}  # 3700 and 5000 m: two flying heights
    assert sapgo.order_project(path).band_width <= 34  # Table 5: 34
    s = sapgo.adjust(path, sapgo.Options(progress=False))
    assert s.converged and 0.9 < s.sigma0 < 1.1 and s.n_cameras == 4


def test_apollo15_lunar_block_adjusts_on_station_priors_alone(tmp_path, capsys):
    """Apollo 15 data set 1 (Table 6): selenocentric, controlled only by station priors;
    adjusts and prints its strip comparison along east, north, up (Table 8)."""
    from conftest import run_cli
    from sapgo.frames import SELENOCENTRIC

    path = tmp_path / "a1.h5"
    info = sapgo.generate_block(path, preset="apollo15-1")
    assert (info["photos"], info["points"], info["control_points"]) == (426, 3319, 0)
    with Project(path) as p:
        assert p.frame().kind == SELENOCENTRIC and p.frame().body == "moon"
        assert p.n_priors == 426
        r = np.linalg.norm(p.read("points")["xyz"], axis=1)
        n_obs = p.read("points")["n_obs"]
    assert abs(np.median(r) - 1737400.0) < 5000.0 and n_obs.max() >= 12
    assert sapgo.order_project(path).band_width <= 32  # Table 6: 32
    code, out, err = run_cli(capsys, "adjust", path, "--no-progress", "--json",
                             tmp_path / "r.json")
    assert code == 0, err
    assert "frame: selenocentric" in out and "sE [m]" in out and "weighted average" in out
    import json

    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["converged"] and 0.9 < rep["sigma0"] < 1.1
    sc = rep["strip_comparison"]
    assert sc["axes"] == ["east", "north", "up"] and len(sc["pairs"]) >= 4
    assert 5.0 < max(sc["weighted_average"]["sigma_m"]) < 300.0
