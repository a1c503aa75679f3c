"""PhotoModeler text exports (DBAT's reading of them): a generated block written in that
format, with a backward (correcting) lens distortion, comes back to the same adjustment."""

import numpy as np
import pytest
from conftest import assert_one_line_error, read_records, run_cli

import sapgo
from sapgo.geometry import BACKWARD, camera_array, observed
from sapgo.project import KIND_CONTROL, KIND_PASS, Project

#: PhotoModeler's camera: c xp yp xs ys (mm; principal point from the top-left, y down)
#: and its correcting K1 K2 K3 P1 P2; the image's pixels.
K = (2.0e-9, -3.0e-14, 0.0, 4.0e-7, -2.0e-7)
WIDTH, HEIGHT = 23000, 23000


def _correction(u, v):
    """PhotoModeler's backward model as DBAT writes it (``browndist.m``, K and P negated
    there): the correction added to a measured point, w = m - principal point, y up."""
    k1, k2, k3, p1, p2 = K
    r2 = u * u + v * v
    radial = k1 * r2 + k2 * r2 ** 2 + k3 * r2 ** 3
    return (u * radial + p1 * (r2 + 2 * u * u) + 2 * p2 * u * v,
            v * radial + 2 * p1 * u * v + p2 * (r2 + 2 * v * v))


def _r(v):
    return repr(float(v))


def _write_pm(src, path, control=True):
    """The generated block ``src`` as a PhotoModeler export: measured pixels whose
    correction gives the block's image coordinates back."""
    rec = read_records(src)
    cam, st, pt, ob = rec["cameras"][0], rec["stations"], rec["points"], rec["observations"]
    xs, ys = float(cam["format_x"]), float(cam["format_y"])
    x0, y0 = float(cam["x0"]), float(cam["y0"])
    xp, yp = x0 + xs / 2, ys / 2 - y0
    camline = " ".join(_r(v) for v in (cam["focal_length"], xp, yp, xs, ys) + K)
    lines = ["Synthetic PhotoModeler export", f" 0.0005 20 {WIDTH} {HEIGHT}",
             " 1 0.1 10 100 100 100 20 20 20", " " + camline, " " + " ".join(["0"] * 10)]
    for s, e in zip(st["id"], st["eo"]):
        om, ph, ka = np.degrees(e[:3])
        lines += [f"  {s} images/photo_{s}.tif",
                  f"  {s} " + " ".join(_r(v) for v in (e[3], e[4], e[5], ka, ph, om)),
                  f"  {s} 0.1 0.1 0.1 0.01 0.01 0.01", "", f"  {s} {camline}",
                  f"  {s} " + " ".join(["0"] * 10)]
    lines.append("")
    ctl = np.flatnonzero(pt["kind"] == KIND_CONTROL) if control else []
    for j in ctl:
        c, sg = pt["control"][j], pt["control_sigma"][j]
        lines.append(f"  {pt['id'][j]} " + " ".join(_r(v) for v in c) + " "
                     + " ".join(_r(v) if v > 0 else "-1.778" for v in sg))
    lines.append("")
    for j in range(len(pt)):
        lines.append(f"  {pt['id'][j]} " + " ".join(_r(v) for v in pt["xyz"][j])
                     + " 0.001 0.001 0.001")
    lines.append("")
    pw, phh = xs / WIDTH, ys / HEIGHT
    for o in ob:
        # the measured point m with m + correction(m - pp) = the ideal point (iterated)
        ix, iy = float(o["x"]), float(o["y"])
        mx, my = ix, iy
        for _ in range(50):
            dx, dy = _correction(mx - x0, my - y0)
            mx, my = ix - dx, iy - dy
        col, row = (mx + xs / 2) / pw, (ys / 2 - my) / phh
        lines.append(f"  {st['id'][o['station']]} {pt['id'][o['point']]} {_r(col)} "
                     f"{_r(row)} 0.6 0.6")
    path.write_text("\n".join(lines) + "\n")
    return rec


