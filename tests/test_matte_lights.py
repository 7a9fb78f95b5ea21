"""Lights from a matte sphere (a gauge), against the rendered lights, and what they are for:
a scene whose finish differs from its gauge's, solved with a virtual gauge of its own."""

import json

import numpy as np
import pytest

from colorps import angular_error, read_lights, synth
from colorps.brdf import DIFFUSE_KNOTS
from colorps.cli import main
from colorps.errors import InputError
from colorps.gauge_check import finish_differs
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


def sphere_stack(lighting, brdf="lambert", noise=0.003, roughness=0.3):
    ball = synth.sphere_surface((130, 140), RADIUS, centre=CENTRE)
    return synth.render(ball, lighting, brdf=brdf, roughness=roughness, noise=noise, seed=1)


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


@pytest.mark.parametrize("brdf, sigma", [("oren-nayar", 0.3), ("oren-nayar", 0.15),
                                         ("lambert", 0.0)])
def test_a_rough_sphere_is_fitted_with_its_roughness(brdf, sigma):
    """An Oren-Nayar sphere (sigma 0.3) is not Lambertian: fitted as one, its
    directions were up to 0.9 degrees off and the residual about 5 %. Fitted with
    the roughness that explains it best (one for all the images), the directions
    are within 0.05 degrees and the intensities within 0.2 %, as on a Lambertian
    sphere; a Lambertian sphere is fitted as one. A roughness between the
    grid's values (0.15) is found too: taken at the grid's 0.1, a 48-light
    sphere's directions were 0.17 degrees off."""
    lighting, colours = coloured_lights()
    stack = sphere_stack(lighting, brdf, roughness=sigma)
    lights, found = matte_sphere_lights(stack, (*CENTRE, RADIUS))
    assert angular_error(lights.directions, lighting.directions[:, 0]).max() < 0.05
    assert np.abs(lights.intensities / colours - 1).max() < 0.002
    assert len({f.roughness for f in found}) == 1
    assert abs(found[0].roughness - sigma) < 0.01
    assert max(f.residual for f in found) < 0.01


def test_a_sheen_does_not_pull_the_lights():
    """Real matte paint has a sheen. A sphere of Oren-Nayar 0.2 under a faint
    GGX coat (F0 0.04, alpha 0.25) fitted on every lit pixel had its directions
    pulled towards the highlights (0.085 degrees off on 48 lights, 0.19 at
    most) and its roughness to 0.16; the pixels about each image's halfway
    vector are left out (HIGHLIGHT_ANGLE)."""
    from colorps.finishes import Gloss

    lighting, colours = coloured_lights()
    ball = synth.sphere_surface((130, 140), RADIUS, centre=CENTRE)
    stack = synth.render(ball, lighting, brdf="oren-nayar", roughness=0.2, noise=0.003, seed=1,
                         gloss=Gloss(0.04, "ggx", alpha=0.25))
    lights, found = matte_sphere_lights(stack, (*CENTRE, RADIUS))
    assert angular_error(lights.directions, lighting.directions[:, 0]).max() < 0.05
    ratio = lights.intensities / colours  # the coat's light makes them all 0.6 % brighter
    assert np.abs(ratio / ratio.mean() - 1).max() < 0.002
    assert abs(found[0].roughness - 0.2) < 0.015


def test_an_unlit_image_is_refused_by_name():
    lighting, _ = coloured_lights(3)
    stack = sphere_stack(lighting)
    stack[1] = 0.0
    with pytest.raises(InputError, match="gauge_01.*only 0 lit pixels"):
        matte_sphere_lights(stack, (*CENTRE, RADIUS), names=["gauge_00", "gauge_01",
                                                              "gauge_02"])


