"""``sapgo import``: text files in, the same records out, in any order and within the budget."""

import shutil
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import sapgo
from conftest import assert_one_line_error, digest, read_records, rewrite, run_cli
from sapgo.errors import DataError, ParameterError
from sapgo.formats.text import export_text
from sapgo.ingest import import_text
from sapgo.project import KIND_PASS, Project

DATASETS = ("cameras", "stations", "station_priors", "points", "observations")


# -- helpers ---------------------------------------------------------------------------





def dataset_bytes(path):
    with Project(path) as p:
        return {k: p.read(k).tobytes() for k in DATASETS}


def assert_same_records(a, b):
    da, db = dataset_bytes(a), dataset_bytes(b)
    for k in DATASETS:
        assert da[k] == db[k], f"/{k} differs"


def data_lines(path):
    """The data lines of a text file (comments and blank lines dropped)."""
    return [ln for ln in path.read_text().splitlines() if ln.strip() and ln[0] != "#"]


def write_lines(path, lines, header="# written by the test\n"):
    path.write_text(header + "".join(ln + "\n" for ln in lines))
    return path


def files_of(d):
    return dict(cameras=d / "cameras.txt", photos=d / "photos.txt",
                measurements=d / "measurements.txt", control=d / "control.txt")


def cli_args(files):
    args = []
    for k, v in files.items():
        for f in v if isinstance(v, list) else [v]:
            args += [f"--{k}", f]
    return args


@pytest.fixture
def exported(small_block, tmp_path):
    """The small generated block and its text export (degrees)."""
    d = tmp_path / "txt"
    export_text(small_block, d)
    return small_block, d


def by_key(arr, keys):
    return arr[np.lexsort(tuple(arr[k] for k in reversed(keys)))]


def input_records_by_id(path):
    """A project's input records keyed by the user's ids, independent of record order."""
    rec = read_records(path)
    cams, st, pt, ob = rec["cameras"], rec["stations"], rec["points"], rec["observations"]
    stations = np.zeros(len(st), [("id", "<i8"), ("camera", "<i8"), ("strip", "<i8"),
                                  ("eo", "<f8", (6,))])
    stations["id"], stations["camera"] = st["id"], cams["id"][st["camera"]]
    stations["strip"], stations["eo"] = st["strip"], st["eo"]
    used = (pt["kind"] != KIND_PASS) | (pt["n_obs"] > 0)
    points = pt[used][["id", "kind", "control", "control_sigma"]]
    points = np.array(points, np.dtype([("id", "<i8"), ("kind", "i1"), ("control", "<f8", (3,)),
                                        ("control_sigma", "<f8", (3,))]))
    points["control"][points["kind"] == KIND_PASS] = 0.0
    points["control_sigma"][points["kind"] == KIND_PASS] = 0.0
    obs = np.zeros(len(ob), [("photo", "<i8"), ("point", "<i8"), ("x", "<f8"), ("y", "<f8"),
                             ("sigma", "<f8")])
    obs["photo"], obs["point"] = st["id"][ob["station"]], pt["id"][ob["point"]]
    obs["x"], obs["y"], obs["sigma"] = ob["x"], ob["y"], ob["sigma"]
    return {"cameras": np.sort(cams, order="id").tobytes(),
            "stations": by_key(stations, ["id"]).tobytes(),
            "points": by_key(points, ["id"]).tobytes(),
            "observations": by_key(obs, ["photo", "point", "x", "y"]).tobytes()}


def adjusted_by_id(path):
    with Project(path) as p:
        st, pt = p.read("stations"), p.read("points")
        eo = st["eo"] + p.solution("station_corr")
        xyz = pt["xyz"] + p.solution("point_corr")
    return (dict(zip(st["id"].tolist(), eo)),
            dict(zip(pt["id"][pt["status"] == 0].tolist(), xyz[pt["status"] == 0])))


# -- round trip ------------------------------------------------------------------------

def test_export_import_reproduces_the_generated_block_and_its_adjustment(exported, tmp_path):
    gen, d = exported
    out = tmp_path / "imported.h5"
    s = import_text(out, **files_of(d))
    assert input_records_by_id(out) == input_records_by_id(gen)
    rec = read_records(gen)
    assert s["photos"] == len(rec["stations"]) and s["observations"] == len(rec["observations"])
    assert s["points_by_kind"]["control"] == int((rec["points"]["kind"] == 1).sum())
    assert s["warnings"] == []
    with Project(out) as p:
        assert not p.ordered and p.n_priors == 0 and not p.has_truth
        assert p.history()[-1]["command"] == "import"
        pt = p.read("points")
        assert (np.diff(pt["id"]) > 0).all() and (pt["station_min"] == -1).all()
        assert np.isfinite(pt["xyz"]).all()
        st = p.read("stations")
        assert (np.diff(st["id"]) > 0).all()
        ob = p.read("observations")
        key = ob["point"] * len(st) + ob["station"]
        assert (np.diff(key) > 0).all()  # grouped by point, by station within a point

    # both adjust to the same result (the text formats carry no station priors)
    if len(rec["station_priors"]):
        rec["station_priors"] = rec["station_priors"][:0]
        rewrite(gen, rec)
    opts = sapgo.Options(progress=False)
    assert sapgo.adjust(gen, opts).converged and sapgo.adjust(out, opts).converged
    (eo_g, xyz_g), (eo_i, xyz_i) = adjusted_by_id(gen), adjusted_by_id(out)
    assert eo_g.keys() == eo_i.keys() and xyz_g.keys() == xyz_i.keys()
    for k in eo_g:
        assert np.abs(eo_g[k][3:] - eo_i[k][3:]).max() < 1e-6
        assert np.abs(eo_g[k][:3] - eo_i[k][:3]).max() < 1e-9
    assert max(np.abs(xyz_g[k] - xyz_i[k]).max() for k in xyz_g) < 1e-6


