"""``sapgo plan`` against ``sapgo adjust``: predicted band width and solve time, measured.

Run:  python benchmarks/plan.py   (writes results/plan.json; a few minutes)

For generated projects (the SAPGO-P presets and larger blocks) the plan of the project
(its actual network, :func:`sapgo.plan.project_network`) gives the band width of the
economical ordering, and :func:`sapgo.plan.solve_time` the solve time per iteration on this
machine (a synthetic band of that shape through the band solver, as ``adjust`` runs it);
``adjust`` then orders the project and runs five iterations (ten on blocks under 3 000
photos, as the plan's time is the fastest of up to 50 runs), and its band width and the
solve time of its fastest iteration (factorisation and substitutions, as the plan's time is
its fastest run) are recorded beside the prediction. The two are taken in ROUNDS
interleaved rounds, because this machine has slow spells of seconds: the table compares
each side's fastest and gives every round's ratio too.
"""

from __future__ import annotations

import json
import platform
import shutil
import tempfile
import time
from pathlib import Path

import sapgo
from sapgo.plan import evaluate, project_network, solve_time

ROOT = Path(__file__).resolve().parents[1]
ROUNDS = 5
LENGTHS = [300, 240, 300, 180, 280, 300, 220, 300]
BLOCKS = {
    "sapgo-p-1": dict(preset="sapgo-p-1"),
    "sapgo-p-2": dict(preset="sapgo-p-2"),
    "sapgo-p-3": dict(preset="sapgo-p-3"),
    "sapgo-p-4": dict(preset="sapgo-p-4"),
    "10 x 100": dict(strips=10, photos_per_strip=100, control_points=100),
    "20 x 500": dict(strips=20, photos_per_strip=500, control_points=400),
    "40 x 250": dict(strips=40, photos_per_strip=250, control_points=400),
    "5 x 2000": dict(strips=5, photos_per_strip=2000, control_points=400),
    # irregular: generated flight designs, the SAPGO-MFL scenes, a real BAL problem
    "shifted, 8 strips of 180-300": dict(strips=8, photos_per_strip=300, shift=0.5,
                                         lengths=LENGTHS, starts=[0, 20, 0, 60, 10, 0, 40, 0],
                                         control_points=200),
    "scales 0.8-1.25, 8 x 300": dict(strips=8, photos_per_strip=300, sidelap=0.3,
                                     scales=[1.0, 0.8, 1.0, 1.25, 1.0, 0.9, 1.1, 1.0],
                                     control_points=200),
    "sapgo-mfl-1": dict(preset="sapgo-mfl-1"),
    "sapgo-mfl-2": dict(preset="sapgo-mfl-2"),
    "bal problem-49 (9 par.)": dict(bal=ROOT / "tests" / "data" / "problem-49-7776-pre.txt.gz"),
}


def make(path, params):
    if "bal" in params:
        from sapgo.formats.bal import import_bal

        import_bal(params["bal"], path)
    else:
        sapgo.generate_block(path, **params)


def main():
    import sys

    sys.path.insert(0, str(Path(__file__).parent))
    from colmap import git_state

    source = git_state()
    tmp = Path(tempfile.mkdtemp(prefix="sapgo-plan-"))
    rows = []
    try:
        for name, params in BLOCKS.items():
            path = tmp / "b.h5"
            path.unlink(missing_ok=True)
            make(path, params)
            t0 = time.perf_counter()
            e = evaluate(project_network(path))
            # the plan's prediction of what adjust will do: the order sapgo order chooses
            rec = dict(e["adjust"], dimension=e["n_units"])
            t_plan = time.perf_counter() - t0
            # ROUNDS rounds of (plan's timing, adjust): this machine has slow spells of
            # seconds, so the two are interleaved and each side's fastest is compared
            pred, meas = [], []
            tree = rec.get("solver") == "tree"
            for _ in range(ROUNDS):
                if tree:   # the plan's model of the tree (flops and nodes), not a timed run
                    from sapgo.ordering import TREE_RATE

                    t = {"predicted_s": rec["predicted_solve_s"], "rate_flops": TREE_RATE,
                         "timed_units": 0, "extrapolated": False}
                else:
                    t = solve_time(rec["dimension"], rec["band_width_m"],
                                   e["parameters_per_unit"])
                pred.append(t)
                # (the plan's time is the fastest of up to 50 runs: adjust gets as many
                # solves on the small blocks, where a round costs little)
                its = 5 if e["n_units"] >= 3000 else 10
                s = sapgo.adjust(path, sapgo.Options(progress=False, max_iterations=its,
                                                     tol_position=1e-12, tol_angle=1e-14))
                # the fastest iteration's solve (as the plan's time is its fastest run)
                meas.append(min(r["solve_s"] for r in s.iteration_log))
            t = min(pred, key=lambda r: r["predicted_s"])
            predicted, measured = t["predicted_s"], min(meas)
            ratios = sorted(p["predicted_s"] / m for p, m in zip(pred, meas))
            row = {"block": name, "photos": rec["dimension"], "solver": rec.get("solver"),
                   "parameters": e["parameters_per_unit"], "recommended": e["recommended"],
                   "ordering_planned": rec["ordering"],
                   "band_width_planned": rec["band_width_m"], "band_width_adjust": s.band_width,
                   "ordering_adjust": s.ordering, "fill_in_blocks": rec["fill_in_blocks"],
                   "rate_gflops": t["rate_flops"] / 1e9,
                   "timed_units": t["timed_units"], "extrapolated": t["extrapolated"],
                   "predicted_solve_s": predicted, "measured_solve_s": measured,
                   "ratio": predicted / measured, "round_ratios": ratios,
                   "predicted_rounds_s": [p["predicted_s"] for p in pred],
                   "measured_rounds_s": meas, "plan_s": t_plan}
            rows.append(row)
            print(json.dumps(row), flush=True)
            out = {"machine": platform.machine(), "sapgo_source": source,
                   "rows": rows}  # (after every block)
            (ROOT / "benchmarks" / "results" / "plan.json").write_text(json.dumps(out,
                                                                              indent=1))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print()
    print("| block | photos | parameters | ordering (plan / adjust) | band width (plan / "
          "adjust) | predicted solve | measured solve | predicted / measured | rounds' ratios | "
          "plan time |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        bw = ("tree" if r.get("solver") == "tree" else
              f"{r['band_width_planned']} / {r['band_width_adjust']}")
        print(f"| {r['block']} | {r['photos']} | {r['parameters']} | "
              f"{r['ordering_planned']} / {r['ordering_adjust']} | {bw} | "
              f"{r['predicted_solve_s']:.3f} s | {r['measured_solve_s']:.3f} s | "
              f"{r['ratio']:.2f} | {' '.join(f'{x:.2f}' for x in r['round_ratios'])} | "
              f"{r['plan_s']:.2f} s |")


if __name__ == "__main__":
    main()
