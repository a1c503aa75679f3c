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
