"""Multifrontal Cholesky of the reduced normal equations on the partition tree (DESIGN 5b).

Node ``i`` of a :class:`~sapgo.solve.partition.Tree` has a dense *front* over its own
stations (``m = k |own|`` unknowns, ``k`` parameters a station) followed by its boundary
(``f = k |boundary|``), held as two arrays: its own columns ``[A11; A21]`` and its update
block ``A22``. In post-order, the front is assembled from

- the node's own points, each eliminated on the spot as in the band build
  (:func:`build_front`: ``M[s,t] -= Nbar_s Ndd^-1 Nbar_t'``, Brown's reduction), its own
  stations' priors, and Levenberg-Marquardt damping on its own stations' diagonal;
- the *update matrices* of its children (``extend-add``: a child's boundary is part of its
  parent's front),

and then partially factored with BLAS-3 (Duff & Reid's multifrontal method):

    L11 = chol(A11)                 dpotrf, pivots tested as in the band solver
    L21 = A21 L11'^-1               dtrsm
    U   = A22 - L21 L21'            dsyrk: the update matrix, passed to the parent
    y1  = L11^-1 b1,  b2 -= L21 y1  forward substitution, passed up with U

``L11``, ``L21`` (the own columns, as they are) and ``y1`` go to the factor file (one record
per node, written in post-order), ``U`` (the update block, as it is) to the parent; the back
substitution reads them top-down, ``x1 = L11'^-1 (y1 - L21' x2)``.

Selected inversion (Takahashi's recurrences on supernodes, as Erisman & Tinney): top-down,
with ``Z22`` the inverse's block over the boundary, gathered from the parent's front,

    X   = L21 L11^-1
    Z21 = -Z22 X
    Z11 = L11'^-1 L11^-1 - X' Z21

gives the inverse over the whole front: every pair of stations that share a point lies in the
front of the point's node, so the points' precision and their observations' redundancy
numbers come out node by node. In core: the front being worked on, the update matrices
waiting for their parents (post-order: a stack), and for the inversion the fronts' inverses
along one path from the root.
"""

from __future__ import annotations

import os

import numpy as np
import scipy.linalg
from numba import njit

from .band import PIVOT_TOLERANCE, PivotError
from .tiles import (Panels, _factor_panel, _left_update, chol_columns, extend_add,
                    invert_tiled, node_bounds, update_bounds, write_dense_panels)
from ..blas import (FNS, L, N, R, T, blas_limits, gemm, gemv, lauum, syrk, trmm, trsm,
                    trsv, trtri)
from ..geometry import N_CALIBRATION
from ..normals import (BAD_LAYOUT, BEHIND_CAMERA, OK, SINGULAR_POINT, _border_point, _chol3,
                       _inverse3, _point_system, _ray_terms, _ray_terms6, _solve3, _workspace)


@njit(cache=True, nogil=True, error_model="numpy")
def build_front(j0, j1, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start, pt_nobs,
                pt_active, obs_station, obs_xy, obs_sigma, obs_active, eo, cam_of_station, cams,
                ctrl_mask, front, upd, rhs, max_rays, npar, lam, behind_ok, cal, bord, cnn,
                ccg, cdiag, c0, c1, st_fixed=None):
    """Add points ``j0 .. j1-1`` of a chunk into a front.

    ``obs_station`` holds each observation's station as its place in the front (-1: not in
    the front), ``eo`` and ``cam_of_station`` are indexed the same way; the front's lower
    triangle (and its diagonal blocks in full) and ``rhs`` (kf) receive the reduced normals
    ``M[s,t] -= Nbar_s Ndd^-1 Nbar_t'``, ``p A'A`` and ``d``: its columns ``c0 .. c1`` (rows
    from ``c0``) in ``front`` and those from ``c1`` on in ``upd`` (rows from ``c1``; a front
    in core: ``c0 = 0``, ``c1 = m``, ``front`` its own columns ``[A11; A21]`` and ``upd``
    its update block ``A22``).
    Self-calibration (``ng = cnn.shape[0] > 0``; ``cal`` as in
    :func:`sapgo.normals.build_points`): ``bord`` (front stations x npar x ng) receives the
    front's rows of the border columns ``B``, ``cnn``, ``ccg`` and ``cdiag`` the border's
    block, right-hand side and undamped diagonal, each point eliminated from them as on
    the band (:func:`sapgo.normals._border_point`). Returns ``(status, point)``: OK, or
    SINGULAR_POINT / BEHIND_CAMERA / BAD_LAYOUT (a station of the point outside the front)
    with the point.

    A panel of a tiled front (:mod:`sapgo.solve.tiles`): ``c0, c1`` the front's columns it
    holds and ``upd`` empty (0 x 0): only the terms in these columns are added, and ``rhs``
    only in the rows of its stations."""
    nbar, a_all, l_all, w_all, st_all, nn, cc, lo, xyz, b_all, o_all = _workspace(max_rays, npar)
    g = np.empty((max_rays, npar, 3))
    nbt = np.empty((max_rays, 3, npar))
    ninv = np.empty((3, 3))
    h = np.empty(3)
    col = np.empty(3)
    tmp = np.empty(3)
    ng = cnn.shape[0]
    slot = np.full(ng, -1, np.int64)
    tcols = np.empty(ng, np.int64)
    ngp = np.empty((ng, 3))
    ggp = np.empty((ng, 3))
    e = np.empty((2, N_CALIBRATION))
    nf = bord.shape[0]
    c2 = c1 + upd.shape[0]   # the columns held: c0 .. c2
    spare = np.zeros((npar, npar))   # out-of-panel rays' diagonal terms (not kept)
    spare_rhs = np.zeros(npar)
    for j in range(j0, j1):
        if pt_active[j] != 0:
            continue
        for i in range(pt_start[j], pt_start[j] + pt_nobs[j]):
            if obs_active[i] and obs_station[i] < 0:
                return BAD_LAYOUT, j
        k = _point_system(j, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start, pt_nobs,
                          obs_station, obs_xy, obs_sigma, obs_active, eo, cam_of_station,
                          cams, ctrl_mask, xyz, nbar, a_all, l_all, w_all,
                          st_all, nn, cc, b_all, o_all, lam, behind_ok, st_fixed)
        if k < 0:
            return BEHIND_CAMERA, j
        if not _chol3(nn, lo):
            return SINGULAR_POINT, j
        _solve3(lo, cc, h)
        if npar == 6:   # (the loops over a station's parameters unrolled)
            _inverse3(lo, ninv)
        for q in range(k):
            s0 = npar * st_all[q]
            if c0 <= s0 < c1:
                diag = front[s0 - c0:s0 - c0 + npar, s0 - c0:s0 - c0 + npar]
            elif c1 <= s0 < c2:
                diag = upd[s0 - c1:s0 - c1 + npar, s0 - c1:s0 - c1 + npar]
            else:
                diag = spare
            drhs = rhs[s0:s0 + npar] if c0 <= s0 < c2 else spare_rhs
            if npar == 6:
                _ray_terms6(q, w_all, a_all, l_all, nbar, h, ninv, diag, drhs, g, nbt)
            else:
                _ray_terms(q, w_all, a_all, l_all, nbar, h, lo, npar, diag, drhs, g, col, tmp)
        # Schur complement into the lower triangle: rays are in ascending station order, so
        # the later station's rows and the earlier's columns (a diagonal block in full;
        # two rays of one station add X and X')
        for q in range(k):
            sq = npar * st_all[q]
            if c0 <= sq < c1:
                dst, off = front, c0
            elif c1 <= sq < c2:
                dst, off = upd, c1
            else:
                continue
            if npar == 6:
                _schur_blocks6(dst, off, g, nbt, q, k, st_all)
            else:
                _schur_blocks(dst, off, g, nbar, q, k, st_all, npar)
        if ng > 0:
            _border_point(j, k, pt_kind, pt_csig, ctrl_mask, eo, cam_of_station, cams, cal,
                          xyz, a_all, l_all, w_all, st_all, g, lo, h, 0, nf, bord, bord, cnn,
                          ccg, cdiag, slot, tcols, ngp, ggp, e, b_all, o_all)
    return OK, -1


