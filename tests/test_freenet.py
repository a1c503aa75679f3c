"""A free network (issue 18): its solution and precision by inner constraints on the object
points equal a dense reference -- a dense Gauss-Newton under minimal constraints, moved onto
the approximations by a similarity (the least change of the points), and the inverse of
the bordered normal matrix ``[[N, G'], [G, 0]]`` (the pseudo-inverse in the points' norm)
-- on the band and on the tree."""

import importlib
import shutil

import h5py
import numpy as np
import pytest

import naive
import sapgo
import sapgo.freenet
from conftest import read_records, rewrite
from sapgo.geometry import attitude_jacobians
from sapgo.project import CONTROL_MASK, Project


def procrustes(y, x):
    """``(s, R, t)`` minimising ``sum |s R y_i + t - x_i|^2`` (Umeyama), written again."""
    my, mx = y.mean(axis=0), x.mean(axis=0)
    u, d, vt = np.linalg.svd((x - mx).T @ (y - my))
    e = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    r = u @ e @ vt
    s = np.trace(np.diag(d) @ e) / ((y - my) ** 2).sum()
    return s, r, mx - s * r @ my


def skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


@pytest.fixture(scope="module")
def free_block(tmp_path_factory, block_cache):
    """A 3 x 6 block whose points are all pass points, marked a free network."""
    src = block_cache("free", strips=3, photos_per_strip=6, control_points=4)
    path = tmp_path_factory.mktemp("free") / "free.h5"
    rec = read_records(src)
    rec["points"]["kind"] = 0
    rewrite(path, rec)
    with h5py.File(path, "r+") as f:
        f.attrs["datum"] = "free"
    return path, rec


@pytest.fixture(scope="module")
def reference(free_block):
    """The dense reference: the solution and the points' and photos' sigmas."""
    return dense_reference(free_block[1])


#: Self-calibration of a free network: radial and decentring distortion.
FREE_CALIB = ("k1", "p1", "p2")


@pytest.fixture(scope="module")
def reference_calibrated(free_block):
    """The dense reference with the camera's FREE_CALIB adjusted too."""
    return dense_reference(free_block[1], FREE_CALIB)


