"""Symbolic factorisation of the reduced normal matrix's block pattern (for ``sapgo plan``).

The reduced normal matrix ``M`` has a non-zero block ``(s, t)`` wherever units ``s`` and ``t``
share a point (Rostom, seeds/000; DESIGN section 4). For a logical order, the block Cholesky
factor ``L`` has the pattern of ``M`` plus the *fill-in*: blocks that are zero in ``M`` but
become non-zero during the elimination. It follows from the graph alone (George & Liu 1981):
``L[i, k]`` (``k < i``) is non-zero exactly when ``k`` lies on the elimination-tree path from
a neighbour ``j < i`` of ``i`` up to ``i`` (the *row subtree* of ``i``). The counts here come
from that symbolic factorisation of the actual graph, never from closed formulas.

Counts are of blocks of the lower triangle including the diagonal (``L``'s pattern), and of
the three storage schemes of seeds/000:

- band: ``n b`` blocks (every row holds ``b`` blocks, the diagonal included);
- envelope (profile, skyline): per row, from its first non-zero block to the diagonal;
- sparse: the non-zero blocks of ``L`` (the pattern of ``M`` plus the fill-in).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _csr(n, s, t):
    """Symmetric adjacency (CSR) of the undirected edges ``(s, t)``, without self-loops."""
    deg = np.zeros(n + 1, np.int64)
    for e in range(s.shape[0]):
        if s[e] != t[e]:
            deg[s[e] + 1] += 1
            deg[t[e] + 1] += 1
    for i in range(n):
        deg[i + 1] += deg[i]
    indptr = deg.copy()
    fill = deg[:n].copy()
    indices = np.empty(indptr[n], np.int64)
    for e in range(s.shape[0]):
        a, b = s[e], t[e]
        if a != b:
            indices[fill[a]] = b
            fill[a] += 1
            indices[fill[b]] = a
            fill[b] += 1
    return indptr, indices


@njit(cache=True)
def _symbolic(n, indptr, indices, perm, inv, cols=np.zeros(0, np.int64),
              starts=np.zeros(0, np.int64)):
    """Row counts of ``L`` (diagonal included) and the first column of every row, for the
    order ``perm`` (``perm[k]`` = node eliminated k-th, ``inv`` its inverse): Liu's
    row-subtree traversal over the elimination tree, built on the fly with path
    compression (``ancestor``). With ``cols`` and ``starts`` (from a first pass's counts)
    the columns of every row of ``L`` are recorded too."""
    parent = np.full(n, -1, np.int64)
    ancestor = np.full(n, -1, np.int64)
    mark = np.full(n, -1, np.int64)
    count = np.ones(n, np.int64)
    first = np.arange(n)
    record = cols.shape[0] > 0
    for i in range(n):
        node = perm[i]
        mark[i] = i
        if record:  # the diagonal first, then the row subtree
            cols[starts[i]] = i
        for p in range(indptr[node], indptr[node + 1]):
            j = inv[indices[p]]
            if j >= i:
                continue
            if j < first[i]:
                first[i] = j
            # the elimination tree: walk up from j towards i, compressing the path
            r = j
            while ancestor[r] != -1 and ancestor[r] != i:
                nxt = ancestor[r]
                ancestor[r] = i
                r = nxt
            if ancestor[r] == -1:
                ancestor[r] = i
                parent[r] = i
            # the row subtree: every node on the tree path from j up to i is in row i
            k = j
            while mark[k] != i:
                mark[k] = i
                if record:
                    cols[starts[i] + count[i]] = k
                count[i] += 1
                if first[i] > k:
                    first[i] = k
                k = parent[k]
                if k == -1:
                    break
    return count, first, parent


def symbolic_counts(n, edges, perm):
    """Counts of the block Cholesky factor of a graph of ``n`` units for the order ``perm``.

    ``edges = (s, t)``: the pairs of units that share a point (each pair once, any order).
    Returns a dict: ``nonzero_blocks`` (the lower triangle of ``M`` with its diagonal),
    ``factor_blocks`` (of ``L``), ``fill_in_blocks`` (their difference), ``band_width``
    (units, the diagonal included), ``envelope_blocks`` (the profile of ``L``: it is that of
    ``M``), ``band_blocks`` (``n b``) and the per-row counts ``row_counts`` and
    ``first_column`` (arrays).
    """
    s, t = (np.asarray(x, np.int64) for x in edges)
    perm = np.asarray(perm, np.int64)
    if len(perm) != n or (np.sort(perm) != np.arange(n)).any():
        raise ValueError(f"perm is not a permutation of {n} units")
    keep = s != t
    s, t = s[keep], t[keep]
    key = np.unique(np.minimum(s, t) * max(n, 1) + np.maximum(s, t))
    s, t = key // max(n, 1), key % max(n, 1)
    inv = np.empty(n, np.int64)
    inv[perm] = np.arange(n)
    indptr, indices = _csr(n, s, t)
    count, first, _ = _symbolic(n, indptr, indices, perm, inv)
    span = np.abs(inv[s] - inv[t])
    band = int(1 + (span.max() if len(span) else 0))
    nnz_m = n + len(s)
    nnz_l = int(count.sum())
    rows = np.arange(n)
    return {
        "units": n,
        "nonzero_blocks": int(nnz_m),
        "factor_blocks": nnz_l,
        "fill_in_blocks": nnz_l - int(nnz_m),
        "band_width": band,
        "band_blocks": int(n * band),
        "envelope_blocks": int((rows - first + 1).sum()),
        "row_counts": count,
        "first_column": first,
    }


def factor_pattern(n, edges, perm):
    """The pattern of the block Cholesky factor for the order ``perm``: ``(rows, cols,
    fill)``, the lower-triangle positions (logical numbers, diagonal included) and whether
    each is fill-in (zero in ``M``)."""
    c = symbolic_counts(n, edges, perm)
    s, t = (np.asarray(x, np.int64) for x in edges)
    perm = np.asarray(perm, np.int64)
    inv = np.empty(n, np.int64)
    inv[perm] = np.arange(n)
    keep = s != t
    s, t = s[keep], t[keep]
    key = np.unique(np.minimum(s, t) * max(n, 1) + np.maximum(s, t))
    s, t = key // max(n, 1), key % max(n, 1)
    indptr, indices = _csr(n, s, t)
    starts = np.concatenate([[0], np.cumsum(c["row_counts"])[:-1]]).astype(np.int64)
    cols = np.empty(int(c["row_counts"].sum()), np.int64)
    _symbolic(n, indptr, indices, perm, inv, cols, starts)
    rows = np.repeat(np.arange(n), c["row_counts"])
    a, b = inv[s], inv[t]
    orig = np.unique(np.maximum(a, b) * max(n, 1) + np.minimum(a, b))
    fill = ~np.isin(rows * max(n, 1) + cols, orig) & (rows != cols)
    return rows, cols, fill
