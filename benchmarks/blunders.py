"""Blunder detection on SAPGO-P-3 (seeds/002 Table 2) with planted blunders.

Run:  python benchmarks/blunders.py [--seeds 1 2 3]   (writes results/blunders.json)
      python benchmarks/blunders.py --scale 100000 --blunders 200 --rounds 3
            (writes results/blunders_scale.json)

For each seed: the block is generated clean and with 20 blunders of 30-100 um (random
observations, one per point, random direction), both with the same seed, so the clean
adjustment is the reference. Each method adjusts the blundered block; reported are the
planted blunders found, false rejections (observations the test chose that hold no
blunder), rays rejected only with their undeterminable point, the blunders detectable at the
method's alpha with 80 % power (Baarda's non-centrality from the observation's redundancy
block), and how far the result lies from the clean solution in units of the clean
solution's standard deviations (stations: X, Y, Z; points: X, Y, Z): the fraction within
1 sigma, the mean and the maximum. The same is run on the block with the 25-point pattern
(more redundancy) to show what the geometry allows.

``--scale N``: snooping at scale. A block of 20 strips of N / 20 photos with ``--blunders``
planted blunders (seed 1) is adjusted plainly and with batch snooping (its rejections
confirmed), each run a process of its own on a fresh copy of the unordered file, the two
taking turns in each of ``--rounds`` rounds (one-at-a-time snooping, a round per rejection,
is not run at this size). The significance level is 1 / the number of observations by
default (``--alpha``): at a fixed 0.001 about one good observation in a thousand tests
significant by chance, which on 900 000 observations is some 900 rejections of good
observations, each a round of one-at-a-time snooping. Reported: time to solution (ordering, iterations, the precision
passes, commit), its ratio to the plain adjustment's, iterations, snooping rounds, the
rejections and the planted blunders found, medians and (min-max) over the rounds, with the
machine's load before each run.
"""

import argparse
import json
import platform
import shutil
import tempfile
import time
import sys
from pathlib import Path

import numpy as np

import sapgo

METHODS = {
    "least squares": {},
    "snooping alpha 1e-3": dict(snooping=True, snooping_alpha=1e-3),
    "snooping alpha 1e-4": dict(snooping=True, snooping_alpha=1e-4),
    "snooping alpha 1e-5": dict(snooping=True, snooping_alpha=1e-5),
    "robust cauchy 30 um": dict(robust="cauchy", robust_threshold_um=30.0),
    "robust huber 15 um": dict(robust="huber", robust_threshold_um=15.0),
}
BLOCKS = {
    "sapgo-p-3": dict(preset="sapgo-p-3"),
    "sapgo-p-3, 25 points per photo": dict(strips=5, photos_per_strip=100, pattern=25,
                                           control_points=48),
}


def solution(path, **kw):
    t0 = time.perf_counter()
    s = sapgo.adjust(path, sapgo.Options(progress=False, max_iterations=60, **kw))
    dt = time.perf_counter() - t0
    with sapgo.Project(path) as p:
        eo = p.read_field("stations", "eo") + p.solution("station_corr")
        xyz = p.read_field("points", "xyz") + p.solution("point_corr")
        ssig, psig = p.solution("station_sigma"), p.solution("point_sigma")
    return s, dt, eo, xyz, ssig, psig


def deviation(a, b, sig):
    ok = sig > 0
    d = np.where(ok, np.abs(a - b) / np.where(ok, sig, 1.0), 0.0)
    return {"within_1_sigma": float((d.max(axis=1) <= 1.0).mean()), "mean": float(d[ok].mean()),
            "max": float(d.max())}


