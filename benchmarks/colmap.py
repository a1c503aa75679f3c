"""sapgo against COLMAP's bundle adjuster (pycolmap, Ceres inside) on the same blocks.

How to run::

    pip install pycolmap          # benchmark-only dependency (4.x; measured with 4.2.1)
    python benchmarks/colmap.py [--sizes 1000,10000] [--rounds 7] [--dir DIR]

A few minutes on 2 cores (DENSE_SCHUR at 1 000 photos alone takes about 40 s). Run it on an
otherwise idle machine: before every timed run the script waits (up to 2 minutes) until other
processes use less than a tenth of a core, and records the CPU time other processes took
during the run (``foreign_cpu_s``). Writes ``benchmarks/results/colmap.json`` and prints the
Markdown table for README.md.

What is compared. For each size a SAPGO-P block is generated (9-point pattern; 1 000 photos =
10 strips of 100, 10 000 photos = 20 strips of 500; one full control point per 25 photos,
*fixed*: ``control_sigma=0``; all other points are check points, i.e. unknown tie points to
both tools). Both tools start from the same file, so from the same observations and the same
starting values (the generator's perturbed stations and intersected points):

- sapgo: ``sapgo.adjust`` on a fresh copy of the unordered file, default ``Options``
  (Gauss-Newton; the ordering is part of its time; the precision pass too: the stations'
  and points' standard deviations and the observations' redundancy numbers and tests,
  which COLMAP does not compute), numba kernels warmed beforehand on a small block; and
  the same with ``precision="none"`` (``--precision none``): the work COLMAP does, the
  adjusted orientations and points, written to the project
  (``speedup_time_to_solution_precision_none``).
- COLMAP: a ``pycolmap.Reconstruction`` built from the file: one ``PINHOLE`` camera per sapgo
  camera at ``S_PX`` pixels per mm (fx = fy = S_PX f, principal point at the format centre),
  ``cam_from_world`` R = diag(1,-1,-1) M, t = -R (Xc - origin) for sapgo's object-to-image
  rotation M = R3(kappa) R2(phi) R1(omega), image points x_px = cx + S_PX (x - x0),
  y_px = cy - S_PX (y - y0), object coordinates relative to the mean station position. The
  mapping is checked against sapgo's own projection kernel before anything is timed.
  Intrinsics constant, control points constant (``BundleAdjustmentConfig.add_constant_point``),
  no gauge fixing, trivial loss, every residual of weight 1 (sapgo: all sigmas equal). Ceres
  (Levenberg-Marquardt) on 2 threads (``min_num_residuals_for_cpu_multi_threading = 0``, or
  COLMAP would run the 1 000-photo block on one), ``auto_select_solver_type`` off, each Schur
  solver the wheel supports: SPARSE_SCHUR (SuiteSparse; Eigen and Accelerate sparse are not
  built in), DENSE_SCHUR (1 000 photos only: the dense reduced camera matrix of 10 000 photos
  would take 29 GB), ITERATIVE_SCHUR with SCHUR_JACOBI, and SPARSE_SCHUR with an initial trust
  region radius of 1e16, i.e. practically undamped steps from the start, as Gauss-Newton.
  Tolerances: function 1e-10, gradient 1e-10, parameter 1e-12, at most 50 iterations.

Measured in ``--rounds`` interleaved rounds (in each round sapgo, sapgo without its
precision pass, then every COLMAP
configuration, each on a fresh copy; a tool whose run took over 10 s runs once): the run of
median time to solution is reported for each, with the spread (min-max) of its times to
solution and seconds per iteration, and the machine's load average before each round. Iterations: sapgo's Gauss-Newton iterations; Ceres' linear solves (one linearisation
and one linear solve each; a rejected LM step would count too). Seconds per iteration: sapgo
build + solve + update over its iterations; Ceres' minimizer time over its iterations. Time to
solution: sapgo's ``adjust`` wall time (ordering, checks, reading and writing the project file
included); COLMAP: building the Ceres problem from the Reconstruction plus ``solve()`` (Ceres'
preprocessor, minimizer and postprocessor); building the Reconstruction from the file in
Python is not counted. Final image RMS in um, computed by this script the same way for both
tools from the adjusted values (sqrt of the mean of the squared image residuals per
coordinate over all observations, residuals in mm x 1000), beside sapgo's own logged value
and the RMS of the residuals it stores. From Ceres' per-iteration log
(``minimizer_progress_to_stdout``, captured) also the iteration and the time at which Ceres
first gets within 1e-6 (relative) of sapgo's final RMS. The best COLMAP configuration is the
fastest to solution among those ending within 1e-3 of sapgo's RMS; ``speedup_per_iteration``
is its seconds per iteration over sapgo's.

COLMAP doing sapgo's work. sapgo's time to solution includes reading its project file, writing
the adjusted project and (by default) the precision pass; COLMAP's includes none of them. So
two more COLMAP figures are measured in the same rounds, after the solve of the first
configuration (SPARSE_SCHUR; recorded as ``after_configuration``: every configuration counted
ends at the same solution within ``RMS_SAME``, and the covariance does not depend on the
linear solver that got there):

- its covariance (``colmap_covariance``): ``pycolmap.estimate_ba_covariance(
  BACovarianceOptions(params=ALL), rec, ba)`` with the CeresBundleAdjuster that has just
  solved, timed, then checked (not None; every image's ``get_cam_cov_from_world`` 6 x 6,
  intrinsics being fixed, finite with a positive diagonal; a point's 3 x 3); the time to pull
  every pose and point covariance out into Python is beside it (``extract_all_s``, not
  counted). What COLMAP computes: it evaluates the Jacobian, eliminates the points (each
  point's 3 x 3 block of J^T J, damped by 1e-8, inverted), factors the Schur complement on
  the poses (and any other variables) with a sparse LDL^T and inverts the factor into a
  *dense* matrix: the pose covariances are the marginal ones, but that matrix takes
  8 (6 photos + other variables)^2 bytes, at 10 000 photos 60 000 x 60 000, 28.8 GB. Where it
  would exceed half the physical memory the covariance is not run (``skipped``, with the
  computed numbers). A point's covariance is its own 3 x 3 block inverted, i.e. *conditional*
  on all other variables held: cheaper than sapgo's marginal point covariances, which carry
  the stations' uncertainty; COLMAP computes no redundancy numbers or tests either (and does
  not scale by a variance factor). Like every COLMAP run it is repeated only while it takes
  under 10 s.
- its file work (``colmap_file_work``): the starting Reconstruction is written once per size
  as a binary model (``write_binary``, outside any timing); each round times reading it
  (``pycolmap.Reconstruction(dir)``) and writing the adjusted Reconstruction into an empty
  directory.

From the medians: ``colmap_best_file_to_file_s`` = read + the best configuration's median time
to solution + write, against sapgo with ``precision="none"``
(``speedup_file_to_file_precision_none``, COLMAP / sapgo like every speedup here), and
``colmap_best_plus_covariance_s`` = the best configuration's median time to solution + the
median covariance (None, with ``colmap_best_plus_covariance_note`` "cannot: needs N GB", where
skipped), against sapgo with its precision pass (``speedup_with_covariance``).

Each tool in a process of its own (``--sapgo-process own``, the default): sapgo's runs go to
one long-lived child process (``multiprocessing``, spawned once, its kernels warmed there),
COLMAP's stay in this one, as a user would run either tool. ``same`` runs both in this
process, as before the sixth session of 27 November. Measured (8 interleaved rounds in one
process, 1 000 photos): sapgo's precision pass took 0.030 s (median) alone, 0.053 s right
after a COLMAP solve and 0.072 s right after COLMAP's covariance; at 10 000 photos the solve
0.167 s an iteration alone and 0.195 s after a COLMAP solve. With sapgo in its own process
colmap.py's median pass at 1 000 photos was still 0.066 s: the slowdown follows COLMAP's
work on the machine, not the shared process (benchmarks/interference.py: it is gone with numpy's
huge-page advice off).
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import json
import math
import multiprocessing
import os
import platform
import re
import resource
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import sapgo

HERE = Path(__file__).resolve().parent
RESULTS = HERE / "results" / "colmap.json"

#: block sizes: photos -> generate_block parameters (9-point pattern, 1 control per 25 photos)
BLOCKS = {
    1000: {"strips": 10, "photos_per_strip": 100, "control_points": 40},
    10000: {"strips": 20, "photos_per_strip": 500, "control_points": 400},
}
S_PX = 100.0  # pixels per mm of the COLMAP images
MAX_DENSE_PHOTOS = 2000  # DENSE_SCHUR only up to this many photos (6n x 6n dense matrix)
CERES_TOL = {"function_tolerance": 1e-10, "gradient_tolerance": 1e-10,
             "parameter_tolerance": 1e-12, "max_num_iterations": 50}
RMS_MATCH = 1e-6  # "reached sapgo's RMS": within this relative difference
REPEAT_BELOW_S = 10.0  # runs slower than this are not repeated
RMS_SAME = 1e-3  # a configuration counts as converged to the same solution within this


# -- the problem, read from a project ---------------------------------------------------------

def load_problem(path):
    """Cameras, stations, points and active observations of a project, adjusted or not.

    Returns a dict of arrays; ``eo``/``xyz`` are the starting values and ``eo_adj``/``xyz_adj``
    the adjusted ones (equal to the starting values when the file has no solution).
    """
    with sapgo.Project(path) as p:
        cams = p.cameras()
        st = p.read("stations", 0, p.n_stations)
        pts = p.read("points", 0, p.n_points)
        obs = p.read("observations", 0, p.n_observations)
        sc = p.solution("station_corr", 0, p.n_stations)
        pc = p.solution("point_corr", 0, p.n_points)
        res = p.solution("residuals", 0, p.n_observations) if p.has_solution else None
        n_priors = p.n_priors
    if n_priors:
        raise SystemExit(f"{path}: station priors are not supported by this benchmark")
    if np.any(cams[["k1", "k2", "k3", "p1", "p2"]].tolist()):
        raise SystemExit(f"{path}: distortion is not supported by this benchmark")
    act = obs["status"] == 0
    act &= st["status"][obs["station"]] == 0
    act &= pts["status"][obs["point"]] == 0
    cam_sigma = cams["sigma_image"][st["camera"][obs["station"]]]
    sig = np.where(obs["sigma"] > 0, obs["sigma"], cam_sigma)
    if not np.allclose(sig[act], sig[act][0], rtol=1e-12, atol=0):
        raise SystemExit(f"{path}: observations of unequal weight; COLMAP would need weights")
    kind = pts["kind"]
    csig = pts["control_sigma"]
    controlled = np.isin(kind, [1, 2, 3])
    fixed_full = (kind == 1) & (csig == 0).all(axis=1)
    if np.any(controlled & ~fixed_full):
        raise SystemExit(f"{path}: only fixed full control (control_sigma 0) is supported")
    xyz = pts["xyz"].copy()
    xyz[fixed_full] = pts["control"][fixed_full]  # sapgo sets fixed components to control
    return {
        "f": cams["focal_length"], "x0": cams["x0"], "y0": cams["y0"],
        "fmt_x": cams["format_x"], "fmt_y": cams["format_y"],
        "camera": st["camera"].astype(np.int64), "station_active": st["status"] == 0,
        "eo": st["eo"].copy(), "eo_adj": st["eo"] + sc,
        "xyz": xyz, "xyz_adj": pts["xyz"] + pc, "fixed": fixed_full,
        "point_active": pts["status"] == 0,
        "st": obs["station"][act].astype(np.int64), "pt": obs["point"][act].astype(np.int64),
        "x": obs["x"][act].copy(), "y": obs["y"][act].copy(), "sigma": float(sig[act][0]),
        "residuals": None if res is None else res[act],
    }


def rotation(eo):
    """sapgo's object-to-image rotation M = R3(kappa) R2(phi) R1(omega), shape (n, 3, 3)."""
    w, p, k = eo[:, 0], eo[:, 1], eo[:, 2]
    n = len(eo)
    one, zero = np.ones(n), np.zeros(n)
    cw, sw, cp, sp, ck, sk = np.cos(w), np.sin(w), np.cos(p), np.sin(p), np.cos(k), np.sin(k)
    R1 = np.stack([one, zero, zero, zero, cw, sw, zero, -sw, cw], 1).reshape(n, 3, 3)
    R2 = np.stack([cp, zero, -sp, zero, one, zero, sp, zero, cp], 1).reshape(n, 3, 3)
    R3 = np.stack([ck, sk, zero, -sk, ck, zero, zero, zero, one], 1).reshape(n, 3, 3)
    return R3 @ R2 @ R1


