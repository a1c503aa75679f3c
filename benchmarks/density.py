"""Realistic tie-point density: blocks of 100 and 300 points a photo, sapgo against COLMAP.

Run:  python benchmarks/density.py [--blocks 10000x100,10000x300,100000x100,100000x300]
      [--rounds 3] [--colmap-max-observations 4000000] [--dir DIR]

Blocks: ``sapgo generate --strips 20 --photos-per-strip P --points-per-photo N`` (tie points
from a random texture, each measured on every photo that covers it; one *fixed* full control
point per 25 photos, the other points check points), ``PHOTOSxN`` in ``--blocks``. Each run is
a process of its own on a fresh copy of the unordered file, started from a bare interpreter
(benchmarks/shape.py's children): sapgo (``sapgo.adjust``, its solver chosen by predicted
cost, the band on these strips; the ordering and the precision pass included) and COLMAP's
bundle adjuster in its best configuration (sparse Schur, CHOLMOD, initial trust radius
1e16) on the same block, taking turns in each round; medians and (min-max) over the rounds.
COLMAP is left out of blocks with more than ``--colmap-max-observations`` observations (its
Python set-up of a reconstruction of that size alone takes minutes).

Build throughput, observations per second of one iteration:

- sapgo: the observations over the build's seconds per iteration (the collinearity
  equations linearised, the points' normals, their elimination and the reduced matrix's
  assembly, by point);
- COLMAP: the observations times the Jacobian evaluations over Ceres' Jacobian evaluation
  time (the residuals and Jacobians alone: Ceres eliminates the points inside its linear
  solver, whose time is given beside it).

Writes ``results/density.json`` and prints the table for benchmarks/README.md.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import sapgo  # noqa: E402
from shape import load, run_child, spread  # noqa: E402

STRIPS = 20
RESULTS = HERE / "results" / "density.json"
COLMAP_BEST = "SPARSE_SCHUR (SuiteSparse), initial trust radius 1e16"


def make_block(name, workdir):
    photos, per = (int(x) for x in name.split("x"))
    path = workdir / f"d{name}.h5"
    t0 = time.perf_counter()
    info = sapgo.generate_block(path, strips=STRIPS, photos_per_strip=photos // STRIPS,
                                points_per_photo=per, control_points=max(4, photos // 25),
                                control_sigma=0.0, progress=False)
    info["generate_s"] = time.perf_counter() - t0
    info["bytes"] = path.stat().st_size
    return path, info


def sapgo_figures(r, n_obs):
    if "error" in r:
        return r
    build = r["phases_per_iteration_s"]["build"]
    r["build_observations_per_s"] = n_obs / build if build > 0 else None
    return r


def colmap_figures(r, n_obs):
    if "error" in r:
        return r
    jac = r.get("ceres_jacobian_evaluation_s") or 0.0
    r["build_observations_per_s"] = (n_obs * r["jacobian_evaluations"] / jac) if jac else None
    r["linear_solver_s_per_iteration"] = r["ceres_linear_solver_s"] / max(r["iterations"], 1)
    return r


def bench_block(name, workdir, rounds, colmap_max):
    src, info = make_block(name, workdir)
    n_obs = info["observations"]
    tools = ["sapgo"] + (["colmap best"] if n_obs <= colmap_max else [])
    runs = {t: [] for t in tools}
    for r in range(rounds):
        for tool in tools:
            path = workdir / "run.h5"
            shutil.copy(src, path)
            if tool == "sapgo":
                res = sapgo_figures(run_child("sapgo", path, "auto"), n_obs)
            else:
                res = colmap_figures(run_child("colmap", path, COLMAP_BEST), n_obs)
            res["round"] = r
            runs[tool].append(res)
            print(json.dumps({"block": name, "tool": tool, "round": r,
                              **{k: res.get(k) for k in ("time_to_solution_s",
                                                         "s_per_iteration",
                                                         "build_observations_per_s",
                                                         "peak_rss_mb", "error")}}),
                  file=sys.stderr)
            for f in workdir.glob("run.h5*"):
                shutil.rmtree(f, ignore_errors=True) if f.is_dir() else f.unlink()
    src.unlink()
    summary = {}
    for tool, rs in runs.items():
        ok = [x for x in rs if "error" not in x]
        summary[tool] = {k: spread([x.get(k) for x in ok]) for k in (
            "s_per_iteration", "time_to_solution_s", "time_to_solution_without_precision_s",
            "build_observations_per_s", "peak_rss_mb", "iterations",
            "linear_solver_s_per_iteration")}
        if tool == "sapgo":
            summary[tool]["build_s_per_iteration"] = spread(
                [x["phases_per_iteration_s"]["build"] for x in ok])
    return {"block": name, "generated": info, "runs": runs, "summary": summary}


def fmt(s, nd=2, scale=1.0):
    if not s:
        return ""
    return (f"{s['median'] * scale:.{nd}f} ({s['min'] * scale:.{nd}f}-"
            f"{s['max'] * scale:.{nd}f})")


def table(rows):
    out = ["| block (photos x points a photo) | observations | tool | s/iteration | to solution s "
           "| without precision s | build, million obs/s | COLMAP linear solver s/iteration "
           "| peak RSS MB | iterations |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        for tool, s in row["summary"].items():
            out.append(
                f"| {row['block']} | {row['generated']['observations']} | {tool} "
                f"| {fmt(s['s_per_iteration'], 3)} | {fmt(s['time_to_solution_s'])} "
                f"| {fmt(s['time_to_solution_without_precision_s'])} "
                f"| {fmt(s['build_observations_per_s'], 2, 1e-6)} "
                f"| {fmt(s['linear_solver_s_per_iteration'], 3)} "
                f"| {fmt(s['peak_rss_mb'], 0)} "
                f"| {fmt(s['iterations'], 0)} |")
    return "\n".join(out)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--blocks", default="10000x100,10000x300,100000x100,100000x300")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--colmap-max-observations", type=int, default=4_000_000)
    ap.add_argument("--dir", default=None)
    ap.add_argument("--output", default=str(RESULTS))
    args = ap.parse_args(argv)
    from colmap import git_state

    t_all = time.perf_counter()
    load_start = load()
    rows = []
    with tempfile.TemporaryDirectory(dir=args.dir, prefix="sapgo-density-") as tmp:
        workdir = Path(tmp)
        warm = workdir / "warm.h5"   # compile or load the kernels outside the timed runs
        sapgo.generate_block(warm, strips=4, photos_per_strip=10, points_per_photo=50,
                             control_points=6, progress=False)
        sapgo.adjust(warm, sapgo.Options(progress=False))
        # each child's own warm-up block (shape.py's warm_path): fixed control, as the blocks
        sapgo.generate_block(workdir / "warm0.h5", strips=12, photos_per_strip=12,
                             control_points=8, control_sigma=0.0, progress=False)
        for name in args.blocks.split(","):
            rows.append(bench_block(name, workdir, args.rounds, args.colmap_max_observations))
    failed = [(r["block"], tool) for r in rows for tool, rs in r["runs"].items()
              for run in rs if run.get("error")]
    if failed:   # (the recorded results stay as they were)
        raise SystemExit(f"density.py: {len(failed)} runs failed (first: {failed[0]}); "
                         f"{args.output} not written")
    result = {
        "benchmark": "realistic tie-point density: sapgo against COLMAP best",
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "platform": platform.platform(), "load_at_start": load_start,
                    "load_at_end": load()},
        "sapgo_version": sapgo.__version__, "sapgo_source": git_state(),
        "rounds": args.rounds, "blocks": {r["block"]: r for r in rows},
        "wall_s": time.perf_counter() - t_all,
    }
    out = Path(args.output)
    out.write_text(json.dumps(result, indent=1, default=float) + "\n")
    print(table(rows))
    print(f"\nResults: {out}  (wall {result['wall_s']:.0f} s, load average at start "
          f"{load_start}, at end {result['machine']['load_at_end']})")


if __name__ == "__main__":
    main()
