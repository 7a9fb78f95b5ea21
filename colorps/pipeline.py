"""Files in, files out: the work behind ``colorps reconstruct`` and ``colorps integrate``.

Each function reads in one straight line: check the outputs, read the inputs,
call the array API (:func:`colorps.reconstruct`, :func:`colorps.integrate`),
write the outputs (:mod:`colorps.outputs`). Option values arrive converted
(:class:`~colorps.Options`); the command line only parses arguments.
"""

from __future__ import annotations

import contextlib
import sys
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from typing import Literal, Sequence

import numpy as np

from . import __version__
from .errors import InputError
from .gauge import DEFAULT_ALBEDO
from .options import Options
from .reconstruct import Reconstruction

__all__ = ["reconstruct_files", "integrate_file", "calibrate_lights_files", "dask_client"]

#: A normal map's finite pixels must be unit vectors within this (half-float
#: files store them to about 1e-3), all but MAX_NON_UNIT_FRACTION of them.
UNIT_TOLERANCE = 0.01
MAX_NON_UNIT_FRACTION = 0.01
#: Seconds to wait for a Dask scheduler given by address.
SCHEDULER_TIMEOUT = 10
#: Scene and gauge exposures (EXIF) that differ by more than this fraction,
#: between lights or overall, are warned about (nominal shutter speeds alike
#: compare exactly; a third of a stop is 26 %).
EXPOSURE_TOLERANCE = 0.02


