"""OpenSfM reconstructions (``reconstruction.json`` and ``tracks.csv``): read, import,
export.

``reconstruction.json`` is a list of reconstructions, each ``{"cameras": {name: camera},
"shots": {image: shot}, "points": {track id: point}, ...}``. A shot's pose is world to
camera, ``x = R X + t`` with ``R`` the axis-angle ``rotation``; the camera frame has x to the
right, y down and z forward (COLMAP's). Focal lengths, principal points and image
coordinates are normalised: pixels from the image centre divided by ``max(width,
height)``, y down. ``tracks.csv`` (tab-separated, an ``OPENSFM_TRACKS_VERSION_vN`` header
from v1) holds ``image, track_id, feature_id, x, y, [scale,] r, g, b, [segmentation,
instance]`` per observation, x and y normalised.

Camera models (OpenSfM's ``geometry.rst``), ``(xn, yn) = (X/Z, Y/Z)``, ``r2 = xn^2 + yn^2``:
``perspective`` ``f (1 + k1 r2 + k2 r2^2) (xn, yn)``; ``brown`` ``(fx, fy) * (d xn + 2 p1 xn
yn + p2 (r2 + 2 xn^2), d yn + p1 (r2 + 2 yn^2) + 2 p2 xn yn) + (cx, cy)``, ``d = 1 + k1 r2 +
k2 r2^2 + k3 r2^3``; ``radial`` and ``simple_radial`` are ``brown`` without some terms. These
are COLMAP's OPENCV model (plus k3) in other units, so the conversion to sapgo's camera is
COLMAP's (:func:`sapgo.formats.colmap.sapgo_camera_rows`), in pixels: sapgo's x = ``xn *
S`` and y = ``-yn * S * fx / fy`` with ``S = max(width, height)``. Fisheye and spherical
cameras are refused: sapgo's frame-camera model cannot hold them.

A camera needs every parameter of its projection type (OpenSfM writes them all), with a
plausible value (:data:`MAX_SIZE`, :data:`FOCAL_RANGE`, :data:`MAX_Y_SCALE`,
:data:`MAX_PRINCIPAL_POINT`); a rotation vector is at most :data:`MAX_ROTATION` radians. A
track observed twice on one shot is one observation at the mean of the two when they agree
within 3 sigma (with a warning), else an error naming both lines (unless
``merge_duplicates``), as the other imports do.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np

from ..lock import writes_project
from ..errors import DataError, ParameterError
from .text import decode_text
from ..validate import MAX_MAGNITUDE   # (positions, coordinates: out of range)

__all__ = ["CAMERA_TYPES", "export_opensfm", "import_opensfm", "opensfm_project",
           "read_opensfm"]

#: The camera models taken, with their keys (all needed, as OpenSfM writes them).
CAMERA_TYPES = {
    "perspective": ("focal", "k1", "k2"),
    "brown": ("focal_x", "focal_y", "c_x", "c_y", "k1", "k2", "p1", "p2", "k3"),
    "radial": ("focal_x", "focal_y", "c_x", "c_y", "k1", "k2"),
    "simple_radial": ("focal_x", "focal_y", "c_x", "c_y", "k1"),
}
#: ``(fx, fy, cx, cy, k1, k2, p1, p2, k3)``: normalised, principal point from the centre.
_ROW = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3")
_FLIP = np.diag([1.0, -1.0, -1.0])
#: The largest image width or height taken (pixels).
MAX_SIZE = 1_000_000
#: The focal lengths taken (normalised by ``max(width, height)``: OpenSfM's are near 1).
FOCAL_RANGE = (1e-3, 1e3)
#: ``focal_x / focal_y`` (sapgo's y scale) is taken from ``1 / MAX_Y_SCALE`` to this.
MAX_Y_SCALE = 4.0
#: The largest principal point offset taken (``c_x``, ``c_y``, normalised).
MAX_PRINCIPAL_POINT = 1.0
#: The largest rotation vector taken (radians; OpenSfM writes at most pi): beyond it the
#: angle has lost its precision.
MAX_ROTATION = 1e3
_INT = re.compile(r"[+-]?[0-9]+\Z")
_INT64 = (-(1 << 63), (1 << 63) - 1)


def _show(v):
    """A JSON value as the file could write it, short."""
    try:
        text = json.dumps(v)
    except (TypeError, ValueError):
        text = repr(v)
    return text if len(text) <= 40 else text[:37] + "..."


def _number(v):
    """The float of a JSON number (not a boolean), or None when it is none or not finite."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    try:
        v = float(v)
    except OverflowError:
        return None
    return v if math.isfinite(v) else None


