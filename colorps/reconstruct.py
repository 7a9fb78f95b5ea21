"""Scene stack + gauge stack -> normals, per-band albedo and match quality.

For each scene pixel p the gauge pixel q with the nearest signature is found
with the exact bucket grid, then (eq. 6 of the paper)::

    n[p] = n[q]
    S*_k[p] = |S_k[p]| / |G_k[q]| * G*_k       for every band k

The signature (and so the normal) comes from the chosen mode: all bands in
colour mode, one band (luminance or a channel) in mono mode. The albedo is
always given for every band of the input, from that band's OV norms.

:func:`reconstruct` runs five named steps: check the inputs, compute the
signatures, match every band subset (:func:`_match`), fit the albedo
(:func:`_albedo`), and say why unsolved pixels are unsolved (:func:`_reasons`).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from dataclasses import dataclass

import numpy as np

from ._checks import check_stack
from .errors import InputError
from .gauge import Gauge, parse_albedo
from .grid import BucketGrid
from .options import FLOAT_DARK_LEVEL, MIN_IMAGES, Options, dark_threshold
from .reasons import Reason, reason_counts
from .signatures import SignatureSet, compute_signatures, measurement_flags

__all__ = ["Reconstruction", "ReconstructionStats", "MatchGroup", "Timings", "reconstruct",
           "GaugeWarning"]

# ---------------------------------------------------------------- tuning
#: Queries per call of the grid (one progress-bar step); bounds the scratch memory.
LOOKUP_CHUNK = 1 << 18
#: Side (pixels) of the tiles in which pixels are looked up. Neighbouring pixels
#: look up the same gauge entries, which then stay in the CPU's caches: colour
#: m = 30 lookups are ~18 % faster than row by row (docs/benchmarks.md).
LOOKUP_TILE = 32
#: Queries ``grid_n="auto"`` times candidate grids on (a regular sample).
AUTO_N_SAMPLE = 4000
#: Below this fraction of usable gauge pixels a GaugeWarning is raised.
GAUGE_USABLE_WARNING = 0.8
#: A band subset needs at least this many usable gauge pixels to get a table.
MIN_TABLE_ENTRIES = 3
#: Least squares albedo (some measurements unusable) needs the usable ones to
#: carry at least this fraction of the gauge OV's energy; else NaN.
MIN_ALBEDO_ENERGY = 0.01


class GaugeWarning(UserWarning):
    """The capture may not fix the normals (gauge losing pixels, too few images)."""


@dataclass(frozen=True)
class MatchGroup:
    """One table and grid, built for the pixels whose usable bands are ``bands``.

    Attributes
    ----------
    bands : tuple of int
        Signature bands matched (all bands unless some were unusable).
    table_size : int
        Gauge entries in the table (gauge pixels with those bands usable).
    grid_n : int
        Grid size N of its bucket grid.
    pixels : int
        Scene pixels matched with it.
    """

    bands: tuple[int, ...]
    table_size: int
    grid_n: int
    pixels: int


@dataclass(frozen=True)
class Timings:
    """Seconds spent per stage (wall clock)."""

    signatures: float
    grid: float
    lookup: float
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
    pixels, solved, solved_from_band_subset : int
    pixels_by_reason : dict of str to int
        Keyed by :attr:`Reason.label`.
    clip_level : float or None
    dark_level : float
        Resolved levels (linear); ``dark_threshold`` = dark_level sqrt(m).
    dark_threshold : float
    max_distance : float or None
    gauge_usable_fraction : float
        Fraction of the gauge mask with every band usable.
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
    pixels_by_reason: dict
    clip_level: float | None
    dark_level: float
    dark_threshold: float
    max_distance: float | None
    gauge_usable_fraction: float
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
        Match distance per band: the Euclidean distance between the scene
        signature and the nearest gauge signature divided by sqrt(number of
        bands matched), so mono and colour values compare (0 = perfectly
        explained; 0.1 is about 6 degrees between the two OVs). NaN where no
        match was attempted.
    solved : (H, W) ndarray of bool
    reason : (H, W) ndarray of uint8
        Why a pixel is not solved: a :class:`~colorps.Reason` code.
    bands_used : (H, W) ndarray of uint8
        Bit k set when band k of the signature was matched (colour mode falls
        back to the valid bands of a pixel).
    stats : ReconstructionStats
    height : (H, W) ndarray or None
        Height map (pixels), when integrated: see :meth:`with_height`.
    """

    normals: np.ndarray
    albedo: np.ndarray
    quality: np.ndarray
    solved: np.ndarray
    reason: np.ndarray
    bands_used: np.ndarray
    stats: ReconstructionStats
    height: np.ndarray | None = None

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                value.flags.writeable = False

    def with_height(self, height: np.ndarray, seconds: float | None = None
                    ) -> "Reconstruction":
        """This result with a height map (and the seconds its integration took)."""
        timings = dataclasses.replace(self.stats.seconds, integration=seconds)
        stats = dataclasses.replace(self.stats, seconds=timings)
        return dataclasses.replace(self, height=np.asarray(height),
                                   stats=stats)


