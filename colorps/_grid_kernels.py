"""Compiled kernels of the bucket grid (private; the API is :mod:`colorps.grid`).

Everything here is exact nearest-neighbour search: every pruning test compares
a *lower bound* of a squared distance with the best squared distance found so
far, and prunes only when the bound exceeds it by a safety margin larger than
the rounding error of the float32 distances (``REL_SLACK``, ``ABS_SLACK``).

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

The grid's data reach the kernels as one :class:`GridData`, a named tuple of
named tuples (numba compiles attribute access on them to plain loads), built by
:mod:`colorps.grid`. The tuning constants of the kernels are in this file,
because numba's cache only notices changes to the file that defines a cached
function; the measurements behind them are in docs/benchmarks.md.
"""

from collections import namedtuple

import numpy as np
from llvmlite import ir
from numba import njit, prange, types
from numba.core import cgutils
from numba.extending import intrinsic

from ._config import FASTMATH

# ---------------------------------------------------------------- tuning
#: Relative and absolute margins of every pruning test (float32 rounding of
#: distances is far below them).
REL_SLACK = 1e-4
ABS_SLACK = 1e-9
#: Bucket truncation (eq. 12) costs one full distance; it pays only when the
#: bucket holds more entries than that.
MIN_ENTRIES_FOR_BALL_TEST = 2
#: Above this many entries a bucket's (u, v, h) bounds per entry pay before its
#: sketch bounds (measured: 1.5x faster with N = 1 at D = 90, 3 % slower at
#: N = 202 where buckets hold up to 16).
LARGE_BUCKET = 32
#: Above D = 8 the fine scan hands over to the coarse level early when, after
#: the first SWITCH_AFTER cells, the best entry is still more than SWITCH_CELLS
#: cells away (sigma = 0.02: 0.55-0.73x; sigma = 0.005 unchanged, measured).
SWITCH_CELLS = 4.0
SWITCH_AFTER = 25
#: Up to this signature dimension a full distance costs no more than any bucket
#: test, so phase 1 tests whole runs of cells without looking at their buckets.
#: Above it, entries (and queries, in a scratch row) are zero-padded to whole
#: vectors of LANES, whose distances squared_distance computes in one pass.
RUN_SCAN_DIMS = 8
#: float32 values per vector of the intrinsics below.
LANES = 16
#: Lanes of a sketch: principal-axis coordinates, then the residual (one vector
#: of LANES float32). Unused axis lanes are zero in queries and boxes alike.
SKETCH_LANES = LANES
#: The query's sketch reads the axis rows this many at a time (independent
#: sums hide each other's latency: 30 % faster than one at a time at D = 90).
AXES_PER_PASS = 5
assert (SKETCH_LANES - 1) % AXES_PER_PASS == 0
#: Queries per unit of work handed to a thread (each allocates its scratch once).
QUERY_CHUNK = 256
U32 = 2.0 ** -24  # unit roundoff of float32
#: Exact squared distances within this relative margin are a tie, which the
#: lower table row wins. Far above float64 rounding (the same distance summed
#: in another order, or compiled for another call, differs in its last bits),
#: far below any difference float32 signatures can make.
TIE_REL = 1e-12

