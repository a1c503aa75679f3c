"""Blunder detection on SAPGO-P-3 (seeds/002 Table 2) with planted blunders.

Run:  python benchmarks/blunders.py [--seeds 1 2 3]   (writes results/blunders.json)

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
"""

import argparse
import json
import platform
import shutil
import tempfile
import time
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
                sapgo.generate_block(clean, seed=seed, **params)
                sapgo.generate_block(bad, seed=seed, blunders=20, **params)
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


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    args = ap.parse_args()
    rows = run(args.seeds)
    out = Path(__file__).parent / "results" / "blunders.json"
    out.write_text(json.dumps({"machine": platform.processor() or platform.machine(),
                               "sapgo": sapgo.__version__, "rows": rows}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
