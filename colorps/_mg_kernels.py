"""numba kernels of the multigrid height solver (see colorps.multigrid).

A level is a weighted 5-point graph Laplacian on an (h, w) grid, given by name:
``east[y, x]`` the weight of the pair (y, x)-(y, x + 1), ``south[y, x]`` that of
(y, x)-(y + 1, x) (0 where a pixel has no such neighbour, or it is outside the
mask), ``diag[y, x]`` the diagonal (1 outside the mask, where nothing couples),
and ``inside[y, x]`` whether the pixel is an unknown. A coarse pixel is the
aggregate of the inside pixels of a 2 x 2 block (P copies its value to them). Rows run in parallel; pixels are visited in red-black order, so a
sweep is the same however the rows are shared out.
"""

from __future__ import annotations

from numba import njit, prange


@njit(cache=True, parallel=True)
def pair_equations(gx, grow, mask, weight, east, south, rhs, degree):
    """The finest level of the height's normal equations (:mod:`colorps.integrate`):
    each pair of 4-neighbours inside ``mask`` weighted by the lesser of their
    ``weight``, its mean slope (``gx`` along x, ``grow`` along the rows) moved
    into ``rhs``, and each pixel's summed pair weights into ``degree``; 0
    elsewhere (every output is written)."""
    h, w = mask.shape
    for y in prange(h):
        for x in range(w):
            e = 0.0
            if x + 1 < w and mask[y, x] and mask[y, x + 1]:
                e = min(weight[y, x], weight[y, x + 1])
            s = 0.0
            if y + 1 < h and mask[y, x] and mask[y + 1, x]:
                s = min(weight[y, x], weight[y + 1, x])
            east[y, x] = e
            south[y, x] = s
    for y in prange(h):
        for x in range(w):
            total = 0.0
            d = east[y, x] + south[y, x]
            if x > 0:
                total += east[y, x - 1] * 0.5 * (gx[y, x - 1] + gx[y, x])
                d += east[y, x - 1]
            if x + 1 < w:
                total -= east[y, x] * 0.5 * (gx[y, x] + gx[y, x + 1])
            if y > 0:
                total += south[y - 1, x] * 0.5 * (grow[y - 1, x] + grow[y, x])
                d += south[y - 1, x]
            if y + 1 < h:
                total -= south[y, x] * 0.5 * (grow[y, x] + grow[y + 1, x])
            rhs[y, x] = total
            degree[y, x] = d


@njit(cache=True, inline="always")
def _neighbours(u, east, south, y, x, h, w):
    """Sum of the weighted neighbour values of pixel (y, x)."""
    total = 0.0
    if x + 1 < w:
        total += east[y, x] * u[y, x + 1]
    if x > 0:
        total += east[y, x - 1] * u[y, x - 1]
    if y + 1 < h:
        total += south[y, x] * u[y + 1, x]
    if y > 0:
        total += south[y - 1, x] * u[y - 1, x]
    return total


@njit(cache=True, parallel=True)
def apply(u, east, south, diag, out):
    """out = L u."""
    h, w = u.shape
    for y in prange(h):
        for x in range(w):
            out[y, x] = diag[y, x] * u[y, x] - _neighbours(u, east, south, y, x, h, w)


@njit(cache=True, parallel=True)
def residual(u, rhs, east, south, diag, out):
    """out = rhs - L u."""
    h, w = u.shape
    for y in prange(h):
        for x in range(w):
            out[y, x] = rhs[y, x] - diag[y, x] * u[y, x] + _neighbours(u, east, south, y, x,
                                                                       h, w)


@njit(cache=True, parallel=True)
def gauss_seidel(u, rhs, east, south, diag, colour):
    """One Gauss-Seidel half-sweep over the pixels with (y + x) % 2 == colour."""
    h, w = u.shape
    for y in prange(h):
        for x in range((y + colour) % 2, w, 2):
            u[y, x] = (rhs[y, x] + _neighbours(u, east, south, y, x, h, w)) / diag[y, x]


@njit(cache=True, parallel=True)
def coarse_level(east, south, diag, inside, c_east, c_south, c_diag, c_inside):
    """The Galerkin operator P^T L P of 2 x 2 aggregation: a pair of coarse
    pixels is weighted by the fine pairs between their blocks, the diagonal is
    the block's inside diagonals less twice the pairs inside it (1 for a block
    with no inside pixel)."""
    h, w = diag.shape
    ch, cw = c_diag.shape
    for cy in prange(ch):
        for cx in range(cw):
            d = 0.0
            e = 0.0
            s = 0.0
            any_inside = False
            for y in range(2 * cy, min(2 * cy + 2, h)):
                for x in range(2 * cx, min(2 * cx + 2, w)):
                    if inside[y, x]:
                        d += diag[y, x]
                        any_inside = True
                    if x + 1 < w:
                        if x == 2 * cx:
                            d -= 2.0 * east[y, x]  # inside the block
                        else:
                            e += east[y, x]  # to the next block
                    if y + 1 < h:
                        if y == 2 * cy:
                            d -= 2.0 * south[y, x]
                        else:
                            s += south[y, x]
            c_inside[cy, cx] = any_inside
            c_diag[cy, cx] = d if any_inside else 1.0
            c_east[cy, cx] = e if cx + 1 < cw else 0.0
            c_south[cy, cx] = s if cy + 1 < ch else 0.0


@njit(cache=True, parallel=True)
def restrict(fine, inside, coarse):
    """coarse = P^T fine: sums over the blocks' inside pixels."""
    h, w = fine.shape
    ch, cw = coarse.shape
    for cy in prange(ch):
        for cx in range(cw):
            total = 0.0
            for y in range(2 * cy, min(2 * cy + 2, h)):
                for x in range(2 * cx, min(2 * cx + 2, w)):
                    if inside[y, x]:
                        total += fine[y, x]
            coarse[cy, cx] = total


@njit(cache=True, parallel=True)
def prolong_add(coarse, scale, inside, fine):
    """fine += scale * P coarse, at the inside pixels."""
    h, w = fine.shape
    for y in prange(h):
        for x in range(w):
            if inside[y, x]:
                fine[y, x] += scale * coarse[y // 2, x // 2]
