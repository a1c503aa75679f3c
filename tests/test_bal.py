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


def scipy_reference(d):
    """The same problem (intrinsics fixed) by scipy.optimize.least_squares (trust region)."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    cams, pts = d["cameras"], d["points"]
    nc, npt = len(cams), len(pts)
    c, j, xy = d["obs_camera"], d["obs_point"], d["obs_xy"]

    def residuals(x):
        rv = x[:3 * nc].reshape(nc, 3)
        t = x[3 * nc:6 * nc].reshape(nc, 3)
        X = x[6 * nc:].reshape(npt, 3)
        r = Rotation.from_rotvec(rv).as_matrix()
        p = np.einsum("nij,nj->ni", r[c], X[j]) + t[c]
        q = -p[:, :2] / p[:, 2:3]
        r2 = (q * q).sum(axis=1)
        dd = 1 + cams[c, 7] * r2 + cams[c, 8] * r2 * r2
        return (cams[c, 6][:, None] * dd[:, None] * q - xy).ravel()

    x0 = np.concatenate([cams[:, :3].ravel(), cams[:, 3:6].ravel(), pts.ravel()])
    sol = least_squares(residuals, x0, method="trf", x_scale="jac", xtol=1e-15, ftol=1e-15,
                        gtol=1e-15, max_nfev=10000)
    return sol.cost


def test_levenberg_marquardt_reaches_the_scipy_minimum(tmp_path):
    """dubrovnik-3-7 with fixed intrinsics (a free network with 6 redundant equations): the
    final cost equals SciPy's least-squares minimum of the same model."""
    d = read_bal(DUBROVNIK)
    ref = scipy_reference(d)
    import_bal(DUBROVNIK, tmp_path / "d.h5")
    s = sapgo.adjust(tmp_path / "d.h5", sapgo.Options(progress=False, max_iterations=100,
                                                      tol_cost=1e-12))
    assert s.converged and s.redundancy == 38 - 39 + 7
    assert s.final_cost == pytest.approx(ref, rel=1e-6)
    assert s.initial_cost == pytest.approx(bal_cost(d), rel=1e-12)
    steps = {r.get("step") for r in s.iteration_log}
    assert "accepted" in steps


def test_round_trip_import_adjust_export_import(tmp_path, capsys):
    src = tmp_path / "d.h5"
    code, text, err = run_cli(capsys, "import", "--format", "bal", DUBROVNIK, src)
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
    r = import_bal(tmp_path / "out.txt", tmp_path / "again.h5")
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
