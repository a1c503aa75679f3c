"""Messages and help (issue 19, item 11): line ends of the text files, plain numbers in
messages, a closed standard output, help texts with their defaults, ``sapgo info`` of an
unordered project, points.csv of points the adjustment did not determine, and observations
given twice in BAL and Bundler files."""

import argparse
import csv
import io
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import assert_one_line_error, read_records, rewrite, run_cli

import sapgo
from sapgo.formats.bal import import_bal, read_bal, write_bal
from sapgo.formats.bundler import import_bundler, read_bundler, write_bundler
from sapgo.formats.text import export_text, read_chunks
from sapgo.project import KIND_CONTROL, Project

DUBROVNIK = Path(__file__).parent / "data" / "dubrovnik-3-7-pre.txt.gz"


def read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


# -- 1. line ends of the text files ---------------------------------------------------------

@pytest.mark.parametrize("end", [b"\r", b"\r\n", b"\n"], ids=["cr", "crlf", "lf"])
def test_read_chunks_takes_every_line_end(tmp_path, end):
    """Blocks hold ``\\n`` line ends only, one per line of the file, and their first line
    numbers count the file's lines, also where a ``\\r\\n`` is cut between two reads."""
    lines = [b"%d %s" % (i, b"x" * (i % 37)) for i in range(1, 2001)]
    data = end.join(lines)           # (no line end after the last line)
    f = tmp_path / "f.txt"
    f.write_bytes(data)
    blocks = list(read_chunks(f, 4096))
    assert len(blocks) > 3
    assert b"".join(c for _, c in blocks) == b"\n".join(lines) + b"\n"
    at = 1
    for first, chunk in blocks:
        assert first == at and int(chunk.split(maxsplit=1)[0]) == at
        at += chunk.count(b"\n")
    # a "\r\n" cut by the reads (4096 bytes: 4095 + "\r" | "\n" ...) ends one line
    f.write_bytes(b"#" * 4095 + b"\r\n2\r\n3")
    assert [(a, c.count(b"\n")) for a, c in read_chunks(f, 4096)] == [(1, 2), (3, 1)]


def _with_line_ends(src, dst, end):
    dst.mkdir(exist_ok=True)
    for f in src.iterdir():
        (dst / f.name).write_bytes(f.read_bytes().replace(b"\n", end))


def _import_dir(capsys, d, out):
    return run_cli(capsys, "import", "--cameras", d / "cameras.txt", "--photos",
                   d / "photos.txt", "--measurements", d / "measurements.txt", "--control",
                   d / "control.txt", out)


def test_text_files_with_mac_and_windows_line_ends_import_alike(small_block, tmp_path,
                                                                capsys):
    export_text(small_block, tmp_path / "lf")
    code, _, err = _import_dir(capsys, tmp_path / "lf", tmp_path / "lf.h5")
    assert code == 0, err
    ref = read_records(tmp_path / "lf.h5")
    for name, end in (("cr", b"\r"), ("crlf", b"\r\n")):
        _with_line_ends(tmp_path / "lf", tmp_path / name, end)
        code, _, err = _import_dir(capsys, tmp_path / name, tmp_path / f"{name}.h5")
        assert code == 0, (name, err)
        rec = read_records(tmp_path / f"{name}.h5")
        for key in ("cameras", "stations", "points", "observations"):
            assert rec[key].tobytes() == ref[key].tobytes(), (name, key)


def test_a_bad_line_of_a_cr_only_file_is_named_by_its_number(small_block, tmp_path, capsys):
    export_text(small_block, tmp_path / "lf")
    m = tmp_path / "lf" / "measurements.txt"
    lines = m.read_text().splitlines()
    lines[4] = lines[4].split()[0] + " " + lines[4].split()[1] + " 1.0 oops"
    m.write_bytes("\r".join(lines).encode() + b"\r")
    code, _, err = _import_dir(capsys, tmp_path / "lf", tmp_path / "x.h5")
    assert_one_line_error(code, err, "measurements.txt:5:", "'oops' is not a number")


# -- 2. plain numbers in messages -----------------------------------------------------------

def _dubrovnik(tmp_path, extra=(), **change):
    """Dubrovnik-3-7 written out as a plain BAL file, with observations ``extra``
    ((camera, point, x, y), appended) and the arrays of ``change`` replaced."""
    d = read_bal(DUBROVNIK)
    d.update(change)
    c, p, xy = d["obs_camera"], d["obs_point"], d["obs_xy"]
    if extra:
        e = np.array(extra, np.float64)
        c = np.concatenate([c, e[:, 0].astype(np.int64)])
        p = np.concatenate([p, e[:, 1].astype(np.int64)])
        xy = np.concatenate([xy, e[:, 2:]])
    f = tmp_path / "problem.txt"
    write_bal(f, d["cameras"], d["points"], c, p, xy)
    return f, d


