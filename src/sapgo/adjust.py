"""The adjustment: Gauss-Newton iterations of build, solve and update (DESIGN section 2).

``adjust(path, Options(...))`` validates the project, orders it if needed, iterates and writes
the adjusted values to ``/solution``; it returns a :class:`Summary` (Ceres-style: termination,
per-iteration log, statistics, time per phase; ``brief_report()`` / ``full_report()``).

Every pass streams records in logical order. In core: per-station vectors (orientation,
corrections, camera, status: about 150 bytes a station), the band-row window of
``b + chunk_rows`` stations and one chunk of points with their observations. Band rows,
right-hand side, current point coordinates and residuals live in a scratch file beside the
project (``NAME.scratch.h5``), removed after the run. The project's input datasets are never
written; results are written to ``/solution`` only when the iterations are over.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import h5py
import numpy as np

from .bandsolve import PIVOT_TOLERANCE, PivotError, solve_out_of_core
from .errors import DatumDefectError, SapgoError, SingularNormalsError
from .normals import (
    BAD_LAYOUT,
    BEHIND_CAMERA,
    CTRL_MASK,
    OK,
    PointChunk,
    build_points,
    update_points,
)
from .ordering import order_project
from .project import (
    CHUNK_RECORDS,
    CONTROL_MASK,
    EO_NAMES,
    STATUS_ACTIVE,
    Project,
)
from .report import Summary, check_point_statistics, truth_statistics
from .validate import check_values

ARCSEC = math.pi / (180 * 3600)
#: At most this many ids of excluded points or stations are listed in a report.
LISTED_IDS = 1000


@dataclasses.dataclass
class Options:
    """How to adjust. Every default is what a SAPGO-P block needs."""

    #: Stop after this many Gauss-Newton iterations even if not converged.
    max_iterations: int = 10
    #: Converged when every station position and point correction is below this (m) ...
    tol_position: float = 1e-4
    #: ... and every station angle correction below this (rad; default 0.1").
    tol_angle: float = 0.1 * ARCSEC
    #: ... and sigma0 changed by less than this fraction since the previous iteration.
    tol_sigma0: float = 1e-3
    #: Station ordering when the project is not ordered yet: "best" or a candidate name.
    ordering: str = "best"
    #: Points read per chunk in the streaming passes.
    chunk_points: int = CHUNK_RECORDS
    #: Band rows kept in core beyond the band width (the solver's read/write block).
    chunk_rows: int = 256
    #: A Cholesky pivot at or below this fraction of its original diagonal counts as zero.
    pivot_tolerance: float = PIVOT_TOLERANCE
    #: Keep the scratch file (band and factor rows) after the run.
    keep_scratch: bool = False
    #: Progress bars: True, False, or None for "when stderr is a terminal".
    progress: bool | None = None

    def check(self):
        if self.max_iterations < 1:
            raise SapgoError("max_iterations must be at least 1")
        if not (self.tol_position > 0 and self.tol_angle > 0 and self.tol_sigma0 > 0):
            raise SapgoError("the convergence tolerances must be positive")
        if self.chunk_points < 1 or self.chunk_rows < 1:
            raise SapgoError("chunk sizes must be positive")
        if not 0 <= self.pivot_tolerance < 1:
            raise SapgoError("pivot_tolerance must be in [0, 1)")
        return self


# -- helpers ---------------------------------------------------------------------------

def _progress(enabled, total, desc):
    from tqdm import tqdm

    if enabled is None:
        enabled = sys.stderr.isatty()
    return tqdm(total=total, desc=desc, unit="", leave=False, disable=not enabled,
                dynamic_ncols=True)


def _wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def scratch_path(path):
    path = Path(path)
    return path.with_name(path.stem + ".scratch.h5")


class _PriorCursor:
    """Station priors, read in chunks in station order as band rows enter the window."""

    def __init__(self, project, chunk):
        self.p = project
        self.n = project.n_priors
        self.chunk = chunk
        self.pos = 0
        self.buf = project.read("station_priors", 0, 0)
        self.bpos = 0

    def take(self, lo, hi):
        """Priors of stations in ``[lo, hi)``; calls must come in increasing station order."""
        out = []
        while True:
            if self.bpos >= len(self.buf):
                if self.pos >= self.n:
                    break
                b = min(self.n, self.pos + self.chunk)
                self.buf = self.p.read("station_priors", self.pos, b)
                self.pos, self.bpos = b, 0
            rec = self.buf[self.bpos]
            if rec["station"] >= hi:
                break
            if rec["station"] >= lo:
                out.append(rec)
            self.bpos += 1
        return out


def _prior_residual(rec, eo):
    v = eo - rec["value"]
    v[:3] = _wrap(v[:3])
    return v


@dataclasses.dataclass
class _Block:
    """Per-station state and block counts (in core: O(stations) small vectors)."""

    station_ids: np.ndarray
    station_active: np.ndarray
    camera: np.ndarray
    eo_approx: np.ndarray
    eo: np.ndarray
    cam_f: np.ndarray
    cam_x0: np.ndarray
    cam_y0: np.ndarray
    default_sigma: np.ndarray  # per station: its camera's sigma_image (mm)
    band_width: int
    n_points: int = 0
    n_rays: int = 0
    n_control: dict = dataclasses.field(default_factory=dict)
    n_weighted_control: int = 0
    n_fixed: int = 0
    n_prior_params: int = 0

    @property
    def n_stations(self):
        return int(self.station_active.sum())

    @property
    def redundancy(self):
        equations = 2 * self.n_rays + self.n_weighted_control + self.n_prior_params
        unknowns = 6 * self.n_stations + 3 * self.n_points - self.n_fixed
        return equations - unknowns


def _load_block(p: Project) -> _Block:
    st = p.read("stations")
    cams = p.cameras()
    blk = _Block(
        station_ids=st["id"].copy(),
        station_active=st["status"] == STATUS_ACTIVE,
        camera=np.ascontiguousarray(st["camera"], dtype=np.int64),
        eo_approx=np.ascontiguousarray(st["eo"]),
        eo=np.ascontiguousarray(st["eo"]).copy(),
        cam_f=np.ascontiguousarray(cams["focal_length"]),
        cam_x0=np.ascontiguousarray(cams["x0"]),
        cam_y0=np.ascontiguousarray(cams["y0"]),
        default_sigma=np.ascontiguousarray(cams["sigma_image"][st["camera"]]),
        band_width=p.band_width,
    )
    names = {1: "full", 2: "horizontal", 3: "vertical"}
    counts = {v: 0 for v in names.values()}
    for a, b in p.chunks("points"):
        pts = p.read("points", a, b)
        act = pts["status"] == STATUS_ACTIVE
        kind = pts["kind"][act]
        blk.n_points += int(act.sum())
        mask = CONTROL_MASK[kind].astype(bool)
        sig = pts["control_sigma"][act]
        blk.n_weighted_control += int((mask & (sig > 0)).sum())
        blk.n_fixed += int((mask & (sig == 0)).sum())
        for k, name in names.items():
            counts[name] += int((kind == k).sum())
    blk.n_control = counts
    for a, b in p.chunks("observations"):
        blk.n_rays += int((p.read_field("observations", "status", a, b) == STATUS_ACTIVE).sum())
    for a, b in p.chunks("station_priors"):
        pr = p.read("station_priors", a, b)
        act = blk.station_active[pr["station"]]
        if act.any():  # the rank of each weight matrix (validated positive semi-definite)
            ev = np.linalg.eigvalsh(pr["weight"][act])
            blk.n_prior_params += int((ev > 1e-12 * ev.max(axis=1, keepdims=True)).sum())
    return blk


def _datum_counts(p: Project):
    """(horizontal, vertical) control points with at least one ray, and the priors."""
    nh = nv = 0
    for a, b in p.chunks("points"):
        pts = p.read("points", a, b)
        seen = pts["n_obs"] > 0
        mask = CONTROL_MASK[pts["kind"][seen]].astype(bool)
        nh += int((mask[:, 0] & mask[:, 1]).sum())
        nv += int(mask[:, 2].sum())
    return nh, nv, p.n_priors


def _datum_advice(nh, nv, n_priors):
    return (
        f"the block has {nh} horizontal (X, Y) and {nv} vertical (Z) control points and "
        f"{n_priors} station priors; at least 2 horizontal and 3 vertical control points, "
        f"not on one line, or station priors are needed to fix the 7 datum parameters "
        f"(3 shifts, 3 rotations, scale). Add control points or station priors."
    )


def check_datum(p: Project):
    """Raise :class:`DatumDefectError` when the control cannot fix the datum."""
    nh, nv, npr = _datum_counts(p)
    if npr == 0 and (nh < 2 or nv < 3):
        raise DatumDefectError(f"{p.path}: datum defect: " + _datum_advice(nh, nv, npr))


# -- the phases ------------------------------------------------------------------------

def _init_rows(band, rhs, base, lo, hi, blk, priors):
    """Band rows of stations ``lo .. hi-1`` enter the window: priors and excluded stations."""
    n = len(blk.station_active)
    hi = min(hi, n)
    for s in range(lo, hi):
        if not blk.station_active[s]:
            band[s - base, :, :6] += np.eye(6)
    for rec in priors.take(lo, hi):
        s = int(rec["station"])
        if not blk.station_active[s]:
            continue
        w = rec["weight"]
        band[s - base, :, :6] += w
        rhs[s - base] += w @ (-_prior_residual(rec, blk.eo[s]))


def _point_error(p, chunk, j, status, blk):
    rec = p.read("points", chunk.start + j, chunk.start + j + 1)[0]
    pid = int(rec["id"])
    if status == BAD_LAYOUT:
        return SapgoError(
            f"{p.path}: point id {pid} (record {chunk.start + j}) does not follow the stored "
            f"logical order and band width {p.band_width}: the records were changed after "
            f"ordering; run 'sapgo order' again"
        )
    if status == BEHIND_CAMERA:
        return SapgoError(
            f"point id {pid} lies behind a photo at its current coordinates: check its "
            f"approximate coordinates and the photos' approximate orientation"
        )
    if CONTROL_MASK[rec["kind"]].any():
        return SingularNormalsError(
            f"point id {pid} cannot be determined: its rays are (nearly) parallel and its "
            f"control does not fix the remaining direction (control_sigma "
            f"{list(rec['control_sigma'])} m); check its image measurements and control"
        )
    return SingularNormalsError(
        f"point id {pid} cannot be determined: its rays are (nearly) parallel and it has no "
        f"control; check its image measurements"
    )


def build(p: Project, scratch, blk: _Block, opts: Options):
    """Stream the points and write the reduced normal band rows to ``scratch``."""
    n = len(blk.station_ids)
    bw = blk.band_width
    cap = min(n, bw + opts.chunk_rows)
    band = np.zeros((cap, 6, 6 * bw))
    rhs = np.zeros((cap, 6))
    band_ds, rhs_ds, xyz_ds = scratch["band"], scratch["rhs"], scratch["xyz"]
    priors = _PriorCursor(p, opts.chunk_points)
    base = 0
    _init_rows(band, rhs, base, 0, cap, blk, priors)

    def advance(new_base):
        nonlocal base
        if new_base <= base:
            raise SapgoError(f"{p.path}: the points are not sorted by their first station; "
                             f"the records were changed after ordering: run 'sapgo order'")
        shift = min(new_base, n) - base
        band_ds[base:base + shift] = band[:shift]
        rhs_ds[base:base + shift] = rhs[:shift]
        band[:cap - shift] = band[shift:]
        rhs[:cap - shift] = rhs[shift:]
        band[cap - shift:] = 0.0
        rhs[cap - shift:] = 0.0
        _init_rows(band, rhs, new_base, base + cap, new_base + cap, blk, priors)
        base = new_base

    with _progress(opts.progress, p.n_points, "build") as bar:
        for a, b in p.chunks("points", opts.chunk_points):
            c = PointChunk(p, a, b, xyz_ds[a:b], blk.default_sigma)
            j = 0
            while j < len(c.xyz):
                j, status, bad = build_points(
                    j, c.xyz, c.kind, c.ctrl, c.csig, c.pt_start, c.nobs, c.smax, c.active,
                    c.obs_station, c.obs_xy, c.obs_sigma, c.obs_active, blk.eo, blk.camera,
                    blk.cam_f, blk.cam_x0, blk.cam_y0, CTRL_MASK, band, rhs, base, c.max_rays,
                )
                if status != OK:
                    raise _point_error(p, c, bad, status, blk)
                if j < len(c.xyz):
                    advance(int(c.smin[j]))
            bar.update(b - a)
    while base < n:
        advance(min(n, base + cap))


def update(p: Project, scratch, blk: _Block, delta, opts: Options):
    """Stream the points: back-solve their corrections, new coordinates and residuals."""
    eo_new = blk.eo + delta
    stats = np.zeros(9)
    xyz_ds, res_ds = scratch["xyz"], scratch["residuals"]
    with _progress(opts.progress, p.n_points, "update") as bar:
        for a, b in p.chunks("points", opts.chunk_points):
            c = PointChunk(p, a, b, xyz_ds[a:b], blk.default_sigma)
            xyz_out = np.empty_like(c.xyz)
            res_out = np.zeros((c.o1 - c.o0, 2))
            update_points(
                c.xyz, c.kind, c.ctrl, c.csig, c.pt_start, c.nobs, c.active, c.obs_station,
                c.obs_xy, c.obs_sigma, c.obs_active, blk.eo, eo_new, delta, blk.camera,
                blk.cam_f, blk.cam_x0, blk.cam_y0, CTRL_MASK, c.max_rays, xyz_out, res_out,
                stats,
            )
            if stats[7]:
                raise _point_error(p, c, int(stats[7]) - 1, int(stats[8]), blk)
            xyz_ds[a:b] = xyz_out
            res_ds[c.o0:c.o1] = res_out
            bar.update(b - a)
    vpv_prior = 0.0
    for a, b in p.chunks("station_priors", opts.chunk_points):
        pr = p.read("station_priors", a, b)
        pr = pr[blk.station_active[pr["station"]]]
        v = eo_new[pr["station"]] - pr["value"]
        v[:, :3] = _wrap(v[:, :3])
        vpv_prior += float(np.einsum("ni,nij,nj->", v, pr["weight"], v))
    blk.eo = eo_new
    return {
        "vpv": stats[0] + stats[1] + vpv_prior,
        "vpv_image": stats[0],
        "rms_x_um": 1000 * math.sqrt(stats[2] / max(stats[4], 1)),
        "rms_y_um": 1000 * math.sqrt(stats[3] / max(stats[4], 1)),
        "image_rms_um": 1000 * math.sqrt((stats[2] + stats[3]) / max(2 * stats[4], 1)),
        "max_point_corr": stats[5],
    }


def _pivot_error(exc: PivotError, blk: _Block, p: Project):
    s = exc.row
    sid = int(blk.station_ids[s])
    param = EO_NAMES[exc.parameter]
    active = np.flatnonzero(blk.station_active)
    last = active[-1] if len(active) else 0
    # a datum defect spreads over the whole block and shows at the end of the elimination;
    # in a block of a few band widths every station is "at the end", so say both
    near_end = s > last - blk.band_width
    small = len(active) <= 3 * blk.band_width
    nh, nv, npr = _datum_counts(p)
    where = (f"the reduced normal equations are not positive definite at station id {sid} "
             f"(logical station {s}, parameter {param})")
    if npr == 0 and (nh < 2 or nv < 3) or (near_end and not small):
        return DatumDefectError(
            f"{where}: datum defect - the block as a whole is not fixed; "
            + _datum_advice(nh, nv, npr)
        )
    if near_end:
        return DatumDefectError(
            f"{where}: a datum defect (control on one line, or too little control: "
            f"{nh} horizontal, {nv} vertical points, {npr} priors) or a station that its "
            f"observations do not determine; check the control layout and station id {sid}"
        )
    return SingularNormalsError(
        f"{where}: the station is not determined by its observations; check its image "
        f"points (at least 3, well spread) and its tie points to the neighbouring photos"
    )


def create_scratch(spath, p: Project, band_width):
    """The scratch file: band rows, right-hand side, current point coordinates, residuals."""
    n, m, nobs = p.n_stations, p.n_points, p.n_observations
    bw = band_width
    rows = max(1, min(n, (1 << 20) // (36 * bw * 8)))
    scratch = h5py.File(spath, "w")
    scratch.create_dataset("band", (n, 6, 6 * bw), "<f8", chunks=(rows, 6, 6 * bw))
    scratch.create_dataset("rhs", (n, 6), "<f8", chunks=(max(1, min(n, 65536)), 6))
    xyz = scratch.create_dataset("xyz", (m, 3), "<f8", chunks=(max(1, min(m, 65536)), 3))
    scratch.create_dataset("residuals", (nobs, 2), "<f8", chunks=(max(1, min(nobs, 65536)), 2))
    for a, b in p.chunks("points"):
        xyz[a:b] = p.read_field("points", "xyz", a, b)
    return scratch


def _iterate(p: Project, scratch, blk: _Block, opts: Options, timings, log):
    """Gauss-Newton iterations; appends to ``log`` and ``timings``; returns converged."""
    n = len(blk.station_ids)
    bw = blk.band_width
    for it in range(1, opts.max_iterations + 1):
        t0 = time.perf_counter()
        build(p, scratch, blk, opts)
        t1 = time.perf_counter()
        with _progress(opts.progress, n, "solve") as bar:
            try:
                delta = solve_out_of_core(
                    scratch["band"], scratch["rhs"], bw, opts.chunk_rows,
                    opts.pivot_tolerance, progress=bar.update,
                )
            except PivotError as exc:
                raise _pivot_error(exc, blk, p) from None
        delta[~blk.station_active] = 0.0
        t2 = time.perf_counter()
        st = update(p, scratch, blk, delta, opts)
        t3 = time.perf_counter()
        timings["build"] += t1 - t0
        timings["solve"] += t2 - t1
        timings["update"] += t3 - t2
        d_ang = float(np.abs(delta[:, :3]).max()) if n else 0.0
        d_pos = float(np.abs(delta[:, 3:]).max()) if n else 0.0
        sigma0 = math.sqrt(max(st["vpv"], 0.0) / blk.redundancy)
        prev = log[-1]["sigma0"] if log else None
        log.append({
            "iteration": it,
            "sigma0": sigma0,
            "image_rms_um": st["image_rms_um"],
            "image_rms_x_um": st["rms_x_um"],
            "image_rms_y_um": st["rms_y_um"],
            "max_station_position_corr_m": d_pos,
            "max_station_angle_corr_arcsec": d_ang / ARCSEC,
            "max_point_corr_m": st["max_point_corr"],
            "build_s": t1 - t0,
            "solve_s": t2 - t1,
            "update_s": t3 - t2,
        })
        if (d_pos < opts.tol_position and st["max_point_corr"] < opts.tol_position
                and d_ang < opts.tol_angle
                and (prev is None or abs(sigma0 - prev) <= opts.tol_sigma0 * prev)):
            return True
        if not np.isfinite(sigma0):
            raise SapgoError("the adjustment diverged (sigma0 is not finite)")
    return False


# -- the run -----------------------------------------------------------------------------

def adjust(path, options: Options | None = None) -> Summary:
    """Adjust the project at ``path``; see the module docstring. Returns a :class:`Summary`."""
    opts = (options or Options()).check()
    path = Path(path)
    t_start = time.perf_counter()
    timings = {"order": 0.0, "build": 0.0, "solve": 0.0, "update": 0.0}
    with Project(path, "r") as p:
        check_values(p)
        check_datum(p)
        needs_order = not p.ordered
    order_info = None
    if needs_order:
        t0 = time.perf_counter()
        order_info = order_project(path, opts.ordering)
        timings["order"] = time.perf_counter() - t0

    log = []
    spath = scratch_path(path)
    with Project(path, "r") as p:
        blk = _load_block(p)
        if blk.n_stations == 0:
            raise DatumDefectError(f"{path}: no station can be adjusted (every photo has fewer "
                                   f"than 3 determinable points)")
        if blk.redundancy <= 0:
            raise SapgoError(f"{path}: the block has no redundancy ({blk.redundancy}): more "
                             f"unknowns than observations")
        try:
            with create_scratch(spath, p, blk.band_width) as scratch:
                converged = _iterate(p, scratch, blk, opts, timings, log)
                summary = _commit(path, p, scratch, blk, log, converged, opts, order_info)
        finally:
            if not opts.keep_scratch:
                spath.unlink(missing_ok=True)
    timings["total"] = time.perf_counter() - t_start
    summary.timings_s = timings
    its = max(1, len(log))
    summary.timings_per_iteration_s = {k: timings[k] / its for k in ("build", "solve", "update")}
    with Project(path, "r+") as q:
        g = q.file["solution"]
        if "report" in g:
            del g["report"]
        g.create_dataset("report", data=json.dumps(summary.to_dict()))
    return summary


def _commit(path, p_read: Project, scratch, blk: _Block, log, converged, opts, order_info):
    """Write the adjusted values to /solution and compute the statistics of the result."""
    last = log[-1]
    xyz_ds, res_ds = scratch["xyz"], scratch["residuals"]
    checks = check_point_statistics()
    truth = truth_statistics() if p_read.has_truth else None
    p_read.close()
    with Project(path, "r+") as q:
        g = q.new_solution()
        g["station_corr"][...] = blk.eo - blk.eo_approx
        excluded_points, n_excluded_points = [], 0
        for a, b in q.chunks("points", opts.chunk_points):
            pts = q.read("points", a, b)
            adj = xyz_ds[a:b]
            g["point_corr"][a:b] = adj - pts["xyz"]
            act = pts["status"] == STATUS_ACTIVE
            ids = pts["id"][~act]
            n_excluded_points += len(ids)
            excluded_points.extend(int(i) for i in ids[:LISTED_IDS - len(excluded_points)])
            checks.add(pts[act], adj[act])
            if truth is not None:
                truth.add_points(q.read_field("truth/points", "xyz", a, b)[act], adj[act])
        for a, b in q.chunks("observations", opts.chunk_points):
            g["residuals"][a:b] = res_ds[a:b]
        if truth is not None:
            truth.add_stations(q.read_field("truth/stations", "eo")[blk.station_active],
                               blk.eo[blk.station_active])
        g.attrs["state"] = "adjusted"
        g.attrs["iterations"] = len(log)
        g.attrs["converged"] = converged
        g.attrs["sigma0"] = last["sigma0"]
        q.commit_solution()
        q.add_history({"command": "adjust", "iterations": len(log), "converged": converged,
                       "sigma0": last["sigma0"]})
        excluded_stations = blk.station_ids[~blk.station_active]
        summary = Summary(
            path=str(path),
            converged=converged,
            termination=(
                f"converged after {len(log)} iterations: corrections below "
                f"{opts.tol_position:g} m and {opts.tol_angle / ARCSEC:.2g}\""
                if converged else
                f"not converged after {len(log)} iterations (max_iterations)"
            ),
            iterations=len(log),
            iteration_log=log,
            sigma0=last["sigma0"],
            redundancy=int(blk.redundancy),
            image_rms_um=last["image_rms_um"],
            image_rms_x_um=last["image_rms_x_um"],
            image_rms_y_um=last["image_rms_y_um"],
            band_width=blk.band_width,
            ordering=q.attr("ordering"),
            band_width_before=order_info.band_width_before if order_info else None,
            n_stations=blk.n_stations,
            n_points=blk.n_points,
            n_observations=blk.n_rays,
            n_cameras=q.n_cameras,
            n_control=blk.n_control,
            excluded_stations=[int(i) for i in excluded_stations[:LISTED_IDS]],
            excluded_points=excluded_points,
            n_excluded_stations=len(excluded_stations),
            n_excluded_points=n_excluded_points,
            check_points=checks.result(),
            control_points=checks.control_result(),
            truth=truth.result() if truth is not None else None,
        )
    return summary
