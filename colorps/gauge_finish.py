"""The finish of a photographed gauge, for a scene solved with the gauge's lights.

A gauge is a sphere of known normals, so its images fix its finish
(:class:`~colorps.brdf.BRDF`) without the ambiguity a scene's fit has: on a
scene of estimated normals the diffuse falloff g and the normals' tilt explain
much the same shading, and a fit there can settle where the normals lean
away from the view and the falloff is flatter than the truth. A Mitsuba
plastic pot (a GGX coat of alpha 0.3 on a textured base, direct light, its
gauge of the same finish), solved with the gauge's lights: its fit at the
true normals 0.68 at grazing, at the matched ones 1.14, and the normals 1.01
degrees off (mean and median), leaning away from the view; with the falloff
fitted on the gauge (:func:`gauge_finish`) and held, 0.18 / 0.10.

The lights are a matte sphere's fit
(:func:`colorps.matte_lights.matte_sphere_lights`), which takes up some of a
glossier gauge's falloff and highlight: their intensities are fitted again
under the gauge's finish (0.24 / 0.15 without). On a gauge whose finish is not
Lambert's their directions are too, in turn with the finish, each pixel's
albedo held at the sphere's times the falloff at its view's cosine (a coat lets
light out as it lets it in). Each pixel's albedo free, the directions and the
albedos traded (a Lambertian gauge's correct directions moved 0.1-1.4 degrees);
held uniform, a coat's darkening towards the rim tilted them. Mitsuba's plastic
gauge: 0.29 -> 0.02 degrees (mean), its falloff then within 0.03 of the
renderer's own; a coated test sphere 1.9 -> under 0.1.

:func:`with_gauge_lights` solves a scene with the lights so measured, its
own finish fitted with the gauge's falloff held: for a gauge whose match
explains the scene poorly. This module sits above :mod:`colorps.virtual`.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .brdf import BRDF, DIFFUSE_KNOTS, VISIBLE_PEAK
from .brdf_fit import fit_brdf
from .camera import Camera
from .gauge import DEFAULT_VIRTUAL_RADIUS, Gauge, parse_albedo
from .lights import Lights
from .matte_lights import matte_sphere_lights, refine_direction
from .resolve import Resolved
from .virtual import with_own_finish

__all__ = ["gauge_finish", "with_gauge_lights"]

# ---------------------------------------------------------------- tuning
#: Pixels of the gauge fitted (a fixed random sample of those within its rim
#: margin), as many as a scene's fit takes: Mitsuba's plastic gauge, its falloff
#: within 0.001 of 4,000 pixels' at every knot, in 0.78 s instead of 2.1.
GAUGE_FIT_PIXELS = 1500
#: Rounds of the pixels' albedos and the lights' intensities in turn.
SCALE_ROUNDS = 3
#: A gauge whose fitted falloff departs from Lambert's by this much somewhere,
#: or that shows a highlight (brdf.VISIBLE_PEAK), has its lights' directions
#: fitted again: DIRECTION_ROUNDS rounds, each of up to DIRECTION_STEPS
#: Gauss-Newton steps per light (matte_lights.refine_direction), then the finish
#: again. Mitsuba's plastic gauge: 0.29 -> 0.02 degrees (mean).
SHOWN_FALLOFF = 0.02
DIRECTION_ROUNDS = 3
DIRECTION_STEPS = 3


def gauge_finish(stack, gauge: Gauge, lights: Lights, *, camera: Camera | None = None,
                 clip_level: float | None = None, dark_level: float = 0.0
                 ) -> tuple[BRDF, Lights]:
    """The gauge's finish under ``lights``, at its known normals, and the lights
    measured again under it.

    :func:`colorps.brdf_fit.fit_brdf` on GAUGE_FIT_PIXELS of the pixels within
    its rim margin, each seen along its ray through a lens, the normals held.
    On a finish that departs from Lambert's (SHOWN_FALLOFF, or a highlight) each
    light's direction is fitted again under it, and the finish again under
    them, DIRECTION_ROUNDS times (:func:`_directions_again`). Then each light's
    intensity per band under that finish (a matte fit's take up some of a
    glossier finish), each pixel's albedo free as a match leaves it,
    SCALE_ROUNDS times in turn.

    Parameters
    ----------
    stack : (m, H, W, c) array_like
        Linear gauge images, one per light.
    gauge : Gauge
        Its normals and the pixels within its rim margin (``mask``).
    lights : Lights
        One per image (a matte sphere's fit).
    camera : Camera, optional
        The lens the images were taken through (default orthographic).
    clip_level, dark_level : float, optional
        Measurements at or above ``clip_level``, or at or below ``dark_level``,
        are left out.

    Returns
    -------
    (BRDF, Lights)
        The finish (on a gauge of one albedo a white highlight and a tinted one
        are alike: take only its falloff, roughness and the highlight's shape
        from it), and the lights, their intensities relative to the gauge's
        albedo seen head-on.

    Raises
    ------
    InputError
        Too few usable lit measurements.
    """
    images = np.asarray(stack)
    c = images.shape[-1]
    ys, xs = np.nonzero(gauge.mask)
    if len(ys) > GAUGE_FIT_PIXELS:
        pick = np.sort(np.random.default_rng(0).choice(len(ys), GAUGE_FIT_PIXELS,
                                                       replace=False))
        ys, xs = ys[pick], xs[pick]
    observed = images[:, ys, xs, :].astype(np.float64)
    usable = np.isfinite(observed) & (observed > dark_level)
    if clip_level is not None:
        usable &= observed < clip_level
    views = None if camera is None else -camera.rays(xs, ys, gauge.mask.shape)
    observed = np.where(usable, observed, 0.0)
    normals = gauge.normals[ys, xs].astype(np.float64)
    colours = lights.as_lighting(c).colours[:, 0, :]
    directions = lights.directions
    brdf, _rms = fit_brdf(observed, normals, directions, colours, usable,
                          known_normals=True, views=views)
    if _departs(brdf):  # a matte fit's directions take up some of the finish
        for _ in range(DIRECTION_ROUNDS):
            directions = _directions_again(observed, usable, normals, views, brdf, directions)
            brdf, _rms = fit_brdf(observed, normals, directions, colours, usable,
                                  known_normals=True, views=views)
        lights = Lights(directions, lights.intensities, names=lights.names)
    shading = dataclasses.replace(brdf, white_highlight=False).shade(
        normals, lights.directions, np.ones((len(lights.directions), c)), views)
    usable &= shading > 0.0
    intensity = np.ones((len(shading), c))
    for _ in range(SCALE_ROUNDS):  # each pixel's albedo, then each light's intensity
        albedo = _scale(observed, shading * intensity[:, None, :], usable, axis=0)
        intensity = _scale(observed, shading * albedo[None], usable, axis=1)
    # The sphere's albedo seen head-on: a pixel's, over the share its finish lets
    # out towards the view (see _directions_again).
    albedo /= _exit_share(normals, views, brdf)
    intensity *= np.median(albedo, axis=0) / parse_albedo(gauge.albedo, c)
    return brdf, Lights(lights.directions, intensity, names=lights.names)


def _departs(brdf: BRDF) -> bool:
    """Whether a gauge's finish departs from Lambert's enough to move a matte
    fit's directions (SHOWN_FALLOFF, or a visible highlight)."""
    return brdf.highlight_peak > VISIBLE_PEAK or \
        float(np.abs(np.subtract(brdf.falloff, 1.0)).max()) > SHOWN_FALLOFF


def _directions_again(observed, usable, normals, views, brdf: BRDF,
                      directions: np.ndarray) -> np.ndarray:
    """Each light's direction refitted under the gauge's finish (up to DIRECTION_STEPS
    Gauss-Newton steps on two tangent angles). The sphere has one albedo, but a
    finish darker towards grazing light is darker towards grazing view too
    (reciprocity: a coat lets light out as it lets it in), so each pixel's
    albedo is held at the falloff at its view's cosine; each light's intensity
    per band is fitted with it. (Each pixel's albedo free, the directions and
    the albedos trade; held uniform, the darker rim tilts the lights.)"""
    tinted = dataclasses.replace(brdf, white_highlight=False)
    exit_share = _exit_share(normals, views, brdf)
    strength = tinted.bands(observed.shape[2])

    def residual(k, light):
        diffuse, lobe = tinted.parts(normals, light[None], views)
        unit = diffuse[0][:, None] * exit_share
        if lobe is not None:
            unit = unit + lobe[0][:, None] * strength
        scale = _scale(observed[k], unit, usable[k], axis=0)
        return np.where(usable[k], observed[k] - unit * scale, 0.0).ravel()

    return np.array([refine_direction(lambda light, k=k: residual(k, light),
                                      np.asarray(light, dtype=np.float64), DIRECTION_STEPS)[0]
                     for k, light in enumerate(directions)])


def _exit_share(normals, views, brdf: BRDF) -> np.ndarray:
    """(N, 1) the share of light a finish lets out towards the view, relative to
    head-on: its falloff at the cosine of the view (reciprocity)."""
    cos_view = normals[:, 2] if views is None else np.einsum("ij,ij->i", normals, views)
    return np.interp(cos_view, DIFFUSE_KNOTS, brdf.falloff)[:, None]


def _scale(observed, model, usable, axis: int) -> np.ndarray:
    """The least-squares factor of ``model`` to ``observed`` over ``axis``."""
    model = np.where(usable, model, 0.0)
    return (model * observed).sum(axis=axis) / np.maximum((model ** 2).sum(axis=axis), 1e-30)


def with_gauge_lights(scene: np.ndarray, gauge_stack: np.ndarray, gauge: Gauge,
                      run: Resolved, *, mask=None, radius: float = DEFAULT_VIRTUAL_RADIUS,
                      camera: Camera | None = None, progress: bool = False, wanted=None):
    """The scene solved with a virtual gauge under the lights measured on the gauge
    and of the scene's own fitted finish: for a gauge whose match explains the
    scene poorly (a finish not the scene's, or a white highlight on a coloured
    scene, which no grey gauge's signatures hold). The lights are a matte
    sphere's fit (:func:`colorps.matte_lights.matte_sphere_lights`, intensities
    relative to its albedo), their intensities fitted again under the gauge's own
    finish, whose diffuse falloff the scene's fit holds (:func:`gauge_finish`).
    Through a lens (``camera``: scene and gauge photographed with it) the
    sphere's normals come from the true rays, and a finish that depends on the
    view has the scene matched again along each pixel's ray
    (:func:`colorps.virtual.view_corrected`, which changes ``scene`` in place).
    Returns (the :class:`~colorps.Reconstruction`, its settings, (the finish,
    its fits), the lights, the gauge's finish); the Reconstruction and its
    settings are None when ``wanted`` (a predicate of the scene's fitted finish
    and the gauge's) says so (:func:`colorps.virtual.with_own_finish`)."""
    lights, _ = matte_sphere_lights(gauge_stack, gauge.sphere, albedo=gauge.albedo,
                                    clip_level=run.gauge_levels[0], camera=camera)
    own, lights = gauge_finish(gauge_stack, gauge, lights, camera=camera,
                               clip_level=run.gauge_levels[0],
                               dark_level=run.options.dark_level)
    return (*with_own_finish(scene, lights, run, mask=mask, radius=radius, camera=camera,
                             progress=progress, held_finish=own,
                             wanted=None if wanted is None else lambda brdf: wanted(brdf, own)),
            lights, own)
