"""The project file, ``project.h5``: SAPGO's direct-access record files as HDF5 datasets.

Each dataset holds fixed-length records addressed by record number, like SAPGO's DEFINE FILE
units (seeds/002, "Data storage"). After ordering, record number == logical number: station
record ``i`` is the ``i``-th station of the bandwidth-minimising order, points are sorted by
(min, max) logical station and observations are grouped by point in that order, so every phase
reads the files front to back in chunks.

Inputs (``/cameras``, ``/stations``, ``/station_priors``, ``/points``, ``/observations``) are
never written by an adjustment; results go to ``/solution``. No command writes a project in
place: new files are built by :class:`ProjectWriter` as ``PATH.tmp`` and renamed over ``PATH``,
and ``adjust`` writes its results into a copy. The band rows of the reduced normal equations
live in the run's work directory beside the project (see :mod:`sapgo.adjust`).

The schema, field by field, is documented in ``docs/project-schema.md``.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import uuid
from pathlib import Path

import h5py
import numpy as np

from . import __version__
from .errors import ClosedProjectError, DataError, ProjectFormatError
from .geometry import AP_NAMES, N_CAMERA

FORMAT_NAME = "sapgo project"
SCHEMA_VERSION = 1

#: Records per HDF5 chunk and per processing chunk.
CHUNK_RECORDS = 65536

#: HDF5's chunk cache of each dataset of an open project: room for a few of its chunks (at
#: most about 1 MB each), so that the passes that read records a few at a time (a block of
#: stations' points in the precision pass, a node's points on the tree) decode and checksum
#: each chunk once instead of once per read (HDF5's default, 1 MB, holds none of them).
CHUNK_CACHE = {"rdcc_nbytes": 4 << 20, "rdcc_nslots": 1021}

# Point kinds (``/points`` field ``kind``).
KIND_PASS = 0
KIND_CONTROL = 1  # full control: X, Y, Z
KIND_HORIZONTAL = 2  # horizontal control: X, Y
KIND_VERTICAL = 3  # vertical control: Z
KIND_CHECK = 4  # known on the ground, not used as control; compared in the report
KIND_NAMES = {
    KIND_PASS: "pass",
    KIND_CONTROL: "control",
    KIND_HORIZONTAL: "horizontal",
    KIND_VERTICAL: "vertical",
    KIND_CHECK: "check",
}
#: Which coordinate components each kind uses as control observations.
CONTROL_MASK = np.array(
    [[0, 0, 0], [1, 1, 1], [1, 1, 0], [0, 0, 1], [0, 0, 0]], dtype=np.int8
)

# Record status (``status`` field of stations, points and observations).
STATUS_ACTIVE = 0
STATUS_EXCLUDED = 1  # left out of the adjustment (undeterminable); kept in the project
STATUS_REJECTED = 2  # observation rejected by the user (or blunder detection); kept, never used

#: Provenance entries kept in the ``history`` attribute (the newest).
HISTORY_LIMIT = 100

EO_NAMES = ("omega", "phi", "kappa", "X", "Y", "Z")

CAMERA_DTYPE = np.dtype(
    [
        ("id", "<i8"),
        ("focal_length", "<f8"),  # mm
        ("x0", "<f8"),  # principal point, mm
        ("y0", "<f8"),
        ("format_x", "<f8"),  # image format, mm
        ("format_y", "<f8"),
        ("sigma_image", "<f8"),  # default image-coordinate standard error, mm
        ("k1", "<f8"),  # radial distortion (Brown), mm^-2, mm^-4, mm^-6
        ("k2", "<f8"),
        ("k3", "<f8"),
        ("p1", "<f8"),  # decentring distortion (Brown), mm^-1
        ("p2", "<f8"),
        ("b1", "<f8"),  # affinity and shear of the image axes (dimensionless)
        ("b2", "<f8"),
        # the distortion model: 0 forward (added to the ideal point), 1 backward
        # (correcting the measured one; sapgo.geometry)
        ("distortion_model", "<i8"),
        # the additional-parameter set (0 none, 1 Ebner's 12, 2 Gruen's 44; sapgo.apsets),
        # its base (mm) and its coefficients (mm; a set of 12 uses a1 .. a12)
        ("ap_set", "<i8"),
        ("ap_base", "<f8"),
    ]
    + [(name, "<f8") for name in AP_NAMES]
)



def camera_record(*values):
    """A /cameras record of its first fields' values in :data:`CAMERA_DTYPE` order (id,
    focal_length, x0, y0, ...); the fields after them 0."""
    rec = np.zeros((), CAMERA_DTYPE)
    for name, v in zip(CAMERA_DTYPE.names, values):
        rec[name] = v
    return rec


STATION_DTYPE = np.dtype(
    [
        ("id", "<i8"),
        ("camera", "<i4"),  # record index into /cameras
        ("strip", "<i4"),  # flight line number (-1 if unknown)
        ("status", "i1"),
        ("eo", "<f8", (6,)),  # approximate omega, phi, kappa (rad), X, Y, Z (m)
    ]
)

PRIOR_DTYPE = np.dtype(
    [
        ("station", "<i8"),  # record index into /stations
        ("value", "<f8", (6,)),  # observed omega, phi, kappa (rad), X, Y, Z (m)
        ("weight", "<f8", (6, 6)),  # weight matrix, units 1/rad^2, 1/m^2
    ]
)

POINT_DTYPE = np.dtype(
    [
        ("id", "<i8"),
        ("kind", "i1"),
        ("status", "i1"),
        ("xyz", "<f8", (3,)),  # approximate X, Y, Z (m)
        ("control", "<f8", (3,)),  # known X, Y, Z (m) for control and check points
        ("control_sigma", "<f8", (3,)),  # standard error of the control (m); 0 = fixed
        ("obs_start", "<i8"),  # first record in /observations
        ("n_obs", "<i4"),  # number of records in /observations
        ("station_min", "<i8"),  # smallest / largest station record of its active rays
        ("station_max", "<i8"),
    ]
)

OBSERVATION_DTYPE = np.dtype(
    [
        ("point", "<i8"),  # record index into /points
        ("station", "<i8"),  # record index into /stations
        ("x", "<f8"),  # image coordinates, mm
        ("y", "<f8"),
        ("sigma", "<f8"),  # standard error of x and y, mm; 0 = the camera's sigma_image
        ("status", "i1"),
    ]
)

TRUTH_STATION_DTYPE = np.dtype([("id", "<i8"), ("eo", "<f8", (6,))])
TRUTH_POINT_DTYPE = np.dtype([("id", "<i8"), ("xyz", "<f8", (3,))])

RECORD_DTYPES = {
    "cameras": CAMERA_DTYPE,
    "stations": STATION_DTYPE,
    "station_priors": PRIOR_DTYPE,
    "points": POINT_DTYPE,
    "observations": OBSERVATION_DTYPE,
}
#: A planted blunder: the observation of point ``point_id`` on photo ``station_id`` (ids,
#: stable across ordering) moved by (dx, dy) mm.
#: Earlier layouts of record datasets that are still read (the fields they lack read as
#: zeros): /cameras before affinity, shear and the distortion model (b1, b2,
#: distortion_model), and before the additional-parameter sets (ap_set, ap_base, a1 ..
#: a44; :meth:`Project.cameras`).
OLDER_DTYPES = {"cameras": (np.dtype(CAMERA_DTYPE.descr[:12]),
                            np.dtype(CAMERA_DTYPE.descr[:15]))}
TRUTH_BLUNDER_DTYPE = np.dtype([("station_id", "<i8"), ("point_id", "<i8"), ("dx", "<f8"),
                                ("dy", "<f8")])
TRUTH_DTYPES = {"truth/stations": TRUTH_STATION_DTYPE, "truth/points": TRUTH_POINT_DTYPE,
                "truth/blunders": TRUTH_BLUNDER_DTYPE}
#: Truth datasets that files of older versions may lack.
TRUTH_OPTIONAL = {"truth/blunders"}

#: Result datasets in ``/solution`` (shape per record, dtype).
SOLUTION_LAYOUT = {
    "station_corr": ("stations", (6,)),  # total corrections to eo
    "point_corr": ("points", (3,)),  # total corrections to xyz
    "residuals": ("observations", (2,)),  # vx, vy (mm), adjusted minus observed
    "station_sigma": ("stations", (6,)),  # a-posteriori standard deviations (rad x3, m x3)
    "point_sigma": ("points", (3,)),  # a-posteriori standard deviations (m)
    # per observation r_x, r_y, r_xy, w_x, w_y, t, robust weight (quality.QUALITY_COLUMNS)
    "obs_quality": ("observations", (7,)),
    # corrections to the camera rows (geometry.CAMERA_FIELDS: f, x0, y0, k1, k2, k3, p1, p2,
    # b1, b2, model, ap_set, ap_base, a1 .. a44) by self-calibration or the photos' own
    # intrinsics; zeros otherwise (a file of an older version has the first 8 or 11: the
    # rest read as zeros)
    "camera_corr": ("cameras", (N_CAMERA,)),
    # per photo: the camera row it was adjusted with, as a correction to its camera's
    # /cameras record (its camera's camera_corr, plus its own parameters when calibrated
    # per photo); files of older versions lack it (read as zeros). Its first 11 columns
    # only (f .. model) when no camera has an additional-parameter set (46 doubles a photo
    # fewer; the rest read as zeros)
    "photo_camera_corr": ("stations", (N_CAMERA,)),
}
#: Optional groups of data that sapgo itself does not use, keyed by ids (not by record
#: numbers), kept for a format's export: ``/colmap`` (a COLMAP model's names, camera models,
#: 2D point indices, colours), ``/bundler`` (colours, keypoint indices), ``/opensfm``
#: (names, camera types and sizes, colours, feature ids; docs/project-schema.md).
#: ``sapgo order`` and ``adjust`` carry them over unchanged.
KEYED_GROUPS = ("colmap", "bundler", "opensfm")
#: Solution datasets that files of older versions may lack (read as zeros).
SOLUTION_OPTIONAL = {"station_sigma", "point_sigma", "obs_quality", "camera_corr",
                     "photo_camera_corr"}
#: Solution datasets that can be narrower (their widths then: the rest read as zeros,
#: :meth:`Project.solution`): files of older versions, and ``photo_camera_corr`` without
#: additional parameters (:data:`PHOTO_CAMERA_NARROW`).
SOLUTION_NARROWER = {"camera_corr": (8, 11), "photo_camera_corr": (11,)}
#: The width of ``photo_camera_corr`` when no camera has an additional-parameter set.
PHOTO_CAMERA_NARROW = 11
#: Solution datasets stored in single precision (the rest in double).
SOLUTION_SINGLE = {"obs_quality"}

#: Every record dataset is written with HDF5's Fletcher-32 checksum of each chunk: a
#: damaged chunk is found when read (:meth:`Project.read` names it) instead of being
#: adjusted as data.
CHECKSUM = {"fletcher32": True}


def solution_dataset(group, name, n, width=None):
    """Create the /solution dataset ``name`` for ``n`` records in ``group`` (zeros),
    ``width`` columns instead of its layout's (:data:`SOLUTION_NARROWER`)."""
    shape = SOLUTION_LAYOUT[name][1] if width is None else (width,)
    return group.create_dataset(
        name, shape=(n,) + shape, dtype="<f4" if name in SOLUTION_SINGLE else "<f8",
        chunks=(max(1, min(n, CHUNK_RECORDS)),) + shape, fillvalue=0.0, **CHECKSUM)


