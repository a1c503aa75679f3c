"""Statistics of an adjusted block and the reports (text and JSON) of a run.

Check points are compared with their known ground coordinates, as in seeds/002 Table 4:
``sX, sY, sZ`` are root mean squares of (adjusted - known), ``sXY = sqrt(sX^2 + sY^2)``.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math

import numpy as np

from . import paging
from .project import CONTROL_MASK, EO_NAMES as EO, KIND_CHECK
from .stripcmp import format_strip_comparison

ARCSEC = math.pi / (180 * 3600)


class _Rms:
    """Running sums for the RMS of 3-D differences."""

    def __init__(self):
        self.n = 0
        self.ss = np.zeros(3)
        self.s = np.zeros(3)
        self.max_xy = 0.0
        self.max_z = 0.0

    def add(self, d):
        if len(d) == 0:
            return
        self.n += len(d)
        self.ss += (d * d).sum(axis=0)
        self.s += d.sum(axis=0)
        self.max_xy = max(self.max_xy, float(np.hypot(d[:, 0], d[:, 1]).max()))
        self.max_z = max(self.max_z, float(np.abs(d[:, 2]).max()))

    def merge(self, other):
        """Add ``other``'s differences."""
        self.n += other.n
        self.ss += other.ss
        self.s += other.s
        self.max_xy = max(self.max_xy, other.max_xy)
        self.max_z = max(self.max_z, other.max_z)

    def result(self):
        if self.n == 0:
            return {"n": 0, "sx": None, "sy": None, "sz": None, "sxy": None}
        sx, sy, sz = np.sqrt(self.ss / self.n)
        mx, my, mz = self.s / self.n
        return {
            "n": self.n, "sx": float(sx), "sy": float(sy), "sz": float(sz),
            "sxy": float(math.hypot(sx, sy)),
            "mean_dx": float(mx), "mean_dy": float(my), "mean_dz": float(mz),
            "max_dxy": self.max_xy, "max_dz": self.max_z,
        }


class check_point_statistics:
    """Accumulates check-point errors and control residuals (weighted components) by chunk."""

    def __init__(self):
        self.check = _Rms()
        self.ctrl_n = np.zeros(3, np.int64)
        self.ctrl_ss = np.zeros(3)

    def add(self, points, adjusted, rot=None):
        """``rot``: per point, the rotation to the axes of the control sigmas
        (``normals.control_rotations``; east, north, up in a CRS), default the frame's."""
        diff = adjusted - points["control"]
        if rot is not None:
            diff = np.einsum("nij,nj->ni", rot, diff)
        chk = points["kind"] == KIND_CHECK
        self.check.add(diff[chk])
        mask = CONTROL_MASK[points["kind"]].astype(bool) & (points["control_sigma"] > 0)
        d = np.where(mask, diff, 0.0)
        self.ctrl_n += mask.sum(axis=0)
        self.ctrl_ss += (d * d).sum(axis=0)

    def merge(self, other):
        """Add ``other``'s points."""
        self.check.merge(other.check)
        self.ctrl_n += other.ctrl_n
        self.ctrl_ss += other.ctrl_ss

    def result(self):
        return self.check.result()

    def control_result(self):
        rms = [float(math.sqrt(s / k)) if k else None for s, k in zip(self.ctrl_ss, self.ctrl_n)]
        return {"n_x": int(self.ctrl_n[0]), "n_y": int(self.ctrl_n[1]),
                "n_z": int(self.ctrl_n[2]), "rms_x": rms[0], "rms_y": rms[1], "rms_z": rms[2]}


