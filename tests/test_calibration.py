"""Self-calibration of shared cameras: a border of camera parameters around the band."""

import os
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest
from conftest import assert_one_line_error, read_records, rewrite, run_cli

import naive
import sapgo
from sapgo.solve.band import (
    BandSolver,
    BorderPivotError,
    border_back_substitute,
    border_solve,
    dense_to_band,
)
from sapgo.apsets import EBNER, GRUEN, N_TERMS
from sapgo.geometry import (
    AP0,
    AP_BASE,
    AP_SET,
    BACKWARD,
    CALIBRATION_FIELDS,
    FORWARD,
    N_CALIBRATION,
    N_CAMERA,
    apply_calibration,
    camera_array,
    camera_partials,
    observed,
    project,
)
from sapgo.project import CONTROL_MASK, Project

CALIB = ("f", "x0", "y0", "k1", "k2", "p1", "p2")
TIGHT = dict(tol_position=1e-9, tol_angle=1e-11, max_iterations=40, progress=False)


@pytest.mark.parametrize("model", [FORWARD, BACKWARD])
@pytest.mark.parametrize("ap_set", [0, EBNER, GRUEN])
def test_camera_partials_equal_central_differences(model, ap_set):
    """Every border parameter's partial of an observation's residual (computed minus
    observed, the backward model's observation corrected at the measurement) against
    central differences of the residual, affinity and shear included, and the coefficients
    of Ebner's and Gruen's additional-parameter sets (with coefficients of a few um)."""
    eo = np.array([0.02, -0.03, 0.5, 100.0, 200.0, 3000.0])
    c = np.zeros(N_CAMERA)
    c[:10] = 152.0, 0.01, -0.02, 1e-5, -2e-9, 3e-13, 1e-5, -2e-5, 2e-4, -3e-4
    c[10] = model
    if ap_set:
        c[AP_SET], c[AP_BASE] = ap_set, 60.0
        n = int(N_TERMS[ap_set])
        c[AP0:AP0 + n] = np.random.default_rng(ap_set).normal(0.0, 3e-3, n)
    e = np.zeros((2, N_CALIBRATION))

    def resid(cam, xyz, o):
        x, y = project(eo, xyz, cam)
        return np.array([x, y]) - np.array(observed(o[0], o[1], cam))

    for xyz, o in (([400.0, -100.0, 150.0], (12.5, -7.25)), ([-900.0, 700.0, -50.0],
                                                           (-40.0, 35.0))):
        xyz = np.array(xyz)
        assert camera_partials(eo, xyz, c, e, *o)
        h = 1e-6
        num = np.zeros((2, N_CALIBRATION))
        for i in range(N_CALIBRATION):
            d = np.zeros(N_CALIBRATION)
            d[i] = h
            num[:, i] = (resid(apply_calibration(c, d), xyz, o)
                         - resid(apply_calibration(c, -d), xyz, o)) / (2 * h)
        np.testing.assert_allclose(e, num, rtol=1e-6, atol=1e-8)


def random_bordered(n_st=40, bw=4, kb=6, ng=5, seed=1):
    rng = np.random.default_rng(seed)
    n = n_st * kb
    a = np.zeros((n + ng, n + ng))
    for i in range(n_st):
        for j in range(i, min(n_st, i + bw)):
            blk = rng.normal(size=(kb, kb))
            a[i * kb:(i + 1) * kb, j * kb:(j + 1) * kb] = blk
            a[j * kb:(j + 1) * kb, i * kb:(i + 1) * kb] = blk.T
    a[:n, :n] = 0.5 * (a[:n, :n] + a[:n, :n].T)
    a[:n, n:] = rng.normal(size=(n, ng))
    a[n:, :n] = a[:n, n:].T
    c = rng.normal(size=(ng, ng))
    a[n:, n:] = c + c.T
    a += np.eye(n + ng) * (np.abs(a).sum(axis=1).max() + 1)
    return a, rng.normal(size=n + ng)


