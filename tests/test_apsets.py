"""The additional-parameter sets of aerial triangulation (Ebner's 12, Gruen's 44): their
terms against Ebner's published formulas and against their defining orthogonality, their
derivatives against central differences, and self-calibration with them against a dense
Gauss-Newton reference (tests/naive.py) whose terms are written independently: Ebner's as
he published them, Gruen's as a null space computed by SVD."""

import shutil

import numpy as np
import pytest
from conftest import assert_one_line_error, read_records, rewrite, run_cli

import naive
import sapgo
from sapgo.apsets import EBNER, GRID, GRUEN, N_TERMS, ap_displacement
from sapgo.geometry import AP0, AP_BASE, AP_SET, N_CAMERA, brown, camera_array
from sapgo.project import CONTROL_MASK, Project

TIGHT = dict(tol_position=1e-9, tol_angle=1e-11, max_iterations=40, progress=False)
#: Ebner's degrees (his b_i are per mm^(degree - 1): sapgo's a_i = b_i b^degree).
EBNER_DEGREES = (1, 1, 2, 2, 2, 2, 3, 3, 3, 3, 4, 4)


def ebner_published(x, y, b):
    """Ebner's (1976) twelve terms as printed, ``(dx, dy)`` per unit of his b_i."""
    q = 2.0 * b * b / 3.0
    return [(x, -y), (y, x), (-(2 * x * x - 2 * q), x * y), (x * y, -(2 * y * y - 2 * q)),
            (y * y - q, 0 * x), (0 * x, x * x - q), (x * (y * y - q), 0 * x),
            (0 * x, y * (x * x - q)), (y * (x * x - q), 0 * x), (0 * x, x * (y * y - q)),
            ((x * x - q) * (y * y - q), 0 * x), (0 * x, (x * x - q) * (y * y - q))]


def ebner_terms(b):
    """Ebner's terms scaled to sapgo's coefficients (``term / b^degree``), for naive."""
    def terms(u, v):
        return [(tx / b ** d, ty / b ** d)
                for (tx, ty), d in zip(ebner_published(u, v, b), EBNER_DEGREES)]
    return terms


def grid(n, b):
    t = np.linspace(-b, b, n)
    x, y = np.meshgrid(t, t)
    return x.ravel(), y.ravel()


def orientation_fields(x, y):
    """What a vertical photo's six orientation parameters do to its image, to first order:
    the shifts, the scale, the rotation and the two tilts' quadratic terms (2n x 6)."""
    one, zero = np.ones_like(x), np.zeros_like(x)
    return np.column_stack([np.r_[one, zero], np.r_[zero, one], np.r_[x, y], np.r_[-y, x],
                            np.r_[x * x, x * y], np.r_[x * y, y * y]])


def gruen_terms_by_svd(b):
    """An independent basis of Gruen's 44 directions: the bi-quartic displacement fields
    orthogonal on the 5 x 5 grid to the orientation's six, as the null space (SVD) of the
    orientation fields against the 50 monomial fields ``(x^i y^j, 0)``, ``(0, x^i y^j)``
    (of ``x / b``, ``y / b``)."""
    x, y = grid(5, 1.0)
    mono = [(i, j) for i in range(5) for j in range(5)]
    zero = np.zeros_like(x)
    g = np.column_stack([np.r_[x ** i * y ** j, zero] for i, j in mono]
                        + [np.r_[zero, x ** i * y ** j] for i, j in mono])
    _, _, vt = np.linalg.svd(orientation_fields(x, y).T @ g)
    null = vt[6:].T    # 50 x 44: monomial coefficients of each field
    null = null / np.abs(g @ null).max(axis=0)   # (each field's largest grid value 1 mm)

    def terms(u, v):
        m = np.array([(u / b) ** i * (v / b) ** j for i, j in mono])
        return list(zip(null[:25].T @ m, null[25:].T @ m))
    return terms


def sapgo_terms(s, b, x, y):
    """sapgo's terms of set ``s`` at the points ``x, y`` (2n x terms)."""
    cols = []
    for t in range(N_TERMS[s]):
        a = np.zeros(44)
        a[t] = 1.0
        d = np.array([ap_displacement(u, v, s, b, a)[:2] for u, v in zip(x, y)])
        cols.append(np.r_[d[:, 0], d[:, 1]])
    return np.column_stack(cols)


