"""The partition tree on Dask distributed (a LocalCluster of 2 worker processes): the
subtrees built and factored on the workers give the threaded run's solution, sigma0,
precision and observation quality (Gauss-Newton, Levenberg-Marquardt, self-calibration,
strips); the updates of tiled fronts travel as their scratch files; the command line."""

import dataclasses
import os
import pickle
import shutil

import numpy as np
import pytest

import sapgo
from conftest import assert_one_line_error, run_cli
from test_adjust import TIGHT
from test_tree_adjust import (  # noqa: F401
    assert_resumed_solution, assert_same_solution, miscalibrated_square, ordered_pair)

distributed = pytest.importorskip("distributed")

from sapgo.solve.distributed import cluster  # noqa: E402


@pytest.fixture(scope="module")
def client():
    with cluster(workers=2, quiet=True) as c:
        yield c


@pytest.fixture(scope="module")
def blocks(tmp_path_factory):
    d = tmp_path_factory.mktemp("dist")
    out = {}
    for name, spec in {"square": dict(strips=6, photos_per_strip=7, control_points=8),
                       "strips": dict(strips=3, photos_per_strip=16, control_points=8)}.items():
        out[name] = d / f"{name}.h5"
        sapgo.generate_block(out[name], seed=4, progress=False, **spec)
    return out


def _both(src, tmp_path, opts, client, leaf=4):
    """The threaded and the distributed adjustment of copies of ``src`` ordered for a tree
    of small leaves; the distributed run's tasks as (name, worker, whether its inputs
    travelled to it)."""
    _, ref = ordered_pair(src, tmp_path, leaf=leaf, name="ref")
    path = tmp_path / "dist.h5"
    shutil.copy(ref, path)
    sr = sapgo.adjust(ref, opts)
    with distributed.get_task_stream(client) as ts:
        sd = sapgo.adjust(path, dataclasses.replace(opts, client=client))
    tasks = {(d["key"].split("-")[0], d["worker"],
              any(x["action"] == "transfer" for x in d["startstops"])) for d in ts.data}
    return ref, path, sr, sd, tasks


@pytest.mark.parametrize("case", ["square", "square-lm", "strips", "calibration",
                                  "square-lm-tiled", "calibration-tiled"])
def test_two_workers_give_the_threaded_solution(case, blocks, miscalibrated_square,  # noqa: F811
                                                tmp_path, client, monkeypatch):
    """The parts on the workers and the top's fronts too: each in one task, or (``tiled``:
    tiles of two stations) built by column panels and factored tile by tile across both
    workers, the children's updates taken piece by piece where they are."""
    from sapgo.solve import distributed as dist

    tiled = case.endswith("-tiled")
    if tiled:
        monkeypatch.setattr(dist, "TOP_TILE", 12)
        case = case[:-len("-tiled")]
    opts = dataclasses.replace(TIGHT, progress=False)
    if case == "square-lm":
        opts = dataclasses.replace(opts, method="levenberg-marquardt")
    if case == "calibration":
        src = miscalibrated_square
        opts = dataclasses.replace(opts, calibrate=("f", "x0", "y0", "k1", "k2", "p1", "p2"))
    else:
        src = blocks[case.split("-")[0]]
    ref, path, sr, sd, tasks = _both(src, tmp_path, opts, client)
    # both workers built, factored, back-substituted, updated and inverted a part of the
    # tree
    tops = ("top_panel", "_t_potrf", "_t_trsm", "_t_update", "_t_add") if tiled else ()
    for step in ("part_step", "part_solve", "part_update", "part_quality",
                 "part_report") + tops:
        assert {w for name, w, _ in tasks if name == step} == set(client.nthreads()), step
    assert any(name == "top_node" for name, _, _ in tasks) != tiled   # (small top fronts)
    # a piece of an update is cut where the update is: nothing moves to the cutting task
    assert any(name == "_t_take" for name, _, _ in tasks)
    assert not any(moved for name, _, moved in tasks if name == "_t_take")
    assert sd.solver == "tree" and sd.converged and sd.iterations == sr.iterations
    assert sd.sigma0 == pytest.approx(sr.sigma0, rel=1e-10)
    assert_same_solution(path, ref, rtol=1e-10)
    # the report's sums over the points and observations, the workers' parts merged
    for key in ("check_points", "control_points", "reliability", "strip_comparison",
                "truth", "precision", "excluded_points", "n_excluded_points"):
        assert_same_report(getattr(sd, key), getattr(sr, key), key)
    # the high correlations found on the workers: the threaded run's (to rounding)
    cd, cr = sd.correlations, sr.correlations
    assert cd["counts"] == cr["counts"]
    assert [(e.get("point_id", e.get("photo_id")), e["pair"]) for e in cd["largest"]] == \
        [(e.get("point_id", e.get("photo_id")), e["pair"]) for e in cr["largest"]]
    np.testing.assert_allclose([e["rho"] for e in cd["largest"]],
                               [e["rho"] for e in cr["largest"]], rtol=1e-9)
    if case == "calibration":
        # (the border's S = C - W'W loses digits to cancellation; the workers' parts, and
        # tiles of two stations, sum W'W in another order than the threads: 1e-10 of the
        # solution is 1e-9 of its sigmas; 1.9e-10 measured untiled on an AVX-512 machine)
        for a, b in zip(sd.calibration, sr.calibration):
            assert a["sigma"] == pytest.approx(b["sigma"], rel=1e-9)


