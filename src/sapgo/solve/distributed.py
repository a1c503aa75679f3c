"""The partition tree's iteration on Dask distributed (docs/theory.md section 4c).

The threaded tree step (:func:`sapgo.solve.tree.tree_step`) deals the tree's independent
subtrees to threads; here the same parts (:func:`sapgo.solve.tree.work_plan`) go to Dask
worker processes, one part to one worker for the whole run (``workers=`` restrictions, the
part's number taken modulo the workers in the order of their addresses). The workers open the
project read-only and the work files on a filesystem shared with the client. An iteration is
three rounds of tasks, one task a part:

- :func:`part_step`: build the part's fronts from its own points, factor them, write their
  records into the factor file ``tree_factor.bin`` at the tree's fixed offsets; return the
  Schur updates the subtree roots pass to the top nodes (dense ``f x f`` blocks with their
  right-hand sides), ``y'y``, the border's sums, the stations' undamped diagonal;
- :func:`part_solve`: the back substitution through the part's nodes, given the top
  stations' corrections; return the part's stations' corrections;
- :func:`part_update`: the part's points back-solved, their coordinates and residuals written
  into the work buffers; return the sums.

The client factors and substitutes through the top nodes and updates their points. A task
only ever reads the state of the last checkpoint and writes at fixed offsets, so running it
again (a worker lost, Dask's retry on another worker) writes the same bytes. Workers unpickle
only what the client sends them, never anything read from a file.

Use: ``Options(client=distributed.Client(...))`` from Python, ``sapgo adjust --workers N``
(a LocalCluster for the run) or ``--scheduler ADDRESS`` from the shell (:func:`cluster`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import sys
import time

import numpy as np

from ..errors import SapgoError

__all__ = ["TRACE", "TRAFFIC", "client_seconds", "cluster", "distributed_quality",
           "distributed_solve", "distributed_step", "distributed_update", "part_solve",
           "note_nodes", "part_quality", "part_solve", "part_step", "part_update",
           "extend_add_tiles", "tile_cuts", "tile_pieces", "tiled_cholesky",
           "tiled_cholesky_dense", "worker_addresses"]

#: Seconds to wait for a scheduler given by its address.
CONNECT_TIMEOUT = 30


def worker_addresses(client):
    """The cluster's worker addresses, sorted (the parts' fixed placement)."""
    workers = sorted(client.scheduler_info()["workers"])
    if not workers:
        raise SapgoError("the Dask cluster has no workers")
    return workers


@contextlib.contextmanager
def cluster(workers=None, scheduler=None, quiet=False):
    """A Dask client for a run: a LocalCluster of ``workers`` processes (one thread each, the
    numba and BLAS threads of each limited to one) or the scheduler at ``scheduler``; the
    dashboard's address is printed on stderr. Yields None when neither is given."""
    if not workers and not scheduler:
        yield None
        return
    try:
        from distributed import Client, LocalCluster
    except ImportError as exc:
        raise SapgoError(f"--workers and --scheduler need Dask distributed ({exc}): "
                         f"pip install 'sapgo[dask]'") from None
    if scheduler:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT)
        except OSError as exc:
            raise SapgoError(f"cannot reach the Dask scheduler at {scheduler}: {exc}") from None
        lc = None
    else:
        import dask

        # a part stays on its worker (no work stealing): its files and, later, its memory
        with dask.config.set({"distributed.scheduler.work-stealing": False}):
            lc = LocalCluster(n_workers=int(workers), threads_per_worker=1, processes=True,
                              dashboard_address=":0",
                              env={"NUMBA_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1",
                                   "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"})
        client = Client(lc)
    try:
        if not quiet:
            sys.stderr.write(f"sapgo: Dask cluster of {len(worker_addresses(client))} "
                             f"workers; dashboard {client.dashboard_link}\n")
        yield client
    finally:
        client.close()
        if lc is not None:
            lc.close()


class _NoBar:
    def update(self, n):
        pass


#: The Dask event topic on which the workers report their points done (the client's
#: progress bars: :class:`_Forwarded`).
TOPIC = "sapgo-progress"


