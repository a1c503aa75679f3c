"""The tree solver inside the adjustment: the same solution, sigma0, precision and
observation quality as the band solver (and the dense reference), with Levenberg-Marquardt,
9-parameter stations, snooping, robust estimation, a forest and kill-and-resume."""

import dataclasses
import json
import os
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest

import sapgo
from conftest import assert_one_line_error, read_records, rewrite, run_cli
from sapgo.work import work_path
from sapgo.project import Project
from test_adjust import TIGHT, adjusted_by_id, dense_reference

SOLUTION = ("station_corr", "point_corr", "residuals", "station_sigma", "point_sigma",
            "obs_quality")


def by_id(path):
    """The solution arrays in id order (stations, points, observations by their ids)."""
    with Project(path) as p:
        st_ids = p.read_field("stations", "id")
        pt_ids = p.read_field("points", "id")
        ob = p.read("observations")
        out = {k: p.solution(k) for k in SOLUTION}
    so, po = np.argsort(st_ids), np.argsort(pt_ids)
    oo = np.lexsort((st_ids[ob["station"]], pt_ids[ob["point"]]))
    return {"station_corr": out["station_corr"][so], "station_sigma": out["station_sigma"][so],
            "point_corr": out["point_corr"][po], "point_sigma": out["point_sigma"][po],
            "residuals": out["residuals"][oo], "obs_quality": out["obs_quality"][oo]}


def assert_same_solution(a, b, rtol=1e-9):
    sa, sb = by_id(a), by_id(b)
    for k in SOLUTION:
        scale = max(np.abs(sb[k]).max(), 1e-300)
        # obs_quality is stored in single precision
        tol = 2e-6 if k == "obs_quality" else rtol
        np.testing.assert_allclose(sa[k], sb[k], rtol=tol, atol=tol * scale, err_msg=k)


def assert_resumed_solution(path, ref):
    """A resumed run's committed result against the uninterrupted run's: the corrections
    and residuals bit for bit; the precision, which comes from normals built again at the
    final state (as on the band), not from the last iteration's, to the convergence
    tolerance; no work directory left."""
    a, b = by_id(path), by_id(ref)
    for k in ("station_corr", "point_corr", "residuals"):
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    for k in ("station_sigma", "point_sigma"):
        np.testing.assert_allclose(a[k], b[k], rtol=1e-6, err_msg=k)
    assert not work_path(path).exists()


def ordered_pair(src, tmp_path, leaf=4, name="b", deep=True):
    """Copies of ``src`` ordered for the band and for a tree of small leaves (``deep``:
    checked to have several levels); with ``deep=False`` also the tree's order result."""
    band, tree = tmp_path / f"{name}-band.h5", tmp_path / f"{name}-tree.h5"
    shutil.copy(src, band)
    shutil.copy(src, tree)
    rb = sapgo.order_project(band, solver="band")
    rt = sapgo.order_project(tree, solver="tree", leaf_stations=leaf)
    assert rb.solver == "band" and rt.solver == "tree"
    if not deep:
        return band, tree, rt
    assert rt.tree["nodes"] > 3 and rt.tree["depth"] >= 3
    return band, tree


@pytest.fixture(scope="module")
def square(tmp_path_factory):
    d = tmp_path_factory.mktemp("sq")
    path = d / "sq.h5"
    sapgo.generate_block(path, strips=6, photos_per_strip=7, control_points=8, seed=4)
    return path


def test_tree_equals_band_on_a_square_block(square, tmp_path):
    band, tree = ordered_pair(square, tmp_path)
    sb = sapgo.adjust(band, TIGHT)
    st = sapgo.adjust(tree, TIGHT)
    assert st.solver == "tree" and sb.solver == "band"
    assert st.tree["nodes"] > 3 and st.tree["flops"] > 0
    assert st.converged and st.iterations == sb.iterations
    assert st.sigma0 == pytest.approx(sb.sigma0, rel=1e-10)
    assert_same_solution(tree, band)
    assert st.reliability["mean_redundancy_number"] == pytest.approx(
        sb.reliability["mean_redundancy_number"], rel=1e-9)
    assert "tree solver" in st.full_report() and "tree solver" in st.brief_report()
    d = st.to_dict()
    assert d["solver"] == "tree" and d["tree"]["leaves"] >= 2