def test_a_camera_with_lens_distortion_imports_and_adjusts(block_cache, tmp_path):
    """Distortion coefficients travel through export and import without a warning; the rays
    are freed of distortion before the approximate points are intersected, and both files
    adjust to the same result."""
    gen = tmp_path / "dist.h5"
    shutil.copy(block_cache("small-dist", strips=2, photos_per_strip=6, control_points=6,
                            distortion=(-2.0e-8, 3.0e-13, -1.0e-18, 1.5e-6, -1.0e-6)), gen)
    d = tmp_path / "text"
    export_text(gen, d)
    out = tmp_path / "imported.h5"
    s = import_text(out, **files_of(d))
    assert s["warnings"] == []
    assert input_records_by_id(out) == input_records_by_id(gen)
    with Project(gen) as p:
        ref = p.read("points")["xyz"]
    with Project(out) as p:
        approx = p.read("points")["xyz"]
    assert np.abs(approx - ref).max() < 1e-6  # the same intersection as the generator's
    opts = sapgo.Options(progress=False)
    assert sapgo.adjust(gen, opts).converged and sapgo.adjust(out, opts).converged
    (eo_g, xyz_g), (eo_i, xyz_i) = adjusted_by_id(gen), adjusted_by_id(out)
    assert max(np.abs(xyz_g[k] - xyz_i[k]).max() for k in xyz_g) < 1e-6
    assert max(np.abs(eo_g[k] - eo_i[k]).max() for k in eo_g) < 1e-6


def test_a_backward_camera_with_affinity_goes_out_and_comes_back(block_cache, tmp_path,
                                                                   capsys):
    """A camera of the backward distortion model with affinity and shear is written with
    its 15 columns and read back to the same records and the same adjustment; an unknown
    model word is one line naming the file, the line and the column."""
    gen = tmp_path / "back.h5"
    shutil.copy(block_cache("small-dist", strips=2, photos_per_strip=6, control_points=6,
                            distortion=(-2.0e-8, 3.0e-13, -1.0e-18, 1.5e-6, -1.0e-6)), gen)
    rec = read_records(gen)
    rec["cameras"][["b1", "b2", "distortion_model"]] = (3e-4, -2e-4, 1)
    rewrite(gen, rec)
    d = tmp_path / "text"
    export_text(gen, d)
    line = data_lines(d / "cameras.txt")[0].split()
    assert len(line) == 15 and line[-1] == "backward"
    out = tmp_path / "imported.h5"
    import_text(out, **files_of(d))
    assert input_records_by_id(out) == input_records_by_id(gen)
    opts = sapgo.Options(progress=False)
    assert sapgo.adjust(gen, opts).sigma0 == pytest.approx(sapgo.adjust(out, opts).sigma0,
                                                           rel=1e-12)
    line[-1] = "backwards"
    write_lines(d / "cameras.txt", [" ".join(line)])
    code, _, err = run_cli(capsys, "import", tmp_path / "bad.h5", *cli_args(files_of(d)))
    assert_one_line_error(code, err, "cameras.txt:2: ", "unknown distortion model 'backwards' "
                          "(column 15); expected forward")


@pytest.mark.parametrize("angles", ["gon", "rad"])
def test_every_angle_unit_reads_back_bitwise(exported, tmp_path, angles):
    gen, d = exported
    export_text(gen, tmp_path / angles, angles=angles)
    import_text(tmp_path / "deg.h5", **files_of(d))
    import_text(tmp_path / f"{angles}.h5", angles=angles, **files_of(tmp_path / angles))
    assert_same_records(tmp_path / "deg.h5", tmp_path / f"{angles}.h5")


def test_shuffled_measurement_files_give_bitwise_the_same_project(exported, tmp_path):
    _, d = exported
    files = files_of(d)
    strip_of = {ln.split()[0]: int(ln.split()[2]) for ln in data_lines(files["photos"])}
    lines = data_lines(files["measurements"])
    in_strip_order = sorted(lines, key=lambda ln: (strip_of[ln.split()[0]], int(ln.split()[0])))
    write_lines(tmp_path / "strips.txt", in_strip_order)
    import_text(tmp_path / "a.h5", **dict(files, measurements=tmp_path / "strips.txt"))

    rng = np.random.default_rng(7)
    by_photo = {}
    for ln in lines:
        by_photo.setdefault(ln.split()[0], []).append(ln)
    shuffled = []
    for photo in rng.permutation(sorted(by_photo)):
        group = by_photo[photo]
        shuffled += [f"# photo {photo}", ""] + [group[i] for i in rng.permutation(len(group))]
    shuffled = [ln + "   # a remark" if i % 7 == 0 and ln else ln for i, ln in enumerate(shuffled)]
    half = len(shuffled) // 2
    parts = [write_lines(tmp_path / "m2.txt", shuffled[half:]),
             write_lines(tmp_path / "m1.txt", shuffled[:half])]
    import_text(tmp_path / "b.h5", memory="4M", **dict(files, measurements=parts))
    assert_same_records(tmp_path / "a.h5", tmp_path / "b.h5")


# -- duplicates ------------------------------------------------------------------------

def test_duplicate_measurements_are_merged_into_their_mean(exported, tmp_path, capsys):
    gen, d = exported
    files = files_of(d)
    lines = data_lines(files["measurements"])
    extra = []
    for i, ln in enumerate(lines[:10]):  # the same points measured again, 2 um off in x
        photo, point, x, y, sig = ln.split()
        extra.append(f"{photo} {point} {float(x) + (0.002 if i % 2 else -0.002)!r} {y} {sig}")
    write_lines(tmp_path / "again.txt", extra)
    out = tmp_path / "dup.h5"
    code, stdout, err = run_cli(capsys, "import", out, *cli_args(files), "--measurements",
                                tmp_path / "again.txt")
    assert code == 0
    warning = [ln for ln in err.splitlines() if "duplicate" in ln]
    assert len(warning) == 1 and warning[0].startswith("sapgo: warning: 10 duplicate")
    assert "largest difference 2.0 um" in warning[0] and "again.txt:2" in warning[0]
    assert "10 duplicate measurement(s) merged" in stdout
    rec = read_records(out)
    assert len(rec["observations"]) == len(lines)
    want = {}
    for a, b in zip(lines[:10], extra):
        a, b = a.split(), b.split()
        want[(int(a[0]), int(a[1]))] = (float(a[2]) + float(b[2])) / 2
    st_id, pt_id = rec["stations"]["id"], rec["points"]["id"]
    for o in rec["observations"]:
        key = (int(st_id[o["station"]]), int(pt_id[o["point"]]))
        if key in want:
            assert o["x"] == want[key]
    # the merge does not depend on the order of the duplicates
    rev = tmp_path / "reversed.txt"
    write_lines(rev, list(reversed(extra + lines)))
    import_text(tmp_path / "rev.h5", **dict(files, measurements=rev))
    assert_same_records(out, tmp_path / "rev.h5")


