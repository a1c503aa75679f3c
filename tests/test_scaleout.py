"""The scale-out replay (sapgo.solve.scaleout): the list scheduler against schedules worked
out by hand, the tiled graph's tasks against the tree's flops, the cost model's fit, the
grid tree against the tree `sapgo order` makes of a generated block."""

import numpy as np
import pytest

import sapgo
from sapgo.solve import scaleout as so
from sapgo.solve.partition import Tree

SLOW = so.Network(bandwidth=1.0, latency=0.5)
FREE = so.Network(bandwidth=1e30, latency=0.0)


def test_a_chain_on_one_worker_takes_the_sum():
    g = so.Graph()
    t = g.add("a", 0, 1.0)
    for s in (2.0, 3.0, 0.5):
        t = g.add("b", 0, s, [(t, 1e9)])   # (no message on one worker)
    r = so.replay(g, SLOW)
    assert r["seconds"] == pytest.approx(6.5) and r["critical_path_s"] == pytest.approx(6.5)
    assert r["messages"] == 0 and r["efficiency"] == pytest.approx(1.0)


def test_messages_wait_for_the_link_and_the_latency():
    # a (w0, 1 s) -> b (w1, 2 s) -> d (w0, 1 s); c (w0, 3 s) -> d; 1 byte at 1 byte/s, 0.5 s
    g = so.Graph()
    a = g.add("a", 0, 1.0)
    b = g.add("b", 1, 2.0, [(a, 1.0)])
    c = g.add("c", 0, 3.0, [(a, 0.0)])
    g.add("d", 0, 1.0, [(b, 1.0), (c, 0.0)])
    r = so.replay(g, SLOW)
    # a 0-1; a's output leaves 1-2, arrives 2.5; b 2.5-4.5; c 1-4; b's leaves 4.5-5.5,
    # arrives 6; d 6-7
    assert r["seconds"] == pytest.approx(7.0)
    assert r["critical_path_s"] == pytest.approx(7.0)
    assert r["critical_path"] == pytest.approx({"a": 1.0, "b": 2.0, "d": 1.0,
                                                "messages": 3.0})
    assert r["messages"] == 2 and r["bytes"] == 2.0
    assert r["work_s"] == 7.0 and r["efficiency"] == pytest.approx(7.0 / 14.0)


def test_the_longest_path_goes_first_and_an_output_travels_once():
    g = so.Graph()
    a = g.add("a", 0, 1.0)
    short = g.add("short", 1, 1.0, [(a, 2.0)])
    long_ = g.add("long", 1, 1.0, [(a, 2.0)])   # (the same output to the same worker)
    g.add("tail", 1, 5.0, [(long_, 0.0)])
    r = so.replay(g, SLOW)
    # a 0-1, its output 1-3 + 0.5: both at 3.5; long first (its tail), tail 4.5-9.5, short
    assert r["messages"] == 1
    assert r["seconds"] == pytest.approx(10.5)
    assert r["busiest_s"] == pytest.approx(7.0)


def test_a_graph_that_cannot_finish_says_so():
    g = so.Graph()
    g.add("a", 0, 1.0)
    with pytest.raises(AssertionError):
        g.add("b", 0, 1.0, [(5, 0.0)])


def _chain_tree():
    """Two leaves of 4 stations under a separator of 3 (own 3, boundary none), a leaf's
    boundary the separator's 3 stations."""
    return Tree(lo=np.array([0, 4, 8]), hi=np.array([4, 8, 11]), first=np.array([0, 1, 0]),
                parent=np.array([2, 2, -1]), leaf=np.array([True, True, False]),
                bptr=np.array([0, 3, 6, 6]), boundary=np.array([8, 9, 10, 8, 9, 10]),
                n_active=11, pt_start=np.array([0, 40, 80, 90]))


@pytest.mark.parametrize("tile", [5, 7, 12, 1000])
def test_the_tiles_of_a_front_do_its_flops(tile):
    """With every kernel at one flop a second, the tile tasks of each top front take the
    front's flops (m^3/3 + m^2 f + m f^2) to rounding, however the tiles cut it."""
    tree = _chain_tree()
    k = 6
    zero = np.zeros(tree.n_nodes)
    ones = {x: 1.0 for x in ("potrf", "trsm", "syrk", "gemm")}
    g = so.tiled_graph(tree, k, 2, zero, zero, zero, zero, ones, tile=tile,
                       plan=([[(0, 1)], [(1, 2)]], [2]))
    fl = so.node_figures(tree, k)["flops"]
    tiles = sum(s for kind, s in zip(g.kind, g.seconds)
                if kind in ("potrf", "trsm", "syrk", "gemm"))
    if tile < 18:   # (the separator's front: 18 unknowns)
        assert tiles == pytest.approx(fl[2], rel=1e-12)
    else:
        assert tiles == 0.0 and "top" in g.kind
    r = so.replay(g, FREE)
    assert r["tasks"] == len(g) and r["seconds"] > 0