@pytest.mark.parametrize("chunk_rows", [1, 3, 7, 100])
def test_bordered_band_equals_the_dense_solve(chunk_rows):
    """The band factored as always, the border solved after it (W = U'^-1 B streamed, the
    dense Schur complement): the same solution, inverse border block and x'b as a dense
    solve of the whole matrix."""
    n_st, bw, kb, ng = 40, 4, 6, 5
    n = n_st * kb
    a, b = random_bordered(n_st, bw, kb, ng)
    x = np.linalg.solve(a, b)
    fac, y = np.zeros((n_st, kb, kb * bw)), np.zeros((n_st, kb))
    solver = BandSolver(n_st, bw, fac, y, chunk_rows=chunk_rows)
    band = dense_to_band(a[:n, :n], bw)
    for i0 in range(0, n_st, 9):
        solver.feed(band[i0:i0 + 9], b[:n].reshape(n_st, kb)[i0:i0 + 9])
    border = a[:n, n:].reshape(n_st, kb, ng).copy()
    delta = solver.finish(border=(border, a[n:, n:], b[n:]))
    np.testing.assert_allclose(delta.ravel(), x[:n], rtol=0, atol=1e-13)
    np.testing.assert_allclose(solver.theta, x[n:], rtol=0, atol=1e-13)
    np.testing.assert_allclose(solver.border_cov, np.linalg.inv(a)[n:, n:], atol=1e-14)
    assert solver.y_norm2 + solver.border_decrease == pytest.approx(b @ x, rel=1e-12)
    # X = M^-1 B, streamed backwards: the border's share of the stations' covariances
    border_back_substitute(fac, border, n_st, bw, step=chunk_rows)
    xm = np.linalg.solve(a[:n, :n], a[:n, n:])
    np.testing.assert_allclose(border.reshape(n, ng), xm, rtol=0, atol=1e-14)
    inv = np.linalg.inv(a)
    np.testing.assert_allclose(-xm @ solver.border_cov, inv[:n, n:], atol=1e-14)
    np.testing.assert_allclose(np.linalg.inv(a[:n, :n]) + xm @ solver.border_cov @ xm.T,
                               inv[:n, :n], atol=1e-13)


def test_an_undeterminable_border_parameter_is_named():
    n_st, bw, kb, ng = 10, 3, 6, 2
    n = n_st * kb
    a, b = random_bordered(n_st, bw, kb, ng, seed=2)
    a[n + 1, :] = a[n, :]  # border column 1 repeats column 0: S is singular there
    a[:, n + 1] = a[:, n]
    fac, y = np.zeros((n_st, kb, kb * bw)), np.zeros((n_st, kb))
    solver = BandSolver(n_st, bw, fac, y)
    solver.feed(dense_to_band(a[:n, :n], bw), b[:n].reshape(n_st, kb))
    with pytest.raises(BorderPivotError) as exc:
        solver.finish(border=(a[:n, n:].reshape(n_st, kb, ng).copy(), a[n:, n:], b[n:]))
    assert exc.value.index == 1
    with pytest.raises(BorderPivotError):
        border_solve(fac, y, np.zeros((n_st, kb, 1)), np.zeros((1, 1)), np.zeros(1), n_st, bw)


@pytest.fixture
def miscalibrated(block_cache, tmp_path):
    """A 2 x 6 block whose images carry distortion while its camera says f + 0.03 mm and no
    distortion at all."""
    dist = (-2.0e-8, 3.0e-13, 0.0, 1.5e-6, -1.0e-6)
    path = tmp_path / "mis.h5"
    shutil.copy(block_cache("small-dist-calib", strips=2, photos_per_strip=6, control_points=6,
                            distortion=dist), path)
    rec = read_records(path)
    rec["cameras"]["focal_length"] += 0.03
    rec["cameras"][["k1", "k2", "p1", "p2"]] = (0.0, 0.0, 0.0, 0.0)
    rewrite(path, rec)
    return path


_DENSE = {}