def test_camera_models_per_photo_calibration_and_fixes_on_two_workers(blocks, tmp_path,
                                                                       client):
    """A backward camera with affinity, self-calibrated with its radial distortion per
    photo, two photos' parameters fixed: the workers reach the threaded solution. (Not the
    principal point per photo: in a vertical block it is all but the photo's tilt, and the
    precision of so ill-conditioned a border differs in its third digit with the order of
    the border's sums.)"""
    from conftest import read_records, rewrite

    rec = read_records(blocks["square"])
    rec["cameras"][["k1", "p1", "b1", "b2", "distortion_model"]] = (1e-8, 2e-7, 1e-4, -5e-5,
                                                                    1)
    src = tmp_path / "src.h5"
    rewrite(src, rec)
    ids = np.sort(rec["stations"]["id"])
    opts = dataclasses.replace(TIGHT, progress=False, calibrate=("f", "x0", "y0", "b1", "b2"),
                               calibrate_per_photo=("k1",),
                               fix=(f"fix:{ids[0]}:all", f"fix:{ids[-1]}:Z"))
    ref, path, sr, sd, _ = _both(src, tmp_path, opts, client)
    assert sd.converged and sd.datum == "fixed" and sd.iterations == sr.iterations
    assert sd.sigma0 == pytest.approx(sr.sigma0, rel=1e-10)
    assert_same_solution(path, ref, rtol=1e-9)
    assert len(sd.calibration) == 5 + len(ids)
    for a, b in zip(sd.calibration, sr.calibration):
        assert a["adjusted"] == pytest.approx(b["adjusted"], rel=1e-9, abs=1e-15)


def assert_same_report(a, b, where, rel=1e-9):
    """Two reports' parts (dicts, lists, numbers) equal, numbers to ``rel``."""
    if isinstance(b, dict):
        assert isinstance(a, dict) and set(a) == set(b), where
        for k in b:
            assert_same_report(a[k], b[k], f"{where}.{k}", rel)
    elif isinstance(b, (list, tuple)):
        assert len(a) == len(b), where
        for j, (x, y) in enumerate(zip(a, b)):
            assert_same_report(x, y, f"{where}[{j}]", rel)
    elif isinstance(b, float):
        assert a == pytest.approx(b, rel=rel, abs=1e-12), where
    else:
        assert a == b, where


def test_a_tiled_update_travels_as_its_scratch_file(tmp_path):
    """A subtree root's update larger than a panel stays in its scratch file in the shared
    work directory: pickled, it is the file's place; unpickled, the receiver reads the
    same panels and its close removes the file."""
    from sapgo.solve.tiles import Panels

    rng = np.random.default_rng(1)
    n, bounds = 10, [0, 4, 7, 10]
    u = Panels(tmp_path, n, bounds)
    full = rng.normal(size=(n, n))
    for j in range(3):
        u.write(j, np.asfortranarray(full[bounds[j]:, bounds[j]:bounds[j + 1]]))
    blob = pickle.dumps(u)
    assert len(blob) < 2000   # (not the data)
    v = pickle.loads(blob)
    for j in range(3):
        np.testing.assert_array_equal(v.panel(j), full[bounds[j]:, bounds[j]:bounds[j + 1]])
    np.testing.assert_array_equal(v.cols(2, 8), u.cols(2, 8))
    v.close()
    assert not os.path.exists(u.path)
    u.close()


