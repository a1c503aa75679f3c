"""Station graph, band width and the rewriting of records in logical order."""

import numpy as np
import pytest

import sapgo
from conftest import read_records, rewrite
from sapgo.ordering import band_width_of, order_project, station_edges
from sapgo.project import STATUS_ACTIVE, STATUS_EXCLUDED, Project

TABLE2 = {  # photos, strips, points, control points (seeds/002 Table 2)
    "sapgo-p-1": (100, 4, 225, 16),
    "sapgo-p-2": (100, 4, 833, 32),
    "sapgo-p-3": (500, 5, 1100, 48),
    "sapgo-p-4": (504, 12, 1050, 44),
}
TABLE4_BAND_WIDTH = {"sapgo-p-1": 10, "sapgo-p-2": 10, "sapgo-p-3": 12, "sapgo-p-4": 26}


def brute_force_band_width(path):
    """1 + max over points of (max - min logical station), from the records directly."""
    with Project(path) as p:
        ob = p.read("observations")
    act = ob["status"] == STATUS_ACTIVE
    b = 1
    for j in np.unique(ob["point"][act]):
        s = ob["station"][act & (ob["point"] == j)]
        b = max(b, 1 + int(s.max() - s.min()))
    return b


@pytest.mark.parametrize("preset", sorted(TABLE2))
def test_presets_have_table2_counts_and_table4_band_widths(block_cache, tmp_path, preset):
    import shutil

    path = tmp_path / "b.h5"
    shutil.copy(block_cache(preset, preset=preset), path)
    photos, strips, points, control = TABLE2[preset]
    rec = read_records(path)
    assert len(rec["stations"]) == photos
    assert len(np.unique(rec["stations"]["strip"])) == strips
    assert len(rec["points"]) == points
    assert (rec["points"]["kind"] == 1).sum() == control
    assert (rec["points"]["kind"] == 4).sum() == points - control
    result = order_project(path)
    assert result.band_width <= TABLE4_BAND_WIDTH[preset]
    assert result.band_width < result.band_width_before
    assert brute_force_band_width(path) == result.band_width
    with Project(path) as p:
        assert p.ordered and p.band_width == result.band_width


def test_records_are_rewritten_in_logical_order(p1_block):
    before = read_records(p1_block)
    order_project(p1_block)
    after = read_records(p1_block)
    st, pt, ob = after["stations"], after["points"], after["observations"]
    # same content, new order
    assert sorted(st["id"]) == sorted(before["stations"]["id"])
    def key(r, s, p):
        return {(int(p["id"][o["point"]]), int(s["id"][o["station"]]), float(o["x"]),
                 float(o["y"])) for o in r}
    assert key(ob, st, pt) == key(before["observations"], before["stations"],
                                  before["points"])
    # points sorted by (min, max) logical station; observations grouped by point, by station
    keys = list(zip(pt["station_min"], pt["station_max"]))
    assert keys == sorted(keys)
    assert (np.diff(ob["point"]) >= 0).all()
    for j in range(len(pt)):
        s = ob["station"][pt["obs_start"][j]:pt["obs_start"][j] + pt["n_obs"][j]]
        assert (np.diff(s) >= 0).all()
        assert s.min() == pt["station_min"][j] and s.max() == pt["station_max"][j]
    # truth follows its records
    np.testing.assert_array_equal(after["truth"]["stations"]["id"], st["id"])
    np.testing.assert_array_equal(after["truth"]["points"]["id"], pt["id"])


