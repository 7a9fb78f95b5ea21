"""The gauge: an object of known normals and albedo, usually a sphere.

Sphere geometry under orthographic view, in pixel coordinates (x = column,
y = row, pixel centres at integers), centre (cx, cy) and radius r in pixels:
see :func:`colorps.geometry.sphere_normals`. Only pixels safely inside
the rim are used: at the rim the normal changes fastest per pixel and pixels
mix sphere and background. How far inside is measured on the gauge's images
where they are at hand (:func:`rim_margin`): a small gauge shows its steepest
normals only in its outermost pixels.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ._config import MIN_RADIUS
from .camera import Camera
from .errors import GaugeError, InputError
from .geometry import circle_of_cone, silhouette_cone, sphere_normals
from .sphere_edge import edge_points
from .spikes import BRIGHT_PERCENTILE, spike_free

__all__ = ["DEFAULT_ALBEDO", "MIN_RADIUS", "Gauge", "check_circle", "find_sphere",
           "parse_albedo", "rim_margin"]

#: Albedo of a gauge when none is given: a white gauge gives absolute albedo.
DEFAULT_ALBEDO = 1.0
#: Radius (pixels) of a rendered (virtual) gauge sphere: about 30,000 table
#: entries; the refinement goes past its pixel grid.
DEFAULT_VIRTUAL_RADIUS = 100.0

# ---------------------------------------------------------------- tuning
#: Pixels closer than max(RIM_MARGIN_PX, RIM_MARGIN_FRACTION r) to the rim are
#: left out of the table when the edge is not measured (Gauge.from_sphere's
#: default): the normal turns fastest there and pixels mix sphere and background.
RIM_MARGIN_PX = 2.0
RIM_MARGIN_FRACTION = 0.02
#: Measured on the images (:func:`rim_margin`), the margin is at least
#: RIM_MARGIN_MIN_PX (a pixel whose centre lies 1 px inside the edge lies wholly
#: inside: its half diagonal is 0.71 px) and RIM_MARGIN_FRACTION r; where the
#: background outside the edge is brighter than DARK_BACKGROUND of the sphere's
#: edge, the edge's blur too (from the edge in to the ramp's shoulder): mixing with
#: a bright background adds a foreign signature, while mixing with a dark one
#: only scales the observation vector, which its normalisation takes out.
RIM_MARGIN_MIN_PX = 1.0
DARK_BACKGROUND = 0.05
#: find_sphere: the sphere is segmented at SEGMENT_LEVEL of the bright level
#: (the BRIGHT_PERCENTILE of the brightest-of-all-images picture); a second
#: region of SECOND_REGION of the largest's size makes the gauge ambiguous; the
#: outline needs MIN_OUTLINE_POINTS points, and a circle fitted by RANSAC
#: (inliers within RANSAC_RESIDUAL_PX, RANSAC_TRIALS trials) must explain
#: MIN_INLIER_FRACTION of it over an arc of MIN_ARC_DEG, hold MIN_INSIDE of the
#: region within REGION_SLACK_PX of its rim, and be MIN_COVER covered by it (a
#: sphere lit from one side only shows half its disk). BRIGHT_PERCENTILE is
#: :mod:`colorps.spikes`'s, which cleans that picture first.
SEGMENT_LEVEL = 0.05
SECOND_REGION = 0.25
MIN_OUTLINE_POINTS = 20
RANSAC_RESIDUAL_PX = 1.0
RANSAC_TRIALS = 500
MIN_INLIER_FRACTION = 0.4
MIN_ARC_DEG = 150.0
MIN_INSIDE = 0.97
REGION_SLACK_PX = 1.5
MIN_COVER = 0.35


def parse_albedo(albedo, bands: int) -> np.ndarray:
    """Gauge albedo as one reflectance in (0, 1] per band (a scalar applies to all)."""
    try:
        values = np.atleast_1d(np.asarray(albedo, dtype=np.float64))
    except (TypeError, ValueError):
        raise GaugeError(f"gauge albedo: expected a number or one per band, got {albedo!r}") from None
    if values.ndim != 1 or values.size not in (1, bands):
        raise GaugeError(f"gauge albedo: expected 1 or {bands} values, got {values.size}")
    if not np.all(np.isfinite(values)) or np.any(values <= 0) or np.any(values > 1):
        raise GaugeError(f"gauge albedo: values are reflectances in (0, 1] (80 % is 0.8), "
                         f"got {values.tolist()}")
    return np.broadcast_to(values, (bands,)).copy()


@dataclass(frozen=True)
class Gauge:
    """Known normals of a gauge image and its albedo.

    Attributes
    ----------
    normals : (H, W, 3) ndarray of float32
        Camera-space unit normals (anything outside ``mask``).
    mask : (H, W) ndarray of bool
        Gauge pixels used for the signature table.
    albedo : float or (c,) array_like
        Intrinsic albedo G* of the gauge (one value, or one per band).
    sphere : (cx, cy, r) or None
        Sphere geometry when the gauge is a sphere.
    stack : (m, H, W, c) ndarray or None
        The gauge's images when colorps rendered them (:meth:`virtual`).
    rim_margin : float or None
        A sphere's pixels closer than this to its rim (pixels) are left out.
    """

    normals: np.ndarray
    mask: np.ndarray
    albedo: object = DEFAULT_ALBEDO
    sphere: tuple[float, float, float] | None = None
    stack: np.ndarray | None = None
    rim_margin: float | None = None

    def __post_init__(self):
        normals = np.asarray(self.normals, dtype=np.float32)
        mask = np.asarray(self.mask, dtype=bool)
        if normals.ndim != 3 or normals.shape[2] != 3 or mask.shape != normals.shape[:2]:
            raise GaugeError(
                f"gauge: normals must be (H, W, 3) and mask (H, W); got {normals.shape} "
                f"and {mask.shape}")
        if not mask.any():
            raise GaugeError("gauge: the mask selects no pixel")
        object.__setattr__(self, "normals", normals)
        object.__setattr__(self, "mask", mask)

    @classmethod
    def from_sphere(cls, shape: tuple[int, int], cx: float, cy: float, radius: float,
                    albedo=DEFAULT_ALBEDO, *, rim_margin: float | None = None,
                    camera: Camera | None = None) -> Gauge:
        """A sphere gauge of centre (cx, cy) and radius ``radius`` (pixels).

        Parameters
        ----------
        shape : (H, W)
            Size of the gauge images.
        cx, cy, radius : float
            Sphere silhouette in pixel coordinates.
        albedo : float or (c,) array_like
        rim_margin : float, optional
            Pixels closer than this to the rim are left out (pixels; default
            ``max(RIM_MARGIN_PX, RIM_MARGIN_FRACTION * radius)``, what a gauge
            needs whose edge has not been measured; ``colorps reconstruct``
            passes :func:`rim_margin` of the gauge's images).
        camera : Camera, optional
            The pinhole camera the gauge images were taken with, in their
            pixel grid (default: orthographic): the normals are then those
            where each pixel's ray meets the sphere
            (:func:`colorps.geometry.sphere_normals`).

        Raises
        ------
        GaugeError
            When the sphere is not entirely inside the image, or too small.
        """
        h, w = shape
        check_circle(shape, (cx, cy, radius))
        if radius < MIN_RADIUS:
            raise GaugeError(f"sphere: radius {radius:g} px is too small for a useful "
                             f"table (need at least {MIN_RADIUS:g} px; 100+ px recommended)")
        margin = (max(RIM_MARGIN_PX, RIM_MARGIN_FRACTION * radius) if rim_margin is None
                  else float(rim_margin))
        normals, rho = sphere_normals((h, w), cx, cy, radius, camera)
        mask = rho <= 1.0 - margin / radius
        normals[~mask] = 0.0
        return cls(normals, mask, albedo, (float(cx), float(cy), float(radius)),
                   rim_margin=float(margin))

    def within(self, box: tuple[slice, slice]) -> Gauge:
        """The gauge in a box (rows, columns) of its images, its sphere's centre
        counted from the box's corner."""
        rows, cols = box
        sphere = None if self.sphere is None else \
            (self.sphere[0] - cols.start, self.sphere[1] - rows.start, self.sphere[2])
        stack = None if self.stack is None else self.stack[:, rows, cols]
        return dataclasses.replace(self, normals=self.normals[rows, cols],
                                   mask=self.mask[rows, cols], sphere=sphere, stack=stack)

    @classmethod
    def virtual(cls, lights, *, radius: float = DEFAULT_VIRTUAL_RADIUS, bands: int | None = None,
                brdf="lambert") -> Gauge:
        """A sphere gauge rendered under calibrated lights (no gauge photographs).

        Parameters
        ----------
        lights : Lights
            Directions and intensities, one per image (:mod:`colorps.lights`).
        radius : float, optional
            Sphere radius in pixels of the rendered table (default
            :data:`DEFAULT_VIRTUAL_RADIUS`).
        bands : int, optional
            Bands of the scene images (default: the intensities').
        brdf : {"lambert", "oren-nayar"} or BRDF, optional
            The finish assumed for scene and gauge alike: a name of
            :func:`colorps.synth.render`'s, or a :class:`colorps.brdf.BRDF`
            (fitted to the scene by :func:`colorps.virtual.fit_scene_brdf`).

        Returns
        -------
        Gauge
            Of albedo 1 (albedo maps come out absolute), with ``stack`` the
            rendered (m, H, W, c) images.

        Examples
        --------
        >>> from colorps import Gauge, Lights
        >>> gauge = Gauge.virtual(Lights([[0, 0, 1], [0.6, 0, 0.8], [0, 0.6, 0.8]]),
        ...                       radius=20, bands=3)
        >>> gauge.stack.shape, gauge.sphere
        ((3, 50, 50, 3), (24.5, 24.5, 20.0))
        """
        from .brdf import BRDF
        from .synth import render, sphere_surface

        bands = bands or lights.intensities.shape[1]
        size = int(np.ceil(2 * radius + 10))
        centre = (size - 1) / 2.0
        ball = sphere_surface(size, radius, bands=bands)
        lighting = lights.as_lighting(bands)
        if isinstance(brdf, BRDF):
            stack = np.zeros((lights.images, size, size, bands), dtype=np.float32)
            stack[:, ball.mask] = brdf.shade(ball.normals[ball.mask], lights.directions,
                                             lighting.colours[:, 0, :])
        else:
            stack = render(ball, lighting, brdf=brdf)
        gauge = cls.from_sphere((size, size), centre, centre, radius, albedo=DEFAULT_ALBEDO)
        return cls(gauge.normals, gauge.mask, gauge.albedo, gauge.sphere, stack,
                   rim_margin=gauge.rim_margin)


def find_sphere(stack, camera: Camera | None = None, *, exclude=None
                ) -> tuple[float, float, float]:
    """Find the gauge sphere's silhouette in a gauge stack.

    The brightest value of every pixel over all images is taken (the union of
    the lit parts: a real capture's lights rarely reach the whole sphere, so
    part of its rim stays dark in every image), the sphere is segmented with a
    low threshold (SEGMENT_LEVEL of the bright level; the background is assumed
    darker), and a circle is fitted robustly with scikit-image (RANSAC over
    ``CircleModel``) to the subpixel outline of the largest region. Only the
    lit arc of the outline lies on the circle; the rest (the terminator, where
    the unlit part begins) lies inside it.

    That outline lies outside the sphere's edge by the blur of its pixels and
    of the lens: 0.4 px on the bundled sample's sharp render (its mean normal
    error 0.27 degrees against 0.13 with the true circle), 1.4 and 2.9 px with a
    Gaussian blur of 1 and 2 px. So the circle is then
    moved to the edge (:func:`_edge_circle`): along radii of that circle the
    brightest picture is fitted by a lit rim, blurred
    (:func:`colorps.sphere_edge.edge_points`), and the circle is fitted again
    to those edges (radius within 0.11 px of the truth on renders area-sampled
    and blurred by 0 to 2 px, lit near the view or across the dome).

    The circle is accepted when its inliers make up MIN_INLIER_FRACTION of the
    outline and span MIN_ARC_DEG around the centre, the region lies within the
    circle and covers MIN_COVER of it.

    Through a lens (``camera``) the sphere's image is an ellipse, and a circle
    fitted to the lit arc of it alone is off by pixels (a sphere of radius 60 px
    2.5 radii off the axis at a focal length of 8 radii: its centre 1.5 px and
    its radius 0.8 px off). The edge points' rays are fitted instead by the cone of rays
    tangent to the sphere (:func:`colorps.geometry.silhouette_cone`, on the
    circle's inliers, then again on every edge point within
    RANSAC_RESIDUAL_PX of that cone), and the circle returned is the one that
    stands for that cone in :func:`colorps.geometry.sphere_normals`.

    Parameters
    ----------
    stack : (m, H, W, c) array_like
        Linear gauge images.
    camera : Camera, optional
        The pinhole camera the images were taken with (default orthographic).
    exclude : (H, W) array_like of bool, optional
        Pixels that are not the gauge, left out of the search: the object, when
        the gauge shares the scene's frame.

    Returns
    -------
    (cx, cy, r) : tuple of float
        Pixel coordinates (x = column, y = row) and radius in pixels.

    Raises
    ------
    GaugeError
        When no convincing circle is found, or two regions could be the gauge.
    """
    from skimage import measure

    data = np.asarray(stack, dtype=np.float32)
    if data.ndim == 3:
        data = data[..., None]
    if data.ndim != 4:
        raise InputError(f"gauge stack: expected (m, H, W, c), got shape {data.shape}")
    if min(data.shape[1:3]) < 2 * MIN_RADIUS:
        raise GaugeError(f"sphere auto: the {data.shape[2]}x{data.shape[1]} gauge images "
                         f"are too small to hold a sphere of {MIN_RADIUS:g}+ px radius")
    brightest, bright = _brightest(data)
    if exclude is not None:
        brightest = np.where(np.asarray(exclude, dtype=bool), np.float32(0.0), brightest)
        bright = float(np.percentile(brightest, BRIGHT_PERCENTILE))
    if not bright > 0:
        raise GaugeError("sphere auto: the gauge images are black; cannot find the sphere")
    level = SEGMENT_LEVEL * bright
    labels = measure.label(brightest > level)
    if labels.max() == 0:
        raise GaugeError("sphere auto: no bright region found in the gauge images")
    sizes = np.bincount(labels.ravel())[1:]
    ranked = np.argsort(sizes)[::-1]
    if len(ranked) > 1 and sizes[ranked[1]] >= SECOND_REGION * sizes[ranked[0]]:
        raise GaugeError(
            f"sphere auto: two bright regions of {sizes[ranked[0]]} and "
            f"{sizes[ranked[1]]} px could each be the gauge; crop the gauge images to one "
            "sphere or give --sphere CX,CY,R (or, for a gauge in the scene's own frame, "
            "--mask of the object)")
    region = labels == ranked[0] + 1
    # Subpixel boundary of the region, on the image masked to it.
    contours = measure.find_contours(np.where(region, brightest, 0.0), level)
    points = max(contours, key=len)[:, ::-1] if contours else np.zeros((0, 2))
    if len(points) < MIN_OUTLINE_POINTS:
        raise GaugeError("sphere auto: the bright region is too small to be a gauge sphere")
    model, inliers = _ransac_circle(points)
    if model is None or inliers is None:
        raise GaugeError("sphere auto: no circle fits the gauge's outline")
    cx, cy, r = _circle_of(model)
    angles = np.degrees(np.arctan2(points[inliers, 1] - cy, points[inliers, 0] - cx))
    gaps = np.diff(np.sort(angles), append=np.sort(angles)[:1] + 360.0) if angles.size \
        else np.array([360.0])
    arc = 360.0 - float(gaps.max())
    ys, xs = np.nonzero(region)
    inside = float(np.mean(np.hypot(xs - cx, ys - cy) <= r + REGION_SLACK_PX))
    cover = region.sum() / (np.pi * r * r)
    if (inliers.mean() < MIN_INLIER_FRACTION or arc < MIN_ARC_DEG
            or inside < MIN_INSIDE or cover < MIN_COVER):
        raise GaugeError(
            f"sphere auto: no convincing circle (best fit ({cx:.1f}, {cy:.1f}) r={r:.1f} "
            f"explains {inliers.mean():.0%} of the outline over a {arc:.0f} degree arc, "
            f"{inside:.0%} of the region inside it, covering {cover:.0%} of the disk); "
            "give --sphere CX,CY,R")
    return _edge_circle(brightest, (cx, cy, r), bright, camera)


def check_circle(shape: tuple[int, int], circle: tuple[float, float, float]) -> None:
    """Raise GaugeError unless ``circle`` (cx, cy, r; pixels) lies whole, finite
    and of positive radius, inside an image of ``shape`` (H, W)."""
    h, w = shape
    cx, cy, radius = circle
    if not np.all(np.isfinite(np.array(circle, dtype=np.float64))) or radius <= 0:
        raise GaugeError(f"sphere: centre and radius must be finite, radius > 0; got "
                         f"{cx}, {cy}, {radius}")
    if cx - radius < -0.5 or cy - radius < -0.5 or cx + radius > w - 0.5 or \
            cy + radius > h - 0.5:
        raise GaugeError(
            f"sphere: circle at ({cx:g}, {cy:g}) with radius {radius:g} is partly "
            f"outside the {w}x{h} gauge image")


def rim_margin(stack, circle: tuple[float, float, float], camera: Camera | None = None
               ) -> float:
    """How far inside its rim a photographed sphere's pixels are usable (pixels).

    Measured on the brightest picture of the images, along the lit radii of
    ``circle`` as :func:`find_sphere` finds the edge: max(RIM_MARGIN_MIN_PX,
    RIM_MARGIN_FRACTION r), or the edge's blur (from the edge in to the ramp's
    shoulder) where the background is brighter than DARK_BACKGROUND of the
    sphere; plus how far ``circle`` reaches past the edge found (not measured
    through a lens, ``camera``, whose sphere's image is an ellipse). Where too
    few radii are lit: max(RIM_MARGIN_PX, RIM_MARGIN_FRACTION r), what
    :meth:`Gauge.from_sphere` takes by default.

    Parameters
    ----------
    stack : (m, H, W, c) array_like
        Linear gauge images.
    circle : (cx, cy, r)
        The sphere's silhouette, pixels.
    camera : Camera, optional

    Returns
    -------
    float
        Pixels; pass it as ``Gauge.from_sphere(..., rim_margin=...)``.

    Raises
    ------
    GaugeError
        When ``circle`` is not entirely inside the images (:func:`check_circle`).

    Examples
    --------
    >>> from colorps import synth
    >>> from colorps.gauge import rim_margin
    >>> from colorps.shapes import dome_lights
    >>> stack = synth.render(synth.sphere_surface(50, 20), dome_lights(8))
    >>> rim_margin(stack, (24.5, 24.5, 20.0))  # a sharp edge on a dark background
    1.0
    """
    data = np.asarray(stack, dtype=np.float32)
    if data.ndim == 3:
        data = data[..., None]
    check_circle(data.shape[1:3], circle)
    cx, cy, r = (float(v) for v in circle)
    unmeasured = max(RIM_MARGIN_PX, RIM_MARGIN_FRACTION * r)
    brightest, bright = _brightest(data)
    if not bright > 0:
        return unmeasured
    edges = edge_points(brightest, (cx, cy, r), bright)
    if len(edges.radius) < MIN_OUTLINE_POINTS:
        return unmeasured
    blur = float(np.median(edges.radius - edges.shoulder)) \
        if np.median(edges.outside) > DARK_BACKGROUND else 0.0
    past = 0.0 if camera is not None else max(0.0, r - float(np.median(edges.radius)))
    return max(RIM_MARGIN_MIN_PX, RIM_MARGIN_FRACTION * r, blur) + past


def _brightest(data: np.ndarray) -> tuple[np.ndarray, float]:
    """The brightest value of every pixel over the (m, H, W, c) images, its
    isolated spikes replaced (every image's fireflies show in it: 1 % of a
    32-light gauge's measurements spiked had the sphere refused as "two bright
    regions" and the rim margin measured 4.4 px instead of 1.2), and its
    BRIGHT_PERCENTILE (the bright level)."""
    brightest = None
    for image in data:  # (one image's temporaries at a time: a whole frame's are large)
        value = np.where(np.isfinite(image), image, 0.0).max(axis=-1)
        brightest = value if brightest is None else np.maximum(brightest, value, out=brightest)
    brightest = spike_free(brightest)
    return brightest, float(np.percentile(brightest, BRIGHT_PERCENTILE))


def _ransac_circle(points: np.ndarray):
    """scikit-image's robust circle fit to (N, 2) points (x, y): (CircleModel or
    None, inlier mask or None), within RANSAC_RESIDUAL_PX."""
    from skimage import measure

    return measure.ransac(points, measure.CircleModel, min_samples=3,
                          residual_threshold=RANSAC_RESIDUAL_PX, max_trials=RANSAC_TRIALS,
                          rng=0)


def _circle_of(model) -> tuple[float, float, float]:
    """(cx, cy, r) of a fitted scikit-image ``CircleModel``."""
    if hasattr(model, "center"):  # scikit-image >= 0.26
        (cx, cy), r = (float(v) for v in model.center), float(model.radius)
        return cx, cy, r
    cx, cy, r = (float(v) for v in model.params)
    return cx, cy, r


def _edge_circle(brightest: np.ndarray, circle: tuple[float, float, float],
                 bright: float, camera: Camera | None = None) -> tuple[float, float, float]:
    """The circle through the sphere's edge near ``circle`` (see :func:`find_sphere`);
    ``circle`` itself when too few radii cross a lit edge."""
    cx, cy, _ = circle
    edges = edge_points(brightest, circle, bright)
    points = np.stack([cx + edges.radius * np.cos(edges.angle),
                       cy + edges.radius * np.sin(edges.angle)], axis=1)
    if len(points) < MIN_OUTLINE_POINTS:
        return circle
    model, inliers = _ransac_circle(points)
    if model is None or inliers is None or inliers.mean() < MIN_INLIER_FRACTION:
        return circle
    if camera is not None:
        return _edge_cone(points, inliers, camera, brightest.shape)
    return _circle_of(model)


def _edge_cone(points: np.ndarray, inliers: np.ndarray, camera: Camera,
               shape: tuple[int, int]) -> tuple[float, float, float]:
    """The circle standing for the cone of rays through the edge ``points`` (x, y):
    fitted to the circle's ``inliers``, then to every point within
    RANSAC_RESIDUAL_PX of that cone."""
    rays = camera.rays(points[:, 0], points[:, 1], shape)
    axis, alpha = silhouette_cone(rays[inliers])
    focal = camera.focal
    off_px = np.abs(np.arccos(np.clip(rays @ axis, -1.0, 1.0)) - alpha) * focal
    near = off_px <= RANSAC_RESIDUAL_PX
    if near.sum() >= MIN_OUTLINE_POINTS:
        axis, alpha = silhouette_cone(rays[near])
    return circle_of_cone(axis, alpha, camera, shape)

