"""Scale-out by simulation (docs/theory.md section 4d): an iteration of the partition tree as
a task graph, replayed on ``W`` workers by a list scheduler with a network model.

The graph's tasks carry their seconds on one core and the bytes of their inputs, measured
on this machine (benchmarks/distributed.py traces every node of a run,
:data:`sapgo.solve.distributed.TRACE`) or given by a cost model fitted to such a trace
(:class:`CostModel`, for blocks too large to run here). Two graphs:

- :func:`built_graph`, the iteration as :mod:`sapgo.solve.distributed` runs it today: the
  parts of the plan on the workers, then the top nodes' tasks on the workers (small fronts
  one task, large ones tile by tile), the back substitution through the top, the
  gathering and the rest of the iteration on the client, three rounds of tasks. Replayed with the costs of a 1-worker
  run it predicts the 1- and 2-worker runs (the model's validation);
- :func:`tiled_graph`, the design for many workers: the subtrees on their workers as today,
  every top front factored tile by tile (``potrf``, ``trsm``, ``syrk``, ``gemm`` on
  ``tile x tile`` blocks, 2-D block-cyclic over the workers below it, proportional mapping)
  and the children's Schur updates sent tile by tile (lower triangles) to the tiles' owners.

:func:`replay` runs a graph: a task starts on its worker when every input has arrived and
the worker is free, the ready task with the longest path to the end first; a message leaves
when its task ends and its sender's link is free, takes ``bytes / bandwidth`` on the link and
arrives ``latency`` later; an output goes once to each worker that needs it.
"""

from __future__ import annotations

import dataclasses
import heapq
import time

import numpy as np

__all__ = ["CostModel", "Graph", "Network", "built_graph", "kernel_rates", "replay",
           "tiled_graph"]


@dataclasses.dataclass(frozen=True)
class Network:
    """``bandwidth`` (bytes a second a worker sends) and ``latency`` (seconds a message)."""

    bandwidth: float = 1.25e9
    latency: float = 50e-6

    def seconds(self, nbytes):
        return self.latency + nbytes / self.bandwidth


class Graph:
    """Tasks in a topological order: each on a fixed worker, with its seconds and its inputs
    ``(task, bytes)`` (a task's output goes to every task that lists it)."""

    def __init__(self):
        self.kind, self.worker, self.seconds, self.deps = [], [], [], []

    def add(self, kind, worker, seconds, deps=()):
        t = len(self.kind)
        deps = [(int(d), float(b)) for d, b in deps]
        assert all(0 <= d < t for d, _ in deps), "inputs before their task"
        self.kind.append(kind)
        self.worker.append(int(worker))
        self.seconds.append(max(float(seconds), 0.0))
        self.deps.append(deps)
        return t

    def __len__(self):
        return len(self.kind)

    def work(self):
        """Seconds of all tasks (on one core each)."""
        return float(sum(self.seconds))


def _levels(g, net):
    """The bottom level of every task (its seconds and the longest path after it, messages
    between workers included) and each task's successor on that path."""
    n = len(g)
    succ = [[] for _ in range(n)]
    for t, deps in enumerate(g.deps):
        for d, b in deps:
            succ[d].append((t, b))
    bl = [0.0] * n
    nxt = [-1] * n
    wk, sec = g.worker, g.seconds
    for t in range(n - 1, -1, -1):
        best, arg = 0.0, -1
        for s, b in succ[t]:
            c = bl[s] + (net.seconds(b) if wk[s] != wk[t] else 0.0)
            if c > best:
                best, arg = c, s
        bl[t] = sec[t] + best
        nxt[t] = arg
    return bl, nxt, succ


