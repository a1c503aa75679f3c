"""``sapgo plan``: the reduced matrix's pattern, band width, fill-in and storage before a
single measurement (Rostom, seeds/000), for the orderings of a network.

A *network* is a set of units (photos of 6 parameters for the bundle, or independent models
of 7) on a grid of strips and columns, and the pairs of units that share a point: the
non-zero blocks of the reduced normal matrix ``M``. It comes from a flight design
(:func:`design_network`) or from an existing project (:func:`project_network`). For every
ordering (:func:`orderings`) the counts come from the symbolic factorisation of the actual
graph (:mod:`sapgo.symbolic`), never from closed formulas.
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import shortest_path

from .errors import ParameterError
from .rawfile import RawArray
from .ordering import grid_orders, reverse_cuthill_mckee
from .symbolic import symbolic_counts

#: The orderings compared (Rostom's ->G down the strips, ->S across them, along the
#: diagonals of the grid, reverse Cuthill-McKee on the graph, and a spiral from the outside).
ORDERINGS = ("down_strip", "across_strip", "diagonal", "rcm", "spiral")


@dataclasses.dataclass
class Network:
    """Units and the pairs of them that share a point.

    ``x``, ``y``: the unit's centre along and across the strips (in a design: photo sides;
    in a project: photo columns and strip numbers); ``s``, ``t``: the connected pairs (each
    once); ``params``: unknowns per unit (6 photos, 7 models); ``kind``: "photos" or
    "models"."""

    x: np.ndarray
    y: np.ndarray
    s: np.ndarray
    t: np.ndarray
    params: int = 6
    kind: str = "photos"
    #: a project's: ``(name, perm)``, the order ``sapgo order`` gives it
    adjust_order: tuple | None = None
    #: a project's: the solver ``sapgo order`` chooses for it, "band" or "tree"
    adjust_solver: str = "band"

    @property
    def n(self):
        return len(self.x)


def _key(v):
    """Line labels of coordinates that are equal up to rounding."""
    return np.unique(np.round(np.asarray(v, np.float64), 6), return_inverse=True)[1]


def orderings(net: Network):
    """``{name: (perm, lines)}`` for :data:`ORDERINGS`: ``perm[k]`` is the unit numbered
    k-th, ``lines[i]`` the line of unit ``i`` (Rostom's lines L(k): the strips for ->G, the
    columns across them for ->S, the anti-diagonals, Cuthill-McKee's level sets, the rings of
    the spiral), numbered in the order's direction."""
    n = net.n
    x, y = net.x, net.y
    kx, ky = _key(x), _key(y)
    out = {
        "down_strip": (np.lexsort((x, ky)), ky),
        "across_strip": (np.lexsort((y, kx)), kx),
    }
    g = sp.csr_matrix((np.ones(2 * len(net.s), np.int8),
                       (np.concatenate([net.s, net.t]), np.concatenate([net.t, net.s]))),
                      shape=(n, n))
    if n:
        perm = reverse_cuthill_mckee(g.indptr, g.indices).astype(np.int64)
        # levels: the graph distance from the order's last unit (reverse Cuthill-McKee
        # numbers level by level from there)
        dist = shortest_path(g, unweighted=True, indices=int(perm[-1]))
        dist[~np.isfinite(dist)] = dist[np.isfinite(dist)].max() + 1 if np.isfinite(
            dist).any() else 0
        lv = dist.max() - dist
        lv = _key(lv)
    else:
        perm, lv = np.zeros(0, np.int64), np.zeros(0, np.int64)
    out["rcm"] = (perm, lv)
    # (diagonal and spiral by line numbers: the same in a design and in a project)
    out.update(grid_orders(kx, ky, y))
    out = {k: out[k] for k in ORDERINGS}
    return out


def partitioned_band_width(net: Network, lines):
    """Rostom's D: the band width in blocks when the band is stored in whole sub-matrices
    b(k, k+t) of lines: per line k, the sizes of the lines from k to the farthest line a unit
    of k is joined to, summed; the largest over k."""
    if net.n == 0:
        return 0
    size = np.bincount(lines)
    reach = np.arange(len(size))
    ls, lt = lines[net.s], lines[net.t]
    lo, hi = np.minimum(ls, lt), np.maximum(ls, lt)
    np.maximum.at(reach, lo, hi)
    csum = np.concatenate([[0], np.cumsum(size)])
    return int((csum[reach + 1] - csum[np.arange(len(size))]).max())


