"""Collinearity kernels against the plain-numpy reference and finite differences."""

import numpy as np
import pytest

import naive
from sapgo.geometry import (
    BACKWARD,
    MODEL,
    brown,
    FORWARD,
    N_CAMERA,
    camera_array,
    distortion,
    intersect,
    linearize,
    observed,
    plain_camera,
    project,
    rotation_matrix,
    turned,
    undistort,
)

#: Brown coefficients of a distorting lens: about 0.06 mm radial and 0.05 mm decentring
#: distortion at the corner of a 23 cm format.
DIST = (-2.0e-8, 3.0e-13, -1.0e-18, 1.5e-6, -1.0e-6)
#: ... with an affinity of 2e-4 and a shear of -3e-4 (0.02 mm and 0.03 mm at 10 cm).
DIST7 = DIST + (2.0e-4, -3.0e-4)


def camera(f=152.0, x0=0.0, y0=0.0, dist=DIST, model=FORWARD):
    """A kernel camera row: ``dist`` (k1, k2, k3, p1, p2[, b1, b2]) and the model."""
    row = np.zeros(N_CAMERA)
    row[:3 + len(dist)] = (f, x0, y0, *dist)
    row[10] = model
    return row


@pytest.fixture
def rng():
    return np.random.default_rng(7)


def random_ray(rng):
    eo = np.array([*rng.normal(0, 0.05, 3), *rng.normal(0, 100, 2), 3800.0])
    eo[2] += rng.choice([0.0, np.pi])
    xyz = np.array([*rng.normal(0, 1500, 2), rng.normal(300, 100)])
    return eo, xyz


def test_rotation_is_orthonormal_and_matches_reference(rng):
    for _ in range(20):
        w, p, k = rng.uniform(-np.pi, np.pi, 3)
        m = rotation_matrix(w, p, k)
        np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(m) == pytest.approx(1.0)
        np.testing.assert_allclose(m, naive.rotation(w, p, k), atol=1e-15)


@pytest.mark.parametrize("dist", [None, DIST, DIST7])
def test_projection_matches_reference(rng, dist):
    c = camera(152.0, 0.01, -0.02, dist or (0.0,) * 5)
    for _ in range(20):
        eo, xyz = random_ray(rng)
        x, y = project(eo, xyz, c)
        np.testing.assert_allclose([x, y], naive.project(eo, xyz, 152.0, 0.01, -0.02, dist),
                                   rtol=0, atol=1e-12)


