"""Coordinate systems (pyproj): round trips, frames, and one block given in three CRSs."""

import shutil

import numpy as np
import pytest

import sapgo
from conftest import read_records
from sapgo.errors import DataError, ParameterError
from sapgo.formats.text import export_text
from sapgo.frames import LOCAL, SELENOCENTRIC, TANGENT, Frame, enu_rotation, parse_crs
from sapgo.ingest import import_text
from sapgo.project import Project

ORIGIN = (48.137, 11.575, 0.0)  # latitude, longitude (deg), height (m)


@pytest.fixture
def rng():
    return np.random.default_rng(11)


def geographic_points(rng, n=20):
    return np.column_stack([ORIGIN[1] + rng.uniform(-0.1, 0.1, n),
                            ORIGIN[0] + rng.uniform(-0.1, 0.1, n), rng.uniform(-50, 4000, n)])


@pytest.mark.parametrize("crs, scale", [("EPSG:4979", (1e-11, 1e-11, 1e-6)),
                                        ("EPSG:4978", (1e-6,) * 3),
                                        ("EPSG:32632", (1e-6,) * 3),
                                        ("EPSG:4326", (1e-11, 1e-11, 1e-6))])
def test_round_trips_through_the_tangent_frame(rng, crs, scale):
    geo = geographic_points(rng)
    frame = Frame(TANGENT, parse_crs("EPSG:4979").to_wkt(), ORIGIN)
    xyz = frame.from_user(geo)
    user = Frame(TANGENT, parse_crs(crs).to_wkt(), ORIGIN)
    given = user.to_user(xyz)  # the same points in ``crs``
    np.testing.assert_allclose(user.from_user(given), xyz, rtol=0, atol=1e-6)
    back = frame.to_user(xyz)
    assert (np.abs(back - geo) <= scale).all()


def test_the_tangent_frame_is_east_north_up_at_its_origin():
    frame = Frame(TANGENT, parse_crs("EPSG:4979").to_wkt(), ORIGIN)
    lat, lon, _ = ORIGIN
    pts = np.array([[lon, lat, 0.0], [lon, lat, 100.0], [lon + 0.001, lat, 0.0],
                    [lon, lat + 0.001, 0.0]])
    x = frame.from_user(pts)
    np.testing.assert_allclose(x[0], 0.0, atol=1e-6)
    np.testing.assert_allclose(x[1], [0, 0, 100.0], atol=1e-6)
    assert x[2, 0] > 70 and abs(x[2, 1]) < 0.01       # east
    assert x[3, 1] > 110 and abs(x[3, 0]) < 1e-6     # north
    r = enu_rotation(lat, lon)[0]
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-15)


def test_orientation_in_the_station_tangent_frame(rng):
    """A photo looking straight down at its own station (tangent omega = phi = 0) looks along
    the station's local vertical in the frame, away from the origin too."""
    frame = Frame(TANGENT, parse_crs("EPSG:4979").to_wkt(), ORIGIN)
    geo = np.array([[ORIGIN[1] + 0.3, ORIGIN[0] - 0.2, 3800.0]])
    xyz = frame.from_user(geo)
    opk = frame.opk_from_user(np.zeros((1, 3)), xyz, "tangent")
    from sapgo.frames import rotation_matrices

    axis = rotation_matrices(opk)[0].T @ np.array([0.0, 0.0, 1.0])  # camera z in the frame
    up_ground = frame.from_user(geo - [0, 0, 3800.0])
    up = (xyz - up_ground)[0] / 3800.0
    np.testing.assert_allclose(axis, up, atol=1e-9)
    assert abs(opk[0, 0]) + abs(opk[0, 1]) > 1e-3  # not vertical in the frame at the origin
    for o in ("tangent", "geocentric"):
        a = rng.normal(0, 0.1, (5, 3))
        pos = xyz.repeat(5, axis=0)
        np.testing.assert_allclose(frame.opk_to_user(frame.opk_from_user(a, pos, o), pos, o),
                                   a, atol=1e-13)


