"""The streamed reduced normals against the full normal matrix reduced densely with numpy."""

from pathlib import Path

import numpy as np
import pytest

import naive
from conftest import read_records, rewrite
from sapgo.adjust import Options, _load_block, build
from sapgo.geometry import attitude_jacobians
from sapgo.work import Work
from sapgo.solve.band import band_to_dense
from sapgo.ordering import order_project
from sapgo.project import (
    CONTROL_MASK,
    KIND_CONTROL,
    KIND_HORIZONTAL,
    KIND_PASS,
    KIND_VERTICAL,
    PRIOR_DTYPE,
    Project,
)


def streamed(path, tmp_path, **opts):
    with Project(path) as p:
        blk = _load_block(p)
        w = Work(tmp_path / "work", p, blk.band_width, create=True)
        try:
            w.initialise(p, 1000)
            build(p, w, blk, Options(progress=False, **opts))
            return band_to_dense(w.factor[:]), w.y[:].ravel(), blk.band_width
        finally:
            w.close()


def dense(path):
    with Project(path) as p:
        st, pt, ob = p.read("stations"), p.read("points"), p.read("observations")
        pr = p.read("station_priors")
        f = p.cameras()["focal_length"][0]
    mask = CONTROL_MASK[pt["kind"]].astype(bool)
    m, d = naive.reduced_normals_dense(
        st["eo"], pt["xyz"], f, ob["station"], ob["point"], np.column_stack([ob["x"], ob["y"]]),
        ob["sigma"], mask, pt["control"], pt["control_sigma"])
    for rec in pr:  # station priors: weighted observations of the six parameters
        s = rec["station"]
        m[6 * s:6 * s + 6, 6 * s:6 * s + 6] += rec["weight"]
        d[6 * s:6 * s + 6] += rec["weight"] @ (rec["value"] - st["eo"][s])
    # sapgo's unknowns of a photo's attitude are the rotation vector that turns it:
    # d(omega, phi, kappa) = J d(theta) (geometry.attitude_jacobians), M' = T' M T
    n = len(st)
    t = np.zeros((6 * n, 6 * n))
    for s, j in enumerate(attitude_jacobians(st["eo"][:, :3])):
        t[6 * s:6 * s + 3, 6 * s:6 * s + 3] = j
        t[6 * s + 3:6 * s + 6, 6 * s + 3:6 * s + 6] = np.eye(3)
    return t.T @ m @ t, t.T @ d


def with_mixed_control_and_prior(path):
    rec = read_records(path)
    kind = rec["points"]["kind"]
    ctrl = np.flatnonzero(kind == 1)
    kind[ctrl[0]] = KIND_HORIZONTAL
    kind[ctrl[1]] = KIND_VERTICAL
    kind[ctrl[2]] = KIND_PASS
    rec["points"]["control_sigma"][ctrl[1]] = [0.0, 0.0, 0.05]
    prior = np.zeros(1, PRIOR_DTYPE)
    prior["station"] = 3
    prior["value"] = rec["stations"]["eo"][3] + [1e-4, -1e-4, 2e-4, 3.0, -2.0, 1.0]
    w = np.diag([1e8, 1e8, 1e8, 0.04, 0.04, 0.25])
    w[3, 4] = w[4, 3] = 0.01
    prior["weight"] = w
    rec["station_priors"] = prior
    rewrite(path, rec)


@pytest.mark.parametrize("chunks", [dict(), dict(chunk_points=5, chunk_rows=1),
                                    dict(chunk_points=3, chunk_rows=2), "parallel"])
