"""The 16-lane vector intrinsics of the grid kernels against numpy in float64."""

import numpy as np
import pytest
from numba import njit

from colorps import _grid_kernels as kernels


@njit
def _distances(query, table):
    out = np.empty(table.shape[0], dtype=np.float32)
    for row in range(table.shape[0]):
        out[row] = kernels.squared_distance(query, table, row)
    return out


@njit
def _gaps(low, high, box_low, box_high):
    out = np.empty(box_low.shape[0], dtype=np.float32)
    for row in range(box_low.shape[0]):
        out[row] = kernels.box_gap(low, high, box_low, box_high, row)
    return out


def _pad(rows, width):
    out = np.zeros((rows.shape[0], width), dtype=np.float32)
    out[:, :rows.shape[1]] = rows
    return out


@pytest.mark.parametrize("dims", [1, 9, 16, 17, 90, 250])
def test_squared_distance_matches_numpy(dims, rng):
    width = -(-dims // kernels.LANES) * kernels.LANES
    table = rng.normal(size=(300, dims)).astype(np.float32)
    query = rng.normal(size=dims).astype(np.float32)
    # A longer query buffer is allowed: only the table's width is read.
    buffer = np.zeros(width + kernels.LANES, dtype=np.float32)
    buffer[:dims] = query
    got = _distances(buffer, _pad(table, width))
    want = ((table.astype(np.float64) - query.astype(np.float64)) ** 2).sum(axis=1)
    np.testing.assert_allclose(got, want, rtol=dims * 2e-7, atol=1e-12)
    # Rows are read whole: a row equal to the query is at distance exactly 0.
    table[7] = query
    assert _distances(buffer, _pad(table, width))[7] == 0.0


def test_box_gap_matches_numpy(rng):
    lanes = kernels.LANES
    centre = rng.normal(size=lanes).astype(np.float32)
    low = centre - np.float32(0.1)
    high = centre + np.float32(0.1)
    a = rng.normal(size=(500, lanes)).astype(np.float32)
    b = a + rng.uniform(0, 0.5, size=a.shape).astype(np.float32)
    got = _gaps(low, high, a, b)
    gap = np.maximum(np.maximum(a - high, low - b), 0.0).astype(np.float64)
    np.testing.assert_allclose(got, (gap ** 2).sum(axis=1), rtol=1e-5, atol=1e-12)
    # Overlapping boxes are at distance 0; a point box is its own sketch.
    assert _gaps(low, high, low[None, :], high[None, :])[0] == 0.0
    inside = centre[None, :]
    assert _gaps(low, high, inside, inside)[0] == 0.0


def test_other_arrays_are_refused():
    """Only C-contiguous float32 arrays of the right rank type-check."""
    table = np.zeros((4, 16), dtype=np.float64)
    query = np.zeros(16, dtype=np.float64)
    with pytest.raises(Exception, match="squared_distance"):
        _distances(query, table)
