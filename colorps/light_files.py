"""Sphere photographs in, a light file out: the work behind ``colorps calibrate-lights``.

:func:`calibrate_lights_files` checks the output first, reads the sphere's
images, finds its circle (or takes it from ``--sphere`` or a mask), fits the
lights (a mirror's highlights: :mod:`colorps.calibrate`; a matte sphere's
shading: :mod:`colorps.matte_lights`) and writes them (:mod:`colorps.lights`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np

from .calibrate import calibrate_lights, highlight_table, sphere_from_mask
from .camera import Camera
from .errors import InputError, OutputError
from .gauge import find_sphere
from .io import check_stack_files, expand_paths, input_levels, read_mask, read_stack
from .lights import LIGHT_FORMATS, write_intensities, write_lights
from .matte_lights import matte_sphere_lights, matte_table

__all__ = ["calibrate_lights_files"]


def calibrate_lights_files(image_patterns: str | Sequence[str],
                           sphere: Literal["auto"] | tuple[float, float, float] | None, out, *,
                           sphere_mask=None, matte: bool = False, encoding="auto",
                           camera: Camera | None = None, albedo=1.0,
                           overwrite: bool = False):
    """Lights from a sphere's images, written as a light file.

    Parameters
    ----------
    image_patterns : str or sequence of str
        The sphere's images, one per light, in capture order.
    sphere : "auto", (cx, cy, r) or None
        The sphere's silhouette in pixels, or found with :func:`colorps.find_sphere`
        on the images (it needs the sphere's disk brighter than the background);
        None with ``sphere_mask``.
    out : str or Path
        ``.txt`` (one "x y z" per line), ``.lp`` (count, then "file x y z") or
        ``.json`` (directions and intensities).
    sphere_mask : str or Path, optional
        A mask image of the sphere (non-zero on it), for a dark sphere that
        ``"auto"`` cannot find (:func:`colorps.calibrate.sphere_from_mask`).
    matte : bool, optional
        A matte sphere (:func:`colorps.matte_lights.matte_sphere_lights`), not a
        mirror's highlights; into a ``.txt`` or ``.lp`` file its intensities go
        to ``<stem>_intensities.txt`` beside it.
    camera : Camera, optional
        With ``matte``: the pinhole camera the images were taken with (the
        sphere's normals from the true rays). Default orthographic.
    albedo : float or (c,) array_like, optional
        With ``matte``: the sphere's albedo, one value or one per band (the
        intensities are relative to it; default 1).

    Returns
    -------
    (Lights, list of Highlight or MatteLight, (cx, cy, r), table lines, paths written)
    """
    out = Path(out)
    if out.suffix.lower() not in LIGHT_FORMATS:
        raise InputError(f"{out}: light files are {', '.join(LIGHT_FORMATS)}")
    beside = matte and out.suffix.lower() != ".json"  # where the intensities go
    targets = [out, out.with_name(f"{out.stem}_intensities.txt")] if beside else [out]
    for target in (t for t in targets if t.exists() and not overwrite):
        raise OutputError(f"{target}: already exists; use --overwrite to replace it")
    if not out.parent.is_dir():
        raise OutputError(f"{out.parent}: output folder does not exist")
    what = "matte sphere" if matte else "mirror sphere"
    if (camera is not None or np.any(np.asarray(albedo) != 1.0)) and not matte:
        raise InputError("--camera and --albedo are for a matte sphere (--matte): a mirror "
                         "sphere's highlights give directions only, read orthographically")
    paths = expand_paths(image_patterns, name=what)
    info = check_stack_files(paths, name=what)[0]
    if (sphere is None) == (sphere_mask is None):
        raise InputError(f"give the {what}'s circle (--sphere) or its mask "
                         "(--sphere-mask), one of them")
    stack, _ = read_stack(paths, encoding, name=what)
    if sphere_mask is not None:
        try:
            found_sphere = sphere_from_mask(read_mask(sphere_mask, stack.shape[1:3]))
        except InputError as exc:
            raise InputError(f"{sphere_mask}: {exc}") from None
    else:
        found_sphere = find_sphere(stack, camera) if sphere == "auto" else tuple(sphere)
    names = [p.name for p in paths]
    fit, table = (matte_sphere_lights, matte_table) if matte else \
        (calibrate_lights, highlight_table)
    lights, found = fit(stack, found_sphere, clip_level=input_levels(info, encoding)[0],
                        names=names, **({"camera": camera, "albedo": albedo} if matte else {}))
    write_lights(lights, out)
    if len(targets) > 1:
        write_intensities(lights, targets[1])
    return lights, found, found_sphere, table(names, found), targets
