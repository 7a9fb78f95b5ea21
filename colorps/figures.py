"""Pictures people would rather look at than read: shaded relief, an overview,
colour-mapped maps with a colour bar, and keys (legends) under map pictures.

Images are returned as float arrays in 0..1 (already display-encoded) and
written by :mod:`colorps.io`, like every other image. A map picture with a key
keeps the map at its own pixels in its top-left H x W corner; the key is a
strip below it (see :func:`with_key`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .io import srgb_encode
from .reasons import Reason

__all__ = ["COLOUR_MAP_STOPS", "DROPPED_COLOURS", "QUALITY_SCALE", "UNCERTAINTY_SCALE",
           "ColourScale", "as_rgb", "colour_mapped", "dropped_entries", "dropped_legend",
           "dropped_picture", "legend", "overview", "overview_step", "picture_codes",
           "reason_legend", "shaded_relief", "with_colour_bar", "with_key"]

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


#: The colour map of the quality and uncertainty pictures and of the viewer:
#: viridis (perceptually uniform, readable in grey and by colour-blind eyes) at
#: nine evenly spaced stops, 8-bit sRGB, linearly interpolated between them.
COLOUR_MAP_STOPS = ((68, 1, 84), (71, 45, 123), (59, 82, 139), (44, 114, 142), (33, 145, 140),
                    (40, 174, 128), (94, 201, 98), (173, 220, 48), (253, 231, 37))
#: Colours of lights.png and the viewer for 1, 2 and 3 or more dropped lights
#: (8-bit sRGB; none dropped: black).
DROPPED_COLOURS = ((90, 200, 255), (255, 170, 0), (255, 40, 200))
#: Pixels drawn at a time (bounded temporaries on large maps).
PICTURE_CHUNK = 1 << 16
#: Key strip under a map picture: text height as a fraction of the picture's
#: width, within these bounds (pixels).
KEY_TEXT_FRACTION = 1 / 40
KEY_TEXT_PX = (12, 48)


@dataclass(frozen=True)
class ColourScale:
    """A colour bar's range: values from ``lo`` to ``hi`` (``log``: evenly in
    log10) map to the colour map; values outside are drawn at its ends.

    Attributes
    ----------
    label : str
        What the values are, with their unit.
    lo, hi : float
        The ends of the bar (lo < hi; both > 0 when ``log``).
    log : bool
        Logarithmic bar.
    """

    label: str
    lo: float
    hi: float
    log: bool = False

    def position(self, values) -> np.ndarray:
        """Where values fall on the bar, 0..1 (NaN stays NaN)."""
        v = np.asarray(values, dtype=np.float64)
        lo, hi = self.lo, self.hi
        if self.log:
            with np.errstate(divide="ignore", invalid="ignore"):
                v = np.log10(np.maximum(v, lo))
            lo, hi = np.log10(lo), np.log10(hi)
        return np.clip((v - lo) / (hi - lo), 0.0, 1.0)

    def ticks(self) -> list[float]:
        """Tick values: the powers of ten on a log bar, else five even steps."""
        if self.log:
            first, last = int(np.ceil(np.log10(self.lo))), int(np.floor(np.log10(self.hi)))
            return [10.0 ** k for k in range(first, last + 1)]
        return list(np.linspace(self.lo, self.hi, 5))


#: The scales of quality.png and uncertainty.png (fixed, so that pictures of
#: different runs compare): about 1 noise unit is a match the noise explains.
QUALITY_SCALE = ColourScale("match residual (noise units)", 0.1, 100.0, log=True)
UNCERTAINTY_SCALE = ColourScale("uncertainty: 68 % radius of the normal (degrees)", 0.01, 10.0,
                                log=True)


def colour_mapped(values, scale: ColourScale) -> np.ndarray:
    """(H, W, 3) float32 sRGB picture of a map through the colour map; NaN is black."""
    values = np.asarray(values)
    out = np.empty((*values.shape, 3), dtype=np.float32)
    flat, flat_out = values.reshape(-1), out.reshape(-1, 3)
    for start in range(0, flat.size, PICTURE_CHUNK):  # bounded temporaries
        piece = slice(start, start + PICTURE_CHUNK)
        flat_out[piece] = _colours_at(scale.position(flat[piece]))
    return out


def _colours_at(position: np.ndarray) -> np.ndarray:
    """The colour map at positions 0..1 (float32 sRGB, (..., 3)); NaN is black."""
    stops = np.asarray(COLOUR_MAP_STOPS, dtype=np.float32) / 255.0
    at = np.nan_to_num(position, nan=0.0) * (len(stops) - 1)
    below = np.minimum(at.astype(np.int64), len(stops) - 2)
    frac = (at - below)[..., None].astype(np.float32)
    rgb = stops[below] * (1 - frac) + stops[below + 1] * frac
    return np.where(np.isnan(position)[..., None], np.float32(0.0), rgb).astype(np.float32)


def _key_text_px(width: int) -> int:
    low, high = KEY_TEXT_PX
    return int(np.clip(round(width * KEY_TEXT_FRACTION), low, high))


def _tick_text(value: float) -> str:
    return f"{value:g}"


def with_colour_bar(picture, scale: ColourScale) -> np.ndarray:
    """A map picture with a colour bar, its ticks and label in a strip below it."""
    width = np.shape(picture)[1]
    text = _key_text_px(width)
    bar_width = max(8 * text, min(width - 3 * text, 24 * text))
    bar = _colours_at(np.linspace(0.0, 1.0, bar_width))
    ticks = [(scale.position(v).item() * (bar_width - 1), _tick_text(v)) for v in scale.ticks()]
    return with_key(picture, _bar_key(bar, ticks, scale.label, text))


def _bar_key(bar: np.ndarray, ticks, label: str, text: int):
    """The drawing of a colour bar key: (width, height, draw(buf, x0, y0));
    ``ticks`` are (position along the bar in pixels, text)."""
    import OpenImageIO as oiio

    height = 4 * text + text // 2
    label_width = oiio.ImageBufAlgo.text_size(label, text, FONT).width

    def draw(buf, x0, y0):
        strip = np.repeat(bar[None], text, axis=0)
        start = x0 + text  # room for half a tick label at the bar's left end
        buf.set_pixels(oiio.ROI(start, start + bar.shape[0], y0, y0 + text, 0, 1, 0, 3), strip)
        for x, words in ticks:
            oiio.ImageBufAlgo.render_text(buf, int(start + x), y0 + 2 * text + text // 4, words,
                                          text, FONT, (0.0, 0.0, 0.0), alignx="center")
        oiio.ImageBufAlgo.render_text(buf, x0, y0 + 4 * text, label, text, FONT,
                                      (0.0, 0.0, 0.0))

    return max(bar.shape[0] + 2 * text, label_width), height, draw


def legend(entries, width: int):
    """The drawing of a legend (swatches and labels, wrapped into rows):
    (width, height, draw(buf, x0, y0)). ``entries``: (8-bit sRGB colour, label)."""
    import OpenImageIO as oiio

    text = _key_text_px(width)
    row_height = text + text // 2
    placed, x, y, used = [], 0, 0, 0
    for colour, label in entries:
        drawn = 2 * text + oiio.ImageBufAlgo.text_size(label, text, FONT).width
        if x and x + drawn + text > max(width, 16 * text):
            x, y = 0, y + row_height
        placed.append((x, y, colour, label))
        used = max(used, x + drawn)
        x += drawn + text

    def draw(buf, x0, y0):
        for px, py, colour, label in placed:
            swatch = np.broadcast_to(np.asarray(colour, np.float32) / 255.0, (text, text, 3))
            buf.set_pixels(oiio.ROI(x0 + px, x0 + px + text, y0 + py, y0 + py + text, 0, 1,
                                    0, 3), np.ascontiguousarray(swatch))
            oiio.ImageBufAlgo.render_text(buf, x0 + px + text + text // 2, y0 + py + text - 2,
                                          label, text, FONT, (0.0, 0.0, 0.0))

    return used, y + row_height, draw


def with_key(picture, key) -> np.ndarray:
    """``picture`` (H, W, 3) at its own pixels in the top-left corner, and below
    it a white strip with ``key`` = (width, height, draw) drawn in it (the
    figure is widened when the key is wider than the picture). ``picture`` is
    sRGB 0..1; the figure is returned as (H', W', 3) uint8 sRGB codes."""
    import OpenImageIO as oiio

    h, w = np.shape(picture)[:2]
    key_width, key_height, draw = key
    margin = _key_text_px(w) // 2
    canvas = np.full((h + key_height + 3 * margin, max(w, key_width + 2 * margin), 3), 255,
                     dtype=np.uint8)  # 8-bit throughout: a float canvas took 4 copies
    canvas[:h, :w] = _codes(picture)
    buf = oiio.ImageBuf(canvas)
    draw(buf, margin, h + 2 * margin)
    if buf.has_error:
        raise RuntimeError(f"OpenImageIO could not draw a key: {buf.geterror()}")
    return buf.get_pixels(oiio.UINT8)


def _codes(picture) -> np.ndarray:
    """8-bit codes of a 0..1 picture (see :func:`picture_codes`)."""
    picture = np.asarray(picture)
    return picture_codes(lambda rows: picture[rows], picture.shape, np.uint8)


def picture_codes(rows_of, shape: tuple[int, ...], dtype=np.uint8) -> np.ndarray:
    """Integer codes (uint8 or uint16, rounded) of a 0..1 picture of ``shape``,
    made by ``rows_of(rows)`` (a slice of rows) PICTURE_CHUNK pixels at a time:
    no picture-sized float temporaries."""
    top = np.iinfo(dtype).max
    out = np.empty(shape, dtype=dtype)
    step = max(1, PICTURE_CHUNK // max(1, shape[1]))  # rows of PICTURE_CHUNK pixels
    for start in range(0, shape[0], step):
        rows = slice(start, start + step)
        piece = np.asarray(rows_of(rows), dtype=np.float32)
        out[rows] = np.rint(np.clip(piece, 0.0, 1.0) * np.float32(top))
    return out


def dropped_picture(count) -> np.ndarray:
    """(H, W, 3) float32 sRGB picture of the number of lights dropped per pixel."""
    table = np.zeros((256, 3), dtype=np.float32)
    for k, rgb in enumerate(DROPPED_COLOURS, start=1):
        table[k:] = np.array(rgb) / 255.0
    return table[np.minimum(np.asarray(count), 255)]


def dropped_entries() -> list[tuple[tuple[int, int, int], str]]:
    """(colour, label) of each count :func:`dropped_picture` draws."""
    names = ("1 light dropped", "2 lights dropped", "3 or more dropped")
    return [((0, 0, 0), "none dropped"), *zip(DROPPED_COLOURS, names)]


def dropped_legend(width: int):
    """The legend of :func:`dropped_picture` (see :func:`legend`)."""
    return legend(dropped_entries(), width)


def reason_legend(width: int):
    """The legend of :func:`colorps.reasons.reason_picture` (see :func:`legend`)."""
    return legend([(r.colour, r.label) for r in Reason], width)
