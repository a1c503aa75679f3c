"""What COLMAP's work in colmap.py's rounds does to sapgo's next run.

Run:  python benchmarks/interference.py [--rounds 8] [--photos 1000]
      python benchmarks/interference.py --alone 10000,100000 [--rounds 5]
      (write results/interference.json, key ``after_work`` or ``alone``, and print the
       table pasted into benchmarks/README.md)

colmap.py runs sapgo in a long-lived process of its own and COLMAP in its own process, the
tools taking turns; sapgo's 1 000-photo runs there took about 1.5 times what they take
alone. This script separates the causes on colmap.py's 1 000-photo block: before each sapgo
run (in its own process, as colmap.py runs it, after colmap.py's wait for an idle machine)
the parent does one of

- ``nothing``;
- ``COLMAP solve``: COLMAP's bundle adjustment in its best configuration;
- ``COLMAP solve + covariance``: the same, then its covariance estimate
  (``estimate_ba_covariance``, a dense 6n x 6n matrix), as colmap.py does once a round;
- ``memory streaming``: 0.1 s of numpy passes over a 512 MB array;

and sapgo runs in two processes in turn: numpy's transparent-huge-page advice on
(numpy's default, kept by sapgo since ``NUMPY_MADVISE_HUGEPAGE=1`` is in that process's
environment) and off (sapgo's default: its commands turn the advice off while they run,
:func:`sapgo.paging.hugepage_advice_off`; before 1d2b198's successor it took
``NUMPY_MADVISE_HUGEPAGE=0``). Medians and
spreads over interleaved rounds of sapgo's time to solution and its precision pass, with the
other processes' CPU time during the run, ``sapgo.threads``' busy looks and the kernel's
compaction stalls (``/proc/vmstat``) during the run; the machine's huge-page settings.

``--alone SIZES``: sapgo alone (nothing before its runs) on blocks of 20 strips of that many
photos in all, or ``RxC`` square blocks (R strips of C photos: the partition tree), one
control point per 25 photos, the advice on and off in turn: whether turning it off costs
the large blocks anything.
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

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
import colmap as C  # noqa: E402  (the same block, COLMAP runs and sapgo process)

import sapgo  # noqa: E402

MODES = ("nothing", "COLMAP solve", "COLMAP solve + covariance", "memory streaming")
ADVICE = ("on", "off")
LABEL = {"on": "on (NUMPY_MADVISE_HUGEPAGE=1)", "off": "off (sapgo's default)"}


def vmstat(key):
    for line in open("/proc/vmstat"):
        if line.startswith(key + " "):
            return int(line.split()[1])
    return None


def thp_settings():
    out = {}
    for name in ("enabled", "defrag"):
        try:
            out[name] = Path(f"/sys/kernel/mm/transparent_hugepage/{name}").read_text().strip()
        except OSError:
            out[name] = None
    return out


def sapgo_processes(wd):
    """Two long-lived sapgo processes (:class:`colmap.SapgoProcess`): numpy's huge-page
    advice on (``NUMPY_MADVISE_HUGEPAGE=1``: numpy's default, which sapgo then keeps) and
    off (sapgo's default; the child takes the environment at its start)."""
    procs = {}
    for advice in ADVICE:
        old = os.environ.get("NUMPY_MADVISE_HUGEPAGE")
        if advice == "on":
            os.environ["NUMPY_MADVISE_HUGEPAGE"] = "1"
        else:
            os.environ.pop("NUMPY_MADVISE_HUGEPAGE", None)
        try:
            d = wd / f"warm-{advice}"
            d.mkdir()
            procs[advice] = C.SapgoProcess(d)
        finally:
            if old is None:
                os.environ.pop("NUMPY_MADVISE_HUGEPAGE", None)
            else:
                os.environ["NUMPY_MADVISE_HUGEPAGE"] = old
    return procs


def save(key, part):
    out = Path(__file__).parent / "results" / "interference.json"
    result = json.loads(out.read_text()) if out.exists() else {}
    if "rows" in result:   # (the first version's layout: the after-work runs at the top)
        result = {"after_work": result}
    result[key] = part
    out.write_text(json.dumps(result, indent=1) + "\n")
    return out


def alone(args):
    """sapgo alone at the sizes of ``args.alone``, the advice on and off in turn."""
    t_start = time.perf_counter()
    sizes = [x for x in args.alone.split(",") if x]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        wd = Path(tmp)
        procs = sapgo_processes(wd)
        try:
            for size in sizes:
                strips, per = ((int(a) for a in size.split("x")) if "x" in size
                               else (20, int(size) // 20))
                n = strips * per
                gen = wd / f"block{size}.h5"
                sapgo.generate_block(gen, progress=False, strips=strips, photos_per_strip=per,
                                     control_points=max(4, n // 25), control_sigma=0.0)
                runs = {a: [] for a in ADVICE}
                loads = []
                for rnd in range(args.rounds):
                    loads.append(C.load_average())
                    for advice in ADVICE if rnd % 2 == 0 else ADVICE[::-1]:
                        path = wd / "run.h5"
                        shutil.copyfile(gen, path)
                        r = procs[advice](path, "full")
                        path.unlink()
                        runs[advice].append(r)
                        print(f"  {size}, round {rnd}, advice {advice}: "
                              f"{r['time_to_solution_s']:.3f} s", file=sys.stderr)
                gen.unlink()
                for advice, rs in runs.items():
                    tts = [r["time_to_solution_s"] for r in rs]
                    prec = [r["phases"]["precision"] for r in rs]
                    solve = [r["phases"]["solve"] for r in rs]
                    rows.append({"photos": n, "block": (f"{strips} x {per}" if "x" in size
                                                        else "20 strips"),
                                 "ordering": rs[0]["ordering"],
                                 "huge_page_advice": advice,
                                 "median_time_to_solution_s": float(np.median(tts)),
                                 "spread_time_to_solution_s": [min(tts), max(tts)],
                                 "median_precision_s": float(np.median(prec)),
                                 "median_solve_s": float(np.median(solve)),
                                 "sigma0": sorted({r["sigma0"] for r in rs}),
                                 "load_before_rounds": loads,
                                 "runs_time_to_solution_s": tts})
        finally:
            for p in procs.values():
                p.close()
    part = {"machine": {"python": sys.version.split()[0], "platform": platform.platform(),
                        "cpus": os.cpu_count(), "transparent_hugepage": thp_settings()},
            "sapgo_version": sapgo.__version__, "sapgo_source": C.git_state(),
            "rounds": args.rounds, "rows": rows, "wall_s": time.perf_counter() - t_start}
    out = save("alone", part)
    print(f"\nsapgo alone, {args.rounds} interleaved rounds; transparent huge pages: "
          f"enabled {part['machine']['transparent_hugepage']['enabled']}, defrag "
          f"{part['machine']['transparent_hugepage']['defrag']}\n")
    print("| photos | block | numpy's huge-page advice | to solution s, median (min-max) | "
          "solve s (all iterations) | precision pass s | sigma0 |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        a = r["spread_time_to_solution_s"]
        print(f"| {r['photos']:,} | {r.get('block', '20 strips')} | "
              f"{LABEL[r['huge_page_advice']]} | "
              f"{r['median_time_to_solution_s']:.3f} ({a[0]:.3f}-{a[1]:.3f}) | "
              f"{r['median_solve_s']:.3f} | {r['median_precision_s']:.3f} | "
              f"{', '.join(f'{x:.10f}' for x in r['sigma0'])} |")
    print(f"\nResults: {out}  (wall {part['wall_s']:.0f} s)")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=None, help="default 8; 5 with --alone")
    ap.add_argument("--photos", type=int, default=1000, choices=sorted(C.BLOCKS))
    ap.add_argument("--alone", default="", help="sapgo alone at these photo counts "
                    "(20 strips) or RxC squares, e.g. 10000,100000,200x200")
    args = ap.parse_args()
    if args.alone:
        args.rounds = args.rounds or 5
        return alone(args)
    args.rounds = args.rounds or 8
    pycolmap = C.import_pycolmap()
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        wd = Path(tmp)
        gen = wd / "block.h5"
        sapgo.generate_block(gen, progress=False, control_sigma=0.0, **C.BLOCKS[args.photos])
        prob = C.load_problem(gen)
        cfg = next(c for c in C.solver_configs(args.photos, pycolmap) if "1e16" in c["name"])
        plan = C.covariance_plan(int(prob["station_active"].sum()), other_params=0)
        if "skipped" in plan:
            sys.exit(f"COLMAP's covariance cannot run here: {plan['skipped']}")
        procs = sapgo_processes(wd)
        big = np.ones(64 * 1024 * 1024)   # 512 MB
        runs = {(m, a): [] for m in MODES for a in ADVICE}
        loads = []
        try:
            for rnd in range(args.rounds):
                loads.append(C.load_average())
                for mode in MODES:
                    for advice in ADVICE:
                        if mode == "COLMAP solve":
                            C.run_colmap(prob, cfg, pycolmap)
                        elif mode == "COLMAP solve + covariance":
                            _, rec, ba, _ = C.run_colmap(prob, cfg, pycolmap, keep=True)
                            cov = C.colmap_covariance(rec, ba, pycolmap, plan, cfg["name"])
                            if "error" in cov:
                                sys.exit(f"COLMAP's covariance: {cov['error']}")
                            del rec, ba
                        elif mode == "memory streaming":
                            t0 = time.perf_counter()
                            while time.perf_counter() - t0 < 0.1:
                                big *= 1.0000001
                        path = wd / "run.h5"
                        shutil.copyfile(gen, path)
                        stalls = vmstat("compact_stall")
                        r = procs[advice](path, "full")
                        stalls = (vmstat("compact_stall") or 0) - (stalls or 0)
                        path.unlink()
                        runs[mode, advice].append({
                            "time_to_solution_s": r["time_to_solution_s"],
                            "precision_s": r["phases"]["precision"],
                            "solve_s": r["phases"]["solve"],
                            "foreign_cpu_s": r["foreign_cpu_s"],
                            "busy_looks": r["threads_looks"]["busy"],
                            "checks": r["threads_looks"]["checks"],
                            "compaction_stalls": stalls,
                            "sigma0": r["sigma0"]})
                        print(f"  round {rnd}: {mode}, advice {advice}: "
                              f"{r['time_to_solution_s']:.4f} s (precision "
                              f"{r['phases']['precision']:.4f})", file=sys.stderr)
        finally:
            for p in procs.values():
                p.close()
    rows = []
    for (mode, advice), rs in runs.items():
        tts = [r["time_to_solution_s"] for r in rs]
        prec = [r["precision_s"] for r in rs]
        rows.append({"before": mode, "huge_page_advice": advice, "runs": rs,
                     "median_time_to_solution_s": float(np.median(tts)),
                     "spread_time_to_solution_s": [min(tts), max(tts)],
                     "median_precision_s": float(np.median(prec)),
                     "spread_precision_s": [min(prec), max(prec)],
                     "foreign_cpu_s_max": max(r["foreign_cpu_s"] for r in rs),
                     "busy_looks": sum(r["busy_looks"] for r in rs),
                     "checks": sum(r["checks"] for r in rs),
                     "compaction_stalls": sum(r["compaction_stalls"] for r in rs),
                     "sigma0": sorted({r["sigma0"] for r in rs})})
    result = {
        "benchmark": "sapgo's next run after COLMAP's work (colmap.py's rounds)",
        "machine": {"python": sys.version.split()[0], "platform": platform.platform(),
                    "cpus": os.cpu_count(), "transparent_hugepage": thp_settings()},
        "sapgo_version": sapgo.__version__, "sapgo_source": C.git_state(),
        "pycolmap_version": pycolmap.__version__, "photos": args.photos,
        "colmap_configuration": cfg["name"], "rounds": args.rounds,
        "load_before_rounds": loads, "rows": rows,
        "wall_s": time.perf_counter() - t_start}
    out = save("after_work", result)
    print(f"\n{args.photos} photos, {args.rounds} interleaved rounds; transparent huge pages: "
          f"enabled {result['machine']['transparent_hugepage']['enabled']}, defrag "
          f"{result['machine']['transparent_hugepage']['defrag']}\n")
    print("| before sapgo's run | numpy's huge-page advice | sapgo to solution s, median "
          "(min-max) | precision pass s, median (min-max) | others' CPU s (max) | busy looks | "
          "compaction stalls |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        a, b = r["spread_time_to_solution_s"], r["spread_precision_s"]
        print(f"| {r['before']} | {LABEL[r['huge_page_advice']]} | "
              f"{r['median_time_to_solution_s']:.4f} ({a[0]:.4f}-{a[1]:.4f}) | "
              f"{r['median_precision_s']:.4f} ({b[0]:.4f}-{b[1]:.4f}) | "
              f"{r['foreign_cpu_s_max']:.3f} | {r['busy_looks']} of {r['checks']} | "
              f"{r['compaction_stalls']} |")
    print(f"\nResults: {out}  (wall {result['wall_s']:.0f} s)")


if __name__ == "__main__":
    main()