def test_a_block_in_photomodelers_format_adjusts_alike(small_block, tmp_path, capsys):
    rec = _write_pm(small_block, tmp_path / "pm.txt")
    code, out, err = run_cli(capsys, "import", "--format", "photomodeler", tmp_path / "pm.txt",
                             tmp_path / "pm.h5")
    assert code == 0, err
    back = read_records(tmp_path / "pm.h5")
    # the camera keeps PhotoModeler's distortion as sapgo's backward model, and the
    # measurements it corrects are the block's own, in mm
    cam = back["cameras"][0]
    assert tuple(cam[k] for k in ("k1", "k2", "k3", "p1", "p2")) == K
    assert cam["distortion_model"] == BACKWARD
    assert cam["x0"] == pytest.approx(rec["cameras"][0]["x0"], abs=1e-12)
    key = lambda r: np.lexsort((r["points"]["id"][r["observations"]["point"]],   # noqa
                                r["stations"]["id"][r["observations"]["station"]]))
    a, b = rec["observations"][key(rec)], back["observations"][key(back)]
    row = camera_array(back["cameras"])[0]
    fixed = np.array([observed(x, y, row) for x, y in zip(b["x"], b["y"])])
    np.testing.assert_allclose(fixed[:, 0], a["x"], atol=1e-9)
    np.testing.assert_allclose(fixed[:, 1], a["y"], atol=1e-9)
    np.testing.assert_allclose(b["sigma"], 0.6 * 230 / WIDTH, rtol=1e-12)
    np.testing.assert_allclose(back["stations"]["eo"], rec["stations"]["eo"], rtol=1e-12,
                               atol=1e-12)
    assert (back["points"]["kind"] == rec["points"]["kind"]
            * (rec["points"]["kind"] == KIND_CONTROL)).all()
    s1 = sapgo.adjust(small_block, sapgo.Options(progress=False))
    s2 = sapgo.adjust(tmp_path / "pm.h5", sapgo.Options(progress=False))
    assert s2.converged
    with Project(small_block) as p1, Project(tmp_path / "pm.h5") as p2:
        x1 = p1.read("points")["xyz"] + p1.solution("point_corr")
        x2 = p2.read("points")["xyz"] + p2.solution("point_corr")
        i1, i2 = p1.read("points")["id"], p2.read("points")["id"]
    common = np.intersect1d(i1, i2)
    d = x1[np.searchsorted(i1, common)] - x2[np.searchsorted(i2, common)]
    assert np.abs(d).max() < 1e-6 and s2.sigma0 == pytest.approx(s1.sigma0, rel=1e-6)
    assert s1.converged


def test_without_control_the_block_is_a_free_network(small_block, tmp_path):
    from sapgo.formats.photomodeler import import_photomodeler

    _write_pm(small_block, tmp_path / "pm.txt", control=False)
    r = import_photomodeler(tmp_path / "pm.txt", tmp_path / "pm.h5")
    assert r["free"] and r["control_points"] == 0
    with Project(tmp_path / "pm.h5") as p:
        assert p.attr("datum") == "free"
        assert (p.read("points")["kind"] == KIND_PASS).all()


@pytest.mark.parametrize("case, where, words", [
    ("size", ":2:", "width and height"),
    ("marked", ":", "is not an object"),
    ("photo", ":", "has no photo block"),
])
def test_malformed_exports_name_the_line(small_block, tmp_path, capsys, case, where, words):
    _write_pm(small_block, tmp_path / "pm.txt")
    lines = (tmp_path / "pm.txt").read_text().splitlines()
    if case == "size":
        lines[1] = " 0.0005 20"
    elif case == "marked":
        lines[-1] = lines[-1].split()[0] + " 999999 1.0 2.0 0.6 0.6"
    else:
        lines[-1] = "987 " + " ".join(lines[-1].split()[1:])
    (tmp_path / "pm.txt").write_text("\n".join(lines) + "\n")
    code, out, err = run_cli(capsys, "import", "--format", "photomodeler", tmp_path / "pm.txt",
                             tmp_path / "x.h5")
    assert_one_line_error(code, err, "pm.txt" + where, words)
    assert not (tmp_path / "x.h5").exists()


