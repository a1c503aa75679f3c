"""Starting values (``sapgo init``) of a block's photos and points from its control, for
near-vertical (aerial) blocks: the approximations the project holds are not used.

1. **The photos as vertical photos, the whole block at once.** Each photo gets a 2-D
   similarity ``X + i Y = t + q (u + i v)`` from its image points (freed of distortion,
   divided by the focal length) to their ground X, Y; each point its X, Y, the control's
   given (full and horizontal control, and check points). The observation equations are
   linear in the similarities and the points: one sparse least-squares solution over the
   block (a planimetric block adjustment of independent photos), which needs no photo to
   see a control point and has no propagation error to speak of. ``q = H e^{i kappa}`` gives
   kappa and the height ``H`` above the known heights the photo sees (full and vertical
   control; else the block's), ``t`` the centre's X, Y; omega = phi = 0.
2. **The points intersected** from the photos (the least-squares point nearest to the rays,
   in front of the photos and seen under 1 degree at least).
3. **Sweeps** (3): each photo resected from its points (Gauss-Newton on the collinearity
   equations, all six parameters), then the points intersected again.

Photos and points not connected to two known X, Y keep their values and are counted. The
result is a start for ``sapgo adjust``, not a solution (tilts of a few degrees are left:
the adjustment takes them out).

Convergent (close-range) photography (``method`` "resection", chosen by "auto" when a photo
sees six known points that span space): each photo that sees six or more points of known
or intersected coordinates, not in one plane, is resected directly (the DLT with the
camera's known focal length, its 3 x 3 part made a rotation, then Gauss-Newton), the points
its placed photos see are intersected, and so on through the block until nothing is
added; then the same sweeps. The project is rewritten atomically (a copy replaced), with an
``init`` entry in its history; a stored solution and a run's work directory are dropped
(their corrections refer to the old approximations). Memory: the block's records and a
sparse system of 4 unknowns a photo and 2 a point, in core.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from pathlib import Path

import numpy as np

from .lock import writes_project
from .errors import DataError

#: Points a photo needs for a resection in a sweep.
MIN_RESECTION = 4
#: Gauss-Newton iterations of a resection.
RESECTION_ITERATIONS = 15
#: The smallest angle (radians) between two rays of a point that is intersected.
MIN_ANGLE = np.radians(1.0)


@dataclasses.dataclass
class InitSummary:
    photos: int
    points: int
    photos_placed: int
    points_intersected: int
    #: ids of photos not placed (the first 20)
    photos_not_placed: list
    points_not_intersected: int
    sweeps: int
    #: "vertical" or "resection" (:data:`METHODS`)
    method: str = "vertical"


def _ideal(ob, st, cams):
    """Observations freed of distortion (from the principal point), nan where it fails."""
    from .geometry import undistort_points

    xy = np.column_stack([ob["x"], ob["y"]]).astype(np.float64)
    out = np.empty_like(xy)
    undistort_points(xy, st["camera"][ob["station"]].astype(np.int64), cams, out)
    return out


def _refine(eo, xyz, xy, cam):
    """Gauss-Newton on the collinearity equations of one photo: its six parameters from
    points ``xyz`` seen at ``xy`` (None if a point falls behind it)."""
    from .geometry import linearize, observed, turned

    eo = eo.copy()
    a, b = np.empty((2, 6)), np.empty((2, 3))
    for _ in range(RESECTION_ITERATIONS):
        rows, res = [], []
        for p, o in zip(xyz, xy):
            x, y, w = linearize(eo, p, cam, a, b)
            if not np.isfinite(x) or w >= 0:
                return None
            rows.append(a.copy())
            res.append(np.array(observed(o[0], o[1], cam)) - np.array([x, y]))
        j, r = np.vstack(rows), np.concatenate(res)
        step, *_ = np.linalg.lstsq(j, r, rcond=None)
        eo[:3] = turned(eo[:3], step[:3])[0]
        eo[3:] += step[3:]
        if np.abs(step).max() < 1e-10 * (1 + np.abs(eo[3:]).max()):
            break
    return eo if np.isfinite(eo).all() else None


def _planimetric(n_st, n_pt, o_st, o_pt, uv, known, ground):
    """The block's photos as vertical photos, all at once: per photo a 2-D similarity
    ``q = a + i b`` and ``t`` taking its image points (``uv``: divided by the focal length)
    to their ground X, Y (``X + i Y = t + q (u + i v)``), per point its X, Y, the known
    points' X, Y given: linear least squares over the whole block (a planimetric block
    adjustment of independent photos). Returns ``q``, ``t`` per photo and X, Y per point
    (nan where the photo or point is not connected to two known points)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import spsolve

    # the photos and points connected to the known points
    g = sp.coo_matrix((np.ones(len(o_st)), (o_st, n_st + o_pt)),
                      shape=(n_st + n_pt, n_st + n_pt))
    _, label = connected_components(g, directed=False)
    good_label = [lab for lab in np.unique(label[n_st:][known])
                  if (label[n_st:][known] == lab).sum() >= 2]
    photo_ok = np.isin(label[:n_st], good_label)
    point_ok = np.isin(label[n_st:], good_label)
    use = photo_ok[o_st] & point_ok[o_pt]
    o_st, o_pt, uv = o_st[use], o_pt[use], uv[use]
    # unknowns: 4 a photo (a, b, tx, ty), then 2 an unknown point (X, Y)
    col_pt = np.full(n_pt, -1)
    free = np.flatnonzero(point_ok & ~known)
    col_pt[free] = 4 * n_st + 2 * np.arange(len(free))
    n = 4 * n_st + 2 * len(free)
    m = len(o_st)
    u, v = uv[:, 0], uv[:, 1]
    r0, r1 = 2 * np.arange(m), 2 * np.arange(m) + 1
    rows = [r0, r0, r0, r1, r1, r1]
    cols = [4 * o_st, 4 * o_st + 1, 4 * o_st + 2, 4 * o_st, 4 * o_st + 1, 4 * o_st + 3]
    vals = [u, -v, np.ones(m), v, u, np.ones(m)]
    rhs = np.zeros(2 * m)
    unk = col_pt[o_pt] >= 0
    rows += [r0[unk], r1[unk]]
    cols += [col_pt[o_pt][unk], col_pt[o_pt][unk] + 1]
    vals += [-np.ones(unk.sum()), -np.ones(unk.sum())]
    rhs[r0[~unk]] = ground[o_pt[~unk], 0]
    rhs[r1[~unk]] = ground[o_pt[~unk], 1]
    a = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(2 * m, n))
    # (photos not connected: their unknowns held at 0 by a unit diagonal)
    idle = np.repeat(~photo_ok, 4)
    nrm = (a.T @ a).tocsc() + sp.diags(np.concatenate([idle, np.zeros(n - 4 * n_st)])
                                       .astype(float))
    x = spsolve(nrm, a.T @ rhs)
    q = x[0:4 * n_st:4] + 1j * x[1:4 * n_st:4]
    t = x[2:4 * n_st:4] + 1j * x[3:4 * n_st:4]
    q[~photo_ok] = np.nan
    xy = np.full((n_pt, 2), np.nan)
    xy[known] = ground[known, :2]
    xy[free, 0], xy[free, 1] = x[col_pt[free]], x[col_pt[free] + 1]
    return q, t, xy


