"""Scene stack + gauge stack -> normals, per-band albedo and match quality.

For each scene pixel p the gauge pixel q with the nearest signature is found
with the exact bucket grid, then (eq. 6 of the paper)::

    n[p] = n[q]
    S*_k[p] = |S_k[p]| / |G_k[q]| * G*_k       for every band k

The signature (and so the normal) comes from the chosen mode: all bands in
colour mode, one band (luminance or a channel) in mono mode. The albedo is
always given for every band of the input, from that band's OV norms.

:func:`reconstruct` runs named steps: check the inputs (:func:`_check_inputs`),
compute the signatures, fit the noise model (:func:`_noise_model`), match every
group of bands, weights and lights (:func:`_match`, then :func:`_light_subsets`),
refine the normals past the gauge's pixel grid (:func:`_refine`), fit the albedo
(:func:`_albedo`), and say why unsolved pixels are unsolved (:func:`_reasons`).
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass

import numpy as np

from . import _pixel_kernels, light_masks
from ._checks import check_stack
from .errors import InputError
from .gauge import Gauge, parse_albedo
from .matching import DROP_LEVEL, Capture, GaugeTables, GroupResult, band_snr, weight_levels
from .noise import NoiseModel, estimate_noise
from .options import FLOAT_DARK_LEVEL, MIN_IMAGES, Options, dark_threshold
from .reasons import Reason, reason_counts
from .refine import refine_normals
from .residuals import light_residuals
from .signatures import SignatureSet, compute_signatures

__all__ = ["Reconstruction", "ReconstructionStats", "MatchGroup", "Timings", "reconstruct",
           "first_residuals", "measured_model_scale", "model_scale_pixels", "GaugeWarning",
           "LowSolvedWarning"]

# ---------------------------------------------------------------- tuning
#: Side (pixels) of the tiles in which pixels are looked up. Neighbouring pixels
#: look up the same gauge entries, which then stay in the CPU's caches: colour
#: m = 30 lookups are ~18 % faster than row by row (docs/benchmarks.md).
LOOKUP_TILE = 32
#: Queries ``grid_n="auto"`` times candidate grids on (a regular sample).
AUTO_N_SAMPLE = 4000
#: Below this fraction of usable gauge pixels a GaugeWarning is raised.
GAUGE_USABLE_WARNING = 0.8
#: Below this fraction of the masked pixels solved, a LowSolvedWarning is raised.
LOW_SOLVED_FRACTION = 0.5
#: A band subset needs at least this many usable gauge pixels to get a table.
MIN_TABLE_ENTRIES = 3
#: Least squares albedo (some measurements unusable) needs the usable ones to
#: carry at least this fraction of the gauge OV's energy; else NaN.
MIN_ALBEDO_ENERGY = 0.01
#: A pixel with clipped measurements in at most this fraction of the images
#: keeps its bands and drops those images' lights instead.
MAX_CLIPPED_FRACTION = 0.5
#: Light subsets: pixels whose residual (noise units) exceeds SUBSET_TRIGGER are
#: re-matched without each of their lights in turn; the best is kept when its
#: residual is at most SUBSET_GAIN of the old one. At least MIN_LIGHTS lights
#: remain, and at most MAX_SUBSET_GROUPS tables are built per round (the
#: largest groups first).
SUBSET_TRIGGER = 3.0
SUBSET_GAIN = 0.7
MIN_LIGHTS = 3
MAX_SUBSET_GROUPS = 128
#: A pixel tries dropping at most this many of its lights per round: those its
#: match explains least (largest |per-light residual|). Every light when m is at
#: most this; with DiLiGenT's 96 lights, trying all cost 190 s of a 205 s run.
MAX_LIGHTS_TRIED = 8
#: The model scale is measured on about this many masked pixels at most: every
#: s-th row and column of the mask (:func:`model_scale_pixels`), the same pixels
#: however the scene is tiled, so a tiled run's first pass matches only them.
#: The median of 2^16 residuals is within about 0.5 % of the whole image's.
MODEL_SCALE_PIXELS = 2 ** 16


class GaugeWarning(UserWarning):
    """The capture may not fix the normals (gauge losing pixels, too few images)."""


class LowSolvedWarning(UserWarning):
    """Less than LOW_SOLVED_FRACTION of the masked pixels were solved."""


@dataclass(frozen=True)
class MatchGroup:
    """One table and grid, built for the pixels whose usable bands are ``bands``.

    Attributes
    ----------
    bands : tuple of int
        Signature bands matched (all bands unless some were unusable).
    table_size : int
        Gauge entries in the table (gauge pixels with those bands usable).
    grid_n : int or None
        None when the group was small enough for brute force.
    pixels : int
        Scene pixels matched with it.
    lights_dropped : tuple of int
        Lights left out of the table (light subsets).
    """

    bands: tuple[int, ...]
    table_size: int
    grid_n: int | None
    pixels: int
    lights_dropped: tuple[int, ...] = ()


@dataclass(frozen=True)
class Timings:
    """Seconds spent per stage (wall clock)."""

    signatures: float
    grid: float
    lookup: float
    refine: float
    total: float
    integration: float | None = None


@dataclass(frozen=True)
class ReconstructionStats:
    """What a reconstruction did (written to report.json as ``statistics``).

    Attributes
    ----------
    images, bands : int
        m, and the number c of input bands.
    mode : str
    signature_dims : int
        Dimension D of the full signature (B m).
    table_size : int
        Gauge pixels with every band usable (the full table |T|).
    grid_n : int or None
        N of the full-signature grid (None when no pixel used it).
    grids : tuple of MatchGroup
        Every table built, full signature first.
    buckets_per_lookup, tests_per_lookup : float
        Mean buckets examined (b) and full distances computed (d) per lookup.
    pixels, solved, solved_from_band_subset, solved_from_light_subset : int
    lights_dropped_per_pixel : dict of str to int
        Solved pixels by number of lights dropped ("0", "1", ...).
    dropped_per_light : list of dict
        Per light: solved pixels that dropped it as darker than the match
        (cast shadow) and as brighter (highlight, interreflection).
    pixels_by_reason : dict of str to int
        Keyed by :attr:`Reason.label`.
    clip_level : float or None
    dark_level : float
        Resolved levels (linear); ``dark_threshold`` = dark_level sqrt(m).
    dark_threshold : float
    noise : dict
        The noise model (:class:`~colorps.noise.NoiseModel`).
    model_scale : float
        Median residual of the first matches when above 1 (model mismatch
        every pixel shares); residuals are divided by it.
    residual_median, residual_p95 : float or None
        Of the matched pixels' ``quality``.
    max_residual, max_distance : float or None
    gauge_usable_fraction : float
        Fraction of the gauge mask with every band usable.
    warnings : tuple of str
        What the run warned about (also issued as Python warnings).
    refined : int
        Solved pixels whose normal was refined past the gauge's pixel grid.
    uncertainty_median, uncertainty_p95 : float or None
        Of the refined pixels' 68 % angular uncertainty (degrees).
    seconds : Timings
    """

    images: int
    bands: int
    mode: str
    signature_dims: int
    table_size: int
    grid_n: int | None
    grids: tuple[MatchGroup, ...]
    buckets_per_lookup: float
    tests_per_lookup: float
    pixels: int
    solved: int
    solved_from_band_subset: int
    solved_from_light_subset: int
    lights_dropped_per_pixel: dict
    dropped_per_light: list
    pixels_by_reason: dict
    clip_level: float | None
    dark_level: float
    dark_threshold: float
    noise: dict
    model_scale: float
    residual_median: float | None
    residual_p95: float | None
    max_residual: float | None
    max_distance: float | None
    gauge_usable_fraction: float
    warnings: tuple[str, ...]
    refined: int
    uncertainty_median: float | None
    uncertainty_p95: float | None
    seconds: Timings

    def as_dict(self) -> dict:
        """Nested plain dicts and lists (JSON-ready)."""
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class Reconstruction:
    """Result of :func:`reconstruct` (frozen; its arrays are read-only).

    Attributes
    ----------
    normals : (H, W, 3) ndarray of float32
        Camera-space unit normals (x right, y up, z towards the camera); NaN
        where not solved.
    albedo : (H, W, c) ndarray of float32
        Intrinsic albedo per input band (linear, relative to the gauge albedo);
        NaN where not solved, and in a band whose usable measurements cannot
        fix its scale (e.g. every lit measurement clipped).
    quality : (H, W) ndarray of float32
        Residual of the match in units of its expected value under the noise
        model (:mod:`colorps.residuals`): about 1 where the gauge explains
        the pixel, far above for cast shadows, highlights or other materials.
        NaN where no match was attempted.
    uncertainty : (H, W) ndarray of float32
        68 % angular radius of the refined normal, degrees (:mod:`colorps.refine`);
        NaN where not solved or not refined.
    solved : (H, W) ndarray of bool
    reason : (H, W) ndarray of uint8
        Why a pixel is not solved: a :class:`~colorps.Reason` code.
    bands_used : (H, W) ndarray of uint8
        Bit k set when band k of the signature was matched (colour mode falls
        back to the valid bands of a pixel).
    dropped_lights : (H, W, words) ndarray of uint64
        Light masks (:mod:`colorps.light_masks`: image i is bit i % 64 of
        word i // 64) of the lights left out of each pixel's match (a cast
        shadow or highlight there); see :attr:`lights_dropped_count`.
    stats : ReconstructionStats
    height : (H, W) ndarray or None
        Height map (pixels), when integrated: see :meth:`with_height`.
    """

    normals: np.ndarray
    albedo: np.ndarray
    quality: np.ndarray
    uncertainty: np.ndarray
    solved: np.ndarray
    reason: np.ndarray
    bands_used: np.ndarray
    dropped_lights: np.ndarray
    stats: ReconstructionStats
    height: np.ndarray | None = None

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                value.flags.writeable = False

    @property
    def lights_dropped_count(self) -> np.ndarray:
        """(H, W) uint8 number of lights dropped from each pixel's match."""
        return light_masks.count(self.dropped_lights).astype(np.uint8)

    def with_height(self, height: np.ndarray, seconds: float | None = None
                    ) -> "Reconstruction":
        """This result with a height map (and the seconds its integration took)."""
        timings = dataclasses.replace(self.stats.seconds, integration=seconds)
        stats = dataclasses.replace(self.stats, seconds=timings)
        return dataclasses.replace(self, height=np.asarray(height),
                                   stats=stats)


