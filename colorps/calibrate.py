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
pixels, its contrast, ``degrees_per_pixel``, how far the light moves when the
centre is off by one pixel (2 / (r nz) radians: large near the rim), and
``rival``, the peak of the brightest other blob over the chosen one's.

A second bright blob (a window, a lamp's housing, a reflection of the room)
makes an image **ambiguous** when its peak rises at least RIVAL_LEVEL of the
brightest's height above the sphere's median: of such candidates
:func:`calibrate_lights` takes the one most like the capture's unambiguous
highlights in size and shape (one light source makes highlights of one size
and shape on one sphere, once the foreshortening towards the rim is undone),
and warns, naming the image and both positions; a candidate whose light would
come from behind the object (a direction with z <= 0: a highlight farther than
sin 45 degrees of the radius from the centre, which lights nothing facing the
camera head on) is taken only when every candidate is. With no unambiguous
image to compare with, it refuses, as it does an image whose light would come
from behind (more likely a reflection of the room than a light of the capture).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from .errors import ColorPSWarning, InputError
from .lights import DIRECTION_HEADER, MIN_ELEVATION_Z, Lights, direction_columns

__all__ = ["AmbiguousHighlightWarning", "Highlight", "calibrate_lights", "find_highlight",
           "highlight_candidates", "highlight_table", "sphere_from_mask"]

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
#: Another blob whose peak rises this fraction of the brightest's height above
#: the sphere's median makes the image ambiguous (see the module docstring): a
#: light's highlight is then still a candidate beside a reflection up to 4
#: times as bright.
RIVAL_LEVEL = 0.25


class AmbiguousHighlightWarning(ColorPSWarning):
    """A mirror-sphere image shows more than one bright blob that could be the light."""


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
    elongation : float
        Its longest over its shortest spread (intensity-weighted second
        moments), with the sphere's foreshortening towards the rim undone (a
        round source: about 1; a window or a bar: more).
    rival : float
        Peak of the brightest other candidate blob over this one's (0: none
        above RIVAL_LEVEL; 1 or more: the chosen blob is not the brightest).
    """

    x: float
    y: float
    direction: np.ndarray
    pixels: int
    clipped: int
    contrast: float
    degrees_per_pixel: float
    elongation: float = 1.0
    rival: float = 0.0

    @property
    def unforeshortened_pixels(self) -> float:
        """Its size as if seen face on: pixels / nz (the sphere's normal at its centre)."""
        return self.pixels / max(float(self.direction[2] + 1.0) ** 0.5 / 2 ** 0.5, 1e-3)

    def as_dict(self) -> dict:
        return dict(x=self.x, y=self.y, direction=self.direction.tolist(), pixels=self.pixels,
                    clipped=self.clipped, contrast=self.contrast,
                    degrees_per_pixel=self.degrees_per_pixel, elongation=self.elongation,
                    rival=self.rival)


def find_highlight(image, sphere: tuple[float, float, float], *,
                   clip_level: float | None = None, name: str = "image") -> Highlight:
    """The highlight of a mirror sphere in one image, and its light direction: the
    brightest of :func:`highlight_candidates`, with ``rival`` the next one's peak
    over its own.

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
    >>> from colorps.shapes import render_mirror_sphere
    >>> ball = synth.sphere_surface(121, 50)
    >>> lights = synth.ring_lights(1, 40)
    >>> image = render_mirror_sphere(ball, lights)[0]
    >>> found = find_highlight(image, (60, 60, 50))
    >>> bool(np.degrees(np.arccos(found.direction @ lights.directions[0, 0])) < 0.3)
    True
    """
    return highlight_candidates(image, sphere, clip_level=clip_level, name=name)[0]


def highlight_candidates(image, sphere: tuple[float, float, float], *,
                         clip_level: float | None = None, name: str = "image"
                         ) -> list[Highlight]:
    """Every blob of a mirror-sphere image that could be the light's highlight,
    brightest first: the blob around the brightest pixel, and each other blob
    whose peak rises RIVAL_LEVEL of its height above the sphere's median (each
    with ``rival`` set to the peak of the brightest other candidate over its own).

    Raises
    ------
    InputError
        As :func:`find_highlight`.
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
    inside = np.where(disk, values, -np.inf)
    peak = float(inside.max())
    contrast = peak / level if level > 0 else np.inf
    if not (peak > 0 and contrast >= MIN_CONTRAST):
        raise InputError(f"{name}: no highlight on the mirror sphere (peak {peak:.3g} is "
                         f"{contrast:.2g}x the sphere's median; at least {MIN_CONTRAST:g}x "
                         "needed): is the light in front of the sphere, and the sphere right? "
                         "A matte sphere (a gauge) has no highlight: pass --matte for it")
    labels = measure.label(disk & (values >= level + RIVAL_LEVEL * (peak - level)),
                           connectivity=2)
    peaks = np.zeros(labels.max() + 1)
    np.maximum.at(peaks, labels.ravel(), np.where(labels > 0, values, 0.0).ravel())
    order = [k for k in np.argsort(-peaks) if k > 0]
    found = []
    for k in order:
        at = np.unravel_index(np.argmax(np.where(labels == k, values, -np.inf)), values.shape)
        found.append(_highlight(values, at, level, disk, (cx, cy, r), clip_level, name,
                                (x, y)))
    found = [f for f in found if f is not None]
    if not found:
        raise InputError(f"{name}: the highlight covers more than "
                         f"{MAX_HIGHLIGHT_FRACTION:.0%} of the sphere: not the reflection of "
                         "a point light (a matte sphere, an area light or overexposure?)")
    peaks_of = [f.contrast for f in found]
    return [_with_rival(f, max((p for j, p in enumerate(peaks_of) if j != i), default=0.0))
            for i, f in enumerate(found)]


def _with_rival(found: Highlight, other_contrast: float) -> Highlight:
    from dataclasses import replace

    return replace(found, rival=other_contrast / found.contrast if other_contrast else 0.0)


def _highlight(values, peak_at, level, disk, sphere, clip_level, name, grid):
    """The highlight blob around ``peak_at`` and its direction (None: too large)."""
    from skimage import measure

    cx, cy, r = sphere
    x, y = grid
    peak = float(values[peak_at])
    threshold = level + HIGHLIGHT_LEVEL * (peak - level)
    labels = measure.label(disk & (values >= threshold), connectivity=2)
    blob = labels == labels[peak_at]
    pixels = int(blob.sum())
    if pixels > MAX_HIGHLIGHT_FRACTION * disk.sum():
        return None
    weight = values[blob] - threshold + 1e-12 * peak
    hx = float((x[blob] * weight).sum() / weight.sum())
    hy = float((y[blob] * weight).sum() / weight.sum())
    nx, ny = (hx - cx) / r, -(hy - cy) / r
    nz = float(np.sqrt(max(1.0 - nx * nx - ny * ny, 0.0)))
    normal = np.array([nx, ny, nz])
    direction = 2.0 * nz * normal - np.array([0.0, 0.0, 1.0])
    direction /= np.linalg.norm(direction)
    clipped = int((values[blob] >= clip_level).sum()) if clip_level is not None else 0
    contrast = peak / level if level > 0 else np.inf
    return Highlight(hx, hy, direction, pixels, clipped, float(contrast),
                     float(np.degrees(2.0 / (r * max(nz, 1e-3)))),
                     _elongation(x[blob] - hx, y[blob] - hy, weight, (nx, -ny), nz))


def _elongation(dx, dy, weight, radial, nz: float) -> float:
    """The square root of the largest over the smallest eigenvalue of the blob's weighted
    covariance, its radial axis stretched by 1 / nz (undoing the foreshortening);
    a blob of one pixel is round (1)."""
    cov = np.cov(np.stack([dx, dy]), aweights=weight, bias=True) if len(dx) > 1 else \
        np.zeros((2, 2))
    norm = float(np.hypot(*radial))
    if norm > 0:
        e = np.array(radial) / norm
        stretch = np.eye(2) + (1.0 / max(nz, 0.05) - 1.0) * np.outer(e, e)
        cov = stretch @ cov @ stretch
    low, high = np.linalg.eigvalsh(cov + 1.0 / 12.0 * np.eye(2))  # + a pixel's own spread
    return float(np.sqrt(high / low))


def sphere_from_mask(mask) -> tuple[float, float, float]:
    """(cx, cy, r) of the sphere a mask image shows: the largest connected region's
    centroid and the radius of a disk of its area (scikit-image's region
    properties).

    Raises
    ------
    InputError
        The mask selects no pixel.
    """
    from skimage import measure

    labels = measure.label(np.asarray(mask, bool))
    regions = measure.regionprops(labels)
    if not regions:
        raise InputError("sphere mask: selects no pixel")
    largest = max(regions, key=lambda region: region.area)
    cy, cx = largest.centroid
    return float(cx), float(cy), float(np.sqrt(largest.area / np.pi))


def calibrate_lights(stack, sphere: tuple[float, float, float], *,
                     clip_level: float | None = None, names=None
                     ) -> tuple[Lights, list[Highlight]]:
    """Light directions of a capture from its mirror-sphere images.

    In an ambiguous image (module docstring) the candidate most like the
    unambiguous images' highlights is taken, with an
    :class:`AmbiguousHighlightWarning`: the least sum of the log ratios of its
    size and of its elongation to their medians (both with the sphere's
    foreshortening undone: :attr:`Highlight.unforeshortened_pixels`,
    :attr:`Highlight.elongation`), of those whose light is in front of the
    object when there are any.

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

    Raises
    ------
    InputError
        An image without a highlight or whose highlight gives a light from
        behind the object, or ambiguous images and no unambiguous one to
        compare them with.
    """
    images = np.asarray(stack)
    names = list(names) if names is not None else [f"image {k}" for k in range(len(images))]
    candidates = [highlight_candidates(image, sphere, clip_level=clip_level, name=name)
                  for image, name in zip(images, names, strict=True)]
    clear = [c[0] for c in candidates if len(c) == 1]
    found = []
    for name, options in zip(names, candidates):
        if len(options) == 1:
            found.append(options[0])
            continue
        where = ", ".join(f"({o.x:.0f}, {o.y:.0f}) {o.pixels} px" for o in options)
        if not clear:
            raise InputError(f"{name}: {len(options)} bright blobs on the mirror sphere "
                             f"({where}) and no image with a single one to tell the light's "
                             "highlight by: mask the other reflections or give cleaner images")
        size = float(np.median([c.unforeshortened_pixels for c in clear]))
        shape = float(np.median([c.elongation for c in clear]))
        in_front = [o for o in options if o.direction[2] >= MIN_ELEVATION_Z] or options
        chosen = min(in_front, key=lambda o: abs(np.log(o.unforeshortened_pixels / size)) +
                     abs(np.log(o.elongation / shape)))
        warnings.warn(f"{name}: {len(options)} bright blobs on the mirror sphere ({where}); "
                      f"took the one at ({chosen.x:.0f}, {chosen.y:.0f}), the most like the "
                      f"other images' highlights in size and shape: check this light",
                      AmbiguousHighlightWarning, stacklevel=2)
        found.append(chosen)
    for name, highlight in zip(names, found):
        if highlight.direction[2] < MIN_ELEVATION_Z:
            elevation = np.degrees(np.arcsin(np.clip(highlight.direction[2], -1.0, 1.0)))
            raise InputError(f"{name}: the highlight at ({highlight.x:.0f}, {highlight.y:.0f}) "
                             f"gives a light from behind the object ({-elevation:.0f} degrees "
                             "below the plane facing the camera), which lights nothing facing "
                             "it: a reflection of the room? Check the image and the sphere's "
                             "circle")
    return Lights(np.array([f.direction for f in found]),
                  names=tuple(str(n) for n in names)), found


def highlight_table(names, found: list[Highlight]) -> list[str]:
    """calibrate-lights' table: per image the direction and how sure it is."""
    lines = [f"{DIRECTION_HEADER} {'px':>4s} {'clip':>4s} {'elong':>5s} {'deg/px':>6s} "
             f"{'rival':>5s}"]
    for name, f in zip(names, found, strict=True):
        lines.append(f"{direction_columns(name, f.direction)} {f.pixels:4d} {f.clipped:4d} "
                     f"{f.elongation:5.2f} {f.degrees_per_pixel:6.2f} {f.rival:5.2f}")
    return lines
