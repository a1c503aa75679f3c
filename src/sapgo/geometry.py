"""Rotations, the collinearity equations and their partial derivatives (numba kernels).

Conventions (DESIGN section 3): object -> image rotation ``M = R3(kappa) R2(phi) R1(omega)``
with the elementary rotations

    R1(w) = [[1, 0, 0], [0, cos w, sin w], [0, -sin w, cos w]]
    R2(p) = [[cos p, 0, -sin p], [0, 1, 0], [sin p, 0, cos p]]
    R3(k) = [[cos k, sin k, 0], [-sin k, cos k, 0], [0, 0, 1]]

and the collinearity equations for a point X seen from station Xc with focal length f and
principal point (x0, y0):

    [u, v, w] = M (X - Xc),    x = x0 - f u / w,    y = y0 - f v / w.

Station parameters are ordered (omega, phi, kappa, Xc, Yc, Zc); angles in radians, object
coordinates in metres, image coordinates in millimetres.
"""

import numpy as np
from numba import njit


@njit(cache=True)
def _elementary(omega, phi, kappa):
    cw, sw = np.cos(omega), np.sin(omega)
    cp, sp = np.cos(phi), np.sin(phi)
    ck, sk = np.cos(kappa), np.sin(kappa)
    r1 = np.array([[1.0, 0.0, 0.0], [0.0, cw, sw], [0.0, -sw, cw]])
    r2 = np.array([[cp, 0.0, -sp], [0.0, 1.0, 0.0], [sp, 0.0, cp]])
    r3 = np.array([[ck, sk, 0.0], [-sk, ck, 0.0], [0.0, 0.0, 1.0]])
    d1 = np.array([[0.0, 0.0, 0.0], [0.0, -sw, cw], [0.0, -cw, -sw]])
    d2 = np.array([[-sp, 0.0, -cp], [0.0, 0.0, 0.0], [cp, 0.0, -sp]])
    d3 = np.array([[-sk, ck, 0.0], [-ck, -sk, 0.0], [0.0, 0.0, 0.0]])
    return r1, r2, r3, d1, d2, d3


@njit(cache=True)
def _mm3(a, b):
    c = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            s = 0.0
            for k in range(3):
                s += a[i, k] * b[k, j]
            c[i, j] = s
    return c


@njit(cache=True)
def rotation_matrix(omega, phi, kappa):
    """``M = R3(kappa) R2(phi) R1(omega)``, object to image."""
    r1, r2, r3, _, _, _ = _elementary(omega, phi, kappa)
    return _mm3(r3, _mm3(r2, r1))


@njit(cache=True)
def rotation_and_derivatives(omega, phi, kappa):
    """``M`` and its derivatives with respect to omega, phi and kappa."""
    r1, r2, r3, d1, d2, d3 = _elementary(omega, phi, kappa)
    r21 = _mm3(r2, r1)
    m = _mm3(r3, r21)
    dm_w = _mm3(r3, _mm3(r2, d1))
    dm_p = _mm3(r3, _mm3(d2, r1))
    dm_k = _mm3(d3, r21)
    return m, dm_w, dm_p, dm_k


@njit(cache=True)
def project(eo, xyz, f, x0, y0):
    """Image coordinates (mm) of object point ``xyz`` seen from station ``eo``."""
    m = rotation_matrix(eo[0], eo[1], eo[2])
    dx = xyz[0] - eo[3]
    dy = xyz[1] - eo[4]
    dz = xyz[2] - eo[5]
    u = m[0, 0] * dx + m[0, 1] * dy + m[0, 2] * dz
    v = m[1, 0] * dx + m[1, 1] * dy + m[1, 2] * dz
    w = m[2, 0] * dx + m[2, 1] * dy + m[2, 2] * dz
    if w == 0.0:
        return np.nan, np.nan
    return x0 - f * u / w, y0 - f * v / w


