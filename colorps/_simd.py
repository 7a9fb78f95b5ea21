"""Sixteen-lane float32 kernels for the bucket grid (private).

numba leaves the lane count of its loops to LLVM, which splits a loop with a
run-time trip count into a vector loop, a narrower vector loop for the tail and
a scalar remainder, each with its own horizontal sum. For the short vectors of
the grid (16 sketch lanes, up to a few hundred signature dimensions) those
tails and sums are most of the latency of a bound or a distance, and the next
pruning decision waits for them. These intrinsics state the vector width
instead: rows are whole multiples of ``LANES`` float32 values (zero-padded by
the caller), read as ``<16 x float>`` and summed once. On CPUs without 512-bit
registers LLVM splits each vector into narrower ones; the results are the same.
"""

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

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
