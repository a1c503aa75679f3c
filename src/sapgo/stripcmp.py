"""Strip-to-strip comparison of common points (seeds/002, Table 8).

SAPGO judged the Apollo 15 blocks, which had no ground control, by how well the strips
(revolutions) fit together: every pass point is derived again from the adjusted exterior
orientation of *each* strip on its own, by intersecting only that strip's rays, and the
coordinates a point gets from two strips are compared. Per pair of strips this gives the
standard error of the differences per coordinate,

    sigma_c = sqrt(sum_i (X_c(i, a) - X_c(i, b))^2 / n)        c = X, Y, Z

over the ``n`` points derived in both strips, and over all pairs the weighted average
``sigma_A = sum n_i sigma_i / sum n_i`` of the paper. For a block in a CRS the differences are
taken along east, north and up at the point (the paper's latitude, longitude and height);
in a local frame along its X, Y, Z.

A point is derived in a strip when it has active rays from at least two photos of that strip
whose intersection is well conditioned (``geometry.intersect_points``, distortion removed
from the rays). Photos with an unknown strip (``strip`` < 0) and excluded stations or points
take no part. The comparison streams over the points in chunks; it holds one accumulator
per pair of strips that share a point.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from . import paging

from .frames import LOCAL
from .geometry import _add_ray, _solve_sym3


@njit(cache=True)
def _strip_points(pt_start, pt_nobs, pt_active, obs_station, obs_xy, obs_active, eo,
                  st_strip, cam_of_station, cams, out_pair, out_diff, out_pos):
    """Differences of the coordinates a point gets from each pair of strips, for a chunk of
    points. Fills ``out_pair`` (m x 2: strip a < strip b), ``out_diff`` (m x 3) and
    ``out_pos`` (m x 3: the point from strip a) and returns ``m``; the outputs must hold
    ``sum_j C(k_j, 2)`` rows (``k_j`` strips of point ``j``)."""
    m = 0
    a = np.empty((3, 3))
    r = np.empty(3)
    x = np.empty(3)
    max_rays = 1
    for j in range(pt_start.shape[0]):
        max_rays = max(max_rays, pt_nobs[j])
    strips = np.empty(max_rays, np.int64)
    xyz = np.empty((max_rays, 3))
    for j in range(pt_start.shape[0]):
        if pt_active[j] != 0:
            continue
        k = 0  # strips of this point with an intersection
        o0, o1 = pt_start[j], pt_start[j] + pt_nobs[j]
        for i in range(o0, o1):
            if not obs_active[i]:
                continue
            s = st_strip[obs_station[i]]
            if s < 0:
                continue
            seen = False
            for q in range(k):
                if strips[q] == s:
                    seen = True
            # first ray of a strip not yet tried: intersect all rays of that strip
            tried = False
            for i2 in range(o0, i):
                if obs_active[i2] and st_strip[obs_station[i2]] == s:
                    tried = True
                    break
            if seen or tried:
                continue
            a[:, :] = 0.0
            r[:] = 0.0
            photos = 0
            last = -1
            good = True
            for i2 in range(i, o1):
                st = obs_station[i2]
                if obs_active[i2] and st_strip[st] == s:
                    good &= _add_ray(eo[st], obs_xy[i2, 0], obs_xy[i2, 1],
                                     cams[cam_of_station[st]], a, r)
                    if st != last:
                        photos += 1
                        last = st
            if good and photos >= 2 and _solve_sym3(a, r, x):
                strips[k] = s
                for c in range(3):
                    xyz[k, c] = x[c]
                k += 1
        for p in range(k):
            for q in range(p + 1, k):
                lo, hi = (p, q) if strips[p] < strips[q] else (q, p)
                out_pair[m, 0] = strips[lo]
                out_pair[m, 1] = strips[hi]
                for c in range(3):
                    out_diff[m, c] = xyz[lo, c] - xyz[hi, c]
                    out_pos[m, c] = xyz[lo, c]
                m += 1
    return m


class StripComparison:
    """Accumulates :func:`_strip_points` over chunks; :meth:`result` gives the report."""

    def __init__(self, strip_of_station, station_active, frame=None):
        """``strip_of_station``: an array, or anything sliced by rows (a project's field
        through :meth:`sapgo.project.Project.read_field`, a chunk at a time)."""
        self.strip = paging.empty(len(station_active), np.int64)
        for a, b in paging.rows(len(self.strip)):
            self.strip[a:b] = np.where(station_active[a:b], strip_of_station[a:b], -1)
        self.acc = {}  # (strip a, strip b) -> [n, sum dx^2, sum dy^2, sum dz^2]
        #: differences along east, north, up at the point for a frame with a CRS (a lunar
        #: block's frame axes are far from them), else along the frame's X, Y, Z
        self.frame = frame if frame is not None and frame.kind != LOCAL else None
        self.axes = ("east", "north", "up") if self.frame is not None else ("X", "Y", "Z")

    def add(self, chunk, eo, cam_of_station, cams):
        """Add the points of a :class:`sapgo.normals.PointChunk` (adjusted orientation
        ``eo``)."""
        st_strip = self.strip[chunk.obs_station] if len(chunk.obs_station) else \
            np.zeros(0, np.int64)
        # an upper bound of the pairs: C(k, 2) with k <= rays of the point
        k = np.minimum(chunk.nobs, _distinct_upper(chunk, st_strip))
        rows = int((k * (k - 1) // 2).sum())
        if rows == 0:
            return
        pair = np.empty((rows, 2), np.int64)
        diff = np.empty((rows, 3))
        pos = np.empty((rows, 3))
        m = _strip_points(chunk.pt_start, chunk.nobs, chunk.active, chunk.obs_station,
                          chunk.obs_xy, chunk.obs_active, eo, self.strip, cam_of_station, cams,
                          pair, diff, pos)
        if not m:
            return
        if self.frame is not None:  # frame axes -> body-fixed -> east, north, up at the point
            r, _ = self.frame._frame_rotation()
            rot = self.frame._station_rotations(pos[:m]) @ r.T
            diff[:m] = np.einsum("nij,nj->ni", rot, diff[:m])
        # the pairs of strips as one key each (np.unique by rows sorts them as records,
        # ten times slower than a sort of integers)
        base = int(pair[:m].max()) + 1
        code, inv = np.unique(pair[:m, 0] * base + pair[:m, 1], return_inverse=True)
        key = np.column_stack([code // base, code % base])
        n = np.bincount(inv.ravel(), minlength=len(key))
        d2 = diff[:m] ** 2   # (bincount adds in the order np.add.at does, ten times faster)
        sq = np.column_stack([np.bincount(inv.ravel(), weights=d2[:, c], minlength=len(key))
                              for c in range(3)])
        for (sa, sb), nn, s in zip(key.tolist(), n.tolist(), sq):
            acc = self.acc.setdefault((sa, sb), [0, 0.0, 0.0, 0.0])
            acc[0] += nn
            for c in range(3):
                acc[1 + c] += float(s[c])

    def merge(self, other):
        """Add ``other``'s pairs of strips."""
        for key, (n, *ss) in other.acc.items():
            acc = self.acc.setdefault(key, [0, 0.0, 0.0, 0.0])
            acc[0] += n
            for c in range(3):
                acc[1 + c] += ss[c]

    def result(self):
        """``{"axes", "pairs": [{"strips": [a, b], "n", "sigma_m": [..]}], "weighted_average":
        {"n", "sigma_m"}}`` (strip numbers as in ``/stations.strip``); None without pairs."""
        if not self.acc:
            return None
        pairs = []
        total = 0
        wsum = np.zeros(3)
        for (sa, sb), (n, *ss) in sorted(self.acc.items()):
            sigma = np.sqrt(np.array(ss) / n)
            pairs.append({"strips": [sa, sb], "n": n, "sigma_m": sigma.tolist()})
            total += n
            wsum += n * sigma
        return {"axes": list(self.axes), "pairs": pairs,
                "weighted_average": {"n": total, "sigma_m": (wsum / total).tolist()}}


