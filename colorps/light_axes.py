"""Does the normal map say that the light file's x and y axes are wrong?

A light file whose y axis points down (image rows) instead of up, whose x and y
columns are swapped, or that is turned a quarter turn about the view axis gives
normals changed the same way: the shading fits them exactly, so the lights check
and the match residuals see nothing. The surface does: the normals of a height
field z(x, y) have no curl (z_xy = z_yx), while a mirror image or a quarter turn
of them, left at the same pixels, has one wherever the surface bends (a sphere,
a face; not a plane). :func:`check_axes` compares the median |curl| of the
slopes of the solved normals with that of each mistake undone (:data:`MISTAKES`):
far larger says which one the light file holds. Turned half a turn (both axes
negated) the normals are those of the surface turned inside out, as integrable as
the truth: that is the convex-concave ambiguity of photometric stereo, which no
check on the normals can see; for the same reason each mistake below is told
apart only up to half a turn.
"""

from __future__ import annotations

import warnings

import numpy as np

from .errors import LightAxesWarning

__all__ = ["MIN_CURL_PIXELS", "MIRROR_RATIO", "MISTAKES", "check_axes", "curl_medians"]

#: The light-file mistakes the normals show: each the 2 x 2 matrix that undoes it
#: on (n_x, n_y), and what to do about it.
MISTAKES = {
    "mirrored": (((1, 0), (0, -1)), "one axis looks mirrored: a file written with image "
                 "rows for y (y down) needs its y values negated (or its x values, if x "
                 "points left)"),
    "swapped": (((0, 1), (1, 0)), "x and y look swapped (or swapped and both negated): "
                "write x (right) first, then y (up)"),
    "turned": (((0, -1), (1, 0)), "the lights look turned a quarter turn about the view "
               "axis: x and y swapped and one of them negated"),
}
#: The solved normals' median |curl| must exceed that of a mistake undone by this
#: factor for the light file to be said to hold it. DiLiGenT Ball: 0.0029 as
#: given, 0.011-0.059 with each mistake undone; with its y values negated, its
#: columns swapped or turned, the undone mistake gives 0.0029 against 0.0114-0.059
#: for the normals as solved. Mitsuba's pots: 0.55-0.6 of the least undone one's;
#: noise alone gives 1.
MIRROR_RATIO = 2.0
#: Pixels whose four neighbours are solved needed for a verdict.
MIN_CURL_PIXELS = 500
#: The curl is measured on a lattice of at most this many pixels (every pixel
#: of DiLiGenT's masks; every 4th row and column of a 4 MP image).
CURL_PIXELS = 250_000
#: Normals closer than this to the image plane (|n_z|) give no slope.
MIN_NZ = 0.05


def curl_medians(normals: np.ndarray, solved: np.ndarray) -> tuple[dict[str, float], int]:
    """Median |curl| of the slopes of solved normals, as given and each mistake undone.

    Parameters
    ----------
    normals : (H, W, 3) ndarray
        Unit normals (x right, y up, z towards the camera); NaN where unsolved.
    solved : (H, W) ndarray of bool

    Returns
    -------
    (dict, int)
        For "as given" and each of :data:`MISTAKES`, the median of
        |dp/drow + dq/dcol| over the pixels whose four neighbours are solved, with
        the slopes p = dz/dx = -n_x / n_z and q = dz/dy = -n_y / n_z (central
        differences; per pixel), on a lattice of every ``step``-th row and column
        that keeps at most CURL_PIXELS of them; and the number of pixels counted
        (the medians NaN when none).
    """
    usable = np.asarray(solved, bool) & (normals[..., 2] > MIN_NZ)
    normals = np.where(usable[..., None], normals, np.nan)
    step = max(1, int(np.ceil(np.sqrt(usable.sum() / CURL_PIXELS))))
    # The four neighbours of each lattice pixel, (n_x, n_y) over n_z, in float64.
    around = [normals[rows, cols][::step, ::step].astype(np.float64) for rows, cols in
              ((np.s_[2:], np.s_[1:-1]), (np.s_[:-2], np.s_[1:-1]),
               (np.s_[1:-1], np.s_[2:]), (np.s_[1:-1], np.s_[:-2]))]
    below, above, right, left = (n[..., :2] / n[..., 2:] for n in around)
    inside = np.isfinite(below + above + right + left).all(axis=-1)
    pixels = int(inside.sum())
    medians = {}
    undo = {"as given": ((1, 0), (0, 1)), **{k: v[0] for k, v in MISTAKES.items()}}
    for name, (row_p, row_q) in undo.items():
        # p = -(row_p . n_xy) / n_z, q likewise; z_col = p and z_row = -q (rows go
        # down): curl = d(z_col)/drow - d(z_row)/dcol = dp/drow + dq/dcol.
        curl = np.abs((below - above) @ np.array(row_p, float) +
                      (right - left) @ np.array(row_q, float))[inside] / 2.0
        medians[name] = float(np.median(curl)) if pixels else float("nan")
    return medians, pixels


def check_axes(normals: np.ndarray, solved: np.ndarray, light_file) -> dict:
    """report.json's record of :func:`curl_medians`, with a
    :class:`~colorps.errors.LightAxesWarning` naming ``light_file`` when the
    solved normals are MIRROR_RATIO times less integrable than with one of
    :data:`MISTAKES` undone (``looks``: that mistake, else None)."""
    medians, pixels = curl_medians(normals, solved)
    mistake = min(MISTAKES, key=lambda name: medians[name])
    as_given, undone = medians["as given"], medians[mistake]
    looks = mistake if pixels >= MIN_CURL_PIXELS and as_given > MIRROR_RATIO * undone \
        else None
    if looks:
        warnings.warn(
            f"{light_file}: {MISTAKES[looks][1]}. The normals solved under these lights are "
            f"{as_given / undone:.1f} times less integrable than with that undone (median "
            f"curl of their slopes {as_given:.3g} against {undone:.3g}); colorps's axes are "
            "x right, y up, z towards the camera", LightAxesWarning, stacklevel=2)
    return dict(curl_medians=medians, pixels=pixels, looks=looks)
