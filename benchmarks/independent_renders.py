"""Captures path-traced by an independent renderer (Mitsuba 3), solved by ``colorps reconstruct``.

Run ``python benchmarks/independent_renders.py [--finish diffuse plastic/diffuse]
[--lights 32] [--spp 32] [--keep DIR]`` (``pip install -e ".[bench]"``: Mitsuba 3 and its
CPU renderer; about two minutes a capture on 2 cores).

Our own renderer (:mod:`colorps.synth`) shares its conventions and its idea of
light with the solver it tests. Mitsuba shares neither: its camera, its pixel
filter (every edge blurred by a pixel or two), its smooth shading normals on a
triangle mesh, its path tracer's one-bounce interreflection with Monte Carlo
noise, its microfacet finishes. Each capture is

* a **pot**: a surface of revolution with grooves, and a torus for a handle in
  front of it (concave folds, cast shadows, light bounced between them), a
  texture of saturated colour patches, as OBJ meshes written by trimesh;
* a **gauge**: a sphere of the same finish (uniform albedo 0.8) off the axis,
  in images of its own (``SCENE/GAUGE``, e.g. ``plastic/diffuse``: a gauge of
  another finish);
* seen by DiLiGenT's camera (612 x 512 pixels, focal length 3772 pixels,
  ten object radii away), lit by ``--lights`` directional lights on a dome up
  to 45 degrees from the view, each a little coloured;
* rendered with ``path`` (``max_depth`` 3: direct light and one bounce) to
  half-float EXRs; the true normals from the ``aov`` integrator's shading
  normals (the mask: pixels whose every sample hit the object).

Then ``colorps reconstruct`` (each in a fresh process) in gauge mode with
default options, gauge mode with ``--camera K.txt`` (and the same with
``--no-interreflections``: the bounced light left in, its radii counting it), and virtual mode
(``--lights``, ``--camera``), against least squares on every light with the
true lights (Woodham; the bands' mean). It prints a markdown table: mean
(refused = 90 degrees) / median / solved, the share of errors within the 68 %
uncertainty, the facets (neighbouring pixels with identical normals) and wall
seconds.
"""

from __future__ import annotations

import argparse
import colorsys
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from colorps.io import read_image, write_image
from colorps.shapes import dome_lights

WIDTH, HEIGHT, FOCAL, DISTANCE = 612, 512, 3772.0, 10.0
GAUGE_CENTRE, GAUGE_RADIUS, GAUGE_ALBEDO = (0.25, -0.12, 0.0), 0.3, 0.8
FINISHES = ("diffuse", "plastic")  # plastic: diffuse under a GGX coat, alpha 0.3


def pot_meshes(folder: Path) -> list[Path]:
    """The pot and its handle as OBJ files (trimesh), texture coordinates included."""
    import trimesh

    def grid_faces(rows, cols):
        i, j = np.meshgrid(np.arange(rows - 1), np.arange(cols - 1), indexing="ij")
        a = i * cols + j
        return np.concatenate([np.stack([a, a + 1, a + cols], -1).reshape(-1, 3),
                               np.stack([a + 1, a + cols + 1, a + cols], -1).reshape(-1, 3)])

    y, u = np.meshgrid(np.linspace(-0.5, 0.5, 400), np.linspace(0, 2 * np.pi, 400), indexing="ij")
    radius = 0.30 + 0.035 * np.cos(2 * np.pi * y / 0.22) + 0.08 * np.sin(np.pi * (y + 0.5))
    pot = (np.stack([radius * np.sin(u), y, radius * np.cos(u)], -1),
           np.stack([u / (2 * np.pi), y + 0.5], -1))
    a, b = np.meshgrid(np.linspace(0, 2 * np.pi, 200), np.linspace(0, 2 * np.pi, 100), indexing="ij")
    ring = 0.16 + 0.045 * np.cos(b)
    handle = (np.stack([ring * np.cos(a) + 0.36, ring * np.sin(a) + 0.05,
                        0.045 * np.sin(b) + 0.12], -1),
              np.stack([a / (2 * np.pi), b / (2 * np.pi)], -1))
    paths = []
    for name, (points, uv) in (("pot", pot), ("handle", handle)):
        mesh = trimesh.Trimesh(points.reshape(-1, 3), grid_faces(*points.shape[:2]), process=False,
                               visual=trimesh.visual.TextureVisuals(uv=uv.reshape(-1, 2)))
        if mesh.volume < 0:  # faces outwards: Mitsuba's finishes are one-sided
            mesh.invert()
        paths.append(folder / f"{name}.obj")
        mesh.export(str(paths[-1]), include_normals=False)
    return paths