def dense_reference(rec, calibrate=()):
    """A dense Gauss-Newton under 7 fixed station parameters (``calibrate``: camera fields
    adjusted too), moved onto the approximations by a similarity, and the inverse of the
    bordered normal matrix of all unknowns (photos, points, camera) at the solution."""
    st, pt, ob = rec["stations"], rec["points"], rec["observations"]
    cam = rec["cameras"][0]
    f = cam["focal_length"]
    fixed = np.zeros((len(st), 6), bool)
    fixed[0] = True
    fixed[-1, 3] = True
    xy = np.column_stack([ob["x"], ob["y"]])
    out = naive.dense_bundle_adjustment(
        st["eo"], pt["xyz"], f, ob["station"], ob["point"], xy, ob["sigma"],
        CONTROL_MASK[pt["kind"]].astype(bool), pt["control"], pt["control_sigma"],
        iterations=50, fixed_station=fixed, calibrate=calibrate)
    eo, xyz, s0 = out[:3]
    row = out[4] if calibrate else np.array([f] + [0.0] * 9)
    cols = [naive.CAMERA_FIELDS.index(n) for n in calibrate]
    # the similarity onto the approximations, applied to the points and the photos
    s, r, t = procrustes(xyz, pt["xyz"])
    xyz = s * xyz @ r.T + t
    m = naive.rotation(eo[:, 0], eo[:, 1], eo[:, 2]).transpose(2, 0, 1) @ r.T
    opk = np.array([[np.arctan2(-q[2, 1], q[2, 2]), np.arcsin(q[2, 0]),
                     np.arctan2(-q[1, 0], q[0, 0])] for q in m])
    eo = np.column_stack([opk, s * eo[:, 3:6] @ r.T + t])
    # the dense normals at the solution: photos (rotation vector, centre), points
    ns, npt = len(st), len(pt)
    base = 6 * ns + 3 * npt
    jac = np.zeros((2 * len(ob), base + len(cols)))
    dist = tuple(row[3:])
    for i, (a, j) in enumerate(zip(ob["station"], ob["point"])):
        ja, jb = naive.jacobian_rotvec_complex_step(eo[a], xyz[j], row[0], row[1], row[2],
                                                    dist=dist)
        jac[2 * i:2 * i + 2, 6 * a:6 * a + 6] = ja / ob["sigma"][i]
        jac[2 * i:2 * i + 2, 6 * ns + 3 * j:6 * ns + 3 * j + 3] = jb / ob["sigma"][i]
        for q, k in enumerate(cols):   # the camera's columns by complex step
            c = row.astype(complex)
            c[k] += 1e-30j * max(abs(row[k]), 1e-30)
            d = naive.project(eo[a].astype(complex), xyz[j].astype(complex), c[0], c[1], c[2],
                              dist=tuple(c[3:])).imag / (1e-30 * max(abs(row[k]), 1e-30))
            jac[2 * i:2 * i + 2, base + q] = d / ob["sigma"][i]
    n = jac.T @ jac
    centre = xyz.mean(axis=0)
    g = np.zeros((7, n.shape[0]))   # inner constraints on the points: G = H_p'
    for j in range(npt):
        h = np.zeros((3, 7))
        h[:, :3] = np.eye(3)
        h[:, 3:6] = -skew(xyz[j] - centre)
        h[:, 6] = xyz[j] - centre
        g[:, 6 * ns + 3 * j:6 * ns + 3 * j + 3] = h.T
    hfull = g.T.copy()   # the null space: the points' rows and the photos' (not the camera's)
    for a in range(ns):
        hfull[6 * a:6 * a + 3, 3:6] = np.eye(3)
        hfull[6 * a + 3:6 * a + 6, :3] = np.eye(3)
        hfull[6 * a + 3:6 * a + 6, 3:6] = -skew(eo[a, 3:6] - centre)
        hfull[6 * a + 3:6 * a + 6, 6] = eo[a, 3:6] - centre
    big = np.block([[n, g.T], [g, np.zeros((7, 7))]])
    q = np.linalg.inv(big)[:n.shape[0], :n.shape[0]]
    qs = np.array([q[6 * a:6 * a + 6, 6 * a:6 * a + 6] for a in range(ns)])
    tj = np.zeros((ns, 6, 6))
    tj[:, :3, :3] = attitude_jacobians(eo[:, :3])
    tj[:, 3:, 3:] = np.eye(3)
    qs = tj @ qs @ tj.transpose(0, 2, 1)
    st_sig = s0 * np.sqrt(np.diagonal(qs, axis1=1, axis2=2))
    pt_sig = s0 * np.sqrt(np.diag(q)[6 * ns:base].reshape(npt, 3))
    return {"eo": eo, "xyz": xyz, "sigma0": s0, "station_sigma": st_sig,
            "point_sigma": pt_sig, "camera": row,
            "camera_sigma": s0 * np.sqrt(np.diag(q)[base:]),
            "null": np.abs(n @ hfull).max() / (np.abs(n).max() * np.abs(hfull).max())}


def compare_solution(run, rec, ref):
    """The adjusted project ``run``'s photos and points against the reference's (to 1e-6
    m); returns them with their sigmas and the orders that match them to the reference."""
    with Project(run) as p:
        sid = p.read_field("stations", "id")
        eo = p.read_field("stations", "eo") + p.solution("station_corr")
        ssig = p.solution("station_sigma")
        pid = p.read_field("points", "id")
        xyz = p.read_field("points", "xyz") + p.solution("point_corr")
        psig = p.solution("point_sigma")
    so, ro = np.argsort(sid), np.argsort(rec["stations"]["id"])
    po, rpo = np.argsort(pid), np.argsort(rec["points"]["id"])
    np.testing.assert_allclose(xyz[po], ref["xyz"][rpo], rtol=0, atol=1e-6)
    np.testing.assert_allclose(eo[so, 3:], ref["eo"][ro, 3:], rtol=0, atol=1e-6)
    return eo, ssig, xyz, psig, so, ro, po, rpo


