"""Recursive-partitioning block-banded Cholesky, in and out of core (DESIGN section 5).

Storage on disk: the reduced matrix ``M`` (n stations, 6x6 blocks, band width ``b`` stations)
is kept as band rows ``band[i] = [M[i,i], M[i,i+1], ..., M[i,i+b-1]]`` (6 x 6b each; blocks
past the last station are zero): ``band[i, r, 6k + c] == M[6i + r, 6(i+k) + c]``. The solver
takes them in station order (:class:`BandSolver`, fed by the build as it completes them, so
they never go to disk), writes the rows of the factor ``U`` (``M = U' U``, same band) in
*diagonal-first* form ``fac[i, r, d] == U[6i + r, 6i + r + d]`` (:func:`factor_to_band` gives
band rows again) and the right-hand side ``y = U'^-1 d``, then back-substitutes reading them
in reverse.

In core the solver works on the lower factor ``L = U'`` in *skewed band storage*: scalar column
``h`` of ``L`` occupies ``LD`` consecutive doubles ``L[h, h], L[h+1, h], ...`` -- LAPACK's lower
band storage, transposed in memory. Row ``r`` of station ``i``'s band row is exactly that column
(``band[i, r, r + d] == L[6i + r + d, 6i + r]``) and a factor row is its first ``6b`` doubles,
so loading and storing are contiguous copies.
The point of the layout: element ``(g, h)`` sits at ``h (LD - 1) + g``, so every submatrix that
lies inside the band is an ordinary Fortran matrix with leading dimension ``LD - 1`` and can be
handed to BLAS-3 as it is (the trick of LAPACK's dpbtrf). Columns live in a **ring** of ``R``
columns (column ``h`` at ``(h mod R) LD``); an update that crosses the end of the ring is split
there, and nothing is ever shifted.

The factorisation goes panel by panel (``P`` scalar columns, a multiple of 6; Elphingstone &
Wong's recursive partitioning with a panel of stations as the partition):

    L11 = chol(A11)                      dpotrf, then the pivot test below
    L21 = A21 L11'^-1                    dtrtri + dtrmm (faster than dtrsm), dtrsm below 100 rows
    A22 -= L21 L21'                      dsyrk on the diagonal part, dgemm below it
    y1 = L11^-1 d1;  d2 -= L21 y1        dtrsv, dgemv

with a look-ahead of one panel on two (or more) threads: thread 0 applies panel k's update to
the columns of panel k+1 and factors panel k+1 at once, while the other threads update the
rest of the trailing block; the split is balanced by operation counts. The BLAS libraries are
held to one thread meanwhile (:func:`sapgo.blas.blas_limits`). Out of core, a segment of
``chunk_rows`` stations is factored as soon as its band rows (and the ``b`` after them) have
been fed, after the factor rows of the segment before have been written out. In core: the
ring (``~(3 chunk_rows + 2 b) x 6`` columns of ``6b + P`` doubles) and one segment of factor
rows in transit.

A pivot ``L[h,h]^2`` at or below ``pivot_tol`` times the original diagonal element (or a failed
dpotrf) stops the factorisation and names the station and parameter.

:func:`cholesky_banded` and :func:`cho_solve_banded` are drop-ins for SciPy's functions of the
same names (same storage, arguments and results) that call LAPACK: on LAPACK's storage, with
its copies in and out, the panel kernel was never faster (see :func:`cholesky_banded`).
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np
import scipy.linalg
from numba import njit, prange

from .. import paging
from .. import threads as _threads
from ..blas import FNS, L, N, R, T, U, blas_limits, gemm, gemv, potrf, syrk, trmm, trsm, trsv, trtri

#: A pivot at or below this fraction of the original diagonal element counts as zero.
PIVOT_TOLERANCE = 1e-12

#: Weight of the panel factorisation's operations (dpotrf, dtrtri, dtrmm) against the
#: dsyrk/dgemm of the trailing update when the threads' shares are balanced: they run at
#: about half the rate.
_PANEL_WEIGHT = 2.0


#: Below this many rows under a panel, dtrsm beats dtrtri + dtrmm.
_TRSM_ROWS = 100


def panel_width(u):
    """Scalar panel width for a scalar half band ``u`` (measured best on 2 cores)."""
    return 24 if u < 200 else 36 if u < 450 else 48


# -- kernels ------------------------------------------------------------------------------

@njit(cache=True, nogil=True)
def _update_cols(fns, a, ring, ld1, k0, pb, c0, c1, m):
    """Trailing columns ``[k0+pb+c0, k0+pb+c1)`` minus ``L21 L21'`` (lower part), where
    ``L21`` is the ``m`` rows below panel ``k0`` (``pb`` columns); split at the ring's end."""
    ld = ld1 - 1
    src = (k0 % ring) * ld1 + pb
    c_lo = k0 + pb
    j = c0
    while j < c1:
        h = c_lo + j
        e = min(c1, j + ring - h % ring)
        base = (h % ring) * ld1
        syrk(fns.dsyrk, L, N, e - j, pb, -1.0, a[src + j:], ld, 1.0, a[base:], ld)
        if m > e:
            gemm(fns.dgemm, N, T, m - e, e - j, pb, -1.0, a[src + e:], ld, a[src + j:], ld,
                 1.0, a[base + e - j:], ld)
        j = e


@njit(cache=True, nogil=True)
def _factor_panel(fns, a, orig, ring, ld1, k0, pb, m, tol, tmp):
    """Factor panel ``k0`` (``pb`` columns, ``m`` rows below); 0 or 1 + the failing column."""
    ld = ld1 - 1
    base = (k0 % ring) * ld1
    x = a[base:]
    info = potrf(fns.dpotrf, L, pb, x, ld)
    good = pb if info == 0 else info - 1
    for j in range(good):
        d = x[j * ld1]
        if not (d * d > tol * orig[(k0 + j) % ring]):
            return j + 1
    if info != 0:
        return info
    if m > _TRSM_ROWS:
        for j in range(pb):
            for i in range(j, pb):
                tmp[j * pb + i] = x[j * ld + i]
        trtri(fns.dtrtri, L, N, pb, tmp, pb)
        trmm(fns.dtrmm, R, L, T, N, m, pb, 1.0, tmp, pb, a[base + pb:], ld)
    elif m > 0:
        trsm(fns.dtrsm, R, L, T, N, m, pb, 1.0, x, ld, a[base + pb:], ld)
    return 0


@njit(cache=True, nogil=True)
def _forward(fns, a, y, ring, ld1, k0, pb, m):
    """``y1 <- L11^-1 y1`` for panel ``k0``, then ``y2 -= L21 y1`` (split at the ring's end)."""
    ld = ld1 - 1
    base = (k0 % ring) * ld1
    yk = y[k0 % ring:]
    trsv(fns.dtrsv, L, N, N, pb, a[base:], ld, yk)
    if m > 0:
        h = (k0 + pb) % ring
        m1 = min(m, ring - h)
        gemv(fns.dgemv, N, m1, pb, -1.0, a[base + pb:], ld, yk, 1.0, y[h:])
        if m > m1:
            gemv(fns.dgemv, N, m - m1, pb, -1.0, a[base + pb + m1:], ld, yk, 1.0, y)


@njit(cache=True, nogil=True)
def _cut(m, near, pb, pn, m2, nthreads):
    """Thread 0's columns ``[0, c)`` (at least the next panel's) so that its update plus the
    next panel's factorisation is a ``1/nthreads`` share of the step's work."""
    if nthreads == 1:
        return m
    panel = _PANEL_WEIGHT * (pn ** 3 / 3.0 + m2 * pn * pn / 2.0)
    total = pb * m * (m + 1) / 2.0 + panel
    share = total / nthreads
    c = near
    work = pb * (near * m - near * (near - 1) / 2.0) + panel
    while c < m and work + pb * (m - c) <= share:
        work += pb * (m - c)
        c += 1
    return c


@njit(cache=True, nogil=True)
def _area_cut(c, m, frac):
    """Column ``x`` in ``[c, m]`` such that columns ``[c, x)`` carry ``frac`` of the update of
    ``[c, m)`` (column ``j`` costs ``m - j``)."""
    if frac >= 1.0:
        return m
    goal = frac * (m - c) * (m - c + 1) / 2.0
    x = c
    acc = 0.0
    while x < m and acc + (m - x) <= goal:
        acc += m - x
        x += 1
    return x