def test_the_same_file_twice_is_loaded_once(exported, tmp_path):
    _, d = exported
    files = files_of(d)
    import_text(tmp_path / "once.h5", **files)
    twice = {k: [v, v] for k, v in files.items()}
    s = import_text(tmp_path / "twice.h5", **twice)
    assert_same_records(tmp_path / "once.h5", tmp_path / "twice.h5")
    n_photos = len(data_lines(files["photos"]))
    assert s["photos_loaded_twice"] == n_photos and s["cameras_loaded_twice"] == 1
    assert s["duplicate_observations"] == len(data_lines(files["measurements"]))
    assert s["duplicate_max_um"] == 0.0
    assert s["control_loaded_twice"] == len(data_lines(files["control"]))
    assert any(f"{n_photos} photo(s) given more than once" in w for w in s["warnings"])


def test_a_photo_given_twice_with_different_values_is_an_error(exported, tmp_path, capsys):
    _, d = exported
    files = files_of(d)
    photo = data_lines(files["photos"])[3].split()
    photo[6] = repr(float(photo[6]) + 0.5)  # X
    write_lines(tmp_path / "more.txt", ["", " ".join(photo)])
    code, _, err = run_cli(capsys, "import", tmp_path / "x.h5", *cli_args(files), "--photos",
                           tmp_path / "more.txt")
    assert_one_line_error(code, err, f"photo {photo[0]} is given twice with different values",
                          "(X)", "photos.txt:5", "more.txt:3")
    assert not (tmp_path / "x.h5").exists()


def test_a_control_point_given_twice_with_different_values_is_an_error(exported, tmp_path):
    _, d = exported
    files = files_of(d)
    ctl = data_lines(files["control"])[2].split()
    ctl[3] = repr(float(ctl[3]) + 0.01)
    write_lines(tmp_path / "c2.txt", [" ".join(ctl)])
    with pytest.raises(DataError, match=rf"control point {ctl[0]} is given twice with "
                                        rf"different values \(coordinates\): .*control.txt:4 and "
                                        rf".*c2.txt:2"):
        import_text(tmp_path / "x.h5", **dict(files, control=[files["control"],
                                                              tmp_path / "c2.txt"]))


def test_control_kinds_unknown_components_and_lonely_points(exported, tmp_path):
    gen, d = exported
    files = files_of(d)
    rec = read_records(gen)
    ids = rec["points"]["id"][rec["points"]["n_obs"] > 0]
    lines = [f"{ids[0]} 1000.5 2000.25 - 0.05 0.05 - horizontal",
             f"{ids[1]} nan - 350.0 - - 0.1 VERTICAL",
             f"{ids[2]} 1 2 3 0 0 0 check",
             "99999 10 20 30 0.1 0.1 0.1",  # no measurement: kept with n_obs 0, reported
             ]
    write_lines(tmp_path / "c.txt", lines)
    out = tmp_path / "k.h5"
    s = import_text(out, **dict(files, control=tmp_path / "c.txt"))
    assert s["control_without_measurements"] == 1
    assert any("have no image measurement (kept with n_obs 0): ids 99999" in w
               for w in s["warnings"])
    assert s["points_by_kind"] == {"pass": len(ids) - 3, "control": 1, "horizontal": 1,
                                   "vertical": 1, "check": 1}
    pt = read_records(out)["points"]
    get = {int(i): r for i, r in zip(pt["id"], pt)}
    h, v, c, lone = get[ids[0]], get[ids[1]], get[ids[2]], get[99999]
    assert h["kind"] == 2 and list(h["control"]) == [1000.5, 2000.25, 0.0]
    assert list(h["control_sigma"]) == [0.05, 0.05, 0.0] and list(h["xyz"][:2]) == [1000.5, 2000.25]
    assert v["kind"] == 3 and v["control"][2] == 350.0 and v["xyz"][2] == 350.0
    assert c["kind"] == 4 and list(c["control"]) == [1, 2, 3] and list(c["xyz"]) != [1, 2, 3]
    assert lone["n_obs"] == 0 and list(lone["xyz"]) == [10, 20, 30]
    assert np.isfinite(pt["xyz"]).all()
    # '-' comes back as '-' and the records read back bitwise
    export_text(out, tmp_path / "again")
    text = (tmp_path / "again" / "control.txt").read_text()
    assert f"{ids[0]} 1000.5 2000.25 - 0.05 0.05 - horizontal" in text
    assert f"{ids[1]} - - 350.0 - - 0.1 vertical" in text
    import_text(tmp_path / "k2.h5", **files_of(tmp_path / "again"))
    assert_same_records(out, tmp_path / "k2.h5")


def test_points_that_cannot_be_intersected_get_finite_coordinates(exported, tmp_path):
    _, d = exported
    files = files_of(d)
    photo = data_lines(files["photos"])[0].split()[0]
    lines = data_lines(files["measurements"]) + [
        f"{photo} 777001 1.0 2.0",       # a single ray
        f"{photo} 777002 -3.0 4.0 0.004",
    ]
    write_lines(tmp_path / "m.txt", lines)
    out = tmp_path / "one.h5"
    s = import_text(out, **dict(files, measurements=tmp_path / "m.txt"))
    assert s["single_ray_points"] >= 2
    rec = read_records(out)
    pt = rec["points"]
    assert np.isfinite(pt["xyz"]).all()
    j = int(np.flatnonzero(pt["id"] == 777001)[0])
    known_z = np.isin(pt["kind"], (1, 3, 4))  # full, vertical and check points
    ground = pt["control"][known_z, 2].mean()
    assert abs(pt["xyz"][j, 2] - ground) < 1e-6  # on its ray at the mean ground height
    assert rec["observations"]["sigma"][pt["obs_start"][j]] == 0.0
    assert sapgo.adjust(out, sapgo.Options(progress=False)).converged