def reconstruct(scene, gauge_stack, gauge: Gauge, options: Options | None = None, *,
                mask=None, progress: bool = False, **changes) -> Reconstruction:
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

    t0 = time.perf_counter()
    min_norm = dark_threshold(options.dark_level, m)
    signature_options = dict(band=options.band, colourspace=options.colourspace,
                             min_norm=min_norm, clip_level=options.clip_level)
    scene_sig = compute_signatures(scene, options.mode, **signature_options)
    gauge_sig = compute_signatures(gauge_stack, options.mode, **signature_options)
    usable_gauge = float((gauge.mask & gauge_sig.valid).sum() / gauge.mask.sum())
    if usable_gauge < GAUGE_USABLE_WARNING:
        warnings.warn(f"only {usable_gauge:.0%} of the gauge pixels have every band usable "
                      "(clipped, too dark or invalid): check the gauge's exposure",
                      GaugeWarning, stacklevel=2)
    t_signatures = time.perf_counter() - t0

    matches = _match(scene_sig, gauge_sig, gauge, mask, options, progress)
    solved = matches.row >= 0
    if options.max_distance is not None:
        solved &= matches.quality <= options.max_distance
    normals = np.where(solved[..., None], matches.normals, np.float32(np.nan))
    albedo = np.full((h, w, c), np.nan, dtype=np.float32)
    albedo[solved] = _albedo(scene[:, solved],
                             gauge_stack.reshape(m, -1, c)[:, matches.row[solved]],
                             gauge_albedo, options.clip_level)
    reason = _reasons(scene_sig, mask, solved, matched=matches.row >= 0)

    n_bands = scene_sig.bands
    full = (1 << n_bands) - 1
    n_matched = int(np.count_nonzero(matches.row >= 0))
    full_grid = [g for g in matches.groups if g.bands == tuple(range(n_bands))]
    stats = ReconstructionStats(
        images=m, bands=c, mode=options.mode, signature_dims=n_bands * m,
        table_size=int((gauge.mask & gauge_sig.valid).sum()),
        grid_n=full_grid[0].grid_n if full_grid else None,
        grids=matches.groups,
        buckets_per_lookup=matches.buckets / n_matched if n_matched else 0.0,
        tests_per_lookup=matches.tests / n_matched if n_matched else 0.0,
        pixels=h * w, solved=int(solved.sum()),
        solved_from_band_subset=int((solved & (matches.bands_used != full)).sum()),
        pixels_by_reason=reason_counts(reason), clip_level=options.clip_level,
        dark_level=float(options.dark_level), dark_threshold=min_norm,
        max_distance=options.max_distance, gauge_usable_fraction=usable_gauge,
        seconds=Timings(signatures=t_signatures, grid=matches.seconds_grid,
                        lookup=matches.seconds_lookup,
                        total=time.perf_counter() - t_start),
    )
    return Reconstruction(normals, albedo, matches.quality, solved, reason,
                          matches.bands_used, stats)


# ---------------------------------------------------------------- steps
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
    """Nearest gauge entry of every scene pixel, over its usable bands."""

    normals: np.ndarray     # (H, W, 3) gauge normal of the match (NaN: none)
    quality: np.ndarray     # (H, W) distance per band (NaN: no match attempted)
    row: np.ndarray         # (H, W) flat gauge pixel index of the match, -1: none
    bands_used: np.ndarray  # (H, W) bit mask of the bands matched
    groups: tuple[MatchGroup, ...]
    buckets: float          # summed over lookups
    tests: float
    seconds_grid: float
    seconds_lookup: float


