"""index.html: a results viewer that relights the object in a web browser.

Every results folder gets ``index.html`` and a ``viewer/`` folder beside the
maps. The page needs no network and no server: its script and style are inline,
and its data are scripts in ``viewer/`` (a page opened from a file may run
scripts beside it, but may not read the pixels of images beside it). It shows

* the object **relit** under a light the user drags (Lambertian: linear albedo
  times the cosine of the light's angle to the normal, then sRGB; or, after a
  run with calibrated lights, the finish it fitted, as :mod:`colorps.relight`),
* the normals, albedo, shaded relief, height, quality, uncertainty, reasons
  and dropped lights, each with its colour bar or legend,
* the values under the cursor: pixel, reason, normal, albedo per band, height,
  quality, uncertainty and lights dropped.

The data form a pyramid of levels, coarsest first: level k holds every s_k-th
row and column of the maps (the values of those pixels, not averages), with s_k
halving from level to level down to the finest, whose longest side is at most
VIEWER_MAX_SIDE pixels. The page loads the coarsest level at once and a finer
one when the zoom needs it, and draws only the pixels on the screen, so a
16-megapixel result opens as fast as a small one. The .exr maps keep every
pixel at full precision.

Each level is ``viewer/level{k}.js``: a call ``colorpsLevel(k, {map: [high,
low]})`` with, per map, two 8-bit RGB PNGs (as data URLs) holding the high and
low bytes of its 16-bit codes (:mod:`colorps.codes`; per-channel ``lo`` and
``hi`` in the page's index):

========  =========================================================
map       channels
========  =========================================================
normal    x, y, z of the camera-space normal (y up), lo -1, hi 1
albedo    the first three bands (one for a single band), linear
scalars   height (pixels), quality (noise units), uncertainty (degrees)
codes     the reason's code, the number of lights dropped (code = value + 1)
========  =========================================================
"""

from __future__ import annotations

import base64
import html
import json
import shutil
import tempfile
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from importlib import resources
from pathlib import Path

import numpy as np

from .codes import code_range, encode
from .errors import InputError
from .figures import (
    COLOUR_MAP_STOPS,
    QUALITY_SCALE,
    UNCERTAINTY_SCALE,
    as_rgb,
    dropped_entries,
)
from .io import WRITE_THREADS, write_image
from .reasons import Reason
from .results import Reconstruction, default_band_names

__all__ = ["VIEWER_FILES", "VIEWER_MAX_SIDE", "VIEWER_MIN_SIDE", "pyramid_steps",
           "serve_viewer", "viewer_page", "write_viewer"]

#: The page and its data folder, in a results folder.
VIEWER_FILES = ("index.html", "viewer")
#: Longest side (pixels) of the finest level the page shows.
VIEWER_MAX_SIDE = 2048
#: Longest side above which a coarser level is added (the first one loaded).
VIEWER_MIN_SIDE = 512
#: Values of the codes map are stored as code = value + 1, exactly.
_COUNT_RANGE = (0.0, 65534.0)


