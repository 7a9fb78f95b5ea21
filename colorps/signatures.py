"""Observation vectors to signatures, in mono and colour mode.

A stack is a float32 array of shape (m, H, W, c): m images (one per lighting
condition), c colour bands, linear pixel values. The observation vector (OV) of
band k at pixel p is ``stack[:, y, x, k]`` in R^m; its signature is the OV divided
by its Euclidean norm.

=========  ===============================================================
mode       signature of a pixel
=========  ===============================================================
"colour"   each band's OV normalised separately, the c unit vectors
           concatenated band-major: (s_band0[0..m-1], s_band1[0..m-1], ...)
           in R^(c*m); every band block has unit norm.
"mono"     one band in R^m: a chosen channel, or the luminance Y computed with
           colour-science from the stack's RGB colourspace (sRGB / Rec. 709
           primaries by default).
=========  ===============================================================
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Literal

import numpy as np

from . import _pixel_kernels, light_masks
from ._checks import check_stack
from .errors import InputError
from .options import FLOAT_DARK_LEVEL, dark_threshold

__all__ = ["NEGATIVE_NOISE", "SignatureSet", "compute_signatures", "luminance",
           "luminance_weights"]

#: A negative measurement is noise around a dark one (linear files with the
#: black level taken off, renders with noise added) and is kept as measured
#: when it lies within NEGATIVE_NOISE of its channel's brightest measurement at
#: the pixel; further below zero it is invalid, as NaN and Inf are. (Every negative
#: value was invalid before: under 32 lights with noise 0.003 that refused 85 %
#: of a scene's pixels and 65 % of its gauge's.)
NEGATIVE_NOISE = 0.25


@dataclass(frozen=True)
class SignatureSet:
    """Signatures of every pixel of a stack.

    Attributes
    ----------
    signatures : (H, W, B * m) ndarray of float32
        Band-major concatenation of per-band unit signatures; the block of a
        band that is not valid is zero. Computed from ``ov`` when first read
        (a reconstruction matches from the OVs and never needs the scene's).
    norms : (H, W, B) ndarray of float32
        Euclidean norm of each band's OV (needed for albedo, eq. 6).
    valid : (H, W) ndarray of bool
        True where every band is valid.
    band_valid : (H, W, B) ndarray of bool
        A band is valid when none of its m measurements is invalid (NaN, Inf,
        or below -NEGATIVE_NOISE times its channel's brightest) or clipped and
        its OV norm exceeds ``min_norm``.
    band_invalid_value, band_clipped, band_dark : (H, W, B) ndarray of bool
        Why a band is not valid (a band may have several reasons).
    ov : (H, W, B, m) ndarray of float32
        The observation vectors of the signature bands, invalid measurements
        set to 0 (smaller negative values kept).
    clipped_lights : (H, W, words) ndarray of uint64
        Light masks (:mod:`colorps.light_masks`) of the images with a clipped
        measurement in a band the signature uses: the match can drop such
        lights instead of losing the band.
    invalid_lights : (H, W, words) ndarray of uint64
        The same of the images with an invalid measurement (NaN, Inf, far
        below zero) in a band the signature uses.
    mode : {"colour", "mono"}
    bands : int
        Number of bands B in the signature (c in colour mode, 1 in mono mode).
    images : int
        Number of images m.
    """

    norms: np.ndarray
    valid: np.ndarray
    band_valid: np.ndarray
    band_invalid_value: np.ndarray
    band_clipped: np.ndarray
    band_dark: np.ndarray
    ov: np.ndarray
    clipped_lights: np.ndarray
    invalid_lights: np.ndarray
    mode: str
    bands: int
    images: int

    @cached_property
    def signatures(self) -> np.ndarray:
        out = np.empty((*self.ov.shape[:2], self.bands * self.images), dtype=np.float32)
        _pixel_kernels.unit_signatures(self.ov, self.band_valid, out)
        return out


def luminance(stack, colourspace: str = "sRGB") -> np.ndarray:
    """Relative luminance Y of each RGB pixel of a stack, using colour-science.

    Parameters
    ----------
    stack : (..., 3) array_like
        Linear RGB values.
    colourspace : str, optional
        Name of a colour-science RGB colourspace (default "sRGB", Rec. 709
        primaries, D65).

    Returns
    -------
    (...) ndarray of float32
    """
    rgb = np.asarray(stack, dtype=np.float32)
    if rgb.shape[-1] != 3:
        raise InputError(f"luminance needs 3 (RGB) bands, got {rgb.shape[-1]}")
    return rgb @ luminance_weights(colourspace)


def luminance_weights(colourspace: str = "sRGB") -> np.ndarray:
    """(3,) float32: the Y row of a colour-science colourspace's RGB -> XYZ matrix.

    The normative matrix, as used by ``colour.RGB_to_XYZ``.
    """
    import colour

    try:
        space = colour.RGB_COLOURSPACES[colourspace]
    except KeyError:
        raise InputError(f"colourspace: unknown RGB colourspace {colourspace!r}") from None
    return np.asarray(space.matrix_RGB_to_XYZ[1], dtype=np.float32)


def _mono_mixing(c: int, band: int | Literal["luminance"] | None,
                 colourspace: str) -> np.ndarray:
    """(1, c) weights of the single band of mono mode over the input channels."""
    if band is None:
        band = "luminance" if c == 3 else 0
    mixing = np.zeros((1, c), dtype=np.float32)
    if isinstance(band, str):
        if band != "luminance":
            raise InputError(f"band: expected a channel index or 'luminance', got {band!r}")
        if c != 3:
            raise InputError(f"luminance needs 3 (RGB) bands, got {c}")
        mixing[0] = luminance_weights(colourspace)
        return mixing
    if isinstance(band, bool) or not isinstance(band, (int, np.integer)) or not 0 <= band < c:
        raise InputError(f"band: expected a channel index in 0..{c - 1}, got {band!r}")
    mixing[0, band] = 1.0
    return mixing


def compute_signatures(stack, mode: Literal["colour", "mono"] = "colour", *,
                       band: int | Literal["luminance"] | None = None,
                       colourspace: str = "sRGB",
                       min_norm: float | None = None,
                       clip_level: float | None = None,
                       box: tuple[slice, slice] | None = None) -> SignatureSet:
    """Normalise the observation vectors of a stack into signatures.

    Parameters
    ----------
    stack : (m, H, W, c) or (m, H, W) array_like
        Linear pixel values of m images.
    mode : {"colour", "mono"}, optional
        Colour: one unit vector per band, concatenated band-major. Mono: a single
        band (see ``band``).
    band : int or "luminance", optional
        Mono mode only: the channel to use, or luminance (the default for 3-band
        stacks; single-band stacks use channel 0).
    colourspace : str, optional
        RGB colourspace of the stack for luminance (colour-science name).
    min_norm : float, optional
        A band's OV whose Euclidean norm is at most this (linear units) cannot be
        normalised: the pixel is reported invalid, never turned into NaN.
        Default: ``FLOAT_DARK_LEVEL * sqrt(m)`` (see
        :func:`colorps.options.dark_threshold`).
    clip_level : float, optional
        Measurements at or above this linear value are clipped (saturated) and
        make their band invalid. None: nothing is clipped.
    box : (slice, slice), optional
        Rows and columns (steps of 1) of the pixels to compute, read in place;
        default every pixel.

    Returns
    -------
    SignatureSet

    Examples
    --------
    >>> import numpy as np
    >>> from colorps import compute_signatures
    >>> stack = np.ones((4, 2, 2, 3), dtype=np.float32)   # m=4, 2x2 px, RGB
    >>> sig = compute_signatures(stack, "colour")
    >>> sig.signatures.shape, float(sig.signatures[0, 0, :4] @ sig.signatures[0, 0, :4])
    ((2, 2, 12), 1.0)
    """
    data = check_stack(stack)
    m = data.shape[0]
    if mode not in ("colour", "mono"):
        raise InputError(f"mode: expected 'colour' or 'mono', got {mode!r}")
    if min_norm is None:
        min_norm = dark_threshold(FLOAT_DARK_LEVEL, m)
    if not np.isfinite(min_norm) or min_norm < 0:
        raise InputError(f"min_norm: expected a finite value >= 0, got {min_norm!r}")
    if clip_level is not None and not clip_level > 0:
        raise InputError(f"clip_level: expected a value > 0 or None, got {clip_level!r}")

    c = data.shape[3]
    rows, cols = (slice(None), slice(None)) if box is None else box
    (first_row, h), (first_col, w) = (_span(rows, data.shape[1]), _span(cols, data.shape[2]))
    if mode == "colour":
        mixing = np.eye(c, dtype=np.float32)
    else:
        mixing = _mono_mixing(c, band, colourspace)
    b = mixing.shape[0]
    ov = np.empty((h, w, b, m), dtype=np.float32)
    norms = np.empty((h, w, b), dtype=np.float32)
    bad_any, clipped_any, dark = (np.empty((h, w, b), dtype=bool) for _ in range(3))
    lights, invalid_lights = light_masks.empty((h, w), m), light_masks.empty((h, w), m)
    _pixel_kernels.observation_vectors(
        data, first_row, first_col, mixing,
        np.inf if clip_level is None else float(clip_level), float(min_norm),
        NEGATIVE_NOISE, ov, norms, bad_any, clipped_any, dark, lights, invalid_lights)
    band_valid = ~bad_any & ~clipped_any & ~dark
    valid = band_valid.all(axis=-1)
    return SignatureSet(
        norms=norms,
        valid=valid,
        band_valid=band_valid,
        band_invalid_value=bad_any,
        band_clipped=clipped_any,
        band_dark=dark,
        ov=ov,
        clipped_lights=lights,
        invalid_lights=invalid_lights,
        mode=mode,
        bands=b,
        images=m,
    )


def _span(part: slice, size: int) -> tuple[int, int]:
    """(first index, count) of a slice of steps of 1 over ``size`` items."""
    first, stop, step = part.indices(size)
    if step != 1:
        raise InputError(f"box: expected slices of step 1, got {part}")
    return first, max(0, stop - first)
