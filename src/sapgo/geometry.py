"""Rotations, the collinearity equations and their partial derivatives (numba kernels).

Conventions (DESIGN section 3): object -> image rotation ``M = R3(kappa) R2(phi) R1(omega)``
with the elementary rotations

    R1(w) = [[1, 0, 0], [0, cos w, sin w], [0, -sin w, cos w]]
    R2(p) = [[cos p, 0, -sin p], [0, 1, 0], [sin p, 0, cos p]]
    R3(k) = [[cos k, sin k, 0], [-sin k, cos k, 0], [0, 0, 1]]

and the collinearity equations for a point X seen from station Xc with focal length f and
principal point (x0, y0), with Brown's lens distortion (radial k1, k2, k3 and decentring p1,
p2) and the affinity and shear of the image axes (b1, b2; Fraser 1997, as Australis and
DBAT), by default (the *forward* model) added to the ideal image point:

    [u, v, w] = M (X - Xc),    xi = -f u / w,    yi = -f v / w,    r^2 = xi^2 + yi^2,
    x = x0 + xi + xi (k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 xi^2) + 2 p2 xi yi + b1 xi + b2 yi,
    y = y0 + yi + yi (k1 r^2 + k2 r^4 + k3 r^6) + p2 (r^2 + 2 yi^2) + 2 p1 xi yi.

A camera of the *backward* model (PhotoModeler, DBAT, Australis: the distortion corrects a
measured point) takes the same polynomial at the measured point (x, y) instead,
``xm = x - x0``, ``ym = y - y0``, ``r^2 = xm^2 + ym^2``, and the corrected point
``(x + dx(xm, ym), y + dy(xm, ym))`` is the one the ideal projection ``(x0 + xi, y0 + yi)``
is fitted to (:func:`observed`): the residual of an observation is ``x0 + xi - x - dx``.

A camera is a row of :data:`CAMERA_FIELDS` (``camera_array``). Station parameters are ordered
(omega, phi, kappa, Xc, Yc, Zc); angles in radians, object coordinates in metres, image
coordinates in millimetres (k1 mm^-2, k2 mm^-4, k3 mm^-6, p1 and p2 mm^-1).
"""

import numpy as np
from numba import njit

from .apsets import MAX_TERMS, ap_displacement, ap_partials

#: The names of the additional parameters' coefficients (:mod:`sapgo.apsets`).
AP_NAMES = tuple(f"a{i + 1}" for i in range(MAX_TERMS))
#: The camera row of the kernels: ``cams[c] = (f, x0, y0, k1, k2, k3, p1, p2, b1, b2,
#: model, ap_set, ap_base, a1, ..., a44)``, ``model`` :data:`FORWARD` or :data:`BACKWARD`
#: (the ``/cameras`` field ``distortion_model``), ``ap_set`` the camera's
#: additional-parameter set (:data:`sapgo.apsets.AP_SETS` by number, 0 none), ``ap_base``
#: its base (mm) and ``a1 .. a44`` its coefficients (mm).
CAMERA_FIELDS = ("focal_length", "x0", "y0", "k1", "k2", "k3", "p1", "p2", "b1", "b2",
                 "distortion_model", "ap_set", "ap_base") + AP_NAMES
N_CAMERA = len(CAMERA_FIELDS)
#: Places in the camera row: the distortion model, the additional-parameter set, its base
#: and its first coefficient.
MODEL, AP_SET, AP_BASE, AP0 = 10, 11, 12, 13
#: The distortion models (the camera row's last field): added to the ideal image point, or
#: correcting the measured one (module docstring).
FORWARD, BACKWARD = 0, 1
DISTORTION_MODELS = ("forward", "backward")
#: The camera row's fields that hold distortion (k1 .. b2).
DISTORTION_COLUMNS = slice(3, 10)


def camera_array(cameras):
    """The kernels' camera rows (n x :data:`N_CAMERA` float64) of ``/cameras`` records (a
    field the records lack, as in projects written before it existed: 0)."""
    names = cameras.dtype.names
    n = len(cameras)
    return np.ascontiguousarray(np.column_stack(
        [np.asarray(cameras[k], dtype=np.float64) if k in names else np.zeros(n)
         for k in CAMERA_FIELDS]).reshape(-1, N_CAMERA))


