"""Normals to height: least-squares integration of the slope field.

Slopes from camera-space normals (x right, y up, z towards the camera), per pixel
step, orthographic::

    dz/dx   = -nx / nz          (one column to the right)
    dz/drow = +ny / nz          (one row down: rows go down, y goes up)

with nz clamped to at least ``min_nz`` (default 0.05, slopes up to about 20)
so nearly vertical normals cannot produce unbounded slopes.

The height z minimises the (weighted) sum over all pairs of 4-neighbouring
pixels inside the mask of (z_b - z_a - g_ab)^2, where g_ab is the mean of the two
pixels' slopes along the pair. Only pairs inside the mask contribute: the
boundary is *free* (no assumption about the height or slope outside), which is
the natural Neumann condition of this least-squares problem.

============  ==========================================================
quantity      unit / convention
============  ==========================================================
height        pixels (the same unit as x and y), larger = nearer the camera
offset        each connected part of the mask is integrated on its own and
              shifted to zero mean height: relative heights *between*
              separate parts are not observable from normals
outside       NaN
============  ==========================================================
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from .errors import InputError

__all__ = ["DEFAULT_TILE", "METHODS", "integrate", "slopes", "weights_from_quality"]

#: Names of the integration methods of :func:`integrate`.
METHODS = ("poisson", "dct")

# ---------------------------------------------------------------- tuning
#: Tiled integration (``integrate(..., tile=T)``): the coarse level has at most
#: COARSE_PIXELS pixels; each tile is solved with TILE_MARGIN extra pixels on
#: every side, whose outer ring is held to known heights (penalty
#: ANCHOR_WEIGHT times the mean pair weight).
COARSE_PIXELS = 2 ** 18
TILE_MARGIN = 48
#: Tile side of a tiled ``colorps reconstruct`` run's integration (pixels).
DEFAULT_TILE = 512
ANCHOR_WEIGHT = 1e3
#: (A second pass holding the rings to the first pass's heights, an overlapping
#: Schwarz step, left the difference to the untiled solve unchanged: it comes
#: from the coarse level's low frequencies.)


def slopes(normals, *, min_nz: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Height slopes (dz/dx, dz/drow) per pixel from camera-space normals.

    Parameters
    ----------
    normals : (H, W, 3) array_like
        Unit normals, x right, y up, z towards the camera.
    min_nz : float, optional
        Lower clamp of nz (grazing normals).

    Returns
    -------
    gx, grow : (H, W) ndarray of float64
    """
    n = np.asarray(normals)
    if n.ndim != 3 or n.shape[2] != 3:
        raise InputError(f"normals: expected shape (H, W, 3), got {n.shape}")
    # Component by component: no float64 copy of the whole map.
    nz = np.maximum(n[..., 2].astype(np.float64), min_nz)
    gx = n[..., 0].astype(np.float64)
    gx /= nz
    np.negative(gx, out=gx)
    grow = n[..., 1].astype(np.float64)
    grow /= nz
    return gx, grow


def weights_from_quality(quality, *, scale: float | None = None) -> np.ndarray:
    """Integration weights from a match-quality map: 1 / (1 + (q / scale)^2).

    Parameters
    ----------
    quality : (H, W) array_like
        Match distances (NaN = unsolved, weight 0).
    scale : float, optional
        Distance at which the weight halves; default 3 x the median distance.
    """
    q = np.asarray(quality, dtype=np.float64)
    finite = np.isfinite(q)
    if scale is None:
        median = np.median(q[finite]) if finite.any() else 0.0
        scale = 3.0 * median if median > 0 else 1.0
    w = 1.0 / (1.0 + (np.where(finite, q, 0.0) / scale) ** 2)
    return np.where(finite, w, 0.0).astype(np.float32)


def _edges(mask: np.ndarray):
    """Index pairs (a, b) of 4-neighbour pixels inside the mask, as flat indices."""
    h, w = mask.shape
    idx = np.arange(h * w).reshape(h, w)
    right = mask[:, :-1] & mask[:, 1:]
    down = mask[:-1, :] & mask[1:, :]
    return (idx[:, :-1][right], idx[:, 1:][right]), (idx[:-1, :][down], idx[1:, :][down])


