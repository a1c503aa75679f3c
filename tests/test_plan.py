"""sapgo plan: the reduced matrix's pattern, fill-in and storage from the network alone."""

from pathlib import Path

import numpy as np
import pytest

from sapgo.symbolic import factor_pattern, symbolic_counts


DATA_BAL = Path(__file__).parent / "data" / "problem-49-7776-pre.txt.gz"


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
            "row_counts": nz.sum(axis=1), "column_counts": nz.sum(axis=0), "pattern": nz}


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
        np.testing.assert_array_equal(got["column_counts"], ref["column_counts"])
        rows, cols, fill = factor_pattern(n, (s, t), perm)
        np.testing.assert_array_equal(np.bincount(rows, minlength=n), ref["row_counts"])
        assert len(rows) == ref["factor_blocks"] and fill.sum() == ref["fill_in_blocks"]
        assert (ref["pattern"][rows, cols]).all()
        inv = np.empty(n, np.int64)
        inv[perm] = np.arange(n)
        assert got["band_width"] == 1 + (np.abs(inv[s] - inv[t]).max() if len(s) else 0)


@pytest.mark.parametrize("design", [dict(strips=6, photos_per_strip=40),
                                    dict(strips=5, photos_per_strip=30, shift=0.5,
                                         lengths=[30, 20, 30, 10, 25]),
                                    dict(strips=4, photos_per_strip=20, forelap=0.8,
                                         sidelap=0.6, units="models", cross=True)])
def test_column_counts_equal_the_row_subtree_walk_on_planning_networks(design):
    """The counts in O(nnz alpha) (elimination tree, postorder, skeleton leaves) against
    the walk over every block of L (the row subtrees), for every ordering, and for a graph
    of two components."""
    from sapgo.plan import design_network, orderings
    from sapgo.symbolic import _csr, _symbolic

    net = design_network(**design)
    graphs = [(net.n, net.s, net.t)]
    graphs.append((2 * net.n, np.concatenate([net.s, net.s + net.n]),
                   np.concatenate([net.t, net.t + net.n])))
    for n, s, t in graphs:
        for name, (perm, _) in orderings(net).items():
            perm = perm if n == net.n else np.concatenate([perm, perm + net.n])
            inv = np.empty(n, np.int64)
            inv[perm] = np.arange(n)
            c = symbolic_counts(n, (s, t), perm)
            rows = _symbolic(n, *_csr(n, s, t), perm, inv)[0]
            assert c["factor_blocks"] == rows.sum(), name


def test_a_band_has_no_fill_outside_the_band_and_a_cycle_fills_its_last_column():
    n = 10
    s, t = np.arange(n - 1), np.arange(1, n)  # a path: tridiagonal, no fill-in
    c = symbolic_counts(n, (s, t), np.arange(n))
    assert c["fill_in_blocks"] == 0 and c["band_width"] == 2 and c["nonzero_blocks"] == 2 * n - 1
    # closing the path into a cycle: eliminating 0, 1, ..., n-3 joins each one's successor
    # to n-1, n-3 fill-in blocks in the last row
    c = symbolic_counts(n, (np.append(s, 0), np.append(t, n - 1)), np.arange(n))
    assert c["fill_in_blocks"] == n - 3 and c["band_width"] == n


