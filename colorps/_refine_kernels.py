"""Compiled kernel of the continuous refinement (private; the API is :mod:`colorps.refine`).

Around each pixel's matched gauge pixel, every gauge measurement (band k,
light i) is modelled as a quadratic in the sub-pixel offset (u, v) (columns,
rows) fitted by least squares to the 5 x 5 neighbourhood (3 x 3 near the rim)::

    G_ki(u, v) = c0 + c1 u + c2 v + c3 u^2 + c4 u v + c5 v^2

and the offset minimising the weighted misfit

    E(u, v) = sum_ki w_ki (S_ki - a_k G_ki(u, v))^2,  a_k the best scale of band k

is found by Gauss-Newton (variable projection: a_k in closed form at every
step, and projected out of the Jacobian, a_k (G_u - (<G, G_u> / <G, G>) G)),
inside the neighbourhood (|u|, |v| <= 1). A pixel matched to a gauge
pixel on the usable gauge's outermost ring (no full 3 x 3 neighbourhood: no
model) starts from the model of a neighbour that has one, at its own place. The
gauge normals get the same quadratic model and are evaluated at the optimum;
the Jacobian gives the offset's covariance (J^T W J)^-1 and, through the
normal's derivatives, the angular uncertainty.
"""

from collections import namedtuple

import numpy as np
from numba import njit, prange

# numba's cache watches only this file: after editing _pixel_kernels._variance,
# touch this one too (or clear its __pycache__), or the refinement keeps the old one.
from ._config import FASTMATH
from ._pixel_kernels import _variance

# ---------------------------------------------------------------- tuning
#: Half sides of the gauge neighbourhoods the quadratic model is fitted to: 5 x 5
#: where the gauge has it, else 3 x 3 (near the rim). A noisy gauge makes a
#: 3 x 3 fit's gradients mostly noise (sigma 0.02 on an r = 100 px sphere: the
#: uncertainty came out 3x too small); 5 x 5 averages that down.
HALVES = (2, 1)
#: Gauss-Newton steps per pixel (each leaves about a fifth of the way to the
#: optimum: 0.005 px to go, median, after 4 on a noisy colour capture).
STEPS = 4
#: Damping added to the normal equations (relative to their trace), for flat
#: neighbourhoods.
DAMPING = 1e-9
#: When the optimum reaches one pixel from the centre, the fit moves
#: to the neighbouring gauge pixel, at most this many times (noisy pixels whose
#: table match is off by more than a pixel).
MAX_MOVES = 3
#: At the usable gauge's edge (the next gauge pixel has no model) the fit may
#: go up to this many pixels past the last modelled one, on its model: scene
#: normals beyond what the gauge shows, as on a sphere off a lens's axis, whose
#: table stops short of grazing on the side away from the axis (7.6 degrees off
#: axis, deep folds: mean 0.82 -> 0.59 degrees, p99 10.3 -> 5.8, facets
#: 1.6 -> 0.0 %; 5 or 8 pixels gave the same).
EXTRAPOLATE = 3.0
#: Pixels handed to a thread at a time (scratch allocated once per chunk).
PIXEL_CHUNK = 256


# ---------------------------------------------------------------- data layout
#: The gauge as the fit sees it: coef (Hg, Wg, B * M, 6) and ncoef (Hg, Wg, 3, 6),
#: the quadratic model of every gauge measurement and normal component around
#: each gauge pixel (:func:`colorps.refine.quadratic_models`); window (Hg, Wg),
#: 0 where a gauge pixel has no usable neighbourhood; ov (Hg, Wg, B, M) its OVs.
GaugeModel = namedtuple("GaugeModel", "coef ncoef window ov")
#: The pixels to refine: scene OVs ov (H, W, B, M); pixel p is (y[p], x[p]),
#: matched to gauge pixel (qy[p], qx[p]), with bands[p] (bit k: band used) and
#: dropped[p] (light masks, (P, words) uint64).
Pixels = namedtuple("Pixels", "ov y x qy qx bands dropped")
#: The scene's (row 0) and gauge's (row 1) noise: noise (2, 3) (read^2, gain,
#: pixel kind), levels (Q,) and table (2, Q) (:func:`colorps._pixel_kernels._variance`).
NoiseTables = namedtuple("NoiseTables", "noise levels table")
#: Outputs, one per pixel: the gauge pixel the fit ended at (y, x) and the
#: offset (u, v) from it, the unit normal (P, 3), the normal's angular variance
#: under the noise model cov and from the sandwich of the residuals fit
#: (radians^2; NaN: no degrees of freedom left), ok, whether it was refined,
#: and over the fit's inliers (below) chi2, the squared residuals in noise units
#: per degree of freedom (NaN: none left), and outliers (P, words), the light
#: mask of its outliers.
Refined = namedtuple("Refined", "y x u v normal cov fit ok chi2 outliers")