def _distinct_upper(chunk, st_strip):
    """Per point: the number of distinct strips among its rays (an upper bound of the strips
    it is derived in)."""
    n = len(chunk.nobs)
    if not len(st_strip):
        return np.zeros(n, np.int64)
    point = np.repeat(np.arange(n), chunk.nobs)
    ok = st_strip >= 0
    if not ok.any():
        return np.zeros(n, np.int64)
    base = int(st_strip.max()) + 1   # (point, strip) as one key: a sort of integers
    pairs = np.unique(point[ok] * base + st_strip[ok])
    return np.bincount(pairs // base, minlength=n)


def format_strip_comparison(sc):
    """Text lines of the report (Table 8's layout)."""
    if sc is None:
        return []
    ax = sc["axes"]
    lines = ["  strip comparison: common points derived from each strip's adjusted orientation "
             "(seeds/002 Table 8)",
             "    strips compared   " + "".join(f"{'s' + a[0].upper() + ' [m]':>10}" for a in ax)
             + "    points"]
    for p in sc["pairs"]:
        a, b = p["strips"]
        lines.append(f"    {a:>6} vs. {b:<6}  " + "".join(f"{v:10.3f}" for v in p["sigma_m"])
                     + f"{p['n']:10d}")
    w = sc["weighted_average"]
    lines.append("    weighted average  " + "".join(f"{v:10.3f}" for v in w["sigma_m"])
                 + f"{w['n']:10d}")
    return lines
