"""Slow, obvious reference implementations the fast kernels are tested against.

Nothing here shares code with ``sapgo``'s kernels: the rotation, the projection, the Jacobian
(complex-step differentiation, exact to rounding) and the dense normal equations are written
again in plain numpy.
"""

import numpy as np
import scipy.linalg


def rotation(omega, phi, kappa):
    """M = R3(kappa) R2(phi) R1(omega); works for complex arguments (complex step)."""
    cw, sw = np.cos(omega), np.sin(omega)
    cp, sp = np.cos(phi), np.sin(phi)
    ck, sk = np.cos(kappa), np.sin(kappa)
    one, zero = np.ones_like(cw), np.zeros_like(cw)
    r1 = np.array([[one, zero, zero], [zero, cw, sw], [zero, -sw, cw]])
    r2 = np.array([[cp, zero, -sp], [zero, one, zero], [sp, zero, cp]])
    r3 = np.array([[ck, sk, zero], [-sk, ck, zero], [zero, zero, one]])
    return np.einsum("ij...,jk...,kl...->il...", r3, r2, r1)


class Terms(tuple):
    """A ``dist`` tuple (k1, k2, k3, p1, p2, b1, b2, t1, ..., tm) whose last m values are
    the coefficients of the displacement fields ``terms(u, v)`` (m x 2, works for complex
    arguments): additional parameters."""

    def __new__(cls, values, terms):
        out = super().__new__(cls, values)
        out.terms = terms
        return out


def _polynomial(u, v, dist):
    """Brown's radial and decentring distortion and the affinity and shear of the x axis at
    ``(u, v)``: ``dist`` = (k1, k2, k3, p1, p2[, b1, b2]), or :class:`Terms` with
    additional parameters after them."""
    k1, k2, k3, p1, p2 = dist[:5]
    b1, b2 = dist[5:7] if len(dist) > 5 else (0.0, 0.0)
    r2 = u ** 2 + v ** 2
    rad = k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    dx = u * rad + p1 * (r2 + 2 * u ** 2) + 2 * p2 * u * v + b1 * u + b2 * v
    dy = v * rad + p2 * (r2 + 2 * v ** 2) + 2 * p1 * u * v
    terms = getattr(dist, "terms", None)
    if terms is not None:
        for a, (tx, ty) in zip(dist[7:], terms(u, v)):
            dx = dx + a * tx
            dy = dy + a * ty
    return dx, dy


def project(eo, xyz, f, x0=0.0, y0=0.0, dist=None):
    """Collinearity for arrays: eo (..., 6), xyz (..., 3) -> (..., 2); ``dist`` = Brown's
    (k1, k2, k3, p1, p2[, b1, b2]) added to the ideal image point (the forward model; works
    for complex arguments)."""
    m = rotation(eo[..., 0], eo[..., 1], eo[..., 2])
    d = xyz - eo[..., 3:6]
    q = np.einsum("ij...,...j->...i", m, d)
    xi, yi = -f * q[..., 0] / q[..., 2], -f * q[..., 1] / q[..., 2]
    if dist is not None:
        dx, dy = _polynomial(xi, yi, dist)
        xi, yi = xi + dx, yi + dy
    return np.stack([x0 + xi, y0 + yi], axis=-1)


def corrected(xy, x0, y0, dist):
    """The backward model: measured image points ``xy`` (..., 2) corrected by the
    distortion polynomial taken at them (from the principal point)."""
    dx, dy = _polynomial(xy[..., 0] - x0, xy[..., 1] - y0, dist)
    return np.stack([xy[..., 0] + dx, xy[..., 1] + dy], axis=-1)