#: ``sapgo init --method``: the vertical start of aerial blocks, resection and intersection
#: propagated through a convergent (close-range) block, or the one the control suits.
METHODS = ("auto", "vertical", "resection")
#: Points of known or intersected coordinates a photo needs for a direct (DLT) resection.
MIN_DLT = 6
#: The DLT's points must span space: the smallest of their spreads (standard deviations
#: along the principal axes) at least this fraction of the largest (else they are planar).
MIN_SPREAD = 0.05


def _dlt(xyz, ideal, f):
    """A photo's orientation ``(omega, phi, kappa, Xc, Yc, Zc)`` from six or more points
    ``xyz`` (not coplanar) and their ideal image coordinates (from the principal point):
    the direct linear transformation with Hartley's normalisation, its 3 x 3 part made the
    nearest matrix ``diag(1, 1, -1) M`` of a rotation ``M`` (sapgo's: ``x = -f u / w``),
    the centre from its last column. None when the points do not determine it."""
    from .frames import opk_of

    n = len(xyz)
    if n < MIN_DLT:
        return None
    c3, c2 = xyz.mean(axis=0), ideal.mean(axis=0)
    s3 = np.sqrt(3) / max(np.sqrt(((xyz - c3) ** 2).sum(axis=1)).mean(), 1e-300)
    s2 = np.sqrt(2) / max(np.sqrt(((ideal - c2) ** 2).sum(axis=1)).mean(), 1e-300)
    X = np.column_stack([(xyz - c3) * s3, np.ones(n)])
    u, v = ((ideal - c2) * s2).T
    a = np.zeros((2 * n, 12))
    a[0::2, 0:4], a[0::2, 8:12] = X, -u[:, None] * X
    a[1::2, 4:8], a[1::2, 8:12] = X, -v[:, None] * X
    _, sv, vt = np.linalg.svd(a)
    if sv[-2] <= 1e-9 * sv[0]:
        return None
    pn = vt[-1].reshape(3, 4)
    t2 = np.array([[s2, 0, -s2 * c2[0]], [0, s2, -s2 * c2[1]], [0, 0, 1.0]])
    t3 = np.eye(4)
    t3[:3, :3] *= s3
    t3[:3, 3] = -s3 * c3
    pm = np.linalg.solve(t2, pn) @ t3            # in ideal image coordinates
    pm = np.diag([1 / f, 1 / f, 1.0]) @ pm       # [x/f, y/f, 1] ~ pm [X, 1]
    A, b = pm[:, :3], pm[:, 3]
    if abs(np.linalg.det(A)) < 1e-300:
        return None
    centre = -np.linalg.solve(A, b)
    U, _, Vt = np.linalg.svd(A)
    B = U @ Vt
    if np.linalg.det(B) > 0:                     # diag(1, 1, -1) M has determinant -1
        B = -B
    m = np.diag([1.0, 1.0, -1.0]) @ B
    # (the determinant fixes the sign of P's scale: the points are in front, w < 0, unless
    # the data say otherwise)
    if not np.isfinite(m).all() or not np.isfinite(centre).all() \
            or np.median((xyz - centre) @ m[2]) >= 0:
        return None
    return np.concatenate([opk_of(m[None])[0], centre])