def smiley_capture(folder, roughness: float, scene_noise: float = 0.002):
    """A smiley of Oren-Nayar ``roughness`` (0: Lambertian) under 16 coloured
    lights and its Lambertian gauge (noise 0.002), written to ``folder`` with the
    mask; returns the scene, the lighting and the lights' colours."""
    lighting, colours = coloured_lights(16)
    scene = synth.smiley_surface(96)
    stack = synth.render(scene, lighting, brdf="oren-nayar" if roughness else "lambert",
                         roughness=roughness, noise=scene_noise, seed=2)
    for k, (image, ball) in enumerate(zip(stack, sphere_stack(lighting, noise=0.002))):
        write_image(folder / f"scene_{k:02d}.exr", image)
        write_image(folder / f"gauge_{k:02d}.exr", ball)
    write_image(folder / "mask.png", scene.mask.astype(np.float32), dtype="uint8")
    return scene, lighting, colours


def varnished_smiley(folder, strength: float, scene_noise: float):
    """A Lambertian smiley under a white GGX coat (alpha 0.3) of Fresnel reflectance
    ``strength`` and 16 coloured lights, with its Lambertian gauge (noise 0.002),
    written to ``folder`` with the mask; returns the scene."""
    from colorps.finishes import Gloss

    lighting, _ = coloured_lights(16)
    scene = synth.smiley_surface(96)
    stack = synth.render(scene, lighting, noise=scene_noise, seed=2,
                         gloss=Gloss(strength, model="ggx", alpha=0.3))
    for k, (image, ball) in enumerate(zip(stack, sphere_stack(lighting, noise=0.002))):
        write_image(folder / f"scene_{k:02d}.exr", image)
        write_image(folder / f"gauge_{k:02d}.exr", ball)
    write_image(folder / "mask.png", scene.mask.astype(np.float32), dtype="uint8")
    return scene


@pytest.fixture(scope="module")
def rough_capture(tmp_path_factory):
    """A rough (Oren-Nayar 0.3) smiley under 16 coloured lights, photographed with a
    Lambertian gauge: a gauge of another finish than the scene's."""
    folder = tmp_path_factory.mktemp("rough")
    return folder, *smiley_capture(folder, 0.3)


def _coated_sphere(gauge, finish, lighting, colours, albedo=0.8):
    """Images of a sphere of ``finish`` seen along the axis, as a reciprocal
    renderer shades it: the falloff of the light's incidence times the same
    falloff of the view's (a coat lets light out as it lets it in)."""
    ys, xs = np.nonzero(gauge.mask)
    normals = gauge.normals[ys, xs]
    exit_share = np.interp(normals[:, 2], DIFFUSE_KNOTS, finish.falloff)
    stack = np.zeros((len(colours), *gauge.mask.shape, 3), np.float32)
    stack[:, ys, xs] = finish.shade(normals, lighting.directions[:, 0], colours,
                                    albedo=np.repeat(albedo * exit_share[:, None], 3, axis=1))
    return stack


def _error(folder, scene):
    normals = read_image(folder / "normal.exr")[0]
    return float(np.nanmean(angular_error(normals[scene.mask], scene.normals[scene.mask])))


def _reconstruct(folder, out, *extra):
    return main(["reconstruct", "--scene", str(folder / "scene_*.exr"), "--mask",
                 str(folder / "mask.png"), "--quiet", "--no-height", "--out", str(out),
                 *extra])


def test_calibrate_lights_matte_writes_the_lights(rough_capture, tmp_path, capsys):
    """calibrate-lights --matte on the gauge: the lights as rendered, for --lights
    (what the default run below does by itself)."""
    folder, _, lighting, colours = rough_capture
    assert main(["calibrate-lights", str(folder / "gauge_*.exr"), "--sphere", "auto",
                 "--matte", "--out", str(tmp_path / "lights.txt")]) == 0
    said = capsys.readouterr().out
    assert "gauge_15.exr" in said and "lights_intensities.txt" in said
    lights = read_lights(tmp_path / "lights.txt", tmp_path / "lights_intensities.txt")
    assert angular_error(lights.directions, lighting.directions[:, 0]).max() < 0.1
    assert np.abs(lights.intensities / colours - 1).max() < 0.01
    # A .json light file holds the intensities itself; nothing is written beside it.
    assert main(["calibrate-lights", str(folder / "gauge_*.exr"), "--sphere", "auto",
                 "--matte", "--out", str(tmp_path / "lights.json")]) == 0
    assert len(json.loads((tmp_path / "lights.json").read_text())["intensities"][0]) == 3
    assert sorted(p.name for p in tmp_path.glob("*intensities*")) == [
        "lights_intensities.txt"]
    # A grey sphere of known albedo: the intensities are the lights' own.
    assert main(["calibrate-lights", str(folder / "gauge_*.exr"), "--sphere", "auto",
                 "--matte", "--albedo", "0.5", "--out", str(tmp_path / "grey.json")]) == 0
    grey = read_lights(tmp_path / "grey.json")
    assert np.abs(grey.intensities / (2 * colours) - 1).max() < 0.01