#: Bytes every writer leaves free beyond its estimate (HDF5's metadata, the chunk cache,
#: the commit's report): a write that would leave less is refused before it starts
#: (``SAPGO_DISK_MARGIN`` bytes instead: the tests fill a small disk for real with 0).
DISK_MARGIN = int(os.environ.get("SAPGO_DISK_MARGIN", 32 << 20))


def free_space(path):
    """``(folder, free bytes)`` of the filesystem of ``path`` (a file or folder; its nearest
    existing folder)."""
    import shutil as _sh

    folder = Path(os.path.abspath(path))
    while not folder.is_dir() and folder != folder.parent:
        folder = folder.parent
    return folder, _sh.disk_usage(folder).free


def ensure_free(path, need, what):
    """Refuse (:class:`~sapgo.errors.DiskFullError`, one line) to write ``need`` more bytes
    to the filesystem of ``path`` (a file or folder; its nearest existing folder) when fewer
    than ``need`` + :data:`DISK_MARGIN` are free. ``what``: what would be written."""
    from .errors import DiskFullError

    folder, free = free_space(path)
    if free < need + DISK_MARGIN:
        raise DiskFullError(
            f"{folder}: not enough free space for {what}: it needs about "
            f"{_size(need + DISK_MARGIN)}, {_size(free)} are free; free some space or give "
            f"another folder")


