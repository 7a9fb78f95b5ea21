"""Band weights: how much each colour band of a pixel counts in its match.

A band's weight is 2^level, its level round(log2(its signal-to-noise ratio
|S_k| / sigma_k over the pixel's best band's)) in DROP_LEVEL + 1 .. 0: a band
in the noise counts less than a bright one, and a band at DROP_LEVEL or
below is left out where the others still fix the normal. The matching policy
(:mod:`colorps.matching`) forms one table per set of bands and levels.
"""

from __future__ import annotations

import numpy as np

from . import _pixel_kernels
from .noise import NoiseModel

__all__ = ["DROP_LEVEL", "band_snr", "band_weights", "weight_levels"]

#: Band weights are 2^level, level = round(log2(relative SNR)) in DROP_LEVEL + 1 .. 0;
#: a band at DROP_LEVEL or below is dropped (it carries under 1/64 of the
#: information of the best band).
DROP_LEVEL = -3


def weight_levels(snr: np.ndarray) -> np.ndarray:
    """Per-band weight levels (int8; DROP_LEVEL or below: drop) of pixels.

    Parameters
    ----------
    snr : (P, B) ndarray
        Each band's signal-to-noise ratio |S_k| / sigma_k (0 where the band is
        unusable; :func:`band_snr`).

    Returns
    -------
    (P, B) ndarray of int8
        round(log2(snr_k / max_j snr_j)) clipped to DROP_LEVEL .. 0 (half-way
        cases to even); DROP_LEVEL where snr_k is 0.
    """
    snr = np.asarray(snr, dtype=np.float64)
    best = snr.max(axis=-1, keepdims=True)
    rel = np.divide(snr, best, out=np.zeros_like(snr), where=best > 0)
    with np.errstate(divide="ignore"):
        levels = np.rint(np.log2(rel))
    return np.clip(levels, DROP_LEVEL, 0).astype(np.int8)


def band_weights(scene_ov: np.ndarray, ys: np.ndarray, xs: np.ndarray, valid: np.ndarray,
                 model: NoiseModel) -> tuple[np.ndarray, np.ndarray]:
    """The bands pixels (ys, xs) are matched on and their weight levels.

    Each band's level is :func:`weight_levels` of its :func:`band_snr`. Bands
    at DROP_LEVEL or below are left out where the others still fix a normal
    (bands x (lights - 1) >= 2); the bands kept get at least DROP_LEVEL + 1,
    the others 0. One compiled pass (the numpy steps took 0.35 s at 4 MP).

    Parameters
    ----------
    scene_ov : (H, W, B, m) ndarray of float32
    ys, xs : (P,) ndarray of int
    valid : (P, B) ndarray of bool
        Usable bands.
    model : NoiseModel

    Returns
    -------
    valid : (P, B) ndarray of bool
        The bands kept.
    levels : (P, B) ndarray of int8
    """
    kept = np.empty(valid.shape, dtype=bool)
    levels = np.empty(valid.shape, dtype=np.int8)
    _pixel_kernels.band_levels(scene_ov, np.asarray(ys, np.int64), np.asarray(xs, np.int64),
                               np.ascontiguousarray(valid, dtype=bool), *model.kernel_args(),
                               DROP_LEVEL, kept, levels)
    return kept, levels


def band_snr(scene_ov: np.ndarray, ys: np.ndarray, xs: np.ndarray, valid: np.ndarray,
             model: NoiseModel) -> np.ndarray:
    """Signal-to-noise ratio |S_k| / sigma_k of each band of pixels (ys, xs).

    Parameters
    ----------
    scene_ov : (H, W, B, m) ndarray of float32
    ys, xs : (P,) ndarray of int
    valid : (P, B) ndarray of bool
        Usable bands (the others get 0).
    model : NoiseModel
        sigma_k^2 is the mean over the m measurements of the model's variance.

    Returns
    -------
    (P, B) ndarray of float64
    """
    out = np.empty(valid.shape, dtype=np.float64)
    _pixel_kernels.band_snr(scene_ov, np.asarray(ys, np.int64), np.asarray(xs, np.int64),
                            np.ascontiguousarray(valid, dtype=bool), *model.kernel_args(), out)
    return out
