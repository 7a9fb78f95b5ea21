"""Files that do not belong in a stack: masks and alpha mattes picked up by a glob.

A glob such as ``'cat/*.tga'`` also matches ``cat.mask.tga``; read as the 13th
photograph, the mask makes a signature no gauge pixel has, and the error that
follows blames the gauge. Two checks name such a file and its position instead:

* by name, before any pixel is read (:func:`check_names`): a file whose name
  says mask, matte or alpha;
* by content, once the stack is read (:func:`check_contents`): an image whose
  pixels take exactly two values, 0 and one level, as a mask does and no
  photograph of a lit object can (a wholly clipped or black image is left to the
  checks that say so).

:func:`relative_exposures` compares the exposures the files' headers record;
:func:`check_exposures` and :func:`check_stack_exposures` warn about scene
images taken at other settings than their gauge images or than each other.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .errors import ExposureWarning, InputError, PairingWarning

if TYPE_CHECKING:
    from .io import ImageInfo

__all__ = ["EXPOSURE_TOLERANCE", "MASK_WORDS", "check_contents", "check_exposures", "check_names",
           "check_stack_exposures", "relative_exposures"]

#: A file whose name (without extension) holds one of these words, as a word
#: or after a separator, is taken for a mask, not a photograph.
MASK_WORDS = ("mask", "matte", "alpha")
_MASK_NAME = re.compile(r"(^|[^a-z])(" + "|".join(MASK_WORDS) + r")([^a-z]|$)")
#: Pixels read for the content check (a regular sample of each image).
CONTENT_SAMPLE = 65536
#: Scene and gauge exposures (EXIF) that differ by more than this fraction,
#: between lights or overall, are warned about (nominal shutter speeds alike
#: compare exactly; a third of a stop is 26 %).
EXPOSURE_TOLERANCE = 0.02


def check_names(paths: Sequence[Path], name: str) -> None:
    """Refuse a stack holding a file named like a mask, naming it and its position."""
    for k, path in enumerate(paths):
        if _MASK_NAME.search(Path(path).stem.lower()):
            raise InputError(
                f"{path}: image {k + 1} of the {len(paths)} {name} images looks like a mask "
                f"(by its name); give the {name} photographs only (a glob such as "
                "'*.png' picks up mask files too), and the mask with --mask")


def check_contents(stack: np.ndarray, paths: Sequence[Path], name: str) -> None:
    """Refuse a stack holding an image of 0 and one other value only (a mask, a
    matte); warn (PairingWarning) of two images holding the same pixels, which
    two lights cannot give (a file copied over another)."""
    m = stack.shape[0]
    if m < 2:
        return
    first_with = {}  # (a sample of each image's pixels: its first image)
    for k in range(m):
        image = stack[k].reshape(-1)
        step = max(1, image.size // CONTENT_SAMPLE)
        values = np.unique(image[::step])
        if values.size == 2 and values[0] <= 0.0 < values[1]:
            raise InputError(
                f"{paths[k]}: image {k + 1} of the {m} {name} images holds only "
                f"2 values ({values[0]:g} and {values[1]:g}), like a "
                f"mask, not a photograph; give the {name} photographs only, and the mask "
                "with --mask")
        j = first_with.setdefault(image[::step].tobytes(), k)
        if j != k and np.array_equal(stack[j], stack[k]):
            warnings.warn(f"{paths[k]}: image {k + 1} of the {m} {name} images holds the "
                          f"same pixels as image {j + 1}, {paths[j]}, which two lights "
                          "cannot give: was one file copied over another?", PairingWarning,
                          stacklevel=3)


def relative_exposures(scene: Sequence[ImageInfo],
                       gauge: Sequence[ImageInfo]) -> np.ndarray | None:
    """Each scene image's exposure over its gauge image's, from their headers.

    A linear pixel value grows as exposure time x ISO / f-number²; each pair
    is compared on the settings both of its headers record.

    Returns
    -------
    (m,) ndarray or None
        The ratios; None unless every pair records its exposure time.

    Examples
    --------
    >>> from pathlib import Path
    >>> from colorps.io import ImageInfo
    >>> info = lambda **exposure: ImageInfo(Path("x.jpg"), 8, 8, 3, "uint8", exposure)
    >>> relative_exposures([info(time=1 / 60, f_number=8.0), info(time=1 / 125, iso=200)],
    ...                    [info(time=1 / 125, f_number=8.0), info(time=1 / 125)]).tolist()
    [2.0833333333333335, 1.0]
    """
    ratios = []
    for s, g in zip(scene, gauge):
        if "time" not in s.exposure or "time" not in g.exposure:
            return None
        ratio = s.exposure["time"] / g.exposure["time"]
        if "iso" in s.exposure and "iso" in g.exposure:
            ratio *= s.exposure["iso"] / g.exposure["iso"]
        if "f_number" in s.exposure and "f_number" in g.exposure:
            ratio *= (g.exposure["f_number"] / s.exposure["f_number"]) ** 2
        ratios.append(ratio)
    return np.array(ratios) if ratios else None


def _furthest_off(ratios: np.ndarray) -> int | None:
    """The image whose exposure ratio is furthest from the median, when the ratios
    spread more than EXPOSURE_TOLERANCE; None when they agree."""
    if ratios.max() <= ratios.min() * (1 + EXPOSURE_TOLERANCE):
        return None
    return int(np.argmax(np.abs(np.log(ratios / np.median(ratios)))))


def check_stack_exposures(scene_infos) -> None:
    """With calibrated lights (no gauge exposed alike to cancel it), warn when the
    headers say the scene's images were exposed differently: naming the image
    most unlike the others, and its place."""
    ratios = relative_exposures(scene_infos, [scene_infos[0]] * len(scene_infos))
    k = None if ratios is None else _furthest_off(ratios)
    if k is None:
        return
    warnings.warn(f"{scene_infos[k].path} (image {k + 1} of {len(ratios)}): exposed "
                  f"{ratios[k] / np.median(ratios):.3g}x the scene's usual exposure (EXIF); "
                  "with calibrated lights every image needs the same exposure (or "
                  "--light-intensities that include it), or the normals are biased",
                  ExposureWarning, stacklevel=3)


def check_exposures(scene_infos, gauge_infos) -> np.ndarray | None:
    """Warn when the headers say scene and gauge were exposed differently;
    return each scene image's exposure over its gauge image's (or None)."""
    ratios = relative_exposures(scene_infos, gauge_infos)
    if ratios is None:
        return None
    shown = ", ".join(f"{r:.3g}" for r in ratios)
    k = _furthest_off(ratios)
    if k is not None:
        warnings.warn(f"{scene_infos[k].path}: scene and gauge were exposed differently "
                      f"under different lights (scene / gauge exposure per image, from "
                      f"EXIF: {shown}); each light's scene and gauge photos need the same "
                      "exposure, or the normals are biased", ExposureWarning, stacklevel=3)
    elif abs(np.log(np.median(ratios))) > np.log1p(EXPOSURE_TOLERANCE):
        factor = float(np.median(ratios))
        warnings.warn(f"{scene_infos[0].path}: the scene was exposed {factor:.3g}x the gauge "
                      f"(EXIF); the albedo, relative to the gauge's, comes out multiplied by "
                      f"{factor:.3g}: divide it, or photograph both alike", ExposureWarning,
                      stacklevel=3)
    return ratios
