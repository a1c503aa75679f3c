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

import threading
import time

import numpy as np
from numba import njit

from .. import threads as _threads
from ..geometry import N_CALIBRATION
from ..normals import OK, PointChunk, station_diagonal
from .fronts import FactorFile, TreeSolver, build_front, factor_layout
from .tiles import Panels

#: File of the tree's factor in the work directory.
FACTOR_FILE = "tree_factor.bin"

#: The adjustment's memory budget on the tree when ``--memory`` is not given: the process's
#: baseline (:data:`BASELINE`), the records held in core, the fronts and update matrices
#: (tiled when they would not fit, checked before any work) and the factor when it fits
#: beside them.
DEFAULT_TREE_MEMORY = 1 << 30

#: What the adjusting process holds besides the solver, counted against the budget: the
#: interpreter, numpy, SciPy, h5py and the compiled kernels (about 250 MiB measured after
#: a first small run), and per station its vectors (orientation, corrections, diagonal,
#: variances, numbering: 400 bytes a station).
BASELINE = 256 << 20
BASELINE_PER_STATION = 400

_EMPTY = np.zeros((0, 0), order="F")   # (no update block: a tiled front's panel)

#: The smallest tiles tried: fronts beyond budget / 2**j in core are tiled, j up to this.
_TILE_STEPS = 10


def tree_budget(opts, held=0, n_stations=0):
    """Bytes the tree solver may hold in core: ``opts.memory`` or the default, less the
    process's baseline for ``n_stations`` stations and the ``held`` bytes of records that
    the run keeps in core (:func:`sapgo.adjust._hold_records`)."""
    from ..extsort import parse_memory

    total = DEFAULT_TREE_MEMORY if opts.memory is None else parse_memory(opts.memory)
    return total - BASELINE - BASELINE_PER_STATION * n_stations - held


def tile_plan(tree, k, budget, plan=None, separate=False):
    """The tiling that fits ``budget`` (with ``plan``, workers side by side, or one worker):
    None when every front fits in core, else ``(front_bytes, panel_bytes)`` for
    :meth:`~sapgo.solve.partition.Tree.peak_front_bytes` and the solver, fronts beyond half
    the budget tiled in panels of half that, halved until the peak fits (or the smallest
    tried). Returns ``(tile, peak bytes)``."""
    need = tree.peak_front_bytes(k, plan, separate=separate)
    if need <= budget:
        return None, need
    big = max(budget, 1 << 20) / 2.0
    for _ in range(_TILE_STEPS):
        tile = (big, big / 2.0)
        need = tree.peak_front_bytes(k, plan, tile, separate)
        if need <= budget:
            break
        big /= 2.0
    return tile, need


def tiling(tree, k, opts, held=0, n_stations=0):
    """The tiling of the run's plan (:func:`work_plan`) as figures: ``tiled_fronts`` (how
    many fronts are factored a panel at a time), ``panel_bytes`` (at most; 0 when none)."""
    _, _, _, tile = work_plan(tree, k, opts, held=held, n_stations=n_stations)
    if tile is None:
        return {"tiled_fronts": 0, "panel_bytes": 0}
    return {"tiled_fronts": int((tree.front_bytes(k) > tile[0]).sum()),
            "panel_bytes": int(tile[1])}


def check_tree_memory(tree, k, opts, path, n_stations=0):
    """Refuse, before any work, a tree whose fronts do not fit the memory budget even
    tiled: one line with the figures and the advice."""
    from ..errors import SapgoError
    from ..extsort import parse_memory

    total = DEFAULT_TREE_MEMORY if opts.memory is None else parse_memory(opts.memory)
    budget = tree_budget(opts, 0, n_stations)
    if budget <= 0:
        base = total - budget
        raise SapgoError(
            f"{path}: --memory {total / 2**20:.0f}M is less than the adjustment's baseline "
            f"on the partition tree ({base / 2**20:.0f} MiB: 256 MiB and "
            f"{BASELINE_PER_STATION} bytes a photo): give --memory "
            f"{-(-base // 2**20) + 128}M or more")
    _, need = tile_plan(tree, k, budget)
    if need > budget:
        f = tree.figures(k)
        raise SapgoError(
            f"{path}: the partition tree's fronts need {need / 2**20:.0f} MiB in core even "
            f"tiled (largest front {f['largest_front']} stations, "
            f"{f['largest_front_bytes'] / 2**20:.0f} MiB), more than the memory budget "
            f"leaves them ({budget / 2**20:.0f} MiB of --memory after the process's "
            f"baseline): give --memory {-(-(need + total - budget) // 2**20) + 64}M or more, "
            f"or --solver band")


