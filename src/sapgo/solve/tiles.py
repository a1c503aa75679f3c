"""Tiled out-of-core fronts: fronts too large for the memory budget, factored and inverted a
column panel at a time (DESIGN 5b; docs/theory.md section 2b).

A *tiled* front of order ``kf`` (``m`` own unknowns, ``f`` boundary ones) is never in core as
a whole. Its columns are cut into panels (own ones, then boundary ones, each a whole number
of stations wide, :func:`node_bounds`), and the left-looking blocked Cholesky runs panel by
panel:

    for each panel j (columns c0 .. c1):
        assemble A[c0:, c0:c1]          own points, priors, damping, children's updates
        A[c0:, j] -= L[c0:, q] L[c0:c1, q]'   for every own panel q before j (read back)
        own panel:       L_jj = chol(A_jj), L_Rj = A_Rj L_jj'^-1, y_j = L_jj^-1 b_j,
                         b_R -= L_Rj y_j      -> the factor file
        boundary panel:  it is the update matrix's panel -> a :class:`Panels` file for
                         the parent

so in core are the panel being assembled, one factor panel read back and a part of a child's
update: a few panels, whatever the front's size. The selected inversion runs the same way
from the last own panel to the first (Takahashi's recurrences by blocks):

    X_q  = L_Rq L_qq^-1,   Z_Rq = -Z_RR X_q,   Z_qq = L_qq'^-1 L_qq^-1 - X_q' Z_Rq

with ``Z_RR`` (the inverse over the later panels, the boundary's part handed down by the
parent) read back panel by panel. The inverse is kept as :class:`Panels` and read by column
where the points' quality and the children's parts need it.

:class:`Panels` is a symmetric matrix stored as its lower triangle by column panels, panel
``j`` the rectangle of rows ``b[j] .. n`` and columns ``b[j] .. b[j+1]`` in Fortran order (its
diagonal block stored in full), in a scratch file of the work directory, removed on close.
"""

from __future__ import annotations

import os
from itertools import count

import numpy as np
from numba import njit

from ..blas import FNS, L, N, R, T, gemm, potrf, syrk, trmm, trsm, trtri

_SERIAL = count()


