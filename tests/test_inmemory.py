"""A small project adjusted in memory (``Options.work_files``): the same kernels as a run
with work files, so the same results to the last bit; nothing written but the commit; a
killed run leaves the project as it was and nothing beside it."""

import json
import os
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest

import sapgo
from conftest import assert_one_line_error, digest, run_cli
from sapgo.adjust import IN_MEMORY_BYTES, _in_memory
from sapgo.project import SOLUTION_LAYOUT, Project
from sapgo.rawfile import CoreArray, RawArray
from sapgo.work import work_path


def results(path):
    """Every /solution dataset, the records (rejections are flagged in them), the report's
    figures (without timings and threads) and the attributes of the adjusted project."""
    with Project(path) as p:
        sol = {k: p.solution(k) for k in SOLUTION_LAYOUT}
        rec = {k: p.read(k) for k in ("stations", "points", "observations")}
        report = json.loads(p.file["solution/report"][()])
        attrs = {k: p.attr(k) for k in ("ordering", "band_width", "solver", "ordered")}
    for key in ("timings_s", "timings_per_iteration_s", "threads", "iteration_log", "path"):
        report.pop(key, None)
    return sol, rec, report, attrs


def assert_same(a, b):
    for part_a, part_b in zip(a[:2], b[:2]):
        assert part_a.keys() == part_b.keys()
        for k in part_a:
            np.testing.assert_array_equal(part_a[k], part_b[k], err_msg=k)
    assert a[2] == b[2]
    assert a[3] == b[3]