@pytest.mark.parametrize("dist", [None, DIST, DIST7])
def test_partials_against_complex_step_and_finite_differences(rng, dist):
    c = camera(152.0, 0.02, -0.01, dist or (0.0,) * 5)
    a = np.empty((2, 6))
    b = np.empty((2, 3))
    for _ in range(50):
        eo, xyz = random_ray(rng)
        x, y, w = linearize(eo, xyz, c, a, b)
        assert w < 0  # the point is in front of the camera
        np.testing.assert_allclose([x, y], naive.project(eo, xyz, 152.0, 0.02, -0.01, dist),
                                   atol=1e-12)
        ac, bc = naive.jacobian_rotvec_complex_step(eo, xyz, 152.0, 0.02, -0.01, dist=dist)
        np.testing.assert_allclose(a, ac, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(b, bc, rtol=1e-10, atol=1e-14)
        # central finite differences, steps scaled to the parameter; the attitude turned
        # by the rotation vector as the adjustment turns it (geometry.turned)
        p = np.concatenate([eo, xyz])
        steps = np.array([1e-6] * 3 + [1e-3] * 6)
        fd = np.zeros((2, 9))
        for k in range(9):
            hi, lo = p.copy(), p.copy()
            if k < 3:
                t = np.zeros(3)
                t[k] = steps[k]
                hi[:3], lo[:3] = turned(eo[:3], t)[0], turned(eo[:3], -t)[0]
            else:
                hi[k] += steps[k]
                lo[k] -= steps[k]
            fd[:, k] = (np.array(project(hi[:6], hi[6:], c))
                        - np.array(project(lo[:6], lo[6:], c))) / (2 * steps[k])
        np.testing.assert_allclose(np.hstack([a, b]), fd, rtol=1e-6, atol=1e-9)


@pytest.mark.parametrize("dist", [DIST, DIST7])
def test_distortion_jacobian_and_inverse(rng, dist):
    """The distortion's Jacobian (not symmetric with affinity and shear) against complex
    steps; undistort inverts it to 1e-12 mm over the whole format."""
    c = camera(dist=dist)
    h = 1e-30
    for xi, yi in rng.uniform(-115, 115, (200, 2)):
        dx, dy, j00, j01, j10, j11 = distortion(xi, yi, c)

        def warp(u, v):
            du, dv = naive._polynomial(u, v, dist)
            return u + du, v + dv

        wx, wy = warp(xi, yi)
        assert (xi + dx, yi + dy) == pytest.approx((wx, wy), abs=1e-13)
        cx = warp(xi + 1j * h, yi)
        cy = warp(xi, yi + 1j * h)
        np.testing.assert_allclose([[j00, j01], [j10, j11]],
                                   [[cx[0].imag / h, cy[0].imag / h],
                                    [cx[1].imag / h, cy[1].imag / h]], rtol=1e-12, atol=1e-15)
        ux, uy, ok = undistort(c[1] + wx, c[2] + wy, c)
        assert ok
        assert abs(ux - xi) < 1e-12 and abs(uy - yi) < 1e-12


def test_the_backward_model_corrects_the_measurement(rng):
    """A backward camera projects the ideal point (its partials those of a camera without
    distortion), fits it to the measurement corrected at the measurement (as the reference
    ``naive.corrected``), and its 'undistorted' point is that corrected measurement."""
    back = camera(152.0, 0.02, -0.01, DIST7, BACKWARD)
    ideal = camera(152.0, 0.02, -0.01, (0.0,) * 7)
    a, b, a0, b0 = (np.empty((2, 6)), np.empty((2, 3)), np.empty((2, 6)), np.empty((2, 3)))
    for _ in range(20):
        eo, xyz = random_ray(rng)
        assert project(eo, xyz, back) == project(eo, xyz, ideal)
        x, y, w = linearize(eo, xyz, back, a, b)
        assert (x, y, w) == linearize(eo, xyz, ideal, a0, b0)
        np.testing.assert_array_equal(a, a0)
        np.testing.assert_array_equal(b, b0)
        m = rng.uniform(-110, 110, 2)
        ref = naive.corrected(m, 0.02, -0.01, DIST7)
        np.testing.assert_allclose(observed(m[0], m[1], back), ref, rtol=0, atol=1e-13)
        assert observed(m[0], m[1], ideal) == (m[0], m[1])
        ux, uy, ok = undistort(m[0], m[1], back)
        assert ok
        np.testing.assert_allclose([ux, uy], ref - [0.02, -0.01], rtol=0, atol=1e-13)


def test_intersection_recovers_the_point(rng):
    xyz = np.array([120.0, -340.0, 410.0])
    eos = np.array([[0.01, -0.02, 0.0, -1000.0, 0.0, 3800.0],
                    [-0.01, 0.015, 0.1, 1300.0, 50.0, 3810.0],
                    [0.0, 0.0, np.pi, 100.0, 2000.0, 3790.0]])
    for dist in (None, DIST):
        c = camera(152.0, 0.01, 0.02, dist or (0.0,) * 5)
        xy = np.array([naive.project(e, xyz, 152.0, 0.01, 0.02, dist) for e in eos])
        p, ok = intersect(eos, xy, np.array([c] * 3))
        assert ok
        np.testing.assert_allclose(p, xyz, atol=1e-6)
        _, ok = intersect(eos[:1], xy[:1], np.array([c]))
        assert not ok


def test_project_observations_and_intersect_points_kernels(rng):
    from sapgo.geometry import intersect_points, project_observations

    eo = np.array([[0.01, -0.01, 0.0, 0.0, 0.0, 3800.0],
                   [0.0, 0.02, 0.05, 2300.0, 0.0, 3810.0],
                   [-0.02, 0.0, np.pi, 1100.0, 2300.0, 3790.0]])
    xyz = np.array([[500.0, 300.0, 120.0], [1500.0, 900.0, 80.0], [1000.0, 1200.0, 200.0]])
    st = np.array([0, 1, 2, 0, 1, 1, 2])
    pt = np.array([0, 0, 0, 1, 1, 2, 2])
    cam_of = np.array([0, 1, 0])  # two cameras: plain, and a distorting one
    cams = np.array([plain_camera(152.0), camera(88.0, 0.03, -0.02)])
    out = np.empty((7, 2))
    project_observations(st, pt, eo, xyz, cam_of, cams, out)
    ref = np.array([naive.project(eo[s], xyz[p], 152.0) if cam_of[s] == 0 else
                    naive.project(eo[s], xyz[p], 88.0, 0.03, -0.02, DIST)
                    for s, p in zip(st, pt)])
    np.testing.assert_allclose(out, ref, atol=1e-12)
    got = np.empty((3, 3))
    ok = np.zeros(3, np.bool_)
    intersect_points(np.array([0, 3, 5]), np.array([3, 2, 2]), st, out, eo, cam_of, cams, got,
                     ok)
    assert ok.all()
    np.testing.assert_allclose(got, xyz, atol=1e-6)


def test_camera_array_takes_the_record_fields():
    from sapgo.project import CAMERA_DTYPE

    rec = np.zeros(2, CAMERA_DTYPE)
    rec["focal_length"] = [152.0, 88.0]
    rec["x0"], rec["y0"] = [0.01, 0.02], [-0.01, 0.0]
    for k, v in zip(("k1", "k2", "k3", "p1", "p2"), DIST):
        rec[k][1] = v
    np.testing.assert_array_equal(camera_array(rec), [plain_camera(152.0, 0.01, -0.01),
                                                      camera(88.0, 0.02, 0.0)])


def test_3x3_cholesky_solve_against_numpy(rng):
    from sapgo.normals import _chol3, _solve3

    for _ in range(20):
        a = rng.normal(0, 1, (3, 3))
        a = a @ a.T + 0.1 * np.eye(3)
        b = rng.normal(0, 1, 3)
        lo = np.zeros((3, 3))
        assert _chol3(a, lo)
        x = np.empty(3)
        _solve3(lo, b, x)
        np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-10)
    assert not _chol3(np.diag([1.0, 1.0, 0.0]), np.zeros((3, 3)))