def _size(n):
    for unit, k in (("GB", 1 << 30), ("MB", 1 << 20), ("kB", 1 << 10)):
        if n >= k:
            return f"{n / k:.1f} {unit}"
    return f"{n} bytes"


def is_disk_full(exc):
    """Is ``exc`` a write that failed for want of space (ENOSPC, EDQUOT, or HDF5's report
    of one)?"""
    import errno as _errno

    if isinstance(exc, OSError) and exc.errno in (_errno.ENOSPC, _errno.EDQUOT):
        return True
    return (isinstance(exc, (OSError, RuntimeError))
            and ("No space left" in str(exc) or "Disk quota exceeded" in str(exc)))


def disk_full_error(path, exc=None):
    """The one-line :class:`~sapgo.errors.DiskFullError` of a write to ``path`` that ran out
    of space."""
    from .errors import DiskFullError

    return DiskFullError(f"{path}: the disk is full (no space left on its filesystem): "
                         f"nothing was changed and the temporary files are removed; free some "
                         f"space and run the command again")


def _now():
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


def append_history(history_json, entry):
    """The ``history`` attribute with ``entry`` (time and version added) appended."""
    h = json.loads(history_json or "[]")
    h.append(dict(entry, time=_now(), sapgo_version=__version__))
    return json.dumps(h[-HISTORY_LIMIT:])


