"""The command line as a user drives it."""

import json

import numpy as np

from conftest import read_records, rewrite
from sapgo.cli import main
from sapgo.project import Project

REQUIRED = {"converged", "iterations", "sigma0", "image_rms_um", "band_width", "n_stations",
            "n_points", "n_observations", "check_points", "timings_s"}


def test_generate_order_adjust_info(tmp_path, capsys):
    path = tmp_path / "p1.h5"
    assert main(["generate", "--preset", "sapgo-p-1", str(path)]) == 0
    out = capsys.readouterr().out
    assert "100 photos" in out and "225 points" in out and "16 control" in out
    assert main(["order", str(path)]) == 0
    out = capsys.readouterr().out
    assert "band width before: 28" in out and "band width after:  10" in out
    report = tmp_path / "out" / "report.json"
    assert main(["adjust", str(path), "--json", str(report), "--no-progress"]) == 0
    out = capsys.readouterr().out
    for words in ("sigma0", "check points (209)", "band width 10", "build", "solve", "update"):
        assert words in out
    r = json.loads(report.read_text())
    assert REQUIRED <= set(r)
    assert set(r["check_points"]) >= {"n", "sx", "sy", "sz", "sxy"}
    assert set(r["timings_s"]) >= {"order", "build", "solve", "update", "total"}
    assert r["converged"] and r["iterations"] <= 6 and r["check_points"]["n"] == 209
    assert r["n_stations"] == 100 and r["n_points"] == 225 and r["n_observations"] == 876
    assert main(["info", str(path), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["adjusted"] and info["band_width"] == 10 and info["stations"] == 100
    with Project(path) as p:
        assert p.history()[-1]["command"] == "adjust"


def test_parameterised_generate(tmp_path, capsys):
    path = tmp_path / "b.h5"
    code = main(["generate", str(path), "--strips", "3", "--photos-per-strip", "7",
                 "--pattern", "25", "--control-points", "12", "--seed", "4",
                 "--sigma-image", "3", "--sidelap", "0.3"])
    assert code == 0
    rec = read_records(path)
    assert len(rec["stations"]) == 21
    assert len(rec["points"]) == (4 * 3 + 1) * (2 * 7 - 1)
    assert (rec["points"]["kind"] == 1).sum() == 12
    assert np.isclose(rec["observations"]["sigma"][0], 0.003)


def test_single_ray_point_is_reported(small_block, capsys):
    rec = read_records(small_block)
    ob = rec["observations"]
    j = int(np.flatnonzero(rec["points"]["kind"] == 4)[0])  # a check point
    pid = int(rec["points"]["id"][j])
    rec["observations"] = np.delete(ob, np.flatnonzero(ob["point"] == j)[1:])
    rewrite(small_block, rec)
    assert main(["adjust", str(small_block), "--no-progress", "--quiet"]) == 0
    err = capsys.readouterr().err
    assert "fewer than 2 photos" in err and str(pid) in err
    with Project(small_block) as p:
        assert pid in p.read_field("points", "id")