def project(M, Xc, X, prob):
    """sapgo's collinearity equations for every active observation: (x, y) in mm."""
    st, pt = prob["st"], prob["pt"]
    cam = prob["camera"][st]
    uvw = np.einsum("nij,nj->ni", M[st], X[pt] - Xc[st])
    f = prob["f"][cam]
    return (prob["x0"][cam] - f * uvw[:, 0] / uvw[:, 2],
            prob["y0"][cam] - f * uvw[:, 1] / uvw[:, 2])


def image_rms_um(M, Xc, X, prob):
    """sqrt(mean of squared image residuals per coordinate) over all active rays, in um."""
    x, y = project(M, Xc, X, prob)
    vx, vy = x - prob["x"], y - prob["y"]
    return 1000.0 * math.sqrt((np.sum(vx * vx) + np.sum(vy * vy)) / (2 * len(vx)))


# -- COLMAP -----------------------------------------------------------------------------------

D = np.diag([1.0, -1.0, -1.0])  # sapgo image frame (w < 0 in front) -> COLMAP camera (z > 0)


def intrinsics(prob, c):
    """PINHOLE parameters and image size of sapgo camera ``c``."""
    w, h = prob["fmt_x"][c] * S_PX, prob["fmt_y"][c] * S_PX
    fpx = S_PX * prob["f"][c]
    return [fpx, fpx, w / 2, h / 2], round(w), round(h)


def to_pixels(prob, x, y, cam):
    cx, cy = prob["fmt_x"][cam] * S_PX / 2, prob["fmt_y"][cam] * S_PX / 2
    return cx + S_PX * (x - prob["x0"][cam]), cy - S_PX * (y - prob["y0"][cam])