# ---------------------------------------------------------------- data layout
#: The PCA plane and the grid on it. center (D,) and axes (2, D) float64 (the
#: table's centroid b and two leading principal axes); half_width R and cell
#: side delta (signature units); n cells per side.
Plane = namedtuple("Plane", "center axes half_width delta n")
#: Table entries in storage order (by block, then cell, row-major). values
#: (K, W) float32, zero-padded to W >= D; aux (K, 3) float64 (u, v, h); sketch
#: (K, SKETCH_LANES) float32; cell (K, 2) int64 (row i, column j of its cell);
#: row (K,) int64, the entry's row in the table given.
Entries = namedtuple("Entries", "values aux sketch cell row")
#: Per cell (flat index i n + j): bucket number (-1: empty) and the range
#: begin .. end of its entries, int64.
Cells = namedtuple("Cells", "bucket begin end")
#: Per non-empty bucket: h_range (B, 2) float64 [h_min, h_max]; box_low,
#: box_high (B, SKETCH_LANES) float32 sketch box; mean (B, W) float32 (padded
#: like entries); radius (B,) float64 about that mean.
Buckets = namedtuple("Buckets", "h_range box_low box_high mean radius")
#: The sketch definition (see ``_query_sketch``): axes (SKETCH_LANES - 1, D)
#: float32, offset (SKETCH_LANES - 1,) float32 = axes b, n_axes used, |b|,
#: 1 / sigma^2, and point_slack (the stored sketches' largest rounding error).
Sketch = namedtuple("Sketch", "axes offset n_axes center_norm inv_sigma2 point_slack")
#: The coarse level: blocks of side x side cells, count per side; start
#: (count^2 + 1,) int64 entry ranges; box_low, box_high sketch boxes; offsets
#: (L, 2) int32 in eq. 15 order and bound2 (L,) their squared distance bounds.
Blocks = namedtuple("Blocks", "side count start box_low box_high offsets bound2")
#: How phase 1 scans: with use_runs, runs (R, 3) int64 (r, s0, s1) of cells of
#: one row sharing a bound run_bound (R,), block_last (n,) the last column of
#: each column's block; else offsets (L, 2) int32 cell by cell with bound (L,).
#: fine_is_all: phase 1 reaches every cell; fine_dd2_max: its reach (cells^2);
#: entry_bound: phase 2 bounds each entry by its sketch (D > SKETCH_LANES).
ScanPlan = namedtuple("ScanPlan", "use_runs runs run_bound block_last offsets bound "
                                  "fine_is_all fine_dd2_max entry_bound")
#: Everything a lookup reads.
GridData = namedtuple("GridData", "plane entries cells buckets sketch blocks plan")
#: The state of one lookup: best entry so far (-1: none), the smallest float32
#: squared distance seen (what pruning compares with), buckets examined, full
#: distances computed, and the best entry's exact squared distance (-1: not
#: computed yet; then dmin2 is the best's).
Search = namedtuple("Search", "best dmin2 buckets tests exact")
#: A query on the PCA plane: (u, v), its distance h from the plane, |q - b|^2
#: and |q|^2 (float64).
Position = namedtuple("Position", "u v h r2 norm2")

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

_VECTOR = ir.VectorType(ir.FloatType(), LANES)
# As the kernels' fastmath: sums may be reassociated, never assumed finite.
_FLAGS = tuple(sorted(FASTMATH))


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


# ---------------------------------------------------------------- bounds
def prune_limit(dmin2):
    """The largest squared distance that could still beat ``dmin2`` (scalar or
    array): above it a lower bound prunes. Plain Python for the brute force of
    :mod:`colorps.tables`, compiled as :func:`_prune_limit` for the kernels."""
    return dmin2 * (1.0 + REL_SLACK) + ABS_SLACK


_prune_limit = njit(cache=True, inline="always")(prune_limit)


@njit(cache=True, inline="always")
def _prunable(bound2, dmin2):
    """True when a lower bound ``bound2`` proves nothing can beat ``dmin2``."""
    return bound2 > _prune_limit(dmin2)


@njit(cache=True, inline="always", fastmath=FASTMATH)
def _dist2_short(query, table, row):
    """float32 |query - table[row]|^2 for rows of up to RUN_SCAN_DIMS values."""
    acc = np.float32(0.0)
    for k in range(table.shape[1]):
        t = query[k] - table[row, k]
        acc += t * t
    return acc


@njit(cache=True, inline="always", fastmath=FASTMATH)
def _dist2(query, table, row):
    """float32 |query - table[row]|^2 over the table's (padded) width."""
    if table.shape[1] > RUN_SCAN_DIMS:  # zero-padded to whole vectors
        return squared_distance(query, table, row)
    return _dist2_short(query, table, row)


@njit(cache=True)
def exact_distance2(query, table, row):
    """|query - table[row]|^2 in float64 over ``table.shape[1]`` values.

    What every lookup, grid or brute force, decides near ties with (see
    :func:`nearer`)."""
    acc = 0.0
    for k in range(table.shape[1]):
        t = np.float64(query[k]) - np.float64(table[row, k])
        acc += t * t
    return acc


@njit(cache=True, inline="always")
def nearer(exact, row, best_exact, best_row):
    """True when a table row at exact squared distance ``exact`` beats the best
    so far: nearer by more than TIE_REL, or as near with a lower row. The one
    rule of the grid's lookup and of the brute force, so both return the same
    row however they visit the table."""
    if best_row < 0 or exact < best_exact * (1.0 - TIE_REL):
        return True
    return exact <= best_exact * (1.0 + TIE_REL) and row < best_row


