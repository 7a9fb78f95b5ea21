"""Compiled per-pixel kernels: observation vectors and albedo (private).

The API is :func:`colorps.compute_signatures` and :func:`colorps.reconstruct`;
these kernels do their whole-image work in one parallel pass over pixels, with
no image-sized temporaries. Conventions are those of :mod:`colorps.signatures`:
a measurement is **invalid** when not finite, or negative by more than noise
around a dark value explains (below ``-negative_fraction`` times its channel's
brightest measurement at the pixel), **clipped** when at or above the clip
level, and a band's OV is **dark** when its Euclidean norm is at most
``min_norm``.
"""

import numpy as np
from numba import njit, prange


@njit(cache=True, inline="always")
def _invalid(v, floor):
    """Not finite, or below ``floor`` (see the module)."""
    return not (v >= floor) or not np.isfinite(v)


@njit(cache=True, parallel=True)
def observation_vectors(stack, first_row, first_col, mixing, clip_level, min_norm,
                        negative_fraction, ov, norms, band_invalid, band_clipped, band_dark,
                        clipped_lights, invalid_lights):
    """Fill the observation vectors of every pixel, their norms and their flags.

    Parameters
    ----------
    stack : (m, H, W, c) float32
        Linear measurements.
    first_row, first_col : int
        Where the box of the outputs begins in the stack (the box is read in
        place: no copy of it is made).
    mixing : (B, c) float32
        Band b's measurement is sum_k mixing[b, k] x (measurement of channel k;
        0 where invalid): the identity in colour mode, a luminance row or a
        one-hot row in mono mode. A band's sources are its channels with a
        non-zero weight; their invalid or clipped measurements are the band's.
    clip_level, min_norm : float
        ``np.inf`` for no clipping.
    negative_fraction : float
        A measurement below ``-negative_fraction`` times its channel's
        brightest at the pixel is invalid; smaller negative values are kept as
        measured.

    Outputs (written in place), of the box's h x w pixels
    -----------------------------------------------------
    ov : (h, w, B, m) float32
    norms : (h, w, B) float32
    band_invalid, band_clipped, band_dark : (h, w, B) bool
    clipped_lights, invalid_lights : (h, w, words) uint64
        Light masks (:mod:`colorps.light_masks`): image i set when a source
        measurement of it is clipped, or invalid.
    """
    m, c = stack.shape[0], stack.shape[3]
    h, w = ov.shape[0], ov.shape[1]
    n_bands = mixing.shape[0]
    for y in prange(h):
        values = np.empty((m, c), dtype=np.float32)  # the pixel's, read once
        floor = np.empty(c, dtype=np.float32)
        for x in range(w):
            floor[:] = 0.0
            for i in range(m):
                for k in range(c):
                    v = stack[i, first_row + y, first_col + x, k]
                    values[i, k] = v
                    if v > floor[k] and np.isfinite(v):
                        floor[k] = v  # the channel's brightest, for now
            for k in range(c):
                floor[k] *= -negative_fraction
            for word in range(clipped_lights.shape[2]):
                clipped_lights[y, x, word] = 0
                invalid_lights[y, x, word] = 0
            for b in range(n_bands):
                invalid = False
                clipped = False
                total = 0.0
                for i in range(m):
                    value = np.float32(0.0)
                    for k in range(c):
                        weight = mixing[b, k]
                        if weight == 0.0:
                            continue
                        v = values[i, k]
                        if v >= clip_level:  # +Inf too: clipped and invalid
                            clipped = True
                            clipped_lights[y, x, i >> 6] |= np.uint64(1) << np.uint64(i & 63)
                        if _invalid(v, floor[k]):
                            invalid = True
                            invalid_lights[y, x, i >> 6] |= np.uint64(1) << np.uint64(i & 63)
                            continue
                        value += weight * v
                    ov[y, x, b, i] = value
                    total += np.float64(value) * np.float64(value)
                norm = np.sqrt(total)
                norms[y, x, b] = norm
                dark = not invalid and norm <= min_norm
                band_invalid[y, x, b] = invalid
                band_clipped[y, x, b] = clipped
                band_dark[y, x, b] = dark