def test_many_control_points_given_twice_stream_through_a_small_budget(exported, tmp_path):
    _, d = exported
    files = files_of(d)
    many = [f"{900000 + i} {i * 0.5!r} {i * 0.25!r} 400.0 0 0 0 check" for i in range(30000)]
    rng = np.random.default_rng(3)
    twice = [many[i] for i in rng.permutation(len(many))]
    write_lines(tmp_path / "a.txt", many)
    write_lines(tmp_path / "b.txt", twice)
    s = import_text(tmp_path / "x.h5", memory="4M",
                    **dict(files, control=[files["control"], tmp_path / "a.txt",
                                           tmp_path / "b.txt"]))
    assert s["control_loaded_twice"] == len(many)
    assert s["control_without_measurements"] == len(many)
    assert s["points_by_kind"]["check"] >= len(many)
    with Project(tmp_path / "x.h5") as p:
        pt = p.read("points")
    lonely = pt[pt["id"] >= 900000]
    assert len(lonely) == len(many) and (lonely["n_obs"] == 0).all()
    assert np.array_equal(lonely["xyz"], lonely["control"])
    twice[-1] = twice[-1].replace(" 400.0 ", " 400.5 ")
    write_lines(tmp_path / "b.txt", twice)
    with pytest.raises(DataError, match=r"given twice with different values \(coordinates\): "
                                        r".*a\.txt:\d+ and .*b\.txt:30001"):
        import_text(tmp_path / "y.h5", memory="4M",
                    **dict(files, control=[tmp_path / "a.txt", tmp_path / "b.txt"]))


def test_mixed_columns_and_the_earliest_error(exported, tmp_path):
    _, d = exported
    files = files_of(d)
    lines = data_lines(files["measurements"])
    mixed = [" ".join(ln.split()[:4]) if i % 3 == 0 else ln for i, ln in enumerate(lines)]
    write_lines(tmp_path / "mixed.txt", mixed)
    s = import_text(tmp_path / "mixed.h5", **dict(files, measurements=tmp_path / "mixed.txt"))
    with Project(tmp_path / "mixed.h5") as p:
        sigma = p.read_field("observations", "sigma")
    assert s["observations"] == len(lines) and (sigma == 0).sum() == len(lines[::3])
    bad = list(lines)
    bad[5] = bad[5].replace(bad[5].split()[4], "-1.0")    # line 7: negative sigma
    bad[3] = "424242 " + " ".join(bad[3].split()[1:])     # line 5: unknown photo
    bad[9] = bad[9] + " 17"                               # line 11: 6 columns
    write_lines(tmp_path / "bad.txt", bad)
    with pytest.raises(DataError, match=r"bad\.txt:5: photo 424242 is not in the photos"):
        import_text(tmp_path / "bad.h5", **dict(files, measurements=tmp_path / "bad.txt"))


# -- stacking sub-blocks ---------------------------------------------------------------

def test_sub_blocks_stacked_with_append_equal_the_whole_block(exported, tmp_path, capsys):
    _, d = exported
    files = files_of(d)
    photos = data_lines(files["photos"])
    strip_of = {ln.split()[0]: int(ln.split()[2]) for ln in photos}
    strips = sorted(set(strip_of.values()))
    first = {p for p, s in strip_of.items() if s == strips[0]}
    meas = data_lines(files["measurements"])
    m1 = [ln for ln in meas if ln.split()[0] in first]
    m2 = [ln for ln in meas if ln.split()[0] not in first]
    seen1 = {ln.split()[1] for ln in m1}
    seen2 = {ln.split()[1] for ln in m2}
    control = data_lines(files["control"])
    c1 = [ln for ln in control if ln.split()[0] in seen1]  # shared points in both parts
    c2 = [ln for ln in control if ln.split()[0] in seen2 or ln.split()[0] not in seen1]
    assert len(c1) and len(c2) and len(m1) and len(m2)
    part = {}
    for k, (ph, m, c) in {1: ([p for p in photos if p.split()[0] in first], m1, c1),
                          2: ([p for p in photos if p.split()[0] not in first], m2, c2)}.items():
        part[k] = dict(photos=write_lines(tmp_path / f"p{k}.txt", ph),
                       measurements=write_lines(tmp_path / f"m{k}.txt", m),
                       control=write_lines(tmp_path / f"c{k}.txt", c))
    whole = tmp_path / "whole.h5"
    import_text(whole, **files)
    stacked = tmp_path / "stacked.h5"
    import_text(stacked, cameras=files["cameras"], **part[1])
    code, stdout, err = run_cli(capsys, "import", stacked, "--append", *cli_args(part[2]))
    assert code == 0 and "appended to" in stdout
    assert "control point(s) given more than once with identical values" in err
    assert_same_records(whole, stacked)
    with Project(stacked) as p:
        assert [h["command"] for h in p.history()] == ["import", "import"]
    assert not (tmp_path / "stacked.h5.import.work").exists()


def test_append_to_a_generated_block_drops_truth_and_keeps_priors(exported, tmp_path):
    from sapgo.project import PRIOR_DTYPE

    gen, d = exported
    rec = read_records(gen)
    prior = np.zeros(1, PRIOR_DTYPE)
    prior["station"] = 2
    prior["value"] = rec["stations"]["eo"][2]
    prior["weight"] = np.eye(6)
    rec["station_priors"] = prior
    rewrite(gen, rec)
    photo_id = int(rec["stations"]["id"][2])
    s = import_text(gen, control=files_of(d)["control"], append=True)
    assert any("/truth" in w and "dropped" in w for w in s["warnings"])
    assert s["control_loaded_twice"] == len(data_lines(files_of(d)["control"]))
    with Project(gen) as p:
        assert not p.has_truth
        pr, st = p.read("station_priors"), p.read("stations")
        assert len(pr) == 1 and st["id"][pr["station"][0]] == photo_id
    assert input_records_by_id(gen) == input_records_by_id(
        import_text(tmp_path / "x.h5", **files_of(d))["path"])


def test_an_existing_output_needs_append_or_force(exported, tmp_path, capsys):
    _, d = exported
    files = files_of(d)
    out = tmp_path / "o.h5"
    import_text(out, **files)
    before = digest(out)
    code, _, err = run_cli(capsys, "import", out, *cli_args(files))
    assert_one_line_error(code, err, "o.h5 exists", "--append", "--force")
    assert digest(out) == before
    assert run_cli(capsys, "import", out, "--force", *cli_args(files))[0] == 0
    assert_same_records(out, out)
    with pytest.raises(ParameterError, match="exclude each other"):
        import_text(out, append=True, force=True, **files)


# -- malformed input -------------------------------------------------------------------



def corrupt(path, index, column, value):
    """Replace a column of the ``index``-th data line; returns its line number."""
    lines = path.read_text().splitlines()
    seen = -1
    for n, ln in enumerate(lines):
        if ln.strip() and ln[0] != "#":
            seen += 1
            if seen == index:
                cols = ln.split()
                if column is None:
                    cols = cols[:value]
                else:
                    cols[column] = value
                lines[n] = " ".join(cols)
                path.write_text("\n".join(lines) + "\n")
                return n + 1
    raise IndexError(index)


