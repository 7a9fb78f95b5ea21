"""Compiled passes of the BRDF fit (private; the API is :mod:`colorps.brdf`).

One round of ``brdf._fit_at`` (alternating least squares at one alpha)
over the measurements of N pixels in m images and c bands, without the
(m, N, c) float64 temporaries numpy needs for each of its steps. The model of
measurement (image i, pixel p, band b), relative to the light's intensity, of
a pixel of albedo a_pb, is::

    model_ipb = a_pb sum_k basis_ipk falloff_k + t_pb lobe_ip specular_b

with t_pb = a_pb for a highlight tinted by the albedo, 1 for a white one
(``white``).

with ``basis`` the diffuse falloff's hat functions times the cosine of
incidence (K of them, the last one's coefficient fixed to 1; at most two
neighbouring hats are not zero, which the normal equations rely on) and ``lobe`` the
highlight lobe times the cosine. Each measurement has a base weight w (0: not
used) and a robust (Huber) factor r.

Arrays (float64, passed by name): ``obs`` and ``weight`` (m, N, c), ``robust``
(m, N, c) updated in place, ``basis`` (m, N, K), ``lobe`` (m, N), ``falloff``
(K,), ``specular`` (c,), ``albedo`` (N, c); ``white`` a bool.
"""

import numpy as np
from numba import njit, prange

#: Pixels per parallel chunk (each chunk sums its own normal equations).
CHUNK_PIXELS = 128


@njit(cache=True, inline="always")
def _diffuse(basis, falloff, i, p):
    total = 0.0
    for k in range(falloff.size):
        total += basis[i, p, k] * falloff[k]
    return total


@njit(cache=True, parallel=True)
def fit_albedo(obs, weight, robust, basis, lobe, falloff, specular, albedo, white):
    """albedo_pb = sum_i w r shape target / sum_i w r shape^2 (in place): shape
    the diffuse term plus, tinted, the highlight; target obs less a white one."""
    m, n, c = obs.shape
    chunks = (n + CHUNK_PIXELS - 1) // CHUNK_PIXELS
    for chunk in prange(chunks):
        first = chunk * CHUNK_PIXELS
        stop = min(first + CHUNK_PIXELS, n)
        num = np.zeros((stop - first, c))
        den = np.zeros((stop - first, c))
        for i in range(m):
            for p in range(first, stop):
                diffuse = _diffuse(basis, falloff, i, p)
                for b in range(c):
                    wr = weight[i, p, b] * robust[i, p, b]
                    highlight = lobe[i, p] * specular[b]
                    shape = diffuse if white else diffuse + highlight
                    target = obs[i, p, b] - highlight if white else obs[i, p, b]
                    num[p - first, b] += wr * shape * target
                    den[p - first, b] += wr * shape * shape
        for p in range(first, stop):
            for b in range(c):
                albedo[p, b] = num[p - first, b] / max(den[p - first, b], 1e-30)


@njit(cache=True, parallel=True)
def white_strength(obs, weight, robust, basis, lobe, falloff, specular):
    """For a white highlight, ``specular`` (in place; one value in every band: the
    lights' own colour) at its least squares with each pixel's albedo fitted
    alongside it (the albedo projected out, band by band):
    s = sum_pb (LO - DL DO / DD) / sum_pb (LL - DL^2 / DD), the sums over the
    pixel's images weighted by w r, of D the diffuse term, L the lobe and O the
    observation; at least 0. (Alternating with the albedo, the two trade off
    along a valley that took hundreds of rounds to cross.)"""
    m, n, c = obs.shape
    chunks = (n + CHUNK_PIXELS - 1) // CHUNK_PIXELS
    num = np.zeros((chunks, c))
    den = np.zeros((chunks, c))
    for chunk in prange(chunks):
        for p in range(chunk * CHUNK_PIXELS, min((chunk + 1) * CHUNK_PIXELS, n)):
            for b in range(c):
                dd = 0.0
                dl = 0.0
                do = 0.0
                ll = 0.0
                lo = 0.0
                for i in range(m):
                    wr = weight[i, p, b] * robust[i, p, b]
                    d = _diffuse(basis, falloff, i, p)
                    lobe_ip = lobe[i, p]
                    dd += wr * d * d
                    dl += wr * d * lobe_ip
                    do += wr * d * obs[i, p, b]
                    ll += wr * lobe_ip * lobe_ip
                    lo += wr * lobe_ip * obs[i, p, b]
                if dd > 1e-30:
                    num[chunk, b] += lo - dl * do / dd
                    den[chunk, b] += ll - dl * dl / dd
    total = den.sum()
    specular[:] = max(num.sum() / total, 0.0) if total > 1e-30 else 0.0