def test_a_gauge_of_another_finish_is_noticed_and_solved(rough_capture, tmp_path, capsys):
    """Through the gauge alone (--no-finish-check) the normals are degrees off and
    nothing shows it but the residual; by default colorps sees the scene match its
    matte gauge at ~3 noise units, solves it again with the gauge's lights and its
    own finish, keeps that (~0.7 noise units), and says so."""
    folder, scene, _, _ = rough_capture
    gauge = ["--gauge", str(folder / "gauge_*.exr"), "--sphere", "auto"]
    assert _reconstruct(folder, tmp_path / "gauge_only", *gauge, "--no-finish-check") == 0
    assert "finish" not in capsys.readouterr().err
    assert _reconstruct(folder, tmp_path / "checked", *gauge) == 0
    said = capsys.readouterr().err
    assert "gauge_00.exr" in said and "Solved instead" in said
    record = json.loads((tmp_path / "checked" / "report.json").read_text())
    finish = record["gauge_check"]["finish"]
    assert finish["taken"] and finish["residual_with_gauge_lights"] < 1.0 < 2.0 < \
        finish["residual_with_gauge"]
    assert record["brdf"]["roughness"] == 0.3
    # Scene and gauge of one camera: the scene's own scatter is the gauge's noise.
    assert 0.8 < record["gauge_check"]["scene_noise_over_gauge"] < 1.3
    gauge_only = _error(tmp_path / "gauge_only", scene)
    checked = _error(tmp_path / "checked", scene)
    assert checked < 0.25 * gauge_only and checked < 0.3, (checked, gauge_only)


def test_a_gauge_a_little_off_the_scenes_finish_is_noticed(tmp_path, capsys):
    """A scene only a little rougher than its Lambertian gauge (Oren-Nayar 0.2):
    it matches the gauge at 1.8 noise units, and every normal is 2.4 degrees off
    through it. That is past FINISH_HINT_SCALE, the gauge's lights with the
    scene's own finish match far better, and the normals come out 0.16 off."""
    scene, _, _ = smiley_capture(tmp_path, 0.2)
    gauge = ["--gauge", str(tmp_path / "gauge_*.exr"), "--sphere", "auto"]
    assert _reconstruct(tmp_path, tmp_path / "gauge_only", *gauge, "--no-finish-check") == 0
    assert _reconstruct(tmp_path, tmp_path / "checked", *gauge) == 0
    assert "Solved instead" in capsys.readouterr().err
    finish = json.loads((tmp_path / "checked" / "report.json").read_text())["gauge_check"][
        "finish"]
    assert finish["taken"] and 1.5 < finish["residual_with_gauge"] < 2.5
    gauge_only, checked = _error(tmp_path / "gauge_only", scene), _error(tmp_path / "checked",
                                                                         scene)
    assert checked < 0.3 < 1.5 < gauge_only, (checked, gauge_only)


