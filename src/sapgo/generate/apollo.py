"""SAPGO-L: Apollo 15 orbital blocks (seeds/002, Tables 6-8 and Figure 8), as generated scenes.

The Apollo 15 metric camera (f = 76.2 mm, 114.3 mm format, image sigma 20 um) photographed
from about 110 km; each revolution's ground track is a great circle of inclination 25 deg,
and successive revolutions' tracks (ascending nodes 6 deg apart, about 50 % sidelap at the
equator) converge at both ends of the block, where points appear on up to 20 photos. The
block spans 200 deg of longitude (argument of latitude -100 .. +100 deg) and about 50 deg of
latitude. There is no ground control: every photo has a prior (orbit and attitude data) and
the priors are the approximate values, as in the paper: the centre orbit to 200 m in
latitude and longitude and 200 m (data sets 1 and 2) or 50 m (data set 3) in height, the
others to 2000 m, attitude 25" (Table 6). The block is computed in the selenocentric frame
(IAU 2015 sphere, R = 1 737 400 m).
"""

from __future__ import annotations

import math

import numpy as np

from ..frames import MOON_RADIUS, SELENOCENTRIC, Frame, _MOON_CRS, enu_rotation, parse_crs
from ..project import CAMERA_DTYPE, PRIOR_DTYPE, camera_record
from .scene import Scene
from .terrain import Terrain

ARCSEC = math.pi / (180 * 3600)
INCLINATION = math.radians(25.0)
ALTITUDE = 110_000.0
#: degrees between the ascending nodes of neighbouring revolutions
NODE_STEP = 6.0
FOCAL, FORMAT = 76.2, 114.3

#: data set -> (photos per orbit, pass points, sigma of the centre orbit's height in m)
APOLLO15 = {
    1: ([85, 85, 86, 85, 85], 3319, 200.0),
    2: ([73] * 6, 3469, 200.0),
    3: ([90] * 7, 4933, 50.0),
}


def _orbit(n, node, altitude, rng):
    """Positions (n x 3, Moon-fixed) and unit velocities of ``n`` exposures along the great
    circle of ascending node ``node``, argument of latitude from -100 to +100 deg."""
    u = np.linspace(-math.radians(100.0), math.radians(100.0), n)
    u += rng.normal(0, 0.01 * (u[1] - u[0]), n)
    ci, si, cn, sn = math.cos(INCLINATION), math.sin(INCLINATION), math.cos(node), math.sin(node)
    p = np.column_stack([np.cos(u), np.sin(u) * ci, np.sin(u) * si])        # Rx(i) (cos u, ..)
    v = np.column_stack([-np.sin(u), np.cos(u) * ci, np.cos(u) * si])
    rz = np.array([[cn, -sn, 0.0], [sn, cn, 0.0], [0.0, 0.0, 1.0]])
    r = MOON_RADIUS + altitude + rng.normal(0, 2000.0, n)
    return (p @ rz.T) * r[:, None], v @ rz.T


def apollo15(data_set, seed=1):
    """The :class:`Scene` of Apollo 15 data set 1, 2 or 3."""
    per_orbit, n_points, sigma_h_centre = APOLLO15[data_set]
    rng = np.random.default_rng([seed, 150 + data_set])
    cams = np.zeros(1, CAMERA_DTYPE)
    cams[0] = camera_record(1, FOCAL, 0.0, 0.0, FORMAT, FORMAT, 0.020)
    n_orb = len(per_orbit)
    step = math.radians(NODE_STEP)
    pos, vel, strip = [], [], []
    for k, n in enumerate(per_orbit):
        p, v = _orbit(n, (k - (n_orb - 1) / 2) * step, ALTITUDE, rng)
        pos.append(p)
        vel.append(v)
        strip.append(np.full(n, 4 + 6 * k))   # revolution numbers, as Table 8's
    pos, vel, strip = np.concatenate(pos), np.concatenate(vel), np.concatenate(strip)
    n_st = len(pos)
    frame = Frame(SELENOCENTRIC, parse_crs(_MOON_CRS).to_3d().to_wkt())
    # nadir-looking, heading along the track, tilts of 0.3 deg, in each station's tangent frame
    lat = np.degrees(np.arcsin(pos[:, 2] / np.linalg.norm(pos, axis=1)))
    lon = np.degrees(np.arctan2(pos[:, 1], pos[:, 0]))
    r_st = enu_rotation(lat, lon)
    v_enu = np.einsum("nij,nj->ni", r_st, vel)
    heading = np.arctan2(v_enu[:, 1], v_enu[:, 0])
    tilt = math.radians(0.3)
    opk_t = np.column_stack([rng.normal(0, tilt, n_st), rng.normal(0, tilt, n_st), heading])
    eo = np.column_stack([frame.opk_from_user(opk_t, pos, "tangent"), pos])
    # priors: the orbit data (true values perturbed by their sigmas) and their weights
    centre = strip == 4 + 6 * (n_orb // 2)
    sig = np.where(centre[:, None], [200.0, 200.0, sigma_h_centre], [2000.0, 2000.0, 2000.0])
    priors = np.zeros(n_st, PRIOR_DTYPE)
    priors["station"] = np.arange(n_st)
    d_enu = rng.normal(0, 1, (n_st, 3)) * sig
    priors["value"][:, 3:] = pos + np.einsum("nji,nj->ni", r_st, d_enu)
    priors["value"][:, :3] = eo[:, :3] + rng.normal(0, 25.0 * ARCSEC, (n_st, 3))
    w = np.zeros((n_st, 6, 6))
    w[:, [0, 1, 2], [0, 1, 2]] = 1.0 / (25.0 * ARCSEC) ** 2
    w[:, 3:, 3:] = np.einsum("nji,nj,njk->nik", r_st, 1.0 / sig ** 2, r_st)
    priors["weight"] = w
    lon_r, lat_r = np.radians(lon), np.radians(lat)
    margin = math.radians(8.0)
    x0, y0 = MOON_RADIUS * (lon_r.min() - margin), MOON_RADIUS * (lat_r.min() - margin)
    terrain = Terrain(MOON_RADIUS * (np.ptp(lon_r) + 2 * margin),
                      MOON_RADIUS * (np.ptp(lat_r) + 2 * margin), relief=800.0, base=0.0,
                      seed=seed, origin=(x0, y0))
    return Scene(cameras=cams, eo=eo, camera=np.zeros(n_st, np.int64), strip=strip,
                 terrain=terrain, n_points=n_points, seed=seed, sphere_radius=MOON_RADIUS,
                 priors=priors, attrs=frame.to_attrs())


SCENES = {f"apollo15-{k}": (lambda seed=1, k=k: apollo15(k, seed)) for k in APOLLO15}
