"""Light bounced between an object's own surfaces, estimated and taken out.

A concave object lights itself: a pixel in a fold receives, besides each
light, what the fold's other walls reflect. A gauge sphere, convex, has none
of it, so the fold's pixels match the wrong gauge normal (tilted towards the
walls that light them) while matching well: for a Lambertian surface the
bounced light is nearly a shading of another normal, and their sum is one more
such shading. Measured on deep folds under 32 lights with a physical one-bounce
(:func:`colorps.synth.render`), it costs 5 degrees mean.

The observed images themselves say how much light leaves every surface patch,
towards every direction alike for a matte finish (Nayar, Ikeuchi and Kanade,
"Shape from interreflections", 1991), so the light a pixel receives from the
rest of the object follows from the shape alone: the sum over the patches q
it sees of ``L_q cos(theta_p) cos(theta_q) A_q / (pi r^2)``, times the pixel's
albedo. :func:`bounce_grid` gathers it (:mod:`colorps.bounce`) on a grid of at
most :data:`BOUNCE_CELLS` cells, the relief integrated from the solved normals,
and :func:`without_interreflections`
subtracts it from the scene and solves again, :data:`PASSES` times, each with
the shape of the pass before. The observed radiance already holds every further
bounce, so one subtraction removes them all, up to the shape's errors.

The albedo's absolute scale is the gauge's stated albedo, which users often
leave at 1: the bounced light's scale is fitted instead (:func:`bounce_scale`),
on the measurements each pass left out as cast shadows, where the scene shows
the bounced light alone.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from colorps import light_masks
from colorps.bounce import BounceGrid, bounced_light, cell_grid, gather
from colorps.integrate import integrate

__all__ = ["bounce_grid", "bounce_scale", "sees_itself", "without_interreflections"]

#: Cells (at most) of the grid the bounce is gathered on: 4096 costs 0.3 s for
#: 32 RGB images on 2 cores, and the bounced light is smooth at that scale.
BOUNCE_CELLS = 4096
#: Solves with the bounced light taken out, each from the shape of the one
#: before (deep folds, 200 px, 32 lights: 5.0 degrees mean; after two passes
#: 0.48, after three 0.38).
PASSES = 3
#: A cell sees itself when the object fills at least this share of its view
#: (form factor; a white surface would add that share of light): below it the
#: error the bounced light causes is within the noise's.
MIN_SHARE = 0.02
#: The object is solved again when at least this share of its cells do.
MIN_LIT_CELLS = 0.005
#: A pass is kept when the gauge explains its measurements at least this much
#: better (median residual) than the uncorrected solve's: the bounced light taken out
#: makes a matte scene more like the gauge (deep folds: residual 1.52 -> 1.01 ->
#: 0.94 noise units), a glossy one's highlights taken as light sent to its
#: neighbours less (varnished folds: 1.12 -> 1.28, 0.74 -> 5.6 degrees).
BETTER_BY = 0.98
#: Shadowed measurements (with some bounced light) needed to fit the scale;
#: fewer, and the gauge's stated albedo is taken as absolute.
MIN_SHADOWED = 200


def bounce_grid(scene: np.ndarray, normals: np.ndarray, solved: np.ndarray,
                albedo: np.ndarray, *, cells: int = BOUNCE_CELLS) -> BounceGrid:
    """The light the solved object sends itself, its relief integrated from its normals.

    :func:`colorps.bounce.gather` on a :func:`colorps.bounce.cell_grid`, the
    relief integrated from the cells' mean normals (orthographic).

    Parameters
    ----------
    scene : (m, H, W, c) ndarray
        Linear measurements.
    normals : (H, W, 3) ndarray
        Unit normals (x right, y up, z towards the camera), used where ``solved``.
    solved : (H, W) ndarray of bool
    albedo : (H, W, c) ndarray
        Each pixel's albedo (relative to the gauge's stated one).
    cells : int, optional
        Cells of the grid, at most.
    """
    grid = cell_grid(normals, solved, cells)
    height = np.zeros(grid.valid.shape)
    if grid.valid.any():
        height = np.nan_to_num(integrate(np.where(grid.valid[..., None], grid.normals, np.nan),
                                         grid.valid))
    return gather(grid, height, scene, solved, albedo)


def bounce_scale(scene: np.ndarray, bounced: np.ndarray, dropped_lights: np.ndarray,
                 solved: np.ndarray, albedo: np.ndarray) -> float | None:
    """The factor the bounced light is off by: the albedo's unknown absolute scale.

    Fitted by least squares, ``scene = scale * bounced``, on the measurements a
    solve left out of its match that are darker than the pixel's median (cast
    shadows: the bounced light alone reaches them; the highlights it also
    leaves out are brighter), and capped where the median albedo would
    reflect all the light it gets (a few pixels' albedo, from few lights, can
    be far off). None when fewer than
    :data:`MIN_SHADOWED` such measurements hold bounced light.
    """
    m = scene.shape[0]
    brightness = scene.sum(axis=3)
    darker = brightness < np.median(brightness, axis=0)[None]  # (not a highlight's)
    shadowed = np.moveaxis(light_masks.to_bool(dropped_lights, m), -1, 0) & darker & solved[None]
    seen, gathered = scene[shadowed], bounced[shadowed]
    holding = gathered > 0
    if holding.sum() < MIN_SHADOWED:
        return None
    scale = float((seen * gathered).sum() / (gathered * gathered).sum())
    typical = float(np.nanmedian(albedo[solved])) if solved.any() else 0.0
    return float(np.clip(scale, 0.0, 1.0 / typical if typical > 0 else np.inf))


def sees_itself(normals: np.ndarray, solved: np.ndarray, *, cells: int = BOUNCE_CELLS
                ) -> float:
    """Share of an object's cells whose view is at least :data:`MIN_SHARE` filled
    by the object itself (its form factor to itself): 0 for a convex one.

    From the shape alone (``normals`` where ``solved``), before any image is read
    again.
    """
    ones = np.ones((1, *solved.shape, 1), dtype=np.float32)
    grid = bounce_grid(ones, normals, solved, np.ones((*solved.shape, 1)), cells=cells)
    return float(np.mean(grid.share[grid.valid] >= MIN_SHARE)) if grid.valid.any() else 0.0


def without_interreflections(read_scene: Callable[[], np.ndarray], first,
                             solve: Callable, *, passes: int = PASSES,
                             cells: int = BOUNCE_CELLS):
    """Solve a scene again without the light its own surfaces bounce.

    Parameters
    ----------
    read_scene : callable
        ``read_scene() -> (m, H, W, c) ndarray``, the linear measurements
        solved into ``first``; called only when the object sees itself.
    first : Reconstruction
        The solve with the bounced light in.
    solve : callable
        ``solve(stack) -> Reconstruction``, the run's solve of another stack.
    passes : int, optional
        Solves without the bounced light, each from the shape of the one before.
    cells : int, optional
        See :func:`bounce_grid`.

    Returns
    -------
    result : Reconstruction
        ``first`` when under :data:`MIN_LIT_CELLS` of the object sees itself
        (:func:`sees_itself`).
    corrected : ndarray or None
        The measurements the result was solved from, the bounced light taken
        out (None: ``first``'s).
    record : dict
        ``sees_itself`` (:func:`sees_itself` of ``first``); ``residuals``
        (median, noise units) of ``first`` and of each pass tried; ``passes``
        kept, each when :func:`_explains_better` than ``first`` (the
        passes stop at the first not kept, or when at the fitted scale under
        :data:`MIN_LIT_CELLS` of the cells get :data:`MIN_SHARE` of bounced
        light); of the last kept, ``scale`` (:func:`bounce_scale`; None: the
        gauge's albedo taken as absolute) and ``bounced_share``, the median
        share of bounced light in the cells it reaches so.
    """
    record = dict(sees_itself=sees_itself(first.normals, first.solved, cells=cells),
                  passes=0, scale=None, bounced_share=None,
                  residuals=[first.stats.residual_median_noise_units])
    if record["sees_itself"] < MIN_LIT_CELLS:
        return first, None, record
    scene, result, corrected = read_scene(), first, None
    for index in range(passes):
        grid = bounce_grid(scene, result.normals, result.solved, result.albedo, cells=cells)
        light = bounced_light(grid, result.albedo, scene.shape[1:3])
        scale = bounce_scale(scene, light, result.dropped_lights, result.solved, result.albedo)
        light *= 1.0 if scale is None else scale
        share = grid.share * (1.0 if scale is None else scale)
        reached = grid.valid & (share >= MIN_SHARE)
        if reached.sum() < MIN_LIT_CELLS * grid.valid.sum():
            break  # the shadows show too little bounced light to matter
        attempt = np.maximum(scene - light, 0.0, out=light)  # (in place: one stack less)
        solved = solve(attempt)
        record["residuals"].append(solved.stats.residual_median_noise_units)
        if not _explains_better(solved, first):
            break  # (a glossy finish: its highlights are not a matte surface's light)
        result, corrected = solved, attempt
        record.update(passes=index + 1, scale=scale, bounced_share=float(
            np.median(share[reached])))
    return result, corrected, record


def _explains_better(solved, before) -> bool:
    """Whether the gauge explains ``solved``'s measurements better than
    ``before``'s: its median residual (noise units) at most :data:`BETTER_BY`
    times theirs."""
    now = solved.stats.residual_median_noise_units
    then = before.stats.residual_median_noise_units
    return now is not None and (then is None or now <= BETTER_BY * then)