class _Fronts:
    """Node by node over the points: each node's front, filled from its own points."""

    def __init__(self, tree, blk, k):
        self.tree, self.blk, self.k = tree, blk, k
        self.loc = np.full(len(blk.station_ids), -1, np.int64)
        self.links = tree.links(k)

    def enter(self, i):
        """Number the stations of node ``i``'s front by their place in it."""
        fr = self.tree.front(i) if self.links is None else self.links[i][0]
        self.stations = fr
        self.eo, self.camera, self.fixed = _enter(fr, self.loc, np.asarray(self.blk.eo),
                                                  np.asarray(self.blk.camera),
                                                  np.asarray(self.blk.fixed))
        return fr

    def leave(self):
        self.loc[self.stations] = -1

    def numbered(self, obs_station, obs_active):
        """The observations' stations, orientations and cameras by place in the front (for
        :func:`sapgo.quality.points_quality`; inactive observations at place 0, never looked
        at), and their fixed parameters."""
        st = self.local(obs_station, obs_active)
        st[st < 0] = 0
        return st, self.eo, self.camera, self.fixed

    def local(self, obs_station, obs_active):
        """The observations' stations as places in the current front (-1: outside, or an
        inactive observation)."""
        return _local(self.loc, obs_station, obs_active)


@njit(cache=True, nogil=True)
def _enter(fr, loc, eo, camera, fixed):
    """``loc[fr] = 0, 1, ..`` and the front's stations' orientations, cameras and fixed
    parameters (:meth:`_Fronts.enter`)."""
    n = fr.shape[0]
    eo_f = np.empty((n, eo.shape[1]))
    cam_f = np.empty(n, camera.dtype)
    fix_f = np.empty(n, fixed.dtype)
    for j in range(n):
        s = fr[j]
        loc[s] = j
        eo_f[j] = eo[s]
        cam_f[j] = camera[s]
        fix_f[j] = fixed[s]
    return eo_f, cam_f, fix_f


@njit(cache=True, nogil=True)
def _local(loc, obs_station, obs_active):
    """:meth:`_Fronts.local`."""
    out = np.empty(obs_station.shape[0], np.int64)
    for j in range(obs_station.shape[0]):
        out[j] = loc[obs_station[j]] if obs_active[j] else -1
    return out


#: The top nodes' speed, factored one after the other with every thread in BLAS, against one
#: worker's on its subtrees (flops a second): at 200 x 200 the top's 8.6 GFlop ran at 54-72
#: GFlop/s, the workers' subtrees at about 49 GFlop/s a thread.
TOP_SPEED = 1.2


def _node_flops(tree, k):
    """Each node's factorisation flops and a fixed cost (the plans' unit of work)."""
    return tree.node_flops(k) + 1e6


def plan_flops(tree, k, per, top):
    """The predicted length of a plan (:func:`parallel_plan`) in one worker's flops: the
    busiest worker's subtrees, then the top nodes at :data:`TOP_SPEED`."""
    fl = _node_flops(tree, k)
    busiest = max(sum(float(fl[a:b].sum()) for a, b in ranges) for ranges in per)
    return busiest + float(fl[np.asarray(top, np.int64)].sum()) / TOP_SPEED


def parallel_plan(tree, k, workers, share=0.5):
    """Split the tree for ``workers`` threads: disjoint subtrees (as node ranges ``(first,
    last + 1)``) dealt to the workers largest first (by flops) and the *top* nodes above
    them, factored afterwards by all threads' BLAS. Subtrees are split until none holds more
    than ``share`` of a worker's share. Returns ``(per_worker, top)``."""
    sub = _node_flops(tree, k)
    size = np.ones(tree.n_nodes, np.int64)
    children = tree.children()
    for i in range(tree.n_nodes):
        for c in children[i]:
            sub[i] += sub[c]
            size[i] += size[c]
    roots = [int(i) for i in np.flatnonzero(tree.parent < 0)]
    if workers < 2 or tree.n_nodes < 4:
        return [[(0, tree.n_nodes)]], []
    total = float(sum(sub[r] for r in roots))
    parts, top = list(roots), []
    while parts:
        j = max(parts, key=lambda x: sub[x])
        if sub[j] <= share * total / workers or not children[j]:
            break
        parts.remove(j)
        top.append(j)
        parts.extend(children[j])
    load = [0.0] * workers
    per = [[] for _ in range(workers)]
    for j in sorted(parts, key=lambda x: -sub[x]):
        w = int(np.argmin(load))
        load[w] += sub[j]
        per[w].append((int(j - size[j] + 1), int(j + 1)))
    return [sorted(x) for x in per], sorted(top)