@pytest.mark.parametrize("solver,keep", [("band", True), ("tree", True), ("band", False)])
def test_free_network_equals_the_dense_inner_constraints(free_block, reference, tmp_path,
                                                         solver, keep, monkeypatch):
    """... with the points' datum columns kept between the S-transform's passes, and
    worked out again in a third pass (``keep`` False: no room to keep them)."""
    path, rec = free_block
    assert reference["null"] < 1e-9   # (H spans the normals' null space)
    if not keep:
        monkeypatch.setattr(sapgo.freenet, "KEEP_COLUMNS_BYTES", 0)
    run = tmp_path / f"{solver}.h5"
    shutil.copy(path, run)
    s = sapgo.adjust(run, sapgo.Options(progress=False, solver=solver, tol_position=1e-10,
                                        tol_angle=1e-12, tol_cost=1e-14, max_iterations=60))
    assert s.converged and s.datum == "free" and s.precision is not None
    assert s.sigma0 == pytest.approx(reference["sigma0"], rel=1e-7)
    eo, ssig, xyz, psig, so, ro, po, rpo = compare_solution(run, rec, reference)
    turn = np.angle(np.exp(1j * (eo[so, :3] - reference["eo"][ro, :3])))   # (mod 2 pi)
    np.testing.assert_allclose(turn, 0.0, rtol=0, atol=1e-9)
    np.testing.assert_allclose(psig[po], reference["point_sigma"][rpo], rtol=1e-7)
    np.testing.assert_allclose(ssig[so], reference["station_sigma"][ro], rtol=1e-7)
    # the inner constraints hold: the points' sum, rotation and scale against their
    # approximations are those of the approximations
    x0 = rec["points"]["xyz"][rpo]
    d, v = xyz[po] - x0, xyz[po] - xyz[po].mean(axis=0)
    size = np.abs(v).max()
    assert np.abs(d.sum(axis=0)).max() < 1e-8 * size * len(d)
    assert np.abs(np.cross(v, d).sum(axis=0)).max() < 1e-8 * size ** 2 * len(d)
    assert abs((v * d).sum()) < 1e-8 * size ** 2 * len(d)


@pytest.mark.parametrize("solver", ["band", "tree"])
def test_self_calibrating_free_network_equals_the_dense_inner_constraints(
        free_block, reference_calibrated, tmp_path, solver):
    """A free network with its camera's radial and decentring distortion adjusted too: its
    solution, sigma0, the photos', points' and camera's precision equal the inverse of the
    bordered normal matrix of all unknowns, camera included, on the band and on the tree."""
    ref = reference_calibrated
    assert ref["null"] < 1e-9
    path, rec = free_block
    run = tmp_path / f"cal-{solver}.h5"
    shutil.copy(path, run)
    s = sapgo.adjust(run, sapgo.Options(progress=False, solver=solver, tol_position=1e-10,
                                        tol_angle=1e-12, tol_cost=1e-14, max_iterations=60,
                                        calibrate=FREE_CALIB))
    assert s.converged and s.datum == "free" and s.precision is not None
    assert s.sigma0 == pytest.approx(ref["sigma0"], rel=1e-7)
    eo, ssig, xyz, psig, so, ro, po, rpo = compare_solution(run, rec, ref)
    np.testing.assert_allclose(psig[po], ref["point_sigma"][rpo], rtol=1e-6)
    np.testing.assert_allclose(ssig[so], ref["station_sigma"][ro], rtol=1e-6)
    rows = {r["parameter"]: r for r in s.calibration}
    for name, sig in zip(FREE_CALIB, ref["camera_sigma"]):
        k = naive.CAMERA_FIELDS.index(name)
        assert rows[name]["adjusted"] == pytest.approx(ref["camera"][k], rel=1e-6,
                                                       abs=1e-6 * sig)
        assert rows[name]["sigma"] == pytest.approx(sig, rel=1e-6)


