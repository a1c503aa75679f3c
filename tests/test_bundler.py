"""Bundler ``bundle.out`` files: the camera model against a direct projection, the BAL
problem of the same block, round trips (colours, keypoints, cameras not reconstructed) and
malformed files."""

from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli

import sapgo
from sapgo.formats.bal import import_bal, read_bal, rodrigues
from sapgo.formats.bundler import (
    bundler_cost,
    export_bundler,
    import_bundler,
    read_bundler,
    write_bundler,
)
from sapgo.geometry import project
from sapgo.project import STATUS_ACTIVE, Project

DUBROVNIK = Path(__file__).parent / "data" / "dubrovnik-3-7-pre.txt.gz"


def _bal_as_bundler(path, out, drop=None):
    """The BAL problem as a Bundler file (rotation matrices), a camera ``drop`` written as
    not reconstructed (zeros) with its observations left out; colours and keys made up."""
    d = read_bal(path)
    cams = d["cameras"]
    r, t, fk = rodrigues(cams[:, :3]), cams[:, 3:6].copy(), cams[:, 6:9].copy()
    keep = np.ones(len(d["obs_camera"]), bool)
    if drop is not None:
        r[drop], t[drop], fk[drop] = 0.0, 0.0, 0.0
        keep = d["obs_camera"] != drop
    rng = np.random.default_rng(3)
    colors = rng.integers(0, 256, (len(d["points"]), 3), dtype=np.uint8)
    keys = rng.integers(0, 5000, keep.sum())
    write_bundler(out, r, t, fk, d["points"], colors, d["obs_camera"][keep],
                  d["obs_point"][keep], keys, d["obs_xy"][keep])
    return d, colors, keys, keep


def test_the_camera_model_is_bundlers(tmp_path):
    """Every imported observation's sapgo projection equals Bundler's own: ``P = R X + t``,
    ``p = -P / P_z`` (the camera looks down -z), ``f (1 + k1 |p|^2 + k2 |p|^4) p``, pixels
    from the image centre with y up; the file's cost is BAL's."""
    f = tmp_path / "bundle.out"
    d, _, _, _ = _bal_as_bundler(DUBROVNIK, f)
    b = read_bundler(f)
    cost = 0.0
    for c, j, xy in zip(b["obs_camera"], b["obs_point"], b["obs_xy"]):
        p = b["rotations"][c] @ b["points"][j] + b["translations"][c]
        q = -p[:2] / p[2]
        fl, k1, k2 = b["fk"][c]
        r2 = q @ q
        cost += 0.5 * float(((fl * (1 + k1 * r2 + k2 * r2 * r2) * q - xy) ** 2).sum())
    assert bundler_cost(b) == pytest.approx(cost, rel=1e-12)
    from sapgo.formats.bal import bal_cost

    assert cost == pytest.approx(bal_cost(d), rel=1e-9)
    r = import_bundler(f, tmp_path / "b.h5", intrinsics="fixed")
    assert r["initial_cost"] == pytest.approx(cost, rel=1e-12)
    from sapgo.geometry import camera_array

    with Project(tmp_path / "b.h5") as p:
        st, pt, ob = p.read("stations"), p.read("points"), p.read("observations")
        rows = camera_array(p.cameras())[st["camera"]]
        assert p.attr("image_unit") == "px" and p.attr("datum") == "free"
    v = np.array([project(st["eo"][s], pt["xyz"][q], rows[s]) for s, q in
                  zip(ob["station"], ob["point"])]) - np.column_stack([ob["x"], ob["y"]])
    assert 0.5 * (v ** 2).sum() == pytest.approx(cost, rel=1e-9)


def test_bundler_and_bal_of_one_block_adjust_alike(tmp_path):
    """The same block as a BAL problem and as a Bundler file: the same adjustment."""
    f = tmp_path / "bundle.out"
    _bal_as_bundler(DUBROVNIK, f)
    import_bal(DUBROVNIK, tmp_path / "a.h5", intrinsics="fixed")
    import_bundler(f, tmp_path / "b.h5", intrinsics="fixed")
    opts = sapgo.Options(progress=False, max_iterations=30, tol_cost=1e-14)
    sa = sapgo.adjust(tmp_path / "a.h5", opts)
    sb = sapgo.adjust(tmp_path / "b.h5", opts)
    assert sb.final_cost == pytest.approx(sa.final_cost, rel=1e-9)
    assert sb.final_cost < sb.initial_cost / 10
    with Project(tmp_path / "a.h5") as a, Project(tmp_path / "b.h5") as b:
        np.testing.assert_allclose(b.read("points")["xyz"] + b.solution("point_corr"),
                                   a.read("points")["xyz"] + a.solution("point_corr"),
                                   rtol=1e-6, atol=1e-6)