def test_a_distortion_folding_beyond_the_format_is_caught():
    """Barrel distortion whose fold lies outside the format can still cover it: undistort
    must not return the mirrored root, and the camera check must refuse it."""
    from sapgo.project import CAMERA_DTYPE
    from sapgo.validate import _distortion_fold

    c = camera(152.0, 0.0, 0.0, (-1 / (3 * 170.0 ** 2), 0.0, 0.0, 0.0, 0.0))
    xi, yi, ok = undistort(110.0, 50.0, c)
    assert not ok or (xi * 110.0 + yi * 50.0 > 0)
    rec = np.zeros(1, CAMERA_DTYPE)[0]
    rec["focal_length"], rec["format_x"], rec["format_y"] = 152.0, 230.0, 230.0
    rec["k1"] = c[3]
    assert _distortion_fold(rec) is not None
    # a mild distortion passes
    rec["k1"] = DIST[0]
    assert _distortion_fold(rec) is None


@pytest.mark.parametrize("dist", [None, DIST])
def test_partials_by_the_photos_intrinsics_by_complex_step(rng, dist):
    """A 2x9 ``a`` gets d(x, y)/d(f, k1 f^2, k2 f^4) too (k3, p1, p2 held in their own
    units), equal to the complex-step derivative of the reference projection; and
    ``apply_intrinsics`` moves a camera row along exactly those parameters."""
    from sapgo.geometry import apply_intrinsics

    d5 = dist or (0.0,) * 5
    c = camera(152.0, 0.02, -0.01, d5)
    a9 = np.empty((2, 9))
    a6 = np.empty((2, 6))
    b = np.empty((2, 3))
    h = 1e-30

    def proj(fc, k1n, k2n, eo, xyz):
        k1, k2 = k1n / fc ** 2, k2n / fc ** 4
        return naive.project(eo, xyz, fc, 0.02, -0.01, (k1, k2, *d5[2:]))

    for _ in range(20):
        eo, xyz = random_ray(rng)
        linearize(eo, xyz, c, a9, b)
        linearize(eo, xyz, c, a6, b)
        np.testing.assert_array_equal(a9[:, :6], a6)
        theta = np.array([152.0, d5[0] * 152.0 ** 2, d5[1] * 152.0 ** 4], dtype=complex)
        for k in range(3):
            t = theta.copy()
            t[k] += 1j * h
            ref = proj(t[0], t[1], t[2], eo.astype(complex), xyz.astype(complex)).imag / h
            np.testing.assert_allclose(a9[:, 6 + k], ref, rtol=1e-10, atol=1e-14)
    moved = apply_intrinsics(c, [0.5, 0.01, -0.002])
    assert moved[0] == 152.5
    assert moved[3] * 152.5 ** 2 == pytest.approx(d5[0] * 152.0 ** 2 + 0.01)
    assert moved[4] * 152.5 ** 4 == pytest.approx(d5[1] * 152.0 ** 4 - 0.002)
    np.testing.assert_array_equal(moved[[1, 2, 5, 6, 7]], c[[1, 2, 5, 6, 7]])