@njit(cache=True, parallel=True)
def unit_signatures(ov, band_valid, signatures):
    """Band-major unit vectors of OVs: ov (H, W, B, m) float32, band_valid (H, W, B);
    signatures (H, W, B * m) float32 written in place: ov / |ov| (float64 norm and
    division), 0 where the band is not valid."""
    h, w, n_bands, m = ov.shape
    for y in prange(h):
        for x in range(w):
            for b in range(n_bands):
                total = 0.0
                for i in range(m):
                    total += np.float64(ov[y, x, b, i]) * np.float64(ov[y, x, b, i])
                norm = np.sqrt(total)
                for i in range(m):
                    signatures[y, x, b * m + i] = (ov[y, x, b, i] / norm) \
                        if band_valid[y, x, b] else 0.0


@njit(cache=True, parallel=True, error_model="numpy")
def albedo(values, ys, xs, gauge, rows, offset, excluded, clip_level, gauge_albedo,
           min_energy, out):
    """Per-band albedo of pixels (ys, xs) matched to gauge pixels ``rows``.

    The gauge's measurements are interpolated bilinearly at the matched pixel
    plus the sub-pixel ``offset`` (columns, rows). With every measurement
    usable the albedo ratio is |S_k| / |G_k| (method eq. 6); otherwise the
    least-squares scale over the usable ones, NaN when those carry under
    ``min_energy`` of |G_k|^2, and NaN where the gauge is dark under every light
    (a fit gone past its rim). Times ``gauge_albedo[k]``.

    Parameters
    ----------
    values : (H, W, c, m) float32
        The scene's measurements, per pixel (its observation vectors in colour
        mode).
    ys, xs, rows : (P,) int64
        Pixel coordinates in ``values`` and flat gauge pixel indices (row-major).
    gauge : (m, Hg, Wg, c) float32
    offset : (P, 2) float32
    excluded : (P, m) bool
        Measurements left out (lights dropped from the pixel's match, and
        those with an invalid value).
    clip_level : float
        ``np.inf`` for no clipping.
    gauge_albedo : (c,) float64
    min_energy : float
    out : (P, c) float32
        Written in place.
    """
    m, hg, wg, c = gauge.shape
    for p in prange(ys.shape[0]):
        qy, qx = rows[p] // wg, rows[p] % wg
        gx = min(max(qx + offset[p, 0], 0.0), wg - 1.0)
        gy = min(max(qy + offset[p, 1], 0.0), hg - 1.0)
        x0 = min(int(np.floor(gx)), max(wg - 2, 0))
        y0 = min(int(np.floor(gy)), max(hg - 2, 0))
        x1 = min(x0 + 1, wg - 1)
        y1 = min(y0 + 1, hg - 1)
        fx = np.float32(gx - x0)
        fy = np.float32(gy - y0)
        for k in range(c):
            scene_energy = 0.0
            gauge_energy = 0.0
            used_energy = 0.0
            product = 0.0
            all_usable = True
            for i in range(m):
                top = gauge[i, y0, x0, k] * (1 - fx) + gauge[i, y0, x1, k] * fx
                bottom = gauge[i, y1, x0, k] * (1 - fx) + gauge[i, y1, x1, k] * fx
                g = np.float64(top * (1 - fy) + bottom * fy)
                s = np.float64(values[ys[p], xs[p], k, i])
                gauge_energy += g * g
                if not np.isfinite(s) or s >= clip_level or excluded[p, i]:
                    all_usable = False
                    continue
                scene_energy += s * s
                used_energy += g * g
                product += s * g
            if not gauge_energy > 0.0:  # a fit past the gauge's rim: no gauge there
                ratio = np.nan
            elif all_usable:
                ratio = np.sqrt(scene_energy) / np.sqrt(gauge_energy)
            elif used_energy >= min_energy * gauge_energy:
                ratio = product / used_energy
            else:
                ratio = np.nan
            out[p, k] = ratio * gauge_albedo[k]