def test_a_thin_varnish_is_asked_for_its_finish(tmp_path, capsys):
    """A Lambertian smiley under a thin varnish (a white GGX coat of Fresnel
    reflectance 0.03) matches its matte gauge at about 1.3 noise units: under
    FINISH_HINT_SCALE, so its own finish is asked first (FINISH_ASK_SCALE). It
    shows the highlight, the gauge's lights with it match far better, and the
    normals come out 0.13 degrees off instead of 0.6."""
    from colorps.gauge_check import FINISH_ASK_SCALE, FINISH_HINT_SCALE

    scene = varnished_smiley(tmp_path, 0.03, scene_noise=0.002)
    gauge = ["--gauge", str(tmp_path / "gauge_*.exr"), "--sphere", "auto"]
    assert _reconstruct(tmp_path, tmp_path / "gauge_only", *gauge, "--no-finish-check") == 0
    scale = json.loads((tmp_path / "gauge_only" / "report.json").read_text())["statistics"][
        "model_scale"]
    assert FINISH_ASK_SCALE < scale < FINISH_HINT_SCALE
    assert _reconstruct(tmp_path, tmp_path / "checked", *gauge) == 0
    assert "Solved instead" in capsys.readouterr().err
    finish = json.loads((tmp_path / "checked" / "report.json").read_text())["gauge_check"][
        "finish"]
    assert finish["taken"] and finish["asked_first"] and finish["brdf"]["specular"][0] > 0.01
    gauge_only, checked = _error(tmp_path / "gauge_only", scene), _error(tmp_path / "checked",
                                                                         scene)
    assert checked < 0.2 < 0.4 < gauge_only, (checked, gauge_only)


def test_a_tiled_run_says_how_to_solve_another_finish(rough_capture, tmp_path, capsys):
    folder, _, _, _ = rough_capture
    assert _reconstruct(folder, tmp_path / "tiled", "--gauge", str(folder / "gauge_*.exr"),
                        "--sphere", "auto", "--tile", "32") == 0
    said = capsys.readouterr().err
    assert "does not try it itself" in said and "--matte" in said
    finish = json.loads((tmp_path / "tiled" / "report.json").read_text())["gauge_check"][
        "finish"]
    assert finish["taken"] is False and finish["residual_with_gauge_lights"] is None


def test_lights_that_cannot_be_measured_leave_the_gauges_result(rough_capture, tmp_path,
                                                                capsys, monkeypatch):
    """The way out failing (here made to) is said, and the run ends with the gauge's
    result, not an error."""
    import colorps.gauge_finish as gauge_finish

    def unmeasurable(*args, **kwargs):
        raise InputError("gauge_03.exr: only 12 lit pixels on the matte sphere")

    monkeypatch.setattr(gauge_finish, "matte_sphere_lights", unmeasurable)
    folder, _, _, _ = rough_capture
    assert _reconstruct(folder, tmp_path / "out", "--gauge", str(folder / "gauge_*.exr"),
                        "--sphere", "auto") == 0
    said = capsys.readouterr().err
    assert "could not (gauge_03.exr: only 12 lit pixels" in said and "by hand" in said
    finish = json.loads((tmp_path / "out" / "report.json").read_text())["gauge_check"][
        "finish"]
    assert finish["taken"] is False and "12 lit pixels" in finish["failed"]


def test_no_finish_hint_where_the_gauge_explains_the_scene(tmp_path, capsys):
    """The same capture with a Lambertian scene: no word of another finish, and the
    gauge's result as it is."""
    smiley_capture(tmp_path, 0.0)
    assert main(["reconstruct", "--scene", str(tmp_path / "scene_*.exr"), "--gauge",
                 str(tmp_path / "gauge_*.exr"), "--sphere", "auto", "--quiet",
                 "--no-height", "--out", str(tmp_path / "out")]) == 0
    assert "finish" not in capsys.readouterr().err
    record = json.loads((tmp_path / "out" / "report.json").read_text())
    assert "finish" not in record["gauge_check"] and record["brdf"] is None