@njit(cache=True)
def nearest_of_candidates(queries, table, pair_query, pair_row, out_row):
    """For each query, the nearest of its candidate rows into ``out_row``.

    Pairs (``pair_query[i]``, ``pair_row[i]``) are compared by :func:`nearer`,
    for a brute-force search that keeps every row within the pruning margin of
    its smallest approximate distance."""
    best = np.full(queries.shape[0], np.inf)
    out_row[:] = -1
    for i in range(pair_query.shape[0]):
        q = pair_query[i]
        r = pair_row[i]
        exact = exact_distance2(queries[q], table, r)
        if nearer(exact, r, best[q], out_row[q]):
            best[q] = exact
            out_row[q] = r


@njit(cache=True, inline="always", fastmath=FASTMATH)
def _keep_nearer(query, values, rows, e, d2, best, dmin2, exact):
    """(best, dmin2, exact) of a search (see :class:`Search`) after entry e, at
    float32 squared distance d2, if it is :func:`nearer` than the best so far.

    An entry farther than the pruning margin of the smallest float32 distance
    seen cannot be, one nearer than that by the margin is (the rounding of
    float32 distances is far smaller): only those in between, near ties, are
    compared exactly (:func:`_near_tie`)."""
    if _prunable(d2, dmin2):
        return best, dmin2, exact
    if d2 < dmin2 * (1.0 - REL_SLACK) - ABS_SLACK:
        return e, d2, -1.0
    return _near_tie(query, values, rows, e, d2, best, dmin2, exact)


@njit(cache=True, fastmath=FASTMATH)  # not inlined: rare, and kept out of the hot loops
def _near_tie(query, values, rows, e, d2, best, dmin2, exact):
    """:func:`_keep_nearer` for an entry within the margin of the best: compared
    exactly (the best's exact distance is computed when first needed)."""
    if exact < 0.0:
        exact = exact_distance2(query, values, best)
    dmin2 = min(d2, dmin2)
    exact_e = exact_distance2(query, values, e)
    if nearer(exact_e, rows[e], exact, rows[best]):
        return e, dmin2, exact_e
    return best, dmin2, exact


@njit(cache=True, inline="always")
def _bucket_counted(search):
    """The search with one more bucket examined."""
    return Search(search.best, search.dmin2, search.buckets + 1, search.tests,
                  search.exact)


@njit(cache=True, inline="always", fastmath=FASTMATH)
def _test_entry(query, entries, e, search):
    """Compute one full distance; keep entry e if it is the nearest so far."""
    d2 = np.float64(_dist2(query, entries.values, e))
    best, dmin2, exact = _keep_nearer(query, entries.values, entries.row, e, d2,
                                      search.best, search.dmin2, search.exact)
    return Search(best, dmin2, search.buckets, search.tests + 1, exact)


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


@njit(cache=True, inline="always", fastmath=FASTMATH)
def _dots5(query, axes, a0):
    """Dot products of ``query`` with axes a0 .. a0 + 4 in one pass (float32)."""
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


@njit(cache=True, inline="always", fastmath=FASTMATH)
def _query_sketch(query, position, sketch, low, high):
    """Intervals [low, high] (float32, per lane) that contain the query's exact sketch.

    ``position.r2`` is |q - b|^2 and ``position.norm2`` is |q|^2 (float64).
    The axis coordinates are float32 dot products: each is within ``tau`` of
    A(q - b), from the standard bound D u sum_k |q_k A_ak| <= D u |q| on a
    float32 dot product (|A_a| = 1, any order of summation), plus the rounding
    of the stored offset A b and of the result. The residual is
    r^2 = |q - b|^2 - |A(q - b)|^2 / sigma^2, with sigma >= 1 the largest
    singular value of the float32 axes: rounded axes are not exactly
    orthonormal, and this keeps r a seminorm, so the bound holds. Its
    interval follows from the errors of the squared coordinates. Every
    interval is further widened by ``point_slack``, the largest distance
    between an entry's exact sketch and its stored float32 one, so stored
    sketches (and boxes of them) can be compared as they are.
    """
    axes = sketch.axes
    n_axes = sketch.n_axes
    tau = (1.25 * (axes.shape[1] + 8) * U32 * (np.sqrt(position.norm2) + sketch.center_norm)
           + sketch.point_slack)
    res2 = position.r2
    err2 = 1e-12 * position.r2
    for a0 in range(0, n_axes, AXES_PER_PASS):
        dots = _dots5(query, axes, a0)
        for r in range(AXES_PER_PASS):
            a = a0 + r
            if a < n_axes:
                x = np.float64(dots[r] - sketch.offset[a])
                res2 -= sketch.inv_sigma2 * x * x
                err2 += tau * (2.0 * abs(x) + tau)
                low[a] = x - tau
                high[a] = x + tau
    low[n_axes] = (np.sqrt(max(res2 - err2, 0.0)) * (1.0 - 4.0 * U32)
                   - sketch.point_slack)
    high[n_axes] = (np.sqrt(max(res2 + err2, 0.0)) * (1.0 + 4.0 * U32)
                    + sketch.point_slack)