class _Progress:
    """A worker's progress bar: the points done sent to the client as Dask events (at most
    one every ``every`` seconds) under the round's ``key``."""

    def __init__(self, key, every=0.5):
        self.key, self.every = key, every
        self.n = 0
        self.t = time.monotonic()

    def update(self, n):
        self.n += int(n)
        if time.monotonic() - self.t >= self.every:
            self.flush()

    def flush(self):
        if self.n:
            try:
                from distributed import get_worker

                get_worker().log_event(TOPIC, {"key": self.key, "n": self.n})
            except ValueError:   # (not on a worker)
                pass
            self.n = 0
        self.t = time.monotonic()


class _Forwarded:
    """The workers' progress events of a round into the client's ``bar``; :meth:`finish`
    then counts what the events did not (the last ones may arrive after the results)."""

    def __init__(self, client, bar):
        import threading
        import uuid

        self.client, self.bar = client, bar
        self.key = uuid.uuid4().hex
        self.n = 0
        self.open = True
        self.lock = threading.Lock()

    def _handler(self, event):
        msg = event[1] if isinstance(event, (tuple, list)) else event
        if isinstance(msg, dict) and msg.get("key") == self.key:
            with self.lock:
                if self.open:
                    self.n += int(msg["n"])
                    self.bar.update(int(msg["n"]))

    def __enter__(self):
        self.client.subscribe_topic(TOPIC, self._handler)
        return self

    def __exit__(self, *exc):
        with self.lock:
            self.open = False
        self.client.unsubscribe_topic(TOPIC)

    def finish(self, total):
        with self.lock:
            self.open = False
            rest = total - self.n
        if rest > 0:
            self.bar.update(rest)


def part_step(path, work_dir, band_width, state, blk, opts, tree, plan, w, lam, iteration,
              tile, trace=False, progress=None):
    """On a worker: build and eliminate part ``w`` of ``plan`` (``(per, top)``) and write its
    nodes' factor records into ``work_dir/tree_factor.bin``. Returns what the client needs
    for the top nodes and the step (a dict of arrays; with ``trace`` each node's seconds,
    :attr:`~sapgo.solve.fronts.TreeSolver.trace`). ``progress``: the key under which its
    points done go to the client's bar (:class:`_Progress`)."""
    from ..blas import blas_limits
    from ..project import Project
    from ..work import Work
    from .fronts import FactorFile, TreeSolver, factor_layout
    from .tiles import Panels
    from .tree import FACTOR_FILE, _run_nodes

    per, top = plan
    k, ng = blk.npar, blk.n_border
    n = len(blk.station_ids)
    t0 = time.perf_counter()
    with Project(path, "r") as p:
        work = Work(work_dir, p, band_width, create=False, block=k, n_border=ng)
        work.state = state
        file = FactorFile(work.dir / FACTOR_FILE, factor_layout(tree, k), n_rhs=1 + ng)
        try:
            solver = TreeSolver(tree, k, None, opts.pivot_tolerance, file=file, n_border=ng,
                                tile=tile, scratch=work.dir)
            solver.set_parts(per, top)
            solver.trace = {} if trace else None
            diag = np.zeros((n, k)) if lam > 0.0 else None
            cb = (np.zeros((ng, ng)), np.zeros(ng), np.zeros(ng))
            seconds = np.zeros(len(per) + 1)
            bar = _Progress(progress) if progress else _NoBar()
            with blas_limits(1):
                _run_nodes(p, work, blk, opts, tree, solver, per[w], lam, diag, seconds, w,
                           iteration, bar, None, cb)
            if progress:
                bar.flush()
            # the subtree roots' updates for the top nodes: in core, or (larger than a
            # panel) their scratch files in the shared work directory, handed over by name
            updates = {int(i): v for i, v in solver.updates.items()}
            for u, _ in updates.values():
                if isinstance(u, Panels):
                    os.close(u._fd)   # (the file stays: the client opens and removes it)
                    u._fd = None
        finally:
            file.close()
            work.close()
    nodes = np.concatenate([np.arange(a, b) for a, b in per[w]])
    return {"updates": updates, "nodes": nodes, "yy": solver.yy[nodes],
            "ww": solver._ww[w], "wy": solver._wy[w], "diag": diag, "border": cb,
            "solver_seconds": float(seconds[w]), "trace": solver.trace,
            "seconds": time.perf_counter() - t0}


