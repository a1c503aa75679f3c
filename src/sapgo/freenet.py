"""The datum of a free network (no control, no priors): minimal constraints to adjust it,
inner constraints to give its solution and precision (docs/theory.md section 1d).

The observations of a free network fix its shape, not its position, orientation and scale:
the normal matrix ``N`` has the 7-dimensional null space ``H`` of the similarity
transformations (3 shifts ``t``, 3 rotations ``w``, the scale ``l``). For a point ``X`` and
a photo's centre ``C`` (about the datum points' centroid ``m``) and attitude (the rotation
vector of sapgo's unknowns, :func:`sapgo.geometry.turn`)::

    dX = t + w x (X - m) + l (X - m)       dC = t + w x (C - m) + l (C - m)    dtheta = w

1. **Adjustment**: 7 station parameters are held (:func:`minimal_constraints`: the six of
   the photo nearest the block's centre, the coordinate of the farthest photo along which
   it lies farthest), so every step is regular. Any such choice gives the same shape, the
   same residuals, sigma0 and redundancy numbers.
2. **Solution** (:func:`to_inner`): the similarity that brings the adjusted object points
   nearest their approximations in least squares (Umeyama's closed form, with scale) is
   applied to the points and photos. The result is the network of the adjusted shape whose
   points moved least from their approximations: ``G (X - X0) = 0`` with ``G = H_p'`` at
   the solution, the inner constraints on the object points.
3. **Precision** (:func:`inner_precision`): the cofactors in the datum of the minimal
   constraints, ``Q`` (the precision pass of the refactored normals), S-transformed to the
   inner constraints: ``Q_G = S Q S'``, ``S = I - H (G H)^-1 G``, which is the inverse of
   the bordered matrix ``[[N, G'], [G, 0]]`` over the unknowns (the pseudo-inverse in the
   norm of the object points). Per block ``i`` of a photo or point::

       Q_G,ii = Q_ii - H_i K B_i' - B_i K H_i' + H_i K (G B) K H_i'

   with ``K = (G H)^-1`` and ``B = Q G'`` (7 columns), found by one solve of the full
   normal equations with 7 right-hand sides: the points' part reduced into the stations
   (:func:`sapgo.normals.datum_columns`), the stations' solved with the factor (band or
   tree), the points' back-substituted. Three streaming passes over the points, of
   which only the first linearises the rays where what it finds fits in memory
   (:data:`KEEP_COLUMNS_BYTES`; no border): the second works from its ``Nbar`` and
   point factors, the third from the second's columns.

With self-calibration (a border) the solve goes through the bordered system (the points
reduced into the border as well, the border solved with its Schur complement); the cameras'
cofactors are the same in both datums (a similarity moves no camera).
"""

from __future__ import annotations

import types

import numpy as np

from . import threads as _threads
from .normals import PointChunk, datum_columns, datum_columns_parallel, datum_sums_parallel

#: The station parameters held for a free network's adjustment: all six of one photo.
ALL_SIX = 0b111111
#: :func:`inner_precision` keeps the points' datum columns of its second pass for its third
#: (2 x 21 doubles a point), and its first pass's rays for the second, each up to this many
#: bytes, else works them out again.
KEEP_COLUMNS_BYTES = 64 << 20


def minimal_constraints(blk):
    """Hold 7 station parameters of a free network (``blk.fixed``): the six of the active
    photo nearest the median of the photos' centres, and of the photo farthest from it the
    centre coordinate (X, Y or Z) of the largest difference. Returns ``(near, far, axis)``
    (logical stations, axis 0-2), or None when fewer than two photos are active."""
    act = np.flatnonzero(blk.station_active)
    if len(act) < 2:
        return None
    pos = blk.eo[act, 3:6]
    near = int(act[np.argmin(np.linalg.norm(pos - np.median(pos, axis=0), axis=1))])
    d = pos - blk.eo[near, 3:6]
    far = int(act[np.argmax(np.linalg.norm(d, axis=1))])
    axis = int(np.argmax(np.abs(blk.eo[far, 3:6] - blk.eo[near, 3:6])))
    blk.fixed[near] |= ALL_SIX
    blk.fixed[far] |= np.int8(1 << (3 + axis))
    return near, far, axis


