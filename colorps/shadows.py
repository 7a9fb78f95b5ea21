"""Pixels in shadow under many lights: matched on the lights that reach them.

A pixel in the cast shadow of several lights (a fold of the object, the foot
of a relief) matches no gauge pixel on all its lights, and the greedy light
subsets of :mod:`colorps.matching` drop at most ``max_dropped_lights`` of them,
one table per subset. Here each such pixel gets its own set of lights instead,
found by a trimmed fit that needs no table:

1. start from the lights that light it: a light whose measurement (per band
   relative to the band's norm, summed over the matched bands) is under
   DARK_FRACTION of the pixel's BRIGHT_RANK-th brightest is left out, as is a
   clipped one and one over SPIKE_LIMIT times it (a renderer's firefly, a
   glint: a single spike made every other light look dark, and the fit then
   explained the spike and a few lights with a wrong normal, 16 degrees off);
2. scan the gauge for the least signature distance over those lights (every
   SCAN_STEP-th gauge pixel, every COARSE_STEP-th around the best, then every
   pixel around that: :func:`colorps._shadow_kernels.masked_search`, exact on
   each window);
3. keep the lights the match explains (per-light residual within
   INLIER_Z noise units, times the model scale, or a change under
   MINOR_FRACTION of the pixel's brightest measurement): an attached shadow,
   dark on the gauge too, comes back; a cast shadow or a highlight stays out;
4. repeat 2-3 (ROUNDS in all), then score the match over the kept lights in
   noise units (:func:`colorps._shadow_kernels.masked_residuals`, as
   :mod:`colorps.residuals` defines the residual).

A gauge pixel's clipped lights (a gauge exposed for a darker scene) leave each
pair's lights in 2 and 4, and the match's clipped ones the pixel's kept lights:
a pixel in shadow under many lights whose normal lies in a clipped patch is
fitted there, not refused.

A pixel takes the new match when it explains it better than the one it had
(a lower residual); on the table's rim only when every light it drops as
darker was predicted bright (a rim match may stand for a normal beyond the
gauge, whose dim lights the rim cannot explain: dropping them would hide
that); the refinement then goes past the gauge's pixel grid on
the same lights, and ``lights.exr`` says which were left out. A pixel needs
at least MIN_LIGHTS lights left (and its bands x (lights - 1) >= 2).
"""

from __future__ import annotations

import math

import numpy as np

from . import _shadow_kernels, light_masks
from ._config import MIN_LIGHTS
from .residuals import MODEL_FLOOR, light_residuals
from .tables import Capture

__all__ = ["ACCEPTED", "BRIGHT_RANK", "COARSE_STEP", "DARK_FRACTION", "INLIER_Z",
           "MINOR_FRACTION", "ROUNDS", "SCAN_STEP", "SPIKE_LIMIT", "fixes_normal",
           "solve_shadowed"]

# ---------------------------------------------------------------- tuning
#: A light is taken as not reaching a pixel, to start with, when the pixel's
#: measurement under it is below this fraction of its brightest.
DARK_FRACTION = 0.2
#: A light is kept when its per-light residual at the match is within this many
#: noise units (times the capture's model scale).
INLIER_Z = 3.0
#: A light whose measurement differs from the match's prediction by less than
#: this fraction of the pixel's brightest is kept whatever its residual: less
#: than a shadow or highlight takes away or adds, more than an attached shadow
#: at the gauge's rim leaves.
MINOR_FRACTION = 0.05
#: A fit whose residual (noise units, on the model scale) is within this explains
#: the pixel; of two such fits the one on more lights is kept.
ACCEPTED = 3.0
#: DARK_FRACTION and SPIKE_LIMIT are of the pixel's BRIGHT_RANK-th brightest
#: measurement: up to BRIGHT_RANK - 1 spikes cannot make the other lights look
#: dark, and lights over SPIKE_LIMIT times it start out left out (the rounds take
#: back those the match explains). With 0.1 % of a 32-light scene's measurements
#: spiked 3 to 30 times, those pixels came out 16 degrees off, accepted (0.25
#: now); 1 % took the folds from 0.12 to 4.30 degrees mean (0.26 now).
BRIGHT_RANK = 3
SPIKE_LIMIT = 3.0
#: Gauge pixels between the candidates of the first, whole-gauge scan, and of
#: the second, around its best (every 4th of a 100 px gauge's whole had taken
#: 80 % of the fit's time; every 8th, then every 4th, found the same matches).
SCAN_STEP = 8
COARSE_STEP = 4
#: Rounds of matching and choosing the lights.
ROUNDS = 2
#: Pixels handled at a time (bounds the (P, B, m) temporaries).
CHUNK_PIXELS = 16384


