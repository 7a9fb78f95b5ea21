"""The exchange files and pictures of a results folder: 16-bit normal maps in both
conventions, the height as 16-bit PNG and float TIFF, pictures with their keys."""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from colorps.cli import main
from colorps.codes import CODE_STEPS, code_range, decode, encode
from colorps.figures import QUALITY_SCALE, colour_mapped, dropped_picture
from colorps.io import read_image
from colorps.reasons import reason_picture


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    """The bundled sample reconstructed by the CLI, in both normal.png conventions."""
    from colorps.sample import sample_folder

    folder, root = sample_folder(), tmp_path_factory.mktemp("exports")
    outs = {}
    for convention in ("opengl", "directx"):
        outs[convention] = root / convention
        assert main(["reconstruct", "--scene", str(folder / "scene_*.exr"), "--gauge",
                     str(folder / "gauge_*.exr"), "--sphere", "auto", "--mask",
                     str(folder / "mask.png"), "--out", str(outs[convention]), "--quiet",
                     "--normal-convention", convention]) == 0
    return outs


def _png16(path):
    values, _ = read_image(path, "linear")
    return values.astype(np.float64)


def test_normal_png_is_16_bit_and_decodes_to_the_exr_normals(results):
    import OpenImageIO as oiio

    out = results["opengl"]
    assert oiio.ImageInput.open(str(out / "normal.png")).spec().format == oiio.UINT16
    normals, _ = read_image(out / "normal.exr")
    solved = np.isfinite(normals).all(axis=-1)
    decoded = _png16(out / "normal.png") * 2 - 1
    assert np.abs(decoded[solved] - normals[solved]).max() <= 2e-5
    assert (decoded[~solved] == -1).all()  # black where not solved
    report = json.loads((out / "report.json").read_text())
    assert report["exports"]["normal.png"]["convention"] == "opengl"


def test_directx_normal_png_flips_y_only(results):
    gl, dx = _png16(results["opengl"] / "normal.png"), _png16(results["directx"] / "normal.png")
    normals, _ = read_image(results["opengl"] / "normal.exr")
    solved = np.isfinite(normals).all(axis=-1)
    np.testing.assert_array_equal(gl[solved][:, [0, 2]], dx[solved][:, [0, 2]])
    ny = 1 - 2 * dx[..., 1]  # DirectX: G = (1 - ny) / 2
    assert np.abs(ny[solved] - normals[solved][:, 1]).max() <= 2e-5
    assert json.loads((results["directx"] / "report.json").read_text())[
        "exports"]["normal.png"]["convention"] == "directx"


def test_height_png_and_tif_hold_the_exr_heights(results):
    out = results["opengl"]
    height, _ = read_image(out / "height.exr")
    height = height[..., 0]
    tif, _ = read_image(out / "height.tif")
    np.testing.assert_array_equal(tif[..., 0], height)  # NaN where NaN, too
    scale = json.loads((out / "report.json").read_text())["exports"]["height.png"]
    assert scale["unit"] == "pixels"
    codes = np.rint(_png16(out / "height.png")[..., 0] * 65535)
    decoded = decode(codes, scale["lo"], scale["hi"])
    inside = np.isfinite(height)
    assert (np.isnan(decoded) == ~inside).all()
    step = (scale["hi"] - scale["lo"]) / CODE_STEPS
    assert np.abs(decoded[inside] - height[inside]).max() <= 0.5 * step + 1e-9
    assert scale["lo"] == pytest.approx(np.nanmin(height))
    assert scale["hi"] == pytest.approx(np.nanmax(height))


def test_key_pictures_keep_the_map_at_its_pixels(results):
    out = results["opengl"]
    quality, _ = read_image(out / "quality.exr")
    h, w = quality.shape[:2]
    picture, _ = read_image(out / "quality.png", "linear")
    assert picture.shape[0] > h and picture.shape[1] >= w  # the colour bar below
    expected = colour_mapped(quality[..., 0], QUALITY_SCALE)
    assert np.abs(picture[:h, :w] - expected).max() <= 1 / 255 + 1e-6
    strip = picture[h:]
    assert (strip > 0.99).mean() > 0.5 and (strip < 0.5).any()  # white with marks on it
    for name in ("invalid.png", "lights.png", "uncertainty.png"):
        shape = read_image(out / name, "linear")[0].shape
        assert shape[0] > h and shape[1] >= w, name