def test_ebner_set_is_ebners_published_formulas():
    """sapgo's construction on the 3 x 3 grid gives Ebner's twelve terms, term for term,
    with a_i = b_i b^degree, anywhere in the image (not only on the grid)."""
    b = 92.0
    rng = np.random.default_rng(3)
    x, y = rng.uniform(-115, 115, 40), rng.uniform(-115, 115, 40)
    ours = sapgo_terms(EBNER, b, x, y)
    for t, ((tx, ty), d) in enumerate(zip(ebner_published(x, y, b), EBNER_DEGREES)):
        np.testing.assert_allclose(ours[:, t] * b ** d, np.r_[tx, ty], rtol=1e-12,
                                   atol=1e-9 * b ** d)


@pytest.mark.parametrize("s", [EBNER, GRUEN])
def test_sets_are_orthogonal_to_each_other_and_to_the_orientation(s):
    """On their grids (3 x 3, 5 x 5 between -b and b) the 12 and 44 terms are orthogonal to
    each other and to the six orientation fields, and with them span every displacement
    the grid can show (2 n^2 directions); Gruen's 44 span the SVD null space's directions."""
    b = 71.0
    x, y = grid(GRID[s], b)
    m = sapgo_terms(s, b, x, y)
    o = orientation_fields(x, y)
    gram = m.T @ m
    scale = np.sqrt(np.outer(np.diag(gram), np.diag(gram)))
    assert np.abs((gram - np.diag(np.diag(gram))) / scale).max() < 1e-12
    assert np.abs(m.T @ o / np.sqrt(np.diag(gram))[:, None]
                  / np.linalg.norm(o, axis=0)[None, :]).max() < 1e-12
    assert np.linalg.matrix_rank(np.c_[m, o]) == 2 * GRID[s] ** 2
    if s == GRUEN:
        ref = np.array(gruen_terms_by_svd(b)(x, y))   # 44 x 2 x 25
        ref = np.concatenate([ref[:, 0, :], ref[:, 1, :]], axis=1).T
        # the same space: each of sapgo's terms is a combination of the reference's
        coef, *_ = np.linalg.lstsq(ref, m, rcond=None)
        assert np.abs(ref @ coef - m).max() < 1e-9 * np.abs(m).max()


@pytest.mark.parametrize("s", [EBNER, GRUEN])
def test_displacement_and_its_jacobian_in_the_camera_row(s):
    """A camera row with a set: brown() adds the set's displacement to Brown's, and its
    Jacobian equals central differences."""
    rng = np.random.default_rng(s)
    c = np.zeros(N_CAMERA)
    c[:10] = 152.0, 0.0, 0.0, 1e-5, -2e-9, 0.0, 1e-5, -2e-5, 2e-4, -3e-4
    c[AP_SET], c[AP_BASE] = s, 80.0
    c[AP0:AP0 + N_TERMS[s]] = rng.normal(0.0, 5e-3, N_TERMS[s])
    plain = c.copy()
    plain[AP_SET] = 0
    h = 1e-4
    for u, v in rng.uniform(-110, 110, (6, 2)):
        d = brown(u, v, c)
        p = brown(u, v, plain)
        ap = ap_displacement(u, v, s, 80.0, c[AP0:AP0 + 44])
        assert d[0] == pytest.approx(p[0] + ap[0], abs=1e-15)
        assert d[1] == pytest.approx(p[1] + ap[1], abs=1e-15)
        fu = (np.array(brown(u + h, v, c)[:2]) - np.array(brown(u - h, v, c)[:2])) / (2 * h)
        fv = (np.array(brown(u, v + h, c)[:2]) - np.array(brown(u, v - h, c)[:2])) / (2 * h)
        np.testing.assert_allclose([d[2] - 1, d[4]], fu, atol=1e-9)
        np.testing.assert_allclose([d[3], d[5] - 1], fv, atol=1e-9)


def planted_block(block_cache, tmp_path, name, s, pattern, coef):
    """A 2 x 6 block whose measurements carry the displacement of set ``s`` with
    coefficients ``coef`` (mm), its camera of that set with all coefficients 0, base 0.4
    times the format."""
    path = tmp_path / f"{name}.h5"
    shutil.copy(block_cache(f"aps-{pattern}", strips=2, photos_per_strip=6, control_points=6,
                            pattern=pattern), path)
    rec = read_records(path)
    cams = rec["cameras"]
    base = 0.4 * float(cams["format_x"][0])
    ob = rec["observations"]
    a = np.zeros(44)
    a[:len(coef)] = coef
    d = np.array([ap_displacement(x, y, s, base, a)[:2] for x, y in zip(ob["x"], ob["y"])])
    ob["x"] += d[:, 0]
    ob["y"] += d[:, 1]
    cams["ap_set"], cams["ap_base"] = s, base
    rewrite(path, rec)
    return path, base