def beyond_brown(rows):
    """Which camera rows have affinity or shear (b1, b2), the backward distortion model or
    an additional-parameter set: what the camera models of COLMAP, OpenSfM, Bundler and BAL
    cannot hold."""
    rows = np.asarray(rows, np.float64).reshape(-1, N_CAMERA)
    return ((rows[:, 8:10] != 0.0).any(axis=1) | (rows[:, MODEL] != FORWARD)
            | (rows[:, AP_SET] != 0.0))


def plain_camera(f, x0=0.0, y0=0.0):
    """A camera row without distortion."""
    row = np.zeros(N_CAMERA)
    row[:3] = f, x0, y0
    return row


@njit(cache=True, error_model="numpy")
def brown(u, v, c):
    """The distortion polynomial of camera row ``c`` at ``(u, v)`` (mm from the principal
    point), its additional-parameter set's displacement included (:mod:`sapgo.apsets`):
    ``(dx, dy, j00, j01, j10, j11)``, where ``J = [[j00, j01], [j10, j11]]`` is the
    Jacobian of ``(u + dx, v + dy)`` by ``(u, v)``."""
    k1, k2, k3, p1, p2, b1, b2 = c[3], c[4], c[5], c[6], c[7], c[8], c[9]
    r2 = u * u + v * v
    rad = r2 * (k1 + r2 * (k2 + r2 * k3))
    drad = k1 + r2 * (2.0 * k2 + 3.0 * r2 * k3)          # d rad / d r^2
    dx = u * rad + p1 * (r2 + 2.0 * u * u) + 2.0 * p2 * u * v + b1 * u + b2 * v
    dy = v * rad + p2 * (r2 + 2.0 * v * v) + 2.0 * p1 * u * v
    j00 = 1.0 + rad + 2.0 * u * u * drad + 6.0 * p1 * u + 2.0 * p2 * v + b1
    j10 = 2.0 * u * v * drad + 2.0 * p1 * v + 2.0 * p2 * u
    j01 = j10 + b2
    j11 = 1.0 + rad + 2.0 * v * v * drad + 6.0 * p2 * v + 2.0 * p1 * u
    if c[AP_SET] != 0.0:
        ax, ay, a00, a01, a10, a11 = ap_displacement(u, v, int(c[AP_SET]), c[AP_BASE],
                                                     c[AP0:AP0 + MAX_TERMS])
        dx += ax
        dy += ay
        j00 += a00
        j01 += a01
        j10 += a10
        j11 += a11
    return dx, dy, j00, j01, j10, j11


@njit(cache=True, error_model="numpy")
def distortion(xi, yi, c):
    """The distortion added at the ideal image point ``(xi, yi)`` (mm, from the principal
    point) by camera row ``c``: :func:`brown` for the forward model, none (``0, 0`` and the
    identity) for the backward one, whose distortion corrects the measurements
    (:func:`observed`)."""
    if c[MODEL] != 0.0:
        return 0.0, 0.0, 1.0, 0.0, 0.0, 1.0
    return brown(xi, yi, c)


@njit(cache=True, error_model="numpy")
def observed(x, y, c):
    """The image point the ideal projection of camera row ``c`` is fitted to, for a
    measurement ``(x, y)``: the measurement itself (forward model), or the measurement
    corrected by the backward model's distortion at it."""
    if c[MODEL] == 0.0:
        return x, y
    dx, dy, _, _, _, _ = brown(x - c[1], y - c[2], c)
    return x + dx, y + dy