def test_bodies_and_bad_crs():
    moon = Frame.for_crs("IAU_2015:30100", np.array([[10.0, 5.0, 100000.0]]))
    assert moon.kind == SELENOCENTRIC and moon.body == "moon"
    x = moon.from_user(np.array([[0.0, 0.0, 0.0], [90.0, 0.0, 1000.0]]))
    np.testing.assert_allclose(x, [[1737400.0, 0, 0], [0, 1738400.0, 0]], atol=1e-6)
    with pytest.raises(DataError, match="different bodies"):
        moon.check_body(parse_crs("EPSG:4979"), "the control")
    with pytest.raises(ParameterError, match="unknown coordinate reference system 'EPSG:0'"):
        parse_crs("EPSG:0")
    assert Frame().kind == LOCAL and Frame.from_attrs({"frame": "local space rectangular"}
                                                      ).kind == LOCAL


# -- one block, three CRSs ---------------------------------------------------------------

def write_in_crs(src_dir, dst_dir, frame_o, crs, orientation):
    """The text files of a local block, its local frame being the tangent frame at
    ``ORIGIN``: photos and control written in ``crs`` (orientation per ``orientation``)."""
    user = Frame(TANGENT, parse_crs(crs).to_wkt(), ORIGIN)
    dst_dir.mkdir()
    for name in ("cameras.txt", "measurements.txt"):
        shutil.copy(src_dir / name, dst_dir / name)
    rows = [ln.split() for ln in open(src_dir / "photos.txt") if ln[0] != "#"]
    eo = np.array([[float(v) for v in r[3:9]] for r in rows])
    xyz = eo[:, 3:]
    opk = user.opk_to_user(np.radians(eo[:, :3]), xyz, orientation)
    pos = user.to_user(xyz)
    with open(dst_dir / "photos.txt", "w") as f:
        for r, a, p in zip(rows, np.degrees(opk), pos):
            f.write(" ".join(r[:3] + [repr(float(v)) for v in (*a, *p)]) + "\n")
    rows = [ln.split() for ln in open(src_dir / "control.txt") if ln[0] != "#"]
    c = user.to_user(np.array([[float(v) for v in r[1:4]] for r in rows]))
    with open(dst_dir / "control.txt", "w") as f:
        for r, p in zip(rows, c):
            f.write(" ".join([r[0]] + [repr(float(v)) for v in p] + r[4:]) + "\n")


def block_in_crs(block_cache, tmp_path, name="small", crs="EPSG:4979",
                 orientation="tangent", **params):
    """A generated local block (``name``, ``params`` for the generator) and the same block
    imported from text written in ``crs``: (local path, imported path, text directory)."""
    params = params or dict(strips=2, photos_per_strip=6, control_points=6)
    src = tmp_path / "local.h5"
    shutil.copy(block_cache(name, **params), src)
    d = tmp_path / "txt"
    export_text(src, d)
    dd = tmp_path / "geo"
    write_in_crs(d, dd, None, crs, orientation)
    out = tmp_path / "geo.h5"
    import_text(out, cameras=dd / "cameras.txt", photos=dd / "photos.txt",
                measurements=dd / "measurements.txt", control=dd / "control.txt", crs=crs,
                orientation=orientation)
    return src, out, dd


def adjusted_ecef(path):
    with Project(path) as p:
        pt = p.read("points")
        xyz = pt["xyz"] + p.solution("point_corr")
        frame = p.frame()
    ecef_frame = Frame(TANGENT, parse_crs("EPSG:4978").to_wkt(),
                       ORIGIN if frame.kind == LOCAL else frame.origin)
    return dict(zip(pt["id"].tolist(), ecef_frame.to_user(xyz)))