@njit(cache=True, parallel=True)
def relative_residuals(obs, weight, basis, lobe, falloff, specular, albedo, white, out):
    """out_ipb = (obs - model) sqrt(w): residuals relative to the pixel's scale."""
    m, n, c = obs.shape
    for i in prange(m):
        for p in range(n):
            diffuse = _diffuse(basis, falloff, i, p)
            for b in range(c):
                tint = 1.0 if white else albedo[p, b]
                model = albedo[p, b] * diffuse + tint * lobe[i, p] * specular[b]
                out[i, p, b] = (obs[i, p, b] - model) * np.sqrt(weight[i, p, b])


@njit(cache=True, parallel=True)
def huber_normal_equations(obs, weight, robust, basis, lobe, falloff, specular, albedo,
                           white, threshold, normal, right):
    """Huber factors, loss and the next fit's normal equations, in one pass.

    Sets ``robust`` to 1 where the relative residual is at most ``threshold``
    and threshold / |residual| beyond. Writes into ``normal`` ((K - 1 + c)^2)
    and ``right`` (K - 1 + c) the normal equations of the (falloff[:-1],
    specular) least squares given the albedo, weighted by w r (not yet
    divided by the total weight). Returns (summed Huber loss, total w r).
    """
    m, n, c = obs.shape
    k = falloff.size
    size = k - 1 + c
    chunks = (n + CHUNK_PIXELS - 1) // CHUNK_PIXELS
    normals = np.zeros((chunks, size, size))
    rights = np.zeros((chunks, size))
    losses = np.zeros(chunks)
    totals = np.zeros(chunks)
    for chunk in prange(chunks):
        first = chunk * CHUNK_PIXELS
        stop = min(first + CHUNK_PIXELS, n)
        part = normals[chunk]
        part_right = rights[chunk]
        loss = 0.0
        total = 0.0
        for i in range(m):
            for p in range(first, stop):
                # The hats overlap in pairs: basis[i, p] is zero but for
                # knots j and j + 1 (only j + 1 may be the fixed last knot).
                j0 = 0
                while j0 < k - 1 and basis[i, p, j0] == 0.0:
                    j0 += 1
                pair = min(j0 + 2, k - 1)
                diffuse = _diffuse(basis, falloff, i, p)
                l_ip = lobe[i, p]
                a2w_sum = 0.0
                awt_sum = 0.0
                for b in range(c):
                    w = weight[i, p, b]
                    if w == 0.0:
                        robust[i, p, b] = 1.0
                        continue
                    a = albedo[p, b]
                    tint = 1.0 if white else a  # the highlight's column: tint lobe
                    residual = abs((obs[i, p, b] - a * diffuse - tint * l_ip * specular[b])
                                   * np.sqrt(w))
                    if residual <= threshold:
                        r = 1.0
                        loss += residual * residual
                    else:
                        r = threshold / max(residual, 1e-30)
                        loss += 2.0 * threshold * residual - threshold * threshold
                    robust[i, p, b] = r
                    wr = w * r
                    total += wr
                    target = obs[i, p, b] - basis[i, p, k - 1] * a  # the fixed knot's out
                    a2w = a * a * wr
                    awt = a * wr * target
                    a2w_sum += a2w
                    awt_sum += awt
                    tl = tint * l_ip
                    part[k - 1 + b, k - 1 + b] += tl * tl * wr
                    part_right[k - 1 + b] += tl * wr * target
                    for j in range(j0, pair):
                        part[j, k - 1 + b] += basis[i, p, j] * a * tl * wr
                for j in range(j0, pair):
                    bj = basis[i, p, j]
                    part_right[j] += bj * awt_sum
                    for q in range(j, pair):
                        part[j, q] += bj * basis[i, p, q] * a2w_sum
        losses[chunk] = loss
        totals[chunk] = total
    normal[:, :] = 0.0
    right[:] = 0.0
    for chunk in range(chunks):
        normal += normals[chunk]
        right += rights[chunk]
    for j in range(size):  # mirror the upper triangle
        for q in range(j + 1, size):
            normal[q, j] = normal[j, q]
    return losses.sum(), totals.sum()
