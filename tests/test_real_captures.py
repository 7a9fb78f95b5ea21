"""Noise model, band weights, light subsets and the auto sphere on messy captures."""

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from colorps import Gauge, GaugeError, angular_error, find_sphere, reconstruct, synth
from colorps.errors import GaugeWarning
from colorps.finishes import Gloss
from colorps.band_weights import DROP_LEVEL, band_snr, band_weights, weight_levels
from colorps.tables import Capture
from colorps.noise import NoiseModel, estimate_noise, quantisation_sigma
from colorps.signatures import compute_signatures

GAUGE_R = 80


def gauge_for(lighting, noise=0.0, seed=2, **render):
    size = 2 * GAUGE_R + 10
    ball = synth.sphere_surface(size, GAUGE_R)
    centre = (size - 1) / 2
    return (synth.render(ball, lighting, noise=noise, seed=seed, **render),
            Gauge.from_sphere((size, size), centre, centre, GAUGE_R))


# ------------------------------------------------------------------ noise model
@pytest.mark.parametrize("read, gain", [(0.01, 0.0), (0.002, 2e-4), (0.0, 5e-4)])
def test_noise_fit_recovers_read_noise_and_gain(read, gain):
    lights = synth.ring_lights(8, 45)
    ball = synth.sphere_surface(180, 80, albedo=0.8)
    clean = synth.render(ball, lights)
    rng = np.random.default_rng(3)
    noisy = clean + rng.normal(size=clean.shape) * np.sqrt(read ** 2 + gain * clean)
    usable = ball.mask & (noisy > 0).all(axis=(0, 3))
    fit = estimate_noise(noisy.astype(np.float32), usable, NoiseModel(0, 0), (89.5, 89.5), 80)
    assert fit.estimated
    level = 0.3  # compare the predicted sigma at a typical level
    truth = np.sqrt(read ** 2 + gain * level)
    assert fit.sigma(np.array([level]))[0] == pytest.approx(truth, rel=0.1)


def test_noise_fit_of_a_scene_whose_pixels_are_lit_by_some_lights_only():
    """Under 32 lights with cast shadows hardly a pixel is lit in every image, and
    a fit on those alone finds nothing (the noise model stayed 0, and a
    --lights run's uncertainties came out at 1e10 degrees); each image's own lit
    pixels give the noise."""
    from colorps.shapes import dome_lights, folds_surface

    lights = dome_lights(32)
    scene = folds_surface(100)
    stack = synth.render(scene, lights, cast_shadows=True, noise=0.003, seed=1)
    lit = (stack > 0).all(axis=3) & scene.mask  # (m, H, W)
    base = NoiseModel(0, 0)
    assert not estimate_noise(stack, lit.all(axis=0), base).estimated
    fit = estimate_noise(stack, lit, base)
    assert fit.estimated
    assert fit.sigma(np.array([0.3]))[0] == pytest.approx(0.003, rel=0.15)


def test_quantisation_of_srgb_codes_grows_with_the_level():
    q = quantisation_sigma(np.array([0.001, 0.05, 0.5, 0.9]), pixel_type="int")
    assert np.all(np.diff(q) > 0)
    assert q[2] == pytest.approx(0.0017, rel=0.1)  # one 8-bit code at 0.5 linear / sqrt(12)
    assert quantisation_sigma(np.array([0.5]), pixel_type="int", top_code=65535)[0] < 1e-5
    assert quantisation_sigma(np.array([0.5]), pixel_type="float")[0] == 0


def test_half_float_quantisation_is_one_half_ulp_over_sqrt12():
    values = np.concatenate([np.geomspace(1e-7, 60000.0, 5000), [0.0, 2.0 ** -14, 1.0]])
    # numpy's own float16 spacing, at values already representable in half
    halves = values.astype(np.float16)
    expected = np.spacing(halves).astype(np.float64) / np.sqrt(12.0)
    got = quantisation_sigma(halves.astype(np.float32), pixel_type="half")
    np.testing.assert_allclose(got, expected, rtol=1e-6)
    model = NoiseModel(read=0.0, gain=0.0, pixel_type="half")
    np.testing.assert_allclose(model.sigma(halves[1:].astype(np.float32)), expected[1:],
                               rtol=1e-6)


