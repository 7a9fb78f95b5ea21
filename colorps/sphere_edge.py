"""Where a photographed sphere's edge lies, along radii of a circle near it.

A lit sphere does not end in a step of constant height. Towards its rim the
surface turns away from the camera: under one light (l_r, l_z) a Lambertian
sphere of radius R shows l_r rho / R + l_z sqrt(1 - (rho / R)^2) at rho from its
centre, which falls as the square root of the distance to the edge. Blurred by
the lens and the pixels, the half-height of such a profile is not the edge: it
lay 0.3-0.8 px inside where the lights are near the view (the rim dim against
the middle) and up to 1.3 px outside in front of a lit backdrop, which put the
normals of a 113 px gauge path-traced by Mitsuba 3 0.19 degrees off (median).

So along each radius the brightest-of-all-images picture (sampled by a cubic
spline) is fitted by that rim over a level background, blurred by a Gaussian:
for each blur of EDGE_BLUR_PX and each edge position on a grid of EDGE_STEP_PX
within EDGE_SEARCH_PX of the circle, the four levels (the rim's step, its
linear and square-root terms, the background) by linear least squares; the
edge is the position of least misfit, refined by a parabola through its grid
neighbours. The brightest picture is, near each stretch of the rim, one
light's. On area-sampled renders of spheres of 20 to 100 px blurred by 0 to
2 px, lit near the view or across a dome, on a dark or a lit backdrop, the
edges lie within 0.15 px of the truth but in one case (a lit backdrop, a dome's
lights, 2 px of blur: 0.57, the half-height rule 0.68), against up to 0.8 px
(1.3) by the half-height rule; docs/benchmarks.md.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

__all__ = ["Edges", "edge_points"]

# ---------------------------------------------------------------- tuning
#: EDGE_RAYS radii sampled every EDGE_STEP_PX from EDGE_INNER_PX inside the
#: circle to EDGE_OUTER_PX outside; radii whose largest value is under
#: EDGE_MIN_LEVEL of the bright level (an unlit part of the rim) are left out.
EDGE_RAYS = 720
EDGE_STEP_PX = 0.05
EDGE_INNER_PX = 8.0
EDGE_OUTER_PX = 4.0
EDGE_MIN_LEVEL = 0.2
#: The edge is searched within EDGE_SEARCH_PX of the circle, under Gaussian
#: blurs of these standard deviations (pixels).
EDGE_SEARCH_PX = 3.0
EDGE_BLUR_PX = (0.25, 0.4, 0.6, 0.8, 1.0, 1.3, 1.6, 2.0, 2.5)
#: The ramp's shoulder, for :func:`colorps.gauge.rim_margin`: the outermost point
#: still at EDGE_SHOULDER of the largest value inside (the 10-90 % edge's 90 %).
EDGE_SHOULDER = 0.9


class Edges(NamedTuple):
    """The sphere's edge along each lit radius of a circle (1-D arrays, one per radius)."""

    angle: np.ndarray     # radians, from +x towards +y (rows)
    radius: np.ndarray    # the edge's distance from the circle's centre, px
    shoulder: np.ndarray  # the ramp's shoulder (EDGE_SHOULDER of the largest value), px
    outside: np.ndarray   # the value EDGE_OUTER_PX outside the circle over the largest


def edge_points(brightest: np.ndarray, circle: tuple[float, float, float],
                bright: float) -> Edges:
    """The sphere's edge along EDGE_RAYS radii of ``circle`` (see the module docstring).

    Parameters
    ----------
    brightest : (H, W) ndarray
        The brightest value of every pixel over the gauge's images.
    circle : (cx, cy, r)
        A circle near the sphere's edge (pixels; x = column, y = row).
    bright : float
        The picture's bright level (radii under EDGE_MIN_LEVEL of it are left out).

    Returns
    -------
    Edges
        Of the lit radii whose edge the rim model places within the search.
    """
    cx, cy, r = circle
    angle = np.linspace(0.0, 2 * np.pi, EDGE_RAYS, endpoint=False)
    along = np.arange(-EDGE_INNER_PX, EDGE_OUTER_PX + EDGE_STEP_PX / 2, EDGE_STEP_PX)
    profile = _profiles(brightest, cx + (r + along) * np.cos(angle)[:, None],
                        cy + (r + along) * np.sin(angle)[:, None])
    top = profile[:, along <= 0].max(axis=1)
    index = np.arange(along.size)
    shoulder = np.where(profile >= EDGE_SHOULDER * top[:, None], index, -1).max(axis=1)
    offset, falls = _fitted_edges(profile, along, r)
    lit = (top >= EDGE_MIN_LEVEL * bright) & np.isfinite(offset) & falls
    return Edges(angle[lit], r + offset[lit], r + along[shoulder[lit]],
                 profile[lit, -1] / top[lit])


