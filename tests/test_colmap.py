"""COLMAP text models: the conversion against COLMAP's own projection, round trips (import,
adjust, export, import), control with a datum, projects of other origins, malformed files;
and the plain-text round trip of ``export --adjusted``."""

import json
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli

import sapgo
from sapgo.formats.colmap import export_colmap, import_colmap
from sapgo.geometry import camera_array, project
from sapgo.project import Project

DATA = Path(__file__).parent / "data"

#: CAMERA_ID: (MODEL, WIDTH, HEIGHT, PARAMS); fx != fy for the PINHOLE and OPENCV cameras
CAMS = {
    1: ("PINHOLE", 1280, 960, [800.0, 812.5, 640.3, 480.7]),
    2: ("SIMPLE_RADIAL", 1280, 960, [750.0, 639.5, 479.5, -0.05]),
    5: ("RADIAL", 1280, 960, [820.0, 650.25, 470.5, -0.03, 0.01]),
    9: ("OPENCV", 1280, 960, [790.0, 781.0, 630.0, 490.0, -0.04, 0.02, 1e-3, -5e-4]),
}


# -- COLMAP's camera model, written out independently of sapgo.formats.colmap ----------

def rot_of_quat(q):
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([[w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z]])


def quat_of_rot(r):
    """Shepperd's method: the largest of w, x, y, z first."""
    t = np.trace(r)
    c = int(np.argmax([t, r[0, 0], r[1, 1], r[2, 2]]))
    if c == 0:
        w = np.sqrt(1 + t) / 2
        return np.array([w, (r[2, 1] - r[1, 2]) / (4 * w), (r[0, 2] - r[2, 0]) / (4 * w),
                         (r[1, 0] - r[0, 1]) / (4 * w)])
    if c == 1:
        x = np.sqrt(1 + 2 * r[0, 0] - t) / 2
        return np.array([(r[2, 1] - r[1, 2]) / (4 * x), x, (r[0, 1] + r[1, 0]) / (4 * x),
                         (r[0, 2] + r[2, 0]) / (4 * x)])
    if c == 2:
        y = np.sqrt(1 + 2 * r[1, 1] - t) / 2
        return np.array([(r[0, 2] - r[2, 0]) / (4 * y), (r[0, 1] + r[1, 0]) / (4 * y), y,
                         (r[1, 2] + r[2, 1]) / (4 * y)])
    z = np.sqrt(1 + 2 * r[2, 2] - t) / 2
    return np.array([(r[1, 0] - r[0, 1]) / (4 * z), (r[0, 2] + r[2, 0]) / (4 * z),
                     (r[1, 2] + r[2, 1]) / (4 * z), z])


def colmap_pixel(model, params, q, t, X):
    """COLMAP's projection of world point X by a camera at pose (q, t), model by model."""
    pc = rot_of_quat(q) @ X + t
    a, b = pc[0] / pc[2], pc[1] / pc[2]
    if model == "PINHOLE":
        fx, fy, cx, cy = params
        return np.array([fx * a + cx, fy * b + cy])
    if model in ("SIMPLE_RADIAL", "RADIAL"):
        f, cx, cy, k1 = params[:4]
        k2 = params[4] if model == "RADIAL" else 0.0
        r2 = a * a + b * b
        d = 1 + k1 * r2 + k2 * r2 * r2
        return np.array([f * a * d + cx, f * b * d + cy])
    fx, fy, cx, cy, k1, k2, p1, p2 = params
    r2 = a * a + b * b
    d = 1 + k1 * r2 + k2 * r2 * r2
    xd = a * d + 2 * p1 * a * b + p2 * (r2 + 2 * a * a)
    yd = b * d + p1 * (r2 + 2 * b * b) + 2 * p2 * a * b
    return np.array([fx * xd + cx, fy * yd + cy])


def small_rotation(rng, sigma):
    w, p, k = rng.normal(0, sigma, 3)
    rx = np.array([[1, 0, 0], [0, np.cos(w), -np.sin(w)], [0, np.sin(w), np.cos(w)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(k), -np.sin(k), 0], [np.sin(k), np.cos(k), 0], [0, 0, 1]])
    return rz @ ry @ rx


