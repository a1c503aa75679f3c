"""The plain-text block formats: cameras, photos, image measurements and control.

Whitespace-separated columns, ``#`` starts a comment (a whole line or the rest of a line),
blank lines are ignored; lines may end as on Unix (LF), Windows (CR LF) or classic Mac OS
(CR). Units: image coordinates, focal length, principal point, format and image sigmas in
mm; ground coordinates and their sigmas in m; angles in the unit the user chooses (``deg``,
``gon`` or ``rad``), stored in radians. Ids are int64. The formats are documented field by
field in ``docs/formats.md``::

    cameras       id focal_length x0 y0 format_x format_y sigma_image
                  [k1 k2 k3 p1 p2 [b1 b2 [forward|backward]]]
    photos        id camera strip omega phi kappa X Y Z
    photos_matrix id camera strip m11 m12 m13 m21 m22 m23 m31 m32 m33 X Y Z
    measurements  photo point x y [sigma]
    control       point X Y Z sX sY sZ [kind]
    priors        photo omega phi kappa X Y Z s_omega s_phi s_kappa sX sY sZ
    prior_covariances  photo omega phi kappa X Y Z c11 c12 ... c66  (upper triangle)

Parsing is chunk by chunk (:func:`read_chunks` cuts a file into blocks of whole lines,
:func:`parse_chunk` turns a block into records). The fast path hands the block to
``numpy.loadtxt``; a block whose lines differ in their optional columns is loaded per column
count. When that fails too, the block is parsed again line by line, which either produces the
same records or raises a :class:`~sapgo.errors.DataError` naming the file, the line and the
column. Value checks
(finite numbers, signs, kinds) run on the parsed records of a block and also name the line.

Angles. Degrees and gon are read with the platform's extended ``long double`` and converted
with pi to 64 bits of precision, then rounded once to float64: on x86-64 (80-bit long
double) :func:`export_text` can always find a decimal angle that reads back to the very same
float64 radians, so export -> import reproduces a project's records bitwise.
"""

from __future__ import annotations

import io
import os
import re
import warnings
from pathlib import Path

import numpy as np

from ..errors import DataError, ParameterError
from ..apsets import AP_SETS, N_TERMS
from ..geometry import AP_NAMES, BACKWARD, FORWARD
from ..project import (
    CHUNK_RECORDS,
    CONTROL_MASK,
    KIND_CHECK,
    KIND_CONTROL,
    KIND_HORIZONTAL,
    KIND_PASS,
    KIND_VERTICAL,
    Project,
)

#: Angle units of the photos file (``--angles``).
ANGLE_UNITS = ("deg", "gon", "rad")
_PI = np.longdouble("3.14159265358979323846264338327950288419716939937510")
_ANGLE_FACTOR = {"deg": _PI / 180, "gon": _PI / 200, "rad": np.longdouble(1)}

#: Kind names of the control file and their point kind codes (``sapgo.project``).
KIND_WORDS = {"full": KIND_CONTROL, "horizontal": KIND_HORIZONTAL,
              "vertical": KIND_VERTICAL, "check": KIND_CHECK}
KIND_WORD_OF = {v: k for k, v in KIND_WORDS.items()}
KIND_WORDS["control"] = KIND_CONTROL  # the project's name of a full control point
#: The distortion models of the cameras file (column 15; sapgo.geometry).
MODEL_WORDS = {"forward": FORWARD, "backward": BACKWARD}
#: Components a control kind cannot do without (X, Y, Z); the others may be '-' or nan.
NEEDED = CONTROL_MASK.astype(bool).copy()
NEEDED[KIND_CHECK] = True

# column types
_ID, _INT, _FLOAT, _ANGLE, _OPT, _KIND = "id", "int", "float", "angle", "opt", "kind"

_INT_RE = re.compile(rb"[+-]?[0-9]+")
_FLOAT_RE = re.compile(
    rb"[+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|inf|infinity|nan)", re.I)
_DASH = re.compile(rb"(?<!\S)-(?!\S)")
_INT64 = (-(1 << 63), (1 << 63) - 1)
#: A line longer than this (bytes) is refused: the file is not a text file of the format.
MAX_LINE = 1 << 20


class TextFormat:
    """One text format: its columns (name, type), the optional tail and the usage line."""

    def __init__(self, name, columns, min_cols, usage, defaults=None, words=None):
        self.name = name
        self.columns = columns
        self.min_cols = min_cols
        self.max_cols = len(columns)
        self.usage = usage
        self.defaults = defaults or {}
        #: the words of each word column and their codes (default: the control kinds)
        self.words = {n: (words or {}).get(n, KIND_WORDS) for n, t in columns if t == _KIND}
        fields = []
        for cname, ctype in columns:
            if ctype == _KIND:
                fields.append((cname, "i1"))
            elif ctype in (_ID, _INT):
                fields.append((cname, "<i8"))
            else:
                fields.append((cname, "<f8"))
        #: dtype of the parsed records: every column, angles in radians, kinds as codes
        self.dtype = np.dtype(fields)

    def expected(self):
        if self.min_cols == self.max_cols:
            n = f"{self.min_cols}"
        elif self.max_cols == self.min_cols + 1:
            n = f"{self.min_cols} or {self.max_cols}"
        else:
            n = f"{self.min_cols} to {self.max_cols}"
        return f"expected {n} columns ({self.usage})"

    def load_dtype(self, ncols, angles):
        """The dtype ``numpy.loadtxt`` reads ``ncols`` columns into."""
        fields = []
        for cname, ctype in self.columns[:ncols]:
            if ctype == _KIND:
                fields.append((cname, "S32"))
            elif ctype in (_ID, _INT):
                fields.append((cname, "<i8"))
            elif ctype == _ANGLE and angles != "rad":
                fields.append((cname, np.longdouble))
            else:
                fields.append((cname, "<f8"))
        return np.dtype(fields)


