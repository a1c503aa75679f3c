"""The partition tree: nested dissection of the station graph (DESIGN section 5b).

The station graph joins two stations that observe a common point. Recursive bisection splits
it into a tree: an internal node is a *vertex separator* S (stations whose removal leaves two
parts that share no point), a leaf a part small enough to be eliminated as a whole. The
stations are numbered in the tree's post-order (a node's subtree first, then its own
stations), so every node owns a contiguous range of logical stations ``lo .. hi`` and its
subtree the range ``first .. hi``; a point's stations form a clique, so they lie in one node
plus its ancestors, and the point belongs to the node of its first (smallest) logical station.
Sorting the points by (first, last) logical station, as ``sapgo order`` always has, therefore
puts each node's points together, in the tree's post-order (SAPGO's "points sorted by logical
station", generalised).

Separators (George 1973; the practice of METIS and of sparse direct solvers):

- **geometric**: the stations of a part are cut across the longest principal axis of their
  positions (aerial and orbital blocks: the positions carry the topology) at the cut among a
  few near the median with the fewest separator stations;
- **graph**: METIS' multilevel nested dissection of the graph alone (``METIS_NodeND``), read
  as a supernodal elimination tree (:func:`supernodal_tree`), for networks whose positions say
  nothing of their topology (close-range, unordered models).

A geometric cut becomes a vertex separator by a minimum vertex cover of the cut's bipartite
graph (König's theorem: a maximum matching, then alternating paths). :func:`best_tree` builds
both trees and keeps the one of the smaller predicted time.

Each node's *front* is its own stations followed by its *boundary*: the ancestors' stations
adjacent to its subtree (the structure of its columns of the Cholesky factor). The factor's
flops and storage follow from the fronts: for ``m = k |S|`` own and ``f = k |boundary|``
boundary unknowns (``k`` parameters a station), ``m^3/3 + m^2 f + m f^2`` flops (dpotrf,
dtrsm, dsyrk) and ``m (m + 1)/2 + m f`` doubles of factor.
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numba import njit
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

#: A part of at most this many stations is a leaf. A leaf is factored as one dense front
#: although its own stations are a band: a smaller leaf wastes fewer flops on explicit
#: zeros (100 x 100 photos: 10.6 GFlop at 24, 12.4 at 48) for more, smaller nodes; 24 was
#: the fastest of 16-48 at 100 x 100 and 200 x 200 photos (a step 5-10 % shorter than at
#: 48, tree steps alternated in one process).
LEAF_STATIONS = 24

#: Boundary stations (summed over the nodes) up to which :meth:`Tree.links` keeps each
#: node's front and children's places from one factorisation to the next (about 60 bytes
#: each, outside the memory budget: 13 MB at most). 100 x 100 photos have 24 000 of them
#: and 200 x 200 109 000, where the per-node work matters; 500 x 500 655 000, where the
#: fronts' flops dwarf it and the memory is better left to them.
LINKS_MAX_BOUNDARY = 200_000

#: Cuts tried around the median of a part's stations along its principal axis (fractions).
CUT_FRACTIONS = (0.5, 0.45, 0.55, 0.4, 0.6)

#: Principal axes of a part's positions tried as cut directions.
AXES = 2


@dataclasses.dataclass
class Tree:
    """A partition tree in post-order (children before their parent, node ``i``'s subtree is
    the node range ``i - size + 1 .. i``).

    ``lo[i] .. hi[i]``: the node's own logical stations; ``first[i] .. hi[i]``: its
    subtree's; ``parent`` (-1 at a root: a disconnected block is a forest); ``leaf``;
    ``boundary[bptr[i]:bptr[i+1]]`` the node's boundary stations (logical, ascending, all
    ``>= hi[i]``). ``n_active`` stations are in the tree (``0 .. n_active``); the others
    (excluded) follow them. ``pt_start`` (nodes + 1): the node's points are the records
    ``pt_start[i] .. pt_start[i+1]`` once the points are in order (``sapgo order`` sets it).
    ``method``: "geometric" or "graph".
    """

    lo: np.ndarray
    hi: np.ndarray
    first: np.ndarray
    parent: np.ndarray
    leaf: np.ndarray
    bptr: np.ndarray
    boundary: np.ndarray
    n_active: int
    method: str = "geometric"
    pt_start: np.ndarray | None = None

    @property
    def n_nodes(self):
        return len(self.lo)

    def own(self, i):
        return int(self.hi[i] - self.lo[i])

    def bnd(self, i):
        return self.boundary[self.bptr[i]:self.bptr[i + 1]]

    def front(self, i):
        """The node's front stations: its own, then its boundary (logical, ascending)."""
        return np.concatenate([np.arange(self.lo[i], self.hi[i]), self.bnd(i)])

    def children(self):
        """Children lists (post-order) of every node."""
        ch = [[] for _ in range(self.n_nodes)]
        for i, p in enumerate(self.parent):
            if p >= 0:
                ch[p].append(i)
        return ch

    def depth(self):
        d = np.zeros(self.n_nodes, np.int64)
        for i in range(self.n_nodes - 1, -1, -1):
            if self.parent[i] >= 0:
                d[i] = d[self.parent[i]] + 1
        return d

    def node_flops(self, k=6):
        """Each node's elimination flops, ``m^3/3 + m^2 f + m f^2`` (dpotrf, dtrsm, dsyrk)
        for ``m`` own and ``f`` boundary unknowns, ``k`` parameters a station."""
        m = k * (self.hi - self.lo).astype(np.float64)
        f = k * np.diff(self.bptr).astype(np.float64)
        return m ** 3 / 3 + m * m * f + m * f * f

    def figures(self, k=6):
        """Depth, leaves, largest front, factor bytes and flops for ``k`` parameters a
        station (the report's and the plan's tree figures)."""
        m = k * (self.hi - self.lo).astype(np.float64)
        f = k * np.diff(self.bptr).astype(np.float64)
        flops = self.node_flops(k)
        doubles = m * (m + 1) / 2 + m * f
        front = (m + f)
        return {
            "nodes": int(self.n_nodes),
            "depth": int(self.depth().max() + 1) if self.n_nodes else 0,
            "leaves": int(self.leaf.sum()),
            "roots": int((self.parent < 0).sum()),
            "largest_front": int(front.max() / k) if self.n_nodes else 0,
            "largest_front_bytes": int(8 * front.max() ** 2) if self.n_nodes else 0,
            "largest_separator": int(((self.hi - self.lo)[~self.leaf]).max())
            if (~self.leaf).any() else 0,
            "factor_bytes": int(8 * doubles.sum()),
            # the fronts and updates in core at once with every front in core, one worker
            "fronts_bytes": self.peak_front_bytes(k) if self.n_nodes else 0,
            "flops": float(flops.sum()),
            "method": self.method,
        }

    def front_bytes(self, k=6):
        """Bytes of each node's front in core: its own columns ``[A11; A21]`` ((m + f) x m)
        and its update block ``A22`` (f x f), which goes on to the parent."""
        m = k * (self.hi - self.lo).astype(np.float64)
        f = k * np.diff(self.bptr).astype(np.float64)
        return 8 * ((m + f) * m + f * f)

    def peak_front_bytes(self, k=6, plan=None, tile=None, separate=False):
        """Bytes in core at the worst moment of the factorisation: the fronts being factored
        plus the update matrices (f x f each) waiting for their parents.

        ``plan``: ``(per_worker, top)`` of :func:`sapgo.solve.tree.parallel_plan`, the
        subtrees (node ranges) factored side by side and the nodes above them factored after:
        the workers' peaks add up (each with the updates of its finished subtrees, which
        wait for the top), then the top runs with all of them. None: one worker, all nodes
        in post-order.

        ``tile``: ``(front_bytes, panel_bytes)``, fronts larger than ``front_bytes`` tiled
        (:mod:`sapgo.solve.tiles`: a panel being assembled, a factor panel read back and a
        part of a child's update, a panel each at most) and updates larger than a panel in
        scratch files (a panel of them in core while they are written or added).

        ``separate``: the workers are processes of their own (Dask), each with its own
        memory: the largest worker's peak, or the top's (with every worker's updates
        passed to it), counts, not their sum."""
        f = k * np.diff(self.bptr).astype(np.float64)
        upd = 8 * f * f
        front = self.front_bytes(k)
        parent = self.parent
        if tile is not None:
            big, panel = tile
            tiled = front > big
            spilled = tiled | (upd > panel)
            # a spilled child or update: a panel of it in core beside the front
            touches = spilled.copy()
            np.logical_or.at(touches, parent[(parent >= 0) & spilled], True)
            front = np.where(tiled, 3.0 * panel, front + np.where(touches, panel, 0.0))
            upd = np.where(spilled, 0.0, upd)
        pending = np.zeros(self.n_nodes)   # bytes of the children's updates held per parent

        def run(nodes, held):
            stack, peak = held, held
            for i in nodes:
                stack -= pending[i]
                peak = max(peak, stack + pending[i] + front[i])
                if parent[i] >= 0:
                    pending[parent[i]] += upd[i]
                    stack += upd[i]
            return peak, stack

        if plan is None:
            return int(run(range(self.n_nodes), 0.0)[0])
        per, top = plan
        total, left, largest = 0.0, 0.0, 0.0
        for ranges in per:
            peak, stack = run((i for a, b in ranges for i in range(a, b)), 0.0)
            total += peak
            left += stack
            largest = max(largest, peak)
        return int(max(largest if separate else total, run(sorted(top), left)[0]))

    def links(self, k=6):
        """Per node, its front's stations and, for each child with a boundary, ``(child,
        ix, cm)``: the scalar places ``ix`` of the child's boundary in the node's front
        (``k`` unknowns a station) and how many of them fall in its own columns. Computed
        once and kept with the tree for the factorisations that follow (one a step), when
        the tree's boundaries are small enough (:data:`LINKS_MAX_BOUNDARY`); else None."""
        got = self.__dict__.get("_links")
        if got is not None and got[0] == k:
            return got[1]
        if len(self.boundary) > LINKS_MAX_BOUNDARY:
            return None
        fronts = [self.front(i) for i in range(self.n_nodes)]
        kids = [[] for _ in range(self.n_nodes)]
        for c, q in enumerate(self.parent):
            if q >= 0 and self.bptr[c + 1] > self.bptr[c]:
                places = np.searchsorted(fronts[q], self.bnd(c))
                ix = (k * places[:, None] + np.arange(k)).ravel()
                kids[q].append((c, ix, int(np.searchsorted(ix, k * self.own(q)))))
        links = list(zip(fronts, kids))
        self.__dict__["_links"] = (k, links)
        return links

    def __getstate__(self):   # (pickled for Dask's workers: without the links)
        state = dict(self.__dict__)
        state.pop("_links", None)
        return state

    # -- storage in the project ------------------------------------------------------
    def to_arrays(self):
        return {"lo": self.lo, "hi": self.hi, "first": self.first, "parent": self.parent,
                "leaf": self.leaf.astype(np.int8), "bptr": self.bptr,
                "boundary": self.boundary,
                "pt_start": (self.pt_start if self.pt_start is not None
                             else np.zeros(0, np.int64))}

    @classmethod
    def from_arrays(cls, a, n_active, method):
        pt = np.asarray(a["pt_start"], np.int64)
        return cls(lo=np.asarray(a["lo"], np.int64), hi=np.asarray(a["hi"], np.int64),
                   first=np.asarray(a["first"], np.int64),
                   parent=np.asarray(a["parent"], np.int64),
                   leaf=np.asarray(a["leaf"]).astype(bool),
                   bptr=np.asarray(a["bptr"], np.int64),
                   boundary=np.asarray(a["boundary"], np.int64), n_active=int(n_active),
                   method=str(method), pt_start=pt if len(pt) else None)