@njit(cache=True)
def linearize(eo, xyz, f, x0, y0, a, b):
    """Computed image coordinates and the partial derivatives of the collinearity equations.

    Fills ``a`` (2x6) with d(x, y)/d(omega, phi, kappa, Xc, Yc, Zc) and ``b`` (2x3) with
    d(x, y)/d(X, Y, Z); returns the computed ``x, y`` and ``w`` (the depth along the optical
    axis, negative for a point in front of the camera).
    """
    m, dm_w, dm_p, dm_k = rotation_and_derivatives(eo[0], eo[1], eo[2])
    d = np.empty(3)
    d[0] = xyz[0] - eo[3]
    d[1] = xyz[1] - eo[4]
    d[2] = xyz[2] - eo[5]
    q = np.zeros(3)
    qw = np.zeros(3)
    qp = np.zeros(3)
    qk = np.zeros(3)
    for i in range(3):
        for k in range(3):
            q[i] += m[i, k] * d[k]
            qw[i] += dm_w[i, k] * d[k]
            qp[i] += dm_p[i, k] * d[k]
            qk[i] += dm_k[i, k] * d[k]
    u, v, w = q[0], q[1], q[2]
    if w >= 0.0:  # behind the camera or in its principal plane: no projection
        return np.nan, np.nan, w
    fw2 = f / (w * w)
    # d x / d q = -f/w * [1, 0, -u/w];  d y / d q = -f/w * [0, 1, -v/w]
    gx0, gx2 = -f / w, f * u / (w * w)
    gy1, gy2 = -f / w, fw2 * v
    # angles
    a[0, 0] = gx0 * qw[0] + gx2 * qw[2]
    a[1, 0] = gy1 * qw[1] + gy2 * qw[2]
    a[0, 1] = gx0 * qp[0] + gx2 * qp[2]
    a[1, 1] = gy1 * qp[1] + gy2 * qp[2]
    a[0, 2] = gx0 * qk[0] + gx2 * qk[2]
    a[1, 2] = gy1 * qk[1] + gy2 * qk[2]
    # object point: d q / d X = M[:, k]; station position is the negative
    for k in range(3):
        bx = gx0 * m[0, k] + gx2 * m[2, k]
        by = gy1 * m[1, k] + gy2 * m[2, k]
        b[0, k] = bx
        b[1, k] = by
        a[0, 3 + k] = -bx
        a[1, 3 + k] = -by
    return x0 - f * u / w, y0 - f * v / w, w


@njit(cache=True)
def intersect(eo_rays, xy_rays, f_rays, x0_rays, y0_rays):
    """Least-squares intersection of image rays: the point nearest to all of them.

    Each ray ``i`` is the line from station ``eo_rays[i]`` through image point ``xy_rays[i]``
    of a camera with focal length ``f_rays[i]`` and principal point ``(x0, y0)``. Returns the
    point and a flag that is False when the rays are (nearly) parallel.
    """
    n = eo_rays.shape[0]
    a = np.zeros((3, 3))
    r = np.zeros(3)
    for i in range(n):
        m = rotation_matrix(eo_rays[i, 0], eo_rays[i, 1], eo_rays[i, 2])
        img = np.array([xy_rays[i, 0] - x0_rays[i], xy_rays[i, 1] - y0_rays[i], -f_rays[i]])
        d = np.zeros(3)
        for k in range(3):
            for j in range(3):
                d[k] += m[j, k] * img[j]
        d /= np.sqrt(d[0] ** 2 + d[1] ** 2 + d[2] ** 2)
        for k in range(3):
            for j in range(3):
                p = (1.0 if k == j else 0.0) - d[k] * d[j]
                a[k, j] += p
                r[k] += p * eo_rays[i, 3 + j]
    # a is symmetric positive semi-definite; singular when all rays are parallel
    evals = np.linalg.eigvalsh(a)
    if n < 2 or evals[0] < 1e-10 * evals[2]:
        return np.zeros(3), False
    return np.linalg.solve(a, r), True


@njit(cache=True)
def intersect_points(obs_start, n_obs, obs_station, obs_xy, eo, cam_of_station, cam_f,
                     cam_x0, cam_y0, out, ok):
    """Intersect every point from its rays (chunk kernel: indices relative to the chunk)."""
    for j in range(obs_start.shape[0]):
        s0 = obs_start[j]
        k = n_obs[j]
        e = np.empty((k, 6))
        xy = np.empty((k, 2))
        ff = np.empty(k)
        xx = np.empty(k)
        yy = np.empty(k)
        for i in range(k):
            st = obs_station[s0 + i]
            c = cam_of_station[st]
            e[i] = eo[st]
            xy[i] = obs_xy[s0 + i]
            ff[i] = cam_f[c]
            xx[i] = cam_x0[c]
            yy[i] = cam_y0[c]
        p, good = intersect(e, xy, ff, xx, yy)
        out[j] = p
        ok[j] = good


@njit(cache=True)
def project_observations(station_of_obs, point_of_obs, eo, xyz, cam_of_station, cam_f,
                         cam_x0, cam_y0, out):
    """Image coordinates of every (station, point) pair into ``out`` (n x 2, mm)."""
    for i in range(station_of_obs.shape[0]):
        s = station_of_obs[i]
        c = cam_of_station[s]
        x, y = project(eo[s], xyz[point_of_obs[i]], cam_f[c], cam_x0[c], cam_y0[c])
        out[i, 0] = x
        out[i, 1] = y
