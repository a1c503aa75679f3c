"""The partition tree on Dask distributed against the same tree in one process.

Square blocks (``sapgo generate --strips S --photos-per-strip S``, one fixed control point per
25 photos), ordered once for the tree; every run a process of its own (through a bare
interpreter, as shape.py: peak RSS by ``wait4``) on a fresh copy, in interleaved rounds:

- ``threads``: one process, the tree's parts on its 2 threads (the default);
- ``serial``: one process, one thread (``NUMBA_NUM_THREADS=1``, BLAS on one thread);
- ``1 worker`` and ``2 workers``: a LocalCluster of 1 or 2 worker processes (one thread
  each) started by the run (``--workers N``), the tree's parts built, factored,
  back-substituted, updated and inverted on the workers, the top fronts built and factored
  on the workers (tiled across them beyond ``--tile`` rows); the back substitution
  through the top, the top's point update and inversion and the commit on the client.

Recorded per run: seconds per iteration and per phase (build, solve, update a step; order,
precision, total), the bytes the client sent to and received from the workers (the pickled
arguments and results of the tasks, ``sapgo.solve.distributed.TRAFFIC``) per iteration, the
peak RSS of the client and of each worker, sigma0. Medians and (min-max) over the rounds.

Then the scale-out replay (:mod:`sapgo.solve.scaleout`, docs/theory.md section 4d): the
1-worker runs trace every node's seconds and every task's seconds and bytes
(``sapgo.solve.distributed.TRACE``); the iteration as built, replayed with those costs on 1
and 2 workers, is compared with the 1- and 2-worker runs (the validation); the iteration as
designed for many workers (top fronts tiled across them) is replayed for ``--simulate``
workers on two networks, for the measured blocks and for ``--big`` (a square block too
large to generate: its tree by geometric bisection of the measured blocks' station graph,
its nodes' seconds by the cost model fitted to the largest measured block). Also measured
here: the tile kernels' rates on one core and a Dask task's cost to the scheduler.

    python benchmarks/distributed.py [--blocks 200x200[,400x400]] [--rounds 3]
        [--simulate 2,8,32,128] [--big 3163x3163] [--tile 2048]
    python benchmarks/distributed.py --replay-only    # the replay again, same runs

Writes results/distributed.json and prints Markdown tables.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
# this script's folder after the installed packages: its name is Dask's package's name
sys.path = [x for x in sys.path if Path(x or ".").resolve() != HERE] + [str(HERE)]
RESULTS = HERE / "results" / "distributed.json"

import sapgo  # noqa: E402

try:   # (Dask's package, before shape.py puts this folder first on the path)
    import distributed as _dask_distributed  # noqa: E402,F401
except ImportError:
    _dask_distributed = None

CONFIGS = ("threads", "serial", "1 worker", "2 workers")


def child(path, config, tile=None):
    import resource

    from sapgo.solve import distributed as dist

    if tile:
        dist.TOP_TILE = int(tile)

    opts = sapgo.Options(progress=False, solver="tree")
    workers = {"1 worker": 1, "2 workers": 2}.get(config)
    rss_workers = None
    between = 0
    t0 = time.perf_counter()
    if workers:
        with dist.cluster(workers=workers, quiet=True) as c:
            t1 = time.perf_counter()
            dist.TRAFFIC["on"] = True
            dist.TRACE["on"] = workers == 1   # (the replay's input: benchmarks/README.md)
            opts.client = c
            s = sapgo.adjust(path, opts)
            rss_workers = sorted(c.run(lambda: resource.getrusage(
                resource.RUSAGE_SELF).ru_maxrss / 1024.0).values())
            # what the workers sent each other (Dask's own count: the top's tiles and
            # pieces of updates)
            between = sum(c.run(lambda dask_worker: dask_worker.transfer_outgoing_bytes_total
                                ).values())
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
        "bytes_between_workers_per_iteration": between / its,
        "tasks": dist.TRAFFIC["tasks"],
        "worker_peak_rss_mb": rss_workers,
        "trace": ({"nodes": {i: [float(np.median([x[0] for x in v])),
                                 float(np.median([x[1] for x in v]))]
                             for i, v in dist.TRACE["nodes"].items()},
                   "rounds": dist.TRACE["rounds"], "client": dist.TRACE["client"],
                   "plan": dist.TRACE.get("plan")} if dist.TRACE["on"] else None),
    }


def run_child(path, config, tile=None):
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
                               "--child", str(path), config, str(tile or "")],
                              capture_output=True, text=True)
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


# -- the scale-out replay (sapgo.solve.scaleout) ------------------------------------------

#: The networks of the projections: (bytes a second a worker sends, seconds a message).
NETWORKS = {"10 Gbit/s": (1.25e9, 50e-6), "1 Gbit/s": (1.25e8, 100e-6)}


def dask_task_seconds(n=2000):
    """Seconds a task costs the scheduler of a LocalCluster of 2 workers: ``n`` no-op tasks
    submitted at once (throughput) and 100 one after the other (a task's latency)."""
    import dask
    from distributed import Client, LocalCluster

    with dask.config.set({"distributed.scheduler.work-stealing": False}), \
            LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                         dashboard_address=None) as lc, Client(lc) as c:
        c.gather(c.map(abs, range(100)))   # (warm)
        t0 = time.perf_counter()
        c.gather(c.map(abs, range(n), pure=False))
        bulk = (time.perf_counter() - t0) / n
        t0 = time.perf_counter()
        for j in range(100):
            c.submit(abs, -j, pure=False).result()
        one = (time.perf_counter() - t0) / 100
    return {"bulk_s": bulk, "latency_s": one}