def dense_calibrated(path, calibrate):
    """The dense least-squares solution (computed once per block and parameter set)."""
    rec = read_records(path)
    key = (rec["observations"].tobytes(), rec["cameras"].tobytes(), tuple(calibrate))
    if key not in _DENSE:
        _DENSE[key] = _dense_calibrated(rec, calibrate)
    return _DENSE[key]


def _dense_calibrated(rec, calibrate):
    st, pt, ob = rec["stations"], rec["points"], rec["observations"]
    cam = rec["cameras"][0]
    return naive.dense_bundle_adjustment(
        st["eo"], pt["xyz"], cam["focal_length"], ob["station"], ob["point"],
        np.column_stack([ob["x"], ob["y"]]), ob["sigma"], CONTROL_MASK[pt["kind"]].astype(bool),
        pt["control"], pt["control_sigma"], iterations=40,
        dist=tuple(float(cam[k]) for k in ("k1", "k2", "k3", "p1", "p2")), calibrate=calibrate)


def adjusted(path):
    with Project(path) as p:
        st, pt = p.read("stations"), p.read("points")
        eo = st["eo"] + p.solution("station_corr")
        xyz = pt["xyz"] + p.solution("point_corr")
        cam = (camera_array(p.cameras()) + p.solution("camera_corr"))[0][:10]
    return eo[np.argsort(st["id"])], xyz[np.argsort(pt["id"])], cam


@pytest.mark.parametrize("method", ["gauss-newton", "levenberg-marquardt"])
def test_self_calibration_equals_dense_least_squares(miscalibrated, method):
    """f, principal point, radial and decentring distortion adjusted with the block: the same
    orientations, points, camera, sigma0 and camera precision as a dense Gauss-Newton over
    every unknown (cameras in raw units), by both methods."""
    eo_r, xyz_r, s0_r, _, cam_r, q_r = dense_calibrated(miscalibrated, CALIB)
    s = sapgo.adjust(miscalibrated, sapgo.Options(method=method, calibrate=CALIB,
                                                  tol_cost=1e-15, **TIGHT))
    assert s.converged
    eo, xyz, cam = adjusted(miscalibrated)
    # Levenberg-Marquardt stops on the cost, which is flat along f against the flying
    # height in this small block: its parameters agree less closely than Gauss-Newton's
    tol = 1.0 if method == "gauss-newton" else 30.0
    assert np.abs(xyz - xyz_r).max() < 1e-6 * tol
    assert np.abs(eo[:, 3:] - eo_r[:, 3:]).max() < 1e-6 * tol
    assert np.abs(eo[:, :3] - eo_r[:, :3]).max() < 1e-9 * tol
    np.testing.assert_allclose(cam, cam_r, rtol=1e-7 * tol, atol=1e-16)
    assert s.sigma0 == pytest.approx(s0_r, rel=1e-8)
    assert s.redundancy == s.to_dict()["redundancy"]
    rows = {r["parameter"]: r for r in s.calibration}
    assert list(rows) == list(CALIB)
    idx = [CALIBRATION_FIELDS.index(k) for k in CALIB]
    for k, i, q in zip(CALIB, idx, q_r):
        assert rows[k]["adjusted"] == pytest.approx(cam_r[i], rel=1e-7 * tol, abs=1e-16)
        # (after Levenberg-Marquardt the precision comes from undamped normals built again)
        assert rows[k]["sigma"] == pytest.approx(s0_r * np.sqrt(q), rel=1e-5 * tol)
    # the model fits better: sigma0 well below the uncalibrated block's (1.20 against 1.69)
    held = miscalibrated.with_name("held.h5")
    rec = read_records(miscalibrated)
    rewrite(held, rec)
    assert sapgo.adjust(held, sapgo.Options(**TIGHT)).sigma0 > 1.3 * s.sigma0


