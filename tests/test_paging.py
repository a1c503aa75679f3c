"""Per-station vectors memory-mapped from scratch files (:mod:`sapgo.paging`,
``--page-stations``): the same adjustment, bit for bit, with the process's pages released."""

import os
import shutil
import signal
import subprocess
import sys

import numpy as np
import pytest

import sapgo
import sapgo.paging as paging
import sapgo.solve.band as band_mod
from sapgo.project import Project
from test_replay import OPTS, equal, prior_block, run  # noqa: F401  (the fixture)


def _rss_mb():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def test_pages_go_back_to_the_page_cache_and_keep_their_data(tmp_path):
    pager = paging.Pager(tmp_path, min_bytes=0)
    a = pager.zeros((4 << 20, 6))             # 192 MiB, sparse: nothing resident yet
    before = _rss_mb()
    assert a.shape == (4 << 20, 6) and not a.any()
    a[:, 2] = np.arange(len(a))               # every page touched
    assert _rss_mb() - before > 150
    pager.release()
    assert _rss_mb() - before < 20            # the pages left the process ...
    assert a[123456, 2] == 123456 and a[:, 2].sum() == len(a) * (len(a) - 1) // 2  # ... not the data
    assert list(tmp_path.iterdir()) == []     # (the file is unlinked: nothing left behind)
    del a
    pager.release()                           # (a map gone meanwhile is skipped)