def point_rows(xyz, centre):
    """``H`` of points (n x 3 x 7): shifts, rotations ``w x (X - m)``, scale."""
    v = np.asarray(xyz, np.float64) - centre
    h = np.zeros((len(v), 3, 7))
    h[:, [0, 1, 2], [0, 1, 2]] = 1.0
    h[:, :, 3:6] = -_cross(v)
    h[:, :, 6] = v
    return h


def station_rows(eo, centre, npar):
    """``H`` of photos (n x npar x 7): attitude ``dtheta = w``, centre as a point, the
    photo's own intrinsics (rows 6-8) 0."""
    h = np.zeros((len(eo), npar, 7))
    h[:, [0, 1, 2], [3, 4, 5]] = 1.0
    h[:, 3:6] = point_rows(np.asarray(eo)[:, 3:6], centre)
    return h


def _cross(v):
    """``[v]x`` (n x 3 x 3): ``[v]x w = v x w``."""
    c = np.zeros((len(v), 3, 3))
    c[:, 0, 1], c[:, 0, 2] = -v[:, 2], v[:, 1]
    c[:, 1, 0], c[:, 1, 2] = v[:, 2], -v[:, 0]
    c[:, 2, 0], c[:, 2, 1] = -v[:, 1], v[:, 0]
    return c


def _chunks(p, work, blk, opts):
    for a, b in p.chunks("points", opts.chunk_points):
        c = PointChunk(p, a, b, work.xyz_current[a:b], blk.camera, blk.cam_sigma, blk.frame,
                       blk.rejected, blk.rejected_points)
        yield a, b, c


def to_inner(p, work, blk, opts):
    """Move the adjusted network (``work.xyz_current``, ``blk.eo``) by the similarity that
    brings its active object points nearest their approximations (the project's ``xyz``);
    returns ``(scale, R, t)``. The normals of the new state are not factored yet
    (``blk.refactor``)."""
    from scipy.spatial.transform import Rotation

    from .geometry import turned

    n = 0
    sx, sy = np.zeros(3), np.zeros(3)
    for a, b, c in _chunks(p, work, blk, opts):
        on = c.active == 0
        sx += p.read_field("points", "xyz", a, b)[on].sum(axis=0)
        sy += c.xyz[on].sum(axis=0)
        n += int(on.sum())
    if n < 3:
        return 1.0, np.eye(3), np.zeros(3)
    mx, my = sx / n, sy / n
    cov = np.zeros((3, 3))
    var_y = 0.0
    for a, b, c in _chunks(p, work, blk, opts):
        on = c.active == 0
        x = p.read_field("points", "xyz", a, b)[on] - mx
        y = c.xyz[on] - my
        cov += x.T @ y
        var_y += float((y * y).sum())
    u, d, vt = np.linalg.svd(cov / n)
    e = np.eye(3)
    e[2, 2] = np.sign(np.linalg.det(u) * np.linalg.det(vt)) or 1.0
    rot = u @ e @ vt
    scale = float(np.trace(np.diag(d) @ e)) / (var_y / n)
    shift = mx - scale * rot @ my
    for a, b in p.chunks("points", opts.chunk_points):
        xyz = np.asarray(work.xyz_current[a:b], np.float64)
        act = p.read_field("points", "status", a, b) == 0
        xyz[act] = scale * xyz[act] @ rot.T + shift
        work.xyz_current[a:b] = xyz
    act = blk.station_active
    theta = np.tile(Rotation.from_matrix(rot).as_rotvec(), (int(act.sum()), 1))
    eo = blk.eo.copy()
    eo[act, :3] = turned(eo[act, :3], theta)
    eo[act, 3:6] = scale * eo[act, 3:6] @ rot.T + shift
    blk.eo[:] = eo
    blk.refactor = True
    return scale, rot, shift