def precision_summary(station_sigma, point_sigma=None, project=None, chunk=65536,
                      active=None):
    """Mean and maximum a-posteriori standard deviation of each station parameter (angles in
    arc seconds, positions in m) over the active stations (``active``: a mask of the rows
    of ``station_sigma``; None: every row), and of each point coordinate over the active
    points that are not fixed (``point_sigma``: the points' file, read in chunks)."""
    total, top, count = np.zeros(6), np.full(6, -np.inf), 0
    for a, b in paging.rows(len(station_sigma), chunk):
        sig = np.asarray(station_sigma[a:b, :6])
        if active is not None:
            sig = sig[active[a:b]]
        if len(sig):
            total += sig.sum(axis=0)
            top = np.maximum(top, sig.max(axis=0))
            count += len(sig)
    if not count:
        return None
    names = ("omega_arcsec", "phi_arcsec", "kappa_arcsec", "X_m", "Y_m", "Z_m")
    scale = [1.0 / (math.pi / (180 * 3600))] * 3 + [1.0] * 3
    out = {"stations": {n: {"mean": float(total[k] / count * scale[k]),
                            "max": float(top[k] * scale[k])}
                        for k, n in enumerate(names)}}
    if point_sigma is not None and project is not None:
        s, m, n = np.zeros(3), np.zeros(3), np.zeros(3, np.int64)
        for a in range(0, project.n_points, chunk):
            b = min(project.n_points, a + chunk)
            ps = point_sigma[a:b]
            act = project.read_field("points", "status", a, b) == 0
            ok = act[:, None] & (ps > 0) & np.isfinite(ps)
            s += np.where(ok, ps, 0.0).sum(axis=0)
            m = np.maximum(m, np.where(ok, ps, 0.0).max(axis=0)) if len(ps) else m
            n += ok.sum(axis=0)
        out["points"] = {f"{c}_m": {"mean": float(s[k] / n[k]) if n[k] else None,
                                    "max": float(m[k]) if n[k] else None}
                         for k, c in enumerate("XYZ")}
    return out


#: Names of the correlations of a station's parameters (upper triangle of its 6 x 6 block).
STATION_PAIRS = [(i, k) for i in range(6) for k in range(i + 1, 6)]
STATION_PAIR_NAMES = [f"{EO[i]}-{EO[k]}" for i, k in STATION_PAIRS]
POINT_PAIR_NAMES = ["X-Y", "X-Z", "Y-Z"]


class HighCorrelations:
    """Correlations above ``threshold`` (absolute) between the parameters of one station or
    of one point: how many of each pair, and the ``listed`` largest with their ids."""

    def __init__(self, threshold=0.9, listed=50):
        self.threshold = threshold
        self.listed = listed
        self.counts = {"stations": dict.fromkeys(STATION_PAIR_NAMES, 0),
                       "points": dict.fromkeys(POINT_PAIR_NAMES, 0)}
        self.largest = []

    def add(self, what, ids, rho):
        """``rho``: n x pairs correlations of the stations or points ``ids`` (``what`` is
        "stations" or "points"); nan for excluded ones."""
        names = STATION_PAIR_NAMES if what == "stations" else POINT_PAIR_NAMES
        big = np.abs(np.nan_to_num(rho)) > self.threshold
        for m, name in enumerate(names):
            self.counts[what][name] += int(big[:, m].sum())
        rows, cols = np.nonzero(big)
        if len(rows) > self.listed:   # (only this chunk's largest can be listed)
            mag = np.abs(rho[rows, cols])
            keep = np.argpartition(-mag, self.listed - 1)[:self.listed]
            rows, cols = rows[keep], cols[keep]
        key = "photo_id" if what == "stations" else "point_id"
        self.largest.extend({key: int(ids[r]), "pair": names[c], "rho": float(rho[r, c])}
                            for r, c in zip(rows.tolist(), cols.tolist()))
        self.largest.sort(key=lambda e: -abs(e["rho"]))
        del self.largest[self.listed:]

    def result(self):
        return {"threshold": self.threshold,
                "counts": {w: {k: v for k, v in c.items() if v} for w, c in self.counts.items()},
                "largest": self.largest}


def station_correlations(cov):
    """The 15 correlations of each station's parameters from its 6 x 6 cofactor blocks
    (n x 6 x 6) as n x 15, in the order of ``STATION_PAIR_NAMES``; nan where a variance is 0."""
    d = np.sqrt(np.einsum("nii->ni", cov))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.stack([cov[:, i, k] / (d[:, i] * d[:, k]) for i, k in STATION_PAIRS], axis=1)


