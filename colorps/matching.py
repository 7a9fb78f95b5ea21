"""The matching policy: which pixels are matched on which bands, weights and lights.

:func:`match_pixels` matches every masked pixel in groups that share one table
(:meth:`colorps.tables.Capture.match`): first on its usable bands with band
weights (and without its clipped lights), then, for pixels the match leaves
far outside the noise, without the lights that explain least (light subsets,
for cast shadows and highlights). The residuals are put on the capture's
model scale in between.

For a group with bands K, weights
2^l_k and lights L the table holds, for every gauge pixel with those bands
usable, the concatenation of 2^l_k g_k (g_k: band k's unit signature over L),
and a pixel's query is the same of its own signatures. The nearest entry is
the exact minimiser of the **weighted signature distance** ::

    D(p, q)^2 = sum over k in K of 4^l_k |s_k(p) - g_k(q)|^2

found by the bucket grid (or, for a group of a few pixels, by brute force:
both exact). The weights are powers of two of each band's signal-to-noise
ratio |S_k| / sigma_k relative to the pixel's best band; a band more than
``DROP_LEVEL`` octaves below is dropped when the others fix the normal
(:mod:`colorps.band_weights`).
"""

from __future__ import annotations

import math
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from . import light_masks
from ._config import AUTO_N_SAMPLE, MIN_LIGHTS
from .band_weights import band_weights
from .clipped_gauge import rematch_near_clipped
from .options import Options
from .residuals import light_residuals
from .shadows import solve_shadowed
from .tables import Capture, GroupResult, group_rows

__all__ = [
    "MatchGroup",
    "Matches",
    "first_match",
    "match_pixels",
    "measured_model_scale",
    "model_scale_pixels",
]

# ---------------------------------------------------------------- tuning
#: Side (pixels) of the tiles in which pixels are looked up. Neighbouring pixels
#: look up the same gauge entries, which then stay in the CPU's caches: colour
#: m = 30 lookups are ~18 % faster than row by row (docs/benchmarks.md).
LOOKUP_TILE = 32
#: A pixel with clipped measurements in at most this fraction of the images
#: keeps its bands and drops those images' lights instead.
MAX_CLIPPED_FRACTION = 0.5
#: Light subsets: pixels whose residual (noise units) exceeds SUBSET_TRIGGER are
#: re-matched without each of their lights in turn; the best is kept when its
#: residual is at most SUBSET_GAIN of the old one. At least MIN_LIGHTS lights
#: remain, and at most MAX_SUBSET_GROUPS tables are built per round (the
#: largest groups first).
SUBSET_TRIGGER = 3.0
#: Table-based light subsets run on captures of at most this many lights; every
#: capture then has each remaining pixel above SUBSET_TRIGGER matched on its own
#: lights (colorps.shadows). With few lights the tables single out one shadowed
#: light more surely; with many, they are too many and too slow (a 96-light
#: capture: 22.8 s against 2.1 s for the per-pixel fit alone, at 0.13 and 0.12
#: degrees; docs/benchmarks.md).
GREEDY_MAX_LIGHTS = 16
SUBSET_GAIN = 0.7
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
#: Groups whose tables and grids are made ahead, in threads, while the group
#: before them is looked up.
PREPARED_AHEAD = 2


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
class Matches:
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


