"""The quality passes of an adjustment: precision and observation quality from the
factor (DESIGN section 6), and the robust weights they give.

:func:`quality_sweep` streams the stations' cofactor blocks from the band's factor
(Takahashi's recurrence, :func:`sapgo.solve.band.covariance_blocks`) or the tree's
(:func:`sapgo.solve.tree.tree_quality`) and, in step with them, the points' standard
deviations and their observations' redundancy numbers and normalised residuals
(:func:`points_quality`). The factor must be the undamped one of the current state
(:func:`sapgo.adjust._precision` sees to it).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from . import paging
from . import threads as _threads
from .geometry import with_rotations
from .normals import PointChunk, point_sigmas_parallel
from .project import STATUS_ACTIVE
from .report import station_correlations
from .solve.band import border_back_substitute, covariance_blocks

#: Columns of the observations' quality file (see :func:`quality_sweep`).
QUALITY_COLUMNS = ("r_x", "r_y", "r_xy", "w_x", "w_y", "t", "weight")


def standardised_residuals(residuals_mm, redundancy):
    """The residual of each observation scaled to the observation's own size,
    ``sqrt(v' R^+ v)`` (mm), ``R`` its 2 x 2 block of the redundancy matrix (columns r_x, r_y,
    r_xy of ``redundancy``; pseudo-inverse where R has rank 1). A good observation's is
    about sigma per coordinate whatever its redundancy, a blunder's about the blunder's size
    times sqrt(r); 0 where R is 0 (a blunder there cannot be seen)."""
    vx, vy = residuals_mm[:, 0], residuals_mm[:, 1]
    rx, ry, rxy = redundancy[:, 0], redundancy[:, 1], redundancy[:, 2]
    det = rx * ry - rxy * rxy
    tr = rx + ry
    full = det > 1e-8 * tr * tr
    with np.errstate(invalid="ignore", divide="ignore"):
        s2 = np.where(full, (ry * vx * vx - 2 * rxy * vx * vy + rx * vy * vy) / det,
                      (rx * vx * vx + 2 * rxy * vx * vy + ry * vy * vy) / (tr * tr))
    return np.sqrt(np.where(tr > 1e-12, np.maximum(s2, 0.0), 0.0))


def robust_weights(residuals_mm, opts, redundancy=None):
    """Weights of the image observations from their previous residuals (n x 2, mm): Huber
    ``min(1, k / r)`` or Cauchy ``1 / (1 + (r / k)^2)``, ``k`` the threshold (um) and ``r``
    the residual's length in um or, given the observations' ``redundancy`` (n x 3: r_x, r_y,
    r_xy), its :func:`standardised_residuals`; all ones without robust estimation."""
    if opts.robust is None or not len(residuals_mm):
        return np.ones(len(residuals_mm))
    if redundancy is None:
        r = 1000.0 * np.hypot(residuals_mm[:, 0], residuals_mm[:, 1])
    else:
        r = 1000.0 * standardised_residuals(residuals_mm, redundancy)
    k = opts.robust_threshold_um
    if opts.robust == "huber":
        return np.where(r <= k, 1.0, k / np.maximum(r, 1e-300))
    return 1.0 / (1.0 + (r / k) ** 2)


def reweight(c, work, opts):
    """Robust estimation, once the least-squares phase has given the redundancy numbers
    (``work.robust_r``): the chunk's observation sigmas divided by sqrt(weight)."""
    if opts.robust is not None and work.robust_r is not None and c.o1 > c.o0:
        w = robust_weights(work.res_current[c.o0:c.o1], opts, work.robust_r[c.o0:c.o1])
        c.obs_sigma = np.ascontiguousarray(c.obs_sigma / np.sqrt(np.maximum(w, 1e-12)))
        return w
    return None


