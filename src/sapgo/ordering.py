"""Station graph, band width and the bandwidth-minimising logical order (DESIGN section 4).

The station graph has one node per exposure station and an edge between two stations that
observe a common point. For a logical order ``pos`` (``pos[s]`` = logical number of station
``s``) the band width of the reduced normal equations, counted in stations as SAPGO counts it
(the diagonal station included; seeds/002 Table 4), is

    b = 1 + max over edges (s, t) of |pos[s] - pos[t]|.

Candidate orders: across-strip (->S, photo columns numbered across the strips; also by plain
along-track coordinate), down-strip (->G, strip after strip) and reverse Cuthill-McKee
(``scipy.sparse.csgraph``) on the graph; the one with the smallest band width wins (ties: the
smallest profile). Points are then sorted by (min logical station, max logical station) so
that a single pass over the points builds the band rows in order (seeds/002, "Data sorting").

Undeterminable data are left out before ordering: a pass or check point needs two active rays
(a full or vertical control point one), a station needs three active points; both rules are
applied until nothing changes. Excluded records stay in the project with status 1; excluded
stations go to the end of the order, excluded points after all active ones.
"""

from __future__ import annotations

import contextlib
import dataclasses
import shutil
from pathlib import Path

import math

import numpy as np
from numba import njit

from . import paging
from .lock import writes_project
from .errors import ParameterError
from .extsort import (DEFAULT_MEMORY, ExternalSorter, _key_order, parse_memory, rechunk,
                      records_at)
from .project import (
    CHECKSUM,
    CHUNK_RECORDS,
    KEYED_GROUPS,
    KIND_CONTROL,
    KIND_VERTICAL,
    OBSERVATION_DTYPE,
    POINT_DTYPE,
    SOLUTION_LAYOUT,
    STATUS_ACTIVE,
    STATUS_EXCLUDED,
    STATUS_REJECTED,
    TRUTH_POINT_DTYPE,
    Project,
    ProjectWriter,
    PHOTO_CAMERA_NARROW,
    RECORD_DTYPES,
    TRUTH_DTYPES,
    append_history,
    solution_dataset,
)

MIN_RAYS_PASS = 2
MIN_POINTS_PER_STATION = 3
#: At most this many ids of excluded points or stations are listed.
LISTED_IDS = 1000


@dataclasses.dataclass
class OrderResult:
    """What :func:`order_project` did."""

    band_width_before: int
    band_width: int
    ordering: str
    candidates: dict  # ordering name -> band width
    excluded_points: list  # ids of points left out (too few rays), at most LISTED_IDS
    excluded_stations: list  # ids of stations left out (too few points), at most LISTED_IDS
    n_excluded_points: int = 0
    n_excluded_stations: int = 0
    seconds: float = 0.0
    solver: str = "band"  # "band" or "tree": what the order was made for
    tree: dict | None = None  # the tree's figures (Tree.figures) when solver is "tree"
    predicted: dict | None = None  # solver -> predicted seconds of one factorisation

    def to_dict(self):
        return dataclasses.asdict(self)


# -- station graph ---------------------------------------------------------------------

@njit(cache=True)
def _point_pairs(obs_start, n_obs, obs_station, obs_active, n_stations):
    """All station pairs (s < t) that share a point, encoded ``s * n + t``."""
    total = 0
    for j in range(obs_start.shape[0]):
        k = 0
        for i in range(obs_start[j], obs_start[j] + n_obs[j]):
            if obs_active[i]:
                k += 1
        total += k * (k - 1) // 2
    out = np.empty(total, np.int64)
    m = 0
    buf = np.empty(64, np.int64)
    for j in range(obs_start.shape[0]):
        k = 0
        for i in range(obs_start[j], obs_start[j] + n_obs[j]):
            if obs_active[i]:
                if k == buf.shape[0]:
                    nb = np.empty(2 * k, np.int64)
                    nb[:k] = buf
                    buf = nb
                buf[k] = obs_station[i]
                k += 1
        for a in range(k):
            for c in range(a + 1, k):
                s, t = buf[a], buf[c]
                if s == t:
                    continue
                if s > t:
                    s, t = t, s
                out[m] = s * n_stations + t
                m += 1
    return out[:m]


def station_edges(obs_start, n_obs, obs_station, obs_active, n_stations, chunk=65536):
    """Unique edges ``(s, t)``, ``s < t``, of the station graph as two int64 arrays."""
    keys = np.zeros(0, np.int64)
    n_points = len(obs_start)
    for a in range(0, n_points, chunk):
        b = min(n_points, a + chunk)
        k = _point_pairs(obs_start[a:b], n_obs[a:b], obs_station, obs_active, n_stations)
        keys = np.union1d(keys, k)
    return keys // n_stations, keys % n_stations


@njit(cache=True)
def _spans(pos, s, t, reach):
    """Largest |pos[s] - pos[t]| over the edges; ``reach[hi]`` = farthest earlier neighbour."""
    widest = 0
    for e in range(s.shape[0]):
        a = pos[s[e]]
        b = pos[t[e]]
        lo, hi = (a, b) if a < b else (b, a)
        d = hi - lo
        widest = max(widest, d)
        reach[hi] = max(reach[hi], d)
    return widest


#: Edges a numba pass over the station graph takes at a time (the edges may be mapped:
#: :func:`sapgo.paging.rows` returns their pages between the chunks).
EDGE_CHUNK = 1 << 22


def _edge_spans(pos, edges, reach):
    """:func:`_spans` over the edges a chunk at a time."""
    s, t = edges
    pos = np.asarray(pos, np.int64)
    widest = 0
    for a, b in paging.rows(len(s), EDGE_CHUNK):
        widest = max(widest, int(_spans(pos, s[a:b], t[a:b], reach)))
    return widest


def band_width_of(pos, edges):
    """Band width (stations, diagonal included) of logical order ``pos`` over ``edges``."""
    if len(edges[0]) == 0:
        return 1
    return 1 + _edge_spans(pos, edges, paging.zeros(len(pos), np.int64))


def band_and_profile(pos, edges):
    """``(band_width_of(pos, edges), profile_of(pos, edges))`` from one pass over the
    edges."""
    if len(edges[0]) == 0:
        return 1, 0
    reach = paging.zeros(len(pos), np.int64)
    span = _edge_spans(pos, edges, reach)
    return 1 + span, sum(int(reach[a:b].sum()) for a, b in paging.rows(len(reach)))


def profile_of(pos, edges):
    """Sum over stations of the distance to their farthest earlier neighbour (tie-breaker)."""
    if len(edges[0]) == 0:
        return 0
    reach = paging.zeros(len(pos), np.int64)
    _edge_spans(pos, edges, reach)
    return sum(int(reach[a:b].sum()) for a, b in paging.rows(len(reach)))


def _adjacency(n, s, t, indptr, indices):
    """Symmetric CSR adjacency of the edges ``(s, t)`` (``indptr`` zero on entry), the
    edges a chunk at a time (:data:`EDGE_CHUNK`)."""
    for a, b in paging.rows(len(s), EDGE_CHUNK):
        _degrees(s[a:b], t[a:b], indptr)
    carry = 0
    for a, b in paging.rows(n + 1):   # (the prefix sums, a chunk at a time)
        seg = np.cumsum(indptr[a:b], dtype=np.int64) + carry
        indptr[a:b] = seg
        carry = int(seg[-1])
    fill = np.array(indptr[:-1])
    for a, b in paging.rows(len(s), EDGE_CHUNK):
        _fill_adjacency(s[a:b], t[a:b], fill, indices)


