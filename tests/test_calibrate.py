"""Light calibration from a mirror sphere, against the lights it was rendered with."""

import subprocess
import sys

import numpy as np
import pytest

from colorps import read_lights, synth
from colorps.calibrate import calibrate_lights, find_highlight
from colorps.errors import InputError
from colorps.io import write_image

SPHERE = (120.0, 118.0, 100.0)


def mirror_ball(lights, **render):
    ball = synth.sphere_surface((240, 241), SPHERE[2], centre=SPHERE[:2])
    return synth.render_mirror_sphere(ball, lights, **render)


def degrees(a, b):
    return np.degrees(np.arccos(np.clip((a * b).sum(axis=-1), -1.0, 1.0)))


@pytest.mark.parametrize("theta", [25, 50, 70])
def test_directions_agree_with_the_rendered_lights(theta):
    lights = synth.ring_lights(8, theta)
    # Overexposed (flat-topped, clipped highlights) and noisy, like a real photo.
    stack = np.minimum(mirror_ball(lights, peak=4.0, noise=0.005, seed=theta), 1.0)
    found_lights, found = calibrate_lights(stack, SPHERE, clip_level=1.0)
    error = degrees(found_lights.directions, lights.directions[:, 0])
    assert error.mean() < 0.3 and error.max() < 0.6
    assert all(f.clipped > 0 for f in found)  # reported as clipped
    assert all(0.5 < f.degrees_per_pixel < 5 for f in found)


def test_an_image_without_highlight_or_of_a_matte_sphere_is_refused():
    lights = synth.ring_lights(2, 45)
    dark = mirror_ball(lights, peak=0.0, noise=0.002)[0]
    with pytest.raises(InputError, match="no highlight"):
        find_highlight(dark, SPHERE, name="dark.exr")
    ball = synth.sphere_surface((240, 241), SPHERE[2], centre=SPHERE[:2])
    matte = synth.render(ball, lights)[0] + 0.01
    with pytest.raises(InputError, match="no highlight"):  # shading, not a highlight
        find_highlight(matte, SPHERE)
    area_light = mirror_ball(lights, spread_deg=30.0)[0]
    with pytest.raises(InputError, match="covers"):
        find_highlight(area_light, SPHERE)


@pytest.mark.parametrize("suffix", [".txt", ".lp", ".json"])
def test_cli_writes_a_light_file_that_reads_back(tmp_path, suffix):
    lights = synth.ring_lights(6, 40)
    for k, image in enumerate(mirror_ball(lights, noise=0.002)):
        write_image(tmp_path / f"chrome_{k:02d}.exr", image)
    out = tmp_path / f"lights{suffix}"
    done = subprocess.run([sys.executable, "-m", "colorps.cli", "calibrate-lights",
                           str(tmp_path / "chrome_*.exr"), "--sphere", "120,118,100",
                           "--out", str(out)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "chrome_05.exr" in done.stdout
    back = read_lights(out, images=6)
    assert degrees(back.directions, lights.directions[:, 0]).max() < 0.5
    if suffix == ".lp":
        assert back.names[0] == "chrome_00.exr"


def test_cli_refuses_without_writing(tmp_path):
    lights = synth.ring_lights(2, 45)
    stack = mirror_ball(lights)
    stack[1] = mirror_ball(lights, peak=0.0)[1]  # the second image shows no light
    for k, image in enumerate(stack):
        write_image(tmp_path / f"chrome_{k}.exr", image)
    out = tmp_path / "lights.txt"
    done = subprocess.run([sys.executable, "-m", "colorps.cli", "calibrate-lights",
                           str(tmp_path / "chrome_*.exr"), "--sphere", "120,118,100",
                           "--out", str(out)], capture_output=True, text=True)
    assert done.returncode != 0
    assert "chrome_1.exr" in done.stderr and "no highlight" in done.stderr
    assert not out.exists()