# ------------------------------------------------------------------ band weights
def test_weight_levels_follow_snr():
    snr = np.array([[100.0, 50.0, 1.0], [20.0, 20.0, 20.0], [0.0, 0.0, 0.0],
                    [8.0, 2.0, 0.0]])
    assert weight_levels(snr).tolist() == [[0, -1, -3], [0, 0, 0], [-3, -3, -3],
                                           [0, -2, -3]]


@pytest.mark.parametrize("pixel_type", ["float", "half"])
def test_band_snr_is_norm_over_model_sigma(pixel_type):
    rng = np.random.default_rng(3)
    ov = rng.uniform(0.0, 1.0, (4, 5, 3, 6)).astype(np.float32)
    ys, xs = np.nonzero(rng.uniform(size=(4, 5)) > 0.3)
    valid = rng.uniform(size=(len(ys), 3)) > 0.2
    model = NoiseModel(read=0.01, gain=0.002, pixel_type=pixel_type)
    got = band_snr(ov, ys, xs, valid, model)
    picked = ov[ys, xs].astype(np.float64)
    sigma2 = (model.sigma(ov[ys, xs]).astype(np.float64) ** 2).mean(axis=-1)
    expected = np.where(valid, np.linalg.norm(picked, axis=-1) / np.sqrt(sigma2), 0.0)
    np.testing.assert_allclose(got, expected, rtol=1e-5)


@pytest.mark.parametrize("m", [2, 3, 8])
def test_band_weights_keep_the_bands_that_fix_a_normal(m):
    """The one-pass band choice against its definition, step by step in numpy:
    levels of the SNR, bands at DROP_LEVEL left out where the rest still fix a
    normal (bands x (lights - 1) >= 2), the kept ones at DROP_LEVEL + 1 or more."""
    rng = np.random.default_rng(m)
    ov = rng.uniform(0.0, 1.0, (30, 40, 3, m)).astype(np.float32)
    ov *= rng.choice([1.0, 0.3, 0.05, 0.005], size=(30, 40, 3, 1)).astype(np.float32)
    ys, xs = np.nonzero(rng.uniform(size=(30, 40)) > 0.2)
    valid = rng.uniform(size=(len(ys), 3)) > 0.15
    model = NoiseModel(read=0.01, gain=0.002, pixel_type="half")
    levels = weight_levels(band_snr(ov, ys, xs, valid, model))
    kept = valid & (levels > DROP_LEVEL)
    fixes_normal = kept.sum(axis=-1) * (m - 1) >= 2
    expected_valid = np.where(fixes_normal[:, None], kept, valid)
    expected = np.where(expected_valid, np.maximum(levels, DROP_LEVEL + 1), 0)
    got_valid, got = band_weights(ov, ys, xs, valid, model)
    np.testing.assert_array_equal(got_valid, expected_valid)
    np.testing.assert_array_equal(got, expected)
    assert got.dtype == np.int8 and (got_valid != valid).any() and (got < 0).any()


@settings(max_examples=15, deadline=None)
@given(m=st.sampled_from([3, 5, 8]), seed=st.integers(0, 2 ** 31),
       levels=st.tuples(st.integers(-2, 0), st.integers(-2, 0), st.just(0)),
       count=st.sampled_from([20, 400]))
def test_weighted_matches_are_brute_force_nearest(m, seed, levels, count):
    """For the weighted distance it defines, every match is the exact nearest entry
    (grid for large groups, brute force for small ones)."""
    rng = np.random.default_rng(seed)
    lights = synth.ring_lights(m, rng.uniform(20, 60), rng.uniform(0.2, 1.0, (m, 3)))
    gauge_stack, gauge = gauge_for(lights)
    scene = synth.smiley_surface(64)
    stack = synth.render(scene, lights, noise=0.01, seed=seed % 1000)
    sig_s, sig_g = compute_signatures(stack), compute_signatures(gauge_stack)
    capture = Capture(sig_s.ov, sig_s.band_valid, sig_g.ov,
                      sig_g.band_valid & gauge.mask[..., None], gauge.normals.reshape(-1, 3),
                      NoiseModel(0.01, 0.0), 1e-4)
    ys, xs = np.nonzero(scene.mask & sig_s.valid)
    pick = rng.choice(len(ys), min(count, len(ys)), replace=False)
    ys, xs = ys[pick], xs[pick]
    result = capture.match(ys, xs, (0, 1, 2), levels, tuple(range(m)))
    w2 = np.exp2(2.0 * np.array(levels))
    g = sig_g.signatures.reshape(-1, 3, m).astype(np.float64)
    table = np.flatnonzero((sig_g.valid & gauge.mask).ravel())
    s = sig_s.signatures[ys, xs].reshape(-1, 3, m).astype(np.float64)
    # Every entry's weighted squared distance, |s|^2 + |g|^2 - 2 s.g in float64 (a
    # matrix product: the brute force without a (queries, entries, bands, m) array).
    sw = (s * np.sqrt(w2)[:, None]).reshape(len(s), -1)
    gw = (g[table] * np.sqrt(w2)[:, None]).reshape(len(table), -1)
    d2 = (sw ** 2).sum(-1)[:, None] + (gw ** 2).sum(-1)[None] - 2.0 * sw @ gw.T
    best = d2.min(axis=1)
    got = (((s - g[result.rows]) ** 2).sum(-1) * w2).sum(-1)
    assert np.all(got <= best * (1 + 1e-4) + 1e-6)


