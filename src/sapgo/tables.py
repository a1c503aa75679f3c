"""Residual reports: CSV tables of an adjusted project (``sapgo adjust --csv DIR``,
``sapgo report PROJECT --csv DIR``).

Three files with a header line, written in chunks (memory: per-photo accumulators and one
chunk of points with their observations):

- ``photos.csv``: per photo its adjusted orientation, standard deviations, number of points
  and image residual statistics (RMS, max);
- ``points.csv``: per point its adjusted coordinates, standard deviations, kind (control and
  check points marked), status, number of rays, largest image residual and, for control and
  check points, adjusted minus known;
- ``observations.csv``: per image observation its residuals, redundancy numbers, normalised
  residuals, test statistic, minimal detectable blunder, robust weight and flag.

A point's ``status`` says whether the adjustment determined it: ``active`` (adjusted),
``excluded`` (left out before the run: too few rays), ``rejected`` (data snooping took
its rays, or the rays left do not determine it) or ``set_aside`` (its rays (nearly)
parallel when the run ended). Only an active point has standard deviations, a largest
residual and adjusted minus known; the others have empty fields there (their X, Y, Z are
the values they had when they were left out), never numbers the adjustment did not
compute. Likewise a photo left out has empty standard deviations, and a photo without
active rays empty residual statistics.

Coordinates are those of the computation frame (m); a project with a CRS gets the user's
coordinates as well (geographic degrees to 9 decimals, about 0.1 mm). Adjusted minus known
of control and check points is along east, north, up at the point in a CRS frame, as their
sigmas are.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from .errors import DataError
from .normals import control_rotations
from .ordering import MIN_RAYS_PASS
from .project import (
    KIND_CONTROL,
    KIND_NAMES,
    KIND_VERTICAL,
    STATUS_ACTIVE,
    STATUS_REJECTED,
    Project,
)
from .report import minimal_detectable_blunder, noncentrality, weakest_redundancy

RAD2DEG = 180.0 / math.pi
RAD2SEC = 3600.0 * RAD2DEG
#: Names of an observation's ``flag``.
FLAGS = {STATUS_ACTIVE: "ok", STATUS_REJECTED: "rejected"}


def _user_columns(frame):
    """Headers and formats of the user's CRS coordinates (none for a local frame)."""
    if frame.kind == "local space rectangular":
        return [], []
    crs = frame.crs
    if crs.is_geographic:
        return ["lon_deg", "lat_deg", "h_m"], ["%.9f", "%.9f", "%.4f"]
    if crs.is_geocentric:
        return ["Xc_m", "Yc_m", "Zc_m"], ["%.4f"] * 3
    return ["E", "N", "h_m"], ["%.4f"] * 3


def _write(f, fmts, columns):
    """Rows of ``columns`` (equal-length lists or arrays) formatted by ``fmts``."""
    if not len(columns[0]):
        return
    line = ",".join(fmts) + "\n"
    cols = [c.tolist() if isinstance(c, np.ndarray) else c for c in columns]
    f.write("".join(line % row for row in zip(*cols)))


def _opt(values, fmt, mask):
    """Formatted values where ``mask``, empty fields elsewhere (as strings)."""
    return [fmt % v if m else "" for v, m in zip(values.tolist(), mask.tolist())]


#: Points per chunk of the tables: their rows are formatted through Python objects, about
#: 1 kB per observation at a time.
TABLE_CHUNK = 8192