def test_calibrate_from_the_command_line_and_bad_options(miscalibrated, tmp_path, capsys):
    import json

    code, out, err = run_cli(capsys, "adjust", miscalibrated, "--calibrate", "f,k1",
                             "--no-progress", "--json", tmp_path / "r.json")
    assert code == 0, err
    assert "self-calibration" in out and "camera 1  f:" in out
    rep = json.loads((tmp_path / "r.json").read_text())
    assert [r["parameter"] for r in rep["calibration"]] == ["f", "k1"]
    assert rep["precision"]["stations"]["X_m"]["max"] > 0
    with Project(miscalibrated) as p:
        corr = p.solution("camera_corr")[0]
    assert corr[0] == pytest.approx(rep["calibration"][0]["correction"])
    assert corr[1] == 0.0 and corr[2] == 0.0  # x0, y0 held
    before = open(miscalibrated, "rb").read()
    for args, words in [(["--calibrate", "f,zoom"], "'zoom'"),
                        (["--calibrate", "f", "--calibrate-cameras", "1,1"], "named twice"),
                        (["--calibrate", "f", "--calibrate-cameras", "7"], "camera id 7"),
                        (["--calibrate-cameras", "1"], "without calibrate"),
                        (["--calibrate", "f,f"], "named twice"),
                        (["--calibrate", "f", "--calibrate-cameras", "x"], "integer ids"),
                        (["--calibrate", "f,x0", "--calibrate-per-photo", "x0"],
                         "x0 is named twice"),
                        (["--calibrate-per-photo", "zoom"], "per photo of 'zoom'")]:
        code, out, err = run_cli(capsys, "adjust", miscalibrated, "--no-progress", *args)
        assert_one_line_error(code, err, words)
    assert open(miscalibrated, "rb").read() == before


RUN = ("import sys, sapgo; sapgo.adjust(sys.argv[1], sapgo.Options(progress=False, "
       "chunk_points=7, chunk_rows=2, max_iterations=30, calibrate=('f', 'k1', 'p1'), "
       "calibrate_per_photo=tuple(sys.argv[2:]), work_files='always'))")


@pytest.mark.parametrize("fault, per_photo", [("solve:3", ()), ("checkpoint:4", ()),
                                              ("checkpoint:4", ("x0", "y0"))])
def test_a_killed_self_calibration_resumes_to_the_same_result(miscalibrated, tmp_path, fault,
                                                              per_photo):
    ref = tmp_path / "ref.h5"
    shutil.copy(miscalibrated, ref)
    subprocess.run([sys.executable, "-c", RUN, str(ref), *per_photo], check=True, timeout=300)
    r = subprocess.run([sys.executable, "-c", RUN, str(miscalibrated), *per_photo],
                       timeout=300, env=dict(os.environ, SAPGO_FAULT=fault),
                       capture_output=True, text=True)
    assert r.returncode == -signal.SIGKILL, r.stderr
    s = sapgo.adjust(miscalibrated, sapgo.Options(progress=False, chunk_points=7, chunk_rows=2,
                                                  max_iterations=30, resume=True,
                                                  calibrate=("f", "k1", "p1"),
                                                  calibrate_per_photo=per_photo))
    assert s.resumed_from_iteration is not None
    a, b = adjusted(ref), adjusted(miscalibrated)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)
    with Project(ref) as p, Project(miscalibrated) as q:
        np.testing.assert_array_equal(p.solution("photo_camera_corr"),
                                      q.solution("photo_camera_corr"))


