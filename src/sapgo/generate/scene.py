"""General generated blocks: any stations and cameras over a terrain (SAPGO-MFL presets).

A :class:`Scene` gives the true exposure stations (orientation, camera, strip), the cameras
and the terrain. :func:`write_scene` puts pass points on a square grid over the ground the
photos cover, with the grid spacing chosen (by bisection) so that the number of points seen on
at least two photos reaches the scene's target, then drops the surplus at random; every image
point inside a photo's format (1 mm margin) is measured, with Gaussian noise of the camera's
``sigma_image``. Control classes (kind, number, sigmas, where) are drawn from those points and
perturbed by their sigmas; approximate stations are the true ones perturbed, approximate
points are intersected from them. Everything is in core: the presets are small.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from numba import njit

from ..geometry import camera_array, intersect_points, project
from ..project import (
    KIND_PASS,
    OBSERVATION_DTYPE,
    POINT_DTYPE,
    STATION_DTYPE,
    TRUTH_POINT_DTYPE,
    TRUTH_STATION_DTYPE,
)

ARCSEC = math.pi / (180 * 3600)


@dataclasses.dataclass
class ControlClass:
    """``n`` control points of ``kind`` with standard errors ``sigma`` (X, Y, Z; m), taken
    ``where``: ``"scattered"`` (at random), ``"north"``, ``"east"`` (along that edge of the
    block)."""

    n: int
    kind: int
    sigma: tuple
    where: str = "scattered"


@dataclasses.dataclass
class Scene:
    cameras: np.ndarray            # CAMERA_DTYPE records
    eo: np.ndarray                 # (n, 6) true orientation
    camera: np.ndarray             # (n,) camera record of each station
    strip: np.ndarray              # (n,) strip (flight line) number
    terrain: object                # callable (x, y) -> z
    n_points: int                  # pass points seen on >= 2 photos
    control: list = dataclasses.field(default_factory=list)
    position_perturbation: float = 10.0   # m
    angle_perturbation: float = 60.0      # arc seconds
    seed: int = 1
    #: A lunar block: the stations are Moon-fixed (selenocentric), the points lie on the
    #: sphere of this radius plus ``terrain(R lon, R lat)``, the grid is in latitude and
    #: longitude, and ``priors`` (station priors, PRIOR_DTYPE) give the approximations.
    sphere_radius: float | None = None
    priors: np.ndarray | None = None
    #: root attributes of the project (frame, crs)
    attrs: dict = dataclasses.field(default_factory=dict)


@njit(cache=True)
def _visible(xyz, eo, cams, cam_of, half_x, half_y, lo, hi, order, out_n):
    """Number of photos each point is inside the format of (stations prefiltered by the
    points' x: ``order`` sorts the stations by ground x, ``lo``/``hi`` the range per point)."""
    for j in range(xyz.shape[0]):
        k = 0
        for q in range(lo[j], hi[j]):
            s = order[q]
            c = cam_of[s]
            x, y = project(eo[s], xyz[j], cams[c])
            if abs(x - cams[c, 1]) < half_x[c] and abs(y - cams[c, 2]) < half_y[c]:
                k += 1
        out_n[j] = k


@njit(cache=True)
def _rays(xyz, eo, cams, cam_of, half_x, half_y, lo, hi, order, out_st, out_xy):
    m = 0
    for j in range(xyz.shape[0]):
        start = m
        for q in range(lo[j], hi[j]):
            s = order[q]
            c = cam_of[s]
            x, y = project(eo[s], xyz[j], cams[c])
            if abs(x - cams[c, 1]) < half_x[c] and abs(y - cams[c, 2]) < half_y[c]:
                out_st[m] = s
                out_xy[m, 0] = x
                out_xy[m, 1] = y
                m += 1
        # stations in increasing order within a point
        for a in range(start + 1, m):
            b = a
            while b > start and out_st[b - 1] > out_st[b]:
                out_st[b - 1], out_st[b] = out_st[b], out_st[b - 1]
                t0, t1 = out_xy[b - 1, 0], out_xy[b - 1, 1]
                out_xy[b - 1, 0], out_xy[b - 1, 1] = out_xy[b, 0], out_xy[b, 1]
                out_xy[b, 0], out_xy[b, 1] = t0, t1
                b -= 1
    return m


class _Visibility:
    def __init__(self, scene):
        self.eo = np.ascontiguousarray(scene.eo)
        self.cams = camera_array(scene.cameras)
        self.cam_of = np.ascontiguousarray(scene.camera, dtype=np.int64)
        self.half_x = scene.cameras["format_x"] / 2 - 1.0
        self.half_y = scene.cameras["format_y"] / 2 - 1.0
        f = scene.cameras["focal_length"][self.cam_of]
        fmt = np.maximum(scene.cameras["format_x"], scene.cameras["format_y"])[self.cam_of]
        self.sphere = scene.sphere_radius
        if self.sphere:
            height = np.linalg.norm(self.eo[:, 3:], axis=1) - self.sphere
            lat = np.arcsin(self.eo[:, 5] / np.linalg.norm(self.eo[:, 3:], axis=1))
            # ground half diagonal with tilt, as an angle of longitude
            self.reach = 0.9 * fmt * height / f / self.sphere / np.cos(np.abs(lat).max() + 0.2)
            key = self.key(self.eo[:, 3:])
        else:
            height = scene.eo[:, 5] - np.median(scene.terrain(scene.eo[:, 3], scene.eo[:, 4]))
            self.reach = 0.9 * fmt * height / f      # ground half diagonal with tilt: generous
            key = self.eo[:, 3]
        self.order = np.argsort(key, kind="stable")
        self.sx = key[self.order]
        self.r = float(self.reach.max())

    def key(self, xyz):
        """The sort key of the prefilter: x, or the longitude on a sphere."""
        return np.arctan2(xyz[:, 1], xyz[:, 0]) if self.sphere else xyz[:, 0]

    def ranges(self, xyz):
        k = self.key(xyz)
        lo = np.searchsorted(self.sx, k - self.r).astype(np.int64)
        hi = np.searchsorted(self.sx, k + self.r, side="right").astype(np.int64)
        return lo, hi

    def count(self, xyz):
        lo, hi = self.ranges(xyz)
        out = np.zeros(len(xyz), np.int64)
        _visible(xyz, self.eo, self.cams, self.cam_of, self.half_x, self.half_y, lo, hi,
                 self.order, out)
        return out

    def rays(self, xyz, n_rays):
        lo, hi = self.ranges(xyz)
        total = int(n_rays.sum())
        st = np.empty(total, np.int64)
        xy = np.empty((total, 2))
        m = _rays(xyz, self.eo, self.cams, self.cam_of, self.half_x, self.half_y, lo, hi,
                  self.order, st, xy)
        assert m == total
        return st, xy


def _grid(scene, spacing, bounds):
    x0, x1, y0, y1 = bounds
    if scene.sphere_radius:  # latitude rows, longitude steps of equal arc length
        R = scene.sphere_radius
        pts = []
        for lat in np.arange(y0, y1 + 1e-12, spacing / R):
            lon = np.arange(x0, x1 + 1e-12, spacing / (R * max(math.cos(lat), 1e-3)))
            h = scene.terrain(R * lon, np.full(len(lon), R * lat))
            r = R + h
            pts.append(np.column_stack([r * math.cos(lat) * np.cos(lon),
                                        r * math.cos(lat) * np.sin(lon),
                                        r * math.sin(lat) * np.ones(len(lon))]))
        return np.concatenate(pts) if pts else np.zeros((0, 3))
    xs = np.arange(x0, x1 + 1e-9, spacing)
    ys = np.arange(y0, y1 + 1e-9, spacing)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    gx, gy = gx.ravel(), gy.ravel()
    return np.column_stack([gx, gy, scene.terrain(gx, gy)])


def pass_points(scene, vis):
    """True coordinates of the pass points: a grid with ``scene.n_points`` points seen on two
    photos or more (bisection on the spacing, then the surplus dropped at random)."""
    e = scene.eo
    if scene.sphere_radius:  # bounds in longitude, latitude (radians); area in m^2
        lon = np.arctan2(e[:, 4], e[:, 3])
        lat = np.arcsin(e[:, 5] / np.linalg.norm(e[:, 3:], axis=1))
        bounds = (lon.min() - vis.r, lon.max() + vis.r, lat.min() - vis.r, lat.max() + vis.r)
        area = (bounds[1] - bounds[0]) * (bounds[3] - bounds[2]) * scene.sphere_radius ** 2
    else:
        bounds = (e[:, 3].min() - vis.r, e[:, 3].max() + vis.r,
                  e[:, 4].min() - vis.r, e[:, 4].max() + vis.r)
        area = (bounds[1] - bounds[0]) * (bounds[3] - bounds[2])
    lo, hi = math.sqrt(area / (50 * scene.n_points)), math.sqrt(area / 2)

    def tied(spacing):
        pts = _grid(scene, spacing, bounds)
        return pts[vis.count(pts) >= 2]

    for _ in range(60):  # largest spacing that still gives enough points
        mid = math.sqrt(lo * hi)
        if len(tied(mid)) >= scene.n_points:
            lo = mid
        else:
            hi = mid
        if hi / lo < 1.0001:
            break
    pts = tied(lo)
    if len(pts) < scene.n_points:
        raise ValueError(f"the scene's photos see only {len(pts)} points on two photos or more "
                         f"at any grid spacing, {scene.n_points} wanted")
    rng = np.random.default_rng([scene.seed, 31])
    keep = np.sort(rng.choice(len(pts), scene.n_points, replace=False))
    return pts[keep]


def _choose_control(scene, xyz, rng):
    """Kinds, control values and sigmas of the points (pass points elsewhere)."""
    n = len(xyz)
    kind = np.full(n, KIND_PASS, np.int8)
    ctrl = np.zeros((n, 3))
    csig = np.zeros((n, 3))
    free = np.ones(n, bool)
    for cc in scene.control:
        idx = np.flatnonzero(free)
        if cc.where in ("north", "east"):
            axis = 1 if cc.where == "north" else 0
            edge = idx[np.argsort(-xyz[idx, axis], kind="stable")][:4 * cc.n]
            other = 1 - axis
            edge = edge[np.argsort(xyz[edge, other])]
            pick = edge[np.round(np.linspace(0, len(edge) - 1, cc.n)).astype(int)]
        else:
            pick = rng.choice(idx, cc.n, replace=False)
        sig = np.asarray(cc.sigma, float)
        known = sig > 0
        kind[pick] = cc.kind
        ctrl[pick] = xyz[pick] + np.where(known, rng.normal(0, 1, (len(pick), 3)) * sig, 0.0)
        ctrl[pick] = np.where(known, ctrl[pick], 0.0)
        csig[pick] = sig
        free[pick] = False
    return kind, ctrl, csig


def write_scene(scene, writer, progress=None):
    """Generate the scene's block into ``writer`` (a ProjectWriter with truth); returns the
    counts."""
    rng = np.random.default_rng([scene.seed, 17])
    vis = _Visibility(scene)
    xyz = pass_points(scene, vis)
    n_rays = vis.count(xyz)
    st, xy = vis.rays(xyz, n_rays)
    cams = camera_array(scene.cameras)
    sig = scene.cameras["sigma_image"][scene.camera[st]]
    xy = xy + rng.normal(0, 1, xy.shape) * sig[:, None]
    n_st = len(scene.eo)
    # approximate stations: the priors' values (orbit data), else the truth perturbed
    if scene.priors is not None:
        approx = np.array(scene.eo)
        approx[scene.priors["station"]] = scene.priors["value"]
    else:
        approx = scene.eo.copy()
        approx[:, :3] += rng.normal(0, scene.angle_perturbation * ARCSEC, (n_st, 3))
        approx[:, 3:] += rng.normal(0, scene.position_perturbation, (n_st, 3))
    kind, ctrl, csig = _choose_control(scene, xyz, rng)
    starts = np.zeros(len(xyz), np.int64)
    np.cumsum(n_rays[:-1], out=starts[1:])
    approx_xyz = np.empty_like(xyz)
    ok = np.zeros(len(xyz), np.bool_)
    intersect_points(starts, n_rays, st, np.ascontiguousarray(xy), approx,
                     np.ascontiguousarray(scene.camera, dtype=np.int64), cams, approx_xyz, ok)
    approx_xyz = np.where(ok[:, None], approx_xyz, xyz + rng.normal(0, 5.0, xyz.shape))

    writer.append("cameras", scene.cameras)
    stations = np.zeros(n_st, STATION_DTYPE)
    stations["id"] = np.arange(1, n_st + 1)
    stations["camera"] = scene.camera
    stations["strip"] = scene.strip
    stations["eo"] = approx
    writer.append("stations", stations)
    if scene.priors is not None:
        writer.append("station_priors", scene.priors)
    if scene.attrs:
        writer.set_attrs(**scene.attrs)
    truth_st = np.zeros(n_st, TRUTH_STATION_DTYPE)
    truth_st["id"] = stations["id"]
    truth_st["eo"] = scene.eo
    writer.append("truth/stations", truth_st)
    points = np.zeros(len(xyz), POINT_DTYPE)
    points["id"] = np.arange(1, len(xyz) + 1)
    points["kind"] = kind
    points["xyz"] = approx_xyz
    points["control"] = ctrl
    points["control_sigma"] = csig
    points["obs_start"] = starts
    points["n_obs"] = n_rays
    points["station_min"] = -1
    points["station_max"] = -1
    writer.append("points", points)
    truth_pt = np.zeros(len(xyz), TRUTH_POINT_DTYPE)
    truth_pt["id"] = points["id"]
    truth_pt["xyz"] = xyz
    writer.append("truth/points", truth_pt)
    obs = np.zeros(len(st), OBSERVATION_DTYPE)
    obs["point"] = np.repeat(np.arange(len(xyz)), n_rays)
    obs["station"] = st
    obs["x"] = xy[:, 0]
    obs["y"] = xy[:, 1]
    obs["sigma"] = sig
    writer.append("observations", obs)
    if progress is not None:
        progress(1)
    return {"photos": n_st, "points": len(xyz), "observations": len(obs),
            "control": int((kind != KIND_PASS).sum()), "cameras": len(scene.cameras),
            "strips": len(np.unique(scene.strip))}
