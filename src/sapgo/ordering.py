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

import dataclasses
import os
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from numba import njit
from scipy.sparse.csgraph import reverse_cuthill_mckee

from .errors import ParameterError
from .project import (
    KIND_CONTROL,
    KIND_VERTICAL,
    STATUS_ACTIVE,
    STATUS_EXCLUDED,
    STATUS_REJECTED,
    Project,
    append_history,
    write_project,
)

MIN_RAYS_PASS = 2
MIN_POINTS_PER_STATION = 3


@dataclasses.dataclass
class OrderResult:
    """What :func:`order_project` did."""

    band_width_before: int
    band_width: int
    ordering: str
    candidates: dict  # ordering name -> band width
    excluded_points: list  # ids of points left out (too few rays)
    excluded_stations: list  # ids of stations left out (too few points)
    seconds: float = 0.0

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


def band_width_of(pos, edges):
    """Band width (stations, diagonal included) of logical order ``pos`` over ``edges``."""
    s, t = edges
    if len(s) == 0:
        return 1
    return int(1 + np.abs(pos[s] - pos[t]).max())


def profile_of(pos, edges):
    """Sum over stations of the distance to their farthest earlier neighbour (tie-breaker)."""
    s, t = edges
    if len(s) == 0:
        return 0
    lo = np.minimum(pos[s], pos[t])
    hi = np.maximum(pos[s], pos[t])
    reach = np.zeros(len(pos), np.int64)
    np.maximum.at(reach, hi, hi - lo)
    return int(reach.sum())


# -- candidate orders ------------------------------------------------------------------

def _flight_axes(xy, strip):
    """Unit vectors along and across the flight lines, from the strips if they are known."""
    dirs = []
    if (strip >= 0).all():
        for s in np.unique(strip):
            p = xy[strip == s]
            if len(p) >= 2:
                c = p - p.mean(axis=0)
                _, _, vt = np.linalg.svd(c, full_matrices=False)
                d = vt[0]
                if dirs and np.dot(d, dirs[0]) < 0:
                    d = -d
                dirs.append(d)
    if dirs:
        along = np.mean(dirs, axis=0)
    else:
        c = xy - xy.mean(axis=0)
        _, _, vt = np.linalg.svd(c, full_matrices=False) if len(xy) >= 2 else (0, 0, np.eye(2))
        along = vt[0]
    n = np.linalg.norm(along)
    along = along / n if n > 0 else np.array([1.0, 0.0])
    return along, np.array([-along[1], along[0]])


def candidate_orders(xy, strip, active, edges):
    """Candidate logical orders of the active stations: ``{name: perm}``.

    ``perm`` lists station record numbers in logical order (active stations only).
    """
    idx = np.flatnonzero(active)
    if len(idx) == 0:
        return {"record": idx}
    xy = xy[idx]
    st = strip[idx]
    along, across = _flight_axes(xy, st)
    u = xy @ along
    v = xy @ across
    # photo spacing along the strips: median gap between neighbours sorted along track
    if (st >= 0).all():
        gaps = []
        for s in np.unique(st):
            us = np.sort(u[st == s])
            gaps.extend(np.diff(us))
        gaps = np.asarray(gaps)
    else:
        gaps = np.diff(np.sort(u))
    gaps = gaps[gaps > 0]
    base = float(np.median(gaps)) if len(gaps) else 1.0
    column = np.floor(u / base + 0.5) if base > 0 else u
    if (st >= 0).all():
        strip_key = np.zeros(len(st))
        for s in np.unique(st):
            strip_key[st == s] = v[st == s].mean()
    else:  # strips unknown: a new strip wherever the across-track gap exceeds half a base
        vs = np.argsort(v)
        breaks = np.concatenate([[0], np.cumsum(np.diff(v[vs]) > 0.5 * base)])
        strip_key = np.empty(len(v))
        strip_key[vs] = breaks
    cands = {
        "across_strip": idx[np.lexsort((v, column))],
        "across_strip_by_position": idx[np.lexsort((v, u))],
        "down_strip": idx[np.lexsort((u, strip_key))],
    }
    # reverse Cuthill-McKee on the active subgraph
    local = np.full(len(active), -1, np.int64)
    local[idx] = np.arange(len(idx))
    s, t = edges
    keep = active[s] & active[t]
    s, t = local[s[keep]], local[t[keep]]
    n = len(idx)
    g = sp.coo_matrix((np.ones(len(s), np.int8), (s, t)), shape=(n, n)).tocsr()
    g = (g + g.T).tocsr()
    cands["reverse_cuthill_mckee"] = idx[reverse_cuthill_mckee(g, symmetric_mode=True)]
    return cands


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
        pairs = np.unique(point_of_obs[live] * n_stations + station_of_obs[live])
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


# -- the order command -----------------------------------------------------------------

def _group_starts(sorted_keys, n):
    counts = np.bincount(sorted_keys, minlength=n)
    starts = np.zeros(n, np.int64)
    np.cumsum(counts[:-1], out=starts[1:])
    return starts, counts