def _spread_ok(xyz):
    """Whether points span space (:data:`MIN_SPREAD`): no plane holds them all."""
    if len(xyz) < 4:
        return False
    sv = np.linalg.svd(xyz - xyz.mean(axis=0), compute_uv=False)
    return bool(sv[-1] >= MIN_SPREAD * sv[0])


@writes_project("init", "path")
def initialise(path, sweeps=3, method="auto"):
    """Starting values for the photos and points of the project ``path`` (the module's
    comment); returns an :class:`InitSummary`. ``method``: "vertical" (aerial blocks),
    "resection" (convergent blocks: :func:`_propagate`) or "auto" (resection when some photo
    sees :data:`MIN_DLT` known points that span space, else vertical)."""
    from .geometry import camera_array
    from .project import (
        KIND_CHECK,
        KIND_CONTROL,
        KIND_HORIZONTAL,
        KIND_VERTICAL,
        STATUS_ACTIVE,
        Project,
    )

    path = Path(path)
    with Project(path) as p:
        cams = camera_array(p.cameras())
        st, pt, ob = p.read("stations"), p.read("points"), p.read("observations")
        history = p.attr("history", "[]")
    n_st, n_pt = len(st), len(pt)
    cam_of = st["camera"].astype(np.int64)
    live = ((ob["status"] == STATUS_ACTIVE) & (pt["status"][ob["point"]] == STATUS_ACTIVE)
            & (st["status"][ob["station"]] == STATUS_ACTIVE))
    ideal = _ideal(ob, st, cams)
    live &= np.isfinite(ideal).all(axis=1)
    active = pt["status"] == STATUS_ACTIVE
    known_xy = np.isin(pt["kind"], (KIND_CONTROL, KIND_HORIZONTAL, KIND_CHECK)) & active
    known_z = np.isin(pt["kind"], (KIND_CONTROL, KIND_VERTICAL, KIND_CHECK)) & active
    known = known_xy & known_z
    if known_xy.sum() < 2 or not known_z.any():
        raise DataError(f"{path}: sapgo init places the photos from points of known "
                        f"coordinates: it needs 2 control or check points with X, Y and one "
                        f"with Z at least, found {int(known_xy.sum())} and "
                        f"{int(known_z.sum())}")
    o_st, o_pt = ob["station"].astype(np.int64), ob["point"].astype(np.int64)
    rows = np.flatnonzero(live)
    f = cams[cam_of[o_st[rows]], 0]
    ground = pt["control"].astype(np.float64)
    if method not in METHODS:
        raise DataError(f"init method {method!r}: choose {', '.join(METHODS)}")
    tried = None
    if method == "auto":
        for s_ in range(n_st):
            seen = np.unique(o_pt[rows[(o_st[rows] == s_) & known[o_pt[rows]]]])
            if len(seen) >= MIN_DLT and _spread_ok(ground[seen]):
                method = "resection"
                break
        else:
            method = "vertical"
        if method == "resection":   # kept if it places every photo (else the vertical start
            tried = _propagate(st, pt, ob, cams, cam_of, rows, ideal, known, ground, sweeps)
            if tried[0].photos_placed < int((st["status"] == STATUS_ACTIVE).sum()):
                method = "vertical"   # is tried too, and the one placing more kept)
    if method == "resection":
        r, eo, xyz = tried or _propagate(st, pt, ob, cams, cam_of, rows, ideal, known, ground,
                                         sweeps)
        _write(path, eo, xyz, history, {"command": "init", "method": "resection",
                                        "photos_placed": r.photos_placed,
                                        "points_intersected": r.points_intersected})
        return r
    q, t, pxy = _planimetric(n_st, n_pt, o_st[rows], o_pt[rows], ideal[rows] / f[:, None],
                             known_xy, ground)
    placed = np.isfinite(q)
    eo = st["eo"].copy()
    # heights: above the mean height of the known points each photo sees, else all's
    zk = np.zeros(n_st)
    nk = np.zeros(n_st)
    kr = rows[known_z[o_pt[rows]]]
    np.add.at(zk, o_st[kr], ground[o_pt[kr], 2])
    np.add.at(nk, o_st[kr], 1.0)
    z0 = np.where(nk > 0, zk / np.maximum(nk, 1), ground[known_z, 2].mean())
    eo[placed] = np.column_stack([np.zeros(placed.sum()), np.zeros(placed.sum()),
                                  np.angle(q[placed]), t[placed].real, t[placed].imag,
                                  z0[placed] + np.abs(q[placed])])
    xyz = pt["xyz"].copy()
    flat = np.isfinite(pxy[:, 0]) & ~known   # (the planimetric X, Y, the known mean height)
    xyz[flat] = np.column_stack([pxy[flat], np.full(flat.sum(), ground[known_z, 2].mean())])
    xyz[known] = ground[known]
    raw = np.column_stack([ob["x"], ob["y"]]).astype(np.float64)
    by_pt = rows[np.argsort(o_pt[rows], kind="stable")]
    by_st = rows[np.argsort(o_st[rows], kind="stable")]
    st_start = np.searchsorted(o_st[by_st], np.arange(n_st + 1))
    got_pt = known.copy()

    def intersect():
        _intersect_placed(by_pt, placed, known, o_st, o_pt, raw, eo, cam_of, cams, xyz,
                          got_pt)
        xyz[known_xy, :2] = ground[known_xy, :2]   # (partial control: its known part)
        xyz[known_z, 2] = ground[known_z, 2]

    intersect()
    # sweeps: each photo resected from its points, then the points intersected again
    for _ in range(sweeps):
        for s in np.flatnonzero(placed):
            mine = by_st[st_start[s]:st_start[s + 1]]
            mine = mine[got_pt[o_pt[mine]]]
            if len(mine) < MIN_RESECTION:
                continue
            new = _refine(eo[s], xyz[o_pt[mine]], raw[mine], cams[cam_of[s]])
            if new is not None:
                eo[s] = new
        intersect()
    lost = st["id"][~placed & (st["status"] == STATUS_ACTIVE)]
    if tried is not None and tried[0].photos_placed >= int(placed.sum()):
        r, eo_r, xyz_r = tried
        _write(path, eo_r, xyz_r, history, {"command": "init", "method": "resection",
                                            "photos_placed": r.photos_placed,
                                            "points_intersected": r.points_intersected})
        return r
    _write(path, eo, xyz, history, {"command": "init", "method": "vertical",
                                    "photos_placed": int(placed.sum()),
                                    "points_intersected": int((got_pt & ~known).sum())})
    return InitSummary(photos=n_st, points=n_pt, photos_placed=int(placed.sum()),
                       points_intersected=int((got_pt & ~known).sum()),
                       photos_not_placed=lost[:20].tolist(),
                       points_not_intersected=int((~got_pt & active).sum()), sweeps=sweeps)


