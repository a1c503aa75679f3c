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
import sys
import time

import numpy as np
from numba import njit

from ..errors import SapgoError

__all__ = ["TRACE", "TRAFFIC", "client_seconds", "cluster", "distributed_quality",
           "distributed_report", "distributed_solve", "distributed_step", "distributed_top",
           "distributed_update", "part_report",
           "note_nodes", "part_quality", "part_solve", "part_step", "part_update",
           "extend_add_tiles", "tile_cuts", "tile_grid", "tile_pieces", "tiled_cholesky",
           "tiled_cholesky_dense", "worker_addresses"]

#: Seconds to wait for a scheduler given by its address.
CONNECT_TIMEOUT = 30


def worker_addresses(client):
    """The cluster's worker addresses, sorted (the parts' fixed placement). Asked of the
    scheduler directly (``nthreads``): ``Client.scheduler_info()`` returns a cache that the
    client's periodic refresh can overwrite with an empty worker list between its fetch and
    its return."""
    workers = sorted(client.nthreads())
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

        # a part stays on its worker (no work stealing): its files and, later, its memory;
        # the inputs scattered to every worker (the tree, the block) keep their copies: the
        # active memory manager would drop all but one, and a worker killed then would take
        # the only copy with it (its tasks could not be run again elsewhere)
        with dask.config.set({"distributed.scheduler.work-stealing": False,
                              "distributed.scheduler.active-memory-manager.start": False}):
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
    from .fronts import FactorFile, TreeSolver, factor_layout
    from .tree import FACTOR_FILE, _run_nodes

    per, top = plan
    k, ng = blk.npar, blk.n_border
    n = len(blk.station_ids)
    t0 = time.perf_counter()
    with _OnWorker(path, work_dir, band_width, state, blk) as (p, work):
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
            # panel) their scratch files in the shared work directory; they stay here
            # until the top's tasks take their pieces (:func:`distributed_top`)
            updates = {int(i): v for i, v in solver.updates.items()}
        finally:
            file.close()
    nodes = np.concatenate([np.arange(a, b) for a, b in per[w]])
    return {"updates": updates, "update_nodes": sorted(updates), "nodes": nodes,
            "yy": solver.yy[nodes],
            "ww": solver._ww[w], "wy": solver._wy[w], "diag": diag, "border": cb,
            "solver_seconds": float(seconds[w]), "trace": solver.trace,
            "seconds": time.perf_counter() - t0}


def distributed_step(p, work, blk, opts, tree, solver, per, top, lam, iteration, bar=None):
    """The workers' parts of a tree step on ``opts.client``: each part's task pinned to its
    worker; their results put into ``solver`` (``y'y``, the border's sums), their points
    done counted into ``bar`` as they go; the parts' futures, whose updates for the top
    nodes stay on the workers, in ``work._dask_parts`` (:func:`distributed_top`). Returns
    ``(diags, border sums, seconds)`` per part as the threaded step's."""
    client = opts.client
    wopts = dataclasses.replace(opts, client=None, progress=False)
    # the block (its stations' orientations and their vectors) goes to each worker once a
    # step, for the parts' and the top's tasks; the tree's arrays are scattered once a run
    # and kept by the workers
    tree_f = getattr(work, "_tree_future", None)
    n_workers = len(worker_addresses(client))
    if (tree_f is None or getattr(work, "_tree_id", None) is not tree
            or tree_f.status != "finished"):   # (lost with a worker: sent again)
        _count(*[tree] * n_workers, key="to_workers")   # (to each)
        tree_f = client.scatter(tree, broadcast=True)
        work._tree_future, work._tree_id = tree_f, tree
    wblk = dataclasses.replace(blk, tree=None)   # (the tree is on the workers already)
    _count(*[wblk] * n_workers, key="to_workers")
    wblk = work._blk_future = client.scatter(wblk, broadcast=True)
    work._dask_plan = (per, top)
    if TRACE["on"]:
        TRACE["plan"] = ([list(r) for r in per], [int(i) for i in top])
    with _Forwarded(client, bar or _NoBar()) as fw:
        results, futures = _round(
            client, "step", part_step,
            [(str(p.file_path), str(work.dir), work.band_width, work.state, wblk, wopts, tree_f,
              (per, top), w, lam, iteration, solver.tile, TRACE["on"], fw.key)
             for w in range(len(per))], keep=True)
    work._dask_parts = [(f, r["update_nodes"]) for f, r in zip(futures, results)]
    pt = tree.pt_start
    fw.finish(sum(int(pt[b] - pt[a]) for r in per for a, b in r))
    diags, cbs = [], []
    # the solver's seconds of each worker (its parts one after the other): the busiest one
    # counts, as the busiest thread's does in the threaded step
    seconds = [0.0] * len(per)
    for w, r in enumerate(results):
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


