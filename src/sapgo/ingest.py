"""Streaming import of a block from plain-text files (``sapgo import``).

``import_text(out, cameras=[...], photos=[...], measurements=[...], control=[...])`` reads the
four text formats of :mod:`sapgo.formats.text` (documented in ``docs/formats.md``) and writes a
new, unordered project through :class:`sapgo.project.ProjectWriter` (built as ``OUT.tmp`` and
renamed over ``OUT`` only when complete, so a failed import leaves ``OUT`` as it was).

Memory. Cameras and photos are held in core (per-photo vectors, some 100 bytes a photo).
Everything else streams within the memory budget (``memory``, default
:data:`sapgo.extsort.DEFAULT_MEMORY`): text is read in blocks of lines of 1/32 of the
budget; control records go through an external sort by id and are merged to a work file;
image measurements go through an external sort by (point id, photo record); a merge-join of
the two sorted streams by point id then produces the points in id order with their
observations, approximate coordinates (ray intersection) and control, written chunk by chunk.
The work directory ``OUT.import.work`` beside the output is removed afterwards, also on
failure.

Determinism. The records depend only on the set of input lines, not on their order, the
order of the files or the memory budget: photos and cameras are sorted by id, points by id,
observations by (point, photo record); duplicate measurements of a point on one photo are
merged by summing their coordinates in sorted value order, so shuffled input gives bitwise the
same project, and importing sub-blocks one after the other with ``append=True`` gives the same
records as importing them together.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import time
from pathlib import Path

import numpy as np

from .lock import writes_project
from .errors import DataError, ParameterError
from .extsort import DEFAULT_MEMORY, ExternalSorter, parse_memory
from .formats.text import (
    CAMERAS,
    CONTROL,
    COVARIANCE_TERMS,
    MEASUREMENTS,
    NEEDED,
    MATRIX_TERMS,
    PHOTOS,
    PHOTOS_MATRIX,
    PRIOR_COVARIANCES,
    PRIOR_PARAMETERS,
    PRIORS,
    check_angles,
    check_axis_order,
    decode_text,
    open_input,
    parse_chunk,
    read_chunks,
    swap_axes,
)
from .frames import (
    LOCAL,
    MOON_RADIUS,
    ORIENTATIONS,
    SELENOCENTRIC,
    Frame,
    OutsideDomain,
    _check_order,
    opk_of,
    opk_of_order,
    parse_crs,
    prior_of_order,
)
from .geometry import AP_NAMES, camera_array, intersect_points, undistort_points
from .project import (
    CAMERA_DTYPE,
    CONTROL_MASK,
    KIND_CHECK,
    KIND_HORIZONTAL,
    KIND_NAMES,
    KIND_PASS,
    KIND_VERTICAL,
    OBSERVATION_DTYPE,
    POINT_DTYPE,
    PRIOR_DTYPE,
    STATION_DTYPE,
    STATUS_ACTIVE,
    STATUS_REJECTED,
    Project,
    ProjectWriter,
    append_history,
)
from .validate import check_records

#: Image measurements as they are sorted: point id, station record, values, origin.
MEAS_DTYPE = np.dtype([("point", "<i8"), ("station", "<i8"), ("x", "<f8"), ("y", "<f8"),
                       ("sigma", "<f8"), ("loc", "<i8")])
#: Control records as they are sorted and kept in the work file.
CTRL_DTYPE = np.dtype([("id", "<i8"), ("kind", "i1"), ("control", "<f8", (3,)),
                       ("sigma", "<f8", (3,)), ("loc", "<i8"), ("raw", "i1")])
#: ``raw``: horizontal or vertical control still in the user's CRS (converted into the frame
#: once the point's approximate position is known, in ``_assemble``).
#: ``loc`` = source number << LOC_BITS | line (or record) number.
LOC_BITS = 40
#: Examples listed in a warning.
EXAMPLES = 5
#: One arc second in radians (the unit of a prior's angle sigmas).
ARCSEC = np.pi / (180 * 3600)
#: Ids listed in a warning.
LISTED = 20
#: Distance along a ray (m) of a point that cannot be intersected when no ground height is
#: known.
DEFAULT_RAY_DISTANCE = 1000.0
#: Fixed piece size of the order-independent sums (records).
_SUM_PIECE = 65536


def _as_list(files):
    if files is None:
        return []
    if isinstance(files, (str, os.PathLike)):
        return [files]
    return list(files)


def _ids(ids, limit=LISTED):
    ids = list(ids)
    s = ", ".join(str(i) for i in ids[:limit])
    return s + (", ..." if len(ids) > limit else "")


class _Sources:
    """Names of the places records come from, for messages (``file:line``)."""

    def __init__(self):
        self._names = []

    def add(self, label, dataset=None):
        label = str(label)
        if dataset is None and (label, None) in self._names:
            label += " (given again)"
        self._names.append((label, dataset))
        return len(self._names) - 1

    @staticmethod
    def loc(src, lines):
        return (np.int64(src) << LOC_BITS) | np.asarray(lines, np.int64)

    def where(self, loc):
        loc = int(loc)
        label, dataset = self._names[loc >> LOC_BITS]
        n = loc & ((1 << LOC_BITS) - 1)
        return f"{label}:{n}" if dataset is None else f"{label} ({dataset} record {n})"


def _member(sorted_ids, ids):
    """Which of ``ids`` are in the sorted array ``sorted_ids``."""
    if not len(sorted_ids):
        return np.zeros(len(ids), bool)
    k = np.minimum(np.searchsorted(sorted_ids, ids), len(sorted_ids) - 1)
    return sorted_ids[k] == ids


def _bits(a):
    """Rows of an (n, k) float array as int64 bit patterns (exact comparison)."""
    return np.ascontiguousarray(a, np.float64).view(np.int64)


def _rotations(eo):
    """Object -> image rotation matrices ``M = R3(kappa) R2(phi) R1(omega)``, (n, 3, 3)."""
    n = len(eo)
    cw, sw = np.cos(eo[:, 0]), np.sin(eo[:, 0])
    cp, sp = np.cos(eo[:, 1]), np.sin(eo[:, 1])
    ck, sk = np.cos(eo[:, 2]), np.sin(eo[:, 2])
    z, o = np.zeros(n), np.ones(n)
    r1 = np.stack([o, z, z, z, cw, sw, z, -sw, cw], axis=1).reshape(n, 3, 3)
    r2 = np.stack([cp, z, -sp, z, o, z, sp, z, cp], axis=1).reshape(n, 3, 3)
    r3 = np.stack([ck, sk, z, -sk, ck, z, z, z, o], axis=1).reshape(n, 3, 3)
    return r3 @ r2 @ r1


def ray_points(eo, xy, f, height, distance, sphere=None):
    """A point on each image ray (``xy``: ideal image coordinates from the principal point,
    :func:`~sapgo.geometry.undistort_points`): where it meets the plane ``Z = height`` (or,
    for a selenocentric frame, the sphere of radius ``sphere``) in front of the camera, else
    at ``distance`` metres from the projection centre (all finite)."""
    m = _rotations(eo)
    img = np.stack([np.nan_to_num(xy[:, 0]), np.nan_to_num(xy[:, 1]), -f], axis=1)
    d = np.einsum("nji,nj->ni", m, img)
    d /= np.linalg.norm(d, axis=1)[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        if sphere:  # |P + t d| = R, the nearer root
            pd = np.einsum("ni,ni->n", eo[:, 3:], d)
            disc = pd * pd - (np.einsum("ni,ni->n", eo[:, 3:], eo[:, 3:]) - sphere * sphere)
            t = -pd - np.sqrt(disc)
            down = disc >= 0
        else:
            t = (height - eo[:, 5]) / d[:, 2]
            down = d[:, 2] < -1e-6
    use = np.isfinite(t) & (t > 0) & down & (t <= 1000.0 * distance)
    t = np.where(use, t, distance)
    return eo[:, 3:] + t[:, None] * d


class _Import:
    def __init__(self, out, files, angles, memory, work, existing, crs=None,
                 orientation="tangent", rotation="opk", axis_order="en"):
        self.out = out
        self.files = files
        self.angles = angles
        self.axis_order = check_axis_order(axis_order)
        self.rotation = rotation
        self.crs = None if crs is None else parse_crs(crs)
        self.orientation = orientation
        self.frame = Frame()
        self.memory = memory
        self.work = work
        self.existing = existing  # path of the project appended to, or None
        self.chunk_bytes = max(64 << 10, memory // 32)
        self.block_records = max(4096, memory // (64 * MEAS_DTYPE.itemsize))
        self.src = _Sources()
        #: conflicting duplicates (beyond 3 sigma) merged too, not refused
        self.merge_all = False
        self.warnings = []
        self.lines = 0
        self.bytes = 0
        self.s = {}  # summary counters

    # -- helpers -------------------------------------------------------------------------
    def _warn(self, msg):
        self.warnings.append(msg)

    def _check_existing(self, dataset, start, bad, message):
        """Raise for the first True of ``bad`` (records of ``OUT`` being appended to)."""
        idx = np.flatnonzero(bad)
        if len(idx):
            i = int(idx[0])
            raise DataError(f"{self.existing}: {dataset} record {start + i}: {message(i)}")

    def _read(self, fmt, path, refs=None):
        """Yield (records, locs) of a text file, chunk by chunk (northing-first coordinates
        put in X, Y order; geographic ones may be written in degrees, minutes, seconds)."""
        src = self.src.add(path)
        xy = fmt in (PHOTOS, PHOTOS_MATRIX, CONTROL, PRIORS, PRIOR_COVARIANCES)
        dms = ("X", "Y") if xy and self.crs is not None and self.crs.is_geographic else ()
        for first, chunk in read_chunks(path, self.chunk_bytes):
            self.bytes += len(chunk)
            rec, lines = parse_chunk(fmt, chunk, first, self.angles, str(path), refs, dms)
            self.lines += len(rec)
            if xy and self.axis_order == "ne":
                swap_axes(fmt, rec)
            if len(rec):
                yield rec, self.src.loc(src, lines)

    def _dedupe(self, what, ids, values, locs, names):
        """Indices of the records to keep, sorted by id; identical repeats dropped, conflicting
        ones an error naming both places. ``values`` (n, k) int64 bit patterns."""
        order = np.lexsort((locs, ids))
        ids_s, vals_s, locs_s = ids[order], values[order], locs[order]
        same = ids_s[1:] == ids_s[:-1]
        twice = np.flatnonzero(same)
        if len(twice):
            differ = vals_s[twice + 1] != vals_s[twice]
            bad = np.flatnonzero(differ.any(axis=1))
            if len(bad):
                i = twice[bad[0]]
                field = names[int(np.flatnonzero(differ[bad[0]])[0])]
                raise DataError(
                    f"{what} {ids_s[i]} is given twice with different values ({field}): "
                    f"{self.src.where(locs_s[i])} and {self.src.where(locs_s[i + 1])}")
        examples = [f"{what} {ids_s[i]} ({self.src.where(locs_s[i])}, "
                    f"{self.src.where(locs_s[i + 1])})" for i in twice[:EXAMPLES]]
        keep = order[np.concatenate([[True], ~same])] if len(order) else order
        return keep, len(twice), examples

    # -- cameras and photos (in core) ----------------------------------------------------
    def read_cameras(self, p):
        recs, locs = [], []
        if p is not None:
            src = self.src.add(self.existing, "cameras")
            cams = p.cameras()
            recs.append(np.array(cams, CAMERA_DTYPE))
            locs.append(self.src.loc(src, np.arange(len(cams))))
        self.camera_frames = []   # (camera id, frame columns, loc): columns 16-22
        for path in self.files["cameras"]:
            for rec, loc in self._read(CAMERAS, path):
                cam = np.zeros(len(rec), CAMERA_DTYPE)   # (the first 15 columns, by place)
                for name, col in zip(CAMERA_DTYPE.names[:15], rec.dtype.names[:15]):
                    cam[name] = rec[col]
                recs.append(cam)
                locs.append(loc)
                for i in np.flatnonzero(rec["frame"] >= 0):
                    self.camera_frames.append((int(rec["id"][i]), rec[i], int(loc[i])))
        given = ", ".join(str(f) for f in self.files["cameras"])
        if not recs or not sum(len(r) for r in recs):
            raise DataError(f"{given}: no camera (every line blank or a comment)" if given
                            else "no camera: give a cameras file (--cameras)")
        cams = np.concatenate(recs)
        locs = np.concatenate(locs)
        if not len(cams):
            raise DataError("no camera in the cameras file(s)")
        # the additional-parameter sets: onto every record of their cameras, the project's
        # too (a camera given again without them keeps the project's: not compared)
        read_additional_parameters(self.files.get("additional_parameters", ()), cams)
        names = tuple(n for n in CAMERA_DTYPE.names[1:] if n not in AP_FIELDS)
        values = _bits(np.stack([cams[n] for n in names], axis=1))
        keep, twice, examples = self._dedupe("camera", cams["id"], values, locs, names)
        if twice:
            self._warn(f"{twice} camera(s) given more than once with identical values were "
                       f"loaded once: {', '.join(examples)}")
        self.s["cameras_loaded_twice"] = twice
        cams = cams[keep]
        self.cameras = cams
        return cams

    def read_photos(self, p):
        cam_ids = self.cameras["id"]
        ids, cam, strip, eo, locs = [], [], [], [], []
        if p is not None:
            src = self.src.add(self.existing, "stations")
            st = p.read("stations")
            old_cam_ids = p.cameras()["id"]
            self._check_existing("stations", 0, (st["camera"] < 0)
                                 | (st["camera"] >= len(old_cam_ids)),
                                 lambda i: f"camera {st['camera'][i]} does not exist")
            self._check_existing("stations", 0, ~np.isfinite(st["eo"]).all(axis=1),
                                 lambda i: f"eo is not finite ({st['eo'][i].tolist()})")
            ids.append(st["id"])
            cam.append(np.searchsorted(cam_ids, old_cam_ids[st["camera"]]))
            strip.append(st["strip"].astype(np.int64))
            eo.append(st["eo"])
            locs.append(self.src.loc(src, np.arange(len(st))))
            self.old_station_ids = st["id"]

        def known_camera(rec):
            unknown = ~_member(cam_ids, rec["camera"])
            return [(unknown, lambda i: f"camera {rec['camera'][i]} is not in the cameras "
                                        f"file(s) (column 2)")]

        n_old = sum(len(e) for e in eo)
        for kind in ("photos", "photos_matrix"):
            for path in self.files[kind]:
                fmt = PHOTOS if kind == "photos" else PHOTOS_MATRIX
                for rec, loc in self._read(fmt, path, known_camera):
                    k = np.searchsorted(cam_ids, rec["camera"])
                    ids.append(rec["id"])
                    cam.append(k)
                    strip.append(rec["strip"])
                    if fmt is PHOTOS:   # (the columns in the order --rotation gives)
                        opk = opk_of_order(np.stack([rec[n] for n in ("omega", "phi",
                                                                      "kappa")], axis=1),
                                           self.rotation)
                    else:
                        m = np.stack([rec[t] for t in MATRIX_TERMS], axis=1).reshape(-1, 3, 3)
                        opk = opk_of(m)
                    eo.append(np.column_stack([opk] + [rec[n] for n in ("X", "Y", "Z")]))
                    locs.append(loc)
        if not ids or not sum(len(i) for i in ids):
            raise DataError("no photo: give a photos file with at least one photo (--photos)")
        ids, cam, strip = np.concatenate(ids), np.concatenate(cam), np.concatenate(strip)
        eo, locs = np.concatenate(eo), np.concatenate(locs)
        try:
            self._set_frame(p, eo[n_old:, 3:])
            if self.crs is not None and len(eo) > n_old:  # the files' photos into the frame
                xyz = self.frame.from_user(eo[n_old:, 3:], self.crs)
                eo[n_old:, :3] = self.frame.opk_from_user(eo[n_old:, :3], xyz,
                                                          self.orientation)
                eo[n_old:, 3:] = xyz
        except OutsideDomain as exc:
            j = n_old + exc.row
            raise DataError(f"{self.src.where(locs[j])}: photo {ids[j]}: {exc}") from None
        values = np.concatenate([cam_ids[cam][:, None], strip[:, None], _bits(eo)], axis=1)
        names = ("camera", "strip", "omega", "phi", "kappa", "X", "Y", "Z")
        keep, twice, examples = self._dedupe("photo", ids, values, locs, names)
        if twice:
            self._warn(f"{twice} photo(s) given more than once with identical values were "
                       f"loaded once: {', '.join(examples)}")
        self.s["photos_loaded_twice"] = twice
        st = np.zeros(len(keep), STATION_DTYPE)
        st["id"] = ids[keep]
        st["camera"] = cam[keep]
        st["strip"] = strip[keep]
        st["status"] = STATUS_ACTIVE
        st["eo"] = eo[keep]
        self.stations = st
        return st

    def _set_frame(self, p, file_xyz):
        """The computation frame: the appended project's, or one for ``--crs`` (at the centre
        of the files' photos), else local; refuse mixing a local project with a CRS."""
        old = p.frame() if p is not None else None
        if old is not None and (old.kind != LOCAL or p.n_stations):
            if (self.crs is None) != (old.kind == LOCAL):
                raise ParameterError(
                    f"{self.existing} is in the frame {old.describe()!r}: the appended files "
                    f"must be given " + ("in a CRS (--crs)" if self.crs is None else
                                         "in its local coordinates (no --crs)"))
            if self.crs is not None:
                old.check_body(self.crs, "the appended data")
            self.frame = old
        elif self.crs is not None:
            self.frame = Frame.for_crs(self.crs, file_xyz)

    def _control_to_frame(self, rec, r, loc):
        """Control of a file in ``--crs`` into the frame. Full control and check points are
        converted at once; horizontal and vertical control keep their CRS values (``raw``)
        until the point's approximate position supplies the unknown coordinates
        (:meth:`_partial_control`). Sigmas are along east, north, up at the point (the
        adjustment rotates them, ``normals.control_rotations``); in a geocentric CRS they
        must be equal in all three coordinates, and horizontal or vertical control needs a
        geographic or projected CRS. A CRS point is fixed in all three coordinates or in
        none."""
        if self.crs is None:
            return

        def refuse(bad, message):
            if bad.any():
                j = int(np.flatnonzero(bad)[0])
                raise DataError(f"{self.src.where(loc[j])}: point {rec['id'][j]}"
                                + message(j))

        kind = r["kind"]
        partial = (kind == KIND_HORIZONTAL) | (kind == KIND_VERTICAL)
        sig = r["sigma"]
        ctrl = CONTROL_MASK[kind].astype(bool)
        if self.crs.is_geocentric:
            refuse(partial, lambda j: (
                f" is {KIND_NAMES[int(kind[j])]} control, which needs a geographic or "
                f"projected CRS (east, north, up are not the axes of a geocentric CRS)"))
            refuse(ctrl.any(axis=1) & ~((sig[:, 0] == sig[:, 1]) & (sig[:, 1] == sig[:, 2])),
                   lambda j: (": control sigmas in a geocentric CRS must be equal in X, Y "
                              "and Z (give east, north, up sigmas in a geographic or "
                              "projected CRS)"))
        fixed = ctrl & (sig == 0)
        refuse(fixed.any(axis=1) & (~fixed.all(axis=1) | partial), lambda j: (
            ": with --crs a control point is fixed (sigma 0) in all three coordinates or "
            "in none; give horizontal and vertical control sigmas > 0"))
        full = ~partial
        if full.any():
            try:
                r["control"][full] = self.frame.from_user(r["control"][full], self.crs)
            except OutsideDomain as exc:
                j = int(np.flatnonzero(full)[exc.row])
                raise DataError(f"{self.src.where(loc[j])}: point {rec['id'][j]}: {exc}") \
                    from None
        r["raw"] = partial

    def _partial_control(self, control, kind, raw, approx):
        """Frame coordinates of horizontal and vertical control given in the CRS (``raw``):
        the unknown coordinates (height, or position) taken from the approximate point, so
        that the reference lies on the point's vertical (horizontal control: any height is
        on that line) or on its height surface near the point (vertical control: the
        surface's curvature over the approximation's error is below a micrometre)."""
        rows = np.flatnonzero(raw)
        if not len(rows):
            return control
        user = self.frame.to_user(approx[rows], self.crs)
        given = control[rows].copy()
        vert = kind[rows] == KIND_VERTICAL
        given[~vert, 2] = user[~vert, 2]
        given[vert, :2] = user[vert, :2]
        out = control.copy()
        out[rows] = self.frame.from_user(given, self.crs)
        return out

    # -- station priors (in core: at most one per photo) ----------------------------------
    def read_priors(self, p, st):
        """The station priors of ``OUT`` (appending) and of the priors files, as PRIOR_DTYPE
        records sorted by station; a photo given twice must have the same prior."""
        ids, value, weight, locs = [], [], [], []
        if p is not None:
            pr = p.read("station_priors")
            if len(pr):
                src = self.src.add(self.existing, "station_priors")
                ids.append(self.old_station_ids[pr["station"]])
                value.append(pr["value"])
                weight.append(pr["weight"])
                locs.append(self.src.loc(src, np.arange(len(pr))))

        def known_photo(rec):
            unknown = ~_member(st["id"], rec["photo"])
            return [(unknown, lambda i: f"photo {rec['photo'][i]} is not in the photos "
                                        f"file(s) (column 1)")]

        for fmt in (PRIORS, PRIOR_COVARIANCES):
            for path in self.files[fmt.name]:
                for rec, loc in self._read(fmt, path, known_photo):
                    ids.append(rec["photo"])
                    v = np.stack([rec[n] for n in PRIOR_PARAMETERS], axis=1)
                    w = self._prior_weights(fmt, rec, loc)
                    v, w = prior_of_order(v, w, self.rotation)
                    if self.crs is not None:
                        v, w = self.frame.prior_from_user(v, w, self.crs, self.orientation)
                    value.append(v)
                    weight.append(w)
                    locs.append(loc)
        if not ids or not sum(len(i) for i in ids):
            return np.zeros(0, PRIOR_DTYPE)
        ids, value, weight = np.concatenate(ids), np.concatenate(value), np.concatenate(weight)
        locs = np.concatenate(locs)
        values = np.concatenate([_bits(value), _bits(weight.reshape(len(ids), 36))], axis=1)
        names = PRIOR_PARAMETERS + tuple(f"weight[{i}][{j}]" for i in range(6)
                                         for j in range(6))
        keep, twice, examples = self._dedupe("prior of photo", ids, values, locs, names)
        if twice:
            self._warn(f"{twice} prior(s) given more than once with identical values were "
                       f"loaded once: {', '.join(examples)}")
        pr = np.zeros(len(keep), PRIOR_DTYPE)
        pr["station"] = np.searchsorted(st["id"], ids[keep])
        pr["value"] = value[keep]
        pr["weight"] = weight[keep]
        return pr[np.argsort(pr["station"], kind="stable")]

    def _prior_weights(self, fmt, rec, loc):
        """6x6 weights (1/rad^2, 1/m^2) of sigmas or covariances given in arc seconds and m;
        a weight that overflows (a sigma of 1e-300) is an error naming the line."""
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            w = self._prior_weights_of(fmt, rec, loc)
        bad = ~np.isfinite(w).all(axis=(1, 2))
        if bad.any():
            r = int(np.flatnonzero(bad)[0])
            raise DataError(f"{self.src.where(loc[r])}: the prior of photo {rec['photo'][r]} "
                            f"has a sigma or covariance too small for its weight (1/sigma^2) "
                            f"to be a number; leave a parameter free with 0 or '-'")
        return w

    def _prior_weights_of(self, fmt, rec, loc):
        scale = np.array([ARCSEC] * 3 + [1.0] * 3)
        n = len(rec)
        w = np.zeros((n, 6, 6))
        if fmt is PRIORS:
            sig = np.stack([rec["s_" + k] for k in PRIOR_PARAMETERS], axis=1) * scale
            on = sig > 0
            d = np.where(on, 1.0 / np.where(on, sig, 1.0) ** 2, 0.0)
            w[:, np.arange(6), np.arange(6)] = d
            return w
        cov = np.zeros((n, 6, 6))
        for t, (i, j) in enumerate((i, j) for i in range(6) for j in range(i, 6)):
            cov[:, i, j] = cov[:, j, i] = rec[COVARIANCE_TERMS[t]] * scale[i] * scale[j]
        for r in range(n):
            try:
                c = np.linalg.cholesky(cov[r])
            except np.linalg.LinAlgError:
                raise DataError(f"{self.src.where(loc[r])}: the covariance of the prior of "
                                f"photo {rec['photo'][r]} is not positive definite "
                                f"(columns 8-28: c11 c12 ... c66 in arc seconds and m)") \
                    from None
            ci = np.linalg.inv(c)
            w[r] = ci.T @ ci
        return w

    # -- control (external sort, merged into a work file) --------------------------------
    def read_control(self, p):
        path = self.work / "control.bin"
        self.control_path = path
        n_twice, examples = 0, []
        counts = dict.fromkeys(KIND_NAMES, 0)
        with ExternalSorter(CTRL_DTYPE, ["id", "loc"], self.memory // 2, self.work,
                            "control") as sorter:
            if p is not None:
                src = self.src.add(self.existing, "points")
                for a, b in p.chunks("points"):
                    pts = p.read("points", a, b)
                    self._check_existing("points", a, (pts["kind"] < 0)
                                         | (pts["kind"] > KIND_CHECK),
                                         lambda i: f"(id {pts['id'][i]}) unknown kind "
                                                   f"{pts['kind'][i]}")
                    sel = np.flatnonzero(pts["kind"] != KIND_PASS)
                    r = np.zeros(len(sel), CTRL_DTYPE)
                    r["id"] = pts["id"][sel]
                    r["kind"] = pts["kind"][sel]
                    r["control"] = pts["control"][sel]
                    r["sigma"] = pts["control_sigma"][sel]
                    r["loc"] = self.src.loc(src, a + sel)
                    # components a kind leaves open may be NaN in a project: 0, as in a file
                    loose = ~NEEDED[r["kind"]] & ~np.isfinite(r["control"])
                    r["control"][loose] = 0.0
                    r["sigma"][loose] = 0.0
                    ctrl = CONTROL_MASK[r["kind"]].astype(bool)
                    r["sigma"][~ctrl & ~np.isfinite(r["sigma"])] = 0.0
                    bad = np.zeros(b - a, bool)
                    bad[sel] = ~(np.isfinite(r["control"]).all(axis=1) & (
                        ~ctrl | ((r["sigma"] >= 0) & np.isfinite(r["sigma"]))).all(axis=1))
                    self._check_existing("points", a, bad, lambda i: (
                        f"(id {pts['id'][i]}) control or control_sigma is not finite or "
                        f"negative"))
                    sorter.add(r)
            for fpath in self.files["control"]:
                for rec, loc in self._read(CONTROL, fpath):
                    r = np.zeros(len(rec), CTRL_DTYPE)
                    r["id"] = rec["id"]
                    r["kind"] = rec["kind"]
                    r["control"] = np.stack([rec["X"], rec["Y"], rec["Z"]], axis=1)
                    r["sigma"] = np.stack([rec["sX"], rec["sY"], rec["sZ"]], axis=1)
                    r["loc"] = loc
                    self._control_to_frame(rec, r, loc)
                    sorter.add(r)
            last = None
            with open(path, "wb") as f:
                for c in sorter.sorted_chunks():
                    ids = c["id"]
                    same = np.empty(len(c), bool)
                    same[0] = last is not None and ids[0] == last["id"][0]
                    same[1:] = ids[1:] == ids[:-1]
                    dup = np.flatnonzero(same)
                    if len(dup):
                        prev = c[np.maximum(dup - 1, 0)]  # copies
                        if dup[0] == 0:
                            prev[0] = last[0]
                        cur = c[dup]
                        diff = np.stack([prev["kind"] != cur["kind"],
                                         (_bits(prev["control"]) != _bits(cur["control"]))
                                         .any(axis=1),
                                         (_bits(prev["sigma"]) != _bits(cur["sigma"]))
                                         .any(axis=1)], axis=1)
                        bad = np.flatnonzero(diff.any(axis=1))
                        if len(bad):
                            j = int(bad[0])
                            what = ("kind", "coordinates", "sigmas")[
                                int(np.flatnonzero(diff[j])[0])]
                            raise DataError(
                                f"control point {cur['id'][j]} is given twice with different "
                                f"values ({what}): {self.src.where(prev['loc'][j])} and "
                                f"{self.src.where(cur['loc'][j])}")
                        n_twice += len(dup)
                        for j in range(min(len(dup), EXAMPLES - len(examples))):
                            examples.append(f"point {cur['id'][j]} "
                                            f"({self.src.where(prev['loc'][j])}, "
                                            f"{self.src.where(cur['loc'][j])})")
                    u = c[~same]
                    u.tofile(f)
                    for k, n in zip(*np.unique(u["kind"], return_counts=True)):
                        counts[int(k)] += int(n)
                    last = c[-1:].copy()
        if n_twice:
            self._warn(f"{n_twice} control point(s) given more than once with identical values "
                       f"were loaded once: {', '.join(examples)}")
        self.s["control_loaded_twice"] = n_twice
        # ground height: mean known Z of the control, summed in id order in fixed pieces
        total, n = 0.0, 0
        for piece in self._control_pieces(_SUM_PIECE):
            z = piece["control"][NEEDED[piece["kind"], 2], 2]
            total += float(np.sum(z))
            n += len(z)
        self.ground = total / n if n else None
        self.n_control = sum(counts.values())

    def _control_pieces(self, size):
        with open(self.control_path, "rb") as f:   # (no piece beyond the file)
            size = max(1, min(size, os.fstat(f.fileno()).st_size // CTRL_DTYPE.itemsize + 1))
            while True:
                c = np.fromfile(f, CTRL_DTYPE, size)
                if not len(c):
                    return
                yield c

    # -- image measurements (external sort) ----------------------------------------------
    def read_measurements(self, p, sorter):
        st_ids = self.stations["id"]
        if p is not None:
            src = self.src.add(self.existing, "observations")
            new_of_old = np.searchsorted(st_ids, self.old_station_ids)
            rejected, expected = 0, 0
            n_old, n_obs = len(self.old_station_ids), p.n_observations
            for a, b in p.chunks("points"):
                pts = p.read("points", a, b)
                tiles = expected + np.concatenate([[0], np.cumsum(pts["n_obs"][:-1])])
                self._check_existing("points", a, (pts["obs_start"] != tiles)
                                     | (pts["n_obs"] < 0) | (tiles + pts["n_obs"] > n_obs),
                                     lambda i: "obs_start/n_obs do not follow the "
                                               "observations grouped by point")
                o0 = expected
                o1 = expected = int(tiles[-1] + pts["n_obs"][-1])
                obs = p.read("observations", o0, o1)
                self._check_existing("observations", o0, (obs["station"] < 0)
                                     | (obs["station"] >= n_old),
                                     lambda i: f"station {obs['station'][i]} does not exist")
                self._check_existing("observations", o0, ~(np.isfinite(obs["x"])
                                                           & np.isfinite(obs["y"])
                                                           & (obs["sigma"] >= 0)
                                                           & np.isfinite(obs["sigma"])),
                                     lambda i: "x, y or sigma is not finite or sigma < 0")
                r = np.zeros(len(obs), MEAS_DTYPE)
                r["point"] = np.repeat(pts["id"], pts["n_obs"])
                r["station"] = new_of_old[obs["station"]]
                r["x"], r["y"], r["sigma"] = obs["x"], obs["y"], obs["sigma"]
                r["loc"] = self.src.loc(src, np.arange(o0, o1))
                rejected += int((obs["status"] == STATUS_REJECTED).sum())
                sorter.add(r)
            if rejected:
                self._warn(f"{rejected} rejected observation(s) of {self.existing} are active "
                           f"again (the text formats have no status)")

        def known_photo(rec):
            unknown = ~_member(st_ids, rec["photo"])
            return [(unknown, lambda i: f"photo {rec['photo'][i]} is not in the photos "
                                        f"file(s) (column 1)")]

        frames = read_image_frames(self.files.get("image_frames", ()), self.cameras["id"])
        self._camera_file_frames(frames)
        for path in self.files["measurements"]:
            for rec, loc in self._read(MEASUREMENTS, path, known_photo):
                k = np.searchsorted(st_ids, rec["photo"])
                r = np.empty(len(rec), MEAS_DTYPE)
                r["point"] = rec["point"]
                r["station"] = k
                r["x"], r["y"], r["sigma"] = frames.to_mm(self.stations["camera"][k],
                                                          rec["x"], rec["y"], rec["sigma"])
                r["loc"] = loc
                sorter.add(r)

    def _camera_file_frames(self, frames):
        """The image frames given in the cameras file (columns 16-22) into ``frames``; a
        camera with a line in ``--image-frames`` too is an error naming both."""
        from .formats.text import FRAME_AXIS_WORDS, FRAME_ORIGIN_WORDS, FRAME_UNIT_WORDS

        words = [{v: k for k, v in w.items()} for w in (FRAME_UNIT_WORDS, FRAME_ORIGIN_WORDS,
                                                        FRAME_AXIS_WORDS)]
        cam_ids = self.cameras["id"]
        for cid, r, loc in getattr(self, "camera_frames", ()):
            j = int(np.searchsorted(cam_ids, cid))
            where = self.src.where(loc)
            if j in frames.given:
                raise DataError(f"{where}: camera {cid}'s image frame is given here and in "
                                f"--image-frames ({frames.given[j]}): give it once")
            unit, origin, axis = (words[0][int(r["frame"])], words[1][int(r["origin"])],
                                  words[2][int(r["y_axis"])])
            set_frame(frames, j, unit, r["pixel_x"], r["pixel_y"], r["frame_width"],
                      r["frame_height"], origin, axis, where, zero_ok=True)

    # -- the merge-join ------------------------------------------------------------------
    def _point_blocks(self, chunks):
        """Blocks of whole points (every record of a point id in one block) of about
        ``block_records`` records from the sorted measurement stream."""
        limit = self.block_records
        pending, n, threshold = [], 0, limit
        for c in chunks:
            pos = 0
            while pos < len(c):
                k = min(len(c) - pos, max(threshold - n, 1))
                pending.append(c[pos:pos + k])
                n += k
                pos += k
                if n >= threshold:
                    buf = np.concatenate(pending) if len(pending) > 1 else pending[0]
                    cut = int(np.searchsorted(buf["point"], buf["point"][-1], "left"))
                    if cut == 0:  # a single point fills the block: keep collecting
                        pending, threshold = [buf], n + limit
                        continue
                    yield buf[:cut]
                    pending, n, threshold = [buf[cut:]], len(buf) - cut, limit
        if n:
            yield np.concatenate(pending) if len(pending) > 1 else pending[0]

    @staticmethod
    def _join(obs_blocks, ctrl_blocks):
        """Pairs (observations, control records) covering the same range of point ids."""
        empty_o, empty_c = np.zeros(0, MEAS_DTYPE), np.zeros(0, CTRL_DTYPE)
        o, c = next(obs_blocks, None), next(ctrl_blocks, None)
        while o is not None or c is not None:
            if o is None:
                yield empty_o, c
                c = next(ctrl_blocks, None)
            elif c is None:
                yield o, empty_c
                o = next(obs_blocks, None)
            elif o["point"][-1] <= c["id"][-1]:
                k = int(np.searchsorted(c["id"], o["point"][-1], "right"))
                yield o, c[:k]
                c = c[k:] if k < len(c) else next(ctrl_blocks, None)
                o = next(obs_blocks, None)
            else:
                k = int(np.searchsorted(o["point"], c["id"][-1], "right"))
                yield o[:k], c
                o = o[k:] if k < len(o) else next(obs_blocks, None)
                c = next(ctrl_blocks, None)

    def _merge_duplicates(self, o):
        """Observations with every (point, station) pair once: duplicates averaged."""
        n = len(o)
        if n == 0:
            return o
        new = np.empty(n, bool)
        new[0] = True
        new[1:] = (o["point"][1:] != o["point"][:-1]) | (o["station"][1:] != o["station"][:-1])
        g = np.flatnonzero(new)
        if len(g) == n:
            return o
        sizes = np.diff(np.append(g, n))
        gid = np.cumsum(new) - 1
        dup_g = np.flatnonzero(sizes > 1)
        members = np.flatnonzero(sizes[gid] > 1)
        sub = o[members]
        sub = sub[np.lexsort((sub["loc"], sub["sigma"], sub["y"], sub["x"], gid[members]))]
        starts = np.flatnonzero(np.concatenate([[True], sub["point"][1:] != sub["point"][:-1]])
                                | np.concatenate([[True], sub["station"][1:]
                                                  != sub["station"][:-1]]))
        sz = np.diff(np.append(starts, len(sub)))
        xs, ys, sig = sub["x"][starts].copy(), sub["y"][starts].copy(), sub["sigma"][starts].copy()
        for k in range(1, int(sz.max())):  # sequential sums in sorted value order
            m = sz > k
            xs[m] += sub["x"][starts[m] + k]
            ys[m] += sub["y"][starts[m] + k]
            sig[m] = np.maximum(sig[m], sub["sigma"][starts[m] + k])
        spread = np.maximum(
            np.maximum.reduceat(sub["x"], starts) - np.minimum.reduceat(sub["x"], starts),
            np.maximum.reduceat(sub["y"], starts) - np.minimum.reduceat(sub["y"], starts))
        if not self.merge_all:
            self._refuse_conflicts(sub, starts, sz, spread)
        out = o[g]  # a copy
        out["x"][dup_g] = xs / sz
        out["y"][dup_g] = ys / sz
        out["sigma"][dup_g] = sig
        out["loc"][dup_g] = sub["loc"][starts]
        s = self.s
        s["duplicate_observations"] += int(len(sub) - len(starts))
        s["duplicate_max_um"] = max(s["duplicate_max_um"], float(spread.max()) * 1000.0)
        st_ids = self.stations["id"]
        for j in range(min(len(starts), EXAMPLES - len(self.dup_examples))):
            a, k = int(starts[j]), int(sz[j])
            where = ", ".join(self.src.where(v) for v in sub["loc"][a:a + min(k, 3)])
            more = ", ..." if k > 3 else ""
            self.dup_examples.append(f"point {sub['point'][a]} on photo "
                                     f"{st_ids[sub['station'][a]]} ({where}{more})")
        return out

    def _refuse_conflicts(self, sub, starts, sz, spread):
        """Duplicates further apart than 3 sigma (their larger sigma, else the camera's) are
        not one measurement: the first such pair is an error naming both lines."""
        sig = np.maximum.reduceat(sub["sigma"], starts)
        cam_sig = self.cameras["sigma_image"][self.stations["camera"][sub["station"][starts]]]
        sig = np.where(sig > 0, sig, cam_sig)
        bad = np.flatnonzero(spread > 3.0 * sig)
        if not len(bad):
            return
        j = int(bad[0])
        a, k = int(starts[j]), int(sz[j])
        grp = sub[a:a + k]
        d = np.hypot(grp["x"][:, None] - grp["x"][None, :], grp["y"][:, None] - grp["y"][None, :])
        i1, i2 = np.unravel_index(int(np.argmax(d)), d.shape)
        raise DataError(
            f"{self.src.where(grp['loc'][i1])} and {self.src.where(grp['loc'][i2])}: point "
            f"{grp['point'][i1]} is measured twice on photo "
            f"{self.stations['id'][grp['station'][i1]]}, {d[i1, i2] * 1000.0:.1f} um apart "
            f"(more than 3 sigma, {3000.0 * sig[j]:.1f} um): correct or remove one, or give "
            f"--merge-duplicates to average them")

    def _assemble(self, o, ctl, point_base):
        """Point and observation records of one block of point ids."""
        o = self._merge_duplicates(o)
        n_o = len(o)
        if n_o:
            first = np.concatenate([[True], o["point"][1:] != o["point"][:-1]])
            o_starts = np.flatnonzero(first)
            o_ids = o["point"][o_starts]
            o_counts = np.diff(np.append(o_starts, n_o))
        else:
            o_starts = o_ids = o_counts = np.zeros(0, np.int64)
        ids = np.union1d(o_ids, ctl["id"]) if len(ctl) else o_ids
        n = len(ids)
        pts = np.zeros(n, POINT_DTYPE)
        pts["id"] = ids
        pts["status"] = STATUS_ACTIVE
        pts["station_min"] = -1
        pts["station_max"] = -1
        at_o = np.searchsorted(ids, o_ids)
        counts = np.zeros(n, np.int64)
        counts[at_o] = o_counts
        pts["n_obs"] = counts
        starts = np.zeros(n, np.int64)
        np.cumsum(counts[:-1], out=starts[1:])
        pts["obs_start"] = starts
        kind = np.zeros(n, np.int8)
        raw = np.zeros(n, bool)
        if len(ctl):
            at_c = np.searchsorted(ids, ctl["id"])
            kind[at_c] = ctl["kind"]
            pts["control"][at_c] = ctl["control"]
            pts["control_sigma"][at_c] = ctl["sigma"]
            raw[at_c] = ctl["raw"] != 0
        pts["kind"] = kind
        control = pts["control"]

        # approximate coordinates: intersection of the rays from the approximate stations
        xyz = np.zeros((n, 3))
        ok = np.zeros(n, np.bool_)
        station = np.ascontiguousarray(o["station"])
        xy = np.ascontiguousarray(np.stack([o["x"], o["y"]], axis=1)) if n_o else np.zeros((0, 2))
        if n_o:
            intersect_points(starts, counts, station, xy, self.eo, self.cam_of_station,
                             self.cams, xyz, ok)
            ok &= np.isfinite(xyz).all(axis=1)
        # one ray (or parallel rays): a point on the first ray at the ground height (a
        # vertical control point: at its known height)
        ray = np.flatnonzero(~ok & (counts > 0))
        if len(ray):
            first_obs = starts[ray]
            s = station[first_obs]
            c = self.cam_of_station[s]
            height = np.full(len(ray), np.nan if self.ground is None else self.ground)
            vert = (kind[ray] == KIND_VERTICAL) & ~raw[ray]
            height[vert] = control[ray[vert], 2]
            ideal = np.empty((len(ray), 2))
            undistort_points(np.ascontiguousarray(xy[first_obs]), c, self.cams, ideal)
            xyz[ray] = ray_points(self.eo[s], ideal, self.cams[c, 0], height,
                                  self.ray_distance, self.sphere)
        none = counts == 0
        xyz[none] = self.no_ray_xyz
        # known components replace the approximations (no rays: check points too); control
        # given in a CRS as horizontal or vertical: into the frame at the approximate point
        bad = ~np.isfinite(xyz).all(axis=1)
        xyz[bad] = self.no_ray_xyz
        if raw.any():
            control = pts["control"] = self._partial_control(control, kind, raw, xyz)
        known = CONTROL_MASK[kind].astype(bool)
        known[none] = NEEDED[kind[none]]
        known[raw] = False
        xyz = np.where(known, control, xyz)
        bad = ~np.isfinite(xyz).all(axis=1)
        xyz[bad] = self.no_ray_xyz
        pts["xyz"] = xyz

        ob = np.zeros(n_o, OBSERVATION_DTYPE)
        ob["point"] = point_base + np.repeat(np.arange(n), counts)
        ob["station"] = o["station"]
        ob["x"] = o["x"]
        ob["y"] = o["y"]
        ob["sigma"] = o["sigma"]
        ob["status"] = STATUS_ACTIVE

        # statistics
        s = self.s
        for k in KIND_NAMES:
            s["kinds"][k] += int((kind == k).sum())
        lonely = ids[(kind != KIND_PASS) & none]
        s["control_without_measurements"] += len(lonely)
        self.lonely_ids.extend(lonely[:LISTED - len(self.lonely_ids)].tolist())
        s["single_ray_points"] += int((counts == 1).sum())
        s["unintersected_points"] += int((~ok & (counts > 1)).sum())
        if n_o:
            self.obs_per_station += np.bincount(station, minlength=len(self.eo))
        return pts, ob

    # -- the whole import ----------------------------------------------------------------
    def run(self):
        s = self.s
        s.update(duplicate_observations=0, duplicate_max_um=0.0, control_without_measurements=0,
                 single_ray_points=0, unintersected_points=0,
                 kinds=dict.fromkeys(KIND_NAMES, 0))
        self.dup_examples, self.lonely_ids = [], []
        attrs = {}
        entry = {"command": "import", "angles": self.angles, "rotation": self.rotation,
                 "axis_order": self.axis_order,
                 "append": bool(self.existing),
                 "crs": None if self.crs is None else self.crs.to_string(),
                 "orientation": self.orientation,
                 "files": {k: [str(f) for f in v] for k, v in self.files.items()}}
        with contextlib.ExitStack() as stack:
            p = stack.enter_context(Project(self.existing)) if self.existing else None
            self.read_cameras(p)
            self.read_photos(p)
            st = self.stations
            self.eo = np.ascontiguousarray(st["eo"])
            self.cam_of_station = st["camera"].astype(np.int64)
            self.cams = camera_array(self.cameras)
            self.read_control(p)
            sorter = ExternalSorter(MEAS_DTYPE, ["point", "station"], self.memory // 2,
                                    self.work, "observations")
            stack.enter_context(sorter)
            self.read_measurements(p, sorter)
            priors = self.read_priors(p, st)
            if p is not None:
                dropped = [n for n, has in (("/truth", p.has_truth),
                                            ("/solution", p.has_solution)) if has]
                if dropped:
                    self._warn(f"{self.existing}: {' and '.join(dropped)} no longer match the "
                               f"records and were dropped")
                history = p.attr("history", "[]")
                p.close()  # everything is read: OUT is replaced below
            else:
                history = "[]"
            attrs["history"] = append_history(history, entry)
            attrs.update(self.frame.to_attrs())
            if sorter.count == 0:
                raise DataError("the block has no image measurement (--measurements)")

            # ground height and fall-backs for points that cannot be intersected
            z_st = float(np.mean(st["eo"][:, 5]))
            if self.ground is not None and z_st - self.ground > 0:
                self.ray_distance = z_st - self.ground
            else:
                self.ray_distance = DEFAULT_RAY_DISTANCE
            ground = self.ground if self.ground is not None else z_st - self.ray_distance
            self.no_ray_xyz = np.array([float(np.mean(st["eo"][:, 3])),
                                        float(np.mean(st["eo"][:, 4])), ground])
            self.sphere = MOON_RADIUS if self.frame.kind == SELENOCENTRIC else None
            if self.sphere:  # points without rays: on the sphere below the stations' mean
                c = np.mean(st["eo"][:, 3:], axis=0)
                n = float(np.linalg.norm(c))
                self.no_ray_xyz = c * (MOON_RADIUS / n) if n > 0 else np.zeros(3)
                self.ray_distance = max(float(np.mean(np.linalg.norm(st["eo"][:, 3:], axis=1)))
                                        - MOON_RADIUS, 1.0)
            self.obs_per_station = np.zeros(len(st), np.int64)

            def named(kind):   # (the files a record set comes from, for check_records)
                return ", ".join(str(f) for f in self.files[kind]) or kind

            check_records(named("cameras"), cameras=self.cameras)
            check_records(named("photos") if self.files["photos"] else named("photos_matrix"),
                          stations=st)
            with ProjectWriter(self.out, attrs) as w:
                w.append("cameras", self.cameras)
                w.append("stations", st)
                w.append("station_priors", priors)
                ctrl_blocks = self._control_pieces(max(4096, self.memory // (64 * 72)))
                for o, ctl in self._join(self._point_blocks(sorter.sorted_chunks()),
                                         ctrl_blocks):
                    pts, ob = self._assemble(o, ctl, w.size("points"))
                    pts["obs_start"] += w.size("observations")
                    check_records(named("measurements"), points=pts)
                    check_records(named("measurements"), observations=ob,
                                  start=w.size("observations"))
                    w.append("points", pts)
                    w.append("observations", ob)
                n_points, n_obs = w.size("points"), w.size("observations")
                w.finish()

        # warnings and summary
        if s["duplicate_observations"]:
            self._warn(f"{s['duplicate_observations']} duplicate image measurement(s) merged "
                       f"(the same point measured more than once on one photo; coordinates "
                       f"averaged, largest difference {s['duplicate_max_um']:.1f} um): "
                       f"{', '.join(self.dup_examples)}")
        if s["control_without_measurements"]:
            n = s["control_without_measurements"]
            more = ", ..." if n > len(self.lonely_ids) else ""
            self._warn(f"{n} control or check point(s) have no image measurement (kept with "
                       f"n_obs 0): ids {_ids(self.lonely_ids)}{more}")
        empty = st["id"][self.obs_per_station == 0]
        if len(empty):
            self._warn(f"{len(empty)} photo(s) have no image measurement: ids {_ids(empty)}")
        kinds = {KIND_NAMES[k]: v for k, v in s["kinds"].items()}
        return {
            "path": str(self.out),
            "appended": bool(self.existing),
            "cameras": len(self.cameras),
            "photos": len(st),
            "points": n_points,
            "points_by_kind": kinds,
            "observations": n_obs,
            "station_priors": len(priors),
            "lines": self.lines,
            "bytes": self.bytes,
            "duplicate_observations": s["duplicate_observations"],
            "duplicate_max_um": s["duplicate_max_um"],
            "duplicate_examples": list(self.dup_examples),
            "photos_loaded_twice": s["photos_loaded_twice"],
            "cameras_loaded_twice": s["cameras_loaded_twice"],
            "control_loaded_twice": s["control_loaded_twice"],
            "control_without_measurements": s["control_without_measurements"],
            "photos_without_measurements": int(len(empty)),
            "single_ray_points": s["single_ray_points"],
            "unintersected_points": s["unintersected_points"],
            "warnings": list(self.warnings),
        }


#: ``--image-frames``: where a unit, origin and y axis put the image centre, in the unit's
#: coordinates with y up (multiples of the width and height).
IMAGE_ORIGINS = {"centre": (0.0, 0.0), "topleft": (-0.5, 0.5), "bottomleft": (-0.5, -0.5)}
IMAGE_UNITS = ("mm", "px")


class ImageFrames:
    """Per camera (by record), how its photos' measurements are turned into sapgo's
    millimetres from the image centre with y up: ``x = (u + ox) * sx``, ``y = (fy v + oy) *
    sy``, ``sigma * ss`` (the identity for cameras without a line)."""

    def __init__(self, n):
        self.sx, self.sy, self.ss = np.ones(n), np.ones(n), np.ones(n)
        self.ox, self.oy, self.fy = np.zeros(n), np.zeros(n), np.ones(n)
        self.given = {}   # camera record -> where its frame was given

    def to_mm(self, cam, x, y, sigma):
        return ((x + self.ox[cam]) * self.sx[cam],
                (self.fy[cam] * y + self.oy[cam]) * self.sy[cam], sigma * self.ss[cam])


#: An image frame's pixel sizes (um) and image sizes (px or mm) are at most this.
MAX_FRAME_VALUE = 1e9


def set_frame(frames, j, unit, px, py, w, h, origin, axis, where, zero_ok=False):
    """Camera record ``j``'s image frame into ``frames``: ``unit`` mm or px, pixel sizes
    ``px``, ``py`` (um; ``-`` or, with ``zero_ok``, 0 for mm), ``w``, ``h`` the image's size
    in the unit (not needed with origin ``centre``), ``origin`` and y ``axis``; bad values
    an error at ``where``."""
    def number(tok, name, needed):
        if (tok == "-" or (zero_ok and not isinstance(tok, str) and float(tok) == 0.0)) \
                and not needed:
            return None
        try:
            v = float(tok)
        except ValueError:
            v = float("nan")
        if not (np.isfinite(v) and 0 < v <= MAX_FRAME_VALUE):
            raise DataError(f"{where}: {name} {repr(tok) if isinstance(tok, str) else f'{v:g}'} "
                            f"must be a positive number" + ("" if needed else
                                                            " or '-'" if not zero_ok
                                                            else " or 0")
                            + (f" (at most {MAX_FRAME_VALUE:g})" if v > MAX_FRAME_VALUE
                               else ""))
        return v

    px = number(px, "pixel_x", unit == "px")
    py = number(py, "pixel_y", unit == "px")
    w = number(w, "width", origin != "centre")
    h = number(h, "height", origin != "centre")
    cx, cy = IMAGE_ORIGINS[origin]
    frames.ox[j] = cx * (w or 0.0)
    frames.oy[j] = cy * (h or 0.0)
    frames.fy[j] = -1.0 if axis == "down" else 1.0
    if unit == "px":
        frames.sx[j], frames.sy[j] = px / 1000.0, py / 1000.0
        frames.ss[j] = np.sqrt(px * py) / 1000.0
    frames.given[j] = where


def camera_lines(paths, cam_ids, usage, ncols):
    """The lines of per-camera files (``--image-frames``, ``--additional-parameters``):
    yields ``(where, tokens, camera)`` for each line that is not blank or a comment, with
    ``camera`` the id's place in ``cam_ids`` (any of its records); a line of fewer than
    ``ncols[0]`` or more than ``ncols[1]`` columns, a camera not in ``cam_ids`` or given
    twice is an error naming the file and line (``usage``: the columns, for the message)."""
    seen = {}
    for path in paths:
        with open_input(path) as f:
            data = f.read()
        lines = decode_text(path, data).splitlines()   # (as the column files)
        for k, line in enumerate(lines, start=1):
            t = line.split("#", 1)[0].split()
            if not t:
                continue
            where = f"{path}:{k}"
            if not ncols[0] <= len(t) <= ncols[1]:
                raise DataError(f"{where}: expected {usage}, got {len(t)} column(s)")
            try:
                cid = int(t[0])
            except ValueError:
                raise DataError(f"{where}: camera {t[0]!r} is not an id") from None
            hit = np.flatnonzero(cam_ids == cid)
            if not len(hit):
                raise DataError(f"{where}: camera {cid} is not in the cameras file(s)")
            if cid in seen:
                raise DataError(f"{where}: camera {cid} has a line already ({seen[cid]})")
            seen[cid] = where
            yield where, t, int(hit[0])


#: The /cameras fields of the additional-parameter sets (``--additional-parameters``).
AP_FIELDS = ("ap_set", "ap_base") + AP_NAMES


def read_additional_parameters(paths, cams):
    """The ``--additional-parameters`` files onto the camera records ``cams`` (in place,
    every record of a camera's id): one line per camera ``camera set base [a1 ... aN]``,
    ``set`` one of :data:`sapgo.apsets.AP_SETS` (``none`` takes a camera's set away),
    ``base`` the grid's half-width in mm or ``auto`` (0.4 times the larger side of the
    camera's format, the photo base at 60 % overlap), then up to N coefficients in mm (12
    for ``ebner``, 44 for ``gruen``; the rest 0). Errors name the file and line."""
    from .apsets import AP_SETS, DEFAULT_BASE_FRACTION, N_TERMS

    usage = f"camera set base [a1 ... aN] (set one of {', '.join(AP_SETS)})"
    for where, t, _ in camera_lines(paths, cams["id"], usage, (3, 3 + len(AP_NAMES))):
        cid = int(t[0])
        rows = np.flatnonzero(cams["id"] == cid)
        if t[1].lower() not in AP_SETS:
            raise DataError(f"{where}: additional-parameter set {t[1]!r}: one of "
                            f"{', '.join(AP_SETS)}")
        s = AP_SETS.index(t[1].lower())
        n = int(N_TERMS[s])
        if len(t) > 3 + n:
            raise DataError(f"{where}: the {AP_SETS[s]} set has {n} coefficient(s), "
                            f"got {len(t) - 3}")
        if t[2].lower() == "auto":
            side = float(max(cams["format_x"][rows[0]], cams["format_y"][rows[0]]))
            base = DEFAULT_BASE_FRACTION * side
            if s and not base > 0:
                raise DataError(f"{where}: base auto needs camera {cid}'s format "
                                f"(format_x, format_y in the cameras file); give the "
                                f"base in mm")
        else:
            try:
                base = float(t[2])
            except ValueError:
                base = float("nan")
            if s and not (np.isfinite(base) and base > 0):
                raise DataError(f"{where}: base {t[2]!r} must be a positive number (mm) "
                                f"or auto")
        coef = np.zeros(len(AP_NAMES))
        for j, tok in enumerate(t[3:]):
            try:
                coef[j] = float(tok)
            except ValueError:
                coef[j] = float("nan")
            if not np.isfinite(coef[j]):
                raise DataError(f"{where}: a{j + 1} {tok!r} is not a finite number")
        cams["ap_set"][rows] = s
        cams["ap_base"][rows] = base if s else 0.0
        for j, name in enumerate(AP_NAMES):
            cams[name][rows] = coef[j]


def read_image_frames(paths, cam_ids):
    """The ``--image-frames`` files: one line per camera ``camera unit pixel_x pixel_y width
    height origin y_axis`` (unit ``mm`` or ``px``; pixel sizes in micrometres, ``-`` for mm;
    width and height in the unit, ``-`` allowed with origin ``centre``; origin ``centre``,
    ``topleft`` or ``bottomleft``, the image's corner itself, not a pixel's centre; y axis
    ``up`` or ``down``). Returns :class:`ImageFrames` over the cameras' records. Errors
    name the file and line."""
    frames = ImageFrames(len(cam_ids))
    usage = "8 columns (camera unit pixel_x pixel_y width height origin y_axis)"
    for where, t, j in camera_lines(paths, np.asarray(cam_ids), usage, (8, 8)):
        unit, origin, axis = t[1], t[6], t[7]
        if unit not in IMAGE_UNITS:
            raise DataError(f"{where}: unit {unit!r}: mm or px")
        if origin not in IMAGE_ORIGINS:
            raise DataError(f"{where}: origin {origin!r}: one of "
                            f"{', '.join(IMAGE_ORIGINS)}")
        if axis not in ("up", "down"):
            raise DataError(f"{where}: y axis {axis!r}: up or down")

        set_frame(frames, j, unit, t[2], t[3], t[4], t[5], origin, axis, where)
    return frames


@writes_project("import", "out")
def import_text(out, cameras=(), photos=(), measurements=(), control=(), angles="deg",
                memory=None, append=False, force=False, priors=(), prior_covariances=(),
                crs=None, orientation="tangent", photos_matrix=(), rotation="opk",
                image_frames=(), axis_order="en", merge_duplicates=False,
                additional_parameters=()):
    """Import a block from text files into the project ``out``; returns a summary dict.

    The same point measured more than once on one photo is merged (averaged, with a
    warning) when the measurements agree within 3 sigma; measurements further apart are an
    error naming their lines, unless ``merge_duplicates`` (``--merge-duplicates``).

    ``cameras``, ``photos``, ``measurements``, ``control``, ``priors`` (exposure-station
    priors with a sigma per parameter) and ``prior_covariances`` (with a full 6x6
    covariance) are paths or lists of paths (several files of a kind are read as one).
    ``angles``: the unit of the photos' and priors' omega, phi, kappa (``"deg"``, ``"gon"``
    or ``"rad"``). ``rotation``: the order of those three angles in the photos' and
    priors' columns and how they compose (:data:`sapgo.frames.ROTATION_ORDERS`: ``"opk"``
    omega-phi-kappa, ``"pok"`` phi-omega-kappa, ``"kpo"`` kappa-phi-omega; the priors'
    angle sigmas or covariances in the same order). ``crs``: the coordinate reference system of the photos' and control's
    X, Y, Z (EPSG or IAU code, WKT, PROJ string; default none: a local frame), in which case
    the block is computed in the local tangent frame at its centre (Earth) or in the
    selenocentric frame (Moon) and ``orientation`` says how omega, phi, kappa are given:
    ``"tangent"`` (to the local east-north-up frame at each station) or ``"geocentric"``
    (to the body-fixed axes); see :mod:`sapgo.frames`. ``photos_matrix``: photos files whose
    orientation is a rotation matrix (object to image, row by row; relative to the same axes)
    instead of three angles. ``image_frames``: files giving, per camera, the unit, origin
    and y axis of its photos' image measurements (:func:`read_image_frames`; cameras not
    listed: mm from the image centre, y up). ``additional_parameters``: files giving
    cameras an additional-parameter set, Ebner's 12 or Gruen's 44, with its base and
    coefficients (:func:`read_additional_parameters`). ``axis_order``: ``"en"`` (X, the easting or
    longitude, first; the default) or ``"ne"`` (the northing or latitude first) in the
    photos, control and priors files (:data:`sapgo.formats.text.AXIS_ORDERS`); with a
    geographic ``crs`` their X and Y may be written in degrees, minutes and seconds, as may
    the angles with ``angles`` "deg" (:func:`sapgo.formats.text.dms_degrees`). ``memory``:
    the budget of the sorting phases (bytes or ``"512M"``; default
    :data:`sapgo.extsort.DEFAULT_MEMORY`).

    If ``out`` exists, ``force=True`` replaces it and ``append=True`` adds the files to it:
    its records are read back and combined with the files as if all had been imported
    together (its cameras, photos and control count as loaded before: identical repeats are
    fine, different values are an error). Its station priors are kept; ``/truth`` and
    ``/solution`` are dropped with a warning.

    Errors (:class:`~sapgo.errors.DataError`, :class:`~sapgo.errors.ParameterError`) are one
    line naming the file and line. The summary dict counts cameras, photos, points (by kind),
    observations, merged duplicates, photos/cameras/control loaded twice and control points
    without measurements, and lists the ``warnings``.
    """
    t0 = time.perf_counter()
    check_angles(angles)
    _check_order(rotation)
    if orientation not in ORIENTATIONS:
        raise ParameterError(f"orientation {orientation!r}: one of {', '.join(ORIENTATIONS)}")
    memory = DEFAULT_MEMORY if memory is None else parse_memory(memory)
    out = Path(out)
    files = {"cameras": _as_list(cameras), "photos": _as_list(photos),
             "photos_matrix": _as_list(photos_matrix),
             "measurements": _as_list(measurements), "control": _as_list(control),
             "priors": _as_list(priors), "prior_covariances": _as_list(prior_covariances),
             "image_frames": _as_list(image_frames),
             "additional_parameters": _as_list(additional_parameters)}
    if append and force:
        raise ParameterError("--append and --force exclude each other: --append adds the files "
                             "to the project, --force replaces it")
    if out.is_dir():
        raise ParameterError(f"{out}: is a directory")
    exists = out.exists()
    if exists and not (append or force):
        raise ParameterError(f"{out} exists: use --append to add the files to it or --force "
                             f"to replace it")
    if not (append and exists):
        for kind in ("cameras", "photos", "measurements"):
            if not files[kind] and not (kind == "photos" and files["photos_matrix"]):
                raise ParameterError(f"no {kind} file given (--{kind})")
    elif not any(files.values()):
        raise ParameterError("nothing to append: give --cameras, --photos, --measurements "
                             "or --control, --priors, --prior-covariances files")
    for kind, paths in files.items():
        for f in paths:
            f = Path(f)
            opt = "--" + kind.replace("_", "-")
            if not f.exists():
                raise ParameterError(f"{f}: no such file ({opt})")
            if f.is_dir():
                raise ParameterError(f"{f}: is a directory, not a {kind} file ({opt})")
    work = out.with_name(out.name + ".import.work")
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    try:
        imp = _Import(out, files, angles, memory, work,
                      out if (append and exists) else None, crs, orientation,
                      rotation, axis_order)
        imp.merge_all = bool(merge_duplicates)
        summary = imp.run()
    finally:
        shutil.rmtree(work, ignore_errors=True)
    summary["seconds"] = time.perf_counter() - t0
    summary["lines_per_second"] = summary["lines"] / max(summary["seconds"], 1e-9)
    return summary


class TextControl:
    """The control and check points of text ``control`` files (docs/formats.md), read exactly
    as :func:`import_text` reads them, for the importers of other formats (COLMAP models):
    the same parser and errors naming file and line, repeats loaded once or refused, and
    with ``crs`` the same conversion into the computation frame.

    ``records`` (:data:`CTRL_DTYPE`, sorted by id, each id once): ``kind``, ``control`` and
    ``sigma`` as the text import stores them, ``loc`` the place for :meth:`where`, ``raw``
    marking horizontal and vertical control still in the CRS (:meth:`partial` converts them
    once the points' approximate positions are known). ``frame``: the local frame, or for a
    ``crs`` the frame at the centre of the control points (the block's photos are not in the
    CRS). ``work``: a scratch directory for the external sort (removed by the caller).
    """

    def __init__(self, paths, work, crs=None, memory=None):
        paths = _as_list(paths)
        for f in map(Path, paths):
            if not f.exists():
                raise ParameterError(f"{f}: no such file (--control)")
            if f.is_dir():
                raise ParameterError(f"{f}: is a directory, not a control file (--control)")
        memory = DEFAULT_MEMORY if memory is None else parse_memory(memory)
        files = dict.fromkeys(("cameras", "photos", "photos_matrix", "measurements",
                               "priors", "prior_covariances"), [])
        files["control"] = paths
        self._imp = imp = _Import(None, files, "deg", memory, Path(work), None, crs)
        if imp.crs is not None:  # the frame at the centre of the points known in X and Y
            xyz = []
            for path in paths:
                for first, chunk in read_chunks(path, imp.chunk_bytes):
                    rec, _ = parse_chunk(CONTROL, chunk, first, "deg", str(path))
                    keep = NEEDED[np.clip(rec["kind"], 0, KIND_CHECK), 1]
                    xyz.append(np.stack([rec["X"], rec["Y"], rec["Z"]], axis=1)[keep])
            xyz = np.concatenate(xyz) if xyz else np.zeros((0, 3))
            if not len(xyz):
                raise ParameterError(f"--crs {crs}: the control files have no point with "
                                     f"known X and Y to place the frame")
            imp.frame = Frame.for_crs(imp.crs, xyz)
        imp.read_control(None)
        pieces = list(imp._control_pieces(_SUM_PIECE))
        self.records = np.concatenate(pieces) if pieces else np.zeros(0, CTRL_DTYPE)
        self.frame = imp.frame
        self.crs = imp.crs
        self.warnings = imp.warnings
        self.loaded_twice = imp.s["control_loaded_twice"]

    def where(self, loc):
        """``file:line`` of a record's ``loc``."""
        return self._imp.src.where(loc)

    def partial(self, control, kind, raw, approx):
        """Frame coordinates of the ``raw`` (horizontal and vertical CRS) control, the
        unknown coordinates taken from the approximate points ``approx`` (as the text
        import does)."""
        return self._imp._partial_control(control, kind, raw, approx)


def summary_text(summary):
    """The one-paragraph summary ``sapgo import`` prints."""
    s = summary
    kinds = ", ".join(f"{n} {k}" for k, n in s["points_by_kind"].items() if n)
    verb = "appended to" if s["appended"] else "imported"
    extra = []
    if s["duplicate_observations"]:
        extra.append(f"{s['duplicate_observations']} duplicate measurement(s) merged")
    if s["station_priors"]:
        extra.append(f"{s['station_priors']} station prior(s) kept")
    tail = ("; " + "; ".join(extra)) if extra else ""
    return (f"{verb} {s['path']}: {s['cameras']} camera(s), {s['photos']} photo(s), "
            f"{s['points']} point(s) ({kinds or 'none'}), {s['observations']} image "
            f"observation(s){tail}; {s['lines']} line(s) read in {s['seconds']:.1f} s "
            f"({s['lines_per_second']:,.0f} lines/s)")
