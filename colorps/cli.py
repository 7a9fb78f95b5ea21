"""The ``colorps`` command line: parses arguments and calls the library."""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import warnings
from dataclasses import fields
from pathlib import Path

import numpy as np

from . import __version__
from .camera import read_camera
from .errors import ColorPSError, GaugeError, InputError
from .gauge import DEFAULT_ALBEDO, DEFAULT_VIRTUAL_RADIUS, parse_albedo
from .heights import integrate_file
from .inputs import CaptureFiles
from .light_files import calibrate_lights_files
from .memory import AUTO_MEMORY_FRACTION
from .options import FLOAT_DARK_LEVEL, NORMAL_CONVENTIONS, Options
from .pipeline import reconstruct_files
from .reasons import Reason
from .relight import FINISHES, RELIT_FORMATS
from .sample import run_demo, write_synthetic_folder
from .synth import FILE_FORMATS, LIGHT_LAYOUTS, SyntheticCapture

__all__ = ["build_parser", "main"]


class _FORMATTER(argparse.HelpFormatter):
    """Show a default where it means something and the help does not say it."""

    def _get_help_string(self, action):
        text = action.help or ""
        # (A --no-... flag's default True only means "not given": not shown.)
        if "default" not in text and action.default not in (None, False, True, argparse.SUPPRESS):
            text += " (default: %(default)s)"
        return text


_DEFAULTS = Options()


def _sphere(text: str):
    if text == "auto":
        return "auto"
    try:
        cx, cy, r = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected 'auto' or CX,CY,R in pixels, got {text!r}") from None
    return cx, cy, r


def _port(text: str) -> int:
    try:
        port = int(text)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"expected a port number 0-65535, got {text!r}")
    return port


def _camera(text: str):
    """--camera's text as a Camera (None for "orthographic")."""
    try:
        return read_camera(text)
    except InputError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _albedo(text: str):
    try:
        values = parse_albedo([float(v) for v in text.split(",")], text.count(",") + 1)
    except GaugeError as error:  # (what parse_albedo refuses)
        raise argparse.ArgumentTypeError(str(error)) from None
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected A or R,G,B, got {text!r}") from None
    return float(values[0]) if len(values) == 1 else values.tolist()


