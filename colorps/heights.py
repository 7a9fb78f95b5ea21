"""A normal-map file in, a height-map file out: the work behind ``colorps integrate``.

:func:`integrate_file` reads a normal map (``normal.exr`` of a reconstruction, or
any X, Y, Z map of unit normals), refuses one that is not, integrates it
(:func:`colorps.integrate`, weighted by a quality map when given) and writes the
height (and a mesh) as :func:`colorps.outputs.save_height` does.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from .errors import InputError
from .integrate import integrate, weights_from_quality
from .io import read_image, read_mask
from .outputs import check_height_targets, save_height

__all__ = ["MAX_NON_UNIT_FRACTION", "UNIT_TOLERANCE", "integrate_file"]

#: A normal map's finite pixels must be unit vectors within this (half-float
#: files store them to about 1e-3), all but MAX_NON_UNIT_FRACTION of them.
UNIT_TOLERANCE = 0.01
MAX_NON_UNIT_FRACTION = 0.01


def integrate_file(normals_path, out, *, mask_path=None, weights_path=None,
                   method: Literal["poisson", "dct"] = "poisson", mesh=None,
                   overwrite: bool = False):
    """Integrate a normal-map file into a height-map file (and optionally a mesh).

    Parameters
    ----------
    normals_path : str or Path
        Normal map with X, Y, Z in its first three channels (e.g. normal.exr).
    out : str or Path
        Height map to write (.exr).
    mask_path, weights_path : str or Path, optional
        Mask image; quality map of a reconstruction (see
        :func:`colorps.weights_from_quality`).
    method : {"poisson", "dct"}
    mesh : str or Path, optional
        Also write a mesh (.ply or .obj).

    Returns
    -------
    (H, W) ndarray
        The height map.
    """
    check_height_targets(out, mesh, overwrite=overwrite)  # fail before the work
    normals, _ = read_image(normals_path, "linear")
    if not 3 <= normals.shape[2] <= 4:  # (a fourth: alpha)
        raise InputError(f"{normals_path}: a normal map has 3 channels (X, Y, Z), got "
                         f"{normals.shape[2]}")
    normals = normals[..., :3]
    finite = np.isfinite(normals).all(axis=-1)
    if not finite.any():
        raise InputError(f"{normals_path}: holds no finite normal (all NaN or Inf)")
    length = np.linalg.norm(normals[finite], axis=-1)
    off = np.abs(length - 1.0) > UNIT_TOLERANCE
    if off.mean() > MAX_NON_UNIT_FRACTION:
        raise InputError(
            f"{normals_path}: is not a normal map: {off.mean():.0%} of its finite pixels "
            f"are not unit vectors (median length {np.median(length):.3g}); colorps writes "
            "normal.exr with X, Y, Z of unit length")
    mask = None if mask_path is None else read_mask(mask_path, normals.shape[:2])
    weights = None
    if weights_path is not None:
        quality, _ = read_image(weights_path, "linear")
        if quality.shape[:2] != normals.shape[:2]:
            raise InputError(f"{weights_path}: size differs from {normals_path}")
        weights = weights_from_quality(quality[..., 0])
    height = integrate(normals, mask, weights=weights, method=method)
    save_height(height, out, mesh=mesh, overwrite=overwrite)
    return height
