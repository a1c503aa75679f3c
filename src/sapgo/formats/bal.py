"""BAL ("Bundle Adjustment in the Large", Agarwal et al. 2010) problems: read, convert, write.

Format (plain text, whitespace separated)::

    num_cameras num_points num_observations
    camera_index point_index x y          (num_observations lines; pixels, origin at the
                                           image centre, y up)
    9 values per camera: Rodrigues rotation (3), translation (3), f, k1, k2
    3 values per point: X, Y, Z

Camera model: ``P = R X + t``, ``p = -P[:2] / P[2]``, ``d = 1 + k1 |p|^2 + k2 |p|^4``,
projection ``f d p``; ``R`` (world to camera) is the Rodrigues vector.

This is sapgo's collinearity model exactly (docs/theory.md section 1) with image units of
pixels: ``M = R``, the projection centre ``Xc = -R' t``, focal length ``f``, principal point
0 and radial distortion ``k1 / f^2``, ``k2 / f^4`` (sapgo's distortion is in image units).
Each BAL camera becomes a photo with a camera of its own (intrinsics held fixed), the image
sigma 1 pixel, so that ``1/2 sum v^2`` is the BAL (Ceres) cost.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..lock import writes_project
from ..errors import DataError
from ..geometry import N_CAMERA


def _tokens_error(path, lines, start, count, per_line, what):
    """The first line among ``lines[start:start + count]`` that does not hold ``per_line``
    numbers: a DataError naming it."""
    for k in range(start, min(len(lines), start + count)):
        parts = lines[k].split()
        if len(parts) != per_line:
            return DataError(f"{path}:{k + 1}: {what}: expected {per_line} values, got "
                             f"{len(parts)}")
        try:
            [float(x) for x in parts]
        except ValueError:
            bad = next(x for x in parts if not _is_number(x))
            return DataError(f"{path}:{k + 1}: {what}: {bad!r} is not a number")
    return DataError(f"{path}:{len(lines)}: the file ends early: {count} {what} lines "
                     f"expected from line {start + 1}")


def _is_number(x):
    try:
        float(x)
        return True
    except ValueError:
        return False


def read_text(path):
    """The text of a file, plain or compressed (``.gz``, ``.bz2``); a file that is not text
    or cannot be read is one line naming it."""
    path = Path(path)
    try:
        if path.suffix == ".gz":
            import gzip

            with gzip.open(path, "rb") as f:
                data = f.read()
        elif path.suffix == ".bz2":
            import bz2

            with bz2.open(path, "rb") as f:
                data = f.read()
        else:
            data = path.read_bytes()
    except (OSError, EOFError) as exc:
        if isinstance(exc, FileNotFoundError):
            raise
        raise DataError(f"{path}: cannot be read ({exc})") from None
    from .text import decode_text

    return decode_text(path, data)


def read_bal(path):
    """Read a BAL problem (plain, ``.gz`` or ``.bz2``): ``dict(cameras (n x 9), points
    (m x 3), obs_camera, obs_point (int64), obs_xy (k x 2))``. Errors name the file and
    line."""
    path = Path(path)
    lines = read_text(path).splitlines()
    first = next((k for k, ln in enumerate(lines) if ln.strip()), None)
    if first is None:
        raise DataError(f"{path}: the file is empty")
    head = lines[first].split()
    if len(head) != 3 or not all(h.isdigit() for h in head):
        raise DataError(f"{path}:{first + 1}: expected 'num_cameras num_points "
                        f"num_observations' (three non-negative integers), got "
                        f"{lines[first].strip()!r}")
    n_cam, n_pt, n_obs = (int(h) for h in head)
    if n_cam < 1 or n_pt < 1 or n_obs < 1:
        raise DataError(f"{path}:{first + 1}: no cameras, points or observations")
    # observation lines: the next n_obs non-empty lines
    body = [k for k in range(first + 1, len(lines)) if lines[k].strip()]
    if len(body) < n_obs:
        raise DataError(f"{path}:{len(lines)}: the file ends early: {n_obs} observation "
                        f"lines expected, {len(body)} lines follow the header")
    obs_lines = body[:n_obs]
    try:
        obs = np.array(" ".join(lines[k] for k in obs_lines).split(), dtype=np.float64)
    except ValueError:
        obs = None
    if obs is None or obs.size != 4 * n_obs:
        for k in obs_lines:
            parts = lines[k].split()
            if len(parts) != 4 or not all(_is_number(x) for x in parts):
                raise DataError(f"{path}:{k + 1}: observation: expected 'camera_index "
                                f"point_index x y', got {lines[k].strip()!r}")
    obs = obs.reshape(n_obs, 4)
    rest_lines = body[n_obs:]
    try:
        rest = np.array(" ".join(lines[k] for k in rest_lines).split(), dtype=np.float64)
    except ValueError:
        for k in rest_lines:
            for x in lines[k].split():
                if not _is_number(x):
                    raise DataError(f"{path}:{k + 1}: camera or point parameter: {x!r} is "
                                    f"not a number") from None
        raise
    need = 9 * n_cam + 3 * n_pt
    if rest.size != need:
        where = rest_lines[-1] + 1 if rest_lines else len(lines)
        raise DataError(f"{path}:{where}: {rest.size} camera and point parameters after the "
                        f"observations, expected {need} (9 per camera, 3 per point)")
    cam_i, pt_i = obs[:, 0], obs[:, 1]
    for name, idx, n in (("camera", cam_i, n_cam), ("point", pt_i, n_pt)):
        bad = np.flatnonzero((idx != np.round(idx)) | (idx < 0) | (idx >= n))
        if len(bad):
            k = obs_lines[bad[0]]
            token = lines[k].split()[0 if name == "camera" else 1]
            raise DataError(f"{path}:{k + 1}: {name} index {token} is not one of "
                            f"0..{n - 1}")
    bad = np.flatnonzero(~np.isfinite(obs[:, 2:]).all(axis=1))
    if len(bad):
        k = obs_lines[bad[0]]
        raise DataError(f"{path}:{k + 1}: observation x or y is not finite")
    cams = rest[:9 * n_cam].reshape(n_cam, 9)
    pts = rest[9 * n_cam:].reshape(n_pt, 3)
    for name, arr, per, off in (("camera", cams, 9, 0), ("point", pts, 3, 9 * n_cam)):
        bad = np.flatnonzero(~np.isfinite(arr).all(axis=1))
        if len(bad):
            j = int(bad[0])
            col = int(np.flatnonzero(~np.isfinite(arr[j]))[0])
            k = rest_lines[min(len(rest_lines) - 1, off + per * j + col)]
            raise DataError(f"{path}:{k + 1}: {name} {j}: a parameter is not finite")
    bad = np.flatnonzero(cams[:, 6] <= 0)
    if len(bad):
        k = rest_lines[9 * int(bad[0]) + 6]
        raise DataError(f"{path}:{k + 1}: camera {int(bad[0])}: focal length "
                        f"{float(cams[bad[0], 6]):g} is not positive")
    return {"cameras": cams, "points": pts, "obs_camera": cam_i.astype(np.int64),
            "obs_point": pt_i.astype(np.int64), "obs_xy": obs[:, 2:].copy(),
            "obs_line": np.asarray(obs_lines, np.int64) + 1}


#: Two observations of one point on one photo at most this many image sigmas apart are one
#: measurement written twice: they are merged (averaged) with a warning. Farther apart
#: they contradict each other, and the import stops unless asked to average them.
DUPLICATE_SIGMAS = 3.0


def merge_repeats(path, d, key, xy, tol, merge, where, pair, what, hint, also=()):
    """Observations of ``d`` (an import's dict, its ``obs_*`` arrays cut in place to each
    repeated pair's first observation) that share ``key`` (a photo and a point) merged at
    the mean of their ``xy`` (pixels; returned, merged). A pair whose observations lie more
    than ``tol`` pixels apart is a :class:`DataError` naming ``path``, both lines
    (``where(i)``) and the pair, unless ``merge``. ``pair(i)``: the (photo, point) words of
    observation ``i`` ("camera 3", "point 7"); ``what``: the pair's kind for the warning
    ("(camera, point)"); ``hint``: the error's advice; ``also``: names of other ``obs_*``
    arrays of ``d`` (n x k) averaged the same way. Returns the merged ``xy`` and the
    warning lines (none without repeats)."""
    _, first, group, counts = np.unique(key, return_index=True, return_inverse=True,
                                        return_counts=True)
    if len(first) == len(key):
        return xy, []
    group = group.ravel()
    by_group = np.argsort(group, kind="stable")   # group g: by_group[start[g]:start[g + 1]]
    start = np.concatenate([[0], np.cumsum(counts)])

    def members(g):
        return by_group[start[g]:start[g + 1]]

    # only a pair whose observations span more than tol can hold two farther apart
    lo = np.full((len(first), 2), np.inf)
    hi = np.full((len(first), 2), -np.inf)
    np.minimum.at(lo, group, xy)
    np.maximum.at(hi, group, xy)
    wide = np.flatnonzero(np.hypot(*(hi - lo).T) > tol)
    conflicts = []   # per such pair, its two farthest observations (in file order), distance
    for g in wide[np.argsort(first[wide], kind="stable")].tolist():
        m = members(g)
        dist = np.hypot(*(xy[m, None, :] - xy[None, m, :]).transpose(2, 0, 1))
        i, j = np.unravel_index(int(np.argmax(dist)), dist.shape)
        if dist[i, j] > tol:
            conflicts.append((*sorted((int(m[i]), int(m[j]))), float(dist[i, j])))
    if conflicts and not merge:
        i, j, dist = conflicts[0]
        more = f" (and {len(conflicts) - 1} more such pair(s))" if len(conflicts) > 1 else ""
        photo, point = pair(i)
        raise DataError(f"{path}: lines {where(i)} and {where(j)}: {photo} observes {point} "
                        f"twice, {dist:.4g} px apart (more than {DUPLICATE_SIGMAS:g} sigma = "
                        f"{tol:g} px){more}: {hint}")
    def average(v):
        return np.column_stack([np.bincount(group, weights=v[:, k]) / counts
                                for k in range(v.shape[1])])

    mean = average(xy)
    averaged = {name: average(d[name]) for name in also}
    keep = np.sort(first)
    pairs = np.sort(first[counts > 1])
    shown = "; ".join(" ".join(pair(i)) + " (lines "
                      + ", ".join(where(k) for k in members(group[i])[:3].tolist())
                      + ")" for i in pairs[:5].tolist())
    close = "" if conflicts else (f" within {DUPLICATE_SIGMAS:g} sigma ({tol:g} px) of "
                                  f"each other")
    out = [f"{path}: {len(pairs)} {what} pair(s) observed more than once{close}: "
           f"each merged into one observation at their mean ({len(key) - len(keep)} "
           f"observation(s) dropped): {shown}{'; ...' if len(pairs) > 5 else ''}"]
    if conflicts:
        i, j, dist = max(conflicts, key=lambda c: c[2])
        out.append(f"{path}: {len(conflicts)} of these pairs lie more than "
                   f"{DUPLICATE_SIGMAS:g} sigma ({tol:g} px) apart and were averaged as "
                   f"asked (--merge-duplicates); the farthest: {' '.join(pair(i))}, lines "
                   f"{where(i)} and {where(j)}, {dist:.4g} px")
    for name in [k for k in d if k.startswith("obs_")]:
        d[name] = averaged[name][group[keep]] if name in averaged else d[name][keep]
    return mean[group[keep]], out


def _merge_duplicates(path, d, sigma=1.0, merge=False, where=None):
    """Each (camera, point) pair observed more than once in ``d`` (a :func:`read_bal` or
    :func:`sapgo.formats.bundler.read_bundler` dict, changed in place) reduced to its first
    observation, moved to the mean of the pair's observations (:func:`merge_repeats`; the
    other ``obs_*`` arrays keep the first one's values). ``where(i)``: the line of
    observation ``i`` in the file as a message gives it (default ``d["obs_line"]``).
    Returns warning lines for the user (none without duplicates)."""
    cam, pt = d["obs_camera"], d["obs_point"]
    if where is None:
        lines = d["obs_line"]

        def where(i):
            return str(int(lines[i]))

    xy, out = merge_repeats(path, d, cam * (int(pt.max(initial=0)) + 1) + pt, d["obs_xy"],
                            DUPLICATE_SIGMAS * sigma, merge, where,
                            lambda i: (f"camera {int(cam[i])}", f"point {int(pt[i])}"),
                            "(camera, point)", "use --merge-duplicates to average them")
    d["obs_xy"] = xy
    return out


def rodrigues(rvec):
    """Rotation matrices (n x 3 x 3) of Rodrigues vectors (n x 3): rotation by |r| about r."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(rvec, np.float64).reshape(-1, 3)).as_matrix()


def rodrigues_vector(m):
    """The inverse of :func:`rodrigues`."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(m, np.float64).reshape(-1, 3, 3)).as_rotvec()


def bal_to_sapgo(cams):
    """Stations ``(omega, phi, kappa, Xc, Yc, Zc)`` and camera rows
    (:data:`sapgo.geometry.CAMERA_FIELDS`) in image units (pixels) of BAL cameras (n x 9)."""
    return snavely_to_sapgo(rodrigues(cams[:, :3]), cams[:, 3:6], cams[:, 6:9])


def snavely_to_sapgo(r, t, fk):
    """:func:`bal_to_sapgo` of cameras given as rotation matrices ``r`` (n x 3 x 3, world to
    camera), translations ``t`` (n x 3) and ``(f, k1, k2)`` rows ``fk`` (Bundler's and BAL's
    camera model, Snavely et al. 2006)."""
    from ..frames import opk_of

    with np.errstate(all="ignore"):   # (values out of range: refused when written)
        centre = -np.einsum("nji,nj->ni", r, t)
        eo = np.column_stack([opk_of(r), centre])
        f = fk[:, 0]
        rows = np.column_stack([f, np.zeros_like(f), np.zeros_like(f), fk[:, 1] / f ** 2,
                                fk[:, 2] / f ** 4, np.zeros((len(f), N_CAMERA - 5))])
    return eo, rows


def sapgo_to_bal(eo, rows):
    """The inverse of :func:`bal_to_sapgo` (cameras without k3, p1, p2 and principal point)."""
    r, t, fk = sapgo_to_snavely(eo, rows)
    return np.column_stack([rodrigues_vector(r), t, fk])


def sapgo_to_snavely(eo, rows):
    """The inverse of :func:`snavely_to_sapgo`: ``(r, t, fk)``."""
    from ..frames import rotation_matrices

    r = rotation_matrices(eo[:, :3])
    t = -np.einsum("nij,nj->ni", r, eo[:, 3:])
    f = rows[:, 0]
    return r, t, np.column_stack([f, rows[:, 3] * f ** 2, rows[:, 4] * f ** 4])


def snavely_cost(r, t, fk, pts, obs_camera, obs_point, obs_xy):
    """``1/2 sum |projection - observation|^2`` of the Snavely camera model (Bundler, BAL)
    with rotation matrices ``r``: ``P = R X + t``, ``p = -P[:2] / P[2]``, projection
    ``f (1 + k1 |p|^2 + k2 |p|^4) p``."""
    c, j = obs_camera, obs_point
    p = np.einsum("nij,nj->ni", r[c], pts[j]) + t[c]
    q = -p[:, :2] / p[:, 2:3]
    r2 = (q * q).sum(axis=1)
    d = 1.0 + fk[c, 1] * r2 + fk[c, 2] * r2 * r2
    proj = fk[c, 0][:, None] * d[:, None] * q
    return 0.5 * float(((proj - obs_xy) ** 2).sum())


def bal_cost(data):
    """The BAL cost ``1/2 sum |projection - observation|^2`` with the file's values, computed
    directly from the BAL camera model (the reference for sapgo's conversion)."""
    cams = data["cameras"]
    return snavely_cost(rodrigues(cams[:, :3]), cams[:, 3:6], cams[:, 6:9], data["points"],
                        data["obs_camera"], data["obs_point"], data["obs_xy"])


def write_bal(path, cams, pts, obs_camera, obs_point, obs_xy):
    """Write a BAL problem (observations in the given order)."""
    with open(path, "w") as f:
        f.write(f"{len(cams)} {len(pts)} {len(obs_camera)}\n")
        f.write("".join(f"{int(a)} {int(b)} {x!r} {y!r}\n" for a, b, x, y in
                        zip(obs_camera.tolist(), obs_point.tolist(), obs_xy[:, 0].tolist(),
                            obs_xy[:, 1].tolist())))
        f.write("".join(f"{v!r}\n" for v in np.asarray(cams, np.float64).ravel().tolist()))
        f.write("".join(f"{v!r}\n" for v in np.asarray(pts, np.float64).ravel().tolist()))


@writes_project("import", "out")
def import_bal(path, out, force=False, intrinsics="adjusted", merge_duplicates=False):
    """Import the BAL problem ``path`` into a new project ``out``: one photo and one camera
    per BAL camera (ids = BAL indices; its f, k1, k2 ``"adjusted"`` with the photo, as
    9-parameter stations, or held ``"fixed"``), the points as pass
    points with the file's coordinates as approximations, image units pixels with sigma 1
    (the project attribute ``image_unit`` is ``"px"``). A (camera, point) pair observed
    more than once is merged into one averaged observation with a warning when its
    observations lie within :data:`DUPLICATE_SIGMAS` pixels of each other; farther apart
    they are an error unless ``merge_duplicates`` (then averaged too). Returns a summary
    dict (``warnings``: lines for the user; ``initial_cost`` of the observations
    imported)."""
    out = _check_out(out, force, intrinsics)
    d = read_bal(path)
    n_read = len(d["obs_camera"])
    warnings = _merge_duplicates(path, d, merge=merge_duplicates)
    with np.errstate(all="ignore"):
        eo, rows = bal_to_sapgo(d["cameras"])
        cost = bal_cost(d)
    if not np.isfinite(cost):
        raise DataError(f"{path}: the initial cost is {cost} (a camera's or point's value out "
                        f"of range?)")
    n = write_snavely_project(out, {"command": "import", "format": "bal", "file": str(path)},
                              eo, rows, np.arange(len(eo)), d["points"], d["obs_camera"],
                              d["obs_point"], d["obs_xy"], intrinsics)
    return {"path": str(out), "cameras": len(eo), "photos": len(eo),
            "points": len(d["points"]), "observations": n,
            "duplicates_dropped": n_read - n, "warnings": warnings,
            "initial_cost": cost}


def _check_out(out, force, intrinsics):
    from ..errors import ParameterError
    from ..project import new_project_path

    if intrinsics not in ("adjusted", "fixed"):
        raise ParameterError(f"intrinsics {intrinsics!r}: adjusted or fixed")
    return new_project_path(out, force)


def write_snavely_project(out, creator, eo, rows, station_ids, pts, obs_camera, obs_point,
                          obs_xy, intrinsics, extra=None, point_ids=None, cameras=None,
                          sigma_image=1.0):
    """A new project ``out`` of a block in pixels without control (BAL, Bundler, OpenSfM):
    one photo and one camera per station (``eo``, camera ``rows`` in pixels, ids
    ``station_ids``; observations name stations by their index in these), or with
    ``cameras`` = ``(ids, rows, formats, station's camera index)`` those cameras, shared;
    the points as pass points (ids ``point_ids``, else their indices) with their
    coordinates as approximations, image sigma ``sigma_image`` pixels, a free network whose
    points may lie behind a photo. ``extra(file)`` writes format-specific groups. Returns
    the number of observations."""
    import json

    from ..project import (
        CAMERA_DTYPE,
        OBSERVATION_DTYPE,
        POINT_DTYPE,
        STATION_DTYPE,
        append_history,
        write_project,
    )

    n_cam, n_pt = len(eo), len(pts)
    # observations grouped by point (a stable sort keeps the file's order within a point)
    order = np.argsort(obs_point, kind="stable")
    oc, op, xy = obs_camera[order], obs_point[order], obs_xy[order]
    if cameras is None:
        # a camera a photo, its format the square that holds its observations
        half = np.zeros(n_cam)
        np.maximum.at(half, oc, np.abs(xy).max(axis=1))
        full = 2.0 * np.ceil(np.maximum(half, 1.0))
        cameras = (station_ids, rows, np.column_stack([full, full]), np.arange(n_cam))
    cam_ids, cam_rows, formats, st_cam = cameras
    camera = np.zeros(len(cam_ids), CAMERA_DTYPE)
    camera["id"] = cam_ids
    for k, name in enumerate(("focal_length", "x0", "y0", "k1", "k2", "k3", "p1", "p2")):
        camera[name] = cam_rows[:, k]
    camera["format_x"], camera["format_y"] = formats[:, 0], formats[:, 1]
    camera["sigma_image"] = sigma_image
    station = np.zeros(n_cam, STATION_DTYPE)
    station["id"] = station_ids
    station["camera"] = st_cam
    station["strip"] = -1
    station["eo"] = eo
    counts = np.bincount(op, minlength=n_pt)
    point = np.zeros(n_pt, POINT_DTYPE)
    point["id"] = np.arange(n_pt) if point_ids is None else point_ids
    point["xyz"] = pts
    point["n_obs"] = counts
    point["obs_start"] = np.concatenate([[0], np.cumsum(counts)[:-1]])
    smin = np.full(n_pt, np.iinfo(np.int64).max)
    smax = np.full(n_pt, -1)
    np.minimum.at(smin, op, oc)
    np.maximum.at(smax, op, oc)
    point["station_min"] = np.where(counts > 0, smin, 0)
    point["station_max"] = np.where(counts > 0, smax, 0)
    obs = np.zeros(len(oc), OBSERVATION_DTYPE)
    obs["point"], obs["station"] = op, oc
    obs["x"], obs["y"] = xy[:, 0], xy[:, 1]
    attrs = {"creator": json.dumps(creator), "image_unit": "px", "datum": "free",
             "points_behind": "allowed", "station_intrinsics": intrinsics,
             "history": append_history("[]", creator)}
    write_project(out, camera, station, point, obs, attrs=attrs, extra=extra)
    return len(obs)


def export_bal(project_path, out_path, adjusted=True):
    """Write a project (its adjusted values, or the inputs) as a BAL problem. Every photo is
    a BAL camera with its camera's f, k1, k2 (principal point, k3, p1 and p2 must be 0);
    cameras and points in the order of their ids, observations by point and camera; excluded
    ones left out."""
    b = snavely_block(project_path, adjusted, "BAL")
    write_bal(out_path, sapgo_to_bal(b["eo"], b["rows"]), b["xyz"], b["obs_camera"],
              b["obs_point"], b["obs_xy"])
    return {"cameras": len(b["eo"]), "points": len(b["xyz"]),
            "observations": len(b["obs_camera"])}


def snavely_block(project_path, adjusted, fmt, any_camera=False):
    """A project's active photos, points and observations for a Snavely-model file (BAL,
    Bundler; ``fmt`` names it in errors): every photo with its camera's f, k1, k2 (principal
    point, k3, p1 and p2 must be 0); photos and points in the order of their ids (an
    import's ids are the file's indices, so a file comes back in its own order),
    observations by point and photo. A dict of ``eo``, ``rows``, ``station_ids``, ``xyz``,
    ``point_ids``, ``obs_camera``, ``obs_point`` (indices in these), ``obs_xy`` and
    ``obs_records`` (the observations' records), ``camera_rows`` (every camera's) and
    ``camera_of_station``. ``any_camera``: no check of the cameras (a format that holds
    principal points and decentring distortion)."""
    from ..geometry import beyond_brown, camera_array
    from ..project import STATUS_ACTIVE, Project

    with Project(project_path) as p:
        st, pt, ob = p.read("stations"), p.read("points"), p.read("observations")
        rows = camera_array(p.cameras())
        eo, xyz = st["eo"], pt["xyz"]
        if adjusted:
            eo = eo + p.solution("station_corr")
            xyz = xyz + p.solution("point_corr")
            rows = rows + p.solution("camera_corr")
    cam_rows = rows
    rows = rows[st["camera"]]
    odd = beyond_brown(rows)
    if odd.any():
        raise DataError(f"{project_path}: photo id {int(st['id'][np.argmax(odd)])}: its "
                        f"camera has affinity or shear (b1, b2), the backward distortion "
                        f"model or an additional-parameter set, which {fmt} cannot hold")
    extra = np.abs(rows[:, [1, 2, 5, 6, 7]]).max(axis=1) > 0
    if extra.any() and not any_camera:
        raise DataError(f"{project_path}: photo id {int(st['id'][np.argmax(extra)])}: its "
                        f"camera has a principal point, k3 or decentring distortion, which "
                        f"{fmt} cannot hold")
    live_st = st["status"] == STATUS_ACTIVE
    live_pt = pt["status"] == STATUS_ACTIVE
    keep = (ob["status"] == STATUS_ACTIVE) & live_pt[ob["point"]] & live_st[ob["station"]]
    st_rec = np.flatnonzero(live_st)[np.argsort(st["id"][live_st], kind="stable")]
    pt_rec = np.flatnonzero(live_pt)[np.argsort(pt["id"][live_pt], kind="stable")]
    new_st = np.full(len(st), -1)
    new_st[st_rec] = np.arange(len(st_rec))
    new_pt = np.full(len(pt), -1)
    new_pt[pt_rec] = np.arange(len(pt_rec))
    o = np.flatnonzero(keep)
    o = o[np.lexsort((new_st[ob["station"][o]], new_pt[ob["point"][o]]))]
    return {"eo": eo[st_rec], "rows": rows[st_rec], "station_ids": st["id"][st_rec],
            "xyz": xyz[pt_rec], "point_ids": pt["id"][pt_rec],
            "obs_camera": new_st[ob["station"][o]], "obs_point": new_pt[ob["point"][o]],
            "obs_xy": np.column_stack([ob["x"][o], ob["y"][o]]), "obs_records": o,
            "camera_rows": cam_rows, "camera_of_station": st["camera"][st_rec]}