@njit(cache=True, inline="always", fastmath=FASTMATH)
def _sketch_gap2(low, high, box_low, box_high, row):
    """Squared distance between a query's sketch intervals and box ``row``.

    A box is one bucket's or block's (``box_low``, ``box_high`` corners), or an
    entry's own sketch (the same array as both corners). All ``SKETCH_LANES``
    lanes are compared: unused ones are 0 in both.
    """
    return np.float64(box_gap(low, high, box_low, box_high, row))


@njit(cache=True, inline="always")
def _aux_gap2(position, entry_aux, e):
    """Lower bound |P(q - g)|^2 + (h(q) - h(g))^2 from entry e's (u, v, h)."""
    du = position.u - entry_aux[e, 0]
    dv = position.v - entry_aux[e, 1]
    dh = position.h - entry_aux[e, 2]
    return du * du + dv * dv + dh * dh


# ---------------------------------------------------------------- scans
@njit(cache=True, inline="always", fastmath=FASTMATH)
def _scan_run(query, position, i, j, run, grid, search):
    """Test every entry of one run of cells (row i + r, columns j + s0 .. j + s1)."""
    plane, cells, values = grid.plane, grid.cells, grid.entries.values
    n, delta, half_width = plane.n, plane.delta, plane.half_width
    ci = i + run[0]
    if ci < 0 or ci >= n:
        return search
    c0 = max(j + run[1], 0)
    c1 = min(j + run[2], n - 1)
    if c0 > c1:
        return search
    gu = _interval_gap(position.u, ci * delta - half_width, (ci + 1) * delta - half_width)
    gv = _interval_gap(position.v, c0 * delta - half_width, (c1 + 1) * delta - half_width)
    if _prunable(gu * gu + gv * gv, search.dmin2):
        return search
    block_last, rows = grid.plan.block_last, grid.entries.row
    best, dmin2, n_buckets, n_tests, exact = search
    limit = _prune_limit(dmin2)
    while c0 <= c1:  # cells of one row are contiguous within a block
        stop = min(c1, block_last[c0])
        first = cells.begin[ci * n + c0]
        last = cells.end[ci * n + stop]
        if first < last:
            n_buckets += 1
        for e in range(first, last):  # runs are used up to RUN_SCAN_DIMS only
            d2 = np.float64(_dist2_short(query, values, e))
            if d2 <= limit:  # not _prunable: the first test of _keep_nearer, hoisted
                best, dmin2, exact = _keep_nearer(query, values, rows, e, d2, best, dmin2,
                                                  exact)
                limit = _prune_limit(dmin2)
        n_tests += last - first
        c0 = stop + 1
    return Search(best, dmin2, n_buckets, n_tests, exact)


