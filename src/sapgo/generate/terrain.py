"""A smooth, seeded synthetic terrain: rolling hills and valleys on a gentle slope."""

import numpy as np


class Terrain:
    """Height ``Z = base + slope + sum of Gaussian hills`` over a rectangular area.

    ``relief`` is the standard deviation of the heights over the area in metres; hill widths
    are a few kilometres so that the surface is smooth at the scale of a photo base.
    """

    def __init__(self, extent_x, extent_y, relief=150.0, base=500.0, seed=0, hills=None):
        rng = np.random.default_rng(seed)
        area = max(extent_x, 1.0) * max(extent_y, 1.0)
        if hills is None:
            hills = int(np.clip(area / 25e6, 6, 400))
        margin = 0.1
        self.cx = rng.uniform(-margin, 1 + margin, hills) * extent_x
        self.cy = rng.uniform(-margin, 1 + margin, hills) * extent_y
        self.width = rng.uniform(2500.0, 9000.0, hills)
        self.amp = rng.normal(0.0, relief, hills)
        self.base = base
        self.gx = rng.normal(0.0, relief / max(extent_x, 1.0))
        self.gy = rng.normal(0.0, relief / max(extent_y, 1.0))
        gx, gy = np.meshgrid(np.linspace(0, extent_x, 64), np.linspace(0, extent_y, 64))
        std = float(np.std(self(gx, gy)))
        if std > 0:
            self.amp *= relief / std
            self.gx *= relief / std
            self.gy *= relief / std

    def __call__(self, x, y):
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        z = self.base + self.gx * x + self.gy * y
        for cx, cy, w, a in zip(self.cx, self.cy, self.width, self.amp):
            z = z + a * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) / (2 * w * w))
        return z