MALFORMED = [
    # file, data line, column (None: cut to `value` columns), value, words in the message
    ("measurements", 30, 2, "1.2.3", ["'1.2.3' is not a number (column 3, x)"]),
    ("measurements", 31, None, 3,
     ["expected 4 or 5 columns (photo point x y [sigma]), found 3"]),
    ("measurements", 32, 1, "1.5", ["'1.5' is not an integer (column 2, point)"]),
    ("measurements", 33, 0, "424242", ["photo 424242 is not in the photos file(s)"]),
    ("measurements", 34, 4, "-0.006", ["sigma must not be negative"]),
    ("measurements", 35, 3, "nan", ["column 4 (y) is nan, expected a finite number"]),
    ("photos", 5, 1, "77", ["camera 77 is not in the cameras file(s)"]),
    ("photos", 6, 0, "x7", ["'x7' is not a number (column 1, id)"]),
    ("control", 3, 7, "fulll", ["unknown kind 'fulll' (column 8)"]),
    ("control", 4, 5, "-1", ["sY must not be negative"]),
    ("control", 5, 3, "-", ["Z is unknown ('-' or nan) but a"]),
    ("cameras", 0, 1, "0", ["focal_length must be positive, found 0.0 (column 2)"]),
    ("cameras", 0, None, 6, ["expected 7 to 22 columns"]),
]


@pytest.mark.parametrize("name,index,column,value,words", MALFORMED,
                         ids=[f"{m[0]}-{m[4][0][:24]}" for m in MALFORMED])
def test_malformed_input_is_one_line_naming_file_and_line(exported, tmp_path, capsys, name,
                                                          index, column, value, words):
    gen, d = exported
    files = files_of(d)
    if name == "control":  # the generator's check points: make them full control points
        lines = [" ".join(ln.split()[:-1] + ["full"]) for ln in data_lines(files["control"])]
        write_lines(files["control"], lines)
    out = tmp_path / "existing.h5"
    import_text(out, **files)
    before = digest(out)
    line = corrupt(files[name], index, column, value)
    code, _, err = run_cli(capsys, "import", out, "--append", *cli_args(files))
    assert_one_line_error(code, err, f"{name}.txt:{line}: ", *words)
    assert digest(out) == before
    assert not (tmp_path / "existing.h5.tmp").exists()
    assert not (tmp_path / "existing.h5.import.work").exists()


def test_a_missing_file_is_named(exported, tmp_path, capsys):
    _, d = exported
    files = dict(files_of(d), control=tmp_path / "nope.txt")
    code, _, err = run_cli(capsys, "import", tmp_path / "x.h5", *cli_args(files))
    assert_one_line_error(code, err, "nope.txt: no such file")
    assert not (tmp_path / "x.h5").exists()


def test_bad_options(exported, tmp_path):
    _, d = exported
    with pytest.raises(ParameterError, match="angle unit"):
        import_text(tmp_path / "x.h5", angles="grad", **files_of(d))
    with pytest.raises(ParameterError, match="memory budget"):
        import_text(tmp_path / "x.h5", memory="lots", **files_of(d))
    with pytest.raises(ParameterError, match="no measurements file"):
        import_text(tmp_path / "x.h5", cameras=d / "cameras.txt", photos=d / "photos.txt")


# -- memory budget ---------------------------------------------------------------------

RUN_MEASURED = textwrap.dedent("""
    import resource, subprocess, sys
    r = subprocess.run([sys.executable, "-m", "sapgo.cli", "import"] + sys.argv[1:],
                       capture_output=True, text=True)
    sys.stderr.write(r.stderr)
    print(r.returncode, resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)
""")


def peak_rss_kb(out, files, memory):
    r = subprocess.run([sys.executable, "-c", RUN_MEASURED, str(out), "--memory", memory,
                        *map(str, cli_args(files))], capture_output=True, text=True, check=True)
    code, rss = r.stdout.split()
    assert code == "0", r.stderr
    return int(rss)


def test_memory_stays_within_the_budget(block_cache, tmp_path):
    budget_mb, slack_mb = 8, 16
    gen = block_cache("import-memory", strips=4, photos_per_strip=25, pattern=25,
                      control_points=32)
    d = tmp_path / "txt"
    export_text(gen, d)
    files = files_of(d)
    base = data_lines(files["measurements"])
    copies = 600_000 // len(base) + 1  # the block repeated with other point ids
    rows = [ln.split(" ", 2) for ln in base]
    with open(tmp_path / "big.txt", "w") as f:
        for k in range(copies):
            off = k * 10_000_000
            f.write("".join(f"{a} {int(b) + off} {rest}\n" for a, b, rest in rows))
    n_lines = copies * len(base)
    record_mb = n_lines * 48 / 2**20
    assert record_mb > 3 * budget_mb  # the sort records are several times the budget
    big = dict(files, measurements=tmp_path / "big.txt")

    peak_rss_kb(tmp_path / "warm.h5", files, "8M")  # numba caches, page cache
    tiny = peak_rss_kb(tmp_path / "tiny.h5", files, "8M")
    large = peak_rss_kb(tmp_path / "large.h5", big, f"{budget_mb}M")
    growth_mb = (large - tiny) / 1024
    assert growth_mb < budget_mb + slack_mb, (growth_mb, tiny / 1024, large / 1024)

    s = import_text(tmp_path / "ref.h5", memory="1G", **big)
    assert s["observations"] == n_lines
    assert_same_records(tmp_path / "large.h5", tmp_path / "ref.h5")


# -- exposure-station priors -----------------------------------------------------------

ARCSEC = np.pi / (180 * 3600)
PRIOR_SIGMA = (10.0, 10.0, 10.0, 0.1, 0.1, 0.1)  # arc seconds, m


def priors_from_truth(gen, d, covariances=False, sigma=PRIOR_SIGMA):
    """A priors file of every photo at its true orientation (degrees): sigmas, or the same
    as a diagonal covariance."""
    rec = read_records(gen)
    st, truth = rec["stations"], rec["truth"]["stations"]
    assert (truth["id"] == st["id"]).all()
    path = d / ("prior_cov.txt" if covariances else "priors.txt")
    with open(path, "w") as f:
        for sid, eo in zip(st["id"], truth["eo"]):
            vals = [repr(float(v)) for v in np.degrees(eo[:3])] + [repr(float(v))
                                                                    for v in eo[3:]]
            if covariances:
                cov = np.diag(np.square(sigma))
                tail = [repr(float(cov[i, j])) for i in range(6) for j in range(i, 6)]
            else:
                tail = [repr(float(s)) for s in sigma]
            f.write(" ".join([str(int(sid))] + vals + tail) + "\n")
    return path


