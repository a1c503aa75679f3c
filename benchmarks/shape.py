"""Any block shape: sapgo's band and tree solvers against COLMAP and CHOLMOD (issue 16).

How to run::

    pip install pycolmap 'scikit-sparse<0.5'   # benchmark-only (CHOLMOD: libsuitesparse-dev)
    python benchmarks/shape.py [--blocks 50x50,100x100,200x200,400x400,20x500]
                               [--rounds 3] [--band-max 40000] [--dir DIR]

Blocks: ``sapgo generate --strips S --photos-per-strip P`` (9-point pattern, 60/20 overlap),
one *fixed* control point per 25 photos, all other points check points (unknown to both
tools). Every run is a process of its own (peak RSS: its ``ru_maxrss`` from ``wait4``,
started from a bare interpreter as in scale.py), on a fresh copy of the unordered generated
file; before its timed run each process adjusts a small block (12 x 12 photos) with the
same tool and configuration, untimed but recorded (``warmup_s``), as colmap.py does: numba
loads sapgo's cached kernels at their first call (0.3-0.6 s a process, most of it LLVM's
start-up), pycolmap its library at import, before COLMAP's timer, and both have first-call
costs; the rounds are interleaved (tree, COLMAP best, COLMAP default,
band, CHOLMOD, then again), and each run records the machine's load average and the CPU time
other processes took meanwhile. Reported: medians over the rounds and the spread (min, max).

- **sapgo tree** / **sapgo band**: ``sapgo.adjust`` with ``solver="tree"`` / ``"band"``
  (ordering included in the time to solution; Gauss-Newton; the precision pass included, and
  its time given apart). Seconds per iteration: build + solve + update over the iterations.
  The band runs in every round up to 10 000 photos, in the first round only up to
  ``--band-max`` photos, and not beyond (its cost grows with the square of the photo count:
  53 s an iteration at 200 x 200 in the issue).
- **COLMAP default** and **COLMAP best**: pycolmap's bundle adjuster (Ceres, SPARSE_SCHUR with
  SuiteSparse, 2 threads), the latter with an initial trust region radius of 1e16 (practically
  Gauss-Newton steps from the start); the configuration as benchmarks/colmap.py describes it.
  Seconds per iteration: Ceres' minimizer time over its linear solves; time to solution:
  problem set-up plus ``solve()``.
- **CHOLMOD** (scikit-sparse, supernodal) factoring the same reduced matrix that sapgo's tree
  factors: the matrix is captured from one tree build (the sum of every node's own
  contributions) and handed to CHOLMOD with each of its orderings (AMD, METIS, NESDIS and its
  "best"); the time of the numeric factorisation plus a solve of the fastest ordering against
  sapgo's factorisation plus solve of the same matrix (the solver time of the same build).
  CHOLMOD is Debian's SuiteSparse 5 (``libsuitesparse-dev``) with OpenBLAS as the system BLAS
  (``libopenblas0-pthread``; with the reference BLAS it is five times slower), scikit-sparse
  0.4.16 (the last release that builds against SuiteSparse 5).

Writes ``benchmarks/results/shape.json`` and prints the Markdown table of benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
RESULTS = HERE / "results" / "shape.json"

import sapgo  # noqa: E402


def block_spec(name):
    s, p = (int(x) for x in name.split("x"))
    return {"strips": s, "photos_per_strip": p, "control_points": max(4, s * p // 25)}


def load():
    try:
        return [float(x) for x in Path("/proc/loadavg").read_text().split()[:3]]
    except OSError:
        return None


def peak_rss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


# -- the child runs ---------------------------------------------------------------------------

def warm_path(path):
    """The small block beside the runs' files whose adjustment, in the child before the
    timed run, loads the kernels (sapgo) or the libraries' first-call state (COLMAP)."""
    return Path(path).parent / "warm0.h5"