def test_precision_with_self_calibration_equals_the_dense_inverse(miscalibrated):
    """With the border: station, point and camera standard deviations and the observations'
    redundancy numbers equal those of the inverse of the full normal matrix over stations,
    points and camera parameters, computed densely (the border's rank-g term X S^-1 X' in
    the stations, V' S^-1 V in the points, and E, X, V in every observation)."""
    from sapgo.work import work_path
    from sapgo.rawfile import RawArray

    calib = ("f", "x0", "y0", "k1", "p1", "p2")
    rec = read_records(miscalibrated)  # one control point fixed (sigma 0), one height fixed
    ctrl = np.flatnonzero(rec["points"]["kind"] == 1)
    rec["points"]["control_sigma"][ctrl[0]] = 0.0
    rec["points"]["control_sigma"][ctrl[1], 2] = 0.0
    rewrite(miscalibrated, rec)
    # data snooping runs the precision sweep twice (after the last test and at the end):
    # the second must see the same border (W, not yet X)
    summary = sapgo.adjust(miscalibrated, sapgo.Options(calibrate=calib, keep_scratch=True,
                                                        snooping=True, **TIGHT))
    assert summary.converged and summary.precision is not None and not summary.rejected
    rec = read_records(miscalibrated)
    st, pt, ob = rec["stations"], rec["points"], rec["observations"]
    with Project(miscalibrated) as p:
        eo = st["eo"] + p.solution("station_corr")
        xyz = pt["xyz"] + p.solution("point_corr")
        cam = (camera_array(p.cameras()) + p.solution("camera_corr"))[0][:10]
        ssig, psig = p.solution("station_sigma"), p.solution("point_sigma")
    quality = RawArray(work_path(miscalibrated) / "quality.bin", (len(ob), 7), mode="r")[:]
    ns, npnt = len(st), len(pt)
    idx = [CALIBRATION_FIELDS.index(k) for k in calib]
    nu = 6 * ns + 3 * npnt + len(idx)

    def proj(e, x, c):
        return naive.project(e, x, c[0], c[1], c[2], dist=tuple(c[3:]))

    rows = []
    for i in range(len(ob)):
        s, j = ob["station"][i], ob["point"][i]
        a, b = naive.jacobian_complex_step(eo[s], xyz[j], cam[0], cam[1], cam[2],
                                           dist=tuple(cam[3:]))
        row = np.zeros((2, nu))
        row[:, 6 * s:6 * s + 6] = a
        row[:, 6 * ns + 3 * j:6 * ns + 3 * j + 3] = b
        for q, k in enumerate(idx):
            c = cam.astype(complex)
            h = 1e-30 * max(abs(cam[k]), 1e-30)
            c[k] += 1j * h
            row[:, 6 * ns + 3 * npnt + q] = proj(eo[s], xyz[j], c).imag / h
        rows.append(row / ob["sigma"][i])
    jac = np.concatenate(rows)
    n = jac.T @ jac
    mask = CONTROL_MASK[pt["kind"]].astype(bool)
    fixed = mask & (pt["control_sigma"] == 0)
    for j, k in zip(*np.nonzero(mask & ~fixed)):
        n[6 * ns + 3 * j + k, 6 * ns + 3 * j + k] += 1.0 / pt["control_sigma"][j, k] ** 2
    keep = np.ones(nu, bool)  # fixed components are no unknowns
    keep[6 * ns:6 * ns + 3 * npnt] = ~fixed.ravel()
    nk = n[np.ix_(keep, keep)]
    sc = 1.0 / np.sqrt(np.diag(nk))
    q = np.zeros((nu, nu))
    q[np.ix_(keep, keep)] = sc[:, None] * np.linalg.inv(nk * sc[:, None] * sc[None, :]) \
        * sc[None, :]
    jac[:, ~keep] = 0.0
    s0 = summary.sigma0
    dq = np.sqrt(np.diag(q))
    np.testing.assert_allclose(ssig, s0 * dq[:6 * ns].reshape(-1, 6), rtol=1e-6)
    np.testing.assert_allclose(psig, s0 * dq[6 * ns:6 * ns + 3 * npnt].reshape(-1, 3),
                               rtol=1e-6)
    got = {r["parameter"]: r["sigma"] for r in summary.calibration}
    for qq, k in enumerate(calib):
        assert got[k] == pytest.approx(s0 * dq[6 * ns + 3 * npnt + qq], rel=1e-6)
    r = np.zeros((len(ob), 3))
    for i in range(len(ob)):
        jj = jac[2 * i:2 * i + 2] * ob["sigma"][i]
        qvv = ob["sigma"][i] ** 2 * np.eye(2) - jj @ q @ jj.T
        r[i] = [qvv[0, 0], qvv[1, 1], qvv[0, 1]] / ob["sigma"][i] ** 2
    np.testing.assert_allclose(quality[:, :3], r, rtol=1e-5, atol=1e-8)
    # the redundancy numbers add up to the redundancy (control takes about none)
    assert r[:, :2].sum() == pytest.approx(summary.redundancy, abs=0.05)
    shutil.rmtree(work_path(miscalibrated), ignore_errors=True)


