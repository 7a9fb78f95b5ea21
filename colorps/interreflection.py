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
subtracts it from the scene and solves again, up to :data:`PASSES` times, each with
the shape of the pass before. The observed radiance already holds every further
bounce, so one subtraction removes them all, up to the shape's errors.

The albedo's absolute scale is the gauge's stated albedo, which users often
leave at 1: the bounced light's scale is fitted instead (:func:`bounce_scale`),
on the measurements in attached shadow (the light is behind the surface, as the
gauge at the same normal shows), where the scene shows the bounced light alone;
without them it is not guessed, and the bounced light stays in. A pass is kept
only when the gauge explains the scene without it better
(:func:`_explains_better`): a glossy finish's highlights are not light a matte
surface sends its neighbours.
"""

from __future__ import annotations

import sys
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from colorps._config import MIN_LIGHTS
from colorps.attached_shadows import attached_shadows, bounce_scale
from colorps.bounce import (
    BounceGrid,
    CellGrid,
    at_pixels,
    bounced_light,
    cell_grid,
    gather,
    light_at,
)
from colorps.errors import InterreflectionWarning
from colorps.gauge import Gauge
from colorps.geometry import angular_error
from colorps.integrate import integrate

__all__ = ["SceneSample", "attached_shadows", "bounce_grid", "bounce_scale", "left_in",
           "moved_by", "relief_cells", "sees_itself", "with_bounce_left_in",
           "with_scale_uncertainty", "without_interreflections"]

#: Cells (at most) of the grid the bounce is gathered on: 4096 costs 0.3 s for
#: 32 RGB images on 2 cores, and the bounced light is smooth at that scale.
BOUNCE_CELLS = 4096
#: Solves with the bounced light taken out, each from the shape of the one
#: before (deep folds, 200 px, 32 lights: 5.0 degrees mean; after two passes
#: 0.48, after three 0.38).
PASSES = 3
#: Passes when the shape to start from is already a corrected one's (the
#: scene's own finish after another finish's gauge, :mod:`colorps.pipeline`):
#: folds of a rough scene on a Lambertian gauge, 300 px under 48 lights, went
#: 1.26 -> 0.38 degrees after one, 0.36 after three, for 14 s more.
PASSES_AGAIN = 1
#: A cell sees itself when the object fills at least this share of its view
#: (form factor; a white surface would add that share of light): below it the
#: error the bounced light causes is within the noise's.
MIN_SHARE = 0.02
#: The object is solved again when at least this share of its cells do.
MIN_LIT_CELLS = 0.005
#: A pass is kept when the gauge explains its measurements at least this much
#: better (median residual, on the pixels the bounced light reaches) than the
#: uncorrected solve's. Taking out physical bounced light does it by far (deep
#: folds: 2.2 -> 1.05 noise units, with a Lambertian gauge for a rough scene 2.7
#: -> 1.9; Mitsuba's matte pot 3.7 -> 2.9); a correction that only nudges the
#: residual may be fitting something else (a varnished scene without bounced
#: light, 1.08 -> 1.06, went 0.64 -> 1.33 degrees). Glossy folds without
#: bounced light, whose clipped noise the scale's fit took for it before it
#: fitted a dark level, went 1.82 -> 1.71 and 0.24 -> 0.97 degrees median; now
#: they stop before the probe. Mitsuba's plastic pot, whose coat leaves more
#: misfit than the bounced light does, needs this bar in virtual mode: 0.897
#: (32 lights) and 0.907 (96: 2.14 -> 1.32 degrees mean when taken out).
BETTER_BY = 0.95
#: ... and more of those pixels explained better than worse by this many standard
#: deviations of a fair coin's count: a lower median alone can happen by chance
#: on a small capture (a 48 px smiley without bounced light: 0.611 -> 0.598).
SIGN_TEST_SDS = 3.0
#: Pixels the first pass is tried on (of those the bounced light reaches) before
#: the whole scene is solved again: 20,000 take a third of a 1 MP solve's time,
#: and their median residual is within 1 % of the whole's.
PROBE_PIXELS = 20_000
#: The scale the attached shadows give (:func:`bounce_scale`) is tried on the
#: probe times SCALE_STEP to the powers -2 to 2, from 1 downhill in the probe's
#: residual (:func:`_downhill`), and the one the gauge explains best kept for
#: every pass. The gathered light is a little short in the deepest shadows and
#: in narrow grooves (a grid of :data:`BOUNCE_CELLS` cells), so the fit runs
#: high by up to a third (Mitsuba's matte pot under 96 lights: 1.35 on the first
#: shape for a 1.15 that takes the bounced light out best): chosen so, 0.8 times
#: it, 0.39 / 0.21 degrees mean / median; 1 times it, 0.43 / 0.29. A coarser
#: step (0.63, 1, 1.2) chose 1 there.
SCALE_STEP = 1.25
SCALE_FACTORS = tuple(SCALE_STEP ** k for k in range(-2, 3))
#: Relative uncertainty of the scale kept: about half the step between
#: :data:`SCALE_FACTORS` about 1. A normal the bounced light moved by an angle is
#: uncertain by this share of it, added to its 68 % radius (deep folds: 42 % of
#: the errors within the radius without it, 80 % with it; their ranking,
#: Spearman 0.50 -> 0.62).
SCALE_UNCERTAINTY = 0.1
#: The bounced light is first looked for on every SAMPLE_EVERY-th row and column
#: of the scene (:class:`SceneSample`, a sixteenth of it, kept from its first
#: read): when even SAMPLE_MARGIN times the scale fitted there reaches too few
#: cells to matter, the scene is not read again (a 4 MP capture: 0.7 s less).
#: Any other outcome reads it and looks again on all of it, as without a sample.
#: A margin of 2 is far wider than the sample's error: the scale is fitted on as
#: many pixels either way (:data:`colorps.attached_shadows.SCALE_PIXELS`), and a
#: cell's mean radiance on at least 2 x 2 of its pixels (or the sample is not used).
SAMPLE_EVERY = 4
SAMPLE_MARGIN = 2.0


@dataclass(frozen=True)
class SceneSample:
    """Every :data:`SAMPLE_EVERY`-th row and column of a scene stack, from the
    first (``values``, (m, h, w, c) float32), kept from its first read for
    :func:`without_interreflections`' first look."""

    values: np.ndarray

    @property
    def every(self) -> int:
        return SAMPLE_EVERY

    @classmethod
    def of(cls, scene: np.ndarray) -> SceneSample:
        return cls(np.array(scene[:, ::SAMPLE_EVERY, ::SAMPLE_EVERY], dtype=np.float32))