def child_sapgo(path, solver, memory=""):
    # numba loads its cached kernels at their first call (0.3-0.4 s a process, most of it
    # LLVM's own start-up); pycolmap loads its library at import, before COLMAP's timer.
    # As in colmap.py, both load theirs before the timed run: a small adjustment first.
    warm = Path(path).with_name(Path(path).stem + "-warm.h5")
    shutil.copy(warm_path(path), warm)
    t0 = time.perf_counter()
    sapgo.adjust(warm, sapgo.Options(progress=False, solver=solver, memory=memory or None))
    warmup = time.perf_counter() - t0
    shutil.rmtree(warm.with_name(warm.name + ".work"), ignore_errors=True)
    warm.unlink(missing_ok=True)
    t0 = time.perf_counter()
    s = sapgo.adjust(path, sapgo.Options(progress=False, solver=solver,
                                         memory=memory or None))
    wall = time.perf_counter() - t0
    t = s.timings_s
    its = max(s.iterations, 1)
    per_it = (t["build"] + t["solve"] + t["update"]) / its
    return {
        "converged": s.converged, "iterations": s.iterations, "sigma0": s.sigma0,
        "image_rms_um": s.image_rms_um, "solver": s.solver, "ordering": s.ordering,
        "band_width": s.band_width, "tree": s.tree,
        "time_to_solution_s": wall,
        "time_to_solution_without_precision_s": wall - t.get("precision", 0.0),
        "s_per_iteration": per_it,
        "phases_s": {k: round(v, 4) for k, v in t.items()},
        "phases_per_iteration_s": {k: t[k] / its for k in ("build", "solve", "update")},
        "factor_bytes": (s.tree["factor_bytes"] if s.tree else
                         8 * 36 * s.n_stations * s.band_width),
        "check_points": {k: s.check_points.get(k) for k in ("n", "sxy", "sz")},
        "warmup_s": warmup,
    }


def child_colmap(path, config):
    import pycolmap

    import colmap as cb

    cfg = [c for c in cb.solver_configs(10 ** 9, pycolmap) if c["name"] == config][0]
    t0 = time.perf_counter()   # (as sapgo's: a small adjustment before the timed one)
    cb.run_colmap(cb.load_problem(warm_path(path)), cfg, pycolmap)
    warmup = time.perf_counter() - t0
    prob = cb.load_problem(path)
    r = cb.run_colmap(prob, cfg, pycolmap)
    r["warmup_s"] = warmup
    r.pop("log", None)
    return r


def child_cholmod(path, repeat=3):
    """The reduced matrix of one tree build, factored by sapgo's tree and by CHOLMOD."""
    import scipy.sparse as sp
    from sksparse.cholmod import analyze

    from sapgo.adjust import _load_block
    from sapgo.work import Work, work_path
    from sapgo.ordering import order_project
    from sapgo.project import Project
    from sapgo.solve.tree import tree_step

    order_project(path, solver="tree")
    # (every front in core: the capture sees whole fronts; sapgo's factorisation as in core)
    opts = sapgo.Options(progress=False, memory="16G")
    parts = []   # (rows, cols, values) per node: one append, as threads call capture
    rhs = {}

    def capture(i, a, b):
        fr = tree.front(i)
        k = 6
        idx = (k * fr[:, None] + np.arange(k)).ravel()
        low = np.tril(np.asarray(a))
        r, c = np.nonzero(low)
        parts.append((idx[r], idx[c], low[r, c]))
        rhs[i] = (idx, np.asarray(b).copy())

    with Project(path) as p:
        blk = _load_block(p)
        tree = blk.tree
        work = Work(work_path(path), p, 0, create=True)
        try:
            work.initialise(p, opts.chunk_points)
            sapgo_s = []
            for r in range(repeat):
                step = tree_step(p, work, blk, opts, tree,
                                 capture=capture if r == 0 else None)
                sapgo_s.append(step["seconds"])
        finally:
            work.close()
            shutil.rmtree(work_path(path), ignore_errors=True)
    n = 6 * tree.n_active
    rows, cols, vals = (np.concatenate(x) for x in zip(*parts))
    low = sp.csc_matrix((vals, (rows, cols)), shape=(n, n))
    low.sum_duplicates()
    m = (low + sp.tril(low, -1).T).tocsc()
    d = np.zeros(n)
    for idx, b in rhs.values():
        d[idx] += b
    x_sapgo = step["delta"][:tree.n_active].ravel()
    res_sapgo = float(np.abs(m @ x_sapgo - d).max() / np.abs(d).max())
    out = {"unknowns": n, "nonzeros_lower": int(low.nnz), "sapgo_factor_solve_s": sapgo_s,
           "sapgo_relative_residual": res_sapgo, "cholmod": {}}
    for ordering in ("amd", "metis", "nesdis", "best"):
        try:
            t0 = time.perf_counter()
            f = analyze(m, mode="supernodal", ordering_method=ordering)
            t_an = time.perf_counter() - t0
            times = []
            for _ in range(repeat):
                t0 = time.perf_counter()
                f.cholesky_inplace(m)
                x = f(d)
                times.append(time.perf_counter() - t0)
            nnz_l = int(f.L().nnz)
            out["cholmod"][ordering] = {
                "analyze_s": t_an, "factor_solve_s": times, "factor_nonzeros": nnz_l,
                "factor_bytes": 8 * nnz_l,
                "relative_residual": float(np.abs(m @ x - d).max() / np.abs(d).max()),
                "same_solution": float(np.abs(x - x_sapgo).max() / np.abs(x_sapgo).max())}
        except Exception as exc:  # an ordering CHOLMOD was built without
            out["cholmod"][ordering] = {"error": str(exc)}
    return out