#: The image frame of a camera's measurements in columns 16-22 of the cameras file (as a
#: line of ``--image-frames``): the unit, and where the origin is and which way y points.
FRAME_UNIT_WORDS = {"none": -2, "mm": 0, "px": 1}   # (-1: an unknown word)
FRAME_ORIGIN_WORDS = {"centre": 0, "topleft": 1, "bottomleft": 2}
FRAME_AXIS_WORDS = {"up": 0, "down": 1}

CAMERAS = TextFormat(
    "cameras",
    [("id", _ID), ("focal_length", _FLOAT), ("x0", _FLOAT), ("y0", _FLOAT),
     ("format_x", _FLOAT), ("format_y", _FLOAT), ("sigma_image", _FLOAT),
     ("k1", _FLOAT), ("k2", _FLOAT), ("k3", _FLOAT), ("p1", _FLOAT), ("p2", _FLOAT),
     ("b1", _FLOAT), ("b2", _FLOAT), ("model", _KIND),
     ("frame", _KIND), ("pixel_x", _FLOAT), ("pixel_y", _FLOAT), ("frame_width", _FLOAT),
     ("frame_height", _FLOAT), ("origin", _KIND), ("y_axis", _KIND)],
    7, "id focal_length x0 y0 format_x format_y sigma_image [k1 k2 k3 p1 p2 [b1 b2 "
       "[forward|backward [mm|px pixel_x pixel_y width height centre|topleft|bottomleft "
       "up|down]]]]",
    defaults={"model": b"forward", "frame": b"none", "origin": b"centre", "y_axis": b"up"},
    words={"model": MODEL_WORDS, "frame": FRAME_UNIT_WORDS, "origin": FRAME_ORIGIN_WORDS,
           "y_axis": FRAME_AXIS_WORDS},
)
PHOTOS = TextFormat(
    "photos",
    [("id", _ID), ("camera", _ID), ("strip", _INT), ("omega", _ANGLE), ("phi", _ANGLE),
     ("kappa", _ANGLE), ("X", _FLOAT), ("Y", _FLOAT), ("Z", _FLOAT)],
    9, "id camera strip omega phi kappa X Y Z",
)
#: Photos with their orientation as a rotation matrix (object to image, row by row).
MATRIX_TERMS = tuple(f"m{i}{j}" for i in (1, 2, 3) for j in (1, 2, 3))
PHOTOS_MATRIX = TextFormat(
    "photos_matrix",
    [("id", _ID), ("camera", _ID), ("strip", _INT)] + [(m, _FLOAT) for m in MATRIX_TERMS]
    + [("X", _FLOAT), ("Y", _FLOAT), ("Z", _FLOAT)],
    15, "id camera strip m11 m12 m13 m21 m22 m23 m31 m32 m33 X Y Z",
)
MEASUREMENTS = TextFormat(
    "measurements",
    [("photo", _ID), ("point", _ID), ("x", _FLOAT), ("y", _FLOAT), ("sigma", _FLOAT)],
    4, "photo point x y [sigma]",
)
CONTROL = TextFormat(
    "control",
    [("id", _ID), ("X", _OPT), ("Y", _OPT), ("Z", _OPT), ("sX", _OPT), ("sY", _OPT),
     ("sZ", _OPT), ("kind", _KIND)],
    7, "point X Y Z sX sY sZ [kind]", defaults={"kind": b"full"},
)
#: The six parameters of a station, in the order of a prior's value and weight.
PRIOR_PARAMETERS = ("omega", "phi", "kappa", "X", "Y", "Z")
PRIORS = TextFormat(
    "priors",
    [("photo", _ID)] + [(n, _ANGLE) for n in PRIOR_PARAMETERS[:3]]
    + [(n, _FLOAT) for n in PRIOR_PARAMETERS[3:]]
    + [("s_" + n, _OPT) for n in PRIOR_PARAMETERS],
    13, "photo omega phi kappa X Y Z s_omega s_phi s_kappa sX sY sZ",
)
#: Upper triangle of a prior's 6x6 covariance, row by row (c11 c12 ... c16 c22 ... c66).
COVARIANCE_TERMS = tuple(f"c{i + 1}{j + 1}" for i in range(6) for j in range(i, 6))
PRIOR_COVARIANCES = TextFormat(
    "prior_covariances",
    [("photo", _ID)] + [(n, _ANGLE) for n in PRIOR_PARAMETERS[:3]]
    + [(n, _FLOAT) for n in PRIOR_PARAMETERS[3:]] + [(c, _FLOAT) for c in COVARIANCE_TERMS],
    28, "photo omega phi kappa X Y Z c11 c12 ... c16 c22 ... c66",
)
FORMATS = {f.name: f for f in (CAMERAS, PHOTOS, PHOTOS_MATRIX, MEASUREMENTS, CONTROL,
                               PRIORS, PRIOR_COVARIANCES)}


#: The order of the horizontal coordinates in the photos, control and priors files
#: (``--axis-order``): ``en`` X (east, longitude) then Y (north, latitude), or ``ne``
#: northing (latitude) first, as many survey and GNSS files (and EPSG:4326) give them.
AXIS_ORDERS = ("en", "ne")


def check_axis_order(order):
    if order not in AXIS_ORDERS:
        raise ParameterError(f"axis order {order!r}: choose en (easting first) or ne "
                             f"(northing first)")
    return order


def swap_axes(fmt, rec):
    """Records of ``fmt`` read with northing first, in place: X and Y swapped, and their
    sigmas (control, priors) or covariance terms (prior covariances) with them."""
    pairs = [("X", "Y"), ("sX", "sY"), ("s_X", "s_Y")]
    if fmt is PRIOR_COVARIANCES:   # parameter 3 (X) <-> 4 (Y)
        perm = [0, 1, 2, 4, 3, 5]
        terms = [(i, j) for i in range(6) for j in range(i, 6)]
        old = {t: rec[c].copy() for t, c in zip(terms, COVARIANCE_TERMS)}
        for (i, j), c in zip(terms, COVARIANCE_TERMS):
            a, b = sorted((perm[i], perm[j]))
            rec[c] = old[(a, b)]
    names = rec.dtype.names
    for a, b in pairs:
        if a in names and b in names:
            rec[a], rec[b] = rec[b].copy(), rec[a].copy()
    return rec


