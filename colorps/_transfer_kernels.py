"""Compiled kernel of re-decoding (private; the API is :mod:`colorps.transfer`)."""

from numba import njit, prange


@njit(cache=True, parallel=True)
def recode(values, from_table, to_table, starts):
    """Replace each value of ``from_table`` by ``to_table``'s at the same code.

    values : (n,) float32, contiguous, in place
        Values looked up in ``from_table`` (strictly increasing, float32).
    from_table, to_table : (top + 1,) float32
        Two decodings of the codes 0 .. top.
    starts : (top + 1,) int64
        The first code whose ``from_table`` value is at least b / (top + 1),
        for b = 0 .. top: where the search for a value in bucket b begins.

    Returns the number of values found in no code (left as they are).
    """
    buckets = starts.size
    top = from_table.size - 1
    missing = 0
    for i in prange(values.size):
        v = values[i]
        code = starts[min(int(v * buckets), buckets - 1)] if v >= 0.0 else 0  # (not NaN)
        while code < top and from_table[code] < v:
            code += 1
        if from_table[code] == v:
            values[i] = to_table[code]
        else:
            missing += 1
    return missing
