"""Real shapes: deep folds under many lights, gauge mode and virtual gauge against least squares.

Run ``python benchmarks/real_shapes.py [--size 200] [--diligent FOLDER]``.
Each synthetic set is a :func:`colorps.shapes.folds_surface` (a dome crossed by
grooves up to 0.35 radii deep) under a :func:`colorps.shapes.dome_lights` dome
(up to 60 degrees from the view), rendered with cast shadows and Gaussian noise
0.003, with a sphere gauge of radius 0.3 x size rendered under the same lights.
Variants: 32 and 96 lights; Oren-Nayar (rough) scene and gauge; a scene of a
slightly different finish than the gauge (Oren-Nayar sigma 0.3 scene, Lambertian
gauge); 8-bit sRGB files (quantised as a camera would store them); a one-bounce
interreflection in the folds (``synth.render(interreflection=1.0)``: physical,
the direct light of every patch seen, by form factors); a gauge seen
through a lens off the optical axis (pinhole, focal length 6 gauge diameters,
the sphere 0.8 diameters off the axis: 7.6 degrees), read with the camera (and,
in the next row, without it); a white GGX coat (alpha 0.3, the microfacet lobe
of physically based renderers) of Fresnel reflectance 0.5 on scene and gauge,
and a varnish (0.04) on the scene only; an 8-bit gauge exposed 1.01 times
brighter and clipped at the top code (where lights meet it head on), read
with that clip level; a small gauge (radius 20 px, 8-bit); fireflies (1 % of the
scene's and the gauge's measurements 3 to 30 times brighter, as a path tracer
leaves them). ``--only TEXT`` runs the sets whose names hold it.

For each set it prints the whole-mask mean angular error with refused pixels
counted as 90 degrees, the median, and the fraction solved, for

* **gauge**: ``colorps reconstruct`` itself (:func:`solved_by_reconstruct`: the
  set written to files, the gauge's circle given, default options), so with the
  light the folds bounce onto themselves taken out and, where the scene's finish
  is not its gauge's, the scene solved again with the gauge's lights and its own
  finish (the set's name then says "the finish route"); for the interreflection
  set a row more without the bounced light taken out;
* **virtual**: the gauge rendered under the calibrated lights with the finish
  fitted to the scene (:func:`colorps.virtual.virtual_gauge`, what ``--lights``
  does), the bounced light taken out likewise and the finish then fitted again;
* **least squares**: Woodham's Lambertian photometric stereo on every light
  (the bands' mean), every pixel solved;

where the gauge's finish differs from the scene's (even a little: Oren-Nayar 0.2
against 0.3), a row more: virtual mode with
the lights measured on the gauge (:func:`colorps.matte_lights.matte_sphere_lights`,
what ``calibrate-lights --matte`` writes); the **facets** of gauge mode: the
fraction of neighbouring solved pixels whose normals are identical (flat patches where the refinement kept a table
normal), and how many of its errors lie within the 68 % uncertainty.

With ``--diligent FOLDER`` (DiLiGenT's ``pmsData/ballPNG``) it adds the Ball, in
virtual mode (it has no gauge photographs).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from colorps import Gauge, Lights, Options, angular_error, reconstruct, synth
from colorps.camera import Camera
from colorps.finishes import Gloss
from colorps.gauge import rim_margin
from colorps.interreflection import without_interreflections
from colorps.matte_lights import matte_sphere_lights
from colorps.memory import kept_grids_mib
from colorps.resolve import StackModel, resolve
from colorps.shapes import dome_lights, folds_surface
from colorps.tables import GaugeTables
from colorps.virtual import corrected, match_along_rays, virtual_gauge, with_own_finish

NOISE = 0.003
#: Roughness of the glossy sets' GGX coat (a renderer's roughness 0.55).
GGX_ALPHA = 0.3


def quantise_srgb(stack: np.ndarray) -> np.ndarray:
    """Linear values as an 8-bit sRGB file stores and colorps decodes them."""
    from colorps.io import srgb_decode, srgb_encode

    return srgb_decode(np.round(srgb_encode(stack) * 255) / 255).astype(np.float32)


def make_set(size: int, m: int, scene_brdf: str, gauge_brdf: str, eight_bit: bool, *,
             interreflection: float = 0.0, perspective: bool = False, gloss: float = 0.0,
             gauge_gloss: float = 0.0, gauge_exposure: float | None = None,
             gauge_radius: float | None = None, fireflies: float = 0.0,
             gauge_roughness: float = 0.3):
    lights = dome_lights(m)
    scene = folds_surface(size)
    stack = synth.render(scene, lights, brdf=scene_brdf, roughness=0.3, noise=NOISE, seed=1,
                         cast_shadows=True, interreflection=interreflection,
                         gloss=Gloss(gloss, "ggx", alpha=GGX_ALPHA))
    radius = 0.3 * size if gauge_radius is None else gauge_radius
    gauge_size = int(2 * radius + 10)
    centre = (gauge_size - 1) / 2
    camera = None
    if perspective:  # the optical axis 0.8 diameters to the left of the sphere
        focal = 6 * 2 * radius
        camera = Camera(focal, focal, centre - 1.6 * radius, centre)
    whole = Gauge.from_sphere((gauge_size, gauge_size), centre, centre, radius, rim_margin=0.0,
                              camera=camera)  # the sphere as photographed, to its edge
    ball = synth.SyntheticSurface(normals=np.where(whole.mask[..., None], whole.normals, 0.0),
                                  mask=whole.mask, albedo=np.ones((gauge_size, gauge_size, 3)),
                                  height=np.zeros((gauge_size, gauge_size)))
    gauge_stack = synth.render(ball, lights, brdf=gauge_brdf, roughness=gauge_roughness,
                               noise=NOISE, seed=2,
                               gloss=Gloss(gauge_gloss, "ggx", alpha=GGX_ALPHA))
    if gauge_exposure is not None:  # exposed this much brighter, clipped at 1 as files are
        gauge_stack = np.minimum(gauge_exposure * gauge_stack, 1.0)
    if eight_bit:
        stack, gauge_stack = quantise_srgb(stack), quantise_srgb(gauge_stack)
    if fireflies:
        stack, gauge_stack = spiked(stack, fireflies, 3), spiked(gauge_stack, fireflies, 4)
    circle = (centre, centre, radius)  # its rim margin measured, as colorps reconstruct does
    gauge = Gauge.from_sphere((gauge_size, gauge_size), *circle, camera=camera,
                              rim_margin=rim_margin(gauge_stack, circle, camera))
    return scene, lights, stack, gauge_stack, gauge, camera


def spiked(stack: np.ndarray, rate: float, seed: int) -> np.ndarray:
    """``stack`` with ``rate`` of its (image, pixel) measurements 3 to 30 times
    brighter plus 0.05: a path tracer's fireflies."""
    rng = np.random.default_rng(seed)
    hit = rng.random(stack.shape[:3]) < rate
    gain = rng.uniform(3.0, 30.0, stack.shape[:3])
    out = stack.copy()
    out[hit] = out[hit] * gain[hit][:, None] + 0.05
    return out


