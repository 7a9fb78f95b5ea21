"""Lights paired with the wrong images: caught, re-paired by name, or refused."""

import json

import numpy as np
import pytest

from colorps import Lights, synth, write_lights
from colorps.cli import main
from colorps.io import read_image


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A 12-image capture whose files sort differently as text and naturally."""
    folder = tmp_path_factory.mktemp("pairing")
    info = synth.write_synthetic(folder, size=40, images=12, theta=40, noise=0.002)
    for k in range(12):  # img1 ... img12: text order img1, img10, img11, img12, img2, ...
        (folder / f"scene_{k:02d}.exr").rename(folder / f"img{k + 1}.exr")
    directions = np.array(info["light_directions"])[:, 0, :]
    return folder, Lights(directions)


def run(capture, out, lights, scene, *extra):
    folder, _ = capture
    scene = scene if isinstance(scene, list) else [scene]
    return main(["reconstruct", "--scene", *scene, "--lights", str(lights),
                 "--mask", str(folder / "mask.png"), "--out", str(out), "--quiet",
                 "--no-height", "--brdf", "lambert", *extra])


def test_explicit_paths_out_of_natural_order_are_warned_about(capture, tmp_path, capsys):
    """An unquoted glob hands the images over sorted as text: a warning names the
    first one out of order, and report.json shows the pairing used."""
    folder, lights = capture
    write_lights(lights, tmp_path / "lights.txt")
    as_text = sorted(str(p) for p in folder.glob("img*.exr"))  # img1, img10, img11, ...
    assert run(capture, tmp_path / "out", tmp_path / "lights.txt", as_text) == 0
    err = capsys.readouterr().err
    assert "out of natural order (img10.exr is image 2, before img2.exr)" in err
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert [row["scene"] for row in report["pairing"]] == as_text
    # A quoted glob is sorted naturally by colorps: no warning.
    assert run(capture, tmp_path / "quoted", tmp_path / "lights.txt",
               str(folder / "img*.exr")) == 0
    assert "natural order" not in capsys.readouterr().err


def test_lp_names_re_pair_the_lights(capture, tmp_path, capsys):
    """An .lp file listing the images in text order is re-paired by name: the same
    normals as a file in the images' order (and a warning saying so)."""
    folder, lights = capture
    names = [f"img{k + 1}.jpg" for k in range(12)]  # a converted capture: other extension
    write_lights(lights, tmp_path / "ordered.lp", names=names)
    order = sorted(range(12), key=lambda k: names[k])  # as text: img1, img10, ...
    shuffled = Lights(lights.directions[order])
    write_lights(shuffled, tmp_path / "shuffled.lp", names=[names[k] for k in order])
    glob = str(folder / "img*.exr")
    assert run(capture, tmp_path / "a", tmp_path / "ordered.lp", glob) == 0
    assert "re-paired" not in capsys.readouterr().err
    assert run(capture, tmp_path / "b", tmp_path / "shuffled.lp", glob) == 0
    assert "re-paired by name" in capsys.readouterr().err
    a = read_image(tmp_path / "a" / "normal.exr")[0]
    b = read_image(tmp_path / "b" / "normal.exr")[0]
    assert np.array_equal(a, b, equal_nan=True)
    report = json.loads((tmp_path / "b" / "report.json").read_text())
    assert [row["light_name"] for row in report["pairing"]] == names


def test_lp_names_that_disagree_with_the_scene_are_refused(capture, tmp_path, capsys):
    folder, lights = capture
    names = [f"img{k + 1}.jpg" for k in range(12)]
    names[3] = "other_capture_7.jpg"
    write_lights(lights, tmp_path / "mixed.lp", names=names)
    out = tmp_path / "out"
    assert run(capture, out, tmp_path / "mixed.lp", str(folder / "img*.exr")) == 1
    err = capsys.readouterr().err
    assert "mixed.lp: its image names and the scene files disagree" in err
    assert "other_capture_7.jpg" in err and "img4.exr" in err
    assert not out.exists()