def order_project(path, method="best"):
    """Order a project: exclusions, station order, point order, records rewritten.

    ``method`` is ``"best"`` (smallest band width of all candidates) or one candidate name
    (``across_strip``, ``down_strip``, ``reverse_cuthill_mckee``, ...). The project is
    rewritten through a temporary file that replaces it only when complete.
    """
    import time

    t0 = time.perf_counter()
    from .validate import check_values

    path = Path(path)
    with Project(path, "r") as p:
        check_values(p, ordered_layout=False)
        stations = p.read("stations")
        points = p.read("points")
        obs = p.read("observations")
        priors = p.read("station_priors")
        cameras = p.read("cameras")
        truth = (
            {"stations": p.read("truth/stations"), "points": p.read("truth/points")}
            if p.has_truth
            else None
        )
        solution = (
            {k: p.solution(k) for k in ("station_corr", "point_corr", "residuals")}
            if p.has_solution
            else None
        )
        sol_attrs = dict(p.file["solution"].attrs) if p.has_solution else None
        report = p.file["solution/report"][()] if "solution/report" in p.file else None
        attrs = {k: p.file.attrs[k] for k in p.file.attrs}
    n_st = len(stations)
    n_pt = len(points)

    point_of_obs = obs["point"]
    station_of_obs = obs["station"]
    pt_active, st_active, obs_active = find_exclusions(
        points["kind"], point_of_obs, station_of_obs, n_st, obs["status"]
    )

    # edges of the station graph over active observations, in record numbering
    order_obs = np.lexsort((station_of_obs, point_of_obs))
    ps = point_of_obs[order_obs]
    starts, counts = _group_starts(ps, n_pt)
    edges = station_edges(starts, counts, station_of_obs[order_obs], obs_active[order_obs], n_st)

    identity = np.arange(n_st)
    b_before = band_width_of(identity, edges)
    cands = candidate_orders(stations["eo"][:, 3:5], stations["strip"], st_active, edges)
    if method != "best" and method not in cands:
        raise ParameterError(f"unknown ordering {method!r}; choose from best, {', '.join(cands)}")
    tail = np.flatnonzero(~st_active)
    scored = {}
    for name, perm in cands.items():
        full = np.concatenate([perm, tail])
        pos = np.empty(n_st, np.int64)
        pos[full] = np.arange(n_st)
        scored[name] = (band_width_of(pos, edges), profile_of(pos, edges), full, pos)
    if method == "best":
        name = min(scored, key=lambda k: scored[k][:2])
    else:
        name = method
    b, _, perm, pos = scored[name]

    # points by (min, max) logical station over active rays; excluded points last
    new_station = pos[station_of_obs]
    big = np.iinfo(np.int64).max
    smin = np.full(n_pt, big, np.int64)
    smax = np.full(n_pt, -1, np.int64)
    np.minimum.at(smin, point_of_obs[obs_active], new_station[obs_active])
    np.maximum.at(smax, point_of_obs[obs_active], new_station[obs_active])
    key_min = np.where(pt_active, smin, n_st)
    key_max = np.where(pt_active, smax, n_st)
    pt_perm = np.lexsort((points["id"], key_max, key_min))
    pt_pos = np.empty(n_pt, np.int64)
    pt_pos[pt_perm] = np.arange(n_pt)

    new_point = pt_pos[point_of_obs]
    obs_perm = np.lexsort((new_station, new_point))

    new_stations = stations[perm].copy()
    new_stations["status"] = np.where(st_active[perm], STATUS_ACTIVE, STATUS_EXCLUDED)
    new_points = points[pt_perm].copy()
    new_points["status"] = np.where(pt_active[pt_perm], STATUS_ACTIVE, STATUS_EXCLUDED)
    new_points["station_min"] = np.where(pt_active[pt_perm], smin[pt_perm], -1)
    new_points["station_max"] = smax[pt_perm]
    new_obs = obs[obs_perm].copy()
    new_obs["point"] = new_point[obs_perm]
    new_obs["station"] = new_station[obs_perm]
    new_obs["status"] = np.where(obs_active[obs_perm], STATUS_ACTIVE, STATUS_EXCLUDED)
    new_obs["status"][obs["status"][obs_perm] == STATUS_REJECTED] = STATUS_REJECTED
    ostart, ocount = _group_starts(new_obs["point"], n_pt)
    new_points["obs_start"] = ostart
    new_points["n_obs"] = ocount
    new_priors = priors.copy()
    if len(new_priors):
        new_priors["station"] = pos[priors["station"]]
        new_priors = new_priors[np.argsort(new_priors["station"], kind="stable")]
    new_truth = None
    if truth is not None:
        new_truth = {"stations": truth["stations"][perm], "points": truth["points"][pt_perm]}

    result = OrderResult(
        band_width_before=b_before,
        band_width=b,
        ordering=name,
        candidates={k: v[0] for k, v in scored.items()},
        excluded_points=[int(i) for i in points["id"][~pt_active]],
        excluded_stations=[int(i) for i in stations["id"][~st_active]],
    )
    history = append_history(attrs.get("history", "[]"), {
        "command": "order", "ordering": name, "band_width": b, "band_width_before": b_before})
    attrs.update(ordered=True, ordering=name, band_width=b, history=history)
    tmp = path.with_name(path.name + ".order.tmp")
    write_project(tmp, cameras, new_stations, new_points, new_obs, new_priors, new_truth,
                  attrs=attrs)
    if solution is not None:
        with Project(tmp, "r+") as q:
            g = q.new_solution()
            g["station_corr"][...] = solution["station_corr"][perm]
            g["point_corr"][...] = solution["point_corr"][pt_perm]
            g["residuals"][...] = solution["residuals"][obs_perm]
            if report is not None:
                g.create_dataset("report", data=report)
            q.commit_solution()
            for k, v in sol_attrs.items():
                g.attrs[k] = v
    os.replace(tmp, path)
    result.seconds = time.perf_counter() - t0
    return result
