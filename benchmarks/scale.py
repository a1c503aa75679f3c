"""Out of core at scale: 10 000 to 1 000 000 photos on this machine, memory bounded.

Run:  python benchmarks/scale.py [--sizes 10000,20000,100000,200000,1000000] [--dir DIR]
      [--solution-sizes 10000,100000]

Every block has 20 strips and the 9-point pattern (SAPGO-P geometry), one full control point
per 25 photos on the strip boundary rows, the rest check points. Each phase runs as its own
process through the command line, as a user would run it: ``sapgo generate``, ``sapgo order
--memory 256M`` and ``sapgo adjust --max-iterations 1``. Per phase: wall time, and the peak
resident set size of the whole process as the operating system measures it (``ru_maxrss``
from ``wait4``). Disk: the project file and the work directory at its fullest (``--keep-
scratch``, then removed).
For the sizes in ``--solution-sizes`` the block is also adjusted to convergence (time to
solution). The memory growth per photo is the difference of the adjust processes' peak RSS
between 20 000 and 200 000 photos and between 100 000 and 1 000 000 photos.

Writes ``results/scale.json`` (``rows``: ``photos``, ``peak_rss_mb``, ``wall_s``,
``band_width`` and the details) and prints the Markdown table for README.md.

The band's factor in a file or replayed (issue 20, item 5)::

    python benchmarks/scale.py --storage 1000000 [--rounds 3] [--dir DIR]

One block of 20 strips generated and ordered (each a process of its own, as above), then
``sapgo adjust`` to convergence with the precision pass, ``--factor-storage file`` and
``--factor-storage replay`` taking turns on fresh copies, ``--rounds`` times: per run the
wall time, each phase (build, solve, update per iteration; precision), peak RSS and the work
directory at its fullest (``--keep-scratch``); medians and (min-max) over the rounds, the
load average before each run. Writes ``results/scale_storage.json`` and prints its table.

Ten million photos on this machine (issue 20, item 5)::

    python benchmarks/scale.py --huge 10000000 [--dir DIR]

One block of 20 strips: ``sapgo generate``, ``sapgo order --memory 256M`` and ``sapgo
adjust`` to convergence with the precision pass (``--keep-scratch``), each a process of its
own as above, with defaults everywhere (the factor storage and the paging of per-photo
vectors as ``auto`` chooses them). Per phase: wall time, peak RSS and the disk it took at
most (free space sampled every second: project copies, sort runs, work files and the
unlinked ``paged.*`` files together). Writes ``huge`` into ``results/scale.json`` (its other
rows are kept) and prints its table. ``--huge-phases generate,order`` measures those two
again (each phase records its commit) and keeps the adjustment's record.

Square blocks (the partition tree, issue 16)::

    python benchmarks/scale.py --squares 200,500,1000 [--dir DIR]

``S x S`` photos (9-point pattern, one full control point per 25 photos), each phase a
process of its own as above: ``sapgo generate``, ``sapgo order --memory 256M`` (the solver
chosen by predicted cost: the tree) and ``sapgo adjust`` to convergence with the precision
pass (``--keep-scratch``: the work directory's size at its fullest). A block the adjustment
refuses (its fronts do not fit the memory budget) is recorded with the refusal and the tree's
figures (``sapgo info --json``): where it stops and why. Writes
``results/scale_square.json`` and prints its table.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

import sapgo

STRIPS = 20
PHOTOS_PER_CONTROL_POINT = 25  # 400 full control points per 10 000 photos


#: Starts the measured process from a bare interpreter: on Linux a child's ``ru_maxrss``
#: starts from the RSS of the process it was forked from, so forking from this script (numpy,
#: h5py, sapgo loaded) would floor every figure at this script's own size.
LAUNCH = (
    "import os, sys\n"
    "pid = os.fork()\n"
    "if pid == 0:\n"
    "    os.execvp(sys.argv[1], sys.argv[1:])\n"
    "_, status, usage = os.wait4(pid, 0)\n"
    "sys.stderr.write(f'\\nLAUNCH {os.waitstatus_to_exitcode(status)} {usage.ru_maxrss}\\n')\n"
    "sys.exit(os.waitstatus_to_exitcode(status))\n"
)


def run(cmd):
    """Run ``cmd``; return (wall seconds, peak RSS MiB of the process, stdout) or raise.

    Output goes to temporary files, not pipes, so a talkative process cannot block.
    """
    import tempfile

    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        code = subprocess.call([sys.executable, "-S", "-c", LAUNCH, *cmd], stdout=out,
                               stderr=err)
        wall = time.perf_counter() - t0
        out.seek(0)
        err.seek(0)
        text, errors = out.read().decode(), err.read().decode()
    if code != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed ({code}): {errors}")
    maxrss_kb = int(errors.rsplit("LAUNCH ", 1)[1].split()[1])
    return wall, maxrss_kb / 1024.0, text


class DiskWatch:
    """The least free space on ``path``'s file system while the block runs (sampled every
    ``period`` s on a thread): ``used()`` is the most the process took beyond the start."""

    def __init__(self, path, period=1.0):
        import threading

        self.path, self.period = str(path), period
        self.start_free = self.min_free = shutil.disk_usage(self.path).free
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self):
        while not self._stop.wait(self.period):
            self.min_free = min(self.min_free, shutil.disk_usage(self.path).free)

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.min_free = min(self.min_free, shutil.disk_usage(self.path).free)

    def used(self):
        return self.start_free - self.min_free


def du(path):
    """Bytes allocated on disk (sparse files count what they use)."""
    path = Path(path)
    if path.is_file():
        return path.stat().st_blocks * 512
    return sum(p.stat().st_blocks * 512 for p in path.rglob("*") if p.is_file())


SAPGO = [sys.executable, "-m", "sapgo.cli"]


def generate_and_order(strips, per_strip, path):
    """``sapgo generate`` and ``sapgo order --memory 256M`` of a block, each a process of
    its own: the row so far, the phases' (wall s, peak RSS MB) and order's output."""
    photos = strips * per_strip
    row = {"photos": photos, "strips": strips, "photos_per_strip": per_strip, "pattern": 9}
    t_gen, rss_gen, _ = run(SAPGO + ["generate", "--strips", str(strips),
                                     "--photos-per-strip", str(per_strip), "--control-points",
                                     str(photos // PHOTOS_PER_CONTROL_POINT), str(path)])
    t_ord, rss_ord, out = run(SAPGO + ["order", "--memory", "256M", str(path)])
    row["project_bytes"] = du(path)
    return row, (t_gen, rss_gen), (t_ord, rss_ord), out


def one(photos, root, to_solution):
    sapgo_cmd = SAPGO
    g = photos // STRIPS
    path = Path(root) / f"scale-{photos}.h5"
    row, (t_gen, rss_gen), (t_ord, rss_ord), _ = generate_and_order(STRIPS, g, path)
    with sapgo.open_project(path) as p:
        row.update(points=p.n_points, observations=p.n_observations,
                   band_width=p.band_width)
    keep = path.with_name(path.name + ".pristine")
    if to_solution:
        shutil.copy(path, keep)
    report = Path(root) / f"scale-{photos}.json"
    t_adj, rss_adj, _ = run(sapgo_cmd + ["adjust", str(path), "--max-iterations", "1",
                                         "--no-progress", "--quiet", "--keep-scratch",
                                         "--json", str(report)])
    work = path.with_name(path.name + ".work")
    row["work_bytes"] = du(work)
    shutil.rmtree(work, ignore_errors=True)
    rep = json.loads(report.read_text())
    t = rep["timings_s"]
    row["phases"] = {
        "generate": {"wall_s": t_gen, "peak_rss_mb": rss_gen},
        "order": {"wall_s": t_ord, "peak_rss_mb": rss_ord},
        "adjust_1_iteration": {"wall_s": t_adj, "peak_rss_mb": rss_adj,
                               "build_s": t["build"], "solve_s": t["solve"],
                               "update_s": t["update"], "commit_s": t.get("commit", 0.0)},
    }
    row["peak_rss_mb"] = rss_adj
    row["peak_rss_mb_any_phase"] = max(rss_gen, rss_ord, rss_adj)
    row["wall_s"] = t_gen + t_ord + t_adj
    row["sigma0_after_1_iteration"] = rep["sigma0"]
    if to_solution:
        shutil.move(keep, path)
        t_sol, rss_sol, _ = run(sapgo_cmd + ["adjust", str(path), "--no-progress", "--quiet",
                                             "--json", str(report)])
        rep = json.loads(report.read_text())
        c = rep["check_points"]
        row["solution"] = {"wall_s": t_sol, "peak_rss_mb": rss_sol,
                           "iterations": rep["iterations"], "converged": rep["converged"],
                           "sigma0": rep["sigma0"], "check_sxy_m": c["sxy"],
                           "check_sz_m": c["sz"],
                           "seconds_per_iteration": rep["timings_per_iteration_s"]}
    path.unlink()
    report.unlink()
    return row


def one_square(side, root, memory=None):
    """Generate, order and adjust (to convergence, with precision) a side x side block;
    ``memory``: ``sapgo adjust --memory`` (default sapgo's own budget, 1 GiB)."""
    sapgo_cmd = SAPGO
    path = Path(root) / f"square-{side}.h5"
    row, (t_gen, rss_gen), (t_ord, rss_ord), out = generate_and_order(side, side, path)
    row["order_output"] = out.strip().splitlines()[-3:]
    _, _, info = run(sapgo_cmd + ["info", str(path), "--json"])
    info = json.loads(info)
    row.update(points=info["points"], observations=info["observations"],
               solver=info["solver"], tree=info["tree"])
    row["phases"] = {"generate": {"wall_s": t_gen, "peak_rss_mb": rss_gen},
                     "order": {"wall_s": t_ord, "peak_rss_mb": rss_ord}}
    row["memory"] = memory
    report = Path(root) / f"square-{side}.json"
    try:
        t_adj, rss_adj, _ = run(sapgo_cmd + ["adjust", str(path), "--no-progress", "--quiet",
                                             "--keep-scratch", "--json", str(report)]
                                + (["--memory", memory] if memory else []))
    except RuntimeError as exc:   # refused or failed: where it stops, and why
        lines = [x[x.index("sapgo: error:"):] for x in str(exc).splitlines()
                 if "sapgo: error:" in x]
        row["stopped"] = (lines[-1] if lines else str(exc).strip())[-1000:]
        path.unlink(missing_ok=True)
        return row
    work = path.with_name(path.name + ".work")
    row["work_bytes"] = du(work)
    shutil.rmtree(work, ignore_errors=True)
    rep = json.loads(report.read_text())
    t = rep["timings_s"]
    c = rep["check_points"]
    row["phases"]["adjust"] = {"wall_s": t_adj, "peak_rss_mb": rss_adj,
                               **{f"{k}_s": v for k, v in t.items()}}
    row.update(iterations=rep["iterations"], converged=rep["converged"], sigma0=rep["sigma0"],
               check_sxy_m=c["sxy"], check_sz_m=c["sz"], peak_rss_mb=rss_adj,
               seconds_per_iteration=sum(rep["timings_per_iteration_s"].values()))
    path.unlink()
    report.unlink()
    return row


def storage(args):
    """``--storage N``: the factor file against the replay on one block (module docstring)."""
    import statistics

    sys.path.insert(0, str(Path(__file__).parent))
    from colmap import git_state
    from shape import load

    n = int(args.storage)
    root = Path(args.dir or Path(__file__).parent.parent / "data" / "generated" / "scale")
    root.mkdir(parents=True, exist_ok=True)
    warm = root / "warm.h5"   # compile or load the kernels outside the measured runs
    sapgo.generate_block(warm, strips=2, photos_per_strip=5, control_points=6, progress=False)
    sapgo.adjust(warm, sapgo.Options(progress=False, factor_storage="replay"))
    warm.unlink()
    path = root / f"storage-{n}.h5"
    row, gen, order, _ = generate_and_order(STRIPS, n // STRIPS, path)
    with sapgo.open_project(path) as p:
        row.update(points=p.n_points, observations=p.n_observations, band_width=p.band_width)
    row["phases"] = {"generate": {"wall_s": gen[0], "peak_rss_mb": gen[1]},
                     "order": {"wall_s": order[0], "peak_rss_mb": order[1]}}
    runs = []
    for r in range(args.rounds):
        for mode in ("file", "replay"):
            copy = root / f"storage-{n}-{mode}.h5"
            shutil.copy(path, copy)
            report = root / f"storage-{n}-{mode}.json"
            before = load()
            wall, rss, _ = run(SAPGO + ["adjust", str(copy), "--no-progress", "--quiet",
                                        "--keep-scratch", "--factor-storage", mode,
                                        "--json", str(report)])
            work = copy.with_name(copy.name + ".work")
            rep = json.loads(report.read_text())
            per = rep["timings_per_iteration_s"]
            runs.append({"round": r, "mode": mode, "wall_s": wall, "peak_rss_mb": rss,
                         "work_bytes": du(work), "iterations": rep["iterations"],
                         "sigma0": rep["sigma0"], "timings_s": rep["timings_s"],
                         "per_iteration_s": per, "iteration_s": sum(per.values()),
                         "iterations_s": [{k: x[k] for k in ("build_s", "solve_s", "update_s")}
                                          for x in rep["iteration_log"]],
                         "load_before": before})
            shutil.rmtree(work, ignore_errors=True)
            copy.unlink()
            report.unlink()
            print(json.dumps(runs[-1]), file=sys.stderr, flush=True)
    path.unlink()

    def stat(mode, get):
        v = [get(x) for x in runs if x["mode"] == mode]
        return {"median": statistics.median(v), "min": min(v), "max": max(v)}

    summary = {}
    for mode in ("file", "replay"):
        summary[mode] = {
            "to_solution_s": stat(mode, lambda x: x["wall_s"]),
            "iteration_s": stat(mode, lambda x: x["iteration_s"]),
            "solve_per_iteration_s": stat(mode, lambda x: x["per_iteration_s"]["solve"]),
            "precision_s": stat(mode, lambda x: x["timings_s"].get("precision", 0.0)),
            "peak_rss_mb": stat(mode, lambda x: x["peak_rss_mb"]),
            "work_gb": stat(mode, lambda x: x["work_bytes"] / 1e9)}
    result = {"machine": {"python": sys.version.split()[0], "platform": platform.platform(),
                          "cpus": os.cpu_count(),
                          "memory_gb": os.sysconf("SC_PAGE_SIZE")
                          * os.sysconf("SC_PHYS_PAGES") / 1e9, "load_at_end": load()},
              "sapgo_version": sapgo.__version__, "sapgo_source": git_state(), "block": row,
              "runs": runs, "summary": summary}
    out = Path(__file__).parent / "results" / "scale_storage.json"
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(storage_markdown(result))


def storage_markdown(result):
    b = result["block"]
    out = [f"{b['photos']:,} photos ({b['strips']} x {b['photos_per_strip']}), band width "
           f"{b['band_width']}; generate {b['phases']['generate']['wall_s']:.1f} s, order "
           f"{b['phases']['order']['wall_s']:.1f} s; {len(result['runs']) // 2} rounds, code "
           f"{(result['sapgo_source'].get('commit') or '?')[:7]}",
           "", "| factor | to solution s | s/iteration | solve s/iteration | precision s | "
           "peak RSS MB | work dir GB |", "|---|---|---|---|---|---|---|"]

    def f(d, fmt):
        return f"{d['median']:{fmt}} ({d['min']:{fmt}}-{d['max']:{fmt}})"

    for mode, s in result["summary"].items():
        out.append(f"| {mode} | {f(s['to_solution_s'], '.1f')} | {f(s['iteration_s'], '.1f')} | "
                   f"{f(s['solve_per_iteration_s'], '.1f')} | {f(s['precision_s'], '.1f')} | "
                   f"{f(s['peak_rss_mb'], '.0f')} | {f(s['work_gb'], '.2f')} |")
    loads = [x["load_before"][0] for x in result["runs"] if x.get("load_before")]
    if loads:
        out += ["", f"Load average before the runs: {min(loads):.2f}-{max(loads):.2f}."]
    return "\n".join(out)


def square_markdown(rows):
    out = ["| block | photos | --memory | solver | tree: nodes, largest front, factor GB, "
           "TFlop | generate s | order s | adjust s (iterations) | s/iteration | precision s | "
           "peak RSS adjust MB | work dir GB | sigma0 | stopped | code |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        t = r.get("tree") or {}
        tree = (f"{t.get('nodes')}, {t.get('largest_front')}, "
                f"{t.get('factor_bytes', 0) / 1e9:.1f}, {t.get('flops', 0) / 1e12:.2f}"
                if isinstance(t, dict) and t else "")
        ph = r["phases"]
        a = ph.get("adjust", {})
        out.append(
            f"| {r['strips']} x {r['photos_per_strip']} | {r['photos']:,} | "
            f"{r.get('memory') or '1G (default)'} | {r.get('solver')} | "
            f"{tree} | {ph['generate']['wall_s']:.1f} | {ph['order']['wall_s']:.1f} | "
            + (f"{a['wall_s']:.1f} ({r['iterations']}) | {r['seconds_per_iteration']:.2f} | "
               f"{a.get('precision_s', 0):.1f} | {a['peak_rss_mb']:.0f} | "
               f"{r['work_bytes'] / 1e9:.2f} | {r['sigma0']:.3f} | |" if a else
               f" | | | | | | {r.get('stopped', '')} |")
            + f" {_code(r)} |")
    return "\n".join(out)


def _code(row):
    """The commit a row was measured at (``+`` with uncommitted source changes)."""
    src = row.get("sapgo_source") or {}
    return (src.get("commit") or "?")[:7] + ("+" if src.get("uncommitted") else "")


def _source():
    sys.path.insert(0, str(Path(__file__).parent))
    from colmap import git_state

    return git_state()


def growth(rows, a, b):
    by = {r["photos"]: r for r in rows}
    if a in by and b in by:
        return (by[b]["peak_rss_mb"] - by[a]["peak_rss_mb"]) * 2**20 / (b - a)
    return None


def markdown(result):
    out = ["| photos | points | observations | band width | generate s | order s | "
           "adjust (1 it.) s | build s | solve s | update s | peak RSS generate MB | "
           "peak RSS order MB | peak RSS adjust MB | project GB | work dir GB |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["rows"]:
        ph = r["phases"]
        a = ph["adjust_1_iteration"]
        out.append(
            f"| {r['photos']:,} | {r['points']:,} | {r['observations']:,} | {r['band_width']} | "
            f"{ph['generate']['wall_s']:.1f} | {ph['order']['wall_s']:.1f} | {a['wall_s']:.1f} | "
            f"{a['build_s']:.1f} | {a['solve_s']:.1f} | {a['update_s']:.1f} | "
            f"{ph['generate']['peak_rss_mb']:.0f} | {ph['order']['peak_rss_mb']:.0f} | "
            f"{a['peak_rss_mb']:.0f} | {r['project_bytes'] / 1e9:.2f} | "
            f"{r['work_bytes'] / 1e9:.2f} |")
    sol = [r for r in result["rows"] if "solution" in r]
    if sol:
        out += ["", "| photos | iterations | time to solution s | s per iteration | sigma0 | "
                "check sXY m | check sZ m | peak RSS MB |", "|---|---|---|---|---|---|---|---|"]
        for r in sol:
            s = s_ = r["solution"]
            per = sum(s_["seconds_per_iteration"].values())
            out.append(f"| {r['photos']:,} | {s['iterations']} | {s['wall_s']:.1f} | {per:.2f} | "
                       f"{s['sigma0']:.3f} | {s['check_sxy_m']:.3f} | {s['check_sz_m']:.3f} | "
                       f"{s['peak_rss_mb']:.0f} |")
    g = result["rss_growth_bytes_per_photo"]
    out.append("")
    out.append("Peak RSS growth of `sapgo adjust --max-iterations 1`: " + ", ".join(
        f"{k.replace('_', ' ')}: {v:.0f} B/photo" for k, v in g.items() if v is not None))
    return "\n".join(out)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="10000,20000,100000,200000,1000000")
    ap.add_argument("--solution-sizes", default="10000,100000")
    ap.add_argument("--dir", default=None, help="where the blocks are written (default: a "
                    "temporary directory under data/generated)")
    ap.add_argument("--squares", default="", help="square blocks instead: sides, e.g. "
                    "200,500,1000 (results/scale_square.json)")
    ap.add_argument("--memory", default=None, help="with --squares: sapgo adjust --memory "
                    "SIZE (default: sapgo's budget, 1 GiB)")
    ap.add_argument("--storage", default="", help="photos: the factor file against the "
                    "replay on one strip block (results/scale_storage.json)")
    ap.add_argument("--rounds", type=int, default=3, help="with --storage: rounds")
    ap.add_argument("--huge", type=int, default=0, help="photos: one block of 20 strips "
                    "generated, ordered and adjusted to convergence with precision (every "
                    "phase recorded: results/scale.json, key huge)")
    ap.add_argument("--huge-phases", default="generate,order,adjust", help="with --huge: "
                    "generate,order to measure those again (the adjustment's record kept)")
    args = ap.parse_args()
    if args.huge:
        return huge(args)
    if args.squares:
        return squares(args)
    if args.storage:
        return storage(args)
    sizes = [int(s) for s in args.sizes.split(",") if s]
    full = {int(s) for s in args.solution_sizes.split(",") if s}
    root = Path(args.dir or Path(__file__).parent.parent / "data" / "generated" / "scale")
    root.mkdir(parents=True, exist_ok=True)
    # warm the numba cache so that no phase times compilation
    warm = root / "warm.h5"
    sapgo.generate_block(warm, strips=2, photos_per_strip=5, control_points=6, progress=False)
    sapgo.adjust(warm, sapgo.Options(progress=False))
    warm.unlink()
    rows = []
    for n in sizes:
        rows.append(one(n, root, n in full))
        print(json.dumps(rows[-1]), file=sys.stderr)
    result = {
        "machine": {"python": sys.version.split()[0], "platform": platform.platform(),
                    "cpus": os.cpu_count(),
                    "memory_gb": os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 1e9},
        "sapgo_version": sapgo.__version__,
        "sapgo_source": _source(),
        "rows": rows,
        "rss_growth_bytes_per_photo": {
            "20000_to_200000": growth(rows, 20000, 200000),
            "100000_to_1000000": growth(rows, 100000, 1000000),
        },
    }
    out = Path(__file__).parent / "results" / "scale.json"
    if out.exists() and "huge" in json.loads(out.read_text()):   # (kept: a run of its own)
        result["huge"] = json.loads(out.read_text())["huge"]
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(markdown(result))


def huge(args):
    """``--huge PHOTOS``: generate, order and adjust one block to convergence, each phase a
    process of its own; wall, peak RSS and the disk taken at most per phase."""
    root = Path(args.dir or Path(__file__).parent.parent / "data" / "generated" / "scale")
    root.mkdir(parents=True, exist_ok=True)
    warm = root / "warm.h5"   # compile or load the kernels outside the measured runs
    sapgo.generate_block(warm, strips=2, photos_per_strip=5, control_points=6, progress=False)
    sapgo.adjust(warm, sapgo.Options(progress=False))
    warm.unlink()
    n = args.huge
    g = n // STRIPS
    path = root / f"huge-{n}.h5"
    report = root / f"huge-{n}.json"
    free_gb = shutil.disk_usage(root).free / 1e9
    load = os.getloadavg()
    phases = {}
    cmds = {
        "generate": SAPGO + ["generate", "--strips", str(STRIPS), "--photos-per-strip", str(g),
                             "--control-points", str(n // PHOTOS_PER_CONTROL_POINT),
                             str(path)],
        "order": SAPGO + ["order", "--memory", "256M", str(path)],
        "adjust": SAPGO + ["adjust", str(path), "--no-progress", "--quiet", "--keep-scratch",
                           "--json", str(report)],
    }
    wanted = [x for x in args.huge_phases.split(",") if x]
    if wanted not in (["generate", "order", "adjust"], ["generate", "order"]):
        raise SystemExit("--huge-phases: generate,order,adjust or generate,order")
    source = _source()
    for name in wanted:
        load_before = os.getloadavg()
        with DiskWatch(root) as disk:
            wall, rss, _ = run(cmds[name])
        phases[name] = {"wall_s": wall, "peak_rss_mb": rss, "disk_taken_gb": disk.used() / 1e9,
                        "load_before": load_before, "sapgo_source": source}
        print(f"{name}: {wall:.1f} s, peak RSS {rss:.0f} MB, disk taken at most "
              f"{disk.used() / 1e9:.2f} GB", file=sys.stderr)
        if name == "generate":
            project_bytes = du(path)
    out = Path(__file__).parent / "results" / "scale.json"
    whole = json.loads(out.read_text()) if out.exists() else {}
    if "adjust" not in wanted:   # the phases measured again; the adjustment's kept
        result = whole["huge"]
        if result["photos"] != n:
            raise SystemExit(f"results/scale.json holds {result['photos']:,} photos, not {n:,}")
        result["phases"].update(phases)
        result["project_bytes"] = project_bytes
        for k, f_ in (("peak_rss_mb_any_phase", "peak_rss_mb"),
                      ("disk_taken_gb_any_phase", "disk_taken_gb")):
            result[k] = max(p[f_] for p in result["phases"].values())
        path.unlink()
        out.write_text(json.dumps(whole, indent=2) + "\n")
        print(huge_markdown(result))
        return
    work = path.with_name(path.name + ".work")
    project_after = du(path)
    rep = json.loads(report.read_text())
    c, t = rep["check_points"], rep["timings_s"]
    result = {
        "what": f"{n:,} photos ({STRIPS} strips x {g:,}), 9-point pattern, one full control "
                f"point per {PHOTOS_PER_CONTROL_POINT} photos: generate, order and adjust to "
                f"convergence with the precision pass, each a process of its own (wall, peak "
                f"RSS of the process, disk taken at most: free space sampled every second)",
        "commands": [" ".join(["sapgo"] + c_[3:]) for c_ in cmds.values()],
        "machine": {"cpus": os.cpu_count(),
                    "memory_gb": os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 1e9,
                    "free_disk_before_gb": free_gb, "load_before": load,
                    "load_at_end": os.getloadavg()},
        "sapgo_source": source,
        "photos": n, "points": None, "observations": rep["n_observations"],
        "phases": phases,
        "project_bytes": project_bytes,
        "project_bytes_adjusted": project_after,
        "work_dir_bytes_at_end": du(work),
        "adjustment": {
            "converged": rep["converged"], "iterations": rep["iterations"],
            "sigma0": rep["sigma0"], "band_width": rep["band_width"],
            "check_sxy_m": c["sxy"], "check_sz_m": c["sz"],
            "seconds_per_iteration": rep["timings_per_iteration_s"],
            "precision_s": t.get("precision"), "commit_s": t.get("commit"),
        },
        "peak_rss_mb_any_phase": max(p["peak_rss_mb"] for p in phases.values()),
        "disk_taken_gb_any_phase": max(p["disk_taken_gb"] for p in phases.values()),
    }
    result["points"] = rep["n_points"]
    shutil.rmtree(work, ignore_errors=True)
    path.unlink()
    report.unlink()
    whole["huge"] = result
    out.write_text(json.dumps(whole, indent=2) + "\n")
    print(huge_markdown(result))


def huge_markdown(r):
    ph, a = r["phases"], r["adjustment"]
    per = a["seconds_per_iteration"]
    out = ["| phase | wall s | peak RSS MB | disk taken at most GB | sapgo |",
           "|---|---|---|---|---|"]
    for name in ("generate", "order", "adjust"):
        p = ph[name]
        out.append(f"| {name} | {p['wall_s']:.0f} | {p['peak_rss_mb']:.0f} | "
                   f"{p['disk_taken_gb']:.1f} | {_code(p if 'sapgo_source' in p else r)} |")
    out += ["", f"{r['photos']:,} photos, {r['points']:,} points, {r['observations']:,} "
            f"observations, band width {a['band_width']}: {a['iterations']} iterations "
            f"(build {per['build']:.1f} s, solve {per['solve']:.1f} s, update "
            f"{per['update']:.1f} s each), precision pass {a['precision_s']:.0f} s; sigma0 "
            f"{a['sigma0']:.4f}, check points sXY {a['check_sxy_m']:.3f} m, sZ "
            f"{a['check_sz_m']:.3f} m; project {r['project_bytes'] / 1e9:.1f} GB "
            f"({r['project_bytes_adjusted'] / 1e9:.1f} GB adjusted: the adjustment's disk "
            f"includes this copy, written beside the project and renamed over it), work "
            f"directory at the end {r['work_dir_bytes_at_end'] / 1e9:.1f} GB (sapgo "
            f"{_code(r)})."]
    return "\n".join(out)


def squares(args):
    root = Path(args.dir or Path(__file__).parent.parent / "data" / "generated" / "scale")
    root.mkdir(parents=True, exist_ok=True)
    warm = root / "warm.h5"   # compile or load the kernels outside the measured runs
    sapgo.generate_block(warm, strips=12, photos_per_strip=12, control_points=8,
                         progress=False)
    sapgo.order_project(warm, solver="tree")
    sapgo.adjust(warm, sapgo.Options(progress=False))
    warm.unlink()
    sys.path.insert(0, str(Path(__file__).parent))
    from colmap import git_state

    rows = []
    for side in (int(s) for s in args.squares.split(",") if s):
        rows.append(one_square(side, root, args.memory))
        rows[-1]["sapgo_source"] = git_state()   # (rows of other runs are kept: each its own)
        print(json.dumps(rows[-1]), file=sys.stderr)

    result = {
        "machine": {"python": sys.version.split()[0], "platform": platform.platform(),
                    "cpus": os.cpu_count(),
                    "memory_gb": os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 1e9,
                    "load_at_end": os.getloadavg()},
        "sapgo_version": sapgo.__version__, "sapgo_source": git_state(), "rows": rows}
    out = Path(__file__).parent / "results" / "scale_square.json"
    if out.exists():   # rows of other sides or budgets measured before are kept
        done = {(r["strips"], r.get("memory")) for r in rows}
        old = [r for r in json.loads(out.read_text()).get("rows", [])
               if (r["strips"], r.get("memory")) not in done]
        result["rows"] = rows = sorted(old + rows,
                                       key=lambda r: (r["photos"], r.get("memory") or ""))
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(square_markdown(rows))


if __name__ == "__main__":
    main()