def evaluate(net: Network, timing=False, seconds=1.0):
    """The counts of every ordering and the recommended one (the least solve work).

    Per ordering: ``dimension`` (unknowns of ``M``), ``nonzero_blocks`` (lower triangle with
    the diagonal), ``band_width_b`` (units, the diagonal included, as SAPGO counts it),
    ``band_width_m`` (scalar rows: ``params`` times that), ``fill_in_blocks``,
    ``factor_blocks``, the storage of the three schemes in blocks and in bytes (band,
    envelope, sparse: the factor's blocks plus a 4-byte index each), the flops of the band
    Cholesky (:func:`band_flops`) and, with ``timing``, the predicted solve time on this
    machine (:func:`solve_time`, once per band width, about ``seconds`` each):
    ``predicted_solve_s``, ``rate_flops``, ``timed_units`` (0: not timed, more than ten
    times the least work; its time at the rate of the widest timed band, an upper bound).
    The network of a project also
    gets ``adjust``: the order ``sapgo order`` will give it (``ordering``, of its own
    candidates, which include these five), its band width, fill-in, flops and time."""
    p = net.params
    res = {}
    for name, (perm, lines) in orderings(net).items():
        c = symbolic_counts(net.n, (net.s, net.t), perm)
        blk = 8 * p * p
        w = c["band_width"]
        d = partitioned_band_width(net, lines)
        flops = band_flops(net.n, w, p)
        envelope = c["envelope_blocks"]
        r = {
            "dimension": net.n,          # T: blocks (units); the unknowns are p T
            "unknowns": p * net.n,
            "nonzero_blocks": c["nonzero_blocks"],
            "band_width_b": d,           # D: in whole sub-matrices b(k, k+t) of lines
            "band_width_m": w,           # W: in blocks m, the diagonal included
            "fill_in_blocks": c["fill_in_blocks"],
            "factor_blocks": c["factor_blocks"],
            "lines": int(lines.max() + 1) if net.n else 0,
            # blocks of each storage scheme (Rostom's TW, TD and the envelope m + F.I.;
            # sparse: the factor's blocks, here equal to the envelope's when it fills it)
            "storage_blocks": {"band": net.n * w, "partitioned_band": net.n * d,
                               "envelope": envelope, "sparse": c["factor_blocks"]},
            "storage_bytes": {"band": blk * net.n * w, "partitioned_band": blk * net.n * d,
                              "envelope": blk * envelope,
                              "sparse": (blk + 4) * c["factor_blocks"] + 8 * (net.n + 1)},
            "band_flops": flops,
        }
        res[name] = r
    best = min(res, key=lambda k: (res[k]["band_flops"], res[k]["fill_in_blocks"]))
    out = {"units": net.kind, "parameters_per_unit": p, "n_units": net.n,
           "orderings": res, "recommended": best, "tree": tree_figures(net)}
    rows = list(res.values())
    if net.adjust_order is not None:
        # a project: the order sapgo order will give it (its own candidates, the least band
        # width), and so the band width and the work of sapgo adjust
        name, perm = net.adjust_order
        c = symbolic_counts(net.n, (net.s, net.t), perm)
        c["band_width"] = c["band_width"] if net.n else 0
        out["adjust"] = {"ordering": name, "solver": net.adjust_solver,
                         "band_width_m": c["band_width"],
                         "fill_in_blocks": c["fill_in_blocks"],
                         "band_flops": band_flops(net.n, c["band_width"], p)}
        if net.adjust_solver == "tree":  # its work is the tree's, not its order's band's
            out["adjust"].update(band_flops=out["tree"]["flops"],
                                 predicted_solve_s=out["tree"]["predicted_solve_s"])
        else:
            rows.append(out["adjust"])
        if (out["adjust"]["band_flops"], out["adjust"]["fill_in_blocks"]) < \
                (res[best]["band_flops"], res[best]["fill_in_blocks"]):
            out["recommended"] = name  # (sapgo order --method NAME, or its default)
    tr = out["tree"]
    if tr is not None and out.get("adjust", {}).get("solver") != "tree" and \
            tr["flops"] < min(r["band_flops"] for r in rows):
        out["recommended"] = "tree"   # (sapgo order --solver tree)
    if timing and net.n:
        # the band widths of orderings within ten times the least work are timed; the rest
        # (hopeless ones: a spiral over a long block) get the rate of the widest timed one,
        # which the wider band would exceed (the rate grows with the width): an upper bound
        least = min(r["band_flops"] for r in rows)
        widths = sorted({r["band_width_m"] for r in rows})
        timed = [w for w in widths if band_flops(net.n, w, p) <= 10.0 * least]
        times = {w: solve_time(net.n, w, p, seconds) for w in timed}
        for r in rows:
            w = r["band_width_m"]
            if w in times:
                t = times[w]
                r.update(predicted_solve_s=t["predicted_s"], rate_flops=t["rate_flops"],
                         timed_units=t["timed_units"])
            else:
                rate = times[max(times)]["rate_flops"]
                r.update(predicted_solve_s=r["band_flops"] / rate, rate_flops=rate,
                         timed_units=0)
    return out


