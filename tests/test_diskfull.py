"""A full disk (issue 19): every writing command checks free space first, and a full disk at
any moment gives one line and exit 2, the project unchanged and no temporaries left.

On a real small filesystem (a tmpfs, when the tests may mount one) and by injecting the
error of a full disk at every phase of an adjustment (``SAPGO_FAULT=enospc@phase``)."""

import contextlib
import os
import shutil
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

from conftest import digest

SAPGO = [sys.executable, "-m", "sapgo.cli"]


def run(*args, env=None, cwd=None):
    r = subprocess.run(SAPGO + [str(a) for a in args], capture_output=True, text=True,
                       env=dict(os.environ, **(env or {})), cwd=cwd)
    return r.returncode, r.stdout, r.stderr


def assert_one_line(code, err, *words):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, (code, err)
    assert len(lines) == 1 and lines[0].startswith("sapgo: error: "), err
    for w in words:
        assert w in lines[0], lines[0]


@contextlib.contextmanager
def small_fs(tmp_path, megabytes):
    """A tmpfs of ``megabytes`` MB (skips the test where it cannot be mounted)."""
    mnt = tmp_path / f"fs-{uuid.uuid4().hex[:6]}"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={megabytes}m", "tmpfs", str(mnt)],
                       capture_output=True)
    if r.returncode != 0:
        pytest.skip("a tmpfs cannot be mounted here (the injected faults below still run)")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


def test_generate_and_import_on_a_full_disk(tmp_path, p1_block):
    with small_fs(tmp_path, 8) as fs:
        code, _, err = run("generate", "--preset", "sapgo-p-3", fs / "p3.h5")
        assert_one_line(code, err, "not enough free space", "p3.h5")
        code, _, err = run("export", p1_block, tmp_path / "txt")
        assert code == 0, err
        files = {p.stem: p for p in (tmp_path / "txt").iterdir()}
        args = ["import", fs / "t.h5"]
        for kind in ("cameras", "photos", "measurements", "control"):
            if kind in files:
                args += [f"--{kind}", files[kind]]
        code, _, err = run(*args)
        assert_one_line(code, err, "not enough free space")
        assert list(fs.iterdir()) == []


def test_order_and_adjust_on_a_disk_with_room_for_the_project_only(tmp_path, block_cache):
    src = block_cache("square", strips=14, photos_per_strip=14, control_points=12)
    size_mb = src.stat().st_size / 2**20
    with small_fs(tmp_path, int(size_mb + 40)) as fs:   # the project and the margin, no more
        path = fs / "b.h5"
        shutil.copy(src, path)
        filler = fs / "filler"
        free = shutil.disk_usage(fs).free
        with open(filler, "wb") as f:   # leave the margin (32 MB) and less than the
            f.truncate(0)                # ordered copy needs (its records alone: 32 kB)
            f.write(b"\0" * max(0, free - (32 << 20) - (32 << 10)))
        before = digest(path)
        for args in (["order", path], ["adjust", path, "--no-progress"]):
            code, _, err = run(*args)
            assert_one_line(code, err, "not enough free space")
            assert digest(path) == before
            assert sorted(p.name for p in fs.iterdir()) == ["b.h5", "filler"]


@pytest.mark.parametrize("phase", ["build:1", "solve:2", "update:1", "checkpoint:1",
                                   "commit-copy", "commit-write", "commit-replace"])
def test_a_full_disk_at_any_phase_of_adjust(small_block, tmp_path, phase):
    before = digest(small_block)
    code, out, err = run("adjust", small_block, "--no-progress",
                         env={"SAPGO_FAULT": f"enospc@{phase}"})
    assert_one_line(code, err, str(small_block), "disk is full", "nothing was changed")
    assert "Traceback" not in err
    assert digest(small_block) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["small.h5"]
    code, out, err = run("adjust", small_block, "--no-progress")   # and then it runs
    assert code == 0, err