def check_angles(angles):
    if angles not in ANGLE_UNITS:
        raise ParameterError(f"angle unit {angles!r}: choose one of {', '.join(ANGLE_UNITS)}")
    return angles


def to_radians(values, angles):
    """Radians (float64) of angles in ``angles`` units (long double input for deg/gon)."""
    if angles == "rad":
        return np.asarray(values, np.float64)
    return (np.asarray(values, np.longdouble) * _ANGLE_FACTOR[angles]).astype(np.float64)


def angle_strings(rad, angles):
    """Decimal strings of float64 radians in ``angles`` units that read back bitwise.

    Returns the strings and the number of values for which no such string was found (only
    possible where ``long double`` has no more precision than ``double``).
    """
    rad = np.ascontiguousarray(rad, np.float64)
    if angles == "rad":
        return [repr(v) for v in rad.tolist()], 0
    factor = _ANGLE_FACTOR[angles]
    d = rad.astype(np.longdouble) / factor
    # the shortest float64 decimal of the angle when it reads back exactly (most angles) ...
    short = [repr(v) for v in d.astype(np.float64).tolist()]
    good = to_radians(np.array(short).astype(np.longdouble), angles).view(np.int64) == \
        rad.view(np.int64)
    # ... else the long double decimal, nudged by a few units in the last place if need be
    bad = np.flatnonzero(~good)
    inexact = 0
    for i in bad[to_radians(d[bad], angles).view(np.int64) != rad[bad].view(np.int64)]:
        found = False
        for direction in (np.longdouble(np.inf), np.longdouble(-np.inf)):
            cand = d[i]
            for _ in range(16):
                cand = np.nextafter(cand, direction)
                if to_radians(np.array([cand]), angles).view(np.int64)[0] == \
                        rad[i:i + 1].view(np.int64)[0]:
                    found = True
                    break
            if found:
                d[i] = cand
                break
        inexact += not found
    if len(bad):
        long = d[bad].astype(str).tolist()
        for i, text in zip(bad.tolist(), long):
            short[i] = text
    return short, inexact


# -- reading ---------------------------------------------------------------------------

def decode_text(path, data):
    """The bytes ``data`` of the file ``path`` as text: UTF-8, a byte-order mark skipped; a
    byte that is not UTF-8 is a :class:`DataError` naming the file and its line."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[:exc.start].count(b"\n") + 1
        raise DataError(f"{path}:{line}: not a text file ({exc.reason})") from None


def open_input(path):
    """``path`` opened for reading, binary; a file that is not there, a directory or a file
    that cannot be read is a :class:`DataError` naming it."""
    try:
        return open(path, "rb")
    except FileNotFoundError:
        raise DataError(f"{path}: no such file") from None
    except IsADirectoryError:
        raise DataError(f"{path}: is a directory, not a text file") from None
    except OSError as exc:
        raise DataError(f"{path}: cannot read ({exc.strerror or exc})") from None


def read_chunks(path, chunk_bytes):
    """Yield ``(first_line_number, block)``: blocks of whole lines of about ``chunk_bytes``.

    Line numbers count from 1. A line ends in ``\\n`` (Unix), ``\\r\\n`` (Windows) or ``\\r``
    alone (classic Mac OS); the blocks hold ``\\n`` only, one for each line end, so that
    line numbers count the lines as an editor shows them. A UTF-8 byte-order mark is
    skipped; a last line without a line end gets one.
    """
    chunk_bytes = max(4096, int(chunk_bytes))
    max_line = max(chunk_bytes, MAX_LINE)
    with open_input(path) as f:
        try:   # (no block beyond the file: a --memory of terabytes reads it at once)
            chunk_bytes = max(4096, min(chunk_bytes, os.fstat(f.fileno()).st_size + 1))
        except OSError:
            pass
        first, rest, start = 1, b"", True
        while True:
            block = f.read(chunk_bytes)
            if start:
                if block.startswith(b"\xef\xbb\xbf"):
                    block = block[3:]
                start = False
            if not block:
                if rest:
                    rest = _unix_line_ends(rest)
                    yield first, rest if rest.endswith(b"\n") else rest + b"\n"
                return
            data = rest + block if rest else block
            tail = b""
            if b"\r" in data:
                if data.endswith(b"\r"):  # (its \n, if any, is in the next block)
                    data, tail = data[:-1], b"\r"
                data = _unix_line_ends(data)
            cut = data.rfind(b"\n")
            if cut < 0:
                if len(data) > max_line:
                    raise DataError(f"{path}:{first}: the line is longer than "
                                    f"{max_line >> 20} MiB: not a text file of this format?")
                rest = data + tail
                continue
            chunk, rest = data[:cut + 1], data[cut + 1:] + tail
            yield first, chunk
            first += chunk.count(b"\n")


def _unix_line_ends(data):
    """``data`` with its Windows (``\\r\\n``) and classic Mac OS (``\\r``) line ends made
    ``\\n``."""
    return data.replace(b"\r\n", b"\n").replace(b"\r", b"\n")


def _first_data_line(chunk):
    """The first line of a block that is neither blank nor a comment (without its comment)."""
    pos = 0
    while pos < len(chunk):
        end = chunk.find(b"\n", pos)
        end = len(chunk) if end < 0 else end
        text = chunk[pos:end].split(b"#", 1)[0]
        if text.strip():
            return text
        pos = end + 1
    return b""


def _data_lines(chunk, first):
    """Line numbers of the data lines of a block (neither blank nor a comment)."""
    lines = chunk.split(b"\n")[:chunk.count(b"\n")]
    keep = [i for i, ln in enumerate(lines) if (s := ln.lstrip()) and s[:1] != b"#"]
    return first + np.asarray(keep, dtype=np.int64)


def _tok(t):
    """A token for a message: printable, one line, at most 40 characters."""
    s = "".join(c if c.isprintable() else "?" for c in t.decode("utf-8", "replace"))
    return s if len(s) <= 40 else s[:37] + "..."


def _where(src, line):
    return f"{src}:{line}"


#: Degrees, minutes and seconds: ``-12:34:56.7``, ``12d34m56.7s``, ``12°34'56.7"``, with
#: the seconds (or minutes and seconds) optional, a sign or a hemisphere (N, E positive; S,
#: W negative) before or after.
_DMS = re.compile(
    r"\s*(?P<h0>[NSEWnsew])?(?P<sign>[+-])?(?P<d>[0-9]+)(?:[:dD°º]\s*)"
    r"(?:(?P<m>[0-9]+(?:\.[0-9]*)?)(?:[:mM'′]\s*)?)?"
    r"(?:(?P<s>[0-9]+(?:\.[0-9]*)?)(?:[sS\"″]|'')?)?(?P<h1>[NSEWnsew])?\s*")


def dms_degrees(text):
    """Decimal degrees (long double) of an angle written in degrees, minutes and seconds
    (:data:`_DMS`), or None when ``text`` is not one. Raises ValueError for minutes or seconds
    of 60 or more, or two hemispheres."""
    m = _DMS.fullmatch(text)
    if m is None or (m["m"] is None and m["s"] is not None):
        return None
    if m["h0"] and m["h1"]:
        raise ValueError("two hemispheres")
    minutes = np.longdouble(m["m"] or "0")
    seconds = np.longdouble(m["s"] or "0")
    if minutes >= 60 or seconds >= 60:
        raise ValueError("minutes and seconds must be below 60")
    if m["s"] is not None and minutes != int(minutes):
        raise ValueError("decimal minutes before seconds")
    value = np.longdouble(m["d"]) + minutes / 60 + seconds / 3600
    hemi = (m["h0"] or m["h1"] or "").upper()
    negative = (m["sign"] == "-") != (hemi in ("S", "W"))
    return -value if negative else value


def _dms_token(tok, where, col):
    """A DMS token's decimal degrees, or None when it is not written in DMS."""
    try:
        text = tok.decode("utf-8")
    except UnicodeDecodeError:
        return None
    try:
        return dms_degrees(text)
    except ValueError as exc:
        raise DataError(f"{where}: '{_tok(tok)}' is no angle in degrees, minutes and seconds "
                        f"({exc}) {col}") from None


