"""OpenSfM datasets: the camera models against OpenSfM's own formulas, round trips and
malformed files."""

import json

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli
from scipy.spatial.transform import Rotation

import sapgo
from sapgo.formats.opensfm import export_opensfm, import_opensfm, read_opensfm
from sapgo.geometry import camera_array, project
from sapgo.project import Project

CAMERAS = {
    "v2 brown 4000 3000": {"projection_type": "brown", "width": 4000, "height": 3000,
                           "focal_x": 0.85, "focal_y": 0.83, "c_x": 0.004, "c_y": -0.003,
                           "k1": -0.05, "k2": 0.01, "p1": 0.001, "p2": -0.002, "k3": 0.003},
    "v2 perspective 3000 4000": {"projection_type": "perspective", "width": 3000,
                                 "height": 4000, "focal": 0.9, "k1": 0.02, "k2": -0.004},
}


def _reference(cam, r, t, x):
    """OpenSfM's projection (geometry.rst), normalised coordinates, written out here."""
    p = r @ x + t
    xn, yn = p[0] / p[2], p[1] / p[2]
    r2 = xn * xn + yn * yn
    if cam["projection_type"] == "perspective":
        d = 1 + cam["k1"] * r2 + cam["k2"] * r2 * r2
        return np.array([cam["focal"] * d * xn, cam["focal"] * d * yn])
    d = 1 + cam["k1"] * r2 + cam["k2"] * r2 ** 2 + cam["k3"] * r2 ** 3
    xd = d * xn + 2 * cam["p1"] * xn * yn + cam["p2"] * (r2 + 2 * xn * xn)
    yd = d * yn + cam["p1"] * (r2 + 2 * yn * yn) + 2 * cam["p2"] * xn * yn
    return np.array([cam["focal_x"] * xd + cam["c_x"], cam["focal_y"] * yd + cam["c_y"]])


def _dataset(d, noise=0.0, seed=1, version=1):
    """Eight shots of two cameras looking down (+z forward, y down) at 80 points."""
    rng = np.random.default_rng(seed)
    pts = np.column_stack([rng.uniform(-40, 40, 80), rng.uniform(-30, 30, 80),
                           rng.uniform(-3, 3, 80)])
    recon = {"cameras": CAMERAS, "shots": {}, "points": {}, "biases": {}}
    rows = ["OPENSFM_TRACKS_VERSION_v1"] if version == 1 else []
    names = list(CAMERAS)
    for i in range(8):
        centre = np.array([-30 + 9 * i, rng.uniform(-5, 5), 100 + rng.uniform(-3, 3)])
        look = Rotation.from_euler("xyz", [np.pi + rng.normal(0, 0.05),
                                           rng.normal(0, 0.05), rng.uniform(0, 2 * np.pi)])
        r = look.as_matrix()          # world -> camera: camera z points down
        t = -r @ centre
        cam = names[i % 2]
        name = f"IMG_{i:04d}.JPG"
        recon["shots"][name] = {"camera": cam, "rotation": look.as_rotvec().tolist(),
                                "translation": t.tolist(), "orientation": 1}
        for j, x in enumerate(pts):
            u = _reference(CAMERAS[cam], r, t, x) + rng.normal(0, noise, 2)
            if np.abs(u).max() < 0.45:
                extra = "\t0.002" if version == 1 else ""
                rows.append(f"{name}\t{j}\t{1000 * i + j}\t{float(u[0])!r}\t"
                            f"{float(u[1])!r}{extra}\t10\t20\t30")
    for j, x in enumerate(pts):
        recon["points"][str(j)] = {"coordinates": x.tolist(), "color": [10.0, 20.0, 30.0]}
    # an image without a shot and a track without a point: left out
    rows.append("NOT_RECONSTRUCTED.JPG\t0\t5\t0.1\t0.1" + ("\t0.002" if version == 1 else "")
                + "\t1\t2\t3")
    d.mkdir(exist_ok=True)
    (d / "reconstruction.json").write_text(json.dumps([recon]))
    (d / "tracks.csv").write_text("\n".join(rows) + "\n")
    return recon