def distributed_step(p, work, blk, opts, tree, solver, per, top, lam, iteration, bar=None):
    """The workers' parts of a tree step on ``opts.client``: each part's task pinned to its
    worker; their results put into ``solver`` (updates for the top nodes, ``y'y``, the
    border's sums), their points done counted into ``bar`` as they go. Returns ``(diags,
    border sums, seconds)`` per part as the threaded step's."""
    client = opts.client
    wopts = dataclasses.replace(opts, client=None, progress=False)
    # the project's path, the work directory and the block (its stations' orientations:
    # 48 bytes a station) travel once a step; the tree's arrays are scattered once a run
    # and kept by the workers
    tree_f = getattr(work, "_tree_future", None)
    if tree_f is None or getattr(work, "_tree_id", None) is not tree:
        _count(*[tree] * len(worker_addresses(client)), key="to_workers")   # (to each)
        tree_f = client.scatter(tree, broadcast=True)
        work._tree_future, work._tree_id = tree_f, tree
    wblk = dataclasses.replace(blk, tree=None)   # (the tree is on the workers already)
    work._dask_plan = (per, top)
    if TRACE["on"]:
        TRACE["plan"] = ([list(r) for r in per], [int(i) for i in top])
    with _Forwarded(client, bar or _NoBar()) as fw:
        results = _round(client, "step", part_step,
                         [(str(p.path), str(work.dir), work.band_width, work.state, wblk,
                           wopts, tree_f, (per, top), w, lam, iteration, solver.tile,
                           TRACE["on"], fw.key)
                          for w in range(len(per))])
    pt = tree.pt_start
    fw.finish(sum(int(pt[b] - pt[a]) for r in per for a, b in r))
    diags, cbs = [], []
    # the solver's seconds of each worker (its parts one after the other): the busiest one
    # counts, as the busiest thread's does in the threaded step
    seconds = [0.0] * len(per)
    n_workers = len(worker_addresses(client))
    for w, r in enumerate(results):
        solver.updates.update(r["updates"])
        solver.yy[r["nodes"]] = r["yy"]
        solver._ww[w] = r["ww"]
        solver._wy[w] = r["wy"]
        diags.append(r["diag"])
        cbs.append(r["border"])
        seconds[w % n_workers] += r["solver_seconds"]
        note_nodes(r["trace"])
    return diags, cbs, seconds


#: Bytes this process sent to and received from the workers (the pickled arguments and
#: results of the tasks), counted while ``TRAFFIC["on"]`` (benchmarks/distributed.py).
TRAFFIC = {"on": False, "to_workers": 0, "from_workers": 0, "tasks": 0}

#: While ``TRACE["on"]``: each node's seconds (``nodes``: node -> (seconds from opening its
#: front to the end of its elimination, seconds of the elimination), wherever it ran), each
#: round of tasks (``rounds``: its kind, the client's seconds from submitting to having
#: every result, and per task its part, its seconds on the worker, the bytes of its
#: arguments and of its result) and the client's own work between the rounds (``client``:
#: seconds per kind, summed over the run): the input of the scale-out replay
#: (:mod:`sapgo.solve.scaleout`, benchmarks/distributed.py).
TRACE = {"on": False, "nodes": {}, "rounds": [], "client": {}}


def _size(*objs):
    import pickle

    from distributed import Future

    return sum(len(pickle.dumps(o, protocol=5)) for o in objs if not isinstance(o, Future))


def _count(*objs, key):
    if TRAFFIC["on"]:
        TRAFFIC[key] += _size(*objs)


def client_seconds(kind, seconds):
    """Add the client's ``seconds`` of ``kind`` to the trace (while it is on)."""
    if TRACE["on"]:
        TRACE["client"][kind] = TRACE["client"].get(kind, 0.0) + seconds


def note_nodes(trace):
    """Add a step's node seconds (:attr:`~sapgo.solve.fronts.TreeSolver.trace`) to the
    trace: each node's list over the iterations."""
    if TRACE["on"] and trace:
        for i, v in trace.items():
            TRACE["nodes"].setdefault(int(i), []).append(tuple(v))


