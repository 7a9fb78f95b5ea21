"""Compiled per-pixel fit of normals under a finish (private; the API is
:func:`colorps.brdf.best_normals`).

For each of N pixels, damped Gauss-Newton on two tangent angles of its normal,
with numerical derivatives, minimises the weighted squared residuals of its
measurements (per unit light) against the finish of :mod:`colorps.brdf`, its
albedo in every band projected out::

    model_ib = a_b D_i(n) + t_b s_b G_i(n)

with D the diffuse shading (falloff g over ``knots``, times the cosine, times
the Oren-Nayar factor of ``roughness``), G the GGX highlight lobe of ``alpha``
(:func:`colorps.brdf.ggx_lobe`), s_b the highlight strength per band and
t_b = a_b for a tinted highlight, 1 for a white one (``white``).

Arrays (float64, passed by name): ``obs`` and ``weight`` (m, N, c),
``normals`` (N, 3) updated in place, ``views`` (N, 3) unit directions towards
the camera, ``directions`` (m, 3), ``knots`` and ``falloff`` (K,),
``specular`` (c,).
"""

import numpy as np
from numba import njit, prange

#: Pixels per parallel chunk (each chunk holds its own scratch residuals).
CHUNK_PIXELS = 64


@njit(cache=True)
def _falloff_at(cosine, knots, falloff):
    """g(cosine), linear between the knots (clamped at the ends)."""
    if cosine <= knots[0]:
        return falloff[0]
    for k in range(1, knots.size):
        if cosine <= knots[k]:
            t = (cosine - knots[k - 1]) / (knots[k] - knots[k - 1])
            return falloff[k - 1] + t * (falloff[k] - falloff[k - 1])
    return falloff[-1]


@njit(cache=True)
def _shading(n, light, view, knots, falloff, alpha, roughness, fresnel_f0):
    """(diffuse D, lobe G) of unit normal ``n`` under one unit light."""
    cos_l = n[0] * light[0] + n[1] * light[1] + n[2] * light[2]
    if cos_l <= 0.0:
        return 0.0, 0.0
    cos_v = min(max(n[0] * view[0] + n[1] * view[1] + n[2] * view[2], 0.0), 1.0)
    diffuse = _falloff_at(cos_l, knots, falloff) * cos_l
    if roughness > 0.0:  # Oren-Nayar, as colorps.finishes.oren_nayar_factor
        s2 = roughness * roughness
        a = 1.0 - 0.5 * s2 / (s2 + 0.33)
        b = 0.45 * s2 / (s2 + 0.09)
        cos_i = min(cos_l, 1.0)
        theta_i = np.arccos(cos_i)
        theta_r = np.arccos(cos_v)
        light_view = light[0] * view[0] + light[1] * view[1] + light[2] * view[2]
        norm = np.sqrt(max(1.0 - cos_i * cos_i, 0.0)) * np.sqrt(max(1.0 - cos_v * cos_v, 0.0))
        cos_phi = (light_view - cos_v * cos_i) / norm if norm > 1e-12 else 0.0
        diffuse *= a + b * max(cos_phi, 0.0) * np.sin(max(theta_i, theta_r)) * \
            np.tan(min(theta_i, theta_r))
    hx, hy, hz = light[0] + view[0], light[1] + view[1], light[2] + view[2]
    length = np.sqrt(hx * hx + hy * hy + hz * hz)
    hx, hy, hz = hx / length, hy / length, hz / length
    cos_h = min(max(n[0] * hx + n[1] * hy + n[2] * hz, 0.0), 1.0)
    cos_d = min(max(light[0] * hx + light[1] * hy + light[2] * hz, 0.0), 1.0)
    a2 = alpha * alpha
    d = cos_h * cos_h * (a2 - 1.0) + 1.0
    lobe = a2 / (d * d) * (1.0 + (1.0 / fresnel_f0 - 1.0) * (1.0 - cos_d) ** 5)
    lobe *= 2.0 * cos_l / (cos_l + np.sqrt(a2 + (1.0 - a2) * cos_l * cos_l))
    lobe /= 2.0 * (cos_v + np.sqrt(a2 + (1.0 - a2) * cos_v * cos_v))
    return diffuse, lobe


@njit(cache=True)
def _residuals(obs, weight, p, n, view, directions, knots, falloff, specular, alpha,
               roughness, white, fresnel_f0, diffuse, lobe, out):
    """Fill ``out`` (m * c) with pixel p's weighted residuals at normal ``n``
    (``diffuse`` and ``lobe``: (m,) scratch); return their sum of squares."""
    m, _, c = obs.shape
    for i in range(m):
        diffuse[i], lobe[i] = _shading(n, directions[i], view, knots, falloff, alpha,
                                       roughness, fresnel_f0)
    cost = 0.0
    for b in range(c):
        num = 0.0
        den = 0.0
        for i in range(m):
            highlight = specular[b] * lobe[i]
            shape = diffuse[i] if white else diffuse[i] + highlight
            target = obs[i, p, b] - highlight if white else obs[i, p, b]
            num += weight[i, p, b] * shape * target
            den += weight[i, p, b] * shape * shape
        albedo = num / max(den, 1e-30)
        for i in range(m):
            highlight = specular[b] * lobe[i]
            model = albedo * diffuse[i] + (highlight if white else albedo * highlight)
            r = (obs[i, p, b] - model) * np.sqrt(weight[i, p, b])
            out[i * c + b] = r
            cost += r * r
    return cost