def test_round_trip_keeps_colours_keys_and_cameras_not_reconstructed(tmp_path, capsys):
    f = tmp_path / "bundle.out"
    d, colors, keys, keep = _bal_as_bundler(DUBROVNIK, f, drop=1)
    code, text, err = run_cli(capsys, "import", "--format", "bundler", "--fixed-intrinsics",
                              f, tmp_path / "b.h5")
    assert code == 0 and "1 camera(s) not reconstructed" in text, err
    with Project(tmp_path / "b.h5") as p:
        assert sorted(p.read("stations")["id"].tolist()) == [0, 2]
    code, text, err = run_cli(capsys, "export", tmp_path / "b.h5", tmp_path / "in.out",
                              "--format", "bundler")
    assert code == 0, err
    a, b = read_bundler(f), read_bundler(tmp_path / "in.out")
    assert b["reconstructed"].tolist() == [True, False, True]
    np.testing.assert_allclose(b["rotations"], a["rotations"], atol=1e-14)
    for key in ("translations", "fk", "points", "obs_xy"):
        np.testing.assert_allclose(b[key], a[key], rtol=1e-12, atol=1e-12, err_msg=key)
    for key in ("colors", "obs_camera", "obs_point", "obs_key"):
        np.testing.assert_array_equal(b[key], a[key], err_msg=key)
    # adjusted, exported, imported: it starts where the adjustment ended (all three
    # cameras: two would leave no redundancy)
    _bal_as_bundler(DUBROVNIK, tmp_path / "all.out")
    import_bundler(tmp_path / "all.out", tmp_path / "all.h5", intrinsics="fixed")
    code, text, err = run_cli(capsys, "adjust", tmp_path / "all.h5", "--no-progress",
                              "--json", tmp_path / "r.json", "--quiet")
    assert code == 0, err
    import json

    final = json.loads((tmp_path / "r.json").read_text())["final_cost"]
    export_bundler(tmp_path / "all.h5", tmp_path / "out.out", adjusted=True)
    out = read_bundler(tmp_path / "out.out")
    assert bundler_cost(out) == pytest.approx(final, rel=1e-9)
    # (the colours and keys went through the ordering and the commit)
    full = read_bundler(tmp_path / "all.out")
    np.testing.assert_array_equal(out["colors"], full["colors"])
    np.testing.assert_array_equal(out["obs_key"], full["obs_key"])
    again = import_bundler(tmp_path / "out.out", tmp_path / "again.h5", intrinsics="fixed")
    assert again["initial_cost"] == pytest.approx(final, rel=1e-9)


def test_a_generated_block_goes_out_and_comes_back(tmp_path):
    """A generated block (no principal point or distortion) as a Bundler file: its photos,
    points and image coordinates come back; a block of another origin gets grey points and
    each photo's observations numbered as keypoints."""
    src = tmp_path / "g.h5"
    sapgo.generate_block(src, strips=2, photos_per_strip=4, progress=False, seed=2)
    export_bundler(src, tmp_path / "g.out", adjusted=False)
    g = read_bundler(tmp_path / "g.out")
    assert (g["colors"] == 128).all()
    for c in np.unique(g["obs_camera"]):
        assert sorted(g["obs_key"][g["obs_camera"] == c]) == list(range(
            int((g["obs_camera"] == c).sum())))
    import_bundler(tmp_path / "g.out", tmp_path / "b.h5")
    with Project(src) as a, Project(tmp_path / "b.h5") as b:
        sa, sb = a.read("stations"), b.read("stations")
        ia = np.argsort(sa["id"])
        np.testing.assert_allclose(sb["eo"][:, 3:], sa["eo"][ia, 3:], rtol=1e-13)
        from sapgo.frames import rotation_matrices

        np.testing.assert_allclose(rotation_matrices(sb["eo"][:, :3]),
                                   rotation_matrices(sa["eo"][ia, :3]), atol=1e-14)
        pa, pb = a.read("points"), b.read("points")
        live = pa["status"] == STATUS_ACTIVE
        np.testing.assert_array_equal(pb["xyz"], pa["xyz"][live][np.argsort(pa["id"][live])])
        oa, ob = a.read("observations"), b.read("observations")
        assert len(ob) == int(((oa["status"] == STATUS_ACTIVE) & live[oa["point"]]).sum())