def _first_fold_plain(xs, ys, row, backward):
    """The fold kernel's grid walked in Python (its functions' Python code, ``undistort``
    compiled): the index of the first fold, or -1."""
    for i, x in enumerate(xs):
        for j, y in enumerate(ys):
            _, _, j00, j01, j10, j11 = brown.py_func(x, y, row)
            if not j00 * j11 - j01 * j10 > 0.0:
                return i * len(ys) + j
            if not backward and not undistort(row[1] + x, row[2] + y, row)[2]:
                return i * len(ys) + j
    return -1


def test_the_fold_kernel_finds_the_first_fold_the_plain_loop_finds():
    """validate's grid kernel against the same grid walked in Python (the kernels' own
    Python functions), on barrel and pincushion distortions of growing strength, forward
    and backward, some of which fold inside the format."""
    from sapgo.project import CAMERA_DTYPE
    from sapgo.validate import _fold_at

    xs, ys = np.linspace(-115, 115, 41), np.linspace(-115, 115, 41)
    found = 0
    for k1 in (-4e-5, -1.5e-5, -1e-6, 1e-7, 1e-6, 1e-5):
        for backward in (False, True):
            rec = np.zeros(1, CAMERA_DTYPE)[0]
            rec["focal_length"], rec["k1"], rec["p1"] = 152.0, k1, 1e-6
            row = camera_array(np.asarray(rec).reshape(1))[0]
            row[MODEL] = 1.0 if backward else 0.0
            want = _first_fold_plain(xs, ys, row, backward)
            assert _fold_at(xs, ys, row, backward) == want
            found += want >= 0
    assert 0 < found < 12


def test_the_mirrored_fold_check_finds_what_the_whole_grid_finds():
    """Radial distortion alone with the principal point at 0 (BAL's cameras): the kernel
    solves one quadrant of the (exactly symmetric) grid and mirrors it; the first fold
    found is the plain loop's over the whole grid, on barrel and pincushion lenses of
    growing strength (k1, k2), forward and backward, formats not square; a principal point
    off 0, a decentring term or a grid not symmetric take the whole grid."""
    from sapgo.project import CAMERA_DTYPE
    from sapgo.validate import _fold_at, _mirrored, fold_grid

    xs, ys = 115.0 * fold_grid(), 80.0 * fold_grid()
    found = 0
    for k1, k2 in ((-4e-5, 0.0), (-1.5e-5, 0.0), (-1e-6, 0.0), (1e-6, -3e-10), (1e-5, 0.0),
                   (-2e-5, 2e-9), (3e-6, -1e-9)):
        for backward in (False, True):
            rec = np.zeros(1, CAMERA_DTYPE)[0]
            rec["focal_length"], rec["k1"], rec["k2"] = 152.0, k1, k2
            row = camera_array(np.asarray(rec).reshape(1))[0]
            row[MODEL] = 1.0 if backward else 0.0
            assert _mirrored(xs, ys, row)
            want = _first_fold_plain(xs, ys, row, backward)
            assert _fold_at(xs, ys, row, backward) == want
            found += want >= 0
            for k, v in ((1, 0.01), (6, 1e-7)):   # x0; p1
                other = row.copy()
                other[k] = v
                assert not _mirrored(xs, ys, other)
    assert 0 < found < 14
    assert not _mirrored(np.linspace(-115, 115, 40), ys, row)