def test_the_factor_buffer_made_at_the_start_serves_every_step(square, tmp_path,
                                                               monkeypatch):
    """The in-core factor's buffer is made once, beside the run's start (start_arena), and
    every factorisation and the precision pass use it: no other is mapped."""
    from sapgo.solve import fronts
    from sapgo.solve import tree as tree_mod

    steps, made = [], []
    real_step, real_map = tree_mod.tree_step, fronts._anonymous
    monkeypatch.setattr(tree_mod, "tree_step",
                        lambda *a, **k: steps.append(1) or real_step(*a, **k))
    monkeypatch.setattr(fronts, "_anonymous", lambda n: made.append(len(steps)) or real_map(n))
    _, tree = ordered_pair(square, tmp_path)
    s = sapgo.adjust(tree, TIGHT)
    assert s.solver == "tree" and s.iterations >= 2 and s.converged
    assert made == [0]   # one buffer, asked for before the first factorisation


def test_tree_equals_the_dense_least_squares(square, tmp_path):
    eo_ref, xyz_ref, sigma0_ref, _ = dense_reference(square)   # (records in id order)
    path = tmp_path / "t.h5"
    shutil.copy(square, path)
    sapgo.order_project(path, solver="tree", leaf_stations=4)
    s = sapgo.adjust(path, TIGHT)
    assert s.solver == "tree" and s.converged
    eo, xyz = adjusted_by_id(path)
    assert np.abs(xyz - xyz_ref).max() < 1e-6
    assert np.abs(eo[:, 3:] - eo_ref[:, 3:]).max() < 1e-6
    assert np.abs(eo[:, :3] - eo_ref[:, :3]).max() < 1e-9
    assert s.sigma0 == pytest.approx(sigma0_ref, rel=1e-8)


def test_levenberg_marquardt_and_snooping_on_the_tree(tmp_path):
    src = tmp_path / "bl.h5"
    sapgo.generate_block(src, strips=4, photos_per_strip=8, control_points=8, blunders=3,
                         blunder_size=(0.08, 0.1), seed=2)
    band, tree = ordered_pair(src, tmp_path)
    opts = sapgo.Options(progress=False, snooping=True, method="levenberg-marquardt",
                         max_iterations=30)
    sb, st = sapgo.adjust(band, opts), sapgo.adjust(tree, opts)
    assert st.method == sb.method == "lm"
    assert [r["cost"] for r in st.iteration_log] == pytest.approx(
        [r["cost"] for r in sb.iteration_log], rel=1e-9)
    assert [(r["photo_id"], r["point_id"]) for r in st.rejected] == \
        [(r["photo_id"], r["point_id"]) for r in sb.rejected]
    assert len(st.rejected) >= 2
    assert_same_solution(tree, band, rtol=1e-8)


def test_robust_estimation_on_the_tree(tmp_path):
    src = tmp_path / "rb.h5"
    sapgo.generate_block(src, strips=4, photos_per_strip=6, control_points=8, blunders=2,
                         seed=5)
    band, tree = ordered_pair(src, tmp_path)
    opts = sapgo.Options(progress=False, robust="cauchy")
    sb, st = sapgo.adjust(band, opts), sapgo.adjust(tree, opts)
    assert st.sigma0 == pytest.approx(sb.sigma0, rel=1e-9)
    assert_same_solution(tree, band, rtol=1e-8)


def test_bal_with_the_photos_intrinsics_on_the_tree(tmp_path):
    """A free network of 9-parameter stations (BAL problem-49, Levenberg-Marquardt): the
    tree's costs equal the band's, step by step."""
    src = tmp_path / "bal.h5"
    data = os.path.join(os.path.dirname(__file__), "data", "problem-49-7776-pre.txt.gz")
    from sapgo.formats.bal import import_bal

    import_bal(data, src)
    band, tree, rt = ordered_pair(src, tmp_path, leaf=8, deep=False)
    assert rt.tree["nodes"] >= 3
    opts = sapgo.Options(progress=False, max_iterations=6)
    sb, st = sapgo.adjust(band, opts), sapgo.adjust(tree, opts)
    assert [r["cost"] for r in st.iteration_log] == pytest.approx(
        [r["cost"] for r in sb.iteration_log], rel=1e-8)
    assert st.final_cost == pytest.approx(sb.final_cost, rel=1e-9)


