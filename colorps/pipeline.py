"""Files in, files out: the work behind ``colorps reconstruct`` and ``colorps integrate``.

These functions read image files, call the array API (:func:`colorps.reconstruct`,
:func:`colorps.integrate`) and write the results. The command line only parses
arguments and calls them.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Literal, Sequence

import numpy as np

from . import __version__
from .errors import InputError, OutputError

__all__ = ["reconstruct_files", "integrate_file", "read_mask"]


def read_mask(path, shape) -> np.ndarray:
    """A mask image (non-zero = inside, first channel) of the given (H, W)."""
    from .io import read_image

    image, _ = read_image(path, "linear")
    if image.shape[:2] != tuple(shape):
        raise InputError(f"{path}: mask is {image.shape[1]}x{image.shape[0]} but the images "
                         f"are {shape[1]}x{shape[0]}")
    return image[..., 0] > 0.5


def _mesh_writer(height, colours):
    from .mesh import height_mesh, write_mesh

    return lambda path: write_mesh(height_mesh(height, colours), path)


def reconstruct_files(scene_patterns: str | Sequence[str], gauge_patterns: str | Sequence[str],
                      sphere, out, *, gauge_albedo=1.0, mode: str = "colour", band=None,
                      mask_path=None, threads: int | None = None, grid_n=None,
                      encoding: str = "auto", clip_level: float | None | str = "auto",
                      dark_level: float | str = "auto", max_distance: float | None = 0.1,
                      height: bool = True, mesh: Literal["ply", "obj", "both"] | None = None,
                      overwrite: bool = False, progress: bool = True):
    """Read scene and gauge stacks, reconstruct, and write the output folder.

    Parameters
    ----------
    scene_patterns, gauge_patterns : str or sequence of str
        Globs, paths or ``@list.txt`` files (see :func:`colorps.io.expand_paths`),
        paired in natural order.
    sphere : "auto" or (cx, cy, r)
        Gauge sphere in gauge-image pixels, or found with :func:`colorps.find_sphere`.
    out : str or Path
        Output folder (see :mod:`colorps.outputs` for the files).
    clip_level : float, None or "auto"
        "auto" derives it from the scene files' bit depth (see
        :func:`colorps.io.input_levels`); None clips nothing.
    dark_level : float or "auto"
        Noise floor of one measurement (linear); bands whose OV norm is below
        ``dark_level * sqrt(m)`` are too dark.
    height : bool
        Also write height.exr, relief.png and overview.png.
    mesh : {"ply", "obj", "both"}, optional
        Also write a mesh of the height field (needs ``height``).

    Other parameters are those of :func:`colorps.reconstruct`.

    Returns
    -------
    Reconstruction
    """
    from .gauge import Gauge, find_sphere
    from .io import expand_paths, input_levels, read_stack
    from .outputs import prepare_output_dir, save_reconstruction
    from .reconstruct import reconstruct

    if mesh and not height:
        raise InputError("--mesh needs the height map; drop --no-height")
    if band is not None and band != "luminance":
        try:
            band = int(band)
        except ValueError:
            raise InputError(f"--band: expected 'luminance' or a channel index, "
                             f"got {band!r}") from None
    prepare_output_dir(out, overwrite=overwrite)  # fail before the long work
    scene_paths = expand_paths(scene_patterns, name="--scene")
    gauge_paths = expand_paths(gauge_patterns, name="--gauge")
    if len(scene_paths) != len(gauge_paths):
        raise InputError(f"--scene gives {len(scene_paths)} images but --gauge gives "
                         f"{len(gauge_paths)}; they are paired in order")
    scene, names = read_stack(scene_paths, encoding, name="scene", progress=progress)
    gauge_stack, _ = read_stack(gauge_paths, encoding, name="gauge", progress=progress)
    if gauge_stack.shape[3] != scene.shape[3]:
        raise InputError(f"{gauge_paths[0]}: has {gauge_stack.shape[3]} channel(s) but "
                         f"{scene_paths[0]} has {scene.shape[3]}")
    auto_clip, auto_dark = input_levels(scene_paths[0], encoding)
    clip_level = auto_clip if clip_level == "auto" else clip_level
    dark_level = auto_dark if dark_level == "auto" else dark_level
    found = find_sphere(gauge_stack) if sphere == "auto" else tuple(sphere)
    gauge = Gauge.from_sphere(gauge_stack.shape[1:3], *found, albedo=gauge_albedo)
    scene_mask = None if mask_path is None else read_mask(mask_path, scene.shape[1:3])
    result = reconstruct(scene, gauge_stack, gauge, mode=mode, band=band, mask=scene_mask,
                         grid_n=grid_n, threads=threads, progress=progress,
                         clip_level=clip_level, min_norm=dark_level * np.sqrt(scene.shape[0]),
                         max_distance=max_distance)
    report = dict(
        colorps_version=__version__, scene=[str(p) for p in scene_paths],
        gauge=[str(p) for p in gauge_paths], sphere=dict(zip(("cx", "cy", "r"), found)),
        sphere_found_automatically=sphere == "auto", gauge_albedo=gauge_albedo, mode=mode,
        band=band, mask=None if mask_path is None else str(mask_path), encoding=encoding,
        channels=names, clip_level=clip_level, dark_level=dark_level,
        max_distance=max_distance,
    )
    extra = {}
    if height:
        from .figures import overview, shaded_relief
        from .integrate import integrate, weights_from_quality
        from .io import write_image

        t0 = time.perf_counter()
        z = integrate(result.normals, result.solved,
                      weights=weights_from_quality(result.quality))
        result.stats["seconds"]["integration"] = time.perf_counter() - t0
        result.height = z
        figure = overview(scene.mean(axis=0), result.normals, result.albedo, z,
                          title=f"colorps {mode} mode: {result.stats['solved']} pixels solved")
        extra["height.exr"] = lambda p: write_image(p, z, channel_names=["Z"])
        extra["relief.png"] = lambda p: write_image(p, shaded_relief(z), dtype="uint8")
        extra["overview.png"] = lambda p: write_image(p, figure, dtype="uint8")
        for kind in ("ply", "obj") if mesh == "both" else (mesh,) if mesh else ():
            extra[f"mesh.{kind}"] = _mesh_writer(z, result.albedo)
    save_reconstruction(result, out, channel_names=names, report=report, overwrite=overwrite,
                        extra_files=extra)
    return result


def integrate_file(normals_path, out, *, mask_path=None, weights_path=None,
                   method: Literal["poisson", "dct"] = "poisson", mesh=None,
                   overwrite: bool = False) -> np.ndarray:
    """Integrate a normal-map file into a height-map file (and optionally a mesh).

    Parameters
    ----------
    normals_path : str or Path
        Normal map with X, Y, Z in its first three channels (e.g. normal.exr).
    out : str or Path
        Height map to write (.exr).
    mask_path, weights_path : str or Path, optional
        Mask image; quality map of a reconstruction (see
        :func:`colorps.weights_from_quality`).
    method : {"poisson", "dct"}
    mesh : str or Path, optional
        Also write a mesh (.ply or .obj).

    Returns
    -------
    (H, W) ndarray
        The height map.
    """
    from .integrate import integrate, weights_from_quality
    from .io import read_image, write_image

    if Path(out).suffix.lower() != ".exr":
        raise InputError(f"--out {out}: the height map is written as OpenEXR (.exr)")
    for target in [Path(out)] + ([Path(mesh)] if mesh else []):
        if target.exists() and not overwrite:
            raise OutputError(f"{target}: already exists; use --overwrite to replace it")
        if not target.parent.is_dir():
            raise OutputError(f"{target.parent}: output folder does not exist")
    normals, _ = read_image(normals_path, "linear")
    if normals.shape[2] < 3:
        raise InputError(f"{normals_path}: a normal map needs 3 channels (X, Y, Z), "
                         f"got {normals.shape[2]}")
    normals = normals[..., :3]
    mask = None if mask_path is None else read_mask(mask_path, normals.shape[:2])
    weights = None
    if weights_path is not None:
        quality, _ = read_image(weights_path, "linear")
        if quality.shape[:2] != normals.shape[:2]:
            raise InputError(f"{weights_path}: size differs from {normals_path}")
        weights = weights_from_quality(quality[..., 0])
    z = integrate(normals, mask, weights=weights, method=method)
    if mesh:
        _mesh_writer(z, None)(mesh)
    write_image(out, z, channel_names=["Z"])
    return z
