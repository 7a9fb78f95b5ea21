"""Draw docs/images/viewer.png: the viewer on the bundled sample, relit from the
right, with the values under the cursor (needs playwright and a Chromium).

    python docs/make_viewer_picture.py [CHROMIUM]
"""

import shutil
import sys
import tempfile
from pathlib import Path

from playwright.sync_api import sync_playwright

from colorps.cli import main

HERE = Path(__file__).resolve().parent


def draw(chromium: str) -> Path:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "results"
        assert main(["demo", "--out", str(out)]) == 0
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1000, "height": 640})
            page.goto((out / "index.html").as_uri())
            page.wait_for_function("colorpsViewer.state.shown >= 0")
            box = page.locator("#light").bounding_box()
            page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
            page.mouse.down()
            page.mouse.move(box["x"] + 0.85 * box["width"], box["y"] + 0.3 * box["height"],
                            steps=5)
            page.mouse.up()
            view = page.locator("#view").bounding_box()
            page.mouse.move(view["x"] + 0.62 * view["width"], view["y"] + 0.38 * view["height"])
            page.wait_for_timeout(200)
            target = HERE / "images" / "viewer.png"
            page.screenshot(path=str(target))
            browser.close()
    return target


if __name__ == "__main__":
    print(draw(sys.argv[1] if len(sys.argv) > 1 else shutil.which("chromium")))
