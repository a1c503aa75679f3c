"""The strip-to-strip comparison (seeds/002 Table 8) against a plain numpy re-derivation."""

import json
import shutil
from itertools import combinations

import numpy as np

import naive
import sapgo
from conftest import read_records, rewrite, run_cli
from sapgo.project import Project


def ray_intersection(centres, directions):
    """The point nearest to the lines ``centres[i] + t directions[i]`` (numpy)."""
    a = np.zeros((3, 3))
    r = np.zeros(3)
    for c, d in zip(centres, directions):
        d = d / np.linalg.norm(d)
        p = np.eye(3) - np.outer(d, d)
        a += p
        r += p @ c
    return np.linalg.solve(a, r)


def reference(path):
    """Per pair of strips: n and the RMS of the coordinate differences, from the project's
    adjusted orientation, intersecting each strip's rays on their own."""
    rec = read_records(path)
    with Project(path) as p:
        eo = rec["stations"]["eo"] + p.solution("station_corr")
    f = rec["cameras"]["focal_length"][0]
    strip = rec["stations"]["strip"]
    ob = rec["observations"]
    acc = {}
    for j in range(len(rec["points"])):
        sel = np.flatnonzero(ob["point"] == j)
        derived = {}
        for s in np.unique(strip[ob["station"][sel]]):
            rays = sel[strip[ob["station"][sel]] == s]
            if len(np.unique(ob["station"][rays])) < 2:
                continue
            centres = eo[ob["station"][rays], 3:]
            dirs = [naive.rotation(*eo[st, :3]).T @ np.array([x, y, -f])
                    for st, x, y in zip(ob["station"][rays], ob["x"][rays], ob["y"][rays])]
            derived[int(s)] = ray_intersection(centres, dirs)
        for a, b in combinations(sorted(derived), 2):
            n, sq = acc.get((a, b), (0, np.zeros(3)))
            acc[(a, b)] = (n + 1, sq + (derived[a] - derived[b]) ** 2)
    return {k: (n, np.sqrt(sq / n)) for k, (n, sq) in acc.items()}


def test_strip_comparison_equals_a_numpy_rederivation(block_cache, tmp_path, capsys):
    path = tmp_path / "b.h5"
    shutil.copy(block_cache("strips3", strips=3, photos_per_strip=6, control_points=8), path)
    code, out, _ = run_cli(capsys, "adjust", path, "--json", tmp_path / "r.json",
                           "--no-progress")
    assert code == 0
    assert "strip comparison" in out and "weighted average" in out
    sc = json.loads((tmp_path / "r.json").read_text())["strip_comparison"]
    ref = reference(path)
    assert {tuple(p["strips"]) for p in sc["pairs"]} == set(ref) == {(1, 2), (2, 3)}
    for p in sc["pairs"]:
        n, sigma = ref[tuple(p["strips"])]
        assert p["n"] == n
        np.testing.assert_allclose(p["sigma_m"], sigma, rtol=1e-7)
    ns = np.array([p["n"] for p in sc["pairs"]])
    sig = np.array([p["sigma_m"] for p in sc["pairs"]])
    assert sc["weighted_average"]["n"] == ns.sum()
    np.testing.assert_allclose(sc["weighted_average"]["sigma_m"], ns @ sig / ns.sum(),
                               rtol=1e-12)
    assert 0.01 < max(sc["weighted_average"]["sigma_m"]) < 1.0  # 6 um noise at 1:25 000


def test_one_strip_has_no_comparison(block_cache, tmp_path):
    path = tmp_path / "b.h5"
    shutil.copy(block_cache("strip1", strips=1, photos_per_strip=8, control_points=6), path)
    summary = sapgo.adjust(path, sapgo.Options(progress=False))
    assert summary.strip_comparison is None
    assert "strip comparison" not in summary.full_report()


def test_photos_without_a_strip_take_no_part(block_cache, tmp_path):
    path = tmp_path / "b.h5"
    shutil.copy(block_cache("strips3", strips=3, photos_per_strip=6, control_points=8), path)
    rec = read_records(path)
    rec["stations"]["strip"][rec["stations"]["strip"] == 3] = -1
    rewrite(path, rec)
    summary = sapgo.adjust(path, sapgo.Options(progress=False))
    assert [p["strips"] for p in summary.strip_comparison["pairs"]] == [[1, 2]]