def match_pixels(capture: Capture, mask: np.ndarray, options: Options, progress: bool,
                 model_scale: float | None = None, origin: tuple[int, int] = (0, 0)
                 ) -> Matches:
    """Match every masked pixel: one table per (bands, weights) group, then light subsets.

    Pixels with every band usable are matched on the full signature, the
    others on the bands they have when those still fix a normal (bands x
    (m - 1) >= 2). In colour mode with ``band_weights`` each band is weighted
    by its signal-to-noise ratio (:func:`colorps.band_weights.weight_levels`).
    With ``light_subsets``, pixels matched next to the gauge's clipped
    patches are matched again without those lights
    (:func:`colorps.clipped_gauge.rematch_near_clipped`, in
    :func:`first_match`). The residuals are then divided by the capture's
    model scale, and, with ``light_subsets``, pixels left far outside the
    noise are re-matched without their most deviant light
    (:func:`_light_subsets`). ``origin`` is
    the (row, column) of the whole scene where ``mask`` begins (the model
    scale's pixels are counted from the whole scene's corner).
    """
    state = first_match(capture, mask, options, progress)
    matched = state.row >= 0
    if model_scale is None:
        sampled = model_scale_pixels(mask, first_row=origin[0], first_col=origin[1])
        model_scale = measured_model_scale(state.quality[matched & sampled &
                                                         np.isfinite(state.quality)])
    state.quality[matched] /= model_scale
    if options.light_subsets and capture.images >= MIN_LIGHTS + 1:
        if capture.images <= GREEDY_MAX_LIGHTS:
            _light_subsets(capture, state, options, model_scale)
        solve_shadowed(capture, state, SUBSET_TRIGGER, model_scale)
    _match_clipped(capture, state, options, model_scale)
    return state.result(model_scale)


def first_match(capture: Capture, mask: np.ndarray, options: Options,
                 progress: bool) -> _MatchState:
    """Every masked pixel's match on its usable bands, before light subsets; the
    residuals are not yet divided by the model scale.

    With many lights (over GREEDY_MAX_LIGHTS) a pixel that loses a band to
    clipped measurements is matched on every light here, with an infinite
    residual: :func:`match_pixels` has the per-pixel fit (which leaves clipped
    lights out) solve it, and matches the few it cannot on their own clipped
    lights (:func:`_match_clipped`). One table per distinct set of clipped
    lights made 103 tables on DiLiGenT Ball (7.4 of its 10.4 s).

    With ``light_subsets``, pixels matched next to the gauge's clipped patches
    are matched again here, without those lights
    (:func:`colorps.clipped_gauge.rematch_near_clipped`): before the model scale
    is measured on these residuals, which the gauge's clipping would inflate.
    """
    h, w = mask.shape
    m, n_bands = capture.images, capture.bands
    ys, xs = _tile_order(mask)
    valid = capture.scene_valid[ys, xs]
    levels = np.zeros(valid.shape, dtype=np.int8)
    if options.band_weights and n_bands > 1:
        valid, levels = band_weights(capture.scene_ov, ys, xs, valid, capture.model)
    dropped = light_masks.empty((len(ys),), m)
    refit = np.zeros(len(ys), dtype=bool)
    if options.light_subsets:
        dropped, valid, levels = _drop_clipped_lights(capture, ys, xs, valid, levels)
        if m > GREEDY_MAX_LIGHTS:
            refit = ~light_masks.is_empty(dropped)
            dropped[refit] = 0
    state = _MatchState.empty(h, w, n_bands, m)
    state.levels[ys, xs] = levels
    _match_groups(capture, state, (ys, xs, valid, levels, dropped), options, progress)
    state.quality[ys[refit], xs[refit]] = np.inf  # matched on clipped values: refit
    if options.light_subsets:  # before the model scale, which a clipped gauge would inflate
        state.groups += [MatchGroup(*record) for record in
                         rematch_near_clipped(capture, state, options)]
    return state