def scores(normals, solved, truth, mask) -> tuple[float, float, float]:
    error = np.where(solved[mask], angular_error(normals[mask], truth[mask]), 90.0)
    return float(error.mean()), float(np.median(error)), float(solved[mask].mean())


def facets(normals, solved) -> float:
    """Fraction of neighbouring solved pixel pairs (4-neighbours) with identical normals."""
    across = solved[:, 1:] & solved[:, :-1]
    down = solved[1:] & solved[:-1]
    same = ((normals[:, 1:] == normals[:, :-1]).all(-1) & across).sum() + \
        ((normals[1:] == normals[:-1]).all(-1) & down).sum()
    return float(same / max(1, across.sum() + down.sum()))


def least_squares(stack, directions, mask) -> np.ndarray:
    g = np.linalg.lstsq(directions, stack.mean(axis=3)[:, mask], rcond=None)[0].T
    normals = np.zeros((*mask.shape, 3))
    normals[mask] = g / np.linalg.norm(g, axis=1, keepdims=True)
    return normals


def solved_as_colorps_does(stack, gauge_stack, gauge, settings, mask, first=None,
                           read_scene=None):
    """``reconstruct`` (or ``first``, a solve already made), then the light a concave
    object bounces onto itself taken out
    (:func:`colorps.interreflection.without_interreflections`, from the scene as
    ``read_scene()`` gives it, ``stack`` by default), as ``colorps reconstruct``
    does by default (the gauge's side and its grids shared by every solve): the
    result and the measurements it was solved from (None: ``stack``)."""
    tables = GaugeTables(kept_grids_mib("auto", stack.shape))

    def solve(images, pixels=None, model_scale=None):
        return reconstruct(images, gauge_stack, gauge, settings, model_scale=model_scale,
                           mask=mask if pixels is None else pixels, tables=tables)

    first = solve(stack) if first is None else first
    return without_interreflections(read_scene or (lambda: stack), first, solve, gauge,
                                    gauge_stack)[:2]