def test_lp_names_unrelated_to_the_files_pair_in_order_with_a_warning(capture, tmp_path,
                                                                      capsys):
    folder, lights = capture
    write_lights(lights, tmp_path / "renamed.lp", names=[f"DSC_{k:04d}.NEF" for k in range(12)])
    assert run(capture, tmp_path / "out", tmp_path / "renamed.lp",
               str(folder / "img*.exr")) == 0
    assert "match none of the scene files" in capsys.readouterr().err


def test_intensities_of_the_wrong_band_count_name_their_file(capture, tmp_path, capsys):
    folder, lights = capture
    write_lights(lights, tmp_path / "lights.txt")
    (tmp_path / "intensities.txt").write_text("1 1\n" * 12)
    out = tmp_path / "out"
    assert run(capture, out, tmp_path / "lights.txt", str(folder / "img*.exr"),
               "--light-intensities", str(tmp_path / "intensities.txt")) == 1
    err = capsys.readouterr().err
    assert "intensities.txt: the intensities have 2 values per light" in err
    assert "3 channel(s)" in err and not out.exists()


def test_shading_subspaces_tell_images_and_lights_out_of_step():
    """A scene and a gauge under the same 8 lights span the same shading subspace,
    as do the lights themselves; the gauge's images or the lights out of step
    (two swapped, all shuffled) are seen and said; 3 images, or no pixel lit in
    every image, give no verdict."""
    from colorps.errors import PairingWarning
    from colorps.pairing import (
        MAX_PAIRING_ANGLE,
        check_shading_pairing,
        light_subspaces,
        shading_subspaces,
    )
    from colorps.shapes import dome_lights

    lighting = dome_lights(8, 40.0)
    lights = Lights(lighting.directions[:, 0], lighting.colours[:, 0])
    scene = synth.smiley_surface(64)
    stack = synth.render(scene, lighting)
    ball = synth.sphere_surface(81, 38)
    gauge = synth.render(ball, lighting)
    reference, pixels = shading_subspaces(gauge, ball.mask)
    assert pixels > 1000 and len(reference) == 3
    for theirs, what in ((reference, "the gauge"), (light_subspaces(lights, 3), "lights")):
        record = check_shading_pairing(stack, scene.mask, theirs, "g.exr", what)
        assert max(record["angle_deg"]) < 1.0 and not record["looks_out_of_step"]
    rng = np.random.default_rng(1)
    for order in ([1, 0, 2, 3, 4, 5, 6, 7], rng.permutation(8)):
        for theirs in (shading_subspaces(gauge[order], ball.mask)[0],
                       light_subspaces(Lights(lights.directions[order],
                                              lights.intensities[order]), 3)):
            with pytest.warns(PairingWarning, match="g.exr: the scene's images do not look"):
                record = check_shading_pairing(stack, scene.mask, theirs, "g.exr", "it")
            assert min(record["angle_deg"]) > MAX_PAIRING_ANGLE and record["looks_out_of_step"]
    assert "skipped" in check_shading_pairing(stack[:3], scene.mask, reference[:3], "g", "it")
    dark = stack.copy()
    dark[0] = 0.0  # no pixel lit in every image
    assert "skipped" in check_shading_pairing(dark, scene.mask, reference, "g", "it")


def test_gauge_images_out_of_step_are_said_not_fitted_as_a_finish(tmp_path, capsys):
    """Through the command line: the bundled sample with two gauge images swapped
    solves, says the images look out of step with the gauge's, records it, and
    does not take the misfit for another finish."""
    import shutil

    from colorps.sample import sample_folder

    folder = sample_folder()
    for k, source in enumerate([1, 0, 2, 3, 4, 5, 6, 7]):
        shutil.copy(folder / f"gauge_{source:02d}.exr", tmp_path / f"gauge_{k:02d}.exr")
    out = tmp_path / "out"
    assert main(["reconstruct", "--scene", str(folder / "scene_*.exr"), "--gauge",
                 str(tmp_path / "gauge_*.exr"), "--sphere", "auto", "--mask",
                 str(folder / "mask.png"), "--out", str(out), "--quiet", "--no-height",
                 "--no-viewer"]) == 0
    err = capsys.readouterr().err
    assert "gauge_00.exr: the scene's images do not look lit by the gauge" in err
    check = json.loads((out / "report.json").read_text())["gauge_check"]
    assert check["pairing"]["looks_out_of_step"] and "finish" not in check
