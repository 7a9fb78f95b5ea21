"""Compiled kernels of the bucket grid (private; the API is :mod:`colorps.grid`).

Everything here is exact nearest-neighbour search: every pruning test compares
a *lower bound* of a squared distance with the best squared distance found so
far, and prunes only when the bound exceeds it by a safety margin larger than
the rounding error of the float32 distances (``_REL_SLACK``, ``_ABS_SLACK``).

Lower bounds used (q = query, g = table entry, b = table centroid, P = the
projection onto the PCA plane, h(x) = |x - b - P(x - b)| the distance of x from
the plane):

* |q - g|^2 = |P(q - g)|^2 + |(I - P)(q - g)|^2 >= |P(q - g)|^2 + (h(q) - h(g))^2.
  Over a bucket, |P(q - g)| is at least the distance from P q to the bucket's
  rectangle and |h(q) - h(g)| at least the gap between h(q) and the bucket's
  [h_min, h_max] interval.
* eq. 13/14 of the paper: entries in a cell at displacement (r, s) are at least
  delta * ||(r, s)||_dd away (used for early termination, eq. 16), and the same
  at the coarse block level with the block side as delta.
* eq. 12 (bucket truncation): |q - g| >= |q - mu| - rho for every g of a bucket
  with mean mu and radius rho.
"""

import numpy as np
from numba import njit, prange

_REL_SLACK = 1e-4
_ABS_SLACK = 1e-9
# Bucket truncation (eq. 12) costs one full distance; it pays only when the bucket
# holds more entries than that.
_MIN_ENTRIES_FOR_BALL_TEST = 2
# Reassociation lets LLVM vectorise the dot products; its rounding changes are
# orders of magnitude below the pruning margins above. No flags that assume
# finite values: inputs are checked, but inf is used as "no entry yet".
_FASTMATH = {"reassoc", "contract"}
# Up to this signature dimension a full distance costs no more than any bucket
# test, so phase 1 tests whole runs of cells without looking at their buckets.
RUN_SCAN_DIMS = 8