def work_plan(tree, k, opts, threads=None, held=0, n_stations=0, separate=False):
    """The plan of :func:`parallel_plan` for ``threads`` workers (default numba's thread
    count) whose fronts fit the memory budget side by side: of the subtree sizes tried
    (``share``), the shortest predicted (:func:`plan_flops`) that fits (smaller subtrees
    leave the large fronts near the root to the top), else one worker, with the
    large fronts tiled if they do not fit in core (:func:`tile_plan`). Returns
    ``(per_worker, top, bytes, tile)`` with the bytes of fronts and updates it holds at its
    peak (:meth:`~sapgo.solve.partition.Tree.peak_front_bytes`).

    ``separate``: the workers are processes with a budget each (Dask), so a worker's fronts
    need to fit its own budget, not the sum; with tiling, the largest subtrees that fit
    (the least work left to the top, which the client does alone)."""
    budget = tree_budget(opts, held, n_stations)
    shares = (0.5, 0.25, 0.125, 0.0625)   # smaller subtrees, more nodes on top
    threads = threads or _threads.parts()
    plans = [parallel_plan(tree, k, threads, share) for share in shares]
    per, top = plans[-1]   # (the smallest subtrees: the one tiled below when none fits)
    if not separate:   # (Dask: the top on the client alone; these shares in this order)
        plans.append(parallel_plan(tree, k, threads, 1.0))
        plans.sort(key=lambda plan: plan_flops(tree, k, *plan))   # (stable: ties by share)
    for per_p, top_p in plans:
        if len(per_p) < 2:
            break
        need = tree.peak_front_bytes(k, (per_p, top_p), separate=separate)
        if need <= budget:
            return per_p, top_p, need, None
    if len(per) > 1:   # the workers' subtrees side by side with the large fronts tiled
        for share in shares if separate else ():
            per_s, top_s = parallel_plan(tree, k, threads, share)
            tile, need = tile_plan(tree, k, budget, (per_s, top_s), True)
            if need <= budget:
                return per_s, top_s, need, tile
        tile, need = tile_plan(tree, k, budget, (per, top))
        if need <= budget:
            return per, top, need, tile
    tile, need = tile_plan(tree, k, budget)
    return [[(0, tree.n_nodes)]], [], need, tile


def _factor_in_core(layout, ng, need, opts, held, n):
    """Whether the factor's records (``layout``, ``1 + ng`` right-hand sides) fit the memory
    budget beside ``need`` bytes of fronts: then the factor stays in core."""
    return FactorFile.record_bytes(layout, 1 + ng).sum() + need <= tree_budget(opts, held, n)


class _Arena:
    """The in-core factor's buffer (:func:`~sapgo.solve.fronts._anonymous`: every page
    mapped) made on a thread of its own; :meth:`result` waits for it."""

    def __init__(self, n):
        from .fronts import _anonymous

        self._out = []
        self._thread = threading.Thread(target=lambda: self._out.append(_anonymous(n)),
                                        name="sapgo-arena", daemon=True)
        self._thread.start()

    def result(self):
        self._thread.join()
        return self._out[0] if self._out else None


