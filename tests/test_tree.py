"""The partition tree and the multifrontal solver against dense references."""

import itertools

import numpy as np
import pytest

from sapgo.solve.band import PivotError
from sapgo.solve.fronts import TreeSolver
from sapgo.solve.partition import best_tree, check_separators, nested_dissection, \
    supernodal_tree


def grid_graph(nx, ny, reach=(2, 1)):
    """Stations of a block of ``ny`` strips of ``nx`` photos, joined as a 9-point pattern
    with 60 % forelap joins them: two along the strip, one across (and diagonals)."""
    idx = np.arange(nx * ny).reshape(ny, nx)
    s, t = [], []
    for dy in range(0, reach[1] + 1):
        for dx in range(-reach[0], reach[0] + 1):
            if dy == 0 and dx <= 0:
                continue
            a = idx[:ny - dy, max(0, -dx):nx - max(0, dx)]
            b = idx[dy:, max(0, dx):nx - max(0, -dx) if dx < 0 else nx][:, :a.shape[1]]
            if dx < 0:
                b = idx[dy:, :nx + dx]
            s.append(a.ravel())
            t.append(b.ravel())
    s, t = np.concatenate(s), np.concatenate(t)
    lo, hi = np.minimum(s, t), np.maximum(s, t)
    pos = np.column_stack([idx.ravel() % nx * 1.0, idx.ravel() // nx * 1.3,
                           np.zeros(nx * ny)])
    return pos, (lo, hi)


def spd_on_graph(n, edges, k, seed):
    rng = np.random.default_rng(seed)
    m = np.zeros((k * n, k * n))
    for s, t in zip(*edges):
        blk = rng.normal(size=(k, k))
        m[k * s:k * s + k, k * t:k * t + k] += blk
        m[k * t:k * t + k, k * s:k * s + k] += blk.T
    m += np.diag(np.abs(m).sum(axis=1) + 1.0)
    return m


#: Tiles for the tests: fronts beyond 5 stations tiled, panels of 12 to 2 columns.
SMALL_TILES = (8 * 30.0 ** 2, 8 * 60 * 12.0)


def _fill(sol, tree, i, ml, k, rhs=None, border=None):
    """Node ``i`` of the matrix ``ml`` (logical order): its own columns into the front (or,
    tiled, panel by panel), ``rhs`` and the ``border``'s rows into its right-hand sides."""
    fs = (k * tree.front(i)[:, None] + np.arange(k)).ravel()
    own = k * tree.own(i)
    tiled = bool(sol.tiled[i])
    a, b = sol.open(i, tiled)
    if b.ndim == 1:
        b[:own] = rhs[fs[:own]]
    else:
        b[:own, 0] = rhs[fs[:own]]
        b[:own, 1:] = border[fs[:own]]
    cols = np.tril(ml[np.ix_(fs, fs[:own])])
    if not tiled:
        a[0][:] = cols   # (the own columns; the update block starts empty)
        sol.eliminate(i, a, b)
        return

    def assemble(c0, c1, panel):
        hi = min(c1, own)
        if c0 < hi:
            panel[:, :hi - c0] += cols[c0:, c0:hi]
    sol.eliminate_tiled(i, assemble, b)