@njit(cache=True, inline="always")
def _variance(value, read2, gain, pixel_kind, levels, table):
    """sigma(v)^2 = read^2 + gain v + q(v)^2 of one measurement (see mean_variance).

    Inlined by _refine_kernels too, whose numba cache does not see edits here.
    """
    v = np.float64(value)
    if not (v > 0.0) or not np.isfinite(v):
        v = 0.0
    variance = read2 + gain * v
    if pixel_kind == 1:
        # One half-float unit at v: 2^(floor(log2 v) - 10), made from the
        # exponent bits of v (11 times faster than frexp and ldexp; exact).
        exponent = (np.float64(max(v, 2.0 ** -14)).view(np.int64) >> 52) & 0x7FF
        ulp = np.int64((exponent - 10) << 52).view(np.float64)
        variance += ulp * ulp / 12.0
    elif pixel_kind == 2:
        q = _evenly_tabulated(v, levels, table)
        variance += q * q
    return variance


@njit(cache=True, inline="always")
def _evenly_tabulated(v, levels, table):
    """np.interp(v, levels, table) for evenly spaced ``levels`` (as
    noise._quantisation_levels makes them): the same value, clamped at the
    ends. numba's np.interp handles any spacing and dtype and took 4 of the
    31 s of the first run's compilation."""
    n = levels.size
    t = (v - levels[0]) / (levels[n - 1] - levels[0]) * (n - 1)
    t = min(max(t, 0.0), np.float64(n - 1))
    k = min(np.int64(t), n - 2)
    f = t - k
    return table[k] * (1.0 - f) + table[k + 1] * f


@njit(cache=True, inline="always")
def _band_norm2(scene_ov, y, x, b, lights):
    """|OV|^2 of band b of pixel (y, x) over ``lights`` (float64)."""
    total = 0.0
    for j in range(lights.size):
        v = np.float64(scene_ov[y, x, b, lights[j]])
        total += v * v
    return total


@njit(cache=True, inline="always")
def _divisor(norm2):
    """|OV| to divide by: 1 for a zero OV, which then stays zero."""
    return np.sqrt(norm2) if norm2 > 0.0 else 1.0


@njit(cache=True, inline="always")
def _unit(scene_ov, y, x, b, light, norm):
    """One component of a unit signature: float64 division, rounded to float32."""
    return np.float32(np.float64(scene_ov[y, x, b, light]) / norm)


@njit(cache=True, parallel=True)
def light_set(ov, lights, valid, min_norm, variance, norm2, mean_variance, usable):
    """The gauge over some lights, in one pass over its OVs.

    Its unit signatures are not stored: the kernels that need them divide the
    OVs by sqrt(norm2) where they read them (:func:`_unit`, as the scene's).

    Parameters
    ----------
    ov : (H, W, B, m) float32
    lights : (L,) int64
    valid : (H, W, B) bool
        Usable bands of the gauge over all lights.
    min_norm : float
        Smallest usable OV norm.
    variance : (H, W, B, m) float32
        Each measurement's noise variance.

    Outputs (written in place)
    --------------------------
    norm2 : (H, W, B) float64
        |OV|^2 over ``lights``.
    mean_variance : (H, W, B) float32
        Mean measurement variance over ``lights``.
    usable : (H, W, B) bool
        ``valid`` and |OV| over ``lights`` above ``min_norm``.
    """
    h, w, n_bands, _ = ov.shape
    n_lights = lights.size
    for y in prange(h):
        for x in range(w):
            for b in range(n_bands):
                total = _band_norm2(ov, y, x, b, lights)
                usable[y, x, b] = valid[y, x, b] and np.sqrt(total) > min_norm
                norm2[y, x, b] = total
                spread = 0.0
                for j in range(n_lights):
                    spread += variance[y, x, b, lights[j]]
                mean_variance[y, x, b] = spread / n_lights


