"""End to end: ``colorps reconstruct`` against the floor of reading and writing its files.

Run ``python benchmarks/end_to_end.py [--sizes 512 1024 2048] [--tile-at 4096]
[--images 8 96]``. For each scene size (pixels on a side) and number of images
it writes a synthetic capture with ``colorps synth`` (8 images unless
``--images`` says otherwise, one coloured light each, noise 0.005, gauge
images of 210 x 210 pixels, half-float EXR, the object mask), then runs, each
in a fresh process so that start-up and imports count as a user feels them:

* **colorps**: ``colorps reconstruct --sphere auto --mask ...`` with default
  options and all default outputs (sizes from ``--tile-at`` on with
  ``--tile``);
* **floor** (the same-outputs floor): a Python process that imports numpy and
  OpenImageIO, reads every scene and gauge image into float32 arrays and
  writes every file colorps wrote, from ready arrays (colorps's own results,
  loaded before the clock starts), in the same formats, pixel types, tiles and
  compression: the EXR and PNG maps and pictures, height.tif, report.json,
  index.html, and the viewer's levels (their PNGs encoded and put in base64
  as colorps does). Its wall time leaves out the loading of the ready arrays
  (the process prints it): the least any tool that reads these files and
  writes these results could take.

It prints a markdown table: wall seconds (best of ``--repeat``), the ratio to
the floor, peak resident memory (the child's ``ru_maxrss``), the float32 size
of the input, and how much the peak grows per byte of input from the previous
size (the memory target is at most 2); with several ``--images``, each run's
time over the same size's run with the fewest images.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

FLOOR = r"""
import base64, glob, json, os, sys, tempfile, time
import numpy as np
import OpenImageIO as oiio
capture, ready, out = sys.argv[1:4]

# Untimed (its seconds are printed and taken off): every file colorps wrote, as
# ready arrays in their stored pixel types, and the viewer's PNGs as arrays.
started = time.perf_counter()
images, texts, levels = {}, {}, {}
for path in sorted(glob.glob(ready + "/*")):
    name = os.path.basename(path)
    if name.endswith((".exr", ".png", ".tif")):
        image = oiio.ImageInput.open(path)
        spec = image.spec()
        images[name] = (image.read_image(spec.format), spec.format, spec.channelnames,
                        spec.tile_width)
        image.close()
    elif os.path.isfile(path):
        texts[name] = open(path, "rb").read()
scratch = tempfile.mkdtemp()
for path in sorted(glob.glob(ready + "/viewer/level*.js")):
    text = open(path).read()
    head, payload = text.split(", ", 1)
    maps = json.loads(payload[:-3])
    arrays = {}
    for map_name, urls in maps.items():
        pair = []
        for url in urls:
            png = os.path.join(scratch, "in.png")
            open(png, "wb").write(base64.b64decode(url.split(",", 1)[1]))
            image = oiio.ImageInput.open(png)
            pair.append(image.read_image(oiio.UINT8))
            image.close()
        arrays[map_name] = pair
    levels[os.path.basename(path)] = (head, arrays)
print(time.perf_counter() - started)


def write(path, data, fmt, names=None, tile=0):
    data = np.ascontiguousarray(data)
    spec = oiio.ImageSpec(data.shape[1], data.shape[0], data.shape[2], fmt)
    if names:
        spec.channelnames = names
    if tile:
        spec.tile_width = spec.tile_height = tile
    if path.endswith(".exr"):
        spec.attribute("compression", "zip")
    elif path.endswith(".png"):
        spec.attribute("png:compressionLevel", 1)
    output = oiio.ImageOutput.create(path)
    output.open(path, spec)
    output.write_image(data)
    output.close()


# Timed: read every input image, write every file colorps writes.
for path in sorted(glob.glob(capture + "/scene_*.exr")) + sorted(glob.glob(capture + "/gauge_*.exr")):
    image = oiio.ImageInput.open(path)
    image.read_image(oiio.FLOAT)
    image.close()
os.makedirs(out + "/viewer", exist_ok=True)
for name, (data, fmt, names, tile) in images.items():
    write(out + "/" + name, data, fmt, names, tile)
for name, data in texts.items():
    open(out + "/" + name, "wb").write(data)
for name, (head, arrays) in levels.items():
    encoded = {}
    for map_name, pair in arrays.items():
        urls = []
        for part in pair:
            png = os.path.join(scratch, "out.png")
            write(png, part, oiio.UINT8)
            urls.append("data:image/png;base64," + base64.b64encode(open(png, "rb").read()).decode())
        encoded[map_name] = urls
    open(out + "/viewer/" + name, "w").write(head + ", " + json.dumps(encoded) + ");\n")