def test_export_and_import_again(small_block, tmp_path, capsys):
    """A generated block written as a PhotoModeler export (10 um pixels), imported again:
    the same observations and adjustment; with --adjusted the adjusted values go out."""
    code, out, err = run_cli(capsys, "export", small_block, tmp_path / "pm.txt", "--format",
                             "photomodeler", "--pixel-size", "10")
    assert code == 0, err
    from sapgo.formats.photomodeler import import_photomodeler

    import_photomodeler(tmp_path / "pm.txt", tmp_path / "back.h5")
    rec, back = read_records(small_block), read_records(tmp_path / "back.h5")
    key = lambda r: np.lexsort((r["points"]["id"][r["observations"]["point"]],   # noqa
                                r["stations"]["id"][r["observations"]["station"]]))
    a, b = rec["observations"][key(rec)], back["observations"][key(back)]
    np.testing.assert_allclose(b["x"], a["x"], atol=1e-9)
    np.testing.assert_allclose(b["y"], a["y"], atol=1e-9)
    s1 = sapgo.adjust(small_block, sapgo.Options(progress=False))
    s2 = sapgo.adjust(tmp_path / "back.h5", sapgo.Options(progress=False))
    assert s2.sigma0 == pytest.approx(s1.sigma0, rel=1e-6)
    # the adjusted values written, read: the adjustment starts at its end
    code, out, err = run_cli(capsys, "export", small_block, tmp_path / "adj.txt", "--format",
                             "photomodeler", "--pixel-size", "10", "--adjusted")
    assert code == 0, err
    import_photomodeler(tmp_path / "adj.txt", tmp_path / "adj.h5")
    s3 = sapgo.adjust(tmp_path / "adj.h5", sapgo.Options(progress=False))
    assert s3.iterations <= 2 and s3.sigma0 == pytest.approx(s1.sigma0, rel=1e-6)
    code, out, err = run_cli(capsys, "export", small_block, tmp_path / "x.txt", "--format",
                             "photomodeler")
    assert_one_line_error(code, err, "--pixel-size")


def _layout(lines):
    """Where the blocks of a :func:`_write_pm` file start (indices into ``lines``): the
    first photo's camera line, the control, object and marked points."""
    k = 5
    while lines[k].strip():
        k += 6
    ctl = k + 1
    obj = next(i for i in range(ctl, len(lines)) if not lines[i].strip()) + 1
    mk = next(i for i in range(obj, len(lines)) if not lines[i].strip()) + 1
    return {"cam": 9, "ctl": ctl, "obj": obj, "mk": mk}


def _edited(small_block, tmp_path, edit):
    """A :func:`_write_pm` file changed by ``edit(lines, layout)`` (in place)."""
    _write_pm(small_block, tmp_path / "pm.txt")
    lines = (tmp_path / "pm.txt").read_text().splitlines()
    edit(lines, _layout(lines))
    (tmp_path / "pm.txt").write_text("\n".join(lines) + "\n")
    return tmp_path / "pm.txt"


def _set(lines, k, col, value):
    t = lines[k].split()
    t[col] = value
    lines[k] = "  " + " ".join(t)


def _import_refused(capsys, path, *words):
    """The CLI import of ``path`` stops with one line holding ``words``, no warning raised
    (a RuntimeWarning is an error here) and no project written."""
    import warnings

    out = path.parent / "x.h5"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        code, _, err = run_cli(capsys, "import", "--format", "photomodeler", path, out)
    assert_one_line_error(code, err, *words)
    assert not out.exists()