def child_main(argv):
    kind, path = argv[0], argv[1]
    t0 = time.perf_counter()
    if kind == "sapgo":
        r = child_sapgo(path, argv[2], argv[3] if len(argv) > 3 else "")
    elif kind == "colmap":
        r = child_colmap(path, argv[2])
    else:
        r = child_cholmod(path)
    r["child_wall_s"] = time.perf_counter() - t0
    r["peak_rss_mb"] = peak_rss_mb()
    print("RESULT " + json.dumps(r, default=float))


# -- the parent -------------------------------------------------------------------------------

def run_child(*args):
    import colmap as cb

    waited = cb.wait_for_idle()
    before = load()
    c0 = cb.cpu_snapshot()
    ch0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    # through a bare interpreter (scale.LAUNCH): a process's peak RSS counts that of the
    # process it was forked from, which would floor every figure at this script's size
    from scale import LAUNCH

    env = dict(os.environ)
    if args[0] != "sapgo" and sapgo.BLAS_TIMEOUT_SET:
        # (sapgo's own OpenBLAS spin time is its setting, not the other tools')
        env["OPENBLAS_THREAD_TIMEOUT"] = "28"   # (OpenBLAS's default)
    proc = subprocess.run([sys.executable, "-S", "-c", LAUNCH, sys.executable, __file__,
                           "--child", *map(str, args)], capture_output=True, text=True,
                          env=env)
    ch1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    # the CPU time other processes took meanwhile (the run's own process not counted)
    child = (ch1.ru_utime + ch1.ru_stime) - (ch0.ru_utime + ch0.ru_stime)
    foreign = max(0.0, cb.foreign_cpu_s(c0) - child)
    line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")]
    if proc.returncode != 0 or not line:
        return {"error": (proc.stderr or proc.stdout)[-2000:], "returncode": proc.returncode}
    r = json.loads(line[-1][7:])
    r.update(load_before=before, foreign_cpu_s=foreign, waited_for_idle_s=waited)
    launch = [x for x in proc.stderr.splitlines() if x.startswith("LAUNCH ")]
    if launch:   # the peak RSS of the run's process alone (wait4's ru_maxrss)
        r["peak_rss_mb"] = int(launch[-1].split()[2]) / 1024.0
    return r


def spread(values):
    v = [x for x in values if x is not None]
    if not v:
        return None
    return {"median": statistics.median(v), "min": min(v), "max": max(v), "n": len(v)}