def make_scene(seed=3, noise=0.5, extra2d=4, world=None):
    """Two strips of five images looking down on 105 ground points, the four camera models,
    noisy 2D points in shuffled order with some that have no 3D point, shuffled tracks,
    quaternions of both signs, a point on one image and one on none. ``world`` = (scale,
    rotation, shift) puts the model in another frame than the ground (``ground``: the true
    coordinates by point id)."""
    rng = np.random.default_rng(seed)
    flip = np.diag([1.0, -1.0, -1.0])  # camera z down
    images, iid = [], 3
    for strip in range(2):
        for k in range(5):
            centre = np.array([k * 90.0, strip * 110.0, 150.0]) + rng.normal(0, 2, 3)
            images.append({"id": iid, "camera": list(CAMS)[(k + strip) % 4],
                           "r": small_rotation(rng, 0.03) @ flip, "C": centre,
                           "name": f"DSC_{iid:04d}.JPG"})
            iid += 4
    gx, gy = np.meshgrid(np.linspace(-60, 420, 13), np.linspace(-60, 170, 8))
    ground = np.column_stack([gx.ravel() + rng.normal(0, 4, gx.size),
                              gy.ravel() + rng.normal(0, 4, gx.size), rng.normal(0, 5, gx.size)])
    ground = np.vstack([ground, [[2000.0, 2000.0, 0.0]]])  # seen by no image
    xyz = ground.copy()
    if world is not None:
        s, rot, shift = world
        xyz = s * ground @ rot.T + shift
        for im in images:
            im["C"] = s * rot @ im["C"] + shift
            im["r"] = im["r"] @ rot.T
    pids = np.sort(rng.choice(10 ** 6, len(ground), replace=False)) + 1
    for im in images:
        im["q"] = quat_of_rot(im["r"]) * (-1 if im["id"] % 3 == 0 else 1)
        im["t"] = -im["r"] @ im["C"]
    obs = {im["id"]: [] for im in images}
    for j, X in enumerate(xyz):
        for im in images:
            model, w, h, par = CAMS[im["camera"]]
            if (im["r"] @ (X - im["C"]))[2] <= 0:
                continue
            uv = colmap_pixel(model, par, im["q"], im["t"], X)
            if 5 < uv[0] < w - 5 and 5 < uv[1] < h - 5:
                obs[im["id"]].append((uv + rng.normal(0, noise, 2), int(pids[j])))
    seen = {}
    for i, lst in obs.items():
        for _, p in lst:
            seen.setdefault(p, []).append(i)
    single = next(p for p, imgs in seen.items() if len(imgs) >= 2)  # keep one ray only
    for i in seen[single][1:]:
        obs[i] = [o for o in obs[i] if o[1] != single]
    pts2d = {}
    for im in images:
        lst = obs[im["id"]] + [(rng.uniform([0, 0], [1280, 960]), -1) for _ in range(extra2d)]
        pts2d[im["id"]] = [lst[k] for k in rng.permutation(len(lst))]
    track = {int(p): [] for p in pids}
    for i, lst in pts2d.items():
        for idx, (_, p) in enumerate(lst):
            if p != -1:
                track[p].append((i, idx))
    for p in track:
        rng.shuffle(track[p])
    points = {int(p): (xyz[j], rng.integers(0, 256, 3), track[int(p)])
              for j, p in enumerate(pids)}
    return {"images": images, "pts2d": pts2d, "points": points,
            "ground": dict(zip(pids.tolist(), ground))}


def write_model(d, m):
    d = Path(d)
    d.mkdir(parents=True, exist_ok=True)
    with open(d / "cameras.txt", "w") as f:
        f.write("# Camera list with one line of data per camera:\n")
        for cid, (model, w, h, par) in CAMS.items():
            f.write(f"{cid} {model} {w} {h} " + " ".join(repr(float(v)) for v in par) + "\n")
    with open(d / "images.txt", "w") as f:
        f.write("# Image list with two lines of data per image:\n")
        for im in m["images"]:
            f.write(" ".join([str(im["id"])] + [repr(float(v)) for v in im["q"]]
                             + [repr(float(v)) for v in im["t"]]
                             + [str(im["camera"]), im["name"]]) + "\n")
            f.write(" ".join(f"{float(uv[0])!r} {float(uv[1])!r} {p}"
                             for uv, p in m["pts2d"][im["id"]]) + "\n")
    with open(d / "points3D.txt", "w") as f:
        f.write("# 3D point list with one line of data per point:\n")
        for pid, (X, rgb, tr) in m["points"].items():
            f.write(" ".join([str(pid)] + [repr(float(v)) for v in X]
                             + [str(int(c)) for c in rgb] + ["0.5"]
                             + [f"{i} {k}" for i, k in tr]) + "\n")
    return d


