"""Crash safety: a run killed with SIGKILL at any moment, then reopened and resumed.

The kills are real: the adjustment runs in a subprocess that is killed by SIGKILL, either at a
chosen point (the ``SAPGO_FAULT`` hook makes the process kill itself there, so every phase is
hit deterministically) or from outside at whatever moment it has reached.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

import sapgo
from conftest import digest, read_records
from sapgo.work import work_path
from sapgo.project import Project

RUN = ("import sys, sapgo; sapgo.adjust(sys.argv[1], sapgo.Options(progress=False, "
       "chunk_points=40, chunk_rows=4, max_iterations=int(sys.argv[2]), work_files='always'))")




def solution(path):
    with Project(path) as p:
        return {k: p.solution(k) for k in ("station_corr", "point_corr", "residuals")}, \
            json.loads(p.file["solution/report"][()])


@pytest.fixture(scope="module")
def reference(block_cache, tmp_path_factory):
    """An ordered p-1 block and its uninterrupted adjustment (same chunking)."""
    d = tmp_path_factory.mktemp("ref")
    ordered = d / "ordered.h5"
    shutil.copy(block_cache("p1", preset="sapgo-p-1"), ordered)
    sapgo.order_project(ordered)
    done = d / "done.h5"
    shutil.copy(ordered, done)
    sapgo.adjust(done, sapgo.Options(progress=False, chunk_points=40, chunk_rows=4))
    return ordered, solution(done)


def killed_run(path, fault, max_iterations=10):
    env = dict(os.environ, SAPGO_FAULT=fault)
    r = subprocess.run([sys.executable, "-c", RUN, str(path), str(max_iterations)], env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == -signal.SIGKILL, r.stderr
    return r


@pytest.mark.parametrize("fault, completed", [
    ("build:1", 0), ("build:2", 1), ("solve:2", 1), ("update:1", 0), ("update:3", 2),
    ("checkpoint:2", 1), ("commit-copy:*", 3), ("commit-write:*", 3), ("commit-replace:*", 3),
])
def test_killed_anywhere_then_resumed(reference, tmp_path, fault, completed):
    ordered, (ref_sol, ref_report) = reference
    assert ref_report["iterations"] == 3
    path = tmp_path / "p1.h5"
    shutil.copy(ordered, path)
    before = digest(path)
    killed_run(path, fault)
    # the project is whole, readable and unchanged: nothing is written to it before the
    # commit's atomic rename
    assert digest(path) == before
    rec = read_records(path)
    assert len(rec["observations"]) > 0
    ck = json.loads((work_path(path) / "checkpoint.json").read_text())
    assert ck["iteration"] == completed
    # resume: continues from the last completed iteration and gives the uninterrupted result
    s = sapgo.adjust(path, sapgo.Options(progress=False, chunk_points=40, chunk_rows=4,
                                         resume=True))
    assert s.resumed_from_iteration == completed
    assert s.iterations == 3 and s.converged
    sol, report = solution(path)
    for k in ref_sol:
        np.testing.assert_array_equal(sol[k], ref_sol[k], err_msg=k)
    assert report["sigma0"] == ref_report["sigma0"]
    assert [r["sigma0"] for r in report["iteration_log"]] == \
        [r["sigma0"] for r in ref_report["iteration_log"]]
    assert not work_path(path).exists()
    assert not path.with_name(path.name + ".commit.tmp").exists()


def test_resume_can_extend_a_run_stopped_by_max_iterations(reference, tmp_path):
    ordered, (ref_sol, _) = reference
    path = tmp_path / "p1.h5"
    shutil.copy(ordered, path)
    killed_run(path, "commit-copy:*", max_iterations=1)
    s = sapgo.adjust(path, sapgo.Options(progress=False, chunk_points=40, chunk_rows=4,
                                         resume=True))
    assert s.resumed_from_iteration == 1 and s.iterations == 3
    np.testing.assert_array_equal(solution(path)[0]["point_corr"], ref_sol["point_corr"])


def test_resume_without_an_interrupted_run_starts_afresh(reference, tmp_path, capsys):
    ordered, (ref_sol, _) = reference
    path = tmp_path / "p1.h5"
    shutil.copy(ordered, path)
    s = sapgo.adjust(path, sapgo.Options(progress=False, chunk_points=40, chunk_rows=4,
                                         resume=True))
    assert s.resumed_from_iteration is None
    assert "no interrupted run" in capsys.readouterr().err
    np.testing.assert_array_equal(solution(path)[0]["point_corr"], ref_sol["point_corr"])


def test_a_checkpoint_of_another_version_of_the_project_is_not_used(reference, tmp_path):
    ordered, (ref_sol, _) = reference
    path = tmp_path / "p1.h5"
    shutil.copy(ordered, path)
    killed_run(path, "update:2")
    sapgo.order_project(path)  # a rewritten project: the checkpoint no longer applies
    s = sapgo.adjust(path, sapgo.Options(progress=False, chunk_points=40, chunk_rows=4,
                                         resume=True))
    assert s.resumed_from_iteration is None and s.iterations == 3


def test_killed_from_outside_mid_run_and_resumed_from_the_command_line(block_cache, tmp_path):
    src = block_cache("resume", strips=20, photos_per_strip=150, control_points=120)
    ref = tmp_path / "ref.h5"
    shutil.copy(src, ref)
    sapgo.order_project(ref)
    path = tmp_path / "block.h5"
    shutil.copy(ref, path)
    sapgo.adjust(ref, sapgo.Options(progress=False))
    before = digest(path)
    proc = subprocess.Popen([sys.executable, "-m", "sapgo.cli", "adjust", str(path),
                             "--no-progress", "--quiet", "--work-files", "always"],
                            stderr=subprocess.PIPE)
    ck = work_path(path) / "checkpoint.json"
    t0 = time.monotonic()
    while time.monotonic() - t0 < 120:  # kill once the first iteration is on disk
        if ck.exists() and json.loads(ck.read_text())["iteration"] >= 1:
            break
        assert proc.poll() is None, "the run ended before it could be killed"
        time.sleep(0.002)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert digest(path) == before
    r = subprocess.run([sys.executable, "-m", "sapgo.cli", "adjust", str(path), "--resume",
                        "--no-progress", "--json", str(tmp_path / "r.json")],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "resumed after iteration" in r.stdout
    report = json.loads((tmp_path / "r.json").read_text())
    assert report["resumed_from_iteration"] >= 1 and report["converged"]
    a, b = solution(path)[0], solution(ref)[0]
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_a_damaged_work_directory_starts_afresh(reference, tmp_path, capsys):
    ordered, (ref_sol, _) = reference
    path = tmp_path / "p1.h5"
    shutil.copy(ordered, path)
    killed_run(path, "update:2")
    with open(work_path(path) / "xyz.1.bin", "r+b") as f:  # a work file cut short
        f.truncate(100)
    s = sapgo.adjust(path, sapgo.Options(progress=False, chunk_points=40, chunk_rows=4,
                                         resume=True))
    assert "cannot be resumed" in capsys.readouterr().err
    assert s.resumed_from_iteration is None and s.iterations == 3
    np.testing.assert_array_equal(solution(path)[0]["point_corr"], ref_sol["point_corr"])


def test_a_bad_memory_budget_is_refused_before_anything_runs(reference, tmp_path):
    ordered, _ = reference
    path = tmp_path / "p1.h5"
    shutil.copy(ordered, path)
    before = digest(path)
    with pytest.raises(sapgo.SapgoError, match="such as 512M"):
        sapgo.adjust(path, sapgo.Options(progress=False, memory="lots"))
    assert digest(path) == before and not work_path(path).exists()


def test_robust_run_killed_in_its_reweighting_phase_resumes_to_the_same_result(tmp_path):
    """The robust phase's redundancy numbers and tolerances survive a kill: the resumed run
    equals the uninterrupted one."""
    path = tmp_path / "b.h5"
    sapgo.generate_block(path, strips=2, photos_per_strip=6, control_points=6, blunders=2,
                         blunder_size=(0.08, 0.1))
    sapgo.order_project(path)
    ref = tmp_path / "ref.h5"
    shutil.copy(path, ref)
    opts = dict(progress=False, robust="cauchy", max_iterations=30)
    s_ref = sapgo.adjust(ref, sapgo.Options(**opts))
    first_robust = next(r["iteration"] for r in s_ref.iteration_log if r["robust_downweighted"])
    assert s_ref.converged and s_ref.iterations > first_robust + 1
    run = ("import sys, sapgo; sapgo.adjust(sys.argv[1], sapgo.Options(progress=False, "
           "robust='cauchy', max_iterations=30, work_files='always'))")
    r = subprocess.run([sys.executable, "-c", run, str(path)], capture_output=True, text=True,
                       env=dict(os.environ, SAPGO_FAULT=f"update:{first_robust + 1}"), timeout=300)
    assert r.returncode == -signal.SIGKILL, r.stderr
    assert (work_path(path) / "robust_r.bin").exists()
    s = sapgo.adjust(path, sapgo.Options(resume=True, **opts))
    assert s.resumed_from_iteration == first_robust
    assert s.iterations == s_ref.iterations
    np.testing.assert_array_equal(solution(path)[0]["point_corr"],
                                  solution(ref)[0]["point_corr"])