def _validate(normals, mask, weights):
    n = np.asarray(normals)
    n = n if n.dtype in (np.float32, np.float64) else n.astype(np.float64)
    if n.ndim != 3 or n.shape[2] != 3:
        raise InputError(f"normals: expected shape (H, W, 3), got {n.shape}")
    finite = np.isfinite(n).all(axis=-1)
    if mask is None:
        mask = finite
    else:
        mask = np.asarray(mask)
        if mask.shape != n.shape[:2]:
            raise InputError(f"mask: shape {mask.shape} differs from the normals' "
                             f"{n.shape[:2]}")
        mask = mask.astype(bool) & finite
    if weights is not None:
        weights = np.asarray(weights)
        weights = weights if weights.dtype in (np.float32, np.float64) else \
            weights.astype(np.float64)
        if weights.shape != n.shape[:2]:
            raise InputError(f"weights: shape {weights.shape} differs from the normals' "
                             f"{n.shape[:2]}")
        if np.any(mask & ~((weights >= 0) & (weights < np.inf))):  # NaN fails both
            raise InputError("weights: must be finite and >= 0 inside the mask")
    return n, mask, weights


def integrate(normals, mask=None, *, weights=None,
              method: Literal["poisson", "dct"] = "poisson", min_nz: float = 0.05,
              tol: float = 1e-6, tile: int | None = None) -> np.ndarray:
    """Integrate a normal map into a height map (pixel units, orthographic).

    Parameters
    ----------
    normals : (H, W, 3) array_like
        Camera-space unit normals (x right, y up, z towards the camera). Pixels
        with NaN normals are outside the mask.
    mask : (H, W) array_like of bool, optional
        Pixels to integrate (default: every pixel with finite normals). Any
        shape: non-rectangular, with holes, several separate parts.
    weights : (H, W) array_like, optional
        Reliability per pixel (>= 0); a pair of neighbours counts with the
        smaller of its two weights. See :func:`weights_from_quality`.
    method : {"poisson", "dct"}, optional
        "poisson": masked weighted least squares, solved by conjugate
        gradients preconditioned with a geometric multigrid on the pixel grid
        (:mod:`colorps.multigrid`). "dct": the same
        least-squares solution computed with fast cosine transforms; needs a
        full rectangle (no mask holes) and no weights.
    min_nz : float, optional
        Lower clamp of nz when converting normals to slopes.
    tol : float, optional
        Relative residual tolerance of the iterative solver. In height units:
        on the 1 MP smiley scene 1e-6 (the default) leaves every height within
        1e-4 px of the converged solve; each factor 10 costs about one more
        CG step.
    tile : int, optional
        "poisson" only: integrate hierarchically, for images too large to
        solve at once. A coarse level (at most COARSE_PIXELS pixels, slopes
        averaged over blocks) is solved whole; then each tile x tile block is
        solved with TILE_MARGIN more pixels around it, whose outer ring is held
        to the upsampled coarse heights. Memory is that of one tile plus the
        coarse level; heights differ from the untiled solve by a small fraction
        of the relief (docs/benchmarks.md). None: one solve.

    Returns
    -------
    (H, W) ndarray of float64
        Height in pixels, NaN outside the mask; each connected part has zero
        mean height (the constant offset is not observable).

    Examples
    --------
    >>> import numpy as np
    >>> from colorps import integrate, synth
    >>> ball = synth.sphere_surface(101, 40)        # radius 40 px, centre (50, 50)
    >>> y, x = np.mgrid[0:101, 0:101]
    >>> cap = (x - 50) ** 2 + (y - 50) ** 2 < 32 ** 2  # up to 53 degrees of slope
    >>> z = integrate(ball.normals, cap)
    >>> truth = np.where(cap, ball.height, np.nan)
    >>> bool(np.nanmax(np.abs(z - (truth - np.nanmean(truth)))) < 0.01)  # pixels
    True
    """
    if method not in METHODS:
        raise InputError(f"method: expected one of {METHODS}, got {method!r}")
    if tile is not None and (isinstance(tile, bool) or not isinstance(tile, (int, np.integer))
                             or tile < 16):
        raise InputError(f"tile: expected a tile side of at least 16 pixels, got {tile!r}")
    if tile is not None and method != "poisson":
        raise InputError("tile: only method 'poisson' integrates in tiles")
    normals, mask, weights = _validate(normals, mask, weights)
    h, w = mask.shape
    height = np.full((h, w), np.nan)
    if not mask.any():
        return height
    if tile is not None and max(h, w) > tile:
        height = _integrate_tiled(normals, mask, weights, tol, int(tile), min_nz)
        return _zero_mean_parts(height, mask)
    if method == "dct":
        if not mask.all() or weights is not None:
            raise InputError("method 'dct' needs a full rectangle (every normal finite, "
                             "no mask) and no weights; use method='poisson'")
        height[:] = _integrate_dct(*slopes(normals, min_nz=min_nz))
    else:  # the slopes are the solver's alone: it frees them once it has its equations
        height[mask] = _integrate_poisson(*_masked_slopes(normals, mask, min_nz), mask,
                                          weights, tol)
    return _zero_mean_parts(height, mask)


