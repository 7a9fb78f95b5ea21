"""Scene stack + gauge stack -> normals, per-band albedo and match quality.

For each scene pixel p the gauge pixel q with the nearest signature is found
with the exact bucket grid, then (eq. 6 of the paper)::

    n[p] = n[q]
    S*_k[p] = |S_k[p]| / |G_k[q]| * G*_k       for every band k

The signature (and so the normal) comes from the chosen mode: all bands in
colour mode, one band (luminance or a channel) in mono mode. The albedo is
always given for every band of the input, from that band's OV norms.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from ._checks import check_stack
from .errors import InputError
from .gauge import Gauge, parse_albedo
from .grid import BucketGrid
from .signatures import DEFAULT_MIN_NORM, compute_signatures, measurement_flags

__all__ = ["Reconstruction", "reconstruct", "REASONS", "MIN_IMAGES", "DEFAULT_MAX_DISTANCE",
           "GaugeWarning"]

#: Codes of the per-pixel ``reason`` map.
REASONS = {0: "solved", 1: "background", 2: "too dark", 3: "clipped", 4: "invalid value",
           5: "no good match"}
#: Fewest images each mode can work with.
MIN_IMAGES = {"mono": 3, "colour": 2}
#: Default largest match distance (per band, see ``quality``) of a solved pixel.
DEFAULT_MAX_DISTANCE = 0.1
_CHUNK = 1 << 18


class GaugeWarning(UserWarning):
    """The capture may not fix the normals (gauge losing pixels, too few images)."""


@dataclass
class Reconstruction:
    """Result of :func:`reconstruct`.

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
        Why a pixel is not solved; codes in :data:`REASONS`.
    bands_used : (H, W) ndarray of uint8
        Bit k set when band k of the signature was matched (colour mode falls
        back to the valid bands of a pixel).
    stats : dict
        Table size, grid N, mean buckets b and entries d per lookup, seconds
        per stage, pixels by reason, grids built per band subset.
    height : (H, W) ndarray or None
        Height map, when integrated (see :func:`colorps.integrate`).
    """

    normals: np.ndarray
    albedo: np.ndarray
    quality: np.ndarray
    solved: np.ndarray
    reason: np.ndarray
    bands_used: np.ndarray
    stats: dict = field(default_factory=dict)
    height: np.ndarray | None = None


def reconstruct(scene, gauge_stack, gauge: Gauge, *,
                mode: Literal["colour", "mono"] = "colour", mask=None,
                band: int | Literal["luminance"] | None = None, colourspace: str = "sRGB",
                grid_n: int | Literal["auto"] | None = None, threads: int | None = None,
                min_norm: float = DEFAULT_MIN_NORM, clip_level: float | None = None,
                max_distance: float | None = DEFAULT_MAX_DISTANCE,
                progress: bool = False) -> Reconstruction:
    """Recover normals and intrinsic colour of a scene from a gauge.

    Parameters
    ----------
    scene : (m, H, W, c) array_like
        Linear scene images, one per lighting condition.
    gauge_stack : (m, Hg, Wg, c) array_like
        Linear gauge images under the same m lighting conditions, same order.
    gauge : Gauge
        Normals, mask and albedo of the gauge (see :meth:`Gauge.from_sphere`).
    mode : {"colour", "mono"}, optional
        Signatures from all bands (colour) or from one band (mono).
    mask : (H, W) array_like of bool, optional
        Scene pixels to solve (default: all).
    band, colourspace : optional
        Mono mode band selection (see :func:`colorps.compute_signatures`).
    grid_n : int or "auto", optional
        Bucket grid size N (default ``round(2 sqrt(|T|))``; "auto" tunes it on a
        sample of the scene's signatures).
    threads : int, optional
        Threads for the lookup (default: all).
    min_norm : float, optional
        A band whose OV norm is at most this (linear units) is "too dark".
    clip_level : float, optional
        Measurements at or above this linear value are clipped (None: no
        clipping; the CLI derives it from the files' bit depth).
    max_distance : float or None, optional
        Pixels whose ``quality`` exceeds this are left unsolved as "no good
        match" (cast shadows, highlights, interreflections, background). None
        keeps every match.
    progress : bool, optional
        Show a progress bar.

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
    >>> result.normals.shape, result.albedo.shape, int(result.solved.sum()) == scene.mask.sum()
    ((64, 64, 3), (64, 64, 3), True)
    """
    t_start = time.perf_counter()
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
    if mode not in MIN_IMAGES:
        raise InputError(f"mode: expected 'colour' or 'mono', got {mode!r}")
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
                      stacklevel=2)
    if max_distance is not None and not max_distance > 0:
        raise InputError(f"max_distance: expected a value > 0 or None, got {max_distance!r}")
    if mask is None:
        mask = np.ones((h, w), dtype=bool)
    mask = np.asarray(mask)
    if mask.shape != (h, w):
        raise InputError(f"mask: shape {mask.shape} differs from the scene's {(h, w)}")
    mask = mask.astype(bool)
    gauge_albedo = parse_albedo(gauge.albedo, c)

    t0 = time.perf_counter()
    options = dict(band=band, colourspace=colourspace, min_norm=min_norm,
                   clip_level=clip_level)
    scene_sig = compute_signatures(scene, mode, **options)
    gauge_sig = compute_signatures(gauge_stack, mode, **options)
    n_bands = scene_sig.bands
    usable_gauge = (gauge.mask & gauge_sig.valid).sum() / gauge.mask.sum()
    if usable_gauge < 0.8:
        warnings.warn(f"only {usable_gauge:.0%} of the gauge pixels have every band usable "
                      "(clipped, too dark or invalid): check the gauge's exposure",
                      GaugeWarning, stacklevel=2)
    band_bits = 1 << np.arange(n_bands)
    scene_code = (scene_sig.band_valid * band_bits).sum(axis=-1)
    gauge_code = (gauge_sig.band_valid * band_bits).sum(axis=-1)
    t_signatures = time.perf_counter() - t0

    normals = np.full((h, w, 3), np.nan, dtype=np.float32)
    quality = np.full((h, w), np.nan, dtype=np.float32)
    match = np.full((h, w), -1, dtype=np.int64)  # flat index of the matched gauge pixel
    bands_used = np.zeros((h, w), dtype=np.uint8)
    grids, t_build, t_lookup = [], 0.0, 0.0
    buckets_total, tests_total = 0.0, 0.0
    for code in sorted(np.unique(scene_code[mask]), reverse=True):
        chosen = [k for k in range(n_bands) if code >> k & 1]
        pixels = mask & (scene_code == code)
        if len(chosen) * (m - 1) < 2:
            continue  # these bands cannot fix a normal: reported below
        table_px = gauge.mask & ((gauge_code & code) == code)
        if table_px.sum() < 3:
            continue
        cols = np.concatenate([np.arange(k * m, (k + 1) * m) for k in chosen])
        t0 = time.perf_counter()
        table = np.ascontiguousarray(gauge_sig.signatures[table_px][:, cols])
        ys, xs = _tile_order(pixels)
        queries = np.ascontiguousarray(scene_sig.signatures[ys, xs][:, cols])
        extra = {}
        if grid_n == "auto":
            extra["sample"] = queries[:: max(1, len(queries) // 4000)]
        grid = BucketGrid(table, grid_n, **extra)
        t_build += time.perf_counter() - t0
        t0 = time.perf_counter()
        rows, dist, b_sum, d_sum = _lookup(grid, queries, threads, progress,
                                           f"matching ({len(chosen)} band(s))")
        t_lookup += time.perf_counter() - t0
        buckets_total += b_sum
        tests_total += d_sum
        normals[ys, xs] = gauge.normals[table_px][rows]
        quality[ys, xs] = dist / np.sqrt(len(chosen))
        match[ys, xs] = np.flatnonzero(table_px)[rows]
        bands_used[pixels] = code
        grids.append(dict(bands=chosen, table_size=int(table.shape[0]), grid_n=grid.n,
                          pixels=int(ys.size)))

    matched = match >= 0
    solved = matched.copy()
    if max_distance is not None:
        solved &= quality <= max_distance
    normals[~solved] = np.nan
    albedo = np.full((h, w, c), np.nan, dtype=np.float32)
    albedo[solved] = _albedo(scene[:, solved], gauge_stack.reshape(m, -1, c)[:, match[solved]],
                             gauge_albedo, clip_level)

    # Why unsolved pixels are unsolved (worst problem of any band first).
    reason = np.zeros((h, w), dtype=np.uint8)
    dark = scene_sig.band_dark.any(axis=-1)
    clipped = scene_sig.band_clipped.any(axis=-1)
    invalid = scene_sig.band_invalid_value.any(axis=-1)
    unsolved = mask & ~solved
    reason[unsolved & dark] = 2
    reason[unsolved & clipped] = 3
    reason[unsolved & invalid] = 4
    reason[unsolved & matched] = 5
    reason[~mask] = 1
    counts = {REASONS[k]: int(np.count_nonzero(reason == k)) for k in REASONS}
    n_matched = int(matched.sum())
    full = (1 << n_bands) - 1
    stats = dict(
        images=m, bands=c, mode=mode, signature_dims=n_bands * m,
        table_size=int((gauge.mask & (gauge_code == full)).sum()),
        grid_n=grids[0]["grid_n"] if grids and grids[0]["bands"] == list(range(n_bands))
        else None,
        grids=grids,
        buckets_per_lookup=buckets_total / n_matched if n_matched else 0.0,
        tests_per_lookup=tests_total / n_matched if n_matched else 0.0,
        pixels=h * w, solved=int(solved.sum()),
        solved_from_band_subset=int((solved & (bands_used != full)).sum()),
        pixels_by_reason=counts, clip_level=clip_level, min_norm=min_norm,
        max_distance=max_distance,
        gauge_usable_fraction=float(usable_gauge),
        seconds=dict(signatures=t_signatures, grid=t_build, lookup=t_lookup,
                     total=time.perf_counter() - t_start),
    )
    return Reconstruction(normals, albedo, quality, solved, reason, bands_used, stats)


def _tile_order(pixels: np.ndarray, tile: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """Row and column indices of the true ``pixels``, tile by tile.

    Tiles of ``tile`` x ``tile`` pixels in row-major order, pixels row-major
    within a tile. Neighbouring pixels have similar normals and look up the same
    gauge entries, which then stay in the CPU's caches: on the Table 1 scene
    (1024-pixel rows) colour m = 30 lookups are ~18 % faster than row by row
    (docs/benchmarks.md).
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
        for a in range(0, len(queries), _CHUNK):
            part = slice(a, a + _CHUNK)
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
    lsq = np.where(used_energy >= 0.01 * energy, lsq, np.nan)
    ratio = np.where(all_usable, eq6, lsq)
    return (ratio * gauge_albedo).astype(np.float32)