def test_saturated_colours_under_coloured_lights_fully_solved():
    """The case of the issue: colour lights, saturated albedo, noise 0.005."""
    m = 8
    phase = 2 * np.pi * np.arange(m) / m
    hue = 0.5 + 0.5 * np.cos(phase[:, None] - np.array([0.0, 2.0, 4.0]) * np.pi / 3)
    lights = synth.ring_lights(m, 45, 0.1 + 0.9 * hue)
    scene = synth.smiley_surface(200)
    stack = synth.render(scene, lights, noise=0.005, seed=1)
    gauge_stack, gauge = gauge_for(lights, noise=0.005)
    errors = {}
    for name, changes in [("mono", dict(mode="mono")), ("unweighted", dict(band_weights=False)),
                          ("weighted", {})]:
        result = reconstruct(stack, gauge_stack, gauge, mask=scene.mask, **changes)
        err = np.where(result.solved, angular_error(result.normals, scene.normals), 90.0)
        errors[name] = float(err[scene.mask].mean())
        if name == "weighted":
            assert result.solved[scene.mask].mean() > 0.999
            rel = np.abs(result.albedo[scene.mask] / scene.albedo[scene.mask] - 1)
            assert np.nanmedian(rel, axis=0).max() < 0.03, np.nanmedian(rel, axis=0)
    assert errors["weighted"] <= errors["mono"] and errors["weighted"] < errors["unweighted"]


# ------------------------------------------------------------------ light subsets
def test_cast_shadows_of_the_relief_solved_with_the_light_identified():
    lights = synth.ring_lights(8, 60)
    scene = synth.smiley_surface(160, relief=0.2)
    shadows = synth.shadow_maps(scene, lights)[:, 0]
    stack = synth.render(scene, lights, cast_shadows=True, noise=0.002, seed=1)
    gauge_stack, gauge = gauge_for(lights, noise=0.002)
    result = reconstruct(stack, gauge_stack, gauge, mask=scene.mask)
    plain = reconstruct(stack, gauge_stack, gauge, mask=scene.mask, light_subsets=False,
                        refuse_poor=True)  # (flagged, not refused, by default)
    one = (shadows.sum(axis=0) == 1) & scene.mask
    assert one.sum() > 500
    lit = np.argmax(shadows[:, one], axis=0).astype(np.uint64)
    identified = result.dropped_lights[..., 0][one] == (np.uint64(1) << lit)
    assert identified.mean() > 0.7
    err = np.where(result.solved, angular_error(result.normals, scene.normals), 90.0)
    err_plain = np.where(plain.solved, angular_error(plain.normals, scene.normals), 90.0)
    assert err[one].mean() < 2.0 < 10 * 2.0 < err_plain[one].mean()
    assert err[scene.mask].mean() < err_plain[scene.mask].mean()
    darker = sum(d["darker"] for d in result.stats.dropped_per_light)
    brighter = sum(d["brighter"] for d in result.stats.dropped_per_light)
    assert darker >= identified.sum() and darker > 5 * brighter
    assert darker + brighter >= result.stats.solved_from_light_subset