def _match(scene_sig: SignatureSet, gauge_sig: SignatureSet, gauge: Gauge, mask: np.ndarray,
           options: Options, progress: bool) -> _Matches:
    """Match every masked pixel with the gauge, one table per subset of usable bands.

    Pixels with every band usable are matched first, on the full signature;
    the others on the bands they have, when those still fix a normal
    (bands x (m - 1) >= 2) and the gauge has a table for them.
    """
    h, w = mask.shape
    m, n_bands = scene_sig.images, scene_sig.bands
    band_bits = 1 << np.arange(n_bands)
    scene_code = (scene_sig.band_valid * band_bits).sum(axis=-1)
    gauge_code = (gauge_sig.band_valid * band_bits).sum(axis=-1)
    normals = np.full((h, w, 3), np.nan, dtype=np.float32)
    quality = np.full((h, w), np.nan, dtype=np.float32)
    row = np.full((h, w), -1, dtype=np.int64)
    bands_used = np.zeros((h, w), dtype=np.uint8)
    groups, buckets, tests, t_grid, t_lookup = [], 0.0, 0.0, 0.0, 0.0
    for code in sorted(np.unique(scene_code[mask]), reverse=True):
        chosen = tuple(k for k in range(n_bands) if code >> k & 1)
        if len(chosen) * (m - 1) < 2:
            continue  # these bands cannot fix a normal: reported by _reasons
        table_px = gauge.mask & ((gauge_code & code) == code)
        if table_px.sum() < MIN_TABLE_ENTRIES:
            continue
        pixels = mask & (scene_code == code)
        cols = np.concatenate([np.arange(k * m, (k + 1) * m) for k in chosen])
        t0 = time.perf_counter()
        table = np.ascontiguousarray(gauge_sig.signatures[table_px][:, cols])
        ys, xs = _tile_order(pixels)
        queries = np.ascontiguousarray(scene_sig.signatures[ys, xs][:, cols])
        sample = queries[:: max(1, len(queries) // AUTO_N_SAMPLE)]
        grid = BucketGrid(table, options.grid_n,
                          sample=sample if options.grid_n == "auto" else None)
        t_grid += time.perf_counter() - t0
        t0 = time.perf_counter()
        rows, dist, b_sum, d_sum = _lookup(grid, queries, options.threads, progress,
                                           f"matching ({len(chosen)} band(s))")
        t_lookup += time.perf_counter() - t0
        buckets += b_sum
        tests += d_sum
        normals[ys, xs] = gauge.normals[table_px][rows]
        quality[ys, xs] = dist / np.sqrt(len(chosen))
        row[ys, xs] = np.flatnonzero(table_px)[rows]
        bands_used[pixels] = code
        groups.append(MatchGroup(chosen, int(table.shape[0]), grid.n, int(ys.size)))
    return _Matches(normals, quality, row, bands_used, tuple(groups), buckets, tests,
                    t_grid, t_lookup)


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


def _lookup(grid: BucketGrid, queries: np.ndarray, threads, progress: bool, label: str):
    """Query in chunks (progress bar); return rows, distances and summed b, d."""
    from tqdm.auto import tqdm

    rows = np.empty(len(queries), dtype=np.int64)
    dist = np.empty(len(queries), dtype=np.float32)
    b_sum = d_sum = 0.0
    with tqdm(total=len(queries), desc=label, unit="px", unit_scale=True,
              disable=not progress, leave=False) as bar:
        for a in range(0, len(queries), LOOKUP_CHUNK):
            part = slice(a, a + LOOKUP_CHUNK)
            rows[part], dist[part], st = grid.query(queries[part], threads=threads,
                                                    return_stats=True)
            b_sum += float(st.buckets_per_query.sum())
            d_sum += float(st.tests_per_query.sum())
            bar.update(len(rows[part]))
    return rows, dist, b_sum, d_sum


def _albedo(scene_ov: np.ndarray, gauge_ov: np.ndarray, gauge_albedo: np.ndarray,
            clip_level: float | None) -> np.ndarray:
    """Per-band albedo of matched pixels (eq. 6, or least squares on usable values).

    Parameters are (m, P, c) observation vectors of the scene pixels and of
    their matched gauge pixels, and the (c,) gauge albedo.
    """
    bad, clipped = measurement_flags(scene_ov, clip_level)
    usable = ~bad & ~clipped
    s = np.where(usable, scene_ov, 0.0).astype(np.float64)
    g = gauge_ov.astype(np.float64)
    all_usable = usable.all(axis=0)
    g_used = np.where(usable, g, 0.0)
    energy = (g * g).sum(axis=0)
    used_energy = (g_used * g_used).sum(axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):  # a black gauge band: NaN
        eq6 = np.sqrt((s * s).sum(axis=0)) / np.sqrt(energy)
        lsq = (s * g_used).sum(axis=0) / used_energy
    # Usable measurements that carry almost none of the light (e.g. every lit one
    # clipped) cannot fix the scale: NaN, not a guess.
    lsq = np.where(used_energy >= MIN_ALBEDO_ENERGY * energy, lsq, np.nan)
    ratio = np.where(all_usable, eq6, lsq)
    return (ratio * gauge_albedo).astype(np.float32)


def _reasons(scene_sig: SignatureSet, mask: np.ndarray, solved: np.ndarray,
             matched: np.ndarray) -> np.ndarray:
    """(H, W) uint8 :class:`Reason` codes; of several problems the larger code wins."""
    reason = np.full(mask.shape, Reason.SOLVED, dtype=np.uint8)
    unsolved = mask & ~solved
    reason[unsolved & scene_sig.band_dark.any(axis=-1)] = Reason.TOO_DARK
    reason[unsolved & scene_sig.band_clipped.any(axis=-1)] = Reason.CLIPPED
    reason[unsolved & scene_sig.band_invalid_value.any(axis=-1)] = Reason.INVALID_VALUE
    reason[unsolved & matched] = Reason.NO_GOOD_MATCH
    reason[~mask] = Reason.BACKGROUND
    return reason