def _propagate(st, pt, ob, cams, cam_of, rows, ideal, known, ground, sweeps):
    """Convergent blocks: photos resected directly (:func:`_dlt`, then Gauss-Newton) from
    the full control and the points already intersected that they see, points intersected
    from the photos already placed, in turns until no photo or point is added; then the
    sweeps of resection and intersection. Photos and points never reached keep their
    values. Returns ``(InitSummary, eo, xyz)``."""
    from .project import STATUS_ACTIVE

    n_st, n_pt = len(st), len(pt)
    o_st, o_pt = ob["station"].astype(np.int64), ob["point"].astype(np.int64)
    raw = np.column_stack([ob["x"], ob["y"]]).astype(np.float64)
    eo = st["eo"].copy()
    xyz = pt["xyz"].copy()
    xyz[known] = ground[known]
    got = known.copy()
    placed = np.zeros(n_st, bool)
    by_st = rows[np.argsort(o_st[rows], kind="stable")]
    by_pt = rows[np.argsort(o_pt[rows], kind="stable")]
    st_start = np.searchsorted(o_st[by_st], np.arange(n_st + 1))

    def resect(s, direct):
        mine = by_st[st_start[s]:st_start[s + 1]]
        mine = mine[got[o_pt[mine]]]
        if len(mine) < (MIN_DLT if direct else MIN_RESECTION):
            return False
        start = eo[s]
        if direct:
            if not _spread_ok(xyz[o_pt[mine]]):
                return False
            start = _dlt(xyz[o_pt[mine]], ideal[mine], cams[cam_of[s], 0])
            if start is None:
                return False
        new = _refine(start, xyz[o_pt[mine]], raw[mine], cams[cam_of[s]])
        if new is None:
            return False
        eo[s] = new
        return True

    def intersect():
        return _intersect_placed(by_pt, placed, known, o_st, o_pt, raw, eo, cam_of, cams, xyz,
                                 got)

    while True:
        added = 0
        for s in np.flatnonzero(~placed & (st["status"] == STATUS_ACTIVE)):
            if resect(s, True):
                placed[s] = True
                added += 1
        added += intersect()
        if not added:
            break
    for _ in range(sweeps):
        for s in np.flatnonzero(placed):
            resect(s, False)
        intersect()
    active = pt["status"] == STATUS_ACTIVE
    lost = st["id"][~placed & (st["status"] == STATUS_ACTIVE)]
    return InitSummary(photos=n_st, points=n_pt, photos_placed=int(placed.sum()),
                       points_intersected=int((got & ~known).sum()),
                       photos_not_placed=lost[:20].tolist(),
                       points_not_intersected=int((~got & active).sum()), sweeps=sweeps,
                       method="resection"), eo, xyz


