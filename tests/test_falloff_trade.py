"""A fitted falloff's trade with the normals' tilt, in their uncertainty."""

import json

import numpy as np

from colorps import Gauge, angular_error, reconstruct
from colorps.brdf import BRDF
from colorps.falloff_trade import falloff_trade
from colorps.geometry import at_nearest_normal
from colorps.io import read_image, write_image
from colorps.lights import Lights, write_lights
from colorps.shapes import dome_lights

#: A falloff brighter towards grazing, as a fit that traded it for the normals'
#: tilt gives (a glossy sphere path-traced by Mitsuba 3 fitted 1.27 at grazing).
RISING = (1.3, 0.95, 0.9, 0.9, 0.93, 0.96, 0.99, 1.0)


def _lights():
    return Lights(dome_lights(24, 45.0).directions[:, 0, :])


def test_the_trade_is_the_error_a_rising_falloff_makes():
    """A sphere of the finish without the rise (the truth), matched on a gauge
    rendered with the rise: its errors are the trade computed from the two
    finishes alone (median within 25 %, correlated over the pixels at 0.73), and a
    falloff that never rises trades nothing."""
    lights = _lights()
    rising = BRDF(falloff=RISING)
    steady = rising.never_brighter_towards_grazing()
    assert all(np.diff(steady.falloff) >= 0) and steady.falloff[-1] == 1.0
    assert falloff_trade(lights, steady, 60.0, 3) is None
    assert falloff_trade(lights, BRDF.lambert(), 60.0, 3) is None
    scene = Gauge.virtual(lights, radius=45.0, bands=3, brdf=steady)  # another pixel grid
    gauge = Gauge.virtual(lights, radius=60.0, bands=3, brdf=rising)
    result = reconstruct(scene.stack, gauge.stack, gauge, mask=scene.mask)
    solved = result.solved & scene.mask
    error = angular_error(result.normals[solved], scene.normals[solved])
    trade = falloff_trade(lights, rising, 60.0, 3)
    predicted = at_nearest_normal(*trade, result.normals[solved])
    assert np.median(error) > 0.5  # the rise moves every normal by degrees
    assert abs(np.median(predicted) / np.median(error) - 1.0) < 0.25
    assert np.corrcoef(predicted, error)[0, 1] > 0.6


def test_a_rising_fitted_falloff_widens_the_radii_it_leaves_out(tmp_path, monkeypatch):
    """A run with a light file whose finish fit traded the normals' tilt for a
    falloff rising towards grazing (the fit held to that here): its errors lay
    outside their radii (0.6 % within); with the trade added 94 %, and report.json
    says what was added."""
    from colorps import falloff_trade as module
    from colorps import virtual
    from colorps.cli import main

    lights = _lights()
    steady = BRDF(falloff=RISING).never_brighter_towards_grazing()
    scene = Gauge.virtual(lights, radius=45.0, bands=3, brdf=steady)
    rng = np.random.default_rng(3)
    for k, image in enumerate(scene.stack):
        noisy = image + rng.normal(0.0, 0.002, image.shape) * scene.mask[..., None]
        write_image(tmp_path / f"scene_{k:02d}.exr", np.maximum(noisy, 0.0).astype(np.float32))
    write_image(tmp_path / "mask.png", scene.mask.astype(np.float32), dtype="uint8")
    write_lights(lights, tmp_path / "lights.json")
    monkeypatch.setattr(virtual, "fit_scene_brdf", lambda *a, **k: (BRDF(falloff=RISING), []))
    within = {}
    for name, tolerance in (("without", 10.0), ("with", module.TRADE_TOLERANCE)):
        monkeypatch.setattr(module, "TRADE_TOLERANCE", tolerance)
        assert main(["reconstruct", "--scene", str(tmp_path / "scene_*.exr"), "--lights",
                     str(tmp_path / "lights.json"), "--mask", str(tmp_path / "mask.png"),
                     "--out", str(tmp_path / name), "--quiet", "--no-height",
                     "--no-viewer"]) == 0
        normals = read_image(tmp_path / name / "normal.exr")[0]
        radius = read_image(tmp_path / name / "uncertainty.exr")[0][..., 0]
        solved = scene.mask & np.isfinite(radius)
        error = angular_error(normals[solved], scene.normals[solved])
        within[name] = float(np.mean(error <= radius[solved]))
    record = json.loads((tmp_path / "with" / "report.json").read_text())["lights_check"]
    assert "falloff_trade" not in json.loads(
        (tmp_path / "without" / "report.json").read_text())["lights_check"]
    assert record["falloff_trade"]["normals_off_deg"] > 0.5
    assert within["without"] < 0.3 < 0.6 < within["with"], within