def test_messages_print_plain_numbers_not_numpy_reprs(tmp_path, capsys):
    """Messages with numbers taken from arrays (a focal length, a duplicate's distance, a
    Bundler rotation's departure) print them as numbers."""
    d = read_bal(DUBROVNIK)
    cams = d["cameras"].copy()
    cams[1, 6] = -500.0
    f, _ = _dubrovnik(tmp_path, cameras=cams)
    code, _, err = run_cli(capsys, "import", "--format", "bal", f, tmp_path / "a.h5")
    assert_one_line_error(code, err, "focal length -500 is not positive")
    f, d = _dubrovnik(tmp_path, extra=[(d["obs_camera"][0], d["obs_point"][0],
                                        d["obs_xy"][0, 0] + 30.5, d["obs_xy"][0, 1])])
    code, _, err = run_cli(capsys, "import", "--format", "bal", f, tmp_path / "b.h5")
    assert_one_line_error(code, err, "30.5 px apart")
    r = np.tile(np.eye(3), (2, 1, 1))
    r[1, 0, 0] = 1.1
    b = tmp_path / "bundle.out"
    write_bundler(b, r, np.ones((2, 3)), np.array([[500.0, 0, 0]] * 2), np.zeros((1, 3)),
                  np.zeros((1, 3), np.uint8), np.array([0, 1]), np.array([0, 0]),
                  np.array([0, 0]), np.zeros((2, 2)))
    code, _, err = run_cli(capsys, "import", "--format", "bundler", b, tmp_path / "c.h5")
    assert_one_line_error(code, err, "departs from I by 0.21")
    for text in (err,):
        assert "np." not in text and "float64" not in text


# -- 3. a closed standard output ------------------------------------------------------------