def reverse_cuthill_mckee(indptr, indices):
    """Reverse Cuthill-McKee order of the symmetric graph in CSR form (``indptr``,
    ``indices``; no self loops): ``perm[k]`` is the node numbered k-th.

    The algorithm of ``scipy.sparse.csgraph.reverse_cuthill_mckee`` (Cuthill & McKee 1969,
    reversed as George 1971): each component from its unvisited node of least degree, a
    breadth-first search whose new nodes are numbered by increasing degree, and the whole
    order reversed. Two differences: every tie (seed and neighbours of equal degree) is
    broken by node number, where SciPy's ``np.argsort`` leaves the seed to the sort kernel
    the CPU selects, so the order is the same on every machine; and the arrays are
    :mod:`sapgo.paging` vectors visited a bounded number of nodes at a time, so that a
    10 000 000-photo graph is never copied into core (SciPy 1.17 copies it: 1.1 GB).
    """
    n = len(indptr) - 1
    perm = paging.empty(n, np.int32)
    if n == 0:
        return perm.astype(np.int64)
    # the nodes by increasing degree, ties by number (a counting sort: stable)
    hist = np.zeros(2, np.int64)
    for a, b in paging.rows(n):
        d = np.diff(np.asarray(indptr[a:b + 1], np.int64))
        top = int(d.max()) + 2
        if top > len(hist):
            hist = np.concatenate([hist, np.zeros(top - len(hist), np.int64)])
        hist += np.bincount(d + 1, minlength=len(hist))
    start = np.cumsum(hist)[:-1]        # (first slot of each degree)
    by_degree = paging.empty(n, np.int32)
    for a, b in paging.rows(n):
        _place_by_degree(indptr, a, b, start, by_degree)
    visited = paging.zeros(n, np.uint8)
    order = paging.empty(n, np.int32)
    state = np.zeros(3, np.int64)       # (head and tail of the queue, next seed candidate)
    while state[0] < n:
        _cuthill_mckee_steps(indptr, indices, by_degree, visited, order, state, CM_STEPS)
        paging.release()
    del by_degree, visited
    for a, b in paging.rows(n):
        perm[a:b] = order[n - b:n - a][::-1]
    return perm


#: Nodes numbered per call of :func:`_cuthill_mckee_steps` (the maps' pages are released
#: between calls).
CM_STEPS = 1 << 18


@njit(cache=True)
def _place_by_degree(indptr, a, b, start, by_degree):
    for i in range(a, b):
        d = indptr[i + 1] - indptr[i]
        by_degree[start[d]] = i
        start[d] += 1


@njit(cache=True)
def _cuthill_mckee_steps(indptr, indices, by_degree, visited, order, state, steps):
    """Number up to ``steps`` more nodes of the Cuthill-McKee breadth-first search whose
    queue is ``order[head:tail]`` (``state = head, tail, seed``); resumable."""
    n = order.shape[0]
    head, tail, seed = state[0], state[1], state[2]
    done = 0
    while head < n and done < steps:
        if head == tail:      # (a new component: its unvisited node of least degree)
            while visited[by_degree[seed]]:
                seed += 1
            v = by_degree[seed]
            visited[v] = 1
            order[tail] = v
            tail += 1
        i = order[head]
        head += 1
        first = tail
        for k in range(indptr[i], indptr[i + 1]):
            j = indices[k]
            if not visited[j]:
                visited[j] = 1
                order[tail] = j
                tail += 1
        # the new nodes by increasing degree (insertion sort: stable, as in SciPy)
        for k in range(first + 1, tail):
            j = order[k]
            d = indptr[j + 1] - indptr[j]
            m = k
            while m > first and indptr[order[m - 1] + 1] - indptr[order[m - 1]] > d:
                order[m] = order[m - 1]
                m -= 1
            order[m] = j
        done += 1
    state[0], state[1], state[2] = head, tail, seed


@njit(cache=True)
def _degrees(s, t, indptr):
    for e in range(s.shape[0]):
        indptr[s[e] + 1] += 1
        indptr[t[e] + 1] += 1


@njit(cache=True)
def _fill_adjacency(s, t, fill, indices):
    for e in range(s.shape[0]):
        indices[fill[s[e]]] = t[e]
        fill[s[e]] += 1
        indices[fill[t[e]]] = s[e]
        fill[t[e]] += 1


# -- candidate orders ------------------------------------------------------------------

def _flight_axes(xy, strip):
    """Unit vectors along and across the flight lines, from the strips if they are known."""
    dirs = []
    if (strip >= 0).all():
        order = np.argsort(strip, kind="stable")
        cuts = np.flatnonzero(np.diff(strip[order])) + 1
        for group in np.split(order, cuts):
            p = xy[group]
            if len(p) >= 2:
                c = p - p.mean(axis=0)
                _, _, vt = np.linalg.svd(c, full_matrices=False)
                d = vt[0]
                if dirs and np.dot(d, dirs[0]) < 0:
                    d = -d
                dirs.append(d)
    if dirs:
        along = np.mean(dirs, axis=0)
    elif len(xy) >= 3:
        # strips unknown: the photos' nearest neighbours lie along the flight lines (the base
        # is shorter than the strip spacing); their mean axis, directions taken mod 180 deg
        d = _nearest(xy)[1]
        angle = np.angle(np.mean(np.exp(2j * np.arctan2(d[:, 1], d[:, 0])))) / 2.0
        along = np.array([math.cos(angle), math.sin(angle)])
    else:
        c = xy - xy.mean(axis=0)
        _, _, vt = np.linalg.svd(c, full_matrices=False) if len(xy) >= 2 else (0, 0, np.eye(2))
        along = vt[0]
    n = np.linalg.norm(along)
    along = along / n if n > 0 else np.array([1.0, 0.0])
    return along, np.array([-along[1], along[0]])


def _nearest(xy):
    """Each point's distance and vector to its nearest other point (a k-d tree)."""
    from scipy.spatial import cKDTree

    dist, j = cKDTree(xy).query(xy, k=2)
    return dist[:, 1], xy[j[:, 1]] - xy


