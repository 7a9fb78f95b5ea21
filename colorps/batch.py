"""Many captures, one command: ``colorps batch``.

A batch is a list of :class:`CaptureSpec` (what one ``colorps reconstruct``
needs), from capture folders laid out by convention (:func:`find_capture`) or
from a manifest file (:func:`read_manifest`). :func:`run_batch` reconstructs each
into its own folder under the output folder, one capture per task: in this
process one after the other, or as tasks on a Dask cluster (a
``dask.distributed.Client``; every worker must see the input and output paths,
as on a shared file system). A capture that fails does not stop the others: its
error is reported, nothing is written for it, and ``batch.json`` in the output
folder lists every capture's outcome.

Folder convention (first match wins)
------------------------------------
=================  ==========================================================
scene images       ``scene_*`` in any format reconstruct reads
                   (:func:`colorps.formats.image_suffixes`: EXR, TIFF, PNG, JPEG,
                   HDR, TGA, BMP, ...), else the files listed in
                   ``filenames.txt`` (DiLiGenT)
gauge              ``gauge_*`` images with the sphere found automatically, else
                   a light file ``lights.txt`` / ``lights.lp`` / ``lights.json``
                   / ``light_directions.txt`` (with ``light_intensities.txt``
                   when present): a virtual gauge
mask               ``mask.*`` in any of those formats, when present
=================  ==========================================================

Manifest
--------
A JSON list of objects with the keys of :class:`CaptureSpec` (``name`` and
``scene`` required; relative paths are relative to the manifest), e.g.
``[{"name": "coin", "scene": "coin/*.exr", "gauge": "ball/*.exr", "sphere":
"auto", "mask": "coin/mask.png"}]``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from .errors import ColorPSError, InputError, OutputError
from .formats import image_suffixes
from .gauge import DEFAULT_ALBEDO, DEFAULT_VIRTUAL_RADIUS
from .inputs import CaptureFiles
from .options import Options

__all__ = [
    "LIGHT_FILES",
    "CaptureOutcome",
    "CaptureSpec",
    "find_capture",
    "read_manifest",
    "run_batch",
]

#: Light files a capture folder may hold instead of gauge images, in that order.
LIGHT_FILES = ("lights.txt", "lights.lp", "lights.json", "light_directions.txt")


@dataclass(frozen=True)
class CaptureSpec:
    """One capture of a batch: the inputs of one ``colorps reconstruct``.

    Attributes
    ----------
    name : str
        Its output folder's name (under the batch's output folder).
    scene : list of str
        Scene images: globs, paths or ``@list.txt``.
    gauge : list of str or None
        Gauge images (with ``sphere``), or None with ``lights``.
    sphere : "auto", (cx, cy, r) or None
    mask, lights, light_intensities : str or None
    gauge_albedo : float or list of float
    virtual_radius : float
    """

    name: str
    scene: list
    gauge: list | None = None
    sphere: object = None
    mask: str | None = None
    lights: str | None = None
    light_intensities: str | None = None
    gauge_albedo: object = DEFAULT_ALBEDO
    virtual_radius: float = DEFAULT_VIRTUAL_RADIUS

    def __post_init__(self) -> None:
        if not self.name or "/" in self.name or self.name in (".", ".."):
            raise InputError(f"capture name {self.name!r}: must be a plain folder name")
        if (self.gauge is None) == (self.lights is None):
            raise InputError(f"capture {self.name}: give either gauge images or a light file")
        if self.gauge is not None and self.sphere is None:
            object.__setattr__(self, "sphere", "auto")

    @property
    def files(self) -> CaptureFiles:
        """The inputs, as :func:`colorps.pipeline.reconstruct_files` takes them."""
        return CaptureFiles(self.scene, gauge=self.gauge, sphere=self.sphere, mask=self.mask,
                            lights=self.lights, light_intensities=self.light_intensities,
                            gauge_albedo=self.gauge_albedo, virtual_radius=self.virtual_radius)


@dataclass(frozen=True)
class CaptureOutcome:
    """What became of one capture: its folder, or its error."""

    name: str
    out: str
    ok: bool
    error: str | None = None
    solved: int = 0
    pixels: int = 0
    seconds: float = 0.0
    warnings: list = field(default_factory=list)


def _one_suffix(folder: Path, prefix: str) -> str | None:
    """The file suffix of a folder's ``prefix*`` images (None: there are none)."""
    suffixes = {p.suffix for p in folder.glob(prefix + "*")
                if p.suffix.lower() in image_suffixes()}
    if len(suffixes) > 1:
        raise InputError(f"{folder}: its {prefix}* images come in several formats "
                         f"({', '.join(sorted(suffixes))}); keep one")
    return suffixes.pop() if suffixes else None


