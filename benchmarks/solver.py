"""The band solver against what a user would otherwise pick, on the same reduced matrices.

Run:  python benchmarks/solver.py [--quick] [--photos 6000]
      (writes results/solver.json, results/solver_bandwidth.png, results/solver_gflops.png
       and prints the tables pasted into benchmarks/README.md)

The matrices are real reduced normal equations: blocks of a fixed number of photos are
generated with 3 to 49 strips (band width 8 to 100 stations after ordering across the strips),
and their band rows are built by sapgo's own ``build`` pass. On each matrix, in one run:

- **sapgo in core**: ``sapgo.solve.band.cholesky_banded`` on LAPACK's lower band storage (the
  drop-in; includes its copies in and out), checked against LAPACK's factor to 1e-8 relative;
- **sapgo out of core**: ``solve_out_of_core`` on the band rows in direct-access files (factor,
  forward and back substitution, ``chunk_rows=256``), against the same driver in core (band
  rows in arrays): the cost of the files;
- **LAPACK dpbtrf**: ``scipy.linalg.cholesky_banded``, best of OpenBLAS with 1 and 2 threads;
- **sparse Cholesky**: CHOLMOD (scikit-sparse) if it is installed, else SciPy's SuperLU with
  natural ordering and no pivoting (the band order is already the good one), best of both
  permutations tried;
- **dense ceiling**: the time the operation count would take at the machine's measured
  dense matrix-multiply rate (DGEMM 2000 x 2000, 2 threads).
- **selected inversion**: ``covariance_blocks`` (the precision pass's band kernel, Takahashi's
  recurrence: the band of the inverse, twice the factorisation's flops) from the in-core
  factor, on every thread and on one (``SAPGO_THREADS=1``: as an adjustment runs it beside
  the points' kernel), against the factorisation + solve in core; the two agree to the
  relative difference recorded.
- **the drop-in call** ``sapgo.solve.band.cholesky_banded(ab, lower=True)`` against
  ``scipy.linalg.cholesky_banded(ab, lower=True)`` on the same C-ordered array: both are
  LAPACK ``dpbtrf`` (the drop-in's own work is SciPy's finiteness check, done once), so the
  ratio is the median of ``CALL_ROUNDS`` ratios of calls paired back to back (alternating
  which goes first), with its spread: what this VM's noise makes of one routine.

Operation count ``n (6b)^2`` (n scalar unknowns, b band width in stations), as the issue
defines it; GFLOP/s = count / seconds. Every time is the median of ``ROUNDS`` interleaved
rounds (the tools taking turns within each round), its spread (min-max) recorded beside it;
the machine's load average before each matrix is recorded. Then solve time against photo
count at fixed band width (20 strips) with the fitted exponent, and the fitted exponent
against band width.
"""

import argparse
import json
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np
import scipy
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg
from threadpoolctl import threadpool_limits

import sapgo
from sapgo.adjust import Options, _load_block, build
from sapgo.work import Work
from sapgo.solve.band import (  # the private pieces time the kernel without its copies
    _factor_range,
    _skewed,
    band_to_dense,
    cholesky_banded,
    covariance_blocks,
    panel_width,
    solve_out_of_core,
)
from sapgo.blas import FNS, blas_limits
from sapgo.ordering import order_project
from sapgo.project import Project
from sapgo.rawfile import RawArray

HERE = Path(__file__).parent
REPEAT = 3
#: Interleaved rounds of the kernel-against-kernel timing.
ROUNDS = 7
#: Paired rounds of the drop-in call against SciPy's (the same LAPACK routine).
CALL_ROUNDS = 15
STRIPS = [3, 5, 7, 12, 16, 24, 32, 40, 49]


def med(times):
    return float(np.median(times))


def spread(times):
    return [float(min(times)), float(max(times))]


def load():
    try:
        return [float(x) for x in Path("/proc/loadavg").read_text().split()[:3]]
    except OSError:
        return None


def best(fn, repeat=REPEAT):
    """Median time of ``repeat`` runs of ``fn`` (and its last result)."""
    times, out = [], None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return med(times), out


