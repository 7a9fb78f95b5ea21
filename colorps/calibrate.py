"""Light directions from a mirror (chrome) sphere: the highlight in each image.

A distant point light seen in a mirror sphere makes one small highlight, where
the sphere's normal n halves the angle between the view v = (0, 0, 1)
(orthographic camera) and the light l. With the highlight's sub-pixel centre
(x, y) on a sphere of centre (cx, cy) and radius r (pixels; conventions of
:mod:`colorps.geometry`)::

    n = ((x - cx) / r, -(y - cy) / r, sqrt(1 - nx^2 - ny^2)),   l = 2 (n . v) n - v

The centre is the intensity-weighted centroid of the connected bright blob
around the brightest pixel (pixels above half-way from the sphere's median to
the peak), which also finds the centre of a clipped, flat-topped highlight.
How sure a direction is shows in its report: the highlight's size, its clipped
pixels, its contrast, and ``degrees_per_pixel``, how far the light moves when
the centre is off by one pixel (2 / (r nz) radians: large near the rim).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InputError
from .lights import Lights

__all__ = ["Highlight", "calibrate_lights", "find_highlight"]

# ---------------------------------------------------------------- tuning
#: Only pixels within this fraction of the radius are searched (the rim is
#: where the silhouette estimate errs most, and it reflects grazing light).
SEARCH_RADIUS_FRACTION = 0.98
#: The highlight is the blob above this fraction of the way from the
#: sphere's median level to its peak.
HIGHLIGHT_LEVEL = 0.5
#: An image has a highlight when its peak exceeds the sphere's median by this
#: factor (and the sphere is not black).
MIN_CONTRAST = 4.0
#: A highlight covering more of the disk than this is not a point light's
#: reflection (a matte sphere, an area light, overexposure): refused.
MAX_HIGHLIGHT_FRACTION = 0.05


@dataclass(frozen=True)
class Highlight:
    """One image's highlight and the light direction it gives.

    Attributes
    ----------
    x, y : float
        Sub-pixel centre (column, row).
    direction : (3,) ndarray
        Unit vector towards the light, camera space.
    pixels : int
        Size of the highlight blob.
    clipped : int
        Its pixels at or above the clip level.
    contrast : float
        Peak over the sphere's median level.
    degrees_per_pixel : float
        Change of the direction per pixel of error in the centre.
    """

    x: float
    y: float
    direction: np.ndarray
    pixels: int
    clipped: int
    contrast: float
    degrees_per_pixel: float

    def as_dict(self) -> dict:
        return dict(x=self.x, y=self.y, direction=self.direction.tolist(), pixels=self.pixels,
                    clipped=self.clipped, contrast=self.contrast,
                    degrees_per_pixel=self.degrees_per_pixel)


def find_highlight(image, sphere: tuple[float, float, float], *,
                   clip_level: float | None = None, name: str = "image") -> Highlight:
    """The highlight of a mirror sphere in one image, and its light direction.

    Parameters
    ----------
    image : (H, W) or (H, W, c) array_like
        Linear values (bands are averaged).
    sphere : (cx, cy, r)
        The sphere's silhouette, pixels.
    clip_level : float, optional
        Values at or above it count as clipped (reported, still used).
    name : str, optional
        What to call the image in errors.

    Raises
    ------
    InputError
        No highlight (too little contrast), or one too large to be a point light.

    Examples
    --------
    >>> import numpy as np
    >>> from colorps import synth
    >>> from colorps.calibrate import find_highlight
    >>> ball = synth.sphere_surface(121, 50)
    >>> lights = synth.ring_lights(1, 40)
    >>> image = synth.render_mirror_sphere(ball, lights)[0]
    >>> found = find_highlight(image, (60, 60, 50))
    >>> bool(np.degrees(np.arccos(found.direction @ lights.directions[0, 0])) < 0.3)
    True
    """
    from skimage import measure

    values = np.asarray(image, dtype=np.float64)
    if values.ndim == 3:
        values = values.mean(axis=-1)
    cx, cy, r = (float(v) for v in sphere)
    h, w = values.shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    rho = np.hypot(x - cx, y - cy) / r
    disk = (rho <= SEARCH_RADIUS_FRACTION) & np.isfinite(values)
    if not disk.any():
        raise InputError(f"{name}: the sphere {cx:g},{cy:g},{r:g} lies outside the image")
    level = float(np.median(values[disk]))
    peak_at = np.unravel_index(np.argmax(np.where(disk, values, -np.inf)), values.shape)
    peak = float(values[peak_at])
    contrast = peak / level if level > 0 else np.inf
    if not (peak > 0 and contrast >= MIN_CONTRAST):
        raise InputError(f"{name}: no highlight on the mirror sphere (peak {peak:.3g} is "
                         f"{contrast:.2g}x the sphere's median; at least {MIN_CONTRAST:g}x "
                         "needed): is the light in front of the sphere, and the sphere right?")
    threshold = level + HIGHLIGHT_LEVEL * (peak - level)
    labels = measure.label(disk & (values >= threshold), connectivity=2)
    blob = labels == labels[peak_at]
    pixels = int(blob.sum())
    if pixels > MAX_HIGHLIGHT_FRACTION * disk.sum():
        raise InputError(f"{name}: the highlight covers {pixels / disk.sum():.0%} of the "
                         "sphere: not the reflection of a point light (a matte sphere, an "
                         "area light or overexposure?)")
    weight = values[blob] - threshold + 1e-12 * peak
    hx = float((x[blob] * weight).sum() / weight.sum())
    hy = float((y[blob] * weight).sum() / weight.sum())
    nx, ny = (hx - cx) / r, -(hy - cy) / r
    nz = float(np.sqrt(max(1.0 - nx * nx - ny * ny, 0.0)))
    normal = np.array([nx, ny, nz])
    direction = 2.0 * nz * normal - np.array([0.0, 0.0, 1.0])
    direction /= np.linalg.norm(direction)
    clipped = int((values[blob] >= clip_level).sum()) if clip_level is not None else 0
    return Highlight(hx, hy, direction, pixels, clipped, float(contrast),
                     float(np.degrees(2.0 / (r * max(nz, 1e-3)))))


def calibrate_lights(stack, sphere: tuple[float, float, float], *,
                     clip_level: float | None = None, names=None
                     ) -> tuple[Lights, list[Highlight]]:
    """Light directions of a capture from its mirror-sphere images.

    Parameters
    ----------
    stack : (m, H, W, c) or (m, H, W) array_like
        Linear images of the mirror sphere, one per light.
    sphere : (cx, cy, r)
    clip_level : float, optional
    names : sequence of str, optional
        Image names (errors, and the ``.lp`` file).

    Returns
    -------
    Lights
        Directions in image order, unit intensities (a mirror sphere does not
        measure them reliably).
    list of Highlight
        What each image showed.
    """
    images = np.asarray(stack)
    names = list(names) if names is not None else [f"image {k}" for k in range(len(images))]
    found = [find_highlight(image, sphere, clip_level=clip_level, name=name)
             for image, name in zip(images, names, strict=True)]
    return Lights(np.array([f.direction for f in found]),
                  names=tuple(str(n) for n in names)), found
