"""SAPGO-P data sets 1-4 (seeds/002 Tables 2-4): accuracy, band width, time per phase.

Run:  python benchmarks/table4.py            (writes results/table4.json, prints the table)

Each preset is generated with its default seed, ordered and adjusted to convergence; the
times are wall-clock seconds per iteration on this machine, beside the 1974 CPU times of
Table 4 (UNIVAC 1108, one iteration). Numba kernels are compiled (or loaded from cache) by a
warm-up run on a small block first, so compilation is not timed.
"""

import json
import platform
import sys
import tempfile
from pathlib import Path

import sapgo

TABLE4 = {  # sx, sy, sz, sxy (m), check points, band width, build, solve, update, total (s)
    "sapgo-p-1": (0.15, 0.18, 0.54, 0.24, 209, 10, 29, 54, 24, 107),
    "sapgo-p-2": (0.14, 0.13, 0.34, 0.19, 801, 10, 67, 46, 58, 170),
    "sapgo-p-3": (0.10, 0.11, 0.29, 0.14, 1052, 12, 151, 313, 128, 592),
    "sapgo-p-4": (0.24, 0.25, 0.45, 0.36, 1006, 26, 162, 1160, 153, 1456),
}


def run():
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        warm = Path(tmp) / "warm.h5"
        sapgo.generate_block(warm, strips=2, photos_per_strip=5, control_points=6)
        sapgo.adjust(warm, sapgo.Options(progress=False))
        for preset, ref in TABLE4.items():
            path = Path(tmp) / f"{preset}.h5"
            sapgo.generate_block(path, preset=preset)
            s = sapgo.adjust(path, sapgo.Options(progress=False))
            c, t = s.check_points, s.timings_per_iteration_s
            rows.append({
                "preset": preset, "photos": s.n_stations, "points": s.n_points,
                "iterations": s.iterations, "converged": s.converged, "sigma0": s.sigma0,
                "band_width": s.band_width, "check_points": c,
                "seconds_per_iteration": t, "seconds_total": s.timings_s,
                "table4": dict(zip(("sx", "sy", "sz", "sxy", "check_points", "band_width",
                                    "build_s", "solve_s", "update_s", "total_s"), ref)),
            })
    return rows


def markdown(rows):
    out = ["| data set | check pts | sX m | sY m | sZ m | sXY m | band width | build s | "
           "solve s | update s | iteration s | iterations |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        c, t, ref = r["check_points"], r["seconds_per_iteration"], r["table4"]
        it = t["build"] + t["solve"] + t["update"]
        out.append(
            f"| {r['preset']} sapgo | {c['n']} | {c['sx']:.2f} | {c['sy']:.2f} | {c['sz']:.2f} | "
            f"{c['sxy']:.2f} | {r['band_width']} | {t['build']:.3f} | {t['solve']:.3f} | "
            f"{t['update']:.3f} | {it:.3f} | {r['iterations']} |")
        out.append(
            f"| {r['preset']} 1974 | {ref['check_points']} | {ref['sx']:.2f} | {ref['sy']:.2f} | "
            f"{ref['sz']:.2f} | {ref['sxy']:.2f} | {ref['band_width']} | {ref['build_s']} | "
            f"{ref['solve_s']} | {ref['update_s']} | {ref['total_s']} | 1 |")
    return "\n".join(out)


def source():
    """The commit and uncommitted source files of the sapgo checkout (colmap.git_state)."""
    sys.path.insert(0, str(Path(__file__).parent))
    from colmap import git_state

    return git_state()


if __name__ == "__main__":
    rows = run()
    result = {"machine": {"python": sys.version.split()[0], "platform": platform.platform(),
                          "processor": platform.processor() or platform.machine()},
              "sapgo_version": sapgo.__version__, "sapgo_source": source(), "rows": rows}
    out = Path(__file__).parent / "results" / "table4.json"
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(markdown(rows))