def only_check_points(d):
    """The control file with every point turned into a check point."""
    path = d / "check.txt"
    lines = [ln.split() for ln in open(d / "control.txt") if ln.strip() and ln[0] != "#"]
    with open(path, "w") as f:
        for t in lines:
            f.write(" ".join(t[:7] + ["check"]) + "\n")
    return path


def test_a_block_controlled_only_by_station_priors_adjusts(exported, tmp_path):
    gen, d = exported
    files = files_of(d)
    files["control"] = [only_check_points(d)]
    out = tmp_path / "priors.h5"
    s = import_text(out, priors=priors_from_truth(gen, d), **files)
    assert s["station_priors"] == 12 and s["points_by_kind"]["control"] == 0
    with Project(out) as p:
        pr = p.read("station_priors")
        st = p.read("stations")
    sig = np.array(PRIOR_SIGMA) * np.array([ARCSEC] * 3 + [1.0] * 3)
    np.testing.assert_allclose(pr["weight"][0], np.diag(1.0 / sig ** 2), rtol=1e-15)
    truth = read_records(gen)["truth"]["stations"]
    np.testing.assert_allclose(pr["value"], truth["eo"][np.searchsorted(truth["id"],
                                                                        st["id"][pr["station"]])],
                               rtol=0, atol=1e-12)
    summary = sapgo.adjust(out, sapgo.Options(progress=False))
    assert summary.converged
    assert summary.check_points["n"] > 0 and summary.check_points["sxy"] < 0.5
    # the same priors given as diagonal covariances: the same weights and result
    out2 = tmp_path / "cov.h5"
    import_text(out2, prior_covariances=priors_from_truth(gen, d, covariances=True), **files)
    with Project(out2) as p:
        np.testing.assert_allclose(p.read("station_priors")["weight"], pr["weight"],
                                   rtol=1e-12, atol=0)
    assert sapgo.adjust(out2, sapgo.Options(progress=False)).converged
    (eo1, xyz1), (eo2, xyz2) = adjusted_by_id(out), adjusted_by_id(out2)
    assert max(np.abs(xyz1[k] - xyz2[k]).max() for k in xyz1) < 1e-6
    assert max(np.abs(eo1[k] - eo2[k]).max() for k in eo1) < 1e-6


@pytest.mark.parametrize("line, words", [
    ("99 0 0 0 0 0 3800 10 10 10 0.1 0.1 0.1", ("priors.txt:1", "photo 99 is not in the photos")),
    ("1 0 0 0 0 0 3800 - 0 - 0 0 -", ("priors.txt:1", "constrains nothing")),
    ("1 0 0 0 0 0 3800 10 -1 10 0.1 0.1 0.1", ("priors.txt:1", "column 9 (s_phi)")),
    ("1 0 0 0 0 0 3800 1e-300 10 10 0.1 0.1 0.1", ("priors.txt:1", "photo 1",
                                                    "too small for its weight")),
])
def test_bad_priors_name_the_line(exported, tmp_path, capsys, line, words):
    gen, d = exported
    (d / "priors.txt").write_text("# priors\n" + line + "\n")
    line_no = words[0].replace(":1", ":2")
    code, _, err = run_cli(capsys, "import", tmp_path / "x.h5", *cli_args(files_of(d)),
                           "--priors", d / "priors.txt")
    assert_one_line_error(code, err, line_no, *words[1:])
    assert not (tmp_path / "x.h5").exists()


def test_priors_given_twice_must_agree(exported, tmp_path):
    gen, d = exported
    path = priors_from_truth(gen, d)
    other = d / "other.txt"
    first = open(path).readline().split()
    first[7] = "20.0"
    other.write_text(" ".join(first) + "\n")
    with pytest.raises(DataError, match=r"prior of photo \d+ is given twice with different "
                                        r"values \(weight\[0\]\[0\]\)"):
        import_text(tmp_path / "x.h5", priors=[path, other], **files_of(d))
    s = import_text(tmp_path / "y.h5", priors=[path, path], **files_of(d))
    assert s["station_priors"] == 12 and any("loaded once" in w for w in s["warnings"])


def test_a_covariance_that_is_not_positive_definite_is_refused(exported, tmp_path):
    gen, d = exported
    path = priors_from_truth(gen, d, covariances=True)
    lines = open(path).read().splitlines()
    t = lines[2].split()
    t[8] = repr(1e9)  # c12 far larger than sqrt(c11 c22)
    lines[2] = " ".join(t)
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"prior_cov.txt:3: the covariance of the prior of "
                                        r"photo \d+ is not positive definite"):
        import_text(tmp_path / "x.h5", prior_covariances=path, **files_of(d))


# -- angle orders (--rotation) ---------------------------------------------------------

def _compose(order, a):
    """``M`` of one photo's three file angles, composed here from sapgo's elementary
    rotations in the documented order (the reference for the import's conversion)."""
    from sapgo.geometry import _elementary

    first, second, third = a
    w, p, k = {"opk": (first, second, third), "pok": (second, first, third),
               "kpo": (third, second, first)}[order]
    r1, r2, r3, _, _, _ = _elementary(w, p, k)
    return {"opk": r3 @ r2 @ r1, "pok": r3 @ r1 @ r2, "kpo": r1 @ r2 @ r3}[order]


