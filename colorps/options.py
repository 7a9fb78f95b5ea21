"""Every setting of a reconstruction, with its default, in one frozen dataclass.

:class:`Options` is shared by :func:`colorps.reconstruct` (array API),
:func:`colorps.pipeline.reconstruct_files` (files in, files out) and the
``colorps reconstruct`` command line, whose flags are the field names with
dashes (``max_distance`` is ``--max-distance``). Each default is stated here
and nowhere else.

Levels are linear pixel values on the 0..1 scale of the decoded images.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import numpy as np

from .errors import InputError

__all__ = ["FLOAT_DARK_LEVEL", "MIN_IMAGES", "NORMAL_CONVENTIONS", "Options", "dark_threshold"]

#: Noise floor of one measurement of a floating-point image (linear units): the
#: dark level that "auto" means for EXR / float TIFF files and for arrays.
FLOAT_DARK_LEVEL = 1e-4 / 3
#: Fewest images each mode can work with.
MIN_IMAGES = {"mono": 3, "colour": 2}

_MODES = ("colour", "mono")
_ENCODINGS = ("auto", "linear", "srgb")
#: Conventions of normal.png: its green channel points up (OpenGL, as normal.exr
#: and camera space) or down (DirectX).
NORMAL_CONVENTIONS = ("opengl", "directx")
_MESHES = (None, "ply", "obj", "both")
_BRDFS = ("fitted", "lambert")


def dark_threshold(dark_level: float, images: int) -> float:
    """Smallest usable OV norm: ``dark_level * sqrt(images)`` (linear units).

    An OV of m measurements that are each at the noise floor has this norm; a
    band whose OV norm is at or below it is "too dark" to normalise.
    """
    return float(dark_level) * float(np.sqrt(images))


@dataclass(frozen=True)
class Options:
    """Settings of a reconstruction (frozen: change one with :meth:`replace`).

    Attributes
    ----------
    mode : {"colour", "mono"}
        Signatures from every band (colour, R^(c m)) or from one band (mono,
        R^m); see :mod:`colorps.signatures`.
    band : int, "luminance" or None
        Mono mode: a channel index, or the luminance Y of RGB stacks. None:
        luminance for 3-band stacks, else channel 0.
    colourspace : str
        colour-science name of the RGB colourspace used for luminance.
    grid_n : int, "auto" or None
        Bucket grid size N. None: ``round(2 sqrt(|T|))`` (the paper's optimum);
        "auto": timed on a sample of the scene's signatures.
    threads : int or None
        Lookup threads (None: all of numba's threads).
    dark_level : float or "auto"
        Noise floor of one measurement (linear). A band whose OV norm is at or
        below ``dark_level * sqrt(m)`` is "too dark". "auto": 2 codes of an
        integer file (decoded like its pixels), :data:`FLOAT_DARK_LEVEL` for
        floating-point files and arrays.
    clip_level : float, "auto" or None
        Measurements at or above this linear value are clipped. "auto": the
        top code of an integer file, no clipping for floating-point files and
        arrays. None: nothing is clipped.
    read_noise, gain : float or "auto"
        The noise model (:mod:`colorps.noise`): read-noise floor (linear) and
        shot-noise variance per unit signal. "auto": fitted to the gauge's
        pixel-to-pixel scatter.
    band_weights : bool
        Colour mode: weight each band's signature by its signal-to-noise ratio
        (powers of two), dropping bands far below the brightest one.
    light_subsets : bool
        Re-solve pixels whose match leaves measurements far outside the noise
        (cast shadows, highlights) from the lights the gauge explains there,
        any number of them (at least 3 remain; :mod:`colorps.shadows`); and
        solve a pixel still over ``max_residual`` when the refinement's robust
        fit explains it on its inliers.
    max_dropped_lights : int
        Before that, for captures of up to ``matching.GREEDY_MAX_LIGHTS`` lights,
        up to this many rounds of table-based light subsets, each dropping the
        one light that helps most (they single out one shadowed light of a few
        more surely; their tables grow too many with more lights).
    max_residual : float or None
        Largest match residual (``quality``, in units of its expected value
        under the noise model) of a good match. A worse one is still solved,
        flagged "solved, poor match" (its uncertainty takes the misfit in),
        or refused as "no good match" with ``refuse_poor``. None: every match
        is good.
    refuse_poor : bool
        Refuse the matches worse than ``max_residual`` instead of flagging them
        (colorps 0.2's behaviour: a clean render's pixels that mix two surfaces
        or a shadow's edge then leave holes, 1 % of a Mitsuba capture whose
        normals were 0.5 degrees off, median).
    max_distance : float or None
        Largest plain signature distance per band of a solved pixel (the
        unweighted distance of colorps 0.1). None: no such limit.
    refine : {"quadratic", "none"}
        Refine each solved normal past the gauge's pixel grid
        (:mod:`colorps.refine`), with a per-pixel uncertainty; "none" keeps
        the table's normal.
    encoding : {"auto", "linear", "srgb"}
        Files only: how stored values map to linear light ("auto": integer
        formats sRGB, floating-point formats linear).
    height : bool
        Files only: also integrate and write the height map, relief and
        overview pictures.
    mesh : {None, "ply", "obj", "both"}
        Files only: also write a mesh of the height field (needs ``height``).
    normal_convention : {"opengl", "directx"}
        Files only: normal.png's green channel points up ("opengl", as
        normal.exr) or down ("directx").
    viewer : bool
        Files only: write the results viewer, index.html (:mod:`colorps.viewer`).
    max_input_gib : float
        Files only: refuse a stack whose decoded pixels (float32) would take
        more than this many GiB, before decoding any (headers are read first).
        A tiled run checks one tile against it.
    memory_limit_gib : float, "auto" or None
        Files only: choose ``tile`` so that the run's estimated peak memory
        stays under this many GiB (:func:`colorps.memory.rows_for_memory`);
        refuse the run when even the smallest tiles would not fit. "auto":
        ``colorps.memory.AUTO_MEMORY_FRACTION`` of the memory available when the run starts
        (:func:`colorps.memory.available_memory_bytes`: the system's, within a
        container's or cluster job's cgroup limit), so a capture larger than the
        machine's memory runs in tiles instead of running out of it. None: no
        limit. Ignored when ``tile`` is given.
    brdf : {"fitted", "lambert"}
        Virtual gauges only (``--lights``): the finish the gauge is rendered
        with. "fitted": a diffuse falloff and highlight fitted to the scene's
        own observations, twice: at a Lambertian gauge's normals, then at the
        first fit's (:mod:`colorps.brdf`); "lambert":
        an ideal matte finish.
    finish_check : bool
        Files, gauge mode: when the scene matches a matte gauge far worse than
        its noise explains (:func:`colorps.gauge_check.finish_differs`: the
        gauge's finish is not the scene's; a little worse,
        :func:`colorps.gauge_check.finish_may_differ`, once the scene's own
        fitted finish shows it), solve it again with the lights measured on the
        gauge and the scene's own fitted finish
        (:func:`colorps.gauge_finish.with_gauge_lights`), and keep that when it
        matches clearly better (:func:`colorps.gauge_check.judge_finish`).
    interreflections : bool
        Files, untiled: where the solved object sees itself (a concave one),
        take out the light its surfaces bounce onto each other, estimated from
        the images and the solved shape, and solve again
        (:func:`colorps.interreflection.without_interreflections`).
    tile : int or None
        Files only: process the scene in bands of this many rows, each read
        from the files when needed (:mod:`colorps.tiles`); the same maps as an
        untiled run. None: the whole scene at once.

    Examples
    --------
    >>> from colorps import Options
    >>> Options().max_residual, Options(mode="mono").replace(threads=1).threads
    (10.0, 1)
    """

    mode: Literal["colour", "mono"] = "colour"
    band: int | Literal["luminance"] | None = None
    colourspace: str = "sRGB"
    grid_n: int | Literal["auto"] | None = None
    threads: int | None = None
    dark_level: float | Literal["auto"] = "auto"
    clip_level: float | Literal["auto"] | None = "auto"
    read_noise: float | Literal["auto"] = "auto"
    gain: float | Literal["auto"] = "auto"
    band_weights: bool = True
    light_subsets: bool = True
    max_dropped_lights: int = 2
    max_residual: float | None = 10.0
    refuse_poor: bool = False
    max_distance: float | None = None
    refine: Literal["quadratic", "none"] = "quadratic"
    encoding: Literal["auto", "linear", "srgb"] = "auto"
    height: bool = True
    mesh: Literal["ply", "obj", "both"] | None = None
    normal_convention: Literal["opengl", "directx"] = "opengl"
    viewer: bool = True
    max_input_gib: float = 8.0
    brdf: Literal["fitted", "lambert"] = "fitted"
    finish_check: bool = True
    interreflections: bool = True
    tile: int | None = None
    memory_limit_gib: float | Literal["auto"] | None = "auto"

    def __post_init__(self) -> None:
        if self.mode not in _MODES:
            raise InputError(f"mode: expected 'colour' or 'mono', got {self.mode!r}")
        if self.band is not None and self.band != "luminance" and not _is_count(self.band, 0):
            raise InputError(f"band: expected 'luminance' or a channel index, "
                             f"got {self.band!r}")
        for name, given in (("band", self.band is not None),
                            ("colourspace", self.colourspace != type(self).colourspace)):
            if given and self.mode == "colour":  # (not silently ignored)
                raise InputError(f"{name}: chooses the one band of mono mode, but the mode is "
                                 "colour (the default), which matches every band: pass "
                                 "--mode mono with it, or leave it out")
        if self.grid_n is not None and self.grid_n != "auto" and not _is_count(self.grid_n, 1):
            raise InputError(f"grid_n: expected a positive integer, 'auto' or None, "
                             f"got {self.grid_n!r}")
        if self.threads is not None and not _is_count(self.threads, 1):
            raise InputError(f"threads: expected a positive integer or None, "
                             f"got {self.threads!r}")
        if self.dark_level != "auto" and not _is_positive(self.dark_level):
            raise InputError(f"dark_level: expected a linear value > 0 or 'auto', "
                             f"got {self.dark_level!r}")
        if self.clip_level not in ("auto", None) and not _is_positive(self.clip_level):
            raise InputError(f"clip_level: expected a linear value > 0, 'auto' or None, "
                             f"got {self.clip_level!r}")
        if self.read_noise != "auto" and not (_is_positive(self.read_noise)
                                              or self.read_noise == 0):
            raise InputError(f"read_noise: expected a linear value >= 0 or 'auto', "
                             f"got {self.read_noise!r}")
        if self.gain != "auto" and not (_is_positive(self.gain) or self.gain == 0):
            raise InputError(f"gain: expected a value >= 0 or 'auto', got {self.gain!r}")
        if not _is_count(self.max_dropped_lights, 0):
            raise InputError(f"max_dropped_lights: expected an integer >= 0, "
                             f"got {self.max_dropped_lights!r}")
        if self.max_residual is not None and not _is_positive(self.max_residual):
            raise InputError(f"max_residual: expected a value > 0 or None, "
                             f"got {self.max_residual!r}")
        if not isinstance(self.refuse_poor, bool):
            raise InputError(f"refuse_poor: expected True or False, got {self.refuse_poor!r}")
        if self.max_distance is not None and not _is_positive(self.max_distance):
            raise InputError(f"max_distance: expected a value > 0 or None, "
                             f"got {self.max_distance!r}")
        if self.refine not in ("quadratic", "none"):
            raise InputError(f"refine: expected 'quadratic' or 'none', got {self.refine!r}")
        if self.encoding not in _ENCODINGS:
            raise InputError(f"encoding: expected 'auto', 'linear' or 'srgb', "
                             f"got {self.encoding!r}")
        if self.brdf not in _BRDFS:
            raise InputError(f"brdf: expected 'fitted' or 'lambert', got {self.brdf!r}")
        if self.normal_convention not in NORMAL_CONVENTIONS:
            raise InputError(f"normal_convention: expected one of {NORMAL_CONVENTIONS}, "
                             f"got {self.normal_convention!r}")
        if not isinstance(self.viewer, bool):
            raise InputError(f"viewer: expected True or False, got {self.viewer!r}")
        if self.mesh not in _MESHES:
            raise InputError(f"mesh: expected 'ply', 'obj', 'both' or None, got {self.mesh!r}")
        if self.tile is not None and (isinstance(self.tile, bool) or
                                      not isinstance(self.tile, int) or self.tile < 1):
            raise InputError(f"tile: expected a number of rows >= 1 or None, got {self.tile!r}")
        if self.memory_limit_gib not in ("auto", None) and \
                not _is_positive(self.memory_limit_gib):
            raise InputError(f"memory_limit_gib: expected a value > 0, 'auto' or None, "
                             f"got {self.memory_limit_gib!r}")
        if not _is_positive(self.max_input_gib):
            raise InputError(f"max_input_gib: expected a value > 0, got {self.max_input_gib!r}")
        if self.mesh is not None and not self.height:
            raise InputError("mesh: a mesh needs the height map (height=True)")

    def replace(self, **changes) -> Options:
        """A copy with some fields changed (checked like a new object)."""
        unknown = sorted(set(changes) - {f.name for f in dataclasses.fields(self)})
        if unknown:
            raise InputError(f"unknown option(s): {', '.join(unknown)}")
        return dataclasses.replace(self, **changes)

    def with_levels(self, clip_level: float | None, dark_level: float) -> Options:
        """Resolve "auto" levels to the given ones (those of the input files)."""
        return self.replace(
            clip_level=clip_level if self.clip_level == "auto" else self.clip_level,
            dark_level=dark_level if self.dark_level == "auto" else self.dark_level)

    @property
    def mesh_kinds(self) -> tuple[str, ...]:
        """Mesh file extensions to write ("ply", "obj"), possibly none."""
        return ("ply", "obj") if self.mesh == "both" else (self.mesh,) if self.mesh else ()

    def as_dict(self) -> dict:
        """The fields as a plain dict (for report.json)."""
        return dataclasses.asdict(self)


def _is_count(value, smallest: int) -> bool:
    return (not isinstance(value, bool) and isinstance(value, (int, np.integer))
            and value >= smallest)


def _is_positive(value) -> bool:
    return (not isinstance(value, (bool, str)) and isinstance(value, (int, float, np.number))
            and bool(np.isfinite(value)) and value > 0)
