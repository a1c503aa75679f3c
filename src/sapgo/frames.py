"""Coordinate systems: the user's CRS and the frame the adjustment computes in (pyproj).

A project holds object coordinates in one Cartesian **computation frame** (root attribute
``frame``):

- ``local space rectangular``: coordinates as the user gave them (no CRS; the default);
- ``local tangent``: an Earth block, in the east-north-up frame at the block centre
  (attribute ``frame_origin``: latitude, longitude in degrees and ellipsoidal height in m of
  the origin): ``x = R (X_ecef - X0_ecef)``;
- ``selenocentric``: a lunar block, in the Moon-fixed Cartesian frame of the IAU 2015 sphere
  (R = 1 737 400 m).

The user's CRS (root attribute ``crs``, WKT) may be any CRS pyproj knows with a height:
geocentric (EPSG:4978), geographic 3D (EPSG:4979; columns X = longitude, Y = latitude in
degrees, Z = ellipsoidal height), a geographic 2D or projected CRS (its heights taken as
ellipsoidal), or a lunar CRS (IAU_2015:30100 and its projections). Orientation angles are
given relative to the local tangent frame at each station (``tangent``: what GNSS/INS and
orbit data give) or relative to the body-fixed geocentric axes (``geocentric``); the frame's
own omega-phi-kappa follow from the rotation ``M_frame = M_given R_given R_frame'``, where
``R`` turns body-fixed vectors into the respective axes.

Everything here works on arrays of any length; the conversions are exact to rounding (pyproj
for the datum, closed-form rotations for the frames).
"""

from __future__ import annotations

import json

import numpy as np

from .errors import DataError, ParameterError

LOCAL = "local space rectangular"
TANGENT = "local tangent"
SELENOCENTRIC = "selenocentric"
FRAMES = (LOCAL, TANGENT, SELENOCENTRIC)
#: How omega-phi-kappa of photos are given (``sapgo import --orientation``).
ORIENTATIONS = ("tangent", "geocentric")

MOON_RADIUS = 1737400.0
_MOON_CRS = "IAU_2015:30100"


def parse_crs(text):
    """A :class:`pyproj.CRS` of an EPSG/IAU code, WKT or PROJ string; ParameterError naming
    the text otherwise."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        return CRS.from_user_input(text)
    except CRSError as exc:
        raise ParameterError(f"unknown coordinate reference system {text!r}: {exc}") from None


def body_of(crs):
    """``"earth"`` or ``"moon"`` from the CRS's ellipsoid; DataError for other bodies."""
    ell = crs.ellipsoid
    a = ell.semi_major_metre if ell is not None else float("nan")
    if abs(a - 6378137.0) < 50000.0:
        return "earth"
    if abs(a - MOON_RADIUS) < 5000.0:
        return "moon"
    raise DataError(f"CRS {crs.name!r}: a body of radius {a:.0f} m is neither the Earth nor "
                    f"the Moon")


def _geocentric(body):
    from pyproj import CRS
    from pyproj.crs import GeocentricCRS

    if body == "earth":
        return CRS.from_epsg(4978)
    return GeocentricCRS(name="Moon (2015) - Sphere / Ocentric, Cartesian",
                         datum=CRS.from_user_input(_MOON_CRS).datum)


def _geographic(body):
    from pyproj import CRS

    if body == "earth":
        return CRS.from_epsg(4979)
    return CRS.from_user_input(_MOON_CRS).to_3d()


def _as_3d(crs):
    """The CRS with a height axis (a 2D geographic or projected CRS: ellipsoidal heights)."""
    if len(crs.axis_info) >= 3 or crs.is_geocentric:
        return crs
    return crs.to_3d()


class OutsideDomain(DataError):
    """Coordinates a CRS transformation cannot take; ``row``: the first of them in the
    array given (callers name its record)."""

    def __init__(self, message, row):
        super().__init__(message)
        self.row = row


