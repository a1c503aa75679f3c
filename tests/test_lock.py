"""The project lock (issue 19): one writing command on a project at a time; a second
writer refused with one line naming the holder; a killed holder's lock taken over; a
failed adjust leaves the project as it was."""

import json
import os
import signal
import subprocess
import sys
import time

import h5py
import numpy as np
import pytest

from conftest import assert_one_line_error, collinear_control, digest, run_cli
from sapgo.lock import lock_path, project_lock

HOLD = """
import sys, time
from pathlib import Path
from sapgo.lock import project_lock
with project_lock(sys.argv[1], sys.argv[2]):
    Path(sys.argv[3]).write_text("held")
    while not Path(sys.argv[4]).exists():
        time.sleep(0.02)
"""


class Holder:
    """Another process holding a project's lock for ``command`` until released."""

    def __init__(self, tmp_path, project, command):
        tag = f"{os.getpid()}-{time.monotonic_ns()}"
        flags = tmp_path / "flags"
        flags.mkdir(exist_ok=True)
        self.held, self.go = flags / f"held-{tag}", flags / f"go-{tag}"
        self.proc = subprocess.Popen([sys.executable, "-c", HOLD, str(project), command,
                                      str(self.held), str(self.go)])
        t0 = time.time()
        while not self.held.exists():
            assert self.proc.poll() is None and time.time() - t0 < 60
            time.sleep(0.02)

    def release(self):
        self.go.write_text("go")
        assert self.proc.wait(60) == 0

    def kill(self):
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(60)


def test_second_adjust_refused_naming_the_holder(small_block, tmp_path, capsys):
    before = digest(small_block)
    h = Holder(tmp_path, small_block, "adjust")
    try:
        code, out, err = run_cli(capsys, "adjust", small_block, "--no-progress")
        assert_one_line_error(code, err, str(small_block), "sapgo adjust",
                              f"process {h.proc.pid}", "try again")
        assert digest(small_block) == before   # not ordered, not written
        assert not (tmp_path / "small.h5.work").exists()
    finally:
        h.release()
    assert not lock_path(small_block).exists()   # (released: the lock file went with it)
    code, out, err = run_cli(capsys, "adjust", small_block, "--no-progress")
    assert code == 0 and "sigma0" in out


def test_adjust_during_order_and_import_during_import(small_block, tmp_path, capsys):
    h = Holder(tmp_path, small_block, "order")
    try:
        code, _, err = run_cli(capsys, "adjust", small_block, "--no-progress")
        assert_one_line_error(code, err, "sapgo order", f"process {h.proc.pid}")
        code, _, err = run_cli(capsys, "order", small_block)
        assert_one_line_error(code, err, "sapgo order")
    finally:
        h.release()
    # two imports of one new project: the second is refused, nothing is created
    bal = tmp_path / "problem.txt"
    bal.write_text("2 3 4\n0 0 1.0 2.0\n1 0 1.5 2.5\n0 1 -1.0 3.0\n1 1 -1.5 3.5\n"
                   + "\n".join(["0.01"] * 18) + "\n" + "\n".join(["1.0"] * 9) + "\n")
    target = tmp_path / "bal.h5"
    h = Holder(tmp_path, target, "import")
    try:
        code, _, err = run_cli(capsys, "import", "--format", "bal", bal, target)
        assert_one_line_error(code, err, str(target), "sapgo import")
        assert not target.exists()
    finally:
        h.release()


def test_killed_holder_is_taken_over(small_block, tmp_path, capsys):
    h = Holder(tmp_path, small_block, "adjust")
    h.kill()
    assert lock_path(small_block).exists()   # left behind by the killed process
    code, out, err = run_cli(capsys, "adjust", small_block, "--no-progress")
    assert code == 0, err
    assert not lock_path(small_block).exists()


def test_lock_is_reentrant_in_process(small_block):
    with project_lock(small_block, "adjust"):
        with project_lock(small_block, "order"):
            assert lock_path(small_block).exists()
        info = json.loads(lock_path(small_block).read_text())
        assert info["pid"] == os.getpid() and info["command"] == "adjust"
    assert not lock_path(small_block).exists()


def test_two_concurrent_adjusts(block_cache, tmp_path):
    """The issue's case: two adjusts of one project at once. Each either finishes or is
    refused by the lock; the project holds the solution of the run that finished last."""
    src = block_cache("square", strips=14, photos_per_strip=14, control_points=12)
    path = tmp_path / "d.h5"
    path.write_bytes(src.read_bytes())
    cmd = [sys.executable, "-m", "sapgo.cli", "adjust", str(path), "--no-progress"]
    runs = [{"json": tmp_path / f"r{i}.json", "extra": extra}
            for i, extra in enumerate([[], ["--max-iterations", "2"]])]
    for r in runs:
        r["proc"] = subprocess.Popen(cmd + r["extra"] + ["--json", str(r["json"])],
                                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    ended = []
    t0 = time.time()
    while len(ended) < 2 and time.time() - t0 < 300:
        for r in runs:
            if r not in ended and r["proc"].poll() is not None:
                ended.append(r)
        time.sleep(0.01)
    for r in runs:
        r["out"], r["err"] = r["proc"].communicate()
        r["code"] = r["proc"].returncode
        assert r["code"] in (0, 2), r["err"]
        if r["code"] == 2:   # refused at once, naming the other run
            assert r["err"].startswith("sapgo: error: ") and "Traceback" not in r["err"]
            # (the holder's note, or "another process" when it was read before written)
            assert ("being written by sapgo adjust" in r["err"]
                    or "being written by another process" in r["err"])
    done = [r for r in ended if r["code"] == 0]
    assert done
    last = json.loads(done[-1]["json"].read_text())
    with h5py.File(path, "r") as f:
        assert float(f["solution"].attrs["sigma0"]) == last["sigma0"]
        assert int(f["solution"].attrs["iterations"]) == last["iterations"]
    assert not any(x.name.endswith((".tmp", ".ordered", ".lock", ".work"))
                   for x in tmp_path.iterdir())


def test_failed_adjust_leaves_the_project_byte_for_byte(small_block, tmp_path, capsys):
    """The implicit ordering goes into the commit: a run that fails writes nothing."""
    collinear_control(small_block)   # passes the count check, fails at the pivot
    before = digest(small_block)
    code, out, err = run_cli(capsys, "adjust", small_block, "--no-progress")
    assert code == 2 and "Traceback" not in err
    assert digest(small_block) == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["small.h5"]


@pytest.mark.parametrize("fault", ["build:2", "commit-write"])
def test_killed_unordered_run_resumes_on_its_ordered_copy(small_block, tmp_path, fault):
    """A run of an unordered project killed midway leaves the project as it was and its
    ordered copy beside it; --resume goes on from the checkpoint on that copy."""
    before = digest(small_block)
    env = dict(os.environ, SAPGO_FAULT=fault)
    cmd = [sys.executable, "-m", "sapgo.cli", "adjust", str(small_block), "--no-progress",
           "--work-files", "always"]
    r = subprocess.run(cmd, env=env, capture_output=True, text=True)
    assert r.returncode == -signal.SIGKILL
    assert digest(small_block) == before
    assert (tmp_path / "small.h5.ordered").exists()
    r = subprocess.run(cmd + ["--resume"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "resumed after iteration" in r.stdout and "discarded" not in r.stderr
    assert sorted(x.name for x in tmp_path.iterdir()) == ["small.h5"]
