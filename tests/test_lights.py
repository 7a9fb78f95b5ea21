"""Calibrated lights: the three file formats, bad light files, and the virtual gauge."""

import json

import numpy as np
import pytest

from colorps import Gauge, InputError, Lights, angular_error, read_lights, reconstruct, synth
from colorps import write_lights
from colorps.cli import main


@pytest.fixture
def lights():
    ring = synth.ring_lights(6, 40, np.random.default_rng(0).uniform(0.5, 1.0, (6, 3)))
    return Lights(ring.directions[:, 0], ring.colours[:, 0])


@pytest.mark.parametrize("suffix", [".txt", ".lp", ".json"])
def test_round_trips(lights, tmp_path, suffix):
    path = write_lights(lights, tmp_path / f"lights{suffix}")
    intensities = None
    if suffix != ".json":  # DiLiGenT keeps intensities in their own file
        intensities = tmp_path / "light_intensities.txt"
        intensities.write_text("".join(" ".join(f"{v:.9g}" for v in row) + "\n"
                                       for row in lights.intensities))
    back = read_lights(path, intensities, images=6)
    np.testing.assert_allclose(back.directions, lights.directions, atol=1e-8)
    np.testing.assert_allclose(back.intensities, lights.intensities, atol=1e-8)
    if suffix == ".lp":
        assert back.names == tuple(f"image_{k:03d}" for k in range(6))


@pytest.mark.parametrize("content, message", [
    ("0 0 1\n0 0 1\n", "lists 2 lights but there are 3 images"),
    ("0 0 1\nnan 0 1\n0 0 1\n", "light 2 is not a finite direction"),
    ("0 0 1\n0 0 0\n0 0 1\n", "light 2 has length 0"),
    ("0 0 1\n0 0.6 -0.8\n0 0 1\n", "light 2 points below the horizon"),
    ("0 0 1\n0 0 2\n0 0 1\n", "not a unit direction"),
    ("0 0 1\n0 0\n0 0 1\n", "line 2 has 2 values"),
    ("0 0 1\nx y z\n0 0 1\n", "line 2 is not 3 numbers"),
])
def test_bad_light_files_name_the_file_and_the_light(tmp_path, content, message):
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(InputError, match=message) as info:
        read_lights(path, images=3)
    assert str(path) in str(info.value)


def test_bad_lp_and_json(tmp_path):
    lp = tmp_path / "bad.lp"
    lp.write_text("3\na.png 0 0 1\nb.png 0 0 1\n")
    with pytest.raises(InputError, match="says 3 lights but lists 2"):
        read_lights(lp)
    doc = tmp_path / "bad.json"
    doc.write_text(json.dumps({"directions": [[0, 0, 1]], "intensities": [[1, 1], [1, 1]]}))
    with pytest.raises(InputError, match="intensities"):
        read_lights(doc)
    with pytest.raises(InputError, match="light files are"):
        read_lights(tmp_path / "lights.csv")


def test_virtual_gauge_gives_the_normals_of_a_rendered_one(lights):
    gauge = Gauge.virtual(lights, radius=80, bands=3)
    ball = synth.sphere_surface(gauge.mask.shape, 80)
    physical = synth.render(ball, lights.as_lighting(3))
    scene = synth.smiley_surface(100)
    stack = synth.render(scene, lights.as_lighting(3), noise=0.002)
    virtual = reconstruct(stack, gauge.stack, gauge, mask=scene.mask)
    rendered = reconstruct(stack, physical, gauge, mask=scene.mask)
    np.testing.assert_array_equal(virtual.normals, rendered.normals)
    err = angular_error(virtual.normals[virtual.solved], scene.normals[virtual.solved])
    assert virtual.solved[scene.mask].all() and np.median(err) < 0.3