def _solve_tree(tree, perm, m, rhs, k, tmp_path, tile=None, where="file"):
    """The tree's solve of ``m x = rhs``; the factor on file, or (``where="core"``) in core
    in a reused buffer full of NaN: whatever the solver does not write, it never reads."""
    from sapgo.solve.fronts import FactorFile, factor_layout

    inv = np.empty_like(perm)
    inv[perm] = np.arange(len(perm))
    sc = (k * perm[:, None] + np.arange(k)).ravel()
    ml = m[np.ix_(sc, sc)]          # logical order
    bl = rhs[sc]
    file = None
    if where == "core":
        layout = factor_layout(tree, k)
        arena = np.full(FactorFile.record_bytes(layout).sum() // 8 + 5, np.nan)
        file = FactorFile(None, layout, arena=arena)
        assert file.arena is arena
    sol = TreeSolver(tree, k, tmp_path / "factor.bin", tile=tile, scratch=tmp_path, file=file)
    for i in range(tree.n_nodes):
        _fill(sol, tree, i, ml, k, bl)
    x = sol.solve(len(perm)).ravel()
    return sol, ml, bl, x


@pytest.mark.parametrize("method,tile", [("geometric", None), ("graph", None),
                                         ("geometric", SMALL_TILES)])
@pytest.mark.parametrize("shape", [(12, 9), (40, 3), (7, 7)])
@pytest.mark.parametrize("where", ["file", "core"])
def test_tree_solve_equals_dense(tmp_path, method, shape, tile, where):
    """The solve, y'y and the selected inversion over every front against dense numpy,
    with every front in core and with the fronts beyond 5 stations tiled (panels of 2
    stations, updates and the inverse's parts in scratch files); the factor on file and in
    core (a reused buffer)."""
    pos, edges = grid_graph(*shape)
    n = len(pos)
    active = np.ones(n, bool)
    tree, perm = (nested_dissection(pos, active, edges, leaf_stations=6) if method == "geometric"
                  else supernodal_tree(active, edges, relax=((6, 1.0),)))
    inv = np.empty_like(perm)
    inv[perm] = np.arange(n)
    assert check_separators(tree, inv[edges[0]], inv[edges[1]])
    assert sorted(perm.tolist()) == list(range(n))
    k = 6
    m = spd_on_graph(n, edges, k, 1)
    rhs = np.random.default_rng(2).normal(size=k * n)
    sol, ml, bl, x = _solve_tree(tree, perm, m, rhs, k, tmp_path, tile, where)
    assert sol.tiled.any() == (tile is not None)
    assert sol.file.in_core == (where == "core")
    np.testing.assert_allclose(x, np.linalg.solve(ml, bl), rtol=1e-9, atol=1e-12)
    # y'y = b' M^-1 b
    assert sol.y_norm2 == pytest.approx(bl @ np.linalg.solve(ml, bl), rel=1e-10)
    # selected inversion: the inverse over every front
    z = np.linalg.inv(ml)
    seen = []

    def check(i, zf):
        fs = (k * tree.front(i)[:, None] + np.arange(k)).ravel()
        if not isinstance(zf, np.ndarray):   # a tiled front's inverse, by panels
            assert sol.tiled[i]
            own = tree.own(i)
            np.testing.assert_allclose(zf.diag_blocks(k, 0, own),
                                       [z[np.ix_(fs[k * s:k * s + k], fs[k * s:k * s + k])]
                                        for s in range(own)], rtol=1e-8, atol=1e-12)
            pick = np.arange(0, len(fs), 5)
            np.testing.assert_allclose(zf.gather(pick), z[np.ix_(fs[pick], fs[pick])],
                                       rtol=1e-8, atol=1e-12)
            zf = zf.dense()
        np.testing.assert_allclose(zf, z[np.ix_(fs, fs)], rtol=1e-8, atol=1e-12)
        seen.append(i)

    sol.inverse(check)
    assert sorted(seen) == list(range(tree.n_nodes))
    # no scratch file is left behind (updates and inverse parts are removed when used)
    assert not list(tmp_path.glob("panels-*"))
    if tile is not None:
        return
    # as the precision pass runs it on two threads: the top first, then each worker's
    # subtrees from the inverses over their roots' boundaries alone
    from sapgo.solve.tree import parallel_plan

    per, top = parallel_plan(tree, k, 2)
    seen.clear()
    held = sol.inverse(check, top) if top else {}
    assert all(tree.parent[c] in top for c in held)
    for ranges in per:
        sol.inverse(check, [i for a, b in ranges for i in range(a, b)], held)
    assert sorted(seen) == list(range(tree.n_nodes))
    sol.close()


@pytest.mark.parametrize("method", ["geometric", "graph"])
def test_tree_solve_without_the_links_equals_dense(tmp_path, monkeypatch, method):
    """A tree too large to keep its links (each node's places worked out node by node)
    solves as the dense reference."""
    from sapgo.solve import partition

    monkeypatch.setattr(partition, "LINKS_MAX_BOUNDARY", 0)
    pos, edges = grid_graph(12, 9)
    n = len(pos)
    active = np.ones(n, bool)
    tree, perm = (nested_dissection(pos, active, edges, leaf_stations=6) if method == "geometric"
                  else supernodal_tree(active, edges, relax=((6, 1.0),)))
    assert tree.links(6) is None
    m = spd_on_graph(n, edges, 6, 1)
    rhs = np.random.default_rng(2).normal(size=6 * n)
    sol, ml, bl, x = _solve_tree(tree, perm, m, rhs, 6, tmp_path, None, "core")
    assert sol.links is None
    np.testing.assert_allclose(x, np.linalg.solve(ml, bl), rtol=1e-9, atol=1e-12)
    sol.close()


@pytest.mark.parametrize("where", ["file", "core"])
def test_many_children_and_damping_equal_dense(tmp_path, where):
    """A hub station joined to five separate chains: METIS' tree gives the hub's node five
    children (the one-call elimination takes two, the others are added before it); with
    damping on every node's own diagonal, the solve and y'y equal dense numpy's of the
    damped matrix."""
    from sapgo.solve.fronts import FactorFile, factor_layout

    arms, length = 5, 4
    s, t = [], []
    for a in range(arms):
        first = 1 + a * length
        s += [0] + list(range(first, first + length - 1))
        t += [first] + list(range(first + 1, first + length))
    edges = (np.array(s), np.array(t))
    n = 1 + arms * length
    active = np.ones(n, bool)
    tree, perm = supernodal_tree(active, edges, relax=((1, 0.0),))
    assert max(len(c) for c in tree.children()) >= 3
    k = 6
    m = spd_on_graph(n, edges, k, 3)
    rhs = np.random.default_rng(4).normal(size=k * n)
    sc = (k * perm[:, None] + np.arange(k)).ravel()
    ml, bl = m[np.ix_(sc, sc)], rhs[sc]
    damping = np.random.default_rng(5).uniform(0.5, 2.0, k * n)
    file = (FactorFile(None, factor_layout(tree, k)) if where == "core" else None)
    sol = TreeSolver(tree, k, tmp_path / "factor.bin", file=file)
    for i in range(tree.n_nodes):
        fs = (k * tree.front(i)[:, None] + np.arange(k)).ravel()
        own = k * tree.own(i)
        a, b = sol.open(i)
        b[:own] = bl[fs[:own]]
        a[0][:] = np.tril(ml[np.ix_(fs, fs[:own])])
        sol.eliminate(i, a, b, damping[fs[:own]])
    x = sol.solve(n).ravel()
    md = ml + np.diag(damping)
    np.testing.assert_allclose(x, np.linalg.solve(md, bl), rtol=1e-9, atol=1e-12)
    assert sol.y_norm2 == pytest.approx(bl @ np.linalg.solve(md, bl), rel=1e-10)
    sol.close()


@pytest.mark.parametrize("n_border", [0, 2])
def test_split_elimination_equals_one_thread(monkeypatch, n_border):
    """Fronts eliminated on two threads (:meth:`TreeSolver._eliminate_split`: every front,
    panels of 7 columns, not a multiple of k, so that a station's unknowns straddle two) give
    the same solution, y'y and border sums as the one-call elimination, and the dense
    solution of the damped matrix; a matrix that is not positive definite fails at the same
    station and parameter both ways."""
    from concurrent.futures import ThreadPoolExecutor

    from sapgo.solve import fronts

    pos, edges = grid_graph(12, 6)
    n = len(pos)
    tree, perm = nested_dissection(pos, np.ones(n, bool), edges, leaf_stations=6)
    k = 6
    m = spd_on_graph(n, edges, k, 8)
    sc = (k * perm[:, None] + np.arange(k)).ravel()
    ml = m[np.ix_(sc, sc)]
    rng = np.random.default_rng(9)
    bl = rng.normal(size=(k * n, 1 + n_border))
    damping = rng.uniform(0.5, 2.0, k * n)
    theta = rng.normal(size=n_border)

    def run(split, matrix):
        sol = TreeSolver(tree, k, None, file=fronts.FactorFile(None, fronts.factor_layout(
            tree, k), n_rhs=1 + n_border), n_border=n_border)
        with ThreadPoolExecutor(1) as pool:
            sol.pool = pool if split else None
            for i in range(tree.n_nodes):
                fs = (k * tree.front(i)[:, None] + np.arange(k)).ravel()
                own = k * tree.own(i)
                a, b = sol.open(i)
                b.reshape(len(fs), -1)[:own] = bl[fs[:own]]
                a[0][:] = np.tril(matrix[np.ix_(fs, fs[:own])])
                sol.eliminate(i, a, b, damping[fs[:own]])
        return sol

    monkeypatch.setattr(fronts, "SPLIT_ROWS", 0)
    monkeypatch.setattr(fronts, "SPLIT_PANEL", 7)
    one, two = run(False, ml), run(True, ml)
    x1 = one.solve(n, theta if n_border else None)
    x2 = two.solve(n, theta if n_border else None)
    np.testing.assert_allclose(x2, x1, rtol=1e-10, atol=1e-12)
    assert two.y_norm2 == pytest.approx(one.y_norm2, rel=1e-12)
    np.testing.assert_allclose(two.ww, one.ww, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(two.wy, one.wy, rtol=1e-10, atol=1e-12)
    md = ml + np.diag(damping)
    r = bl[:, 0] - bl[:, 1:] @ theta if n_border else bl[:, 0]
    np.testing.assert_allclose(x2.ravel(), np.linalg.solve(md, r), rtol=1e-9, atol=1e-12)
    bad = ml.copy()   # (an unknown of the last station made dependent: fails in the root)
    j = k * (n - 1) + 4
    bad[j, :] = 0.0
    bad[:, j] = 0.0
    damping[j] = 0.0
    fails = []
    for split in (False, True):
        with pytest.raises(PivotError) as err:
            run(split, bad)
        fails.append((err.value.row, err.value.parameter))
    assert fails[0] == fails[1] == (n - 1, 4)


def test_front_memory_model_is_what_the_solver_holds(tmp_path):
    """The fronts' peak of ``Tree.peak_front_bytes`` is, to the byte, the most the solver
    holds at once (the front being built, its own columns and its update block, plus the
    updates waiting for their parents); the plan of two workers needs at least as much."""
    from sapgo.solve.tree import parallel_plan

    pos, edges = grid_graph(30, 12)
    n = len(pos)
    tree, perm = nested_dissection(pos, np.ones(n, bool), edges, leaf_stations=8)
    k = 6
    m = spd_on_graph(n, edges, k, 4)
    inv = np.empty_like(perm)
    inv[perm] = np.arange(n)
    sc = (k * perm[:, None] + np.arange(k)).ravel()
    ml = m[np.ix_(sc, sc)]
    sol = TreeSolver(tree, k, None, file=None)
    peak = 0
    for i in range(tree.n_nodes):
        a, b = sol.open(i)
        peak = max(peak, a[0].nbytes + a[1].nbytes
                   + sum(u[0].nbytes for u in sol.updates.values()))
        fs = (k * tree.front(i)[:, None] + np.arange(k)).ravel()
        own = k * tree.own(i)
        a[0][:] = np.tril(ml[np.ix_(fs, fs[:own])])
        sol.eliminate(i, a, b)
    assert peak == tree.peak_front_bytes(k)
    assert tree.peak_front_bytes(k, parallel_plan(tree, k, 2)) >= peak


def test_work_plan_takes_the_shortest_plan_that_fits():
    """Of the subtree sizes tried, the plan of the smallest predicted length
    (``plan_flops``: the busiest worker, then the top) among those whose fronts fit; on a
    square grid's balanced tree that is one subtree a worker and the root alone on top. A
    budget that only a smaller-fronted plan fits gets that plan (or one worker)."""
    import sapgo
    from sapgo.solve import tree as tree_mod

    pos, edges = grid_graph(40, 40)
    n = len(pos)
    tree, _ = nested_dissection(pos, np.ones(n, bool), edges, leaf_stations=16)
    k = 6
    shares = (1.0, 0.5, 0.25, 0.125, 0.0625)
    plans = [tree_mod.parallel_plan(tree, k, 2, s) for s in shares]
    lengths = [tree_mod.plan_flops(tree, k, *pl) for pl in plans]
    opts = sapgo.Options(memory="8G")
    per, top, need, tile = tree_mod.work_plan(tree, k, opts, threads=2)
    assert tile is None and len(per) == 2
    assert tree_mod.plan_flops(tree, k, per, top) == min(lengths)
    assert (per, top) == plans[int(np.argmin(lengths))]
    # a brute-force check of plan_flops itself
    fl = {i: (k * tree.own(i)) ** 3 / 3 + (k * tree.own(i)) ** 2 * k * len(tree.bnd(i))
          + k * tree.own(i) * (k * len(tree.bnd(i))) ** 2 + 1e6 for i in range(tree.n_nodes)}
    busiest = max(sum(fl[i] for a, b in w for i in range(a, b)) for w in per)
    assert np.isclose(tree_mod.plan_flops(tree, k, per, top),
                      busiest + sum(fl[i] for i in top) / tree_mod.TOP_SPEED)
    # too small a budget for the chosen plan's fronts side by side: another one that fits
    small = need - 1 + tree_mod.BASELINE + tree_mod.BASELINE_PER_STATION * 0
    per2, top2, need2, tile2 = tree_mod.work_plan(
        tree, k, sapgo.Options(memory=str(int(small))), threads=2)
    assert need2 <= small - tree_mod.BASELINE and (per2, top2) != (per, top)


def test_disconnected_block_is_a_forest(tmp_path):
    pos1, e1 = grid_graph(10, 3)
    n1 = len(pos1)
    pos = np.concatenate([pos1, pos1 + [100.0, 0, 0]])
    edges = (np.concatenate([e1[0], e1[0] + n1]), np.concatenate([e1[1], e1[1] + n1]))
    active = np.ones(2 * n1, bool)
    active[5] = False            # an excluded station follows the tree
    tree, perm = nested_dissection(pos, active, edges, leaf_stations=8)
    assert (tree.parent < 0).sum() == 2
    assert tree.n_active == 2 * n1 - 1 and perm[-1] == 5
    k = 6
    keep = active[edges[0]] & active[edges[1]]
    m = spd_on_graph(2 * n1, (edges[0][keep], edges[1][keep]), k, 3)
    rhs = np.random.default_rng(4).normal(size=k * 2 * n1)
    sc_act = (k * perm[:tree.n_active, None] + np.arange(k)).ravel()
    sub = m[np.ix_(sc_act, sc_act)]
    sol = TreeSolver(tree, k, tmp_path / "f.bin")
    for i in range(tree.n_nodes):
        a, b = sol.open(i)
        fs = (k * tree.front(i)[:, None] + np.arange(k)).ravel()
        own = k * tree.own(i)
        a[0][:] = np.tril(sub[np.ix_(fs, fs[:own])])
        b[:own] = rhs[sc_act][fs[:own]]
        sol.eliminate(i, a, b)
    x = sol.solve(2 * n1)
    np.testing.assert_allclose(x[:tree.n_active].ravel(), np.linalg.solve(sub, rhs[sc_act]),
                               rtol=1e-9)
    assert (x[tree.n_active:] == 0).all()


def test_pivot_names_the_station(tmp_path):
    pos, edges = grid_graph(8, 4)
    n = len(pos)
    tree, perm = nested_dissection(pos, np.ones(n, bool), edges, leaf_stations=6)
    k = 6
    m = spd_on_graph(n, edges, k, 5)
    bad = 17
    inv = np.empty_like(perm)
    inv[perm] = np.arange(n)
    s = k * bad + 2
    m[s, :] = 0.0
    m[:, s] = 0.0
    for tile in (None, SMALL_TILES):
        with pytest.raises(PivotError) as e:
            _solve_tree(tree, perm, m, np.ones(k * n), k, tmp_path, tile)
        assert e.value.row == inv[bad] and e.value.parameter == 2


def test_best_tree_prefers_the_smaller_predicted_time():
    from sapgo.ordering import TREE_NODE_SECONDS, TREE_RATE

    pos, edges = grid_graph(30, 30)
    tree, perm, flops = best_tree(pos, np.ones(900, bool), edges)
    assert set(flops) == {"geometric", "graph"}
    other = [m for m in flops if m != tree.method][0]
    t_other, _ = best_tree(pos, np.ones(900, bool), edges, methods=(other,))[:2]
    cost = lambda t: t.figures()["flops"] / TREE_RATE + TREE_NODE_SECONDS * t.n_nodes
    assert cost(tree) <= cost(t_other)
    # positions that say nothing: the graph method alone
    tree2, _, flops2 = best_tree(np.full((900, 3), np.nan), np.ones(900, bool), edges)
    assert set(flops2) == {"graph"}


def test_konig_cover_is_a_minimum_vertex_cover():
    """The separator kernel against scipy's maximum matching (König: a minimum cover has
    as many vertices as a maximum matching) and the definition of a cover."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import maximum_bipartite_matching

    from sapgo.solve.partition import _cut_cover

    rng = np.random.default_rng(7)
    for trial in range(60):
        nl, nr = (int(x) for x in rng.integers(1, 25, size=2))
        ne = int(rng.integers(1, 3 * max(nl, nr)))
        ls = rng.integers(0, nl, ne)
        rs = rng.integers(0, nr, ne) + nl            # right vertices after the left ones
        side = np.r_[np.zeros(nl, np.int8), np.ones(nr, np.int8)]
        swap = rng.random(ne) < 0.5                  # edges given either way round
        same = rng.integers(0, nl, 5), rng.integers(0, nl, 5)   # not cut: ignored
        es = np.r_[np.where(swap, rs, ls), same[0]].astype(np.int64)
        et = np.r_[np.where(swap, ls, rs), same[1]].astype(np.int64)
        cover = set(_cut_cover(side, es, et).tolist())
        assert all(a in cover or b in cover for a, b in zip(ls, rs))
        lu, li = np.unique(ls, return_inverse=True)
        ru, ri = np.unique(rs, return_inverse=True)
        g = csr_matrix((np.ones(ne), (li, ri)), shape=(len(lu), len(ru)))
        matching = int((maximum_bipartite_matching(g, perm_type="column") >= 0).sum())
        assert len(cover) == matching


def test_boundaries_sweep_against_the_definition():
    """:func:`set_boundaries`' numba sweep against the definition node by node: a node's
    boundary is the distinct stations after its own among its own stations' neighbours and
    its children's boundaries; both methods' trees of grids and of random graphs, and the
    tree links (each child's boundary places in its parent's front)."""
    from sapgo.solve.partition import set_boundaries

    def by_definition(tree, s, t):
        nbr = {}
        for a, b in zip(s.tolist(), t.tolist()):
            nbr.setdefault(a, set()).add(b)
            nbr.setdefault(b, set()).add(a)
        children = tree.children()
        bnd = []
        for i in range(tree.n_nodes):
            lo, hi = int(tree.lo[i]), int(tree.hi[i])
            x = set()
            for st in range(lo, hi):
                x |= nbr.get(st, set())
            for c in children[i]:
                x |= set(bnd[c].tolist())
            bnd.append(np.array(sorted(y for y in x if y >= hi), np.int64))
        return bnd

    rng = np.random.default_rng(3)
    cases = [grid_graph(12, 9), grid_graph(30, 3)]
    for n in (40, 90):
        e = rng.integers(0, n, size=(2, 3 * n))
        e = e[:, e[0] != e[1]]
        cases.append((rng.normal(size=(n, 3)), (e.min(axis=0), e.max(axis=0))))
    for pos, edges in cases:
        n = len(pos)
        for tree, perm in (nested_dissection(pos, np.ones(n, bool), edges, leaf_stations=6),
                           supernodal_tree(np.ones(n, bool), edges)):
            where = np.empty(n, np.int64)
            where[perm] = np.arange(n)
            s, t = where[edges[0]], where[edges[1]]
            set_boundaries(tree, s, t)
            want = by_definition(tree, s, t)
            for i in range(tree.n_nodes):
                assert np.array_equal(tree.bnd(i), want[i])
            for i, (front, kids) in enumerate(tree.links(6)):
                assert np.array_equal(front, tree.front(i))
                for c, ix, cm in kids:
                    places = np.searchsorted(front, tree.bnd(c))
                    assert np.array_equal(front[places], tree.bnd(c))
                    assert np.array_equal(ix, (6 * places[:, None] + np.arange(6)).ravel())
                    assert cm == int((ix < 6 * tree.own(i)).sum())


def test_amalgamation_kernel_against_the_loop_in_words():
    """The relaxed amalgamation (numba) against its statement in plain Python: each
    supernode that is its parent's last child joins it when some (stations, zeros) rule
    allows, its children passing to the node it joined."""
    from sapgo.solve.partition import RELAX, _amalgamate

    def in_words(lo, hi, sp, bnd, csum, relax):
        lo, sp = lo.copy(), sp.copy()
        zeros = np.zeros(len(lo))
        alive = np.ones(len(lo), bool)
        for a in range(len(lo)):
            q = sp[a]
            if q < 0 or hi[a] != lo[q]:
                continue
            cols = hi[q] - lo[a]
            span = np.arange(lo[a], hi[a])
            z = float((hi[q] - span + bnd[q]).sum() - (csum[hi[a]] - csum[lo[a]]))
            total = zeros[a] + zeros[q] + z
            entries = cols * (cols + 1) / 2 + cols * bnd[q]
            if any(cols <= nr and total <= zr * entries for nr, zr in relax):
                lo[q] = lo[a]
                zeros[q] = total
                alive[a] = False
                sp[sp == a] = q
        return lo, sp, alive

    rng = np.random.default_rng(9)
    for trial in range(40):
        m = int(rng.integers(2, 60))
        sizes = rng.integers(1, 6, m)
        hi = np.cumsum(sizes)
        lo = hi - sizes
        sp = np.array([int(rng.integers(a + 1, m)) if a < m - 1 and rng.random() < 0.9
                       else -1 for a in range(m)], np.int64)
        bnd = rng.integers(0, 30, m)
        cnt = rng.integers(1, 40, int(hi[-1]))
        csum = np.concatenate([[0], np.cumsum(cnt)])
        for relax in (RELAX, ((4, 0.3),)):
            want = in_words(lo, hi, sp, bnd, csum, relax)
            got_lo, got_sp = lo.copy(), sp.copy()
            alive = _amalgamate(got_lo, hi, got_sp, bnd, csum,
                                np.array([r[0] for r in relax]),
                                np.array([r[1] for r in relax], float))
            assert np.array_equal(alive, want[2])
            assert np.array_equal(got_lo[alive], want[0][alive])
            assert np.array_equal(got_sp[alive], want[1][alive])


@pytest.mark.parametrize("shape", [(15, 12), (60, 4)])
def test_metis_supernodal_tree_solves_exactly(tmp_path, shape):
    from sapgo.solve.partition import supernodal_tree

    pos, edges = grid_graph(*shape)
    n = len(pos)
    tree, perm = supernodal_tree(np.ones(n, bool), edges)
    inv = np.empty_like(perm)
    inv[perm] = np.arange(n)
    assert check_separators(tree, inv[edges[0]], inv[edges[1]])
    assert tree.n_nodes > 2 and (tree.lo[1:] == tree.hi[:-1]).all()
    k = 6
    m = spd_on_graph(n, edges, k, 9)
    rhs = np.random.default_rng(3).normal(size=k * n)
    _, ml, bl, x = _solve_tree(tree, perm, m, rhs, k, tmp_path)
    np.testing.assert_allclose(x, np.linalg.solve(ml, bl), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("w,rows", [(20, 50), (75, 75), (130, 300)])
def test_recursive_column_cholesky_against_numpy(w, rows):
    """chol_columns (recursive halves above CHOL_LEAF columns) gives numpy's Cholesky
    columns, and names the first failing pivot wherever it lies (in the first leaf or in a
    later one) as dpotrf with the band's pivot test would."""
    from sapgo.blas import FNS
    from sapgo.solve.tiles import CHOL_LEAF, chol_columns

    assert CHOL_LEAF < 75   # (w = 20: one leaf; 75, 130: several)
    rng = np.random.default_rng(w)
    g = rng.normal(size=(rows, rows))
    a = g @ g.T + rows * np.eye(rows)
    panel = np.asfortranarray(np.tril(a[:, :w]))
    orig = np.diag(a)[:w].copy()
    assert chol_columns(FNS, panel.reshape(-1, order="F"), rows, rows, w, 1e-12, orig) == 0
    np.testing.assert_allclose(np.tril(panel), np.linalg.cholesky(a)[:, :w], rtol=1e-11,
                               atol=1e-11)
    for bad in sorted({0, w // 2, w - 1}):   # column ``bad`` a combination of the earlier
        b = a.copy()
        c = b[:, :bad] @ rng.normal(size=bad)
        b[:, bad] = c
        b[bad, :] = c
        b[bad, bad] = c[:bad] @ np.linalg.solve(b[:bad, :bad], c[:bad]) if bad else 0.0
        panel = np.asfortranarray(np.tril(b[:, :w]))
        orig = np.abs(np.diag(b)[:w]) + 1.0
        got = chol_columns(FNS, panel.reshape(-1, order="F"), rows, rows, w, 1e-10, orig)
        assert got == bad + 1, (bad, got)


def test_extend_add_and_front_zeros_against_numpy():
    """The extend-add kernel (stretch by stretch) equals numpy's fancy-indexed add on the
    lower triangle, for scattered and contiguous places; a fresh front is zero on its block
    lower triangle (all that is read)."""
    from sapgo.solve.fronts import _zero_block_lower
    from sapgo.solve.tiles import extend_add

    rng = np.random.default_rng(7)
    k = 6
    for trial in range(30):
        nf = int(rng.integers(2, 40))
        places = np.sort(rng.choice(nf, int(rng.integers(1, nf + 1)), replace=False))
        ix = (k * places[:, None] + np.arange(k)).ravel()
        m, n = int(rng.integers(0, 25)), len(ix)
        u = np.asfortranarray(rng.normal(size=(m + n, m + n)))
        a = np.asfortranarray(rng.normal(size=(k * nf, k * nf)))
        want = a.copy()
        low = np.tril(u[m:, m:])
        r, c = np.nonzero(np.tril(np.ones((n, n))))
        np.add.at(want, (ix[r], ix[c]), low[r, c])
        extend_add(a, 0, np.asfortranarray(u[m:, m:]), 0, ix, 0, n)
        assert np.array_equal(a, want)
        # a panel of the front (rows and columns from c0 to c1): the child's columns that
        # fall in it, read from the child's update by column range
        c0 = k * int(rng.integers(0, nf))
        c1 = min(k * nf, c0 + k * int(rng.integers(1, 4)))
        ca, cb = np.searchsorted(ix, [c0, c1])
        panel = np.asfortranarray(a[c0:, c0:c1])
        s = np.asfortranarray(u[m + ca:, m + ca:m + cb])
        extend_add(panel, c0, s, ca, ix, ca, cb)
        sel = (c >= ca) & (c < cb)
        np.add.at(want, (ix[r[sel]], ix[c[sel]]), low[r[sel], c[sel]])
        assert np.array_equal(panel, want[c0:, c0:c1])
    z = np.asfortranarray(rng.normal(size=(5 * k, 5 * k)))
    _zero_block_lower(z, k)
    blocks = np.kron(np.tril(np.ones((5, 5))), np.ones((k, k))) > 0
    assert np.all(z[blocks] == 0.0)


def test_held_records_read_as_the_file(tmp_path):
    """Records held in core read exactly as from the file, a copy each time; too large a
    budget keeps them in the file, a writable project never holds them."""
    import shutil

    from sapgo.generate import generate_block
    from sapgo.project import Project

    path = tmp_path / "h.h5"
    generate_block(path, strips=3, photos_per_strip=6, control_points=6, progress=False)
    with Project(path) as p:
        ref = {n: (p.read(n, 3, 40), p.read_field(n, "status", 5, 30))
               for n in ("points", "observations")}
        assert p.hold(max_bytes=10) == 0
        assert p.hold() > 0
        for n, (recs, status) in ref.items():
            got = p.read(n, 3, 40)
            assert np.array_equal(got, recs) and got.dtype == recs.dtype
            assert np.array_equal(p.read_field(n, "status", 5, 30), status)
            got["status"] = 99   # a copy: the held records do not change
            assert np.array_equal(p.read(n, 3, 40), recs)
    shutil.copy(path, tmp_path / "w.h5")
    with Project(tmp_path / "w.h5", "r+") as q:
        assert q.hold() == 0


def test_bordered_tree_solve_equals_dense(tmp_path):
    """Self-calibration's border on the tree: the right-hand side and the border's columns
    ``B`` forward-substituted together through the fronts; the border's Schur complement
    from ``W'W`` and ``W'y``, then the stations, ``X = M^-1 B`` and ``t'S^-1 t`` against a
    dense solve of the bordered matrix (in core and through the factor file)."""
    from sapgo.solve.band import border_schur_solve
    from sapgo.solve.fronts import FactorFile, factor_layout

    pos, edges = grid_graph(14, 6)
    n = len(pos)
    tree, perm = nested_dissection(pos, np.ones(n, bool), edges, leaf_stations=6)
    k, ng = 6, 5
    rng = np.random.default_rng(11)
    m = spd_on_graph(n, edges, k, 3)
    sc = (k * perm[:, None] + np.arange(k)).ravel()
    ml = m[np.ix_(sc, sc)]
    bb = rng.normal(size=(k * n, ng))
    c = bb.T @ np.linalg.solve(ml, bb) + np.diag(rng.uniform(1, 2, ng))
    d, g = rng.normal(size=k * n), rng.normal(size=ng)
    full = np.block([[ml, bb], [bb.T, c]])
    want = np.linalg.solve(full, np.r_[d, g])
    for path, tile in itertools.product((None, tmp_path / "f.bin"), (None, SMALL_TILES)):
        file = FactorFile(path, factor_layout(tree, k), n_rhs=1 + ng)
        sol = TreeSolver(tree, k, None, file=file, n_border=ng, tile=tile, scratch=tmp_path)
        assert sol.tiled.any() == (tile is not None)
        for i in range(tree.n_nodes):
            _fill(sol, tree, i, ml, k, d, bb)
        theta, decrease, s_inv = border_schur_solve(c - sol.ww, g - sol.wy)
        x = sol.solve(n, theta).ravel()
        np.testing.assert_allclose(np.r_[x, theta], want, rtol=1e-9, atol=1e-11)
        np.testing.assert_allclose(s_inv, np.linalg.inv(full)[k * n:, k * n:], rtol=1e-9,
                                   atol=1e-12)
        np.testing.assert_allclose(sol.border_x(n).reshape(k * n, ng),
                                   np.linalg.solve(ml, bb), rtol=1e-9, atol=1e-11)
        # x'b of the solution = y'y + t'S^-1 t
        assert sol.y_norm2 + decrease == pytest.approx(np.r_[d, g] @ want, rel=1e-10)
        sol.close()


def count_trees(monkeypatch):
    """``best_tree`` counting its calls (the active stations of each): ``(calls, real)``."""
    import sapgo.solve.partition as partition

    calls = []
    real = partition.best_tree

    def counting(pos, active, *a, **kw):
        calls.append(int(np.count_nonzero(active)))
        return real(pos, active, *a, **kw)

    monkeypatch.setattr(partition, "best_tree", counting)
    return calls, real


def test_a_block_whose_band_beats_the_trees_fixed_cost_is_not_partitioned(monkeypatch):
    """``choose_solver`` "auto": when the band's predicted factorisation takes no longer
    than the tree's fixed cost alone, no tree is built (none could predict less), and the
    choice is the one the whole tree gives; forced, the tree is still built."""
    import sapgo.ordering as ordering
    import sapgo.solve.partition as partition

    calls, real = count_trees(monkeypatch)
    pos, edges = grid_graph(30, 30)   # 900 stations, square: band width about 31
    b = ordering.band_width_of(np.arange(900), edges)
    tree, _, pred = ordering.choose_solver(pos, np.ones(900, bool), edges, b)
    assert pred["band"] <= ordering.TREE_FIXED_SECONDS
    assert tree is None and calls == [] and "tree" not in pred
    whole, _, _ = real(pos, np.ones(900, bool), edges, partition.LEAF_STATIONS)
    full = ordering.predict_solver(900, b, whole)   # (what the comparison would have been)
    assert full["tree"] >= full["band"] == pred["band"]
    tree, _, _ = ordering.choose_solver(pos, np.ones(900, bool), edges, b, solver="tree")
    assert calls == [900] and tree is not None


def test_large_strip_block_keeps_the_band_without_partitioning_it(monkeypatch):
    """``choose_solver`` on a block above ``SCREEN_STATIONS``: a long strip block is settled
    by the tree of a window of the band order (the whole block is never partitioned, and
    the choice is the one the whole tree gives); a square block goes on to its tree."""
    import sapgo.ordering as ordering

    monkeypatch.setattr(ordering, "SCREEN_STATIONS", 1000)
    monkeypatch.setattr(ordering, "WINDOW_STATIONS", 600)
    monkeypatch.setattr(ordering, "MIN_WINDOW_STATIONS", 100)
    monkeypatch.setattr(ordering, "TREE_FIXED_SECONDS", 0.0)   # (the band of 4 strips: less)
    calls, _ = count_trees(monkeypatch)

    def band_order(nx, ny):   # across the strips: photo j of every strip, then j + 1
        return np.arange(nx * ny).reshape(ny, nx).T.ravel()

    def band_width(nx, ny, edges):
        perm = band_order(nx, ny)
        pos = np.empty(nx * ny, np.int64)
        pos[perm] = np.arange(nx * ny)
        return ordering.band_width_of(pos, edges)

    pos, edges = grid_graph(800, 4)           # 3 200 stations in 4 strips
    b = band_width(800, 4, edges)
    tree, _, pred = ordering.choose_solver(pos, np.ones(3200, bool), edges, b,
                                           band_perm=band_order(800, 4))
    assert tree is None and calls == [600] and pred["tree_window"] > 2 * pred["band"]
    calls.clear()
    tree_all, _, pred_all = ordering.choose_solver(pos, np.ones(3200, bool), edges, b)
    assert tree_all is None and calls == [3200]   # the whole tree agrees
    assert pred["tree_window"] <= 1.2 * pred_all["tree"]
    calls.clear()
    pos, edges = grid_graph(40, 40)           # 1 600 stations, square
    b = band_width(40, 40, edges)
    tree, _, pred = ordering.choose_solver(pos, np.ones(1600, bool), edges, b,
                                           band_perm=band_order(40, 40))
    # (the window: a fifth of the block, 320 stations)
    assert calls == [320, 1600] and tree is not None and pred["tree"] < pred["band"]