@njit(cache=True, nogil=True, parallel=True)
def _factor_range(fns, a, y, orig, ring, ld1, n, u, p, k_start, k_stop, first, tol, nthreads):
    """Factor the panels starting at ``k_start, k_start + p, ... < k_stop`` (scalar columns)
    with forward substitution; panel ``k_start`` is already factored unless ``first``, and the
    panel at ``k_stop`` is factored on return (look-ahead). Returns -1 or the failing column.
    """
    tmp = np.empty((max(1, nthreads), p * p))
    fail = np.full(1, -1, np.int64)
    if first:
        pb = min(p, n - k_start)
        f = _factor_panel(fns, a, orig, ring, ld1, k_start, pb, min(u, n - k_start - pb), tol,
                          tmp[0])
        if f:
            return k_start + f - 1
    for k0 in range(k_start, k_stop, p):
        pb = min(p, n - k0)
        c_lo = k0 + pb
        m = min(u, n - c_lo)
        if c_lo >= n:
            _forward(fns, a, y, ring, ld1, k0, pb, m)
            continue
        pn = min(p, n - c_lo)
        if m <= 0:  # the next panel lies outside this one's band (u < p)
            _forward(fns, a, y, ring, ld1, k0, pb, m)
            f = _factor_panel(fns, a, orig, ring, ld1, c_lo, pn, min(u, n - c_lo - pn), tol,
                              tmp[0])
            if f:
                return c_lo + f - 1
            continue
        near = min(pn, m)
        m2 = min(u, n - c_lo - pn)
        c = _cut(m, near, pb, pn, m2, nthreads)
        for t in prange(nthreads):
            if t == nthreads - 1:  # the forward substitution runs beside the update
                _forward(fns, a, y, ring, ld1, k0, pb, m)
            if t == 0:
                _update_cols(fns, a, ring, ld1, k0, pb, 0, c, m)
                f = _factor_panel(fns, a, orig, ring, ld1, c_lo, pn, m2, tol, tmp[0])
                if f:
                    fail[0] = c_lo + f - 1
            else:
                lo = _area_cut(c, m, (t - 1) / (nthreads - 1))
                hi = _area_cut(c, m, t / (nthreads - 1))
                if hi > lo:
                    _update_cols(fns, a, ring, ld1, k0, pb, lo, hi, m)
        if fail[0] >= 0:
            return fail[0]
    return -1


@njit(cache=True, nogil=True, parallel=True)
def _load_rows(band, rhs, i0, a, y, orig, ring, ld1):
    """Band rows of stations ``i0 ..`` into the ring as columns of ``L`` (zero padded)."""
    width = band.shape[2]
    k = band.shape[1]
    for ii in prange(band.shape[0]):
        for r in range(k):
            h = k * (i0 + ii) + r
            base = (h % ring) * ld1
            for d in range(width - r):
                a[base + d] = band[ii, r, r + d]
            for d in range(width - r, ld1):
                a[base + d] = 0.0
            y[h % ring] = rhs[ii, r]
            orig[h % ring] = abs(band[ii, r, r])


@njit(cache=True, nogil=True, fastmath=True)
def _back_rows(fac, y, x, i0, n):
    """Back substitution ``x <- U^-1 y`` for the scalar rows of the stations ``i0 ..`` of the
    factor rows ``fac`` (in reverse; diagonal-first, ``fac[i, r, d] = U[h, h + d]``); ``x``
    holds the solution of the rows after them."""
    width = fac.shape[2]
    k = fac.shape[1]
    for ii in range(fac.shape[0] - 1, -1, -1):
        for r in range(k - 1, -1, -1):
            h = k * (i0 + ii) + r
            s = y[ii, r]
            top = min(width, n - h)
            for d in range(1, top):
                s -= fac[ii, r, d] * x[h + d]
            x[h] = s / fac[ii, r, 0]


@njit(cache=True, nogil=True, parallel=True)
def _take_cols(a, y, ring, ld1, lo, fac, rhs):
    """Diagonal-first factor rows ``fac`` (k x 6 x 6b) and ``rhs`` (k x 6) from the ring
    columns ``lo, lo + 1, ...`` (slots modulo ``ring``)."""
    width = fac.shape[2]
    k = fac.shape[1]
    for ii in prange(fac.shape[0]):
        for r in range(k):
            slot = (lo + k * ii + r) % ring
            base = slot * ld1
            for d in range(width):
                fac[ii, r, d] = a[base + d]
            rhs[ii, r] = y[slot]


def factor_to_band(fac):
    """Band rows of ``U`` (``band[i, r, r + d] = U[h, h + d]``, lower triangle of each diagonal
    block zero) from the solver's diagonal-first factor rows ``fac[i, r, d] = U[h, h + d]``
    (``h = 6 i + r``)."""
    fac = np.asarray(fac)
    band = np.zeros_like(fac)
    width = fac.shape[2]
    for r in range(fac.shape[1]):
        band[:, r, r:] = fac[:, r, :width - r]
    return band


@njit(cache=True, nogil=True)
def _border_rows(fac, win, y, i0, n, s_mat, t_vec, yy):
    """Forward substitution of the border columns, ``W = U'^-1 B``, for the scalar rows of
    the stations ``i0 ..`` of the diagonal-first factor rows ``fac``: ``win`` (scalar rows
    x ng) holds ``B`` of these stations and the ``b`` after them (row 0 = station ``i0``)
    and receives ``W``; meanwhile ``S -= W'W``, ``t -= W'y`` (``y = U'^-1 d``, the
    forward-substituted right-hand side of the same rows) and ``yy += y'y``."""
    width = fac.shape[2]
    kb = fac.shape[1]
    ng = win.shape[1]
    for ii in range(fac.shape[0]):
        for r in range(kb):
            h = kb * (i0 + ii) + r
            lh = kb * ii + r
            u0 = fac[ii, r, 0]
            for c in range(ng):
                win[lh, c] /= u0
            top = min(width, n - h)
            for d in range(1, top):
                ud = fac[ii, r, d]
                if ud != 0.0:
                    for c in range(ng):
                        win[lh + d, c] -= ud * win[lh, c]
            yh = y[ii, r]
            yy[0] += yh * yh
            for c in range(ng):
                wc = win[lh, c]
                t_vec[c] -= wc * yh
                for c2 in range(ng):
                    s_mat[c, c2] -= wc * win[lh, c2]


@njit(cache=True)
def _dense_cholesky(a, tol):
    """Lower Cholesky factor of the symmetric matrix ``a`` (overwritten); -1, or the first
    column whose pivot is at or below ``tol`` times its original diagonal element."""
    ng = a.shape[0]
    orig = np.empty(ng)
    for i in range(ng):
        orig[i] = a[i, i]
    for j in range(ng):
        s = a[j, j]
        for k in range(j):
            s -= a[j, k] * a[j, k]
        if not (s > tol * orig[j]) or not (s > 0.0):
            return j
        a[j, j] = np.sqrt(s)
        for i in range(j + 1, ng):
            x = a[i, j]
            for k in range(j):
                x -= a[i, k] * a[j, k]
            a[i, j] = x / a[j, j]
    for i in range(ng):
        for j in range(i + 1, ng):
            a[i, j] = 0.0
    return -1


@njit(cache=True, nogil=True)
def _border_back_rows(fac, win, i0, n):
    """Back substitution of the border columns, ``X = U^-1 W``, for the scalar rows of the
    stations ``i0 ..`` of the factor rows ``fac`` (in reverse): ``win`` (scalar rows x ng)
    holds ``W`` of these stations followed by ``X`` of the ``b`` stations after them."""
    width = fac.shape[2]
    kb = fac.shape[1]
    ng = win.shape[1]
    for ii in range(fac.shape[0] - 1, -1, -1):
        for r in range(kb - 1, -1, -1):
            h = kb * (i0 + ii) + r
            lh = kb * ii + r
            top = min(width, n - h)
            for d in range(1, top):
                ud = fac[ii, r, d]
                if ud != 0.0:
                    for c in range(ng):
                        win[lh, c] -= ud * win[lh + d, c]
            u0 = fac[ii, r, 0]
            for c in range(ng):
                win[lh, c] /= u0