def replay(g, net, workers=None):
    """Run ``g`` on its workers (``workers``: their number, default the largest worker id +
    1). Returns a dict: ``seconds`` (the makespan), ``critical_path_s`` (the longest chain of
    tasks and messages: no number of workers does better), ``critical_path`` (seconds per
    task kind and ``messages`` along it), ``work_s`` (the tasks' seconds), ``efficiency``
    (``work / (workers x seconds)``), ``busiest_s`` (the most seconds a worker computes),
    ``messages``, ``bytes`` (sent between workers), ``max_bytes_sent`` (by one worker),
    ``tasks`` and ``tasks_by_kind``."""
    n = len(g)
    n_w = int(workers or (max(g.worker) + 1 if n else 1))
    bl, nxt, succ = _levels(g, net)
    wk, sec = g.worker, g.seconds
    remaining = [len(d) for d in g.deps]
    avail = [0.0] * n
    waiting = [[] for _ in range(n_w)]   # (available at, task)
    ready = [[] for _ in range(n_w)]     # (-bottom level, task)
    running = [False] * n_w
    link = [0.0] * n_w
    busy = [0.0] * n_w
    sent_by = [0.0] * n_w
    sent = {}
    events = []   # (time, sequence, task finished or -1 - worker to wake)
    seq = 0
    done = 0
    stats = {"messages": 0, "bytes": 0.0}

    def dispatch(w, now):
        nonlocal seq
        if running[w]:
            return
        q = waiting[w]
        while q and q[0][0] <= now:
            _, t = heapq.heappop(q)
            heapq.heappush(ready[w], (-bl[t], t))
        if ready[w]:
            _, t = heapq.heappop(ready[w])
            running[w] = True
            busy[w] += sec[t]
            seq += 1
            heapq.heappush(events, (now + sec[t], seq, t))
        elif q:
            seq += 1
            heapq.heappush(events, (q[0][0], seq, -1 - w))

    for t in range(n):
        if remaining[t] == 0:
            heapq.heappush(waiting[wk[t]], (0.0, t))
    for w in range(n_w):
        dispatch(w, 0.0)
    end = 0.0
    while events:
        now, _, x = heapq.heappop(events)
        if x < 0:
            dispatch(-1 - x, now)
            continue
        t, w = x, wk[x]
        running[w] = False
        done += 1
        end = max(end, now)
        touched = {w}
        for s, b in succ[t]:
            ws = wk[s]
            if ws == w:
                arrive = now
            else:
                arrive = sent.get((t, ws))
                if arrive is None:   # (once to each worker)
                    start = max(now, link[w])
                    link[w] = start + b / net.bandwidth
                    arrive = link[w] + net.latency
                    sent[(t, ws)] = arrive
                    stats["messages"] += 1
                    stats["bytes"] += b
                    sent_by[w] += b
            avail[s] = max(avail[s], arrive)
            remaining[s] -= 1
            if remaining[s] == 0:
                heapq.heappush(waiting[ws], (avail[s], s))
                touched.add(ws)
        for u in touched:
            dispatch(u, now)
    if done != n:
        raise ValueError(f"the task graph did not finish: {n - done} of {n} tasks left")
    # the critical path: from the task of the largest bottom level along its successors
    path = {"messages": 0.0}
    t = int(np.argmax(bl)) if n else -1
    while t >= 0:
        path[g.kind[t]] = path.get(g.kind[t], 0.0) + sec[t]
        s = nxt[t]
        if s >= 0 and wk[s] != wk[t]:
            b = next(b for d, b in g.deps[s] if d == t)
            path["messages"] += net.seconds(b)
        t = s
    work = float(sum(sec))
    return {"seconds": end, "critical_path_s": max(bl) if n else 0.0,
            "critical_path": path, "work_s": work,
            "efficiency": work / (n_w * end) if end > 0 else 1.0,
            "busiest_s": max(busy), "messages": stats["messages"], "bytes": stats["bytes"],
            "max_bytes_sent": max(sent_by), "tasks": n, "workers": n_w,
            "tasks_by_kind": {k: g.kind.count(k) for k in sorted(set(g.kind))}}


