"""One exception hierarchy for everything colorps refuses to do, one for its warnings.

Every error a user can cause derives from :class:`ColorPSError`, so a caller
can catch them all at once, and the CLI turns them into a one-line message and
a non-zero exit code instead of a traceback.
"""

__all__ = [
    "CameraWarning",
    "ColorPSError",
    "ColorPSWarning",
    "EncodingWarning",
    "ExposureWarning",
    "GaugeError",
    "GaugeWarning",
    "ImageReadError",
    "InputError",
    "InterreflectionWarning",
    "LightAxesWarning",
    "LossyInputWarning",
    "LowSolvedWarning",
    "OutputError",
    "PairingWarning",
]


class ColorPSError(Exception):
    """Base class of all errors raised by colorps for bad input or settings."""


class InputError(ColorPSError, ValueError):
    """An argument has the wrong shape, type or value."""


class ImageReadError(ColorPSError, OSError):
    """An image file is missing, unreadable or inconsistent with its stack."""


class GaugeError(ColorPSError, ValueError):
    """The gauge (sphere geometry, albedo, circle detection) is unusable."""


class OutputError(ColorPSError, OSError):
    """The output location cannot be written, or would overwrite results."""


class ColorPSWarning(UserWarning):
    """Base class of every warning colorps issues: the run goes on, but a result
    may be less than it looks (filter them all at once with this class)."""


class GaugeWarning(ColorPSWarning):
    """The capture may not fix the normals (gauge losing pixels, too few images)."""


class LowSolvedWarning(ColorPSWarning):
    """Less than ``results.LOW_SOLVED_FRACTION`` of the masked pixels were solved."""


class LossyInputWarning(ColorPSWarning):
    """An input uses lossy compression (JPEG): results will be noisier."""


class PairingWarning(ColorPSWarning):
    """Images and lights may be paired wrongly (order, names)."""


class EncodingWarning(ColorPSWarning):
    """Integer files fit far better decoded the other way (sRGB or linear)."""


class ExposureWarning(ColorPSWarning):
    """Scene and gauge images were exposed differently (their EXIF says so)."""


class InterreflectionWarning(ColorPSWarning):
    """An object that lights itself was solved with its bounced light left in."""


class LightAxesWarning(ColorPSWarning):
    """The light file's x and y look mirrored, swapped or turned (the normals solved
    under it are far less integrable than with that undone)."""


class CameraWarning(ColorPSWarning):
    """The camera was taken from the images' EXIF (no ``--camera`` given)."""
