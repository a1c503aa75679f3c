"""BAL problems through sapgo and through Ceres (pycolmap, pyceres), the same camera model.

How to run::

    pip install pycolmap pyceres  # benchmark-only (the bench extra; measured with 4.2.1, 2.6)
    python benchmarks/bal.py [--rounds 7] [--problems NAME ...] [--no-exact] [--exact-tight]
                             [--out PATH]

Problems: ``problem-49-7776`` (Ladybug) and ``dubrovnik-3-7`` from ../shared/datasets/bal
(or tests/data); ``--problems`` picks some of them. Writes ``benchmarks/results/bal.json``
(with every problem; a subset writes JSON only with ``--out``) and prints three Markdown
tables: every run, sapgo against the fastest Ceres configuration, and sapgo's final cost with
free intrinsics against Ceres'.

Camera model: BAL's (Rodrigues rotation, translation, f, k1, k2 per camera). sapgo imports
each camera as a photo with a camera of its own (``sapgo.formats.bal.import_bal``), with
``intrinsics="fixed"`` (stations of 6 parameters, f, k1, k2 held) or ``"adjusted"`` (stations
of 9 parameters: the photo's f, k1, k2 adjusted with it). Ceres gets the same problem in two
ways:

- *ceres*: COLMAP's bundle adjuster through pycolmap (compiled). One ``RADIAL`` camera
  (f, cx = cy = 0, k1, k2: COLMAP's radial model is BAL's) per image, ``cam_from_world`` =
  diag(1, -1, -1) (R, t) and observations (x, -y), because COLMAP's camera looks along +z
  with y down; the cost of this conversion is checked against the BAL file's own initial
  cost before anything is timed. COLMAP's reprojection error sets the residual of a point
  behind its camera to zero, so its cost is not quite BAL's (problem-49-7776: initial cost
  8.508021e5 instead of 8.509125e5): each row also holds the BAL cost of COLMAP's solution
  (``final_cost_recomputed``, by this script).
- *ceres (exact)*: Ceres through pyceres with BAL's own reprojection error written in Python
  (Snavely's functor, analytic derivatives): the exact BAL cost. Its time is the Python
  callbacks (about 4.4 s per iteration on problem-49-7776), not a speed comparison; it is
  the reference for the final cost. With ``--no-exact`` it is skipped.

Two comparisons, each at two tolerances:

- **intrinsics fixed**: rotations, translations and points adjusted; f, k1, k2 held.
- **intrinsics free** (all 9 camera parameters, the usual BAL benchmark): f, k1, k2 of each
  camera adjusted too.

Settings. Ceres: Levenberg-Marquardt, 2 threads, COLMAP's adjuster with SPARSE_SCHUR and
with DENSE_SCHUR (its best configuration for these sizes; the faster is its entry in the
summary), the exact functor with DENSE_SCHUR. sapgo: Levenberg-Marquardt (a free network).
Tolerances: *default* = Ceres' (function 1e-6, gradient 1e-10, parameter 1e-8, 100
iterations), sapgo ``tol_cost`` 1e-6 like Ceres' function tolerance, ``max_iterations`` 100,
its other tolerances its defaults; *tight* = Ceres function 1e-12, gradient 1e-16, parameter
1e-14, 500 iterations; sapgo ``tol_cost`` 1e-12, ``max_iterations`` 500 and its correction
tolerances (``tol_position``, ``tol_angle``, ``tol_sigma0``) 1e-14 / 1e-14 / 1e-12, so that
only the cost criterion (or the iteration limit) stops it; whether each run converged is
recorded. The exact functor runs with free intrinsics at the tight tolerances only with
``--exact-tight`` (up to 500 iterations at about 4.4 s: more than half an hour on
problem-49-7776).

The target (issue: "problem-49-7776: our final cost equal to Ceres' converged cost within
0.1 %"): the reference is the exact Ceres run with free intrinsics at the default
tolerances. For sapgo's free-intrinsics runs (default and tight) the script prints and
stores (``cost_check`` in the JSON) the relative difference (sapgo - Ceres) / Ceres of the
final cost to that run, to the exact tight run when there is one, and to COLMAP's run at the
same tolerance (its fastest configuration): to COLMAP's own cost (a different function, see
above) and to the BAL cost of COLMAP's solution; and whether it is within 0.1 % of the
reference, or lower or higher (the reference stops on Ceres' function tolerance, so a lower
cost is possible).

dubrovnik-3-7 with free intrinsics is underdetermined (38 residuals, 48 unknowns less the 7
of the datum): Ceres drives its cost to rounding noise, sapgo refuses it (no redundancy: the
row records the refusal), and no relative difference is computed.

Cost = 1/2 sum of squared residuals in pixels (Ceres' definition); sapgo's final cost is
checked against the BAL cost of its exported solution (``final_cost_recomputed``; a warning
if they differ by more than 1e-6). Time: sapgo's ``adjust`` wall time (numba warmed;
ordering, checks and writing the project included) and its time per iteration (build +
solve + update); COLMAP: problem construction plus ``solve()``, and its minimizer time per
iteration; the exact functor: ``solve()`` and that divided by the iterations. sapgo runs
twice in each round: with its precision pass (the default: the stations' and points'
standard deviations, the observations' redundancy numbers and tests, which Ceres does not
compute) and with ``precision="none"`` (``--precision none``: the work Ceres does).
``--rounds`` interleaved rounds (default 7: sapgo, sapgo without precision, each COLMAP
configuration, in turn, the machine's load average recorded before each round; a
configuration whose run took over 10 s runs once): each row gives the median time to
solution and per iteration with the spread (min-max) of its runs; the fastest COLMAP
configuration is the one of lowest median. The exact functor runs once.

COLMAP doing sapgo's work. sapgo's time to solution includes reading its project, writing the
adjusted one and (by default) the precision pass; COLMAP's includes none of them. So in every
round, after the solve of the first COLMAP configuration (SPARSE_SCHUR; the covariance does
not depend on the linear solver that reached the solution) and outside its timing, two more
figures are measured as colmap.py measures them (see there):

- COLMAP's covariance, ``pycolmap.estimate_ba_covariance(BACovarianceOptions(params=ALL),
  rec, ba)``: the marginal covariances of the poses (and of f, k1, k2 with free intrinsics)
  from a dense inverse of the factor of their Schur complement (8 (6 + 3 with free
  intrinsics)^2 cameras^2 bytes; not run where that exceeds half the physical memory), and
  the points' covariances *conditional* on all other variables held (each point's own 3 x 3
  block inverted), cheaper than sapgo's marginal point covariances; checked (not None, every
  pose 6 x 6, finite, positive diagonal). A BAL problem has no datum (no control, no gauge
  fixed by the adjuster), so its Schur complement on the poses is singular: on the adjuster
  that solved, COLMAP refuses it (None, "rank deficient": dubrovnik-3-7) or, its rank test
  counting exactly zero pivots only, inverts it into numbers without meaning
  (problem-49-7776). That attempt is timed and kept (``free_network``); the covariance
  counted is timed on a second CeresBundleAdjuster built, not solved, on the adjusted
  Reconstruction with COLMAP's ``THREE_POINTS`` gauge (three points held, every pose keeps its
  6 x 6; building it, ``gauge_problem_setup_s``, not counted). dubrovnik-3-7 with free
  intrinsics has no redundancy (sapgo refuses it; no summary row).
- COLMAP's file work: the starting Reconstruction written once per problem as a binary model
  (``write_binary``, outside any timing); each round times reading it
  (``pycolmap.Reconstruction(dir)``) and writing the adjusted one into an empty directory.

The SPARSE_SCHUR rows hold them (``colmap_covariance``, ``colmap_file_work``: the runs, their
medians and spreads); the summary adds ``colmap_best_file_to_file_s`` = read + the fastest
configuration's median time to solution + write, against sapgo with ``precision="none"``
(``ratio_file_to_file_precision_none``), and ``colmap_best_plus_covariance_s`` = the fastest
configuration's median + the median covariance (None, with
``colmap_best_plus_covariance_note``, where it was not run or failed), against sapgo with its
precision pass (``ratio_to_solution_with_covariance``); ratios sapgo / COLMAP like the others.
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
from sapgo.formats.bal import bal_cost, export_bal, import_bal, read_bal, rodrigues

sys.path.insert(0, str(Path(__file__).parent))
from colmap import (capture_stdout, colmap_covariance, colmap_file_work,  # noqa: E402
                    covariance_plan, load_average, median_of,
                    parse_progress, same_work, span_runs, summarize_covariance,
                    summarize_file_work, write_model)

ROOT = Path(__file__).resolve().parents[1]
PROBLEMS = {"problem-49-7776": "problem-49-7776-pre.txt",
            "dubrovnik-3-7": "dubrovnik-3-7-pre.txt"}
FLIP = np.diag([1.0, -1.0, -1.0])
DEFAULT_TOL = {"function_tolerance": 1e-6, "gradient_tolerance": 1e-10,
               "parameter_tolerance": 1e-8, "max_num_iterations": 100}
TIGHT_TOL = {"function_tolerance": 1e-12, "gradient_tolerance": 1e-16,
             "parameter_tolerance": 1e-14, "max_num_iterations": 500}
#: sapgo's options per tolerance (besides progress): tol_cost = Ceres' function tolerance;
#: tight also makes the correction criteria negligible, so that the cost criterion decides.
SAPGO_TOL = {"default": {"tol_cost": 1e-6, "max_iterations": 100},
             "tight": {"tol_cost": 1e-12, "max_iterations": 500, "tol_position": 1e-14,
                       "tol_angle": 1e-14, "tol_sigma0": 1e-12}}
TOLERANCES = {"default": DEFAULT_TOL, "tight": TIGHT_TOL}
COLMAP_SOLVERS = ("SPARSE_SCHUR", "DENSE_SCHUR")
#: the issue's target: sapgo's final cost within this fraction of Ceres' (exact, free, default)
TARGET = 1e-3


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


def run_ceres(d, pycolmap, solver, tol, refine_intrinsics, threads=2, keep=False):
    """COLMAP's adjuster on the BAL problem ``d``; with ``keep`` returns ``(row,
    reconstruction, bundle adjuster, options, config)``: the adjusted Reconstruction and the
    CeresBundleAdjuster that solved it, for :func:`colmap_extras`."""
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
    termination = str(cs.termination_type).split(".")[-1]
    row = {"tool": "ceres", "solver": solver, "intrinsics": "free" if refine_intrinsics
           else "fixed", "threads": threads, "tolerances": dict(tol),
           "initial_cost": cs.initial_cost,
           "final_cost": cs.final_cost, "final_cost_recomputed": colmap_cost(rec, d),
           "iterations": its, "successful_steps": cs.num_successful_steps,
           "termination": termination, "converged": termination == "CONVERGENCE",
           "time_to_solution_s": t3 - t1,
           "s_per_iteration": cs.minimizer_time_in_seconds / max(its, 1),
           "log": parse_progress(out["text"])}
    return (row, rec, ba, opts, config) if keep else row


def colmap_extras(d, pycolmap, solver, tol, refine_intrinsics, plan, model_dir, scratch):
    """:func:`run_ceres`, then, outside its timing, COLMAP's covariance of its solution and
    COLMAP's file work (colmap.py's ``colmap_covariance`` and ``colmap_file_work``), under
    the row's private keys ``_covariance`` and ``_file_work`` (taken out by main).

    A BAL problem has no datum (COLMAP's adjuster fixes no gauge here, nor does the
    problem), so the Schur complement on the poses is singular (7 degrees of freedom). On the
    adjuster that solved, ``estimate_ba_covariance`` either refuses it (None: dubrovnik-3-7)
    or, its rank test counting exactly zero pivots only, returns the inverse of a singular
    matrix, numbers without meaning (problem-49-7776). That attempt is timed and kept
    (``free_network``); the covariance counted is taken on a second CeresBundleAdjuster built
    (not solved) on the adjusted Reconstruction with COLMAP's ``THREE_POINTS`` gauge (three
    points held: every pose keeps its 6 x 6 covariance): ``gauge``, the time to build it
    ``gauge_problem_setup_s``, not counted."""
    row, rec, ba, opts, config = run_ceres(d, pycolmap, solver, tol, refine_intrinsics,
                                           keep=True)
    cov = colmap_covariance(rec, ba, pycolmap, plan, solver, wait=False)
    if "skipped" not in plan:
        gauged = pycolmap.BundleAdjustmentConfig()
        for image_id in config.images:
            gauged.add_image(image_id)
        gauged.fix_gauge(pycolmap.BundleAdjustmentGauge.THREE_POINTS)
        t0 = time.perf_counter()
        ba3 = pycolmap.create_default_ceres_bundle_adjuster(opts, gauged, rec)
        setup = time.perf_counter() - t0
        cov = dict(colmap_covariance(rec, ba3, pycolmap, plan, solver, wait=False),
                   gauge="THREE_POINTS (for the covariance only)",
                   gauge_problem_setup_s=setup, free_network=dict(cov, gauge="none"))
        del ba3
    row["_covariance"] = cov
    row["_file_work"] = colmap_file_work(model_dir, rec, scratch, pycolmap, wait=False)
    return row


def _stopped_by(s, tol_cost):
    """What ended a sapgo run: "cost change" (an accepted step lowered the cost by at most
    ``tol_cost``), "corrections" (sapgo's correction and sigma0 criteria), "no lower cost"
    (the damping ran out) or "max_iterations"."""
    if not s.converged:
        return "max_iterations"
    log = s.iteration_log
    if log and log[-1].get("step") == "rejected":
        return "no lower cost"
    costs = [s.initial_cost] + [float(r["cost"]) for r in log if r.get("step") != "rejected"]
    if len(costs) >= 2 and costs[-2] - costs[-1] <= tol_cost * costs[-2]:
        return "cost change"
    return "corrections"


def run_sapgo(path, workdir, tol_name, intrinsics, precision="full"):
    """sapgo on the BAL file ``path``: ``intrinsics`` "fixed" or "adjusted" (import_bal's),
    the options of ``SAPGO_TOL[tol_name]``, the precision pass ``precision``."""
    proj = Path(workdir) / "p.h5"
    import_bal(path, proj, force=True, intrinsics=intrinsics)
    opts = SAPGO_TOL[tol_name]
    t0 = time.perf_counter()
    try:
        s = sapgo.adjust(proj, sapgo.Options(progress=False, precision=precision, **opts))
    except sapgo.SapgoError as exc:  # e.g. no redundancy: more unknowns than observations
        return {"tool": "sapgo", "solver": "banded (Levenberg-Marquardt)",
                "intrinsics": "free" if intrinsics == "adjusted" else "fixed",
                "import_intrinsics": intrinsics, "options": dict(opts), "precision": precision,
                "tol_cost": opts["tol_cost"], "error": str(exc).split(": ", 1)[-1],
                "initial_cost": None, "final_cost": None, "iterations": 0,
                "converged": False, "time_to_solution_s": time.perf_counter() - t0,
                "s_per_iteration": None}
    wall = time.perf_counter() - t0
    out = Path(workdir) / "adjusted.txt"
    export_bal(proj, out)
    recomputed = bal_cost(read_bal(out))
    if abs(recomputed - s.final_cost) > 1e-6 * max(s.final_cost, 1e-12 * s.initial_cost):
        print(f"  warning: {path.name} ({intrinsics}, {tol_name}): sapgo's final cost "
              f"{s.final_cost:.9e}, the BAL cost of its exported solution {recomputed:.9e}",
              file=sys.stderr, flush=True)
    ti = s.timings_per_iteration_s
    return {"tool": "sapgo", "solver": "banded (Levenberg-Marquardt)",
            "intrinsics": "free" if intrinsics == "adjusted" else "fixed",
            "import_intrinsics": intrinsics, "options": dict(opts), "precision": precision,
            "tol_cost": opts["tol_cost"], "initial_cost": s.initial_cost,
            "final_cost": s.final_cost, "final_cost_recomputed": recomputed,
            "iterations": s.iterations, "converged": s.converged,
            "stopped_by": _stopped_by(s, opts["tol_cost"]), "termination": s.termination,
            "accepted_steps": sum(1 for r in s.iteration_log if r.get("step") == "accepted"),
            "time_to_solution_s": wall, "s_per_iteration": ti["build"] + ti["solve"]
            + ti["update"], "band_width": s.band_width}


def _snavely_class():
    from colmap import import_other

    pyceres = import_other("pyceres")

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
    termination = str(summ.termination_type).split(".")[-1]
    return {"tool": "ceres (exact BAL cost, Python functor)", "solver": solver,
            "intrinsics": "free" if refine_intrinsics else "fixed", "threads": 2,
            "tolerances": dict(tol),
            "initial_cost": summ.initial_cost, "final_cost": summ.final_cost,
            "iterations": its, "successful_steps": summ.num_successful_steps,
            "termination": termination, "converged": termination == "CONVERGENCE",
            "time_to_solution_s": dt, "s_per_iteration": dt / max(its, 1)}


def best(runs):
    return min(runs, key=lambda r: r["time_to_solution_s"])


#: A configuration whose run took longer than this (s) runs in one round only.
REPEAT_BELOW_S = 10.0


def median_run(runs):
    """The run of median time to solution (the lower middle of an even count), its times to
    solution and per iteration replaced by the medians of all ``runs``, which it lists
    (``runs_time_to_solution_s``, ``runs_s_per_iteration``); a refusal as it is."""
    if "error" in runs[0]:
        return runs[0]
    r = median_of(runs)
    r["time_to_solution_s"] = r.pop("median_time_to_solution_s")
    r["s_per_iteration"] = r.pop("median_s_per_iteration")
    return r


def spread(r, key, scale=1.0, nd=3, unit=" s"):
    """``median (min-max)`` of a row's runs (its figure alone when it ran once)."""
    runs = r.get({"time_to_solution_s": "runs_time_to_solution_s",
                  "s_per_iteration": "runs_s_per_iteration"}[key]) or [r[key]]
    v = f"{r[key] * scale:.{nd}f}{unit}"
    if len(runs) == 1:
        return v
    return f"{v} ({min(runs) * scale:.{nd}f}-{max(runs) * scale:.{nd}f})"



EXACT = "ceres (exact BAL cost, Python functor)"


def _pick(rows, **kw):
    """The rows whose fields equal ``kw``."""
    return [r for r in rows if all(r.get(k) == v for k, v in kw.items())]


def _rel(a, b):
    """(a - b) / b, None when b is 0."""
    return None if b == 0 else (a - b) / b


def _ratio(a, b):
    return a / b if b > 0 else float("inf")


def _fmt_rel(x):
    if x is None:
        return "-"
    return "0.0000 %" if abs(x) < 5e-7 else f"{100 * x:+.4f} %"


def summary_rows(rows):
    """sapgo against the fastest COLMAP configuration, per problem, tolerance, intrinsics."""
    out = []
    for r in _pick(rows, tool="sapgo", precision="full"):
        if "error" in r:
            continue
        key = {"problem": r["problem"], "tolerance": r["tolerance"],
               "intrinsics": r["intrinsics"]}
        ceres = _pick(rows, tool="ceres", **key)
        if not ceres:
            continue
        c = best(ceres)
        bare = _pick(rows, tool="sapgo", precision="none", **key)
        extra = {}
        if bare and "error" not in bare[0]:
            extra = dict(sapgo_precision_none_time_to_solution_s=bare[0]["time_to_solution_s"],
                         ratio_to_solution_precision_none=_ratio(
                             bare[0]["time_to_solution_s"], c["time_to_solution_s"]))
        out.append(dict(key, **extra, sapgo_time_to_solution_s=r["time_to_solution_s"],
                        sapgo_s_per_iteration=r["s_per_iteration"],
                        sapgo_iterations=r["iterations"], sapgo_final_cost=r["final_cost"],
                        ceres_solver=c["solver"], ceres_time_to_solution_s=c["time_to_solution_s"],
                        ceres_s_per_iteration=c["s_per_iteration"],
                        ceres_iterations=c["iterations"], ceres_final_cost=c["final_cost"],
                        ratio_to_solution=_ratio(r["time_to_solution_s"],
                                                 c["time_to_solution_s"]),
                        ratio_per_iteration=_ratio(r["s_per_iteration"], c["s_per_iteration"]),
                        **same_work_row(r, bare, c, ceres)))
    return out


def same_work_row(sap, bare, c, ceres):
    """COLMAP doing sapgo's work (the summary's added figures): its file work and covariance
    (medians and runs, from the row of the configuration they followed), the fastest
    configuration ``c`` read + to solution + write (``colmap_best_file_to_file_s``) against
    sapgo with ``precision="none"`` (``bare``, its rows) and ``c`` + covariance
    (``colmap_best_plus_covariance_s``) against sapgo with its precision pass (``sap``);
    ratios sapgo / COLMAP like every ratio here."""
    x = next((x for x in ceres if "colmap_file_work" in x), None)
    if x is None:
        return {}
    cov, files = x["colmap_covariance"], x["colmap_file_work"]
    gauge = next((run["gauge"] for run in cov.get("runs", []) if "gauge" in run), None)
    out = {"colmap_read_s": files.get("median_read_s"),
           "colmap_runs_read_s": files.get("runs_read_s"),
           "colmap_write_s": files.get("median_write_s"),
           "colmap_runs_write_s": files.get("runs_write_s"),
           "colmap_covariance_s": cov.get("median_covariance_s"),
           "colmap_runs_covariance_s": cov.get("runs_covariance_s"),
           "colmap_covariance_after": cov.get("after_configuration"),
           "colmap_covariance_gauge": gauge,
           "colmap_covariance_dense_matrix_bytes": cov["dense_matrix_bytes"]}
    for k in ("skipped", "error"):
        if k in cov:
            out[f"colmap_covariance_{k}"] = cov[k]
    out.update(same_work(c["time_to_solution_s"], files, cov))
    f2f, plus = out["colmap_best_file_to_file_s"], out["colmap_best_plus_covariance_s"]
    none_ok = bare and "error" not in bare[0]
    out["ratio_file_to_file_precision_none"] = (
        _ratio(bare[0]["time_to_solution_s"], f2f) if none_ok and f2f is not None else None)
    out["ratio_to_solution_with_covariance"] = (
        None if plus is None else _ratio(sap["time_to_solution_s"], plus))
    return out


def cost_check(rows):
    """sapgo's final cost with free intrinsics (default and tight) against Ceres': the exact
    functor at the default tolerances (the issue's reference) and at the tight ones if run,
    and COLMAP at the same tolerance (fastest configuration; its own cost, which zeroes the
    residuals of points behind a camera, and the BAL cost of its solution)."""
    out = []
    for r in _pick(rows, tool="sapgo", intrinsics="free", precision="full"):
        if "error" in r:
            out.append({"problem": r["problem"], "sapgo_tolerance": r["tolerance"],
                        "sapgo_error": r["error"]})
            continue
        e = {"problem": r["problem"], "sapgo_tolerance": r["tolerance"],
             "sapgo_final_cost": r["final_cost"], "sapgo_converged": r["converged"],
             "sapgo_iterations": r["iterations"]}
        for tol in ("default", "tight"):
            exact = _pick(rows, tool=EXACT, intrinsics="free", problem=r["problem"],
                          tolerance=tol)
            if exact:
                x = exact[0]
                e[f"exact_{tol}_final_cost"] = x["final_cost"]
                e[f"exact_{tol}_converged"] = x["converged"]
                e[f"rel_to_exact_{tol}"] = _rel(r["final_cost"], x["final_cost"])
        colmap = _pick(rows, tool="ceres", intrinsics="free", problem=r["problem"],
                       tolerance=r["tolerance"])
        if colmap:
            c = best(colmap)
            e.update(colmap_solver=c["solver"], colmap_final_cost=c["final_cost"],
                     colmap_final_bal_cost=c["final_cost_recomputed"],
                     colmap_converged=c["converged"],
                     rel_to_colmap=_rel(r["final_cost"], c["final_cost"]),
                     rel_to_colmap_bal_cost=_rel(r["final_cost"], c["final_cost_recomputed"]))
        ref = e.get("rel_to_exact_default")
        # an underdetermined problem (dubrovnik-3-7 with 9 free parameters per camera: 38
        # residuals, 48 unknowns) ends at a cost of rounding noise: no relative comparison
        e["zero_residual"] = r["final_cost"] <= 1e-12 * r["initial_cost"]
        # the reference stops on Ceres' function tolerance, so a lower cost is possible:
        # "lower" says sapgo is below it by more than the target, "higher" above it
        e["within_target"] = None if ref is None or e["zero_residual"] else abs(ref) <= TARGET
        e["target_side"] = None if e["within_target"] in (None, True) else \
            ("lower" if ref < 0 else "higher")
        out.append(e)
    return out


def problem_names(values):
    """``--problems`` values (short names or file names) as keys of PROBLEMS."""
    names = []
    for v in values:
        key = v.removesuffix(".gz").removesuffix(".txt").removesuffix("-pre")
        if key not in PROBLEMS:
            raise SystemExit(f"unknown problem {v!r}: one of {', '.join(PROBLEMS)}")
        names.append(key)
    return names


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7,
                    help="interleaved rounds of sapgo (with and without its precision pass) "
                         "and each COLMAP configuration; the median run is kept, with the "
                         "spread (a configuration whose run took over 10 s runs once)")
    ap.add_argument("--problems", nargs="+", default=list(PROBLEMS), metavar="NAME",
                    help=f"problems to run (default: all: {' '.join(PROBLEMS)})")
    ap.add_argument("--no-exact", dest="exact", action="store_false",
                    help="skip Ceres with the exact BAL functor (pip install pyceres; slow: "
                         "Python callbacks)")
    ap.add_argument("--exact-tight", action="store_true",
                    help="also run the exact functor with free intrinsics at the tight "
                         "tolerances (up to 500 iterations at about 4.4 s on "
                         "problem-49-7776)")
    ap.add_argument("--out", type=Path, default=None,
                    help="the JSON file (default: benchmarks/results/bal.json when every "
                         "problem runs; with --problems, none unless given)")
    args = ap.parse_args(argv)
    names = problem_names(args.problems)
    out = args.out
    if out is None and set(names) == set(PROBLEMS):
        out = Path(__file__).parent / "results" / "bal.json"
    from colmap import import_pycolmap

    pycolmap = import_pycolmap()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        warm = Path(tmp) / "warm.h5"
        for intrinsics in ("fixed", "adjusted"):  # numba: both station layouts
            # dubrovnik-3-7 with 9 parameters a camera has more unknowns than observations
            for name in ["dubrovnik-3-7"] + names:
                import_bal(find(PROBLEMS[name]), warm, force=True, intrinsics=intrinsics)
                try:
                    sapgo.adjust(warm, sapgo.Options(progress=False, max_iterations=2))
                    break
                except sapgo.SapgoError:
                    continue
        for name in names:
            path = find(PROBLEMS[name])
            d = read_bal(path)
            ref = bal_cost(d)
            rec, _ = reconstruction(d, pycolmap)
            check = colmap_cost(rec, d)
            assert abs(check - ref) <= 1e-9 * ref, (check, ref)
            # the starting values as COLMAP's binary model, read in every round
            model_dir = Path(tmp) / f"{name}-colmap-model"
            model = write_model(rec, model_dir)
            del rec
            n_cams = len(d["cameras"])
            for tol_name, tol in TOLERANCES.items():
                for intrinsics in ("fixed", "adjusted"):
                    free = intrinsics == "adjusted"
                    tag = dict(problem=name, tolerance=tol_name, file=PROBLEMS[name],
                               file_initial_cost=ref)
                    # COLMAP's covariance: 6 pose parameters a camera, with free
                    # intrinsics f, k1, k2 too (the principal point held)
                    plan = covariance_plan(n_cams, other_params=3 * n_cams if free else 0)
                    confs = [lambda p=precision: run_sapgo(path, tmp, tol_name, intrinsics, p)
                             for precision in ("full", "none")]
                    # after the first COLMAP configuration's solve: its covariance, file work
                    confs += [lambda v=solver: colmap_extras(d, pycolmap, v, tol, free, plan,
                                                             model_dir, tmp)
                              if v == COLMAP_SOLVERS[0] else run_ceres(d, pycolmap, v, tol, free)
                              for solver in COLMAP_SOLVERS]
                    runs, loads = [[] for _ in confs], []
                    for _ in range(max(1, args.rounds)):   # interleaved rounds
                        loads.append(load_average())
                        for fn, done in zip(confs, runs):
                            if done and ("error" in done[0] or done[-1]["time_to_solution_s"]
                                         > REPEAT_BELOW_S):
                                continue
                            done.append(fn())
                    block = []
                    for done in runs:
                        cov = [x.pop("_covariance") for x in done if "_covariance" in x]
                        files = [x.pop("_file_work") for x in done if "_file_work" in x]
                        row = dict(median_run(done), load_before_rounds=loads)
                        if files:
                            free_net = [c.pop("free_network") for c in cov
                                        if "free_network" in c]
                            row["colmap_covariance"] = summarize_covariance(cov, plan)
                            if free_net:  # the attempt on the adjuster that solved
                                row["colmap_covariance"]["free_network"] = \
                                    summarize_covariance(free_net, {"gauge": "none"})
                            row["colmap_file_work"] = summarize_file_work(files, model)
                            c, f = row["colmap_covariance"], row["colmap_file_work"]
                            gauge = next((x["gauge"] for x in cov if "gauge" in x), "-")
                            what = (c.get("skipped") or c.get("error") or
                                    f"{c['median_covariance_s']:.4f} s, gauge {gauge}")
                            print(f"  {name} {tol_name} COLMAP covariance (after "
                                  f"{c.get('after_configuration')}) {row['intrinsics']}: "
                                  f"{what}; read {f['median_read_s']:.4f} s, write "
                                  f"{f['median_write_s']:.4f} s", file=sys.stderr, flush=True)
                        block.append(row)
                    if args.exact and (not free or tol_name == "default" or args.exact_tight):
                        block.append(run_pyceres(d, free, tol))
                    for r in block:
                        rows.append(dict(r, **tag))
                        what = (f"refused: {r['error']}" if "error" in r else
                                f"{r['final_cost']:.6e}, {r['iterations']} iterations, "
                                f"{r['time_to_solution_s']:.3f} s")
                        print(f"  {name} {tol_name} {r['tool']} {r['solver']} "
                              f"{r['intrinsics']}: {what}", file=sys.stderr, flush=True)
    summary = summary_rows(rows)
    checks = cost_check(rows)
    refs = {(r["problem"], r["intrinsics"]): r["final_cost"]
            for r in _pick(rows, tool=EXACT, tolerance="default")}

    print("| problem | tolerance | tool | linear solver | intrinsics | initial cost | final cost "
          "| final cost vs exact Ceres (default) | converged | iterations | per iteration "
          "| to solution |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "error" in r:
            tool = r["tool"] + (", --precision none" if r.get("precision") == "none" else "")
            print(f"| {r['problem']} | {r['tolerance']} | {tool} | {r['solver']} | "
                  f"{r['intrinsics']} | - | - | - | refused: {r['error']} | - | - | - |")
            continue
        rel = _rel(r["final_cost"], refs[r["problem"], r["intrinsics"]]) \
            if (r["problem"], r["intrinsics"]) in refs else None
        if r["final_cost"] <= 1e-12 * r["initial_cost"]:
            rel = None  # rounding noise of a zero-residual problem
        conv = "yes" if r["converged"] else "no"
        tool = r["tool"]
        if tool == "sapgo":
            conv += f" ({r['stopped_by']})"
            tool += ", --precision none" if r["precision"] == "none" else ""
        print(f"| {r['problem']} | {r['tolerance']} | {tool} | {r['solver']} | "
              f"{r['intrinsics']} | {r['initial_cost']:.6e} | {r['final_cost']:.6e} | "
              f"{_fmt_rel(rel)} | {conv} | {r['iterations']} | "
              f"{spread(r, 's_per_iteration', 1000, 1, ' ms')} | "
              f"{spread(r, 'time_to_solution_s')} |")

    print("\nsapgo against the fastest COLMAP configuration (medians; sapgo's time with its "
          "precision pass, and without it: the work Ceres does; and COLMAP doing sapgo's "
          "work: reading and writing its model, and its covariance):\n")
    print("| problem | tolerance | intrinsics | sapgo to solution | sapgo --precision none "
          "| sapgo per iteration | sapgo iterations | Ceres (fastest) | Ceres to solution "
          "| Ceres per iteration | Ceres iterations | to solution, sapgo / Ceres | the same, "
          "--precision none | per iteration, sapgo / Ceres | COLMAP read model ms | COLMAP "
          "write model ms | COLMAP best file to file | sapgo --precision none / that | "
          "COLMAP covariance ms | COLMAP best + covariance | sapgo / that |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    ms = (lambda v: None if v is None else [1000 * x for x in v])
    sec = (lambda v: "-" if v is None else f"{v:.4f} s")
    for r in summary:
        none_s = r.get("sapgo_precision_none_time_to_solution_s")
        none_r = r.get("ratio_to_solution_precision_none")
        if "colmap_covariance_s" not in r:
            cov_ms = "-"
        elif r.get("colmap_covariance_skipped"):
            cov_ms = f"skipped ({r['colmap_covariance_dense_matrix_bytes'] / 1e9:.1f} GB)"
        elif r["colmap_covariance_s"] is None:
            cov_ms = f"failed: {r.get('colmap_covariance_error', 'not run')}"
        else:
            cov_ms = span_runs(ms(r["colmap_runs_covariance_s"]), 2)
        plus = r.get("colmap_best_plus_covariance_s")
        plus = sec(plus) if plus is not None else r.get("colmap_best_plus_covariance_note", "-")
        f2f_r, cov_r = (r.get("ratio_file_to_file_precision_none"),
                        r.get("ratio_to_solution_with_covariance"))
        print(f"| {r['problem']} | {r['tolerance']} | {r['intrinsics']} | "
              f"{r['sapgo_time_to_solution_s']:.3f} s | "
              f"{'-' if none_s is None else f'{none_s:.3f} s'} | "
              f"{r['sapgo_s_per_iteration'] * 1000:.1f} ms | {r['sapgo_iterations']} | "
              f"{r['ceres_solver']} | {r['ceres_time_to_solution_s']:.3f} s | "
              f"{r['ceres_s_per_iteration'] * 1000:.1f} ms | {r['ceres_iterations']} | "
              f"{r['ratio_to_solution']:.2f} | {'-' if none_r is None else f'{none_r:.2f}'} | "
              f"{r['ratio_per_iteration']:.2f} | "
              f"{span_runs(ms(r.get('colmap_runs_read_s')), 2)} | "
              f"{span_runs(ms(r.get('colmap_runs_write_s')), 2)} | "
              f"{sec(r.get('colmap_best_file_to_file_s'))} | "
              f"{'-' if f2f_r is None else f'{f2f_r:.2f}'} | {cov_ms} | {plus} | "
              f"{'-' if cov_r is None else f'{cov_r:.2f}'} |")
    gauges = sorted({r["colmap_covariance_gauge"] for r in summary
                     if r.get("colmap_covariance_gauge")})
    print("\nCOLMAP best file to file: reading the starting binary model "
          "(`pycolmap.Reconstruction(dir)`) + the fastest configuration's median time to "
          "solution + writing the adjusted model (`write_binary`), medians. COLMAP covariance: "
          "`estimate_ba_covariance(params=ALL)` after each round's "
          f"{COLMAP_SOLVERS[0]} solve (gauge: {'; '.join(gauges) or '-'}"
          + ("; a BAL problem has no datum: on the adjuster that solved COLMAP refuses its "
             "singular Schur complement or inverts it into numbers without meaning, so the "
             "covariance counted is taken with three points held, that attempt's time in the "
             "JSON as free_network" if any("THREE_POINTS" in g for g in gauges) else "")
          + "): pose (and free intrinsics) covariances marginal, "
          "from a dense inverse of the factor of their Schur complement; point covariances "
          "*conditional* on all other variables held, cheaper than sapgo's marginal ones. "
          "COLMAP best + covariance: fastest median time to solution + median covariance, "
          "against sapgo with its precision pass.")

    print("\nsapgo's final cost with free intrinsics against Ceres' "
          f"(target: within {100 * TARGET:g} % of exact Ceres, default tolerances; COLMAP's "
          "cost zeroes the residuals of points behind a camera, a different function):\n")
    print("| problem | sapgo tolerance | sapgo final cost | exact Ceres (default) | "
          "vs exact (default) | exact Ceres (tight) | vs exact (tight) | COLMAP (same "
          "tolerance) | vs COLMAP | BAL cost of COLMAP's solution | vs that | within "
          "target |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")

    def cost(e, key, conv=None):
        if key not in e:
            return "-"
        c = f"{e[key]:.6e}"
        return c if conv is None or e.get(conv, True) else c + " (not converged)"

    for e in checks:
        if "sapgo_error" in e:
            print(f"| {e['problem']} | {e['sapgo_tolerance']} | refused: {e['sapgo_error']} "
                  f"| - | - | - | - | - | - | - | - | - |")
            continue
        noise = e["zero_residual"]
        rel = (lambda k: "- (zero residual)" if noise else _fmt_rel(e.get(k)))
        target = {None: "-", True: "yes", False: f"no ({e['target_side']})"}[e["within_target"]]
        print(f"| {e['problem']} | {e['sapgo_tolerance']} | "
              f"{cost(e, 'sapgo_final_cost', 'sapgo_converged')} | "
              f"{cost(e, 'exact_default_final_cost', 'exact_default_converged')} | "
              f"{rel('rel_to_exact_default')} | "
              f"{cost(e, 'exact_tight_final_cost', 'exact_tight_converged')} | "
              f"{rel('rel_to_exact_tight') if 'exact_tight_final_cost' in e else '-'} | "
              f"{cost(e, 'colmap_final_cost', 'colmap_converged')} | {rel('rel_to_colmap')} | "
              f"{cost(e, 'colmap_final_bal_cost')} | {rel('rel_to_colmap_bal_cost')} | "
              f"{target} |")

    if out is None:
        print("\nno JSON written (a subset of the problems: use --out to keep it)")
        return
    meta = {"machine": platform.processor() or platform.machine(),
            "pycolmap": pycolmap.__version__, "sapgo": sapgo.__version__,
            "rounds": args.rounds, "problems": names, "exact": args.exact,
            "exact_tight": args.exact_tight, "target": TARGET}
    sys.path.insert(0, str(Path(__file__).parent))
    from colmap import git_state

    meta["sapgo_source"] = git_state()
    if args.exact:
        import pyceres

        meta["pyceres"] = getattr(pyceres, "__version__", None)
    out.write_text(json.dumps(dict(meta, rows=rows, summary=summary, cost_check=checks),
                              indent=1, default=_json_default))
    print(f"\nwrote {out}")


def _json_default(x):
    if isinstance(x, np.generic):
        return x.item()
    raise TypeError(f"{type(x).__name__} is not JSON serialisable")


if __name__ == "__main__":
    main()
