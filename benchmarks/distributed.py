"""The partition tree on Dask distributed against the same tree in one process.

Square blocks (``sapgo generate --strips S --photos-per-strip S``, one fixed control point per
25 photos), ordered once for the tree; every run a process of its own (through a bare
interpreter, as shape.py: peak RSS by ``wait4``) on a fresh copy, in interleaved rounds:

- ``threads``: one process, the tree's parts on its 2 threads (the default);
- ``serial``: one process, one thread (``NUMBA_NUM_THREADS=1``, BLAS on one thread);
- ``1 worker`` and ``2 workers``: a LocalCluster of 1 or 2 worker processes (one thread
  each) started by the run (``--workers N``), the tree's parts built, factored,
  back-substituted and updated on the workers, the top nodes, the precision pass and the
  commit on the client.

Recorded per run: seconds per iteration and per phase (build, solve, update a step; order,
precision, total), the bytes the client sent to and received from the workers (the pickled
arguments and results of the tasks, ``sapgo.solve.distributed.TRAFFIC``) per iteration, the
peak RSS of the client and of each worker, sigma0. Medians and (min-max) over the rounds.

    python benchmarks/distributed.py [--blocks 200x200[,400x400]] [--rounds 3]

Writes results/distributed.json and prints a Markdown table.
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
# this script's folder after the installed packages: its name is Dask's package's name
sys.path = [x for x in sys.path if Path(x or ".").resolve() != HERE] + [str(HERE)]
RESULTS = HERE / "results" / "distributed.json"

import sapgo  # noqa: E402

CONFIGS = ("threads", "serial", "1 worker", "2 workers")


def child(path, config):
    import resource

    from sapgo.solve import distributed as dist

    opts = sapgo.Options(progress=False, solver="tree")
    workers = {"1 worker": 1, "2 workers": 2}.get(config)
    rss_workers = None
    t0 = time.perf_counter()
    if workers:
        with dist.cluster(workers=workers, quiet=True) as c:
            t1 = time.perf_counter()
            dist.TRAFFIC["on"] = True
            opts.client = c
            s = sapgo.adjust(path, opts)
            rss_workers = sorted(c.run(lambda: resource.getrusage(
                resource.RUSAGE_SELF).ru_maxrss / 1024.0).values())
    else:
        t1 = t0
        s = sapgo.adjust(path, opts)
    wall = time.perf_counter() - t1
    t = s.timings_s
    its = max(s.iterations, 1)
    return {
        "sigma0": s.sigma0, "iterations": s.iterations,
        "cluster_start_s": t1 - t0, "time_to_solution_s": wall,
        "s_per_iteration": (t["build"] + t["solve"] + t["update"]) / its,
        "per_iteration_s": {k: t[k] / its for k in ("build", "solve", "update")},
        "phases_s": {k: round(v, 4) for k, v in t.items()},
        "bytes_to_workers_per_iteration": dist.TRAFFIC["to_workers"] / its if workers else 0,
        "bytes_from_workers_per_iteration": (dist.TRAFFIC["from_workers"] / its
                                             if workers else 0),
        "tasks": dist.TRAFFIC["tasks"],
        "worker_peak_rss_mb": rss_workers,
    }


def run_child(path, config):
    import shape

    env_one = config == "serial"
    old = dict(os.environ)
    if env_one:
        os.environ.update(NUMBA_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    try:
        from colmap import cpu_snapshot, foreign_cpu_s, wait_for_idle  # noqa: F401
        import subprocess
        import resource

        from scale import LAUNCH

        waited = wait_for_idle()
        before = shape.load()
        c0 = cpu_snapshot()
        ch0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        proc = subprocess.run([sys.executable, "-S", "-c", LAUNCH, sys.executable, __file__,
                               "--child", str(path), config], capture_output=True, text=True)
        ch1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    finally:
        os.environ.clear()
        os.environ.update(old)
    own = (ch1.ru_utime + ch1.ru_stime) - (ch0.ru_utime + ch0.ru_stime)
    line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")]
    if proc.returncode != 0 or not line:
        return {"error": (proc.stderr or proc.stdout)[-2000:]}
    r = json.loads(line[-1][7:])
    launch = [x for x in proc.stderr.splitlines() if x.startswith("LAUNCH ")]
    if launch:
        r["client_peak_rss_mb"] = int(launch[-1].split()[2]) / 1024.0
    r.update(load_before=before, foreign_cpu_s=max(0.0, foreign_cpu_s(c0) - own),
             waited_for_idle_s=waited)
    return r


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--blocks", default="200x200")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument("--dir", default=None)
    ap.add_argument("--output", default=str(RESULTS))
    ap.add_argument("--child", nargs=2)
    args = ap.parse_args(argv)
    if args.child:
        print("RESULT " + json.dumps(child(*args.child)))
        return
    import shape
    from colmap import git_state

    configs = [c.strip() for c in args.configs.split(",")]
    t_all = time.perf_counter()
    out = {"benchmark": "the partition tree on Dask distributed against one process",
           "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                       "platform": platform.platform()},
           "sapgo_version": sapgo.__version__, "sapgo_source": git_state(),
           "rounds": args.rounds, "blocks": {}}
    with tempfile.TemporaryDirectory(dir=args.dir, prefix="sapgo-dist-") as tmp:
        tmp = Path(tmp)
        warm = tmp / "warm.h5"   # the kernels compiled or loaded outside the timed runs
        sapgo.generate_block(warm, strips=12, photos_per_strip=12, control_points=8,
                             progress=False)
        sapgo.adjust(warm, sapgo.Options(progress=False, solver="tree"))
        for name in args.blocks.split(","):
            spec = shape.block_spec(name)
            gen = tmp / f"{name}.h5"
            info = sapgo.generate_block(gen, progress=False, control_sigma=0.0, **spec)
            sapgo.order_project(gen, solver="tree")
            print(f"\n{name}: {info['photos']} photos", file=sys.stderr)
            runs = {c: [] for c in configs}
            for r in range(args.rounds):
                for c in configs:
                    path = tmp / "run.h5"
                    shutil.copy(gen, path)
                    res = run_child(path, c)
                    shutil.rmtree(path.with_name(path.name + ".work"), ignore_errors=True)
                    path.unlink(missing_ok=True)
                    runs[c].append(res)
                    brief = {k: (round(res[k], 3) if isinstance(res.get(k), float) else res.get(k))
                             for k in ("s_per_iteration", "time_to_solution_s", "error")
                             if k in res}
                    print(f"  round {r} {c}: {brief}", file=sys.stderr)
            summary = {}
            for c, rs in runs.items():
                ok = [x for x in rs if "error" not in x]
                summary[c] = {
                    "s_per_iteration": shape.spread([x["s_per_iteration"] for x in ok]),
                    "solve_per_iteration_s": shape.spread(
                        [x["per_iteration_s"]["solve"] for x in ok]),
                    "build_per_iteration_s": shape.spread(
                        [x["per_iteration_s"]["build"] for x in ok]),
                    "update_per_iteration_s": shape.spread(
                        [x["per_iteration_s"]["update"] for x in ok]),
                    "time_to_solution_s": shape.spread([x["time_to_solution_s"] for x in ok]),
                    "precision_s": shape.spread([x["phases_s"].get("precision") for x in ok]),
                    "client_peak_rss_mb": shape.spread([x.get("client_peak_rss_mb")
                                                        for x in ok]),
                    "worker_peak_rss_mb": [x["worker_peak_rss_mb"] for x in ok],
                    "bytes_to_workers_per_iteration": shape.spread(
                        [x["bytes_to_workers_per_iteration"] for x in ok]),
                    "bytes_from_workers_per_iteration": shape.spread(
                        [x["bytes_from_workers_per_iteration"] for x in ok]),
                    "sigma0": sorted({x["sigma0"] for x in ok}),
                }
            row = {"block": name, "photos": info["photos"], "runs": runs, "summary": summary}
            s1, s2 = summary.get("1 worker"), summary.get("2 workers")
            if s1 and s2 and s1["solve_per_iteration_s"] and s2["solve_per_iteration_s"]:
                row["solve_speedup_2_vs_1_worker"] = (s1["solve_per_iteration_s"]["median"] /
                                                      s2["solve_per_iteration_s"]["median"])
                row["iteration_speedup_2_vs_1_worker"] = (s1["s_per_iteration"]["median"] /
                                                          s2["s_per_iteration"]["median"])
            out["blocks"][name] = row
    out["wall_s"] = time.perf_counter() - t_all
    out["machine"]["load_at_end"] = shape.load()
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    Path(args.output).write_text(json.dumps(out, indent=1) + "\n")
    print(table(out))
    print(f"\nResults: {args.output}  (wall {out['wall_s']:.0f} s)")


def table(out):
    def rng(s, nd=2):
        if not s:
            return ""
        return f"{s['median']:.{nd}f} ({s['min']:.{nd}f}-{s['max']:.{nd}f})"

    lines = ["| block | run | s/iteration | build / solve / update s a step | to solution s "
             "| precision s | MB to / from workers an iteration | peak RSS MB client; "
             "workers | sigma0 |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, row in out["blocks"].items():
        for c, s in row["summary"].items():
            if not s["s_per_iteration"]:
                continue
            to, fr = s["bytes_to_workers_per_iteration"], s["bytes_from_workers_per_iteration"]
            wr = [w for w in s["worker_peak_rss_mb"] if w]
            lines.append(
                f"| {name} | {c} | {rng(s['s_per_iteration'])} | "
                f"{s['build_per_iteration_s']['median']:.2f} / "
                f"{s['solve_per_iteration_s']['median']:.2f} / "
                f"{s['update_per_iteration_s']['median']:.2f} | "
                f"{rng(s['time_to_solution_s'], 1)} | {rng(s['precision_s'])} | "
                f"{(to['median'] / 1e6 if to else 0):.1f} / {(fr['median'] / 1e6 if fr else 0):.1f} | "
                f"{s['client_peak_rss_mb']['median']:.0f}; "
                f"{', '.join(f'{x:.0f}' for x in wr[-1]) if wr else ''} | "
                f"{s['sigma0'][0]:.10f}{' (+%d)' % (len(s['sigma0']) - 1) if len(s['sigma0']) > 1 else ''} |")
        if "solve_speedup_2_vs_1_worker" in row:
            lines.append(f"\n{name}: 2 workers against 1, solve {row['solve_speedup_2_vs_1_worker']:.2f}x,"
                         f" iteration {row['iteration_speedup_2_vs_1_worker']:.2f}x")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
