"""The results viewer on large results: writing it, and using it in Chromium.

Run ``python benchmarks/viewer.py [--sizes 1024 2048 4096] [--chromium PATH]``.
For each size (pixels on a side) it makes a result of a sphere-and-bumps
object (smooth normals with fine texture in the albedo and noise in the
quality, like a real run's maps), writes the viewer with
:func:`colorps.viewer.write_viewer`, then opens index.html from the file in
headless Chromium (playwright) at 1280 x 800 and measures what a user waits
for:

* **write**: seconds to write index.html and viewer/, and the data's size;
* **first frame**: from navigation to the first drawn frame (coarsest level);
* **relight**: median milliseconds to draw a frame while the light is dragged
  (the page's own timing of its drawing, 1280 x 800 minus the side panel);
* **1:1**: from zooming to 1:1 until the finest level is drawn.

It prints a markdown table.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np


def fake_result(side: int, seed: int = 0):
    """A result-like object with the maps the viewer reads."""
    rng = np.random.default_rng(seed)
    y, x = (np.mgrid[0:side, 0:side] + 0.5) / side * 2 - 1
    r2 = x * x + y * y
    bumps = 0.05 * np.sin(40 * x) * np.sin(40 * y)
    n = np.dstack([x + bumps, -y + bumps, np.sqrt(np.clip(1 - r2, 0, 1))])
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    inside = r2 < 0.95
    n[~inside] = np.nan
    texture = 0.5 + 0.3 * np.sin(7 * x)[..., None] * np.array([1.0, 0.6, 0.2])
    albedo = np.where(inside[..., None], texture + 0.01 * rng.standard_normal((side, side, 3)),
                      np.nan).astype(np.float32)
    quality = np.where(inside, rng.gamma(2.0, 0.5, (side, side)), np.nan).astype(np.float32)
    height = np.where(inside, side / 2 * np.sqrt(np.clip(1 - r2, 0, 1)), np.nan)
    reason = np.where(inside, 0, 1).astype(np.uint8)
    return SimpleNamespace(normals=n.astype(np.float32), albedo=albedo, quality=quality,
                           uncertainty=quality / 10, height=height.astype(np.float32),
                           reason=reason, lights_dropped_count=np.zeros_like(reason),
                           stats=SimpleNamespace(solved=int(inside.sum()), mode="colour"))


def measure(side: int, chromium: str) -> dict:
    from playwright.sync_api import sync_playwright

    from colorps.viewer import write_viewer

    result = fake_result(side)
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        write_viewer(result, tmp)
        write_s = time.perf_counter() - t0
        data_mb = sum(p.stat().st_size for p in Path(tmp, "viewer").iterdir()) / 1e6
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            t0 = time.perf_counter()
            page.goto(Path(tmp, "index.html").as_uri())
            page.wait_for_function("colorpsViewer.state.shown >= 0", timeout=120000)
            first_s = time.perf_counter() - t0
            box = page.locator("#light").bounding_box()
            cx, cy = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
            page.mouse.move(cx, cy)
            page.mouse.down()
            times = []
            for k in range(20):
                page.mouse.move(cx + 60 * np.cos(k / 3), cy + 60 * np.sin(k / 3))
                page.evaluate("() => new Promise(r => requestAnimationFrame(() => "
                              "requestAnimationFrame(r)))")
                times.append(page.evaluate("colorpsViewer.state.renderMs"))
            relight_ms = float(np.median(times))
            page.mouse.up()
            finest = len(page.evaluate("colorpsViewer.INDEX.levels")) - 1
            t0 = time.perf_counter()
            page.click("#one")
            page.wait_for_function(f"colorpsViewer.state.shown === {finest}", timeout=120000)
            one_s = time.perf_counter() - t0
            browser.close()
    return dict(side=side, write=write_s, mb=data_mb, first=first_s, relight=relight_ms,
                one=one_s, levels=finest + 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048, 4096])
    parser.add_argument("--chromium", default=shutil.which("chromium"))
    args = parser.parse_args()
    print("| result | levels | write (s) | data (MB) | first frame (s) | relight (ms/frame) "
          "| to 1:1 (s) |")
    print("|---|---|---|---|---|---|---|")
    for side in args.sizes:
        r = measure(side, args.chromium)
        print(f"| {side} x {side} ({side * side / 1e6:.0f} MP) | {r['levels']} | "
              f"{r['write']:.2f} | {r['mb']:.0f} | {r['first']:.2f} | {r['relight']:.0f} | "
              f"{r['one']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
