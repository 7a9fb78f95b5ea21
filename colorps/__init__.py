"""colorps: gauge-based multichannel (colour) photometric stereo.

Conventions: pixel (x, y) = (column, row); camera-space normals with x right,
y up, z towards the camera; all arithmetic on linear pixel values.
"""

from importlib.metadata import PackageNotFoundError, version

from .errors import ColorPSError, GaugeError, ImageReadError, InputError, OutputError
from . import synth
from .gauge import Gauge, find_sphere
from .grid import BucketGrid, QueryStats
from .integrate import integrate, weights_from_quality
from .reconstruct import Reconstruction, reconstruct
from .signatures import SignatureSet, compute_signatures, luminance

try:
    __version__ = version("colorps")
except PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0+unknown"

__all__ = [
    "BucketGrid", "QueryStats", "Gauge", "find_sphere", "Reconstruction", "reconstruct",
    "synth", "integrate", "weights_from_quality", "SignatureSet", "compute_signatures", "luminance",
    "ColorPSError", "GaugeError", "ImageReadError", "InputError", "OutputError",
    "__version__",
]