def texture(seed: int = 0) -> np.ndarray:
    """(512, 512, 3) linear albedo: 8 x 16 patches of saturated colours."""
    rng = np.random.default_rng(seed)
    cells = np.array([[colorsys.hsv_to_rgb(rng.random(), 0.5 + 0.5 * rng.random(),
                                           0.35 + 0.6 * rng.random()) for _ in range(16)]
                      for _ in range(8)])
    return np.repeat(np.repeat(cells, 64, 0), 32, 1).astype(np.float32)


def finish(mi, kind: str, reflectance) -> dict:
    """A Mitsuba BSDF of ``kind`` with a texture (array) or uniform albedo."""
    albedo = ({"type": "bitmap", "bitmap": mi.Bitmap(reflectance), "raw": True,
               "filter_type": "nearest"} if isinstance(reflectance, np.ndarray)
              else {"type": "rgb", "value": [reflectance] * 3})
    if kind == "diffuse":
        return {"type": "diffuse", "reflectance": albedo}
    return {"type": "roughplastic", "distribution": "ggx", "alpha": 0.3,
            "diffuse_reflectance": albedo, "nonlinear": False}


def sensor(mi, spp: int) -> dict:
    """DiLiGenT's camera: principal point at the image's centre, ten radii away."""
    return {"type": "perspective", "fov_axis": "x",
            "fov": 2 * math.degrees(math.atan(WIDTH / 2 / FOCAL)),
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, DISTANCE], target=[0, 0, 0],
                                                       up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": WIDTH, "height": HEIGHT, "pixel_format": "rgba"},
            "sampler": {"type": "independent", "sample_count": spp}}


def render_capture(folder: Path, kind: str, lights: int, spp: int) -> None:
    """Write the capture of ``kind`` (the finish, or SCENE/GAUGE finishes): scene_NN.exr,
    gauge_NN.exr, mask.png, lights.json, K.txt, truth.npy."""
    scene_finish, gauge_finish = (kind.split("/") * 2)[:2]
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    pot, handle = pot_meshes(folder)
    albedo = texture()
    scene = {name: {"type": "obj", "filename": str(path),
                    "bsdf": finish(mi, scene_finish, albedo)}
             for name, path in (("pot", pot), ("handle", handle))}
    gauge = {"ball": {"type": "sphere", "center": list(GAUGE_CENTRE), "radius": GAUGE_RADIUS,
                      "bsdf": finish(mi, gauge_finish, GAUGE_ALBEDO)}}
    truth = mi.load_dict({"type": "scene", "integrator": {"type": "aov", "aovs": "nn:sh_normal"},
                          "sensor": sensor(mi, 64), **scene})
    mi.render(truth)
    normals = np.array(truth.sensors()[0].film().bitmap())[..., 4:7]
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    mask = length[..., 0] > 0.995  # every sample on the object (its edges: fewer)
    np.save(folder / "truth.npy", np.where(mask[..., None], normals / np.maximum(length, 1e-9),
                                           np.nan).astype(np.float32))
    write_image(folder / "mask.png", mask.astype(np.uint8) * 255, dtype="uint8")
    directions = dome_lights(lights, 45.0).directions[:, 0]
    tints = 1.0 + 0.15 * np.random.default_rng(1).uniform(-1, 1, (lights, 3))
    for k, (direction, tint) in enumerate(zip(directions, tints)):
        light = {"type": "directional", "direction": (-direction).tolist(),
                 "irradiance": {"type": "rgb", "value": (np.pi * tint).tolist()}}
        for name, objects in (("scene", scene), ("gauge", gauge)):
            image = mi.render(mi.load_dict({
                "type": "scene", "sensor": sensor(mi, spp), "light": light,
                "integrator": {"type": "path", "max_depth": 3}, **objects}), seed=k)
            write_image(folder / f"{name}_{k:02d}.exr", np.array(image)[..., :3], dtype="half")
    (folder / "lights.json").write_text(json.dumps(
        {"directions": directions.tolist(), "intensities": tints.tolist()}))
    (folder / "K.txt").write_text(f"{FOCAL} 0 {(WIDTH - 1) / 2}\n0 {FOCAL} {(HEIGHT - 1) / 2}\n0 0 1\n")


