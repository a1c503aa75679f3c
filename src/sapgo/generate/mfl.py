"""SAPGO-MFL data sets (seeds/002, Table 5 and Figures 6-7), as generated scenes.

``sapgo-mfl-1``: 273 photos in 16 parallel strips flown at similar heights with six camera
systems (normal-angle lenses of 150.7 to 153.4 mm, each with its own principal point and
lens distortion), 1771 pass points; control as the paper's: 40 horizontal points of +-10 m along
the north and east edges, 85 horizontal points of +-40 m and 125 vertical points of +-5 m
scattered over the block; image sigma 20 um.
"""

from __future__ import annotations

import math

import numpy as np

from ..project import CAMERA_DTYPE, KIND_HORIZONTAL, KIND_VERTICAL, camera_record
from .scene import ControlClass, Scene
from .terrain import Terrain

#: (focal length mm, x0, y0 mm, k1 mm^-2, p1 mm^-1) of the six camera systems of data set 1
MFL1_CAMERAS = [
    (152.13, 0.011, -0.006, -1.1e-9, 2.0e-7),
    (151.87, -0.004, 0.009, 0.8e-9, -1.0e-7),
    (153.42, 0.002, 0.003, -2.3e-9, 0.0),
    (152.61, -0.008, -0.012, 1.5e-9, 1.5e-7),
    (150.72, 0.005, 0.004, -4.0e-9, -2.0e-7),
    (153.05, 0.0, -0.002, 0.5e-9, 0.0),
]
#: the camera of each of the 16 strips
MFL1_STRIP_CAMERA = [0, 0, 0, 1, 1, 1, 2, 2, 2, 3, 3, 3, 4, 4, 5, 5]


def _cameras(spec, sigma_image):
    cams = np.zeros(len(spec), CAMERA_DTYPE)
    for i, (f, x0, y0, k1, p1) in enumerate(spec):
        cams[i] = camera_record(i + 1, f, x0, y0, 230.0, 230.0, sigma_image, k1, 0.0, 0.0,
                                p1)
    return cams


def mfl1(seed=1):
    """The :class:`Scene` of SAPGO-MFL data set 1."""
    rng = np.random.default_rng([seed, 101])
    cams = _cameras(MFL1_CAMERAS, 0.020)
    base_height = 4500.0
    ground = 500.0
    footprint = 0.230 * base_height / 0.152   # m on the ground, normal-angle cameras
    photo_base = 0.4 * footprint          # 60 % forelap for the normal-angle cameras
    spacing = 0.7 * footprint             # 30 % sidelap
    counts = [17] * 15 + [18]             # 273 photos
    eo, cam, strip = [], [], []
    for s, n in enumerate(counts):
        heading = 0.0 if s % 2 == 0 else math.pi
        h = ground + base_height * (1 + rng.normal(0, 0.02))
        x = np.arange(n) * photo_base + rng.normal(0, 0.02 * photo_base, n)
        y = s * spacing + rng.normal(0, 0.02 * spacing, n)
        tilt = math.radians(1.0)
        e = np.column_stack([
            np.clip(rng.normal(0, tilt, n), -3 * tilt, 3 * tilt),
            np.clip(rng.normal(0, tilt, n), -3 * tilt, 3 * tilt),
            heading + rng.normal(0, math.radians(1.0), n),
            x, y, h + rng.normal(0, 10.0, n)])
        eo.append(e)
        cam.append(np.full(n, MFL1_STRIP_CAMERA[s]))
        strip.append(np.full(n, s + 1))
    eo = np.concatenate(eo)
    extent_x, extent_y = np.ptp(eo[:, 3]) + footprint, np.ptp(eo[:, 4]) + footprint
    terrain = Terrain(extent_x, extent_y, relief=150.0, base=ground, seed=seed,
                      origin=(-footprint / 2, -footprint / 2))
    control = [ControlClass(20, KIND_HORIZONTAL, (10.0, 10.0, 0.0), "north"),
               ControlClass(20, KIND_HORIZONTAL, (10.0, 10.0, 0.0), "east"),
               ControlClass(85, KIND_HORIZONTAL, (40.0, 40.0, 0.0)),
               ControlClass(125, KIND_VERTICAL, (0.0, 0.0, 5.0))]
    return Scene(cameras=cams, eo=eo, camera=np.concatenate(cam), strip=np.concatenate(strip),
                 terrain=terrain, n_points=1771, control=control, seed=seed)