def _round(client, kind, fn, args, keep=False):
    """``fn(*args[w])`` on part ``w``'s worker for every part; the results in order.
    Every task returns a dict with its ``seconds``. ``keep``: the results without their
    ``updates`` (:func:`_strip`) and the futures, whose updates stay on the workers."""
    t0 = time.perf_counter()
    futures, sent = [], []
    for w, a in enumerate(args):
        n_in = _size(*a) if TRAFFIC["on"] or TRACE["on"] else 0
        sent.append(n_in)
        if TRAFFIC["on"]:
            TRAFFIC["to_workers"] += n_in
        TRAFFIC["tasks"] += 1
        futures.append(client.submit(fn, *a, **_pinned(client, w)))
    if keep:
        out = client.gather([client.submit(_strip, f, **_pinned(client, w))
                             for w, f in enumerate(futures)])
    else:
        out = client.gather(futures)
    wall = time.perf_counter() - t0
    got = [_size(r) for r in out] if TRAFFIC["on"] or TRACE["on"] else [0] * len(out)
    if TRAFFIC["on"]:
        TRAFFIC["from_workers"] += sum(got)
    if TRACE["on"]:
        TRACE["rounds"].append({"kind": kind, "wall_s": wall, "tasks": [
            {"part": w, "seconds": float(r["seconds"]), "bytes_in": sent[w],
             "bytes_out": got[w]} for w, r in enumerate(out)]})
    return (out, futures) if keep else out


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

    t0 = time.perf_counter()
    stats, robust = np.zeros(11), np.zeros(2, np.int64)
    with _OnWorker(path, work_dir, band_width, state, blk) as (p, work):
        bar = _Progress(progress) if progress else None
        for a, b in ranges:
            update_range(p, work, blk, delta, opts, a, b, stats, robust, cams_new, lam,
                         dtheta, iteration, bar)
        if bar is not None:
            bar.flush()
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
                         [(str(p.file_path), str(work.dir), work.band_width, work.state, wblk,
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
    from ..quality import QUALITY_COLUMNS
    from ..rawfile import RawArray
    from ..report import HighCorrelations
    from .fronts import FactorFile, TreeSolver, factor_layout
    from .tree import FACTOR_FILE, quality_visitor

    t0 = time.perf_counter()
    k, ng = blk.npar, blk.n_border
    n = len(blk.station_ids)
    var = np.zeros((n, k))
    correlations = HighCorrelations(threshold) if threshold is not None else None
    with _OnWorker(path, work_dir, band_width, state, blk) as (p, work):
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
        args.append((str(p.file_path), str(work.dir), work.band_width, work.state, wblk, wopts,
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



def part_report(path, work_dir, band_width, state, blk, opts, ranges, precision):
    """On a worker: the report's sums (:class:`sapgo.adjust.ReportSums`) over its part's
    points (``ranges``) and their observations, the quality read from the shared work
    files (``precision``). Returns ``{"sums", "seconds"}``."""
    from ..adjust import ReportSums
    from ..quality import QUALITY_COLUMNS
    from ..rawfile import RawArray
    from ..report import reliability_statistics

    t0 = time.perf_counter()
    with _OnWorker(path, work_dir, band_width, state, blk) as (p, work):
        quality = (RawArray(work.dir / "quality.bin", (p.n_observations, len(QUALITY_COLUMNS)))
                   if precision else None)
        try:
            sums = ReportSums(p, blk, opts, reliability_statistics(opts.snooping_alpha)
                              if precision else None)
            for a, b in ranges:
                sums.add(p, blk, opts, work.xyz_current, quality, a, b)
        finally:
            if quality is not None:
                quality.close()
    return {"sums": sums.travel(), "seconds": time.perf_counter() - t0}


def distributed_report(client, p, work, blk, opts, sums):
    """The report's sums of each part's points on its worker (:func:`part_report`), added
    into ``sums``. Returns the point ranges left to the client (the top nodes')."""
    per, top = work._dask_plan
    pt = blk.tree.pt_start
    wopts = dataclasses.replace(opts, client=None, progress=False)
    wblk = dataclasses.replace(blk, tree=None)
    ranges = [[(int(pt[a]), int(pt[b])) for a, b in r] for r in per]
    results = _round(client, "report", part_report,
                     [(str(p.file_path), str(work.dir), work.band_width, work.state, wblk, wopts,
                       ranges[w], sums.reliability is not None) for w in range(len(per))])
    for res in results:
        sums.merge(res["sums"])
    return [(int(pt[i]), int(pt[i + 1])) for i in sorted(top)]


# -- a front factored tile by tile across the workers -----------------------------------
#
# The building block of the top fronts tiled across workers (the design the scale-out replay
# simulates, :func:`sapgo.solve.scaleout.tiled_graph`): the same cuts, kernels, placement
# and dependencies, here as Dask tasks whose data Dask moves between the workers.

def tile_cuts(m, n, tile, unit=1):
    """Row ranges of a front of ``n`` rows whose first ``m`` are eliminated: the own rows,
    then the boundary rows, each cut in as few tiles of at most ``tile`` rows as it needs,
    of equal size in whole ``unit`` (a station's parameters; ``tile`` a multiple of it),
    the last no longer than the others: 2 100 rows in tiles of 2 048 are two of 1 050, not
    2 048 and a sliver that would leave one worker the whole of the work."""
    tile = max(unit, unit * (tile // unit))
    out = []
    for a0, a1 in ((0, m), (m, n)):
        q = -(-(a1 - a0) // tile)
        size = unit * -(-(a1 - a0) // (unit * q)) if q else 0
        out += [(a, min(a + size, a1)) for a in range(a0, a1, size or 1)]
    return out


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


def _t_add(tile, r0, c0, *pieces):
    """``tile`` (rows from ``r0``, columns from ``c0`` of the front) plus the pieces
    ``(rows, cols, block)`` (places in the front; :func:`_add_lower`)."""
    out = np.array(tile, copy=True, order="F")
    for rows, cols, block in pieces:
        _add_lower(out, r0, c0, rows, cols, block)
    return out


@njit(cache=True, nogil=True)
def _add_lower(out, r0, c0, rows, cols, block):
    """``out[rows - r0, cols - c0] += block`` where the front's row is not above its column:
    an update's strict upper triangle is not set (its diagonal blocks are in full; the rest
    may be anything, NaN included)."""
    for j in range(len(cols)):
        c = cols[j]
        for i in range(len(rows)):
            if rows[i] >= c:
                out[rows[i] - r0, c - c0] += block[i, j]


def extend_add_tiles(client, tiles, cuts, updates):
    """The children's Schur updates added into a front's tiles as Dask tasks: ``updates``
    a list of ``(u, places)`` (``u`` an array or a future on the child's worker, ``places``
    its rows' places in the front); each tile's piece cut out where the update is
    (:func:`tile_pieces`, so that only the piece travels) and added on the tile's worker.
    Returns the tiles (futures where something was added)."""
    blocks = [(np.asarray(pl), np.asarray(pl), u, None, None) for u, pl in updates]
    return _add_blocks(client, tiles, cuts, blocks, _tile_places(client))


def tile_grid(n):
    """``(rows, cols)`` of the grid of ``n`` workers a front's tiles are dealt over, as
    square as ``n`` allows, the longer side down the rows: the tiles below a diagonal tile
    (one column, factored after it, ``trsm``) go to as many workers as there are rows."""
    c = int(np.sqrt(n))
    while n % c:
        c -= 1
    return n // c, c


def _tile_places(client):
    """``where(i, j)``: the submit options placing tile ``(i, j)``'s tasks on one worker,
    2-D block-cyclic over the cluster's workers (:func:`tile_grid`)."""
    addresses = worker_addresses(client)
    r, c = tile_grid(len(addresses))

    def where(i, j):
        return {"workers": [addresses[(i % r) * c + (j % c)]], "allow_other_workers": True,
                "pure": False}

    return where


def _t_potrf(a, first, orig=None, tol=0.0, base=(0, 1)):
    """``chol(a)`` (lower) of a diagonal tile whose first row is the front's ``first``;
    with ``orig`` (its diagonal as assembled) the band solver's pivot test (a pivot, the
    squared diagonal of the factor, at or below ``tol`` times it fails). A failure raises
    :class:`TilePivotError` naming the front's row (``base``: the front's first station and
    the parameters a station)."""
    import scipy.linalg

    try:
        low = scipy.linalg.cholesky(a, lower=True, check_finite=False)
    except np.linalg.LinAlgError:
        low = None
    if low is not None:
        if orig is None:
            return low
        bad = np.flatnonzero(~(np.diagonal(low) ** 2 > tol * orig))
        if not len(bad):
            return low
        raise TilePivotError(first + int(bad[0]), *base)
    # the first row whose pivot fails
    for j in range(1, a.shape[0] + 1):
        try:
            np.linalg.cholesky(a[:j, :j])
        except np.linalg.LinAlgError:
            raise TilePivotError(first + j - 1, *base) from None
    raise TilePivotError(first + a.shape[0] - 1, *base)


def _t_trsm(a, low):
    import scipy.linalg

    return scipy.linalg.solve_triangular(low, a.T, lower=True, check_finite=False).T


def _t_update(a, x, y):
    """``a - x y'``; a diagonal tile (``y`` None: ``a - x x'``) by BLAS ``syrk``, half the
    flops, into a copy of ``a`` whose strict upper triangle is left as it was (not used:
    :func:`_t_potrf` and :func:`_add_lower` read the lower one). The arrays are taken in
    the layout they come in (C-ordered ones as their Fortran-ordered transposes), so BLAS
    copies nothing."""
    if y is not None:
        return a - x @ y.T
    from scipy.linalg import blas

    ct = not a.flags.f_contiguous     # (work on a' = the same lower triangle, as upper)
    c = np.array(a.T if ct else a, order="F", copy=True)
    xt = not x.flags.f_contiguous     # (x' is Fortran-ordered: x x' = (x')' x')
    out = blas.dsyrk(-1.0, x.T if xt else x, beta=1.0, c=c, trans=int(xt), lower=int(not ct),
                     overwrite_c=1)
    return out.T if ct else out


def tiled_cholesky(client, tiles, cuts, mt, origs=None, tol=0.0, tag="", base=(0, 1)):
    """The partial Cholesky of a symmetric front given as its lower tiles ``tiles[(i, j)]``
    (``i >= j``; arrays or futures) over the row ranges ``cuts`` (:func:`tile_cuts`), the
    first ``mt`` of them eliminated, as Dask tasks: each tile's tasks on one worker, 2-D
    block-cyclic over the cluster's workers (``potrf`` of a diagonal tile, ``trsm`` of the
    tiles below it, ``syrk`` / ``gemm`` of the trailing tiles, right-looking). Returns the
    tiles' futures: ``L`` in the first ``mt`` tile columns, the Schur complement (the
    update for the parent, lower tiles) in the others. ``origs``: the diagonal tiles'
    diagonals as assembled (by tile column, arrays or futures), for the pivot test with
    ``tol`` (:func:`_t_potrf`); ``tag`` goes into the tasks' keys; ``base`` names a failing
    pivot's station (:class:`TilePivotError`)."""
    where = _tile_places(client)
    cur = dict(tiles)
    nt = len(cuts)
    origs = origs or {}
    for k in range(mt):
        cur[(k, k)] = client.submit(_t_potrf, cur[(k, k)], cuts[k][0], origs.get(k), tol,
                                    base, key=_key("_t_potrf", tag), **where(k, k))
        for i in range(k + 1, nt):
            cur[(i, k)] = client.submit(_t_trsm, cur[(i, k)], cur[(k, k)],
                                        key=_key("_t_trsm", tag), **where(i, k))
        for j in range(k + 1, nt):
            for i in range(j, nt):
                cur[(i, j)] = client.submit(_t_update, cur[(i, j)], cur[(i, k)],
                                            cur[(j, k)] if i != j else None,
                                            key=_key("_t_update", tag), **where(i, j))
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


# -- the top nodes on the workers ----------------------------------------------------------
#
# The nodes above the parts (``top``) as one graph of Dask tasks, submitted at once: a front
# of at most one tile (:data:`TOP_TILE` rows) is built, assembled and factored by one task on
# one worker (:func:`top_node`); a larger one is built by column panels (:func:`top_panel`),
# cut into tiles, the children's pieces added where the tiles are (:func:`_add_blocks`) and
# factored tile by tile across the workers (:func:`tiled_cholesky`). The right-hand sides
# travel with the tiles as one more row of tiles, ``R = b'`` (nr rows: the right-hand side
# and the border's columns): the right-looking elimination turns ``R`` into ``y'`` over the
# own columns and into the parent's right-hand side over the boundary's. The factor's tiles
# are written into the factor file where they are; the client gathers ``y`` (m x nr a node),
# the border's sums and, at the end, nothing else. Updates stay on the worker that made them
# until the parent's tiles take their pieces.

#: Rows of a tile of a top front (rounded down to whole stations): fronts of more rows are
#: factored tile by tile across the workers, smaller ones by one task.
TOP_TILE = 2048


class TilePivotError(ValueError):
    """A pivot failed on a worker (picklable): ``row`` of the front whose own stations
    start at station ``lo``, ``k`` parameters a station (the station and parameter of
    :class:`~sapgo.solve.band.PivotError`)."""

    def __init__(self, row, lo=0, k=1):
        super().__init__(row, lo, k)
        self.row, self.lo, self.k = int(row), int(lo), int(k)

    @property
    def station(self):
        return self.lo + self.row // self.k

    @property
    def parameter(self):
        return self.row % self.k

    def __str__(self):
        return f"non-positive pivot at row {self.row}"


def _dig(obj, key):
    """``obj[key[0]][key[1]]..`` (``"T"``: transposed, a vector as a row)."""
    for x in key or ():
        if isinstance(x, str) and x == "T":
            obj = obj.T if obj.ndim == 2 else obj[None, :]
        else:
            obj = obj[x]
    return obj


def _t_take(obj, key, r, c):
    """The piece ``[r, c]`` of the block ``_dig(obj, key)`` (an array or a
    :class:`~sapgo.solve.tiles.Panels` of a subtree root's update), cut where it is."""
    from .tiles import Panels

    u = _dig(obj, key)
    if isinstance(u, Panels):
        if u._fd is None:   # (handed over already: reopen by name)
            u.__setstate__(u.__getstate__())
        c0 = int(c.min())
        cols = u.cols(c0, int(c.max()) + 1)
        return np.ascontiguousarray(cols[np.ix_(r - c0, c - c0)])
    return np.ascontiguousarray(u[np.ix_(r, c)])


def _take(client, u, key, r, c, at, tag=""):
    """The task cutting the piece ``[r, c]`` of ``_dig(u, key)`` on the worker ``at``
    holding ``u`` (None: where Dask likes). Pinned: left to itself, the scheduler may run
    it on an idle worker and move all of ``u`` there (a part's result, its updates whole)
    to cut a piece of it."""
    where = {"workers": [at], "allow_other_workers": True} if at else {}
    return client.submit(_t_take, u, key, r, c, pure=False, key=_key("_t_take", tag),
                         **where)


def _add_blocks(client, tiles, cuts, blocks, where, tag=""):
    """Add ``blocks`` (``(rows, cols, u, key, at)``: the block ``_dig(u, key)`` at places
    ``rows`` x ``cols`` of the front, ``u`` an array or a future on the worker ``at``) into
    the front's lower ``tiles`` over ``cuts``: each tile's piece cut where the block is
    (only the piece travels), added on the tile's worker. Returns the tiles (futures where
    added)."""
    out = dict(tiles)
    adds = {}
    for rows, cols, u, key, at in blocks:
        rows, cols = np.asarray(rows), np.asarray(cols)
        for (a, b), (r, c) in tile_pieces(rows, cols if cols is not rows else rows,
                                          cuts).items():
            piece = _take(client, u, key, r, c, at, tag)
            adds.setdefault((a, b), []).append((rows[r], cols[c], piece))
    for (a, b), pieces in adds.items():   # (Dask resolves the futures in the tuples)
        out[(a, b)] = client.submit(_t_add, out[(a, b)], cuts[a][0], cuts[b][0], *pieces,
                                    key=_key("_t_add", tag), **where(a, b))
    return out


def _key(name, tag=""):
    import uuid

    return f"{name}-{tag}{uuid.uuid4().hex}"


class _OnWorker:
    """A worker's view of the project and the work files at the last checkpoint (the
    build and update tasks' setting)."""

    def __init__(self, path, work_dir, band_width, state, blk):
        from ..project import Project
        from ..work import Work

        self.p = Project(path, "r")
        try:
            self.work = Work(work_dir, self.p, band_width, create=False, block=blk.npar,
                             n_border=blk.n_border)
        except BaseException:
            self.p.close()
            raise
        self.work.state = state

    def __enter__(self):
        return self.p, self.work

    def __exit__(self, *exc):
        try:
            self.work.close()
        finally:
            self.p.close()


def _front_part(env, blk, opts, tree, i, lam, priors, damping, c0, c1):
    """Columns ``c0 .. c1`` (rows from ``c0``) of top node ``i``'s front from its own points
    and priors, its own diagonal there damped; ``b`` (front x nr: the right-hand side's rows
    ``c0 .. c1``, with ``c0 == 0`` the border's columns in full) and the border's sums."""
    from .tree import _Fronts, build_panel, node_points

    p, work = env
    k, ng = blk.npar, blk.n_border
    fronts = _Fronts(tree, blk, k)
    fr = fronts.enter(i)
    n = k * len(fr)
    m = k * tree.own(i)
    a = np.zeros((n - c0, c1 - c0), order="F")
    b = np.zeros((n, 1 + ng), order="F")
    rhs = b[:, 0]
    sums = (np.zeros((ng, ng)), np.zeros(ng), np.zeros(ng))
    bord = b[:, 1:].reshape(len(fr), k, ng) if ng else np.zeros((len(fr), k, 0))
    for r0, w, g in priors:
        if c0 <= r0 < c1:
            a[r0 - c0:r0 - c0 + 6, r0 - c0:r0 - c0 + 6] += w
            rhs[r0:r0 + 6] += g
    build_panel(p, blk, fronts, node_points(p, work, blk, opts, tree, fronts, i), lam, a,
                rhs, bord, sums, c0, c1)
    if damping is not None and c0 < m:
        e = min(c1, m)
        idx = np.arange(e - c0)
        a[idx, idx] += damping[c0:e]
    return a, b, (sums if c0 == 0 else None)


def top_panel(path, work_dir, band_width, state, blk, opts, tree, i, lam, priors, damping,
              c0, c1, rows):
    """On a worker: a column panel of a tiled top front (:func:`_front_part`) as ``{"tiles":
    its tiles, rows ``rows`` (``(r0, r1)`` from ``c0``), "b": its rows of the right-hand side
    (w x 1), "bord": the border's rows (n x ng, first panel), "border": the border's sums
    (first panel) or None}``."""
    t0 = time.perf_counter()
    with _OnWorker(path, work_dir, band_width, state, blk) as env:
        a, b, sums = _front_part(env, blk, opts, tree, i, lam, priors, damping, c0, c1)
    return {"tiles": [a[r0 - c0:r1 - c0] for r0, r1 in rows],
            "b": np.ascontiguousarray(b[c0:c1, :1]),
            "bord": np.ascontiguousarray(b[:, 1:]) if c0 == 0 else None, "border": sums,
            "seconds": time.perf_counter() - t0}


def _t_rrow(rhs, bord, c0, c1):
    """Tile ``(R, J)``: the right-hand sides' rows ``c0 .. c1`` transposed (nr x w)."""
    out = np.zeros((1 + (0 if bord is None else bord.shape[1]), c1 - c0))
    out[0] = rhs[:, 0]
    if bord is not None:
        out[1:] = bord[c0:c1].T
    return out


def _t_diag(a):
    return np.diagonal(a).copy()


def _t_write(work_dir, layout, nr, i, r0, c0, tile):
    """Write tile ``(r0, c0)`` of node ``i``'s factor columns into the factor file (a
    diagonal tile's upper triangle is not used)."""
    from pathlib import Path

    from .fronts import FactorFile
    from .tree import FACTOR_FILE

    file = FactorFile(Path(work_dir) / FACTOR_FILE, layout, "w", n_rhs=nr)
    try:
        file.write_cols(i, c0, np.asfortranarray(tile), r0=r0)
    finally:
        file.close()
    return tile.shape[1]


def top_node(path, work_dir, band_width, state, blk, opts, tree, i, lam, priors, damping,
             layout, tol, *pieces):
    """On a worker: top node ``i``'s front in core (at most one tile): built from its
    points and priors, damped, the children's ``pieces`` (``(rows, cols, block)``, places
    in the front with its right-hand sides as rows ``n ..``) added, factored, its record
    written into the factor file. Returns ``{"u": the update (f x f, lower triangle), "ubT":
    its right-hand sides (nr x f), "y1", "border", "seconds"}``."""
    from ..blas import FNS, blas_limits
    from .fronts import FactorFile, _factor_front
    from .tree import FACTOR_FILE

    t0 = time.perf_counter()
    k = blk.npar
    m = k * tree.own(i)
    with _OnWorker(path, work_dir, band_width, state, blk) as env:
        a, b, sums = _front_part(env, blk, opts, tree, i, lam, priors, damping, 0,
                                 k * len(tree.front(i)))
        n = a.shape[0]
        for rows, cols, block in pieces:
            inner = rows < n
            if inner.all():
                _add_lower(a, 0, 0, rows, cols, block)
            else:   # (rows of the right-hand sides: b')
                b[cols, (rows - n)[:, None]] += block
        own = a[:, :m]
        upd = np.asfortranarray(a[m:, m:])
        with blas_limits(1):
            fail = _factor_front(FNS, own.reshape(-1, order="F"), n, m,
                                 upd.reshape(-1, order="F"), b.reshape(-1, order="F"),
                                 b.shape[1], tol)
        if fail:
            raise TilePivotError(fail - 1, tree.lo[i], k)
        file = FactorFile(env[1].dir / FACTOR_FILE, layout, "w", n_rhs=b.shape[1])
        try:
            file.write(i, own, b[:m])
        finally:
            file.close()
    return {"u": upd, "ubT": np.ascontiguousarray(b[m:].T), "y1": b[:m].copy(order="F"),
            "border": sums, "seconds": time.perf_counter() - t0}


def _strip(res):
    """A part's result without its updates (they stay on the worker)."""
    return {x: v for x, v in res.items() if x != "updates"}


def _top_inputs(p, work, blk, opts, tree, top, lam, diag):
    """Per top node: its own stations' priors (``(row, weight, right-hand side)``) and
    damping."""
    from ..adjust import _PriorCursor

    k = blk.npar
    priors = _PriorCursor(p, opts.chunk_points, blk)
    out = {}
    for i in top:
        lo, hi = int(tree.lo[i]), int(tree.hi[i])
        mine = []
        for s, w, r in priors.take(lo, hi):
            mine.append((k * (s - lo), np.array(w, dtype=np.float64), r))
        damping = None
        if lam > 0.0:
            damping = lam * np.clip(diag[lo:hi], 1e-6, 1e32).ravel()
        out[i] = (mine, damping)
    return out


def distributed_top(client, p, work, blk, opts, tree, solver, top, parts, lam, diag, cb):
    """The top nodes on the workers (the section's comment): factor records written into
    the factor file, ``y1`` written by the client, ``y'y`` and the border's ``W'W``,
    ``W'y`` into ``solver``, the border's sums into ``cb``. ``parts``: per part, its
    future and the nodes of its subtree roots' updates."""
    from .band import PivotError
    from .fronts import factor_layout

    k, ng = blk.npar, blk.n_border
    nr = 1 + ng
    tile = max(k, k * (TOP_TILE // k))
    layout = factor_layout(tree, k)
    wopts = dataclasses.replace(opts, client=None, progress=False)
    tree_f = work._tree_future
    common = (str(p.file_path), str(work.dir), work.band_width, work.state, work._blk_future,
              wopts, tree_f)
    inputs = _top_inputs(p, work, blk, opts, tree, top, lam, diag)
    addresses = worker_addresses(client)
    blocks = {}      # node -> its update's blocks for the parent
    home = {}        # node -> the worker holding its update (a small node's parent goes there)
    for w, (fut, nodes) in enumerate(parts):
        for c in nodes:
            f = k * len(tree.bnd(c))
            home[c] = addresses[w % len(addresses)]
            blocks[c] = [(np.arange(f), np.arange(f), fut, ("updates", c, 0), home[c]),
                         (f + np.arange(nr), np.arange(f), fut, ("updates", c, 1, "T"),
                          home[c])]
    stream = contextlib.nullcontext()
    if TRACE["on"]:
        from distributed import get_task_stream

        stream = get_task_stream(client)
    with stream as ts:
        ys, borders, writes = _submit_top(client, blk, tree, top, common, inputs, blocks,
                                          home, layout, opts.pivot_tolerance, lam,
                                          str(work.dir), tile)
        try:
            got_y, got_b, _ = client.gather([ys, borders, writes])
        except TilePivotError as exc:
            raise PivotError(exc.station, exc.parameter) from None
    if TRACE["on"]:
        _note_top(ts.data)
    for i in sorted(top):
        m = k * tree.own(i)
        y1 = np.zeros((m, nr), order="F")
        for r0, y in got_y[i]:
            y1[r0:r0 + y.shape[0]] = y
        solver.note_y(i, y1 if ng else y1[:, 0])
        solver.file.write_y(i, y1)
    for s in got_b:
        if s is not None and ng:
            for acc, x in zip(cb, s):
                acc += x


#: The tasks of a top node that eliminate (the trace's second figure of a node).
_ELIMINATE = {"top_node", "_t_potrf", "_t_trsm", "_t_update"}


def _note_top(stream):
    """The top nodes' seconds from Dask's task stream (their tasks' keys carry ``n<node>``):
    per node the sum of its tasks' seconds and of those that eliminate."""
    per = {}
    for d in stream:
        name, tag = (d["key"].split("-") + ["", ""])[:2]
        if not tag.startswith("n"):
            continue
        sec = sum(s["stop"] - s["start"] for s in d.get("startstops", ())
                  if s.get("action") == "compute")
        tot, eli = per.get(int(tag[1:]), (0.0, 0.0))
        per[int(tag[1:])] = (tot + sec, eli + (sec if name in _ELIMINATE else 0.0))
    note_nodes(per)


def _submit_top(client, blk, tree, top, common, inputs, blocks, home, layout, tol, lam,
                work_dir, tile):
    """The top nodes' tasks (:func:`distributed_top`): ``blocks`` and ``home`` hold the
    parts' updates and receive the top nodes'. Returns the futures of each node's ``y1``
    pieces (``(first row, piece)``), of the border's sums and of the factor's writes."""
    from .fronts import _scalar

    k, ng = blk.npar, blk.n_border
    nr = 1 + ng
    addresses = worker_addresses(client)
    where = _tile_places(client)
    children = tree.children()
    ys, borders, writes = {}, [], []
    for i in sorted(top):
        fr = tree.front(i)
        n, m = k * len(fr), k * tree.own(i)
        f = n - m
        priors, damping = inputs[i]
        mine = []
        for c in children[i]:
            if c in blocks:
                ext = np.concatenate([_scalar(np.searchsorted(fr, tree.bnd(c)), k),
                                      n + np.arange(nr)])
                mine += [(ext[r], ext[cc], u, key, at)
                         for r, cc, u, key, at in blocks.pop(c)]
        tag = f"n{i}-"
        if n <= tile:
            cuts = [(0, n), (n, n + nr)]
            # (where the largest child's update is)
            kids = [c for c in children[i] if c in home]
            target = (home[max(kids, key=lambda c: len(tree.bnd(c)))] if kids else
                      addresses[i % len(addresses)])
            pieces = []
            for rows, cols, u, key, at in mine:
                for (a, b), (r, cc) in tile_pieces(rows, cols, cuts).items():
                    piece = _take(client, u, key, r, cc, at, tag)
                    pieces.append((rows[r], cols[cc], piece))
            fut = client.submit(top_node, *common, i, lam, priors, damping, layout,
                                tol, *pieces, key=_key("top_node", tag),
                                workers=[target], allow_other_workers=True, pure=False)
            ys[i] = [(0, client.submit(_dig, fut, ("y1",), key=_key("_dig", tag)))]
            borders.append(client.submit(_dig, fut, ("border",), key=_key("_dig", tag)))
            blocks[i] = [(np.arange(f), np.arange(f), fut, ("u",), target),
                         (f + np.arange(nr), np.arange(f), fut, ("ubT",), target)]
            home[i] = target
            continue
        cuts = tile_cuts(m, n, tile, k) + [(n, n + nr)]
        nt = len(cuts)
        mt = sum(1 for a0, _ in cuts if a0 < m)
        panels = [client.submit(top_panel, *common, i, lam, priors, damping, c0, c1,
                                cuts[j:-1], key=_key("top_panel", tag), **where(j, j))
                  for j, (c0, c1) in enumerate(cuts[:-1])]
        bord = (client.submit(_dig, panels[0], ("bord",), key=_key("_dig", tag))
                if ng else None)
        borders.append(client.submit(_dig, panels[0], ("border",), key=_key("_dig", tag)))
        tiles = {}
        for j, (c0, c1) in enumerate(cuts[:-1]):
            for r in range(j, nt - 1):   # (views of the panel, where it is)
                tiles[(r, j)] = client.submit(_dig, panels[j], ("tiles", r - j),
                                              key=_key("_dig", tag))
            rhs = client.submit(_dig, panels[j], ("b",), key=_key("_dig", tag))
            tiles[(nt - 1, j)] = client.submit(_t_rrow, rhs, bord, c0, c1,
                                               key=_key("_t_rrow", tag), **where(nt - 1, j))
        tiles[(nt - 1, nt - 1)] = np.zeros((nr, nr))
        tiles = _add_blocks(client, tiles, cuts, mine, where, tag)
        origs = {j: client.submit(_t_diag, tiles[(j, j)], key=_key("_t_diag", tag),
                                  **where(j, j)) for j in range(mt)}
        out = tiled_cholesky(client, tiles, cuts, mt, origs, tol, tag,
                             (int(tree.lo[i]), k))
        for j in range(mt):
            for r in range(j, nt - 1):
                writes.append(client.submit(_t_write, work_dir, layout, nr, i,
                                            cuts[r][0], cuts[j][0], out[(r, j)],
                                            key=_key("_t_write", tag), **where(r, j)))
        ys[i] = [(cuts[j][0], client.submit(_dig, out[(nt - 1, j)], ("T",),
                                            key=_key("_dig", tag))) for j in range(mt)]
        blocks[i] = [(np.arange(cuts[r][0], cuts[r][1]) - m,
                      np.arange(cuts[j][0], cuts[j][1]) - m, out[(r, j)], None,
                      where(r, j)["workers"][0])
                     for j in range(mt, nt) for r in range(j, nt)
                     if (r, j) != (nt - 1, nt - 1)]
        home[i] = where(nt - 1, nt - 1)["workers"][0]
    return ys, borders, writes
