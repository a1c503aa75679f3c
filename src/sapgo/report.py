"""Statistics of an adjusted block and the reports (text and JSON) of a run.

Check points are compared with their known ground coordinates, as in seeds/002 Table 4:
``sX, sY, sZ`` are root mean squares of (adjusted - known), ``sXY = sqrt(sX^2 + sY^2)``.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np

from .project import CONTROL_MASK, KIND_CHECK
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

    def result(self):
        return self.check.result()

    def control_result(self):
        rms = [float(math.sqrt(s / k)) if k else None for s, k in zip(self.ctrl_ss, self.ctrl_n)]
        return {"n_x": int(self.ctrl_n[0]), "n_y": int(self.ctrl_n[1]),
                "n_z": int(self.ctrl_n[2]), "rms_x": rms[0], "rms_y": rms[1], "rms_z": rms[2]}


def precision_summary(station_sigma, point_sigma=None, project=None, chunk=65536):
    """Mean and maximum a-posteriori standard deviation of each station parameter (angles in
    arc seconds, positions in m) over the active stations, and of each point coordinate over
    the active points that are not fixed (``point_sigma``: the points' file, read in
    chunks)."""
    if not len(station_sigma):
        return None
    names = ("omega_arcsec", "phi_arcsec", "kappa_arcsec", "X_m", "Y_m", "Z_m")
    scale = [1.0 / (math.pi / (180 * 3600))] * 3 + [1.0] * 3
    out = {"stations": {n: {"mean": float(np.mean(station_sigma[:, k]) * scale[k]),
                            "max": float(np.max(station_sigma[:, k]) * scale[k])}
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
    #: The iteration an interrupted run was resumed from (None: not resumed).
    resumed_from_iteration: int | None = None
    #: Common points derived from each strip's orientation, compared pair by pair
    #: (:mod:`sapgo.stripcmp`; None when no two strips share a derived point).
    strip_comparison: dict | None = None
    #: The computation frame and the user's CRS (:func:`sapgo.frames.frame_info`).
    frame: dict | None = None
    #: A-posteriori standard deviations of the station parameters (:func:`precision_summary`).
    precision: dict | None = None
    #: Observations rejected by data snooping (photo and point ids, normalised residual).
    rejected: list = dataclasses.field(default_factory=list)
    #: Planted blunders against the rejections: ``{"planted", "found", "false_rejections"}``.
    blunder_check: dict | None = None

    def to_dict(self):
        return dataclasses.asdict(self)

    def to_json(self, indent=2):
        return json.dumps(self.to_dict(), indent=indent)

    def brief_report(self):
        c = self.check_points
        chk = (f", check points sXY {c['sxy']:.3f} m sZ {c['sz']:.3f} m" if c["n"] else "")
        return (f"{'converged' if self.converged else 'NOT converged'} in {self.iterations} "
                f"iterations: sigma0 {self.sigma0:.3f}, image RMS {self.image_rms_um:.2f} um"
                f"{chk}, band width {self.band_width}, {self.timings_s.get('total', 0):.2f} s")

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
        L.append("                      [um]        [m]       [\"]       [m]      [s]      [s]"
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
        L.append(f"  image residuals RMS: x {self.image_rms_x_um:.2f} um, "
                 f"y {self.image_rms_y_um:.2f} um, both {self.image_rms_um:.2f} um")
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
        if self.rejected:
            shown = ", ".join(f"photo {r['photo_id']} point {r['point_id']} (w {r['w']:.1f})"
                              for r in self.rejected[:10])
            more = ", ..." if len(self.rejected) > 10 else ""
            L.append(f"  data snooping rejected {len(self.rejected)} observation(s): "
                     f"{shown}{more}")
        if self.blunder_check:
            b = self.blunder_check
            L.append(f"  planted blunders: {b['found']} of {b['planted']} found, "
                     f"{b['false_rejections']} false rejection(s)")
        L.extend(format_strip_comparison(self.strip_comparison))
        t = self.timings_s
        if t:
            L.append(
                f"  time [s]: order {t['order']:.2f}, build {t['build']:.2f}, solve "
                f"{t['solve']:.2f}, update {t['update']:.2f}, commit {t.get('commit', 0):.2f}, "
                f"total {t['total']:.2f}"
            )
            ti = self.timings_per_iteration_s
            L.append(f"  per iteration [s]: build {ti['build']:.3f}, solve {ti['solve']:.3f}, "
                     f"update {ti['update']:.3f}")
        return "\n".join(L)


def _length(metres):
    """A length for the report: mm below a metre, m above."""
    return f"{1000 * metres:.2f} mm" if metres < 1.0 else f"{metres:.3f} m"


def _ids(ids, limit=20):
    s = ", ".join(str(i) for i in ids[:limit])
    return f"(ids {s}{', ...' if len(ids) > limit else ''})"
