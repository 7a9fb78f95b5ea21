"""Captures in tiles: bands of rows reconstructed apart, in this process or on Dask.

A tile is a band of whole rows of the scene. Every scene pixel's result
depends on the gauge, the noise model and the capture's **model scale** only
(:mod:`colorps.residuals`), so tiles can be solved independently once the
scale is known. A tiled run therefore has two passes:

1. each tile's first residuals (:func:`colorps.reconstruct.first_residuals`)
   at the pixels the scale is measured on
   (:func:`colorps.matching.model_scale_pixels`: at most about 2^16 of
   them, so this pass costs little more than reading the tiles), gathered
   into the capture's model scale
   (:func:`colorps.matching.measured_model_scale`);
2. each tile's :func:`colorps.reconstruct` with that scale.

The normals, albedo, quality, uncertainty and reason maps are then the same
as those of one untiled run (tests check it); the statistics are combined
(:func:`colorps.results.combine_statistics`).
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

import contextlib
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError, LowSolvedWarning
from .figures import overview_step
from .gauge import Gauge
from .matching import measured_model_scale, model_scale_pixels
from .memory import DEFAULT_TILE_ROWS, release_freed_memory, tile_rows
from .options import Options
from .reconstruct import first_residuals, reconstruct
from .resolve import Resolved, resolve
from .results import Reconstruction, combine_statistics
from .tables import GaugeTables

__all__ = ["StackFiles", "dask_client", "reconstruct_tiled"]

#: Seconds to wait for a Dask scheduler given by address.
SCHEDULER_TIMEOUT = 10


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
        return read_stack(self.paths, self.encoding, name=self.name, rows=(start, stop),
                          warn_lossy=False)[0]  # (said once, when the run began)


def reconstruct_tiled(scene, gauge_stack, gauge: Gauge,
                      options: Options | Resolved | None = None, *,
                      tile: int = DEFAULT_TILE_ROWS, mask=None, client=None,
                      progress: bool = False, return_preview: bool = False):
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
    gauge_stack, gauge, options, mask
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
    _m, h, w, _c = scene.shape
    mask = np.ones((h, w), bool) if mask is None else np.asarray(mask, dtype=bool)
    if mask.shape != (h, w):
        raise InputError(f"mask: shape {mask.shape} differs from the scene's {(h, w)}")
    ranges = tile_rows(h, tile)
    run = _TiledRun(scene, ranges, gauge_stack, gauge, client, progress)
    # One GaugeTables for every tile: each table's grid is built once (per worker).
    shared = dict(options=resolve(options), tables=GaugeTables())
    # The first pass matches only the pixels the model scale is measured on.
    sampled = model_scale_pixels(mask)
    residuals = []
    run.each(_first_task, [sampled[a:b] for a, b in ranges], shared, "first matches",
             lambda k, found: residuals.append(found))
    model_scale = measured_model_scale(np.concatenate(residuals))
    joined = _Joined(h, overview_step((h, w)) if return_preview else None)
    run.each(_tile_task, [mask[a:b] for a, b in ranges], dict(shared, model_scale=model_scale),
             "tiles", lambda k, outcome: joined.add(k, ranges[k], *outcome))
    del shared  # the grids kept for the tiles
    maps = {name: joined.maps.pop(name) for name in _MAPS}
    order = sorted(joined.stats)
    stats = combine_statistics([joined.stats[k] for k in order],
                               [joined.matched[k] for k in order], maps, mask,
                               list(dict.fromkeys(s for k in order for s in joined.said[k])),
                               time.perf_counter() - t_start)
    result = Reconstruction(**maps, stats=stats)
    release_freed_memory()
    return (result, joined.preview) if return_preview else result


def _first_task(scene, rows, tile_mask, gauge_stack, gauge, *, options, tables):
    """A tile's first residuals; ``scene[:, rows]`` is the tile, ``tile_mask`` the
    pixels to match (only its rows with any are processed: each pixel's
    residual is its own)."""
    keep = tile_mask.any(axis=1)
    if not keep.any():
        return np.zeros(0, dtype=np.float32)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the whole run reports, once
        return first_residuals(scene[:, rows[0]:rows[1]][:, keep], gauge_stack, gauge,
                               options, mask=tile_mask[keep], tables=tables)


def _tile_task(scene, rows, tile_mask, gauge_stack, gauge, *, options, tables, model_scale):
    """A tile's reconstruction, the warnings it raised (but low-solved ones), and
    its mean image at the rows and columns the overview draws (the preview)."""
    piece = scene[:, rows[0]:rows[1]]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = reconstruct(piece, gauge_stack, gauge, options, mask=tile_mask,
                             model_scale=model_scale, tables=tables)
    said = [(w.category, str(w.message)) for w in caught
            if not issubclass(w.category, LowSolvedWarning)]
    step = overview_step(scene.shape[1:3])
    drawn = piece[:, (-rows[0]) % step::step, ::step]
    return result, said, np.asarray(drawn, dtype=np.float32).mean(axis=0)


@dataclass
class _TiledRun:
    """The tiles of one capture and where they run (this process or a Dask client)."""

    scene: object           # (m, H, W, c) ndarray or StackFiles
    ranges: list            # (start, stop) rows of each tile
    gauge_stack: np.ndarray
    gauge: Gauge
    client: object = None
    progress: bool = False

    def each(self, task, masks, shared: dict, what: str, collect) -> None:
        """Run ``task`` on every tile, handing ``collect(k, outcome)`` each outcome
        (in any order on Dask)."""
        if self.client is None:
            self._in_process(task, masks, shared, what, collect)
        else:
            self._on_dask(task, masks, shared, collect)

    def _in_process(self, task, masks, shared, what, collect) -> None:
        from tqdm.auto import tqdm

        for k, (rows, tile_mask) in enumerate(tqdm(list(zip(self.ranges, masks)), desc=what,
                                                   disable=not self.progress, leave=False)):
            collect(k, task(self.scene, rows, tile_mask, self.gauge_stack, self.gauge,
                            **shared))
            release_freed_memory()  # the tile's temporaries, before the next tile's

    def _on_dask(self, task, masks, shared, collect) -> None:
        from dask.distributed import as_completed
        from dask.distributed import progress as dask_progress

        client = self.client
        gauge_stack, gauge, tables = client.scatter(
            [np.ascontiguousarray(self.gauge_stack), self.gauge, shared["tables"]],
            broadcast=True, hash=False)
        shared = dict(shared, tables=tables)
        futures = {}
        for k, (rows, tile_mask) in enumerate(zip(self.ranges, masks)):
            piece, piece_rows = self.scene, rows  # files: the worker reads its own rows
            if isinstance(self.scene, np.ndarray):  # in memory: each tile sent on its own
                piece, piece_rows = self.scene[:, rows[0]:rows[1]], (0, rows[1] - rows[0])
            futures[client.submit(task, piece, piece_rows, tile_mask, gauge_stack, gauge,
                                  **shared, pure=False)] = k
        if self.progress:
            dask_progress(list(futures))
        for future, outcome in as_completed(list(futures), with_results=True):
            collect(futures.pop(future), outcome)
            future.release()


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
                self.maps[name] = np.empty((self.height, *piece.shape[1:]), piece.dtype)
            self.maps[name][rows[0]:rows[1]] = piece
        if self.preview_step is not None:
            step = self.preview_step
            if self.preview is None:
                self.preview = np.empty((-(-self.height // step), *mean.shape[1:]),
                                        np.float32)
            first = -(-rows[0] // step)  # the first drawn row in this tile
            self.preview[first:first + len(mean)] = mean
        self.stats[k] = result.stats
        self.said[k] = said
        self.matched[k] = int(np.isfinite(result.quality).sum())


#: The maps of a Reconstruction a tiled run joins, in its field order.
_MAPS = ("normals", "albedo", "quality", "uncertainty", "solved", "reason", "bands_used",
         "dropped_lights")


@contextlib.contextmanager
def dask_client(scheduler):
    """A context of a Dask client: None (no scheduler), the given client, or one
    connected to a scheduler address / a local cluster started for "local"."""
    if scheduler is None or not isinstance(scheduler, str):
        yield scheduler
        return
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError:
        raise InputError("--scheduler needs Dask: pip install 'colorps[dask]'") from None
    if scheduler == "local":
        with LocalCluster(dashboard_address=None) as cluster, Client(cluster) as client:
            yield client
        return
    try:
        client = Client(scheduler, timeout=SCHEDULER_TIMEOUT)
    except ValueError as error:  # an address Dask cannot read (http://, a typo)
        raise InputError(f"--scheduler {scheduler}: not a Dask scheduler address ({error}); "
                         "give tcp://HOST:8786, or 'local'") from None
    except (OSError, TimeoutError) as error:
        raise InputError(f"--scheduler {scheduler}: cannot connect ({error})") from None
    with client:
        yield client
