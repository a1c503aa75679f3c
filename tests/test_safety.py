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