@njit(cache=True, inline="always", fastmath=FASTMATH)
def _scan_bucket(query, position, sketched, low, high, ci, cj, bucket, start, stop, grid,
                 search):
    """Test ``bucket``, that of cell (ci, cj), entries start .. stop - 1; return
    the updated search.

    With ``sketched`` the query's sketch intervals (``low``, ``high``) are known.

    * With the sketch: the bucket's sketch box, then (``plan.entry_bound``,
      buckets of several entries) each entry's sketch. The sketch box contains
      the (u, v) rectangle test, which costs more than it saves here.
    * Without, one entry: that entry's (u, v, h) bound, tighter than the
      bucket's and no dearer.
    * Without, several entries: the cell's rectangle and the bucket's interval
      of distances from the PCA plane, bucket truncation (eq. 12), then the
      per-entry (u, v, h) bound.
    """
    plane, entries, buckets = grid.plane, grid.entries, grid.buckets
    entry_bound = grid.plan.entry_bound
    if sketched:
        if _prunable(_sketch_gap2(low, high, buckets.box_low, buckets.box_high, bucket),
                     search.dmin2):
            return search
        search = _bucket_counted(search)
        if stop - start == 1:  # the bucket's box is its entry's sketch
            return _test_entry(query, entries, start, search)
        # Up to D = 16 the (u, v, h) bound is the only per-entry test worth its
        # cost. Above, the entry's sketch bound is, and the (u, v, h) bound
        # comes first only in large buckets (coarse grids), where it prunes most.
        aux_first = not entry_bound or stop - start > LARGE_BUCKET
        for e in range(start, stop):
            if aux_first and _prunable(_aux_gap2(position, entries.aux, e), search.dmin2):
                continue
            if entry_bound and _prunable(
                    _sketch_gap2(low, high, entries.sketch, entries.sketch, e),
                    search.dmin2):
                continue
            search = _test_entry(query, entries, e, search)
        return search
    if stop - start == 1:  # the entry's own (u, v, h) bound is tighter
        if _prunable(_aux_gap2(position, entries.aux, start), search.dmin2):
            return search
        search = _test_entry(query, entries, start, search)
        return _bucket_counted(search)
    box_u0 = ci * plane.delta - plane.half_width
    box_v0 = cj * plane.delta - plane.half_width
    gu = _interval_gap_free(position.u, box_u0, box_u0 + plane.delta)
    gv = _interval_gap_free(position.v, box_v0, box_v0 + plane.delta)
    gh = _interval_gap_free(position.h, buckets.h_range[bucket, 0],
                            buckets.h_range[bucket, 1])
    if _prunable(gu * gu + gv * gv + gh * gh, search.dmin2):
        return search
    search = _bucket_counted(search)
    if stop - start >= MIN_ENTRIES_FOR_BALL_TEST and search.dmin2 < np.inf:
        centre_dist = np.sqrt(np.float64(_dist2(query, buckets.mean, bucket)))
        gap = centre_dist - buckets.radius[bucket]
        if gap > 0.0 and _prunable(gap * gap, search.dmin2):
            return search
    for e in range(start, stop):
        if _prunable(_aux_gap2(position, entries.aux, e), search.dmin2):
            continue
        search = _test_entry(query, entries, e, search)
    return search


@njit(cache=True, inline="always", fastmath=FASTMATH)
def _position(query, plane):
    """The query's :class:`Position` (projection on the PCA plane), in float64."""
    pu = 0.0
    pv = 0.0
    r2 = 0.0
    q_norm2 = 0.0
    center, axes = plane.center, plane.axes
    for k in range(center.shape[0]):
        x = np.float64(query[k])
        t = x - center[k]
        pu += t * axes[0, k]
        pv += t * axes[1, k]
        r2 += t * t
        q_norm2 += x * x
    h = np.sqrt(max(r2 - pu * pu - pv * pv, 0.0))
    return Position(pu, pv, h, r2, q_norm2)


