"""The tree solve inside the adjustment: build, factor and solve node by node, and the
precision pass on the tree (DESIGN section 5b; docs/theory.md section 2b).

The points are in the tree's post-order (each node's points together, ``tree.pt_start``), so
one streaming pass over them builds every node's front in turn: the node's points are
eliminated into it (:func:`sapgo.solve.fronts.build_front`, stations numbered by their place
in the front), its own stations' priors added, and the front handed to the
:class:`~sapgo.solve.fronts.TreeSolver`, which adds the children's update matrices, factors it
and keeps its update for the parent. The factor goes to ``tree_factor.bin`` in the work
directory; in core: the front being built, the update matrices waiting for their parents, one
chunk of points and per-station vectors.
"""

from __future__ import annotations

import time

import numpy as np

from ..normals import CTRL_MASK, OK, PointChunk, point_sigmas, station_diagonal
from .fronts import TreeSolver, build_front

#: File of the tree's factor in the work directory.
FACTOR_FILE = "tree_factor.bin"


class _Fronts:
    """Node by node over the points: each node's front, filled from its own points."""

    def __init__(self, tree, blk, k):
        self.tree, self.blk, self.k = tree, blk, k
        self.loc = np.full(len(blk.station_ids), -1, np.int64)

    def enter(self, i):
        """Number the stations of node ``i``'s front by their place in it."""
        fr = self.tree.front(i)
        self.loc[fr] = np.arange(len(fr))
        self.stations = fr
        self.eo = np.ascontiguousarray(self.blk.eo[fr])
        self.camera = np.ascontiguousarray(self.blk.camera[fr])
        return fr

    def leave(self):
        self.loc[self.stations] = -1

    def local(self, obs_station, obs_active):
        """The observations' stations as places in the current front (-1: outside, or an
        inactive observation)."""
        loc = self.loc[obs_station]
        return np.ascontiguousarray(np.where(obs_active, loc, -1))


def tree_step(p, work, blk, opts, tree, lam=0.0, iteration=0):
    """Build and factor the reduced normals on the tree and solve them.

    Returns ``(delta, diag, y_norm2, seconds)``: the stations' corrections (n x k, zero
    outside the tree), the stations' undamped diagonal (with ``lam > 0``, else None),
    ``y'y`` (for the Levenberg-Marquardt gain ratio) and the seconds spent factoring and
    solving (the rest is the build). Raises :class:`~sapgo.bandsolve.PivotError` (logical
    station, parameter) when the normals are not positive definite.
    """
    from ..adjust import _PriorCursor, _fault, _point_error, _prior_residual, _progress, \
        _reweight

    k = blk.npar
    n = len(blk.station_ids)
    solver = TreeSolver(tree, k, work.dir / FACTOR_FILE, opts.pivot_tolerance)
    fronts = _Fronts(tree, blk, k)
    priors = _PriorCursor(p, opts.chunk_points)
    diag = np.zeros((n, k)) if lam > 0.0 else None
    seconds = 0.0
    node = -1
    a = b = None
    pt = tree.pt_start

    def open_node(i):
        nonlocal a, b
        fronts.enter(i)
        a, b = solver.open(i)
        lo, hi = int(tree.lo[i]), int(tree.hi[i])
        for rec in priors.take(lo, hi):
            s = int(rec["station"]) - lo
            w = rec["weight"]
            a[k * s:k * s + 6, k * s:k * s + 6] += w
            b[k * s:k * s + 6] += w @ (-_prior_residual(rec, blk.eo[lo + s]))

    def close_node(i):
        nonlocal seconds
        fronts.leave()
        damping = None
        if lam > 0.0:
            d = np.clip(diag[tree.lo[i]:tree.hi[i]], 1e-6, 1e32)
            damping = lam * d.ravel()
        t0 = time.perf_counter()
        solver.eliminate(i, a, b, damping)
        seconds += time.perf_counter() - t0

    try:
        end = int(pt[-1]) if tree.n_nodes else 0
        with _progress(opts.progress, p.n_points, "build") as bar:
            for a0, b0 in p.chunks("points", opts.chunk_points):
                if a0 >= end:
                    break
                b0 = min(b0, end)
                c = PointChunk(p, a0, b0, work.xyz_current[a0:b0], blk.camera, blk.cam_sigma,
                               blk.frame, blk.rejected, blk.rejected_points)
                _reweight(c, work, opts)
                if diag is not None:
                    station_diagonal(c.xyz, c.active, c.pt_start, c.nobs, c.obs_station,
                                     c.obs_sigma, c.obs_active, blk.eo, blk.camera, blk.cams,
                                     diag)
                j = a0
                while j < b0:
                    while node < 0 or pt[node + 1] <= j:
                        if node >= 0:
                            close_node(node)
                        node += 1
                        open_node(node)
                    j1 = min(b0, int(pt[node + 1]))
                    st = fronts.local(c.obs_station, c.obs_active)
                    status, bad = build_front(
                        j - a0, j1 - a0, c.xyz, c.kind, c.ctrl, c.csig, c.rot, c.pt_start,
                        c.nobs, c.active, st, c.obs_xy, c.obs_sigma, c.obs_active, fronts.eo,
                        fronts.camera, blk.cams, CTRL_MASK, a, b, c.max_rays, k, lam,
                        blk.behind_ok)
                    if status != OK:
                        raise _point_error(p, c, bad, status, blk)
                    j = j1
                del c
                bar.update(b0 - a0)
                _fault("build", iteration)
        while node < tree.n_nodes - 1:
            if node >= 0:
                close_node(node)
            node += 1
            open_node(node)
        if node >= 0:
            close_node(node)
        t0 = time.perf_counter()
        delta = solver.solve(n)
        seconds += time.perf_counter() - t0
        return delta, diag, solver.y_norm2, seconds
    finally:
        solver.close()


