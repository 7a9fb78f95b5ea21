"""Image I/O: the only module that talks to OpenImageIO.

Everything else in colorps sees float32 numpy arrays of *linear* values.

==================  ==========================  ==============================
format              stored as                   default decoding
==================  ==========================  ==============================
OpenEXR, HDR        half / float                linear
TIFF                8 / 16-bit int, 32 float    int: sRGB, float: linear
PNG                 8 / 16-bit int              sRGB
JPEG                8-bit int (lossy)           sRGB
==================  ==========================  ==============================

Integer values are scaled to 0..1 as OpenImageIO scales them; 8- and 16-bit
codes are decoded through a table of every code's linear value
(:mod:`colorps.transfer`, colour-science's sRGB transfer function). Alpha
channels are dropped.
"""

from __future__ import annotations

import contextlib
import glob
import os
import tempfile
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from .errors import ImageReadError, InputError, LossyInputWarning, OutputError
from .formats import CAMERA_RAW_SUFFIXES
from .options import FLOAT_DARK_LEVEL
from .transfer import TABLE_TYPES, decoding_table, srgb_decode

__all__ = [
    "Encoding",
    "ImageInfo",
    "check_decoded_size",
    "check_stack_files",
    "expand_paths",
    "file_mode",
    "input_levels",
    "pixel_type",
    "read_image",
    "read_info",
    "read_mask",
    "read_stack",
    "srgb_decode",
    "srgb_encode",
    "top_code",
    "warn_lossy_stack",
    "write_image",
]

#: Images of a stack decoded at a time (threads): 96 16-bit PNGs of 612 x 512
#: read in 0.53 s on 2 threads against 1.05 s on one.
READ_THREADS = min(8, os.cpu_count() or 1)
#: Files encoded at once (OpenImageIO's encoders release the GIL): one per core.
WRITE_THREADS = os.cpu_count() or 1
#: How stored pixel values map to linear light.
Encoding = Literal["auto", "linear", "srgb"]
_INTEGER_TYPES = ("uint8", "int8", "uint16", "int16", "uint32", "int32")
_MAX_CODE = {"uint8": 255, "int8": 127, "uint16": 65535, "int16": 32767,
             "uint32": 4294967295, "int32": 2147483647}
#: Dark level of integer files, in codes of the file's pixel type.
DARK_CODES = 2.0
#: What a warning about JPEG input says after the file's name.
LOSSY_ADVICE = "JPEG is lossy 8-bit; expect noisier normals than from raw, 16-bit TIFF or EXR"
#: Header attributes of a photo's exposure (OpenImageIO's names of the EXIF
#: tags) and what colorps calls them: seconds, f-number, ISO sensitivity.
EXPOSURE_ATTRIBUTES = {"ExposureTime": "time", "FNumber": "f_number",
                       "Exif:PhotographicSensitivity": "iso", "Exif:ISOSpeedRatings": "iso"}


def _open_input(path: Path):
    """An open OpenImageIO ImageInput, or an ImageReadError naming the file."""
    import OpenImageIO as oiio

    if path.is_dir():
        raise ImageReadError(f"{path}: is a directory, not an image")
    if not path.exists():
        raise ImageReadError(f"{path}: no such file")
    if path.suffix.lower() in CAMERA_RAW_SUFFIXES:  # (many are TIFF inside: a TIFF
        # reader would return their thumbnail or undemosaiced sensor data)
        raise ImageReadError(
            f"{path}: camera raw files are not read; convert them to linear 16-bit "
            "TIFF (dcraw -4 -T, or darktable / RawTherapee with a linear profile and "
            "no tone curve), the same way for scene and gauge, and pass --encoding linear")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise ImageReadError(f"{path}: cannot read image ({oiio.geterror().strip()})")
    return inp