def test_free_network_of_the_minimal_constraints_has_the_same_shape(free_block, tmp_path):
    """The minimal constraints chosen are only the adjustment's: the residuals and sigma0
    are those of any datum (here the user's own 7 fixed parameters)."""
    path, rec = free_block
    st = rec["stations"]
    a, b = int(st["id"][0]), int(st["id"][-1])
    runs = {}
    for name, fix in (("inner", ()), ("fixed", (f"fix:{a}:all", f"fix:{b}:X"))):
        run = tmp_path / f"{name}.h5"
        shutil.copy(path, run)
        runs[name] = sapgo.adjust(run, sapgo.Options(progress=False, fix=fix,
                                                     tol_position=1e-10, tol_angle=1e-12,
                                                     tol_cost=1e-14, max_iterations=60))
        with Project(run) as p:
            runs[name + "_res"] = p.solution("residuals")
    assert runs["inner"].sigma0 == pytest.approx(runs["fixed"].sigma0, rel=1e-9)
    np.testing.assert_allclose(runs["inner_res"], runs["fixed_res"], rtol=0, atol=1e-9)


@pytest.mark.parametrize("options", [dict(snooping=True), dict(robust="huber"),
                                     dict(method="gauss-newton")])
def test_snooping_robust_and_gauss_newton_on_a_free_network(free_block, tmp_path, options):
    """With its datum held while it adjusts, a free network takes every method; the
    redundancy numbers are those of any datum."""
    path, _ = free_block
    run = tmp_path / "run.h5"
    shutil.copy(path, run)
    s = sapgo.adjust(run, sapgo.Options(progress=False, max_iterations=40, **options))
    assert s.converged and s.datum == "free" and s.precision is not None
    assert s.reliability["mean_redundancy_number"] == pytest.approx(
        s.redundancy / (2 * s.n_observations), rel=1e-3)


def _by_id(path):
    with Project(path) as p:
        pid = p.read_field("points", "id")
        xyz = p.read_field("points", "xyz") + p.solution("point_corr")
        sid = p.read_field("stations", "id")
        eo = p.read_field("stations", "eo") + p.solution("station_corr")
    return dict(zip(pid.tolist(), xyz)), dict(zip(sid.tolist(), eo))


def test_datum_free_makes_control_points_tie_points(block_cache, free_block, tmp_path):
    """``--datum free`` on a block with control is the free network of the same points
    (its control points tie points; here every one has two rays or more)."""
    src = block_cache("free", strips=3, photos_per_strip=6, control_points=4)
    free_path, _ = free_block
    runs = {}
    for name, path, datum in (("chosen", src, "free"), ("marked", free_path, None)):
        run = tmp_path / f"{name}.h5"
        shutil.copy(path, run)
        runs[name] = sapgo.adjust(run, sapgo.Options(progress=False, datum=datum,
                                                     tol_position=1e-10, tol_angle=1e-12,
                                                     tol_cost=1e-14, max_iterations=60))
        runs[name + "_xyz"], runs[name + "_eo"] = _by_id(run)
    assert runs["chosen"].datum == "free" and runs["chosen"].precision is not None
    assert runs["chosen"].sigma0 == pytest.approx(runs["marked"].sigma0, rel=1e-9)
    for i, x in runs["marked_xyz"].items():
        np.testing.assert_allclose(runs["chosen_xyz"][i], x, rtol=0, atol=1e-7)
    # every point of the generated block is control or check: now all check points
    assert runs["chosen"].check_points["n"] == runs["chosen"].n_points
    assert runs["marked"].check_points["n"] == 0


def _with_priors(rec, sigma_pos=0.05, sigma_ang=1e-4):
    """The records with a prior of every photo at its true orientation."""
    from sapgo.project import PRIOR_DTYPE

    st = rec["stations"]
    pr = np.zeros(len(st), PRIOR_DTYPE)
    pr["station"] = np.arange(len(st))
    pr["value"] = rec["truth"]["stations"]["eo"]
    pr["weight"] = np.diag([sigma_ang ** -2] * 3 + [sigma_pos ** -2] * 3)
    rec["station_priors"] = pr
    return rec


