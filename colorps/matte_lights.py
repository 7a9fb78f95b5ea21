"""Light directions and intensities from a matte sphere: a Lambertian fit per image.

A distant light of direction l and intensity E_b in band b shows on a matte
(Lambertian) sphere of albedo a_b as I_b(n) = a_b E_b max(n . l, 0) at the
pixel of normal n (:class:`colorps.Gauge`'s normals within its rim margin). Over
the lit part of the sphere this is linear in s = sum_b a_b E_b l, so each
image's light is the least-squares fit of the bands' sum that
:func:`colorps.gauge_check.lambertian_fit` makes (the fit by which colorps
checks that gauge images show a lit sphere), on the pixels it lights at a
cosine of at least its LIT_FRACTION (the terminator, where a real finish and
the light's size depart from max(n . l, 0) most, is left out). Each band's
intensity is then E_b = (sum I_b n . l) / (a_b sum (n . l)^2) over the same
pixels.

This is what a capture with a gauge of another finish than the scene's needs:
its lights, for a virtual gauge of the scene's own fitted finish (``colorps
reconstruct --lights``). The fit assumes the sphere is Lambertian: a rough or
glossy sphere biases the direction towards where its shading departs from the
cosine, and :attr:`MatteLight.residual` (the fit's relative RMS residual) says
how far it departs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .camera import Camera
from .errors import InputError
from .gauge import Gauge, parse_albedo
from .gauge_check import lambertian_fit
from .lights import DIRECTION_HEADER, MIN_ELEVATION_Z, Lights, direction_columns

__all__ = ["MatteLight", "matte_sphere_lights", "matte_table"]

# ---------------------------------------------------------------- tuning
#: An image needs this many lit pixels on the sphere.
MIN_LIT_PIXELS = 30


@dataclass(frozen=True)
class MatteLight:
    """What one image of a matte sphere gave.

    Attributes
    ----------
    direction : (3,) ndarray
        Unit vector towards the light (camera space).
    intensity : (c,) ndarray
        Per band, relative to the sphere's albedo (1 for a white one).
    pixels : int
        Lit pixels the fit used.
    residual : float
        RMS of the fit's residuals over the RMS of the values (0 on a Lambertian
        sphere without noise; a few per cent on real matte paint).
    """

    direction: np.ndarray
    intensity: np.ndarray
    pixels: int
    residual: float


def matte_sphere_lights(stack, sphere: tuple[float, float, float], *, albedo=1.0,
                        clip_level: float | None = None, names=None,
                        camera: Camera | None = None) -> tuple[Lights, list[MatteLight]]:
    """Lights of a capture from its images of a matte sphere (see the module docstring).

    Parameters
    ----------
    stack : (m, H, W, c) or (m, H, W) array_like
        Linear images of the sphere, one per light.
    sphere : (cx, cy, r)
        Its silhouette, pixels.
    albedo : float or (c,) array_like, optional
        The sphere's albedo per band (intensities are relative to it).
    clip_level : float, optional
        Values at or above it (saturated) are left out.
    names : sequence of str, optional
        Image names, for errors and the returned :class:`~colorps.Lights`.
    camera : Camera, optional
        The pinhole camera the images were taken with: the sphere's normals
        come from the true ray through each pixel (as with ``--camera``), and
        the directions are in that camera's frame. Default orthographic.

    Returns
    -------
    Lights
        Directions and per-band intensities in image order.
    list of MatteLight
        What each image gave.

    Raises
    ------
    InputError
        An image with too few lit pixels on the sphere, or whose light comes
        from behind the object.
    """
    images = np.asarray(stack, dtype=np.float64)
    if images.ndim == 3:
        images = images[..., None]
    if images.ndim != 4:
        raise InputError(f"matte sphere: expected (m, H, W[, c]) images, got {images.shape}")
    names = list(names) if names is not None else [f"image {k}" for k in range(len(images))]
    gauge = Gauge.from_sphere(images.shape[1:3], *sphere, camera=camera)
    values = images[:, gauge.mask]  # (m, P, c)
    if clip_level is not None:
        values = np.where((values < clip_level).all(axis=2, keepdims=True), values, np.nan)
    normals = gauge.normals[gauge.mask]
    vectors, lit = lambertian_fit(values.sum(axis=2), normals)
    albedo = parse_albedo(albedo, images.shape[3])
    found = [_light(values[k, lit[k]], normals[lit[k]], vectors[k], albedo, name)
             for k, name in enumerate(names)]
    lights = Lights(np.array([f.direction for f in found]),
                    np.array([f.intensity for f in found]), names=tuple(names))
    return lights, found


def _light(shown: np.ndarray, normals: np.ndarray, vector: np.ndarray, albedo: np.ndarray,
           name: str) -> MatteLight:
    """One image's light from its (P, c) lit values at their (P, 3) normals and the
    fitted vector of the bands' sum."""
    if len(shown) < MIN_LIT_PIXELS:
        raise InputError(f"{name}: only {len(shown)} lit pixels on the matte sphere (need "
                         f"{MIN_LIT_PIXELS}); is the light on, the sphere in the picture "
                         "and not saturated?")
    direction = vector / np.linalg.norm(vector)
    if not direction[2] >= MIN_ELEVATION_Z:
        raise InputError(f"{name}: the matte sphere's shading gives a light from behind "
                         f"the object (direction {np.round(direction, 3).tolist()})")
    cosine = normals @ direction
    intensity = (shown * cosine[:, None]).sum(axis=0) / (cosine ** 2).sum()
    residual = np.sqrt(np.mean((shown - cosine[:, None] * intensity) ** 2)
                       / np.mean(shown ** 2))
    return MatteLight(direction, np.maximum(intensity / albedo, 1e-12), len(shown),
                      float(residual))


def matte_table(names, found: list[MatteLight]) -> list[str]:
    """calibrate-lights --matte's table: per image the direction, the intensity
    per band and how Lambertian the sphere looked (relative RMS residual)."""
    lines = [f"{DIRECTION_HEADER} {'px':>6s} {'resid':>6s}  intensity"]
    for name, f in zip(names, found, strict=True):
        lines.append(f"{direction_columns(name, f.direction)} {f.pixels:6d} "
                     f"{f.residual:6.3f}  " + " ".join(f"{v:.4g}" for v in f.intensity))
    return lines
