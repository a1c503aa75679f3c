"""Bad input: one clear line, a non-zero exit code, and the project left as it was."""


import h5py
import numpy as np
import pytest

import sapgo
from conftest import (assert_one_line_error, collinear_control, digest, read_records,
                      rewrite, run_cli)
from sapgo.errors import DataError, DatumDefectError, ProjectFormatError








def test_a_text_file_is_not_a_project(tmp_path, capsys):
    f = tmp_path / "notes.h5"
    f.write_text("photo point x y\n")
    with pytest.raises(ProjectFormatError, match="not a sapgo project"):
        sapgo.open_project(f)
    assert_one_line_error(*run_cli(capsys, "adjust", f)[::2], "not a sapgo project")


def test_a_foreign_hdf5_file_is_not_a_project(tmp_path, capsys):
    f = tmp_path / "other.h5"
    with h5py.File(f, "w") as h:
        h["x"] = np.arange(3)
    before = digest(f)
    assert_one_line_error(*run_cli(capsys, "adjust", f)[::2], "not a sapgo project")
    assert_one_line_error(*run_cli(capsys, "order", f)[::2], "not a sapgo project")
    assert digest(f) == before


def test_missing_file(tmp_path, capsys):
    assert_one_line_error(*run_cli(capsys, "info", tmp_path / "nope.h5")[::2], "no such file")


def test_another_schema_version(small_block, capsys):
    with h5py.File(small_block, "r+") as h:
        h.attrs["schema_version"] = 99
    before = digest(small_block)
    with pytest.raises(ProjectFormatError, match="schema version 99"):
        sapgo.open_project(small_block)
    assert_one_line_error(*run_cli(capsys, "adjust", small_block)[::2], "schema version 99")
    assert digest(small_block) == before


def test_block_without_control(small_block, capsys):
    rec = read_records(small_block)
    rec["points"]["kind"][rec["points"]["kind"] == 1] = 4
    rewrite(small_block, rec)
    before = digest(small_block)
    with pytest.raises(DatumDefectError, match="datum defect"):
        sapgo.adjust(small_block, sapgo.Options(progress=False))
    code, _, err = run_cli(capsys, "adjust", small_block)
    assert_one_line_error(code, err, "datum defect", "control points", "--datum free")
    assert digest(small_block) == before
    assert not small_block.with_name("small.h5.work").exists()


def test_collinear_control_is_a_datum_defect_found_by_the_pivot(small_block):
    # the factorisation must find the free rotation and say so
    collinear_control(small_block)
    with pytest.raises(DatumDefectError, match="datum defect") as e:
        sapgo.adjust(small_block, sapgo.Options(progress=False))
    assert "station id" in str(e.value)


@pytest.mark.parametrize("dataset,field,index,value,words", [
    ("observations", "x", 5, np.nan, ("observations record 5", "x is NaN")),
    ("stations", "eo", 3, np.inf, ("stations record 3", "eo[", "infinite")),
    ("points", "xyz", 7, np.nan, ("points record 7", "xyz[", "NaN")),
])
def test_non_finite_values(small_block, capsys, dataset, field, index, value, words):
    with h5py.File(small_block, "r+") as h:
        rec = h[dataset][index]
        if rec[field].ndim:
            rec[field][1] = value
        else:
            rec[field] = value
        h[dataset][index] = rec
    before = digest(small_block)
    with pytest.raises(DataError):
        sapgo.adjust(small_block, sapgo.Options(progress=False))
    assert_one_line_error(*run_cli(capsys, "adjust", small_block)[::2], *words)
    assert digest(small_block) == before


def test_lens_distortion_that_folds_the_image_is_refused(small_block, capsys):
    """k1 given in the wrong unit (per um^2 read as per mm^2) folds the image over inside the
    format: a one-line error naming the camera and the units, the project unchanged."""
    rec = read_records(small_block)
    rec["cameras"]["k1"] = -2.0e-5
    rewrite(small_block, rec)
    before = digest(small_block)
    assert_one_line_error(*run_cli(capsys, "adjust", small_block)[::2], "cameras record 0",
                          "(id 1)", "folds the image over", "mm^-2")
    assert digest(small_block) == before


@pytest.mark.parametrize("field, value, words", [
    ("ap_set", 3, ["additional-parameter set 3", "none, ebner, gruen"]),
    ("ap_base", 0.0, ["base of its ebner set must be positive"]),
    ("a5", np.nan, ["a5 is NaN"]),
    ("a1", 0.05, ["folds the image over"]),
])
def test_bad_additional_parameters_in_a_project_are_refused(small_block, capsys, field,
                                                            value, words):
    """A project whose camera holds an unknown additional-parameter set, a set without a
    base, a coefficient that is not finite, or coefficients that fold the image (50 um of
    Ebner's b1 per unit xi: the scale term): a one-line error naming the camera, the
    project unchanged."""
    rec = read_records(small_block)
    cams = rec["cameras"]
    cams["ap_set"], cams["ap_base"] = 1, 92.0
    cams[field] = value
    if field == "a1":
        cams["a1"] = -100.0   # (a scale of -100 mm per 92 mm: folds the image)
    rewrite(small_block, rec)
    before = digest(small_block)
    assert_one_line_error(*run_cli(capsys, "adjust", small_block)[::2], "cameras record 0",
                          "(id 1)", *words)
    assert digest(small_block) == before