def reconstruct(scene, gauge_stack, gauge: Gauge, options: Options | None = None, *,
                mask=None, noise: NoiseModel | None = None,
                gauge_noise: NoiseModel | None = None,
                gauge_levels: tuple[float | None, float] | None = None,
                model_scale: float | None = None, tables: GaugeTables | None = None,
                progress: bool = False, **changes) -> Reconstruction:
    """Recover normals and intrinsic colour of a scene from a gauge.

    Parameters
    ----------
    scene : (m, H, W, c) array_like
        Linear scene images, one per lighting condition.
    gauge_stack : (m, Hg, Wg, c) array_like
        Linear gauge images under the same m lighting conditions, same order.
    gauge : Gauge
        Normals, mask and albedo of the gauge (see :meth:`Gauge.from_sphere`).
    options : Options, optional
        Settings (default ``Options()``). "auto" levels mean those of
        floating-point data: no clipping, dark level
        :data:`~colorps.options.FLOAT_DARK_LEVEL`.
    mask : (H, W) array_like of bool, optional
        Scene pixels to solve (default: all).
    noise : NoiseModel, optional
        The data's pixel type and encoding (quantisation), and the read noise
        and gain to start from (default: floating-point data). "auto" fields of
        ``options`` are fitted to the gauge.
    gauge_noise, gauge_levels : optional
        The gauge's pixel type (a NoiseModel) and (clip, dark) levels, when its
        files are stored differently from the scene's (default: the scene's).
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
    least-squares scale over its usable (finite, non-negative, unclipped)
    measurements.

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
    t_start = time.perf_counter()
    options = (options or Options()).replace(**changes)
    options = options.with_levels(None, FLOAT_DARK_LEVEL)  # arrays are floating point
    scene, gauge_stack, mask = _check_inputs(scene, gauge_stack, gauge, mask, options.mode)
    m, h, w, c = scene.shape
    gauge_albedo = parse_albedo(gauge.albedo, c)

    setup = _setup(scene, gauge_stack, gauge, options, noise, gauge_noise, gauge_levels,
                   tables)
    capture, scene_sig, gauge_sig = setup.capture, setup.scene_sig, setup.gauge_sig
    model, min_norm, usable_gauge, said = (setup.model, setup.min_norm, setup.usable_gauge,
                                           setup.said)
    t_signatures = setup.seconds

    matches = _match(capture, mask, options, progress, model_scale)
    matched = matches.row >= 0
    solved = matched.copy()
    if options.max_residual is not None:
        solved &= matches.quality <= options.max_residual
    if options.max_distance is not None:
        solved &= matches.distance <= options.max_distance
    normals = np.full((h, w, 3), np.nan, dtype=np.float32)
    normals[solved] = capture.gauge_normals[matches.row[solved]]
    uncertainty = np.full((h, w), np.nan, dtype=np.float32)
    offset = np.zeros((int(solved.sum()), 2), dtype=np.float32)
    t0 = time.perf_counter()
    if options.refine != "none" and solved.any():
        refined = _refine(capture, gauge, gauge_sig, matches, solved, options)
        normals[solved] = refined.normals
        uncertainty[solved] = refined.uncertainty
        offset = refined.offset
    t_refine = time.perf_counter() - t0
    albedo = np.full((h, w, c), np.nan, dtype=np.float32)
    albedo[solved] = _albedo(scene, gauge_stack, solved, matches, offset, gauge_albedo,
                             options.clip_level)
    reason = _reasons(scene_sig, mask, solved, matched, matches.dropped)
    message = low_solved_message(reason, mask, solved)
    if message:
        said.append(message)
        warnings.warn(message, LowSolvedWarning, stacklevel=2)

    n_bands = scene_sig.bands
    full = (1 << n_bands) - 1
    n_matched = int(np.count_nonzero(matched))
    full_grid = [g for g in matches.groups if g.bands == tuple(range(n_bands))
                 and g.lights_dropped == () and g.grid_n is not None]
    q = matches.quality[matched]
    stats = ReconstructionStats(
        images=m, bands=c, mode=options.mode, signature_dims=n_bands * m,
        table_size=int((gauge.mask & gauge_sig.valid).sum()),
        grid_n=full_grid[0].grid_n if full_grid else None,
        grids=matches.groups,
        buckets_per_lookup=matches.buckets / n_matched if n_matched else 0.0,
        tests_per_lookup=matches.tests / n_matched if n_matched else 0.0,
        pixels=h * w, solved=int(solved.sum()),
        solved_from_band_subset=int((solved & (matches.bands_used != full)).sum()),
        solved_from_light_subset=int((solved & ~light_masks.is_empty(matches.dropped)).sum()),
        lights_dropped_per_pixel=_dropped_histogram(matches.dropped[solved]),
        dropped_per_light=_dropped_per_light(matches, solved, m),
        pixels_by_reason=reason_counts(reason), clip_level=options.clip_level,
        dark_level=float(options.dark_level), dark_threshold=min_norm,
        noise=model.as_dict(), model_scale=matches.model_scale,
        residual_median=float(np.median(q)) if q.size else None,
        residual_p95=float(np.percentile(q, 95)) if q.size else None,
        max_residual=options.max_residual, max_distance=options.max_distance,
        gauge_usable_fraction=usable_gauge, warnings=tuple(said),
        refined=int(np.isfinite(uncertainty).sum()),
        uncertainty_median=_median(uncertainty[solved]),
        uncertainty_p95=_percentile(uncertainty[solved], 95),
        seconds=Timings(signatures=t_signatures, grid=matches.seconds_grid,
                        lookup=matches.seconds_lookup, refine=t_refine,
                        total=time.perf_counter() - t_start),
    )
    return Reconstruction(normals, albedo, matches.quality, uncertainty, solved, reason,
                          matches.bands_used,
                          np.where(solved[..., None], matches.dropped, np.uint64(0)),
                          stats)


def low_solved_message(reason: np.ndarray, mask: np.ndarray, solved: np.ndarray
                       ) -> str | None:
    """What to warn when under LOW_SOLVED_FRACTION of the mask was solved (else None)."""
    n_masked = int(mask.sum())
    if not (n_masked and 0 < solved.sum() < LOW_SOLVED_FRACTION * n_masked):
        return None
    counts = reason_counts(reason[mask & ~solved])
    worst = max(counts, key=counts.get)
    return (f"only {solved.sum() / n_masked:.0%} of the {n_masked} masked pixels were "
            f"solved (mostly '{worst}': {counts[worst]} pixels)")


def first_residuals(scene, gauge_stack, gauge: Gauge, options: Options | None = None, *,
                    mask=None, noise: NoiseModel | None = None,
                    gauge_noise: NoiseModel | None = None,
                    gauge_levels: tuple[float | None, float] | None = None,
                    tables: GaugeTables | None = None) -> np.ndarray:
    """Residuals of the first matches of a piece of a scene, before any scaling.

    :func:`reconstruct` divides residuals by the model scale of its scene
    (:func:`measured_model_scale` of these); a capture processed in pieces
    gathers the pieces' first residuals, measures the scale once and hands it
    to each piece's ``reconstruct(..., model_scale=)``. Arguments as for
    :func:`reconstruct`.

    Returns
    -------
    (P,) ndarray of float32
        One per matched pixel, in no particular order.
    """
    options = (options or Options()).with_levels(None, FLOAT_DARK_LEVEL)
    scene, gauge_stack, mask = _check_inputs(scene, gauge_stack, gauge, mask, options.mode)
    setup = _setup(scene, gauge_stack, gauge, options, noise, gauge_noise, gauge_levels,
                   tables)
    state = _first_match(setup.capture, mask, options, progress=False)
    return state.quality[state.row >= 0]


# ---------------------------------------------------------------- steps
@dataclass(frozen=True)
class _Setup:
    """Signatures, noise model and the capture to match (private)."""

    capture: Capture
    scene_sig: SignatureSet
    gauge_sig: SignatureSet
    model: NoiseModel
    min_norm: float
    usable_gauge: float
    said: list
    seconds: float


def _setup(scene, gauge_stack, gauge: Gauge, options: Options, noise, gauge_noise,
           gauge_levels, tables=None) -> _Setup:
    """Signatures of both stacks, the noise model, and the capture to match."""
    m = scene.shape[0]
    t0 = time.perf_counter()
    min_norm = dark_threshold(options.dark_level, m)
    signature_options = dict(band=options.band, colourspace=options.colourspace,
                             min_norm=min_norm, clip_level=options.clip_level)
    scene_sig = compute_signatures(scene, options.mode, **signature_options)
    if gauge_levels is not None:
        signature_options.update(clip_level=gauge_levels[0],
                                 min_norm=dark_threshold(gauge_levels[1], m))
    gauge_sig = compute_signatures(gauge_stack, options.mode, **signature_options)
    usable_gauge = float((gauge.mask & gauge_sig.valid).sum() / gauge.mask.sum())
    said = []
    if usable_gauge < GAUGE_USABLE_WARNING:
        said.append(f"only {usable_gauge:.0%} of the gauge pixels have every band usable "
                    "(clipped, too dark or invalid): check the gauge's exposure")
        warnings.warn(said[-1], GaugeWarning, stacklevel=3)
    gauge_model = _noise_model(gauge_stack, gauge, gauge_sig, options, gauge_noise or noise)
    model = dataclasses.replace(noise or gauge_model, read=gauge_model.read,
                                gain=gauge_model.gain, estimated=gauge_model.estimated)
    capture = Capture(
        scene_ov=scene_sig.ov, scene_valid=scene_sig.band_valid,
        gauge_ov=gauge_sig.ov, gauge_valid=gauge_sig.band_valid & gauge.mask[..., None],
        gauge_normals=gauge.normals.reshape(-1, 3), model=model, min_norm=min_norm,
        gauge_model=gauge_model, scene_clipped=scene_sig.clipped_lights,
        scene_invalid=scene_sig.band_invalid_value.any(axis=-1), tables=tables)
    return _Setup(capture, scene_sig, gauge_sig, model, min_norm, usable_gauge, said,
                  time.perf_counter() - t0)


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


@dataclass(frozen=True)
class _Matches:
    """Nearest gauge entry of every scene pixel, over its usable bands and lights."""

    row: np.ndarray         # (H, W) flat gauge pixel index of the match, -1: none
    quality: np.ndarray     # (H, W) residual in noise units (NaN: no match attempted)
    distance: np.ndarray    # (H, W) plain signature distance per band
    bands_used: np.ndarray  # (H, W) bit mask of the bands matched
    dropped: np.ndarray     # (H, W, words) light masks of the lights dropped
    brighter: np.ndarray    # (H, W, words): of those, the ones brighter than the match
    groups: tuple[MatchGroup, ...]
    model_scale: float
    buckets: float          # summed over lookups
    tests: float
    seconds_grid: float
    seconds_lookup: float


def _match(capture: Capture, mask: np.ndarray, options: Options, progress: bool,
           model_scale: float | None = None) -> _Matches:
    """Match every masked pixel: one table per (bands, weights) group, then light subsets.

    Pixels with every band usable are matched on the full signature, the
    others on the bands they have when those still fix a normal (bands x
    (m - 1) >= 2). In colour mode with ``band_weights`` each band is weighted
    by its signal-to-noise ratio (:func:`colorps.matching.weight_levels`).
    The residuals are then divided by the capture's model scale, and, with
    ``light_subsets``, pixels left far outside the noise are re-matched
    without their most deviant light (:func:`_light_subsets`).
    """
    state = _first_match(capture, mask, options, progress)
    matched = state.row >= 0
    if model_scale is None:
        model_scale = measured_model_scale(state.quality[matched & model_scale_pixels(mask)])
    state.quality[matched] /= model_scale
    if options.light_subsets and capture.images >= MIN_LIGHTS + 1:
        _light_subsets(capture, state, options, model_scale)
    return state.result(model_scale)


def _group_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of a (P, k) integer array and each row's group index.

    What ``np.unique(rows, axis=0, return_inverse=True)`` returns (groups in
    lexicographic order), from one 1-D unique of a mixed-radix code of each
    row: columns of a small range of values are digits as they are, others are
    first replaced by their rank, and the code is compacted whenever the next
    digit could overflow it.
    """
    group = np.zeros(len(rows), dtype=np.int64)
    span = 1  # group < span
    for column in rows.T:
        low, high = int(column.min(initial=0)), int(column.max(initial=0))
        if high - low < 1 << 16:
            digit, width = column - low, high - low + 1
        else:
            _, digit = np.unique(column, return_inverse=True)
            width = int(digit.max(initial=0)) + 1
        if span * width >= 1 << 62:
            _, group = np.unique(group, return_inverse=True)
            span = int(group.max(initial=0)) + 1
        group = group * width + digit.ravel()
        span *= width
    _, first, group = np.unique(group, return_index=True, return_inverse=True)
    return rows[first], group.ravel()


