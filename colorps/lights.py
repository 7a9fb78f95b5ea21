"""Calibrated lights: directions and intensities, and the files they come in.

=========  ===================================================================
format     content
=========  ===================================================================
``.txt``   one light per line, "x y z" (DiLiGenT's light_directions.txt),
           optionally after a line holding just the count; intensities in a
           second file, one "r g b" per line (light_intensities.txt)
``.lp``    the RTI format: a count line, then "filename x y z" per light; as
           written on Windows too (backslash paths with spaces, decimal
           commas, CRLF line ends)
``.json``  ``{"directions": [[x, y, z], ...], "intensities": [[r, g, b], ...]}``
=========  ===================================================================

Directions are unit vectors towards the light in camera space (x right, y up,
z towards the camera), in the order of the images. Intensities are linear, one
per band (default 1).
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import InputError

__all__ = ["DIRECTION_HEADER", "LIGHT_FORMATS", "Lights", "direction_columns", "read_lights",
           "write_intensities", "write_lights"]

#: File formats of :func:`read_lights` and :func:`write_lights`.
LIGHT_FORMATS = (".txt", ".lp", ".json")
#: A direction must have a norm within this of 1 before it is normalised
#: (files store a few digits), and point at least this far above the horizon.
NORM_TOLERANCE = 0.05
MIN_ELEVATION_Z = 1e-3


@dataclass(frozen=True)
class Lights:
    """Distant lights of an m-image capture, one per image.

    Attributes
    ----------
    directions : (m, 3) ndarray of float64
        Unit vectors towards the lights (camera space).
    intensities : (m, c) ndarray of float64
        Linear intensity of each light in each band.
    names : tuple of str
        Image file names (from ``.lp`` files), or empty.

    Examples
    --------
    >>> from colorps import Lights
    >>> lights = Lights([[0, 0, 1], [0.6, 0, 0.8]])
    >>> lights.images, lights.intensities.tolist()
    (2, [[1.0], [1.0]])
    """

    directions: np.ndarray
    intensities: np.ndarray | None = None
    names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        d = _directions(self.directions, "lights")
        i = np.ones((len(d), 1)) if self.intensities is None else \
            np.asarray(self.intensities, dtype=np.float64)
        if i.ndim == 1:
            i = i[:, None]
        if i.ndim != 2 or i.shape[0] != len(d):
            raise InputError(f"light intensities: expected {len(d)} rows (one per light), "
                             f"got shape {i.shape}")
        if not np.all(np.isfinite(i)) or np.any(i <= 0):
            raise InputError("light intensities: values must be finite and > 0")
        object.__setattr__(self, "directions", d)
        object.__setattr__(self, "intensities", i)
        object.__setattr__(self, "names", tuple(self.names))

    @property
    def images(self) -> int:
        return self.directions.shape[0]

    def as_lighting(self, bands: int):
        """The :class:`colorps.synth.Lighting` of these lights with ``bands`` bands."""
        from .synth import Lighting

        colours = np.broadcast_to(self.intensities, (self.images, bands)) \
            if self.intensities.shape[1] in (1, bands) else None
        if colours is None:
            raise InputError(f"light intensities have {self.intensities.shape[1]} bands but "
                             f"the images have {bands}")
        return Lighting(self.directions[:, None, :], np.array(colours)[:, None, :])


def _directions(values, source: str) -> np.ndarray:
    try:
        d = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{source}: light directions must be numbers") from None
    if d.ndim != 2 or d.shape[1] != 3 or d.shape[0] == 0:
        raise InputError(f"{source}: expected one 'x y z' direction per light, got shape "
                         f"{d.shape}")
    for k, row in enumerate(d, start=1):
        norm = np.linalg.norm(row)
        if not np.all(np.isfinite(row)):
            raise InputError(f"{source}: light {k} is not a finite direction ({row.tolist()})")
        if norm == 0 or abs(norm - 1.0) > NORM_TOLERANCE:
            raise InputError(f"{source}: light {k} has length {norm:.3g}, not a unit "
                             "direction")
        if row[2] / norm < MIN_ELEVATION_Z:
            raise InputError(f"{source}: light {k} points below the horizon (z = "
                             f"{row[2]:.3g}; z is towards the camera)")
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _numbers(path: Path, lines: Sequence[str], width: int, what: str) -> np.ndarray:
    rows = []
    for number, line in enumerate(lines, start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        try:
            rows.append([float(v) for v in parts])
        except ValueError:
            raise InputError(f"{path}: line {number} is not {width} number"
                             f"{'s' if width > 1 else ''} ({line!r})") \
                from None
        if len(rows[-1]) != width:
            raise InputError(f"{path}: line {number} has {len(rows[-1])} values, expected "
                             f"{width} ({what})")
    if not rows:
        raise InputError(f"{path}: holds no {what}")
    return np.array(rows)


def _lp_line(path: Path, number: int, line: str) -> tuple[str, list[float]]:
    """(file name, [x, y, z]) of one light line of an ``.lp`` file.

    The last three fields are the direction (decimal commas allowed, as
    Windows writes them in some locales, or the three joined by commas);
    everything before them is the image's path, spaces included, of which the
    file name is kept (Windows or POSIX separators)."""
    from pathlib import PureWindowsPath

    fields = line.strip().split()
    numbers = None
    if len(fields) >= 2 and fields[-1].count(",") == 2 and "." in fields[-1]:
        numbers, name = fields[-1].split(","), fields[:-1]  # "x,y,z"
    elif len(fields) >= 4:
        numbers, name = fields[-3:], fields[:-3]
    try:
        direction = [float(v.replace(",", ".")) for v in numbers] if numbers else None
    except ValueError:
        direction = None
    if direction is None or not name:
        raise InputError(f"{path}: line {number} is not 'filename x y z' ({line.strip()!r})")
    name = " ".join(name).strip('"')
    return PureWindowsPath(name).name if "\\" in name else Path(name).name, direction


def _without_count_line(lines: Sequence[str]) -> list[str]:
    """The lines of a ``.txt`` of directions without a first line that holds
    only their count (a common layout)."""
    data = [line for line in lines if line.split("#", 1)[0].strip()]
    if data and len(data[0].split("#", 1)[0].split()) == 1:
        try:
            count = int(data[0].split("#", 1)[0])
        except ValueError:
            return list(lines)
        if count == len(data) - 1:
            return data[1:]
    return list(lines)


def read_lights(path, intensities=None, *, images: int | None = None) -> Lights:
    """Read a light file (see the module docstring).

    Parameters
    ----------
    path : str or Path
        ``.txt``, ``.lp`` or ``.json``.
    intensities : str or Path, optional
        A ``.txt`` of one "r g b" (or one value) per light, for ``.txt`` and
        ``.lp`` directions.
    images : int, optional
        The number of images the lights must match.

    Raises
    ------
    InputError
        Unreadable file, wrong count, NaN, zero or non-unit vectors, lights
        below the horizon; the message names the file (and line).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in LIGHT_FORMATS:
        raise InputError(f"{path}: light files are {', '.join(LIGHT_FORMATS)}")
    try:
        text = path.read_text(encoding="utf-8-sig", errors="replace")
    except OSError as exc:
        raise InputError(f"{path}: cannot read light file ({exc.strerror})") from None
    names: tuple[str, ...] = ()
    values = None
    if suffix == ".json":
        try:
            doc = json.loads(text)
            directions = doc["directions"]
            values = doc.get("intensities")
        except (ValueError, KeyError, TypeError) as exc:
            raise InputError(f"{path}: not a colorps light file ({exc})") from None
        directions = np.asarray(directions, dtype=np.float64) if isinstance(
            directions, list) else directions
    elif suffix == ".lp":
        lines = [line for line in text.splitlines() if line.strip()]
        try:
            count = int(lines[0].split()[0])
        except (IndexError, ValueError):
            raise InputError(f"{path}: the first line of an .lp file is the light count") \
                from None
        body = lines[1:]
        if len(body) != count:
            raise InputError(f"{path}: says {count} lights but lists {len(body)}")
        names, rows = zip(*(_lp_line(path, number, line)
                            for number, line in enumerate(body, start=2)))
        directions = np.array(rows)
    else:
        directions = _numbers(path, _without_count_line(text.splitlines()), 3,
                              "light directions")
    if intensities is not None:
        ipath = Path(intensities)
        try:
            lines = ipath.read_text().splitlines()
        except OSError as exc:
            raise InputError(f"{ipath}: cannot read intensities ({exc.strerror})") from None
        first = next((line for line in lines if line.split("#", 1)[0].strip()), "")
        width = len(first.replace(",", " ").split()) or 1
        values = _numbers(ipath, lines, width, "light intensities")
    directions = _directions(directions, str(path))
    try:
        lights = Lights(directions, values, names)
    except InputError as exc:  # the intensities: name their own file
        source = path if intensities is None else Path(intensities)
        raise InputError(f"{source}: {exc}") from None
    if images is not None and lights.images != images:
        raise InputError(f"{path}: lists {lights.images} lights but there are {images} "
                         "images; they are paired in order")
    return lights