def _load_json(path):
    text = decode_text(path, path.read_bytes())
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise DataError(f"{path}:{exc.lineno}: not JSON: {exc.msg}") from None


def _paths(path):
    path = Path(path)
    if path.is_dir():
        rec = path / "reconstruction.json"
    else:
        rec, path = path, path.parent
    if not rec.exists():
        raise DataError(f"{rec}: no such file (an OpenSfM dataset has reconstruction.json "
                        f"and tracks.csv)")
    tracks = path / "tracks.csv"
    if not tracks.exists():
        raise DataError(f"{tracks}: no such file (the observations of {rec.name})")
    return rec, tracks


def _camera_row(rec, name, cam):
    """A camera's ``_ROW`` values and ``(width, height)``; errors name it."""
    where = f"{rec}: camera {name!r}"
    if not isinstance(cam, dict):
        raise DataError(f"{where}: not an object")
    kind = cam.get("projection_type", "perspective")
    if kind not in CAMERA_TYPES:
        raise DataError(f"{where}: projection_type {kind!r}: sapgo's frame-camera model takes "
                        f"{', '.join(CAMERA_TYPES)}")
    vals = {}
    for key in ("width", "height") + CAMERA_TYPES[kind]:
        v = cam.get(key)
        if v is None:
            raise DataError(f"{where}: {key} is missing")
        x = _number(v)
        if key in ("width", "height"):
            if x is None or not (x.is_integer() and 1 <= x <= MAX_SIZE):
                raise DataError(f"{where}: {key} {_show(v)} is not an image size in pixels "
                                f"(width and height must be whole numbers from 1 to "
                                f"{MAX_SIZE})")
        elif x is None:
            raise DataError(f"{where}: {key} {_show(v)} is not a finite number")
        vals[key] = x
    for key in ("focal", "focal_x", "focal_y"):
        if key not in vals:
            continue
        if vals[key] <= 0:
            raise DataError(f"{where}: the focal length must be positive ({key} "
                            f"{vals[key]:g})")
        lo, hi = FOCAL_RANGE
        if not lo <= vals[key] <= hi:
            raise DataError(f"{where}: {key} {vals[key]:g} is not a plausible focal length "
                            f"(normalised by max(width, height): from {lo:g} to {hi:g})")
    for key in ("c_x", "c_y"):
        if key in vals and abs(vals[key]) > MAX_PRINCIPAL_POINT:
            raise DataError(f"{where}: {key} {vals[key]:g} is not a plausible principal point "
                            f"(normalised, from the image centre: at most "
                            f"{MAX_PRINCIPAL_POINT:g} either way)")
    if kind == "perspective":
        vals["focal_x"] = vals["focal_y"] = vals["focal"]
    ratio = vals["focal_x"] / vals["focal_y"]
    if not 1 / MAX_Y_SCALE <= ratio <= MAX_Y_SCALE:
        raise DataError(f"{where}: focal_x / focal_y = {ratio:g} is not a plausible pixel "
                        f"aspect ratio (sapgo scales the image y axis by it: from "
                        f"{1 / MAX_Y_SCALE:g} to {MAX_Y_SCALE:g})")
    row = [vals["focal_x"], vals["focal_y"], vals.get("c_x", 0.0), vals.get("c_y", 0.0),
           vals.get("k1", 0.0), vals.get("k2", 0.0), vals.get("p1", 0.0),
           vals.get("p2", 0.0), vals.get("k3", 0.0)]
    return kind, row, (vals["width"], vals["height"])