def _parse_token(fmt, ci, tok, angles, src, line, dms=()):
    cname, ctype = fmt.columns[ci]
    col = f"(column {ci + 1}, {cname})"
    if ((ctype == _ANGLE and angles == "deg") or cname in dms) and not _FLOAT_RE.fullmatch(tok):
        v = _dms_token(tok, _where(src, line), col)
        if v is not None:
            return v if ctype == _ANGLE else float(v)
    if ctype in (_ID, _INT):
        if not _INT_RE.fullmatch(tok):
            if _FLOAT_RE.fullmatch(tok):
                raise DataError(f"{_where(src, line)}: '{_tok(tok)}' is not an integer {col}")
            raise DataError(f"{_where(src, line)}: '{_tok(tok)}' is not a number {col}")
        v = int(tok)
        if not _INT64[0] <= v <= _INT64[1]:
            raise DataError(f"{_where(src, line)}: '{_tok(tok)}' is outside the int64 range "
                            f"{col}")
        return v
    if ctype == _KIND:
        return tok.lower()[:32]
    if ctype == _OPT and tok == b"-":
        return np.nan
    if not _FLOAT_RE.fullmatch(tok):
        raise DataError(f"{_where(src, line)}: '{_tok(tok)}' is not a number {col}")
    if ctype == _ANGLE and angles != "rad":
        return np.longdouble(tok.decode("ascii"))
    return float(tok)


def _parse_lines(fmt, chunk, first, lines, angles, src, refs=None, dms=()):
    """Slow path: parse a block line by line; returns the wide loadtxt-style array.

    On a syntax error the records before the bad line are value-checked first, so that the
    error reported is always the one on the earliest line.
    """
    dtype = fmt.load_dtype(fmt.max_cols, angles)
    rows = []
    text_lines = chunk.split(b"\n")
    for ln in lines.tolist():
        text = text_lines[ln - first].split(b"#", 1)[0]
        toks = text.split()
        try:
            if not fmt.min_cols <= len(toks) <= fmt.max_cols:
                raise DataError(f"{_where(src, ln)}: {fmt.expected()}, found {len(toks)}")
            vals = [_parse_token(fmt, i, t, angles, src, ln, dms) for i, t in enumerate(toks)]
        except DataError:
            done = np.array(rows, dtype=dtype) if rows else np.zeros(0, dtype)
            check_records(fmt, done, _normalize(fmt, done, fmt.max_cols, angles),
                          lines[:len(rows)], src, refs)
            raise
        for cname, _ in fmt.columns[len(vals):]:
            vals.append(fmt.defaults.get(cname, 0))
        rows.append(tuple(vals))
    return np.array(rows, dtype=dtype) if rows else np.zeros(0, dtype)


def _normalize(fmt, arr, ncols, angles):
    """Parsed records (``fmt.dtype``) from a loadtxt-style array of ``ncols`` columns."""
    out = np.zeros(len(arr), fmt.dtype)
    for i, (cname, ctype) in enumerate(fmt.columns):
        if i >= ncols:
            if ctype == _KIND:
                out[cname] = fmt.words[cname][fmt.defaults[cname].decode()]
            continue
        if ctype == _ANGLE:
            out[cname] = to_radians(arr[cname], angles)
        elif ctype == _KIND:
            codes = np.full(len(arr), -1, np.int8)
            words = np.char.lower(arr[cname])
            for word, code in fmt.words[cname].items():
                codes[words == word.encode()] = code
            out[cname] = codes
        else:
            out[cname] = arr[cname]
    return out