def _number(kind, smallest, what: str):
    """An argument type: a finite ``kind`` (float or int) of at least ``smallest``."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            value = None
        if value is None or not np.isfinite(value) or value < smallest:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return value

    return parse


_positive_float = _number(float, np.nextafter(0.0, 1.0), "a value > 0")
_non_negative_float = _number(float, 0.0, "a value >= 0")
_positive_int = _number(int, 1, "a positive integer")
_non_negative_int = _number(int, 0, "an integer >= 0")
_channel = _number(int, 0, "'luminance' or a channel index")


def _or_words(convert, **words):
    """An argument type: one of the given words (to its value), else ``convert``."""

    def parse(text: str):
        if text in words:
            return words[text]
        try:
            return convert(text)
        except argparse.ArgumentTypeError as exc:
            raise argparse.ArgumentTypeError(
                f"{exc}; or one of {', '.join(map(repr, words))}") from None

    return parse


def _shown(value) -> str:
    """An option value as typed on the command line."""
    return "none" if value is None else str(value)


def _add_options(parser: argparse.ArgumentParser) -> None:
    """The flags of Options' fields: dest is the field, defaults are Options()'s."""
    parser.add_argument("--brdf", choices=("fitted", "lambert"), default=_DEFAULTS.brdf,
                        help="with --lights: the finish the gauge is rendered with (fitted: "
                             "diffuse falloff + highlight fitted to the scene)")
    parser.add_argument("--mode", choices=("colour", "mono"), default=_DEFAULTS.mode,
                        help="signatures from all bands or from one band")
    parser.add_argument("--band", type=_or_words(_channel, luminance="luminance"),
                        default=_DEFAULTS.band, metavar="luminance|K",
                        help="mono mode: 'luminance' (RGB) or a channel index "
                             "(default: luminance for RGB, else channel 0)")
    parser.add_argument("--colourspace", default=_DEFAULTS.colourspace, metavar="NAME",
                        help="mono mode: colour-science name of the RGB colourspace of the "
                             "luminance")
    parser.add_argument("--threads", type=_positive_int, default=_DEFAULTS.threads,
                        help="lookup threads (default: all cores)")
    parser.add_argument("--grid-n", type=_or_words(_positive_int, auto="auto"),
                        default=_DEFAULTS.grid_n, metavar="N|auto",
                        help="bucket grid size (default: round(2 sqrt(table size)))")
    parser.add_argument("--encoding", choices=("auto", "linear", "srgb"),
                        default=_DEFAULTS.encoding,
                        help="pixel encoding: auto = integer formats sRGB, float formats linear")
    parser.add_argument("--clip-level", type=_or_words(_positive_float, auto="auto", none=None),
                        default=_DEFAULTS.clip_level, metavar="V|auto|none",
                        help="linear value at or above which a measurement is clipped; auto: "
                             "the top code of integer files, none for float files "
                             f"(default: {_shown(_DEFAULTS.clip_level)})")
    parser.add_argument("--dark-level", type=_or_words(_positive_float, auto="auto"),
                        default=_DEFAULTS.dark_level, metavar="V|auto",
                        help="linear noise floor of one measurement; bands whose OV norm is "
                             "below V sqrt(m) are too dark; auto: 2 codes of integer files, "
                             f"{FLOAT_DARK_LEVEL:.2g} for float files "
                             f"(default: {_shown(_DEFAULTS.dark_level)})")
    parser.add_argument("--read-noise", type=_or_words(_non_negative_float, auto="auto"),
                        default=_DEFAULTS.read_noise, metavar="V|auto",
                        help="noise model: read-noise floor of one measurement (linear); "
                             "auto: fitted to the gauge's pixel scatter "
                             f"(default: {_shown(_DEFAULTS.read_noise)})")
    parser.add_argument("--gain", type=_or_words(_non_negative_float, auto="auto"),
                        default=_DEFAULTS.gain, metavar="G|auto",
                        help="noise model: shot-noise variance per unit linear signal; "
                             f"auto: fitted to the gauge (default: {_shown(_DEFAULTS.gain)})")
    parser.add_argument("--no-band-weights", dest="band_weights", action="store_false",
                        help="colour mode: weigh every band alike, however dark")
    parser.add_argument("--no-finish-check", dest="finish_check", action="store_false",
                        help="keep the gauge's result even where the finish looks another")
    parser.add_argument("--no-interreflections", dest="interreflections", action="store_false",
                        help="keep the light a concave object bounces onto itself")
    parser.add_argument("--no-light-subsets", dest="light_subsets", action="store_false",
                        help="do not re-solve shadowed or highlighted pixels from their lit lights")
    parser.add_argument("--max-dropped-lights", type=_non_negative_int,
                        default=_DEFAULTS.max_dropped_lights, metavar="K",
                        help="rounds of table-based light subsets (up to 16 lights) before "
                             "the per-pixel fit, one light each")
    parser.add_argument("--max-residual", type=_or_words(_positive_float, none=None),
                        default=_DEFAULTS.max_residual, metavar="R|none",
                        help="largest residual of a good match, in noise units (quality.exr); "
                             "worse ones are solved, flagged 'solved, poor match' "
                             f"(default: {_shown(_DEFAULTS.max_residual)})")
    parser.add_argument("--refuse-poor", action="store_true", default=_DEFAULTS.refuse_poor,
                        help="refuse those instead ('no good match')")
    parser.add_argument("--max-distance", type=_or_words(_positive_float, none=None),
                        default=_DEFAULTS.max_distance, metavar="D|none",
                        help="also refuse pixels whose plain signature distance per band "
                             f"exceeds D (default: {_shown(_DEFAULTS.max_distance)})")
    parser.add_argument("--refine", choices=("quadratic", "none"), default=_DEFAULTS.refine,
                        help="refine normals past the gauge's pixel grid (quadratic model of "
                             "the gauge around each match), with uncertainty.exr")
    parser.add_argument("--max-input-gib", type=_positive_float, default=_DEFAULTS.max_input_gib,
                        metavar="G", help="refuse a stack that would take more than G GiB "
                             "decoded (checked from the headers, before decoding)")
    parser.add_argument("--tile", type=_positive_int, default=_DEFAULTS.tile, metavar="ROWS",
                        help="process the scene in bands of ROWS rows read from the files when "
                             "needed (same results; bounded memory for the matching)")
    parser.add_argument("--memory-limit", dest="memory_limit_gib",
                        type=_or_words(_positive_float, auto="auto", none=None),
                        default=_DEFAULTS.memory_limit_gib, metavar="GIB|auto|none",
                        help="choose --tile so the run's estimated peak memory stays under "
                             "GIB GiB (refused when even small tiles would not fit); auto: "
                             f"{100 * AUTO_MEMORY_FRACTION:.0f}%% of the memory available at the start; "
                             f"none: no limit (default: {_shown(_DEFAULTS.memory_limit_gib)})")
    parser.add_argument("--no-height", dest="height", action="store_false",
                        help="skip the height map, relief and overview pictures")
    parser.add_argument("--mesh", choices=("ply", "obj", "both"), default=_DEFAULTS.mesh,
                        help="also write a mesh of the height field with albedo colours")
    parser.add_argument("--normal-convention", choices=NORMAL_CONVENTIONS,
                        default=_DEFAULTS.normal_convention,
                        help="normal.png's green channel: y up (OpenGL, Blender, Unity) or "
                             "y down (DirectX, Unreal); normal.exr is always y up")
    parser.add_argument("--no-viewer", dest="viewer", action="store_false",
                        help="skip the results viewer (index.html and viewer/)")



def build_parser() -> argparse.ArgumentParser:
    """The ``colorps`` argument parser (sub-commands reconstruct, integrate, demo, synth)."""
    parser = argparse.ArgumentParser(
        prog="colorps", description="Gauge-based colour photometric stereo: normals, "
        "intrinsic colour and match quality from a scene stack and a gauge stack.")
    parser.add_argument("--version", action="version", version=f"colorps {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    rec = sub.add_parser("reconstruct", formatter_class=_FORMATTER,
                         help="photos in; normal map, albedo and quality out")
    rec.add_argument("--scene", nargs="+", required=True, metavar="PATTERN",
                     help="scene images: quoted globs, paths or @list.txt (natural order)")
    rec.add_argument("--gauge", nargs="+", metavar="PATTERN",
                     help="gauge images under the same lights, same order")
    rec.add_argument("--sphere", type=_sphere, metavar="auto|CX,CY,R",
                     help="gauge sphere in gauge-image pixels, or 'auto' to find it")
    rec.add_argument("--camera", type=_camera, default="auto", metavar="F|K.txt|FILE.json",
                     help="a pinhole camera: focal length in pixels (principal point at the "
                          "image centre), a 3 x 3 intrinsic matrix K.txt, a JSON (fx, fy, px, "
                          "py), 'orthographic', or 'auto' (default): the focal length the "
                          "images' EXIF records, else orthographic")
    rec.add_argument("--lights", metavar="FILE",
                     help="instead of --gauge/--sphere: calibrated light directions "
                          "(.txt 'x y z' per image, .lp or .json); the gauge is rendered")
    rec.add_argument("--light-intensities", metavar="FILE",
                     help="with --lights: one 'r g b' (or one value) per image")
    rec.add_argument("--virtual-radius", type=_positive_float,
                     default=DEFAULT_VIRTUAL_RADIUS, metavar="R",
                     help="with --lights: radius (px) of the rendered gauge sphere")
    rec.add_argument("--gauge-albedo", type=_albedo, default=DEFAULT_ALBEDO, metavar="A|R,G,B",
                     help="albedo of the gauge, one value or one per band")
    rec.add_argument("--out", required=True, metavar="DIR", help="output folder")
    rec.add_argument("--mask", metavar="FILE", help="scene mask image (non-zero = solve)")
    rec.add_argument("--overwrite", action="store_true", help="replace existing results")
    rec.add_argument("--quiet", action="store_true", help="no progress bar or summary")
    _add_options(rec)
    rec.add_argument("--scheduler", default=None, metavar="ADDRESS",
                     help="run the tiles on a Dask cluster: a scheduler address "
                          "(tcp://host:8786) or 'local' for a local cluster; needs "
                          "pip install 'colorps[dask]' (default: tiles run in this process)")

    bat = sub.add_parser("batch", formatter_class=_FORMATTER,
                         help="reconstruct many captures (folders or a manifest), one per "
                              "task, locally or on a Dask cluster")
    bat.add_argument("folders", nargs="*", metavar="FOLDER",
                     help="capture folders: scene_* images (any format reconstruct "
                          "reads: EXR, TIFF, PNG, JPEG, HDR, TGA, ...), gauge_* images or "
                          "a light file, optional mask.* (see colorps.batch)")
    bat.add_argument("--manifest", metavar="FILE.json",
                     help="a JSON list of captures instead of (or besides) folders")
    bat.add_argument("--out", required=True, metavar="DIR",
                     help="output folder: one sub-folder per capture, and batch.json")
    bat.add_argument("--scheduler", default=None, metavar="ADDRESS",
                     help="run the captures as tasks on a Dask cluster: a scheduler "
                          "address or 'local' (default: one after the other here)")
    bat.add_argument("--overwrite", action="store_true", help="replace existing results")
    bat.add_argument("--quiet", action="store_true", help="no progress bar or table")
    _add_options(bat)

    integ = sub.add_parser("integrate", formatter_class=_FORMATTER,
                           help="integrate a normal map (normal.exr) into a height map")
    integ.add_argument("normals", metavar="NORMALS", help="normal map (X, Y, Z channels)")
    integ.add_argument("--out", required=True, metavar="FILE",
                       help="height map to write (.exr)")
    integ.add_argument("--mask", metavar="FILE", help="mask image (non-zero = integrate)")
    integ.add_argument("--weights", metavar="FILE",
                       help="quality.exr of a reconstruction: unreliable pixels count less")
    integ.add_argument("--method", choices=("poisson", "dct"), default="poisson",
                       help="masked sparse least squares, or DCT for full rectangles")
    integ.add_argument("--mesh", metavar="FILE", help="also write a mesh (.ply or .obj)")
    integ.add_argument("--overwrite", action="store_true", help="replace existing files")

    cal = sub.add_parser("calibrate-lights", formatter_class=_FORMATTER,
                         help="lights from a mirror sphere's highlights, or a matte sphere")
    cal.add_argument("images", nargs="+", metavar="IMAGES",
                     help="sphere images (globs or paths), one per light, in order")
    cal.add_argument("--matte", action="store_true",
                     help="a matte sphere (a gauge): directions and intensities by a "
                          "Lambertian fit of its shading")
    cal.add_argument("--camera", type=_camera, metavar="F|K.txt|FILE.json",
                     help="with --matte: the pinhole camera, as for reconstruct")
    cal.add_argument("--albedo", type=_albedo, default=1.0, metavar="A|R,G,B",
                     help="with --matte: the sphere's albedo (intensities are relative to it)")
    cal.add_argument("--sphere", type=_sphere, metavar="auto|CX,CY,R",
                     help="sphere silhouette in pixels, or 'auto' to find it")
    cal.add_argument("--sphere-mask", metavar="FILE",
                     help="instead of --sphere: a mask image of the sphere (non-zero on "
                          "it), for a dark sphere 'auto' cannot find")
    cal.add_argument("--out", required=True, metavar="FILE",
                     help="light file to write: .txt, .lp or .json")
    cal.add_argument("--overwrite", action="store_true", help="replace an existing file")

    rel = sub.add_parser("relight", formatter_class=_FORMATTER,
                         help="render a results folder under new lights")
    rel.add_argument("results", metavar="RESULTS", help="a results folder (normal.exr, "
                     "albedo.exr)")
    rel.add_argument("--lights", required=True, metavar="FILE",
                     help="light directions (.txt 'x y z' per image, .lp or .json)")
    rel.add_argument("--light-intensities", metavar="FILE",
                     help="one 'r g b' (or one value) per light")
    rel.add_argument("--out", required=True, metavar="DIR",
                     help="folder for relit_001, relit_002, ...")
    rel.add_argument("--format", choices=RELIT_FORMATS, default="png",
                     help="8-bit sRGB PNG or linear float EXR")
    rel.add_argument("--finish", choices=FINISHES, default=FINISHES[0],
                     help="Lambertian, or the finish a --lights run fitted (report.json)")
    rel.add_argument("--overwrite", action="store_true", help="replace existing images")

    view = sub.add_parser("view", formatter_class=_FORMATTER,
                          help="open a results folder's viewer (index.html) in a browser")
    view.add_argument("results", metavar="RESULTS", help="a results folder")
    view.add_argument("--serve", action="store_true",
                      help="serve it over http on 127.0.0.1 instead of opening the file "
                           "(until Ctrl-C)")
    view.add_argument("--port", type=_port, default=0,
                      help="with --serve: the port (default: any free one)")

    demo = sub.add_parser("demo", formatter_class=_FORMATTER,
                          help="run the full pipeline on the bundled sample and report "
                               "its accuracy against ground truth")
    demo.add_argument("--out", default="colorps-demo", metavar="DIR", help="output folder")
    demo.add_argument("--data", default=None, metavar="DIR",
                      help="a folder made by 'colorps synth' (default: the bundled sample)")
    demo.add_argument("--mode", choices=("colour", "mono"), default="colour")
    demo.add_argument("--overwrite", action="store_true", help="replace existing results")

    syn = sub.add_parser("synth", formatter_class=_FORMATTER,
                         help="render a synthetic smiley scene + sphere gauge with truth")
    syn.add_argument("--out", required=True, metavar="DIR")
    made = SyntheticCapture()  # (its defaults)
    syn.add_argument("--size", type=_positive_int, default=made.size, help="scene size (px)")
    syn.add_argument("--images", type=_positive_int, default=made.images,
                     help="number of images m")
    syn.add_argument("--theta", type=float, default=made.theta, help="light angle (deg)")
    syn.add_argument("--lights", choices=LIGHT_LAYOUTS, default=made.lights,
                     help="white, one coloured light per image, two colours per image, or "
                     "white over half the azimuths")
    syn.add_argument("--brdf", choices=("lambert", "oren-nayar"), default=made.brdf)
    syn.add_argument("--noise", type=float, default=made.noise, help="noise sigma (0..1)")
    syn.add_argument("--gauge-radius", type=float, default=made.gauge_radius,
                     help="sphere radius (px)")
    syn.add_argument("--seed", type=int, default=made.seed)
    syn.add_argument("--relief", type=float, default=made.relief,
                     help="height of the eyes in face radii (the mouth is 0.8 of it deep)")
    syn.add_argument("--cast-shadows", action="store_true",
                     help="the relief casts shadows (truth in truth_shadows.png)")
    syn.add_argument("--gloss", type=float, default=made.gloss,
                     help="strength of a white highlight the matte gauge does not share")
    syn.add_argument("--format", dest="file_format", choices=FILE_FORMATS,
                     default=made.file_format,
                     help="half-float linear EXR, or 8-bit sRGB PNG like a camera's")
    syn.add_argument("--overwrite", action="store_true", help="replace an earlier capture")
    return parser


class _Terminated(KeyboardInterrupt):
    """SIGTERM, handled like Ctrl-C: every temporary file is removed on the way out."""


@contextlib.contextmanager
def _signals_caught():
    """Within the context, turn SIGINT (unless ignored, as in a background job)
    into KeyboardInterrupt and SIGTERM into _Terminated, and record each in the
    list yielded: an interrupt that arrives while a library is mid-call can
    surface as that library's error instead, and must still count as one."""
    received: list[int] = []

    def handler(signum, frame):
        received.append(signum)
        raise _Terminated if signum == signal.SIGTERM else KeyboardInterrupt

    wanted = [signal.SIGTERM]
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        wanted.append(signal.SIGINT)
    previous = {signum: signal.signal(signum, handler) for signum in wanted}
    try:
        yield received
    finally:
        for signum, before in previous.items():
            signal.signal(signum, before)