def _masked_slopes(normals: np.ndarray, mask: np.ndarray, min_nz: float):
    """:func:`slopes`, 0 outside the mask (as of a normal (0, 0, 0) there)."""
    gx, grow = slopes(normals, min_nz=min_nz)
    gx[~mask] = 0.0
    grow[~mask] = 0.0
    return gx, grow


def _integrate_dct(gx: np.ndarray, grow: np.ndarray) -> np.ndarray:
    """Unweighted least squares on a full rectangle, diagonalised by DCT-II."""
    from scipy.fft import dctn, idctn

    h, w = gx.shape
    gh = 0.5 * (gx[:, :-1] + gx[:, 1:])
    gv = 0.5 * (grow[:-1, :] + grow[1:, :])
    rhs = np.zeros((h, w))  # A^T g: divergence of the edge slopes
    rhs[:, :-1] -= gh
    rhs[:, 1:] += gh
    rhs[:-1, :] -= gv
    rhs[1:, :] += gv
    eig = (2 - 2 * np.cos(np.pi * np.arange(h) / h))[:, None] + \
          (2 - 2 * np.cos(np.pi * np.arange(w) / w))[None, :]
    coeffs = dctn(rhs, type=2, norm="ortho")
    eig[0, 0] = 1.0
    coeffs /= eig
    coeffs[0, 0] = 0.0
    return idctn(coeffs, type=2, norm="ortho")


def _integrate_poisson(gx, grow, mask, weights, tol, anchor=None) -> np.ndarray:
    """Weighted masked least squares: the normal equations on the pixel grid,
    solved by multigrid-preconditioned CG (:mod:`colorps.multigrid`).

    ``anchor``, optional (H, W) heights (NaN: free): pixels where it is finite
    are held to it (a penalty ANCHOR_WEIGHT times the mean pair weight).
    Returns the heights of the mask pixels, in row-major order.
    """
    from .multigrid import solve

    system, rhs = _grid_equations(gx, grow, mask, weights, anchor)
    del gx, grow  # freed for the solve where the caller holds no reference
    heights, _ = solve(system, rhs, tol=tol)
    return heights[mask]