def pyramid_steps(shape: tuple[int, int], max_side: int = VIEWER_MAX_SIDE,
                  min_side: int = VIEWER_MIN_SIDE) -> list[int]:
    """Sampling steps of the viewer's levels, coarsest first.

    The finest step is the smallest that brings the longest side to at most
    ``max_side``; each coarser level doubles it, until the longest side is at
    most ``min_side``.

    Examples
    --------
    >>> pyramid_steps((4096, 3072))
    [8, 4, 2]
    >>> pyramid_steps((300, 200))
    [1]
    """
    side = max(shape[:2])
    step = max(1, -(-side // max_side))
    steps = [step]
    while -(-side // steps[-1]) > min_side:
        steps.append(steps[-1] * 2)
    return steps[::-1]


def write_viewer(result: Reconstruction, out_dir, *, band_names=None, title: str = "",
                 finish: dict | None = None, max_side: int = VIEWER_MAX_SIDE,
                 min_side: int = VIEWER_MIN_SIDE,
                 finished: Callable[[], Reconstruction] | None = None) -> Path:
    """Write ``index.html`` and ``viewer/`` for a reconstruction into a folder.

    Parameters
    ----------
    result : Reconstruction
        Its height map is shown when it has one.
    out_dir : str or Path
        An existing folder.
    band_names : sequence of str, optional
        Names of the albedo's bands (default R, G, B / Y / B0, B1, ...).
    title : str, optional
        The page's heading.
    finish : dict, optional
        A fitted finish (:meth:`colorps.brdf.BRDF.as_dict`, report.json's
        ``brdf``): the page can relight with it.
    max_side, min_side : int, optional
        The pyramid's bounds (see :func:`pyramid_steps`).
    finished : callable, optional
        ``finished()`` returns ``result`` with its height, while the height is
        still being integrated: the maps that do not need it are encoded first
        (the finest level's, most of the work, while it waits).

    Returns
    -------
    Path
        The page.
    """
    out = Path(out_dir)
    maps = _maps(result)
    # Normals and codes have fixed ranges; the other maps span their values.
    ranges = {"normal": [(-1.0, 1.0)] * 3, "codes": [_COUNT_RANGE] * 2,
              "albedo": [code_range(channel) for channel in maps["albedo"]]}
    steps = pyramid_steps(result.normals.shape, max_side, min_side)
    data = out / "viewer"
    data.mkdir(exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=".png-", dir=data))
    try:
        # OpenImageIO's PNG encoder releases the GIL: the maps encode in parallel,
        # WRITE_THREADS at a time (each holds its codes and bytes).
        with ThreadPoolExecutor(WRITE_THREADS) as pool:
            def encode(name: str, k: int):  # level k's pair of PNGs of map ``name``
                return pool.submit(_png_pair, [c[::steps[k], ::steps[k]] for c in maps[name]],
                                   ranges[name], scratch / f"{k}-{name}")

            for k in reversed(range(len(steps))):  # the finest first (see ``finished``)
                pending = {name: encode(name, k) for name in maps}
                if "scalars" not in maps:  # (the height, waited for once)
                    result = result if finished is None else finished()
                    maps["scalars"] = _scalars(result)
                    ranges["scalars"] = [code_range(channel) for channel in maps["scalars"]]
                    pending["scalars"] = encode("scalars", k)
                # Written map by map: the finest level's text is tens of megabytes.
                with open(data / f"level{k}.js", "w", encoding="utf-8") as script:
                    script.write(f"colorpsLevel({k}, {{")
                    for j, name in enumerate(_MAP_ORDER):
                        urls = pending.pop(name).result()  # dropped once written
                        script.write(f"{', ' if j else ''}{json.dumps(name)}: {json.dumps(urls)}")
                    script.write("});\n")
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    index = _index(result, steps, ranges, band_names, title, finish)
    page = out / "index.html"
    page.write_text(_page(index, title), encoding="utf-8")
    return page


#: The maps of a level, in the order its script lists them.
_MAP_ORDER = ("normal", "albedo", "scalars", "codes")


def _maps(result: Reconstruction) -> dict[str, list[np.ndarray]]:
    """The viewer's maps but the scalars (:func:`_scalars`), each a list of (H, W)
    channels (NaN = no value; views of the result's maps where they can be)."""
    albedo = result.albedo if result.albedo.shape[-1] == 1 else as_rgb(result.albedo)
    count = np.minimum(result.lights_dropped_count, 255)
    return {"normal": [result.normals[..., k] for k in range(3)],
            "albedo": [albedo[..., k] for k in range(albedo.shape[-1])],
            "codes": [result.reason, count]}


def _scalars(result: Reconstruction) -> list[np.ndarray]:
    """The scalars map's channels: height (NaN without one), quality, uncertainty."""
    height = result.height if result.height is not None else \
        np.full(result.normals.shape[:2], np.nan, dtype=np.float32)
    return [height, result.quality, result.uncertainty]


def _png_pair(channels: list[np.ndarray], ranges, prefix: Path) -> list[str]:
    """Data URLs of two 8-bit RGB PNGs: the high and the low bytes of the codes
    of the channels (encoded through files named from ``prefix``)."""
    high = np.zeros((*channels[0].shape, 3), dtype=np.uint8)
    low = np.zeros_like(high)
    for k, (channel, (lo, hi)) in enumerate(zip(channels, ranges)):
        codes = encode(channel, lo, hi)
        high[..., k], low[..., k] = codes >> 8, codes & 0xFF
    urls = []
    for part, byte in (("high", high), ("low", low)):
        path = write_image(prefix.with_name(f"{prefix.name}-{part}.png"), byte, dtype="uint8")
        urls.append("data:image/png;base64," + base64.b64encode(path.read_bytes()).decode())
    return urls


def _index(result: Reconstruction, steps, ranges, band_names, title, finish) -> dict:
    """What the page knows besides the levels: sizes, ranges, keys, scales."""
    h, w = result.normals.shape[:2]
    c = result.albedo.shape[-1]
    if band_names is None:
        band_names = default_band_names(c)
    bands = list(band_names)[:1] if c == 1 else list(band_names)[:3]

    def scale(s):
        return {"label": s.label, "lo": s.lo, "hi": s.hi, "log": s.log, "ticks": s.ticks()}

    return {
        "title": title, "width": w, "height": h, "bands": bands,
        "levels": [{"step": s, "width": -(-w // s), "height": -(-h // s)} for s in steps],
        "ranges": ranges, "has_height": result.height is not None, "finish": finish,
        "colour_map": COLOUR_MAP_STOPS,
        "scales": {"quality": scale(QUALITY_SCALE), "uncertainty": scale(UNCERTAINTY_SCALE)},
        "reasons": [{"code": int(r), "label": r.label, "colour": r.colour} for r in Reason],
        "dropped": [{"colour": colour, "label": label}
                    for colour, label in dropped_entries()],
        "solved": int(result.stats.solved), "mode": result.stats.mode,
    }


def _page(index: dict, title: str) -> str:
    template = resources.files("colorps").joinpath("viewer.html").read_text(encoding="utf-8")
    # JSON inside a <script> element: "</" must not appear as such.
    payload = json.dumps(index).replace("</", "<\\/")
    return (template.replace("{{TITLE}}", html.escape(title or "colorps results"))
            .replace("{{INDEX}}", payload))


def viewer_page(results) -> Path:
    """The viewer page of a results folder.

    Raises
    ------
    InputError
        The folder has no index.html and viewer/ folder.
    """
    folder = Path(results)
    page = folder / "index.html"
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder; give a colorps results folder")
    if not page.is_file() or not (folder / "viewer").is_dir():
        raise InputError(f"{page}: no viewer here (results written with --no-viewer, or by "
                         "colorps 0.2); run colorps reconstruct again to get one")
    return page


def serve_viewer(results, port: int = 0):
    """An HTTP server of a results folder on 127.0.0.1 (for a browser that will
    not open files, or one on another machine through an SSH tunnel).

    Parameters
    ----------
    results : str or Path
        A results folder with a viewer.
    port : int, optional
        0: any free port.

    Returns
    -------
    http.server.ThreadingHTTPServer
        Not yet serving: call ``serve_forever()`` (and ``server_close()``);
        the page is at ``http://127.0.0.1:{server.server_port}/index.html``.
    """
    import functools
    from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer

    folder = viewer_page(results).parent

    class Handler(SimpleHTTPRequestHandler):
        def log_message(self, format, *args):
            pass

    handler = functools.partial(Handler, directory=str(folder))
    return ThreadingHTTPServer(("127.0.0.1", port), handler)