def reduced_matrix(tmp, strips, photos):
    """Band rows and right-hand side of a generated block's reduced normals (first iteration)."""
    path = Path(tmp) / f"s{strips}.h5"
    g = max(4, photos // strips)
    sapgo.generate_block(path, strips=strips, photos_per_strip=g,
                         control_points=max(6, strips * g // 25), progress=False)
    order_project(path, solver="band")   # (the band solver is what this benchmark times)
    with Project(path) as p:
        blk = _load_block(p)
        w = Work(Path(tmp) / f"s{strips}.work", p, blk.band_width, create=True)
        try:
            w.initialise(p, 100000)
            build(p, w, blk, Options(progress=False))
            band, rhs = w.factor[:], w.y[:]
        finally:
            w.close()
    shutil.rmtree(Path(tmp) / f"s{strips}.work")
    path.unlink()
    return band, rhs, blk.band_width


def lower_storage(band):
    """LAPACK lower band storage ``ab[i - j, j] = a[i, j]`` of band rows."""
    n_st, _, width = band.shape
    n, u = 6 * n_st, width - 1
    ab = np.zeros((u + 1, n))
    for r in range(6):
        for d in range(width - r):
            ab[d, r::6] = band[:, r, r + d]
    # entries past the end of the matrix are not referenced; keep them zero
    for d in range(u + 1):
        ab[d, n - d:] = 0.0
    return ab


def gemm_rate():
    a = np.random.default_rng(0).random((2000, 2000))
    b = a.T.copy()
    times = []
    for _ in range(5):   # the ceiling: the fastest
        t0 = time.perf_counter()
        a @ b
        times.append(time.perf_counter() - t0)
    t = min(times)
    return 2 * 2000 ** 3 / t / 1e9


def sparse_solver():
    try:
        from sksparse.cholmod import cholesky  # noqa: F401
        return "CHOLMOD (scikit-sparse)"
    except ImportError:
        return "SuperLU (scipy)"


def sparse_time(band, rhs):
    """Best time of a sparse Cholesky (or LU) factorisation and solve of the same matrix."""
    a = scipy.sparse.csc_matrix(band_to_dense(band)) if band.shape[0] <= 1500 else \
        _sparse_from_band(band)
    b = rhs.ravel()
    try:
        from sksparse.cholmod import cholesky

        results = []
        for mode in ("supernodal", "simplicial"):
            for order in ("natural", "amd"):
                t, x = best(lambda: cholesky(a, mode=mode, ordering_method=order)(b), 2)
                results.append((t, f"{mode}, {order}", x))
        return min(results, key=lambda r: r[0])
    except ImportError:
        results = []
        for perm in ("NATURAL", "MMD_AT_PLUS_A"):
            def run():
                lu = scipy.sparse.linalg.splu(a, permc_spec=perm, diag_pivot_thresh=0.0,
                                              options={"SymmetricMode": True})
                return lu.solve(b)
            t, x = best(run, 2)
            results.append((t, perm, x))
        return min(results, key=lambda r: r[0])


def _sparse_from_band(band):
    n_st, _, width = band.shape
    n = 6 * n_st
    rows, cols, vals = [], [], []
    for r in range(6):
        for c in range(r, width):
            v = band[:, r, c]
            i = 6 * np.arange(n_st) + r
            j = 6 * np.arange(n_st) + c
            ok = (j < n) & (v != 0)
            rows.append(i[ok])
            cols.append(j[ok])
            vals.append(v[ok])
    i, j, v = (np.concatenate(x) for x in (rows, cols, vals))
    up = scipy.sparse.coo_matrix((v, (i, j)), shape=(n, n))
    low = scipy.sparse.coo_matrix((v[i != j], (j[i != j], i[i != j])), shape=(n, n))
    return (up + low).tocsc()


def one_matrix(tmp, band, rhs, bw, gemm, with_sparse=True):
    n_st = band.shape[0]
    n = 6 * n_st
    count = n * (6 * bw) ** 2
    ab = lower_storage(band)
    # Factorisation alone, each on its own storage laid out beforehand (no copies timed):
    # LAPACK dpbtrf on a Fortran-ordered array it may overwrite, lower and upper form
    # (SciPy's default), 1 and 2 OpenBLAS threads, the best of the four counted (its best
    # configuration); sapgo's panel kernel on its skewed storage.
    ab_f = np.asfortranarray(ab)
    ab_u = np.zeros_like(ab)                       # upper form: ab_u[u + i - j, j] = a[i, j]
    for d in range(ab.shape[0]):
        ab_u[ab.shape[0] - 1 - d, d:] = ab[d, :n - d]
    ab_uf = np.asfortranarray(ab_u)
    u = 6 * bw - 1
    p = panel_width(u)
    lap = {(form, threads): [] for form in ("lower", "upper") for threads in (1, 2)}
    ts = []
    ref = c = None
    # Interleaved rounds, medians kept: this machine's speed drifts for seconds at a
    # time (other tenants), which must not favour either side. A pause after LAPACK lets
    # OpenBLAS's idle threads stop spinning before sapgo's kernel runs.
    for _ in range(ROUNDS):
        for form, threads in lap:
            with threadpool_limits(threads, "blas"):
                work = (ab_f if form == "lower" else ab_uf).copy(order="F")
                t0 = time.perf_counter()
                out = scipy.linalg.cholesky_banded(work, lower=form == "lower",
                                                   overwrite_ab=True, check_finite=False)
                lap[form, threads].append(time.perf_counter() - t0)
                if form == "lower":
                    ref = out
        time.sleep(0.2)
        a, c, _, _, ld1 = _skewed(ab, True, p)
        ring = -(-n // p) * p
        orig = np.zeros(ring)
        orig[:n] = np.abs(a[:n * ld1:ld1])
        y = np.zeros(ring)
        # every thread, as sapgo.threads gives an idle machine: the build before left
        # numba's count wherever its last look at the machine set it (one thread for this
        # matrix's every round, when that look met a passing process)
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        t0 = time.perf_counter()
        with blas_limits(1):
            fail = _factor_range(FNS, a, y, orig, ring, ld1, n, u, p, 0, n, True, 0.0,
                                 numba.get_num_threads())
        ts.append(time.perf_counter() - t0)
        kernel_threads = numba.get_num_threads()
        assert fail < 0
    lap_spread = {k: spread(v) for k, v in lap.items()}
    lap = {k: med(v) for k, v in lap.items()}
    t_lapack = min(lap.values())   # LAPACK's best configuration, by its median
    lapack_best = "%s form, %d thread%s" % (*min(lap, key=lap.get),
                                           "s" if min(lap, key=lap.get)[1] > 1 else "")
    t_ours = med(ts)
    diff = float(np.abs(np.asarray(c) - ref).max() / np.abs(ref).max())
    # The drop-in call against SciPy's, C-ordered input as a user would pass it (both copy),
    # also in interleaved rounds
    # (the two alternate which goes first, and no earlier result stays alive during a call:
    # both allocate the factor's copy afresh)
    # Both are the same LAPACK call (the drop-in's own work is SciPy's finiteness check,
    # done once): their ratio measures this VM's noise, so it is the median of the ratios of
    # the calls paired back to back, over CALL_ROUNDS rounds
    calls = {"scipy": [], "sapgo": []}
    funcs = {"scipy": scipy.linalg.cholesky_banded, "sapgo": cholesky_banded}
    for rnd in range(CALL_ROUNDS):
        time.sleep(0.2)
        for name in (("scipy", "sapgo") if rnd % 2 == 0 else ("sapgo", "scipy")):
            t0 = time.perf_counter()
            funcs[name](ab, lower=True)
            calls[name].append(time.perf_counter() - t0)
    c2 = cholesky_banded(ab, lower=True)   # (untimed: checked against LAPACK's factor)
    t_call_lapack, t_call_ours = med(calls["scipy"]), med(calls["sapgo"])
    call_ratios = [a / b for a, b in zip(calls["scipy"], calls["sapgo"])]
    diff_call = float(np.abs(np.asarray(c2) - ref).max() / np.abs(ref).max())
    # full solves (factor, forward and back substitution), the same driver with 256-station
    # segments: in core (band rows in arrays) and out of core (band rows in files)
    def in_core():
        b, r = band.copy(), rhs.copy()
        t0 = time.perf_counter()
        x = solve_out_of_core(b, r, bw, chunk_rows=256)
        return time.perf_counter() - t0, x

    d = Path(tmp) / "ooc"
    d.mkdir(exist_ok=True)

    def ooc():
        bf = RawArray.create(d / "band.bin", band.shape)
        rf = RawArray.create(d / "rhs.bin", rhs.shape)
        bf[:] = band
        rf[:] = rhs
        t0 = time.perf_counter()
        x = solve_out_of_core(bf, rf, bw, chunk_rows=256)
        dt = time.perf_counter() - t0
        bf.close()
        rf.close()
        return dt, x

    def lapack_solve():
        t0 = time.perf_counter()
        x = scipy.linalg.cho_solve_banded((scipy.linalg.cholesky_banded(ab, lower=True), True),
                                          rhs.ravel())
        return time.perf_counter() - t0, x

    solves = {"in": [], "ooc": [], "lapack": []}
    for _ in range(ROUNDS):   # the three full solves taking turns (a pause after LAPACK,
        time.sleep(0.2)       # whose OpenBLAS threads spin for a while after a call)
        solves["in"].append(in_core())
        solves["ooc"].append(ooc())
        solves["lapack"].append(lapack_solve())
    x_in, x_ooc, x_lap = (solves[k][-1][1] for k in ("in", "ooc", "lapack"))
    # the selected inversion from the in-core factor (covariance_blocks, the precision
    # pass's kernel without the points): every thread, and one (the adjustment runs its
    # BLAS on one thread beside the points' kernel), taking turns
    fac = band.copy()
    solve_out_of_core(fac, rhs.copy(), bw, chunk_rows=256)
    inverses = {"all": [], "one": []}
    blocks = {}
    for _ in range(ROUNDS):
        for key in inverses:
            with sapgo_threads(None if key == "all" else "1"):
                t0 = time.perf_counter()
                blocks[key] = covariance_blocks(fac, n_st, bw)
                inverses[key].append(time.perf_counter() - t0)
    inv_diff = float(np.abs(blocks["all"] - blocks["one"]).max()
                     / np.abs(blocks["all"]).max())
    solve_times = {k: [t for t, _ in v] for k, v in solves.items()}
    t_in, t_ooc, t_lapack_solve = (med(solve_times[k]) for k in ("in", "ooc", "lapack"))
    sol_diff = float(np.abs(x_ooc - x_in).max() / np.abs(x_in).max())
    row = {
        "band_width": bw, "stations": n_st, "unknowns": n, "count_gflop": count / 1e9,
        "factor_s": {"sapgo_in_core": t_ours, "lapack_dpbtrf": t_lapack,
                     "lapack_1_thread": min(lap["lower", 1], lap["upper", 1]),
                     "lapack_2_threads": min(lap["lower", 2], lap["upper", 2]),
                     **{f"lapack_{f}_{t}_thread{'s' if t > 1 else ''}": v
                        for (f, t), v in lap.items()},
                     "dense_ceiling": count / (gemm * 1e9)},
        "lapack_best_configuration": lapack_best,
        "spread_s": {"sapgo_in_core_factor": spread(ts),
                     **{f"lapack_{f}_{t}_thread{'s' if t > 1 else ''}": v
                        for (f, t), v in lap_spread.items()},
                     "sapgo_call": spread(calls["sapgo"]), "scipy_call": spread(calls["scipy"]),
                     "solve_sapgo_in_core": spread(solve_times["in"]),
                     "solve_sapgo_out_of_core": spread(solve_times["ooc"]),
                     "solve_lapack": spread(solve_times["lapack"])},
        "rounds": ROUNDS,
        "call_s": {"sapgo_cholesky_banded": t_call_ours,
                   "scipy_cholesky_banded": t_call_lapack},
        "ratio_call_scipy_over_sapgo": med(call_ratios),
        "ratio_call_scipy_over_sapgo_spread": spread(call_ratios),
        "call_rounds": CALL_ROUNDS,
        "sapgo_kernel_threads": kernel_threads,
        "solve_s": {"sapgo_in_core": t_in, "sapgo_out_of_core": t_ooc,
                    "lapack_dpbtrf_dpbtrs": t_lapack_solve},
        "gflops": {"sapgo_in_core": count / t_ours / 1e9, "lapack_dpbtrf": count / t_lapack / 1e9,
                   "dense_ceiling": gemm},
        "ratio_lapack_over_sapgo": t_lapack / t_ours,
        "ratio_out_of_core_over_in_core": t_ooc / t_in,
        "inverse_s": {"all_threads": med(inverses["all"]), "one_thread": med(inverses["one"])},
        "inverse_spread_s": {"all_threads": spread(inverses["all"]),
                             "one_thread": spread(inverses["one"])},
        "ratio_inverse_over_solve_in_core": med(inverses["all"]) / t_in,
        "inverse_max_rel_diff_one_vs_all_threads": inv_diff,
        "factor_max_rel_diff_vs_lapack": diff,
        "drop_in_max_rel_diff_vs_scipy": diff_call,
        "solution_max_rel_diff_out_of_core_vs_in_core": sol_diff,
        "solution_max_rel_diff_vs_lapack": float(np.abs(x_in.ravel() - x_lap).max()
                                                 / np.abs(x_lap).max()),
    }
    if with_sparse:
        t_sp, how, x_sp = sparse_time(band, rhs)
        row["solve_s"]["sparse"] = t_sp
        row["sparse_configuration"] = how
        row["gflops"]["sparse_solve"] = count / t_sp / 1e9
        row["ratio_sparse_over_sapgo_solve"] = t_sp / t_in
    return row


def fit(x, y):
    k, c = np.polyfit(np.log(x), np.log(y), 1)
    return float(k), float(c)


def scaling_in_photos(tmp, sizes):
    rows = []
    for photos in sizes:
        band, rhs, bw = reduced_matrix(tmp, 20, photos)
        d = Path(tmp) / "scale"
        d.mkdir(exist_ok=True)
        ts = []
        for _ in range(ROUNDS):
            bf = RawArray.create(d / "band.bin", band.shape)
            rf = RawArray.create(d / "rhs.bin", rhs.shape)
            bf[:] = band
            rf[:] = rhs
            t = time.perf_counter()
            solve_out_of_core(bf, rf, bw, chunk_rows=256)
            ts.append(time.perf_counter() - t)
            bf.close()
            rf.close()
        rows.append({"photos": band.shape[0], "band_width": bw, "sapgo_out_of_core_s": med(ts),
                     "spread_s": spread(ts)})
        del band, rhs
    return rows


def plots(res, out_dir, suffix=""):
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib not installed: no plots (pip install sapgo[plot])")
        return []
    rows = res["by_band_width"]
    bw = np.array([r["band_width"] for r in rows], float)
    t = np.array([r["solve_s"]["sapgo_out_of_core"] for r in rows])
    k, c = res["fit_band_width"]["exponent"], res["fit_band_width"]["log_constant"]
    fig, ax = plt.subplots(figsize=(6, 4.2))
    ax.loglog(bw, t, "o", label="sapgo out of core (factor + solve)")
    for key, label in (("lapack_dpbtrf_dpbtrs", "LAPACK dpbtrf + dpbtrs"),
                       ("sparse", res["sparse_solver"])):
        y = [r["solve_s"].get(key) for r in rows]
        if all(v is not None for v in y):
            ax.loglog(bw, y, "s--", ms=4, label=label)
    xs = np.linspace(bw.min(), bw.max(), 50)
    ax.loglog(xs, np.exp(c) * xs ** k, "-", label=f"fit: t ~ b^{k:.2f}")
    ax.set_xlabel("band width b (stations)")
    ax.set_ylabel("solve time (s)")
    ax.set_title(f"Solve time, {rows[0]['stations']} photos")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    p1 = out_dir / f"solver_bandwidth{suffix}.png"
    fig.savefig(p1, dpi=110)
    plt.close(fig)
    fig, ax = plt.subplots(figsize=(6, 4.2))
    for key, label in (("sapgo_in_core", "sapgo"), ("lapack_dpbtrf", "LAPACK dpbtrf"),
                       ("sparse_solve", res["sparse_solver"] + " (factor + solve)"),
                       ("dense_ceiling", "dense DGEMM rate")):
        y = [r["gflops"].get(key) for r in rows]
        if all(v is not None for v in y):
            ax.plot(bw, y, "o-" if key != "dense_ceiling" else "k:", label=label)
    ax.set_xlabel("band width b (stations)")
    ax.set_ylabel("GFLOP/s  (count n (6b)^2)")
    ax.set_title("Factorisation rate, same matrices, 2 cores")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    p2 = out_dir / f"solver_gflops{suffix}.png"
    fig.savefig(p2, dpi=110)
    plt.close(fig)
    return [str(p1.relative_to(out_dir.parent)), str(p2.relative_to(out_dir.parent))]


class sapgo_threads:
    """``SAPGO_THREADS`` for the block: None (auto, every thread on an idle machine) or a
    number of threads."""

    def __init__(self, setting):
        self.setting = setting

    def __enter__(self):
        from sapgo import threads

        self.old = threads._setting
        if self.setting is not None:
            threads._setting = self.setting

    def __exit__(self, *exc):
        from sapgo import threads

        threads._setting = self.old


def table(res):
    out = [f"Medians of {res['by_band_width'][0].get('rounds', '?')} interleaved rounds; "
           "factor times with (min-max).", "",
           "| b | stations | LAPACK dpbtrf s | sapgo s | ratio | GFLOP/s sapgo / LAPACK / "
           "ceiling | drop-in call ratio (min-max of paired calls) | sapgo in core solve s | out of core s | ooc/in-core | "
           f"{res['sparse_solver']} s | max rel diff | selected inversion s, every thread / one "
           "(x in-core solve) |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in res["by_band_width"]:
        f, s, g = r["factor_s"], r["solve_s"], r["gflops"]
        sp = r.get("spread_s", {})
        cfg = r["lapack_best_configuration"].replace(" form, ", "_").replace(" thread", "_thread")
        lap_sp = sp.get(f"lapack_{cfg}", [float("nan")] * 2)
        our_sp = sp.get("sapgo_in_core_factor", [float("nan")] * 2)
        cs = r.get("ratio_call_scipy_over_sapgo_spread", [float("nan")] * 2)
        out.append(
            f"| {r['band_width']} | {r['stations']} | {f['lapack_dpbtrf']:.4f} "
            f"({lap_sp[0]:.4f}-{lap_sp[1]:.4f}) | "
            f"{f['sapgo_in_core']:.4f} ({our_sp[0]:.4f}-{our_sp[1]:.4f}) | "
            f"**{r['ratio_lapack_over_sapgo']:.2f}** | "
            f"{g['sapgo_in_core']:.0f} / {g['lapack_dpbtrf']:.0f} / {g['dense_ceiling']:.0f} | "
            f"{r['ratio_call_scipy_over_sapgo']:.2f} ({cs[0]:.2f}-{cs[1]:.2f}) | "
            f"{s['sapgo_in_core']:.4f} | "
            f"{s['sapgo_out_of_core']:.4f} | "
            f"{r['ratio_out_of_core_over_in_core']:.2f} | "
            f"{s.get('sparse', float('nan')):.3f} | {r['factor_max_rel_diff_vs_lapack']:.1e} | "
            + (f"{r['inverse_s']['all_threads']:.4f} / {r['inverse_s']['one_thread']:.4f} "
               f"({r['ratio_inverse_over_solve_in_core']:.2f}) |" if "inverse_s" in r else
               "|"))
    out.append("")
    out.append("| photos | band width | sapgo out-of-core solve s |")
    out.append("|---|---|---|")
    for r in res["by_photos"]:
        out.append(f"| {r['photos']} | {r['band_width']} | {r['sapgo_out_of_core_s']:.3f} |")
    out.append("")
    ff = res["fit_band_width_factor"]
    out.append(f"Fitted exponents: solve time ~ b^{res['fit_band_width']['exponent']:.2f} "
               f"(fixed photo count), ~ n^{res['fit_photos']['exponent']:.2f} (fixed band "
               f"width); factorisation alone ~ b^{ff['sapgo']:.2f} (LAPACK b^{ff['lapack']:.2f}, "
               f"operation count b^{ff['operation_count']:.2f}).")
    return "\n".join(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--photos", type=int, default=6000, help="photos per band-width block")
    ap.add_argument("--sizes", default="5000,10000,20000,50000,100000",
                    help="photo counts for the scaling at fixed band width")
    ap.add_argument("--quick", action="store_true", help="small blocks, for a smoke run")
    args = ap.parse_args()
    strips = STRIPS
    sizes = [int(s) for s in args.sizes.split(",")]
    if args.quick:
        strips, sizes, args.photos = [3, 12, 24], [2000, 4000], 1200
    gemm = gemm_rate()
    res = {"machine": {"platform": platform.platform(), "processor": platform.processor(),
                       "python": sys.version.split()[0], "numpy": np.__version__,
                       "scipy": scipy.__version__, "cores": 2},
           "dense_gemm_gflops": gemm, "sparse_solver": sparse_solver(),
           "photos": args.photos, "by_band_width": []}
    sys.path.insert(0, str(HERE))
    from colmap import git_state

    res["sapgo_source"] = git_state()
    with tempfile.TemporaryDirectory(dir=HERE.parent / "data" if (HERE.parent / "data").exists()
                                     else None) as tmp:
        warm_band, warm_rhs, warm_bw = reduced_matrix(tmp, 3, 60)
        one_matrix(tmp, warm_band, warm_rhs, warm_bw, gemm, with_sparse=False)
        for s in strips:
            band, rhs, bw = reduced_matrix(tmp, s, args.photos)
            before = load()
            row = one_matrix(tmp, band, rhs, bw, gemm, with_sparse=bw <= 66)
            row["load_before"] = before
            res["by_band_width"].append(row)
            print(f"b={bw:3d}: LAPACK {row['factor_s']['lapack_dpbtrf']:.4f} s, sapgo "
                  f"{row['factor_s']['sapgo_in_core']:.4f} s, ratio "
                  f"{row['ratio_lapack_over_sapgo']:.2f}; out of core / in core "
                  f"{row['ratio_out_of_core_over_in_core']:.2f}", flush=True)
            del band, rhs
        res["by_photos"] = scaling_in_photos(tmp, sizes)
    rows = res["by_band_width"]
    k, c = fit([r["band_width"] for r in rows], [r["solve_s"]["sapgo_out_of_core"] for r in rows])
    res["fit_band_width"] = {"exponent": k, "log_constant": c}
    bws = [r["band_width"] for r in rows]
    res["fit_band_width_factor"] = {
        name: fit(bws, [r["factor_s"][key] for r in rows])[0]
        for name, key in (("sapgo", "sapgo_in_core"), ("lapack", "lapack_dpbtrf"),
                          ("operation_count", "dense_ceiling"))}
    k2, c2 = fit([r["photos"] for r in res["by_photos"]],
                 [r["sapgo_out_of_core_s"] for r in res["by_photos"]])
    res["fit_photos"] = {"exponent": k2, "log_constant": c2}
    out_dir = HERE / "results"
    out_dir.mkdir(exist_ok=True)
    res["plots"] = plots(res, out_dir, "_quick" if args.quick else "")
    name = "solver_quick.json" if args.quick else "solver.json"
    (out_dir / name).write_text(json.dumps(res, indent=1))
    print(table(res))
    print(f"fitted exponents: band width {k:.2f}, photos {k2:.2f}")


if __name__ == "__main__":
    main()