def _transform(src, dst, xyz):
    from pyproj import Transformer
    from pyproj.exceptions import ProjError

    t = Transformer.from_crs(src, dst, always_xy=True)
    if "ballpark" in t.description.lower():
        raise DataError(f"no accurate transformation from {src.name!r} to {dst.name!r} is "
                        f"available (pyproj offers only '{t.description}', e.g. a geoid "
                        f"model for orthometric heights is missing): give coordinates with "
                        f"ellipsoidal heights")
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    try:
        out = np.column_stack(t.transform(xyz[:, 0], xyz[:, 1], xyz[:, 2], errcheck=True))
    except ProjError as exc:   # (which coordinates: those the unchecked call leaves inf)
        bad = ~np.isfinite(np.column_stack(t.transform(xyz[:, 0], xyz[:, 1],
                                                       xyz[:, 2]))).all(axis=1)
        row = int(np.flatnonzero(bad)[0]) if bad.any() else 0
        why = " ".join(str(exc).split())
        raise OutsideDomain(
            f"coordinates ({', '.join(f'{v:.10g}' for v in xyz[row])}) are outside the domain "
            f"of {src.name!r} ({why}; a latitude beyond 90 degrees, or the axes swapped?)",
            row) from None
    return out


def enu_rotation(lat_deg, lon_deg):
    """Rotations (n x 3 x 3) turning body-fixed vectors into east, north, up at geodetic
    ``lat``, ``lon`` (degrees)."""
    lat = np.radians(np.asarray(lat_deg, np.float64)).reshape(-1)
    lon = np.radians(np.asarray(lon_deg, np.float64)).reshape(-1)
    sl, cl, sb, cb = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    z = np.zeros_like(lat)
    return np.stack([np.stack([-sb, cb, z], axis=1),
                     np.stack([-sl * cb, -sl * sb, cl], axis=1),
                     np.stack([cl * cb, cl * sb, sl], axis=1)], axis=1)


def rotation_matrices(opk):
    """``M = R3(kappa) R2(phi) R1(omega)`` for rows of (omega, phi, kappa) radians."""
    from .geometry import rotation_matrix

    opk = np.asarray(opk, np.float64).reshape(-1, 3)
    return np.array([rotation_matrix(w, p, k) for w, p, k in opk]).reshape(-1, 3, 3)


#: Orders of the three angles of a photo (``--rotation``; the files' columns in that order):
#: ``opk`` ``M = R3(kappa) R2(phi) R1(omega)`` (sapgo's), ``pok`` (phi-omega-kappa, Y
#: primary) ``M = R3(kappa) R1(omega) R2(phi)``, ``kpo`` (kappa-phi-omega) ``M = R1(omega)
#: R2(phi) R3(kappa)``; ``R1``, ``R2``, ``R3`` the rotations of the frame about its x, y, z
#: axes (docs/theory.md section 1). Each is the transpose of scipy's intrinsic Euler
#: rotation of the same angles in the order given: ``M' = Rx Ry Rz`` for ``opk``.
ROTATION_ORDERS = {"opk": "XYZ", "pok": "YXZ", "kpo": "ZYX"}


def _check_order(order):
    from .errors import ParameterError

    if order not in ROTATION_ORDERS:
        raise ParameterError(f"rotation order {order!r}: choose one of "
                             f"{', '.join(ROTATION_ORDERS)}")


def matrices_of_angles(a, order="opk"):
    """``M`` (n x 3 x 3, object to image) of angles (n x 3, radians) in the file's order:
    ``(omega, phi, kappa)``, ``(phi, omega, kappa)`` or ``(kappa, phi, omega)``."""
    from scipy.spatial.transform import Rotation

    _check_order(order)
    a = np.asarray(a, np.float64).reshape(-1, 3)
    return np.transpose(Rotation.from_euler(ROTATION_ORDERS[order], a).as_matrix()
                        .reshape(-1, 3, 3), (0, 2, 1))


