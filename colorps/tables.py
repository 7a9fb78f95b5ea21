"""The gauge's tables: the gauge over a subset of lights and bands, as a table to match.

A :class:`Capture` holds the scene's and the gauge's observation vectors and
the noise model; :meth:`Capture.match` builds the weighted table of one group
(usable bands, band weights, lights: see :mod:`colorps.matching` for the
policy that forms the groups), finds every query's exact nearest entry with a
bucket grid or, for a few pixels, by brute force (:func:`nearest`), and
scores each match in noise units (:mod:`colorps.residuals`).
:class:`GaugeTables` keeps the grids for the other tiles of one capture.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from . import _grid_kernels, _pixel_kernels, light_masks
from ._config import AUTO_N_SAMPLE
from .errors import InputError
from .grid import BucketGrid
from .noise import NoiseModel
from .residuals import GaugeOverLights, MatchedGroup, match_residual, table_resolution

__all__ = ["Capture", "GaugeTables", "GroupResult", "PreparedGroup", "group_rows", "nearest"]

# ---------------------------------------------------------------- tuning
#: A table needs at least this many gauge entries; a group with fewer is not matched.
MIN_TABLE_ENTRIES = 3
#: Groups of fewer pixels are matched by brute force instead of a grid.
BRUTE_FORCE_PIXELS = 128
#: Brute force works on blocks of about this many distances (queries x table rows).
BRUTE_FORCE_BLOCK = 1 << 22
#: GaugeTables keeps grids up to this many MiB (a 30k-entry colour grid of 8
#: images takes about 16): the ones first built, which are the largest groups'.
TABLE_CACHE_MIB = 192
#: A capture keeps the gauge over the light subsets it matched last up to this many
#: MiB (a 201 x 201 gauge of RGB images takes 2.5 MiB a subset).
LIGHT_SET_CACHE_MIB = 256


class GaugeTables:
    """Bucket grids of one gauge's tables, and what else is made of the gauge
    alone, kept to be used again.

    The tiles of a capture, and the solves of one run (the bounced light's
    passes, :mod:`colorps.interreflection`), match against the same tables
    (same gauge, options and model): with one GaugeTables passed to each
    :func:`colorps.reconstruct`, every table's grid is built once instead of
    once per solve (in each Dask worker: a scattered copy fills on its own).
    Grids are kept while they fit in ``max_mib``; the first built stay (a
    tile matches its largest groups first, so those are the ones kept).
    The gauge they were built for is checked by a fingerprint of its
    observation vectors and settings: another gauge raises an InputError.
    The gauge's prepared stack, signatures, noise model and refinement models
    are kept too (:meth:`kept`; one gauge's worth, not counted in ``max_mib``).
    """

    def __init__(self, max_mib: float = TABLE_CACHE_MIB) -> None:
        self.max_bytes = int(max_mib * 2 ** 20)
        self.bytes = 0
        self.reused = 0
        self._grids: dict = {}
        self._kept: dict = {}
        self._fingerprint = None
        self._lock = threading.RLock()

    def attach(self, fingerprint: bytes) -> None:
        """Check (or, the first time, record) the gauge's fingerprint."""
        with self._lock:
            if self._fingerprint is None:
                self._fingerprint = fingerprint
            elif fingerprint != self._fingerprint:
                raise InputError("tables: these GaugeTables were built for another gauge "
                                 "or other options; use one per capture and settings")

    def get(self, key):
        with self._lock:
            grid = self._grids.get(key)
            if grid is not None:
                self.reused += 1
            return grid

    def kept(self, name: str, sources: tuple, make: Callable[[], object]):
        """What ``make()`` returns for ``sources``: made on the first call, and
        again only when called with other sources (compared by identity, each
        held until then) under the same ``name``."""
        with self._lock:
            held = self._kept.get(name)
            if held is None or len(held[0]) != len(sources) or \
                    any(a is not b for a, b in zip(held[0], sources)):
                held = self._kept[name] = (sources, make())
            return held[1]

    def keep(self, key, grid: BucketGrid) -> None:
        size = grid.nbytes
        with self._lock:
            if key not in self._grids and self.bytes + size <= self.max_bytes:
                self._grids[key] = grid
                self.bytes += size

    def __getstate__(self) -> dict:  # sent to Dask workers empty, without the lock
        return dict(max_bytes=self.max_bytes, fingerprint=self._fingerprint)

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["max_bytes"] / 2 ** 20)
        self._fingerprint = state["fingerprint"]