def _vec(rec, what, v, n=3):
    out = [_number(x) for x in v] if isinstance(v, list) else []
    if len(out) != n or None in out:
        raise DataError(f"{rec}: {what}: expected {n} finite numbers, got {v!r}"[:300])
    return out


def read_opensfm(path, index=0):
    """Read reconstruction ``index`` of an OpenSfM dataset (its directory, or its
    ``reconstruction.json`` with ``tracks.csv`` beside it): a dict of ``cameras`` (names),
    ``camera_types``, ``camera_rows`` (n x 9, :data:`_ROW`), ``sizes`` (n x 2), ``shots``
    (names), ``shot_camera`` (indices), ``rotations`` (world to camera, n x 3 x 3),
    ``translations``, ``points`` (track ids), ``xyz``, ``colors``, ``obs_shot``,
    ``obs_point``, ``obs_xy`` (normalised), ``obs_feature``, ``obs_scale``, ``obs_line``
    (in ``tracks.csv``), ``version`` and ``reconstructions`` (how many the file holds).
    Tracks of images or points not in the reconstruction are left out; a reconstruction
    without points or observations is refused. Errors name the file, and the line in
    ``tracks.csv``."""
    from scipy.spatial.transform import Rotation

    rec_path, tracks_path = _paths(path)
    data = _load_json(rec_path)
    if not isinstance(data, list) or not data:
        raise DataError(f"{rec_path}: expected a list of reconstructions")
    if not 0 <= index < len(data):
        raise ParameterError(f"{rec_path} holds {len(data)} reconstruction(s): the index "
                             f"{index} is not one of 0..{len(data) - 1}")
    r = data[index]
    if not isinstance(r, dict) or not all(isinstance(r.get(k), dict) for k in
                                          ("cameras", "shots", "points")):
        raise DataError(f"{rec_path}: reconstruction {index}: expected an object with "
                        f"'cameras', 'shots' and 'points'")
    cameras = sorted(r["cameras"])
    c_index = {c: i for i, c in enumerate(cameras)}
    types, rows, sizes = [], [], []
    for c in cameras:
        kind, row, size = _camera_row(rec_path, c, r["cameras"][c])
        types.append(kind)
        rows.append(row)
        sizes.append(size)
    shots = sorted(r["shots"])
    if not shots:
        raise DataError(f"{rec_path}: reconstruction {index} has no shots")
    s_index = {s: i for i, s in enumerate(shots)}
    shot_camera, rotvec, trans = [], [], []
    for s in shots:
        sh = r["shots"][s]
        if not isinstance(sh, dict) or sh.get("camera") not in c_index:
            raise DataError(f"{rec_path}: shot {s!r}: its camera "
                            f"{sh.get('camera') if isinstance(sh, dict) else None!r} is "
                            f"not one of the reconstruction's cameras")
        shot_camera.append(c_index[sh["camera"]])
        rv = _vec(rec_path, f"shot {s!r}: rotation", sh.get("rotation"))
        angle = math.hypot(*rv)
        if not angle <= MAX_ROTATION:
            raise DataError(f"{rec_path}: shot {s!r}: rotation {_show(rv)}: a rotation "
                            f"vector of {angle:.3g} rad is not usable (at most "
                            f"{MAX_ROTATION:g}; OpenSfM writes at most pi)")
        rotvec.append(rv)
        trans.append(_vec(rec_path, f"shot {s!r}: translation", sh.get("translation")))
    points = sorted(r["points"])
    if not points:
        raise DataError(f"{rec_path}: reconstruction {index} has no points (the block has "
                        f"no image measurement)")
    p_index = {p: i for i, p in enumerate(points)}
    xyz, colors = [], []
    for p in points:
        pt = r["points"][p]
        xyz.append(_vec(rec_path, f"point {p!r}: coordinates",
                        pt.get("coordinates") if isinstance(pt, dict) else None))
        col = pt.get("color", [128, 128, 128])
        rgb = _vec(rec_path, f"point {p!r}: color", col)
        if not all(0 <= c <= 255 for c in rgb):
            raise DataError(f"{rec_path}: point {p!r}: color {_show(col)}: red, green and "
                            f"blue must be from 0 to 255")
        colors.append(rgb)
    rotations = Rotation.from_rotvec(np.array(rotvec)).as_matrix().reshape(-1, 3, 3)
    bad = ~np.isfinite(rotations).all(axis=(1, 2))
    if bad.any():
        i = int(np.argmax(bad))
        raise DataError(f"{rec_path}: shot {shots[i]!r}: rotation {_show(rotvec[i])} is not a "
                        f"usable rotation vector")
    obs = _read_tracks(tracks_path, s_index, p_index)
    if not len(obs["obs_shot"]):
        raise DataError(f"{tracks_path}: no image measurement: no line observes a track of "
                        f"{rec_path.name}'s reconstruction {index} on one of its shots")
    return {"cameras": cameras, "camera_types": types,
            "camera_rows": np.array(rows, np.float64).reshape(-1, 9),
            "sizes": np.array(sizes, np.float64).reshape(-1, 2), "shots": shots,
            "shot_camera": np.array(shot_camera, np.int64),
            "rotations": rotations,
            "translations": np.array(trans, np.float64).reshape(-1, 3), "points": points,
            "xyz": np.array(xyz, np.float64).reshape(-1, 3),
            "colors": np.clip(np.round(np.array(colors, np.float64).reshape(-1, 3)), 0,
                              255).astype(np.uint8),
            "reconstructions": len(data), **obs}


