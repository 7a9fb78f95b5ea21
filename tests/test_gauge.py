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


@pytest.mark.parametrize("radius", [20, 40])
@pytest.mark.parametrize("lights", ["dome", "near the view"])
def test_the_edge_of_a_blurred_lit_rim_is_found(radius, lights):
    """The edge, not the half-height of the rim's ramp: lit near the view the rim
    is dim against the middle (that half-height lay 0.34-0.57 px inside the edge), and
    in front of a lit backdrop it lay up to 1.3 px outside. Area-sampled renders
    blurred by 0, 1 and 2 px; find_sphere on a dark background (radius within
    0.11 px, centre 0.18),
    the edges along the true circle's radii in front of a lit backdrop (which
    find_sphere's segmentation does not take; within 0.15 px but for the dome's
    lights under a 2 px blur: 0.57, the half-height 0.68)."""
    from colorps.gauge import _brightest
    from colorps.shapes import dome_lights
    from colorps.sphere_edge import edge_points

    lighting = dome_lights(16) if lights == "dome" else synth.ring_lights(8, 20)
    supersample = 160 // radius  # (the same detail on both)
    for blur in (0.0, 1.0, 2.0):
        stack, centre = antialiased_sphere(radius, lighting, blur=blur, supersample=supersample)
        cx, cy, r = find_sphere(stack)
        assert abs(r - radius) < 0.15, (blur, r)
        assert np.hypot(cx - centre, cy - centre) < 0.2, (blur, cx, cy)
        stack, centre = antialiased_sphere(radius, lighting, backdrop=0.3, blur=blur,
                                           supersample=supersample)
        brightest, bright = _brightest(stack)
        edges = edge_points(brightest, (centre, centre, radius), bright)
        assert len(edges.radius) > 600 and abs(np.median(edges.radius) - radius) < 0.6


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
    for bad in (0, -1, [1, 2], np.nan, "x", 80, [0.5, 0.5, 1.2]):  # (80: a percentage)
        with pytest.raises(GaugeError, match="gauge albedo"):
            parse_albedo(bad, 3)


def antialiased_sphere(radius, lights, backdrop=0.0, blur=0.0, supersample=8):
    """A sphere rendered as a camera sees it: each pixel the mean over its area
    (supersample x supersample points), in front of a Lambertian backdrop facing
    the camera (``backdrop`` its albedo), optionally blurred (Gaussian, pixels)."""
    from scipy.ndimage import gaussian_filter

    size = int(2 * radius + 10)
    big = size * supersample
    fine = synth.sphere_surface(big, radius * supersample)
    hi = synth.render(fine, lights)
    behind = backdrop * np.maximum(lights.directions[:, 0, 2], 0.0)
    hi = np.where(fine.mask[None, ..., None], hi, behind[:, None, None, None])
    stack = hi.reshape(len(hi), size, supersample, size, supersample, -1).mean(axis=(2, 4))
    if blur:
        stack = gaussian_filter(stack, (0, blur, blur, 0))
    return stack.astype(np.float32), (size - 1) / 2


def test_rim_margin_measured_on_the_images():
    """A sharp edge, or any edge on a dark background (mixing with it only
    scales the observation vector): the floor, 1 px (or 0.02 r). A blurred edge
    on a bright backdrop: the blur too. A circle too large: that much more."""
    from colorps.gauge import rim_margin
    from colorps.shapes import dome_lights

    lights = dome_lights(16)
    for blur in (0.0, 1.0, 2.0):  # (plus the edge's own error: under 0.1 px)
        stack, centre = antialiased_sphere(20, lights, blur=blur)
        assert rim_margin(stack, (centre, centre, 20)) == pytest.approx(1.0, abs=0.1)
        assert rim_margin(stack, (centre, centre, 21)) == pytest.approx(2.0, abs=0.1)
    big, centre = antialiased_sphere(100, lights, supersample=2)
    assert rim_margin(big, (centre, centre, 100)) == pytest.approx(2.0, abs=0.05)
    margins = [rim_margin(antialiased_sphere(20, lights, backdrop=0.3, blur=blur)[0],
                          (centre_20 := (int(2 * 20 + 10) - 1) / 2, centre_20, 20))
               for blur in (0.0, 1.0, 2.0)]
    assert margins[0] < 1.5 and 1.5 < margins[1] < margins[2]
    # No lit edge to measure: what Gauge.from_sphere takes by default.
    assert rim_margin(np.zeros((4, 50, 50, 3), np.float32), (24.5, 24.5, 20)) == 2.0


def test_a_small_gauge_keeps_its_steep_normals():
    """With the rim margin measured (1 px on a sharp, anti-aliased render) a
    gauge of radius 20 px shows normals to 72 degrees instead of 64: the scene's
    steep groove walls (65-75 degrees) are no longer clamped at the table's edge
    (3.2 -> 0.6 degrees there, 0.44 -> 0.18 over the scene)."""
    import warnings

    from colorps import angular_error, reconstruct
    from colorps.gauge import rim_margin
    from colorps.shapes import dome_lights, folds_surface

    lights = dome_lights(32)
    scene = folds_surface(120)
    stack = synth.render(scene, lights, noise=0.003, seed=1)
    gauge_stack, _ = antialiased_sphere(20, lights)
    gauge_stack += np.random.default_rng(2).normal(0, 0.003, gauge_stack.shape).astype(np.float32)
    circle = find_sphere(gauge_stack)
    tilt = np.degrees(np.arccos(scene.normals[..., 2]))
    steep = scene.mask & (tilt > 65)
    assert steep.sum() > 300

    def errors(margin):
        gauge = Gauge.from_sphere(gauge_stack.shape[1:3], *circle, rim_margin=margin)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = reconstruct(stack, gauge_stack, gauge, mask=scene.mask)
        assert result.solved[scene.mask].all()
        return angular_error(result.normals, scene.normals)

    measured = rim_margin(gauge_stack, circle)
    assert measured == pytest.approx(1.0, abs=0.1)
    before, after = errors(None), errors(measured)  # None: 2 px
    assert after[steep].mean() < 0.5 * before[steep].mean()
    assert after[scene.mask].mean() < 0.75 * before[scene.mask].mean()


def test_a_gauge_in_a_whole_frame_is_solved_in_its_box():
    """A solve works on the gauge's mask's box (a photographed gauge fills little
    of its frame): the same sphere in a frame 3 x 4 times as large gives the same
    maps as in a tight one, and Gauge.within moves the sphere with the box."""
    from colorps import reconstruct

    lights = synth.ring_lights(8, 45)
    scene = synth.smiley_surface(48)
    stack = synth.render(scene, lights, noise=0.002, seed=1)
    tight = synth.render(synth.sphere_surface(61, 28), lights, noise=0.002, seed=2)
    frame = np.zeros((8, 180, 240, 3), dtype=np.float32)
    frame[:, 40:101, 150:211] = tight
    alone = reconstruct(stack, tight, Gauge.from_sphere((61, 61), 30, 30, 28), mask=scene.mask)
    whole = Gauge.from_sphere((180, 240), 180, 70, 28)
    framed = reconstruct(stack, frame, whole, mask=scene.mask)
    for name in ("normals", "albedo", "quality", "uncertainty"):
        assert np.array_equal(getattr(alone, name), getattr(framed, name), equal_nan=True), name
    boxed = whole.within((slice(40, 101), slice(150, 211)))
    assert boxed.sphere == (30.0, 30.0, 28.0)
    assert np.array_equal(boxed.mask, whole.mask[40:101, 150:211])