MFL2_CAMERAS = [
    (152.08, 0.006, -0.004, -1.4e-9, 1.0e-7),
    (153.01, -0.003, 0.007, 1.1e-9, 0.0),
    (151.55, 0.009, 0.002, -0.6e-9, -1.2e-7),
    (152.63, -0.005, -0.008, 2.0e-9, 0.5e-7),
]


def _strip(rng, start, direction, n, base, height, camera, number, tilt_deg=1.0):
    """``n`` photos from ``start`` (x, y) along the unit ``direction`` every ``base`` m."""
    heading = math.atan2(direction[1], direction[0])
    t = np.arange(n) * base + rng.normal(0, 0.02 * base, n)
    tilt = math.radians(tilt_deg)
    e = np.column_stack([
        np.clip(rng.normal(0, tilt, n), -3 * tilt, 3 * tilt),
        np.clip(rng.normal(0, tilt, n), -3 * tilt, 3 * tilt),
        heading + rng.normal(0, math.radians(1.0), n),
        start[0] + t * direction[0], start[1] + t * direction[1],
        height + rng.normal(0, 10.0, n)])
    return e, np.full(n, camera), np.full(n, number)


def mfl2(seed=1):
    """The :class:`Scene` of SAPGO-MFL data set 2: 167 photos of four camera systems, 1457
    points. A western area flown east-west at 4500 m (camera 1: 9 lines of 7 photos), an
    eastern area overlapping it flown north-south at 3200 m (cameras 2 and 3 alternating: 8
    lines of 12 photos), and one diagonal line across both at 4500 m (camera 4: 8 photos);
    control as the paper's (45 horizontal +-10 m on the north and east edges, 61 horizontal
    +-40 m, 106 vertical +-5 m)."""
    rng = np.random.default_rng([seed, 102])
    cams = _cameras(MFL2_CAMERAS, 0.020)
    ground = 500.0
    parts = []
    fp1 = 0.230 * 4500.0 / 0.152
    b1, a1 = 0.4 * fp1, 0.7 * fp1
    for s in range(9):
        d = (1.0, 0.0) if s % 2 == 0 else (-1.0, 0.0)
        x0 = 0.0 if s % 2 == 0 else 6 * b1
        parts.append(_strip(rng, (x0, s * a1), d, 7, b1, ground + 4500.0, 0, s + 1))
    fp2 = 0.230 * 3200.0 / 0.153
    b2, a2 = 0.4 * fp2, 0.7 * fp2
    x_east = 6 * b1 + 0.5 * (fp1 + fp2) - 0.3 * fp2   # overlapping the western area
    for s in range(8):
        d = (0.0, 1.0) if s % 2 == 0 else (0.0, -1.0)
        y0 = 0.0 if s % 2 == 0 else 11 * b2
        parts.append(_strip(rng, (x_east + s * a2, y0), d, 12, b2, ground + 3200.0,
                            1 + s % 2, 10 + s))
    diag = np.array([1.0, -1.0]) / math.sqrt(2.0)
    start = (x_east - 5 * b1 * diag[0], 11 * b2 - 5 * b1 * diag[1])
    parts.append(_strip(rng, start, diag, 8, b1, ground + 4500.0, 3, 18))
    eo = np.concatenate([p[0] for p in parts])
    lo = eo[:, 3:5].min(axis=0) - fp1
    extent = float((eo[:, 3:5].max(axis=0) - lo).max()) + fp1
    terrain = Terrain(extent, extent, relief=150.0, base=ground, seed=seed,
                      origin=(float(lo[0]), float(lo[1])))
    control = [ControlClass(23, KIND_HORIZONTAL, (10.0, 10.0, 0.0), "north"),
               ControlClass(22, KIND_HORIZONTAL, (10.0, 10.0, 0.0), "east"),
               ControlClass(61, KIND_HORIZONTAL, (40.0, 40.0, 0.0)),
               ControlClass(106, KIND_VERTICAL, (0.0, 0.0, 5.0))]
    return Scene(cameras=cams, eo=eo, camera=np.concatenate([p[1] for p in parts]),
                 strip=np.concatenate([p[2] for p in parts]), terrain=terrain, n_points=1457,
                 control=control, seed=seed)


#: Scene presets: name -> function(seed) returning a Scene.
SCENES = {"sapgo-mfl-1": mfl1, "sapgo-mfl-2": mfl2}
