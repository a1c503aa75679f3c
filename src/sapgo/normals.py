"""Streaming build of the reduced normal equations, band row by band row (DESIGN sections 2-3).

For every point ``j`` (in logical order) and every station ``s`` that observes it, the
linearised collinearity equations give ``A`` (2x6, station) and ``B`` (2x3, point). With weight
``p = 1/sigma^2`` the point contributes (Brown's reduction; seeds/003)

    N_ss   += p A'A          c_s  += p A'l                          (station diagonal)
    Nbar_s  = p A'B          Ndd_j = sum_s p B'B + control weight    cdd_j = sum_s p B'l + ...
    M_st   -= Nbar_s Ndd_j^-1 Nbar_t'       d_s -= Nbar_s Ndd_j^-1 cdd_j

so the point is eliminated as soon as it is formed and only the 6x6 station blocks remain.
Band row ``s`` holds ``M[s, s + k]`` for ``k = 0 .. b-1`` (a 6 x 6b array, the diagonal block
full). Points are sorted by their smallest logical station, so once a point with smallest
station ``t`` is reached no later point touches the rows before ``t``: those rows are finished
and written to the band dataset. In core there is only a window of ``b + chunk`` rows.

Control components enter as weighted observations of the point (a sigma of 0 fixes the
component: it is eliminated, never divided by zero); station priors add their weight matrix
to the diagonal block when the row enters the window.

The per-ray kernels here and in :mod:`sapgo.geometry` are compiled with
``error_model="numpy"`` (no branch raising ``ZeroDivisionError`` after each division: every
divisor is tested before, or is a pivot, a weight or a focal length), and the helpers called
once a ray are plain calls, not numba's ``inline="always"``. Both let numba's reference-count
pruning drop the atomic increments and decrements of the arrays that a call receives or a
view makes, which were about half of the build's time (measured with ``perf`` on the
100 x 100 block's fronts: 4.25 us a point before, 2.81 after, the workspace's rays filled
in place instead of through per-point arrays).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .geometry import N_CALIBRATION, camera_partials, linearize, observed, project
from .project import CONTROL_MASK, STATUS_ACTIVE

# kernel status codes
OK = 0
SINGULAR_POINT = 1
BEHIND_CAMERA = 2
BAD_LAYOUT = 3  # the records do not follow the logical order the band width was computed for


@njit(cache=True, error_model="numpy", nogil=True, inline="always")
def fixed_columns(a, mask):
    """Zero the columns of ``a`` (2 x npar) of the station parameters whose bits are set
    in ``mask`` (bit u: parameter u of omega, phi, kappa, X, Y, Z), held fixed: as unknowns
    they are gone from the observation equations, and the unit weight the priors' cursor
    gives them (``sapgo.adjust._PriorCursor``) keeps the normals regular with their
    corrections exactly 0."""
    if mask != 0:
        for u in range(6):
            if (mask >> u) & 1:
                a[0, u] = 0.0
                a[1, u] = 0.0


@njit(cache=True, error_model="numpy")
def _point_system(j, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start, pt_nobs,
                  obs_station, obs_xy, obs_sigma, obs_active, eo, cam_of_station, cams,
                  ctrl_mask, xyz, nbar, a_all, l_all, w_all, st_all, nn, cc, b_all, o_all,
                  lam=0.0, behind_ok=False, st_fixed=None):
    """Linearise point ``j``: fill its rays' A, B, l, p, Nbar and its 3x3 system nn, cc.

    Returns the number of active rays ``k`` (negative when a point is behind a camera).
    ``xyz`` receives the point's current coordinates (fixed control components replaced by
    their control values). ``lam > 0``: Levenberg-Marquardt damping, ``lam`` times the
    diagonal of nn (clamped to [1e-6, 1e32], as Ceres does) added to it. ``behind_ok``: a
    point behind a camera is projected all the same (BAL problems), not refused.
    ``st_fixed`` (per station, bits 0-5): station parameters held fixed (``--datum fix``):
    their columns of A are zero, so they take no part in the normals (see
    :func:`fixed_columns`).
    """
    kind = pt_kind[j]
    for c in range(3):
        xyz[c] = pt_xyz[j, c]
        if ctrl_mask[kind, c] and pt_csig[j, c] == 0.0:
            xyz[c] = pt_ctrl[j, c]
    nn[:, :] = 0.0
    cc[:] = 0.0
    npar = a_all.shape[2]  # parameters per station: 6, or 9 with the photo's intrinsics
    k = 0
    for i in range(pt_start[j], pt_start[j] + pt_nobs[j]):
        if not obs_active[i]:
            continue
        s = obs_station[i]
        cam = cam_of_station[s]
        a = a_all[k]
        b = b_all[k]
        x, y, w = linearize(eo[s], xyz, cams[cam], a, b)
        if w == 0.0 or (w > 0.0 and not behind_ok):
            return -1
        if st_fixed is not None and s < st_fixed.shape[0]:
            fixed_columns(a, st_fixed[s])
        p = 1.0 / (obs_sigma[i] * obs_sigma[i])
        ox, oy = observed(obs_xy[i, 0], obs_xy[i, 1], cams[cam])
        l0 = ox - x
        l1 = oy - y
        o_all[k, 0] = obs_xy[i, 0]
        o_all[k, 1] = obs_xy[i, 1]
        for r in range(npar):
            for c in range(3):
                nbar[k, r, c] = p * (a[0, r] * b[0, c] + a[1, r] * b[1, c])
        for r in range(3):
            for c in range(3):
                nn[r, c] += p * (b[0, r] * b[0, c] + b[1, r] * b[1, c])
            cc[r] += p * (b[0, r] * l0 + b[1, r] * l1)
        l_all[k, 0] = l0
        l_all[k, 1] = l1
        w_all[k] = p
        st_all[k] = s
        k += 1
    for c in range(3):
        if ctrl_mask[kind, c]:
            sig = pt_csig[j, c]
            if sig > 0.0:  # along row c of the control rotation (east, north, up in a CRS)
                wc = 1.0 / (sig * sig)
                d = 0.0
                for q in range(3):
                    d += pt_rot[j, c, q] * (pt_ctrl[j, q] - xyz[q])
                for r in range(3):
                    for q in range(3):
                        nn[r, q] += wc * pt_rot[j, c, r] * pt_rot[j, c, q]
                    cc[r] += wc * pt_rot[j, c, r] * d
            else:  # fixed component (frame axis; a CRS point is fixed in all three or none)
                for r in range(3):
                    nn[r, c] = 0.0
                    nn[c, r] = 0.0
                nn[c, c] = 1.0
                cc[c] = 0.0
                for q in range(k):
                    for r in range(npar):
                        nbar[q, r, c] = 0.0
    if lam > 0.0:
        for r in range(3):
            nn[r, r] += lam * min(max(nn[r, r], 1e-6), 1e32)
    return k


@njit(cache=True, error_model="numpy", nogil=True)
def station_diagonal(pt_xyz, pt_active, pt_start, pt_nobs, obs_station, obs_sigma, obs_active,
                     eo, cam_of_station, cams, diag):
    """Add each station's diagonal of the (unreduced) normal matrix, ``sum p a_u^2`` over its
    active observations of active points of a chunk, into ``diag`` (stations x 6): the
    scaling of the Levenberg-Marquardt damping (the tree's; the band's build sums it in
    :func:`build_points`)."""
    npar = diag.shape[1]
    a = np.empty((2, npar))
    b = np.empty((2, 3))
    for j in range(pt_xyz.shape[0]):
        if pt_active[j] != 0:
            continue
        for i in range(pt_start[j], pt_start[j] + pt_nobs[j]):
            if not obs_active[i]:
                continue
            s = obs_station[i]
            linearize(eo[s], pt_xyz[j], cams[cam_of_station[s]], a, b)
            p = 1.0 / (obs_sigma[i] * obs_sigma[i])
            for u in range(npar):
                diag[s, u] += p * (a[0, u] * a[0, u] + a[1, u] * a[1, u])


@njit(cache=True, error_model="numpy")
def _chol3(nn, lo):
    """Cholesky factor ``lo`` (lower) of the 3x3 SPD matrix ``nn``; False if not SPD.

    A pivot counts as zero at or below 1e-13 of its own diagonal element (scale-free, as in
    :mod:`sapgo.solve.band`).
    """
    for i in range(3):
        for j in range(i + 1):
            s = nn[i, j]
            for k in range(j):
                s -= lo[i, k] * lo[j, k]
            if i == j:
                if not (s > 1e-13 * nn[i, i]) or not (s > 0.0):
                    return False
                lo[i, i] = np.sqrt(s)
            else:
                lo[i, j] = s / lo[j, j]
    return True


@njit(cache=True, error_model="numpy")
def _solve3(lo, rhs, out):
    y0 = rhs[0] / lo[0, 0]
    y1 = (rhs[1] - lo[1, 0] * y0) / lo[1, 1]
    y2 = (rhs[2] - lo[2, 0] * y0 - lo[2, 1] * y1) / lo[2, 2]
    out[2] = y2 / lo[2, 2]
    out[1] = (y1 - lo[2, 1] * out[2]) / lo[1, 1]
    out[0] = (y0 - lo[1, 0] * out[1] - lo[2, 0] * out[2]) / lo[0, 0]


@njit(cache=True, error_model="numpy")
def _workspace(max_rays, npar=6):
    """Per-point work arrays of :func:`_point_system` for points of up to ``max_rays`` rays
    and stations of ``npar`` parameters."""
    return (np.empty((max_rays, npar, 3)), np.empty((max_rays, 2, npar)),
            np.empty((max_rays, 2)),
            np.empty(max_rays), np.empty(max_rays, np.int64), np.empty((3, 3)), np.empty(3),
            np.zeros((3, 3)), np.empty(3), np.empty((max_rays, 2, 3)), np.empty((max_rays, 2)))


@njit(cache=True, error_model="numpy", nogil=True)
def _ray_terms(q, w_all, a_all, l_all, nbar, h, lo, npar, diag, rhs_row, g, col, tmp):
    """Ray ``q`` of a point: ``p A'A`` into its station's diagonal block ``diag[:npar,
    :npar]``, ``p A'l - Nbar Ndd^-1 cdd`` into ``rhs_row`` (``h = Ndd^-1 cdd``), and its rows
    of ``G = Nbar Ndd^-1`` into ``g[q]`` (``lo``: the Cholesky factor of ``Ndd``)."""
    p = w_all[q]
    a = a_all[q]
    for u in range(npar):
        for v in range(npar):
            diag[u, v] += p * (a[0, u] * a[0, v] + a[1, u] * a[1, v])
        s = p * (a[0, u] * l_all[q, 0] + a[1, u] * l_all[q, 1])
        for c in range(3):
            s -= nbar[q, u, c] * h[c]
        rhs_row[u] += s
    for u in range(npar):
        for c in range(3):
            col[c] = nbar[q, u, c]
        _solve3(lo, col, tmp)
        for c in range(3):
            g[q, u, c] = tmp[c]


@njit(cache=True, error_model="numpy", nogil=True)
def _inverse3(lo, out):
    """The inverse ``(L L')^-1`` of a 3 x 3 matrix from its Cholesky factor ``lo``."""
    i00 = 1.0 / lo[0, 0]
    i11 = 1.0 / lo[1, 1]
    i22 = 1.0 / lo[2, 2]
    i10 = -lo[1, 0] * i00 * i11
    i21 = -lo[2, 1] * i11 * i22
    i20 = -(lo[2, 0] * i00 + lo[2, 1] * i10) * i22
    out[0, 0] = i00 * i00 + i10 * i10 + i20 * i20
    out[1, 0] = out[0, 1] = i10 * i11 + i20 * i21
    out[2, 0] = out[0, 2] = i20 * i22
    out[1, 1] = i11 * i11 + i21 * i21
    out[2, 1] = out[1, 2] = i21 * i22
    out[2, 2] = i22 * i22


@njit(cache=True, error_model="numpy", nogil=True)
def _ray_terms6(q, w_all, a_all, l_all, nbar, h, ninv, diag, rhs_row, g, nbt):
    """:func:`_ray_terms` for 6 parameters a station (the loops unrolled), with
    ``G = Nbar Ndd^-1`` from the inverse ``ninv`` (:func:`_inverse3`) instead of six
    triangular solves; ``Nbar`` transposed into ``nbt[q]`` besides."""
    p = w_all[q]
    l0 = l_all[q, 0]
    l1 = l_all[q, 1]
    for u in range(6):
        pa0 = p * a_all[q, 0, u]
        pa1 = p * a_all[q, 1, u]
        for v in range(6):
            diag[u, v] += pa0 * a_all[q, 0, v] + pa1 * a_all[q, 1, v]
        n0, n1, n2 = nbar[q, u, 0], nbar[q, u, 1], nbar[q, u, 2]
        rhs_row[u] += pa0 * l0 + pa1 * l1 - (n0 * h[0] + n1 * h[1] + n2 * h[2])
        for c in range(3):
            g[q, u, c] = n0 * ninv[0, c] + n1 * ninv[1, c] + n2 * ninv[2, c]
            nbt[q, c, u] = nbar[q, u, c]


@njit(cache=True, error_model="numpy", nogil=True)
def _rays6(k, base, split, band, rhs, ovf_band, ovf_rhs, w_all, a_all, l_all, nbar, h, ninv,
           g, nbt, st_all):
    """:func:`_ray_terms6` of a point's ``k`` rays into their band rows."""
    for q in range(k):
        r = st_all[q] - base
        row = band[r] if r < split else ovf_band[r - split]
        rrow = rhs[r] if r < split else ovf_rhs[r - split]
        _ray_terms6(q, w_all, a_all, l_all, nbar, h, ninv, row, rrow, g, nbt)


@njit(cache=True, error_model="numpy", nogil=True)
def _schur6(k, base, split, band, ovf_band, st_all, g, nbar, nbt):
    """The Schur complement of a point into its band rows, ``M[s_q, s_t] -= G_q Nbar_t'``,
    for 6 parameters a station (the loops unrolled)."""
    for q in range(k):
        r = st_all[q] - base
        row = band[r] if r < split else ovf_band[r - split]
        for t in range(q, k):
            off = 6 * (st_all[t] - st_all[q])
            for u in range(6):
                g0, g1, g2 = g[q, u, 0], g[q, u, 1], g[q, u, 2]
                for v in range(6):
                    row[u, off + v] -= g0 * nbt[t, 0, v] + g1 * nbt[t, 1, v] + g2 * nbt[t, 2, v]
            if st_all[t] == st_all[q] and t != q:   # (two rays of one photo: both ways)
                for u in range(6):
                    for v in range(6):
                        row[v, off + u] -= g[q, u, 0] * nbar[t, v, 0] \
                            + g[q, u, 1] * nbar[t, v, 1] + g[q, u, 2] * nbar[t, v, 2]


#: Doubles of a point's kept system (:func:`_keep_point`): the Cholesky factor of its
#: (damped) 3 x 3 block, its right-hand side, its coordinates and the block's diagonal.
KEPT_POINT = 18


@njit(cache=True, error_model="numpy", nogil=True, inline="always")
def _keep_point(j, keep_pt, keep_nbar, lo, cc, xyz, nn, nbar, pt_start, pt_nobs, obs_active):
    """Point ``j``'s system as :func:`_point_system` linearised it into ``keep_pt[j]``
    (``lo`` by rows, ``cc``, ``xyz``, the diagonal of ``nn``) and its active rays' ``Nbar``
    into ``keep_nbar`` at their observations' rows."""
    for r in range(3):
        for c in range(3):
            keep_pt[j, 3 * r + c] = lo[r, c]
        keep_pt[j, 9 + r] = cc[r]
        keep_pt[j, 12 + r] = xyz[r]
        keep_pt[j, 15 + r] = nn[r, r]
    q = 0
    for i in range(pt_start[j], pt_start[j] + pt_nobs[j]):
        if obs_active[i]:
            keep_nbar[i] = nbar[q]
            q += 1


@njit(cache=True, error_model="numpy", nogil=True, inline="always")
def _kept_point(j, keep_pt, keep_nbar, pt_start, pt_nobs, obs_station, obs_active, lo, cc,
                xyz, nn, nbar, st_all):
    """:func:`_keep_point` read back into the workspace of :func:`_point_system` (``nn``:
    its diagonal alone); the number of active rays."""
    for r in range(3):
        for c in range(3):
            lo[r, c] = keep_pt[j, 3 * r + c]
        cc[r] = keep_pt[j, 9 + r]
        xyz[r] = keep_pt[j, 12 + r]
        nn[r, r] = keep_pt[j, 15 + r]
    k = 0
    for i in range(pt_start[j], pt_start[j] + pt_nobs[j]):
        if obs_active[i]:
            nbar[k] = keep_nbar[i]
            st_all[k] = obs_station[i]
            k += 1
    return k



@njit(cache=True, error_model="numpy", nogil=True)
def build_points(j0, j_stop, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start, pt_nobs,
                 pt_smax, pt_active, obs_station, obs_xy, obs_sigma, obs_active, eo, cam_of_station,
                 cams, ctrl_mask, band, rhs, base, max_rays, split, ovf_band,
                 ovf_rhs, cal, bord, ovf_bord, cnn, ccg, cdiag, lam=0.0, behind_ok=False,
                 st_fixed=None, dg=None, ovf_dg=None, keep_pt=None, keep_nbar=None):
    """Add points ``j0 .. j_stop-1`` of a chunk into the band-row window.

    ``band[r]`` (6 x 6b) and ``rhs[r]`` (6) are the rows of logical station ``base + r``;
    rows ``r >= split`` go to ``ovf_band[r - split]`` / ``ovf_rhs[r - split]`` instead (a
    thread's private rows, see :func:`build_points_parallel`). Processing stops before the
    first active point whose largest station lies beyond the window. Returns
    ``(next_point, status, point)``: status OK, or SINGULAR_POINT / BEHIND_CAMERA /
    BAD_LAYOUT with the offending point.

    Self-calibration (a border of ``ng = bord.shape[2]`` camera parameters; ``cal[camera,
    field]`` is the border column of a camera's field or -1, :func:`camera_partials`):
    ``bord[r]`` (6 x ng) are the border columns of band row ``r`` (``ovf_bord`` beside
    ``ovf_band``), ``cnn`` (ng x ng, full) and ``ccg`` (ng) the border's block and
    right-hand side, ``cdiag`` the diagonal of its unreduced block; every point is
    eliminated from them as from the band (docs/theory.md section 1c). ``ng = 0``: no border.

    ``dg`` (rows x npar, beside ``band``; ``ovf_dg`` beside ``ovf_band``): each station's
    diagonal of the unreduced normal matrix, ``sum p a_u^2`` over its rays (fixed parameters'
    columns 0), added in: the scaling of the Levenberg-Marquardt damping. None: not kept.

    ``keep_pt`` (chunk points x :data:`KEPT_POINT`) and ``keep_nbar`` (chunk observations x
    npar x 3), when given with rows: each point's system as linearised here
    (:func:`_keep_point`), for :func:`update_points` to back-solve from instead of
    linearising the point again.
    """
    cap = band.shape[0]
    npar = band.shape[1]
    nbar, a_all, l_all, w_all, st_all, nn, cc, lo, xyz, b_all, o_all = _workspace(max_rays, npar)
    g = np.empty((max_rays, npar, 3))
    nbt = np.empty((max_rays, 3, npar))
    h = np.empty(3)
    col = np.empty(3)
    tmp = np.empty(3)
    ninv = np.empty((3, 3))
    ng = bord.shape[2]
    slot = np.full(ng, -1, np.int64)     # border column -> its place among the point's
    tcols = np.empty(ng, np.int64)       # the border columns the point touches
    ngp = np.empty((ng, 3))              # Nbar of the border: sum p E' B
    ggp = np.empty((ng, 3))              # Ndd^-1 Nbar_g'
    e = np.empty((2, N_CALIBRATION))
    for j in range(j0, j_stop):
        if pt_active[j] != 0:
            continue
        if pt_smax[j] >= base + cap:
            return j, OK, -1
        k = _point_system(j, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start, pt_nobs,
                          obs_station, obs_xy, obs_sigma, obs_active, eo, cam_of_station,
                          cams, ctrl_mask, xyz, nbar, a_all, l_all, w_all,
                          st_all, nn, cc, b_all, o_all, lam, behind_ok, st_fixed)
        if k < 0:
            return j, BEHIND_CAMERA, j
        bw = band.shape[2] // npar
        for q in range(k):
            r = st_all[q] - base
            if r < 0 or r >= cap or st_all[q] - st_all[0] >= bw or (
                    q > 0 and st_all[q] < st_all[q - 1]) or r - split >= ovf_band.shape[0]:
                return j, BAD_LAYOUT, j
        if not _chol3(nn, lo):
            return j, SINGULAR_POINT, j
        _solve3(lo, cc, h)
        if keep_pt is not None and keep_pt.shape[0] > 0:
            _keep_point(j, keep_pt, keep_nbar, lo, cc, xyz, nn, nbar, pt_start, pt_nobs,
                        obs_active)
        if npar == 6:   # (the loops over a station's parameters unrolled)
            _inverse3(lo, ninv)
            _rays6(k, base, split, band, rhs, ovf_band, ovf_rhs, w_all, a_all, l_all, nbar,
                   h, ninv, g, nbt, st_all)
        else:
            for q in range(k):
                r = st_all[q] - base
                row = band[r] if r < split else ovf_band[r - split]
                rrow = rhs[r] if r < split else ovf_rhs[r - split]
                _ray_terms(q, w_all, a_all, l_all, nbar, h, lo, npar, row, rrow, g, col, tmp)
                for c in range(3):   # (Nbar transposed: the update below runs along its rows)
                    for v in range(npar):
                        nbt[q, c, v] = nbar[q, v, c]
        if dg is not None and dg.shape[0] > 0:
            for q in range(k):
                r = st_all[q] - base
                drow = dg[r] if r < split else ovf_dg[r - split]
                pq = w_all[q]
                for u in range(npar):
                    drow[u] += pq * (a_all[q, 0, u] * a_all[q, 0, u]
                                     + a_all[q, 1, u] * a_all[q, 1, u])
        # Schur complement into the band rows: M[s_q, s_t] -= G_q Nbar_t'
        if npar == 6:
            _schur6(k, base, split, band, ovf_band, st_all, g, nbar, nbt)
        else:
            for q in range(k):
                r = st_all[q] - base
                row = band[r] if r < split else ovf_band[r - split]
                for t in range(q, k):
                    off = npar * (st_all[t] - st_all[q])
                    for u in range(npar):   # (the rank-3 update, its three terms hoisted)
                        g0, g1, g2 = g[q, u, 0], g[q, u, 1], g[q, u, 2]
                        for v in range(npar):
                            row[u, off + v] -= g0 * nbt[t, 0, v] + g1 * nbt[t, 1, v] \
                                + g2 * nbt[t, 2, v]
                    if st_all[t] == st_all[q] and t != q:   # (two rays of one photo: both ways)
                        for u in range(npar):
                            for v in range(npar):
                                row[v, off + u] -= g[q, u, 0] * nbar[t, v, 0] \
                                    + g[q, u, 1] * nbar[t, v, 1] + g[q, u, 2] * nbar[t, v, 2]
        if ng > 0:
            _border_point(j, k, pt_kind, pt_csig, ctrl_mask, eo, cam_of_station, cams, cal, xyz,
                          a_all, l_all, w_all, st_all, g, lo, h, base, split, bord, ovf_bord,
                          cnn, ccg, cdiag, slot, tcols, ngp, ggp, e, b_all, o_all)
    return j_stop, OK, -1


@njit(cache=True, error_model="numpy", nogil=True)
def _add_border_rows(out, scale, e, cal_row, b_q):
    """``out[g] += scale (e[0, f] b_q[0] + e[1, f] b_q[1])`` for each calibrated field ``f``
    of a ray (``g = cal_row[f]``, its border column; ``e`` the ray's border partials,
    ``b_q`` its 2 x 3 partials by the point): the ray's share of ``Nbar_g = sum p E' B``."""
    for f in range(N_CALIBRATION):
        g = cal_row[f]
        if g < 0:
            continue
        for c in range(3):
            out[g, c] += scale * (e[0, f] * b_q[0, c] + e[1, f] * b_q[1, c])


@njit(cache=True, error_model="numpy", nogil=True)
def _ray_border(eo, xyz, c, cal_row, e, ox, oy):
    """The border partials ``e`` (2 x N_CALIBRATION) of a ray (measured at ``ox, oy``) of a
    camera with calibrated parameters (``cal_row``, the camera's row of ``cal``); False
    (nothing computed) when the camera is not calibrated."""
    used = False
    for f in range(N_CALIBRATION):
        if cal_row[f] >= 0:
            used = True
    if not used:
        return False
    camera_partials(eo, xyz, c, e, ox, oy)
    return True


@njit(cache=True, error_model="numpy", nogil=True)
def _border_point(j, k, pt_kind, pt_csig, ctrl_mask, eo, cam_of_station, cams, cal, xyz, a_all,
                  l_all, w_all, st_all, g, lo, h, base, split, bord, ovf_bord, cnn, ccg,
                  cdiag, slot, tcols, ngp, ggp, e, b_all, o_all):
    """Point ``j``'s share of the border (see :func:`build_points`): the direct terms of its
    ``k`` rays, ``p A'E`` into the border columns of their band rows, ``p E'E`` and ``p E'l``
    into the border block, then its elimination, ``-G_q Nbar_g'``, ``-Nbar_g Ndd^-1 Nbar_g'``
    and ``-Nbar_g Ndd^-1 cdd`` (``G_q = Nbar_q Ndd^-1`` and ``h = Ndd^-1 cdd`` come from
    the band's elimination)."""
    npar = a_all.shape[2]
    nt = 0
    for q in range(k):
        s = st_all[q]
        cam = cam_of_station[s]
        if not _ray_border(eo[s], xyz, cams[cam], cal[cam], e, o_all[q, 0], o_all[q, 1]):
            continue
        p = w_all[q]
        a = a_all[q]
        r = s - base
        brow = bord[r] if r < split else ovf_bord[r - split]
        for f in range(N_CALIBRATION):
            c1 = cal[cam, f]
            if c1 < 0:
                continue
            if slot[c1] < 0:
                slot[c1] = nt
                tcols[nt] = c1
                for c in range(3):
                    ngp[nt, c] = 0.0
                nt += 1
            sl = slot[c1]
            ex, ey = e[0, f], e[1, f]
            for u in range(npar):
                brow[u, c1] += p * (a[0, u] * ex + a[1, u] * ey)
            ccg[c1] += p * (ex * l_all[q, 0] + ey * l_all[q, 1])
            cdiag[c1] += p * (ex * ex + ey * ey)
            for c in range(3):
                ngp[sl, c] += p * (ex * b_all[q, 0, c] + ey * b_all[q, 1, c])
            for f2 in range(N_CALIBRATION):
                c2 = cal[cam, f2]
                if c2 >= 0:
                    cnn[c1, c2] += p * (ex * e[0, f2] + ey * e[1, f2])
    kind = pt_kind[j]
    for c in range(3):  # a fixed control component is no unknown (as in _point_system)
        if ctrl_mask[kind, c] and pt_csig[j, c] == 0.0:
            for t in range(nt):
                ngp[t, c] = 0.0
    for t in range(nt):
        _solve3(lo, ngp[t], ggp[t])
    for t in range(nt):
        c1 = tcols[t]
        x = 0.0
        for c in range(3):
            x += ngp[t, c] * h[c]
        ccg[c1] -= x
        for t2 in range(nt):
            x = 0.0
            for c in range(3):
                x += ggp[t, c] * ngp[t2, c]
            cnn[c1, tcols[t2]] -= x
    for q in range(k):
        r = st_all[q] - base
        brow = bord[r] if r < split else ovf_bord[r - split]
        for u in range(npar):
            for t in range(nt):
                x = 0.0
                for c in range(3):
                    x += g[q, u, c] * ngp[t, c]
                brow[u, tcols[t]] -= x
    for t in range(nt):
        slot[tcols[t]] = -1


@njit(cache=True, error_model="numpy", nogil=True, parallel=True)
def build_points_parallel(j0, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start, pt_nobs,
                          pt_smin, pt_smax, pt_active, obs_station, obs_xy, obs_sigma,
                          obs_active, eo, cam_of_station, cams, ctrl_mask, band, rhs, base,
                          max_rays, ovf_band, ovf_rhs, min_points, cal, bord, ovf_bord, cnn,
                          ccg, cdiag, lam=0.0, behind_ok=False, st_fixed=None, dg=None,
                          ovf_dg=None, keep_pt=None, keep_nbar=None):
    """:func:`build_points` for the points from ``j0`` that fit the window, on
    ``len(ovf_band)`` threads over station ranges.

    The points (sorted by first station) are cut into equal parts; part ``t`` owns the rows
    from its first point's first station up to the next part's, and writes the rows beyond
    (at most ``b`` of them) into its own buffer ``ovf_band[t]``, which is added to the window
    afterwards. Fewer than ``min_points`` points a thread are built on one thread. Same
    return value as :func:`build_points`. The border (``ng = bord.shape[2]`` columns) goes
    the same way: ``ovf_bord[t]`` beside ``ovf_band[t]``, and thread ``t`` adds into
    ``cnn[t]``, ``ccg[t]``, ``cdiag[t]`` (the caller sums them). The stations' diagonal
    ``dg`` (rows x npar, 0 rows: not kept; required, as ``ovf_dg``, threads x b x npar) the
    same way: ``ovf_dg[t]`` beside ``ovf_band[t]``. ``keep_pt``, ``keep_nbar``: as
    :func:`build_points` (every thread writes its own points' rows).
    """
    cap = band.shape[0]
    n_pts = pt_xyz.shape[0]
    j_end = n_pts
    for j in range(j0, n_pts):
        if pt_active[j] == 0 and pt_smax[j] >= base + cap:
            j_end = j
            break
    nthreads = ovf_band.shape[0]
    empty_b = ovf_band[0, :0]
    empty_r = ovf_rhs[0, :0]
    empty_g = ovf_bord[0, :0]
    empty_d = ovf_dg[0, :0]
    if nthreads < 2 or j_end - j0 < max(1, min_points) * nthreads:
        j, status, bad = build_points(j0, j_end, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot,
                                      pt_start, pt_nobs, pt_smax, pt_active, obs_station, obs_xy,
                                      obs_sigma, obs_active, eo, cam_of_station, cams,
                                      ctrl_mask, band, rhs, base, max_rays, cap,
                                      empty_b, empty_r, cal, bord, empty_g, cnn[0], ccg[0],
                                      cdiag[0], lam, behind_ok, st_fixed, dg, empty_d,
                                      keep_pt, keep_nbar)
        if status != OK or j < j_end:
            return j, status, bad
        return j_end, OK, -1
    cut = np.empty(nthreads + 1, np.int64)
    split = np.empty(nthreads, np.int64)
    for t in range(nthreads + 1):
        cut[t] = j0 + (j_end - j0) * t // nthreads
    for t in range(nthreads):
        split[t] = cap if t == nthreads - 1 else max(0, min(cap, pt_smin[cut[t + 1]] - base))
    res = np.zeros((nthreads, 3), np.int64)
    for t in prange(nthreads):
        ovf_band[t] = 0.0
        ovf_rhs[t] = 0.0
        ovf_bord[t] = 0.0
        ovf_dg[t] = 0.0
        ob = ovf_band[t] if t < nthreads - 1 else empty_b
        od = ovf_dg[t] if t < nthreads - 1 else empty_d
        orr = ovf_rhs[t] if t < nthreads - 1 else empty_r
        og = ovf_bord[t] if t < nthreads - 1 else empty_g
        j, status, bad = build_points(cut[t], cut[t + 1], pt_xyz, pt_kind, pt_ctrl, pt_csig,
                                      pt_rot, pt_start, pt_nobs, pt_smax, pt_active, obs_station,
                                      obs_xy, obs_sigma, obs_active, eo, cam_of_station, cams,
                                      ctrl_mask, band, rhs, base, max_rays,
                                      split[t], ob, orr, cal, bord, og, cnn[t], ccg[t],
                                      cdiag[t], lam, behind_ok, st_fixed, dg, od, keep_pt,
                                      keep_nbar)
        res[t, 0] = j
        res[t, 1] = status
        res[t, 2] = bad
    for t in range(nthreads):
        if res[t, 1] != OK:
            return res[t, 0], res[t, 1], res[t, 2]
        if res[t, 0] < cut[t + 1]:  # cannot happen: all points fit the window
            return res[t, 0], BAD_LAYOUT, res[t, 0]
    for t in range(nthreads - 1):
        for r in range(ovf_band.shape[1]):
            rr = split[t] + r
            if rr >= cap:
                break
            band[rr] += ovf_band[t, r]
            rhs[rr] += ovf_rhs[t, r]
            bord[rr] += ovf_bord[t, r]
            if dg.shape[0] > 0:
                dg[rr] += ovf_dg[t, r]
    return j_end, OK, -1


@njit(cache=True, error_model="numpy", nogil=True, parallel=True)
def update_points_parallel(nthreads, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start,
                           pt_nobs, pt_active, obs_station, obs_xy, obs_sigma, obs_active, eo,
                           delta, cam_of_station, cams, ctrl_mask, max_rays, xyz_out,
                           resid_out, stats, lam=0.0, behind_ok=False, cams_new=None,
                           dtheta=None, st_fixed=None, eo_next=None, keep_pt=None,
                           keep_nbar=None):
    """:func:`update_points` on ``nthreads`` threads: the points cut into that many runs of
    about equal observations, each with its own statistics, added in run order afterwards
    (the maximum for ``stats[5]``, the first run's bad point for ``stats[7:9]``). A point
    writes only its own coordinates and its own observations' residuals. ``keep_pt``,
    ``keep_nbar``: the chunk's points' systems as the build kept them (see
    :func:`update_points`; no rows: none)."""
    n = pt_xyz.shape[0]
    nt = max(1, min(nthreads, n))
    cut = _runs(pt_start, pt_nobs, nt)
    part = np.zeros((nt, stats.shape[0]))
    kp = np.empty((0, KEPT_POINT)) if keep_pt is None else keep_pt
    kn = np.empty((0, delta.shape[1], 3)) if keep_nbar is None else keep_nbar
    for t in prange(nt):
        a, b = cut[t], cut[t + 1]
        if b > a:
            update_points(pt_xyz[a:b], pt_kind[a:b], pt_ctrl[a:b], pt_csig[a:b], pt_rot[a:b],
                          pt_start[a:b], pt_nobs[a:b], pt_active[a:b], obs_station, obs_xy,
                          obs_sigma, obs_active, eo, delta, cam_of_station, cams, ctrl_mask,
                          max_rays, xyz_out[a:b], resid_out, part[t], lam, behind_ok,
                          cams_new, dtheta, st_fixed, eo_next, kp[a:b], kn)
    for t in range(nt):
        if part[t, 7] != 0.0 and stats[7] == 0.0:
            stats[7] = part[t, 7] + cut[t]
            stats[8] = part[t, 8]
        for c in range(stats.shape[0]):
            if c == 5:
                stats[5] = max(stats[5], part[t, 5])
            elif c != 7 and c != 8:
                stats[c] += part[t, c]


@njit(cache=True, error_model="numpy", nogil=True)
def update_points(pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start, pt_nobs, pt_active,
                  obs_station, obs_xy, obs_sigma, obs_active, eo, delta, cam_of_station, cams,
                  ctrl_mask, max_rays, xyz_out, resid_out, stats, lam=0.0,
                  behind_ok=False, cams_new=None, dtheta=None, st_fixed=None, eo_next=None,
                  keep_pt=None, keep_nbar=None):
    """Back-solve point corrections and compute residuals for a chunk of points.

    ``eps_j = Ndd_j^-1 (cdd_j - sum_s Nbar_s' delta_s)`` with the system linearised at the
    values the normals were built with (``eo``, ``pt_xyz``); the residuals
    ``v = computed - observed`` are then evaluated at the new values (``eo_next``, the
    stations after the step, :func:`sapgo.adjust.next_orientations`; required, and
    ``xyz_out``). ``stats`` accumulates: 0 vPv image, 1 vPv control, 2 sum vx^2, 3 sum vy^2,
    4 image rays, 5 max |eps|, 6 control components, 7 bad point (index+1) or 0,
    8 its status code, 9 sum of c' Ndd^-1 c, 10 sum of D eps^2 (undamped diagonal).
    ``lam``: the Levenberg-Marquardt damping the normals were built with.
    ``delta`` has a row of 6 or 9 parameters per station; with 9, ``cams_new`` holds the camera
    rows moved by the intrinsics' corrections (one camera per photo), for the residuals.
    ``dtheta`` (camera rows x N_CALIBRATION): the self-calibration step of each camera's border parameters
    (:func:`sapgo.geometry.camera_partials`; zero where not adjusted), which enters the
    back-solution as ``- Nbar_g' dtheta``; ``cams_new`` then holds the moved cameras.
    ``keep_pt``, ``keep_nbar`` (with rows, and no ``dtheta``): each point's system as the
    build of the same state and damping kept it (:func:`_keep_point`), read instead of
    linearising the point again: the same numbers.
    """
    npar = delta.shape[1]
    e = np.empty((2, N_CALIBRATION))
    nbar, a_all, l_all, w_all, st_all, nn, cc, lo, xyz, b_all, o_all = _workspace(max_rays, npar)
    cams_v = cams if cams_new is None else cams_new
    eps = np.empty(3)
    e_new = np.empty(eo_next.shape[1])   # (with its rotation: geometry.with_rotations)
    # per camera row: its fields up to the last one the step moves (0: none)
    moved = np.zeros(cams.shape[0], np.int64)
    if dtheta is not None:
        for c in range(dtheta.shape[0]):
            for f in range(N_CALIBRATION):
                if dtheta[c, f] != 0.0:
                    moved[c] = f + 1
    kept = dtheta is None and keep_pt is not None and keep_pt.shape[0] > 0
    for j in range(pt_xyz.shape[0]):
        if pt_active[j] != 0:
            xyz_out[j] = pt_xyz[j]
            continue
        if kept:
            k = _kept_point(j, keep_pt, keep_nbar, pt_start, pt_nobs, obs_station, obs_active,
                            lo, cc, xyz, nn, nbar, st_all)
        else:
            k = _point_system(j, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start, pt_nobs,
                              obs_station, obs_xy, obs_sigma, obs_active, eo, cam_of_station,
                              cams, ctrl_mask, xyz, nbar, a_all, l_all, w_all,
                              st_all, nn, cc, b_all, o_all, lam, behind_ok, st_fixed)
        if k < 0 or not (kept or _chol3(nn, lo)):
            stats[7] = j + 1
            stats[8] = BEHIND_CAMERA if k < 0 else SINGULAR_POINT
            return
        # the step's predicted cost decrease (Levenberg-Marquardt's gain ratio): the point's
        # share c' Ndd^-1 c (stats 9) and D eps^2 with D the undamped diagonal (stats 10)
        _solve3(lo, cc, eps)
        for c in range(3):
            stats[9] += cc[c] * eps[c]
        for q in range(k):
            s = st_all[q]
            for c in range(3):
                x = 0.0
                for u in range(npar):
                    x += nbar[q, u, c] * delta[s, u]
                cc[c] -= x
        if dtheta is not None:
            kind = pt_kind[j]
            for q in range(k):
                s = st_all[q]
                cam = cam_of_station[s]
                if moved[cam] == 0:
                    continue
                camera_partials(eo[s], xyz, cams[cam], e, o_all[q, 0], o_all[q, 1])
                dx = 0.0
                dy = 0.0
                for f in range(moved[cam]):
                    dx += e[0, f] * dtheta[cam, f]
                    dy += e[1, f] * dtheta[cam, f]
                p = w_all[q]
                for c in range(3):
                    if not (ctrl_mask[kind, c] and pt_csig[j, c] == 0.0):
                        cc[c] -= p * (b_all[q, 0, c] * dx + b_all[q, 1, c] * dy)
        _solve3(lo, cc, eps)
        if lam > 0.0:
            for c in range(3):
                stats[10] += min(max(nn[c, c] / (1.0 + lam), 1e-6), 1e32) * eps[c] * eps[c]
        kind = pt_kind[j]
        for c in range(3):
            xyz_out[j, c] = xyz[c] + eps[c]
            if abs(eps[c]) > stats[5]:
                stats[5] = abs(eps[c])
        for c in range(3):
            if ctrl_mask[kind, c] and pt_csig[j, c] > 0.0:
                v = 0.0
                for q in range(3):
                    v += pt_rot[j, c, q] * (xyz_out[j, q] - pt_ctrl[j, q])
                stats[1] += v * v / (pt_csig[j, c] * pt_csig[j, c])
                stats[6] += 1
        for i in range(pt_start[j], pt_start[j] + pt_nobs[j]):
            s = obs_station[i]
            cam = cam_of_station[s]
            for u in range(e_new.shape[0]):   # (the attitude turned by the rotation vector)
                e_new[u] = eo_next[s, u]
            # rejected observations get their residual too (how far off they are); only the
            # active ones count in the statistics
            x, y = project(e_new, xyz_out[j], cams_v[cam])
            ox, oy = observed(obs_xy[i, 0], obs_xy[i, 1], cams_v[cam])
            vx = x - ox
            vy = y - oy
            if not obs_active[i]:
                ok = math.isfinite(vx) and math.isfinite(vy)
                resid_out[i, 0] = vx if ok else 0.0
                resid_out[i, 1] = vy if ok else 0.0
                continue
            resid_out[i, 0] = vx
            resid_out[i, 1] = vy
            p = 1.0 / (obs_sigma[i] * obs_sigma[i])
            stats[0] += p * (vx * vx + vy * vy)
            stats[2] += vx * vx
            stats[3] += vy * vy
            stats[4] += 1


@njit(cache=True, error_model="numpy", nogil=True)
def _runs(pt_start, pt_nobs, nt):
    """Cut points ``0 .. n`` into ``nt`` runs of about equal observations: the runs'
    bounds (nt + 1)."""
    n = pt_start.shape[0]
    cut = np.empty(nt + 1, np.int64)
    cut[0] = 0
    cut[nt] = n
    total = pt_start[n - 1] + pt_nobs[n - 1] - pt_start[0] if n > 0 else 0
    j = 0
    for t in range(1, nt):
        want = pt_start[0] + total * t // nt
        while j < n and pt_start[j] < want:
            j += 1
        cut[t] = j
    return cut


@njit(cache=True, error_model="numpy", nogil=True)
def _thread_runs(nthreads, pt_start, pt_nobs):
    """:func:`_runs` for ``nthreads`` threads (at most one a point): one run where the
    points' observations do not follow each other (each point's after the one before)."""
    n = pt_start.shape[0]
    nt = max(1, min(nthreads, n))
    for j in range(1, n):
        if pt_start[j] < pt_start[j - 1] + pt_nobs[j - 1]:
            nt = 1
    return _runs(pt_start, pt_nobs, nt)


@njit(cache=True, error_model="numpy", nogil=True, parallel=True)
def point_sigmas_parallel(nthreads, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start,
                          pt_nobs, pt_active, obs_station, obs_xy, obs_sigma, obs_active, eo,
                          cam_of_station, cams, ctrl_mask, max_rays, zb, base, res, out, out_r,
                          out_w, npar=6, cal=None, xw=None, xbase=0, sig_b=None, st_fixed=None,
                          behind_ok=False, obs_predict=None):
    """:func:`point_sigmas` on ``nthreads`` threads: the points cut into runs of about equal
    observations (:func:`_runs`), each run given its own points' rows and its own
    observations' rows (a point's observations follow each other, the points' in turn);
    observations of no run 0. Points whose observations do not follow each other in that
    way: one thread."""
    n = pt_xyz.shape[0]
    nt = max(1, min(nthreads, n))
    for j in range(1, n):
        if pt_start[j] < pt_start[j - 1] + pt_nobs[j - 1]:
            nt = 1
    if nt < 2:
        point_sigmas(pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start, pt_nobs, pt_active,
                     obs_station, obs_xy, obs_sigma, obs_active, eo, cam_of_station, cams,
                     ctrl_mask, max_rays, zb, base, res, out, out_r, out_w, npar, cal, xw,
                     xbase, sig_b, st_fixed, behind_ok, obs_predict)
        return
    out_r[:, :] = 0.0
    out_w[:, :] = 0.0
    cut = _runs(pt_start, pt_nobs, nt)
    for t in prange(nt):
        a, b = cut[t], cut[t + 1]
        if b > a:
            o0, o1 = pt_start[a], pt_start[b - 1] + pt_nobs[b - 1]
            if obs_predict is None:
                point_sigmas(pt_xyz[a:b], pt_kind[a:b], pt_ctrl[a:b], pt_csig[a:b],
                             pt_rot[a:b], pt_start[a:b] - o0, pt_nobs[a:b], pt_active[a:b],
                             obs_station[o0:o1], obs_xy[o0:o1], obs_sigma[o0:o1],
                             obs_active[o0:o1], eo, cam_of_station, cams, ctrl_mask,
                             max_rays, zb, base, res[o0:o1], out[a:b], out_r[o0:o1],
                             out_w[o0:o1], npar, cal, xw, xbase, sig_b, st_fixed, behind_ok)
            else:
                point_sigmas(pt_xyz[a:b], pt_kind[a:b], pt_ctrl[a:b], pt_csig[a:b],
                             pt_rot[a:b], pt_start[a:b] - o0, pt_nobs[a:b], pt_active[a:b],
                             obs_station[o0:o1], obs_xy[o0:o1], obs_sigma[o0:o1],
                             obs_active[o0:o1], eo, cam_of_station, cams, ctrl_mask,
                             max_rays, zb, base, res[o0:o1], out[a:b], out_r[o0:o1],
                             out_w[o0:o1], npar, cal, xw, xbase, sig_b, st_fixed, behind_ok,
                             obs_predict[o0:o1])


@njit(cache=True, error_model="numpy", nogil=True)
def point_sigmas(pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start, pt_nobs, pt_active,
                 obs_station, obs_xy, obs_sigma, obs_active, eo, cam_of_station, cams,
                 ctrl_mask, max_rays, zb, base, res, out, out_r, out_w, npar=6, cal=None,
                 xw=None, xbase=0, sig_b=None, st_fixed=None, behind_ok=False,
                 obs_predict=None):
    """Precision of the points of a chunk and the quality of their observations (stations
    of ``npar`` parameters: 6, or 9 with the photo's intrinsics). ``behind_ok``: a point
    behind a camera is a point all the same (BAL problems), as in the build.

    ``out`` (n x 6): the points' cofactor standard deviations (multiply by sigma0) and the
    correlations of X-Y, X-Z and Y-Z, from the point block of the inverse of the full normal
    matrix,

        Q_pp = G + G (sum_q sum_r Nbar_q' Z[s_q, s_r] Nbar_r) G,    G = N_pp^-1,

    ``Z`` the stations' cofactors inside the band (``zb[k - base, j - base]``, the window of
    :func:`sapgo.solve.band.covariance_blocks`); fixed components and excluded points 0,
    singular points nan. ``out_r`` (observations x 3): redundancy numbers ``r = q_vv / sigma^2``
    of x and y and the off-diagonal ``q_xy / sigma^2`` of the observation's 2 x 2 block of the
    redundancy matrix, with ``Q_vv = sigma^2 I - [A B] Q [A B]'``
    (``Q_sp = -sum_t Z[s, t] Nbar_t G``);
    ``out_w`` (observations x 3): normalised residuals ``v / (sigma sqrt(r))`` of the residuals
    ``res`` and the observation's 2-D statistic ``sqrt(v' Q_vv^+ v)`` (divide by sigma0);
    inactive observations 0, except those ``obs_predict`` marks (observations rejected in
    the run, their station's rows in ``zb``): their residual predicted from the others,
    ``Q_v = sigma^2 I + [A B] Q [A B]'`` (the observation outside the adjustment), gives
    ``out_w`` the normalised residuals ``v / sqrt(q_v)`` and the 2-D statistic
    ``sqrt(v' Q_v^-1 v)``, which in the linear model equals the statistic the observation
    would get brought back alone, with sigma0 of that adjustment (docs/theory.md, "Snooping
    in batches"); ``out_r`` stays 0.

    Self-calibration (docs/theory.md section 1c): ``cal`` as in :func:`build_points`,
    ``xw[s - xbase]`` (k x ng) the rows of ``X = M^-1 B`` of the stations, ``sig_b`` (ng x ng)
    the border's cofactors ``S^-1``. The inverse of the bordered matrix adds to the point
    ``T += V' S^-1 V`` with ``V = sum_q X[s_q]' Nbar_q - Nbar_g``, and to an observation
    with design row ``[A, B, E]`` the terms of ``cov(delta_s) += X_s S^-1 X_s'``,
    ``cov(delta_s, theta) = -X_s S^-1``, ``cov(eps, theta) = G V' S^-1``,
    ``cov(delta_s, eps) -= X_s S^-1 V G``, ``cov(theta) = S^-1``."""
    nbar, a_all, l_all, w_all, st_all, nn, cc, lo, xyz, b_all, o_all = _workspace(max_rays, npar)
    g = np.empty((3, 3))
    t = np.empty((3, 3))
    qpp = np.empty((3, 3))
    qsp = np.empty((npar, 3))
    zn = np.empty((npar, 3))
    zn_all = np.empty((max_rays, npar, 3))   # W of each ray of the point
    zn1 = np.empty((1, npar, 3))
    e = np.empty(3)
    col = np.empty(3)
    a = np.empty((2, npar))
    b = np.empty((2, 3))
    qv = np.empty((2, 2))
    zq = np.empty((npar, 2))
    bq = np.empty((3, 2))
    ng = 0 if sig_b is None else sig_b.shape[0]
    vb = np.zeros((ng, 3))        # V = sum_q X[s_q]' Nbar_q - Nbar_g
    sv = np.zeros((ng, 3))        # S^-1 V
    eb = np.zeros((2, ng))        # the observation's border partials
    ec = np.empty((2, N_CALIBRATION))
    xs_s = np.zeros((npar, ng))   # X_s S^-1
    for i in range(out_r.shape[0]):
        for c in range(out_r.shape[1]):
            out_r[i, c] = 0.0
        for c in range(out_w.shape[1]):
            out_w[i, c] = 0.0
    for j in range(pt_xyz.shape[0]):
        for c in range(out.shape[1]):
            out[j, c] = 0.0
        if pt_active[j] != 0:
            continue
        k = _point_system(j, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start, pt_nobs,
                          obs_station, obs_xy, obs_sigma, obs_active, eo, cam_of_station,
                          cams, ctrl_mask, xyz, nbar, a_all, l_all, w_all, st_all, nn, cc, b_all, o_all,
                          0.0, behind_ok, st_fixed)
        if k < 0 or not _chol3(nn, lo):
            for c in range(out.shape[1]):
                out[j, c] = np.nan
            continue
        for c in range(3):
            e[:] = 0.0
            e[c] = 1.0
            _solve3(lo, e, col)
            for r in range(3):
                g[r, c] = col[r]
        # W_q = sum_r Z[s_q, s_r] Nbar_r for every ray (npar x 3; the observations' Q_sp
        # below takes it too), then T = sum_q Nbar_q' W_q: k^2 products of 6 x 6 by 6 x 3
        for q in range(k):
            _station_w(zb, npar * st_all[q] - base, st_all, nbar, k, npar, base, zn_all, q)
        t[:, :] = 0.0
        for q in range(k):
            for a6 in range(npar):
                for c1 in range(3):
                    nq = nbar[q, a6, c1]
                    for c2 in range(3):
                        t[c1, c2] += nq * zn_all[q, a6, c2]
        if ng > 0:
            vb[:, :] = 0.0
            for q in range(k):  # V: X' Nbar over the rays, minus Nbar_g (direct terms)
                s = st_all[q]
                xr = s - xbase
                for u in range(npar):
                    for cg in range(ng):
                        xv = xw[xr, u, cg]
                        for c in range(3):
                            vb[cg, c] += xv * nbar[q, u, c]
                cam = cam_of_station[s]
                if not _ray_border(eo[s], xyz, cams[cam], cal[cam], ec, o_all[q, 0],
                                   o_all[q, 1]):
                    continue
                _add_border_rows(vb, -w_all[q], ec, cal[cam], b_all[q])
            kind = pt_kind[j]
            for c in range(3):  # a fixed component is no unknown
                if ctrl_mask[kind, c] and pt_csig[j, c] == 0.0:
                    for cg in range(ng):
                        vb[cg, c] = 0.0
            for cg in range(ng):
                for c in range(3):
                    x = 0.0
                    for c2 in range(ng):
                        x += sig_b[cg, c2] * vb[c2, c]
                    sv[cg, c] = x
            for c1 in range(3):
                for c2 in range(3):
                    x = 0.0
                    for cg in range(ng):
                        x += vb[cg, c1] * sv[cg, c2]
                    t[c1, c2] += x
        for c1 in range(3):
            for c2 in range(3):
                v = g[c1, c2]
                for p1 in range(3):
                    for p2 in range(3):
                        v += g[c1, p1] * t[p1, p2] * g[p2, c2]
                qpp[c1, c2] = v
        kind = pt_kind[j]
        for c in range(3):
            if not (ctrl_mask[kind, c] and pt_csig[j, c] == 0.0):
                out[j, c] = math.sqrt(max(qpp[c, c], 0.0))
        for m in range(3):
            c1, c2 = (0, 0, 1)[m], (1, 2, 2)[m]
            d = qpp[c1, c1] * qpp[c2, c2]
            out[j, 3 + m] = qpp[c1, c2] / math.sqrt(d) if d > 0.0 else 0.0
        # the observations: the k-th active ray of the point is the k-th active observation
        q = 0
        for i in range(pt_start[j], pt_start[j] + pt_nobs[j]):
            pred = False
            if not obs_active[i]:
                if obs_predict is None or not obs_predict[i]:
                    continue
                pred = True   # (rejected: its residual predicted from the k rays)
            s = obs_station[i]
            if pred:   # (an active ray's A and B are the point system's, q-th active ray)
                linearize(eo[s], xyz, cams[cam_of_station[s]], a, b)
                if st_fixed is not None and s < st_fixed.shape[0]:
                    fixed_columns(a, st_fixed[s])
            else:
                for m in range(2):
                    for a6 in range(npar):
                        a[m, a6] = a_all[q, m, a6]
                    for c in range(3):
                        b[m, c] = b_all[q, m, c]
            for c in range(3):  # a fixed component is no unknown (qpp holds a placeholder)
                if ctrl_mask[kind, c] and pt_csig[j, c] == 0.0:
                    b[0, c] = 0.0
                    b[1, c] = 0.0
            sq = npar * s - base
            # Q_sp = -(sum_r Z[s, s_r] Nbar_r) G: W of this ray (s = st_all[q]); of a
            # predicted observation's station, summed here
            if pred:
                _station_w(zb, sq, st_all, nbar, k, npar, base, zn1, 0)
                for a6 in range(npar):
                    for c in range(3):
                        zn[a6, c] = zn1[0, a6, c]
            else:
                for a6 in range(npar):
                    for c in range(3):
                        zn[a6, c] = zn_all[q, a6, c]
            if ng > 0:  # zn += X_s S^-1 V; the border's partials of the observation
                xr = s - xbase
                for a6 in range(npar):
                    for cg in range(ng):
                        x = 0.0
                        for c2 in range(ng):
                            x += xw[xr, a6, c2] * sig_b[c2, cg]
                        xs_s[a6, cg] = x
                    for c in range(3):
                        x = 0.0
                        for cg in range(ng):
                            x += xw[xr, a6, cg] * sv[cg, c]
                        zn[a6, c] += x
                eb[:, :] = 0.0
                cam = cam_of_station[s]
                camera_partials(eo[s], xyz, cams[cam], ec, obs_xy[i, 0], obs_xy[i, 1])
                for f in range(N_CALIBRATION):
                    cg = cal[cam, f]
                    if cg >= 0:
                        eb[0, cg] = ec[0, f]
                        eb[1, cg] = ec[1, f]
            for a6 in range(npar):
                for c in range(3):
                    v = 0.0
                    for p1 in range(3):
                        v -= zn[a6, p1] * g[p1, c]
                    qsp[a6, c] = v
            sig2 = obs_sigma[i] * obs_sigma[i]
            # [A B] Q [A B]' = A Z A' + A Q_sp B' + B Q_sp' A' + B Q_pp B' (Z = Z[s, s]),
            # element (m, m2) = a_m . zq_m2 + a_m2 . zq_m + b_m . bq_m2 with the columns
            # zq = Z A' / 2 + Q_sp B' (npar x 2) and bq = Q_pp B' (3 x 2): about 170
            # products an observation of 6 parameters instead of about 490 (with A and
            # B of the point's system, not linearised again: 1 000 photos, the points'
            # pass 8.1 against 9.7 ms on one thread, measured)
            for a6 in range(npar):
                z0 = 0.0
                z1 = 0.0
                for b6 in range(npar):
                    z = zb[sq + a6, sq + b6]
                    z0 += z * a[0, b6]
                    z1 += z * a[1, b6]
                y0 = 0.0
                y1 = 0.0
                for c in range(3):
                    y0 += qsp[a6, c] * b[0, c]
                    y1 += qsp[a6, c] * b[1, c]
                zq[a6, 0] = 0.5 * z0 + y0
                zq[a6, 1] = 0.5 * z1 + y1
            for c1 in range(3):
                bq[c1, 0] = qpp[c1, 0] * b[0, 0] + qpp[c1, 1] * b[0, 1] + qpp[c1, 2] * b[0, 2]
                bq[c1, 1] = qpp[c1, 0] * b[1, 0] + qpp[c1, 1] * b[1, 1] + qpp[c1, 2] * b[1, 2]
            for m in range(2):
                for m2 in range(m, 2):
                    cmm = 0.0
                    for a6 in range(npar):
                        cmm += a[m, a6] * zq[a6, m2] + a[m2, a6] * zq[a6, m]
                    for c1 in range(3):
                        cmm += b[m, c1] * bq[c1, m2]
                    if ng > 0:
                        cmm += _border_terms(m, m2, a, b, eb, xw[s - xbase], xs_s, sv, g,
                                             sig_b)
                    qv[m, m2] = (sig2 if m == m2 else 0.0) + (cmm if pred else -cmm)
                if not pred:
                    out_r[i, m] = qv[m, m] / sig2
            if not pred:
                out_r[i, 2] = qv[0, 1] / sig2
            for m in range(2):
                qvv = qv[m, m]
                out_w[i, m] = res[i, m] / math.sqrt(qvv) if qvv > 0.0 else 0.0
            # the observation's 2-D test: sqrt(v' Q_vv^+ v) (pseudo-inverse: a two-ray point
            # leaves its observations one degree of freedom, Q_vv of rank 1)
            vx, vy = res[i, 0], res[i, 1]
            det = qv[0, 0] * qv[1, 1] - qv[0, 1] * qv[0, 1]
            tr = qv[0, 0] + qv[1, 1]
            if det > 1e-8 * tr * tr:
                t2 = (qv[1, 1] * vx * vx - 2.0 * qv[0, 1] * vx * vy + qv[0, 0] * vy * vy) / det
            elif tr > 0.0:
                t2 = (qv[0, 0] * vx * vx + 2.0 * qv[0, 1] * vx * vy + qv[1, 1] * vy * vy) / (
                    tr * tr)
            else:
                t2 = 0.0
            out_w[i, 2] = math.sqrt(max(t2, 0.0))
            if not pred:
                q += 1


@njit(cache=True, error_model="numpy", nogil=True)
def _station_w(zb, sq, st_all, nbar, k, npar, base, out, q):
    """``out[q] = sum_r Z[s, s_r] Nbar_r`` (npar x 3) over a point's ``k`` rays, ``Z``'s rows
    of the station ``s`` from ``zb[sq]`` (:func:`point_sigmas`)."""
    for a6 in range(npar):
        w0 = 0.0
        w1 = 0.0
        w2 = 0.0
        for r in range(k):
            sr = npar * st_all[r] - base
            for b6 in range(npar):
                z = zb[sq + a6, sr + b6]
                w0 += z * nbar[r, b6, 0]
                w1 += z * nbar[r, b6, 1]
                w2 += z * nbar[r, b6, 2]
        out[q, a6, 0] = w0
        out[q, a6, 1] = w1
        out[q, a6, 2] = w2


@njit(cache=True, error_model="numpy")
def _border_terms(m, m2, a, b, eb, xs, xs_s, sv, g, sig_b):
    """The border's share of ``[A B E] Q [A B E]'`` (rows ``m, m2``) for an observation at a
    station with ``X_s`` (``xs``), ``X_s S^-1`` (``xs_s``), ``S^-1 V`` (``sv``): ``A X_s S^-1
    X_s' A'`` and, both ways, ``A cov(delta_s, theta) E' = -A X_s S^-1 E'``,
    ``B cov(eps, theta) E' = B G V' S^-1 E'``, then ``E S^-1 E'``."""
    npar = a.shape[1]
    ng = eb.shape[1]
    x = 0.0
    for a6 in range(npar):
        for b6 in range(npar):
            z = 0.0
            for cg in range(ng):
                z += xs_s[a6, cg] * xs[b6, cg]
            x += a[m, a6] * z * a[m2, b6]
    for cg in range(ng):
        # A cov(delta, theta) and B cov(eps, theta), rows m and m2
        am = 0.0
        am2 = 0.0
        for a6 in range(npar):
            am -= a[m, a6] * xs_s[a6, cg]
            am2 -= a[m2, a6] * xs_s[a6, cg]
        bm = 0.0
        bm2 = 0.0
        for c1 in range(3):
            gv = 0.0
            for c2 in range(3):
                gv += g[c1, c2] * sv[cg, c2]
            bm += b[m, c1] * gv
            bm2 += b[m2, c1] * gv
        x += (am + bm) * eb[m2, cg] + (am2 + bm2) * eb[m, cg]
        for cg2 in range(ng):
            x += eb[m, cg] * sig_b[cg, cg2] * eb[m2, cg2]
    return x


class PointChunk:
    """The arrays of a chunk of points and their observations, ready for the kernels."""

    __slots__ = ("start", "stop", "o0", "o1", "xyz", "kind", "ctrl", "csig", "rot", "pt_start",
                 "nobs", "smax", "smin", "active", "obs_station", "obs_xy", "obs_sigma",
                 "obs_active", "max_rays")

    def __init__(self, project, start, stop, xyz, camera, cam_sigma, frame=None, rejected=None,
                 rejected_points=None):
        # kept for the run (Project.keep_point_chunks): the first chunk of these points, for
        # this camera table and frame (another asks afresh, and is not kept)
        kept = getattr(project, "point_chunks", None)
        entry = kept.get((start, stop)) if kept is not None else None
        same = (entry is not None and entry[0] is camera and entry[1] is cam_sigma
                and entry[2] is frame)
        base = entry[3] if same else None
        if base is None and entry is None and kept:   # a part of a kept chunk (views)
            base = _kept_part(kept, start, stop, camera, cam_sigma, frame)
        if base is None:
            base = _chunk_arrays(project, start, stop, camera, cam_sigma, frame)
            size = sum(a.nbytes for a in base if isinstance(a, np.ndarray))
            if kept is not None and entry is None and project.point_chunk_room >= size:
                kept[(start, stop)] = (camera, cam_sigma, frame, base)
                project.point_chunk_room -= size
        (self.o0, self.o1, self.kind, self.ctrl, self.csig, self.rot, self.pt_start, self.nobs,
         self.smax, self.smin, self.active, self.obs_station, self.obs_xy, self.obs_sigma,
         self.obs_active, self.max_rays) = base
        self.start, self.stop = start, stop
        self.xyz = np.ascontiguousarray(xyz, dtype=np.float64)
        if rejected is not None and len(rejected):  # rejected in this run (data snooping)
            lo, hi = np.searchsorted(rejected, [self.o0, self.o1])
            if hi > lo:
                self.obs_active = self.obs_active.copy()   # (never the kept one)
                self.obs_active[rejected[lo:hi] - self.o0] = False
        if rejected_points is not None and len(rejected_points):
            lo, hi = np.searchsorted(rejected_points, [start, stop])
            if hi > lo:
                self.active = self.active.copy()
                self.active[rejected_points[lo:hi] - start] = 1


def _kept_part(kept, start, stop, camera, cam_sigma, frame):
    """:func:`_chunk_arrays` of points ``start .. stop`` as views of a kept chunk that holds
    them all (read for the same cameras and frame), or None. (The precision pass on the
    tree asks node by node for parts of the build's chunks.)"""
    for (a, b), (cam, sig, fr, base) in list(kept.items()):   # (another thread may add)
        if a <= start and stop <= b and cam is camera and sig is cam_sigma and fr is frame:
            break
    else:
        return None
    (o0, _, kind, ctrl, csig, rot, pt_start, nobs, smax, smin, active, obs_station,
     obs_xy, obs_sigma, obs_active, max_rays) = base
    i, j = start - a, stop - a
    q0 = int(pt_start[i]) if j > i else 0
    q1 = int(pt_start[j - 1] + nobs[j - 1]) if j > i else 0
    return (o0 + q0, o0 + q1, kind[i:j], ctrl[i:j], csig[i:j], rot[i:j], pt_start[i:j] - q0,
            nobs[i:j], smax[i:j], smin[i:j], active[i:j], obs_station[q0:q1], obs_xy[q0:q1],
            obs_sigma[q0:q1], obs_active[q0:q1], max_rays)


#: Bytes of :class:`PointChunk`'s arrays a point and an observation (kept for a run by
#: :meth:`sapgo.project.Project.keep_point_chunks`).
CHUNK_POINT_BYTES = 8 + 24 + 24 + 72 + 8 + 8 + 8 + 8 + 8
CHUNK_OBS_BYTES = 8 + 16 + 8 + 1


def _chunk_arrays(project, start, stop, camera, cam_sigma, frame):
    """:class:`PointChunk`'s arrays of points ``start .. stop`` (all but the coordinates),
    before the run's rejections: ``(o0, o1, kind, ctrl, csig, rot, pt_start, nobs, smax,
    smin, active, obs_station, obs_xy, obs_sigma, obs_active, max_rays)``."""
    pts = project.read("points", start, stop)
    o0 = int(pts["obs_start"][0]) if len(pts) else 0
    o1 = int(pts["obs_start"][-1] + pts["n_obs"][-1]) if len(pts) else 0
    obs = project.read("observations", o0, o1)
    c = np.ascontiguousarray
    nobs = c(pts["n_obs"], dtype=np.int64)
    return (o0, o1, c(pts["kind"], dtype=np.int64), c(pts["control"]),
            c(pts["control_sigma"]), control_rotations(pts["kind"], pts["control"], frame),
            c(pts["obs_start"] - o0), nobs, c(pts["station_max"]), c(pts["station_min"]),
            c(pts["status"], dtype=np.int64), c(obs["station"]),
            c(np.column_stack([obs["x"], obs["y"]])),
            # sigma 0: the standard error of the station's camera
            c(np.where(obs["sigma"] > 0, obs["sigma"], cam_sigma[camera[obs["station"]]])),
            c(obs["status"] == STATUS_ACTIVE), int(max(1, nobs.max() if len(nobs) else 1)))


def control_rotations(kind, control, frame=None):
    """Per point, the rotation from the frame's axes to the axes its control sigmas (and
    check-point errors) are along (n x 3 x 3): the identity in a local frame, east, north, up
    at the point in a frame with a CRS (docs/theory.md section 1a)."""
    rot = np.zeros((len(kind), 3, 3))
    rot[:, [0, 1, 2], [0, 1, 2]] = 1.0
    if frame is not None and frame.kind != "local space rectangular":
        ctrl = np.flatnonzero((kind >= 1) & (kind <= 4))
        if len(ctrl):
            r, _ = frame._frame_rotation()
            rot[ctrl] = frame._station_rotations(control[ctrl]) @ r.T
    return np.ascontiguousarray(rot)


#: Points a thread at least, for the build to run on several threads.
PARALLEL_MIN_POINTS = 32

CTRL_MASK = np.ascontiguousarray(CONTROL_MASK.astype(np.int64))


@njit(cache=True, error_model="numpy")
def point_costs(pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start, pt_nobs, pt_active,
                obs_station, obs_xy, obs_sigma, obs_active, eo, cam_of_station, cams,
                ctrl_mask):
    """The weighted squared residuals of a chunk's active points at their current values:
    ``(sum p |v|^2 of the image observations, sum of the control terms)``; fixed control
    components take their control values (as in the adjustment)."""
    xyz = np.empty(3)
    vpv_img = 0.0
    vpv_ctl = 0.0
    for j in range(pt_xyz.shape[0]):
        if pt_active[j] != 0:
            continue
        kind = pt_kind[j]
        for c in range(3):
            xyz[c] = pt_xyz[j, c]
            if ctrl_mask[kind, c] and pt_csig[j, c] == 0.0:
                xyz[c] = pt_ctrl[j, c]
        for i in range(pt_start[j], pt_start[j] + pt_nobs[j]):
            if not obs_active[i]:
                continue
            s = obs_station[i]
            c = cams[cam_of_station[s]]
            x, y = project(eo[s], xyz, c)
            ox, oy = observed(obs_xy[i, 0], obs_xy[i, 1], c)
            vx, vy = x - ox, y - oy
            vpv_img += (vx * vx + vy * vy) / (obs_sigma[i] * obs_sigma[i])
        for c in range(3):
            if ctrl_mask[kind, c] and pt_csig[j, c] > 0.0:
                v = 0.0
                for q in range(3):
                    v += pt_rot[j, c, q] * (xyz[q] - pt_ctrl[j, q])
                vpv_ctl += v * v / (pt_csig[j, c] * pt_csig[j, c])
    return vpv_img, vpv_ctl


@njit(cache=True, error_model="numpy", nogil=True, parallel=True)
def point_costs_parallel(nthreads, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start,
                         pt_nobs, pt_active, obs_station, obs_xy, obs_sigma, obs_active, eo,
                         cam_of_station, cams, ctrl_mask):
    """:func:`point_costs` on ``nthreads`` threads, the points cut into runs of about equal
    observations (:func:`_runs`); the runs' sums added in run order (the same sums for the
    same thread count; BAL problem-49's 31 843 rays: 3.1 ms on one thread)."""
    n = pt_xyz.shape[0]
    nt = max(1, min(nthreads, n))
    cut = _runs(pt_start, pt_nobs, nt)
    img = np.zeros(nt)
    ctl = np.zeros(nt)
    for t in prange(nt):
        a, b = cut[t], cut[t + 1]
        img[t], ctl[t] = point_costs(pt_xyz[a:b], pt_kind[a:b], pt_ctrl[a:b], pt_csig[a:b],
                                     pt_rot[a:b], pt_start[a:b], pt_nobs[a:b],
                                     pt_active[a:b], obs_station, obs_xy, obs_sigma,
                                     obs_active, eo, cam_of_station, cams, ctrl_mask)
    vpv_img = 0.0
    vpv_ctl = 0.0
    for t in range(nt):
        vpv_img += img[t]
        vpv_ctl += ctl[t]
    return vpv_img, vpv_ctl


@njit(cache=True, error_model="numpy", nogil=True, parallel=True)
def datum_columns_parallel(nthreads, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start,
                           pt_nobs, pt_active, obs_station, obs_xy, obs_sigma, obs_active, eo,
                           cam_of_station, cams, ctrl_mask, max_rays, h_pt, x_st, r_st, b_pt,
                           behind_ok, st_fixed, cal, r_g, x_g):
    """:func:`datum_columns` with the stations' solution ``x_st`` (the pass that writes the
    points' own columns ``b_pt`` and nothing shared) on ``nthreads`` threads, the points cut
    into runs of about equal observations as :func:`point_sigmas_parallel` cuts them; the
    first point that cannot be linearised (index + 1), else 0."""
    cut = _thread_runs(nthreads, pt_start, pt_nobs)
    nt = cut.shape[0] - 1
    bad = np.zeros(nt, np.int64)
    for t in prange(nt):
        a, b = cut[t], cut[t + 1]
        if b > a:
            o0, o1 = pt_start[a], pt_start[b - 1] + pt_nobs[b - 1]
            k = datum_columns(pt_xyz[a:b], pt_kind[a:b], pt_ctrl[a:b], pt_csig[a:b],
                              pt_rot[a:b], pt_start[a:b] - o0, pt_nobs[a:b], pt_active[a:b],
                              obs_station[o0:o1], obs_xy[o0:o1], obs_sigma[o0:o1],
                              obs_active[o0:o1], eo, cam_of_station, cams, ctrl_mask,
                              max_rays, h_pt[a:b], x_st, r_st, b_pt[a:b], behind_ok,
                              st_fixed, cal, r_g, x_g)
            if k > 0:
                bad[t] = a + k
    for t in range(nt):
        if bad[t] > 0:
            return bad[t]
    return 0


@njit(cache=True, error_model="numpy", nogil=True, parallel=True)
def datum_sums_parallel(nthreads, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start,
                        pt_nobs, pt_active, obs_station, obs_xy, obs_sigma, obs_active, eo,
                        cam_of_station, cams, ctrl_mask, max_rays, h_pt, r_st, behind_ok,
                        st_fixed, cal, r_g, keep_nbar=None, keep_lo=None):
    """:func:`datum_columns` without the stations' solution (the pass that sums into the
    stations' and the border's reduced right-hand sides ``r_st`` and ``r_g``) on
    ``nthreads`` threads: each run of points (cut as :func:`datum_columns_parallel` cuts
    them) sums into a copy of its own, and the copies are added in run order -- the same
    sums for the same count of runs, whatever threads run them. The caller sees that
    ``nthreads`` copies fit in memory. The first point that cannot be linearised (index +
    1), else 0. ``keep_nbar``, ``keep_lo``: as :func:`datum_columns` keeps them."""
    cut = _thread_runs(nthreads, pt_start, pt_nobs)
    nt = cut.shape[0] - 1
    bad = np.zeros(nt, np.int64)
    rs = np.zeros((nt, r_st.shape[0], r_st.shape[1], r_st.shape[2]))
    rg = np.zeros((nt, r_g.shape[0], r_g.shape[1]))
    for t in prange(nt):
        a, b = cut[t], cut[t + 1]
        if b > a:
            o0, o1 = pt_start[a], pt_start[b - 1] + pt_nobs[b - 1]
            if keep_lo is None:
                k = datum_columns(pt_xyz[a:b], pt_kind[a:b], pt_ctrl[a:b], pt_csig[a:b],
                                  pt_rot[a:b], pt_start[a:b] - o0, pt_nobs[a:b],
                                  pt_active[a:b], obs_station[o0:o1], obs_xy[o0:o1],
                                  obs_sigma[o0:o1], obs_active[o0:o1], eo, cam_of_station,
                                  cams, ctrl_mask, max_rays, h_pt[a:b], None, rs[t],
                                  h_pt[a:b], behind_ok, st_fixed, cal, rg[t], rg[t])
            else:
                k = datum_columns(pt_xyz[a:b], pt_kind[a:b], pt_ctrl[a:b], pt_csig[a:b],
                                  pt_rot[a:b], pt_start[a:b] - o0, pt_nobs[a:b],
                                  pt_active[a:b], obs_station[o0:o1], obs_xy[o0:o1],
                                  obs_sigma[o0:o1], obs_active[o0:o1], eo, cam_of_station,
                                  cams, ctrl_mask, max_rays, h_pt[a:b], None, rs[t],
                                  h_pt[a:b], behind_ok, st_fixed, cal, rg[t], rg[t],
                                  keep_nbar[o0:o1], keep_lo[a:b])
            if k > 0:
                bad[t] = a + k
    for t in range(nt):
        if bad[t] > 0:
            return bad[t]
    for t in range(nt):
        r_st += rs[t]
        r_g += rg[t]
    return 0


@njit(cache=True, error_model="numpy", nogil=True)
def datum_columns(pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start, pt_nobs, pt_active,
                  obs_station, obs_xy, obs_sigma, obs_active, eo, cam_of_station, cams,
                  ctrl_mask, max_rays, h_pt, x_st, r_st, b_pt, behind_ok, st_fixed, cal,
                  r_g, x_g, keep_nbar=None, keep_lo=None):
    """The points' share of a solve of the full normal equations ``N [x_s; x_g; x_p] =
    [0; 0; h]`` for several right-hand sides at once (columns), ``h`` on the points only
    (``h_pt``, chunk points x 3 x c; a free network's inner constraints,
    :mod:`sapgo.freenet`); ``x_g`` the border's unknowns of a self-calibration (``cal``:
    the border column of each camera row's field, as in :func:`build_points`; ``r_g`` with
    no rows: no border).

    Without ``x_st`` (None): the reduced right-hand sides of the stations,
    ``r_s -= sum Nbar Ndd^-1 h`` into ``r_st`` (stations x npar x c), and of the border,
    ``r_g -= Nbar_g Ndd^-1 h`` into ``r_g`` (border x c). With ``x_st`` (the stations'
    solution, stations x npar x c, and ``x_g`` the border's, border x c): the points',
    ``x_p = Ndd^-1 (h - sum Nbar' x_s - Nbar_g' x_g)``, into ``b_pt`` (chunk points x 3 x
    c). The normals as the build forms them (undamped; fixed station parameters' columns
    zero). Returns the first point that cannot be linearised (index + 1), else 0.

    ``keep_nbar`` (observations x npar x 3) and ``keep_lo`` (points x 3 x 3), given to the
    pass without ``x_st`` and without a border: each active ray's ``Nbar`` at its
    observation's row and each active point's Cholesky factor of ``Ndd``, from which
    :func:`datum_columns_kept` gives the second pass's ``x_p`` without linearising again."""
    npar = r_st.shape[1]
    nc = h_pt.shape[2]
    nbar, a_all, l_all, w_all, st_all, nn, cc, lo, xyz, b_all, o_all = _workspace(max_rays, npar)
    col = np.empty(3)
    sol = np.empty(3)
    ng = r_g.shape[0]
    ngp = np.zeros((ng, 3))              # Nbar_g of the point (its border columns' rows)
    touched = np.empty(ng, np.int64)
    seen = np.zeros(ng, np.bool_)
    e = np.empty((2, N_CALIBRATION))
    for j in range(pt_xyz.shape[0]):
        if pt_active[j] != 0:
            continue
        k = _point_system(j, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start, pt_nobs,
                          obs_station, obs_xy, obs_sigma, obs_active, eo, cam_of_station,
                          cams, ctrl_mask, xyz, nbar, a_all, l_all, w_all,
                          st_all, nn, cc, b_all, o_all, 0.0, behind_ok, st_fixed)
        if k < 0 or not _chol3(nn, lo):
            return j + 1
        if keep_lo is not None:
            for r in range(3):
                for c in range(3):
                    keep_lo[j, r, c] = lo[r, c]
            q = 0
            for i in range(pt_start[j], pt_start[j] + pt_nobs[j]):
                if obs_active[i]:   # (the q-th active observation is the q-th ray)
                    for u in range(npar):
                        for r in range(3):
                            keep_nbar[i, u, r] = nbar[q, u, r]
                    q += 1
        nt = 0
        for q in range(k if ng > 0 else 0):   # Nbar_g = sum p E' B over the point's rays
            s = st_all[q]
            cam = cam_of_station[s]
            if not _ray_border(eo[s], xyz, cams[cam], cal[cam], e, o_all[q, 0], o_all[q, 1]):
                continue
            for f in range(N_CALIBRATION):
                c1 = cal[cam, f]
                if c1 >= 0 and not seen[c1]:
                    seen[c1] = True
                    touched[nt] = c1
                    nt += 1
            _add_border_rows(ngp, w_all[q], e, cal[cam], b_all[q])
        kind = pt_kind[j]
        for r in range(3):  # a fixed control component is no unknown (as in _point_system)
            if ctrl_mask[kind, r] and pt_csig[j, r] == 0.0:
                for t in range(nt):
                    ngp[touched[t], r] = 0.0
        for c in range(nc):
            for r in range(3):
                col[r] = h_pt[j, r, c]
            if x_st is None:
                _solve3(lo, col, sol)
                for q in range(k):
                    _minus_nbar_sol(nbar, q, sol, r_st, st_all[q], c)
                for t in range(nt):
                    c1 = touched[t]
                    r_g[c1, c] -= (ngp[c1, 0] * sol[0] + ngp[c1, 1] * sol[1]
                                   + ngp[c1, 2] * sol[2])
            else:
                for q in range(k):
                    _minus_nbar_x(nbar, q, x_st, st_all[q], c, col)
                for t in range(nt):
                    c1 = touched[t]
                    for r in range(3):
                        col[r] -= ngp[c1, r] * x_g[c1, c]
                _solve3(lo, col, sol)
                for r in range(3):
                    b_pt[j, r, c] = sol[r]
        for t in range(nt):
            c1 = touched[t]
            seen[c1] = False
            for r in range(3):
                ngp[c1, r] = 0.0
    return 0


@njit(cache=True, error_model="numpy", nogil=True, inline="always")
def _minus_nbar_sol(nbar, q, sol, r_st, s, c):
    """``r_st[s, :, c] -= Nbar_q sol``: one ray's share of its station's reduced right-hand
    side of a datum column (``sol = Ndd^-1 h`` of its point)."""
    for u in range(r_st.shape[1]):
        x = 0.0
        for r in range(3):
            x += nbar[q, u, r] * sol[r]
        r_st[s, u, c] -= x


@njit(cache=True, error_model="numpy", nogil=True, inline="always")
def _minus_nbar_x(nbar, q, x_st, s, c, col):
    """``col -= Nbar_q' x_s[:, c]``: one ray's station term of a point's datum column
    (``nbar[q]`` is the ray's 6x3 or npar x 3 block, ``s`` its station)."""
    for r in range(3):
        x = 0.0
        for u in range(x_st.shape[1]):
            x += nbar[q, u, r] * x_st[s, u, c]
        col[r] -= x


@njit(cache=True, error_model="numpy", nogil=True)
def _datum_columns_kept(pt_start, pt_nobs, pt_active, obs_station, obs_active, h_pt, x_st,
                        b_pt, keep_nbar, keep_lo):
    """:func:`datum_columns`' pass with ``x_st`` (no border) from what its first pass
    kept: ``x_p = Ndd^-1 (h - sum Nbar' x_s)`` of each active point into ``b_pt``."""
    nc = h_pt.shape[2]
    col = np.empty(3)
    sol = np.empty(3)
    for j in range(pt_start.shape[0]):
        if pt_active[j] != 0:
            continue
        for c in range(nc):
            for r in range(3):
                col[r] = h_pt[j, r, c]
            for i in range(pt_start[j], pt_start[j] + pt_nobs[j]):
                if not obs_active[i]:
                    continue
                _minus_nbar_x(keep_nbar, i, x_st, obs_station[i], c, col)
            _solve3(keep_lo[j], col, sol)
            for r in range(3):
                b_pt[j, r, c] = sol[r]


@njit(cache=True, error_model="numpy", nogil=True)
def _datum_sums_kept(pt_start, pt_nobs, pt_active, obs_station, obs_active, h_pt, r_st,
                     keep_pt, keep_nbar):
    """:func:`datum_columns`' pass without ``x_st`` (no border) from the build's kept
    systems of the same state, undamped (:func:`_keep_point`: each point's factor of
    ``Ndd`` by rows in ``keep_pt[j, :9]``, each active ray's ``Nbar`` at its observation's
    row of ``keep_nbar``): ``r_s -= sum Nbar Ndd^-1 h`` into ``r_st``, the same arithmetic
    on the same numbers, no ray linearised."""
    nc = h_pt.shape[2]
    lo = np.empty((3, 3))
    col = np.empty(3)
    sol = np.empty(3)
    for j in range(pt_start.shape[0]):
        if pt_active[j] != 0:
            continue
        for r in range(3):
            for c in range(3):
                lo[r, c] = keep_pt[j, 3 * r + c]
        for c in range(nc):
            for r in range(3):
                col[r] = h_pt[j, r, c]
            _solve3(lo, col, sol)
            for i in range(pt_start[j], pt_start[j] + pt_nobs[j]):
                if obs_active[i]:
                    _minus_nbar_sol(keep_nbar, i, sol, r_st, obs_station[i], c)


@njit(cache=True, error_model="numpy", nogil=True, parallel=True)
def datum_sums_kept(nthreads, pt_start, pt_nobs, pt_active, obs_station, obs_active, h_pt,
                    r_st, keep_pt, keep_nbar):
    """:func:`datum_sums_parallel` (no border) from the build's kept systems
    (:func:`_datum_sums_kept`): the points cut into the same runs, each run's sums in a
    copy of its own, added in run order -- the same sums bit for bit."""
    cut = _thread_runs(nthreads, pt_start, pt_nobs)
    nt = cut.shape[0] - 1
    rs = np.zeros((nt, r_st.shape[0], r_st.shape[1], r_st.shape[2]))
    for t in prange(nt):
        a, b = cut[t], cut[t + 1]
        if b > a:
            _datum_sums_kept(pt_start[a:b], pt_nobs[a:b], pt_active[a:b], obs_station,
                             obs_active, h_pt[a:b], rs[t], keep_pt[a:b], keep_nbar)
    for t in range(nt):
        r_st += rs[t]


@njit(cache=True, error_model="numpy", nogil=True, parallel=True)
def datum_columns_kept(nthreads, pt_start, pt_nobs, pt_active, obs_station, obs_active, h_pt,
                       x_st, b_pt, keep_nbar, keep_lo):
    """The second pass of :func:`datum_columns` (with ``x_st``, no border) from the
    ``Nbar`` and the factors of ``Ndd`` its first pass kept (``keep_nbar``, ``keep_lo``):
    the same arithmetic on the same numbers, without linearising the rays again; on
    ``nthreads`` threads, the points cut as :func:`point_sigmas_parallel` cuts them."""
    n = pt_start.shape[0]
    nt = max(1, min(nthreads, n))
    for j in range(1, n):
        if pt_start[j] < pt_start[j - 1] + pt_nobs[j - 1]:
            nt = 1
    if nt < 2:
        _datum_columns_kept(pt_start, pt_nobs, pt_active, obs_station, obs_active, h_pt,
                            x_st, b_pt, keep_nbar, keep_lo)
        return
    cut = _runs(pt_start, pt_nobs, nt)
    for t in prange(nt):
        a, b = cut[t], cut[t + 1]
        if b > a:
            o0, o1 = pt_start[a], pt_start[b - 1] + pt_nobs[b - 1]
            _datum_columns_kept(pt_start[a:b] - o0, pt_nobs[a:b], pt_active[a:b],
                                obs_station[o0:o1], obs_active[o0:o1], h_pt[a:b], x_st,
                                b_pt[a:b], keep_nbar[o0:o1], keep_lo[a:b])