def parse_model(d):
    """The three files as dicts keyed by id (a reader of the test's own)."""
    d = Path(d)
    data = lambda name: [ln for ln in (d / name).read_text().splitlines()  # noqa: E731
                         if not ln.startswith("#")]
    cams = {}
    for ln in data("cameras.txt"):
        t = ln.split()
        cams[int(t[0])] = (t[1], int(t[2]), int(t[3]), np.array(t[4:], float))
    images, lines = {}, data("images.txt")
    for head, pts in zip(lines[0::2], lines[1::2]):
        t, p = head.split(), pts.split()
        images[int(t[0])] = (np.array(t[1:5], float), np.array(t[5:8], float), int(t[8]), t[9],
                             np.array(p, float).reshape(-1, 3))
    points = {}
    for ln in data("points3D.txt"):
        t = ln.split()
        points[int(t[0])] = (np.array(t[1:4], float), [int(v) for v in t[4:7]],
                             sorted(zip(map(int, t[8::2]), map(int, t[9::2]))))
    return cams, images, points


def assert_same_model(a, b):
    """The same ids, names, models, sizes, 2D point indices, colours and tracks, and the same
    values to 1e-12."""
    (ca, ia, pa), (cb, ib, pb) = parse_model(a), parse_model(b)
    close = dict(rtol=1e-12, atol=1e-12)
    assert ca.keys() == cb.keys() and ia.keys() == ib.keys() and pa.keys() == pb.keys()
    for k in ca:
        assert ca[k][:3] == cb[k][:3]
        np.testing.assert_allclose(cb[k][3], ca[k][3], **close)
    for k in ia:
        assert ia[k][2:4] == ib[k][2:4]
        for u, v in zip(ia[k][:2] + ia[k][4:], ib[k][:2] + ib[k][4:]):
            np.testing.assert_allclose(v, u, **close)
    for k in pa:
        assert pa[k][1:] == pb[k][1:]
        np.testing.assert_allclose(pb[k][0], pa[k][0], **close)


def residuals_by_key(path):
    """sapgo's residuals (computed - observed, pixels) of a project by (image id, point id)."""
    with Project(path) as p:
        st, pt, ob, cams = p.read("stations"), p.read("points"), p.read("observations"), \
            p.cameras()
    rows = camera_array(cams)
    out = {}
    for o in ob:
        s, j = st[o["station"]], pt[o["point"]]
        x, y = project(s["eo"], j["xyz"], rows[s["camera"]])
        out[(int(s["id"]), int(j["id"]))] = np.array([x - o["x"], y - o["y"]])
    return out


@pytest.fixture(scope="module")
def scene():
    return make_scene()


@pytest.fixture
def model(scene, tmp_path):
    return write_model(tmp_path / "model", scene)


# -- the conversion --------------------------------------------------------------------

def test_conversion_reproduces_colmaps_projection(scene, model, tmp_path):
    """sapgo's collinearity residuals of the imported project equal COLMAP's reprojection
    residuals, x as they are and y times -fx/fy (image y up, scaled to one focal length),
    for every camera model, with fx != fy for PINHOLE and OPENCV."""
    r = import_colmap(model, tmp_path / "a.h5")
    got = residuals_by_key(tmp_path / "a.h5")
    worst = dict.fromkeys(["PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"], 0.0)
    count = dict.fromkeys(worst, 0)
    for im in scene["images"]:
        cam, _, _, par = CAMS[im["camera"]]
        s = par[0] / par[1] if cam in ("PINHOLE", "OPENCV") else 1.0
        for uv, pid in scene["pts2d"][im["id"]]:
            if pid == -1:
                continue
            du, dv = colmap_pixel(cam, par, im["q"], im["t"], scene["points"][pid][0]) - uv
            v = got.pop((im["id"], pid))
            worst[cam] = max(worst[cam], abs(v[0] - du), abs(v[1] + s * dv))
            count[cam] += 1
    assert not got and min(count.values()) > 20
    assert max(worst.values()) < 1e-9, worst
    assert r["y_scaled_cameras"] == 2 and r["free"]
    assert r["camera_models"] == {"PINHOLE": 1, "SIMPLE_RADIAL": 1, "RADIAL": 1, "OPENCV": 1}
    with Project(tmp_path / "a.h5") as p:
        assert p.attr("image_unit") == "px" and p.attr("datum") == "free"
        cams = p.cameras()
    k = list(cams["id"]).index(9)  # OPENCV: fx, fy, cx, cy, k1, k2, p1, p2
    f, s = 790.0, 790.0 / 781.0
    assert cams["focal_length"][k] == f
    np.testing.assert_allclose([cams[n][k] for n in ("x0", "y0", "k1", "k2", "p1", "p2")],
                               [630 - 640, s * (480 - 490), -0.04 / f ** 2, 0.02 / f ** 4,
                                -5e-4 / f, -1e-3 / f], rtol=1e-14)


