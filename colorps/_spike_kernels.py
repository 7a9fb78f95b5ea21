"""Compiled kernel of the spike test (private; the API is :mod:`colorps.spikes`)."""

import numpy as np
from numba import njit, prange


@njit(cache=True, parallel=True)
def neighbour_medians(values, out):
    """The median of each measurement's 8 neighbours in its image and channel.

    values, out : (m, H, W, c) float32
        ``out`` is written in place; beyond the border the nearest row or
        column stands in. The median of 8 is the mean of the 4th and 5th.
    """
    m, h, w, c = values.shape
    for y in prange(h):
        ring = np.empty(8, dtype=np.float32)
        for i in range(m):
            for x in range(w):
                for k in range(c):
                    n = 0
                    for dy in (-1, 0, 1):
                        for dx in (-1, 0, 1):
                            if dy == 0 and dx == 0:
                                continue
                            yy = min(max(y + dy, 0), h - 1)
                            xx = min(max(x + dx, 0), w - 1)
                            v = values[i, yy, xx, k]
                            j = n  # insertion sort, 8 values
                            while j > 0 and ring[j - 1] > v:
                                ring[j] = ring[j - 1]
                                j -= 1
                            ring[j] = v
                            n += 1
                    out[i, y, x, k] = 0.5 * (ring[3] + ring[4])
