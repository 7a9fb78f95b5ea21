"""Shared input checks (private): one place, not repeated in every function."""

from __future__ import annotations

import numpy as np

from .errors import InputError


def as_float32_2d(array, name: str) -> np.ndarray:
    """Return ``array`` as a C-contiguous float32 2-D array, or raise.

    Raises :class:`~colorps.errors.InputError` naming ``name`` when the array
    is not 2-D, is empty, or holds NaN or Inf.
    """
    try:
        arr = np.asarray(array)
    except Exception as exc:  # ragged lists and the like
        raise InputError(f"{name}: cannot be converted to an array ({exc})") from None
    if arr.ndim != 2:
        raise InputError(f"{name}: expected a 2-D array (rows, dims), got shape {arr.shape}")
    if arr.shape[0] == 0 or arr.shape[1] == 0:
        raise InputError(f"{name}: is empty (shape {arr.shape})")
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise InputError(f"{name}: expected real numbers, got dtype {arr.dtype}")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    if not np.isfinite(arr).all():
        bad = int(np.count_nonzero(~np.isfinite(arr).all(axis=1)))
        raise InputError(f"{name}: {bad} row(s) hold NaN or Inf values")
    return arr


def check_stack(stack, name: str = "stack") -> np.ndarray:
    """Return an image stack as float32 of shape (m, H, W, c), or raise.

    A 3-D array (m, H, W) is taken as a single-band stack.
    """
    arr = np.asarray(stack)
    if arr.ndim == 3:
        arr = arr[..., np.newaxis]
    if arr.ndim != 4:
        raise InputError(
            f"{name}: expected shape (m, H, W, c) or (m, H, W), got {arr.shape}"
        )
    if min(arr.shape) == 0:
        raise InputError(f"{name}: is empty (shape {arr.shape})")
    if not np.issubdtype(arr.dtype, np.number) or np.iscomplexobj(arr):
        raise InputError(f"{name}: expected real pixel values, got dtype {arr.dtype}")
    return np.ascontiguousarray(arr, dtype=np.float32)


def resolve_threads(threads: int | None) -> int:
    """Number of threads to use: ``None`` means all numba threads."""
    import numba

    available = numba.config.NUMBA_NUM_THREADS
    if threads is None:
        return available
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise InputError(f"threads: expected a positive integer or None, got {threads!r}")
    return int(min(threads, available))


def mask_box(mask: np.ndarray, margin: int = 0) -> tuple[slice, slice]:
    """Rows and columns of the smallest box holding every pixel of a 2-D boolean
    mask, grown by ``margin`` pixels within the image (the whole image when none
    is set)."""
    rows, cols = np.nonzero(mask.any(axis=1))[0], np.nonzero(mask.any(axis=0))[0]
    if not len(rows):
        return slice(0, mask.shape[0]), slice(0, mask.shape[1])
    h, w = mask.shape
    return (slice(max(int(rows[0]) - margin, 0), min(int(rows[-1]) + 1 + margin, h)),
            slice(max(int(cols[0]) - margin, 0), min(int(cols[-1]) + 1 + margin, w)))