def test_invalid_and_lights_pictures_draw_the_maps():
    reason = np.array([[0, 1], [5, 6]], dtype=np.uint8)
    assert reason_picture(reason)[1, 0].tolist() == pytest.approx([1.0, 40 / 255, 40 / 255])
    count = np.array([[0, 1], [2, 7]])
    picture = dropped_picture(count)
    assert picture[0, 0].tolist() == [0, 0, 0]
    assert picture[1, 1].tolist() == pytest.approx([1.0, 40 / 255, 200 / 255])  # 7: 3 or more


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-1e4, 1e4) | st.just(float("nan")), min_size=1, max_size=50))
def test_codes_round_trip_within_half_a_step(values):
    v = np.array(values)
    lo, hi = code_range(v)
    decoded = decode(encode(v, lo, hi), lo, hi)
    assert (np.isnan(decoded) == np.isnan(v)).all()
    finite = np.isfinite(v)
    assert np.all(np.abs(decoded[finite] - v[finite]) <= (hi - lo) / (2 * CODE_STEPS) * 1.0001)


def test_relight_command_renders_lambertian_images(results, tmp_path):
    out = results["opengl"]
    lights = tmp_path / "lights.txt"
    directions = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -0.6, 0.8]])
    np.savetxt(lights, directions)
    relit = tmp_path / "relit"
    assert main(["relight", str(out), "--lights", str(lights), "--out", str(relit),
                 "--format", "exr"]) == 0
    normals, _ = read_image(out / "normal.exr")
    albedo, _ = read_image(out / "albedo.exr")
    files = sorted(relit.glob("relit_*.exr"))
    assert len(files) == 3
    for path, light in zip(files, directions):
        image, _ = read_image(path)
        expected = albedo * np.maximum(normals @ light, 0.0)[..., None]
        solved = np.isfinite(normals).all(axis=-1)
        np.testing.assert_allclose(image[solved], expected[solved], atol=2e-3, rtol=1e-3)
        assert (image[~solved] == 0).all()
    # The same again without --overwrite is refused, and the folder is untouched.
    before = {p.name: p.stat().st_mtime_ns for p in relit.iterdir()}
    assert main(["relight", str(out), "--lights", str(lights), "--out", str(relit),
                 "--format", "exr"]) != 0
    assert {p.name: p.stat().st_mtime_ns for p in relit.iterdir()} == before


def test_relight_refuses_a_folder_without_results(tmp_path, capsys):
    lights = tmp_path / "lights.txt"
    np.savetxt(lights, [[0.0, 0.0, 1.0]])
    assert main(["relight", str(tmp_path), "--lights", str(lights), "--out",
                 str(tmp_path / "r")]) != 0
    err = capsys.readouterr().err
    assert "normal.exr" in err and "Traceback" not in err
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize("white", [False, True])
def test_relight_with_the_fitted_finish(results, tmp_path, white):
    """--finish fitted shades with report.json's brdf: a diffuse falloff and a GGX
    highlight (view along +z; the renderer's coat of colorps.finishes), tinted by
    the albedo or white, as the model states it."""
    import shutil

    from colorps.brdf import BRDF, DIFFUSE_KNOTS, FRESNEL_F0
    from colorps.finishes import Gloss, gloss_shape

    folder = tmp_path / "glossy"
    shutil.copytree(results["opengl"], folder)
    report = json.loads((folder / "report.json").read_text())
    falloff = (1.0, 0.9, 0.9, 0.95, 1.0, 1.0, 1.0, 1.0)
    report["brdf"] = BRDF(falloff, (0.3,), 0.2, white_highlight=white).as_dict()
    (folder / "report.json").write_text(json.dumps(report))
    lights = tmp_path / "lights.txt"
    light = np.array([0.5, 0.3, 0.81])
    light /= np.linalg.norm(light)
    np.savetxt(lights, light[None])
    assert main(["relight", str(folder), "--lights", str(lights), "--out",
                 str(tmp_path / "r"), "--format", "exr", "--finish", "fitted"]) == 0
    image, _ = read_image(next((tmp_path / "r").glob("relit_*.exr")))
    normals, _ = read_image(folder / "normal.exr")
    albedo, _ = read_image(folder / "albedo.exr")
    solved = np.isfinite(normals).all(axis=-1)
    n = normals[solved].astype(np.float64)
    cosine = np.maximum(n @ light, 0.0)
    diffuse = cosine * np.interp(cosine, DIFFUSE_KNOTS, falloff)
    highlight = 0.3 * gloss_shape(n, light, Gloss(FRESNEL_F0, "ggx", alpha=0.2)) / FRESNEL_F0
    expected = albedo[solved] * diffuse[:, None] + \
        highlight[:, None] * (1.0 if white else albedo[solved])
    np.testing.assert_allclose(image[solved], expected, atol=2e-3, rtol=1e-3)
    # A folder whose run fitted no finish says so.
    assert main(["relight", str(results["opengl"]), "--lights", str(lights), "--out",
                 str(tmp_path / "none"), "--finish", "fitted"]) == 1
    assert not (tmp_path / "none").exists()
