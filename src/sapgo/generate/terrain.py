"""A smooth, seeded synthetic terrain of rolling hills and valleys, of any extent.

The hills are scattered over square tiles (one hill per 25 km^2 on average), each tile seeded
from the block seed and its tile indices, so the height at a place does not depend on how far
the block extends or in which order it is evaluated: a block of a million photographs is
generated chunk by chunk and gets the same terrain as one evaluated at once.

Each hill is a Gaussian bump of width ``w`` (2.5 to 9 km) cut off smoothly at ``3 w``
(``a * (exp(-r^2 / 2w^2) - exp(-4.5))``), so only the hills of the 3 x 3 tiles around a point
matter. The amplitudes are scaled so that the expected standard deviation of the heights is
``relief``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

TILE = 27_000.0  # m: three times the widest hill
HILLS_PER_TILE = 29  # about one hill per 25 km^2
W_MIN, W_MAX = 2500.0, 9000.0
_CUT = math.exp(-4.5)


def _profile_energy():
    """E[integral of the squared hill profile over the plane] for unit amplitude."""
    w = np.linspace(W_MIN, W_MAX, 201)
    r = np.linspace(0.0, 3.0, 3001)  # in units of w
    g = np.exp(-0.5 * r * r) - _CUT
    unit = np.trapezoid(g * g * 2 * np.pi * r, r)
    return float(unit * np.mean(w * w))


@njit(cache=True)
def _heights(x, y, cx, cy, width, amp, tile_start, n_tx, n_ty, x_off, y_off, base, out):
    for i in range(x.shape[0]):
        tx = int(math.floor((x[i] - x_off) / TILE))
        ty = int(math.floor((y[i] - y_off) / TILE))
        z = base
        for ix in range(tx - 1, tx + 2):
            if ix < 0 or ix >= n_tx:
                continue
            for iy in range(ty - 1, ty + 2):
                if iy < 0 or iy >= n_ty:
                    continue
                t = ix * n_ty + iy
                for h in range(tile_start[t], tile_start[t + 1]):
                    dx = x[i] - cx[h]
                    dy = y[i] - cy[h]
                    q = (dx * dx + dy * dy) / (width[h] * width[h])
                    if q < 9.0:
                        z += amp[h] * (math.exp(-0.5 * q) - _CUT)
        out[i] = z


class Terrain:
    """Height ``Z = base + sum of hills`` over ``[x0, x1] x [y0, y1]`` (with a margin)."""

    def __init__(self, extent_x, extent_y, relief=100.0, base=500.0, seed=0, origin=(0.0, 0.0)):
        margin = TILE
        self.x_off = origin[0] - margin
        self.y_off = origin[1] - margin
        self.n_tx = int(math.ceil((extent_x + 2 * margin) / TILE)) + 1
        self.n_ty = int(math.ceil((extent_y + 2 * margin) / TILE)) + 1
        self.base = float(base)
        # amplitude so that Var(Z) = density * E[a^2] * energy = relief^2
        density = HILLS_PER_TILE / (TILE * TILE)
        amp_sd = relief / math.sqrt(density * _profile_energy()) if relief > 0 else 0.0
        n = self.n_tx * self.n_ty
        cx = np.empty(n * HILLS_PER_TILE)
        cy = np.empty_like(cx)
        w = np.empty_like(cx)
        a = np.empty_like(cx)
        for ix in range(self.n_tx):
            for iy in range(self.n_ty):
                rng = np.random.default_rng([seed, 7919, ix, iy])
                k = (ix * self.n_ty + iy) * HILLS_PER_TILE
                sl = slice(k, k + HILLS_PER_TILE)
                cx[sl] = self.x_off + (ix + rng.random(HILLS_PER_TILE)) * TILE
                cy[sl] = self.y_off + (iy + rng.random(HILLS_PER_TILE)) * TILE
                w[sl] = rng.uniform(W_MIN, W_MAX, HILLS_PER_TILE)
                a[sl] = rng.normal(0.0, amp_sd, HILLS_PER_TILE)
        self.cx, self.cy, self.width, self.amp = cx, cy, w, a
        self.tile_start = np.arange(n + 1, dtype=np.int64) * HILLS_PER_TILE

    def __call__(self, x, y):
        x = np.ascontiguousarray(x, dtype=np.float64)
        y = np.ascontiguousarray(y, dtype=np.float64)
        shape = np.broadcast(x, y).shape
        x, y = np.broadcast_to(x, shape).ravel(), np.broadcast_to(y, shape).ravel()
        out = np.empty(x.shape[0])
        _heights(np.ascontiguousarray(x), np.ascontiguousarray(y), self.cx, self.cy,
                 self.width, self.amp, self.tile_start, self.n_tx, self.n_ty, self.x_off,
                 self.y_off, self.base, out)
        return out.reshape(shape)
