"""Harder synthetic captures: deep concave folds, domes of many lights, a mirror ball.

:mod:`colorps.synth` renders the paper's smiley scene, whose low relief casts
few shadows. Real objects have folds that hide a pixel from many of a dome's
lights at once; :func:`folds_surface` is such an object (a dome crossed by
deep grooves), and :func:`dome_lights` a light dome of 32-96 lights like the
rigs of museum and inspection imaging (and DiLiGenT's). Render them with
:func:`colorps.synth.render` (``cast_shadows=True``). :func:`render_mirror_sphere`
renders the chrome ball ``colorps calibrate-lights`` reads.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError
from .synth import Lighting, SyntheticSurface

__all__ = ["dome_lights", "folds_surface", "render_mirror_sphere"]


def folds_surface(size: int = 200, *, depth: float = 0.35, period: float = 0.5,
                  rim: float = 0.95) -> SyntheticSurface:
    """A dome crossed by deep grooves (concave folds), with a coloured albedo.

    The height, in radii R = 0.47 ``size`` of the disk it covers, is ::

        z = 0.5 sqrt(1 - X^2 - Y^2) + depth (1 - cos(2 pi X / period)) / 2 cos(pi Y / 2)

    so the grooves run along y, ``period`` radii apart and up to ``depth``
    radii deep at the middle row, shallowing towards the top and bottom. Their
    walls hide the pixels near the groove bottoms from many lights.

    Parameters
    ----------
    size : int
        Image side (pixels).
    depth, period : float, optional
        Groove depth and spacing, in radii.
    rim : float, optional
        Keep pixels within this fraction of the radius.

    Returns
    -------
    SyntheticSurface
        Normals from the height field's exact slopes; albedo a warm base with a
        saturated blue band across the middle and a red patch top right.
    """
    if size < 8 or depth < 0 or period <= 0:
        raise InputError("folds_surface: size >= 8, depth >= 0 and period > 0 please")
    radius = 0.47 * size
    c = (size - 1) / 2.0
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    X, Y = (x - c) / radius, -(y - c) / radius
    mask = rim * rim > X * X + Y * Y
    r2 = np.clip(1.0 - X * X - Y * Y, 1e-6, None)
    dome = np.sqrt(r2)
    groove = 0.5 - 0.5 * np.cos(2 * np.pi * X / period)
    fade = np.cos(np.pi * Y / 2)
    f = 0.5 * dome + depth * groove * fade
    fx = -0.5 * X / dome + depth * fade * np.pi / period * np.sin(2 * np.pi * X / period)
    fy = -0.5 * Y / dome - depth * groove * np.pi / 2 * np.sin(np.pi * Y / 2)
    n = np.stack([-fx, -fy, np.ones_like(f)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    albedo = np.empty((size, size, 3))
    albedo[:] = (0.70, 0.50, 0.35)
    albedo[np.abs(Y) < 0.15] = (0.10, 0.60, 0.80)
    albedo[(X > 0.4) & (Y > 0.2)] = (0.85, 0.10, 0.05)
    return SyntheticSurface(np.where(mask[..., None], n, 0.0), mask,
                            np.where(mask[..., None], albedo, 0.0),
                            np.where(mask, radius * f, np.nan))


def dome_lights(m: int, max_theta_deg: float = 60.0, *, bands: int = 3) -> Lighting:
    """``m`` white lights spread evenly over a dome, up to ``max_theta_deg`` from the view.

    A Fibonacci spiral: equal solid angle per light, azimuths turned by the
    golden angle from one light to the next, elevations from near the view
    axis down to ``max_theta_deg``.
    """
    if m < 3 or not 0 < max_theta_deg < 90:
        raise InputError("dome_lights: m >= 3 lights and 0 < max_theta_deg < 90 please")
    k = np.arange(m) + 0.5
    cos_theta = 1.0 - (1.0 - np.cos(np.deg2rad(max_theta_deg))) * k / m
    phi = np.pi * (1.0 + 5.0 ** 0.5) * k
    sin_theta = np.sqrt(1.0 - cos_theta ** 2)
    directions = np.stack([sin_theta * np.cos(phi), sin_theta * np.sin(phi), cos_theta], 1)
    return Lighting(directions[:, None, :], np.ones((m, 1, bands)))


def render_mirror_sphere(surface: SyntheticSurface, lighting: Lighting, *,
                         spread_deg: float = 1.0, ambient: float = 0.03,
                         peak: float = 1.0, noise: float = 0.0,
                         seed: int | None = 0) -> np.ndarray:
    """Images of a mirror (chrome) surface reflecting each image's lights.

    Each distant light is a small round source: a pixel whose mirror direction
    r = 2 (n . v) n - v makes the angle theta with it shows
    ``peak * colour * exp(-theta^2 / (2 spread^2))``, on top of a dim uniform
    environment ``ambient`` (so the sphere's disk is visible); 0 outside the mask.

    Returns
    -------
    (m, H, W, c) ndarray of float32
        Linear values (not clipped: clip them to mimic saturation).
    """
    n = surface.normals
    reflected = 2.0 * n[..., 2:3] * n - np.array([0.0, 0.0, 1.0])
    spread = np.radians(spread_deg)
    rng = np.random.default_rng(seed)
    images = np.zeros((lighting.images, *surface.mask.shape, lighting.bands))
    for k in range(lighting.images):
        images[k] += ambient
        for direction, colour in zip(lighting.directions[k], lighting.colours[k]):
            theta = np.arccos(np.clip(reflected @ direction, -1.0, 1.0))
            images[k] += peak * np.exp(-theta ** 2 / (2 * spread ** 2))[..., None] * colour
        if noise:
            images[k] += rng.normal(0.0, noise, images[k].shape)
        images[k][~surface.mask] = 0.0
    return images.astype(np.float32)
