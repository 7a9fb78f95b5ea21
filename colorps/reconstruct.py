"""Scene stack + gauge stack -> normals, per-band albedo and match quality.

For each scene pixel p the gauge pixel q with the nearest signature is found
with the exact bucket grid, then (eq. 6 of the paper)::

    n[p] = n[q]
    S*_k[p] = |S_k[p]| / |G_k[q]| * G*_k       for every band k

The signature (and so the normal) comes from the chosen mode: all bands in
colour mode, one band (luminance or a channel) in mono mode. The albedo is
always given for every band of the input, from that band's OV norms.

:func:`reconstruct` reads top to bottom: resolve the settings
(:func:`colorps.resolve.resolve`), check the inputs, compute the signatures and
fit the noise model (:func:`_setup`), match (:func:`colorps.matching.match_pixels`:
the matching policy), refine the normals past the gauge's pixel grid
(:func:`_refine`), fit the albedo (:func:`_albedo`), say why unsolved pixels
are unsolved (:func:`_reasons`), and gather the statistics
(:func:`colorps.results.run_statistics`).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass

import numpy as np

from . import _pixel_kernels, light_masks
from ._blas import one_blas_thread
from ._checks import check_stack, mask_box
from ._pages import small_pages
from .errors import GaugeWarning, InputError, LowSolvedWarning
from .gauge import Gauge, parse_albedo
from .matching import Matches, first_match, match_pixels
from .memory import release_freed_memory
from .noise import NoiseModel, estimate_noise
from .options import MIN_IMAGES, Options, dark_threshold
from .reasons import Reason
from .refine import Matched, Refinement, misfit_radius, quadratic_models, refine_normals
from .resolve import Resolved, resolve
from .results import (
    MAX_UNCERTAINTY,
    Reconstruction,
    Timings,
    low_solved_message,
    run_statistics,
)
from .shadows import INLIER_Z, fixes_normal
from .signatures import SignatureSet, compute_signatures
from .spikes import replace_spikes
from .tables import Capture, GaugeTables

__all__ = ["first_residuals", "reconstruct"]

# ---------------------------------------------------------------- tuning
#: Below this fraction of usable gauge pixels a GaugeWarning is raised.
GAUGE_USABLE_WARNING = 0.8
#: The gauge is worked on in its mask's box grown by this many pixels (the 3 x 3
#: neighbourhoods of the spike test and the noise fit): a gauge photographed in
#: a whole frame is mostly background.
GAUGE_BOX_MARGIN = 2
#: Least squares albedo (some measurements unusable) needs the usable ones to
#: carry at least this fraction of the gauge OV's energy; else NaN.
MIN_ALBEDO_ENERGY = 0.01
#: Mono mode takes the albedo's measurements from the stack in pieces of this
#: many rows (each transposed to pixel-major order, a bounded copy).
ALBEDO_ROWS = 256


def reconstruct(scene, gauge_stack, gauge: Gauge, options: Options | Resolved | None = None,
                *, mask=None, model_scale: float | None = None,
                tables: GaugeTables | None = None, progress: bool = False,
                **changes) -> Reconstruction:
    """Recover normals and intrinsic colour of a scene from a gauge.

    Parameters
    ----------
    scene : (m, H, W, c) array_like
        Linear scene images, one per lighting condition.
    gauge_stack : (m, Hg, Wg, c) array_like
        Linear gauge images under the same m lighting conditions, same order.
    gauge : Gauge
        Normals, mask and albedo of the gauge (see :meth:`Gauge.from_sphere`).
    options : Options or Resolved, optional
        Settings (default ``Options()``). With Options, the stacks are taken
        for floating-point data ("auto" levels: no clipping, dark level
        :data:`~colorps.options.FLOAT_DARK_LEVEL`); a
        :class:`~colorps.resolve.Resolved` says how each stack was stored
        (:func:`colorps.resolve.resolve`). "auto" read noise and gain are
        fitted to the gauge.
    mask : (H, W) array_like of bool, optional
        Scene pixels to solve (default: all).
    model_scale : float, optional
        Divide the residuals by this instead of the model scale measured from
        this scene's first matches (:func:`first_residuals`): pieces of one
        capture processed apart share the whole capture's scale.
    tables : GaugeTables, optional
        Grids of this gauge's tables kept from earlier pieces of the same
        capture (same gauge and options), used again instead of rebuilt;
        the grids built here are offered to it.
    progress : bool, optional
        Show a progress bar.
    **changes
        Fields of :class:`Options` to change, e.g. ``mode="mono"``.

    Returns
    -------
    Reconstruction

    Notes
    -----
    In colour mode a pixel with some bands too dark, clipped or invalid is
    solved from its remaining bands, with a bucket grid over those bands of the
    gauge table (built once per band subset, when first needed), provided they
    still fix a normal (bands x (m - 1) >= 2). Every band then gets its albedo
    from the found normal: eq. 6 when all its measurements are usable, else the
    least-squares scale over its usable (unclipped) measurements, leaving out
    the lights with an invalid (NaN, Inf, far below zero) measurement in any band.

    In colour mode the albedo is taken from the observation vectors, and
    ``scene`` is not referenced past them: a caller that holds no reference of
    its own (as :func:`colorps.pipeline.reconstruct_files` does) gets the
    stack's memory back for the matching.

    Examples
    --------
    >>> from colorps import Gauge, reconstruct, synth
    >>> lights = synth.ring_lights(6, 45)
    >>> scene = synth.smiley_surface(64)
    >>> ball = synth.sphere_surface(101, 48)
    >>> result = reconstruct(synth.render(scene, lights), synth.render(ball, lights),
    ...                      Gauge.from_sphere((101, 101), 50, 50, 48), mask=scene.mask)
    >>> result.normals.shape, result.albedo.shape, bool(result.solved.sum() == scene.mask.sum())
    ((64, 64, 3), (64, 64, 3), True)
    """
    with one_blas_thread(), small_pages():
        t_start = time.perf_counter()
        run = resolve(options, **changes)
        options = run.options
        scene, gauge_stack, mask = _check_inputs(scene, gauge_stack, gauge, mask, options.mode)
        whole, box = mask.shape, mask_box(mask)  # only the mask's box is worked on
        origin, mask = (box[0].start, box[1].start), mask[box]
        setup = _setup(scene, box, gauge_stack, gauge, run, tables)
        gauge = setup.gauge  # within its mask's box, as the matches' rows count
        m, _, _, c = scene.shape
        # In colour mode the OVs hold every measurement: the stack is let go.
        stack_box = None if options.mode == "colour" else scene[:, box[0], box[1]]
        del scene
        release_freed_memory()  # each step's temporaries, before the next step's
        matches = match_pixels(setup.capture, mask, options, progress, model_scale, origin=origin)
        release_freed_memory()
        solved = matches.row >= 0
        if options.max_distance is not None:
            solved &= matches.distance <= options.max_distance
        poor = np.zeros_like(solved)
        if options.max_residual is not None:
            poor = solved & ~(matches.quality <= options.max_residual)
            solved &= ~poor
        if options.refine == "none" and not options.refuse_poor:
            solved |= poor  # flagged (Reason.SOLVED_POOR_MATCH), not refused
        normals = np.full((*mask.shape, 3), np.nan, dtype=np.float32)
        normals[solved] = setup.capture.gauge_normals[matches.row[solved]]
        uncertainty = np.full(mask.shape, np.nan, dtype=np.float32)
        offset = np.zeros((int(solved.sum()), 2), dtype=np.float32)
        t0 = time.perf_counter()
        if options.refine != "none" and (solved | poor).any():
            solved, matches, refined = _refine(setup.capture, gauge, matches,
                                               solved, poor, options)
            # The noise's uncertainty or the one the residuals show along the
            # normal's directions, whichever is larger, grown by how much worse than
            # the noise the match explains the pixel (the reduced chi-square's root,
            # its residual): a pixel the gauge explains poorly is less certain. Or,
            # where larger, the misfit's own radius (refine.misfit_radius). At most
            # MAX_UNCERTAINTY.
            misfit = np.maximum(1.0, np.nan_to_num(matches.quality[solved], nan=1.0))
            normals[solved] = refined.normals
            uncertainty[solved] = np.minimum(np.fmax(
                np.fmax(refined.uncertainty, refined.measured_uncertainty) * misfit,
                _misfit_radius(refined, matches, solved, setup.capture.images)),
                MAX_UNCERTAINTY)
            offset = refined.offset
            del refined  # its other per-pixel arrays are not needed past here
            release_freed_memory()
        t_refine = time.perf_counter() - t0
        albedo = np.full((*mask.shape, c), np.nan, dtype=np.float32)
        albedo[solved] = _albedo(setup.scene_sig, stack_box, setup.gauge_stack, solved, matches,
                                 offset, parse_albedo(gauge.albedo, c), options.clip_level)
        reason = _reasons(setup.scene_sig, mask, solved, matches, options.max_residual)
        message = low_solved_message(reason, mask, solved)
        if message:
            setup.said.append(message)
            warnings.warn(message, LowSolvedWarning, stacklevel=2)
        seconds = Timings(signatures=setup.seconds, grid=matches.seconds_grid,
                          lookup=matches.seconds_lookup, refine=t_refine,
                          total=time.perf_counter() - t_start)
        stats = run_statistics(
            matches, solved, reason, uncertainty, images=m, bands=c, mode=options.mode,
            signature_dims=setup.scene_sig.bands * m,
            table_size=int((gauge.mask & setup.gauge_sig.valid).sum()),
            clip_level=options.clip_level, dark_level=float(options.dark_level),
            dark_threshold=setup.capture.min_norm, noise=setup.capture.model.as_dict(),
            max_residual=options.max_residual, max_distance=options.max_distance,
            gauge_usable_fraction=setup.usable_gauge, gauge_spikes_replaced=setup.gauge_spikes,
            warnings=tuple(setup.said),
            seconds=seconds)
        return _embed(Reconstruction(normals, albedo, matches.quality, uncertainty, solved, reason,
                                     matches.bands_used,
                                     np.where(solved[..., None], matches.dropped, np.uint64(0)),
                                     stats), box, whole)


def first_residuals(scene, gauge_stack, gauge: Gauge, options: Options | Resolved | None = None,
                    *, mask=None, tables: GaugeTables | None = None) -> np.ndarray:
    """Residuals of the first matches of a piece of a scene, before any scaling.

    :func:`reconstruct` divides residuals by the model scale of its scene
    (:func:`colorps.matching.measured_model_scale` of these); a capture
    processed in pieces gathers the pieces' first residuals, measures the
    scale once and hands it to each piece's ``reconstruct(..., model_scale=)``.
    Arguments as for :func:`reconstruct`.

    Returns
    -------
    (P,) ndarray of float32
        One per matched pixel, in no particular order.
    """
    run = resolve(options)
    scene, gauge_stack, mask = _check_inputs(scene, gauge_stack, gauge, mask,
                                             run.options.mode)
    setup = _setup(scene, None, gauge_stack, gauge, run, tables)
    state = first_match(setup.capture, mask, run.options, progress=False)
    return state.quality[state.row >= 0]


# ---------------------------------------------------------------- steps
@dataclass(frozen=True)
class _Setup:
    """Signatures, noise model and the capture to match (private)."""

    capture: Capture
    gauge: Gauge  # within its mask's box (GAUGE_BOX_MARGIN)
    scene_sig: SignatureSet
    gauge_sig: SignatureSet
    gauge_stack: np.ndarray  # the same box, its spikes replaced (colorps.spikes)
    gauge_spikes: int
    usable_gauge: float
    said: list
    seconds: float


def _setup(scene, box, gauge_stack, gauge: Gauge, run: Resolved, tables=None) -> _Setup:
    """Signatures of both stacks (the scene's of its ``box``, None: all), the
    noise model, and the capture to match; the gauge's side as ``tables``
    keeps it (:func:`_gauge_side`)."""
    options = run.options
    m = scene.shape[0]
    t0 = time.perf_counter()
    side = _gauge_side(gauge_stack, gauge, run) if tables is None else \
        tables.kept(("gauge side", run), (gauge_stack, gauge),
                    lambda: _gauge_side(gauge_stack, gauge, run))
    said = []
    if side.spikes:
        said.append(f"{side.spikes} isolated spikes in the gauge's images (fireflies, hot "
                    "pixels) were replaced by their neighbours' median")
        warnings.warn(said[-1], GaugeWarning, stacklevel=3)
    if side.usable < GAUGE_USABLE_WARNING:
        said.append(f"only {side.usable:.0%} of the gauge pixels have every band usable "
                    "(clipped, too dark or invalid): check the gauge's exposure")
        warnings.warn(said[-1], GaugeWarning, stacklevel=3)
    min_norm = dark_threshold(options.dark_level, m)
    scene_sig = compute_signatures(scene, options.mode, box=box, band=options.band,
                                   colourspace=options.colourspace, min_norm=min_norm,
                                   clip_level=options.clip_level)
    gauge_sig, gauge_model = side.signatures, side.model
    model = dataclasses.replace(run.scene.noise, read=gauge_model.read,
                                gain=gauge_model.gain, estimated=gauge_model.estimated)
    capture = Capture(
        scene_ov=scene_sig.ov, scene_valid=scene_sig.band_valid, gauge_ov=gauge_sig.ov,
        gauge_valid=side.valid, gauge_normals=side.gauge.normals.reshape(-1, 3), model=model,
        min_norm=min_norm, gauge_model=gauge_model, scene_clipped=scene_sig.clipped_lights,
        scene_invalid=scene_sig.band_invalid_value.any(axis=-1), gauge_clipped=side.clipped,
        gauge_unclipped=side.unclipped, tables=tables)
    return _Setup(capture, side.gauge, scene_sig, gauge_sig, side.stack, side.spikes,
                  side.usable, said, time.perf_counter() - t0)


@dataclass(frozen=True)
class _GaugeSide:
    """What a solve makes of the gauge alone (private; kept by GaugeTables)."""

    gauge: Gauge  # within its mask's box (GAUGE_BOX_MARGIN)
    stack: np.ndarray  # the same box, its spikes replaced (colorps.spikes)
    spikes: int
    signatures: SignatureSet
    usable: float  # share of the gauge's pixels with every band usable
    model: NoiseModel
    valid: np.ndarray  # Capture's gauge_valid, gauge_clipped, gauge_unclipped
    clipped: np.ndarray
    unclipped: np.ndarray


def _gauge_side(gauge_stack, gauge: Gauge, run: Resolved) -> _GaugeSide:
    """The gauge in its mask's box, its signatures and noise model; a photographed
    gauge's spikes replaced first."""
    options = run.options
    box = mask_box(gauge.mask, GAUGE_BOX_MARGIN)
    gauge, gauge_stack = gauge.within(box), gauge_stack[:, box[0], box[1]]
    spikes = 0
    if gauge.stack is None:  # photographed (a rendered gauge has no spikes)
        gauge_stack, spikes = replace_spikes(gauge_stack, gauge.mask)
    gauge_clip, gauge_dark = run.gauge_levels
    gauge_sig = compute_signatures(gauge_stack, options.mode, band=options.band,
                                   colourspace=options.colourspace,
                                   min_norm=dark_threshold(gauge_dark, gauge_stack.shape[0]),
                                   clip_level=gauge_clip)
    usable = float((gauge.mask & gauge_sig.valid).sum() / gauge.mask.sum())
    model = _noise_model(gauge_stack, gauge, gauge_sig, options, run.gauge.noise)
    inside = gauge.mask[..., None]
    return _GaugeSide(gauge, gauge_stack, spikes, gauge_sig, usable, model,
                      valid=gauge_sig.band_valid & inside,
                      clipped=np.where(inside, gauge_sig.clipped_lights, np.uint64(0)),
                      unclipped=~gauge_sig.band_invalid_value & ~gauge_sig.band_dark & inside)


def _embed(result: Reconstruction, box: tuple[slice, slice], shape: tuple[int, int]
           ) -> Reconstruction:
    """A reconstruction of the mask's box as one of the whole image: outside the
    box every pixel is background (no normal, no match)."""
    if result.solved.shape == tuple(shape):
        return result
    maps = {}
    for field in ("normals", "albedo", "quality", "uncertainty", "solved", "reason",
                  "bands_used", "dropped_lights"):
        inside = getattr(result, field)
        fill = {"solved": False, "reason": Reason.BACKGROUND, "bands_used": 0,
                "dropped_lights": 0}.get(field, np.nan)
        maps[field] = np.full((*shape, *inside.shape[2:]), fill, dtype=inside.dtype)
        maps[field][box] = inside
    outside = int(np.prod(shape)) - result.solved.size
    by_reason = dict(result.stats.pixels_by_reason)
    label = Reason.BACKGROUND.label
    by_reason[label] = by_reason.get(label, 0) + outside
    stats = dataclasses.replace(result.stats, pixels=int(np.prod(shape)),
                                pixels_by_reason=by_reason)
    return dataclasses.replace(result, stats=stats, **maps)


def _check_inputs(scene, gauge_stack, gauge: Gauge, mask, mode: str):
    """Checked float32 stacks and a boolean mask, or an InputError saying what is wrong."""
    scene = check_stack(scene, "scene")
    gauge_stack = check_stack(gauge_stack, "gauge")
    m, h, w, c = scene.shape
    if gauge_stack.shape[0] != m:
        raise InputError(f"scene has {m} images but the gauge has {gauge_stack.shape[0]}; "
                         "they must be taken pairwise under the same lights")
    if gauge_stack.shape[3] != c:
        raise InputError(f"scene images have {c} channel(s) but gauge images have "
                         f"{gauge_stack.shape[3]}")
    if gauge_stack.shape[1:3] != gauge.mask.shape:
        raise InputError(f"gauge geometry is {gauge.mask.shape[1]}x{gauge.mask.shape[0]} "
                         f"but gauge images are {gauge_stack.shape[2]}x{gauge_stack.shape[1]}")
    if m < MIN_IMAGES[mode]:
        hint = ("" if mode == "colour" else
                "; colour mode can work with 2 images lit by mixed-colour lights")
        raise InputError(f"{mode} mode needs at least {MIN_IMAGES[mode]} images, got {m}{hint}")
    if mode == "colour" and m < 3:
        if c < 2:
            raise InputError("colour mode with 2 images needs several bands (mixed-colour "
                             "lights)")
        warnings.warn("colour mode with 2 images solves normals only when each image is lit "
                      "by several lights of different colours at once", GaugeWarning,
                      stacklevel=3)
    if mask is None:
        mask = np.ones((h, w), dtype=bool)
    mask = np.asarray(mask)
    if mask.shape != (h, w):
        raise InputError(f"mask: shape {mask.shape} differs from the scene's {(h, w)}")
    return scene, gauge_stack, mask.astype(bool)


def _refine(capture: Capture, gauge: Gauge, matches: Matches,
            solved: np.ndarray, poor: np.ndarray, options: Options
            ) -> tuple[np.ndarray, Matches, Refinement]:
    """Refine the solved pixels' normals, weighting each measurement by its noise.

    The ``poor`` pixels (matched, but the table's nearest entry leaves them
    over ``max_residual``) are refined too. With ``light_subsets`` they are
    solved as good matches when the robust fit explains its inliers within it
    on enough lights (as :mod:`colorps.shadows` asks): lights in cast shadow
    near the table's rim, where the shadow search keeps them, and normals past
    the gauge's edge, which no entry is near; their outliers join their
    dropped lights and their quality is the inliers' residual. The others are
    solved as they are (poor matches, flagged) unless ``refuse_poor``.
    Returns the solved pixels, the matches with those changes, and the
    refinement of the solved pixels (row-major order).
    """
    if not options.light_subsets and options.refuse_poor:
        poor = np.zeros_like(poor)
    tried = solved | poor
    ys, xs = np.nonzero(tried)
    matched = Matched(ys, xs, matches.row[ys, xs], matches.bands_used[ys, xs],
                      matches.dropped[ys, xs])
    # The gauge's models are fitted where its bands are usable but for clipped
    # measurements: a pixel near a clipped patch leaves those lights out (or its
    # robust fit down-weights them); without them it kept the table's normal.
    usable = capture.gauge_unclipped.all(axis=-1)
    if capture.tables is not None:  # every usable pixel's model, kept for the next solve
        usable = capture.tables.kept("refinement models", (capture.gauge_ov, gauge),
                                     lambda: quadratic_models(capture.gauge_ov.reshape(
                                         *usable.shape, -1), gauge.normals, usable))
    refined = refine_normals(capture.scene_ov, capture.gauge_ov, gauge.normals, usable,
                             matched, capture.model, capture.gauge_model or capture.model,
                             model_scale=matches.model_scale, outlier_z=INLIER_Z,
                             threads=options.threads)
    if not poor.any():
        return solved, matches, refined
    dropped = matches.dropped[ys, xs] | refined.outliers
    lights = capture.images - light_masks.count(dropped)
    bands = light_masks.count(matches.bands_used[ys, xs][:, None])  # bits set: bands matched
    fitted = refined.inlier_residual / matches.model_scale
    rescued = poor[ys, xs] & refined.refined & (fitted <= options.max_residual) & \
        fixes_normal(bands, lights) & options.light_subsets
    keep = solved[ys, xs] | rescued | (poor[ys, xs] & (not options.refuse_poor))
    quality, all_dropped = matches.quality.copy(), matches.dropped.copy()
    quality[ys[rescued], xs[rescued]] = fitted[rescued]
    all_dropped[ys[rescued], xs[rescued]] = dropped[rescued]
    solved = solved.copy()
    solved[ys[keep], xs[keep]] = True
    kept = Refinement(*(getattr(refined, f.name)[keep] for f in dataclasses.fields(refined)))
    return solved, dataclasses.replace(matches, quality=quality, dropped=all_dropped), kept


def _misfit_radius(refined: Refinement, matches: Matches, solved: np.ndarray,
                   images: int) -> np.ndarray:
    """(P,) :func:`refine.misfit_radius` of the solved pixels: the noise's radius
    and the residual before the capture's model scale, over their bands and lights."""
    bands = light_masks.count(matches.bands_used[solved][:, None])  # bits set: bands
    lights = images - light_masks.count(matches.dropped[solved])
    return misfit_radius(refined.uncertainty / matches.model_scale,
                         matches.quality[solved] * matches.model_scale,
                         bands * (lights - 1))


def _albedo(scene_sig: SignatureSet, stack_box: np.ndarray | None, gauge_stack: np.ndarray,
            solved: np.ndarray, matches: Matches, offset: np.ndarray,
            gauge_albedo: np.ndarray, clip_level: float | None) -> np.ndarray:
    """(P, c) albedo of the solved pixels (method eq. 6, or least squares on the
    usable measurements), against the gauge at each refined position.

    The measurements are the colour-mode OVs of ``scene_sig``, or, in mono
    mode, those of ``stack_box`` (the scene's box), ALBEDO_ROWS rows at a
    time. See :func:`colorps._pixel_kernels.albedo`; a pixel's dropped lights
    and those with an invalid measurement are left out of its fit.
    """
    ys, xs = np.nonzero(solved)
    m = gauge_stack.shape[0]
    out = np.empty((len(ys), gauge_stack.shape[3]), dtype=np.float32)
    excluded = light_masks.to_bool(matches.dropped[ys, xs] | scene_sig.invalid_lights[ys, xs], m)
    pieces = [(0, solved.shape[0])] if stack_box is None else \
        [(row, row + ALBEDO_ROWS) for row in range(0, solved.shape[0], ALBEDO_ROWS)]
    for first, last in pieces:
        pick = slice(*np.searchsorted(ys, (first, last)))  # ys ascend
        values = scene_sig.ov if stack_box is None else \
            np.ascontiguousarray(stack_box[:, first:last].transpose(1, 2, 3, 0))
        _pixel_kernels.albedo(values, ys[pick] - first, xs[pick], gauge_stack,
                              matches.row[ys[pick], xs[pick]],
                              np.ascontiguousarray(offset[pick], dtype=np.float32),
                              excluded[pick], np.inf if clip_level is None else float(clip_level),
                              np.asarray(gauge_albedo, dtype=np.float64), MIN_ALBEDO_ENERGY,
                              out[pick])
    return out


def _reasons(scene_sig: SignatureSet, mask: np.ndarray, solved: np.ndarray,
             matches: Matches, max_residual: float | None) -> np.ndarray:
    """(H, W) uint8 :class:`Reason` codes; of several problems the larger code wins."""
    reason = np.full(mask.shape, Reason.SOLVED, dtype=np.uint8)
    reason[solved & ~light_masks.is_empty(matches.dropped)] = Reason.SOLVED_FROM_LIGHT_SUBSET
    if max_residual is not None:
        reason[solved & (matches.quality > max_residual)] = Reason.SOLVED_POOR_MATCH
    matched, unsolved = matches.row >= 0, mask & ~solved
    reason[unsolved & scene_sig.band_dark.any(axis=-1)] = Reason.TOO_DARK
    reason[unsolved & scene_sig.band_clipped.any(axis=-1)] = Reason.CLIPPED
    reason[unsolved & scene_sig.band_invalid_value.any(axis=-1)] = Reason.INVALID_VALUE
    reason[unsolved & matched] = Reason.NO_GOOD_MATCH
    reason[~mask] = Reason.BACKGROUND
    return reason


def _noise_model(gauge_stack: np.ndarray, gauge: Gauge, gauge_sig: SignatureSet,
                 options: Options, base: NoiseModel | None) -> NoiseModel:
    """The capture's noise model: the given read noise and gain, or the gauge's."""
    if options.read_noise == "auto" or options.gain == "auto":
        centre, radius = (gauge.sphere[:2], gauge.sphere[2]) if gauge.sphere else (None, None)
        fitted = estimate_noise(gauge_stack, gauge.mask & gauge_sig.valid, base, centre,
                                radius)
        base = dataclasses.replace(base, read=fitted.read, gain=fitted.gain,
                                   estimated=fitted.estimated)
    changes = {}
    if options.read_noise != "auto":
        changes["read"] = float(options.read_noise)
    if options.gain != "auto":
        changes["gain"] = float(options.gain)
    return dataclasses.replace(base, **changes) if changes else base