def build_reconstruction(prob, pycolmap):
    """The project as a pycolmap Reconstruction and BundleAdjustmentConfig (starting values)."""
    origin = prob["eo"][prob["station_active"], 3:].mean(axis=0)
    rec = pycolmap.Reconstruction()
    for c in range(len(prob["f"])):
        params, w, h = intrinsics(prob, c)
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(model="PINHOLE", width=w, height=h, params=params, camera_id=c + 1))
    M = rotation(prob["eo"])
    R = D @ M
    Xc = prob["eo"][:, 3:] - origin
    t = -np.einsum("nij,nj->ni", R, Xc)
    st, pt = prob["st"], prob["pt"]
    order = np.lexsort((np.arange(len(st)), st))  # observations grouped by station
    cam = prob["camera"][st]
    xp, yp = to_pixels(prob, prob["x"], prob["y"], cam)
    kp = np.column_stack([xp, yp])[order]
    idx_in_image = np.empty(len(st), np.int64)
    bounds = np.searchsorted(st[order], np.arange(len(M) + 1))
    for s in range(len(M)):
        a, b = bounds[s], bounds[s + 1]
        idx_in_image[order[a:b]] = np.arange(b - a)
        if not prob["station_active"][s]:
            continue
        img = pycolmap.Image(name=f"{s}", keypoints=kp[a:b], camera_id=int(prob["camera"][s]) + 1,
                             image_id=s + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R[s]), t[s])
        rec.add_image_with_trivial_frame(img, pose)
    config = pycolmap.BundleAdjustmentConfig()
    for s in np.flatnonzero(prob["station_active"]):
        config.add_image(int(s) + 1)
    porder = np.lexsort((np.arange(len(pt)), pt))
    pbounds = np.searchsorted(pt[porder], np.arange(len(prob["xyz"]) + 1))
    point_ids = np.zeros(len(prob["xyz"]), np.int64)
    X = prob["xyz"] - origin
    for j in range(len(X)):
        a, b = pbounds[j], pbounds[j + 1]
        if b == a:
            continue
        track = pycolmap.Track()
        for q in porder[a:b]:
            track.add_element(int(st[q]) + 1, int(idx_in_image[q]))
        pid = rec.add_point3D(X[j], track)
        point_ids[j] = pid
        if prob["fixed"][j]:
            config.add_constant_point(pid)
    return rec, config, origin, point_ids


def colmap_values(rec, prob, origin, point_ids):
    """COLMAP's current poses and points in sapgo's terms: (M, Xc, X), absolute coordinates."""
    n = len(prob["eo"])
    M = np.repeat(np.eye(3)[None], n, axis=0)
    Xc = prob["eo"][:, 3:].copy()
    for s in np.flatnonzero(prob["station_active"]):
        T = rec.image(int(s) + 1).cam_from_world()
        R = T.rotation.matrix()
        M[s] = D @ R
        Xc[s] = -R.T @ T.translation + origin
    X = prob["xyz"].copy()
    for j in np.flatnonzero(point_ids):
        X[j] = rec.point3D(int(point_ids[j])).xyz + origin
    return M, Xc, X


def verify_mapping(rec, prob, origin, pycolmap):
    """COLMAP's projection of the starting values == sapgo's, to ~1e-9 relative."""
    M, Xc, X = rotation(prob["eo"]), prob["eo"][:, 3:], prob["xyz"]
    x, y = project(M, Xc, X, prob)
    # sapgo's own kernel on the same values
    from sapgo.geometry import plain_camera, project_observations

    cams = np.array([plain_camera(f, x0, y0)
                     for f, x0, y0 in zip(prob["f"], prob["x0"], prob["y0"])])
    xy = np.empty((len(x), 2))
    project_observations(prob["st"], prob["pt"], prob["eo"], X, prob["camera"], cams, xy)
    d_sapgo = max(np.abs(xy[:, 0] - x).max(), np.abs(xy[:, 1] - y).max())
    # COLMAP: world -> camera -> image, per image
    cam = prob["camera"][prob["st"]]
    xp, yp = to_pixels(prob, x, y, cam)
    col = np.empty((len(x), 2))
    st, pt = prob["st"], prob["pt"]
    for s in np.unique(st):
        sel = np.flatnonzero(st == s)
        image = rec.image(int(s) + 1)
        p_cam = image.cam_from_world() * np.ascontiguousarray(X[pt[sel]] - origin)
        col[sel] = rec.camera(int(prob["camera"][s]) + 1).img_from_cam(p_cam)
    d_px = max(np.abs(col[:, 0] - xp).max(), np.abs(col[:, 1] - yp).max())
    scale = S_PX * float(np.abs(prob["x"]).max())  # pixels from the principal point
    rel = d_px / scale
    if d_sapgo > 1e-9 or rel > 1e-8:
        raise SystemExit(f"projection mapping check failed: sapgo kernel {d_sapgo:.3g} mm, "
                         f"COLMAP {d_px:.3g} px ({rel:.3g} relative)")
    return {"max_diff_numpy_vs_sapgo_kernel_mm": d_sapgo, "max_diff_colmap_px": d_px,
            "max_diff_colmap_relative": rel}


@contextlib.contextmanager
def capture_stdout():
    """Capture what C++ writes to file descriptor 1 (Ceres' progress log)."""
    libc = ctypes.CDLL(None)
    sys.stdout.flush()
    libc.fflush(None)
    saved = os.dup(1)
    with tempfile.TemporaryFile(mode="w+b") as tmp:
        os.dup2(tmp.fileno(), 1)
        out = {"text": ""}
        try:
            yield out
        finally:
            libc.fflush(None)
            os.dup2(saved, 1)
            os.close(saved)
            tmp.seek(0)
            out["text"] = tmp.read().decode(errors="replace")


LOG_LINE = re.compile(r"^\s*(\d+)\s+([-+0-9.eE]+)\s+([-+0-9.eE]+)\s+([-+0-9.eE]+)\s+"
                      r"([-+0-9.eE]+)\s+([-+0-9.eE]+)\s+([-+0-9.eE]+)\s+(\d+)\s+"
                      r"([-+0-9.eE]+)\s+([-+0-9.eE]+)\s*$")


def parse_progress(text):
    """Ceres' trust-region progress lines: iteration, cost, cost_change, ..., total_time."""
    rows = []
    for line in text.splitlines():
        m = LOG_LINE.match(line)
        if m:
            g = m.groups()
            rows.append({"iteration": int(g[0]), "cost": float(g[1]), "cost_change": float(g[2]),
                         "gradient": float(g[3]), "step": float(g[4]), "tr_ratio": float(g[5]),
                         "tr_radius": float(g[6]), "iter_time_s": float(g[8]),
                         "total_time_s": float(g[9])})
    return rows


def import_other(name):
    """Module ``name`` of another tool (pycolmap, pyceres), its statically linked OpenBLAS
    loaded with OpenBLAS's own spin time (28) when sapgo set its own
    (``sapgo.BLAS_TIMEOUT_SET``: the variable is read when a library loads, so sapgo's
    libraries keep 20 and the other tool runs as it does alone)."""
    import importlib

    key = "OPENBLAS_THREAD_TIMEOUT"
    old = os.environ.get(key)
    if sapgo.BLAS_TIMEOUT_SET:
        os.environ[key] = "28"
    try:
        return importlib.import_module(name)
    finally:
        if old is not None:
            os.environ[key] = old


