"""COLMAP's text model (``cameras.txt``, ``images.txt``, ``points3D.txt``): read, convert,
write.

The files (COLMAP's documentation, "Output format"; ``#`` starts a comment line)::

    cameras.txt    CAMERA_ID MODEL WIDTH HEIGHT PARAMS...
    images.txt     IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME     two lines per image:
                   X Y POINT3D_ID  X Y POINT3D_ID ...               (may be empty; -1 = no
                                                                     3D point)
    points3D.txt   POINT3D_ID X Y Z R G B ERROR IMAGE_ID POINT2D_IDX IMAGE_ID POINT2D_IDX ...

Camera model (COLMAP's ``sensor/models.h``): ``x_cam = R X + t`` with ``R`` the rotation of
the unit quaternion ``(qw, qx, qy, qz)`` (world to camera); the camera looks along +z, image
y points down; ``x' = x_cam / z_cam``, ``y' = y_cam / z_cam``, ``r2 = x'^2 + y'^2``,
``x'' = x' (1 + k1 r2 + k2 r2^2) + 2 p1 x' y' + p2 (r2 + 2 x'^2)``,
``y'' = y' (1 + k1 r2 + k2 r2^2) + p1 (r2 + 2 y'^2) + 2 p2 x' y'``,
pixel ``u = fx x'' + cx``, ``v = fy y'' + cy``, the centre of the upper-left pixel at
(0.5, 0.5). Models read: PINHOLE (fx fy cx cy), SIMPLE_RADIAL (f cx cy k), RADIAL (f cx cy k1
k2) and OPENCV (fx fy cx cy k1 k2 p1 p2); fx = fy = f and p1 = p2 = 0 for the radial ones.

This is sapgo's collinearity model (docs/theory.md section 1; ``sapgo.geometry``) in pixels,
exactly: ``M = diag(1, -1, -1) R`` (sapgo's camera looks along -w with image y up),
``Xc = -R' t``; image coordinates from the image centre, y up, ``x = u - W/2`` and
``y = s (H/2 - v)`` with ``s = fx / fy`` (sapgo has one focal length: the y axis is scaled
so that ``fy s = fx``); focal length ``f = fx``, principal point ``x0 = cx - W/2``,
``y0 = s (H/2 - cy)``, Brown distortion in pixels ``k1 / f^2``, ``k2 / f^4``, ``k3 = 0``,
``p1 = p2_colmap / f``, ``p2 = -p1_colmap / f``. The y residuals are then ``-s`` times
COLMAP's (the geometry is exact; only the weight of y differs by ``s^2``, a few 1e-3 at most
for real cameras).

What sapgo does not use is kept in the project's ``/colmap`` group, keyed by ids (the records
are reordered by ``sapgo order``), so that :func:`export_colmap` reproduces the model: camera
models and sizes, image names, the POINT2D_IDX of every observation, the 2D points without a
3D point, point colours (docs/project-schema.md).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..lock import writes_project
from ..errors import DataError, ParameterError
from .text import decode_text

#: Camera models read and written, with COLMAP's parameter names in file order.
CAMERA_MODELS = {
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}
#: The general parameter vector every model is held in (OPENCV's).
PARAMS = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")
#: Where each model's parameters go in :data:`PARAMS` (``f`` fills fx and fy).
_SLOTS = {"PINHOLE": ((0,), (1,), (2,), (3,)),
          "SIMPLE_RADIAL": ((0, 1), (2,), (3,), (4,)),
          "RADIAL": ((0, 1), (2,), (3,), (4,), (5,)),
          "OPENCV": ((0,), (1,), (2,), (3,), (4,), (5,), (6,), (7,))}
FILES = ("cameras.txt", "images.txt", "points3D.txt")
#: Largest deviation of a quaternion's norm from 1 that is read (it is then normalised).
QUATERNION_TOLERANCE = 1e-6
#: Records of the ``/colmap`` group (docs/project-schema.md).
COLMAP_CAMERA_DTYPE = np.dtype([("id", "<i8"), ("model", "S16"), ("width", "<i8"),
                                ("height", "<i8"), ("y_scale", "<f8")])
COLMAP_POINT_DTYPE = np.dtype([("id", "<i8"), ("rgb", "u1", (3,))])
COLMAP_POINT2D_DTYPE = np.dtype([("image_id", "<i8"), ("index", "<i8"), ("x", "<f8"),
                                 ("y", "<f8")])
COLMAP_OBSERVATION_DTYPE = np.dtype([("point_id", "<i8"), ("image_id", "<i8"),
                                     ("rank", "<i4"), ("index", "<i8")])


def _image_dtype():
    import h5py

    return np.dtype([("id", "<i8"), ("name", h5py.string_dtype()),
                     ("qvec_read", "<f8", (4,))])


# -- reading ---------------------------------------------------------------------------

def _lines(path):
    try:
        text = decode_text(path, path.read_bytes())
    except IsADirectoryError:
        raise DataError(f"{path}: is a directory, not a file of a COLMAP text model") from None
    except OSError as exc:
        raise DataError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    return text.lstrip("\ufeff").splitlines()


def _data(lines):
    """(line number, fields) of the lines that are neither blank nor a comment."""
    for k, text in enumerate(lines):
        s = text.strip()
        if s and s[0] != "#":
            yield k + 1, s.split()


_INT64 = (-(1 << 63), (1 << 63) - 1)


def _int(tok, where, col, name):
    try:
        v = int(tok)
    except ValueError:
        raise DataError(f"{where}: {tok[:40]!r} is not an integer (column {col}, {name})") \
            from None
    if not _INT64[0] <= v <= _INT64[1]:
        raise DataError(f"{where}: {tok[:40]!r} is outside the int64 range (column {col}, "
                        f"{name})")
    return v


def _float(tok, where, col, name):
    try:
        v = float(tok)
    except ValueError:
        raise DataError(f"{where}: {tok[:40]!r} is not a number (column {col}, {name})") \
            from None
    if not math.isfinite(v):
        raise DataError(f"{where}: column {col} ({name}) is {tok}, expected a finite number")
    return v


def _bad_column(toks, parse, names):
    """Raise for the first of ``toks`` that ``parse`` refuses (columns counted from 1)."""
    for i, t in enumerate(toks):
        parse(t, i + 1, names[i % len(names)])


def _read_cameras(path):
    ids, models, size, params, lines = [], [], [], [], {}
    for ln, tok in _data(_lines(path)):
        where = f"{path}:{ln}"
        if len(tok) < 4:
            raise DataError(f"{where}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS..., found "
                            f"{len(tok)} field(s)")
        cid = _int(tok[0], where, 1, "CAMERA_ID")
        model = tok[1]
        if model not in CAMERA_MODELS:
            raise DataError(f"{where}: camera model {model[:40]!r} (column 2) is not read; "
                            f"sapgo reads {', '.join(CAMERA_MODELS)}")
        names = CAMERA_MODELS[model]
        if len(tok) != 4 + len(names):
            raise DataError(f"{where}: a {model} camera has {len(names)} parameters "
                            f"({' '.join(names)}), found {len(tok) - 4}")
        w, h = _int(tok[2], where, 3, "WIDTH"), _int(tok[3], where, 4, "HEIGHT")
        if w <= 0 or h <= 0:
            raise DataError(f"{where}: WIDTH and HEIGHT must be positive, found {w} {h}")
        vals = [_float(t, where, 5 + i, names[i]) for i, t in enumerate(tok[4:])]
        row = np.zeros(len(PARAMS))
        for v, slots in zip(vals, _SLOTS[model]):
            row[list(slots)] = v
        if not (row[0] > 0 and row[1] > 0):
            raise DataError(f"{where}: the focal length must be positive (column 5"
                            f"{'' if model in ('SIMPLE_RADIAL', 'RADIAL') else ' or 6'})")
        if cid in lines:
            raise DataError(f"{where}: camera {cid} is given twice (also line {lines[cid]})")
        lines[cid] = ln
        ids.append(cid)
        models.append(model)
        size.append((w, h))
        params.append(row)
    if not ids:
        raise DataError(f"{path}: no camera")
    return {"ids": np.array(ids, np.int64), "models": models,
            "size": np.array(size, np.int64).reshape(-1, 2),
            "params": np.array(params).reshape(-1, len(PARAMS)), "lines": lines}


def _read_images(path, cameras):
    lines = _lines(path)
    cam_of = {c: i for i, c in enumerate(cameras["ids"].tolist())}
    ids, qvec, tvec, cam, names, head_lines, pts_lines = [], [], [], [], [], [], []
    xs, ys, pids, counts = [], [], [], []
    seen, named = {}, {}
    k = 0
    while k < len(lines):
        s = lines[k].strip()
        if not s or s[0] == "#":
            k += 1
            continue
        ln = k + 1
        where = f"{path}:{ln}"
        tok = s.split()
        if len(tok) != 10:
            raise DataError(f"{where}: expected 10 fields (IMAGE_ID QW QX QY QZ TX TY TZ "
                            f"CAMERA_ID NAME), found {len(tok)}")
        iid = _int(tok[0], where, 1, "IMAGE_ID")
        q = [_float(t, where, 2 + i, n) for i, (t, n) in enumerate(zip(tok[1:5], "QW QX QY QZ"
                                                                       .split()))]
        t = [_float(t, where, 6 + i, n) for i, (t, n) in enumerate(zip(tok[5:8], "TX TY TZ"
                                                                       .split()))]
        cid = _int(tok[8], where, 9, "CAMERA_ID")
        if cid not in cam_of:
            raise DataError(f"{where}: camera {cid} (column 9) is not in cameras.txt")
        norm = math.sqrt(sum(v * v for v in q))
        if not abs(norm - 1.0) <= QUATERNION_TOLERANCE:
            raise DataError(f"{where}: the quaternion QW QX QY QZ (columns 2-5) has the norm "
                            f"{norm!r}, not 1 (tolerance {QUATERNION_TOLERANCE:g})")
        if iid in seen:
            raise DataError(f"{where}: image {iid} is given twice (also line {seen[iid]})")
        seen[iid] = ln
        if tok[9] in named:   # (a name is the image's file: two images cannot share it)
            raise DataError(f"{where}: image {iid}'s NAME {tok[9]!r} (column 10) is also "
                            f"image {named[tok[9]][0]}'s (line {named[tok[9]][1]})")
        named[tok[9]] = (iid, ln)
        # the 2D points: the next line, whatever it holds (empty: no 2D point)
        k += 1
        text = lines[k].strip() if k < len(lines) else ""
        pln = k + 1
        where = f"{path}:{pln}"
        if text[:1] == "#":
            raise DataError(f"{where}: expected the 2D points of image {iid} (X Y POINT3D_ID "
                            f"triples, or an empty line), found a comment")
        pt = text.split()
        if len(pt) % 3:
            raise DataError(f"{where}: the 2D points of image {iid} are X Y POINT3D_ID "
                            f"triples, found {len(pt)} fields")
        try:
            xy = np.array(pt, dtype=object).reshape(-1, 3)
            x = np.array(xy[:, 0], np.float64)
            y = np.array(xy[:, 1], np.float64)
            pid = np.array([int(v) for v in xy[:, 2]], np.int64)
        except (ValueError, OverflowError):
            _bad_column(pt, lambda tok, c, n: (_int if n == "POINT3D_ID" else _float)(
                tok, where, c, n), ("X", "Y", "POINT3D_ID"))
            raise
        bad = np.flatnonzero(~(np.isfinite(x) & np.isfinite(y)))
        if len(bad):
            _bad_column(pt[3 * bad[0]:3 * bad[0] + 2], lambda tok, c, n: _float(
                tok, where, 3 * bad[0] + c, n), ("X", "Y"))
        ids.append(iid)
        qvec.append(q)
        tvec.append(t)
        cam.append(cam_of[cid])
        names.append(tok[9])
        head_lines.append(ln)
        pts_lines.append(pln)
        xs.append(x)
        ys.append(y)
        pids.append(pid)
        counts.append(len(x))
        k += 1
    if not ids:
        raise DataError(f"{path}: no image")
    counts = np.array(counts, np.int64)
    return {"ids": np.array(ids, np.int64), "qvec": np.array(qvec).reshape(-1, 4),
            "tvec": np.array(tvec).reshape(-1, 3), "camera": np.array(cam, np.int64),
            "names": names, "lines": np.array(head_lines, np.int64),
            "points_lines": np.array(pts_lines, np.int64), "n2d": counts,
            "start": np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64),
            "xy": np.column_stack([np.concatenate(xs), np.concatenate(ys)]),
            "point3d": np.concatenate(pids).astype(np.int64)}


def _read_points(path):
    ids, xyz, rgb, err, lines, t_img, t_idx, t_len = [], [], [], [], [], [], [], []
    seen = {}
    for ln, tok in _data(_lines(path)):
        where = f"{path}:{ln}"
        if len(tok) < 8 or (len(tok) - 8) % 2:
            raise DataError(f"{where}: expected POINT3D_ID X Y Z R G B ERROR and IMAGE_ID "
                            f"POINT2D_IDX pairs, found {len(tok)} fields")
        pid = _int(tok[0], where, 1, "POINT3D_ID")
        if pid < 0:
            raise DataError(f"{where}: POINT3D_ID must not be negative, found {pid} (-1 marks "
                            f"a 2D point without a 3D point)")
        if pid in seen:
            raise DataError(f"{where}: 3D point {pid} is given twice (also line {seen[pid]})")
        seen[pid] = ln
        xyz.append([_float(tok[1 + i], where, 2 + i, n) for i, n in enumerate("XYZ")])
        c = [_int(tok[4 + i], where, 5 + i, n) for i, n in enumerate("RGB")]
        for i, v in enumerate(c):
            if not 0 <= v <= 255:
                raise DataError(f"{where}: colour {'RGB'[i]} must be 0 to 255, found {v} "
                                f"(column {5 + i})")
        rgb.append(c)
        try:
            err.append(float(tok[7]))
        except ValueError:
            raise DataError(f"{where}: {tok[7][:40]!r} is not a number (column 8, ERROR)") \
                from None
        track = tok[8:]
        try:
            tr = [int(v) for v in track]
            if tr and not (_INT64[0] <= min(tr) and max(tr) <= _INT64[1]):
                raise ValueError
        except ValueError:
            _bad_column(track, lambda v, c, n: _int(v, where, 8 + c, n),
                        ("IMAGE_ID", "POINT2D_IDX"))
            raise
        t_img.extend(tr[0::2])
        t_idx.extend(tr[1::2])
        t_len.append(len(tr) // 2)
        ids.append(pid)
        lines.append(ln)
    if not ids:
        raise DataError(f"{path}: no 3D point")
    return {"ids": np.array(ids, np.int64), "xyz": np.array(xyz).reshape(-1, 3),
            "rgb": np.array(rgb, np.uint8).reshape(-1, 3), "error": np.array(err),
            "lines": np.array(lines, np.int64), "n_track": np.array(t_len, np.int64),
            "track_image": np.array(t_img, np.int64), "track_index": np.array(t_idx, np.int64)}


def _check_tracks(model, images_path, points_path):
    """The tracks of points3D.txt and the POINT3D_IDs of images.txt must tell the same: every
    track element names an image and one of its 2D points, which names the point back."""
    im, pt = model["images"], model["points"]
    order = np.argsort(pt["ids"])
    sorted_ids = pt["ids"][order]
    # 2D points naming a 3D point that does not exist
    named = np.flatnonzero(im["point3d"] != -1)
    at = np.minimum(np.searchsorted(sorted_ids, im["point3d"][named]), len(sorted_ids) - 1)
    missing = named[sorted_ids[at] != im["point3d"][named]]
    image_of_2d = np.repeat(np.arange(len(im["ids"])), im["n2d"])
    if len(missing):
        g = int(missing[0])
        i = int(image_of_2d[g])
        idx = g - int(im["start"][i])
        raise DataError(f"{images_path}:{im['points_lines'][i]}: 3D point {im['point3d'][g]} "
                        f"(column {3 * idx + 3}, 2D point {idx} of image {im['ids'][i]}) is "
                        f"not in points3D.txt")
    # track elements: a known image, an index in range, the 2D point naming this point
    img_order = np.argsort(im["ids"])
    sorted_img = im["ids"][img_order]
    n_t = len(pt["track_image"])
    owner = np.repeat(np.arange(len(pt["ids"])), pt["n_track"])
    pos = np.arange(n_t) - np.repeat(np.cumsum(pt["n_track"]) - pt["n_track"], pt["n_track"])
    at = np.minimum(np.searchsorted(sorted_img, pt["track_image"]), len(sorted_img) - 1)
    known = sorted_img[at] == pt["track_image"]
    rec = img_order[at]
    idx = pt["track_index"]
    in_range = known & (idx >= 0) & (idx < im["n2d"][rec])
    p3 = np.append(im["point3d"], -2)  # a pad for the elements out of range
    g = np.where(in_range, im["start"][rec] + np.where(in_range, idx, 0), len(p3) - 1)
    names_back = in_range & (p3[g] == pt["ids"][owner])
    first_seen = np.zeros(n_t, bool)
    if n_t:
        u, first = np.unique(np.where(names_back, g, -1 - np.arange(n_t)), return_index=True)
        first_seen[first] = True
    bad = np.flatnonzero(~names_back | ~first_seen)
    if len(bad):
        e = int(bad[0])
        j, p = int(owner[e]), int(pos[e])
        where = f"{points_path}:{pt['lines'][j]}"
        img = int(pt["track_image"][e])
        if not known[e]:
            raise DataError(f"{where}: image {img} (column {9 + 2 * p}) is not in images.txt")
        if not in_range[e]:
            raise DataError(f"{where}: POINT2D_IDX {int(idx[e])} (column {10 + 2 * p}) is out "
                            f"of range: image {img} has {int(im['n2d'][rec[e]])} 2D points")
        if not names_back[e]:
            other = int(p3[g[e]])
            says = "no 3D point" if other == -1 else f"3D point {other}"
            raise DataError(f"{where}: 2D point {int(idx[e])} of image {img} (column "
                            f"{10 + 2 * p}) has {says} in {images_path.name}:"
                            f"{im['points_lines'][rec[e]]}, not this point "
                            f"{int(pt['ids'][j])}")
        raise DataError(f"{where}: 2D point {int(idx[e])} of image {img} (column {10 + 2 * p})"
                        f" is listed twice in the track")
    # every 2D point naming a 3D point is in that point's track
    listed = np.zeros(len(p3), bool)
    listed[g[names_back]] = True
    unlisted = named[~listed[named]]
    if len(unlisted):
        g0 = int(unlisted[0])
        i = int(image_of_2d[g0])
        idx0 = g0 - int(im["start"][i])
        p = int(np.searchsorted(sorted_ids, im["point3d"][g0]))
        raise DataError(f"{images_path}:{im['points_lines'][i]}: 2D point {idx0} of image "
                        f"{im['ids'][i]} (column {3 * idx0 + 3}) names 3D point "
                        f"{im['point3d'][g0]}, whose track ({points_path.name}:"
                        f"{pt['lines'][order[p]]}) does not list it")


def read_colmap(model_dir):
    """Read and check a COLMAP text model: ``dict(cameras, images, points)`` of arrays (the
    cameras' parameters as :data:`PARAMS` rows). Errors name the file and line."""
    model_dir = Path(model_dir)
    if not model_dir.exists():
        raise DataError(f"{model_dir}: no such directory (the COLMAP text model: "
                        f"{', '.join(FILES)})")
    if not model_dir.is_dir():
        raise DataError(f"{model_dir}: not a directory: give the directory of the COLMAP "
                        f"text model ({', '.join(FILES)})")
    paths = [model_dir / f for f in FILES]
    for p in paths:
        if not p.exists():
            binary = p.with_suffix(".bin")
            hint = (f"; {binary.name} is COLMAP's binary model: convert it with 'colmap "
                    f"model_converter --output_type TXT'" if binary.exists() else "")
            raise DataError(f"{p}: no such file (a COLMAP text model has {', '.join(FILES)})"
                            f"{hint}")
    cams = _read_cameras(paths[0])
    model = {"cameras": cams, "images": _read_images(paths[1], cams),
             "points": _read_points(paths[2])}
    _check_tracks(model, paths[1], paths[2])
    return model


# -- the camera model ------------------------------------------------------------------

def rotation_of_quaternion(q):
    """Rotation matrices (n x 3 x 3, world to camera) of quaternions (n x 4: qw qx qy qz),
    normalised first."""
    q = np.asarray(q, np.float64).reshape(-1, 4)
    w, x, y, z = (q / np.linalg.norm(q, axis=1)[:, None]).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], 1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], 1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], 1),
    ], axis=1)