def test_the_cameras_are_opensfms(tmp_path):
    """Every imported observation's sapgo projection is OpenSfM's, converted: x = xn S,
    y = -yn S fx / fy (S = max(width, height)); residuals of a moved point are OpenSfM's
    residuals in pixels."""
    recon = _dataset(tmp_path / "ds")
    r = import_opensfm(tmp_path / "ds", tmp_path / "o.h5")
    assert r["photos"] == 8 and r["points"] == 80 and r["mean_error_px"] < 1e-9
    with Project(tmp_path / "o.h5") as p:
        st, pt, ob = p.read("stations"), p.read("points"), p.read("observations")
        rows = camera_array(p.cameras())
        assert p.attr("image_unit") == "px" and p.attr("datum") == "free"
    assert len(ob) == r["observations"] > 300
    shots = sorted(recon["shots"])
    for k in range(0, len(ob), 7):
        s, j = int(ob["station"][k]), int(ob["point"][k])
        name = shots[s]
        cam = CAMERAS[recon["shots"][name]["camera"]]
        big = max(cam["width"], cam["height"])
        fy_over = (cam["focal_x"] / cam["focal_y"] if "focal_x" in cam else 1.0)
        moved = pt["xyz"][j] + [0.3, -0.2, 0.4]
        rr = Rotation.from_rotvec(recon["shots"][name]["rotation"]).as_matrix()
        ref = _reference(cam, rr, np.array(recon["shots"][name]["translation"]), moved)
        obs = np.array([ob["x"][k], ob["y"][k]])
        want = (ref - np.array([obs[0] / big, -obs[1] / (big * fy_over)])) * [big, -big *
                                                                               fy_over]
        got = project(st["eo"][s], moved, rows[st["camera"][s]]) - obs
        np.testing.assert_allclose(got, want, atol=1e-7)