def quality_sweep(p_read, work, blk, opts, sigma0, correlations=None):
    """Precision and observation quality from the last iteration's factor.

    The stations' cofactor blocks by Takahashi's recurrence streamed backwards (the blocks to
    ``cov.bin``; ``station_sigma`` in core, 48 bytes a station), and, in step with it, the
    points whose first station is in the block just finished (points are sorted by it,
    excluded ones last): their standard deviations (``point_sigma.bin``) and their
    observations' redundancy numbers and normalised residuals (``quality.bin``, columns
    ``QUALITY_COLUMNS``: r_x, r_y and r_xy of the observation's block of the redundancy
    matrix, w_x, w_y, the 2-D statistic ``t = sqrt(v' Q_vv^+ v) / sigma0`` and the robust
    weight). Correlations of a station's or a point's parameters above the threshold go to
    ``correlations`` (a :class:`~sapgo.report.HighCorrelations`) when given. Returns
    ``(station_sigma, point_sigma file, quality file)``."""
    n_st = len(blk.station_ids)
    if blk.tree is not None:
        return _quality_tree(p_read, work, blk, opts, sigma0, correlations)
    first = paging.zeros(n_st + 1, np.int64)
    for a, b in p_read.chunks("points", opts.chunk_points):
        sm = p_read.read_field("points", "station_min", a, b)
        sm = sm[p_read.read_field("points", "status", a, b) == STATUS_ACTIVE]
        if len(sm):   # (points are sorted by their first station: a range of stations)
            lo = int(sm.min())
            cnt = np.bincount(sm - lo)
            first[1 + lo:1 + lo + len(cnt)] += cnt
    carry = 0
    for a, b in paging.rows(n_st + 1):
        first[a:b] = np.cumsum(first[a:b]) + carry
        carry = int(first[b - 1])
    ng = blk.n_border
    cal = sig_b = xb_ds = None
    if ng:  # self-calibration: X = M^-1 B (its own file: W stays, the sweep can run again)
        xb_ds = work.array("xborder.bin", (n_st, blk.npar, ng))
        border_back_substitute(work.band_factor()[0], work.border, n_st, blk.band_width, opts.chunk_rows,
                               out=xb_ds)
        cal, sig_b = blk.cal, np.ascontiguousarray(blk.border_cov, dtype=np.float64)
    psig = work.array("point_sigma.bin", (p_read.n_points, 3))
    quality = work.array("quality.bin", (p_read.n_observations, len(QUALITY_COLUMNS)))
    eo_k = with_rotations(blk.eo)   # (each station's rotation once, not at every ray)

    def points_of(start, stop, zb, base, alone=False):
        p0, p1 = int(first[start]), int(first[stop])
        xw = (np.ascontiguousarray(xb_ds[start:min(n_st, stop + blk.band_width)],
                                   dtype=np.float64) if ng else None)
        for a in range(p0, p1, opts.chunk_points):
            points_quality(p_read, work, blk, opts, a, min(p1, a + opts.chunk_points), sigma0,
                           psig, quality, correlations, zb, base, None, xw, start, cal, sig_b,
                           threads=_threads.parts() if alone else 1, eo=eo_k)

    k = blk.npar
    cov = work.array("cov.bin", (n_st, k, k))
    try:
        var = covariance_blocks(work.band_factor()[0], n_st, blk.band_width, opts.chunk_rows, out=cov,
                                on_block=points_of if opts.precision == "full" else None,
                                observations=p_read.n_observations)
        for a, b in paging.rows(n_st, opts.chunk_points) if ng else ():  # + X S^-1 X'
            x = np.asarray(xb_ds[a:b], dtype=np.float64)
            blocks = cov[a:b] + np.einsum("iag,gh,ibh->iab", x, sig_b, x)
            cov[a:b] = blocks
        for a, b in paging.rows(n_st, opts.chunk_points):   # the attitude in omega, phi, kappa
            blocks = in_angles(cov[a:b], blk.eo[a:b], blk.fixed[a:b])
            cov[a:b] = blocks
            var[a:b] = np.diagonal(blocks, axis1=1, axis2=2)
        if correlations is not None:
            _station_correlations(cov, blk, opts, correlations)
    finally:
        cov.close()
        if xb_ds is not None:
            xb_ds.close()
    return station_sigma(blk, sigma0, var), psig, quality


def _station_correlations(cov, blk, opts, correlations):
    """Correlations of each station's parameters from its cofactor blocks (``cov``) into
    ``correlations``, chunk by chunk."""
    n_st = len(blk.station_ids)
    for a, b in paging.rows(n_st, opts.chunk_points):
        rho = station_correlations(cov[a:b][:, :6, :6])
        rho[~blk.station_active[a:b]] = np.nan
        correlations.add("stations", blk.station_ids[a:b], rho)