def _loadtxt(fmt, text, ncols, angles):
    if fmt is CONTROL:
        text = _DASH.sub(b"nan", text)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return np.loadtxt(io.BytesIO(text), dtype=fmt.load_dtype(ncols, angles), comments="#",
                          ndmin=1)


def _load_grouped(fmt, chunk, first, lines, angles):
    """A block whose lines differ in their optional columns: loadtxt per column count, the
    rows put back in line order (the wide loadtxt-style array), or None if that fails."""
    text_lines = chunk.split(b"\n")
    data = [text_lines[i] for i in (lines - first).tolist()]
    counts = np.fromiter((len(ln.split(b"#", 1)[0].split()) for ln in data), np.int64,
                         len(data))
    wide = np.zeros(len(data), fmt.load_dtype(fmt.max_cols, angles))
    for cname, default in fmt.defaults.items():
        wide[cname] = default
    for nc in np.unique(counts).tolist():
        if not fmt.min_cols <= nc <= fmt.max_cols:
            return None
        idx = np.flatnonzero(counts == nc)
        try:
            arr = _loadtxt(fmt, b"\n".join([data[i] for i in idx.tolist()]) + b"\n", nc,
                           angles)
        except ValueError:
            return None
        if len(arr) != len(idx):
            return None
        for name in arr.dtype.names:
            wide[name][idx] = arr[name]
    return wide


def parse_chunk(fmt, chunk, first, angles, src, refs=None, dms=()):
    """Records (``fmt.dtype``) and line numbers of a block of whole lines.

    ``src`` names the file in messages. ``refs(rec)`` may add checks (``(mask, message(i))``
    pairs, e.g. that referenced ids exist). Raises :class:`DataError` for the first bad line.
    Angles in degrees (``angles`` "deg") and the columns named in ``dms`` (geographic
    coordinates) may also be written in degrees, minutes and seconds (:func:`dms_degrees`).
    """
    head = _first_data_line(chunk)
    if not head:
        return np.zeros(0, fmt.dtype), np.zeros(0, np.int64)
    n_lines = chunk.count(b"\n")
    ncols = len(head.split())
    arr, lines = None, None
    fast = fmt.min_cols <= ncols <= fmt.max_cols and not (
        fmt is PHOTOS and angles != "rad" and (b"x" in chunk or b"X" in chunk or b"(" in chunk))
    if fast:
        try:
            arr = _loadtxt(fmt, chunk, ncols, angles)
        except ValueError:
            arr = None
        if arr is not None:
            if len(arr) == n_lines:  # no line was skipped: no blank or comment line
                lines = first + np.arange(n_lines, dtype=np.int64)
            else:
                lines = _data_lines(chunk, first)
                if len(arr) != len(lines):
                    arr = None
    if arr is None and fast and fmt.min_cols < fmt.max_cols:
        if lines is None:
            lines = _data_lines(chunk, first)
        arr = _load_grouped(fmt, chunk, first, lines, angles)  # optional columns mixed
        ncols = fmt.max_cols
    rec = None if arr is None else _normalize(fmt, arr, ncols, angles)
    if fmt is CONTROL and rec is not None and (rec["kind"] < 0).any():
        rec = None  # name the unknown kind as written (the fast path read '-' as nan)
    if rec is None:
        if lines is None:
            lines = _data_lines(chunk, first)
        arr = _parse_lines(fmt, chunk, first, lines, angles, src, refs, dms)
        rec = _normalize(fmt, arr, fmt.max_cols, angles)
    if fmt is CAMERAS:
        refs = _whole_frames(refs, _token_counts(chunk, first, lines))
    check_records(fmt, arr, rec, lines, src, refs)
    if fmt is CONTROL:
        _settle_control(rec)
    return rec, lines


def _token_counts(chunk, first, lines):
    """The number of columns of each of ``lines`` of a block."""
    text_lines = chunk.split(b"\n")
    return np.fromiter((len(text_lines[i].split(b"#", 1)[0].split())
                        for i in (lines - first).tolist()), np.int64, len(lines))


def _whole_frames(refs, counts):
    """``refs`` with the check that a camera's image frame (columns 16-22) is given whole:
    a unit with fewer columns, or some of columns 17-22 without the rest, would be read with
    defaults for the rest."""
    def checks(rec):
        bad = ((counts > 16) & (counts < 22)) | ((counts == 16) & (rec["frame"] >= 0))
        return list(refs(rec) if refs else []) + [(bad, lambda i: (
            f"an image frame needs columns 16-22 (mm|px pixel_x pixel_y width height "
            f"origin y_axis), found {int(counts[i])} columns"))]
    return checks


# -- value checks ----------------------------------------------------------------------

def _col(fmt, name):
    return next(i for i, (c, _) in enumerate(fmt.columns) if c == name) + 1


def _finite_checks(fmt, rec, names):
    out = []
    for name in names:
        v = rec[name]
        out.append((~np.isfinite(v), lambda i, n=name, v=v: (
            f"column {_col(fmt, n)} ({n}) is {_num(v[i])}, expected a finite number")))
    return out


def _num(x):
    return repr(float(x))