def _med(v):
    return float(np.median(v)) if len(v) else 0.0


def merged_nodes(runs):
    """Each node's seconds over the 1-worker runs (their medians over the iterations): the
    medians over the rounds, as ``{"total": [...], "elim": [...]}`` by node (None: a node
    no run traced), rounded to 4 significant digits; the runs' own node lists dropped
    (the result file keeps only these)."""
    nodes = {}
    for r in runs:
        tr = r.get("trace") or {}
        for i, v in (tr.pop("nodes", None) or {}).items():
            nodes.setdefault(int(i), []).append(v)
    n = max(nodes) + 1 if nodes else 0

    def med(i, j):
        v = nodes.get(i)
        return float(f"{_med([x[j] for x in v]):.4g}") if v else None

    return {"total": [med(i, 0) for i in range(n)], "elim": [med(i, 1) for i in range(n)]}


def replay_inputs(runs, nodes):
    """The 1-worker runs' traces as the replay's inputs: each node's seconds (``nodes``,
    :func:`merged_nodes`), each part's task seconds and bytes per round kind, the client's
    seconds, and the overheads (:func:`sapgo.solve.scaleout.built_graph`)."""
    ts = [r for r in runs if "error" not in r and r.get("trace")]
    total = {i: v for i, v in enumerate(nodes["total"]) if v is not None}
    elim = {i: v for i, v in enumerate(nodes["elim"]) if v is not None}
    per, top = ts[0]["trace"]["plan"]
    per = [[tuple(x) for x in ranges] for ranges in per]
    n_parts = len(per)
    part_nodes = [[i for a, b in ranges for i in range(a, b)] for ranges in per]
    kinds = ("step", "back", "update")
    task = {kd: [[] for _ in range(n_parts)] for kd in kinds}
    nbytes = {kd: [([], []) for _ in range(n_parts)] for kd in kinds}
    wall = {kd: [] for kd in kinds}
    client = {"back": [], "update": []}
    for r in ts:
        counts = {kd: 0 for kd in kinds}
        for rd in r["trace"]["rounds"]:
            kd = rd["kind"]
            if kd not in counts:   # (the precision pass's round: not an iteration's)
                continue
            counts[kd] += 1
            for t in rd["tasks"]:
                task[kd][t["part"]].append(t["seconds"])
                nbytes[kd][t["part"]][0].append(t["bytes_in"])
                nbytes[kd][t["part"]][1].append(t["bytes_out"])
            # (one worker: the tasks one after the other)
            wall[kd].append(rd["wall_s"] - sum(t["seconds"] for t in rd["tasks"]))
        for kd in client:
            client[kd].append(r["trace"]["client"].get(kd, 0.0) / max(counts[kd], 1))
    step_task = [_med(x) for x in task["step"]]
    over = {"task": [max(0.0, step_task[w] - sum(total.get(i, 0.0) for i in part_nodes[w]))
                     for w in range(n_parts)],
            **{kd: max(0.0, _med(wall[kd])) for kd in kinds}}
    inp = {"total": total, "elim": elim, "plan": (per, top), "part_nodes": part_nodes,
           "step_task_s": step_task,
           "back_s": [_med(x) for x in task["back"]],
           "update_s": [_med(x) for x in task["update"]],
           "bytes": {kd: [(_med(a), _med(b)) for a, b in nbytes[kd]] for kd in kinds},
           "top_back_s": _med(client["back"]), "top_update_s": _med(client["update"]),
           "overhead": over}
    s_it = _med([r["s_per_iteration"] for r in ts])
    accounted = (step_task and sum(step_task) + over["step"]
                 + sum(total.get(i, 0.0) for i in top) + inp["top_back_s"]
                 + sum(inp["back_s"]) + over["back"] + sum(inp["update_s"]) + over["update"]
                 + inp["top_update_s"])
    over["client"] = max(0.0, s_it - accounted)
    inp["measured_s_per_iteration"] = s_it
    return inp