def quadratic_fit_matrix(half: int) -> np.ndarray:
    """(6, (2 half + 1)^2) least-squares fit of (1, u, v, u^2, uv, v^2) to a patch,
    row-major (row offsets -half .. half outer, column offsets inner)."""
    dv, du = np.mgrid[-half:half + 1, -half:half + 1]
    du, dv = du.ravel().astype(np.float64), dv.ravel().astype(np.float64)
    design = np.stack([np.ones(du.size), du, dv, du * du, du * dv, dv * dv], axis=1)
    return np.linalg.pinv(design).astype(np.float64)


@njit(cache=True, parallel=True)
def fit_quadratics(series, ys, xs, half, fit, coef):
    """coef[y, x, s, :] = fit @ (the (2 half + 1)^2 patch of series s around (y, x))
    for every pixel (ys[p], xs[p]); ``fit`` is :func:`quadratic_fit_matrix`."""
    side = 2 * half + 1
    n_series = series.shape[2]
    for p in prange(ys.size):
        y, x = ys[p], xs[p]
        for s in range(n_series):
            c0 = c1 = c2 = c3 = c4 = c5 = 0.0
            t = 0
            for dy in range(side):
                for dx in range(side):
                    value = series[y + dy - half, x + dx - half, s]
                    c0 += fit[0, t] * value
                    c1 += fit[1, t] * value
                    c2 += fit[2, t] * value
                    c3 += fit[3, t] * value
                    c4 += fit[4, t] * value
                    c5 += fit[5, t] * value
                    t += 1
            coef[y, x, s, 0] = c0
            coef[y, x, s, 1] = c1
            coef[y, x, s, 2] = c2
            coef[y, x, s, 3] = c3
            coef[y, x, s, 4] = c4
            coef[y, x, s, 5] = c5


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _eval(coef, y, x, j, u, v):
    """Value and (d/du, d/dv) at (u, v) of quadratic j of gauge pixel (y, x)."""
    c0 = coef[y, x, j, 0]
    c1 = coef[y, x, j, 1]
    c2 = coef[y, x, j, 2]
    c3 = coef[y, x, j, 3]
    c4 = coef[y, x, j, 4]
    c5 = coef[y, x, j, 5]
    value = c0 + c1 * u + c2 * v + c3 * u * u + c4 * u * v + c5 * v * v
    return value, c1 + 2.0 * c3 * u + c4 * v, c2 + c4 * u + 2.0 * c5 * v


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _band_scale(coef, y, x, obs, weights, robust, robust_on, k, n_lights, u, v, models):
    """The best scale a_k of band k's model at (u, v) (weights times the robust
    factors when ``robust_on``), and the model's slopes along itself, <G, G_u> /
    <G, G> and <G, G_v> / <G, G>, under the same weights; (0, 0, 0) when no
    measurement of the band is used. ``models`` (3, M) receives the model's
    value and derivatives (G, G_u, G_v) at each light the band uses, for the
    caller's pass over the residuals.

    The slopes project a_k out of the Jacobian (variable projection): a move
    of (u, v) that only brightens the band is taken up by a_k, so only G_u -
    (<G, G_u> / <G, G>) G moves the fit. Left in, the normal equations were too
    steep: each step went about half way (0.04 px still to go after 4 steps)
    and the offset's covariance came out too small.
    """
    sg = 0.0
    gg = 0.0
    ggu = 0.0
    ggv = 0.0
    for i in range(n_lights):
        if weights[k, i] > 0.0:
            g, gu, gv = _eval(coef, y, x, k * n_lights + i, u, v)
            models[0, i] = g
            models[1, i] = gu
            models[2, i] = gv
            wt = weights[k, i] * (robust[k, i] if robust_on else 1.0)
            sg += wt * obs[k, i] * g
            gg += wt * g * g
            ggu += wt * g * gu
            ggv += wt * g * gv
    if not gg > 0.0:
        return 0.0, 0.0, 0.0
    return sg / gg, ggu / gg, ggv / gg


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _gauss_newton(coef, y, x, obs, weights, robust, limit, n_bands, n_lights, u, v, reach,
                  models):
    """STEPS Gauss-Newton steps from (u, v) inside the neighbourhood; returns the
    offset and the normal equations' matrix (h00, h01, h11) at it. Each
    measurement's weight is times its robust factor, which each step sets to
    min(1, limit / |residual in noise units|) for the next (Huber). ``models``
    (3, M) is scratch (:func:`_band_scale`)."""
    h00 = h01 = h11 = 0.0
    for _ in range(STEPS):
        h00 = 0.0
        h01 = 0.0
        h11 = 0.0
        g0 = 0.0
        g1 = 0.0
        for k in range(n_bands):
            a, slope_u, slope_v = _band_scale(coef, y, x, obs, weights, robust, True, k,
                                              n_lights, u, v, models)
            if a == 0.0:
                continue
            for i in range(n_lights):
                wt = weights[k, i] * robust[k, i]
                if wt > 0.0:
                    g = models[0, i]
                    r = obs[k, i] - a * g
                    z = abs(r) * np.sqrt(weights[k, i])
                    robust[k, i] = min(1.0, limit / z) if z > 0.0 else 1.0
                    ju = a * (models[1, i] - slope_u * g)
                    jv = a * (models[2, i] - slope_v * g)
                    h00 += wt * ju * ju
                    h01 += wt * ju * jv
                    h11 += wt * jv * jv
                    g0 += wt * ju * r
                    g1 += wt * jv * r
        damp = DAMPING * (h00 + h11) + 1e-30
        a00 = h00 + damp
        a11 = h11 + damp
        det = a00 * a11 - h01 * h01
        if det <= 0.0:
            break
        u = min(max(u + (a11 * g0 - h01 * g1) / det, -reach), reach)
        v = min(max(v + (a00 * g1 - h01 * g0) / det, -reach), reach)
    return u, v, h00, h01, h11


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _meat(coef, y, x, obs, weights, robust, n_bands, n_lights, u, v, models):
    """The measured residuals' spread along the Jacobian at (u, v), the middle
    of the sandwich covariance: sum (w r)^2 J J^T (m00, m01, m11) over the
    measurements the fit used, at their noise weights w (not down-weighted:
    a measurement the gauge does not explain counts in full), times n / (n - p)
    for the n measurements and p fitted values (the offset and a scale per band)."""
    m00 = m01 = m11 = 0.0
    count = 0
    scales = 0
    for k in range(n_bands):
        a, slope_u, slope_v = _band_scale(coef, y, x, obs, weights, robust, False, k,
                                          n_lights, u, v, models)
        if a == 0.0:
            continue
        scales += 1
        for i in range(n_lights):
            wt = weights[k, i]
            if wt > 0.0:
                g = models[0, i]
                r = obs[k, i] - a * g
                spread = (wt * r) ** 2
                ju = a * (models[1, i] - slope_u * g)
                jv = a * (models[2, i] - slope_v * g)
                m00 += spread * ju * ju
                m01 += spread * ju * jv
                m11 += spread * jv * jv
                count += 1
    free = count - scales - 2
    if free <= 0:
        return 0.0, 0.0, 0.0, False
    scale = count / free
    return scale * m00, scale * m01, scale * m11, True


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _inliers(coef, y, x, obs, weights, robust, limit, cut, n_bands, n_lights, u, v, outliers,
             models):
    """The fit's chi-square per degree of freedom over its inliers: the lights
    none of whose measurements the robust fit left more than ``cut`` noise
    units off (robust factor limit / residual below limit / cut); the others
    are set in ``outliers`` (a light mask)."""
    for k in range(n_bands):
        for i in range(n_lights):
            if weights[k, i] > 0.0 and robust[k, i] * cut < limit:
                outliers[i >> 6] |= np.uint64(1) << np.uint64(i & 63)
    chi2 = 0.0
    count = 0
    scales = 0
    for k in range(n_bands):
        a, _slope_u, _slope_v = _band_scale(coef, y, x, obs, weights, robust, True, k,
                                            n_lights, u, v, models)
        if a == 0.0:
            continue
        scales += 1
        for i in range(n_lights):
            if weights[k, i] > 0.0 and not _has(outliers, i):
                r = obs[k, i] - a * models[0, i]
                chi2 += weights[k, i] * r * r
                count += 1
    free = count - scales - 2
    return chi2 / free if free > 0 else np.nan


