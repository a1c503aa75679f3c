"""Bundler (Snavely et al. 2006, Bundler v0.3 and v0.4) ``bundle.out`` files: read, import,
export.

Format (plain text, whitespace separated)::

    # Bundle file v0.3
    num_cameras num_points
    per camera, 5 lines:  f k1 k2  /  R (3 lines of 3, world to camera)  /  t (3)
    per point, 3 lines:   X Y Z  /  R G B (0-255)  /  n cam key x y  cam key x y ...

Image coordinates are pixels from the image centre, x to the right, y up; a camera Bundler
did not reconstruct is written as zeros. Camera model (BAL's, which was made from Bundler's
files): ``P = R X + t``, ``p = -P[:2] / P[2]``, projection ``f (1 + k1 |p|^2 + k2 |p|^4) p``;
sapgo's collinearity model in pixels (:mod:`sapgo.formats.bal`). A reconstructed camera
becomes a photo with a camera of its own (id: the camera's index in the file), a point a
pass point (id: its index); the colours and keypoint indices are kept in the project's
``/bundler`` group and written back by the export.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..lock import writes_project
from ..errors import DataError
from .bal import (
    _check_out,
    _merge_duplicates,
    read_text,
    sapgo_to_snavely,
    snavely_block,
    snavely_cost,
    snavely_to_sapgo,
    write_snavely_project,
)

__all__ = ["BUNDLER_OBSERVATION_DTYPE", "BUNDLER_POINT_DTYPE", "bundler_cost",
           "export_bundler", "import_bundler", "read_bundler", "write_bundler"]

#: ``/bundler/points``: a point's colour.
BUNDLER_POINT_DTYPE = np.dtype([("id", "<i8"), ("rgb", "u1", (3,))])
#: ``/bundler/observations``: an observation's keypoint index (by point id and photo id).
BUNDLER_OBSERVATION_DTYPE = np.dtype([("point_id", "<i8"), ("photo_id", "<i8"),
                                      ("key", "<i8")])

#: Largest departure of a camera's ``R' R`` from the identity that is taken as rounding
#: (Bundler writes 10 significant digits); the rotation is then made orthonormal.
ROTATION_TOL = 1e-6

#: The Bundler versions read (the header ``# Bundle file v0.3``).
VERSIONS = ("0.3", "0.4")

#: Smallest focal length (pixels) taken as a camera's: below it the camera is refused (an
#: image of more than a few pixels would span nearly 180 degrees, and k1 / f^2, k2 / f^4
#: of sapgo's model lose their meaning or overflow).
MIN_FOCAL = 1e-6

_INT = re.compile(r"[+-]?[0-9]+")
_INT64 = (-(2 ** 63), 2 ** 63 - 1)


def _numbers(path, lines, where, per_line, what):
    """The numbers of the lines ``where`` (indices into ``lines``), ``per_line`` each, as
    an array (len(where) x per_line); errors name the file and line."""
    try:
        a = np.array(" ".join(lines[k] for k in where).split(), dtype=np.float64)
    except ValueError:
        a = None
    if a is not None and a.size == per_line * len(where):
        return a.reshape(len(where), per_line)
    for k in where:
        parts = lines[k].split()
        for x in parts:
            try:
                float(x)
            except ValueError:
                raise DataError(f"{path}:{k + 1}: {what}: {x!r} is not a number") from None
        if len(parts) != per_line:
            raise DataError(f"{path}:{k + 1}: {what}: expected {per_line} numbers, got "
                            f"{len(parts)}")
    raise AssertionError("unreachable")


def _keys(tokens):
    """The keypoint indices ``tokens`` (strings) as exact int64, or ``(i, message)`` of the
    first one that is not an index: decimal digits (an integral number below 2^53, e.g.
    ``5.0``, is taken too), at least 0 and in the int64 range."""
    joined = "".join(tokens)
    if joined.isascii() and "_" not in joined:
        try:
            keys = np.array(tokens, dtype=np.str_).astype(np.int64)
        except (ValueError, OverflowError):
            keys = None
        if keys is not None:
            bad = np.flatnonzero(keys < 0)
            return keys if not len(bad) else (int(bad[0]), "is not an index (an integer "
                                                           ">= 0)")
    keys = np.zeros(len(tokens), np.int64)
    for i, x in enumerate(tokens):
        if _INT.fullmatch(x):
            v = int(x)
            if not _INT64[0] <= v <= _INT64[1]:
                return i, "is outside the int64 range"
        else:
            try:
                f = float(x)
            except ValueError:
                return i, "is not a number"
            if not (abs(f) < 2.0 ** 53 and f == round(f)):
                return i, "is not an index (an integer >= 0)"
            v = int(f)
        if v < 0:
            return i, "is not an index (an integer >= 0)"
        keys[i] = v
    return keys


def read_bundler(path):
    """Read a Bundler ``.out`` file (plain, ``.gz`` or ``.bz2``): a dict of ``rotations``
    (n x 3 x 3), ``translations`` (n x 3), ``fk`` (n x 3: f, k1, k2), ``reconstructed`` (n: a camera
    not all zeros), ``points`` (m x 3), ``colors`` (m x 3), ``obs_camera``, ``obs_point``,
    ``obs_key`` (int64), ``obs_xy`` (k x 2), ``obs_line`` and ``obs_view`` (an
    observation's line and its place in the line's view list, from 1), ``camera_line``
    (n: each camera's first line) and ``version``. Errors name the file and line: among
    them a version other than v0.3 and v0.4, a keypoint index that is not an exact
    non-negative int64, a focal length below :data:`MIN_FOCAL` and an observation whose
    projection is not finite."""
    path = Path(path)
    lines = read_text(path).splitlines()
    data = [k for k, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")]
    at = next((k for k, ln in enumerate(lines) if ln.lstrip().startswith("#")), None)
    version = lines[at].strip()[1:].strip() if at is not None else ""
    if not data:
        raise DataError(f"{path}: the file is empty")
    said = re.fullmatch(r"bundle\s+file\s+v?(\S+)", version, re.IGNORECASE)
    if said and said.group(1) not in VERSIONS:
        raise DataError(f"{path}:{at + 1}: Bundle file version {said.group(1)!r}: only "
                        f"v{' and v'.join(VERSIONS)} are read")
    head = lines[data[0]].split()
    if len(head) != 2 or not all(h.isascii() and h.isdigit() for h in head):
        raise DataError(f"{path}:{data[0] + 1}: expected 'num_cameras num_points' (two "
                        f"non-negative integers), got {lines[data[0]].strip()!r}")
    n_cam, n_pt = (int(h) for h in head)
    if n_cam < 1:
        raise DataError(f"{path}:{data[0] + 1}: no cameras")
    body = data[1:]
    need = 5 * n_cam + 3 * n_pt
    if len(body) < need:
        raise DataError(f"{path}:{len(lines)}: the file ends early: {n_cam} cameras (5 "
                        f"lines each) and {n_pt} points (3 lines each) need {need} lines "
                        f"after the header, {len(body)} follow")
    if len(body) > need:
        raise DataError(f"{path}:{body[need] + 1}: more lines than {n_cam} cameras and "
                        f"{n_pt} points need")
    cam = _numbers(path, lines, body[:5 * n_cam], 3, "camera").reshape(n_cam, 5, 3)
    fk, rot, t = cam[:, 0].copy(), cam[:, 1:4].copy(), cam[:, 4].copy()
    cam_line = lambda j, r: body[5 * j + r] + 1   # noqa: E731
    bad = np.flatnonzero(~np.isfinite(cam.reshape(n_cam, -1)).all(axis=1))
    if len(bad):
        raise DataError(f"{path}:{cam_line(int(bad[0]), 0)}: camera {int(bad[0])}: a "
                        f"parameter is not finite")
    reconstructed = np.abs(cam.reshape(n_cam, -1)).max(axis=1) > 0
    for j in np.flatnonzero(reconstructed):
        j = int(j)
        if fk[j, 0] <= 0:
            raise DataError(f"{path}:{cam_line(j, 0)}: camera {j}: focal length "
                            f"{float(fk[j, 0]):g} is not positive")
        if fk[j, 0] < MIN_FOCAL:
            raise DataError(f"{path}:{cam_line(j, 0)}: camera {j}: focal length "
                            f"{float(fk[j, 0]):g} pixels is implausibly small (at least "
                            f"{MIN_FOCAL:g} expected)")
        err = np.abs(rot[j].T @ rot[j] - np.eye(3)).max()
        det = np.linalg.det(rot[j])
        if err > ROTATION_TOL or det <= 0:
            raise DataError(f"{path}:{cam_line(j, 1)}: camera {j}: R is not a rotation "
                            f"matrix (R'R departs from I by {err:.2g}, det {det:.6g})")
        u, _, vt = np.linalg.svd(rot[j])   # (the nearest rotation: rounding removed)
        rot[j] = u @ vt
    pts_lines = body[5 * n_cam:]
    pts = _numbers(path, lines, pts_lines[0::3], 3, "point position")
    rgb = _numbers(path, lines, pts_lines[1::3], 3, "point colour")
    bad = np.flatnonzero(~np.isfinite(pts).all(axis=1))
    if len(bad):
        raise DataError(f"{path}:{pts_lines[3 * int(bad[0])] + 1}: point {int(bad[0])}: "
                        f"a coordinate is not finite")
    bad = np.flatnonzero(((rgb < 0) | (rgb > 255) | (rgb != np.round(rgb))).any(axis=1))
    if len(bad):
        raise DataError(f"{path}:{pts_lines[3 * int(bad[0]) + 1] + 1}: point {int(bad[0])}: "
                        f"a colour is not an integer 0..255")
    counts = np.zeros(n_pt, np.int64)
    tokens = []
    for i, k in enumerate(pts_lines[2::3]):
        parts = lines[k].split()
        n = parts[0] if parts else ""
        if not (n.isascii() and n.isdigit()) or len(parts) != 1 + 4 * int(n):
            raise DataError(f"{path}:{k + 1}: point {i}: view list: expected 'n' and n "
                            f"times 'camera key x y', got {len(parts)} values")
        counts[i] = int(n)
        tokens += parts[1:]
    try:
        views = np.array(tokens, dtype=np.float64).reshape(-1, 4)
    except ValueError:
        views = None
    obs_point = np.repeat(np.arange(n_pt), counts)

    def view_line(o):
        return pts_lines[3 * int(obs_point[o]) + 2] + 1

    if views is None:
        for i, k in enumerate(pts_lines[2::3]):
            for x in lines[k].split()[1:]:
                try:
                    float(x)
                except ValueError:
                    raise DataError(f"{path}:{k + 1}: point {i}: view list: {x!r} is not "
                                    f"a number") from None
    v = views[:, 0]
    bad = np.flatnonzero((v != np.round(v)) | (v < 0) | (v >= n_cam))
    if len(bad):
        o = int(bad[0])
        raise DataError(f"{path}:{view_line(o)}: point {int(obs_point[o])}: camera "
                        f"{v[o]:g} is not one of 0..{n_cam - 1}")
    # keypoint indices: exact integers (as floats, indices beyond 2^53 would merge)
    keys = _keys(tokens[1::4])
    if isinstance(keys, tuple):
        o, why = keys
        raise DataError(f"{path}:{view_line(o)}: point {int(obs_point[o])}: key "
                        f"{tokens[4 * o + 1]!r} {why}")
    obs_camera = views[:, 0].astype(np.int64)
    bad = np.flatnonzero(~reconstructed[obs_camera])
    if len(bad):
        o = int(bad[0])
        raise DataError(f"{path}:{view_line(o)}: point {int(obs_point[o])}: camera "
                        f"{int(obs_camera[o])} was not reconstructed (all zeros) but sees it")
    bad = np.flatnonzero(~np.isfinite(views[:, 2:]).all(axis=1))
    if len(bad):
        o = int(bad[0])
        raise DataError(f"{path}:{view_line(o)}: point {int(obs_point[o])}: an image "
                        f"coordinate is not finite")
    # every observation's projection and residual finite (a camera or point value so large,
    # or a point so near a camera's plane, that they overflow: the cost would be nan)
    with np.errstate(all="ignore"):
        c, j = obs_camera, obs_point
        p = np.einsum("nij,nj->ni", rot[c], pts[j]) + t[c]
        q = -p[:, :2] / p[:, 2:3]
        r2 = (q * q).sum(axis=1)
        proj = fk[c, 0][:, None] * (1.0 + fk[c, 1] * r2 + fk[c, 2] * r2 * r2)[:, None] * q
        res = ((proj - views[:, 2:]) ** 2).sum(axis=1)
    bad = np.flatnonzero(~np.isfinite(res))
    if len(bad):
        o = int(bad[0])
        cj = int(obs_camera[o])
        raise DataError(f"{path}:{view_line(o)}: point {int(obs_point[o])}: its projection "
                        f"by camera {cj} (lines {cam_line(cj, 0)}-{cam_line(cj, 4)}) is not "
                        f"finite: a camera or point value is out of range")
    line = np.asarray(pts_lines[2::3], np.int64)[obs_point] + 1 if len(obs_point) else \
        np.zeros(0, np.int64)
    view = np.arange(len(obs_point)) - np.repeat(np.cumsum(counts) - counts, counts) + 1
    return {"rotations": rot, "translations": t, "fk": fk, "reconstructed": reconstructed,
            "points": pts, "colors": rgb.astype(np.uint8), "obs_camera": obs_camera,
            "obs_point": obs_point, "obs_key": keys,
            "obs_xy": views[:, 2:].copy(), "obs_line": line, "obs_view": view,
            "camera_line": np.asarray(body[:5 * n_cam:5], np.int64) + 1,
            "version": version}


def bundler_cost(d):
    """The Snavely-model cost ``1/2 sum |projection - observation|^2`` of a
    :func:`read_bundler` dict (the reference for the import)."""
    return snavely_cost(d["rotations"], d["translations"], d["fk"], d["points"],
                        d["obs_camera"], d["obs_point"], d["obs_xy"])


def write_bundler(path, r, t, fk, pts, colors, obs_camera, obs_point, obs_key, obs_xy):
    """Write a Bundler v0.3 file: cameras ``(r, t, fk)`` (all zeros: not reconstructed),
    points with colours, observations (camera and point indices, keypoint index, x, y)
    grouped by point in the given order."""
    order = np.argsort(obs_point, kind="stable")
    counts = np.bincount(obs_point, minlength=len(pts))
    with open(path, "w") as f:
        f.write("# Bundle file v0.3\n")
        f.write(f"{len(fk)} {len(pts)}\n")
        for j in range(len(fk)):
            f.write("{!r} {!r} {!r}\n".format(*fk[j].tolist()))
            for row in r[j]:
                f.write("{!r} {!r} {!r}\n".format(*row.tolist()))
            f.write("{!r} {!r} {!r}\n".format(*t[j].tolist()))
        at = 0
        for i in range(len(pts)):
            f.write("{!r} {!r} {!r}\n".format(*pts[i].tolist()))
            f.write("{} {} {}\n".format(*colors[i].tolist()))
            o = order[at:at + counts[i]]
            at += counts[i]
            f.write(" ".join([str(int(counts[i]))] + [
                f"{int(c)} {int(k)} {x!r} {y!r}" for c, k, x, y in
                zip(obs_camera[o].tolist(), obs_key[o].tolist(), obs_xy[o, 0].tolist(),
                    obs_xy[o, 1].tolist())]) + "\n")


@writes_project("import", "out")
def import_bundler(path, out, force=False, intrinsics="adjusted", merge_duplicates=False):
    """Import the Bundler file ``path`` into a new project ``out``: one photo and one
    camera per reconstructed camera (ids: the cameras' indices in the file; f, k1, k2
    ``"adjusted"`` with the photo or held ``"fixed"``), the points as pass points (ids:
    their indices) with the file's coordinates as approximations, image units pixels with
    sigma 1, a free network; the colours and keypoint indices in ``/bundler``. A camera
    listed twice in a point's view list is merged as :func:`sapgo.formats.bal.import_bal`
    merges BAL duplicates (the first keypoint index kept; beyond 3 pixels an error unless
    ``merge_duplicates``). Returns a summary dict (``warnings``: lines for the user)."""
    out = _check_out(out, force, intrinsics)
    d = read_bundler(path)
    n_read = len(d["obs_camera"])
    warnings = _merge_duplicates(
        path, d, merge=merge_duplicates,
        where=lambda i, line=d["obs_line"], view=d["obs_view"]: (
            f"{int(line[i])} (view {int(view[i])})"))
    rec = np.flatnonzero(d["reconstructed"])
    index = np.full(len(d["fk"]), -1)
    index[rec] = np.arange(len(rec))
    with np.errstate(all="ignore"):
        eo, rows = snavely_to_sapgo(d["rotations"][rec], d["translations"][rec],
                                    d["fk"][rec])
    bad = np.flatnonzero(~(np.isfinite(eo).all(axis=1) & np.isfinite(rows).all(axis=1)))
    if len(bad):
        j = int(rec[bad[0]])
        raise DataError(f"{path}:{d['camera_line'][j]}: camera {j}: a value is out of range "
                        f"for sapgo's camera model (its projection centre -R't or k1 / f^2, "
                        f"k2 / f^4 is not finite)")
    with np.errstate(all="ignore"):
        cost = bundler_cost(d)
    if not np.isfinite(cost):   # (each observation's residual is finite: their sum is not)
        raise DataError(f"{path}: the initial cost is {cost} (the residuals are too large "
                        f"to sum: a camera's or point's value out of range?)")

    def extra(file):
        g = file.create_group("bundler")
        g.attrs["version"] = d["version"]
        g.attrs["cameras"] = len(d["fk"])
        pt = np.zeros(len(d["points"]), BUNDLER_POINT_DTYPE)
        pt["id"] = np.arange(len(pt))
        pt["rgb"] = d["colors"]
        g.create_dataset("points", data=pt)
        ob = np.zeros(len(d["obs_key"]), BUNDLER_OBSERVATION_DTYPE)
        ob["point_id"], ob["photo_id"], ob["key"] = d["obs_point"], d["obs_camera"], d["obs_key"]
        g.create_dataset("observations", data=ob[np.lexsort((ob["photo_id"],
                                                              ob["point_id"]))])

    n = write_snavely_project(out, {"command": "import", "format": "bundler",
                                    "file": str(path)}, eo, rows, rec, d["points"],
                              index[d["obs_camera"]], d["obs_point"], d["obs_xy"], intrinsics,
                              extra)
    return {"path": str(out), "cameras": len(rec), "photos": len(rec),
            "not_reconstructed": int(len(d["fk"]) - len(rec)), "points": len(d["points"]),
            "observations": n, "duplicates_dropped": n_read - n, "warnings": warnings,
            "initial_cost": cost, "version": d["version"]}


def export_bundler(project_path, out_path, adjusted=True):
    """Write a project (its adjusted values, or the inputs) as a Bundler v0.3 file. Every
    active photo is a camera with its camera's f, k1, k2 (principal point, k3, p1 and p2
    must be 0), in the order of the ids; a project imported from Bundler gets its cameras
    back at their indices (the ones not reconstructed, or excluded, as zeros), with the
    points' colours and the keypoint indices; other projects get grey points and each
    photo's observations numbered as keypoints."""
    import h5py

    b = snavely_block(project_path, adjusted, "Bundler")
    r, t, fk = sapgo_to_snavely(b["eo"], b["rows"])
    ids, pid = b["station_ids"], b["point_ids"]
    oc, op = b["obs_camera"], b["obs_point"]
    with h5py.File(project_path, "r") as f:
        g = f.get("bundler")
        n_file = int(g.attrs["cameras"]) if g is not None else 0
        gp = g["points"][...] if g is not None else None
        go = g["observations"][...] if g is not None else None
    colors = np.full((len(pid), 3), 128, np.uint8)
    keys = np.zeros(len(oc), np.int64)
    if g is not None and len(ids) and ids.min() >= 0 and ids.max() < n_file:
        # the file's own camera indices, and what it held besides the geometry
        where = np.searchsorted(gp["id"], pid)
        hit = (where < len(gp)) & (gp["id"][np.minimum(where, len(gp) - 1)] == pid)
        colors[hit] = gp["rgb"][where[hit]]
        want = pid[op] * (n_file + 1) + ids[oc]
        have = go["point_id"] * (n_file + 1) + go["photo_id"]
        at = np.searchsorted(have, want)
        ok = (at < len(have)) & (have[np.minimum(at, len(have) - 1)] == want)
        keys[ok] = go["key"][at[ok]]
        full = np.zeros((n_file, 3, 3)), np.zeros((n_file, 3)), np.zeros((n_file, 3))
        full[0][ids], full[1][ids], full[2][ids] = r, t, fk
        r, t, fk = full
        oc = ids[oc]
    else:   # (each photo's observations numbered from 0)
        order = np.argsort(oc, kind="stable")
        n = np.bincount(oc, minlength=len(ids))
        keys[order] = np.arange(len(oc)) - np.repeat(np.cumsum(n) - n, n)
    write_bundler(out_path, r, t, fk, b["xyz"], colors, oc, op, keys, b["obs_xy"])
    return {"cameras": len(fk), "photos": len(ids), "points": len(pid),
            "observations": len(oc)}
