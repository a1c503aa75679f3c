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

from ..project import CAMERA_DTYPE, KIND_HORIZONTAL, KIND_VERTICAL
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
        cams[i] = (i + 1, f, x0, y0, 230.0, 230.0, sigma_image, k1, 0.0, 0.0, p1, 0.0)
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


#: Scene presets: name -> function(seed) returning a Scene.
SCENES = {"sapgo-mfl-1": mfl1}
