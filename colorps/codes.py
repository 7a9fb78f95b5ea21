"""16-bit codes of float maps, as height.png and the viewer's data store them.

Code 0 means "no value" (NaN); codes 1 to 65535 spread ``lo`` to ``hi``
linearly, so a value decodes as ``lo + (code - 1) * (hi - lo) / 65534`` within
half a step, (hi - lo) / 131068, of what was encoded (values outside lo..hi are
clipped to them). ``lo`` and ``hi`` are recorded beside the codes (report.json,
the viewer's index).
"""

from __future__ import annotations

import numpy as np

__all__ = ["CODE_STEPS", "code_range", "decode", "encode"]

#: Steps between the lowest and the highest value (code 0 is "no value").
CODE_STEPS = 65534
#: Values encoded at a time (bounded temporaries, and they stay in the caches).
ENCODE_CHUNK = 1 << 16


def code_range(values) -> tuple[float, float]:
    """``(lo, hi)`` spanning the finite values (0, 1 when there are none; hi > lo)."""
    v = np.asarray(values)
    finite = v[np.isfinite(v)]
    if finite.size == 0:
        return 0.0, 1.0
    lo, hi = float(finite.min()), float(finite.max())
    return lo, hi if hi > lo else lo + 1.0


def encode(values, lo: float, hi: float) -> np.ndarray:
    """uint16 codes of ``values`` (NaN -> 0), in pieces of ENCODE_CHUNK values
    (float64 temporaries of a 16-megapixel map took gigabytes)."""
    v = np.asarray(values)
    codes = np.empty(v.shape, dtype=np.uint16)
    flat, flat_codes = v.reshape(-1), codes.reshape(-1)
    for start in range(0, flat.size, ENCODE_CHUNK):
        piece = flat[start:start + ENCODE_CHUNK].astype(np.float64)
        scaled = np.clip((piece - lo) / (hi - lo), 0.0, 1.0) * CODE_STEPS + 1.0
        flat_codes[start:start + ENCODE_CHUNK] = np.where(
            np.isfinite(piece), np.rint(np.nan_to_num(scaled, nan=0.0)), 0.0)
    return codes


def decode(codes, lo: float, hi: float) -> np.ndarray:
    """float64 values of uint16 codes (0 -> NaN)."""
    c = np.asarray(codes, dtype=np.float64)
    return np.where(c > 0, lo + (c - 1.0) * (hi - lo) / CODE_STEPS, np.nan)