def _read_tracks(path, s_index, p_index):
    """The observations of ``tracks.csv`` on the reconstruction's shots and points."""
    ncols = {0: 8, 1: 9, 2: 11}
    shot, point, xy, feature, scale, where = [], [], [], [], [], []
    version = 0
    with open(path, newline="", encoding="utf-8-sig", errors="surrogateescape") as f:
        for k, line in enumerate(f, start=1):
            line = line.rstrip("\r\n")
            if not line.isascii():
                try:
                    line.encode("utf-8")
                except UnicodeEncodeError:
                    raise DataError(f"{path}:{k}: not a text file (a byte that is not "
                                    f"UTF-8)") from None
            if k == 1 and line.startswith("OPENSFM_TRACKS_VERSION_v"):
                try:
                    version = int(line[len("OPENSFM_TRACKS_VERSION_v"):])
                except ValueError:
                    version = -1
                if version not in ncols:
                    raise DataError(f"{path}:1: tracks version {line[:60]!r}: sapgo reads "
                                    f"v0, v1 and v2")
                continue
            if not line.strip():
                continue
            cols = line.split("\t")
            if len(cols) != ncols[version]:
                raise DataError(f"{path}:{k}: expected {ncols[version]} tab-separated "
                                f"columns (tracks v{version}), got {len(cols)}")
            s, p = s_index.get(cols[0]), p_index.get(cols[1])
            if s is None or p is None:
                continue
            tok = cols[2].strip()
            if not _INT.match(tok):
                raise DataError(f"{path}:{k}: feature_id {tok[:40]!r} is not an integer")
            feat = int(tok)
            if not _INT64[0] <= feat <= _INT64[1]:
                raise DataError(f"{path}:{k}: feature_id {tok[:40]!r} is outside the int64 "
                                f"range")
            vals = []
            for name, col in (("x", 3), ("y", 4), ("scale", 5))[:3 if version >= 1 else 2]:
                try:
                    v = float(cols[col])
                except ValueError:
                    raise DataError(f"{path}:{k}: {name} {cols[col][:40]!r} is not a "
                                    f"number") from None
                if not math.isfinite(v):
                    raise DataError(f"{path}:{k}: {name} {cols[col][:40]!r} is not finite")
                vals.append(v)
            shot.append(s)
            point.append(p)
            xy.append(vals[:2])
            feature.append(feat)
            scale.append(vals[2] if version >= 1 else 0.0)
            where.append(k)
    return {"obs_shot": np.array(shot, np.int64), "obs_point": np.array(point, np.int64),
            "obs_xy": np.array(xy, np.float64).reshape(-1, 2),
            "obs_feature": np.array(feature, np.int64),
            "obs_scale": np.array(scale, np.float64), "obs_line": np.array(where, np.int64),
            "version": version}