def test_the_trace_holds_every_node_and_task(blocks, tmp_path, client, monkeypatch):
    """With the trace on (the scale-out replay's input), every node's seconds once an
    iteration wherever it ran, three rounds of one task a part an iteration with their
    seconds and bytes, the client's share; the replay of the iteration as built runs."""
    from sapgo.solve import distributed as dist
    from sapgo.solve import scaleout

    monkeypatch.setitem(dist.TRACE, "on", True)
    monkeypatch.setitem(dist.TRACE, "nodes", {})
    monkeypatch.setitem(dist.TRACE, "rounds", [])
    monkeypatch.setitem(dist.TRACE, "client", {})
    _, ref = ordered_pair(blocks["square"], tmp_path, leaf=4, name="ref")
    s = sapgo.adjust(ref, dataclasses.replace(TIGHT, progress=False, client=client))
    from sapgo.project import Project

    with Project(ref, "r") as p:
        tree = p.tree()
    per, top = dist.TRACE["plan"]
    assert sorted(dist.TRACE["nodes"]) == list(range(tree.n_nodes))
    its = {len(v) for v in dist.TRACE["nodes"].values()}
    assert its == {s.iterations}
    kinds = [r["kind"] for r in dist.TRACE["rounds"]]
    assert kinds == ["step", "back", "update"] * s.iterations + ["quality", "report"]
    for r in dist.TRACE["rounds"]:
        assert [t["part"] for t in r["tasks"]] == list(range(len(per)))
        assert all(t["seconds"] > 0 and t["bytes_in"] > 0 and t["bytes_out"] > 0
                   for t in r["tasks"])
        assert r["wall_s"] >= max(t["seconds"] for t in r["tasks"])
    assert dist.TRACE["client"]["back"] > 0 and dist.TRACE["client"]["update"] > 0
    for total, elim in (x for v in dist.TRACE["nodes"].values() for x in v):
        assert total >= elim > 0
    step = [float(np.median([x[0] for x in dist.TRACE["nodes"][i]]))
            for i in range(tree.n_nodes)]
    zero = {"step": 0.0, "back": 0.0, "update": 0.0, "client": 0.0, "task": [0.0] * len(per)}
    b = {kd: [(1.0, 1.0)] * len(per) for kd in ("step", "back", "update")}
    g = scaleout.built_graph(tree, ([[tuple(x) for x in r] for r in per], top), step,
                             [0.0] * len(per), [0.0] * len(per), 0.0, 0.0, zero, b, 2)
    r = scaleout.replay(g, scaleout.Network())
    assert r["work_s"] == pytest.approx(sum(step))
    assert r["seconds"] < r["work_s"]


def _report_progress(key):
    from sapgo.solve.distributed import _Progress

    bar = _Progress(key)
    bar.update(5)
    bar.update(7)
    bar.flush()
    return 12


class _Bar:
    def __init__(self):
        self.n = 0

    def update(self, n):
        self.n += n


def test_the_workers_progress_reaches_the_client(client):
    """Points done on a worker go to the client's bar as Dask events, once; what has not
    arrived when the round ends is counted then."""
    import time

    from sapgo.solve.distributed import _Forwarded

    bar = _Bar()
    with _Forwarded(client, bar) as fw:
        assert client.submit(_report_progress, fw.key, pure=False).result() == 12
        t0 = time.monotonic()
        while bar.n < 12 and time.monotonic() - t0 < 10:
            time.sleep(0.05)
    assert bar.n == 12   # (through the event)
    fw.finish(20)
    assert bar.n == 20
    other = _Bar()   # another round's events are not counted
    with _Forwarded(client, other) as fw2:
        client.submit(_report_progress, "not-this-round", pure=False).result()
        time.sleep(0.5)
    fw2.finish(3)
    assert other.n == 3