def fixes_normal(bands, lights) -> np.ndarray:
    """Whether a pixel's ``bands`` usable bands over ``lights`` lights (counts,
    broadcast) still fix a normal: at least MIN_LIGHTS lights and
    bands x (lights - 1) >= 2."""
    lights = np.asarray(lights)
    return (lights >= MIN_LIGHTS) & (np.asarray(bands) * (lights - 1) >= 2)


def solve_shadowed(capture: Capture, state, limit: float, model_scale: float) -> int:
    """Match again, each on its own lights, the pixels whose residual exceeds ``limit``.

    Parameters
    ----------
    capture : Capture
    state : colorps.matching._MatchState
        Every pixel's match so far (row, quality, distance, bands_used,
        levels, dropped, brighter), improved in place.
    limit : float
        Residual (noise units, on the model scale) above which a pixel is tried.
    model_scale : float
        The capture's model scale (residuals are divided by it).

    Returns
    -------
    int
        Pixels whose match was replaced.
    """
    ys, xs = np.nonzero((state.row >= 0) & (state.quality > limit))
    if not len(ys):
        return 0
    interior = _interior(_usable_gauge(capture))  # one table for every chunk
    replaced = 0
    for a in range(0, len(ys), CHUNK_PIXELS):
        replaced += _solve_chunk(capture, state, ys[a:a + CHUNK_PIXELS],
                                 xs[a:a + CHUNK_PIXELS], model_scale, interior)
    return replaced