def solved_by_reconstruct(stack, gauge_stack, gauge, mask, eight_bit: bool, *,
                          camera=None, options: Options | None = None):
    """``colorps reconstruct``'s orchestrator (:func:`colorps.pipeline.reconstruct_files`)
    on the set written to files: float EXRs, or 8-bit sRGB PNGs for an 8-bit set, the
    gauge's circle given (``--sphere``), the scene's mask, ``camera`` (``--camera``, None:
    orthographic). So the gauge column is what a user gets: the bounced light taken
    out, and a scene whose finish is not its gauge's solved again with the gauge's
    lights and its own finish. The result and report.json's ``gauge_check``."""
    import json
    import tempfile

    from colorps.inputs import CaptureFiles
    from colorps.io import srgb_encode, write_image
    from colorps.pipeline import reconstruct_files

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for name, images in (("scene", stack), ("gauge", gauge_stack)):
            for k, image in enumerate(images):
                if eight_bit:  # the codes the set was quantised to
                    write_image(folder / f"{name}_{k:02d}.png",
                                np.round(srgb_encode(image) * 255).astype(np.uint8), dtype="uint8")
                else:
                    write_image(folder / f"{name}_{k:02d}.exr", image)
        write_image(folder / "mask.png", mask.astype(np.uint8) * 255, dtype="uint8")
        ext = "png" if eight_bit else "exr"
        inputs = CaptureFiles(str(folder / f"scene_*.{ext}"), gauge=str(folder / f"gauge_*.{ext}"),
                              sphere=gauge.sphere, mask=folder / "mask.png",
                              camera="orthographic" if camera is None else camera)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # (the route is recorded in report.json)
            result = reconstruct_files(inputs, folder / "out", options=options,
                                       progress=False)
        report = json.loads((folder / "out" / "report.json").read_text())
    return result, report.get("gauge_check", {})


def run_virtual(stack, lights: Lights, mask, settings=None):
    """Virtual mode as ``colorps reconstruct --lights`` runs it: the finish fitted,
    matched (again, corrected, where the finish asks for it), the bounced light
    taken out of the scene as that match saw it, the finish fitted again."""
    gauge, run, brdf, _ = virtual_gauge(stack, lights, settings or Options(), mask=mask)
    first, _ = match_along_rays(stack.copy(), gauge, run, lights, brdf, None, mask=mask)
    result, corrected_stack = solved_as_colorps_does(
        stack, gauge.stack, gauge, run, mask, first,
        lambda: corrected(stack.copy(), first, lights, brdf, None, run))
    if corrected_stack is None:
        return result
    return with_own_finish(corrected_stack, lights, run, mask=mask)[0]  # fitted again


def coverage(result, truth, mask) -> float:
    """Fraction of the solved pixels whose error is within their 68 % uncertainty."""
    ok = mask & result.solved & np.isfinite(result.uncertainty)
    return float(np.mean(angular_error(result.normals[ok], truth[ok]) <= result.uncertainty[ok]))