@njit(cache=True, error_model="numpy")
def undistort(x, y, c):
    """The ideal image point ``(xi, yi)`` (from the principal point) that camera row ``c``
    images at ``(x, y)``: Newton's method on ``xi + dx(xi, yi) = x - x0`` (forward model),
    the corrected measurement (backward). Returns ``(xi, yi, converged)``."""
    if c[MODEL] != 0.0:
        xo, yo = observed(x, y, c)
        return xo - c[1], yo - c[2], True
    xd, yd = x - c[1], y - c[2]
    xi, yi = xd, yd
    if (c[3] == 0.0 and c[4] == 0.0 and c[5] == 0.0 and c[6] == 0.0 and c[7] == 0.0
            and c[8] == 0.0 and c[9] == 0.0 and c[AP_SET] == 0.0):
        return xi, yi, True
    for _ in range(50):
        dx, dy, j00, j01, j10, j11 = distortion(xi, yi, c)
        fx, fy = xi + dx - xd, yi + dy - yd
        det = j00 * j11 - j01 * j10
        if det == 0.0 or not np.isfinite(det):
            return xi, yi, False
        sx = (j11 * fx - j01 * fy) / det
        sy = (j00 * fy - j10 * fx) / det
        xi -= sx
        yi -= sy
        if abs(sx) + abs(sy) <= 1e-13 * (1.0 + abs(xi) + abs(yi)):
            # the root on the branch of the measured point, where the mapping is one-to-one
            _, _, j00, j01, j10, j11 = distortion(xi, yi, c)
            ok = j00 * j11 - j01 * j10 > 0.0 and xi * xd + yi * yd >= 0.0
            return xi, yi, ok
    return xi, yi, False


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
def _mm3(a, b):
    c = np.zeros((3, 3))
    for i in range(3):
        for j in range(3):
            s = 0.0
            for k in range(3):
                s += a[i, k] * b[k, j]
            c[i, j] = s
    return c


@njit(cache=True, error_model="numpy")
def _rot9(omega, phi, kappa):
    """The nine elements of ``M = R3(kappa) R2(phi) R1(omega)``, row by row (no allocation)."""
    cw, sw = np.cos(omega), np.sin(omega)
    cp, sp = np.cos(phi), np.sin(phi)
    ck, sk = np.cos(kappa), np.sin(kappa)
    return (ck * cp, ck * sp * sw + sk * cw, -ck * sp * cw + sk * sw,
            -sk * cp, -sk * sp * sw + ck * cw, sk * sp * cw + ck * sw,
            sp, -cp * sw, cp * cw)


#: Columns of an orientation row that carries its rotation (:func:`with_rotations`):
#: omega, phi, kappa, X, Y, Z, then the nine elements of ``M`` row by row.
EO_ROTATION = 15
#: :func:`with_rotations` appends the rotations for blocks of up to this many stations
#: (72 bytes a station; beyond, the kernels take the bare rows, whose arrays may be paged).
ROTATION_STATIONS = 250_000


@njit(cache=True, error_model="numpy")
def rotation9(eo):
    """The nine elements of ``M`` of the orientation row ``eo``: its own columns 6 .. 14
    where it carries them (:func:`with_rotations`), else :func:`_rot9` of its angles (six
    sines and cosines: a fifth of :func:`linearize`'s time, measured)."""
    if eo.shape[0] >= EO_ROTATION:
        return (eo[6], eo[7], eo[8], eo[9], eo[10], eo[11], eo[12], eo[13], eo[14])
    return _rot9(eo[0], eo[1], eo[2])


@njit(cache=True, error_model="numpy")
def _fill_rotations(eo, out):
    for s in range(eo.shape[0]):
        for u in range(6):
            out[s, u] = eo[s, u]
        m = _rot9(eo[s, 0], eo[s, 1], eo[s, 2])
        for k in range(9):
            out[s, 6 + k] = m[k]


def with_rotations(eo):
    """The orientations ``eo`` (n x 6) for the kernels: each row with its rotation matrix
    appended (n x :data:`EO_ROTATION`, :func:`rotation9`), computed once instead of at every
    ray; ``eo`` itself beyond :data:`ROTATION_STATIONS` stations. The same numbers either
    way (the same function computes them)."""
    if eo.ndim != 2 or eo.shape[1] != 6 or len(eo) > ROTATION_STATIONS:
        return eo
    out = np.empty((len(eo), EO_ROTATION))
    _fill_rotations(np.ascontiguousarray(eo, dtype=np.float64), out)
    return out