def test_a_scene_noisier_than_its_gauge_is_not_taken_for_another_finish(tmp_path, capsys):
    """A Lambertian scene with ten times its gauge's noise (a path-traced scene's
    bounced light against a lone sphere's noise-free render) matches at about 10
    noise units: the finish check alone would blame the finish. The scene's own
    scatter explains it, and its own fitted finish (Lambertian) has no highlight
    nor roughness: said so, and the gauge's result kept."""
    scene, _, _ = smiley_capture(tmp_path, 0.0, scene_noise=0.02)
    assert _reconstruct(tmp_path, tmp_path / "out", "--gauge", str(tmp_path / "gauge_*.exr"),
                        "--sphere", "auto") == 0
    said = capsys.readouterr().err
    assert "scene_00.exr" in said and "noisier than its gauge" in said
    assert "Solved instead" not in said and "did no better" not in said
    record = json.loads((tmp_path / "out" / "report.json").read_text())
    checked = record["gauge_check"]
    assert checked["finish"]["taken"] is False and record["brdf"] is None
    assert "its own fitted finish is the matte gauge's" in said
    assert 7 < checked["scene_noise_over_gauge"] < 13
    scale = record["statistics"]["model_scale"]
    assert finish_differs(scale, {**checked, "scene_noise_over_gauge": None})  # alone: yes
    assert not finish_differs(scale, checked)



def test_a_glossy_scene_noisier_than_its_gauge_takes_its_own_finish(tmp_path, capsys):
    """The same noisy scene under a white GGX coat (as a path tracer renders a
    plastic pot against a lone sphere): the residuals cannot tell, but its own
    fitted finish has a highlight the matte gauge has not, so that solution is
    taken, and it is closer to the truth than the gauge's."""
    scene = varnished_smiley(tmp_path, 0.04, scene_noise=0.02)
    gauge = ["--gauge", str(tmp_path / "gauge_*.exr"), "--sphere", "auto"]
    assert _reconstruct(tmp_path, tmp_path / "gauge_only", *gauge, "--no-finish-check") == 0
    assert _reconstruct(tmp_path, tmp_path / "out", *gauge) == 0
    said = capsys.readouterr().err
    assert "noisier than its gauge" in said and "Solved instead" in said
    checked = json.loads((tmp_path / "out" / "report.json").read_text())["gauge_check"]
    assert checked["scene_noise_over_gauge"] > 2 and checked["finish"]["taken"]
    assert max(checked["finish"]["brdf"]["specular"]) > 0.01
    assert _error(tmp_path / "out", scene) < 0.8 * _error(tmp_path / "gauge_only", scene)

def test_a_noisy_matte_scene_on_a_coated_gauge_is_matched_without_the_coat(tmp_path):
    """The reverse: a noisy Lambertian scene against a gauge under a clear coat
    (its highlight, and the light its coat keeps from its base at grazing
    incidence). The scene's own finish has none of the gauge's: that differs,
    though its residuals cannot tell, and the solution with the gauge's lights
    and the scene's finish is taken, closer to the truth than the gauge's."""
    from colorps import Gauge
    from colorps.brdf import BRDF, DIFFUSE_KNOTS, coat_transmission
    from colorps.gauge_check import shows_finish

    lighting, colours = coloured_lights(16)
    scene = synth.smiley_surface(64)
    stack = synth.render(scene, lighting, noise=0.02, seed=2)
    coat = BRDF(falloff=tuple(coat_transmission(DIFFUSE_KNOTS, 0.2)), specular=(0.05,),
                alpha=0.2, white_highlight=True)
    assert shows_finish(BRDF.lambert(), coat) and shows_finish(coat)  # a highlight on either
    assert not shows_finish(BRDF.lambert()) and not shows_finish(BRDF(roughness=0.3),
                                                                 BRDF(roughness=0.3))
    balls = _coated_sphere(Gauge.from_sphere((130, 140), *CENTRE, RADIUS, rim_margin=0.0),
                           coat, lighting, colours)
    for k, (image, ball) in enumerate(zip(stack, balls)):
        write_image(tmp_path / f"scene_{k:02d}.exr", image)
        write_image(tmp_path / f"gauge_{k:02d}.exr", ball)
    write_image(tmp_path / "mask.png", scene.mask.astype(np.float32), dtype="uint8")
    gauge_files = ["--gauge", str(tmp_path / "gauge_*.exr"), "--sphere", "auto",
                   "--gauge-albedo", "0.8"]
    assert _reconstruct(tmp_path, tmp_path / "gauge_only", *gauge_files,
                        "--no-finish-check") == 0
    assert _reconstruct(tmp_path, tmp_path / "out", *gauge_files) == 0
    checked = json.loads((tmp_path / "out" / "report.json").read_text())["gauge_check"]
    assert checked["scene_noise_over_gauge"] > 2 and checked["finish"]["taken"]
    # 3.3 -> 1.07 degrees, as with a Lambertian gauge (1.09): the lights, which a
    # Lambertian fit to the coated sphere tilts 1.5-2.4 degrees, fitted again under
    # its finish (gauge_finish); 1.84 without.
    assert _error(tmp_path / "out", scene) < 0.4 * _error(tmp_path / "gauge_only", scene)