def test_highlights_the_gauge_lacks_are_dropped_as_brighter():
    lights = synth.ring_lights(8, 45)
    scene = synth.smiley_surface(140, coloured=False)
    stack = synth.render(scene, lights, gloss=Gloss(0.6, shininess=80), noise=0.002, seed=1)
    gauge_stack, gauge = gauge_for(lights, noise=0.002)
    spots = synth.highlight_maps(scene, lights, gloss=Gloss(0.6, shininess=80), level=0.05)[:, 0]
    one = (spots.sum(axis=0) == 1) & scene.mask
    assert one.sum() > 100
    result = reconstruct(stack, gauge_stack, gauge, mask=scene.mask)
    which = np.argmax(spots[:, one], axis=0).astype(np.uint64)
    assert (result.dropped_lights[..., 0][one] == (np.uint64(1) << which)).mean() > 0.8
    assert sum(d["brighter"] for d in result.stats.dropped_per_light) > 0.8 * one.sum()
    err = angular_error(result.normals[one], scene.normals[one])
    assert np.nanmedian(err) < 1.0


def test_never_fewer_than_three_lights():
    lights = synth.ring_lights(4, 45)
    scene = synth.smiley_surface(100)
    stack = synth.render(scene, lights)
    stack[0, 30:60, 30:60] *= 0.1
    stack[1, 40:70, 40:70] *= 0.1
    gauge_stack, gauge = gauge_for(lights)
    result = reconstruct(stack, gauge_stack, gauge, mask=scene.mask)
    assert result.lights_dropped_count.max() <= 1  # 4 lights: one may go, 3 remain
    assert result.stats.solved_from_light_subset > 0


# ------------------------------------------------------------------ auto sphere
def one_sided_lights(m=6, theta=50.0):
    phi = np.linspace(0, np.pi, m)
    t = np.radians(theta)
    dirs = np.stack([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi),
                     np.full(m, np.cos(t))], axis=1)
    return synth.Lighting(dirs[:, None, :], np.ones((m, 1, 3)))


@pytest.mark.parametrize("radius", [30, 60, 100])
@pytest.mark.parametrize("blur", [0.0, 1.5])
def test_auto_sphere_on_a_sphere_lit_from_one_side(radius, blur):
    """The circle through the sphere's edge, not through its outline at a low
    level (0.3 px outside on a sharp render, 2 px with a blur of 1.5 px)."""
    from scipy.ndimage import gaussian_filter

    ball = synth.sphere_surface((2 * radius + 30, 2 * radius + 50), radius,
                                centre=(radius + 12.3, radius + 20.7))
    stack = gaussian_filter(synth.render(ball, one_sided_lights(), noise=0.003),
                            (0, blur, blur, 0))
    eight_bit = np.round(np.clip(stack, 0, 1) * 255) / 255
    cx, cy, r = find_sphere(eight_bit)
    assert abs(cx - (radius + 12.3)) < 0.5 and abs(cy - (radius + 20.7)) < 0.5
    assert abs(r - radius) < 0.25


@pytest.mark.parametrize("blur", [0.0, 1.0, 2.0])
def test_auto_sphere_lit_all_round_within_a_tenth_of_a_pixel(blur):
    from scipy.ndimage import gaussian_filter

    ball = synth.sphere_surface((150, 140), 60, centre=(72.4, 68.9))
    stack = gaussian_filter(synth.render(ball, synth.ring_lights(8, 45), noise=0.003),
                            (0, blur, blur, 0))
    cx, cy, r = find_sphere(stack)
    assert abs(cx - 72.4) < 0.05 and abs(cy - 68.9) < 0.05 and abs(r - 60) < 0.1


def test_auto_sphere_refuses_two_spheres_and_none():
    lights = synth.ring_lights(3, 30)
    two = sum(synth.render(synth.sphere_surface((100, 220), 40, centre=(cx, 50)), lights)
              for cx in (50, 160))
    with pytest.raises(GaugeError, match="two bright regions"):
        find_sphere(two)
    square = np.pad(np.ones((3, 40, 40, 3), np.float32), ((0, 0), (20, 20), (20, 20), (0, 0)))
    with pytest.raises(GaugeError, match="no convincing circle"):
        find_sphere(square)
    with pytest.raises(GaugeError, match="too small"):
        find_sphere(np.ones((3, 1, 1, 3)))


