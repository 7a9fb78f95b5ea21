"""Lights from a matte sphere (a gauge), against the rendered lights, and what they are for:
a scene whose finish differs from its gauge's, solved with a virtual gauge of its own."""

import json

import numpy as np
import pytest

from colorps import angular_error, read_lights, synth
from colorps.cli import main
from colorps.errors import InputError
from colorps.io import read_image, write_image
from colorps.matte_lights import matte_sphere_lights

CENTRE = (64.3, 70.8)  # (x, y)
RADIUS = 55


def coloured_lights(m=12):
    """Two rings of m / 2 coloured lights, 55 and 25 degrees from the view."""
    colours = np.random.default_rng(0).uniform(0.5, 1.0, (m, 3))
    low = synth.ring_lights(m // 2, 55.0, colours[:m // 2])
    high = synth.ring_lights(m - m // 2, 25.0, colours[m // 2:], azimuth0_deg=22.5)
    return synth.Lighting(np.concatenate([low.directions, high.directions]),
                          np.concatenate([low.colours, high.colours])), colours


def sphere_stack(lighting, brdf="lambert", noise=0.003):
    ball = synth.sphere_surface((130, 140), RADIUS, centre=CENTRE)
    return synth.render(ball, lighting, brdf=brdf, roughness=0.3, noise=noise, seed=1)


@pytest.mark.parametrize("eight_bit", [False, True])
def test_directions_and_intensities_of_a_lambertian_sphere(eight_bit):
    lighting, colours = coloured_lights()
    stack = sphere_stack(lighting)
    if eight_bit:  # as an 8-bit sRGB file stores it and colorps decodes it
        from colorps.io import srgb_decode, srgb_encode

        stack = srgb_decode(np.round(srgb_encode(np.clip(stack, 0, 1)) * 255) / 255)
    lights, found = matte_sphere_lights(stack, (*CENTRE, RADIUS))
    error = angular_error(lights.directions, lighting.directions[:, 0])
    assert error.max() < (0.3 if eight_bit else 0.05), error
    assert np.abs(lights.intensities / colours - 1).max() < (0.02 if eight_bit else 0.002)
    assert max(f.residual for f in found) < (0.03 if eight_bit else 0.01)


def test_a_rough_sphere_is_fitted_and_said_to_be_less_lambertian():
    """An Oren-Nayar sphere (sigma 0.3) is not Lambertian: its directions come
    out within a degree, and the residual says the fit is off by about 5 %."""
    lighting, _ = coloured_lights()
    lights, found = matte_sphere_lights(sphere_stack(lighting, "oren-nayar"),
                                        (*CENTRE, RADIUS))
    assert angular_error(lights.directions, lighting.directions[:, 0]).max() < 1.0
    assert min(f.residual for f in found) > 0.03


def test_an_unlit_image_is_refused_by_name():
    lighting, _ = coloured_lights(3)
    stack = sphere_stack(lighting)
    stack[1] = 0.0
    with pytest.raises(InputError, match="gauge_01.*only 0 lit pixels"):
        matte_sphere_lights(stack, (*CENTRE, RADIUS), names=["gauge_00", "gauge_01",
                                                              "gauge_02"])


def test_a_gauge_of_another_finish_through_its_lights(tmp_path, capsys):
    """A rough (Oren-Nayar) scene photographed with a Lambertian gauge: matched
    against the gauge the normals are degrees off; calibrate-lights --matte on
    the gauge, then --lights with the scene's own fitted finish, is as good as
    a gauge of the scene's finish."""
    lighting, colours = coloured_lights(16)
    scene = synth.smiley_surface(96)
    stack = synth.render(scene, lighting, brdf="oren-nayar", roughness=0.3, noise=0.002,
                         seed=2)
    for k, (image, ball) in enumerate(zip(stack, sphere_stack(lighting, noise=0.002))):
        write_image(tmp_path / f"scene_{k:02d}.exr", image)
        write_image(tmp_path / f"gauge_{k:02d}.exr", ball)
    write_image(tmp_path / "mask.png", scene.mask.astype(np.float32), dtype="uint8")
    common = ["reconstruct", "--scene", str(tmp_path / "scene_*.exr"), "--mask",
              str(tmp_path / "mask.png"), "--quiet", "--no-height"]

    def error(folder):
        normals = read_image(folder / "normal.exr")[0]
        return float(np.nanmean(angular_error(normals[scene.mask], scene.normals[scene.mask])))

    assert main([*common, "--gauge", str(tmp_path / "gauge_*.exr"), "--sphere", "auto",
                 "--out", str(tmp_path / "by_gauge")]) == 0
    hint = capsys.readouterr().err  # the run says which way out there is
    assert "gauge_00.exr" in hint and "--matte" in hint and "noise units" in hint
    assert main(["calibrate-lights", str(tmp_path / "gauge_*.exr"), "--sphere", "auto",
                 "--matte", "--out", str(tmp_path / "lights.txt")]) == 0
    said = capsys.readouterr().out
    assert "gauge_15.exr" in said and "lights_intensities.txt" in said
    lights = read_lights(tmp_path / "lights.txt", tmp_path / "lights_intensities.txt")
    assert angular_error(lights.directions, lighting.directions[:, 0]).max() < 0.1
    assert np.abs(lights.intensities / colours - 1).max() < 0.01
    assert main([*common, "--lights", str(tmp_path / "lights.txt"), "--light-intensities",
                 str(tmp_path / "lights_intensities.txt"),
                 "--out", str(tmp_path / "by_lights")]) == 0
    by_gauge, by_lights = error(tmp_path / "by_gauge"), error(tmp_path / "by_lights")
    assert by_lights < 0.25 * by_gauge, (by_lights, by_gauge)
    # A .json light file holds the intensities itself; nothing is written beside it.
    assert main(["calibrate-lights", str(tmp_path / "gauge_*.exr"), "--sphere", "auto",
                 "--matte", "--out", str(tmp_path / "lights.json")]) == 0
    assert len(json.loads((tmp_path / "lights.json").read_text())["intensities"][0]) == 3
    assert not (tmp_path / "lights_intensities_intensities.txt").exists()
    assert not (tmp_path / "lights.json_intensities.txt").exists()


def test_no_finish_hint_where_the_gauge_explains_the_scene(tmp_path, capsys):
    """The same capture with a Lambertian scene: no word of another finish."""
    lighting, _ = coloured_lights(16)
    scene = synth.smiley_surface(96)
    stack = synth.render(scene, lighting, noise=0.002, seed=2)
    for k, (image, ball) in enumerate(zip(stack, sphere_stack(lighting, noise=0.002))):
        write_image(tmp_path / f"scene_{k:02d}.exr", image)
        write_image(tmp_path / f"gauge_{k:02d}.exr", ball)
    assert main(["reconstruct", "--scene", str(tmp_path / "scene_*.exr"), "--gauge",
                 str(tmp_path / "gauge_*.exr"), "--sphere", "auto", "--quiet",
                 "--no-height", "--out", str(tmp_path / "out")]) == 0
    assert "--matte" not in capsys.readouterr().err