@njit(cache=True, error_model="numpy")
def _opk9(m):
    """(omega, phi, kappa) of the nine elements of a rotation ``M = R3 R2 R1`` (row by
    row); at phi = +-90 degrees omega = 0 and kappa takes the rest (as
    :func:`sapgo.frames.opk_of`)."""
    s = m[6]
    if s > 1.0:
        s = 1.0
    elif s < -1.0:
        s = -1.0
    phi = np.arcsin(s)
    if np.hypot(m[0], m[3]) < 1e-9:
        return 0.0, phi, np.arctan2(m[1], m[4])
    return np.arctan2(-m[7], m[8]), phi, np.arctan2(-m[3], m[0])


@njit(cache=True, error_model="numpy")
def turn(omega, phi, kappa, t0, t1, t2):
    """The angles of a photo turned by the rotation vector ``theta = (t0, t1, t2)`` (the
    adjustment's unknowns of a photo's attitude, in the object frame): ``M' = M R(-theta)``,
    ``R(v) = exp([v]x)`` (Rodrigues), so that ``M' d = M d + M [d]x theta`` to first order
    (:func:`linearize`). Any attitude, phi = +-90 degrees included, has neighbours in every
    direction of theta; only the angles read off ``M'`` meet the lock."""
    m = _rot9(omega, phi, kappa)
    a = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    if a == 0.0:
        return omega, phi, kappa
    x, y, z = -t0 / a, -t1 / a, -t2 / a
    c, s = np.cos(a), np.sin(a)
    v = 1.0 - c
    r = (c + x * x * v, x * y * v - z * s, x * z * v + y * s,
         y * x * v + z * s, c + y * y * v, y * z * v - x * s,
         z * x * v - y * s, z * y * v + x * s, c + z * z * v)
    n = np.empty(9)
    for i in range(3):
        for j in range(3):
            n[3 * i + j] = (m[3 * i] * r[j] + m[3 * i + 1] * r[3 + j]
                            + m[3 * i + 2] * r[6 + j])
    w, p, k = _opk9(n)
    # of the two triples of angles of M' (and their turns by 2 pi), the one nearest the
    # old angles: a small turn moves the angles a little, whatever range they were given in
    best = 1e300
    bw, bp, bk = w, p, k
    for cw, cp, ck in ((w, p, k), (w + np.pi, np.pi - p, k + np.pi)):
        cw = omega + _near(cw - omega)
        cp = phi + _near(cp - phi)
        ck = kappa + _near(ck - kappa)
        d = abs(cw - omega) + abs(cp - phi) + abs(ck - kappa)
        if d < best:
            best, bw, bp, bk = d, cw, cp, ck
    return bw, bp, bk


@njit(cache=True, error_model="numpy")
def _near(a):
    """``a`` turned by a multiple of 2 pi into [-pi, pi)."""
    return (a + np.pi) % (2.0 * np.pi) - np.pi


@njit(cache=True, error_model="numpy")
def turn_all(opk, theta, out):
    """:func:`turn` of rows of angles (n x 3) by rows of rotation vectors, into ``out``."""
    for i in range(opk.shape[0]):
        w, p, k = turn(opk[i, 0], opk[i, 1], opk[i, 2], theta[i, 0], theta[i, 1],
                       theta[i, 2])
        out[i, 0] = w
        out[i, 1] = p
        out[i, 2] = k


def turned(opk, theta):
    """Angles (n x 3) turned by rotation vectors (n x 3): :func:`turn` row by row."""
    opk = np.ascontiguousarray(opk, np.float64).reshape(-1, 3)
    out = np.empty_like(opk)
    turn_all(opk, np.ascontiguousarray(theta, np.float64).reshape(-1, 3), out)
    return out


