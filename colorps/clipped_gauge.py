"""A gauge with clipped measurements: matches without the lights it clipped.

A gauge exposed for a darker scene clips where a light meets its sphere head
on (a white sphere, 8-bit files). The table over every light leaves those gauge
pixels out, so a scene pixel whose normal lies there, unclipped itself, matches
the nearest entry outside: a normal off by a few degrees with a residual of a
few noise units, under the light subsets' trigger. (Over lights that leave out
a gauge pixel's clipped ones, that pixel is in the table again:
:meth:`colorps.tables.Capture.light_set`.)

:func:`rematch_near_clipped` matches each pixel whose match lies within
NEAR_PX of gauge pixels with clipped lights again without those lights, and
keeps that match where it explains the pixel better (a lower residual): one
table per set of lights left out, MAX_GROUPS of them at most. Pixels already
without lights of their own (clipped in the scene) are left to the per-pixel
fit of :mod:`colorps.shadows`, which leaves out each gauge pixel's clipped
lights too. Those lights join the pixel's dropped ones
(``lights.exr``). A gauge with nothing clipped costs nothing.
"""

from __future__ import annotations

import numpy as np

from . import light_masks
from ._config import AUTO_N_SAMPLE, MIN_LIGHTS
from .options import Options
from .tables import Capture, group_rows

__all__ = ["MAX_GROUPS", "NEAR_PX", "rematch_near_clipped"]

#: Gauge pixels (Chebyshev distance) around a match whose clipped lights the
#: pixel is matched without: the nearest entry outside a clipped patch is next
#: to it.
NEAR_PX = 2
#: Tables (sets of lights left out) tried at most, the largest groups first:
#: under many lights the clipped patches overlap in many combinations.
MAX_GROUPS = 128


def rematch_near_clipped(capture: Capture, state, options: Options) -> list[tuple]:
    """Match again, without the gauge's clipped lights near their match, the
    matched pixels of ``state`` (matching's per-pixel state: ``row``,
    ``quality`` not yet divided by the model scale, ``distance``, ``bands_used``,
    ``dropped``; updated in place where the new match is better). Returns, per
    table used, (bands, table size, grid N, pixels, lights left out) for the
    run's record."""
    if capture.gauge_clipped is None or not capture.gauge_clipped.any():
        return []
    m = capture.images
    near = _near(capture.gauge_clipped, NEAR_PX).reshape(-1, capture.gauge_clipped.shape[-1])
    # Pixels clipped in the scene (lights left out already, or an infinite
    # residual: to be refitted without them) are the per-pixel fit's: their sets
    # with these would make a table each.
    ys, xs = np.nonzero((state.row >= 0) & light_masks.is_empty(state.dropped) &
                        np.isfinite(state.quality))
    without = near[state.row[ys, xs]]
    todo = ~light_masks.is_empty(without) & (m - light_masks.count(without) >= MIN_LIGHTS)
    ys, xs, without = ys[todo], xs[todo], without[todo]
    codes = state.bands_used[ys, xs]
    records = []
    keys, inverse = group_rows(np.column_stack([without.view(np.int64), codes.astype(np.int64)]))
    for g in np.argsort(-np.bincount(inverse), kind="stable")[:MAX_GROUPS]:
        key = keys[g]
        pick = np.flatnonzero(inverse == g)
        left_out = light_masks.lights(key[:-1].view(np.uint64))
        bands = tuple(k for k in range(capture.bands) if int(key[-1]) >> k & 1)
        if len(bands) * (m - len(left_out) - 1) < 2:
            continue
        kept = tuple(i for i in range(m) if i not in left_out)
        result = capture.match(ys[pick], xs[pick], bands, (0,) * len(bands), kept,
                               grid_n=options.grid_n, threads=options.threads,
                               sample_size=AUTO_N_SAMPLE)
        better = (result.rows >= 0) & (result.residual < state.quality[ys[pick], xs[pick]])
        by, bx = ys[pick][better], xs[pick][better]
        state.row[by, bx] = result.rows[better]
        state.quality[by, bx] = result.residual[better]
        state.distance[by, bx] = result.distance[better]
        state.dropped[by, bx] = key[:-1].view(np.uint64)
        records.append((bands, result.table_size, result.grid_n, int(better.sum()), left_out))
    return records


def _near(masks: np.ndarray, reach: int) -> np.ndarray:
    """(H, W, words) the union of the light masks within ``reach`` pixels
    (Chebyshev) of each pixel."""
    h, w, _ = masks.shape
    padded = np.pad(masks, ((reach, reach), (reach, reach), (0, 0)))
    union = np.zeros_like(masks)
    for dy in range(2 * reach + 1):
        for dx in range(2 * reach + 1):
            union |= padded[dy:dy + h, dx:dx + w]
    return union
