"""BAL problems through sapgo and through Ceres (pycolmap), the same camera model, one run.

How to run::

    pip install pycolmap          # benchmark-only dependency (measured with 4.2.1)
    python benchmarks/bal.py [--repeat 3]

Problems: ``problem-49-7776`` (Ladybug) and ``dubrovnik-3-7`` from ../shared/datasets/bal
(or tests/data). Writes ``benchmarks/results/bal.json`` and prints the Markdown table.

Camera model: BAL's (Rodrigues rotation, translation, f, k1, k2 per camera). sapgo imports
each camera as a photo with a camera of its own (``sapgo.formats.bal``). Ceres gets the same
problem through pycolmap: one ``RADIAL`` camera (f, cx = cy = 0, k1, k2: COLMAP's radial model
is BAL's) per image, ``cam_from_world`` = diag(1, -1, -1) (R, t) and observations (x, -y),
because COLMAP's camera looks along +z with y down; the costs of both conversions are checked
against the BAL file's own initial cost before anything is timed.

Two comparisons:

- **intrinsics fixed** (sapgo's model today: stations of 6 parameters): both tools adjust
  rotations, translations and points; f, k1, k2 held. Ceres: Levenberg-Marquardt,
  SPARSE_SCHUR and DENSE_SCHUR, 2 threads, its default tolerances (function 1e-6, gradient
  1e-10, parameter 1e-8); sapgo: Levenberg-Marquardt (a free network), ``tol_cost`` 1e-6 like
  Ceres' function tolerance. And both with tight tolerances (1e-12), for the converged cost.
- **all 9 parameters free** (the usual BAL benchmark): Ceres only, for reference; sapgo's
  per-photo intrinsics are not built yet.

Cost = 1/2 sum of squared residuals in pixels (Ceres' definition). Time: sapgo's ``adjust``
wall time (numba warmed; ordering, checks and writing the project included) and its time per
iteration (build + solve + update); Ceres: problem construction plus ``solve()`` and its
minimizer time per iteration.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import sapgo
from sapgo.formats.bal import bal_cost, import_bal, read_bal, rodrigues

sys.path.insert(0, str(Path(__file__).parent))
from colmap import capture_stdout, parse_progress  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
PROBLEMS = ["problem-49-7776-pre.txt", "dubrovnik-3-7-pre.txt"]
FLIP = np.diag([1.0, -1.0, -1.0])
DEFAULT_TOL = {"function_tolerance": 1e-6, "gradient_tolerance": 1e-10,
               "parameter_tolerance": 1e-8, "max_num_iterations": 100}
TIGHT_TOL = {"function_tolerance": 1e-12, "gradient_tolerance": 1e-16,
             "parameter_tolerance": 1e-14, "max_num_iterations": 500}


def find(name):
    for d in (ROOT.parent / "shared" / "datasets" / "bal", ROOT / "tests" / "data"):
        for p in (d / name, d / (name + ".gz")):
            if p.exists():
                return p
    raise FileNotFoundError(name)


def reconstruction(d, pycolmap):
    """The BAL problem as a pycolmap Reconstruction (see the module docstring)."""
    cams, pts = d["cameras"], d["points"]
    rec = pycolmap.Reconstruction()
    half = np.zeros(len(cams))
    np.maximum.at(half, d["obs_camera"], np.abs(d["obs_xy"]).max(axis=1))
    R = FLIP @ rodrigues(cams[:, :3])
    t = cams[:, 3:6] @ FLIP
    c, j, xy = d["obs_camera"], d["obs_point"], d["obs_xy"]
    order = np.lexsort((np.arange(len(c)), c))
    bounds = np.searchsorted(c[order], np.arange(len(cams) + 1))
    index_in_image = np.empty(len(c), np.int64)
    for k in range(len(cams)):
        size = int(2 * np.ceil(half[k] + 1))
        rec.add_camera_with_trivial_rig(pycolmap.Camera(
            model="RADIAL", width=size, height=size,
            params=[cams[k, 6], 0.0, 0.0, cams[k, 7], cams[k, 8]], camera_id=k + 1))
        a, b = bounds[k], bounds[k + 1]
        index_in_image[order[a:b]] = np.arange(b - a)
        kp = np.column_stack([xy[order[a:b], 0], -xy[order[a:b], 1]])
        img = pycolmap.Image(name=str(k), keypoints=kp, camera_id=k + 1, image_id=k + 1)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(R[k]), t[k]))
    config = pycolmap.BundleAdjustmentConfig()
    for k in range(len(cams)):
        config.add_image(k + 1)
    porder = np.lexsort((np.arange(len(j)), j))
    pb = np.searchsorted(j[porder], np.arange(len(pts) + 1))
    for q in range(len(pts)):
        track = pycolmap.Track()
        for o in porder[pb[q]:pb[q + 1]]:
            track.add_element(int(c[o]) + 1, int(index_in_image[o]))
        rec.add_point3D(pts[q], track)
    return rec, config


def colmap_cost(rec, d):
    """1/2 sum of squared reprojection errors of a Reconstruction (pixels), by this script."""
    total = 0.0
    for img in rec.images.values():
        cam = rec.cameras[img.camera_id]
        for p2 in img.points2D:
            if not p2.has_point3D():
                continue
            X = rec.points3D[p2.point3D_id].xyz
            q = img.cam_from_world() * X  # points behind the camera count too, as in Ceres
            f, cx, cy, k1, k2 = cam.params
            u, v = q[0] / q[2], q[1] / q[2]
            r2 = u * u + v * v
            dd = 1 + k1 * r2 + k2 * r2 * r2
            proj = np.array([f * dd * u + cx, f * dd * v + cy])
            total += float(((proj - p2.xy) ** 2).sum())
    return 0.5 * total


def run_ceres(d, pycolmap, solver, tol, refine_intrinsics, threads=2):
    import pycolmap.pyceres as pc

    rec, config = reconstruction(d, pycolmap)
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = refine_intrinsics
    opts.refine_extra_params = refine_intrinsics
    opts.refine_principal_point = False
    opts.refine_rig_from_world = True
    opts.refine_points3D = True
    opts.print_summary = False
    opts.ceres.auto_select_solver_type = False
    opts.ceres.min_num_residuals_for_cpu_multi_threading = 0
    opts.ceres.use_gpu = False
    so = opts.ceres.solver_options
    so.num_threads = threads
    so.minimizer_progress_to_stdout = True
    so.logging_type = pc.LoggingType.PER_MINIMIZER_ITERATION
    so.linear_solver_type = getattr(pc.LinearSolverType, solver)
    for k, v in tol.items():
        setattr(so, k, v)
    with capture_stdout() as out:
        t1 = time.perf_counter()
        ba = pycolmap.create_default_ceres_bundle_adjuster(opts, config, rec)
        summary = ba.solve()
        t3 = time.perf_counter()
    cs = summary.ceres_summary
    its = cs.num_successful_steps + cs.num_unsuccessful_steps
    return {"tool": "ceres", "solver": solver, "intrinsics": "free" if refine_intrinsics
            else "fixed", "tolerances": dict(tol), "initial_cost": cs.initial_cost,
            "final_cost": cs.final_cost, "final_cost_recomputed": colmap_cost(rec, d),
            "iterations": its, "successful_steps": cs.num_successful_steps,
            "termination": str(cs.termination_type).split(".")[-1],
            "time_to_solution_s": t3 - t1,
            "s_per_iteration": cs.minimizer_time_in_seconds / max(its, 1),
            "log": parse_progress(out["text"])}


def run_sapgo(path, workdir, tol_cost, max_iterations):
    proj = Path(workdir) / "p.h5"
    import_bal(path, proj, force=True)
    t0 = time.perf_counter()
    s = sapgo.adjust(proj, sapgo.Options(progress=False, tol_cost=tol_cost,
                                         max_iterations=max_iterations))
    wall = time.perf_counter() - t0
    ti = s.timings_per_iteration_s
    return {"tool": "sapgo", "solver": "banded (Levenberg-Marquardt)", "intrinsics": "fixed",
            "tol_cost": tol_cost, "initial_cost": s.initial_cost, "final_cost": s.final_cost,
            "iterations": s.iterations, "converged": s.converged,
            "accepted_steps": sum(1 for r in s.iteration_log if r.get("step") == "accepted"),
            "time_to_solution_s": wall, "s_per_iteration": ti["build"] + ti["solve"]
            + ti["update"], "band_width": s.band_width}


def _snavely_class():
    import pyceres

    def skew(v):
        return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])

    class Snavely(pyceres.CostFunction):
        """BAL's reprojection error. Parameter blocks: the camera (rotation vector and
        translation, 6; with f, k1, k2, 9) and the point (3). ``intr``: the fixed (f, k1, k2)
        of a 6-parameter camera."""

        def __init__(self, xy, intr=None):
            super().__init__()
            self.xy = xy
            self.intr = intr
            self.set_num_residuals(2)
            self.set_parameter_block_sizes([6 if intr is not None else 9, 3])

        def Evaluate(self, parameters, residuals, jacobians):
            cam, X = parameters[0], parameters[1]
            w, t = cam[:3], cam[3:6]
            f, k1, k2 = self.intr if self.intr is not None else cam[6:9]
            th2 = w @ w
            th = np.sqrt(th2)
            if th > 1e-12:
                K = skew(w / th)
                R = np.eye(3) + np.sin(th) * K + (1 - np.cos(th)) * K @ K
            else:
                R = np.eye(3) + skew(w)
            P = R @ X + t
            p = -P[:2] / P[2]
            r2 = p @ p
            d = 1 + k1 * r2 + k2 * r2 * r2
            residuals[:] = f * d * p - self.xy
            if jacobians is None:
                return True
            dp_dP = np.array([[-1 / P[2], 0.0, P[0] / P[2] ** 2],
                              [0.0, -1 / P[2], P[1] / P[2] ** 2]])
            dd_dp = (k1 + 2 * k2 * r2) * 2 * p
            J_P = f * (d * np.eye(2) + np.outer(p, dd_dp)) @ dp_dP
            if jacobians[0] is not None:
                if th > 1e-12:  # d(R X)/dw (Gallego and Yezzi 2015)
                    dRX = -R @ skew(X) @ (np.outer(w, w) + (R.T - np.eye(3)) @ skew(w)) / th2
                else:
                    dRX = -skew(R @ X)
                Jc = np.zeros((2, 6 if self.intr is not None else 9))
                Jc[:, :3] = J_P @ dRX
                Jc[:, 3:6] = J_P
                if self.intr is None:
                    Jc[:, 6] = d * p
                    Jc[:, 7] = f * r2 * p
                    Jc[:, 8] = f * r2 * r2 * p
                jacobians[0][:] = Jc.ravel()
            if jacobians[1] is not None:
                jacobians[1][:] = (J_P @ R).ravel()
            return True

    return Snavely


def run_pyceres(d, refine_intrinsics, tol, solver="DENSE_SCHUR"):
    """Ceres with BAL's own reprojection error (Snavely's functor, in Python with analytic
    derivatives): the exact cost, points behind a camera included. Its time is dominated by
    the Python callbacks and is not a speed comparison."""
    import pyceres

    Snavely = _snavely_class()
    cams, pts = d["cameras"].copy(), d["points"].copy()
    blocks = [np.ascontiguousarray(cams[k] if refine_intrinsics else cams[k, :6])
              for k in range(len(cams))]
    pblocks = [np.ascontiguousarray(pts[k]) for k in range(len(pts))]
    prob = pyceres.Problem()
    for c, j, xy in zip(d["obs_camera"], d["obs_point"], d["obs_xy"]):
        cf = Snavely(xy.copy(), None if refine_intrinsics else cams[c, 6:9].copy())
        prob.add_residual_block(cf, None, [blocks[c], pblocks[j]])
    opts = pyceres.SolverOptions()
    opts.linear_solver_type = getattr(pyceres.LinearSolverType, solver)
    for k, v in tol.items():
        setattr(opts, k, v)
    opts.num_threads = 2
    summ = pyceres.SolverSummary()
    t0 = time.perf_counter()
    pyceres.solve(opts, prob, summ)
    dt = time.perf_counter() - t0
    its = summ.num_successful_steps + summ.num_unsuccessful_steps
    return {"tool": "ceres (exact BAL cost, Python functor)", "solver": solver,
            "intrinsics": "free" if refine_intrinsics else "fixed", "tolerances": dict(tol),
            "initial_cost": summ.initial_cost, "final_cost": summ.final_cost,
            "iterations": its, "successful_steps": summ.num_successful_steps,
            "termination": str(summ.termination_type).split(".")[-1],
            "time_to_solution_s": dt, "s_per_iteration": dt / max(its, 1)}


def best(runs):
    return min(runs, key=lambda r: r["time_to_solution_s"])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--no-exact", dest="exact", action="store_false",
                    help="skip Ceres with the exact BAL functor (pip install pyceres; slow: "
                         "Python callbacks)")
    args = ap.parse_args(argv)
    import pycolmap

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        warm = Path(tmp) / "warm.h5"
        import_bal(find(PROBLEMS[1]), warm)
        sapgo.adjust(warm, sapgo.Options(progress=False))
        for name in PROBLEMS:
            path = find(name)
            d = read_bal(path)
            ref = bal_cost(d)
            rec, _ = reconstruction(d, pycolmap)
            check = colmap_cost(rec, d)
            assert abs(check - ref) <= 1e-9 * ref, (check, ref)
            for tol_name, tol in (("default", DEFAULT_TOL), ("tight", TIGHT_TOL)):
                runs = [run_sapgo(path, tmp, tol["function_tolerance"],
                                  tol["max_num_iterations"]) for _ in range(args.repeat)]
                rows.append(dict(best(runs), problem=name, tolerance=tol_name,
                                 file_initial_cost=ref))
                for solver in ("SPARSE_SCHUR", "DENSE_SCHUR"):
                    runs = [run_ceres(d, pycolmap, solver, tol, False)
                            for _ in range(args.repeat)]
                    rows.append(dict(best(runs), problem=name, tolerance=tol_name,
                                     file_initial_cost=ref))
                runs = [run_ceres(d, pycolmap, "DENSE_SCHUR", tol, True)
                        for _ in range(args.repeat)]
                rows.append(dict(best(runs), problem=name, tolerance=tol_name,
                                 file_initial_cost=ref))
                if args.exact:
                    rows.append(dict(run_pyceres(d, False, tol), problem=name,
                                     tolerance=tol_name, file_initial_cost=ref))
                    if tol_name == "default":
                        rows.append(dict(run_pyceres(d, True, tol), problem=name,
                                         tolerance=tol_name, file_initial_cost=ref))
    for r in rows:
        print(f"| {r['problem']} | {r['tolerance']} | {r['tool']} | {r['solver']} | "
              f"{r['intrinsics']} | {r['initial_cost']:.6e} | {r['final_cost']:.6e} | "
              f"{r['iterations']} | {r['s_per_iteration'] * 1000:.1f} ms | "
              f"{r['time_to_solution_s']:.3f} s |")
    out = Path(__file__).parent / "results" / "bal.json"
    out.write_text(json.dumps({"machine": platform.processor() or platform.machine(),
                               "pycolmap": pycolmap.__version__, "sapgo": sapgo.__version__,
                               "rows": rows}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