def start_arena(work, blk, opts):
    """When the tree's factor will stay in core, map its buffer's pages (about 0.07 s for
    the 193 MB of the 100 x 100 block, the kernel zeroing them) on a thread of its own, so
    that this overlaps the run's checks and first reads instead of delaying the first
    factorisation. Nothing on Dask or when the factor goes to a file."""
    tree = blk.tree
    if tree is None or getattr(opts, "client", None) is not None or work.tree_arena is not None:
        return
    k, n, ng = blk.npar, len(blk.station_ids), blk.n_border
    layout = factor_layout(tree, k)
    _, _, need, _ = work_plan(tree, k, opts, None, blk.held, n)
    if _factor_in_core(layout, ng, need, opts, blk.held, n):
        work.tree_arena = _Arena(int(FactorFile.record_bytes(layout, 1 + ng).sum()) // 8)


def tree_step(p, work, blk, opts, tree, lam=0.0, iteration=0, threads=None, capture=None):
    """Build and factor the reduced normals on the tree and solve them.

    Independent subtrees are built and factored on ``threads`` threads (default: numba's
    thread count) with single-threaded BLAS each, the nodes above them afterwards on the
    same threads, a large front split between them
    (:meth:`~sapgo.solve.fronts.TreeSolver._eliminate_split`) (:func:`parallel_plan`; one
    worker, the top with all threads in BLAS, when the subtrees' fronts side by side would
    not fit the memory budget, :func:`work_plan`). The factor is kept in core when it fits
    the memory budget beside the fronts (:func:`tree_budget`), else in
    ``tree_factor.bin``; either way it stays with ``work.tree_factor`` for the precision
    pass.

    Self-calibration (``blk.n_border`` columns): the border's columns are built into each
    front beside its right-hand side and forward-substituted with it
    (:class:`~sapgo.solve.fronts.TreeSolver`), the border's block and right-hand side summed
    over the threads and damped as on the band, and the border solved densely
    (:func:`~sapgo.solve.band.border_schur_solve`) before the stations.

    Returns a dict as :func:`sapgo.adjust._factor_solve`'s: ``delta`` (the stations'
    corrections, n x k, zero outside the tree), ``diag`` (the stations' undamped diagonal
    with ``lam > 0``, else None), ``border`` (``(cnn, ccg, cdiag)`` or None), ``theta``,
    ``border_cov`` (``S^-1``), ``xb`` (``x'b`` of the step: ``y'y`` plus the border's
    share, for the Levenberg-Marquardt gain ratio) and ``seconds`` spent factoring and
    solving (the rest is the build). Raises :class:`~sapgo.solve.band.PivotError` (logical
    station, parameter) when the normals are not positive definite and
    :class:`~sapgo.solve.band.BorderPivotError` when the border's are not.
    ``capture(i, front, rhs)`` (benchmarks) sees each node's front with its own points,
    priors and damping, before the children's updates are added: their sum over the nodes
    is the reduced normal matrix.
    """
    from concurrent.futures import ThreadPoolExecutor

    from ..adjust import _progress
    from ..blas import blas_limits
    from .band import border_schur_solve

    k = blk.npar
    n = len(blk.station_ids)
    ng = blk.n_border
    old = getattr(work, "tree_factor", None)
    if old is not None:
        old.close()
        work.tree_factor = None
    layout = factor_layout(tree, k)
    client = getattr(opts, "client", None)
    if client is not None:   # Dask: a part a worker process, the factor in the shared file
        from .distributed import worker_addresses

        threads = max(2, len(worker_addresses(client)))
    per, top, need, tile = work_plan(tree, k, opts, threads, blk.held, n,
                                     separate=client is not None)
    in_core = client is None and _factor_in_core(layout, ng, need, opts, blk.held, n)
    # in core, the last step's buffer again (its pages are faulted in already), or the one
    # made beside the run's start (:func:`start_arena`)
    arena = getattr(work, "tree_arena", None)
    if isinstance(arena, _Arena):
        arena = arena.result()
    file = FactorFile(None if in_core else work.dir / FACTOR_FILE, layout, n_rhs=1 + ng,
                      arena=arena)
    work.tree_arena = file.arena if in_core else None
    solver = TreeSolver(tree, k, None, opts.pivot_tolerance, file=file, n_border=ng,
                        tile=tile, scratch=work.dir)
    solver.set_parts(per, top)
    from .distributed import TRACE, note_nodes

    solver.trace = {} if TRACE["on"] else None
    if capture is not None and solver.tiled.any():
        raise ValueError("capture needs every front in core: give a larger --memory")
    diags = [np.zeros((n, k)) if lam > 0.0 else None for _ in per]
    # the border's block, right-hand side and undamped diagonal, a set per thread
    cb = [(np.zeros((ng, ng)), np.zeros(ng), np.zeros(ng)) for _ in range(len(per) + 1)]
    seconds = np.zeros(len(per) + 1)
    pool = None   # the parts' threads, kept for the top (a large front split between them)
    try:
        with _progress(opts.progress, p.n_points, "build") as bar:
            if client is not None:
                from .distributed import distributed_step

                file.close()   # the workers write their records; read back after them
                diags[:len(per)], cb[:len(per)], sec = distributed_step(
                    p, work, blk, opts, tree, solver, per, top, lam, iteration, bar)
                seconds[:len(per)] = sec
                file = FactorFile(work.dir / FACTOR_FILE, layout, n_rhs=1 + ng)
                solver.file = file
            elif len(per) > 1:
                pool = ThreadPoolExecutor(len(per))
                with blas_limits(1):
                    jobs = [pool.submit(_run_nodes, p, work, blk, opts, tree, solver, ranges,
                                        lam, diags[w], seconds, w, iteration, bar, capture,
                                        cb[w]) for w, ranges in enumerate(per)]
                    for j in jobs:
                        j.result()
            else:
                _run_nodes(p, work, blk, opts, tree, solver, per[0], lam, diags[0], seconds,
                           0, iteration, bar, capture, cb[0])
            diag = None
            if lam > 0.0:
                diag = diags[0]
                for d in diags[1:]:
                    diag += d
            if top and client is not None:   # Dask: the top's fronts on the workers too
                from .distributed import distributed_top

                t_top = time.perf_counter()
                if lam > 0.0:
                    points_diagonal(p, work, blk, opts, tree, top, diag)
                distributed_top(client, p, work, blk, opts, tree, solver, top,
                                work._dask_parts, lam, diag, cb[len(per)])
                work._dask_parts = work._blk_future = None   # (the parts' updates go)
                file.close()   # (opened again: what the workers wrote, on any filesystem)
                file = FactorFile(work.dir / FACTOR_FILE, layout, n_rhs=1 + ng)
                solver.file = file
                seconds[len(per)] += time.perf_counter() - t_top
                bar.update(sum(int(tree.pt_start[j + 1] - tree.pt_start[j]) for j in top))
            elif top:
                # with the parts' threads: a large front in core split between this thread
                # and the pool's (each on one BLAS thread), the others (tiled, or a child's
                # update in panels on disk) with every thread in BLAS
                solver.pool = pool
                _run_nodes(p, work, blk, opts, tree, solver, [(j, j + 1) for j in top], lam,
                           diag, seconds, len(per), iteration, bar, capture, cb[len(per)])
    finally:
        solver.pool = None
        if pool is not None:
            pool.shutdown()
    t0 = time.perf_counter()
    out = {"diag": diag, "border": None, "theta": None, "border_cov": None}
    theta = None
    decrease = 0.0
    if ng:
        cnn, ccg, cdiag = (sum(x[i] for x in cb) for i in range(3))
        if lam > 0.0:
            cnn[np.arange(ng), np.arange(ng)] += lam * np.clip(cdiag, 1e-6, 1e32)
        theta, decrease, s_inv = border_schur_solve(cnn - solver.ww, ccg - solver.wy,
                                                    opts.pivot_tolerance)
        out.update(border=(cnn, ccg, cdiag), theta=theta, border_cov=s_inv)
    if client is not None:
        from .distributed import distributed_solve

        out["delta"] = distributed_solve(client, work, tree, solver, n, theta, per, top)
    else:
        out["delta"] = solver.solve(n, theta, (per, top))
    out["xb"] = solver.y_norm2 + decrease
    work.tree_factor = file
    note_nodes(solver.trace)
    # the threads' solver time overlaps: count the busiest thread's
    out["seconds"] = (float(seconds[:len(per)].max() + seconds[len(per)])
                      + time.perf_counter() - t0)
    return out


def _run_nodes(p, work, blk, opts, tree, solver, ranges, lam, diag, seconds, slot,
               iteration, bar, capture=None, border=None):
    """Build and eliminate the nodes of ``ranges`` (``(first, stop)`` node ranges, each in
    post-order) from their points, read chunk by chunk; ``diag`` receives the stations'
    undamped diagonal of these points, ``border`` (``(cnn, ccg, cdiag)``, this thread's) the
    border's share; the solver's seconds go to ``seconds[slot]``."""
    from ..adjust import _PriorCursor, _point_error
    from ..quality import reweight
    from ..work import _fault

    k = blk.npar
    ng = blk.n_border
    fronts = _Fronts(tree, blk, k)
    priors = _PriorCursor(p, opts.chunk_points, blk)
    pt = tree.pt_start
    state = {"node": -1, "a": None, "b": None, "rhs": None, "bord": None}
    cnn, ccg, cdiag = border if border is not None else (np.zeros((0, 0)), np.zeros(0),
                                                         np.zeros(0))
    cal = blk.cal if ng else np.full((0, N_CALIBRATION), -1, np.int64)

    def open_node(i):
        t_open = time.perf_counter()
        fr = fronts.enter(i)
        tiled = bool(solver.tiled[i])
        a, b = solver.open(i, tiled)
        rhs = b if b.ndim == 1 else b[:, 0]
        # the front's rows of the border's columns: a view of b (stations x k x ng)
        bord = (b[:, 1:].reshape(len(fr), k, ng) if ng else np.zeros((len(fr), k, 0)))
        assert not ng or np.shares_memory(bord, b)
        lo, hi = int(tree.lo[i]), int(tree.hi[i])
        held = []   # a tiled front's priors: added panel by panel
        for s, w, r in priors.take(lo, hi):
            s -= lo
            if tiled:
                held.append((k * s, w))
            else:   # (own stations: own columns)
                a[0][k * s:k * s + 6, k * s:k * s + 6] += w
            rhs[k * s:k * s + 6] += r
        state.update(node=i, a=a, b=b, rhs=rhs, bord=bord, tiled=tiled, priors=held,
                     chunks=None, opened=t_open)

    def assemble(c0, c1, a):
        """A panel of the tiled front at hand: its own points (the border's terms with the
        first panel; the points read once for all its panels) and its priors."""
        for r0, w in state["priors"]:
            if c0 <= r0 < c1:
                a[r0 - c0:r0 - c0 + 6, r0 - c0:r0 - c0 + 6] += w
        if state["chunks"] is None:
            state["chunks"] = node_points(p, work, blk, opts, tree, fronts, state["node"])
        build_panel(p, blk, fronts, state["chunks"], lam, a, state["rhs"], state["bord"],
                    (cnn, ccg, cdiag), c0, c1)

    def close_node():
        i = state["node"]
        damping = None
        if lam > 0.0:
            damping = lam * np.clip(diag[tree.lo[i]:tree.hi[i]], 1e-6, 1e32).ravel()
        if capture is not None:   # (the front in full, a copy)
            own, upd = state["a"]
            m = own.shape[1]
            full = np.zeros((own.shape[0], own.shape[0]), order="F")
            full[:, :m] = own
            full[m:, m:] = upd
            capture(i, full, state["b"])
        t0 = time.perf_counter()
        if state["tiled"]:
            solver.eliminate_tiled(i, assemble, state["b"], damping)
        else:
            solver.eliminate(i, state["a"], state["b"], damping)
        fronts.leave()
        t1 = time.perf_counter()
        seconds[slot] += t1 - t0
        if solver.trace is not None:
            solver.trace[int(i)] = (t1 - state["opened"], t1 - t0)
        state.update(node=-1, chunks=None)

    for first, stop in ranges:
        p0, p1 = int(pt[first]), int(pt[stop])
        node = first
        open_node(node)
        for a0 in range(p0, p1, opts.chunk_points):
            b0 = min(p1, a0 + opts.chunk_points)
            c = PointChunk(p, a0, b0, work.xyz_current[a0:b0], blk.camera, blk.cam_sigma,
                           blk.frame, blk.rejected, blk.rejected_points)
            reweight(c, work, opts)
            st = np.full(len(c.obs_station), -1, np.int64)
            if diag is not None:
                station_diagonal(c.xyz, c.active, c.pt_start, c.nobs, c.obs_station,
                                 c.obs_sigma, c.obs_active, blk.eo, blk.camera, blk.cams, diag)
            j = a0
            while j < b0:
                while pt[node + 1] <= j:
                    close_node()
                    node += 1
                    open_node(node)
                j1 = min(b0, int(pt[node + 1]))
                if state["tiled"]:   # built panel by panel when the node is closed
                    j = j1
                    continue
                if j1 > j:   # the places of these points' observations only
                    o0 = int(c.pt_start[j - a0])
                    o1 = int(c.pt_start[j1 - 1 - a0] + c.nobs[j1 - 1 - a0])
                    st[o0:o1] = fronts.local(c.obs_station[o0:o1], c.obs_active[o0:o1])
                status, bad = build_front(
                    j - a0, j1 - a0, c.xyz, c.kind, c.ctrl, c.csig, c.rot, c.pt_start,
                    c.nobs, c.active, st, c.obs_xy, c.obs_sigma, c.obs_active, fronts.eo,
                    fronts.camera, blk.cams, blk.ctrl_mask, *state["a"], state["rhs"],
                    c.max_rays, k, lam, blk.behind_ok, cal, state["bord"], cnn, ccg, cdiag,
                    0, state["a"][0].shape[1], fronts.fixed)
                if status != OK:
                    raise _point_error(p, c, bad, status, blk)
                j = j1
            del c
            bar.update(b0 - a0)
            _fault("build", iteration)
        close_node()
        while node < stop - 1:
            node += 1
            open_node(node)
            close_node()


def points_diagonal(p, work, blk, opts, tree, nodes, diag):
    """The stations' undamped diagonal (``diag``, stations x k) of the points of
    ``nodes``."""
    from ..quality import reweight

    pt = tree.pt_start
    for i in nodes:
        q0, q1 = int(pt[i]), int(pt[i + 1])
        for a0 in range(q0, q1, opts.chunk_points):
            b0 = min(q1, a0 + opts.chunk_points)
            c = PointChunk(p, a0, b0, work.xyz_current[a0:b0], blk.camera, blk.cam_sigma,
                           blk.frame, blk.rejected, blk.rejected_points)
            reweight(c, work, opts)
            station_diagonal(c.xyz, c.active, c.pt_start, c.nobs, c.obs_station,
                             c.obs_sigma, c.obs_active, blk.eo, blk.camera, blk.cams, diag)


def node_points(p, work, blk, opts, tree, fronts, i):
    """Node ``i``'s own points, read (and reweighted) in chunks, each with its
    observations' places in the front (``fronts`` entered at ``i``): a separator's points,
    read once for all the panels of its front."""
    from ..quality import reweight

    pt = tree.pt_start
    q0, q1 = int(pt[i]), int(pt[i + 1])
    out = []
    for a0 in range(q0, q1, opts.chunk_points):
        b0 = min(q1, a0 + opts.chunk_points)
        c = PointChunk(p, a0, b0, work.xyz_current[a0:b0], blk.camera, blk.cam_sigma,
                       blk.frame, blk.rejected, blk.rejected_points)
        reweight(c, work, opts)
        out.append((c, fronts.local(c.obs_station, c.obs_active)))
    return out


def build_panel(p, blk, fronts, chunks, lam, a, rhs, bord, sums, c0, c1):
    """Columns ``c0 .. c1`` (rows from ``c0``) of a front from its points ``chunks``
    (:func:`node_points`) into ``a``, their rows of the right-hand side into ``rhs``; with
    ``c0 == 0`` the border's rows ``bord`` (front stations x k x ng) and sums ``sums``
    (``(cnn, ccg, cdiag)``) too."""
    from ..adjust import _point_error

    k, ng = blk.npar, blk.n_border
    cal = blk.cal if ng else np.full((0, N_CALIBRATION), -1, np.int64)
    if c0 != 0:
        bord = np.zeros((bord.shape[0], k, 0))
        sums = (np.zeros((0, 0)), np.zeros(0), np.zeros(0))
    for c, st in chunks:
        status, bad = build_front(
            0, len(c.active), c.xyz, c.kind, c.ctrl, c.csig, c.rot, c.pt_start, c.nobs,
            c.active, st, c.obs_xy, c.obs_sigma, c.obs_active, fronts.eo, fronts.camera,
            blk.cams, blk.ctrl_mask, a, _EMPTY, rhs, c.max_rays, k, lam, blk.behind_ok, cal,
            bord, *sums, c0, c1, fronts.fixed)
        if status != OK:
            raise _point_error(p, c, bad, status, blk)


#: Points a tiled front's quality takes at a time (the inverse over their stations is
#: gathered from its panels).
TILED_QUALITY_POINTS = 512


def _gathered(z, fronts, k, xw):
    """For :func:`sapgo.quality.points_quality` on a tiled front's inverse ``z``
    (:class:`~sapgo.solve.tiles.Panels`): a function of the chunk's observations giving the
    inverse over the stations they see (gathered), their places in it, orientations,
    cameras and border rows."""
    def take(obs_station, obs_active):
        st, eo, camera, fixed = fronts.numbered(obs_station, obs_active)
        places = np.unique(st[obs_active]) if obs_active.any() else np.zeros(1, np.int64)
        zs = z.gather((k * places[:, None] + np.arange(k)).ravel())
        st = np.ascontiguousarray(np.searchsorted(places, st), dtype=np.int64)
        st[~obs_active] = 0
        return (zs.T, st, np.ascontiguousarray(eo[places]),
                np.ascontiguousarray(camera[places]),
                None if xw is None else np.ascontiguousarray(xw[places]),
                np.ascontiguousarray(fixed[places]))
    return take


def quality_visitor(p, work, blk, opts, tree, sigma0, psig, quality, cov, var, correlations,
                    xb, cal, sig_b, lock):
    """The precision pass's ``on_node(i, z)`` for :meth:`~sapgo.solve.fronts.TreeSolver
    .inverse`: node ``i``'s stations' cofactor blocks into ``cov`` and their diagonals into
    ``var``, its points' standard deviations into ``psig`` and their observations' quality
    into ``quality`` (``correlations``, if any, told the high ones). ``xb``, ``cal``,
    ``sig_b``: self-calibration's ``X = M^-1 B``, border and ``S^-1`` (else None)."""
    from ..quality import in_angles, points_quality

    k = blk.npar
    ng = blk.n_border
    fronts_of = {}   # one numbering of the front's stations per thread

    def my_fronts():
        t = threading.get_ident()
        if t not in fronts_of:
            fronts_of[t] = _Fronts(tree, blk, k)
        return fronts_of[t]

    def on_node(i, z):
        lo, hi = int(tree.lo[i]), int(tree.hi[i])
        tiled = isinstance(z, Panels)
        if tiled:
            blocks = z.diag_blocks(k, 0, hi - lo)
        else:
            blocks = np.empty((hi - lo, k, k))
            for s in range(hi - lo):
                blocks[s] = z[k * s:k * s + k, k * s:k * s + k]
        if ng:
            blocks += np.einsum("sag,gh,sbh->sab", xb[lo:hi], sig_b, xb[lo:hi])
        blocks = in_angles(blocks, blk.eo[lo:hi], blk.fixed[lo:hi])   # (omega, phi, kappa)
        cov[lo:hi] = blocks
        var[lo:hi] = np.diagonal(blocks, axis1=1, axis2=2)
        p0, p1 = int(tree.pt_start[i]), int(tree.pt_start[i + 1])
        if p1 <= p0 or opts.precision != "full":   # (--precision stations: no points)
            return
        fronts = my_fronts()
        fr = fronts.enter(i)
        xw = np.ascontiguousarray(xb[fr]) if ng else None   # by place in the front
        try:
            if tiled:   # a few points at a time, the inverse over their stations gathered
                for a0 in range(p0, p1, TILED_QUALITY_POINTS):
                    a1 = min(p1, a0 + TILED_QUALITY_POINTS)
                    points_quality(p, work, blk, opts, a0, a1, sigma0, psig, quality,
                                   correlations, _gathered(z, fronts, k, xw), 0, None, None,
                                   0, cal, sig_b, lock=lock)
            else:
                zc = z.T   # C order: z is symmetric
                for a0 in range(p0, p1, opts.chunk_points):
                    points_quality(p, work, blk, opts, a0, min(p1, a0 + opts.chunk_points),
                                   sigma0, psig, quality, correlations, zc, 0,
                                   fronts.numbered, xw, 0, cal, sig_b, lock=lock)
        finally:
            fronts.leave()

    return on_node


def tree_quality(p, work, blk, opts, tree, sigma0, psig, quality, cov, correlations):
    """The precision pass on the tree: the selected inversion top-down and, node by node,
    the stations' cofactor blocks (``cov``), the points' standard deviations (``psig``) and
    their observations' quality (``quality``), as :func:`sapgo.quality.quality_sweep` does
    along the band. Self-calibration: the stations' cofactors gain the border's share
    ``X S^-1 X'`` (``X = M^-1 B`` from :meth:`~sapgo.solve.fronts.TreeSolver.border_x`, in
    core, ``S^-1`` the last step's ``blk.border_cov``) and the points' and observations'
    kernel its terms, as on the band. On Dask (``opts.client``) the parts' nodes are
    inverted on their workers (:func:`sapgo.solve.distributed.distributed_quality`).
    Returns the stations' variances (n x k)."""
    k = blk.npar
    n = len(blk.station_ids)
    ng = blk.n_border
    var = np.zeros((n, k))
    client = getattr(opts, "client", None)
    if client is not None:
        from .distributed import worker_addresses

        threads = max(2, len(worker_addresses(client)))
        per, top, _, tile = work_plan(tree, k, opts, threads, blk.held, n, separate=True)
    else:
        per, top, _, tile = work_plan(tree, k, opts, held=blk.held, n_stations=n)
    file = getattr(work, "tree_factor", None)
    if file is None:   # (a resumed run: the factor file of the last step)
        file = FactorFile(work.dir / FACTOR_FILE, factor_layout(tree, k), "r", n_rhs=1 + ng)
    solver = TreeSolver(tree, k, None, file=file, n_border=ng, tile=tile, scratch=work.dir)
    xb = cal = sig_b = None
    if ng:
        xb = solver.border_x(n)
        cal, sig_b = blk.cal, np.ascontiguousarray(blk.border_cov, dtype=np.float64)
    lock = threading.Lock()
    on_node = quality_visitor(p, work, blk, opts, tree, sigma0, psig, quality, cov, var,
                              correlations, xb, cal, sig_b, lock)

    from concurrent.futures import ThreadPoolExecutor

    from ..blas import blas_limits

    if len(per) < 2:
        solver.inverse(on_node)
        return var
    held = solver.inverse(on_node, top) if top else {}
    if client is not None:
        from .distributed import distributed_quality

        distributed_quality(client, p, work, blk, opts, tree, per, held, sigma0, tile, xb,
                            var, correlations)
        return var
    with blas_limits(1), ThreadPoolExecutor(len(per)) as pool:
        jobs = [pool.submit(solver.inverse, on_node,
                            [i for a, b in ranges for i in range(a, b)], held)
                for ranges in per]
        for j in jobs:
            j.result()
    return var