class ProjectWriter:
    """Write a new project file record chunk by record chunk, atomically.

    The file is built as ``PATH.tmp`` and renamed over ``path`` by :meth:`finish`; if anything
    fails first (or the process is killed), ``path`` is untouched and :meth:`abort` (or the
    context manager) removes the temporary file. Records are appended in chunks, so nothing
    has to be held whole::

        with ProjectWriter(path, attrs) as w:
            w.append("stations", chunk)
            ...
            w.finish()

    ``sizes``: the records each dataset will hold (by name), where known: a dataset's
    chunks then hold no more records than that (one chunk of about a megabyte otherwise,
    read, checksummed and copied whole however few records it holds).

    ``memory``: the file is built in memory (HDF5's core driver, nothing written) and
    :meth:`finish` hands over the open file instead (``sapgo adjust``'s ordered copy of a
    small project, :func:`memory_image`). The records appended are held as arrays and each
    dataset is created whole, with its data, by :meth:`finish` (one write each instead of
    a resize and a write an append): until then the file has none of the record datasets.
    """

    def __init__(self, path, attrs=None, truth=False, tmp_suffix=".tmp", sizes=None,
                 memory=False):
        self.path = Path(path)
        self.memory = memory
        self.tmp = self.path.with_name(self.path.name + tmp_suffix)
        #: (memory) the records appended, by dataset: the run reads them, not the file
        self.records = {}
        if memory:
            est = sum(int(n) * RECORD_DTYPES[k].itemsize for k, n in (sizes or {}).items()
                      if k in RECORD_DTYPES)
            self._f = h5py.File(self.tmp, "w", driver="core", backing_store=False,
                                block_size=core_block_size(2 * est))
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            if self.path.is_dir():
                raise IsADirectoryError(21, "Is a directory", str(self.path))
            ensure_free(self.path.parent, 0, f"the new project {self.path.name}")
            self._f = h5py.File(self.tmp, "w")
        f = self._f
        head = {"format": FORMAT_NAME, "schema_version": SCHEMA_VERSION,
                "sapgo_version": __version__, "created": _now(),
                "units": json.dumps({"object": "m", "image": "mm", "angles": "rad",
                                     "weights": "1/unit^2"}),
                "frame": "local space rectangular", "crs": "", "ordered": False,
                "ordering": "", "band_width": 0, "history": json.dumps([])}
        head.update(attrs or {})
        head["uuid"] = uuid.uuid4().hex
        fa = f.attrs   # (each written once: an attribute write takes 0.1 ms)
        for k, v in head.items():
            fa[k] = v
        self._names = dict(RECORD_DTYPES)
        if truth:
            f.create_group("truth")
            self._names.update(TRUTH_DTYPES)
        self._rows = {}
        for name, dtype in self._names.items():
            rows = max(1, min(CHUNK_RECORDS, (1 << 20) // dtype.itemsize))
            if sizes is not None and name in sizes:
                rows = max(1, min(rows, int(sizes[name])))
            self._rows[name] = rows
            if not memory:
                f.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dtype,
                                 chunks=(rows,), **CHECKSUM)

    @property
    def file(self):
        return self._f

    def size(self, name):
        if self.memory:
            return sum(len(r) for r in self.records.get(name, ()))
        return int(self._f[name].shape[0])

    def append(self, name, records):
        """Append records to dataset ``name``; returns the record number of the first."""
        if self.memory:   # (a copy: the caller may reuse its buffer)
            n = self.size(name)
            self.records.setdefault(name, []).append(
                np.array(records, dtype=self._names[name], copy=True))
            return n
        ds = self._f[name]
        records = np.asarray(records, dtype=ds.dtype)
        ensure_free(self.tmp, 2 * records.nbytes, f"the new project {self.path.name}")
        n = ds.shape[0]
        if len(records):
            ds.resize((n + len(records),))
            ds[n:] = records
        return n

    def set_attrs(self, **attrs):
        for k, v in attrs.items():
            self._f.attrs[k] = v

    def finish(self):
        """Close the file and move it into place (in memory: the open file, handed over)."""
        if self.memory:
            f, self._f = self._f, None
            self.records = {name: np.concatenate(parts) if len(parts) > 1 else parts[0]
                            for name, parts in self.records.items()}
            for name, dtype in self._names.items():
                data = self.records.get(name)
                if data is None:   # (held too: the run's reads find every dataset held)
                    data = self.records[name] = np.zeros(0, dtype)
                f.create_dataset(name, data=data, maxshape=(None,),
                                 chunks=(self._rows[name],), **CHECKSUM)
            f.flush()
            return f
        self._f.close()
        self._f = None
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self):
        if self._f is not None:
            f, self._f = self._f, None
            try:
                f.close()
            except (OSError, RuntimeError):   # (a full disk: the file goes anyway)
                pass
        if not self.memory:
            self.tmp.unlink(missing_ok=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.abort()


def new_project_path(out, force):
    """``out`` as a Path for a new project: refused when it is a directory, or exists
    without ``force`` (one line each)."""
    from .errors import ParameterError

    out = Path(out)
    if out.is_dir():
        raise ParameterError(f"{out}: is a directory")
    if out.exists() and not force:
        raise ParameterError(f"{out} exists: use --force to replace it")
    return out


def point_records(point_of_obs, n_points, **fields):
    """``/points`` records of ``n_points`` points whose observations come grouped by point
    (``point_of_obs``: each observation's point record, ascending): ``n_obs`` and
    ``obs_start`` from them, ``station_min`` and ``station_max`` -1 (unknown: ``sapgo
    order`` sets them), the other ``fields`` (``id``, ``kind``, ``xyz``, ``control``, ...)
    as given."""
    counts = np.bincount(np.asarray(point_of_obs, np.int64), minlength=n_points)
    out = np.zeros(n_points, POINT_DTYPE)
    for name, value in fields.items():
        out[name] = value
    out["n_obs"] = counts
    out["obs_start"] = np.cumsum(counts) - counts
    out["station_min"] = out["station_max"] = -1
    return out


def write_project(path, cameras, stations, points, observations, priors=None, truth=None,
                  attrs=None, extra=None):
    """Write a new project file atomically from whole record arrays (small blocks, tests).

    ``cameras``, ``stations``, ``points``, ``observations`` and ``priors`` are structured
    arrays of the record dtypes (or anything convertible); ``truth`` is an optional dict with
    ``stations`` and ``points`` structured arrays in record order. Points must already hold
    ``obs_start``/``n_obs`` consistent with ``observations``. ``extra(file)`` writes a
    format's own groups (:data:`KEYED_GROUPS`) into the new file. Large blocks are written
    with :class:`ProjectWriter`.
    """
    from .validate import check_records

    creator = json.loads((attrs or {}).get("creator", "{}") or "{}")
    if creator.get("command") == "import":   # (the records of a format's import: checked)
        check_records(creator.get("file") or creator.get("path") or creator.get("model")
                      or path, *(r if isinstance(r, np.ndarray) and r.dtype.names else None
                                 for r in (cameras, stations, points, observations)))
    sizes = {"cameras": len(cameras), "stations": len(stations), "points": len(points),
             "observations": len(observations),
             "station_priors": 0 if priors is None else len(priors)}
    if truth is not None:
        sizes.update({"truth/stations": len(truth["stations"]),
                      "truth/points": len(truth["points"])})
    with ProjectWriter(path, attrs, truth=truth is not None, sizes=sizes) as w:
        w.append("cameras", cameras)
        w.append("stations", stations)
        w.append("station_priors", priors if priors is not None else np.zeros(0, PRIOR_DTYPE))
        w.append("points", points)
        w.append("observations", observations)
        if truth is not None:
            w.append("truth/stations", truth["stations"])
            w.append("truth/points", truth["points"])
        if extra is not None:
            extra(w.file)
        return w.finish()


#: HDF5 types of numpy dtypes, by (dtype, logical) (h5py's ``py_create``: 0.1 ms a call,
#: 1 ms for the cameras' 61 fields; every open project read each dataset's afresh).
_HTYPES = {}


def _htype(dtype, logical=False):
    """h5py's ``py_create(dtype, logical)``, made once a process (HDF5 types in memory are
    not bound to a file)."""
    key = (dtype, bool(logical))
    t = _HTYPES.get(key)
    if t is None:
        t = _HTYPES[key] = h5py.h5t.py_create(dtype, logical=logical)
    return t


def _schema_dtype(ds, name):
    """The schema's dtype of record dataset ``name`` when ``ds`` holds exactly that type
    (compared by HDF5; h5py's ``ds.dtype`` works the type out afresh for every dataset
    opened, 0.1-1.2 ms each), else None."""
    expected = RECORD_DTYPES.get(name) or TRUTH_DTYPES.get(name)
    if expected is not None and ds.id.get_type() == _htype(expected, logical=True):
        return expected
    return None


def _read_only(view):
    """``view`` (of records held in memory), marked read only."""
    view.flags.writeable = False
    return view


def _memory_dtype(ds, name):
    """The dtype records of dataset ``ds`` (``name``) are read into: the schema's for a
    record dataset of the schema's fields, in whatever order and byte order the file
    stores them (HDF5 converts compound members by name), so that the kernels always get
    the native layout; else the file's own (an older version's narrower cameras)."""
    dt = _schema_dtype(ds, name)
    if dt is not None:
        return dt
    dt = ds.dtype
    expected = RECORD_DTYPES.get(name) or TRUTH_DTYPES.get(name)
    if expected is not None and dt.names is not None and set(dt.names) == set(expected.names):
        return expected
    return dt


def _dtype_matches(actual, expected):
    if actual.names is None or set(actual.names) != set(expected.names):
        return False
    for name in expected.names:
        a, e = actual.fields[name][0], expected.fields[name][0]
        if a.shape != e.shape or a.base.kind != e.base.kind or \
                a.base.itemsize != e.base.itemsize:
            return False
    return True


#: Files whose structure a read-only open validated, by :func:`_file_key`: an unchanged
#: file (same inode, size and modification time) is not validated again by the same process
#: (a run opens its project four or five times; each validation reads every dataset's type).
_VALIDATED = {}


def _file_key(path):
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns)


