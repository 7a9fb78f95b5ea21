"""The 2-D bucket grid: exact nearest-signature lookup (paper sections 1.6 - 1.11).

The table of gauge signatures is a (nearly flat) 2-D manifold in R^D, so it is
bucketed on a grid over its two principal axes. A lookup scans the cells around
the query's cell in order of the cells' distance bound (eq. 15) and stops as soon
as no unscanned cell can hold a closer entry (eq. 16). The result is always the
brute-force nearest entry, never an approximation.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import numpy as np

from . import _grid_kernels
from ._checks import as_float32_2d, resolve_threads
from ._config import AUTO_N_SAMPLE
from .errors import InputError

__all__ = ["BucketGrid", "QueryStats"]

# ---------------------------------------------------------------- tuning
# Constants of the grid's construction; the measurements behind them are in
# docs/benchmarks.md. Those of the lookup kernels are in _grid_kernels.py.

#: Default N per table size K: the paper's optimum round(2 sqrt(K)), about
#: 0.25 entries per cell.
CELLS_PER_SQRT_ENTRY = 2.0
#: Principal axes in a sketch (at most SKETCH_LANES - 1; the last lane is the
#: residual). 10 axes measured 1.6-2.0x slower at D = 90, 5 axes 1.3-3.6x.
SKETCH_AXES = 15
#: Candidate N of ``n="auto"``, as factors of the default, timed on at most
#: _config.AUTO_N_SAMPLE queries (1 thread, best of AUTO_N_REPEATS).
AUTO_N_FACTORS = (0.25, 0.5, 1.0, 2.0)
AUTO_N_REPEATS = 3
#: Largest grid: N^2 cells may not exceed max(MAX_CELLS_PER_ENTRY K, MIN_CELL_LIMIT)
#: (each cell costs about 20 bytes; the default N gives 4 cells per entry, and
#: larger grids only slow lookups down).
MAX_CELLS_PER_ENTRY = 1024
MIN_CELL_LIMIT = 1 << 20
#: Queries numba hands to a thread at a time (lookup cost varies over an
#: image: noisy or unlit regions), in units of the kernel's QUERY_CHUNK.
THREAD_CHUNKS = 4
#: Fine scan plans kept, one per grid size N (they depend on N alone, and a
#: capture's groups mostly share one N: computing it was 40 % of a build).
SCAN_ORDER_CACHE = 4


def fine_radius(n: int) -> int:
    """Cells (eq. 15 norm) the fine scan of phase 1 reaches on an N x N grid.

    Beyond it blocks of cells take over; both about sqrt(N), measured best on
    the benchmark's noisy and outlier runs.
    """
    return max(2, int(round(np.sqrt(n) / 3)))


def block_side(n: int) -> int:
    """Side, in cells, of a block of the coarse level (phase 2)."""
    return max(2, int(round(np.sqrt(n) / 2)))


@dataclass(frozen=True)
class QueryStats:
    """Work done by a batch of lookups.

    Attributes
    ----------
    buckets : float
        Mean number of non-empty buckets examined per lookup (the paper's b).
    tests : float
        Mean number of table entries whose full distance was computed (d).
    buckets_per_query, tests_per_query : (Q,) ndarray of int32
        The same counts per query.
    """

    buckets: float
    tests: float
    buckets_per_query: np.ndarray
    tests_per_query: np.ndarray


def _scan_order(extent: int) -> tuple[np.ndarray, np.ndarray]:
    """Displacements in {-extent+1..extent-1}^2 sorted by eq. 15, ties by length.

    Returns the (L, 2) int32 offsets and their squared ``||.||_dd`` norms (in
    cell units, int64), read-only.
    """
    r = np.arange(-extent + 1, extent, dtype=np.int64)
    dr, ds = np.meshgrid(r, r, indexing="ij")
    dr = dr.ravel()
    ds = ds.ravel()
    dd2 = np.maximum(np.abs(dr) - 1, 0) ** 2 + np.maximum(np.abs(ds) - 1, 0) ** 2
    order = np.lexsort((dr * dr + ds * ds, dd2))
    offsets = np.stack([dr[order], ds[order]], axis=1).astype(np.int32)
    return _read_only(offsets), _read_only(dd2[order])


def _read_only(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


def _row_runs(offsets: np.ndarray, dd2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Group a scan order into runs of cells of one row with the same bound.

    ``offsets`` (L, 2) sorted by ``dd2`` (eq. 15). Within each group of equal
    ``dd2`` the cells of one row r with consecutive s form one run (r, s0, s1);
    runs keep the order of their first cell. Returns (R, 3) int64 runs and
    their dd2.
    """
    runs, bounds = [], []
    start = 0
    while start < len(dd2):
        stop = start + int(np.searchsorted(dd2[start:], dd2[start], side="right"))
        group = offsets[start:stop]
        by_row = {}
        for rank, (r, s) in enumerate(group.tolist()):
            by_row.setdefault(r, []).append((s, rank))
        pieces = []
        for r, cells in by_row.items():
            cells.sort()
            s0, rank0 = cells[0]
            prev = s0
            for s, rank in cells[1:]:
                if s == prev + 1:
                    prev = s
                    rank0 = min(rank0, rank)
                    continue
                pieces.append((rank0, r, s0, prev))
                s0, prev, rank0 = s, s, rank
            pieces.append((rank0, r, s0, prev))
        pieces.sort()
        runs.extend((r, s0, s1) for _, r, s0, s1 in pieces)
        bounds.extend([dd2[start]] * len(pieces))
        start = stop
    return np.array(runs, dtype=np.int64).reshape(-1, 3), np.array(bounds, dtype=np.int64)


def _padded(rows: np.ndarray) -> np.ndarray:
    """Rows as the kernels read them: C-contiguous float32, and above
    ``RUN_SCAN_DIMS`` zero-padded to whole vectors of ``_grid_kernels.LANES``."""
    dims = rows.shape[1]
    width = dims
    if dims > _grid_kernels.RUN_SCAN_DIMS:
        width = -(-dims // _grid_kernels.LANES) * _grid_kernels.LANES
    out = np.zeros((rows.shape[0], width), dtype=np.float32)
    out[:, :dims] = rows
    return out


def _sketches(principal: np.ndarray, center: np.ndarray,
              entries: np.ndarray) -> tuple[_grid_kernels.Sketch, np.ndarray]:
    """Sketch definition (for the kernel) and every entry's sketch.

    ``principal`` holds the principal axes as rows, leading first; ``entries``
    (K, D) float64. The sketch of x is (A(x - b), r(x)) in ``SKETCH_LANES``
    float32 lanes, A the float32-rounded leading axes, r^2 = |x - b|^2 -
    |A(x - b)|^2 / sigma^2 (see ``_grid_kernels._query_sketch``); lanes past
    the residual are 0. Returns the kernel's Sketch and the (K, lanes)
    float32 entry sketches.
    """
    lanes = _grid_kernels.SKETCH_LANES
    dims = entries.shape[1]
    n_axes = min(SKETCH_AXES, lanes - 1, dims)
    axes32 = np.zeros((lanes - 1, dims), dtype=np.float32)
    axes32[:n_axes] = principal[:n_axes]
    axes64 = axes32[:n_axes].astype(np.float64)
    sigma = max(1.0, np.linalg.norm(axes64, 2)) * (1 + 1e-12)
    offset = np.zeros(lanes - 1, dtype=np.float32)
    offset[:n_axes] = axes64 @ center
    centred = entries - center
    norms = np.sqrt(np.einsum("ij,ij->i", centred, centred))
    coords = np.zeros((entries.shape[0], lanes))
    coords[:, :n_axes] = centred @ axes64.T
    res2 = norms ** 2 - (coords[:, :n_axes] ** 2).sum(axis=1) / sigma ** 2
    coords[:, n_axes] = np.sqrt(np.maximum(res2, 0.0))
    points = coords.astype(np.float32)
    # Stored sketches are off by float32 rounding, and residuals by the float64
    # rounding of their cancellation; queries' intervals are widened by this.
    point_slack = (4.0 * _grid_kernels.U32 + 1e-7) * (1.0 + norms.max())
    sketch = _grid_kernels.Sketch(axes=axes32, offset=offset, n_axes=n_axes,
                                  center_norm=float(np.linalg.norm(center)),
                                  inv_sigma2=1.0 / sigma ** 2, point_slack=float(point_slack))
    return sketch, points


def _boxes(points: np.ndarray, first: np.ndarray,
           groups: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Low and high corners, (G, lanes) each, of consecutive groups of points.

    Groups start at ``first``. With ``groups`` (a mask over G >= len(first)
    groups) the boxes land in the masked rows; the others are empty (+inf, -inf).
    """
    low = np.minimum.reduceat(points, first, axis=0)
    high = np.maximum.reduceat(points, first, axis=0)
    if groups is None:
        return low, high
    all_low = np.full((groups.size, points.shape[1]), np.inf, dtype=np.float32)
    all_high = np.full((groups.size, points.shape[1]), -np.inf, dtype=np.float32)
    all_low[groups], all_high[groups] = low, high
    return all_low, all_high

# ---------------------------------------------------------------- build steps
def _plane(t64: np.ndarray, n: int):
    """The PCA plane and the N x N grid on it (eq. 11), and where entries fall.

    Returns the kernel's Plane, the (D, D) principal axes as rows (leading
    first), each entry's (u, v, h) as (K, 3) float64, and its cell (row i,
    column j) as two (K,) int64 arrays.
    """
    dims = t64.shape[1]
    center = t64.mean(axis=0)
    centred = t64 - center
    _, eigvec = np.linalg.eigh(centred.T @ centred)  # moment matrix, ascending
    principal = eigvec[:, ::-1].T  # rows, leading first
    axes = np.zeros((2, dims))
    axes[: min(2, dims)] = principal[:2]  # D = 1 leaves a zero second axis
    proj = centred @ axes.T  # (K, 2), same arithmetic as the kernel
    r2 = np.einsum("ij,ij->i", centred, centred)  # 10 times faster than a sum of squares
    pu, pv = proj[:, 0], proj[:, 1]
    h = np.sqrt(np.maximum(r2 - pu * pu - pv * pv, 0.0))
    extent = max(np.abs(pu).max(), np.abs(pv).max())
    half_width = extent + 1e-6 * (1.0 + extent)  # eq. 11, eps > 0
    delta = 2.0 * half_width / n
    ci = np.clip(np.floor((pu + half_width) / delta).astype(np.int64), 0, n - 1)
    cj = np.clip(np.floor((pv + half_width) / delta).astype(np.int64), 0, n - 1)
    plane = _grid_kernels.Plane(center=center, axes=axes, half_width=float(half_width),
                                delta=float(delta), n=n)
    return plane, principal, np.stack([pu, pv, h], axis=1), ci, cj


@lru_cache(maxsize=SCAN_ORDER_CACHE)
def _cell_ranks(n: int, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Storage position of every cell (by block, then row-major), and its block
    (both indexed by the row-major cell number; cached, read-only)."""
    n_blocks = -(-n // block)
    row, col = np.divmod(np.arange(n * n), n)
    block_of = (row // block) * n_blocks + col // block
    rank = np.empty(n * n, dtype=np.int64)
    rank[np.argsort(block_of * (n * n) + row * n + col, kind="stable")] = np.arange(n * n)
    return _read_only(rank), _read_only(block_of)


def _storage(ci: np.ndarray, cj: np.ndarray, n: int, block: int):
    """Storage order of the entries, and the ranges of cells, buckets and blocks.

    Entries are stored by block, then cell in row-major order, so every bucket
    and every block is a contiguous range (CSR storage at both levels), and so
    are the cells of one row within a block. Every cell, empty or not, has a
    begin and an end.

    Returns the (K,) order, the first storage position of each bucket, the
    kernel's Cells, and the (blocks^2 + 1,) int64 block starts.
    """
    n_blocks = -(-n // block)
    rank, block_of = _cell_ranks(n, block)
    cell = ci * n + cj
    position = rank[cell]
    order = np.argsort(position, kind="stable")
    counts = np.bincount(position, minlength=n * n)  # entries per cell, storage order
    end = np.cumsum(counts)[rank]
    begin = end - counts[rank]
    cell_sorted = np.take(cell, order)
    first = np.flatnonzero(np.r_[True, cell_sorted[1:] != cell_sorted[:-1]])
    bucket = np.full(n * n, -1, dtype=np.int32)
    bucket[cell_sorted[first]] = np.arange(first.size, dtype=np.int32)
    block_start = np.zeros(n_blocks * n_blocks + 1, dtype=np.int64)
    np.cumsum(np.bincount(block_of[cell], minlength=n_blocks * n_blocks), out=block_start[1:])
    return order, first, _grid_kernels.Cells(bucket=bucket, begin=begin, end=end), block_start


def _buckets(sorted64: np.ndarray, h_sorted: np.ndarray, first: np.ndarray,
             entry_sketch: np.ndarray) -> _grid_kernels.Buckets:
    """Per bucket: [h_min, h_max], the sketch box, the mean and the radius about it
    (one compiled pass, :func:`colorps._grid_kernels.bucket_summaries`)."""
    n_buckets, lanes = first.size, entry_sketch.shape[1]
    h_range = np.empty((n_buckets, 2))
    box_low = np.empty((n_buckets, lanes), dtype=np.float32)
    box_high = np.empty((n_buckets, lanes), dtype=np.float32)
    mean = _padded(np.zeros((n_buckets, sorted64.shape[1]), dtype=np.float32))
    radius = np.empty(n_buckets)
    _grid_kernels.bucket_summaries(sorted64, h_sorted, entry_sketch, first, h_range, box_low,
                                   box_high, mean, radius)
    return _grid_kernels.Buckets(h_range=h_range, box_low=box_low, box_high=box_high,
                                 mean=mean, radius=radius)


def _blocks(entry_sketch: np.ndarray, block_start: np.ndarray, n: int, block: int,
            delta: float) -> _grid_kernels.Blocks:
    """The coarse level: block ranges, sketch boxes and the block scan order."""
    n_blocks = -(-n // block)
    # Empty blocks are never tested; give them an empty box all the same.
    filled = block_start[:-1] < block_start[1:]
    box_low, box_high = _boxes(entry_sketch, block_start[:-1][filled], filled)
    offsets, dd2 = _scan_order(n_blocks)
    return _grid_kernels.Blocks(side=block, count=n_blocks, start=block_start,
                                box_low=box_low, box_high=box_high, offsets=offsets,
                                bound2=(block * delta) ** 2 * dd2.astype(np.float64))


@lru_cache(maxsize=SCAN_ORDER_CACHE)
def _fine_scan(n: int, use_runs: bool) -> tuple:
    """The part of the scan plan that depends on N alone (cached, read-only):
    fine offsets and their dd2 (cell by cell) or row runs and theirs."""
    fine_dd2_max = fine_radius(n) ** 2
    # Offsets with dd2 <= fine_dd2_max have |dr|, |ds| <= fine_radius + 1: the
    # scan order of that extent starts with the same offsets, in the same order.
    offsets, dd2 = _scan_order(min(n, fine_radius(n) + 2))
    n_fine = int(np.searchsorted(dd2, fine_dd2_max, side="right"))
    fine_offsets, fine_dd2 = offsets[:n_fine], dd2[:n_fine]
    runs, run_dd2 = np.zeros((0, 3), dtype=np.int64), fine_dd2[:0]
    if use_runs:
        runs, run_dd2 = _row_runs(fine_offsets, fine_dd2)
        fine_offsets, fine_dd2 = fine_offsets[:0], fine_dd2[:0]
    return (_read_only(runs), _read_only(run_dd2), np.ascontiguousarray(fine_offsets),
            fine_dd2, n_fine == (2 * n - 1) ** 2, fine_dd2_max)


def _scan_plan(n: int, dims: int, block: int, delta: float) -> _grid_kernels.ScanPlan:
    """Phase 1's scan order: runs of cells (D <= RUN_SCAN_DIMS) or cell by cell."""
    use_runs = dims <= _grid_kernels.RUN_SCAN_DIMS
    runs, run_dd2, fine_offsets, fine_dd2, fine_is_all, fine_dd2_max = _fine_scan(
        n, use_runs)
    return _grid_kernels.ScanPlan(
        use_runs=use_runs, runs=runs, run_bound=delta * np.sqrt(run_dd2.astype(np.float64)),
        # The last column of each column's block, looked up: an integer
        # division per run cost 8-14 % of a mono lookup (measured).
        block_last=np.minimum((np.arange(n) // block + 1) * block - 1, n - 1),
        offsets=fine_offsets,
        bound=delta * np.sqrt(fine_dd2.astype(np.float64)),
        fine_is_all=fine_is_all, fine_dd2_max=fine_dd2_max,
        # The per-entry sketch bound of phase 2 costs one vector of float32
        # lanes; it pays when a full distance costs more (measured: 5-7 %
        # faster at D = 30 than without it).
        entry_bound=dims > _grid_kernels.SKETCH_LANES)


class BucketGrid:
    """Exact nearest-neighbour index for a table of signatures (a 2-D manifold).

    Parameters
    ----------
    signatures : (K, D) array_like
        Table entries (gauge signatures), K >= 1, finite. Stored as float32.
    n : int, "auto" or None, optional
        Grid size N (N x N cells). ``None`` uses the paper's optimum
        ``round(2 * sqrt(K))`` (about 0.25 entries per cell). ``"auto"`` times a
        few candidates on ``sample`` (a sample of the actual queries) and keeps
        the fastest: the best N falls as the queries' noise rises. ``n = 1`` is
        a linear scan.
    sample : (Q, D) array_like, optional
        Queries used by ``n="auto"``; without it ``"auto"`` means ``None``.

    Attributes
    ----------
    n : int
        Grid size N.
    size : int
        Number of table entries K.
    dims : int
        Signature dimension D.
    cell_side : float
        Side delta = 2 R / N of a cell in signature units (eq. 11).

    Notes
    -----
    Besides the paper's structure (PCA plane, buckets in CSR order with their
    means and radii, the precomputed scan order of eq. 15, bucket truncation of
    eq. 12 and early termination of eq. 16), three exact prunings keep lookups
    cheap; see ``docs/method.md``:

    * every entry and bucket also carries its distance h from the PCA plane, so
      |P(q - g)|^2 + (h(q) - h(g))^2, a lower bound of |q - g|^2, rejects most
      entries for 8 flops instead of D;
    * every entry has a *sketch*: its coordinates on up to 15 leading principal
      axes and the residual beyond them (float32). Buckets and blocks keep the
      box of their entries' sketches, a lower bound that stays tight where the
      manifold curves away from the plane. A lookup computes its query's
      sketch before it would spend about as much on full distances, or at once
      when the previous query (a neighbouring pixel) needed it;
    * once the scan has passed a few cells without terminating, or (D > 8) its
      best entry is still several cells away, it continues at a coarse level of
      blocks of cells with sketch boxes, so a query at distance r from the
      table no longer costs (r / delta)^2 cells.

    Distances are computed in float32, projections and bounds in float64 or in
    float32 with rounding-error intervals; a pruning test keeps a relative
    margin of 1e-4, so the returned entry is the brute-force nearest up to
    float32 rounding of near-ties.

    References
    ----------
    .. [1] R. F. Saracchini, J. Stolfi, H. C. G. Leitão, G. Atkinson, M. L. Smith,
       "A Bucket Grid Structure to Speed Up Table Lookup in Gauge-Based
       Photometric Stereo".

    Examples
    --------
    >>> import numpy as np
    >>> from colorps import BucketGrid
    >>> rng = np.random.default_rng(0)
    >>> table = rng.normal(size=(1000, 3)).astype(np.float32)
    >>> grid = BucketGrid(table)
    >>> rows, dist = grid.query(table[:5] + 0.001)
    >>> rows.tolist()
    [0, 1, 2, 3, 4]
    """

    def __init__(self, signatures, n: int | Literal["auto"] | None = None, *,
                 sample=None) -> None:
        table = as_float32_2d(signatures, "signatures")
        if isinstance(n, str):
            if n != "auto":
                raise InputError(f"n: expected a positive integer, 'auto' or None, got {n!r}")
            n = None if sample is None else _choose_n(table, as_float32_2d(sample, "sample"))
        if n is None:
            n = default_n(table.shape[0])
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise InputError(f"n: expected a positive integer, 'auto' or None, got {n!r}")
        limit = max(MAX_CELLS_PER_ENTRY * table.shape[0], MIN_CELL_LIMIT)
        if int(n) ** 2 > limit:
            raise InputError(
                f"n: a {n} x {n} grid ({int(n) ** 2 * 20 / 2 ** 30:.1f} GiB of cells) is far "
                f"too fine for {table.shape[0]} table entries; at most N = "
                f"{int(np.sqrt(limit))} (default {default_n(table.shape[0])})")
        self._build(table, int(n))

    # ------------------------------------------------------------------ build
    def _build(self, table: np.ndarray, n: int) -> None:
        k_entries, dims = table.shape
        t64 = table.astype(np.float64)
        plane, principal, uvh, ci, cj = _plane(t64, n)
        block = block_side(n)
        order, first, cells, block_start = _storage(ci, cj, n, block)
        # np.take: a row gather 5 times faster than fancy indexing (measured).
        sorted64 = np.take(t64, order, axis=0)
        uvh_sorted = np.take(uvh, order, axis=0)
        sketch, entry_sketch = _sketches(principal, plane.center, sorted64)
        entries = _grid_kernels.Entries(
            values=_padded(np.take(table, order, axis=0)), aux=uvh_sorted,
            sketch=entry_sketch,
            cell=np.stack([np.take(ci, order), np.take(cj, order)], axis=1),
            row=order.astype(np.int64))
        self._data = _grid_kernels.GridData(
            plane=plane, entries=entries, cells=cells,
            buckets=_buckets(sorted64, uvh_sorted[:, 2].copy(), first, entry_sketch),
            sketch=sketch,
            blocks=_blocks(entry_sketch, block_start, n, block, plane.delta),
            plan=_scan_plan(n, dims, block, plane.delta))
        self.n = n
        self.size = k_entries
        self.dims = dims
        self.cell_side = plane.delta
        self.half_width = plane.half_width
        self.center = plane.center
        self.axes = plane.axes.copy()
        self.bucket_counts = cells.end - cells.begin

    # ------------------------------------------------------------------ query
    def query(self, queries, *, threads: int | None = None, return_stats: bool = False):
        """Find the exact nearest table entry of every query.

        Parameters
        ----------
        queries : (Q, D) array_like
            Query signatures, finite, same D as the table.
        threads : int, optional
            Number of threads (default: all of numba's threads).
        return_stats : bool, optional
            Also return a :class:`QueryStats` (buckets examined b, entries tested d).

        Returns
        -------
        rows : (Q,) ndarray of int64
            Index into the table (the ``signatures`` given to the constructor)
            of the nearest entry; of entries at the same distance (compared in
            float64), the lowest row.
        distances : (Q,) ndarray of float32
            Euclidean distance to that entry.
        stats : QueryStats
            Only when ``return_stats`` is true.
        """
        q = as_float32_2d(queries, "queries")
        if q.shape[1] != self.dims:
            raise InputError(
                f"queries: have {q.shape[1]} dimensions but the table has {self.dims}"
            )
        import numba

        n_threads = resolve_threads(threads)
        rows = np.empty(q.shape[0], dtype=np.int64)
        dist = np.empty(q.shape[0], dtype=np.float32)
        n_buckets = np.empty(q.shape[0], dtype=np.int32)
        n_tests = np.empty(q.shape[0], dtype=np.int32)
        previous = numba.get_num_threads()
        numba.set_num_threads(n_threads)
        try:
            # Lookup cost varies over an image (noisy or unlit regions): hand out
            # chunks of queries to threads dynamically, not in two fixed halves.
            with numba.parallel_chunksize(THREAD_CHUNKS):
                _grid_kernels.lookup(q, *self._data, rows, dist, n_buckets, n_tests)
        finally:
            numba.set_num_threads(previous)
        if not return_stats:
            return rows, dist
        stats = QueryStats(float(n_buckets.mean()), float(n_tests.mean()), n_buckets, n_tests)
        return rows, dist, stats

    @property
    def nbytes(self) -> int:
        """Bytes of the grid's arrays (what keeping it costs)."""
        def total(value):
            if isinstance(value, np.ndarray):
                return value.nbytes
            return sum(total(v) for v in value) if isinstance(value, tuple) else 0
        return total(tuple(self._data)) + self.bucket_counts.nbytes

    def __repr__(self) -> str:
        return (f"BucketGrid(size={self.size}, dims={self.dims}, n={self.n}, "
                f"alpha={self.size / self.n ** 2:.3g})")


def default_n(size: int) -> int:
    """The default grid size N for a table of ``size`` entries (paper's optimum)."""
    return max(1, int(round(CELLS_PER_SQRT_ENTRY * np.sqrt(size))))


def _choose_n(table: np.ndarray, sample: np.ndarray,
              max_sample: int = AUTO_N_SAMPLE) -> int:
    """Pick the fastest grid size N for queries like ``sample`` (timed, 1 thread)."""
    if sample.shape[1] != table.shape[1]:
        raise InputError(
            f"sample: has {sample.shape[1]} dimensions but the table has {table.shape[1]}"
        )
    if sample.shape[0] > max_sample:
        pick = np.random.default_rng(0).choice(sample.shape[0], max_sample, replace=False)
        sample = sample[pick]
    base = CELLS_PER_SQRT_ENTRY * np.sqrt(table.shape[0])
    candidates = sorted({max(1, int(round(base * f))) for f in AUTO_N_FACTORS})
    best_n, best_time = candidates[0], np.inf
    for n in candidates:
        grid = BucketGrid(table, n)
        grid.query(sample[:8], threads=1)  # compile / warm up
        elapsed = min(_timed(grid, sample) for _ in range(AUTO_N_REPEATS))
        if elapsed < best_time:
            best_n, best_time = n, elapsed
    return best_n


def _timed(grid: BucketGrid, sample: np.ndarray) -> float:
    start = time.perf_counter()
    grid.query(sample, threads=1)
    return time.perf_counter() - start
