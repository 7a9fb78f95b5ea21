"""Compiled kernel of the form factors' gather (private; the API is :mod:`colorps.bounce`)."""

from typing import NamedTuple

import numpy as np
from numba import njit, prange

#: How far (cells) the relief must rise above the segment between two cells to
#: hide one from the other: half a cell, the heights' own resolution.
HIDING_RISE = 0.5


@njit(cache=True)
def _visible(height, valid, y0, x0, y1, x1):
    """Whether the straight segment between cells (y0, x0) and (y1, x1) passes
    above the relief ``height`` (cells on the way only; the ends excluded)."""
    steps = max(abs(y1 - y0), abs(x1 - x0))
    z0, z1 = height[y0, x0], height[y1, x1]
    for s in range(1, steps):
        t = s / steps
        y = int(np.rint(y0 + t * (y1 - y0)))
        x = int(np.rint(x0 + t * (x1 - x0)))
        if valid[y, x] and height[y, x] > z0 + t * (z1 - z0) + HIDING_RISE:
            return False
    return True


class Cells(NamedTuple):
    """The object on a grid of cells, as :func:`gather` reads it.

    height : (h, w) float64
        Relief, in cells (a cell is one unit across).
    normals : (h, w, 3) float64
        Unit normals (x right, y up, z towards the camera).
    area : (h, w) float64
        Surface area of each cell, in cells (1 / n_z for a flat patch).
    radiance : (h, w, k) float64
        Radiance each cell sends out, per image and band (Lambertian: the same
        towards every direction).
    valid : (h, w) bool
        Cells on the surface.
    """

    height: np.ndarray
    normals: np.ndarray
    area: np.ndarray
    radiance: np.ndarray
    valid: np.ndarray


@njit(cache=True, parallel=True)
def gather(cells, out):
    """Irradiance / pi each of ``cells`` (:class:`Cells`) receives from every
    other cell it sees, written to ``out`` ((h, w, k) float64): the sum over
    the cells q it sees of L_q cos(theta_p) cos(theta_q) A_q / (pi r^2), the
    form factor's gather, which a Lambertian cell of albedo rho reflects as
    rho times this."""
    height, normals, area, radiance, valid = cells
    h, w = height.shape
    k = radiance.shape[2]
    for p in prange(h * w):
        py, px = p // w, p % w
        out[py, px, :] = 0.0
        if not valid[py, px]:
            continue
        for qy in range(h):
            for qx in range(w):
                if not valid[qy, qx] or (qy == py and qx == px):
                    continue
                vx, vy = float(qx - px), float(py - qy)  # image rows go down, y up
                vz = height[qy, qx] - height[py, px]
                r2 = vx * vx + vy * vy + vz * vz
                r = np.sqrt(r2)
                cos_p = (normals[py, px, 0] * vx + normals[py, px, 1] * vy
                         + normals[py, px, 2] * vz) / r
                cos_q = -(normals[qy, qx, 0] * vx + normals[qy, qx, 1] * vy
                          + normals[qy, qx, 2] * vz) / r
                if cos_p <= 0.0 or cos_q <= 0.0:
                    continue
                if not _visible(height, valid, py, px, qy, qx):
                    continue
                g = cos_p * cos_q * area[qy, qx] / (np.pi * r2)
                for i in range(k):
                    out[py, px, i] += g * radiance[qy, qx, i]


@njit(cache=True, parallel=True)
def cell_sums(values, where, step, out):
    """Sums of ``values`` ((H, W, k) float32) over the pixels ``where`` ((H, W)
    bool) holds, in ``step`` x ``step`` blocks, added to ``out`` ((h, w, k)
    float64, h = ceil(H / step), w = ceil(W / step))."""
    rows, cols = where.shape
    k = values.shape[2]
    for cy in prange(out.shape[0]):
        for y in range(cy * step, min((cy + 1) * step, rows)):
            for x in range(cols):
                if where[y, x]:
                    cx = x // step
                    for i in range(k):
                        out[cy, cx, i] += values[y, x, i]
