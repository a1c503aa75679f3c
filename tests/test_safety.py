"""Nothing lost, nothing silent (issue 19): checksums, overwrites, results kept by a
reordering."""

import h5py
import numpy as np
import pytest

from conftest import assert_one_line_error, digest, run_cli
from sapgo.project import CHECKSUM, RECORD_DTYPES, Project


def flip_byte(path, dataset, chunk=0):
    """Flip one byte in the middle of chunk ``chunk`` of ``dataset`` on disk."""
    with h5py.File(path, "r") as f:
        info = f[dataset].id.get_chunk_info(chunk)
        rows = f[dataset].chunks[0]
    with open(path, "r+b") as fh:
        fh.seek(info.byte_offset + info.size // 2)
        b = fh.read(1)
        fh.seek(info.byte_offset + info.size // 2)
        fh.write(bytes([b[0] ^ 0x10]))
    return rows


def test_record_datasets_have_checksums(small_block):
    with h5py.File(small_block, "r") as f:
        for name in RECORD_DTYPES:
            assert f[name].fletcher32, name
    assert CHECKSUM == {"fletcher32": True}


@pytest.mark.parametrize("dataset", ["observations", "points", "stations"])
def test_flipped_byte_is_one_line_naming_the_records(small_block, capsys, dataset):
    with h5py.File(small_block, "r") as f:
        n = f[dataset].shape[0]
    rows = flip_byte(small_block, dataset)
    before = digest(small_block)
    code, _, err = run_cli(capsys, "adjust", small_block, "--no-progress")
    assert_one_line_error(code, err, str(small_block), f"/{dataset} records 0..",
                          "checksum", "restore")
    assert f"0..{min(rows, n) - 1} " in err
    assert digest(small_block) == before


def test_generate_refuses_an_existing_project(small_block, capsys):
    before = digest(small_block)
    code, _, err = run_cli(capsys, "generate", "--preset", "sapgo-p-1", small_block)
    assert_one_line_error(code, err, str(small_block), "exists", "--force")
    assert digest(small_block) == before
    code, out, _ = run_cli(capsys, "generate", "--preset", "sapgo-p-1", small_block, "--force")
    assert code == 0 and "100 photos" in out


def test_reordering_an_adjusted_project_keeps_every_result(p1_block, capsys):
    """Point sigmas and observation quality follow their records to the new order."""
    assert run_cli(capsys, "adjust", p1_block, "--no-progress")[0] == 0

    def by_id(path):
        with Project(path) as p:
            pid = p.read_field("points", "id")
            obs = p.read("observations")
            okey = pid[obs["point"]] * 100000 + p.read_field("stations", "id")[obs["station"]]
            return ({i: s for i, s in zip(pid, p.solution("point_sigma"))},
                    {k: q for k, q in zip(okey, p.solution("obs_quality"))})

    sig0, q0 = by_id(p1_block)
    assert any(np.any(s > 0) for s in sig0.values())
    assert run_cli(capsys, "order", p1_block, "--solver", "tree")[0] == 0
    sig1, q1 = by_id(p1_block)
    assert sig1.keys() == sig0.keys() and q1.keys() == q0.keys()
    for i in sig0:
        np.testing.assert_array_equal(sig1[i], sig0[i])
    for k in q0:
        np.testing.assert_array_equal(q1[k], q0[k])


def test_earlier_rejections_are_reported_and_can_be_reset(block_cache, tmp_path, capsys):
    """Snooping's rejections stay out of later runs, said in the report; --reset-rejections
    brings them back (issue 19, item 6)."""
    import sapgo
    from sapgo.project import STATUS_REJECTED

    path = tmp_path / "b.h5"
    path.write_bytes(block_cache("blunders", strips=3, photos_per_strip=8, control_points=8,
                                 blunders=3).read_bytes())
    s1 = sapgo.adjust(path, sapgo.Options(snooping=True, progress=False))
    n = len(s1.rejected)
    found = s1.blunder_check["found"]
    assert n >= 1 and found >= 1

    def rejected():
        with Project(path) as p:
            return int((p.read_field("observations", "status") == STATUS_REJECTED).sum())

    assert rejected() == n
    code, out, _ = run_cli(capsys, "adjust", path, "--no-progress")
    assert code == 0
    assert f"{n} observation(s) rejected by an earlier run are kept out" in out
    assert "--reset-rejections" in out
    assert rejected() == n
    code, out, _ = run_cli(capsys, "adjust", path, "--no-progress", "--reset-rejections",
                           "--snooping")
    assert code == 0 and f"{n} observation(s) rejected by an earlier run were brought back" in out
    assert f"planted blunders: {found} of 3 found" in out
    s = sapgo.adjust(path, sapgo.Options(reset_rejections=True, progress=False))
    assert s.rejections_reset == n and s.rejections_kept == 0 and rejected() == 0


def _exported(small_block, tmp_path, dx_mm):
    """The small block as text files, its first measurement given again ``dx_mm`` apart."""
    code = run_cli_plain("export", small_block, tmp_path / "txt")
    assert code == 0
    m = tmp_path / "txt" / "measurements.txt"
    lines = m.read_text().splitlines()
    first = lines[1].split()
    again = " ".join([first[0], first[1], repr(float(first[2]) + dx_mm)] + first[3:])
    m.write_text("\n".join(lines + [again]) + "\n")
    args = ["import", tmp_path / "t.h5"]
    for kind in ("cameras", "photos", "measurements", "control"):
        args += [f"--{kind}", tmp_path / "txt" / f"{kind}.txt"]
    return args, len(lines) + 1


def run_cli_plain(*args):
    from sapgo.cli import main

    return main([str(a) for a in args])


def test_conflicting_duplicates_are_an_error_unless_merged(small_block, tmp_path, capsys):
    args, line = _exported(small_block, tmp_path, 0.5)   # 500 um apart, sigma 6 um
    capsys.readouterr()
    code, _, err = run_cli(capsys, *args)
    assert_one_line_error(code, err, "measurements.txt:2 and", f"measurements.txt:{line}",
                          "500.0 um apart", "--merge-duplicates")
    assert not (tmp_path / "t.h5").exists()
    code, out, err = run_cli(capsys, *args, "--merge-duplicates")
    assert code == 0 and "duplicate image measurement(s) merged" in err + out


def test_agreeing_duplicates_are_merged_with_a_warning(small_block, tmp_path, capsys):
    args, _ = _exported(small_block, tmp_path, 0.002)   # 2 um apart: within 3 sigma
    capsys.readouterr()
    code, out, err = run_cli(capsys, *args)
    assert code == 0 and "1 duplicate image measurement(s) merged" in err + out


@pytest.mark.parametrize("solver", ["band", "tree"])
def test_precision_stations_and_none(block_cache, tmp_path, solver):
    """``--precision stations`` gives the photos' standard deviations of the full pass, bit
    for bit, without the points' or the observations'; ``none`` gives none; the solution is
    the same."""
    import sapgo

    src = block_cache("prec", strips=4, photos_per_strip=8, control_points=8)
    out = {}
    for mode in ("full", "stations", "none"):
        run = tmp_path / f"{mode}.h5"
        run.write_bytes(src.read_bytes())
        s = sapgo.adjust(run, sapgo.Options(progress=False, solver=solver, precision=mode))
        with Project(run) as p:
            out[mode] = (s, p.solution("station_sigma"), p.solution("point_sigma"),
                         p.solution("obs_quality"), p.solution("point_corr"))
    full, st, no = out["full"], out["stations"], out["none"]
    np.testing.assert_array_equal(st[1], full[1])
    np.testing.assert_array_equal(st[4], full[4])
    np.testing.assert_array_equal(no[4], full[4])
    assert (full[2] > 0).any() and not st[2].any() and not st[3].any()
    assert not no[1].any() and not no[2].any()
    assert st[0].precision is not None and st[0].reliability is None
    assert no[0].precision is None
    assert "--precision stations" in st[0].full_report()
    assert "--precision none" in no[0].full_report()
