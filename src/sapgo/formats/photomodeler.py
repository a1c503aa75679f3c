"""PhotoModeler's text export, as DBAT reads it (Börlin and Grussenmeyer's Damped Bundle
Adjustment Toolbox: ``loadpm.m``): read and import.

Layout (whitespace-separated; a blank line ends a block)::

    title
    tolerance max_iterations width height        (width, height: the image's pixels,
                                                  appended by hand, as DBAT asks)
    9 default sigmas
    c xp yp xs ys K1 K2 K3 P1 P2                 (the camera: mm; xp, yp from the image's
                                                  top-left corner, y down; xs, ys its format)
    10 sigmas of the camera
    per photo (N: its number from 0, on every line):
      N name                  N X Y Z kappa phi omega (degrees)       N 6 sigmas
      N covariances (or a blank line)             N c xp yp xs ys K1 K2 K3 P1 P2
      N 10 sigmas
    <blank>
    control points:   id X Y Z sX sY sZ ...      <blank>  (may be empty)
    object points:    id X Y Z sX sY sZ ...      <blank>  (the approximations)
    marked points:    photo id x y sx sy ...     <blank or end>  (pixels from the top-left,
                                                  y down)

Conventions (DBAT's ``prob2dbatstruct.m`` and camera model): ``M = R3(kappa) R2(phi)
R1(omega)`` and the projection ``x0 - f u / w`` are sapgo's. PhotoModeler's K1-K3, P1, P2
are a *backward* model: they correct a measured point ``m`` (mm, y up) into the ideal one,
``m + w (K1 r^2 + K2 r^4 + K3 r^6) + (P1 (r^2 + 2 x^2) + 2 P2 x y, 2 P1 x y + P2 (r^2 +
2 y^2))`` with ``w = (x, y) = m - (principal point)``: sapgo's backward distortion model
(:mod:`sapgo.geometry`), so the import keeps the measurements as they are (in mm from the
image centre, y up) and gives each camera its K1-K3, P1, P2 as k1-k3, p1, p2 of that model:
held, they correct the measurements exactly as DBAT does; self-calibrated (``--calibrate``),
they are adjusted in PhotoModeler's own model. Marked points' sigmas are taken as pixels.

Checks beyond the layout: ids are exact int64 integers; a photo's camera needs c, xs, ys
positive; a mark's sigma must not be negative (0 or none: the camera's); a photo, control
or object point given twice is loaded once with a warning when the repeats are the same
(bit for bit), else refused naming both lines; a point marked twice on a photo is averaged
with a warning within :data:`DUPLICATE_SIGMAS` sigmas, else refused naming both lines.
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
from ..geometry import AP_SET, BACKWARD

__all__ = ["export_photomodeler", "import_photomodeler", "pm_correct", "read_photomodeler"]


#: Marks of one point on one photo at most this many sigmas apart (the larger of their
#: sigmas, else the camera's 0.1 pixel) are one measurement written twice: averaged, with a
#: warning. Farther apart they contradict each other and the import stops.
DUPLICATE_SIGMAS = 3.0
#: A marked point's sigma (pixels) when the file gives none (or 0): the camera's.
DEFAULT_SIGMA_PX = 0.1

_INT = re.compile(r"[+-]?[0-9]+")
_INT64 = (-(2 ** 63), 2 ** 63 - 1)
_PHOTO_COLUMNS = ("name", "X", "Y", "Z", "kappa", "phi", "omega", "c", "xp", "yp", "xs",
                  "ys", "K1", "K2", "K3", "P1", "P2")
_POINT_COLUMNS = ("X", "Y", "Z", "sX", "sY", "sZ")


def _floats(path, k, line, n, what, first_int=False):
    """``n`` numbers of a line (after the photo number when ``first_int``)."""
    t = line.split()
    if first_int:
        t = t[1:]
    if len(t) < n:
        raise DataError(f"{path}:{k + 1}: {what}: expected {n} numbers, got {len(t)}")
    try:
        v = [float(x) for x in t[:n]]
    except ValueError:
        bad = next(x for x in t[:n] if not _num(x))
        raise DataError(f"{path}:{k + 1}: {what}: {bad!r} is not a number") from None
    if not all(math.isfinite(x) for x in v):
        raise DataError(f"{path}:{k + 1}: {what}: a value is not finite")
    return v


def _num(x):
    try:
        float(x)
        return True
    except ValueError:
        return False


def _id(path, k, token, what):
    """An id written in decimal digits (an optional sign) in the int64 range, exactly."""
    if not _INT.fullmatch(token):
        raise DataError(f"{path}:{k + 1}: {token!r} is not an integer ({what})")
    v = int(token)
    if not _INT64[0] <= v <= _INT64[1]:
        raise DataError(f"{path}:{k + 1}: {token!r} is outside the int64 range ({what})")
    return v


def _photo_no(line):
    t = line.split()
    return int(t[0]) if t and re.fullmatch(r"-?[0-9]+", t[0]) else None


def _fmt(v):
    """A float as short as it reads back."""
    return f"{v:g}" if float(f"{v:g}") == v else repr(v)


def _bits(values):
    return [x.hex() if isinstance(x, float) else x for x in values]


def _differ(a, b, names):
    """The names of the columns where ``a`` and ``b`` differ (bit for bit)."""
    return [nm for nm, x, y in zip(names, _bits(a), _bits(b)) if x != y]


def _once(path, what, key, line, values, seen, names, warnings):
    """True the first time ``key`` is seen (remembered with its line and values); a repeat
    with the same values is False (loaded once, with a warning), with others an error
    naming both lines."""
    if key not in seen:
        seen[key] = (line, values)
        return True
    first, old = seen[key]
    diff = _differ(old, values, names)
    if diff:
        raise DataError(f"{what} {key} is given twice with different values "
                        f"({', '.join(diff)}): {path}:{first} and {path}:{line}")
    warnings.append(f"{path}:{line}: {what} {key} is given again with the same values "
                    f"(first on line {first}): loaded once")
    return False


def _merge_marks(path, marked, lines, warnings):
    """The marks (photo, point, col, row, sx, sy) with each (photo, point) pair marked more
    than once reduced to one at their mean (summed in sorted value order; the sigmas of
    the mark with the largest given ones) when they lie within :data:`DUPLICATE_SIGMAS`
    sigmas of each other, else an error naming the pair and both lines. Returns the
    marks, their lines and, changed in place, ``warnings``."""
    groups = {}
    for i, (ph, pt) in enumerate((r[0], r[1]) for r in marked):
        groups.setdefault((ph, pt), []).append(i)
    dup = [g for g in groups.values() if len(g) > 1]
    if not dup:
        return marked, lines
    drop, shown = set(), []
    for g in dup:
        col = np.array([marked[i][2] for i in g])
        row = np.array([marked[i][3] for i in g])
        sig = [math.sqrt(marked[i][4] * marked[i][5]) if marked[i][4] > 0 and
               marked[i][5] > 0 else 0.0 for i in g]
        tol = DUPLICATE_SIGMAS * (max(sig) if max(sig) > 0 else DEFAULT_SIGMA_PX)
        with np.errstate(all="ignore"):
            dist = np.hypot(col[:, None] - col[None, :], row[:, None] - row[None, :])
        a, b = np.unravel_index(int(np.argmax(dist)), dist.shape)
        if not dist[a, b] <= tol:
            a, b = sorted((int(a), int(b)))
            ph, pt = marked[g[0]][:2]
            raise DataError(f"{path}: lines {lines[g[a]]} and {lines[g[b]]}: point {pt} is "
                            f"marked twice on photo {ph}, {float(dist[a, b]):.4g} px apart "
                            f"(more than {DUPLICATE_SIGMAS:g} sigma = {tol:.4g} px)")
        keep = g[0]
        best = g[int(np.argmax(sig))]
        marked[keep] = [*marked[keep][:2], math.fsum(np.sort(col)) / len(g),
                        math.fsum(np.sort(row)) / len(g), *marked[best][4:6]]
        drop.update(g[1:])
        if len(shown) < 5:
            shown.append(f"photo {marked[keep][0]} point {marked[keep][1]} (lines "
                         + ", ".join(str(lines[i]) for i in g[:3]) + ")")
    warnings.append(f"{path}: {len(dup)} (photo, point) pair(s) marked more than once within "
                    f"{DUPLICATE_SIGMAS:g} sigma of each other: each merged into one "
                    f"observation at their mean ({len(drop)} mark(s) dropped): "
                    f"{'; '.join(shown)}{'; ...' if len(dup) > 5 else ''}")
    keep = [i for i in range(len(marked)) if i not in drop]
    return [marked[i] for i in keep], [lines[i] for i in keep]


def read_photomodeler(path):
    """Read a PhotoModeler text export: a dict of ``size`` (width, height px), ``camera``
    (c, xp, yp, xs, ys, K1, K2, K3, P1, P2), ``photos`` (number, name, X, Y, Z, kappa, phi,
    omega in degrees, camera row) and ``photo_line`` (each one's first line), ``control``
    and ``points`` (id, X, Y, Z, sX, sY, sZ) with their exact int64 ids ``control_id`` and
    ``point_id``, ``marked`` (photo, id, x, y, sx, sy; pixels) with ``marked_ids`` (photo,
    id; int64) and ``marked_line``, and ``warnings`` (repeats loaded once, marks merged).
    A photo, control or object point given twice with different values, or a point marked
    twice on a photo more than :data:`DUPLICATE_SIGMAS` sigmas apart, is an error. Errors
    name the file and line."""
    path = Path(path)
    lines = decode_text(path, path.read_bytes()).splitlines()
    if not any(ln.strip() for ln in lines):
        raise DataError(f"{path}: the file is empty (a PhotoModeler text export starts with "
                        f"5 header lines)")
    if len(lines) < 5:
        raise DataError(f"{path}:{len(lines)}: the file ends early: 5 header lines expected")
    head = lines[1].split()
    if len(head) < 4:
        raise DataError(f"{path}:2: expected 'tolerance iterations width height' (the image's "
                        f"width and height in pixels appended by hand, as DBAT asks), got "
                        f"{lines[1].strip()!r}")
    w, h = _floats(path, 1, lines[1], 4, "header")[2:]
    if not (w > 0 and h > 0):
        raise DataError(f"{path}:2: the image's width and height must be positive pixels")
    camera = _floats(path, 3, lines[3], 10, "camera")
    warnings = []
    photos, photo_line, seen = [], [], {}
    k = 5
    while k < len(lines) and _photo_no(lines[k]) is not None and len(lines[k].split()) >= 2 \
            and not _num(lines[k].split()[1]):
        n = _id(path, k, lines[k].split()[0], "photo number")
        name = lines[k].split(None, 1)[1].strip()
        if k + 5 >= len(lines):
            raise DataError(f"{path}:{len(lines)}: the file ends in photo {n}'s block")
        for j in (1, 2, 4, 5):
            if _photo_no(lines[k + j]) != n:
                raise DataError(f"{path}:{k + j + 1}: expected a line of photo {n}, got "
                                f"{lines[k + j].strip()!r}")
        pos = _floats(path, k + 1, lines[k + 1], 6, f"photo {n}", first_int=True)
        cam = _floats(path, k + 4, lines[k + 4], 10, f"photo {n}'s camera", first_int=True)
        for col, name_ in ((0, "c"), (3, "xs"), (4, "ys")):
            if not cam[col] > 0:
                raise DataError(f"{path}:{k + 5}: photo {n}'s camera: {name_} must be "
                                f"positive, found {_fmt(cam[col])}")
        if _once(path, "photo", n, k + 1, [name, *pos, *cam], seen, _PHOTO_COLUMNS,
                 warnings):
            photos.append((n, name, pos, cam))
            photo_line.append(k + 1)
        k += 6
    if not photos:
        raise DataError(f"{path}:{k + 1}: no photo block (expected 'N name' after the 5 "
                        f"header lines)")
    # the blank line that ends the photos, then blocks of lines separated by blank lines
    if k < len(lines) and lines[k].strip():
        raise DataError(f"{path}:{k + 1}: expected a blank line after the photos, got "
                        f"{lines[k].strip()!r}")
    k += 1
    blocks = [[]]
    while k < len(lines) and len(blocks) <= 3:
        if lines[k].strip():
            blocks[-1].append(k)
        else:
            blocks.append([])
        k += 1
    while len(blocks) < 3:
        blocks.append([])
    tables = []
    for what, block in (("control point", blocks[0]), ("object point", blocks[1])):
        ids, rows, seen = [], [], {}
        for i in block:
            pid = _id(path, i, lines[i].split()[0], f"{what} id")
            v = _floats(path, i, lines[i], 6, what, first_int=True)
            if _once(path, what, pid, i + 1, v, seen, _POINT_COLUMNS, warnings):
                ids.append(pid)
                rows.append(v)
        tables.append((np.array(ids, np.int64), np.array(rows, np.float64).reshape(-1, 6)))
    marked, marked_line = [], []
    for i in blocks[2]:
        t = lines[i].split()
        if len(t) < 4:
            raise DataError(f"{path}:{i + 1}: marked point: expected 'photo id x y [sx sy]', "
                            f"got {lines[i].strip()!r}")
        ph = _id(path, i, t[0], "marked point's photo")
        pt = _id(path, i, t[1], "marked point's id")
        v = _floats(path, i, " ".join(t[2:]), 4 if len(t) >= 6 else 2, "marked point")
        for tok, x in zip(t[4:6], v[2:4]):
            if x < 0:
                raise DataError(f"{path}:{i + 1}: marked point sigma must be positive, found "
                                f"{tok} (0 or none: the camera's sigma)")
        marked.append([ph, pt, v[0], v[1]] + (v[2:4] if len(v) == 4 else [0.0, 0.0]))
        marked_line.append(i + 1)
    marked, marked_line = _merge_marks(path, marked, marked_line, warnings)
    (cid, cval), (oid, oval) = tables
    return {"size": (w, h), "camera": camera, "photos": photos, "photo_line": photo_line,
            "control": np.column_stack([cid.astype(np.float64), cval]),
            "points": np.column_stack([oid.astype(np.float64), oval]),
            "control_id": cid, "point_id": oid,
            "marked": np.array(marked, np.float64).reshape(-1, 6),
            "marked_ids": np.array([r[:2] for r in marked], np.int64).reshape(-1, 2),
            "marked_line": np.array(marked_line, np.int64), "lines": blocks,
            "warnings": warnings}


def pm_correct(x, y, camera):
    """PhotoModeler's backward correction of measured points (mm from the image centre, y
    up): the ideal points (see the module's comment). ``camera``: c, xp, yp, xs, ys, K1, K2,
    K3, P1, P2 (xp, yp from the top-left corner, y down)."""
    c, xp, yp, xs, ys, k1, k2, k3, p1, p2 = camera
    x0, y0 = xp - xs / 2, ys / 2 - yp
    u, v = x - x0, y - y0
    r2 = u * u + v * v
    radial = k1 * r2 + k2 * r2 * r2 + k3 * r2 ** 3
    return (x + u * radial + p1 * (r2 + 2 * u * u) + 2 * p2 * u * v,
            y + v * radial + 2 * p1 * u * v + p2 * (r2 + 2 * v * v))


@writes_project("import", "out")
def import_photomodeler(path, out, force=False):
    """Import a PhotoModeler text export into a new project ``out``: one camera per
    distinct camera row of the photos (its distortion in the backward model, as
    PhotoModeler's), photos with ids their numbers, the object points (ids theirs) as pass
    points with their coordinates as approximations, the control points as full control
    (a sigma at or below 0: fixed), or a free network without control. Returns a summary
    dict (``warnings``: lines for the user: repeats loaded once, marks merged)."""
    from ..project import (
        CAMERA_DTYPE,
        KIND_CONTROL,
        OBSERVATION_DTYPE,
        STATION_DTYPE,
        append_history,
        new_project_path,
        point_records,
        write_project,
    )

    out = new_project_path(out, force)
    d = read_photomodeler(path)
    w, h = d["size"]
    rows = [tuple(cam) for _, _, _, cam in d["photos"]]
    uniq = sorted(set(rows), key=rows.index)
    cam_of_photo = np.array([uniq.index(r) for r in rows], np.int64)
    cams = np.array(uniq, np.float64)
    camera = np.zeros(len(cams), CAMERA_DTYPE)
    camera["id"] = np.arange(1, len(cams) + 1)
    camera["focal_length"] = cams[:, 0]
    camera["x0"], camera["y0"] = cams[:, 1] - cams[:, 3] / 2, cams[:, 4] / 2 - cams[:, 2]
    camera["format_x"], camera["format_y"] = cams[:, 3], cams[:, 4]
    for k, name in enumerate(("k1", "k2", "k3", "p1", "p2")):
        camera[name] = cams[:, 5 + k]
    camera["distortion_model"] = BACKWARD
    with np.errstate(all="ignore"):
        pw, ph = cams[:, 3] / w, cams[:, 4] / h
        camera["sigma_image"] = np.sqrt(pw * ph) * 0.1   # (0.1 px where a point has none)
    bad = np.flatnonzero(~(np.isfinite(pw) & (pw > 0) & np.isfinite(ph) & (ph > 0)
                           & np.isfinite(camera["sigma_image"]) & (camera["sigma_image"] > 0)))
    if len(bad):
        j = int(np.flatnonzero(cam_of_photo == bad[0])[0])
        raise DataError(f"{path}:{d['photo_line'][j] + 4}: photo {d['photos'][j][0]}'s "
                        f"camera: the pixel size (xs / width, ys / height) is out of range")
    ids = np.array([n for n, _, _, _ in d["photos"]], np.int64)
    if len(np.unique(ids)) != len(ids):
        raise AssertionError("photo numbers repeat")   # (read_photomodeler refuses them)
    pos = np.array([p for _, _, p, _ in d["photos"]], np.float64)
    station = np.zeros(len(ids), STATION_DTYPE)
    station["id"] = ids
    station["camera"] = cam_of_photo
    station["strip"] = -1
    station["eo"][:, :3] = np.radians(pos[:, [5, 4, 3]])   # (kappa phi omega in the file)
    station["eo"][:, 3:] = pos[:, :3]
    # points: the object points, the control's values where given (ids exact int64)
    pts, pts_id = d["points"][:, 1:], d["point_id"]
    ctrl, ctrl_id = d["control"][:, 1:], d["control_id"]
    all_ids = np.unique(np.concatenate([pts_id, ctrl_id]))
    n_pt = len(all_ids)
    xyz = np.zeros((n_pt, 3))
    xyz[np.searchsorted(all_ids, pts_id)] = pts[:, :3]
    kind = np.zeros(n_pt, np.int8)
    control = np.zeros((n_pt, 3))
    csig = np.zeros((n_pt, 3))
    if len(ctrl):
        at = np.searchsorted(all_ids, ctrl_id)
        kind[at] = KIND_CONTROL
        control[at] = ctrl[:, :3]
        csig[at] = np.maximum(ctrl[:, 3:6], 0.0)      # (<= 0: fixed, as DBAT reads it)
        only = ~np.isin(ctrl_id, pts_id)
        xyz[at[only]] = ctrl[only, :3]
    m, m_ids, m_line = d["marked"], d["marked_ids"], d["marked_line"]
    if not len(m):
        raise DataError(f"{path}: no marked points (image measurements)")
    order_ids = np.argsort(ids, kind="stable")
    sorted_ids = ids[order_ids]
    at = np.searchsorted(sorted_ids, m_ids[:, 0])
    bad = np.flatnonzero((at >= len(ids)) | (sorted_ids[np.minimum(at, len(ids) - 1)]
                                             != m_ids[:, 0]))
    if len(bad):
        raise DataError(f"{path}:{int(m_line[bad[0]])}: marked point on photo "
                        f"{int(m_ids[bad[0], 0])}, which has no photo block")
    st_rec = order_ids[at]
    p_rec = np.searchsorted(all_ids, m_ids[:, 1])
    bad = np.flatnonzero((p_rec >= n_pt) | (all_ids[np.minimum(p_rec, n_pt - 1)]
                                            != m_ids[:, 1]))
    if len(bad):
        raise DataError(f"{path}:{int(m_line[bad[0]])}: marked point {int(m_ids[bad[0], 1])} "
                        f"is not an object or control point")
    c = cam_of_photo[st_rec]
    given = (m[:, 4] > 0) & (m[:, 5] > 0)
    with np.errstate(all="ignore"):
        x = m[:, 2] * pw[c] - cams[c, 3] / 2
        y = cams[c, 4] / 2 - m[:, 3] * ph[c]
        sig = np.where(given, np.sqrt(m[:, 4] * m[:, 5] * pw[c] * ph[c]), 0.0)
    bad = np.flatnonzero(~(np.isfinite(x) & np.isfinite(y) & np.isfinite(sig))
                         | (given & ~(sig > 0)))
    if len(bad):
        raise DataError(f"{path}:{int(m_line[bad[0]])}: marked point: a value is out of range "
                        f"once converted to mm")
    order = np.lexsort((st_rec, p_rec))
    obs = np.zeros(len(m), OBSERVATION_DTYPE)
    obs["point"], obs["station"] = p_rec[order], st_rec[order]
    obs["x"], obs["y"], obs["sigma"] = x[order], y[order], sig[order]
    point = point_records(obs["point"], n_pt, id=all_ids, kind=kind, xyz=xyz,
                          control=control, control_sigma=csig)
    free = not len(ctrl)
    creator = {"command": "import", "format": "photomodeler", "file": str(path)}
    attrs = {"creator": json.dumps(creator), "history": append_history("[]", creator)}
    if free:
        attrs.update(datum="free")
    write_project(out, camera, station, point, obs, attrs=attrs)
    return {"path": str(out), "cameras": len(camera), "photos": len(station),
            "points": n_pt, "control_points": int(len(ctrl)), "observations": len(obs),
            "free": free, "warnings": d["warnings"]}


def export_photomodeler(project_path, out_path, adjusted=False, pixel_size=None):
    """Write a project (its inputs, or with ``adjusted`` its adjusted values) as a
    PhotoModeler text export that :func:`import_photomodeler` and DBAT read: the image
    measurements in pixels of ``pixel_size`` micrometres (from the top-left corner, y down;
    the image's size on line 2), a camera of the backward model without affinity as it is
    (PhotoModeler's own model), the others without distortion and their measurements freed
    of it (K, P 0: the measurements are ideal), photos by their ids (>= 0),
    full control points as control (a sigma 0: fixed), every active point as an object
    point. Horizontal and vertical control have no place in the format and go as object
    points only. Image coordinates must be millimetres. Returns a dict of counts."""
    from ..geometry import camera_array, undistort_points
    from ..project import KIND_CONTROL, KIND_HORIZONTAL, KIND_VERTICAL, STATUS_ACTIVE, Project

    if pixel_size is None or not (pixel_size > 0 and math.isfinite(pixel_size)):
        raise ParameterError("--pixel-size UM (micrometres, positive) is needed: a "
                             "PhotoModeler export gives the measurements in pixels")
    with Project(project_path) as p:
        if str(p.attr("image_unit", "mm") or "mm") != "mm":
            raise ParameterError(f"{project_path}: the image coordinates are not in mm: a "
                                 f"PhotoModeler export needs a camera in mm")
        if adjusted and not p.has_solution:
            raise DataError(f"{project_path}: the project has no adjusted solution: run "
                            f"'sapgo adjust' first")
        cams = camera_array(p.cameras())
        st, pt, ob = p.read("stations"), p.read("points"), p.read("observations")
        eo, xyz = st["eo"].copy(), pt["xyz"].copy()
        if adjusted:
            cams = cams + p.solution("camera_corr")
            eo += p.solution("station_corr")
            xyz += p.solution("point_corr")
        formats = np.column_stack([p.cameras()["format_x"], p.cameras()["format_y"]])
        sigma_cam = p.cameras()["sigma_image"]
    if (st["id"] < 0).any():
        raise DataError(f"{project_path}: photo id {int(st['id'][st['id'] < 0][0])}: "
                        f"PhotoModeler numbers photos from 0")
    pw = pixel_size / 1000.0
    live = ((ob["status"] == STATUS_ACTIVE) & (pt["status"][ob["point"]] == STATUS_ACTIVE)
            & (st["status"][ob["station"]] == STATUS_ACTIVE))
    o = np.flatnonzero(live)
    o = o[np.lexsort((pt["id"][ob["point"][o]], st["id"][ob["station"][o]]))]
    cam_of = st["camera"].astype(np.int64)
    xy = np.column_stack([ob["x"][o], ob["y"][o]]).astype(np.float64)
    # a camera of PhotoModeler's own (backward) model goes as it is, with the measurements;
    # for the others the measurements are freed of the distortion
    own = ((cams[:, 10] == BACKWARD) & (cams[:, 8:10] == 0.0).all(axis=1)
           & (cams[:, AP_SET] == 0.0))
    ideal = np.empty_like(xy)
    undistort_points(xy, cam_of[ob["station"][o]], cams, ideal)
    c = cam_of[ob["station"][o]]
    ideal[own[c]] = xy[own[c]] - cams[c[own[c]], 1:3]
    bad = np.flatnonzero(~np.isfinite(ideal).all(axis=1))
    if len(bad):
        raise DataError(f"{project_path}: the distortion of photo "
                        f"{int(st['id'][ob['station'][o[bad[0]]]])}'s camera cannot be "
                        f"inverted at one of its points")
    mx, my = ideal[:, 0] + cams[c, 1], ideal[:, 1] + cams[c, 2]
    col, row = (mx + formats[c, 0] / 2) / pw, (formats[c, 1] / 2 - my) / pw
    sig = np.where(ob["sigma"][o] > 0, ob["sigma"][o], sigma_cam[c]) / pw

    def camline(k):
        f, x0, y0 = cams[k, :3]
        xs, ys = formats[k]
        dist = cams[k, 3:8] if own[k] else np.zeros(5)
        return " ".join(repr(float(v)) for v in (f, x0 + xs / 2, ys / 2 - y0, xs, ys,
                                                 *dist))

    if not (np.allclose(formats / pw, formats[0] / pw)):
        raise DataError(f"{project_path}: the cameras' formats differ: a PhotoModeler export "
                        f"holds one image size")
    lines = [f"sapgo export of {Path(project_path).name}",
             f" 0.0001 20 {float(formats[0, 0] / pw)!r} {float(formats[0, 1] / pw)!r}",
             " 1 0.1 10 100 100 100 20 20 20", " " + camline(0), " " + " ".join(["0"] * 10)]
    order = np.argsort(st["id"], kind="stable")
    for s in order:
        if st["status"][s] != STATUS_ACTIVE:
            continue
        n = int(st["id"][s])
        om, ph, ka = np.degrees(eo[s, :3])
        lines += [f"  {n} photo_{n}",
                  f"  {n} " + " ".join(repr(float(v)) for v in (*eo[s, 3:], ka, ph, om)),
                  f"  {n} 0 0 0 0 0 0", "", f"  {n} {camline(cam_of[s])}",
                  f"  {n} " + " ".join(["0"] * 10)]
    lines.append("")
    act = pt["status"] == STATUS_ACTIVE
    full = np.flatnonzero(act & (pt["kind"] == KIND_CONTROL))
    for j in full:
        lines.append(f"  {int(pt['id'][j])} " + " ".join(
            repr(float(v)) for v in (*pt["control"][j], *pt["control_sigma"][j])))
    lines.append("")
    for j in np.flatnonzero(act)[np.argsort(pt["id"][act], kind="stable")]:
        lines.append(f"  {int(pt['id'][j])} " + " ".join(repr(float(v)) for v in xyz[j])
                     + " 0 0 0")
    lines.append("")
    lines += [f"  {int(st['id'][ob['station'][i]])} {int(pt['id'][ob['point'][i]])} "
              f"{float(a)!r} {float(b)!r} {float(s)!r} {float(s)!r}"
              for i, a, b, s in zip(o, col, row, sig)]
    Path(out_path).write_text("\n".join(lines) + "\n")
    return {"photos": int((st["status"] == STATUS_ACTIVE).sum()), "points": int(act.sum()),
            "control_points": len(full), "observations": len(o),
            "partial_control": int((act & np.isin(pt["kind"], (KIND_HORIZONTAL,
                                                                KIND_VERTICAL))).sum())}
