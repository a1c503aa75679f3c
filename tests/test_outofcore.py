"""The out-of-core building blocks against obvious in-core references.

External sort against np.lexsort; direct-access files against numpy arrays; the streaming
exclusion rules against the in-core fixed point; ordering with a budget far smaller than the
data against ordering in memory; the streamed generator across column blocks.
"""

import shutil

import numpy as np
import pytest

import sapgo
from conftest import read_records, rewrite
from sapgo.extsort import ExternalSorter, parse_memory, rechunk
from sapgo.generate import sapgo_p
from sapgo.ordering import _station_activity, find_exclusions
from sapgo.project import Project
from sapgo.rawfile import RawArray
from sapgo.validate import check_values


@pytest.mark.parametrize("n, memory, keys", [
    (0, 4 << 20, ["a"]),
    (1000, 4 << 20, ["a", "b"]),
    (400_000, 4 << 20, ["a", "b"]),  # 100 runs: merged in several passes
    (200_000, 64 << 20, ["a", "c"]),  # one run in memory, no file
])
def test_external_sort_equals_lexsort(tmp_path, n, memory, keys):
    dt = np.dtype([("a", "<i8"), ("b", "<f8"), ("c", "<i4"), ("pay", "<f8", (3,))])
    rng = np.random.default_rng(n)
    r = np.zeros(n, dt)
    r["a"] = rng.integers(0, max(1, n // 10), n)  # many ties on the first key
    r["b"] = rng.normal(size=n)
    r["c"] = rng.permutation(n)
    r["pay"] = rng.normal(size=(n, 3))
    with ExternalSorter(dt, keys, memory, tmp_path / "w") as s:
        for a in range(0, n, 33_333):
            s.add(r[a:a + 33_333])
        chunks = list(s.sorted_chunks())
        spilled = len(s._runs) > 0
    out = np.concatenate(chunks) if chunks else np.zeros(0, dt)
    ref = r[np.lexsort(tuple(r[k] for k in reversed(keys)))]
    np.testing.assert_array_equal(out[keys], ref[keys])
    # the payload travels with its key (keys are unique here on (a, b) and (a, c))
    np.testing.assert_array_equal(out, ref)
    assert spilled == (n * dt.itemsize * 4 > memory)
    assert not any((tmp_path / "w").glob("*.bin"))


def test_rechunk_and_memory_sizes():
    parts = [np.arange(0, 7), np.arange(7, 8), np.arange(8, 30)]
    out = list(rechunk(iter(parts), 10))
    assert [len(c) for c in out] == [10, 10, 10]
    np.testing.assert_array_equal(np.concatenate(out), np.arange(30))
    assert parse_memory("512M") == 512 << 20
    assert parse_memory("2G") == 2 << 30
    assert parse_memory("64MiB") == 64 << 20
    with pytest.raises(sapgo.SapgoError, match="such as 512M"):
        parse_memory("lots")
    with pytest.raises(sapgo.SapgoError, match="minimum"):
        parse_memory("1K")


def test_raw_array_reads_what_was_written(tmp_path):
    a = RawArray.create(tmp_path / "a.bin", (100, 6, 12))
    ref = np.zeros((100, 6, 12))
    np.testing.assert_array_equal(a[:], ref)  # a new file reads as zeros
    rng = np.random.default_rng(0)
    for start, stop in [(0, 10), (95, 100), (40, 41), (10, 95)]:
        block = rng.normal(size=(stop - start, 6, 12))
        a[start:stop] = block
        ref[start:stop] = block
    np.testing.assert_array_equal(a[:], ref)
    np.testing.assert_array_equal(a[37], ref[37])
    a.close()
    b = RawArray(tmp_path / "a.bin", (100, 6, 12), mode="r")
    np.testing.assert_array_equal(b[20:60], ref[20:60])
    with pytest.raises(IndexError):
        b[::2]
    b.close()
    with pytest.raises(ValueError, match="expected"):
        RawArray(tmp_path / "a.bin", (101, 6, 12))


def test_streaming_exclusions_equal_the_in_core_fixed_point(block_cache, tmp_path):
    path = tmp_path / "b.h5"
    shutil.copy(block_cache("small", strips=2, photos_per_strip=6, control_points=6), path)
    rec = read_records(path)
    ob, pt = rec["observations"], rec["points"]
    # remove rays so that points fall below 2 rays and a photo below 3 points, in cascade
    rng = np.random.default_rng(3)
    drop = rng.random(len(ob)) < 0.35
    drop |= ob["station"] == 4
    keep = ~drop
    keep[np.flatnonzero(ob["station"] == 4)[:2]] = True
    rec["observations"] = ob[keep]
    ob = rec["observations"]
    ob["status"][rng.random(len(ob)) < 0.05] = 2  # some rejected rays
    rewrite(path, rec)
    pa_ref, sa_ref, _ = find_exclusions(pt["kind"], ob["point"], ob["station"],
                                        len(rec["stations"]), ob["status"])
    assert (~pa_ref).any() and (~sa_ref).any()
    with Project(path) as p:
        for chunk in (1, 7, 1000):
            np.testing.assert_array_equal(_station_activity(p, chunk)[0], sa_ref)
    r = sapgo.order_project(path)
    assert sorted(r.excluded_points) == sorted(pt["id"][~pa_ref].tolist())
    assert r.n_excluded_stations == int((~sa_ref).sum())


def test_ordering_with_a_tiny_budget_equals_ordering_in_memory(block_cache, tmp_path):
    src = block_cache("p3", preset="sapgo-p-3")
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    shutil.copy(src, a)
    shutil.copy(src, b)
    # 4 MiB budget and 100-point chunks: every sort spills many runs
    ra = sapgo.order_project(a, memory="4M", chunk=100)
    rb = sapgo.order_project(b)
    assert ra.band_width == rb.band_width == 12
    x, y = read_records(a), read_records(b)
    for k in ("stations", "points", "observations", "station_priors", "cameras"):
        np.testing.assert_array_equal(x[k], y[k], err_msg=k)
    for k in ("stations", "points"):
        np.testing.assert_array_equal(x["truth"][k], y["truth"][k])
    with Project(a) as p:
        check_values(p)


def test_generator_streams_column_blocks_consistently(tmp_path, monkeypatch):
    # three column blocks of 100 columns: rays, intersections and control across the seams
    monkeypatch.setattr(sapgo_p, "COLUMN_BLOCK", 100)
    path = tmp_path / "g.h5"
    info = sapgo.generate_block(path, strips=3, photos_per_strip=250, control_points=40,
                                progress=False)
    assert info["points"] == 7 * 250 and info["control_points"] == 40
    with Project(path) as p:
        check_values(p, ordered_layout=False)
        pts, ob = p.read("points"), p.read("observations")
        truth = p.read("truth/points")
    # every point id appears once, numbered column by column; rays per point from geometry
    np.testing.assert_array_equal(pts["id"], np.arange(1, len(pts) + 1))
    rows, cols = 7, 250
    r, c = np.arange(len(pts)) % rows, np.arange(len(pts)) // rows
    strips_seeing = np.where((r % 2 == 0) & (r > 0) & (r < rows - 1), 2, 1)
    photos_seeing = np.where((c == 0) | (c == cols - 1), 2, 3)
    np.testing.assert_array_equal(pts["n_obs"], strips_seeing * photos_seeing)
    # the approximate coordinates are intersections near the truth, also at the seams
    err = np.abs(pts["xyz"] - truth["xyz"]).max(axis=1)
    assert err.max() < 50.0
    assert np.all(np.diff(ob["point"]) >= 0)