def dense(path, terms, n_terms, calibrate):
    rec = read_records(path)
    st, pt, ob = rec["stations"], rec["points"], rec["observations"]
    cam = rec["cameras"][0]
    eo, xyz, s0, _, cam_r, q = naive.dense_bundle_adjustment(
        st["eo"], pt["xyz"], cam["focal_length"], ob["station"], ob["point"],
        np.column_stack([ob["x"], ob["y"]]), ob["sigma"],
        CONTROL_MASK[pt["kind"]].astype(bool), pt["control"], pt["control_sigma"],
        iterations=40, calibrate=calibrate, terms=terms, n_terms=n_terms)
    return eo[np.argsort(st["id"])], xyz[np.argsort(pt["id"])], s0, cam_r, q


def adjusted(path):
    with Project(path) as p:
        st, pt = p.read("stations"), p.read("points")
        eo = st["eo"] + p.solution("station_corr")
        xyz = pt["xyz"] + p.solution("point_corr")
        cam = (camera_array(p.cameras()) + p.solution("camera_corr"))[0]
    return eo[np.argsort(st["id"])], xyz[np.argsort(pt["id"])], cam


EBNER_PLANTED = (4e-3, -3e-3, 5e-3, -4e-3, 3e-3, 2e-3, -6e-3, 4e-3, 5e-3, -3e-3, 6e-3, -5e-3)


def test_self_calibration_with_ebners_set_equals_dense_least_squares(block_cache, tmp_path):
    """Ebner's twelve adjusted with the block (9-point pattern): the same orientations,
    points, coefficients, sigma0 and coefficient precision as a dense Gauss-Newton with
    Ebner's printed terms; the planted coefficients come back; the tree agrees."""
    path, base = planted_block(block_cache, tmp_path, "ebner", EBNER, 9, EBNER_PLANTED)
    names = tuple(f"a{i + 1}" for i in range(12))
    eo_r, xyz_r, s0_r, cam_r, q_r = dense(path, ebner_terms(base), 12, names)
    tree = tmp_path / "ebner-tree.h5"
    shutil.copy(path, tree)
    s = sapgo.adjust(path, sapgo.Options(calibrate=("ap",), **TIGHT))
    assert s.converged
    eo, xyz, cam = adjusted(path)
    assert np.abs(xyz - xyz_r).max() < 1e-6
    assert np.abs(eo[:, 3:] - eo_r[:, 3:]).max() < 1e-6
    assert np.abs(eo[:, :3] - eo_r[:, :3]).max() < 1e-9
    np.testing.assert_allclose(cam[AP0:AP0 + 12], cam_r[10:22], rtol=1e-6, atol=1e-10)
    assert s.sigma0 == pytest.approx(s0_r, rel=1e-8)
    rows = {r["parameter"]: r for r in s.calibration}
    assert list(rows) == list(names)
    for k, q, planted in zip(names, q_r, EBNER_PLANTED):
        assert rows[k]["sigma"] == pytest.approx(s0_r * np.sqrt(q), rel=1e-5)
        # (measured x = ideal + d: the forward model's coefficients are the planted ones)
        assert rows[k]["adjusted"] == pytest.approx(planted, abs=5 * rows[k]["sigma"])
    t = sapgo.adjust(tree, sapgo.Options(calibrate=("ap",), solver="tree", **TIGHT))
    assert t.sigma0 == pytest.approx(s.sigma0, rel=1e-9)
    np.testing.assert_allclose(adjusted(tree)[2], cam, rtol=1e-8, atol=1e-14)


def test_self_calibration_with_gruens_set_equals_dense_least_squares(block_cache, tmp_path):
    """Gruen's 44 adjusted with f on a block of the 25-point pattern: the same orientations,
    points, focal length and sigma0 as a dense Gauss-Newton whose 44 terms are the SVD null
    space (another basis of the same space: the coefficients differ, the fit does not)."""
    rng = np.random.default_rng(44)
    planted = rng.normal(0.0, 3e-3, 44)
    path, base = planted_block(block_cache, tmp_path, "gruen", GRUEN, 25, planted)
    names = tuple(f"a{i + 1}" for i in range(44))
    eo_r, xyz_r, s0_r, cam_r, _ = dense(path, gruen_terms_by_svd(base), 44, ("f",) + names)
    s = sapgo.adjust(path, sapgo.Options(calibrate=("f", "ap"), **TIGHT))
    assert s.converged
    eo, xyz, cam = adjusted(path)
    assert np.abs(xyz - xyz_r).max() < 1e-6
    assert np.abs(eo[:, 3:] - eo_r[:, 3:]).max() < 1e-6
    assert np.abs(eo[:, :3] - eo_r[:, :3]).max() < 1e-9
    assert cam[0] == pytest.approx(cam_r[0], rel=1e-9)
    assert s.sigma0 == pytest.approx(s0_r, rel=1e-8)
    rows = {r["parameter"]: r for r in s.calibration}
    assert list(rows) == ["f"] + list(names)
    for k, a in zip(names, planted):
        assert rows[k]["adjusted"] == pytest.approx(a, abs=5 * rows[k]["sigma"])