def quaternion_of_rotation(r, reference=None):
    """Unit quaternions (n x 4: qw qx qy qz) of rotation matrices; of the two (q and -q), the
    one nearer to ``reference`` (n x 4) where given, else the one with qw >= 0."""
    from scipy.spatial.transform import Rotation

    xyzw = Rotation.from_matrix(np.asarray(r, np.float64).reshape(-1, 3, 3)).as_quat()
    q = np.column_stack([xyzw[:, 3], xyzw[:, :3]])
    ref = np.column_stack([np.ones(len(q)), np.zeros((len(q), 3))]) if reference is None \
        else np.asarray(reference, np.float64).reshape(-1, 4)
    q[np.einsum("ni,ni->n", q, ref) < 0] *= -1.0
    return q


_FLIP = np.diag([1.0, -1.0, -1.0])


def sapgo_camera_rows(params, size):
    """sapgo camera rows (f, x0, y0, k1, k2, k3, p1, p2 in pixels, y up from the image
    centre) and the y scales ``s = fx / fy`` of COLMAP cameras (:data:`PARAMS` rows and
    WIDTH, HEIGHT)."""
    fx, fy, cx, cy, k1, k2, p1, p2 = np.asarray(params, np.float64).T
    w, h = np.asarray(size, np.float64).T
    s = fx / fy
    f = fx
    rows = np.column_stack([f, cx - w / 2, s * (h / 2 - cy), k1 / f ** 2, k2 / f ** 4,
                            np.zeros_like(f), p2 / f, -p1 / f, np.zeros((len(f), 3))])
    return rows, s