def _checks(fmt, arr, rec):
    """(mask, message(i)) pairs in column order."""
    if fmt is MEASUREMENTS:
        c = _finite_checks(fmt, rec, ("x", "y", "sigma"))
        c.append((rec["sigma"] < 0, lambda i: (
            f"sigma must not be negative, found {_num(rec['sigma'][i])} (column 5)")))
        return c
    if fmt is CAMERAS:
        names = [n for n, t in fmt.columns[1:] if t != _KIND]
        c = _finite_checks(fmt, rec, names)
        c.append((rec["model"] < 0, lambda i: (
            f"unknown distortion model '{_tok(arr['model'][i])}' (column 15); expected "
            f"forward (added to the ideal point) or backward (correcting the measured one)")))
        for n, col, what in (("frame", 16, "image unit; expected mm or px"),
                             ("origin", 21, "image origin; expected centre, topleft or "
                                            "bottomleft"),
                             ("y_axis", 22, "image y axis; expected up or down")):
            c.append((rec[n] == -1, lambda i, n=n, col=col, what=what: (
                f"unknown {what}, found '{_tok(arr[n][i])}' (column {col})")))
        c.append((~(rec["focal_length"] > 0), lambda i: (
            f"focal_length must be positive, found {_num(rec['focal_length'][i])} "
            f"(column 2)")))
        for n in ("format_x", "format_y"):
            c.append((rec[n] < 0, lambda i, n=n: (
                f"{n} must not be negative, found {_num(rec[n][i])} "
                f"(column {_col(fmt, n)})")))
        c.append((~(rec["sigma_image"] > 0), lambda i: (
            f"sigma_image must be positive, found {_num(rec['sigma_image'][i])} (column 7)")))
        return c
    if fmt is PHOTOS:
        st = rec["strip"]
        c = [((st < -1) | (st > np.iinfo(np.int32).max), lambda i: (
            f"strip must be -1 (unknown) or a flight line number >= 0, found {st[i]} "
            f"(column 3)"))]
        c += _finite_checks(fmt, rec, ("omega", "phi", "kappa", "X", "Y", "Z"))
        return c
    if fmt is CONTROL:
        kind = rec["kind"]
        k_ok = np.clip(kind, 0, KIND_CHECK)
        need, ctrl = NEEDED[k_ok], CONTROL_MASK[k_ok].astype(bool)

        def what(i):
            k = int(kind[i])
            return "a check point" if k == KIND_CHECK else f"a {KIND_WORD_OF[k]} control point"

        c = [(kind < 0, lambda i: (
            f"unknown kind '{_tok(arr['kind'][i])}' (column 8); expected full, horizontal, "
            f"vertical or check"))]
        for k, n in enumerate(("X", "Y", "Z")):
            v = rec[n]
            c.append((np.isinf(v), lambda i, n=n, v=v, k=k: (
                f"column {k + 2} ({n}) is {_num(v[i])}, expected a finite number or '-'")))
            c.append((np.isnan(v) & need[:, k], lambda i, n=n, k=k: (
                f"{n} is unknown ('-' or nan) but {what(i)} needs it (column {k + 2})")))
        for k, n in enumerate(("sX", "sY", "sZ")):
            v = rec[n]
            c.append((np.isinf(v), lambda i, n=n, v=v, k=k: (
                f"column {k + 5} ({n}) is {_num(v[i])}, expected a finite number or '-'")))
            c.append((v < 0, lambda i, n=n, v=v, k=k: (
                f"{n} must not be negative (0 fixes the coordinate), found {_num(v[i])} "
                f"(column {k + 5})")))
            c.append((np.isnan(v) & ctrl[:, k], lambda i, n=n, k=k: (
                f"{n} is unknown ('-' or nan) but {what(i)} needs it (column {k + 5}; "
                f"0 fixes the coordinate)")))
        return c
    if fmt is PHOTOS_MATRIX:
        st = rec["strip"]
        c = [((st < -1) | (st > np.iinfo(np.int32).max), lambda i: (
            f"strip must be -1 (unknown) or a flight line number >= 0, found {st[i]} "
            f"(column 3)"))]
        c += _finite_checks(fmt, rec, MATRIX_TERMS + ("X", "Y", "Z"))
        m = np.stack([rec[t] for t in MATRIX_TERMS], axis=1).reshape(-1, 3, 3)
        err = np.abs(m @ np.transpose(m, (0, 2, 1)) - np.eye(3)).max(axis=(1, 2))
        bad = ~(err < 1e-6) | ~(np.linalg.det(np.where(np.isfinite(m), m, 0.0)) > 0)
        c.append((bad, lambda i: (
            f"the matrix (columns 4-12) is not a rotation: |M M' - I| = {_num(err[i])}, "
            f"expected below 1e-6 and det M = +1")))
        return c
    if fmt is PRIORS:
        c = _finite_checks(fmt, rec, PRIOR_PARAMETERS)
        sig = np.stack([rec["s_" + n] for n in PRIOR_PARAMETERS], axis=1)
        for k, n in enumerate(PRIOR_PARAMETERS):
            v = sig[:, k]
            c.append((np.isinf(v) | (v < 0), lambda i, n=n, v=v, k=k: (
                f"column {k + 8} (s_{n}) is {_num(v[i])}, expected a sigma > 0, or 0 or '-' "
                f"for an unconstrained parameter")))
        c.append((~(sig > 0).any(axis=1), lambda i: (
            "every sigma is 0 or '-': the prior constrains nothing (columns 8-13)")))
        return c
    if fmt is PRIOR_COVARIANCES:
        return _finite_checks(fmt, rec, PRIOR_PARAMETERS + COVARIANCE_TERMS)
    raise ValueError(fmt)


def check_records(fmt, arr, rec, lines, src, refs=None):
    """Raise :class:`DataError` for the earliest line whose values are invalid."""
    if not len(rec):
        return
    best = None
    for mask, message in _checks(fmt, arr, rec) + (refs(rec) if refs else []):
        idx = np.flatnonzero(mask)
        if len(idx) and (best is None or idx[0] < best[0]):
            best = (int(idx[0]), message)
    if best is not None:
        i, message = best
        raise DataError(f"{_where(src, int(lines[i]))}: {message(i)}")