def reconstruct_files(scene_patterns: str | Sequence[str],
                      gauge_patterns: str | Sequence[str] | None,
                      sphere: Literal["auto"] | tuple[float, float, float] | None, out, *,
                      gauge_albedo=DEFAULT_ALBEDO, mask_path=None, options: Options | None = None,
                      lights=None, light_intensities=None, virtual_radius: float = 100.0,
                      overwrite: bool = False, progress: bool = True,
                      scheduler=None) -> Reconstruction:
    """Read scene and gauge stacks, reconstruct, and write the output folder.

    Parameters
    ----------
    scene_patterns, gauge_patterns : str or sequence of str
        Globs, paths or ``@list.txt`` files (see :func:`colorps.io.expand_paths`),
        paired in natural order.
    sphere : "auto" or (cx, cy, r)
        Gauge sphere in gauge-image pixels, or found with :func:`colorps.find_sphere`.
        Both gauge arguments are None when ``lights`` is given.
    out : str or Path
        Output folder (see :mod:`colorps.outputs` for the files).
    gauge_albedo : float or sequence of float, optional
        Albedo of the gauge, one value or one per band.
    mask_path : str or Path, optional
        Scene mask image (non-zero = solve).
    options : Options, optional
        Settings (default ``Options()``); "auto" levels come from the first
        scene file's pixel type (see :func:`colorps.io.input_levels`).
    overwrite : bool, optional
        Replace existing results.
    lights, light_intensities : str or Path, optional
        A light file (:func:`colorps.read_lights`) instead of gauge images: the
        gauge is rendered (:meth:`colorps.Gauge.virtual`, a sphere of
        ``virtual_radius`` pixels with the finish ``options.brdf``: by default
        fitted to the scene, :func:`colorps.brdf.fit_scene_brdf`).
    progress : bool, optional
        Progress bars on reading and matching.
    scheduler : str or dask.distributed.Client, optional
        Run the scene's tiles (``options.tile``, default 256 rows when a
        scheduler is given) on a Dask cluster: a client, a scheduler address,
        or "local" for a local cluster started for this run.

    Returns
    -------
    Reconstruction
        With its height map when ``options.height``.
    """
    from .brdf import BRDF, fit_scene_brdf
    from .figures import overview_step
    from .gauge import Gauge, find_sphere
    from .lights import read_lights
    from .noise import NoiseModel, estimate_noise
    from .integrate import DEFAULT_TILE, integrate, weights_from_quality
    from .io import (check_decoded_size, check_stack_files, expand_paths, input_levels,
                     noise_base, read_image, read_mask, read_stack)
    from .outputs import TILED_EXR_SIDE, prepare_output_dir, save_reconstruction
    from .reconstruct import reconstruct
    from .tiles import (DEFAULT_TILE_ROWS, StackFiles, memory_limit, reconstruct_tiled,
                        release_freed_memory, rows_for_memory)

    options = options or Options()
    prepare_output_dir(out, overwrite=overwrite)  # fail before the long work
    if (lights is None) == (gauge_patterns is None):
        raise InputError("give either gauge images (and their sphere) or a light file")
    scene_paths = expand_paths(scene_patterns, name="scene")
    # Every header first: sizes, channels, pixel types and memory, before any pixel.
    limit = options.max_input_gib * 2 ** 30
    scene_infos = check_stack_files(scene_paths, name="scene")
    scene_info = scene_infos[0]
    limit_gib, limit_source = memory_limit(options.memory_limit_gib)
    why_tiled = None if options.tile is None else f"--tile {options.tile}"
    if options.tile is None and limit_gib is not None:
        options = options.replace(tile=rows_for_memory(
            limit_gib, (len(scene_paths), scene_info.height, scene_info.width,
                        scene_info.channels), source=limit_source))
        if options.tile is not None:
            why_tiled = f"{limit_source} is too small for the whole scene"
    if scheduler is not None and options.tile is None:
        options = options.replace(tile=DEFAULT_TILE_ROWS)
        why_tiled = "--scheduler: tiles are its tasks"
    tiled = options.tile is not None
    if not tiled:
        check_decoded_size(scene_infos, limit, name="scene")
    else:
        # One tile's stack is what is held at a time.
        tile_bytes = 4 * len(scene_paths) * scene_info.channels * scene_info.width * \
            min(options.tile, scene_info.height)
        if tile_bytes > limit:
            raise InputError(f"{scene_paths[0]}: a tile of {options.tile} rows of "
                             f"{len(scene_paths)} images takes {tile_bytes / 2 ** 30:.1f} "
                             f"GiB, more than --max-input-gib {options.max_input_gib:g}; "
                             "use fewer rows (--tile)")
        if lights is not None and "auto" in (options.read_noise, options.gain):
            raise InputError(f"a tiled run ({why_tiled}) with --lights needs "
                             "--read-noise and --gain: the noise of a virtual-gauge run is "
                             "fitted to the whole scene at once")
        if lights is not None and options.brdf == "fitted":
            raise InputError(f"a tiled run ({why_tiled}) with --lights needs "
                             "--brdf lambert: the finish of a virtual-gauge run is fitted to "
                             "the whole scene at once")
    exposures = None
    if lights is not None:
        light_set = read_lights(lights, light_intensities, images=len(scene_paths))
        gauge_paths = []
    else:
        gauge_paths = expand_paths(gauge_patterns, name="gauge")
        if len(scene_paths) != len(gauge_paths):
            raise InputError(f"the scene has {len(scene_paths)} images but the gauge "
                             f"{len(gauge_paths)}; they are paired in order")
        gauge_infos = check_stack_files(gauge_paths, name="gauge", max_bytes=limit)
        gauge_info = gauge_infos[0]
        exposures = _check_exposures(scene_infos, gauge_infos)
        if gauge_info.channels != scene_info.channels:
            raise InputError(f"{gauge_paths[0]}: has {gauge_info.channels} channel(s) but "
                             f"{scene_paths[0]} has {scene_info.channels}")
    mask = None
    if mask_path is not None:
        mask = read_mask(mask_path, (scene_info.height, scene_info.width))
        if not mask.any():
            raise InputError(f"{mask_path}: the mask selects no pixel (non-zero = solve)")
    if tiled:
        if progress:  # a tiled run is slower: say why it is tiled
            from tqdm import tqdm

            tqdm.write(f"colorps: the scene's {scene_info.height} rows in tiles of "
                       f"{options.tile} ({why_tiled})", file=sys.stderr)
        scene = StackFiles(tuple(scene_paths), (len(scene_paths), scene_info.height,
                                                scene_info.width, scene_info.channels),
                           options.encoding)
        names = read_image(scene_paths[0], options.encoding, rows=(0, 1))[1]
    else:
        scene, names = read_stack(scene_paths, options.encoding, name="scene",
                                  progress=progress)
    scene_noise = noise_base(scene_info, options.encoding)
    requested = options  # "auto" levels resolve per stack, from its own files
    options = options.with_levels(*input_levels(scene_info, options.encoding))
    brdf = fit_history = None
    if lights is not None:
        gauge_noise = NoiseModel(read=0.0, gain=0.0)  # rendered: only float rounding
        gauge_levels = options.replace(clip_level=None)
        if "auto" in (options.read_noise, options.gain):
            # A rendered gauge has no scatter to measure: measure the scene's.
            usable = np.isfinite(scene).all(axis=(0, 3)) & (scene > 0).all(axis=(0, 3))
            if mask is not None:
                usable &= mask
            fitted = estimate_noise(scene, usable, scene_noise)
            options = options.replace(
                read_noise=fitted.read if options.read_noise == "auto" else options.read_noise,
                gain=fitted.gain if options.gain == "auto" else options.gain)
        brdf = BRDF.lambert()
        if options.brdf == "fitted":
            brdf, fit_history = fit_scene_brdf(scene, light_set, options, mask=mask,
                                               noise=scene_noise, radius=virtual_radius,
                                               progress=progress)
        gauge = Gauge.virtual(light_set, radius=virtual_radius, bands=scene.shape[3],
                              brdf=brdf)
        gauge_stack, found = gauge.stack, gauge.sphere
    else:
        gauge_stack, _ = read_stack(gauge_paths, options.encoding, name="gauge",
                                    progress=progress)
        # Levels and quantisation belong to each stack's files (checked alike above).
        gauge_levels = requested.with_levels(*input_levels(gauge_info, options.encoding))
        gauge_noise = noise_base(gauge_info, options.encoding)
        found = find_sphere(gauge_stack) if sphere == "auto" else tuple(sphere)
        gauge = Gauge.from_sphere(gauge_stack.shape[1:3], *found, albedo=gauge_albedo)

    levels = (gauge_levels.clip_level, gauge_levels.dark_level)
    if tiled:
        with dask_client(scheduler) as client:
            result, preview = reconstruct_tiled(
                scene, gauge_stack, gauge, options, tile=options.tile, mask=mask,
                noise=scene_noise, gauge_noise=gauge_noise, gauge_levels=levels,
                client=client, progress=progress, return_preview=True)
    else:
        result = reconstruct(scene, gauge_stack, gauge, options, mask=mask,
                             noise=scene_noise, gauge_noise=gauge_noise, gauge_levels=levels,
                             progress=progress)
        step = overview_step(scene.shape[1:3])
        preview = scene[:, ::step, ::step].mean(axis=0)  # what the overview draws
    del scene  # the stack is not needed past here: free it for integration and writing
    _check_solved(result, scene_paths, gauge_paths, mask_path)

    def with_height(result: Reconstruction) -> Reconstruction:
        t0 = time.perf_counter()
        # A tiled run integrates in tiles too (memory of one tile + a coarse level).
        height = integrate(result.normals, result.solved,
                           weights=weights_from_quality(result.quality),
                           tile=DEFAULT_TILE if tiled else None)
        if tiled:
            release_freed_memory()
        return result.with_height(height, time.perf_counter() - t0)

    if options.height and tiled:  # one thing at a time: memory is what counts
        result = with_height(result)

    report = dict(
        colorps_version=__version__, scene=[str(p) for p in scene_paths],
        gauge=[str(p) for p in gauge_paths], sphere=dict(zip(("cx", "cy", "r"), found)),
        sphere_found_automatically=sphere == "auto",
        lights=None if lights is None else str(lights),
        light_intensities=None if light_intensities is None else str(light_intensities),
        virtual_gauge=lights is not None, gauge_albedo=gauge_albedo,
        brdf=None if brdf is None else brdf.as_dict(), brdf_fits=fit_history,
        mask=None if mask_path is None else str(mask_path), channels=names,
        options=options.as_dict(), memory_limit_gib_used=limit_gib,
        tiled_because=why_tiled,
        exposure_scene_over_gauge=None if exposures is None else exposures.tolist(),
        gauge_levels=dict(clip_level=gauge_levels.clip_level,
                          dark_level=gauge_levels.dark_level),
    )
    # An untiled run integrates in a thread while the maps are written (the
    # solver and OpenImageIO's writers release the GIL): the two overlap.
    with ThreadPoolExecutor(max_workers=1) as pool:
        finished = pool.submit(with_height, result) \
            if options.height and result.height is None else None
        save_reconstruction(result, out, channel_names=names, scene_preview=preview,
                            report=report, mesh=options.mesh_kinds, overwrite=overwrite,
                            finished=finished, exr_tile=TILED_EXR_SIDE if tiled else None)
    return result if finished is None else finished.result()