@njit(cache=True, inline="always")
def _modelled_neighbour(window, y, x):
    """(dy, dx) of the 8-neighbour of (y, x) with the widest model window (a
    4-neighbour before a diagonal one); (0, 0) when none has one."""
    best_dy = 0
    best_dx = 0
    best = 0
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (-1, 1), (1, -1), (1, 1)):
        yy = y + dy
        xx = x + dx
        if 0 <= yy < window.shape[0] and 0 <= xx < window.shape[1] and window[yy, xx] > best:
            best = window[yy, xx]
            best_dy = dy
            best_dx = dx
    return best_dy, best_dx


@njit(cache=True, inline="always")
def _has(mask, i):
    """Image i is in the light mask (words of uint64, colorps.light_masks)."""
    return (mask[i >> 6] >> np.uint64(i & 63)) & np.uint64(1) != 0


@njit(cache=True, inline="always")
def _model_variance(v, noise, levels, table, row):
    """sigma(v)^2 under noise model ``row``: noise[row] = (read^2, gain, kind)."""
    return _variance(v, noise[row, 0], noise[row, 1], int(noise[row, 2]), levels, table[row])


@njit(cache=True, fastmath=FASTMATH, inline="always")
def _weights(scene_ov, gauge_ov, py, px, y, x, bands, dropped, noise, levels, table, obs,
             weights):
    """Fill obs (B, M) with the pixel's measurements and weights (B, M) with
    1 / (sigma_S^2 + (|S_k| / |G_k|)^2 sigma_G^2) for the bands and lights its
    match used (0 for the others); sigma^2 as _pixel_kernels._variance gives it,
    of the scene's (row 0 of noise and table) and the gauge's (row 1) model."""
    n_bands, n_lights = obs.shape
    for k in range(n_bands):
        used = (bands >> k) & 1
        s2 = 0.0
        g2 = 0.0
        for i in range(n_lights):
            obs[k, i] = scene_ov[py, px, k, i]
            if used and not _has(dropped, i):
                s2 += obs[k, i] * obs[k, i]
                g = gauge_ov[y, x, k, i]
                g2 += g * g
        ratio2 = s2 / g2 if g2 > 0.0 else 0.0
        for i in range(n_lights):
            weights[k, i] = 0.0
            if used and g2 > 0.0 and not _has(dropped, i):
                variance = _model_variance(obs[k, i], noise, levels, table, 0) + \
                    ratio2 * _model_variance(gauge_ov[y, x, k, i], noise, levels, table, 1)
                weights[k, i] = 1.0 / max(variance, 1e-30)