def border_back_substitute(factor_ds, border_ds, n_st, band_width, step=256, out=None):
    """``X = M^-1 B = U^-1 W`` from ``W`` (``border_ds``, n x k x ng, as :func:`border_solve`
    left it) into ``out`` (default: in place), reading the factor rows backwards ``step``
    stations at a time: the border's share of the stations' covariances,
    ``cov(delta) = M^-1 + X S^-1 X'`` and ``cov(delta, theta) = -X S^-1``."""
    out = border_ds if out is None else out
    kb = factor_ds.shape[1]
    ng = border_ds.shape[2]
    n = kb * n_st
    step = max(1, step)
    carry = np.zeros((0, kb, ng))
    stop = n_st
    while stop > 0:
        start = max(0, stop - step)
        w = np.asarray(border_ds[start:stop], dtype=np.float64)
        win = np.ascontiguousarray(np.concatenate([w, carry]).reshape(-1, ng))
        fac = np.ascontiguousarray(factor_ds[start:stop], dtype=np.float64)
        _border_back_rows(fac, win, start, n)
        x = win.reshape(-1, kb, ng)
        out[start:stop] = x[:stop - start]
        carry = x[:band_width].copy()
        stop = start


def band_solve_columns(factor_ds, r, n_st, band_width, step=256):
    """``M^-1 R`` for the columns ``R`` (n_st x k x c, in core) with the band's factor
    ``M = U'U`` (``factor_ds``, diagonal-first rows): the forward substitution of
    :func:`border_solve` and the back substitution of :func:`border_back_substitute`."""
    kb = factor_ds.shape[1]
    c = r.shape[2]
    n = kb * n_st
    win = np.ascontiguousarray(np.asarray(r, dtype=np.float64).reshape(-1, c))
    s_mat, t_vec, yy = np.zeros((c, c)), np.zeros(c), np.zeros(1)
    step = max(1, step)
    for base in range(0, n_st, step):   # W = U'^-1 R, in place (rows after it: in win)
        stop = min(n_st, base + step)
        fac = np.ascontiguousarray(factor_ds[base:stop], dtype=np.float64)
        _border_rows(fac, win[kb * base:], np.zeros((stop - base, kb)), base, n, s_mat,
                     t_vec, yy)
    stop = n_st
    while stop > 0:   # X = U^-1 W
        start = max(0, stop - step)
        fac = np.ascontiguousarray(factor_ds[start:stop], dtype=np.float64)
        _border_back_rows(fac, win[kb * start:], start, n)
        stop = start
    return win.reshape(n_st, kb, c)


class BorderPivotError(Exception):
    """A border parameter that the block cannot determine (a non-positive pivot of the
    border's Schur complement); ``index`` is its border column."""

    def __init__(self, index):
        super().__init__(f"non-positive pivot of the border at column {index}")
        self.index = index


def border_solve(factor_ds, y_ds, border_ds, cnn, ccg, n_st, band_width, step=256,
                 pivot_tol=PIVOT_TOLERANCE):
    """Solve the border of a bordered band after the band's factorisation.

    The full system is ``[[M, B], [B', C]] [delta; theta] = [d; c]`` with ``M = U'U`` the
    band (already factored: ``factor_ds`` holds ``U``, ``y_ds`` holds ``y = U'^-1 d``) and
    ``B`` (``border_ds``, n x k x ng) the border columns of the band rows. One forward pass
    over the factor rows turns ``B`` into ``W = U'^-1 B`` (in place) and forms the border's
    Schur complement ``S = C - W'W`` and ``t = c - W'y``; ``theta = S^-1 t`` (a dense
    Cholesky, ng x ng, scaled to a unit diagonal); a second pass sets ``y <- y - W theta``,
    after which the band's back substitution ``delta = U^-1 y`` gives the stations. In core:
    ``step + b`` stations' border rows. Returns ``(theta, y'y, t'S^-1 t)``; the last two are
    ``x'b`` of the solution split into the band's and the border's share (for the
    Levenberg-Marquardt gain ratio), and ``S^-1`` (the border's cofactor matrix when the
    band is the reduced normal matrix). Raises :class:`BorderPivotError` when ``S`` is not
    positive definite at ``pivot_tol``.
    """
    kb = factor_ds.shape[1]
    ng = cnn.shape[0]
    n = kb * n_st
    s_mat = np.array(cnn, dtype=np.float64)
    t_vec = np.array(ccg, dtype=np.float64)
    yy = np.zeros(1)
    step = max(1, step)
    win = np.zeros(((step + band_width) * kb, ng))
    base = loaded = 0
    while base < n_st:
        stop = min(n_st, base + step)
        need = min(n_st, stop + band_width)
        if need > loaded:
            win[(loaded - base) * kb:(need - base) * kb] = np.asarray(
                border_ds[loaded:need], dtype=np.float64).reshape(-1, ng)
            loaded = need
        fac = np.ascontiguousarray(factor_ds[base:stop], dtype=np.float64)
        y = np.ascontiguousarray(y_ds[base:stop], dtype=np.float64)
        _border_rows(fac, win, y, base, n, s_mat, t_vec, yy)
        border_ds[base:stop] = win[:(stop - base) * kb].reshape(stop - base, kb, ng)
        rest = loaded - stop
        win[:rest * kb] = win[(stop - base) * kb:(loaded - base) * kb]
        win[rest * kb:] = 0.0
        base = stop
    theta, decrease, s_inv = border_schur_solve(s_mat, t_vec, pivot_tol)
    for a in range(0, n_st, step):
        b = min(n_st, a + step)
        w = np.asarray(border_ds[a:b], dtype=np.float64)
        y_ds[a:b] = np.asarray(y_ds[a:b], dtype=np.float64) - w @ theta
    return theta, float(yy[0]), decrease, s_inv


def border_schur_solve(s_mat, t_vec, pivot_tol=PIVOT_TOLERANCE):
    """``theta = S^-1 t`` for the border's Schur complement ``S = C - W'W`` (ng x ng) and
    ``t = c - W'y``, by a dense Cholesky of ``S`` scaled to a unit diagonal (whichever
    solver factored the stations: the band or the tree). Returns ``(theta, t'S^-1 t,
    S^-1)``; raises :class:`BorderPivotError` when ``S`` is not positive definite at
    ``pivot_tol``."""
    import scipy.linalg

    ng = s_mat.shape[0]
    s_mat = 0.5 * (s_mat + s_mat.T)
    dg = np.diag(s_mat).copy()
    if ng and not (dg > 0.0).all():
        raise BorderPivotError(int(np.argmin(dg > 0.0)))
    scale = 1.0 / np.sqrt(dg) if ng else dg
    lo = np.ascontiguousarray(s_mat * scale[:, None] * scale[None, :])
    fail = _dense_cholesky(lo, pivot_tol)
    if fail >= 0:
        raise BorderPivotError(int(fail))
    inv = scipy.linalg.solve_triangular(lo, np.eye(ng), lower=True) if ng else lo
    s_inv = (inv.T @ inv) * scale[:, None] * scale[None, :]
    z = scipy.linalg.solve_triangular(lo, scale * t_vec, lower=True) if ng else t_vec
    theta = scale * scipy.linalg.solve_triangular(lo.T, z, lower=False) if ng else t_vec
    return theta, float(z @ z), s_inv


# -- drivers ------------------------------------------------------------------------------

class PivotError(Exception):
    """Raised by the drivers with the station (row) and parameter of a failed pivot."""

    def __init__(self, row, parameter):
        super().__init__(f"non-positive pivot at row {row}, parameter {parameter}")
        self.row = row
        self.parameter = parameter