def _settle_control(rec):
    """Unknown ('-', nan) and uncontrolled sigmas become 0, so that all values are finite."""
    for k, (n, s) in enumerate((("X", "sX"), ("Y", "sY"), ("Z", "sZ"))):
        unknown = np.isnan(rec[n])
        rec[n][unknown] = 0.0
        rec[s][unknown | np.isnan(rec[s])] = 0.0


# -- writing ---------------------------------------------------------------------------

_HEADERS = {
    "cameras": "# cameras: id focal_length x0 y0 format_x format_y sigma_image [k1 k2 k3 p1 p2 "
               "[b1 b2 [forward|backward [mm|px pixel_x pixel_y width height origin y_axis]]]]  "
               "(mm; k1..k3 mm^-2, mm^-4, mm^-6, p1 p2 mm^-1)",
    "additional_parameters": "# additional parameters: camera set base a1 ... aN  (set "
                             "ebner: 12, gruen: 44 coefficients; base and coefficients "
                             "in mm)",
    "photos": "# photos: id camera strip omega phi kappa X Y Z  (angles in {angles}, "
              "X Y Z in m; strip -1 = unknown)",
    "measurements": "# measurements: photo point x y sigma  (mm; sigma 0 = the camera's "
                    "sigma_image)",
    "control": "# control: point X Y Z sX sY sZ kind  (m; sigma 0 fixes the coordinate; "
               "'-' = unknown)",
}


def _nonzero_bits(a):
    return np.ascontiguousarray(a, np.float64).view(np.int64) != 0


def export_text(project_path, out_dir, angles="deg", chunk=CHUNK_RECORDS, rotation="opk"):
    """Write a project's input records as ``cameras.txt``, ``photos.txt``,
    ``measurements.txt`` and ``control.txt`` in ``out_dir``, and
    ``additional_parameters.txt`` when a camera has an additional-parameter set.

    Floats are written as the shortest decimal that reads back to the same float64 (angles in
    ``angles`` units, see :func:`angle_strings`), so :func:`sapgo.ingest.import_text` of the
    files reproduces the records bitwise. Records are streamed in chunks of ``chunk``; per
    station vectors (ids) are held in core. Points of kind pass do not appear in
    ``control.txt``; observation statuses, station priors, approximate point coordinates and
    solutions are not exported. ``rotation``: the order of the photos' three angles
    (:data:`sapgo.frames.ROTATION_ORDERS`; other than ``"opk"`` they are converted and
    read back to about 1e-15 rad, not bitwise). Returns a dict with the paths and record
    counts.
    """
    from ..frames import _check_order, order_of_opk

    check_angles(angles)
    _check_order(rotation)
    out_dir = Path(out_dir)
    paths = {k: out_dir / f"{k}.txt" for k in ("cameras", "photos", "measurements", "control")}
    counts = dict.fromkeys(paths, 0)
    inexact = 0
    with Project(project_path) as p:   # (a project that cannot be read: no directory made)
        out_dir.mkdir(parents=True, exist_ok=True)
        cams = p.cameras()
        with open(paths["cameras"], "w") as f:
            f.write(_HEADERS["cameras"] + "\n")
            for c in cams:
                vals = [c[n] for n in ("focal_length", "x0", "y0", "format_x", "format_y",
                                       "sigma_image")]
                dist = [c[n] for n in ("k1", "k2", "k3", "p1", "p2")]
                aff = [c[n] for n in ("b1", "b2")]
                backward = int(c["distortion_model"]) == MODEL_WORDS["backward"]
                if backward or _nonzero_bits(np.array(dist + aff)).any():
                    vals += dist
                if backward or _nonzero_bits(np.array(aff)).any():
                    vals += aff
                words = [repr(float(v)) for v in vals] + (["backward"] if backward else [])
                f.write(" ".join([str(int(c["id"]))] + words) + "\n")
                counts["cameras"] += 1
        if cams["ap_set"].any():   # (import --additional-parameters)
            paths["additional_parameters"] = out_dir / "additional_parameters.txt"
            counts["additional_parameters"] = 0
            with open(paths["additional_parameters"], "w") as f:
                f.write(_HEADERS["additional_parameters"] + "\n")
                for c in cams[cams["ap_set"] != 0]:
                    s_ = int(c["ap_set"])
                    coef = [repr(float(c[n])) for n in AP_NAMES[:int(N_TERMS[s_])]]
                    f.write(" ".join([str(int(c["id"])), AP_SETS[s_],
                                      repr(float(c["ap_base"]))] + coef) + "\n")
                    counts["additional_parameters"] += 1
        cam_ids = cams["id"]
        station_ids = p.read_field("stations", "id")
        with open(paths["photos"], "w") as f:
            f.write(_HEADERS["photos"].format(angles=angles).replace(
                "omega phi kappa", {"opk": "omega phi kappa", "pok": "phi omega kappa",
                                    "kpo": "kappa phi omega"}[rotation]) + "\n")
            for a, b in p.chunks("stations", chunk):
                st = p.read("stations", a, b)
                eo = st["eo"]
                if rotation != "opk":
                    eo = np.column_stack([order_of_opk(eo[:, :3], rotation), eo[:, 3:]])
                ang = []
                for k in range(3):
                    s, bad = angle_strings(eo[:, k], angles)
                    ang.append(s)
                    inexact += bad
                lines = [
                    f"{i} {c} {s} {w} {ph} {ka} {x!r} {y!r} {z!r}"
                    for i, c, s, w, ph, ka, x, y, z in zip(
                        st["id"].tolist(), cam_ids[st["camera"]].tolist(), st["strip"].tolist(),
                        ang[0], ang[1], ang[2], eo[:, 3].tolist(), eo[:, 4].tolist(),
                        eo[:, 5].tolist())
                ]
                f.write("\n".join(lines) + "\n")
                counts["photos"] += len(lines)
        with open(paths["measurements"], "w") as fm, open(paths["control"], "w") as fc:
            fm.write(_HEADERS["measurements"] + "\n")
            fc.write(_HEADERS["control"] + "\n")
            for a, b in p.chunks("points", chunk):
                pts = p.read("points", a, b)
                o0 = int(pts["obs_start"][0])
                o1 = int(pts["obs_start"][-1] + pts["n_obs"][-1])
                obs = p.read("observations", o0, o1)
                pid = pts["id"]
                rows = zip(station_ids[obs["station"]].tolist(),
                           np.repeat(pid, pts["n_obs"]).tolist(), obs["x"].tolist(),
                           obs["y"].tolist(), obs["sigma"].tolist())
                text = "\n".join(f"{s} {q} {x!r} {y!r} {g!r}" for s, q, x, y, g in rows)
                if text:
                    fm.write(text + "\n")
                counts["measurements"] += len(obs)
                ctl = pts[pts["kind"] != KIND_PASS]
                odd = ctl["id"][~np.isin(ctl["kind"], list(KIND_WORD_OF))]
                if len(odd):
                    raise DataError(f"{project_path}: point {odd[0]} has an unknown kind")
                lines = []
                for r in ctl:
                    kind = int(r["kind"])
                    need = NEEDED[kind]
                    vals, sigs = [], []
                    for k in range(3):
                        v, s = float(r["control"][k]), float(r["control_sigma"][k])
                        unknown = (not need[k] and np.float64(v).view(np.int64) == 0
                                   and np.float64(s).view(np.int64) == 0)
                        vals.append("-" if unknown else repr(v))
                        sigs.append("-" if unknown else repr(s))
                    lines.append(" ".join([str(int(r["id"]))] + vals + sigs
                                          + [KIND_WORD_OF[kind]]))
                if lines:
                    fc.write("\n".join(lines) + "\n")
                counts["control"] += len(lines)
    return {"paths": {k: str(v) for k, v in paths.items()}, "counts": counts,
            "angles": angles, "inexact_angles": inexact}