def test_round_trip_and_adjustment(tmp_path, capsys):
    recon = _dataset(tmp_path / "ds", noise=0.0004)
    code, text, err = run_cli(capsys, "import", "--format", "opensfm", tmp_path / "ds",
                              tmp_path / "o.h5")
    assert code == 0 and "OpenSfM's mean reprojection error" in text, err
    code, text, err = run_cli(capsys, "export", tmp_path / "o.h5", tmp_path / "in",
                              "--format", "opensfm")
    assert code == 0, err
    a, b = read_opensfm(tmp_path / "ds"), read_opensfm(tmp_path / "in")
    assert a["shots"] == b["shots"] and a["points"] == b["points"]
    assert a["cameras"] == b["cameras"] and a["camera_types"] == b["camera_types"]
    np.testing.assert_allclose(b["camera_rows"], a["camera_rows"], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(b["rotations"], a["rotations"], atol=1e-13)
    np.testing.assert_allclose(b["translations"], a["translations"], rtol=1e-12,
                               atol=1e-10)
    np.testing.assert_allclose(b["xyz"], a["xyz"], rtol=0, atol=0)
    oa = np.lexsort((a["obs_shot"], a["obs_point"]))
    ob_ = np.lexsort((b["obs_shot"], b["obs_point"]))
    for key in ("obs_shot", "obs_point", "obs_feature"):
        np.testing.assert_array_equal(b[key][ob_], a[key][oa], err_msg=key)
    np.testing.assert_allclose(b["obs_xy"][ob_], a["obs_xy"][oa], rtol=1e-13, atol=1e-16)
    np.testing.assert_array_equal(b["colors"], a["colors"])
    # adjusted (a free network, the cameras held), written, read: it starts at the end
    s = sapgo.adjust(tmp_path / "o.h5", sapgo.Options(progress=False, max_iterations=30))
    assert s.final_cost < s.initial_cost
    export_opensfm(tmp_path / "o.h5", tmp_path / "adj", adjusted=True)
    again = import_opensfm(tmp_path / "adj", tmp_path / "again.h5")
    with Project(tmp_path / "again.h5") as p:
        n = len(p.read("observations"))
    # (sigma 1 px: the cost is half the sum of squared pixel residuals; y scaled by fx/fy)
    assert again["observations"] == n
    s2 = sapgo.adjust(tmp_path / "again.h5", sapgo.Options(progress=False, max_iterations=1))
    assert s2.initial_cost == pytest.approx(s.final_cost, rel=1e-7)


BAD = {
    "fisheye": (lambda r: r[0]["cameras"]["v2 brown 4000 3000"].update(
        projection_type="fisheye"), "reconstruction.json", "fisheye"),
    "size": (lambda r: r[0]["cameras"]["v2 brown 4000 3000"].update(width=0),
             "reconstruction.json", "width and height"),
    "camera": (lambda r: r[0]["shots"]["IMG_0001.JPG"].update(camera="nope"),
               "reconstruction.json", "'nope' is not one of"),
    "rotation": (lambda r: r[0]["shots"]["IMG_0001.JPG"].update(rotation=[1, 2]),
                 "reconstruction.json", "rotation: expected 3"),
}


@pytest.mark.parametrize("case", sorted(BAD) + ["json", "tracks", "version"])
def test_malformed_datasets_name_file_and_place(tmp_path, capsys, case):
    d = tmp_path / "ds"
    _dataset(d)
    if case in BAD:
        change, where, words = BAD[case]
        r = json.loads((d / "reconstruction.json").read_text())
        change(r)
        (d / "reconstruction.json").write_text(json.dumps(r))
    elif case == "json":
        (d / "reconstruction.json").write_text('[{"cameras": {},\n "shots": }]')
        where, words = "reconstruction.json:2:", "not JSON"
    elif case == "tracks":
        lines = (d / "tracks.csv").read_text().splitlines()
        lines[3] = lines[3].replace("\t", " ", 1)
        (d / "tracks.csv").write_text("\n".join(lines) + "\n")
        where, words = "tracks.csv:4:", "tab-separated columns"
    else:
        text = (d / "tracks.csv").read_text().replace("VERSION_v1", "VERSION_v7")
        (d / "tracks.csv").write_text(text)
        where, words = "tracks.csv:1:", "v0, v1 and v2"
    code, out, err = run_cli(capsys, "import", "--format", "opensfm", d, tmp_path / "x.h5")
    assert_one_line_error(code, err, where, words)
    assert not (tmp_path / "x.h5").exists()


def test_tracks_v0_and_the_reconstruction_index(tmp_path, capsys):
    _dataset(tmp_path / "ds", version=0)
    r = import_opensfm(tmp_path / "ds" / "reconstruction.json", tmp_path / "o.h5")
    assert r["observations"] > 300 and r["reconstructions"] == 1
    code, out, err = run_cli(capsys, "import", "--format", "opensfm", tmp_path / "ds",
                             tmp_path / "y.h5", "--reconstruction", "3")
    assert_one_line_error(code, err, "1 reconstruction(s)", "0..0")


def test_export_needs_an_opensfm_import(tmp_path, capsys, small_block):
    code, out, err = run_cli(capsys, "export", small_block, tmp_path / "x", "--format",
                             "opensfm")
    assert_one_line_error(code, err, "not imported from OpenSfM")


# -- malformed input found by fuzzing: one-line errors naming the file and the place ---------
BRN, PSP = "v2 brown 4000 3000", "v2 perspective 3000 4000"


def _cam(key, value):
    def change(r, key=key, value=value):
        cam = r[0]["cameras"][PSP if key in ("focal",) else BRN]
        if value is KeyError:
            del cam[key]
        else:
            cam[key] = value
    return change


JSON_BAD = {
    "huge width": (_cam("width", 10 ** 30), f"camera '{BRN}': width 1000000000000000000000000"
                   "000000 is not an image size in pixels"),
    "fractional width": (_cam("width", 4000.5), "width 4000.5 is not an image size in pixels"),
    "boolean height": (_cam("height", True), "height true is not"),
    "boolean focal": (_cam("focal_x", True), f"camera '{BRN}': focal_x true is not a finite"),
    "no k1": (_cam("k1", KeyError), f"camera '{BRN}': k1 is missing"),
    "no perspective k2": (lambda r: r[0]["cameras"][PSP].pop("k2"),
                          f"camera '{PSP}': k2 is missing"),
    "no c_x": (_cam("c_x", KeyError), f"camera '{BRN}': c_x is missing"),
    "tiny focal_y": (_cam("focal_y", 1e-300), f"camera '{BRN}': focal_y 1e-300"),
    "lopsided focal": (_cam("focal_y", 100.0), f"camera '{BRN}': focal_x / focal_y"),
    "far principal point": (_cam("c_x", 1e200), f"camera '{BRN}': c_x 1e+200"),
    "huge rotation": (lambda r: r[0]["shots"]["IMG_0001.JPG"].update(rotation=[1e300, 0, 0]),
                      "shot 'IMG_0001.JPG': rotation"),
    "large rotation": (lambda r: r[0]["shots"]["IMG_0001.JPG"].update(rotation=[1e20, 0, 0]),
                       "shot 'IMG_0001.JPG': rotation"),
    "boolean rotation": (lambda r: r[0]["shots"]["IMG_0001.JPG"].update(
        rotation=[True, 0, 0]), "shot 'IMG_0001.JPG': rotation: expected 3 finite numbers"),
    "huge translation": (lambda r: r[0]["shots"]["IMG_0001.JPG"].update(
        translation=[1e308, 1e308, 1e308]), "shot 'IMG_0001.JPG': its rotation and trans"),
    "far point": (lambda r: r[0]["points"]["3"].update(coordinates=[1e300, 0, 0]),
                  "point '3': coordinates"),
    "no points": (lambda r: r[0].update(points={}), "has no points"),
    "colour range": (lambda r: r[0]["points"]["3"].update(color=[999, 0, -3]),
                     "point '3': color"),
    "colour boolean": (lambda r: r[0]["points"]["3"].update(color=[True, 0, 3]),
                       "point '3': color"),
}


@pytest.mark.parametrize("case", sorted(JSON_BAD))
def test_bad_reconstruction_values_are_one_line_errors(tmp_path, capsys, case):
    d = tmp_path / "ds"
    _dataset(d)
    change, words = JSON_BAD[case]
    r = json.loads((d / "reconstruction.json").read_text())
    change(r)
    (d / "reconstruction.json").write_text(json.dumps(r))
    code, out, err = run_cli(capsys, "import", "--format", "opensfm", d, tmp_path / "x.h5")
    assert_one_line_error(code, err, "reconstruction.json: ", words)
    assert not (tmp_path / "x.h5").exists()


def _line(k, col, value):
    """Line ``k`` (from 1) of tracks.csv with column ``col`` replaced."""
    def change(lines):
        cols = lines[k - 1].split("\t")
        cols[col] = value
        lines[k - 1] = "\t".join(cols)
        return lines
    return change


TRACKS_BAD = {
    "huge feature id": (_line(3, 2, "99999999999999999999"),
                        "tracks.csv:3: feature_id '99999999999999999999' is outside the "
                        "int64 range"),
    "fractional feature id": (_line(3, 2, "1.5"), "tracks.csv:3: feature_id '1.5'"),
    "nan scale": (_line(4, 5, "nan"), "tracks.csv:4: scale"),
    "empty": (lambda lines: [], "tracks.csv: no image measurement"),
    "header only": (lambda lines: lines[:1], "tracks.csv: no image measurement"),
    "conflicting duplicate": (lambda lines: lines + [lines[1].replace(
        lines[1].split("\t")[3], repr(float(lines[1].split("\t")[3]) + 0.1))],
        "lines 2 and "),
}


@pytest.mark.parametrize("case", sorted(TRACKS_BAD) + ["not utf-8"])
def test_bad_tracks_are_one_line_errors(tmp_path, capsys, case):
    d = tmp_path / "ds"
    _dataset(d)
    lines = (d / "tracks.csv").read_text().splitlines()
    if case == "not utf-8":
        raw = ("\n".join(lines[:4]) + "\n").encode() + b"IMG_0000.JPG\t\xe9\t1\t0.1\t0.1\t0.1" \
            b"\t1\t2\t3\n" + ("\n".join(lines[4:]) + "\n").encode()
        (d / "tracks.csv").write_bytes(raw)
        words = ["tracks.csv:5: not a text file"]
    else:
        change, word = TRACKS_BAD[case]
        lines = change(lines)
        (d / "tracks.csv").write_text("".join(ln + "\n" for ln in lines))
        words = [word]
        if case == "conflicting duplicate":
            words += [f"and {len(lines)}: shot 'IMG_0000.JPG' observes track", "px apart"]
    code, out, err = run_cli(capsys, "import", "--format", "opensfm", d, tmp_path / "x.h5")
    assert_one_line_error(code, err, *words)
    assert not (tmp_path / "x.h5").exists()


def test_agreeing_duplicates_are_merged(tmp_path):
    d = tmp_path / "ds"
    _dataset(d)
    base = import_opensfm(d, tmp_path / "a.h5")
    assert base["warnings"] == []
    lines = (d / "tracks.csv").read_text().splitlines()
    cols = lines[1].split("\t")
    x = float(cols[3])
    cols[3] = repr(x + 0.5 / 4000)   # half a pixel off
    lines.append("\t".join(cols))
    (d / "tracks.csv").write_text("\n".join(lines) + "\n")
    r = import_opensfm(d, tmp_path / "b.h5")
    assert r["observations"] == base["observations"]
    assert len(r["warnings"]) == 1 and f"lines 2, {len(lines)}" in r["warnings"][0]
    with Project(tmp_path / "a.h5") as p:
        a = p.read("observations")
    with Project(tmp_path / "b.h5") as p:
        b = p.read("observations")
    moved = np.flatnonzero(np.abs(a["x"] - b["x"]) > 1e-9)
    assert len(moved) == 1 and b["x"][moved[0]] - a["x"][moved[0]] == pytest.approx(0.25)
    # asked to, conflicting ones are averaged too
    cols[3] = repr(x + 0.1)
    lines[-1] = "\t".join(cols)
    (d / "tracks.csv").write_text("\n".join(lines) + "\n")
    r = import_opensfm(d, tmp_path / "c.h5", merge_duplicates=True)
    assert r["observations"] == base["observations"] and len(r["warnings"]) == 2


@pytest.mark.parametrize("case", ["garbage", "missing", "directory", "truncated"])
def test_export_of_a_bad_project_names_it(tmp_path, capsys, case):
    path = tmp_path / "p.h5"
    if case == "garbage":
        path.write_bytes(b"this is not HDF5\n" * 10)
        words = "not a sapgo project (the file is not HDF5)"
    elif case == "directory":
        path.mkdir()
        words = "is a directory"
    elif case == "truncated":
        _dataset(tmp_path / "ds")
        import_opensfm(tmp_path / "ds", tmp_path / "ok.h5")
        path.write_bytes((tmp_path / "ok.h5").read_bytes()[:3000])
        words = "cannot open as HDF5"
    else:
        words = "no such file"
    code, out, err = run_cli(capsys, "export", path, tmp_path / "out", "--format", "opensfm")
    assert_one_line_error(code, err, f"{path}: ", words)


def test_far_image_coordinates_name_the_line(tmp_path, capsys):
    d = tmp_path / "ds"
    _dataset(d)
    lines = _line(3, 3, "1e300")((d / "tracks.csv").read_text().splitlines())
    (d / "tracks.csv").write_text("\n".join(lines) + "\n")
    code, out, err = run_cli(capsys, "import", "--format", "opensfm", d, tmp_path / "x.h5")
    assert_one_line_error(code, err, "tracks.csv:3: x, y 1e+300")
    assert not (tmp_path / "x.h5").exists()
