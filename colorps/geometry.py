"""Normals: the sphere's normal field and the angle between two normal maps.

Conventions: pixel (x, y) = (column, row), pixel centres at integers; camera
space x right, y up, z towards the camera; orthographic view.
"""

from __future__ import annotations

import numpy as np

__all__ = ["angular_error", "sphere_normals"]


def sphere_normals(shape: tuple[int, int], cx: float, cy: float,
                   radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Normals of a sphere seen orthographically, and its unclipped disk distance.

    Parameters
    ----------
    shape : (H, W)
        Image size in pixels.
    cx, cy, radius : float
        Silhouette centre and radius, pixels.

    Returns
    -------
    normals : (H, W, 3) ndarray of float64
        n = ((x - cx) / r, -(y - cy) / r, sqrt(1 - nx^2 - ny^2)); nz is 0
        outside the disk (where the normal is meaningless).
    rho : (H, W) ndarray of float64
        Distance from the centre in radii (1 on the silhouette).

    Examples
    --------
    >>> from colorps.geometry import sphere_normals
    >>> n, rho = sphere_normals((5, 5), 2, 2, 2)
    >>> n[2, 2].tolist(), n[0, 2].tolist(), float(rho[2, 0])
    ([0.0, -0.0, 1.0], [0.0, 1.0, 0.0], 1.0)
    """
    h, w = shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    nx = (x - cx) / radius
    ny = -(y - cy) / radius
    nz = np.sqrt(np.clip(1.0 - nx * nx - ny * ny, 0.0, None))
    return np.stack([nx, ny, nz], axis=-1), np.hypot(nx, ny)


def angular_error(a, b) -> np.ndarray:
    """Angle between unit normals, in degrees.

    Parameters
    ----------
    a, b : (..., 3) array_like
        Unit vectors (broadcast against each other).

    Returns
    -------
    (...) ndarray of float64
        Degrees in [0, 180]; NaN where either input is NaN.

    Examples
    --------
    >>> from colorps.geometry import angular_error
    >>> float(angular_error([1, 0, 0], [0, 0, 1]))
    90.0
    """
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    cos = np.clip((a * b).sum(axis=-1), -1.0, 1.0)
    return np.degrees(np.arccos(cos))