def test_one_block_in_local_geographic_and_geocentric_coordinates(block_cache, tmp_path):
    src = tmp_path / "local.h5"
    shutil.copy(block_cache("small", strips=2, photos_per_strip=6, control_points=6), src)
    rec = read_records(src)
    assert (rec["points"]["control_sigma"][rec["points"]["kind"] == 1] > 0).all()
    d = tmp_path / "txt"
    export_text(src, d)
    opts = sapgo.Options(progress=False, tol_position=1e-7, tol_angle=1e-9,
                         max_iterations=20)
    local = tmp_path / "l.h5"
    import_text(local, cameras=d / "cameras.txt", photos=d / "photos.txt",
                measurements=d / "measurements.txt", control=d / "control.txt")
    assert sapgo.adjust(local, opts).converged
    ref = adjusted_ecef(local)
    for crs, orientation in (("EPSG:4979", "tangent"), ("EPSG:4978", "geocentric")):
        dd = tmp_path / crs.replace(":", "_")
        write_in_crs(d, dd, None, crs, orientation)
        out = tmp_path / f"{crs.replace(':', '_')}.h5"
        import_text(out, cameras=dd / "cameras.txt", photos=dd / "photos.txt",
                    measurements=dd / "measurements.txt", control=dd / "control.txt",
                    crs=crs, orientation=orientation)
        with Project(out) as p:
            f = p.frame()
        assert f.kind == TANGENT and abs(f.origin[0] - ORIGIN[0]) < 0.1
        s = sapgo.adjust(out, opts)
        assert s.converged
        got = adjusted_ecef(out)
        assert got.keys() == ref.keys()
        worst = max(np.abs(got[k] - ref[k]).max() for k in ref)
        assert worst < 1e-3, (crs, worst)


def test_adjusted_results_in_the_users_crs(block_cache, tmp_path, capsys):
    """export --adjusted writes the adjusted block back in the CRS it was given in."""
    from conftest import run_cli

    _, out, _ = block_in_crs(block_cache, tmp_path)
    code, text, err = run_cli(capsys, "adjust", out, "--no-progress")
    assert code == 0 and "frame: local tangent (east, north, up at 48.1" in text, err
    code, text, err = run_cli(capsys, "export", out, tmp_path / "res", "--adjusted")
    assert code == 0, err
    pts = np.loadtxt(tmp_path / "res" / "adjusted_points.txt", usecols=(0, 1, 2, 3))
    ecef = adjusted_ecef(out)
    back = Frame(TANGENT, parse_crs("EPSG:4978").to_wkt(), ORIGIN).from_user(
        np.array([ecef[int(i)] for i in pts[:, 0]]))
    geo = Frame(TANGENT, parse_crs("EPSG:4979").to_wkt(), ORIGIN).to_user(back)
    np.testing.assert_allclose(pts[:, 1:], geo, rtol=0, atol=1e-9)
    assert 11.3 < pts[:, 1].mean() < 11.8 and 48.0 < pts[:, 2].mean() < 48.3
    ph = np.loadtxt(tmp_path / "res" / "adjusted_photos.txt")
    assert len(ph) == 12 and (np.abs(ph[:, 3:5]) < 1.0).all()  # near-vertical: degrees