def _first_match(capture: Capture, mask: np.ndarray, options: Options,
                 progress: bool) -> "_MatchState":
    """Every masked pixel's match on its usable bands, before light subsets; the
    residuals are not yet divided by the model scale."""
    from tqdm.auto import tqdm

    h, w = mask.shape
    m, n_bands = capture.images, capture.bands
    ys, xs = _tile_order(mask)
    valid = capture.scene_valid[ys, xs]
    levels = np.zeros(valid.shape, dtype=np.int8)
    if options.band_weights and n_bands > 1:
        levels = weight_levels(band_snr(capture.scene_ov, ys, xs, valid, capture.model))
        kept = valid & (levels > DROP_LEVEL)
        fixes_normal = kept.sum(axis=-1) * (m - 1) >= 2
        valid = np.where(fixes_normal[:, None], kept, valid)
        levels = np.where(valid, np.maximum(levels, DROP_LEVEL + 1), 0).astype(np.int8)
    dropped = light_masks.empty((len(ys),), m)
    if options.light_subsets:
        dropped, valid, levels = _drop_clipped_lights(capture, ys, xs, valid, levels,
                                                      options)
    code = (valid * (1 << np.arange(n_bands))).sum(axis=-1)
    state = _MatchState.empty(h, w, n_bands, m)
    state.levels[ys, xs] = levels
    words = dropped.shape[1]
    # One int64 row per pixel: its light-mask words (bit for bit), bands, levels.
    keys, inverse = _group_rows(np.column_stack([dropped.view(np.int64), code.astype(np.int64),
                                                 levels.astype(np.int64)]))
    order = np.argsort(-np.bincount(inverse), kind="stable")
    with tqdm(total=len(ys), desc="matching", unit="px", unit_scale=True,
              disable=not progress, leave=False) as bar:
        for g in order:
            mask_words = keys[g, :words].view(np.uint64)
            lights_dropped = light_masks.lights(mask_words)
            bands = tuple(k for k in range(n_bands) if int(keys[g, words]) >> k & 1)
            pick = inverse == g
            bar.update(int(pick.sum()))
            if len(bands) * (m - len(lights_dropped) - 1) < 2:
                continue  # these bands cannot fix a normal: reported by _reasons
            gy, gx = ys[pick], xs[pick]
            kept = tuple(i for i in range(m) if i not in lights_dropped)
            result = capture.match(gy, gx, bands,
                                   tuple(int(v) for v in keys[g, words + 1:][list(bands)]),
                                   kept,
                                   grid_n=options.grid_n, threads=options.threads,
                                   sample_size=AUTO_N_SAMPLE)
            state.record(gy, gx, result, bands, keys[g, words], lights_dropped)
            state.dropped[gy, gx] = mask_words
            state.brighter[gy, gx] = mask_words  # clipped: brighter than recorded
    return state


