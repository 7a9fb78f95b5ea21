"""Pictures people would rather look at than read: shaded relief and an overview.

Images are returned as float arrays in 0..1 (already display-encoded) and
written by :mod:`colorps.io`, like every other image.
"""

from __future__ import annotations

import numpy as np

from .io import srgb_encode

__all__ = ["as_rgb", "overview", "overview_step", "shaded_relief"]

#: The overview's panels are drawn from images subsampled to at most this many
#: pixels on a side (a panel is 320 pixels wide): drawing a 4096-pixel image
#: into it only costs time.
OVERVIEW_SIDE = 640
#: Overview layout in pixels: panel side, margin around a panel, title text size;
#: and the font (one of OpenImageIO's bundled fonts).
PANEL_SIDE = 300
PANEL_MARGIN = 10
TITLE_PX = 16
FONT = "DroidSans"


def as_rgb(values) -> np.ndarray:
    """Three display bands: the first three bands, or one band repeated as grey."""
    v = np.asarray(values, dtype=np.float32)
    return v[..., :3] if v.shape[-1] >= 3 else np.repeat(v[..., :1], 3, axis=-1)


def shaded_relief(height, *, azimuth_deg: float = 135.0, elevation_deg: float = 45.0,
                  exaggeration: float = 1.0) -> np.ndarray:
    """Grey hill-shading of a height map, lit from the upper left by default.

    Parameters
    ----------
    height : (H, W) array_like
        Height in pixels (NaN outside: drawn black).
    azimuth_deg, elevation_deg : float, optional
        Light direction in the image plane (degrees from +x towards +y, y up)
        and above it.
    exaggeration : float, optional
        Vertical exaggeration of the relief.

    Returns
    -------
    (H, W) ndarray of float32 in 0..1
    """
    z = np.asarray(height, dtype=np.float32) * np.float32(exaggeration)
    inside = np.isfinite(z)
    if not inside.any():
        return np.zeros(z.shape, dtype=np.float32)
    if not inside.all():
        z = _rim_filled(z, inside)
    drow = np.gradient(z, axis=0) if z.shape[0] > 1 else np.zeros_like(z)
    dx = np.gradient(z, axis=1) if z.shape[1] > 1 else np.zeros_like(z)
    az, el = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    light = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)],
                     dtype=np.float32)
    # The unit normal is (-dx, drow, 1) / |.| (y up: dz/dy = -dz/drow).
    shade = (light[2] - dx * light[0] + drow * light[1]) / np.sqrt(dx * dx + drow * drow + 1)
    return np.where(inside, 0.1 + 0.9 * np.clip(shade, 0.0, 1.0), 0.0).astype(np.float32)