# -- round trips -----------------------------------------------------------------------

def test_round_trip_import_adjust_export_import(model, tmp_path, capsys):
    """The adjusted model, re-imported, starts at the adjusted final cost; the input model
    comes back with its ids, names, POINT2D indices, colours and values (1e-12); ordering
    and adjusting leave /colmap as it was."""
    a = tmp_path / "a.h5"
    code, out, err = run_cli(capsys, "import", "--format", "colmap", model, a)
    assert code == 0 and "free network" in out and "mean reprojection error" in out, err
    assert "seen on too few images" in err  # kept, and left out by ordering
    with h5py.File(a, "r") as f:
        before = {k: repr(f["colmap"][k][()].tolist()) for k in f["colmap"]}
    code, out, err = run_cli(capsys, "adjust", a, "--no-progress", "--json", tmp_path / "r.json",
                             "--quiet")
    assert code == 0, err
    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["converged"] and rep["method"] == "lm"
    code, out, err = run_cli(capsys, "info", a)
    assert code == 0 and "band_width" in out, err
    with Project(a) as p:
        assert p.ordered and p.has_solution
        assert {k: repr(p.file["colmap"][k][()].tolist()) for k in p.file["colmap"]} == before
    code, out, err = run_cli(capsys, "export", a, tmp_path / "in", "--format", "colmap")
    assert code == 0, err
    assert_same_model(model, tmp_path / "in")
    assert (tmp_path / "in" / "images.txt").read_text().count("DSC_") == 10
    code, out, err = run_cli(capsys, "export", a, tmp_path / "adj", "--format", "colmap",
                             "--adjusted")
    assert code == 0, err
    again = tmp_path / "again.h5"
    import_colmap(tmp_path / "adj", again)
    s = sapgo.adjust(again, sapgo.Options(progress=False, max_iterations=1))
    assert s.initial_cost == pytest.approx(rep["final_cost"], rel=1e-9)
    # ERROR: the mean reprojection error of each track, from the written values
    _, images, points = parse_model(tmp_path / "adj")
    ids = [k for k, v in points.items() if len(v[2]) >= 2][:5]
    errors = {int(ln.split()[0]): float(ln.split()[7])
              for ln in (tmp_path / "adj" / "points3D.txt").read_text().splitlines()
              if ln[0] != "#"}
    cams = parse_model(tmp_path / "adj")[0]
    for pid in ids:
        d = []
        for i, idx in points[pid][2]:
            q, t, cid, _, pts = images[i]
            uv = colmap_pixel(cams[cid][0], cams[cid][3], q, t, points[pid][0])
            d.append(np.linalg.norm(uv - pts[idx, :2]))
        assert errors[pid] == pytest.approx(np.mean(d), rel=1e-9)