# -- costs ------------------------------------------------------------------------------

def kernel_rates(tile=2048, repeat=3):
    """Flops a second of one core in the tiled factorisation's four kernels on ``tile x
    tile`` blocks (scipy's LAPACK and BLAS, one thread): the best of ``repeat`` runs."""
    import scipy.linalg.blas as blas
    import scipy.linalg.lapack as lapack

    from ..blas import blas_limits

    rng = np.random.default_rng(1)
    a = rng.standard_normal((tile, tile))
    spd = np.asfortranarray(a @ a.T + tile * np.eye(tile))
    b = np.asfortranarray(rng.standard_normal((tile, tile)))
    c = np.asfortranarray(rng.standard_normal((tile, tile)))
    low = np.asfortranarray(np.linalg.cholesky(spd))
    t3 = float(tile) ** 3
    jobs = {
        "potrf": (lambda: lapack.dpotrf(spd, lower=1, overwrite_a=0), t3 / 3),
        "trsm": (lambda: blas.dtrsm(1.0, low, b, side=1, lower=1, trans_a=1), t3),
        "syrk": (lambda: blas.dsyrk(-1.0, b, beta=1.0, c=c, lower=1, overwrite_c=1), t3),
        "gemm": (lambda: blas.dgemm(-1.0, b, c, beta=1.0, c=a, trans_b=1, overwrite_c=1),
                 2 * t3),
    }
    out = {}
    with blas_limits(1):
        for name, (fn, flops) in jobs.items():
            best = np.inf
            for _ in range(repeat):
                t0 = time.perf_counter()
                fn()
                best = min(best, time.perf_counter() - t0)
            out[name] = flops / best
    return out


def node_figures(tree, k):
    """Per node: ``m`` and ``f`` (its own and its boundary's scalar unknowns), ``flops`` of
    its elimination, ``factor_bytes`` (its factor record: own columns and right-hand side)
    and ``points``."""
    m = k * (tree.hi - tree.lo).astype(np.float64)
    f = k * np.diff(tree.bptr).astype(np.float64)
    pts = (np.diff(tree.pt_start).astype(np.float64) if tree.pt_start is not None
           else np.zeros(tree.n_nodes))
    return {"m": m, "f": f, "flops": tree.node_flops(k),
            "factor_bytes": 8 * (m * (m + 1) / 2 + m * f + m), "points": pts}


@dataclasses.dataclass
class CostModel:
    """Seconds of a node on one core from its figures (:func:`node_figures`): the
    elimination ``elim_fixed + flops / rate``, the build ``build_fixed + build_point x
    points``, the back substitution ``factor_bytes / back_rate`` and the point update
    ``update_point x points``; fitted to a traced run by :meth:`fit`."""

    rate: float
    elim_fixed: float
    build_fixed: float
    build_point: float
    back_rate: float
    update_point: float

    @classmethod
    def fit(cls, fig, nodes, elim, back_s, update_s):
        """Least squares over the traced ``nodes`` (their ``total`` and ``elim`` seconds);
        ``back_s`` and ``update_s``: the seconds of the back substitution and of the point
        update of those nodes (summed)."""
        nodes = np.asarray(nodes, np.int64)
        total, el = (np.asarray(x, np.float64) for x in elim)
        fl = fig["flops"][nodes]
        a = np.column_stack([np.ones(len(nodes)), fl])
        (e0, inv_rate), *_ = np.linalg.lstsq(a, el, rcond=None)
        if inv_rate <= 0:   # (no front large enough to tell: the mean rate)
            inv_rate, e0 = el.sum() / fl.sum(), 0.0
        pts = fig["points"][nodes]
        a = np.column_stack([np.ones(len(nodes)), pts])
        (b0, bp), *_ = np.linalg.lstsq(a, total - el, rcond=None)
        return cls(rate=1.0 / inv_rate, elim_fixed=max(e0, 0.0), build_fixed=max(b0, 0.0),
                   build_point=max(bp, 0.0),
                   back_rate=fig["factor_bytes"][nodes].sum() / max(back_s, 1e-12),
                   update_point=update_s / max(fig["points"][nodes].sum(), 1.0))

    def step(self, fig):
        return self.build(fig) + self.elim_fixed + fig["flops"] / self.rate

    def build(self, fig):
        return self.build_fixed + self.build_point * fig["points"]

    def back(self, fig):
        return fig["factor_bytes"] / self.back_rate

    def update(self, fig):
        return self.update_point * fig["points"]