def _show_warning(message, category, filename, lineno, file=None, line=None):
    print(f"colorps: warning: {message}", file=sys.stderr)


#: Shown once when a run has to compile colorps' numba kernels: the first run
#: after installing, which spends about 45 s of a 2-core machine on it (the
#: compiled kernels are cached beside the package, so later runs skip this).
COMPILE_NOTICE = ("colorps: compiling its numba kernels for this machine (once after "
                  "installing: 30 s to 2 minutes; later runs load them from the cache)")


@contextlib.contextmanager
def _compile_notice(enabled: bool = True, package: str = __package__):
    """Within the context, print COMPILE_NOTICE the first time numba compiles a kernel
    of ``package`` (not cached), so that a long first run is not taken for a hang."""
    from numba.core import event

    class Notice(event.Listener):
        shown = False

        def on_start(self, ev):
            module = getattr(ev.data["dispatcher"].py_func, "__module__", "") or ""
            if not self.shown and module.split(".")[0] == package:
                self.shown = True
                from tqdm import tqdm

                tqdm.write(COMPILE_NOTICE, file=sys.stderr)  # keeps progress bars intact

        def on_end(self, ev):
            pass

    if not enabled:
        yield
        return
    with event.install_listener("numba:compile", Notice()):
        yield


def main(argv=None) -> int:
    """Run ``colorps`` with ``argv`` (default: sys.argv); return the exit code.

    0 on success, 1 for an error colorps reports (one line on stderr), 2 for
    malformed arguments, 130 when interrupted (Ctrl-C), 143 on SIGTERM.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "reconstruct" and args.mesh and not args.height:
        parser.error("--mesh needs the height map; drop --no-height")
    if args.command == "reconstruct":
        if args.lights is None and (args.gauge is None or args.sphere is None):
            parser.error("give --gauge and --sphere, or --lights")
        if args.lights is not None and (args.gauge is not None or args.sphere is not None):
            parser.error("--lights replaces --gauge and --sphere; give one or the other")
        if args.light_intensities is not None and args.lights is None:
            parser.error("--light-intensities needs --lights")
    with (_signals_caught() as received, warnings.catch_warnings(),
          _compile_notice(not getattr(args, "quiet", False))):
        warnings.simplefilter("always")  # the CLI prints every warning it meets
        warnings.showwarning = _show_warning
        return _run(args, received)


def _run(args, received: list[int]) -> int:
    """Run the command; ``received`` lists the signals caught while it ran."""
    try:
        if args.command == "reconstruct":
            options = _options(args)
            inputs = CaptureFiles(args.scene, gauge=args.gauge, sphere=args.sphere,
                                  camera=args.camera, mask=args.mask, lights=args.lights,
                                  light_intensities=args.light_intensities,
                                  gauge_albedo=args.gauge_albedo,
                                  virtual_radius=args.virtual_radius)
            result = reconstruct_files(inputs, args.out, options=options,
                                       overwrite=args.overwrite, progress=not args.quiet,
                                       scheduler=args.scheduler)
            if not args.quiet:
                s = result.stats
                median, poor = s.residual_median or 0.0, s.pixels_by_reason[Reason.SOLVED_POOR_MATCH.label]
                print(f"solved {s.solved} of {s.pixels} pixels ({s.solved_from_light_subset} "
                      f"from a light subset, {poor} poor matches flagged; table "
                      f"{s.table_size}, grid N={s.grid_n}, median residual "
                      f"{median:.2f}, {s.residual_median_noise_units or 0.0:.2f} in noise "
                      f"units before the model scale {s.model_scale:.2f}; 68 % radius median "
                      f"{s.uncertainty_median or 0.0:.2f} deg; {s.seconds.run:.2f} s in all); "
                      f"results in {args.out}/")
        elif args.command == "batch":
            return _batch(args)
        elif args.command == "integrate":
            z = integrate_file(args.normals, args.out, mask_path=args.mask,
                               weights_path=args.weights, method=args.method, mesh=args.mesh,
                               overwrite=args.overwrite)
            print(f"integrated {np.isfinite(z).sum()} pixels; relief depth "
                  f"{np.nanmax(z) - np.nanmin(z):.2f} px; wrote {args.out}")
        elif args.command == "calibrate-lights":
            _, found, sphere, table, written = calibrate_lights_files(
                args.images, args.sphere, args.out, sphere_mask=args.sphere_mask,
                matte=args.matte, camera=args.camera, albedo=args.albedo,
                overwrite=args.overwrite)
            print(f"sphere at {sphere[0]:.1f},{sphere[1]:.1f} radius {sphere[2]:.1f} px")
            print("\n".join(table))
            print(f"wrote {len(found)} lights to {', '.join(map(str, written))}")
        elif args.command == "relight":
            from .relight import relight_files

            written = relight_files(args.results, args.lights, args.out,
                                    intensities=args.light_intensities,
                                    file_format=args.format, finish=args.finish,
                                    overwrite=args.overwrite)
            print(f"wrote {len(written)} relit images to {args.out}/")
        elif args.command == "view":
            _view(args)
        elif args.command == "demo":
            _, report = run_demo(args.out, args.data, args.mode, args.overwrite)
            print("\n".join(report.lines(args.mode, args.out)))
        elif args.command == "synth":
            write_synthetic_folder(args.out, SyntheticCapture(**{
                field.name: getattr(args, field.name) for field in fields(SyntheticCapture)}),
                args.overwrite)
            print(f"wrote a synthetic stack with ground truth to {args.out}/")
    except BaseException as exc:
        # Whatever failed after a signal arrived failed because of it.
        if isinstance(exc, KeyboardInterrupt) or (received and isinstance(exc, Exception)):
            if isinstance(exc, _Terminated) or signal.SIGTERM in received:
                print("colorps: terminated; no partial results were written", file=sys.stderr)
                return 143
            print("colorps: interrupted; no partial results were written", file=sys.stderr)
            return 130
        if isinstance(exc, ColorPSError):
            print(f"colorps: error: {exc}", file=sys.stderr)
            return 1
        raise
    return 0


def _view(args) -> None:
    """Colorps view: open the page, or serve the folder until Ctrl-C."""
    import webbrowser

    from .viewer import serve_viewer, viewer_page

    if not args.serve:
        url = viewer_page(args.results).resolve().as_uri()
        if webbrowser.open(url):
            print(f"opened {url}")
        else:
            print(f"no browser found here: open {url} in one, or use --serve")
        return
    try:
        server = serve_viewer(args.results, args.port)
    except OSError as exc:
        raise InputError(f"--port {args.port}: cannot serve on it ({exc.strerror or exc})") \
            from None
    print(f"serving the viewer at http://127.0.0.1:{server.server_port}/index.html "
          "(Ctrl-C to stop)", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:  # the way to stop it
        print("stopped serving")
    finally:
        server.server_close()


def _options(args) -> Options:
    """The Options the parsed flags of reconstruct or batch stand for."""
    return Options(**{f.name: getattr(args, f.name) for f in fields(Options)})


def _batch(args) -> int:
    """Colorps batch: every capture, a table, exit code 1 if any failed."""
    from .batch import find_capture, read_manifest, run_batch
    from .tiles import dask_client

    captures = [find_capture(folder) for folder in args.folders]
    if args.manifest:
        captures += read_manifest(args.manifest)
    if not captures:
        raise InputError("batch: give capture folders or --manifest")
    options = _options(args)
    with dask_client(args.scheduler) as client:
        outcomes = run_batch(captures, args.out, options, client=client,
                             overwrite=args.overwrite, progress=not args.quiet)
    failed = [o for o in outcomes if not o.ok]
    if not args.quiet:
        width = max(len(o.name) for o in outcomes)
        for o in outcomes:
            state = (f"solved {o.solved} of {o.pixels} px in {o.seconds:.1f} s" if o.ok
                     else f"FAILED: {o.error}")
            print(f"{o.name:{width}s}  {state}")
        print(f"{len(outcomes) - len(failed)} of {len(outcomes)} captures reconstructed; "
              f"summary in {Path(args.out) / 'batch.json'}")
    for o in failed:
        print(f"colorps: error: {o.name}: {o.error}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
