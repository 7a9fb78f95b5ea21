"""The results viewer (index.html): its data against the maps, and the page in a
real browser (headless Chromium): drawn, relit as numpy relights, moved by a drag."""

import base64
import json
import os
import re
import shutil
import threading
import urllib.request

import numpy as np
import pytest

from colorps.cli import main
from colorps.codes import decode
from colorps.io import read_image, srgb_encode
from colorps.relight import relight
from colorps.viewer import pyramid_steps, serve_viewer, write_viewer


def _chromium():
    for name in (os.environ.get("COLORPS_CHROMIUM"), "chromium", "chromium-browser",
                 "google-chrome"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    from colorps.sample import sample_folder

    folder, out = sample_folder(), tmp_path_factory.mktemp("viewer") / "out"
    assert main(["reconstruct", "--scene", str(folder / "scene_*.exr"), "--gauge",
                 str(folder / "gauge_*.exr"), "--sphere", "auto", "--mask",
                 str(folder / "mask.png"), "--out", str(out), "--quiet"]) == 0
    return out


def _levels(folder):
    """The data of every level file, as the page receives them."""
    out = {}
    for path in sorted((folder / "viewer").glob("level*.js")):
        k, payload = re.fullmatch(r"colorpsLevel\((\d+), (.*)\);\n", path.read_text(),
                                  re.S).groups()
        out[int(k)] = json.loads(payload)
    return out


def _index(folder):
    text = (folder / "index.html").read_text()
    found = re.search(r'<script id="colorps-index" type="application/json">(.*?)</script>',
                      text, re.S)
    return json.loads(found.group(1).replace("<\\/", "</"))


def test_pyramid_bounds():
    for shape in [(1, 1), (300, 200), (513, 100), (4096, 4096), (5000, 300), (20000, 20000)]:
        steps = pyramid_steps(shape)
        side = max(shape)
        assert -(-side // steps[-1]) <= 2048  # the finest level fits
        assert steps[-1] == 1 or -(-side // (steps[-1] - 1)) > 2048  # and is no coarser
        assert -(-side // steps[0]) <= 512 or len(steps) == 1
        assert all(b == 2 * a for a, b in zip(steps[1:], steps))  # halving, coarsest first


def test_level_data_decode_to_the_maps(results):
    """The page's 16-bit codes (two 8-bit PNGs) hold the .exr values."""
    import tempfile

    index, levels = _index(results), _levels(results)
    report = json.loads((results / "report.json").read_text())["statistics"]
    absolute = report["residual_median"] * report["model_scale"]
    assert f"median residual {absolute:.2f} noise units" in index["title"]  # the fit as is
    normals, _ = read_image(results / "normal.exr")
    quality, _ = read_image(results / "quality.exr")
    assert len(levels) == len(index["levels"]) == 1
    hi_url, lo_url = levels[0]["normal"]
    with tempfile.TemporaryDirectory() as tmp:
        parts = []
        for k, url in enumerate((hi_url, lo_url)):
            path = f"{tmp}/{k}.png"
            with open(path, "wb") as f:
                f.write(base64.b64decode(url.split(",", 1)[1]))
            parts.append(np.rint(read_image(path, "linear")[0] * 255).astype(np.int64))
    codes = parts[0] * 256 + parts[1]
    decoded = np.stack([decode(codes[..., c], *index["ranges"]["normal"][c]) for c in range(3)],
                       axis=-1)
    solved = np.isfinite(normals).all(axis=-1)
    assert (np.isnan(decoded).any(axis=-1) == ~solved).all()
    assert np.abs(decoded[solved] - normals[solved]).max() <= 2e-5
    lo, hi = index["ranges"]["scalars"][1]
    assert lo == pytest.approx(np.nanmin(quality)) and hi == pytest.approx(np.nanmax(quality))


def test_viewer_is_served_over_http(results):
    server = serve_viewer(results)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        base = f"http://127.0.0.1:{server.server_port}"
        page = urllib.request.urlopen(f"{base}/index.html", timeout=10).read().decode()
        assert "colorps-index" in page
        level = urllib.request.urlopen(f"{base}/viewer/level0.js", timeout=10).read()
        assert level.startswith(b"colorpsLevel(0, ")
    finally:
        server.shutdown()
        server.server_close()


def test_view_refuses_a_folder_without_a_viewer(tmp_path, capsys):
    assert main(["view", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "index.html" in err and "Traceback" not in err


def test_no_viewer_option_writes_no_viewer(results, tmp_path):
    from colorps.sample import sample_folder

    folder = sample_folder()
    out = tmp_path / "o"
    assert main(["reconstruct", "--scene", str(folder / "scene_*.exr"), "--gauge",
                 str(folder / "gauge_*.exr"), "--sphere", "auto", "--out", str(out),
                 "--quiet", "--no-viewer", "--no-height"]) == 0
    assert not (out / "index.html").exists() and not (out / "viewer").exists()
    assert (out / "normal.exr").exists()


# ------------------------------------------------------------------ in Chromium
@pytest.fixture(scope="module")
def browser():
    playwright = pytest.importorskip("playwright.sync_api", reason="playwright is not "
                                     "installed (pip install -e '.[test]')")
    executable = _chromium()
    if executable is None:
        pytest.skip("no Chromium here: install Debian's chromium (apt-get install chromium) "
                    "or set COLORPS_CHROMIUM to a Chromium or Chrome executable")
    with playwright.sync_playwright() as p:
        launched = p.chromium.launch(executable_path=executable, args=["--no-sandbox"])
        yield launched
        launched.close()


def _open(browser, folder, errors, viewport=(800, 500)):
    page = browser.new_page(viewport={"width": viewport[0], "height": viewport[1]})
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.on("console", lambda m: errors.append(m.text) if m.type == "error" else None)
    page.goto((folder / "index.html").resolve().as_uri())
    page.wait_for_function("window.colorpsViewer && colorpsViewer.state.shown >= 0",
                           timeout=20000)
    return page


def _frame(page):
    """The canvas's pixels after the next frame, and the view's state."""
    page.evaluate("() => new Promise(r => requestAnimationFrame(() => requestAnimationFrame(r)))")
    frame = page.evaluate("""() => {
        const v = document.getElementById('view'), s = colorpsViewer.state;
        const d = v.getContext('2d').getImageData(0, 0, v.width, v.height).data;
        let text = '';
        for (let i = 0; i < d.length; i += 32768)
            text += String.fromCharCode.apply(null, d.subarray(i, i + 32768));
        return {w: v.width, h: v.height, data: btoa(text), zoom: s.zoom, cx: s.cx,
                cy: s.cy, light: s.light, shown: s.shown, exposure: s.exposure};
    }""")
    frame["data"] = np.frombuffer(base64.b64decode(frame["data"]), dtype=np.uint8)
    return frame


def _expected_relit(frame, normals, albedo, brdf=None):
    """What the canvas should show, from normal.exr and albedo.exr (numpy)."""
    h, w = frame["h"], frame["w"]
    canvas = frame["data"].astype(np.int64).reshape(h, w, 4)[..., :3]
    py, px = np.mgrid[0:h, 0:w]
    x = np.floor(frame["cx"] + (px + 0.5 - w / 2) / frame["zoom"]).astype(np.int64)
    y = np.floor(frame["cy"] + (py + 0.5 - h / 2) / frame["zoom"]).astype(np.int64)
    inside = (x >= 0) & (y >= 0) & (x < normals.shape[1]) & (y < normals.shape[0])
    solved = np.zeros_like(inside)
    lit = relight(normals, albedo, frame["light"], brdf=brdf) * 2.0 ** frame["exposure"]
    expected = np.rint(srgb_encode(np.clip(lit, 0, 1)) * 255)
    solved[inside] = np.isfinite(normals[y[inside], x[inside]]).all(axis=-1)
    return canvas[solved], expected[y[solved], x[solved]]


def test_page_draws_and_relights_as_numpy_does(browser, results):
    errors = []
    page = _open(browser, results, errors)
    normals, _ = read_image(results / "normal.exr")
    albedo, _ = read_image(results / "albedo.exr")
    before = _frame(page)
    shown, expected = _expected_relit(before, normals, albedo)
    assert len(shown) > 10000  # the object fills much of the canvas
    assert np.abs(shown - expected).max() <= 2  # 8-bit levels
    # Drag the light from the widget's centre to its right edge: light from +x.
    box = page.locator("#light").bounding_box()
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    page.mouse.down()
    page.mouse.move(box["x"] + box["width"] - 4, box["y"] + box["height"] / 2, steps=6)
    page.mouse.up()
    after = _frame(page)
    lx, ly, lz = after["light"]
    assert lx > 0.95 and abs(ly) < 0.05 and lz < 0.3
    shown_after, expected_after = _expected_relit(after, normals, albedo)
    assert np.abs(shown_after - expected_after).max() <= 2
    assert np.abs(shown_after.astype(float) - shown).mean() > 20  # it visibly changed
    assert errors == []
    page.close()


def test_views_keys_and_readout(browser, results):
    errors = []
    page = _open(browser, results, errors)
    normals, _ = read_image(results / "normal.exr")
    pictures = {}
    for view in ("normal", "albedo", "relief", "height", "quality", "uncertainty", "reasons",
                 "lights"):
        page.check(f"input[value={view}]")
        frame = _frame(page)
        pictures[view] = frame["data"].astype(np.int64).reshape(frame["h"], frame["w"], 4)
        key = page.inner_text("#key")
        assert key.strip(), view
    assert "noise units" in page.evaluate("() => { selectView('quality'); "
                                          "return document.getElementById('key').innerText; }")
    assert all(np.abs(pictures[a] - pictures[b]).sum() > 0
               for a, b in [("normal", "albedo"), ("quality", "uncertainty"),
                            ("relief", "height")])
    # The values under the cursor: the normal of the pixel under it.
    frame = _frame(page)
    box = page.locator("#view").bounding_box()
    px, py = frame["w"] // 2 + 7, frame["h"] // 2 - 11
    page.mouse.move(box["x"] + px, box["y"] + py)
    text = page.inner_text("#readout")
    x, y = (int(v) for v in re.search(r"pixel\s+\((\d+), (\d+)\)", text).groups())
    assert x == int(np.floor(frame["cx"] + (px - frame["w"] / 2) / frame["zoom"]))
    assert y == int(np.floor(frame["cy"] + (py - frame["h"] / 2) / frame["zoom"]))
    shown = [float(v) for v in re.search(r"normal\s+\(([^)]*)\)", text).group(1).split(",")]
    np.testing.assert_allclose(shown, normals[y, x], atol=1e-4)
    assert "solved" in text
    assert errors == []
    page.close()


def test_finer_levels_load_when_zoomed(browser, results, tmp_path):
    """A pyramid of three levels: the coarsest first, the finest once zoomed in."""
    folder = tmp_path / "pyramid"
    shutil.copytree(results, folder)
    write_viewer(_loaded_result(results), folder, max_side=256, min_side=16)
    steps = [level["step"] for level in _index(folder)["levels"]]
    assert steps == [16, 8, 4, 2, 1]
    errors = []
    # The 256 px result fitted into a 64 px canvas: every 4th pixel is enough.
    page = _open(browser, folder, errors, viewport=(300 + 64, 64))
    assert _frame(page)["shown"] == 2
    assert page.evaluate("colorpsViewer.state.loading.length") == 3  # 3 and 4 not loaded
    box = page.locator("#view").bounding_box()
    page.mouse.move(box["x"] + 32, box["y"] + 32)
    page.mouse.wheel(0, -800)  # zoom x exp(800 / 500): past 1:1
    page.wait_for_function("colorpsViewer.state.shown === 4", timeout=20000)
    assert errors == []
    page.close()


def _loaded_result(folder):
    """A Reconstruction-like object from a results folder's maps (what the viewer reads)."""
    from types import SimpleNamespace

    read = {name: read_image(folder / f"{name}.exr")[0] for name in
            ("normal", "albedo", "quality", "uncertainty", "height")}
    reason = np.where(np.isfinite(read["normal"]).all(axis=-1), 0, 1).astype(np.uint8)
    return SimpleNamespace(
        normals=read["normal"], albedo=read["albedo"], quality=read["quality"][..., 0],
        uncertainty=read["uncertainty"][..., 0], height=read["height"][..., 0],
        reason=reason, lights_dropped_count=np.zeros(reason.shape, np.uint8),
        stats=SimpleNamespace(solved=int((reason == 0).sum()), mode="colour"))


def test_page_relights_with_the_fitted_finish(browser, results, tmp_path):
    """With a fitted finish the page relights as colorps.relight does with it, and
    the checkbox turns it off again."""
    from colorps.brdf import BRDF

    finish = BRDF((1.0, 0.9, 0.9, 0.95, 1.0, 1.0, 1.0, 1.0), (0.3,), 0.2, roughness=0.3)
    folder = tmp_path / "glossy"
    shutil.copytree(results, folder)
    write_viewer(_loaded_result(results), folder, finish=finish.as_dict())
    errors = []
    page = _open(browser, folder, errors)
    normals, _ = read_image(results / "normal.exr")
    albedo, _ = read_image(results / "albedo.exr")
    assert page.is_visible("#finish")
    frame = _frame(page)
    shown, expected = _expected_relit(frame, normals, albedo, finish)
    assert np.abs(shown - expected).max() <= 2
    page.uncheck("#finish")
    frame = _frame(page)
    shown, expected = _expected_relit(frame, normals, albedo)
    assert np.abs(shown - expected).max() <= 2
    assert errors == []
    page.close()


def test_serving_on_a_bad_or_busy_port_is_one_line(results, capsys):
    import socket

    with pytest.raises(SystemExit) as exited:
        main(["view", str(results), "--serve", "--port", "99999"])
    assert exited.value.code == 2 and "0-65535" in capsys.readouterr().err
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert main(["view", str(results), "--serve", "--port", str(port)]) == 1
    err = capsys.readouterr().err
    assert f"--port {port}: cannot serve on it" in err and "Traceback" not in err
