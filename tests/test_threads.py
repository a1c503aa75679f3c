"""The kernels' thread count: one while other processes run, every thread on an idle
machine, and the same results either way."""

import multiprocessing
import shutil
import time

import numba
import numpy as np
import pytest

import sapgo
from sapgo import threads


def _spin(stop):
    while not stop.is_set():
        pass


def test_another_running_process_is_seen():
    if threads.others_running() is None:
        pytest.skip("no /proc")
    stop = multiprocessing.Event()
    proc = multiprocessing.Process(target=_spin, args=(stop,), daemon=True)
    proc.start()
    try:
        time.sleep(0.3)
        seen = [threads.others_running() for _ in range(20)]
    finally:
        stop.set()
        proc.join(10)
    assert max(seen) >= 1


def test_adapt_uses_one_thread_while_others_run_and_all_after_the_hold(monkeypatch):
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one thread")
    others = [0]
    monkeypatch.setattr(threads, "others_running", lambda: others[0])
    monkeypatch.setattr(threads, "_setting", "auto")
    monkeypatch.setattr(threads, "CHECK_SECONDS", 0.0)
    monkeypatch.setattr(threads, "HOLD_SECONDS", 0.2)
    monkeypatch.setattr(threads, "CONFIRM", 1)
    monkeypatch.setattr(threads, "_local", type(threads._local)())
    try:
        assert threads.adapt() == numba.config.NUMBA_NUM_THREADS
        others[0] = 1
        monkeypatch.setattr(threads, "CONFIRM", 2)
        assert threads.adapt() == numba.config.NUMBA_NUM_THREADS   # (one look: not yet)
        assert threads.adapt() == 1 and numba.get_num_threads() == 1
        others[0] = 0
        assert threads.adapt() == 1          # (held)
        time.sleep(0.25)
        assert threads.adapt() == numba.config.NUMBA_NUM_THREADS
        assert numba.get_num_threads() == numba.config.NUMBA_NUM_THREADS
        monkeypatch.setattr(threads, "_setting", "1")   # SAPGO_THREADS=1: no looking
        others[0] = 0
        assert threads.adapt() == 1 and threads.parts() == 1
    finally:
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)


def test_an_adjustment_on_one_thread_equals_the_one_on_all(p1_block, tmp_path, monkeypatch):
    """The work is split into the same parts whatever number of threads runs them: a run
    that found the machine busy throughout is the idle run bit for bit."""
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one thread")
    monkeypatch.setattr(threads, "_setting", "auto")
    monkeypatch.setattr(threads, "CHECK_SECONDS", 0.0)
    monkeypatch.setattr(threads, "CONFIRM", 1)
    out = {}
    for busy in (0, 1):
        monkeypatch.setattr(threads, "others_running", lambda b=busy: b)
        monkeypatch.setattr(threads, "_local", type(threads._local)())
        path = tmp_path / f"run{busy}.h5"
        shutil.copy(p1_block, path)
        try:
            s = sapgo.adjust(path, sapgo.Options(progress=False))
        finally:
            numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        th = s.threads
        assert th["threads"] == numba.config.NUMBA_NUM_THREADS and th["checks"] > 0
        assert th["busy"] == (th["checks"] if busy else 0)
        assert ("other processes were running" in s.full_report()) == bool(busy)
        with sapgo.open_project(path) as p:
            out[busy] = (s.sigma0, p.file["solution/station_corr"][:],
                         p.file["solution/point_corr"][:], p.file["solution/station_sigma"][:])
    assert out[0][0] == out[1][0]
    for a, b in zip(out[0][1:], out[1][1:]):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("value", ["two", "0", "-1", "1.5"])
def test_a_bad_sapgo_threads_is_refused_in_one_line(monkeypatch, value):
    monkeypatch.setattr(threads, "_setting", value)
    with pytest.raises(sapgo.errors.ParameterError, match="SAPGO_THREADS"):
        threads.parts()
    with pytest.raises(sapgo.errors.ParameterError, match="SAPGO_THREADS"):
        sapgo.Options().check()


def test_blas_limits_sets_the_libraries_threads_and_puts_them_back():
    from threadpoolctl import threadpool_info

    from sapgo import blas
    from sapgo.blas import blas_limits

    with blas_limits(1):   # (the libraries are looked up at the first use, once a process)
        pass
    known = {lib.filepath for lib in blas._CONTROLLER[0]}

    def blas_threads():   # (as threadpoolctl sees them afresh)
        return [i["num_threads"] for i in threadpool_info()
                if i["user_api"] == "blas" and i["filepath"] in known]

    before = blas_threads()
    assert before
    with blas_limits(1):
        assert blas_threads() == [1] * len(before)
        with blas_limits(2):
            assert blas_threads() == [2] * len(before)
        assert blas_threads() == [1] * len(before)
    assert blas_threads() == before