def _intersect_placed(by_pt, placed, known, o_st, o_pt, raw, eo, cam_of, cams, xyz, got):
    """Intersect every point not known that two or more placed photos see (observations
    ``by_pt``, sorted by point) into ``xyz``, those in front of their photos and seen under
    :data:`MIN_ANGLE` marked in ``got``; returns how many were not marked before."""
    from .geometry import intersect_points

    sel = by_pt[placed[o_st[by_pt]] & ~known[o_pt[by_pt]]]
    pts, counts = np.unique(o_pt[sel], return_counts=True)
    if not len(pts):
        return 0
    starts = (np.cumsum(counts) - counts).astype(np.int64)
    out = np.zeros((len(pts), 3))
    ok = np.zeros(len(pts), bool)
    intersect_points(starts, counts.astype(np.int64), o_st[sel], raw[sel], eo, cam_of, cams,
                     out, ok)
    ok &= (counts >= 2) & _good_points(out, starts, counts, o_st[sel], eo)
    new = int((ok & ~got[pts]).sum())
    xyz[pts[ok]] = out[ok]
    got[pts[ok]] = True
    return new


def _good_points(xyz, starts, counts, stations, eo):
    """Whether each intersected point lies in front of all its photos and is seen under
    :data:`MIN_ANGLE` at least."""
    from .frames import rotation_matrices

    m = rotation_matrices(eo[stations, :3])
    owner = np.repeat(np.arange(len(starts)), counts)
    d = xyz[owner] - eo[stations, 3:6]
    w = np.einsum("nj,nj->n", m[:, 2, :], d)
    bad = np.zeros(len(starts), bool)
    np.logical_or.at(bad, owner, ~(w < 0))
    unit = d / np.maximum(np.linalg.norm(d, axis=1), 1e-300)[:, None]
    # the widest angle between a point's rays: against its first ray
    cosang = np.einsum("nj,nj->n", unit, unit[starts][owner])
    widest = np.ones(len(starts))
    np.minimum.at(widest, owner, cosang)
    return ~bad & (widest < np.cos(MIN_ANGLE))


def _write(path, eo, xyz, history, entry):
    """The new approximations into a copy of the project, then the copy over it; the
    solution and the work directory dropped."""
    import h5py

    from .project import append_history

    tmp = path.with_name(path.name + ".init.tmp")
    shutil.copyfile(path, tmp)
    try:
        with h5py.File(tmp, "r+") as f:
            st = f["stations"][...]
            st["eo"] = eo
            f["stations"][...] = st
            pts = f["points"][...]
            pts["xyz"] = xyz
            f["points"][...] = pts
            for name in ("solution", "solution.new"):
                if name in f:
                    del f[name]
            f.attrs["history"] = append_history(history, entry)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    shutil.rmtree(path.with_name(path.name + ".work"), ignore_errors=True)