def bounce_grid(scene: np.ndarray, normals: np.ndarray, solved: np.ndarray,
                albedo: np.ndarray, *, cells: int = BOUNCE_CELLS, every: int = 1,
                relief: tuple[CellGrid, np.ndarray] | None = None) -> BounceGrid:
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
    every : int, optional
        ``scene`` holds every ``every``-th row and column of the image (a
        :class:`SceneSample`'s values): each cell's radiance is the mean of its
        sampled pixels.
    relief : (CellGrid, ndarray), optional
        :func:`relief_cells` of ``normals`` and ``solved`` at ``cells``, made before.
    """
    grid, height = relief_cells(normals, solved, cells) if relief is None else relief
    return gather(grid, height, scene, solved, albedo, every=every)


def relief_cells(normals: np.ndarray, solved: np.ndarray, cells: int = BOUNCE_CELLS
                 ) -> tuple[CellGrid, np.ndarray]:
    """The solved object's :func:`colorps.bounce.cell_grid` of at most ``cells``
    cells, and its relief (in cells) integrated from their mean normals."""
    grid = cell_grid(normals, solved, cells)
    height = np.zeros(grid.valid.shape)
    if grid.valid.any():
        height = np.nan_to_num(integrate(np.where(grid.valid[..., None], grid.normals, np.nan),
                                         grid.valid))
    return grid, height


def sees_itself(normals: np.ndarray, solved: np.ndarray, *, cells: int = BOUNCE_CELLS,
                relief: tuple[CellGrid, np.ndarray] | None = None) -> float:
    """Share of an object's cells whose view is at least :data:`MIN_SHARE` filled
    by the object itself (its form factor to itself): 0 for a convex one.

    From the shape alone (``normals`` where ``solved``; ``relief``, optional:
    their :func:`relief_cells`), before any image is read again.
    """
    ones = np.ones((1, *solved.shape, 1), dtype=np.float32)
    grid = bounce_grid(ones, normals, solved, np.ones((*solved.shape, 1)), cells=cells,
                       relief=relief)
    return float(np.mean(grid.share[grid.valid] >= MIN_SHARE)) if grid.valid.any() else 0.0


def left_in(result, why: str, advice: str) -> dict:
    """report.json's record of a run that cannot take the bounced light out
    (``why``), with a warning (and ``advice``) when the solved object sees itself."""
    share = sees_itself(result.normals, result.solved)
    if share >= MIN_LIT_CELLS:
        warnings.warn(f"{share:.0%} of the object sees itself, but {why} leaves the light it "
                      "bounces onto itself in: normals in its folds may lean towards the walls "
                      f"that light them, and uncertainty.exr counts how far{advice}",
                      InterreflectionWarning, stacklevel=3)
    return dict(skipped=why, sees_itself=share)


def without_interreflections(read_scene: Callable[[], np.ndarray], first,
                             solve: Callable, gauge: Gauge, gauge_stack: np.ndarray, *,
                             passes: int = PASSES, cells: int = BOUNCE_CELLS,
                             solved_as_read: bool = True, sample: SceneSample | None = None,
                             progress: bool = False):
    """Solve a scene again without the light its own surfaces bounce.

    Parameters
    ----------
    read_scene : callable
        ``read_scene() -> (m, H, W, c) ndarray``, the linear measurements
        solved into ``first``; called only when the object sees itself.
    first : Reconstruction
        The solve with the bounced light in.
    solve : callable
        ``solve(stack, pixels, model_scale) -> Reconstruction``, the run's
        solve of another stack, on the (H, W) bool mask ``pixels`` (None: the
        run's own) at that model scale (None: its own measured; a sample of
        the pixels is solved at ``first``'s, which the whole measured).
    gauge : Gauge
    gauge_stack : (m, Hg, Wg, c) ndarray
        The gauge ``first`` was solved with and its images (what each light
        gives each normal: :func:`attached_shadows`).
    passes : int, optional
        Solves without the bounced light, each from the shape of the one before.
    cells : int, optional
        See :func:`bounce_grid`.
    solved_as_read : bool, optional
        Whether ``first`` was solved from the measurements as read. False:
        ``first`` is only the shape to start from (solved from measurements
        whose bounced light another gauge's solve took out), and a pass is
        kept when it explains the probe better than ``solve`` does the
        measurements as read (solved on the probe alone).
    sample : SceneSample, optional
        Of the measurements ``first`` was solved from: looked at first
        (:data:`SAMPLE_MARGIN`); ``read_scene`` is then called only when it
        shows enough bounced light to matter.
    progress : bool, optional
        Say on stderr what is done (the object sees itself, each pass, why the
        bounced light stays in).

    Returns
    -------
    result : Reconstruction
        ``first`` when under :data:`MIN_LIT_CELLS` of the object sees itself
        (:func:`sees_itself`) or no pass is kept; else the last pass kept, its
        uncertainty widened by :data:`SCALE_UNCERTAINTY` of how far each
        normal moved.
    corrected : ndarray or None
        The measurements the result was solved from, the bounced light taken
        out (None: ``first``'s).
    record : dict
        ``sees_itself`` (:func:`sees_itself` of ``first``); ``residuals``:
        the median residual (noise units) over the probe (:func:`_probe`: up
        to :data:`PROBE_PIXELS` pixels the first estimate's bounced light
        reaches with :data:`MIN_SHARE` of their measurements) of ``first``,
        of the first pass tried on the probe alone, then of each whole pass;
        ``passes`` kept, each explaining the probe better than ``first``
        (:func:`_explains_better`) and than the pass before (the shadows' fit,
        refitted on each pass's shape, can drift: Mitsuba's matte pot under 96
        lights went 0.40 degrees median after one pass, 0.48 after three, its
        residuals 3.01, 3.05, 3.04); of the last kept, ``scale``
        (:func:`bounce_scale`) and ``bounced_share``, the median share of
        bounced light in the cells so reached; ``stopped``: why no further pass
        was kept (None: all were), at the first not explained better (the
        passes end there: the next would start from its shape), or before
        any solve when the scale cannot be fitted (no attached shadows: the bounced
        light is not guessed) or at it under :data:`MIN_LIT_CELLS` of the cells
        are so reached; ``fitted_scale``, when no pass was kept after the scale
        was fitted (for :func:`with_bounce_left_in`); ``sampled``, when only
        ``sample`` was looked at (its :attr:`SceneSample.every`).
    """
    relief = relief_cells(first.normals, first.solved, cells)  # (first's, for each look)
    record = dict(sees_itself=sees_itself(first.normals, first.solved, relief=relief),
                  passes=0, scale=None, bounced_share=None, residuals=[], stopped=None)
    if record["sees_itself"] < MIN_LIT_CELLS:
        return first, None, record
    say = _say if progress else (lambda message: None)
    say(f"{record['sees_itself']:.0%} of the object sees itself: estimating the light it "
        "bounces onto itself")
    in_shadow = attached_shadows(gauge, gauge_stack)
    scale = None if sample is None else _too_little_in(sample, first, in_shadow, relief)
    if scale is not None:
        record.update(stopped=_TOO_LITTLE, fitted_scale=scale, sampled=sample.every)
        say(f"the bounced light stays in: {_TOO_LITTLE} (on a sample of the pixels)")
        return first, None, record
    scene, result, corrected, probe, factor = read_scene(), first, None, None, 1.0
    for index in range(passes):
        grid = bounce_grid(scene, result.normals, result.solved, result.albedo, cells=cells,
                           relief=relief if result is first else None)
        scale = bounce_scale(scene, grid, result, in_shadow)
        if scale is None:
            record["stopped"] = _NO_SHADOWS
            break
        reached, enough = _reached(grid, scale)
        if not enough:
            record["stopped"] = _TOO_LITTLE
            break
        if probe is None:  # tried first on a sample of the pixels it reaches
            probe = _probe(reached, grid.step, first.solved)
            before = first if solved_as_read else solve(scene, probe, first.stats.model_scale)
            factor, tried = _downhill(
                _without_at(scene, grid, scale, result.albedo, probe),
                lambda stack, at=probe: solve(stack, at, first.stats.model_scale),
                lambda solved, at=probe: _residual(solved, at))
            record["residuals"] = [_residual(before, probe), _residual(tried, probe)]
            if not _explains_better(tried, before, probe):  # (a glossy finish's
                record["stopped"] = "the gauge explains it no better"  # highlights)
                break
        scale *= factor
        say(f"solving again without it (pass {index + 1} of up to {passes}, its scale "
            f"{scale:.2f})")
        light = bounced_light(grid, result.albedo, scene.shape[1:3])
        light *= scale
        attempt = _taken_out(scene, light)  # (in place: one stack less)
        solved = solve(attempt, None, None)
        record["residuals"].append(_residual(solved, probe))
        if not _explains_better(solved, before, probe):
            record["stopped"] = "the gauge explains it no better"
            break
        if corrected is not None and record["residuals"][-1] >= record["residuals"][-2]:
            record["stopped"] = _WORSE_THAN_BEFORE  # (the next would start from it)
            say(f"pass {index + 1} explains it no better than pass {index}: pass {index} kept")
            break
        result, corrected = solved, attempt
        record.update(passes=index + 1, scale=scale, bounced_share=float(
            np.median(scale * grid.share[reached])))
    if record["stopped"] and not record["passes"]:
        say(f"the bounced light stays in: {record['stopped']}")
        if scale is not None:
            record["fitted_scale"] = scale
    return (result if corrected is None else
            with_scale_uncertainty(result, moved_by(result, first))), \
        corrected, record


def with_bounce_left_in(result, record: dict, *, cells: int = BOUNCE_CELLS):
    """``result`` with its 68 % radii widened by the bounced light left in its
    measurements, when ``record`` (:func:`without_interreflections`' or
    :func:`left_in`'s) says no pass took it out.

    A matte pixel whose measurements hold a share s of light bounced from walls
    of normal n_w shades like the normal n + s n_w (up to its length): its normal
    leans towards the walls by up to arcsin(s) (when they face it at 90 +
    arcsin(s) degrees), an error its match cannot see, the sum being one more
    shading. That angle is added to each radius in quadrature
    (:meth:`colorps.Reconstruction.with_uncertainty_added`), s estimated from the
    solved shape and albedo alone (:func:`_lit_alike`: every wall lit as the
    pixel it lights), times the bounced light's scale where it was fitted
    (``record``'s ``fitted_scale``, :func:`bounce_scale`; else the albedo's
    stated scale). Mitsuba's pot under 32 lights solved with the bounced light
    in, with `--camera`: matte 22 -> 78 % of the errors within the radius, plastic
    32 -> 80 %.
    ``record`` gets ``left_in_share``, the median s over the solved pixels
    (none when the object does not see itself: ``sees_itself`` under
    :data:`MIN_LIT_CELLS`).
    """
    if record.get("passes") or record.get("sees_itself", 1.0) < MIN_LIT_CELLS or \
            not result.solved.any():
        return result
    scale = record.get("fitted_scale", 1.0)
    if scale <= 0.0:  # the shadows show none
        record["left_in_share"] = 0.0
        return result
    grid = _lit_alike(result, cells)
    share = np.clip(scale * at_pixels(grid, grid.share, result.solved.shape), 0.0, 1.0)
    share[~result.solved] = 0.0
    record["left_in_share"] = float(np.median(share[result.solved]))
    return result.with_uncertainty_added(np.degrees(np.arcsin(share)))


def _lit_alike(result, cells: int) -> BounceGrid:
    """The light ``result``'s solved object bounces onto itself were every wall lit
    as brightly as the pixel it lights: its radiance is its albedo (the bounced
    share of a band then the sum over the walls of their albedo times their form
    factor, whatever the lights)."""
    albedo = np.nan_to_num(result.albedo).astype(np.float32)
    return bounce_grid(albedo[None], result.normals, result.solved, albedo, cells=cells)


def _say(message: str) -> None:
    """One line of progress on stderr."""
    print(f"bounced light: {message}", file=sys.stderr)


def moved_by(result, first) -> np.ndarray:
    """(H, W) float32 angle (degrees) between ``result``'s normals and
    ``first``'s where both are solved, 0 elsewhere: how far taking the bounced
    light out moved each."""
    moved = np.zeros(result.solved.shape, dtype=np.float32)
    both = result.solved & first.solved
    moved[both] = angular_error(result.normals[both], first.normals[both])
    return moved


def with_scale_uncertainty(result, moved: np.ndarray):
    """``result`` with its 68 % radius widened by what the bounced light's scale
    leaves open: :data:`SCALE_UNCERTAINTY` of how far taking it out moved each
    normal (``moved``, degrees: :func:`moved_by`), added in quadrature. For a
    result solved again from the corrected measurements (a finish fitted again),
    ``moved`` is the correction's own."""
    return result.with_uncertainty_added(SCALE_UNCERTAINTY * moved)


_NO_SHADOWS = "too few measurements in attached shadow to fit its scale"
_TOO_LITTLE = "the shadows show too little bounced light to matter"
_WORSE_THAN_BEFORE = "the gauge explains it no better than after the pass before"


def _too_little_in(sample: SceneSample, first, in_shadow: Callable,
                   relief: tuple[CellGrid, np.ndarray]) -> float | None:
    """The bounced light's scale fitted on ``sample`` when even :data:`SAMPLE_MARGIN`
    times it reaches under :data:`MIN_LIT_CELLS` of the cells of ``relief``
    (``first``'s :func:`relief_cells`); else None (as when the cells are under 2 x 2
    of the sample's pixels, or the scale cannot be fitted)."""
    if relief[0].step < 2 * sample.every:
        return None
    grid = bounce_grid(sample.values, first.normals, first.solved, first.albedo,
                       every=sample.every, relief=relief)
    scale = bounce_scale(sample.values, grid, first, in_shadow, every=sample.every)
    if scale is None or _reached(grid, SAMPLE_MARGIN * scale)[1]:
        return None
    return scale


def _reached(grid: BounceGrid, scale: float) -> tuple[np.ndarray, bool]:
    """The valid cells of ``grid`` whose bounced light at ``scale`` is at least
    :data:`MIN_SHARE` of their measurements, and whether they are at least
    :data:`MIN_LIT_CELLS` of the valid ones (enough to matter)."""
    reached = grid.valid & (scale * grid.share >= MIN_SHARE)
    return reached, bool(reached.sum() >= MIN_LIT_CELLS * grid.valid.sum())


def _without_at(scene: np.ndarray, grid: BounceGrid, scale: float, albedo: np.ndarray,
                pixels: np.ndarray):
    """``without(factor)``: ``scene`` with that factor times ``scale`` times the
    bounced light taken out at ``pixels`` ((H, W) bool) alone; one copy of
    ``scene``, its probed pixels rewritten at each call (use each before the next)."""
    ys, xs = np.nonzero(pixels)
    seen, light = scene[:, ys, xs], scale * light_at(grid, albedo, ys, xs)
    out = scene.copy()

    def without(factor: float) -> np.ndarray:
        out[:, ys, xs] = _taken_out(seen, factor * light)
        return out

    return without


def _taken_out(seen: np.ndarray, light: np.ndarray) -> np.ndarray:
    """``seen`` less the bounced ``light`` (both (m, ..., c); into ``light``),
    at least 0; as seen where that would leave fewer than MIN_LIGHTS lights
    lit that had light.

    A pixel deep in a fold is lit mostly by bounced light, and a little too
    much of it, from a neighbour's albedo or normal a little off, took every
    light out of it (7 pixels of the bounced folds of
    ``tests/test_interreflection.py``, which came out too dark to solve).
    """
    np.subtract(seen, light, out=light)
    np.maximum(light, 0.0, out=light)
    emptied = ((light > 0).any(axis=-1).sum(axis=0) < MIN_LIGHTS) & \
        ((seen > 0).any(axis=-1).sum(axis=0) >= MIN_LIGHTS)
    light[:, emptied] = seen[:, emptied]
    return light


def _downhill(without: Callable, solve: Callable, residual: Callable) -> tuple[float, object]:
    """The probe solved at the least-residual of :data:`SCALE_FACTORS`
    (``solve(without(factor))``), found from 1 downhill in ``residual``: each
    factor's neighbours are tried, and the walk moves to the lower while it is
    lower than where it is (the residual falls, then rises, about the scale that
    fits: 3 or 4 solves of the 5). Returns that factor and its solve."""
    tries, costs = {}, {}

    def cost(k: int) -> float:
        if k not in costs:
            tries[k] = solve(without(SCALE_FACTORS[k]))
            costs[k] = residual(tries[k])
        return costs[k]

    here = SCALE_FACTORS.index(1.0)
    while True:
        nearest = min((k for k in (here - 1, here + 1) if 0 <= k < len(SCALE_FACTORS)),
                      key=cost)
        if not cost(nearest) < cost(here):
            return SCALE_FACTORS[here], tries[here]
        here = nearest


def _probe(reached: np.ndarray, step: int, solved: np.ndarray) -> np.ndarray:
    """Up to :data:`PROBE_PIXELS` solved pixels of the cells in ``reached``
    (a fixed draw), as an (H, W) bool mask."""
    h, w = solved.shape
    inside = solved & np.repeat(np.repeat(reached, step, axis=0), step, axis=1)[:h, :w]
    ys, xs = np.nonzero(inside)
    if ys.size > PROBE_PIXELS:
        keep = np.random.default_rng(0).choice(ys.size, PROBE_PIXELS, replace=False)
        ys, xs = ys[keep], xs[keep]
    out = np.zeros_like(solved)
    out[ys, xs] = True
    return out


def _explains_better(after, before, pixels: np.ndarray) -> bool:
    """Whether the gauge explains ``after``'s measurements of ``pixels`` better
    than ``before``'s: on the pixels both solved, a median residual at most
    :data:`BETTER_BY` times theirs, and more pixels better than worse by
    :data:`SIGN_TEST_SDS` standard deviations of a fair coin's count."""
    both = pixels & after.solved & before.solved
    now = after.quality[both] * after.stats.model_scale
    then = before.quality[both] * before.stats.model_scale
    better, worse = int(np.sum(now < then)), int(np.sum(now > then))
    return bool(both.any()) and float(np.median(now)) <= BETTER_BY * float(np.median(then)) \
        and better - worse > SIGN_TEST_SDS * np.sqrt(better + worse)


def _residual(result, pixels: np.ndarray) -> float:
    """Median residual (noise units, before the model scale) of ``result`` over
    the ``pixels`` it solved; inf when it solved none of them."""
    solved = pixels & result.solved
    if not solved.any():
        return float("inf")
    return float(np.median(result.quality[solved]) * result.stats.model_scale)