def test_data_snooping_with_self_calibration(block_cache, tmp_path):
    """A large blunder in a miscalibrated 9-point-pattern block: data snooping with the camera
    calibrated finds it (the redundancy numbers include the border) and nothing else."""
    dist = (-2.0e-8, 0.0, 0.0, 0.0, 0.0)
    path = tmp_path / "b.h5"
    shutil.copy(block_cache("calib-blunder", strips=3, photos_per_strip=8, control_points=8,
                            distortion=dist, blunders=1, blunder_size=(0.2, 0.2)), path)
    with Project(path, "r+") as p:  # the camera says: no distortion
        cams = p.file["cameras"][:]
        cams["k1"] = 0.0
        p.file["cameras"][:] = cams
        assert len(p.read("truth/blunders")) == 1
    s = sapgo.adjust(path, sapgo.Options(calibrate=("f", "k1"), snooping=True, progress=False,
                                         max_iterations=30))
    assert s.converged
    assert s.blunder_check["planted"] == 1 and s.blunder_check["found"] == 1
    assert s.blunder_check["false_rejections"] <= 1
    k1 = {r["parameter"]: r for r in s.calibration}["k1"]
    assert abs(k1["adjusted"] - dist[0]) < 3 * k1["sigma"]


def test_ordering_again_keeps_the_cameras_and_station_precision(miscalibrated):
    """Re-ordering an adjusted, self-calibrated project keeps /solution/camera_corr and the
    stations' standard deviations (moved with their stations)."""
    sapgo.adjust(miscalibrated, sapgo.Options(calibrate=("f", "k1"), progress=False))

    def by_id(path):
        with Project(path) as p:
            ids = p.read_field("stations", "id")
            return (p.solution("camera_corr"), p.solution("station_sigma")[np.argsort(ids)],
                    p.solution("station_corr")[np.argsort(ids)])

    before = by_id(miscalibrated)
    assert before[0][0, 0] != 0.0 and (before[1] > 0).all()
    sapgo.order_project(miscalibrated, "down_strip")
    for a, b in zip(before, by_id(miscalibrated)):
        np.testing.assert_array_equal(a, b)


def test_a_border_too_large_is_refused(miscalibrated, monkeypatch, capsys):
    """The border is dense: more global unknowns than MAX_BORDER are refused with advice."""
    monkeypatch.setattr(sys.modules["sapgo.adjust"], "MAX_BORDER", 4)
    code, out, err = run_cli(capsys, "adjust", miscalibrated, "--no-progress", "--calibrate",
                             "f,x0,y0,k1,k2")
    assert_one_line_error(code, err, "5 global unknowns (at most 4")


@pytest.fixture
def backward_block(block_cache, tmp_path):
    """The 2 x 6 block of :func:`miscalibrated` with an affinity and shear put into its
    measurements (b1 3e-4, b2 -2e-4), its camera of the backward model (PhotoModeler,
    DBAT): distortion, affinity and shear all unknown (zero), f 0.03 mm off."""
    dist = (-2.0e-8, 3.0e-13, 0.0, 1.5e-6, -1.0e-6)
    path = tmp_path / "back.h5"
    shutil.copy(block_cache("small-dist-calib", strips=2, photos_per_strip=6, control_points=6,
                            distortion=dist), path)
    rec = read_records(path)
    ob = rec["observations"]
    x, y = ob["x"].copy(), ob["y"].copy()
    ob["x"] = x + 3e-4 * x - 2e-4 * y
    cams = rec["cameras"]
    cams["focal_length"] += 0.03
    cams[["k1", "k2", "p1", "p2"]] = (0.0, 0.0, 0.0, 0.0)
    cams["distortion_model"] = BACKWARD
    rewrite(path, rec)
    return path


BACK_CALIB = ("f", "x0", "y0", "k1", "k2", "p1", "p2", "b1", "b2")