BAD = {
    "header": ("# Bundle file v0.3\n3 7 1\n", ":2:", "two non-negative integers"),
    "short": ("# Bundle file v0.3\n1 0\n1 0 0\n", ":3:", "ends early"),
    "number": ("# Bundle file v0.3\n1 0\n1 0 x\n1 0 0\n0 1 0\n0 0 1\n0 0 0\n", ":3:",
               "'x' is not a number"),
    "rotation": ("# Bundle file v0.3\n1 0\n1 0 0\n1 0 0\n0 2 0\n0 0 1\n0 0 0\n", ":4:",
                 "not a rotation"),
    "focal": ("# Bundle file v0.3\n1 0\n-1 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 0\n", ":3:",
              "focal length"),
    "views": ("# Bundle file v0.3\n1 1\n1 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 5\n1 2 3\n"
              "1 2 3\n2 0 0 1.0 2.0\n", ":10:", "view list"),
    "camera": ("# Bundle file v0.3\n1 1\n1 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 5\n1 2 3\n"
               "1 2 3\n1 4 0 1.0 2.0\n", ":10:", "camera 4 is not one of 0..0"),
    "unreconstructed": ("# Bundle file v0.3\n2 1\n1 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 5\n"
                        + "0 0 0\n" * 5 + "1 2 3\n1 2 3\n1 1 0 1.0 2.0\n", ":15:",
                        "camera 1 was not reconstructed"),
    "colour": ("# Bundle file v0.3\n1 1\n1 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 5\n1 2 3\n"
               "1 2 300\n0\n", ":9:", "colour"),
    "key_int64": ("# Bundle file v0.3\n1 1\n1 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 5\n1 2 3\n"
                  "1 2 3\n1 0 99999999999999999999 1.0 2.0\n", ":10:",
                  "point 0: key '99999999999999999999' is outside the int64 range"),
    "key_2p64": ("# Bundle file v0.3\n1 1\n1 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 5\n1 2 3\n"
                 "1 2 3\n1 0 9223372036854775808 1.0 2.0\n", ":10:", "int64 range"),
    "tiny_focal": ("# Bundle file v0.3\n1 1\n1e-300 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 -5\n"
                   "1 2 3\n1 2 3\n1 0 0 1.0 2.0\n", ":3:",
                   "camera 0: focal length 1e-300 pixels is implausibly small"),
    "huge_translation": ("# Bundle file v0.3\n1 1\n100 0 0\n1 0 0\n0 1 0\n0 0 1\n"
                         "1e300 0 -5\n1 2 3\n1 2 3\n1 0 0 1.0 2.0\n", ":10:",
                         "point 0: its projection by camera 0 (lines 3-7) is not finite"),
    "version": ("# Bundle file v0.9\n1 0\n1 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 5\n", ":1:",
                "version '0.9': only v0.3 and v0.4 are read"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_malformed_bundler_files_name_file_and_line(tmp_path, capsys, case):
    text, line, words = BAD[case]
    f = tmp_path / "bad.out"
    f.write_text(text)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")   # (a RuntimeWarning printed is a failure too)
        code, out, err = run_cli(capsys, "import", "--format", "bundler", f,
                                 tmp_path / "x.h5")
    assert_one_line_error(code, err, f"bad.out{line}", words)
    assert not (tmp_path / "x.h5").exists()


def test_keys_are_exact_and_v04_is_read(tmp_path):
    """A keypoint index beyond 2^53 is kept exactly (as a float it would be its
    neighbour); a v0.4 file and one without a header are read, an integral key written as
    a float still taken."""
    import h5py

    big = 9007199254740993
    cam = "100 0 0\n1 0 0\n0 1 0\n0 0 1\n0 0 -5\n"
    for head in ("# Bundle file v0.4\n", "", "# Bundle file v0.3\n"):
        f = tmp_path / "k.out"
        f.write_text(f"{head}2 1\n{cam}{cam}1 2 3\n1 2 3\n2 0 {big} 1.0 2.0 1 7.0 1.5 2.5\n")
        assert read_bundler(f)["obs_key"].tolist() == [big, 7]
        import_bundler(f, tmp_path / "k.h5", force=True)
        with h5py.File(tmp_path / "k.h5", "r") as h:
            assert sorted(h["bundler/observations"]["key"].tolist()) == [7, big]