def model_scale_pixels(mask: np.ndarray, step: int | None = None, first_row: int = 0
                       ) -> np.ndarray:
    """The masked pixels whose first residuals give the model scale.

    Every ``step``-th row and column, counted from row and column 0 of the
    whole scene; by default ``step`` = floor(sqrt(masked pixels /
    MODEL_SCALE_PIXELS)), at least 1 (every pixel of a scene of up to
    4 x MODEL_SCALE_PIXELS masked pixels).

    Parameters
    ----------
    mask : (H, W) ndarray of bool
        Pixels to solve (of the scene, or of a band of its rows).
    step : int, optional
        The whole scene's step, for a band of its rows.
    first_row : int, optional
        Row of the whole scene where ``mask`` begins.
    """
    if step is None:
        step = max(1, math.isqrt(int(np.count_nonzero(mask)) // MODEL_SCALE_PIXELS))
    picked = np.zeros(mask.shape, dtype=bool)
    picked[(-first_row) % step::step, ::step] = True
    return picked & mask


def measured_model_scale(residuals: np.ndarray) -> float:
    """The model scale of first-pass residuals: their RMS median, when above 1.

    The BRDF and light mismatch every pixel shares; 1 when the noise model
    explains the median pixel.
    """
    if residuals.size == 0:
        return 1.0
    return float(np.sqrt(max(1.0, np.median(residuals.astype(np.float32) ** 2))))


def _drop_clipped_lights(capture: Capture, ys, xs, valid, levels, options: Options):
    """Pixels that lose a band to a few clipped measurements keep the band and drop
    those lights instead (at most MAX_CLIPPED_FRACTION of them; at least MIN_LIGHTS
    remain; invalid values still make a band unusable). Returns their dropped-light
    masks, usable bands and levels."""
    m = capture.images
    unusable = capture.scene_clipped[ys, xs]
    count = light_masks.count(unusable)
    invalid = capture.scene_invalid[ys, xs]
    candidates = (count > 0) & (count <= MAX_CLIPPED_FRACTION * m) & \
        (m - count >= MIN_LIGHTS) & ~valid.all(axis=-1) & ~invalid
    dropped = light_masks.empty((len(ys),), m)
    if not candidates.any():
        return dropped, valid, levels
    pick = np.flatnonzero(candidates)
    kept = ~light_masks.to_bool(unusable[pick], m)  # (P', m)
    ov = capture.scene_ov[ys[pick], xs[pick]] * kept[:, None, :]
    norms = np.sqrt(np.einsum("...i,...i->...", ov, ov, dtype=np.float64))
    bands = norms > capture.min_norm
    enough = bands.sum(axis=-1) * (kept.sum(axis=-1) - 1) >= 2
    pick, bands = pick[enough], bands[enough]
    dropped[pick] = unusable[pick]
    valid = valid.copy()
    valid[pick] = bands
    levels = levels.copy()
    levels[pick] = 0
    return dropped, valid, levels


@dataclass
class _MatchState:
    """Per-pixel matches while they are being improved (mutable, private)."""

    row: np.ndarray
    quality: np.ndarray
    distance: np.ndarray
    bands_used: np.ndarray
    levels: np.ndarray
    dropped: np.ndarray
    brighter: np.ndarray
    groups: list
    totals: np.ndarray  # buckets, tests, seconds grid, seconds lookup

    @classmethod
    def empty(cls, h: int, w: int, n_bands: int, m: int) -> "_MatchState":
        return cls(row=np.full((h, w), -1, dtype=np.int64),
                   quality=np.full((h, w), np.nan, dtype=np.float32),
                   distance=np.full((h, w), np.nan, dtype=np.float32),
                   bands_used=np.zeros((h, w), dtype=np.uint8),
                   levels=np.zeros((h, w, n_bands), dtype=np.int8),
                   dropped=light_masks.empty((h, w), m),
                   brighter=light_masks.empty((h, w), m), groups=[],
                   totals=np.zeros(4))

    def record(self, ys, xs, result: GroupResult, bands, code, lights_dropped) -> None:
        """Keep a group's matches."""
        self.totals += (result.buckets, result.tests, result.seconds_grid,
                        result.seconds_lookup)
        self.groups.append(MatchGroup(tuple(int(k) for k in bands), result.table_size,
                                      result.grid_n, int(len(ys)), tuple(lights_dropped)))
        self.row[ys, xs] = result.rows
        self.quality[ys, xs] = result.residual
        self.distance[ys, xs] = result.distance
        self.bands_used[ys, xs] = code

    def result(self, model_scale: float) -> _Matches:
        b, d, t_grid, t_lookup = self.totals
        return _Matches(self.row, self.quality, self.distance, self.bands_used,
                        self.dropped, self.brighter, tuple(self.groups), model_scale,
                        b, d, t_grid, t_lookup)


def _light_subsets(capture: Capture, state: _MatchState, options: Options,
                   model_scale: float) -> None:
    """Re-match pixels far outside the noise without the lights that explain least.

    A pixel whose residual exceeds SUBSET_TRIGGER is matched again once per
    light it still uses, each time without that light (one table per light
    subset and band subset, built when first needed; tables of few pixels are
    brute force), and keeps the best of these when it lowers its residual.
    This repeats, greedily, up to ``max_dropped_lights`` times (at least
    MIN_LIGHTS lights remain); in the end a pixel keeps its subset match only
    if that lowered the residual to at most SUBSET_GAIN of the full match's.
    A dropped light is "darker" (cast shadow) or "brighter" (highlight,
    interreflection) than the final match predicts. Subset tables weigh a
    pixel's usable bands alike: with band weights too, the number of tables
    would multiply.
    """
    m, n_bands = capture.images, capture.bands
    bits = light_masks.single(m)
    words = bits.shape[1]
    before = dict(row=state.row.copy(), quality=state.quality.copy(),
                  distance=state.distance.copy(), dropped=state.dropped.copy(),
                  brighter=state.brighter.copy())
    for _ in range(options.max_dropped_lights):
        left = m - light_masks.count(state.dropped)
        candidates = (state.row >= 0) & (state.quality > SUBSET_TRIGGER) & \
            (left - 1 >= MIN_LIGHTS)
        if not candidates.any():
            break  # still check the gain and classify what earlier rounds dropped
        ys, xs = _tile_order(candidates)
        best_q = state.quality[ys, xs].copy()
        best_light = np.full(len(ys), -1)
        best_rows = np.full(len(ys), -1, dtype=np.int64)
        best_distance = np.zeros(len(ys), dtype=np.float32)
        dropped = state.dropped[ys, xs]
        codes = state.bands_used[ys, xs].astype(np.uint64)
        tried = _lights_to_try(capture, state, ys, xs)
        which_pixel, which_light = np.nonzero(tried)
        keys, inverse = _group_rows(
            np.column_stack([dropped[which_pixel] | bits[which_light], codes[which_pixel]]))
        order = np.argsort(-np.bincount(inverse), kind="stable")[:MAX_SUBSET_GROUPS]
        for g in order:
            pick = np.flatnonzero(inverse == g)
            pixels = which_pixel[pick]
            lights_kept = tuple(int(i) for i in
                                np.flatnonzero(~light_masks.to_bool(keys[g, :words], m)))
            band_tuple = tuple(k for k in range(n_bands) if int(keys[g, words]) >> k & 1)
            result = capture.match(ys[pixels], xs[pixels], band_tuple,
                                   (0,) * len(band_tuple), lights_kept, grid_n=options.grid_n,
                                   threads=options.threads, sample_size=AUTO_N_SAMPLE)
            state.totals += (result.buckets, result.tests, result.seconds_grid,
                             result.seconds_lookup)
            residual = result.residual / model_scale
            better = np.isfinite(residual) & (result.rows >= 0) & (residual < best_q[pixels])
            chosen = pixels[better]
            best_q[chosen] = residual[better]
            best_light[chosen] = which_light[pick][better]
            best_rows[chosen] = result.rows[better]
            best_distance[chosen] = result.distance[better]
        keep = best_light >= 0
        if not keep.any():
            break
        ky, kx, light = ys[keep], xs[keep], best_light[keep]
        state.row[ky, kx] = best_rows[keep]
        state.quality[ky, kx] = best_q[keep]
        state.distance[ky, kx] = best_distance[keep]
        state.dropped[ky, kx] |= bits[light]
    # Keep a subset match only where it explains the pixel clearly better.
    changed = (state.dropped != before["dropped"]).any(axis=-1)
    revert = changed & ~(state.quality <= SUBSET_GAIN * before["quality"])
    for name, value in before.items():
        getattr(state, name)[revert] = value[revert]
    ky, kx = np.nonzero((state.dropped != before["dropped"]).any(axis=-1))
    if not ky.size:
        return
    # Darker or brighter than the final match predicts?
    lights = ~light_masks.to_bool(state.dropped[ky, kx], m)
    band_mask = ((state.bands_used[ky, kx][:, None] >> np.arange(n_bands)) & 1) == 1
    z = light_residuals(capture.scene_ov[ky, kx],
                        capture.gauge_ov.reshape(-1, n_bands, m)[state.row[ky, kx]],
                        lights, band_mask, capture.model)
    state.brighter[ky, kx] = before["brighter"][ky, kx] | \
        light_masks.from_bool(~lights & (z > 0))
    for subset, count in zip(*np.unique(state.dropped[ky, kx], axis=0, return_counts=True)):
        state.groups.append(MatchGroup(tuple(range(n_bands)), 0, None, int(count),
                                       light_masks.lights(subset)))


def _lights_to_try(capture: Capture, state: "_MatchState", ys, xs) -> np.ndarray:
    """(P, m) bool: the lights each pixel tries to drop this round.

    Lights it still uses, at most MAX_LIGHTS_TRIED of them: the ones with the
    largest |per-light residual| against its current match.
    """
    m, n_bands = capture.images, capture.bands
    used = ~light_masks.to_bool(state.dropped[ys, xs], m)
    tried = used.copy()
    if m <= MAX_LIGHTS_TRIED or not len(ys):
        return tried
    band_mask = ((state.bands_used[ys, xs][:, None] >> np.arange(n_bands)) & 1) == 1
    z = light_residuals(capture.scene_ov[ys, xs],
                        capture.gauge_ov.reshape(-1, n_bands, m)[state.row[ys, xs]],
                        used, band_mask, capture.model)
    score = np.where(tried, np.abs(z), -np.inf)
    top = np.argpartition(-score, MAX_LIGHTS_TRIED - 1, axis=1)[:, :MAX_LIGHTS_TRIED]
    chosen = np.zeros_like(tried)
    np.put_along_axis(chosen, top, True, axis=1)
    return chosen & tried


def _tile_order(pixels: np.ndarray, tile: int = LOOKUP_TILE
                ) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices of the true ``pixels``, tile by tile.

    Tiles of ``tile`` x ``tile`` pixels in row-major order, pixels row-major
    within a tile (see :data:`LOOKUP_TILE`).
    """
    ys, xs = np.nonzero(pixels)  # row-major, which a stable sort keeps within tiles
    tiles_across = -(-pixels.shape[1] // tile)
    key = (ys // tile) * tiles_across + xs // tile
    if key.size and key.max() < 2 ** 16:
        key = key.astype(np.uint16)  # numpy sorts small integers by radix sort
    order = np.argsort(key, kind="stable")
    return ys[order], xs[order]


def _albedo(scene: np.ndarray, gauge_stack: np.ndarray, solved: np.ndarray,
            matches: "_Matches", offset: np.ndarray, gauge_albedo: np.ndarray,
            clip_level: float | None) -> np.ndarray:
    """(P, c) albedo of the solved pixels (method eq. 6, or least squares on the
    usable measurements), against the gauge at each refined position.

    See :func:`colorps._pixel_kernels.albedo`; a pixel's dropped lights are
    left out of its fit.
    """
    ys, xs = np.nonzero(solved)
    out = np.empty((len(ys), scene.shape[3]), dtype=np.float32)
    excluded = np.ascontiguousarray(light_masks.to_bool(matches.dropped[ys, xs],
                                                         scene.shape[0]))
    _pixel_kernels.albedo(scene, ys, xs, gauge_stack, matches.row[ys, xs],
                          np.ascontiguousarray(offset, dtype=np.float32), excluded,
                          np.inf if clip_level is None else float(clip_level),
                          np.asarray(gauge_albedo, dtype=np.float64), MIN_ALBEDO_ENERGY, out)
    return out


def _reasons(scene_sig: SignatureSet, mask: np.ndarray, solved: np.ndarray,
             matched: np.ndarray, dropped: np.ndarray) -> np.ndarray:
    """(H, W) uint8 :class:`Reason` codes; of several problems the larger code wins."""
    reason = np.full(mask.shape, Reason.SOLVED, dtype=np.uint8)
    reason[solved & ~light_masks.is_empty(dropped)] = Reason.SOLVED_FROM_LIGHT_SUBSET
    unsolved = mask & ~solved
    reason[unsolved & scene_sig.band_dark.any(axis=-1)] = Reason.TOO_DARK
    reason[unsolved & scene_sig.band_clipped.any(axis=-1)] = Reason.CLIPPED
    reason[unsolved & scene_sig.band_invalid_value.any(axis=-1)] = Reason.INVALID_VALUE
    reason[unsolved & matched] = Reason.NO_GOOD_MATCH
    reason[~mask] = Reason.BACKGROUND
    return reason


def _refine(capture: Capture, gauge: Gauge, gauge_sig: SignatureSet, matches: _Matches,
            solved: np.ndarray, options: Options):
    """Refine the solved pixels' normals, weighting each measurement by its noise."""
    ys, xs = np.nonzero(solved)
    return refine_normals(capture.scene_ov, capture.gauge_ov, gauge.normals,
                          gauge.mask & gauge_sig.valid, ys, xs, matches.row[ys, xs],
                          matches.bands_used[ys, xs], matches.dropped[ys, xs], capture.model,
                          capture.gauge_model or capture.model,
                          model_scale=matches.model_scale, threads=options.threads)


def _median(values: np.ndarray) -> float | None:
    finite = values[np.isfinite(values)]
    return float(np.median(finite)) if finite.size else None


def _percentile(values: np.ndarray, q: float) -> float | None:
    finite = values[np.isfinite(values)]
    return float(np.percentile(finite, q)) if finite.size else None


def _noise_model(gauge_stack: np.ndarray, gauge: Gauge, gauge_sig: SignatureSet,
                 options: Options, base: NoiseModel | None) -> NoiseModel:
    """The capture's noise model: the given read noise and gain, or the gauge's."""
    base = base or NoiseModel(read=0.0, gain=0.0)
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


def _dropped_histogram(dropped: np.ndarray) -> dict:
    counts = np.bincount(light_masks.count(dropped), minlength=1)
    return {str(k): int(v) for k, v in enumerate(counts)}


def _dropped_per_light(matches: _Matches, solved: np.ndarray, m: int) -> list:
    dropped = light_masks.to_bool(matches.dropped[solved], m)
    brighter = light_masks.to_bool(matches.brighter[solved], m)
    return [dict(light=i, darker=int((dropped[:, i] & ~brighter[:, i]).sum()),
                 brighter=int(brighter[:, i].sum())) for i in range(m)]
