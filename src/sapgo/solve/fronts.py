"""Multifrontal Cholesky of the reduced normal equations on the partition tree (DESIGN 5b).

Node ``i`` of a :class:`~sapgo.solve.partition.Tree` has a dense *front* over its own
stations (``m = k |own|`` unknowns, ``k`` parameters a station) followed by its boundary
(``f = k |boundary|``). In post-order, the front is assembled from

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

``L11``, ``L21`` and ``y1`` go to the factor file (one record per node, written in
post-order); the back substitution reads them top-down, ``x1 = L11'^-1 (y1 - L21' x2)``.

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
from scipy.linalg import blas, lapack

from ..bandsolve import PIVOT_TOLERANCE, PivotError
from ..normals import (BAD_LAYOUT, BEHIND_CAMERA, OK, SINGULAR_POINT, _chol3, _point_system,
                       _solve3, _workspace)


@njit(cache=True, nogil=True)
def build_front(j0, j1, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start, pt_nobs,
                pt_active, obs_station, obs_xy, obs_sigma, obs_active, eo, cam_of_station, cams,
                ctrl_mask, front, rhs, max_rays, npar, lam=0.0, behind_ok=False):
    """Add points ``j0 .. j1-1`` of a chunk into a dense front.

    ``obs_station`` holds each observation's station as its place in the front (-1: not in
    the front), ``eo`` and ``cam_of_station`` are indexed the same way; ``front``
    (kf x kf, lower triangle and the diagonal blocks filled) and ``rhs`` (kf) receive the
    reduced normals ``M[s,t] -= Nbar_s Ndd^-1 Nbar_t'``, ``p A'A`` and ``d``. Returns
    ``(status, point)``: OK, or SINGULAR_POINT / BEHIND_CAMERA / BAD_LAYOUT (a station of
    the point outside the front) with the point."""
    nbar, a_all, l_all, w_all, st_all, nn, cc, lo, xyz, b_all = _workspace(max_rays, npar)
    g = np.empty((max_rays, npar, 3))
    h = np.empty(3)
    col = np.empty(3)
    tmp = np.empty(3)
    for j in range(j0, j1):
        if pt_active[j] != 0:
            continue
        for i in range(pt_start[j], pt_start[j] + pt_nobs[j]):
            if obs_active[i] and obs_station[i] < 0:
                return BAD_LAYOUT, j
        k = _point_system(j, pt_xyz, pt_kind, pt_ctrl, pt_csig, pt_rot, pt_start, pt_nobs,
                          obs_station, obs_xy, obs_sigma, obs_active, eo, cam_of_station,
                          cams, ctrl_mask, xyz, nbar, a_all, l_all, w_all,
                          st_all, nn, cc, b_all, lam, behind_ok)
        if k < 0:
            return BEHIND_CAMERA, j
        if not _chol3(nn, lo):
            return SINGULAR_POINT, j
        _solve3(lo, cc, h)
        for q in range(k):
            s0 = npar * st_all[q]
            p = w_all[q]
            a = a_all[q]
            for u in range(npar):
                for v in range(npar):
                    front[s0 + u, s0 + v] += p * (a[0, u] * a[0, v] + a[1, u] * a[1, v])
                s = p * (a[0, u] * l_all[q, 0] + a[1, u] * l_all[q, 1])
                for c in range(3):
                    s -= nbar[q, u, c] * h[c]
                rhs[s0 + u] += s
            for u in range(npar):
                for c in range(3):
                    col[c] = nbar[q, u, c]
                _solve3(lo, col, tmp)
                for c in range(3):
                    g[q, u, c] = tmp[c]
        # Schur complement into the lower triangle: rays are in ascending station order, so
        # the later station's rows and the earlier's columns (a diagonal block in full;
        # two rays of one station add X and X')
        for q in range(k):
            sq = npar * st_all[q]
            for t in range(q, k):
                st = npar * st_all[t]
                for u in range(npar):
                    for v in range(npar):
                        x = 0.0
                        for c in range(3):
                            x += g[q, u, c] * nbar[t, v, c]
                        if st != sq:
                            front[st + v, sq + u] -= x
                        else:
                            front[sq + u, sq + v] -= x
                            if t != q:
                                front[sq + v, sq + u] -= x
    return OK, -1


class FactorFile:
    """The factor's records, one per node (``L11``, ``L21``, ``y1``), in a work file written
    in post-order and read back in any order (``os.pwrite`` / ``os.pread``)."""

    def __init__(self, path, n_nodes, mode="w", layout=None):
        self.path = path
        flags = os.O_RDWR | os.O_CREAT | os.O_TRUNC if mode == "w" else os.O_RDONLY
        self._fd = os.open(path, flags, 0o644)
        self.offset = np.zeros(n_nodes, np.int64)
        self.shape = np.zeros((n_nodes, 2), np.int64)
        self.end = 0
        self.nbytes = 0
        if layout is not None:  # an existing file written in post-order
            self.shape[:] = layout
            m, f = layout[:, 0], layout[:, 1]
            size = 8 * (m * m + f * m + m)
            self.offset[1:] = np.cumsum(size)[:-1]
            self.end = self.nbytes = int(size.sum())
            if os.fstat(self._fd).st_size != self.end:
                actual = os.fstat(self._fd).st_size
                self.close()
                raise OSError(f"{path}: {actual} bytes, expected {self.end} for the tree's "
                              f"factor")

    def write(self, i, l11, l21, y1):
        m, f = l11.shape[0], l21.shape[0]
        self.offset[i] = self.end
        self.shape[i] = (m, f)
        data = [np.ascontiguousarray(x, dtype=np.float64).ravel(order="F") for x in
                (l11, l21, y1)]
        buf = np.concatenate(data)
        os.pwrite(self._fd, buf.tobytes(), self.end)
        self.end += buf.nbytes
        self.nbytes = self.end

    def read(self, i):
        m, f = (int(x) for x in self.shape[i])
        n = m * m + f * m + m
        buf = np.frombuffer(os.pread(self._fd, 8 * n, int(self.offset[i])), np.float64)
        if len(buf) != n:
            raise OSError(f"{self.path}: factor record {i} cut short")
        l11 = buf[:m * m].reshape((m, m), order="F")
        l21 = buf[m * m:m * m + f * m].reshape((f, m), order="F")
        y1 = buf[m * m + f * m:]
        return l11, l21, y1

    def close(self):
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def _scalar(idx, k):
    """Scalar indices of the unknowns of stations at places ``idx`` (k each)."""
    return (k * np.asarray(idx, np.int64)[:, None] + np.arange(k)).ravel()


class TreeSolver:
    """The numeric multifrontal factorisation, solve and selected inversion on a tree.

    Use: for each node in post-order, ``A, b = solver.open(i)`` gives the zeroed front (own
    stations, then boundary; scalar order ``k`` parameters a station), the caller adds the
    node's own contributions into its lower triangle and ``b``, then ``solver.eliminate(i,
    A, b, damping)``. After the last node, ``solve()`` returns ``delta`` (stations x k) and
    ``y_norm2`` is ``y'y``. ``inverse(on_node)`` runs the selected inversion afterwards.
    """

    def __init__(self, tree, npar, factor_path, pivot_tol=PIVOT_TOLERANCE):
        self.tree = tree
        self.k = npar
        self.pivot_tol = pivot_tol
        self.children = tree.children()
        self.file = FactorFile(factor_path, tree.n_nodes)
        self.updates = {}
        self.y_norm2 = 0.0
        self.factored = 0

    @classmethod
    def reopen(cls, tree, npar, factor_path):
        """The solver of a factor file written by an earlier factorisation of ``tree``
        (for :meth:`inverse` and :meth:`solve`)."""
        self = cls.__new__(cls)
        self.tree, self.k, self.pivot_tol = tree, npar, PIVOT_TOLERANCE
        self.children = tree.children()
        layout = np.column_stack([npar * (tree.hi - tree.lo), npar * np.diff(tree.bptr)])
        self.file = FactorFile(factor_path, tree.n_nodes, "r", layout.astype(np.int64))
        self.updates, self.y_norm2, self.factored = {}, 0.0, tree.n_nodes
        return self

    def open(self, i):
        t = self.tree
        nf = t.own(i) + len(t.bnd(i))
        kf = self.k * nf
        return np.zeros((kf, kf), order="F"), np.zeros(kf)

    def eliminate(self, i, a, b, damping=None):
        """Extend-add the children's updates into front ``a`` (F-order, lower triangle) and
        ``b``, add ``damping`` (own scalar unknowns) to the own diagonal, factor the own
        part and keep the update for the parent."""
        t, k = self.tree, self.k
        m = k * t.own(i)
        if self.children[i]:
            fr = t.front(i)
            for c in self.children[i]:
                if c not in self.updates:  # a child not adjacent to its parent's front
                    continue
                u, ub = self.updates.pop(c)
                ix = _scalar(np.searchsorted(fr, t.bnd(c)), k)
                _extend_add(a, b, u, ub, ix)
        if damping is not None:
            idx = np.arange(m)
            a[idx, idx] += damping
        orig = np.diagonal(a)[:m].copy()
        a11 = a[:m, :m]
        l11, info = lapack.dpotrf(a11, lower=1, clean=1, overwrite_a=0)
        bad = -1
        if info > 0:
            bad = info - 1
        elif info == 0 and m:
            piv = np.diagonal(l11) ** 2
            low = np.flatnonzero(~(piv > self.pivot_tol * orig))
            bad = int(low[0]) if len(low) else -1
        if bad >= 0:
            raise PivotError(int(t.lo[i]) + bad // k, bad % k)
        y1 = scipy.linalg.solve_triangular(l11, b[:m], lower=True, check_finite=False) \
            if m else np.zeros(0)
        self.y_norm2 += float(y1 @ y1)
        f = a.shape[0] - m
        if f:
            l21 = blas.dtrsm(1.0, l11, a[m:, :m], side=1, lower=1, trans_a=1)
            u = blas.dsyrk(-1.0, l21, beta=1.0, c=a[m:, m:], lower=1, trans=0)
            ub = b[m:] - l21 @ y1
            if t.parent[i] >= 0:
                self.updates[i] = (u, ub)
        else:
            l21 = np.zeros((0, m))
        self.file.write(i, l11, l21, y1)
        self.factored += 1

    def solve(self, n_stations):
        """``delta`` (n_stations x k; stations outside the tree 0) by back substitution
        down the tree."""
        t, k = self.tree, self.k
        x = np.zeros(k * n_stations)
        for i in range(t.n_nodes - 1, -1, -1):
            l11, l21, y1 = self.file.read(i)
            r = y1
            if l21.shape[0]:
                r = y1 - l21.T @ x[_scalar(t.bnd(i), k)]
            x[k * t.lo[i]:k * t.hi[i]] = scipy.linalg.solve_triangular(
                l11, r, lower=True, trans="T", check_finite=False)
        return x.reshape(n_stations, k)

    def inverse(self, on_node):
        """Selected inversion top-down: ``on_node(i, z)`` with ``z`` (kf x kf, C order,
        symmetric) the inverse of the reduced matrix over node ``i``'s front."""
        t, k = self.tree, self.k
        held = {}
        left = np.array([len(c) for c in self.children])
        for i in range(t.n_nodes - 1, -1, -1):
            l11, l21, _ = self.file.read(i)
            m, f = l11.shape[0], l21.shape[0]
            linv, info = lapack.dtrtri(l11, lower=1)
            z = np.empty((m + f, m + f))
            if f:
                p = int(t.parent[i])
                fr = t.front(p)
                ix = _scalar(np.searchsorted(fr, t.bnd(i)), k)
                zp = held[p]
                z22 = zp[np.ix_(ix, ix)]
                x = l21 @ linv
                z21 = -(z22 @ x)
                z11 = linv.T @ linv - x.T @ z21
                z[:m, :m] = z11
                z[m:, :m] = z21
                z[:m, m:] = z21.T
                z[m:, m:] = z22
            else:
                z[:, :] = linv.T @ linv
            p = int(t.parent[i])
            if p >= 0:
                left[p] -= 1
                if left[p] == 0:
                    held.pop(p, None)
            on_node(i, z)
            if left[i] > 0:
                held[i] = z

    def close(self):
        self.file.close()


def _extend_add(a, b, u, ub, ix):
    """``a[ix, ix] += u`` (lower triangle of ``u`` mapped onto that of ``a``: ``ix`` is
    ascending) and ``b[ix] += ub``."""
    _extend_add_kernel(a, u, ix)
    b[ix] += ub


@njit(cache=True, nogil=True)
def _extend_add_kernel(a, u, ix):
    n = ix.shape[0]
    for c in range(n):
        jc = ix[c]
        for r in range(c, n):
            a[ix[r], jc] += u[r, c]