def test_orientation_as_rotation_matrices(block_cache, tmp_path, capsys):
    """Photos given with rotation matrices import to the same stations as with angles; a
    matrix that is not a rotation names the line."""
    from conftest import assert_one_line_error, run_cli
    from sapgo.frames import rotation_matrices

    src = tmp_path / "local.h5"
    shutil.copy(block_cache("small", strips=2, photos_per_strip=6, control_points=6), src)
    d = tmp_path / "txt"
    export_text(src, d, angles="rad")
    rows = [ln.split() for ln in open(d / "photos.txt") if ln[0] != "#"]
    with open(d / "pm.txt", "w") as f:
        for r in rows:
            m = rotation_matrices(np.array([[float(v) for v in r[3:6]]]))[0]
            f.write(" ".join(r[:3] + [repr(float(v)) for v in m.ravel()] + r[6:9]) + "\n")
    files = dict(cameras=d / "cameras.txt", measurements=d / "measurements.txt",
                 control=d / "control.txt")
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    import_text(a, photos=d / "photos.txt", angles="rad", **files)
    import_text(b, photos_matrix=d / "pm.txt", **files)
    with Project(a) as p, Project(b) as q:
        ea, eb = p.read("stations")["eo"], q.read("stations")["eo"]
    dk = (ea[:, 2] - eb[:, 2] + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(ea[:, :2], eb[:, :2], atol=1e-14)
    np.testing.assert_allclose(dk, 0.0, atol=1e-14)
    np.testing.assert_array_equal(ea[:, 3:], eb[:, 3:])
    lines = open(d / "pm.txt").read().splitlines()
    t = lines[1].split()
    t[3] = repr(float(t[3]) * 1.01)
    lines[1] = " ".join(t)
    (d / "pm.txt").write_text("\n".join(lines) + "\n")
    code, _, err = run_cli(capsys, "import", tmp_path / "c.h5", "--photos-matrix",
                           d / "pm.txt", *[f"--{k}={v}" for k, v in files.items()])
    assert_one_line_error(code, err, "pm.txt:2", "is not a rotation")


def test_strip_comparison_of_a_block_in_a_crs_equals_its_local_twin(block_cache, tmp_path):
    """In a tangent frame the differences are turned into east, north, up at each point: the
    same as the local twin's X, Y, Z (its axes are east, north, up at the origin)."""
    src, out, _ = block_in_crs(block_cache, tmp_path, "strips3", strips=3, photos_per_strip=6,
                               control_points=8)
    opts = sapgo.Options(progress=False)
    a = sapgo.adjust(src, opts).strip_comparison
    b = sapgo.adjust(out, opts).strip_comparison
    assert a["axes"] == ["X", "Y", "Z"] and b["axes"] == ["east", "north", "up"]
    np.testing.assert_allclose(b["weighted_average"]["sigma_m"],
                               a["weighted_average"]["sigma_m"], rtol=0.02)


def test_horizontal_and_vertical_control_in_a_crs(block_cache, tmp_path):
    """Horizontal and vertical control given in EPSG:4979 (sigmas along east, north, up at
    the point) adjust to the ground points of the local twin, whose control sigmas lie along
    its axes (east, north, up at the origin): equal to the millimetre."""
    from conftest import rewrite

    src = tmp_path / "local.h5"
    shutil.copy(block_cache("small", strips=2, photos_per_strip=6, control_points=6), src)
    rec = read_records(src)
    ctrl = np.flatnonzero(rec["points"]["kind"] == 1)
    rec["points"]["kind"][ctrl[:2]] = 2                  # horizontal
    rec["points"]["control_sigma"][ctrl[:2]] = [0.02, 0.02, 0.0]
    rec["points"]["kind"][ctrl[2:4]] = 3                 # vertical
    rec["points"]["control_sigma"][ctrl[2:4]] = [0.0, 0.0, 0.03]
    rec["points"]["control_sigma"][ctrl[4:]] = [0.01, 0.02, 0.03]  # anisotropic full
    rewrite(src, rec)
    d = tmp_path / "txt"
    export_text(src, d)
    dd = tmp_path / "geo"
    truth = dict(zip(rec["truth"]["points"]["id"].tolist(), rec["truth"]["points"]["xyz"]))
    write_in_crs_partial(d, dd, truth)
    out = tmp_path / "geo.h5"
    import_text(out, cameras=dd / "cameras.txt", photos=dd / "photos.txt",
                measurements=dd / "measurements.txt", control=dd / "control.txt",
                crs="EPSG:4979")
    with Project(out) as p:
        kinds = p.read("points")["kind"]
    assert (kinds == 2).sum() == 2 and (kinds == 3).sum() == 2
    opts = sapgo.Options(progress=False, tol_position=1e-7, tol_angle=1e-9,
                         max_iterations=20)
    local = tmp_path / "l.h5"
    import_text(local, cameras=d / "cameras.txt", photos=d / "photos.txt",
                measurements=d / "measurements.txt", control=d / "control.txt")
    s1, s2 = sapgo.adjust(local, opts), sapgo.adjust(out, opts)
    assert s1.converged and s2.converged
    # the local twin's horizontal control lets the point move along the vertical at the
    # origin, the CRS one along its own vertical (1e-3 rad apart here): a few millimetres
    ref, got = adjusted_ecef(local), adjusted_ecef(out)
    worst = max(np.abs(got[k] - ref[k]).max() for k in ref)
    assert worst < 5e-3, worst
    assert s2.sigma0 == pytest.approx(s1.sigma0, rel=1e-3)
    # the residuals along east, north, up at the point are the geodetic differences: a
    # horizontal point's adjusted longitude and latitude against its control's, in metres
    from sapgo.normals import control_rotations

    with Project(out) as p:
        pt = p.read("points")
        adj = pt["xyz"] + p.solution("point_corr")
        frame = p.frame()
    lines = {int(ln.split()[0]): ln.split() for ln in open(dd / "control.txt")}
    rot = control_rotations(pt["kind"], pt["control"], frame)
    for j in np.flatnonzero(pt["kind"] == 2):
        lon, lat, _ = frame.to_user(adj[j][None])[0]
        c_lon, c_lat = float(lines[int(pt["id"][j])][1]), float(lines[int(pt["id"][j])][2])
        de = np.radians(lon - c_lon) * 6378137.0 * np.cos(np.radians(lat))
        dn = np.radians(lat - c_lat) * 6378137.0
        v = rot[j] @ (adj[j] - pt["control"][j])
        np.testing.assert_allclose(v[:2], [de, dn], rtol=0.01, atol=2e-5)
        assert np.hypot(de, dn) < 0.1
    for j in np.flatnonzero(pt["kind"] == 3):
        _, _, h = frame.to_user(adj[j][None])[0]
        v = rot[j] @ (adj[j] - pt["control"][j])
        assert v[2] == pytest.approx(h - float(lines[int(pt["id"][j])][3]), abs=1e-5)


def write_in_crs_partial(src_dir, dst_dir, truth):
    """As write_in_crs (EPSG:4979, tangent), keeping '-' for the unknown coordinates of
    horizontal and vertical control. The same constraints: a horizontal point's longitude
    and latitude, a vertical point's ellipsoidal height, all taken at the true point (a
    local vertical control fixes the height above the tangent plane at the origin, which at
    the point differs from the ellipsoidal height by the Earth's curvature)."""
    write_in_crs(src_dir, dst_dir, None, "EPSG:4979", "tangent")
    user = Frame(TANGENT, parse_crs("EPSG:4979").to_wkt(), ORIGIN)
    src = [ln.split() for ln in open(src_dir / "control.txt") if ln[0] != "#"]
    out = [ln.split() for ln in open(dst_dir / "control.txt")]
    for s, o in zip(src, out):
        unknown = [k for k in range(3) if s[1 + k] == "-"]
        if not unknown:
            continue
        x = np.array(truth[int(s[0])], float)
        for k in range(3):
            if k not in unknown:
                x[k] = float(s[1 + k])
        g = user.to_user(x[None])[0]
        for k in range(3):
            o[1 + k] = "-" if k in unknown else repr(float(g[k]))
    (dst_dir / "control.txt").write_text("\n".join(" ".join(o) for o in out) + "\n")


def test_anisotropic_sigmas_in_a_geocentric_crs_are_refused(exported_geo, tmp_path):
    d = exported_geo
    dd = tmp_path / "ecef"
    write_in_crs(d.parent / "txt", dd, None, "EPSG:4978", "geocentric")
    rows = (dd / "control.txt").read_text().splitlines()
    t = rows[0].split()
    t[4:7] = ["0.1", "0.1", "0.3"]
    rows[0] = " ".join(t)
    (dd / "control.txt").write_text("\n".join(rows) + "\n")
    with pytest.raises(DataError, match="control.txt:1: point .* geocentric CRS must be "):
        import_text(tmp_path / "x.h5", cameras=dd / "cameras.txt", photos=dd / "photos.txt",
                    measurements=dd / "measurements.txt", control=dd / "control.txt",
                    crs="EPSG:4978", orientation="geocentric")


@pytest.fixture
def exported_geo(block_cache, tmp_path):
    return block_in_crs(block_cache, tmp_path)[2]


def test_gimbal_lock_ballpark_transformations_and_orientation_names():
    from sapgo.frames import opk_of, rotation_matrices

    for phi in (np.pi / 2, -np.pi / 2):
        m = np.round(rotation_matrices(np.array([[0.3, phi, 0.5]]))[0], 9)
        np.testing.assert_allclose(rotation_matrices(opk_of(m))[0], m, atol=1e-8)
    f = Frame(TANGENT, parse_crs("EPSG:32632+5773").to_wkt(), ORIGIN)
    with pytest.raises(DataError, match="no accurate transformation"):
        f.from_user(np.array([[690000.0, 5333000.0, 500.0]]))
    g = Frame(TANGENT, parse_crs("EPSG:4979").to_wkt(), ORIGIN)
    with pytest.raises(ParameterError, match="orientation 'Tangent'"):
        g.opk_to_user(np.zeros((1, 3)), np.zeros((1, 3)), "Tangent")


def test_appending_data_of_another_body_is_refused(exported_geo, tmp_path):
    """Control of the Moon appended to an Earth block: a clear error, the project kept."""
    from conftest import digest

    d = exported_geo
    out = tmp_path / "earth.h5"
    import_text(out, cameras=d / "cameras.txt", photos=d / "photos.txt",
                measurements=d / "measurements.txt", control=d / "control.txt",
                crs="EPSG:4979")
    before = digest(out)
    (d / "moon.txt").write_text("9001 10.0 5.0 0.0 1 1 1 full\n")
    with pytest.raises(DataError, match="the appended data is given in .*Moon.*earth block"):
        import_text(out, control=d / "moon.txt", crs="IAU_2015:30100", append=True)
    with pytest.raises(ParameterError, match="must be given in a CRS"):
        import_text(out, control=d / "control.txt", append=True)
    assert digest(out) == before


def _dms(deg, hemi=None):
    """Degrees as D:M:S with 13 decimals of seconds (or D°M'S" with a hemisphere)."""
    neg = deg < 0
    a = abs(deg)
    d = int(a)
    m = int((a - d) * 60)
    s = (a - d - m / 60) * 3600
    if hemi:
        return f"{d}°{m:02d}'{s:.13f}\"{hemi[1] if neg else hemi[0]}"
    return f"{'-' if neg else ''}{d}:{m:02d}:{s:.13f}"


def test_northing_first_and_degrees_minutes_seconds_read_alike(block_cache, tmp_path,
                                                                 capsys):
    """The geographic block of :func:`block_in_crs` written northing (latitude) first, its
    latitudes, longitudes and angles in degrees, minutes and seconds (two notations), reads
    back to the same project (to the digits written) and adjusts alike
    (``--axis-order ne``); a DMS token with 61 minutes is one line naming file and line."""
    from conftest import assert_one_line_error, run_cli

    src, out, dd = block_in_crs(block_cache, tmp_path)
    ne = tmp_path / "ne"
    ne.mkdir()
    for name in ("cameras.txt", "measurements.txt"):
        shutil.copy(dd / name, ne / name)
    with open(ne / "photos.txt", "w") as f:
        for r in (ln.split() for ln in open(dd / "photos.txt") if ln[0] != "#"):
            ang = [_dms(float(v)) for v in r[3:6]]
            lon, lat = float(r[6]), float(r[7])
            f.write(" ".join(r[:3] + ang + [_dms(lat, "NS"), _dms(lon, "EW"), r[8]]) + "\n")
    with open(ne / "control.txt", "w") as f:
        for r in (ln.split() for ln in open(dd / "control.txt") if ln[0] != "#"):
            lon, lat = float(r[1]), float(r[2])
            f.write(" ".join([r[0], _dms(lat), _dms(lon), r[3], r[5], r[4]] + r[6:]) + "\n")
    got = tmp_path / "ne.h5"
    import_text(got, cameras=ne / "cameras.txt", photos=ne / "photos.txt",
                measurements=ne / "measurements.txt", control=ne / "control.txt",
                crs="EPSG:4979", axis_order="ne")
    a, b = read_records(out), read_records(got)
    np.testing.assert_allclose(b["stations"]["eo"][:, :3], a["stations"]["eo"][:, :3],
                               rtol=0, atol=1e-13)
    np.testing.assert_allclose(b["stations"]["eo"][:, 3:], a["stations"]["eo"][:, 3:],
                               rtol=0, atol=1e-6)
    np.testing.assert_allclose(b["points"]["control"], a["points"]["control"], rtol=0,
                               atol=1e-6)
    np.testing.assert_array_equal(b["points"]["control_sigma"], a["points"]["control_sigma"])
    opts = sapgo.Options(progress=False)
    assert sapgo.adjust(got, opts).sigma0 == pytest.approx(sapgo.adjust(out, opts).sigma0,
                                                           rel=1e-6)
    lines = (ne / "control.txt").read_text().splitlines()
    cols = lines[1].split()
    cols[1] = "49:61:00"
    lines[1] = " ".join(cols)
    (ne / "control.txt").write_text("\n".join(lines) + "\n")
    code, _, err = run_cli(capsys, "import", tmp_path / "bad.h5", "--cameras",
                           ne / "cameras.txt", "--photos", ne / "photos.txt", "--measurements",
                           ne / "measurements.txt", "--control", ne / "control.txt", "--crs",
                           "EPSG:4979", "--axis-order", "ne")
    assert_one_line_error(code, err, "control.txt:2: '49:61:00' is no angle in degrees, "
                          "minutes and seconds (minutes and seconds must be below 60) "
                          "(column 2, X)")


@pytest.mark.parametrize("which", ["photos", "control"])
def test_coordinates_outside_the_crs_name_their_line(exported_geo, tmp_path, which):
    """A latitude beyond 90 degrees (longitude and latitude swapped, say) in the photos or
    the control: one line naming the file, the line and the id (pyproj's error before)."""
    d = exported_geo
    dd = tmp_path / "bad"
    shutil.copytree(d, dd)
    rows = (dd / f"{which}.txt").read_text().splitlines()
    k = next(i for i, r in enumerate(rows) if r.strip() and r[0] != "#")
    t = rows[k].split()
    col = 7 if which == "photos" else 2     # (the latitude: Y of longitude, latitude, h)
    t[col] = "95.0"
    rows[k] = " ".join(t)
    (dd / f"{which}.txt").write_text("\n".join(rows) + "\n")
    with pytest.raises(DataError, match=rf"{which}.txt:{k + 1}: (photo|point) {t[0]}: "
                                        r"coordinates \(.*95.*\) are outside the domain"):
        import_text(tmp_path / "x.h5", cameras=dd / "cameras.txt", photos=dd / "photos.txt",
                    measurements=dd / "measurements.txt", control=dd / "control.txt",
                    crs="EPSG:4979")
    assert not (tmp_path / "x.h5").exists()
