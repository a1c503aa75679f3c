"""The adjustment: Gauss-Newton iterations of build, solve and update (DESIGN section 2).

``adjust(path, Options(...))`` validates the project, orders it if needed, iterates and writes
the adjusted values to ``/solution``; it returns a :class:`Summary` (Ceres-style: termination,
per-iteration log, statistics, time per phase; ``brief_report()`` / ``full_report()``).

Every pass streams records in logical order. In core: per-station vectors (orientation,
corrections, camera, status: a few hundred bytes a station), the band-row window of
``b + chunk_rows`` stations and one chunk of points with their observations.

Crash safety. The project file is never opened for writing while the run is going on. Band
rows, right-hand side, point coordinates and residuals live in direct-access files
(:class:`sapgo.rawfile.RawArray`) in a work directory beside the project, ``NAME.h5.work/``.
Point coordinates and residuals are double-buffered: iteration ``k`` reads buffer
``(k - 1) % 2`` and writes buffer ``k % 2``, and only when it is complete is the checkpoint
(the stations' orientation and ``checkpoint.json``) replaced atomically. A process killed at
any moment therefore leaves the last completed iteration on disk, and ``adjust(...,
Options(resume=True))`` (``sapgo adjust --resume``) continues from it. The results are written
into a copy of the project that replaces it by an atomic rename; the work directory is removed
after that.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import shutil
import sys
import time
import uuid
from pathlib import Path

import numpy as np

from .lock import writes_project
from . import normals, paging
from . import threads as _threads
from .solve.band import (
    PIVOT_TOLERANCE,
    BandSolver,
    BorderPivotError,
    PivotError,
)
from .errors import (
    DatumDefectError,
    ParameterError,
    ProjectFormatError,
    SapgoError,
    SingularNormalsError,
    UndeterminedPointError,
)
from .apsets import AP_SETS, N_TERMS
from .geometry import (
    AP_NAMES,
    AP_SET,
    CALIBRATION_COLUMNS,
    CALIBRATION_FIELDS,
    CALIBRATION_POWERS,
    INTRINSICS,
    N_CALIBRATION,
    N_CAMERA,
    beyond_brown,
    camera_array,
    project_observations,
    turned,
    with_rotations,
)
from .normals import (
    BAD_LAYOUT,
    BEHIND_CAMERA,
    CTRL_MASK,
    OK,
    PointChunk,
    build_points_parallel,
    control_rotations,
    point_costs_parallel,
    update_points_parallel,
)
from .ordering import order_project
from .extsort import parse_memory
from .project import (
    CONTROL_MASK,
    EO_NAMES,
    KIND_CHECK,
    KIND_CONTROL,
    PHOTO_CAMERA_NARROW,
    PRIOR_DTYPE,
    STATUS_ACTIVE,
    STATUS_REJECTED,
    Project,
    disk_full_error,
    ensure_free,
    is_disk_full,
    memory_image,
    write_image,
)
from .report import (
    HighCorrelations,
    Summary,
    check_point_statistics,
    precision_summary,
    noncentrality,
    reliability_statistics,
    truth_statistics,
)
from .quality import quality_sweep, reweight
from .stripcmp import StripComparison
from .work import Work, _fault, _identity, work_path
from .frames import frame_info
from .validate import check_values

ARCSEC = math.pi / (180 * 3600)
#: Solution methods (:attr:`Options.method`).
METHODS = ("auto", "gauss-newton", "levenberg-marquardt")
#: Where the band's factor rows live (``Options.factor_storage``).
FACTOR_STORAGES = ("auto", "core", "file", "replay")
#: Whether a run has work files (``Options.work_files``).
WORK_FILES = ("auto", "always", "never")
#: ``work_files`` "auto": a project file up to this size (and a sixteenth of the memory
#: budget) is adjusted in memory, without work files or checkpoints (a run of seconds).
IN_MEMORY_BYTES = 64 << 20
#: The datums ``--datum`` names (:attr:`Options.datum`; None: the project's).
DATUMS = (None, "control", "priors", "free")
#: Iterations of a run without ``max_iterations``: Gauss-Newton converges in a few, the
#: damped steps of Levenberg-Marquardt (a free network, a BAL problem) may need many
#: (Ceres' default, 50).
GN_MAX_ITERATIONS = 10
LM_MAX_ITERATIONS = 50
#: Columns of the observations' quality (work file ``quality.bin``, ``/solution/obs_quality``).
#: At most this many ids of excluded points or stations are listed in a report.
LISTED_IDS = 1000


@dataclasses.dataclass
class Options:
    """How to adjust. Every default is what a SAPGO-P block needs."""

    #: Stop after this many iterations even if not converged (None: 10 Gauss-Newton
    #: iterations, or :data:`LM_MAX_ITERATIONS` for a free network or Levenberg-Marquardt).
    max_iterations: int | None = None
    #: Converged when every station position and point correction is below this (m) ...
    tol_position: float = 1e-4
    #: ... and every station angle correction below this (rad; default 0.1").
    tol_angle: float = 0.1 * ARCSEC
    #: ... and sigma0 changed by less than this fraction since the previous iteration.
    tol_sigma0: float = 1e-3
    #: Station ordering when the project is not ordered yet: "best" or a candidate name.
    ordering: str = "best"
    #: Points read per chunk in the streaming passes (with their observations: about 4 MB
    #: of records per 10 000 points of a 9-point block).
    chunk_points: int = 16384
    #: Band rows kept in core beyond the band width (the solver's read/write block).
    chunk_rows: int = 256
    #: A Cholesky pivot at or below this fraction of its original diagonal counts as zero.
    pivot_tolerance: float = PIVOT_TOLERANCE
    #: Keep the work directory (band and factor rows, buffers) after the run.
    keep_scratch: bool = False
    #: Continue an interrupted run from its last completed iteration (if there is one).
    resume: bool = False
    #: Memory budget of the external sorts when the project has to be ordered first (default
    #: 512 MiB) and, on the tree, of the whole adjustment (default 1 GiB): the process's
    #: baseline, the records held in core for the run's passes (at most a quarter), the
    #: solver's fronts (tiled when they would not fit) and its factor when it fits. On the
    #: band a quarter of it (of 1 GiB by default) bounds the factor rows kept in core
    #: (``factor_storage`` "auto").
    memory: int | str | None = None
    #: Progress bars: True, False, or None for "when stderr is a terminal".
    progress: bool | None = None
    #: Robust estimation of the image observations: None, "huber" or "cauchy" (iteratively
    #: reweighted from the previous iteration's residuals; control and priors never are).
    robust: str | None = None
    #: Threshold of the robust weight function, um of standardised image residual
    #: (``sqrt(v' R^+ v)``, the residual scaled by its redundancy).
    robust_threshold_um: float = 30.0
    #: Reweighting has converged when the corrections are below this fraction of the mean
    #: standard deviations of the least-squares solution (or the absolute tolerances).
    robust_tolerance: float = 0.01
    #: Baarda's data snooping after convergence: reject the observation with the largest
    #: normalised residual above the critical value of ``snooping_alpha`` and iterate again.
    snooping: bool = False
    snooping_alpha: float = 0.001
    #: Data snooping rejects at most this many observations.
    max_rejections: int = 1000
    #: Data snooping rejects, each round, every significant observation whose photos are
    #: not those of one rejected already in the round, and confirms its rejections at the
    #: end (:func:`_snoop`); False (the default): the largest alone, one round a rejection.
    snooping_batch: bool = False
    #: Bring back the observations an earlier run rejected (data snooping flags them
    #: rejected in the project; without this they stay out, and the report says how many).
    reset_rejections: bool = False
    #: Correlations of a station's or a point's parameters above this are listed.
    correlation_threshold: float = 0.9
    #: "auto" (Gauss-Newton; Levenberg-Marquardt from the first step that raises the cost,
    #: and always for a free network), "gauss-newton" or "levenberg-marquardt".
    method: str = "auto"
    #: Levenberg-Marquardt: the first damping ``mu`` (the normals' diagonal times ``1 + mu``;
    #: Ceres' initial trust region radius 1e4 is mu = 1e-4).
    lm_initial_mu: float = 1e-4
    #: Levenberg-Marquardt: converged when an accepted step lowers the cost by less than this
    #: fraction (Ceres' function_tolerance).
    tol_cost: float = 1e-6
    #: Self-calibration: the camera fields adjusted with the block, shared by every photo of
    #: the camera (a few global unknowns bordering the band; docs/theory.md section 1c):
    #: any of "f", "x0", "y0", "k1", "k2", "k3", "p1", "p2". Empty: cameras held fixed.
    calibrate: tuple = ()
    #: The camera ids self-calibrated (None: every camera with a photo).
    calibrate_cameras: tuple | None = None
    #: Self-calibration: the camera fields adjusted per photo (each photo of a calibrated
    #: camera its own value, e.g. the principal point of a camera that refocuses), beside the
    #: shared ones of ``calibrate`` (any of those fields; not both).
    calibrate_per_photo: tuple = ()
    #: Station parameters held fixed (true constraints, ``--datum fix:IDS:PARAMS``): pairs
    #: ``(photo ids, parameter names)`` of omega, phi, kappa, X, Y, Z (or "IDS:PARAMS"
    #: strings). With them the datum is the user's: no control is required.
    fix: tuple = ()
    #: The datum (``--datum``): None (the project's: its control and priors, or a free
    #: network when it has neither), "control" (the control points alone; station priors
    #: not used), "priors" (the station priors alone; control points used as check points)
    #: or "free" (neither: a free network by inner constraints, control points as check
    #: points; :mod:`sapgo.freenet`). ``fix`` adds held parameters to any but "free".
    datum: str | None = None
    #: The precision pass after convergence (``--precision``): "full" (the stations' and
    #: points' standard deviations, the observations' redundancy numbers and tests),
    #: "stations" (the stations' alone, in a fraction of the time) or "none".
    precision: str = "full"
    #: Where the band's factor rows live between the factorisation and the passes that read
    #: them back (``--factor-storage``): "core" (arrays in the process: no file written or
    #: read back), "file" (``factor.bin``: 12 KB a photo at band width 42, read back at the
    #: disk's speed once beyond the page cache), "replay" (no factor file: the solver's state
    #: at the start of every segment of about 5 000 photos, and each segment refactored from
    #: its band rows built again when it is read back;
    #: :class:`sapgo.solve.band.FactorReplay`) or "auto" (core when the factor takes at
    #: most a quarter of the memory budget, :func:`factor_core_limit`; replay when it would
    #: exceed half the machine's memory, :func:`factor_file_limit`, or nine tenths of the
    #: free disk; else the file). Self-calibration's border cannot be replayed.
    factor_storage: str = "auto"
    #: The run's scratch: "always" (the work directory ``NAME.h5.work`` beside the project,
    #: and an unordered project's ordered copy beside it: checkpointed every iteration, so
    #: ``resume`` continues an interrupted run), "never" (all in memory: the ordered copy
    #: and the buffers, the band's factor within ``factor_storage``'s core budget; no
    #: checkpoint, an interrupted run starts again; the commit writes the adjusted project
    #: in one write) or "auto" (never for a project file up to :data:`IN_MEMORY_BYTES` and
    #: a sixteenth of the memory budget, a run of seconds; always beyond, on Dask, with
    #: ``keep_scratch``, or to resume a run).
    work_files: str = "auto"
    #: Above this many stations the per-station vectors of the run (orientations, step,
    #: variances: 48 bytes a station each) are memory-mapped from scratch files whose pages
    #: go back to the page cache as the passes move on (:mod:`sapgo.paging`;
    #: ``--page-stations``; None: :data:`sapgo.paging.PAGE_STATIONS`, 0: always).
    page_stations: int | None = None
    #: The linear solver: "band" (recursive partitioning of the band: long strips), "tree"
    #: (the partition tree of nested dissection: any block shape) or "auto" (the project's
    #: order as ``sapgo order`` chose it by predicted cost; an unordered project is ordered
    #: for the cheaper). A project ordered for the other solver is ordered again first.
    solver: str = "auto"
    #: A Dask distributed ``Client``: the partition tree's subtrees are built and factored
    #: on its workers, a part a worker for the whole run (they must see the project and its
    #: work directory on a shared filesystem; :mod:`sapgo.solve.distributed`). None: threads
    #: of this process.
    client: object = None

    def check(self):
        """Refuse, before any work, every option out of its range (one line each)."""
        from .ordering import ORDERINGS

        _threads.parts()   # (SAPGO_THREADS: a number or "auto")

        def number(name, value, lo, hi, what, closed_hi=False):
            try:
                v = float(value)
            except (TypeError, ValueError):
                v = math.nan
            if not (math.isfinite(v) and lo < v and (v <= hi if closed_hi else v < hi)):
                raise ParameterError(f"{name} {value!r}: {what}")

        for name in ("max_iterations", "max_rejections", "chunk_points", "chunk_rows"):
            v = getattr(self, name)
            if name == "max_iterations" and v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                raise ParameterError(f"{name} {v!r}: a whole number")
        if self.max_iterations is not None and self.max_iterations < 1:
            raise ParameterError(f"--max-iterations (max_iterations) {self.max_iterations}: "
                                 f"at least 1")
        if self.max_rejections < 0:
            raise ParameterError(f"max_rejections {self.max_rejections}: 0 or more")
        for name in ("tol_position", "tol_angle", "tol_sigma0"):
            number(f"--{name.replace('_', '-')} ({name})", getattr(self, name), 0.0, math.inf,
                   "the convergence tolerances must be positive and finite")
        number("--alpha (snooping_alpha)", self.snooping_alpha, 0.0, 1.0,
               "the significance level of data snooping is a probability between 0 and 1 "
               "(e.g. 0.001)")
        number("correlation_threshold", self.correlation_threshold, 0.0, 1.0,
               "a correlation above 0, at most 1", closed_hi=True)
        number("robust_tolerance", self.robust_tolerance, 0.0, math.inf,
               "a positive fraction")
        if self.ordering not in ORDERINGS:
            raise ParameterError(f"ordering {self.ordering!r}: choose from "
                                 f"{', '.join(ORDERINGS)}")
        if self.method not in METHODS:
            raise SapgoError(f"method {self.method!r}: one of {', '.join(METHODS)}")
        number("lm_initial_mu", self.lm_initial_mu, 0.0, math.inf, "positive and finite")
        number("--tol-cost (tol_cost)", self.tol_cost, 0.0, math.inf, "positive and finite")
        if self.chunk_points < 1 or self.chunk_rows < 1:
            raise SapgoError("chunk sizes must be positive")
        if not 0 <= self.pivot_tolerance < 1:
            raise SapgoError("pivot_tolerance must be in [0, 1)")
        if self.memory is not None:
            parse_memory(self.memory)  # a bad size is refused before anything runs
        if self.solver not in ("auto", "band", "tree"):
            raise SapgoError(f"solver {self.solver!r}: choose auto, band or tree")
        if self.robust not in (None, "huber", "cauchy"):
            raise SapgoError(f"robust {self.robust!r}: choose huber or cauchy")
        number("--robust-threshold (robust_threshold_um)", self.robust_threshold_um, 0.0, math.inf,
               "the robust threshold must be positive (um)")
        if isinstance(self.calibrate, str):
            self.calibrate = tuple(x for x in self.calibrate.replace(",", " ").split() if x)
        self.calibrate = tuple(self.calibrate)
        bad = [x for x in self.calibrate if x not in CALIBRATION_NAMES]
        if bad:
            raise SapgoError(f"self-calibration of {bad[0]!r}: the camera parameters that can "
                             f"be adjusted are {CALIBRATION_HELP}")
        if len(set(self.calibrate)) != len(self.calibrate):
            raise SapgoError("self-calibration: a camera parameter is named twice")
        if isinstance(self.calibrate_per_photo, str):
            self.calibrate_per_photo = tuple(
                x for x in self.calibrate_per_photo.replace(",", " ").split() if x)
        self.calibrate_per_photo = tuple(self.calibrate_per_photo)
        bad = [x for x in self.calibrate_per_photo if x not in CALIBRATION_NAMES]
        if bad:
            raise SapgoError(f"self-calibration per photo of {bad[0]!r}: the camera "
                             f"parameters that can be adjusted are {CALIBRATION_HELP}")
        both = [x for x in self.calibrate_per_photo if x in self.calibrate
                or (x == "ap" and any(y in AP_NAMES for y in self.calibrate))
                or (x in AP_NAMES and "ap" in self.calibrate)]
        if both or len(set(self.calibrate_per_photo)) != len(self.calibrate_per_photo):
            raise SapgoError(f"self-calibration: {(both or self.calibrate_per_photo)[0]} is "
                             f"named twice (a parameter is shared by a camera's photos or "
                             f"adjusted per photo, not both)")
        self.fix = tuple(parse_fix(f) for f in self.fix)
        if self.factor_storage not in FACTOR_STORAGES:
            raise ParameterError(f"factor storage {self.factor_storage!r}: choose "
                                 f"{', '.join(FACTOR_STORAGES)}")
        if self.work_files not in WORK_FILES:
            raise ParameterError(f"work files {self.work_files!r}: choose "
                                 f"{', '.join(WORK_FILES)}")
        if self.page_stations is not None and self.page_stations < 0:
            raise ParameterError(f"page stations {self.page_stations}: a number of stations, "
                                 f"0 or more")
        if self.precision not in ("full", "stations", "none"):
            raise ParameterError(f"precision {self.precision!r}: choose full, stations or none")
        if self.snooping_batch and not self.snooping:
            raise ParameterError("snooping_batch is a way of data snooping: set snooping too "
                                 "(sapgo adjust --snooping-batch implies --snooping)")
        if self.datum not in DATUMS:
            raise ParameterError(f"datum {self.datum!r}: choose control, priors or free (or "
                                 f"fix:IDS:PARAMS)")
        if self.datum == "free" and self.fix:
            raise ParameterError("--datum free and --datum fix: a free network's datum is "
                                 "its inner constraints; held parameters make it another")
        if self.calibrate_cameras is not None:
            self.calibrate_cameras = tuple(int(c) for c in self.calibrate_cameras)
            if len(set(self.calibrate_cameras)) != len(self.calibrate_cameras):
                raise SapgoError("self-calibration: a camera id is named twice")
            if not self.calibrate and not self.calibrate_per_photo:
                raise SapgoError("calibrate_cameras without calibrate: name the camera "
                                 "parameters to adjust")
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


_NO_PRIORS = np.zeros(0, PRIOR_DTYPE)


class _PriorCursor:
    """Station priors, read in chunks in station order as band rows enter the window, handed
    out as their terms of the normal equations; and for each station parameter held fixed
    (``blk.fixed``, ``--datum fix``) a unit weight at its current value (its columns of A
    are zero, :func:`sapgo.normals.fixed_columns`: the unit diagonal keeps the normals
    regular and its correction exactly 0)."""

    def __init__(self, project, chunk, blk):
        self.p = project
        self.n = project.n_priors
        self.chunk = chunk
        self.pos = 0
        self.buf = _NO_PRIORS   # (replaced by the first chunk read; no read here: 0.4 ms)
        self.bpos = 0
        self.blk = blk

    def seek(self, station):
        """Start at the first prior record of a station at or after ``station`` (records
        sorted by station; a binary search of the file)."""
        lo, hi = 0, self.n
        while lo < hi:
            mid = (lo + hi) // 2
            if int(self.p.read_field("station_priors", "station", mid, mid + 1)[0]) < station:
                lo = mid + 1
            else:
                hi = mid
        self.pos, self.buf, self.bpos = lo, _NO_PRIORS, 0
        return self

    def records(self, lo, hi):
        """Prior records of stations in ``[lo, hi)``; calls must come in increasing station
        order."""
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

    def take(self, lo, hi):
        """``(station, W, r)`` of the priors of stations in ``[lo, hi)``: their weight and
        right-hand side in the adjustment's unknowns (:func:`prior_terms`)."""
        out = []
        fixed = self.blk.fixed
        if len(fixed) and fixed[lo:hi].any():   # (in the unknowns themselves)
            for s in lo + np.flatnonzero(fixed[lo:hi]):
                bits = (int(fixed[s]) >> np.arange(6)) & 1
                out.append((int(s), np.diag(bits.astype(np.float64)), np.zeros(6)))
        recs = self.records(lo, hi) if self.blk.use_priors else []
        if recs:
            recs = np.array(recs, dtype=self.buf.dtype)
            w, r = prior_terms(recs, self.blk.eo[recs["station"]])
            out += list(zip(recs["station"].tolist(), w, r))
        return out