def test_a_disconnected_block_is_a_forest(tmp_path):
    """Two blocks far apart in one project: one subtree each, the same as the band."""
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    sapgo.generate_block(a, strips=3, photos_per_strip=5, control_points=6, seed=1)
    sapgo.generate_block(b, strips=3, photos_per_strip=5, control_points=6, seed=2)
    ra, rb = read_records(a), read_records(b)
    shift = np.array([1e5, 0.0, 0.0])
    rb["stations"]["eo"][:, 3:6] += shift
    rb["points"]["xyz"] += shift
    rb["points"]["control"] += shift
    rb["truth"]["stations"]["eo"][:, 3:6] += shift
    rb["truth"]["points"]["xyz"] += shift
    ns, npt = len(ra["stations"]), len(ra["points"])
    rb["stations"]["id"] += 10 ** 6
    rb["points"]["id"] += 10 ** 6
    rb["observations"]["station"] += ns
    rb["observations"]["point"] += npt
    merged = {k: np.concatenate([ra[k], rb[k]]) for k in ("cameras", "stations", "points",
                                                          "observations", "station_priors")}
    merged["cameras"] = ra["cameras"]
    merged["truth"] = {k: np.concatenate([ra["truth"][k], rb["truth"][k]])
                       for k in ("stations", "points")}
    src = tmp_path / "two.h5"
    rewrite(src, merged)
    band, tree, rt = ordered_pair(src, tmp_path, deep=False)
    assert rt.tree["roots"] == 2
    sb, st = sapgo.adjust(band, TIGHT), sapgo.adjust(tree, TIGHT)
    assert st.sigma0 == pytest.approx(sb.sigma0, rel=1e-10)
    assert_same_solution(tree, band)


def test_the_solver_option_orders_again(square, tmp_path):
    path = tmp_path / "s.h5"
    shutil.copy(square, path)
    sapgo.order_project(path, solver="tree", leaf_stations=4)
    s = sapgo.adjust(path, sapgo.Options(progress=False, solver="band"))
    assert s.solver == "band"
    with Project(path) as p:
        assert p.solver == "band" and p.tree() is None and "tree" not in p.file
    s = sapgo.adjust(path, sapgo.Options(progress=False, solver="tree"))
    assert s.solver == "tree"
    with Project(path) as p:
        assert p.solver == "tree" and p.tree() is not None
    # auto keeps the order the project has
    s = sapgo.adjust(path, sapgo.Options(progress=False))
    assert s.solver == "tree" and s.timings_s["order"] == 0.0
    with pytest.raises(sapgo.SapgoError, match="solver 'x'"):
        sapgo.adjust(path, sapgo.Options(solver="x"))


def test_a_stale_tree_is_never_used(square, tmp_path):
    """A tree that no longer matches the records is refused by Project.tree() and the
    project ordered again before adjusting."""
    import h5py

    path = tmp_path / "s.h5"
    shutil.copy(square, path)
    sapgo.order_project(path, solver="tree", leaf_stations=4)
    with h5py.File(path, "r+") as f:
        pt = f["tree/pt_start"][()]
        pt[-1] = 10 ** 9
        f["tree/pt_start"][...] = pt
    with Project(path) as p:
        with pytest.raises(sapgo.SapgoError, match="does not match the records"):
            p.tree()
    s = sapgo.adjust(path, sapgo.Options(progress=False, solver="tree"))
    assert s.converged and s.timings_s["order"] > 0


@pytest.fixture(scope="module")
def miscalibrated_square(tmp_path_factory):
    """A 5 x 6 block whose images carry distortion while its camera says f + 0.03 mm and
    no distortion."""
    d = tmp_path_factory.mktemp("cal")
    path = d / "cal.h5"
    sapgo.generate_block(path, strips=5, photos_per_strip=6, control_points=8, seed=6,
                         distortion=(-2.0e-8, 3.0e-13, 0.0, 1.5e-6, -1.0e-6))
    rec = read_records(path)
    rec["cameras"]["focal_length"] += 0.03
    rec["cameras"][["k1", "k2", "p1", "p2"]] = (0.0, 0.0, 0.0, 0.0)
    rewrite(path, rec)
    return path


