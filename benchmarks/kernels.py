"""What the tree's fronts can reach on this machine: BLAS and LAPACK rates at front sizes.

The partition tree factors dense fronts with ``m`` own and ``f`` boundary unknowns
(``m`` = 54 to 1 200, ``f`` = 150 to 1 200 on the generated square blocks). This script
measures, one thread each (as the tree's workers run them) and called from numba without
the GIL (as the solver calls them, ``sapgo.blas``):

- ``dgemm``'s rate alone and two at once on two threads (the machine's ceiling);
- at front sizes, the rates of the three steps of a front's partial Cholesky with plain
  LAPACK/BLAS (``dpotrf`` of ``A11``, ``dtrsm`` of ``A21``, ``dsyrk`` of the update) and of
  the own columns by recursive halves (``sapgo.solve.tiles.chol_columns``), which the solver
  uses;
- the selected inversion's kernel per front (``sapgo.solve.fronts._front_inverse``).

Best of 30 calls each; prints a Markdown table and writes results/kernels.json.

    python benchmarks/kernels.py
"""

from __future__ import annotations

import json
import os
import platform
import sys
import threading
import time
from pathlib import Path

import numpy as np
from numba import njit

sys.path.insert(0, str(Path(__file__).parent))

import sapgo  # noqa: E402
from sapgo.blas import FNS, L, N, R, T, blas_limits, gemm, potrf, syrk, trsm  # noqa: E402
from sapgo.solve.fronts import _front_inverse  # noqa: E402
from sapgo.solve.tiles import chol_columns  # noqa: E402

RESULTS = Path(__file__).parent / "results" / "kernels.json"
SIZES = ((54, 150), (120, 250), (216, 480), (288, 250), (600, 900), (1200, 1200))


@njit(nogil=True)
def _gemm_loop(fns, n, f, m, z, x, c):
    for _ in range(n):
        gemm(fns.dgemm, N, N, f, m, f, 1.0, z, f, x, f, 0.0, c, f)


@njit(nogil=True)
def _plain(fns, a, kf, m, a22, f):
    potrf(fns.dpotrf, L, m, a, kf)
    if f > 0:
        trsm(fns.dtrsm, R, L, T, N, f, m, 1.0, a, kf, a[m:], kf)
        syrk(fns.dsyrk, L, N, f, m, -1.0, a[m:], kf, 1.0, a22, f)


@njit(nogil=True)
def _potrf_only(fns, a, kf, m):
    potrf(fns.dpotrf, L, m, a, kf)


@njit(nogil=True)
def _trsm_only(fns, a, kf, m, f):
    trsm(fns.dtrsm, R, L, T, N, f, m, 1.0, a, kf, a[m:], kf)


@njit(nogil=True)
def _syrk_only(fns, a, kf, m, a22, f):
    syrk(fns.dsyrk, L, N, f, m, -1.0, a[m:], kf, 1.0, a22, f)


@njit(nogil=True)
def _recursive(fns, a, kf, m, a22, f, orig):
    chol_columns(fns, a, kf, kf, m, 1e-14, orig)
    if f > 0:
        syrk(fns.dsyrk, L, N, f, m, -1.0, a[m:], kf, 1.0, a22, f)


def best(fn, reps=30):
    fn()
    ts = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return min(ts)


def gemm_rates():
    """dgemm (f x f times f x m, f = 900, m = 600) alone and two at once."""
    f, m, n = 900, 600, 20
    rng = np.random.default_rng(0)

    def run(out, i):
        z, x, c = rng.normal(size=f * f), rng.normal(size=f * m), np.empty(f * m)
        _gemm_loop(FNS, 1, f, m, z, x, c)
        t0 = time.perf_counter()
        _gemm_loop(FNS, n, f, m, z, x, c)
        out[i] = 2.0 * f * f * m * n / (time.perf_counter() - t0) / 1e9

    alone, two = [0.0], [0.0, 0.0]
    run(alone, 0)
    ths = [threading.Thread(target=run, args=(two, i)) for i in range(2)]
    for t in ths:
        t.start()
    for t in ths:
        t.join()
    return {"dgemm_one_thread_gflops": alone[0], "dgemm_two_threads_at_once_gflops": two}