@njit(cache=True, nogil=True, error_model="numpy")
def _schur_blocks(a, off, g, nbar, q, k, st_all, npar):
    """``a[s - off, t - off] -= G_q Nbar_t'`` for ray ``q``'s station (column) and the
    point's later rays' stations ``t`` (rows; a diagonal block in full, two rays of one
    station adding X and X')."""
    sq = npar * st_all[q] - off
    for t in range(q, k):
        st = npar * st_all[t] - off
        for u in range(npar):
            for v in range(npar):
                x = 0.0
                for c in range(3):
                    x += g[q, u, c] * nbar[t, v, c]
                if st != sq:
                    a[st + v, sq + u] -= x
                else:
                    a[sq + u, sq + v] -= x
                    if t != q:
                        a[sq + v, sq + u] -= x


@njit(cache=True, nogil=True, error_model="numpy")
def _schur_blocks6(a, off, g, nbt, q, k, st_all):
    """:func:`_schur_blocks` for 6 parameters a station (the loops unrolled; ``nbt``:
    ``Nbar`` transposed, :func:`sapgo.normals._ray_terms6`)."""
    sq = 6 * st_all[q] - off
    for t in range(q, k):
        st = 6 * st_all[t] - off
        for u in range(6):
            g0, g1, g2 = g[q, u, 0], g[q, u, 1], g[q, u, 2]
            if st != sq:
                for v in range(6):
                    a[st + v, sq + u] -= g0 * nbt[t, 0, v] + g1 * nbt[t, 1, v] + g2 * nbt[t, 2, v]
            else:
                for v in range(6):
                    x = g0 * nbt[t, 0, v] + g1 * nbt[t, 1, v] + g2 * nbt[t, 2, v]
                    a[sq + u, sq + v] -= x
                    if t != q:
                        a[sq + v, sq + u] -= x


def factor_layout(tree, k):
    """Rows and columns ``(m, f)`` of each node's factor record: own and boundary unknowns."""
    return np.column_stack([k * (tree.hi - tree.lo), k * np.diff(tree.bptr)]).astype(np.int64)