def test_a_coated_scene_on_a_matte_gauge_is_matched_under_its_coats_loss(tmp_path,
                                                                        monkeypatch):
    """A scene under a clear coat that lets less light into its base towards
    grazing incidence (as Mitsuba's and pbrt's plastics do), against a matte
    gauge: the falloff measured on the gauge has no such loss, and held as it
    is, it tilts the normals; the scene is matched better with that falloff
    under its fitted coat's loss (BRDF.coat_adjusted), which is taken."""
    from colorps.brdf import BRDF, DIFFUSE_KNOTS, coat_transmission

    lighting, colours = coloured_lights(16)
    scene = synth.smiley_surface(64)
    coated = BRDF(falloff=tuple(coat_transmission(DIFFUSE_KNOTS, 0.2)), specular=(0.05,),
                  alpha=0.2, white_highlight=True)
    stack = np.zeros((16, *scene.mask.shape, 3), np.float32)
    stack[:, scene.mask] = coated.shade(scene.normals[scene.mask], lighting.directions[:, 0],
                                        colours, albedo=scene.albedo[scene.mask])
    stack += np.random.default_rng(2).normal(0, 0.004, stack.shape).astype(np.float32)
    for k, (image, ball) in enumerate(zip(stack, sphere_stack(lighting, noise=0.002))):
        write_image(tmp_path / f"scene_{k:02d}.exr", np.maximum(image, 0.0))
        write_image(tmp_path / f"gauge_{k:02d}.exr", ball)
    write_image(tmp_path / "mask.png", scene.mask.astype(np.float32), dtype="uint8")
    gauge = ["--gauge", str(tmp_path / "gauge_*.exr"), "--sphere", "auto",
             "--no-interreflections"]  # (no bounced light here: its passes would cost 3 s)
    assert _reconstruct(tmp_path, tmp_path / "out", *gauge) == 0
    finish = json.loads((tmp_path / "out" / "report.json").read_text())["gauge_check"]["finish"]
    assert finish["taken"] and finish["brdf"]["falloff"][0] < 0.9  # the coat's loss
    with monkeypatch.context() as patch:  # the same run without that candidate
        patch.setattr(BRDF, "coat_adjusted", lambda self, held: None)
        assert _reconstruct(tmp_path, tmp_path / "held", *gauge) == 0
    assert _error(tmp_path / "out", scene) < 0.5 * _error(tmp_path / "held", scene)


FOCAL = 250.0  # pixels: rays up to 12 degrees off the axis on the gauge's rim


def test_a_matte_sphere_through_a_lens():
    """Through a lens the sphere's normals come from the true rays; read
    orthographically the same images give directions degrees off."""
    from colorps import Gauge
    from colorps.camera import Camera

    lighting, colours = coloured_lights()
    camera = Camera(FOCAL, FOCAL, None, None)
    gauge = Gauge.from_sphere((130, 140), *CENTRE, RADIUS, rim_margin=0.0, camera=camera)
    ball = synth.SyntheticSurface(normals=np.where(gauge.mask[..., None], gauge.normals, 0.0),
                                  mask=gauge.mask, albedo=np.ones((130, 140, 3)),
                                  height=np.zeros((130, 140)))
    stack = synth.render(ball, lighting, noise=0.003, seed=1)
    lights, _ = matte_sphere_lights(stack, (*CENTRE, RADIUS), camera=camera)
    assert angular_error(lights.directions, lighting.directions[:, 0]).max() < 0.1
    assert np.abs(lights.intensities / colours - 1).max() < 0.01
    flat, _ = matte_sphere_lights(stack, (*CENTRE, RADIUS))
    assert angular_error(flat.directions, lighting.directions[:, 0]).max() > 2.0