def _round(client, kind, fn, args):
    """``fn(*args[w])`` on part ``w``'s worker for every part; the results in order.
    Every task returns a dict with its ``seconds``."""
    t0 = time.perf_counter()
    futures, sent = [], []
    for w, a in enumerate(args):
        n_in = _size(*a) if TRAFFIC["on"] or TRACE["on"] else 0
        sent.append(n_in)
        if TRAFFIC["on"]:
            TRAFFIC["to_workers"] += n_in
        TRAFFIC["tasks"] += 1
        futures.append(client.submit(fn, *a, **_pinned(client, w)))
    out = client.gather(futures)
    wall = time.perf_counter() - t0
    got = [_size(r) for r in out] if TRAFFIC["on"] or TRACE["on"] else [0] * len(out)
    if TRAFFIC["on"]:
        TRAFFIC["from_workers"] += sum(got)
    if TRACE["on"]:
        TRACE["rounds"].append({"kind": kind, "wall_s": wall, "tasks": [
            {"part": w, "seconds": float(r["seconds"]), "bytes_in": sent[w],
             "bytes_out": got[w]} for w, r in enumerate(out)]})
    return out


def _pinned(client, w):
    addresses = worker_addresses(client)
    return {"workers": [addresses[w % len(addresses)]], "allow_other_workers": True,
            "pure": False}   # (a lost worker: the scheduler runs the task again)


def part_solve(work_dir, tree, k, ng, x, ranges, theta, tile):
    """On a worker: the back substitution of its part's nodes (``ranges``) from the factor
    file, ``x`` holding the top nodes' stations; returns the part's stations' rows of ``x``
    per range (``rows``) and the task's ``seconds``."""
    from pathlib import Path

    from ..blas import blas_limits
    from .fronts import FactorFile, TreeSolver, factor_layout
    from .tree import FACTOR_FILE

    t0 = time.perf_counter()
    file = FactorFile(Path(work_dir) / FACTOR_FILE, factor_layout(tree, k), "r", n_rhs=1 + ng)
    try:
        solver = TreeSolver(tree, k, None, file=file, n_border=ng, tile=tile,
                            scratch=Path(work_dir))
        nodes = sorted((i for a, b in ranges for i in range(a, b)), reverse=True)
        with blas_limits(1):
            solver.back_substitute(x, nodes, theta)
    finally:
        file.close()
    return {"rows": [x[k * int(tree.lo[a]):k * int(tree.hi[b - 1])] for a, b in ranges],
            "seconds": time.perf_counter() - t0}


def distributed_solve(client, work, tree, solver, n, theta, per, top):
    """``delta`` (n x k): the top nodes' back substitution here, then each part's on its
    worker (the stations' corrections travel, 8 k bytes a station each way)."""
    k, ng = solver.k, solver.n_border
    x = np.zeros(k * n)
    t0 = time.perf_counter()
    solver.back_substitute(x, sorted(top, reverse=True), theta)
    client_seconds("back", time.perf_counter() - t0)
    tree_f = work._tree_future
    results = _round(client, "back", part_solve,
                     [(str(work.dir), tree_f, k, ng, x, per[w], theta, solver.tile)
                      for w in range(len(per))])
    for w, res in enumerate(results):
        for (a, b), r in zip(per[w], res["rows"]):
            x[k * int(tree.lo[a]):k * int(tree.hi[b - 1])] = r
    return x.reshape(n, k)


def part_update(path, work_dir, band_width, state, blk, opts, delta, ranges, cams_new, lam,
                dtheta, iteration, progress=None):
    """On a worker: :func:`sapgo.adjust.update_range` of its part's points (``ranges``),
    their new coordinates and residuals into the shared work buffers; returns the sums
    (``stats``, ``robust``) and the task's ``seconds``."""
    from ..adjust import update_range
    from ..project import Project
    from ..work import Work

    t0 = time.perf_counter()
    stats, robust = np.zeros(11), np.zeros(2, np.int64)
    with Project(path, "r") as p:
        work = Work(work_dir, p, band_width, create=False, block=blk.npar,
                    n_border=blk.n_border)
        work.state = state
        try:
            bar = _Progress(progress) if progress else None
            for a, b in ranges:
                update_range(p, work, blk, delta, opts, a, b, stats, robust, cams_new, lam,
                             dtheta, iteration, bar)
            if bar is not None:
                bar.flush()
        finally:
            work.close()
    return {"stats": stats, "robust": robust, "seconds": time.perf_counter() - t0}