def test_additional_parameters_import_export_and_errors(block_cache, tmp_path, capsys):
    """The --additional-parameters file: read into the cameras, written by export and read
    back bitwise, adjusted with --calibrate ap from the command line; bad lines and bad
    --calibrate names are one-line errors naming the file and line or the camera."""
    src = tmp_path / "src.h5"
    shutil.copy(block_cache("aps-9", strips=2, photos_per_strip=6, control_points=6,
                            pattern=9), src)
    d = tmp_path / "txt"
    assert run_cli(capsys, "export", src, d)[0] == 0
    ap = tmp_path / "ap.txt"
    ap.write_text("# camera set base a1 ...\n1 ebner auto 0.001 -0.002 0.5e-3\n")
    files = ["--cameras", d / "cameras.txt", "--photos", d / "photos.txt", "--measurements",
             d / "measurements.txt", "--control", d / "control.txt"]
    one = tmp_path / "one.h5"
    code, _, err = run_cli(capsys, "import", one, *files, "--additional-parameters", ap)
    assert code == 0, err
    with Project(one) as p:
        c = p.cameras()[0]
        assert c["ap_set"] == EBNER
        assert c["ap_base"] == pytest.approx(0.4 * max(c["format_x"], c["format_y"]))
        assert (c["a1"], c["a2"], c["a3"], c["a4"]) == (0.001, -0.002, 0.5e-3, 0.0)
    d2 = tmp_path / "txt2"
    assert run_cli(capsys, "export", one, d2)[0] == 0
    assert (d2 / "additional_parameters.txt").exists()
    two = tmp_path / "two.h5"
    code, _, err = run_cli(capsys, "import", two, *[str(x).replace(str(d), str(d2))
                                                      for x in files],
                           "--additional-parameters", d2 / "additional_parameters.txt")
    assert code == 0, err
    with Project(one) as p, Project(two) as q:
        assert p.cameras().tobytes() == q.cameras().tobytes()
    code, out, err = run_cli(capsys, "adjust", two, "--calibrate", "ap", "--max-iterations",
                             "10")
    assert code == 0, err
    # bad lines
    for text, words in (("1 ebner\n", ["ap.txt:1", "expected camera set base"]),
                        ("7 ebner 90\n", ["ap.txt:1", "camera 7 is not in the cameras"]),
                        ("1 brown 90\n", ["ap.txt:1", "'brown'", "ebner, gruen"]),
                        ("1 ebner -4\n", ["ap.txt:1", "base '-4'"]),
                        ("1 ebner 90 " + "0 " * 13 + "\n", ["ap.txt:1", "12 coefficient"]),
                        ("1 gruen 90 0 x\n", ["ap.txt:1", "a2 'x'"]),
                        ("1 ebner 90\n\n1 gruen 90\n", ["ap.txt:3", "has a line already"])):
        ap.write_text(text)
        code, _, err = run_cli(capsys, "import", tmp_path / "bad.h5", *files,
                               "--additional-parameters", ap, "--force")
        assert_one_line_error(code, err, *words)
        assert not (tmp_path / "bad.h5").exists()
    # bad --calibrate names for this camera
    code, _, err = run_cli(capsys, "adjust", two, "--calibrate", "a13")
    assert_one_line_error(code, err, "a13 of camera id 1", "a1 .. a12")
    code, _, err = run_cli(capsys, "adjust", src, "--calibrate", "ap")
    assert_one_line_error(code, err, "none of the calibrated cameras has an "
                                     "additional-parameter set")
    code, _, err = run_cli(capsys, "adjust", src, "--calibrate", "a1")
    assert_one_line_error(code, err, "a1 of camera id 1", "no additional-parameter set")
    code, _, err = run_cli(capsys, "adjust", src, "--calibrate", "a45")
    assert_one_line_error(code, err, "'a45'", "a1 .. a44")
