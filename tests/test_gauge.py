import numpy as np
import pytest

from colorps import Gauge, GaugeError, find_sphere, synth
from colorps.gauge import parse_albedo


def test_sphere_normals_follow_conventions():
    g = Gauge.from_sphere((41, 61), cx=30.0, cy=20.0, radius=18.0, rim_margin=0)
    # Right of centre: +x; above the centre (smaller row): +y; centre: +z.
    np.testing.assert_allclose(g.normals[20, 30], [0, 0, 1], atol=1e-7)
    np.testing.assert_allclose(g.normals[20, 39], [0.5, 0, np.sqrt(0.75)], atol=1e-6)
    np.testing.assert_allclose(g.normals[11, 30], [0, 0.5, np.sqrt(0.75)], atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(g.normals[g.mask], axis=1), 1, atol=1e-6)
    assert g.mask[20, 30 + 18] and not g.mask[20, 30 + 19]  # rim itself, margin 0


def test_rim_margin_keeps_pixels_inside():
    g = Gauge.from_sphere((101, 101), 50, 50, 48)
    y, x = np.nonzero(g.mask)
    assert np.hypot(x - 50, y - 50).max() <= 48 - 2 + 1e-9


@pytest.mark.parametrize("args, message", [
    ((100, 100, 50, 30, 40), "partly outside"),
    ((100, 100, 30, 80, 40), "partly outside"),
    ((100, 100, 50, 50, 51), "partly outside"),
    ((100, 100, 50, 50, 5), "too small"),
    ((100, 100, np.nan, 20, 10), "finite"),
    ((100, 100, 50, 50, -3), "radius > 0"),
])
def test_bad_spheres(args, message):
    h, w, cx, cy, radius = args
    with pytest.raises(GaugeError, match=message):
        Gauge.from_sphere((h, w), cx, cy, radius)


def test_find_sphere_on_rendered_gauge():
    surface = synth.sphere_surface((180, 220), 70.0, centre=(101.3, 88.6))
    for theta in (10, 45):
        stack = synth.render(surface, synth.ring_lights(5, theta), noise=0.002)
        cx, cy, r = find_sphere(stack)
        assert abs(cx - 101.3) < 0.5 and abs(cy - 88.6) < 0.5 and abs(r - 70) < 1.0


def test_find_sphere_refuses_non_circles(rng):
    with pytest.raises(GaugeError, match="black"):
        find_sphere(np.zeros((3, 50, 50, 3)))
    square = np.zeros((3, 80, 80, 3), np.float32)
    square[:, 10:70, 10:70] = 1.0
    with pytest.raises(GaugeError, match="no convincing circle"):
        find_sphere(square)


def test_gauge_from_any_normal_map():
    normals = np.zeros((5, 5, 3))
    normals[..., 2] = 1
    mask = np.zeros((5, 5), bool)
    mask[1:4, 1:4] = True
    assert Gauge(normals, mask, albedo=[0.5, 0.6, 0.7]).mask.sum() == 9
    with pytest.raises(GaugeError, match="no pixel"):
        Gauge(normals, np.zeros((5, 5), bool))
    with pytest.raises(GaugeError, match="normals must be"):
        Gauge(normals[..., :2], mask)


def test_parse_albedo():
    np.testing.assert_array_equal(parse_albedo(0.8, 3), [0.8, 0.8, 0.8])
    np.testing.assert_array_equal(parse_albedo([0.1, 0.2, 0.3], 3), [0.1, 0.2, 0.3])
    for bad in (0, -1, [1, 2], np.nan, "x"):
        with pytest.raises(GaugeError, match="gauge albedo"):
            parse_albedo(bad, 3)