# ------------------------------------------------------------------ files, end to end
def test_8bit_one_sided_capture_with_defaults_and_auto_sphere(tmp_path):
    """Like the real captures of the issue: 12 lights from one side, 8-bit sRGB PNGs,
    cast shadows, noise; default options and --sphere auto."""
    import json

    from colorps.cli import main
    from colorps.io import read_image, read_mask
    from colorps.synth import write_synthetic

    data = tmp_path / "capture"
    write_synthetic(data, size=160, images=12, theta=50, lights="one-sided", noise=0.003,
                    relief=0.2, cast_shadows=True, file_format="png8", gauge_radius=50)
    out = tmp_path / "out"
    assert main(["reconstruct", "--scene", str(data / "scene_*.png"), "--gauge",
                 str(data / "gauge_*.png"), "--sphere", "auto", "--mask",
                 str(data / "mask.png"), "--out", str(out), "--quiet"]) == 0
    report = json.loads((out / "report.json").read_text())
    stats = report["statistics"]
    assert abs(report["sphere"]["r"] - 50) < 1 and report["sphere_found_automatically"]
    assert stats["noise"]["pixel_type"] == "int" and stats["noise"]["estimated"]
    mask = read_mask(data / "mask.png", (160, 160))
    normals, _ = read_image(out / "normal.exr")
    truth, _ = read_image(data / "truth_normal.exr")
    solved = np.isfinite(normals[..., 0]) & mask
    assert solved.sum() >= 0.98 * mask.sum()
    assert np.median(angular_error(normals[solved], truth[solved])) < 1.0
    assert stats["solved_from_light_subset"] > 0
    lights = read_image(out / "lights.exr")[0][..., 0]
    assert (lights[mask] > 0).sum() == stats["solved_from_light_subset"]


def test_pixel_groups_are_the_distinct_rows():
    from colorps.tables import group_rows

    rng = np.random.default_rng(5)
    rows = np.column_stack([rng.integers(0, 3, 5000) << 40, rng.integers(0, 8, 5000),
                            rng.integers(-2, 1, (5000, 3))])
    # Light-mask words with the top bit set (negative as int64), and digits wide
    # enough that their code must be compacted on the way.
    wide = np.column_stack([rng.integers(-2 ** 63, -1, 5000, dtype=np.int64),
                            rng.integers(0, 60000, (5000, 5))])
    wide[2500:] = wide[:2500]  # repeated rows
    for table in (rows, wide, rows[:0]):
        keys, group = group_rows(table)
        expected_keys, expected_group = np.unique(table, axis=0, return_inverse=True)
        assert np.array_equal(keys, expected_keys)
        assert np.array_equal(group, expected_group.ravel())


@pytest.mark.parametrize("model", [
    NoiseModel(0.002, 0.001, "float"), NoiseModel(0.002, 0.001, "half"),
    NoiseModel(0.001, 0.0005, "int", 255, "srgb"), NoiseModel(0.0, 0.0, "int", 65535, "linear")])
def test_mean_variance_is_the_mean_of_sigma_squared(model):
    rng = np.random.default_rng(2)
    values = (rng.random((50, 3, 8)) * 1.2 - 0.1).astype(np.float32)
    values[0, 0, :2] = [np.nan, np.inf]
    expected = (model.sigma(values).astype(np.float64) ** 2).mean(axis=-1)
    np.testing.assert_allclose(model.mean_variance(values), expected, rtol=1e-5)


def test_light_sets_are_kept_within_their_memory_bound(monkeypatch):
    """A capture of many lights tries many light subsets: the gauge over each is
    kept only while the ones used last fit in LIGHT_SET_CACHE_MIB, and one
    recomputed after being dropped is the same."""
    from colorps import tables as matching

    lights = synth.ring_lights(12, 45)
    gauge_stack, gauge = gauge_for(lights)
    sig = compute_signatures(gauge_stack)
    capture = Capture(sig.ov, sig.band_valid, sig.ov, sig.band_valid & gauge.mask[..., None],
                      gauge.normals.reshape(-1, 3), NoiseModel(0.01, 0.0), 1e-4)
    every = tuple(range(12))
    one = capture.light_set(every).nbytes
    monkeypatch.setattr(matching, "LIGHT_SET_CACHE_MIB", 3.5 * one / 2 ** 20)
    first = capture.light_set(every[1:])
    for k in range(2, 12):
        capture.light_set(tuple(i for i in every if i != k))
        assert sum(s.nbytes for s in capture._light_sets.values()) <= 3.5 * one
    assert every in capture._light_sets and every[1:] not in capture._light_sets
    again = capture.light_set(every[1:])
    assert again is not first
    for name in ("norm2", "variance", "usable"):
        assert np.array_equal(getattr(again, name), getattr(first, name)), name
    every_row = np.arange(first.resolution.shape[0])
    assert np.array_equal(again.resolution_at(every_row), first.resolution_at(every_row))