def _match_groups(capture: Capture, state: _MatchState, pixels, options: Options,
                  progress: bool) -> None:
    """Match pixels (ys, xs, usable bands, levels, dropped-light masks) one table
    per group of the same dropped lights, bands and levels; record into ``state``."""
    from tqdm.auto import tqdm

    ys, xs, valid, levels, dropped = pixels
    m, n_bands = capture.images, capture.bands
    code = (valid * (1 << np.arange(n_bands))).sum(axis=-1)
    words = dropped.shape[1]
    # One int64 row per pixel: its light-mask words (bit for bit), bands, levels.
    keys, inverse = group_rows(np.column_stack([dropped.view(np.int64), code.astype(np.int64),
                                                 levels.astype(np.int64)]))
    sizes = np.bincount(inverse)
    order = np.argsort(-sizes, kind="stable")
    groups = []  # (group, bands, levels, band code, dropped-light words, dropped lights)
    for g in order:
        mask_words = keys[g, :words].view(np.uint64)
        lights_dropped = light_masks.lights(mask_words)
        bands = tuple(k for k in range(n_bands) if int(keys[g, words]) >> k & 1)
        if len(bands) * (m - len(lights_dropped) - 1) >= 2:  # else reported by _reasons
            groups.append((g, bands, tuple(int(v) for v in keys[g, words + 1:][list(bands)]),
                           keys[g, words], mask_words, lights_dropped))

    # Each group's pixels, in their tile order: one stable sort, not a pass per group.
    by_group = np.argsort(inverse.astype(np.uint16) if len(sizes) < 2 ** 16 else inverse,
                          kind="stable")
    ends = np.cumsum(sizes)

    def prepare(group):
        g, bands, group_levels, _, _, lights_dropped = group
        pick = by_group[ends[g] - sizes[g]:ends[g]]
        kept = tuple(i for i in range(m) if i not in lights_dropped)
        return capture.prepare(ys[pick], xs[pick], bands, group_levels, kept,
                               grid_n=options.grid_n, sample_size=AUTO_N_SAMPLE)

    with tqdm(total=len(ys), desc="matching", unit="px", unit_scale=True,
              disable=not progress, leave=False) as bar, \
            ThreadPoolExecutor(max_workers=PREPARED_AHEAD, initializer=_one_thread) as pool:
        # The next groups' tables and grids are made in the pool while this
        # group is looked up (both release the GIL): a grid was built on one
        # core between two lookups.
        ready = deque(pool.submit(prepare, group) for group in groups[:PREPARED_AHEAD])
        bar.update(len(ys) - sum(int(sizes[group[0]]) for group in groups))  # (not matched)
        for i, (_, bands, _, band_code, mask_words, lights_dropped) in enumerate(groups):
            prepared = ready.popleft().result()
            if i + PREPARED_AHEAD < len(groups):
                ready.append(pool.submit(prepare, groups[i + PREPARED_AHEAD]))
            result = capture.finish(prepared, threads=options.threads)
            bar.update(len(prepared.ys))
            gy, gx = prepared.ys, prepared.xs
            state.record(gy, gx, result, bands, band_code, lights_dropped)
            state.dropped[gy, gx] = mask_words
            state.brighter[gy, gx] = mask_words  # clipped: brighter than recorded


def _one_thread() -> None:
    """Numba's parallel loops in this thread run in it alone (the setting is per
    thread): groups made ready beside a lookup's threads would oversubscribe the
    cores."""
    import numba

    numba.set_num_threads(1)


def _match_clipped(capture: Capture, state: _MatchState, options: Options,
                   model_scale: float) -> None:
    """Pixels :func:`first_match` left to the per-pixel fit that it could not
    solve (an infinite residual still): matched on their own clipped lights,
    one table per set, as captures of few lights are."""
    ys, xs = np.nonzero(np.isinf(state.quality))
    if not len(ys):
        return
    valid = capture.scene_valid[ys, xs]
    levels = np.zeros(valid.shape, dtype=np.int8)
    dropped, valid, levels = _drop_clipped_lights(capture, ys, xs, valid, levels)
    state.row[ys, xs] = -1
    state.quality[ys, xs] = np.nan
    _match_groups(capture, state, (ys, xs, valid, levels, dropped), options, False)
    state.quality[ys, xs] /= model_scale


