"""How well a match explains a pixel, in units of what the noise model expects.

For a scene pixel p matched to gauge pixel q over the lights L (m' of them),
band k has the signature residual d_k = |s_k - g_k|^2 (s, g unit vectors over
L). Its expected value when q is the right normal is ::

    E_k = (m' - 1) (sigma_S^2 / |S_k|^2 + sigma_G^2 / |G_k|^2) + h_k(q)^2 / 6

the noise of both unit vectors (sigma^2: the mean variance of the band's
measurements, :class:`~colorps.noise.NoiseModel`; m' - 1 directions
perpendicular to the signature) plus the table's own resolution: h_k(q) is the
RMS signature step from q to its 4 neighbours on the gauge, and a point
uniformly placed among table entries h apart lies h^2 / 6 from the nearest on
average; plus MODEL_FLOOR^2, the least mismatch of any real gauge and scene
(finish, shape, light fall-off), which keeps noiseless data from making every
small difference infinitely significant. The **residual** of the match is ::

    r(p) = sqrt( mean over matched bands of d_k / E_k )

about 1 for a pixel the gauge explains, and much larger for a cast shadow, a
highlight, or a material the gauge does not share. ``quality.exr`` is r
divided by the capture's model scale (its median over the image when that
exceeds 1: BRDF and light mismatch that every pixel shares).

The per-light residual (S_ki - a_k G_ki) / sigma(S_ki), with a_k the
least-squares albedo ratio of band k, summed over bands and divided by sqrt(B),
says which light a poor match disagrees with: negative for a cast shadow,
positive for a highlight.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .noise import NoiseModel

__all__ = [
    "MODEL_FLOOR",
    "GaugeOverLights",
    "MatchedGroup",
    "light_residuals",
    "match_residual",
    "table_resolution",
]

#: Signature residual per band (unit vectors; 0.005 is about 0.3 degrees between
#: two OVs) that any match is allowed on top of noise and table resolution.
MODEL_FLOOR = 0.005


def table_resolution(signatures: np.ndarray, usable: np.ndarray, rows=None,
                     out: np.ndarray | None = None, *, lights=None,
                     norm2: np.ndarray | None = None) -> np.ndarray:
    """Squared signature step h^2 from gauge pixels to their usable 4-neighbours.

    Parameters
    ----------
    signatures : (H, W, B, m) ndarray
        Per-band unit signatures of the gauge, or with ``norm2`` the OVs they
        are made of.
    usable : (H, W) ndarray of bool
    rows : (n,) array_like of int, optional
        Flat pixel indices (y * W + x) to compute; default every pixel.
    out : (H * W, B) ndarray of float64, optional
        Written at ``rows`` (the rest is left as it is) and returned.
    lights : sequence of int, optional
        With ``norm2``: the lights the signatures are over (default all).
    norm2 : (H, W, B) ndarray of float64, optional
        |OV|^2 over ``lights``: the signatures are then the OVs over ``lights``
        divided by sqrt(norm2), computed where they are read (the gauge over a
        light subset is not stored as signatures).

    Returns
    -------
    (H, W, B) ndarray of float64, or ``out``
        Mean over usable neighbours of |g_k(q) - g_k(neighbour)|^2 (0 where
        a pixel has none).
    """
    from . import _pixel_kernels

    h, w, n_bands, m = signatures.shape
    whole = out is None
    if whole:
        out = np.empty((h * w, n_bands))
    rows = np.arange(h * w) if rows is None else np.asarray(rows, dtype=np.int64)
    if norm2 is None:  # already unit signatures: divide by 1, which is exact
        lights, norm2 = None, np.ones((h, w, n_bands))
    lights = np.arange(m) if lights is None else np.asarray(lights, dtype=np.int64)
    _pixel_kernels.neighbour_steps(np.ascontiguousarray(signatures, dtype=np.float32), lights,
                                   np.ascontiguousarray(norm2, dtype=np.float64),
                                   np.ascontiguousarray(usable, dtype=bool), rows, out)
    return out.reshape(h, w, n_bands) if whole else out


class MatchedGroup(NamedTuple):
    """Pixels matched on one group's bands and lights.

    Attributes
    ----------
    ys, xs : (P,) ndarray of int
        The matched pixels.
    bands, lights : sequence of int
        The bands matched and the lights used (m' of them).
    rows : (P,) ndarray of int
        Each pixel's match: a flat gauge pixel index.
    """

    ys: np.ndarray
    xs: np.ndarray
    bands: np.ndarray
    lights: np.ndarray
    rows: np.ndarray


class GaugeOverLights(NamedTuple):
    """The gauge over a group's lights, as its residuals need it.

    Attributes
    ----------
    ov : (Hg, Wg, B, m) ndarray of float32
        The gauge's OVs over every light (its unit signatures over the lights
        are these divided by sqrt(norm2)).
    norm2, variance : (Hg * Wg, B) ndarray
        Squared gauge OV norms and mean measurement variances over the lights.
    resolution : (Hg * Wg, B) ndarray
        h^2 of each gauge pixel (:func:`table_resolution`).
    """

    ov: np.ndarray
    norm2: np.ndarray
    variance: np.ndarray
    resolution: np.ndarray


def match_residual(scene_ov: np.ndarray, group: MatchedGroup, gauge: GaugeOverLights,
                   model: NoiseModel) -> tuple[np.ndarray, np.ndarray]:
    """The residual r of matched pixels (see the module docstring), and their
    plain signature distance per band, sqrt(mean over bands of d_k).

    Parameters
    ----------
    scene_ov : (H, W, B, m) ndarray of float32
        The scene's observation vectors.
    group : MatchedGroup
        The matched pixels, their bands and lights, and their matches.
    gauge : GaugeOverLights
        The gauge over those lights.
    model : NoiseModel
        Of the scene's measurements.

    Returns
    -------
    residual, distance : (P,) ndarray of float32
    """
    from . import _pixel_kernels

    n = len(group.ys)
    residual = np.empty(n, dtype=np.float32)
    distance = np.empty(n, dtype=np.float32)
    group = MatchedGroup(*(np.asarray(a, np.int64) for a in group))
    gauge = GaugeOverLights(np.ascontiguousarray(gauge.ov, np.float32),
                            *(np.ascontiguousarray(a) for a in gauge[1:]))
    _pixel_kernels.group_residuals(scene_ov, group, gauge, model.kernel_args(),
                                   MODEL_FLOOR ** 2, residual, distance)
    return residual, distance


def light_residuals(scene_ov, gauge_ov, lights, bands_used, model: NoiseModel, *,
                    extra_variance: np.ndarray | None = None) -> np.ndarray:
    """Signed residual of every light, in noise units: (P, B, m) OVs -> (P, m).

    Only ``lights`` ((P, m) bool) enter the albedo fit; the others get a
    residual too (what they would need to be), which callers ignore.
    ``extra_variance`` ((P, B), optional) is added to every measurement's
    noise variance of its pixel and band (what else a right match leaves).
    """
    from . import _pixel_kernels

    n, bands, m = scene_ov.shape
    extra = np.zeros((n, bands)) if extra_variance is None else \
        np.ascontiguousarray(np.broadcast_to(extra_variance, (n, bands)), dtype=np.float64)
    out = np.empty((n, m))
    _pixel_kernels.light_residuals(np.ascontiguousarray(scene_ov), np.ascontiguousarray(gauge_ov),
                                   np.ascontiguousarray(lights, dtype=bool),
                                   np.ascontiguousarray(bands_used, dtype=bool), extra,
                                   model.kernel_args(), out)
    return out