@pytest.mark.parametrize("method", ["gauss-newton", "levenberg-marquardt"])
def test_self_calibration_on_the_tree_equals_the_band(miscalibrated_square, tmp_path, method):
    """Self-calibration's border on the tree: the same orientations, points, camera,
    sigma0, precision (stations, points, camera parameters) and observation quality as on
    the band (itself tested against the dense bordered inverse, tests/test_calibration.py),
    with Gauss-Newton and with Levenberg-Marquardt's damping of the border."""
    band, tree = ordered_pair(miscalibrated_square, tmp_path)
    opts = dataclasses.replace(TIGHT, method=method,
                               calibrate=("f", "x0", "y0", "k1", "k2", "p1", "p2"))
    sb = sapgo.adjust(band, opts)
    st = sapgo.adjust(tree, opts)
    assert st.solver == "tree" and st.converged and st.iterations == sb.iterations
    assert st.sigma0 == pytest.approx(sb.sigma0, rel=1e-10)
    assert_same_solution(tree, band)
    with Project(band) as pb, Project(tree) as pt:
        np.testing.assert_allclose(pt.solution("camera_corr"), pb.solution("camera_corr"),
                                   rtol=1e-9, atol=1e-15)
    assert len(st.calibration) == len(sb.calibration) == 7
    for a, b in zip(st.calibration, sb.calibration):
        assert a["parameter"] == b["parameter"] and a["sigma"] > 0
        assert a["sigma"] == pytest.approx(b["sigma"], rel=1e-8)


@pytest.mark.parametrize("method", ["gauss-newton", "levenberg-marquardt"])
def test_top_fronts_split_between_threads_equal_the_band(miscalibrated_square, tmp_path,
                                                         monkeypatch, method):
    """The top nodes' fronts eliminated on two threads (every one of them, in panels of 7
    columns; on the real blocks only fronts of SPLIT_ROWS rows and more) with
    self-calibration's border and with damping: the same result as the band."""
    from sapgo.solve import fronts

    monkeypatch.setattr(fronts, "SPLIT_ROWS", 0)
    monkeypatch.setattr(fronts, "SPLIT_PANEL", 7)
    split = []
    real = fronts.TreeSolver._eliminate_split
    monkeypatch.setattr(fronts.TreeSolver, "_eliminate_split",
                        lambda self, *a: split.append(1) or real(self, *a))
    band, tree = ordered_pair(miscalibrated_square, tmp_path)
    opts = dataclasses.replace(TIGHT, method=method,
                               calibrate=("f", "x0", "y0", "k1", "k2", "p1", "p2"))
    sb = sapgo.adjust(band, opts)
    st = sapgo.adjust(tree, opts)
    assert split, "no front was split between threads"
    assert st.solver == "tree" and st.converged and st.iterations == sb.iterations
    assert st.sigma0 == pytest.approx(sb.sigma0, rel=1e-10)
    assert_same_solution(tree, band)
    for a, b in zip(st.calibration, sb.calibration):
        assert a["sigma"] == pytest.approx(b["sigma"], rel=1e-8)