def _solve_stations(work, blk, opts, r):
    """``M^-1 R`` (stations x npar x c) with the factor of the precision pass."""
    n, k = len(blk.station_ids), blk.npar
    if blk.tree is None:
        from .solve.band import band_solve_columns

        return band_solve_columns(work.band_factor()[0], r, n, blk.band_width, opts.chunk_rows)
    from .solve.fronts import FactorFile, TreeSolver, factor_layout
    from .solve.tree import FACTOR_FILE, work_plan

    file = getattr(work, "tree_factor", None)
    if file is None:
        file = FactorFile(work.dir / FACTOR_FILE, factor_layout(blk.tree, k), "r",
                          n_rhs=1 + blk.n_border)
    _, _, _, tile = work_plan(blk.tree, k, opts, held=blk.held, n_stations=n)
    solver = TreeSolver(blk.tree, k, None, file=file, n_border=blk.n_border, tile=tile,
                        scratch=work.dir)
    return solver.solve_columns(r.reshape(k * n, -1)).reshape(n, k, -1)


def _border_x(work, blk, opts):
    """``X = M^-1 B`` (stations x npar x border) of a self-calibration, as the precision
    pass had it: the band's from its file (``quality_sweep``), the tree's substituted
    back again."""
    n, k, ng = len(blk.station_ids), blk.npar, blk.n_border
    if blk.tree is None:
        xb = work.array("xborder.bin", (n, k, ng), "r")
        try:
            return np.asarray(xb[0:n], dtype=np.float64).reshape(n, k, ng)
        finally:
            xb.close()
    from .solve.fronts import FactorFile, TreeSolver, factor_layout
    from .solve.tree import FACTOR_FILE, work_plan

    file = getattr(work, "tree_factor", None)
    if file is None:
        file = FactorFile(work.dir / FACTOR_FILE, factor_layout(blk.tree, k), "r",
                          n_rhs=1 + ng)
    _, _, _, tile = work_plan(blk.tree, k, opts, held=blk.held, n_stations=n)
    return TreeSolver(blk.tree, k, None, file=file, n_border=ng, tile=tile,
                      scratch=work.dir).border_x(n)


#: The first inner-constraint pass runs on every thread when a copy of the stations' (and
#: the border's) right-hand sides for each thread takes at most this many bytes (about
#: 190 000 stations on 2 threads), else on one thread.
PRIVATE_SUMS_BYTES = 64 << 20