# -- separators ---------------------------------------------------------------------------

@njit(cache=True)
def _konig_cover(nl, nr, ptr, adj):
    """Maximum matching of a bipartite graph (augmenting paths, Kuhn) and the minimum
    vertex cover it gives (König): the left vertices not reached and the right vertices
    reached by alternating paths from the unmatched left ones."""
    match_l = np.full(nl, -1, np.int64)
    match_r = np.full(nr, -1, np.int64)
    stamp = np.zeros(nr, np.int64)
    stack_u = np.empty(nl + 1, np.int64)
    stack_e = np.empty(nl + 1, np.int64)
    via = np.empty(nl + 1, np.int64)
    for root in range(nl):
        top = 0
        stack_u[0] = root
        stack_e[0] = ptr[root]
        found = -1
        while top >= 0:
            u = stack_u[top]
            e = stack_e[top]
            if e == ptr[u + 1]:
                top -= 1
                continue
            stack_e[top] = e + 1
            v = adj[e]
            if stamp[v] == root + 1:
                continue
            stamp[v] = root + 1
            via[top] = v
            if match_r[v] == -1:
                found = top
                break
            top += 1
            stack_u[top] = match_r[v]
            stack_e[top] = ptr[match_r[v]]
        for lev in range(found, -1, -1):
            match_l[stack_u[lev]] = via[lev]
            match_r[via[lev]] = stack_u[lev]
    vis_l = np.zeros(nl, np.bool_)
    vis_r = np.zeros(nr, np.bool_)
    queue = np.empty(nl, np.int64)
    head = tail = 0
    for u in range(nl):
        if match_l[u] == -1:
            vis_l[u] = True
            queue[tail] = u
            tail += 1
    while head < tail:
        u = queue[head]
        head += 1
        for e in range(ptr[u], ptr[u + 1]):
            v = adj[e]
            if not vis_r[v]:
                vis_r[v] = True
                w = match_r[v]
                if w >= 0 and not vis_l[w]:
                    vis_l[w] = True
                    queue[tail] = w
                    tail += 1
    return ~vis_l, vis_r