def test_cli_with_a_light_file(tmp_path, capsys):
    data = tmp_path / "capture"
    info = synth.write_synthetic(data, size=64, images=6, theta=40, noise=0.002)
    lights = Lights(np.array(info["light_directions"])[:, 0],
                    np.array(info["light_colours"])[:, 0])
    write_lights(lights, data / "lights.txt")
    out = tmp_path / "out"
    assert main(["reconstruct", "--scene", str(data / "scene_*.exr"), "--lights",
                 str(data / "lights.txt"), "--mask", str(data / "mask.png"), "--out",
                 str(out), "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["virtual_gauge"] and report["statistics"]["solved"] > 0
    assert abs(report["statistics"]["noise"]["read"] - 0.002) < 0.001  # from the scene
    # The synthetic scene is matte: the fitted finish must come out close to Lambert.
    assert len(report["brdf_fits"]) == 2
    assert max(report["brdf"]["specular"]) < 0.01
    assert np.allclose(report["brdf"]["falloff"][2:], 1.0, atol=0.05)
    assert main(["reconstruct", "--scene", str(data / "scene_*.exr"), "--lights",
                 str(data / "lights.txt"), "--tile", "16", "--read-noise", "0.002",
                 "--gain", "0", "--out", str(tmp_path / "tiled")]) == 1
    assert "needs --brdf lambert" in capsys.readouterr().err
    assert main(["reconstruct", "--scene", str(data / "scene_*.exr"), "--lights",
                 str(data / "lights.txt"), "--tile", "16", "--read-noise", "0.002",
                 "--gain", "0", "--brdf", "lambert", "--mask", str(data / "mask.png"),
                 "--out", str(tmp_path / "tiled"), "--quiet"]) == 0
    tiled = json.loads((tmp_path / "tiled" / "report.json").read_text())
    assert tiled["brdf"]["specular"] == [0.0] and tiled["brdf_fits"] is None
    with pytest.raises(SystemExit) as stop:
        main(["reconstruct", "--scene", str(data / "scene_*.exr"), "--lights",
              str(data / "lights.txt"), "--sphere", "auto", "--out", str(tmp_path / "o2")])
    assert stop.value.code == 2 and "replaces --gauge" in capsys.readouterr().err
    (data / "short.txt").write_text("0 0 1\n0.6 0 0.8\n0 0.6 0.8\n")
    assert main(["reconstruct", "--scene", str(data / "scene_*.exr"), "--lights",
                 str(data / "short.txt"), "--out", str(tmp_path / "o3")]) == 1
    assert "lists 3 lights but there are 6 images" in capsys.readouterr().err
    assert not (tmp_path / "o3").exists()


def test_light_files_as_users_have_them(tmp_path):
    """An RTI .lp written on Windows (backslash paths with spaces, decimal commas,
    CRLF, a byte-order mark), one with 'x,y,z' joined, and a .txt that starts
    with the count: all read to the same lights, names kept without folders."""
    directions = np.array([[0.5, 0.0, np.sqrt(0.75)], [0.0, -0.6, 0.8], [-0.28, 0.0, 0.96]])
    windows = tmp_path / "dome.lp"
    lines = ["3"] + [f"C:\\Users\\Ann Lee\\RTI shots\\img {k:02d}.jpg " +
                     " ".join(f"{v:.6f}".replace(".", ",") for v in d)
                     for k, d in enumerate(directions, start=1)]
    windows.write_bytes(("\ufeff" + "\r\n".join(lines) + "\r\n").encode("utf-8"))
    joined = tmp_path / "joined.lp"
    joined.write_text("3\n" + "\n".join(f"/data/shot_{k}.tif " + ",".join(f"{v:.6f}" for v in d)
                                        for k, d in enumerate(directions)) + "\n")
    counted = tmp_path / "lights.txt"
    counted.write_text("3\n" + "\n".join(" ".join(f"{v:.6f}" for v in d)
                                         for d in directions) + "\n")
    for path in (windows, joined, counted):
        lights = read_lights(path, images=3)
        np.testing.assert_allclose(lights.directions, directions, atol=1e-5)
    assert read_lights(windows).names == ("img 01.jpg", "img 02.jpg", "img 03.jpg")
    assert read_lights(joined).names == ("shot_0.tif", "shot_1.tif", "shot_2.tif")


def test_bad_light_files_name_the_file_at_fault(tmp_path):
    good = tmp_path / "lights.txt"
    good.write_text("0 0 1\n0.6 0 0.8\n0 0.6 0.8\n")
    bad_intensities = tmp_path / "intensities.txt"
    bad_intensities.write_text("1 1 1\n1 -2 1\n1 1 1\n")
    with pytest.raises(InputError, match="^.*intensities.txt: .*> 0"):
        read_lights(good, bad_intensities)
    broken = tmp_path / "broken.lp"
    broken.write_text("2\nimg1.png 0 0 1\nimg2.png 0 zero 1\n")
    with pytest.raises(InputError, match="broken.lp: line 3 is not 'filename x y z'"):
        read_lights(broken)
    wrong_count = tmp_path / "count.txt"
    wrong_count.write_text("5\n0 0 1\n0.6 0 0.8\n0 0.6 0.8\n")
    with pytest.raises(InputError, match="count.txt: line 1"):
        read_lights(wrong_count)


@pytest.mark.parametrize("lattice", [250_000, 2_000])
def test_the_curl_of_a_surfaces_normals_tells_a_light_files_axes(monkeypatch, lattice):
    """A sphere's normals have (next to) no curl; mirrored, swapped in x and y or
    turned a quarter turn at the same pixels they have a large one, and each
    mistake is named; the truth, half a turn, a surface that bends along one
    axis only, noise and a handful of pixels are not flagged."""
    from colorps.errors import LightAxesWarning
    from colorps import light_axes
    from colorps.light_axes import MISTAKES, check_axes, curl_medians

    monkeypatch.setattr(light_axes, "CURL_PIXELS", lattice)  # every pixel; every 2nd
    ball = synth.sphere_surface(101, 45)
    normals = np.where(ball.mask[..., None], ball.normals, np.nan)
    medians, pixels = curl_medians(normals, ball.mask)
    assert pixels > (5000 if lattice > 10_000 else 1000)
    assert all(medians["as given"] < 0.3 * medians[name] for name in MISTAKES)
    assert check_axes(normals, ball.mask, "lights.txt")["looks"] is None
    for name, (undo, _) in MISTAKES.items():
        made = normals.copy()  # the mistake: the inverse of its undoing
        made[..., :2] = normals[..., :2] @ np.linalg.inv(np.array(undo, float)).T
        for turn in (1.0, -1.0):  # and half a turn more: the same verdict
            with pytest.warns(LightAxesWarning, match="lights.txt: "):
                record = check_axes(made * [turn, turn, 1.0], ball.mask, "lights.txt")
            assert record["looks"] == name
    both = normals * np.array([-1.0, -1.0, 1.0])  # half a turn: inside out, integrable
    assert check_axes(both, ball.mask, "lights.txt")["looks"] is None
    # A cylinder along y bends in x only: as given, it has no curl either.
    x = np.linspace(-0.9, 0.9, 80)
    tube = np.zeros((60, 80, 3))
    tube[..., 0], tube[..., 2] = x, np.sqrt(1 - x ** 2)
    record = check_axes(tube * [1, -1, 1], np.ones((60, 80), bool), "lights.txt")
    assert record["looks"] is None and record["pixels"] > 4000 * lattice / 250_000
    rng = np.random.default_rng(0)
    noise = rng.normal(size=(80, 80, 3)) * [0.2, 0.2, 0] + [0, 0, 1]
    noise /= np.linalg.norm(noise, axis=-1, keepdims=True)
    assert check_axes(noise, np.ones((80, 80), bool), "lights.txt")["looks"] is None
    few = np.zeros_like(ball.mask)
    few[45:55, 30:40] = True
    record = check_axes(normals * [1, -1, 1], few & ball.mask, "l.txt")
    assert record["pixels"] < 500 and record["looks"] is None


def test_a_light_file_with_y_down_is_said_to_look_mirrored(tmp_path, capsys):
    """Through the command line: the same capture with its light file's y values
    negated (image rows for y) solves, says the lights look mirrored and records
    it; the true file does not."""
    data = tmp_path / "capture"
    info = synth.write_synthetic(data, size=64, images=8, theta=40, noise=0.002)
    directions = np.array(info["light_directions"])[:, 0]
    colours = np.array(info["light_colours"])[:, 0]
    write_lights(Lights(directions, colours), data / "lights.txt")
    write_lights(Lights(directions * [1, -1, 1], colours), data / "y_down.txt")
    said = {}
    for name in ("lights.txt", "y_down.txt"):
        out = tmp_path / name
        assert main(["reconstruct", "--scene", str(data / "scene_*.exr"), "--lights",
                     str(data / name), "--mask", str(data / "mask.png"), "--out", str(out),
                     "--quiet", "--no-height", "--no-viewer"]) == 0
        said[name] = ("one axis looks mirrored" in capsys.readouterr().err,
                      json.loads((out / "report.json").read_text())["lights_check"]["axes"])
    assert said["lights.txt"][0] is False and said["lights.txt"][1]["looks"] is None
    assert said["y_down.txt"][0] is True and said["y_down.txt"][1]["looks"] == "mirrored"
