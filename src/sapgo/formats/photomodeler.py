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
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..lock import writes_project
from ..errors import DataError, ParameterError
from ..geometry import AP_SET, BACKWARD

__all__ = ["export_photomodeler", "import_photomodeler", "pm_correct", "read_photomodeler"]


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


def _photo_no(line):
    t = line.split()
    return int(t[0]) if t and t[0].lstrip("-").isdigit() else None


def read_photomodeler(path):
    """Read a PhotoModeler text export: a dict of ``size`` (width, height px), ``camera``
    (c, xp, yp, xs, ys, K1, K2, K3, P1, P2), ``photos`` (number, name, X, Y, Z, kappa, phi,
    omega in degrees, camera row), ``control`` and ``points`` (id, X, Y, Z, sX, sY, sZ) and
    ``marked`` (photo, id, x, y, sx, sy; pixels). Errors name the file and line."""
    path = Path(path)
    try:
        lines = path.read_text(errors="strict").splitlines()
    except UnicodeDecodeError as exc:
        raise DataError(f"{path}: not a text file ({exc.reason})") from None
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
    photos = []
    k = 5
    while k < len(lines) and _photo_no(lines[k]) is not None and len(lines[k].split()) >= 2 \
            and not _num(lines[k].split()[1]):
        n = _photo_no(lines[k])
        name = lines[k].split(None, 1)[1].strip()
        if k + 5 >= len(lines):
            raise DataError(f"{path}:{len(lines)}: the file ends in photo {n}'s block")
        for j in (1, 2, 4, 5):
            if _photo_no(lines[k + j]) != n:
                raise DataError(f"{path}:{k + j + 1}: expected a line of photo {n}, got "
                                f"{lines[k + j].strip()!r}")
        pos = _floats(path, k + 1, lines[k + 1], 6, f"photo {n}", first_int=True)
        cam = _floats(path, k + 4, lines[k + 4], 10, f"photo {n}'s camera", first_int=True)
        photos.append((n, name, pos, cam))
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
    control = [[int(lines[i].split()[0])] + _floats(path, i, lines[i], 6, "control point",
                                                     first_int=True) for i in blocks[0]]
    points = [[int(lines[i].split()[0])] + _floats(path, i, lines[i], 6, "object point",
                                                    first_int=True) for i in blocks[1]]
    marked = []
    for i in blocks[2]:
        t = lines[i].split()
        if len(t) < 4 or not t[0].isdigit():
            raise DataError(f"{path}:{i + 1}: marked point: expected 'photo id x y [sx sy]', "
                            f"got {lines[i].strip()!r}")
        v = _floats(path, i, lines[i], 5 if len(t) >= 6 else 3, "marked point",
                    first_int=True)
        if v[0] != int(v[0]):
            raise DataError(f"{path}:{i + 1}: marked point: id {t[1]!r} is not an integer")
        marked.append([int(t[0]), int(v[0]), v[1], v[2]] + (v[3:5] if len(v) == 5
                                                             else [0.0, 0.0]))
    return {"size": (w, h), "camera": camera, "photos": photos,
            "control": np.array(control, np.float64).reshape(-1, 7),
            "points": np.array(points, np.float64).reshape(-1, 7),
            "marked": np.array(marked, np.float64).reshape(-1, 6), "lines": blocks}


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
    dict."""
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
    pw, ph = cams[:, 3] / w, cams[:, 4] / h
    camera["sigma_image"] = np.sqrt(pw * ph) * 0.1       # (0.1 px where a point has none)
    ids = np.array([n for n, _, _, _ in d["photos"]], np.int64)
    if len(np.unique(ids)) != len(ids):
        raise DataError(f"{path}: photo numbers repeat")
    pos = np.array([p for _, _, p, _ in d["photos"]], np.float64)
    station = np.zeros(len(ids), STATION_DTYPE)
    station["id"] = ids
    station["camera"] = cam_of_photo
    station["strip"] = -1
    station["eo"][:, :3] = np.radians(pos[:, [5, 4, 3]])   # (kappa phi omega in the file)
    station["eo"][:, 3:] = pos[:, :3]
    # points: the object points, the control's values where given
    pts = d["points"]
    ctrl = d["control"]
    all_ids = np.unique(np.concatenate([pts[:, 0], ctrl[:, 0]])).astype(np.int64)
    n_pt = len(all_ids)
    xyz = np.zeros((n_pt, 3))
    xyz[np.searchsorted(all_ids, pts[:, 0].astype(np.int64))] = pts[:, 1:4]
    kind = np.zeros(n_pt, np.int8)
    control = np.zeros((n_pt, 3))
    csig = np.zeros((n_pt, 3))
    if len(ctrl):
        at = np.searchsorted(all_ids, ctrl[:, 0].astype(np.int64))
        kind[at] = KIND_CONTROL
        control[at] = ctrl[:, 1:4]
        csig[at] = np.maximum(ctrl[:, 4:7], 0.0)      # (<= 0: fixed, as DBAT reads it)
        only = ~np.isin(ctrl[:, 0], pts[:, 0])
        xyz[at[only]] = ctrl[only, 1:4]
    m = d["marked"]
    if not len(m):
        raise DataError(f"{path}: no marked points (image measurements)")
    st_rec = np.searchsorted(ids, m[:, 0].astype(np.int64))
    bad = np.flatnonzero((st_rec >= len(ids)) | (ids[np.minimum(st_rec, len(ids) - 1)]
                                                 != m[:, 0]))
    if len(bad):
        line = d["lines"][2][bad[0]] + 1
        raise DataError(f"{path}:{line}: marked point on photo {int(m[bad[0], 0])}, which "
                        f"has no photo block")
    p_rec = np.searchsorted(all_ids, m[:, 1].astype(np.int64))
    bad = np.flatnonzero((p_rec >= n_pt) | (all_ids[np.minimum(p_rec, n_pt - 1)] != m[:, 1]))
    if len(bad):
        line = d["lines"][2][bad[0]] + 1
        raise DataError(f"{path}:{line}: marked point {int(m[bad[0], 1])} is not an object "
                        f"or control point")
    c = cam_of_photo[st_rec]
    x = m[:, 2] * pw[c] - cams[c, 3] / 2
    y = cams[c, 4] / 2 - m[:, 3] * ph[c]
    sig = np.where((m[:, 4] > 0) & (m[:, 5] > 0), np.sqrt(m[:, 4] * m[:, 5] * pw[c] * ph[c]),
                   0.0)
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
            "free": free}


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