def import_pycolmap():
    """pycolmap and its pyceres (:func:`import_other`)."""
    import_other("pycolmap.pyceres")
    return import_other("pycolmap")


def solver_configs(n_photos, pycolmap):
    import pycolmap.pyceres as pc

    L = pc.LinearSolverType
    suitesparse = pc.SparseLinearAlgebraLibraryType.SUITE_SPARSE
    cfgs = [{"name": "SPARSE_SCHUR (SuiteSparse)", "linear_solver_type": L.SPARSE_SCHUR,
             "sparse_linear_algebra_library_type": suitesparse}]
    if n_photos <= MAX_DENSE_PHOTOS:
        cfgs.append({"name": "DENSE_SCHUR (Eigen)", "linear_solver_type": L.DENSE_SCHUR,
                     "dense_linear_algebra_library_type": pc.DenseLinearAlgebraLibraryType.EIGEN})
    cfgs.append({"name": "ITERATIVE_SCHUR + SCHUR_JACOBI", "linear_solver_type": L.ITERATIVE_SCHUR,
                 "preconditioner_type": pc.PreconditionerType.SCHUR_JACOBI})
    # Levenberg-Marquardt as good as undamped from the first step, i.e. Gauss-Newton like sapgo
    cfgs.append({"name": "SPARSE_SCHUR (SuiteSparse), initial trust radius 1e16",
                 "linear_solver_type": L.SPARSE_SCHUR,
                 "sparse_linear_algebra_library_type": suitesparse,
                 "initial_trust_region_radius": 1e16})
    return cfgs


def run_colmap(prob, cfg, pycolmap, threads=2, keep=False):
    """One COLMAP bundle adjustment from the starting values; returns its figures, with
    ``keep`` as ``(figures, reconstruction, bundle adjuster, point ids)``: the adjusted
    Reconstruction and the CeresBundleAdjuster that solved it, for :func:`colmap_covariance`
    and :func:`colmap_file_work` (None on a refused configuration)."""
    import pycolmap.pyceres as pc

    t0 = time.perf_counter()
    rec, config, origin, point_ids = build_reconstruction(prob, pycolmap)
    t_build_rec = time.perf_counter() - t0
    waited = wait_for_idle()
    opts = pycolmap.BundleAdjustmentOptions()
    opts.refine_focal_length = False
    opts.refine_principal_point = False
    opts.refine_extra_params = False
    opts.refine_rig_from_world = True
    opts.refine_points3D = True
    opts.print_summary = False
    opts.ceres.auto_select_solver_type = False
    opts.ceres.min_num_residuals_for_cpu_multi_threading = 0
    opts.ceres.use_gpu = False
    so = opts.ceres.solver_options
    so.num_threads = threads
    so.minimizer_progress_to_stdout = True  # the per-iteration log, captured from fd 1
    so.logging_type = pc.LoggingType.PER_MINIMIZER_ITERATION  # COLMAP sets SILENT: no log
    for k, v in CERES_TOL.items():
        setattr(so, k, v)
    for k, v in cfg.items():
        if k != "name":
            setattr(so, k, v)
    so.max_trust_region_radius = max(so.max_trust_region_radius, so.initial_trust_region_radius)
    ok, msg = so.IsValid()
    if not ok:
        r = {"configuration": cfg["name"], "error": msg}
        return (r, None, None, None) if keep else r
    with capture_stdout() as out:
        c0 = cpu_snapshot()
        t1 = time.perf_counter()
        ba = pycolmap.create_default_ceres_bundle_adjuster(opts, config, rec)
        t2 = time.perf_counter()
        summary = ba.solve()
        t3 = time.perf_counter()
        foreign = foreign_cpu_s(c0)
    cs = summary.ceres_summary
    log = parse_progress(out["text"])
    its = cs.num_linear_solves  # one linearisation and linear solve per iteration
    n_res = cs.num_residuals  # 2 per observation
    M, Xc, X = colmap_values(rec, prob, origin, point_ids)
    rms = image_rms_um(M, Xc, X, prob)
    for row in log:  # cost = 1/2 sum r^2 in px^2
        row["image_rms_um"] = 1000.0 * math.sqrt(2 * row["cost"] / n_res) / S_PX
    r = {
        "configuration": cfg["name"],
        "linear_solver_type": str(cs.linear_solver_type_used).split(".")[-1],
        "preconditioner": str(cs.preconditioner_type_used).split(".")[-1],
        "sparse_library": str(cs.sparse_linear_algebra_library_type).split(".")[-1],
        "threads_used": cs.num_threads_used,
        "tolerances": dict(CERES_TOL),
        "termination": str(cs.termination_type).split(".")[-1],
        "message": cs.message,
        "iterations": its,
        "ceres_minimizer_iterations": cs.num_successful_steps + cs.num_unsuccessful_steps,
        "jacobian_evaluations": cs.num_jacobian_evaluations,
        "successful_steps": cs.num_successful_steps,
        "unsuccessful_steps": cs.num_unsuccessful_steps,
        "time_to_solution_s": t3 - t1,
        "s_per_iteration": cs.minimizer_time_in_seconds / max(its, 1),
        "problem_setup_s": t2 - t1,
        "ceres_total_s": cs.total_time_in_seconds,
        "ceres_preprocessor_s": cs.preprocessor_time_in_seconds,
        "ceres_minimizer_s": cs.minimizer_time_in_seconds,
        "ceres_postprocessor_s": cs.postprocessor_time_in_seconds,
        "ceres_linear_solver_s": cs.linear_solver_time_in_seconds,
        "ceres_jacobian_evaluation_s": cs.jacobian_evaluation_time_in_seconds,
        "ceres_residual_evaluation_s": cs.residual_evaluation_time_in_seconds,
        "reconstruction_from_file_s": t_build_rec,
        "foreign_cpu_s": foreign,
        "waited_for_idle_s": waited,
        "final_rms_um": rms,
        "final_rms_um_from_ceres_cost": 1000.0 * math.sqrt(2 * cs.final_cost / n_res) / S_PX,
        "initial_rms_um_from_ceres_cost": 1000.0 * math.sqrt(2 * cs.initial_cost / n_res) / S_PX,
        "num_residuals": n_res,
        "num_parameters": cs.num_effective_parameters_reduced,
        "log": log,
    }
    return (r, rec, ba, point_ids) if keep else r


# -- COLMAP's covariance and file work ---------------------------------------------------------

#: COLMAP's covariance runs only if its dense matrix takes at most this fraction of the RAM
COV_MEMORY_FRACTION = 0.5