def attitude_jacobians(opk):
    """``J = d(omega, phi, kappa) / d theta`` (n x 3 x 3) at rows of angles: how the angles
    move as :func:`turn` turns a photo, analytically: ``dM'/dtheta_k = -M [e_k]x`` through
    ``phi = asin(m20)``, ``omega = atan2(-m21, m22)``, ``kappa = atan2(-m10, m00)``;
    singular at phi = +-90 degrees, where the angles cannot follow every turn."""
    opk = np.ascontiguousarray(opk, np.float64).reshape(-1, 3)
    w, p, k = opk.T
    cw, sw, cp, sp, ck, sk = np.cos(w), np.sin(w), np.cos(p), np.sin(p), np.cos(k), np.sin(k)
    m = np.empty((len(opk), 3, 3))
    m[:, 0] = np.column_stack([ck * cp, ck * sp * sw + sk * cw, -ck * sp * cw + sk * sw])
    m[:, 1] = np.column_stack([-sk * cp, -sk * sp * sw + ck * cw, sk * sp * cw + ck * sw])
    m[:, 2] = np.column_stack([sp, -cp * sw, cp * cw])
    zero = np.zeros((len(opk), 3))
    c0, c1, c2 = m[:, :, 0], m[:, :, 1], m[:, :, 2]
    dms = (np.stack([zero, -c2, c1], axis=2), np.stack([c2, zero, -c0], axis=2),
           np.stack([-c1, c0, zero], axis=2))
    j = np.empty((len(opk), 3, 3))
    qw = m[:, 2, 1] ** 2 + m[:, 2, 2] ** 2
    qk = m[:, 1, 0] ** 2 + m[:, 0, 0] ** 2
    for i, dm in enumerate(dms):
        j[:, 0, i] = (-m[:, 2, 2] * dm[:, 2, 1] + m[:, 2, 1] * dm[:, 2, 2]) / qw
        j[:, 1, i] = dm[:, 2, 0] / cp
        j[:, 2, i] = (-m[:, 0, 0] * dm[:, 1, 0] + m[:, 1, 0] * dm[:, 0, 0]) / qk
    return j


@njit(cache=True, error_model="numpy")
def rotation_matrix(omega, phi, kappa):
    """``M = R3(kappa) R2(phi) R1(omega)``, object to image."""
    r = _rot9(omega, phi, kappa)
    m = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            m[i, j] = r[3 * i + j]
    return m


@njit(cache=True, error_model="numpy")
def rotation_and_derivatives(omega, phi, kappa):
    """``M`` and its derivatives with respect to omega, phi and kappa."""
    r1, r2, r3, d1, d2, d3 = _elementary(omega, phi, kappa)
    r21 = _mm3(r2, r1)
    m = _mm3(r3, r21)
    dm_w = _mm3(r3, _mm3(r2, d1))
    dm_p = _mm3(r3, _mm3(d2, r1))
    dm_k = _mm3(d3, r21)
    return m, dm_w, dm_p, dm_k


@njit(cache=True, error_model="numpy")
def project(eo, xyz, c):
    """Image coordinates (mm) of object point ``xyz`` seen from station ``eo`` with camera
    row ``c``."""
    f = c[0]
    m = rotation9(eo)
    dx = xyz[0] - eo[3]
    dy = xyz[1] - eo[4]
    dz = xyz[2] - eo[5]
    u = m[0] * dx + m[1] * dy + m[2] * dz
    v = m[3] * dx + m[4] * dy + m[5] * dz
    w = m[6] * dx + m[7] * dy + m[8] * dz
    if w == 0.0:
        return np.nan, np.nan
    xi, yi = -f * u / w, -f * v / w
    dx, dy, _, _, _, _ = distortion(xi, yi, c)
    return c[1] + xi + dx, c[2] + yi + dy


