"""One exception hierarchy for everything colorps refuses to do.

Every error a user can cause derives from :class:`ColorPSError`, so a caller
can catch them all at once, and the CLI turns them into a one-line message and
a non-zero exit code instead of a traceback.
"""

__all__ = ["ColorPSError", "InputError", "ImageReadError", "GaugeError", "OutputError"]


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
