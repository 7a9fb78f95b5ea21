"""Light one patch of a matte surface sends another: the form factors' gather.

A patch q of radiance L_q (the same towards every direction: a matte, or
Lambertian, surface) and area A_q, seen from a patch p at distance r, gives p
the irradiance ``L_q cos(theta_p) cos(theta_q) A_q / r^2``; p, of albedo rho,
sends back rho / pi times its sum over the patches it sees. Here the patches are
the cells of a coarse grid over the image (:func:`cell_grid`: at most so many
cells, each the mean of its pixels), the relief is a height field seen
orthographically (heights in pixels), a pair is hidden where the relief rises
above the segment between them, and the sum runs over every pair of cells
(:func:`colorps._bounce_kernels.gather`, numba, parallel over cells).

:mod:`colorps.interreflection` gathers the light an object's observed images
say it sends itself; :mod:`colorps.synth` renders a one-bounce interreflection
from the direct light on the true relief.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from colorps import _bounce_kernels

__all__ = ["BounceGrid", "CellGrid", "at_pixels", "bounced_light", "cell_grid", "cell_heights",
           "gather", "light_at"]


@dataclass(frozen=True)
class CellGrid:
    """The pixels of a surface grouped into square cells.

    Attributes
    ----------
    step : int
        Pixels per cell side.
    count : (h, w) ndarray of float64
        The surface's pixels in each cell.
    valid : (h, w) ndarray of bool
        Cells at least half covered by the surface, facing the camera.
    normals : (h, w, 3) ndarray of float64
        Each cell's mean normal, unit length.
    area : (h, w) ndarray of float64
        Each cell's surface area, in cells (a pixel of normal n covers 1 / n_z
        of a pixel's area; n_z held above 0.05).
    """

    step: int
    count: np.ndarray
    valid: np.ndarray
    normals: np.ndarray
    area: np.ndarray

    def means(self, values: np.ndarray, where: np.ndarray, every: int = 1) -> np.ndarray:
        """Each cell's mean of ``values`` (first two axes the image's) over ``where``.

        ``every`` > 1: ``values`` holds every ``every``-th row and column of the
        image (from the first), a sample of it; each cell's mean is then over
        its sampled pixels (``where`` is still the whole image's)."""
        if every == 1:
            total, count = _cell_sum(values, where, self.step), self.count
        else:
            total, count = _sampled_cell_sum(values, where[::every, ::every], every,
                                             self.step, self.count.shape)
        return total / np.maximum(count, 1.0).reshape(count.shape + (1,) * (values.ndim - 2))


@dataclass(frozen=True)
class BounceGrid:
    """The light a surface sends itself, on a :class:`CellGrid`.

    Attributes
    ----------
    step : int
        Pixels per cell side.
    valid : (h, w) ndarray of bool
    irradiance : (h, w, m, c) ndarray of float64
        Light each cell receives from the rest of the surface, divided by pi
        (what a white matte cell sends back), per image and band.
    share : (h, w) ndarray of float64
        The bounced light's share of each valid cell's measurements: its mean
        albedo times ``irradiance`` against its mean radiance, summed over
        images and bands.
    """

    step: int
    valid: np.ndarray
    irradiance: np.ndarray
    share: np.ndarray


def cell_grid(normals: np.ndarray, surface: np.ndarray, cells: int) -> CellGrid:
    """Group the pixels of ``surface`` ((H, W) bool; ``normals`` (H, W, 3), x right,
    y up, z towards the camera) into at most about ``cells`` square cells."""
    step = max(1, int(np.ceil(np.sqrt(max(int(surface.sum()), 1) / cells))))
    count = _cell_sum(np.ones(surface.shape, np.float32), surface, step)
    mean_normals = _cell_sum(normals, surface, step)
    mean_normals /= np.maximum(np.linalg.norm(mean_normals, axis=-1, keepdims=True), 1e-12)
    area = _cell_sum(1.0 / np.maximum(normals[..., 2], 0.05), surface, step)
    valid = (count >= 0.5 * step * step) & (mean_normals[..., 2] > 0.0)
    return CellGrid(step, count, valid, mean_normals, area / (step * step))


def cell_heights(grid: CellGrid, height: np.ndarray, surface: np.ndarray) -> np.ndarray:
    """The cells' mean height, in cells, of a relief ``height`` in pixels."""
    return grid.means(height, surface) / grid.step


def gather(grid: CellGrid, height: np.ndarray, scene: np.ndarray, surface: np.ndarray,
           albedo: np.ndarray, *, every: int = 1) -> BounceGrid:
    """Gather the light the surface sends itself.

    Parameters
    ----------
    grid : CellGrid
    height : (h, w) ndarray
        The cells' relief, in cells.
    scene : (m, H, W, c) ndarray
        Linear radiance of each pixel (as photographed: a matte surface sends
        the same towards every direction), per image and band.
    surface : (H, W) ndarray of bool
        The pixels ``grid`` was made of.
    albedo : (H, W, c) ndarray
        Each pixel's albedo (NaN: none); only for the :attr:`BounceGrid.share`.
    every : int, optional
        ``scene`` holds every ``every``-th row and column of the image, a
        sample of it (:meth:`CellGrid.means`).

    Returns
    -------
    BounceGrid
    """
    m, c = scene.shape[0], scene.shape[3]
    radiance = np.empty((*grid.valid.shape, m, c))
    for i in range(m):  # one image at a time: no stack-sized temporaries
        radiance[:, :, i] = grid.means(scene[i], surface, every)
    radiance = radiance.reshape(*grid.valid.shape, m * c)
    irradiance = np.zeros_like(radiance)
    _bounce_kernels.gather(_bounce_kernels.Cells(
        np.asarray(height, dtype=np.float64), grid.normals, grid.area, radiance, grid.valid),
        irradiance)
    irradiance = irradiance.reshape(*grid.valid.shape, m, c)
    reflected = irradiance * grid.means(np.nan_to_num(albedo), surface)[:, :, None]
    share = reflected.sum(axis=(2, 3)) / np.maximum(radiance.sum(axis=2), 1e-12)
    return BounceGrid(grid.step, grid.valid, irradiance, np.where(grid.valid, share, 0.0))


def bounced_light(grid: BounceGrid, albedo: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The light each pixel reflects from the rest of the surface, (m, H, W, c) float32.

    The grid's irradiance, interpolated as :func:`at_pixels` does, times each
    pixel's albedo (0 where it has none).
    """
    spread, weight = _spreading(grid, shape)
    m, c = grid.irradiance.shape[2:]
    out = np.empty((m, *shape, c), dtype=np.float32)
    reflect = np.nan_to_num(albedo).astype(np.float32) / weight[..., None]
    for i in range(m):
        for k in range(c):
            out[i, ..., k] = spread(grid.irradiance[:, :, i, k] * grid.valid) * reflect[..., k]
    return out


def at_pixels(grid: BounceGrid, cell_map: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A map of ``grid``'s cells ((h, w)) at every pixel of an image of ``shape``,
    (H, W) float32: interpolated bilinearly between valid cell centres (beyond
    the outer centres: the nearest)."""
    spread, weight = _spreading(grid, shape)
    return spread(np.where(grid.valid, cell_map, 0.0)) / weight


def _spreading(grid: BounceGrid, shape: tuple[int, int]):
    """``spread(cell_map)``, (h, w) -> (H, W) by two products with each pixel's
    weights of the cells of :func:`_neighbours`, and the valid cells' weight at
    each pixel (at least 1e-12): their ratio interpolates between valid cells."""
    rows = _interpolation(shape[0], grid.step, grid.valid.shape[0])
    cols = _interpolation(shape[1], grid.step, grid.valid.shape[1]).T

    def spread(cell_map: np.ndarray) -> np.ndarray:
        return rows @ cell_map.astype(np.float32) @ cols

    return spread, np.maximum(spread(grid.valid), 1e-12)


def light_at(grid: BounceGrid, albedo: np.ndarray, ys: np.ndarray, xs: np.ndarray
             ) -> np.ndarray:
    """:func:`bounced_light` at pixels (``ys``, ``xs``) only: (m, n, c) float32."""
    y0, y1, fy = _neighbours(ys, grid.step, grid.valid.shape[0])
    x0, x1, fx = _neighbours(xs, grid.step, grid.valid.shape[1])
    total = np.zeros((len(ys), *grid.irradiance.shape[2:]))
    weight = np.zeros(len(ys))
    for rows, across in ((y0, 1 - fy), (y1, fy)):
        for cols, along in ((x0, 1 - fx), (x1, fx)):
            share = across * along * grid.valid[rows, cols]
            total += share[:, None, None] * grid.irradiance[rows, cols]
            weight += share
    reflect = np.nan_to_num(albedo[ys, xs]) / np.maximum(weight, 1e-12)[:, None]
    return np.moveaxis(total * reflect[:, None, :], 1, 0).astype(np.float32)


def _neighbours(pixels: np.ndarray, step: int, cells: int):
    """The cells whose centres bracket each pixel (lower, upper) and the upper's
    linear weight; outside the outer centres the nearest, weight 1."""
    at = np.clip((np.asarray(pixels) + 0.5) / step - 0.5, 0.0, cells - 1)
    lower = np.floor(at).astype(np.intp)
    return lower, np.minimum(lower + 1, cells - 1), at - lower


def _interpolation(pixels: int, step: int, cells: int) -> np.ndarray:
    """(pixels, cells) float32: each pixel's linear weights of the cells of
    :func:`_neighbours`."""
    lower, upper, frac = _neighbours(np.arange(pixels), step, cells)
    weights = np.zeros((pixels, cells), dtype=np.float32)
    np.add.at(weights, (np.arange(pixels), lower), 1.0 - frac)
    np.add.at(weights, (np.arange(pixels), upper), frac)
    return weights


def _cell_sum(values: np.ndarray, where: np.ndarray, step: int) -> np.ndarray:
    """Sums (float64) of ``values`` (first two axes the image's, the rest kept) over
    the pixels ``where`` holds, in ``step`` x ``step`` blocks (the last ones
    partial): :func:`colorps._bounce_kernels.cell_sums`."""
    h, w = where.shape
    rest = values.shape[2:]
    out = np.zeros((-(-h // step), -(-w // step), int(np.prod(rest))))
    _bounce_kernels.cell_sums(np.ascontiguousarray(values, dtype=np.float32).reshape(h, w, -1),
                              np.ascontiguousarray(where, dtype=bool), int(step), out)
    return out.reshape(*out.shape[:2], *rest)


def _sampled_cell_sum(values: np.ndarray, where: np.ndarray, every: int, step: int,
                      shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_cell_sum` of a sample (every ``every``-th row and column of the
    image; ``where`` sampled alike) on the whole image's ``step`` x ``step``
    cells, of ``shape``; and each cell's sampled pixels."""
    rows = np.arange(where.shape[0]) * every // step
    cols = np.arange(where.shape[1]) * every // step
    cell = (rows[:, None] * shape[1] + cols[None, :])[where]
    flat = np.asarray(values, dtype=np.float64)[where].reshape(len(cell), -1)
    size = shape[0] * shape[1]
    total = np.stack([np.bincount(cell, flat[:, k], minlength=size)
                      for k in range(flat.shape[1])], axis=-1)
    count = np.bincount(cell, minlength=size).astype(np.float64)
    return total.reshape(*shape, *values.shape[2:]), count.reshape(shape)
