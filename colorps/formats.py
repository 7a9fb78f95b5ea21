"""Which files are images colorps reads: every format of the OpenImageIO build
it runs with, except camera raw (demosaicing and white balance are a raw
converter's job; such a file is refused with advice, see :mod:`colorps.io`).
"""

from __future__ import annotations

from functools import lru_cache

__all__ = ["CAMERA_RAW_SUFFIXES", "image_suffixes"]

#: File name suffixes of camera raw formats, which colorps does not decode
#: (demosaicing and white balance are a raw converter's job): such a file is
#: refused with advice on converting it to a linear TIFF.
CAMERA_RAW_SUFFIXES = frozenset([
    ".3fr", ".arw", ".cr2", ".cr3", ".crw", ".dcr", ".dng", ".erf", ".fff", ".iiq", ".k25",
    ".kdc", ".mef", ".mos", ".mrw", ".nef", ".nrw", ".orf", ".pef", ".raf", ".raw", ".rw2",
    ".rwl", ".sr2", ".srf", ".srw", ".x3f"])


#: OpenImageIO formats that are not image files of a capture.
_NOT_CAPTURE_FORMATS = ("null", "term")


@lru_cache(maxsize=1)
def image_suffixes() -> frozenset[str]:
    """File name suffixes (lower case, with the dot) of the image formats colorps
    reads: every format of this OpenImageIO build but camera raw.

    Examples
    --------
    >>> {".exr", ".tif", ".png", ".jpg", ".hdr"} <= image_suffixes()
    True
    >>> ".nef" in image_suffixes()
    False
    """
    import OpenImageIO as oiio

    found = set()
    for entry in oiio.get_string_attribute("extension_list").split(";"):
        name, _, extensions = entry.partition(":")
        if name not in _NOT_CAPTURE_FORMATS:
            found.update(f".{e.lower()}" for e in extensions.split(",") if e)
    return frozenset(found - CAMERA_RAW_SUFFIXES)