@njit(cache=True, parallel=True, nogil=True)
def group_table(gauge_ov, lights, gauge_norm2, pixels, bands, weights, table):
    """The table of a group: weighted unit gauge signatures of some bands at some
    pixels over some lights.

    gauge_ov (Hg, Wg, B, m) float32, lights (L,) int64, gauge_norm2 (Hg, Wg, B)
    float64 (|OV|^2 over ``lights``), pixels (K,) int64 flat gauge pixels (usable
    in every band of ``bands``), bands (k,) int64, weights (k,) float32; table
    (K, k * L) float32 written in place, band-major, each entry as
    :func:`group_queries` makes a scene's.
    """
    width = gauge_ov.shape[1]
    n_lights = lights.size
    for e in prange(pixels.size):
        y, x = pixels[e] // width, pixels[e] % width
        for i in range(bands.size):
            b = bands[i]
            norm = _divisor(gauge_norm2[y, x, b])
            for j in range(n_lights):
                table[e, i * n_lights + j] = _unit(gauge_ov, y, x, b, lights[j], norm) * \
                    weights[i]


@njit(cache=True, parallel=True, nogil=True)
def group_queries(scene_ov, ys, xs, bands, lights, weights, queries):
    """The queries of a group of pixels: weighted unit signatures over some lights.

    Parameters
    ----------
    scene_ov : (H, W, B, m) float32
    ys, xs : (P,) int64
        The pixels.
    bands, lights : (K,) and (L,) int64
        The bands matched and the lights used.
    weights : (K,) float32
        Band weights.

    Outputs (written in place)
    --------------------------
    queries : (P, K * L) float32
        Band-major, weights[k] times band k's OV over ``lights`` divided by its
        norm (float64 division, rounded to float32; a zero OV stays zero).
    """
    n_lights = lights.size
    for p in prange(ys.size):
        y, x = ys[p], xs[p]
        for k in range(bands.size):
            b = bands[k]
            norm = _divisor(_band_norm2(scene_ov, y, x, b, lights))
            for j in range(n_lights):
                queries[p, k * n_lights + j] = \
                    _unit(scene_ov, y, x, b, lights[j], norm) * weights[k]


@njit(cache=True, parallel=True, nogil=True, error_model="numpy")
def group_residuals(scene_ov, group, gauge, noise, floor2, residual, distance):
    """Residual and signature distance of each pixel's match (colorps.residuals).

    Parameters
    ----------
    scene_ov : (H, W, B, m) float32
    group : colorps.residuals.MatchedGroup
        ys, xs, bands, lights as for group_queries; rows (P,) int64, each
        pixel's gauge match (flat gauge pixel index).
    gauge : colorps.residuals.GaugeOverLights
        ov (Hg, Wg, B, m) float32, the gauge's OVs (its unit signatures over
        ``lights`` are these divided by sqrt(norm2)); norm2, variance and
        resolution (Hg * Wg, B): squared OV norms and mean measurement
        variances over ``lights``, and h^2, of the gauge.
    noise : tuple
        The scene's noise model (read2, gain, pixel_kind, levels, table; see
        mean_variance).
    floor2 : float
        MODEL_FLOOR^2.

    Outputs (written in place)
    --------------------------
    residual : (P,) float32
        sqrt(mean over bands of d_k / E_k).
    distance : (P,) float32
        sqrt(mean over bands of d_k): the plain signature distance per band.
    """
    ys, xs, bands, lights, rows = group
    gauge_ov, gauge_norm2, gauge_var, resolution = gauge
    read2, gain, pixel_kind, levels, table = noise
    n_lights, n_bands = lights.size, bands.size
    width = gauge_ov.shape[1]
    for p in prange(ys.size):
        y, x, q = ys[p], xs[p], rows[p]
        qy, qx = q // width, q % width
        ratio_sum = 0.0
        d_sum = 0.0
        for k in range(n_bands):
            b = bands[k]
            variance = 0.0
            for j in range(n_lights):
                variance += _variance(scene_ov[y, x, b, lights[j]], read2, gain, pixel_kind,
                                      levels, table)
            variance = np.float64(np.float32(variance / n_lights))
            total = _band_norm2(scene_ov, y, x, b, lights)
            norm = _divisor(total)
            gauge_norm = _divisor(gauge_norm2[q, b])
            d = 0.0
            for j in range(n_lights):
                unit = _unit(scene_ov, y, x, b, lights[j], norm)
                diff = np.float64(unit) - np.float64(_unit(gauge_ov, qy, qx, b, lights[j],
                                                           gauge_norm))
                d += diff * diff
            expected = (n_lights - 1) * (variance / total + gauge_var[q, b] / gauge_norm2[q, b]) \
                + resolution[q, b] / 6.0 + floor2
            ratio_sum += d / max(expected, 1e-30)
            d_sum += d
        residual[p] = np.sqrt(ratio_sum / n_bands)
        distance[p] = np.sqrt(d_sum / n_bands)