@pytest.mark.parametrize("case", ["gauss-newton", "levenberg-marquardt", "calibration"])
def test_tiled_fronts_give_the_in_core_result(miscalibrated_square, tmp_path, monkeypatch,
                                              case):
    """Fronts beyond 5 stations tiled (panels of 2 stations, the factor in core or in its
    file, updates and the inverse's parts in scratch files): the same solution, sigma0,
    precision and observation quality as with every front in core."""
    import sapgo.solve.fronts as fronts
    import sapgo.solve.tree as tree_mod
    from test_tree import SMALL_TILES

    _, ref = ordered_pair(miscalibrated_square, tmp_path, name="ref")
    path = tmp_path / "tiled.h5"
    shutil.copy(ref, path)
    opts = dataclasses.replace(TIGHT, method="levenberg-marquardt" if case[0] == "l" else
                               "gauss-newton", chunk_points=40)
    if case == "calibration":
        opts = dataclasses.replace(opts, calibrate=("f", "x0", "y0", "k1", "k2", "p1", "p2"))
    sr = sapgo.adjust(ref, opts)
    seen = {"tiled": 0, "inverted": 0}
    eliminate, invert = fronts.TreeSolver.eliminate_tiled, fronts.invert_tiled

    def counted(name, f):
        def g(*a, **kw):
            seen[name] += 1
            return f(*a, **kw)
        return g
    monkeypatch.setattr(fronts.TreeSolver, "eliminate_tiled", counted("tiled", eliminate))
    monkeypatch.setattr(fronts, "invert_tiled", counted("inverted", invert))
    # (Gauss-Newton: a peak beyond the budget, so that the factor goes to its file)
    need = 1 << 40 if case[0] == "g" else 0
    monkeypatch.setattr(tree_mod, "work_plan",
                        lambda tree, k, opts, threads=None, held=0, n_stations=0, separate=False:
                        ([[(0, tree.n_nodes)]], [], need, SMALL_TILES))
    st = sapgo.adjust(path, opts)
    assert seen["tiled"] > 0 and seen["inverted"] > 0
    assert st.tree["tiled_fronts"] > 0 and sr.tree["tiled_fronts"] == 0
    assert "fronts tiled for the memory budget" in st.full_report()
    assert st.converged and st.iterations == sr.iterations
    assert st.sigma0 == pytest.approx(sr.sigma0, rel=1e-10)
    assert_same_solution(path, ref)
    if case == "calibration":
        for a, b in zip(st.calibration, sr.calibration):
            assert a["sigma"] == pytest.approx(b["sigma"], rel=1e-8)


def test_order_and_adjust_from_the_command_line(square, tmp_path, capsys):
    path = tmp_path / "s.h5"
    shutil.copy(square, path)
    code, out, _ = run_cli(capsys, "order", path, "--solver", "tree", "--leaf-stations", "4")
    assert code == 0 and "solver: tree" in out and "predicted factorisation" in out
    code, out, _ = run_cli(capsys, "info", path, "--json")
    info = json.loads(out)
    assert info["solver"] == "tree" and info["tree"]["nodes"] > 3
    code, out, _ = run_cli(capsys, "adjust", path, "--no-progress")
    assert code == 0 and "tree solver" in out
    with pytest.raises(SystemExit) as e:
        run_cli(capsys, "adjust", path, "--solver", "bush")
    assert e.value.code == 2 and "invalid choice: 'bush'" in capsys.readouterr().err


RUN = ("import sys, sapgo; sapgo.adjust(sys.argv[1], sapgo.Options(progress=False, "
       "chunk_points=40, max_iterations=10))")


@pytest.mark.parametrize("fault", ["build:2", "solve:1", "update:2", "checkpoint:2",
                                   "commit-write:*"])
