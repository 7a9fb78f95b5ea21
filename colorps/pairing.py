"""Which light goes with which image: checked, never guessed.

Images and lights are paired in order, and a wrong order gives confident wrong
normals (25-57 degrees off, measured) with nothing to show for it. Two mistakes
users make are caught here:

* **Images in the wrong order.** An unquoted shell glob hands the images over
  sorted as text (``img1, img10, img11, img2, ...``); colorps sorts a quoted glob
  naturally itself. Explicit paths out of natural order get a
  :class:`~colorps.errors.PairingWarning` naming the first pair out of order.
* **A light file that names other images.** An ``.lp`` file names the image of
  each light. When every name matches a scene file (by file name without its
  extension, ignoring case, so a converted ``IMG_0001.tif`` matches
  ``IMG_0001.JPG``), the lights are re-paired by name; when some match and others
  do not, the run is refused, naming them; when none match (the images were
  renamed), they are paired in order with a warning.

:func:`pairing_record` is what report.json says of the pairing.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .errors import InputError, PairingWarning
from .lights import Lights

__all__ = ["check_natural_order", "pair_lights", "pairing_record"]


def check_natural_order(paths: Sequence[Path], patterns, name: str) -> None:
    """Warn when explicitly listed ``paths`` are not in natural order."""
    from natsort import natsorted

    if isinstance(patterns, (str, Path)) or len(patterns) < 2:
        return  # one glob or list file: sorted by colorps
    names = [p.name for p in paths]
    ordered = natsorted(names)
    if names == ordered:
        return
    k = next(i for i, (a, b) in enumerate(zip(names, ordered)) if a != b)
    warnings.warn(f"{paths[k]}: the {name} images are listed out of natural order "
                  f"({names[k]} is image {k + 1}, before {ordered[k]}); they are paired "
                  "with the lights in the order given. Quote a glob ('img_*.png') to "
                  "let colorps sort it", PairingWarning, stacklevel=3)


def pair_lights(lights: Lights, scene_paths: Sequence[Path], source) -> Lights:
    """The lights in the order of the scene images, by the names of an ``.lp`` file.

    Parameters
    ----------
    lights : Lights
        As read from ``source`` (names empty unless it was an ``.lp`` file).
    scene_paths : sequence of Path
    source : str or Path
        The light file, for messages.

    Returns
    -------
    Lights
        Re-ordered when every name matches a scene file; as given when there are
        no names, or none match (with a warning).

    Raises
    ------
    InputError
        Some names match scene files and some do not, or two lights name one image.
    """
    if not lights.names:
        return lights
    stems = [_stem(p) for p in scene_paths]
    wanted = [_stem(n) for n in lights.names]
    found = [w in stems for w in wanted]
    if not any(found):
        warnings.warn(f"{source}: its image names ({lights.names[0]}, ...) match none of the "
                      f"scene files ({Path(scene_paths[0]).name}, ...); the lights are paired "
                      "with the images in order", PairingWarning, stacklevel=3)
        return lights
    if not all(found) or len(set(wanted)) != len(wanted) or set(wanted) != set(stems):
        missing = [n for n, f in zip(lights.names, found) if not f]
        unlit = [Path(p).name for p, s in zip(scene_paths, stems) if s not in wanted]
        raise InputError(f"{source}: its image names and the scene files disagree "
                         f"(lights for {', '.join(missing[:3]) or 'no missing image'}"
                         f"{'...' if len(missing) > 3 else ''} with no scene file; scene "
                         f"files {', '.join(unlit[:3]) or 'none'}"
                         f"{'...' if len(unlit) > 3 else ''} with no light): check that "
                         "the light file is this capture's")
    order = [wanted.index(s) for s in stems]
    if order != list(range(len(order))):
        first = next(k for k, i in enumerate(order) if i != k)
        warnings.warn(f"{source}: the lights are listed in another order than the scene "
                      f"images ({Path(scene_paths[first]).name} is light {order[first] + 1} "
                      f"of the file, image {first + 1}); re-paired by name",
                      PairingWarning, stacklevel=3)
    return Lights(lights.directions[order], lights.intensities[order],
                  tuple(lights.names[i] for i in order))


def pairing_record(scene_paths: Sequence[Path], gauge_paths: Sequence[Path],
                   lights: Lights | None) -> list[dict]:
    """report.json's pairing: per image, its scene file and its gauge file or light."""
    rows = []
    for k, path in enumerate(scene_paths):
        row = {"image": k + 1, "scene": str(path)}
        if gauge_paths:
            row["gauge"] = str(gauge_paths[k])
        if lights is not None:
            row["light"] = np.round(lights.directions[k], 6).tolist()
            if lights.names:
                row["light_name"] = lights.names[k]
        rows.append(row)
    return rows


def _stem(name) -> str:
    return Path(str(name)).stem.lower()