def chi2_isf(alpha, dof=2):
    """The critical value of a chi-square test of ``dof`` degrees of freedom at significance
    ``alpha``: ``-2 ln alpha`` for 2 (exact, without importing scipy.stats), scipy's
    otherwise."""
    if dof == 2:
        return -2.0 * math.log(alpha)
    from scipy.stats import chi2

    return float(chi2.isf(alpha, dof))


def ncx2_sf(x, dof, lam):
    """The survival function of the non-central chi-square distribution at ``x``: the
    Poisson(``lam / 2``) mixture of central chi-squares of ``dof + 2j`` degrees of freedom,
    in closed form for even ``dof`` (Poisson weights in logarithms; the sum runs 40 standard
    deviations past the Poisson mean)."""
    if dof % 2:
        from scipy.stats import ncx2

        return float(ncx2.sf(x, dof, lam))
    h, mu = 0.5 * x, 0.5 * lam
    # central chi-square sf of 2m degrees of freedom: exp(-h) sum_{i<m} h^i / i!
    term_c = math.exp(-h)              # h^i / i! exp(-h), i = 0
    central = 0.0
    for i in range(dof // 2):
        central += term_c
        term_c *= h / (i + 1)
    log_mu = math.log(mu) if mu > 0 else -math.inf
    total = 0.0
    for j in range(int(mu + 40.0 * math.sqrt(mu) + 50)):
        if j:
            central += term_c          # sf of dof + 2j degrees of freedom
            term_c *= h / (dof // 2 + j)
        total += math.exp(-mu + (j * log_mu if j else 0.0) - math.lgamma(j + 1)) * central
    return min(1.0, total)


@functools.lru_cache(maxsize=64)
def noncentrality(alpha, power=0.8, dof=2):
    """Baarda's lower bound of the non-centrality parameter: the lambda at which a test of
    ``dof`` degrees of freedom at significance ``alpha`` rejects with probability ``power``
    (the power grows with lambda: the Illinois variant of regula falsi in a bracket, a
    dozen evaluations of :func:`ncx2_sf` where bisection took fifty; kept per process)."""
    crit = chi2_isf(alpha, dof)

    def excess(lam):
        return ncx2_sf(crit, dof, lam) - power

    lo, f_lo = 0.0, alpha - power   # (the central distribution: the test's own alpha)
    hi = 2.0 * crit + 10.0
    f_hi = excess(hi)
    while f_hi <= 0.0 and hi < 1e8:   # (power 0.8 comes near (sqrt(crit) + 1)^2)
        lo, f_lo, hi = hi, f_hi, 2.0 * hi
        f_hi = excess(hi)
    side, mid = 0, lo
    for _ in range(200):
        last = mid
        mid = (lo * f_hi - hi * f_lo) / (f_hi - f_lo)
        if not lo < mid < hi:
            mid = 0.5 * (lo + hi)
        f_mid = excess(mid)
        if f_mid == 0.0 or abs(mid - last) <= 1e-14 * mid or hi - lo <= 1e-14 * hi:
            break
        if f_mid < 0.0:
            lo, f_lo = mid, f_mid
            if side < 0:
                f_hi *= 0.5
            side = -1
        else:
            hi, f_hi = mid, f_mid
            if side > 0:
                f_lo *= 0.5
            side = 1
    return mid


def weakest_redundancy(r_x, r_y, r_xy):
    """The smaller eigenvalue of each observation's 2 x 2 block of the redundancy matrix
    ``[[r_x, r_xy], [r_xy, r_y]]``: the share of a blunder in the worst direction that
    shows in the residuals (0: a blunder that way cannot be detected)."""
    h = 0.5 * (r_x + r_y)
    return np.maximum(h - np.sqrt(0.25 * (r_x - r_y) ** 2 + r_xy ** 2), 0.0)


def minimal_detectable_blunder(sigma, r_min, lam0):
    """Internal reliability: the smallest blunder (same unit as ``sigma``) that the 2-D test
    detects with the power behind ``lam0`` in the worst direction, ``sigma sqrt(lam0 /
    r_min)``; inf where ``r_min`` is 0."""
    with np.errstate(divide="ignore"):
        return np.where(r_min > 1e-9, sigma * np.sqrt(lam0 / np.maximum(r_min, 1e-300)),
                        np.inf)


class reliability_statistics:
    """Redundancy numbers and minimal detectable blunders of the active image observations,
    accumulated by chunk."""

    def __init__(self, alpha, power=0.8):
        self.alpha, self.power = alpha, power
        self.lam0 = noncentrality(alpha, power)
        self.n = 0
        self.sum_r = 0.0
        self.uncontrolled = 0
        self.mdb = []

    def add(self, quality, sigma_mm, active):
        q = quality[active]
        if not len(q):
            return
        r_min = weakest_redundancy(q[:, 0], q[:, 1], q[:, 2])
        mdb = 1000.0 * minimal_detectable_blunder(sigma_mm[active], r_min, self.lam0)
        self.n += len(q)
        self.sum_r += float(q[:, 0].sum() + q[:, 1].sum())
        self.uncontrolled += int((r_min < 0.01).sum())
        fin = mdb[np.isfinite(mdb) & (r_min >= 0.01)]
        # a bounded sample for the quantiles: every k-th value once there are many
        step = max(1, self.n // 200000)
        self.mdb.append(fin[::step].astype(np.float32))

    def merge(self, other):
        """Add ``other``'s observations (its sample of the blunders joins this one's)."""
        self.n += other.n
        self.sum_r += other.sum_r
        self.uncontrolled += other.uncontrolled
        self.mdb.extend(other.mdb)

    def result(self):
        if not self.n:
            return None
        m = np.concatenate(self.mdb) if self.mdb else np.zeros(0)

        def q(v):
            return float(np.quantile(m, v)) if len(m) else None

        return {"alpha": self.alpha, "power": self.power, "lambda0": self.lam0,
                "mean_redundancy_number": self.sum_r / (2 * self.n),
                "observations": self.n,
                "uncontrolled": self.uncontrolled,
                "mdb_um": {"median": q(0.5), "p90": q(0.9),
                           "max": float(m.max()) if len(m) else None}}


class truth_statistics:
    """Errors against the generator's true values (points and stations)."""

    def __init__(self):
        self.points = _Rms()
        self.st_n = 0
        self.st_pos = 0.0
        self.st_ang = 0.0

    def add_points(self, true_xyz, adjusted):
        self.points.add(adjusted - true_xyz)

    def add_stations(self, true_eo, eo):
        d = eo - true_eo
        d[:, :3] = (d[:, :3] + np.pi) % (2 * np.pi) - np.pi
        self.st_n += len(d)
        self.st_pos += float((d[:, 3:] ** 2).sum())
        self.st_ang += float((d[:, :3] ** 2).sum())

    def result(self):
        n = max(self.st_n, 1)
        return {
            "points": self.points.result(),
            "stations": {
                "n": self.st_n,
                "position_rms_m": math.sqrt(self.st_pos / (3 * n)),
                "angle_rms_arcsec": math.sqrt(self.st_ang / (3 * n)) / ARCSEC,
            },
        }


@dataclasses.dataclass
class Summary:
    """The outcome of :func:`sapgo.adjust`: usable result, statistics and timings."""

    path: str
    converged: bool
    termination: str
    iterations: int
    iteration_log: list
    sigma0: float
    redundancy: int
    image_rms_um: float
    image_rms_x_um: float
    image_rms_y_um: float
    band_width: int
    ordering: str
    band_width_before: int | None
    n_stations: int
    n_points: int
    n_observations: int
    n_cameras: int
    n_control: dict
    excluded_stations: list  # ids (the first 1000)
    excluded_points: list  # ids (the first 1000)
    n_excluded_stations: int
    check_points: dict
    control_points: dict
    n_excluded_points: int = 0
    truth: dict | None = None
    timings_s: dict = dataclasses.field(default_factory=dict)
    timings_per_iteration_s: dict = dataclasses.field(default_factory=dict)
    #: The kernels' threads (:mod:`sapgo.threads`): ``threads`` on an idle machine, and of
    #: ``checks`` looks at the machine, ``busy`` found other processes running (the kernels
    #: then ran on one thread).
    threads: dict = dataclasses.field(default_factory=dict)
    #: The iteration an interrupted run was resumed from (None: not resumed).
    resumed_from_iteration: int | None = None
    #: Common points derived from each strip's orientation, compared pair by pair
    #: (:mod:`sapgo.stripcmp`; None when no two strips share a derived point).
    strip_comparison: dict | None = None
    #: The computation frame and the user's CRS (:func:`sapgo.frames.frame_info`).
    frame: dict | None = None
    #: A-posteriori standard deviations of the station parameters (:func:`precision_summary`).
    precision: dict | None = None
    #: Correlations above the threshold between one station's or one point's parameters
    #: (:class:`HighCorrelations`).
    correlations: dict | None = None
    #: Internal reliability: redundancy numbers and minimal detectable blunders of the image
    #: observations (:class:`reliability_statistics`).
    reliability: dict | None = None
    #: "gn" (Gauss-Newton) or "lm" (Levenberg-Marquardt, from the first rejected step).
    method: str = "gn"
    #: Half the weighted sum of squared residuals (images, control, priors) at the start and
    #: at the end: the cost as Ceres reports it.
    initial_cost: float | None = None
    final_cost: float | None = None
    #: "control" (control points and priors fix the datum; ``--datum control``: the
    #: control alone), "priors" (``--datum priors``: the station priors alone), "fixed"
    #: (station parameters held fixed, ``--datum fix``, with whatever control there is) or
    #: "free" (a free network: inner constraints).
    datum: str = "control"
    #: the datum was the user's choice (``--datum``), not the project's
    datum_chosen: bool = False
    #: the precision pass (``--precision``): "full", "stations" or "none"
    precision_mode: str = "full"
    #: Pass points set aside during the run, their rays (nearly) parallel at the values of
    #: the time: ``{"point": id, "set_aside": iteration, "back": iteration or None}``.
    set_aside: list = dataclasses.field(default_factory=list)
    #: The project's image unit: "mm", or "px" (BAL problems: the ``*_um`` figures are then
    #: thousandths of a pixel).
    image_unit: str = "mm"
    #: Observations rejected by data snooping (photo and point ids, normalised residual).
    rejected: list = dataclasses.field(default_factory=list)
    #: Batch snooping: the observations it rejected and brought back when it confirmed its
    #: rejections (their tests no longer significant), as ``rejected``'s entries without w.
    reinstated: list = dataclasses.field(default_factory=list)
    #: Observations an earlier run rejected, kept out of this one (0 with
    #: ``--reset-rejections``, which brought ``rejections_reset`` of them back).
    rejections_kept: int = 0
    rejections_reset: int = 0
    #: Planted blunders against the rejections: ``{"planted", "found", "false_rejections",
    #: "rejected_with_point", "detectable", "found_detectable", ...}``.
    blunder_check: dict | None = None
    #: Self-calibration: per adjusted camera parameter ``{"camera", "parameter", "initial",
    #: "adjusted", "correction", "sigma"}`` (the parameter's own unit: f, x0, y0 image units,
    #: k1 per unit squared, ...; and ``"photo"``, its id, for a parameter calibrated per
    #: photo); None without self-calibration.
    calibration: list | None = None
    #: The linear solver: "band" or "tree" (the partition tree of nested dissection).
    solver: str = "band"
    #: The partition tree's figures when the solver is the tree: nodes, depth, leaves,
    #: roots, largest front (stations) and its bytes, largest separator, factor bytes,
    #: flops of one factorisation, and the bisection method.
    tree: dict | None = None

    def to_dict(self):
        return dataclasses.asdict(self)

    def _fields(self):
        """The fields as a dict, not copied (what :meth:`to_json` writes: ``asdict``'s deep
        copy of the iteration log and the lists took 2.8 ms of a 120 ms run of 1 000
        photos)."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}

    def _img(self, um):
        """An image residual figure in the project's unit."""
        return f"{um / 1000:.3f} px" if self.image_unit == "px" else f"{um:.2f} um"

    def to_json(self, indent=2):
        return json.dumps(self._fields(), indent=indent)

    def brief_report(self):
        c = self.check_points
        chk = (f", check points sXY {c['sxy']:.3f} m sZ {c['sz']:.3f} m" if c["n"] else "")
        return (f"{'converged' if self.converged else 'NOT converged'} in {self.iterations} "
                f"iterations: sigma0 {self.sigma0:.3f}, image RMS {self._img(self.image_rms_um)}"
                f"{chk}, {self._solver_brief()}, {self.timings_s.get('total', 0):.2f} s")

    def _solver_brief(self):
        if self.solver == "tree" and self.tree:
            return (f"tree solver ({self.tree['nodes']} nodes, largest front "
                    f"{self.tree['largest_front']} stations)")
        return f"band width {self.band_width}"

    def full_report(self):
        L = []
        ctrl = self.n_control
        L.append(f"sapgo adjustment of {self.path}")
        L.append(
            f"  block: {self.n_stations} photos, {self.n_points} points "
            f"({ctrl.get('full', 0)} full, {ctrl.get('horizontal', 0)} horizontal, "
            f"{ctrl.get('vertical', 0)} vertical control; {self.check_points['n']} check), "
            f"{self.n_observations} image observations, {self.n_cameras} camera(s)"
        )
        before = (f" (record order: {self.band_width_before})"
                  if self.band_width_before is not None else "")
        if self.frame and self.frame["kind"] != "local space rectangular":
            L.append(f"  frame: {self.frame['description']}")
        if self.solver == "tree" and self.tree:
            t = self.tree
            L.append(f"  order: {self.ordering}, tree solver: {t['nodes']} nodes ({t['leaves']} "
                     f"leaves, depth {t['depth']}), largest front {t['largest_front']} "
                     f"stations ({t['largest_front_bytes'] / 2**20:.1f} MiB), factor "
                     f"{t['factor_bytes'] / 2**20:.1f} MiB, {t['flops'] / 1e9:.2f} GFlop")
            if t.get("tiled_fronts"):
                L.append(f"  {t['tiled_fronts']} fronts tiled for the memory budget (panels "
                         f"of at most {t['panel_bytes'] / 2**20:.1f} MiB; all fronts in core "
                         f"would need {t['fronts_bytes'] / 2**20:.0f} MiB)")
        else:
            L.append(f"  order: {self.ordering}, band width {self.band_width} stations{before}")
        if self.excluded_stations:
            L.append(f"  left out, too few points: {self.n_excluded_stations} photos "
                     f"{_ids(self.excluded_stations)}")
        if self.excluded_points:
            L.append(f"  left out, too few rays: {self.n_excluded_points} points "
                     f"{_ids(self.excluded_points)}")
        L.append("")
        L.append("  iter   sigma0  image RMS  max dXYZc   max dang  max dXYZ    build    solve"
                 "   update")
        L.append(f"                      [{'um' if self.image_unit != 'px' else 'mpx'}]"
                 "        [m]       [\"]       [m]      [s]      [s]"
                 "      [s]")
        for r in self.iteration_log:
            L.append(
                f"  {r['iteration']:4d} {r['sigma0']:8.3f} {r['image_rms_um']:10.2f} "
                f"{r['max_station_position_corr_m']:10.4f} "
                f"{r['max_station_angle_corr_arcsec']:10.3f} {r['max_point_corr_m']:9.4f} "
                f"{r['build_s']:8.3f} {r['solve_s']:8.3f} {r['update_s']:8.3f}"
            )
        L.append("")
        if self.resumed_from_iteration is not None:
            L.append(f"  resumed after iteration {self.resumed_from_iteration} of an "
                     f"interrupted run")
        L.append(f"  {self.termination}")
        L.append(f"  sigma0 = {self.sigma0:.4f}  (redundancy {self.redundancy})")
        L.append(f"  image residuals RMS: x {self._img(self.image_rms_x_um)}, "
                 f"y {self._img(self.image_rms_y_um)}, both {self._img(self.image_rms_um)}")
        if self.initial_cost is not None and self.final_cost is not None:
            L.append(f"  cost (1/2 sum of squared weighted residuals): initial "
                     f"{self.initial_cost:.6e}, final {self.final_cost:.6e}"
                     + (" (Levenberg-Marquardt)" if self.method == "lm" else ""))
        if self.set_aside:
            out = [e["point"] for e in self.set_aside if e["back"] is None]
            L.append(f"  set aside, rays (nearly) parallel at the values of the time: "
                     f"{len(self.set_aside)} point(s), {len(self.set_aside) - len(out)} "
                     f"back later" + (f"; left out: {_ids(out)}" if out else ""))
        if self.datum == "fixed":
            L.append("  datum: station parameters held fixed (--datum fix), with the control "
                     "and priors given; their standard deviations are 0")
        if self.precision_mode != "full":
            L.append("  precision: " + (
                "not computed (--precision none)" if self.precision_mode == "none" else
                "the photos' alone (--precision stations): no points' standard deviations, "
                "redundancy numbers or tests of the observations"))
        if self.datum == "priors":
            L.append("  datum: the station priors alone (--datum priors); the control points "
                     "are used as check points")
        if self.datum == "control" and self.datum_chosen:
            L.append("  datum: the control points alone (--datum control); the station priors "
                     "are not used")
        if self.datum == "free":
            L.append("  a free network (no control or priors): datum by inner constraints on "
                     "the object points (their least change from the approximations: "
                     "centroid, rotation and scale kept)" + (
                         "; precision in that datum" if self.precision else
                         "; with self-calibration no precision is computed"))
        if self.calibration:
            unit = self.image_unit
            L.append(f"  self-calibration (camera, parameter: initial -> adjusted +- sigma; "
                     f"image unit {unit}):")
            for r in self.calibration:
                sig = "" if r["sigma"] is None else f" +- {r['sigma']:.6g}"
                who = f"camera {r['camera']}" + (f" photo {r['photo']}" if "photo" in r else "")
                L.append(f"    {who} {r['parameter']:>2}: {r['initial']:.9g} -> "
                         f"{r['adjusted']:.9g}{sig}")
        c = self.check_points
        if c["n"]:
            L.append(
                f"  check points ({c['n']}): sX {c['sx']:.3f} m  sY {c['sy']:.3f} m  "
                f"sZ {c['sz']:.3f} m  sXY {c['sxy']:.3f} m  (max |dXY| {c['max_dxy']:.3f} m,"
                f" max |dZ| {c['max_dz']:.3f} m)"
            )
        cp = self.control_points
        if cp["n_x"] or cp["n_z"]:
            parts = [f"{a} {_length(cp['rms_' + a.lower()])}"
                     for a in ("X", "Y", "Z") if cp["rms_" + a.lower()] is not None]
            L.append(f"  control residuals RMS: {', '.join(parts)}")
        if self.truth:
            tp, ts = self.truth["points"], self.truth["stations"]
            if tp["n"]:
                L.append(f"  against the generator's truth: {tp['n']} points sXY "
                         f"{tp['sxy']:.3f} m sZ {tp['sz']:.3f} m; {ts['n']} stations "
                         f"position RMS {ts['position_rms_m']:.3f} m, angles RMS "
                         f"{ts['angle_rms_arcsec']:.2f}\"")
        if self.precision:
            s = self.precision["stations"]
            L.append("  station precision (mean / max): "
                     + ", ".join(f"{n.split('_')[0]} {s[n]['mean']:.2f} / {s[n]['max']:.2f}"
                                 + (chr(34) if "arcsec" in n else " m") for n in s))
            pp = self.precision.get("points")
            if pp and pp["X_m"]["mean"] is not None:
                L.append("  point precision (mean / max): "
                         + ", ".join(f"{n[0]} {pp[n]['mean']:.3f} / {pp[n]['max']:.3f} m"
                                     for n in pp if pp[n]["mean"] is not None))
        if self.correlations and self.correlations["largest"]:
            c = self.correlations
            n = sum(sum(v.values()) for v in c["counts"].values())
            top = ", ".join(
                (f"photo {e['photo_id']}" if "photo_id" in e else f"point {e['point_id']}")
                + f" {e['pair']} {e['rho']:+.3f}" for e in c["largest"][:5])
            L.append(f"  correlations above {c['threshold']}: {n} ({top}"
                     f"{', ...' if n > 5 else ''})")
        if self.reliability:
            r = self.reliability
            m = r["mdb_um"]
            mdb = (f"; minimal detectable blunder (alpha {r['alpha']:g}, power "
                   f"{r['power']:.0%}) median {self._img(m['median'])}, 90 % "
                   f"{self._img(m['p90'])}"
                   if m["median"] is not None else "")
            L.append(f"  reliability: mean redundancy number {r['mean_redundancy_number']:.2f}"
                     f"{mdb}; {r['uncontrolled']} observations uncontrolled in one direction")
        if self.rejections_kept:
            L.append(f"  {self.rejections_kept} observation(s) rejected by an earlier run are "
                     f"kept out (sapgo adjust --reset-rejections brings them back)")
        if self.rejections_reset:
            L.append(f"  {self.rejections_reset} observation(s) rejected by an earlier run were "
                     f"brought back (--reset-rejections)")
        if self.rejected:
            tested = [r for r in self.rejected if r.get("by", "test") == "test"]
            shown = ", ".join(f"photo {r['photo_id']} point {r['point_id']} (t {r['w']:.1f})"
                              for r in tested[:10])
            more = ", ..." if len(tested) > 10 else ""
            extra = len(self.rejected) - len(tested)
            L.append(f"  data snooping rejected {len(tested)} observation(s): {shown}{more}"
                     + (f"; {extra} more with their point" if extra else ""))
            alpha = (self.reliability or {}).get("alpha")
            if alpha and alpha * self.n_observations >= 1.0:
                L.append(f"  (at alpha {alpha:g} about {alpha * self.n_observations:.0f} of "
                         f"the {self.n_observations} observations test significant by "
                         f"chance, blunder or not: on a block this size choose alpha near "
                         f"{1.0 / self.n_observations:.0e})")
        if self.reinstated:
            L.append(f"  batch snooping brought back {len(self.reinstated)} observation(s) "
                     f"when it confirmed its rejections (their tests no longer significant)")
        if self.blunder_check:
            b = self.blunder_check
            det = (f" ({b['found_detectable']} of the {b['detectable']} detectable at alpha "
                   f"{b['alpha']:g})" if "detectable" in b else "")
            L.append(f"  planted blunders: {b['found']} of {b['planted']} found{det}, "
                     f"{b['false_rejections']} false rejection(s)")
        L.extend(format_strip_comparison(self.strip_comparison))
        t = self.timings_s
        if t:
            L.append(
                f"  time [s]: order {t['order']:.2f}, build {t['build']:.2f}, solve "
                f"{t['solve']:.2f}, update {t['update']:.2f}, precision {t.get('precision', 0):.2f}, "
                f"commit {t.get('commit', 0):.2f}, "
                f"total {t['total']:.2f}"
            )
            ti = self.timings_per_iteration_s
            L.append(f"  per iteration [s]: build {ti['build']:.3f}, solve {ti['solve']:.3f}, "
                     f"update {ti['update']:.3f}")
        th = self.threads
        if th.get("busy"):
            L.append(f"  other processes were running: {th['busy']} of {th['checks']} looks "
                     f"found one, and the kernels ran on one thread of {th['threads']} then "
                     f"(SAPGO_THREADS=N fixes the count)")
        return "\n".join(L)


def _length(metres):
    """A length for the report: mm below a metre, m above."""
    return f"{1000 * metres:.2f} mm" if metres < 1.0 else f"{metres:.3f} m"


def _ids(ids, limit=20):
    s = ", ".join(str(i) for i in ids[:limit])
    return f"(ids {s}{', ...' if len(ids) > limit else ''})"