def test_datum_control_and_priors_leave_out_the_other(block_cache, tmp_path):
    """``--datum control`` is the block without its priors; ``--datum priors`` the block
    whose control points are check points."""
    src = block_cache("free", strips=3, photos_per_strip=6, control_points=4)
    rec = _with_priors(read_records(src))
    both = tmp_path / "both.h5"
    rewrite(both, rec)
    no_priors = tmp_path / "no_priors.h5"
    rewrite(no_priors, dict(read_records(src), station_priors=rec["station_priors"][:0]))
    checks = read_records(src)
    checks["station_priors"] = rec["station_priors"]
    checks["points"]["kind"][checks["points"]["kind"] == 1] = 4
    as_checks = tmp_path / "as_checks.h5"
    rewrite(as_checks, checks)
    tight = dict(progress=False, tol_position=1e-10, tol_angle=1e-12, max_iterations=40)
    for datum, ref_path in (("control", no_priors), ("priors", as_checks)):
        run = tmp_path / f"{datum}.h5"
        shutil.copy(both, run)
        s = sapgo.adjust(run, sapgo.Options(datum=datum, **tight))
        r = sapgo.adjust(ref_path, sapgo.Options(**tight))
        assert s.datum == datum
        assert s.sigma0 == pytest.approx(r.sigma0, rel=1e-9)
        assert s.redundancy == r.redundancy
        assert s.check_points["n"] == r.check_points["n"]
        xs, _ = _by_id(run)
        xr, _ = _by_id(ref_path)
        for i, x in xr.items():
            np.testing.assert_allclose(xs[i], x, rtol=0, atol=1e-7)


def test_datum_priors_without_priors_is_one_line(small_block, capsys):
    from conftest import assert_one_line_error, digest, run_cli

    before = digest(small_block)
    code, _, err = run_cli(capsys, "adjust", small_block, "--datum", "priors")
    assert_one_line_error(code, err, "--datum priors", "no station priors")
    assert digest(small_block) == before


def test_free_network_stations_precision_alone(free_block, tmp_path):
    """``--precision stations`` on a free network: the photos' inner-constraint standard
    deviations of the full pass, the same solution."""
    path, _ = free_block
    out = {}
    for mode in ("full", "stations"):
        run = tmp_path / f"{mode}.h5"
        shutil.copy(path, run)
        sapgo.adjust(run, sapgo.Options(progress=False, precision=mode, tol_cost=1e-14))
        with Project(run) as p:
            out[mode] = (p.solution("station_sigma"), p.solution("point_corr"))
    np.testing.assert_allclose(out["stations"][0], out["full"][0], rtol=1e-12)
    np.testing.assert_array_equal(out["stations"][1], out["full"][1])


def test_datum_free_leaves_out_a_one_ray_control_point(block_cache, tmp_path):
    """A control point that keeps one ray is determined by its control alone: with the
    control not used (``--datum free``) it is left out of the run, exactly as if it were
    not in the project (the same sigma0 and redundancy)."""
    src = block_cache("free", strips=3, photos_per_strip=6, control_points=4)
    rec = read_records(src)
    pt, ob = rec["points"], rec["observations"]
    j = int(np.flatnonzero(pt["kind"] == 1)[0])
    mine = np.flatnonzero(ob["point"] == j)
    one = tmp_path / "one.h5"
    rewrite(one, dict(rec, observations=np.delete(ob, mine[1:])))
    gone = read_records(one)
    keep = np.ones(len(gone["points"]), bool)
    keep[j] = False
    ob2 = gone["observations"][gone["observations"]["point"] != j]
    ob2["point"] -= (ob2["point"] > j)
    without = tmp_path / "without.h5"
    rewrite(without, dict(gone, points=gone["points"][keep], observations=ob2,
                          truth=dict(gone["truth"], points=gone["truth"]["points"][keep])))
    opts = dict(progress=False, datum="free", tol_cost=1e-14, max_iterations=60)
    a = sapgo.adjust(one, sapgo.Options(**opts))
    b = sapgo.adjust(without, sapgo.Options(**opts))
    assert a.redundancy == b.redundancy and a.n_points == b.n_points
    assert a.sigma0 == pytest.approx(b.sigma0, rel=1e-9)