def distributed_update(p, work, blk, delta, opts, iteration, lam, dtheta, cams_new, stats,
                       stats_robust, bar=None):
    """The point update of each part's points on its worker (:func:`part_update`); their
    sums added into ``stats`` and ``stats_robust``, their points counted into ``bar`` as
    they go. Returns the point ranges done."""
    client = opts.client
    per, top = work._dask_plan
    pt = blk.tree.pt_start
    wopts = dataclasses.replace(opts, client=None, progress=False)
    wblk = dataclasses.replace(blk, tree=None)
    ranges = [[(int(pt[a]), int(pt[b])) for a, b in per[w]] for w in range(len(per))]
    with _Forwarded(client, bar or _NoBar()) as fw:
        results = _round(client, "update", part_update,
                         [(str(p.path), str(work.dir), work.band_width, work.state, wblk,
                           wopts, delta, ranges[w], cams_new, lam, dtheta, iteration, fw.key)
                          for w in range(len(per))])
    fw.finish(sum(b - a for rr in ranges for a, b in rr))
    for res in results:
        st, rb = res["stats"], res["robust"]
        stats[5] = max(stats[5], st[5])
        st[5] = 0.0
        stats += st
        stats_robust += rb
    return [r for rr in ranges for r in rr]


def part_quality(path, work_dir, band_width, state, blk, opts, tree, ranges, held, sigma0,
                 tile, xb, threshold):
    """On a worker: the precision pass of its part's nodes (``ranges``): their selected
    inversion from the factor file, ``held`` giving the inverse over the part's subtree
    roots' boundaries (computed by the client over the top nodes); the stations' cofactor
    blocks, the points' standard deviations and the observations' quality written into the
    shared work files (``cov.bin``, ``point_sigma.bin``, ``quality.bin``). Returns the
    stations' variances per range (``var``), the high correlations found (``correlations``,
    a :class:`~sapgo.report.HighCorrelations` or None) and the task's ``seconds``."""
    from ..blas import blas_limits
    from ..project import Project
    from ..quality import QUALITY_COLUMNS
    from ..rawfile import RawArray
    from ..report import HighCorrelations
    from ..work import Work
    from .fronts import FactorFile, TreeSolver, factor_layout
    from .tree import FACTOR_FILE, quality_visitor

    t0 = time.perf_counter()
    k, ng = blk.npar, blk.n_border
    n = len(blk.station_ids)
    var = np.zeros((n, k))
    correlations = HighCorrelations(threshold) if threshold is not None else None
    with Project(path, "r") as p:
        work = Work(work_dir, p, band_width, create=False, block=k, n_border=ng)
        work.state = state
        files = []
        try:
            d = work.dir
            psig = RawArray(d / "point_sigma.bin", (p.n_points, 3))
            files.append(psig)
            quality = RawArray(d / "quality.bin", (p.n_observations, len(QUALITY_COLUMNS)))
            files.append(quality)
            cov = RawArray(d / "cov.bin", (n, k, k))
            files.append(cov)
            file = FactorFile(d / FACTOR_FILE, factor_layout(tree, k), "r", n_rhs=1 + ng)
            files.append(file)
            solver = TreeSolver(tree, k, None, file=file, n_border=ng, tile=tile, scratch=d)
            cal = sig_b = None
            if ng:
                cal, sig_b = blk.cal, np.ascontiguousarray(blk.border_cov, dtype=np.float64)
            on_node = quality_visitor(p, work, blk, opts, tree, sigma0, psig, quality, cov,
                                      var, correlations, xb, cal, sig_b, None)
            with blas_limits(1):
                solver.inverse(on_node, [i for a, b in ranges for i in range(a, b)], held)
        finally:
            for f in files:
                f.close()
            work.close()
    return {"var": [var[int(tree.lo[a]):int(tree.hi[b - 1])] for a, b in ranges],
            "correlations": correlations, "seconds": time.perf_counter() - t0}