def _separator(verts, side, es, et):
    """The vertex separator of a cut of ``verts`` into ``side`` 0 and 1 (``side`` indexed by
    position in ``verts``; ``es``, ``et`` the part's edges as positions): a minimum vertex
    cover of the cut edges (:func:`_cut_cover`)."""
    return _cut_cover(side, es, et)


@njit(cache=True)
def _cut_edge(side, a, b):
    """An edge ``(a, b)`` as (side-0 end, side-1 end), or (-1, -1) when it is not cut."""
    if side[a] == side[b]:
        return -1, -1
    if side[a] != 0:
        return b, a
    return a, b


@njit(cache=True)
def _cut_cover(side, es, et):
    """A minimum vertex cover of the edges between side 0 and side 1 (positions): the cut's
    bipartite graph in compressed rows, left (side 0) vertices numbered as met, and König's
    cover of it (:func:`_konig_cover`)."""
    n = side.shape[0]
    lid = np.full(n, -1, np.int64)
    rid = np.full(n, -1, np.int64)
    lpos = np.empty(n, np.int64)
    rpos = np.empty(n, np.int64)
    ptr = np.zeros(n + 1, np.int64)   # (first nl + 1 used) cut edges per left vertex
    nl = nr = nc = 0
    for e in range(es.shape[0]):      # number the cut's vertices, count its edges
        a, b = _cut_edge(side, es[e], et[e])
        if a < 0:
            continue
        if lid[a] < 0:
            lid[a] = nl
            lpos[nl] = a
            nl += 1
        if rid[b] < 0:
            rid[b] = nr
            rpos[nr] = b
            nr += 1
        ptr[lid[a] + 1] += 1
        nc += 1
    if nc == 0:
        return np.zeros(0, np.int64)
    ptr = ptr[:nl + 1]
    for u in range(nl):
        ptr[u + 1] += ptr[u]
    fill = ptr[:-1].copy()
    adj = np.empty(nc, np.int64)
    for e in range(es.shape[0]):      # the right neighbours of each left vertex
        a, b = _cut_edge(side, es[e], et[e])
        if a < 0:
            continue
        adj[fill[lid[a]]] = rid[b]
        fill[lid[a]] += 1
    in_l, in_r = _konig_cover(nl, nr, ptr, adj)
    out = np.empty(int(in_l.sum()) + int(in_r.sum()), np.int64)
    j = 0
    for u in range(nl):
        if in_l[u]:
            out[j] = lpos[u]
            j += 1
    for v in range(nr):
        if in_r[v]:
            out[j] = rpos[v]
            j += 1
    return out