# -- the graphs --------------------------------------------------------------------------

def _part_nodes(per):
    return [[i for a, b in ranges for i in range(a, b)] for ranges in per]


def built_graph(tree, plan, step_s, part_back_s, part_update_s, top_update_s, top_back_s,
                overhead, bytes_, workers, k=6, build_s=None, rates=None, tile=2048,
                task_s=0.0):
    """The iteration as :mod:`sapgo.solve.distributed` runs it on ``workers`` workers (part
    ``w`` on worker ``w mod workers``, the client the worker numbered ``workers``): the
    parts' step tasks; the top nodes' tasks on the workers (:func:`_top_graph`: a front of
    at most ``tile`` rows one task where its largest child's update is, a larger one tile by
    tile over all the workers, its build ``build_s`` and the kernels at ``rates`` plus
    ``task_s`` a task; without ``rates`` every top front one task); the client's gathering,
    its back substitution through the top, the back-substitution and update rounds.

    ``step_s`` (node -> seconds of building and eliminating it), ``part_back_s`` and
    ``part_update_s`` (seconds of each part's back-substitution and update tasks),
    ``top_back_s`` and ``top_update_s`` (the client's), ``overhead`` (``task``: seconds of
    a step task besides its nodes, per part; ``step``, ``back``, ``update``: the client's
    seconds of each round besides the tasks' own; ``client``: the rest of the iteration on
    the client), ``bytes_`` (per round kind, per part: ``(to the worker, from it)``)."""
    per, top = plan
    f_all = node_figures(tree, k)["f"].astype(np.int64)
    g = Graph()
    c = workers
    start = g.add("client", c, 0.0)
    out, last_step, home = {}, {}, {}
    ends = []
    for w, nodes in enumerate(_part_nodes(per)):
        t = g.add("task", w % workers, overhead["task"][w], [(start, bytes_["step"][w][0])])
        for i in nodes:
            t = g.add("step", w % workers, step_s[i], [(t, 0)])
        for i in nodes:   # (the updates stay on the worker until the step task's end)
            out[i] = [(t, 0, int(f_all[i]), 0, int(f_all[i]))]
            home[i] = w % workers
        ends.append((t, bytes_["step"][w][1]))
    t = g.add("round", c, overhead["step"], ends)
    children = tree.children()
    groups = {}
    big = (k * (tree.hi - tree.lo + np.diff(tree.bptr)) > tile if rates is not None
           else np.zeros(tree.n_nodes, bool))
    for i in sorted(top):
        kids = [x for x in children[i] if x in home]
        home[i] = (home[max(kids, key=lambda x: f_all[x])] if kids else i % workers)
        groups[i] = list(range(workers)) if big[i] else [home[i]]
    _top_graph(g, tree, k, top, groups, out, last_step, t, step_s,
               build_s if build_s is not None else np.zeros(tree.n_nodes),
               rates or {}, tile if rates is not None else np.inf, task_s, half=False)
    last = [x for i in top for x in (last_step[i] if isinstance(last_step[i], list)
                                     else [last_step[i]])]
    t = g.add("top", c, top_back_s, [(t, 0)] + [(x, 0) for x in last])
    ends = [(g.add("back", w % workers, part_back_s[w], [(t, bytes_["back"][w][0])]),
             bytes_["back"][w][1]) for w in range(len(per))]
    t = g.add("round", c, overhead["back"], ends)
    ends = [(g.add("update", w % workers, part_update_s[w], [(t, bytes_["update"][w][0])]),
             bytes_["update"][w][1]) for w in range(len(per))]
    t = g.add("round", c, overhead["update"], ends)
    t = g.add("top", c, top_update_s, [(t, 0)])
    g.add("client", c, overhead["client"], [(t, 0)])
    return g