def angles_of_matrices(m, order="opk"):
    """The inverse of :func:`matrices_of_angles` (the middle angle in -90..90 degrees)."""
    from scipy.spatial.transform import Rotation

    _check_order(order)
    m = np.asarray(m, np.float64).reshape(-1, 3, 3)
    if order == "opk":
        return opk_of(m)
    import warnings

    with warnings.catch_warnings():   # (gimbal lock: scipy warns and sets the third to 0)
        warnings.simplefilter("ignore", UserWarning)
        return Rotation.from_matrix(np.transpose(m, (0, 2, 1))).as_euler(
            ROTATION_ORDERS[order])


def opk_of_order(a, order="opk"):
    """omega, phi, kappa (n x 3) of angles in ``order`` (``opk``: the same values)."""
    a = np.asarray(a, np.float64).reshape(-1, 3)
    if order == "opk":
        return a.copy()
    return opk_of(matrices_of_angles(a, order))


def order_of_opk(opk, order="opk"):
    """The inverse of :func:`opk_of_order`."""
    opk = np.asarray(opk, np.float64).reshape(-1, 3)
    if order == "opk":
        return opk.copy()
    return angles_of_matrices(rotation_matrices(opk), order)


def prior_of_order(value, weight, order="opk"):
    """Prior values (n x 6: three angles in ``order``, X, Y, Z) and weights (n x 6 x 6, the
    angles' rows and columns in the same order) as omega, phi, kappa: the weights carried
    over with the Jacobian ``T`` of the conversion, ``W = T^-T W T^-1`` (``T`` by central
    differences, as :meth:`Frame.prior_from_user`)."""
    value = np.asarray(value, np.float64).reshape(-1, 6)
    weight = np.asarray(weight, np.float64).reshape(-1, 6, 6)
    if order == "opk":
        return value.copy(), weight.copy()
    eye = np.broadcast_to(np.eye(3), (len(value), 3, 3))
    return (np.column_stack([opk_of_order(value[:, :3], order), value[:, 3:]]),
            carried_weights(weight, lambda a: opk_of_order(a, order), value[:, :3], eye))


def carried_weights(weight, convert, angles, q):
    """Station prior weights (n x 6 x 6) carried through a change of their parameters:
    the angles by ``convert`` (n x 3 -> n x 3, its Jacobian by central differences), the
    positions by the rotations ``q`` (n x 3 x 3; the cross terms left out), ``W' = T^-T W
    T^-1``, symmetrised."""
    h = 1e-7
    g = np.empty((len(angles), 3, 3))
    for k in range(3):
        hi, lo = angles.copy(), angles.copy()
        hi[:, k] += h
        lo[:, k] -= h
        d = convert(hi) - convert(lo)
        g[:, :, k] = ((d + np.pi) % (2 * np.pi) - np.pi) / (2 * h)
    t = np.zeros((len(angles), 6, 6))
    t[:, :3, :3] = g
    t[:, 3:, 3:] = q
    ti = np.linalg.inv(t)
    w = np.transpose(ti, (0, 2, 1)) @ weight @ ti
    return 0.5 * (w + np.transpose(w, (0, 2, 1)))


def opk_of(m):
    """(omega, phi, kappa) of rotation matrices ``M = R3 R2 R1`` (n x 3 x 3)."""
    m = np.asarray(m, np.float64).reshape(-1, 3, 3)
    phi = np.arcsin(np.clip(m[:, 2, 0], -1.0, 1.0))
    omega = np.arctan2(-m[:, 2, 1], m[:, 2, 2])
    kappa = np.arctan2(-m[:, 1, 0], m[:, 0, 0])
    # phi = +-90 deg: omega and kappa are not separable; omega = 0 and kappa from the rest
    lock = np.hypot(m[:, 0, 0], m[:, 1, 0]) < 1e-9
    omega[lock] = 0.0
    kappa[lock] = np.arctan2(m[lock, 0, 1], m[lock, 1, 1])
    return np.column_stack([omega, phi, kappa])


def frame_info(frame):
    """The frame for reports: ``{"kind", "crs", "origin"}`` (crs: its name, or None)."""
    return {"kind": frame.kind, "crs": frame.crs.name if frame.crs_text else None,
            "origin": None if frame.origin is None else [float(v) for v in frame.origin],
            "description": frame.describe()}


