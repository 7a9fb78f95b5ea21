"""The ``colorps`` command line: parses arguments and calls the library."""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

from . import __version__
from .errors import ColorPSError, InputError
from .pipeline import integrate_file, read_mask, reconstruct_files


class _FORMATTER(argparse.HelpFormatter):
    """Show a default where it means something and the help does not say it."""

    def _get_help_string(self, action):
        text = action.help or ""
        if "default" not in text and action.default not in (None, False, argparse.SUPPRESS):
            text += " (default: %(default)s)"
        return text


def _sphere(text: str):
    if text == "auto":
        return "auto"
    try:
        cx, cy, r = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected 'auto' or CX,CY,R in pixels, got {text!r}") from None
    return cx, cy, r


def _albedo(text: str):
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected A or R,G,B, got {text!r}") from None
    if any(not np.isfinite(v) or v <= 0 for v in values):
        raise argparse.ArgumentTypeError(f"albedo values must be > 0, got {text!r}")
    return values[0] if len(values) == 1 else values


def _level(text: str):
    if text == "none":
        return "none"
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not (np.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a linear value > 0 or 'none', got {text!r}")
    return value


def _none_or(value, default):
    """A level option: None (not given) becomes ``default``, "none" becomes None."""
    if value is None:
        return default
    return None if value == "none" else value


def _positive_float(text: str):
    value = _level(text)
    if value == "none":
        raise argparse.ArgumentTypeError("expected a linear value > 0")
    return value


def _positive_int(text: str):
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return n


def _grid_n(text: str):
    return "auto" if text == "auto" else _positive_int(text)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="colorps", description="Gauge-based colour photometric stereo: normals, "
        "intrinsic colour and match quality from a scene stack and a gauge stack.")
    parser.add_argument("--version", action="version", version=f"colorps {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    rec = sub.add_parser("reconstruct", formatter_class=_FORMATTER,
                         help="photos in; normal map, albedo and quality out")
    rec.add_argument("--scene", nargs="+", required=True, metavar="PATTERN",
                     help="scene images: quoted globs, paths or @list.txt (natural order)")
    rec.add_argument("--gauge", nargs="+", required=True, metavar="PATTERN",
                     help="gauge images under the same lights, same order")
    rec.add_argument("--sphere", type=_sphere, required=True, metavar="auto|CX,CY,R",
                     help="gauge sphere in gauge-image pixels, or 'auto' to find it")
    rec.add_argument("--gauge-albedo", type=_albedo, default=1.0, metavar="A|R,G,B",
                     help="albedo of the gauge, one value or one per band")
    rec.add_argument("--mode", choices=("colour", "mono"), default="colour",
                     help="signatures from all bands or from one band")
    rec.add_argument("--band", default=None, metavar="luminance|K",
                     help="mono mode: 'luminance' (RGB) or a channel index "
                          "(default: luminance for RGB, else channel 0)")
    rec.add_argument("--out", required=True, metavar="DIR", help="output folder")
    rec.add_argument("--mask", metavar="FILE", help="scene mask image (non-zero = solve)")
    rec.add_argument("--threads", type=_positive_int, default=None,
                     help="lookup threads (default: all cores)")
    rec.add_argument("--grid-n", type=_grid_n, default=None, metavar="N|auto",
                     help="bucket grid size (default: round(2 sqrt(table size)))")
    rec.add_argument("--encoding", choices=("auto", "linear", "srgb"), default="auto",
                     help="pixel encoding: auto = integer formats sRGB, float formats linear")
    rec.add_argument("--clip-level", type=_level, default=None, metavar="V|none",
                     help="linear value at or above which a measurement is clipped "
                          "(default: from the bit depth: top code of integer files, "
                          "none for float files)")
    rec.add_argument("--dark-level", type=_positive_float, default=None, metavar="V",
                     help="linear noise floor of one measurement; bands whose OV norm is "
                          "below V sqrt(m) are too dark (default: 2 codes of integer "
                          "files, 3.3e-5 for float files)")
    rec.add_argument("--max-distance", type=_level, default=0.1, metavar="D|none",
                     help="largest match distance (per band) of a solved pixel; worse "
                          "matches are reported as 'no good match'")
    rec.add_argument("--no-height", action="store_true",
                     help="skip the height map, relief and overview pictures")
    rec.add_argument("--mesh", choices=("ply", "obj", "both"), default=None,
                     help="also write a mesh of the height field with albedo colours")
    rec.add_argument("--overwrite", action="store_true", help="replace existing results")
    rec.add_argument("--quiet", action="store_true", help="no progress bar or summary")

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

    demo = sub.add_parser("demo", formatter_class=_FORMATTER,
                          help="run the full pipeline on the bundled sample and report "
                               "its accuracy against ground truth")
    demo.add_argument("--out", default="colorps-demo", metavar="DIR", help="output folder")
    demo.add_argument("--data", default=None, metavar="DIR",
                      help="sample folder (default: data/sample of the source tree)")
    demo.add_argument("--mode", choices=("colour", "mono"), default="colour")
    demo.add_argument("--overwrite", action="store_true", help="replace existing results")

    syn = sub.add_parser("synth", formatter_class=_FORMATTER,
                         help="render a synthetic smiley scene + sphere gauge with truth")
    syn.add_argument("--out", required=True, metavar="DIR")
    syn.add_argument("--size", type=_positive_int, default=256, help="scene size (px)")
    syn.add_argument("--images", type=_positive_int, default=8, help="number of images m")
    syn.add_argument("--theta", type=float, default=45.0, help="light angle from view (deg)")
    syn.add_argument("--lights", choices=("white", "colour", "mixed"), default="white",
                     help="white, one coloured light per image, or two colours per image")
    syn.add_argument("--brdf", choices=("lambert", "oren-nayar"), default="lambert")
    syn.add_argument("--noise", type=float, default=0.0, help="Gaussian noise sigma (0..1)")
    syn.add_argument("--gauge-radius", type=float, default=100.0, help="sphere radius (px)")
    syn.add_argument("--seed", type=int, default=0)
    return parser