# Rostom (seeds/000) Table 2: the numerical example (6 x 20 km, 1:10 000, 23 cm photos),
# independent models. (p, q, cross, ordering, s, g): T, m, F.I., W, D as the paper prints
# them, except where the paper is wrong (see ERRATA): the counts come from the graph.
TABLE2 = [
    (0.6, 0.2, False, "across_strip", 4, 24, 92, 381, 132, 6, 8),
    (0.6, 0.2, False, "down_strip", 12, 8, 84, 365, 330, 9, 14),
    (0.6, 0.6, False, "across_strip", 6, 24, 138, 873, 264, 9, 12),
    (0.6, 0.6, False, "down_strip", 22, 8, 154, 1065, 1230, 16, 21),
    (0.6, 0.6, True, "across_strip", 6, 24, 258, 3294, 1884, 24, 27),
    (0.6, 0.6, True, "down_strip", 22, 8, 322, 4318, 4290, 32, 37),
    (0.8, 0.2, False, "across_strip", 4, 44, 168, 1104, 486, 10, 12),
    (0.8, 0.2, False, "down_strip", 12, 13, 132, 899, 792, 14, 22),
    # ->S1: the paper's W is 45 (8s - 3); this ordering gives its F.I. exactly and W = 47
    (0.8, 0.6, True, "across_strip", 6, 44, 472, 10312, 8097, 47, 55),
    (0.8, 0.6, True, "down_strip", 22, 13, 515, 11586, 10296, 51, 59),
    # the paper prints m = 2534; its own formula 13sg - 41s - 15g + 48 gives 2574
    (0.8, 0.6, False, "across_strip", 6, 44, 252, 2574, 972, 15, 18),
    (0.8, 0.6, False, "down_strip", 22, 13, 242, 2669, 2952, 25, 33),
    (0.8, 0.8, False, "across_strip", 11, 44, 462, 8289, 3402, 27, 33),
    (0.8, 0.8, False, "down_strip", 44, 13, 484, 9454, 11952, 47, 55),
]


@pytest.mark.parametrize("case", TABLE2, ids=lambda c: f"{c[0]:.0%}-{c[1]:.0%}"
                         f"{'+C' if c[2] else ''}-{c[3]}")
def test_rostom_table_2_is_reproduced_from_the_graph(case):
    from sapgo.plan import design_network, evaluate

    p, q, cross, order, s, g, t, m, fi, w, d = case
    r = evaluate(design_network(s, g, p, q, units="models", cross=cross))["orderings"][order]
    assert (r["dimension"], r["nonzero_blocks"], r["fill_in_blocks"], r["band_width_m"],
            r["band_width_b"]) == (t, m, fi, w, d)
    # the storage of Table 2: envelope m + F.I. (the fill fills it), TW and TD
    assert r["storage_blocks"]["envelope"] == m + fi == r["storage_blocks"]["sparse"]
    assert r["storage_blocks"]["band"] == t * w and r["storage_blocks"]["partitioned_band"] == t * d


@pytest.mark.parametrize("s, g", [(3, 5), (5, 9), (7, 12)])
def test_rostom_table_1_formulas_hold_for_homogeneous_networks(s, g):
    """Table 1's closed formulas (60 % forelap, 20 % sidelap; 80 / 20) against the graph."""
    from sapgo.plan import design_network, evaluate

    e = evaluate(design_network(s, g, 0.6, 0.2, units="models"))["orderings"]
    assert e["across_strip"]["nonzero_blocks"] == 5 * s * g - 8 * s - 3 * g + 5
    assert e["across_strip"]["fill_in_blocks"] == (g - 2) * (s - 1) * (s - 2)
    assert e["down_strip"]["fill_in_blocks"] == (s - 1) * (g - 2) * (g - 3)
    assert e["across_strip"]["band_width_m"] == s + 2 and e["down_strip"]["band_width_m"] == g + 1
    assert e["across_strip"]["band_width_b"] == 2 * s
    assert e["down_strip"]["band_width_b"] == 2 * (g - 1)
    e = evaluate(design_network(s, g, 0.8, 0.2, units="models"))["orderings"]
    assert e["across_strip"]["dimension"] == s * (g - 2)
    assert e["across_strip"]["nonzero_blocks"] == 8 * s * g - 25 * s - 5 * g + 16
    assert e["down_strip"]["fill_in_blocks"] == (s - 1) * (g - 4) * (g - 5)
    assert e["across_strip"]["fill_in_blocks"] == (2 * g - 7) * (s - 1) * (s - 2)


def test_the_plan_of_a_generated_project_is_the_band_width_adjust_uses(block_cache):
    """sapgo-p-3: the recommended ordering's band width (photos) is the one ordering finds."""
    import sapgo
    from sapgo.plan import evaluate, project_network
    from sapgo.project import Project
    import shutil
    import tempfile
    from pathlib import Path

    src = block_cache("p3", preset="sapgo-p-3")
    e = evaluate(project_network(src))
    rec = e["orderings"][e["recommended"]]
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "p3.h5"
        shutil.copy(src, path)
        sapgo.order_project(path)
        with Project(path) as p:
            assert p.band_width == rec["band_width_m"] == 12
    assert e["recommended"] == "across_strip" and e["units"] == "photos"
    assert rec["dimension"] == 500 and rec["unknowns"] == 3000