def nearest(table: np.ndarray, queries: np.ndarray, *, grid_n=None, threads=None,
            sample=None, tables: GaugeTables | None = None, key=None
            ) -> tuple[np.ndarray, float, float, int | None]:
    """Exact nearest table row of each query; (rows, summed b, summed d, grid N or None).

    With ``tables`` the grid of ``key`` is taken from it when it holds one,
    and a grid built is offered to it."""
    grid = _grid_for(table, len(queries), grid_n=grid_n, sample=sample, tables=tables, key=key)
    return _nearest_with(grid, table, queries, threads=threads)


def _grid_for(table: np.ndarray, n_queries: int, *, grid_n=None, sample=None,
             tables: GaugeTables | None = None, key=None) -> BucketGrid | None:
    """The grid :func:`nearest` matches ``n_queries`` queries with: ``tables``'
    grid of ``key``, else None for fewer than BRUTE_FORCE_PIXELS (brute
    force), else a grid built (and offered to ``tables``)."""
    grid = None if tables is None else tables.get(key)
    if grid is None and n_queries >= BRUTE_FORCE_PIXELS:
        grid = BucketGrid(table, grid_n, sample=sample if grid_n == "auto" else None)
        if tables is not None:
            tables.keep(key, grid)
    return grid


def _nearest_with(grid: BucketGrid | None, table: np.ndarray, queries: np.ndarray, *,
                 threads=None) -> tuple[np.ndarray, float, float, int | None]:
    """:func:`nearest` with the grid :func:`_grid_for` gave (None: brute force)."""
    if grid is None:
        return (_brute_force(table, queries), float(len(queries)),
                float(len(queries) * len(table)), None)
    rows, _, st = grid.query(queries, threads=threads, return_stats=True)
    return (rows, float(st.buckets_per_query.sum()), float(st.tests_per_query.sum()),
            grid.n)


