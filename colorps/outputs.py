"""Every output file of a reconstruction, written all together or not at all.

==============  ==============================================================
file            content
==============  ==============================================================
normal.exr      float32 camera-space unit normals, channels X, Y, Z; NaN where
                not solved
normal.png      8-bit preview (n + 1) / 2 in R, G, B; black where not solved
albedo.exr      float32 linear albedo, one channel per input band (input names)
albedo.png      sRGB preview, black where not solved
quality.exr     float32 match residual in noise units (about 1 = explained,
                see :mod:`colorps.residuals`); NaN where no match was tried
invalid.png     why pixels are not solved, one colour per
                :class:`~colorps.Reason`: black solved, grey background, blue
                too dark, yellow clipped, magenta invalid value (NaN, Inf,
                negative), red no good match, teal solved from a light subset
uncertainty.exr float32 68 % angular radius of each refined normal (degrees);
                NaN where not solved or not refined
lights.png      lights dropped per pixel (cast shadows, highlights): black
                none, then :data:`DROPPED_COLOURS` for 1, 2, 3+ lights
lights.exr      the dropped lights as float32 bit masks of 16 images per
                channel: bit i % 16 of channel i // 16 is image i (channels
                "L" for up to 16 images, else "L0-15", "L16-31", ...)
report.json     inputs, options, statistics, pixels by reason
height.exr      float32 height in pixels (see :mod:`colorps.integrate`), when
                the result has a height map
relief.png      shaded relief of the height map, with it
overview.png    scene, normals, albedo and relief side by side, with it
mesh.ply/.obj   triangle mesh of the height field with albedo vertex colours,
                when asked for
==============  ==============================================================

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
import tempfile
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from pathlib import Path

import numpy as np

from .errors import OutputError
from .figures import as_rgb, overview, shaded_relief
from .interrupts import interrupts_kept
from .io import file_mode, srgb_encode, write_image
from .reasons import Reason, reason_picture
from .results import Reconstruction

__all__ = [
    "HEIGHT_FILES",
    "MESH_FILES",
    "OUTPUT_FILES",
    "check_height_targets",
    "prepare_output_dir",
    "save_height",
    "save_reconstruction",
]

#: Written by every reconstruction.
OUTPUT_FILES = ("normal.exr", "normal.png", "albedo.exr", "albedo.png", "quality.exr",
                "invalid.png", "lights.png", "lights.exr", "uncertainty.exr", "report.json")
#: Colours (8-bit sRGB) of lights.png for 1, 2 and 3 or more dropped lights.
DROPPED_COLOURS = ((90, 200, 255), (255, 170, 0), (255, 40, 200))
#: Written when the result has a height map.
HEIGHT_FILES = ("height.exr", "relief.png", "overview.png")
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


def save_reconstruction(result: Reconstruction, out_dir, *,
                        channel_names: Sequence[str] | None = None,
                        scene_preview: np.ndarray | None = None,
                        report: dict | None = None, mesh: Sequence[str] = (),
                        overwrite: bool = False,
                        finished: Future[Reconstruction] | None = None,
                        exr_tile: int | None = None) -> list[Path]:
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
        Inputs and options to record in report.json beside the statistics.
    mesh : sequence of {"ply", "obj"}, optional
        Mesh files to write (needs ``result.height``).
    overwrite : bool, optional
        Replace existing results.
    finished : concurrent.futures.Future of Reconstruction, optional
        ``result`` with its height map, still being computed (the pipeline
        integrates in a thread meanwhile): the files that need no height are
        written first, the height files and report.json once it is done. An
        error it raises fails the whole write (nothing is left behind).
    exr_tile : int, optional
        Write the .exr maps in tiles of this side (pixels), as a tiled run does
        (TILED_EXR_SIDE); default scanlines.

    Returns
    -------
    list of Path
        The files written.
    """
    if mesh and result.height is None and finished is None:
        raise OutputError("a mesh needs the height map; integrate the normals first")
    writers = _writers(result, channel_names, scene_preview, report, mesh, finished, exr_tile)
    out = prepare_output_dir(out_dir, overwrite=overwrite)
    return _write_folder(out, writers)


