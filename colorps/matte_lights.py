"""Light directions and intensities from a matte sphere: a diffuse fit per image.

A distant light of direction l and intensity E_b in band b shows on a matte
sphere of albedo a_b as I_b(n) = a_b E_b R(n, l) max(n . l, 0) at the pixel of
normal n (:class:`colorps.Gauge`'s normals within its rim margin), R the
Oren-Nayar factor of the sphere's roughness sigma (1 for a Lambertian sphere,
sigma 0; :func:`colorps.finishes.oren_nayar_factor`). Each image's light is
first the least-squares fit of the bands' sum that
:func:`colorps.gauge_check.lambertian_fit` makes (the fit by which colorps
checks that gauge images show a lit sphere, linear in sum_b a_b E_b l), on the
pixels it lights at a cosine of at least its LIT_FRACTION (the terminator,
where a real finish and the light's size depart from the model most, is left
out). Real matte paint is rough: a rough sphere is brighter towards the view
than the cosine, and the Lambertian fit tilts each direction to explain it. So
every roughness of ROUGHNESS_GRID is tried, one for all the images (the sphere
has one finish), each direction refined under it by Gauss-Newton on the same
pixels; from the grid's best the roughness is then refined between its
neighbours (:func:`colorps.brdf.refined_roughness`: a sphere
of roughness 0.15, between the grid's values, had its directions 0.17
degrees off at 0.1), and the roughness that explains the images best is kept
(:attr:`MatteLight.roughness`). Each band's intensity is then
E_b = (sum I_b S) / (a_b sum S^2) over the same pixels, S the fitted shading.

Real matte paint has a sheen: a faint highlight about the normal halfway
between the light and the view, which pulls a diffuse fit's direction towards
it and its roughness off. The pixels whose normal lies within HIGHLIGHT_ANGLE
of that halfway vector (of the Lambertian fit's light; along each pixel's ray
through a lens) are left out of the fits.

This is what a capture with a gauge of another finish than the scene's needs:
its lights, for a virtual gauge of the scene's own fitted finish (``colorps
reconstruct --lights``). A glossier sphere still biases them, and
:attr:`MatteLight.residual` (the fit's relative RMS residual) says how far it
departs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .brdf_fit import ROUGHNESS_GRID, refined_roughness
from .camera import Camera
from .errors import InputError
from .finishes import oren_nayar_factor
from .gauge import Gauge, parse_albedo
from .gauge_check import lambertian_fit
from .lights import DIRECTION_HEADER, MIN_ELEVATION_Z, Lights, direction_columns

__all__ = ["MatteLight", "matte_sphere_lights", "matte_table", "refine_direction"]

# ---------------------------------------------------------------- tuning
#: An image needs this many lit pixels on the sphere.
MIN_LIT_PIXELS = 30
#: Gauss-Newton steps of each direction at each roughness (the steps shrink
#: below 1e-6 radians by the fourth on the test spheres).
DIRECTION_STEPS = 6
#: Lit pixels of an image its rough fits use at most (a fixed sample).
ROUGH_FIT_PIXELS = 4000
#: Pixels whose normal is within this many degrees of the halfway vector between
#: an image's light and the view are left out (a sheen's highlight). A sphere
#: of Oren-Nayar 0.2 under a GGX coat (F0 0.04, alpha 0.25), 48 lights: its
#: directions 0.085 degrees off (0.19 at most) and roughness 0.161 with every
#: lit pixel, 0.026 and 0.185 leaving out 20 degrees, 0.009 (0.023) and 0.195
#: leaving out 30; matte spheres alike either way (within 0.01 degrees).
HIGHLIGHT_ANGLE = 30.0


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
        RMS of the fit's residuals over the RMS of the values (0 on a matte
        sphere without noise; a few per cent on real matte paint).
    roughness : float
        The sphere's Oren-Nayar roughness the fit took (radians; 0: Lambertian),
        the same for every image.
    """

    direction: np.ndarray
    intensity: np.ndarray
    pixels: int
    residual: float
    roughness: float = 0.0


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
    views = None
    if camera is not None:  # towards the camera, along each pixel's ray
        ys, xs = np.nonzero(gauge.mask)
        views = -camera.rays(xs, ys, gauge.mask.shape)
    vectors, lit = lambertian_fit(values.sum(axis=2), normals)
    for k, name in enumerate(names):
        if lit[k].sum() < MIN_LIT_PIXELS:
            raise InputError(f"{name}: only {int(lit[k].sum())} lit pixels on the matte "
                             f"sphere (need {MIN_LIT_PIXELS}); is the light on, the sphere "
                             "in the picture and not saturated?")
    lit = _without_highlights(lit, normals, views, vectors)
    directions, roughness = _rough_fit(values.sum(axis=2), normals, views, vectors, lit)
    albedo = parse_albedo(albedo, images.shape[3])
    found = [_light(values[k, lit[k]], _shading(normals[lit[k]], directions[k], roughness,
                                                None if views is None else views[lit[k]]),
                    directions[k], albedo, name, roughness)
             for k, name in enumerate(names)]
    lights = Lights(np.array([f.direction for f in found]),
                    np.array([f.intensity for f in found]), names=tuple(names))
    return lights, found