def _point_pass(p, work, blk, opts, centre, x_st, r_st, on_chunk, r_g, x_g, rays=None,
                systems=None):
    """One pass of :func:`sapgo.normals.datum_columns` over the points (``r_g``, ``x_g``:
    the border's reduced right-hand sides and solution, border x 7); ``on_chunk(a, b, c,
    h, b_pt)`` after each chunk (``b_pt``: the points' columns, with ``x_st``).

    ``rays`` (a list, no border): the pass without ``x_st`` appends to it each chunk with
    its rays' ``Nbar`` and its points' factors (``keep_nbar``, ``keep_lo``); the pass with
    ``x_st`` given the filled list works from them (:func:`sapgo.normals.
    datum_columns_kept`: the same numbers, no chunk read and no ray linearised again).
    ``systems`` (with ``rays``): the build's kept systems of this state, undamped
    (``keep_pt``, ``keep_nbar``, :func:`sapgo.adjust._kept_systems`), from which the pass
    without ``x_st`` sums too (:func:`sapgo.normals.datum_sums_kept`), and whose factors and
    ``Nbar`` it hands to the second pass: no ray linearised at all."""
    from .adjust import _point_error
    from .geometry import N_CALIBRATION, with_rotations
    from .normals import (BEHIND_CAMERA, _datum_sums_kept, datum_columns_kept,
                          datum_sums_kept)

    if x_st is not None and rays:
        for a, b, c, h, keep_nbar, keep_lo in rays:
            b_pt = np.zeros_like(h)
            _threads.adapt()
            datum_columns_kept(_threads.parts(), c.pt_start, c.nobs, c.active, c.obs_station,
                               c.obs_active, h, x_st, b_pt, keep_nbar, keep_lo)
            on_chunk(a, b, c, h, b_pt)
        return
    cal = blk.cal if blk.n_border else np.zeros((0, N_CALIBRATION), np.int64)
    eo_k = with_rotations(blk.eo)   # (each station's rotation once, not at every ray)
    private = _threads.parts() * 8 * (r_st.size + r_g.size) <= PRIVATE_SUMS_BYTES
    for a, b, c in _chunks(p, work, blk, opts):
        h = point_rows(c.xyz, centre)
        h[c.active != 0] = 0.0
        b_pt = np.zeros_like(h)
        if x_st is None and rays is not None and systems is not None:
            keep_pt, keep_nbar = systems[0][a:b], systems[1][c.o0:c.o1]
            if private:   # (as datum_sums_parallel sums, else as datum_columns)
                _threads.adapt()
                datum_sums_kept(_threads.parts(), c.pt_start, c.nobs, c.active,
                                c.obs_station, c.obs_active, h, r_st, keep_pt, keep_nbar)
            else:
                _datum_sums_kept(c.pt_start, c.nobs, c.active, c.obs_station, c.obs_active,
                                 h, r_st, keep_pt, keep_nbar)
            rays.append((a, b, c, h, keep_nbar,
                         np.ascontiguousarray(keep_pt[:, :9]).reshape(b - a, 3, 3)))
            on_chunk(a, b, c, h, b_pt)
            continue
        keep = () if rays is None or x_st is not None else (
            np.empty((len(c.obs_station), blk.npar, 3)), np.empty((b - a, 3, 3)))
        args = (c.xyz, c.kind, c.ctrl, c.csig, c.rot, c.pt_start, c.nobs, c.active,
                c.obs_station, c.obs_xy, c.obs_sigma, c.obs_active, eo_k, blk.camera,
                blk.cams, blk.ctrl_mask, c.max_rays, h, x_st, r_st, b_pt, blk.behind_ok,
                blk.fixed, cal, r_g, x_g)
        if x_st is None and not private:   # (sums into the stations' rows)
            bad = datum_columns(*args, *keep)
        elif x_st is None:   # (each thread's sums in a copy of its own)
            _threads.adapt()
            bad = datum_sums_parallel(_threads.parts(), *args[:18], r_st, blk.behind_ok,
                                      blk.fixed, cal, r_g, *keep)
        else:
            _threads.adapt()
            bad = datum_columns_parallel(_threads.parts(), *args)
        if bad:
            raise _point_error(p, c, bad - 1, BEHIND_CAMERA, blk)
        if keep:
            rays.append((a, b, c, h, *keep))
        on_chunk(a, b, c, h, b_pt)