def test_control_gives_the_datum_and_check_points(scene, tmp_path, capsys):
    """A model in a frame of its own (scale 0.013, rotated) with control in the ground's
    coordinates: aligned to the full control points, adjusted by Gauss-Newton with that
    datum, sigma0 near 1 with the true image sigma, check points near their known
    coordinates; horizontal and vertical control in a CRS too."""
    from scipy.spatial.transform import Rotation

    rot = Rotation.from_euler("xyz", [30, -50, 120], degrees=True).as_matrix()
    m = make_scene(world=(0.013, rot, np.array([5.0, -3.0, 2.0])))
    d = write_model(tmp_path / "model", m)
    rng = np.random.default_rng(1)
    ids = [p for p, v in m["points"].items() if len(v[2]) >= 3]
    lines, check = [], []
    for k, pid in enumerate(ids[::6]):
        x = (m["ground"][pid] + rng.normal(0, 0.02, 3)).tolist()
        lines.append(f"{pid} {x[0]!r} {x[1]!r} {x[2]!r} 0.02 0.02 0.02 "
                     f"{'full' if k % 2 == 0 else 'check'}")
        if k % 2:
            check.append(pid)
    g1, g2 = m["ground"][ids[1]].tolist(), m["ground"][ids[2]].tolist()
    lines.append(f"{ids[1]} {g1[0]!r} {g1[1]!r} - 0.02 0.02 - horizontal")
    lines.append(f"{ids[2]} - - {g2[2]!r} - - 0.03 vertical")
    (tmp_path / "control.txt").write_text("\n".join(lines) + "\n")
    shift = [690000.0, 5330000.0, 520.0]  # the ground as UTM zone 32 coordinates
    utm = []
    for t in (ln.split() for ln in lines):
        xyz = [v if v == "-" else repr(float(v) + shift[k]) for k, v in enumerate(t[1:4])]
        utm.append(" ".join([t[0]] + xyz + t[4:]))
    (tmp_path / "utm.txt").write_text("\n".join(utm) + "\n")
    for name, extra in (("local", []), ("utm", ["--crs", "EPSG:32632"])):
        out = tmp_path / f"{name}.h5"
        code, text, err = run_cli(capsys, "import", "--format", "colmap", d, out, "--control",
                                  tmp_path / ("utm.txt" if extra else "control.txt"),
                                  "--sigma-image", "0.5", *extra)
        n_full = len(ids[::6]) - len(check)
        assert code == 0 and f"aligned to {n_full} full control points" in text, err
        s = sapgo.adjust(out, sapgo.Options(progress=False))
        assert s.converged and s.method == "gn" and s.datum == "control"
        assert 0.8 < s.sigma0 < 1.2
        assert s.check_points["n"] == len(check) >= 3
        # 0.5 px of image noise is about 0.1 m on the ground (150 m above it, f = 800 px)
        assert s.check_points["sxy"] < 0.5 and s.check_points["sz"] < 0.5
        with Project(out) as p:
            assert p.attr("datum", "") == "" and p.frame().kind == (
                "local tangent" if extra else "local space rectangular")
            pts = p.read("points")
            adj = pts["xyz"] + p.solution("point_corr")
            if not extra:  # adjusted check points against the ground truth
                for pid in check:
                    j = int(np.flatnonzero(pts["id"] == pid)[0])
                    assert np.abs(adj[j] - m["ground"][pid]).max() < 0.6
    # export writes the adjusted model in the computation frame
    code, text, err = run_cli(capsys, "export", tmp_path / "local.h5", tmp_path / "out",
                              "--format", "colmap", "--adjusted")
    assert code == 0, err
    pts = parse_model(tmp_path / "out")[2]
    assert np.abs(pts[check[0]][0] - m["ground"][check[0]]).max() < 0.6


def test_projects_of_other_origins_are_written_in_pixels(small_block, tmp_path, capsys):
    """A generated block (mm): refused without a pixel size; with one, the COLMAP model's
    residuals are sapgo's divided by the pixel size. A BAL problem (pixels, k1 and k2):
    OPENCV cameras that reproduce its reprojection errors. k3 cannot be written."""
    from sapgo.formats.bal import bal_to_sapgo, import_bal, read_bal

    code, _, err = run_cli(capsys, "export", small_block, tmp_path / "x", "--format", "colmap")
    assert_one_line_error(code, err, "in mm", "--pixel-size")
    code, text, err = run_cli(capsys, "export", small_block, tmp_path / "mm", "--format",
                              "colmap", "--pixel-size", "10")
    assert code == 0 and "PINHOLE" in text, err
    import_colmap(tmp_path / "mm", tmp_path / "mm.h5")
    v_mm, v_px = residuals_by_key(small_block), residuals_by_key(tmp_path / "mm.h5")
    assert v_mm.keys() == v_px.keys()
    assert max(np.abs(v_px[k] - v_mm[k] / 0.010).max() for k in v_mm) < 1e-7
    assert "photo_" in (tmp_path / "mm" / "images.txt").read_text()

    bal = DATA / "dubrovnik-3-7-pre.txt.gz"
    import_bal(bal, tmp_path / "bal.h5")
    export_colmap(tmp_path / "bal.h5", tmp_path / "balc")
    assert (tmp_path / "balc" / "cameras.txt").read_text().count("OPENCV") == 3
    r = import_colmap(tmp_path / "balc", tmp_path / "balc.h5")
    d = read_bal(bal)
    eo, rows = bal_to_sapgo(d["cameras"])
    v = np.array([project(eo[a], d["points"][b], rows[a]) for a, b in
                  zip(d["obs_camera"], d["obs_point"])]) - d["obs_xy"]
    assert r["mean_reprojection_error"] == pytest.approx(np.linalg.norm(v, axis=1).mean(),
                                                        rel=1e-9)

    with h5py.File(small_block, "r+") as f:
        cams = f["cameras"][:]
        cams["k3"] = 1e-9
        f["cameras"][...] = cams
    code, _, err = run_cli(capsys, "export", small_block, tmp_path / "k3", "--format", "colmap",
                           "--pixel-size", "10")
    assert_one_line_error(code, err, "k3")