def _geometric_cut(pos, es, et):
    """Side (0/1) of each station of a part and its separator (positions in the part):
    across the principal axis of the positions, the cut with the fewest separator stations
    among a few near the median (ties: nearer the median)."""
    n = len(pos)
    c = pos - pos.mean(axis=0)
    scale = np.abs(c).max()
    if not np.isfinite(scale) or scale == 0.0:
        return None
    _, _, vt = np.linalg.svd(c / scale, full_matrices=False)
    best = None
    for axis in vt[:AXES]:
        order = np.argsort(c @ axis, kind="stable")
        for frac in CUT_FRACTIONS:
            k = min(n - 1, max(1, int(round(frac * n))))
            side = np.ones(n, np.int8)
            side[order[:k]] = 0
            sep = _separator(None, side, es, et)
            if best is None or len(sep) < len(best[1]):
                best = (side, sep)
    return best


# -- the tree -----------------------------------------------------------------------------

class _Node:
    __slots__ = ("own", "children", "leaf")

    def __init__(self, own, leaf):
        self.own, self.children, self.leaf = own, [], leaf


def _dissect(verts, es, et, pos, leaf_stations):
    """The subtree(s) of the part ``verts`` (station numbers; ``es``, ``et`` its edges as
    positions in ``verts``): a list of root nodes (several when the part falls apart)."""
    roots = []
    todo = [(verts, es, et, roots)]
    while todo:
        v, a, b, out = todo.pop()
        n = len(v)
        if n <= leaf_stations:
            out.append(_Node(v, True))
            continue
        cut = _geometric_cut(pos[v], a, b)
        if cut is None or len(cut[1]) >= n // 2:   # no useful separator: a (large) leaf
            out.append(_Node(v, True))
            continue
        side, sep = cut
        in_sep = np.zeros(n, bool)
        in_sep[sep] = True
        node = None
        if len(sep):
            node = _Node(v[sep], False)
            out.append(node)
        for s in (0, 1):
            keep = (side == s) & ~in_sep
            idx = np.full(n, -1, np.int64)
            idx[keep] = np.arange(int(keep.sum()))
            e = keep[a] & keep[b]
            if keep.any():
                todo.append((v[keep], idx[a[e]], idx[b[e]],
                             node.children if node is not None else out))
    return roots