def prior_terms(recs, eo):
    """Normal-equation terms ``(W', r)`` (n x 6 x 6, n x 6) of prior records at the stations'
    current values ``eo``: the priors observe omega, phi, kappa, while the adjustment turns
    a photo by a rotation vector (:func:`sapgo.geometry.turn`), so the angles' rows go
    through ``J = d(omega, phi, kappa)/d theta`` (:func:`sapgo.geometry.attitude_jacobians`):
    ``W' = T' W T``, ``r = -T' W v`` with ``T = diag(J, I)`` and ``v`` the prior's residual
    (angles wrapped)."""
    from .geometry import attitude_jacobians

    w = np.asarray(recs["weight"], np.float64)
    v = np.asarray(eo, np.float64)[:, :6] - recs["value"]
    v[:, :3] = _wrap(v[:, :3])
    t = np.zeros((len(recs), 6, 6))
    t[:, :3, :3] = attitude_jacobians(eo[:, :3])
    t[:, 3:, 3:] = np.eye(3)
    tw = np.transpose(t, (0, 2, 1)) @ w
    return tw @ t, -np.einsum("nij,nj->ni", tw, v)


@dataclasses.dataclass
class _Block:
    """Per-station state and block counts (in core: O(stations) small vectors)."""

    station_ids: np.ndarray
    station_active: np.ndarray
    camera: np.ndarray
    eo: np.ndarray
    cams: np.ndarray  # per camera: the kernels' row (f, x0, y0, k1, k2, k3, p1, p2)
    cam_sigma: np.ndarray  # per camera: sigma_image (mm), for observations with sigma 0
    band_width: int
    frame: object = None  # sapgo.frames.Frame: control sigmas along east, north, up in a CRS
    #: observations rejected by data snooping in this run (record numbers, sorted) and, in the
    #: order of rejection, ``{"observation", "w", "by"}``: the test statistic it was rejected
    #: with, "test" or "point" (the other rays of a point left with fewer than two)
    rejected: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))
    rejections: list = dataclasses.field(default_factory=list)
    #: observations batch snooping rejected and brought back when confirmed (record numbers)
    reinstated: list = dataclasses.field(default_factory=list)
    #: data snooping's last precision pass: ``(key, result, correlations)``
    #: (:func:`_snooping_pass`), which the commit takes if nothing changed since
    last_pass: tuple | None = None
    #: planted blunders (generated blocks): their observations and non-centrality parameters
    #: in the adjustment with every observation (None: not computed yet)
    planted: dict | None = None
    #: points left undeterminable by those rejections (excluded for the rest of the run)
    rejected_points: np.ndarray = dataclasses.field(
        default_factory=lambda: np.zeros(0, np.int64))
    n_points: int = 0
    n_rays: int = 0
    n_control: dict = dataclasses.field(default_factory=dict)
    n_weighted_control: int = 0
    n_fixed: int = 0
    #: per station, its parameters held fixed (bit u: omega, phi, kappa, X, Y, Z;
    #: ``Options.fix``), and their number over the active stations
    fixed: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int8))
    n_fixed_params: int = 0
    #: pass points set aside during the run, their rays (nearly) parallel at the values of
    #: the time (record -> [record, active rays, id, iteration]); they are among
    #: ``rejected_points`` until their rays allow them back (:func:`_bring_back`), and
    #: ``aside_log`` tells what happened to each
    aside: dict = dataclasses.field(default_factory=dict)
    aside_log: list = dataclasses.field(default_factory=list)
    n_prior_params: int = 0
    #: a free network (no control, no priors; the project attribute ``datum`` is "free",
    #: or ``--datum free``): adjusted under minimal constraints, given in the inner
    #: constraints' datum (:mod:`sapgo.freenet`)
    free: bool = False
    #: which control components the kernels use (by point kind): the control's
    #: ``CTRL_MASK``, or none when the datum is not the control's (``--datum free|priors``)
    ctrl_mask: np.ndarray = dataclasses.field(default_factory=lambda: CTRL_MASK)
    #: the station priors are observations (not with ``--datum free|control``)
    use_priors: bool = True
    #: control points left out of the run: one ray, their control not used (``--datum``)
    one_ray_control: int = 0
    #: the datum as the user chose it (``Options.datum``), or None: the project's
    datum: str | None = None
    #: parameters per station: 6, or 9 with the photo's own intrinsics adjusted (project
    #: attribute ``station_intrinsics`` "adjusted"; f, k1 f^2, k2 f^4, see
    #: :data:`sapgo.geometry.INTRINSICS`; one camera per photo)
    npar: int = 6
    #: points behind a camera are projected all the same (project attribute
    #: ``points_behind`` "allowed": BAL problems), not refused
    behind_ok: bool = False
    #: self-calibration: ``cal[camera, field]`` is the border column of a camera's field
    #: (:data:`sapgo.geometry.CALIBRATION_FIELDS`), -1 where held; ``border`` lists
    #: ``(camera index, field index)`` by column
    cal: np.ndarray = dataclasses.field(
        default_factory=lambda: np.full((0, N_CALIBRATION), -1, np.int64))
    border: list = dataclasses.field(default_factory=list)
    #: the camera record of every camera row (rows beyond the project's cameras: a photo's
    #: own row, for parameters calibrated per photo, :func:`_set_calibration`)
    row_camera: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int64))
    #: the border's cofactors ``S^-1`` of the last accepted step (ng x ng)
    border_cov: np.ndarray | None = None
    #: the factor in the work files is not the undamped one of the current state (a
    #: Levenberg-Marquardt step, a rejected step, a resumed run): the precision sweep builds
    #: and factors the normals once more, undamped, first
    refactor: bool = False
    #: the partition tree (:class:`sapgo.solve.partition.Tree`) when the project is ordered
    #: for the tree solver, else None (the band)
    tree: object = None
    #: bytes of point and observation records held in core for the run (out of the memory
    #: budget that the tree solver's fronts and factor share)
    held: int = 0
    #: the band's factor is replayed, not kept in a file (``Options.factor_storage``)
    replay: bool = False
    #: the band's factor rows are arrays in core, not a file (``Options.factor_storage``)
    core: bool = False

    @property
    def solver(self):
        return "band" if self.tree is None else "tree"

    @property
    def n_border(self):
        return len(self.border)

    @property
    def n_stations(self):
        return int(self.station_active.sum())

    @property
    def redundancy(self):
        equations = 2 * self.n_rays + self.n_weighted_control + self.n_prior_params
        unknowns = (self.npar * self.n_stations + 3 * self.n_points - self.n_fixed
                    + self.n_border - self.n_fixed_params)
        # a free network: its 7 datum parameters are not determined by the observations
        return equations - unknowns + (7 if self.free else 0)


def _load_block(p: Project) -> _Block:
    cams = p.cameras()
    active = paging.empty(p.n_stations, bool)
    for a, b in p.chunks("stations"):
        active[a:b] = p.read_field("stations", "status", a, b) == STATUS_ACTIVE
    blk = _Block(
        station_ids=paging.field(p, "stations", "id"),
        station_active=active,
        camera=paging.field(p, "stations", "camera", np.int32),
        eo=paging.field(p, "stations", "eo", np.float64),
        cams=camera_array(cams),
        cam_sigma=np.ascontiguousarray(cams["sigma_image"]),
        band_width=p.band_width,
        frame=p.frame(),
        free=p.attr("datum", "") == "free",
        behind_ok=p.attr("points_behind", "") == "allowed",
        npar=9 if p.attr("station_intrinsics", "") == "adjusted" else 6,
        tree=p.tree(),
    )
    blk.fixed = paging.zeros(len(blk.station_ids), np.int8)
    if blk.npar == 9:
        cam = blk.camera[blk.station_active]
        shared = np.bincount(cam, minlength=len(blk.cams))
        if (shared > 1).any():
            c = int(np.argmax(shared > 1))
            raise SapgoError(f"{p.path}: the photos' own intrinsics are adjusted "
                             f"(station_intrinsics), but camera id "
                             f"{int(p.cameras()['id'][c])} is shared by {int(shared[c])} "
                             f"photos: each photo needs a camera of its own")
    names = {1: "full", 2: "horizontal", 3: "vertical"}
    counts = {v: 0 for v in names.values()}
    for a, b in p.chunks("points"):
        pts = p.read("points", a, b, copy=False)
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
        blk.n_rays += int((p.read_field("observations", "status", a, b, copy=False)
                           == STATUS_ACTIVE).sum())
    for a, b in p.chunks("station_priors"):
        pr = p.read("station_priors", a, b, copy=False)
        act = blk.station_active[pr["station"]]
        if act.any():  # the rank of each weight matrix (validated positive semi-definite)
            ev = np.linalg.eigvalsh(pr["weight"][act])
            blk.n_prior_params += int((ev > 1e-12 * ev.max(axis=1, keepdims=True)).sum())
    return blk


#: The names ``--calibrate`` takes: the camera fields, and ``ap`` for all the coefficients
#: of each calibrated camera's additional-parameter set (``a1 .. a12`` of Ebner's, ``a1 ..
#: a44`` of Gruen's).
CALIBRATION_NAMES = CALIBRATION_FIELDS + ("ap",)
CALIBRATION_HELP = (", ".join(CALIBRATION_FIELDS[:10]) + ", ap (a camera's whole "
                    "additional-parameter set) or a1 .. a44 (its coefficients)")


def _camera_fields(names, row, cid, p):
    """The calibration fields (indices into :data:`CALIBRATION_FIELDS`) that ``names``
    stand for on the camera row ``row`` (camera id ``cid``): ``ap`` expands to the
    coefficients of its additional-parameter set (none without one); a coefficient beyond
    its set is an error."""
    n_ap = int(N_TERMS[int(row[AP_SET])])
    out = []
    for name in names:
        if name == "ap":
            out.extend(10 + t for t in range(n_ap))
            continue
        f = CALIBRATION_FIELDS.index(name)
        if f >= 10 + n_ap:
            have = (f"its {AP_SETS[int(row[AP_SET])]} set has a1 .. a{n_ap}" if n_ap else
                    "it has no additional-parameter set (import one with "
                    "--additional-parameters)")
            raise SapgoError(f"{p.path}: self-calibration of {name} of camera id {cid}: "
                             f"{have}")
        out.append(f)
    return out


#: Self-calibration: at most this many border unknowns (cameras x parameters). The border's
#: block is dense (g x g in core, g^3 to factor, g^2 work per observation in the precision
#: sweep, g doubles per station parameter on disk).
MAX_BORDER = 256


def _set_calibration(blk: _Block, p: Project, opts: Options):
    """The border of a self-calibration (``Options.calibrate``): a column per adjusted field
    of every calibrated camera that has an active photo. Fields calibrated per photo
    (``Options.calibrate_per_photo``) give each active photo of a calibrated camera a camera
    row of its own (appended to ``blk.cams``; ``blk.row_camera`` says whose), with a column
    of its own for those fields and the camera's columns for the shared ones."""
    n_cam = len(blk.cams)
    blk.row_camera = np.arange(n_cam, dtype=np.int64)
    blk.cal = np.full((n_cam, N_CALIBRATION), -1, np.int64)
    blk.border = []
    if blk.npar == 9:
        odd = np.flatnonzero(beyond_brown(blk.cams))
        if len(odd):
            raise SapgoError(f"{p.path}: the photos' own intrinsics (station_intrinsics) "
                             f"are adjusted with the forward distortion model without "
                             f"affinity or additional parameters; camera id "
                             f"{int(p.cameras()['id'][odd[0]])} has another")
    if not opts.calibrate and not opts.calibrate_per_photo:
        return
    if blk.npar != 6:
        raise SapgoError(f"{p.path}: the photos' own intrinsics are adjusted already "
                         f"(station_intrinsics): self-calibration of shared cameras does not "
                         f"go with it; import with the intrinsics fixed")
    ids = p.cameras()["id"]
    used = np.zeros(n_cam, bool)
    used[blk.camera[blk.station_active]] = True
    if opts.calibrate_cameras is None:
        chosen = np.flatnonzero(used)
    else:
        chosen = []
        for cid in opts.calibrate_cameras:
            hit = np.flatnonzero(ids == cid)
            if not len(hit):
                raise SapgoError(f"{p.path}: self-calibration of camera id {cid}: no such "
                                 f"camera (ids: {', '.join(str(int(i)) for i in ids[:20])})")
            if not used[hit[0]]:
                raise SapgoError(f"{p.path}: self-calibration of camera id {cid}: none of "
                                 f"its photos can be adjusted")
            chosen.append(int(hit[0]))
    chosen = np.asarray(chosen, np.int64)
    shared = {int(c): _camera_fields(opts.calibrate, blk.cams[c], int(ids[c]), p)
              for c in chosen}
    own = {int(c): _camera_fields(opts.calibrate_per_photo, blk.cams[c], int(ids[c]), p)
           for c in chosen}
    for names in (opts.calibrate, opts.calibrate_per_photo):
        if "ap" in names and not any(blk.cams[c, AP_SET] for c in chosen):
            raise SapgoError(f"{p.path}: self-calibration of ap: none of the calibrated "
                             f"cameras has an additional-parameter set (import one with "
                             f"--additional-parameters)")
    photos = (np.flatnonzero(blk.station_active & np.isin(blk.camera, chosen))
              if opts.calibrate_per_photo else np.zeros(0, np.int64))
    n_shared = sum(len(x) for x in shared.values())
    n_own = sum(len(own[int(blk.camera[s])]) for s in photos)
    total = n_shared + n_own
    if total > MAX_BORDER:
        raise SapgoError(
            f"{p.path}: self-calibration of {len(chosen)} cameras ({n_shared} shared "
            f"parameters) and {len(photos)} photos ({n_own} parameters) = "
            f"{total} global unknowns (at most {MAX_BORDER}: the border is dense); choose "
            f"the cameras with --calibrate-cameras, or, with a camera per photo, adjust the "
            f"photos' own intrinsics (import a BAL problem without --fixed-intrinsics)")
    for c in chosen:
        for f in shared[int(c)]:
            blk.cal[c, f] = len(blk.border)
            blk.border.append((int(c), f))
    if len(photos):   # a camera row per photo: the camera's shared columns, its own ones
        rows = n_cam + np.arange(len(photos))
        cams = blk.camera[photos].astype(np.int64)
        blk.cams = np.ascontiguousarray(np.vstack([blk.cams, blk.cams[cams]]))
        blk.cam_sigma = np.ascontiguousarray(np.concatenate([blk.cam_sigma,
                                                             blk.cam_sigma[cams]]))
        blk.cal = np.vstack([blk.cal, blk.cal[cams]])
        blk.row_camera = np.concatenate([blk.row_camera, cams])
        blk.camera = blk.camera.copy()
        blk.camera[photos] = rows
        for r, c in zip(rows, cams):
            for f in own[int(c)]:
                blk.cal[r, f] = len(blk.border)
                blk.border.append((int(r), f))


