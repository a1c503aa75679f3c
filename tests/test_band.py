"""The recursive-partitioning block-banded Cholesky against LAPACK and dense solves."""

import h5py
import numpy as np
import pytest
import scipy.linalg

from naive import banded_from_dense
from sapgo.solve.band import (
    BandSolver,
    PivotError,
    band_to_dense,
    dense_to_band,
    factor_to_band,
    solve_in_core,
    solve_out_of_core,
)


def random_block_banded(n, bw, seed=0, q=6):
    """A symmetric positive definite matrix, q x q blocks, band width ``bw`` stations."""
    rng = np.random.default_rng(seed)
    a = np.zeros((q * n, q * n))
    for i in range(n):
        for k in range(1, bw):
            j = i + k
            if j < n:
                blk = rng.normal(0, 1, (q, q))
                a[q * i:q * i + q, q * j:q * j + q] = blk
                a[q * j:q * j + q, q * i:q * i + q] = blk.T
    # scale rows very differently, as angles and positions are (intrinsics more so)
    scale = [1e8, 1e8, 1e8, 1.0, 1.0, 1.0] + [1e-3, 1e12, 1e20][:q - 6]
    d = np.tile(scale, n) * rng.uniform(0.5, 2, q * n)
    a += np.diag(np.abs(a).sum(axis=1) + 1.0)
    s = np.sqrt(d)
    a = a * s[:, None] * s[None, :]
    return (a + a.T) / 2


@pytest.mark.parametrize("n,bw", [(1, 1), (5, 1), (12, 3), (30, 10), (40, 26)])
def test_in_core_matches_lapack_and_dense(n, bw):
    a = random_block_banded(n, bw, seed=n + bw)
    rhs = np.random.default_rng(1).normal(0, 1, 6 * n)
    band = dense_to_band(a, bw)
    np.testing.assert_array_equal(band_to_dense(band), a)
    factor, delta = solve_in_core(band, rhs.reshape(n, 6))
    # the same upper factor as LAPACK's dpbtrf
    cb = scipy.linalg.cholesky_banded(banded_from_dense(a, bw), lower=False)
    u_lapack = np.zeros_like(a)
    ud = 6 * bw - 1
    for j in range(6 * n):
        for i in range(max(0, j - ud), j + 1):
            u_lapack[i, j] = cb[ud + i - j, j]
    u_ours = np.triu(band_to_dense(factor))
    np.testing.assert_allclose(u_ours, u_lapack, rtol=1e-10, atol=1e-10 * np.abs(u_lapack).max())
    x_dense = scipy.linalg.solve(a, rhs, assume_a="pos")
    np.testing.assert_allclose(delta.ravel(), x_dense, rtol=1e-9,
                               atol=1e-12 * np.abs(x_dense).max())


@pytest.mark.parametrize("chunk_rows, threads, storage", [
    (1, None, "h5"), (2, None, "h5"), (7, None, "h5"), (1000, None, "h5"),
    # one kernel thread (file transfers then overlap on a helper thread when a core is
    # free), and more kernel threads than cores
    (3, 1, "raw"), (3, 3, "raw")])