def write_tables(project_path, out_dir, chunk=TABLE_CHUNK, alpha=None, power=0.8):
    """Write ``photos.csv``, ``points.csv`` and ``observations.csv`` of an adjusted project
    into ``out_dir`` (created). ``alpha``: significance level of the minimal detectable
    blunders (default: the run's data snooping alpha, else 0.001). Returns paths and counts.
    """
    out_dir = Path(out_dir)
    with Project(project_path) as p:
        if not p.has_solution or p.file["solution"].attrs.get("state") != "adjusted":
            raise DataError(f"{project_path}: the project has no adjusted solution: run "
                            f"'sapgo adjust' first")
        try:
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DataError(f"{out_dir}: cannot create the directory ({exc.strerror})") from exc
        report = json.loads(p.file["solution/report"][()])
        # points the run set aside and never brought back: not adjusted
        aside = np.array(sorted({int(e["point"]) for e in report.get("set_aside") or ()
                                 if e.get("back") is None}), np.int64)
        if alpha is None:
            alpha = (report.get("reliability") or {}).get("alpha", 0.001)
        lam0 = noncentrality(alpha, power)
        frame = p.frame()
        user_names, user_fmts = _user_columns(frame)
        cams = p.cameras()
        cam_sigma = cams["sigma_image"]
        st = p.read("stations")
        st_ids = st["id"]
        n_st = len(st)
        # per photo: rays, sum of vx^2 and vy^2, largest residual (um)
        st_n = np.zeros(n_st, np.int64)
        st_ss = np.zeros((n_st, 2))
        st_max = np.zeros(n_st)
        paths = {k: out_dir / f"{k}.csv" for k in ("photos", "points", "observations")}
        counts = dict.fromkeys(paths, 0)
        with open(paths["points"], "w") as fp, open(paths["observations"], "w") as fo:
            fp.write(",".join(["point_id", "kind", "status", "X_m", "Y_m", "Z_m"] + user_names
                              + ["sX_m", "sY_m", "sZ_m", "n_rays", "max_residual_um",
                                 "dX_m", "dY_m", "dZ_m"]) + "\n")
            fo.write("photo_id,point_id,point_kind,x_mm,y_mm,vx_um,vy_um,r_x,r_y,w_x,w_y,t,"
                     "mdb_um,weight,flag\n")
            for a, b in p.chunks("points", chunk):
                pts = p.read("points", a, b)
                xyz = pts["xyz"] + p.solution("point_corr", a, b)
                psig = p.solution("point_sigma", a, b)
                o0 = int(pts["obs_start"][0])
                o1 = int(pts["obs_start"][-1] + pts["n_obs"][-1])
                ob = p.read("observations", o0, o1)
                res = 1000.0 * p.solution("residuals", o0, o1)
                q = p.solution("obs_quality", o0, o1).astype(np.float64)
                act = ob["status"] == STATUS_ACTIVE
                length = np.where(act, np.hypot(res[:, 0], res[:, 1]), 0.0)
                s = ob["station"]
                np.add.at(st_n, s[act], 1)
                np.add.at(st_ss, s[act], res[act] ** 2)
                np.maximum.at(st_max, s[act], length[act])
                # points: rays are counted once per photo (sapgo.ordering's rule)
                owner = np.repeat(np.arange(len(pts)), pts["n_obs"])
                pairs = np.unique(owner[act] * n_st + s[act])
                n_rays = np.bincount(pairs // n_st, minlength=len(pts)).astype(np.int64)
                max_res = np.zeros(len(pts))
                np.maximum.at(max_res, owner, length)
                known = (pts["kind"] >= 1) & (pts["kind"] <= 4)
                rot = control_rotations(pts["kind"], pts["control"], frame)
                diff = np.einsum("nij,nj->ni", rot, xyz - pts["control"])
                # (a full or vertical control point is determined by one ray, others by
                # two: sapgo.ordering's rule)
                need = np.where((pts["kind"] == KIND_CONTROL) | (pts["kind"] == KIND_VERTICAL),
                                1, MIN_RAYS_PASS)
                status = np.where(pts["status"] != STATUS_ACTIVE, "excluded",
                                  np.where(n_rays >= need, "active", "rejected")).astype("U9")
                status[np.isin(pts["id"], aside) & (status == "active")] = "set_aside"
                adjusted = status == "active"
                kind = [KIND_NAMES.get(int(k), str(int(k))) for k in pts["kind"].tolist()]
                user = frame.to_user(xyz) if user_names else np.zeros((len(pts), 0))
                _write(fp, ["%d", "%s", "%s", "%.6f", "%.6f", "%.6f"] + user_fmts
                       + ["%s", "%s", "%s", "%d", "%s", "%s", "%s", "%s"],
                       [pts["id"], kind, status.tolist(), xyz[:, 0], xyz[:, 1], xyz[:, 2]]
                       + [user[:, k] for k in range(user.shape[1])]
                       + [_opt(psig[:, k], "%.6g", adjusted & (psig[:, k] > 0))
                          for k in range(3)]
                       + [n_rays, _opt(max_res, "%.3f", adjusted & (n_rays > 0))]
                       + [_opt(diff[:, k], "%.6f", known & adjusted) for k in range(3)])
                counts["points"] += len(pts)
                # observations
                sig = np.where(ob["sigma"] > 0, ob["sigma"], cam_sigma[st["camera"][s]])
                mdb = 1000.0 * minimal_detectable_blunder(
                    sig, weakest_redundancy(q[:, 0], q[:, 1], q[:, 2]), lam0)
                live = act & (q[:, 6] > 0)  # adjusted with this observation
                # (an observation of a point the run did not adjust is not used either)
                used = act & adjusted[ob["point"] - a]
                flag = np.where(used, "ok", np.where(ob["status"] == STATUS_REJECTED,
                                                     "rejected", "excluded"))
                predicted = (ob["status"] == STATUS_REJECTED) & (q[:, 5] > 0)
                _write(fo, ["%d", "%d", "%s", "%.6f", "%.6f", "%.3f", "%.3f", "%s", "%s", "%s",
                            "%s", "%s", "%s", "%.4g", "%s"],
                       [st_ids[s], pts["id"][ob["point"] - a],
                        [kind[j] for j in (ob["point"] - a).tolist()],
                        ob["x"], ob["y"], res[:, 0], res[:, 1]]
                       + [_opt(q[:, k], "%.4f", live) for k in range(2)]
                       # (rejected by the run's snooping: the test it would get back)
                       + [_opt(q[:, k], "%.3f", live | predicted) for k in (3, 4, 5)]
                       + [_opt(mdb, "%.1f", live), q[:, 6], flag.tolist()])
                counts["observations"] += len(ob)
        with open(paths["photos"], "w") as f:
            ang_names = ["omega_deg", "phi_deg", "kappa_deg"]
            extra = (["omega_enu_deg", "phi_enu_deg", "kappa_enu_deg"] if user_names else [])
            f.write(",".join(["photo_id", "camera_id", "strip", "status"] + ang_names
                             + ["X_m", "Y_m", "Z_m"] + extra + user_names
                             + ["s_omega_arcsec", "s_phi_arcsec", "s_kappa_arcsec", "sX_m",
                                "sY_m", "sZ_m", "n_points", "rms_um", "rms_x_um", "rms_y_um",
                                "max_um"]) + "\n")
            for a, b in p.chunks("stations", chunk):
                eo = st["eo"][a:b] + p.solution("station_corr", a, b)
                sg = p.solution("station_sigma", a, b)
                n = st_n[a:b]
                with np.errstate(invalid="ignore", divide="ignore"):
                    rms_xy = np.sqrt(st_ss[a:b] / np.maximum(n, 1)[:, None])
                rms = np.sqrt(0.5 * (rms_xy ** 2).sum(axis=1))
                cols = [st_ids[a:b], cams["id"][st["camera"][a:b]], st["strip"][a:b],
                        np.where(st["status"][a:b] == STATUS_ACTIVE, "active",
                                 "excluded").tolist()]
                cols += [eo[:, k] * RAD2DEG for k in range(3)] + [eo[:, k] for k in (3, 4, 5)]
                fmts = ["%d", "%d", "%d", "%s"] + ["%.9f"] * 3 + ["%.6f"] * 3
                if user_names:
                    opk = frame.opk_to_user(eo[:, :3], eo[:, 3:], "tangent")
                    user = frame.to_user(eo[:, 3:])
                    cols += [opk[:, k] * RAD2DEG for k in range(3)]
                    cols += [user[:, k] for k in range(3)]
                    fmts += ["%.9f"] * 3 + user_fmts
                # (a photo left out has no sigmas, one without active rays no residuals)
                in_run = st["status"][a:b] == STATUS_ACTIVE
                cols += [_opt(sg[:, k] * RAD2SEC, "%.6g", in_run) for k in range(3)]
                cols += [_opt(sg[:, k], "%.6g", in_run) for k in (3, 4, 5)]
                cols += [n] + [_opt(v, "%.3f", n > 0)
                               for v in (rms, rms_xy[:, 0], rms_xy[:, 1], st_max[a:b])]
                fmts += ["%s"] * 6 + ["%d", "%s", "%s", "%s", "%s"]
                _write(f, fmts, cols)
                counts["photos"] += b - a
    return {"paths": {k: str(v) for k, v in paths.items()}, "counts": counts}