def _grid_equations(gx, grow, mask, weights, anchor):
    """The normal equations of :func:`_normal_equations` as a
    :class:`~colorps.multigrid.GridSystem` and its right-hand side (H, W)."""
    from ._mg_kernels import pair_equations
    from .multigrid import GridSystem

    h, w = mask.shape
    weight = np.ones((h, w)) if weights is None else np.asarray(weights, dtype=np.float64)
    east, south, rhs, degree = (np.empty((h, w)) for _ in range(4))
    pair_equations(np.ascontiguousarray(gx, dtype=np.float64),
                   np.ascontiguousarray(grow, dtype=np.float64),
                   np.ascontiguousarray(mask, dtype=np.bool_), np.ascontiguousarray(weight),
                   east, south, rhs, degree)
    pairs = int((mask[:, :-1] & mask[:, 1:]).sum() + (mask[:-1] & mask[1:]).sum())
    mean_weight = (east.sum() + south.sum()) / pairs if pairs else 0.0
    # As in _normal_equations: a tiny shift makes each part's constant unique.
    diag = degree
    diag += 1e-9 * max(mean_weight, 1e-12)
    if anchor is not None:
        held = np.where(mask, anchor, np.nan)
        pull = np.where(np.isfinite(held), ANCHOR_WEIGHT * max(mean_weight, 1e-12), 0.0)
        diag += pull
        rhs += pull * np.nan_to_num(held)
    diag[~mask] = 1.0
    rhs[~mask] = 0.0
    return GridSystem(east, south, diag, mask.copy()), rhs


def _integrate_poisson_amg(gx, grow, mask, weights, tol, anchor=None) -> np.ndarray:
    """:func:`_integrate_poisson` through pyamg's classical AMG (Ruge-Stuben) and
    CG on the sparse normal equations: the reference the tests hold the
    multigrid solver to."""
    import pyamg

    lap, rhs = _normal_equations(gx, grow, mask, weights, anchor)
    if lap is None:
        return np.zeros(rhs.size)
    # (Built in a function of its own: its index and edge arrays are freed
    # before the AMG setup, the peak of the integration's memory.)
    solver = pyamg.ruge_stuben_solver(lap, max_coarse=500)  # classical AMG: fast setup
    return solver.solve(rhs, tol=tol, accel="cg", maxiter=400)


def _normal_equations(gx, grow, mask, weights, anchor):
    """L = A^T W A (a weighted graph Laplacian, CSR with int32 indices) and
    rhs = A^T W g over the mask pixels (row-major); L is None without any pair."""
    import scipy.sparse as sp

    inside = mask.ravel()
    n = int(inside.sum())
    index = np.int32 if n < 2 ** 31 else np.int64
    compact = np.full(mask.size, -1, dtype=index)
    compact[inside] = np.arange(n, dtype=index)
    (ha, hb), (va, vb) = _edges(mask)
    fx, frow = gx.ravel(), grow.ravel()
    target = np.concatenate([0.5 * (fx[ha] + fx[hb]), 0.5 * (frow[va] + frow[vb])])
    if weights is None:
        wt = np.ones(target.size)
    else:
        flat = weights.ravel()
        wt = np.minimum(flat[np.concatenate([ha, va])], flat[np.concatenate([hb, vb])])
    a = compact[np.concatenate([ha, va])]
    b = compact[np.concatenate([hb, vb])]
    del ha, hb, va, vb, compact
    if a.size == 0:
        return None, np.zeros(n)
    # A tiny diagonal shift makes each part's constant unique (removed
    # afterwards) and keeps pixels without any weighted neighbour at 0.
    degree = np.bincount(a, wt, n) + np.bincount(b, wt, n)
    rhs = np.bincount(b, wt * target, n) - np.bincount(a, wt * target, n)
    diag = degree + 1e-9 * max(wt.mean(), 1e-12)
    if anchor is not None:
        held = anchor.ravel()[inside]
        pull = np.where(np.isfinite(held), ANCHOR_WEIGHT * max(wt.mean(), 1e-12), 0.0)
        diag = diag + pull
        rhs = rhs + pull * np.nan_to_num(held)
    diagonal = np.arange(n, dtype=index)
    lap = sp.coo_matrix((np.concatenate([-wt, -wt, diag]),
                         (np.concatenate([a, b, diagonal]), np.concatenate([b, a, diagonal]))),
                        shape=(n, n)).tocsr()
    return lap, rhs