def front_rates(m, f):
    rng = np.random.default_rng(m + f)
    kf = m + f
    g = rng.normal(size=(kf, kf))
    a = g @ g.T + kf * np.eye(kf)
    own = np.asfortranarray(np.tril(a[:, :m])).reshape(-1, order="F")
    upd = np.asfortranarray(a[m:, m:]).reshape(-1, order="F")
    orig = np.diag(a)[:m].copy()
    fl = (m ** 3 / 3.0, m * m * f, m * f * f)

    def copies():
        return own.copy(), upd.copy()

    t_copy = best(copies)
    fac = np.linalg.cholesky(a)
    col = np.asfortranarray(fac[:, :m]).reshape(-1, order="F")
    t_pot = best(lambda: _potrf_only(FNS, own.copy(), kf, m)) - t_copy / 2
    t_trsm = best(lambda: _trsm_only(FNS, col.copy(), kf, m, f)) - t_copy / 2
    t_syrk = best(lambda: _syrk_only(FNS, col, kf, m, upd.copy(), f)) - t_copy / 2
    t_plain = best(lambda: _plain(FNS, *_split(copies(), kf, m), f)) - t_copy
    t_rec = best(lambda: _recursive(FNS, *_split(copies(), kf, m), f, orig)) - t_copy
    z22 = np.asfortranarray(np.linalg.inv(a)[m:, m:])
    colf = np.asfortranarray(fac[:, :m])
    t_inv = best(lambda: _front_inverse(colf, z22, 6))
    inv_fl = 2.0 / 3.0 * m ** 3 + 2.0 * m * m * f + 2.0 * m * f * f
    return {
        "m": m, "f": f, "gflop_factor": sum(fl) / 1e9,
        "dpotrf_gflops": fl[0] / t_pot / 1e9, "dtrsm_gflops": fl[1] / t_trsm / 1e9,
        "dsyrk_gflops": fl[2] / t_syrk / 1e9,
        "plain_front_gflops": sum(fl) / t_plain / 1e9,
        "recursive_front_gflops": sum(fl) / t_rec / 1e9,
        "front_inverse_gflops": inv_fl / t_inv / 1e9,
    }


def _split(c, kf, m):
    return c[0], kf, m, c[1]


def main():
    with blas_limits(1):
        g = gemm_rates()
        rows = [front_rates(m, f) for m, f in SIZES]
    from colmap import git_state

    out = {"benchmark": "BLAS and LAPACK rates at the tree's front sizes, one thread each",
           "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                       "platform": platform.platform(), "load": os.getloadavg()},
           "sapgo_version": sapgo.__version__, "sapgo_source": git_state(), **g,
           "fronts": rows}
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(out, indent=1) + "\n")
    two = g["dgemm_two_threads_at_once_gflops"]
    print(f"dgemm, one thread: {g['dgemm_one_thread_gflops']:.1f} GFlop/s; two threads at "
          f"once: {two[0]:.1f} + {two[1]:.1f}\n")
    print("| m | f | dpotrf | dtrsm | dsyrk | front, plain | front, recursive halves | "
          "front inverse |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['m']} | {r['f']} | {r['dpotrf_gflops']:.1f} | {r['dtrsm_gflops']:.1f} | "
              f"{r['dsyrk_gflops']:.1f} | {r['plain_front_gflops']:.1f} | "
              f"{r['recursive_front_gflops']:.1f} | {r['front_inverse_gflops']:.1f} |")
    print(f"\n(GFlop/s, one thread each; results: {RESULTS})")


if __name__ == "__main__":
    main()