def _project_costs(tree, k, inp):
    """Per-node seconds for the projections: the traced nodes of the parts as measured, the
    others (the top's) and the back substitution, update and build by the cost model fitted
    to the parts' nodes."""
    from sapgo.solve import scaleout as so

    fig = so.node_figures(tree, k)
    nodes = [i for p in inp["part_nodes"] for i in p if i in inp["total"]]
    model = so.CostModel.fit(fig, nodes, ([inp["total"][i] for i in nodes],
                                          [inp["elim"][i] for i in nodes]),
                             sum(inp["back_s"]), sum(inp["update_s"]))
    step = model.step(fig)
    for i in nodes:
        step[i] = inp["total"][i]
    return model, step, model.back(fig), model.update(fig), model.build(fig)


def _projection(tree, k, costs, rates, task, workers, tile):
    from sapgo.solve import scaleout as so
    from sapgo.solve.tree import parallel_plan

    step, back, update, build = costs
    out = {}
    for w in workers:
        plan = parallel_plan(tree, k, w)
        g = so.tiled_graph(tree, k, w, step, back, update, build, rates, tile,
                           task["bulk_s"], plan=plan)
        per, top = plan
        part_peak = max(tree.peak_front_bytes(k, ([r], []), separate=True)
                        for r in per if r) if w > 1 else tree.peak_front_bytes(k)
        top_share = max((tree.front_bytes(k)[i] / max(1, len(per)) for i in top), default=0)
        for net_name, (bw, lat) in NETWORKS.items():
            r = so.replay(g, so.Network(bw, lat))
            # the tasks Dask would see (a part's nodes are one task of a round), each
            # costing the one scheduler the time measured here
            by = r["tasks_by_kind"]
            dask_tasks = (sum(v for kd, v in by.items() if kd not in ("subtree", "start",
                                                                        "sums"))
                          + sum(1 for x in per if x))
            floor = dask_tasks * task["bulk_s"]
            out[f"{w} workers, {net_name}"] = {
                "workers": w, "network": net_name,
                "s_per_iteration": max(r["seconds"], floor), "replay_s": r["seconds"],
                "scheduler_floor_s": floor, "critical_path_s": r["critical_path_s"],
                "critical_path": r["critical_path"], "work_s": r["work_s"],
                "efficiency": r["work_s"] / (w * max(r["seconds"], floor)),
                "speedup_over_one_core": r["work_s"] / max(r["seconds"], floor),
                "bytes_per_iteration": r["bytes"], "max_bytes_sent_by_a_worker":
                r["max_bytes_sent"], "messages": r["messages"], "tasks": dask_tasks,
                "tasks_by_kind": by,
                "top_nodes": len(top), "fronts_gb_per_worker_about":
                max(part_peak, top_share) / 1e9}
    return out