def _integrate_tiled(normals, mask, weights, tol, tile, min_nz) -> np.ndarray:
    """Hierarchical integration: a coarse solve, then tiles anchored to it."""
    from scipy import ndimage

    h, w = mask.shape
    factor = max(2, int(np.ceil(np.sqrt(mask.sum() / COARSE_PIXELS))))
    hc, wc = -(-h // factor), -(-w // factor)
    # Block sums of weight, weighted slopes and mask pixels, a band of blocks at a time.
    sums = np.zeros((3, hc, wc))
    count = np.zeros((hc, wc))
    for r in range(hc):
        rows = slice(r * factor, min((r + 1) * factor, h))
        inside = mask[rows]
        weight = inside * (1.0 if weights is None else weights[rows])
        gx, grow = slopes(np.where(inside[..., None], normals[rows], 0.0), min_nz=min_nz)
        pad = wc * factor - w
        for k, value in enumerate((weight, weight * gx, weight * grow)):
            sums[k, r] = np.pad(value, ((0, 0), (0, pad))).reshape(
                value.shape[0], wc, factor).sum(axis=(0, 2))
        count[r] = np.pad(inside, ((0, 0), (0, pad))).reshape(
            inside.shape[0], wc, factor).sum(axis=(0, 2))
    coarse_mask = (count > 0) & (sums[0] > 0)
    mean_weight = np.divide(sums[0], count, out=np.zeros_like(count), where=count > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        # Slopes per coarse step: factor fine pixels.
        cgx = np.where(coarse_mask, factor * sums[1] / sums[0], 0.0)
        cgrow = np.where(coarse_mask, factor * sums[2] / sums[0], 0.0)
    coarse = np.full((hc, wc), np.nan)
    coarse[coarse_mask] = _integrate_poisson(cgx, cgrow, coarse_mask,
                                             None if weights is None else mean_weight, tol)
    filled, known_coarse = np.nan_to_num(coarse), coarse_mask.astype(float)

    def upsampled(ys, xs):
        """Coarse heights at fine pixels (ys, xs); block centres are at
        factor i + (factor - 1) / 2."""
        at = [(ys - (factor - 1) / 2.0) / factor, (xs - (factor - 1) / 2.0) / factor]
        value = ndimage.map_coordinates(filled, at, order=1, mode="nearest")
        known = ndimage.map_coordinates(known_coarse, at, order=1, mode="nearest")
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(known > 0.25, value / known, np.nan)

    height = np.full((h, w), np.nan)
    for y0 in range(0, h, tile):
        for x0 in range(0, w, tile):
            y1, x1 = min(y0 + tile, h), min(x0 + tile, w)
            if not mask[y0:y1, x0:x1].any():
                continue
            a0, b0 = max(0, y0 - TILE_MARGIN), max(0, x0 - TILE_MARGIN)
            a1, b1 = min(h, y1 + TILE_MARGIN), min(w, x1 + TILE_MARGIN)
            inside = mask[a0:a1, b0:b1]
            ring = np.zeros(inside.shape, dtype=bool)
            if a0 > 0:
                ring[0] = True
            if a1 < h:
                ring[-1] = True
            if b0 > 0:
                ring[:, 0] = True
            if b1 < w:
                ring[:, -1] = True
            anchor = np.full(inside.shape, np.nan)
            ring_y, ring_x = np.nonzero(ring)
            anchor[ring_y, ring_x] = upsampled(ring_y + a0, ring_x + b0)
            gx, grow = slopes(np.where(inside[..., None], normals[a0:a1, b0:b1], 0.0),
                              min_nz=min_nz)
            solved = np.full(inside.shape, np.nan)
            solved[inside] = _integrate_poisson(
                gx, grow, inside, None if weights is None else weights[a0:a1, b0:b1], tol,
                anchor)
            height[y0:y1, x0:x1] = solved[y0 - a0:y1 - a0, x0 - b0:x1 - b0]
    return height


def _zero_mean_parts(height: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Shift each 4-connected part of the mask to zero mean height (in place, a
    band of rows at a time: no image-sized temporary)."""
    from scipy import ndimage

    labels, count = ndimage.label(mask)
    if count:
        offsets = np.r_[0.0, ndimage.mean(height, labels, index=np.arange(1, count + 1))]
        for start in range(0, height.shape[0], 256):
            rows = slice(start, start + 256)
            height[rows] -= offsets[labels[rows]]
    height[~mask] = np.nan
    return height
