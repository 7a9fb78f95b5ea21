"""Does the gauge look like a lit sphere? A check of its images against its geometry.

Every gauge image, under one distant light, should shade its sphere like a
matte ball: I(q) = max(0, n(q) . L) with n(q) the sphere's normal at pixel q
and L the light (times the albedo). :func:`sphere_fit` fits L to each image by
least squares on the pixels it lights and gives the relative RMS residual.
A real matte gauge, decoded right, leaves a few percent (its finish is not
quite Lambertian); much more says the images are not of a lit sphere at that
place. Two mistakes show so:

* **the wrong images or place**: scene and gauge swapped, another object, a
  wrong ``--sphere``, a chrome ball: a residual over POOR_FIT
  (:func:`check_gauge` warns, naming the first gauge file);
* **the wrong encoding**: 8- or 16-bit files decoded as sRGB that are linear
  (or the other way): the fit of the other decoding is much better
  (under ENCODING_RATIO of this one's), and :func:`check_gauge` warns with
  the ``--encoding`` to use.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from .errors import GaugeWarning
from .gauge import Gauge

__all__ = ["ENCODING_RATIO", "POOR_FIT", "check_gauge", "sphere_fit"]

# ---------------------------------------------------------------- tuning
#: Relative RMS residual of the Lambertian sphere fit above which the gauge
#: images do not look like a lit sphere: synthetic matte, glossy (0.3) and rough
#: (Oren-Nayar 0.5) gauges left 0.01, 0.07 and 0.10; a smiley scene read as the
#: gauge (stacks swapped) 0.26.
POOR_FIT = 0.18
#: The other decoding fits better by at least this factor: the encoding is wrong.
ENCODING_RATIO = 0.5
#: A pixel takes part in an image's fit where the fitted light reaches it by at
#: least this fraction of its strength (the terminator is left out).
LIT_FRACTION = 0.1
#: Rounds of fitting the light and choosing the pixels it lights.
FIT_ROUNDS = 3


def sphere_fit(stack: np.ndarray, gauge: Gauge) -> float:
    """Median over the images of the relative RMS residual of a Lambertian fit.

    Parameters
    ----------
    stack : (m, Hg, Wg, c) ndarray
        Linear gauge images.
    gauge : Gauge
        Its geometry (the normals inside its mask).

    Returns
    -------
    float
        sqrt(sum r^2 / sum I^2) over the lit pixels of each image (I the bands'
        mean, r = I - n . L), the median over the images.
    """
    normals = gauge.normals[gauge.mask]  # (P, 3)
    values = np.asarray(stack, dtype=np.float64)[:, gauge.mask].mean(axis=-1)  # (m, P)
    residuals = []
    for image in values:
        lit = np.isfinite(image) & (image > LIT_FRACTION * np.nanmax(image, initial=0.0))
        if lit.sum() < 10:
            continue
        for _ in range(FIT_ROUNDS):
            light = np.linalg.lstsq(normals[lit], image[lit], rcond=None)[0]
            shade = normals @ light
            lit = np.isfinite(image) & (shade > LIT_FRACTION * np.linalg.norm(light))
            if lit.sum() < 10:
                break
        r = image[lit] - shade[lit]
        residuals.append(np.sqrt((r * r).sum() / max((image[lit] ** 2).sum(), 1e-30)))
    return float(np.median(residuals)) if residuals else float("nan")


def check_gauge(stack: np.ndarray, gauge: Gauge, first_file: Path, encoding: str,
                integer_files: bool) -> dict:
    """Warn when the gauge images do not look like a lit sphere, or fit much better
    decoded the other way; return what report.json records.

    Parameters
    ----------
    stack : (m, Hg, Wg, c) ndarray
        The gauge images as decoded.
    gauge : Gauge
    first_file : Path
        The first gauge file, for messages.
    encoding : {"auto", "linear", "srgb"}
        How the files were decoded ("auto": sRGB for integer files).
    integer_files : bool
        The files store integers (the encoding question arises).
    """
    fit = sphere_fit(stack, gauge)
    record = dict(sphere_fit_residual=fit, other_encoding_residual=None)
    if integer_files:
        from .io import srgb_decode, srgb_encode

        read_as_srgb = encoding in ("auto", "srgb")
        other = srgb_encode(stack) if read_as_srgb else srgb_decode(np.clip(stack, 0, 1))
        other_fit = sphere_fit(other, gauge)
        record["other_encoding_residual"] = other_fit
        if other_fit < ENCODING_RATIO * fit:
            flag = "linear" if read_as_srgb else "srgb"
            warnings.warn(
                f"{first_file}: the gauge's shading fits a lit sphere far better read as "
                f"{'linear' if read_as_srgb else 'sRGB'} (relative residual "
                f"{other_fit:.3f}) than as "
                f"{'sRGB' if read_as_srgb else 'linear'} ({fit:.3f}): the files are "
                f"probably {flag}; pass --encoding {flag}", GaugeWarning, stacklevel=3)
            return record
    if fit > POOR_FIT:
        warnings.warn(
            f"{first_file}: the gauge images do not look like a matte sphere lit from one "
            f"direction at the given place (relative residual of a Lambertian fit "
            f"{fit:.2f}; matte gauges leave about 0.1 or less): check that scene and gauge are not "
            "swapped, --sphere, and that the gauge is not a mirror ball", GaugeWarning,
            stacklevel=3)
    return record