def _sapgo_cameras(rows, sizes):
    """sapgo camera rows (pixels, y up from the centre) and y scales of OpenSfM camera rows
    (:data:`_ROW`, normalised) and sizes."""
    from .colmap import sapgo_camera_rows

    big = sizes.max(axis=1)
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = rows.T
    params = np.column_stack([fx * big, fy * big, sizes[:, 0] / 2 + cx * big,
                              sizes[:, 1] / 2 + cy * big, k1, k2, p1, p2])
    out, s = sapgo_camera_rows(params, sizes)
    out[:, 5] = k3 / out[:, 0] ** 6
    return out, s


def _opensfm_cameras(rows, y_scale, sizes):
    """The inverse of :func:`_sapgo_cameras`."""
    from .colmap import colmap_params

    params = colmap_params(rows, y_scale, sizes)
    big = sizes.max(axis=1)
    fx, fy, cx, cy, k1, k2, p1, p2 = params.T
    return np.column_stack([fx / big, fy / big, (cx - sizes[:, 0] / 2) / big,
                            (cy - sizes[:, 1] / 2) / big, k1, k2, p1, p2,
                            rows[:, 5] * rows[:, 0] ** 6])


def opensfm_project(d, cam, r, t, xyz):
    """OpenSfM's own projection (normalised image coordinates, n x 2) of points ``xyz`` by
    cameras ``cam`` (n x 9, :data:`_ROW`) at poses ``r``, ``t`` (the reference for the
    conversion; ``d`` unused, for symmetry with the readers)."""
    pc = np.einsum("nij,nj->ni", r, xyz) + t
    xn, yn = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
    fx, fy, cx, cy, k1, k2, p1, p2, k3 = cam.T
    r2 = xn * xn + yn * yn
    dr = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 ** 3
    xd = dr * xn + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
    yd = dr * yn + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
    return np.column_stack([fx * xd + cx, fy * yd + cy])


def _merge_duplicates(path, d, xy, tol, merge):
    """Each (shot, track) pair observed more than once in ``d`` (a :func:`read_opensfm`
    dict, its ``obs_*`` arrays cut in place to the pair's first observation) merged at the
    mean of ``xy`` (its observations in pixels; the merged ones returned) and of its
    normalised ``obs_xy``, by :func:`sapgo.formats.bal.merge_repeats`: observations of a
    pair more than ``tol`` pixels apart are an error naming both lines of ``path``
    (``tracks.csv``), unless ``merge``. Returns the merged ``xy`` and warning lines (none
    without duplicates)."""
    from .bal import merge_repeats

    shot, pt, lines = d["obs_shot"], d["obs_point"], d["obs_line"]
    return merge_repeats(
        path, d, shot * (len(d["points"]) + 1) + pt, xy, tol, merge,
        lambda i: str(int(lines[i])),
        lambda i: (f"shot {d['shots'][shot[i]]!r}", f"track {d['points'][pt[i]]!r}"),
        "(shot, track)", "correct or remove one, or give --merge-duplicates",
        also=("obs_xy",))


def _int_ids(names):
    """The names as int64 ids when all are decimal integers (distinct), else 1, 2, ..."""
    try:
        ids = np.array([int(n) for n in names], np.int64)
        if len(np.unique(ids)) == len(ids) and all(str(i) == n for i, n in zip(ids, names)):
            return ids
    except (ValueError, OverflowError):
        pass
    return np.arange(1, len(names) + 1, dtype=np.int64)