def in_angles(blocks, eo, fixed):
    """Stations' cofactor blocks (n x k x k) of the adjustment's unknowns, the attitude a
    rotation vector (:func:`sapgo.geometry.turn`), as blocks of omega, phi, kappa: ``T Q
    T'`` with ``T = diag(J, I)``, ``J = d(omega, phi, kappa)/d theta`` at the stations'
    values ``eo`` (:func:`sapgo.geometry.attitude_jacobians`; exact for the linearised
    cofactors, undefined at phi = +-90 degrees, where the angles are); the rows and
    columns of the parameters held fixed (``fixed``, the stations' bits of
    ``_Block.fixed``) 0: no variance (their unit diagonal in the normals is none).
    One numba kernel (:func:`_in_angles`): the tree's precision pass calls this once a
    node, where numpy's small-array calls cost 0.15 ms each."""
    blocks = np.ascontiguousarray(blocks, np.float64)
    if not len(blocks):
        return blocks
    out = np.empty_like(blocks)
    _in_angles(blocks, np.ascontiguousarray(np.asarray(eo, np.float64)[:, :3]),
               np.ascontiguousarray(fixed, np.int64), out)
    return out


@njit(cache=True, error_model="numpy")
def _in_angles(blocks, opk, fixed, out):
    """:func:`in_angles`: ``out[s] = T blocks[s] T'`` with ``J`` as
    :func:`sapgo.geometry.attitude_jacobians` works it out, station by station."""
    n, k = blocks.shape[0], blocks.shape[1]
    m = np.empty((3, 3))
    dm = np.empty((3, 3, 3))
    j = np.empty((3, 3))
    tmp = np.empty((k, k))
    for s in range(n):
        w, p, kk = opk[s, 0], opk[s, 1], opk[s, 2]
        cw, sw, cp, sp = np.cos(w), np.sin(w), np.cos(p), np.sin(p)
        ck, sk = np.cos(kk), np.sin(kk)
        m[0, 0], m[0, 1], m[0, 2] = ck * cp, ck * sp * sw + sk * cw, -ck * sp * cw + sk * sw
        m[1, 0], m[1, 1], m[1, 2] = -sk * cp, -sk * sp * sw + ck * cw, sk * sp * cw + ck * sw
        m[2, 0], m[2, 1], m[2, 2] = sp, -cp * sw, cp * cw
        for r in range(3):   # dM/dtheta_i = -M [e_i]x, by columns
            dm[0, r, 0], dm[0, r, 1], dm[0, r, 2] = 0.0, -m[r, 2], m[r, 1]
            dm[1, r, 0], dm[1, r, 1], dm[1, r, 2] = m[r, 2], 0.0, -m[r, 0]
            dm[2, r, 0], dm[2, r, 1], dm[2, r, 2] = -m[r, 1], m[r, 0], 0.0
        qw = m[2, 1] ** 2 + m[2, 2] ** 2
        qk = m[1, 0] ** 2 + m[0, 0] ** 2
        for i in range(3):
            j[0, i] = (-m[2, 2] * dm[i, 2, 1] + m[2, 1] * dm[i, 2, 2]) / qw
            j[1, i] = dm[i, 2, 0] / cp
            j[2, i] = (-m[0, 0] * dm[i, 1, 0] + m[1, 0] * dm[i, 0, 0]) / qk
        for a in range(k):   # T Q
            for b in range(k):
                if a < 3:
                    tmp[a, b] = (j[a, 0] * blocks[s, 0, b] + j[a, 1] * blocks[s, 1, b]
                                 + j[a, 2] * blocks[s, 2, b])
                else:
                    tmp[a, b] = blocks[s, a, b]
        for a in range(k):   # (T Q) T'
            for b in range(k):
                if b < 3:
                    out[s, a, b] = tmp[a, 0] * j[b, 0] + tmp[a, 1] * j[b, 1] + tmp[a, 2] * j[b, 2]
                else:
                    out[s, a, b] = tmp[a, b]
        for c in range(min(k, 6)):
            if (fixed[s] >> c) & 1:
                for b in range(k):
                    out[s, c, b] = 0.0
                    out[s, b, c] = 0.0


