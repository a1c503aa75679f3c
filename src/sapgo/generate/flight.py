"""Generated blocks of a flight design, irregular or not (the designs ``sapgo plan`` takes).

The photos are those of :func:`sapgo.plan.design_footprints`: strip ``k`` flown at photo
scale ``scale * c_k`` (``c_k`` its relative scale: the footprint's side, so the flying height
is ``c_k`` times the nominal), photo ``j`` above the centre of its footprint, every other
strip shifted by ``shift`` bases, strips of their own lengths and starts. Vertical photos
(tilts of ``tilt`` degrees) of one camera over terrain of ``relief`` m; pass points on a
grid of about ``points_per_photo`` on each photo (an overlap narrower than the grid's
spacing may hold none), full control points scattered over the block. The block
is written as a :class:`~sapgo.generate.scene.Scene`, so every image point inside a photo's
format is measured.
"""

from __future__ import annotations

import math

import numpy as np

from ..errors import ParameterError
from ..project import CAMERA_DTYPE, KIND_CONTROL, camera_record
from .scene import ControlClass, Scene
from .terrain import Terrain


def flight_scene(strips, photos_per_strip, forelap=0.6, sidelap=0.2, shift=0.0, lengths=None,
                 starts=None, scales=None, points_per_photo=100, control_points=None,
                 control_sigma=0.05, scale=10000.0, focal_length=152.0, format=230.0,
                 sigma_image=0.006, relief=30.0, tilt=0.5, seed=1):
    """The :class:`Scene` of a flight design (arguments as :func:`sapgo.plan.design_network`;
    ``scale`` the nominal photo scale number, ``control_points`` default one per ten photos,
    at least 8)."""
    from ..plan import design_footprints

    strip, index, foot = design_footprints(strips, photos_per_strip, forelap, sidelap, shift,
                                           lengths, starts, scales)
    if points_per_photo < 9:
        raise ParameterError("points_per_photo: at least 9")
    rng = np.random.default_rng([seed, 103])
    n = len(strip)
    side = format * scale / 1000.0          # m: the nominal footprint's side
    height = focal_length * scale / 1000.0  # m above the ground
    ground = 300.0
    c = foot[:, 1] - foot[:, 0]             # the photos' relative scales
    cams = np.zeros(1, CAMERA_DTYPE)
    cams[0] = camera_record(1, focal_length, 0.0, 0.0, format, format, sigma_image)
    heading = np.where(strip % 2 == 0, 0.0, math.pi)
    t = math.radians(tilt)
    eo = np.column_stack([
        np.clip(rng.normal(0, t, n), -3 * t, 3 * t),
        np.clip(rng.normal(0, t, n), -3 * t, 3 * t),
        heading + np.clip(rng.normal(0, t, n), -3 * t, 3 * t),
        (foot[:, 0] + foot[:, 1]) / 2 * side,
        (foot[:, 2] + foot[:, 3]) / 2 * side,
        ground + c * height + rng.normal(0, 0.002 * height, n),
    ])
    lo = foot[:, [0, 2]].min(axis=0) * side
    extent = (foot[:, [1, 3]].max(axis=0) * side - lo)
    terrain = Terrain(float(extent[0]), float(extent[1]), relief=relief, base=ground,
                      seed=seed, origin=(float(lo[0]), float(lo[1])))
    # points seen on two photos or more: about points_per_photo on each photo, a photo's
    # points lying on 2 to 4 photos (the scene's grid spacing follows from the number)
    area = float(np.sum(c * c))
    n_points = int(points_per_photo * area / 3.0)
    n_control = control_points if control_points is not None else max(8, n // 10)
    control = [ControlClass(n_control, KIND_CONTROL, (control_sigma,) * 3)]
    return Scene(cameras=cams, eo=eo, camera=np.zeros(n, np.int64),
                 strip=strip + 1, terrain=terrain, n_points=n_points, control=control,
                 position_perturbation=5.0, angle_perturbation=20.0, seed=seed)