CASES = {
    "default": dict(),
    "self-calibration": dict(calibrate=("f", "k1", "p1"), max_iterations=30),
    "robust": dict(robust="cauchy", max_iterations=30),
    "snooping": dict(snooping=True),
    "free network": dict(datum="free"),
    "stations only": dict(precision="stations"),
    "tree": dict(solver="tree"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_in_memory_run_equals_the_run_with_work_files(p1_block, tmp_path, case):
    """Unordered (ordered in memory), then adjusted again (read whole into memory): every
    result as with work files, bit for bit."""
    files = tmp_path / "files.h5"
    shutil.copy(p1_block, files)
    opts = dict(progress=False, **CASES[case])
    for _ in range(2):
        a = sapgo.adjust(p1_block, sapgo.Options(work_files="never", **opts))
        b = sapgo.adjust(files, sapgo.Options(work_files="always", **opts))
        assert a.iterations == b.iterations and a.sigma0 == b.sigma0
        assert_same(results(p1_block), results(files))
    assert sorted(x.name for x in tmp_path.iterdir()) == ["files.h5", "p1.h5"]


def test_default_run_of_a_small_project_is_in_memory(p1_block, monkeypatch):
    module = sys.modules["sapgo.adjust"]   # (sapgo.adjust is the function)
    opts = sapgo.Options(progress=False)
    size = os.path.getsize(p1_block)
    assert size < IN_MEMORY_BYTES
    assert _in_memory(p1_block, opts, None)
    assert not _in_memory(p1_block, sapgo.Options(work_files="always"), None)
    assert not _in_memory(p1_block, sapgo.Options(keep_scratch=True), None)
    assert not _in_memory(p1_block, sapgo.Options(factor_storage="file"), None)
    assert not _in_memory(p1_block, opts, {"iteration": 1})   # (a run to resume)
    monkeypatch.setattr(module, "IN_MEMORY_BYTES", size - 1)   # (a larger project)
    assert not _in_memory(p1_block, opts, None)
    assert _in_memory(p1_block, sapgo.Options(work_files="never"), None)
    # and a sixteenth of the memory budget
    monkeypatch.setattr(module, "IN_MEMORY_BYTES", size)
    assert _in_memory(p1_block, sapgo.Options(memory=f"{16 * size}"), None)
    assert not _in_memory(p1_block, sapgo.Options(memory=f"{16 * size - 16}"), None)


RUN = ("import sys, sapgo; sapgo.adjust(sys.argv[1], sapgo.Options(progress=False, "
       "snooping=True))")


@pytest.mark.parametrize("fault", ["build:2", "checkpoint:1", "commit-write"])
def test_killed_in_memory_run_leaves_nothing_but_the_project(p1_block, tmp_path, fault):
    """No work directory, no ordered copy, no checkpoint: the project as it was; the run
    again (--resume finds nothing to resume) gives the uninterrupted result."""
    ref = tmp_path / "ref.h5"
    shutil.copy(p1_block, ref)
    sapgo.adjust(ref, sapgo.Options(progress=False, snooping=True))
    before = digest(p1_block)
    r = subprocess.run([sys.executable, "-c", RUN, str(p1_block)], capture_output=True,
                       text=True, env=dict(os.environ, SAPGO_FAULT=fault), timeout=300)
    assert r.returncode == -signal.SIGKILL, r.stderr
    assert digest(p1_block) == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["p1.h5", "p1.h5.lock", "ref.h5"]
    s = sapgo.adjust(p1_block, sapgo.Options(progress=False, snooping=True, resume=True))
    assert s.resumed_from_iteration is None
    assert_same(results(p1_block), results(ref))


def test_the_same_run_with_work_files_leaves_its_checkpoint(p1_block, tmp_path):
    """(The counterpart: with work files the killed run leaves what --resume needs.)"""
    code = RUN.replace("snooping=True", "snooping=True, work_files='always'")
    r = subprocess.run([sys.executable, "-c", code, str(p1_block)], capture_output=True,
                       text=True, env=dict(os.environ, SAPGO_FAULT="build:2"), timeout=300)
    assert r.returncode == -signal.SIGKILL, r.stderr
    assert (work_path(p1_block) / "checkpoint.json").exists()
    assert (tmp_path / "p1.h5.ordered").exists()


@pytest.mark.parametrize("flag, value", [("--resume", None), ("--keep-scratch", None),
                                         ("--factor-storage", "replay")])
def test_never_refuses_what_needs_work_files(p1_block, capsys, flag, value):
    before = digest(p1_block)
    args = ["adjust", p1_block, "--no-progress", "--work-files", "never", flag]
    code, _, err = run_cli(capsys, *(args + ([value] if value else [])))
    assert_one_line_error(code, err, "--work-files never", flag)
    assert digest(p1_block) == before


def test_core_array_reads_and_writes_as_the_file_does(tmp_path):
    rng = np.random.default_rng(3)
    f = RawArray(tmp_path / "a.bin", (50, 3, 2), mode="w")
    m = CoreArray((50, 3, 2))
    for a, b in ((0, 7), (7, 50), (20, 21)):
        x = rng.normal(size=(b - a, 3, 2))
        f[a:b] = x
        m[a:b] = x
    m.write(3, np.ones((2, 3, 2)))
    f.write(3, np.ones((2, 3, 2)))
    np.testing.assert_array_equal(m[0:50], f[0:50])
    np.testing.assert_array_equal(m[-1], f[-1])
    got = m[0:5]
    got[...] = -1.0   # (a copy, as the file's read is)
    np.testing.assert_array_equal(m[0:5], f[0:5])
    out = np.empty((4, 3, 2))
    np.testing.assert_array_equal(m.read(10, 14, out), f.read(10, 14))
    with pytest.raises(IndexError):
        m.write(49, np.zeros((2, 3, 2)))
    with pytest.raises(IndexError):
        m[0:50:2]
    f.close()
    m.close()


def test_ctrl_c_says_what_was_kept(p1_block, capsys, monkeypatch):
    """Interrupted in memory: nothing to resume, and the message says so; with work files
    (a checkpoint beside the project) it says how to resume."""
    module = sys.modules["sapgo.adjust"]   # (the command imports adjust from it)

    def interrupted(path, opts):
        if opts.work_files == "always":
            work_path(path).mkdir()
            (work_path(path) / "checkpoint.json").write_text("{}")
        raise KeyboardInterrupt

    monkeypatch.setattr(module, "adjust", interrupted)
    code, _, err = run_cli(capsys, "adjust", p1_block, "--no-progress")
    assert code == 130 and "held in memory and kept no checkpoint" in err
    assert "--resume" not in err
    code, _, err = run_cli(capsys, "adjust", p1_block, "--no-progress", "--work-files", "always")
    assert code == 130 and f"sapgo adjust --resume {p1_block}" in err


def test_a_factor_beyond_the_budget_goes_to_a_file_in_memory_too(block_cache, tmp_path,
                                                                  monkeypatch):
    """In memory the factor follows --memory as with work files: with a 4 MiB budget the
    factor of SAPGO-P-4 (3.8 MB, band width 26) is not kept in core but written to the work
    directory made for it; the results as with work files, and nothing left."""
    work_module = sys.modules["sapgo.work"]
    made = []
    real = work_module.Work.__init__

    def spy(self, *args, **kwargs):
        real(self, *args, **kwargs)
        made.append(self)

    monkeypatch.setattr(work_module.Work, "__init__", spy)
    src = block_cache("p4", preset="sapgo-p-4")
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    shutil.copy(src, a)
    shutil.copy(src, b)
    opts = dict(progress=False, memory="4M")
    sapgo.adjust(a, sapgo.Options(work_files="never", **opts))
    sapgo.adjust(b, sapgo.Options(work_files="always", **opts))
    assert not made[0].files and made[1].files
    for w in made:
        assert type(w.factor) is RawArray and w.factor.path.name == "factor.bin"
    assert type(made[0].xyz[0]) is CoreArray
    assert_same(results(a), results(b))
    assert sorted(x.name for x in tmp_path.iterdir()) == ["a.h5", "b.h5"]