@writes_project("import", "out")
def import_opensfm(path, out, index=0, sigma_image=1.0, force=False,
                   merge_duplicates=False):
    """Import reconstruction ``index`` of the OpenSfM dataset ``path`` into a new project
    ``out``: one sapgo camera per OpenSfM camera (intrinsics held fixed), one photo per shot
    (ids 1, 2, ... in the order of the image names), one pass point per point (ids: the
    track ids when they are integers, else 1, 2, ... in their order), one observation per
    track entry on a reconstructed shot and point; pixels from the image centre, y up,
    sigma ``sigma_image`` pixels; a free network. Names, camera types, sizes, colours,
    feature ids and scales go to ``/opensfm``. A track observed more than once on a shot
    is one observation at their mean when they agree within 3 sigma, else an error naming
    both lines unless ``merge_duplicates`` (the first one's feature id and scale kept).
    Returns a summary dict (``warnings``: lines for the user)."""
    from ..frames import opk_of
    from ..project import new_project_path
    from .bal import write_snavely_project

    out = new_project_path(out, force)
    if not (sigma_image > 0 and math.isfinite(sigma_image)):
        raise ParameterError(f"--sigma-image must be a positive number of pixels, found "
                             f"{sigma_image!r}")
    d = read_opensfm(path, index)
    rec_path, tracks_path = _paths(path)
    with np.errstate(all="ignore"):
        rows, y_scale = _sapgo_cameras(d["camera_rows"], d["sizes"])
        formats = np.column_stack([d["sizes"][:, 0], d["sizes"][:, 1] * y_scale])
    bad = ~(np.isfinite(rows).all(axis=1) & np.isfinite(formats).all(axis=1))
    if bad.any():
        c = int(np.argmax(bad))
        raise DataError(f"{rec_path}: camera {d['cameras'][c]!r}: its parameters do not "
                        f"convert to finite values of sapgo's camera (f, x0, y0, k1, k2, k3, "
                        f"p1, p2 in pixels: {', '.join(f'{v:g}' for v in rows[c, :8])})")
    cam = d["shot_camera"]
    big = d["sizes"].max(axis=1)
    r = d["rotations"]
    with np.errstate(all="ignore"):
        eo = np.column_stack([opk_of(_FLIP @ r),
                              -np.einsum("nji,nj->ni", r, d["translations"])])
    bad = ~(np.isfinite(eo).all(axis=1) & (np.abs(eo[:, 3:]) <= MAX_MAGNITUDE).all(axis=1))
    if bad.any():
        s = int(np.argmax(bad))
        raise DataError(f"{rec_path}: shot {d['shots'][s]!r}: its rotation and translation "
                        f"put the camera at {_show(eo[s, 3:].tolist())}, beyond "
                        f"{MAX_MAGNITUDE:g}: a value out of range")
    bad = ~(np.abs(d["xyz"]) <= MAX_MAGNITUDE).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise DataError(f"{rec_path}: point {d['points'][i]!r}: coordinates "
                        f"{_show(d['xyz'][i].tolist())} beyond {MAX_MAGNITUDE:g}: a value "
                        f"out of range")
    o_cam = cam[d["obs_shot"]]
    xy = np.column_stack([d["obs_xy"][:, 0] * big[o_cam],
                          -d["obs_xy"][:, 1] * big[o_cam] * y_scale[o_cam]])
    bad = ~(np.abs(xy) <= MAX_MAGNITUDE).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise DataError(f"{tracks_path}:{d['obs_line'][i]}: x, y {d['obs_xy'][i, 0]:g}, "
                        f"{d['obs_xy'][i, 1]:g} are {_show(xy[i].tolist())} pixels, beyond "
                        f"{MAX_MAGNITUDE:g}: a value out of range")
    from .bal import DUPLICATE_SIGMAS

    xy, warnings = _merge_duplicates(tracks_path, d, xy, DUPLICATE_SIGMAS * sigma_image,
                                     merge_duplicates)
    o_cam = cam[d["obs_shot"]]
    # the reference: OpenSfM's own reprojection error, pixels
    proj = opensfm_project(d, d["camera_rows"][o_cam], r[d["obs_shot"]],
                           d["translations"][d["obs_shot"]], d["xyz"][d["obs_point"]])
    err = np.linalg.norm(proj - d["obs_xy"], axis=1) * big[o_cam]
    ids_shot = np.arange(1, len(d["shots"]) + 1, dtype=np.int64)
    ids_point = _int_ids(d["points"])

    def extra(file):
        import h5py

        text = h5py.string_dtype()
        g = file.create_group("opensfm")
        g.attrs["source"] = str(path)
        g.attrs["reconstruction"] = index
        g.attrs["tracks_version"] = d["version"]
        c = np.zeros(len(d["cameras"]), [("id", "<i8"), ("name", text), ("type", text),
                                         ("width", "<f8"), ("height", "<f8"),
                                         ("y_scale", "<f8")])
        c["id"] = np.arange(1, len(c) + 1)
        c["name"], c["type"] = d["cameras"], d["camera_types"]
        c["width"], c["height"] = d["sizes"][:, 0], d["sizes"][:, 1]
        c["y_scale"] = y_scale
        g.create_dataset("cameras", data=c)
        s = np.zeros(len(d["shots"]), [("id", "<i8"), ("name", text)])
        s["id"], s["name"] = ids_shot, d["shots"]
        g.create_dataset("shots", data=s)
        p = np.zeros(len(d["points"]), [("id", "<i8"), ("name", text), ("rgb", "u1", (3,))])
        p["id"], p["name"], p["rgb"] = ids_point, d["points"], d["colors"]
        g.create_dataset("points", data=p)
        o = np.zeros(len(d["obs_shot"]), [("point_id", "<i8"), ("photo_id", "<i8"),
                                          ("feature", "<i8"), ("scale", "<f8")])
        o["point_id"], o["photo_id"] = ids_point[d["obs_point"]], ids_shot[d["obs_shot"]]
        o["feature"], o["scale"] = d["obs_feature"], d["obs_scale"]
        g.create_dataset("observations", data=o[np.lexsort((o["feature"], o["photo_id"],
                                                            o["point_id"]))])

    n = write_snavely_project(
        out, {"command": "import", "format": "opensfm", "path": str(path), "index": index},
        eo, None, ids_shot, d["xyz"], d["obs_shot"], d["obs_point"], xy, "fixed", extra,
        point_ids=ids_point, cameras=(np.arange(1, len(rows) + 1), rows, formats, cam),
        sigma_image=sigma_image)
    return {"path": str(out), "cameras": len(d["cameras"]), "photos": len(d["shots"]),
            "points": len(d["points"]), "observations": n,
            "reconstructions": d["reconstructions"], "index": index,
            "mean_error_px": float(err.mean()) if len(err) else 0.0,
            "warnings": warnings}