def _write_folder(out: Path, writers: dict) -> list[Path]:
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
    """
    out = out.absolute()
    inside = out.is_dir() and _in_place(out)
    made = [] if inside else _make_parents(out.parent)
    try:
        try:
            tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.colorps-",
                                        dir=out if inside else out.parent))
        except OSError as exc:
            raise OutputError(f"{out}: cannot create output folder ({exc.strerror})") from None
        try:
            with interrupts_kept():  # the mesh writer (trimesh) can swallow a Ctrl-C
                for name, write in writers.items():
                    try:
                        write(tmp / name)
                    except OSError as exc:
                        raise OutputError(f"{out}: cannot write {name} "
                                          f"({exc.strerror or exc})") from None
            if inside:
                for name in writers:
                    os.replace(tmp / name, out / name)
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
    return [out / name for name in writers]


def _in_place(out: Path) -> bool:
    """Whether an existing results folder must keep its identity (be written into,
    not exchanged): it holds files other than colorps's results, is a symbolic
    link or a mount point (a container's volume: nothing can be renamed over it),
    is or holds the current folder, or its parent cannot be written."""
    if out.is_symlink() or os.path.ismount(out):
        return True
    here = Path.cwd().resolve()
    if out.resolve() == here or out.resolve() in here.parents:
        return True
    if not os.access(out.parent, os.W_OK | os.X_OK):
        return True
    return not {p.name for p in out.iterdir()} <= set(_ALL_FILES)


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
    from .errors import InputError
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


def _writers(result: Reconstruction, channel_names, scene_preview, report, mesh,
             finished=None, exr_tile=None) -> dict[str, Callable[[Path], object]]:
    """``{file name: write(path)}`` of every file to write: the maps, then those
    that need the height (waiting for ``finished``), report.json last."""

    def final() -> Reconstruction:
        return result if finished is None else finished.result()

    c = result.albedo.shape[-1]
    if channel_names is None:
        channel_names = {1: ["Y"], 3: ["R", "G", "B"]}.get(c, [f"B{k}" for k in range(c)])
    solved = result.solved[..., None]

    def exr(p, image, channels):
        return write_image(p, image, channel_names=channels, tile=exr_tile)

    writers = {
        "normal.exr": lambda p: exr(p, result.normals, ["X", "Y", "Z"]),
        "normal.png": lambda p: write_image(p, np.where(solved, (result.normals + 1) / 2, 0.0),
                                            dtype="uint8"),
        "albedo.exr": lambda p: exr(p, result.albedo, list(channel_names)),
        "albedo.png": lambda p: write_image(
            p, srgb_encode(as_rgb(np.where(solved, result.albedo, 0.0))), dtype="uint8"),
        "quality.exr": lambda p: exr(p, result.quality, ["Q"]),
        "invalid.png": lambda p: write_image(p, reason_picture(result.reason), dtype="uint8"),
        "lights.png": lambda p: write_image(p, _dropped_picture(result.lights_dropped_count),
                                            dtype="uint8"),
        "lights.exr": lambda p: _write_light_channels(p, result.dropped_lights,
                                                      result.stats.images, exr_tile),
        "uncertainty.exr": lambda p: exr(p, result.uncertainty, ["U"]),
    }
    if result.height is not None or finished is not None:
        preview = result.albedo if scene_preview is None else scene_preview
        title = f"colorps {result.stats.mode} mode: {result.stats.solved} pixels solved"
        writers["height.exr"] = lambda p: exr(p, final().height, ["Z"])
        writers["relief.png"] = lambda p: write_image(p, shaded_relief(final().height),
                                                      dtype="uint8")
        writers["overview.png"] = lambda p: write_image(
            p, overview(preview, result.normals, result.albedo, final().height, title=title),
            dtype="uint8")
        for kind in mesh:
            writers[MESH_FILES[kind]] = lambda p: _write_mesh(final().height, result.albedo, p)
    about = {"reasons": {str(int(r)): r.label for r in Reason}, "conventions": _CONVENTIONS,
             "files": [*list(writers), "report.json"]}
    writers["report.json"] = lambda p: p.write_text(json.dumps(
        {**(report or {}), "statistics": final().stats.as_dict(), **about}, indent=2,
        default=_jsonable))
    return writers


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


def _dropped_picture(count: np.ndarray) -> np.ndarray:
    table = np.zeros((256, 3), dtype=np.float32)
    for k, rgb in enumerate(DROPPED_COLOURS, start=1):
        table[k:] = np.array(rgb) / 255.0
    return table[count]


def _write_mesh(height, colours, path) -> None:
    from .mesh import height_mesh, write_mesh

    write_mesh(height_mesh(height, colours), path)


def _jsonable(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value)}")