"""


def run(command: list[str], untimed_in_stdout: bool = False) -> tuple[float, int]:
    """Wall seconds and peak resident bytes of one child process (``os.wait4``);
    with ``untimed_in_stdout``, less the seconds the child printed first."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        t0 = time.perf_counter()
        child = subprocess.Popen(command, stdout=out, stderr=err)
        _, status, usage = os.wait4(child.pid, 0)
        wall = time.perf_counter() - t0
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read(), err.read()
    if os.waitstatus_to_exitcode(status):
        raise RuntimeError(stderr.decode().strip().splitlines()[-1] if stderr.strip()
                           else f"exit code {os.waitstatus_to_exitcode(status)}")
    if untimed_in_stdout:
        wall -= float(stdout.decode().split()[0])
    return wall, usage.ru_maxrss * 1024  # KiB on Linux


def measure(command: list[str], repeat: int, untimed_in_stdout: bool = False
            ) -> tuple[float, int]:
    walls, peaks = [], []
    for _ in range(repeat):
        wall, peak = run(command, untimed_in_stdout)
        walls.append(wall)
        peaks.append(peak)
    return min(walls), max(peaks)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[512, 1024, 2048])
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--tile-at", type=int, default=4096,
                        help="sizes from this on also run with --tile (default: 4096)")
    parser.add_argument("--tile", type=int, default=1024)
    parser.add_argument("--memory-limit", type=float, default=None, metavar="GIB",
                        help="also run every size with --memory-limit GIB")
    parser.add_argument("--images", type=int, nargs="+", default=[8],
                        help="images (lights) per capture (default: 8)")
    args = parser.parse_args(argv)
    colorps = [sys.executable, "-m", "colorps"]  # as the console script runs it
    rows, previous, fewest = [], None, {}
    with tempfile.TemporaryDirectory() as tmp:
        for images, size in ((m, s) for m in sorted(args.images) for s in sorted(args.sizes)):
            if size == min(args.sizes):
                previous = None  # memory growth is between sizes of one light count
            capture = Path(tmp) / f"capture{size}_{images}"
            subprocess.run([*colorps, "synth", "--out", str(capture), "--size", str(size),
                            "--images", str(images), "--lights", "colour", "--noise", "0.005",
                            "--gauge-radius", "100"], check=True, capture_output=True)
            input_bytes = 4 * 3 * images * (size * size + 210 * 210)
            out = Path(tmp) / "out"
            out.mkdir(exist_ok=True)
            runs = [("colorps", [])]
            if size >= args.tile_at:
                runs = [(f"colorps --tile {args.tile}", ["--tile", str(args.tile)])]
            if args.memory_limit:
                runs.append((f"colorps --memory-limit {args.memory_limit:g}",
                             ["--memory-limit", str(args.memory_limit)]))
            measured = []
            for label, extra in runs:
                command = [*colorps, "reconstruct", "--scene", str(capture / "scene_*.exr"), "--gauge", str(capture / "gauge_*.exr"), "--sphere", "auto", "--mask", str(capture / "mask.png"), "--out", str(out / "result"), "--overwrite", "--quiet", *extra]
                try:
                    measured.append((label, *measure(command, args.repeat)))
                except RuntimeError as refused:
                    measured.append((label, None, str(refused)))
            floor_wall, _ = measure([sys.executable, "-c", FLOOR, str(capture),
                                     str(out / "result"), str(out / "floor")], args.repeat,
                                    untimed_in_stdout=True)
            for label, wall, peak in measured:
                if wall is None:
                    rows.append((f"{size * size / 1e6:.2f}", str(images), label,
                                 f"{floor_wall:.2f}", "refused", "", "", "",
                                 f"{input_bytes / 2**20:.0f}", peak))
                    continue
                fewest.setdefault((size, label), wall)
                first = label == runs[0][0]  # growth compares the sizes' first runs
                growth = ("" if previous is None or not first else
                          f"{(peak - previous[1]) / (input_bytes - previous[0]):.2f}")
                rows.append((f"{size * size / 1e6:.2f}", str(images), label,
                             f"{floor_wall:.2f}", f"{wall:.2f}", f"{wall / floor_wall:.1f}",
                             f"{wall / fewest[size, label]:.1f}", f"{peak / 2**20:.0f}",
                             f"{input_bytes / 2**20:.0f}", growth))
                if first:
                    previous = (input_bytes, peak)
            print(f"{size}, {images} images: done", file=sys.stderr)
    print(f"\nend to end, {os.cpu_count()} cores, RGB scene and gauge images, best of "
          f"{args.repeat}\n")
    head = ("MP", "images", "run", "floor s", "colorps s", "x floor",
            f"x {min(args.images)} images", "peak MiB", "input MiB",
            "peak growth / input byte")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for row in rows:
        print("| " + " | ".join(row) + " |")


if __name__ == "__main__":
    main()
