"""SAPGO-P: generated vertical blocks of parallel strips (seeds/002, Tables 2 and 3).

Geometry. Strips run along +X (alternate strips flown back, kappa = 180 deg); photo ``g`` of
strip ``s`` is exposed above ``X = g B``, ``Y = (s + 1/2) A`` with the photo base
``B = (1 - forelap) * format * scale`` and strip spacing ``A = (1 - sidelap) * format * scale``.
Pass points lie on a grid: the 9-point pattern puts on every photo the three columns at the
neighbours' nadirs (``X = (g-1) B, g B, (g+1) B``) and the three rows at the strip centre and
the middles of the two sidelaps; the 25-point pattern halves both spacings. Columns run from
the first to the last nadir of a strip, rows are shared between neighbouring strips, so a block
of S strips of G photos has ``(2S+1) G`` (9-point) or ``(4S+1)(2G-1)`` (25-point) points:
225, 833, 1100 and 1050 for the four presets of Table 2.

Image points that tilt and relief push off the format (1 mm margin) are not measured.

``points_per_photo`` (``sapgo generate --points-per-photo N``) replaces the pattern by the
tie points of modern image matching: a random texture of points scattered uniformly over the
pattern's extent, ``N`` on average in a photo's ground footprint, each measured on every photo
whose format holds it (points seen on fewer than two photos left out): with 60 % forelap and
20 % sidelap a point falls on about 3 photos, so a photo holds about ``N`` of them.
Perturbations as Table 3: station positions 5 m, angles 20", image coordinates 6 um, ground
control 1 mm. Approximate pass-point coordinates are intersected from the perturbed stations.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from .. import paging
from ..errors import ParameterError
from ..geometry import camera_array, intersect_points, project_observations
from ..project import (
    CAMERA_DTYPE,
    KIND_CHECK,
    KIND_CONTROL,
    OBSERVATION_DTYPE,
    POINT_DTYPE,
    STATION_DTYPE,
    TRUTH_POINT_DTYPE,
    TRUTH_STATION_DTYPE,
    camera_record,
)
from .terrain import Terrain

ARCSEC = math.pi / (180 * 3600)


@dataclasses.dataclass
class BlockSpec:
    """Parameters of a generated block; every field has the SAPGO-P default."""

    strips: int = 4
    photos_per_strip: int = 25
    pattern: int = 9  # points per photo: 9 (3x3) or 25 (5x5)
    #: tie points per photo from a random texture instead of the pattern: points scattered
    #: at random over the block (about this many in a photo's ground footprint), each
    #: measured on every photo whose format it falls in (None: the pattern)
    points_per_photo: int | None = None
    control_points: int = 16  # full (XYZ) control points; all other points are check points
    forelap: float = 0.6
    sidelap: float = 0.2
    focal_length: float = 152.0  # mm
    scale: float = 25000.0  # photo scale number
    format: float = 230.0  # mm, square
    sigma_image: float = 0.006  # mm: image-coordinate perturbation and its standard error
    station_position_perturbation: float = 5.0  # m
    station_angle_perturbation: float = 20.0  # arc seconds
    control_perturbation: float = 0.001  # m
    control_sigma: float | None = None  # m; default: the control perturbation
    terrain_relief: float = 100.0  # m, standard deviation of the terrain heights
    tilt: float = 0.5  # deg, standard deviation of the true photo tilts
    point_jitter: float = 0.04  # fraction of the grid spacing
    #: the camera's lens distortion (Brown: k1 mm^-2, k2 mm^-4, k3 mm^-6, p1, p2 mm^-1),
    #: applied to the simulated image coordinates and stored with the camera
    distortion: tuple = (0.0, 0.0, 0.0, 0.0, 0.0)
    #: planted blunders: this many image observations moved by 30 to 100 um (``blunder_size``,
    #: mm), listed in /truth/blunders
    blunders: int = 0
    blunder_size: tuple = (0.030, 0.100)
    seed: int = 1

    def check(self):
        """Raise ParameterError with a readable message when a parameter is out of range."""
        if self.strips < 1 or self.photos_per_strip < 2:
            raise ParameterError("a block needs at least 1 strip of 2 photos")
        if self.pattern not in (9, 25):
            raise ParameterError("pattern must be 9 or 25 points per photo")
        if self.points_per_photo is not None:
            if not isinstance(self.points_per_photo, (int, np.integer)):
                raise ParameterError(f"points per photo must be a whole number, not "
                                     f"{self.points_per_photo!r}")
            if self.pattern != 9:
                raise ParameterError("points per photo and the 25-point pattern exclude each "
                                     "other: give one of them")
            if not 4 <= self.points_per_photo <= MAX_POINTS_PER_PHOTO:
                raise ParameterError(f"points per photo must be between 4 and "
                                     f"{MAX_POINTS_PER_PHOTO}, not {self.points_per_photo}")
        if not 0.5 <= self.forelap < 0.9:
            raise ParameterError("forelap must be in [0.5, 0.9) so that points appear on 3 photos")
        if not 0.1 <= self.sidelap < 0.6:
            raise ParameterError(
                "sidelap must be in [0.1, 0.6) so that the pattern fits the format")
        if self.focal_length <= 0 or self.scale <= 0 or self.format <= 0:
            raise ParameterError("focal length, scale and format must be positive")
        self.distortion = tuple(float(v) for v in self.distortion)
        if len(self.distortion) != 5 or not all(np.isfinite(self.distortion)):
            raise ParameterError("distortion must be 5 finite numbers: k1 k2 k3 p1 p2")
        if self.sigma_image < 0 or self.station_position_perturbation < 0 or \
                self.station_angle_perturbation < 0 or self.control_perturbation < 0:
            raise ParameterError("perturbations must not be negative")
        n = self.n_points
        if not 0 <= self.control_points <= n:
            raise ParameterError(f"control_points must be between 0 and the {n} points")
        return self

    @property
    def sub(self):
        return 1 if self.pattern == 9 else 2

    @property
    def n_rows(self):
        return (2 * self.sub) * self.strips + 1

    @property
    def n_cols(self):
        return self.sub * (self.photos_per_strip - 1) + 1

    @property
    def n_points(self):
        """The points of the pattern; with ``points_per_photo``, the expected number
        scattered over the block (the points seen on fewer than two photos then go)."""
        if self.points_per_photo is not None:
            return int(round(self.texture_density * self.texture_area))
        return self.n_rows * self.n_cols

    @property
    def footprint(self):
        """A photo's ground footprint's side (m, at the mean terrain height)."""
        return self.format * self.scale / 1000.0

    @property
    def texture_density(self):
        """Points per square metre of the random texture (``points_per_photo``)."""
        return self.points_per_photo / self.footprint ** 2

    @property
    def texture_area(self):
        """The ground the random texture covers: the pattern's extent, from the first to
        the last nadir along the strips and over the strips' width across."""
        return (self.photos_per_strip - 1) * self.base * self.strips * self.strip_spacing

    @property
    def n_photos(self):
        return self.strips * self.photos_per_strip

    @property
    def base(self):
        return (1 - self.forelap) * self.format * self.scale / 1000.0

    @property
    def strip_spacing(self):
        return (1 - self.sidelap) * self.format * self.scale / 1000.0

    @property
    def flying_height(self):
        return self.focal_length * self.scale / 1000.0