def panel_width(rows, k, panel_bytes):
    """Columns of a panel of ``rows`` rows within ``panel_bytes``: a whole number of
    stations (``k`` columns each), at least one."""
    return max(k, int(panel_bytes // (8 * max(rows, 1))) // k * k)


def node_bounds(m, f, k, panel_bytes):
    """Panel boundaries of a tiled front: the own columns ``0 .. m`` in panels of ``m + f``
    rows, then the boundary ``m .. m + f`` in panels of at most ``f`` rows (these are the
    update matrix's panels)."""
    w = panel_width(m + f, k, panel_bytes)
    own = list(range(0, m, w))
    wb = panel_width(f, k, panel_bytes)
    bnd = list(range(m, m + f, wb))
    return np.array(own + bnd + [m + f], np.int64)


def update_bounds(m, f, k, panel_bytes):
    """The boundary panels of :func:`node_bounds` as the update matrix's own (0 .. f)."""
    b = node_bounds(m, f, k, panel_bytes)
    return b[b >= m] - m


class Panels:
    """A symmetric ``n x n`` matrix by lower column panels in a scratch file (module doc).

    ``bounds``: the panels' first columns and ``n``. Panels are written whole
    (:meth:`write`) in any order and read whole, by column range or by column."""

    def __init__(self, directory, n, bounds):
        self.n = int(n)
        self.b = np.asarray(bounds, np.int64)
        w = np.diff(self.b)
        size = 8 * (self.n - self.b[:-1]) * w
        self.off = np.zeros(len(w), np.int64)
        self.off[1:] = np.cumsum(size)[:-1]
        self.nbytes = int(size.sum())
        self.path = os.path.join(str(directory), f"panels-{os.getpid()}-{next(_SERIAL)}.bin")
        self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_TRUNC, 0o600)

    @property
    def n_panels(self):
        return len(self.b) - 1

    def write(self, j, a):
        """Panel ``j``: ``(n - b[j]) x w`` (Fortran order)."""
        a = np.asfortranarray(a)
        assert a.shape == (self.n - self.b[j], self.b[j + 1] - self.b[j])
        os.pwrite(self._fd, memoryview(a.reshape(-1, order="F")), int(self.off[j]))

    def _read(self, nbytes, offset):
        buf = os.pread(self._fd, nbytes, offset)
        if len(buf) != nbytes:
            raise OSError(f"{self.path}: panel data cut short")
        return np.frombuffer(buf, np.float64)

    def panel(self, j):
        rows = self.n - int(self.b[j])
        w = int(self.b[j + 1] - self.b[j])
        return self._read(8 * rows * w, int(self.off[j])).reshape((rows, w), order="F")

    def cols(self, c0, c1):
        """Rows ``c0 .. n`` of columns ``c0 .. c1`` (Fortran order; above the diagonal only
        what a panel's diagonal block holds)."""
        out = np.empty((self.n - c0, c1 - c0), order="F")
        p = int(np.searchsorted(self.b, c0, side="right")) - 1
        c = c0
        while c < c1:
            b0, b1 = int(self.b[p]), int(self.b[p + 1])
            e = min(c1, b1)
            rows = self.n - b0
            blk = self._read(8 * rows * (e - c), int(self.off[p]) + 8 * rows * (c - b0))
            blk = blk.reshape((rows, e - c), order="F")
            if b0 >= c0:   # a later panel: its rows start at b0 (above: upper, unset)
                out[:b0 - c0, c - c0:e - c0] = 0.0
                out[b0 - c0:, c - c0:e - c0] = blk
            else:
                out[:, c - c0:e - c0] = blk[c0 - b0:]
            c, p = e, p + 1
        return out

    def column(self, c, r0, r1=None):
        """Rows ``r0 .. r1`` (default ``n``) of column ``c`` (``r0 >=`` the first column of
        ``c``'s panel)."""
        p = int(np.searchsorted(self.b, c, side="right")) - 1
        b0 = int(self.b[p])
        rows = self.n - b0
        r1 = self.n if r1 is None else r1
        return self._read(8 * (r1 - r0), int(self.off[p]) + 8 * ((c - b0) * rows + r0 - b0))

    def gather(self, idx):
        """The full symmetric matrix over the ascending indices ``idx`` (Fortran order)."""
        idx = np.asarray(idx, np.int64)
        n = len(idx)
        out = np.empty((n, n), order="F")
        last = int(idx[-1]) + 1 if n else 0
        for c in range(n):   # (each column read from its diagonal to the last row wanted)
            col = self.column(int(idx[c]), int(idx[c]), last)
            out[c:, c] = col[idx[c:] - idx[c]]
        _upper_from_lower(out)
        return out

    def gather_panels(self, idx, bounds, directory):
        """:meth:`gather` into a new :class:`Panels` with ``bounds`` (a child's update
        layout), a panel at a time."""
        idx = np.asarray(idx, np.int64)
        out = Panels(directory, len(idx), bounds)
        try:
            for j in range(out.n_panels):
                o0, o1 = int(bounds[j]), int(bounds[j + 1])
                a = np.empty((len(idx) - o0, o1 - o0), order="F")
                for c in range(o0, o1):
                    col = self.column(int(idx[c]), int(idx[c]), int(idx[-1]) + 1)
                    a[c - o0:, c - o0] = col[idx[c:] - idx[c]]
                _upper_from_lower(a)
                out.write(j, a)
        except BaseException:
            out.close()
            raise
        return out

    def dense(self):
        """The whole matrix in core (full, Fortran order)."""
        out = np.empty((self.n, self.n), order="F")
        for j in range(self.n_panels):
            b0, b1 = int(self.b[j]), int(self.b[j + 1])
            out[b0:, b0:b1] = self.panel(j)
        _upper_from_lower(out)
        return out

    def diag_blocks(self, k, s0, s1):
        """The ``k x k`` diagonal blocks of stations ``s0 .. s1`` (columns ``k s``)."""
        out = np.empty((s1 - s0, k, k))
        for s in range(s0, s1):
            for c in range(k):
                col = self.column(k * s + c, k * s + c)
                out[s - s0, c:, c] = col[:k - c]
                out[s - s0, c, c:] = col[:k - c]
        return out

    def close(self):
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass

    def __getstate__(self):
        # sent to another process (Dask, a shared filesystem): the file's place, not its
        # data; the receiver opens it and owns it from then on (its close removes it)
        state = dict(self.__dict__)
        state["_fd"] = None
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._fd = os.open(self.path, os.O_RDWR)

    def __del__(self):
        self.close()


def write_dense_panels(z, bounds, directory, shift=0):
    """A :class:`Panels` of ``z[shift:, shift:]`` (full symmetric, Fortran order) with
    ``bounds`` (relative to ``shift``)."""
    n = z.shape[0] - shift
    out = Panels(directory, n, bounds)
    for j in range(out.n_panels):
        b0, b1 = int(bounds[j]) + shift, int(bounds[j + 1]) + shift
        out.write(j, z[b0:, b0:b1])
    return out


@njit(cache=True, nogil=True)
def _upper_from_lower(a):
    """Copy the lower triangle of the leading square of ``a`` into its upper one."""
    w = min(a.shape[0], a.shape[1])
    for c in range(w):
        for r in range(c + 1, w):
            a[c, r] = a[r, c]


@njit(cache=True, nogil=True)
def _left_update(fns, a, lda, rows, w, lq, kf, r0, wq):
    """``A[:rows, :w] -= Lq[r0:r0+rows] Lq[r0:r0+w]'`` (a panel's update from an earlier
    own panel ``Lq``, kf x wq, Fortran order)."""
    gemm(fns.dgemm, N, T, rows, w, wq, -1.0, lq[r0:], kf, lq[r0:], kf, 1.0, a, lda)


@njit(cache=True, nogil=True)
def potrf_tested(fns, a, lda, w, tol, orig):
    """``dpotrf`` of the leading ``w x w`` block of ``a`` with the band solver's pivot test:
    0, or 1 + the first column whose pivot (squared diagonal of the factor) is at or below
    ``tol`` times ``orig`` (its diagonal before the factorisation), or where dpotrf
    failed."""
    info = potrf(fns.dpotrf, L, w, a, lda)
    good = w if info == 0 else info - 1
    for j in range(good):
        d = a[j * lda + j]
        if not (d * d > tol * orig[j]):
            return j + 1
    return info


#: Columns below which :func:`chol_columns` leaves the work to LAPACK's ``dpotrf`` and
#: BLAS' ``dtrsm`` (above it, halves: the bulk in ``dgemm`` and ``dsyrk``, which run near
#: the machine's peak where OpenBLAS' ``dtrsm`` and ``dpotrf`` do not on fronts of a few
#: hundred columns).
CHOL_LEAF = 32


@njit(cache=True, nogil=True)
def chol_columns(fns, a, lda, rows, w, tol, orig):
    """Cholesky factor of a column panel in place: ``a`` (F order, leading dimension
    ``lda``) holds ``rows x w`` with its leading ``w x w`` block symmetric (lower triangle
    used); on return ``[L11; L21]``, ``L11 = chol(A11)`` and ``L21 = A21 L11'^-1``. By
    recursive halves of the columns (Gustavson's recursive Cholesky): the left half, its
    update of the right half (``dsyrk``, ``dgemm``), the right half. Returns 0, or 1 + the
    first column whose pivot fails :func:`potrf_tested`'s test (``orig``: the diagonal
    before the factorisation)."""
    if w <= CHOL_LEAF:
        fail = potrf_tested(fns, a, lda, w, tol, orig)
        if fail:
            return fail
        if rows > w:
            trsm(fns.dtrsm, R, L, T, N, rows - w, w, 1.0, a, lda, a[w:], lda)
        return 0
    h = w // 2
    fail = chol_columns(fns, a, lda, rows, h, tol, orig)
    if fail:
        return fail
    syrk(fns.dsyrk, L, N, w - h, h, -1.0, a[h:], lda, 1.0, a[h * lda + h:], lda)
    if rows > w:
        gemm(fns.dgemm, N, T, rows - w, w - h, h, -1.0, a[w:], lda, a[h:], lda, 1.0,
             a[h * lda + w:], lda)
    fail = chol_columns(fns, a[h * lda + h:], lda, rows - h, w - h, tol, orig[h:])
    return fail + h if fail else 0


@njit(cache=True, nogil=True)
def _factor_panel(fns, a, lda, w, b, ldb, c0, nr, tol, orig):
    """Factor an own panel in place (``a``: rows c0 .. kf of its w columns): ``L_jj =
    chol(A_jj)``, ``L_Rj = A_Rj L_jj'^-1``; forward-substitute the right-hand sides
    (``b``: kf x nr, Fortran order) through it. Returns 0 or 1 + the panel's first column
    whose pivot is at or below ``tol`` times its diagonal before the factorisation
    (``orig``, as assembled)."""
    fail = chol_columns(fns, a, lda, lda, w, tol, orig)
    if fail:
        return fail
    below = lda - w
    trsm(fns.dtrsm, L, L, N, N, w, nr, 1.0, a, lda, b[c0:], ldb)
    if below > 0:
        gemm(fns.dgemm, N, N, below, nr, w, -1.0, a[w:], lda, b[c0:], ldb, 1.0, b[c0 + w:],
             ldb)
    return 0


@njit(cache=True, nogil=True)
def _inverse_panel_start(fns, lq, ld, w, x, linv):
    """From own factor panel ``lq`` (its rows from its first column: ``ld`` x w, Fortran
    order): ``linv = L_qq^-1`` (w x w) and ``x = L_Rq L_qq^-1`` ((ld - w) x w)."""
    rows = ld - w
    for c in range(w):
        for r in range(w):
            linv[c * w + r] = lq[c * ld + r] if r >= c else 0.0
    trtri(fns.dtrtri, L, N, w, linv, w)
    for c in range(w):
        for r in range(rows):
            x[c * rows + r] = lq[c * ld + w + r]
    if rows > 0:
        trmm(fns.dtrmm, R, L, N, N, rows, w, 1.0, linv, w, x, rows)


@njit(cache=True, nogil=True)
def _sym_panel_product(fns, zp, wp, x, rows, w, y, off):
    """``Y += Z X`` for the part of a symmetric ``Z`` held by one of its lower panels
    ``zp`` (rows off .. rows of the panel's columns off .. off+wp, relative to ``X``'s and
    ``Y``'s rows; ``rows x w`` each, Fortran order): the panel itself and its transpose
    below the diagonal block."""
    pr = rows - off
    gemm(fns.dgemm, N, N, pr, w, wp, 1.0, zp, pr, x[off:], rows, 1.0, y[off:], rows)
    if pr > wp:
        gemm(fns.dgemm, T, N, wp, w, pr - wp, 1.0, zp[wp:], pr, x[off + wp:], rows, 1.0,
             y[off:], rows)


@njit(cache=True, nogil=True)
def _inverse_panel_finish(fns, linv, x, y, rows, w, out):
    """Panel ``q`` of the inverse (``out``: (w + rows) x w, Fortran order):
    ``Z_qq = Linv' Linv + X' Y`` (in full) and ``Z_Rq = -Y``."""
    ld = w + rows
    syrk(fns.dsyrk, L, T, w, w, 1.0, linv, w, 0.0, out, ld)
    for c in range(w):
        for r in range(c):
            out[c * ld + r] = 0.0
    if rows > 0:
        gemm(fns.dgemm, T, N, w, w, rows, 1.0, x, rows, y, rows, 1.0, out, ld)
    for c in range(w):
        for r in range(c + 1, w):
            out[r * ld + c] = out[c * ld + r]
        for r in range(rows):
            out[c * ld + w + r] = -y[c * rows + r]


def invert_tiled(lcols, m, kf, bounds, z22, directory):
    """Selected inversion of a tiled front: the inverse over it as :class:`Panels`
    (``bounds``: :func:`node_bounds`). ``lcols(c0, c1)`` reads the factor's columns
    ``c0 .. c1`` from row ``c0`` (Fortran order); ``z22``: the inverse over the boundary, dense
    (full, Fortran order) or :class:`Panels` laid out as the boundary panels of ``bounds``."""
    z = Panels(directory, kf, bounds)
    try:
        n_own = int(np.searchsorted(bounds, m))
        for j in range(n_own, len(bounds) - 1):   # the boundary's part, as handed down
            b0, b1 = int(bounds[j]), int(bounds[j + 1])
            if isinstance(z22, Panels):
                z.write(j, z22.panel(j - n_own))
            else:
                z.write(j, z22[b0 - m:, b0 - m:b1 - m])
        for q in range(n_own - 1, -1, -1):
            c0, c1 = int(bounds[q]), int(bounds[q + 1])
            w = c1 - c0
            rows = kf - c1
            lq = np.asfortranarray(lcols(c0, c1))
            linv = np.empty(w * w)
            x = np.empty(rows * w)
            _inverse_panel_start(FNS, lq.reshape(-1, order="F"), kf - c0, w, x, linv)
            del lq
            y = np.zeros(rows * w)
            for p in range(q + 1, len(bounds) - 1):
                zp = z.panel(p)
                _sym_panel_product(FNS, zp.reshape(-1, order="F"), zp.shape[1], x, rows, w, y,
                                   int(bounds[p]) - c1)
                del zp
            out = np.empty((kf - c0, w), order="F")
            _inverse_panel_finish(FNS, linv, x, y, rows, w, out.reshape(-1, order="F"))
            z.write(q, out)
    except BaseException:
        z.close()
        raise
    return z


@njit(cache=True, nogil=True)
def extend_add(a, off, s, s0, ix, ca, cb):
    """``a[ix[r] - off, ix[c] - off] += s[r - s0, c - s0]`` for the columns ``c`` in
    ``ca .. cb`` and the rows ``r >= c`` of a child's update (``s``: its rows and columns
    from ``s0``; ``ix`` ascending, the places of the child's boundary in the parent's front;
    ``a`` the parent's front, or its panel starting at row and column ``off``). ``ix`` runs
    in stretches of consecutive places (a station's k unknowns at least), so each column is
    added stretch by stretch, contiguous on both sides."""
    n = ix.shape[0]
    start = np.empty(n + 1, np.int64)   # the stretches: [start[s], start[s + 1])
    ns = 0
    for r in range(n):
        if r == 0 or ix[r] != ix[r - 1] + 1:
            start[ns] = r
            ns += 1
    start[ns] = n
    st = 0
    for c in range(ca, cb):
        jc = ix[c] - off
        while start[st + 1] <= c:
            st += 1
        for q in range(st, ns):
            r0 = max(start[q], c)
            r1 = start[q + 1]
            d = ix[r0] - r0 - off
            for r in range(r0, r1):
                a[d + r, jc] += s[r - s0, c - s0]