def _up(x, k):
    return -(-x // k) * k


class _Inline:
    """:class:`_Background`'s interface, running the job at once in the caller's thread."""

    _result = None

    def start(self, fn, *args):
        self._result = fn(*args)

    def wait(self):
        result, self._result = self._result, None
        return result


class _Background:
    """One job at a time on a helper thread; ``wait()`` returns its result or re-raises."""

    def __init__(self):
        self._thread = None
        self._box = None

    def start(self, fn, *args):
        box = self._box = {}

        def run():
            try:
                box["result"] = fn(*args)
            except BaseException as exc:  # re-raised in the caller's thread
                box["error"] = exc

        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()

    def wait(self):
        if self._thread is None:
            return None
        self._thread.join()
        self._thread = None
        if "error" in self._box:
            raise self._box["error"]
        return self._box.get("result")


class BandSolver:
    """Streaming factorisation: band rows go in, in station order; factor rows go out.

    ``feed(band, rhs)`` takes the next band rows (k x 6 x 6b) and right-hand-side rows
    (k x 6) -- any number at a time, e.g. as the build completes them -- places them into the
    ring and factors every segment of ``chunk_rows`` stations whose rows are all in. The factor
    rows and the forward-substituted right-hand side are written to ``factor_ds`` and
    ``y_ds`` (n x 6 x 6b and n x 6: direct-access files, HDF5 datasets or arrays), so the band
    rows never go to disk. ``finish()`` factors the rest and returns the solution ``delta``
    (n x 6), back-substituting from the factor rows read in reverse. ``seconds`` is the time
    spent in the solver so far. In core: the ring of about ``3 chunk_rows + 2 b`` stations'
    columns and one segment of factor rows in transit.
    """

    def __init__(self, n_st, band_width, factor_ds, y_ds, chunk_rows=256,
                 pivot_tol=PIVOT_TOLERANCE, progress=None, panel=None, threads=None, block=6,
                 replay=None):
        self.n_st = n_st
        self.block = kb = block          # parameters per station
        self.width = width = kb * band_width
        self.n = n = kb * n_st
        self.u = u = width - 1
        self.p = p = panel or _up(panel_width(u), kb)
        if p % kb:
            raise ValueError(f"panel width {p} is not a multiple of {kb}")
        self.factor_ds, self.y_ds = factor_ds, y_ds
        # factor rows in core (C-contiguous arrays): taken out of the ring into them directly
        self._in_place = all(isinstance(a, np.ndarray) and a.flags.c_contiguous
                             and a.dtype == np.float64 for a in (factor_ds, y_ds))
        self.chunk_rows = max(1, chunk_rows)
        self.pivot_tol = pivot_tol
        self.progress = progress
        self.nthreads = threads or _threads.parts()
        self.seg = _up(kb * self.chunk_rows, p)          # scalar columns per segment
        self.ld1 = u + p + 1
        self.ring = min(_up(3 * self.seg + u + 2 * p + kb, p), _up(max(n, 1), p))
        self.a = np.zeros(self.ring * self.ld1)
        self.y = np.zeros(self.ring)
        self.orig = np.zeros(self.ring)
        self.loaded = 0          # stations placed into the ring
        self.stored = 0          # stations whose factor rows left the ring
        self.k = 0               # scalar columns factored
        self.limit = n           # factor no further (a replayed segment stops at its end)
        self.seconds = 0.0
        #: ``y'y`` of the rows taken so far (when the factor rows are not kept in a file)
        self.yy = 0.0
        #: :class:`FactorReplay` (``replay`` a directory): no factor file; the ring's state
        #: is kept at every replay segment's start and the rows are refactored on demand
        self.replay = None
        if replay is not None:
            self.replay = FactorReplay(self, replay)
        # The factor rows are written by a helper thread only when a core is free for it: the
        # kernel's threads meet at a barrier every panel, and a transfer that takes one of
        # their cores stalls both (measured on 2 cores).
        self._writer = (_Background() if (os.cpu_count() or 1) > self.nthreads else _Inline())

    def feed(self, band, rhs):
        """Place the next band rows (and right-hand-side rows) and factor what is ready."""
        t0 = time.perf_counter()
        band = np.ascontiguousarray(band, dtype=np.float64)
        kb = self.block
        rhs = np.ascontiguousarray(rhs, dtype=np.float64).reshape(-1, kb)
        if band.shape[1:] != (kb, self.width) or len(rhs) != len(band):
            raise ValueError(f"band rows of shape {band.shape[1:]} and {len(rhs)} right-hand "
                             f"side rows, expected ({kb}, {self.width}) and {len(band)}")
        if self.loaded + len(band) > self.n_st:
            raise ValueError(f"{self.loaded + len(band)} band rows fed for {self.n_st} stations")
        i = 0
        while i < len(band):
            room = (kb * self.stored + self.ring) // kb - self.loaded
            take = min(room, len(band) - i)
            if take > 0:
                self._writer.wait()   # (the slots may still be on their way to the file)
                _load_rows(band[i:i + take], rhs[i:i + take], self.loaded, self.a, self.y,
                           self.orig, self.ring, self.ld1)
                self.loaded += take
                i += take
            self._factor_ready()
        self.seconds += time.perf_counter() - t0

    def _reach(self, col):
        """Stations covering the scalar columns below ``col``."""
        return min(self.n_st, -(-min(self.n, col) // self.block))

    def _factor_ready(self):
        n, u, p = self.n, self.u, self.p
        while self.k < min(n, self.limit):
            k = self.k
            stop = min(n, k + self.seg)
            if self.loaded < self._reach(stop + u + p):
                return
            self._writer.wait()
            self._writer.start(self._write, *self._take(k // self.block))
            _threads.adapt()
            with blas_limits(1):
                fail = _factor_range(FNS, self.a, self.y, self.orig, self.ring, self.ld1, n,
                                     u, p, k, stop, k == 0, self.pivot_tol, self.nthreads)
            if fail >= 0:
                self._writer.wait()
                raise PivotError(fail // self.block, fail % self.block)
            if self.progress is not None:
                self.progress((stop - k) // self.block)
            self.k = stop
            if self.replay is not None and stop < n and stop % self.replay.cols_per_segment == 0:
                self.replay.save(self)

    def state(self):
        """The ring's state at ``k`` (look-ahead panel factored): the columns ``k .. k + W``
        the eliminations so far have touched (``W = max(6b, P)``), their right-hand side and
        original diagonal; ``(cols, y, orig)``."""
        h = np.arange(self.k, min(self.n, self.k + self.replay.state_cols)) % self.ring
        return self.a.reshape(self.ring, self.ld1)[h], self.y[h], self.orig[h]

    def restore(self, k, cols, y, orig):
        """Resume at scalar column ``k`` from :meth:`state`; the band rows from station
        ``loaded`` on are to be fed."""
        h = np.arange(k, k + len(cols)) % self.ring
        self.a.reshape(self.ring, self.ld1)[h] = cols
        self.y[h] = y
        self.orig[h] = orig
        self.k = k
        self.stored = k // self.block
        self.loaded = (k + len(cols)) // self.block

    def _take(self, i1):
        """Factor rows of the stations ``stored .. i1`` out of the ring (diagonal-first: the
        first ``6 b`` doubles of each column of ``L``)."""
        i0 = self.stored
        kb = self.block
        if self._in_place:
            fac, rhs = self.factor_ds[i0:i1], self.y_ds[i0:i1]
        else:
            fac = np.empty((i1 - i0, kb, self.width))
            rhs = np.empty((i1 - i0, kb))
        _take_cols(self.a, self.y, self.ring, self.ld1, (kb * i0) % self.ring, fac, rhs)
        self.stored = i1
        return i0, fac, rhs

    def _write(self, i0, band, rhs):
        if not len(band):
            return
        if self.factor_ds is None:   # (replayed when needed)
            self.yy += float((rhs * rhs).sum())
            if self.replay is not None:
                self.replay.keep_tail(i0, band, rhs)
            return
        if not self._in_place:
            self.factor_ds[i0:i0 + len(band)] = band
            self.y_ds[i0:i0 + len(rhs)] = rhs

    def finish(self, border=None, back=True):
        """Factor the rest (every row must have been fed) and return ``delta`` (n x 6).

        ``border = (border_ds, cnn, ccg)``: a bordered band (:func:`border_solve`); the
        border's solution is left in ``theta``, ``y'y`` and ``t'S^-1 t`` in ``y_norm2`` and
        ``border_decrease``, ``S^-1`` in ``border_cov``. ``back=False``: the factorisation
        alone (returns None). With a replay the factor rows are read through
        ``replay.factor`` and ``replay.y``."""
        if self.loaded != self.n_st:
            raise ValueError(f"{self.loaded} band rows fed for {self.n_st} stations")
        t0 = time.perf_counter()
        if self.n == 0:
            return np.zeros((0, self.block))
        self._factor_ready()
        self._writer.wait()
        self._write(*self._take(self.n_st))
        if self.replay is not None:
            self.replay.recorded()
            delta = None
            if back:
                delta = self.replay.back_substitute()
            self.seconds += time.perf_counter() - t0
            return delta
        if border is not None:
            self.theta, self.y_norm2, self.border_decrease, self.border_cov = border_solve(
                self.factor_ds, self.y_ds, border[0], border[1], border[2], self.n_st,
                self.width // self.block, self.chunk_rows, self.pivot_tol)
        delta = None
        if back:   # read back in blocks of at least 8 MiB (fewer, larger reads)
            step = max(self.chunk_rows, (8 << 20) // (8 * self.block * self.width))
            delta = _back_substitute(self.factor_ds, self.y_ds, self.n_st, step, self.block)
        self.seconds += time.perf_counter() - t0
        return delta


#: A replayed segment's factor rows in core (bytes): the segments' length.
REPLAY_SEGMENT_BYTES = 64 << 20


class _Offset:
    """Rows ``s0 ..`` of an array, written as the factor file's rows are (``a[i:j] = x``)."""

    def __init__(self, arr, s0):
        self.arr, self.s0 = arr, s0

    def __setitem__(self, key, value):
        a, b = key.start - self.s0, key.stop - self.s0
        if a < 0 or b > len(self.arr):
            raise ValueError(f"factor rows {key.start}..{key.stop} outside the segment")
        self.arr[a:b] = value


class _Rows:
    """``replay.factor`` / ``replay.y``: read like the factor file (contiguous row ranges)."""

    def __init__(self, replay, which, shape):
        self.replay, self.which, self.shape = replay, which, shape

    def __len__(self):
        return self.shape[0]

    def __getitem__(self, key):
        if not isinstance(key, slice):
            raise IndexError("replayed factor rows: contiguous row ranges only")
        lo, hi, step = key.indices(self.shape[0])
        if step != 1:
            raise IndexError("replayed factor rows: contiguous row ranges only")
        return self.replay.rows(lo, max(lo, hi))[self.which]


class FactorReplay:
    """The band's factor without a factor file: recomputed a segment at a time on demand.

    While the :class:`BandSolver` factors (forward), the ring's state at the start of every
    segment of ``R`` stations (``W = max(6b, P)`` touched columns of ``6b + P`` doubles, about
    0.6 MB at b = 42; :meth:`BandSolver.state`) goes to ``replay.bin`` in ``directory`` and
    the factor rows are dropped (the last segment's are kept). A read of factor rows
    (``factor[lo:hi]``, ``y[lo:hi]``, in any order; the back substitution and Takahashi's
    recurrence read backwards) restores the state of the segment holding them into a fresh
    solver and feeds it the segment's band rows again from ``rebuild(lo, hi, feed)`` (the
    caller's build of those rows, points and state unchanged since the forward pass), up
    to the ``u + P`` scalar columns after the segment that its last panels need. The last
    two segments read stay in core (their buffers reused).

    Scratch: ``n / R`` states instead of ``n`` factor rows (``R`` from
    :data:`REPLAY_SEGMENT_BYTES`: about 5 000 stations at b = 42, so 0.12 MB a thousand
    stations against 12 MB); time: the band rows built and factored once more for each
    backward pass. The same panels in the same order reproduce the factor exactly when the
    rebuilt rows are the forward pass's (rounding of the build's parallel sums aside).
    """

    def __init__(self, solver, directory):
        from ..rawfile import RawArray

        self.n_st, self.kb, self.width = solver.n_st, solver.block, solver.width
        self.n, self.u, self.p = solver.n, solver.u, solver.p
        self.args = (solver.n_st, solver.width // solver.block, None, None,
                     solver.chunk_rows, solver.pivot_tol, None, solver.p, solver.nthreads,
                     solver.block)
        seg_st = solver.seg // solver.block          # stations per factored chunk
        row_bytes = 8 * self.kb * self.width
        m = max(1, REPLAY_SEGMENT_BYTES // max(1, seg_st * row_bytes))
        self.R = min(m * seg_st, max(1, self.n_st))   # stations per replay segment
        self.cols_per_segment = self.kb * self.R
        self.state_cols = _up(max(self.width, self.p), self.kb)
        self.J = max(1, -(-self.n_st // self.R))
        self.ld1 = solver.ld1
        rec = self.state_cols * (self.ld1 + 2)
        self.file = RawArray(Path(directory) / "replay.bin", (self.J, rec), mode="w")
        #: ``rebuild(lo, hi, feed)``: feeds the band rows of stations ``lo .. hi`` (set by
        #: the caller before the first read)
        self.rebuild = None
        self.replays = 0           # segments refactored so far
        self.cache = {}            # segment -> (fac, y), the last two read
        self._spare = []           # buffers of segments dropped from the cache
        self._last = None          # ((lo, hi), rows): the last range read
        self._tail = (self.J - 1) * self.R
        self._tail_rows = None
        self.factor = _Rows(self, 0, (self.n_st, self.kb, self.width))
        self.y = _Rows(self, 1, (self.n_st, self.kb))

    def rows_needed(self, j):
        """Stations whose band rows segment ``j``'s replay is fed: ``(lo, hi)``."""
        s0 = j * self.R
        s1 = min(self.n_st, s0 + self.R)
        lo = min(self.n_st, s0 + self.state_cols // self.kb) if j else 0
        hi = min(self.n_st, s1 + -(-(self.u + self.p) // self.kb) + 1)
        return lo, hi

    def save(self, solver):
        j = solver.k // self.cols_per_segment
        cols, y, orig = solver.state()
        rec = np.zeros(self.file.shape[1])
        w, sc, ld1 = len(cols), self.state_cols, self.ld1
        rec[:w * ld1] = cols.reshape(-1)
        rec[sc * ld1:sc * ld1 + w] = y
        rec[sc * (ld1 + 1):sc * (ld1 + 1) + w] = orig
        self.file[j] = rec

    def keep_tail(self, i0, band, rhs):
        """The forward pass's rows of the last segment, kept (no replay for it)."""
        i1 = i0 + len(band)
        if i1 <= self._tail:
            return
        if self._tail_rows is None:
            self._tail_rows = self._buffers(self.n_st - self._tail)
        a = max(i0, self._tail)
        self._tail_rows[0][a - self._tail:i1 - self._tail] = band[a - i0:]
        self._tail_rows[1][a - self._tail:i1 - self._tail] = rhs[a - i0:]

    def recorded(self):
        """The forward pass is over."""
        if self._tail_rows is not None:
            self.cache[self.J - 1] = self._tail_rows
            self._tail_rows = None

    def _buffers(self, m):
        for i, (fac, y) in enumerate(self._spare):
            if len(fac) >= m:
                del self._spare[i]
                return fac[:m], y[:m]
        return np.empty((self.R, self.kb, self.width))[:m], np.empty((self.R, self.kb))[:m]

    def _replay(self, j):
        s0 = j * self.R
        s1 = min(self.n_st, s0 + self.R)
        fac, y = self._buffers(s1 - s0)
        args = list(self.args)
        args[2], args[3] = _Offset(fac, s0), _Offset(y, s0)
        sol = BandSolver(*args)
        sol.limit = self.kb * s1
        if j:
            rec = self.file[j]
            w = min(self.state_cols, self.n - self.kb * s0)
            sc, ld1 = self.state_cols, self.ld1
            sol.restore(self.kb * s0, rec[:w * ld1].reshape(w, ld1), rec[sc * ld1:sc * ld1 + w],
                        rec[sc * (ld1 + 1):sc * (ld1 + 1) + w])
        lo, hi = self.rows_needed(j)
        if lo != sol.loaded:
            raise AssertionError(f"replay of segment {j}: rows from {lo}, state at {sol.loaded}")
        if hi > lo:
            self.rebuild(lo, hi, sol.feed)
        if sol.loaded < hi:
            raise ValueError(f"replay of segment {j}: band rows fed to {sol.loaded}, "
                             f"expected {hi}")
        sol._factor_ready()
        sol._writer.wait()
        sol._write(*sol._take(s1))
        self.replays += 1
        return fac, y

    def back_substitute(self):
        """``delta = U^-1 y`` (n x k), a segment at a time from the last."""
        x = paging.zeros(self.n)
        for j in range(self.J - 1, -1, -1):
            fac, y = self.segment(j)
            _back_rows(fac, y, x, j * self.R, self.n)
        return x.reshape(self.n_st, self.kb)

    def segment(self, j):
        """Factor rows and ``y`` of segment ``j`` (read-only views, valid until two more
        segments have been read)."""
        got = self.cache.get(j)
        if got is None:
            while len(self.cache) >= 2:   # (its buffers serve the next replay)
                old = self.cache.pop(next(iter(self.cache)))
                self._spare.append((old[0].base if old[0].base is not None else old[0],
                                    old[1].base if old[1].base is not None else old[1]))
            got = self._replay(j)
            self.cache[j] = got
        return got

    def rows(self, lo, hi):
        """Factor rows and ``y`` of the stations ``lo .. hi``: views of the segment's
        buffers when in one segment (valid until two more segments have been read; the
        readers, streaming forwards or backwards, hold at most the last), else copies."""
        if hi <= lo:
            return (np.empty((0, self.kb, self.width)), np.empty((0, self.kb)))
        if self._last is not None and self._last[0] == (lo, hi):   # (factor, then y)
            return self._last[1]
        parts = []
        j0, j1 = lo // self.R, (hi - 1) // self.R
        for j in range(j0, j1 + 1):
            fac, y = self.segment(j)
            a, b = max(lo, j * self.R) - j * self.R, min(hi, (j + 1) * self.R) - j * self.R
            parts.append((fac[a:b], y[a:b]) if j0 == j1 else (fac[a:b].copy(), y[a:b].copy()))
        if len(parts) == 1:   # (views: a later read may reuse the buffers)
            out = parts[0]
        else:
            out = (np.concatenate([q[0] for q in parts]), np.concatenate([q[1] for q in parts]))
        self._last = ((lo, hi), out)
        return out

    def close(self):
        self.file.close()
        self.cache.clear()
        self._spare.clear()
        self._last = None


def solve_out_of_core(band_ds, rhs_ds, band_width, chunk_rows=256, pivot_tol=PIVOT_TOLERANCE,
                      progress=None, panel=None, threads=None):
    """Factor the band rows of ``band_ds`` in place and solve for ``rhs_ds``.

    ``band_ds`` (n x 6 x 6b) and ``rhs_ds`` (n x 6) are direct-access files, HDF5 datasets or
    arrays. The factor rows (diagonal-first, see the module docstring) overwrite the band rows
    and the forward-substituted right-hand side overwrites ``rhs_ds``; returns the solution
    ``delta`` (n x 6). The rows are read segment by
    segment and fed to a :class:`BandSolver` (a segment is read before any of its rows is
    overwritten). ``panel`` (scalar columns, a multiple of 6) and ``threads`` override the
    defaults.
    """
    n_st = band_ds.shape[0]
    kb = band_ds.shape[1]
    width = kb * band_width
    if band_ds.shape[2] != width:
        raise ValueError(f"band rows have shape {band_ds.shape[1:]}, expected ({kb}, {width})")
    solver = BandSolver(n_st, band_width, band_ds, rhs_ds, chunk_rows, pivot_tol, progress,
                        panel, threads, block=kb)
    step = max(1, chunk_rows)
    for i0 in range(0, n_st, step):
        i1 = min(n_st, i0 + step)
        solver.feed(np.ascontiguousarray(band_ds[i0:i1], dtype=np.float64),
                    np.ascontiguousarray(rhs_ds[i0:i1], dtype=np.float64))
    return solver.finish()


def _back_substitute(band_ds, rhs_ds, n_st, step, block=6):
    """``delta = U^-1 y`` reading the factor rows in reverse segments, the next one read while
    the current one is solved."""
    n = block * n_st
    x = paging.zeros(n)

    def read(lo, hi):
        return (np.ascontiguousarray(band_ds[lo:hi], dtype=np.float64),
                np.ascontiguousarray(rhs_ds[lo:hi], dtype=np.float64))

    bg = _Background()
    stop = n_st
    start = max(0, stop - step)
    chunk = read(start, stop)
    while stop > 0:
        nxt = max(0, start - step)
        if start > 0:
            bg.start(read, nxt, start)
        _back_rows(chunk[0], chunk[1], x, start, n)
        chunk = bg.wait() if start > 0 else None
        stop, start = start, nxt
    return x.reshape(n_st, block)


@njit(cache=True, nogil=True)
def _inverse_rows(fns, fac, i0, n, zb, state, out_blocks, margin, sb, uh, ut, w, s, g):
    """Takahashi's recurrence for the stations ``i0 ..`` of the diagonal-first factor rows
    ``fac`` (in reverse), ``sb`` stations (``nb = k sb`` scalar rows ``H``) at a time:
    with ``T`` the ``u`` scalar rows after ``H`` (``u`` the scalar band width),
    ``Z = M^-1 = U^-1 U'^-1`` and ``V = U[H, H]^-1`` (dtrsm of the identity, nb x nb),

        G = V U[H, T]                                     (dgemm)
        Z[H, T] = -G Z[T, T]                              (dgemm)
        Z[H, H] = V V' - Z[H, T] G'                       (two dgemm)

    (from ``U Z = U'^-1``, lower triangular, and ``Z`` symmetric; the rows of ``H`` a
    block of ``U``'s upper triangle). The same as ``Z[H, T] = -V (U[H, T] Z[T, T])``, with
    no triangular solve of ``nb x u``: OpenBLAS's dtrsm of that shape ran at a sixth of
    dgemm's rate (measured; the inversion 0.44 s against 0.22 at 10 000 stations of band
    width 42, one thread). Only dgemm and dtrsm: OpenBLAS's dtrtri, dlauum and dtrmm round
    differently on one thread and on two, so the results would follow the machine's load
    (:mod:`sapgo.threads`); dgemm does too where it splits its work (band widths of about
    100 stations and more: the last bit, docs/theory.md). ``zb`` (B x B, ``B >= nb + u + margin``) holds ``Z``
    of the scalar rows and columns ``base .. base + B`` (``state[0] = base``), shifted
    when the rows reach its start (the band of ``Z`` only: nothing reads further), so that
    the block the rows need is contiguous;
    ``out_blocks[i - i0]`` receives the k x k diagonal block of station ``i``. Work space:
    ``uh`` (nb x nb), ``ut``, ``w``, ``g`` (nb x u) and ``s`` (nb x nb), F order, flat."""
    width = fac.shape[2]
    kb = fac.shape[1]
    u = width - 1
    bsz = zb.shape[0]
    flat = zb.reshape(-1)
    hi = fac.shape[0]
    while hi > 0:
        lo = max(0, hi - sb)
        nb = kb * (hi - lo)
        h0 = kb * (i0 + lo)
        t = min(u, n - h0 - nb)
        base = state[0]
        if h0 < base:  # shift the window: rows h0+nb .. h0+nb+u+margin-1 to its top part
            nbase = max(0, h0 + nb + u + margin - bsz)
            kept = min(u + margin, n - h0 - nb, base + bsz - h0 - nb)
            d0 = h0 + nb - base
            d1 = h0 + nb - nbase
            for a in range(kept - 1, -1, -1):  # moving down: last row first; the band only
                for c in range(max(0, a - u), min(kept, a + u + 1)):
                    zb[d1 + a, d1 + c] = zb[d0 + a, d0 + c]
            state[0] = nbase
            base = nbase
        p = h0 - base
        for c in range(nb * nb):
            uh[c] = 0.0
        for c in range(nb * t):
            ut[c] = 0.0
        for a in range(nb):   # U[H, H] and U[H, T] from the diagonal-first rows
            ii = lo + a // kb
            r = a % kb
            for d in range(min(width, nb + t - a)):
                col = a + d
                if col < nb:
                    uh[col * nb + a] = fac[ii, r, d]
                else:
                    ut[(col - nb) * nb + a] = fac[ii, r, d]
        for c in range(nb * nb):
            s[c] = 0.0
        for a in range(nb):
            s[a * nb + a] = 1.0
        trsm(fns.dtrsm, L, U, N, N, nb, nb, 1.0, uh, nb, s, nb)   # V
        for c in range(nb * nb):
            uh[c] = s[c]
        gemm(fns.dgemm, N, T, nb, nb, nb, 1.0, uh, nb, uh, nb, 0.0, s, nb)   # V V'
        if t > 0:
            q = (p + nb) * bsz + p + nb
            gemm(fns.dgemm, N, N, nb, t, nb, 1.0, uh, nb, ut, nb, 0.0, g, nb)   # G
            gemm(fns.dgemm, N, N, nb, t, t, -1.0, g, nb, flat[q:], bsz, 0.0, w, nb)
            gemm(fns.dgemm, N, T, nb, nb, t, -1.0, w, nb, g, nb, 1.0, s, nb)
            for c in range(t):
                for a in range(nb):
                    zb[p + a, p + nb + c] = w[c * nb + a]
                    zb[p + nb + c, p + a] = w[c * nb + a]
        for c in range(nb):
            for a in range(c + 1):
                zb[p + a, p + c] = s[c * nb + a]
                zb[p + c, p + a] = s[c * nb + a]
        for ii in range(lo, hi):
            q = kb * (i0 + ii) - base
            for a in range(kb):
                for c in range(kb):
                    out_blocks[ii, a, c] = zb[q + a, q + c]
        hi = lo


#: Stations a block of rows of the selected inversion (:func:`_inverse_rows`) at most.
INVERSE_STATIONS = 8
#: Stations a block where its main product (``nb x u`` by ``u x u``) stays below
#: ``SMALL_GEMM`` multiply-adds (else 1 station, if that does): there OpenBLAS multiplies
#: without packing, and blocks of 2 stations ran 1.5-1.7 times faster than blocks of 8
#: (band widths 8-42, one thread: 0.092 s against 0.154 at 3 936 stations of band width 42),
#: blocks of 1 station 5-9 % faster at 50-60; above that blocks of 8 were as fast as any
#: (band widths 80-150).
SMALL_INVERSE_STATIONS = 2
SMALL_GEMM = 1_000_000


def inverse_stations(kb, band_width):
    """Stations a block of rows of the selected inversion, for ``kb`` parameters a station
    and band width ``band_width`` (stations)."""
    u = kb * band_width - 1
    for sb in (SMALL_INVERSE_STATIONS, 1):
        if kb * sb * u * u <= SMALL_GEMM:
            return max(1, min(sb, band_width))
    return max(1, min(INVERSE_STATIONS, band_width))

#: Bytes of the selected inversion's window of ``Z`` at most, when a larger block of stations
#: (their points' precision at once, :func:`covariance_blocks`' ``on_block``) asks for more
#: than the band needs. The window's band is what the inversion's products read: beyond the
#: cache it ran at half its rate (measured, precision pass of the adjustment, medians of 9
#: and 3 runs: 1 000 photos of band width 22 31.5 ms with 64 MiB, 26.8 with 8, 25.6 with 4,
#: 26.4 with 2; 10 000 photos of band width 42 367 ms with 64 MiB, 336 with 8, 340 with 4,
#: 377 with 2, where the points' calls grow too many).
INVERSE_WINDOW_BYTES = 8 << 20


#: Flops of the selected inversion (``2 n u^2``) per observation of the points below which
#: the points go beside the inversion (:func:`covariance_blocks`): there the inversion on one
#: BLAS thread still takes longer than the points, and the points' time is saved; above it
#: the inversion's second thread saves more. From the two blocks measured: 100 000 photos in
#: strips (band width 42, 84 000 flops an observation), precision pass 4.4 s one after the
#: other, 3.4 s side by side; the 200 x 200 block (band width 203, 2 million flops an
#: observation), 10.8 s against 16.3 s.
OVERLAP_FLOPS_PER_OBSERVATION = 300_000
#: Observations of the points at least, for the points to go beside the inversion: below,
#: one after the other, the inversion's BLAS and then the points on every thread were
#: faster (measured, precision pass of the adjustment, medians of 9 runs in 8 interleaved
#: rounds: 1 000 photos in strips, 8 940 observations, 18.6 ms against 21.6 side by side;
#: 10 000 photos, 89 400 observations, 0.36-0.37 s one after the other against 0.27-0.29
#: side by side).
OVERLAP_MIN_OBSERVATIONS = 30_000


def covariance_blocks(factor_ds, n_st, band_width, step=256, out=None, on_block=None,
                      observations=0):
    """The 6x6 diagonal blocks of ``M^-1`` (the stations' cofactor matrices) from the factor
    rows of :class:`BandSolver` (diagonal-first, ``factor_ds`` n x 6 x 6b), by Takahashi's
    recurrence streamed backwards ``step`` stations at a time, by blocks of
    :func:`inverse_stations` stations (BLAS-3, :func:`_inverse_rows`): in core ``Z`` of a window
    of at least ``4 (6b) + 6`` scalar rows and columns (``(24 b)^2`` doubles) and one block of
    factor rows. Returns the
    blocks (n x 6 x 6), or writes them to ``out`` (a direct-access file, dataset or array)
    block by block and returns the variances (n x 6) only.

    ``on_block(start, stop, zb, base)`` is called after each block of stations
    ``start .. stop`` (then at most ``step`` stations, at least ``b`` unless ``step`` is
    smaller, and no more than the window's ``INVERSE_WINDOW_BYTES`` allow beyond those ``b``):
    ``zb[k - base, j - base] = Z[k, j]`` for
    the scalar rows and columns ``k, j`` of those stations and the ``6b - 1`` after them,
    inside the band (the covariances a point observed from those stations needs); with
    ``alone=True`` where no inversion runs beside it (the last block, or every block when
    the two do not overlap): then it may take every thread. Stations
    of ``k`` parameters (``factor_ds`` n x k x kb) give k x k blocks. ``observations``: how
    many image observations ``on_block`` will visit, for the choice of
    :data:`OVERLAP_FLOPS_PER_OBSERVATION` and :data:`OVERLAP_MIN_OBSERVATIONS`."""
    from concurrent.futures import ThreadPoolExecutor

    kb = factor_ds.shape[1]
    width = kb * band_width
    u = width - 1
    n = kb * n_st
    sb = inverse_stations(kb, band_width)
    nb = kb * sb
    threads = _threads.parts()
    # with two threads or more and enough observations for on_block (above), on_block on a
    # thread of its own: two windows of Z in turn,
    # each one block of stations and the band after it (the next block's first rows, the
    # band after it, copied over first), the inversion's BLAS on one thread beside it (on
    # two it was slower, measured); else one window, shifted when the rows reach its start
    overlap = (on_block is not None and threads > 1
               and observations >= OVERLAP_MIN_OBSERVATIONS
               and 2.0 * n * u * u < OVERLAP_FLOPS_PER_OBSERVATION * observations)
    margin = 0
    if overlap:
        most = int(np.sqrt(INVERSE_WINDOW_BYTES / 8)) - u - kb
        step = max(1, min(step, max(band_width, most // kb)))
        bsz = min(n, kb * step + u + kb)
    else:
        if on_block is not None:   # blocks of at least b stations, more while the window fits
            most = int(np.sqrt(INVERSE_WINDOW_BYTES / 8)) - nb - kb - 2 * u
            step = max(1, min(step, max(band_width, most // (2 * kb))))
            margin = kb * step
        # (shifted every u + margin rows or so: the copies cost about u + margin a row)
        bsz = max(4 * width + kb, 2 * (u + margin) + nb + kb)
    wins = [np.zeros((bsz, bsz)) for _ in range(2 if overlap else 1)]
    bases = [max(0, n - bsz)] * len(wins)
    busy = [None] * len(wins)   # the on_block still reading each window
    uh, s = np.empty(nb * nb), np.empty(nb * nb)
    ut, w, g = (np.empty(nb * max(u, 1)) for _ in range(3))
    keep = out is None
    blocks_all = np.empty((n_st, kb, kb)) if keep else None
    var = paging.empty((n_st, kb))
    cur = 0
    stop = n_st
    pool = ThreadPoolExecutor(1) if overlap else None
    try:
        while stop > 0:
            start = max(0, stop - step)
            if overlap:
                if busy[cur] is not None:
                    busy[cur].result()
                    busy[cur] = None
                base = max(0, min(kb * stop + u, n) - bsz)
                if stop < n_st:   # the band after the block, from the other window
                    t = min(u, n - kb * stop)
                    _copy_rows(wins[1 - cur], bases[1 - cur], wins[cur], base, kb * stop, t)
                bases[cur] = base
            fac = np.ascontiguousarray(factor_ds[start:stop], dtype=np.float64)
            blocks = np.empty((stop - start, kb, kb))
            state = np.array([bases[cur]], np.int64)
            others = _threads.adapt() == 1 < threads   # (another process running)
            with blas_limits(1 if overlap or others else threads):
                _inverse_rows(FNS, fac, start, n, wins[cur], state, blocks, margin, sb, uh, ut,
                              w, s, g)
            bases[cur] = int(state[0])   # (shifted, on one window; never on two)
            var[start:stop] = np.diagonal(blocks, axis1=1, axis2=2)
            if overlap and start > 0:
                busy[cur] = pool.submit(on_block, start, stop, wins[cur], bases[cur])
                cur = 1 - cur
            elif on_block is not None:   # (nothing to invert beside it: all threads its own)
                for f in busy:
                    if f is not None:
                        f.result()
                busy = [None] * len(wins)
                on_block(start, stop, wins[cur], bases[cur], alone=True)
            if keep:
                blocks_all[start:stop] = blocks
            else:
                out[start:stop] = blocks
            stop = start
    finally:
        for f in busy:
            if f is not None:
                f.result()
        if pool is not None:
            pool.shutdown()
    return blocks_all if keep else var


@njit(cache=True, nogil=True)
def _copy_rows(src, sbase, dst, dbase, r0, t):
    """``dst[r - dbase, c - dbase] = src[r - sbase, c - sbase]`` for ``r, c`` in
    ``r0 .. r0 + t``."""
    for a in range(t):
        for c in range(t):
            dst[r0 + a - dbase, r0 + c - dbase] = src[r0 + a - sbase, r0 + c - sbase]


def solve_in_core(band, rhs, pivot_tol=PIVOT_TOLERANCE, panel=None, threads=None):
    """Factor band rows ``band`` (n x 6 x 6b) and solve; returns ``(factor, delta)``.

    The same kernels and driver as the out-of-core path, on arrays instead of files (segments
    of 256 stations: the ring stays small and in cache); ``factor`` holds the band rows of
    ``U`` (as :func:`factor_to_band`).
    """
    band = np.array(band, dtype=np.float64, order="C")
    kb = band.shape[1]
    y = np.array(rhs, dtype=np.float64, order="C").reshape(-1, kb)
    delta = solve_out_of_core(band, y, band.shape[2] // kb, 256, pivot_tol, panel=panel,
                              threads=threads)
    return factor_to_band(band), delta


def band_to_dense(band):
    """The full symmetric matrix of band rows (for tests and small problems)."""
    n, q, width = band.shape
    bw = width // q
    a = np.zeros((q * n, q * n))
    for i in range(n):
        for k in range(bw):
            j = i + k
            if j >= n:
                break
            blk = band[i, :, q * k:q * k + q]
            a[q * i:q * i + q, q * j:q * j + q] = blk
            if k:
                a[q * j:q * j + q, q * i:q * i + q] = blk.T
            else:
                a[q * i:q * i + q, q * i:q * i + q] = np.triu(blk) + np.triu(blk, 1).T
    return a


def dense_to_band(a, band_width, block=6):
    """Band rows of a symmetric block-banded matrix (inverse of :func:`band_to_dense`),
    ``block`` parameters per station."""
    q = block
    n = a.shape[0] // q
    band = np.zeros((n, q, q * band_width))
    for i in range(n):
        for k in range(band_width):
            j = i + k
            if j >= n:
                break
            band[i, :, q * k:q * k + q] = a[q * i:q * i + q, q * j:q * j + q]
    return band


# -- drop-in replacements for scipy.linalg.cholesky_banded / cho_solve_banded -----------

def _skewed(ab, lower, p):
    """Skewed storage for a LAPACK banded array ``ab`` (u + 1, n), upper or lower form.

    Returns ``(a, view, u, n, ld1)``: ``a`` is the kernel's storage (column ``h`` of ``L`` at
    ``a[h ld1:]``) and ``view`` an (u + 1, n) strided view of it laid out like ``ab``, which
    received ``ab`` in one copy and shows the factor afterwards. Entries of ``ab`` that the
    factorisation does not reference keep their values.
    """
    u, n = ab.shape[0] - 1, ab.shape[1]
    ld1 = u + p + 1
    ring = _up(max(n, 1), p)
    pad = 0 if lower else u * ld1        # the upper form's unreferenced corner lies before
    buf = np.zeros(pad + ring * ld1)
    item = buf.itemsize
    if lower:  # ab[d, h] = L[h + d, h] at a[h ld1 + d]
        view = np.lib.stride_tricks.as_strided(buf, (u + 1, n), (item, ld1 * item))
    else:  # ab[i, j] = U[j - u + i, j] = L[j, j - u + i] at a[(j - u + i) ld1 + u - i]
        view = np.lib.stride_tricks.as_strided(buf[pad - u * ld1 + u:], (u + 1, n),
                                               ((ld1 - 1) * item, ld1 * item))
    if ab.dtype == np.float64:
        _skew_copy(ab, buf[pad:], ld1, lower)
    else:
        view[...] = ab
    return buf[pad:], view, u, n, ld1


@njit(cache=True, nogil=True, parallel=True)
def _skew_copy(ab, a, ld1, lower):
    """``a[h ld1 + d] = L[h + d, h]`` from LAPACK storage, 64 columns at a time (both reads and
    writes stay in cache; a plain strided assignment is a cache-hostile transposition)."""
    u, n = ab.shape[0] - 1, ab.shape[1]
    for blk in prange((n + 63) // 64):
        h0 = 64 * blk
        h1 = min(n, h0 + 64)
        for d in range(u + 1):
            if lower:
                for h in range(h0, h1):
                    a[h * ld1 + d] = ab[d, h]
            else:
                for h in range(h0, min(h1, n - d)):
                    a[h * ld1 + d] = ab[u - d, h + d]


def _banded_input(ab, check_finite):
    ab = np.asarray_chkfinite(ab) if check_finite else np.asarray(ab)
    if ab.ndim != 2:
        raise ValueError(f"expected a 2-D banded array (u + 1, n), got shape {ab.shape}")
    return ab


def cholesky_banded(ab, overwrite_ab=False, lower=False, check_finite=True):
    """Cholesky factor of a symmetric positive definite banded matrix, as SciPy's.

    Same storage, arguments and result as :func:`scipy.linalg.cholesky_banded` (upper form
    ``ab[u + i - j, j] == a[i, j]`` for i <= j, lower form ``ab[i - j, j] == a[i, j]`` for
    i >= j), and computed by it: LAPACK ``dpbtrf``. Called this way, on an array in
    LAPACK's storage that has to be copied into the panel kernel's skewed layout and back,
    sapgo's own kernel was slower than LAPACK at every band width measured (random band
    matrices, 5 000-200 000 unknowns, 6-600 off-diagonals, both forms: 0.32-1.01 times
    LAPACK's speed, medians of 5 interleaved runs); its place is the out-of-core solver
    (:class:`BandSolver`, :func:`solve_out_of_core`), which keeps the band rows in the
    kernel's own layout and streams them from disk. Raises
    :class:`numpy.linalg.LinAlgError` naming the leading minor that is not positive
    definite.
    """
    ab = _banded_input(ab, check_finite)
    c = scipy.linalg.cholesky_banded(ab, overwrite_ab=overwrite_ab, lower=lower,
                                     check_finite=False)
    if overwrite_ab and c is not ab and ab.dtype == np.float64 and ab.flags.writeable:
        ab[...] = c   # (the factor in the caller's array, as before)
        return ab
    return c


def cho_solve_banded(cb_and_lower, b, overwrite_b=False, check_finite=True):
    """Solve ``a x = b`` with the factor from :func:`cholesky_banded`, as SciPy's (LAPACK
    ``dpbtrs``). ``b`` may be a vector (n,) or a matrix (n, k)."""
    cb, lower = cb_and_lower
    cb = _banded_input(cb, check_finite)
    b = np.asarray_chkfinite(b) if check_finite else np.asarray(b)
    if b.shape[0] != cb.shape[1]:
        raise ValueError(f"shapes of cb {cb.shape} and b {b.shape} are not compatible")
    return scipy.linalg.cho_solve_banded((cb, lower), b, overwrite_b=overwrite_b,
                                         check_finite=False)