def _check_exposures(scene_infos, gauge_infos) -> np.ndarray | None:
    """Warn when the headers say scene and gauge were exposed differently;
    return each scene image's exposure over its gauge image's (or None)."""
    from .io import ExposureWarning, relative_exposures

    ratios = relative_exposures(scene_infos, gauge_infos)
    if ratios is None:
        return None
    shown = ", ".join(f"{r:.3g}" for r in ratios)
    if ratios.max() > ratios.min() * (1 + EXPOSURE_TOLERANCE):
        k = int(np.argmax(np.abs(np.log(ratios / np.median(ratios)))))
        warnings.warn(f"{scene_infos[k].path}: scene and gauge were exposed differently "
                      f"under different lights (scene / gauge exposure per image, from "
                      f"EXIF: {shown}); each light's scene and gauge photos need the same "
                      "exposure, or the normals are biased", ExposureWarning, stacklevel=3)
    elif abs(np.log(np.median(ratios))) > np.log1p(EXPOSURE_TOLERANCE):
        factor = float(np.median(ratios))
        warnings.warn(f"{scene_infos[0].path}: the scene was exposed {factor:.3g}x the gauge "
                      f"(EXIF); the albedo, relative to the gauge's, comes out multiplied by "
                      f"{factor:.3g}: divide it, or photograph both alike", ExposureWarning,
                      stacklevel=3)
    return ratios