def _columns(u, labels, base, order=None):
    """Photo column numbers: counted photo by photo along each strip, so they do not drift.

    A global ``u / base`` drifts by a column every few thousand photos when ``base`` is
    estimated to a part in 10^4; counting the gaps between neighbours (each rounded to a
    whole number of bases) keeps neighbouring strips' columns aligned over any length. A
    strip starts at a quarter-base column: a strip shifted by half a base lies between its
    neighbours' columns. A strip of another photo scale (its base 2 % or more from the
    block's) is not in the block's columns: each of its photos goes to the quarter-base
    column of its position. ``order``: ``np.lexsort((u, labels))`` when the caller has it.
    """
    column = paging.zeros(len(u), np.float64)
    if base <= 0 or len(u) == 0:
        return column
    umin = min(float(u[a:b].min()) for a, b in paging.rows(len(u)))
    if order is None:
        order = np.lexsort((u, labels))
    lab = paging.take(labels, order)
    us = paging.take(u, order)
    cuts = np.concatenate([[0]] + [a + 1 + np.flatnonzero(np.diff(lab[a:b + 1]))
                                   for a, b in paging.rows(len(lab) - 1)])[1:].astype(np.int64)
    for a, b in zip(np.concatenate([[0], cuts]), np.concatenate([cuts, [len(us)]])):
        gaps = np.diff(us[a:b])
        pos = gaps[gaps > 0]
        if len(pos) and abs(float(np.median(pos)) / base - 1.0) >= 0.02:
            # a strip of another photo scale (its own base 2 % or more from the block's):
            # its photos are not in the block's columns; each goes to the quarter-base
            # column of its position
            column[order[a:b]] = np.rint(4.0 * (us[a:b] - umin) / base) / 4.0
            continue
        steps = np.maximum(1, np.rint(gaps / base)).astype(np.int64)
        # (a strip's first column to a quarter of a base: strips shifted by part of a base,
        # as in a shifted flight, keep their own columns between their neighbours')
        first = np.rint(4.0 * (us[a] - umin) / base) / 4.0
        column[order[a:b]] = first + np.concatenate([[0], np.cumsum(steps)])
    return column


def grid_coordinates(xy, strip):
    """The stations on the grid of the block: ``(u, v, column, labels, strip_key)``.

    ``u``, ``v``: positions along and across the flight lines; ``column``: photo columns
    counted photo by photo along each strip (:func:`_columns`); ``labels``: strip numbers
    0, 1, ... (from ``strip``, or, where the strips are unknown, a new strip wherever the
    across-track gap exceeds half a base); ``strip_key``: each station's strip position
    across the flight lines (its strip's mean ``v``)."""
    along, across = _flight_axes(xy, strip)
    n = len(xy)
    u, v = paging.empty(n), paging.empty(n)
    for a, b in paging.rows(n):   # (a chunk at a time: the arrays may be mapped)
        u[a:b] = xy[a:b] @ along
        v[a:b] = xy[a:b] @ across
    known = all(bool((strip[a:b] >= 0).all()) for a, b in paging.rows(n))
    order = None
    # photo spacing along the strips: median gap between neighbours sorted along track
    if known:
        labels = _labels(strip)
        order = np.lexsort((u, labels))
        gaps = paging.empty(max(0, n - 1))
        m = 0
        for a, b in paging.rows(n - 1):
            o = order[a:b + 1]
            g = np.diff(u[o])[np.diff(labels[o]) == 0]
            g = g[g > 0]
            gaps[m:m + len(g)] = g
            m += len(g)
        gaps = gaps[:m]
    elif len(xy) >= 3:  # strips unknown: the distance to the nearest photo
        gaps = _nearest(xy)[0]
        gaps = gaps[gaps > 0]
    else:
        gaps = np.diff(np.sort(u))
        gaps = gaps[gaps > 0]
    base = float(np.median(gaps)) if len(gaps) else 1.0
    del gaps
    if known:
        k = max((int(labels[a:b].max()) for a, b in paging.rows(n)), default=-1) + 1
        total, count = np.zeros(k), np.zeros(k)
        for a, b in paging.rows(n):
            total += np.bincount(labels[a:b], v[a:b], minlength=k)
            count += np.bincount(labels[a:b], minlength=k)
        mean = total / np.maximum(count, 1)
        strip_key = paging.empty(n)
        for a, b in paging.rows(n):
            strip_key[a:b] = mean[labels[a:b]]
    else:  # strips unknown: a new strip wherever the across-track gap exceeds half a base
        vs = np.argsort(v)
        breaks = np.concatenate([[0], np.cumsum(np.diff(v[vs]) > 0.5 * base)])
        strip_key = np.empty(len(v))
        strip_key[vs] = breaks
        labels = strip_key.astype(np.int64)
    return u, v, _columns(u, labels, base, order), labels, strip_key


def _labels(x):
    """``np.unique(x, return_inverse=True)[1]``, a chunk at a time into a (possibly
    mapped) array: each value's rank among the distinct values."""
    uniq = np.zeros(0, np.asarray(x[:0]).dtype)
    for a, b in paging.rows(len(x)):
        uniq = np.union1d(uniq, x[a:b])
    out = paging.empty(len(x), np.int64)
    for a, b in paging.rows(len(x)):
        out[a:b] = np.searchsorted(uniq, x[a:b])
    return out


def grid_orders(kx, ky, across):
    """The diagonal and spiral orders of units on a grid of line numbers ``kx`` (columns
    along the strips) and ``ky`` (strips, in order across them); ``across`` breaks ties
    within a diagonal. ``{name: (perm, lines)}``: the diagonal lines ``kx + ky``, and the
    spiral's rings from the outside inwards (each ring by angle from its corner)."""
    n = len(kx)
    kd = paging.empty(n, np.int64)
    for a, b in paging.rows(n):   # (a chunk at a time: the arrays may be mapped)
        kd[a:b] = kx[a:b] + ky[a:b]
    out = {"diagonal": (np.lexsort((across, kd)), kd)}
    if len(kx):
        mx = max(int(kx[a:b].max()) for a, b in paging.rows(n))
        my = max(int(ky[a:b].max()) for a, b in paging.rows(n))
        cx, cy = mx / 2.0, my / 2.0
        ring, angle = paging.empty(n, np.int64), paging.empty(n)
        for a, b in paging.rows(n):
            x, y = kx[a:b], ky[a:b]
            ring[a:b] = np.minimum.reduce([x, mx - x, y, my - y])
            angle[a:b] = np.mod(np.arctan2(y - cy, x - cx) - math.pi, 2 * math.pi)
        out["spiral"] = (np.lexsort((angle, ring)), ring)
    else:
        out["spiral"] = (np.zeros(0, np.int64), np.zeros(0, np.int64))
    return out


#: The station orders ``sapgo order`` and ``adjust --ordering`` take: "best" (the least band
#: width of all) or one candidate of :func:`candidate_orders` by name.
ORDERINGS = ("best", "across_strip", "across_strip_by_position", "down_strip", "diagonal",
             "spiral", *(f"sweep_{deg}" for deg in range(0, 180, 15)),
             "reverse_cuthill_mckee")


def candidate_orders(xy, strip, active, edges, grid=None):
    """Candidate logical orders of the active stations: ``{name: perm}``.

    ``perm`` lists station record numbers in logical order (active stations only).
    ``grid``: the active stations' :func:`grid_coordinates`, when the caller has them.
    """
    return dict(iter_candidate_orders(xy, strip, active, edges, grid))