_MISSING = object()   # (an attribute the file does not have: Project.attr)


def _span(start, stop, n):
    """``start:stop`` of ``n`` rows as numpy slices them (None, negative, beyond the end)."""
    start, stop, _ = slice(start, stop).indices(n)
    return start, max(start, stop)


class Project:
    """An open sapgo project file.

    Opening validates the file: that it is HDF5, that it is a sapgo project of this schema
    version and that every record dataset has the documented fields. Values are checked by
    :func:`sapgo.validate.check_values` before an adjustment.

    Use it as a context manager::

        with Project("block.h5") as p:
            print(p.n_stations, p.band_width)
    """

    def __init__(self, path, mode="r", shown=None, memory=None, held=None, tiling=True):
        # ``tiling``: check at the open that the points' observation ranges end where
        # /observations does (False: the caller runs validate.check_values, which checks
        # the whole tiling on its pass over the points). ``shown``: the name messages give (``sapgo adjust`` reads an unordered project's
        # ordered copy, ``file_path``, under the project's own name). ``memory``: an open
        # HDF5 file in memory (:func:`memory_image`) that the caller validated or wrote and
        # closes: ``path`` only names it; ``held``: its records by dataset, as written
        # (:class:`ProjectWriter` in memory), held for the reads
        self.file_path = Path(path)
        self.path = self.file_path
        self._check_tiling = tiling
        if mode not in ("r", "r+"):
            raise ValueError("mode must be 'r' or 'r+'")
        self._own = memory is None
        if memory is None:
            self._open_file(mode)
        else:
            self._f = memory
        self._read_only = mode == "r"
        self._held = dict(held or {})
        self._open = {}   # datasets kept open (read only): their chunk caches stay
        self._lengths = {}   # (read only) datasets' lengths
        self._types = {}   # (read only) (dataset, field): memory dtype and HDF5 type of reads
        self.point_chunks = None   # :meth:`keep_point_chunks`
        self.point_chunk_room = 0
        self._attrs = {}   # (read only) attributes read
        self._cameras = None   # (read only) the camera records as CAMERA_DTYPE
        if shown is not None:
            self.path = Path(shown)

    def _open_file(self, mode):
        """Open and validate the file (a read-only open of an unchanged file once)."""
        if not self.path.exists():
            raise ProjectFormatError(f"{self.path}: no such file")
        if self.path.is_dir():
            raise ProjectFormatError(f"{self.path}: is a directory, not a sapgo project")
        if not h5py.is_hdf5(self.path):
            raise ProjectFormatError(
                f"{self.path}: not a sapgo project (the file is not HDF5)"
            )
        try:
            self._f = h5py.File(self.file_path, mode, **CHUNK_CACHE)
        except OSError as exc:
            raise ProjectFormatError(f"{self.path}: cannot open as HDF5 ({exc})") from None
        try:
            key = _file_key(self.file_path)
            if mode != "r" or key not in _VALIDATED:
                self._validate_structure()
                if mode == "r" and key is not None:
                    _VALIDATED[key] = None
                    while len(_VALIDATED) > 64:
                        del _VALIDATED[next(iter(_VALIDATED))]
        except Exception:
            self._f.close()
            raise

    # -- validation ---------------------------------------------------------------------
    def _validate_structure(self):
        f = self._f
        fmt = f.attrs.get("format")
        if isinstance(fmt, bytes):
            fmt = fmt.decode()
        if fmt != FORMAT_NAME:
            raise ProjectFormatError(
                f"{self.path}: not a sapgo project (HDF5 file without the "
                f"'format = {FORMAT_NAME}' attribute)"
            )
        version = f.attrs.get("schema_version")
        if version is None or int(version) != SCHEMA_VERSION:
            raise ProjectFormatError(
                f"{self.path}: project schema version {version}, but this sapgo "
                f"({__version__}) reads schema version {SCHEMA_VERSION}"
            )
        for name, dtype in list(RECORD_DTYPES.items()) + (
            list(TRUTH_DTYPES.items()) if "truth" in f else []
        ):
            if name not in f:
                if name in TRUTH_OPTIONAL:
                    continue
                raise ProjectFormatError(f"{self.path}: dataset /{name} is missing")
            ds = f[name]
            if not isinstance(ds, h5py.Dataset) or ds.ndim != 1:
                raise ProjectFormatError(f"{self.path}: /{name} is not a record dataset")
            if _schema_dtype(ds, name) is None and not (_dtype_matches(ds.dtype, dtype)
                    or any(_dtype_matches(ds.dtype, d) for d in OLDER_DTYPES.get(name, ()))):
                raise ProjectFormatError(
                    f"{self.path}: /{name} records have fields {ds.dtype.names}, "
                    f"expected {dtype.names} (see docs/project-schema.md)"
                )
        n_pt, n_ob = len(f["points"]), len(f["observations"])
        end = n_ob
        if n_pt and getattr(self, "_check_tiling", True):   # (all of it: check_values)
            try:
                last = f["points"][n_pt - 1]
                end = int(last["obs_start"]) + int(last["n_obs"])
            except OSError:   # (a chunk failing its checksum: the reads name it, as before)
                end = n_ob
        if end != n_ob:
            raise ProjectFormatError(
                f"{self.path}: the points' obs_start and n_obs cover {end} observations but "
                f"/observations has {n_ob} records: the project is damaged")
        if "truth" in f:
            if len(f["truth/stations"]) != len(f["stations"]) or len(f["truth/points"]) != len(
                f["points"]
            ):
                raise ProjectFormatError(
                    f"{self.path}: /truth does not have one record per station and point"
                )
        if "solution" in f:
            for name, (parent, shape) in SOLUTION_LAYOUT.items():
                ds = f["solution"].get(name)
                if ds is None and name in SOLUTION_OPTIONAL:
                    continue
                narrower = (ds is not None and name in SOLUTION_NARROWER and ds.ndim == 2
                            and ds.shape[0] == len(f[parent])
                            and ds.shape[1] in SOLUTION_NARROWER[name])
                if ds is None or (ds.shape != (len(f[parent]),) + shape and not narrower):
                    raise ProjectFormatError(
                        f"{self.path}: /solution/{name} is missing or does not match /{parent}"
                    )

    # -- life cycle ---------------------------------------------------------------------
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def close(self):
        self._attrs = {}
        self._cameras = None
        self._held = {}
        self._open = {}
        self._lengths = {}
        self._types = {}
        self.point_chunks = None
        if self._f is not None:
            if self._own:
                self._f.close()
            self._f = None

    @property
    def file(self):
        if self._f is None:
            raise ClosedProjectError(f"{self.path}: the project is closed")
        return self._f

    # -- sizes and attributes -----------------------------------------------------------
    def __len_of(self, name):
        if not self._read_only:
            return int(self.file[name].shape[0])
        n = self._lengths.get(name)   # (read only: fixed; opening a dataset takes 0.1 ms)
        if n is None:
            n = self._lengths[name] = int(self._dataset(name).shape[0])
        return n

    @property
    def n_cameras(self):
        return self.__len_of("cameras")

    @property
    def n_stations(self):
        return self.__len_of("stations")

    @property
    def n_points(self):
        return self.__len_of("points")

    @property
    def n_observations(self):
        return self.__len_of("observations")

    def length(self, name):
        """Records of dataset ``name`` (read only: kept)."""
        return self.__len_of(name)

    @property
    def n_priors(self):
        return self.__len_of("station_priors")

    @property
    def ordered(self):
        return bool(self.file.attrs.get("ordered", False))

    @property
    def band_width(self):
        return int(self.file.attrs.get("band_width", 0))

    @property
    def solver(self):
        """The solver the project's order was made for: "band" or "tree"."""
        return str(self.attr("solver", "band") or "band")

    def tree(self):
        """The partition tree stored by ``sapgo order`` (:class:`sapgo.solve.partition.Tree`),
        or None when the project is ordered for the band. A tree that no longer matches the
        records (stations or points changed since) raises :class:`ProjectFormatError`."""
        from .solve.partition import Tree

        if self.solver != "tree" or "tree" not in self._f:
            return None
        g = self._f["tree"]
        try:
            tree = Tree.from_arrays({k: g[k][()] for k in g}, g.attrs["n_active"],
                                    g.attrs.get("method", "geometric"))
        except KeyError as exc:
            raise ProjectFormatError(f"{self.path}: /tree is incomplete ({exc})") from None
        if (tree.pt_start is None or len(tree.pt_start) != tree.n_nodes + 1
                or tree.pt_start[-1] > self.n_points or tree.n_active > self.n_stations
                or (tree.n_nodes and tree.hi[-1] > tree.n_active)):
            raise ProjectFormatError(f"{self.path}: the stored partition tree does not match "
                                     f"the records (changed since 'sapgo order')")
        return tree

    @property
    def has_truth(self):
        return "truth" in self.file

    @property
    def has_solution(self):
        return "solution" in self.file

    def attr(self, name, default=None):
        if not self._read_only:
            v = self.file.attrs.get(name, default)
            return v.decode() if isinstance(v, bytes) else v
        if name not in self._attrs:   # (read only: fixed; an attribute read takes 0.1 ms)
            v = self.file.attrs.get(name, _MISSING)
            self._attrs[name] = v.decode() if isinstance(v, bytes) else v
        v = self._attrs[name]
        if v is _MISSING:
            return default
        return v.copy() if isinstance(v, np.ndarray) else v

    def history(self):
        return json.loads(self.attr("history", "[]"))

    def frame(self):
        """The computation frame and the user's CRS (:class:`sapgo.frames.Frame`)."""
        from .frames import Frame

        return Frame.from_attrs({k: self.attr(k) for k in ("frame", "crs", "frame_origin")})

    def add_history(self, entry):
        self.file.attrs["history"] = append_history(self.attr("history", "[]"), entry)

    # -- record access ------------------------------------------------------------------
    def record_bytes(self, names=("points", "observations")):
        """Bytes of the records of datasets ``names``."""
        held = self._held
        return sum(held[n].nbytes if n in held else
                   self._dataset(n).shape[0] * self._dataset(n).id.get_type().get_size()
                   for n in names)

    def hold(self, names=("points", "observations"), max_bytes=256 << 20):
        """Read the records of datasets ``names`` into core once, when together they take at
        most ``max_bytes``, so that the many passes of an adjustment slice memory instead of
        reading the file (a project opened read only: the records cannot change under it).
        ``names`` None: every record dataset. Returns the bytes held (0: the records stay
        in the file)."""
        if not self._read_only:
            return 0
        if names is None:   # (every record dataset of the file)
            names = [n for n in (*RECORD_DTYPES, *TRUTH_DTYPES)
                     if n in self._held or n in self.file]
        size = self.record_bytes(names)
        if size > max_bytes:
            return 0
        for n in names:
            if n not in self._held:
                ds = self._dataset(n)
                rows = ds.shape[0]
                self._held[n] = self._checked(ds, 0, rows, lambda: self._rows(n, ds, 0, rows))
        return size

    def keep_point_chunks(self, expected_bytes, max_bytes):
        """Keep the kernels' arrays of every chunk of points read
        (:class:`sapgo.normals.PointChunk`: all but the coordinates, converted once) for the
        rest of the run, when the project is open read only (its records cannot change) and
        ``expected_bytes`` (what they will come to) is at most ``max_bytes``. Returns the
        bytes reserved (0: nothing kept)."""
        if not self._read_only or expected_bytes > max_bytes:
            return 0
        self.point_chunks = {}
        self.point_chunk_room = int(expected_bytes)   # (what is left: spent as kept)
        return int(expected_bytes)

    def read(self, name, start=0, stop=None, copy=True):
        """Records ``start:stop`` of dataset ``name`` (e.g. ``"points"``, ``"truth/points"``).
        ``copy=False``: records held in memory come as a read-only view of them (a caller
        that only looks: the checks, the counts)."""
        held = self._held.get(name)
        if held is not None:
            return held[start:stop].copy() if copy else _read_only(held[start:stop])
        ds = self._dataset(name)
        if self._read_only and ds.ndim == 1:
            n = self.__len_of(name)
            start, stop = _span(start, stop, n)
            return self._checked(ds, start, stop, lambda: self._rows(name, ds, start, stop))
        stop = ds.shape[0] if stop is None else stop
        return self._checked(ds, start, stop, lambda: ds[start:stop])

    def read_field(self, name, field, start=0, stop=None, copy=True):
        held = self._held.get(name)
        if held is not None:
            v = held[field][start:stop]
            return v.copy() if copy else _read_only(v)
        ds = self._dataset(name)
        if self._read_only and ds.ndim == 1:
            n = self.__len_of(name)
            start, stop = _span(start, stop, n)
            return self._checked(ds, start, stop,
                                 lambda: self._rows(name, ds, start, stop, field))
        stop = ds.shape[0] if stop is None else stop
        if stop <= start:
            return np.zeros((0,) + ds.dtype.fields[field][0].shape, ds.dtype.fields[field][0].base)
        return self._checked(ds, start, stop, lambda: ds.fields(field)[start:stop])

    def _rows(self, name, ds, start, stop, field=None):
        """Records ``start:stop`` of the record dataset ``ds`` (``name``), or their field
        ``field``, by HDF5's own read into an array of the records' (or the field's) type:
        h5py's slicing works the compound type out afresh every time (0.3-0.7 ms a read),
        which a run of a small block does a hundred times. Read-only projects."""
        types = self._types.get((name, field))
        if types is None:
            dt = (self._rows(name, ds, 0, 0).dtype if field is not None
                  else _memory_dtype(ds, name))
            mem = dt if field is None else np.dtype([(field, dt.fields[field][0])])
            types = self._types[name, field] = (mem, _htype(mem))
        mem, htype = types
        out = np.empty(stop - start, mem)
        if stop > start:
            fspace = ds.id.get_space()
            fspace.select_hyperslab((start,), (stop - start,))
            ds.id.read(h5py.h5s.create_simple((stop - start,)), fspace, out, htype)
        return out if field is None else np.ascontiguousarray(out[field])

    def _dataset(self, name):
        """Dataset ``name``, kept open when the project is read only, so that HDF5's chunk
        cache (:data:`CHUNK_CACHE`) serves the next read of the same chunk (a dataset
        opened afresh starts with an empty cache)."""
        if not self._read_only:
            return self.file[name]
        ds = self._open.get(name)
        if ds is None:
            ds = self._open[name] = self.file[name]
        return ds

    def _checked(self, ds, start, stop, read):
        """``read()`` of records ``start:stop`` of ``ds``; a chunk that fails its checksum
        (or cannot be read at all) raises :class:`DataError` naming the dataset and the
        chunk's records."""
        try:
            return read()
        except OSError as exc:
            rows = (ds.chunks or (max(1, stop - start),))[0]
            lo, hi = start, stop
            for a in range(start - start % rows, stop, rows):   # the chunk at fault
                try:
                    ds[max(a, start):min(a + rows, stop)]
                except OSError:
                    lo, hi = max(a, start), min(a + rows, ds.shape[0])
                    break
            text = str(exc).lower()
            why = ("fail their checksum (Fletcher-32)" if ds.fletcher32 and (
                "filter" in text or "fletcher" in text or "checksum" in text)
                else "cannot be read")
            raise DataError(f"{self.path}: {ds.name} records {lo}..{hi - 1} {why}: the file "
                            f"was damaged on disk or in transfer; restore the project from "
                            f"a copy") from None

    def chunks(self, name, size=CHUNK_RECORDS):
        """Yield ``(start, stop)`` ranges covering dataset ``name`` in processing order (while
        a run's per-station vectors are paged, their pages are released after each range:
        :func:`sapgo.paging.rows`)."""
        from .paging import rows

        yield from rows(self.__len_of(name), size)

    def cameras(self):
        """The camera records as :data:`CAMERA_DTYPE` (fields an older version's file lacks:
        0, the forward model without affinity)."""
        cams = self._cameras
        if cams is None:
            cams = self.read("cameras")
            if cams.dtype != CAMERA_DTYPE:
                out = np.zeros(len(cams), CAMERA_DTYPE)
                for name in cams.dtype.names:
                    if name in CAMERA_DTYPE.names:
                        out[name] = cams[name]
                cams = out
            if self._read_only:   # (fixed: kept)
                self._cameras = cams
        return cams.copy() if self._read_only else cams

    # -- solution -----------------------------------------------------------------------
    def solution(self, name, start=0, stop=None):
        """Slice of a /solution dataset; zeros when the project has not been adjusted."""
        parent, shape = SOLUTION_LAYOUT[name]
        n = self.__len_of(parent)
        stop = n if stop is None else stop
        if not self.has_solution or name not in self.file["solution"]:
            return np.zeros((stop - start,) + shape)
        ds = self.file["solution"][name]
        data = self._checked(ds, start, stop, lambda: ds[start:stop])
        if data.shape[1:] != shape:   # (an older version's narrower rows)
            full = np.zeros((len(data),) + shape)
            full[:, :data.shape[1]] = data
            data = full
        return data

    def new_solution(self, cameras=None):
        """A new, zeroed result group ``/solution.new`` sized to the current records.

        Fill it, then :meth:`commit_solution` puts it in place of ``/solution``: an old
        solution stays readable until the new one is complete. ``cameras``: the camera
        records, when the caller has them.
        """
        f = self.file
        if "solution.new" in f:
            del f["solution.new"]
        g = f.create_group("solution.new")
        narrow = not (self.cameras() if cameras is None else cameras)["ap_set"].any()
        #: the datasets made, by name (looking one up in the group takes 0.1 ms)
        self.new_datasets = {
            name: solution_dataset(g, name, len(f[parent]),
                                   PHOTO_CAMERA_NARROW if narrow and name == "photo_camera_corr"
                                   else None)
            for name, (parent, _) in SOLUTION_LAYOUT.items()}
        g.attrs["state"] = "initial"
        g.attrs["iterations"] = 0
        g.attrs["converged"] = False
        return g

    def commit_solution(self):
        """Replace ``/solution`` with the completed ``/solution.new``."""
        f = self.file
        if "solution" in f:
            del f["solution"]
        f.move("solution.new", "solution")
        return f["solution"]