def physical_memory_bytes():
    """The machine's physical memory in bytes (None if the system does not say)."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def covariance_plan(n_photos, other_params=0, memory=None):
    """Whether COLMAP's covariance (``pycolmap.estimate_ba_covariance``) fits in memory.

    COLMAP eliminates the points, factors the Schur complement on all other variables (6 per
    photo, plus ``other_params``: the tangent sizes of the other variable blocks, e.g. free
    intrinsics) and inverts the factor into a *dense* matrix of that order: ``8 * (6 n_photos +
    other_params)**2`` bytes. Returns the computed numbers; with ``skipped`` (the reason) when
    that exceeds ``COV_MEMORY_FRACTION`` of the physical memory (``memory`` bytes; default this
    machine's, and skipped when unknown).
    """
    n = 6 * int(n_photos) + int(other_params)
    need = 8 * n * n
    mem = physical_memory_bytes() if memory is None else int(memory)
    plan = {"params": "ALL", "photos": int(n_photos), "other_params": int(other_params),
            "dense_matrix_size": n, "dense_matrix_bytes": need, "physical_memory_bytes": mem,
            "memory_limit_bytes": None if mem is None else int(COV_MEMORY_FRACTION * mem)}
    if mem is None:
        return {"skipped": f"physical memory unknown; needs a dense {n} x {n} matrix: "
                           f"{need / 1e9:.1f} GB", **plan}
    if need > COV_MEMORY_FRACTION * mem:
        return {"skipped": f"needs a dense {n} x {n} matrix: {need / 1e9:.1f} GB", **plan}
    return plan


def colmap_covariance(rec, ba, pycolmap, plan, after, wait=True):
    """Time COLMAP's covariance of the adjustment ``ba`` (a CeresBundleAdjuster) has just solved
    on ``rec``: ``estimate_ba_covariance`` with ``params=ALL`` (poses, points and any other
    variables). ``after``: the configuration of that solve. ``wait``: wait for an idle
    machine first (:func:`wait_for_idle`). Not run when ``plan`` (:func:`covariance_plan`)
    says ``skipped``.

    Besides the time (``covariance_s``) it checks the result: not None, the pose covariance of
    every image 6 x 6 (fixed intrinsics: rotation and translation), finite, with a positive
    diagonal, and a point's 3 x 3; ``extract_all_s`` is the time to pull every image's pose
    covariance and every point's covariance out of the result (a Python loop; not part of
    ``covariance_s``). A failed check is an ``error``, its time not counted.
    """
    if "skipped" in plan:
        return {"after_configuration": after, "skipped": plan["skipped"]}
    waited = wait_for_idle() if wait else None
    options = pycolmap.BACovarianceOptions(params=pycolmap.BACovarianceOptionsParams.ALL)
    c0 = cpu_snapshot()
    t0 = time.perf_counter()
    cov = pycolmap.estimate_ba_covariance(options, rec, ba)
    dt = time.perf_counter() - t0
    foreign = foreign_cpu_s(c0)
    r = {"after_configuration": after, "covariance_s": dt,
         "cpu_s": cpu_snapshot()[1] - c0[1], "foreign_cpu_s": foreign,
         "waited_for_idle_s": waited}
    if cov is None:
        r["error"] = "estimate_ba_covariance returned None"
        return r
    image_ids = sorted(rec.images)
    point_ids = sorted(rec.points3D)
    t1 = time.perf_counter()
    cams = [cov.get_cam_cov_from_world(i) for i in image_ids]
    pts = [cov.get_point_cov(j) for j in point_ids]
    r["extract_all_s"] = time.perf_counter() - t1
    del cov  # COLMAP's dense inverse factor
    first = cams[0] if cams else None
    r["image_id_checked"] = image_ids[0] if image_ids else None
    r["cam_cov_shape"] = None if first is None else list(first.shape)
    got = [c for c in cams if c is not None]
    r["images_without_covariance"] = len(cams) - len(got)
    r["points_without_covariance"] = sum(1 for c in pts if c is None)  # constant (control)
    pt = next((c for c in pts if c is not None), None)
    r["point_cov_shape"] = None if pt is None else list(pt.shape)
    if first is None or first.shape != (6, 6) or any(c.shape != (6, 6) for c in got):
        r["error"] = f"get_cam_cov_from_world({r['image_id_checked']}): {r['cam_cov_shape']}"
        return r
    diag = np.array([np.diag(c) for c in got])
    r["pose_covariances_finite"] = bool(all(np.isfinite(c).all() for c in got))
    r["pose_variance_range"] = [float(diag.min()), float(diag.max())]
    if not r["pose_covariances_finite"] or diag.min() <= 0:
        r["error"] = "pose covariances not finite or not positive"
    elif pt is not None and pt.shape != (3, 3):
        r["error"] = f"get_point_cov: {r['point_cov_shape']}"
    return r


def write_model(rec, model_dir):
    """Write ``rec`` as a binary COLMAP model into ``model_dir`` (once, outside any timing)."""
    model_dir = Path(model_dir)
    model_dir.mkdir(parents=True, exist_ok=True)
    rec.write_binary(str(model_dir))
    files = sorted(model_dir.iterdir())
    return {"format": "COLMAP binary model", "files": [f.name for f in files],
            "model_bytes": sum(f.stat().st_size for f in files)}


def colmap_file_work(model_dir, rec, scratch, pycolmap, wait=True):
    """Time COLMAP reading the starting model (``pycolmap.Reconstruction(model_dir)``, written
    by :func:`write_model`) and writing the adjusted ``rec`` (``write_binary``) into a new,
    empty directory under ``scratch`` (removed afterwards, outside the timing)."""
    waited = wait_for_idle() if wait else None
    t0 = time.perf_counter()
    read = pycolmap.Reconstruction(str(model_dir))
    t1 = time.perf_counter()
    counts = (read.num_images(), read.num_points3D(), read.compute_num_observations())
    del read
    out = Path(tempfile.mkdtemp(dir=scratch, prefix="colmap-out-"))
    t2 = time.perf_counter()
    rec.write_binary(str(out))
    t3 = time.perf_counter()
    written = sum(f.stat().st_size for f in out.iterdir())
    shutil.rmtree(out)
    r = {"read_s": t1 - t0, "write_s": t3 - t2, "written_bytes": written,
         "waited_for_idle_s": waited}
    if counts != (rec.num_images(), rec.num_points3D(), rec.compute_num_observations()):
        r["error"] = f"the model read back has (images, points, observations) {counts}"
    return r


def _runs_figures(runs, key):
    """``runs_<key>``, ``median_<key>`` and ``spread_<key>`` ([min, max]) over ``runs``."""
    v = [r[key] for r in runs if key in r]
    return {f"runs_{key}": v, f"median_{key}": float(np.median(v)) if v else None,
            f"spread_{key}": [min(v), max(v)] if v else None}


def summarize_covariance(runs, plan):
    """COLMAP's covariance over the rounds: :func:`covariance_plan`'s numbers, the per-round
    runs and the median and spread of ``covariance_s`` (and ``extract_all_s``) of the runs
    without an error."""
    out = dict(plan)
    if "skipped" in plan:
        return out
    ok = [r for r in runs if "error" not in r]
    out["after_configuration"] = runs[0]["after_configuration"] if runs else None
    out.update(_runs_figures(ok, "covariance_s"))
    out.update(_runs_figures(ok, "extract_all_s"))
    if runs and not ok:
        out["error"] = runs[0]["error"]
    out["runs"] = runs
    return out


def summarize_file_work(runs, model):
    """COLMAP's reading and writing of its model over the rounds: medians and spreads."""
    ok = [r for r in runs if "error" not in r]
    out = dict(model, **_runs_figures(ok, "read_s"), **_runs_figures(ok, "write_s"))
    if runs and not ok:
        out["error"] = runs[0]["error"]
    out["runs"] = runs
    return out