@contextlib.contextmanager
def dask_client(scheduler):
    """A context of a Dask client: None (no scheduler), the given client, or one
    connected to a scheduler address / a local cluster started for "local"."""
    if scheduler is None or not isinstance(scheduler, str):
        yield scheduler
        return
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError:
        raise InputError("--scheduler needs Dask: pip install 'colorps[dask]'") from None
    if scheduler == "local":
        with LocalCluster(dashboard_address=None) as cluster, Client(cluster) as client:
            yield client
        return
    try:
        client = Client(scheduler, timeout=SCHEDULER_TIMEOUT)
    except (OSError, TimeoutError) as error:
        raise InputError(f"--scheduler {scheduler}: cannot connect ({error})") from None
    with client:
        yield client


def _check_solved(result: Reconstruction, scene_paths, gauge_paths, mask_path) -> None:
    """Refuse a run that solved nothing, saying why."""
    stats = result.stats
    if stats.solved:
        return
    reasons = {k: v for k, v in stats.pixels_by_reason.items() if v and k != "background"}
    where = f"mask {mask_path}" if mask_path else "the scene"
    if stats.table_size == 0 and gauge_paths:
        raise InputError(f"{gauge_paths[0]}: no gauge pixel has every band usable "
                         "(clipped, too dark or invalid), so nothing can be matched; check "
                         "the gauge images and --sphere")
    worst = max(reasons, key=reasons.get) if reasons else "background"
    raise InputError(f"{scene_paths[0]}: no pixel of {where} could be solved (mostly "
                     f"'{worst}': {reasons.get(worst, 0)} pixels); see --dark-level, "
                     "--clip-level and --max-residual")