def _top_graph(g, tree, k, top, groups, out, last_step, start, step_s, build_s, rates,
               tile, task_s, half=True):
    """The top nodes' tasks (:func:`tiled_graph`, :func:`built_graph`): a front of at most
    ``tile`` rows one task (``step_s``) on the first worker of its group (``groups``: node
    -> workers), a larger one tile by tile 2-D block-cyclic over its group (its points'
    build, ``build_s``, split over the workers holding its tiles; the kernels at ``rates``
    plus ``task_s`` a task); the children's updates (``out``: node -> the tasks holding
    blocks of its update) sent to the tiles they land on (``half``: a diagonal block as its
    lower triangle). Fills ``out`` and ``last_step`` for the top nodes; returns the workers
    holding each tiled node's tiles."""
    from .distributed import tile_cuts, tile_grid

    fig = node_figures(tree, k)
    m_all, f_all = fig["m"].astype(np.int64), fig["f"].astype(np.int64)
    children = tree.children()
    half_ok = half
    holding = {}   # a tiled top node: the workers holding its tiles
    tile_of = {}

    def front_pos(i, c):
        """Scalar rows of child ``c``'s boundary in node ``i``'s front."""
        fr = tree.front(i)
        pos = np.searchsorted(fr, tree.bnd(c))
        return (k * pos[:, None] + np.arange(k)).ravel()

    for i in sorted(top):
        grp = groups[i]
        m, f = int(m_all[i]), int(f_all[i])
        big = m + f > tile
        # the tiles' row ranges: own rows, then boundary rows, each cut in tiles
        cuts = tile_cuts(m, m + f, tile, k) if big else [(0, m + f)]
        mt = sum(1 for a, _ in cuts if a < m)
        nt = len(cuts)
        starts = np.array([a for a, _ in cuts])
        pr, pc = tile_grid(len(grp))

        def own(a, b):
            return grp[(a % pr) * pc + (b % pc)] if big else grp[0]

        # the children's updates, by the tiles they land on
        into = {}
        for c in children[i]:
            pos = front_pos(i, c)
            tl = np.searchsorted(starts, pos, side="right") - 1
            for (t, r0, r1, c0, c1) in out[c]:
                ra, ca = tl[r0:r1], tl[c0:c1]
                for a in np.unique(ra):
                    na = int((ra == a).sum())
                    for b in np.unique(ca):
                        if b > a:
                            continue
                        nb = int((ca == b).sum())
                        half = half_ok and a == b and (r0, r1) == (c0, c1)
                        nbytes = 8.0 * na * nb / (2 if half else 1)
                        into.setdefault((int(a), int(b)), []).append((t, nbytes))
        if not big:
            deps = [(start, 0)] + [d for v in into.values() for d in v]
            t = g.add("top", grp[0], step_s[i], deps)
            tile_of[i] = {}
            out[i] = [(t, 0, f, 0, f)]
            last_step[i] = t
            continue
        # (the workers holding tiles of it build their share of its points' terms)
        holders = sorted({own(a, b) for a in range(nt) for b in range(a + 1)})
        holding[i] = holders
        builds = {w: g.add("build", w, build_s[i] / len(holders), [(start, 0)])
                  for w in holders}
        last = {}

        def op(kind, a, b, seconds, reads):
            w = own(a, b)
            deps = list(reads)
            if (a, b) in last:
                deps.append((last[(a, b)], 0))
            else:
                deps.append((builds[w], 0))
                deps.extend(into.get((a, b), []))
            t = g.add(kind, w, seconds + task_s, deps)
            last[(a, b)] = t
            return t

        d = [b - a for a, b in cuts]
        for kk in range(mt):
            tb = 8.0 * d[kk] * d[kk]
            p = op("potrf", kk, kk, d[kk] ** 3 / 3 / rates["potrf"], [])
            tr = {}
            for a in range(kk + 1, nt):
                tr[a] = op("trsm", a, kk, d[a] * d[kk] ** 2 / rates["trsm"], [(p, tb / 2)])
            for b in range(kk + 1, nt):
                for a in range(b, nt):
                    reads = [(tr[a], 8.0 * d[a] * d[kk])]
                    if a == b:
                        op("syrk", a, a, d[a] ** 2 * d[kk] / rates["syrk"], reads)
                    else:
                        reads.append((tr[b], 8.0 * d[b] * d[kk]))
                        op("gemm", a, b, 2.0 * d[a] * d[b] * d[kk] / rates["gemm"], reads)
        tile_of[i] = last
        out[i] = [(last[(a, b)], cuts[a][0] - m, cuts[a][1] - m, cuts[b][0] - m,
                   cuts[b][1] - m) for a in range(mt, nt) for b in range(mt, a + 1)]
        # (its factor: every own-column tile's last task)
        last_step[i] = [last[(a, b)] for a in range(nt) for b in range(min(a + 1, mt))]
    return holding