def test_in_core_below_the_threshold_and_outside_a_run(tmp_path):
    assert not paging.active()
    x = paging.zeros((1000, 6))
    assert isinstance(x, np.ndarray) and x.base is None
    with paging.paged(tmp_path) as pager:
        assert paging.active() and pager._thread.is_alive()
        small = paging.zeros(10)
        big = paging.empty((paging.MIN_PAGED_BYTES // 8 + 1,))
        assert small.base is None and big.base is not None   # (the map)
        c = paging.copy(np.arange(300000.0).reshape(-1, 3))
        assert c.base is not None and c[-1, 2] == 299999.0
    assert not paging.active() and pager._thread is None


def test_npy_written_and_read_a_chunk_at_a_time(tmp_path, monkeypatch):
    monkeypatch.setattr(paging, "CHUNK_ROWS", 7)
    a = np.random.default_rng(1).normal(size=(100, 6))
    with open(tmp_path / "a.npy", "wb") as f:
        paging.save_npy(f, a)
    np.testing.assert_array_equal(np.load(tmp_path / "a.npy"), a)
    with paging.paged(tmp_path, min_bytes=0):
        b = paging.load_npy(tmp_path / "a.npy")
        assert b.base is not None
    np.testing.assert_array_equal(b, a)
    cut = tmp_path / "cut.npy"
    cut.write_bytes((tmp_path / "a.npy").read_bytes()[:-8])
    with pytest.raises(ValueError, match="bytes, not those of"):
        paging.npy_header(cut)


@pytest.mark.parametrize("kw", [dict(factor_storage="file"),
                                dict(factor_storage="replay"),
                                dict(factor_storage="file", method="levenberg-marquardt"),
                                dict(factor_storage="replay", snooping=True)])
def test_paged_run_is_the_in_core_run(prior_block, tmp_path, monkeypatch, kw):  # noqa: F811
    """Every per-station vector mapped (``page_stations=0``): the same adjustment, precision
    and rejections, bit for bit; pages released throughout."""
    monkeypatch.setattr(band_mod, "REPLAY_SEGMENT_BYTES", 1)
    rounds = []
    real = paging.Pager.release

    def counting(self):
        rounds.append(1)
        real(self)

    monkeypatch.setattr(paging.Pager, "release", counting)
    s_c, c = run(prior_block, tmp_path, "core", **kw)
    assert not rounds
    s_p, p = run(prior_block, tmp_path, "mapped", page_stations=0, **kw)
    assert len(rounds) > 10
    assert s_p.iterations == s_c.iterations and s_p.sigma0 == s_c.sigma0
    assert [x["observation"] for x in s_p.rejected] == [x["observation"] for x in s_c.rejected]
    for k in ("eo", "xyz", "residuals", "station_sigma", "point_sigma", "obs_quality"):
        equal(c[k], p[k], 0, k)
    assert s_p.precision == s_c.precision
    assert [x for x in tmp_path.iterdir() if x.name.startswith("paged.")] == []


def test_paging_threshold(prior_block, tmp_path):  # noqa: F811
    """Above ``page_stations`` stations the run pages, at or below it not."""
    seen = []
    real = paging.paged

    def spy(directory, enabled=True, min_bytes=paging.MIN_PAGED_BYTES):
        seen.append(enabled)
        return real(directory, enabled, min_bytes)

    import importlib

    adjust_mod = importlib.import_module("sapgo.adjust")
    orig = adjust_mod.paging.paged
    adjust_mod.paging.paged = spy
    try:
        with Project(prior_block) as p:
            n = p.n_stations
        for limit, want in [(n, False), (n - 1, True), (None, False)]:
            path = tmp_path / f"t{limit}.h5"
            shutil.copy(prior_block, path)
            sapgo.adjust(path, sapgo.Options(**OPTS, page_stations=limit))
            assert seen[-1] is want
    finally:
        adjust_mod.paging.paged = orig
    with pytest.raises(sapgo.SapgoError, match="page stations -1"):
        sapgo.Options(page_stations=-1).check()


RUN = ("import sys, sapgo; "
       "sapgo.adjust(sys.argv[1], sapgo.Options(progress=False, chunk_points=40, "
       "chunk_rows=2, page_stations=0, resume=len(sys.argv) > 2, work_files='always'))")


@pytest.mark.parametrize("fault", ["update:2", "checkpoint:1"])
def test_paged_run_killed_and_resumed(prior_block, tmp_path, fault):  # noqa: F811
    """Killed with its vectors mapped, resumed from the checkpoint (read a chunk at a time
    into mapped vectors): the uninterrupted result, bit for bit."""
    _, ref = run(prior_block, tmp_path, "ref")
    path = tmp_path / "killed.h5"
    shutil.copy(prior_block, path)
    r = subprocess.run([sys.executable, "-c", RUN, str(path)], capture_output=True, text=True,
                       env=dict(os.environ, SAPGO_FAULT=fault), timeout=300)
    assert r.returncode == -signal.SIGKILL, r.stderr
    r = subprocess.run([sys.executable, "-c", RUN, str(path), "resume"],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    assert "cannot be resumed" not in r.stderr and "no interrupted run" not in r.stderr
    with Project(path) as p:
        eo = p.read("stations")["eo"]
        sig = p.solution("station_sigma")
    equal(ref["eo"], eo, 0, "eo")
    equal(ref["station_sigma"], sig, 0, "station_sigma")
    assert [x for x in tmp_path.iterdir() if x.name.startswith("paged.")] == []


def _datasets(path):
    import h5py

    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                out[name] = obj[()]
        f.visititems(visit)
        out["attrs"] = {k: v for k, v in f.attrs.items() if k not in ("uuid", "history")}
    return out


@pytest.mark.parametrize("solver", ["band", "auto"])
def test_paged_order_is_the_in_core_order(block_cache, tmp_path, monkeypatch, solver):
    """``sapgo order`` of a block above ``page_stations`` (0 here): per-station
    vectors and the station graph mapped, the edges sorted externally; the same records,
    candidates and band width as in core. A photo with too few points (excluded) makes
    the exclusion passes run twice."""
    from conftest import read_records, rewrite

    rec = read_records(block_cache("paged-order", strips=5, photos_per_strip=40,
                                   control_points=12, seed=4))
    from sapgo.project import STATUS_REJECTED

    ob = rec["observations"]
    mine = np.flatnonzero(ob["station"] == 57)
    ob["status"][mine[2:]] = STATUS_REJECTED   # photo 57 keeps 2 points: excluded
    src = tmp_path / "src.h5"
    rewrite(src, rec)
    results = {}
    real = paging.Pager.zeros
    monkeypatch.setattr(paging, "CHUNK_ROWS", 37)
    for name, limit in [("core", None), ("mapped", 0)]:
        path = tmp_path / f"{name}.h5"
        shutil.copy(src, path)
        calls = []
        monkeypatch.setattr(paging.Pager, "zeros",
                            lambda self, *a, **k: calls.append(1) or real(self, *a, **k))
        r = sapgo.order_project(path, solver=solver, memory="4M", page_stations=limit)
        results[name] = (r, _datasets(path), len(calls))
    (rc, dc, nc), (rm, dm, nm) = results["core"], results["mapped"]
    assert nc == 0 and nm > 20 and rc.excluded_stations
    assert (rm.band_width, rm.ordering, rm.candidates, rm.excluded_stations,
            rm.n_excluded_points) == (rc.band_width, rc.ordering, rc.candidates,
                                      rc.excluded_stations, rc.n_excluded_points)
    assert dm.keys() == dc.keys()
    for k in dc:
        if k == "attrs":
            assert {a: str(v) for a, v in dm[k].items()} == {a: str(v) for a, v in dc[k].items()}
        else:
            np.testing.assert_array_equal(dm[k], dc[k], err_msg=k)


def test_a_full_disk_is_an_error_naming_the_directory(tmp_path, monkeypatch):
    """The scratch vector's blocks are allocated when it is made: a full disk is an
    OSError there (one line from the command line), not a SIGBUS at a write."""
    import errno

    def full(fd, offset, length):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(os, "posix_fallocate", full)
    pager = paging.Pager(tmp_path, min_bytes=0)
    with pytest.raises(OSError, match="No space left on device") as exc:
        pager.zeros((1000, 6))
    assert exc.value.filename == os.fspath(tmp_path) and "scratch vector" in str(exc.value)
    assert list(tmp_path.iterdir()) == []


def _advice_now():
    """numpy's huge-page advice as it is (asked through its switch, then put back)."""
    switch = paging._advice_switch()
    now = switch(True)
    switch(now)
    return now


@pytest.mark.parametrize("numpy_setting", [True, False])
def test_commands_run_with_numpy_hugepage_advice_off(small_block, monkeypatch,
                                                    numpy_setting):
    """``adjust`` (and every command that writes a project) runs with numpy's huge-page
    advice off, and leaves numpy's setting as it found it, after a failure too; a value of
    ``NUMPY_MADVISE_HUGEPAGE`` in the environment is kept."""
    import importlib

    adjust_mod = importlib.import_module("sapgo.adjust")   # (sapgo.adjust: the function)
    monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
    switch = paging._advice_switch()
    assert switch is not None   # (numpy >= 1.20 has it; the pinned range does)
    seen = []
    real = adjust_mod.check_values

    def spy(p):
        seen.append(_advice_now())
        return real(p)

    monkeypatch.setattr(adjust_mod, "check_values", spy)
    before = switch(numpy_setting)
    try:
        sapgo.adjust(small_block, sapgo.Options(max_iterations=2))
        assert seen == [False] and _advice_now() is numpy_setting
        with pytest.raises(sapgo.SapgoError, match="999999"):   # (inside the command)
            sapgo.adjust(small_block, sapgo.Options(fix=("fix:999999:all",)))
        assert seen == [False, False] and _advice_now() is numpy_setting
        monkeypatch.setenv("NUMPY_MADVISE_HUGEPAGE", "1")
        seen.clear()
        sapgo.adjust(small_block, sapgo.Options(max_iterations=2))
        assert seen == [numpy_setting]
    finally:
        switch(before)


@pytest.mark.parametrize("numpy_setting", [True, False])
def test_hugepage_advice_off_counts_threads(monkeypatch, numpy_setting):
    """Two blocks in two threads, the first to open closing first: the advice stays off
    until the second closes, and then numpy's setting is the one found before both (a
    switch that each block restores by itself would leave it off, or on too early)."""
    import threading

    monkeypatch.delenv("NUMPY_MADVISE_HUGEPAGE", raising=False)
    switch = paging._advice_switch()
    assert switch is not None
    a_in, b_in, a_out, b_check = (threading.Event() for _ in range(4))
    seen = {}

    def first():
        with paging.hugepage_advice_off():
            a_in.set()
            b_in.wait(10)
            seen["a inside"] = _advice_now()
        a_out.set()

    def second():
        a_in.wait(10)
        with paging.hugepage_advice_off():
            b_in.set()
            a_out.wait(10)
            seen["b inside, a gone"] = _advice_now()
        b_check.set()

    before = switch(numpy_setting)
    try:
        threads = [threading.Thread(target=first), threading.Thread(target=second)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(20)
        assert b_check.is_set() and a_out.is_set()
        assert seen == {"a inside": False, "b inside, a gone": False}
        assert _advice_now() is numpy_setting
        # nested in one thread (a command inside another): the same
        with paging.hugepage_advice_off():
            with paging.hugepage_advice_off():
                assert _advice_now() is False
            assert _advice_now() is False
        assert _advice_now() is numpy_setting
        assert paging._advice_depth == 0
    finally:
        switch(before)