def _rim_filled(z: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """Heights with each outside pixel next to the inside (4-neighbours) set to a
    neighbour's height, the rest 0: the central differences of np.gradient at
    inside pixels then never reach across the rim."""
    out = np.where(inside, z, np.float32(0.0))
    done = inside.copy()
    whole = slice(None)
    for dst, src in ((slice(1, None), slice(None, -1)), (slice(None, -1), slice(1, None))):
        for axis in (0, 1):
            to = (dst, whole) if axis == 0 else (whole, dst)
            of = (src, whole) if axis == 0 else (whole, src)
            take = ~done[to] & inside[of]
            out[to][take] = z[of][take]
            done[to] |= take
    return out


def overview_step(shape: tuple[int, ...]) -> int:
    """The overview draws every s-th row and column of an (H, W, ...) image:
    s = ceil(max(H, W) / OVERVIEW_SIDE), at least 1."""
    return max(1, -(-max(shape[:2]) // OVERVIEW_SIDE))


def overview(scene_image, normals, albedo, height, *, title: str = "") -> np.ndarray:
    """Side-by-side figure: scene photo, normal map, albedo, shaded relief.

    Each panel is fitted into PANEL_SIDE x PANEL_SIDE pixels under its title,
    on a white canvas; drawn with OpenImageIO (a triangle-filter resize, four
    times faster than its default Lanczos at this size, and text in its bundled
    fonts), so no plotting library is loaded.

    Parameters
    ----------
    scene_image : (H, W, c) array_like
        One linear scene image (e.g. the mean of the stack), or only the pixels
        drawn of it: every s-th row and column, s = :func:`overview_step`.
    normals : (H, W, 3) array_like
        Camera-space normals (NaN = unsolved).
    albedo : (H, W, c) array_like
        Linear albedo (NaN = unsolved).
    height : (H, W) array_like or None
        Height map (NaN outside), or None to leave the panel out.
    title : str, optional
        A line above the panels.

    Returns
    -------
    (h, w, 3) ndarray of float32 in 0..1
        The rendered figure (sRGB), ready for :func:`colorps.io.write_image`.
    """
    import OpenImageIO as oiio

    step = overview_step(np.shape(normals))
    pick = (slice(None, None, step), slice(None, None, step))
    normals, albedo = (np.asarray(a)[pick] for a in (normals, albedo))
    scene_image = np.asarray(scene_image)
    if scene_image.shape[:2] != normals.shape[:2]:
        scene_image = scene_image[pick]
    photo = as_rgb(scene_image)
    peak = np.nanpercentile(photo, 99.5) if np.isfinite(photo).any() else 1.0
    panels = [("scene (mean image)", srgb_encode(photo / (peak if peak > 0 else 1.0))),
              ("normals (n + 1) / 2", np.nan_to_num((np.asarray(normals) + 1) / 2, nan=0.0)),
              ("albedo", srgb_encode(as_rgb(albedo)))]
    if height is not None:
        # Slopes per subsampled pixel are step times steeper: shade the same relief.
        panels.append(("shaded relief", shaded_relief(np.asarray(height)[pick],
                                                      exaggeration=1.0 / step)))
    cell = PANEL_SIDE + 2 * PANEL_MARGIN
    top = 2 * TITLE_PX if title else 0
    canvas = np.ones((top + 2 * TITLE_PX + cell, cell * len(panels), 3), dtype=np.float32)
    for k, (_, image) in enumerate(panels):
        image = np.clip(np.nan_to_num(image, nan=0.0), 0.0, 1.0).astype(np.float32)
        image = image if image.ndim == 3 else np.repeat(image[..., None], 3, axis=-1)
        scale = PANEL_SIDE / max(image.shape[:2])
        ph, pw = (max(1, round(side * scale)) for side in image.shape[:2])
        fitted = oiio.ImageBufAlgo.resize(oiio.ImageBuf(np.ascontiguousarray(image)),
                                          "triangle", roi=oiio.ROI(0, pw, 0, ph, 0, 1, 0, 3))
        y0 = top + 2 * TITLE_PX + PANEL_MARGIN + (PANEL_SIDE - ph) // 2
        x0 = k * cell + PANEL_MARGIN + (PANEL_SIDE - pw) // 2
        canvas[y0:y0 + ph, x0:x0 + pw] = np.clip(fitted.get_pixels(oiio.FLOAT), 0.0, 1.0)
    figure = oiio.ImageBuf(canvas)
    black = (0.0, 0.0, 0.0)
    for k, (name, _) in enumerate(panels):
        oiio.ImageBufAlgo.render_text(figure, k * cell + cell // 2, top + TITLE_PX + TITLE_PX // 2,
                                      name, TITLE_PX, FONT, black, alignx="center")
    if title:
        oiio.ImageBufAlgo.render_text(figure, canvas.shape[1] // 2, top - TITLE_PX // 3,
                                      title, TITLE_PX + 2, FONT, black, alignx="center")
    if figure.has_error:
        raise RuntimeError(f"OpenImageIO could not draw the overview: {figure.geterror()}")
    return np.clip(figure.get_pixels(oiio.FLOAT), 0.0, 1.0)