def _brute_force(table: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """The grid's answer without a grid: each query's nearest table row, by the
    grid's rule for near ties (:func:`_grid_kernels.exact_distance2`).

    Distances come from |q|^2 + |t|^2 - 2 q.t in float64, in blocks of queries
    x table rows (not x dimensions too: with 96 lights that left one query per
    block, a matrix-vector product each); every row within the grid's pruning
    margin of a query's smallest is then compared exactly."""
    table = np.ascontiguousarray(table, dtype=np.float32)
    queries = np.ascontiguousarray(queries, dtype=np.float32)
    t = table.astype(np.float64)
    t2 = np.einsum("ij,ij->i", t, t)
    rows = np.empty(len(queries), dtype=np.int64)
    step = max(1, BRUTE_FORCE_BLOCK // max(1, len(table)))
    for a in range(0, len(queries), step):
        q = queries[a:a + step].astype(np.float64)
        d2 = np.einsum("ij,ij->i", q, q)[:, None] + t2[None, :] - 2.0 * q @ t.T
        limit = _grid_kernels.prune_limit(d2.min(axis=1))
        pair_query, pair_row = np.nonzero(d2 <= limit[:, None])
        _grid_kernels.nearest_of_candidates(queries[a:a + step], table, pair_query,
                                            pair_row, rows[a:a + step])
    return rows


@dataclass
class _LightSet:
    """The gauge over one subset of lights: what tables and residuals need.

    Its unit signatures are the gauge's OVs over ``lights`` divided by
    sqrt(norm2), computed where the kernels read them (stored, they took
    46 MiB a subset for a 201 x 201 gauge of 96 RGB images).
    """

    gauge_ov: np.ndarray    # (Hg, Wg, B, m) float32, every light (shared, not owned)
    lights: np.ndarray      # (m',) int64
    norm2: np.ndarray       # (Hg, Wg, B)
    variance: np.ndarray    # (Hg, Wg, B)
    usable: np.ndarray      # (Hg, Wg, B) bool
    #: (Hg * Wg, B) h^2 (residuals.table_resolution), computed at the pixels
    #: matched so far (NaN elsewhere): a subset's groups match few of them.
    resolution: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        hg, wg, n_bands = self.usable.shape
        self.resolution = np.full((hg * wg, n_bands), np.nan)

    def resolution_at(self, rows: np.ndarray) -> np.ndarray:
        """The whole (Hg * Wg, B) h^2 array, computed at least at ``rows``."""
        todo = rows[np.isnan(self.resolution[rows, 0])]
        if len(todo):
            todo = np.arange(len(self.resolution)) if len(todo) > len(self.resolution) \
                else np.unique(todo)
            table_resolution(self.gauge_ov, self.usable.all(axis=-1), todo,
                             out=self.resolution, lights=self.lights, norm2=self.norm2)
        return self.resolution

    @property
    def nbytes(self) -> int:
        """Bytes this light set owns (not the shared gauge OVs)."""
        return sum(a.nbytes for a in (self.norm2, self.variance, self.resolution,
                                      self.usable))


@dataclass(frozen=True)
class GroupResult:
    """One group's matches: gauge pixel (flat index, -1: no table) and residual."""

    rows: np.ndarray
    residual: np.ndarray
    distance: np.ndarray  # plain signature distance per band (unweighted)
    table_size: int
    grid_n: int | None
    buckets: float
    tests: float
    seconds_grid: float
    seconds_lookup: float


@dataclass
class Capture:
    """Scene and gauge observation vectors, per band, with the noise model.

    Attributes
    ----------
    scene_ov : (H, W, B, m) ndarray of float32
        Scene OVs of the signature bands (0 where a band is unusable).
    scene_valid : (H, W, B) ndarray of bool
    scene_clipped : (H, W, words) ndarray of uint64
        Light masks (:mod:`colorps.light_masks`) of the images with a clipped
        measurement at a scene pixel.
    scene_invalid : (H, W) ndarray of bool
        Scene pixels with an invalid (NaN, Inf, negative) measurement.
    gauge_ov : (Hg, Wg, B, m) ndarray of float32
    gauge_valid : (Hg, Wg, B) ndarray of bool
        Usable bands of gauge pixels inside the gauge mask.
    gauge_normals : (Hg * Wg, 3) ndarray
    model : NoiseModel
        Of the scene's measurements.
    min_norm : float
        Smallest usable OV norm over any light subset.
    gauge_model : NoiseModel, optional
        Of the gauge's measurements, when its files differ from the scene's.
    gauge_clipped : (Hg, Wg, words) ndarray of uint64, optional
        Light masks of the images with a clipped measurement at a gauge pixel.
    gauge_unclipped : (Hg, Wg, B) ndarray of bool, optional
        Bands of gauge pixels inside the gauge mask that would be usable but
        for clipped measurements: over lights that leave out every clipped one
        of a pixel, its band is usable (``gauge_valid`` holds over all lights).
    tables : GaugeTables, optional
        Grids kept from other pieces of the same capture (checked against
        :meth:`gauge_fingerprint`), and offered the ones built here.
    """

    scene_ov: np.ndarray
    scene_valid: np.ndarray
    gauge_ov: np.ndarray
    gauge_valid: np.ndarray
    gauge_normals: np.ndarray
    model: NoiseModel
    min_norm: float
    gauge_model: NoiseModel | None = None
    scene_clipped: np.ndarray | None = None
    scene_invalid: np.ndarray | None = None
    gauge_clipped: np.ndarray | None = None
    gauge_unclipped: np.ndarray | None = None
    tables: GaugeTables | None = None
    _light_sets: OrderedDict = field(default_factory=OrderedDict)
    _gauge_variance: np.ndarray | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock)

    @property
    def images(self) -> int:
        return self.scene_ov.shape[-1]

    @property
    def bands(self) -> int:
        return self.scene_ov.shape[-2]

    def __post_init__(self) -> None:
        self.gauge_ov = np.ascontiguousarray(self.gauge_ov)  # the kernels read it often
        if self.tables is not None:
            gauge = (self.gauge_ov, self.gauge_valid, self.gauge_clipped)
            self.tables.attach(self.tables.kept("fingerprint", gauge, self.gauge_fingerprint))

    def gauge_fingerprint(self) -> bytes:
        """A digest of everything the tables are made of: the gauge's OVs, its
        usable bands and the smallest usable norm."""
        import hashlib

        digest = hashlib.blake2b(np.ascontiguousarray(self.gauge_ov).tobytes())
        digest.update(np.ascontiguousarray(self.gauge_valid).tobytes())
        if self.gauge_clipped is not None:
            digest.update(np.ascontiguousarray(self.gauge_clipped).tobytes())
        digest.update(repr((self.gauge_ov.shape, float(self.min_norm))).encode())
        return digest.digest()

    def light_set(self, lights: tuple[int, ...]) -> _LightSet:
        """The gauge restricted to ``lights``, kept while the light sets used last
        fit in LIGHT_SET_CACHE_MIB (the set of every light always stays)."""
        with self._lock:  # (groups are prepared in threads: colorps.matching)
            return self._light_set(lights)

    def _light_set(self, lights: tuple[int, ...]) -> _LightSet:
        if lights in self._light_sets:
            self._light_sets.move_to_end(lights)
        else:
            if self._gauge_variance is None:  # per measurement, computed once
                self._gauge_variance = self._variance() if self.tables is None else \
                    self.tables.kept("variance", (self.gauge_ov, self.gauge_valid,
                                                  self.gauge_unclipped, self.gauge_model),
                                     self._variance)
            hg, wg, n_bands, _ = self.gauge_ov.shape
            norm2 = np.empty((hg, wg, n_bands))
            variance = np.empty((hg, wg, n_bands), dtype=np.float32)
            usable = np.empty((hg, wg, n_bands), dtype=bool)
            light_index = np.array(lights, dtype=np.int64)
            _pixel_kernels.light_set(self.gauge_ov, light_index, self._valid_over(lights),
                                     float(self.min_norm), self._gauge_variance, norm2,
                                     variance, usable)
            self._light_sets[lights] = _LightSet(gauge_ov=self.gauge_ov, lights=light_index,
                                                 norm2=norm2, variance=variance, usable=usable)
            self._forget_light_sets(keep=lights)
        return self._light_sets[lights]

    def _variance(self) -> np.ndarray:
        """(Hg, Wg, B, m) float32 variance of every gauge measurement under the
        gauge's noise model, on the pixels with a band that may be usable (0
        elsewhere: a gauge photographed in a whole frame is mostly background)."""
        model = self.gauge_model or self.model
        inside = self.gauge_valid.any(axis=-1)
        if self.gauge_unclipped is not None:
            inside |= self.gauge_unclipped.any(axis=-1)
        variance = np.zeros(self.gauge_ov.shape, dtype=np.float32)
        variance[inside] = model.sigma(self.gauge_ov[inside]) ** 2
        return variance

    def _valid_over(self, lights: tuple[int, ...]) -> np.ndarray:
        """(Hg, Wg, B) gauge bands valid over ``lights``: valid over every light,
        or valid but for clipped measurements none of which is among ``lights``."""
        valid = np.ascontiguousarray(self.gauge_valid)
        if self.gauge_clipped is None or self.gauge_unclipped is None:
            return valid
        chosen = light_masks.from_bool(np.isin(np.arange(self.images), lights))
        untouched = ~(self.gauge_clipped & chosen).any(axis=-1)
        return np.ascontiguousarray(valid | (self.gauge_unclipped & untouched[..., None]))

    def _forget_light_sets(self, keep: tuple[int, ...]) -> None:
        """Drop the least recently used light sets beyond LIGHT_SET_CACHE_MIB."""
        every = tuple(range(self.images))
        total = sum(s.nbytes for s in self._light_sets.values())
        for lights in list(self._light_sets):
            if total <= LIGHT_SET_CACHE_MIB * 2 ** 20:
                break
            if lights not in (keep, every):
                total -= self._light_sets.pop(lights).nbytes

    def match(self, ys: np.ndarray, xs: np.ndarray, bands: tuple[int, ...],
              levels: tuple[int, ...], lights: tuple[int, ...], *, grid_n=None,
              threads=None, sample_size: int = AUTO_N_SAMPLE) -> GroupResult:
        """Match pixels (ys, xs) on ``bands`` weighted 2^levels over ``lights``."""
        return self.finish(self.prepare(ys, xs, bands, levels, lights, grid_n=grid_n,
                                        sample_size=sample_size), threads=threads)

    def prepare(self, ys: np.ndarray, xs: np.ndarray, bands: tuple[int, ...],
                levels: tuple[int, ...], lights: tuple[int, ...], *, grid_n=None,
                sample_size: int = AUTO_N_SAMPLE) -> PreparedGroup:
        """The first half of :meth:`match`: the group's table, queries and grid
        (None: too few pixels, matched by brute force; or too few table entries).

        It may run in another thread while :meth:`finish` matches the group
        before (:func:`colorps.matching.first_match` does so); only it makes
        light sets and grids."""
        t0 = time.perf_counter()
        gauge = self.light_set(lights)
        band_list = list(bands)
        table_px = gauge.usable[..., band_list].all(axis=-1)
        ys, xs = np.asarray(ys, np.int64), np.asarray(xs, np.int64)
        if table_px.sum() < MIN_TABLE_ENTRIES:
            return PreparedGroup(ys, xs, bands, lights, gauge, None, None, None, None,
                                 time.perf_counter() - t0)
        scale = np.exp2(np.array(levels, dtype=np.float32))
        band_index, light_index = np.array(bands, np.int64), np.array(lights, np.int64)
        table_rows = np.flatnonzero(table_px)
        table = np.empty((len(table_rows), len(bands) * len(lights)), dtype=np.float32)
        _pixel_kernels.group_table(self.gauge_ov, light_index, gauge.norm2, table_rows,
                                   band_index, scale, table)
        queries = np.empty((len(ys), len(bands) * len(lights)), dtype=np.float32)
        _pixel_kernels.group_queries(self.scene_ov, ys, xs, band_index, light_index, scale,
                                     queries)
        grid = _grid_for(table, len(ys), grid_n=grid_n,
                        sample=queries[:: max(1, len(ys) // sample_size)],
                        tables=self.tables, key=(bands, levels, lights, grid_n))
        return PreparedGroup(ys, xs, bands, lights, gauge, table, table_rows, queries, grid,
                             time.perf_counter() - t0)

    def finish(self, group: PreparedGroup, *, threads=None) -> GroupResult:
        """The second half of :meth:`match`: the group's nearest entries, scored."""
        n_rows = len(group.ys)
        if group.table is None:
            nothing = np.full(n_rows, np.nan, np.float32)
            return GroupResult(np.full(n_rows, -1, np.int64), nothing, nothing, 0, None, 0.0,
                               0.0, group.seconds, 0.0)
        t0 = time.perf_counter()
        found, b_sum, d_sum, grid_n = _nearest_with(group.grid, group.table, group.queries,
                                                   threads=threads)
        rows = group.table_rows[found]
        t_lookup = time.perf_counter() - t0
        gauge = group.gauge
        residual, distance = match_residual(
            self.scene_ov, MatchedGroup(group.ys, group.xs, np.array(group.bands, np.int64),
                                        gauge.lights, rows),
            GaugeOverLights(self.gauge_ov, gauge.norm2.reshape(-1, self.bands),
                            gauge.variance.reshape(-1, self.bands), gauge.resolution_at(rows)),
            self.model)
        return GroupResult(rows, residual, distance, len(group.table), grid_n, b_sum, d_sum,
                           group.seconds, t_lookup)


@dataclass(frozen=True)
class PreparedGroup:
    """A group made ready to match (:meth:`Capture.prepare`): its pixels, bands
    and lights, the gauge over those lights, its table (None: fewer than
    MIN_TABLE_ENTRIES entries), their gauge pixels, the queries, the grid
    (None: brute force) and the seconds that took."""

    ys: np.ndarray
    xs: np.ndarray
    bands: tuple
    lights: tuple
    gauge: _LightSet
    table: np.ndarray | None
    table_rows: np.ndarray | None
    queries: np.ndarray | None
    grid: BucketGrid | None
    seconds: float


def group_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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