def distributed_quality(client, p, work, blk, opts, tree, per, held, sigma0, tile, xb, var,
                        correlations):
    """The precision pass of each part on its worker (:func:`part_quality`), the client
    having inverted the top nodes (``held``: the inverses over the parts' subtree roots'
    boundaries); their stations' variances into ``var``, their high correlations added to
    ``correlations``."""
    wopts = dataclasses.replace(opts, client=None, progress=False)
    wblk = dataclasses.replace(blk, tree=None)
    tree_f = getattr(work, "_tree_future", None)
    if tree_f is None or getattr(work, "_tree_id", None) is not tree:
        tree_f = client.scatter(tree, broadcast=True)   # (a resumed run: not sent yet)
        work._tree_future, work._tree_id = tree_f, tree
    threshold = correlations.threshold if correlations is not None else None
    args = []
    for ranges in per:
        mine = {i: z for i, z in held.items()
                if any(a <= i < b for a, b in ranges)}   # (the part's subtree roots)
        args.append((str(p.path), str(work.dir), work.band_width, work.state, wblk, wopts,
                     tree_f, ranges, mine, sigma0, tile, xb, threshold))
    for w, res in enumerate(_round(client, "quality", part_quality, args)):
        for (a, b), v in zip(per[w], res["var"]):
            var[int(tree.lo[a]):int(tree.hi[b - 1])] = v
        if correlations is not None:
            theirs = res["correlations"]
            for what, counts in theirs.counts.items():
                for name, c in counts.items():
                    correlations.counts[what][name] += c
            correlations.largest.extend(theirs.largest)
            correlations.largest.sort(key=lambda e: -abs(e["rho"]))
            del correlations.largest[correlations.listed:]



# -- a front factored tile by tile across the workers -----------------------------------
#
# The building block of the top fronts tiled across workers (the design the scale-out replay
# simulates, :func:`sapgo.solve.scaleout.tiled_graph`): the same cuts, kernels, placement
# and dependencies, here as Dask tasks whose data Dask moves between the workers.

def tile_cuts(m, n, tile):
    """Row ranges of a front of ``n`` rows whose first ``m`` are eliminated: the own rows,
    then the boundary rows, each cut in tiles of at most ``tile`` rows."""
    return ([(a, min(a + tile, m)) for a in range(0, m, tile)] +
            [(a, min(a + tile, n)) for a in range(m, n, tile)])


def tile_pieces(rows, cols, cuts):
    """Where a block lands in a front's tiles: ``rows`` and ``cols`` (ascending places in
    the front of the block's rows and columns; a child's update has ``rows is cols``, its
    boundary's places) against the tiles' row ranges ``cuts``. Returns ``{(a, b): (r, c)}``
    for the lower tiles ``a >= b`` it touches, ``r`` and ``c`` the block's row and column
    indices landing in tile ``(a, b)``."""
    starts = np.array([c0 for c0, _ in cuts])
    tr = np.searchsorted(starts, rows, side="right") - 1
    tc = tr if cols is rows else np.searchsorted(starts, cols, side="right") - 1
    by_r = {int(a): np.flatnonzero(tr == a) for a in np.unique(tr)}
    by_c = by_r if cols is rows else {int(b): np.flatnonzero(tc == b) for b in np.unique(tc)}
    return {(a, b): (r, c) for a, r in by_r.items() for b, c in by_c.items() if b <= a}


def _t_take(u, r, c):
    return np.ascontiguousarray(u[np.ix_(r, c)])


def _t_add(tile, r0, c0, *pieces):
    """``tile`` (rows from ``r0``, columns from ``c0`` of the front) plus the pieces
    ``(rows, cols, block)`` (places in the front)."""
    out = np.array(tile, copy=True)
    for rows, cols, block in pieces:
        out[np.ix_(rows - r0, cols - c0)] += block
    return out


