"""Light calibration from a mirror sphere, against the lights it was rendered with."""

import subprocess
import sys

import numpy as np
import pytest

from colorps import read_lights, synth
from colorps.calibrate import calibrate_lights, find_highlight
from colorps.errors import InputError
from colorps.io import write_image
from colorps.shapes import render_mirror_sphere

SPHERE = (120.0, 118.0, 100.0)


def mirror_ball(lights, **render):
    ball = synth.sphere_surface((240, 241), SPHERE[2], centre=SPHERE[:2])
    return render_mirror_sphere(ball, lights, **render)


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
    with pytest.raises(InputError, match="no highlight.*pass --matte"):  # shading only
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


def _with_window(image, at=(60, 150), half=7, level=3.0):
    """A bright square reflection (a window) on the sphere, brighter than the light."""
    out = image.copy()
    y, x = at
    out[y - half:y + half, x - half:x + half] = level
    return out


def test_a_brighter_window_beside_the_highlight_is_not_taken_for_the_light():
    from colorps.calibrate import AmbiguousHighlightWarning

    lights = synth.ring_lights(6, 45)
    stack = mirror_ball(lights, noise=0.002, seed=2)
    stack[2] = _with_window(stack[2])
    with pytest.warns(AmbiguousHighlightWarning, match=r"image 2: 2 bright blobs"):
        found_lights, found = calibrate_lights(stack, SPHERE)
    error = degrees(found_lights.directions, lights.directions[:, 0])
    assert error.max() < 0.6  # the window (brighter, larger) was not taken
    assert found[2].rival > 1.0  # and the light's blob is not the brightest
    assert all(f.rival == 0.0 for k, f in enumerate(found) if k != 2)


def test_a_reflection_of_the_highlights_size_but_not_its_shape_is_not_taken():
    """A bright bar (a window frame, a strip light's housing) of as many pixels as
    the highlights: told apart by its shape. Highlights near the rim are
    elongated by the foreshortening, which the comparison undoes."""
    from colorps.calibrate import AmbiguousHighlightWarning, find_highlight

    lights = synth.ring_lights(6, 70)  # highlights far out, foreshortened
    stack = mirror_ball(lights, spread_deg=2.0, noise=0.002, seed=3)
    clean = [find_highlight(image, SPHERE) for image in stack]
    assert max(f.elongation for f in clean) < 1.6  # round once unforeshortened
    size = int(np.median([f.pixels for f in clean]))
    bar = stack[4].copy()
    bar[112:114, 115:115 + size // 2] = 2.0  # as many pixels, brighter than the light
    stack[4] = bar
    with pytest.warns(AmbiguousHighlightWarning, match="image 4: 2 bright blobs"):
        found_lights, found = calibrate_lights(stack, SPHERE)
    assert degrees(found_lights.directions, lights.directions[:, 0]).max() < 0.6
    assert found[4].rival > 1.0 and found[4].elongation < 1.6


def test_only_ambiguous_images_are_refused():
    lights = synth.ring_lights(3, 45)
    stack = np.stack([_with_window(image) for image in mirror_ball(lights, noise=0.002)])
    with pytest.raises(InputError, match="bright blobs on the mirror sphere"):
        calibrate_lights(stack, SPHERE)


def test_a_dark_sphere_is_found_from_its_mask(tmp_path):
    """A chrome ball darker than its background: --sphere-mask gives its circle."""
    from colorps.calibrate import sphere_from_mask

    y, x = np.mgrid[0:240, 0:241]
    disk = np.hypot(x - SPHERE[0], y - SPHERE[1]) <= SPHERE[2]
    cx, cy, r = sphere_from_mask(disk)
    assert abs(cx - SPHERE[0]) < 0.1 and abs(cy - SPHERE[1]) < 0.1 and abs(r - SPHERE[2]) < 0.5
    lights = synth.ring_lights(4, 40)
    for k, image in enumerate(mirror_ball(lights, noise=0.002)):
        dark = np.where(disk[..., None], 0.05 * image / image.max() + 0.02, 0.4)
        dark[disk] += np.where(image[disk] > 0.5 * image.max(), 0.9, 0.0)
        write_image(tmp_path / f"dark_{k}.exr", dark)
    write_image(tmp_path / "ball_mask.png", disk.astype(np.float32), dtype="uint8")
    out = tmp_path / "lights.txt"
    done = subprocess.run([sys.executable, "-m", "colorps.cli", "calibrate-lights",
                           str(tmp_path / "dark_*.exr"), "--sphere-mask",
                           str(tmp_path / "ball_mask.png"), "--out", str(out)],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    error = degrees(read_lights(out).directions, lights.directions[:, 0])
    assert error.max() < 1.0
    neither = subprocess.run([sys.executable, "-m", "colorps.cli", "calibrate-lights",
                              str(tmp_path / "dark_*.exr"), "--out",
                              str(tmp_path / "other.txt")], capture_output=True, text=True)
    assert neither.returncode == 1 and "--sphere-mask" in neither.stderr
    assert "Traceback" not in neither.stderr and not (tmp_path / "other.txt").exists()


def test_a_reflection_from_behind_the_object_is_not_taken_for_the_light():
    """A lamp behind the object (105 degrees from the view) reflected brighter than
    the light, a round highlight like the others: told apart by its position,
    which would give a light that lights nothing facing the camera. Where it is
    the only highlight, the image is refused, by name."""
    from colorps.calibrate import AmbiguousHighlightWarning

    lights = synth.ring_lights(6, 45)
    lamp = synth.ring_lights(1, 105)
    stack = mirror_ball(lights, noise=0.002, seed=4)
    reflection = mirror_ball(lamp, noise=0.0)[0]
    stack[1] = stack[1] + 1.5 * reflection
    with pytest.warns(AmbiguousHighlightWarning, match="image 1: 2 bright blobs"):
        found_lights, found = calibrate_lights(stack, SPHERE)
    assert degrees(found_lights.directions, lights.directions[:, 0]).max() < 0.6
    assert found[1].rival > 1.0
    stack[1] = 1.5 * reflection + 0.002
    with pytest.raises(InputError, match=r"image 1: the highlight at .* from behind the "
                       r"object \(1[45] degrees below"):
        calibrate_lights(stack, SPHERE)
