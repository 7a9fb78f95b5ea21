"""Compiled kernels of the shadow-robust match (private; the API is :mod:`colorps.shadows`).

Every pixel has its own set of lights (``keep``, (P, m) bool): those not in a
cast shadow, a highlight or clipped. Signatures are over those lights only, so
no table can be built for them all; instead each pixel scans a window of gauge
pixels (a coarse lattice of the whole gauge first, then the neighbourhood of
the best) with the masked signature distance

    D(p, q)^2 = sum over matched bands k of |s_k,L(p) - g_k,L(q)|^2

s_k,L, g_k,L the unit vectors of band k's OVs over the pixel's lights L,
computed from dot products without forming them: |s - g|^2 = 2 - 2 S.G / (|S| |G|).
A gauge pixel's clipped lights leave L for that pair: its measurement under them
is a lower bound, not a value (a gauge exposed for a darker scene clips where a
light meets it head on).
"""

from collections import namedtuple

import numpy as np
from numba import njit, prange

# numba's cache watches only this file: after editing _pixel_kernels._variance,
# touch this one too (or clear its __pycache__).
from ._pixel_kernels import _variance

#: The pixels to match: scene OVs ov (H, W, B, m) float32; pixel p is (y[p], x[p]),
#: matched on the bands with bands[p, k] true, over the lights with keep[p, i] true.
Pixels = namedtuple("Pixels", "ov y x bands keep")
#: The gauge: its OVs ov (Hg, Wg, B, m) float32, usable (Hg, Wg, B) bool (but for
#: clipped measurements) and clipped (Hg, Wg, words) uint64, the light masks of the
#: images with a clipped measurement (colorps.light_masks).
GaugeOVs = namedtuple("GaugeOVs", "ov usable clipped")
#: A window of gauge pixels around centre (cy[p], cx[p]): rows cy + step * i and
#: columns cx + step * j for |i|, |j| <= reach.
Window = namedtuple("Window", "cy cx reach step")


@njit(cache=True)
def _clipped_at(clipped, gy, gx, i):
    """Whether light i is clipped at gauge pixel (gy, gx)."""
    return (clipped[gy, gx, i >> 6] >> np.uint64(i & 63)) & np.uint64(1) != 0


@njit(cache=True)
def _lit(keep, clipped, p, gy, gx, i):
    """Whether light i is in the pair's L: kept by pixel p, not clipped at (gy, gx)."""
    return keep[p, i] and not _clipped_at(clipped, gy, gx, i)


@njit(cache=True, parallel=True)
def masked_search(pixels, gauge, window, min_lights, out_row, out_d2):
    """The gauge pixel of each window with the least masked signature distance,
    among those whose L holds at least ``min_lights`` lights.

    Writes its flat index (-1 when the window holds no usable gauge pixel) and
    D^2 (summed over the matched bands) into out_row and out_d2. A gauge pixel
    with no clipped light (most) has L the pixel's kept lights, whose scene
    norms are summed once per pixel.
    """
    scene_ov, ys, xs, _, keep = pixels
    gauge_ov, _, clipped = gauge
    cy, cx, reach, step = window
    hg, wg, n_bands, m = gauge_ov.shape
    for p in prange(ys.size):
        y, x = ys[p], xs[p]
        kept = 0
        for i in range(m):
            if keep[p, i]:
                kept += 1
        ss = np.zeros(n_bands)  # |S_k,L|^2 over the kept lights
        for b in range(n_bands):
            for i in range(m):
                if keep[p, i]:
                    ss[b] += np.float64(scene_ov[y, x, b, i]) ** 2
        best, best_d2 = -1, np.inf
        for di in range(-reach, reach + 1):
            gy = cy[p] + step * di
            if gy < 0 or gy >= hg:
                continue
            for dj in range(-reach, reach + 1):
                gx = cx[p] + step * dj
                if gx < 0 or gx >= wg:
                    continue
                any_clipped = _any_clipped(clipped, gy, gx)
                if not any_clipped and kept < min_lights:
                    continue
                d2 = _pair_d2(pixels, gauge, p, gy, gx, ss, any_clipped, min_lights, best_d2)
                if d2 < best_d2:
                    best, best_d2 = gy * wg + gx, d2
        out_row[p] = best
        out_d2[p] = best_d2