def _read_rows(inp, spec, start: int, stop: int, as_type: str = "float"):
    """Rows ``start`` to ``stop - 1`` of an open image as ``as_type``: scanlines,
    or for a tiled file the row of tiles holding them (tile reads must be
    tile-aligned)."""
    if spec.tile_width <= 0:
        return inp.read_scanlines(0, 0, spec.y + start, spec.y + stop, 0, 0, spec.nchannels,
                                  as_type)
    first = start // spec.tile_height * spec.tile_height
    last = min(-(-stop // spec.tile_height) * spec.tile_height, spec.height)
    block = inp.read_tiles(0, 0, spec.x, spec.x + spec.width, spec.y + first, spec.y + last,
                           spec.z, spec.z + max(1, spec.depth), 0, spec.nchannels, as_type)
    if block is None:
        return None
    block = np.asarray(block).reshape(last - first, spec.width, spec.nchannels)
    return block[start - first:stop - first]


def file_mode(directory: bool = False) -> int:
    """Permission bits a new file (or folder) gets under the current umask."""
    mask = os.umask(0)
    os.umask(mask)
    return (0o777 if directory else 0o666) & ~mask


@dataclass(frozen=True)
class ImageInfo:
    """What an image file's header says (nothing decoded).

    Attributes
    ----------
    path : Path
    width, height, channels : int
        Size in pixels; channels without alpha.
    pixel_type : str
        OpenImageIO's name of the stored type ("uint8", "uint16", "half", "float", ...).
    exposure : dict
        The exposure settings the header records (EXIF): any of "time"
        (seconds), "f_number" and "iso"; empty for most EXR and for converted files.
    file_format : str
        OpenImageIO's name of the file format ("openexr", "png", "jpeg", "tiff", ...).
    """

    path: Path
    width: int
    height: int
    channels: int
    pixel_type: str
    exposure: dict = field(default_factory=dict, compare=False)
    file_format: str = ""

    @property
    def decoded_bytes(self) -> int:
        """Bytes of the image decoded to float32."""
        return self.width * self.height * self.channels * 4


def read_info(path) -> ImageInfo:
    """Read an image file's header only: size, channels and pixel type."""
    path = Path(path)
    inp = _open_input(path)
    try:
        spec = inp.spec()
        alpha = 1 if spec.alpha_channel >= 0 else 0
        exposure = {}
        for attribute, key in EXPOSURE_ATTRIBUTES.items():
            value = spec.getattribute(attribute)
            if isinstance(value, (int, float)) and np.isfinite(value) and value > 0:
                exposure.setdefault(key, float(value))
        return ImageInfo(path, int(spec.width), int(spec.height),
                         int(spec.nchannels) - alpha, str(spec.format), exposure,
                         inp.format_name())
    finally:
        inp.close()


def check_stack_files(paths: Sequence, *, name: str = "stack",
                      max_bytes: float | None = None) -> list[ImageInfo]:
    """Check a stack's headers before any pixel is decoded.

    Every file must have the size, channel count and pixel type of the first
    (so clip and dark levels, which follow from the pixel type, hold for every
    file), and the decoded stack must fit in ``max_bytes``.

    Raises
    ------
    ImageReadError
        A file is unreadable or differs from the first (the message names both).
    InputError
        The decoded stack would exceed ``max_bytes``.
    """
    paths = [Path(p) for p in paths]
    if not paths:
        raise ImageReadError(f"{name}: no images given")
    infos = [read_info(p) for p in paths]
    first = infos[0]
    for k, info in enumerate(infos[1:], start=2):
        where = f"{info.path} (image {k} of {len(infos)} of the {name})"
        if (info.width, info.height, info.channels) != (first.width, first.height,
                                                        first.channels):
            raise ImageReadError(
                f"{where}: size {info.width}x{info.height} with {info.channels} "
                f"channel(s) differs from image 1, {first.path} ({first.width}x"
                f"{first.height} with {first.channels})")
        if info.pixel_type != first.pixel_type:
            raise ImageReadError(
                f"{where}: pixel type {info.pixel_type} differs from image 1, {first.path} "
                f"({first.pixel_type}); clip and dark levels follow from the pixel type, "
                "so every image of a stack must be stored alike")
    if max_bytes is not None:
        check_decoded_size(infos, max_bytes, name=name)
    return infos


def warn_lossy_stack(infos: Sequence[ImageInfo], name: str = "stack") -> None:
    """Warn once (:class:`~colorps.errors.LossyInputWarning`) when a stack's
    files (their checked headers) are JPEG, naming the first and how many."""
    lossy = [info.path for info in infos if info.file_format == "jpeg"]
    if lossy:
        more = f"and {len(lossy) - 1} more of" if len(lossy) > 1 else "1 of"
        which = f" ({more} the {name}'s {len(infos)} images)" if len(infos) > 1 else ""
        warnings.warn(f"{lossy[0]}{which}: {LOSSY_ADVICE}", LossyInputWarning, stacklevel=3)


def _check_distinct(paths: Sequence[Path], name: str) -> None:
    """Refuse a stack that names one file twice (each image is one light), by
    resolved path, so ``a/x.png`` and ``./a/x.png`` or a link count alike."""
    seen = {}
    for k, path in enumerate(paths):
        key = path.resolve()
        if key in seen:
            raise InputError(f"{path}: given twice in the {name} stack (images "
                             f"{seen[key] + 1} and {k + 1} of {len(paths)}); each image "
                             "must be taken under its own light")
        seen[key] = k


def check_decoded_size(infos: Sequence[ImageInfo], max_bytes: float, *,
                       name: str = "stack") -> None:
    """Refuse a stack (its checked headers) whose decoded pixels exceed ``max_bytes``.

    Raises
    ------
    InputError
        Naming the first file, the stack's size and the limit.
    """
    first = infos[0]
    total = sum(i.decoded_bytes for i in infos)
    if total > max_bytes:
        raise InputError(
            f"{first.path}: the {name} stack ({len(infos)} images of {first.width}x"
            f"{first.height}x{first.channels}) would need {total / 2 ** 30:.1f} GiB decoded, "
            f"more than the limit of {max_bytes / 2 ** 30:.1f} GiB (--max-input-gib)")


@contextlib.contextmanager
def atomic_target(path):
    """Yield a temporary path beside ``path``; move it onto ``path`` on success.

    On any error (or Ctrl-C, or SIGTERM turned into one by the CLI) the
    temporary file is removed and ``path`` is left as it was. The file gets
    the permissions of a new file under the umask, not mkstemp's 0600.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, file_mode())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def top_code(source) -> int | None:
    """The largest code of an integer file's pixel type (255 for 8-bit), else None.

    ``source`` is the file or its :class:`ImageInfo`."""
    return _MAX_CODE.get(_pixel_type(source))


def pixel_type(source) -> str:
    """"int", "half" or "float": the kind of number a file stores (see
    :class:`~colorps.noise.NoiseModel`). ``source`` is the file or its :class:`ImageInfo`."""
    kind = _pixel_type(source)
    return "int" if kind in _INTEGER_TYPES else "half" if kind == "half" else "float"


def _pixel_type(source) -> str:
    """A file's stored pixel type, from its :class:`ImageInfo` or its header."""
    return source.pixel_type if isinstance(source, ImageInfo) else read_info(source).pixel_type


def input_levels(source, encoding: Encoding = "auto") -> tuple[float | None, float]:
    """Clip level and dark level (linear) implied by an image file's pixel type.

    Integer files: a measurement is clipped at the top code (linear value of
    code - 1/2) and dark below :data:`DARK_CODES` codes, both decoded with
    ``encoding`` like the pixels themselves. Floating-point files: nothing is
    clipped and the dark level is :data:`~colorps.options.FLOAT_DARK_LEVEL`.

    Parameters
    ----------
    source : str, Path or ImageInfo
        The file, or its header as already read.

    Returns
    -------
    clip_level : float or None
    dark_level : float
    """
    pixel_type = _pixel_type(source)
    if pixel_type not in _INTEGER_TYPES:
        return None, FLOAT_DARK_LEVEL
    top = _MAX_CODE[pixel_type]
    levels = np.array([(top - 0.5) / top, DARK_CODES / top], dtype=np.float32)
    if encoding in ("auto", "srgb"):
        levels = srgb_decode(levels)
    return float(levels[0]), float(levels[1])


#: zlib level of PNG files written: 1 writes a 1-megapixel normal map 3.5 times
#: faster than the default 6, for 12 % more bytes (measured 2026-12-02).
PNG_COMPRESSION = 1
#: srgb_encode converts this many values at a time (3 x 2^20: 12 MiB of float32).
SRGB_CHUNK = 3 * 2 ** 20


def srgb_encode(values) -> np.ndarray:
    """Linear values to sRGB-encoded (0..1, clipped), for previews and 8-bit files.

    OpenImageIO's colour conversion (OCIO, multi-threaded C++) applies the sRGB
    transfer function: within 1e-5 of colour-science's ``cctf_encoding``,
    far below an 8-bit code, and it spares the previews colour-science's
    import (which loads its plotting module).
    """
    import OpenImageIO as oiio

    values = np.asarray(values, np.float32)
    out = np.empty(values.shape, dtype=np.float32)
    flat, flat_out = values.reshape(-1), out.reshape(-1)
    for start in range(0, flat.size, SRGB_CHUNK):  # bounded temporaries
        piece = np.clip(np.nan_to_num(flat[start:start + SRGB_CHUNK], nan=0.0), 0.0, 1.0)
        pad = -piece.size % 3  # OCIO converts RGB triples; any shape goes as rows of them
        buf = oiio.ImageBuf(np.concatenate([piece, np.zeros(pad, np.float32)])
                            .reshape(1, -1, 3))
        encoded = oiio.ImageBufAlgo.colorconvert(buf, "linear", "sRGB")
        if encoded.has_error:
            raise RuntimeError(f"OpenImageIO sRGB conversion failed: {encoded.geterror()}")
        flat_out[start:start + piece.size] = encoded.get_pixels(oiio.FLOAT).ravel()[
            :piece.size]
    return np.clip(out, 0.0, 1.0, out=out)


def read_image(path, encoding: Encoding = "auto", *, rows: tuple[int, int] | None = None,
               warn_lossy: bool = True) -> tuple[np.ndarray, list[str]]:
    """Read one image as linear float32.

    Parameters
    ----------
    path : str or Path
    encoding : {"auto", "linear", "srgb"}, optional
        How stored values map to linear light. "auto": integer formats are
        sRGB-encoded, floating-point formats (EXR, HDR, float TIFF) are linear.
    rows : (start, stop), optional
        Read only these rows (scanlines ``start`` to ``stop - 1``): OpenImageIO
        decodes little more than them, so a tile of a large image costs its
        own size in memory.
    warn_lossy : bool, optional
        Warn (:class:`~colorps.errors.LossyInputWarning`) when the file is a JPEG.

    Returns
    -------
    image : (H, W, c) ndarray of float32
        Linear values (alpha dropped).
    channel_names : list of str

    Raises
    ------
    ImageReadError
        Missing, unreadable, truncated or corrupt file, or a directory.
    """
    if encoding not in ("auto", "linear", "srgb"):
        raise InputError(f"encoding: expected 'auto', 'linear' or 'srgb', got {encoding!r}")
    path = Path(path)
    inp = _open_input(path)
    try:
        spec = inp.spec()
        file_format = inp.format_name()
        height = spec.height
        stored = str(spec.format)
        # 8/16-bit codes are read as they are and decoded by table (same values).
        as_type = stored if stored in TABLE_TYPES else "float"
        if rows is None:
            pixels = inp.read_image(0, 0, 0, spec.nchannels, as_type)
        else:
            start, stop = rows
            if not 0 <= start < stop <= spec.height:
                raise InputError(f"{path}: rows {start}..{stop} outside its {spec.height}")
            pixels = _read_rows(inp, spec, start, stop, as_type)
            height = stop - start
        problem = inp.geterror().strip()
    finally:
        inp.close()
    if pixels is None or problem:
        raise ImageReadError(f"{path}: corrupt or truncated image ({problem or 'no data'})")
    if warn_lossy and file_format == "jpeg":
        warnings.warn(f"{path}: {LOSSY_ADVICE}", LossyInputWarning, stacklevel=2)
    pixels = np.asarray(pixels).reshape(height, spec.width, -1)
    names = list(spec.channelnames)
    keep = [k for k in range(spec.nchannels) if k != spec.alpha_channel]
    if len(keep) < spec.nchannels:
        pixels = pixels[..., keep]
    names = [names[k] for k in keep]
    srgb = encoding == "srgb" or (encoding == "auto" and stored in _INTEGER_TYPES)
    if as_type != "float":
        return decoding_table(_MAX_CODE[as_type], "srgb" if srgb else "linear")[pixels], names
    pixels = np.asarray(pixels, dtype=np.float32)
    if srgb:
        pixels = srgb_decode(pixels)
    return np.ascontiguousarray(pixels), names


def read_mask(path, shape: tuple[int, int]) -> np.ndarray:
    """A mask image of the given (H, W): True where its first channel is non-zero.

    Read as stored (linear), so any value above one half counts as inside.

    Raises
    ------
    ImageReadError
        The file cannot be read.
    InputError
        Its size differs from ``shape``.
    """
    image, _ = read_image(path, "linear")
    if image.shape[:2] != tuple(shape):
        raise InputError(f"{path}: mask is {image.shape[1]}x{image.shape[0]} but the images "
                         f"are {shape[1]}x{shape[0]}")
    return image[..., 0] > 0.5


def read_stack(paths: Sequence, encoding: Encoding = "auto", *, name: str = "stack",
               progress: bool = False, max_bytes: float | None = None,
               rows: tuple[int, int] | None = None,
               warn_lossy: bool = True) -> tuple[np.ndarray, list[str]]:
    """Read images that share size, channels and pixel type into a (m, H, W, c) stack.

    ``rows`` = (start, stop) reads only those rows of each image (a tile). With
    ``warn_lossy``, JPEG files are warned about once for the stack
    (:func:`warn_lossy_stack`).

    All headers are checked first (:func:`check_stack_files`), so a file that
    does not fit is refused before any pixel is decoded.

    Raises
    ------
    ImageReadError
        When a file cannot be read, or differs in size, channels or pixel type
        from the first one (the message names both).
    InputError
        When the decoded stack would exceed ``max_bytes``.
    """
    from collections import deque
    from concurrent.futures import ThreadPoolExecutor

    from tqdm.auto import tqdm

    paths = [Path(p) for p in paths]
    infos = check_stack_files(paths, name=name, max_bytes=max_bytes)
    if warn_lossy:
        warn_lossy_stack(infos, name)
    first, names, stack = None, None, None
    bar = tqdm(total=len(paths), desc=f"reading {name}", disable=not progress, leave=False)
    # Decoded by READ_THREADS at a time (OpenImageIO lets go of the GIL), in order,
    # each placed in the stack as it comes: never the images and the stack at once.
    with bar, ThreadPoolExecutor(min(READ_THREADS, len(paths))) as pool:
        reading = deque()
        for k, path in enumerate(paths):
            reading.append((k, path, pool.submit(read_image, path, encoding, rows=rows,
                                                     warn_lossy=False)))
            while reading and (len(reading) > READ_THREADS or k == len(paths) - 1):
                at, source, job = reading.popleft()
                image, channel_names = job.result()
                if stack is None:
                    first, names = source, channel_names
                    stack = np.empty((len(paths), *image.shape), dtype=np.float32)
                elif image.shape != stack.shape[1:]:
                    raise ImageReadError(
                        f"{source}: size {image.shape[1]}x{image.shape[0]} with "
                        f"{image.shape[2]} channel(s) differs from {first} ({stack.shape[2]}x"
                        f"{stack.shape[1]} with {stack.shape[3]})")
                stack[at] = image
                bar.update()
    return stack, names


def write_image(path, image, *, channel_names: Sequence[str] | None = None,
                dtype: Literal["float", "half", "uint8", "uint16"] = "float",
                tile: int | None = None) -> Path:
    """Write an image atomically (temporary file in the same folder, then rename).

    Parameters
    ----------
    path : str or Path
        Destination; the format follows the extension.
    image : (H, W) or (H, W, c) array_like
        Values as they should be stored (integer types expect 0..1, already
        encoded: see :func:`srgb_encode`), or an array of the file's integer
        pixel type (uint8, uint16), whose codes are written as they are.
    channel_names : sequence of str, optional
    dtype : {"float", "half", "uint8", "uint16"}, optional
        Pixel type in the file.
    tile : int, optional
        OpenEXR only: store the image in tile x tile pixel tiles (readers can
        then decode a region without the rest of the file); default scanlines.
    """
    import OpenImageIO as oiio

    path = Path(path)
    if dtype not in ("float", "half", "uint8", "uint16"):
        raise InputError(f"dtype: expected 'float', 'half', 'uint8' or 'uint16', got {dtype!r}")
    data = np.asarray(image)
    if data.dtype != np.dtype(dtype if dtype in ("uint8", "uint16") else np.float32):
        data = data.astype(np.float32)  # codes are written as they are; values as 0..1
    if data.ndim == 2:
        data = data[..., np.newaxis]
    h, w, c = data.shape
    if tile is not None and (path.suffix.lower() != ".exr" or isinstance(tile, bool)
                             or not isinstance(tile, (int, np.integer)) or tile < 1):
        raise InputError(f"{path}: tile: expected a tile side in pixels for an .exr file, "
                         f"got {tile!r}")
    spec = oiio.ImageSpec(w, h, c, dtype)
    if channel_names is not None:
        spec.channelnames = tuple(channel_names)
    if tile is not None:
        spec.tile_width = spec.tile_height = int(tile)
        spec.tile_depth = 1
    if path.suffix.lower() == ".exr":
        spec.attribute("compression", "zip")
    elif path.suffix.lower() == ".png":
        spec.attribute("png:compressionLevel", PNG_COMPRESSION)
    with atomic_target(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise OutputError(f"{path}: cannot write ({oiio.geterror().strip()})")
        if not out.open(str(tmp), spec):
            raise OutputError(f"{path}: cannot write ({out.geterror().strip()})")
        ok = out.write_image(np.ascontiguousarray(data))
        out.close()
        if not ok:
            raise OutputError(f"{path}: cannot write ({out.geterror().strip()})")
    return path


def expand_paths(patterns: str | Sequence[str], *, name: str = "images") -> list[Path]:
    """Expand quoted globs, plain paths and ``@list.txt`` files, naturally sorted.

    Each pattern is expanded and naturally sorted on its own (``img2`` before
    ``img10``); the results are concatenated in the order given. A path that
    exists is taken as it is, even when its name holds glob characters
    (``shot [0].exr``). A list file
    holds one path per line (relative to the list file; ``#`` starts a comment).

    Raises
    ------
    ImageReadError
        A glob that matches nothing, a missing list file, or no paths at all.
    InputError
        One file named twice (each image of a stack is one light).
    """
    from natsort import natsorted

    if isinstance(patterns, (str, Path)):
        patterns = [patterns]
    paths: list[Path] = []
    for pattern in map(str, patterns):
        if pattern.startswith("@"):
            listing = Path(pattern[1:])
            try:
                lines = listing.read_text().splitlines()
            except OSError as exc:
                raise ImageReadError(f"{listing}: cannot read list file ({exc.strerror})") from None
            for line in lines:
                line = line.split("#", 1)[0].strip()
                if line:
                    p = Path(line)
                    paths.append(p if p.is_absolute() else listing.parent / p)
        elif glob.has_magic(pattern) and not Path(pattern).exists():
            matches = natsorted(glob.glob(pattern))
            if not matches:
                raise ImageReadError(f"{name}: pattern {pattern!r} matches no file")
            paths.extend(Path(m) for m in matches)
        else:
            paths.append(Path(pattern))
    if not paths:
        raise ImageReadError(f"{name}: no images given")
    for path in paths:
        if not path.exists():
            raise ImageReadError(f"{path}: no such file")
    _check_distinct(paths, name)
    return paths
