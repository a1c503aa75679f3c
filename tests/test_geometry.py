"""Collinearity kernels against the plain-numpy reference and finite differences."""

import numpy as np
import pytest

import naive
from sapgo.geometry import intersect, linearize, project, rotation_matrix


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


def test_projection_matches_reference(rng):
    for _ in range(20):
        eo, xyz = random_ray(rng)
        x, y = project(eo, xyz, 152.0, 0.01, -0.02)
        np.testing.assert_allclose([x, y], naive.project(eo, xyz, 152.0, 0.01, -0.02),
                                   rtol=0, atol=1e-12)


def test_partials_against_complex_step_and_finite_differences(rng):
    a = np.empty((2, 6))
    b = np.empty((2, 3))
    for _ in range(50):
        eo, xyz = random_ray(rng)
        x, y, w = linearize(eo, xyz, 152.0, 0.0, 0.0, a, b)
        assert w < 0  # the point is in front of the camera
        np.testing.assert_allclose([x, y], naive.project(eo, xyz, 152.0), atol=1e-12)
        ac, bc = naive.jacobian_complex_step(eo, xyz, 152.0)
        np.testing.assert_allclose(a, ac, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(b, bc, rtol=1e-10, atol=1e-14)
        # central finite differences, steps scaled to the parameter
        p = np.concatenate([eo, xyz])
        steps = np.array([1e-6] * 3 + [1e-3] * 6)
        fd = np.zeros((2, 9))
        for k in range(9):
            hi, lo = p.copy(), p.copy()
            hi[k] += steps[k]
            lo[k] -= steps[k]
            fd[:, k] = (np.array(project(hi[:6], hi[6:], 152.0, 0.0, 0.0))
                        - np.array(project(lo[:6], lo[6:], 152.0, 0.0, 0.0))) / (2 * steps[k])
        np.testing.assert_allclose(np.hstack([a, b]), fd, rtol=1e-6, atol=1e-9)


def test_intersection_recovers_the_point(rng):
    xyz = np.array([120.0, -340.0, 410.0])
    eos = np.array([[0.01, -0.02, 0.0, -1000.0, 0.0, 3800.0],
                    [-0.01, 0.015, 0.1, 1300.0, 50.0, 3810.0],
                    [0.0, 0.0, np.pi, 100.0, 2000.0, 3790.0]])
    xy = np.array([naive.project(e, xyz, 152.0) for e in eos])
    p, ok = intersect(eos, xy, np.full(3, 152.0), np.zeros(3), np.zeros(3))
    assert ok
    np.testing.assert_allclose(p, xyz, atol=1e-6)
    _, ok = intersect(eos[:1], xy[:1], np.full(1, 152.0), np.zeros(1), np.zeros(1))
    assert not ok


def test_project_observations_and_intersect_points_kernels(rng):
    from sapgo.geometry import intersect_points, project_observations

    eo = np.array([[0.01, -0.01, 0.0, 0.0, 0.0, 3800.0],
                   [0.0, 0.02, 0.05, 2300.0, 0.0, 3810.0],
                   [-0.02, 0.0, np.pi, 1100.0, 2300.0, 3790.0]])
    xyz = np.array([[500.0, 300.0, 120.0], [1500.0, 900.0, 80.0], [1000.0, 1200.0, 200.0]])
    st = np.array([0, 1, 2, 0, 1, 1, 2])
    pt = np.array([0, 0, 0, 1, 1, 2, 2])
    cams = np.zeros(3, np.int64)
    out = np.empty((7, 2))
    project_observations(st, pt, eo, xyz, cams, np.array([152.0]), np.zeros(1), np.zeros(1),
                         out)
    np.testing.assert_allclose(out, naive.project(eo[st], xyz[pt], 152.0), atol=1e-12)
    got = np.empty((3, 3))
    ok = np.zeros(3, np.bool_)
    intersect_points(np.array([0, 3, 5]), np.array([3, 2, 2]), st, out, eo, cams,
                     np.array([152.0]), np.zeros(1), np.zeros(1), got, ok)
    assert ok.all()
    np.testing.assert_allclose(got, xyz, atol=1e-6)


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