def nested_dissection(pos, active, edges, leaf_stations=LEAF_STATIONS):
    """The partition tree of the active stations by geometric bisection, and the logical
    order it gives (:func:`supernodal_tree` for METIS' graph method).

    ``pos`` (n x d) station positions, ``active`` the
    stations in the adjustment, ``edges = (s, t)`` the station graph (station numbers).
    Returns ``(tree, perm)``: ``perm`` the stations in logical order (the tree's post-order,
    then the inactive stations), ``tree`` with logical station numbers.
    """
    n_st = len(active)
    act = np.flatnonzero(active)
    s, t = (np.asarray(x, np.int64) for x in edges)
    keep = active[s] & active[t]
    s, t = s[keep], t[keep]
    idx = np.full(n_st, -1, np.int64)
    idx[act] = np.arange(len(act))
    es, et = idx[s], idx[t]
    # the components first: each its own subtree
    n = len(act)
    g = csr_matrix((np.ones(len(es), np.int8), (es, et)), shape=(n, n))
    n_comp, label = connected_components(g, directed=False)
    roots = []
    pos = np.asarray(pos, np.float64)
    for c in range(n_comp):
        mask = label == c
        loc = np.full(n, -1, np.int64)
        loc[mask] = np.arange(int(mask.sum()))
        e = mask[es]
        roots.extend(_dissect(act[mask], loc[es[e]], loc[et[e]], pos, leaf_stations))
    return _number(roots, n_st, act, s, t, "geometric")


