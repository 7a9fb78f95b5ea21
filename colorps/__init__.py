"""colorps: gauge-based multichannel (colour) photometric stereo.

Conventions: pixel (x, y) = (column, row); camera-space normals with x right,
y up, z towards the camera; all arithmetic on linear pixel values.
"""

from importlib.metadata import PackageNotFoundError, version

from .errors import ColorPSError, GaugeError, ImageReadError, InputError, OutputError
from . import light_masks, synth
from .brdf import BRDF, fit_scene_brdf
from .gauge import Gauge, find_sphere
from .geometry import angular_error, sphere_normals
from .grid import BucketGrid, QueryStats
from .integrate import integrate, weights_from_quality
from .lights import Lights, read_lights, write_lights
from .matching import GaugeTables
from .options import Options
from .reasons import Reason
from .reconstruct import Reconstruction, ReconstructionStats, reconstruct
from .signatures import SignatureSet, compute_signatures, luminance

try:
    __version__ = version("colorps")
except PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0+unknown"

__all__ = [
    "reconstruct", "Options", "Reconstruction", "ReconstructionStats", "Reason",
    "Gauge", "find_sphere", "BRDF", "fit_scene_brdf", "light_masks", "Lights", "read_lights",
    "write_lights", "BucketGrid", "QueryStats", "GaugeTables",
    "SignatureSet", "compute_signatures", "luminance",
    "integrate", "weights_from_quality", "angular_error", "sphere_normals", "synth",
    "ColorPSError", "GaugeError", "ImageReadError", "InputError", "OutputError",
    "__version__",
]
