"""The camera: orthographic, or a pinhole of known intrinsics (given, or read from EXIF).

A pinhole camera of focal lengths (fx, fy) and principal point (px, py), all in
pixels, sees the pixel (x, y) along the ray ::

    d = ((x - px) / fx, -(y - py) / fy, -1),  normalised

in colorps's camera space (x right, y up, z towards the camera: the camera looks
along -z). Under it a sphere's image is an ellipse, not a circle, and its
normals are not the orthographic formula's: :func:`colorps.geometry.sphere_normals`
takes a camera and intersects each pixel's ray with the sphere.

``--camera`` gives it as a focal length in pixels (principal point at the image
centre), a DiLiGenT-style ``K.txt`` (the 3 x 3 intrinsic matrix, one row per
line: ``fx 0 px`` / ``0 fy py`` / ``0 0 1``), or a JSON file
(``{"fx": .., "fy": .., "px": .., "py": ..}``, or ``{"K": [[...], [...], [...]]}``).
Without it (``--camera auto``) the camera is the one the photographs' EXIF
records (:func:`exif_camera`), else orthographic.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import InputError

__all__ = ["CROP_ASPECT", "EXIF_FOCAL_RANGE", "FOCAL_PLANE_UNIT_MM", "FRAME_35MM_DIAGONAL_MM",
           "Camera", "exif_camera", "read_camera"]

#: Millimetres per unit of EXIF's FocalPlaneResolutionUnit (2: inch, 3: cm,
#: 4: mm, 5: micrometre).
FOCAL_PLANE_UNIT_MM = {2: 25.4, 3: 10.0, 4: 1.0, 5: 1e-3}
#: The diagonal (mm) of the 36 x 24 mm frame of EXIF's FocalLengthIn35mmFilm.
FRAME_35MM_DIAGONAL_MM = float(np.hypot(36.0, 24.0))
#: An image whose width over height differs by more than this share from the
#: one its EXIF records (PixelXDimension, PixelYDimension) was cropped.
CROP_ASPECT = 0.01
#: A focal length from EXIF is taken between these multiples of the image's
#: diagonal (a 10 mm fisheye to a 2000 mm lens on a full frame); else it is not
#: a camera's.
EXIF_FOCAL_RANGE = (0.2, 50.0)


@dataclass(frozen=True)
class Camera:
    """A pinhole camera's intrinsics, pixels.

    Attributes
    ----------
    fx, fy : float
        Focal lengths (pixels).
    px, py : float or None
        Principal point (pixel coordinates); None: the centre of the image it
        is used with.
    source : str or None
        Where it came from, when not given (:func:`exif_camera`).
    """

    fx: float
    fy: float
    px: float | None = None
    py: float | None = None
    source: str | None = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        for name in ("fx", "fy"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise InputError(f"camera: {name} must be a focal length > 0 in pixels, "
                                 f"got {value!r}")

    @property
    def focal(self) -> float:
        """The mean focal length (fx + fy) / 2, pixels: the scale of angles at
        the principal point."""
        return (self.fx + self.fy) / 2.0

    def principal(self, shape: tuple[int, int]) -> tuple[float, float]:
        """(px, py) for an image of ``shape`` (H, W)."""
        h, w = shape
        return (float((w - 1) / 2 if self.px is None else self.px),
                float((h - 1) / 2 if self.py is None else self.py))

    def rays(self, x, y, shape: tuple[int, int]) -> np.ndarray:
        """Unit rays (..., 3) into the scene through pixel coordinates (x, y)."""
        px, py = self.principal(shape)
        x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
        d = np.stack([(x - px) / self.fx, -(y - py) / self.fy, -np.ones_like(x)], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def as_dict(self) -> dict:
        record = dict(model="pinhole", fx=self.fx, fy=self.fy, px=self.px, py=self.py)
        return record if self.source is None else dict(record, source=self.source)


def exif_camera(path) -> Camera | None:
    """The pinhole camera an image file's EXIF records, or None when it records none.

    The focal length in pixels is EXIF's FocalLength (mm) times its
    FocalPlaneXResolution (pixels per FocalPlaneResolutionUnit), scaled by the
    image's width over the width EXIF's PixelXDimension records (a converter's
    resize); else its FocalLengthIn35mmFilm times the image's diagonal over the
    35 mm frame's. The principal point is the image's centre. A crop to
    another shape than the one EXIF's PixelXDimension and PixelYDimension
    record gives None; a crop to the same shape is taken for a resize: give
    ``--camera`` for cropped photographs.

    Parameters
    ----------
    path : str or Path
        An image file (its header is read).

    Returns
    -------
    Camera or None
        With ``source`` saying which tags gave it.
    """
    import OpenImageIO as oiio

    image = oiio.ImageInput.open(str(path))
    if image is None:
        return None
    try:
        spec = image.spec()
        tags = {name: spec.getattribute(f"Exif:{name}") for name in (
            "FocalLength", "FocalPlaneXResolution", "FocalPlaneResolutionUnit",
            "PixelXDimension", "PixelYDimension", "FocalLengthIn35mmFilm")}
        width, height = int(spec.width), int(spec.height)
    finally:
        image.close()
    tags = {k: float(v) for k, v in tags.items() if isinstance(v, (int, float)) and v > 0}
    if {"PixelXDimension", "PixelYDimension"} <= set(tags):  # cropped: another shape
        shot = tags["PixelXDimension"] / tags["PixelYDimension"]
        if min(abs(width / height / aspect - 1) for aspect in (shot, 1 / shot)) > CROP_ASPECT:
            return None
    unit = FOCAL_PLANE_UNIT_MM.get(int(tags.get("FocalPlaneResolutionUnit", 0)))
    if {"FocalLength", "FocalPlaneXResolution"} <= set(tags) and unit:
        resized = width / tags.get("PixelXDimension", width)
        focal = tags["FocalLength"] * tags["FocalPlaneXResolution"] / unit * resized
        how = (f"FocalLength {tags['FocalLength']:g} mm x FocalPlaneXResolution "
               f"{tags['FocalPlaneXResolution'] / unit:g} px/mm" +
               (f" x {resized:.4g} (resized)" if resized != 1 else ""))
    elif "FocalLengthIn35mmFilm" in tags:
        focal = tags["FocalLengthIn35mmFilm"] * np.hypot(width, height) / FRAME_35MM_DIAGONAL_MM
        how = f"FocalLengthIn35mmFilm {tags['FocalLengthIn35mmFilm']:g} mm"
    else:
        return None
    low, high = EXIF_FOCAL_RANGE
    if not low <= focal / np.hypot(width, height) <= high:
        return None
    return Camera(float(focal), float(focal), source=f"EXIF of {Path(path).name}: {how}")


def read_camera(spec) -> Camera | str | None:
    """A Camera from ``--camera``'s text: a focal length in pixels, or a file.

    Parameters
    ----------
    spec : str, Path, float or None
        None or "orthographic": no camera (orthographic view). "auto": returned
        as it is (the files' EXIF camera, :func:`exif_camera`, once they are
        known). A number: the focal length in pixels (principal point at the image centre). A path:
        a ``K.txt`` (3 x 3 matrix) or a ``.json`` file (see the module docstring).

    Examples
    --------
    >>> from colorps.camera import read_camera
    >>> read_camera("3700")
    Camera(fx=3700.0, fy=3700.0, px=None, py=None)
    """
    if spec is None or spec == "orthographic":
        return None
    if spec == "auto":
        return "auto"
    if isinstance(spec, (int, float)) or _is_number(spec):
        f = float(spec)
        return Camera(f, f)
    path = Path(spec)
    if not path.is_file():
        raise InputError(f"{path}: no such camera file (give a focal length in pixels, a "
                         "K.txt or a .json)")
    text = path.read_text(errors="replace")
    if path.suffix.lower() == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as error:
            raise InputError(f"{path}: not valid JSON ({error})") from None
        if isinstance(data, dict) and "K" in data:
            return _from_matrix(data["K"], path)
        if isinstance(data, dict) and {"fx", "fy"} <= set(data):
            try:
                return Camera(float(data["fx"]), float(data["fy"]),
                              None if data.get("px") is None else float(data["px"]),
                              None if data.get("py") is None else float(data["py"]))
            except (TypeError, ValueError):
                raise InputError(f"{path}: fx, fy, px and py must be numbers") from None
        raise InputError(f"{path}: a camera JSON holds fx and fy (and px, py), or K")
    try:
        rows = [[float(v) for v in line.replace(",", " ").split()]
                for line in text.splitlines() if line.strip()]
    except ValueError:
        raise InputError(f"{path}: a K.txt holds a 3 x 3 matrix of numbers") from None
    return _from_matrix(rows, path)


def _from_matrix(rows, path: Path) -> Camera:
    """A Camera from a 3 x 3 intrinsic matrix (zero skew)."""
    try:
        k = np.asarray(rows, dtype=np.float64)
    except (TypeError, ValueError):  # ragged rows, or not numbers
        k = None
    if k is None or k.shape != (3, 3):
        raise InputError(f"{path}: the intrinsic matrix K must be 3 x 3")
    if abs(k[0, 1]) > 1e-9 * abs(k[0, 0]) or not np.allclose(k[2], [0, 0, 1]) or \
            k[1, 0] != 0:
        raise InputError(f"{path}: K must be [[fx, 0, px], [0, fy, py], [0, 0, 1]] "
                         "(no skew)")
    return Camera(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))


def _is_number(text) -> bool:
    try:
        float(text)
    except (TypeError, ValueError):
        return False
    return True