def test_the_bars_count_every_point_once(blocks, tmp_path, client, monkeypatch):
    import contextlib
    import importlib

    adj = importlib.import_module("sapgo.adjust")   # (sapgo.adjust is also the function)
    bars = []

    @contextlib.contextmanager
    def counting(enabled, total, desc):
        bars.append((desc, total, _Bar()))
        yield bars[-1][2]

    monkeypatch.setattr(adj, "_progress", counting)
    _, ref = ordered_pair(blocks["square"], tmp_path, leaf=4, name="ref")
    s = sapgo.adjust(ref, dataclasses.replace(TIGHT, progress=True, client=client))
    assert {d for d, _, _ in bars} == {"build", "update"}
    assert sum(1 for d, _, _ in bars if d == "build") == s.iterations
    for desc, total, bar in bars:
        assert bar.n == total, desc


def test_a_front_tiled_across_the_workers_is_the_dense_partial_cholesky(client):
    """The building block of the top fronts tiled across workers: a front's partial
    Cholesky as Dask tasks over its tiles (own rows and boundary rows cut apart), against
    scipy's dense factor and Schur complement; the tasks spread over both workers, as many
    of each kind as the scale-out replay counts."""
    import scipy.linalg

    from sapgo.solve.distributed import tile_cuts, tiled_cholesky_dense

    rng = np.random.default_rng(5)
    n, m, tile = 300, 170, 64
    g = rng.standard_normal((n, n))
    a = g @ g.T + n * np.eye(n)
    with distributed.get_task_stream(client) as ts:
        low, s = tiled_cholesky_dense(client, a, m, tile)
    l11 = scipy.linalg.cholesky(a[:m, :m], lower=True)
    l21 = scipy.linalg.solve_triangular(l11, a[m:, :m].T, lower=True).T
    np.testing.assert_allclose(low[:m], l11, rtol=1e-12, atol=1e-12 * n)
    np.testing.assert_allclose(low[m:], l21, rtol=1e-12, atol=1e-12 * n)
    np.testing.assert_allclose(s, np.tril(a[m:, m:] - l21 @ l21.T), rtol=1e-12,
                               atol=1e-10 * n)
    cuts = tile_cuts(m, n, tile)
    nt, mt = len(cuts), sum(1 for c0, _ in cuts if c0 < m)
    kinds = [d["key"].split("-")[0] for d in ts.data]
    assert kinds.count("_t_potrf") == mt
    assert kinds.count("_t_trsm") == sum(nt - k - 1 for k in range(mt))
    assert kinds.count("_t_update") == sum(nt - j for k in range(mt)
                                           for j in range(k + 1, nt))
    assert len({d["worker"] for d in ts.data}) == 2


def test_childrens_updates_reach_the_tiles_they_land_on(client):
    """Two children's Schur updates added into a front's tiles piece by piece (each piece
    cut where the update is), then the tiled factorisation: the dense extend-add and
    scipy's partial factor and Schur complement."""
    import scipy.linalg

    from sapgo.solve.distributed import extend_add_tiles, tile_cuts, tiled_cholesky

    rng = np.random.default_rng(6)
    n, m, tile = 260, 150, 48
    g = rng.standard_normal((n, n))
    own = g @ g.T + n * np.eye(n)
    dense = own.copy()
    updates = []
    for size in (90, 120):
        places = np.sort(rng.choice(n, size, replace=False))
        h = rng.standard_normal((size, size))
        u = h @ h.T
        dense[np.ix_(places, places)] += u
        updates.append((client.scatter(u), places))
    cuts = tile_cuts(m, n, tile)
    mt = sum(1 for c0, _ in cuts if c0 < m)
    tiles = {(i, j): own[cuts[i][0]:cuts[i][1], cuts[j][0]:cuts[j][1]].copy()
             for i in range(len(cuts)) for j in range(i + 1)}
    assembled = client.gather(extend_add_tiles(client, tiles, cuts, updates))
    for (i, j), t in assembled.items():   # (a diagonal tile's upper triangle: not used)
        want = dense[cuts[i][0]:cuts[i][1], cuts[j][0]:cuts[j][1]]
        if i == j:
            t, want = np.tril(t), np.tril(want)
        np.testing.assert_allclose(t, want, rtol=1e-13, atol=1e-12, err_msg=str((i, j)))
    fac = client.gather(tiled_cholesky(client, extend_add_tiles(client, tiles, cuts, updates),
                                       cuts, mt))
    l11 = scipy.linalg.cholesky(dense[:m, :m], lower=True)
    l21 = scipy.linalg.solve_triangular(l11, dense[m:, :m].T, lower=True).T
    s = dense[m:, m:] - l21 @ l21.T
    for (i, j), t in fac.items():
        (r0, r1), (c0, c1) = cuts[i], cuts[j]
        want = (np.vstack([l11, l21])[r0:r1, c0:c1] if j < mt else
                s[r0 - m:r1 - m, c0 - m:c1 - m])
        got = np.tril(t) if i == j else t
        want = np.tril(want) if i == j else want
        np.testing.assert_allclose(got, want, rtol=1e-11, atol=1e-10, err_msg=str((i, j)))