def project_turned(eo, theta, xyz, f, x0=0.0, y0=0.0, dist=None):
    """The projection by the photo ``eo`` turned by the rotation vector ``theta`` to first
    order, ``M (I - [theta]x)`` (sapgo turns by ``M exp(-[theta]x)``: the same first
    derivative, all a complex step sees)."""
    m = rotation(eo[0], eo[1], eo[2])
    t0, t1, t2 = theta
    skew = np.array([[0, -t2, t1], [t2, 0, -t0], [-t1, t0, 0]])
    m = m @ (np.eye(3) - skew)
    q = m @ (xyz - eo[3:6])
    xi, yi = -f * q[0] / q[2], -f * q[1] / q[2]
    if dist is not None:
        dx, dy = _polynomial(xi, yi, dist)
        xi, yi = xi + dx, yi + dy
    return np.array([x0 + xi, y0 + yi])


def jacobian_rotvec_complex_step(eo, xyz, f, x0=0.0, y0=0.0, h=1e-30, dist=None):
    """d(x, y)/d(theta, Xc, xyz) for one ray by complex step, the attitude's unknowns the
    rotation vector of :func:`project_turned`: (2 x 6), (2 x 3)."""
    jac = np.zeros((2, 9))
    for k in range(3):
        t = np.zeros(3, complex)
        t[k] = 1j * h
        jac[:, k] = project_turned(eo.astype(complex), t, xyz.astype(complex), f, x0, y0,
                                   dist).imag / h
    p = np.concatenate([eo, xyz]).astype(complex)
    for k in range(3, 9):
        q = p.copy()
        q[k] += 1j * h
        jac[:, k] = project(q[:6], q[6:], f, x0, y0, dist).imag / h
    return jac[:, :6], jac[:, 6:]


def jacobian_complex_step(eo, xyz, f, x0=0.0, y0=0.0, h=1e-30, dist=None):
    """d(x, y)/d(eo, xyz) for one ray by complex step: (2 x 6), (2 x 3)."""
    p = np.concatenate([eo, xyz]).astype(complex)
    jac = np.zeros((2, 9))
    for k in range(9):
        q = p.copy()
        q[k] += 1j * h
        jac[:, k] = project(q[:6], q[6:], f, x0, y0, dist).imag / h
    return jac[:, :6], jac[:, 6:]


def reduced_normals_dense(eo, xyz, f, obs_station, obs_point, obs_xy, obs_sigma,
                          ctrl_mask=None, ctrl=None, ctrl_sigma=None):
    """Full normal matrix of stations and points, reduced with numpy: (M, d).

    Builds ``N = J' P J`` and ``c = J' P l`` over all unknowns, then
    ``M = N_ss - N_sp N_pp^-1 N_ps``, ``d = c_s - N_sp N_pp^-1 c_p`` densely.
    """
    ns, npnt = len(eo), len(xyz)
    nu = 6 * ns + 3 * npnt
    n = np.zeros((nu, nu))
    c = np.zeros(nu)
    for i in range(len(obs_station)):
        s, j = obs_station[i], obs_point[i]
        a, b = jacobian_complex_step(eo[s], xyz[j], f)
        row = np.zeros((2, nu))
        row[:, 6 * s:6 * s + 6] = a
        row[:, 6 * ns + 3 * j:6 * ns + 3 * j + 3] = b
        misclosure = obs_xy[i] - project(eo[s], xyz[j], f)
        w = 1.0 / obs_sigma[i] ** 2
        n += w * row.T @ row
        c += w * row.T @ misclosure
    if ctrl_mask is not None:
        for j in range(npnt):
            for k in range(3):
                if ctrl_mask[j, k]:
                    w = 1.0 / ctrl_sigma[j, k] ** 2
                    q = 6 * ns + 3 * j + k
                    n[q, q] += w
                    c[q] += w * (ctrl[j, k] - xyz[j, k])
    s = slice(0, 6 * ns)
    p = slice(6 * ns, nu)
    npp_inv_nps = np.linalg.solve(n[p, p], n[p, s])
    m = n[s, s] - n[s, p] @ npp_inv_nps
    d = c[s] - n[s, p] @ np.linalg.solve(n[p, p], c[p])
    return m, d


#: Camera fields in sapgo's order (f, x0, y0, k1, k2, k3, p1, p2, b1, b2).
CAMERA_FIELDS = ("f", "x0", "y0", "k1", "k2", "k3", "p1", "p2", "b1", "b2")