def _profiles(picture: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """``picture`` at (xs, ys) by a cubic spline, fitted on the box they span
    (with a margin) rather than the whole frame."""
    from scipy.ndimage import map_coordinates

    h, w = picture.shape
    x0, y0 = max(0, int(np.floor(xs.min())) - 4), max(0, int(np.floor(ys.min())) - 4)
    x1, y1 = min(w, int(np.ceil(xs.max())) + 5), min(h, int(np.ceil(ys.max())) + 5)
    box = np.asarray(picture[y0:y1, x0:x1], dtype=np.float64)
    return map_coordinates(box, [ys - y0, xs - x0], order=3, mode="nearest")


def _fitted_edges(profile: np.ndarray, along: np.ndarray, radius: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Each (R, S) profile's edge, as an offset along ``along`` (NaN: the least
    misfit at the search's end), and whether the fitted rim falls outwards there
    (1 px inside the edge above the background); ``radius``: the sphere's,
    about (px)."""
    shifts = np.arange(-EDGE_SEARCH_PX, EDGE_SEARCH_PX + EDGE_STEP_PX / 2, EDGE_STEP_PX)
    power = np.einsum("rs,rs->r", profile, profile)
    misfit = np.full((shifts.size, len(profile)), np.inf)
    fall = np.zeros((shifts.size, len(profile)))  # the rim 1 px in over the background
    inward = 1.0 / max(radius, 1.0)
    at_one_px = np.array([1.0, inward, np.sqrt(inward * (2.0 - inward)), -1.0])
    for sigma in EDGE_BLUR_PX:
        bases = _shifted_bases(along, shifts, sigma, radius)  # (shifts, 4, S)
        rhs = (bases.reshape(-1, along.size) @ profile.T).reshape(shifts.size, 4, -1)
        gram = bases @ bases.transpose(0, 2, 1) + 1e-12 * np.eye(4)
        levels = np.linalg.inv(gram) @ rhs  # (shifts, 4, R): one gram a shift
        cost = power[None, :] - (levels * rhs).sum(axis=1)
        better = cost < misfit
        misfit = np.where(better, cost, misfit)
        fall = np.where(better, np.einsum("b,kbr->kr", at_one_px, levels), fall)
    best = misfit.argmin(axis=0)
    rays = np.arange(len(profile))
    inner = (best > 0) & (best < shifts.size - 1)
    k = np.clip(best, 1, shifts.size - 2)
    a, b, c = misfit[k - 1, rays], misfit[k, rays], misfit[k + 1, rays]
    curve = a - 2 * b + c
    parabola = np.where(curve > 0, 0.5 * (a - c) / np.where(curve > 0, curve, 1.0), 0.0)
    offset = shifts[k] + np.clip(parabola, -1.0, 1.0) * EDGE_STEP_PX
    return np.where(inner, offset, np.nan), fall[best, rays] > 0


def _shifted_bases(along: np.ndarray, shifts: np.ndarray, sigma: float,
                   radius: float) -> np.ndarray:
    """(shifts, 4, S): a Lambertian sphere's rim lit by one light (its step at
    the edge, then rho / R and sqrt(1 - (rho / R)^2) of a sphere of ``radius``
    px, as (R - rho) / R and the root) and the background beyond an edge at
    each shift, blurred by a Gaussian of ``sigma`` px, sampled at ``along``."""
    half = int(np.ceil(4.0 * sigma / EDGE_STEP_PX))
    kernel = np.exp(-0.5 * (EDGE_STEP_PX * np.arange(-half, half + 1) / sigma) ** 2)
    kernel /= kernel.sum()
    # x = along - shift over every shift, and the kernel's reach on both sides;
    # blurred[i] is at x[i + half], and a shift's samples start at its own i.
    first = along[0] - shifts[-1] - half * EDGE_STEP_PX
    x = first + EDGE_STEP_PX * np.arange(along.size + shifts.size - 1 + 2 * half)
    inside = x < 0
    inward = np.where(inside, -x / max(radius, 1.0), 0.0).clip(0.0, 1.0)  # (R - rho) / R
    sharp = np.stack([inside * 1.0, inside * inward, np.sqrt(inward * (2.0 - inward)),
                      (~inside) * 1.0])
    blurred = np.stack([np.convolve(b, kernel, mode="valid") for b in sharp])
    start = np.rint((shifts[-1] - shifts) / EDGE_STEP_PX).astype(int)
    windows = np.lib.stride_tricks.sliding_window_view(blurred, along.size, axis=1)
    return np.ascontiguousarray(windows[:, start].transpose(1, 0, 2))
