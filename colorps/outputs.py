"""Write a reconstruction to an output folder, all files or none.

==============  ==============================================================
file            content
==============  ==============================================================
normal.exr      float32 camera-space unit normals, channels X, Y, Z; NaN where
                not solved
normal.png      8-bit preview (n + 1) / 2 in R, G, B; black where not solved
albedo.exr      float32 linear albedo, one channel per input band (input names)
albedo.png      sRGB preview (colour-science), black where not solved
quality.exr     float32 match distance (signature units); NaN where not solved
invalid.png     why pixels are not solved, one colour per reason: black solved,
                grey background, blue too dark, yellow clipped, magenta
                invalid value (NaN, Inf, negative), red no good match
report.json     inputs, parameters, statistics, pixels by reason
height.exr      float32 height in pixels (see :mod:`colorps.integrate`), optional
relief.png      shaded relief of the height map, optional
overview.png    scene, normals, albedo and relief side by side, optional
mesh.ply/.obj   triangle mesh of the height field with albedo vertex colours,
                optional
==============  ==============================================================

Files are first written to a temporary folder inside the output folder and only
moved into place once all of them were written, so a failed or interrupted run
leaves no half-written result.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Sequence

import numpy as np

from .errors import OutputError
from .figures import as_rgb
from .io import srgb_encode, write_image
from .reconstruct import REASONS, Reconstruction

__all__ = ["OUTPUT_FILES", "OPTIONAL_FILES", "prepare_output_dir", "save_reconstruction"]

OUTPUT_FILES = ("normal.exr", "normal.png", "albedo.exr", "albedo.png", "quality.exr",
                "invalid.png", "report.json")
#: Colours of invalid.png, by reason code (see colorps.reconstruct.REASONS).
REASON_COLOURS = {0: (0, 0, 0), 1: (64, 64, 64), 2: (40, 90, 255), 3: (255, 220, 0),
                  4: (255, 0, 255), 5: (255, 40, 40)}
#: Written when asked for (height maps are on by default in the CLI).
OPTIONAL_FILES = ("height.exr", "relief.png", "overview.png", "mesh.ply", "mesh.obj")


def prepare_output_dir(out_dir, *, overwrite: bool = False,
                       files: Sequence[str] = OUTPUT_FILES + OPTIONAL_FILES,
                       create: bool = False) -> Path:
    """Check an output folder before any work is done (and create it if asked).

    Without ``create`` nothing is made: a missing folder only needs its nearest
    existing parent to be a writable folder, so a run that fails later leaves
    no trace.

    Raises
    ------
    OutputError
        The path is a file, cannot be created or written, or already holds
        results and ``overwrite`` is false.
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: output path exists and is not a folder")
    if out.is_dir():
        if not os.access(out, os.W_OK | os.X_OK):
            raise OutputError(f"{out}: output folder is not writable")
        existing = [name for name in files if (out / name).exists()]
        if existing and not overwrite:
            raise OutputError(f"{out}: already holds results ({', '.join(existing)}); "
                              "use --overwrite to replace them")
    else:
        parent = out.absolute().parent
        while not parent.exists():
            parent = parent.parent
        if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
            raise OutputError(f"{out}: cannot create output folder ({parent} is not a "
                              "writable folder)")
    if create:
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise OutputError(f"{out}: cannot create output folder ({exc.strerror})") from None
    return out


def save_reconstruction(result: Reconstruction, out_dir, *,
                        channel_names: Sequence[str] | None = None,
                        report: dict | None = None, overwrite: bool = False,
                        extra_files: dict | None = None) -> list[Path]:
    """Write all output files of a reconstruction (see the module docstring).

    Parameters
    ----------
    result : Reconstruction
    out_dir : str or Path
    channel_names : sequence of str, optional
        Names of the input bands (default R, G, B or Y / B0, B1, ...).
    report : dict, optional
        Inputs and parameters to record in report.json beside the statistics.
    overwrite : bool, optional
        Replace existing results.
    extra_files : dict, optional
        More ``{file name: writer}`` to write in the same transaction; each
        ``writer(path)`` writes one file (e.g. the height map, a mesh).

    Returns
    -------
    list of Path
        The files written.
    """
    out = prepare_output_dir(out_dir, overwrite=overwrite, create=True)
    c = result.albedo.shape[-1]
    if channel_names is None:
        channel_names = {1: ["Y"], 3: ["R", "G", "B"]}.get(c, [f"B{k}" for k in range(c)])
    normal_png = np.where(result.solved[..., None], (result.normals + 1) / 2, 0.0)
    albedo_png = srgb_encode(as_rgb(np.where(result.solved[..., None], result.albedo, 0.0)))
    doc = dict(report or {})
    doc["statistics"] = result.stats
    doc["reasons"] = {str(k): v for k, v in REASONS.items()}
    doc["conventions"] = ("camera-space normals: x right, y up, z towards the camera; "
                          "pixel (x, y) = (column, row); linear values")
    doc["files"] = list(OUTPUT_FILES) + sorted(extra_files or {})
    try:
        tmp = Path(tempfile.mkdtemp(prefix=".colorps-", dir=out))
    except OSError as exc:
        raise OutputError(f"{out}: cannot write ({exc.strerror})") from None
    try:
        write_image(tmp / "normal.exr", result.normals, channel_names=["X", "Y", "Z"])
        write_image(tmp / "normal.png", normal_png, dtype="uint8")
        write_image(tmp / "albedo.exr", result.albedo, channel_names=list(channel_names))
        write_image(tmp / "albedo.png", albedo_png, dtype="uint8")
        write_image(tmp / "quality.exr", result.quality, channel_names=["Q"])
        write_image(tmp / "invalid.png", _reason_picture(result.reason), dtype="uint8")
        for name, writer in (extra_files or {}).items():
            writer(tmp / name)
        (tmp / "report.json").write_text(json.dumps(doc, indent=2, default=_jsonable))
        written = []
        for name in doc["files"]:
            os.replace(tmp / name, out / name)
            written.append(out / name)
        return written
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _reason_picture(reason: np.ndarray) -> np.ndarray:
    table = np.zeros((256, 3), dtype=np.float32)
    for code, rgb in REASON_COLOURS.items():
        table[code] = np.array(rgb) / 255.0
    return table[reason]


def _jsonable(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value)}")
