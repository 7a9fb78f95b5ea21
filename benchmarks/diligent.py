"""colorps on a DiLiGenT object: mean / median angular error against its ground truth.

Run ``python benchmarks/diligent.py FOLDER [--mode colour|mono]`` with a DiLiGenT
object folder (``pmsData/ballPNG`` and the like: 96 16-bit linear PNGs,
``light_directions.txt``, ``light_intensities.txt``, ``mask.png``,
``Normal_gt.mat``). The data set is not ours to ship: get it from its authors
(or the public copy in the t-taniai/neuralps repository). colorps runs
``reconstruct`` with a virtual gauge rendered under the calibrated lights
(``--lights``) with the finish fitted to the scene (``--brdf fitted``), default
options otherwise, and the images read as linear. It also prints least squares
(Woodham's Lambertian photometric stereo on every light) for comparison.

DiLiGenT's light and normal coordinates are x right, y up, z towards the
camera, like colorps's.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from colorps import Options, angular_error  # noqa: E402
from colorps.inputs import CaptureFiles  # noqa: E402
from colorps.pipeline import reconstruct_files  # noqa: E402


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folder", type=Path)
    parser.add_argument("--mode", choices=("colour", "mono"), default="colour")
    parser.add_argument("--refine", choices=("quadratic", "none"), default="quadratic")
    parser.add_argument("--brdf", choices=("fitted", "lambert"), default="fitted")
    parser.add_argument("--no-light-subsets", dest="light_subsets", action="store_false")
    parser.add_argument("--keep-all", action="store_true",
                        help="refuse nothing (max_residual None)")
    args = parser.parse_args(argv)
    from scipy.io import loadmat

    folder = args.folder
    names = (folder / "filenames.txt").read_text().split()
    truth = loadmat(folder / "Normal_gt.mat")["Normal_gt"].astype(np.float64)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        inputs = CaptureFiles([str(folder / n) for n in names], mask=folder / "mask.png",
                              lights=folder / "light_directions.txt",
                              light_intensities=folder / "light_intensities.txt")
        result = reconstruct_files(
            inputs, Path(tmp) / "out",
            options=Options(mode=args.mode, refine=args.refine, encoding="linear", brdf=args.brdf,
                            height=False, light_subsets=args.light_subsets,
                            max_residual=None if args.keep_all else Options().max_residual),
            progress=False)
        seconds = time.perf_counter() - t0
    from colorps.io import read_mask

    mask = read_mask(folder / "mask.png", truth.shape[:2])
    solved = result.solved & mask
    err = np.where(solved, angular_error(result.normals, truth), 90.0)[mask]
    s = result.stats
    print(f"{folder.name}: {args.mode} mode, brdf {args.brdf}, refine {args.refine}, light subsets "
          f"{args.light_subsets}, keep all {args.keep_all}, {s.images} images")
    print(f"  solved {solved.sum()} of {mask.sum()} mask pixels ({solved.sum() / mask.sum():.2%})")
    print(f"  angular error (refused = 90 deg): mean {err.mean():.2f}, median "
          f"{np.median(err):.2f}, 95th percentile {np.percentile(err, 95):.2f} deg")
    solved_err = angular_error(result.normals[solved], truth[solved])
    print(f"  over solved pixels: mean {solved_err.mean():.2f}, median "
          f"{np.median(solved_err):.2f} deg; model scale {s.model_scale:.2f}, "
          f"{s.solved_from_light_subset} from a light subset; {seconds:.1f} s")
    ls = least_squares_normals(folder, names, mask)
    ls_err = angular_error(ls[mask], truth[mask])
    print(f"  least squares (all lights, Lambertian): mean {ls_err.mean():.2f}, median "
          f"{np.median(ls_err):.2f} deg")
    return 0


def least_squares_normals(folder: Path, names, mask) -> np.ndarray:
    """Woodham's photometric stereo: n ~ pinv(L) I per pixel, grey = mean of I / E."""
    from colorps import read_lights
    from colorps.io import read_stack

    lights = read_lights(folder / "light_directions.txt", folder / "light_intensities.txt")
    stack, _ = read_stack([str(folder / n) for n in names], "linear", progress=False)
    grey = (stack[:, mask] / lights.intensities[:, None, :]).mean(axis=-1)  # (m, P)
    solution = np.linalg.pinv(lights.directions) @ grey
    normals = np.full(mask.shape + (3,), np.nan)
    normals[mask] = (solution / np.linalg.norm(solution, axis=0)).T
    return normals


if __name__ == "__main__":
    sys.exit(main())