def _number(roots, n_st, act, s, t, method):
    """Post-order numbering of the nodes and stations; boundaries from the graph."""
    perm = np.empty(n_st, np.int64)
    lo, hi, first, parent, leaf = [], [], [], [], []
    at = 0
    # iterative post-order: (node, parent index placeholder, expanded?)
    stack = [(r, -1, False, None) for r in reversed(roots)]
    pending_parent = []
    while stack:
        node, par, expanded, start = stack.pop()
        if not expanded:
            stack.append((node, par, True, at))
            for ch in reversed(node.children):
                stack.append((ch, None, False, None))
            continue
        i = len(lo)
        k = len(node.own)
        perm[at:at + k] = node.own
        lo.append(at)
        hi.append(at + k)
        first.append(start)
        leaf.append(node.leaf)
        parent.append(-1)
        pending_parent.append(node)
        node.own = i  # reuse the slot: the node's number, for its children's parent links
        at += k
    for i, node in enumerate(pending_parent):
        for ch in node.children:
            parent[ch.own] = i
    n_active = at
    inactive = np.setdiff1d(np.arange(n_st), act)
    perm[at:] = inactive
    tree = Tree(lo=np.array(lo, np.int64), hi=np.array(hi, np.int64),
                first=np.array(first, np.int64), parent=np.array(parent, np.int64),
                leaf=np.array(leaf, bool), bptr=np.zeros(1, np.int64),
                boundary=np.zeros(0, np.int64), n_active=n_active, method=method)
    pos = np.empty(n_st, np.int64)
    pos[perm] = np.arange(n_st)
    set_boundaries(tree, pos[s], pos[t])
    return tree, perm


#: Relaxed amalgamation of supernodes (as CHOLMOD's nrelax and zrelax, in stations): a
#: child is merged into its parent when together they have at most ``n`` own stations and
#: the explicit zeros are at most the fraction ``z`` of the merged front's entries.
RELAX = ((8, 1.0), (32, 0.5), (96, 0.1))


def supernodal_tree(active, edges, k=6, relax=RELAX):
    """The tree of METIS' multilevel nested dissection ordering (``METIS_NodeND`` through
    ``pymetis.nested_dissection``): the elimination tree of the station graph in that
    order, postordered (each subtree contiguous), its chains of stations of equal structure
    merged into supernodes, and small supernodes amalgamated with their parents when few
    zeros come with it (``relax``: bigger fronts for BLAS-3 at the bottom of the tree, as
    sparse direct solvers do). Returns ``(tree, perm)`` as :func:`nested_dissection`."""
    import pymetis

    from ..symbolic import _column_counts, _csr

    n_st = len(active)
    act = np.flatnonzero(active)
    n = len(act)
    s, t = (np.asarray(x, np.int64) for x in edges)
    keep = active[s] & active[t]
    s, t = s[keep], t[keep]
    idx = np.full(n_st, -1, np.int64)
    idx[act] = np.arange(n)
    es, et = idx[s], idx[t]
    indptr, indices = _csr(n, es, et)
    if n > 1 and len(indices):
        perm, _ = pymetis.nested_dissection(adjacency=pymetis.CSRAdjacency(
            adj_starts=indptr, adjacent=indices))
        perm = np.asarray(perm, np.int64)
    else:
        perm = np.arange(n)
    inv = np.empty(n, np.int64)
    inv[perm] = np.arange(n)
    counts, parent, post = _column_counts(n, indptr, indices, inv)
    # renumber in postorder
    order = perm[post]                      # local station of each column, postordered
    newpos = np.empty(n, np.int64)
    newpos[post] = np.arange(n)
    par = np.where(parent[post] >= 0, newpos[np.maximum(parent[post], 0)], -1)
    cnt = counts[post]
    nchild = np.bincount(par[par >= 0], minlength=n)
    # fundamental supernodes: column j joins j - 1 when j is j-1's parent, j-1 its only
    # child, and their structures agree
    start = np.ones(n, bool)
    if n > 1:
        j = np.arange(1, n)
        start[1:] = ~((par[j - 1] == j) & (nchild[j] == 1) & (cnt[j - 1] == cnt[j] + 1))
    c0 = np.flatnonzero(start)
    c1 = np.append(c0[1:], n)
    sn_of = np.cumsum(start) - 1
    m = len(c0)
    sp = np.where(par[c1 - 1] >= 0, sn_of[np.maximum(par[c1 - 1], 0)], -1)
    bnd = cnt[c0] - (c1 - c0)               # boundary stations of each supernode
    csum = np.concatenate([[0], np.cumsum(cnt)])
    lo, hi = c0.astype(np.int64), c1.astype(np.int64)
    sp = sp.astype(np.int64)
    alive = _amalgamate(lo, hi, sp, bnd.astype(np.int64), csum.astype(np.int64),
                        np.array([nr for nr, _ in relax], np.int64),
                        np.array([zr for _, zr in relax], np.float64))
    live = np.flatnonzero(alive)
    new_id = np.full(m, -1, np.int64)
    new_id[live] = np.arange(len(live))
    parent_n = np.where(sp[live] >= 0, new_id[np.maximum(sp[live], 0)], -1)
    nn = len(live)
    first = lo[live].copy()
    for i in range(nn):                      # a subtree starts at its first descendant
        p_ = parent_n[i]
        if p_ >= 0:
            first[p_] = min(first[p_], first[i])
    has_child = np.zeros(nn, bool)
    has_child[parent_n[parent_n >= 0]] = True
    tree = Tree(lo=lo[live].astype(np.int64), hi=hi[live].astype(np.int64), first=first,
                parent=parent_n.astype(np.int64), leaf=~has_child,
                bptr=np.zeros(1, np.int64), boundary=np.zeros(0, np.int64), n_active=n,
                method="graph")
    full = np.empty(n_st, np.int64)
    full[:n] = act[order]
    full[n:] = np.setdiff1d(np.arange(n_st), act)
    pos = np.empty(n_st, np.int64)
    pos[full] = np.arange(n_st)
    set_boundaries(tree, pos[s], pos[t])
    return tree, full