def control_layout(n_rows, n_cols, n, spacing_row, spacing_col, rows_per_strip=2):
    """Grid (row, col) indices of ``n`` full control points spread over the block.

    As the classical rule for blocks of vertical photographs asks (vertical control in every
    sidelap, horizontal control around the perimeter), the points lie on every strip boundary
    row, evenly spaced along it; the first and last rows (the block's long edges) start and
    end at the corners, the rows between are staggered by half a spacing on alternate rows so
    that every strip has control at one of its edges twice as often. With fewer than two
    points per boundary row the points form the most nearly square lattice instead.
    """
    if n == 0:
        return np.zeros(0, int), np.zeros(0, int)
    rows = np.arange(0, n_rows, rows_per_strip)
    rr, cc = [], []
    if n >= 2 * len(rows) and n_cols >= 2:
        per = n / len(rows)
        for i, r in enumerate(rows):
            k = int(round((i + 1) * per) - round(i * per))
            if i % 2 == 0 or i == len(rows) - 1:
                cols = np.linspace(0, n_cols - 1, k)
            else:
                step = (n_cols - 1) / k
                cols = step / 2 + step * np.arange(k)
            cols = np.unique(np.round(cols).astype(int))
            rr.extend([r] * len(cols))
            cc.extend(cols.tolist())
    else:
        extent_r = max((n_rows - 1) * spacing_row, 1.0)
        extent_c = max((n_cols - 1) * spacing_col, 1.0)
        best = None
        for nr in range(1, min(n, n_rows) + 1):
            nc = math.ceil(n / nr)
            if nc > n_cols:
                continue
            dr = extent_r / max(nr - 1, 0.5)
            dc = extent_c / max(nc - 1, 0.5)
            cost = (nr * nc > n, abs(math.log(dr / dc)) + 0.05 * (nr * nc - n))
            if best is None or cost < best[0]:
                best = (cost, nr, nc)
        _, nr, nc = best
        lr = np.unique(np.round(np.linspace(0, n_rows - 1, nr)).astype(int))
        lc = np.unique(np.round(np.linspace(0, n_cols - 1, nc)).astype(int))
        g1, g2 = np.meshgrid(lr, lc, indexing="ij")
        rr, cc = g1.ravel().tolist(), g2.ravel().tolist()
        surplus = len(rr) - n
        if surplus > 0:  # drop surplus points evenly, corners kept
            corners = {(lr[0], lc[0]), (lr[0], lc[-1]), (lr[-1], lc[0]), (lr[-1], lc[-1])}
            pool = [i for i in range(len(rr)) if (rr[i], cc[i]) not in corners]
            drop = {pool[i] for i in np.round(np.linspace(0, len(pool) - 1, surplus)).astype(int)}
            rr = [v for i, v in enumerate(rr) if i not in drop]
            cc = [v for i, v in enumerate(cc) if i not in drop]
    rr, cc = np.asarray(rr, int), np.asarray(cc, int)
    if len(rr) < n:  # lines too short for distinct points: take further points evenly
        taken = set(zip(rr.tolist(), cc.tolist()))
        extra = []
        for k in np.round(np.linspace(0, n_rows * n_cols - 1, 2 * n + 1)).astype(np.int64):
            r, c = divmod(int(k), n_cols)
            while (r, c) in taken:  # the next free grid point
                k = (k + 1) % (n_rows * n_cols)
                r, c = divmod(int(k), n_cols)
            taken.add((r, c))
            extra.append((r, c))
            if len(rr) + len(extra) == n:
                break
        extra = np.array(extra, int).reshape(-1, 2)
        rr = np.concatenate([rr, extra[:, 0]])
        cc = np.concatenate([cc, extra[:, 1]])
    return rr, cc


