"""Relit images: the recovered object under new distant lights.

Each image is, per band, the albedo times the light's intensity times the
finish's shading: Lambertian, max(0, n . l), or the finish a run with calibrated
lights fitted (:class:`colorps.brdf.BRDF`: a diffuse falloff and a Blinn-Phong
highlight, view along +z), linear, from ``normal.exr`` and ``albedo.exr`` of a
results folder (black where a pixel is not solved). The viewer (index.html)
draws the same in the browser.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np

from .brdf import BRDF
from .errors import InputError
from .io import read_image, srgb_encode, write_image
from .lights import read_lights
from .outputs import write_folder

__all__ = ["FINISHES", "RELIT_FORMATS", "relight", "relight_files"]

#: File formats of relit images: 8-bit sRGB PNG, or linear float EXR.
RELIT_FORMATS = ("png", "exr")
#: Finishes relit images are shaded with: Lambertian, or the one a run fitted.
FINISHES = ("lambert", "fitted")


def relight(normals, albedo, direction, intensity=1.0, brdf: BRDF | None = None
            ) -> np.ndarray:
    """The object under one distant light.

    Parameters
    ----------
    normals : (H, W, 3) array_like
        Camera-space unit normals (NaN where not solved).
    albedo : (H, W, c) array_like
        Linear albedo.
    direction : (3,) array_like
        Towards the light, camera space (normalised here).
    intensity : float or (c,) array_like, optional
        The light's linear intensity per band.
    brdf : BRDF, optional
        The finish; default Lambertian.

    Returns
    -------
    (H, W, c) ndarray of float32
        Linear values; 0 where not solved.

    Examples
    --------
    >>> import numpy as np
    >>> n = np.array([[[0.0, 0.0, 1.0], [0.6, 0.0, 0.8]]])
    >>> relight(n, np.full((1, 2, 1), 0.5), [0.0, 0.0, 1.0])[..., 0].astype(float).round(3).tolist()
    [[0.5, 0.4]]
    """
    light = np.asarray(direction, dtype=np.float64)
    light = light / np.linalg.norm(light)
    n = np.asarray(normals, dtype=np.float32)
    albedo = np.asarray(albedo, dtype=np.float32)
    if brdf is None or brdf.is_lambert:
        image = albedo * np.maximum(n @ light.astype(np.float32), 0.0)[..., None]
    else:  # (a white highlight does not scale with the albedo)
        c = albedo.shape[-1]
        solved = np.isfinite(n).all(axis=-1) & np.isfinite(albedo).all(axis=-1)
        image = np.zeros((*n.shape[:2], c), dtype=np.float32)
        image[solved] = brdf.shade(n[solved], light[None], np.ones((1, c)),
                                   albedo=albedo[solved].astype(np.float64))[0]
    image = image * np.asarray(intensity, dtype=np.float32)
    return np.where(np.isfinite(image), image, np.float32(0.0)).astype(np.float32)


def relight_files(results, lights, out, *, intensities=None,
                  file_format: Literal["png", "exr"] = "png", finish: str = "lambert",
                  overwrite: bool = False) -> list[Path]:
    """Write relit images of a results folder, one per light of a light file.

    Parameters
    ----------
    results : str or Path
        A results folder (its normal.exr and albedo.exr are read).
    lights : str or Path
        A light file (see :func:`colorps.lights.read_lights`).
    out : str or Path
        Folder for relit_001, relit_002, ... (written all together or not at all).
    intensities : str or Path, optional
        A light intensities file.
    file_format : {"png", "exr"}, optional
        8-bit sRGB PNG (clipped at 1), or linear float EXR.
    finish : {"lambert", "fitted"}, optional
        "fitted": the finish the run fitted (report.json's ``brdf``, a run with
        calibrated lights); refused when the results have none.
    overwrite : bool, optional
        Replace relit images already there.

    Returns
    -------
    list of Path
    """
    if file_format not in RELIT_FORMATS:
        raise InputError(f"format: expected one of {RELIT_FORMATS}, got {file_format!r}")
    folder = Path(results)
    for name in ("normal.exr", "albedo.exr"):
        if not (folder / name).is_file():
            raise InputError(f"{folder / name}: not found; give a colorps results folder")
    normals, _ = read_image(folder / "normal.exr")
    albedo, _ = read_image(folder / "albedo.exr")
    if normals.shape[-1] != 3 or albedo.shape[:2] != normals.shape[:2]:
        raise InputError(f"{folder}: normal.exr and albedo.exr do not form one result "
                         f"(shapes {normals.shape} and {albedo.shape})")
    if finish not in FINISHES:
        raise InputError(f"finish: expected one of {FINISHES}, got {finish!r}")
    brdf = _fitted_finish(folder) if finish == "fitted" else None
    light_set = read_lights(lights, intensities)
    c = albedo.shape[-1]
    if light_set.intensities.shape[1] not in (1, c):
        raise InputError(f"{intensities}: {light_set.intensities.shape[1]} bands per light, "
                         f"but albedo.exr has {c}")

    def writer(k):
        def write(path):
            image = relight(normals, albedo, light_set.directions[k], light_set.intensities[k],
                            brdf)
            if file_format == "png":
                return write_image(path, srgb_encode(np.clip(image, 0.0, 1.0)), dtype="uint8")
            return write_image(path, image)
        return write

    digits = max(3, len(str(light_set.images)))
    writers = {f"relit_{k + 1:0{digits}d}.{file_format}": writer(k)
               for k in range(light_set.images)}
    return write_folder(out, writers, overwrite=overwrite)


def _fitted_finish(folder: Path) -> BRDF:
    """The finish recorded in a results folder's report.json."""
    import json

    try:
        record = json.loads((folder / "report.json").read_text()).get("brdf")
    except (OSError, ValueError) as exc:
        raise InputError(f"{folder / 'report.json'}: cannot read it ({exc})") from None
    if not record:
        raise InputError(f"{folder / 'report.json'}: records no fitted finish (only a run "
                         "with --lights and --brdf fitted has one); use --finish lambert")
    return BRDF.from_dict(record)
