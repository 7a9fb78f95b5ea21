"""End to end: ``colorps reconstruct`` against the floor of reading and writing its files.

Run ``python benchmarks/end_to_end.py [--sizes 512 1024 2048] [--tile-at 4096]``.
For each scene size (pixels on a side) it writes a synthetic capture with
``colorps synth`` (8 images, one coloured light each, noise 0.005, gauge
images of 210 x 210 pixels, half-float EXR, the object mask), then runs, each
in a fresh process so that start-up and imports count as a user feels them:

* **floor**: a Python process that imports numpy and OpenImageIO, reads every
  scene and gauge image into float32 arrays and writes one float32 EXR and one
  8-bit PNG of the scene's size: the least any tool that reads these files and
  writes a result could do;
* **colorps**: ``colorps reconstruct --sphere auto --mask ...`` with default
  options and all default outputs (sizes from ``--tile-at`` on with
  ``--tile``).

It prints a markdown table: wall seconds (best of ``--repeat``), the ratio to
the floor, peak resident memory (the child's ``ru_maxrss``), the float32 size
of the input, and how much the peak grows per byte of input from the previous
size (the memory target is at most 2).
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
import sys, glob
import numpy as np
import OpenImageIO as oiio
folder, out = sys.argv[1], sys.argv[2]
arrays = []
for path in sorted(glob.glob(folder + "/scene_*.exr")) + sorted(glob.glob(folder + "/gauge_*.exr")):
    image = oiio.ImageInput.open(path)
    arrays.append(image.read_image(oiio.FLOAT))
    image.close()
picture = np.asarray(arrays[0], np.float32)
spec = oiio.ImageSpec(picture.shape[1], picture.shape[0], 3, oiio.FLOAT)
for name, data, fmt in (("floor.exr", picture, oiio.FLOAT),
                        ("floor.png", (np.clip(picture, 0, 1) * 255).astype(np.uint8),
                         oiio.UINT8)):
    spec = oiio.ImageSpec(data.shape[1], data.shape[0], data.shape[2], fmt)
    output = oiio.ImageOutput.create(out + "/" + name)
    output.open(out + "/" + name, spec)
    output.write_image(data)
    output.close()
"""


def run(command: list[str]) -> tuple[float, int]:
    """Wall seconds and peak resident bytes of one child process (``os.wait4``)."""
    t0 = time.perf_counter()
    child = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    stderr = child.stderr.read()
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - t0
    child.returncode = os.waitstatus_to_exitcode(status)
    if child.returncode:
        raise RuntimeError(stderr.decode().strip().splitlines()[-1] if stderr.strip()
                           else f"exit code {child.returncode}")
    return wall, usage.ru_maxrss * 1024  # KiB on Linux


def measure(command: list[str], repeat: int) -> tuple[float, int]:
    walls, peaks = [], []
    for _ in range(repeat):
        wall, peak = run(command)
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
    args = parser.parse_args(argv)
    colorps = [sys.executable, "-m", "colorps.cli"]
    rows, previous = [], None
    with tempfile.TemporaryDirectory() as tmp:
        for size in sorted(args.sizes):
            capture = Path(tmp) / f"capture{size}"
            subprocess.run(colorps + ["synth", "--out", str(capture), "--size", str(size),
                                      "--lights", "colour", "--noise", "0.005",
                                      "--gauge-radius", "100"], check=True,
                           capture_output=True)
            input_bytes = 4 * 3 * 8 * (size * size + 210 * 210)
            out = Path(tmp) / "out"
            out.mkdir(exist_ok=True)
            floor_wall, floor_peak = measure([sys.executable, "-c", FLOOR, str(capture),
                                              str(out)], args.repeat)
            runs = [("colorps", [])]
            if size >= args.tile_at:
                runs = [(f"colorps --tile {args.tile}", ["--tile", str(args.tile)])]
            if args.memory_limit:
                runs.append((f"colorps --memory-limit {args.memory_limit:g}",
                             ["--memory-limit", str(args.memory_limit)]))
            for label, extra in runs:
                command = colorps + [
                    "reconstruct", "--scene", str(capture / "scene_*.exr"),
                    "--gauge", str(capture / "gauge_*.exr"), "--sphere", "auto",
                    "--mask", str(capture / "mask.png"), "--out", str(out / "result"),
                    "--overwrite", "--quiet", *extra]
                try:
                    wall, peak = measure(command, args.repeat)
                except RuntimeError as refused:
                    rows.append((f"{size * size / 1e6:.2f}", label, f"{floor_wall:.2f}",
                                 "refused", "", "", f"{input_bytes / 2**20:.0f}",
                                 str(refused)))
                    continue
                first = label == runs[0][0]  # growth compares the sizes' first runs
                growth = ("" if previous is None or not first else
                          f"{(peak - previous[1]) / (input_bytes - previous[0]):.2f}")
                rows.append((f"{size * size / 1e6:.2f}", label, f"{floor_wall:.2f}",
                             f"{wall:.2f}", f"{wall / floor_wall:.1f}",
                             f"{peak / 2**20:.0f}",
                             f"{input_bytes / 2**20:.0f}", growth))
                if first:
                    previous = (input_bytes, peak)
            print(f"{size}: done", file=sys.stderr)
    print(f"\nend to end, {os.cpu_count()} cores, 8 RGB images + 8 gauge images, best of "
          f"{args.repeat}\n")
    head = ("MP", "run", "floor s", "colorps s", "x floor", "peak MiB", "input MiB",
            "peak growth / input byte")
    print("| " + " | ".join(head) + " |")
    print("|" + "---|" * len(head))
    for row in rows:
        print("| " + " | ".join(row) + " |")


if __name__ == "__main__":
    main()