def integrate_file(normals_path, out, *, mask_path=None, weights_path=None,
                   method: Literal["poisson", "dct"] = "poisson", mesh=None,
                   overwrite: bool = False):
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
    from .io import read_image, read_mask
    from .outputs import check_height_targets, save_height

    check_height_targets(out, mesh, overwrite=overwrite)  # fail before the work
    normals, _ = read_image(normals_path, "linear")
    if normals.shape[2] < 3:
        raise InputError(f"{normals_path}: a normal map needs 3 channels (X, Y, Z), "
                         f"got {normals.shape[2]}")
    if normals.shape[2] > 4:
        raise InputError(f"{normals_path}: a normal map has 3 channels (X, Y, Z), got "
                         f"{normals.shape[2]}")
    normals = normals[..., :3]
    finite = np.isfinite(normals).all(axis=-1)
    if not finite.any():
        raise InputError(f"{normals_path}: holds no finite normal (all NaN or Inf)")
    length = np.linalg.norm(normals[finite], axis=-1)
    off = np.abs(length - 1.0) > UNIT_TOLERANCE
    if off.mean() > MAX_NON_UNIT_FRACTION:
        raise InputError(
            f"{normals_path}: is not a normal map: {off.mean():.0%} of its finite pixels "
            f"are not unit vectors (median length {np.median(length):.3g}); colorps writes "
            "normal.exr with X, Y, Z of unit length")
    mask = None if mask_path is None else read_mask(mask_path, normals.shape[:2])
    weights = None
    if weights_path is not None:
        quality, _ = read_image(weights_path, "linear")
        if quality.shape[:2] != normals.shape[:2]:
            raise InputError(f"{weights_path}: size differs from {normals_path}")
        weights = weights_from_quality(quality[..., 0])
    height = integrate(normals, mask, weights=weights, method=method)
    save_height(height, out, mesh=mesh, overwrite=overwrite)
    return height


def calibrate_lights_files(image_patterns: str | Sequence[str],
                           sphere: Literal["auto"] | tuple[float, float, float], out, *,
                           encoding="auto", overwrite: bool = False):
    """Light directions from mirror-sphere images, written as a light file.

    Parameters
    ----------
    image_patterns : str or sequence of str
        The mirror-sphere images, one per light, in capture order.
    sphere : "auto" or (cx, cy, r)
        The sphere's silhouette in pixels, or found with :func:`colorps.find_sphere`
        on the images (it needs the sphere's disk brighter than the background).
    out : str or Path
        ``.txt`` (one "x y z" per line), ``.lp`` (count, then "file x y z") or
        ``.json``.

    Returns
    -------
    (Lights, list of Highlight, (cx, cy, r))
    """
    from pathlib import Path

    from .calibrate import calibrate_lights
    from .errors import OutputError
    from .gauge import find_sphere
    from .io import check_stack_files, expand_paths, input_levels, read_stack
    from .lights import LIGHT_FORMATS, write_lights

    out = Path(out)
    if out.suffix.lower() not in LIGHT_FORMATS:
        raise InputError(f"{out}: light files are {', '.join(LIGHT_FORMATS)}")
    if out.exists() and not overwrite:
        raise OutputError(f"{out}: already exists; use --overwrite to replace it")
    if not out.parent.is_dir():
        raise OutputError(f"{out.parent}: output folder does not exist")
    paths = expand_paths(image_patterns, name="mirror sphere")
    info = check_stack_files(paths, name="mirror sphere")[0]
    stack, _ = read_stack(paths, encoding, name="mirror sphere")
    found_sphere = find_sphere(stack) if sphere == "auto" else tuple(sphere)
    clip_level, _ = input_levels(info, encoding)
    lights, found = calibrate_lights(stack, found_sphere, clip_level=clip_level,
                                     names=[p.name for p in paths])
    write_lights(lights, out)
    return lights, found, found_sphere