def test_streamed_reduced_normals_equal_dense(small_block, tmp_path, chunks, monkeypatch):
    if chunks == "parallel":  # every window split between the threads, down to 1 point each
        import numba

        from sapgo import normals
        if numba.config.NUMBA_NUM_THREADS < 2:   # (the parts, whatever runs them)
            pytest.skip("one thread")
        monkeypatch.setattr(normals, "PARALLEL_MIN_POINTS", 1)
        chunks = dict(chunk_rows=3)
    with_mixed_control_and_prior(small_block)
    order_project(small_block)
    m_ref, d_ref = dense(small_block)
    m, d, bw = streamed(small_block, tmp_path, **chunks)
    assert bw < 12  # the test exercises a real band, not a full matrix
    scale = np.abs(np.diag(m_ref))
    tol = 1e-9 * np.sqrt(np.outer(scale, scale))
    assert (np.abs(m - m_ref) <= tol).all()
    np.testing.assert_allclose(d, d_ref, rtol=1e-8, atol=1e-9 * np.abs(d_ref).max())
    # outside the band the reduced matrix is exactly zero
    n = m.shape[0] // 6
    for i in range(n):
        for j in range(i + bw, n):
            assert not m_ref[6 * i:6 * i + 6, 6 * j:6 * j + 6].any() or \
                np.abs(m_ref[6 * i:6 * i + 6, 6 * j:6 * j + 6]).max() < 1e-9 * scale.max()


def _whole_chunk(path):
    """The ordered project's block and all its points as one chunk."""
    from sapgo.normals import PointChunk

    order_project(path)
    with Project(path) as p:
        blk = _load_block(p)
        c = PointChunk(p, 0, p.n_points, p.read_field("points", "xyz"), blk.camera,
                       blk.cam_sigma, blk.frame, blk.rejected, blk.rejected_points)
    return blk, c


@pytest.mark.parametrize("threads", [2, 3, 50])
def test_parallel_update_equals_the_one_thread_kernel(p1_block, threads):
    """update_points_parallel cuts the points into runs on threads of their own: the same
    coordinates and residuals bit for bit as update_points on one thread, the statistics
    to rounding (summed by run), and a bad point named by its index in the chunk."""
    from sapgo.adjust import next_orientations
    from sapgo.normals import update_points, update_points_parallel

    blk, c = _whole_chunk(p1_block)
    rng = np.random.default_rng(3)
    delta = rng.normal(0, 1e-5, (len(blk.eo), 6))
    delta[:, 3:] *= 1e5
    eo_next = next_orientations(blk.eo, delta)

    def run(fn, *first):
        xyz = np.empty_like(c.xyz)
        res = np.zeros((c.o1 - c.o0, 2))
        stats = np.zeros(11)
        fn(*first, c.xyz, c.kind, c.ctrl, c.csig, c.rot, c.pt_start, c.nobs, c.active,
           c.obs_station, c.obs_xy, c.obs_sigma, c.obs_active, blk.eo, delta, blk.camera,
           blk.cams, blk.ctrl_mask, c.max_rays, xyz, res, stats, 0.0, blk.behind_ok, None,
           None, blk.fixed, eo_next)
        return xyz, res, stats

    xyz1, res1, st1 = run(update_points)
    xyz2, res2, st2 = run(update_points_parallel, threads)
    np.testing.assert_array_equal(xyz2, xyz1)
    np.testing.assert_array_equal(res2, res1)
    np.testing.assert_allclose(st2, st1, rtol=1e-12)
    assert st1[4] == c.obs_active.sum() and st1[7] == 0
    # a point behind its photos: the first one is named, by its index in the chunk
    bad = len(c.xyz) * 2 // 3
    c.xyz[bad, 2] = blk.eo[c.obs_station[c.pt_start[bad]], 5] + 5000.0
    _, _, st1 = run(update_points)
    _, _, st2 = run(update_points_parallel, threads)
    assert st1[7] == st2[7] == bad + 1 and st1[8] == st2[8] != 0