class Frame:
    """The computation frame of a project and the user's CRS (see the module docstring)."""

    def __init__(self, kind=LOCAL, crs="", origin=None):
        if kind not in FRAMES:
            raise ParameterError(f"unknown frame {kind!r}; one of {', '.join(FRAMES)}")
        self.kind = kind
        self.crs_text = crs or ""
        self.origin = None if origin is None else np.asarray(origin, np.float64)
        self._crs = None

    # -- construction and storage ------------------------------------------------------
    @classmethod
    def for_crs(cls, crs, station_xyz):
        """The frame for a block given in ``crs`` (text or CRS) with projection centres
        ``station_xyz`` (in that CRS): the tangent frame at the centre for the Earth
        (origin: the mean centre's latitude and longitude, height 0), selenocentric for the
        Moon."""
        crs = parse_crs(crs) if isinstance(crs, str) else crs
        body = body_of(crs)
        wkt = crs.to_wkt()
        if body == "moon":
            return cls(SELENOCENTRIC, wkt)
        ecef = _transform(_as_3d(crs), _geocentric(body), station_xyz)
        centre = ecef.mean(axis=0)
        lon, lat, _ = _transform(_geocentric(body), _geographic(body), centre)[0]
        return cls(TANGENT, wkt, (lat, lon, 0.0))

    @classmethod
    def from_attrs(cls, attrs):
        """The frame stored in a project's root attributes (old files: local)."""
        kind = str(attrs.get("frame", LOCAL) or LOCAL)
        if kind not in FRAMES:
            kind = LOCAL
        origin = attrs.get("frame_origin")
        return cls(kind, str(attrs.get("crs", "") or ""),
                   None if origin is None or len(origin) != 3 else origin)

    def to_attrs(self):
        out = {"frame": self.kind, "crs": self.crs_text}
        if self.origin is not None:
            out["frame_origin"] = self.origin
        return out

    def describe(self):
        """One line for reports."""
        if self.kind == LOCAL:
            return LOCAL
        name = self.crs.name
        if self.kind == TANGENT:
            lat, lon, h = self.origin
            return (f"{TANGENT} (east, north, up at {lat:.6f}, {lon:.6f}; user's CRS {name})")
        return f"{SELENOCENTRIC} (IAU 2015 Moon sphere; user's CRS {name})"

    def to_json(self):
        return json.dumps({"frame": self.kind, "crs": self.crs_text,
                           "origin": None if self.origin is None else self.origin.tolist()})

    # -- properties --------------------------------------------------------------------
    @property
    def crs(self):
        if self._crs is None and self.crs_text:
            self._crs = parse_crs(self.crs_text)
        return self._crs

    @property
    def body(self):
        return None if self.kind == LOCAL else ("moon" if self.kind == SELENOCENTRIC
                                                else "earth")

    def _frame_rotation(self):
        """Rotation turning body-fixed vectors into the frame's axes, and the origin's
        body-fixed position."""
        if self.kind == TANGENT:
            lat, lon, h = self.origin
            r = enu_rotation(lat, lon)[0]
            x0 = _transform(_geographic("earth"), _geocentric("earth"), [lon, lat, h])[0]
            return r, x0
        return np.eye(3), np.zeros(3)

    # -- points ------------------------------------------------------------------------
    def check_body(self, crs, what):
        """Refuse data of another body than the frame's (``what`` names the data)."""
        if self.kind == LOCAL:
            return
        b = body_of(crs)
        if b != self.body:
            raise DataError(f"{what} is given in {crs.name!r} ({b}), but the block is a "
                            f"{self.body} block ({self.describe()}): data of different "
                            f"bodies cannot be adjusted together")

    def from_user(self, xyz, crs=None):
        """Frame coordinates of points given in the user's CRS (or ``crs``)."""
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        if self.kind == LOCAL:
            return xyz.copy()
        crs = self.crs if crs is None else crs
        ecef = _transform(_as_3d(crs), _geocentric(self.body), xyz)
        r, x0 = self._frame_rotation()
        return (ecef - x0) @ r.T

    def to_user(self, xyz, crs=None):
        """The user's CRS (or ``crs``) coordinates of frame coordinates."""
        xyz = np.asarray(xyz, np.float64).reshape(-1, 3)
        if self.kind == LOCAL:
            return xyz.copy()
        r, x0 = self._frame_rotation()
        ecef = xyz @ r + x0
        return _transform(_geocentric(self.body), _as_3d(self.crs if crs is None else crs),
                          ecef)

    def _station_rotations(self, frame_xyz):
        """Rotations body-fixed -> east, north, up at the stations (frame coordinates)."""
        r, x0 = self._frame_rotation()
        ecef = frame_xyz @ r + x0
        lon, lat, _ = _transform(_geocentric(self.body), _geographic(self.body), ecef).T
        return enu_rotation(lat, lon)

    # -- orientation -------------------------------------------------------------------
    def opk_from_user(self, opk, frame_xyz, orientation="tangent"):
        """Frame omega-phi-kappa (radians) of angles given ``orientation``-relative at
        stations with frame coordinates ``frame_xyz``."""
        opk = np.asarray(opk, np.float64).reshape(-1, 3)
        if self.kind == LOCAL:
            return opk.copy()
        m = rotation_matrices(opk)
        r, _ = self._frame_rotation()
        if orientation == "tangent":
            m = m @ self._station_rotations(frame_xyz)
        elif orientation != "geocentric":
            raise ParameterError(f"orientation {orientation!r}: one of "
                                 f"{', '.join(ORIENTATIONS)}")
        return opk_of(m @ r.T)

    def opk_to_user(self, opk, frame_xyz, orientation="tangent"):
        """The inverse of :meth:`opk_from_user`."""
        opk = np.asarray(opk, np.float64).reshape(-1, 3)
        if self.kind == LOCAL:
            return opk.copy()
        if orientation not in ORIENTATIONS:
            raise ParameterError(f"orientation {orientation!r}: one of "
                                 f"{', '.join(ORIENTATIONS)}")
        m = rotation_matrices(opk)
        r, _ = self._frame_rotation()
        m = m @ r
        if orientation == "tangent":
            m = m @ np.transpose(self._station_rotations(frame_xyz), (0, 2, 1))
        return opk_of(m)

    # -- station priors ----------------------------------------------------------------
    def prior_from_user(self, value, weight, crs=None, orientation="tangent"):
        """Frame values and weights of station priors given in the user's CRS: ``value``
        (n x 6: omega, phi, kappa radians, X, Y, Z in ``crs``) and ``weight`` (n x 6 x 6) for
        angles in that orientation and positions along the station's east, north, up (the
        body-fixed X, Y, Z for a geocentric CRS). The weights are carried over with the
        Jacobian ``T`` of the conversion: ``W_frame = T^-T W T^-1`` (``T`` block-diagonal: the
        angles' by central differences, the positions' a rotation; the angle-position cross
        terms, about 2e-7 rad/m, are left out: a relative weight error below 1e-6)."""
        value = np.asarray(value, np.float64).reshape(-1, 6)
        weight = np.asarray(weight, np.float64).reshape(-1, 6, 6)
        if self.kind == LOCAL:
            return value.copy(), weight.copy()
        crs = self.crs if crs is None else crs
        xyz = self.from_user(value[:, 3:], crs)
        opk = self.opk_from_user(value[:, :3], xyz, orientation)
        r, _ = self._frame_rotation()
        q = (np.broadcast_to(r, (len(xyz), 3, 3)) if crs.is_geocentric
             else r @ np.transpose(self._station_rotations(xyz), (0, 2, 1)))
        w = carried_weights(weight, lambda a: self.opk_from_user(a, xyz, orientation),
                            value[:, :3].copy(), q)
        return np.column_stack([opk, xyz]), w