@njit(cache=True, fastmath=FASTMATH)
def _refine_pixel(p, coef, ncoef, window, obs, weights, robust, models, limit, qy, qx, out_y,
                  out_x, out_u, out_v, out_normal, out_cov, out_fit, out_ok):
    n_bands, n_lights = obs.shape
    robust[:] = 1.0
    y, x = qy[p], qx[p]
    out_ok[p] = False
    u = 0.0
    v = 0.0
    if window[y, x] == 0:
        # A gauge pixel without a model (its neighbourhood reaches past the
        # usable gauge: the rim) starts from a neighbour that has one, at the
        # pixel's own place (offset -dy, -dx from it).
        dy, dx = _modelled_neighbour(window, y, x)
        if dy == 0 and dx == 0:
            return
        y += dy
        x += dx
        u = -float(dx)
        v = -float(dy)
    h00 = h01 = h11 = 0.0
    for move in range(MAX_MOVES + 1):
        u, v, h00, h01, h11 = _gauss_newton(coef, y, x, obs, weights, robust, limit,
                                            n_bands, n_lights, u, v, 1.0, models)
        step_x = 1 if u >= 1.0 else -1 if u <= -1.0 else 0
        step_y = 1 if v >= 1.0 else -1 if v <= -1.0 else 0
        if (step_x == 0 and step_y == 0) or move == MAX_MOVES:
            break
        if window[y + step_y, x + step_x] == 0:
            u, v, h00, h01, h11 = _gauss_newton(coef, y, x, obs, weights, robust, limit,
                                                n_bands, n_lights, u, v, EXTRAPOLATE, models)
            break
        y += step_y
        x += step_x
        u -= step_x
        v -= step_y
    out_y[p] = y
    out_x[p] = x
    det = h00 * h11 - h01 * h01
    if not det > 0.0:
        return
    # Normal at (u, v), and its derivatives for the angular covariance.
    nx, nxu, nxv = _eval(ncoef, y, x, 0, u, v)
    ny, nyu, nyv = _eval(ncoef, y, x, 1, u, v)
    nz, nzu, nzv = _eval(ncoef, y, x, 2, u, v)
    norm = np.sqrt(nx * nx + ny * ny + nz * nz)
    if not norm > 0.0:
        return
    out_u[p] = u
    out_v[p] = v
    out_normal[p, 0] = nx / norm
    out_normal[p, 1] = ny / norm
    out_normal[p, 2] = nz / norm
    # cov(u, v) = (J^T W J)^-1; the normal's angular variance = trace(Jn C Jn^T).
    c00 = h11 / det
    c01 = -h01 / det
    c11 = h00 / det
    tu = (nxu * nxu + nyu * nyu + nzu * nzu) / (norm * norm)
    tuv = (nxu * nxv + nyu * nyv + nzu * nzv) / (norm * norm)
    tv = (nxv * nxv + nyv * nyv + nzv * nzv) / (norm * norm)
    out_cov[p] = c00 * tu + 2.0 * c01 * tuv + c11 * tv
    # The sandwich C M C, M the measured residuals' spread: the covariance the
    # residuals show, whatever their cause.
    m00, m01, m11, used = _meat(coef, y, x, obs, weights, robust, n_bands, n_lights, u, v,
                                models)
    if used:
        s00 = c00 * c00 * m00 + 2.0 * c00 * c01 * m01 + c01 * c01 * m11
        s01 = c00 * c01 * m00 + (c00 * c11 + c01 * c01) * m01 + c01 * c11 * m11
        s11 = c01 * c01 * m00 + 2.0 * c01 * c11 * m01 + c11 * c11 * m11
        out_fit[p] = s00 * tu + 2.0 * s01 * tuv + s11 * tv
    out_ok[p] = True