def dense_bundle_adjustment(eo, xyz, f, obs_station, obs_point, obs_xy, obs_sigma, ctrl_mask,
                            ctrl, ctrl_sigma, iterations=30, tol=1e-11, dist=None,
                            calibrate=(), x0=0.0, y0=0.0, model="forward",
                            calibrate_per_photo=(), fixed_station=None, terms=None,
                            n_terms=0):
    """Gauss-Newton on the full dense normal equations (no reduction, no band).

    Control components with sigma 0 are held at their control values. ``calibrate``: names
    of the (one) camera's fields adjusted too (self-calibration; raw units, derivatives by
    complex step, the normal equations scaled to a unit diagonal); ``calibrate_per_photo``:
    fields adjusted per photo (each photo its own unknown). Returns adjusted ``(eo, xyz,
    sigma0, iterations)``, and with calibration the camera row (f, x0, y0, k1, k2, k3, p1,
    p2, b1, b2) as a fifth element (per photo, n x 10, with ``calibrate_per_photo``) and the
    cofactors of the adjusted fields as a sixth (the shared ones, then per photo, photo by
    photo). ``model`` "backward": the residual is the ideal projection minus the
    measurement corrected by ``dist`` at it (:func:`corrected`). ``fixed_station`` (n x 6
    bools): station parameters held at their values (no unknowns). ``terms``: additional
    parameters, ``n_terms`` displacement fields ``terms(u, v)`` (:class:`Terms`) whose
    coefficients ``a1 .. a<n_terms>`` follow the ten fields in the camera row (``dist``
    may give their values after b1, b2) and can be calibrated by those names.
    """
    eo = eo.astype(float).copy()
    xyz = xyz.astype(float).copy()
    given = list(dist if dist is not None else ())
    d7 = (given[:7] + [0.0] * 7)[:7]
    ext = (given[7:] + [0.0] * n_terms)[:n_terms]
    ns, npnt = len(eo), len(xyz)
    cs = np.tile(np.array([f, x0, y0, *d7, *ext], dtype=float), (ns, 1))   # a row per photo
    names = CAMERA_FIELDS + tuple(f"a{i + 1}" for i in range(n_terms))
    cal = [names.index(n) for n in calibrate]
    per = [names.index(n) for n in calibrate_per_photo]

    def dist_of(c):
        return Terms(tuple(c[3:]), terms) if terms is not None else tuple(c[3:])
    ncal, nper = len(cal), len(per)
    ncam = ncal + ns * nper
    fixed = ctrl_mask & (ctrl_sigma == 0)
    xyz[fixed] = ctrl[fixed]
    weighted = ctrl_mask & (ctrl_sigma > 0)
    free_pt = ~fixed.ravel()
    free_st = (np.ones(6 * ns, bool) if fixed_station is None
               else ~np.asarray(fixed_station, bool).ravel())
    index = np.concatenate([free_st, free_pt, np.ones(ncam, bool)])
    nobs = len(obs_station)
    base = 6 * ns + 3 * npnt

    def resid(e, x, c, o):   # computed minus observed (the backward model's: corrected)
        if model == "backward":
            return project(e, x, c[0], c[1], c[2]) - corrected(o, c[1], c[2], dist_of(c))
        return project(e, x, c[0], c[1], c[2], dist=dist_of(c)) - o

    def resid_rows(e, x, c, o):   # resid of many rays, a camera row each (n x 2)
        dist = tuple(c[:, 3:].T)
        if terms is not None:
            dist = Terms(dist, terms)
        if model == "backward":
            return (project(e, x, c[:, 0], c[:, 1], c[:, 2])
                    - corrected(o, c[:, 1], c[:, 2], dist))
        return project(e, x, c[:, 0], c[:, 1], c[:, 2], dist=dist) - o

    for it in range(1, iterations + 1):
        jac = np.zeros((2 * nobs + weighted.sum(), base + ncam))
        res = np.zeros(jac.shape[0])
        for i in range(nobs):
            s, j = obs_station[i], obs_point[i]
            cam = cs[s]
            a, b = jacobian_complex_step(eo[s], xyz[j], cam[0], cam[1], cam[2],
                                         dist=None if model == "backward" else dist_of(cam))
            sw = 1.0 / obs_sigma[i]
            jac[2 * i:2 * i + 2, 6 * s:6 * s + 6] = a * sw
            jac[2 * i:2 * i + 2, 6 * ns + 3 * j:6 * ns + 3 * j + 3] = b * sw
            res[2 * i:2 * i + 2] = resid(eo[s], xyz[j], cam, obs_xy[i]) * sw
        # the camera columns by complex step, all observations at once
        rows = np.arange(nobs)
        e_all, x_all, c_all = eo[obs_station], xyz[obs_point], cs[obs_station]
        sw_all = 1.0 / obs_sigma
        cols = [(np.full(nobs, base + q), k) for q, k in enumerate(cal)]
        cols += [(base + ncal + obs_station * nper + q, k) for q, k in enumerate(per)]
        for col, k in cols:
            c = c_all.astype(complex)
            h = 1e-30 * np.maximum(np.abs(c_all[:, k]), 1e-30)
            c[:, k] += 1j * h
            d = (resid_rows(e_all, x_all, c, obs_xy).imag / h[:, None]) * sw_all[:, None]
            jac[2 * rows, col] = d[:, 0]
            jac[2 * rows + 1, col] = d[:, 1]
        r = 2 * nobs
        for j, k in zip(*np.nonzero(weighted)):
            jac[r, 6 * ns + 3 * j + k] = 1.0 / ctrl_sigma[j, k]
            res[r] = (xyz[j, k] - ctrl[j, k]) / ctrl_sigma[j, k]
            r += 1
        jr = jac[:, index]
        scale = 1.0 / np.sqrt((jr * jr).sum(axis=0))
        jr = jr * scale
        n = jr.T @ jr
        g = jr.T @ res
        dx = np.zeros(len(index))
        dx[index] = -scale * scipy.linalg.solve(n, g, assume_a="pos")
        eo += dx[:6 * ns].reshape(ns, 6)
        xyz += dx[6 * ns:base].reshape(npnt, 3)
        dc = dx[base:]
        cs[:, cal] += dc[:ncal]
        if nper:
            cs[:, per] += dc[ncal:].reshape(ns, nper)
        moved = np.concatenate([cs[0, cal], cs[:, per].ravel()]) if ncam else np.zeros(0)
        if np.abs(dx[:base]).max() < tol and (
                not ncam or (np.abs(dc) <= 1e-12 * np.abs(moved)).all()):
            break
    # final residuals
    v = np.array([resid(eo[s], xyz[j], cs[s], obs_xy[i])
                  for i, (s, j) in enumerate(zip(obs_station, obs_point))])
    vpv = float(((v / obs_sigma[:, None]) ** 2).sum())
    vc = (xyz - ctrl)[weighted] / ctrl_sigma[weighted]
    vpv += float((vc ** 2).sum())
    redundancy = (2 * nobs + weighted.sum() - int(free_st.sum()) - 3 * npnt + fixed.sum()
                  - ncam)
    if ncam:  # and the camera parameters' cofactors (the inverse of the last normals)
        q = scale[:, None] * np.linalg.inv(n) * scale[None, :]
        return (eo, xyz, np.sqrt(vpv / redundancy), it, cs if nper else cs[0],
                np.diag(q)[-ncam:])
    return eo, xyz, np.sqrt(vpv / redundancy), it


def banded_from_dense(m, band_width):
    """scipy ``cholesky_banded`` upper storage ``ab[u + i - j, j] == a[i, j]`` of ``m``."""
    u = 6 * band_width - 1
    n = m.shape[0]
    ab = np.zeros((u + 1, n))
    for j in range(n):
        for i in range(max(0, j - u), j + 1):
            ab[u + i - j, j] = m[i, j]
    return ab