#: The station parameters ``--datum fix`` names, in the order of a station's eo (bit u).
FIX_PARAMETERS = ("omega", "phi", "kappa", "X", "Y", "Z")


def parse_fix(spec):
    """``(photo ids, bit mask)`` of a fix: ``"IDS:PARAMS"`` (``--datum fix:IDS:PARAMS``
    without ``fix:``; ids and parameter names separated by commas, ``all`` for the six) or a
    pair ``(ids, names)``, names of :data:`FIX_PARAMETERS` (any case)."""
    if isinstance(spec, str):
        text = spec[4:] if spec.lower().startswith("fix:") else spec
        if text.count(":") != 1:
            raise SapgoError(f"datum fix {spec!r}: expected fix:IDS:PARAMS, e.g. "
                             f"fix:101:omega,phi,kappa,X,Y,Z fix:102,103:Z")
        ids_t, names_t = text.split(":")
        try:
            ids = tuple(int(x) for x in ids_t.split(",") if x.strip())
        except ValueError:
            raise SapgoError(f"datum fix {spec!r}: the photo ids must be integer ids, "
                             f"separated by commas") from None
        names = tuple(x.strip() for x in names_t.split(",") if x.strip())
    elif isinstance(spec, tuple) and len(spec) == 2 and isinstance(spec[1], int):
        return tuple(int(i) for i in spec[0]), int(spec[1])
    else:
        ids, names = tuple(int(i) for i in spec[0]), tuple(spec[1])
        if isinstance(spec[1], str):
            names = tuple(x for x in spec[1].replace(",", " ").split() if x)
    if not ids or not names:
        raise SapgoError(f"datum fix {spec!r}: name the photo ids and their parameters")
    return ids, _fix_mask(spec, names)


def _fix_mask(spec, names):
    """The bit mask of a fix's parameter names; omega, phi and kappa only together (a
    photo is turned by a rotation vector: its attitude is held, not one of its angles)."""
    mask = 0
    lower = [n.lower() for n in FIX_PARAMETERS]
    for n in names:
        if n.lower() == "all":
            mask |= 63
            continue
        if n.lower() not in lower:
            raise SapgoError(f"datum fix: unknown station parameter {n!r}; choose from "
                             f"{', '.join(FIX_PARAMETERS)} or all")
        mask |= 1 << lower.index(n.lower())
    if mask & 7 not in (0, 7):
        raise SapgoError(f"datum fix {spec!r}: omega, phi and kappa are held together (the "
                         f"adjustment turns a photo by a rotation vector, not angle by "
                         f"angle): name all three, or all")
    return mask


def _set_fixed(blk: _Block, p: Project, opts: Options):
    """``blk.fixed`` from ``Options.fix``: every named photo must exist and be adjusted, and
    a fixed parameter must not have a prior as well."""
    n = len(blk.station_ids)
    blk.fixed = paging.zeros(n, np.int8)
    blk.n_fixed_params = 0
    if not opts.fix:
        return
    order = np.argsort(blk.station_ids, kind="stable")
    sorted_ids = blk.station_ids[order]
    for ids, mask in opts.fix:
        for pid in ids:
            at = int(np.searchsorted(sorted_ids, pid))
            if at >= n or sorted_ids[at] != pid:
                raise SapgoError(f"{p.path}: datum fix of photo id {pid}: no such photo")
            s = int(order[at])
            if not blk.station_active[s]:
                raise SapgoError(f"{p.path}: datum fix of photo id {pid}: the photo is "
                                 f"excluded from the adjustment")
            blk.fixed[s] |= mask
    for a, b in p.chunks("station_priors"):
        pr = p.read("station_priors", a, b)
        w = np.diagonal(pr["weight"], axis1=1, axis2=2) > 0
        bits = (blk.fixed[pr["station"]][:, None].astype(np.int64) >> np.arange(6)) & 1
        hit = np.flatnonzero((w & (bits == 1)).any(axis=1))
        if len(hit):
            s = int(pr["station"][hit[0]])
            u = int(np.flatnonzero(w[hit[0]] & (bits[hit[0]] == 1))[0])
            raise SapgoError(f"{p.path}: datum fix of photo id {int(blk.station_ids[s])}: "
                             f"its {FIX_PARAMETERS[u]} has a prior too; fix it or weight it, "
                             f"not both")
    act = blk.fixed[blk.station_active].astype(np.int64)
    blk.n_fixed_params = int(((act[:, None] >> np.arange(6)) & 1).sum())
    blk.free = False   # (the user's datum)


def _set_datum(blk: _Block, p: Project, opts: Options):
    """The datum the user chose (``Options.datum``): the control's components and the
    priors in or out of the normals (the counts of the redundancy with them); a control
    point left with one ray when its control is out is left out of the run."""
    if opts.datum is None:
        return
    blk.datum = opts.datum
    if opts.datum in ("priors", "free"):
        blk.ctrl_mask = np.zeros_like(CTRL_MASK)
        blk.n_weighted_control = blk.n_fixed = 0
        one_ray, rays = [], 0
        for a, b in p.chunks("points"):
            pts = p.read("points", a, b)
            ctrl = CONTROL_MASK[pts["kind"]].any(axis=1) & (pts["status"] == STATUS_ACTIVE)
            if not ctrl.any():
                continue
            o0 = int(pts["obs_start"][0])
            o1 = int(pts["obs_start"][-1] + pts["n_obs"][-1])
            ob = p.read("observations", o0, o1)
            live = ob["status"] == STATUS_ACTIVE
            owner = np.repeat(np.arange(b - a), pts["n_obs"])
            pairs = np.unique(owner[live] * p.n_stations + ob["station"][live])
            distinct = np.bincount(pairs // p.n_stations, minlength=b - a)
            out = ctrl & (distinct < 2)
            one_ray.extend((a + np.flatnonzero(out)).tolist())
            rays += int((live & out[owner]).sum())
        if one_ray:
            blk.rejected_points = np.union1d(blk.rejected_points, one_ray).astype(np.int64)
            blk.n_points -= len(one_ray)
            blk.n_rays -= rays
        blk.one_ray_control = len(one_ray)
    if opts.datum in ("control", "free"):
        blk.use_priors = False
        blk.n_prior_params = 0
    if opts.datum == "free":
        blk.free = True
    elif opts.datum == "priors" and blk.n_prior_params == 0 and not blk.n_fixed_params:
        raise DatumDefectError(f"{p.path}: --datum priors: the project has no station priors "
                               f"(import them with --priors, or choose another datum)")
    elif opts.datum in ("control", "priors"):
        blk.free = False


def _border_names(blk: _Block, p: Project):
    """``"camera <id> <field>"`` (``"photo <id> <field>"`` for a field calibrated per photo)
    of every border column (for messages and the report)."""
    ids = p.cameras()["id"]
    n_cam = len(ids)
    names = []
    for c, f in blk.border:
        if c < n_cam:
            names.append(f"camera {int(ids[c])} {CALIBRATION_FIELDS[f]}")
        else:
            s = int(np.flatnonzero(blk.camera == c)[0])
            names.append(f"photo {int(blk.station_ids[s])} {CALIBRATION_FIELDS[f]}")
    return names


def _border_step(blk: _Block, theta):
    """Per camera row, the step of its border parameters (zero where held): rows x
    :data:`~sapgo.geometry.N_CALIBRATION` (a shared column moves every row it is in)."""
    dtheta = np.zeros((len(blk.cams), N_CALIBRATION))
    on = blk.cal >= 0
    dtheta[on] = np.asarray(theta)[blk.cal[on]]
    return dtheta


def _border_settled(blk: _Block, dtheta):
    """Self-calibration has converged when no camera's step moves an image point at the
    distance f from the principal point by more than 1/1000 of the camera's sigma (every
    scaled border parameter moves it by about its own size: df, dx0, d(k1 f^2) f, ...)."""
    f = blk.cams[:, 0]
    move = np.abs(dtheta).copy()
    move[:, 3:10] *= np.abs(f)[:, None]   # (the additional parameters are in mm)
    return bool((move.max(axis=1) <= 1e-3 * blk.cam_sigma).all())


def _calibration_report(p: Project, blk: _Block, run, sigma0):
    """Per self-calibrated camera parameter: its value before and after, the correction and
    its a-posteriori standard deviation (sigma0 times the root of the border's cofactor, in
    the field's own unit)."""
    cams0 = camera_array(p.cameras())
    ids = p.cameras()["id"]
    # (a free network's: the S-transformation to the inner constraints leaves the cameras'
    # cofactors as they are, the similarity not moving a camera; sapgo.freenet)
    cov = blk.border_cov
    rows = []
    for col, (c, f) in enumerate(blk.border):
        scale = float(blk.cams[c, 0]) ** int(CALIBRATION_POWERS[f])
        sig = (sigma0 * math.sqrt(max(cov[col][col], 0.0)) / scale if cov is not None
               else None)
        c0 = int(blk.row_camera[c]) if len(blk.row_camera) else c
        k = int(CALIBRATION_COLUMNS[f])
        row = {"camera": int(ids[c0]), "parameter": CALIBRATION_FIELDS[f],
               "initial": float(cams0[c0, k]), "adjusted": float(blk.cams[c, k]),
               "correction": float(blk.cams[c, k] - cams0[c0, k]), "sigma": sig}
        if c != c0:   # a parameter calibrated per photo
            row["photo"] = int(blk.station_ids[np.flatnonzero(blk.camera == c)[0]])
        rows.append(row)
    return rows


def _border_pivot_error(exc: BorderPivotError, blk: _Block, p: Project):
    name = _border_names(blk, p)[exc.index]
    return SingularNormalsError(
        f"{p.path}: self-calibration: {name} cannot be determined by this block (it is not "
        f"separable from the other unknowns: e.g. f from the flying height without height "
        f"differences, or the principal point from the photos' positions without position "
        f"priors); adjust fewer camera parameters")


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
        f"(3 shifts, 3 rotations, scale). Add control points or station priors, or adjust "
        f"it as a free network (--datum free)."
    )


def check_datum(p: Project, fixed=False, datum=None):
    """Raise :class:`DatumDefectError` when the control cannot fix the datum (a project
    marked as a free network, ``datum = "free"``, needs none, nor one whose datum the user
    gives by fixed station parameters, ``fixed``, or chooses free). ``datum``: the user's
    choice (:attr:`Options.datum`): "control" counts the control alone, "priors" the
    priors alone."""
    if datum == "free" or fixed or (datum is None and p.attr("datum", "") == "free"):
        return
    nh, nv, npr = _datum_counts(p)
    if datum == "priors":
        if npr == 0:
            raise DatumDefectError(f"{p.path}: --datum priors: the project has no station "
                                   f"priors (import them with --priors, or choose another "
                                   f"datum)")
        return
    if datum == "control":
        npr = 0
    if npr == 0 and (nh < 2 or nv < 3):
        raise DatumDefectError(f"{p.path}: datum defect: " + _datum_advice(nh, nv, npr))


# -- the phases ------------------------------------------------------------------------

def _init_rows(band, rhs, base, lo, hi, blk, priors):
    """Band rows of stations ``lo .. hi-1`` enter the window: priors and excluded stations."""
    n = len(blk.station_active)
    hi = min(hi, n)
    k = blk.npar
    for s in range(lo, hi):
        if not blk.station_active[s]:
            band[s - base, :, :k] += np.eye(k)
    for s, w, r in priors.take(lo, hi):
        if not blk.station_active[s]:
            continue
        band[s - base, :6, :6] += w
        rhs[s - base, :6] += r


def _behind_depths(chunk, blk, rays):
    """The camera-frame z (negative: in front) of the chunk's observations ``rays``."""
    from .frames import rotation_matrices

    s = chunk.obs_station[rays]
    owner = np.searchsorted(chunk.pt_start, rays, side="right") - 1
    m = rotation_matrices(blk.eo[s, :3])
    return np.einsum("nj,nj->n", m[:, 2, :], chunk.xyz[owner] - blk.eo[s, 3:6])


def _behind_message(p, chunk, j, pid, blk):
    """A point behind a photo: which photos, and when most of its chunk's rays point
    backwards too, the hint that the frame or the axes are mirrored."""
    a = int(chunk.pt_start[j])
    mine = a + np.flatnonzero(chunk.obs_active[a:a + int(chunk.nobs[j])])
    st = sorted({int(p.read("stations", int(s), int(s) + 1)["id"][0])
                 for s in chunk.obs_station[mine[_behind_depths(chunk, blk, mine) >= 0]]})
    photos = ", ".join(map(str, st[:5])) + (", ..." if len(st) > 5 else "")
    text = (f"point id {pid} lies behind photo(s) id {photos or '?'} at its current "
            f"coordinates")
    rays = np.flatnonzero(chunk.obs_active)[:20000]
    share = float(np.mean(_behind_depths(chunk, blk, rays) >= 0)) if len(rays) else 0.0
    if share > 0.5:
        return (f"{text}, and so do {share:.0%} of the rays of the points around it: are "
                f"the axes mirrored (northing before easting, Z down, image y down, or the "
                f"rotations of another convention)? sapgo takes X, Y, Z right-handed (east, "
                f"north, up), image x to the right and y up, and a camera looking down its "
                f"-z axis (docs/theory.md section 1)")
    return (f"{text}: check its approximate coordinates and the photos' approximate "
            f"orientation")


def _point_error(p, chunk, j, status, blk):
    rec = p.read("points", chunk.start + j, chunk.start + j + 1)[0]
    pid = int(rec["id"])
    if status == BAD_LAYOUT:
        where = ("has a station outside the front of its partition tree node"
                 if blk.tree is not None else
                 f"does not follow the stored logical order and band width {p.band_width}")
        return SapgoError(
            f"{p.path}: point id {pid} (record {chunk.start + j}) {where}: the records were "
            f"changed after ordering; run 'sapgo order' again"
        )
    if status == BEHIND_CAMERA:
        return SapgoError(_behind_message(p, chunk, j, pid, blk))
    if CONTROL_MASK[rec["kind"]].any():
        return SingularNormalsError(
            f"point id {pid} cannot be determined: its rays are (nearly) parallel and its "
            f"control does not fix the remaining direction (control_sigma "
            f"{list(rec['control_sigma'])} m); check its image measurements and control"
        )
    return UndeterminedPointError(
        f"point id {pid} cannot be determined: its rays are (nearly) parallel and it has no "
        f"control; check its image measurements", chunk.start + j
    )


class PointMarks:
    """Where the points of given first stations begin: for each of ``rows`` (station
    numbers), the index of the first active point whose first station is at or after it
    (the points are sorted by first station; excluded ones carry none). Filled by the
    forward build (:func:`build` ``marks``), read by the replays (``rows``)."""

    def __init__(self, rows, n_points):
        self.rows = np.unique(np.asarray(rows, np.int64))
        self.points = np.full(len(self.rows), n_points, np.int64)
        self.n_points = n_points
        self._next = 0

    def see(self, a, smin, status):
        """The chunk of points ``a ..`` (their first stations and status)."""
        while self._next < len(self.rows):
            at = np.flatnonzero((status == 0) & (smin >= self.rows[self._next]))
            if not len(at):
                return
            self.points[self._next] = a + int(at[0])
            self._next += 1

    def index(self, row):
        i = int(np.searchsorted(self.rows, row))
        if i == len(self.rows) or self.rows[i] != row:
            raise KeyError(f"no mark at station {row}")
        return int(self.points[i])


