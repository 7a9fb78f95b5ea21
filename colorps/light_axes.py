"""Does the normal map say that one axis of the light file is mirrored?

A light file whose y axis points down (image rows) instead of up, or whose x
axis points left, gives normals mirrored the same way: the shading fits them
exactly, so the lights check and the match residuals see nothing. The surface
does: the normals of a height field z(x, y) have no curl (z_xy = z_yx), while
their mirror image in x or in y has a curl of 2 z_xy wherever the surface bends
in x and y together (a sphere, a face; not a plane or a cylinder along an axis).
:func:`check_axes` compares the median |curl| of the slopes of the solved
normals with that of their mirror image: far larger says the light file's axes
are mirrored. Mirrored in both x and y (turned half a turn) the normals are those
of the surface turned inside out, as integrable as the truth: that is the
convex-concave ambiguity of photometric stereo, which no check on the normals
can see.
"""

from __future__ import annotations

import warnings

import numpy as np

from .errors import LightAxesWarning

__all__ = ["MIN_CURL_PIXELS", "MIRROR_RATIO", "check_axes", "curl_medians"]

#: The solved normals' median |curl| must exceed their mirror image's by this
#: factor for the light file to be called mirrored. DiLiGenT Ball: 0.0029
#: against 0.0114 as given, 0.0114 against 0.0029 with y negated in its light
#: file; Mitsuba's pots 0.55-0.6 times their mirror's; noise alone gives 1.
MIRROR_RATIO = 2.0
#: Pixels whose four neighbours are solved needed for a verdict.
MIN_CURL_PIXELS = 500
#: Normals closer than this to the image plane (|n_z|) give no slope.
MIN_NZ = 0.05


def curl_medians(normals: np.ndarray, solved: np.ndarray) -> tuple[float, float, int]:
    """Median |curl| of the slopes of solved normals and of their mirror image.

    Parameters
    ----------
    normals : (H, W, 3) ndarray
        Unit normals (x right, y up, z towards the camera); NaN where unsolved.
    solved : (H, W) ndarray of bool

    Returns
    -------
    (float, float, int)
        The median |dp/drow + dq/dcol| of the slopes p = dz/dx = -n_x / n_z and
        q = dz/dy = -n_y / n_z (central differences, per pixel squared), the same
        for the normals mirrored in y (n_y negated; in x it is the same number),
        and the pixels counted (NaN, NaN, 0 when none).
    """
    normals = np.asarray(normals, dtype=np.float64)
    usable = np.asarray(solved, bool) & np.isfinite(normals).all(axis=-1) & \
        (normals[..., 2] > MIN_NZ)
    nz = np.where(usable, normals[..., 2], np.nan)
    p, q = -normals[..., 0] / nz, -normals[..., 1] / nz
    dp_drow = (p[2:, 1:-1] - p[:-2, 1:-1]) / 2.0
    dq_dcol = (q[1:-1, 2:] - q[1:-1, :-2]) / 2.0
    inside = np.isfinite(dp_drow) & np.isfinite(dq_dcol)
    if not inside.any():
        return float("nan"), float("nan"), 0
    # z_col = p and z_row = -q (rows go down): curl = d(z_col)/drow - d(z_row)/dcol.
    as_solved = np.median(np.abs(dp_drow + dq_dcol)[inside])
    mirrored = np.median(np.abs(dp_drow - dq_dcol)[inside])
    return float(as_solved), float(mirrored), int(inside.sum())


def check_axes(normals: np.ndarray, solved: np.ndarray, light_file) -> dict:
    """report.json's record of :func:`curl_medians`, with a
    :class:`~colorps.errors.LightAxesWarning` naming ``light_file`` when the
    solved normals are MIRROR_RATIO times less integrable than their mirror."""
    as_solved, mirrored, pixels = curl_medians(normals, solved)
    flagged = pixels >= MIN_CURL_PIXELS and as_solved > MIRROR_RATIO * mirrored
    if flagged:
        warnings.warn(
            f"{light_file}: one axis of the lights looks mirrored: the normals solved "
            f"under them are {as_solved / mirrored:.1f} times less integrable than their "
            "mirror image (median curl of their slopes "
            f"{as_solved:.3g} against {mirrored:.3g}). colorps's axes are x right, y up, "
            "z towards the camera; a file written with image rows for y (y down) needs "
            "its y values negated", LightAxesWarning, stacklevel=2)
    return dict(curl_median=as_solved, mirrored_curl_median=mirrored, pixels=pixels,
                looks_mirrored=bool(flagged))