@njit(cache=True, inline="always")
def _prunable(bound2, dmin2):
    """True when a lower bound ``bound2`` proves nothing can beat ``dmin2``."""
    return bound2 > dmin2 * (1.0 + _REL_SLACK) + _ABS_SLACK


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _dist2(query, table, row):
    acc = np.float32(0.0)
    for k in range(query.shape[0]):
        t = query[k] - table[row, k]
        acc += t * t
    return acc


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _test_entry(query, entries, e, best, dmin2, n_tests):
    """Compute one full distance; keep the entry if it is the closest so far."""
    d2 = np.float64(_dist2(query, entries, e))
    if d2 < dmin2:
        return e, d2, n_tests + 1
    return best, dmin2, n_tests + 1


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _scan_run(query, pu, pv, i, j, run, n, delta, half_width, block, cell_begin,
              cell_end, entries, best, dmin2, n_buckets, n_tests):
    """Test every entry of one run of cells (row i + r, columns j + s0 .. j + s1)."""
    ci = i + run[0]
    if ci < 0 or ci >= n:
        return best, dmin2, n_buckets, n_tests
    c0 = max(j + run[1], 0)
    c1 = min(j + run[2], n - 1)
    if c0 > c1:
        return best, dmin2, n_buckets, n_tests
    gu = _interval_gap(pu, ci * delta - half_width, (ci + 1) * delta - half_width)
    gv = _interval_gap(pv, c0 * delta - half_width, (c1 + 1) * delta - half_width)
    if _prunable(gu * gu + gv * gv, dmin2):
        return best, dmin2, n_buckets, n_tests
    while c0 <= c1:  # cells of one row are contiguous within a block
        stop = min(c1, (c0 // block + 1) * block - 1)
        first = cell_begin[ci * n + c0]
        last = cell_end[ci * n + stop]
        if first < last:
            n_buckets += 1
        for e in range(first, last):
            best, dmin2, n_tests = _test_entry(query, entries, e, best, dmin2, n_tests)
        c0 = stop + 1
    return best, dmin2, n_buckets, n_tests


@njit(cache=True, inline="always")
def _interval_gap(x, lo, hi):
    if x < lo:
        return lo - x
    if x > hi:
        return x - hi
    return 0.0


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _scan_bucket(query, pu, pv, h, bucket, start, stop, entries, entry_aux, bucket_h,
                 bucket_mean, bucket_radius, box_u0, box_v0, delta, best, dmin2,
                 n_buckets, n_tests):
    """Test one non-empty bucket (entries start .. stop - 1); update (best, dmin2, b, d)."""
    gu = _interval_gap(pu, box_u0, box_u0 + delta)
    gv = _interval_gap(pv, box_v0, box_v0 + delta)
    gh = _interval_gap(h, bucket_h[bucket, 0], bucket_h[bucket, 1])
    if _prunable(gu * gu + gv * gv + gh * gh, dmin2):
        return best, dmin2, n_buckets, n_tests
    n_buckets += 1
    if stop - start >= _MIN_ENTRIES_FOR_BALL_TEST and dmin2 < np.inf:
        gap = np.sqrt(np.float64(_dist2(query, bucket_mean, bucket))) - bucket_radius[bucket]
        if gap > 0.0 and _prunable(gap * gap, dmin2):
            return best, dmin2, n_buckets, n_tests
    for e in range(start, stop):
        du = pu - entry_aux[e, 0]
        dv = pv - entry_aux[e, 1]
        dh = h - entry_aux[e, 2]
        if _prunable(du * du + dv * dv + dh * dh, dmin2):
            continue
        best, dmin2, n_tests = _test_entry(query, entries, e, best, dmin2, n_tests)
    return best, dmin2, n_buckets, n_tests


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _lookup_one(query, scratch, center, axes, half_width, delta, n, entries,
                entry_aux, entry_far, entry_cell, cell_bucket, cell_begin, cell_end,
                bucket_h, bucket_mean, bucket_radius, scan_offsets, scan_bound2, fine_is_all,
                fine_dd2_max, block, n_blocks, block_start, block_box,
                block_offsets, block_bound2, entry_bound, run_scan):
    """Exact nearest entry of one query: (row in ``entries``, squared distance, b, d)."""
    # Projection on the PCA plane and distance from it, in float64.
    pu = 0.0
    pv = 0.0
    r2 = 0.0
    for k in range(query.shape[0]):
        t = np.float64(query[k]) - center[k]
        pu += t * axes[0, k]
        pv += t * axes[1, k]
        r2 += t * t
    h = np.sqrt(max(r2 - pu * pu - pv * pv, 0.0))
    i = min(max(int(np.floor((pu + half_width) / delta)), 0), n - 1)
    j = min(max(int(np.floor((pv + half_width) / delta)), 0), n - 1)

    best = -1
    dmin2 = np.inf
    n_buckets = 0
    n_tests = 0

    # Phase 1: the paper's scan (Procedure 1) over the nearby cells, eq. 15 order.
    # Either in runs (low dimensions: the cells of one row that share a bound,
    # one contiguous range of entries) or cell by cell; the other list is empty.
    runs, run_bound2 = run_scan
    for o in range(runs.shape[0]):
        if _prunable(run_bound2[o], dmin2):  # early termination, eq. 16
            return best, dmin2, n_buckets, n_tests
        best, dmin2, n_buckets, n_tests = _scan_run(
            query, pu, pv, i, j, runs[o], n, delta, half_width, block, cell_begin,
            cell_end, entries, best, dmin2, n_buckets, n_tests)
    for o in range(scan_offsets.shape[0]):
        if _prunable(scan_bound2[o], dmin2):  # early termination, eq. 16
            return best, dmin2, n_buckets, n_tests
        ci = i + scan_offsets[o, 0]
        cj = j + scan_offsets[o, 1]
        if ci < 0 or ci >= n or cj < 0 or cj >= n:
            continue
        bucket = cell_bucket[ci * n + cj]
        if bucket < 0:
            continue
        best, dmin2, n_buckets, n_tests = _scan_bucket(
            query, pu, pv, h, bucket, cell_begin[ci * n + cj], cell_end[ci * n + cj],
            entries, entry_aux, bucket_h, bucket_mean, bucket_radius,
            ci * delta - half_width, cj * delta - half_width, delta, best, dmin2,
            n_buckets, n_tests)
    if fine_is_all:  # phase 1 covered the whole grid
        return best, dmin2, n_buckets, n_tests

    # Phase 2: the query lies far from the table. Scan blocks of block x block
    # cells in the same order at the coarse level; bound blocks and entries with
    # the k leading principal components plus the residual beyond them, which
    # stays tight where the manifold curves away from the plane.
    n_axes = scratch.shape[0] - 1
    res2 = r2
    for a in range(n_axes):
        t = 0.0
        for k in range(query.shape[0]):
            t += (np.float64(query[k]) - center[k]) * axes[a, k]
        scratch[a] = t
        res2 -= t * t
    scratch[n_axes] = np.sqrt(max(res2, 0.0))
    bi = i // block
    bj = j // block
    for o in range(block_offsets.shape[0]):
        if _prunable(block_bound2[o], dmin2):
            break
        ki = bi + block_offsets[o, 0]
        kj = bj + block_offsets[o, 1]
        if ki < 0 or ki >= n_blocks or kj < 0 or kj >= n_blocks:
            continue
        kb = ki * n_blocks + kj
        start = block_start[kb]
        stop = block_start[kb + 1]
        if start == stop:
            continue
        lb = 0.0
        for a in range(n_axes + 1):
            g = _interval_gap(scratch[a], block_box[kb, 2 * a], block_box[kb, 2 * a + 1])
            lb += g * g
        if _prunable(lb, dmin2):
            continue
        n_buckets += 1
        for e in range(start, stop):
            ri = max(abs(entry_cell[e, 0] - i) - 1, 0)
            rj = max(abs(entry_cell[e, 1] - j) - 1, 0)
            if ri * ri + rj * rj <= fine_dd2_max:
                continue  # phase 1 tested it
            if entry_bound:
                lb = 0.0
                for a in range(n_axes + 1):
                    g = scratch[a] - entry_far[e, a]
                    lb += g * g
                if _prunable(lb, dmin2):
                    continue
            best, dmin2, n_tests = _test_entry(query, entries, e, best, dmin2, n_tests)
    return best, dmin2, n_buckets, n_tests


_CHUNK = 256


@njit(cache=True, parallel=True, fastmath=_FASTMATH)
def lookup(queries, far_axes, center, axes, half_width, delta, n, entries, entry_aux,
           entry_far, entry_cell, cell_bucket, cell_begin, cell_end, bucket_h,
           bucket_mean, bucket_radius, scan_offsets, scan_bound2, fine_is_all,
           fine_dd2_max, block,
           n_blocks, block_start, block_box, block_offsets, block_bound2, entry_bound,
           run_scan, out_row, out_dist, out_buckets, out_tests):
    """Nearest table row for every query (``prange`` over chunks of queries).

    Each chunk allocates its (far_axes + 1) scratch values once, outside the
    per-query loop.
    """
    n_queries = queries.shape[0]
    n_chunks = (n_queries + _CHUNK - 1) // _CHUNK
    for chunk in prange(n_chunks):
        scratch = np.empty(far_axes + 1)
        for q in range(chunk * _CHUNK, min((chunk + 1) * _CHUNK, n_queries)):
            best, dmin2, nb, nd = _lookup_one(
                queries[q], scratch, center, axes, half_width, delta, n, entries,
                entry_aux, entry_far, entry_cell, cell_bucket, cell_begin, cell_end,
                bucket_h, bucket_mean, bucket_radius, scan_offsets, scan_bound2, fine_is_all,
                fine_dd2_max, block, n_blocks, block_start, block_box,
                block_offsets, block_bound2, entry_bound, run_scan)
            out_row[q] = best
            out_dist[q] = np.sqrt(dmin2)
            out_buckets[q] = nb
            out_tests[q] = nd