@njit(cache=True)
def _moved(n, t1, t2, u, v, out):
    """``out`` = n + u t1 + v t2, normalised and facing the camera (z >= 0)."""
    for k in range(3):
        out[k] = n[k] + u * t1[k] + v * t2[k]
    out[2] = max(out[2], 0.0)  # (the sign of z is that of z over the length)
    length = np.sqrt(out[0] ** 2 + out[1] ** 2 + out[2] ** 2)
    for k in range(3):
        out[k] /= length


@njit(cache=True, parallel=True)
def best_normals(obs, weight, normals, views, directions, knots, falloff, specular, alpha,
                 roughness, white, fresnel_f0, steps, max_step, eps):
    """Each pixel's normal moved to its least weighted squared residual (in place)."""
    m, n_pixels, c = obs.shape
    chunks = (n_pixels + CHUNK_PIXELS - 1) // CHUNK_PIXELS
    for chunk in prange(chunks):
        current = np.empty(m * c)
        along_u = np.empty(m * c)
        along_v = np.empty(m * c)
        trial = np.empty(m * c)
        diffuse = np.empty(m)
        lobe = np.empty(m)
        n = np.empty(3)
        t1 = np.empty(3)
        t2 = np.empty(3)
        probe = np.empty(3)
        for p in range(chunk * CHUNK_PIXELS, min((chunk + 1) * CHUNK_PIXELS, n_pixels)):
            for k in range(3):
                n[k] = normals[p, k]
            view = views[p]
            # A tangent basis: t1 = n x helper, t2 = n x t1.
            hx, hy, hz = (1.0, 0.0, 0.0) if abs(n[0]) < 0.9 else (0.0, 1.0, 0.0)
            t1[0], t1[1], t1[2] = n[1] * hz - n[2] * hy, n[2] * hx - n[0] * hz, \
                n[0] * hy - n[1] * hx
            length = np.sqrt(t1[0] ** 2 + t1[1] ** 2 + t1[2] ** 2)
            for k in range(3):
                t1[k] /= length
            t2[0], t2[1], t2[2] = n[1] * t1[2] - n[2] * t1[1], n[2] * t1[0] - n[0] * t1[2], \
                n[0] * t1[1] - n[1] * t1[0]
            u = 0.0
            v = 0.0
            damping = 1e-3
            _moved(n, t1, t2, u, v, probe)
            cost = _residuals(obs, weight, p, probe, view, directions, knots, falloff, specular,
                              alpha, roughness, white, fresnel_f0, diffuse, lobe, current)
            for _ in range(steps):
                _moved(n, t1, t2, u + eps, v, probe)
                _residuals(obs, weight, p, probe, view, directions, knots, falloff, specular,
                           alpha, roughness, white, fresnel_f0, diffuse, lobe, along_u)
                _moved(n, t1, t2, u, v + eps, probe)
                _residuals(obs, weight, p, probe, view, directions, knots, falloff, specular,
                           alpha, roughness, white, fresnel_f0, diffuse, lobe, along_v)
                a = 0.0
                b = 0.0
                d = 0.0
                gu = 0.0
                gv = 0.0
                for j in range(m * c):
                    ju = (along_u[j] - current[j]) / eps
                    jv = (along_v[j] - current[j]) / eps
                    a += ju * ju
                    b += ju * jv
                    d += jv * jv
                    gu += ju * current[j]
                    gv += jv * current[j]
                a_d = a * (1.0 + damping)
                d_d = d * (1.0 + damping)
                det = max(a_d * d_d - b * b, 1e-30)
                du = min(max(-(d_d * gu - b * gv) / det, -max_step), max_step)
                dv = min(max(-(a_d * gv - b * gu) / det, -max_step), max_step)
                _moved(n, t1, t2, u + du, v + dv, probe)
                trial_cost = _residuals(obs, weight, p, probe, view, directions, knots, falloff,
                                        specular, alpha, roughness, white, fresnel_f0, diffuse,
                                        lobe, trial)
                if trial_cost < cost:
                    u += du
                    v += dv
                    cost = trial_cost
                    current[:] = trial
                    damping /= 3.0
                else:
                    damping *= 10.0
            _moved(n, t1, t2, u, v, probe)
            for k in range(3):
                normals[p, k] = probe[k]