def test_plan_from_the_command_line(tmp_path, capsys):
    import json

    from conftest import run_cli

    code, out, err = run_cli(capsys, "plan", "--strips", "3", "--photos-per-strip", "5",
                             "--units", "models", "--json", tmp_path / "p.json", "--plot",
                             tmp_path / "m.png", "--no-timing")
    assert code == 0, err
    rep = json.loads((tmp_path / "p.json").read_text())
    assert set(rep["orderings"]) == {"down_strip", "across_strip", "diagonal", "rcm", "spiral"}
    s = rep["orderings"]["across_strip"]
    assert (s["dimension"], s["nonzero_blocks"], s["fill_in_blocks"], s["band_width_b"],
            s["band_width_m"]) == (12, 41, 6, 6, 5)  # Rostom's Figure 12 network
    assert rep["recommended"] == "across_strip" and (tmp_path / "m.png").stat().st_size > 0
    assert "across_strip" in out
    code, out, err = run_cli(capsys, "plan", "--strips", "2", "--photos-per-strip", "4",
                             "--json", tmp_path / "t.json")
    assert code == 0, err
    r = json.loads((tmp_path / "t.json").read_text())["orderings"]["down_strip"]
    assert r["predicted_solve_s"] > 0 and r["rate_flops"] > 1e6


@pytest.mark.parametrize("args, words", [
    (["--strips", "3"], "--photos-per-strip"),
    (["--strips", "3", "--photos-per-strip", "5", "--cross"], "cross models"),
    (["--strips", "3", "--photos-per-strip", "5", "--forelap", "30"], "forelap"),
    (["--strips", "3", "--photos-per-strip", "5", "--sidelap", "x"], "--sidelap 'x'"),
])
def test_bad_plan_options(capsys, args, words):
    from conftest import assert_one_line_error, run_cli

    code, out, err = run_cli(capsys, "plan", *args)
    assert_one_line_error(code, err, words)


def test_irregular_designs():
    """Shifted strips (Rostom section 7.1: a model joined to two, not three, models of the
    next strip), strips of different lengths, starts and scales."""
    from sapgo.plan import design_network, evaluate

    s, g = 4, 10
    n = g - 1
    for shift, per_pair in ((0.0, 3 * n - 2), (0.5, 2 * n - 1)):
        net = design_network(s, g, 0.6, 0.2, "models", shift=shift)
        r = evaluate(net)["orderings"]["across_strip"]
        assert r["nonzero_blocks"] == s * n + s * (n - 1) + (s - 1) * per_pair
    net = design_network(3, 10, 0.6, 0.2, "photos", lengths=[10, 8, 12], starts=[0, 2, -1],
                         scales=[1, 1, 1.3])
    assert net.n == 30 and net.params == 6
    e = evaluate(net)
    assert e["recommended"] == "across_strip"
    assert e["orderings"]["across_strip"]["band_width_m"] < \
        e["orderings"]["down_strip"]["band_width_m"]