def test_info_into_a_closed_pipe_is_quiet(small_block):
    """``sapgo info P | head -0``: no 'Broken pipe', no traceback, exit code 0."""
    proc = subprocess.Popen([sys.executable, "-m", "sapgo.cli", "info", str(small_block)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()   # (before the interpreter has started: every write fails)
    err = proc.stderr.read().decode()
    proc.stderr.close()
    assert proc.wait(timeout=120) == 0, err
    assert "pipe" not in err.lower() and "Traceback" not in err, err


class _ClosedPipe(io.StringIO):
    """A standard output whose reader has gone."""

    def write(self, text):
        raise BrokenPipeError(32, "Broken pipe")

    def flush(self):
        raise BrokenPipeError(32, "Broken pipe")


def test_report_into_a_closed_stdout_still_writes_its_tables(small_block, tmp_path, capsys,
                                                             monkeypatch):
    sapgo.adjust(small_block, sapgo.Options(progress=False))
    monkeypatch.setattr(sys, "stdout", _ClosedPipe())
    code, _, err = run_cli(capsys, "report", small_block, "--csv", tmp_path / "csv")
    assert code == 0 and "pipe" not in err.lower() and "error" not in err, err
    assert len(read_csv(tmp_path / "csv" / "points.csv")) > 10


# -- 4. help texts --------------------------------------------------------------------------

#: Flags whose help says what happens without them (not to be reworded here).
IMPLICIT_DEFAULT = {("generate", "--force"), ("adjust", "--reset-rejections")}


def test_every_command_and_option_has_a_help_text_with_its_default():
    from sapgo.cli import build_parser

    ap = build_parser()
    sub = next(a for a in ap._actions if isinstance(a, argparse._SubParsersAction))
    helps = {c.dest: c.help for c in sub._choices_actions}
    missing = []
    for name, parser in sub.choices.items():
        if not helps.get(name) or not parser.description:
            missing.append(f"{name}: help and description")
        for a in parser._actions:
            if isinstance(a, argparse._HelpAction):
                continue
            opt = a.option_strings[0] if a.option_strings else a.dest
            if not a.help:
                missing.append(f"{name} {opt}: help")
            elif a.option_strings and "default" not in a.help.lower() and \
                    (name, opt) not in IMPLICIT_DEFAULT:
                missing.append(f"{name} {opt}: its default")
    assert not missing, missing


@pytest.mark.parametrize("command, words", [
    ("generate", ["--strips N", "(default 4", "(default 25"]),
    ("order", ["the project file", "(default"]),
    ("info", ["Describe a project file", "(default: one item a line)"]),
])
def test_help_shows_the_defaults(capsys, command, words):
    from sapgo.cli import main

    with pytest.raises(SystemExit) as e:
        main([command, "--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert e.value.code == 0
    for w in words:
        assert w in out, w


# -- 5. info of an unordered project -----------------------------------------------------------

def test_info_says_an_unordered_project_has_no_band_width_yet(small_block, capsys):
    code, out, err = run_cli(capsys, "info", small_block)
    assert code == 0, err
    line = next(ln for ln in out.splitlines() if ln.startswith("band_width"))
    assert "not ordered yet" in line and "0" not in line, line
    code, out, _ = run_cli(capsys, "info", small_block, "--json")
    info = json.loads(out)
    assert info["ordered"] is False and info["band_width"] is None
    assert run_cli(capsys, "order", small_block)[0] == 0
    code, out, _ = run_cli(capsys, "info", small_block, "--json")
    info = json.loads(out)
    assert info["ordered"] is True and info["band_width"] > 0


# -- 6. points.csv of points not determined ---------------------------------------------------

def test_points_csv_leaves_a_rejected_control_point_empty(tmp_path, capsys):
    """A weighted control point on two photos, one with a 100 um blunder: data snooping
    takes both rays, and points.csv says 'rejected' with empty sigmas, residual and
    adjusted minus known (not the zeros or stale values of a point not adjusted); another
    control point on one photo is determined by its control and shows the sigmas stored in
    /solution/point_sigma."""
    path = tmp_path / "b.h5"
    sapgo.generate_block(path, strips=3, photos_per_strip=8, control_points=8,
                         control_sigma=0.05, progress=False)
    rec = read_records(path)
    pt, ob = rec["points"], rec["observations"]
    bad, one = (int(j) for j in np.flatnonzero(pt["kind"] == KIND_CONTROL)[:2])
    rays = {j: np.flatnonzero(ob["point"] == j) for j in (bad, one)}
    ob["x"][rays[bad][0]] += 0.1
    rec["observations"] = np.delete(ob, np.concatenate([rays[bad][2:], rays[one][1:]]))
    rewrite(path, rec)
    s = sapgo.adjust(path, sapgo.Options(progress=False, snooping=True))
    assert s.converged and any(r["point_id"] == pt["id"][bad] for r in s.rejected)
    code, _, err = run_cli(capsys, "report", path, "--quiet", "--csv", tmp_path / "csv")
    assert code == 0, err
    rows = {int(r["point_id"]): r for r in read_csv(tmp_path / "csv" / "points.csv")}
    r = rows[int(pt["id"][bad])]
    assert r["kind"] == "control" and r["status"] == "rejected" and r["n_rays"] == "0"
    for col in ("sX_m", "sY_m", "sZ_m", "max_residual_um", "dX_m", "dY_m", "dZ_m"):
        assert r[col] == "", (col, r)
    with Project(path) as p:   # (the adjustment ordered the points)
        sig = p.solution("point_sigma")[np.flatnonzero(p.read("points")["id"]
                                                       == pt["id"][one])[0]]
    r = rows[int(pt["id"][one])]
    assert r["status"] == "active" and r["n_rays"] == "1" and sig[0] > 0
    for k, col in enumerate(("sX_m", "sY_m", "sZ_m")):
        assert float(r[col]) == pytest.approx(sig[k], rel=1e-5)
    assert r["dX_m"] != "" and r["max_residual_um"] != ""
    obs = read_csv(tmp_path / "csv" / "observations.csv")
    assert {o["flag"] for o in obs if int(o["point_id"]) == pt["id"][bad]} == {"rejected"}
    # a point the run set aside (its rays nearly parallel) and did not bring back
    import h5py

    from sapgo.tables import write_tables

    pid = next(i for i, r in rows.items() if r["kind"] == "check" and r["status"] == "active")
    with h5py.File(path, "r+") as f:
        report = json.loads(f["solution/report"][()])
        report["set_aside"] = [{"point": pid, "set_aside": 2, "back": None}]
        del f["solution/report"]
        f["solution"].create_dataset("report", data=json.dumps(report))
    write_tables(path, tmp_path / "csv2")
    r = next(r for r in read_csv(tmp_path / "csv2" / "points.csv") if int(r["point_id"]) == pid)
    assert r["status"] == "set_aside" and r["n_rays"] != "0"
    for col in ("sX_m", "sY_m", "sZ_m", "max_residual_um", "dX_m", "dY_m", "dZ_m"):
        assert r[col] == "", (col, r)
    obs = read_csv(tmp_path / "csv2" / "observations.csv")
    assert {o["flag"] for o in obs if int(o["point_id"]) == pid} == {"excluded"}


# -- 7. observations given twice in BAL and Bundler files ----------------------------------------

def test_bal_duplicates_within_three_pixels_are_merged_with_a_warning(tmp_path, capsys):
    d = read_bal(DUBROVNIK)
    c, p, xy = int(d["obs_camera"][3]), int(d["obs_point"][3]), d["obs_xy"][3]
    n = len(d["obs_camera"])
    f, _ = _dubrovnik(tmp_path, extra=[(c, p, xy[0] + 1.0, xy[1] - 2.0)])
    code, out, err = run_cli(capsys, "import", "--format", "bal", f, tmp_path / "a.h5")
    assert code == 0, err
    warn = [ln for ln in err.splitlines() if ln.startswith("sapgo: warning:")]
    assert len(warn) == 1 and "1 (camera, point) pair(s)" in warn[0], err
    assert f"camera {c} point {p} (lines 5, {n + 2})" in warn[0]
    assert f"{n} image observations" in out
    with Project(tmp_path / "a.h5") as prj:
        ob = prj.read("observations")
    mine = (ob["station"] == c) & (ob["point"] == p)
    assert mine.sum() == 1
    np.testing.assert_allclose([ob["x"][mine][0], ob["y"][mine][0]],
                               [xy[0] + 0.5, xy[1] - 1.0])


def test_bal_duplicates_far_apart_are_one_line_error(tmp_path, capsys):
    d = read_bal(DUBROVNIK)
    c, p, xy = int(d["obs_camera"][0]), int(d["obs_point"][0]), d["obs_xy"][0]
    n = len(d["obs_camera"])
    f, _ = _dubrovnik(tmp_path, extra=[(c, p, xy[0] + 60.0, xy[1] + 80.0)])
    code, _, err = run_cli(capsys, "import", "--format", "bal", f, tmp_path / "a.h5")
    assert_one_line_error(code, err, "problem.txt", f"lines 2 and {n + 2}", f"camera {c}",
                          f"point {p}", "100 px apart", "use --merge-duplicates to average")
    assert not (tmp_path / "a.h5").exists()
    r = import_bal(f, tmp_path / "b.h5", merge_duplicates=True)
    assert r["observations"] == n and r["duplicates_dropped"] == 1
    assert any("more than 3 sigma" in w and "100 px" in w for w in r["warnings"])
    with Project(tmp_path / "b.h5") as prj:
        ob = prj.read("observations")
    mine = (ob["station"] == c) & (ob["point"] == p)
    np.testing.assert_allclose([ob["x"][mine][0], ob["y"][mine][0]],
                               [xy[0] + 30.0, xy[1] + 40.0])


def _bundler_with_twice(tmp_path, shift):
    """Dubrovnik-3-7 as a Bundler file whose first point lists its first camera twice, the
    second time ``shift`` pixels off."""
    from sapgo.formats.bal import rodrigues

    d = read_bal(DUBROVNIK)
    cams = d["cameras"]
    c, p, xy = d["obs_camera"], d["obs_point"], d["obs_xy"]
    first = int(np.flatnonzero(p == 0)[0])
    c = np.append(c, c[first])
    p = np.append(p, 0)
    xy = np.vstack([xy, xy[first] + shift])
    f = tmp_path / "bundle.out"
    write_bundler(f, rodrigues(cams[:, :3]), cams[:, 3:6], cams[:, 6:9], d["points"],
                  np.zeros((len(d["points"]), 3), np.uint8), c, p, np.arange(len(c)), xy)
    return f, int(c[first]), xy[first]


def test_bundler_duplicates_are_merged_or_refused_alike(tmp_path, capsys):
    f, cam, xy = _bundler_with_twice(tmp_path, np.array([0.0, 2.0]))
    n = len(read_bundler(f)["obs_camera"])
    r = import_bundler(f, tmp_path / "a.h5")
    assert r["observations"] == n - 1 and len(r["warnings"]) == 1
    assert f"camera {cam} point 0" in r["warnings"][0]
    f, cam, xy = _bundler_with_twice(tmp_path, np.array([0.0, 100.0]))
    code, _, err = run_cli(capsys, "import", "--format", "bundler", f, tmp_path / "b.h5")
    # the point's view list is line 2 + 5 * 3 cameras + 3 (its position and colour)
    assert_one_line_error(code, err, "bundle.out: lines 20 (view 1) and 20 (view", f"camera "
                          f"{cam} observes point 0 twice, 100 px apart", "--merge-duplicates")
    r = import_bundler(f, tmp_path / "c.h5", merge_duplicates=True)
    assert r["observations"] == n - 1 and r["duplicates_dropped"] == 1