def colmap_params(rows, y_scale, size):
    """The inverse of :func:`sapgo_camera_rows`: :data:`PARAMS` rows (k3 must be 0)."""
    f, x0, y0, k1, k2, _, p1, p2 = np.asarray(rows, np.float64)[:, :8].T
    w, h = np.asarray(size, np.float64).T
    return np.column_stack([f, f / y_scale, x0 + w / 2, h / 2 - y0 / y_scale, k1 * f ** 2,
                            k2 * f ** 4, -p2 * f, p1 * f])


def colmap_project(params, r, t, xyz):
    """COLMAP's projection (pixels, n x 2) of points ``xyz`` (n x 3) by cameras ``params``
    (n x 8, :data:`PARAMS`) at poses ``r`` (n x 3 x 3, world to camera) and ``t`` (n x 3)."""
    pc = np.einsum("nij,nj->ni", r, xyz) + t
    with np.errstate(divide="ignore", invalid="ignore"):
        xn, yn = pc[:, 0] / pc[:, 2], pc[:, 1] / pc[:, 2]
    fx, fy, cx, cy, k1, k2, p1, p2 = np.asarray(params, np.float64).T
    r2 = xn * xn + yn * yn
    radial = k1 * r2 + k2 * r2 * r2
    xd = xn + xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
    yd = yn + yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
    return np.column_stack([fx * xd + cx, fy * yd + cy])