def same_work(best_s, files, cov):
    """COLMAP doing sapgo's work, from the best configuration's median time to solution
    ``best_s``: ``colmap_best_file_to_file_s`` = read + ``best_s`` + write (medians of
    :func:`summarize_file_work`), ``colmap_best_plus_covariance_s`` = ``best_s`` + the median
    covariance (None, with ``colmap_best_plus_covariance_note``, when it was not run)."""
    read, write = files.get("median_read_s"), files.get("median_write_s")
    out = {"colmap_best_file_to_file_s": None if read is None or write is None
           else read + best_s + write}
    c = cov.get("median_covariance_s")
    out["colmap_best_plus_covariance_s"] = None if c is None else best_s + c
    if "skipped" in cov:
        out["colmap_best_plus_covariance_note"] = (
            f"cannot: needs {cov['dense_matrix_bytes'] / 1e9:.1f} GB")
    elif c is None:
        out["colmap_best_plus_covariance_note"] = f"failed: {cov.get('error')}"
    return out


def span_runs(values, nd):
    """``median (min-max)`` of a list of figures (the figure alone when there is one)."""
    if not values:
        return "-"
    if len(values) == 1:
        return fmt(values[0], nd)
    return (f"{fmt(float(np.median(values)), nd)} ({fmt(min(values), nd)}-"
            f"{fmt(max(values), nd)})")


def covariance_cell(cov, nd=2):
    """COLMAP's covariance time for a table: median (min-max), or why there is none."""
    if "skipped" in cov:
        return f"skipped ({cov['dense_matrix_bytes'] / 1e9:.1f} GB)"
    if cov.get("median_covariance_s") is None:
        return f"failed: {cov.get('error', 'not run')}"
    return span_runs(cov["runs_covariance_s"], nd)


# -- machine load ---------------------------------------------------------------------------

def cpu_snapshot():
    """(CPU seconds busy on the whole machine, CPU seconds of this process) so far."""
    try:
        with open("/proc/stat") as fh:
            v = [int(x) for x in fh.readline().split()[1:9]]
        busy = (v[0] + v[1] + v[2] + v[5] + v[6] + v[7]) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError):
        busy = float("nan")
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return busy, ru.ru_utime + ru.ru_stime


def wait_for_idle(max_wait=120.0, threshold=0.1, window=0.5):
    """Wait (at most ``max_wait`` s) until other processes use under ``threshold`` of a core.

    Returns the seconds waited, or None if the machine never became idle.
    """
    t0 = time.perf_counter()
    while True:
        c0 = cpu_snapshot()
        time.sleep(window)
        if not foreign_cpu_s(c0) > threshold * window:  # NaN (no /proc/stat): go on
            return time.perf_counter() - t0
        if time.perf_counter() - t0 > max_wait:
            print("  warning: the machine is busy; timing anyway", file=sys.stderr)
            return None


def foreign_cpu_s(start):
    """CPU seconds that other processes used since ``start`` (a :func:`cpu_snapshot`).

    A timed run on 2 cores is only as good as the machine is idle: sapgo's two-thread solver
    in particular slows down by an order of magnitude when another process keeps a core busy.
    """
    busy, own = cpu_snapshot()
    return max(0.0, (busy - start[0]) - (own - start[1]))


# -- sapgo ------------------------------------------------------------------------------------

def warm_numba(workdir):
    """Compile (or load from the cache) sapgo's kernels outside the timed runs."""
    path = workdir / "warm.h5"
    sapgo.generate_block(path, preset="sapgo-p-1", progress=False, control_sigma=0.0)
    sapgo.adjust(path, sapgo.Options(progress=False))
    path.unlink()


def run_sapgo(path, precision="full"):
    from sapgo import threads

    waited = wait_for_idle()
    looks = dict(threads.STATS)
    c0 = cpu_snapshot()
    t0 = time.perf_counter()
    summary = sapgo.adjust(path, sapgo.Options(progress=False, precision=precision))
    wall = time.perf_counter() - t0
    looks = {k: threads.STATS[k] - looks[k] for k in looks}
    foreign = foreign_cpu_s(c0)
    t = summary.timings_s
    its = summary.iterations
    prob = load_problem(path)
    rms = image_rms_um(rotation(prob["eo_adj"]), prob["eo_adj"][:, 3:], prob["xyz_adj"], prob)
    v = prob["residuals"]
    rms_stored = 1000.0 * math.sqrt(np.mean(v * v))
    phases = {k: t.get(k, 0.0) for k in ("order", "build", "solve", "update", "precision",
                                           "commit")}
    phases["other"] = t["total"] - sum(phases.values())  # checks, loading, work files, checkpoints
    return {
        "precision": precision,
        "converged": summary.converged,
        "iterations": its,
        "time_to_solution_s": wall,
        "s_per_iteration": (t["build"] + t["solve"] + t["update"]) / its,
        "final_rms_um": rms,
        "final_rms_um_sapgo_log": summary.image_rms_um,
        "final_rms_um_from_stored_residuals": rms_stored,
        "sigma0": summary.sigma0,
        "foreign_cpu_s": foreign,
        "waited_for_idle_s": waited,
        "threads_looks": looks,   # (sapgo.threads: looks, and those finding others running)
        "band_width": summary.band_width,
        "ordering": summary.ordering,
        "phases": phases,
        "phases_per_iteration_s": {k: t[k] / its for k in ("build", "solve", "update")},
        "iteration_log": [{k: r[k] for k in ("iteration", "image_rms_um", "sigma0", "build_s",
                                             "solve_s", "update_s")}
                          for r in summary.iteration_log],
        "check_points": {k: summary.check_points.get(k) for k in ("n", "sx", "sy", "sz", "sxy")},
    }


# -- the benchmark ----------------------------------------------------------------------------

def _child_warm(workdir):
    """Initialiser of the child process that runs sapgo: compile or load the kernels there."""
    warm = Path(workdir) / "child-warm"
    warm.mkdir(exist_ok=True)
    warm_numba(warm)


class SapgoProcess:
    """sapgo's runs in one long-lived process of their own (``--sapgo-process own``): a
    callable like :func:`run_sapgo`."""

    def __init__(self, workdir):
        ctx = multiprocessing.get_context("spawn")
        self.pool = ctx.Pool(1, initializer=_child_warm, initargs=(str(workdir),))

    def __call__(self, path, precision="full"):
        return self.pool.apply(run_sapgo, (path, precision))

    def close(self):
        self.pool.close()
        self.pool.join()


def best_of(runs, key="time_to_solution_s"):
    return min(runs, key=lambda r: r[key])


