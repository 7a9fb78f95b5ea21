"""A geometric multigrid solver for the height map's masked Poisson system.

The integration's normal equations (:mod:`colorps.integrate`) are a weighted
graph Laplacian on the pixel grid: each pair of 4-neighbours inside the mask
couples its two heights with the pair's weight. This module solves them with
conjugate gradients preconditioned by one multigrid V-cycle:

* levels of 2 x 2 aggregation: a coarse pixel stands for the inside pixels of
  a block, and its operator is the fine one's Galerkin product P^T L P (pairs
  between blocks add up), so masks of any shape, holes and separate parts
  coarsen without special cases;
* red-black Gauss-Seidel smoothing (SMOOTHING sweeps before, the same in the
  reverse colour order after: the cycle is symmetric, as CG needs), rows in
  parallel (numba, :mod:`colorps._mg_kernels`);
* the coarse correction scaled by OVERCORRECTION (aggregation's constant
  prolongation under-corrects smooth errors; a constant factor keeps the
  preconditioner symmetric);
* a dense solve on the coarsest level (at most COARSEST_PIXELS pixels).

It replaced pyamg's classical AMG as the default: same heights within 1e-4 px
(tests), several times faster, and parallel (docs/benchmarks.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import _mg_kernels

__all__ = ["COARSEST_PIXELS", "OVERCORRECTION", "SMOOTHING", "GridSystem", "solve"]

# ---------------------------------------------------------------- tuning
#: Gauss-Seidel sweeps (a red and a black half-sweep each) before and after the
#: coarse correction.
SMOOTHING = 2
#: Scale of the coarse correction.
OVERCORRECTION = 2.0
#: Pixels of the coarsest level (solved directly).
COARSEST_PIXELS = 400


@dataclass(frozen=True)
class GridSystem:
    """A weighted 5-point Laplacian on an (h, w) grid (see :mod:`colorps._mg_kernels`).

    Attributes
    ----------
    east, south : (h, w) ndarray of float64
        Weights of the pairs (y, x)-(y, x + 1) and (y, x)-(y + 1, x); 0 where
        there is no such pair.
    diag : (h, w) ndarray of float64
        Diagonal: the pixel's pair weights and any shift; 1 outside.
    inside : (h, w) ndarray of bool
        The unknowns.
    """

    east: np.ndarray
    south: np.ndarray
    diag: np.ndarray
    inside: np.ndarray

    def coarser(self) -> GridSystem:
        ch, cw = -(-self.diag.shape[0] // 2), -(-self.diag.shape[1] // 2)
        east, south, diag = (np.zeros((ch, cw)) for _ in range(3))
        inside = np.zeros((ch, cw), dtype=np.bool_)
        _mg_kernels.coarse_level(self.east, self.south, self.diag, self.inside, east, south,
                                 diag, inside)
        return GridSystem(east, south, diag, inside)

    def dense(self) -> np.ndarray:
        """The operator as a dense matrix over every pixel (row-major)."""
        h, w = self.diag.shape
        n = h * w
        matrix = np.diag(self.diag.ravel())
        index = np.arange(n).reshape(h, w)
        for weights, a, b in ((self.east[:, :-1], index[:, :-1], index[:, 1:]),
                              (self.south[:-1], index[:-1], index[1:])):
            matrix[a.ravel(), b.ravel()] -= weights.ravel()
            matrix[b.ravel(), a.ravel()] -= weights.ravel()
        return matrix


def solve(system: GridSystem, rhs: np.ndarray, *, tol: float = 1e-6, maxiter: int = 400
          ) -> tuple[np.ndarray, int]:
    """Solve L u = rhs by multigrid-preconditioned conjugate gradients.

    Parameters
    ----------
    system : GridSystem
        The operator (symmetric positive definite on the inside pixels).
    rhs : (h, w) ndarray of float64
        0 outside.
    tol : float, optional
        Stop when |rhs - L u| <= tol |rhs|.
    maxiter : int, optional
        At most this many CG steps.

    Returns
    -------
    (u, iterations)
        u is 0 outside.
    """
    levels = [system]
    while levels[-1].diag.size > COARSEST_PIXELS and min(levels[-1].diag.shape) > 1:
        levels.append(levels[-1].coarser())
    coarsest = np.linalg.pinv(levels[-1].dense(), hermitian=True)
    r = np.where(system.inside, rhs, 0.0)  # the residual of u = 0
    u = np.zeros_like(r)
    norm = np.linalg.norm(r)
    if norm == 0.0:
        return u, 0
    # Each level's arrays, made once (fresh ones at every cycle cost a 4 MP solve
    # 0.1-0.5 s of first touches): its approximation, its residual, and its
    # right-hand side (restricted from the finer level's residual).
    work = [(np.empty(level.diag.shape), np.empty(level.diag.shape),
             np.empty(level.diag.shape)) for level in levels]
    z = _v_cycle(levels, 0, r, coarsest, work)
    p = z.copy()
    rz = float(np.vdot(r, z))
    lp = np.empty_like(r)
    for iteration in range(1, maxiter + 1):
        _mg_kernels.apply(p, system.east, system.south, system.diag, lp)
        alpha = rz / float(np.vdot(p, lp))
        # In place (a 4 MP array is 32 MiB): lp is free once r has its step.
        r -= np.multiply(alpha, lp, out=lp)
        u += np.multiply(alpha, p, out=lp)
        if np.linalg.norm(r) <= tol * norm:
            return u, iteration
        z = _v_cycle(levels, 0, r, coarsest, work)  # (in work[0]: used before the next)
        rz, previous = float(np.vdot(r, z)), rz
        p *= rz / previous
        p += z
    return u, maxiter


def _v_cycle(levels: list[GridSystem], k: int, rhs: np.ndarray, coarsest: np.ndarray,
             work: list) -> np.ndarray:
    """One symmetric V-cycle from a zero guess: an approximation of L_k^-1 rhs,
    in ``work[k]``'s first array (each level's three work arrays)."""
    level = levels[k]
    u, residual, _ = work[k]
    if k == len(levels) - 1:
        np.multiply((coarsest @ rhs.ravel()).reshape(rhs.shape), level.inside, out=u)
        return u
    u.fill(0.0)
    for _ in range(SMOOTHING):
        for colour in (0, 1):
            _mg_kernels.gauss_seidel(u, rhs, level.east, level.south, level.diag, colour)
    _mg_kernels.residual(u, rhs, level.east, level.south, level.diag, residual)
    coarse = work[k + 1][2]
    _mg_kernels.restrict(residual, level.inside, coarse)
    correction = _v_cycle(levels, k + 1, coarse, coarsest, work)
    _mg_kernels.prolong_add(correction, OVERCORRECTION, level.inside, u)
    for _ in range(SMOOTHING):
        for colour in (1, 0):
            _mg_kernels.gauss_seidel(u, rhs, level.east, level.south, level.diag, colour)
    return u