@njit(cache=True, error_model="numpy")
def linearize(eo, xyz, c, a, b):
    """Computed image coordinates and the partial derivatives of the collinearity equations.

    Fills ``a`` (2x6) with d(x, y)/d(theta, Xc, Yc, Zc), ``theta`` the rotation vector
    that turns the photo (:func:`turn`: any attitude, phi = +-90 degrees included), and
    ``b`` (2x3) with d(x, y)/d(X, Y, Z), distortion included (chain rule through its
    Jacobian); an ``a`` of
    2x9 gets the partials by the photo's intrinsics too (:data:`INTRINSICS`); returns the
    computed ``x, y`` and ``w`` (the depth along the optical axis, negative for a point in
    front of the camera).
    """
    f = c[0]
    # q = M d, and its derivatives by the rotation vector theta of the attitude
    # (M' = M R(-theta), :func:`turn`): dq/dtheta = M [d]x, column k = M (e_k x ... ):
    # [d]x = [[0, -d2, d1], [d2, 0, -d0], [-d1, d0, 0]]
    m = rotation9(eo)
    d0, d1, d2 = xyz[0] - eo[3], xyz[1] - eo[4], xyz[2] - eo[5]
    q = (m[0] * d0 + m[1] * d1 + m[2] * d2, m[3] * d0 + m[4] * d1 + m[5] * d2,
         m[6] * d0 + m[7] * d1 + m[8] * d2)
    qw = (m[1] * d2 - m[2] * d1, m[4] * d2 - m[5] * d1, m[7] * d2 - m[8] * d1)
    qp = (-m[0] * d2 + m[2] * d0, -m[3] * d2 + m[5] * d0, -m[6] * d2 + m[8] * d0)
    qk = (m[0] * d1 - m[1] * d0, m[3] * d1 - m[4] * d0, m[6] * d1 - m[7] * d0)
    u, v, w = q[0], q[1], q[2]
    if w == 0.0:  # in the principal plane: no projection (behind the camera, w > 0, the
        return np.nan, np.nan, w  # callers refuse unless told otherwise: BAL problems)
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
    xi, yi = -f * u / w, -f * v / w
    dx, dy, j00, j01, j10, j11 = distortion(xi, yi, c)
    if j00 != 1.0 or j01 != 0.0 or j10 != 0.0 or j11 != 1.0:
        for k in range(6):
            a0, a1 = a[0, k], a[1, k]
            a[0, k] = j00 * a0 + j01 * a1
            a[1, k] = j10 * a0 + j11 * a1
        for k in range(3):
            b0, b1 = b[0, k], b[1, k]
            b[0, k] = j00 * b0 + j01 * b1
            b[1, k] = j10 * b0 + j11 * b1
    if a.shape[1] >= 9:  # the photo's own intrinsics (f, k1 f^2, k2 f^4): see INTRINSICS
        # (forward cameras without affinity: sapgo.adjust refuses the others)
        r2 = xi * xi + yi * yi
        k1, k2, k3, p1, p2 = c[3], c[4], c[5], c[6], c[7]
        rad12 = 1.0 + r2 * (k1 + r2 * k2)
        r6k3 = 7.0 * k3 * r2 * r2 * r2
        tx = 2.0 * (p1 * (r2 + 2.0 * xi * xi) + 2.0 * p2 * xi * yi)
        ty = 2.0 * (p2 * (r2 + 2.0 * yi * yi) + 2.0 * p1 * xi * yi)
        a[0, 6] = (xi * (rad12 + r6k3) + tx) / f
        a[1, 6] = (yi * (rad12 + r6k3) + ty) / f
        f2 = f * f
        a[0, 7] = xi * r2 / f2
        a[1, 7] = yi * r2 / f2
        a[0, 8] = xi * r2 * r2 / (f2 * f2)
        a[1, 8] = yi * r2 * r2 / (f2 * f2)
    return c[1] + xi + dx, c[2] + yi + dy, w


#: The per-photo intrinsics of 9-parameter stations (parameters 6, 7, 8): the focal length
#: and the radial distortion normalised by it, ``k1 f^2`` and ``k2 f^4`` (dimensionless: BAL's
#: k1 and k2); k3, p1, p2 and the principal point stay fixed.
INTRINSICS = ("f", "k1*f^2", "k2*f^4")


def apply_intrinsics(c, d):
    """The camera row ``c`` with its intrinsics moved by ``d`` = (df, d(k1 f^2), d(k2 f^4))."""
    out = np.array(c, dtype=np.float64)
    f0 = out[0]
    f1 = f0 + d[0]
    out[0] = f1
    out[3] = (out[3] * f0 ** 2 + d[1]) / f1 ** 2
    out[4] = (out[4] * f0 ** 4 + d[2]) / f1 ** 4
    return out


