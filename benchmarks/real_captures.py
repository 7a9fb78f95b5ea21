"""Accuracy on messy synthetic captures: band weights and light subsets, against brute force.

Run ``python benchmarks/real_captures.py [--size 256]``. Each scene is a smiley
(coloured albedo with saturated regions) and a sphere gauge of radius
``--gauge-radius`` under m distant lights, rendered with the messes of real
captures: noise, coloured lights, cast shadows of the relief, a highlight the
gauge does not share, 8-bit sRGB quantisation. Every method is scored on the
whole object mask, counting refused pixels as 90 degrees:

* ``brute force``: float64 nearest colour signature over all lights, every
  band alike, nothing refused (scipy's cKDTree, exact);
* ``brute force grey``: the same on luminance (a plain grey lookup);
* colorps in mono mode, colour unweighted and colour weighted, each with and
  without light subsets (defaults otherwise: refusal by the noise model).

Prints a markdown table (solved %, mean / median / 95th percentile error,
seconds) per scene.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from colorps import Gauge, angular_error, compute_signatures, reconstruct, synth  # noqa: E402
from colorps.io import srgb_decode, srgb_encode  # noqa: E402
from colorps.io import DARK_CODES  # noqa: E402
from colorps.noise import NoiseModel  # noqa: E402
from colorps.resolve import StackModel, resolve  # noqa: E402


def coloured_lights(m: int, theta: float) -> synth.Lighting:
    phase = 2 * np.pi * np.arange(m) / m
    hue = 0.5 + 0.5 * np.cos(phase[:, None] - np.array([0.0, 2.0, 4.0]) * np.pi / 3)
    return synth.ring_lights(m, theta, 0.1 + 0.9 * hue)


def eight_bit(stack: np.ndarray) -> np.ndarray:
    """Quantise linear values as an 8-bit sRGB file would, and decode them again."""
    codes = np.round(srgb_encode(np.clip(stack, 0, 1)) * 255) / 255
    return srgb_decode(codes)


SCENES = {
    "white, noise 0.005": dict(lights=lambda: synth.ring_lights(8, 45), noise=0.005),
    "colour lights, noise 0.005": dict(lights=lambda: coloured_lights(8, 45), noise=0.005),
    "cast shadows (theta 60), noise 0.002": dict(
        lights=lambda: synth.ring_lights(8, 60), noise=0.002, relief=0.2,
        render=dict(cast_shadows=True)),
    "highlights, noise 0.002": dict(lights=lambda: synth.ring_lights(8, 45), noise=0.002,
                                    render=dict(gloss=0.5),
                                    gauge_render={}),
    "8-bit sRGB, 12 lights, noise 0.003, shadows": dict(
        lights=lambda: synth.ring_lights(12, 50), noise=0.003, relief=0.2, bits=8,
        render=dict(cast_shadows=True)),
}
METHODS = {
    "mono": dict(mode="mono"),
    "mono + subsets": dict(mode="mono", light_subsets=True),
    "colour unweighted": dict(band_weights=False),
    "colour unweighted + subsets": dict(band_weights=False, light_subsets=True),
    "colour weighted": dict(),
    "colour weighted + subsets": dict(light_subsets=True),
}


def brute_force(scene_stack, gauge_stack, gauge, mask, grey: bool) -> np.ndarray:
    """Normals of the float64 nearest signature over all lights (nothing refused)."""
    from scipy.spatial import cKDTree

    mode = "mono" if grey else "colour"
    s = compute_signatures(scene_stack, mode, min_norm=0.0)
    g = compute_signatures(gauge_stack, mode, min_norm=0.0)
    table = g.valid & gauge.mask
    tree = cKDTree(g.signatures[table].astype(np.float64))
    _, rows = tree.query(s.signatures[mask].astype(np.float64))
    normals = np.full(mask.shape + (3,), np.nan)
    normals[mask] = gauge.normals[table][rows]
    return normals


def score(normals, solved, truth, mask) -> tuple[float, float, float, float]:
    err = np.where(solved, angular_error(normals, truth), 90.0)[mask]
    return (float(solved[mask].mean()), float(err.mean()), float(np.median(err)),
            float(np.percentile(err, 95)))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256, help="scene size (px)")
    parser.add_argument("--gauge-radius", type=int, default=80, help="sphere radius (px)")
    parser.add_argument("--figure", metavar="PNG",
                        help="also draw the cast-shadow scene's maps into this picture")
    args = parser.parse_args(argv)
    r = args.gauge_radius
    size = 2 * r + 10
    centre = (size - 1) / 2
    gauge = Gauge.from_sphere((size, size), centre, centre, r)
    ball = synth.sphere_surface(size, r)
    print(f"Scenes {args.size} px, gauge r = {r} px; error in degrees over the object "
          "mask, refused pixels counted as 90.\n")
    for name, spec in SCENES.items():
        lights = spec["lights"]()
        scene = synth.smiley_surface(args.size, relief=spec.get("relief", 0.12))
        stack = synth.render(scene, lights, noise=spec["noise"], seed=1, **spec.get("render", {}))
        gauge_stack = synth.render(ball, lights, noise=spec["noise"], seed=2)
        storage = None  # float arrays
        if spec.get("bits") == 8:
            stack, gauge_stack = eight_bit(stack), eight_bit(gauge_stack)
            clip, dark = srgb_decode(np.array([254.5, DARK_CODES]) / 255)  # as 8-bit files'
            storage = StackModel(float(clip), float(dark), NoiseModel(
                0.0, 0.0, pixel_type="int", top_code=255, encoding="srgb"))
        mask = scene.mask
        print(f"### {name} (m = {lights.images})\n")
        print("| method | solved | mean | median | 95th pct | seconds |")
        print("|---|---|---|---|---|---|")
        for label, grey in (("brute force (float64, all lights)", False),
                            ("brute force grey", True)):
            t0 = time.perf_counter()
            normals = brute_force(stack, gauge_stack, gauge, mask, grey)
            seconds = time.perf_counter() - t0
            solved, mean, median, p95 = score(normals, mask, scene.normals, mask)
            print(f"| {label} | {solved:.1%} | {mean:.2f} | {median:.2f} | {p95:.2f} | "
                  f"{seconds:.2f} |")
        for label, changes in METHODS.items():
            changes = dict(changes)
            changes.setdefault("light_subsets", False)
            t0 = time.perf_counter()
            result = reconstruct(stack, gauge_stack, gauge, resolve(None, scene=storage),
                                 mask=mask, **changes)
            seconds = time.perf_counter() - t0
            solved, mean, median, p95 = score(result.normals, result.solved, scene.normals,
                                              mask)
            print(f"| colorps {label} | {solved:.1%} | {mean:.2f} | {median:.2f} | "
                  f"{p95:.2f} | {seconds:.2f} |", flush=True)
        print()
        if args.figure and "cast shadows" in name:
            draw(args.figure, stack, gauge_stack, gauge, scene)
    return 0


def draw(path, stack, gauge_stack, gauge, scene) -> None:
    """Scene, quality, dropped lights and errors with and without light subsets."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from colorps.figures import dropped_picture

    full = reconstruct(stack, gauge_stack, gauge, mask=scene.mask)
    plain = reconstruct(stack, gauge_stack, gauge, mask=scene.mask, light_subsets=False)
    panels = [
        ("scene (mean image)", srgb_encode(np.clip(stack.mean(axis=0), 0, 1)), {}),
        ("quality without subsets\n(residual, noise units)",
         np.where(scene.mask, plain.quality, np.nan), dict(cmap="magma", vmin=0, vmax=10)),
        ("lights dropped\n(blue 1, orange 2)", dropped_picture(full.lights_dropped_count), {}),
        ("error without subsets (deg)",
         np.where(plain.solved, angular_error(plain.normals, scene.normals), 90.0),
         dict(cmap="viridis", vmin=0, vmax=10)),
        ("error with subsets (deg)",
         np.where(full.solved, angular_error(full.normals, scene.normals), 90.0),
         dict(cmap="viridis", vmin=0, vmax=10)),
    ]
    fig, axes = plt.subplots(1, len(panels), figsize=(3.2 * len(panels), 3.6))
    for ax, (title, image, style) in zip(axes, panels):
        shown = ax.imshow(np.where(scene.mask[..., None] if image.ndim == 3 else scene.mask,
                                   image, np.nan if image.ndim == 2 else 0), **style)
        ax.set_title(title, fontsize=9)
        ax.axis("off")
        if style:
            fig.colorbar(shown, ax=ax, fraction=0.046, pad=0.02)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    print(f"wrote {path}")


if __name__ == "__main__":
    sys.exit(main())