def test_a_gauge_clipped_where_lights_meet_it_head_on(monkeypatch):
    """A white gauge exposed to its top code under 24 lights: 64 % of its pixels
    have a clipped measurement, so the table over every light leaves them out,
    and the refinement had no models there either: the scene's (unclipped)
    pixels matched the nearest entry outside and kept its normal (2.1 degrees
    mean). With models fitted but for clipped measurements (0.25) and each pixel
    matched again without the gauge's clipped lights near its match, or fitted on
    its own lights without the clipped ones of the gauge pixels it scans
    (colorps.shadows), the normals come out as with a gauge that clips nothing
    (0.11 against 0.10)."""
    import importlib

    from colorps.shapes import dome_lights, folds_surface

    lights = dome_lights(24)
    scene = folds_surface(100)
    stack = synth.render(scene, lights, noise=0.002, seed=1)
    ball = synth.sphere_surface(90, 40)
    rendered = synth.render(ball, lights, noise=0.002, seed=2)
    gauge = Gauge.from_sphere((90, 90), 44.5, 44.5, 40)

    def errors(gauge_stack):
        with warnings.catch_warnings():  # the clipped gauge's exposure warning
            warnings.simplefilter("ignore", GaugeWarning)
            result = reconstruct(stack, gauge_stack, gauge, mask=scene.mask, clip_level=1.0)
        ok = scene.mask & result.solved
        assert ok.sum() == scene.mask.sum()
        return angular_error(result.normals[ok], scene.normals[ok])

    clipped = np.minimum(1.015 * rendered, 1.0)
    assert (clipped[:, gauge.mask] >= 1.0).any(axis=(0, 2)).mean() > 0.5
    reference = errors(0.95 * rendered)  # the same gauge, nothing clipped
    rematched = errors(clipped)
    matching = importlib.import_module("colorps.matching")
    shadows = importlib.import_module("colorps.shadows")
    monkeypatch.setattr(matching, "rematch_near_clipped", lambda *args, **kwargs: [])
    monkeypatch.setattr(shadows, "_usable_gauge", lambda capture: capture.gauge_valid)
    first = errors(clipped)
    assert rematched.mean() < 1.25 * reference.mean()
    assert rematched.mean() < 0.6 * first.mean()
    assert np.percentile(rematched, 95) < 1.25 * np.percentile(reference, 95)


def test_a_clipped_gauge_and_cast_shadows_under_many_lights(monkeypatch):
    """Pixels in the cast shadow of many lights are fitted on their own lights
    (colorps.shadows); where their normal lies in a clipped patch of the gauge,
    that fit leaves out the gauge pixel's clipped lights too. Scanning only the
    gauge pixels clipped under no light, it found none near the true normal and
    refused the pixel ("no good match"); now every pixel is solved, as with a
    gauge that clips nothing."""
    import importlib

    from colorps.shapes import dome_lights, folds_surface

    lights = dome_lights(32)
    scene = folds_surface(100)
    stack = synth.render(scene, lights, noise=0.002, seed=1, cast_shadows=True)
    rendered = synth.render(synth.sphere_surface(90, 40), lights, noise=0.002, seed=2)
    gauge = Gauge.from_sphere((90, 90), 44.5, 44.5, 40)

    def run(gauge_stack):
        with warnings.catch_warnings():  # the clipped gauge's exposure warning
            warnings.simplefilter("ignore", GaugeWarning)
            result = reconstruct(stack, gauge_stack, gauge, mask=scene.mask, clip_level=1.0,
                                 refuse_poor=True)  # (flagged, not refused, by default)
        errors = np.where(result.solved, angular_error(result.normals, scene.normals), 90.0)
        return errors[scene.mask], result

    clipped = np.minimum(1.015 * rendered, 1.0)
    assert (clipped[:, gauge.mask] >= 1.0).any(axis=(0, 2)).mean() > 0.5
    reference, _ = run(0.95 * rendered)  # the same gauge, nothing clipped
    fitted, _ = run(clipped)
    assert (reference < 90).all() and (fitted < 90).all()
    assert fitted.mean() < 1.25 * reference.mean()  # 0.12 against 0.11 degrees

    shadows = importlib.import_module("colorps.shadows")  # as it was: no clipped pixel scanned
    monkeypatch.setattr(shadows, "_usable_gauge", lambda capture: capture.gauge_valid)
    monkeypatch.setattr(shadows, "_unclipped_at", lambda capture, keep, rows: keep)
    before, _ = run(clipped)
    assert (before == 90).mean() > 0.005  # 1.9 % refused