def _top_tile(tile, k):
    """The rows of a top front's tile as the iteration cuts them (whole stations)."""
    return max(k, k * (tile // k))


def simulate(gen, row, task, rates, tile, workers):
    """The replay of a measured block: validation against its 1- and 2-worker runs, and
    the projections to ``workers`` workers with the tiled top."""
    from sapgo.project import Project
    from sapgo.solve import scaleout as so

    with Project(gen, "r") as p:
        tree = p.tree()
    k = 6
    inp = replay_inputs(row["runs"]["1 worker"], row["trace_nodes"])
    free = so.Network(1e30, 0.0)   # (the bytes' time on one machine: in the overheads)
    valid = {}
    # (a tiled top front: its build as traced, its tiles' kernels at the measured rates)
    build = np.array([inp["total"].get(i, 0.0) - inp["elim"].get(i, 0.0)
                      for i in range(tree.n_nodes)])
    for w in (1, 2):
        g = so.built_graph(tree, inp["plan"], [inp["total"].get(i, 0.0)
                                               for i in range(tree.n_nodes)],
                           inp["back_s"], inp["update_s"], inp["top_update_s"],
                           inp["top_back_s"], inp["overhead"], inp["bytes"], w, k, build,
                           rates, _top_tile(tile, k), task["bulk_s"])
        r = so.replay(g, free)
        meas = row["summary"][f"{w} worker{'s' if w > 1 else ''}"]["s_per_iteration"]
        valid[f"{w} worker{'s' if w > 1 else ''}"] = {
            "predicted_s": r["seconds"], "measured_s": meas["median"] if meas else None,
            "measured_range": [meas["min"], meas["max"]] if meas else None,
            "error": (r["seconds"] / meas["median"] - 1.0) if meas else None}
    model, *costs = _project_costs(tree, k, inp)
    proj = _projection(tree, k, costs, rates, task, workers, tile)
    return {"validation": valid, "model": dataclasses.asdict(model),
            "overheads": inp["overhead"], "projections": proj}, model


def big_block(spec, stencil_from, model, points_per_station, rates, task, workers, tile):
    """The projection of a square block too large to generate: its tree by
    :func:`sapgo.solve.scaleout.grid_tree` on the station graph of a generated block, its
    nodes' seconds by the cost model fitted to a measured block."""
    from sapgo.solve import scaleout as so

    s, p = (int(x) for x in spec.split("x"))
    offsets, spacing = so.stencil(stencil_from)
    t0 = time.perf_counter()
    tree = so.grid_tree(s, p, offsets, spacing)
    t_tree = time.perf_counter() - t0
    own = tree.hi - tree.lo
    tree.pt_start = np.concatenate([[0], np.cumsum(np.round(own * points_per_station))]
                                   ).astype(np.int64)
    k = 6
    fig = so.node_figures(tree, k)
    costs = (model.step(fig), model.back(fig), model.update(fig), model.build(fig))
    out = {"photos": s * p, "tree_seconds": t_tree, "figures": tree.figures(k),
           "offsets": offsets, "points_per_station": points_per_station,
           "projections": _projection(tree, k, costs, rates, task, workers, tile)}
    return out


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--blocks", default="200x200")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--configs", default=",".join(CONFIGS))
    ap.add_argument("--dir", default=None)
    ap.add_argument("--output", default=str(RESULTS))
    ap.add_argument("--child", nargs=3)
    ap.add_argument("--tile", type=int, default=2048,
                    help="rows of a tile of the top fronts (the runs' and the replay's)")
    ap.add_argument("--simulate", default="2,8,32,128",
                    help="workers of the scale-out replay")
    ap.add_argument("--big", default="3163x3163",
                    help="the square block of the projection beyond the measured ones")
    ap.add_argument("--replay-only", action="store_true",
                    help="the replay again from the runs recorded in --output")
    args = ap.parse_args(argv)
    if args.child:
        print("RESULT " + json.dumps(child(*args.child)))
        return
    import shape
    from colmap import git_state

    from sapgo.solve import scaleout

    configs = [c.strip() for c in args.configs.split(",")]
    sim_workers = [int(x) for x in args.simulate.split(",") if x]
    t_all = time.perf_counter()
    if args.replay_only:
        out = json.loads(Path(args.output).read_text())
        args.blocks = ",".join(out["blocks"])
        configs = []
    else:
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
        # the replay's measured inputs besides the runs' traces
        from colmap import wait_for_idle

        wait_for_idle()
        rates = scaleout.kernel_rates(args.tile)
        task = dask_task_seconds()
        out["replay_inputs"] = {"kernel_flops_per_s": rates, "dask_task_s": task,
                                "tile": args.tile, "networks": NETWORKS,
                                "load": shape.load()}
        print(f"kernels at tile {args.tile}: "
              + ", ".join(f"{k} {v / 1e9:.1f} GFlop/s" for k, v in rates.items())
              + f"; a Dask task {task['bulk_s'] * 1e3:.2f} ms (in bulk), "
              f"{task['latency_s'] * 1e3:.2f} ms (alone)", file=sys.stderr)
        gens, model, pps = [], None, None
        for name in args.blocks.split(","):
            spec = shape.block_spec(name)
            gen = tmp / f"{name}.h5"
            info = sapgo.generate_block(gen, progress=False, control_sigma=0.0, **spec)
            sapgo.order_project(gen, solver="tree")
            gens.append(gen)
            pps = info["points"] / info["photos"] if "points" in info else pps
            print(f"\n{name}: {info['photos']} photos", file=sys.stderr)
            if args.replay_only:
                row = out["blocks"][name]
                row["replay"], model = simulate(gen, row, task, rates, args.tile,
                                                sim_workers)
                continue
            runs = {c: [] for c in configs}
            for r in range(args.rounds):
                for c in configs:
                    path = tmp / "run.h5"
                    shutil.copy(gen, path)
                    res = run_child(path, c, args.tile)
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
                    "bytes_between_workers_per_iteration": shape.spread(
                        [x.get("bytes_between_workers_per_iteration", 0) for x in ok]),
                    "sigma0": sorted({x["sigma0"] for x in ok}),
                }
            row = {"block": name, "photos": info["photos"], "runs": runs, "summary": summary}
            s1, s2 = summary.get("1 worker"), summary.get("2 workers")
            if s1 and s2 and s1["solve_per_iteration_s"] and s2["solve_per_iteration_s"]:
                row["solve_speedup_2_vs_1_worker"] = (s1["solve_per_iteration_s"]["median"] /
                                                      s2["solve_per_iteration_s"]["median"])
                row["iteration_speedup_2_vs_1_worker"] = (s1["s_per_iteration"]["median"] /
                                                          s2["s_per_iteration"]["median"])
            if runs.get("1 worker") and any(r.get("trace") for r in runs["1 worker"]):
                row["trace_nodes"] = merged_nodes(runs["1 worker"])
                row["replay"], model = simulate(gen, row, task, rates, args.tile,
                                                sim_workers)
            out["blocks"][name] = row
        if model is not None and args.big:
            print(f"\n{args.big}: the tree of the generated blocks' station graph",
                  file=sys.stderr)
            out["big"] = big_block(args.big, gens[0], model, pps, rates, task, sim_workers,
                                   args.tile)
    out["replay_wall_s" if args.replay_only else "wall_s"] = time.perf_counter() - t_all
    out["machine"]["load_at_end"] = shape.load()
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    Path(args.output).write_text(dumps(out))
    print(table(out))
    wall = out["replay_wall_s" if args.replay_only else "wall_s"]
    print(f"\nResults: {args.output}  (wall {wall:.0f} s)")


