"""Sets of lights (images) as bit masks, for any number of images.

A mask is ``words(m)`` uint64 words along the last axis: image i is bit
``i % 64`` of word ``i // 64``. An (H, W) map of masks is an (H, W, words)
array; masks compare, group and combine (``|``, ``&``) word by word.

Examples
--------
>>> from colorps import light_masks
>>> mask = light_masks.of_lights([2, 70], 96)
>>> mask.tolist(), light_masks.lights(mask), int(light_masks.count(mask))
([4, 64], (2, 70), 2)
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "count",
    "empty",
    "from_bool",
    "is_empty",
    "lights",
    "of_lights",
    "single",
    "to_bool",
    "words",
]

WORD_BITS = 64


def words(m: int) -> int:
    """uint64 words of a mask of m images (at least 1)."""
    return max(1, -(-int(m) // WORD_BITS))


def empty(shape: tuple[int, ...], m: int) -> np.ndarray:
    """Masks of no light: (``*shape``, words(m)) zeros."""
    return np.zeros((*shape, words(m)), dtype=np.uint64)


def single(m: int) -> np.ndarray:
    """(m, words(m)): row i is the mask of image i alone."""
    out = empty((m,), m)
    i = np.arange(m)
    out[i, i // WORD_BITS] = np.uint64(1) << (i % WORD_BITS).astype(np.uint64)
    return out


def of_lights(indices, m: int) -> np.ndarray:
    """The mask of the given images."""
    out = empty((), m)
    for i in indices:
        out[int(i) // WORD_BITS] |= np.uint64(1) << np.uint64(int(i) % WORD_BITS)
    return out


def from_bool(flags: np.ndarray) -> np.ndarray:
    """(..., m) bool -> (..., words(m)) masks."""
    flags = np.asarray(flags, dtype=bool)
    m = flags.shape[-1]
    return (flags[..., None] * single(m)).sum(axis=-2, dtype=np.uint64)


def to_bool(masks: np.ndarray, m: int) -> np.ndarray:
    """(..., words) masks -> (..., m) bool: image i in each mask."""
    masks = np.asarray(masks, dtype=np.uint64)
    out = np.empty((*masks.shape[:-1], m), dtype=bool)
    for i in range(m):  # one image at a time: (..., m) uint64 temporaries took gigabytes
        out[..., i] = masks[..., i // WORD_BITS] & np.uint64(1 << (i % WORD_BITS)) != 0
    return out


def count(masks: np.ndarray) -> np.ndarray:
    """(...) number of images in each (..., words) mask."""
    return np.bitwise_count(np.asarray(masks, dtype=np.uint64)).sum(axis=-1, dtype=np.int64)


def is_empty(masks: np.ndarray) -> np.ndarray:
    """(...) bool: the mask holds no image."""
    return ~np.asarray(masks).any(axis=-1)


def lights(mask: np.ndarray) -> tuple[int, ...]:
    """The images of one (words,) mask, ascending."""
    mask = np.asarray(mask, dtype=np.uint64)
    return tuple(int(i) for i in np.flatnonzero(to_bool(mask, mask.shape[-1] * WORD_BITS)))