def test_out_of_core_equals_in_core(tmp_path, chunk_rows, threads, storage):
    from sapgo.rawfile import RawArray

    n, bw = 37, 6
    a = random_block_banded(n, bw, seed=3)
    band = dense_to_band(a, bw)
    rhs = np.random.default_rng(2).normal(0, 1, (n, 6))
    factor_ref, delta_ref = solve_in_core(band, rhs)
    with h5py.File(tmp_path / "s.h5", "w") as f:
        if storage == "h5":
            bds = f.create_dataset("band", data=band, chunks=(4, 6, 6 * bw))
            rds = f.create_dataset("rhs", data=rhs)
        else:
            bds = RawArray.create(tmp_path / "band.bin", band.shape)
            rds = RawArray.create(tmp_path / "rhs.bin", rhs.shape)
            bds[:] = band
            rds[:] = rhs
        delta = solve_out_of_core(bds, rds, bw, chunk_rows=chunk_rows, threads=threads)
        np.testing.assert_allclose(factor_to_band(bds[:]), factor_ref, rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(delta, delta_ref, rtol=1e-11, atol=1e-15)
    np.testing.assert_allclose(a @ delta.ravel(), rhs.ravel(), rtol=1e-8,
                               atol=1e-8 * np.abs(rhs).max())


@pytest.mark.parametrize("chunk_rows", [1, 3, 50])
def test_band_solver_fed_in_pieces(chunk_rows):
    """Rows fed in pieces of any size (one row, more than the ring holds) give the same
    factor and solution as the in-core solve; feeding too many rows or finishing early is
    refused."""
    n, bw = 41, 5
    a = random_block_banded(n, bw, seed=7)
    band = dense_to_band(a, bw)
    rhs = np.random.default_rng(4).normal(0, 1, (n, 6))
    factor_ref, delta_ref = solve_in_core(band, rhs)
    fac = np.full_like(band, np.nan)
    y = np.full_like(rhs, np.nan)
    solver = BandSolver(n, bw, fac, y, chunk_rows=chunk_rows)
    rng = np.random.default_rng(chunk_rows)
    i = 0
    while i < n:
        k = min(n - i, int(rng.integers(1, 30)))
        solver.feed(band[i:i + k], rhs[i:i + k])
        i += k
    with pytest.raises(ValueError, match="fed for 41 stations"):
        solver.feed(band[:1], rhs[:1])
    delta = solver.finish()
    np.testing.assert_allclose(factor_to_band(fac), factor_ref, rtol=1e-12, atol=1e-300)
    np.testing.assert_allclose(delta, delta_ref, rtol=1e-11, atol=1e-15)
    early = BandSolver(n, bw, fac, y, chunk_rows=chunk_rows)
    early.feed(band[:10], rhs[:10])
    with pytest.raises(ValueError, match="10 band rows fed for 41"):
        early.finish()


def test_non_positive_pivot_names_the_row():
    n, bw = 10, 3
    a = random_block_banded(n, bw, seed=5)
    a[6 * 6 + 2, 6 * 6 + 2] = -1.0  # row 6, parameter 2 is indefinite
    with pytest.raises(PivotError) as e:
        solve_in_core(dense_to_band(a, bw), np.zeros((n, 6)))
    assert e.value.row == 6 and e.value.parameter == 2
    with pytest.raises(PivotError) as e:
        solve_out_of_core(dense_to_band(a, bw), np.zeros((n, 6)), bw, chunk_rows=2)
    assert e.value.row == 6


def test_singular_matrix_is_caught_by_the_relative_pivot_test():
    # a rank-deficient (positive semi-definite) block-banded matrix: rounding leaves a tiny
    # positive pivot that must still count as zero
    n, bw = 8, 2
    a = random_block_banded(n, bw, seed=9)
    v = np.random.default_rng(0).normal(0, 1, 6 * n)
    v[6 * 5:] = 0
    v[6 * 3:6 * 4] = 0
    a_sing = a - 0.0 * np.outer(v, v)
    w, q = np.linalg.eigh(a[:12, :12])
    a_sing[:12, :12] = (q * np.r_[0.0, w[1:]]) @ q.T  # first two stations: one zero eigenvalue
    with pytest.raises(PivotError) as e:
        solve_in_core(dense_to_band(a_sing, bw), np.zeros((n, 6)))
    assert e.value.row in (0, 1)


# -- the drop-in for scipy.linalg.cholesky_banded ---------------------------------------

def scalar_banded(n, u, seed):
    """A random SPD matrix of scalar band ``u`` and its upper and lower LAPACK storage."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, n))
    i, j = np.indices((n, n))
    a = np.where(np.abs(i - j) <= u, a + a.T, 0.0) + (2 * u + 3) * 4 * np.eye(n)
    up, lo = np.zeros((u + 1, n)), np.zeros((u + 1, n))
    for c in range(n):
        for r in range(max(0, c - u), c + 1):
            up[u + r - c, c] = a[r, c]
        for r in range(c, min(n, c + u + 1)):
            lo[r - c, c] = a[r, c]
    return a, up, lo


@pytest.mark.parametrize("n, u", [(1, 0), (7, 3), (40, 0), (61, 17), (150, 71), (96, 95)])
def test_cholesky_banded_is_a_drop_in_for_scipy(n, u):
    from sapgo.solve.band import cho_solve_banded, cholesky_banded

    a, up, lo = scalar_banded(n, u, seed=n + u)
    rng = np.random.default_rng(1)
    for lower, ab in ((False, up), (True, lo)):
        ref = scipy.linalg.cholesky_banded(ab, lower=lower)
        c = cholesky_banded(ab, lower=lower)
        assert c.shape == ref.shape
        np.testing.assert_allclose(c, ref, rtol=0, atol=1e-12 * np.abs(ref).max())
        for b in (rng.normal(size=n), rng.normal(size=(n, 3))):
            x = cho_solve_banded((c, lower), b)
            assert x.shape == b.shape
            np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-10, atol=1e-12)
    ab = up.copy()
    out = cholesky_banded(ab, overwrite_ab=True)
    assert out is ab and np.allclose(ab, scipy.linalg.cholesky_banded(up))


def test_cholesky_banded_names_the_leading_minor_like_scipy():
    from sapgo.solve.band import cholesky_banded

    _, up, _ = scalar_banded(30, 4, seed=3)
    up[4, 17] = -1.0  # diagonal element 17: the 18th leading minor is not positive definite
    with pytest.raises(np.linalg.LinAlgError) as ref:
        scipy.linalg.cholesky_banded(up)
    with pytest.raises(np.linalg.LinAlgError, match="18-th leading minor") as ours:
        cholesky_banded(up)
    assert str(ref.value).split()[0] == str(ours.value).split()[0]
    with pytest.raises(ValueError):
        cholesky_banded(np.full((2, 3), np.nan))


@pytest.mark.parametrize("small", [True, False])
@pytest.mark.parametrize("step, n, bw", [(1, 23, 5), (5, 23, 5), (1000, 23, 5), (7, 90, 3),
                                         (3, 12, 12), (4, 40, 11)])
def test_covariance_blocks_equal_the_dense_inverse(step, n, bw, small, monkeypatch):
    """Takahashi's selected inversion from the factor rows, streamed backwards in blocks of
    any size (the window shifted many times for the longer block), gives the diagonal blocks
    of the dense inverse, with the rows taken 2 stations at a time (a small band) or 8."""
    import sapgo.solve.band as band
    from sapgo.solve.band import covariance_blocks

    if not small:
        monkeypatch.setattr(band, "SMALL_GEMM", 0)
    assert band.inverse_stations(6, bw) == min(bw, 2 if small else 8)

    a = random_block_banded(n, bw, seed=11)
    band = dense_to_band(a, bw)
    fac = band.copy()
    solve_out_of_core(fac, np.zeros((n, 6)), bw, chunk_rows=4)
    blocks = covariance_blocks(fac, n, bw, step=step)
    inv = np.linalg.inv(a)
    for i in range(n):
        ref = inv[6 * i:6 * i + 6, 6 * i:6 * i + 6]
        np.testing.assert_allclose(blocks[i], ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())
    out = np.zeros((n, 6, 6))
    var = covariance_blocks(fac, n, bw, step=step, out=out)
    np.testing.assert_array_equal(out, blocks)
    np.testing.assert_array_equal(var, np.diagonal(blocks, axis1=1, axis2=2))


@pytest.mark.parametrize("small", [True, False])
def test_covariance_blocks_do_not_depend_on_the_blas_threads(monkeypatch, small):
    """The selected inversion gives the same blocks bit for bit with its BLAS on one
    thread and on two (the kernels' threads follow the machine's load)."""
    import numba

    import sapgo.solve.band as band
    from sapgo import threads as sapgo_threads

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one thread")
    if not small:
        monkeypatch.setattr(band, "SMALL_GEMM", 0)
    n, bw = 60, 12
    a = random_block_banded(n, bw, seed=13)
    fac = dense_to_band(a, bw)
    solve_out_of_core(fac, np.zeros((n, 6)), bw, chunk_rows=5)
    got = []
    for threads in ("1", "2"):
        monkeypatch.setattr(sapgo_threads, "_setting", threads)
        got.append(band.covariance_blocks(fac, n, bw, step=16))
    np.testing.assert_array_equal(got[0], got[1])


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("step", [3, 7, 100])
def test_covariance_window_holds_the_band_of_the_inverse_for_each_block(step, threads,
                                                                      monkeypatch):
    """The window handed to ``on_block`` holds the band of the inverse over the block's
    stations and the band after them, for blocks shorter and longer than the band (the
    window shifted within a block and between blocks; on two threads, ``on_block`` on a
    thread of its own with two windows in turn)."""
    import numba

    from sapgo import threads as sapgo_threads
    from sapgo.solve.band import covariance_blocks

    if threads > numba.config.NUMBA_NUM_THREADS:
        pytest.skip("one thread")
    monkeypatch.setattr(sapgo_threads, "_setting", str(threads))
    numba.set_num_threads(threads)

    n, bw = 40, 4
    a = random_block_banded(n, bw, seed=12)
    fac = dense_to_band(a, bw)
    solve_out_of_core(fac, np.zeros((n, 6)), bw, chunk_rows=3)
    inv = np.linalg.inv(a)
    seen = []

    def check(start, stop, zb, base, alone=False):
        assert alone == (threads == 1 or start == 0)   # (nothing beside it: the last block)
        lo, hi = 6 * start, min(6 * n, 6 * stop + 6 * bw - 1)
        for k in range(lo, hi):
            for j in range(max(lo, k - 6 * bw + 1), min(hi, k + 6 * bw)):
                assert zb[k - base, j - base] == pytest.approx(inv[k, j], rel=1e-9,
                                                              abs=1e-12 * abs(inv).max())
        seen.append((start, stop))

    try:
        blocks = covariance_blocks(fac, n, bw, step=step, on_block=check,
                                   observations=10 ** 9)   # (beside: on two threads)
    finally:
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
    np.testing.assert_allclose(np.diagonal(blocks, axis1=1, axis2=2),
                               np.diagonal(inv).reshape(n, 6), rtol=1e-9)
    assert seen[0][1] == n and seen[-1][0] == 0
    assert all(b - a == min(step, n) for a, b in seen[:-1])


@pytest.mark.parametrize("n, bw, chunk_rows", [(17, 4, 3), (40, 9, 50), (1, 1, 1)])
def test_stations_of_nine_parameters(n, bw, chunk_rows):
    """Stations of 9 parameters (orientation and per-photo intrinsics): the solver, fed in
    pieces, the out-of-core path and the selected inversion equal the dense computation."""
    from sapgo.solve.band import covariance_blocks

    a = random_block_banded(n, bw, seed=5, q=9)
    band = dense_to_band(a, bw, block=9)
    np.testing.assert_array_equal(band_to_dense(band), np.triu(a, 0) + np.triu(a, 1).T)
    rhs = np.random.default_rng(2).normal(0, 1, (n, 9))
    ref = np.linalg.solve(a, rhs.ravel()).reshape(n, 9)
    factor, delta = solve_in_core(band, rhs)
    np.testing.assert_allclose(delta, ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())
    fac = np.zeros_like(band)
    y = np.zeros_like(rhs)
    solver = BandSolver(n, bw, fac, y, chunk_rows=chunk_rows, block=9)
    for i in range(0, n, 5):
        solver.feed(band[i:i + 5], rhs[i:i + 5])
    np.testing.assert_allclose(solver.finish(), delta, rtol=1e-12, atol=1e-300)
    blocks = covariance_blocks(fac, n, bw, step=3)
    inv = np.linalg.inv(a)
    for i in range(n):
        r = inv[9 * i:9 * i + 9, 9 * i:9 * i + 9]
        np.testing.assert_allclose(blocks[i], r, rtol=1e-8, atol=1e-10 * np.abs(r).max())


@pytest.mark.parametrize("n, bw, chunk_rows, seg_bytes, k", [
    (61, 5, 3, 1, 6),        # a segment per factored chunk: 21 segments
    (61, 5, 4, 40_000, 6),   # several chunks a segment
    (20, 7, 2, 1, 6),        # segments shorter than the band
    (33, 4, 2, 1, 9),        # stations of nine parameters
    (9, 3, 50, 1, 6)])       # one segment
def test_replayed_factor_equals_the_stored_factor(tmp_path, monkeypatch, n, bw, chunk_rows,
                                                  seg_bytes, k):
    """Without a factor file (:class:`FactorReplay`) the factor rows read back, in any order,
    equal the stored ones bit for bit, and so do the solution and the cofactor blocks;
    each backward read refactors one segment from its saved state and the rows fed again
    (exactly the rows it needs), the last segment coming from the forward pass."""
    import sapgo.solve.band as band_mod
    from sapgo.solve.band import covariance_blocks

    monkeypatch.setattr(band_mod, "REPLAY_SEGMENT_BYTES", seg_bytes)
    a = random_block_banded(n, bw, seed=n + k, q=k)
    band = dense_to_band(a, bw, block=k)
    rhs = np.random.default_rng(5).normal(0, 1, (n, k))
    fac = np.zeros_like(band)
    y = np.zeros_like(rhs)
    ref = BandSolver(n, bw, fac, y, chunk_rows=chunk_rows, block=k)
    ref.feed(band, rhs)
    delta_ref = ref.finish()
    solver = BandSolver(n, bw, None, None, chunk_rows=chunk_rows, block=k, replay=tmp_path)
    fed = []

    def rebuild(lo, hi, feed):
        fed.append((lo, hi))
        for i in range(lo, hi, 2):
            feed(band[i:min(hi, i + 2)], rhs[i:min(hi, i + 2)])

    solver.replay.rebuild = rebuild
    for i in range(0, n, 5):
        solver.feed(band[i:i + 5], rhs[i:i + 5])
    delta = solver.finish()
    rep = solver.replay
    assert rep.J == -(-n // rep.R) and rep.replays == rep.J - 1
    need = [rep.rows_needed(j) for j in range(rep.J - 2, -1, -1)]
    assert fed == [r for r in need if r[1] > r[0]]
    np.testing.assert_array_equal(delta, delta_ref)
    assert solver.yy == pytest.approx(float((y * y).sum()), rel=1e-13)
    for lo, hi in [(0, n), (n - 3, n), (2, 9), (0, 1)]:
        np.testing.assert_array_equal(rep.factor[lo:hi], fac[lo:hi])
        np.testing.assert_array_equal(rep.y[lo:hi], y[lo:hi])
    np.testing.assert_array_equal(covariance_blocks(rep.factor, n, bw, step=3),
                                  covariance_blocks(fac, n, bw, step=3))
    # a replay fed too few rows is refused, not solved with a hole
    rep.cache.clear()
    rep._last = None
    rep.rebuild = lambda lo, hi, feed: feed(band[lo:hi - 1], rhs[lo:hi - 1])
    if rep.J > 1:
        with pytest.raises(ValueError, match="replay of segment 0: band rows fed to"):
            rep.factor[0:1]