@pytest.mark.parametrize("col, value, words", [
    (1, "-152.0", "photo 1's camera: c must be positive, found -152"),
    (4, "0", "photo 1's camera: xs must be positive, found 0"),
    (4, "-230.0", "photo 1's camera: xs must be positive, found -230"),
    (5, "0.0", "photo 1's camera: ys must be positive, found 0"),
])
def test_a_photos_camera_row_is_checked(small_block, tmp_path, capsys, col, value, words):
    path = _edited(small_block, tmp_path, lambda ln, at: _set(ln, at["cam"], col, value))
    assert (tmp_path / "pm.txt").read_text().splitlines()[9].split()[0] == "1"
    _import_refused(capsys, path, "pm.txt:10:", words)


def test_ids_are_exact_integers(small_block, tmp_path, capsys):
    """An id beyond 2^53 is read exactly: it keeps its marks and does not merge with its
    neighbour; ids that are no integers or outside int64 are refused."""
    from sapgo.formats.photomodeler import import_photomodeler

    big = 9007199254740993

    def edit(lines, at):
        old = lines[at["obj"]].split()[0]
        _set(lines, at["obj"], 0, str(big))
        for k in range(at["mk"], len(lines)):
            if lines[k].split()[1] == old:
                _set(lines, k, 1, str(big))

    path = _edited(small_block, tmp_path, edit)
    r = import_photomodeler(path, tmp_path / "big.h5")
    with Project(tmp_path / "big.h5") as p:
        pt, ob = p.read("points"), p.read("observations")
    assert big in pt["id"].tolist() and big - 1 not in pt["id"].tolist()
    assert (pt["id"][ob["point"]] == big).sum() >= 2 and r["points"] == len(pt)
    # a mark on big - 1 names a point that is not there
    lines = path.read_text().splitlines()
    at = _layout(lines)
    k = next(k for k in range(at["mk"], len(lines)) if lines[k].split()[1] == str(big))
    _set(lines, k, 1, str(big - 1))
    path.write_text("\n".join(lines) + "\n")
    _import_refused(capsys, path, f"pm.txt:{k + 1}:", f"marked point {big - 1} is not")
    for value, words in (("99999999999999999999", "'99999999999999999999' is outside the "
                                                   "int64 range"),
                         ("1.0", "'1.0' is not an integer")):
        _set(lines, k, 1, value)
        path.write_text("\n".join(lines) + "\n")
        _import_refused(capsys, path, f"pm.txt:{k + 1}:", words)
    lines = _edited(small_block, tmp_path, lambda ln, at: None).read_text().splitlines()
    at = _layout(lines)
    _set(lines, at["ctl"], 0, "1e3")
    path.write_text("\n".join(lines) + "\n")
    _import_refused(capsys, path, f"pm.txt:{at['ctl'] + 1}:", "'1e3' is not an integer")


def _repeat(lines, k, change=None):
    """Line ``k`` written again after it, its column ``change[0]`` set to ``change[1]``."""
    lines.insert(k + 1, lines[k])
    if change:
        _set(lines, k + 1, *change)


@pytest.mark.parametrize("block, what", [("ctl", "control point"), ("obj", "object point")])
def test_a_point_given_twice(small_block, tmp_path, capsys, block, what):
    """Given twice with the same values: loaded once, with a warning; with different
    values: an error naming the id and both lines."""
    from sapgo.formats.photomodeler import import_photomodeler

    path = _edited(small_block, tmp_path, lambda ln, at: _repeat(ln, at[block]))
    lines = path.read_text().splitlines()
    k = _layout(lines)[block]
    pid = lines[k].split()[0]
    r = import_photomodeler(path, tmp_path / "once.h5")
    assert any(f"{what} {pid} is given again" in w and f"pm.txt:{k + 2}" in w
               for w in r["warnings"])
    (tmp_path / "ref").mkdir()
    ref = import_photomodeler(_edited(small_block, tmp_path / "ref", lambda ln, at: None),
                              tmp_path / "ref.h5")
    assert (r["points"], r["control_points"]) == (ref["points"], ref["control_points"])
    _set(lines, k + 1, 3, "500.0")
    path.write_text("\n".join(lines) + "\n")
    _import_refused(capsys, path, f"{what} {pid} is given twice with different values (Z)",
                    f"pm.txt:{k + 1} and ", f"pm.txt:{k + 2}")