@pytest.mark.parametrize("threads", [1, 2, 3, 50])
def test_parallel_point_costs_equal_the_one_thread_kernel_and_the_obvious_sum(p1_block,
                                                                              threads):
    """point_costs_parallel (the cost at the starting values) sums by run what point_costs
    sums on one thread (to rounding), and its image term is the plain sum of p |v|^2 over
    the active rays of the active points (an inactive point and an inactive ray among them),
    their residuals projected one by one."""
    from sapgo.geometry import observed, project
    from sapgo.normals import point_costs, point_costs_parallel

    blk, c = _whole_chunk(p1_block)
    c.active[len(c.xyz) // 3] = 1
    c.obs_active[c.pt_start[len(c.xyz) // 2]] = False
    args = (c.xyz, c.kind, c.ctrl, c.csig, c.rot, c.pt_start, c.nobs, c.active,
            c.obs_station, c.obs_xy, c.obs_sigma, c.obs_active, blk.eo, blk.camera, blk.cams,
            blk.ctrl_mask)
    one = point_costs(*args)
    par = point_costs_parallel(threads, *args)
    np.testing.assert_allclose(par, one, rtol=1e-12)
    ref = 0.0
    for j in range(len(c.xyz)):
        if c.active[j]:
            continue
        xyz = c.xyz[j].copy()
        fixed = blk.ctrl_mask[c.kind[j]].astype(bool) & (c.csig[j] == 0.0)
        xyz[fixed] = c.ctrl[j][fixed]
        for i in range(c.pt_start[j], c.pt_start[j] + c.nobs[j]):
            if c.obs_active[i]:
                cam = blk.cams[blk.camera[c.obs_station[i]]]
                x, y = project(blk.eo[c.obs_station[i]], xyz, cam)
                ox, oy = observed(c.obs_xy[i, 0], c.obs_xy[i, 1], cam)
                ref += ((x - ox) ** 2 + (y - oy) ** 2) / c.obs_sigma[i] ** 2
    assert ref > 0.0
    np.testing.assert_allclose(par[0], ref, rtol=1e-12)


@pytest.mark.parametrize("threads", [2, 3, 50])
def test_parallel_point_sigmas_equal_the_one_thread_kernel(p1_block, threads):
    """point_sigmas_parallel gives each run its own points and its own observations: the
    points' precision and the observations' redundancy numbers and tests bit for bit those
    of point_sigmas on one thread (an inactive point and an inactive observation among
    them); a chunk whose points' observations do not follow each other goes on one
    thread, the same again."""
    from sapgo.normals import point_sigmas, point_sigmas_parallel

    blk, c = _whole_chunk(p1_block)
    c.active[4] = 1
    c.obs_active[c.pt_start[7]] = False
    n = 6 * len(blk.eo)
    rng = np.random.default_rng(5)
    m = rng.normal(size=(n, n))
    zb = np.linalg.inv(m @ m.T + n * np.eye(n)) * 1e-4   # (any cofactors: the same ones)
    res = rng.normal(0, 3e-3, (len(c.obs_station), 2))

    def run(fn, *first, pt_start=c.pt_start):
        out = np.full((len(c.xyz), 6), 7.0)
        out_r = np.full((len(c.obs_station), 3), 7.0)
        out_w = np.full((len(c.obs_station), 3), 7.0)
        fn(*first, c.xyz, c.kind, c.ctrl, c.csig, c.rot, pt_start, c.nobs, c.active,
           c.obs_station, c.obs_xy, c.obs_sigma, c.obs_active, blk.eo, blk.camera, blk.cams,
           blk.ctrl_mask, c.max_rays, zb, 0, res, out, out_r, out_w, 6, None, None, 0, None,
           blk.fixed, blk.behind_ok)
        return out, out_r, out_w

    ref = run(point_sigmas)
    assert np.isfinite(ref[0]).all() and (ref[1][:, 0] != 0).sum() > 0.9 * len(res)
    for x, y in zip(run(point_sigmas_parallel, threads), ref):
        np.testing.assert_array_equal(x, y)
    swapped = c.pt_start.copy()   # (the first two points' observations in the other order)
    swapped[0], swapped[1] = c.pt_start[0] + c.nobs[1], c.pt_start[0]
    if c.nobs[0] == c.nobs[1]:
        for x, y in zip(run(point_sigmas_parallel, threads, pt_start=swapped),
                        run(point_sigmas, pt_start=swapped)):
            np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("threads", [1, 2])
def test_damping_diagonal_of_the_build_equals_the_obvious_sum(p1_block, tmp_path, threads,
                                                              monkeypatch):
    """The band's build sums the Levenberg-Marquardt damping's diagonal (each station's
    ``sum p a_u^2`` over its rays) in its kernel, window by window (windows of 5 rows
    beyond the band; on one thread chunks of 37 points) and thread by thread: equal to the sum taken
    observation by observation in Python from the collinearity partials, a station's held
    parameters 0."""
    from sapgo import threads as sapgo_threads
    from sapgo.geometry import linearize
    from sapgo.normals import fixed_columns

    monkeypatch.setattr(sapgo_threads, "_setting", str(threads))
    blk, c = _whole_chunk(p1_block)
    a, b = np.empty((2, 6)), np.empty((2, 3))
    with Project(p1_block) as p:
        blk = _load_block(p)
        blk.fixed[3] |= 0b000101   # (omega and kappa of station 3 held)
        w = Work(tmp_path / "work", p, blk.band_width, create=True)
        try:
            w.initialise(p, 1000)
            rows = []
            opts = Options(progress=False, chunk_points=37 if threads == 1 else 10 ** 6,
                           chunk_rows=5)
            for lam in (0.0, 1e-3):
                got = []
                diag, _ = build(p, w, blk, opts, lam=lam,
                                sink=lambda r, y, got=got: got.append(np.array(r)))
                rows.append(np.concatenate(got))
        finally:
            w.close()
    ref = np.zeros((len(blk.eo), 6))
    for j in range(len(c.xyz)):
        if c.active[j] != 0:
            continue
        for i in range(c.pt_start[j], c.pt_start[j] + c.nobs[j]):
            if c.obs_active[i]:
                s = c.obs_station[i]
                linearize(blk.eo[s], c.xyz[j], blk.cams[blk.camera[s]], a, b)
                fixed_columns(a, blk.fixed[s])
                ref[s] += (a * a).sum(axis=0) / c.obs_sigma[i] ** 2
    np.testing.assert_allclose(diag, ref, rtol=1e-12)
    assert (diag[3, [0, 2]] == 0).all() and (diag > 0).sum() == diag.size - 2
    assert not np.array_equal(rows[0], rows[1])   # (damped: stations and points)


@pytest.mark.parametrize("solver", ["band", "tree"])
def test_kept_point_chunks_change_nothing(tmp_path, monkeypatch, solver):
    """The points' chunks kept for the run (Project.keep_point_chunks) give bit for bit the
    run that converts every chunk afresh, with data snooping's rejections on top of them,
    and the kept arrays stay as they were read (the run's rejections never written into
    them)."""
    import shutil

    import sapgo
    from sapgo import normals
    from sapgo.project import Project

    src = tmp_path / "src.h5"
    sapgo.generate_block(src, strips=4, photos_per_strip=8, control_points=8, blunders=3,
                         blunder_size=(0.08, 0.1), seed=2, progress=False)
    opts = sapgo.Options(progress=False, snooping=True, solver=solver)
    kept, made = [], []
    real_keep, real_arrays = Project.keep_point_chunks, normals._chunk_arrays

    def keep(self, expected, most):
        got = real_keep(self, expected, most)
        kept.append(self.point_chunks)
        return got

    def arrays(*a):
        out = real_arrays(*a)
        made.append((out, [x.copy() if isinstance(x, np.ndarray) else x for x in out]))
        return out

    runs = {}
    for name in ("kept", "afresh"):
        path = tmp_path / f"{name}.h5"
        shutil.copy(src, path)
        monkeypatch.setattr(Project, "keep_point_chunks",
                            keep if name == "kept" else (lambda self, e, m: 0))
        monkeypatch.setattr(normals, "_chunk_arrays", arrays)
        runs[name] = (sapgo.adjust(path, opts), path)
        if name == "kept":
            assert kept and kept[-1], "no chunk was kept"
            held = {id(entry[3]) for entry in kept[-1].values()}
            seen = [(out, copy) for out, copy in made if id(out) in held]
            assert len(seen) == len(held)
            for out, copy in seen:   # as read: nothing written into them during the run
                for x, y in zip(out, copy):
                    np.testing.assert_array_equal(x, y)
    (sk, pk), (sa, pa) = runs["kept"], runs["afresh"]
    assert len(sk.rejected) >= 2
    assert sk.sigma0 == sa.sigma0 and sk.iterations == sa.iterations
    assert [(r["photo_id"], r["point_id"]) for r in sk.rejected] == \
        [(r["photo_id"], r["point_id"]) for r in sa.rejected]
    with Project(pk) as qk, Project(pa) as qa:
        for name in ("station_corr", "point_corr", "residuals", "point_sigma"):
            np.testing.assert_array_equal(qk.solution(name), qa.solution(name))


def test_part_of_a_kept_chunk_is_the_chunk_read_afresh(tmp_path):
    """A chunk of points inside a kept one (the tree's precision pass asks node by node) is
    served as views of the kept arrays, equal to the same points converted afresh; a range
    no kept chunk holds, or another camera table, is read afresh and not kept."""
    import sapgo
    from sapgo import normals
    from sapgo.normals import PointChunk

    path = tmp_path / "b.h5"
    sapgo.generate_block(path, strips=3, photos_per_strip=6, control_points=4, progress=False)
    with Project(path) as p:
        blk = _load_block(p)
        n = p.n_points
        xyz = p.read("points")["xyz"]
        p.keep_point_chunks(1 << 30, 1 << 30)
        whole = PointChunk(p, 0, n // 2, xyz[:n // 2], blk.camera, blk.cam_sigma, blk.frame)
        assert list(p.point_chunks) == [(0, n // 2)]
        rng = np.random.default_rng(0)
        cases = [(0, n // 2), (3, 4), (0, 1), (n // 2 - 1, n // 2), (5, 5)]
        cases += [tuple(sorted(rng.integers(0, n // 2 + 1, 2))) for _ in range(20)]
        for a, b in cases:
            part = PointChunk(p, a, b, xyz[a:b], blk.camera, blk.cam_sigma, blk.frame)
            fresh = normals._chunk_arrays(p, a, b, blk.camera, blk.cam_sigma, blk.frame)
            got = (part.o0, part.o1, part.kind, part.ctrl, part.csig, part.rot,
                   part.pt_start, part.nobs, part.smax, part.smin, part.active,
                   part.obs_station, part.obs_xy, part.obs_sigma, part.obs_active)
            if b > a:
                for x, y in zip(got, fresh[:-1]):
                    np.testing.assert_array_equal(x, y)
                assert np.shares_memory(part.obs_xy, whole.obs_xy)
            assert part.max_rays >= fresh[-1]
        assert list(p.point_chunks) == [(0, n // 2)]   # (parts are not kept again)
        # beyond the kept chunk, or for another camera table: read afresh
        other = PointChunk(p, n // 2 - 1, n // 2 + 1, xyz[n // 2 - 1:n // 2 + 1], blk.camera,
                           blk.cam_sigma, blk.frame)
        assert not np.shares_memory(other.obs_xy, whole.obs_xy)
        cams = blk.camera.copy()
        again = PointChunk(p, 1, 3, xyz[1:3], cams, blk.cam_sigma, blk.frame)
        assert not np.shares_memory(again.obs_xy, whole.obs_xy)


def _two_rays_of_one_photo(path, every=3):
    """Every ``every``-th point not control measured twice on its first photo (the second
    mark 2 um away): two active rays of one station, the case the Schur update adds both
    ways."""
    rec = read_records(path)
    ob = rec["observations"]
    pass_pt = np.flatnonzero(rec["points"]["kind"] != KIND_CONTROL)[::every]
    assert len(pass_pt) > 0
    first = np.searchsorted(ob["point"], pass_pt)   # (sorted by point)
    extra = ob[first].copy()
    extra["x"] += 0.002
    rec["observations"] = np.insert(ob, first + 1, extra)
    rewrite(path, rec)
    return len(first)


def test_two_rays_of_one_photo_reduce_as_dense(small_block, tmp_path):
    """The unrolled 6-parameter build (:func:`sapgo.normals._schur6`) with two rays of one
    photo against the dense reduction."""
    assert _two_rays_of_one_photo(small_block) > 0
    order_project(small_block)
    m_ref, d_ref = dense(small_block)
    m, d, _ = streamed(small_block, tmp_path)
    scale = np.abs(np.diag(m_ref))
    assert (np.abs(m - m_ref) <= 1e-9 * np.sqrt(np.outer(scale, scale))).all()
    np.testing.assert_allclose(d, d_ref, rtol=1e-8, atol=1e-9 * np.abs(d_ref).max())


def test_two_rays_of_one_photo_tree_equals_band(small_block, tmp_path):
    """The tree's fronts (:func:`sapgo.solve.fronts._schur_blocks6`) with two rays of one
    photo: the same adjustment as the band's."""
    import shutil

    import sapgo

    _two_rays_of_one_photo(small_block)
    tree = tmp_path / "tree.h5"
    shutil.copy(small_block, tree)
    tight = dict(tol_position=1e-9, tol_angle=1e-11, progress=False)
    band = sapgo.adjust(small_block, sapgo.Options(solver="band", **tight))
    tr = sapgo.adjust(tree, sapgo.Options(solver="tree", **tight))
    assert tr.solver == "tree" and band.solver == "band"
    assert abs(tr.sigma0 - band.sigma0) <= 1e-9 * band.sigma0
    with Project(small_block) as a, Project(tree) as b:
        ia, ib = np.argsort(a.read_field("points", "id")), np.argsort(b.read_field("points", "id"))
        xa = a.solution("point_corr")[ia] + a.read_field("points", "xyz")[ia]
        xb = b.solution("point_corr")[ib] + b.read_field("points", "xyz")[ib]
        sa, sb = a.solution("point_sigma")[ia], b.solution("point_sigma")[ib]
        ja = np.argsort(a.read_field("stations", "id"))
        jb = np.argsort(b.read_field("stations", "id"))
        ea, eb = a.solution("station_sigma")[ja], b.solution("station_sigma")[jb]
    np.testing.assert_allclose(xb, xa, rtol=0, atol=1e-7)
    # the precision comes from the normal matrix itself (a wrong one still converges)
    np.testing.assert_allclose(sb, sa, rtol=1e-8)
    np.testing.assert_allclose(eb, ea, rtol=1e-8)


@pytest.mark.parametrize("case", ["controlled", "bal_free_network", "self_calibration"])
def test_rotations_carried_in_the_orientation_rows_change_no_bit(tmp_path, small_block, case,
                                                                 monkeypatch):
    """The kernels take each station's rotation matrix from its orientation row
    (geometry.with_rotations) instead of six sines and cosines at every ray: every number
    the adjustment writes -- orientations, points, residuals, precision, quality -- is bit
    for bit that of the rows without them (ROTATION_STATIONS 0), on a controlled block with
    precision, a BAL free network with radial distortion (Levenberg-Marquardt, the
    S-transform) and a self-calibration (the border's partials)."""
    import shutil

    import h5py

    import sapgo
    from sapgo import geometry
    from sapgo.formats.bal import import_bal

    if case == "bal_free_network":
        src = tmp_path / "d.h5"
        import_bal(Path(__file__).parent / "data" / "dubrovnik-3-7-pre.txt.gz", src,
                   intrinsics="fixed")
        opts = Options(progress=False)
    else:
        src = small_block
        opts = Options(progress=False, calibrate=("f", "k1") if case == "self_calibration"
                       else ())
    out = {}
    for limit in (geometry.ROTATION_STATIONS, 0):
        monkeypatch.setattr(geometry, "ROTATION_STATIONS", limit)
        path = tmp_path / f"run{limit}.h5"
        shutil.copy(src, path)
        s = sapgo.adjust(path, opts)
        with h5py.File(path, "r") as f:   # (the report apart: its timings and path differ)
            out[limit] = {k: f["solution"][k][()] for k in f["solution"] if k != "report"}
        out[limit].update(sigma0=s.sigma0, cost=s.final_cost,
                          log=[r["cost"] for r in s.iteration_log])
    with_rot, bare = out.values()
    assert with_rot.keys() == bare.keys() and len(bare) > 5
    for k in bare:
        np.testing.assert_array_equal(with_rot[k], bare[k], err_msg=k)