@njit(cache=True)
def _amalgamate(lo, hi, sp, bnd, csum, nrelax, zrelax):
    """:func:`supernodal_tree`'s relaxed amalgamation, children before parents: a supernode
    ``a`` that is its parent's last child (their stations adjacent) joins it when together
    they have at most ``nrelax[r]`` own stations and the explicit zeros (the child's columns
    taking the parent's structure, counted from the column counts' sums ``csum``) are at
    most ``zrelax[r]`` of the merged front's entries, for some ``r``. Updates ``lo`` and
    ``sp`` (parents: a merged node's children go to the node it joined) in place; returns
    which supernodes remain."""
    m = lo.shape[0]
    zeros = np.zeros(m)
    alive = np.ones(m, np.bool_)
    into = np.full(m, -1, np.int64)
    for a in range(m):
        q = sp[a]
        if q < 0 or hi[a] != lo[q]:
            continue                         # not the last child: its stations are not adjacent
        cols = hi[q] - lo[a]
        # the child's columns take the parent's structure: the zeros that brings
        z = 0.0
        for col in range(lo[a], hi[a]):
            z += hi[q] - col + bnd[q]
        z -= csum[hi[a]] - csum[lo[a]]
        total_z = zeros[a] + zeros[q] + z
        entries = cols * (cols + 1) / 2 + cols * bnd[q]
        for r in range(nrelax.shape[0]):
            if cols <= nrelax[r] and total_z <= zrelax[r] * entries:
                lo[q] = lo[a]
                zeros[q] = total_z
                alive[a] = False
                into[a] = q
                break
    for c in range(m):   # the children of merged supernodes: of the supernode they joined
        q = sp[c]
        while q >= 0 and not alive[q]:
            q = into[q]
        sp[c] = q
    return alive


def set_boundaries(tree, s, t):
    """Each node's boundary from the logical edges ``(s, t)``: the stations after its
    subtree adjacent to its own stations or in a child's boundary (bottom-up)."""
    n = max(int(tree.n_active), int(max(s.max(), t.max()) + 1) if len(s) else 0)
    a = np.concatenate([s, t]).astype(np.int64)
    b = np.concatenate([t, s]).astype(np.int64)
    order = np.argsort(a, kind="stable")
    a, b = a[order], b[order]
    ptr = np.searchsorted(a, np.arange(n + 1))
    par = np.asarray(tree.parent, np.int64)
    kids = np.flatnonzero(par >= 0)
    corder = kids[np.argsort(par[kids], kind="stable")]   # children by parent, in order
    cptr = np.searchsorted(par[corder], np.arange(tree.n_nodes + 1))
    tree.__dict__.pop("_links", None)   # (places worked out for the old boundaries)
    tree.bptr, tree.boundary = _boundaries(np.asarray(tree.lo, np.int64),
                                           np.asarray(tree.hi, np.int64), ptr, b, cptr,
                                           corder, n)