def run(seeds):
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for block, params in BLOCKS.items():
            for seed in seeds:
                clean = Path(tmp) / "clean.h5"
                bad = Path(tmp) / "bad.h5"
                sapgo.generate_block(clean, seed=seed, force=True, **params)
                sapgo.generate_block(bad, seed=seed, blunders=20, force=True, **params)
                sc, _, eoc, xyzc, ssc, psc = solution(clean)
                for name, kw in METHODS.items():
                    work = Path(tmp) / "work.h5"
                    shutil.copy(bad, work)
                    s, dt, eo, xyz, _, _ = solution(work, **kw)
                    row = {"block": block, "seed": seed, "method": name,
                           "iterations": s.iterations, "converged": s.converged,
                           "seconds": dt, "sigma0": s.sigma0,
                           "blunder_check": s.blunder_check,
                           "stations": deviation(eo[:, 3:], eoc[:, 3:], ssc[:, 3:]),
                           "points": deviation(xyz, xyzc, psc),
                           "check_points": s.check_points, "clean_check_points": sc.check_points,
                           "reliability": s.reliability}
                    rows.append(row)
                    b = s.blunder_check
                    print(f"{block:32s} seed {seed} {name:22s} found {b['found']:2d}/20 "
                          f"false {b['false_rejections']} with-point {b['rejected_with_point']}"
                          f" detectable {b.get('detectable', '-')} | stations within 1 sigma "
                          f"{row['stations']['within_1_sigma']:.3f} max "
                          f"{row['stations']['max']:.2f} | points "
                          f"{row['points']['within_1_sigma']:.3f} max {row['points']['max']:.2f}"
                          f" | {s.iterations} it {dt:.1f} s", flush=True)
    return rows


SCALE_MODES = {"plain": {}, "batch snooping": dict(snooping=True, snooping_batch=True)}


def scale_child(path, mode, alpha):
    """One run of :func:`run_scale` (in its own process): prints ``RESULT {json}``."""
    t0 = time.perf_counter()
    s = sapgo.adjust(path, sapgo.Options(progress=False, snooping_alpha=float(alpha),
                                         **SCALE_MODES[mode]))
    dt = time.perf_counter() - t0
    b = s.blunder_check or {}
    print("RESULT " + json.dumps({
        "seconds": dt, "iterations": s.iterations, "converged": s.converged,
        "sigma0": s.sigma0, "rejected": len(s.rejected),
        "reinstated": len(getattr(s, "reinstated", []) or []),
        "found": b.get("found"), "planted": b.get("planted"),
        "false_rejections": b.get("false_rejections"), "detectable": b.get("detectable"),
        "found_detectable": b.get("found_detectable"), "timings_s": s.timings_s}))