#: Self-calibration of shared cameras (a bordered band, docs/theory.md section 1c): the
#: camera fields that can be adjusted, in :data:`CAMERA_FIELDS` order, by their short names
#: (the additional parameters' coefficients of the camera's set last).
CALIBRATION_FIELDS = ("f", "x0", "y0", "k1", "k2", "k3", "p1", "p2", "b1", "b2") + AP_NAMES
N_CALIBRATION = len(CALIBRATION_FIELDS)
#: The camera row's column of each calibration field.
CALIBRATION_COLUMNS = np.concatenate([np.arange(10), AP0 + np.arange(MAX_TERMS)])
#: The border parameter of field ``i`` is the field times ``f ** CALIBRATION_POWERS[i]`` (f
#: at the linearisation point): all of them in image units or dimensionless, so that the
#: border is well scaled whatever the units (k1 f^2, k2 f^4, k3 f^6, p1 f, p2 f, b1, b2;
#: the additional parameters' coefficients are in mm already).
CALIBRATION_POWERS = np.concatenate([np.array([0, 0, 0, 2, 4, 6, 1, 1, 0, 0], np.int64),
                                     np.zeros(MAX_TERMS, np.int64)])


@njit(cache=True, error_model="numpy")
def camera_partials(eo, xyz, c, e, ox, oy):
    """Partial derivatives of an observation's residual by the camera's border parameters.

    Fills ``e`` (2 x :data:`N_CALIBRATION`) with d(x, y) / d(f, x0, y0, k1 f^2, k2 f^4,
    k3 f^6, p1 f, p2 f, b1, b2, a1, ..., a44; the coefficients beyond the camera's
    additional-parameter set left as they are) at station ``eo``, object point ``xyz``, camera row ``c``
    and measurement ``(ox, oy)`` (each scaled border parameter :data:`CALIBRATION_POWERS`,
    f held at its current value in the scaling), of the residual ``computed - observed`` of
    the module docstring. Forward model: ``d xi / d f = xi / f`` through the distortion's
    Jacobian, ``d x / d x0 = 1``, ``d x / d k1 = xi r^2``, ``d x / d p1 = r^2 + 2 xi^2``,
    ``d x / d b1 = xi``, ...; backward model: ``d / d f = xi / f``, the principal point
    through the correction's Jacobian at the measurement, and the distortion terms at the
    measurement with the opposite sign (the corrected measurement is subtracted). Returns
    False in the principal plane (no projection)."""
    f = c[0]
    m = rotation9(eo)
    d0, d1, d2 = xyz[0] - eo[3], xyz[1] - eo[4], xyz[2] - eo[5]
    u = m[0] * d0 + m[1] * d1 + m[2] * d2
    v = m[3] * d0 + m[4] * d1 + m[5] * d2
    w = m[6] * d0 + m[7] * d1 + m[8] * d2
    if w == 0.0:
        return False
    xi, yi = -f * u / w, -f * v / w
    f2 = f * f
    if c[MODEL] != 0.0:   # backward: -d(correction)/d(parameter) at the measurement
        xm, ym = ox - c[1], oy - c[2]
        _, _, j00, j01, j10, j11 = brown(xm, ym, c)
        e[0, 0] = xi / f
        e[1, 0] = yi / f
        e[0, 1] = j00
        e[1, 1] = j10
        e[0, 2] = j01
        e[1, 2] = j11
        sign = -1.0
    else:
        _, _, j00, j01, j10, j11 = brown(xi, yi, c)
        e[0, 0] = (j00 * xi + j01 * yi) / f
        e[1, 0] = (j10 * xi + j11 * yi) / f
        e[0, 1] = 1.0
        e[1, 1] = 0.0
        e[0, 2] = 0.0
        e[1, 2] = 1.0
        xm, ym = xi, yi
        sign = 1.0
    r2 = xm * xm + ym * ym
    q = r2 / f2
    e[0, 3] = sign * xm * q
    e[1, 3] = sign * ym * q
    e[0, 4] = sign * xm * q * q
    e[1, 4] = sign * ym * q * q
    e[0, 5] = sign * xm * q * q * q
    e[1, 5] = sign * ym * q * q * q
    e[0, 6] = sign * (r2 + 2.0 * xm * xm) / f
    e[1, 6] = sign * 2.0 * xm * ym / f
    e[0, 7] = sign * 2.0 * xm * ym / f
    e[1, 7] = sign * (r2 + 2.0 * ym * ym) / f
    e[0, 8] = sign * xm
    e[1, 8] = 0.0
    e[0, 9] = sign * ym
    e[1, 9] = 0.0
    ap_partials(xm, ym, int(c[AP_SET]), c[AP_BASE], sign, e, 10)
    return True