def export_opensfm(project_path, out_dir, adjusted=True):
    """Write a project imported from OpenSfM (its adjusted values, or the inputs) as an
    OpenSfM dataset: ``reconstruction.json`` (one reconstruction: its cameras, with the
    adjusted values where they were adjusted, its shots and points) and ``tracks.csv`` (v1)
    in ``out_dir``, with the names, camera types, colours, feature ids and scales it was
    imported with. Returns a dict of counts."""
    from scipy.spatial.transform import Rotation

    from ..frames import rotation_matrices
    from ..project import Project
    from .bal import snavely_block

    with Project(project_path) as p:   # (its errors name the file: not HDF5, missing, ...)
        g = p.file.get("opensfm")
        if g is None:
            raise DataError(f"{project_path}: not imported from OpenSfM (no /opensfm): the "
                            f"names of its cameras, images and tracks are not known")
        cams, shots, pts, obs = (g[k][()] for k in ("cameras", "shots", "points",
                                                    "observations"))
    b = snavely_block(project_path, adjusted, "OpenSfM", any_camera=True)
    for what, have, ids in (("photo", shots["id"], b["station_ids"]),
                            ("point", pts["id"], b["point_ids"]),
                            ("camera", np.arange(len(cams)), np.unique(b["camera_of_station"]))):
        missing = np.setdiff1d(ids, have)
        if len(missing):
            raise DataError(f"{project_path}: {what} id {int(missing[0])} is not in /opensfm "
                            f"(the project changed after its import): its OpenSfM name is "
                            f"not known")
    dec = np.vectorize(lambda v: v.decode() if isinstance(v, bytes) else str(v), otypes=[object])
    cam_name, cam_type, shot_name = dec(cams["name"]), dec(cams["type"]), dec(shots["name"])
    pt_name = dec(pts["name"])
    sizes = np.column_stack([cams["width"], cams["height"]])
    # each photo's camera, by its record (the import made one camera per OpenSfM camera)
    st_cam = b["camera_of_station"]
    rows = b["camera_rows"]
    orows = _opensfm_cameras(rows, cams["y_scale"], sizes)
    recon = {"cameras": {}, "shots": {}, "points": {}, "biases": {}}
    for i, name in enumerate(cam_name):
        v = dict(zip(_ROW, orows[i].tolist()))
        c = {"projection_type": cam_type[i], "width": int(sizes[i, 0]),
             "height": int(sizes[i, 1])}
        if cam_type[i] == "perspective":
            c.update(focal=v["fx"], k1=v["k1"], k2=v["k2"])
        else:
            keys = {"brown": ("focal_x", "focal_y", "c_x", "c_y", "k1", "k2", "p1", "p2",
                              "k3"),
                    "radial": ("focal_x", "focal_y", "c_x", "c_y", "k1", "k2"),
                    "simple_radial": ("focal_x", "focal_y", "c_x", "c_y", "k1")}[cam_type[i]]
            src = {"focal_x": "fx", "focal_y": "fy", "c_x": "cx", "c_y": "cy"}
            c.update({k: v[src.get(k, k)] for k in keys})
        recon["cameras"][name] = c
    r = _FLIP @ rotation_matrices(b["eo"][:, :3])
    t = -np.einsum("nij,nj->ni", r, b["eo"][:, 3:])
    rv = Rotation.from_matrix(r).as_rotvec()
    s_of_id = dict(zip(shots["id"].tolist(), shot_name))
    for j, sid in enumerate(b["station_ids"].tolist()):
        recon["shots"][s_of_id[sid]] = {"camera": cam_name[st_cam[j]],
                                        "rotation": rv[j].tolist(),
                                        "translation": t[j].tolist()}
    p_row = {pid: k for k, pid in enumerate(pts["id"].tolist())}
    for j, pid in enumerate(b["point_ids"].tolist()):
        k = p_row[pid]
        recon["points"][pt_name[k]] = {"coordinates": b["xyz"][j].tolist(),
                                       "color": [float(x) for x in pts["rgb"][k]]}
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "reconstruction.json").write_text(json.dumps([recon], indent=1))
    # observations: back to normalised coordinates
    big = sizes.max(axis=1)
    oc = st_cam[b["obs_camera"]]
    xn = b["obs_xy"][:, 0] / big[oc]
    yn = -b["obs_xy"][:, 1] / (big[oc] * cams["y_scale"][oc])
    pid = b["point_ids"][b["obs_point"]]
    sid = b["station_ids"][b["obs_camera"]]
    key = obs["point_id"] * (len(shots) + 1) + obs["photo_id"]
    want = pid * (len(shots) + 1) + sid
    at = np.minimum(np.searchsorted(key, want), max(len(key) - 1, 0))
    hit = (key[at] == want) if len(key) else np.zeros(len(want), bool)
    feat = np.where(hit, obs["feature"][at] if len(key) else 0, -1)
    scale = np.where(hit, obs["scale"][at] if len(key) else 0.0, 0.0)
    with open(out_dir / "tracks.csv", "w") as f:
        f.write("OPENSFM_TRACKS_VERSION_v1\n")
        for j, (p_id, s_id, ft, x, y, sc) in enumerate(zip(
                pid.tolist(), sid.tolist(), feat.tolist(), xn.tolist(), yn.tolist(),
                scale.tolist())):
            k = p_row[p_id]
            rgb = pts["rgb"][k].tolist()
            f.write(f"{s_of_id[s_id]}\t{pt_name[k]}\t{ft}\t{x!r}\t{y!r}\t{sc!r}\t"
                    f"{rgb[0]}\t{rgb[1]}\t{rgb[2]}\n")
    return {"cameras": len(cam_name), "photos": len(b["station_ids"]),
            "points": len(b["point_ids"]), "observations": len(pid)}