def run_scale(n_photos, n_blunders, rounds, alpha):
    import statistics
    import subprocess

    from colmap import git_state
    from shape import load

    strips = 20
    rows = {m: [] for m in SCALE_MODES}
    with tempfile.TemporaryDirectory() as tmp:
        gen = Path(tmp) / "block.h5"
        info = sapgo.generate_block(gen, strips=strips, photos_per_strip=n_photos // strips,
                                    control_points=max(4, n_photos // 25), seed=1,
                                    blunders=n_blunders, progress=False)
        n_obs = info["observations"]
        if alpha is None:   # about one good observation's test above it by chance
            alpha = float(f"{1.0 / n_obs:.0e}")
        print(f"{info['photos']} photos, {info['points']} points, {n_obs} observations, "
              f"{n_blunders} blunders; alpha {alpha:g} (chance rejections expected: "
              f"{alpha * n_obs:.1f})", flush=True)
        for r in range(rounds):
            for mode in SCALE_MODES:
                run = Path(tmp) / "run.h5"
                shutil.copy(gen, run)
                before = load()
                proc = subprocess.run([sys.executable, __file__, "--child", str(run), mode,
                                       str(alpha)], capture_output=True, text=True)
                line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")]
                if proc.returncode or not line:
                    raise SystemExit(f"{mode}: {proc.stderr[-2000:]}")
                res = json.loads(line[-1][7:])
                res["load_before"] = before
                rows[mode].append(res)
                print(f"  round {r} {mode}: {res['seconds']:.1f} s, {res['iterations']} it, "
                      f"{res['rejected']} rejected, found {res['found']}/{res['planted']}, "
                      f"load {before}", flush=True)
                run.unlink()

    def spread(v):
        return {"median": statistics.median(v), "min": min(v), "max": max(v)}

    plain = [x["seconds"] for x in rows["plain"]]
    ratios = [b / a for a, b in zip(plain, [x["seconds"] for x in rows["batch snooping"]])]
    summary = {m: {"seconds": spread([x["seconds"] for x in v]),
                   "iterations": spread([x["iterations"] for x in v]),
                   "rejected": v[-1]["rejected"], "reinstated": v[-1]["reinstated"],
                   "found": v[-1]["found"], "planted": v[-1]["planted"],
                   "false_rejections": v[-1]["false_rejections"],
                   "detectable": v[-1]["detectable"],
                   "found_detectable": v[-1]["found_detectable"],
                   "precision_s": spread([x["timings_s"].get("precision", 0.0) for x in v])}
               for m, v in rows.items()}
    summary["ratio_batch_to_plain"] = spread(ratios)
    print("\n| mode | to solution s | of which precision passes s | iterations | rejected | "
          "planted blunders found | of them detectable (80 % power) | false rejections | "
          "brought back |")
    print("|---|---|---|---|---|---|---|---|---|")
    for m in SCALE_MODES:
        x = summary[m]
        sec, it = x["seconds"], x["iterations"]
        pr = x["precision_s"]
        det = (f"{x['found_detectable']} of {x['detectable']}" if x["detectable"] is not None
               else "")
        print(f"| {m} | {sec['median']:.1f} ({sec['min']:.1f}-{sec['max']:.1f}) | "
              f"{pr['median']:.1f} | {it['median']:g} ({it['min']}-{it['max']}) | "
              f"{x['rejected']} | {x['found']} of {x['planted']} | {det} | "
              f"{x['false_rejections']} | {x['reinstated']} |")
    rt = summary["ratio_batch_to_plain"]
    print(f"\nbatch snooping / plain, time to solution, same round: {rt['median']:.2f} "
          f"({rt['min']:.2f}-{rt['max']:.2f})")
    return {"benchmark": "blunders --scale", "photos": info["photos"],
            "observations": info["observations"], "blunders": n_blunders, "rounds": rounds,
            "alpha": alpha,
            "sapgo_version": sapgo.__version__, "sapgo_source": git_state(),
            "load_at_end": load(), "runs": rows, "summary": summary}


def markdown(rows):
    """The table of benchmarks/README.md: each cell the seeds' figures, ``a / b / c``."""
    from collections import OrderedDict

    cells = OrderedDict()
    for r in rows:
        cells.setdefault((r["block"], r["method"]), []).append(r)
    out = ["| block | method | found (of 20) | false | with their point | detectable | found of "
           "detectable | stations within 1σ | points within 1σ | max station dev. [σ] | "
           "iterations | time [s] |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]

    def join(rs, get):
        return " / ".join(get(r) for r in rs)

    for (block, method), rs in cells.items():
        rs = sorted(rs, key=lambda r: r["seed"])
        tested = method.startswith("snooping")

        def b(key):
            return join(rs, lambda r: str(r["blunder_check"][key])) if tested else "–"

        st_in = join(rs, lambda r: "%.0f %%" % (100 * r["stations"]["within_1_sigma"]))
        pt_in = join(rs, lambda r: "%.1f %%" % (100 * r["points"]["within_1_sigma"]))
        st_max = join(rs, lambda r: "%.1f" % r["stations"]["max"])
        its = join(rs, lambda r: str(r["iterations"]))
        secs = join(rs, lambda r: "%.1f" % r["seconds"])
        out.append(
            f"| {block} | {method} | {b('found')} | {b('false_rejections')} | "
            f"{b('rejected_with_point')} | {b('detectable')} | {b('found_detectable')} | "
            f"{st_in} | {pt_in} | {st_max} | {its} | {secs} |")
    return "\n".join(out)


def main():
    if len(sys.argv) > 1 and sys.argv[1] == "--child":
        scale_child(sys.argv[2], sys.argv[3], sys.argv[4])
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--scale", type=int, default=None, metavar="PHOTOS",
                    help="snooping at scale on a block of this many photos in 20 strips")
    ap.add_argument("--blunders", type=int, default=200)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--alpha", type=float, default=None,
                    help="--scale: the snooping's significance level (default: 1 / the "
                         "observations, rounded; at 0.001 a 900 000-observation block has "
                         "about 900 good observations above the critical value by chance)")
    args = ap.parse_args()
    if args.scale:
        res = run_scale(args.scale, args.blunders, args.rounds, args.alpha)
        out = Path(__file__).parent / "results" / "blunders_scale.json"
        out.write_text(json.dumps(res, indent=1))
        print(f"wrote {out}")
        return
    rows = run(args.seeds)
    out = Path(__file__).parent / "results" / "blunders.json"
    sys.path.insert(0, str(Path(__file__).parent))
    from colmap import git_state

    out.write_text(json.dumps({"machine": platform.processor() or platform.machine(),
                               "sapgo": sapgo.__version__, "sapgo_source": git_state(),
                               "rows": rows}, indent=1))
    print(markdown(rows))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