@pytest.mark.parametrize("order", ["pok", "kpo"])
def test_a_block_in_another_angle_order_adjusts_alike(exported, tmp_path, capsys, order):
    """The block's photos and priors written phi-omega-kappa or kappa-phi-omega (by the
    export), read with --rotation: the same orientations, prior weights and adjustment."""
    from scipy.spatial.transform import Rotation

    gen, d = exported
    files = files_of(d)
    files["control"] = [only_check_points(d)]
    ref = tmp_path / "opk.h5"
    import_text(ref, prior_covariances=priors_from_truth(gen, d, covariances=True), **files)
    # the photos in the order, as the export writes them
    od = tmp_path / order
    code, _, err = run_cli(capsys, "export", ref, od, "--rotation", order)
    assert code == 0, err
    header = open(od / "photos.txt").readline()
    assert {"pok": "phi omega kappa", "kpo": "kappa phi omega"}[order] in header
    with Project(ref) as p:
        st = p.read("stations")
        pr = p.read("station_priors")
    from sapgo.frames import rotation_matrices

    m_ref = dict(zip(st["id"].tolist(), rotation_matrices(st["eo"][:, :3])))
    for ln in open(od / "photos.txt"):
        if ln.startswith("#"):
            continue
        t = ln.split()
        np.testing.assert_allclose(_compose(order, np.radians([float(x) for x in t[3:6]])),
                                   m_ref[int(t[0])], atol=1e-13)
    # the priors in the order: values from the matrices, covariances carried over with the
    # Jacobian of opk -> order (central differences of scipy's Euler angles, here)
    seq = {"pok": "YXZ", "kpo": "ZYX"}[order]

    def to_order(opk):
        return Rotation.from_euler("XYZ", opk).as_euler(seq)

    cov_path = tmp_path / f"prior_cov_{order}.txt"
    with open(cov_path, "w") as f:
        for rec in pr:
            v, w = rec["value"], rec["weight"]
            h = 1e-6
            jac = np.column_stack([(to_order(v[:3] + h * e) - to_order(v[:3] - h * e)) / (2 * h)
                                   for e in np.eye(3)])
            t6 = np.eye(6)
            t6[:3, :3] = jac
            cov = t6 @ np.linalg.inv(w) @ t6.T
            scale = np.array([ARCSEC] * 3 + [1.0] * 3)
            cov = cov / np.outer(scale, scale)
            vals = list(np.degrees(to_order(v[:3]))) + list(v[3:])
            f.write(" ".join([str(int(st["id"][rec["station"]]))]
                             + [repr(float(x)) for x in vals]
                             + [repr(float(cov[i, j])) for i in range(6) for j in range(i, 6)])
                    + "\n")
    files["photos"] = [od / "photos.txt"]
    out = tmp_path / f"{order}.h5"
    code, _, err = run_cli(capsys, "import", out, "--rotation", order,
                           "--prior-covariances", cov_path, *cli_args(files))
    assert code == 0, err
    with Project(out) as p:
        st2, pr2 = p.read("stations"), p.read("station_priors")
    np.testing.assert_allclose(rotation_matrices(st2["eo"][:, :3]),
                               rotation_matrices(st["eo"][:, :3]), atol=1e-13)
    dv = pr2["value"] - pr["value"]
    dv[:, :3] = (dv[:, :3] + np.pi) % (2 * np.pi) - np.pi   # (kappa 181 deg = -179 deg)
    assert np.abs(dv).max() < 1e-12
    np.testing.assert_allclose(pr2["weight"], pr["weight"], rtol=1e-6,
                               atol=1e-6 * np.abs(pr["weight"]).max())
    s1 = sapgo.adjust(ref, sapgo.Options(progress=False))
    s2 = sapgo.adjust(out, sapgo.Options(progress=False))
    assert s2.sigma0 == pytest.approx(s1.sigma0, rel=1e-6)
    (eo1, xyz1), (eo2, xyz2) = adjusted_by_id(ref), adjusted_by_id(out)
    assert max(np.abs(xyz1[k] - xyz2[k]).max() for k in xyz1) < 1e-6
    # adjusted photos written in the order read back to the same rotations
    code, _, err = run_cli(capsys, "export", out, tmp_path / "adj", "--adjusted",
                           "--rotation", order)
    assert code == 0, err
    for ln in open(tmp_path / "adj" / "adjusted_photos.txt"):
        if not ln.startswith("#"):
            t = ln.split()
            m = _compose(order, np.radians([float(x) for x in t[3:6]]))
            np.testing.assert_allclose(m, rotation_matrices(eo2[int(t[0])][:3])[0],
                                       atol=1e-12)


# -- image coordinate conventions (--image-frames) -------------------------------------

@pytest.mark.parametrize("given", ["image-frames", "cameras"])
@pytest.mark.parametrize("frame", ["px topleft down", "mm bottomleft up", "px centre down"])
def test_measurements_in_other_image_frames_adjust_alike(exported, tmp_path, capsys, frame,
                                                         given):
    """The block's measurements rewritten in pixels from the top-left corner with y down
    (4.6 x 5.0 um pixels), in mm from the bottom-left corner, or in pixels from the centre
    with y down, read with --image-frames or with the frame in the cameras file (columns
    16-22): the same observations and adjustment."""
    gen, d = exported
    files = files_of(d)
    ref = tmp_path / "ref.h5"
    import_text(ref, **files)
    unit, origin, axis = frame.split()
    px, py = (4.6, 5.0) if unit == "px" else (1000.0, 1000.0)   # (um a unit)
    cams = [ln.split() for ln in data_lines(d / "cameras.txt")]
    fx, fy = float(cams[0][4]), float(cams[0][5])   # (the format, mm)
    w, h = fx * 1000 / px, fy * 1000 / py
    lines = []
    for ln in data_lines(d / "measurements.txt"):
        photo, point, x, y, sigma = ln.split()
        u, v = float(x) * 1000 / px, float(y) * 1000 / py
        if axis == "down":
            v = -v
        if origin == "topleft":
            u, v = u + w / 2, v + h / 2
        elif origin == "bottomleft":
            u, v = u + w / 2, v + h / 2
        s = float(sigma) * 1000 / float(np.sqrt(px * py))
        lines.append(f"{photo} {point} {u!r} {v!r} {s!r}")
    files["measurements"] = write_lines(tmp_path / "m.txt", lines)
    none = "-" if given == "image-frames" else "0"
    size = (none, none) if origin == "centre" else (repr(w), repr(h))
    pix = (repr(px), repr(py)) if unit == "px" else (none, none)
    out = tmp_path / "other.h5"
    if given == "image-frames":
        frames = write_lines(tmp_path / "frames.txt",
                             [" ".join([c[0], unit, *pix, *size, origin, axis]) for c in cams])
        extra = ["--image-frames", frames]
    else:   # the first 15 columns, then the frame
        full = [c + ["0"] * (14 - len(c)) + ["forward"] if len(c) < 15 else c for c in cams]
        files["cameras"] = write_lines(tmp_path / "cams.txt",
                                       [" ".join(c + [unit, *pix, *size, origin, axis])
                                        for c in full])
        extra = []
    code, _, err = run_cli(capsys, "import", out, *extra, *cli_args(files))
    assert code == 0, err
    def observations(path):
        rec = read_records(path)
        st, pt, ob = rec["stations"], rec["points"], rec["observations"]
        key = (st["id"][ob["station"]], pt["id"][ob["point"]])
        o = np.lexsort((key[1], key[0]))
        return np.column_stack([key[0][o], key[1][o]]), ob[o]

    (ka, a), (kb, b) = observations(ref), observations(out)
    np.testing.assert_array_equal(kb, ka)
    np.testing.assert_allclose(b["x"], a["x"], atol=1e-9)
    np.testing.assert_allclose(b["y"], a["y"], atol=1e-9)
    np.testing.assert_allclose(b["sigma"], a["sigma"], rtol=1e-12)
    s1 = sapgo.adjust(ref, sapgo.Options(progress=False))
    s2 = sapgo.adjust(out, sapgo.Options(progress=False))
    assert s2.sigma0 == pytest.approx(s1.sigma0, rel=1e-6)