@njit(cache=True, fastmath=FASTMATH, parallel=True)
def refine(gauge, pixels, noise_tables, limit, cut, out):
    """Refine every pixel (``prange`` over chunks); see the module docstring.

    ``gauge`` is a :data:`GaugeModel`, ``pixels`` the :data:`Pixels` to refine,
    ``noise_tables`` the :data:`NoiseTables` of both stacks; measurements more
    than ``limit`` noise units off are down-weighted, and lights with one more
    than ``cut`` off are the fit's outliers. The results are written into
    ``out``, a :data:`Refined` of preallocated arrays (y and x start as qy and
    qx, outliers as zeros).
    """
    coef, ncoef, window, gauge_ov = gauge
    scene_ov, py, px, qy, qx, bands, dropped = pixels
    noise, levels, table = noise_tables
    out_y, out_x, out_u, out_v, out_normal, out_cov, out_fit, out_ok, out_chi2, outliers = out
    n = py.shape[0]
    n_bands, n_lights = scene_ov.shape[2], scene_ov.shape[3]
    n_chunks = (n + PIXEL_CHUNK - 1) // PIXEL_CHUNK
    for chunk in prange(n_chunks):
        obs = np.empty((n_bands, n_lights))
        weights = np.empty((n_bands, n_lights))
        robust = np.empty((n_bands, n_lights))
        models = np.empty((3, n_lights))
        for p in range(chunk * PIXEL_CHUNK, min((chunk + 1) * PIXEL_CHUNK, n)):
            _weights(scene_ov, gauge_ov, py[p], px[p], qy[p], qx[p], bands[p], dropped[p],
                     noise, levels, table, obs, weights)
            _refine_pixel(p, coef, ncoef, window, obs, weights, robust, models, limit, qy, qx,
                          out_y, out_x, out_u, out_v, out_normal, out_cov, out_fit, out_ok)
            if out_ok[p]:
                out_chi2[p] = _inliers(coef, out_y[p], out_x[p], obs, weights, robust, limit,
                                       cut, n_bands, n_lights, out_u[p], out_v[p], outliers[p],
                                       models)