def errors(folder: Path, out: Path) -> str:
    """Mean (refused = 90) / median / solved, and the share within the 68 % radius."""
    truth = np.load(folder / "truth.npy")
    mask = np.isfinite(truth[..., 0])
    normals = read_image(out / "normal.exr")[0][..., :3]
    radius = read_image(out / "uncertainty.exr")[0][..., 0]
    solved = mask & np.isfinite(normals[..., 0])
    error = np.full(mask.shape, 90.0)
    error[solved] = np.degrees(np.arccos(np.clip((normals[solved] * truth[solved]).sum(-1), -1, 1)))
    within = np.mean(error[solved] <= radius[solved])
    return (f"{error[mask].mean():.2f} / {np.median(error[mask]):.2f} / "
            f"{100 * solved[mask].mean():.2f}% | {100 * within:.0f}% | "
            f"{100 * facets(normals):.3f}%")


def facets(normals: np.ndarray) -> float:
    """The share of neighbouring solved pixels (across and down) whose normals are
    identical: flat patches of one gauge normal."""
    solved = np.isfinite(normals[..., 0])
    pairs = same = 0
    for a, b, both in ((normals[:, 1:], normals[:, :-1], solved[:, 1:] & solved[:, :-1]),
                       (normals[1:], normals[:-1], solved[1:] & solved[:-1])):
        pairs += int(both.sum())
        same += int((np.all(a == b, axis=-1) & both).sum())
    return same / max(pairs, 1)


def least_squares(folder: Path) -> str:
    """Woodham's photometric stereo on every light, with the true lights."""
    truth = np.load(folder / "truth.npy")
    mask = np.isfinite(truth[..., 0])
    lights = json.loads((folder / "lights.json").read_text())
    directions, tints = np.array(lights["directions"]), np.array(lights["intensities"])
    shading = np.array([read_image(folder / f"scene_{k:02d}.exr")[0][mask] / tints[k]
                        for k in range(len(directions))]).mean(axis=-1)
    g = np.linalg.lstsq(directions, shading, rcond=None)[0].T
    cosine = (g / np.linalg.norm(g, axis=1, keepdims=True) * truth[mask]).sum(-1)
    error = np.degrees(np.arccos(np.clip(cosine, -1, 1)))
    return f"{error.mean():.2f} / {np.median(error):.2f} / 100.00% |  | "


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--finish", nargs="+", default=list(FINISHES),
                        help=f"{' or '.join(FINISHES)}, or SCENE/GAUGE finishes")
    parser.add_argument("--lights", type=int, default=32)
    parser.add_argument("--spp", type=int, default=32, help="samples per pixel")
    parser.add_argument("--keep", type=Path, help="render into (or reuse) this folder")
    args = parser.parse_args()
    root = args.keep or Path(tempfile.mkdtemp())
    rows = []
    for kind in args.finish:
        if not set(kind.split("/")) <= set(FINISHES):
            parser.error(f"--finish {kind}: finishes are {', '.join(FINISHES)}")
        folder = root / f"{kind.replace('/', '-on-')}-{args.lights}"
        folder.mkdir(parents=True, exist_ok=True)
        if not (folder / "K.txt").exists():
            started = time.perf_counter()
            render_capture(folder, kind, args.lights, args.spp)
            print(f"{kind}: rendered in {time.perf_counter() - started:.0f} s", file=sys.stderr)
        base = [sys.executable, "-m", "colorps.cli", "reconstruct",
                "--scene", str(folder / "scene_*.exr"),
                "--mask", str(folder / "mask.png"), "--quiet", "--overwrite"]
        gauge = ["--gauge", str(folder / "gauge_*.exr"), "--sphere", "auto",
                 "--gauge-albedo", str(GAUGE_ALBEDO)]
        camera = ["--camera", str(folder / "K.txt")]
        runs = {"gauge, default options": gauge, "gauge, --camera": gauge + camera,
                "gauge, --camera --no-interreflections": [*gauge, *camera,
                                                          "--no-interreflections"],
                "virtual (--lights), --camera": ["--lights", str(folder / "lights.json"), *camera]}
        for name, extra in runs.items():
            out = folder / ("out-" + name.split(",")[0].split(" ")[0] + str(len(extra)))
            started = time.perf_counter()
            subprocess.run(base + extra + ["--out", str(out)], check=True)
            seconds = time.perf_counter() - started
            rows.append(f"| {kind} | {name} | {errors(folder, out)} | {seconds:.1f} |")
        rows.append(f"| {kind} | least squares, true lights | {least_squares(folder)} |  |")
    print(f"\nMitsuba 3 captures, {args.lights} lights, {args.spp} samples per pixel: mean "
          "(refused = 90 deg) / median (deg) / solved\n")
    print("| finish | run | errors | within 68 % | facets | seconds |")
    print("|---|---|---|---|---|---|")
    print("\n".join(rows))


if __name__ == "__main__":
    main()
