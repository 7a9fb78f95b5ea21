"""The noise model of a capture: the expected standard deviation of every measurement.

A measurement v (linear, 0..1 scale) of a photo has variance ::

    sigma(v)^2 = read^2 + gain * v + quantisation(v)^2

* ``read``: a floor (sensor read noise, dark current), linear units;
* ``gain * v``: shot noise, whose variance grows with the signal;
* ``quantisation(v)``: one code step of the file's pixel type at v, in linear
  units, divided by sqrt(12) (a uniform rounding error). For sRGB-encoded
  integer files the step is taken through colour-science's sRGB decoding at v,
  so it shrinks in the shadows and grows in the highlights; for half-float
  files it is one half-float unit of v; for float32 files it is 0.

``read`` and ``gain`` come from the gauge's own pixel-to-pixel scatter
(:func:`estimate_noise`): a sphere's shading is smooth, so what a local
quadratic fit over 3 x 3 pixels does not explain is noise. A user who knows
the camera can give them instead (``Options.read_noise``, ``Options.gain``).

Everything downstream is expressed in units of this sigma: the band weights of
colour signatures, the quality map and the acceptance of a match.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import numpy as np

from ._checks import mask_box

__all__ = ["NoiseModel", "estimate_noise", "file_noise", "lit_measurements",
           "quantisation_sigma"]

#: The read-noise floor of floating-point data with no measurable scatter (linear).
FLOAT_READ_NOISE = 1e-5
#: Gauge pixels further than this fraction of the radius from the centre are not
#: used to estimate noise (the shading curves fastest near the rim).
NOISE_RADIUS_FRACTION = 0.85
#: NoiseModel.sigma interpolates the quantisation term between this many levels
#: in 0..1 (exact at integer codes' midpoints to well under 1 %).
QUANTISATION_SAMPLES = 4097
#: Brightness bins of the noise fit, and the fewest pixels a bin needs.
NOISE_BINS = 16
NOISE_MIN_PIXELS = 50
#: The fit takes the scatter of at most this many pixels (a fixed random sample
#: of the usable ones; every pixel of a gauge): a 4 MP scene's took every pixel's
#: float64 values and residuals, 1.4 GB.
NOISE_SAMPLE_PIXELS = 100_000

PixelType = Literal["int", "half", "float"]


def quantisation_sigma(values: np.ndarray, *, pixel_type: PixelType, top_code: int = 255,
                       encoding: Literal["linear", "srgb"] = "srgb") -> np.ndarray:
    """Standard deviation (linear) of the rounding of ``values`` to the file's codes.

    Parameters
    ----------
    values : ndarray
        Linear measurements (0..1 scale).
    pixel_type : {"int", "half", "float"}
        The file's pixel type.
    top_code : int, optional
        Largest code of an integer file (255 for 8 bits, 65535 for 16 bits).
    encoding : {"linear", "srgb"}, optional
        How an integer file's codes map to linear light.
    """
    v = np.asarray(values, dtype=np.float64)
    if pixel_type == "float":
        return np.zeros_like(v)
    if pixel_type == "half":
        return _half_ulp(v) / np.sqrt(12.0)
    step = 1.0 / top_code
    if encoding == "linear":
        return np.full_like(v, step / np.sqrt(12.0))
    from .io import srgb_decode, srgb_encode

    code = srgb_encode(np.clip(v, 0.0, 1.0)).astype(np.float64)
    up = srgb_decode(np.clip(code + step / 2, 0.0, 1.0)).astype(np.float64)
    down = srgb_decode(np.clip(code - step / 2, 0.0, 1.0)).astype(np.float64)
    return (up - down) / np.sqrt(12.0)


def _half_ulp(values: np.ndarray) -> np.ndarray:
    """One half-float unit in the last place at ``values``: 2^(e - 10) for
    2^e <= |v| < 2^(e + 1), and 2^-24 below 2^-14 (subnormals).

    Read off the float32 exponent bits: integer work, no logarithm.
    """
    v = np.maximum(np.abs(np.asarray(values, np.float32)), np.float32(2.0 ** -14))
    exponent_bits = v.view(np.int32) & np.int32(0x7F800000)
    return (exponent_bits - np.int32(10 << 23)).view(np.float32)


@dataclass(frozen=True)
class NoiseModel:
    """sigma(v)^2 = read^2 + gain v + quantisation(v)^2 for every measurement v.

    Attributes
    ----------
    read : float
        Read-noise floor (linear units).
    gain : float
        Shot-noise variance per unit of linear signal.
    pixel_type : {"int", "half", "float"}
    top_code : int
        Largest code of integer files.
    encoding : {"linear", "srgb"}
        How integer codes map to linear light.
    estimated : bool
        True when ``read`` and ``gain`` were fitted to the gauge.

    Examples
    --------
    >>> import numpy as np
    >>> from colorps.noise import NoiseModel
    >>> model = NoiseModel(read=0.001, gain=0.0, pixel_type="float")
    >>> [round(float(v), 6) for v in model.sigma(np.array([0.0, 0.5]))]
    [0.001, 0.001]
    """

    read: float
    gain: float
    pixel_type: PixelType = "float"
    top_code: int = 255
    encoding: Literal["linear", "srgb"] = "linear"
    estimated: bool = False

    def sigma(self, values) -> np.ndarray:
        """Standard deviation of each measurement (linear units, float32, same shape)."""
        v = np.asarray(values, dtype=np.float32)
        v = np.where(np.isfinite(v) & (v > 0), v, np.float32(0.0))
        variance = np.float32(self.read ** 2) + np.float32(self.gain) * v
        if self.pixel_type == "int":
            levels, table = _quantisation_table(self.top_code, self.encoding)
            q = np.interp(v, levels, table).astype(np.float32)
            variance += q * q
        elif self.pixel_type == "half":
            q = _half_ulp(v)
            variance += q * q / np.float32(12.0)
        return np.sqrt(variance)

    def mean_variance(self, values) -> np.ndarray:
        """Mean of sigma^2 over the last axis: (..., m) measurements -> (...) float32.

        The same as ``(self.sigma(values) ** 2).mean(axis=-1)``, in one
        compiled pass with no temporaries of the measurements' size.
        """
        from ._pixel_kernels import mean_variance

        v = np.asarray(values, dtype=np.float32)
        flat = np.ascontiguousarray(v.reshape(-1, v.shape[-1]))
        out = np.empty(flat.shape[0], dtype=np.float32)
        mean_variance(flat, *self.kernel_args(), out)
        return out.reshape(v.shape[:-1])

    def kernel_args(self) -> tuple:
        """The model as the compiled kernels take it: (read^2, gain, pixel kind
        0 float / 1 half / 2 integer, quantisation levels, their sigma)."""
        levels = table = np.zeros(1)
        if self.pixel_type == "int":
            levels, table = _quantisation_table(self.top_code, self.encoding)
        return (float(self.read) ** 2, float(self.gain),
                {"float": 0, "half": 1, "int": 2}[self.pixel_type], levels, table)

    def as_dict(self) -> dict:
        return dict(read=self.read, gain=self.gain, pixel_type=self.pixel_type,
                    top_code=self.top_code, encoding=self.encoding, estimated=self.estimated)


def file_noise(source, encoding: Literal["auto", "linear", "srgb"] = "auto") -> NoiseModel:
    """The noise model of a file's pixel type: its quantisation only (read noise
    and gain 0, to be fitted or given).

    Parameters
    ----------
    source : str, Path or ImageInfo
        The file, or its header as already read (:func:`colorps.io.read_info`).
    encoding : {"auto", "linear", "srgb"}
        How its integer codes map to linear light ("auto": sRGB).
    """
    from .io import pixel_type, top_code

    kind = pixel_type(source)
    if kind == "int":
        return NoiseModel(read=0.0, gain=0.0, pixel_type="int", top_code=top_code(source),
                          encoding="linear" if encoding == "linear" else "srgb")
    return NoiseModel(read=0.0, gain=0.0, pixel_type=kind)


@lru_cache(maxsize=1)
def _quantisation_levels() -> np.ndarray:
    """The QUANTISATION_SAMPLES levels in 0..1 the quantisation term is tabulated at."""
    levels = np.linspace(0.0, 1.0, QUANTISATION_SAMPLES)
    levels.setflags(write=False)
    return levels


@lru_cache(maxsize=8)
def _quantisation_table(top_code: int, encoding: str) -> tuple[np.ndarray, np.ndarray]:
    levels = _quantisation_levels()
    return levels, quantisation_sigma(levels, pixel_type="int", top_code=top_code,
                                      encoding=encoding)


def _quadratic_residual_filter() -> np.ndarray:
    """3 x 3 weights r such that sum(r * patch) is the patch centre minus the
    value at the centre of the least-squares quadratic through the patch."""
    y, x = np.mgrid[-1:2, -1:2]
    x, y = x.ravel(), y.ravel()
    design = np.stack([np.ones(9), x, y, x * x, x * y, y * y], axis=1).astype(np.float64)
    hat_row = design[4] @ np.linalg.pinv(design)
    residual = -hat_row
    residual[4] += 1.0
    return residual.reshape(3, 3)


def estimate_noise(gauge_stack: np.ndarray, usable: np.ndarray, base: NoiseModel,
                   centre: tuple[float, float] | None = None,
                   radius: float | None = None) -> NoiseModel:
    """Fit ``read`` and ``gain`` of ``base`` to the gauge's pixel-to-pixel scatter.

    Parameters
    ----------
    gauge_stack : (m, H, W, c) ndarray
        Linear gauge images.
    usable : (H, W) or (m, H, W) ndarray of bool
        Pixels whose measurements are all usable (no clip, no NaN), or each
        image's own (a scene under many lights, where few pixels are lit in
        every image: a pixel counts in the images that light it).
    base : NoiseModel
        Pixel type and encoding of the files; its read and gain are kept where
        the gauge cannot tell (too few pixels).
    centre, radius : optional
        Sphere geometry (pixels): only pixels within NOISE_RADIUS_FRACTION of
        the radius are used.

    Returns
    -------
    NoiseModel
        ``read`` and ``gain`` fitted by non-negative least squares to the
        robust (median absolute deviation) variance of the residuals of a
        local quadratic fit, binned by brightness, after removing the known
        quantisation variance (over NOISE_SAMPLE_PIXELS pixels at most).
    """
    from scipy.ndimage import binary_erosion, correlate
    from scipy.optimize import nnls

    m, h, w, c = gauge_stack.shape
    usable = np.asarray(usable, dtype=bool)
    box = mask_box(usable if usable.ndim == 2 else usable.any(axis=0))
    # Only the usable pixels' box is filtered: an inner pixel's 3 x 3 lies in it
    # (a scene's mask is often a small part of its images).
    within = np.ones((h, w), dtype=bool)[box]
    if centre is not None and radius is not None:
        yy, xx = np.mgrid[0:h, 0:w]
        within = (np.hypot(xx - centre[0], yy - centre[1]) < NOISE_RADIUS_FRACTION * radius)[box]

    def sample(image_usable):  # inner pixels of one image's usable ones, and a sample
        inner = binary_erosion(image_usable, np.ones((3, 3), bool), border_value=0) & within
        taken = np.flatnonzero(inner)
        if taken.size > NOISE_SAMPLE_PIXELS:
            taken = np.sort(np.random.default_rng(0).choice(taken, NOISE_SAMPLE_PIXELS,
                                                            replace=False))
        return taken

    shared = sample(usable[box]) if usable.ndim == 2 else None
    kernel = _quadratic_residual_filter()
    gain_factor = float((kernel * kernel).sum())  # var(residual) = factor * sigma^2
    values, residuals = [], []
    for i in range(m):
        image_usable = usable[box] if shared is not None else usable[i][box]
        taken = shared if shared is not None else sample(image_usable)
        if taken.size < NOISE_MIN_PIXELS:
            continue
        for k in range(c):  # one image's band at a time in float64
            image = np.asarray(gauge_stack[i, box[0], box[1], k], dtype=np.float64)
            r = correlate(np.where(image_usable, image, 0.0), kernel, mode="nearest")
            values.append(image.ravel()[taken])
            residuals.append(r.ravel()[taken])
    if not values:
        return base
    v = np.concatenate(values)
    r = np.concatenate(residuals)
    edges = np.quantile(v, np.linspace(0, 1, NOISE_BINS + 1))
    rows, target = [], []
    for lo, hi in itertools.pairwise(edges):
        pick = (v >= lo) & (v <= hi)
        if pick.sum() < NOISE_MIN_PIXELS:
            continue
        mad = np.median(np.abs(r[pick] - np.median(r[pick])))
        variance = (1.4826 * mad) ** 2 / gain_factor
        level = float(np.median(v[pick]))
        q = quantisation_sigma(np.array([level]), pixel_type=base.pixel_type,
                               top_code=base.top_code, encoding=base.encoding)[0]
        rows.append([1.0, level])
        target.append(max(variance - q * q, 0.0))
    if len(rows) < 2:
        return base
    (read2, gain), _ = nnls(np.array(rows), np.array(target))
    floor = FLOAT_READ_NOISE if base.pixel_type != "int" else 0.0
    return NoiseModel(read=float(max(np.sqrt(read2), floor)), gain=float(gain),
                      pixel_type=base.pixel_type, top_code=base.top_code,
                      encoding=base.encoding, estimated=True)


def lit_measurements(scene: np.ndarray, mask=None) -> np.ndarray:
    """(m, H, W) bool: each image's pixels of the (m, H, W, c) ``scene`` with every
    band finite and lit, within ``mask`` ((H, W) bool, optional). What
    :func:`estimate_noise` takes as ``usable`` for a scene's own scatter: under
    many lights few pixels are lit in all images."""
    usable = np.isfinite(scene).all(axis=3) & (scene > 0).all(axis=3)
    if mask is not None:
        usable &= np.asarray(mask, dtype=bool)
    return usable