@njit(cache=True, inline="always")
def _any_clipped(clipped, gy, gx):
    """Whether gauge pixel (gy, gx) has any clipped light."""
    for word in range(clipped.shape[2]):  # noqa: SIM110 (a loop numba compiles)
        if clipped[gy, gx, word] != 0:
            return True
    return False


@njit(cache=True, inline="always")
def _pair_d2(pixels, gauge, p, gy, gx, ss, any_clipped, min_lights, best_d2):
    """D^2 of pixel p and gauge pixel (gy, gx) over L: p's kept lights, but for
    those clipped at (gy, gx) when it has any (``any_clipped``; else ``ss``
    holds p's squared norms per band over its kept lights, summed once). Inf
    when L holds fewer than ``min_lights`` or a band is unusable; at least
    ``best_d2`` once the sum reaches it."""
    scene_ov, ys, xs, bands, keep = pixels
    gauge_ov, usable, clipped = gauge
    y, x = ys[p], xs[p]
    m = gauge_ov.shape[3]
    if any_clipped:
        n_lights = 0
        for i in range(m):
            if _lit(keep, clipped, p, gy, gx, i):
                n_lights += 1
        if n_lights < min_lights:
            return np.inf
    d2 = 0.0
    for b in range(gauge_ov.shape[2]):
        if not bands[p, b]:
            continue
        if not usable[gy, gx, b]:
            return np.inf
        dot, gg, s2 = 0.0, 0.0, 0.0
        for i in range(m):
            if _lit(keep, clipped, p, gy, gx, i) if any_clipped else keep[p, i]:
                g = np.float64(gauge_ov[gy, gx, b, i])
                s = np.float64(scene_ov[y, x, b, i])
                dot += s * g
                gg += g * g
                s2 += s * s
        norm2 = s2 if any_clipped else ss[b]
        if gg <= 0.0 or norm2 <= 0.0:
            return np.inf
        d2 += 2.0 - 2.0 * dot / np.sqrt(norm2 * gg)
        if d2 >= best_d2:
            return d2
    return d2


@njit(cache=True, parallel=True)
def masked_residuals(pixels, gauge, rows, resolution, noise, gauge_noise, floor2, residual,
                     distance):
    """Residual and signature distance of each pixel's match over its own lights.

    As colorps.residuals describes (and _pixel_kernels.group_residuals computes
    for one light set), with L each pixel's kept lights but for its match's
    clipped ones; ``resolution``
    (Hg * Wg, B) is h^2 over every light, and ``noise``, ``gauge_noise`` the
    scene's and gauge's models (read2, gain, pixel_kind, levels, table).
    """
    scene_ov, ys, xs, bands, keep = pixels
    gauge_ov, _, clipped = gauge
    read2, gain, kind, levels, table = noise
    g_read2, g_gain, g_kind, g_levels, g_table = gauge_noise
    wg, n_bands, m = gauge_ov.shape[1], gauge_ov.shape[2], gauge_ov.shape[3]
    for p in prange(ys.size):
        y, x, q = ys[p], xs[p], rows[p]
        qy, qx = q // wg, q % wg
        n_lights = 0
        for i in range(m):
            if _lit(keep, clipped, p, qy, qx, i):
                n_lights += 1
        ratio_sum, d_sum, used = 0.0, 0.0, 0
        for b in range(n_bands):
            if not bands[p, b]:
                continue
            s2, g2, sg, var_s, var_g = 0.0, 0.0, 0.0, 0.0, 0.0
            for i in range(m):
                if _lit(keep, clipped, p, qy, qx, i):
                    s = np.float64(scene_ov[y, x, b, i])
                    g = np.float64(gauge_ov[qy, qx, b, i])
                    s2 += s * s
                    g2 += g * g
                    sg += s * g
                    var_s += _variance(s, read2, gain, kind, levels, table)
                    var_g += _variance(g, g_read2, g_gain, g_kind, g_levels, g_table)
            if s2 <= 0.0 or g2 <= 0.0:
                continue
            d = max(2.0 - 2.0 * sg / np.sqrt(s2 * g2), 0.0)
            expected = (n_lights - 1) * (var_s / n_lights / s2 + var_g / n_lights / g2) \
                + resolution[q, b] / 6.0 + floor2
            ratio_sum += d / max(expected, 1e-30)
            d_sum += d
            used += 1
        residual[p] = np.sqrt(ratio_sum / used) if used else np.inf
        distance[p] = np.sqrt(d_sum / used) if used else np.inf
