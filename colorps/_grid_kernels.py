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
* the sketch bound: with A the k leading principal axes and r(x) the residual
  beyond them, |q - g|^2 >= |A(q - g)|^2 + (r(q) - r(g))^2. The sketch
  (A(x - b), r(x)) has at most ``SKETCH_LANES`` float32 lanes. Entries keep
  their sketch, buckets and blocks the box of their entries' sketches; a
  query's sketch is computed in float32 and widened into intervals that
  contain the exact values (``_query_sketch``), so every test stays a true
  lower bound. It stays tight where the manifold curves away from the plane,
  and for queries far from the table or with many near-ties.
"""

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

# ---------------------------------------------------------------- 16-lane vectors
# numba leaves the lane count of its loops to LLVM, which splits a loop with a
# run-time trip count into a vector loop, a narrower vector loop for the tail and
# a scalar remainder, each with its own horizontal sum. For the grid's short
# vectors (16 sketch lanes, up to a few hundred signature dimensions) those tails
# and sums are most of the latency of a bound or a distance, and the next pruning
# decision waits for them. These two intrinsics state the width instead: rows
# are whole multiples of LANES float32 values (zero-padded by the grid), read as
# <16 x float> and summed once. Where the CPU has no 512-bit registers LLVM
# splits each vector into narrower ones; results are the same. They live in
# this file because numba's cache only notices changes to the file that defines
# a cached function.

LANES = 16
_VECTOR = ir.VectorType(ir.FloatType(), LANES)
# As the kernels' fastmath: sums may be reassociated, never assumed finite.
_FLAGS = ("reassoc", "contract")


def _is_float32_c(array_type, ndim: int) -> bool:
    return (isinstance(array_type, types.Array) and array_type.dtype == types.float32
            and array_type.ndim == ndim and array_type.layout == "C")


def _vector_pointer(context, builder, array_type, array, indices):
    """Pointer to ``array[indices]`` as a pointer to 16-lane vectors."""
    proxy = context.make_array(array_type)(context, builder, array)
    element = cgutils.get_item_pointer(context, builder, array_type, proxy, indices)
    return builder.bitcast(element, _VECTOR.as_pointer())


def _load(builder, pointer, chunk):
    # Rows are only 4-byte aligned: unaligned vector loads.
    return builder.load(builder.gep(pointer, [chunk]), align=4)


def _sum_lanes(builder, vector):
    reduce_type = ir.FunctionType(ir.FloatType(), [ir.FloatType(), _VECTOR])
    reduce = cgutils.get_or_insert_function(builder.module, reduce_type,
                                            "llvm.vector.reduce.fadd.v16f32")
    # -0.0 is the identity of fadd: the start value costs no addition.
    return builder.call(reduce, [ir.Constant(ir.FloatType(), -0.0), vector],
                        fastmath=_FLAGS)


@intrinsic
def squared_distance(typingctx, query, table, row):
    """float32 |query - table[row]|^2 over ``table.shape[1]`` values.

    ``table.shape[1]`` must be a multiple of ``LANES`` and ``query`` at least
    that long; the padding must be zero in both.
    """
    if not (_is_float32_c(query, 1) and _is_float32_c(table, 2)
            and isinstance(row, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        query_value, table_value, row_value = args
        index_type = context.get_value_type(types.intp)
        zero = ir.Constant(index_type, 0)
        row_index = context.cast(builder, row_value, signature.args[2], types.intp)
        q = _vector_pointer(context, builder, signature.args[0], query_value, [zero])
        t = _vector_pointer(context, builder, signature.args[1], table_value,
                            [row_index, zero])
        table_proxy = context.make_array(signature.args[1])(context, builder, table_value)
        width = cgutils.unpack_tuple(builder, table_proxy.shape)[1]
        chunks = builder.udiv(width, ir.Constant(index_type, LANES))
        total = cgutils.alloca_once_value(builder, ir.Constant(_VECTOR, None))
        with cgutils.for_range(builder, chunks) as loop:
            chunk = loop.index
            diff = builder.fsub(_load(builder, q, chunk), _load(builder, t, chunk),
                                flags=_FLAGS)
            square = builder.fmul(diff, diff, flags=_FLAGS)
            builder.store(builder.fadd(builder.load(total), square, flags=_FLAGS), total)
        return _sum_lanes(builder, builder.load(total))

    return types.float32(query, table, row), codegen


@intrinsic
def box_gap(typingctx, low, high, box_low, box_high, row):
    """float32 sum over lanes of max(box_low[row] - high, low - box_high[row], 0)^2.

    The squared distance between the intervals [low, high] (one per lane,
    ``LANES`` lanes) and box ``row``; 0 in lanes where they overlap.
    """
    if not (_is_float32_c(low, 1) and _is_float32_c(high, 1)
            and _is_float32_c(box_low, 2) and _is_float32_c(box_high, 2)
            and isinstance(row, types.Integer)):
        return None

    def codegen(context, builder, signature, args):
        low_value, high_value, box_low_value, box_high_value, row_value = args
        index_type = context.get_value_type(types.intp)
        zero = ir.Constant(index_type, 0)
        row_index = context.cast(builder, row_value, signature.args[4], types.intp)
        lo = builder.load(_vector_pointer(context, builder, signature.args[0], low_value,
                                          [zero]), align=4)
        hi = builder.load(_vector_pointer(context, builder, signature.args[1], high_value,
                                          [zero]), align=4)
        box_lo = builder.load(_vector_pointer(context, builder, signature.args[2],
                                              box_low_value, [row_index, zero]), align=4)
        box_hi = builder.load(_vector_pointer(context, builder, signature.args[3],
                                              box_high_value, [row_index, zero]), align=4)
        below = builder.fsub(box_lo, hi, flags=_FLAGS)  # box above the interval
        above = builder.fsub(lo, box_hi, flags=_FLAGS)  # box below it
        gap = builder.select(builder.fcmp_ordered(">", below, above), below, above)
        nothing = ir.Constant(_VECTOR, None)
        gap = builder.select(builder.fcmp_ordered(">", gap, nothing), gap, nothing)
        return _sum_lanes(builder, builder.fmul(gap, gap, flags=_FLAGS))

    return types.float32(low, high, box_low, box_high, row), codegen


_REL_SLACK = 1e-4
_ABS_SLACK = 1e-9
# Bucket truncation (eq. 12) costs one full distance; it pays only when the bucket
# holds more entries than that.
_MIN_ENTRIES_FOR_BALL_TEST = 2
# Above this many entries a bucket's (u, v, h) bounds per entry pay before its
# sketch bounds (measured: 1.5x faster with N = 1 at D = 90, 3 % slower at
# N = 202 where buckets hold up to 16).
_LARGE_BUCKET = 32
# Above D = 8 the fine scan hands over to the coarse level early when, after the
# first _SWITCH_AFTER cells, the best entry is still more than _SWITCH_CELLS
# cells away (sigma = 0.02: 0.55-0.73x; sigma = 0.005 unchanged, measured).
_SWITCH_CELLS = 4.0
_SWITCH_AFTER = 25
# Reassociation lets LLVM vectorise the dot products; its rounding changes are
# orders of magnitude below the pruning margins above. No flags that assume
# finite values: inputs are checked, but inf is used as "no entry yet".
_FASTMATH = {"reassoc", "contract"}
# Up to this signature dimension a full distance costs no more than any bucket
# test, so phase 1 tests whole runs of cells without looking at their buckets.
# Above it, entries (and queries, in a scratch row) are zero-padded to whole
# vectors of LANES, whose distances squared_distance computes in one pass.
RUN_SCAN_DIMS = 8
# Lanes of a sketch: principal-axis coordinates, then the residual (one vector
# of LANES float32). Unused axis lanes are zero in queries and boxes alike.
SKETCH_LANES = LANES
_U32 = 2.0 ** -24  # unit roundoff of float32


@njit(cache=True, inline="always")
def _prunable(bound2, dmin2):
    """True when a lower bound ``bound2`` proves nothing can beat ``dmin2``."""
    return bound2 > dmin2 * (1.0 + _REL_SLACK) + _ABS_SLACK


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _dist2_short(query, table, row):
    """float32 |query - table[row]|^2 for rows of up to RUN_SCAN_DIMS values."""
    acc = np.float32(0.0)
    for k in range(table.shape[1]):
        t = query[k] - table[row, k]
        acc += t * t
    return acc


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _dist2(query, table, row):
    """float32 |query - table[row]|^2 over the table's (padded) width."""
    if table.shape[1] > RUN_SCAN_DIMS:  # zero-padded to whole vectors
        return squared_distance(query, table, row)
    return _dist2_short(query, table, row)


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _test_entry(query, entries, e, best, dmin2, n_tests):
    """Compute one full distance; keep the entry if it is the closest so far."""
    d2 = np.float64(_dist2(query, entries, e))
    if d2 < dmin2:
        return e, d2, n_tests + 1
    return best, dmin2, n_tests + 1


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _scan_run(query, pu, pv, i, j, run, n, delta, half_width, block_last, cell_begin,
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
        stop = min(c1, block_last[c0])
        first = cell_begin[ci * n + c0]
        last = cell_end[ci * n + stop]
        if first < last:
            n_buckets += 1
        for e in range(first, last):  # runs are used up to RUN_SCAN_DIMS only
            d2 = np.float64(_dist2_short(query, entries, e))
            if d2 < dmin2:
                best = e
                dmin2 = d2
        n_tests += last - first
        c0 = stop + 1
    return best, dmin2, n_buckets, n_tests


@njit(cache=True, inline="always")
def _dd2(dr, ds):
    """Squared eq. 15 norm ||(r, s)||_dd^2 of a cell displacement, in cells."""
    return max(abs(dr) - 1, 0) ** 2 + max(abs(ds) - 1, 0) ** 2


@njit(cache=True, inline="always")
def _interval_gap(x, lo, hi):
    """Distance from x to the interval [lo, hi] (0 inside).

    With tests: in the run scan (D <= 8) the outcome is predictable, and this
    is 7-11 % faster there than ``_interval_gap_free``.
    """
    if x < lo:
        return lo - x
    if x > hi:
        return x - hi
    return 0.0


@njit(cache=True, inline="always")
def _interval_gap_free(x, lo, hi):
    """``_interval_gap`` without branches, for the bucket tests (D > 8), whose
    outcome is unpredictable (D = 90 theta 45: 0.87x in one comparison; other
    cases within this machine's noise)."""
    return max(lo - x, x - hi, 0.0)


_AXES_PER_PASS = 5
# The sketch's axis rows (SKETCH_LANES - 1 of them) are read five at a time.
assert (SKETCH_LANES - 1) % _AXES_PER_PASS == 0


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _dots5(query, axes, a0):
    """Dot products of ``query`` with axes a0 .. a0 + 4 in one pass (float32).

    Five independent sums hide each other's addition latency: 30 % faster
    than one axis per pass at D = 90.
    """
    t0 = np.float32(0.0)
    t1 = np.float32(0.0)
    t2 = np.float32(0.0)
    t3 = np.float32(0.0)
    t4 = np.float32(0.0)
    for k in range(axes.shape[1]):
        x = query[k]
        t0 += x * axes[a0, k]
        t1 += x * axes[a0 + 1, k]
        t2 += x * axes[a0 + 2, k]
        t3 += x * axes[a0 + 3, k]
        t4 += x * axes[a0 + 4, k]
    return (t0, t1, t2, t3, t4)


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _query_sketch(query, r2, q_norm2, sketch, low, high):
    """Intervals [low, high] (float32, per lane) that contain the query's exact sketch.

    ``r2`` is |q - b|^2 and ``q_norm2`` is |q|^2 (float64). The axis
    coordinates are float32 dot products: each is within ``tau`` of A(q - b),
    from the standard bound D u sum_k |q_k A_ak| <= D u |q| on a float32 dot
    product (|A_a| = 1, any order of summation), plus the rounding of the
    stored offset A b and of the result. The residual is
    r^2 = |q - b|^2 - |A(q - b)|^2 / sigma^2, with sigma >= 1 the largest
    singular value of the float32 axes: rounded axes are not exactly
    orthonormal, and this keeps r a seminorm, so the bound holds. Its
    interval follows from the errors of the squared coordinates. Every
    interval is further widened by ``point_slack``, the largest distance
    between an entry's exact sketch and its stored float32 one, so stored
    sketches (and boxes of them) can be compared as they are.
    """
    axes, offset, n_axes, center_norm, inv_sigma2, point_slack = sketch
    tau = (1.25 * (axes.shape[1] + 8) * _U32 * (np.sqrt(q_norm2) + center_norm)
           + point_slack)
    res2 = r2
    err2 = 1e-12 * r2
    for a0 in range(0, n_axes, _AXES_PER_PASS):
        dots = _dots5(query, axes, a0)
        for r in range(_AXES_PER_PASS):
            a = a0 + r
            if a < n_axes:
                x = np.float64(dots[r] - offset[a])
                res2 -= inv_sigma2 * x * x
                err2 += tau * (2.0 * abs(x) + tau)
                low[a] = x - tau
                high[a] = x + tau
    low[n_axes] = np.sqrt(max(res2 - err2, 0.0)) * (1.0 - 4.0 * _U32) - point_slack
    high[n_axes] = np.sqrt(max(res2 + err2, 0.0)) * (1.0 + 4.0 * _U32) + point_slack


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _sketch_gap2(low, high, box_low, box_high, row):
    """Squared distance between a query's sketch intervals and box ``row``.

    A box is one bucket's or block's (``box_low``, ``box_high`` corners), or an
    entry's own sketch (the same array as both corners). All ``SKETCH_LANES``
    lanes are compared: unused ones are 0 in both.
    """
    return np.float64(box_gap(low, high, box_low, box_high, row))


@njit(cache=True, inline="always")
def _aux_gap2(pu, pv, h, entry_aux, e):
    """Lower bound |P(q - g)|^2 + (h(q) - h(g))^2 from entry e's (u, v, h)."""
    du = pu - entry_aux[e, 0]
    dv = pv - entry_aux[e, 1]
    dh = h - entry_aux[e, 2]
    return du * du + dv * dv + dh * dh


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _scan_bucket(query, pu, pv, h, has_sketch, low, high, bucket, start, stop,
                 entries, entry_aux, entry_sketch, entry_bound, bucket_h, box_low,
                 box_high, bucket_mean, bucket_radius, box_u0, box_v0, delta, best,
                 dmin2, n_buckets, n_tests):
    """Test one non-empty bucket (entries start .. stop - 1); update (best, dmin2, b, d).

    (pu, pv, h) is the query's (u, v, h); with ``has_sketch`` its sketch
    intervals (``low``, ``high``) are known.

    * With the sketch: the bucket's sketch box, then (``entry_bound``, buckets
      of several entries) each entry's sketch. The sketch box contains the
      (u, v) rectangle test, which costs more than it saves here.
    * Without, one entry: that entry's (u, v, h) bound, tighter than the
      bucket's and no dearer.
    * Without, several entries: the cell's rectangle and the bucket's interval
      of distances from the PCA plane, bucket truncation (eq. 12), then the
      per-entry (u, v, h) bound.
    """
    if has_sketch:
        if _prunable(_sketch_gap2(low, high, box_low, box_high, bucket), dmin2):
            return best, dmin2, n_buckets, n_tests
        n_buckets += 1
        if stop - start == 1:  # the bucket's box is its entry's sketch
            best, dmin2, n_tests = _test_entry(query, entries, start, best, dmin2, n_tests)
            return best, dmin2, n_buckets, n_tests
        # Up to D = 16 the (u, v, h) bound is the only per-entry test worth its
        # cost. Above, the entry's sketch bound is, and the (u, v, h) bound
        # comes first only in large buckets (coarse grids), where it prunes most.
        aux_first = not entry_bound or stop - start > _LARGE_BUCKET
        for e in range(start, stop):
            if aux_first and _prunable(_aux_gap2(pu, pv, h, entry_aux, e), dmin2):
                continue
            if entry_bound and _prunable(
                    _sketch_gap2(low, high, entry_sketch, entry_sketch, e), dmin2):
                continue
            best, dmin2, n_tests = _test_entry(query, entries, e, best, dmin2, n_tests)
        return best, dmin2, n_buckets, n_tests
    if stop - start == 1:  # the entry's own (u, v, h) bound is tighter
        if _prunable(_aux_gap2(pu, pv, h, entry_aux, start), dmin2):
            return best, dmin2, n_buckets, n_tests
        best, dmin2, n_tests = _test_entry(query, entries, start, best, dmin2, n_tests)
        return best, dmin2, n_buckets + 1, n_tests
    gu = _interval_gap_free(pu, box_u0, box_u0 + delta)
    gv = _interval_gap_free(pv, box_v0, box_v0 + delta)
    gh = _interval_gap_free(h, bucket_h[bucket, 0], bucket_h[bucket, 1])
    if _prunable(gu * gu + gv * gv + gh * gh, dmin2):
        return best, dmin2, n_buckets, n_tests
    n_buckets += 1
    if stop - start >= _MIN_ENTRIES_FOR_BALL_TEST and dmin2 < np.inf:
        centre_dist = np.sqrt(np.float64(_dist2(query, bucket_mean, bucket)))
        gap = centre_dist - bucket_radius[bucket]
        if gap > 0.0 and _prunable(gap * gap, dmin2):
            return best, dmin2, n_buckets, n_tests
    for e in range(start, stop):
        if _prunable(_aux_gap2(pu, pv, h, entry_aux, e), dmin2):
            continue
        best, dmin2, n_tests = _test_entry(query, entries, e, best, dmin2, n_tests)
    return best, dmin2, n_buckets, n_tests


@njit(cache=True, inline="always", fastmath=_FASTMATH)
def _lookup_one(query, low, high, center, axes, half_width, delta, n, entries,
                entry_aux, entry_sketch, entry_cell, cell_bucket, cell_begin, cell_end,
                buckets, sketch, scan_offsets, scan_bound, fine_is_all,
                fine_dd2_max, block, n_blocks, block_start, block_boxes,
                block_offsets, block_bound2, entry_bound, run_scan, eager):
    """Exact nearest entry of one query.

    Returns (row in ``entries``, squared distance, b, d, whether the query's
    sketch was computed). ``low`` and ``high`` are the caller's scratch space
    for the query's sketch intervals (``SKETCH_LANES`` float32 each). With
    ``eager`` the sketch is computed at the first non-empty bucket.
    """
    # Projection on the PCA plane and distance from it, in float64.
    pu = 0.0
    pv = 0.0
    r2 = 0.0
    q_norm2 = 0.0
    for k in range(center.shape[0]):
        x = np.float64(query[k])
        t = x - center[k]
        pu += t * axes[0, k]
        pv += t * axes[1, k]
        r2 += t * t
        q_norm2 += x * x
    h = np.sqrt(max(r2 - pu * pu - pv * pv, 0.0))
    i = min(max(int(np.floor((pu + half_width) / delta)), 0), n - 1)
    j = min(max(int(np.floor((pv + half_width) / delta)), 0), n - 1)
    # Eq. 15 bounds a cell's distance for a query anywhere in cell (i, j). This
    # query lies ``margin`` inside every border of its cell, so every cell but
    # its own is at least (delta ||(r, s)||_dd + margin) away.
    fu = (pu + half_width) / delta - i
    fv = (pv + half_width) / delta - j
    margin = max(min(fu, 1.0 - fu, fv, 1.0 - fv), 0.0) * delta

    best = -1
    dmin2 = np.inf
    n_buckets = 0
    n_tests = 0
    has_sketch = False

    # Phase 1: the paper's scan (Procedure 1) over the nearby cells, eq. 15 order.
    # Either in runs (low dimensions: the cells of one row that share a bound,
    # one contiguous range of entries) or cell by cell; the other list is empty.
    runs, run_bound, block_last = run_scan
    for o in range(runs.shape[0]):
        if _prunable((run_bound[o] + margin) ** 2, dmin2):  # early termination, eq. 16
            return best, dmin2, n_buckets, n_tests, has_sketch
        best, dmin2, n_buckets, n_tests = _scan_run(
            query, pu, pv, i, j, runs[o], n, delta, half_width, block_last, cell_begin,
            cell_end, entries, best, dmin2, n_buckets, n_tests)
    # Cell by cell: the query's sketch costs about as much as n_axes full
    # distances, so it is computed before the scan would spend that much
    # (counting the next bucket's entries) and is paid back by the sketch tests
    # from then on: the ski-rental rule, within about twice the better choice
    # made in hindsight. The caller asks for it at once (``eager``) when the
    # previous query, a neighbouring pixel in the pipeline's order, needed it.
    n_axes = sketch[2]
    bucket_h, box_low, box_high, bucket_mean, bucket_radius = buckets
    switch2 = (_SWITCH_CELLS * delta) ** 2
    covered_dd2 = fine_dd2_max + 1  # entries of cells with smaller dd2 were tested
    for o in range(scan_offsets.shape[0]):
        if _prunable((scan_bound[o] + margin) ** 2, dmin2):  # early termination, eq. 16
            return best, dmin2, n_buckets, n_tests, has_sketch
        dr = scan_offsets[o, 0]
        ds = scan_offsets[o, 1]
        if o >= _SWITCH_AFTER and switch2 < dmin2 < np.inf:
            # The best entry so far is more than _SWITCH_CELLS cells away, so
            # the fine scan would visit more than about pi _SWITCH_CELLS^2
            # cells: the coarse level is cheaper. Every cell with a smaller
            # dd2 than this one has been scanned; phase 2 skips only those.
            covered_dd2 = _dd2(dr, ds)
            break
        ci = i + dr
        cj = j + ds
        if ci < 0 or ci >= n or cj < 0 or cj >= n:
            continue
        bucket = cell_bucket[ci * n + cj]
        if bucket < 0:
            continue
        start = cell_begin[ci * n + cj]
        stop = cell_end[ci * n + cj]
        if not has_sketch and (eager or n_tests + (stop - start) > n_axes):
            _query_sketch(query, r2, q_norm2, sketch, low, high)
            has_sketch = True
        best, dmin2, n_buckets, n_tests = _scan_bucket(
            query, pu, pv, h, has_sketch, low, high, bucket,
            start, stop, entries, entry_aux, entry_sketch, entry_bound, bucket_h,
            box_low, box_high, bucket_mean, bucket_radius,
            ci * delta - half_width, cj * delta - half_width, delta, best, dmin2,
            n_buckets, n_tests)
    if fine_is_all and covered_dd2 > fine_dd2_max:  # phase 1 covered the whole grid
        return best, dmin2, n_buckets, n_tests, has_sketch

    # Phase 2: the query lies far from the table. Scan blocks of block x block
    # cells in the same order at the coarse level; bound blocks and entries
    # with the sketch.
    if not has_sketch:
        _query_sketch(query, r2, q_norm2, sketch, low, high)
        has_sketch = True
    block_low, block_high = block_boxes
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
        if _prunable(_sketch_gap2(low, high, block_low, block_high, kb), dmin2):
            continue
        n_buckets += 1
        for e in range(start, stop):
            if _dd2(entry_cell[e, 0] - i, entry_cell[e, 1] - j) < covered_dd2:
                continue  # phase 1 tested it
            if entry_bound and _prunable(
                    _sketch_gap2(low, high, entry_sketch, entry_sketch, e), dmin2):
                continue
            best, dmin2, n_tests = _test_entry(query, entries, e, best, dmin2, n_tests)
    return best, dmin2, n_buckets, n_tests, has_sketch


_CHUNK = 256


@njit(cache=True, parallel=True, fastmath=_FASTMATH)
def lookup(queries, center, axes, half_width, delta, n, entries, entry_aux, entry_sketch,
           entry_cell, cell_bucket, cell_begin, cell_end, buckets, sketch, scan_offsets,
           scan_bound, fine_is_all, fine_dd2_max, block, n_blocks, block_start,
           block_boxes, block_offsets, block_bound2, entry_bound, run_scan, out_row,
           out_dist, out_buckets, out_tests):
    """Nearest table row for every query (``prange`` over chunks of queries).

    Each chunk allocates its scratch space (a query's sketch intervals, and a
    zero-padded copy of the query when entries are padded) once, outside the
    per-query loop.
    """
    n_queries = queries.shape[0]
    n_chunks = (n_queries + _CHUNK - 1) // _CHUNK
    for chunk in prange(n_chunks):
        low = np.zeros(SKETCH_LANES, dtype=np.float32)
        high = np.zeros(SKETCH_LANES, dtype=np.float32)
        padded = np.zeros(entries.shape[1], dtype=np.float32)  # the padding stays 0
        eager = False
        for q in range(chunk * _CHUNK, min((chunk + 1) * _CHUNK, n_queries)):
            query = queries[q]
            if padded.shape[0] > queries.shape[1]:
                padded[:queries.shape[1]] = query
                query = padded
            best, dmin2, nb, nd, sketched = _lookup_one(
                query, low, high, center, axes, half_width, delta, n, entries,
                entry_aux, entry_sketch, entry_cell, cell_bucket, cell_begin, cell_end,
                buckets, sketch, scan_offsets, scan_bound, fine_is_all, fine_dd2_max,
                block, n_blocks, block_start, block_boxes, block_offsets, block_bound2,
                entry_bound, run_scan, eager)
            eager = sketched  # neighbours tend to need the same work
            out_row[q] = best
            out_dist[q] = np.sqrt(dmin2)
            out_buckets[q] = nb
            out_tests[q] = nd