def _solve_chunk(capture: Capture, state, ys, xs, model_scale: float,
                 interior: np.ndarray) -> int:
    """:func:`solve_shadowed` for some pixels; the number replaced. ``interior``
    is :func:`_interior` of the gauge.

    Two starts, the better kept per pixel: the lights that light the pixel and
    a scan of the whole gauge; and its current match with the lights that match
    explains (a pixel whose few outlying lights are highlights, not shadows).
    Of two fits that explain the pixel the one on more lights is kept.
    """
    m, n_bands = capture.images, capture.bands
    ov = capture.scene_ov[ys, xs].astype(np.float64)  # (P, B, m)
    bands = ((state.bands_used[ys, xs][:, None] >> np.arange(n_bands)) & 1) == 1
    clipped = np.zeros((len(ys), m), dtype=bool) if capture.scene_clipped is None else \
        light_masks.to_bool(capture.scene_clipped[ys, xs], m)
    norm = np.sqrt((ov * ov).sum(axis=-1, keepdims=True))
    brightness = (np.divide(ov, norm, out=np.zeros_like(ov), where=norm > 0)
                  * bands[..., None]).sum(axis=1)  # (P, m)
    reference = np.sort(brightness, axis=1)[:, -min(BRIGHT_RANK, m)][:, None]
    lit = (brightness >= DARK_FRACTION * reference) & \
        (brightness <= SPIKE_LIMIT * reference) & ~clipped
    gauge = _gauge_ovs(capture)
    hg, wg = capture.gauge_ov.shape[:2]
    centre = (np.full(len(ys), hg // 2), np.full(len(ys), wg // 2))
    scanned = _search(capture, ys, xs, bands, lit, gauge, centre,
                      math.ceil(max(hg, wg) / 2 / SCAN_STEP), SCAN_STEP)
    scanned = _search(capture, ys, xs, bands, lit, gauge, np.divmod(np.maximum(scanned, 0), wg),
                      SCAN_STEP // COARSE_STEP, COARSE_STEP)
    current = state.row[ys, xs]
    explained = _inliers(capture, ov, bands, ~clipped, current, model_scale) & ~clipped
    fits = [_trimmed_fit(capture, ys, xs, ov, bands, clipped, gauge, keep, rows, model_scale)
            for keep, rows in ((lit, scanned), (explained, current))]
    # Of two fits that explain the pixel (residual within ACCEPTED), the one on
    # more of its lights (a wrong match explains a few of them well), or as
    # many more closely; else the one that explains it, else the closer.
    kept = [fit[1].sum(axis=1) for fit in fits]
    good = [fit[3] <= ACCEPTED for fit in fits]
    closer = fits[1][3] < fits[0][3]
    more = (kept[1] > kept[0]) | ((kept[1] == kept[0]) & closer)
    second = np.where(good[0] & good[1], more, np.where(good[0] | good[1], good[1], closer))
    rows, keep, z, quality, distance = (np.where(second.reshape((-1,) + (1,) * (a.ndim - 1)),
                                                 b, a) for a, b in zip(*fits))
    enough = fixes_normal(bands.sum(axis=1), keep.sum(axis=1))
    # A match on the table's rim may stand for a normal beyond the gauge, whose
    # dim lights near the terminator the rim cannot explain; dropping them would
    # hide that. On the rim, every light dropped as darker must have been
    # predicted bright (a shadow takes away much light).
    predicted, _ = _shares(ov, _matched(capture, rows), bands, keep)
    faint = predicted < DARK_FRACTION * predicted.max(axis=1, keepdims=True)
    inside = interior.ravel()[np.maximum(rows, 0)] | \
        ~(~keep & (z < 0) & faint).any(axis=1)
    better = enough & (rows >= 0) & inside & np.isfinite(quality) & \
        (quality < state.quality[ys, xs])
    ky, kx = ys[better], xs[better]
    state.row[ky, kx] = rows[better]
    state.quality[ky, kx] = quality[better]
    state.distance[ky, kx] = distance[better]
    state.levels[ky, kx] = 0
    state.dropped[ky, kx] = light_masks.from_bool(~keep[better])
    state.brighter[ky, kx] = light_masks.from_bool(~keep[better] & (z[better] > 0))
    return int(better.sum())


def _interior(usable: np.ndarray) -> np.ndarray:
    """(Hg, Wg): gauge pixels whose 3 x 3 neighbourhood has every band usable."""
    from scipy.ndimage import binary_erosion

    return binary_erosion(usable.all(axis=-1), np.ones((3, 3), bool))


def _usable_gauge(capture: Capture) -> np.ndarray:
    """(Hg, Wg, B) gauge bands usable over the lights that leave out their
    pixel's clipped ones (``gauge_unclipped``, which holds ``gauge_valid``)."""
    usable = capture.gauge_valid if capture.gauge_unclipped is None else \
        capture.gauge_unclipped
    return np.ascontiguousarray(usable)


def _gauge_ovs(capture: Capture) -> _shadow_kernels.GaugeOVs:
    """The gauge as the kernels take it: a pair's lights leave out the gauge
    pixel's clipped ones."""
    clipped = capture.gauge_clipped
    if clipped is None:
        clipped = light_masks.empty(capture.gauge_ov.shape[:2], capture.images)
    return _shadow_kernels.GaugeOVs(capture.gauge_ov, _usable_gauge(capture),
                                    np.ascontiguousarray(clipped))


def _unclipped_at(capture: Capture, keep: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(P, m) ``keep`` but for the lights clipped at each pixel's matched gauge pixel."""
    if capture.gauge_clipped is None:
        return keep
    masks = capture.gauge_clipped.reshape(-1, capture.gauge_clipped.shape[-1])
    return keep & ~light_masks.to_bool(masks[np.maximum(rows, 0)], capture.images)


def _trimmed_fit(capture, ys, xs, ov, bands, clipped, gauge, keep, rows, model_scale):
    """ROUNDS of matching around ``rows`` and keeping the lights the match explains;
    (rows, keep, per-light residuals, residual on the model scale, distance)."""
    wg = capture.gauge_ov.shape[1]
    for round_ in range(ROUNDS + 1):
        rows = _search(capture, ys, xs, bands, keep, gauge, np.divmod(np.maximum(rows, 0), wg),
                       COARSE_STEP, 1)
        if round_ < ROUNDS:
            keep = _inliers(capture, ov, bands, keep, rows, model_scale) & ~clipped
    keep = _unclipped_at(capture, keep, rows)
    z = _light_z(capture, ov, _matched(capture, rows), bands, keep, rows)
    quality, distance = _residuals(capture, ys, xs, bands, keep, gauge, rows)
    return rows, keep, z, quality / model_scale, distance


def _matched(capture, rows) -> np.ndarray:
    """(P, B, m) float64 OVs of each pixel's matched gauge pixel."""
    n_bands, m = capture.bands, capture.images
    return capture.gauge_ov.reshape(-1, n_bands, m)[np.maximum(rows, 0)].astype(np.float64)


def _light_z(capture, ov, g, bands, keep, rows) -> np.ndarray:
    """(P, m) per-light residuals of pixels of OVs ``ov`` at matched gauge OVs ``g``
    (:func:`colorps.residuals.light_residuals`, the albedo fitted over their
    ``keep`` lights), in units of what a right match leaves: the measurement's
    noise, and the table's step and the model floor (:mod:`colorps.residuals`)
    spread over the lights. Negative for a shadow, positive for a highlight."""
    rows = np.maximum(rows, 0)
    resolution = capture.light_set(tuple(range(capture.images))).resolution_at(rows)
    spread = (resolution[rows] / 6.0 + MODEL_FLOOR ** 2) * \
        (ov * ov * keep[:, None, :]).sum(axis=-1) / \
        np.maximum(keep.sum(axis=1), 1)[:, None]  # (P, B)
    return light_residuals(ov, g, keep, bands, capture.model, extra_variance=spread)


def _shares(ov, g, bands, keep) -> tuple[np.ndarray, np.ndarray]:
    """(P, m) each light's predicted measurement at the match and its change from
    it to the pixel's, each band relative to its norm, summed over the bands."""
    w = keep[:, None, :]
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = (ov * g * w).sum(axis=-1) / (g * g * w).sum(axis=-1)
        norm = np.sqrt((ov * ov * w).sum(axis=-1))[..., None]
        predicted = np.where(bands[..., None], ratio[..., None] * g / norm, 0.0)
        change = np.where(bands[..., None], np.abs(ov / norm - predicted), 0.0)
    return np.nan_to_num(predicted).sum(axis=1), np.nan_to_num(change).sum(axis=1)


def _inliers(capture, ov, bands, keep, rows, model_scale) -> np.ndarray:
    """The lights the match at ``rows`` explains: per-light residual within
    INLIER_Z noise units (times the model scale), or a disagreement under
    MINOR_FRACTION of the pixel's brightest predicted measurement (:func:`_shares`;
    a cast shadow or a highlight changes a measurement by much more, a light near
    grazing by less). Lights of ``keep`` clipped at the match stay: it says
    nothing of them."""
    g = _matched(capture, rows)
    pair = _unclipped_at(capture, keep, rows)
    z = _light_z(capture, ov, g, bands, pair, rows)
    predicted, change = _shares(ov, g, bands, pair)
    minor = change < MINOR_FRACTION * predicted.max(axis=1, keepdims=True)
    return (np.abs(z) <= INLIER_Z * model_scale) | minor | (keep & ~pair)


def _search(capture, ys, xs, bands, keep, gauge, centre, reach: int, step: int) -> np.ndarray:
    """Each pixel's best gauge pixel in a window (flat index, -1: none)."""
    pixels = _shadow_kernels.Pixels(capture.scene_ov, np.asarray(ys, np.int64),
                                    np.asarray(xs, np.int64), np.ascontiguousarray(bands),
                                    np.ascontiguousarray(keep))
    window = _shadow_kernels.Window(np.asarray(centre[0], np.int64),
                                    np.asarray(centre[1], np.int64), int(reach), int(step))
    rows = np.empty(len(ys), dtype=np.int64)
    d2 = np.empty(len(ys))
    _shadow_kernels.masked_search(pixels, gauge, window, MIN_LIGHTS, rows, d2)
    return rows


def _residuals(capture, ys, xs, bands, keep, gauge, rows) -> tuple[np.ndarray, np.ndarray]:
    """Residual (noise units, before the model scale) and distance of each match
    (inf where there is none)."""
    quality = np.full(len(ys), np.inf, dtype=np.float32)
    distance = np.full(len(ys), np.inf, dtype=np.float32)
    found = rows >= 0
    if not found.any():
        return quality, distance
    pixels = _shadow_kernels.Pixels(capture.scene_ov, np.asarray(ys[found], np.int64),
                                    np.asarray(xs[found], np.int64),
                                    np.ascontiguousarray(bands[found]),
                                    np.ascontiguousarray(keep[found]))
    resolution = capture.light_set(tuple(range(capture.images))).resolution_at(rows[found])
    gauge_model = capture.gauge_model or capture.model
    q = np.empty(int(found.sum()), dtype=np.float32)
    d = np.empty(int(found.sum()), dtype=np.float32)
    _shadow_kernels.masked_residuals(pixels, gauge, rows[found], resolution,
                                     capture.model.kernel_args(), gauge_model.kernel_args(),
                                     MODEL_FLOOR ** 2, q, d)
    quality[found], distance[found] = q, d
    return quality, distance