@njit(cache=True, inline="always", fastmath=FASTMATH)
def _lookup_one(query, low, high, grid, eager):
    """Exact nearest entry of one query.

    Returns (the final :class:`Search`, whether the query's sketch was
    computed). ``low`` and ``high`` are the caller's scratch space for the
    query's sketch intervals (``SKETCH_LANES`` float32 each). With ``eager``
    the sketch is computed at the first non-empty bucket.
    """
    plane, plan = grid.plane, grid.plan
    n, delta, half_width = plane.n, plane.delta, plane.half_width
    position = _position(query, plane)
    i = min(max(int(np.floor((position.u + half_width) / delta)), 0), n - 1)
    j = min(max(int(np.floor((position.v + half_width) / delta)), 0), n - 1)
    # Eq. 15 bounds a cell's distance for a query anywhere in cell (i, j). This
    # query lies ``margin`` inside every border of its cell, so every cell but
    # its own is at least (delta ||(r, s)||_dd + margin) away.
    fu = (position.u + half_width) / delta - i
    fv = (position.v + half_width) / delta - j
    margin = max(min(fu, 1.0 - fu, fv, 1.0 - fv), 0.0) * delta
    search = Search(-1, np.inf, 0, 0, -1.0)
    sketched = False

    # Phase 1: the paper's scan (Procedure 1) over the nearby cells, eq. 15 order.
    covered_dd2 = plan.fine_dd2_max + 1  # entries of cells with smaller dd2 were tested
    if plan.use_runs:
        # Low dimensions: the cells of one row that share a bound are one
        # contiguous range of entries, tested without looking at their buckets.
        for o in range(plan.runs.shape[0]):
            if _prunable((plan.run_bound[o] + margin) ** 2, search.dmin2):  # eq. 16
                return search, sketched
            search = _scan_run(query, position, i, j, plan.runs[o], grid, search)
    else:
        # Cell by cell: the query's sketch costs about as much as n_axes full
        # distances, so it is computed before the scan would spend that much
        # (counting the next bucket's entries) and is paid back by the sketch
        # tests from then on: the ski-rental rule, within about twice the better
        # choice made in hindsight. The caller asks for it at once (``eager``)
        # when the previous query, a neighbouring pixel in the pipeline's
        # order, needed it.
        n_axes = grid.sketch.n_axes
        cells = grid.cells
        switch2 = (SWITCH_CELLS * delta) ** 2
        for o in range(plan.offsets.shape[0]):
            if _prunable((plan.bound[o] + margin) ** 2, search.dmin2):  # eq. 16
                return search, sketched
            dr = plan.offsets[o, 0]
            ds = plan.offsets[o, 1]
            if o >= SWITCH_AFTER and switch2 < search.dmin2 < np.inf:
                # The best entry so far is more than SWITCH_CELLS cells away, so
                # the fine scan would visit more than about pi SWITCH_CELLS^2
                # cells: the coarse level is cheaper. Every cell with a smaller
                # dd2 than this one has been scanned; phase 2 skips only those.
                covered_dd2 = _dd2(dr, ds)
                break
            ci = i + dr
            cj = j + ds
            if ci < 0 or ci >= n or cj < 0 or cj >= n:
                continue
            cell = ci * n + cj
            bucket = cells.bucket[cell]
            if bucket < 0:
                continue
            start = cells.begin[cell]
            stop = cells.end[cell]
            if not sketched and (eager or search.tests + (stop - start) > n_axes):
                _query_sketch(query, position, grid.sketch, low, high)
                sketched = True
            search = _scan_bucket(query, position, sketched, low, high, ci, cj, bucket,
                                  start, stop, grid, search)
    if plan.fine_is_all and covered_dd2 > plan.fine_dd2_max:  # phase 1 covered the grid
        return search, sketched

    # Phase 2: the query lies far from the table. Scan blocks of side x side
    # cells in the same order at the coarse level; bound blocks and entries
    # with the sketch.
    if not sketched:
        _query_sketch(query, position, grid.sketch, low, high)
        sketched = True
    blocks, entries = grid.blocks, grid.entries
    bi = i // blocks.side
    bj = j // blocks.side
    for o in range(blocks.offsets.shape[0]):
        if _prunable(blocks.bound2[o], search.dmin2):
            break
        ki = bi + blocks.offsets[o, 0]
        kj = bj + blocks.offsets[o, 1]
        if ki < 0 or ki >= blocks.count or kj < 0 or kj >= blocks.count:
            continue
        kb = ki * blocks.count + kj
        start = blocks.start[kb]
        stop = blocks.start[kb + 1]
        if start == stop:
            continue
        if _prunable(_sketch_gap2(low, high, blocks.box_low, blocks.box_high, kb),
                     search.dmin2):
            continue
        search = _bucket_counted(search)
        for e in range(start, stop):
            if _dd2(entries.cell[e, 0] - i, entries.cell[e, 1] - j) < covered_dd2:
                continue  # phase 1 tested it
            if plan.entry_bound and _prunable(
                    _sketch_gap2(low, high, entries.sketch, entries.sketch, e),
                    search.dmin2):
                continue
            search = _test_entry(query, entries, e, search)
    return search, sketched