def stations_of_poses(q, t):
    """sapgo stations (omega, phi, kappa, Xc, Yc, Zc) of COLMAP poses."""
    from ..frames import opk_of

    r = rotation_of_quaternion(q)
    centre = -np.einsum("nji,nj->ni", r, t)
    return np.column_stack([opk_of(_FLIP @ r), centre])


def poses_of_stations(eo, reference=None):
    """The inverse of :func:`stations_of_poses`: rotation matrices, quaternions and
    translations."""
    from ..frames import rotation_matrices

    r = _FLIP @ rotation_matrices(eo[:, :3])
    t = -np.einsum("nij,nj->ni", r, eo[:, 3:])
    return r, quaternion_of_rotation(r, reference), t


def model_for(params, preferred=None):
    """The COLMAP model that holds a :data:`PARAMS` row: ``preferred`` if it can, else
    PINHOLE without distortion, OPENCV otherwise."""
    fx, fy, _, _, k1, k2, p1, p2 = params
    fits = {"PINHOLE": k1 == k2 == p1 == p2 == 0.0,
            "SIMPLE_RADIAL": fx == fy and k2 == p1 == p2 == 0.0,
            "RADIAL": fx == fy and p1 == p2 == 0.0, "OPENCV": True}
    if preferred in fits and fits[preferred]:
        return preferred
    return "PINHOLE" if fits["PINHOLE"] else "OPENCV"


def model_params(model, params):
    """A model's parameters (file order) of a :data:`PARAMS` row."""
    return [params[slots[0]] for slots in _SLOTS[model]]


def similarity(src, dst):
    """Scale ``s``, rotation ``q`` and shift ``t`` with ``dst ~ s q src + t`` in least squares
    (Umeyama 1991, "Least-squares estimation of transformation parameters between two point
    patterns"), and the RMS of the fit."""
    mu_s, mu_d = src.mean(axis=0), dst.mean(axis=0)
    a, b = src - mu_s, dst - mu_d
    u, d, vt = np.linalg.svd(b.T @ a / len(src))
    e = np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0])
    q = u @ e @ vt
    s = float(np.trace(np.diag(d) @ e) / ((a * a).sum() / len(src)))
    t = mu_d - s * q @ mu_s
    rms = float(np.sqrt(((s * a @ q.T + mu_d - dst) ** 2).sum(axis=1).mean()))
    return s, q, t, rms


# -- import ----------------------------------------------------------------------------