@njit(cache=True, parallel=True, error_model="numpy")
def light_residuals(scene_ov, gauge_ov, lights, bands_used, extra_variance, noise, out):
    """Signed residual of every light in noise units (colorps.residuals.light_residuals).

    Parameters
    ----------
    scene_ov, gauge_ov : (P, B, m) float32 or float64
        Each pixel's OVs and its matched gauge pixel's.
    lights : (P, m) bool
        The lights each band's albedo ratio is fitted over.
    bands_used : (P, B) bool
    extra_variance : (P, B) float64
        Added to every measurement's noise variance of its pixel and band.
    noise : tuple
        The scene's noise model (read2, gain, pixel_kind, levels, table; see
        mean_variance).

    Outputs (written in place)
    --------------------------
    out : (P, m) float64
        Sum over the used bands of (S - a G) / sigma, a the band's least-squares
        ratio over ``lights``, divided by sqrt(bands used); a band whose sums are
        not finite (an invalid measurement) adds nothing.
    """
    read2, gain, pixel_kind, levels, table = noise
    n_pixels, n_bands, m = scene_ov.shape
    for p in prange(n_pixels):
        used = 0
        for i in range(m):
            out[p, i] = 0.0
        for b in range(n_bands):
            if not bands_used[p, b]:
                continue
            used += 1
            sg = 0.0
            gg = 0.0
            for i in range(m):
                w = 1.0 if lights[p, i] else 0.0  # (NaN * 0 stays NaN, as in numpy)
                s, g = np.float64(scene_ov[p, b, i]), np.float64(gauge_ov[p, b, i])
                sg += s * g * w
                gg += g * g * w
            ratio = sg / gg
            for i in range(m):
                s, g = np.float64(scene_ov[p, b, i]), np.float64(gauge_ov[p, b, i])
                sigma = np.sqrt(_variance(s, read2, gain, pixel_kind, levels, table)
                                + extra_variance[p, b])
                r = (s - ratio * g) / sigma
                if np.isfinite(r):
                    out[p, i] += r
        scale = 1.0 / np.sqrt(max(used, 1))
        for i in range(m):
            out[p, i] *= scale


@njit(cache=True, inline="always")
def _band_snr(scene_ov, y, x, b, read2, gain, pixel_kind, levels, table):
    """|S_b| / sigma_b of pixel (y, x) (see band_snr)."""
    m = scene_ov.shape[3]
    total = 0.0
    variance = 0.0
    for i in range(m):
        v = scene_ov[y, x, b, i]
        total += np.float64(v) * np.float64(v)
        variance += _variance(v, read2, gain, pixel_kind, levels, table)
    variance = np.float64(np.float32(variance / m))
    return np.sqrt(total) / np.sqrt(max(variance, 1e-30))


@njit(cache=True, parallel=True)
def band_snr(scene_ov, ys, xs, valid, read2, gain, pixel_kind, levels, table, out):
    """|S_k| / sigma_k of each band of pixels (ys, xs), sigma_k^2 the mean variance
    of its measurements (float32-rounded, as mean_variance gives it); 0 where
    ``valid`` (P, B) is false. scene_ov (H, W, B, m) float32; out (P, B) float64."""
    n_bands = scene_ov.shape[2]
    for p in prange(ys.size):
        for b in range(n_bands):
            out[p, b] = _band_snr(scene_ov, ys[p], xs[p], b, read2, gain, pixel_kind, levels,
                                  table) if valid[p, b] else 0.0