def bench_block(name, workdir, rounds, band_max, tools, band_all=10000, memory=""):
    spec = block_spec(name)
    gen = workdir / f"{name}.h5"
    info = sapgo.generate_block(gen, progress=False, control_sigma=0.0, **spec)
    n = info["photos"]
    print(f"\n{name}: {n} photos, {info['points']} points, {info['observations']} "
          f"observations", file=sys.stderr)
    runs = {t: [] for t in tools}
    if n > band_max:
        runs.pop("sapgo band", None)
    for r in range(rounds):
        for tool in runs:
            if tool == "sapgo band" and n > band_all and r > 0:
                continue   # a slow band: one round
            if tool.startswith("sapgo"):
                path = workdir / f"{name}-run.h5"
                shutil.copy(gen, path)
                res = run_child("sapgo", path, tool.split()[1], memory or "")
                shutil.rmtree(path.with_name(path.name + ".work"), ignore_errors=True)
                path.unlink(missing_ok=True)
            elif tool == "cholmod":
                if r > 0:
                    continue   # three repeats inside one run
                path = workdir / f"{name}-chol.h5"
                shutil.copy(gen, path)
                res = run_child("cholmod", path)
                path.unlink(missing_ok=True)
            else:
                cfg = ("SPARSE_SCHUR (SuiteSparse), initial trust radius 1e16"
                       if tool == "colmap best" else "SPARSE_SCHUR (SuiteSparse)")
                res = run_child("colmap", gen, cfg)
            res["round"] = r
            runs[tool].append(res)
            brief = {k: round(res[k], 3) for k in ("s_per_iteration", "time_to_solution_s",
                                                   "peak_rss_mb") if k in res}
            print(f"  round {r} {tool}: {brief or res.get('error', '')[-300:]}",
                  file=sys.stderr)
    row = {"block": name, "photos": n, "points": info["points"],
           "observations": info["observations"], "runs": runs, "summary": {}}
    for tool, rs in runs.items():
        ok = [x for x in rs if "error" not in x]
        if tool == "cholmod":
            if ok:
                c = ok[0]
                best = min((v for v in c["cholmod"].values() if "factor_solve_s" in v),
                           key=lambda v: min(v["factor_solve_s"]), default=None)
                row["summary"][tool] = {
                    "sapgo_factor_solve_s": spread(c["sapgo_factor_solve_s"]),
                    "cholmod_best_factor_solve_s": (spread(best["factor_solve_s"])
                                                    if best else None),
                    "cholmod_best_ordering": next((k for k, v in c["cholmod"].items()
                                                   if v is best), None),
                    "cholmod_factor_bytes": best["factor_bytes"] if best else None,
                    "unknowns": c["unknowns"]}
            continue
        row["summary"][tool] = {
            "s_per_iteration": spread([x.get("s_per_iteration") for x in ok]),
            "time_to_solution_s": spread([x.get("time_to_solution_s") for x in ok]),
            "time_to_solution_without_precision_s": spread(
                [x.get("time_to_solution_without_precision_s") for x in ok]),
            "peak_rss_mb": spread([x.get("peak_rss_mb") for x in ok]),
            "iterations": [x.get("iterations") for x in ok],
            "factor_bytes": ok[0].get("factor_bytes") if ok else None,
            "errors": len(rs) - len(ok)}
    s = row["summary"]
    try:
        tree = s["sapgo tree"]["s_per_iteration"]["median"]
        row["speedup_per_iteration_vs_colmap_best"] = \
            s["colmap best"]["s_per_iteration"]["median"] / tree
        row["speedup_to_solution_vs_colmap_best"] = \
            s["colmap best"]["time_to_solution_s"]["median"] / \
            s["sapgo tree"]["time_to_solution_s"]["median"]
    except (KeyError, TypeError):
        pass
    return row


def fmt(v, nd=2):
    if v is None:
        return ""
    return f"{v:.{nd}f}" if isinstance(v, float) else str(v)


def med(s, tool, key):
    try:
        return s[tool][key]["median"]
    except (KeyError, TypeError):
        return None


def rng(s, tool, key):
    try:
        x = s[tool][key]
        return f"{x['median']:.2f} ({x['min']:.2f}-{x['max']:.2f})"
    except (KeyError, TypeError):
        return ""