def extend_add_tiles(client, tiles, cuts, updates):
    """The children's Schur updates added into a front's tiles as Dask tasks: ``updates``
    a list of ``(u, places)`` (``u`` an array or a future on the child's worker, ``places``
    its rows' places in the front); each tile's piece cut out where the update is
    (:func:`tile_pieces`, so that only the piece travels) and added on the tile's worker.
    Returns the tiles (futures where something was added)."""
    where = _tile_places(client)
    out = dict(tiles)
    adds = {}
    for u, places in updates:
        places = np.asarray(places)
        for (a, b), (r, c) in tile_pieces(places, places, cuts).items():
            piece = client.submit(_t_take, u, r, c, pure=False)
            adds.setdefault((a, b), []).append((places[r], places[c], piece))
    for (a, b), pieces in adds.items():   # (Dask resolves the futures in the tuples)
        out[(a, b)] = client.submit(_t_add, out[(a, b)], cuts[a][0], cuts[b][0], *pieces,
                                    **where(a, b))
    return out


def _tile_places(client):
    """``where(i, j)``: the submit options placing tile ``(i, j)``'s tasks on one worker,
    2-D block-cyclic over the cluster's workers (a grid as square as their number)."""
    addresses = worker_addresses(client)
    w = len(addresses)
    r = int(np.sqrt(w))
    while w % r:
        r -= 1
    c = w // r

    def where(i, j):
        return {"workers": [addresses[(i % r) * c + (j % c)]], "allow_other_workers": True,
                "pure": False}

    return where


def _t_potrf(a, first):
    import scipy.linalg

    try:
        return scipy.linalg.cholesky(a, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        # the first row whose pivot fails
        for j in range(1, a.shape[0] + 1):
            try:
                np.linalg.cholesky(a[:j, :j])
            except np.linalg.LinAlgError:
                raise ValueError(f"non-positive pivot at row {first + j - 1}") from None
        raise


def _t_trsm(a, low):
    import scipy.linalg

    return scipy.linalg.solve_triangular(low, a.T, lower=True, check_finite=False).T


def _t_update(a, x, y):
    return a - x @ y.T


def tiled_cholesky(client, tiles, cuts, mt):
    """The partial Cholesky of a symmetric front given as its lower tiles ``tiles[(i, j)]``
    (``i >= j``; arrays or futures) over the row ranges ``cuts`` (:func:`tile_cuts`), the
    first ``mt`` of them eliminated, as Dask tasks: each tile's tasks on one worker, 2-D
    block-cyclic over the cluster's workers (``potrf`` of a diagonal tile, ``trsm`` of the
    tiles below it, ``syrk`` / ``gemm`` of the trailing tiles, right-looking). Returns the
    tiles' futures: ``L`` in the first ``mt`` tile columns, the Schur complement (the
    update for the parent, lower tiles) in the others."""
    where = _tile_places(client)
    cur = dict(tiles)
    nt = len(cuts)
    for k in range(mt):
        cur[(k, k)] = client.submit(_t_potrf, cur[(k, k)], cuts[k][0], **where(k, k))
        for i in range(k + 1, nt):
            cur[(i, k)] = client.submit(_t_trsm, cur[(i, k)], cur[(k, k)], **where(i, k))
        for j in range(k + 1, nt):
            for i in range(j, nt):
                cur[(i, j)] = client.submit(_t_update, cur[(i, j)], cur[(i, k)],
                                            cur[(j, k)], **where(i, j))
    return cur


def tiled_cholesky_dense(client, a, m, tile):
    """:func:`tiled_cholesky` of the dense symmetric ``a`` (its lower triangle), ``m``
    rows eliminated: ``(L, S)`` with ``L`` the ``n x m`` factor columns and ``S`` the
    Schur complement ``A22 - L21 L21'`` (lower triangle; tests and benchmarks)."""
    n = a.shape[0]
    cuts = tile_cuts(m, n, tile)
    mt = sum(1 for a0, _ in cuts if a0 < m)
    tiles = {(i, j): np.ascontiguousarray(a[cuts[i][0]:cuts[i][1], cuts[j][0]:cuts[j][1]])
             for i in range(len(cuts)) for j in range(i + 1)}
    out = client.gather(tiled_cholesky(client, tiles, cuts, mt))
    low = np.zeros((n, m))
    s = np.zeros((n - m, n - m))
    for (i, j), t in out.items():
        (r0, r1), (c0, c1) = cuts[i], cuts[j]
        if j < mt:
            low[r0:r1, c0:c1] = np.tril(t) if i == j else t
        else:
            s[r0 - m:r1 - m, c0 - m:c1 - m] = t
    return low, np.tril(s)