def median_of(runs, key="time_to_solution_s"):
    """The run of median ``key`` (the lower middle of an even count), with the spread of its
    times beside it."""
    ordered = sorted(runs, key=lambda r: r[key])
    r = dict(ordered[(len(ordered) - 1) // 2])
    r["runs_time_to_solution_s"] = [x["time_to_solution_s"] for x in runs]
    r["runs_s_per_iteration"] = [x["s_per_iteration"] for x in runs]
    r["median_time_to_solution_s"] = float(np.median(r["runs_time_to_solution_s"]))
    r["median_s_per_iteration"] = float(np.median(r["runs_s_per_iteration"]))
    return r


def load_average():
    try:
        return [float(x) for x in Path("/proc/loadavg").read_text().split()[:3]]
    except OSError:
        return None


def bench_size(n_photos, workdir, pycolmap, rounds, sapgo_run=run_sapgo):
    spec = BLOCKS[n_photos]
    gen = workdir / f"block{n_photos}.h5"
    info = sapgo.generate_block(gen, progress=False, control_sigma=0.0, **spec)
    print(f"\n{n_photos} photos: {info['points']} points ({info['control_points']} fixed control),"
          f" {info['observations']} observations", file=sys.stderr)
    prob = load_problem(gen)  # starting values, read before anything adjusts a copy
    initial_rms = image_rms_um(rotation(prob["eo"]), prob["eo"][:, 3:], prob["xyz"], prob)

    # COLMAP: check the mapping once
    rec, _, origin, _ = build_reconstruction(prob, pycolmap)
    check = verify_mapping(rec, prob, origin, pycolmap)
    # the starting values as COLMAP's binary model, read in every round (outside any timing)
    model_dir = workdir / f"colmap{n_photos}"
    model = write_model(rec, model_dir)
    del rec
    # COLMAP's covariance: intrinsics fixed, so no variables besides the poses and points
    plan = covariance_plan(int(prob["station_active"].sum()), other_params=0)
    if "skipped" in plan:
        print(f"  COLMAP covariance skipped: {plan['skipped']} (over "
              f"{COV_MEMORY_FRACTION:g} of {plan['physical_memory_bytes'] / 1e9:.1f} GB)",
              file=sys.stderr)
    configs = solver_configs(n_photos, pycolmap)
    # interleaved rounds: sapgo (a fresh copy of the generated file), then each configuration;
    # after the first configuration's solve COLMAP's covariance and its file work
    sap_runs, bare_runs, reps, errors, loads = [], [], {c["name"]: [] for c in configs}, {}, []
    cov_runs, file_runs = [], []
    for rnd in range(max(1, rounds)):
        loads.append(load_average())
        for runs, precision in ((sap_runs, "full"), (bare_runs, "none")):
            if runs and runs[-1]["time_to_solution_s"] > REPEAT_BELOW_S:
                continue
            path = workdir / f"sapgo{n_photos}.h5"
            shutil.copyfile(gen, path)
            runs.append(sapgo_run(path, precision))
            print(f"  round {rnd}: sapgo (precision {precision}): {runs[-1]['iterations']} it, "
                  f"{runs[-1]['time_to_solution_s']:.2f} s, RMS "
                  f"{runs[-1]['final_rms_um']:.4f} um", file=sys.stderr)
            path.unlink()
        for cfg in configs:
            name = cfg["name"]
            if name in errors or (reps[name] and reps[name][-1]["time_to_solution_s"]
                                  > REPEAT_BELOW_S):
                continue
            r, rec, ba, _ = run_colmap(prob, cfg, pycolmap, keep=True)
            if "error" in r:
                errors[name] = r
                print(f"  COLMAP {name}: {r['error']}", file=sys.stderr)
                continue
            reps[name].append(r)
            if cfg is configs[0]:
                if not (cov_runs and cov_runs[-1].get("covariance_s", 0.0) > REPEAT_BELOW_S):
                    cov_runs.append(colmap_covariance(rec, ba, pycolmap, plan, name))
                file_runs.append(colmap_file_work(model_dir, rec, workdir, pycolmap))
                c, f = cov_runs[-1], file_runs[-1]
                what = c.get("skipped") or c.get("error") or f"{c['covariance_s']:.2f} s"
                print(f"  round {rnd}: COLMAP covariance (after {name}): {what}; "
                      f"read {f['read_s']:.3f} s, write {f['write_s']:.3f} s", file=sys.stderr)
            del rec, ba
    sap = median_of(sap_runs)
    bare = median_of(bare_runs)
    runs = []
    for cfg in configs:
        name = cfg["name"]
        if not reps[name]:
            runs.append(errors[name])
            continue
        r = median_of(reps[name])
        r["rms_relative_difference_to_sapgo"] = ((r["final_rms_um"] - sap["final_rms_um"])
                                                 / sap["final_rms_um"])
        hit = next((row for row in r["log"] if row["image_rms_um"]
                    <= sap["final_rms_um"] * (1 + RMS_MATCH)), None)
        r["iterations_to_sapgo_rms"] = None if hit is None else hit["iteration"]
        r["time_to_sapgo_rms_s"] = (None if hit is None else
                                    r["problem_setup_s"] + hit["total_time_s"])
        runs.append(r)
        print(f"  COLMAP {cfg['name']}: {r['iterations']} it, {r['time_to_solution_s']:.2f} s, "
              f"{r['s_per_iteration']:.3f} s/it, RMS {r['final_rms_um']:.4f} um "
              f"({r['termination']}: {r['message']})", file=sys.stderr)
    good = [r for r in runs if "error" not in r
            and abs(r["rms_relative_difference_to_sapgo"]) <= RMS_SAME]
    best = best_of(good) if good else None
    cov = summarize_covariance(cov_runs, plan)
    files = summarize_file_work(file_runs, model)
    out = {
        "photos": n_photos,
        "block": dict(spec, pattern=9, control_sigma=0.0, points=info["points"],
                      observations=info["observations"]),
        "initial_rms_um": initial_rms,
        "mapping_check": check,
        "rounds": rounds,
        "load_before_rounds": loads,
        "sapgo": sap,
        "sapgo_precision_none": bare,
        "colmap": None if best is None else dict(best, best_of_configurations=True),
        "colmap_all_configurations": runs,
        "colmap_covariance": cov,
        "colmap_file_work": files,
    }
    if best is not None:
        out["speedup_per_iteration"] = (best["median_s_per_iteration"]
                                        / sap["median_s_per_iteration"])
        out["speedup_per_iteration_fastest_colmap_iteration"] = (
            min(r["s_per_iteration"] for r in good) / sap["s_per_iteration"])
        out["speedup_time_to_solution"] = (best["median_time_to_solution_s"]
                                           / sap["median_time_to_solution_s"])
        # the same work as COLMAP's: no precision pass (the orientation and the points alone)
        out["speedup_time_to_solution_precision_none"] = (best["median_time_to_solution_s"]
                                                          / bare["median_time_to_solution_s"])
        out["rms_relative_difference"] = ((best["final_rms_um"] - sap["final_rms_um"])
                                          / sap["final_rms_um"])
        # COLMAP doing sapgo's work: reading and writing a model, and the covariance
        out.update(same_work(best["median_time_to_solution_s"], files, cov))
        f2f, plus = out["colmap_best_file_to_file_s"], out["colmap_best_plus_covariance_s"]
        out["speedup_file_to_file_precision_none"] = (
            None if f2f is None else f2f / bare["median_time_to_solution_s"])
        out["speedup_with_covariance"] = (None if plus is None
                                          else plus / sap["median_time_to_solution_s"])
    return out


def fmt(v, nd=3):
    return "-" if v is None else f"{v:.{nd}f}"


def span(r, key, nd):
    """``median (min-max)`` of a tool's runs (its single figure when it ran once)."""
    runs = r.get({"time_to_solution_s": "runs_time_to_solution_s",
                  "s_per_iteration": "runs_s_per_iteration"}[key]) or [r[key]]
    if len(runs) == 1:
        return fmt(runs[0], nd)
    return f"{fmt(float(np.median(runs)), nd)} ({fmt(min(runs), nd)}-{fmt(max(runs), nd)})"


def table(rows):
    L = [("| photos | tool | configuration | iterations | s per iteration median (min-max) | "
          "time to solution s median (min-max) | "
          "final RMS um | Ceres iterations to sapgo's RMS |"),
         "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for s, what in ((r["sapgo"], ""), (r.get("sapgo_precision_none"),
                                           ", --precision none")):
            if s is None:
                continue
            L.append(f"| {r['photos']:,} | sapgo | Gauss-Newton, band Cholesky{what} | "
                     f"{s['iterations']} | {span(s, 's_per_iteration', 3)} | "
                     f"{span(s, 'time_to_solution_s', 2)} | {fmt(s['final_rms_um'], 4)} | |")
        for c in r["colmap_all_configurations"]:
            if "error" in c:
                continue
            best_conf = r["colmap"] and c["configuration"] == r["colmap"]["configuration"]
            star = " (best)" if best_conf else ""
            to_rms = c["iterations_to_sapgo_rms"]
            L.append(f"| {r['photos']:,} | COLMAP {pycolmap_version} | "
                     f"{c['configuration']}{star} | "
                     f"{c['iterations']} | {span(c, 's_per_iteration', 3)} | "
                     f"{span(c, 'time_to_solution_s', 2)} | {fmt(c['final_rms_um'], 4)} | "
                     f"{to_rms if to_rms is not None else '-'} |")
    L.append("")
    L.append("| photos | speedup per iteration (COLMAP best / sapgo) | speedup time to solution | "
             "the same, sapgo --precision none | RMS relative difference | "
             "COLMAP read model s | COLMAP write model s | COLMAP best file to file s | "
             "speedup, sapgo --precision none against it | COLMAP covariance s | "
             "COLMAP best + covariance s | speedup, sapgo against it |")
    L.append("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        files = r.get("colmap_file_work") or {}
        cov = r.get("colmap_covariance") or {}
        plus = r.get("colmap_best_plus_covariance_s")
        plus = (fmt(plus, 2) if plus is not None
                else r.get("colmap_best_plus_covariance_note", "-"))
        L.append(f"| {r['photos']:,} | {fmt(r.get('speedup_per_iteration'), 2)} | "
                 f"{fmt(r.get('speedup_time_to_solution'), 2)} | "
                 f"{fmt(r.get('speedup_time_to_solution_precision_none'), 2)} | "
                 f"{r.get('rms_relative_difference', float('nan')):.2e} | "
                 f"{span_runs(files.get('runs_read_s'), 3)} | "
                 f"{span_runs(files.get('runs_write_s'), 3)} | "
                 f"{fmt(r.get('colmap_best_file_to_file_s'), 2)} | "
                 f"{fmt(r.get('speedup_file_to_file_precision_none'), 2)} | "
                 f"{covariance_cell(cov) if cov else '-'} | "
                 f"{plus} | "
                 f"{fmt(r.get('speedup_with_covariance'), 2)} |")
    after = next((r["colmap_covariance"].get("after_configuration") for r in rows
                  if (r.get("colmap_covariance") or {}).get("after_configuration")), None)
    L.append("")
    L.append("COLMAP best file to file: reading the starting binary model "
             "(`pycolmap.Reconstruction(dir)`) + the best configuration's median time to "
             "solution + writing the adjusted model (`write_binary`), medians; against sapgo "
             "--precision none (which reads and writes its project). COLMAP covariance: "
             "`estimate_ba_covariance(params=ALL)`"
             + (f" after each round's {after} solve" if after else "")
             + " (the same solution within the RMS tolerance): pose covariances marginal, "
             "from a dense inverse of the factor of the pose Schur complement (8 (6 photos)^2 "
             "bytes: not run where that exceeds half the memory); point covariances "
             "*conditional* on all other variables held (each point's own 3 x 3 block "
             "inverted), cheaper than sapgo's marginal point covariances. COLMAP best + "
             "covariance: best median time to solution + median covariance, against sapgo "
             "with its precision pass. Speedups: COLMAP / sapgo.")
    return "\n".join(L)


pycolmap_version = "?"


def git_state():
    """The commit of the sapgo checkout and its uncommitted source files (what was timed)."""
    import subprocess

    root = HERE.parent
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True,
                              text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "src"], cwd=root,
                               capture_output=True, text=True, check=True).stdout.split("\n")
    except (OSError, subprocess.CalledProcessError):
        return None
    return {"commit": head, "uncommitted": [d[3:] for d in dirty if d.strip()]}