def test_ordered_records_are_chunked_no_larger_than_they_are(p1_block):
    """The ordered project's record datasets are chunked to their records (at most a
    megabyte a chunk): a small block's file is not a megabyte a dataset, read, checksummed
    and copied whole at every pass."""
    import h5py

    from sapgo.project import RECORD_DTYPES, TRUTH_DTYPES

    size_before = p1_block.stat().st_size
    order_project(p1_block)
    with h5py.File(p1_block, "r") as f:
        for name in (*RECORD_DTYPES, *TRUTH_DTYPES):
            if name not in f:
                continue
            ds = f[name]
            assert ds.chunks[0] <= max(1, len(ds)), name
            assert ds.chunks[0] * ds.dtype.itemsize <= 1 << 20, name
            assert ds.id.get_storage_size() <= max(1, len(ds)) * ds.dtype.itemsize + 64, name
    assert p1_block.stat().st_size < size_before / 2


def test_band_width_from_edges_matches_definition():
    # three points: on stations {0, 1, 2}, {2, 5}, {4, 5}
    starts = np.array([0, 3, 5])
    counts = np.array([3, 2, 2])
    stations = np.array([0, 1, 2, 2, 5, 4, 5])
    edges = station_edges(starts, counts, stations, np.ones(7, bool), 6)
    assert band_width_of(np.arange(6), edges) == 4
    pos = np.array([0, 1, 2, 5, 4, 3])  # stations 3 and 5 swapped
    assert band_width_of(pos, edges) == 3


def test_undeterminable_points_and_photos_are_left_out(small_block):
    rec = read_records(small_block)
    ob, pt = rec["observations"], rec["points"]
    # a check point seen on one photo only
    single = int(np.flatnonzero((pt["kind"] == 4) & (np.bincount(ob["point"]) >= 2))[0])
    drop = np.flatnonzero(ob["point"] == single)[1:]
    # a photo keeping only two of its points
    photo = 2
    drop = np.union1d(drop, np.flatnonzero(ob["station"] == photo)[2:])
    rec["observations"] = np.delete(ob, drop)
    rewrite(small_block, rec)
    result = order_project(small_block)
    assert int(pt["id"][single]) in result.excluded_points
    assert int(rec["stations"]["id"][photo]) in result.excluded_stations
    after = read_records(small_block)
    assert len(after["points"]) == len(pt)  # nothing deleted
    ex = after["points"][after["points"]["id"] == pt["id"][single]][0]
    assert ex["status"] == STATUS_EXCLUDED
    exs = after["stations"][after["stations"]["id"] == rec["stations"]["id"][photo]][0]
    assert exs["status"] == STATUS_EXCLUDED
    assert after["stations"]["status"][-1] == STATUS_EXCLUDED  # excluded stations go last
    summary = sapgo.adjust(small_block, sapgo.Options(progress=False))
    assert summary.converged
    assert int(pt["id"][single]) in summary.excluded_points
    assert int(rec["stations"]["id"][photo]) in summary.excluded_stations


def test_duplicate_measurements_on_one_photo_are_one_ray(small_block):
    rec = read_records(small_block)
    ob, pt = rec["observations"], rec["points"]
    j = int(np.flatnonzero(pt["kind"] == 4)[0])
    mine = np.flatnonzero(ob["point"] == j)
    dup = ob[mine[:1]].copy()
    dup["x"] += 0.001
    rec["observations"] = np.concatenate([np.delete(ob, mine[1:]), dup])
    rec["observations"] = rec["observations"][np.argsort(rec["observations"]["point"],
                                                         kind="stable")]
    rewrite(small_block, rec)
    result = order_project(small_block)
    assert int(pt["id"][j]) in result.excluded_points
    assert sapgo.adjust(small_block, sapgo.Options(progress=False)).converged


def test_rejected_observations_stay_rejected(small_block):
    from sapgo.project import STATUS_REJECTED

    rec = read_records(small_block)
    rec["observations"]["x"][10] += 0.5  # a 500 um blunder, rejected by the user
    rec["observations"]["status"][10] = STATUS_REJECTED
    key = (int(rec["observations"]["point"][10]), int(rec["observations"]["station"][10]))
    pid = int(rec["points"]["id"][key[0]])
    sid = int(rec["stations"]["id"][key[1]])
    rewrite(small_block, rec)
    s = sapgo.adjust(small_block, sapgo.Options(progress=False))
    assert s.sigma0 < 1.5
    after = read_records(small_block)
    ob = after["observations"]
    hit = ((after["points"]["id"][ob["point"]] == pid)
           & (after["stations"]["id"][ob["station"]] == sid))
    assert ob["status"][hit][0] == STATUS_REJECTED
    assert s.n_observations == len(ob) - 1