# -- malformed models ------------------------------------------------------------------

CAMERAS = "# cameras\n1 PINHOLE 100 80 50.0 50.0 50.0 40.0\n2 OPENCV 100 80 50 50 50 40 0 0 0 0\n"
IMAGES = ("# images\n1 1 0 0 0 0 0 10 1 a.jpg\n10 20 1 30 40 -1\n"
          "2 1 0 0 0 1 0 10 2 b.jpg\n12 22 1 33 44 2\n3 1 0 0 0 2 0 10 1 c.jpg\n\n")
POINTS = "# points\n1 0 0 0 1 2 3 0.5 1 0 2 0\n2 1 1 1 0 0 0 0.1 2 1\n"


def _replace(text, line, new):
    lines = text.splitlines()
    lines[line - 1] = new
    return "\n".join(lines) + "\n"


#: case: (file, line replaced (None: the file removed), new text, place, words)
BAD = {
    "missing file": ("images.txt", None, None, "images.txt:", "no such file"),
    "camera fields": ("cameras.txt", 2, "1 PINHOLE 100", "cameras.txt:2:", "CAMERA_ID MODEL"),
    "camera parameters": ("cameras.txt", 2, "1 PINHOLE 100 80 50 50 50", "cameras.txt:2:",
                          "4 parameters"),
    "camera number": ("cameras.txt", 3, "2 OPENCV 100 80 50 50 50 40 0 0 x 0", "cameras.txt:3:",
                      "'x' is not a number (column 11, p1)"),
    "camera model": ("cameras.txt", 2, "1 OPENCV_FISHEYE 100 80 50 50 50 40 0 0 0 0",
                     "cameras.txt:2:", "OPENCV_FISHEYE"),
    "image fields": ("images.txt", 2, "1 1 0 0 0 0 0 10 1", "images.txt:2:", "10 fields"),
    "image camera": ("images.txt", 4, "2 1 0 0 0 1 0 10 7 b.jpg", "images.txt:4:", "camera 7"),
    "quaternion": ("images.txt", 2, "1 1.001 0 0 0 0 0 10 1 a.jpg", "images.txt:2:",
                   "quaternion"),
    "2D triples": ("images.txt", 3, "10 20 1 30 40", "images.txt:3:", "triples"),
    "2D number": ("images.txt", 5, "12 22 1 33 4.4.4 2", "images.txt:5:",
                  "'4.4.4' is not a number (column 5, Y)"),
    "2D point id": ("images.txt", 5, "12 22 1 33 44 1.5", "images.txt:5:",
                    "'1.5' is not an integer (column 6, POINT3D_ID)"),
    "unknown 3D point": ("images.txt", 3, "10 20 1 30 40 9", "images.txt:3:",
                         "3D point 9 (column 6"),
    "point fields": ("points3D.txt", 3, "2 1 1 1 0 0 0", "points3D.txt:3:", "POINT3D_ID X Y Z"),
    "odd track": ("points3D.txt", 3, "2 1 1 1 0 0 0 0.1 2", "points3D.txt:3:", "pairs"),
    "point number": ("points3D.txt", 2, "1 0 y 0 1 2 3 0.5 1 0 2 0", "points3D.txt:2:",
                     "'y' is not a number (column 3, Y)"),
    "POINT2D_IDX range": ("points3D.txt", 3, "2 1 1 1 0 0 0 0.1 2 5", "points3D.txt:3:",
                          "POINT2D_IDX 5 (column 10) is out of range"),
    "track image": ("points3D.txt", 3, "2 1 1 1 0 0 0 0.1 4 1", "points3D.txt:3:", "image 4"),
    "track twice": ("points3D.txt", 2, "1 0 0 0 1 2 3 0.5 1 0 2 0 1 0", "points3D.txt:2:",
                    "listed twice"),
    "image twice": ("images.txt", 4, "1 1 0 0 0 1 0 10 2 b.jpg", "images.txt:4:",
                    "image 1 is given twice (also line 2)"),
    "name twice": ("images.txt", 4, "2 1 0 0 0 1 0 10 2 a.jpg", "images.txt:4:",
                   "image 2's NAME 'a.jpg' (column 10) is also image 1's (line 2)"),
    "track mismatch": ("points3D.txt", 3, "2 1 1 1 0 0 0 0.1 2 0", "points3D.txt:3:",
                       "has 3D point 1"),
    "not in the track": ("images.txt", 3, "10 20 1 30 40 2", "images.txt:3:",
                         "does not list it"),
    "control id": ("control.txt", 1, "99 0 0 0 1 1 1", "control.txt:1:",
                   "point 99 is not a 3D point"),
    "control line": ("control.txt", 1, "1 0 0", "control.txt:1:", "expected 7 or 8 columns"),
    "fy out of range": ("cameras.txt", 2, "1 PINHOLE 100 80 50.0 1e-300 50.0 40.0",
                        "/m: cameras record 0 (id 1)", "format_y 4e+303 is beyond"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_malformed_models_name_file_and_line(tmp_path, capsys, case):
    name, line, new, place, words = BAD[case]
    d = tmp_path / "m"
    d.mkdir()
    files = {"cameras.txt": CAMERAS, "images.txt": IMAGES, "points3D.txt": POINTS,
             "control.txt": "1 0 0 0 1 1 1\n2 1 1 1 1 1 1 check\n"}
    for f, text in files.items():
        if f == name and line is None:
            continue
        (d / f).write_text(_replace(text, line, new) if f == name else text)
    code, _, err = run_cli(capsys, "import", "--format", "colmap", d, tmp_path / "x.h5",
                           *(["--control", d / "control.txt"] if name == "control.txt" else []))
    assert_one_line_error(code, err, place, words)
    assert [p.name for p in tmp_path.iterdir()] == ["m"]  # no project, temporary or work file


def test_the_valid_small_model_imports(tmp_path):
    """The base of the malformed cases is itself valid (its 2D point without a 3D point,
    its one-ray point and its image without 2D points are kept), and comes back as it was."""
    d = tmp_path / "m"
    d.mkdir()
    for f, text in (("cameras.txt", CAMERAS), ("images.txt", IMAGES), ("points3D.txt", POINTS)):
        (d / f).write_text(text)
    r = import_colmap(d, tmp_path / "x.h5")
    assert (r["photos"], r["points"], r["observations"], r["points2D_without_3D"]) == \
        (3, 2, 3, 1)
    assert r["undetermined_points"] == 1
    export_colmap(tmp_path / "x.h5", tmp_path / "back")
    assert_same_model(d, tmp_path / "back")
    assert (tmp_path / "back" / "images.txt").read_text().endswith("c.jpg\n\n")


def test_options_that_do_not_apply_are_refused(tmp_path, capsys):
    d = tmp_path / "m"
    d.mkdir()
    for f, text in (("cameras.txt", CAMERAS), ("images.txt", IMAGES), ("points3D.txt", POINTS)):
        (d / f).write_text(text)
    for args, words in (((d, tmp_path / "x.h5", "--append"), "--append"),
                        ((d, tmp_path / "x.h5", "--crs", "EPSG:32632"), "--control"),
                        ((d, tmp_path / "x.h5", "--sigma-image", "0"), "--sigma-image"),
                        ((d,), "MODEL_DIR")):
        code, _, err = run_cli(capsys, "import", "--format", "colmap", *args)
        assert_one_line_error(code, err, words)
    code, _, err = run_cli(capsys, "import", tmp_path / "y.h5", "--sigma-image", "2")
    assert_one_line_error(code, err, "--sigma-image applies to --format colmap")
    assert [p.name for p in tmp_path.iterdir()] == ["m"]
    import_colmap(d, tmp_path / "x.h5")
    code, _, err = run_cli(capsys, "import", "--format", "colmap", d, tmp_path / "x.h5")
    assert_one_line_error(code, err, "exists", "--force")
    code, _, err = run_cli(capsys, "export", tmp_path / "x.h5", tmp_path / "o", "--format",
                           "colmap", "--adjusted")
    assert_one_line_error(code, err, "no adjusted solution")


# -- the plain-text formats: export --adjusted, imported again -------------------------

def test_text_export_of_the_adjusted_block_imports_again(small_block, tmp_path, capsys):
    """adjusted_photos.txt is a photos file: imported with the block's cameras,
    measurements and control it gives the adjusted stations, and the adjustment stays where
    it was. adjusted_points.txt (id X Y Z kind n_obs) is no input format: the text import
    intersects the points again from the adjusted stations."""
    code, _, err = run_cli(capsys, "adjust", small_block, "--no-progress", "--quiet", "--json",
                           tmp_path / "r.json")
    assert code == 0, err
    rep = json.loads((tmp_path / "r.json").read_text())
    for args in ((), ("--adjusted",)):
        code, _, err = run_cli(capsys, "export", small_block, tmp_path / "txt", *args)
        assert code == 0, err
    d = tmp_path / "txt"
    again = tmp_path / "again.h5"
    code, _, err = run_cli(capsys, "import", again, "--cameras", d / "cameras.txt",
                           "--photos", d / "adjusted_photos.txt", "--measurements",
                           d / "measurements.txt", "--control", d / "control.txt")
    assert code == 0, err
    with Project(small_block) as p:
        st = p.read("stations")
        adj = dict(zip(st["id"].tolist(), st["eo"] + p.solution("station_corr")))
        pt = p.read("points")
        xyz = dict(zip(pt["id"].tolist(), pt["xyz"] + p.solution("point_corr")))
    with Project(again) as p:
        st2 = p.read("stations")
    assert sorted(adj) == sorted(st2["id"].tolist())
    for i, eo in zip(st2["id"].tolist(), st2["eo"]):
        np.testing.assert_allclose(eo[:3], adj[i][:3], rtol=0, atol=1e-14)
        np.testing.assert_allclose(eo[3:], adj[i][3:], rtol=1e-15, atol=0)
    s = sapgo.adjust(again, sapgo.Options(progress=False))
    assert s.converged and s.final_cost == pytest.approx(rep["final_cost"], rel=1e-6)
    with Project(again) as p:
        pt2 = p.read("points")
        xyz2 = pt2["xyz"] + p.solution("point_corr")
    act = pt2["status"] == 0
    assert max(np.abs(xyz2[j] - xyz[int(pt2["id"][j])]).max()
               for j in np.flatnonzero(act)) < 1e-5
    pts = np.loadtxt(d / "adjusted_points.txt", usecols=(0, 1, 2, 3))
    assert max(np.abs(r[1:] - xyz[int(r[0])]).max() for r in pts) < 1e-9
    shutil.rmtree(d)


@pytest.mark.parametrize("where", ["one place", "a line"])
def test_control_at_one_place_or_on_a_line_is_refused(scene, tmp_path, capsys, where):
    """Full control points whose given coordinates coincide or lie on a line (the model's
    points do not): the similarity is undetermined; one line naming the control file and
    the points (the model was collapsed to a point, scale 0, before)."""
    m = make_scene()
    d = write_model(tmp_path / "model", m)
    ids = [p for p, v in m["points"].items() if len(v[2]) >= 3][::7][:4]
    lines = [f"{pid} {k if where == 'a line' else 0} {k if where == 'a line' else 0} "
             f"{k if where == 'a line' else 0} 0.02 0.02 0.02" for k, pid in enumerate(ids)]
    (tmp_path / "control.txt").write_text("\n".join(lines) + "\n")
    code, _, err = run_cli(capsys, "import", "--format", "colmap", d, tmp_path / "x.h5",
                           "--control", tmp_path / "control.txt")
    assert_one_line_error(code, err, "control.txt: the full control points",
                          "at one place or on a line")
    assert not (tmp_path / "x.h5").exists()


def test_options_between_the_paths(tmp_path, capsys):
    """``import --format colmap MODEL --sigma-image 1 OUT``: the paths around an option are
    both taken (argparse left OUT over before); an unknown word after them is still an
    error."""
    d = tmp_path / "m"
    d.mkdir()
    for f, text in (("cameras.txt", CAMERAS), ("images.txt", IMAGES), ("points3D.txt", POINTS)):
        (d / f).write_text(text)
    code, _, err = run_cli(capsys, "import", "--format", "colmap", d, "--sigma-image", "1",
                           tmp_path / "x.h5")
    assert code == 0, err
    assert (tmp_path / "x.h5").exists()
    with pytest.raises(SystemExit) as exc:   # (argparse's usage error)
        run_cli(capsys, "adjust", tmp_path / "x.h5", "surplus")
    assert exc.value.code == 2 and "unrecognized arguments: surplus" in capsys.readouterr().err
