"""colorps: gauge-based multichannel (colour) photometric stereo.

Conventions: pixel (x, y) = (column, row); camera-space normals with x right,
y up, z towards the camera; all arithmetic on linear pixel values.
"""

from importlib.metadata import PackageNotFoundError, version

from . import light_masks, synth
from .brdf import BRDF
from .errors import (
    ColorPSError,
    ColorPSWarning,
    GaugeError,
    ImageReadError,
    InputError,
    OutputError,
)
from .gauge import Gauge, find_sphere
from .geometry import angular_error, sphere_normals
from .grid import BucketGrid, QueryStats
from .integrate import integrate, weights_from_quality
from .lights import Lights, read_lights, write_lights
from .options import Options
from .reasons import Reason
from .reconstruct import reconstruct
from .resolve import Resolved, StackModel, resolve
from .results import Reconstruction, ReconstructionStats
from .signatures import SignatureSet, compute_signatures, luminance
from .tables import GaugeTables
from .virtual import fit_scene_brdf

try:
    __version__ = version("colorps")
except PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0+unknown"

__all__ = [
    "BRDF",
    "BucketGrid",
    "ColorPSError",
    "ColorPSWarning",
    "Gauge",
    "GaugeError",
    "GaugeTables",
    "ImageReadError",
    "InputError",
    "Lights",
    "Options",
    "OutputError",
    "QueryStats",
    "Reason",
    "Reconstruction",
    "ReconstructionStats",
    "Resolved",
    "SignatureSet",
    "StackModel",
    "__version__",
    "angular_error",
    "compute_signatures",
    "find_sphere",
    "fit_scene_brdf",
    "integrate",
    "light_masks",
    "luminance",
    "read_lights",
    "reconstruct",
    "resolve",
    "sphere_normals",
    "synth",
    "weights_from_quality",
    "write_lights",
]
