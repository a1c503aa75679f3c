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


def project(eo, xyz, f, x0=0.0, y0=0.0, dist=None):
    """Collinearity for arrays: eo (..., 6), xyz (..., 3) -> (..., 2); ``dist`` = Brown's
    (k1, k2, k3, p1, p2) added to the ideal image point (works for complex arguments)."""
    m = rotation(eo[..., 0], eo[..., 1], eo[..., 2])
    d = xyz - eo[..., 3:6]
    q = np.einsum("ij...,...j->...i", m, d)
    xi, yi = -f * q[..., 0] / q[..., 2], -f * q[..., 1] / q[..., 2]
    if dist is not None:
        k1, k2, k3, p1, p2 = dist
        r2 = xi ** 2 + yi ** 2
        rad = k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
        xi, yi = (xi + xi * rad + p1 * (r2 + 2 * xi ** 2) + 2 * p2 * xi * yi,
                  yi + yi * rad + p2 * (r2 + 2 * yi ** 2) + 2 * p1 * xi * yi)
    return np.stack([x0 + xi, y0 + yi], axis=-1)


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


#: Camera fields in sapgo's order (f, x0, y0, k1, k2, k3, p1, p2).
CAMERA_FIELDS = ("f", "x0", "y0", "k1", "k2", "k3", "p1", "p2")


def dense_bundle_adjustment(eo, xyz, f, obs_station, obs_point, obs_xy, obs_sigma, ctrl_mask,
                            ctrl, ctrl_sigma, iterations=30, tol=1e-11, dist=None,
                            calibrate=(), x0=0.0, y0=0.0):
    """Gauss-Newton on the full dense normal equations (no reduction, no band).

    Control components with sigma 0 are held at their control values. ``calibrate``: names
    of the (one) camera's fields adjusted too (self-calibration; raw units, derivatives by
    complex step, the normal equations scaled to a unit diagonal). Returns adjusted
    ``(eo, xyz, sigma0, iterations)``, and the camera row (f, x0, y0, k1, k2, k3, p1, p2) as
    a fifth element and the
    cofactors of the adjusted fields as a sixth when ``calibrate`` is given.
    """
    eo = eo.astype(float).copy()
    xyz = xyz.astype(float).copy()
    cam = np.array([f, x0, y0, *(dist if dist is not None else (0.0,) * 5)], dtype=float)
    cal = [CAMERA_FIELDS.index(n) for n in calibrate]
    ncal = len(cal)
    fixed = ctrl_mask & (ctrl_sigma == 0)
    xyz[fixed] = ctrl[fixed]
    weighted = ctrl_mask & (ctrl_sigma > 0)
    ns, npnt = len(eo), len(xyz)
    free_pt = ~fixed.ravel()
    index = np.concatenate([np.ones(6 * ns, bool), free_pt, np.ones(ncal, bool)])
    nobs = len(obs_station)

    def proj(e, x, c):
        return project(e, x, c[0], c[1], c[2], dist=tuple(c[3:]))

    for it in range(1, iterations + 1):
        jac = np.zeros((2 * nobs + weighted.sum(), 6 * ns + 3 * npnt + ncal))
        res = np.zeros(jac.shape[0])
        for i in range(nobs):
            s, j = obs_station[i], obs_point[i]
            a, b = jacobian_complex_step(eo[s], xyz[j], cam[0], cam[1], cam[2],
                                         dist=tuple(cam[3:]))
            sw = 1.0 / obs_sigma[i]
            jac[2 * i:2 * i + 2, 6 * s:6 * s + 6] = a * sw
            jac[2 * i:2 * i + 2, 6 * ns + 3 * j:6 * ns + 3 * j + 3] = b * sw
            for q, k in enumerate(cal):
                c = cam.astype(complex)
                c[k] += 1e-30j * max(abs(cam[k]), 1e-30)
                jac[2 * i:2 * i + 2, 6 * ns + 3 * npnt + q] = (
                    proj(eo[s], xyz[j], c).imag / (1e-30 * max(abs(cam[k]), 1e-30)) * sw)
            res[2 * i:2 * i + 2] = (proj(eo[s], xyz[j], cam) - obs_xy[i]) * sw
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
        xyz += dx[6 * ns:6 * ns + 3 * npnt].reshape(npnt, 3)
        cam[cal] += dx[6 * ns + 3 * npnt:]
        if np.abs(dx[:6 * ns + 3 * npnt]).max() < tol and (
                not ncal or (np.abs(dx[6 * ns + 3 * npnt:]) <= 1e-12 * np.abs(cam[cal])).all()):
            break
    # final residuals
    v = proj(eo[obs_station], xyz[obs_point], cam) - obs_xy
    vpv = float(((v / obs_sigma[:, None]) ** 2).sum())
    vc = (xyz - ctrl)[weighted] / ctrl_sigma[weighted]
    vpv += float((vc ** 2).sum())
    redundancy = 2 * nobs + weighted.sum() - 6 * ns - 3 * npnt + fixed.sum() - ncal
    if ncal:  # and the camera parameters' cofactors (the inverse of the last normals)
        q = scale[:, None] * np.linalg.inv(n) * scale[None, :]
        return eo, xyz, np.sqrt(vpv / redundancy), it, cam, np.diag(q)[-ncal:]
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