def tree_figures(net: Network):
    """The partition tree of the network (:func:`sapgo.solve.partition.best_tree` on the
    units' positions): its figures (:meth:`~sapgo.solve.partition.Tree.figures`: nodes,
    depth, leaves, largest front, factor bytes, flops) and the predicted time of one
    factorisation (:func:`sapgo.ordering.predict_solver`)."""
    from .ordering import predict_solver
    from .solve.partition import best_tree

    if net.n == 0:
        return None
    pos = np.column_stack([net.x, net.y, np.zeros(net.n)])
    tree, _, _ = best_tree(pos, np.ones(net.n, bool), (net.s, net.t), k=net.params)
    f = tree.figures(net.params)
    f["predicted_solve_s"] = predict_solver(net.n, 1, tree, net.params)["tree"]
    return f


#: bytes passed over before every timed solve (twice a large last-level cache)
_FLUSH_BYTES = 64 << 20


def solve_time(n_units, band_width, params=6, seconds=1.0, memory=400e6):
    """The time of one solve of ``n_units`` units of ``params`` parameters at a band width
    (blocks), measured on this machine as ``sapgo adjust`` runs the solver: a random
    positive definite band of that shape fed to :class:`sapgo.solve.band.BandSolver` in
    segments of 256 stations, its factor rows kept where adjust keeps them by default (in
    core up to :func:`sapgo.adjust.factor_core_limit`, else written to a work file) and read
    back by the back substitution (the solver's own time, the fastest of several runs, in
    about ``seconds`` in all), each run with caches as cold as after adjust's build.

    A block small enough (at most ``memory`` bytes of band rows, a run of at most a quarter
    of ``seconds``) is solved at its own size, fixed costs and all. A larger one is solved at
    the largest size ``n1`` that is, and its time extrapolated in proportion to the band
    flops (:func:`band_flops`; at that size the fixed costs are negligible). Returns
    ``{"predicted_s", "rate_flops", "timed_units", "extrapolated"}``."""
    from .adjust import Options, factor_core_limit
    from .solve.band import BandSolver

    b = max(1, int(band_width))
    n_units = int(n_units)
    core = 8 * n_units * params * (params * b + 1) <= factor_core_limit(Options())
    if n_units <= 0:
        return {"predicted_s": 0.0, "rate_flops": 0.0, "timed_units": 0, "extrapolated": False}
    n_max = min(n_units, max(2, int(memory / (8.0 * params * params * b))))
    rng = np.random.default_rng(0)
    # adjust's solve follows its build, which has passed over the points and the band rows:
    # every timed run starts with caches cold, after a pass over a buffer larger than the
    # caches (not timed)
    flush = np.zeros(_FLUSH_BYTES // 8)
    with tempfile.TemporaryDirectory(prefix="sapgo-rate-") as d:
        state = {}

        def rows(m):
            """A random positive definite band of (at least) m units and its work files,
            made anew only when a larger one is needed (in place: no temporaries)."""
            if state.get("m", 0) < m:
                for f in state.get("files", ()):
                    if isinstance(f, RawArray):
                        f.close()
                state.clear()
                band = np.empty((m, params, params * b))
                rng.random(out=band)
                band -= 0.5
                band *= 0.2 / b
                idx = np.arange(params)
                band[:, idx, idx] = params * b  # diagonally dominant
                files = ((np.empty(band.shape), np.empty((m, params))) if core else
                         (RawArray(Path(d) / "factor.bin", band.shape, mode="w"),
                          RawArray(Path(d) / "y.bin", (m, params), mode="w")))
                state.update(m=m, band=band, rhs=rng.random((m, params)), files=files)
            return state["band"], state["rhs"], state["files"]

        def run(m):
            band, rhs, (fac, y) = rows(m)
            np.add(flush, 1.0, out=flush)
            solver = BandSolver(m, b, fac, y, 256, block=params)
            for i0 in range(0, m, 256):
                solver.feed(band[i0:min(m, i0 + 256)], rhs[i0:min(m, i0 + 256)])
            solver.finish()
            return solver.seconds

        def best(m, budget, least=3):
            times = [run(m)]  # (the first run also touches the work files)
            while len(times) < least or (sum(times) < budget and len(times) < 50):
                times.append(run(m))
            return min(times[1:])

        try:
            # grow to the size whose run takes a quarter of the time (each size's fastest of
            # two runs: one slow run would stop the growth), and never extrapolate from fewer
            # than 32 b units, where the fixed costs still count
            n1 = min(n_max, 8 * b)
            run(n1)  # compile and warm
            t1 = best(n1, 0.0)
            for _ in range(6):
                want = min(n_max, int(0.25 * seconds * n1 / max(t1, 1e-9)))
                if want <= 1.2 * n1:
                    break
                n1 = want
                t1 = best(n1, 0.0)
            n1 = max(n1, min(n_max, 32 * b))
            t1 = best(n1, seconds)
        finally:
            for f in state.get("files", ()):
                if isinstance(f, RawArray):
                    f.close()
            state.clear()
    # a block of n1 units or fewer is timed at its own size, fixed costs and all; a larger
    # one from n1 units, where the fixed costs are negligible: the time grows with the flops
    rate = band_flops(n1, b, params) / t1
    return {"predicted_s": band_flops(n_units, b, params) / rate, "rate_flops": rate,
            "timed_units": n1, "extrapolated": n1 < n_units}


def band_flops(n, b, p=6):
    """Floating-point operations of the band Cholesky of ``n`` units of ``p`` parameters and
    band width ``b`` (units, the diagonal included): per scalar column with ``h`` entries
    below the diagonal (the half band ``u = p b - 1``, fewer in the last columns), ``h (h + 1)``
    for the update of the trailing triangle and ``h + 1`` for the column itself."""
    m = p * n
    u = p * b - 1
    h = np.minimum(u, m - 1 - np.arange(m)).astype(np.float64)
    return float((h * h + 2 * h + 1).sum())


def design_footprints(strips, photos_per_strip, forelap=0.6, sidelap=0.2, shift=0.0,
                      lengths=None, starts=None, scales=None):
    """The photos of a flight design (see :func:`design_network`): ``(strip, index,
    footprint)``, the footprint ``(x0, x1, y0, y1)`` in photo sides, strip by strip."""
    check_design(strips, photos_per_strip, forelap, sidelap)
    lengths = _per_strip(lengths, strips, photos_per_strip, "lengths", int)
    starts = _per_strip(starts, strips, 0.0, "starts", float)
    scales = _per_strip(scales, strips, 1.0, "scales", float)
    if not all(math.isfinite(v) for v in [shift, *starts, *scales]):
        raise ParameterError("shift, strip starts and scales must be finite numbers")
    if min(lengths) < 2 or min(scales) <= 0:
        raise ParameterError("every strip needs at least 2 photos and a positive scale")
    bx, by = 1.0 - forelap, 1.0 - sidelap
    strip = np.repeat(np.arange(strips), lengths)
    index = np.concatenate([np.arange(n) for n in lengths])
    c = np.asarray(scales, np.float64)[strip]
    x0 = (np.asarray(starts, np.float64)[strip] + index) * bx * c + shift * bx * (strip % 2)
    y0 = strip * by
    return strip, index, np.column_stack([x0, x0 + c, y0, y0 + c])


def design_network(strips, photos_per_strip, forelap=0.6, sidelap=0.2, units="photos",
                   cross=False, model_step=None, shift=0.0, lengths=None, starts=None,
                   scales=None):
    """The network of a flight design (Rostom, seeds/000 sections 1-4 and 7).

    With the photo side as unit, photo ``(k, j)`` (strip ``k``, photo ``j``) covers
    ``[x_kj, x_kj + c_k] x [y_k, y_k + c_k]``: ``x_kj = (start_k + j) bx c_k`` plus
    ``shift bx`` on every other strip, ``y_k = k by``, ``bx = 1 - forelap``,
    ``by = 1 - sidelap``, ``c_k`` the strip's relative photo scale (``scales``; 1: all
    photos of one scale). ``lengths`` and ``starts`` (photos, bases) give strips of
    different lengths and starts; ``shift`` (a fraction of the base) shifts every other
    strip. Units: the photos (bundle, 6 parameters), or the models (independent models, 7)
    of photos ``j`` and ``j + step`` of a strip (``model_step``: 1, or 2 from 75 % forelap
    on: "models from a strip are constructed from every other photograph", for p = 80 %)
    and, with ``cross``, the cross models of photo ``j`` of strips ``k`` and ``k + 1`` (a
    sidelap of 50 % or more, strips of one scale, not shifted). Two units are joined when
    their areas (a photo's footprint, a model's stereo overlap) overlap with a positive area:
    tie points in every common area."""
    if units not in ("photos", "models"):
        raise ParameterError(f"units {units!r}: photos or models")
    strip, _, foot = design_footprints(strips, photos_per_strip, forelap, sidelap, shift,
                                       lengths, starts, scales)
    one_scale = np.ptp(foot[:, 1] - foot[:, 0]) < 1e-12
    if cross and (units != "models" or sidelap < 0.5 or shift or not one_scale):
        raise ParameterError("cross models (+C) are models between the strips: they need "
                             "--units models, a sidelap of 50 % or more, strips of one scale "
                             "and no shift")
    bx = 1.0 - forelap
    first = np.concatenate([[0], np.cumsum(np.bincount(strip, minlength=strips))])
    lengths = np.diff(first)

    def photo(k, j):
        return tuple(foot[first[k] + j])

    rect = []
    if units == "photos":
        rect = list(map(tuple, foot))
    else:
        step = model_step or (2 if forelap >= 0.75 else 1)
        if 1.0 - step * bx <= 0:
            raise ParameterError(f"photos {step} apart do not overlap at {forelap:.0%} "
                                 f"forelap: no models")
        for k in range(strips):
            for i in range(lengths[k] - step):
                a, b = photo(k, i), photo(k, i + step)
                rect.append((b[0], a[1], a[2], a[3]))
        if cross:
            for k in range(strips - 1):
                for j in range(min(lengths[k], lengths[k + 1])):
                    a, b = photo(k, j), photo(k + 1, j)
                    rect.append((max(a[0], b[0]), min(a[1], b[1]), b[2], a[3]))
    r = np.array(rect, np.float64).reshape(-1, 4)
    s, t = _overlapping_pairs(r)
    return Network(x=(r[:, 0] + r[:, 1]) / 2, y=(r[:, 2] + r[:, 3]) / 2, s=s, t=t,
                   params=6 if units == "photos" else 7, kind=units)


def _overlapping_pairs(r, eps=1e-9):
    """The pairs ``i < j`` of rectangles ``r`` (n x 4: x0, x1, y0, y1) that overlap with a
    positive area. The rectangles go into cells as large as the largest of them, so only a
    cell and its neighbours need comparing: O(n) pairs for a flight design of any size."""
    n = len(r)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    wx = float((r[:, 1] - r[:, 0]).max())
    wy = float((r[:, 3] - r[:, 2]).max())
    cx = np.floor((r[:, 0] - r[:, 0].min()) / wx).astype(np.int64)
    cy = np.floor((r[:, 2] - r[:, 2].min()) / wy).astype(np.int64)
    ncy = int(cy.max()) + 3
    cell = (cx + 1) * ncy + (cy + 1)
    order = np.argsort(cell, kind="stable")
    sorted_cells = cell[order]
    s_all, t_all = [], []
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            target = cell + dx * ncy + dy
            lo = np.searchsorted(sorted_cells, target, "left")
            hi = np.searchsorted(sorted_cells, target, "right")
            cnt = hi - lo
            i = np.repeat(np.arange(n), cnt)
            j = order[np.repeat(lo, cnt) + (np.arange(cnt.sum()) - np.repeat(
                np.cumsum(cnt) - cnt, cnt))]
            keep = i < j
            i, j = i[keep], j[keep]
            ox = np.minimum(r[i, 1], r[j, 1]) - np.maximum(r[i, 0], r[j, 0])
            oy = np.minimum(r[i, 3], r[j, 3]) - np.maximum(r[i, 2], r[j, 2])
            hit = (ox > eps) & (oy > eps)
            s_all.append(i[hit])
            t_all.append(j[hit])
    return np.concatenate(s_all), np.concatenate(t_all)


def _per_strip(values, strips, default, name, cast):
    if values is None:
        return [cast(default)] * strips
    try:
        values = [cast(v) for v in values]
    except (ValueError, OverflowError):
        raise ParameterError(f"{name}: {list(values)} are not finite numbers") from None
    if len(values) != strips:
        raise ParameterError(f"{name}: {len(values)} values for {strips} strips")
    return values


def project_network(path, chunk=None):
    """The network of an existing project: its photos (the parameters of its stations: 6, or
    9 with their own intrinsics) and the pairs that observe a common point, after the
    exclusion rules of ``sapgo order`` (its actual topology, irregular or not). ``x`` is the
    photo's column along the flight lines, ``y`` its strip (the strips ordered across the
    flight direction); ``adjust_order`` is the order ``sapgo order`` (and so ``sapgo
    adjust``) gives the project: its name and the units in that order."""
    from .ordering import (
        _station_activity,
        best_order,
        candidate_orders,
        choose_solver,
        grid_coordinates,
        score_orders,
    )
    from .project import CHUNK_RECORDS, Project

    with Project(path) as p:
        st = p.read("stations")
        params = 9 if p.attr("station_intrinsics", "") == "adjusted" else 6
        active, (s, t) = _station_activity(p, chunk or CHUNK_RECORDS)
    idx = np.flatnonzero(active)
    local = np.full(len(st), -1, np.int64)
    local[idx] = np.arange(len(idx))
    keep = active[s] & active[t]
    s, t = np.asarray(s[keep], np.int64), np.asarray(t[keep], np.int64)
    xy = st["eo"][:, 3:5]
    if len(idx):
        grid = grid_coordinates(xy[idx], st["strip"][idx])
        _, _, column, _, strip_key = grid
        y = np.unique(strip_key, return_inverse=True)[1].astype(np.float64)
        x = column.astype(np.float64)
        scored = score_orders(candidate_orders(xy, st["strip"], active, (s, t), grid),
                              active, (s, t))
        name = best_order(scored)
        chosen = (name, local[scored[name][2][:len(idx)]])
        tree, perm_t, _ = choose_solver(st["eo"][:, 3:6], active, (s, t),
                                        scored[name][0], params, band_perm=scored[name][2])
        if tree is not None:
            chosen = (f"nested_dissection_{tree.method}", local[perm_t[:len(idx)]])
    else:
        x = y = np.zeros(0)
        chosen = ("record", np.zeros(0, np.int64))
        tree = None
    return Network(x=x, y=y, s=local[s], t=local[t], params=params, kind="photos",
                   adjust_order=chosen, adjust_solver="band" if tree is None else "tree")


def check_design(strips, photos_per_strip, forelap, sidelap):
    if strips < 1 or photos_per_strip < 2:
        raise ParameterError("a flight design needs at least 1 strip of 2 photos")
    if not all(math.isfinite(v) for v in (forelap, sidelap)):
        raise ParameterError("forelap and sidelap must be finite numbers")
    if not 0.5 <= forelap < 1.0:
        raise ParameterError(f"forelap {forelap}: between 0.5 and 1 (a fraction, e.g. 0.6)")
    if not 0.0 <= sidelap < 1.0:
        raise ParameterError(f"sidelap {sidelap}: between 0 and 1 (a fraction, e.g. 0.2)")


#: The most blocks of the factor that --plot draws (each costs 17 bytes while drawn).
MAX_DRAWN_BLOCKS = 200_000_000


def write_pattern(net: Network, path, ordering, max_cells=600):
    """Draw the pattern of ``M`` with its fill-in for an ordering (Rostom's Figure 12): the
    non-zero blocks, the fill-in of the factor, and the boundaries of the lines. A
    project's network also takes ``"adjust"`` (or its name): the order ``sapgo order``
    gives it. Networks of
    more than ``max_cells`` units are drawn in ``max_cells`` x ``max_cells`` cells (a cell is
    non-zero if any block in it is, else fill-in if any is)."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    from .plots import _pyplot
    from .symbolic import factor_pattern

    if ordering == "adjust" or ordering not in ORDERINGS:
        if net.adjust_order is None or ordering not in ("adjust", net.adjust_order[0]):
            raise ParameterError(f"no ordering {ordering!r} to draw: choose from "
                                 f"{', '.join(ORDERINGS)}"
                                 + (", adjust" if net.adjust_order is not None else ""))
        ordering, perm = net.adjust_order
        lines = None
    else:
        perm, lines = orderings(net)[ordering]
    blocks = symbolic_counts(net.n, (net.s, net.t), perm)["factor_blocks"]
    if blocks > MAX_DRAWN_BLOCKS:
        raise ParameterError(f"the factor of {ordering} has {blocks:,} blocks, too many to "
                             f"draw (at most {MAX_DRAWN_BLOCKS:,}): draw the recommended "
                             f"ordering, or a smaller block")
    rows, cols, fill = factor_pattern(net.n, (net.s, net.t), perm)
    n = net.n
    cells = max(1, min(n, max_cells))
    img = np.zeros((cells, cells), np.int8)
    ri, ci = rows * cells // max(n, 1), cols * cells // max(n, 1)
    value = np.where(fill, 1, 2).astype(np.int8)
    np.maximum.at(img, (ri, ci), value)
    img = np.maximum(img, img.T)
    plt = _pyplot()
    # constrained layout: the legend goes under the axes, outside the matrix
    fig, ax = plt.subplots(figsize=(7, 7.6), layout="constrained")
    cmap = ListedColormap(["white", "#f4b183", "#1f4e79"])
    ax.imshow(img, cmap=cmap, vmin=0, vmax=2, interpolation="nearest",
              extent=(-0.5, n - 0.5, n - 0.5, -0.5))
    if n <= max_cells and lines is not None:
        for b in np.flatnonzero(np.diff(lines[perm])) + 0.5:
            ax.axhline(b, color="0.8", lw=0.5)
            ax.axvline(b, color="0.8", lw=0.5)
    unit = net.kind[:-1] if net.kind.endswith("s") else net.kind
    ax.set_xlabel(f"{unit} number in the {ordering} order (column of M)")
    ax.set_ylabel(f"{unit} number (row of M)")
    ax.set_title(f"pattern of M, {ordering}: {n} {net.kind}, "
                 f"{int((~fill).sum())} blocks (lower), {int(fill.sum())} fill-in"
                 + (f"\n(drawn in {cells} x {cells} cells)" if cells < n else ""),
                 fontsize=10)
    handles = [Patch(color="#1f4e79", label="non-zero block of M"),
               Patch(color="#f4b183", label="fill-in of the factor")]
    if n <= max_cells and lines is not None:
        handles.append(Patch(facecolor="white", edgecolor="0.6",
                             label="boundaries of the ordering's lines"))
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=8,
               frameon=False)
    fig.savefig(path, dpi=120)
    plt.close(fig)
