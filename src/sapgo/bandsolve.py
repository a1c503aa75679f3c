"""Recursive-partitioning block-banded Cholesky, in and out of core (DESIGN section 5).

Storage: the reduced matrix ``M`` (n stations, 6x6 blocks, band width ``b`` stations) is kept
as band rows ``band[i] = [M[i,i], M[i,i+1], ..., M[i,i+b-1]]`` (6 x 6b each; blocks past the
last station are zero). Element ``band[i, r, 6k + c] == M[6i + r, 6(i+k) + c]``.

Factorisation ``M = U' U`` with ``U`` upper block-banded of the same band (Elphingstone & Wong
1973; seeds/002 "Solution of reduced normal equations"), station by station:

    U[i,i]     = chol(M[i,i])                       (upper, 6x6)
    U[i,i+k]   = U[i,i]'^-1 M[i,i+k]                k = 1 .. b-1
    M[i+k,i+l] -= U[i,i+k]' U[i,i+l]                1 <= k <= l <= b-1
    y[i]       = U[i,i]'^-1 d[i];   d[i+k] -= U[i,i+k]' y[i]

Row ``i`` only changes rows ``i+1 .. i+b-1``, so a window of ``b + chunk`` rows in core is
enough: rows are read in station order, factored, and written back (factor row over band row);
back substitution ``delta[i] = U[i,i]^-1 (y[i] - sum_k U[i,i+k] delta[i+k])`` then reads the
factor rows in reverse. A pivot that is not positive (relative to the row's original diagonal)
stops the factorisation and names the station.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: A pivot at or below this fraction of the original diagonal element counts as zero.
PIVOT_TOLERANCE = 1e-12


@njit(cache=True)
def factor_rows(band, rhs, orig_diag, r_lo, r_hi, n_valid, pivot_tol):
    """Factor window rows ``r_lo .. r_hi-1`` in place and push their updates forward.

    Rows ``r_hi .. n_valid-1`` of the window receive the updates (they must hold the rows
    that follow). ``rhs`` is forward-substituted along. Returns ``(-1, -1)`` or the window row
    and parameter (0-5) of the first non-positive pivot.
    """
    width = band.shape[2]
    bw = width // 6
    for r in range(r_lo, r_hi):
        # --- U[i,i]: upper Cholesky of the 6x6 diagonal block (upper triangle is used)
        for i in range(6):
            s = band[r, i, i]
            for k in range(i):
                s -= band[r, k, i] * band[r, k, i]
            if not (s > pivot_tol * orig_diag[r, i]) or not (s > 0.0):
                return r, i
            d = np.sqrt(s)
            band[r, i, i] = d
            for j in range(i + 1, 6):
                t = band[r, i, j]
                for k in range(i):
                    t -= band[r, k, i] * band[r, k, j]
                band[r, i, j] = t / d
        for i in range(1, 6):
            for j in range(i):
                band[r, i, j] = 0.0
        # --- U[i,i+k] = U[i,i]'^-1 M[i,i+k]  (forward substitution, column by column)
        for c in range(6, width):
            for i in range(6):
                t = band[r, i, c]
                for k in range(i):
                    t -= band[r, k, i] * band[r, k, c]
                band[r, i, c] = t / band[r, i, i]
        _forward_row(band, rhs, r, n_valid)
        # --- update the following rows: M[i+k, i+l] -= U[i,i+k]' U[i,i+l]
        for k in range(1, bw):
            rr = r + k
            if rr >= n_valid:
                break
            c0 = 6 * k
            for a in range(6):
                for c in range(c0, width):
                    t = 0.0
                    for m in range(6):
                        t += band[r, m, c0 + a] * band[r, m, c]
                    band[rr, a, c - c0] -= t
    return -1, -1


@njit(cache=True)
def _forward_row(factor, y, r, n_valid):
    """Forward substitution of row ``r``: ``y[r] <- U[r,r]'^-1 y[r]``, then
    ``y[r+k] -= U[r,r+k]' y[r]`` for the following rows below ``n_valid``."""
    width = factor.shape[2]
    for i in range(6):
        t = y[r, i]
        for k in range(i):
            t -= factor[r, k, i] * y[r, k]
        y[r, i] = t / factor[r, i, i]
    for k in range(1, width // 6):
        rr = r + k
        if rr >= n_valid:
            break
        for a in range(6):
            t = 0.0
            for m in range(6):
                t += factor[r, m, 6 * k + a] * y[r, m]
            y[rr, a] -= t


@njit(cache=True)
def back_substitute(factor, y, delta_next, n_next, out):
    """Back substitution for rows ``len(factor)-1 .. 0`` of a block of factor rows.

    ``delta_next`` holds the solution of the ``n_next`` rows that follow the block (already
    solved); ``out`` receives the block's solution.
    """
    n = factor.shape[0]
    width = factor.shape[2]
    bw = width // 6
    for r in range(n - 1, -1, -1):
        t = np.empty(6)
        for i in range(6):
            t[i] = y[r, i]
        for k in range(1, bw):
            rr = r + k
            if rr < n:
                x = out[rr]
            elif rr - n < n_next:
                x = delta_next[rr - n]
            else:
                break
            for i in range(6):
                s = 0.0
                for c in range(6):
                    s += factor[r, i, 6 * k + c] * x[c]
                t[i] -= s
        for i in range(5, -1, -1):
            s = t[i]
            for c in range(i + 1, 6):
                s -= factor[r, i, c] * out[r, c]
            out[r, i] = s / factor[r, i, i]


class PivotError(Exception):
    """Raised by the drivers with the station (row) and parameter of a failed pivot."""

    def __init__(self, row, parameter):
        super().__init__(f"non-positive pivot at row {row}, parameter {parameter}")
        self.row = row
        self.parameter = parameter


def solve_out_of_core(band_ds, rhs_ds, band_width, chunk_rows=256, pivot_tol=PIVOT_TOLERANCE,
                      progress=None):
    """Factor the band rows of dataset ``band_ds`` in place and solve for ``rhs_ds``.

    ``band_ds`` (n x 6 x 6b) and ``rhs_ds`` (n x 6) are HDF5 datasets (or arrays). The factor
    rows overwrite the band rows and the forward-substituted right-hand side overwrites
    ``rhs_ds``; returns the solution ``delta`` (n x 6). In core: ``b + chunk_rows`` rows.
    """
    n = band_ds.shape[0]
    bw = band_width
    width = 6 * bw
    if band_ds.shape[1:] != (6, width):
        raise ValueError(f"band rows have shape {band_ds.shape[1:]}, expected (6, {width})")
    cap = min(n, bw + max(1, chunk_rows))
    band = np.zeros((cap, 6, width))
    rhs = np.zeros((cap, 6))
    orig = np.zeros((cap, 6))
    base = 0
    loaded = min(n, cap)
    band[:loaded] = band_ds[0:loaded]
    rhs[:loaded] = rhs_ds[0:loaded]
    orig[:loaded] = np.abs(np.diagonal(band[:loaded], axis1=1, axis2=2))
    while base < n:
        hi = n if loaded == n else loaded - bw + 1
        r, i = factor_rows(band, rhs, orig, 0, hi - base, loaded - base, pivot_tol)
        if r >= 0:
            raise PivotError(base + r, i)
        m = hi - base
        band_ds[base:hi] = band[:m]
        rhs_ds[base:hi] = rhs[:m]
        if progress is not None:
            progress(m)
        keep = loaded - hi
        band[:keep] = band[m:m + keep]
        rhs[:keep] = rhs[m:m + keep]
        orig[:keep] = orig[m:m + keep]
        base = hi
        new_loaded = min(n, base + cap)
        if new_loaded > loaded:
            k0, k1 = keep, keep + new_loaded - loaded
            band[k0:k1] = band_ds[loaded:new_loaded]
            rhs[k0:k1] = rhs_ds[loaded:new_loaded]
            orig[k0:k1] = np.abs(np.diagonal(band[k0:k1], axis1=1, axis2=2))
            loaded = new_loaded
    # back substitution, factor rows read in reverse blocks
    delta = np.zeros((n, 6))
    step = max(1, chunk_rows)
    stop = n
    while stop > 0:
        start = max(0, stop - step)
        factor = np.ascontiguousarray(band_ds[start:stop])
        y = np.ascontiguousarray(rhs_ds[start:stop])
        nxt = np.ascontiguousarray(delta[stop:min(n, stop + bw)])
        out = np.zeros((stop - start, 6))
        back_substitute(factor, y, nxt, len(nxt), out)
        delta[start:stop] = out
        stop = start
    return delta


def solve_in_core(band, rhs, pivot_tol=PIVOT_TOLERANCE):
    """Factor band rows ``band`` (n x 6 x 6b) and solve; returns ``(factor, delta)``.

    The same kernels as the out-of-core path with the whole band in one window.
    """
    band = np.array(band, dtype=np.float64, order="C")
    y = np.array(rhs, dtype=np.float64, order="C")
    n = band.shape[0]
    orig = np.abs(np.diagonal(band, axis1=1, axis2=2)).copy()
    r, i = factor_rows(band, y, orig, 0, n, n, pivot_tol)
    if r >= 0:
        raise PivotError(r, i)
    delta = np.zeros((n, 6))
    back_substitute(band, y, np.zeros((0, 6)), 0, delta)
    return band, delta


def band_to_dense(band):
    """The full symmetric matrix of band rows (for tests and small problems)."""
    n, _, width = band.shape
    bw = width // 6
    a = np.zeros((6 * n, 6 * n))
    for i in range(n):
        for k in range(bw):
            j = i + k
            if j >= n:
                break
            blk = band[i, :, 6 * k:6 * k + 6]
            a[6 * i:6 * i + 6, 6 * j:6 * j + 6] = blk
            if k:
                a[6 * j:6 * j + 6, 6 * i:6 * i + 6] = blk.T
            else:
                a[6 * i:6 * i + 6, 6 * i:6 * i + 6] = np.triu(blk) + np.triu(blk, 1).T
    return a


def dense_to_band(a, band_width):
    """Band rows of a symmetric block-banded matrix (inverse of :func:`band_to_dense`)."""
    n = a.shape[0] // 6
    band = np.zeros((n, 6, 6 * band_width))
    for i in range(n):
        for k in range(band_width):
            j = i + k
            if j >= n:
                break
            band[i, :, 6 * k:6 * k + 6] = a[6 * i:6 * i + 6, 6 * j:6 * j + 6]
    return band


# -- drop-in replacements for scipy.linalg.cholesky_banded / cho_solve_banded -----------

def _block_indices(n_blocks, bw):
    """Scalar (row, col) of every element of the band rows ``(n_blocks, 6, 6 bw)``."""
    i = np.arange(n_blocks)[:, None, None]
    r = np.arange(6)[None, :, None]
    kc = np.arange(6 * bw)[None, None, :]
    p = 6 * i + r
    q = 6 * i + kc
    return np.broadcast_to(p, (n_blocks, 6, 6 * bw)), np.broadcast_to(q, (n_blocks, 6, 6 * bw))


def _to_blocks(ab, lower, triangle):
    """Band rows of a LAPACK banded array ``ab`` (u + 1, n) of either form.

    ``triangle``: only the elements on and above the diagonal (a triangular factor ``U``;
    a lower-form ``L`` is read as ``U = L'``); otherwise the symmetric matrix. The scalar
    order is padded to a multiple of 6 with an identity. Returns ``(band, n, u)``.
    """
    ab = np.asarray(ab)
    if ab.ndim != 2:
        raise ValueError(f"expected a 2-D banded array (u + 1, n), got shape {ab.shape}")
    n, u = ab.shape[1], ab.shape[0] - 1
    nb = max(1, -(-n // 6))
    p, q = _block_indices(nb, (u + 5) // 6 + 1)
    lo, hi = np.minimum(p, q), np.maximum(p, q)
    ok = (hi - lo <= u) & (hi < n)
    if triangle:
        ok &= q >= p
    band = np.zeros(p.shape)
    if lower:  # ab[i - j, j] = a[i, j] for i >= j: element (hi, lo)
        band[ok] = ab[(hi - lo)[ok], lo[ok]]
    else:  # ab[u + i - j, j] = a[i, j] for i <= j
        band[ok] = ab[(u + lo - hi)[ok], hi[ok]]
    pad = np.arange(n, 6 * nb)
    band[pad // 6, pad % 6, pad % 6] = 1.0
    return band, n, u


def scipy_to_band(ab, lower=False):
    """Band rows (6x6 station blocks) of a symmetric matrix in LAPACK banded storage.

    ``ab`` is laid out as for :func:`scipy.linalg.cholesky_banded`: upper form
    ``ab[u + i - j, j] == a[i, j]`` (i <= j) or lower form ``ab[i - j, j] == a[i, j]``
    (i >= j). The scalar order ``n`` is padded to a multiple of 6 with an identity.
    Returns ``(band, n, u)``.
    """
    return _to_blocks(ab, lower, triangle=False)


def band_to_scipy(factor, n, u, lower=False):
    """LAPACK banded storage of the triangular factor held in band rows (see above).

    Upper: ``c[u + i - j, j] = U[i, j]`` with ``a = U' U``; lower: ``c[i - j, j] = L[i, j]``
    with ``L = U'``.
    """
    nb, _, width = factor.shape
    p, q = _block_indices(nb, width // 6)
    ok = (q >= p) & (q - p <= u) & (q < n)
    c = np.zeros((u + 1, n))
    if lower:
        c[(q - p)[ok], p[ok]] = factor[ok]
    else:
        c[(u + p - q)[ok], q[ok]] = factor[ok]
    return c


def cholesky_banded(ab, overwrite_ab=False, lower=False, check_finite=True):
    """Cholesky factor of a symmetric positive definite banded matrix, as SciPy's.

    Same storage, arguments and result as :func:`scipy.linalg.cholesky_banded`; computed
    with the block kernels of the out-of-core solver (6x6 station blocks, so the scalar band
    is rounded up to whole blocks internally). Raises :class:`numpy.linalg.LinAlgError`
    naming the leading minor that is not positive definite.
    """
    ab = np.asarray_chkfinite(ab) if check_finite else np.asarray(ab)
    band, n, u = scipy_to_band(ab, lower)
    nb = band.shape[0]
    rhs = np.zeros((nb, 6))
    orig = np.abs(np.diagonal(band, axis1=1, axis2=2)).copy()
    r, i = factor_rows(band, rhs, orig, 0, nb, nb, 0.0)
    if r >= 0:
        raise np.linalg.LinAlgError(
            f"{6 * r + i + 1}-th leading minor not positive definite")
    c = band_to_scipy(band, n, u, lower)
    if overwrite_ab and ab.dtype == np.float64 and ab.flags.writeable:
        ab[...] = c
        return ab
    return c


def cho_solve_banded(cb_and_lower, b, overwrite_b=False, check_finite=True):
    """Solve ``a x = b`` with the factor from :func:`cholesky_banded`, as SciPy's.

    ``b`` may be a vector (n,) or a matrix (n, k).
    """
    cb, lower = cb_and_lower
    cb = np.asarray_chkfinite(cb) if check_finite else np.asarray(cb)
    b = np.asarray_chkfinite(b) if check_finite else np.asarray(b)
    factor, n, u = _to_blocks(cb, lower, triangle=True)
    if b.shape[0] != n:
        raise ValueError(f"shapes of cb {cb.shape} and b {b.shape} are not compatible")
    nb = factor.shape[0]
    cols = b.reshape(n, -1).astype(np.float64)
    out = np.empty_like(cols)
    for j in range(cols.shape[1]):
        y = np.zeros(6 * nb)
        y[:n] = cols[:, j]
        y = y.reshape(nb, 6)
        _forward_substitute(factor, y)
        x = np.zeros((nb, 6))
        back_substitute(factor, y, np.zeros((0, 6)), 0, x)
        out[:, j] = x.ravel()[:n]
    out = out.reshape(b.shape)
    if overwrite_b and b.dtype == np.float64 and b.flags.writeable:
        b[...] = out
        return b
    return out


@njit(cache=True)
def _forward_substitute(factor, y):
    """``y <- U'^-1 y`` for factor rows ``U`` (the solve that factor_rows does on the fly)."""
    nb = factor.shape[0]
    for r in range(nb):
        _forward_row(factor, y, r, nb)