def memory_image(path):
    """The project file ``path`` read whole into memory as an HDF5 file that takes writes
    and never writes them back (HDF5's core driver without a backing store): ``sapgo
    adjust`` on a small project commits from it (:func:`write_image`). None when the file
    cannot be opened so (then the run reads the file itself)."""
    try:
        size = os.path.getsize(path)
        return h5py.File(path, "r+", driver="core", backing_store=False,
                         block_size=core_block_size(size))
    except OSError:
        return None


def core_block_size(grows_by):
    """The increment of an HDF5 file in memory (the core driver's ``block_size``) for a
    file that grows by about ``grows_by`` bytes: the driver reallocates its image every
    increment (64 KiB by default), so a file in memory that takes a few megabytes of
    records or results was copied whole dozens of times (p49: 7.5 against 4.7 ms for the
    records, 6.9 against 3.6 for the solution at 8 MiB). But the driver zero-fills each
    increment as it takes it, every page of it touched, used or not: 0.6 ms a MiB on this
    VM, so that at 8 MiB the ordered copy of BAL problem-49 (4 MB of records) took 34-37 ms
    against 22-24 ms at 1 MiB or 256 KiB (the writer's opening 6-8 ms against 1.3;
    medians of 7 runs, 4 interleaved rounds), and at 10 000 photos 103-125 ms at 1 MiB,
    127-155 at 256 KiB (more copies), 138-147 at 8 MiB. A power of two from 64 KiB to
    :data:`CORE_BLOCK_MAX`."""
    b = 1 << 16
    while b < grows_by and b < CORE_BLOCK_MAX:
        b <<= 1
    return b


#: The largest increment of a file in memory (:func:`core_block_size`).
CORE_BLOCK_MAX = 1 << 20


def write_image(f, path):
    """Write the HDF5 file ``f`` held in memory to ``path`` (a new file) in one write."""
    f.flush()
    image = f.id.get_file_image()
    ensure_free(path, len(image), f"the adjusted copy of {Path(path).name}")
    with open(path, "wb") as out:
        out.write(image)


def open_project(path, mode="r"):
    """Open and validate a project file; see :class:`Project`."""
    return Project(path, mode)