def main(argv=None):
    global pycolmap_version
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="1000,10000",
                    help=f"comma-separated photo counts out of {sorted(BLOCKS)}")
    ap.add_argument("--dir", default=None, help="scratch directory (default: a temporary one)")
    ap.add_argument("--rounds", type=int, default=7,
                    help="interleaved rounds (a tool whose run took over 10 s runs once); the "
                         "median run is reported with the spread")
    ap.add_argument("--output", default=str(RESULTS))
    ap.add_argument("--sapgo-process", choices=("own", "same"), default="own",
                    help="sapgo's runs in a long-lived process of their own (the default) or "
                         "in this one, beside COLMAP's")
    args = ap.parse_args(argv)
    try:
        pycolmap = import_pycolmap()
    except ImportError:
        raise SystemExit("this benchmark needs pycolmap: pip install pycolmap")
    pycolmap_version = pycolmap.__version__
    sizes = [int(s) for s in args.sizes.split(",")]
    for n in sizes:
        if n not in BLOCKS:
            raise SystemExit(f"unknown size {n}; choose from {sorted(BLOCKS)}")
    t_all = time.perf_counter()
    with tempfile.TemporaryDirectory(dir=args.dir, prefix="sapgo-colmap-") as tmp:
        workdir = Path(tmp)
        warm_numba(workdir)
        runner = SapgoProcess(workdir) if args.sapgo_process == "own" else run_sapgo
        try:
            rows = [bench_size(n, workdir, pycolmap, args.rounds, runner) for n in sizes]
        finally:
            if runner is not run_sapgo:
                runner.close()
    result = {
        "benchmark": "sapgo vs COLMAP bundle adjustment (pycolmap/Ceres), same blocks",
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "platform": platform.platform()},
        "sapgo_version": sapgo.__version__,
        "sapgo_source": git_state(),
        "pycolmap_version": pycolmap.__version__,
        "ceres_version": getattr(pycolmap, "__ceres_version__", None),
        "pixels_per_mm": S_PX,
        "ceres_tolerances": CERES_TOL,
        "rounds": args.rounds,
        "sapgo_process": args.sapgo_process,
        "sizes": {str(r["photos"]): r for r in rows},
        "wall_s": time.perf_counter() - t_all,
    }
    big = next((r for r in rows if r["photos"] == 10000), None)
    result["speedup_per_iteration"] = None if big is None else big.get("speedup_per_iteration")
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(table(rows))
    print(f"\nResults: {out}  (wall {result['wall_s']:.0f} s)")


if __name__ == "__main__":
    main()