def test_the_tiled_graph_splits_the_work_and_sends_the_updates():
    tree = _chain_tree()
    k = 6
    fig = so.node_figures(tree, k)
    step = fig["flops"] / 1e9
    g = so.tiled_graph(tree, k, 2, step, 0 * step, 0 * step, 0 * step,
                       {x: 1e9 for x in ("potrf", "trsm", "syrk", "gemm")}, tile=6,
                       plan=([[(0, 1)], [(1, 2)]], [2]))
    r = so.replay(g, FREE)
    # both leaves at once, then the separator's tiles on both workers
    assert set(g.worker) == {0, 1}
    assert r["seconds"] < r["work_s"]
    slow = so.replay(g, so.Network(bandwidth=1e3, latency=0.0))
    # each leaf's update (18 x 18, lower triangle) reaches the separator's tiles
    assert slow["bytes"] >= 8 * 18 * 19 / 2
    assert slow["seconds"] > r["seconds"]


def test_the_cost_model_recovers_its_parameters():
    rng = np.random.default_rng(2)
    n = 40
    fig = {"flops": rng.uniform(1e6, 1e9, n), "points": rng.integers(10, 1000, n) * 1.0,
           "factor_bytes": rng.uniform(1e4, 1e7, n), "m": np.ones(n), "f": np.ones(n)}
    true = so.CostModel(rate=2e9, elim_fixed=1e-4, build_fixed=2e-4, build_point=3e-6,
                        back_rate=4e9, update_point=5e-6)
    el = true.elim_fixed + fig["flops"] / true.rate
    total = el + true.build(fig)
    m = so.CostModel.fit(fig, np.arange(n), (total, el), true.back(fig).sum(),
                         true.update(fig).sum())
    for name in ("rate", "elim_fixed", "build_fixed", "build_point", "back_rate",
                 "update_point"):
        assert getattr(m, name) == pytest.approx(getattr(true, name), rel=1e-6), name
    assert m.step(fig) == pytest.approx(total)


def test_kernel_rates_are_measured():
    r = so.kernel_rates(64, repeat=1)
    assert set(r) == {"potrf", "trsm", "syrk", "gemm"} and all(v > 1e6 for v in r.values())


def test_built_graph_on_one_worker_is_the_sum_of_its_tasks():
    tree = _chain_tree()
    plan = ([[(0, 1)], [(1, 2)]], [2])
    step = np.array([1.0, 2.0, 3.0])
    b = {kind: [(10.0, 20.0), (10.0, 20.0)] for kind in ("step", "back", "update")}
    over = {"task": [0.1, 0.2], "step": 0.3, "back": 0.4, "update": 0.5, "client": 0.6}
    g = so.built_graph(tree, plan, step, [0.7, 0.8], [0.9, 1.0], 1.1, 1.2, over, b, 1)
    one = so.replay(g, FREE)
    assert one["seconds"] == pytest.approx(g.work())
    two = so.replay(so.built_graph(tree, plan, step, [0.7, 0.8], [0.9, 1.0], 1.1, 1.2, over,
                                   b, 2), FREE)
    # the parts side by side: the shorter of each round hidden
    assert two["seconds"] == pytest.approx(g.work() - (0.1 + 1.0) - 0.7 - 0.9)


def test_built_graph_tiles_a_large_top_front_across_the_workers():
    """The top on the workers as built: the separator's front (18 rows) beyond a tile of
    6 rows is built and factored tile by tile on both workers (its flops at the kernels'
    rate, its build as given); on one worker the iteration is the sum of its tasks."""
    tree = _chain_tree()
    k = 6
    plan = ([[(0, 1)], [(1, 2)]], [2])
    step = np.array([1.0, 2.0, 3.0])
    build = np.array([0.0, 0.0, 0.5])
    b = {kind: [(10.0, 20.0), (10.0, 20.0)] for kind in ("step", "back", "update")}
    over = {"task": [0.1, 0.2], "step": 0.3, "back": 0.4, "update": 0.5, "client": 0.6}
    rates = {x: 1e3 for x in ("potrf", "trsm", "syrk", "gemm")}
    graphs = {w: so.built_graph(tree, plan, step, [0.7, 0.8], [0.9, 1.0], 1.1, 1.2, over, b,
                                w, k, build, rates, tile=6) for w in (1, 2)}
    g = graphs[2]
    tiles = [(kd, w) for kd, w in zip(g.kind, g.worker) if kd in ("potrf", "syrk", "gemm")]
    assert {w for _, w in tiles} == {0, 1} and "top" in g.kind
    fl = so.node_figures(tree, k)["flops"][2]
    assert sum(s for kd, s in zip(g.kind, g.seconds)
               if kd in ("potrf", "trsm", "syrk", "gemm")) == pytest.approx(fl / 1e3)
    assert sum(s for kd, s in zip(g.kind, g.seconds) if kd == "build") == pytest.approx(0.5)
    one = so.replay(graphs[1], FREE)
    assert one["seconds"] == pytest.approx(graphs[1].work())
    assert so.replay(g, FREE)["seconds"] < one["seconds"]


def test_the_grid_tree_is_the_tree_of_the_generated_block(tmp_path):
    path = tmp_path / "g.h5"
    sapgo.generate_block(path, strips=24, photos_per_strip=24, control_points=8,
                         progress=False)
    offsets, spacing = so.stencil(path)
    assert (0, 1) in offsets and (1, 0) in offsets
    sapgo.order_project(path, solver="tree")
    from sapgo.project import Project

    with Project(path, "r") as p:
        real = p.tree().figures()
    grid = so.grid_tree(24, 24, offsets, spacing).figures()
    assert grid["flops"] == pytest.approx(real["flops"], rel=0.05)
    assert grid["largest_front"] == pytest.approx(real["largest_front"], rel=0.1)