@pytest.fixture(scope="module")
def rough_capture_through_a_lens(tmp_path_factory):
    """The rough smiley and its Lambertian gauge photographed through a lens: the
    scene shaded for each pixel's own view (Oren-Nayar depends on it), the
    gauge's sphere seen along the true rays."""
    from colorps import BRDF, Gauge
    from colorps.camera import Camera

    folder = tmp_path_factory.mktemp("lens")
    lighting, _ = coloured_lights(16)
    camera = Camera(FOCAL, FOCAL, None, None)
    (folder / "camera.json").write_text(json.dumps(dict(fx=FOCAL, fy=FOCAL)))
    scene = synth.smiley_surface(96)
    ys, xs = np.nonzero(scene.mask)
    views = -camera.rays(xs, ys, scene.mask.shape)
    shading = BRDF(roughness=0.3).shade(scene.normals[ys, xs], lighting.directions[:, 0],
                                        lighting.colours[:, 0], views)
    noise = np.random.default_rng(3).normal(0.0, 0.002, shading.shape)
    stack = np.zeros((16, *scene.mask.shape, 3), np.float32)
    stack[:, ys, xs] = np.clip(shading * scene.albedo[ys, xs] + noise, 0, None)
    gauge = Gauge.from_sphere((130, 140), *CENTRE, RADIUS, rim_margin=0.0, camera=camera)
    ball = synth.SyntheticSurface(normals=np.where(gauge.mask[..., None], gauge.normals, 0.0),
                                  mask=gauge.mask, albedo=np.ones((130, 140, 3)),
                                  height=np.zeros((130, 140)))
    for k, (image, photo) in enumerate(zip(stack, synth.render(ball, lighting, noise=0.002,
                                                                seed=2))):
        write_image(folder / f"scene_{k:02d}.exr", image)
        write_image(folder / f"gauge_{k:02d}.exr", photo)
    write_image(folder / "mask.png", scene.mask.astype(np.float32), dtype="uint8")
    return folder, scene, lighting


def test_another_finish_through_a_lens_is_solved(rough_capture_through_a_lens, tmp_path,
                                                 capsys):
    """With --camera the way out is taken too: the gauge's lights measured along
    the true rays, the scene's finish fitted and the scene matched again along
    each pixel's ray: 0.15 degrees mean from 5.3 through the gauge."""
    folder, scene, lighting = rough_capture_through_a_lens
    gauge = ["--gauge", str(folder / "gauge_*.exr"), "--sphere", f"{CENTRE[0]},{CENTRE[1]},"
             f"{RADIUS}", "--camera", str(folder / "camera.json")]
    assert _reconstruct(folder, tmp_path / "gauge_only", *gauge, "--no-finish-check") == 0
    assert _reconstruct(folder, tmp_path / "checked", *gauge) == 0
    assert "Solved instead" in capsys.readouterr().err
    report = json.loads((tmp_path / "checked" / "report.json").read_text())
    assert report["gauge_check"]["finish"]["taken"]
    gauge_only = _error(tmp_path / "gauge_only", scene)
    checked = _error(tmp_path / "checked", scene)
    assert checked < 0.15 * gauge_only and checked < 0.6, (checked, gauge_only)
    assert report["matched_along_rays"]
    # The same lights by hand; a mirror sphere is not read through a lens.
    assert main(["calibrate-lights", str(folder / "gauge_*.exr"), "--sphere", "auto",
                 "--matte", "--camera", str(folder / "camera.json"), "--out",
                 str(tmp_path / "lights.json")]) == 0
    lights = read_lights(tmp_path / "lights.json")
    assert angular_error(lights.directions, lighting.directions[:, 0]).max() < 0.2
    assert main(["calibrate-lights", str(folder / "gauge_*.exr"), "--sphere", "auto",
                 "--camera", "300", "--out", str(tmp_path / "mirror.txt")]) == 1
    assert "for a matte sphere (--matte)" in capsys.readouterr().err