@njit(cache=True, parallel=True)
def band_levels(scene_ov, ys, xs, valid, read2, gain, pixel_kind, levels, table, drop_level,
                out_valid, out_levels):
    """The bands each pixel (ys, xs) is matched on and their weight levels, in one
    pass (the policy of colorps.band_weights.band_weights).

    A band's level is round(log2(snr / the pixel's best snr)), half-way cases
    to even, clipped to ``drop_level`` .. 0 (``drop_level`` where its snr is 0;
    snr as band_snr gives it). Bands above ``drop_level`` are kept when they
    still fix a normal (kept bands x (lights - 1) >= 2), else every valid
    band is; kept bands get at least ``drop_level + 1``, the others 0.
    valid, out_valid (P, B) bool; out_levels (P, B) int8.
    """
    n_bands, m = scene_ov.shape[2], scene_ov.shape[3]
    for p in prange(ys.size):
        snr = np.zeros(n_bands)
        best = 0.0
        for b in range(n_bands):
            if valid[p, b]:
                snr[b] = _band_snr(scene_ov, ys[p], xs[p], b, read2, gain, pixel_kind, levels,
                                   table)
                best = max(best, snr[b])
        n_kept = 0
        for b in range(n_bands):
            level = drop_level
            if best > 0.0 and snr[b] > 0.0:
                level = min(max(np.rint(np.log2(snr[b] / best)), drop_level), 0.0)
            out_levels[p, b] = np.int8(level)
            if valid[p, b] and level > drop_level:
                n_kept += 1
        fixes_normal = n_kept * (m - 1) >= 2
        for b in range(n_bands):
            keep = valid[p, b] and (out_levels[p, b] > drop_level or not fixes_normal)
            out_valid[p, b] = keep
            out_levels[p, b] = max(out_levels[p, b], drop_level + 1) if keep else 0


@njit(cache=True, parallel=True)
def mean_variance(values, read2, gain, pixel_kind, levels, table, out):
    """Mean over the last axis of sigma(v)^2 = read^2 + gain v + q(v)^2.

    Parameters
    ----------
    values : (N, m) float32
        Measurements (non-finite or negative ones count as 0).
    read2, gain : float
    pixel_kind : int
        0: float (q = 0), 1: half float (q = one half-float unit / sqrt(12)),
        2: integer codes (q interpolated in ``table`` at ``levels``).
    levels, table : (L,) float64
    out : (N,) float32
        Written in place.
    """
    n, m = values.shape
    for p in prange(n):
        total = 0.0
        for i in range(m):
            total += _variance(values[p, i], read2, gain, pixel_kind, levels, table)
        out[p] = total / m


@njit(cache=True, parallel=True)
def neighbour_steps(ov, lights, norm2, usable, rows, out):
    """Mean squared signature step from pixels to their usable 4-neighbours.

    Parameters
    ----------
    ov : (H, W, B, m) float32
        Per-band OVs (or unit signatures, with ``norm2`` all 1).
    lights : (L,) int64
        The lights of the signatures.
    norm2 : (H, W, B) float64
        |OV|^2 over ``lights``: a signature is ov / sqrt(norm2) (:func:`_unit`).
    usable : (H, W) bool
    rows : (n,) int64
        Flat pixel indices (y * W + x) to compute.
    out : (H * W, B) float64
        Written in place at ``rows``: mean over usable neighbours (both pixels
        usable) of sum_i (g[q, b, i] - g[neighbour, b, i])^2; 0 with no such
        neighbour.
    """
    h, w, n_bands, _ = ov.shape
    n_lights = lights.size
    for j in prange(rows.size):
        q = rows[j]
        y, x = q // w, q % w
        for b in range(n_bands):
            out[q, b] = 0.0
        if not usable[y, x]:
            continue
        count = 0
        for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            ny, nx = y + dy, x + dx
            if ny < 0 or ny >= h or nx < 0 or nx >= w or not usable[ny, nx]:
                continue
            count += 1
            for b in range(n_bands):
                norm, other_norm = _divisor(norm2[y, x, b]), _divisor(norm2[ny, nx, b])
                total = 0.0
                for i in range(n_lights):
                    d = np.float64(_unit(ov, y, x, b, lights[i], norm)) - \
                        _unit(ov, ny, nx, b, lights[i], other_norm)
                    total += d * d
                out[q, b] += total
        if count:
            for b in range(n_bands):
                out[q, b] /= count
