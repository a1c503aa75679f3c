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

from .ordering import _unique


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


@njit(cache=True)
def _column_counts(n, indptr, indices, inv):
    """Column counts of ``L`` (diagonal included) in O(nnz alpha), without visiting ``L``:
    the elimination tree with path compression, its postorder, and Gilbert, Ng & Peyton's
    skeleton-leaf counting with least common ancestors (as CSparse's ``cs_counts``). The
    graph is given in original numbers, the order by ``inv`` (node -> logical number).
    Returns ``(counts, parent, post)``: the counts, the elimination tree and its postorder,
    all in logical numbers."""
    # the adjacency in logical numbers
    nbr = np.empty(indices.shape[0], np.int64)
    ptr = np.zeros(n + 1, np.int64)
    for v in range(n):
        ptr[inv[v] + 1] = indptr[v + 1] - indptr[v]
    for k in range(n):
        ptr[k + 1] += ptr[k]
    for v in range(n):
        k = inv[v]
        for q in range(indptr[v], indptr[v + 1]):
            nbr[ptr[k] + q - indptr[v]] = inv[indices[q]]
    # elimination tree
    parent = np.full(n, -1, np.int64)
    anc = np.full(n, -1, np.int64)
    for k in range(n):
        for q in range(ptr[k], ptr[k + 1]):
            i = nbr[q]
            while i != -1 and i < k:
                nxt = anc[i]
                anc[i] = k
                if nxt == -1:
                    parent[i] = k
                i = nxt
    # postorder (children by a linked list, depth-first with a stack)
    head = np.full(n, -1, np.int64)
    nxt_child = np.full(n, -1, np.int64)
    for j in range(n - 1, -1, -1):
        if parent[j] != -1:
            nxt_child[j] = head[parent[j]]
            head[parent[j]] = j
    post = np.empty(n, np.int64)
    stack = np.empty(n, np.int64)
    k = 0
    for root in range(n):
        if parent[root] != -1:
            continue
        top = 0
        stack[0] = root
        while top >= 0:
            p = stack[top]
            c = head[p]
            if c == -1:
                top -= 1
                post[k] = p
                k += 1
            else:
                head[p] = nxt_child[c]
                top += 1
                stack[top] = c
    # counts
    delta = np.zeros(n, np.int64)
    first = np.full(n, -1, np.int64)
    maxfirst = np.full(n, -1, np.int64)
    prevleaf = np.full(n, -1, np.int64)
    ancestor = np.arange(n)
    for k in range(n):
        j = post[k]
        delta[j] = 1 if first[j] == -1 else 0  # j is a leaf of the tree
        while j != -1 and first[j] == -1:
            first[j] = k
            j = parent[j]
    for k in range(n):
        j = post[k]
        if parent[j] != -1:
            delta[parent[j]] -= 1
        for q in range(ptr[j], ptr[j + 1]):
            i = nbr[q]
            # is j a leaf of the row subtree of i?
            if i <= j or first[j] <= maxfirst[i]:
                continue
            maxfirst[i] = first[j]
            jprev = prevleaf[i]
            prevleaf[i] = j
            delta[j] += 1
            if jprev != -1:  # a later leaf: the least common ancestor loses one
                lca = jprev
                while lca != ancestor[lca]:
                    lca = ancestor[lca]
                s_ = jprev
                while s_ != lca:
                    up = ancestor[s_]
                    ancestor[s_] = lca
                    s_ = up
                delta[lca] -= 1
        if parent[j] != -1:
            ancestor[j] = parent[j]
    for j in range(n):
        if parent[j] != -1:
            delta[parent[j]] += delta[j]
    return delta, parent, post


def symbolic_counts(n, edges, perm):
    """Counts of the block Cholesky factor of a graph of ``n`` units for the order ``perm``.

    ``edges = (s, t)``: the pairs of units that share a point (each pair once, any order).
    Returns a dict: ``nonzero_blocks`` (the lower triangle of ``M`` with its diagonal),
    ``factor_blocks`` (of ``L``), ``fill_in_blocks`` (their difference), ``band_width``
    (units, the diagonal included), ``envelope_blocks`` (the profile of ``L``: it is that of
    ``M``), ``band_blocks`` (``n b``), the per-column counts ``column_counts`` and the
    first block of every row ``first_column`` (arrays, in logical numbers).
    """
    s, t = (np.asarray(x, np.int64) for x in edges)
    perm = np.asarray(perm, np.int64)
    if len(perm) != n or (np.sort(perm) != np.arange(n)).any():
        raise ValueError(f"perm is not a permutation of {n} units")
    keep = s != t
    s, t = s[keep], t[keep]
    key = _unique(np.minimum(s, t) * max(n, 1) + np.maximum(s, t))
    s, t = key // max(n, 1), key % max(n, 1)
    inv = np.empty(n, np.int64)
    inv[perm] = np.arange(n)
    indptr, indices = _csr(n, s, t)
    # (L's columns counted without visiting L: a million photos in seconds, whatever the
    # fill; the envelope is M's: every row's first non-zero block)
    count = _column_counts(n, indptr, indices, inv)[0]
    a, b = inv[s], inv[t]
    first = np.arange(n)
    np.minimum.at(first, np.maximum(a, b), np.minimum(a, b))
    span = np.abs(a - b)
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
        "column_counts": count,
        "first_column": first,
    }


def factor_pattern(n, edges, perm):
    """The pattern of the block Cholesky factor for the order ``perm``: ``(rows, cols,
    fill)``, the lower-triangle positions (logical numbers, diagonal included) and whether
    each is fill-in (zero in ``M``)."""
    s, t = (np.asarray(x, np.int64) for x in edges)
    perm = np.asarray(perm, np.int64)
    inv = np.empty(n, np.int64)
    inv[perm] = np.arange(n)
    keep = s != t
    s, t = s[keep], t[keep]
    key = _unique(np.minimum(s, t) * max(n, 1) + np.maximum(s, t))
    s, t = key // max(n, 1), key % max(n, 1)
    indptr, indices = _csr(n, s, t)
    row_counts = _symbolic(n, indptr, indices, perm, inv)[0]
    starts = np.concatenate([[0], np.cumsum(row_counts)[:-1]]).astype(np.int64)
    cols = np.empty(int(row_counts.sum()), np.int64)
    _symbolic(n, indptr, indices, perm, inv, cols, starts)
    rows = np.repeat(np.arange(n), row_counts)
    a, b = inv[s], inv[t]
    orig = _unique(np.maximum(a, b) * max(n, 1) + np.minimum(a, b))
    fill = ~np.isin(rows * max(n, 1) + cols, orig) & (rows != cols)
    return rows, cols, fill