# Table 1's formulas (T, m; F.I., W, D for ->S and ->G) for every case, where they are valid
# (W needs s >= 3 at 60 % sidelap and s >= 5 at 80 %; 80/80 also s >= 4 for m and F.I.).
TABLE1 = {
    (0.6, 0.6, False): lambda s, g: dict(
        T=s * (g - 1), m=8 * s * g - 13 * s - 9 * g + 15,
        S=((g - 2) * (s - 2) * (s - 3), s + 3, 2 * s),
        G=((2 * s - 3) * (g - 2) * (g - 3), 2 * g, 3 * (g - 1))),
    (0.6, 0.6, True): lambda s, g: dict(
        T=2 * s * g - (s + g), m=32 * s * g - 46 * s - 46 * g + 66,
        S=((7 * g - 11) * (s - 2) * (s - 3), 4 * s, 5 * s - 3),
        G=((7 * s - 11) * (g - 2) * (g - 3), 4 * g, 5 * g - 3)),
    (0.8, 0.6, False): lambda s, g: dict(
        T=s * (g - 2), m=13 * s * g - 41 * s - 15 * g + 48,
        S=((2 * g - 7) * (s - 2) * (s - 3), 2 * s + 3, 3 * s),
        G=((2 * s - 3) * (g - 4) * (g - 5), 2 * g - 1, 3 * (g - 2))),
    (0.8, 0.8, False): lambda s, g: dict(
        T=s * (g - 2), m=23 * s * g - 73 * s - 50 * g + 160,
        S=((2 * g - 7) * (s - 4) * (s - 5), 2 * s + 5, 3 * s),
        G=((4 * s - 10) * (g - 4) * (g - 5), 4 * g - 5, 5 * (g - 2))),
    (0.8, 0.6, True): lambda s, g: dict(  # ->S1: F.I. and D as printed, W = 8s - 1 (see above)
        T=2 * s * (g - 1) - g, m=55 * s * g - 151 * s - 80 * g + 218,
        S=((10 * g - 22) * (s - 2) * (s - 3) + (g - 5) * (4 * s * s - 13 * s + 13), 8 * s - 1,
           5 * (2 * s - 1)),
        G=((7 * s - 11) * (g - 4) * (g - 5), 4 * g - 1, 5 * g - 6)),
}


@pytest.mark.parametrize("case", sorted(TABLE1), ids=lambda c: f"{c[0]:.0%}-{c[1]:.0%}"
                         f"{'+C' if c[2] else ''}")
@pytest.mark.parametrize("s, g", [(5, 9), (6, 12), (7, 10)])
def test_rostom_table_1_formulas_for_every_case(case, s, g):
    from sapgo.plan import design_network, evaluate

    p, q, cross = case
    want = TABLE1[case](s, g)
    e = evaluate(design_network(s, g, p, q, units="models", cross=cross))["orderings"]
    for name, key in (("across_strip", "S"), ("down_strip", "G")):
        r = e[name]
        assert (r["dimension"], r["nonzero_blocks"]) == (want["T"], want["m"])
        assert (r["fill_in_blocks"], r["band_width_m"], r["band_width_b"]) == want[key], name


def test_a_flight_design_plans_what_the_generated_block_of_that_design_has(block_cache):
    """The bundle design (photos, 60 % / 20 %) against a generated 5 x 40 block of the same
    design: the same non-zero blocks, band widths and fill-in for every ordering."""
    from sapgo.plan import design_network, evaluate, project_network

    src = block_cache("5x40", strips=5, photos_per_strip=40)
    got = evaluate(project_network(src))["orderings"]
    want = evaluate(design_network(5, 40, 0.6, 0.2, "photos"))["orderings"]
    for name in want:
        for key in ("dimension", "nonzero_blocks", "band_width_m", "fill_in_blocks"):
            assert got[name][key] == want[name][key], (name, key)


def _flight_project(path, tilt=0.0, relief=0.0, points_per_photo=100, **design):
    from sapgo.generate.flight import flight_scene
    from sapgo.generate.scene import write_scene
    from sapgo.project import ProjectWriter

    scene = flight_scene(**design, tilt=tilt, relief=relief, points_per_photo=points_per_photo)
    with ProjectWriter(path, {}, truth=True) as w:
        write_scene(scene, w)
        w.finish()
    return path


def _pairs(net):
    return {(min(a, b), max(a, b)) for a, b in zip(net.s.tolist(), net.t.tolist())}


ALL = ("down_strip", "across_strip", "diagonal", "rcm", "spiral")