def row(name, results, seconds, facet=float("nan"), within=float("nan")):
    cells = " | ".join(f"{mean:.2f} / {median:.2f} / {solved:.2%}"
                       for mean, median, solved in results)
    print(f"| {name} | {cells} | {facet:.2%} | {within:.0%} | {seconds:.1f} |", flush=True)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=200)
    parser.add_argument("--diligent", type=Path)
    parser.add_argument("--only", default="", metavar="TEXT")
    args = parser.parse_args(argv)
    print("mean (refused = 90 deg) / median (deg) / solved\n")
    print("| set | gauge | virtual | least squares | gauge-mode facets | gauge-mode within "
          "68 % | gauge-mode seconds |")
    print("|---|---|---|---|---|---|---|")
    sets = [("32 lights, Lambertian", 32, "lambert", "lambert", False, {}),
            ("96 lights, Lambertian", 96, "lambert", "lambert", False, {}),
            ("32 lights, rough (Oren-Nayar) scene and gauge", 32, "oren-nayar", "oren-nayar",
             False, {}),
            ("32 lights, rough scene, Lambertian gauge", 32, "oren-nayar", "lambert", False,
             {}),
            ("32 lights, 8-bit sRGB", 32, "lambert", "lambert", True, {}),
            ("32 lights, 8-bit sRGB, rough scene, Lambertian gauge", 32, "oren-nayar",
             "lambert", True, {}),
            ("32 lights, 8-bit sRGB, rough scene (0.3), gauge a little smoother (0.2)", 32,
             "oren-nayar", "oren-nayar", True, {"gauge_roughness": 0.2}),
            ("32 lights, one-bounce interreflection (physical)", 32, "lambert", "lambert",
             False, {"interreflection": 1.0}),
            ("32 lights, perspective gauge, with --camera", 32, "lambert", "lambert", False,
             {"perspective": True}),
            ("32 lights, glossy (GGX coat F0 0.5) scene and gauge", 32, "lambert", "lambert",
             False, {"gloss": 0.5, "gauge_gloss": 0.5}),
            ("32 lights, varnished (GGX coat F0 0.04) scene, matte gauge", 32, "lambert",
             "lambert", False, {"gloss": 0.04}),
            ("32 lights, 8-bit sRGB, gauge exposed 1.01x and clipped", 32, "lambert", "lambert",
             True, {"gauge_exposure": 1.01}),
            ("32 lights, 8-bit sRGB, small gauge (radius 20 px)", 32, "lambert", "lambert", True,
             {"gauge_radius": 20}),
            ("32 lights, fireflies (1 % of scene and gauge measurements 3-30x)", 32, "lambert",
             "lambert", False, {"fireflies": 0.01})]
    for name, m, scene_brdf, gauge_brdf, eight_bit, extra in sets:
        if args.only not in name:
            continue
        scene, lights, stack, gauge_stack, gauge, camera = make_set(
            args.size, m, scene_brdf, gauge_brdf, eight_bit, **extra)
        mask = scene.mask
        t0 = time.perf_counter()
        clip = {"clip_level": 1.0} if "gauge_exposure" in extra else {}
        result, checked = solved_by_reconstruct(stack, gauge_stack, gauge, mask, eight_bit,
                                                camera=camera, options=Options(**clip))
        seconds = time.perf_counter() - t0
        if checked.get("finish", {}).get("taken"):
            name += " (the finish route)"
        if extra.get("interreflection"):  # the bounced light left in (and in the radii)
            kept = solved_by_reconstruct(stack, gauge_stack, gauge, mask, eight_bit, camera=camera,
                                         options=Options(interreflections=False, **clip))[0]
            mean, median, solved = scores(kept.normals, kept.solved, scene.normals, mask)
            print(f"| (the same, --no-interreflections) | {mean:.2f} / {median:.2f} / "
                  f"{solved:.2%} | | | {facets(kept.normals, kept.solved & mask):.2%} | "
                  f"{coverage(kept, scene.normals, mask):.0%} | |", flush=True)
        plain = None
        if extra.get("perspective"):  # the same images, the gauge read orthographically
            plain = solved_by_reconstruct(stack, gauge_stack, gauge, mask, eight_bit)[0]
        calibrated = Lights(lights.directions[:, 0, :], lights.colours[:, 0, :])
        virtual = run_virtual(stack, calibrated, mask)
        ls = least_squares(stack, lights.directions[:, 0, :], mask)
        row(name, [scores(result.normals, result.solved, scene.normals, mask),
                   scores(virtual.normals, virtual.solved, scene.normals, mask),
                   scores(ls, mask, scene.normals, mask)], seconds,
            facets(result.normals, result.solved & mask), coverage(result, scene.normals, mask))
        if plain is not None:
            mean, median, solved = scores(plain.normals, plain.solved, scene.normals, mask)
            print(f"| (the same gauge read without the camera) | {mean:.2f} / {median:.2f} / "
                  f"{solved:.2%} | | | | {coverage(plain, scene.normals, mask):.0%} | |",
                  flush=True)
        if scene_brdf != gauge_brdf or "gauge_roughness" in extra:
            # the gauge's lights, for the scene's own finish
            measured, _ = matte_sphere_lights(gauge_stack, gauge.sphere)
            by_lights = run_virtual(stack, measured, mask)
            mean, median, solved = scores(by_lights.normals, by_lights.solved, scene.normals,
                                          mask)
            print(f"| (the same, lights from the gauge: calibrate-lights --matte) | | "
                  f"{mean:.2f} / {median:.2f} / {solved:.2%} | | | | |", flush=True)
    if args.diligent is not None:
        ball(args.diligent)


def ball(folder: Path) -> None:
    from scipy.io import loadmat

    from colorps import read_lights
    from colorps.io import read_mask, read_stack

    names = (folder / "filenames.txt").read_text().split()
    stack, _ = read_stack([folder / n for n in names], "linear", name="ball")
    lights = read_lights(folder / "light_directions.txt", folder / "light_intensities.txt",
                         images=len(names))
    truth = loadmat(folder / "Normal_gt.mat")["Normal_gt"].astype(np.float64)
    mask = read_mask(folder / "mask.png", truth.shape[:2])
    # 16-bit files: their clip level and quantisation, as colorps reconstruct reads them.
    stored = resolve(Options(encoding="linear"),
                     scene=StackModel.of_file(folder / names[0], "linear"))
    t0 = time.perf_counter()
    result = run_virtual(stack, lights, mask, stored)
    seconds = time.perf_counter() - t0
    ls = least_squares(stack / lights.intensities[:, None, None, :], lights.directions, mask)
    row("DiLiGenT Ball (96 photographs)", [(np.nan, np.nan, np.nan),
                                           scores(result.normals, result.solved, truth, mask),
                                           scores(ls, mask, truth, mask)], seconds,
        within=coverage(result, truth, mask))


if __name__ == "__main__":
    main()
