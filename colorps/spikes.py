"""Isolated spikes in a gauge's images: replaced by their neighbours' median.

A path tracer's fireflies, a sensor's hot pixel or a cosmic ray put one
measurement of one image far above its neighbours. On a gauge the shading is
smooth, so such a measurement is no shading at all, yet it becomes a table
entry and bends the refinement's local models around it: 0.1 % of a 32-light
gauge's measurements spiked 3 to 30 times took the folds from 0.12 to 0.77
degrees mean, 1 % to 3.46 (0.12 and 0.13 with them replaced;
``docs/benchmarks.md``). A measurement more than SPIKE_RATIO times the median
of its 8 neighbours (same image and channel), plus SPIKE_FLOOR of the gauge's
bright level or SPIKE_NOISE noise sds (so that noise around a dark value is
not a spike), is replaced by that median, and the run says how many were
(``report.json``'s ``gauge_spikes_replaced``, and a warning). A highlight,
even a glossy gauge's, spans several pixels and is left as it is.

The scene's own spikes need no repair: its pixels are matched on the lights
that agree (:mod:`colorps.shadows` leaves a light far brighter than the
pixel's others out of its first guess).
"""

from __future__ import annotations

import numpy as np

from . import _spike_kernels
from ._checks import mask_box

__all__ = ["BRIGHT_PERCENTILE", "SPIKE_FLOOR", "SPIKE_RATIO", "replace_spikes",
           "spike_free"]

#: A gauge measurement is a spike when it exceeds SPIKE_RATIO times the median
#: of its 8 neighbours plus SPIKE_FLOOR times the gauge's bright level
#: (the 99.5th percentile of its brightest picture). On clean, glossy (GGX
#: alpha 0.3), rough, 8-bit, clipped and 20 px gauges none is found; of fireflies
#: 3 to 30 times the shading, 86 %, the rest too faint to matter. A ratio of 3
#: let the fainter through, and with the scene spiked too the folds came out
#: 5.43 degrees mean (0.38 with 2).
SPIKE_RATIO = 2.0
SPIKE_FLOOR = 0.02
#: ... and over SPIKE_NOISE times the noise (1.4826 x the median absolute
#: difference of the measurements from their neighbours' medians): noise around
#: a dark value is no spike (a gauge under dim coloured lights, noise 0.005, had
#: one).
SPIKE_NOISE = 8.0
#: Percentile of a gauge's brightest picture taken as its bright level (also
#: find_sphere's, :mod:`colorps.gauge`).
BRIGHT_PERCENTILE = 99.5


def replace_spikes(stack: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, int]:
    """The gauge's images with the spikes inside ``mask`` replaced.

    Parameters
    ----------
    stack : (m, H, W, c) ndarray
        Linear gauge images (not changed).
    mask : (H, W) ndarray of bool
        The gauge's pixels.

    Returns
    -------
    (ndarray, int)
        ``stack`` itself when there is no spike, else a float32 copy with each
        spike replaced by the median of its 8 neighbours; and how many
        measurements were replaced.

    Examples
    --------
    >>> import numpy as np
    >>> from colorps.spikes import replace_spikes
    >>> images = np.full((2, 5, 5, 1), 0.5, np.float32)
    >>> images[1, 2, 2, 0] = 9.0  # a firefly
    >>> repaired, count = replace_spikes(images, np.ones((5, 5), bool))
    >>> count, float(repaired[1, 2, 2, 0])
    (1, 0.5)
    """
    inside = np.asarray(mask, dtype=bool)
    if not inside.any():
        return stack, 0
    box = mask_box(inside, 1)  # each pixel's 8 neighbours
    part = np.asarray(stack[:, box[0], box[1]], dtype=np.float32)
    values = np.where(np.isfinite(part), part, np.float32(0.0))
    bright = float(np.percentile(values.max(axis=(0, 3))[inside[box]], BRIGHT_PERCENTILE))
    spike, median = _spikes(values, bright, inside[box][None, ..., None])
    count = int(spike.sum())
    if not count:
        return stack, 0
    repaired = np.array(stack, dtype=np.float32, copy=True)
    repaired[:, box[0], box[1]] = np.where(spike, median, part)
    return repaired, count


def spike_free(picture: np.ndarray) -> np.ndarray:
    """An (H, W) picture with its spikes (as :func:`replace_spikes` finds them,
    against its own bright level) replaced by their neighbours' median: the
    brightest picture of a gauge's images, where every image's fireflies show.

    Examples
    --------
    >>> import numpy as np
    >>> from colorps.spikes import spike_free
    >>> picture = np.zeros((5, 5), np.float32)
    >>> picture[1, 3] = 0.8  # a firefly on a dark background
    >>> float(spike_free(picture).max())
    0.0
    """
    values = np.where(np.isfinite(picture), picture, np.float32(0.0)).astype(np.float32)
    values = np.ascontiguousarray(values[None, ..., None])
    spike, median = _spikes(values, float(np.percentile(values, BRIGHT_PERCENTILE)),
                            np.ones(values.shape, bool))
    return np.where(spike, median, values)[0, ..., 0]


def _spikes(values: np.ndarray, bright: float, where: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray]:
    """Where (within ``where``) the (m, H, W, c) ``values`` exceed SPIKE_RATIO
    times the median of their 8 neighbours plus the larger of SPIKE_FLOOR times
    ``bright`` and SPIKE_NOISE times the noise (the robust spread of the values
    about that median within ``where``); and that median."""
    median = np.empty_like(values)
    _spike_kernels.neighbour_medians(values, median)
    within = np.broadcast_to(where, values.shape)
    spread = np.abs(values - median)[within]
    noise = 1.4826 * float(np.median(spread)) if spread.size else 0.0
    floor = max(SPIKE_FLOOR * bright, SPIKE_NOISE * noise)
    return (values > SPIKE_RATIO * median + floor) & within, median