def test_self_calibration_of_the_backward_model_with_affinity_equals_dense_least_squares(
        backward_block):
    """The backward (correction) model with affinity and shear, self-calibrated with the
    block: the same orientations, points, camera, sigma0 and camera precision as a dense
    Gauss-Newton over every unknown of that model (tests/naive.py, camera partials by
    complex step); and it fits: the affinity put into the measurements comes back."""
    rec = read_records(backward_block)
    st, pt, ob = rec["stations"], rec["points"], rec["observations"]
    cam0 = rec["cameras"][0]
    eo_r, xyz_r, s0_r, _, cam_r, q_r = naive.dense_bundle_adjustment(
        st["eo"], pt["xyz"], cam0["focal_length"], ob["station"], ob["point"],
        np.column_stack([ob["x"], ob["y"]]), ob["sigma"],
        CONTROL_MASK[pt["kind"]].astype(bool), pt["control"], pt["control_sigma"],
        iterations=40, dist=(0.0,) * 7, calibrate=BACK_CALIB, model="backward")
    s = sapgo.adjust(backward_block, sapgo.Options(calibrate=BACK_CALIB, **TIGHT))
    assert s.converged
    eo, xyz, cam = adjusted(backward_block)
    eo_r, xyz_r = eo_r[np.argsort(st["id"])], xyz_r[np.argsort(pt["id"])]
    assert np.abs(xyz - xyz_r).max() < 1e-6
    assert np.abs(eo[:, 3:] - eo_r[:, 3:]).max() < 1e-6
    assert np.abs(eo[:, :3] - eo_r[:, :3]).max() < 1e-9
    np.testing.assert_allclose(cam, cam_r, rtol=1e-7, atol=1e-16)
    assert s.sigma0 == pytest.approx(s0_r, rel=1e-8)
    rows = {r["parameter"]: r for r in s.calibration}
    assert list(rows) == list(BACK_CALIB)
    for k, q in zip(BACK_CALIB, q_r):
        i = CALIBRATION_FIELDS.index(k)
        assert rows[k]["adjusted"] == pytest.approx(cam_r[i], rel=1e-7, abs=1e-16)
        assert rows[k]["sigma"] == pytest.approx(s0_r * np.sqrt(q), rel=1e-5)
    # the measurements' affinity is found (the correction undoes it: about -3e-4, +2e-4)
    assert rows["b1"]["adjusted"] == pytest.approx(-3e-4, abs=5 * rows["b1"]["sigma"])
    assert rows["b2"]["adjusted"] == pytest.approx(2e-4, abs=5 * rows["b2"]["sigma"])
    # the tree reaches the same solution
    tree = backward_block.with_name("tree.h5")
    rewrite(tree, read_records(backward_block))
    t = sapgo.adjust(tree, sapgo.Options(calibrate=BACK_CALIB, solver="tree", **TIGHT))
    assert t.sigma0 == pytest.approx(s.sigma0, rel=1e-9)
    np.testing.assert_allclose(adjusted(tree)[2], cam, rtol=1e-8, atol=1e-16)


def test_a_held_backward_camera_equals_its_corrected_measurements(backward_block, tmp_path):
    """Held, a backward camera's distortion corrects the measurements once and for all: the
    block adjusts to the same solution as its measurements corrected beforehand with a
    camera without distortion (what an import that applies the correction does)."""
    rec = read_records(backward_block)
    rec["cameras"][["k1", "k2", "p1", "p2", "b1", "b2"]] = (2e-8, -3e-13, -1.5e-6, 1e-6,
                                                             2e-4, -1e-4)
    rewrite(backward_block, rec)
    row = camera_array(rec["cameras"])[0]
    ob = rec["observations"]
    xy = np.array([observed(x, y, row) for x, y in zip(ob["x"], ob["y"])])
    ob["x"], ob["y"] = xy[:, 0], xy[:, 1]
    rec["cameras"][["k1", "k2", "p1", "p2", "b1", "b2", "distortion_model"]] = (0,) * 7
    plain = tmp_path / "plain.h5"
    rewrite(plain, rec)
    a = sapgo.adjust(backward_block, sapgo.Options(**TIGHT))
    b = sapgo.adjust(plain, sapgo.Options(**TIGHT))
    assert a.sigma0 == pytest.approx(b.sigma0, rel=1e-12)
    ea, xa, _ = adjusted(backward_block)
    eb, xb, _ = adjusted(plain)
    np.testing.assert_allclose(xa, xb, rtol=0, atol=1e-9)
    np.testing.assert_allclose(ea, eb, rtol=0, atol=1e-9)