def inner_precision(p, work, blk, opts, sigma0, station_sigma, psig, systems=None):
    """The precision of the minimal constraints' datum (``station_sigma``, n x 6 in
    omega, phi, kappa, X, Y, Z, and ``psig``, the points' file, both from the precision
    pass of the current state) S-transformed to the inner constraints on the object points
    (the module's comment), in place. Returns the 7 x 7 ``K = (G H)^-1``. ``systems``: the
    points' systems the precision pass's build of this state kept, undamped (``keep_pt``,
    ``keep_nbar``; :func:`_point_pass`), or None."""
    from .quality import in_angles

    n, k = len(blk.station_ids), blk.npar
    # the datum points' centroid and G H
    tot, cnt = np.zeros(3), 0
    for _, _, c in _chunks(p, work, blk, opts):
        on = c.active == 0
        tot += c.xyz[on].sum(axis=0)
        cnt += int(on.sum())
    centre = tot / max(cnt, 1)
    gh = np.zeros((7, 7))
    for _, _, c in _chunks(p, work, blk, opts):
        h = point_rows(c.xyz[c.active == 0], centre).reshape(-1, 7)
        gh += h.T @ h   # (one product: a third of einsum's time)
    kk = np.linalg.inv(gh)
    # B = Q G': the stations' part through the factor, the points' by back-substitution;
    # with self-calibration the border's through its Schur complement S (S^-1 the
    # border's cofactors): x_g = S^-1 (r_g - X' r_s), x_s = M^-1 r_s - X x_g
    ng = blk.n_border
    r_st = np.zeros((n, k, 7))
    r_g = np.zeros((ng, 7))
    # the first pass's rays kept for the second (no border), up to KEEP_COLUMNS_BYTES:
    # an observation's Nbar and its chunk's arrays, 8 (3 npar + 8) bytes, and a point's
    # factor of Ndd, its rows h and its chunk's arrays, 52 doubles
    rays = [] if not ng and 8 * ((3 * k + 8) * p.n_observations + 52 * p.n_points) \
        <= KEEP_COLUMNS_BYTES else None
    _point_pass(p, work, blk, opts, centre, None, r_st, lambda *x: None, r_g, r_g, rays,
                systems)
    x_st = np.ascontiguousarray(_solve_stations(work, blk, opts, r_st.copy()))   # (in place)
    x_g = np.zeros((ng, 7))
    if ng:
        xb = _border_x(work, blk, opts)
        x_g = np.asarray(blk.border_cov) @ (r_g - np.einsum("nkg,nkc->gc", xb, r_st))
        x_st = np.ascontiguousarray(x_st - np.einsum("nkg,gc->nkc", xb, x_g))
    gb = np.zeros((7, 7))
    # the points' columns of this pass serve the points' precision below too: kept when
    # they take at most KEEP_COLUMNS_BYTES, else worked out again in a third pass
    kept = [] if psig is not None and 2 * 21 * 8 * p.n_points <= KEEP_COLUMNS_BYTES else None

    def add_gb(a, b, c, h, b_pt):
        gb[:] += np.einsum("irc,ird->cd", h, b_pt)
        if kept is not None:
            kept.append((a, b, types.SimpleNamespace(active=c.active), h, b_pt))

    _point_pass(p, work, blk, opts, centre, x_st, r_st, add_gb, r_g, x_g, rays)
    rays = None

    def delta(h, bq):   # -H K B' - B K H' + H K (G B) K H'
        hk = h @ kk
        return (np.einsum("irc,cd,isd->irs", hk, gb, hk)
                - np.einsum("irc,isc->irs", hk, bq) - np.einsum("irc,isc->irs", bq, hk))

    def delta_diagonal(h, bq):   # delta's diagonal alone (a point's 3 variances)
        hk = (h.reshape(-1, 7) @ kk).reshape(h.shape)   # (one product, not one a point)
        hg = (hk.reshape(-1, 7) @ gb).reshape(h.shape)
        return (hg * hk).sum(axis=2) - 2.0 * (hk * bq).sum(axis=2)

    def fix_points(a, b, c, h, b_pt):
        d = delta_diagonal(h, b_pt)
        s = np.asarray(psig[a:b], np.float64)
        on = c.active == 0
        s[on] = np.sqrt(np.maximum(s[on] ** 2 + sigma0 ** 2 * d[on], 0.0))
        psig[a:b] = s

    if kept is not None:
        for args in kept:
            fix_points(*args)
    elif psig is not None:   # (None: the stations' precision alone)
        _point_pass(p, work, blk, opts, centre, x_st, r_st, fix_points, r_g, x_g)
    act = blk.station_active
    hs = station_rows(blk.eo[act], centre, k)
    d = in_angles(delta(hs, x_st[act]), blk.eo[act], np.zeros(int(act.sum()), np.int64))
    add = np.diagonal(d, axis1=1, axis2=2)[:, :6]
    station_sigma[act] = np.sqrt(np.maximum(station_sigma[act] ** 2 + sigma0 ** 2 * add, 0.0))
    return kk