class _StateView:
    """``blk`` seen with some of its attributes replaced (``eo``, ``cams``, ``rejected``,
    ``rejected_points``: the state a replay's rows are built from), ``blk`` itself left
    alone for whoever reads it meanwhile."""

    def __init__(self, blk, state):
        self._blk = blk
        for k, v in state.items():
            if v is not None:
                setattr(self, k, v)

    def __getattr__(self, name):
        return getattr(self._blk, name)


def build(p: Project, work, blk: _Block, opts: Options, xyz=None, iteration=0, sink=None,
          lam=0.0, marks=None, rows=None, diag=None, state=None):
    """Stream the points and hand over the reduced normal band rows as they are completed.

    Completed rows go to ``sink(band_rows, rhs_rows)`` in station order (the adjustment feeds
    them straight to the :class:`~sapgo.solve.band.BandSolver`). Without a sink they are
    written into the files ``work.factor`` and ``work.y`` as they are, for tests and
    benchmarks that look at the band rows themselves. ``xyz`` is the array of current point
    coordinates (rows in point order; default ``work.xyz_current``). ``lam > 0``:
    Levenberg-Marquardt damping, ``lam`` times the diagonal of the unreduced normal matrix
    (clamped to [1e-6, 1e32]) added to every station's and every point's diagonal.

    Returns ``(diag, border)``: the stations' undamped diagonal (n x k, with ``lam > 0``,
    else None) and, with self-calibration, ``(cnn, ccg, cdiag)`` -- the border block, its
    right-hand side (both reduced, damped) and its undamped diagonal -- the border columns
    of the band rows having gone to ``work.border`` row by row with the band rows (else
    None).

    ``marks`` (a :class:`PointMarks`): filled on the way. ``rows = (lo, hi)``: the band
    rows of stations ``lo .. hi`` alone, built again from the points whose first station
    lies in ``lo - b + 1 .. hi`` (found through ``marks`` of the full build of the same
    state; ``diag`` its damping diagonal), for :class:`~sapgo.solve.band.FactorReplay`;
    ``state``: attributes of ``blk`` to build from instead (:class:`_StateView`).
    """
    if state is not None:
        blk = _StateView(blk, state)
    n = len(blk.station_ids)
    bw = blk.band_width
    cap = min(n, bw + opts.chunk_rows)
    k = blk.npar
    band = np.zeros((cap, k, k * bw))
    rhs = np.zeros((cap, k))
    threads = _threads.parts()  # per part: b rows of its own beyond its station range
    ovf_band = np.zeros((threads, bw, k, k * bw))
    ovf_rhs = np.zeros((threads, bw, k))
    ng = blk.n_border
    bord = np.zeros((cap, k, ng))
    ovf_bord = np.zeros((threads, bw, k, ng))
    cnn_t, ccg_t, cdiag_t = (np.zeros((threads, ng, ng)), np.zeros((threads, ng)),
                             np.zeros((threads, ng)))
    # the damping's diagonal of the window's stations, summed by the kernel (a replay's rows
    # take the full build's, ``diag``)
    keep_diag = lam > 0.0 and rows is None
    dg = np.zeros((cap if keep_diag else 0, k))
    ovf_dg = np.zeros((threads, bw, k))
    if sink is None:
        def sink(rows, rhs_rows, band_ds=work.factor, rhs_ds=work.y):
            band_ds[base:base + len(rows)] = rows
            rhs_ds[base:base + len(rows)] = rhs_rows
    xyz_ds = work.xyz_current if xyz is None else xyz
    # each point's system kept for the update of this state (work.kept, :func:`_kept_systems`;
    # a full build replaces them, a replay's rows leave them)
    keep = None
    if xyz is None and rows is None and state is None:
        work.kept = None
        keep = _kept_systems(p, blk, opts)
    keep_pt, keep_nbar = keep if keep is not None else (
        np.empty((0, normals.KEPT_POINT)), np.empty((0, k, 3)))
    priors = _PriorCursor(p, opts.chunk_points, blk)
    base = 0
    ranges = p.chunks("points", opts.chunk_points)
    if rows is not None:   # a replay's rows: from the points that reach them
        if ng:
            raise ValueError("band rows built again: not with a border")
        lo_row, hi_row = rows
        base = max(0, lo_row - bw + 1)
        j0, j1 = marks.index(base), marks.index(hi_row)
        ranges = [(a, min(j1, a + opts.chunk_points)) for a in range(j0, j1, opts.chunk_points)]
        priors.seek(base)
        row_sink = sink

        def sink(rows_, rhs_rows):   # (the rows before lo_row are incomplete)
            skip = max(0, lo_row - base)
            stop = max(skip, min(len(rows_), hi_row - base))
            if stop > skip:
                row_sink(rows_[skip:stop], rhs_rows[skip:stop])
    elif marks is not None:
        marks.rows = marks.rows[marks.rows <= n]
    if lam > 0.0:
        if rows is None:
            diag = paging.zeros((n, k))
        plain_sink = sink

        def sink(rows, rhs_rows):  # the rows are complete: add the damping on the diagonal
            d = np.clip(diag[base:base + len(rows)], 1e-6, 1e32)
            idx = np.arange(k)
            rows[:, idx, idx] += lam * d
            plain_sink(rows, rhs_rows)
    _init_rows(band, rhs, base, base, base + cap, blk, priors)

    def advance(new_base):
        nonlocal base
        if new_base <= base:
            raise SapgoError(f"{p.path}: the points are not sorted by their first station; "
                             f"the records were changed after ordering: run 'sapgo order'")
        shift = min(new_base, n) - base
        if ng:
            work.border[base:base + shift] = bord[:shift]
            bord[:cap - shift] = bord[shift:]
            bord[cap - shift:] = 0.0
        if keep_diag:   # (the rows are complete: every point that sees them is in)
            diag[base:base + shift] = dg[:shift]
            dg[:cap - shift] = dg[shift:]
            dg[cap - shift:] = 0.0
        sink(band[:shift], rhs[:shift])
        band[:cap - shift] = band[shift:]
        rhs[:cap - shift] = rhs[shift:]
        band[cap - shift:] = 0.0
        rhs[cap - shift:] = 0.0
        _init_rows(band, rhs, new_base, base + cap, new_base + cap, blk, priors)
        base = new_base

    eo_k = with_rotations(blk.eo)   # (each station's rotation once, not at every ray)
    with _progress(opts.progress and rows is None, p.n_points, "build") as bar:
        for a, b in ranges:
            c = PointChunk(p, a, b, xyz_ds[a:b], blk.camera, blk.cam_sigma, blk.frame, blk.rejected,
                           blk.rejected_points)
            reweight(c, work, opts)
            if marks is not None and rows is None:
                marks.see(a, c.smin, c.active)
            j = 0
            while j < len(c.xyz):
                _threads.adapt()
                j, status, bad = build_points_parallel(
                    j, c.xyz, c.kind, c.ctrl, c.csig, c.rot, c.pt_start, c.nobs, c.smin, c.smax,
                    c.active, c.obs_station, c.obs_xy, c.obs_sigma, c.obs_active, eo_k,
                    blk.camera, blk.cams, blk.ctrl_mask, band, rhs, base,
                    c.max_rays, ovf_band, ovf_rhs, normals.PARALLEL_MIN_POINTS, blk.cal,
                    bord, ovf_bord, cnn_t, ccg_t, cdiag_t, lam, blk.behind_ok, blk.fixed,
                    dg, ovf_dg, keep_pt[a:b], keep_nbar[c.o0:c.o1],
                )
                if status != OK:
                    raise _point_error(p, c, bad, status, blk)
                if j < len(c.xyz):
                    advance(int(c.smin[j]))
            del c  # release the chunk before the next one is read
            bar.update(b - a)
            if rows is None:
                _fault("build", iteration)
    end = n if rows is None else hi_row
    while base < end:
        advance(min(end, base + cap))
    if keep is not None:
        work.kept = (keep_pt, keep_nbar, lam)
    border = None
    if ng:
        cnn, ccg, cdiag = cnn_t.sum(axis=0), ccg_t.sum(axis=0), cdiag_t.sum(axis=0)
        if lam > 0.0:
            cnn[np.arange(ng), np.arange(ng)] += lam * np.clip(cdiag, 1e-6, 1e32)
        border = (cnn, ccg, cdiag)
    return (diag if lam > 0.0 else None), border


#: Bytes of the points' systems the build keeps for the update at most (and a sixteenth of
#: the memory budget): :func:`_kept_systems`.
KEPT_SYSTEMS_BYTES = 64 << 20


