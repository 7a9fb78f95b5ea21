"""Every output file of a reconstruction, written all together or not at all.

===============  =============================================================
file             content
===============  =============================================================
normal.exr       float32 camera-space unit normals, channels X, Y, Z; NaN where
                 not solved
normal.png       16-bit normal map (n + 1) / 2 in R, G, B, y up ("opengl") or
                 y down ("directx", G = (1 - ny) / 2); black where not solved
albedo.exr       float32 linear albedo, one channel per input band (input names)
albedo.png       sRGB preview, black where not solved
quality.exr      float32 match residual in noise units (about 1 = explained,
                 see :mod:`colorps.residuals`); NaN where no match was tried
quality.png      quality.exr through the colour map, with its colour bar
                 (:data:`~colorps.figures.QUALITY_SCALE`)
invalid.png      why pixels are not solved, one colour per
                 :class:`~colorps.Reason` (black solved, grey background, blue
                 too dark, yellow clipped, magenta invalid value, red no good
                 match, teal solved from a light subset, orange solved from a
                 poor match), with a legend
uncertainty.exr  float32 68 % angular radius of each refined normal (degrees);
                 NaN where not solved or not refined
uncertainty.png  uncertainty.exr through the colour map, with its colour bar
lights.png       lights dropped per pixel (cast shadows, highlights): black
                 none, then :data:`~colorps.figures.DROPPED_COLOURS` for 1, 2,
                 3+ lights, with a legend
lights.exr       the dropped lights as float32 bit masks of 16 images per
                 channel: bit i % 16 of channel i // 16 is image i (channels
                 "L" for up to 16 images, else "L0-15", "L16-31", ...)
index.html       the results viewer (relighting, every map, values under the
viewer/          cursor) and its data: see :mod:`colorps.viewer`
report.json      inputs, options, statistics, pixels by reason, the scales of
                 height.png and the normal map's convention
height.exr       float32 height in pixels (see :mod:`colorps.integrate`), when
                 the result has a height map
height.tif       the same as a float32 TIFF (NaN outside), for GIS and DEM tools
height.png       16-bit codes of the height (:mod:`colorps.codes`: 0 outside,
                 else lo + (code - 1) (hi - lo) / 65534 pixels, lo and hi in
                 report.json "exports")
relief.png       shaded relief of the height map, with it
overview.png     scene, normals, albedo and relief side by side, with it
mesh.ply/.obj    triangle mesh of the height field with albedo vertex colours,
                 when asked for
===============  =============================================================

Pictures with a key (quality, uncertainty, invalid, lights) hold the map at its
own pixels in their top-left H x W corner, the key in a strip below.

A tiled run (``--tile``, ``--memory-limit``, ``--scheduler``) writes its
.exr maps in TILED_EXR_SIDE x TILED_EXR_SIDE pixel tiles, so that a viewer or
a later tiled job reads a region of a large map without decoding the rest.

Files are first written to a new folder beside the output folder, which then
takes its place in one rename (see ``_write_folder``), so a failed or
interrupted run leaves no half-written result and no temporary files.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sys
import tempfile
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from .codes import code_range, encode
from .errors import InputError, OutputError
from .figures import (
    QUALITY_SCALE,
    UNCERTAINTY_SCALE,
    as_rgb,
    colour_mapped,
    dropped_legend,
    dropped_picture,
    overview,
    picture_codes,
    reason_legend,
    shaded_relief,
    with_colour_bar,
    with_key,
)
from .interrupts import interrupts_kept
from .io import WRITE_THREADS, file_mode, srgb_encode, write_image
from .options import NORMAL_CONVENTIONS
from .reasons import Reason, reason_picture
from .results import Reconstruction, default_band_names
from .viewer import VIEWER_FILES, write_viewer

__all__ = [
    "HEIGHT_FILES",
    "MESH_FILES",
    "OUTPUT_FILES",
    "Exports",
    "check_height_targets",
    "height_codes",
    "normal_picture",
    "prepare_output_dir",
    "save_height",
    "save_reconstruction",
    "write_folder",
]

#: Written by every reconstruction.
OUTPUT_FILES = ("normal.exr", "normal.png", "albedo.exr", "albedo.png", "quality.exr",
                "quality.png", "invalid.png", "lights.png", "lights.exr", "uncertainty.exr",
                "uncertainty.png", *VIEWER_FILES, "report.json")
#: Written when the result has a height map.
HEIGHT_FILES = ("height.exr", "height.tif", "height.png", "relief.png", "overview.png")
#: Written when asked for, by kind.
MESH_FILES = {"ply": "mesh.ply", "obj": "mesh.obj"}
_ALL_FILES = OUTPUT_FILES + HEIGHT_FILES + tuple(MESH_FILES.values())
#: Tile side (pixels) of the .exr maps of a tiled run (OpenEXR's usual 64).
TILED_EXR_SIDE = 64
_CONVENTIONS = ("camera-space normals: x right, y up, z towards the camera; "
                "pixel (x, y) = (column, row); linear values")


def prepare_output_dir(out_dir, *, overwrite: bool = False,
                       files: Sequence[str] = _ALL_FILES, create: bool = False) -> Path:
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
    if not str(out_dir).strip():
        raise OutputError("--out is empty: name the results folder (it would be the "
                          "current folder)")
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


@dataclass(frozen=True)
class Exports:
    """How the files beyond the maps are written.

    Attributes
    ----------
    mesh : tuple of {"ply", "obj"}
        Mesh files to write (needs the height map).
    normal_convention : {"opengl", "directx"}
        normal.png's green channel: y up (OpenGL, as normal.exr) or y down
        (DirectX: G = (1 - ny) / 2).
    viewer : bool
        Write index.html and viewer/ (see :mod:`colorps.viewer`).
    exr_tile : int or None
        Write the .exr maps in tiles of this side (pixels), as a tiled run does
        (TILED_EXR_SIDE); None: scanlines.
    """

    mesh: tuple[str, ...] = ()
    normal_convention: Literal["opengl", "directx"] = "opengl"
    viewer: bool = True
    exr_tile: int | None = None

    def __post_init__(self) -> None:
        if self.normal_convention not in NORMAL_CONVENTIONS:
            raise InputError(f"normal_convention: expected one of {NORMAL_CONVENTIONS}, "
                             f"got {self.normal_convention!r}")


def save_reconstruction(result: Reconstruction, out_dir, *,
                        channel_names: Sequence[str] | None = None,
                        scene_preview: np.ndarray | None = None,
                        report: dict | None = None, exports: Exports = Exports(),
                        overwrite: bool = False,
                        finished: Future[Reconstruction] | None = None,
                        progress: bool = False) -> list[Path]:
    """Write every output file of a reconstruction (see the module docstring).

    Parameters
    ----------
    result : Reconstruction
        With ``result.height`` set, the height files are written too.
    out_dir : str or Path
    channel_names : sequence of str, optional
        Names of the input bands (default R, G, B or Y / B0, B1, ...).
    scene_preview : (H, W, c) ndarray, optional
        Linear scene image for overview.png (default: the albedo), whole or at
        the pixels it draws (see :func:`colorps.figures.overview`).
    report : dict, optional
        Inputs and options to record in report.json beside the statistics; a
        value with an ``as_dict()`` method (a :class:`~colorps.results.RunClock`)
        is read when report.json is written, last.
    exports : Exports, optional
        Mesh files, normal.png's convention, the viewer, tiled .exr maps.
    overwrite : bool, optional
        Replace existing results.
    finished : concurrent.futures.Future of Reconstruction, optional
        ``result`` with its height map, still being computed (the pipeline
        integrates in a thread meanwhile): the files that need no height are
        written first, the height files, the viewer and report.json once it is
        done. An error it raises fails the whole write (nothing is left behind).
    progress : bool, optional
        A progress bar over the files, naming the one being written.

    Returns
    -------
    list of Path
        The files written.
    """
    if exports.mesh and result.height is None and finished is None:
        raise OutputError("a mesh needs the height map; integrate the normals first")
    writers = _writers(result, channel_names, scene_preview, report, exports, finished)
    out = prepare_output_dir(out_dir, overwrite=overwrite)
    return _write_folder(out, writers, progress)


def write_folder(out_dir, writers: dict[str, Callable[[Path], object]], *,
                 overwrite: bool = False, replaces: Callable[[str], bool] | None = None
                 ) -> list[Path]:
    """Write files all together or not at all (see :func:`_write_folder`).

    Parameters
    ----------
    out_dir : str or Path
        The folder (made when missing).
    writers : dict of str to callable
        ``{file name: write(path)}``, called in order.
    overwrite : bool, optional
        Replace files of these names already there.
    replaces : callable, optional
        Whether a file name already there is one of an earlier set these files
        replace (default: a colorps result's): a folder of such files alone is
        exchanged whole; one holding others is written into, and the earlier
        set's files not written again are removed.

    Returns
    -------
    list of Path
    """
    out = prepare_output_dir(out_dir, overwrite=overwrite, files=list(writers))
    return _write_folder(out, writers, replaces=replaces)


def _write_folder(out: Path, writers: dict, progress: bool = False,
                  replaces: Callable[[str], bool] | None = None) -> list[Path]:
    """Write every file into a new folder beside ``out``, then swap it in.

    A new ``out`` appears whole, by one rename. An existing one that holds only
    colorps results is exchanged with the new folder in one atomic rename
    (``renameat2(RENAME_EXCHANGE)``; two renames where the system lacks it),
    so an interruption leaves either the old results or the new ones. An
    existing folder that is not to be replaced (:func:`_in_place`: it holds
    other files, is a link or a mount point, holds the current folder, or its
    parent cannot be written) keeps its identity: the files are written in a
    hidden folder inside it, on its file system, and moved in one by one.
    On any failure nothing is left behind: not the new folder, not the
    parents made for it, and an existing ``out`` is untouched.

    Each writer writes the file of its name and may write others beside it
    (the viewer's page writes its data folder): whatever the writers leave is
    moved. Returns those paths.
    """
    out = out.absolute()
    inside = out.is_dir() and _in_place(out, replaces or set(_ALL_FILES).__contains__)
    made = [] if inside else _make_parents(out.parent)
    try:
        try:
            tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.colorps-",
                                        dir=out if inside else out.parent))
        except OSError as exc:
            raise OutputError(f"{out}: cannot create output folder ({exc.strerror})") from None
        try:
            with interrupts_kept():  # (the mesh writer, trimesh, can swallow a Ctrl-C)
                _run_writers(writers, tmp, out, progress)
            written = sorted(os.listdir(tmp))  # a writer may add beside its file
            if inside:
                for name in written:
                    _replace(tmp / name, out / name)
                for name in os.listdir(out) if replaces else ():  # an earlier set's rest
                    if replaces(name) and name not in written:
                        os.remove(out / name)
            elif not out.exists():
                os.chmod(tmp, file_mode(directory=True))
                os.rename(tmp, out)
            else:
                os.chmod(tmp, file_mode(directory=True))
                _exchange(tmp, out)
                shutil.rmtree(tmp, ignore_errors=True)  # now the old results
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    except BaseException:
        for folder in reversed(made):
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
    return [out / name for name in written]


def _run_writers(writers: dict, tmp: Path, out: Path, progress: bool) -> None:
    """Call every writer on its path in ``tmp``, WRITE_THREADS at a time (the
    encoders release the GIL), the last one (report.json) after all the others;
    on a failure or an interrupt, no writer is still running when this returns."""
    *first, last = writers

    def write(name):
        try:
            writers[name](tmp / name)
        except OSError as exc:
            raise OutputError(f"{out}: cannot write {name} ({exc.strerror or exc})") from None
        return name

    with _files_bar(len(first), progress) as bar, \
            ThreadPoolExecutor(WRITE_THREADS, thread_name_prefix="colorps-write") as pool:
        jobs = [pool.submit(write, name) for name in first]
        try:
            for job in as_completed(jobs):
                bar.set_postfix_str(job.result(), refresh=False)
                bar.update()
        except BaseException:
            for job in jobs:
                job.cancel()
            raise  # leaving the pool waits for the writers under way
    write(last)


def _files_bar(total: int, progress: bool):
    """A progress bar over files written (a do-nothing one without ``progress``)."""
    from tqdm import tqdm

    return tqdm(total=total, desc="writing", unit="file", disable=not progress,
                leave=False, file=sys.stderr)


def _replace(source: Path, target: Path) -> None:
    """Move a file or folder over ``target`` (a folder: the old one is moved
    aside first, then removed)."""
    if target.is_dir() and not target.is_symlink():
        old = target.with_name(f".{target.name}.colorps-old-{os.getpid()}")
        os.rename(target, old)
        os.rename(source, target)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(source, target)


def _in_place(out: Path, replaced: Callable[[str], bool]) -> bool:
    """Whether an existing results folder must keep its identity (be written into,
    not exchanged): it holds files other than those ``replaced`` says, is a symbolic
    link or a mount point (a container's volume: nothing can be renamed over it),
    is or holds the current folder, or its parent cannot be written."""
    if out.is_symlink() or os.path.ismount(out):
        return True
    here = Path.cwd().resolve()
    if out.resolve() == here or out.resolve() in here.parents:
        return True
    if not os.access(out.parent, os.W_OK | os.X_OK):
        return True
    return not all(replaced(p.name) for p in out.iterdir())


def _make_parents(folder: Path) -> list[Path]:
    """Create ``folder`` and missing parents; return those made, outermost first."""
    missing = []
    while not folder.exists():
        missing.append(folder)
        folder = folder.parent
    made = []
    try:
        for path in reversed(missing):
            path.mkdir()
            made.append(path)
    except OSError as exc:
        for path in reversed(made):
            with contextlib.suppress(OSError):
                path.rmdir()
        raise OutputError(f"{missing[0]}: cannot create folder ({exc.strerror})") from None
    return made


def _exchange(a: Path, b: Path) -> None:
    """Swap two folders atomically where Linux allows it, else by two renames."""
    import ctypes

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        renameat2 = None
    if renameat2 is not None:
        at_fdcwd, rename_exchange = -100, 2
        if renameat2(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b),
                     rename_exchange) == 0:
            return
    old = b.with_name(f".{b.name}.colorps-old-{os.getpid()}")
    os.rename(b, old)
    os.rename(a, b)
    os.rename(old, a)


def check_height_targets(out, mesh=None, *, overwrite: bool = False) -> None:
    """Check where :func:`save_height` will write, before any work is done.

    Raises
    ------
    InputError
        ``out`` is not an OpenEXR (.exr) path, or ``mesh`` not .ply / .obj.
    OutputError
        A target exists (and not ``overwrite``) or its folder does not.
    """
    from .mesh import MESH_FORMATS

    if Path(out).suffix.lower() != ".exr":
        raise InputError(f"{out}: the height map is written as OpenEXR (.exr)")
    if mesh is not None and Path(mesh).suffix.lower().lstrip(".") not in MESH_FORMATS:
        raise InputError(f"{mesh}: mesh format must be one of {MESH_FORMATS}")
    for target in [Path(out)] + ([Path(mesh)] if mesh else []):
        if target.exists() and not overwrite:
            raise OutputError(f"{target}: already exists; use --overwrite to replace it")
        if not target.parent.is_dir():
            raise OutputError(f"{target.parent}: output folder does not exist")


def save_height(height: np.ndarray, out, *, mesh=None, overwrite: bool = False) -> None:
    """Write a height map (.exr, channel Z) and optionally a mesh of it (.ply/.obj)."""
    check_height_targets(out, mesh, overwrite=overwrite)
    if mesh:
        _write_mesh(height, None, mesh)
    write_image(out, height, channel_names=["Z"])


def _writers(result: Reconstruction, channel_names, scene_preview, report, exports: Exports,
             finished=None) -> dict[str, Callable[[Path], object]]:
    """``{file name: write(path)}`` of every file to write: the maps, then those
    that need the height (waiting for ``finished``), report.json last."""

    def final() -> Reconstruction:
        return result if finished is None else finished.result()

    c = result.albedo.shape[-1]
    if channel_names is None:
        channel_names = default_band_names(c)
    solved = result.solved[..., None]
    width = result.normals.shape[1]
    title = f"colorps {result.stats.mode} mode: {result.stats.solved} pixels solved"
    if result.stats.residual_median is not None:  # the fit before any run-level scale
        title += f", median residual {result.stats.residual_median_noise_units:.2f} noise units"

    def exr(p, image, channels):
        return write_image(p, image, channel_names=channels, tile=exports.exr_tile)

    def picture(p, image):
        return write_image(p, image, dtype="uint8")

    writers = {
        "normal.exr": lambda p: exr(p, result.normals, ["X", "Y", "Z"]),
        "normal.png": lambda p: write_image(p, picture_codes(
            lambda rows: normal_picture(result.normals[rows], exports.normal_convention),
            (*solved.shape[:2], 3), np.uint16), dtype="uint16"),
        "albedo.exr": lambda p: exr(p, result.albedo, list(channel_names)),
        "albedo.png": lambda p: picture(p, picture_codes(
            lambda rows: srgb_encode(as_rgb(np.where(solved[rows], result.albedo[rows], 0.0))),
            (*solved.shape[:2], 3))),
        "quality.exr": lambda p: exr(p, result.quality, ["Q"]),
        "quality.png": lambda p: picture(p, with_colour_bar(
            colour_mapped(result.quality, QUALITY_SCALE), QUALITY_SCALE)),
        "invalid.png": lambda p: picture(p, with_key(reason_picture(result.reason),
                                                     reason_legend(width))),
        "lights.png": lambda p: picture(p, with_key(
            dropped_picture(result.lights_dropped_count), dropped_legend(width))),
        "lights.exr": lambda p: _write_light_channels(p, result.dropped_lights,
                                                      result.stats.images, exports.exr_tile),
        "uncertainty.exr": lambda p: exr(p, result.uncertainty, ["U"]),
        "uncertainty.png": lambda p: picture(p, with_colour_bar(
            colour_mapped(result.uncertainty, UNCERTAINTY_SCALE), UNCERTAINTY_SCALE)),
    }
    exported = {"normal.png": {"convention": exports.normal_convention,
                               "encoding": "16-bit (n + 1) / 2, y up" if
                               exports.normal_convention == "opengl" else
                               "16-bit (nx + 1) / 2, (1 - ny) / 2, (nz + 1) / 2: y down"}}
    if result.height is not None or finished is not None:
        preview = result.albedo if scene_preview is None else scene_preview
        writers["height.exr"] = lambda p: exr(p, final().height, ["Z"])
        writers["height.tif"] = lambda p: write_image(p, final().height)
        writers["height.png"] = lambda p: write_image(
            p, height_codes(final().height)[0] / np.float32(65535), dtype="uint16")
        writers["relief.png"] = lambda p: picture(p, shaded_relief(final().height))
        writers["overview.png"] = lambda p: picture(
            p, overview(preview, result.normals, result.albedo, final().height, title=title))
        for kind in exports.mesh:
            writers[MESH_FILES[kind]] = lambda p: _write_mesh(final().height, result.albedo, p)
    if exports.viewer:  # the page, and its data folder beside it
        finish = (report or {}).get("brdf")  # a --lights run's fitted finish
        writers["index.html"] = lambda p: write_viewer(
            result, p.parent, band_names=channel_names, title=title, finish=finish,
            finished=final)
        if finished is not None:  # its maps but one need no height: first while it comes
            writers = {"index.html": writers.pop("index.html"), **writers}  # (benchmarks.md)
    about = {"reasons": {str(int(r)): r.label for r in Reason}, "conventions": _CONVENTIONS}

    def report_json(p):
        about["files"] = [*sorted(os.listdir(p.parent)), "report.json"]  # all before it
        if final().height is not None:
            lo, hi = _height_range(final().height)
            exported["height.png"] = {"unit": "pixels", "lo": lo, "hi": hi,
                                      "decoding": "code 0: outside; else lo + (code - 1) * "
                                                  "(hi - lo) / 65534"}
        p.write_text(json.dumps({**(report or {}), "statistics": final().stats.as_dict(),
                                 "exports": exported, **about}, indent=2, default=_jsonable))

    writers["report.json"] = report_json
    return writers


def normal_picture(normals, convention: str = "opengl") -> np.ndarray:
    """normal.png's values, 0..1: (n + 1) / 2, green (1 - ny) / 2 for "directx";
    0 where not solved (NaN)."""
    if convention not in NORMAL_CONVENTIONS:
        raise InputError(f"normal_convention: expected one of {NORMAL_CONVENTIONS}, "
                         f"got {convention!r}")
    n = np.asarray(normals, dtype=np.float32)
    picture = (n + 1) / 2
    if convention == "directx":
        picture[..., 1] = 1 - picture[..., 1]
    return np.where(np.isfinite(n).all(axis=-1, keepdims=True), picture, np.float32(0.0))


def height_codes(height) -> tuple[np.ndarray, float, float]:
    """height.png's 16-bit codes (:mod:`colorps.codes`) of the heights as
    height.exr stores them (float32), and their lo and hi."""
    lo, hi = _height_range(height)
    return encode(np.asarray(height, dtype=np.float32), lo, hi), lo, hi


def _height_range(height) -> tuple[float, float]:
    """The range (lo, hi) of height.png's codes: that of the heights as stored (float32)."""
    return code_range(np.asarray(height, dtype=np.float32))


#: Images per float32 channel of lights.exr (exact integers up to 2^24).
LIGHTS_PER_CHANNEL = 16


def _write_light_channels(path, dropped: np.ndarray, m: int, exr_tile=None):
    """lights.exr: 16 images' bits per float32 channel, cut straight from the
    masks' 64-bit words (no per-image array)."""
    per_word = 64 // LIGHTS_PER_CHANNEL
    starts = range(0, m, LIGHTS_PER_CHANNEL)
    channels = np.empty((*dropped.shape[:2], len(starts)), dtype=np.float32)
    for j, _ in enumerate(starts):
        shift = np.uint64(LIGHTS_PER_CHANNEL * (j % per_word))
        channels[..., j] = (dropped[..., j // per_word] >> shift) & \
            np.uint64(2 ** LIGHTS_PER_CHANNEL - 1)
    names = ["L"] if m <= LIGHTS_PER_CHANNEL else \
        [f"L{a}-{min(a + LIGHTS_PER_CHANNEL, m) - 1}" for a in starts]
    return write_image(path, channels, channel_names=names, tile=exr_tile)


def _write_mesh(height, colours, path) -> None:
    from .mesh import height_mesh, write_mesh

    write_mesh(height_mesh(height, colours), path)


def _jsonable(value):
    if hasattr(value, "as_dict"):
        return value.as_dict()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value)}")
