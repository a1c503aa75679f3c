"""Residual reports (CSV tables), plots and ``sapgo report``."""

import csv
import json
import math

import numpy as np
import pytest
from conftest import run_cli

import sapgo
from sapgo.project import KIND_NAMES, Project


def read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture
def snooped(tmp_path):
    """A small block with planted blunders, adjusted with data snooping."""
    path = tmp_path / "b.h5"
    sapgo.generate_block(path, strips=3, photos_per_strip=8, control_points=8, blunders=3,
                         blunder_size=(0.08, 0.1))
    s = sapgo.adjust(path, sapgo.Options(progress=False, snooping=True))
    assert s.rejected
    return path, s


def test_tables_agree_with_the_solution(snooped, tmp_path, capsys):
    path, s = snooped
    code, text, err = run_cli(capsys, "report", path, "--quiet", "--csv", tmp_path / "csv")
    assert code == 0, err
    photos = read_csv(tmp_path / "csv" / "photos.csv")
    points = read_csv(tmp_path / "csv" / "points.csv")
    obs = read_csv(tmp_path / "csv" / "observations.csv")
    with Project(path) as p:
        st, pt, ob = p.read("stations"), p.read("points"), p.read("observations")
        res = 1000 * p.solution("residuals")
        psig = p.solution("point_sigma")
        ssig = p.solution("station_sigma")
        q = p.solution("obs_quality")
        xyz = pt["xyz"] + p.solution("point_corr")
        eo = st["eo"] + p.solution("station_corr")
    assert len(photos) == len(st) and len(points) == len(pt) and len(obs) == len(ob)
    # per observation: residuals, w, t and the flag of the rejected ones
    np.testing.assert_allclose([float(o["vx_um"]) for o in obs], res[:, 0], atol=1e-3)
    ok = [o["flag"] == "ok" for o in obs]
    np.testing.assert_allclose([float(o["t"]) for o, k in zip(obs, ok) if k], q[ok, 5],
                               atol=1e-3)
    flagged = {(int(o["photo_id"]), int(o["point_id"])) for o in obs
               if o["flag"] == "rejected"}
    assert flagged == {(r["photo_id"], r["point_id"]) for r in s.rejected}
    for i, o in enumerate(obs):
        if o["flag"] == "rejected":
            assert o["r_x"] == "" and o["mdb_um"] == "" and float(o["weight"]) == 0
            # the rejected observation keeps its residual: a planted blunder of 80-100 um;
            # and gets the test it would have brought back alone, above the critical 3.72
            if (int(o["photo_id"]), int(o["point_id"])) in {
                    (r["photo_id"], r["point_id"]) for r in s.rejected if r["by"] == "test"}:
                assert math.hypot(float(o["vx_um"]), float(o["vy_um"])) > 30
                assert float(o["t"]) == pytest.approx(q[i, 5], abs=1e-3) and q[i, 5] > 3.72
        else:
            assert float(o["mdb_um"]) > 6 * math.sqrt(s.reliability["lambda0"])
    # per photo: RMS and count recomputed from the residuals
    act = ob["status"] == 0
    for i in (0, len(st) // 2, len(st) - 1):
        m = act & (ob["station"] == i)
        row = photos[i]
        assert int(row["photo_id"]) == st["id"][i] and int(row["n_points"]) == m.sum()
        assert float(row["rms_x_um"]) == pytest.approx(np.sqrt(np.mean(res[m, 0] ** 2)),
                                                       abs=1e-3)
        assert float(row["max_um"]) == pytest.approx(np.hypot(*res[m].T).max(), abs=1e-3)
        assert float(row["X_m"]) == pytest.approx(eo[i, 3], abs=1e-6)
        assert float(row["s_omega_arcsec"]) == pytest.approx(
            ssig[i, 0] * 180 / math.pi * 3600, rel=1e-5)
    # per point: kind marked, sigmas, rays, adjusted minus known of check points
    kinds = {r["kind"] for r in points}
    assert {"control", "check", "pass"} <= kinds or {"control", "check"} <= kinds
    for j in range(len(pt)):
        r = points[j]
        assert r["kind"] == KIND_NAMES[int(pt["kind"][j])]
        assert float(r["Z_m"]) == pytest.approx(xyz[j, 2], abs=1e-6)
        if r["status"] == "active" and psig[j, 0] > 0:
            assert float(r["sX_m"]) == pytest.approx(psig[j, 0], rel=1e-5)
        if r["kind"] in ("check", "control"):
            assert float(r["dZ_m"]) == pytest.approx(xyz[j, 2] - pt["control"][j, 2],
                                                      abs=1e-6)
        else:
            assert r["dZ_m"] == ""


def test_a_one_ray_control_point_is_active_with_its_sigmas(tmp_path, capsys):
    """A weighted full control point seen on one photo is determined (its control fixes
    it): points.csv gives it active, with the sigmas the adjustment stored."""
    from conftest import read_records, rewrite

    from sapgo.project import KIND_CONTROL

    path = tmp_path / "b.h5"
    sapgo.generate_block(path, strips=3, photos_per_strip=8, control_points=8,
                         control_sigma=0.05, progress=False)
    rec = read_records(path)
    pt, ob = rec["points"], rec["observations"]
    j = int(np.flatnonzero(pt["kind"] == KIND_CONTROL)[0])
    pid = int(pt["id"][j])
    mine = np.flatnonzero(ob["point"] == j)
    assert len(mine) >= 2
    rec["observations"] = np.delete(ob, mine[1:])   # (one ray left)
    rewrite(path, rec)
    s = sapgo.adjust(path, sapgo.Options(progress=False))
    assert s.converged
    code, text, err = run_cli(capsys, "report", path, "--quiet", "--csv", tmp_path / "csv")
    assert code == 0, err
    with Project(path) as p:
        sig = p.solution("point_sigma")[np.flatnonzero(p.read("points")["id"] == pid)[0]]
    row = next(r for r in read_csv(tmp_path / "csv" / "points.csv")
               if int(r["point_id"]) == pid)
    assert row["kind"] == "control" and int(row["n_rays"]) == 1 and sig[0] > 0
    assert row["status"] == "active"
    assert float(row["sX_m"]) == pytest.approx(sig[0], rel=1e-5)


def test_tables_in_a_geographic_crs(block_cache, tmp_path):
    """A project imported in longitude, latitude, height gets them with 9 decimals."""
    from test_frames import block_in_crs

    from sapgo.tables import write_tables

    _, geo, _ = block_in_crs(block_cache, tmp_path)
    sapgo.adjust(geo, sapgo.Options(progress=False))
    write_tables(geo, tmp_path / "csv")
    points = read_csv(tmp_path / "csv" / "points.csv")
    assert len(points[0]["lon_deg"].split(".")[1]) == 9
    assert 11 < float(points[0]["lon_deg"]) < 12 and 47.5 < float(points[0]["lat_deg"]) < 48.5
    photos = read_csv(tmp_path / "csv" / "photos.csv")
    assert abs(float(photos[0]["omega_enu_deg"])) < 1.0


def test_plots_are_written(snooped, tmp_path, capsys):
    pytest.importorskip("matplotlib")
    path, _ = snooped
    code, text, err = run_cli(capsys, "report", path, "--quiet", "--plots", tmp_path / "pl")
    assert code == 0, err
    names = sorted(x.name for x in (tmp_path / "pl").iterdir())
    assert names == ["checkpoints.png", "layout.png", "matrix.png", "residuals_camera_1.png"]
    for n in names:
        assert (tmp_path / "pl" / n).stat().st_size > 10_000


def test_matrix_pattern_is_the_band(small_block):
    """The station pairs drawn as the reduced matrix are those sharing a point, and the
    widest of them spans the band width."""
    from sapgo.plots import station_pairs

    sapgo.order_project(small_block)
    with Project(small_block) as p:
        pairs = np.concatenate(list(station_pairs(p, chunk=7)))
        ob, bw = p.read("observations"), p.band_width
    ref = set()
    for j in np.unique(ob["point"]):
        s = ob["station"][ob["point"] == j]
        ref |= {(min(a, b), max(a, b)) for a in s for b in s}
    assert set(map(tuple, pairs.tolist())) == ref
    assert (pairs[:, 1] - pairs[:, 0]).max() + 1 == bw


def test_report_needs_an_adjusted_project(small_block, capsys):
    from conftest import assert_one_line_error

    code, text, err = run_cli(capsys, "report", small_block, "--csv", "x")
    assert code == 2
    assert_one_line_error(code, err, "no adjusted solution")


def test_report_command_prints_the_stored_report(snooped, capsys):
    path, s = snooped
    code, text, err = run_cli(capsys, "report", path)
    assert code == 0 and "data snooping rejected" in text and "reliability:" in text, err
    code, text, err = run_cli(capsys, "report", path, "--json")
    assert json.loads(text)["sigma0"] == pytest.approx(s.sigma0)


def test_matrix_envelope_holds_the_fill_in(block_cache, tmp_path):
    """Every non-zero block of the Cholesky factor of a matrix with the reduced normals'
    block pattern lies inside the drawn envelope; blocks drawn non-zero are those pairs."""
    import shutil

    from sapgo.plots import matrix_pattern, station_pairs

    path = tmp_path / "p.h5"
    shutil.copy(block_cache("small3", strips=3, photos_per_strip=6, control_points=6), path)
    sapgo.order_project(path, "reverse_cuthill_mckee")
    with Project(path) as p:
        img, bw = matrix_pattern(p)
        pairs = np.concatenate(list(station_pairs(p)))
        n = p.n_stations
    rng = np.random.default_rng(0)
    m = np.zeros((n, n))
    m[pairs[:, 0], pairs[:, 1]] = rng.uniform(0.1, 1.0, len(pairs))
    m = m + m.T + 4 * n * np.eye(n)
    u = np.linalg.cholesky(m).T  # upper factor, one scalar per station block
    nz = np.abs(u) > 1e-14
    assert (img[nz | nz.T] >= 1).all()
    assert ((img == 2) == ((m != 0) & ~np.eye(n, dtype=bool) | np.eye(n, dtype=bool))).all()
    assert (img == 1).any()  # the block has fill-in to hold


def test_plots_without_matplotlib_are_refused_before_the_run(small_block, capsys,
                                                              monkeypatch):
    import sys

    from conftest import assert_one_line_error

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import fails
    code, text, err = run_cli(capsys, "adjust", small_block, "--plots", "x", "--no-progress")
    assert_one_line_error(code, err, "plots need matplotlib")
    with Project(small_block) as p:
        assert not p.has_solution  # refused before adjusting