def write_lights(lights: Lights, path, *, names: Sequence[str] | None = None) -> Path:
    """Write lights as ``.txt`` (directions only), ``.lp`` or ``.json``."""
    from .io import atomic_target

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in LIGHT_FORMATS:
        raise InputError(f"{path}: light files are {', '.join(LIGHT_FORMATS)}")
    names = list(names or lights.names or [f"image_{k:03d}" for k in range(lights.images)])
    if suffix == ".json":
        text = json.dumps(dict(directions=lights.directions.tolist(),
                               intensities=lights.intensities.tolist()), indent=1)
    elif suffix == ".lp":
        text = f"{lights.images}\n" + "".join(
            f"{name} {x:.9g} {y:.9g} {z:.9g}\n" for name, (x, y, z) in
            zip(names, lights.directions, strict=True))
    else:
        text = "".join(f"{x:.9g} {y:.9g} {z:.9g}\n" for x, y, z in lights.directions)
    with atomic_target(path) as tmp:
        tmp.write_text(text)
    return path


def write_intensities(lights: Lights, path) -> Path:
    """Write the lights' intensities as ``.txt``, one "r g b" (one value per band)
    per image: the file ``--light-intensities`` reads."""
    from .io import atomic_target

    path = Path(path)
    text = "".join(" ".join(f"{v:.9g}" for v in row) + "\n" for row in lights.intensities)
    with atomic_target(path) as tmp:
        tmp.write_text(text)
    return path


#: The first columns of calibrate-lights' tables (:func:`direction_columns`).
DIRECTION_HEADER = f"{'image':24s} {'x':>7s} {'y':>7s} {'z':>7s} {'elev':>5s}"


def direction_columns(name: str, direction) -> str:
    """An image's name, its light's direction and elevation (degrees), as the
    first columns of calibrate-lights' tables."""
    x, y, z = direction
    return (f"{name[:24]:24s} {x:7.4f} {y:7.4f} {z:7.4f} "
            f"{np.degrees(np.arcsin(np.clip(z, -1, 1))):5.1f}")