@pytest.mark.parametrize("design, ppp, same", [
    (dict(strips=4, photos_per_strip=10, shift=0.5), 100, ALL),
    (dict(strips=4, photos_per_strip=10, lengths=[10, 7, 9, 5], starts=[0, 2, 1, 4]), 100, ALL),
    # other scales: the photos of a strip of another scale lie between the block's columns,
    # at the quarter-base column of their position in a project, at their exact position in
    # the design: the same across-strip order, other lines (D) and diagonals
    (dict(strips=4, photos_per_strip=10, scales=[1.0, 0.8, 1.2, 1.0], sidelap=0.3), 1000,
     ("down_strip", "rcm", "spiral", ("across_strip", "band_width_m", "fill_in_blocks"))),
    (dict(strips=3, photos_per_strip=9, forelap=0.8, sidelap=0.6), 100, ALL),
])
def test_an_irregular_flight_design_plans_the_topology_of_its_generated_block(tmp_path, design,
                                                                              ppp, same):
    """Shifted strips, strips of other lengths and starts, strips of other scales: the
    design's network (footprints that overlap with a positive area) is exactly the network
    of the block generated from that design (vertical photos over flat ground, points in
    every common area: the narrowest overlap of the scales' case, 4 % of a photo, needs a
    denser grid), and so are the counts of the orderings (T, m, W, D, fill-in, storage)."""
    from sapgo.plan import design_network, evaluate, project_network

    path = _flight_project(tmp_path / "f.h5", points_per_photo=ppp, **design)
    want, got = design_network(**design), project_network(path)
    assert got.n == want.n
    assert _pairs(got) == _pairs(want)
    e_want, e_got = evaluate(want)["orderings"], evaluate(got)["orderings"]
    for name in same:
        if isinstance(name, tuple):
            name, *keys = name
            assert [e_got[name][k] for k in keys] == [e_want[name][k] for k in keys], name
        else:
            assert e_got[name] == e_want[name], name
    assert all(e_got[k]["nonzero_blocks"] == e_want[k]["nonzero_blocks"] for k in e_want)


def test_the_plan_of_irregular_projects_predicts_the_order_and_band_width_of_sapgo_order(
        tmp_path, block_cache):
    """A shifted block of strips of other lengths (tilted photos over hills), SAPGO-MFL-2 (two
    areas flown across each other and a diagonal strip) and a BAL problem (9 parameters a
    photo): the plan names the order sapgo order then applies, with its band width."""
    import shutil

    import sapgo
    from sapgo.formats.bal import import_bal
    from sapgo.plan import evaluate, project_network
    from sapgo.project import Project

    irregular = _flight_project(tmp_path / "irr.h5", tilt=0.5, relief=30.0, strips=5,
                                photos_per_strip=14, shift=0.5,
                                lengths=[14, 10, 14, 8, 12], starts=[0, 3, 0, 5, 1])
    mfl = tmp_path / "mfl2.h5"
    shutil.copy(block_cache("mfl2", preset="sapgo-mfl-2"), mfl)
    bal = tmp_path / "bal.h5"
    import_bal(DATA_BAL, bal)
    for path, params in ((irregular, 6), (mfl, 6), (bal, 9)):
        e = evaluate(project_network(path))
        assert e["parameters_per_unit"] == params
        plan = e["adjust"]
        r = sapgo.order_project(path)
        with Project(path) as p:
            assert (r.ordering, p.band_width) == (plan["ordering"], plan["band_width_m"]), path
        # sapgo order's candidates include the plan's five orderings
        assert min(o["band_width_m"] for o in e["orderings"].values()) >= plan["band_width_m"]


def test_solve_time_is_timed_at_the_block_size_or_extrapolated_from_a_smaller_run():
    from sapgo.plan import solve_time

    small = solve_time(40, 5, seconds=0.2)
    assert small["timed_units"] == 40 and not small["extrapolated"]
    assert small["predicted_s"] > 0
    # a large block: timed at 32 b units or more (fixed costs no longer count), within the
    # memory given, and scaled by the flops
    big = solve_time(200_000, 12, seconds=0.2, memory=40e6)
    assert big["extrapolated"] and 32 * 12 <= big["timed_units"] <= 40e6 / (8 * 36 * 12)
    assert big["predicted_s"] > small["predicted_s"]
    seven = solve_time(30, 4, params=7, seconds=0.1)  # independent models: 7 x 7 blocks
    assert seven["timed_units"] == 30 and seven["predicted_s"] > 0