@pytest.mark.parametrize("calibrate", [(), FREE_CALIB])
def test_first_inner_constraint_pass_on_threads_equals_one_thread(free_block, tmp_path,
                                                                  monkeypatch, calibrate):
    """The first S-transform pass sums the stations' (and the border's) right-hand sides
    in a copy for each thread (:func:`sapgo.normals.datum_sums_parallel`); with no room
    for the copies it runs on one thread: the same precision either way, to rounding."""
    path, _ = free_block
    out = {}
    for room in (sapgo.freenet.PRIVATE_SUMS_BYTES, 0):
        monkeypatch.setattr(sapgo.freenet, "PRIVATE_SUMS_BYTES", room)
        run = tmp_path / f"room{room}.h5"
        shutil.copy(path, run)
        sapgo.adjust(run, sapgo.Options(progress=False, calibrate=calibrate))
        with Project(run) as p:
            out[room] = (p.solution("station_sigma"), p.solution("point_sigma"))
    a, b = out.values()
    assert np.abs(a[0]).max() > 0 and np.abs(a[1]).max() > 0
    np.testing.assert_allclose(a[0], b[0], rtol=1e-10, atol=0)
    np.testing.assert_allclose(a[1], b[1], rtol=1e-10, atol=0)


@pytest.mark.parametrize("room, systems", [(None, True), (0, True), (None, False)])
def test_second_inner_constraint_pass_from_the_first_ones_rays(free_block, tmp_path,
                                                              monkeypatch, room, systems):
    """The S-transform's second pass works from the rays' ``Nbar`` and the points' factors
    its first pass kept (:func:`sapgo.normals.datum_columns_kept`, with the first pass on
    threads or, with no room for the copies, on one), and the first pass itself from the
    points' systems the precision pass's build kept (``systems``:
    :func:`sapgo.normals.datum_sums_kept`; without them it linearises the rays): the same
    arithmetic, so the same stations' and points' precision to the bit as the passes that
    linearise every ray again (nothing kept)."""
    if room is not None:
        monkeypatch.setattr(sapgo.freenet, "PRIVATE_SUMS_BYTES", room)
    if not systems:
        monkeypatch.setattr(importlib.import_module("sapgo.adjust"), "KEPT_SYSTEMS_BYTES", 0)
    path, _ = free_block
    calls, sums = [], []
    kept = sapgo.normals.datum_columns_kept
    monkeypatch.setattr(sapgo.normals, "datum_columns_kept",
                        lambda *a: calls.append(1) or kept(*a))
    for name in ("datum_sums_kept", "_datum_sums_kept"):
        fn = getattr(sapgo.normals, name)
        monkeypatch.setattr(sapgo.normals, name, lambda *a, fn=fn: sums.append(1) or fn(*a))
    out = {}
    for keep in (sapgo.freenet.KEEP_COLUMNS_BYTES, 0):
        monkeypatch.setattr(sapgo.freenet, "KEEP_COLUMNS_BYTES", keep)
        run = tmp_path / f"keep{keep}.h5"
        shutil.copy(path, run)
        sapgo.adjust(run, sapgo.Options(progress=False))
        with Project(run) as p:
            out[keep] = (p.solution("station_sigma"), p.solution("point_sigma"))
        assert bool(calls) == bool(keep)
        assert bool(sums) == bool(keep and systems)
        calls.clear()
        sums.clear()
    a, b = out.values()
    assert np.abs(a[0]).max() > 0 and np.abs(a[1]).max() > 0
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