def table(rows):
    out = ["| block | photos | tool | s/iteration median (min-max) | to solution s | "
           "without precision s | peak RSS MB | factor MB | iterations |",
           "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        s = r["summary"]
        for tool in ("sapgo tree", "sapgo band", "colmap best", "colmap default"):
            if tool not in s:
                continue
            fb = s[tool].get("factor_bytes")
            out.append(
                f"| {r['block']} | {r['photos']} | {tool} | {rng(s, tool, 's_per_iteration')} | "
                f"{rng(s, tool, 'time_to_solution_s')} | "
                f"{rng(s, tool, 'time_to_solution_without_precision_s')} | "
                f"{fmt(med(s, tool, 'peak_rss_mb'), 0)} | "
                f"{fmt(fb / 2**20, 0) if fb else ''} | "
                f"{','.join(str(i) for i in s[tool]['iterations'])} |")
    out += ["", "| block | tree vs COLMAP best, per iteration | to solution | sapgo tree "
            "factor + solve s | CHOLMOD best factor + solve s (ordering) | CHOLMOD factor MB |",
            "|---|---|---|---|---|---|"]
    for r in rows:
        c = r["summary"].get("cholmod") or {}
        sp_ = r.get("speedup_per_iteration_vs_colmap_best")
        st_ = r.get("speedup_to_solution_vs_colmap_best")
        a, b = c.get("sapgo_factor_solve_s"), c.get("cholmod_best_factor_solve_s")
        out.append(f"| {r['block']} | {fmt(sp_)}x | {fmt(st_)}x | "
                   f"{fmt(a['median'], 3) if a else ''} | "
                   f"{fmt(b['median'], 3) if b else ''} ({c.get('cholmod_best_ordering', '')}) | "
                   f"{fmt(c['cholmod_factor_bytes'] / 2**20, 0) if c.get('cholmod_factor_bytes') else ''} |")
    return "\n".join(out)


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--child":
        return child_main(argv[1:])
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--blocks", default="50x50,100x100,200x200,400x400,20x500")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--band-max", type=int, default=40000,
                    help="the band solver only up to this many photos")
    ap.add_argument("--tools", default="sapgo tree,colmap best,colmap default,sapgo band,cholmod")
    ap.add_argument("--dir", default=None)
    ap.add_argument("--memory", default="", help="sapgo adjust --memory for sapgo's runs "
                    "(default: sapgo's own, 1 GiB for the whole adjustment on the tree)")
    ap.add_argument("--output", default=str(RESULTS))
    args = ap.parse_args(argv)
    from colmap import git_state

    tools = [t.strip() for t in args.tools.split(",")]
    if "cholmod" in tools:
        import importlib.util

        if importlib.util.find_spec("sksparse") is None:
            raise SystemExit("shape.py: the cholmod tool needs scikit-sparse (pip install "
                             "'scikit-sparse<0.5', with Debian's libsuitesparse-dev and "
                             "libopenblas0-pthread); install it, or leave cholmod out of "
                             "--tools")
    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory(dir=args.dir, prefix="sapgo-shape-") as tmp:
        workdir = Path(tmp)
        warm = workdir / "warm.h5"   # compile or load the kernels outside the timed runs
        sapgo.generate_block(warm, strips=12, photos_per_strip=12, control_points=8,
                             progress=False)
        for solver in ("tree", "band"):
            shutil.copy(warm, workdir / "w2.h5")
            sapgo.adjust(workdir / "w2.h5", sapgo.Options(progress=False, solver=solver))
        # each child's own warm-up block (warm_path): fixed control, as the blocks
        sapgo.generate_block(workdir / "warm0.h5", strips=12, photos_per_strip=12,
                             control_points=8, control_sigma=0.0, progress=False)
        rows = []
        for name in args.blocks.split(","):
            rows.append(bench_block(name, workdir, args.rounds, args.band_max, tools,
                                    memory=args.memory))
            partial = {"blocks": {r["block"]: r for r in rows}}
            Path(args.output).with_suffix(".partial.json").write_text(
                json.dumps(partial, indent=1, default=float))
    result = {
        "benchmark": "sapgo band and tree against COLMAP and CHOLMOD, square blocks and strips",
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "platform": platform.platform(), "load_at_end": load()},
        "sapgo_version": sapgo.__version__, "sapgo_source": git_state(),
        "rounds": args.rounds, "sapgo_memory": args.memory or "default (1G)",
        "blocks": {r["block"]: r for r in rows},
        "speedup_per_iteration_vs_colmap_best": {
            r["block"]: r.get("speedup_per_iteration_vs_colmap_best") for r in rows},
        "wall_s": time.perf_counter() - t_all,
    }
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1, default=float) + "\n")
    Path(args.output).with_suffix(".partial.json").unlink(missing_ok=True)
    print(table(rows))
    print(f"\nResults: {out}  (wall {result['wall_s']:.0f} s)")


if __name__ == "__main__":
    main()