def model_scale_pixels(mask: np.ndarray, step: int | None = None, first_row: int = 0,
                       first_col: int = 0) -> np.ndarray:
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
    first_row, first_col : int, optional
        Row and column of the whole scene where ``mask`` begins.
    """
    if step is None:
        step = max(1, math.isqrt(int(np.count_nonzero(mask)) // MODEL_SCALE_PIXELS))
    picked = np.zeros(mask.shape, dtype=bool)
    picked[(-first_row) % step::step, (-first_col) % step::step] = True
    return picked & mask


def measured_model_scale(residuals: np.ndarray) -> float:
    """The model scale of first-pass residuals: their RMS median, when above 1.

    The BRDF and light mismatch every pixel shares; 1 when the noise model
    explains the median pixel.
    """
    if residuals.size == 0:
        return 1.0
    return float(np.sqrt(max(1.0, np.median(residuals.astype(np.float32) ** 2))))


def _drop_clipped_lights(capture: Capture, ys, xs, valid, levels):
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
    def empty(cls, h: int, w: int, n_bands: int, m: int) -> _MatchState:
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
                                      result.grid_n, len(ys), tuple(lights_dropped)))
        self.row[ys, xs] = result.rows
        self.quality[ys, xs] = result.residual
        self.distance[ys, xs] = result.distance
        self.bands_used[ys, xs] = code

    def result(self, model_scale: float) -> Matches:
        b, d, t_grid, t_lookup = self.totals
        return Matches(self.row, self.quality, self.distance, self.bands_used,
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
    before = dict(row=state.row.copy(), quality=state.quality.copy(),
                  distance=state.distance.copy(), dropped=state.dropped.copy(),
                  brighter=state.brighter.copy())
    for _ in range(options.max_dropped_lights):
        if not _drop_one_more(capture, state, options, model_scale):
            break  # still check the gain and classify what earlier rounds dropped
    # Keep a subset match only where it explains the pixel clearly better.
    changed = (state.dropped != before["dropped"]).any(axis=-1)
    revert = changed & ~(state.quality <= SUBSET_GAIN * before["quality"])
    for name, value in before.items():
        getattr(state, name)[revert] = value[revert]
    ky, kx = np.nonzero((state.dropped != before["dropped"]).any(axis=-1))
    if not ky.size:
        return
    # Darker or brighter than the final match predicts?
    m, n_bands = capture.images, capture.bands
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


def _drop_one_more(capture: Capture, state: _MatchState, options: Options,
                   model_scale: float) -> bool:
    """One round of light subsets: every pixel still far outside the noise tries
    its match without each light it may drop (:func:`_lights_to_try`) and keeps
    the best that lowers its residual. False when no pixel tried or gained."""
    m, n_bands = capture.images, capture.bands
    bits = light_masks.single(m)
    words = bits.shape[1]
    left = m - light_masks.count(state.dropped)
    candidates = (state.row >= 0) & (state.quality > SUBSET_TRIGGER) & \
        (left - 1 >= MIN_LIGHTS)
    if not candidates.any():
        return False
    ys, xs = _tile_order(candidates)
    best_q = state.quality[ys, xs].copy()
    best_light = np.full(len(ys), -1)
    best_rows = np.full(len(ys), -1, dtype=np.int64)
    best_distance = np.zeros(len(ys), dtype=np.float32)
    dropped = state.dropped[ys, xs]
    codes = state.bands_used[ys, xs].astype(np.uint64)
    which_pixel, which_light = np.nonzero(_lights_to_try(capture, state, ys, xs))
    keys, inverse = group_rows(
        np.column_stack([dropped[which_pixel] | bits[which_light], codes[which_pixel]]))
    for g in np.argsort(-np.bincount(inverse), kind="stable")[:MAX_SUBSET_GROUPS]:
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
        return False
    ky, kx, light = ys[keep], xs[keep], best_light[keep]
    state.row[ky, kx] = best_rows[keep]
    state.quality[ky, kx] = best_q[keep]
    state.distance[ky, kx] = best_distance[keep]
    state.dropped[ky, kx] |= bits[light]
    return True


def _lights_to_try(capture: Capture, state: _MatchState, ys, xs) -> np.ndarray:
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