def dumps(out):
    """The results as indented JSON with lists of numbers on one line each (the traces)."""
    import re

    text = json.dumps(out, indent=1)
    return re.sub(r"\[\s*((?:-?[\d.e+-]+|null)(?:,\s*(?:-?[\d.e+-]+|null))*)\s*\]",
                  lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]",
                  text) + "\n"


def table(out):
    def rng(s, nd=2):
        if not s:
            return ""
        return f"{s['median']:.{nd}f} ({s['min']:.{nd}f}-{s['max']:.{nd}f})"

    lines = ["| block | run | s/iteration | build / solve / update s a step | to solution s "
             "| precision s | MB to / from / between workers an iteration | peak RSS MB "
             "client; workers | sigma0 |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, row in out["blocks"].items():
        for c, s in row["summary"].items():
            if not s["s_per_iteration"]:
                continue
            to, fr = s["bytes_to_workers_per_iteration"], s["bytes_from_workers_per_iteration"]
            bw = s.get("bytes_between_workers_per_iteration")
            wr = [w for w in s["worker_peak_rss_mb"] if w]
            lines.append(
                f"| {name} | {c} | {rng(s['s_per_iteration'])} | "
                f"{s['build_per_iteration_s']['median']:.2f} / "
                f"{s['solve_per_iteration_s']['median']:.2f} / "
                f"{s['update_per_iteration_s']['median']:.2f} | "
                f"{rng(s['time_to_solution_s'], 1)} | {rng(s['precision_s'])} | "
                f"{(to['median'] / 1e6 if to else 0):.1f} / {(fr['median'] / 1e6 if fr else 0):.1f}"
                f" / {(bw['median'] / 1e6 if bw else 0):.1f} | "
                f"{s['client_peak_rss_mb']['median']:.0f}; "
                f"{', '.join(f'{x:.0f}' for x in wr[-1]) if wr else ''} | "
                f"{s['sigma0'][0]:.10f}{' (+%d)' % (len(s['sigma0']) - 1) if len(s['sigma0']) > 1 else ''} |")
        if "solve_speedup_2_vs_1_worker" in row:
            lines.append(f"\n{name}: 2 workers against 1, solve {row['solve_speedup_2_vs_1_worker']:.2f}x,"
                         f" iteration {row['iteration_speedup_2_vs_1_worker']:.2f}x")
    lines.append(replay_table(out))
    return "\n".join(lines)


def replay_table(out):
    """The replay's validation and projections as Markdown."""
    rows = [(name, row["replay"]) for name, row in out["blocks"].items() if "replay" in row]
    if not rows:
        return ""
    inp = out.get("replay_inputs", {})
    lines = ["", "Replay of the 1-worker runs' traces (the iteration as built: parts on the "
             "workers, the top fronts on the workers too):", "",
             "| block | run | replayed s/iteration | measured s/iteration | error |",
             "|---|---|---|---|---|"]
    for name, rp in rows:
        for run, v in rp["validation"].items():
            if v["measured_s"] is None:
                continue
            lines.append(f"| {name} | {run} | {v['predicted_s']:.2f} | {v['measured_s']:.2f} "
                         f"({v['measured_range'][0]:.2f}-{v['measured_range'][1]:.2f}) | "
                         f"{100 * v['error']:+.1f} % |")
    rates = inp.get("kernel_flops_per_s", {})
    lines += ["", f"Projections (the top fronts tiled across the workers, tiles of "
              f"{inp.get('tile')} rows; one core a worker; kernels "
              + ", ".join(f"{k} {v / 1e9:.1f}" for k, v in rates.items())
              + f" GFlop/s; a Dask task {inp.get('dask_task_s', {}).get('bulk_s', 0) * 1e3:.2f}"
              " ms of the scheduler's time):", "",
              "| block | workers | network | s/iteration | replay s; scheduler's s | "
              "critical path s | efficiency | speedup over 1 core | GB sent an iteration | "
              "Dask tasks | fronts GB a worker |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    proj = [(name, rp["projections"]) for name, rp in rows]
    if "big" in out:
        proj.append((f"{out['big']['photos']:,} photos (model)".replace(",", " "),
                     out["big"]["projections"]))
    for name, pr in proj:
        for v in pr.values():
            lines.append(f"| {name} | {v['workers']} | {v['network']} | "
                         f"{v['s_per_iteration']:.1f} | {v['replay_s']:.1f}; "
                         f"{v['scheduler_floor_s']:.1f} | {v['critical_path_s']:.1f} | "
                         f"{v['efficiency']:.2f} | {v['speedup_over_one_core']:.1f} | "
                         f"{v['bytes_per_iteration'] / 1e9:.2f} | {v['tasks']} | "
                         f"{v['fronts_gb_per_worker_about']:.2f} |")
    if "big" in out:
        f = out["big"]["figures"]
        lines.append(f"\n{out['big']['photos']} photos: tree of {f['nodes']} nodes, depth "
                     f"{f['depth']}, largest front {f['largest_front']} stations, "
                     f"{f['flops'] / 1e12:.0f} TFlop, factor {f['factor_bytes'] / 1e9:.0f} GB "
                     f"(tree built in {out['big']['tree_seconds']:.0f} s)")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