def _mask_file(folder: Path) -> str | None:
    """The folder's ``mask.*`` image, if any (refused when there are several)."""
    masks = sorted(p for p in folder.glob("mask.*") if p.suffix.lower() in image_suffixes())
    if len(masks) > 1:
        raise InputError(f"{folder}: holds several masks ({', '.join(p.name for p in masks)}); "
                         "keep one")
    return str(masks[0]) if masks else None


def find_capture(folder) -> CaptureSpec:
    """The capture in a folder laid out by the convention (module docstring).

    Raises
    ------
    InputError
        When the folder is missing or holds no scene images, or neither gauge
        images nor a light file.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: is not a capture folder")
    scene_suffix = _one_suffix(folder, "scene_")
    if scene_suffix:
        scene = [str(folder / f"scene_*{scene_suffix}")]
    elif (folder / "filenames.txt").is_file():
        scene = [f"@{folder / 'filenames.txt'}"]
    else:
        others = sorted({p.suffix for p in folder.glob("scene_*")})
        found = f" (scene_* files found are {', '.join(others)}: not images colorps reads)" \
            if others else ""
        raise InputError(f"{folder}: holds no scene_* images and no filenames.txt{found}")
    common = dict(name=folder.name, scene=scene, mask=_mask_file(folder))
    gauge_suffix = _one_suffix(folder, "gauge_")
    if gauge_suffix:
        return CaptureSpec(gauge=[str(folder / f"gauge_*{gauge_suffix}")], sphere="auto",
                           **common)
    for candidate in LIGHT_FILES:
        if (folder / candidate).is_file():
            intensities = folder / "light_intensities.txt"
            return CaptureSpec(lights=str(folder / candidate),
                               light_intensities=str(intensities)
                               if intensities.is_file() else None, **common)
    raise InputError(f"{folder}: holds no gauge_* images and no light file "
                     f"({', '.join(LIGHT_FILES)})")


def read_manifest(path) -> list[CaptureSpec]:
    """The captures a JSON manifest lists (module docstring).

    Raises
    ------
    InputError
        Unreadable JSON, an entry that is not an object, unknown keys, or two
        captures of one name; the message names the file and entry.
    """
    path = Path(path)
    try:
        entries = json.loads(path.read_text())
    except OSError as exc:
        raise InputError(f"{path}: cannot read manifest ({exc.strerror})") from None
    except ValueError as exc:
        raise InputError(f"{path}: not JSON ({exc})") from None
    if not isinstance(entries, list) or not entries:
        raise InputError(f"{path}: a manifest is a non-empty JSON list of captures")
    known = {f.name for f in fields(CaptureSpec)}
    specs = []
    for number, entry in enumerate(entries, start=1):
        if not isinstance(entry, dict):
            raise InputError(f"{path}: entry {number} is not an object")
        unknown = sorted(set(entry) - known)
        if unknown:
            raise InputError(f"{path}: entry {number} has unknown key(s) "
                             f"{', '.join(unknown)} (known: {', '.join(sorted(known))})")
        if "name" not in entry or "scene" not in entry:
            raise InputError(f"{path}: entry {number} needs 'name' and 'scene'")
        entry = dict(entry)
        for key in ("scene", "gauge"):
            if isinstance(entry.get(key), str):
                entry[key] = [entry[key]]
            if entry.get(key) is not None:
                entry[key] = [_relative(path, p) for p in entry[key]]
        for key in ("mask", "lights", "light_intensities"):
            if entry.get(key) is not None:
                entry[key] = _relative(path, entry[key])
        if isinstance(entry.get("sphere"), list):
            entry["sphere"] = tuple(float(v) for v in entry["sphere"])
        try:
            specs.append(CaptureSpec(**entry))
        except InputError as exc:
            raise InputError(f"{path}: entry {number}: {exc}") from None
    _check_names(specs, str(path))
    return specs


def _relative(manifest: Path, value: str) -> str:
    at = value.startswith("@")
    raw = Path(value[1:] if at else value)
    resolved = raw if raw.is_absolute() else manifest.parent / raw
    return ("@" if at else "") + str(resolved)


def _check_names(specs: Sequence[CaptureSpec], source: str) -> None:
    seen = set()
    for spec in specs:
        if spec.name in seen:
            raise InputError(f"{source}: two captures are named {spec.name!r}; each gets "
                             "its own output folder")
        seen.add(spec.name)


def run_one(spec: CaptureSpec, out, options: Options, overwrite: bool = False
            ) -> CaptureOutcome:
    """Reconstruct one capture into ``out / spec.name``; errors become the outcome."""
    import warnings

    from .pipeline import reconstruct_files

    target = Path(out) / spec.name
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        try:
            result = reconstruct_files(spec.files, target, options=options,
                                       overwrite=overwrite, progress=False)
        except ColorPSError as exc:
            return CaptureOutcome(spec.name, str(target), False, str(exc),
                                  seconds=time.perf_counter() - t0)
    return CaptureOutcome(spec.name, str(target), True, None, result.stats.solved,
                          result.stats.pixels, time.perf_counter() - t0,
                          [str(w.message) for w in said])


def run_batch(captures: Sequence[CaptureSpec], out, options: Options | None = None, *,
              client=None, overwrite: bool = False,
              progress: bool = True) -> list[CaptureOutcome]:
    """Reconstruct every capture into its own folder under ``out``.

    Parameters
    ----------
    captures : sequence of CaptureSpec
    out : str or Path
        Output folder (created; each capture writes ``out / name``), with
        ``batch.json``: every capture's outcome.
    options : Options, optional
        Settings shared by all captures.
    client : dask.distributed.Client, optional
        Run one capture per task on this cluster (progress: Dask's progress
        bar); default: one after the other in this process.
    overwrite : bool, optional
        Replace existing results (else a capture whose folder exists fails).
    progress : bool, optional

    Returns
    -------
    list of CaptureOutcome
        In the order of ``captures``.
    """
    from tqdm.auto import tqdm

    options = options or Options()
    if not captures:
        raise InputError("batch: no captures given")
    _check_names(captures, "batch")
    out = Path(out)
    summary = out / "batch.json"
    if summary.exists() and not overwrite:
        raise OutputError(f"{summary}: already exists; use --overwrite to replace it")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{out}: cannot create the output folder ({exc.strerror})") from None
    if client is None:
        outcomes = []
        for spec in tqdm(captures, desc="captures", unit="capture", disable=not progress):
            outcomes.append(run_one(spec, out, options, overwrite))
    else:
        futures = client.map(run_one, list(captures), out=str(out), options=options,
                             overwrite=overwrite, pure=False)
        if progress:
            from dask.distributed import progress as dask_progress

            dask_progress(futures)
        outcomes = client.gather(futures)
    from .io import atomic_target

    with atomic_target(summary) as tmp:
        tmp.write_text(json.dumps(dict(options=options.as_dict(),
                                       captures=[asdict(o) for o in outcomes]), indent=1))
    return outcomes