def tree_quality(p, work, blk, opts, tree, sigma0, psig, quality, cov, correlations,
                 quality_columns):
    """The precision pass on the tree: the selected inversion top-down and, node by node,
    the stations' cofactor blocks (``cov``), the points' standard deviations (``psig``) and
    their observations' quality (``quality``), as :func:`sapgo.adjust._quality_sweep` does
    along the band. Returns the stations' variances (n x k)."""
    from ..adjust import _reweight
    from .fronts import FactorFile  # noqa: F401  (the factor file of the last tree_step)

    k = blk.npar
    n = len(blk.station_ids)
    var = np.zeros((n, k))
    solver = TreeSolver.reopen(tree, k, work.dir / FACTOR_FILE)
    fronts = _Fronts(tree, blk, k)
    xyz_ds, res_ds = work.xyz_current, work.res_current

    def on_node(i, z):
        lo, hi = int(tree.lo[i]), int(tree.hi[i])
        m = k * (hi - lo)
        blocks = np.empty((hi - lo, k, k))
        for s in range(hi - lo):
            blocks[s] = z[k * s:k * s + k, k * s:k * s + k]
        cov[lo:hi] = blocks
        var[lo:hi] = np.diagonal(blocks, axis1=1, axis2=2)
        p0, p1 = int(tree.pt_start[i]), int(tree.pt_start[i + 1])
        if p1 <= p0:
            return
        fronts.enter(i)
        zc = np.ascontiguousarray(z)
        try:
            for a0 in range(p0, p1, opts.chunk_points):
                b0 = min(p1, a0 + opts.chunk_points)
                c = PointChunk(p, a0, b0, xyz_ds[a0:b0], blk.camera, blk.cam_sigma, blk.frame,
                               blk.rejected)
                weight = _reweight(c, work, opts)
                out = np.empty((b0 - a0, 6))
                out_r = np.empty((c.o1 - c.o0, 3))
                out_w = np.empty((c.o1 - c.o0, 3))
                st = fronts.local(c.obs_station, c.obs_active)
                st[st < 0] = 0   # inactive observations: never looked at
                point_sigmas(c.xyz, c.kind, c.ctrl, c.csig, c.rot, c.pt_start, c.nobs,
                             c.active, st, c.obs_xy, c.obs_sigma, c.obs_active, fronts.eo,
                             fronts.camera, blk.cams, CTRL_MASK, c.max_rays, zc, 0,
                             np.ascontiguousarray(res_ds[c.o0:c.o1]), out, out_r, out_w, k)
                psig[a0:b0] = sigma0 * out[:, :3]
                if weight is None:
                    weight = np.ones(c.o1 - c.o0)
                quality[c.o0:c.o1] = np.concatenate(
                    [out_r, out_w / sigma0, np.where(c.obs_active, weight, 0.0)[:, None]],
                    axis=1)
                if correlations is not None:
                    rho = np.where((c.active == 0)[:, None], out[:, 3:], np.nan)
                    correlations.add("points", p.read_field("points", "id", a0, b0), rho)
        finally:
            fronts.leave()
        del m

    try:
        solver.inverse(on_node)
    finally:
        solver.close()
    return var