def test_generator_distortion_from_the_command_line(tmp_path, capsys):
    code, out, err = run_cli(capsys, "generate", "--strips", "2", "--photos-per-strip", "4",
                             "--control-points", "6", "--distortion=-2e-8,0,0,1e-6,0",
                             tmp_path / "d.h5")
    assert code == 0, err
    with sapgo.Project(tmp_path / "d.h5") as p:
        cam = p.cameras()[0]
    assert (cam["k1"], cam["p1"]) == (-2e-8, 1e-6)
    with pytest.raises(SystemExit) as exc:  # argparse: usage and the error, exit code 2
        run_cli(capsys, "generate", "--distortion", "1,2", tmp_path / "e.h5")
    assert exc.value.code == 2
    assert "expected 5 numbers separated by commas" in capsys.readouterr().err


def test_bad_generator_parameters(tmp_path, capsys):
    assert_one_line_error(*run_cli(capsys, "generate", "--pattern", "9", "--forelap", "0.2",
                                   tmp_path / "x.h5")[::2], "forelap")
    assert not (tmp_path / "x.h5").exists()


def test_indefinite_prior_weight_is_refused(small_block, capsys):
    from sapgo.project import PRIOR_DTYPE

    rec = read_records(small_block)
    prior = np.zeros(1, PRIOR_DTYPE)
    prior["station"] = 1
    prior["value"] = rec["stations"]["eo"][1]
    w = np.eye(6)
    w[3, 4] = w[4, 3] = 3.0  # eigenvalue -2
    prior["weight"] = w
    rec["station_priors"] = prior
    rewrite(small_block, rec)
    assert_one_line_error(*run_cli(capsys, "adjust", small_block)[::2], "station_priors record 0",
                          "positive semi-definite")


def test_records_changed_after_ordering_are_detected(small_block, capsys):
    sapgo.order_project(small_block)
    with h5py.File(small_block, "r+") as h:
        h.attrs["band_width"] = int(h.attrs["band_width"]) - 2
    code, _, err = run_cli(capsys, "adjust", small_block)
    assert_one_line_error(code, err, "sapgo order")


def test_point_in_the_plane_of_a_photo(small_block, capsys):
    rec = read_records(small_block)
    ob = rec["observations"]
    j = int(np.flatnonzero(rec["points"]["kind"] == 4)[0])
    s = int(ob["station"][ob["point"] == j][0])
    rec["points"]["xyz"][j] = rec["stations"]["eo"][s, 3:]
    rewrite(small_block, rec)
    code, _, err = run_cli(capsys, "adjust", small_block)
    assert_one_line_error(code, err, f"point id {rec['points']['id'][j]}", "behind photo(s)",
                          f"id {rec['stations']['id'][s]}", "check its approximate")


def test_a_mirrored_frame_is_named(small_block, capsys):
    """Z pointing down (the block's heights negated, the photos as they were): every point
    lies behind its photos, and the message points at the axes, not at one point."""
    rec = read_records(small_block)
    for name, field, col in (("points", "xyz", 2), ("points", "control", 2),
                             ("stations", "eo", 5)):
        rec[name][field][:, col] *= -1.0
    rewrite(small_block, rec)
    code, _, err = run_cli(capsys, "adjust", small_block)
    assert_one_line_error(code, err, "behind photo(s)", "mirrored", "right-handed")


def test_order_validates_references(small_block, capsys):
    with h5py.File(small_block, "r+") as h:
        r = h["observations"][4]
        r["station"] = 999
        h["observations"][4] = r
    before = digest(small_block)
    assert_one_line_error(*run_cli(capsys, "order", small_block)[::2], "observations record 4",
                          "station 999")
    assert digest(small_block) == before


def test_output_path_that_is_a_directory(tmp_path, capsys):
    (tmp_path / "d.h5").mkdir()
    assert_one_line_error(*run_cli(capsys, "generate", "--preset", "sapgo-p-1",
                                   tmp_path / "d.h5")[::2])


def test_observations_cut_short_are_a_damaged_project(small_block, tmp_path, capsys):
    """/observations shorter than the points' obs_start and n_obs say (a damaged or hand-made
    file): every command refuses it in one line at the open (``plan`` read past the end in a
    kernel before), and the file is left as it was."""
    with h5py.File(small_block, "r+") as h:
        obs = h["observations"][:5]
        del h["observations"]
        h.create_dataset("observations", data=obs)
    before = digest(small_block)
    for args in (("plan", small_block), ("order", small_block), ("adjust", small_block),
                 ("info", small_block), ("export", small_block, tmp_path / "out"),
                 ("export", "--format", "bal", small_block, tmp_path / "out.txt")):
        assert_one_line_error(*run_cli(capsys, *args)[::2], "the project is damaged",
                              "/observations has 5 records")
    assert digest(small_block) == before


def test_a_refused_export_makes_no_directory(small_block, tmp_path, capsys):
    """An export of a file that is not a project, or ``--adjusted`` of a project never
    adjusted: one line, and no output directory left behind (an empty one before)."""
    bad = tmp_path / "notes.h5"
    bad.write_text("not a project\n")
    assert_one_line_error(*run_cli(capsys, "export", bad, tmp_path / "out1")[::2],
                          "not a sapgo project")
    assert_one_line_error(*run_cli(capsys, "export", "--adjusted", small_block,
                                   tmp_path / "out2")[::2], "no adjusted solution")
    assert not (tmp_path / "out1").exists() and not (tmp_path / "out2").exists()


def test_a_refused_import_leaves_no_new_folder(tmp_path, capsys):
    """An import into a folder that does not exist yet, refused: the folders made for it
    (for its lock) are removed again; a successful one keeps them."""
    bad = tmp_path / "bad.txt"
    bad.write_text("1 1 1\n0 0 1 2\n" + "0\n" * 9 + "1\n2\n3\n")   # (f = 0)
    out = tmp_path / "new" / "deeper" / "x.h5"
    code, _, err = run_cli(capsys, "import", "--format", "bal", bad, out)
    assert_one_line_error(code, err, "focal length")
    assert not (tmp_path / "new").exists()
