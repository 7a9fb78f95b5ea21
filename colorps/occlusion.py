"""What a relief hides from itself: the cast shadows of directional lights, and
the share of the sky each point sees.

The relief is a height field (heights in pixels, seen orthographically, x right,
y up, image rows down), as :class:`colorps.synth.SyntheticSurface` holds it:
``height``, ``mask`` and unit ``normals``. :mod:`colorps.synth` renders shadows
and ambient light with it; tests take the true shadows from it.
"""

from __future__ import annotations

import numpy as np

__all__ = ["SKY_SAMPLES", "shadow_maps", "sky_visibility"]

#: Directions over the upper hemisphere :func:`sky_visibility` traces by default.
SKY_SAMPLES = 24


def shadow_maps(surface, lighting) -> np.ndarray:
    """Where the relief casts a shadow: (m, L, H, W) bool, per image and light.

    ``surface`` holds ``height``, ``mask`` and ``normals``; ``lighting``,
    ``directions`` (m, L, 3): unit vectors towards each light of each image.

    A pixel is in the cast shadow of a light when the height field rises above
    the straight ray from the pixel towards the light (marched one pixel at a
    time, heights in pixels, orthographic). Attached shadows (the light behind
    the surface) are not counted: the shading already makes them 0.
    """
    from scipy.ndimage import map_coordinates

    h, w = surface.mask.shape
    z = np.where(surface.mask, surface.height, -np.inf)
    ys, xs = np.nonzero(surface.mask)
    z0 = z[ys, xs]
    top = float(np.max(z0)) if z0.size else 0.0
    m, n_lights = lighting.directions.shape[:2]
    out = np.zeros((m, n_lights, h, w), dtype=bool)
    filled = np.where(surface.mask, surface.height, np.nanmin(surface.height)
                      if surface.mask.any() else 0.0)
    for k in range(m):
        for index, light in enumerate(lighting.directions[k]):
            across = np.hypot(light[0], light[1])
            if across < 1e-9 or light[2] <= 0:
                continue
            ux, uy = light[0] / across, -light[1] / across  # image rows go down
            rise = light[2] / across  # height gained per pixel travelled
            blocked = np.zeros(ys.size, dtype=bool)
            for t in range(1, h + w):
                ray = z0 + t * rise
                live = ~blocked & (ray <= top)
                if not live.any():
                    break
                px, py = xs + t * ux, ys + t * uy
                inside = (px >= 0) & (px <= w - 1) & (py >= 0) & (py <= h - 1)
                ground = map_coordinates(filled, [py, px], order=1, mode="nearest")
                blocked |= live & inside & (ground > ray + 1e-9)
            facing = surface.normals[ys, xs] @ light > 0
            out[k, index, ys, xs] = blocked & facing
    return out


def sky_visibility(surface, samples: int = SKY_SAMPLES) -> np.ndarray:
    """(H, W) fraction of the sky above each pixel that the relief leaves open:
    of ``samples`` directions spread evenly over the upper hemisphere (a
    Fibonacci spiral), weighted by their cosine to the pixel's normal, the part
    not blocked by the relief (:func:`shadow_maps`). 1 on open flat or convex
    parts, less in grooves and folds (where the pixel sees the surface itself);
    0 outside the mask."""
    k = np.arange(samples) + 0.5
    z = 1.0 - k / samples  # evenly in z: even in solid angle
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    rho = np.sqrt(1.0 - z * z)
    directions = np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=1)
    blocked = shadow_maps(surface, _Directions(directions[None]))[0]  # (samples, H, W)
    cosine = np.maximum(np.einsum("hwc,sc->shw", surface.normals, directions), 0.0)
    total = cosine.sum(axis=0)
    open_sky = np.where(blocked, 0.0, cosine).sum(axis=0) / np.maximum(total, 1e-12)
    return np.where(surface.mask, np.clip(open_sky, 0.0, 1.0), 0.0)


class _Directions:
    """Lights given by their directions alone, as :func:`shadow_maps` reads them."""

    def __init__(self, directions: np.ndarray) -> None:
        self.directions = directions