def iter_candidate_orders(xy, strip, active, edges, grid=None):
    """:func:`candidate_orders` one at a time, ``(name, perm)``: a scorer that keeps only
    the best holds two orders, not all 18 (8 bytes a station each)."""
    idx = paging.nonzero(active)
    if len(idx) == 0:
        yield "record", idx
        return
    xy = paging.take(xy, idx)
    u, v, column, labels, strip_key = grid or grid_coordinates(xy, paging.take(strip, idx))

    def ordered(perm):   # (the records of the active stations in the order perm)
        return paging.take(idx, perm)

    yield "across_strip", ordered(np.lexsort((v, column)))
    yield "across_strip_by_position", ordered(np.lexsort((v, u)))
    yield "down_strip", ordered(np.lexsort((u, strip_key)))
    # along the diagonals of the grid, and a spiral from the outside (Rostom's orderings)
    kx, ky = _labels(column), _labels(strip_key)
    del u, column, labels, strip_key
    for name, (perm, _) in grid_orders(kx, ky, v).items():
        yield name, ordered(perm)
    del kx, ky, v
    # sweeps across the block in 12 directions: for blocks of crossing flight lines
    d, e = paging.empty(len(idx)), paging.empty(len(idx))
    for deg in range(0, 180, 15):
        a = math.radians(deg)
        for i, j in paging.rows(len(idx)):
            d[i:j] = xy[i:j] @ np.array([math.cos(a), math.sin(a)])
            e[i:j] = xy[i:j] @ np.array([-math.sin(a), math.cos(a)])
        yield f"sweep_{deg}", ordered(np.lexsort((e, d)))
    del d, e, xy
    # reverse Cuthill-McKee on the active subgraph (CSR built directly, int32 indices)
    n = len(idx)
    local = paging.empty(len(active), np.int32)
    for i, j in paging.rows(len(active)):
        local[i:j] = -1
    for i, j in paging.rows(n):
        local[idx[i:j]] = np.arange(i, j)
    es, et = edges
    s, t = paging.empty(len(es), np.int32), paging.empty(len(es), np.int32)
    m = 0
    for i, j in paging.rows(len(es)):
        ls, lt = local[es[i:j]], local[et[i:j]]
        keep = (ls >= 0) & (lt >= 0)
        k = int(keep.sum())
        s[m:m + k], t[m:m + k] = ls[keep], lt[keep]
        m += k
    del local
    s, t = s[:m], t[:m]
    indptr = paging.zeros(n + 1, np.int32)
    indices = paging.empty(2 * m, np.int32)
    _adjacency(n, s, t, indptr, indices)
    del s, t
    yield "reverse_cuthill_mckee", ordered(reverse_cuthill_mckee(indptr, indices))


# -- exclusions ------------------------------------------------------------------------

