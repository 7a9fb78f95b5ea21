"""The bounced light's scale, fitted where the lights are behind the surface.

:func:`colorps.interreflection.bounce_grid` gathers the light an object sends
itself from its images, at the albedo's stated scale, which users often leave
at 1. Where a light is behind the surface (its attached shadow, as the gauge
at the same normal shows), the scene holds the bounced light alone: the scale
is the least-squares factor between those measurements and the light gathered
for them (:func:`bounce_scale`, through a dark level of at least 0). Without
enough such measurements it is not guessed.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from colorps._checks import mask_box
from colorps.bounce import BounceGrid, light_at
from colorps.gauge import Gauge

__all__ = ["MIN_SHADOWED", "SCALE_PIXELS", "SHADOW_LEVEL", "SHADOW_MARGIN_DEG",
           "attached_shadows", "bounce_scale"]

#: Measurements in attached shadow (with some bounced light) needed to fit the scale;
#: fewer, and the bounced light is left in (not guessed from the stated albedo).
MIN_SHADOWED = 200
#: A light leaves a gauge pixel dark (its attached shadow) when it gives it
#: under this share of what it gives the gauge's brightest pixel: above the
#: noise of a dark gauge, below what a light grazing it gives.
SHADOW_LEVEL = 0.02
#: ... and a scene's measurement counts as in attached shadow when every gauge
#: pixel within this angle of its normal is dark: a normal a little off (the
#: bounced light tilts a fold's by degrees) or a light a little nearer than
#: far away must not bring a lit measurement in. Wider is as safe but fits
#: higher, from the deepest shadows, where the grid's gathering falls shortest
#: (Mitsuba's matte pot: 1.35 at 0 degrees, 1.38 at 2, 1.48 at 5, 1.80 at 10).
SHADOW_MARGIN_DEG = 2.0
#: Solved pixels (a fixed draw) the scale is fitted on: under 96 lights their
#: measurements and gathered light take 46 MB (100,000: 230 MB), and Mitsuba's
#: matte pot's scale came out 1.108 (100,000: 1.105), its normals the same.
SCALE_PIXELS = 20_000


def bounce_scale(scene: np.ndarray, grid: BounceGrid, result,
                 in_shadow: Callable[[np.ndarray], np.ndarray], *, every: int = 1
                 ) -> float | None:
    """The factor ``grid``'s bounced light is off by: the albedo's unknown absolute scale.

    Fitted by least squares, ``scene = dark + scale * bounced`` (``dark``, at
    least 0, the level shadows hold without any light: a camera's noise
    clipped at zero, which averages 0.4 sigma, or flare), on the measurements
    in attached shadow (``in_shadow``: :func:`attached_shadows` of the gauge,
    at the normals of ``result``, the solve ``grid`` was made from), which only
    bounced light reaches. Cast shadows are not used: their partly lit edges (a
    lens's blur, a light's size, a renderer's pixel filter) bias the fit high
    (Mitsuba's matte pot under 96 lights fitted 2.3 on them where the bounced
    light it rendered, its images less those of the direct light alone, fits
    1.3; on attached shadows 1.38, and the rendered bounced light there 1.38).
    Fitted on up to :data:`SCALE_PIXELS` of the solved pixels (a fixed draw);
    capped where the median albedo would reflect all the light it gets (a few
    pixels' albedo, from few lights, can be far off). None when fewer than
    :data:`MIN_SHADOWED` such measurements hold bounced light. ``every`` > 1:
    ``scene`` holds every ``every``-th row and column of the image (a
    :class:`colorps.interreflection.SceneSample`'s values), and the pixels are
    drawn from those.
    """
    ys, xs = np.nonzero(result.solved[::every, ::every])  # (in the sample's pixels)
    if ys.size > SCALE_PIXELS:
        keep = np.sort(np.random.default_rng(0).choice(ys.size, SCALE_PIXELS, replace=False))
        ys, xs = ys[keep], xs[keep]
    seen = scene[:, ys, xs]
    ys, xs = ys * every, xs * every
    shadowed = in_shadow(result.normals[ys, xs])  # (m, n)
    gathered = light_at(grid, result.albedo, ys, xs)[shadowed]
    if (gathered > 0).sum() < MIN_SHADOWED:
        return None
    scale = _through_dark_level(seen[shadowed].ravel(), gathered.ravel())
    typical = float(np.nanmedian(result.albedo[result.solved])) if result.solved.any() else 0.0
    return float(np.clip(scale, 0.0, 1.0 / typical if typical > 0 else np.inf))


def _through_dark_level(seen: np.ndarray, gathered: np.ndarray) -> float:
    """The least-squares slope of ``seen = dark + slope * gathered``, the dark
    level at least 0 (through the origin where the free fit puts it below)."""
    seen, gathered = seen.astype(np.float64), gathered.astype(np.float64)
    centred = gathered - gathered.mean()
    slope = float((seen * centred).sum() / max(float((centred * centred).sum()), 1e-300))
    if seen.mean() - slope * gathered.mean() >= 0.0:
        return slope
    return float((seen * gathered).sum() / max(float((gathered * gathered).sum()), 1e-300))


def attached_shadows(gauge: Gauge, gauge_stack: np.ndarray
                     ) -> Callable[[np.ndarray], np.ndarray]:
    """Where each light of ``gauge_stack`` leaves the gauge dark (under
    :data:`SHADOW_LEVEL` of its brightest pixel) at a normal and at every gauge
    pixel within :data:`SHADOW_MARGIN_DEG` of it: its attached shadow.

    Returns ``in_shadow(normals)``: (m, n) bool at (n, 3) ``normals`` (False
    where not finite). The gauge's part (each light's dark pixels, by a
    distance transform of its lit ones in the sphere's box, and the search
    tree of its normals) is made once, for every pass's normals.
    """
    from scipy import ndimage
    from scipy.spatial import cKDTree

    m = gauge_stack.shape[0]
    inside = gauge.mask & np.isfinite(gauge.normals).all(axis=-1)
    rows, cols = mask_box(inside, 1)
    inside = inside[rows, cols]
    if not inside.any():
        return lambda normals: np.zeros((m, len(normals)), dtype=bool)
    tree = cKDTree(gauge.normals[rows, cols][inside])
    margin = gauge.sphere[2] * np.sin(np.radians(SHADOW_MARGIN_DEG)) \
        if gauge.sphere is not None else 1.0
    dark = np.empty((m, int(inside.sum())), dtype=bool)  # (m, gauge pixels)
    for light, image in enumerate(gauge_stack):
        value = np.nan_to_num(np.asarray(image[rows, cols], dtype=np.float32)).sum(axis=-1)
        brightest = float(value[inside].max())
        unlit = ~((value > SHADOW_LEVEL * brightest) & inside)
        away = ndimage.distance_transform_edt(unlit) if not unlit.all() else \
            np.full(unlit.shape, np.inf)  # (pixels to the nearest lit one)
        dark[light] = away[inside] > margin

    def in_shadow(normals: np.ndarray) -> np.ndarray:
        nearest = tree.query(np.nan_to_num(normals))[1]
        return dark[:, nearest] & np.isfinite(normals).all(axis=-1)[None]

    return in_shadow
