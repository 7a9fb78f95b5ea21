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

* **Images and lights paired out of step** (gauge images in another order than
  the scene's, a light file's lines in another order than the images): under
  distant lights the pixels of a matte surface lit in every image span, image by
  image, the same 3-D subspace of R^m as the lights' directions times their
  intensities (band by band), whatever the normals and albedos, and so do the
  gauge's. :func:`check_shading_pairing` measures the largest principal angle
  between the scene's subspace and the gauge's (or the light file's) and warns
  beyond MAX_PAIRING_ANGLE. An axis of the light file mirrored or swapped leaves
  the subspace as it is (:mod:`colorps.light_axes` sees those).

:func:`pairing_record` is what report.json says of the pairing.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .errors import InputError, PairingWarning
from .lights import Lights

__all__ = ["MAX_PAIRING_ANGLE", "check_natural_order", "check_shading_pairing",
           "light_subspaces", "pair_lights", "pairing_record", "shading_subspaces"]

#: Largest principal angle (degrees) between the scene's shading subspace and the
#: gauge's or the light file's, in the band where they agree best, for a pairing to
#: pass. Paired right: the bundled sample 0.01, Mitsuba's pots (bounced light, a
#: glossy coat, a gauge of another finish, perspective) 0.2-0.7, DiLiGenT Ball
#: (a strong highlight) 2.0, Oren-Nayar 0.5 scenes against a Lambertian gauge 2-4,
#: one also glossy, shadowed and clipped 10. Out of step: two of the sample's 8
#: images swapped 31, shuffled 79; Ball's light file off by one line 60, shuffled
#: 89 (two of its 96 lines swapped: 8, not seen; without its intensities: 23).
MAX_PAIRING_ANGLE = 20.0
#: A measurement is lit above this fraction of its band's brightest in the stack,
#: and may be clipped from UNCLIPPED_FRACTION of it up.
LIT_FRACTION = 0.02
UNCLIPPED_FRACTION = 0.98
#: Pixels lit in every image needed for a verdict, and the most used (a sample),
#: looked for among at most CANDIDATE_PIXELS of the mask (a fixed sample: a
#: 96-image megapixel stack is not copied band by band).
MIN_LIT_PIXELS = 100
LIT_SAMPLE = 20_000
CANDIDATE_PIXELS = 4 * LIT_SAMPLE
#: The subspace is fitted again on this share of the pixels it fits best, twice
#: (highlights, shadow edges and bounced light leave it).
KEEP_SHARE = 0.8
TRIM_ROUNDS = 2


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


def shading_subspaces(stack: np.ndarray, mask: np.ndarray | None = None
                      ) -> tuple[list[np.ndarray], int]:
    """Per band, an orthonormal (m, 3) basis of the span of the pixels lit and not
    clipped in every image (each pixel's m values scaled to unit length; the basis
    fitted again on the KEEP_SHARE it fits best, TRIM_ROUNDS times), and the fewest
    such pixels of a band (no basis when under MIN_LIT_PIXELS: an empty list)."""
    _m, _h, width, bands = stack.shape
    chosen = np.flatnonzero(np.ones(stack.shape[1:3], bool) if mask is None
                            else np.asarray(mask, bool))
    rng = np.random.default_rng(0)
    if len(chosen) > CANDIDATE_PIXELS:
        chosen = np.sort(rng.choice(chosen, CANDIDATE_PIXELS, replace=False))
    rows, cols = np.divmod(chosen, width)
    bases, fewest = [], None
    for b in range(bands):
        values = stack[:, rows, cols, b]  # (m, pixels)
        top = np.nanmax(values)  # lit, and not clipped, in every image
        lit = np.isfinite(values).all(axis=0) & (values > LIT_FRACTION * top).all(axis=0)
        lit &= (values < UNCLIPPED_FRACTION * top).all(axis=0)
        fewest = int(lit.sum()) if fewest is None else min(fewest, int(lit.sum()))
        if lit.sum() < MIN_LIT_PIXELS:
            return [], fewest
        columns = np.flatnonzero(lit)
        if len(columns) > LIT_SAMPLE:
            columns = np.sort(rng.choice(columns, LIT_SAMPLE, replace=False))
        pixels = values[:, columns].astype(np.float64)
        pixels /= np.linalg.norm(pixels, axis=0)
        for _ in range(TRIM_ROUNDS):
            basis = np.linalg.svd(pixels, full_matrices=False)[0][:, :3]
            misfit = np.linalg.norm(pixels - basis @ (basis.T @ pixels), axis=0)
            pixels = pixels[:, misfit <= np.quantile(misfit, KEEP_SHARE)]
        bases.append(np.linalg.svd(pixels, full_matrices=False)[0][:, :3])
    return bases, fewest


def light_subspaces(lights: Lights, bands: int) -> list[np.ndarray]:
    """Per band, an orthonormal (m, 3) basis of the span of the light file's
    directions times their intensities in that band."""
    colours = lights.as_lighting(bands).colours[:, 0, :]  # (m, c)
    return [np.linalg.qr(colours[:, b:b + 1] * lights.directions)[0] for b in range(bands)]


def check_shading_pairing(scene: np.ndarray, mask, reference: list[np.ndarray],
                          source, what: str) -> dict:
    """report.json's record of how far the scene's shading subspace lies from
    ``reference`` (:func:`shading_subspaces` of the gauge, or :func:`light_subspaces`
    of the light file ``what`` names), with a :class:`~colorps.errors.PairingWarning`
    naming ``source`` when the pairing looks out of step (``looks_out_of_step``)."""
    m = scene.shape[0]
    if m < 4 or not reference:
        return dict(skipped=f"{m} images" if m < 4 else f"too few lit pixels in {what}")
    bases, pixels = shading_subspaces(scene, mask)
    if not bases:
        return dict(skipped=f"{pixels} scene pixels lit in every image")
    angles = [float(np.degrees(np.arccos(np.clip(
        np.linalg.svd(ours.T @ theirs, compute_uv=False).min(), -1.0, 1.0))))
        for ours, theirs in zip(bases, reference, strict=True)]
    out_of_step = min(angles) > MAX_PAIRING_ANGLE
    if out_of_step:
        warnings.warn(
            f"{source}: the scene's images do not look lit by {what} in this order: the "
            f"span of their shading lies {min(angles):.0f} degrees from {what}'s (paired "
            f"right, under {MAX_PAIRING_ANGLE:.0f}). Check that they are in the same order "
            "(and, with a light file, its intensities); the normals are unreliable",
            PairingWarning, stacklevel=2)
    return dict(angle_deg=angles, pixels=pixels, looks_out_of_step=bool(out_of_step))