def export_adjusted(project_path, out_dir, angles="deg", orientation="tangent",
                    chunk=CHUNK_RECORDS, rotation="opk"):
    """Write the adjusted photos and points of an adjusted project in the user's CRS:
    ``adjusted_photos.txt`` (``id camera strip omega phi kappa X Y Z``) and
    ``adjusted_points.txt`` (``id X Y Z kind n_obs``; excluded points are left out).

    For a project imported with a CRS the coordinates are converted back into it (a
    geographic CRS: longitude, latitude in degrees, ellipsoidal height) and the angles are
    given per ``orientation`` (``"tangent"``: to the east-north-up frame at each photo, or
    ``"geocentric"``); for a local project they are the frame's. ``rotation``: the order
    of the three angles (:data:`sapgo.frames.ROTATION_ORDERS`). Streams in chunks.
    Returns a dict with the paths and counts.
    """
    from ..frames import _check_order, order_of_opk

    check_angles(angles)
    _check_order(rotation)
    names = {"opk": "omega phi kappa", "pok": "phi omega kappa",
             "kpo": "kappa phi omega"}[rotation]
    out_dir = Path(out_dir)
    paths = {"photos": out_dir / "adjusted_photos.txt",
             "points": out_dir / "adjusted_points.txt"}
    counts = dict.fromkeys(paths, 0)
    with Project(project_path) as p:
        if not p.has_solution:
            raise DataError(f"{project_path}: the project has no adjusted solution: run "
                            f"'sapgo adjust' first")
        out_dir.mkdir(parents=True, exist_ok=True)
        frame = p.frame()
        if frame.kind == "local space rectangular":
            where, axes = "", "frame X, Y, Z in m"
        else:
            crs = frame.crs
            if crs.is_geocentric:
                axes = "geocentric X, Y, Z in m"
            elif crs.is_geographic:
                axes = "longitude, latitude in degrees, ellipsoidal height in m"
            else:
                unit = crs.axis_info[0].unit_name
                axes = f"easting, northing in {unit}, ellipsoidal height in m"
            where = f"; {crs.name}; angles {orientation}"
        cam_ids = p.cameras()["id"]
        with open(paths["photos"], "w") as f:
            f.write(f"# adjusted photos: id camera strip {names} X Y Z  (angles in "
                    f"{angles}; X Y Z: {axes}{where})\n")
            for a, b in p.chunks("stations", chunk):
                st = p.read("stations", a, b)
                eo = st["eo"] + p.solution("station_corr", a, b)
                opk = order_of_opk(frame.opk_to_user(eo[:, :3], eo[:, 3:], orientation),
                                   rotation)
                xyz = frame.to_user(eo[:, 3:])
                ang = (opk if angles == "rad" else
                       opk / float(_ANGLE_FACTOR[angles]))
                act = st["status"] == 0
                for i in np.flatnonzero(act):
                    f.write(" ".join([str(int(st["id"][i])), str(int(cam_ids[st["camera"][i]])),
                                      str(int(st["strip"][i]))]
                                     + [repr(float(v)) for v in ang[i]]
                                     + [repr(float(v)) for v in xyz[i]]) + "\n")
                counts["photos"] += int(act.sum())
        with open(paths["points"], "w") as f:
            f.write(f"# adjusted points: id X Y Z kind n_obs  (X Y Z: {axes}{where})\n")
            for a, b in p.chunks("points", chunk):
                pts = p.read("points", a, b)
                xyz = frame.to_user(pts["xyz"] + p.solution("point_corr", a, b))
                act = pts["status"] == 0
                for i in np.flatnonzero(act):
                    f.write(" ".join([str(int(pts["id"][i]))]
                                     + [repr(float(v)) for v in xyz[i]]
                                     + [KIND_WORD_OF.get(int(pts["kind"][i]), "pass"),
                                        str(int(pts["n_obs"][i]))]) + "\n")
                counts["points"] += int(act.sum())
    return {"paths": {k: str(v) for k, v in paths.items()}, "counts": counts}