def test_a_photo_given_twice(small_block, tmp_path, capsys):
    from sapgo.formats.photomodeler import import_photomodeler

    def edit(lines, at):
        lines[11:11] = lines[5:11]

    path = _edited(small_block, tmp_path, edit)
    r = import_photomodeler(path, tmp_path / "once.h5")
    assert r["photos"] == len(read_records(small_block)["stations"])
    assert any("photo 1 is given again" in w and "pm.txt:12" in w for w in r["warnings"])
    lines = path.read_text().splitlines()
    _set(lines, 12, 3, "4300.5")
    path.write_text("\n".join(lines) + "\n")
    _import_refused(capsys, path, "photo 1 is given twice with different values (Z): ",
                    "pm.txt:6 and ", "pm.txt:12")


def test_a_point_marked_twice_on_a_photo(small_block, tmp_path, capsys):
    """Within 3 sigma: one observation at the mean, with a warning; farther: an error
    naming the photo, the point and both lines."""
    from sapgo.formats.photomodeler import import_photomodeler

    def edit(lines, at):
        k = len(lines) - 1
        _repeat(lines, k, (2, repr(float(lines[k].split()[2]) + 1.0)))

    path = _edited(small_block, tmp_path, edit)
    lines = path.read_text().splitlines()
    n = len(lines)
    ph, pt = lines[-1].split()[:2]
    r = import_photomodeler(path, tmp_path / "merged.h5")
    assert r["observations"] == len(read_records(small_block)["observations"])
    assert any(f"photo {ph} point {pt} (lines {n - 1}, {n})" in w for w in r["warnings"])
    back = read_records(tmp_path / "merged.h5")
    o = back["observations"]
    mine = o[(back["stations"]["id"][o["station"]] == int(ph))
             & (back["points"]["id"][o["point"]] == int(pt))]
    col = (float(lines[-1].split()[2]) + float(lines[-2].split()[2])) / 2
    assert len(mine) == 1
    assert mine["x"][0] == pytest.approx(col * 230 / WIDTH - 115, abs=1e-12)
    _set(lines, n - 1, 2, repr(float(lines[-1].split()[2]) + 10000.0))
    path.write_text("\n".join(lines) + "\n")
    _import_refused(capsys, path, f"pm.txt: lines {n - 1} and {n}: point {pt} is marked "
                    f"twice on photo {ph}, 1e+04 px apart (more than 3 sigma = 1.8 px)")


def test_a_marks_sigma_must_not_be_negative(small_block, tmp_path, capsys):
    """A negative sigma is an error; 0 (like none) takes the camera's sigma."""
    from sapgo.formats.photomodeler import import_photomodeler

    path = _edited(small_block, tmp_path, lambda ln, at: (_set(ln, len(ln) - 1, 4, "0"),
                                                          _set(ln, len(ln) - 1, 5, "0")))
    import_photomodeler(path, tmp_path / "zero.h5")
    assert (read_records(tmp_path / "zero.h5")["observations"]["sigma"] == 0).sum() == 1
    lines = path.read_text().splitlines()
    _set(lines, len(lines) - 1, 4, "-0.6")
    path.write_text("\n".join(lines) + "\n")
    _import_refused(capsys, path, f"pm.txt:{len(lines)}: marked point sigma must be "
                    f"positive, found -0.6")


def test_an_empty_file(tmp_path, capsys):
    for text in ("", "\n  \n"):
        (tmp_path / "pm.txt").write_text(text)
        _import_refused(capsys, tmp_path / "pm.txt", "pm.txt: the file is empty")
