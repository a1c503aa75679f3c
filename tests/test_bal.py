"""BAL problems: reading, the camera model, Levenberg-Marquardt on free networks, round trips
and malformed files."""

from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, run_cli

import sapgo
from sapgo.formats.bal import (
    bal_cost,
    bal_to_sapgo,
    export_bal,
    import_bal,
    read_bal,
    rodrigues,
)
from sapgo.geometry import project

DATA = Path(__file__).parent / "data"
DUBROVNIK = DATA / "dubrovnik-3-7-pre.txt.gz"
LADYBUG = DATA / "problem-49-7776-pre.txt.gz"


def test_initial_cost_of_problem_49_is_reproduced(tmp_path):
    """The known initial cost 8.509125e5, from the BAL model and from sapgo's collinearity
    model after the conversion (which is what the adjustment starts from)."""
    d = read_bal(LADYBUG)
    assert bal_cost(d) == pytest.approx(8.509125e5, rel=1e-6)
    eo, rows = bal_to_sapgo(d["cameras"])
    c, j = d["obs_camera"], d["obs_point"]
    v = np.array([project(eo[a], d["points"][b], rows[a]) for a, b in zip(c, j)]) - d["obs_xy"]
    assert 0.5 * (v ** 2).sum() == pytest.approx(bal_cost(d), rel=1e-12)
    r = import_bal(LADYBUG, tmp_path / "l.h5")
    s = sapgo.adjust(tmp_path / "l.h5", sapgo.Options(progress=False, max_iterations=1))
    assert s.initial_cost == pytest.approx(8.509125e5, rel=1e-6) == r["initial_cost"]
    assert s.final_cost < s.initial_cost / 10 and s.datum == "free" and s.method == "lm"