@njit(cache=True, fastmath=FASTMATH, _nrt=False)
def _lookup_chunk(queries, first, stop, grid, low, high, padded, out_row, out_dist,
                  out_buckets, out_tests):
    """Look up queries first .. stop - 1 into the outputs (one thread's unit of work).

    ``low``, ``high`` are scratch for a query's sketch intervals and ``padded``
    a zero row as wide as the entries, into which each query is copied when
    the entries are padded (copying a whole chunk at once instead measured
    the same within noise).

    Compiled without numba's reference counting (``_nrt=False``): every
    attribute access on ``grid`` that yields an array would otherwise count a
    reference up and down (two atomic operations), and that made lookups
    1.4-1.8x slower (measured). Nothing here allocates.
    """
    dims = queries.shape[1]
    eager = False
    for q in range(first, stop):
        query = queries[q]
        if padded.shape[0] > dims:
            for k in range(dims):
                padded[k] = query[k]
            query = padded
        search, sketched = _lookup_one(query, low, high, grid, eager)
        eager = sketched  # neighbours tend to need the same work
        out_row[q] = grid.entries.row[search.best]
        out_dist[q] = np.sqrt(search.exact if search.exact >= 0.0 else search.dmin2)
        out_buckets[q] = search.buckets
        out_tests[q] = search.tests


@njit(cache=True, parallel=True, nogil=True, fastmath=FASTMATH)
def lookup(queries, plane, entries, cells, buckets, sketch, blocks, plan, out_row,
           out_dist, out_buckets, out_tests):
    """Nearest table row of every query into the outputs (``prange`` over chunks).

    The parts of a :class:`GridData` come one by one: numba's parallel loops
    take flat tuples only, not tuples of tuples. The outputs (table row, distance, buckets examined b and full distances d per query) are
    plain arrays: with numba 0.68 writes to arrays held in a tuple were lost
    in a parallel loop. Each chunk of ``QUERY_CHUNK`` queries allocates its
    scratch space once.
    """
    n_queries = queries.shape[0]
    n_chunks = (n_queries + QUERY_CHUNK - 1) // QUERY_CHUNK
    for chunk in prange(n_chunks):
        grid = GridData(plane, entries, cells, buckets, sketch, blocks, plan)
        low = np.zeros(SKETCH_LANES, dtype=np.float32)
        high = np.zeros(SKETCH_LANES, dtype=np.float32)
        padded = np.zeros(entries.values.shape[1], dtype=np.float32)  # padding stays 0
        first = chunk * QUERY_CHUNK
        _lookup_chunk(queries, first, min(first + QUERY_CHUNK, n_queries), grid, low, high,
                      padded, out_row, out_dist, out_buckets, out_tests)


# ---------------------------------------------------------------- build
@njit(cache=True, parallel=True, nogil=True)
def bucket_summaries(sorted64, h_sorted, sketches, first, h_range, box_low, box_high, mean,
                     radius):
    """Per bucket: its [h_min, h_max], sketch box, mean and radius about the mean.

    Bucket b holds the sorted entries ``first[b]`` up to the next bucket's first
    (or the end). Written in place: ``h_range`` (B, 2) float64, ``box_low`` and
    ``box_high`` (B, lanes) float32, ``mean`` (B, >= D) float32 (columns past D
    untouched), ``radius`` (B,) float64: the largest float64 distance of an
    entry from the float32 mean, inflated by a relative 1e-6 and 1e-7 for
    rounding. The mean is summed entry by entry in storage order.
    """
    k_entries, dims = sorted64.shape
    n_buckets = first.size
    lanes = sketches.shape[1]
    for b in prange(n_buckets):
        start = first[b]
        stop = first[b + 1] if b + 1 < n_buckets else k_entries
        h_low, h_high = h_sorted[start], h_sorted[start]
        for lane in range(lanes):
            box_low[b, lane] = sketches[start, lane]
            box_high[b, lane] = sketches[start, lane]
        for e in range(start + 1, stop):
            h_low = min(h_low, h_sorted[e])
            h_high = max(h_high, h_sorted[e])
            for lane in range(lanes):
                box_low[b, lane] = min(box_low[b, lane], sketches[e, lane])
                box_high[b, lane] = max(box_high[b, lane], sketches[e, lane])
        h_range[b, 0] = h_low
        h_range[b, 1] = h_high
        for d in range(dims):
            total = 0.0
            for e in range(start, stop):
                total += sorted64[e, d]
            mean[b, d] = np.float32(total / (stop - start))
        spread2 = 0.0
        for e in range(start, stop):
            s2 = 0.0
            for d in range(dims):
                diff = sorted64[e, d] - np.float64(mean[b, d])
                s2 += diff * diff
            spread2 = max(spread2, s2)
        radius[b] = np.sqrt(spread2) * (1 + 1e-6) + 1e-7