class FactorFile:
    """The factor's records, one per node (``L11``, ``L21``, ``y1``) at offsets fixed by the
    tree (``layout``: ``(m, f)`` per node), so that nodes may be written in any order and by
    several threads: in a work file (``os.pwrite`` / ``os.pread``), or in core
    (``path`` None) when the factor fits the memory budget. ``y1`` has ``n_rhs`` columns:
    the right-hand side, then the border's (self-calibration) forward-substituted columns."""

    def __init__(self, path, layout, mode="w", n_rhs=1, arena=None):
        self.path = path
        self.shape = np.asarray(layout, np.int64)
        self.n_rhs = n_rhs
        size = self.record_bytes(self.shape, n_rhs)
        self.offset = np.zeros(len(size), np.int64)
        self.offset[1:] = np.cumsum(size)[:-1]
        self.nbytes = int(size.sum())
        self._at = [(o // 8, m, f) for o, (m, f) in zip(self.offset.tolist(),
                                                        self.shape.tolist())]
        self._buf = None
        self._fd = None
        self.arena = None
        if path is None:
            # in core: one buffer for all records, ``arena`` (the last factorisation's) when
            # large enough, so that an iteration's fronts reuse pages already faulted in
            n = self.nbytes // 8
            if arena is None or arena.size < n:
                arena = _anonymous(n)
            self.arena = arena
            self._buf = arena[:n]
            return
        if mode == "w":
            # the last factorisation's file is overwritten in place, not truncated: every
            # record is written again, and truncating a large file costs the page cache (and
            # a forced write-back on close on ext4)
            self._fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
            if os.fstat(self._fd).st_size != self.nbytes:
                os.ftruncate(self._fd, self.nbytes)
        else:
            self._fd = os.open(path, os.O_RDONLY)
            actual = os.fstat(self._fd).st_size
            if actual != self.nbytes:
                self.close()
                raise OSError(f"{path}: {actual} bytes, expected {self.nbytes} for the tree's "
                              f"factor")

    @staticmethod
    def record_bytes(layout, n_rhs=1):
        """Bytes of each node's record: ``[L11; L21]`` and ``y1`` with ``n_rhs`` columns."""
        m, f = layout[:, 0], layout[:, 1]
        return 8 * ((m + f) * m + m * n_rhs)

    @property
    def in_core(self):
        return self._buf is not None

    def _cols(self, i):
        o, m, f = self._at[i]
        return self._buf[o:o + (m + f) * m].reshape((m + f, m), order="F")

    def _y(self, i):
        y = self.y_slot(i)
        return y if self.n_rhs == 1 else y.reshape((len(y) // self.n_rhs, self.n_rhs),
                                                   order="F")

    def y_slot(self, i):
        """In core, the place of node ``i``'s ``y1`` (flat, m x n_rhs in F order)."""
        o, m, f = self._at[i]
        o += (m + f) * m
        return self._buf[o:o + m * self.n_rhs]

    def own(self, i):
        """In core, the place of node ``i``'s factor columns ((m + f) x m, F order, not
        zeroed): a front's own columns assembled and factored there are written by
        :meth:`write` without a copy. None when the factor is on file."""
        return self._cols(i) if self._buf is not None else None

    def in_place(self, a):
        """Whether ``a`` lies in the factor in core (:meth:`own`'s view of a record)."""
        return self._buf is not None and np.may_share_memory(a, self._buf)

    def write(self, i, col, y1):
        """Node ``i``'s factor columns ``[L11; L21]`` ((m + f) x m, F order, e.g. the first
        columns of its front; the upper triangle of ``L11`` is not used) and ``y1`` (m, or
        m x n_rhs in F order)."""
        if self._buf is not None:
            dst = self._cols(i)
            if col.ctypes.data != dst.ctypes.data or col.strides != dst.strides:
                dst[...] = col   # (not the open front's own columns)
            self._y(i)[...] = y1
            return
        col = np.asfortranarray(col)   # (the front's first columns: contiguous already)
        os.pwrite(self._fd, memoryview(col.reshape(-1, order="F")), int(self.offset[i]))
        os.pwrite(self._fd, memoryview(np.asfortranarray(y1).reshape(-1, order="F")),
                  int(self.offset[i]) + col.nbytes)

    def write_cols(self, i, c0, a, r0=None):
        """A panel of node ``i``'s factor columns: ``a`` ((m + f - c0) x w, F order) is
        rows ``c0 ..`` of columns ``c0 .. c0 + w`` (the rows above are not used); with
        ``r0``, ``a`` is rows ``r0 .. r0 + len(a)`` of them (a tile)."""
        m, f = (int(x) for x in self.shape[i])
        kf, w = m + f, a.shape[1]
        r0 = c0 if r0 is None else r0
        if self._buf is not None:
            self._cols(i)[r0:r0 + a.shape[0], c0:c0 + w] = a
            return
        for c in range(w):
            os.pwrite(self._fd, memoryview(np.ascontiguousarray(a[:, c])),
                      int(self.offset[i]) + 8 * ((c0 + c) * kf + r0))

    def write_y(self, i, y1):
        """Node ``i``'s ``y1`` (after :meth:`write_cols`)."""
        m, f = (int(x) for x in self.shape[i])
        if self._buf is not None:
            self._y(i)[...] = y1
            return
        os.pwrite(self._fd, memoryview(np.asfortranarray(y1).reshape(-1, order="F")),
                  int(self.offset[i]) + 8 * (m + f) * m)

    def read_cols(self, i, c0, c1, r0=0):
        """Rows ``r0 ..`` of columns ``c0 .. c1`` of node ``i``'s ``[L11; L21]`` ((m + f -
        r0) x (c1 - c0), F order): one read, or with ``r0 > 0`` a read a column."""
        if self._buf is not None:
            return self._cols(i)[r0:, c0:c1]
        m, f = (int(x) for x in self.shape[i])
        kf = m + f
        if r0 == 0:
            n = kf * (c1 - c0)
            buf = np.frombuffer(os.pread(self._fd, 8 * n, int(self.offset[i]) + 8 * kf * c0),
                                np.float64)
            if len(buf) != n:
                raise OSError(f"{self.path}: factor record {i} cut short")
            return buf.reshape((kf, c1 - c0), order="F")
        out = np.empty((kf - r0, c1 - c0), order="F")
        for c in range(c0, c1):
            view = memoryview(out[:, c - c0])
            if os.preadv(self._fd, [view], int(self.offset[i]) + 8 * (c * kf + r0)) != \
                    view.nbytes:
                raise OSError(f"{self.path}: factor record {i} cut short")
        return out

    def read_y(self, i):
        """Node ``i``'s ``y1`` (m, or m x n_rhs)."""
        if self._buf is not None:
            return self._y(i)
        m, f = (int(x) for x in self.shape[i])
        nr = self.n_rhs
        buf = np.frombuffer(os.pread(self._fd, 8 * m * nr, int(self.offset[i]) + 8 * (m + f) * m),
                            np.float64)
        if len(buf) != m * nr:
            raise OSError(f"{self.path}: factor record {i} cut short")
        return buf if nr == 1 else buf.reshape((m, nr), order="F")

    def read(self, i):
        """``(col, y1)`` of node ``i`` (as :meth:`write`)."""
        if self._buf is not None:
            return self._cols(i), self._y(i)
        m, f = (int(x) for x in self.shape[i])
        nr = self.n_rhs
        n = (m + f) * m + m * nr
        buf = np.frombuffer(os.pread(self._fd, 8 * n, int(self.offset[i])), np.float64)
        if len(buf) != n:
            raise OSError(f"{self.path}: factor record {i} cut short")
        y1 = buf[(m + f) * m:]
        return (buf[:(m + f) * m].reshape((m + f, m), order="F"),
                y1 if nr == 1 else y1.reshape((m, nr), order="F"))

    def records(self, a, b, out=None):
        """The records of nodes ``a .. b - 1`` (consecutive at their offsets) as one flat
        float64 array and the offset (in doubles) of its first element: the buffer itself in
        core, one read on file (into ``out`` when given, large enough)."""
        o0, o1 = int(self.offset[a]), (int(self.offset[b]) if b < len(self.offset)
                                       else self.nbytes)
        if self._buf is not None:
            return self._buf, 0
        n = (o1 - o0) // 8
        buf = out[:n] if out is not None and len(out) >= n else np.empty(n)
        if os.preadv(self._fd, [memoryview(buf)], o0) != o1 - o0:
            raise OSError(f"{self.path}: factor records {a}..{b - 1} cut short")
        return buf, o0 // 8

    def close(self):
        """Release the factor (in core) or close its file."""
        self._buf = None   # (the arena stays with whoever keeps it for the next one)
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def _anonymous(n):
    """``n`` float64 in fresh anonymous memory, its pages mapped at once where the system
    can (``MAP_POPULATE``): numpy's own large arrays ask for transparent huge pages, whose
    first faults can stall for compaction (0.1 to 0.4 s for 200 MB on a fragmented
    machine), and two threads faulting in ordinary pages contend (0.2 s); populated: 0.06 s."""
    import mmap

    if n == 0:
        return np.empty(0)
    try:
        flags = (mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | getattr(mmap, "MAP_POPULATE", 0))
        return np.frombuffer(mmap.mmap(-1, 8 * n, flags=flags), np.float64)
    except (AttributeError, OSError, ValueError, TypeError):   # (not a POSIX system)
        return np.empty(n)


_MALLOC_TUNED = []


def tune_malloc():
    """Keep freed fronts and update matrices in the process's heap (glibc's ``mallopt``:
    mmap threshold 32 MiB, its maximum; the heap's top trimmed only beyond 64 MiB; at most
    4 arenas, so that the solver's threads share their freed memory), so that the next front
    reuses their pages instead of faulting in fresh zero pages: on the 100 x 100 block this
    halves the factorisation (0.36 s against 0.7 s). Elsewhere than glibc, nothing is done."""
    if _MALLOC_TUNED:
        return
    _MALLOC_TUNED.append(True)
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold, m_arena_max = -1, -3, -8
        libc.mallopt(m_arena_max, 4)
        libc.mallopt(m_mmap_threshold, 32 << 20)
        libc.mallopt(m_trim_threshold, 64 << 20)
    except (OSError, AttributeError):
        pass


def _scalar(idx, k):
    """Scalar indices of the unknowns of stations at places ``idx`` (k each)."""
    return (k * np.asarray(idx, np.int64)[:, None] + np.arange(k)).ravel()


#: Fronts of at least this many rows (m + f) among the top nodes are eliminated by two
#: threads (:meth:`TreeSolver._eliminate_split`) ...
SPLIT_ROWS = 384
#: ... in panels of about this many own columns (the diagonal block's Cholesky on one thread).
SPLIT_PANEL = 512


def _equal_work_column(kids, kf):
    """The front column splitting the children's extend-add (``kids``: ``(u, ub, ix, cm)``)
    into two halves of equal work: column ``c`` of a child's update has ``n - c`` entries
    (its lower triangle)."""
    cols = np.arange(kf + 1)
    work = np.zeros(kf + 1)
    for _, _, ix, _ in kids:
        n = len(ix)
        a = np.searchsorted(ix, cols).astype(np.float64)
        work += a * n - a * (a - 1.0) / 2.0
    return int(np.searchsorted(work, work[-1] / 2.0))


class TreeSolver:
    """The numeric multifrontal factorisation, solve and selected inversion on a tree.

    Use: for each node in post-order, ``A, b = solver.open(i)`` gives the zeroed front (own
    stations, then boundary; scalar order ``k`` parameters a station) as ``A = (own,
    upd)``, its own columns and its update block; the caller adds the node's own
    contributions into their lower triangles and ``b``, then ``solver.eliminate(i, A, b,
    damping)`` (a tiled front: :meth:`eliminate_tiled`). After the last node, ``solve()``
    returns ``delta`` (stations x k) and ``y_norm2`` is ``y'y``. ``inverse(on_node)`` runs
    the selected inversion afterwards.

    Self-calibration (``n_border`` columns ``B`` of the stations against the border's
    unknowns): ``b`` is ``kf x (1 + n_border)``, the right-hand side and then the front's
    rows of ``B``, forward-substituted together (``W = L^-1 B``), so that after the last node
    ``ww = W'W`` and ``wy = W'y`` give the border's Schur complement ``S = C - W'W`` and
    ``t = c - W'y`` (:func:`sapgo.solve.band.border_schur_solve`); ``solve(n, theta)``
    then gives the stations and :meth:`border_x` ``X = M^-1 B`` for the precision pass.
    """

    def __init__(self, tree, npar, factor_path, pivot_tol=PIVOT_TOLERANCE, file=None,
                 n_border=0, tile=None, scratch=None):
        self.tree = tree
        self.k = npar
        # tiled fronts (tile: (front bytes beyond which a front is tiled, panel bytes)):
        # their panels, and updates and inverses' parts larger than a panel, in scratch
        # files of ``scratch``
        self.tile = tile
        self.tiled = (np.zeros(tree.n_nodes, bool) if tile is None else
                      tree.front_bytes(npar) > tile[0])
        self.panel_bytes = None if tile is None else tile[1]
        self.scratch = scratch
        self.pivot_tol = pivot_tol
        self.children = tree.children()
        self._mf = factor_layout(tree, npar).tolist()   # (each node's m, f)
        self.links = tree.links(npar)   # (None for a large tree: each node's worked out)
        self.n_border = n_border
        self.file = file if file is not None else FactorFile(
            factor_path, factor_layout(tree, npar), n_rhs=1 + n_border)
        self.updates = {}
        self.yy = np.zeros(tree.n_nodes)
        # the border's W'W and W'y summed per part of the work (:meth:`set_parts`): each
        # part's nodes in their fixed order, then the parts in theirs, so that the sums do
        # not depend on which thread finished first (a resumed run repeats them bit for bit)
        self.part = np.zeros(tree.n_nodes, np.int64)
        self._ww = np.zeros((1, n_border, n_border))
        self._wy = np.zeros((1, n_border))
        # node -> (seconds from opening the front to its elimination's end, seconds of the
        # elimination) when a dict (benchmarks/distributed.py: the scale-out replay's input)
        self.trace = None
        # a thread pool of at least one thread while the top nodes are eliminated: large
        # fronts then split between it and the caller (:meth:`_eliminate_split`)
        self.pool = None
        tune_malloc()

    def set_parts(self, per, top):
        """The parts of a plan (:func:`sapgo.solve.tree.parallel_plan`): each worker's
        subtrees, then the top nodes; each part run by one thread at a time."""
        for w, ranges in enumerate(per):
            for a, b in ranges:
                self.part[a:b] = w
        self.part[np.asarray(top, np.int64)] = len(per)
        ng = self.n_border
        self._ww = np.zeros((len(per) + 1, ng, ng))
        self._wy = np.zeros((len(per) + 1, ng))

    @property
    def ww(self):
        """``W'W`` of the border (self-calibration) over the nodes eliminated."""
        return self._ww.sum(axis=0)

    @property
    def wy(self):
        """``W'y`` of the border over the nodes eliminated."""
        return self._wy.sum(axis=0)

    @property
    def y_norm2(self):
        """``y'y`` of the forward substitution (``x'b`` of the solution)."""
        return float(self.yy.sum())

    def open(self, i, tiled=False):
        """``(A, b)`` of node ``i``: the zeroed front as ``(own, upd)``, its own columns
        ``[A11; A21]`` (kf x m) and its update block ``A22`` (f x f), both F order and
        zeroed on their block lower triangles (None when ``tiled``: its panels come one at
        a time, :meth:`eliminate_tiled`), and the right-hand side(s)."""
        m, f = self._mf[i]
        a = None
        if not tiled:   # (numpy's allocation: huge pages where large)
            own = self.file.own(i)
            if own is None:
                own = np.empty((m + f, m), order="F")
            upd = np.empty((f, f), order="F")
            _zero_front(own, upd, self.k)
            a = (own, upd)
        return a, (np.zeros(m + f) if not self.n_border else
                   np.zeros((m + f, 1 + self.n_border), order="F"))

    def bounds(self, i):
        """Panel boundaries of node ``i``'s front when tiled
        (:func:`sapgo.solve.tiles.node_bounds`)."""
        t, k = self.tree, self.k
        return node_bounds(k * t.own(i), k * len(t.bnd(i)), k, self.panel_bytes)

    def _big(self, f):
        """Whether an f x f update or inverse's part goes to a scratch file."""
        return self.tile is not None and 8 * f * f > self.panel_bytes

    def _children_updates(self, i):
        """The children's updates for node ``i`` as ``(u, ub, ix, cm)``: ``u`` in core or
        :class:`~sapgo.solve.tiles.Panels`, ``ub`` its right-hand side(s), ``ix`` its
        places in the front, ``cm`` how many of them fall in the own columns."""
        t, k = self.tree, self.k
        out = []
        if self.children[i]:
            if self.links is not None:
                kids = self.links[i][1]
            else:   # (a large tree: worked out node by node)
                fr = t.front(i)
                kids = []
                for c in self.children[i]:
                    if c in self.updates:
                        ix = _scalar(np.searchsorted(fr, t.bnd(c)), k)
                        kids.append((c, ix, int(np.searchsorted(ix, k * t.own(i)))))
            for c, ix, cm in kids:
                if c not in self.updates:  # a child not adjacent to its parent's front
                    continue
                u, ub = self.updates.pop(c)
                out.append((u, ub, ix, cm))
        return out

    def _keep_update(self, i, upd, m, b):
        """Keep node ``i``'s update ``upd`` for its parent: in core, or in a scratch file
        when larger than a panel; with its right-hand side(s) ``b[m:]`` (a view of the
        node's own ``b`` with one right-hand side)."""
        f = upd.shape[0]
        if self._big(f):
            upd = write_dense_panels(upd, update_bounds(m, f, self.k, self.panel_bytes),
                                     self.scratch)
        self.updates[i] = (upd, b[m:] if b.ndim == 1 else b[m:].copy(order="F"))

    def eliminate(self, i, a, b, damping=None):
        """Extend-add the children's updates into front ``a = (own, upd)`` (:meth:`open`)
        and ``b``, add ``damping`` (own scalar unknowns) to the own diagonal, factor the
        own columns (they are the factor's record, kept as they are) and keep the update
        block for the parent: in one kernel call (:func:`_eliminate_front`) for up to two
        children in core, the others' added first; split between two threads
        (:meth:`_eliminate_split`) when :attr:`pool` is set and the front is large."""
        t = self.tree
        own, upd = a
        m, f = own.shape[1], upd.shape[0]
        nr = 1 + self.n_border
        bflat = b.reshape(-1, order="F")
        kids = self._children_updates(i)
        in_place = self.file.in_place(own)   # (factored in its record already)
        y = self.file.y_slot(i) if in_place else np.empty(m * nr)
        if (self.pool is not None and m + f >= SPLIT_ROWS
                and not any(isinstance(u, Panels) for u, _, _, _ in kids)):
            with blas_limits(1):
                fail, yy = self._eliminate_split(own, upd if f else _NO_UPDATE, f, b, bflat,
                                                 nr, kids, damping, y)
        else:
            quick = []
            for u, ub, ix, cm in kids:
                if isinstance(u, Panels):
                    b[ix] += ub
                    for j in range(u.n_panels):
                        b0, b1 = int(u.b[j]), int(u.b[j + 1])
                        s = u.panel(j)
                        if b0 < cm:
                            extend_add(own, 0, s, b0, ix, b0, min(b1, cm))
                        if b1 > cm:
                            extend_add(upd, m, s, b0, ix, max(b0, cm), b1)
                    u.close()
                elif len(quick) == 2:   # (a third child in core: more than bisection gives)
                    _add_child(own, upd if f else _NO_UPDATE, f, bflat, m + f, nr, u,
                               ub.reshape(-1, order="F"), ix, cm)
                else:
                    quick.append((u, ub.reshape(-1, order="F"), ix, cm))
            while len(quick) < 2:
                quick.append((_NO_UPDATE, _NO_X, _NO_IX, 0))
            fail, yy = _eliminate_front(
                FNS, own, upd if f else _NO_UPDATE, f, bflat, nr,
                self.pivot_tol, _NO_X if damping is None else damping, *quick[0], *quick[1], y)
        if fail:
            raise PivotError(int(t.lo[i]) + (fail - 1) // self.k, (fail - 1) % self.k)
        y1 = y if nr == 1 else y.reshape((m, nr), order="F")
        if nr == 1:
            self.yy[i] = yy
        else:
            self.note_y(i, y1)
        if not in_place:
            self.file.write(i, own, y1)
        if f > 0 and t.parent[i] >= 0:
            self._keep_update(i, upd, m, b)

    def _pair(self, fn, first, second):
        """``fn(*first)`` on this thread and ``fn(*second)`` on :attr:`pool`'s at once."""
        job = self.pool.submit(fn, *second)
        try:
            fn(*first)
        finally:
            job.result()

    def _eliminate_split(self, own, upd, f, b, bflat, nr, kids, damping, y):
        """:func:`_eliminate_front`'s work on two threads, each with single-threaded BLAS
        (:func:`_split_part`): the children's updates split by front columns of equal work,
        then a right-looking blocked Cholesky of the own columns in panels of about
        :data:`SPLIT_PANEL` columns: the panel's diagonal block on one thread, the rows
        below it (``dtrsm``) and the trailing lower triangle (``dsyrk``, ``dgemm``) split in
        two. (OpenBLAS's own two threads took 14-60 ms on the 100 x 100 block's two top
        fronts, depending on the phase of the VM: many small calls, each waking the other
        virtual CPU; split, 17-20 ms.)
        Returns ``(fail, y1'y1)`` as :func:`_eliminate_front`."""
        m = own.shape[1]
        kf = m + f
        for u, ub, ix, cm in kids:
            b[ix] += ub
        tol = self.pivot_tol

        def part(op, c0, c1, p0=0, p1=0, child=(_NO_UPDATE, None, _NO_IX, 0), orig=_NO_X):
            u, _, ix, cm = child
            return _split_part(FNS, op, own, upd, f, u, ix, cm, p0, p1, c0, c1, tol, orig,
                               bflat, nr, y)

        if kids:
            def add(c0, c1):
                for child in kids:
                    part(ADD, c0, c1, child=child)
            c = _equal_work_column(kids, kf)
            self._pair(add, (0, c), (c, kf))
        if damping is not None:
            own[np.arange(m), np.arange(m)] += damping
        orig = own.diagonal().copy()
        panels = max(1, int(round(m / SPLIT_PANEL)))
        width = -(-m // panels)
        for p0 in range(0, m, width):
            p1 = min(m, p0 + width)
            fail, _ = part(CHOL, 0, 0, p0, p1, orig=orig)
            if fail:
                return fail, 0.0
            h = (p1 + kf) // 2
            self._pair(part, (TRSM, p1, h, p0, p1), (TRSM, h, kf, p0, p1))
            c = p1 + int(round((kf - p1) * (1.0 - 0.5 ** 0.5)))   # (equal halves of work)
            self._pair(part, (UPDATE, p1, c, p0, p1), (UPDATE, c, kf, p0, p1))
        return part(FORWARD, 0, 0)

    def _forward_done(self, i, b, m):
        """``y1`` of node ``i`` from its forward-substituted ``b``; ``y'y`` and the
        border's ``W'W``, ``W'y`` accumulated."""
        y1 = b[:m].copy(order="F")
        self.note_y(i, y1)
        return y1

    def note_y(self, i, y1):
        """Node ``i``'s ``y1`` (m, or m x n_rhs) into ``y'y`` and the border's sums."""
        if self.n_border:
            w = y1[:, 1:]
            self.yy[i] = float(y1[:, 0] @ y1[:, 0])
            ww, wy = w.T @ w, w.T @ y1[:, 0]
            self._ww[self.part[i]] += ww
            self._wy[self.part[i]] += wy
        else:
            self.yy[i] = float(y1 @ y1)
        return y1

    def eliminate_tiled(self, i, assemble, b, damping=None):
        """Node ``i``'s tiled front (:mod:`sapgo.solve.tiles`), a panel at a time:
        ``assemble(c0, c1, a)`` adds the node's own contributions (points, priors) to the
        panel ``a`` (rows ``c0 ..``, columns ``c0 .. c1``; ``c0 = 0`` the first, where the
        border's terms go); then the children's updates, ``damping``, the earlier own
        panels' updates; own panels are factored into the factor file, boundary panels
        become the update for the parent (a scratch file). ``b`` as for
        :meth:`eliminate`, complete but for the own points' terms that ``assemble`` adds."""
        t, k = self.tree, self.k
        m = k * t.own(i)
        kf = k * (t.own(i) + len(t.bnd(i)))
        bounds = self.bounds(i)
        n_own = int(np.searchsorted(bounds, m))
        kids = self._children_updates(i)
        for _, ub, ix, _ in kids:
            b[ix] += ub
        nr = 1 + self.n_border
        b2 = b if b.ndim == 2 else b[:, None]
        bflat = b2.reshape(-1, order="F")
        assert np.shares_memory(bflat, b)
        upd = (Panels(self.scratch, kf - m, bounds[n_own:] - m)
               if kf > m and t.parent[i] >= 0 else None)
        try:
            for j in range(len(bounds) - 1):
                c0, c1 = int(bounds[j]), int(bounds[j + 1])
                w = c1 - c0
                a = np.zeros((kf - c0, w), order="F")
                assemble(c0, c1, a)
                for u, _, ix, _ in kids:
                    ca, cb = (int(x) for x in np.searchsorted(ix, [c0, c1]))
                    if ca < cb:
                        if isinstance(u, Panels):
                            extend_add(a, c0, u.cols(ca, cb), ca, ix, ca, cb)
                        else:
                            extend_add(a, c0, u, 0, ix, ca, cb)
                if damping is not None and c0 < m:
                    a[np.arange(w), np.arange(w)] += damping[c0:c1]
                orig = a[np.arange(w), np.arange(w)].copy()
                aflat = a.reshape(-1, order="F")
                for q in range(min(j, n_own)):   # (the rows from c0 of earlier panels)
                    q0, q1 = int(bounds[q]), int(bounds[q + 1])
                    lq = np.asfortranarray(self.file.read_cols(i, q0, q1, c0))
                    _left_update(FNS, aflat, kf - c0, kf - c0, w, lq.reshape(-1, order="F"),
                                 kf - c0, 0, q1 - q0)
                    del lq
                if j < n_own:
                    fail = _factor_panel(FNS, aflat, kf - c0, w, bflat, kf, c0, nr,
                                         self.pivot_tol, orig)
                    if fail:
                        raise PivotError(int(t.lo[i]) + (c0 + fail - 1) // k,
                                         (c0 + fail - 1) % k)
                    self.file.write_cols(i, c0, a)
                elif upd is not None:
                    upd.write(j - n_own, a)
                del a, aflat
        except BaseException:
            if upd is not None:
                upd.close()
            raise
        finally:
            for u, _, _, _ in kids:
                if isinstance(u, Panels):
                    u.close()
        y1 = self._forward_done(i, b, m)
        self.file.write_y(i, y1)
        if upd is not None:
            self.updates[i] = (upd, b[m:].copy(order="F"))

    def _back_tiled(self, i, r, xb):
        """Back substitution through tiled node ``i``'s factor a panel at a time: its own
        unknowns (m x c) from ``r`` (m x c) and the boundary's solution ``xb`` (f x c)."""
        m = r.shape[0]
        bounds = self.bounds(i)
        x = np.empty_like(r)
        for q in range(int(np.searchsorted(bounds, m)) - 1, -1, -1):
            q0, q1 = int(bounds[q]), int(bounds[q + 1])
            lq = self.file.read_cols(i, q0, q1, q0)   # (rows from q0)
            w = q1 - q0
            rq = r[q0:q1] - lq[w:m - q0].T @ x[q1:m] - lq[m - q0:].T @ xb
            x[q0:q1] = scipy.linalg.solve_triangular(lq[:w], rq, lower=True, trans="T",
                                                     check_finite=False)
        return x

    def solve(self, n_stations, theta=None, plan=None):
        """``delta`` (n_stations x k; stations outside the tree 0) by back substitution
        down the tree (with a border: of ``y - W theta``). ``plan``: ``(per_worker, top)``
        of :func:`sapgo.solve.tree.parallel_plan`: the top nodes first, then the workers'
        subtrees side by side (each writes its own stations and reads its ancestors')."""
        t, k = self.tree, self.k
        x = np.zeros(k * n_stations)
        if plan is None or len(plan[0]) < 2:
            self.back_substitute(x, range(t.n_nodes - 1, -1, -1), theta)
            return x.reshape(n_stations, k)
        from concurrent.futures import ThreadPoolExecutor

        from ..blas import blas_limits

        per, top = plan
        self.back_substitute(x, sorted(top, reverse=True), theta)
        with blas_limits(1), ThreadPoolExecutor(len(per)) as pool:
            for job in [pool.submit(self.back_substitute, x,
                                    sorted((i for a, b in ranges for i in range(a, b)),
                                           reverse=True), theta) for ranges in per]:
                job.result()
        return x.reshape(n_stations, k)

    def back_substitute(self, x, nodes, theta=None):
        """``x`` (k n_stations) of the stations of ``nodes`` (in descending order: a node
        after its ancestors, whose stations ``x`` holds already)."""
        t, k = self.tree, self.k
        size = self.file.record_bytes(self.file.shape, self.file.n_rhs)
        th = np.zeros(0) if theta is None else np.ascontiguousarray(theta, dtype=np.float64)
        nodes = list(nodes)
        out = None if self.file.in_core else np.empty(BACK_BYTES // 8)
        j = 0
        while j < len(nodes):
            i = nodes[j]
            if self.tiled[i]:
                y1 = self.file.read_y(i)
                r = y1 if not self.n_border else y1[:, 0] - y1[:, 1:] @ theta
                x[k * t.lo[i]:k * t.hi[i]] = self._back_tiled(
                    i, r[:, None], x[_scalar(t.bnd(i), k)][:, None])[:, 0]
                j += 1
                continue
            # a run of consecutive nodes i, i - 1, ..: their records in one piece
            e, total = j + 1, size[i]
            while (e < len(nodes) and nodes[e] == nodes[e - 1] - 1
                   and not self.tiled[nodes[e]] and total + size[nodes[e]] <= BACK_BYTES):
                total += size[nodes[e]]
                e += 1
            buf, base = self.file.records(nodes[e - 1], i + 1, out)
            _back_nodes(FNS, buf, base, self.file.offset // 8, self.file.shape,
                        self.file.n_rhs, th, t.lo, t.bptr, t.boundary, k, x, i,
                        nodes[e - 1])
            j = e

    def border_x(self, n_stations):
        """``X = M^-1 B`` (n_stations x k x n_border): the border's columns substituted
        back down the tree from ``W`` (the stations' share of the border's covariances,
        ``cov(delta) = M^-1 + X S^-1 X'``)."""
        t, k, ng = self.tree, self.k, self.n_border
        x = np.zeros((k * n_stations, ng))
        for i in range(t.n_nodes - 1, -1, -1):
            if self.tiled[i]:
                x[k * t.lo[i]:k * t.hi[i]] = self._back_tiled(
                    i, self.file.read_y(i)[:, 1:], x[_scalar(t.bnd(i), k)])
                continue
            col, y1 = self.file.read(i)
            m = col.shape[1]
            r = y1[:, 1:]
            if col.shape[0] > m:
                r = r - col[m:].T @ x[_scalar(t.bnd(i), k)]
            x[k * t.lo[i]:k * t.hi[i]] = scipy.linalg.solve_triangular(
                col[:m], r, lower=True, trans="T", check_finite=False)
        return x.reshape(n_stations, k, ng)

    def solve_columns(self, r):
        """``M^-1 R`` for the columns ``R`` (k n_stations x c; stations outside the tree
        0) with the factor in the file: forward substitution up the tree (post-order), back
        substitution down it (a tiled front a panel at a time)."""
        t, k = self.tree, self.k
        y = np.array(r, dtype=np.float64, copy=True)
        for i in range(t.n_nodes):
            own = slice(k * int(t.lo[i]), k * int(t.hi[i]))
            bnd = _scalar(t.bnd(i), k)
            m = own.stop - own.start
            if self.tiled[i]:
                bounds = self.bounds(i)
                for q in range(len(bounds) - 1):
                    q0, q1 = int(bounds[q]), int(bounds[q + 1])
                    if q0 >= m:
                        break
                    lq = self.file.read_cols(i, q0, q1, q0)   # (rows from q0)
                    w = q1 - q0
                    yq = scipy.linalg.solve_triangular(lq[:w], y[own][q0:q1], lower=True,
                                                       check_finite=False)
                    y[own.start + q0:own.start + q1] = yq
                    y[own.start + q1:own.stop] -= lq[w:m - q0] @ yq
                    if len(bnd):
                        y[bnd] -= lq[m - q0:] @ yq
                continue
            col, _ = self.file.read(i)
            yo = scipy.linalg.solve_triangular(col[:m], y[own], lower=True, check_finite=False)
            y[own] = yo
            if col.shape[0] > m:
                y[bnd] -= col[m:] @ yo
        x = np.zeros_like(y)
        for i in range(t.n_nodes - 1, -1, -1):
            own = slice(k * int(t.lo[i]), k * int(t.hi[i]))
            bnd = _scalar(t.bnd(i), k)
            if self.tiled[i]:
                x[own] = self._back_tiled(i, y[own], x[bnd])
                continue
            col, _ = self.file.read(i)
            m = col.shape[1]
            rr = y[own]
            if col.shape[0] > m:
                rr = rr - col[m:].T @ x[bnd]
            x[own] = scipy.linalg.solve_triangular(col[:m], rr, lower=True, trans="T",
                                                   check_finite=False)
        return x

    def inverse(self, on_node, nodes=None, held=None):
        """Selected inversion top-down: ``on_node(i, z)`` with ``z`` (kf x kf, F order,
        symmetric) the inverse of the reduced matrix over node ``i``'s front.

        ``nodes``: the nodes to visit (default all), visited in reverse post-order, so that
        a parent comes before its children; ``held``: for the nodes whose parent is not
        visited, the inverse over their boundary (a dict by node, read only) -- the way the
        subtrees of :func:`sapgo.solve.tree.parallel_plan` are inverted by several threads.
        Returns the inverses over the boundaries of the children not visited. A front's
        inverse goes as soon as it has given each child its part (the inverse over the
        child's boundary), so that in core are the front at hand and the parts of the
        children still to visit."""
        t, k = self.tree, self.k
        nodes = range(t.n_nodes) if nodes is None else nodes
        inside = set(nodes)
        parts = {}   # the inverses over the boundaries of the children still to visit
        keep = {}
        for i in sorted(inside, reverse=True):
            z22 = parts.pop(i, None)
            if z22 is None:
                z22 = held[i] if len(t.bnd(i)) else np.zeros((0, 0), order="F")
            if self.tiled[i]:
                z = invert_tiled(lambda c0, c1, i=i: self.file.read_cols(i, c0, c1, c0),
                                 k * t.own(i), k * (t.own(i) + len(t.bnd(i))),
                                 self.bounds(i), z22, self.scratch)
            else:
                if isinstance(z22, Panels):
                    z22 = z22.dense()
                col, _ = self.file.read(i)
                z = _front_inverse(col, z22, k)
                del col
            if isinstance(z22, Panels) and z22 is not (held or {}).get(i):
                z22.close()
            del z22
            try:
                on_node(i, z)
                fr = t.front(i)
                for c in self.children[i]:   # each child's part now: z goes
                    if len(t.bnd(c)):
                        idx = _scalar(np.searchsorted(fr, t.bnd(c)), k)
                        (parts if c in inside else keep)[c] = self._part(z, idx, c)
            finally:
                if isinstance(z, Panels):
                    z.close()
            del z
        return keep

    def _part(self, z, idx, c):
        """Child ``c``'s part of the inverse ``z`` over its boundary ``idx``: in core, or in
        a scratch file laid out as the child's boundary panels when larger than a panel."""
        t, k = self.tree, self.k
        if not self._big(len(idx)):
            return z.gather(idx) if isinstance(z, Panels) else _gather(z, idx)
        ub = update_bounds(k * t.own(c), len(idx), k, self.panel_bytes)
        if isinstance(z, Panels):
            return z.gather_panels(idx, ub, self.scratch)
        return write_dense_panels(_gather(z, idx), ub, self.scratch)

    def close(self):
        self.file.close()


def _front_inverse(col, z22, k):
    """The inverse over a front from its factor columns and the inverse over its boundary
    ``z22`` (f x f, F order): Takahashi's recurrences on the supernode."""
    m = col.shape[1]
    f = col.shape[0] - m
    z = np.empty((m + f, m + f), order="F")   # (every entry is written)
    _inverse_front(FNS, np.asfortranarray(col).reshape(-1, order="F"), m, f,
                   np.asfortranarray(z22).reshape(-1, order="F"), z.reshape(-1, order="F"))
    return z


@njit(cache=True, nogil=True)
def _factor_front(fns, a, kf, m, a22, b, nr, tol):
    """Partial Cholesky of a front in place (``a`` the F-order data of its own columns,
    kf x m, ``a22`` of its update block, f x f): ``L11 = chol(A11)``, ``L21 = A21
    L11'^-1``, ``A22 -= L21 L21'``, ``b1 = L11^-1 b1``, ``b2 -= L21 b1`` (``b`` kf x nr, F
    order: the right-hand side and a border's columns). Returns 0, or 1 + the first own
    column whose pivot is at or below ``tol`` times its diagonal before the factorisation
    (or where dpotrf failed)."""
    f = kf - m
    orig = np.empty(m)
    for j in range(m):
        orig[j] = a[j * kf + j]
    fail = chol_columns(fns, a, kf, kf, m, tol, orig)
    if fail:
        return fail
    if f > 0:
        syrk(fns.dsyrk, L, N, f, m, -1.0, a[m:], kf, 1.0, a22, f)
    _forward_front(fns, a, kf, m, b, nr)
    return 0


@njit(cache=True, nogil=True)
def _forward_front(fns, a, kf, m, b, nr):
    """The forward substitution through a factored front (``a``: its own columns, kf x m,
    flat F order): ``b1 = L11^-1 b1``, ``b2 -= L21 b1`` (``b`` kf x nr, flat F order)."""
    f = kf - m
    if nr == 1:
        trsv(fns.dtrsv, L, N, N, m, a, kf, b)
        if f > 0:
            gemv(fns.dgemv, N, f, m, -1.0, a[m:], kf, b, 1.0, b[m:])
    else:
        trsm(fns.dtrsm, L, L, N, N, m, nr, 1.0, a, kf, b, kf)
        if f > 0:
            gemm(fns.dgemm, N, N, f, nr, m, -1.0, a[m:], kf, b, kf, 1.0, b[m:], kf)


@njit(cache=True, nogil=True)
def _take_y(b, kf, m, nr, y):
    """``y1`` (the first m rows of ``b``, kf x nr flat F order) copied into ``y`` (m x nr
    flat); returns ``y1'y1`` of the first column."""
    for c in range(nr):
        for j in range(m):
            y[c * m + j] = b[c * kf + j]
    yy = 0.0
    for j in range(m):
        yy += b[j] * b[j]
    return yy


#: A front's update block when it has none (a root's): F order, as the others, so that
#: :func:`_eliminate_front` is compiled for one type.
_NO_UPDATE = np.zeros((2, 2), order="F")
_NO_IX = np.zeros(0, np.int64)
_NO_X = np.zeros(0)


@njit(cache=True, nogil=True)
def _add_child(own, upd, f, b, kf, nr, u, ub, ix, cm):
    """A child's update ``u`` and right-hand side(s) ``ub`` (flat, len(ix) x nr, F order)
    added into the front (``own``, ``upd`` with ``f`` rows) and ``b`` (flat, kf x nr)."""
    n = ix.shape[0]
    for c in range(nr):
        for r in range(n):
            b[c * kf + ix[r]] += ub[c * n + r]
    extend_add(own, 0, u, 0, ix, 0, cm)
    if f > 0:
        extend_add(upd, kf - f, u, 0, ix, cm, n)


@njit(cache=True, nogil=True)
def _eliminate_front(fns, own, upd, f, b, nr, tol, damping, u1, ub1, ix1, cm1, u2, ub2, ix2,
                     cm2, y):
    """A front's elimination in one call (:meth:`TreeSolver.eliminate`): up to two
    children's updates added (``ix`` empty: none), ``damping`` on the own diagonal (empty:
    none), the partial Cholesky (:func:`_factor_front`) and ``y1`` (m x nr, flat, F order)
    copied into ``y``. ``own`` (kf x m) and ``upd`` (f x f; :data:`_NO_UPDATE` for none)
    F order, ``b`` flat (kf x nr). Returns ``(fail, y1'y1)`` of the first column."""
    kf, m = own.shape
    if ix1.shape[0]:
        _add_child(own, upd, f, b, kf, nr, u1, ub1, ix1, cm1)
    if ix2.shape[0]:
        _add_child(own, upd, f, b, kf, nr, u2, ub2, ix2, cm2)
    for j in range(damping.shape[0]):
        own[j, j] += damping[j]
    a22 = upd.T.reshape(upd.size) if f > 0 else np.empty(0)
    fail = _factor_front(fns, own.T.reshape(kf * m), kf, m, a22, b, nr, tol)
    yy = 0.0
    if fail == 0:
        yy = _take_y(b, kf, m, nr, y)
    return fail, yy


#: The phases of :func:`_split_part`.
ADD, CHOL, TRSM, UPDATE, FORWARD = range(5)


@njit(cache=True, nogil=True)
def _split_part(fns, op, own, upd, f, u, ix, cm, p0, p1, c0, c1, tol, orig, b, nr, y):
    """One thread's part of a phase of a top node's elimination on two threads
    (:meth:`TreeSolver._eliminate_split`; one kernel for all the phases, loaded once).
    ``own`` (kf x m) and ``upd`` (f x f) F order as :func:`_eliminate_front`'s. ``op``:

    - ``ADD``: the front's columns ``c0 .. c1`` of a child's update ``u`` (its places
      ``ix``, ``cm`` of them in the own columns): the child's columns that land there (a run
      of them, ``ix`` ascending), so that threads given apart column ranges never add into
      the same place;
    - ``CHOL``: the Cholesky factor of the panel ``p0 .. p1``'s diagonal block (updated by
      the panels before it) in place, pivots tested against ``orig`` as
      :func:`_factor_front`'s; returns ``(0 or 1 + the failing own column, 0)``;
    - ``TRSM``: rows ``c0 .. c1`` (below the panel) of the panel's columns,
      ``L_r = A_r L_pp'^-1``;
    - ``UPDATE``: the front's columns ``c0 .. c1`` (right of the panel; the own ones in
      ``own``, the boundary's in ``upd``) less the panel's ``L L'``: each range's diagonal
      block by ``dsyrk``, the rows below it by ``dgemm``;
    - ``FORWARD``: the forward substitution through the factored own columns
      (:func:`_forward_front`, ``b`` flat kf x nr) and ``y1`` into ``y``; returns
      ``(0, y1'y1)``.
    """
    kf, m = own.shape
    a = own.T.reshape(kf * m)
    if op == ADD:
        lo = np.searchsorted(ix, c0)
        hi = np.searchsorted(ix, c1)
        e = min(hi, cm)
        if lo < e:
            extend_add(own, 0, u, 0, ix, lo, e)
        s = max(lo, cm)
        if f > 0 and s < hi:
            extend_add(upd, m, u, 0, ix, s, hi)
    elif op == CHOL:
        w = p1 - p0
        fail = chol_columns(fns, a[p0 * kf + p0:], kf, w, w, tol, orig[p0:p1])
        return (fail + p0 if fail else 0), 0.0
    elif op == TRSM:
        if c1 > c0:
            trsm(fns.dtrsm, R, L, T, N, c1 - c0, p1 - p0, 1.0, a[p0 * kf + p0:], kf,
                 a[p0 * kf + c0:], kf)
    elif op == UPDATE:
        w = p1 - p0
        lp = p0 * kf   # (the panel's column p0, row 0)
        e = min(c1, m)
        if c0 < e:
            syrk(fns.dsyrk, L, N, e - c0, w, -1.0, a[lp + c0:], kf, 1.0, a[c0 * kf + c0:], kf)
            if kf > e:
                gemm(fns.dgemm, N, T, kf - e, e - c0, w, -1.0, a[lp + e:], kf, a[lp + c0:],
                     kf, 1.0, a[c0 * kf + e:], kf)
        s = max(c0, m)
        if s < c1:
            a22 = upd.T.reshape(f * f)
            q = s - m
            syrk(fns.dsyrk, L, N, c1 - s, w, -1.0, a[lp + s:], kf, 1.0, a22[q * f + q:], f)
            if kf > c1:
                gemm(fns.dgemm, N, T, kf - c1, c1 - s, w, -1.0, a[lp + c1:], kf, a[lp + s:],
                     kf, 1.0, a22[q * f + c1 - m:], f)
    elif op == FORWARD:
        _forward_front(fns, a, kf, m, b, nr)
        return 0, _take_y(b, kf, m, nr, y)
    return 0, 0.0


#: Bytes of factor records read at once by the back substitution (from the factor file).
BACK_BYTES = 32 << 20


@njit(cache=True, nogil=True)
def _back_nodes(fns, buf, base, offset, shape, nr, theta, lo, bptr, boundary, k, x, hi_node,
                lo_node):
    """Back substitution of nodes ``hi_node`` down to ``lo_node`` (their records in ``buf``,
    which starts at double ``base`` of the factor): ``x_own = L11'^-1 (r - L21' x_bnd)``,
    ``r = y1[:, 0] - y1[:, 1:] theta`` (``theta`` the border's solution, or empty)."""
    for i in range(hi_node, lo_node - 1, -1):
        m, f = shape[i, 0], shape[i, 1]
        kf = m + f
        o = offset[i] - base
        col = buf[o:o + kf * m]
        yo = o + kf * m
        y = buf[yo:yo + m].copy()
        for g in range(theta.shape[0]):
            for j in range(m):
                y[j] -= buf[yo + (g + 1) * m + j] * theta[g]
        if f > 0:
            xb = np.empty(f)
            b0 = bptr[i]
            for s in range(f // k):
                st = boundary[b0 + s]
                for c in range(k):
                    xb[k * s + c] = x[k * st + c]
            gemv(fns.dgemv, T, f, m, -1.0, col[m:], kf, xb, 1.0, y)
        trsv(fns.dtrsv, L, T, N, m, col, kf, y)
        x0 = k * lo[i]
        for j in range(m):
            x[x0 + j] = y[j]


#: Columns a block of the lower half of ``X' Z21`` in :func:`_inverse_front`.
INVERSE_BLOCK = 96


@njit(cache=True, nogil=True)
def _inverse_front(fns, col, m, f, z22, z):
    """``z`` ((m+f) x (m+f), F order) <- the inverse over a front from its factor columns
    ``col`` ([L11; L21], (m+f) x m, F order) and ``Z22`` (f x f, F order): ``X = L21
    L11^-1``, ``Z21 = -Z22 X``, ``Z11 = L11^-T L11^-1 - X' Z21`` (``dtrtri`` and ``dlauum``,
    as ``dpotri``; the symmetric ``X' Z21`` by blocks of columns, its lower half only)."""
    kf = m + f
    for c in range(m):
        for r in range(c, m):
            z[c * kf + r] = col[c * kf + r]
    trtri(fns.dtrtri, L, N, m, z, kf)
    if f > 0:
        x = np.empty(f * m)
        for c in range(m):
            for r in range(f):
                x[c * f + r] = col[c * kf + m + r]
        trmm(fns.dtrmm, R, L, N, N, f, m, 1.0, z, kf, x, f)
    lauum(fns.dlauum, L, m, z, kf)
    if f > 0:
        gemm(fns.dgemm, N, N, f, m, f, -1.0, z22, f, x, f, 0.0, z[m:], kf)
        for c0 in range(0, m, INVERSE_BLOCK):
            w = min(INVERSE_BLOCK, m - c0)
            gemm(fns.dgemm, T, N, m - c0, w, f, -1.0, x[c0 * f:], f, z[c0 * kf + m:], kf,
                 1.0, z[c0 * kf + c0:], kf)
        for c in range(f):
            for r in range(c, f):
                z[(m + c) * kf + m + r] = z22[c * f + r]
    _mirror_lower(z, kf)


@njit(cache=True, nogil=True)
def _mirror_lower(z, n):
    """The upper triangle of an n x n F-order matrix (flat) from its lower one, by tiles
    (the strided writes stay in cache)."""
    b = 32
    for cb in range(0, n, b):
        for rb in range(cb, n, b):
            for c in range(cb, min(cb + b, n)):
                for r in range(max(rb, c + 1), min(rb + b, n)):
                    z[r * n + c] = z[c * n + r]


@njit(cache=True, nogil=True)
def _gather(zp, ix):
    n = ix.shape[0]
    out = np.empty((n, n)).T   # F order
    for c in range(n):
        jc = ix[c]
        for r in range(n):
            out[r, c] = zp[ix[r], jc]
    return out


@njit(cache=True, nogil=True)
def _zero_front(own, upd, k):
    """:func:`_zero_block_lower` of a front's own columns and its update block."""
    _zero_block_lower(own, k)
    _zero_block_lower(upd, k)


@njit(cache=True, nogil=True)
def _zero_block_lower(a, k):
    """Zero the block lower triangle (blocks k x k) of an F-order matrix (a front's own
    columns, or its update block): all that a front uses, its lower triangle and its
    stations' diagonal blocks in full; the rest is never read (half the memory traffic of
    zeroing it all)."""
    for c in range(a.shape[1]):
        a[c - c % k:, c] = 0.0