def scipy_reference(d, intrinsics=False, dense_lm=False):
    """The same problem by scipy.optimize.least_squares (trust region): intrinsics fixed, or
    adjusted with each camera (9 parameters). The Jacobian is exact and sparse: complex-step
    derivatives, one evaluation per parameter of a camera and per coordinate of a point
    (every residual depends on one camera and one point)."""
    from scipy.optimize import least_squares
    from scipy.sparse import coo_matrix

    cams, pts = d["cameras"], d["points"]
    nc, npt = len(cams), len(pts)
    c, j, xy = d["obs_camera"], d["obs_point"], d["obs_xy"]
    m = 9 if intrinsics else 6

    def residuals(x):
        cam = x[:m * nc].reshape(nc, m)
        X = x[m * nc:].reshape(npt, 3)
        f, k1, k2 = (cam[:, 6], cam[:, 7], cam[:, 8]) if intrinsics else \
            (cams[:, 6], cams[:, 7], cams[:, 8])
        w = cam[c, :3]
        theta = np.sqrt((w * w).sum(axis=1))  # Rodrigues, complex-safe (no zero rotations)
        k = w / theta[:, None]
        Xj = X[j]
        cross = np.cross(k, Xj)
        dot = (k * Xj).sum(axis=1)[:, None]
        p = (Xj * np.cos(theta)[:, None] + cross * np.sin(theta)[:, None]
             + k * dot * (1 - np.cos(theta))[:, None] + cam[c, 3:6])
        q = -p[:, :2] / p[:, 2:3]
        r2 = (q * q).sum(axis=1)
        dd = 1 + k1[c] * r2 + k2[c] * r2 * r2
        return (f[c][:, None] * dd[:, None] * q - xy).ravel()

    rows = np.arange(2 * len(c))
    cols = [(m * c[:, None] + np.arange(m)[None, :], m), (m * nc + 3 * j[:, None]
                                                           + np.arange(3)[None, :], 3)]

    def jacobian(x):
        h = 1e-30
        ri, ci, vi = [], [], []
        for idx, width in cols:
            for u in range(width):
                xc = x.astype(complex)
                xc[np.unique(idx[:, u])] += 1j * h
                dr = residuals(xc).imag / h
                ri.append(rows)
                ci.append(np.repeat(idx[:, u], 2))
                vi.append(dr)
        return coo_matrix((np.concatenate(vi), (np.concatenate(ri), np.concatenate(ci))),
                          shape=(2 * len(c), len(x))).tocsr()

    x = np.concatenate([cams[:, :m].ravel(), pts.ravel()])
    if dense_lm:
        return _dense_levenberg_marquardt(residuals, jacobian, x)
    sol = least_squares(residuals, x, jac=lambda x: jacobian(x).toarray(), method="trf",
                        x_scale="jac", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    return sol.cost


def _dense_levenberg_marquardt(residuals, jacobian, x, iterations=200):
    """Plain Levenberg-Marquardt on the dense normal equations (Nielsen's damping update),
    steps by the symmetric eigendecomposition (a free network's gauge directions get no
    step), to a relative cost change of 1e-13: the reference minimum for problems too large
    for a dense QR of the Jacobian."""
    import scipy.linalg

    r = residuals(x)
    cost, mu, nu = 0.5 * r @ r, 1e-4, 2.0
    for _ in range(iterations):
        jac = jacobian(x)
        n = (jac.T @ jac).toarray()
        g = jac.T @ r
        s = 1.0 / np.sqrt(np.clip(np.diag(n), 1e-12, None))  # Jacobi scaling
        ns = n * s[:, None] * s[None, :]
        w, v = scipy.linalg.eigh(ns)
        keep = w > 1e-12 * w[-1]
        step = -s * (v[:, keep] @ ((v[:, keep].T @ (s * g)) / (w[keep] + mu)))
        r_new = residuals(x + step)
        cost_new = 0.5 * r_new @ r_new
        predicted = -(g @ step) - 0.5 * step @ (n @ step)
        rho = (cost - cost_new) / predicted if predicted > 0 else -1.0
        if rho > 0:
            done = cost - cost_new <= 1e-13 * cost
            x, r, cost = x + step, r_new, cost_new
            mu, nu = mu * max(1 / 3, 1 - (2 * rho - 1) ** 3), 2.0
            if done:
                break
        else:  # no step lowers the cost any more: the minimum
            mu, nu = mu * nu, 2 * nu
            if mu > 1e16:
                break
    return cost


def test_levenberg_marquardt_reaches_the_scipy_minimum(tmp_path):
    """dubrovnik-3-7 with fixed intrinsics (a free network with 6 redundant equations): the
    final cost equals SciPy's least-squares minimum of the same model."""
    d = read_bal(DUBROVNIK)
    ref = scipy_reference(d)
    import_bal(DUBROVNIK, tmp_path / "d.h5", intrinsics="fixed")
    s = sapgo.adjust(tmp_path / "d.h5", sapgo.Options(progress=False, max_iterations=100,
                                                      tol_cost=1e-12))
    assert s.converged and s.redundancy == 38 - 39 + 7
    assert s.final_cost == pytest.approx(ref, rel=1e-6)
    assert s.initial_cost == pytest.approx(bal_cost(d), rel=1e-12)
    steps = {r.get("step") for r in s.iteration_log}
    assert "accepted" in steps


def ladybug_subset(n_cam=4, min_rays=3, min_angle=2.0):
    """The first cameras of problem-49-7776 and the points they see at least ``min_rays``
    times, in front of every camera and with rays at least ``min_angle`` degrees apart: a
    small, well-determined problem with its own intrinsics per camera (the full problem's
    weakest points have a flat cost towards infinity, which leaves no minimum to compare)."""
    d = read_bal(LADYBUG)
    cams, pts = d["cameras"][:n_cam], d["points"]
    keep = d["obs_camera"] < n_cam
    c, j = d["obs_camera"][keep], d["obs_point"][keep]
    r = rodrigues(cams[:, :3])
    centre = -np.einsum("nji,nj->ni", r, cams[:, 3:6])
    depth = np.einsum("nij,nj->ni", r[c], pts[j])[:, 2] + cams[c, 5]
    ray = pts[j] - centre[c]
    ray /= np.linalg.norm(ray, axis=1)[:, None]
    good = np.bincount(j, minlength=len(pts)) >= min_rays
    good &= np.bincount(j, weights=depth > 0, minlength=len(pts)) == 0
    for p in np.flatnonzero(good):  # the widest angle between two rays of the point
        u = ray[j == p]
        good[p] = np.degrees(np.arccos(np.clip((u @ u.T).min(), -1, 1))) >= min_angle
    sel = np.isin(j, np.flatnonzero(good))
    remap = np.full(len(pts), -1)
    remap[good] = np.arange(good.sum())
    return {"cameras": cams, "points": pts[good], "obs_camera": c[sel],
            "obs_point": remap[j[sel]], "obs_xy": d["obs_xy"][keep][sel]}


def test_photos_own_intrinsics_reach_the_scipy_minimum(tmp_path):
    """Nine parameters per photo (rotation, position, f, k1, k2), as BAL's usual problem: the
    final cost equals SciPy's minimum; the adjusted intrinsics are in /solution/camera_corr
    and the exported problem holds them (its cost is the final cost)."""
    from sapgo.formats.bal import write_bal
    from sapgo.project import Project

    d = ladybug_subset()
    src = tmp_path / "sub.txt"
    write_bal(src, d["cameras"], d["points"], d["obs_camera"], d["obs_point"], d["obs_xy"])
    ref = scipy_reference(d, intrinsics=True, dense_lm=True)
    opts = sapgo.Options(progress=False, max_iterations=200, tol_cost=1e-12)
    import_bal(src, tmp_path / "f.h5", intrinsics="fixed")
    fixed = sapgo.adjust(tmp_path / "f.h5", opts)
    import_bal(src, tmp_path / "s.h5")
    s = sapgo.adjust(tmp_path / "s.h5", opts)
    assert s.converged and fixed.converged
    assert s.final_cost == pytest.approx(ref, rel=1e-8)
    assert s.final_cost < 0.97 * fixed.final_cost  # the intrinsics matter
    with Project(tmp_path / "s.h5") as p:
        corr = p.solution("camera_corr")
    assert np.abs(corr[:, 0]).max() > 0.01  # focal lengths moved
    export_bal(tmp_path / "s.h5", tmp_path / "out.txt", adjusted=True)
    assert bal_cost(read_bal(tmp_path / "out.txt")) == pytest.approx(s.final_cost, rel=1e-9)


def test_round_trip_import_adjust_export_import(tmp_path, capsys):
    src = tmp_path / "d.h5"
    # (dubrovnik-3-7 has 38 image coordinates: too few for 9 parameters a photo)
    code, text, err = run_cli(capsys, "import", "--format", "bal", "--fixed-intrinsics",
                              DUBROVNIK, src)
    assert code == 0 and "initial cost" in text, err
    code, text, err = run_cli(capsys, "adjust", src, "--no-progress", "--json",
                              tmp_path / "r.json", "--quiet")
    assert code == 0, err
    import json

    rep = json.loads((tmp_path / "r.json").read_text())
    code, text, err = run_cli(capsys, "export", src, tmp_path / "out.txt", "--format", "bal",
                              "--adjusted")
    assert code == 0, err
    back = read_bal(tmp_path / "out.txt")
    assert bal_cost(back) == pytest.approx(rep["final_cost"], rel=1e-9)
    r = import_bal(tmp_path / "out.txt", tmp_path / "again.h5", intrinsics="fixed")
    assert r["initial_cost"] == pytest.approx(rep["final_cost"], rel=1e-9)
    # the inputs round-trip exactly (rotations through omega-phi-kappa to 1e-15)
    export_bal(src, tmp_path / "in.txt", adjusted=False)
    orig, again = read_bal(DUBROVNIK), read_bal(tmp_path / "in.txt")
    np.testing.assert_allclose(rodrigues(again["cameras"][:, :3]),
                               rodrigues(orig["cameras"][:, :3]), atol=1e-14)
    np.testing.assert_allclose(again["cameras"][:, 3:], orig["cameras"][:, 3:], rtol=1e-12)
    assert sorted(zip(again["obs_point"].tolist(), again["obs_camera"].tolist())) == \
        sorted(zip(orig["obs_point"].tolist(), orig["obs_camera"].tolist()))


def test_levenberg_marquardt_equals_gauss_newton_on_a_controlled_block(small_block):
    """Forced Levenberg-Marquardt converges to the Gauss-Newton solution."""
    import shutil

    lm = small_block.with_name("lm.h5")
    shutil.copy(small_block, lm)
    tight = dict(progress=False, tol_position=1e-9, tol_angle=1e-11, max_iterations=30)
    s_gn = sapgo.adjust(small_block, sapgo.Options(**tight))
    s_lm = sapgo.adjust(lm, sapgo.Options(method="levenberg-marquardt", tol_cost=1e-14,
                                          **tight))
    assert s_gn.method == "gn" and s_lm.method == "lm"
    assert s_lm.final_cost == pytest.approx(s_gn.final_cost, rel=1e-8)
    from sapgo.project import Project

    with Project(small_block) as a, Project(lm) as b:
        np.testing.assert_allclose(b.solution("point_corr"), a.solution("point_corr"),
                                   atol=1e-6)


BAD = {
    "header": ("3 7\n", ":1:", "three non-negative integers"),
    "observation": ("1 1 2\n0 0 1.0\n", ":2:", "observation"),
    "index": ("1 1 2\n0 0 1 2\n0 5 1 2\n" + "0\n" * 9 + "1\n2\n3\n", ":3:", "point index 5"),
    "number": ("1 1 1\n0 0 1 2\n" + "0\n" * 4 + "x\n" + "0\n" * 4 + "1\n2\n3\n", ":7:",
               "'x' is not a number"),
    "short": ("1 1 1\n0 0 1 2\n" + "0\n" * 5, ":7:", "expected 12"),
    "focal": ("1 1 1\n0 0 1 2\n" + "0\n" * 9 + "1\n2\n3\n", ":9:", "focal length"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_malformed_bal_files_name_file_and_line(tmp_path, capsys, case):
    text, line, words = BAD[case]
    f = tmp_path / "bad.txt"
    f.write_text(text)
    code, out, err = run_cli(capsys, "import", "--format", "bal", f, tmp_path / "x.h5")
    assert_one_line_error(code, err, f"bad.txt{line}", words)
    assert not (tmp_path / "x.h5").exists()


@pytest.mark.parametrize("camera, words", [
    ("0 0 0 0 0 -10 1e-300 0.1 0", "cameras record 0 (id 0): k1 is infinite"),
    ("1e300 0 0 0 0 -10 500 0 0", "the initial cost is nan"),
    ("0 0 0 0 0 1e300 500 0 0", "stations record 0 (id 0): eo 1e+300 is beyond 1e+15"),
    ("0 0 0 0 0 -10 500 1e300 0", "the initial cost is inf"),
])
def test_bal_values_out_of_range_are_refused(tmp_path, capsys, camera, words):
    """Finite values whose conversion or cost is not a number (a focal length of 1e-300
    makes k1 / f^2 infinite): refused in one line, nothing written (NaN and inf were
    stored before, with RuntimeWarnings)."""
    f = tmp_path / "bad.txt"
    f.write_text("1 1 1\n0 0 1 2\n" + "\n".join(camera.split()) + "\n0.1\n0\n1\n")
    code, out, err = run_cli(capsys, "import", "--format", "bal", f, tmp_path / "x.h5")
    assert_one_line_error(code, err, "bad.txt", words)
    assert not (tmp_path / "x.h5").exists()


def test_append_is_refused_for_a_bal_import(tmp_path, capsys):
    f = tmp_path / "p.txt"
    f.write_text("1 1 1\n0 0 1 2\n" + "0\n" * 5 + "-10\n500\n0\n0\n0.1\n0\n1\n")
    code, _, err = run_cli(capsys, "import", "--format", "bal", "--append", f, tmp_path / "x.h5")
    assert_one_line_error(code, err, "--append applies to the text files' import",
                          "--format bal makes a new project")


def test_a_byte_that_is_not_utf8_names_its_line(tmp_path, capsys):
    f = tmp_path / "bad.txt"
    f.write_bytes(b"1 1 1\n0 0 1 2\n0\n0\n0\n0\n0\n-10\n500\n\xe9\n0\n0.1\n0\n1\n")
    code, _, err = run_cli(capsys, "import", "--format", "bal", f, tmp_path / "x.h5")
    assert_one_line_error(code, err, "bad.txt:10: not a text file")
    assert not (tmp_path / "x.h5").exists()
