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
def _rot9(omega, phi, kappa):
    """The nine elements of ``M = R3(kappa) R2(phi) R1(omega)``, row by row (no allocation)."""
    cw, sw = np.cos(omega), np.sin(omega)
    cp, sp = np.cos(phi), np.sin(phi)
    ck, sk = np.cos(kappa), np.sin(kappa)
    return (ck * cp, ck * sp * sw + sk * cw, -ck * sp * cw + sk * sw,
            -sk * cp, -sk * sp * sw + ck * cw, sk * sp * cw + ck * sw,
            sp, -cp * sw, cp * cw)


@njit(cache=True)
def rotation_matrix(omega, phi, kappa):
    """``M = R3(kappa) R2(phi) R1(omega)``, object to image."""
    r = _rot9(omega, phi, kappa)
    m = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            m[i, j] = r[3 * i + j]
    return m


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
    m = _rot9(eo[0], eo[1], eo[2])
    dx = xyz[0] - eo[3]
    dy = xyz[1] - eo[4]
    dz = xyz[2] - eo[5]
    u = m[0] * dx + m[1] * dy + m[2] * dz
    v = m[3] * dx + m[4] * dy + m[5] * dz
    w = m[6] * dx + m[7] * dy + m[8] * dz
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
    # q = M d with M = R3 R2 R1, and its derivatives without forming matrices:
    # dR1/dw = Kx R1, dR2/dp = Ky R2, dR3/dk = Kz R3 with constant skew matrices K, so
    # dq/dw = R3 R2 Kx (R1 d), dq/dp = R3 Ky (R2 R1 d), dq/dk = Kz q.
    cw, sw = np.cos(eo[0]), np.sin(eo[0])
    cp, sp = np.cos(eo[1]), np.sin(eo[1])
    ck, sk = np.cos(eo[2]), np.sin(eo[2])
    d0, d1, d2 = xyz[0] - eo[3], xyz[1] - eo[4], xyz[2] - eo[5]
    p10, p11, p12 = d0, cw * d1 + sw * d2, -sw * d1 + cw * d2  # R1 d
    p20, p21, p22 = cp * p10 - sp * p12, p11, sp * p10 + cp * p12  # R2 R1 d
    q = (ck * p20 + sk * p21, -sk * p20 + ck * p21, p22)
    # Kx (R1 d) = (0, p12, -p11) -> R2 -> R3
    t0, t1, t2 = sp * p11, p12, cp * -p11
    qw = (ck * t0 + sk * t1, -sk * t0 + ck * t1, t2)
    # Ky (R2 R1 d) = (-p22, 0, p20) -> R3
    qp = (ck * -p22, sk * p22, p20)
    qk = (q[1], -q[0], 0.0)
    m = (ck * cp, ck * sp * sw + sk * cw, -ck * sp * cw + sk * sw,
         -sk * cp, -sk * sp * sw + ck * cw, sk * sp * cw + ck * sw,
         sp, -cp * sw, cp * cw)
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
        bx = gx0 * m[k] + gx2 * m[6 + k]
        by = gy1 * m[3 + k] + gy2 * m[6 + k]
        b[0, k] = bx
        b[1, k] = by
        a[0, 3 + k] = -bx
        a[1, 3 + k] = -by
    return x0 - f * u / w, y0 - f * v / w, w


@njit(cache=True)
def _add_ray(eo, x, y, f, x0, y0, a, r):
    """Add the ray from station ``eo`` through image point (x, y) to the normal system."""
    m = _rot9(eo[0], eo[1], eo[2])
    i0, i1, i2 = x - x0, y - y0, -f
    d0 = m[0] * i0 + m[3] * i1 + m[6] * i2
    d1 = m[1] * i0 + m[4] * i1 + m[7] * i2
    d2 = m[2] * i0 + m[5] * i1 + m[8] * i2
    norm = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    d = (d0 / norm, d1 / norm, d2 / norm)
    for k in range(3):
        for j in range(3):
            p = (1.0 if k == j else 0.0) - d[k] * d[j]
            a[k, j] += p
            r[k] += p * eo[3 + j]


@njit(cache=True)
def _solve_sym3(a, r, out):
    """Solve the 3x3 ray system by Cholesky; False when (nearly) singular (parallel rays).

    A pivot below 1e-10 of the largest diagonal element counts as singular.
    """
    scale = max(a[0, 0], max(a[1, 1], a[2, 2]))
    tol = 1e-10 * scale
    l00 = a[0, 0]
    if l00 <= tol:
        return False
    l00 = np.sqrt(l00)
    l10 = a[1, 0] / l00
    l20 = a[2, 0] / l00
    l11 = a[1, 1] - l10 * l10
    if l11 <= tol:
        return False
    l11 = np.sqrt(l11)
    l21 = (a[2, 1] - l20 * l10) / l11
    l22 = a[2, 2] - l20 * l20 - l21 * l21
    if l22 <= tol:
        return False
    l22 = np.sqrt(l22)
    z0 = r[0] / l00
    z1 = (r[1] - l10 * z0) / l11
    z2 = (r[2] - l20 * z0 - l21 * z1) / l22
    out[2] = z2 / l22
    out[1] = (z1 - l21 * out[2]) / l11
    out[0] = (z0 - l10 * out[1] - l20 * out[2]) / l00
    return True


@njit(cache=True)
def intersect(eo_rays, xy_rays, f_rays, x0_rays, y0_rays):
    """Least-squares intersection of image rays: the point nearest to all of them.

    Each ray ``i`` is the line from station ``eo_rays[i]`` through image point ``xy_rays[i]``
    of a camera with focal length ``f_rays[i]`` and principal point ``(x0, y0)``. Returns the
    point and a flag that is False when the rays are (nearly) parallel or fewer than two.
    """
    n = eo_rays.shape[0]
    a = np.zeros((3, 3))
    r = np.zeros(3)
    out = np.zeros(3)
    for i in range(n):
        _add_ray(eo_rays[i], xy_rays[i, 0], xy_rays[i, 1], f_rays[i], x0_rays[i], y0_rays[i],
                 a, r)
    if n < 2 or not _solve_sym3(a, r, out):
        return np.zeros(3), False
    return out, True


@njit(cache=True)
def intersect_points(obs_start, n_obs, obs_station, obs_xy, eo, cam_of_station, cam_f,
                     cam_x0, cam_y0, out, ok):
    """Intersect every point from its rays (chunk kernel: indices relative to the chunk)."""
    a = np.empty((3, 3))
    r = np.empty(3)
    p = np.empty(3)
    for j in range(obs_start.shape[0]):
        a[:, :] = 0.0
        r[:] = 0.0
        for i in range(obs_start[j], obs_start[j] + n_obs[j]):
            st = obs_station[i]
            c = cam_of_station[st]
            _add_ray(eo[st], obs_xy[i, 0], obs_xy[i, 1], cam_f[c], cam_x0[c], cam_y0[c], a, r)
        good = n_obs[j] >= 2 and _solve_sym3(a, r, p)
        ok[j] = good
        for k in range(3):
            out[j, k] = p[k] if good else 0.0


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