def test_a_tile_piece_is_where_the_block_lands():
    from sapgo.solve.distributed import tile_cuts, tile_pieces

    cuts = tile_cuts(5, 12, 3)   # own 0-3, 3-5; boundary 5-8, 8-11, 11-12
    assert cuts == [(0, 3), (3, 5), (5, 8), (8, 11), (11, 12)]
    # as few tiles as needed, of equal size in whole stations: no sliver of a tile
    assert tile_cuts(2106, 5000, 2048, 6) == [(0, 1056), (1056, 2106), (2106, 3558),
                                              (3558, 5000)]
    assert tile_cuts(12, 12, 5, 6) == [(0, 6), (6, 12)]
    places = np.array([1, 4, 6, 7, 11])
    p = tile_pieces(places, places, cuts)
    assert set(p) == {(a, b) for a in (0, 1, 2, 4) for b in (0, 1, 2, 4) if b <= a}
    r, c = p[(2, 1)]
    assert list(places[r]) == [6, 7] and list(places[c]) == [4]
    # every element of the lower triangle lands once
    hits = np.zeros((5, 5), int)
    for r, c in p.values():
        hits[np.ix_(r, c)] += 1
    assert (np.tril(hits) == np.tril(np.ones((5, 5), int))).all()


def test_a_tiled_front_names_its_failing_pivot(client):
    from sapgo.solve.distributed import tiled_cholesky_dense

    a = np.eye(200)
    a[130, 130] = -1.0
    with pytest.raises(ValueError, match="non-positive pivot at row 130"):
        tiled_cholesky_dense(client, a, 150, 64)


def test_parts_with_tiled_fronts_hand_their_updates_to_the_top(blocks, tmp_path, client,
                                                               monkeypatch):
    """The parts' fronts tiled for a small memory budget (panels of 2 stations): a subtree
    root's update larger than a panel stays in its scratch file on the worker, the top's
    tasks cut their pieces from it; the client substitutes back through and inverts the top
    from the records the workers wrote. The threaded solution and precision."""
    import sapgo.solve.tree as tree_mod
    from sapgo.solve import distributed as dist
    from test_tree import SMALL_TILES

    plan = tree_mod.work_plan
    plans = []

    def small(*a, **kw):
        plans.append(plan(*a, **kw)[:3] + (SMALL_TILES,))
        return plans[-1]

    monkeypatch.setattr(tree_mod, "work_plan", small)
    monkeypatch.setattr(dist, "TOP_TILE", 24)
    opts = dataclasses.replace(TIGHT, progress=False, chunk_points=40)
    ref, path, sr, sd, tasks = _both(blocks["square"], tmp_path, opts, client)
    per, top, _, tile = plans[-1]
    from sapgo.project import Project

    with Project(path, "r") as p:
        tree = p.tree()
    # a part's subtree root with an update larger than a panel: a scratch file
    roots = [b - 1 for r in per for _, b in r]
    assert any(8 * (6 * len(tree.bnd(i))) ** 2 > tile[1] for i in roots)
    assert sd.converged and sd.iterations == sr.iterations
    assert sd.sigma0 == pytest.approx(sr.sigma0, rel=1e-10)
    assert_same_solution(path, ref, rtol=1e-10)
    assert not list(tmp_path.glob("*.work"))   # (the scratch files went with the run's)