def _kept_systems(p, blk: _Block, opts: Options):
    """Arrays for the build to keep every point's system in (chunk points x
    :data:`sapgo.normals.KEPT_POINT` and observations x npar x 3, :func:`sapgo.normals.
    build_points`), so that the update back-solves from them instead of linearising each
    point again (the same numbers; about two thirds of the update's time); None where they
    would take more than :data:`KEPT_SYSTEMS_BYTES` or a sixteenth of ``--memory``, for
    robust estimation (whose weights the update works out again) and for self-calibration
    (whose update needs each ray's partials: the step moves the border)."""
    if opts.robust is not None or blk.n_border:
        return None
    size = 8 * (p.n_points * normals.KEPT_POINT + p.n_observations * blk.npar * 3)
    budget = DEFAULT_CORE_BUDGET if opts.memory is None else parse_memory(opts.memory)
    if size > min(KEPT_SYSTEMS_BYTES, budget // 16):
        return None
    return (np.empty((p.n_points, normals.KEPT_POINT)),
            np.empty((p.n_observations, blk.npar, 3)))


def _moved_cameras(blk: _Block, delta, dtheta=None):
    """The camera rows after a step: moved by the intrinsics' corrections of 9-parameter
    stations (``delta[:, 6:9]``: f, k1 f^2, k2 f^4 of each photo's own camera), or by the
    self-calibration step ``dtheta`` (cameras x N_CALIBRATION,
    :func:`sapgo.geometry.camera_partials`' scaled parameters)."""
    cams = blk.cams.copy()
    if dtheta is not None:
        cams[:, CALIBRATION_COLUMNS] += dtheta / cams[:, :1] ** CALIBRATION_POWERS[None, :]
    if blk.npar == 9:
        act = np.flatnonzero(blk.station_active)
        c = blk.camera[act]
        d = delta[act, 6:9]
        f0 = blk.cams[c, 0]
        f1 = f0 + d[:, 0]
        cams[c, 0] = f1
        cams[c, 3] = (blk.cams[c, 3] * f0 ** 2 + d[:, 1]) / f1 ** 2
        cams[c, 4] = (blk.cams[c, 4] * f0 ** 4 + d[:, 2]) / f1 ** 4
    return np.ascontiguousarray(cams)


def next_orientations(eo, delta, out=None):
    """The stations after a step ``delta`` (n x 6 or more): the attitudes turned by the
    rotation vectors ``delta[:, :3]`` (:func:`sapgo.geometry.turn`), the centres moved.
    ``out``: the array to fill (a chunk of rows at a time), else a new one."""
    if out is not None:
        for a, b in paging.rows(len(eo)):
            out[a:b] = next_orientations(eo[a:b], delta[a:b])
        return out
    out = np.array(eo, dtype=np.float64, copy=True)
    out[:, :3] = turned(eo[:, :3], delta[:, :3])
    out[:, 3:6] += delta[:, 3:6]
    return out


def _abs_max(a, cols):
    """``max |a[:, cols]|`` (0 for no rows), a chunk of rows at a time."""
    m = 0.0
    for i, j in paging.rows(len(a)):
        m = max(m, float(np.abs(a[i:j, cols]).max()))
    return m


def _uncovered(cover):
    """The ranges ``(a, b)`` where ``cover`` is 0."""
    z = np.concatenate([[0], (cover == 0).astype(np.int8), [0]])
    d = np.flatnonzero(np.diff(z))
    return [(int(a), int(b)) for a, b in zip(d[::2], d[1::2])]


def update_range(p: Project, work, blk: _Block, delta, opts: Options, a0, b0, stats,
                 stats_robust, cams_new, lam=0.0, dtheta=None, iteration=0, bar=None,
                 eo_next=None):
    """:func:`update` of points ``a0 .. b0``: their new coordinates and residuals into the
    work buffers, ``stats`` (:func:`sapgo.normals.update_points`) and ``stats_robust``
    accumulated. ``eo_next``: :func:`next_orientations` of the step (computed when None)."""
    xyz_in, xyz_out_ds, res_ds = work.xyz_current, work.xyz_next, work.res_next
    if eo_next is None:
        eo_next = next_orientations(blk.eo, delta)
    eo_k, eo_next = with_rotations(blk.eo), with_rotations(eo_next)
    # the build's systems of this state and damping (:func:`_kept_systems`)
    kept = getattr(work, "kept", None)
    if kept is None or kept[2] != lam or dtheta is not None:
        kept = (np.empty((0, normals.KEPT_POINT)), np.empty((0, blk.npar, 3)))
    for a in range(a0, b0, opts.chunk_points):
        b = min(b0, a + opts.chunk_points)
        c = PointChunk(p, a, b, xyz_in[a:b], blk.camera, blk.cam_sigma, blk.frame, blk.rejected,
                       blk.rejected_points)
        w = reweight(c, work, opts)
        if w is not None:
            stats_robust[0] += int((w < 1.0).sum())
            stats_robust[1] += int((w < 0.1).sum())
        xyz_out = np.empty_like(c.xyz)
        res_out = np.zeros((c.o1 - c.o0, 2))
        _threads.adapt()
        update_points_parallel(
            _threads.parts(),
            c.xyz, c.kind, c.ctrl, c.csig, c.rot, c.pt_start, c.nobs, c.active, c.obs_station,
            c.obs_xy, c.obs_sigma, c.obs_active, eo_k, delta, blk.camera,
            blk.cams, blk.ctrl_mask, c.max_rays, xyz_out, res_out,
            stats, lam, blk.behind_ok, cams_new, dtheta, blk.fixed, eo_next,
            kept[0][a:b], kept[1][c.o0:c.o1],
        )
        if stats[7]:
            raise _point_error(p, c, int(stats[7]) - 1, int(stats[8]), blk)
        xyz_out_ds[a:b] = xyz_out
        res_ds[c.o0:c.o1] = res_out
        del c, xyz_out, res_out  # release the chunk before the next one is read
        if bar is not None:
            bar.update(b - a)
        _fault("update", iteration)


def update(p: Project, work, blk: _Block, delta, opts: Options, iteration=0, lam=0.0,
           dtheta=None):
    """Stream the points: back-solve their corrections, new coordinates and residuals.

    Reads the current coordinates from ``work.xyz_current`` and writes the new ones and the
    residuals to the other buffer (``work.xyz_next``, ``work.res_next``).
    """
    stats = np.zeros(11)
    stats_robust = np.zeros(2, np.int64)  # observations downweighted, and to below a tenth
    cams_new = _moved_cameras(blk, delta, dtheta)
    eo_next = next_orientations(blk.eo, delta, out=paging.empty(blk.eo.shape))
    client = getattr(opts, "client", None)
    with _progress(opts.progress, p.n_points, "update") as bar:
        mine = [(0, p.n_points)]
        if client is not None and blk.tree is not None:
            # Dask: each worker its part's points, the client the rest (the top nodes')
            from .solve.distributed import distributed_update

            theirs = distributed_update(p, work, blk, delta, opts, iteration, lam, dtheta,
                                        cams_new, stats, stats_robust, bar)
            cover = np.zeros(p.n_points + 1, np.int64)
            for a, b in theirs:
                cover[a] += 1
                cover[b] -= 1
            mine = _uncovered(np.cumsum(cover)[:-1])
        t0 = time.perf_counter()
        for a, b in mine:
            update_range(p, work, blk, delta, opts, a, b, stats, stats_robust, cams_new, lam,
                         dtheta, iteration, bar, eo_next)
        if client is not None:
            from .solve.distributed import client_seconds

            client_seconds("update", time.perf_counter() - t0)
    vpv_prior = 0.0
    for a, b in p.chunks("station_priors", opts.chunk_points) if blk.use_priors else ():
        pr = p.read("station_priors", a, b)
        pr = pr[blk.station_active[pr["station"]]]
        v = eo_next[pr["station"]] - pr["value"]
        v[:, :3] = _wrap(v[:, :3])
        vpv_prior += float(np.einsum("ni,nij,nj->", v, pr["weight"], v))
    paging.assign(blk.eo, eo_next)
    del eo_next
    blk.cams = cams_new
    return {
        "vpv": stats[0] + stats[1] + vpv_prior,
        "vpv_image": stats[0],
        "rms_x_um": 1000 * math.sqrt(stats[2] / max(stats[4], 1)),
        "rms_y_um": 1000 * math.sqrt(stats[3] / max(stats[4], 1)),
        "image_rms_um": 1000 * math.sqrt((stats[2] + stats[3]) / max(2 * stats[4], 1)),
        "max_point_corr": stats[5],
        "points_cNc": stats[9],
        "points_dDd": stats[10],
        "downweighted": int(stats_robust[0]),
        "downweighted_below_tenth": int(stats_robust[1]),
    }


def _pivot_error(exc: PivotError, blk: _Block, p: Project):
    s = exc.row
    sid = int(blk.station_ids[s])
    param = (EO_NAMES + INTRINSICS)[exc.parameter]
    active = np.flatnonzero(blk.station_active)
    last = active[-1] if len(active) else 0
    # a datum defect spreads over the whole block and shows at the end of the elimination;
    # in a block of a few band widths every station is "at the end", so say both
    if blk.tree is None:
        near_end = s > last - blk.band_width
        small = len(active) <= 3 * blk.band_width
    else:  # on the tree the end of the elimination is a root's separator
        t = blk.tree
        node = int(np.searchsorted(t.hi, s, side="right"))
        near_end = node < t.n_nodes and t.parent[node] < 0
        small = t.n_nodes <= 3
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


def _accepted(log):
    """The log entries of accepted steps (Levenberg-Marquardt logs rejected ones too)."""
    return [r for r in log if r.get("step", "accepted") == "accepted"]


#: At most this many points (and this fraction of the points) are set aside in a run
#: before an undetermined point stops it as an error.
MAX_ASIDE = 1000
MAX_ASIDE_FRACTION = 0.01


def _active_rays(p, blk, j):
    """Point record ``j``'s active observations (not rejected)."""
    pt = p.read("points", j, j + 1)[0]
    o0, o1 = int(pt["obs_start"]), int(pt["obs_start"] + pt["n_obs"])
    obs = p.read("observations", o0, o1)
    live = np.flatnonzero(obs["status"] == STATUS_ACTIVE)
    live = live[~np.isin(o0 + live, blk.rejected)]
    return pt, obs[live]


def _note_aside(run, blk):
    run["aside"] = [list(v) for v in blk.aside.values()]
    run["aside_log"] = blk.aside_log
    run["rejected_points"] = blk.rejected_points.tolist()


def _set_aside(p, work, blk, opts, run, exc, iteration):
    """A pass point undetermined at the current values (``exc``, its rays (nearly)
    parallel): left out of the adjustment from now on, until :func:`_bring_back` finds
    its rays fit again; too many such points stop the run with ``exc``."""
    j = exc.record
    if j in blk.aside or len(blk.aside) >= max(1, min(MAX_ASIDE, int(MAX_ASIDE_FRACTION
                                                                     * blk.n_points) + 1)):
        raise exc
    pt, rays = _active_rays(p, blk, j)
    blk.aside[j] = [j, len(rays), int(pt["id"]), iteration]
    blk.aside_log.append({"point": int(pt["id"]), "set_aside": iteration, "back": None})
    blk.rejected_points = np.sort(np.append(blk.rejected_points, j)).astype(np.int64)
    blk.n_points -= 1
    blk.n_rays -= len(rays)
    _note_aside(run, blk)
    run["cost"] = _cost(p, work, blk, opts)   # the cost function lost the point
    print(f"sapgo: warning: point id {int(pt['id'])} set aside in iteration {iteration}: its "
          f"rays are (nearly) parallel at the current values; it comes back when they fit",
          file=sys.stderr)


def _bring_back(p, work, blk, opts, run, iteration):
    """The points set aside whose rays now meet at a clear angle: intersected from the
    current orientations and taken into the adjustment again."""
    from .geometry import intersect

    back = []
    for j, (_, n_rays, pid, _) in list(blk.aside.items()):
        pt, rays = _active_rays(p, blk, j)
        if len(rays) < 2:
            continue
        st = rays["station"].astype(np.int64)
        xyz, ok = intersect(blk.eo[st], np.column_stack([rays["x"], rays["y"]]),
                            blk.cams[blk.camera[st]])
        if not ok or not np.isfinite(xyz).all():
            continue
        work.xyz_current[j:j + 1] = xyz[None, :]
        del blk.aside[j]
        blk.rejected_points = blk.rejected_points[blk.rejected_points != j]
        blk.n_points += 1
        blk.n_rays += len(rays)
        for e in reversed(blk.aside_log):
            if e["point"] == pid and e["back"] is None:
                e["back"] = iteration
                break
        back.append(pid)
    if back:
        _note_aside(run, blk)
        run["cost"] = _cost(p, work, blk, opts)   # the cost function has them again
        print(f"sapgo: warning: {len(back)} point(s) set aside before are back in iteration "
              f"{iteration}: {', '.join(str(i) for i in back[:20])}", file=sys.stderr)


def _cost(p: Project, work, blk: _Block, opts: Options):
    """Half the weighted sum of squared residuals at the current state (images, control,
    priors): the cost Ceres reports."""
    vpv = 0.0
    xyz_ds = work.xyz_current
    eo_k = with_rotations(blk.eo)
    for a, b in p.chunks("points", opts.chunk_points):
        c = PointChunk(p, a, b, xyz_ds[a:b], blk.camera, blk.cam_sigma, blk.frame, blk.rejected,
                       blk.rejected_points)
        reweight(c, work, opts)
        _threads.adapt()
        img, ctl = point_costs_parallel(
            _threads.parts(), c.xyz, c.kind, c.ctrl, c.csig, c.rot, c.pt_start, c.nobs,
            c.active, c.obs_station, c.obs_xy, c.obs_sigma, c.obs_active, eo_k,
            blk.camera, blk.cams, blk.ctrl_mask)
        if not math.isfinite(img):
            raise _nonfinite_error(p, c, blk)
        vpv += img + ctl
    for a, b in p.chunks("station_priors", opts.chunk_points) if blk.use_priors else ():
        pr = p.read("station_priors", a, b)
        pr = pr[blk.station_active[pr["station"]]]
        v = blk.eo[pr["station"]] - pr["value"]
        v[:, :3] = _wrap(v[:, :3])
        vpv += float(np.einsum("ni,nij,nj->", v, pr["weight"], v))
    return 0.5 * vpv


def _nonfinite_error(p: Project, c, blk: _Block):
    """The error of a non-finite cost at the starting values in chunk ``c``: its first
    point behind (or in the plane of) a photo, named as the build names it, else its first
    observation whose residual is not finite."""
    rays = np.flatnonzero(c.obs_active)
    behind = rays[_behind_depths(c, blk, rays) >= 0]
    if len(behind):
        j = int(np.searchsorted(c.pt_start, behind[0], side="right") - 1)
        return _point_error(p, c, j, BEHIND_CAMERA, blk)
    return SapgoError(f"{p.path}: {_nonfinite_ray(p, c, blk)}")


def _diverged(p: Project, work, blk: _Block, opts: Options, it):
    """The message of a step that made the cost non-finite: its first such observation."""
    for a, b in p.chunks("points", opts.chunk_points):
        c = PointChunk(p, a, b, work.xyz_next[a:b], blk.camera, blk.cam_sigma, blk.frame,
                       blk.rejected, blk.rejected_points)
        res = np.asarray(work.res_next[c.o0:c.o1])
        if not np.isfinite(res[c.obs_active]).all():
            return (f"{p.path}: the adjustment diverged: "
                    + _nonfinite_ray(p, c, blk, res, f"after iteration {it}"))
    return f"{p.path}: the adjustment diverged at iteration {it} (sigma0 is not finite)"


def _nonfinite_ray(p: Project, c, blk: _Block, res=None, when="at the starting values"):
    """The one-line message of the first active observation of chunk ``c`` whose residual
    (``res``, else projected here) is not finite: its record, point and photo."""
    n = c.stop - c.start
    if res is None:
        res = np.zeros((c.o1 - c.o0, 2))
        point_of = np.repeat(np.arange(n), c.nobs)
        project_observations(c.obs_station, point_of, blk.eo, c.xyz, blk.camera, blk.cams,
                             res)
        res -= c.obs_xy
    point_of = np.repeat(np.arange(c.start, c.stop), c.nobs)
    bad = np.flatnonzero(~np.isfinite(res).all(axis=1) & c.obs_active
                         & (c.active[point_of - c.start] == 0))
    if not len(bad):
        return f"the cost is not finite {when} (no single observation at fault)"
    i = int(bad[0])
    pid = int(p.read_field("points", "id", int(point_of[i]), int(point_of[i]) + 1)[0])
    sid = int(blk.station_ids[c.obs_station[i]])
    return (f"observations record {c.o0 + i} (point id {pid}, photo id {sid}): its "
            f"residual is not finite {when}: check the point's and the photo's values (units, "
            f"columns) and the camera")


def _factor_solve(p: Project, work: Work, blk: _Block, opts: Options, it=0, mu=0.0,
                  back=True):
    """Build the reduced normals (damped by ``mu``), factor and solve them with the block's
    solver: the band (the factorisation runs inside the build: every segment of band rows is
    factored as soon as the build has completed it, so the band rows never go to disk) or
    the partition tree (node by node, :func:`sapgo.solve.tree.tree_step`).

    Returns a dict: ``delta``, ``diag`` (the stations' undamped diagonal with ``mu > 0``),
    ``border`` (self-calibration: ``(cnn, ccg, cdiag)``), ``theta``, ``border_cov``, ``xb``
    (``x'b`` of the step: ``y'y`` plus the border's share) and ``seconds`` (in the solver:
    booked as "solve", the rest as "build"). ``back=False``: the factorisation alone (for
    the precision pass; ``delta`` None on the band).

    Band without a factor file (``blk.replay``): the forward pass keeps the solver's state
    at each replay segment's start and where each segment's points begin
    (:class:`PointMarks`); the back substitution, and later passes reading the factor
    (``work.band_factor()``), refactor each segment from its band rows built again from the
    state of the forward pass (orientations, cameras, rejections, point coordinates: the
    factor the file would hold, whatever changed since; with robust weights, whose
    residuals move, the replay is dropped after the step and the precision pass factors
    anew)."""
    if blk.tree is not None:
        from .solve.tree import tree_step

        try:
            return tree_step(p, work, blk, opts, blk.tree, mu, it)
        except PivotError as exc:
            raise _pivot_error(exc, blk, p) from None
        except BorderPivotError as exc:
            raise _border_pivot_error(exc, blk, p) from None
    n = len(blk.station_ids)
    work.drop_replay()
    replay = work.dir if blk.replay else None
    solver = BandSolver(n, blk.band_width, None if replay else work.factor,
                        None if replay else work.y, opts.chunk_rows, opts.pivot_tolerance,
                        block=blk.npar, replay=replay)
    marks = None
    if replay is not None:
        rep = solver.replay
        need = [rep.rows_needed(j) for j in range(rep.J)]
        marks = PointMarks([max(0, lo - blk.band_width + 1) for lo, _ in need]
                           + [hi for _, hi in need], p.n_points)
    try:
        diag, border = build(p, work, blk, opts, iteration=it, sink=solver.feed, lam=mu,
                             marks=marks)
        if replay is not None:
            # the state these rows are built from (an update changes eo in place: _iterate
            # hands over its copy from before, state["eo"])
            state = {"eo": None, "cams": blk.cams, "rejected": blk.rejected,
                     "rejected_points": blk.rejected_points, "xyz": work.xyz_current}

            def rebuild(lo, hi, feed):   # (blk is read meanwhile by the precision pass)
                build(p, work, blk, opts, xyz=state["xyz"], iteration=it, sink=feed, lam=mu,
                      marks=marks, rows=(lo, hi), diag=diag,
                      state={k: v for k, v in state.items() if k != "xyz"})

            solver.replay.rebuild = rebuild
            solver.replay.state = state
            work.replay = solver.replay
        delta = solver.finish(None if border is None else
                              (work.border, border[0], border[1]), back=back)
    except PivotError as exc:
        raise _pivot_error(exc, blk, p) from None
    except BorderPivotError as exc:
        raise _border_pivot_error(exc, blk, p) from None
    if replay is not None:
        xb = solver.yy
    elif border is None:
        xb = 0.0
        for a, b in paging.rows(n):
            y = work.y[a:b]
            xb += float((y * y).sum())
    else:
        xb = solver.y_norm2 + solver.border_decrease
    return {"delta": delta, "diag": diag, "border": border,
            "theta": solver.theta if border is not None else None,
            "border_cov": solver.border_cov if border is not None else None,
            "xb": xb, "seconds": solver.seconds}


def _iterate(p: Project, work: Work, blk: _Block, opts: Options, timings, log, run,
             limit=None, reject=True):
    """Iterations (Gauss-Newton, or Levenberg-Marquardt steps) until converged or ``limit``
    entries in ``log`` (default ``max_iterations``); appends to ``log``; returns converged.

    ``run["cost"]`` is the cost of the current state. Levenberg-Marquardt (``run["method"]``
    "lm") damps the normals by ``mu`` times their diagonal; a step that does not lower the
    cost is rejected (logged, parameters restored) and ``mu`` raised, an accepted one lowers
    ``mu``. With ``Options.method`` "auto", Gauss-Newton turns into Levenberg-Marquardt at
    the first step that raises the cost. ``reject=False``: every step is taken (the
    cost function changes between steps, as in robust reweighting)."""
    limit = limit or opts.max_iterations
    while len(log) < limit:
        it = len(log) + 1
        lm = run.get("method") == "lm"
        mu = float(run.get("mu", opts.lm_initial_mu)) if lm else 0.0
        t0 = time.perf_counter()
        _bring_back(p, work, blk, opts, run, it)
        while True:
            try:
                step = _factor_solve(p, work, blk, opts, it, mu)
                break
            except UndeterminedPointError as exc:   # set it aside; the step once more
                _set_aside(p, work, blk, opts, run, exc, it)
        _fault("solve", it)
        delta, diag, border = step["delta"], step["diag"], step["border"]
        delta[~blk.station_active] = 0.0
        theta, border_cov = step["theta"], step["border_cov"]
        dtheta = _border_step(blk, theta) if border is not None else None
        t2 = time.perf_counter()
        t1 = t0 + (t2 - t0 - step["seconds"])
        eo_before, cams_before = paging.copy(blk.eo), blk.cams
        st = update(p, work, blk, delta, opts, iteration=it, lam=mu, dtheta=dtheta)
        t3 = time.perf_counter()
        timings["build"] += t1 - t0
        timings["solve"] += t2 - t1
        timings["update"] += t3 - t2
        d_ang = _abs_max(delta, slice(0, 3))
        d_pos = _abs_max(delta, slice(3, 6))
        step_s = delta
        xb_step = step["xb"]
        del delta, step
        cost = 0.5 * st["vpv"]
        prev_cost = run.get("cost")
        rho = None
        if lm and prev_cost is not None:
            # predicted decrease 1/2 (dx' b + mu dx' D dx), with dx' b = |y|^2 (the stations'
            # reduced system: y = U'^-1 d) + sum over points of c' Ndd^-1 c
            # (+ t' S^-1 t, the border's share, with self-calibration)
            xb = xb_step
            dsd = sum(float((np.clip(diag[a:b], 1e-6, 1e32) * step_s[a:b] ** 2).sum())
                      for a, b in paging.rows(len(diag))) if diag is not None else 0.0
            if border is not None:
                dsd += float((np.clip(border[2], 1e-6, 1e32) * theta ** 2).sum())
            pred = 0.5 * (xb + st["points_cNc"] + mu * (dsd + st["points_dDd"]))
            rho = (prev_cost - cost) / pred if pred > 0 else 0.0
        sigma0 = math.sqrt(max(st["vpv"], 0.0) / blk.redundancy)
        ok = np.isfinite(cost)
        if reject and prev_cost is not None and np.isfinite(prev_cost):
            if lm:  # a step that lowers the cost by at least 1e-3 of the predicted decrease
                # (Ceres' min_relative_decrease), or equal to rounding (converged)
                ok = ok and (cost <= prev_cost * (1.0 + 1e-12) if rho is None else
                             (rho > 1e-3 or abs(cost - prev_cost) <= 1e-12 * prev_cost))
            elif opts.method == "auto":
                ok = ok and cost <= prev_cost * (1.0 + 1e-9)
        if not ok and not lm and not (reject and opts.method != "gauss-newton"):
            raise SapgoError(_diverged(p, work, blk, opts, it))
        accepted = _accepted(log)
        prev = accepted[-1]["sigma0"] if accepted else None
        log.append({
            "iteration": it,
            "sigma0": sigma0,
            "cost": cost,
            "image_rms_um": st["image_rms_um"],
            "image_rms_x_um": st["rms_x_um"],
            "image_rms_y_um": st["rms_y_um"],
            "max_station_position_corr_m": d_pos,
            "max_station_angle_corr_arcsec": d_ang / ARCSEC,
            "max_point_corr_m": st["max_point_corr"],
            "robust_downweighted": st["downweighted"],
            "build_s": t1 - t0,
            "solve_s": t2 - t1,
            "update_s": t3 - t2,
        })
        blk.refactor = lm or not ok
        if work.replay is not None:   # the factor stays that of the state before the step
            if ok and work.robust_r is None:
                work.replay.state["eo"] = eo_before
            else:
                work.drop_replay()
        if lm or not ok:
            log[-1]["mu"] = mu
            log[-1]["rho"] = rho
            log[-1]["step"] = "accepted" if ok else "rejected"
        if not ok:  # restore the state; damp more (Levenberg-Marquardt from now on)
            paging.assign(blk.eo, eo_before)
            blk.cams = cams_before
            if lm:
                nu = float(run.get("nu", 2.0))
                run["mu"], run["nu"] = mu * nu, nu * 2.0
            else:
                run["method"], run["mu"], run["nu"] = "lm", opts.lm_initial_mu, 2.0
            if run["mu"] > 1e16:  # no step lowers the cost: a minimum
                return True
            continue
        if lm:  # Ceres: radius / max(1/3, 1 - (2 rho - 1)^3)
            factor = 1.0 / 3.0 if rho is None else max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            run["mu"], run["nu"] = max(mu * factor, 1e-16), 2.0
        run["cost"] = cost
        if border_cov is not None:  # the cameras' cofactors (scaled border parameters)
            run["border_cov"] = border_cov.tolist()
            blk.border_cov = border_cov
        tol_pos, tol_ang = run.get("robust_tol") or (opts.tol_position, opts.tol_angle)
        converged = bool(
            d_pos < tol_pos and st["max_point_corr"] < tol_pos and d_ang < tol_ang
            and (prev is None or abs(sigma0 - prev) <= opts.tol_sigma0 * prev)
            and (dtheta is None or _border_settled(blk, dtheta)))
        if lm and prev_cost is not None and prev_cost - cost <= opts.tol_cost * prev_cost:
            converged = True
        work.save(work.state + 1, blk.eo, dict(run, log=log, timings=timings,
                                                converged=converged), cams=blk.cams)
        if converged:
            return True
    return False


# -- the run -----------------------------------------------------------------------------

def _needs_order(p: Project, opts: Options):
    """An unordered project, one ordered for the other solver than the one asked for, or
    one whose stored tree no longer matches its records is ordered (again) first."""
    if not p.ordered:
        return True
    if opts.solver != "auto" and opts.solver != p.solver:
        return True
    try:
        p.tree()
    except ProjectFormatError:
        return True
    return False


def _hold_records(p, blk, opts):
    """On the tree, read the point and observation records into core once for the run's
    passes (which visit them node by node, many small reads), when they take at most a
    quarter of the solver's memory budget (:func:`sapgo.solve.tree.tree_budget`). Returns
    the bytes held, which the solver's budget then lacks (its fronts are tiled sooner).
    The band streams them in large chunks and holds nothing proportional to them."""
    from .solve.tree import tree_budget

    if blk.tree is None:
        return 0
    return p.hold(max_bytes=tree_budget(opts, 0, len(blk.station_ids)) // 4)


#: Bytes of kept point chunks (:func:`_keep_chunks`) at most on the band.
KEEP_CHUNKS_BYTES = 64 << 20


def _keep_chunks(p, blk, opts):
    """Keep the kernels' arrays of the points' chunks for the run
    (:meth:`sapgo.project.Project.keep_point_chunks`), so that every pass after the first
    converts nothing: room for two sets of chunks (the build's and the update's, cut apart
    on the tree), when it is at most an eighth of the tree's memory budget (on the band
    :data:`KEEP_CHUNKS_BYTES`). Returns the bytes reserved."""
    from .normals import CHUNK_OBS_BYTES, CHUNK_POINT_BYTES
    from .solve.tree import tree_budget

    need = 2 * (p.n_points * CHUNK_POINT_BYTES + p.n_observations * CHUNK_OBS_BYTES)
    room = (tree_budget(opts, blk.held, len(blk.station_ids)) // 8 if blk.tree is not None
            else KEEP_CHUNKS_BYTES)
    return p.keep_point_chunks(need, room)


def _tree_figures(blk, opts):
    """The tree's figures for the summary, with the tiling the run's budget gave
    (:func:`sapgo.solve.tree.tiling`)."""
    from .solve.tree import tiling

    if blk.tree is None:
        return None
    return {**blk.tree.figures(blk.npar),
            **tiling(blk.tree, blk.npar, opts, blk.held, len(blk.station_ids))}


#: Beyond this fraction of the machine's memory in band factor rows, ``--factor-storage
#: auto`` replays the factor instead of writing it. While the file stays in the page cache
#: from one iteration to the next it is the faster (24 GB here: at 1 000 000 photos, 12 GB
#: of factor, 22 s an iteration against the replay's 30, benchmarks/README.md); beyond the
#: memory every iteration writes and reads it at the disk's speed.
FACTOR_FILE_FRACTION = 1 / 2


def factor_file_limit():
    """Bytes of band factor rows up to which ``--factor-storage auto`` keeps the file."""
    try:
        mem = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        mem = 24 << 30
    return int(FACTOR_FILE_FRACTION * mem)


#: The band's factor rows are kept in core by ``--factor-storage auto`` up to this fraction
#: of the memory budget (``--memory``, default :data:`DEFAULT_CORE_BUDGET`).
FACTOR_CORE_FRACTION = 1 / 4

#: The memory budget :func:`factor_core_limit` divides when ``--memory`` is not given.
DEFAULT_CORE_BUDGET = 1 << 30


def factor_core_limit(opts: Options):
    """Bytes of band factor rows up to which ``--factor-storage auto`` keeps them in core."""
    total = DEFAULT_CORE_BUDGET if opts.memory is None else parse_memory(opts.memory)
    return int(FACTOR_CORE_FRACTION * total)


def _choose_storage(blk: _Block, opts: Options, work_dir):
    """Where the band's factor rows go, by ``opts.factor_storage``: sets ``blk.replay``
    and ``blk.core``. "auto" keeps them in core up to :func:`factor_core_limit`, replays a
    factor beyond :func:`factor_file_limit` or beyond nine tenths of the free space where
    the work files go, and writes the file between the two (a run ``in_memory`` too: a
    factor beyond the memory budget is a file, or replayed, in the work directory made for
    it)."""
    blk.replay = blk.core = False
    if blk.tree is not None:
        return
    if opts.factor_storage == "replay":
        if blk.n_border:
            raise ParameterError("--factor-storage replay: self-calibration's border needs "
                                 "the factor file (or the factor in core); use "
                                 "--factor-storage core, file or auto")
        blk.replay = True
        return
    factor = 8 * len(blk.station_ids) * blk.npar * (blk.npar * blk.band_width + 1)
    if opts.factor_storage == "core":
        blk.core = True
        return
    if opts.factor_storage != "auto":
        return
    if factor <= factor_core_limit(opts):
        blk.core = True
        return
    if blk.n_border:
        return
    from .project import free_space

    blk.replay = factor > factor_file_limit() or factor > 0.9 * free_space(work_dir)[1]


def _work_band(blk: _Block):
    """The band width of the work files' band rows: none for the tree (its factor has a
    file of its own)."""
    return blk.band_width if blk.tree is None else 0


@writes_project("adjust", "path")
def adjust(path, options: Options | None = None) -> Summary:
    """Adjust the project at ``path``; see the module docstring. Returns a :class:`Summary`."""
    opts = dataclasses.replace(options or Options()).check()   # (a copy: filled in below)
    path = Path(path)
    t_start = time.perf_counter()
    timings = {"order": 0.0, "build": 0.0, "solve": 0.0, "update": 0.0, "commit": 0.0}
    wpath = work_path(path)
    checkpoint = Work.load_checkpoint(wpath) if opts.resume else None
    in_memory = _in_memory(path, opts, checkpoint)
    order_info = mem = None   # (mem: in memory, the project or its ordered copy, HDF5)
    # an unordered project is ordered into a copy beside it (NAME.h5.ordered), which the
    # commit makes the project: a run that fails leaves the project as it was
    ordered = ordered_path(path)
    src = path
    p = Project(path, "r", tiling=False)   # (check_values checks the tiling, below)
    try:
        if in_memory:   # (its records read once, for the checks and the ordering)
            p.hold(None, max_bytes=IN_MEMORY_BYTES)
        n_rejected = check_values(p)["rejected"]
        check_datum(p, fixed=bool(opts.fix), datum=opts.datum)
        if opts.fix:   # (refused before the implicit ordering rewrites the project)
            import types

            _set_fixed(types.SimpleNamespace(
                station_ids=p.read_field("stations", "id"),
                station_active=p.read_field("stations", "status") == STATUS_ACTIVE), p, opts)
        needs_order = _needs_order(p, opts) or bool(opts.reset_rejections and n_rejected)
        source_uuid = p.attr("uuid", "")
        if needs_order:
            src = ordered
            if in_memory or checkpoint is None or not _ordered_copy_of(
                    ordered, source_uuid, opts.reset_rejections):
                checkpoint = None  # (a run on another ordered copy cannot be resumed)
                if in_memory:
                    ordered.unlink(missing_ok=True)   # (an interrupted run's)
                t0 = time.perf_counter()
                order_info = order_project(path, opts.ordering, memory=opts.memory,
                                           solver=opts.solver, out=ordered,
                                           reset_rejections=opts.reset_rejections,
                                           checked=True, page_stations=opts.page_stations,
                                           in_memory=in_memory, project=p)
                mem = order_info.file
                timings["order"] = time.perf_counter() - t0
        p.close()
        if not needs_order:
            ordered.unlink(missing_ok=True)   # (an interrupted run's, of an older project)
            if in_memory:
                mem = memory_image(path)
        earlier = (0, n_rejected) if opts.reset_rejections else (n_rejected, 0)
        summary = _adjust_ordered(path, src, wpath, opts, checkpoint, order_info, timings,
                                  t_start, earlier, mem=mem, in_memory=in_memory)
    except SapgoError:
        ordered.unlink(missing_ok=True)
        raise
    except (OSError, RuntimeError) as exc:   # a full disk: no temporaries are left
        if not is_disk_full(exc):
            raise
        ordered.unlink(missing_ok=True)
        shutil.rmtree(wpath, ignore_errors=True)
        raise disk_full_error(path, exc) from None
    finally:
        p.close()
        if mem is not None:
            mem.close()
    ordered.unlink(missing_ok=True)
    return summary


def _in_memory(path, opts: Options, checkpoint):
    """Is the run on ``path`` held in memory, without work files (``opts.work_files``)?"""
    if opts.work_files == "always":
        return False
    if opts.work_files == "never":
        clash = ("Dask (a client)" if getattr(opts, "client", None) is not None else
                 f"--factor-storage {opts.factor_storage}"
                 if opts.factor_storage in ("file", "replay") else
                 "--keep-scratch" if opts.keep_scratch else
                 "--resume" if opts.resume else None)
        if clash:
            raise ParameterError(f"--work-files never: {clash} needs the work files; use "
                                 f"--work-files auto or always")
        return True
    budget = DEFAULT_CORE_BUDGET if opts.memory is None else parse_memory(opts.memory)
    try:
        size = os.path.getsize(path)
    except OSError:   # (no such file: opening it says so)
        return False
    return (getattr(opts, "client", None) is None and not opts.keep_scratch
            and opts.factor_storage in ("auto", "core") and checkpoint is None
            and size <= min(IN_MEMORY_BYTES, budget // 16))



def ordered_path(path):
    """Where ``sapgo adjust`` orders an unordered project (``NAME.h5.ordered`` beside it):
    the run reads it, the commit makes it the project, an interrupted run resumes on it."""
    path = Path(path)
    return path.with_name(path.name + ".ordered")


def _ordered_copy_of(ordered, source_uuid, reset):
    """Is ``ordered`` a whole ordered copy of the project of uuid ``source_uuid``, made with
    the earlier rejections reset or kept as ``reset`` says?"""
    if not ordered.exists():
        return False
    try:
        with Project(ordered, "r") as q:
            return (bool(source_uuid) and q.attr("ordered_from", "") == source_uuid
                    and bool(q.attr("rejections_reset", False)) == bool(reset))
    except (OSError, SapgoError):
        return False


def _adjust_ordered(path, src, wpath, opts, checkpoint, order_info, timings, t_start,
                    earlier=(0, 0), mem=None, in_memory=False):
    """:func:`adjust` on the ordered project ``src`` (``path`` itself, or its ordered copy);
    the results are committed to ``path``. ``earlier``: the observations an earlier run
    rejected, (kept out, brought back), for the report. ``in_memory``: no work files;
    ``mem``: ``src`` as an HDF5 file in memory (the commit writes it out, adjusted), or
    None (the file itself)."""
    looks = dict(_threads.STATS)   # (what sapgo.threads finds during the run: the report)
    log = []
    resumed_from = None
    held = getattr(order_info, "records", None) if mem is not None else None
    with Project(src, "r", shown=path, memory=mem, held=held) as p, paging.paged(
            wpath.parent, _paged(p, opts), 0 if opts.page_stations == 0 else
            paging.MIN_PAGED_BYTES):
        if in_memory:   # (every pass slices the records in memory)
            p.hold(None, max_bytes=IN_MEMORY_BYTES)
        blk = _load_block(p)
        _set_calibration(blk, p, opts)
        _set_fixed(blk, p, opts)
        _set_datum(blk, p, opts)
        if blk.free:   # 7 station parameters held (the inner constraints come at the commit)
            from .freenet import minimal_constraints

            minimal_constraints(blk)
        if blk.tree is not None:
            from .solve.tree import check_tree_memory

            check_tree_memory(blk.tree, blk.npar, opts, path, len(blk.station_ids))
        blk.held = _hold_records(p, blk, opts)
        blk.held += _keep_chunks(p, blk, opts)
        if opts.max_iterations is None:
            opts.max_iterations = (LM_MAX_ITERATIONS if blk.free
                                   or opts.method == "levenberg-marquardt"
                                   else GN_MAX_ITERATIONS)
        if blk.n_stations == 0:
            raise DatumDefectError(f"{path}: no station can be adjusted (every photo has fewer "
                                   f"than 3 determinable points)")
        if blk.redundancy <= 0:
            raise SapgoError(f"{path}: the block has no redundancy ({blk.redundancy}): more "
                             f"unknowns than observations")
        ident = _identity(p, blk.band_width)
        ident["solver"] = blk.solver
        if blk.border:  # a run with another self-calibration is another run
            ident["calibration"] = _border_names(blk, p)
        if checkpoint is not None and checkpoint.get("identity") != ident:
            checkpoint = None  # the project changed since: start again
        if not opts.resume and (wpath / "checkpoint.json").exists():
            sys.stderr.write(f"sapgo: warning: an interrupted run of {path} was found and is "
                             f"discarded (use --resume to continue it)\n")
        if opts.resume and checkpoint is None:
            sys.stderr.write(f"sapgo: warning: no interrupted run of {path} to resume; "
                             f"starting from the beginning\n")
        converged = False
        work = None
        _choose_storage(blk, opts, wpath)
        if checkpoint is not None:
            try:
                work = Work(wpath, p, _work_band(blk), create=False, block=blk.npar,
                            n_border=blk.n_border, replay=blk.replay,
                            core=blk.core)
            except (OSError, ValueError) as exc:  # work files missing or cut short
                sys.stderr.write(f"sapgo: warning: the interrupted run of {path} cannot be "
                                 f"resumed ({exc}); starting from the beginning\n")
                checkpoint = None
        if work is None:
            work = Work(wpath, p, _work_band(blk), create=True, block=blk.npar,
                        n_border=blk.n_border, replay=blk.replay, core=blk.core,
                        files=not in_memory)
        if blk.tree is not None:   # (the factor's pages mapped meanwhile, when in core)
            from .solve.tree import start_arena

            start_arena(work, blk, opts)
        try:
            if checkpoint is None:
                run = {"run": uuid.uuid4().hex, "identity": ident}
                work.initialise(p, opts.chunk_points)
                if blk.free or opts.method == "levenberg-marquardt":
                    run["method"], run["mu"], run["nu"] = "lm", opts.lm_initial_mu, 2.0
                run["cost"] = run["initial_cost"] = _cost(p, work, blk, opts)
                work.save(0, blk.eo, dict(run, log=[], timings=timings, converged=False))
            else:
                run = {"run": checkpoint["run"], "identity": ident}
                blk.eo = paging.load_npy(checkpoint["eo_path"])
                if checkpoint.get("cams") is not None:
                    blk.cams = np.ascontiguousarray(checkpoint["cams"], dtype=np.float64)
                blk.rejections = list(checkpoint.get("rejections", []))
                blk.rejected = np.sort(np.array([r["observation"] for r in blk.rejections],
                                                np.int64))
                blk.planted = checkpoint.get("planted")
                blk.n_rays -= len(blk.rejected)
                kept = np.array(checkpoint.get("rejected_points", []), np.int64)
                blk.n_points -= len(np.setdiff1d(kept, blk.rejected_points))
                blk.rejected_points = np.union1d(blk.rejected_points, kept).astype(np.int64)
                blk.aside = {int(a[0]): [int(x) for x in a]
                             for a in checkpoint.get("aside", [])}
                blk.aside_log = list(checkpoint.get("aside_log", []))
                blk.n_rays -= sum(a[1] for a in blk.aside.values())
                run["rejections"] = blk.rejections
                run["planted"] = blk.planted
                blk.reinstated = list(checkpoint.get("reinstated", []))
                for key in ("robust_tol", "method", "mu", "nu", "cost", "initial_cost",
                            "border_cov", "reinstated", "snooping_confirmed",
                            "snooping_rounds",
                            "snooping_group"):   # (the last: a version's before 2026-11-27)
                    if checkpoint.get(key) is not None:
                        run[key] = checkpoint[key]
                run["rejected_points"] = blk.rejected_points.tolist()
                if blk.aside or blk.aside_log:
                    _note_aside(run, blk)
                if run.get("border_cov") is not None:
                    blk.border_cov = np.array(run["border_cov"])
                blk.refactor = True
                log = checkpoint["log"]
                for k, v in checkpoint["timings"].items():
                    timings[k] = v + (timings[k] if k == "order" else 0.0)
                work.state = int(checkpoint["iteration"])
                converged = bool(checkpoint["converged"])
                resumed_from = work.state
            if opts.robust is not None and work.robust_r is None:
                # least squares first; then reweighted iterations with its redundancy
                if not converged:
                    _iterate(p, work, blk, opts, timings, log, run)
                t0 = time.perf_counter()
                sig, _, quality = _precision(p, work, blk, opts,
                                                 _accepted(log)[-1]["sigma0"], run=run,
                                                 iteration=len(log))
                # reweighting converges linearly: it stops when the corrections are below
                # a fraction of the least-squares standard deviations
                act = sig[blk.station_active]
                run["robust_tol"] = [
                    max(opts.tol_position, opts.robust_tolerance * float(act[:, 3:].mean())),
                    max(opts.tol_angle, opts.robust_tolerance * float(act[:, :3].mean()))]
                work.start_robust(quality, opts.chunk_points)
                timings["precision"] = timings.get("precision", 0.0) + time.perf_counter() - t0
                converged = _iterate(p, work, blk, opts, timings, log, run,
                                     limit=len(log) + opts.max_iterations, reject=False)
            elif not converged:
                # (resumed inside snooping: the adjustment after its last round goes on)
                rounds = opts.snooping and run.get("snooping_rounds", 0) > 0
                converged = _iterate(p, work, blk, opts, timings, log, run,
                                     limit=len(log) + opts.max_iterations if rounds else None)
            if opts.snooping and log:
                converged = _snoop(p, work, blk, opts, timings, log, run, converged)
            if not log:
                raise SapgoError(f"{path}: no iteration was run (max_iterations "
                                 f"{opts.max_iterations} and a checkpoint at iteration "
                                 f"{work.state})")
            summary = _commit(path, p, work, blk, log, converged, opts, order_info, run,
                              looks, timings, t_start, resumed_from, earlier, mem)
        except SapgoError:
            # the data cannot be adjusted: nothing worth resuming
            work.close()
            if not opts.keep_scratch:
                shutil.rmtree(wpath, ignore_errors=True)
            raise
        finally:
            work.close()
    if not opts.keep_scratch:
        shutil.rmtree(wpath, ignore_errors=True)
    timings["total"] = time.perf_counter() - t_start
    return summary


def _paged(p: Project, opts: Options):
    """Are the run's per-station vectors memory-mapped (:mod:`sapgo.paging`)?"""
    limit = paging.PAGE_STATIONS if opts.page_stations is None else opts.page_stations
    return p.n_stations > limit or limit == 0


def _precision(p: Project, work, blk: _Block, opts: Options, sigma0, correlations=None,
               mode="full", run=None, iteration=0):
    """:func:`sapgo.quality.quality_sweep` from the undamped factor of the current state
    (factored once more first when the last one was damped or rejected). ``mode``: "full"
    (stations, points and the observations' quality: what snooping and robust estimation
    need) or "stations" (the stations' blocks alone, ``--precision stations``). ``run``
    and ``iteration``: a pass point undetermined without the damping is set aside, as in
    an iteration (:func:`_undamped_factor`)."""
    if blk.refactor or (blk.replay and work.replay is None):
        _undamped_factor(p, work, blk, opts, run, iteration)
    if opts.precision != mode:
        opts = dataclasses.replace(opts, precision=mode)
    return quality_sweep(p, work, blk, opts, sigma0, correlations)


def _undamped_factor(p: Project, work, blk: _Block, opts: Options, run=None, iteration=0):
    """Build and factor the normals of the current state without damping (the work files'
    factor, ``y`` and border), for the precision sweep after Levenberg-Marquardt steps.
    A pass point whose rays are (nearly) parallel, which the damping held, is set aside
    (:func:`_set_aside`, reported with the iteration ``iteration``; with ``run`` given):
    it has no precision to give, and the others are not held back by it. The run's cost
    stays the adjustment's (the point's residuals in it, as in sigma0)."""
    while True:
        try:
            step = _factor_solve(p, work, blk, opts, back=False)
            break
        except UndeterminedPointError as exc:
            if run is None:
                raise
            cost = run.get("cost")
            _set_aside(p, work, blk, opts, run, exc, iteration)
            run["cost"] = cost   # (the adjustment's cost: the precision pass moves nothing)
    if step["border"] is not None:
        blk.border_cov = step["border_cov"]
    blk.refactor = False


def _snoop(p, work, blk, opts, timings, log, run, converged):
    """Baarda's data snooping: while the largest test statistic of an active image
    observation, ``t = sqrt(v' Q_vv^-1 v) / sigma0`` (its two coordinates together), exceeds
    the critical value of ``opts.snooping_alpha`` (chi-square with 2 degrees of freedom),
    reject (flagged, never deleted) and iterate again. Returns converged.

    One at a time (the default) rejects the largest each round. In batches
    (``opts.snooping_batch``) a round rejects, from the largest down, every significant
    observation whose neighbourhood -- the photos that see its point -- shares no photo
    with one taken already in the round: a blunder moves the tests of its own point's rays
    and of the photos that see it most. When no test is significant any more, the batch
    rejections are confirmed (:func:`_confirm`) from the same precision pass: each
    rejection's residual predicted from the adjustment without it gives the test it would
    have brought back alone; one no longer significant (it had taken the blame of a
    blunder beside it) is brought back, and the rounds go on."""
    group = run.pop("snooping_group", None)
    if group:   # (a checkpoint of a version that confirmed by groups brought back: in)
        blk.reinstated.extend(int(i) for i in group)
        run["reinstated"] = blk.reinstated
        run["snooping_confirmed"] = sorted(set(run.get("snooping_confirmed", [])) |
                                           {int(i) for i in group})
    while True:
        converged, quality = _snoop_rounds(p, work, blk, opts, timings, log, run, converged)
        if not opts.snooping_batch or not _confirm(p, work, blk, opts, timings, log, run,
                                                   quality):
            return converged
        converged = _iterate(p, work, blk, opts, timings, log, run,
                             limit=len(log) + opts.max_iterations)


def _snooping_critical(opts):
    from .report import chi2_isf

    return float(np.sqrt(chi2_isf(opts.snooping_alpha, 2)))


def _neighbourhood(p, i):
    """Observation ``i``'s point, the point's observation range and records, and the photos
    that see the point (the tests a rejection of ``i`` moves most)."""
    j = int(p.read("observations", i, i + 1)[0]["point"])
    pt = p.read("points", j, j + 1)[0]
    o0, o1 = int(pt["obs_start"]), int(pt["obs_start"] + pt["n_obs"])
    ob = p.read("observations", o0, o1)
    return j, o0, o1, ob, set(ob["station"].tolist())


def _confirm(p, work, blk, opts, timings, log, run, quality):
    """Confirm batch snooping's rejections by test not yet confirmed
    (``run["snooping_confirmed"]``), the block adjusted without them and no test
    significant: a rejection whose point keeps two rays without it is tested as if brought
    back alone. The precision pass predicts its residual from the others (``v``, cofactor
    ``Q_v = sigma^2 I + [A B] Q [A B]'``; ``quality``'s column t holds
    ``sqrt(v' Q_v^-1 v) / sigma0``, :func:`sapgo.normals.point_sigmas`); brought back, the
    adjustment's ``v' P v`` would grow by ``T^2 = v' Q_v^-1 v`` and its redundancy by 2, and
    its own test would be ``T / sigma0'`` with ``sigma0'^2 = (v' P v + T^2) / (r + 2)``
    (the linear model's identity). Significant, it stays out; not, it is brought back
    (``blk.reinstated``). Either way it is confirmed (never brought back twice); a point
    gone with it keeps it out. ``quality``: the pass of the current state (None: one is
    made). Returns whether any was brought back."""
    confirmed = set(run.get("snooping_confirmed", []))
    rejected = set(blk.rejected.tolist())
    gone = set(blk.rejected_points.tolist())
    todo = []
    for r in blk.rejections:
        i = int(r["observation"])
        if r["by"] != "test" or i in confirmed:
            continue
        confirmed.add(i)
        j, o0, o1, ob, _ = _neighbourhood(p, i)
        live = [k for k in range(o0, o1) if ob["status"][k - o0] == STATUS_ACTIVE
                and k not in rejected]
        if len(live) >= 2 and j not in gone:   # (else its point went with it: it stays out)
            todo.append(i)
    run["snooping_confirmed"] = sorted(confirmed)
    if not todo:
        return False
    sigma0 = _accepted(log)[-1]["sigma0"]
    if quality is None:
        t0 = time.perf_counter()
        quality = _snooping_pass(p, work, blk, opts, sigma0, run, log)
        timings["precision"] = timings.get("precision", 0.0) + time.perf_counter() - t0
    crit = _snooping_critical(opts)
    vpv, red = sigma0 ** 2 * blk.redundancy, blk.redundancy
    back = []
    for i in todo:
        t2 = (float(quality[i][5]) * sigma0) ** 2
        if t2 <= crit ** 2 * (vpv + t2) / (red + 2):
            back.append(i)
    if not back:
        return False
    blk.rejected = blk.rejected[~np.isin(blk.rejected, back)]
    blk.n_rays += len(back)
    blk.rejections = [r for r in blk.rejections if int(r["observation"]) not in back]
    blk.reinstated.extend(back)
    run["reinstated"] = blk.reinstated
    run["rejections"] = blk.rejections
    run["snooping_rounds"] = run.get("snooping_rounds", 0) + 1
    run["cost"] = _cost(p, work, blk, opts)
    return True


def _snooping_pass(p, work, blk, opts, sigma0, run, log):
    """A precision pass of data snooping (:func:`_precision`, "full"): its result, with the
    stations' correlations, kept for the commit (:func:`_kept_pass`) should nothing change
    before it. Returns the observations' quality."""
    correlations = HighCorrelations(opts.correlation_threshold)
    out = _precision(p, work, blk, opts, sigma0, correlations, run=run, iteration=len(log))
    blk.last_pass = (_pass_key(blk, log), out, correlations)
    return out[2]


def _pass_key(blk, log):
    """What a precision pass's result depends on, beyond the project: the iterations so far
    and the observations and points out of the adjustment."""
    return (len(log), blk.rejected.tobytes(), blk.rejected_points.tobytes(),
            tuple(sorted(blk.aside)), blk.free)


def _kept_pass(blk, log, mode):
    """The last snooping pass's ``((station_sigma, point_sigma, quality), correlations)``
    when nothing changed since it and the commit asks for the full precision, else None."""
    kept = getattr(blk, "last_pass", None)
    if kept is None or mode != "full" or blk.free or blk.refactor or \
            kept[0] != _pass_key(blk, log):
        return None
    return kept[1], kept[2]


def _snoop_rounds(p, work, blk, opts, timings, log, run, converged):
    """The rounds of :func:`_snoop` until no test is significant. Returns converged and the
    observations' quality of the last precision pass if it is of the final state (None:
    the rejections reached ``max_rejections`` after it)."""
    crit = _snooping_critical(opts)
    confirmed = set(run.get("snooping_confirmed", []))
    quality = None
    while len(blk.rejected) < opts.max_rejections:
        t0 = time.perf_counter()
        quality = _snooping_pass(p, work, blk, opts, _accepted(log)[-1]["sigma0"], run, log)
        _note_planted(p, blk, quality, run)
        cand_t, cand_i = [], []
        for a, b in p.chunks("observations", opts.chunk_points):
            q = quality[a:b]
            act = p.read_field("observations", "status", a, b) == STATUS_ACTIVE
            if len(blk.rejected):
                act &= ~np.isin(np.arange(a, b), blk.rejected)
            w = np.where(act, q[:, 5], 0.0)
            if not opts.snooping_batch:   # (the largest of the chunk is enough)
                i = int(np.argmax(w)) if len(w) else 0
                if len(w) and w[i] > crit:
                    cand_t.append(float(w[i]))
                    cand_i.append(a + i)
                continue
            big = np.flatnonzero(w > crit)
            cand_t.extend(w[big].tolist())
            cand_i.extend((a + big).tolist())
        timings["precision"] = timings.get("precision", 0.0) + time.perf_counter() - t0
        if not cand_i:
            break
        order = np.argsort(-np.array(cand_t), kind="stable")
        if not opts.snooping_batch:
            order = order[:1]
        taken_photos = set()
        batch = []
        room = opts.max_rejections - len(blk.rejected)
        for k in order.tolist():
            if len(batch) >= room:
                break
            worst, best = cand_i[k], cand_t[k]
            if worst in confirmed and len(batch):   # (brought back once: alone, as the largest)
                continue
            j, o0, o1, ob, photos = _neighbourhood(p, worst)
            if photos & taken_photos:
                continue   # (its tests move with a rejection of this round: next round)
            taken_photos |= photos
            if worst in blk.reinstated:   # (brought back once, significant again now)
                blk.reinstated.remove(worst)
                run["reinstated"] = blk.reinstated
            batch.append((worst, best, j, o0, o1, ob))
        for worst, best, j, o0, o1, ob in batch:
            # a point left with fewer than two rays cannot be determined: all its rays go
            # (the blunder cannot be told from the other ray of a two-ray point)
            live = np.arange(o0, o1)[ob["status"] == STATUS_ACTIVE]
            live = live[~np.isin(live, blk.rejected)]
            blk.rejections.append({"observation": worst, "w": best, "by": "test"})
            drop = [worst]
            if len(live) - 1 < 2:
                drop = live.tolist()
                blk.rejections.extend({"observation": int(i), "w": best, "by": "point"}
                                      for i in live.tolist() if i != worst)
                blk.rejected_points = np.sort(np.append(blk.rejected_points, j))
                blk.n_points -= 1
            blk.rejected = np.sort(np.concatenate([blk.rejected, np.array(drop, np.int64)]))
            blk.n_rays -= len(drop)
        run["rejections"] = blk.rejections
        run["rejected_points"] = blk.rejected_points.tolist()
        run["snooping_rounds"] = run.get("snooping_rounds", 0) + 1
        run["cost"] = _cost(p, work, blk, opts)  # the cost function lost observations
        converged = _iterate(p, work, blk, opts, timings, log, run,
                             limit=len(log) + opts.max_iterations)
        quality = None
    return converged, quality


def _station_index(blk, ids):
    """``{photo id: station}`` of the photo ids ``ids`` (those of the block), found a chunk
    of stations at a time."""
    want = np.unique(np.asarray(ids, np.int64))
    out = {}
    for a, b in paging.rows(len(blk.station_ids)):
        sid = np.asarray(blk.station_ids[a:b], np.int64)
        for k in np.flatnonzero(np.isin(sid, want)):
            out[int(sid[k])] = a + int(k)
    return out


def _note_planted(p, blk, quality, run):
    """Once, with every observation still in: for each planted blunder (``/truth/blunders``)
    its observation and non-centrality ``lambda = d' R d / sigma^2`` (``d`` the blunder,
    ``R`` the observation's 2 x 2 block of the redundancy matrix): the blunder is detectable
    with 80 % power when lambda reaches :func:`~sapgo.report.noncentrality`."""
    if blk.planted is not None or not (p.has_truth and "truth/blunders" in p.file):
        return
    bl = p.read("truth/blunders")
    st_index = _station_index(blk, bl["station_id"])
    want = {int(pid) for pid in bl["point_id"]}
    where = {}
    for a, b in p.chunks("points"):
        ids = p.read_field("points", "id", a, b)
        for k in np.flatnonzero(np.isin(ids, list(want))):
            where[int(ids[k])] = a + int(k)
    out = []
    for rec in bl:
        j = where.get(int(rec["point_id"]))
        s = st_index.get(int(rec["station_id"]))
        if j is None or s is None:
            continue
        pt = p.read("points", j, j + 1)[0]
        o0 = int(pt["obs_start"])
        obs = p.read("observations", o0, o0 + int(pt["n_obs"]))
        hit = np.flatnonzero(obs["station"] == s)
        if not len(hit):
            continue
        i = o0 + int(hit[0])
        q = quality[i]
        sig = obs["sigma"][hit[0]] if obs["sigma"][hit[0]] > 0 else blk.cam_sigma[
            blk.camera[s]]
        d = np.array([rec["dx"], rec["dy"]])
        r = np.array([[q[0], q[2]], [q[2], q[1]]])
        out.append({"observation": i, "photo_id": int(rec["station_id"]),
                    "point_id": int(rec["point_id"]), "lambda": float(d @ r @ d / sig ** 2)})
    blk.planted = {"blunders": out}
    run["planted"] = blk.planted


def _observation_ids(p, blk, obs):
    """``{"observation", "photo_id", "point_id"}`` of the observations ``obs``."""
    out = []
    for i in obs:
        o = p.read("observations", int(i), int(i) + 1)[0]
        out.append({"observation": int(i), "photo_id": int(blk.station_ids[o["station"]]),
                    "point_id": int(p.read("points", int(o["point"]), int(o["point"]) + 1)[0]
                                    ["id"])})
    return out


def _rejected_list(p, blk):
    """The observations data snooping rejected, in the order of rejection: photo and point
    ids, the test statistic and whether the test chose it or it went with its point."""
    ids = _observation_ids(p, blk, [r["observation"] for r in blk.rejections])
    return [dict(o, w=float(r["w"]), by=r["by"]) for o, r in zip(ids, blk.rejections)]


def _blunder_check(p, blk, alpha):
    """Planted blunders (``/truth/blunders``) against the rejected observations.

    ``false_rejections`` counts observations the test rejected that hold no planted blunder;
    the other rays of a point left undeterminable go with it (``rejected_with_point``).
    ``detectable``: planted blunders whose non-centrality reaches Baarda's bound for
    ``alpha`` and 80 % power, i.e. the ones the block's geometry lets the test find."""
    if not (p.has_truth and "truth/blunders" in p.file) or not len(p.read("truth/blunders")):
        return None
    bl = p.read("truth/blunders")
    planted = set(zip(bl["station_id"].tolist(), bl["point_id"].tolist()))
    rej = _rejected_list(p, blk)
    got = {(r["photo_id"], r["point_id"]) for r in rej}
    tested = {(r["photo_id"], r["point_id"]) for r in rej if r["by"] == "test"}
    out = {"planted": len(planted), "found": len(planted & got),
           "false_rejections": len(tested - planted),
           "rejected_with_point": len(got - tested - planted)}
    if blk.planted is not None:
        lam0 = noncentrality(alpha)
        det = {(b["photo_id"], b["point_id"]) for b in blk.planted["blunders"]
               if b["lambda"] >= lam0}
        out.update(alpha=alpha, power=0.8, lambda0=lam0, detectable=len(det),
                   found_detectable=len(det & got))
    return out


class _FieldRows:
    """A project's field read by row ranges (``f[a:b]``), a chunk at a time."""

    def __init__(self, p, table, name):
        self.p, self.table, self.name = p, table, name

    def __len__(self):
        return int(self.p.file[self.table].shape[0])

    def __getitem__(self, key):
        a, b, _ = key.indices(len(self))
        return self.p.read_field(self.table, self.name, a, b)


class ReportSums:
    """The report's statistics over a project's points and their image observations,
    accumulated by point ranges (:meth:`add`) and merged (:meth:`merge`: a Dask worker's
    part): the observations' reliability (with the precision), the check points and the
    control's residuals, the errors against the truth, the strips' comparison and the
    excluded points."""

    def __init__(self, p, blk, opts, reliability=None):
        self.reliability = reliability
        self.checks = check_point_statistics()
        self.truth = truth_statistics() if p.has_truth else None
        self.strips = StripComparison(_FieldRows(p, "stations", "strip"), blk.station_active,
                                      p.frame())
        self.excluded = []   # (point index, id), the first LISTED_IDS
        self.n_excluded = 0

    def add(self, p, blk, opts, xyz, quality, a, b):
        """Points ``a .. b`` (adjusted coordinates ``xyz``, by point index) and their
        observations (``quality``, by observation index, or None without the precision)."""
        for a0 in range(a, b, opts.chunk_points):
            b0 = min(b, a0 + opts.chunk_points)
            pts = p.read("points", a0, b0)
            adj = np.asarray(xyz[a0:b0])
            chunk = PointChunk(p, a0, b0, adj, blk.camera, blk.cam_sigma, None, blk.rejected,
                               blk.rejected_points)
            if self.reliability is not None and chunk.o1 > chunk.o0:
                o0, o1 = chunk.o0, chunk.o1
                ob = p.read("observations", o0, o1)
                act = ob["status"] == STATUS_ACTIVE
                if len(blk.rejected):
                    act &= ~np.isin(np.arange(o0, o1), blk.rejected)
                sig = np.where(ob["sigma"] > 0, ob["sigma"],
                               blk.cam_sigma[blk.camera[ob["station"]]])
                self.reliability.add(np.asarray(quality[o0:o1]), sig, act)
            self.strips.add(chunk, blk.eo, blk.camera, blk.cams)
            act = pts["status"] == STATUS_ACTIVE
            out = np.flatnonzero(~act)
            self.n_excluded += len(out)
            self.excluded.extend((a0 + int(j), int(pts["id"][j]))
                                 for j in out[:LISTED_IDS - len(self.excluded)])
            used = act & (chunk.active == 0)   # (and not left out of this run)
            if not blk.ctrl_mask.any():   # the control unused (--datum priors|free): checks
                pts = pts.copy()
                pts["kind"][pts["kind"] == KIND_CONTROL] = KIND_CHECK
            self.checks.add(pts[used], adj[used],
                            control_rotations(pts["kind"][used], pts["control"][used],
                                              blk.frame))
            if self.truth is not None:
                self.truth.add_points(p.read_field("truth/points", "xyz", a0, b0)[act],
                                      adj[act])

    def travel(self):
        """What goes back from a worker: the sums, not the stations' strips."""
        self.strips.strip = None
        return self

    def merge(self, other):
        """Add ``other``'s sums (another part's points)."""
        if self.reliability is not None:
            self.reliability.merge(other.reliability)
        self.checks.merge(other.checks)
        if self.truth is not None:
            self.truth.points.merge(other.truth.points)
        self.strips.merge(other.strips)
        self.excluded = sorted(self.excluded + other.excluded)[:LISTED_IDS]
        self.n_excluded += other.n_excluded

    def excluded_ids(self):
        return [i for _, i in sorted(self.excluded)[:LISTED_IDS]]


def _commit(path, p_read: Project, work: Work, blk: _Block, log, converged, opts, order_info,
            run, looks, timings, t_start, resumed_from, earlier=(0, 0), mem=None):
    """Write the adjusted values and the report into a copy of the project, then replace it.

    The project is never opened for writing: the copy gets ``/solution`` and the history and
    is renamed over the project when complete, so a kill at any moment leaves either the old
    or the new project, both whole. ``mem``: the run's project (or ordered copy) in memory,
    which takes the results there and is written out whole in one write.
    """
    t_commit = time.perf_counter()
    accepted = _accepted(log)
    if not accepted:
        raise SapgoError(f"{path}: no step lowered the cost from its initial value "
                         f"{run.get('initial_cost')}: nothing to write")
    last = accepted[-1]
    xyz_ds, res_ds = work.xyz_current, work.res_current
    t_prec = time.perf_counter()
    correlations = HighCorrelations(opts.correlation_threshold)
    mode = opts.precision
    if blk.free:   # a free network: the solution of the inner constraints (sapgo.freenet)
        from .freenet import to_inner

        to_inner(p_read, work, blk, opts)
        correlations = None   # (those of the minimal constraints' datum mean nothing)
    # --precision none: no precision
    no_precision = mode == "none"
    if no_precision:  # no precision: zeros, and no report of it
        station_sigma = paging.zeros((len(blk.station_ids), 6))
        psig = quality = None
        correlations = reliability = None
    else:
        kept = _kept_pass(blk, log, mode) if correlations is not None else None
        systems = None   # (the points' systems of this state, when its build keeps them)
        if kept is not None:   # (snooping's last pass: of this state, nothing changed)
            (station_sigma, psig, quality), correlations = kept
        else:
            fresh = blk.refactor   # (the precision pass builds this state's normals anew)
            station_sigma, psig, quality = _precision(p_read, work, blk, opts,
                                                      last["sigma0"], correlations, mode,
                                                      run=run, iteration=len(log))
            held = getattr(work, "kept", None)
            if fresh and blk.tree is None and held is not None and held[2] == 0.0 \
                    and len(held[0]) == p_read.n_points:
                systems = held[:2]
        if mode != "full":   # (the stations' alone: no points, no observations' quality)
            psig = quality = None
        if blk.free:
            from .freenet import inner_precision

            inner_precision(p_read, work, blk, opts, last["sigma0"], station_sigma, psig,
                            systems)
        reliability = None
        if quality is not None:
            _note_planted(p_read, blk, quality, run)
            reliability = reliability_statistics(opts.snooping_alpha)
    # the report's sums over the points and their observations: each Dask part's points on
    # its worker, the rest here
    sums = ReportSums(p_read, blk, opts, reliability)
    rest = [(0, p_read.n_points)]
    if getattr(opts, "client", None) is not None and getattr(work, "_dask_plan", None):
        from .solve.distributed import distributed_report

        rest = distributed_report(opts.client, p_read, work, blk, opts, sums)
    for a, b in rest:
        sums.add(p_read, blk, opts, xyz_ds, quality, a, b)
    t_prec = time.perf_counter() - t_prec
    timings["precision"] = timings.get("precision", 0.0) + t_prec
    checks, truth, strips = sums.checks, sums.truth, sums.strips
    excluded_points, n_excluded_points = sums.excluded_ids(), sums.n_excluded
    if truth is not None:
        for a, b in p_read.chunks("truth/stations", opts.chunk_points):
            act = blk.station_active[a:b]
            truth.add_stations(p_read.read_field("truth/stations", "eo", a, b)[act],
                               blk.eo[a:b][act])
    excluded_stations = blk.station_ids[~blk.station_active]
    summary = Summary(
        rejections_kept=earlier[0], rejections_reset=earlier[1],
        datum_chosen=blk.datum is not None,
        path=str(path),
        converged=converged,
        termination=(
            (f"converged after {len(log)} iterations: corrections below "
             f"{opts.tol_position:g} m and {opts.tol_angle / ARCSEC:.2g}\""
             if run.get("method") != "lm" else
             f"converged after {len(log)} iterations ({len(accepted)} accepted "
             f"Levenberg-Marquardt steps): cost change below {opts.tol_cost:g} or "
             f"corrections below tolerance")
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
        solver=blk.solver,
        tree=_tree_figures(blk, opts),
        ordering=p_read.attr("ordering"),
        band_width_before=order_info.band_width_before if order_info else None,
        n_stations=blk.n_stations,
        n_points=blk.n_points,
        n_observations=blk.n_rays,
        n_cameras=p_read.n_cameras,
        n_control=blk.n_control,
        excluded_stations=[int(i) for i in excluded_stations[:LISTED_IDS]],
        excluded_points=excluded_points,
        n_excluded_stations=len(excluded_stations),
        n_excluded_points=n_excluded_points,
        check_points=checks.result(),
        control_points=checks.control_result(),
        truth=truth.result() if truth is not None else None,
        timings_s=timings,
        resumed_from_iteration=resumed_from,
        strip_comparison=strips.result(),
        frame=frame_info(p_read.frame()),
        precision=None if no_precision else precision_summary(
            station_sigma, psig, p_read, opts.chunk_points, blk.station_active),
        correlations=None if correlations is None else correlations.result(),
        reliability=None if reliability is None else reliability.result(),
        precision_mode=mode,
        calibration=_calibration_report(p_read, blk, run, last["sigma0"]) if blk.border
        else None,
        method=run.get("method", "gn"),
        initial_cost=run.get("initial_cost"),
        final_cost=run.get("cost"),
        datum="free" if blk.free else ("fixed" if blk.n_fixed_params else
                                       (blk.datum or "control")),
        set_aside=list(blk.aside_log),
        image_unit=str(p_read.attr("image_unit", "mm") or "mm"),
        rejected=_rejected_list(p_read, blk),
        reinstated=_observation_ids(p_read, blk, blk.reinstated),
        blunder_check=_blunder_check(p_read, blk, opts.snooping_alpha),
    )
    its = max(1, len(log))
    summary.timings_per_iteration_s = {k: timings[k] / its for k in ("build", "solve", "update")}
    summary.threads = {"threads": _threads.parts(),
                       **{k: _threads.STATS[k] - looks[k] for k in ("checks", "busy")}}
    width = N_CAMERA if blk.cams[:, AP_SET].any() else PHOTO_CAMERA_NARROW
    n_st, n_pt, n_ob = p_read.n_stations, p_read.n_points, p_read.n_observations
    solution_bytes = 8 * (n_st * (18 + 2 * width) + n_pt * 6 + n_ob * 6)
    # a run in memory: the cameras, stations and points the run holds (the image's own,
    # not read from it again)
    held = None if mem is None else {"cameras": p_read.cameras(),
                                     "eo": p_read.read_field("stations", "eo"),
                                     "xyz": p_read.read_field("points", "xyz")}
    p_read.close()

    tmp = path.with_name(path.name + ".commit.tmp")
    try:
        if mem is None:
            ensure_free(tmp, os.path.getsize(p_read.file_path) + solution_bytes,
                        f"the adjusted copy of {path.name}")
            shutil.copyfile(p_read.file_path, tmp)   # (the project, or its ordered copy)
        _fault("commit-copy")
        with Project(tmp, "r+", memory=mem) as q:
            for key in ("ordered_from", "rejections_reset"):   # (the run's copy's own)
                if key in q.file.attrs:
                    del q.file.attrs[key]
            cams = q.cameras() if held is None else held["cameras"]
            g = q.new_solution(cams)
            sol = q.new_datasets
            for a, b in paging.rows(n_st, opts.chunk_points):
                eo = (q.read_field("stations", "eo", a, b) if held is None
                      else held["eo"][a:b])
                sol["station_corr"][a:b] = blk.eo[a:b] - eo
            cams0 = camera_array(cams)
            n_cam = len(cams0)
            sol["camera_corr"][:] = blk.cams[:n_cam] - cams0
            # each photo's camera row as adjusted (its own with per-photo calibration)
            rc = blk.row_camera if len(blk.row_camera) else np.arange(n_cam)
            pcc = sol["photo_camera_corr"]   # (narrower without additional parameters)
            for a, b in paging.rows(n_st, opts.chunk_points):
                rows = blk.camera[a:b].astype(np.int64)
                pcc[a:b] = (blk.cams[rows] - cams0[rc[rows]])[:, :pcc.shape[1]]
            for a, b in paging.rows(n_pt, opts.chunk_points):
                xyz = (q.read_field("points", "xyz", a, b) if held is None
                       else held["xyz"][a:b])
                sol["point_corr"][a:b] = xyz_ds[a:b] - xyz
            for a, b in paging.rows(n_ob, opts.chunk_points):
                sol["residuals"][a:b] = res_ds[a:b]
            for a, b in paging.rows(n_st, opts.chunk_points) if not no_precision else ():
                sol["station_sigma"][a:b] = station_sigma[a:b]   # (else zeros: the fill)
            for a, b in paging.rows(n_pt, opts.chunk_points) if psig is not None else ():
                sol["point_sigma"][a:b] = psig[a:b]
            for a, b in (paging.rows(n_ob, opts.chunk_points) if quality is not None
                         else ()):
                sol["obs_quality"][a:b] = quality[a:b]
            if len(blk.rejected):  # flagged, never deleted
                obs_ds = q.file["observations"]
                for i in blk.rejected.tolist():
                    rec = obs_ds[i]
                    rec["status"] = STATUS_REJECTED
                    obs_ds[i] = rec
            g.attrs["state"] = "adjusted"
            g.attrs["iterations"] = len(log)
            g.attrs["converged"] = converged
            g.attrs["sigma0"] = last["sigma0"]
            g.attrs["run"] = run["run"]
            timings["commit"] = time.perf_counter() - t_commit - t_prec   # (precision apart)
            timings["total"] = time.perf_counter() - t_start
            g.create_dataset("report", data=summary.to_json(indent=None))
            _fault("commit-write")
            q.commit_solution()
            q.add_history({"command": "adjust", "iterations": len(log),
                           "converged": converged, "sigma0": last["sigma0"]})
            if mem is not None:
                write_image(mem, tmp)
        _fault("commit-replace")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return summary
