"""Captures in tiles: bands of rows reconstructed apart, in this process or on Dask.

A tile is a band of whole rows of the scene. Every scene pixel's result
depends on the gauge, the noise model and the capture's **model scale** only
(:mod:`colorps.residuals`), so tiles can be solved independently once the
scale is known. A tiled run therefore has two passes:

1. each tile's first residuals (:func:`colorps.reconstruct.first_residuals`)
   at the pixels the scale is measured on
   (:func:`colorps.reconstruct.model_scale_pixels`: at most about 2^16 of
   them, so this pass costs little more than reading the tiles), gathered
   into the capture's model scale
   (:func:`colorps.reconstruct.measured_model_scale`);
2. each tile's :func:`colorps.reconstruct` with that scale.

The normals, albedo, quality, uncertainty and reason maps are then the same
as those of one untiled run (tests check it); the statistics are combined.
Only one tile's stack is in memory per worker at a time when the scene is a
:class:`StackFiles` (read row by row from the files).

On a cluster, pass a ``dask.distributed.Client``: the gauge is scattered to
every worker once, and tiles run as tasks (``pip install "colorps[dask]"``).

One limit of the equivalence: a round of light subsets builds at most
``MAX_SUBSET_GROUPS`` tables (the largest groups of its pixels); a tile whose
pixels need other tables than the whole image's largest ones may try them.
Below that many distinct (dropped lights, bands) combinations per round, which
covers captures with up to about 16 lights, results are identical.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError
from .figures import overview_step
from .gauge import Gauge
from .matching import TABLE_CACHE_MIB, GaugeTables
from .noise import NoiseModel
from .options import AUTO_MEMORY_FRACTION, Options
from .reconstruct import (LowSolvedWarning, Reconstruction, Timings, _median, _percentile,
                          first_residuals, low_solved_message, measured_model_scale,
                          model_scale_pixels, reconstruct)

__all__ = ["StackFiles", "tile_rows", "reconstruct_tiled", "rows_for_memory",
           "memory_limit", "available_memory_bytes", "cgroup_available_bytes",
           "DEFAULT_TILE_ROWS"]

#: Rows per tile when none are given: about 64 MiB of float32 per tile for 8 RGB
#: images of 4096 columns.
DEFAULT_TILE_ROWS = 256

# ---------------------------------------------------------------- memory model
#: Peak memory of a tiled run, measured at 4 and 16 MP (2026-12-02): BASE_MIB
#: for the interpreter, libraries and gauge; while the tiles run, MAP_BYTES per
#: scene pixel for the maps and preview gathered so far, plus TILE_FIXED_MIB and
#: WORKING_BYTES per byte of the tile's float32 input (6.2 measured; 8 leaves a
#: margin); after them FINISH_BYTES per pixel for the integration and the files
#: written (102 measured). A tile has at least MIN_TILE_ROWS rows. An untiled run
#: is the same with the whole scene as its one tile. The grids kept for the
#: tiles (matching.TABLE_CACHE_MIB) come on top while the tiles run.
BASE_MIB = 250
MAP_BYTES = 60
TILE_FIXED_MIB = 300
WORKING_BYTES = 8.0
FINISH_BYTES = 110
MIN_TILE_ROWS = 16


#: Where Linux mounts the control groups whose memory limits a container or a
#: cluster job (Docker, Kubernetes, SLURM) runs under; /proc/meminfo, which
#: psutil reads, knows nothing of them.
CGROUP_ROOT = Path("/sys/fs/cgroup")
#: A cgroup v1 memory limit at or above this many bytes means "no limit".
CGROUP_UNLIMITED = 2 ** 60


def available_memory_bytes() -> int:
    """Memory this process can use now, in bytes.

    The least of: the system's available memory
    (``psutil.virtual_memory().available``: free memory plus caches the system
    can drop), what the control groups the process runs in leave it
    (:func:`cgroup_available_bytes`: a container's or a cluster job's memory
    limit), and inside a Dask worker the worker's own memory limit.
    """
    import sys

    import psutil

    available = psutil.virtual_memory().available
    in_cgroup = cgroup_available_bytes()
    if in_cgroup is not None:
        available = min(available, in_cgroup)
    if "distributed" in sys.modules:  # only a process that uses Dask can be a worker
        from distributed import get_worker

        try:
            worker_limit = get_worker().memory_manager.memory_limit
        except ValueError:  # not in a worker
            worker_limit = None
        if worker_limit:
            available = min(available, int(worker_limit))
    return int(available)


def cgroup_available_bytes(root: Path = CGROUP_ROOT,
                           membership: str | None = None) -> int | None:
    """What the memory limits of this process's control groups leave it, in bytes.

    For the process's cgroup and each of its ancestors that sets a memory
    limit: the limit, less the memory charged to the group, plus the group's
    file cache other than shared memory (which the kernel reclaims before it
    kills, and which psutil's figure counts as available too). The least
    of them; None where no group sets a limit, or on systems without cgroups.

    Parameters
    ----------
    root : Path
        Mount point of the cgroup file systems: cgroup v2 unified at ``root``,
        v1's memory controller at ``root/memory``.
    membership : str, optional
        The text of ``/proc/self/cgroup`` (read from there when None).
    """
    try:
        if membership is None:
            membership = Path("/proc/self/cgroup").read_text()
    except OSError:
        return None
    found = []
    for line in membership.splitlines():
        number, _, rest = line.partition(":")
        controllers, _, group = rest.partition(":")
        if number == "0" and controllers == "":  # cgroup v2
            files = root, "memory.max", "memory.current", ("file", "shmem")
        elif "memory" in controllers.split(","):  # cgroup v1
            files = root / "memory", "memory.limit_in_bytes", "memory.usage_in_bytes", \
                ("total_cache", "total_shmem")
        else:
            continue
        left = _cgroup_tree_available(*files, group.strip().lstrip("/"))
        if left is not None:
            found.append(left)
    return min(found) if found else None


def _cgroup_tree_available(mount: Path, limit_file: str, usage_file: str,
                           cache_keys: tuple[str, str], group: str) -> int | None:
    """The least memory left by the limits of ``group`` and its ancestors under
    ``mount``. Inside a container the group path names the host's hierarchy,
    which the container sees as its ``mount``: then the mount itself is read."""
    folder = mount / group if group and (mount / group).is_dir() else mount
    least = None
    while True:
        try:
            text = (folder / limit_file).read_text().strip()
            limit = None if text == "max" else int(text)
            if limit is not None and limit < CGROUP_UNLIMITED:
                usage = int((folder / usage_file).read_text())
                stat = dict(row.split(" ", 1) for row in
                            (folder / "memory.stat").read_text().splitlines() if " " in row)
                cache, shared = (int(stat.get(key, 0)) for key in cache_keys)
                left = max(limit - usage + max(cache - shared, 0), 0)
                least = left if least is None else min(least, left)
        except (OSError, ValueError):
            pass
        if folder == mount or mount not in folder.parents:
            return least
        folder = folder.parent


def memory_limit(setting: float | str | None) -> tuple[float | None, str]:
    """The memory limit in GiB that ``Options.memory_limit_gib`` means now.

    Returns
    -------
    limit_gib : float or None
        The number given; for "auto", ``AUTO_MEMORY_FRACTION`` of
        :func:`available_memory_bytes`; None for no limit.
    source : str
        How an error message names the limit (``--memory-limit 2 GiB``, or
        the automatic limit with the memory it was taken from).
    """
    if setting is None:
        return None, "no memory limit"
    if setting == "auto":
        available = available_memory_bytes() / 2 ** 30
        limit = AUTO_MEMORY_FRACTION * available
        return limit, (f"--memory-limit auto ({limit:.1f} GiB: {AUTO_MEMORY_FRACTION:.0%} of "
                       f"the {available:.1f} GiB available)")
    return float(setting), f"--memory-limit {setting:g} GiB"


def rows_for_memory(limit_gib: float, shape: tuple[int, int, int, int], *,
                    source: str | None = None) -> int | None:
    """Rows per tile that keep a run of an (m, H, W, c) scene under ``limit_gib``.

    Returns
    -------
    int or None
        None when the whole scene fits untiled.

    Raises
    ------
    InputError
        When even MIN_TILE_ROWS rows would not fit, saying how much is needed
        (and naming the limit as ``source``, default ``--memory-limit ...``).
    """
    source = source or f"--memory-limit {limit_gib:g} GiB"
    m, h, w, c = shape
    mib = 2 ** 20
    limit = limit_gib * 2 ** 30
    finish = BASE_MIB * mib + FINISH_BYTES * h * w
    budget = limit - (BASE_MIB + TILE_FIXED_MIB + TABLE_CACHE_MIB) * mib - MAP_BYTES * h * w
    row_bytes = WORKING_BYTES * 4 * m * c * w
    if finish <= limit and budget >= row_bytes * h:
        return None
    rows = int(budget // row_bytes) if budget > 0 else 0
    if finish > limit or rows < MIN_TILE_ROWS:
        need = max(finish, limit - budget + row_bytes * MIN_TILE_ROWS) / 2 ** 30
        raise InputError(f"{source}: a {w}x{h} capture of {m} "
                         f"images needs about {need:.1f} GiB even in tiles of "
                         f"{MIN_TILE_ROWS} rows (its whole-image maps, height "
                         f"integration and outputs take {finish / 2 ** 30:.1f} GiB)")
    return rows


@dataclass(frozen=True)
class StackFiles:
    """A scene stack left in its files, read a band of rows at a time.

    ``stack[:, start:stop]`` (the only indexing a tiled run needs) reads those
    rows of every image (:func:`colorps.io.read_stack` with ``rows``); it is
    small to send to a Dask worker, which reads its own tiles.
    """

    paths: tuple[Path, ...]
    shape: tuple[int, int, int, int]  # (m, H, W, c)
    encoding: str = "auto"
    name: str = "scene"

    def __getitem__(self, key) -> np.ndarray:
        from .io import read_stack

        if not (isinstance(key, tuple) and len(key) == 2 and key[0] == slice(None)
                and isinstance(key[1], slice) and key[1].step in (None, 1)):
            raise TypeError("StackFiles supports stack[:, start:stop] only")
        start, stop, _ = key[1].indices(self.shape[1])
        return read_stack(self.paths, self.encoding, name=self.name, rows=(start, stop))[0]


def tile_rows(height: int, tile: int) -> list[tuple[int, int]]:
    """(start, stop) row ranges of ``tile`` rows covering ``height`` rows."""
    if tile < 1:
        raise InputError(f"tile: expected at least 1 row, got {tile}")
    return [(start, min(start + tile, height)) for start in range(0, height, tile)]


def _first_task(scene, rows, tile_mask, gauge_stack, gauge, *, options, noise, gauge_noise,
                gauge_levels, tables):
    """A tile's first residuals; ``scene[:, rows]`` is the tile, ``tile_mask`` the
    pixels to match (only its rows with any are processed: each pixel's
    residual is its own)."""
    keep = tile_mask.any(axis=1)
    if not keep.any():
        return np.zeros(0, dtype=np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the whole run reports, once
        return first_residuals(scene[:, rows[0]:rows[1]][:, keep], gauge_stack, gauge,
                               options, mask=tile_mask[keep], noise=noise,
                               gauge_noise=gauge_noise, gauge_levels=gauge_levels,
                               tables=tables)


def _tile_task(scene, rows, tile_mask, gauge_stack, gauge, *, options, noise, gauge_noise,
               gauge_levels, tables, model_scale):
    """A tile's reconstruction, the warnings it raised (but low-solved ones), and
    its mean image at the rows and columns the overview draws (the preview)."""
    piece = scene[:, rows[0]:rows[1]]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = reconstruct(piece, gauge_stack, gauge, options,
                             mask=tile_mask, noise=noise, gauge_noise=gauge_noise,
                             gauge_levels=gauge_levels, model_scale=model_scale,
                             tables=tables)
    said = [(w.category, str(w.message)) for w in caught
            if not issubclass(w.category, LowSolvedWarning)]
    step = overview_step(scene.shape[1:3])
    drawn = piece[:, (-rows[0]) % step::step, ::step]
    return result, said, np.asarray(drawn, dtype=np.float32).mean(axis=0)


def reconstruct_tiled(scene, gauge_stack, gauge: Gauge, options: Options | None = None, *,
                      tile: int = DEFAULT_TILE_ROWS, mask=None,
                      noise: NoiseModel | None = None, gauge_noise: NoiseModel | None = None,
                      gauge_levels: tuple[float | None, float] | None = None,
                      client=None, progress: bool = False, return_preview: bool = False):
    """:func:`colorps.reconstruct`, a band of ``tile`` rows at a time.

    Parameters
    ----------
    scene : (m, H, W, c) ndarray or StackFiles
        The scene stack, in memory or left in its files.
    tile : int, optional
        Rows per tile.
    client : dask.distributed.Client, optional
        Run the tiles as tasks on this cluster (the gauge is scattered to every
        worker once). Default: one after the other in this process.
    progress : bool, optional
        A progress bar over tiles (Dask's own with a client).
    return_preview : bool, optional
        Also return the scene's mean image at the pixels the overview draws
        (every s-th row and column, s = :func:`colorps.figures.overview_step`),
        float32, made from the tiles as they are read (the files are not read
        again for it).
    gauge_stack, gauge, options, mask, noise, gauge_noise, gauge_levels
        As for :func:`colorps.reconstruct`.

    Returns
    -------
    Reconstruction, or (Reconstruction, ndarray) with ``return_preview``
        The same maps as an untiled run; statistics combined over the tiles.

    Examples
    --------
    >>> import numpy as np
    >>> from colorps import Gauge, reconstruct, synth
    >>> from colorps.tiles import reconstruct_tiled
    >>> lights = synth.ring_lights(6, 45)
    >>> scene = synth.smiley_surface(64)
    >>> ball = synth.sphere_surface(101, 48)
    >>> stack, gauge_stack = synth.render(scene, lights), synth.render(ball, lights)
    >>> gauge = Gauge.from_sphere((101, 101), 50, 50, 48)
    >>> whole = reconstruct(stack, gauge_stack, gauge, mask=scene.mask)
    >>> tiled = reconstruct_tiled(stack, gauge_stack, gauge, tile=16, mask=scene.mask)
    >>> bool(np.array_equal(whole.normals, tiled.normals, equal_nan=True))
    True
    """
    t_start = time.perf_counter()
    options = options or Options()
    m, h, w, c = scene.shape
    mask = None if mask is None else np.asarray(mask, dtype=bool)
    if mask is not None and mask.shape != (h, w):
        raise InputError(f"mask: shape {mask.shape} differs from the scene's {(h, w)}")
    ranges = tile_rows(h, tile)
    masks = [None if mask is None else mask[a:b] for a, b in ranges]
    # One GaugeTables for every tile: each table's grid is built once (per worker).
    shared = dict(options=options, noise=noise, gauge_noise=gauge_noise,
                  gauge_levels=gauge_levels, tables=GaugeTables())
    run = _in_process if client is None else _on_dask
    # The first pass matches only the pixels the model scale is measured on.
    whole = mask if mask is not None else np.ones((h, w), dtype=bool)
    sampled = model_scale_pixels(whole)
    residuals = []
    run(client, _first_task, scene, ranges, [sampled[a:b] for a, b in ranges], gauge_stack,
        gauge, shared, progress, "first matches", lambda k, found: residuals.append(found))
    model_scale = measured_model_scale(np.concatenate(residuals))
    joined = _Joined(h, overview_step((h, w)) if return_preview else None)
    run(client, _tile_task, scene, ranges, masks, gauge_stack, gauge,
        dict(shared, model_scale=model_scale), progress, "tiles",
        lambda k, outcome: joined.add(k, ranges[k], *outcome))
    del shared  # the grids kept for the tiles
    result = _stitch(joined, mask if mask is not None else np.ones((h, w), bool),
                     time.perf_counter() - t_start)
    release_freed_memory()
    return (result, joined.preview) if return_preview else result


class _Joined:
    """The whole-image maps, filled in as tiles finish (in any order); each
    tile's maps are let go once copied, so they are never held twice."""

    def __init__(self, height: int, preview_step: int | None) -> None:
        self.height = height
        self.maps: dict[str, np.ndarray] = {}
        self.stats: dict[int, object] = {}
        self.said: dict[int, list] = {}
        self.matched: dict[int, int] = {}
        self.preview_step = preview_step
        self.preview = None

    def add(self, k: int, rows: tuple[int, int], result: Reconstruction, said, mean) -> None:
        for name in _MAPS:
            piece = getattr(result, name)
            if name not in self.maps:
                self.maps[name] = np.empty((self.height,) + piece.shape[1:], piece.dtype)
            self.maps[name][rows[0]:rows[1]] = piece
        if self.preview_step is not None:
            step = self.preview_step
            if self.preview is None:
                self.preview = np.empty((-(-self.height // step),) + mean.shape[1:],
                                        np.float32)
            first = -(-rows[0] // step)  # the first drawn row in this tile
            self.preview[first:first + len(mean)] = mean
        self.stats[k] = result.stats
        self.said[k] = said
        self.matched[k] = int(np.isfinite(result.quality).sum())


#: The maps of a Reconstruction a tiled run joins, in its field order.
_MAPS = ("normals", "albedo", "quality", "uncertainty", "solved", "reason", "bands_used",
         "dropped_lights")


def _in_process(client, task, scene, ranges, masks, gauge_stack, gauge, shared, progress,
                what, collect):
    """Run ``task`` on each tile in turn, handing ``collect(k, outcome)`` each outcome."""
    from tqdm.auto import tqdm

    for k, (rows, tile_mask) in enumerate(tqdm(list(zip(ranges, masks)), desc=what,
                                               disable=not progress, leave=False)):
        collect(k, task(scene, rows, tile_mask, gauge_stack, gauge, **shared))
        release_freed_memory()  # the tile's temporaries, before the next tile's


def release_freed_memory() -> None:
    """Give memory that numpy has freed back to the system (glibc ``malloc_trim``).

    glibc keeps freed blocks of a few MiB on its heap for reuse: after a tile's
    temporaries are freed the process stays that much larger (57 bytes per
    pixel of a 4 MP run, measured). A no-op where the C library has no
    ``malloc_trim``.
    """
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _on_dask(client, task, scene, ranges, masks, gauge_stack, gauge, shared, progress, what,
             collect):
    """Run ``task`` on each tile as a Dask task; ``collect(k, outcome)`` as each ends."""
    from dask.distributed import as_completed
    from dask.distributed import progress as dask_progress

    gauge_stack, gauge, tables = client.scatter(
        [np.ascontiguousarray(gauge_stack), gauge, shared["tables"]], broadcast=True,
        hash=False)
    shared = dict(shared, tables=tables)
    futures = {}
    for k, (rows, tile_mask) in enumerate(zip(ranges, masks)):
        piece, piece_rows = scene, rows  # files: the worker reads its own rows
        if isinstance(scene, np.ndarray):  # in memory: each tile is sent on its own
            piece, piece_rows = scene[:, rows[0]:rows[1]], (0, rows[1] - rows[0])
        futures[client.submit(task, piece, piece_rows, tile_mask, gauge_stack, gauge,
                              **shared, pure=False)] = k
    if progress:
        dask_progress(list(futures))
    for future, outcome in as_completed(list(futures), with_results=True):
        collect(futures.pop(future), outcome)
        future.release()


def _stitch(joined: _Joined, mask, seconds) -> Reconstruction:
    """One Reconstruction from the joined maps, statistics combined over the tiles
    (top to bottom)."""
    order = sorted(joined.stats)
    tile_stats = [joined.stats[k] for k in order]
    n_matched = [joined.matched[k] for k in order]
    said = list(dict.fromkeys(s for k in order for s in joined.said[k]))
    normals, albedo, quality, uncertainty, solved, reason, bands_used, dropped = (
        joined.maps.pop(name) for name in _MAPS)
    first = tile_stats[0]
    matched = np.isfinite(quality)

    def total(name):
        return sum(getattr(t, name) for t in tile_stats)

    def counts(name):  # summed dicts, keys in the first tile's order, zeros kept
        out = {}
        for t in tile_stats:
            for key, value in getattr(t, name).items():
                out[key] = out.get(key, 0) + int(value)
        return out

    def per_lookup(name):
        weight = sum(n_matched)
        return (sum(getattr(t, name) * n for t, n in zip(tile_stats, n_matched)) / weight
                if weight else 0.0)

    groups = Counter()
    for t in tile_stats:
        for g in t.grids:
            groups[dataclasses.replace(g, pixels=0)] += g.pixels
    grids = tuple(sorted((dataclasses.replace(g, pixels=n) for g, n in groups.items()),
                         key=lambda g: -g.pixels))
    message = low_solved_message(reason, mask, solved)
    warnings_said = [text for _, text in said]
    for category, text in said:
        warnings.warn(text, category, stacklevel=3)
    if message:
        warnings_said.append(message)
        warnings.warn(message, LowSolvedWarning, stacklevel=3)
    q = quality[matched]
    refined = uncertainty[solved]
    timing = Timings(**{f.name: sum(getattr(t.seconds, f.name) or 0.0 for t in tile_stats)
                        for f in dataclasses.fields(Timings)})
    stats = dataclasses.replace(
        first, grid_n=next((t.grid_n for t in tile_stats if t.grid_n), None),
        grids=grids, buckets_per_lookup=per_lookup("buckets_per_lookup"),
        tests_per_lookup=per_lookup("tests_per_lookup"), pixels=total("pixels"),
        solved=total("solved"), solved_from_band_subset=total("solved_from_band_subset"),
        solved_from_light_subset=total("solved_from_light_subset"),
        lights_dropped_per_pixel=counts("lights_dropped_per_pixel"),
        dropped_per_light=[dict(light=i, darker=sum(t.dropped_per_light[i]["darker"]
                                                    for t in tile_stats),
                                brighter=sum(t.dropped_per_light[i]["brighter"]
                                             for t in tile_stats))
                           for i in range(first.images)],
        pixels_by_reason=counts("pixels_by_reason"),
        residual_median=_median(q), residual_p95=_percentile(q, 95),
        warnings=tuple(warnings_said), refined=total("refined"),
        uncertainty_median=_median(refined), uncertainty_p95=_percentile(refined, 95),
        seconds=dataclasses.replace(timing, total=seconds, integration=None))
    return Reconstruction(normals, albedo, quality, uncertainty, solved, reason, bands_used,
                          dropped, stats)
