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
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from ._checks import check_stack
from .errors import InputError
from .gauge import Gauge, parse_albedo
from .grid import BucketGrid
from .signatures import DEFAULT_MIN_NORM, compute_signatures

__all__ = ["Reconstruction", "reconstruct", "REASONS", "MIN_IMAGES"]

#: Codes of the per-pixel ``reason`` map.
REASONS = {0: "solved", 1: "background", 2: "too dark", 3: "non-finite"}
#: Fewest images each mode can work with.
MIN_IMAGES = {"mono": 3, "colour": 2}
_CHUNK = 1 << 18


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
        NaN where not solved.
    quality : (H, W) ndarray of float32
        Match distance: Euclidean distance between the scene signature and the
        nearest gauge signature (0 = perfectly explained; a colour signature
        has c unit blocks, so distances reach up to 2 sqrt(c)). NaN where not
        solved.
    solved : (H, W) ndarray of bool
    reason : (H, W) ndarray of uint8
        Why a pixel is not solved; codes in :data:`REASONS`.
    stats : dict
        Table size, grid N, mean buckets b and entries d per lookup, seconds
        per stage, unsolved counts by reason.
    height : (H, W) ndarray or None
        Height map, when integrated (see :func:`colorps.integrate`).
    """

    normals: np.ndarray
    albedo: np.ndarray
    quality: np.ndarray
    solved: np.ndarray
    reason: np.ndarray
    stats: dict = field(default_factory=dict)
    height: np.ndarray | None = None


def reconstruct(scene, gauge_stack, gauge: Gauge, *,
                mode: Literal["colour", "mono"] = "colour", mask=None,
                band: int | Literal["luminance"] | None = None, colourspace: str = "sRGB",
                grid_n: int | Literal["auto"] | None = None, threads: int | None = None,
                min_norm: float = DEFAULT_MIN_NORM, progress: bool = False) -> Reconstruction:
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
        OVs with a smaller norm (linear units) are "too dark" to solve.
    progress : bool, optional
        Show a progress bar.

    Returns
    -------
    Reconstruction

    Examples
    --------
    >>> from colorps import Gauge, reconstruct, synth
    >>> lights = synth.ring_lights(6, 45)
    >>> scene = synth.smiley_surface(64)
    >>> ball = synth.sphere_surface(101, 48)
    >>> result = reconstruct(synth.render(scene, lights), synth.render(ball, lights),
    ...                      Gauge.from_sphere((101, 101), 50, 50, 48))
    >>> result.normals.shape, result.albedo.shape
    ((64, 64, 3), (64, 64, 3))
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
    if mask is None:
        mask = np.ones((h, w), dtype=bool)
    mask = np.asarray(mask)
    if mask.shape != (h, w):
        raise InputError(f"mask: shape {mask.shape} differs from the scene's {(h, w)}")
    mask = mask.astype(bool)
    gauge_albedo = parse_albedo(gauge.albedo, c)

    # Signatures: scene and gauge, in the chosen mode, and per-band norms for eq. 6.
    t0 = time.perf_counter()
    options = dict(band=band, colourspace=colourspace, min_norm=min_norm)
    scene_sig = compute_signatures(scene, mode, **options)
    gauge_sig = compute_signatures(gauge_stack, mode, **options)
    gauge_bands = compute_signatures(gauge_stack, "colour", min_norm=min_norm)
    in_table = gauge.mask & gauge_sig.valid
    if in_table.sum() < 3:
        raise InputError("gauge: fewer than 3 usable gauge pixels (is the gauge lit and "
                         "inside the sphere mask?)")
    table = gauge_sig.signatures[in_table]
    table_normals = gauge.normals[in_table]
    table_norms = gauge_bands.norms[in_table]  # (K, c)
    finite = np.isfinite(scene).all(axis=(0, 3))
    todo = mask & scene_sig.valid
    t_signatures = time.perf_counter() - t0

    t0 = time.perf_counter()
    queries = scene_sig.signatures[todo]
    grid_options = {}
    if grid_n == "auto":
        grid_options["sample"] = queries[:: max(1, len(queries) // 4000)] if len(queries) else None
    grid = BucketGrid(table, grid_n, **grid_options)
    t_build = time.perf_counter() - t0

    t0 = time.perf_counter()
    rows = np.empty(len(queries), dtype=np.int64)
    dist = np.empty(len(queries), dtype=np.float32)
    buckets = np.zeros(len(queries), dtype=np.int32)
    tests = np.zeros(len(queries), dtype=np.int32)
    from tqdm.auto import tqdm

    with tqdm(total=len(queries), desc="matching", unit="px", unit_scale=True,
              disable=not progress, leave=False) as bar:
        for a in range(0, len(queries), _CHUNK):
            part = slice(a, a + _CHUNK)
            rows[part], dist[part], st = grid.query(queries[part], threads=threads,
                                                    return_stats=True)
            buckets[part], tests[part] = st.buckets_per_query, st.tests_per_query
            bar.update(len(rows[part]))
    t_lookup = time.perf_counter() - t0

    normals = np.full((h, w, 3), np.nan, dtype=np.float32)
    albedo = np.full((h, w, c), np.nan, dtype=np.float32)
    quality = np.full((h, w), np.nan, dtype=np.float32)
    normals[todo] = table_normals[rows]
    with np.errstate(divide="ignore", invalid="ignore"):
        albedo[todo] = (_band_norms(scene_sig, scene, min_norm)[todo]
                        / table_norms[rows] * gauge_albedo)
    quality[todo] = dist

    reason = np.zeros((h, w), dtype=np.uint8)
    reason[~finite] = 3
    reason[finite & ~scene_sig.valid] = 2
    reason[~mask] = 1
    counts = {REASONS[k]: int(np.count_nonzero(reason == k)) for k in REASONS}
    stats = dict(
        images=m, bands=c, mode=mode, table_size=int(table.shape[0]), grid_n=grid.n,
        signature_dims=int(table.shape[1]),
        buckets_per_lookup=float(buckets.mean()) if len(buckets) else 0.0,
        tests_per_lookup=float(tests.mean()) if len(tests) else 0.0,
        pixels=h * w, solved=int(todo.sum()), unsolved_by_reason=counts,
        seconds=dict(signatures=t_signatures, grid=t_build, lookup=t_lookup,
                     total=time.perf_counter() - t_start),
    )
    return Reconstruction(normals, albedo, quality, todo, reason, stats)


def _band_norms(sig, scene: np.ndarray, min_norm: float) -> np.ndarray:
    """Per-band OV norms of every input band (mono signatures keep only one)."""
    if sig.mode == "colour":
        return sig.norms
    return compute_signatures(scene, "colour", min_norm=min_norm).norms
