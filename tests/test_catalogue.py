"""The bad-input catalogue of issue 19, one case per line: the damage done to a copy of a small
block, the command, the exit code, words of the first (and only) line of the error; every
case leaves the project byte for byte as it was, and no file beside it."""

import h5py
import pytest

from conftest import collinear_control, digest, run_cli
from test_safety import flip_byte


def set_obs(path, field, value, record=5):
    with h5py.File(path, "r+") as f:
        ds = f["observations"]
        r = ds[record]
        r[field] = value
        ds[record] = r


def set_eo(path, k, value, record=7):
    with h5py.File(path, "r+") as f:
        ds = f["stations"]
        r = ds[record]
        r["eo"][k] = value
        ds[record] = r


def set_xyz(path, value, record=3):
    with h5py.File(path, "r+") as f:
        ds = f["points"]
        r = ds[record]
        r["xyz"][2] = value
        ds[record] = r


NOTHING = None
CASES = [
    # damage                                    command                     code  first line
    (NOTHING, ["adjust", "--alpha", "2"], 2, "--alpha (snooping_alpha) 2.0: the significance"),
    (NOTHING, ["adjust", "--alpha", "0"], 2, "--alpha (snooping_alpha) 0.0"),
    (NOTHING, ["adjust", "--alpha", "1"], 2, "--alpha (snooping_alpha) 1.0"),
    (NOTHING, ["adjust", "--alpha", "-1"], 2, "--alpha (snooping_alpha) -1.0"),
    (NOTHING, ["adjust", "--alpha", "nan"], 2, "--alpha (snooping_alpha) nan"),
    (NOTHING, ["adjust", "--tol-cost", "inf"], 2, "--tol-cost (tol_cost) inf"),
    (NOTHING, ["adjust", "--tol-position", "0"], 2, "--tol-position (tol_position) 0.0"),
    (NOTHING, ["adjust", "--max-iterations", "0"], 2, "--max-iterations (max_iterations) 0"),
    (NOTHING, ["adjust", "--robust-threshold", "-1"], 2, "--robust-threshold"),
    (NOTHING, ["adjust", "--memory", "12Q"], 2, "12Q"),
    (NOTHING, ["generate", "--preset", "sapgo-p-1"], 2, "exists: use --force"),
    (lambda p: set_obs(p, "x", 1e300), ["adjust"], 2, "lie far outside camera 1's format"),
    (lambda p: set_obs(p, "y", -5e4), ["adjust"], 2, "observations record 5"),
    (lambda p: set_obs(p, "x", float("nan")), ["adjust"], 2, "x is NaN"),
    (lambda p: set_eo(p, 5, 1e300), ["adjust"], 2, "are beyond 1e+10 m from the frame's origin"),
    (lambda p: set_eo(p, 3, 5e8), ["adjust"], 2, "times the block's size"),
    (lambda p: set_xyz(p, 1e12), ["adjust"], 2, "points record 3"),
    (lambda p: flip_byte(p, "observations"), ["adjust"], 2, "fail their checksum"),
    (lambda p: flip_byte(p, "points"), ["order"], 2, "/points records 0.."),
    (collinear_control, ["adjust"], 2, "not positive definite"),
]


@pytest.mark.parametrize("damage, command, code, first", CASES,
                         ids=[f"{i}-{c[1][0]}-{c[3][:24]}" for i, c in enumerate(CASES)])
def test_bad_input(small_block, tmp_path, capsys, damage, command, code, first):
    if damage is not None:
        damage(small_block)
    before = digest(small_block)
    args = command[:1] + ([small_block] if command[0] != "generate" else
                          command[1:] + [small_block]) + (command[1:] if command[0] !=
                                                          "generate" else [])
    got, _, err = run_cli(capsys, *args)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert got == code, err
    assert len(lines) == 1 and lines[0].startswith("sapgo: error: ") and first in lines[0], err
    assert digest(small_block) == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["small.h5"]