@pytest.mark.parametrize("line, words", [
    ("99 px 4.6 4.6 6000 4000 topleft down", "camera 99 is not in the cameras"),
    ("1 pixels 4.6 4.6 6000 4000 topleft down", "unit 'pixels'"),
    ("1 px 4.6 4.6 - - topleft down", "width '-' must be a positive number"),
    ("1 px - 4.6 6000 4000 centre down", "pixel_x '-'"),
    ("1 px 4.6 4.6 6000 4000 middle down", "origin 'middle'"),
    ("1 px 4.6 4.6 6000 4000 centre sideways", "y axis 'sideways'"),
    ("1 px 4.6 4.6 6000 4000", "expected 8 columns"),
    ("1 px 1e300 4.6 6000 4000 topleft down", "pixel_x '1e300' must be a positive number"),
])
def test_bad_image_frames_name_the_line(exported, tmp_path, capsys, line, words):
    gen, d = exported
    frames = write_lines(tmp_path / "frames.txt", [line])
    code, _, err = run_cli(capsys, "import", tmp_path / "x.h5", "--image-frames", frames,
                           *cli_args(files_of(d)))
    assert_one_line_error(code, err, "frames.txt:2", words)
    assert not (tmp_path / "x.h5").exists()


def test_image_frames_file_with_a_byte_order_mark_or_missing(exported, tmp_path, capsys):
    """A byte-order mark at the start of an --image-frames file is skipped (the line is read:
    its camera named), as in the column files; a file that is not there is a one-line error."""
    gen, d = exported
    frames = tmp_path / "frames.txt"
    frames.write_bytes(b"\xef\xbb\xbf99 px 4.6 4.6 6000 4000 topleft down\n")
    code, _, err = run_cli(capsys, "import", tmp_path / "x.h5", "--image-frames", frames,
                           *cli_args(files_of(d)))
    assert_one_line_error(code, err, "frames.txt:1", "camera 99 is not in the cameras")
    code, _, err = run_cli(capsys, "import", tmp_path / "x.h5", "--image-frames",
                           tmp_path / "none.txt", *cli_args(files_of(d)))
    assert_one_line_error(code, err, "none.txt", "no such file")
    assert not (tmp_path / "x.h5").exists()


@pytest.mark.parametrize("tail, frames, words", [
    ("pixels 4.6 4.6 0 0 centre down", None, "unknown image unit; expected mm or px, found "
                                             "'pixels' (column 16)"),
    ("px 4.6 4.6 0 0 middle down", None, "(column 21)"),
    ("px 0 4.6 0 0 centre down", None, "pixel_x 0 must be a positive number"),
    ("px 4.6 4.6 0 0 topleft down", None, "width 0 must be a positive number"),
    ("px 4.6 4.6 0 0 centre down", "1 px 4.6 4.6 - - centre down",
     "camera 1's image frame is given here and in --image-frames"),
    ("px 4.6 5.0 6000 4000 topleft", None, "image frame needs columns 16-22 (mm|px pixel_x "
                                           "pixel_y width height origin y_axis), found 21"),
    ("px", None, "image frame needs columns 16-22"),
    ("none 4.6", None, "found 17 columns"),
])
def test_bad_frames_in_the_cameras_file_name_the_line(exported, tmp_path, capsys, tail,
                                                      frames, words):
    """The image frame in columns 16-22 of the cameras file: bad values, or a frame given
    there and in --image-frames, are one line naming the cameras file's line."""
    gen, d = exported
    files = files_of(d)
    cams = [ln.split() for ln in data_lines(d / "cameras.txt")]
    full = [c + ["0"] * (14 - len(c)) + ["forward"] for c in cams]
    files["cameras"] = write_lines(tmp_path / "cams.txt",
                                   [" ".join(c) + " " + tail for c in full])
    extra = ["--image-frames", write_lines(tmp_path / "f.txt", [frames])] if frames else []
    code, _, err = run_cli(capsys, "import", tmp_path / "x.h5", *extra, *cli_args(files))
    assert_one_line_error(code, err, "cams.txt:2", words)
    assert not (tmp_path / "x.h5").exists()


def test_a_memory_budget_beyond_the_machine_reads_the_files_whole(exported, tmp_path, capsys):
    """``--memory`` of terabytes: the files are read whole (no buffer beyond a file's size;
    a MemoryError traceback before), and the project is the one the default budget makes."""
    gen, d = exported
    code, _, err = run_cli(capsys, "import", tmp_path / "big.h5", "--memory", "99999999T",
                           *cli_args(files_of(d)))
    assert code == 0, err
    code, _, err = run_cli(capsys, "import", tmp_path / "default.h5", *cli_args(files_of(d)))
    assert code == 0, err
    with sapgo.open_project(tmp_path / "big.h5") as a, \
            sapgo.open_project(tmp_path / "default.h5") as b:
        for name in ("stations", "points", "observations"):
            np.testing.assert_array_equal(a.read(name), b.read(name))


def test_a_cameras_file_without_cameras_is_named(exported, tmp_path, capsys):
    gen, d = exported
    files = files_of(d)
    files["cameras"] = write_lines(tmp_path / "cams.txt", [])
    code, _, err = run_cli(capsys, "import", tmp_path / "x.h5", *cli_args(files))
    assert_one_line_error(code, err, "cams.txt: no camera")
    assert not (tmp_path / "x.h5").exists()