def _angular_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    cos = np.clip((a * b).sum(axis=-1), -1.0, 1.0)
    return np.degrees(np.arccos(cos))


def run_demo(out, data=None, mode="colour", overwrite=False):
    """Reconstruct the bundled sample and print accuracy against its ground truth."""
    from .io import read_image

    folder = Path(data) if data else Path(__file__).resolve().parent.parent / "data" / "sample"
    info_path = folder / "sample.json"
    if not info_path.exists():
        raise InputError(f"{info_path}: sample not found; run from a source checkout or give "
                         "--data DIR (make one with 'colorps synth --out DIR')")
    info = json.loads(info_path.read_text())
    g = info["gauge_sphere"]
    mask = folder / "mask.png"
    result = reconstruct_files([str(folder / "scene_*.exr")], [str(folder / "gauge_*.exr")],
                               (g["cx"], g["cy"], g["r"]), out,
                               gauge_albedo=info["gauge_albedo"], mode=mode, overwrite=overwrite,
                               mask_path=mask if mask.exists() else None)
    truth_n, _ = read_image(folder / "truth_normal.exr")
    truth_a, _ = read_image(folder / "truth_albedo.exr")
    truth_mask = read_mask(folder / "truth_mask.png", truth_n.shape[:2])
    ok = truth_mask & result.solved
    err = _angular_error_deg(result.normals[ok], truth_n[ok])
    rel = np.abs(result.albedo[ok] / truth_a[ok] - 1)
    print(f"colorps demo ({mode} mode): {ok.sum()} of {truth_mask.sum()} scene pixels solved")
    print(f"  normal error (deg): mean {err.mean():.3f}, median {np.median(err):.3f}, "
          f"95th percentile {np.percentile(err, 95):.3f}")
    print("  albedo relative error, median per band: "
          + ", ".join(f"{np.median(rel[:, k]):.2%}" for k in range(rel.shape[1])))
    truth_height = folder / "truth_height.exr"
    if result.height is not None and truth_height.exists():
        z_true = read_image(truth_height)[0][..., 0]
        both = ok & np.isfinite(result.height)
        err = (result.height[both] - result.height[both].mean()) - \
            (z_true[both] - z_true[both].mean())
        depth = np.ptp(z_true[both])
        print(f"  height RMS error {np.sqrt(np.mean(err ** 2)):.2f} px "
              f"({np.sqrt(np.mean(err ** 2)) / depth:.2%} of the {depth:.1f} px relief)")
    print(f"  outputs in {out}/ (normal.png, albedo.png, quality.exr, report.json, ...)")
    return result


def _warning_line(message, category, filename, lineno, line=None):
    return f"colorps: warning: {message}\n"


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    warnings.formatwarning = _warning_line
    try:
        if args.command == "reconstruct":
            result = reconstruct_files(
                args.scene, args.gauge, args.sphere, args.out, gauge_albedo=args.gauge_albedo,
                mode=args.mode, band=args.band, mask_path=args.mask, threads=args.threads,
                grid_n=args.grid_n, encoding=args.encoding, overwrite=args.overwrite,
                progress=not args.quiet, height=not args.no_height, mesh=args.mesh,
                clip_level=_none_or(args.clip_level, "auto"),
                dark_level="auto" if args.dark_level is None else args.dark_level,
                max_distance=_none_or(args.max_distance, None))
            if not args.quiet:
                s = result.stats
                print(f"solved {s['solved']} of {s['pixels']} pixels "
                      f"(table {s['table_size']}, grid N={s['grid_n']}, "
                      f"{s['seconds']['total']:.2f} s); results in {args.out}/")
        elif args.command == "integrate":
            z = integrate_file(args.normals, args.out, mask_path=args.mask,
                               weights_path=args.weights, method=args.method, mesh=args.mesh,
                               overwrite=args.overwrite)
            inside = np.isfinite(z)
            print(f"integrated {inside.sum()} pixels; relief depth "
                  f"{np.nanmax(z) - np.nanmin(z):.2f} px; wrote {args.out}")
        elif args.command == "demo":
            run_demo(args.out, args.data, args.mode, args.overwrite)
        elif args.command == "synth":
            from .synth import write_synthetic

            write_synthetic(args.out, size=args.size, images=args.images, theta=args.theta,
                            lights=args.lights, brdf=args.brdf, noise=args.noise,
                            gauge_radius=args.gauge_radius, seed=args.seed)
            print(f"wrote a synthetic stack with ground truth to {args.out}/")
    except ColorPSError as exc:
        print(f"colorps: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("colorps: interrupted; no partial results were written", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