def tiled_graph(tree, k, workers, step_s, back_s, update_s, build_s, rates, tile=2048,
                task_s=0.0, plan=None):
    """The iteration for ``workers`` workers (one core each) as designed for many workers:
    the subtrees of :func:`~sapgo.solve.tree.parallel_plan` on their workers (each node's
    ``step_s``), the top fronts larger than one tile factored tile by tile on the workers
    below them (``build_s`` of their own points split over those workers; the kernels at
    ``rates``, :func:`kernel_rates`, plus ``task_s`` a task), smaller top fronts as one task
    on the first of them; the Schur updates sent as lower triangles, tile by tile; back
    substitution (``back_s``) and point update (``update_s``) down the tree; the sums to
    worker 0. Arrays per node."""
    from .tree import parallel_plan

    per, top = plan or parallel_plan(tree, k, workers)
    f_all = node_figures(tree, k)["f"].astype(np.int64)
    first = tree.first
    n_nodes = tree.n_nodes
    owner = np.full(n_nodes, -1, np.int64)   # a part's nodes: its worker
    for w, nodes in enumerate(_part_nodes(per)):
        owner[nodes] = w
    g = Graph()
    start = g.add("start", 0, 0.0)
    # out[i]: how node i's update leaves it: [(task, rows lo, rows hi, cols lo, cols hi)]
    # in its boundary's scalar rows (a task holding that block of the update)
    out = {}
    last_step = {}
    for w, nodes in enumerate(_part_nodes(per)):
        t = start
        for i in nodes:
            t = g.add("subtree", w, step_s[i], [(t, 0)])
            last_step[i] = t
            f = int(f_all[i])
            out[i] = [(t, 0, f, 0, f)]
    # the top nodes' worker groups: the workers of the parts below them
    groups = {}
    for i in top:
        below = owner[first[i]:i + 1]
        ws = sorted(set(int(x) for x in below[below >= 0]))
        groups[i] = ws or list(range(workers))
    t_back_of = {}
    holding = _top_graph(g, tree, k, top, groups, out, last_step, start, step_s, build_s,
                         rates, tile, task_s)
    top_set = set(int(i) for i in top)
    # back substitution down the tree: the top nodes on their groups, then the parts
    ends = []
    for i in sorted(top, reverse=True):
        grp = groups[i]
        par = int(tree.parent[i])
        deps = [(t, 8.0 * k * f_all[i] / len(holding.get(i, grp[:1])))
                for t in t_back_of.get(par, [])]
        ls = last_step[i] if isinstance(last_step[i], list) else [last_step[i]]
        deps += [(t, 0) for t in ls]
        ws = holding.get(i, grp[:1])
        t_back_of[i] = [g.add("back", w, back_s[i] / len(ws), deps) for w in ws]
        ends += [g.add("update", w, update_s[i] / len(ws), [(t, 0)])
                 for w, t in zip(ws, t_back_of[i])]
    for w, nodes in enumerate(_part_nodes(per)):
        if not nodes:
            continue
        roots = [b - 1 for a, b in per[w]]
        deps = [(last_step[nodes[-1]], 0)]
        for r in roots:
            par = int(tree.parent[r])
            if par >= 0 and par in top_set:
                deps += [(t, 8.0 * k * f_all[r]) for t in t_back_of[par]]
        t = g.add("back", w, float(np.sum(back_s[nodes])), deps)
        ends.append(g.add("update", w, float(np.sum(update_s[nodes])), [(t, 0)]))
    g.add("sums", 0, 0.0, [(t, 100.0) for t in ends])
    return g


