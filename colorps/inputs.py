"""The files of one capture: what ``colorps reconstruct`` is given to read.

:class:`CaptureFiles` names the scene images, and either the gauge images and
their sphere or a light file, with the mask and the gauge's albedo. It only
names and checks the combination; :func:`colorps.pipeline.reconstruct_files`
reads them.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Sequence
from dataclasses import dataclass

from .camera import Camera, exif_camera
from .errors import CameraWarning, InputError
from .gauge import DEFAULT_ALBEDO, DEFAULT_VIRTUAL_RADIUS

__all__ = ["CaptureFiles"]


@dataclass(frozen=True)
class CaptureFiles:
    """The inputs of one reconstruction, as files.

    Attributes
    ----------
    scene : str or sequence of str
        Scene images: globs, paths or ``@list.txt`` files
        (:func:`colorps.io.expand_paths`), in natural order.
    gauge : str or sequence of str, optional
        Gauge images under the same lights, paired with the scene's in order.
    sphere : "auto" or (cx, cy, r), optional
        The gauge sphere in gauge-image pixels, or found with
        :func:`colorps.find_sphere` ("auto", the default with gauge images).
    camera : Camera, "auto" or None, optional
        The pinhole camera of the images (:mod:`colorps.camera`); None or
        "orthographic": orthographic; "auto" (the default): the camera the
        images' EXIF records (:meth:`with_exif_camera`), else orthographic.
    mask : str or Path, optional
        Scene mask image (non-zero = solve).
    lights, light_intensities : str or Path, optional
        A light file (:func:`colorps.read_lights`) instead of gauge images: the
        gauge is rendered (:mod:`colorps.virtual`).
    gauge_albedo : float or sequence of float
        Albedo of the gauge, one value or one per band.
    virtual_radius : float
        Radius (pixels) of the rendered gauge, with ``lights``.

    Examples
    --------
    >>> from colorps.inputs import CaptureFiles
    >>> CaptureFiles("scene_*.exr", gauge="gauge_*.exr").sphere
    'auto'
    """

    scene: str | Sequence[str]
    gauge: str | Sequence[str] | None = None
    sphere: object = None
    camera: Camera | str | None = "auto"
    mask: object = None
    lights: object = None
    light_intensities: object = None
    gauge_albedo: object = DEFAULT_ALBEDO
    virtual_radius: float = DEFAULT_VIRTUAL_RADIUS

    def __post_init__(self) -> None:
        if self.camera == "orthographic":
            object.__setattr__(self, "camera", None)
        if isinstance(self.camera, str) and self.camera != "auto":
            raise InputError(f"camera: a Camera, 'auto' or 'orthographic', got {self.camera!r}")
        if (self.gauge is None) == (self.lights is None):
            raise InputError("give either gauge images (and their sphere) or a light file")
        if self.gauge is not None and self.sphere is None:
            object.__setattr__(self, "sphere", "auto")
        if self.lights is None and self.light_intensities is not None:
            raise InputError("light intensities go with a light file (--lights)")

    def with_exif_camera(self, infos) -> CaptureFiles:
        """These inputs with "auto" replaced by the camera the EXIF of the first of
        ``infos`` (:class:`colorps.io.ImageInfo`: the first gauge image, the first
        scene image) records (:func:`colorps.camera.exif_camera`; said by a
        CameraWarning), else by None (orthographic); None too when the images
        differ in size (one stack was cropped: its principal point is not known)."""
        if self.camera != "auto":
            return self
        sizes = {(info.width, info.height) for info in infos}
        camera = None if len(sizes) > 1 else next(
            filter(None, (exif_camera(info.path) for info in infos)), None)
        if camera is not None:
            warnings.warn(f"no --camera: the camera of the images' EXIF, a focal length of "
                          f"{camera.focal:.0f} px ({camera.source}); give --camera when they "
                          "were cropped, or 'orthographic'", CameraWarning, stacklevel=2)
        return dataclasses.replace(self, camera=camera)