@writes_project("import", "out")
def import_colmap(model_dir, out, control=(), crs=None, sigma_image=1.0, force=False,
                  memory=None):
    """Import the COLMAP text model in ``model_dir`` into a new project ``out``.

    One sapgo camera per COLMAP camera (ids = CAMERA_IDs; intrinsics held fixed), one photo
    per image (ids = IMAGE_IDs, strip unknown), one pass point per 3D point (ids =
    POINT3D_IDs, the model's coordinates as approximations) and one observation per 2D point
    with a 3D point; image unit pixels with sigma ``sigma_image`` (project attribute
    ``image_unit`` "px"); what sapgo does not use goes to ``/colmap``.

    ``control``: text control files (docs/formats.md; ids = POINT3D_IDs), read as
    :func:`sapgo.ingest.import_text` reads them, in ``crs`` if given. The model is then
    brought into the control's frame by the similarity transformation that fits its full
    control points (at least 3, not on a line) and the block is adjusted with that datum;
    without control it is a free network (``datum`` "free", Levenberg-Marquardt). Returns a
    summary dict.
    """
    import shutil

    from ..frames import Frame, opk_of, rotation_matrices
    from ..ingest import TextControl
    from ..ordering import MIN_RAYS_PASS, _unique
    from ..project import (
        CAMERA_DTYPE,
        KIND_CONTROL,
        KIND_NAMES,
        KIND_VERTICAL,
        OBSERVATION_DTYPE,
        STATION_DTYPE,
        STATUS_ACTIVE,
        append_history,
        new_project_path,
        point_records,
        write_project,
    )

    out = new_project_path(out, force)
    if not (sigma_image > 0 and math.isfinite(sigma_image)):
        raise ParameterError(f"--sigma-image must be a positive number of pixels, found "
                             f"{sigma_image!r}")
    control = [control] if isinstance(control, (str, Path)) else list(control or ())
    if crs is not None and not control:
        raise ParameterError("--crs is the coordinate system of the control files: give "
                             "--control (a COLMAP model has no coordinate system of its own)")
    model_dir = Path(model_dir)
    model = read_colmap(model_dir)
    cams, im, pt = model["cameras"], model["images"], model["points"]
    warnings = []

    # COLMAP's own reprojection error of the model as read (the reference for the import)
    r_cam = rotation_of_quaternion(im["qvec"])
    has3d = np.flatnonzero(im["point3d"] != -1)
    obs_image = np.repeat(np.arange(len(im["ids"])), im["n2d"])[has3d]
    pt_order = np.argsort(pt["ids"], kind="stable")
    obs_point = pt_order[np.searchsorted(pt["ids"][pt_order], im["point3d"][has3d])]
    proj = colmap_project(cams["params"][im["camera"][obs_image]], r_cam[obs_image],
                          im["tvec"][obs_image], pt["xyz"][obs_point])
    dist = np.linalg.norm(proj - im["xy"][has3d], axis=1)
    mean_error = float(dist.mean()) if len(dist) else 0.0

    # records in id order
    c_ord = np.argsort(cams["ids"], kind="stable")
    c_rec = np.empty(len(c_ord), np.int64)
    c_rec[c_ord] = np.arange(len(c_ord))
    with np.errstate(all="ignore"):   # (values out of range: refused when written)
        rows, y_scale = sapgo_camera_rows(cams["params"][c_ord], cams["size"][c_ord])
        size = cams["size"][c_ord]
        camera = np.zeros(len(c_ord), CAMERA_DTYPE)
        camera["id"] = cams["ids"][c_ord]
        for k, name in enumerate(("focal_length", "x0", "y0", "k1", "k2", "k3", "p1", "p2")):
            camera[name] = rows[:, k]
        camera["format_x"] = size[:, 0]
        camera["format_y"] = size[:, 1] * y_scale
    camera["sigma_image"] = sigma_image

    i_ord = np.argsort(im["ids"], kind="stable")
    i_rec = np.empty(len(i_ord), np.int64)
    i_rec[i_ord] = np.arange(len(i_ord))
    eo = stations_of_poses(im["qvec"][i_ord], im["tvec"][i_ord])
    station = np.zeros(len(i_ord), STATION_DTYPE)
    station["id"] = im["ids"][i_ord]
    station["camera"] = c_rec[im["camera"][i_ord]]
    station["strip"] = -1
    station["status"] = STATUS_ACTIVE

    xyz = pt["xyz"][pt_order].copy()
    n_pt = len(pt_order)
    p_rec = np.empty(n_pt, np.int64)
    p_rec[pt_order] = np.arange(n_pt)
    kind = np.zeros(n_pt, np.int8)
    ctrl = np.zeros((n_pt, 3))
    ctrl_sigma = np.zeros((n_pt, 3))
    frame = Frame()
    aligned = None
    work = out.with_name(out.name + ".import.work")
    if control:
        shutil.rmtree(work, ignore_errors=True)
        work.mkdir(parents=True)
        try:
            tc = TextControl(control, work, crs=crs, memory=memory)
        finally:
            shutil.rmtree(work, ignore_errors=True)
        warnings += tc.warnings
        frame = tc.frame
        rec = tc.records
        ids_sorted = pt["ids"][pt_order]
        at = np.minimum(np.searchsorted(ids_sorted, rec["id"]), n_pt - 1)
        absent = np.flatnonzero(ids_sorted[at] != rec["id"])
        if len(absent):  # the earliest place
            j = int(absent[np.argmin(rec["loc"][absent])])
            raise DataError(f"{tc.where(rec['loc'][j])}: point {rec['id'][j]} is not a 3D point "
                            f"of the COLMAP model (the POINT3D_IDs of "
                            f"{model_dir / 'points3D.txt'})")
        kind[at] = rec["kind"]
        ctrl[at] = rec["control"]
        ctrl_sigma[at] = rec["sigma"]
        raw = np.zeros(n_pt, bool)
        raw[at] = rec["raw"] != 0
        # the model into the control's frame: the similarity of its full control points
        full = np.flatnonzero((kind == KIND_CONTROL) & ~raw)
        spread = (np.linalg.svd(xyz[full] - xyz[full].mean(axis=0), compute_uv=False)
                  if len(full) >= 3 else np.zeros(3))
        # (nearly on a line: the rotation about it would be set by the noise)
        if len(full) >= 3 and spread[1] > 1e-3 * spread[0]:
            given = np.linalg.svd(ctrl[full] - ctrl[full].mean(axis=0), compute_uv=False)
            if not given[1] > 1e-3 * given[0]:   # (the control's own coordinates: the same)
                shown = ", ".join(str(int(v)) for v in ids_sorted[full[:5]])
                raise DataError(
                    f"{', '.join(str(c) for c in control)}: the full control points "
                    f"({shown}{', ...' if len(full) > 5 else ''}) are at one place or on a "
                    f"line: the similarity that brings the model to them is undetermined")
            s, q, t, rms = similarity(xyz[full], ctrl[full])
            xyz = s * xyz @ q.T + t
            eo = np.column_stack([opk_of(rotation_matrices(eo[:, :3]) @ q.T),
                                  s * eo[:, 3:] @ q.T + t])
            angle = math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(q) - 1) / 2))))
            aligned = {"points": int(len(full)), "scale": s, "rotation_deg": angle,
                       "shift": [float(v) for v in t], "rms": rms}
        elif crs is not None:
            raise DataError(f"{len(full)} full control point(s) of the control files are 3D "
                            f"points of the model: at least 3, not on or near a line, are "
                            f"needed to bring the model into the frame of --crs")
        else:
            warnings.append(f"fewer than 3 full control points (not on a line): the model is "
                            f"not aligned to the control; its coordinates are taken to be in "
                            f"the control's system (e.g. a model georeferenced by COLMAP's "
                            f"model_aligner)")
        if raw.any():
            ctrl = tc.partial(ctrl, kind, raw, xyz)
    station["eo"] = eo

    # observations: grouped by point, by station and POINT2D_IDX within a point
    o_station = i_rec[obs_image]
    o_point = p_rec[obs_point]
    img_of_2d = np.repeat(np.arange(len(im["ids"])), im["n2d"])
    index_2d = np.arange(len(im["point3d"])) - im["start"][img_of_2d]
    o_index = index_2d[has3d]
    o_cam = c_rec[im["camera"][obs_image]]
    w_h = size[o_cam].astype(np.float64)
    ox = im["xy"][has3d, 0] - w_h[:, 0] / 2
    oy = y_scale[o_cam] * (w_h[:, 1] / 2 - im["xy"][has3d, 1])
    o = np.lexsort((o_index, o_station, o_point))
    obs = np.zeros(len(o), OBSERVATION_DTYPE)
    obs["point"], obs["station"] = o_point[o], o_station[o]
    obs["x"], obs["y"] = ox[o], oy[o]
    obs["status"] = STATUS_ACTIVE
    point = point_records(obs["point"], n_pt, id=pt["ids"][pt_order], kind=kind,
                          status=STATUS_ACTIVE, xyz=xyz, control=ctrl,
                          control_sigma=ctrl_sigma)

    # /colmap: what sapgo does not use, keyed by ids
    g_cam = np.zeros(len(c_ord), COLMAP_CAMERA_DTYPE)
    g_cam["id"] = camera["id"]
    g_cam["model"] = [cams["models"][i].encode() for i in c_ord]
    g_cam["width"], g_cam["height"] = size[:, 0], size[:, 1]
    g_cam["y_scale"] = y_scale
    g_img = np.zeros(len(i_ord), _image_dtype())
    g_img["id"] = station["id"]
    g_img["name"] = [im["names"][i] for i in i_ord]
    g_img["qvec_read"] = im["qvec"][i_ord]
    no3d = np.flatnonzero(im["point3d"] == -1)
    g_2d = np.zeros(len(no3d), COLMAP_POINT2D_DTYPE)
    g_2d["image_id"] = im["ids"][img_of_2d[no3d]]
    g_2d["index"] = index_2d[no3d]
    g_2d["x"], g_2d["y"] = im["xy"][no3d, 0], im["xy"][no3d, 1]
    g_2d = g_2d[np.lexsort((g_2d["index"], g_2d["image_id"]))]
    g_obs = np.zeros(len(obs), COLMAP_OBSERVATION_DTYPE)
    g_obs["point_id"] = point["id"][obs["point"]]
    g_obs["image_id"] = station["id"][obs["station"]]
    g_obs["index"] = o_index[o]
    g_obs["rank"] = _ranks(g_obs["point_id"], g_obs["image_id"], obs["x"], obs["y"])
    g_obs = g_obs[np.lexsort((g_obs["rank"], g_obs["image_id"], g_obs["point_id"]))]
    g_pt = np.zeros(n_pt, COLMAP_POINT_DTYPE)
    g_pt["id"] = point["id"]
    g_pt["rgb"] = pt["rgb"][pt_order]

    free = not control
    creator = {"command": "import", "format": "colmap", "model": str(model_dir),
               "control": [str(c) for c in control],
               "crs": None if frame.crs_text == "" else frame.crs.to_string()}
    attrs = {"creator": json.dumps(creator), "image_unit": "px",
             "history": append_history("[]", creator)}
    attrs.update(frame.to_attrs())
    if free:
        attrs.update(datum="free", points_behind="allowed")
    def extra(file):
        g = file.create_group("colmap")
        g.attrs["model"] = str(model_dir)
        for name, data in (("cameras", g_cam), ("images", g_img), ("points", g_pt),
                           ("observations", g_obs), ("points2D", g_2d)):
            g.create_dataset(name, data=data)

    write_project(out, camera, station, point, obs, attrs=attrs, extra=extra)

    by_kind = {KIND_NAMES[k]: int((kind == k).sum()) for k in KIND_NAMES}
    # as the text import: kept, and left out by ordering (sapgo.ordering: a pass, check or
    # horizontal control point needs 2 rays, a full or vertical control point 1; a ray is a
    # distinct point and image)
    pairs = _unique(o_point * len(station) + o_station)
    rays = np.bincount(pairs // len(station), minlength=n_pt)
    need = np.where((kind == KIND_CONTROL) | (kind == KIND_VERTICAL), 1, MIN_RAYS_PASS)
    few = point["id"][rays < need]
    if len(few):
        warnings.append(f"{len(few)} point(s) seen on too few images (2, or 1 for full and "
                        f"vertical control) cannot be determined: they stay in the project "
                        f"and are left out of the adjustment: ids "
                        f"{', '.join(map(str, few[:20].tolist()))}"
                        f"{', ...' if len(few) > 20 else ''}")
    return {"path": str(out), "cameras": len(camera), "photos": len(station),
            "points": n_pt, "points_by_kind": by_kind, "observations": len(obs),
            "points2D_without_3D": len(g_2d), "undetermined_points": int(len(few)),
            "camera_models": {m: cams["models"].count(m) for m in CAMERA_MODELS
                              if m in cams["models"]},
            "y_scaled_cameras": int((y_scale != 1.0).sum()), "free": free,
            "mean_reprojection_error": mean_error, "aligned": aligned,
            "frame": frame.describe(), "warnings": warnings}


def _ranks(point_id, image_id, x, y):
    """The rank of each observation among those of its point in the same image, by (x, y)
    (0 unless a point is seen more than once in an image): with the ids, a key that does not
    depend on the record order."""
    o = np.lexsort((y, x, image_id, point_id))
    new = np.ones(len(o), bool)
    new[1:] = (point_id[o][1:] != point_id[o][:-1]) | (image_id[o][1:] != image_id[o][:-1])
    start = np.maximum.accumulate(np.where(new, np.arange(len(o)), 0))
    rank = np.empty(len(o), np.int32)
    rank[o] = np.arange(len(o)) - start
    return rank


# -- export ----------------------------------------------------------------------------

def _decode(v):
    return v.decode() if isinstance(v, bytes) else str(v)


def export_colmap(project_path, out_dir, adjusted=False, pixel_size=None):
    """Write a project as a COLMAP text model (``cameras.txt``, ``images.txt``,
    ``points3D.txt`` in ``out_dir``): its inputs, or with ``adjusted`` its adjusted values
    (stations + ``/solution/station_corr``, points + ``point_corr``, cameras +
    ``camera_corr``). Every photo, point and observation is written (excluded ones with
    their input values). ERROR is each track's mean reprojection error in pixels, computed
    from the written values.

    A project imported from COLMAP comes back with its ids, names, camera models and sizes,
    POINT2D indices, 2D points without a 3D point and colours (``/colmap``). Any other project
    is written with names ``photo_<id>``, PINHOLE cameras (OPENCV with distortion; k3 cannot
    be written), the image size from the camera's format, 2D points in the order of their
    point ids and grey points. Image coordinates must be pixels (``image_unit`` "px"), or
    millimetres converted with ``pixel_size`` (micrometres). Returns a dict of counts.
    """
    from ..geometry import beyond_brown, camera_array
    from ..project import Project

    out_dir = Path(out_dir)
    with Project(project_path) as p:
        unit = str(p.attr("image_unit", "mm") or "mm")
        if adjusted and not (p.has_solution
                             and p.file["solution"].attrs.get("state") == "adjusted"):
            raise DataError(f"{project_path}: the project has no adjusted solution: run "
                            f"'sapgo adjust' first")
        cams, st, pt, ob = p.cameras(), p.read("stations"), p.read("points"), \
            p.read("observations")
        rows = camera_array(cams)
        eo, xyz = st["eo"].copy(), pt["xyz"].copy()
        if adjusted:
            rows = rows + p.solution("camera_corr")
            eo += p.solution("station_corr")
            xyz += p.solution("point_corr")
        g = p.file.get("colmap")
        extra = None if g is None else {k: g[k][()] for k in ("cameras", "images", "points",
                                                             "observations", "points2D")}
    if unit == "px":
        if pixel_size is not None:
            raise ParameterError(f"--pixel-size applies to projects in mm; {project_path} is "
                                 f"in pixels")
        scale = 1.0
    elif pixel_size is None:
        raise ParameterError(f"{project_path}: the image coordinates are in {unit}, a COLMAP "
                             f"model is in pixels: give the pixel size (--pixel-size UM, "
                             f"micrometres)")
    elif not (pixel_size > 0 and math.isfinite(pixel_size)):
        raise ParameterError(f"--pixel-size must be a positive number of micrometres, found "
                             f"{pixel_size!r}")
    else:
        scale = 1000.0 / pixel_size  # pixels per mm
    odd = np.flatnonzero(beyond_brown(rows))
    if len(odd):
        raise DataError(f"{project_path}: camera {int(cams['id'][odd[0]])} has affinity or "
                        f"shear (b1, b2), the backward distortion model or an "
                        f"additional-parameter set, which COLMAP's "
                        f"camera models cannot hold")
    bad = np.flatnonzero(rows[:, 5] != 0.0)
    if len(bad):
        raise DataError(f"{project_path}: camera {int(cams['id'][bad[0]])} has k3 = "
                        f"{float(rows[bad[0], 5]):g}, which COLMAP's camera models cannot hold")
    # pixels: f, x0, y0 times scale; k1 / scale^2, k2 / scale^4, p / scale
    rows = rows[:, :8] * np.array([scale, scale, scale, scale ** -2, scale ** -4, 0.0,
                                   1 / scale, 1 / scale])
    x_px, y_px = ob["x"] * scale, ob["y"] * scale
    n_cam = len(cams)
    st_id, pt_id = st["id"], pt["id"]
    o_img, o_pt = st_id[ob["station"]], pt_id[ob["point"]]

    if extra is not None:
        info = _colmap_group(project_path, extra, cams["id"], st_id, pt_id, o_img, o_pt,
                             x_px, y_px)
        models, size, y_scale, names, qref, o_index, more, rgb = info
    else:
        models = [None] * n_cam
        y_scale = np.ones(n_cam)
        size = np.zeros((n_cam, 2), np.int64)
        fmt = np.column_stack([cams["format_x"], cams["format_y"]]) * scale
        reach = np.zeros((n_cam, 2))  # observations' extent from the image centre
        oc = st["camera"][ob["station"]]
        np.maximum.at(reach, oc, np.abs(np.column_stack([x_px, y_px])))
        size = np.maximum(np.ceil(np.where(fmt > 0, fmt, 2 * reach) - 1e-9), 1).astype(
            np.int64)
        names = [f"photo_{i}" for i in st_id.tolist()]
        qref = None
        o = np.lexsort((y_px, x_px, o_pt, o_img))
        o_index = np.empty(len(ob), np.int64)
        first = np.ones(len(o), bool)
        first[1:] = o_img[o][1:] != o_img[o][:-1]
        start = np.maximum.accumulate(np.where(first, np.arange(len(o)), 0))
        o_index[o] = np.arange(len(o)) - start
        more = np.zeros(0, COLMAP_POINT2D_DTYPE)
        rgb = np.zeros((len(pt), 3), np.uint8)
    params = colmap_params(rows, y_scale, size)
    models = [model_for(params[i], models[i]) for i in range(n_cam)]
    r, q, t = poses_of_stations(eo, qref)

    # the 2D points of each image: observations and those without a 3D point
    cam_st = st["camera"]
    w_h = size[cam_st[ob["station"]]].astype(np.float64)
    u = x_px + w_h[:, 0] / 2
    v = w_h[:, 1] / 2 - y_px / y_scale[cam_st[ob["station"]]]
    st_order = np.argsort(st_id, kind="stable")
    m_st = np.zeros(0, np.int64)
    if len(more):
        pos = np.minimum(np.searchsorted(st_id[st_order], more["image_id"]), len(st_id) - 1)
        bad = st_id[st_order[pos]] != more["image_id"]
        if bad.any():
            raise DataError(f"{project_path}: /colmap: a 2D point of image "
                            f"{int(more['image_id'][np.argmax(bad)])}, which is not a photo of "
                            f"the project (the project was changed after the COLMAP import)")
        m_st = st_order[pos]
    all_st = np.concatenate([ob["station"], m_st])
    all_idx = np.concatenate([o_index, more["index"]])
    all_uv = np.concatenate([np.column_stack([u, v]), np.column_stack([more["x"],
                                                                      more["y"]])])
    all_pid = np.concatenate([o_pt, np.full(len(more), -1, np.int64)])
    o2 = np.lexsort((all_idx, all_st))
    n2d = np.bincount(all_st, minlength=len(st))
    start = np.concatenate([[0], np.cumsum(n2d)[:-1]])
    expect = np.arange(len(o2)) - np.repeat(start, n2d)
    if (all_idx[o2] != expect).any():
        k = int(np.argmax(all_idx[o2] != expect))
        raise DataError(f"{project_path}: /colmap: the 2D points of image "
                        f"{int(st_id[all_st[o2][k]])} are not numbered 0, 1, ... (the project "
                        f"was changed after the COLMAP import)")

    # ERROR: the mean reprojection error of each track, from the written values
    proj = colmap_project(params[cam_st[ob["station"]]], r[ob["station"]], t[ob["station"]],
                          xyz[ob["point"]])
    d = np.linalg.norm(proj - np.column_stack([u, v]), axis=1)
    n_track = np.bincount(ob["point"], minlength=len(pt))
    with np.errstate(invalid="ignore"):
        error = np.bincount(ob["point"], weights=d, minlength=len(pt)) / n_track
    error[n_track == 0] = -1.0

    out_dir.mkdir(parents=True, exist_ok=True)
    c_ord = np.argsort(cams["id"], kind="stable")
    with open(out_dir / "cameras.txt", "w") as f:
        f.write("# Camera list with one line of data per camera:\n"
                "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
                f"# Number of cameras: {n_cam}\n")
        for i in c_ord.tolist():
            vals = model_params(models[i], params[i])
            f.write(" ".join([str(int(cams["id"][i])), models[i], str(int(size[i, 0])),
                              str(int(size[i, 1]))] + [repr(float(x)) for x in vals]) + "\n")
    n_obs = len(ob)
    with open(out_dir / "images.txt", "w") as f:
        f.write("# Image list with two lines of data per image:\n"
                "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
                "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
                f"# Number of images: {len(st)}, mean observations per image: "
                f"{n_obs / max(len(st), 1)}\n")
        uv_s, pid_s = all_uv[o2], all_pid[o2]
        for i in st_order.tolist():
            a, b = int(start[i]), int(start[i] + n2d[i])
            head = [str(int(st_id[i]))] + [repr(float(x)) for x in q[i]] + \
                [repr(float(x)) for x in t[i]] + [str(int(cams["id"][cam_st[i]])), names[i]]
            f.write(" ".join(head) + "\n")
            f.write(" ".join(f"{x!r} {y!r} {k}" for x, y, k in zip(
                uv_s[a:b, 0].tolist(), uv_s[a:b, 1].tolist(), pid_s[a:b].tolist())) + "\n")
    # tracks: by image id and POINT2D_IDX
    o3 = np.lexsort((o_index, o_img, ob["point"]))
    tr_start = np.concatenate([[0], np.cumsum(n_track)[:-1]])
    tr_img, tr_idx = o_img[o3], o_index[o3]
    p_ord = np.argsort(pt_id, kind="stable")
    with open(out_dir / "points3D.txt", "w") as f:
        f.write("# 3D point list with one line of data per point:\n"
                "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
                f"# Number of points: {len(pt)}, mean track length: "
                f"{n_obs / max(len(pt), 1)}\n")
        for j in p_ord.tolist():
            a, b = int(tr_start[j]), int(tr_start[j] + n_track[j])
            f.write(" ".join([str(int(pt_id[j]))] + [repr(float(x)) for x in xyz[j]]
                             + [str(int(c)) for c in rgb[j]] + [repr(float(error[j]))]
                             + [f"{i} {k}" for i, k in zip(tr_img[a:b].tolist(),
                                                          tr_idx[a:b].tolist())]) + "\n")
    return {"directory": str(out_dir), "cameras": n_cam, "images": len(st),
            "points": len(pt), "observations": n_obs, "points2D": len(o2),
            "models": {m: models.count(m) for m in CAMERA_MODELS if m in models}}


def _colmap_group(project_path, g, cam_ids, st_id, pt_id, o_img, o_pt, x_px, y_px):
    """What ``/colmap`` holds for the project's cameras, photos, points and observations
    (looked up by id); DataError when it does not describe them."""
    def lookup(table, ids, what):
        if not len(ids):
            return table[:0]
        order = np.argsort(table["id"], kind="stable")
        at = np.minimum(np.searchsorted(table["id"][order], ids), max(len(order) - 1, 0))
        if not len(order) or (table["id"][order][at] != ids).any():
            k = int(np.argmax(table["id"][order][at] != ids)) if len(order) else 0
            raise DataError(f"{project_path}: /colmap/{what} has no record of id "
                            f"{int(ids[k])} (the project was changed after the COLMAP "
                            f"import)")
        return table[order[at]]

    c = lookup(g["cameras"], cam_ids, "cameras")
    models = [_decode(m) for m in c["model"]]
    size = np.column_stack([c["width"], c["height"]]).astype(np.int64)
    im = lookup(g["images"], st_id, "images")
    names = [_decode(n) for n in im["name"]]
    rgb = lookup(g["points"], pt_id, "points")["rgb"]
    # each observation's POINT2D_IDX by (point id, image id, rank)
    obs_t = g["observations"]
    rank = _ranks(o_pt, o_img, x_px, y_px)
    o = np.lexsort((rank, o_img, o_pt))
    t = np.lexsort((obs_t["rank"], obs_t["image_id"], obs_t["point_id"]))
    same = len(o) == len(t) and bool(
        (obs_t["point_id"][t] == o_pt[o]).all() and (obs_t["image_id"][t] == o_img[o]).all()
        and (obs_t["rank"][t] == rank[o]).all())
    if not same:
        raise DataError(f"{project_path}: /colmap/observations does not list the project's "
                        f"observations (the project was changed after the COLMAP import)")
    index = np.empty(len(o), np.int64)
    index[o] = obs_t["index"][t]
    return (models, size, c["y_scale"].astype(np.float64), names, im["qvec_read"], index,
            g["points2D"], rgb)