def find_exclusions(kind, point_of_obs, station_of_obs, n_stations, obs_status=None):
    """Statuses of points, stations and observations after the exclusion rules.

    Returns boolean arrays ``point_active``, ``station_active``, ``obs_active``.
    """
    n_points = len(kind)
    obs_active = np.ones(len(point_of_obs), bool)
    if obs_status is not None:  # rejected observations stay out; exclusions are recomputed
        obs_active &= obs_status != STATUS_REJECTED
    point_active = np.ones(n_points, bool)
    station_active = np.ones(n_stations, bool)
    single_ok = (kind == KIND_CONTROL) | (kind == KIND_VERTICAL)
    while True:
        live = obs_active & point_active[point_of_obs] & station_active[station_of_obs]
        # rays and points are counted once per distinct (point, station) pair
        pairs = _unique(point_of_obs[live] * n_stations + station_of_obs[live])
        rays = np.bincount(pairs // n_stations, minlength=n_points)
        new_points = (rays >= MIN_RAYS_PASS) | (single_ok & (rays >= 1))
        pairs = pairs[new_points[pairs // n_stations]]
        live = live & new_points[point_of_obs]
        per_station = np.bincount(pairs % n_stations, minlength=n_stations)
        new_stations = per_station >= MIN_POINTS_PER_STATION
        if (new_points == point_active).all() and (new_stations == station_active).all():
            return point_active, station_active, live
        point_active &= new_points
        station_active &= new_stations


# -- streaming passes --------------------------------------------------------------------

@njit(cache=True)
def _chunk_activity(starts, counts, obs_station, obs_status, single_ok, station_active,
                    point_active, obs_active, station_points):
    """Exclusion rules on one chunk of points, given which stations are active.

    A ray is usable when the observation is not rejected and its station is active; a point
    is active with 2 distinct usable stations (1 for full or vertical control). Fills
    ``point_active``, ``obs_active`` (usable rays of active points) and adds 1 to
    ``station_points[s]`` for every active point seen by station ``s`` (not counted when
    ``station_points`` is empty).
    """
    for j in range(starts.shape[0]):
        a = starts[j]
        b = a + counts[j]
        k = 0
        for i in range(a, b):
            use = obs_status[i] != STATUS_REJECTED and station_active[obs_station[i]]
            obs_active[i] = use
            if use and _first_ray(obs_station, obs_active, a, i):
                k += 1
        ok = k >= MIN_RAYS_PASS or (single_ok[j] and k >= 1)
        point_active[j] = ok
        for i in range(a, b):
            if not ok:
                obs_active[i] = False
            elif (station_points.shape[0] > 0 and obs_active[i]
                  and _first_ray(obs_station, obs_active, a, i)):
                station_points[obs_station[i]] += 1


@njit(cache=True)
def _first_ray(obs_station, obs_active, a, i):
    """True when no active ray ``a .. i-1`` of the point comes from ray ``i``'s station."""
    for q in range(a, i):
        if obs_active[q] and obs_station[q] == obs_station[i]:
            return False
    return True


@njit(cache=True)
def _ray_range_kernel(starts, counts, station, active, smin, smax):
    for j in range(starts.shape[0]):
        for i in range(starts[j], starts[j] + counts[j]):
            if active[i]:
                s = station[i]
                if s < smin[j]:
                    smin[j] = s
                if s > smax[j]:
                    smax[j] = s


def _ray_range(starts, counts, station, active):
    """Smallest and largest station of each point's active rays (int64 max / -1 if none)."""
    smin = np.full(len(starts), np.iinfo(np.int64).max, np.int64)
    smax = np.full(len(starts), -1, np.int64)
    _ray_range_kernel(starts, counts, np.ascontiguousarray(station), active, smin, smax)
    return smin, smax


class _Chunk:
    """Points ``a:b`` of a project with their observations and exclusion flags."""

    def __init__(self, p, a, b, station_active, station_points=None, fields=None,
                 reset=False):
        self.a, self.b = a, b
        self.pts = p.read("points", a, b)
        self.o0 = int(self.pts["obs_start"][0]) if b > a else 0
        self.o1 = int(self.pts["obs_start"][-1] + self.pts["n_obs"][-1]) if b > a else 0
        if fields is None:
            self.obs = p.read("observations", self.o0, self.o1)
        else:
            self.obs = {f: p.read_field("observations", f, self.o0, self.o1) for f in fields}
        if reset:   # (earlier rejections brought back)
            status = self.obs["status"]
            if isinstance(self.obs, dict):
                self.obs["status"] = status = status.copy()
            status[status == STATUS_REJECTED] = STATUS_ACTIVE
        self.starts = np.ascontiguousarray(self.pts["obs_start"] - self.o0)
        self.counts = np.ascontiguousarray(self.pts["n_obs"], dtype=np.int64)
        self.station = np.ascontiguousarray(self.obs["station"])
        kind = self.pts["kind"]
        single = (kind == KIND_CONTROL) | (kind == KIND_VERTICAL)
        self.point_active = np.zeros(b - a, np.bool_)
        self.obs_active = np.zeros(self.o1 - self.o0, np.bool_)
        sp_counts = station_points if station_points is not None else np.zeros(0, np.int64)
        _chunk_activity(self.starts, self.counts, self.station,
                        np.ascontiguousarray(self.obs["status"]), single, station_active,
                        self.point_active, self.obs_active, sp_counts)


def _unique(x):
    """Sorted unique values (a sort and a mask: faster than np.unique's hash for int64)."""
    x = np.sort(x)
    if len(x) < 2:
        return x
    keep = np.empty(len(x), bool)
    keep[0] = True
    np.not_equal(x[1:], x[:-1], out=keep[1:])
    return x[keep]


def _station_activity(p, chunk, reset=False, memory=None, work=None):
    """Active stations and the station-graph edges after the exclusion rules.

    Passes over the point chunks until the active stations stop changing (usually one pass:
    nothing is excluded). Every pass also gathers the unique edges over its active rays, so
    the last pass, the one that changes nothing, delivers the graph as well. Returns
    ``(active, (s, t))`` with ``s < t`` (int32 when the stations allow). ``reset``:
    observations rejected by an earlier run count as active (``--reset-rejections``).
    """
    n_st = p.n_stations
    active = paging.empty(n_st, np.bool_)
    for a, b in paging.rows(n_st):
        active[a:b] = True
    dt = np.int32 if n_st < 2**31 else np.int64
    while True:
        per_station = paging.zeros(n_st, np.int64)
        edges = _EdgeKeys(n_st, memory, work)
        for a, b in p.chunks("points", chunk):
            c = _Chunk(p, a, b, active, per_station, fields=("station", "status"),
                       reset=reset)
            edges.add(_unique(_point_pairs(c.starts, c.counts, c.station, c.obs_active,
                                           n_st)))
        changed = False
        for a, b in paging.rows(n_st):
            new = active[a:b] & (per_station[a:b] >= MIN_POINTS_PER_STATION)
            changed = changed or bool((new != active[a:b]).any())
            active[a:b] = new
        del per_station
        if not changed:
            return active, edges.edges(dt)
        edges.close()


class _EdgeKeys:
    """The unique keys ``s * n + t`` of the station graph's edges, gathered chunk by chunk:
    merged in core, or, while the run's vectors are paged (:mod:`sapgo.paging`: a very large
    block), sorted externally within ``memory`` bytes in ``work`` and written into mapped
    arrays."""

    def __init__(self, n_st, memory=None, work=None):
        self.n_st = n_st
        self.sorter = None
        if paging.active():
            self.sorter = ExternalSorter(np.dtype([("k", "<i8")]), ["k"],
                                         (memory or DEFAULT_MEMORY) // 2, work, "edges")
        self.parts, self.n_parts, self.merged = [], 0, np.zeros(0, np.int64)

    def add(self, keys):
        if self.sorter is not None:
            self.sorter.add(keys.view(self.sorter.dtype))
            return
        self.parts.append(keys)
        self.n_parts += len(keys)
        if self.n_parts > max(len(self.merged), 1 << 20):
            self.merged = _unique(np.concatenate([self.merged] + self.parts))
            self.parts, self.n_parts = [], 0

    def edges(self, dt):
        """``(s, t)`` with ``s < t``, in key order."""
        n = self.n_st
        if self.sorter is None:
            keys = _unique(np.concatenate([self.merged] + self.parts))
            self.parts = self.merged = None
            return (keys // n).astype(dt), (keys % n).astype(dt)
        s = paging.empty(self.sorter.count, dt)
        t = paging.empty(self.sorter.count, dt)
        m, last = 0, None
        for chunk in self.sorter.sorted_chunks():
            k = chunk["k"]
            keep = np.empty(len(k), bool)
            if len(k):
                keep[0] = last is None or k[0] != last
                np.not_equal(k[1:], k[:-1], out=keep[1:])
                last = k[-1]
            k = k[keep]
            s[m:m + len(k)] = k // n
            t[m:m + len(k)] = k % n
            m += len(k)
            paging.release()
        self.close()
        return s[:m], t[:m]

    def close(self):
        if self.sorter is not None:
            self.sorter.close()
            self.sorter = None


# -- the order command -----------------------------------------------------------------

SOLVERS = ("auto", "band", "tree")


@writes_project("order", "path")
def order_project(path, method="best", memory=None, chunk=CHUNK_RECORDS, solver="auto",
                  leaf_stations=None, out=None, reset_rejections=False, checked=False,
                  page_stations=None, in_memory=False, project=None):
    """Order a project: exclusions, station order, point order, records rewritten.

    ``method`` is ``"best"`` (smallest band width of all candidates) or one candidate name
    (``across_strip``, ``down_strip``, ``reverse_cuthill_mckee``, ...) for the band.
    ``solver``: "band" (the band order), "tree" (the partition tree's post-order, stored
    in ``/tree``; :mod:`sapgo.solve.partition`) or "auto" (the one of the smaller predicted
    factorisation time, :func:`predict_solver`). ``leaf_stations``: the tree's largest leaf
    (default :data:`sapgo.solve.partition.LEAF_STATIONS`). Every pass streams
    the records in chunks; the points and observations are put in their new order by external
    sorts within ``memory`` bytes (default :data:`sapgo.extsort.DEFAULT_MEMORY`). In core:
    per-station vectors and the station graph (a few edges per station), memory-mapped
    beyond ``page_stations``. The project is
    rewritten through a temporary file that replaces it only when complete; with ``out``
    the ordered project is written there instead (attribute ``ordered_from``: the uuid of
    ``path``) and ``path`` is left as it was (``sapgo adjust`` orders into its commit).
    ``reset_rejections``: observations rejected by an earlier run (data snooping) are
    active again in the ordered project. ``checked``: the caller has checked the
    project's values already (:func:`sapgo.validate.check_values`; ``sapgo adjust``).
    ``page_stations``: above this many stations (default
    :data:`sapgo.paging.PAGE_STATIONS`; 0: always) the per-station vectors, the station
    graph's edges (sorted externally within ``memory``) and the candidate orders are
    memory-mapped (:mod:`sapgo.paging`). ``in_memory``: the ordered project (``out``'s
    name) is built in memory, never written, and returned open as the result's ``file``
    (an h5py File the caller closes; ``sapgo adjust`` on a small project), its records as
    the result's ``records`` (arrays by dataset). ``project``:
    ``path`` open already (a :class:`~sapgo.project.Project` read only; the caller's).
    """
    import time

    from .validate import check_values

    t0 = time.perf_counter()
    memory = DEFAULT_MEMORY if memory is None else parse_memory(memory)
    path = Path(path)
    work = path.with_name(path.name + ".order.work")
    with contextlib.nullcontext(project) if project is not None else Project(path, "r") as p:
        if not checked:   # (sapgo adjust has checked them just before)
            check_values(p, ordered_layout=False)
        if solver not in SOLVERS:
            raise ParameterError(f"unknown solver {solver!r}; choose from {', '.join(SOLVERS)}")
        try:
            # a very large block's per-station vectors and station graph memory-mapped
            limit = paging.PAGE_STATIONS if page_stations is None else page_stations
            with paging.paged(path.resolve().parent, p.n_stations > limit or limit == 0,
                              0 if limit == 0 else paging.MIN_PAGED_BYTES):
                result = _order(p, work, method, memory, chunk, solver, leaf_stations, out,
                                reset_rejections, in_memory)
        finally:
            shutil.rmtree(work, ignore_errors=True)
    result.seconds = time.perf_counter() - t0
    return result


def score_orders(cands, active, edges, keep="best"):
    """``{name: (band_width, profile, perm, pos)}`` of the candidate orders (a dict, or
    ``(name, perm)`` pairs as :func:`iter_candidate_orders` yields them; the inactive
    stations appended at the end): ``perm`` the records in logical order, ``pos`` each
    record's logical number. ``perm`` and ``pos`` are kept for the order ``keep`` names
    ("best": :func:`best_order`'s; None: all), None for the others."""
    n_st = len(active)
    tail = np.concatenate([a + np.flatnonzero(~active[a:b]) for a, b in paging.rows(n_st)]
                          or [np.zeros(0, np.int64)]).astype(np.int64)
    scored = {}
    held = None
    for name, perm in (cands.items() if isinstance(cands, dict) else cands):
        full = paging.empty(n_st, np.int64)
        for a, b in paging.rows(len(perm)):
            full[a:b] = perm[a:b]
        full[len(perm):] = tail
        del perm
        pos = paging.inverse(full)
        scored[name] = (*band_and_profile(pos, edges), full, pos)
        if keep is None:
            continue
        if keep == "best":
            if held is not None and scored[held][:2] <= scored[name][:2]:
                scored[name] = scored[name][:2] + (None, None)
                continue
            if held is not None:
                scored[held] = scored[held][:2] + (None, None)
            held = name
        elif name != keep:
            scored[name] = scored[name][:2] + (None, None)
        del full, pos
    return scored


def best_order(scored):
    """The order ``sapgo order`` applies: the least band width, then the least profile."""
    return min(scored, key=lambda k: scored[k][:2])


def predict_solver(n_active, band_width, tree, k=6):
    """Predicted seconds of one factorisation by the band and by the tree: flops at the
    rate each kernel reaches on this kind of machine (2 cores: the band's panels and the
    tree's fronts both about 25 GFlop/s in the mix of sizes they meet), plus the tree's
    fixed costs (per node and per pass: a small block stays on the band, the tested path
    of strips)."""
    u = k * band_width
    out = {"band": k * n_active * float(u) * u / BAND_RATE}
    if tree is not None:
        f = tree.figures(k)
        out["tree"] = (f["flops"] / TREE_RATE + TREE_NODE_SECONDS * f["nodes"]
                       + TREE_FIXED_SECONDS)
    return out


#: Rates of the solvers' kernels (flops per second) and the tree's fixed costs (s), for
#: :func:`predict_solver` (measured on 2 cores: benchmarks/shape.py).
BAND_RATE = 25e9
TREE_RATE = 25e9
TREE_NODE_SECONDS = 2e-4
TREE_FIXED_SECONDS = 0.01


#: Above this many active stations ``choose_solver`` first screens the tree on a window of
#: the band order (:func:`_window_tree_seconds`) before it partitions the whole block (on
#: 10 000 photos in 20 strips the whole tree took 0.13 s of the ordering's 0.33, only to
#: find the band faster; the window's tree 0.03 s).
SCREEN_STATIONS = 5_000
#: Stations in that window: a fifth of the block's active stations, at least
#: ``MIN_WINDOW_STATIONS``, at most ``WINDOW_STATIONS``.
WINDOW_STATIONS = 20_000
MIN_WINDOW_STATIONS = 2_000


def _window_tree_seconds(pos, active, edges, band_perm, leaf_stations, k):
    """The tree's predicted factorisation time of the whole block scaled from the tree of
    a window of consecutive active stations in the middle of the band order (a fifth of
    them, between ``MIN_WINDOW_STATIONS`` and ``WINDOW_STATIONS``): the
    window's tree is built (both methods, :func:`~sapgo.solve.partition.best_tree`) and its
    flops and nodes per station times the block's active stations.

    A screen, not a prediction: eliminating an induced subgraph never fills more than the
    whole graph does among its vertices, so the block's factor costs at least the sum over
    disjoint windows, and a window of a long strip is like any other. On a square or
    irregular block the window (a few rows across the band) is cheap and the screen lets
    the whole block be partitioned."""
    from .solve.partition import best_tree

    act = np.asarray(band_perm, np.int64)[:int(np.count_nonzero(active))]
    m = min(len(act), max(MIN_WINDOW_STATIONS, min(WINDOW_STATIONS, len(act) // 5)))
    start = (len(act) - m) // 2
    # the window as a problem of its own (stations 0 .. m-1 in the order of their record
    # numbers): its arrays are the window's size, not the block's
    win = np.sort(act[start:start + m])
    parts = []
    for a, b in paging.rows(len(edges[0])):   # (the window's edges, a chunk at a time)
        s, t = (np.asarray(x[a:b], np.int64) for x in edges)
        ls = np.minimum(np.searchsorted(win, s), m - 1)
        lt = np.minimum(np.searchsorted(win, t), m - 1)
        keep = (win[ls] == s) & (win[lt] == t)
        parts.append((ls[keep], lt[keep]))
    s = np.concatenate([q[0] for q in parts]) if parts else np.zeros(0, np.int64)
    t = np.concatenate([q[1] for q in parts]) if parts else np.zeros(0, np.int64)
    tree, _, _ = best_tree(None if pos is None else np.asarray(pos[win], np.float64),
                           np.ones(m, bool), (s, t),
                           leaf_stations, k=k)
    f = tree.figures(k)
    scale = len(act) / m
    return scale * (f["flops"] / TREE_RATE + TREE_NODE_SECONDS * f["nodes"])


def choose_solver(pos, active, edges, band_width, k=6, solver="auto", leaf_stations=None,
                  band_perm=None):
    """The band or the partition tree for a station graph, as ``sapgo order`` chooses:
    ``(tree or None, tree perm or None, predicted seconds per solver)``; ``solver`` "band"
    or "tree" forces the choice. ``band_perm`` (the band order, active stations first):
    on a block of more than ``SCREEN_STATIONS`` active stations, "auto" keeps the band
    without partitioning the block when the tree of a window predicts more than twice the
    band's time (a long strip block; ``predicted["tree_window"]``)."""
    from .solve.partition import LEAF_STATIONS, best_tree

    n_active = int(np.count_nonzero(active))
    predicted = predict_solver(n_active, band_width, None, k)
    if solver == "band" or n_active == 0:
        return None, None, predicted
    band = predicted["band"]
    if solver == "auto" and band <= TREE_FIXED_SECONDS:   # (no tree can predict less)
        return None, None, predicted
    if solver == "auto" and band_perm is not None and n_active > SCREEN_STATIONS:
        predicted["tree_window"] = _window_tree_seconds(
            pos, active, edges, band_perm, leaf_stations or LEAF_STATIONS, k)
        if predicted["tree_window"] > 2.0 * band:
            return None, None, predicted
    tree, perm, _ = best_tree(pos, active, edges, leaf_stations or LEAF_STATIONS, k=k,
                              enough=None if solver == "tree" else lambda t: t > 2.0 * band)
    predicted = predict_solver(n_active, band_width, tree, k)
    if solver == "tree" or predicted["tree"] < predicted["band"]:
        return tree, perm, predicted
    return None, None, predicted


def _records_in_memory(p, w, st_active, pos, n_st, reset, has_truth, tree, node_points,
                       excluded_points):
    """:func:`_order`'s points and observations (and the points' truth) in their new order
    for an ordered copy built in memory (``sapgo adjust`` on a small project without a
    solution): the records the streamed passes write -- the same sort keys, the same
    stable order -- from whole arrays in one pass, without the external sorters' copies.
    Appends them to ``w``, counts each node's points into ``node_points`` (a tree) and
    the excluded points' ids into ``excluded_points``; returns how many were excluded."""
    n_pt = p.n_points
    c = _Chunk(p, 0, n_pt, st_active, reset=reset)
    new_st = pos[c.station]
    smin, smax = _ray_range(c.starts, c.counts, new_st, c.obs_active)
    kmin = np.where(c.point_active, smin, n_st)
    kmax = np.where(c.point_active, smax, n_st)
    order = _key_order([kmin, kmax, np.asarray(c.pts["id"], np.int64),
                        np.arange(n_pt, dtype=np.int64)])
    r = c.pts.copy()
    r["status"] = np.where(c.point_active, STATUS_ACTIVE, STATUS_EXCLUDED)
    r["station_min"] = np.where(c.point_active, smin, -1)
    r["station_max"] = smax
    r = records_at(r, order)
    r["obs_start"] = np.concatenate([[0], np.cumsum(r["n_obs"][:-1])]) if n_pt else 0
    w.append("points", r)
    if has_truth:
        w.append("truth/points", records_at(p.read("truth/points"), order))
    if tree is not None:   # the points of each node (by their first station)
        km = kmin[order]
        km = km[km < tree.n_active]
        node_points += np.bincount(np.searchsorted(tree.hi, km, side="right"),
                                   minlength=tree.n_nodes)
    new = np.empty(n_pt, np.int64)
    new[order] = np.arange(n_pt, dtype=np.int64)
    point = np.repeat(new, c.counts)
    o = c.obs.copy()
    rejected = o["status"] == STATUS_REJECTED
    o["status"] = np.where(c.obs_active, STATUS_ACTIVE, STATUS_EXCLUDED)
    o["status"][rejected] = STATUS_REJECTED
    o["point"] = point
    o["station"] = new_st
    # (the observations' own index last: distinct keys; gathered point by point in the new
    # order first, each point's rays a run, nearly sorted)
    near = None
    if np.array_equal(c.starts, np.cumsum(c.counts) - c.counts) and \
            int(c.counts.sum()) == len(point):   # (each observation in one point's run)
        counts = c.counts[order]
        near = np.repeat(c.starts[order] - (np.cumsum(counts) - counts), counts)
        near += np.arange(len(near), dtype=np.int64)
    w.append("observations", records_at(o, _key_order(
        [point, new_st, np.arange(c.o0, c.o1, dtype=np.int64)], near)))
    ids = c.pts["id"][~c.point_active]
    excluded_points.extend(int(i) for i in ids[:LISTED_IDS])
    return len(ids)


def _order(p, work, method, memory, chunk, solver="auto", leaf_stations=None, out=None,
           reset=False, in_memory=False):

    stations = paging.records(p, "stations")
    n_st, n_pt = p.n_stations, p.n_points
    st_active, edges = _station_activity(p, chunk, reset, memory, work)

    b_before = band_width_of(paging.arange(n_st), edges)
    if method != "best" and method not in ORDERINGS[1:]:
        raise ParameterError(f"unknown ordering {method!r}; choose from "
                             f"{', '.join(ORDERINGS)}")
    cands = iter_candidate_orders(stations["eo"][:, 3:5], stations["strip"], st_active, edges)
    scored = score_orders(cands, st_active, edges, keep=method)
    name = best_order(scored) if method == "best" or method not in scored else method
    b, _, perm, pos = scored[name]
    candidates = {k: int(v[0]) for k, v in scored.items()}
    scored.clear()
    k_par = 9 if p.attr("station_intrinsics", "") == "adjusted" else 6
    if method != "best" and solver == "auto":
        solver = "band"   # a band ordering asked for by name
    tree, perm_t, predicted = choose_solver(stations["eo"][:, 3:6], st_active, edges, b, k_par,
                                            solver, leaf_stations, band_perm=perm)
    if tree is not None:
        perm = perm_t
        pos = paging.inverse(perm)
        b = band_width_of(pos, edges)
        name = f"nested_dissection_{tree.method}"
    del edges

    has_truth, has_solution = p.has_truth, p.has_solution
    pt_fields = [("kmin", "<i8"), ("kmax", "<i8"), ("id", "<i8"), ("old", "<i8"),
                 ("rec", POINT_DTYPE)]
    if has_truth:
        pt_fields.append(("truth", TRUTH_POINT_DTYPE))
    if has_solution:
        pt_fields += [("corr", "<f8", (3,)), ("sigma", "<f8", (3,))]
    ob_fields = [("point", "<i8"), ("station", "<i8"), ("seq", "<i8"),
                 ("rec", OBSERVATION_DTYPE)]
    if has_solution:
        ob_fields += [("res", "<f8", (2,)), ("quality", "<f4", (7,))]
    pt_dtype, ob_dtype = np.dtype(pt_fields), np.dtype(ob_fields)
    map_dtype = np.dtype([("old", "<i8"), ("new", "<i8")])

    excluded_points, n_excluded_points = [], 0
    fa = p.file.attrs
    attrs = {k: fa[k] for k in fa if k != "uuid"}
    history = append_history(attrs.get("history", "[]"), {
        "command": "order", "ordering": name, "band_width": b, "band_width_before": b_before})
    attrs.update(ordered=True, ordering=name, band_width=b, history=history,
                 solver="tree" if tree is not None else "band")
    if out is not None:
        attrs["ordered_from"] = p.attr("uuid", "")
        attrs["rejections_reset"] = bool(reset)
    node_points = np.zeros(tree.n_nodes if tree is not None else 0, np.int64)

    with ExternalSorter(pt_dtype, ["kmin", "kmax", "id", "old"], memory // 2, work,
                        "points") as pts_sort, \
            ProjectWriter(out or p.path, attrs, truth=has_truth, tmp_suffix=".order.tmp",
                          sizes={n: p.length(n) for n in (*RECORD_DTYPES, *TRUTH_DTYPES)
                                 if n in p.file}, memory=in_memory) as w:
        if in_memory and not has_solution:   # (one pass over whole arrays, no sorter)
            n_excluded_points = _records_in_memory(p, w, st_active, pos, n_st, reset,
                                                   has_truth, tree, node_points,
                                                   excluded_points)
        else:
            # 1. points keyed by (min, max) logical station of their active rays
            for a, b_ in p.chunks("points", chunk):
                c = _Chunk(p, a, b_, st_active, fields=("station", "status"), reset=reset)
                new_st = pos[c.station]
                smin, smax = _ray_range(c.starts, c.counts, new_st, c.obs_active)
                rec = np.zeros(b_ - a, pt_dtype)
                rec["kmin"] = np.where(c.point_active, smin, n_st)
                rec["kmax"] = np.where(c.point_active, smax, n_st)
                rec["id"] = c.pts["id"]
                rec["old"] = np.arange(a, b_)
                r = c.pts.copy()
                r["status"] = np.where(c.point_active, STATUS_ACTIVE, STATUS_EXCLUDED)
                r["station_min"] = np.where(c.point_active, smin, -1)
                r["station_max"] = smax
                rec["rec"] = r
                if has_truth:
                    rec["truth"] = p.read("truth/points", a, b_)
                if has_solution:
                    rec["corr"] = p.solution("point_corr", a, b_)
                    rec["sigma"] = p.solution("point_sigma", a, b_)
                ids = c.pts["id"][~c.point_active]
                n_excluded_points += len(ids)
                excluded_points.extend(int(i) for i in ids[:LISTED_IDS - len(excluded_points)])
                pts_sort.add(rec)

            # 2. points written in the new order; the old -> new map sorted back by old number
            if has_solution:
                sol = w.file.create_group("solution.new")
                for k, v in p.file["solution"].attrs.items():
                    sol.attrs[k] = v
                narrow = not p.cameras()["ap_set"].any()
                for dname, (parent, _) in SOLUTION_LAYOUT.items():
                    solution_dataset(sol, dname, {"stations": n_st, "points": n_pt,
                                                  "cameras": p.n_cameras}.get(parent,
                                                                              p.n_observations),
                                     PHOTO_CAMERA_NARROW if narrow and dname == "photo_camera_corr"
                                     else None)
                sol["station_corr"][...] = p.solution("station_corr")[perm]
                sol["station_sigma"][...] = p.solution("station_sigma")[perm]
                pcc = sol["photo_camera_corr"]
                pcc[...] = p.solution("photo_camera_corr")[perm][:, :pcc.shape[1]]
                sol["camera_corr"][...] = p.solution("camera_corr")  # cameras keep their order
                if "report" in p.file["solution"]:
                    sol.create_dataset("report", data=p.file["solution/report"][()])
            with ExternalSorter(map_dtype, ["old"], memory // 4, work, "map") as map_sort:
                new, start = 0, 0
                for c in pts_sort.sorted_chunks():
                    r = c["rec"].copy()
                    r["obs_start"] = start + np.concatenate([[0], np.cumsum(r["n_obs"][:-1])])
                    start = int(r["obs_start"][-1] + r["n_obs"][-1])
                    w.append("points", r)
                    if has_truth:
                        w.append("truth/points", c["truth"])
                    if has_solution:   # (every per-point and per-observation result)
                        sol["point_corr"][new:new + len(c)] = c["corr"]
                        sol["point_sigma"][new:new + len(c)] = c["sigma"]
                    if tree is not None:  # the points of each node (by their first station)
                        km = c["kmin"][c["kmin"] < tree.n_active]
                        node_points += np.bincount(np.searchsorted(tree.hi, km, side="right"),
                                                   minlength=tree.n_nodes)
                    m = np.zeros(len(c), map_dtype)
                    m["old"] = c["old"]
                    m["new"] = np.arange(new, new + len(c))
                    map_sort.add(m)
                    new += len(c)
                pts_sort.close()

                # 3. observations relabelled (old point order = record order) and sorted
                with ExternalSorter(ob_dtype, ["point", "station", "seq"], memory // 2, work,
                                    "observations") as obs_sort:
                    maps = rechunk(map_sort.sorted_chunks(), chunk)
                    for (a, b_), m in zip(p.chunks("points", chunk), maps):
                        c = _Chunk(p, a, b_, st_active, reset=reset)
                        rec = np.zeros(c.o1 - c.o0, ob_dtype)
                        rec["point"] = np.repeat(m["new"], c.counts)
                        rec["station"] = pos[c.station]
                        rec["seq"] = np.arange(c.o0, c.o1)
                        o = c.obs.copy()
                        rejected = o["status"] == STATUS_REJECTED
                        o["status"] = np.where(c.obs_active, STATUS_ACTIVE, STATUS_EXCLUDED)
                        o["status"][rejected] = STATUS_REJECTED
                        o["point"] = rec["point"]
                        o["station"] = rec["station"]
                        rec["rec"] = o
                        if has_solution:
                            rec["res"] = p.solution("residuals", c.o0, c.o1)
                            rec["quality"] = p.solution("obs_quality", c.o0, c.o1)
                        obs_sort.add(rec)
                    map_sort.close()
                    at = 0
                    for c in obs_sort.sorted_chunks():
                        w.append("observations", c["rec"])
                        if has_solution:
                            sol["residuals"][at:at + len(c)] = c["res"]
                            sol["obs_quality"][at:at + len(c)] = c["quality"]
                        at += len(c)

        # 4. per-station records (a chunk at a time)
        for a, b_ in paging.rows(n_st):
            new_stations = stations[perm[a:b_]]
            new_stations["status"] = np.where(st_active[perm[a:b_]], STATUS_ACTIVE,
                                              STATUS_EXCLUDED)
            w.append("stations", new_stations)
        w.append("cameras", p.cameras())
        priors = p.read("station_priors")
        if len(priors):
            priors["station"] = pos[priors["station"]]
            priors = priors[np.argsort(priors["station"], kind="stable")]
        w.append("station_priors", priors)
        if has_truth:
            truth = paging.records(p, "truth/stations")
            for a, b_ in paging.rows(n_st):
                w.append("truth/stations", truth[perm[a:b_]])
            del truth
            if "truth/blunders" in p.file:  # keyed by ids: unchanged by the order
                w.append("truth/blunders", p.read("truth/blunders"))
        for group in KEYED_GROUPS:  # keyed by ids: unchanged by the order
            if group in p.file:
                p.file.copy(p.file[group], w.file, group)
        if has_solution:
            w.file.move("solution.new", "solution")
        if tree is not None:
            tree.pt_start = np.concatenate([[0], np.cumsum(node_points)]).astype(np.int64)
            g = w.file.create_group("tree")
            g.attrs["n_active"] = tree.n_active
            g.attrs["method"] = tree.method
            for key, arr in tree.to_arrays().items():
                g.create_dataset(key, data=arr, **(CHECKSUM if np.size(arr) else {}))
        # replaces the project (still open here for reading: POSIX keeps it), or in memory
        written = w.finish()
    result = OrderResult(
        band_width_before=b_before,
        band_width=b,
        ordering=name,
        candidates=candidates,
        excluded_points=excluded_points,
        excluded_stations=[int(i) for a, b_ in paging.rows(n_st)
                           for i in stations["id"][a:b_][~st_active[a:b_]]][:LISTED_IDS],
        n_excluded_points=n_excluded_points,
        n_excluded_stations=sum(int((~st_active[a:b_]).sum()) for a, b_ in paging.rows(n_st)),
        solver="tree" if tree is not None else "band",
        tree=tree.figures(k_par) if tree is not None else None,
        predicted=predicted,
    )
    # (not fields: not in the report) the ordered project in memory, and its records
    result.file, result.records = (written, w.records) if in_memory else (None, None)
    return result