@pytest.mark.parametrize("tile", [None, 12])
def test_a_datum_defect_in_the_top_names_the_threaded_runs_station(blocks, tmp_path, client,
                                                                   monkeypatch, tile):
    """Three control points on a line leave a rotation free: the pivot that fails on the
    workers (in a top front's task, or in one of its tiles) names the station the threaded
    run names."""
    from conftest import collinear_control
    from sapgo.errors import DatumDefectError
    from sapgo.solve import distributed as dist

    if tile:
        monkeypatch.setattr(dist, "TOP_TILE", tile)
    _, ref = ordered_pair(blocks["square"], tmp_path, leaf=4, name="ref")
    collinear_control(ref)
    path = tmp_path / "d.h5"
    shutil.copy(ref, path)
    opts = dataclasses.replace(TIGHT, progress=False)
    with pytest.raises(DatumDefectError) as want:
        sapgo.adjust(ref, opts)
    with pytest.raises(DatumDefectError) as got:
        sapgo.adjust(path, dataclasses.replace(opts, client=client))
    assert str(got.value) == str(want.value).replace(str(ref), str(path))


def test_workers_from_the_command_line(blocks, tmp_path, capsys):
    path = tmp_path / "c.h5"
    shutil.copy(blocks["square"], path)
    code, _, err = run_cli(capsys, "adjust", path, "--workers", "2", "--no-progress")
    assert code == 0, err
    assert "Dask cluster of 2 workers; dashboard http" in err
    ref = tmp_path / "r.h5"
    shutil.copy(blocks["square"], ref)
    code, _, err = run_cli(capsys, "adjust", ref, "--solver", "tree", "--no-progress")
    assert code == 0, err
    assert_same_solution(path, ref, rtol=1e-10)


@pytest.mark.parametrize("args,message", [
    (["--workers", "0"], "--workers 0: give 1 or more worker processes"),
    (["--workers", "2", "--solver", "band"], "not with --solver band"),
    (["--scheduler", "tcp://127.0.0.1:1"], "cannot reach the Dask scheduler at tcp://127.0.0.1:1"),
])
def test_bad_cluster_options_are_one_line_errors(blocks, tmp_path, capsys, monkeypatch, args,
                                                 message):
    monkeypatch.setattr("sapgo.solve.distributed.CONNECT_TIMEOUT", 2)
    path = tmp_path / "e.h5"
    shutil.copy(blocks["square"], path)
    before = path.read_bytes()
    code, _, err = run_cli(capsys, "adjust", path, "--no-progress", *args)
    assert_one_line_error(code, err, message)
    assert path.read_bytes() == before


def test_a_killed_worker_gives_the_same_result(blocks, tmp_path):
    """One worker killed (SIGKILL) in the middle of building its part in the second
    iteration: Dask runs the part again (the restarted or the other worker), it writes the
    same records at the same offsets, and the run ends with the threaded run's solution."""
    from sapgo.solve.distributed import worker_addresses
    from sapgo.work import FAULT_ENV

    opts = dataclasses.replace(TIGHT, progress=False, chunk_points=40)
    _, ref = ordered_pair(blocks["square"], tmp_path, leaf=4, name="ref")
    path = tmp_path / "killed.h5"
    shutil.copy(ref, path)
    sr = sapgo.adjust(ref, opts)
    with cluster(workers=2, quiet=True) as c:
        first = worker_addresses(c)[0]
        c.run(lambda: os.environ.__setitem__(FAULT_ENV, "build:2"), workers=[first])
        sd = sapgo.adjust(path, dataclasses.replace(opts, client=c))
        assert first not in worker_addresses(c)   # it died (its nanny started another)
    assert sd.converged and sd.iterations == sr.iterations
    assert sd.sigma0 == pytest.approx(sr.sigma0, rel=1e-12)
    assert_same_solution(path, ref, rtol=1e-12)