# -- blocks too large to generate ------------------------------------------------------

def stencil(path):
    """The station graph of a generated block (``sapgo generate``: station ``id`` numbered
    strip by strip) as ``(strips apart, photos apart)`` offsets (those of at least a fifth
    as many edges as the most common one), and the stations' spacing ``(along strips,
    across)``."""
    from ..ordering import _station_activity
    from ..project import Project

    with Project(path, "r") as p:
        st = p.read("stations", 0, p.n_stations)
        _, (s, t) = _station_activity(p, 1 << 16)
    ids = st["id"].astype(np.int64) - 1
    strip = st["strip"].astype(np.int64)
    per_strip = int(np.bincount(strip).max())
    col = ids - (strip - strip.min()) * per_strip
    ds, dc = strip[t] - strip[s], col[t] - col[s]
    flip = (ds < 0) | ((ds == 0) & (dc < 0))
    ds, dc = np.where(flip, -ds, ds), np.where(flip, -dc, dc)
    pairs, count = np.unique(np.stack([ds, dc], 1), axis=0, return_counts=True)
    order = np.argsort(-count)
    keep = count[order] >= 0.2 * count.max()   # (not the odd edge of a control point)
    eo = st["eo"]
    along = np.median(np.abs(np.diff(eo[:, 3])[np.diff(strip) == 0]))
    across = (np.ptp(eo[:, 4]) / max(np.ptp(strip), 1)) if np.ptp(strip) else along
    return [tuple(int(x) for x in pairs[j]) for j in order[keep]], (float(along),
                                                                     float(across))


def grid_tree(strips, photos, offsets, spacing=(1.0, 1.0), leaf_stations=None):
    """The partition tree (geometric bisection, :func:`~sapgo.solve.partition
    .nested_dissection`) of a ``strips x photos`` block whose station graph joins the
    stations ``offsets`` (:func:`stencil`) apart, without generating it."""
    from .partition import LEAF_STATIONS, nested_dissection

    n = strips * photos
    r, c = np.divmod(np.arange(n, dtype=np.int64), photos)
    pos = np.stack([c * spacing[0], r * spacing[1]], 1).astype(np.float64)
    s_all, t_all = [], []
    for ds, dc in offsets:
        ok = (r + ds < strips) & (c + dc >= 0) & (c + dc < photos)
        s = np.flatnonzero(ok)
        s_all.append(s)
        t_all.append(s + ds * photos + dc)
    del r, c
    s, t = np.concatenate(s_all), np.concatenate(t_all)
    del s_all, t_all
    tree, _ = nested_dissection(pos, np.ones(n, bool), (s, t),
                                leaf_stations or LEAF_STATIONS)
    return tree