#: Point columns generated per block: the random numbers of a column block depend only on the
#: seed and the block number, so the output does not depend on memory or chunking.
COLUMN_BLOCK = 512

#: The most tie points a photo of the random texture may ask for.
MAX_POINTS_PER_PHOTO = 5000


def texture_columns(spec):
    """Photo bases along the strips generated at once with a random texture: about 9 x
    :data:`COLUMN_BLOCK` points per strip and block (a fixed number: the output does not
    depend on memory)."""
    return max(1, COLUMN_BLOCK * 9 // spec.points_per_photo)


def _texture_slab(spec, x0, x1, rng, terrain, true_eo, cams):
    """The random texture's points with ``x0 <= X < x1`` (sorted by X) and their image
    observations (every photo whose format, less a 1 mm margin, holds the point; the
    points seen on fewer than two photos left out). Returns ``(true_xyz, o_st, o_pt, xy)``
    with the observations by point, then photo, and their image coordinates without
    noise."""
    S, G = spec.strips, spec.photos_per_strip
    B, A = spec.base, spec.strip_spacing
    n = int(rng.poisson(spec.texture_density * (x1 - x0) * S * A))
    px = np.sort(rng.uniform(x0, x1, n))
    py = rng.uniform(0.0, S * A, n)
    true_xyz = np.column_stack([px, py, terrain(px, py)])
    half = spec.footprint / 2
    # the photos that may see a point: the nearest ones along and across the strips
    reach_g, reach_s = int(math.ceil(half / B)) + 1, int(math.ceil(half / A)) + 1
    g0 = np.rint(px / B).astype(np.int64)
    s0 = np.floor(py / A).astype(np.int64)
    dg = np.arange(-reach_g, reach_g + 1)
    ds = np.arange(-reach_s, reach_s + 1)
    cand_g = (g0[:, None, None] + dg[None, :, None]) + 0 * ds[None, None, :]
    cand_s = (s0[:, None, None] + ds[None, None, :]) + 0 * dg[None, :, None]
    cand_p = np.broadcast_to(np.arange(n)[:, None, None], cand_g.shape)
    cand_g, cand_s, cand_p = cand_g.ravel(), cand_s.ravel(), cand_p.ravel()
    ok = (cand_g >= 0) & (cand_g < G) & (cand_s >= 0) & (cand_s < S)
    ok &= np.abs(px[cand_p] - cand_g * B) < 1.2 * half
    ok &= np.abs(py[cand_p] - (cand_s + 0.5) * A) < 1.2 * half
    o_st, o_pt = cand_s[ok] * G + cand_g[ok], cand_p[ok]
    order = np.lexsort((o_st, o_pt))
    o_st, o_pt = o_st[order], o_pt[order]
    xy = np.empty((len(o_pt), 2))
    project_observations(o_st, o_pt, true_eo, true_xyz, np.zeros(S * G, np.int64), cams, xy)
    inside = (np.abs(xy) < spec.format / 2 - 1.0).all(axis=1)
    o_st, o_pt, xy = o_st[inside], o_pt[inside], xy[inside]
    rays = np.bincount(o_pt, minlength=n)
    tied = rays >= 2
    new = np.cumsum(tied) - 1
    keep = tied[o_pt]
    return true_xyz[tied], o_st[keep], new[o_pt[keep]], xy[keep]


def _station_arrays(spec, z_mean):
    """True and approximate orientation of every station (per-station vectors; mapped from
    scratch files while :func:`sapgo.paging.paged`), drawn a chunk of stations at a time in
    the order of one draw per column over all stations (the generator's stream, and so the
    block, do not depend on the chunks)."""
    rng = np.random.default_rng([spec.seed, 1])
    S, G = spec.strips, spec.photos_per_strip
    n = S * G
    B, A, H = spec.base, spec.strip_spacing, spec.flying_height
    tilt = math.radians(spec.tilt)
    true_eo = paging.empty((n, 6))
    for col in range(6):
        for a, b in paging.rows(n):
            st_strip, st_g = np.divmod(np.arange(a, b), G)
            if col < 2:
                v = np.clip(rng.normal(0, tilt, b - a), -3 * tilt, 3 * tilt)
            elif col == 2:
                v = np.where(st_strip % 2 == 0, 0.0, math.pi) + rng.normal(
                    0, math.radians(1.0), b - a)
            elif col == 3:
                v = st_g * B + rng.normal(0, 0.01 * B, b - a)
            elif col == 4:
                v = (st_strip + 0.5) * A + rng.normal(0, 0.01 * A, b - a)
            else:
                v = z_mean + H + rng.normal(0, 0.003 * H, b - a)
            true_eo[a:b, col] = v
    approx_eo = paging.copy(true_eo)
    for a, b in paging.rows(n):
        approx_eo[a:b, :3] += rng.normal(0, spec.station_angle_perturbation * ARCSEC, (b - a, 3))
    for a, b in paging.rows(n):
        approx_eo[a:b, 3:] += rng.normal(0, spec.station_position_perturbation, (b - a, 3))
    return true_eo, approx_eo


def write_block(spec: BlockSpec, writer, progress=None):
    """Generate a SAPGO-P block into ``writer`` (a :class:`sapgo.project.ProjectWriter`).

    Points are numbered column by column along the strips (``id = c * rows + r + 1``) and
    written a block of :data:`COLUMN_BLOCK` columns at a time with their observations, so
    memory holds the per-station vectors and one column block, whatever the block's size.
    With ``spec.points_per_photo`` the random texture's points instead, by X, a slab of
    :func:`texture_columns` photo bases at a time (:func:`_texture_slab`); the control
    points are those nearest to the pattern's control places. Returns the counts.
    """
    spec.check()
    S, G, sub = spec.strips, spec.photos_per_strip, spec.sub
    B, A = spec.base, spec.strip_spacing
    n_rows, n_cols = spec.n_rows, spec.n_cols
    row_step = A / (2 * sub)
    col_step = B / sub
    terrain = Terrain((n_cols - 1) * col_step, (n_rows - 1) * row_step,
                      relief=spec.terrain_relief, seed=spec.seed)
    z_mean = terrain.base
    sigma = max(spec.sigma_image, 1e-6)

    cameras = np.zeros(1, CAMERA_DTYPE)
    cameras[0] = camera_record(1, spec.focal_length, 0.0, 0.0, spec.format, spec.format, sigma,
                               *spec.distortion)
    cams = camera_array(cameras)
    writer.append("cameras", cameras)
    true_eo, approx_eo = _station_arrays(spec, z_mean)
    n_st = S * G
    for a, b in paging.rows(n_st):
        stations = np.zeros(b - a, STATION_DTYPE)
        stations["id"] = np.arange(a + 1, b + 1)
        stations["strip"] = np.arange(a, b) // G + 1
        stations["eo"] = approx_eo[a:b]
        writer.append("stations", stations)
    for a, b in paging.rows(n_st):
        truth_st = np.zeros(b - a, TRUTH_STATION_DTYPE)
        truth_st["id"] = np.arange(a + 1, b + 1)
        truth_st["eo"] = true_eo[a:b]
        writer.append("truth/stations", truth_st)
    del stations, truth_st

    rr, cc = control_layout(n_rows, n_cols, spec.control_points, row_step, col_step, 2 * sub)
    control_index = np.sort(cc.astype(np.int64) * n_rows + rr)
    csig = spec.control_sigma if spec.control_sigma is not None else spec.control_perturbation
    cam_of_station = paging.zeros(n_st, np.int64)
    # the pattern of a photo: rows 0 .. 2 sub of its strip, columns sub g - sub .. sub g + sub
    k = np.arange(-sub, sub + 1)
    dr, dc = np.meshgrid(np.arange(0, 2 * sub + 1), k, indexing="ij")
    dr, dc = dr.ravel(), dc.ravel()

    counts = {"points": 0, "observations": 0, "control": 0}
    texture = spec.points_per_photo is not None
    if texture:   # slabs of photo bases (columns) along the strips; the control nearest
        cb = texture_columns(spec)   # to the pattern's control places
        slabs = [(c0, min(n_cols - 1, c0 + cb)) for c0 in range(0, n_cols - 1, cb)]
        tx, ty = cc * col_step, rr * row_step
    else:
        slabs = [(c0, min(n_cols, c0 + COLUMN_BLOCK)) for c0 in range(0, n_cols, COLUMN_BLOCK)]
    for blk, (c0, c1) in enumerate(slabs):
        rng = np.random.default_rng([spec.seed, 2, blk])
        first = counts["points"]
        if texture:
            x0, x1 = c0 * col_step, c1 * col_step
            if c1 == n_cols - 1:   # (the last nadir's points too)
                x1 = np.nextafter(x1, np.inf)
            true_xyz, o_st, o_pt, xy = _texture_slab(spec, x0, x1, rng, terrain, true_eo,
                                                     cams)
            xy += rng.normal(0, spec.sigma_image, xy.shape)
            n_pts = len(true_xyz)
            is_control = np.zeros(n_pts, bool)
            want = np.flatnonzero((tx >= x0) & (tx < x1))
            if n_pts and len(want):
                d2 = ((true_xyz[None, :, 0] - tx[want, None]) ** 2
                      + (true_xyz[None, :, 1] - ty[want, None]) ** 2)
                is_control[np.argmin(d2, axis=1)] = True
        else:
            # points of columns c0 .. c1-1, column by column
            cols = np.repeat(np.arange(c0, c1), n_rows)
            rows = np.tile(np.arange(n_rows), c1 - c0)
            n_pts = len(cols)
            jit = spec.point_jitter
            px = cols * col_step + rng.uniform(-jit, jit, n_pts) * col_step
            py = rows * row_step + rng.uniform(-jit, jit, n_pts) * row_step
            true_xyz = np.column_stack([px, py, terrain(px, py)])

            # observations: photos whose pattern reaches these columns
            g_lo = max(0, -(-(c0 - sub) // sub))
            g_hi = min(G - 1, (c1 - 1 + sub) // sub)
            g = np.arange(g_lo, g_hi + 1)
            st = (np.arange(S)[:, None] * G + g[None, :]).ravel()
            o_st = np.repeat(st, len(dr))
            o_row = np.repeat(2 * sub * (st // G), len(dr)) + np.tile(dr, len(st))
            o_col = np.repeat(sub * (st % G), len(dc)) + np.tile(dc, len(st))
            keep = (o_col >= c0) & (o_col < c1)
            o_st, o_pt = o_st[keep], (o_col[keep] - c0) * n_rows + o_row[keep]
            order = np.lexsort((o_st, o_pt))
            o_st, o_pt = o_st[order], o_pt[order]
            xy = np.empty((len(o_pt), 2))
            project_observations(o_st, o_pt, true_eo, true_xyz, cam_of_station, cams, xy)
            xy += rng.normal(0, spec.sigma_image, xy.shape)
            # a pattern point displaced off the photo (tilt, relief) cannot be measured on it
            inside = (np.abs(xy) < spec.format / 2 - 1.0).all(axis=1)
            o_st, o_pt, xy = o_st[inside], o_pt[inside], xy[inside]

            # control and check points
            lo, hi = np.searchsorted(control_index, [first, first + n_pts])
            is_control = np.zeros(n_pts, bool)
            is_control[control_index[lo:hi] - first] = True
        control = true_xyz + np.where(
            is_control[:, None], rng.normal(0, spec.control_perturbation, (n_pts, 3)), 0.0)

        # approximate coordinates: intersection from the approximate stations
        n_obs = np.bincount(o_pt, minlength=n_pts)
        starts = np.zeros(n_pts, np.int64)
        np.cumsum(n_obs[:-1], out=starts[1:])
        approx = np.empty((n_pts, 3))
        ok = np.zeros(n_pts, np.bool_)
        intersect_points(starts, n_obs, o_st, xy, approx_eo, cam_of_station, cams, approx, ok)
        fallback = rng.normal(0, spec.station_position_perturbation, (n_pts, 3))
        approx = np.where(ok[:, None], approx, true_xyz + fallback)
        approx[is_control] = control[is_control]

        points = np.zeros(n_pts, POINT_DTYPE)
        points["id"] = np.arange(first, first + n_pts) + 1
        points["kind"] = np.where(is_control, KIND_CONTROL, KIND_CHECK)
        points["xyz"] = approx
        points["control"] = control
        points["control_sigma"] = np.where(is_control[:, None], csig, 0.0)
        points["obs_start"] = counts["observations"] + starts
        points["n_obs"] = n_obs
        points["station_min"] = -1
        points["station_max"] = -1
        writer.append("points", points)
        truth_pt = np.zeros(n_pts, TRUTH_POINT_DTYPE)
        truth_pt["id"] = points["id"]
        truth_pt["xyz"] = true_xyz
        writer.append("truth/points", truth_pt)
        obs = np.zeros(len(o_pt), OBSERVATION_DTYPE)
        obs["point"] = o_pt + first
        obs["station"] = o_st
        obs["x"] = xy[:, 0]
        obs["y"] = xy[:, 1]
        obs["sigma"] = sigma
        writer.append("observations", obs)
        counts["points"] += n_pts
        counts["observations"] += len(obs)
        counts["control"] += int(is_control.sum())
        if progress is not None:
            progress(c1 - c0 + (texture and c1 == n_cols - 1))
    counts["photos"] = n_st
    return counts