def test_the_gauges_own_finish_is_fitted_at_its_known_normals():
    """A coated gauge (a falloff darker towards grazing and a GGX lobe): its finish
    fitted at its known normals gives the falloff it was rendered with, which a
    scene's fit then holds whatever its normals (on estimated ones the falloff
    trades with their tilt), and its lights' intensities come out as rendered."""
    from colorps import BRDF, Gauge, Lights
    from colorps.brdf_fit import fit_brdf
    from colorps.gauge_finish import gauge_finish

    lighting, colours = coloured_lights(16)
    finish = BRDF(falloff=(0.6, 0.68, 0.75, 0.82, 0.9, 0.95, 0.99, 1.0), specular=(0.05,),
                  alpha=0.3)
    gauge = Gauge.from_sphere((130, 140), *CENTRE, RADIUS, rim_margin=1.0, albedo=0.8)
    stack = _coated_sphere(gauge, finish, lighting, colours)
    ys, xs = np.nonzero(gauge.mask)
    # As a matte sphere's fit leaves them: directions tilted, intensities off.
    matte, _ = matte_sphere_lights(stack, (*CENTRE, RADIUS), albedo=0.8)
    assert angular_error(matte.directions, lighting.directions[:, 0]).mean() > 0.5
    fitted, measured = gauge_finish(stack, gauge, Lights(matte.directions, colours * 1.1))
    assert angular_error(measured.directions, lighting.directions[:, 0]).max() < 0.1
    assert np.abs(np.array(fitted.falloff) - finish.falloff).max() < 0.02, fitted.falloff
    assert np.abs(measured.intensities / colours - 1).max() < 0.01
    # A Lambertian gauge's directions, which the matte fit has right, are kept.
    lambert = sphere_stack(lighting, noise=0.002)
    plain, _ = matte_sphere_lights(lambert, (*CENTRE, RADIUS))
    _, kept = gauge_finish(lambert, gauge, plain)
    assert angular_error(kept.directions, lighting.directions[:, 0]).max() < 0.05
    # A scene's fit at normals about 3 degrees off keeps the held falloff.
    rng = np.random.default_rng(5)
    some = rng.choice(len(ys), 1500, replace=False)
    tilted = gauge.normals[ys[some], xs[some]] + rng.normal(0, 0.05, (1500, 3))
    tilted /= np.linalg.norm(tilted, axis=1, keepdims=True)
    observed = stack[:, ys[some], xs[some]].astype(np.float64)
    held, _ = fit_brdf(observed, tilted, lighting.directions[:, 0], colours, observed > 0,
                       held_falloff=fitted.falloff)
    assert np.abs(np.array(held.falloff) - fitted.falloff).max() < 1e-3


def test_a_dark_background_is_said_once(tmp_path, capsys):
    """A rough scene on a black background three times its size, run without a
    mask: under half the frame is solved, and the run says so once, for the result
    it keeps, with what to do; the finish route's samples and passes, which had
    each said their own share, say nothing."""
    smiley_capture(tmp_path, 0.3)
    for path in tmp_path.glob("scene_*.exr"):
        write_image(path, np.pad(read_image(path)[0], ((0, 96), (0, 96), (0, 0))))
    assert main(["reconstruct", "--scene", str(tmp_path / "scene_*.exr"), "--gauge",
                 str(tmp_path / "gauge_*.exr"), "--sphere", "auto", "--quiet", "--no-height",
                 "--no-viewer", "--out", str(tmp_path / "out")]) == 0
    said = capsys.readouterr().err
    record = json.loads((tmp_path / "out" / "report.json").read_text())
    assert record["gauge_check"]["finish"]["taken"]  # (the route's passes ran)
    assert said.count("masked pixels were solved") == 1, said
    assert "mostly 'too dark'" in said and "left out by a mask" in said
    assert record["statistics"]["warnings"] == [
        line.removeprefix("colorps: warning: ") for line in said.splitlines()
        if "masked pixels were solved" in line]
