"""Pixels in shadow under many lights: the masked search against brute force, the
per-pixel residual against the table's, and whole captures of deep folds."""

import numpy as np
import pytest

from colorps import Gauge, Reason, angular_error, light_masks, reconstruct, synth
from colorps import _shadow_kernels as kernels
from colorps._config import MIN_LIGHTS
from colorps.noise import NoiseModel
from colorps.residuals import MODEL_FLOOR
from colorps.shapes import dome_lights, folds_surface
from colorps.signatures import compute_signatures
from colorps.tables import Capture


def small_gauge(lights, radius=20, noise=0.0, seed=2):
    size = 2 * radius + 6
    ball = synth.sphere_surface(size, radius)
    centre = (size - 1) / 2
    stack = synth.render(ball, lights, noise=noise, seed=seed)
    return stack, Gauge.from_sphere((size, size), centre, centre, radius)


@pytest.mark.parametrize("seed", range(4))
def test_masked_search_finds_the_brute_force_nearest(seed):
    """Over a window that covers the gauge, the kernel's match is the exact
    minimiser of the masked signature distance (float64 brute force), each pair
    over the pixel's lights but for the gauge pixel's clipped ones, and on at
    least MIN_LIGHTS of them."""
    rng = np.random.default_rng(seed)
    lights = dome_lights(12)
    gauge_stack, gauge = small_gauge(lights)
    sig = compute_signatures(gauge_stack)
    usable = np.ascontiguousarray(sig.band_valid & gauge.mask[..., None])
    ov = sig.ov  # (Hg, Wg, 3, 12)
    hg, wg = gauge.mask.shape
    # Scene pixels: gauge OVs scaled per band, noised, some lights darkened (shadows).
    picks = np.flatnonzero(gauge.mask.ravel())[rng.integers(0, gauge.mask.sum(), 200)]
    scene = ov.reshape(-1, 3, 12)[picks] * rng.uniform(0.3, 2, (200, 3, 1))
    scene = np.abs(scene + rng.normal(0, 0.01, scene.shape)).astype(np.float32)
    keep = rng.random((200, 12)) > 0.3
    keep[:, :3] = True
    bands = rng.random((200, 3)) > 0.2
    bands[:, 0] = True
    pixels = kernels.Pixels(scene[None], np.zeros(200, np.int64), np.arange(200),
                            bands, keep)
    window = kernels.Window(np.full(200, hg // 2), np.full(200, wg // 2), max(hg, wg), 1)
    # A third of the gauge pixels clipped under one to nine lights.
    clipped_bool = (rng.random((hg, wg, 12)) < rng.uniform(0.05, 0.8, (hg, wg, 1))) & \
        (rng.random((hg, wg, 1)) < 0.33)
    clipped = light_masks.from_bool(clipped_bool)
    rows, d2 = np.empty(200, np.int64), np.empty(200)
    kernels.masked_search(pixels, kernels.GaugeOVs(ov, usable, clipped), window, MIN_LIGHTS,
                          rows, d2)
    g = ov.reshape(-1, 3, 12).astype(np.float64)
    for p in range(200):
        lit = keep[p] & ~clipped_bool.reshape(-1, 12)  # (Q, 12)
        s = scene[p].astype(np.float64)[None] * lit[:, None, :]
        gk = g * lit[:, None, :]
        with np.errstate(invalid="ignore", divide="ignore"):
            sn = s / np.linalg.norm(s, axis=-1, keepdims=True)
            gn_norm = np.linalg.norm(gk, axis=-1, keepdims=True)
            gn = gk / gn_norm
            dist = ((sn - gn) ** 2).sum(axis=-1)  # (Q, 3)
        ok = usable.reshape(-1, 3)[:, bands[p]].all(axis=1) & \
            (gn_norm[..., 0] > 0).all(axis=1) & (lit.sum(axis=1) >= MIN_LIGHTS)
        total = np.where(ok, dist[:, bands[p]].sum(axis=1), np.inf)
        assert total[rows[p]] == pytest.approx(total.min(), abs=1e-9)
        assert d2[p] == pytest.approx(total.min(), abs=1e-9)


def test_masked_residuals_over_every_light_are_the_table_residuals():
    """With every light kept, the per-pixel residual is the one the tables give."""
    lights = dome_lights(10)
    gauge_stack, gauge = small_gauge(lights, noise=0.003)
    scene = synth.render(synth.sphere_surface(30, 12), lights, noise=0.003, seed=5)
    sig, gsig = compute_signatures(scene), compute_signatures(gauge_stack)
    model = NoiseModel(0.003, 0.0)
    capture = Capture(sig.ov, sig.band_valid, gsig.ov, gsig.band_valid & gauge.mask[..., None],
                      gauge.normals.reshape(-1, 3), model, 1e-4)
    ys, xs = np.nonzero(synth.sphere_surface(30, 12).mask)
    every = tuple(range(10))
    group = capture.match(ys, xs, (0, 1, 2), (0, 0, 0), every)
    pixels = kernels.Pixels(capture.scene_ov, ys.astype(np.int64), xs.astype(np.int64),
                            np.ones((len(ys), 3), bool), np.ones((len(ys), 10), bool))
    q, d = np.empty(len(ys), np.float32), np.empty(len(ys), np.float32)
    resolution = capture.light_set(every).resolution_at(group.rows)
    no_clipping = light_masks.empty(capture.gauge_ov.shape[:2], 10)
    kernels.masked_residuals(pixels, kernels.GaugeOVs(capture.gauge_ov, capture.gauge_valid,
                                                      no_clipping),
                             group.rows, resolution, model.kernel_args(), model.kernel_args(),
                             MODEL_FLOOR ** 2, q, d)
    np.testing.assert_allclose(q, group.residual, rtol=1e-4)
    np.testing.assert_allclose(d, group.distance, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("model", [NoiseModel(0.003, 1e-4, "int", 255, "srgb"),
                                   NoiseModel(0.002, 0.0, "half"), NoiseModel(0.001, 0.0)])
def test_per_light_residuals_are_the_formula(model):
    """The compiled per-light residual is (S - a G) / sigma(S) summed over the used
    bands over sqrt(their count), a each band's least-squares ratio over the kept
    lights, written out in numpy here; a band with an invalid measurement or no
    gauge signal adds nothing."""
    from colorps.residuals import light_residuals

    rng = np.random.default_rng(1)
    n, bands, m = 500, 3, 40
    scene_ov = rng.random((n, bands, m)).astype(np.float32)
    gauge_ov = scene_ov + rng.normal(0, 0.01, scene_ov.shape)
    scene_ov[5, 1, 3] = np.nan
    gauge_ov[7, 0] = 0.0
    keep, used = rng.random((n, m)) > 0.2, rng.random((n, bands)) > 0.1
    extra = rng.random((n, bands)) * 1e-4
    s, g = scene_ov.astype(np.float64), gauge_ov
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = (s * g * keep[:, None]).sum(axis=-1) / (g * g * keep[:, None]).sum(axis=-1)
        r = (s - ratio[..., None] * g) / np.sqrt(model.sigma(s) ** 2 + extra[..., None])
    r = np.where(used[..., None] & np.isfinite(r), r, 0.0)
    expected = r.sum(axis=1) / np.sqrt(np.maximum(used.sum(axis=1), 1))[:, None]
    got = light_residuals(scene_ov, gauge_ov, keep, used, model, extra_variance=extra)
    np.testing.assert_allclose(got, expected, rtol=1e-5, atol=1e-5)
    assert np.isfinite(got).all()


def least_squares(stack, lights, mask):
    """Woodham's photometric stereo on every light (grey: the bands' mean)."""
    directions = lights.directions[:, 0, :]
    g = np.linalg.lstsq(directions, stack.mean(axis=3)[:, mask], rcond=None)[0].T
    return g / np.linalg.norm(g, axis=1, keepdims=True)


@pytest.fixture(scope="module")
def folds():
    lights = dome_lights(32)
    scene = folds_surface(96)
    stack = synth.render(scene, lights, noise=0.003, seed=1, cast_shadows=True)
    gauge_stack, gauge = small_gauge(lights, radius=40, noise=0.003)
    shadows = synth.shadow_maps(scene, lights).any(axis=1)  # (m, H, W)
    return scene, lights, stack, gauge_stack, gauge, shadows


def test_pixels_shadowed_under_many_lights_are_solved(folds):
    """Deep folds under a 32-light dome: every pixel solved from the lights that
    reach it, far better than least squares, and the cast shadows are the
    lights left out."""
    scene, lights, stack, gauge_stack, gauge, shadows = folds
    mask = scene.mask
    hidden = shadows[:, mask].sum(axis=0)
    assert np.percentile(hidden, 90) >= 4  # a capture where many pixels lose lights
    result = reconstruct(stack, gauge_stack, gauge, mask=mask)
    solved = result.solved[mask]
    error = np.where(solved, angular_error(result.normals[mask], scene.normals[mask]), 90.0)
    ls = angular_error(least_squares(stack, lights, mask), scene.normals[mask])
    assert solved.mean() >= 0.995
    assert error.mean() < min(1.0, ls.mean() / 4)
    assert np.median(error) < 0.5
    deep = hidden >= 3
    assert np.median(error[deep]) < 1.0
    # The cast shadows of solved pixels are among the lights they dropped, but
    # for those near grazing incidence, which change the pixel within the noise.
    from colorps import light_masks

    dropped = light_masks.to_bool(result.dropped_lights[mask], len(stack)).T  # (m, P)
    cosine = lights.directions[:, 0, :] @ scene.normals[mask].T  # (m, P)
    shadowed = shadows[:, mask] & solved[None] & (cosine >= 0.2)
    assert (dropped & shadowed).sum() >= 0.98 * shadowed.sum()


def test_shadowed_pixels_are_refused_without_light_subsets(folds):
    """The same capture with light subsets off refuses what it cannot explain
    (the stage is what solves them), or by default solves it flagged as a poor
    match, its uncertainty wider than its error."""
    scene, lights, stack, gauge_stack, gauge, shadows = folds
    plain = reconstruct(stack, gauge_stack, gauge, mask=scene.mask, light_subsets=False,
                        refuse_poor=True)
    assert plain.solved[scene.mask].mean() < 0.98
    refused = scene.mask & ~plain.solved
    flagged = reconstruct(stack, gauge_stack, gauge, mask=scene.mask, light_subsets=False)
    assert flagged.solved[scene.mask].all()
    assert (flagged.reason[refused] == Reason.SOLVED_POOR_MATCH).all()
    error = angular_error(flagged.normals[refused], scene.normals[refused])
    assert np.mean(error <= flagged.uncertainty[refused]) > 0.68


def test_one_bounce_interreflection_lights_folds_not_open_surfaces():
    """sky_visibility: 1 on an open flat surface, lower in a deep groove; the
    bounced light of render(interreflection=...) follows it."""
    from colorps.shapes import dome_lights, folds_surface

    flat = synth.SyntheticSurface(normals=np.tile([0.0, 0.0, 1.0], (40, 40, 1)),
                                  mask=np.ones((40, 40), bool),
                                  albedo=np.full((40, 40, 3), 0.5), height=np.zeros((40, 40)))
    open_sky = synth.sky_visibility(flat)
    assert np.allclose(open_sky, 1.0, atol=0.03)
    lights = dome_lights(8)
    np.testing.assert_allclose(synth.render(flat, lights, interreflection=1.0),
                               synth.render(flat, lights), atol=0.02 * 0.5)
    folds = folds_surface(96)
    sky = synth.sky_visibility(folds)
    inside = sky[folds.mask]
    assert inside.min() < 0.8 and np.median(inside) > 0.9  # grooves hidden, most open
    plain = synth.render(folds, lights, cast_shadows=True)
    bounced = synth.render(folds, lights, cast_shadows=True, interreflection=0.5)
    extra = (bounced - plain).mean(axis=(0, 3))
    hidden = folds.mask & (sky < 0.8)
    exposed = folds.mask & (sky > 0.97)
    assert extra[hidden].mean() > 5 * max(extra[exposed].mean(), 1e-4)
    assert (bounced >= plain - 1e-6).all()


def test_light_masks_round_trip_and_count_every_light():
    """Masks of up to 130 images (three words): the images set come back, and
    their count is the number of True flags."""
    rng = np.random.default_rng(3)
    flags = rng.uniform(size=(50, 130)) < rng.uniform(size=(50, 1))
    flags[0] = False
    flags[1] = True
    masks = light_masks.from_bool(flags)
    np.testing.assert_array_equal(light_masks.to_bool(masks, 130), flags)
    np.testing.assert_array_equal(light_masks.count(masks), flags.sum(axis=1))