def test_a_killed_client_resumes_to_the_same_result(blocks, tmp_path):
    """``sapgo adjust --workers 2`` killed (SIGKILL) after the second iteration's solve:
    ``--resume --workers 2`` continues from the checkpoint to the uninterrupted run's
    solution, and the killed run's workers do not outlive it."""
    import subprocess
    import sys
    import time

    from sapgo.work import FAULT_ENV

    _, ref = ordered_pair(blocks["square"], tmp_path, leaf=4, name="ref")
    path = tmp_path / "k.h5"
    shutil.copy(ref, path)
    sapgo.adjust(ref, sapgo.Options(progress=False))
    cmd = [sys.executable, "-m", "sapgo.cli", "adjust", str(path), "--no-progress",
           "--workers", "2"]
    before = set(_python_children())
    r = subprocess.run(cmd, env=dict(os.environ, **{FAULT_ENV: "solve:2"}),
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == -9, r.stderr
    r = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert_resumed_solution(path, ref)
    # no worker process of the killed run left behind (orphans: new, and their parent gone)
    deadline = time.time() + 30
    while time.time() < deadline and _orphans(before):
        time.sleep(0.5)
    assert not _orphans(before)


def _python_children():
    """``{pid: (ppid, args)}`` of the machine's processes."""
    import subprocess

    out = subprocess.run(["ps", "-eo", "pid=,ppid=,args="], capture_output=True,
                         text=True).stdout
    procs = {}
    for ln in out.splitlines():
        pid, ppid, args = ln.strip().split(None, 2) + [""] * (3 - len(ln.split(None, 2)))
        procs[int(pid)] = (int(ppid), args)
    return procs


def _orphans(before):
    return [pid for pid, (ppid, args) in _python_children().items()
            if pid not in before and ppid == 1 and "multiprocessing" in args]


def test_a_tls_cluster_works_unchanged(blocks, tmp_path):
    """A cluster with TLS and mutual authentication (Dask's own security settings, here
    temporary certificates): the same solution as the threaded run."""
    from distributed import Client, LocalCluster
    from distributed.security import Security

    pytest.importorskip("cryptography")
    opts = dataclasses.replace(TIGHT, progress=False)
    _, ref = ordered_pair(blocks["square"], tmp_path, leaf=4, name="ref")
    path = tmp_path / "tls.h5"
    shutil.copy(ref, path)
    sr = sapgo.adjust(ref, opts)
    sec = Security.temporary()
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, protocol="tls",
                      security=sec, dashboard_address=None) as lc, \
            Client(lc, security=sec) as c:
        assert c.scheduler.address.startswith("tls://")
        sd = sapgo.adjust(path, dataclasses.replace(opts, client=c))
    assert sd.sigma0 == pytest.approx(sr.sigma0, rel=1e-12)
    assert_same_solution(path, ref, rtol=1e-12)


def test_a_free_network_on_two_workers(blocks, tmp_path, client):
    """A free network (inner constraints, sapgo.freenet): the workers' factor gives the
    threaded run's solution and precision."""
    import h5py

    from conftest import read_records, rewrite

    rec = read_records(blocks["square"])
    rec["points"]["kind"] = 0
    src = tmp_path / "free.h5"
    rewrite(src, rec)
    with h5py.File(src, "r+") as f:
        f.attrs["datum"] = "free"
    opts = dataclasses.replace(TIGHT, progress=False, tol_cost=1e-14, max_iterations=60)
    ref, path, sr, sd, _ = _both(src, tmp_path, opts, client)
    assert sd.converged and sd.datum == "free" and sd.precision is not None
    assert sd.sigma0 == pytest.approx(sr.sigma0, rel=1e-10)
    from test_tree_adjust import by_id

    a, b = by_id(path), by_id(ref)
    for k in ("station_corr", "point_corr", "residuals", "station_sigma", "point_sigma"):
        np.testing.assert_allclose(a[k], b[k], rtol=1e-8, atol=1e-8 * np.abs(b[k]).max(),
                                   err_msg=k)
    # the redundancy numbers (their normalised residuals divide by sqrt(r), which is all
    # but 0 for some rays of a block of pass points only: those are not compared)
    np.testing.assert_allclose(a["obs_quality"][:, :3], b["obs_quality"][:, :3], rtol=0,
                               atol=2e-6)