def points_quality(p_read, work, blk, opts, a, b, sigma0, psig, quality, correlations,
                    zb, base, stations=None, xw=None, xlo=0, cal=None, sig_b=None, lock=None,
                    threads=1, eo=None):
    """Points ``a .. b`` (a chunk): their standard deviations into ``psig`` and their
    observations' quality into ``quality`` (:func:`sapgo.normals.point_sigmas` with the
    stations' cofactors ``zb`` from ``base``). ``stations(obs_station, obs_active)`` gives
    the observations' stations as indices into ``zb``'s stations with their orientation
    and camera (the tree numbers them by their place in a front); default the logical
    stations. ``zb`` may instead be a function of the chunk's ``(obs_station,
    obs_active)`` giving ``(zb, stations, orientations, cameras, xw)`` (a tiled front's
    inverse gathered over the chunk's stations). ``threads``: the kernel's threads
    (:func:`sapgo.normals.point_sigmas_parallel`; more than one only where nothing else
    runs beside it). ``eo``: the stations' orientations for the kernel (with their
    rotations, :func:`sapgo.geometry.with_rotations`; default ``blk.eo``)."""
    c = PointChunk(p_read, a, b, work.xyz_current[a:b], blk.camera, blk.cam_sigma, blk.frame,
                   blk.rejected)
    weight = reweight(c, work, opts)
    out = np.empty((b - a, 6))
    out_r = np.empty((c.o1 - c.o0, 3))
    out_w = np.empty((c.o1 - c.o0, 3))
    predict = rejected_in(blk.rejected, c.o0, c.o1)
    if predict is not None and stations is None and not callable(zb):
        # (the band's window holds every station of the point: of its active observations
        # by the ordering, of a rejected one as it was active then; checked all the same)
        row = blk.npar * c.obs_station[predict] - base
        predict[predict] = (row >= 0) & (row + blk.npar <= zb.shape[0])
    seen = c.obs_active if predict is None else c.obs_active | predict
    if callable(zb):
        zb, st, eo, camera, xw, fixed = zb(c.obs_station, seen)
    else:
        st, eo, camera, fixed = ((c.obs_station, blk.eo if eo is None else eo, blk.camera,
                                  blk.fixed)
                                 if stations is None else
                                 stations(c.obs_station, seen))
    point_sigmas_parallel(threads, c.xyz, c.kind, c.ctrl, c.csig, c.rot, c.pt_start, c.nobs,
                          c.active, st, c.obs_xy, c.obs_sigma, c.obs_active, eo, camera,
                          blk.cams, blk.ctrl_mask, c.max_rays, zb, base,
                          np.ascontiguousarray(work.res_current[c.o0:c.o1]), out, out_r, out_w,
                          blk.npar, cal, xw, xlo, sig_b, fixed, blk.behind_ok, predict)
    psig[a:b] = sigma0 * out[:, :3]
    if weight is None:
        weight = np.ones(c.o1 - c.o0)
    quality[c.o0:c.o1] = np.concatenate(
        [out_r, out_w / sigma0, np.where(c.obs_active, weight, 0.0)[:, None]], axis=1)
    if correlations is not None:
        rho = np.where((c.active == 0)[:, None], out[:, 3:], np.nan)
        ids = p_read.read_field("points", "id", a, b)
        if lock is None:
            correlations.add("points", ids, rho)
        else:
            with lock:
                correlations.add("points", ids, rho)


def rejected_in(rejected, o0, o1):
    """The observations ``o0 .. o1`` that ``rejected`` (sorted indices: data snooping's
    rejections in the run) holds, as a mask, or None when it holds none: the precision pass
    predicts their residuals from the other observations (:func:`sapgo.normals.point_sigmas`,
    ``obs_predict``)."""
    if rejected is None or not len(rejected):
        return None
    lo, hi = np.searchsorted(rejected, [o0, o1])
    if hi == lo:
        return None
    mask = np.zeros(o1 - o0, np.bool_)
    mask[rejected[lo:hi] - o0] = True
    return mask


def station_sigma(blk, sigma0, var):
    """The stations' standard deviations (n x 6, zero for those not adjusted) from their
    variances ``var``, a chunk of rows at a time."""
    out = paging.empty((len(var), 6))
    for a, b in paging.rows(len(var)):
        out[a:b] = sigma0 * np.sqrt(np.maximum(var[a:b, :6], 0.0))
        out[a:b][~blk.station_active[a:b]] = 0.0
    return out


def _quality_tree(p_read, work, blk, opts, sigma0, correlations=None):
    """:func:`quality_sweep` on the partition tree (:func:`sapgo.solve.tree.tree_quality`:
    the selected inversion top-down, the points node by node)."""
    from .solve.tree import tree_quality

    n_st, k = len(blk.station_ids), blk.npar
    psig = work.array("point_sigma.bin", (p_read.n_points, 3))
    quality = work.array("quality.bin", (p_read.n_observations, len(QUALITY_COLUMNS)))
    cov = work.array("cov.bin", (n_st, k, k))
    try:
        var = tree_quality(p_read, work, blk, opts, blk.tree, sigma0, psig, quality, cov,
                           correlations)
        if correlations is not None:
            _station_correlations(cov, blk, opts, correlations)
    finally:
        cov.close()
    return station_sigma(blk, sigma0, var), psig, quality