def test_columns_of_shifted_strips_and_of_strips_of_another_scale():
    """Columns counted along each strip: a strip shifted by half a base sits between its
    neighbours' columns; a strip of another photo scale at the quarter-base columns of its
    positions; jitter of a few per cent of a base changes nothing."""
    from sapgo.ordering import _columns

    rng = np.random.default_rng(3)
    j = np.arange(6, dtype=float)
    u = np.concatenate([j, j + 0.5, 1.25 * j + 0.1]) * 100.0 + rng.normal(0, 1.5, 18)
    labels = np.repeat([0, 1, 2], 6)
    col = _columns(u, labels, 100.0)
    np.testing.assert_array_equal(col[:6], j)
    np.testing.assert_array_equal(col[6:12], j + 0.5)
    np.testing.assert_array_equal(col[12:], np.rint(4 * (1.25 * j + 0.1)) / 4)


def test_a_block_without_strip_numbers_is_ordered_as_with_them(block_cache, tmp_path):
    """Strip numbers removed (an import without them): the flight direction and the base
    come from the photos' nearest neighbours, the strips from the gaps across track, so the
    columns, the strips and the band width are those of the block with its strips."""
    import shutil

    import h5py

    from sapgo.ordering import grid_coordinates
    from sapgo.project import Project

    src = block_cache("8x30", strips=8, photos_per_strip=30, control_points=20)
    with_strips, without = tmp_path / "a.h5", tmp_path / "b.h5"
    shutil.copy(src, with_strips)
    shutil.copy(src, without)
    with h5py.File(without, "r+") as f:
        st = f["stations"][:]
        strip = st["strip"].copy()
        st["strip"] = -1
        f["stations"][:] = st
    xy = st["eo"][:, 3:5]
    _, _, col_a, lab_a, _ = grid_coordinates(xy, strip)
    _, _, col_b, lab_b, _ = grid_coordinates(xy, st["strip"])
    np.testing.assert_array_equal(lab_b, strip - 1)  # (strips 1..8 across the block)
    np.testing.assert_array_equal(col_b, col_a)
    widths = []
    for path in (with_strips, without):
        order_project(path)
        with Project(path) as p:
            widths.append(p.band_width)
    assert widths[0] == widths[1] == 18


def _rcm_reference(n, s, t):
    """Reverse Cuthill-McKee as written in words: each component from its unvisited node
    of least degree (ties: lowest number), breadth first, each node's new neighbours by
    increasing degree (ties: in adjacency order), the whole order reversed."""
    adj = [[] for _ in range(n)]
    for a, b in zip(s, t):
        adj[a].append(b)
        adj[b].append(a)
    deg = [len(x) for x in adj]
    seen, order = [False] * n, []
    for seed in sorted(range(n), key=lambda v: deg[v]):
        if seen[seed]:
            continue
        seen[seed] = True
        order.append(seed)
        head = len(order) - 1
        while head < len(order):
            new = [j for j in adj[order[head]] if not seen[j]]
            new = list(dict.fromkeys(new))
            for j in new:
                seen[j] = True
            order.extend(sorted(new, key=lambda v: deg[v]))
            head += 1
    return order[::-1], adj