def apply_calibration(c, dtheta):
    """The camera row ``c`` moved by the border step ``dtheta`` (:data:`N_CALIBRATION`:
    df, dx0, dy0, d(k1 f^2), d(k2 f^4), d(k3 f^6), d(p1 f), d(p2 f), db1, db2, da1, ...,
    da44, scaled by the current f as in :func:`camera_partials`)."""
    out = np.array(c, dtype=np.float64)
    f0 = out[0]
    out[CALIBRATION_COLUMNS] += (np.asarray(dtheta, dtype=np.float64)
                                 / f0 ** CALIBRATION_POWERS)
    return out


@njit(cache=True, error_model="numpy")
def _add_ray(eo, x, y, c, a, r):
    """Add the ray from station ``eo`` through image point (x, y) of camera row ``c`` to the
    normal system (the image point freed of distortion first); False (nothing added) when
    the distortion cannot be inverted there."""
    m = rotation9(eo)
    i0, i1, ok = undistort(x, y, c)
    if not ok:
        return False
    i2 = -c[0]
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
    return True


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
def intersect(eo_rays, xy_rays, cam_rays):
    """Least-squares intersection of image rays: the point nearest to all of them.

    Each ray ``i`` is the line from station ``eo_rays[i]`` through image point ``xy_rays[i]``
    of camera row ``cam_rays[i]``. Returns the point and a flag that is False when the rays
    are (nearly) parallel or fewer than two.
    """
    n = eo_rays.shape[0]
    a = np.zeros((3, 3))
    r = np.zeros(3)
    out = np.zeros(3)
    good = True
    for i in range(n):
        good &= _add_ray(eo_rays[i], xy_rays[i, 0], xy_rays[i, 1], cam_rays[i], a, r)
    if n < 2 or not good or not _solve_sym3(a, r, out):
        return np.zeros(3), False
    return out, True


@njit(cache=True, error_model="numpy")
def intersect_points(obs_start, n_obs, obs_station, obs_xy, eo, cam_of_station, cams, out,
                     ok):
    """Intersect every point from its rays (chunk kernel: indices relative to the chunk)."""
    a = np.empty((3, 3))
    r = np.empty(3)
    p = np.empty(3)
    for j in range(obs_start.shape[0]):
        a[:, :] = 0.0
        r[:] = 0.0
        good = True
        for i in range(obs_start[j], obs_start[j] + n_obs[j]):
            st = obs_station[i]
            c = cam_of_station[st]
            good &= _add_ray(eo[st], obs_xy[i, 0], obs_xy[i, 1], cams[c], a, r)
        good = good and n_obs[j] >= 2 and _solve_sym3(a, r, p)
        ok[j] = good
        for k in range(3):
            out[j, k] = p[k] if good else 0.0


@njit(cache=True, error_model="numpy")
def undistort_points(xy, cam_of_row, cams, out):
    """Ideal image coordinates (from the principal point) of the image points ``xy`` (n x 2)
    taken with cameras ``cams[cam_of_row]``, into ``out`` (nan where Newton fails)."""
    for i in range(xy.shape[0]):
        xi, yi, ok = undistort(xy[i, 0], xy[i, 1], cams[cam_of_row[i]])
        out[i, 0] = xi if ok else np.nan
        out[i, 1] = yi if ok else np.nan


@njit(cache=True, error_model="numpy")
def project_observations(station_of_obs, point_of_obs, eo, xyz, cam_of_station, cams, out):
    """Image coordinates of every (station, point) pair into ``out`` (n x 2, mm)."""
    for i in range(station_of_obs.shape[0]):
        s = station_of_obs[i]
        c = cam_of_station[s]
        x, y = project(eo[s], xyz[point_of_obs[i]], cams[c])
        out[i, 0] = x
        out[i, 1] = y