def test_irregular_designs_from_the_command_line(tmp_path, capsys):
    """sapgo generate of an irregular design, sapgo plan of it (the order sapgo order will
    choose, drawn with --plot-ordering adjust), sapgo order --method diagonal / spiral."""
    import json

    from conftest import assert_one_line_error, run_cli

    from sapgo.project import Project

    path = tmp_path / "irr.h5"
    code, out, err = run_cli(capsys, "generate", path, "--strips", "3", "--photos-per-strip",
                             "8", "--shift", "0.5", "--strip-lengths", "8,6,8",
                             "--strip-starts", "0,1,0", "--control-points", "8")
    assert code == 0, err
    assert "22 photos in 3 strips" in out
    code, out, err = run_cli(capsys, "plan", path, "--no-timing", "--json", tmp_path / "p.json",
                             "--plot", tmp_path / "m.png", "--plot-ordering", "adjust")
    assert code == 0, err
    rep = json.loads((tmp_path / "p.json").read_text())
    assert "sapgo order will choose " + rep["adjust"]["ordering"] in out
    assert rep["project"] == str(path) and (tmp_path / "m.png").stat().st_size > 0
    for method in ("diagonal", "spiral"):
        code, out, err = run_cli(capsys, "order", path, "--method", method)
        assert code == 0, err
        with Project(path) as p:
            assert p.attr("ordering") == method
    for args, words in (
            (["--shift", "0.5", "--pattern", "25"], ("irregular flight design", "pattern")),
            (["--strip-lengths", "8,x"], ("--strip-lengths",)),
            (["--strip-lengths", "8,6.5"], ("whole numbers",)),
            (["--strips", "2", "--scales", "1,1,1"], ("scales", "3 values for 2 strips")),
            (["--preset", "sapgo-p-1", "--shift", "0.5"], ("preset",)),
            (["--shift", "nan"], ("--shift", "finite")),
            (["--strips", "2", "--scales", "nan,1"], ("--scales", "finite")),
            (["--strip-lengths", "inf,5"], ("--strip-lengths", "finite"))):
        code, out, err = run_cli(capsys, "generate", tmp_path / "bad.h5", *args)
        assert_one_line_error(code, err, *words)
        assert not (tmp_path / "bad.h5").exists()
    for args, words in (
            ([path, "--shift", "0.5"], ("either a project or a flight design",)),
            (["--strips", "2", "--photos-per-strip", "4", "--plot-ordering", "adjust"],
             ("give a project",)),
            (["--strips", "2", "--photos-per-strip", "4", "--strip-lengths", "nan,5"],
             ("--strip-lengths", "finite"))):
        code, out, err = run_cli(capsys, "plan", *args, "--no-timing")
        assert_one_line_error(code, err, *words)
    # the strips of a design given strip by strip
    code, out, err = run_cli(capsys, "generate", tmp_path / "l.h5", "--strip-lengths", "6,5",
                             "--control-points", "8")
    assert code == 0 and "11 photos in 2 strips" in out, err


def test_the_two_column_orders_nearest_rostoms_s2():
    """80/60 (+C), Table 2's block: ->S2 is defined only in the paper's missing Figure 10-4
    (F.I. 8928, W 46). In each column of the grid, the cross models first and then the strip
    models: F.I. 8994, W 46; the strip models first: F.I. 6420, W 46 (docs/theory.md 3a)."""
    from sapgo.plan import design_network

    net = design_network(6, 44, 0.8, 0.6, units="models", cross=True)
    # strip models lie at y = k by + 1/2, cross models between two strips
    cross = np.abs((net.y - 0.5) / 0.4 - np.round((net.y - 0.5) / 0.4)) > 1e-6
    assert cross.sum() == 5 * 44 and net.n == 472
    got = {}
    for name, d in (("cross first", -0.1), ("strip first", 0.1)):
        key = np.round((net.x + np.where(cross, d, 0.0)) / 0.1).astype(np.int64)
        c = symbolic_counts(net.n, (net.s, net.t), np.lexsort((net.y, key)))
        got[name] = (c["fill_in_blocks"], c["band_width"])
    assert got == {"cross first": (8994, 46), "strip first": (6420, 46)}


def test_a_factor_too_large_to_draw_is_refused_in_one_line(tmp_path, capsys, monkeypatch):
    import sapgo.plan
    from conftest import assert_one_line_error, run_cli

    monkeypatch.setattr(sapgo.plan, "MAX_DRAWN_BLOCKS", 50)
    code, out, err = run_cli(capsys, "plan", "--strips", "3", "--photos-per-strip", "20",
                             "--no-timing", "--plot", tmp_path / "m.png", "--plot-ordering",
                             "down_strip")
    assert_one_line_error(code, err, "too many to draw", "down_strip")
    assert not (tmp_path / "m.png").exists()