def test_principal_points_per_photo_with_shared_focal_length_and_distortion(miscalibrated):
    """The principal point adjusted per photo (each photo's own x0, y0) while f and the
    distortion are shared by the camera's photos: the same orientations, points, cameras,
    sigma0 and precision as a dense Gauss-Newton with those unknowns; each photo's row is
    in /solution/photo_camera_corr, the report names the photos."""
    shared, own = ("f", "k1", "p1", "p2"), ("x0", "y0")
    rec = read_records(miscalibrated)
    st, pt, ob = rec["stations"], rec["points"], rec["observations"]
    eo_r, xyz_r, s0_r, _, cams_r, q_r = naive.dense_bundle_adjustment(
        st["eo"], pt["xyz"], rec["cameras"][0]["focal_length"], ob["station"], ob["point"],
        np.column_stack([ob["x"], ob["y"]]), ob["sigma"],
        CONTROL_MASK[pt["kind"]].astype(bool), pt["control"], pt["control_sigma"],
        iterations=40, dist=(0.0,) * 5, calibrate=shared, calibrate_per_photo=own)
    s = sapgo.adjust(miscalibrated, sapgo.Options(calibrate=shared, calibrate_per_photo=own,
                                                  **TIGHT))
    assert s.converged
    eo, xyz, cam = adjusted(miscalibrated)
    order_s, order_p = np.argsort(st["id"]), np.argsort(pt["id"])
    assert np.abs(xyz - xyz_r[order_p]).max() < 1e-6
    assert np.abs(eo[:, 3:] - eo_r[order_s, 3:]).max() < 1e-6
    assert np.abs(eo[:, :3] - eo_r[order_s, :3]).max() < 1e-9
    assert s.sigma0 == pytest.approx(s0_r, rel=1e-8)
    with Project(miscalibrated) as p:
        rows = camera_array(p.cameras())[p.read_field("stations", "camera")] \
            + p.solution("photo_camera_corr")
        ids = p.read_field("stations", "id")
    rows = rows[np.argsort(ids)][:, :10]
    np.testing.assert_allclose(rows, cams_r[order_s], rtol=1e-7, atol=1e-12)
    # the shared fields are the camera's (camera_corr), alike in every photo's row
    for k in shared:
        i = CALIBRATION_FIELDS.index(k)
        assert cam[i] == pytest.approx(cams_r[0, i], rel=1e-7)
    rep = s.calibration
    assert [r["parameter"] for r in rep[:len(shared)]] == list(shared)
    per = [r for r in rep if "photo" in r]
    assert len(per) == len(own) * len(st) and {r["photo"] for r in per} == set(st["id"])
    q_own = q_r[len(shared):].reshape(len(st), len(own))
    for r in per:
        s_rec = int(np.flatnonzero(st["id"] == r["photo"])[0])
        k = own.index(r["parameter"])
        assert r["adjusted"] == pytest.approx(cams_r[s_rec, CALIBRATION_FIELDS.index(
            r["parameter"])], abs=1e-9)
        assert r["sigma"] == pytest.approx(s0_r * np.sqrt(q_own[s_rec, k]), rel=1e-5)
    # the tree reaches the same solution
    tree = miscalibrated.with_name("tree.h5")
    rewrite(tree, read_records(miscalibrated))
    t = sapgo.adjust(tree, sapgo.Options(calibrate=shared, calibrate_per_photo=own,
                                         solver="tree", **TIGHT))
    assert t.sigma0 == pytest.approx(s.sigma0, rel=1e-9)
