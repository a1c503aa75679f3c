"""sapgo plan: the reduced matrix's pattern, fill-in and storage from the network alone."""

import numpy as np
import pytest

from sapgo.symbolic import symbolic_counts


def dense_reference(n, s, t, perm, seed=0):
    """Block counts by a numeric Cholesky of a random SPD matrix with the graph's pattern
    (scalar 1 x 1 blocks; random values make an accidental zero in L improbable)."""
    rng = np.random.default_rng(seed)
    a = np.zeros((n, n))
    w = rng.uniform(0.5, 1.5, len(s))
    a[s, t] = w
    a[t, s] = w
    a += np.eye(n) * (np.abs(a).sum(axis=1).max() + 1.0)
    p = a[np.ix_(perm, perm)]
    low = np.linalg.cholesky(p)
    nz = np.abs(low) > 1e-13
    pattern = np.tril(np.abs(p) > 0)
    first = np.argmax(nz, axis=1)
    return {"factor_blocks": int(nz.sum()), "nonzero_blocks": int(pattern.sum()),
            "fill_in_blocks": int(nz.sum() - pattern.sum()),
            "envelope_blocks": int((np.arange(n) - first + 1).sum()),
            "row_counts": nz.sum(axis=1)}


@pytest.mark.parametrize("seed", range(6))
def test_symbolic_factorisation_equals_a_numeric_cholesky(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(5, 60))
    m = int(rng.integers(n, 4 * n))
    s, t = rng.integers(0, n, m), rng.integers(0, n, m)
    keep = s != t
    s, t = s[keep], t[keep]
    key = np.unique(np.minimum(s, t) * n + np.maximum(s, t))
    s, t = key // n, key % n
    for perm in (np.arange(n), rng.permutation(n)):
        got = symbolic_counts(n, (t, s), perm)  # (either order of a pair)
        ref = dense_reference(n, s, t, perm, seed)
        for k in ("factor_blocks", "nonzero_blocks", "fill_in_blocks", "envelope_blocks"):
            assert got[k] == ref[k], k
        np.testing.assert_array_equal(got["row_counts"], ref["row_counts"])
        inv = np.empty(n, np.int64)
        inv[perm] = np.arange(n)
        assert got["band_width"] == 1 + (np.abs(inv[s] - inv[t]).max() if len(s) else 0)


def test_a_band_has_no_fill_outside_the_band_and_a_cycle_fills_its_last_column():
    n = 10
    s, t = np.arange(n - 1), np.arange(1, n)  # a path: tridiagonal, no fill-in
    c = symbolic_counts(n, (s, t), np.arange(n))
    assert c["fill_in_blocks"] == 0 and c["band_width"] == 2 and c["nonzero_blocks"] == 2 * n - 1
    # closing the path into a cycle: eliminating 0, 1, ..., n-3 joins each one's successor
    # to n-1, n-3 fill-in blocks in the last row
    c = symbolic_counts(n, (np.append(s, 0), np.append(t, n - 1)), np.arange(n))
    assert c["fill_in_blocks"] == n - 3 and c["band_width"] == n