def test_a_killed_tree_run_resumes_to_the_same_result(square, tmp_path, fault):
    ref = tmp_path / "ref.h5"
    shutil.copy(square, ref)
    sapgo.order_project(ref, solver="tree", leaf_stations=4)
    path = tmp_path / "k.h5"
    shutil.copy(ref, path)
    sapgo.adjust(ref, sapgo.Options(progress=False, chunk_points=40))
    env = dict(os.environ, SAPGO_FAULT=fault)
    r = subprocess.run([sys.executable, "-c", RUN, str(path)], env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == -signal.SIGKILL, r.stderr
    s = sapgo.adjust(path, sapgo.Options(progress=False, chunk_points=40, resume=True))
    assert s.converged and s.solver == "tree"
    assert_resumed_solution(path, ref)


RUN_CAL = ("import sys, sapgo; sapgo.adjust(sys.argv[1], sapgo.Options(progress=False, "
           "chunk_points=40, max_iterations=10, calibrate=('f', 'x0', 'y0', 'k1', 'p1'){}))")


@pytest.mark.parametrize("fault,method", [("build:2", ""), ("update:3", ""),
                                          ("solve:2", ", method='levenberg-marquardt'")])
def test_a_killed_self_calibrating_tree_run_resumes_to_the_same_result(
        miscalibrated_square, tmp_path, fault, method):
    """Self-calibration on the tree (the border, its damping with Levenberg-Marquardt)
    killed at a moment of an iteration and resumed: the same stations, points, residuals
    and camera as the uninterrupted run, bit for bit."""
    _, ref = ordered_pair(miscalibrated_square, tmp_path, name="ref")
    path = tmp_path / "k.h5"
    shutil.copy(ref, path)
    run = RUN_CAL.format(method)
    r = subprocess.run([sys.executable, "-c", run, str(ref)], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    r = subprocess.run([sys.executable, "-c", run, str(path)], capture_output=True, text=True,
                       env=dict(os.environ, SAPGO_FAULT=fault), timeout=300)
    assert r.returncode == -signal.SIGKILL, r.stderr
    r = subprocess.run([sys.executable, "-c", run.replace("chunk_points=40",
                                                          "chunk_points=40, resume=True"),
                        str(path)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    a, b = by_id(path), by_id(ref)
    for k in ("station_corr", "point_corr", "residuals"):
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    with Project(path) as pa, Project(ref) as pb:
        np.testing.assert_array_equal(pa.solution("camera_corr"), pb.solution("camera_corr"))
    assert not work_path(path).exists()


def test_fronts_larger_than_the_memory_budget_are_refused_before_any_work(square, tmp_path,
                                                                         monkeypatch, capsys):
    from sapgo.solve.partition import Tree

    path = tmp_path / "s.h5"
    shutil.copy(square, path)
    sapgo.order_project(path, solver="tree", leaf_stations=4)
    before = open(path, "rb").read()
    monkeypatch.setattr(Tree, "peak_front_bytes",
                        lambda self, k=6, plan=None, tile=None, separate=False: 3 << 30)
    code, _, err = run_cli(capsys, "adjust", path, "--no-progress", "--memory", "2G")
    # 3 GiB for the fronts, 256 MiB and 400 bytes a station (42) for the process
    assert_one_line_error(code, err, "fronts need 3072 MiB in core even tiled",
                          "--memory 3393M", "--solver band")
    assert open(path, "rb").read() == before and not work_path(path).exists()


def test_a_budget_below_the_baseline_is_refused_before_any_work(square, tmp_path, capsys):
    path = tmp_path / "s.h5"
    shutil.copy(square, path)
    sapgo.order_project(path, solver="tree", leaf_stations=4)
    before = open(path, "rb").read()
    code, _, err = run_cli(capsys, "adjust", path, "--no-progress", "--memory", "200M")
    # 256 MiB and 400 bytes a station (42)
    assert_one_line_error(code, err, "--memory 200M is less than the adjustment's baseline",
                          "(256 MiB", "--memory 385M")
    assert open(path, "rb").read() == before and not work_path(path).exists()


def test_a_point_the_tree_cannot_place_is_named(square, tmp_path, capsys):
    """An observation moved to a station outside its point's front (records changed after
    ordering): one line naming the point, the project untouched."""
    import h5py

    path = tmp_path / "s.h5"
    shutil.copy(square, path)
    sapgo.order_project(path, solver="tree", leaf_stations=4)
    with Project(path) as p:
        tree = p.tree()
        pts = p.read("points")
        ob = p.read("observations")
    leaf = int(np.flatnonzero(tree.leaf)[0])
    j = int(tree.pt_start[leaf])           # the first point of a leaf
    far = [s for s in range(tree.n_active) if s not in set(tree.front(leaf).tolist())]
    o = int(pts["obs_start"][j]) + int(pts["n_obs"][j]) - 1
    assert far and ob["station"][o] < far[-1]
    with h5py.File(path, "r+") as f:
        rec = f["observations"][o]
        rec["station"] = far[-1]
        f["observations"][o] = rec
    before = open(path, "rb").read()
    code, _, err = run_cli(capsys, "adjust", path, "--no-progress")
    assert_one_line_error(code, err, f"point id {int(pts['id'][j])}", "partition tree",
                          "sapgo order")
    assert open(path, "rb").read() == before