@njit(cache=True)
def _append(out, m, y):
    """``out[m] = y``, ``out`` doubled first when full; returns ``out``."""
    if m == out.shape[0]:
        grown = np.empty(2 * m, out.dtype)
        grown[:m] = out[:m]
        out = grown
    out[m] = y
    return out


@njit(cache=True)
def _boundaries(lo, hi, ptr, b, cptr, corder, n):
    """:func:`set_boundaries`' sweep: nodes in post-order, each node's boundary the
    distinct stations ``>= hi`` among its own stations' neighbours (``b[ptr[s]:ptr[s+1]]``)
    and its children's boundaries (``corder[cptr[i]:cptr[i+1]]``), ascending."""
    nn = lo.shape[0]
    mark = np.full(n, -1, np.int64)
    bptr = np.zeros(nn + 1, np.int64)
    out = np.empty(max(16, b.shape[0] // 2), np.int64)   # (doubled when full)
    m = 0
    for i in range(nn):
        start = m
        h = hi[i]
        for e in range(ptr[lo[i]], ptr[h]):
            y = b[e]
            if y >= h and mark[y] != i:
                mark[y] = i
                out = _append(out, m, y)
                m += 1
        for q in range(cptr[i], cptr[i + 1]):
            c = corder[q]
            for e in range(bptr[c], bptr[c + 1]):
                y = out[e]
                if y >= h and mark[y] != i:
                    mark[y] = i
                    out = _append(out, m, y)
                    m += 1
        out[start:m] = np.sort(out[start:m])
        bptr[i + 1] = m
    return bptr, out[:m].copy()


def check_separators(tree, s, t):
    """True when every logical edge joins a node's stations to its own or its ancestors':
    the tree's separators separate (a test's invariant and the adjustment's guard)."""
    owner = np.empty(tree.n_active, np.int64)
    for i in range(tree.n_nodes):
        owner[tree.lo[i]:tree.hi[i]] = i
    a, b = np.minimum(s, t), np.maximum(s, t)
    inside = b < tree.n_active
    a, b = a[inside], b[inside]
    # the later station must be in the front of the earlier station's node
    na = owner[a]
    ok = np.ones(len(a), bool)
    for i in np.unique(na):
        sel = na == i
        f = tree.front(i)
        ok[sel] = np.isin(b[sel], f)
    return bool(ok.all())


def best_tree(pos, active, edges, leaf_stations=LEAF_STATIONS, methods=None, k=6,
              enough=None):
    """The tree of the smaller predicted factorisation time (flops and nodes) of the
    geometric bisection and METIS' nested dissection (:func:`supernodal_tree`; ``methods``
    to restrict them). ``enough(seconds)``: when it says the first tree's predicted time
    settles the matter (a long strip, where the band wins by far), the second is not
    built. Returns ``(tree, perm, {method: flops})``."""
    from ..ordering import TREE_NODE_SECONDS, TREE_RATE

    methods = methods or ("geometric", "graph")
    found = {}
    for m in methods:
        if found and enough is not None:
            first = next(iter(found.values()))
            if enough(first[0] / TREE_RATE + TREE_NODE_SECONDS * first[1].n_nodes):
                break
        if m == "geometric" and (pos is None or not np.isfinite(pos).all()):
            continue
        if m == "graph":   # (a smaller leaf also caps the amalgamation)
            relax = tuple((min(nr, leaf_stations), zr) for nr, zr in RELAX)
            tree, perm = supernodal_tree(active, edges, k, relax)
        else:
            tree, perm = nested_dissection(pos, active, edges, leaf_stations)
        found[m] = (tree.figures(k)["flops"], tree, perm)

    def seconds(m):   # flops at the fronts' rate and the cost per node
        return found[m][0] / TREE_RATE + TREE_NODE_SECONDS * found[m][1].n_nodes

    best = min(found, key=seconds)
    return found[best][1], found[best][2], {m: v[0] for m, v in found.items()}