@pytest.mark.parametrize("steps", [1, 3, 1 << 18])
def test_reverse_cuthill_mckee_matches_the_algorithm_in_words(monkeypatch, steps):
    import scipy.sparse as sp
    from scipy.sparse.csgraph import reverse_cuthill_mckee as scipy_rcm
    from sapgo import ordering

    monkeypatch.setattr(ordering, "CM_STEPS", steps)   # (resumed after every few nodes)
    rng = np.random.default_rng(7)
    agree = 0
    for _ in range(60):
        n = int(rng.integers(1, 40))
        m = int(rng.integers(0, 3 * n))
        s, t = rng.integers(0, n, m), rng.integers(0, n, m)
        keep = s < t
        s, t = s[keep], t[keep]
        # adjacency as order's _adjacency builds it: edges in order, each row unsorted
        key = np.unique(s * n + t)
        s, t = key // n, key % n
        indptr = np.zeros(n + 1, np.int32)
        indices = np.empty(2 * len(s), np.int32)
        ordering._adjacency(n, s.astype(np.int32), t.astype(np.int32), indptr, indices)
        want, adj = _rcm_reference(n, s, t)
        got = ordering.reverse_cuthill_mckee(indptr, indices)
        assert list(got) == want
        for i in range(n):   # (the CSR is the graph)
            assert sorted(indices[indptr[i]:indptr[i + 1]]) == sorted(adj[i])
        # SciPy's result differs only where its unstable seed sort breaks a tie otherwise
        g = sp.csr_matrix((np.ones(len(indices)), indices, indptr), shape=(n, n))
        theirs = scipy_rcm(g, symmetric_mode=True)
        agree += np.array_equal(theirs, got)
        if not np.array_equal(theirs, got):
            deg = np.diff(indptr)
            assert len(set(deg[list(want)])) < n   # (there was a tie to break)
    assert agree >= 10   # (19 of the 60 here)


@pytest.mark.parametrize("case", ["plain", "left out", "rejections reset", "tree"])
def test_ordered_copy_in_memory_has_the_records_of_the_streamed_one(small_block, tmp_path,
                                                                    case):
    """``sapgo adjust``'s ordered copy of a small project, built in memory from whole arrays
    (``in_memory``), holds the records, truth and tree the streamed passes write to a file:
    the same sort keys, the same order, bit for bit."""
    from sapgo.project import STATUS_REJECTED

    rec = read_records(small_block)
    ob, pt = rec["observations"], rec["points"]
    if case == "left out":   # a point on one photo, a photo with two points
        single = int(np.flatnonzero((pt["kind"] == 4) & (np.bincount(ob["point"]) >= 2))[0])
        drop = np.union1d(np.flatnonzero(ob["point"] == single)[1:],
                          np.flatnonzero(ob["station"] == 2)[2:])
        rec["observations"] = np.delete(ob, drop)
    if case == "rejections reset":
        rec["observations"]["status"][[10, 40]] = STATUS_REJECTED
    rewrite(small_block, rec)
    kw = dict(reset_rejections=case == "rejections reset",
              solver="tree" if case == "tree" else "auto")
    streamed = order_project(small_block, out=tmp_path / "streamed.h5", **kw)
    held = order_project(small_block, out=tmp_path / "held.h5", in_memory=True, **kw)
    try:
        assert held.to_dict() | {"seconds": 0} == streamed.to_dict() | {"seconds": 0}
        with Project(tmp_path / "streamed.h5") as s:
            names = [n for n in ("stations", "points", "observations", "cameras",
                                 "station_priors", "truth/stations", "truth/points")
                     if n in s.file]
            assert "truth/points" in names
            for n in names:
                np.testing.assert_array_equal(held.file[n][()], s.file[n][()], err_msg=n)
                np.testing.assert_array_equal(held.records[n], s.file[n][()], err_msg=n)
            assert ("tree" in held.file) == ("tree" in s.file) == (case == "tree")
            for k in s.file["tree"] if case == "tree" else ():
                np.testing.assert_array_equal(held.file["tree"][k][()], s.file["tree"][k][()])
            for k in ("ordering", "band_width", "solver", "ordered", "rejections_reset"):
                assert held.file.attrs[k] == s.file.attrs[k], k
    finally:
        held.file.close()
    assert not (tmp_path / "held.h5").exists()
