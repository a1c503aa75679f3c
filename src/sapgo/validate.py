"""Value checks of a project's inputs, chunk by chunk, before anything is computed.

Each problem is reported as one line naming the dataset, the record number and the user's id
(``points record 17 (id 18): control[2] is NaN``).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from .errors import DataError
from .apsets import AP_SETS, N_TERMS
from .geometry import (
    AP_NAMES,
    AP_SET,
    BACKWARD,
    DISTORTION_MODELS,
    FORWARD,
    brown,
    camera_array,
    undistort,
)
from .project import (
    CONTROL_MASK,
    KIND_CHECK,
    KIND_NAMES,
    STATUS_ACTIVE,
    STATUS_EXCLUDED,
    STATUS_REJECTED,
    Project,
)


def _first_bad(mask):
    idx = np.flatnonzero(mask)
    return int(idx[0]) if len(idx) else -1


def _describe(value):
    if np.isnan(value):
        return "NaN"
    if np.isinf(value):
        return "infinite"
    return repr(float(value))


def _check_finite(name, start, ids, field, values):
    """Raise for the first non-finite entry of ``values`` (n, ...) in a chunk."""
    v = values.reshape(len(values), -1)
    bad = ~np.isfinite(v)
    rows = bad.any(axis=1)
    i = _first_bad(rows)
    if i >= 0:
        comp = int(np.flatnonzero(bad[i])[0])
        label = field if v.shape[1] == 1 else f"{field}[{comp}]"
        idtxt = f" (id {ids[i]})" if ids is not None else ""
        raise DataError(f"{name} record {start + i}{idtxt}: {label} is {_describe(v[i, comp])}")


#: Positions and image coordinates beyond this (in any unit) are not a block's: a value of
#: the input out of range (an import refuses them, :func:`check_records`).
MAX_MAGNITUDE = 1e15


def check_records(source, cameras=None, stations=None, points=None, observations=None,
                  start=0):
    """An import's records before they are written: every camera value, orientation, point
    coordinate and image measurement a finite number, and positions and image coordinates
    within :data:`MAX_MAGNITUDE` (a value that a conversion took out of range: a focal length
    of 1e-300, a pixel size of 1e300). The first problem is a :class:`DataError` naming
    ``source`` (the input) and the record (``start``: the first record's number, for a
    chunk of points and observations)."""
    sets = []
    if cameras is not None:
        floats = [n for n in cameras.dtype.names if cameras.dtype[n].base.kind == "f"]
        sets.append(("cameras", cameras, floats, [(n, slice(None)) for n in floats]))
    if stations is not None:
        sets.append(("stations", stations, ["eo"], [("eo", slice(3, 6))]))
    if points is not None:
        sets.append(("points", points, ["xyz"], [("xyz", slice(0, 3))]))
    if observations is not None:
        sets.append(("observations", observations, ["x", "y", "sigma"],
                     [("x", slice(None)), ("y", slice(None))]))
    for name, rec, fields, bounded in sets:
        if not len(rec):
            continue
        ids = rec["id"] if "id" in rec.dtype.names else None
        try:
            for field in fields:
                _check_finite(name, start, ids, field, np.asarray(rec[field], np.float64))
        except DataError as exc:
            raise DataError(f"{source}: {exc} (a value of the input out of range?)") from None
        for field, cols in bounded:
            v = np.abs(np.asarray(rec[field], np.float64).reshape(len(rec), -1)[:, cols])
            i = _first_bad((v > MAX_MAGNITUDE).any(axis=1))
            if i >= 0:
                idtxt = f" (id {ids[i]})" if ids is not None else ""
                raise DataError(f"{source}: {name} record {start + i}{idtxt}: {field} "
                                f"{v[i].max():.6g} is beyond {MAX_MAGNITUDE:g} (a "
                                f"value of the input out of range?)")


def check_values(project: Project, ordered_layout=True):
    """Check every input value; raise :class:`DataError` at the first problem. Returns
    ``{"rejected": n}``: the observations flagged rejected (by an earlier run), counted on
    the way.

    ``ordered_layout``: also check what an ordered project promises (priors by station).
    """
    n_rejected = 0
    path = project.path
    n_cam = project.n_cameras
    n_st = project.n_stations
    n_pt = project.n_points
    if n_cam == 0:
        raise DataError(f"{path}: the project has no camera")
    if n_st == 0:
        raise DataError(f"{path}: the project has no station (photo)")
    cams = project.cameras()
    for f in ("focal_length", "x0", "y0", "format_x", "format_y", "sigma_image",
              "k1", "k2", "k3", "p1", "p2", "b1", "b2", "ap_base") + AP_NAMES:
        _check_finite("cameras", 0, cams["id"], f, cams[f])
    for i, c in enumerate(cams):
        if not 0 <= c["ap_set"] < len(AP_SETS):
            raise DataError(f"cameras record {i} (id {c['id']}): additional-parameter set "
                            f"{c['ap_set']} is none of 0 .. {len(AP_SETS) - 1} "
                            f"({', '.join(AP_SETS)})")
        if c["ap_set"] and not c["ap_base"] > 0:
            raise DataError(f"cameras record {i} (id {c['id']}): the base of its "
                            f"{AP_SETS[int(c['ap_set'])]} set must be positive (mm), not "
                            f"{c['ap_base']:g}")
        if c["distortion_model"] not in (FORWARD, BACKWARD):
            raise DataError(f"cameras record {i} (id {c['id']}): distortion model "
                            f"{c['distortion_model']} is neither {FORWARD} (forward) nor "
                            f"{BACKWARD} (backward)")
        if c["focal_length"] <= 0:
            raise DataError(f"cameras record {i} (id {c['id']}): focal length must be positive")
        if c["sigma_image"] <= 0:
            raise DataError(f"cameras record {i} (id {c['id']}): sigma_image must be positive")
    # (every camera's fold in one kernel, once their fields are checked)
    for i, (c, fold) in enumerate(zip(cams, _distortion_folds(cams))):
        if fold is not None:
            raise DataError(
                f"cameras record {i} (id {c['id']}): the lens distortion (k1 {c['k1']:g}, "
                f"k2 {c['k2']:g}, k3 {c['k3']:g}, p1 {c['p1']:g}, p2 {c['p2']:g}, "
                f"b1 {c['b1']:g}, b2 {c['b2']:g}, "
                + (f"its {AP_SETS[int(c['ap_set'])]} set's a1 .. a{int(N_TERMS[c['ap_set']])}, "
                   if c["ap_set"] else "")
                + f"{DISTORTION_MODELS[int(c['distortion_model'])]} model) folds the "
                f"image over at ({fold[0]:.1f}, {fold[1]:.1f}) mm from the principal point, "
                f"inside the format: check the coefficients and their units (k1 mm^-2, "
                f"k2 mm^-4, k3 mm^-6, p1 and p2 mm^-1)"
            )
    cam_of_station = np.zeros(n_st, np.int32)   # (40 MB at 10 000 000 photos)
    for a, b in project.chunks("stations"):
        st = project.read("stations", a, b, copy=False)
        _check_finite("stations", a, st["id"], "eo", st["eo"])
        i = _first_bad((st["camera"] < 0) | (st["camera"] >= n_cam))
        if i >= 0:
            raise DataError(f"stations record {a + i} (id {st['id'][i]}): camera index "
                            f"{st['camera'][i]} is not one of the {n_cam} cameras")
        cam_of_station[a:b] = st["camera"]
    _check_station_spread(project)
    for a, b in project.chunks("station_priors"):
        pr = project.read("station_priors", a, b, copy=False)
        i = _first_bad((pr["station"] < 0) | (pr["station"] >= n_st))
        if i >= 0:
            raise DataError(f"station_priors record {a + i}: station {pr['station'][i]} "
                            f"does not exist")
        _check_finite("station_priors", a, None, "value", pr["value"])
        _check_finite("station_priors", a, None, "weight", pr["weight"])
        w = pr["weight"]
        asym = np.abs(w - np.transpose(w, (0, 2, 1))).max(axis=(1, 2)) > 1e-9 * (
            np.abs(w).max(axis=(1, 2)) + 1e-300)
        i = _first_bad(asym)
        if i >= 0:
            raise DataError(f"station_priors record {a + i}: the weight matrix is not "
                            f"symmetric")
        ev = np.linalg.eigvalsh(w)
        i = _first_bad(ev[:, 0] < -1e-12 * np.abs(ev).max(axis=1))
        if i >= 0:
            raise DataError(f"station_priors record {a + i}: the weight matrix is not "
                            f"positive semi-definite (eigenvalue {ev[i, 0]:.3g})")
    if project.ordered and ordered_layout:
        last = -1
        for a, b in project.chunks("station_priors"):
            st = project.read_field("station_priors", "station", a, b)
            i = _first_bad(np.diff(np.concatenate([[last], st])) < 0)
            if i >= 0:
                raise DataError(f"station_priors record {a + i}: priors of an ordered project "
                                f"must be sorted by station (run 'sapgo order')")
            last = st[-1]
    expected_start = 0
    for a, b in project.chunks("points"):
        pts = project.read("points", a, b, copy=False)
        ids = pts["id"]
        _check_finite("points", a, ids, "xyz", pts["xyz"])
        i = _first_bad((np.abs(pts["xyz"]) > MAX_COORDINATE).any(axis=1))
        if i >= 0:
            raise DataError(f"points record {a + i} (id {ids[i]}): xyz {_triple(pts['xyz'][i])}"
                            f" is beyond {MAX_COORDINATE:.0e} m from the frame's origin: "
                            f"check its units and columns")
        kind = pts["kind"]
        i = _first_bad((kind < 0) | (kind > KIND_CHECK))
        if i >= 0:
            raise DataError(f"points record {a + i} (id {ids[i]}): unknown kind {kind[i]}; "
                            f"kinds are {KIND_NAMES}")
        known = CONTROL_MASK[kind].astype(bool) | (kind == KIND_CHECK)[:, None]
        ctrl = np.where(known, pts["control"], 0.0)
        _check_finite("points", a, ids, "control", ctrl)
        csig = np.where(CONTROL_MASK[kind].astype(bool), pts["control_sigma"], 0.0)
        _check_finite("points", a, ids, "control_sigma", csig)
        i = _first_bad((csig < 0).any(axis=1))
        if i >= 0:
            raise DataError(f"points record {a + i} (id {ids[i]}): control_sigma must not be "
                            f"negative (0 fixes the coordinate)")
        starts = pts["obs_start"]
        counts = pts["n_obs"]
        exp = expected_start + np.concatenate([[0], np.cumsum(counts[:-1])])
        i = _first_bad((starts != exp) | (counts < 0))
        if i >= 0:
            raise DataError(f"points record {a + i} (id {ids[i]}): obs_start/n_obs do not "
                            f"follow the observations grouped by point")
        if int(starts[-1] + counts[-1]) > project.n_observations:
            raise DataError(f"{path}: the points' obs_start and n_obs cover at least "
                            f"{int(starts[-1] + counts[-1])} observations but /observations "
                            f"has {project.n_observations} records: the project is damaged")
        owners = project.read_field("observations", "point", int(starts[0]),
                                    int(starts[-1] + counts[-1]), copy=False)
        i = _first_bad(owners != np.repeat(np.arange(a, b), counts))
        if i >= 0:
            raise DataError(f"observations record {int(starts[0]) + i}: its point "
                            f"{owners[i]} is not the point whose range holds it")
        expected_start = int(starts[-1] + counts[-1])
    if expected_start != project.n_observations:
        raise DataError(f"{path}: the points reference {expected_start} observations, "
                        f"the project has {project.n_observations}")
    reach_of_camera = FORMAT_REACH * np.maximum(cams["format_x"], cams["format_y"])
    x0_of_camera, y0_of_camera = cams["x0"], cams["y0"]
    for a, b in project.chunks("observations"):
        obs = project.read("observations", a, b, copy=False)
        pt = obs["point"]
        i = _first_bad((pt < 0) | (pt >= n_pt))
        if i >= 0:
            raise DataError(f"observations record {a + i}: point {pt[i]} does not exist")
        i = _first_bad((obs["station"] < 0) | (obs["station"] >= n_st))
        if i >= 0:
            pid = project.read("points", int(pt[i]), int(pt[i]) + 1)["id"][0]
            raise DataError(f"observations record {a + i} (point id {pid}): station "
                            f"{obs['station'][i]} does not exist")
        for f in ("x", "y", "sigma"):
            bad = ~np.isfinite(obs[f])
            i = _first_bad(bad)
            if i >= 0:
                pid = project.read("points", int(pt[i]), int(pt[i]) + 1)["id"][0]
                sid = project.read("stations", int(obs["station"][i]),
                                   int(obs["station"][i]) + 1)["id"][0]
                raise DataError(f"observations record {a + i} (point id {pid}, photo id "
                                f"{sid}): {f} is {_describe(obs[f][i])}")
        i = _first_bad(obs["sigma"] < 0)
        if i >= 0:
            raise DataError(f"observations record {a + i}: sigma must not be negative "
                            f"(0 takes the camera's sigma_image)")
        # (per camera, then per observation: a field at a time, not the cameras' records)
        cam = cam_of_station[obs["station"]]
        reach = reach_of_camera[cam]
        far = (reach > 0) & ((np.abs(obs["x"] - x0_of_camera[cam]) > reach)
                             | (np.abs(obs["y"] - y0_of_camera[cam]) > reach))
        i = _first_bad(far)
        if i >= 0:
            c = cams[cam]
            pid = project.read("points", int(pt[i]), int(pt[i]) + 1)["id"][0]
            sid = project.read("stations", int(obs["station"][i]),
                               int(obs["station"][i]) + 1)["id"][0]
            unit = project.attr("image_unit", "mm") or "mm"
            raise DataError(
                f"observations record {a + i} (point id {pid}, photo id {sid}): image "
                f"coordinates ({obs['x'][i]:.6g}, {obs['y'][i]:.6g}) {unit} lie far outside "
                f"camera {c['id'][i]}'s format ({c['format_x'][i]:g} x {c['format_y'][i]:g} "
                f"{unit}, principal point ({c['x0'][i]:g}, {c['y0'][i]:g})): check the "
                f"measurement's units, its image frame (origin, axes) and its camera")
        i = _first_bad((obs["status"] != STATUS_ACTIVE) & (obs["status"] != STATUS_EXCLUDED)
                       & (obs["status"] != STATUS_REJECTED))
        if i >= 0:
            raise DataError(f"observations record {a + i}: unknown status {obs['status'][i]}")
        n_rejected += int((obs["status"] == STATUS_REJECTED).sum())
    if project.has_truth:
        for a, b in project.chunks("truth/points"):
            _check_finite("truth/points", a, None, "xyz",
                          project.read_field("truth/points", "xyz", a, b))
        for a, b in project.chunks("truth/stations"):
            _check_finite("truth/stations", a, None, "eo",
                          project.read_field("truth/stations", "eo", a, b))
    return {"rejected": n_rejected}


#: Plausibility: an image coordinate farther than this many format widths from the
#: principal point is an error (a unit, frame or camera mix-up), not a measurement.
FORMAT_REACH = 2.0
#: Plausibility: a coordinate beyond this (m) from the frame's origin is an error (beyond
#: a planetary frame's reach: the Moon's orbit is 4e8 m).
MAX_COORDINATE = 1e10
#: Plausibility: a photo farther from the block's centre than this many times the block's
#: own size is an error.
STATION_REACH = 100.0
#: The block's centre and size are medians over at most about this many photos (every
#: photo up to it, else every k-th: the check's memory does not grow with the block).
SPREAD_SAMPLE = 1 << 20


def _triple(v):
    return "(" + ", ".join(f"{x:.6g}" for x in v) + ")"


def _check_station_spread(project):
    """Photos at absurd positions: beyond :data:`MAX_COORDINATE`, or farther from the
    median photo than :data:`STATION_REACH` times the block's size (the median distance of
    the photos from it, at least the median distance of the points from it, at least 1 m)."""
    n_st = project.n_stations
    # the medians over every photo up to SPREAD_SAMPLE photos, else over every k-th
    step = max(1, -(-n_st // SPREAD_SAMPLE))
    sample = []
    for a, b in project.chunks("stations"):
        pos = project.read_field("stations", "eo", a, b, copy=False)[:, 3:6]
        i = _first_bad((np.abs(pos) > MAX_COORDINATE).any(axis=1))
        if i >= 0:
            sid = project.read_field("stations", "id", a + i, a + i + 1)[0]
            raise DataError(f"stations record {a + i} (id {sid}): X, Y, Z {_triple(pos[i])} "
                            f"are beyond {MAX_COORDINATE:.0e} m from the frame's origin: "
                            f"check the photo's units and columns")
        sample.append(pos[(-a) % step::step].copy())   # (a view would keep the chunk)
    if n_st < 2:
        return
    sample = np.concatenate(sample)
    centre = np.median(sample, axis=0)
    size = float(np.median(np.linalg.norm(sample - centre, axis=1)))
    n_pt = project.n_points
    if n_pt:   # (every point up to 16 x 4096, else a sample: 16 runs of 4096 points)
        starts = (np.zeros(1, np.int64) if n_pt <= 16 * 4096 else
                  np.linspace(0, n_pt - 4096, 16).astype(np.int64))
        run = 4096 if n_pt > 16 * 4096 else n_pt
        xyz = np.concatenate([project.read_field("points", "xyz", int(a), int(a) + run)
                              for a in starts])
        size = max(size, float(np.median(np.linalg.norm(xyz - centre, axis=1))))
    size = max(size, 1.0)
    far, i, where = -1.0, -1, None
    for a, b in project.chunks("stations"):
        pos = project.read_field("stations", "eo", a, b)[:, 3:6]
        dist = np.linalg.norm(pos - centre, axis=1)
        k = int(np.argmax(dist))
        if dist[k] > far:
            far, i, where = float(dist[k]), a + k, pos[k]
    if far > STATION_REACH * size:
        sid = project.read_field("stations", "id", i, i + 1)[0]
        raise DataError(f"stations record {i} (id {sid}): X, Y, Z {_triple(where)} lie "
                        f"{far:.3g} m from the block's median photo, {far / size:.0f} "
                        f"times the block's size ({size:.3g} m): check the photo's "
                        f"coordinates (units, columns, frame)")


#: The grid over the format on which :func:`_distortion_fold` looks for a fold.
FOLD_GRID = 41


def _distortion_fold(cam):
    """The first image point (x, y) inside the format (a grid of 41 x 41 over it, from the
    principal point: ideal points for the forward model, measured ones for the backward)
    where the distortion mapping stops being one-to-one (Jacobian determinant <= 0), else
    None."""
    return _distortion_folds(np.asarray(cam).reshape(1))[0]


def _distortion_folds(cams):
    """:func:`_distortion_fold` of every camera record of ``cams``: a list, one kernel
    (a BAL problem has a camera a photo: one call a camera took 0.5 ms)."""
    names = cams.dtype.names
    dist = np.zeros(len(cams), bool)
    for k in ("k1", "k2", "k3", "p1", "p2", "b1", "b2", "ap_set"):
        if k in names:
            dist |= cams[k] != 0
    out = [None] * len(cams)
    which = np.flatnonzero(dist)
    if len(which) == 0:
        return out
    sub = cams[which]
    rows = camera_array(sub)
    half = 0.5 * np.column_stack([sub["format_x"], sub["format_y"]]).astype(np.float64)
    backward = np.asarray(sub["distortion_model"] == BACKWARD)
    grid = fold_grid()
    first = _folds_at(grid, half, rows, backward)
    for j, i in enumerate(which):
        if first[j] >= 0:
            out[i] = (grid[first[j] // FOLD_GRID] * half[j, 0],
                      grid[first[j] % FOLD_GRID] * half[j, 1])
    return out


@njit(cache=True, parallel=True)
def _folds_at(grid, half, rows, backward):
    """:func:`_fold_at` of camera row ``rows[c]`` on the grid ``grid`` (-1 .. 1) scaled to
    its half format ``half[c]``, for every camera (threads over the cameras)."""
    first = np.empty(rows.shape[0], np.int64)
    for c in prange(rows.shape[0]):
        first[c] = _fold_at(grid * half[c, 0], grid * half[c, 1], rows[c], backward[c])
    return first


def fold_grid(n=FOLD_GRID):
    """The fold check's grid over -1 .. 1 (``n`` odd): ``linspace``'s points, made exactly
    symmetric about 0 (each negative one the negated positive one)."""
    half = np.linspace(0.0, 1.0, n // 2 + 1)
    return np.concatenate([-half[:0:-1], half])


@njit(cache=True)
def _folds(x, y, row, backward):
    """Does camera row ``row`` fold at grid point ``(x, y)`` (from the principal point)?"""
    _, _, j00, j01, j10, j11 = brown(x, y, row)
    if not j00 * j11 - j01 * j10 > 0.0:
        return True
    if backward:
        return False
    # every measured point of the format must map back to an ideal point on its own branch
    # (a barrel distortion can fold beyond the format and still cover it)
    _, _, ok = undistort(row[1] + x, row[2] + y, row)
    return not ok


@njit(cache=True)
def _mirrored(xs, ys, row):
    """Is the fold verdict of ``row`` the same at ``(+-x, +-y)`` on the grid ``xs, ys``,
    bit for bit? With radial terms alone and the principal point at 0 (BAL's cameras)
    :func:`brown` is even in each coordinate exactly (its odd terms only change sign, a
    rounding commutes with a negation), so is Newton's path in :func:`undistort`, mirrored;
    the grids must be symmetric exactly and of odd length."""
    if row[1] != 0.0 or row[2] != 0.0 or row[AP_SET] != 0.0:
        return False
    for k in range(6, 10):   # p1, p2, b1, b2
        if row[k] != 0.0:
            return False
    return _symmetric(xs) and _symmetric(ys)


@njit(cache=True)
def _symmetric(g):
    """Is grid ``g`` of odd length and symmetric about its middle point exactly?"""
    n = g.shape[0]
    if n % 2 == 0:
        return False
    for i in range(n // 2 + 1):
        if g[i] != -g[n - 1 - i]:
            return False
    return True


@njit(cache=True)
def _fold_at(xs, ys, row, backward):
    """:func:`_distortion_fold`'s grid (x outer, y inner) in one kernel: the index
    ``len(ys) i + j`` of the first fold, or -1 (a Python loop took 4 ms a camera: 0.2 s for
    a BAL problem's 49 cameras). Where the verdict is mirrored (:func:`_mirrored`), from
    one quadrant's points (a quarter of the Newton solves: BAL problem-49's 49 cameras took
    3.3 ms on the whole grid), the same index."""
    nx, ny = xs.shape[0], ys.shape[0]
    if not _mirrored(xs, ys, row):
        for i in range(nx):
            for j in range(ny):
                if _folds(xs[i], ys[j], row, backward):
                    return i * ny + j
        return -1
    mx, my = nx // 2, ny // 2
    bad = np.zeros((nx - mx, ny - my), np.bool_)
    for i in range(mx, nx):
        for j in range(my, ny):
            bad[i - mx, j - my] = _folds(xs[i], ys[j], row, backward)
    for i in range(nx):
        for j in range(ny):
            if bad[abs(i - mx), abs(j - my)]:
                return i * ny + j
    return -1