def _without_highlights(lit: np.ndarray, normals: np.ndarray, views, vectors: np.ndarray
                        ) -> np.ndarray:
    """The (m, P) ``lit`` pixels less those within HIGHLIGHT_ANGLE of the halfway
    vector between each image's light (its Lambertian ``vectors``) and the view
    (``views``, (P, 3), or the axis); an image keeps every lit pixel when fewer
    than MIN_LIT_PIXELS would remain."""
    view = np.array([0.0, 0.0, 1.0]) if views is None else views
    kept = lit.copy()
    for k, vector in enumerate(vectors):
        half = vector / np.linalg.norm(vector) + view
        half /= np.linalg.norm(half, axis=-1, keepdims=True)
        away = np.einsum("...i,...i->...", normals, half) < np.cos(np.radians(HIGHLIGHT_ANGLE))
        if (lit[k] & away).sum() >= MIN_LIT_PIXELS:
            kept[k] &= away
    return kept


def _shading(normals: np.ndarray, direction: np.ndarray, roughness: float,
             views: np.ndarray | None) -> np.ndarray:
    """(P,) the sphere's shading R(n, l) max(n . l, 0) for unit intensity and albedo."""
    cosine = np.maximum(normals @ direction, 0.0)
    if roughness == 0.0:
        return cosine
    return cosine * oren_nayar_factor(normals, direction, roughness, views)[0]


def _rough_fit(sums: np.ndarray, normals: np.ndarray, views, vectors: np.ndarray,
               lit: np.ndarray) -> tuple[np.ndarray, float]:
    """The (m, 3) directions and the one roughness that explain the images' band
    sums (m, P) best on their lit pixels: the best of ROUGHNESS_GRID, each
    direction refined from its Lambertian ``vectors``, then refined between the
    grid's neighbours (see the module docstring)."""
    rng = np.random.default_rng(0)
    picks = []
    for row in lit:
        pick = np.flatnonzero(row)
        if len(pick) > ROUGH_FIT_PIXELS:
            pick = np.sort(rng.choice(pick, ROUGH_FIT_PIXELS, replace=False))
        picks.append(pick)
    start = vectors / np.linalg.norm(vectors, axis=1, keepdims=True)

    def fitted(roughness: float, starts: np.ndarray) -> tuple[np.ndarray, float]:
        directions, cost = [], 0.0
        for k, pick in enumerate(picks):
            direction, part = _refined_direction(
                sums[k, pick], normals[pick], None if views is None else views[pick],
                starts[k], roughness)
            directions.append(direction)
            cost += part
        return np.array(directions), cost

    tried = {roughness: fitted(roughness, start) for roughness in ROUGHNESS_GRID}
    best = min(tried, key=lambda r: tried[r][1])
    from_best = tried[best][0]  # each roughness between refines the grid's best directions

    def cost(roughness: float) -> float:
        if roughness not in tried:
            tried[roughness] = fitted(roughness, from_best)
        return tried[roughness][1]

    best = refined_roughness(cost, best)
    return tried[best][0], float(best)