def test_every_cameras_fold_in_one_kernel_as_one_camera_at_a_time():
    """validate's fold check of all cameras at once (one parallel kernel) against the grid
    of each camera walked alone (:func:`_fold_at` over ``linspace(-h, h, 41)``), on cameras
    without distortion, mild, folding, backward and of different formats; and the camera
    check names the first camera that folds, by record and id."""
    from sapgo.errors import DataError
    from sapgo.project import CAMERA_DTYPE
    from sapgo.validate import FOLD_GRID, _distortion_folds, _fold_at, check_values

    recs = np.zeros(8, CAMERA_DTYPE)
    recs["id"] = np.arange(10, 18)
    recs["focal_length"], recs["sigma_image"] = 152.0, 0.005
    recs["format_x"] = [230, 230, 230, 100, 230, 60, 230, 230]
    recs["format_y"] = [230, 230, 230, 80, 230, 90, 230, 230]
    recs["k1"] = [0.0, DIST[0], -4e-5, -4e-5, 1e-5, -1.5e-5, -1e-6, 0.0]
    recs["p1"] = [0.0, 0.0, 1e-6, 0.0, 0.0, 1e-6, 0.0, 0.0]
    recs["distortion_model"] = [0, 0, 0, 1, 1, 0, 0, 0]
    got = _distortion_folds(recs)
    folding = 0
    for rec, fold in zip(recs, got):
        row = camera_array(np.asarray(rec).reshape(1))[0]
        xs = np.linspace(-0.5 * rec["format_x"], 0.5 * rec["format_x"], FOLD_GRID)
        ys = np.linspace(-0.5 * rec["format_y"], 0.5 * rec["format_y"], FOLD_GRID)
        i = _fold_at(xs, ys, row, rec["distortion_model"] == 1) if rec["k1"] else -1
        if i < 0:
            assert fold is None
        else:
            folding += 1
            np.testing.assert_allclose(fold, (xs[i // FOLD_GRID], ys[i % FOLD_GRID]),
                                       rtol=1e-12, atol=1e-12)
    assert 0 < folding < len(recs) - 2
    first = next(i for i, f in enumerate(got) if f is not None)

    class Cameras:   # (check_values reads the cameras before anything else)
        path, n_cameras, n_stations, n_points = "p.h5", len(recs), 1, 0

        def cameras(self):
            return recs

    with pytest.raises(DataError, match=rf"cameras record {first} \(id {10 + first}\): the "
                                        r"lens distortion .* folds the image over"):
        check_values(Cameras())


def test_in_angles_kernel_against_the_matrix_products():
    """sapgo.quality.in_angles (one numba kernel) against ``T Q T'`` with numpy's products
    and :func:`attitude_jacobians`, for 6 and 9 parameters a station, with fixed parameters'
    rows and columns zeroed."""
    from sapgo.geometry import attitude_jacobians
    from sapgo.quality import in_angles

    rng = np.random.default_rng(11)
    for k in (6, 9):
        n = 40
        a = rng.normal(size=(n, k, k))
        q = a @ np.transpose(a, (0, 2, 1))
        eo = np.column_stack([rng.uniform(-1.2, 1.2, (n, 3)), rng.normal(size=(n, 3))])
        fixed = rng.integers(0, 64, n) * (rng.random(n) < 0.3)
        t = np.zeros((n, k, k))
        t[:, :3, :3] = attitude_jacobians(eo[:, :3])
        t[:, 3:, 3:] = np.eye(k - 3)
        want = t @ q @ np.transpose(t, (0, 2, 1))
        held = ((fixed[:, None] >> np.arange(6)) & 1) == 1
        keep = np.ones((n, k))
        keep[:, :6][held] = 0.0
        want *= keep[:, :, None] * keep[:, None, :]
        got = in_angles(q, eo, fixed)
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * np.abs(want).max())
        assert (got[held.nonzero()[0], held.nonzero()[1], :] == 0).all()