def _refined_direction(shown: np.ndarray, normals: np.ndarray, views, direction: np.ndarray,
                       roughness: float) -> tuple[np.ndarray, float]:
    """One light's direction under ``roughness`` (Gauss-Newton on two tangent
    angles, the intensity projected out) and its relative squared residual."""

    def residual(d):
        shade = _shading(normals, d, roughness, views)
        return shown - shade * (shown @ shade) / max(shade @ shade, 1e-30)

    direction, cost = refine_direction(residual, direction, DIRECTION_STEPS)
    return direction, float(cost / max(shown @ shown, 1e-30))


def refine_direction(residual, direction: np.ndarray, steps: int) -> tuple[np.ndarray, float]:
    """A unit direction refined by up to ``steps`` Gauss-Newton steps on two
    tangent angles (derivatives over 1e-6 radians), each taken only when it
    lowers the sum of squares of ``residual(direction)`` (a 1-D array); the
    direction and that sum."""

    def turned(d, du, dv):
        helper = [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0]
        t1 = np.cross(d, helper)
        t1 /= np.linalg.norm(t1)
        moved = d + du * t1 + dv * np.cross(d, t1)
        return moved / np.linalg.norm(moved)

    eps = 1e-6
    current = residual(direction)
    cost = current @ current
    for _ in range(steps):
        jacobian = np.stack([(residual(turned(direction, eps, 0.0)) - current) / eps,
                             (residual(turned(direction, 0.0, eps)) - current) / eps], axis=1)
        step = np.linalg.lstsq(jacobian, -current, rcond=None)[0]
        trial = turned(direction, *step)
        trial_residual = residual(trial)
        if trial_residual @ trial_residual >= cost:
            break
        direction, current = trial, trial_residual
        cost = current @ current
    return direction, float(cost)


def _light(shown: np.ndarray, shade: np.ndarray, direction: np.ndarray, albedo: np.ndarray,
           name: str, roughness: float) -> MatteLight:
    """One image's light from its (P, c) lit values, their fitted (P,) shading for
    unit intensity and its direction."""
    if not direction[2] >= MIN_ELEVATION_Z:
        raise InputError(f"{name}: the matte sphere's shading gives a light from behind "
                         f"the object (direction {np.round(direction, 3).tolist()})")
    intensity = (shown * shade[:, None]).sum(axis=0) / (shade ** 2).sum()
    residual = np.sqrt(np.mean((shown - shade[:, None] * intensity) ** 2)
                       / np.mean(shown ** 2))
    return MatteLight(direction, np.maximum(intensity / albedo, 1e-12), len(shown),
                      float(residual), roughness)


def matte_table(names, found: list[MatteLight]) -> list[str]:
    """calibrate-lights --matte's table: per image the direction, the intensity
    per band and how Lambertian the sphere looked (relative RMS residual)."""
    lines = [f"{DIRECTION_HEADER} {'px':>6s} {'resid':>6s}  intensity"]
    for name, f in zip(names, found, strict=True):
        lines.append(f"{direction_columns(name, f.direction)} {f.pixels:6d} "
                     f"{f.residual:6.3f}  " + " ".join(f"{v:.4g}" for v in f.intensity))
    roughness = found[0].roughness if found else 0.0
    lines.append("the sphere shaded as Lambertian" if roughness == 0.0 else
                 f"the sphere shaded as rough (Oren-Nayar sigma {roughness:.3f} rad)")
    return lines
