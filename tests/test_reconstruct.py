import sys

import numpy as np
import pytest

from colorps import (
    BucketGrid,
    Gauge,
    InputError,
    angular_error,
    compute_signatures,
    reconstruct,
    synth,
)
from colorps.errors import GaugeWarning

GAUGE_R = 150.0




def lit_by_all(surface, lighting):
    cos = np.einsum("hwc,mlc->hwml", surface.normals, lighting.directions)
    return surface.mask & (cos > 0).all(axis=(2, 3))


def run(lighting, *, scene=None, brdf="lambert", noise=0.0, mode="colour", gauge_albedo=1.0,
        **kwargs):
    scene = synth.smiley_surface(160) if scene is None else scene
    size = int(2 * GAUGE_R + 8)
    ball = synth.sphere_surface(size, GAUGE_R, albedo=gauge_albedo)
    scene_stack = synth.render(scene, lighting, brdf=brdf, noise=noise, seed=1)
    gauge_stack = synth.render(ball, lighting, brdf=brdf, noise=noise, seed=2)
    centre = (size - 1) / 2
    gauge = Gauge.from_sphere((size, size), centre, centre, GAUGE_R, albedo=gauge_albedo)
    result = reconstruct(scene_stack, gauge_stack, gauge, mode=mode, mask=scene.mask,
                         **kwargs)
    return scene, result


@pytest.mark.parametrize("brdf", ["lambert", "oren-nayar"])
@pytest.mark.parametrize("mode", ["colour", "mono"])
def test_noiseless_accuracy(brdf, mode):
    lighting = synth.ring_lights(8, 45)
    scene, result = run(lighting, brdf=brdf, mode=mode)
    ok = lit_by_all(scene, lighting)
    assert result.solved[ok].all()
    err = angular_error(result.normals[ok], scene.normals[ok])
    assert err.mean() <= 0.5, err.mean()
    rel = np.abs(result.albedo[ok] / scene.albedo[ok] - 1)
    assert rel.mean(axis=0).max() <= 0.01, rel.mean(axis=0)
    np.testing.assert_allclose(np.linalg.norm(result.normals[result.solved], axis=-1), 1,
                               atol=1e-5)
    assert np.isnan(result.normals[~result.solved]).all()
    assert result.stats.table_size > 60000 and result.stats.solved == scene.mask.sum()


def test_white_lights_colour_albedo_ratios_in_both_modes():
    lighting = synth.ring_lights(6, 40)
    for mode in ("colour", "mono"):
        scene, result = run(lighting, mode=mode, gauge_albedo=[0.9, 0.8, 0.7])
        ok = lit_by_all(scene, lighting)
        # Albedo relative to the gauge's: per band, and as colour ratios.
        rel = np.abs(result.albedo[ok] / scene.albedo[ok] - 1)
        assert np.median(rel) < 0.005
        ratio = result.albedo[ok][:, 0] / result.albedo[ok][:, 2]
        truth = scene.albedo[ok][:, 0] / scene.albedo[ok][:, 2]
        assert np.median(np.abs(ratio / truth - 1)) < 0.005


def test_noise_colour_mode_no_worse_than_mono():
    """Grey surface, white lights, independent noise in each band."""
    lighting = synth.ring_lights(6, 45)
    scene = synth.smiley_surface(160, coloured=False)
    errors = {}
    for mode in ("colour", "mono"):
        _, result = run(lighting, scene=scene, noise=0.01, mode=mode)
        ok = lit_by_all(scene, lighting)
        errors[mode] = angular_error(result.normals[ok], scene.normals[ok]).mean()
    assert errors["colour"] <= errors["mono"] * 1.02, errors


def test_two_images_with_mixed_colour_lights():
    """Two images, each lit by two lights of different colours at once."""
    lighting = synth.mixed_lights(2, 40)
    with pytest.warns(GaugeWarning, match="several lights of different colours"):
        scene, result = run(lighting, mode="colour")
    ok = lit_by_all(scene, lighting) & result.solved
    colour_err = angular_error(result.normals[ok], scene.normals[ok])
    assert colour_err.mean() < 1.0, colour_err.mean()
    with pytest.raises(InputError, match="mono mode needs at least 3 images.*colour mode"):
        run(lighting, mode="mono")
    # What mono mode would get from the same two luminance images: one degree of
    # freedom per pixel (the ratio of two values) cannot fix a normal.
    size = int(2 * GAUGE_R + 8)
    ball = synth.sphere_surface(size, GAUGE_R)
    gauge = Gauge.from_sphere((size, size), (size - 1) / 2, (size - 1) / 2, GAUGE_R)
    g = compute_signatures(synth.render(ball, lighting), "mono")
    s = compute_signatures(synth.render(scene, lighting), "mono")
    table = gauge.mask & g.valid
    rows, _ = BucketGrid(g.signatures[table]).query(s.signatures[ok])
    mono_err = angular_error(gauge.normals[table][rows], scene.normals[ok])
    assert mono_err.mean() > 10 * colour_err.mean(), (mono_err.mean(), colour_err.mean())


def test_one_coloured_light_per_image_adds_nothing_over_mono():
    """Per band the OV is the mono OV scaled image-wise by the light colours, a
    fixed linear map: the colour signature holds the same information."""
    phase = 2 * np.pi * np.arange(5) / 5
    colours = 0.3 + 0.7 * (0.5 + 0.5 * np.cos(phase[:, None] - [0, 2.1, 4.2]))
    lighting = synth.ring_lights(5, 45, colours)
    scene = synth.smiley_surface(160, coloured=False)
    normals = {}
    for mode in ("colour", "mono"):
        _, result = run(lighting, scene=scene, mode=mode, band=0 if mode == "mono" else None)
        normals[mode] = result.normals
    ok = lit_by_all(scene, lighting)
    for mode in normals:
        assert angular_error(normals[mode][ok], scene.normals[ok]).mean() < 0.5


def test_reasons_and_stats():
    lighting = synth.ring_lights(4, 30)
    scene = synth.smiley_surface(80)
    stack = synth.render(scene, lighting)
    stack[:, 40, 40] = np.nan
    ball = synth.sphere_surface(120, 55)
    gauge = Gauge.from_sphere((120, 120), 59.5, 59.5, 55)
    mask = scene.mask.copy()
    mask[:, :10] = False
    result = reconstruct(stack, synth.render(ball, lighting), gauge, mask=mask)
    assert result.reason[40, 40] == 4 and not result.solved[40, 40]
    assert (result.reason[~mask] == 1).all()
    assert (result.reason[mask & ~scene.mask] == 2).all()  # black background
    by_reason = result.stats.pixels_by_reason
    assert by_reason["invalid value"] == 1 and by_reason["solved"] == result.solved.sum()
    seconds = result.stats.seconds
    assert min(seconds.signatures, seconds.grid, seconds.lookup) >= 0
    assert seconds.total >= seconds.grid + seconds.lookup and seconds.integration is None


@pytest.mark.parametrize("change, message", [
    (lambda s, g: (s[:3], g), "scene has 3 images but the gauge has 4"),
    (lambda s, g: (s[..., :1], g), "channel"),
    (lambda s, g: (s, g[:, :50]), "gauge geometry"),
])
def test_mismatched_inputs(change, message):
    lighting = synth.ring_lights(4, 30)
    scene = synth.render(synth.smiley_surface(40), lighting)
    gauge_stack = synth.render(synth.sphere_surface(120, 55), lighting)
    gauge = Gauge.from_sphere((120, 120), 59.5, 59.5, 55)
    s, g = change(scene, gauge_stack)
    with pytest.raises(InputError, match=message):
        reconstruct(s, g, gauge)
    with pytest.raises(InputError, match="mask"):
        reconstruct(scene, gauge_stack, gauge, mask=np.ones((3, 3), bool))


def test_tile_order_is_a_permutation_tile_by_tile(rng):
    from colorps.matching import _tile_order

    pixels = rng.random((70, 45)) < 0.6
    ys, xs = _tile_order(pixels, tile=16)
    assert sorted(zip(ys.tolist(), xs.tolist())) == sorted(zip(*np.nonzero(pixels)))
    # Tiles in row-major order, and pixels row-major inside each tile.
    key = np.stack([ys // 16, xs // 16, ys, xs], axis=1)
    assert all(tuple(a) < tuple(b) for a, b in zip(key[:-1], key[1:]))


def test_only_the_masks_box_is_worked_on_and_the_maps_cover_the_image():
    """A mask in one corner: the maps are the whole image's, background outside,
    and equal to a run on the box cut out by hand; the statistics count every
    pixel of the image."""
    from colorps.reasons import Reason

    lights = synth.ring_lights(6, 45)
    scene = synth.smiley_surface(96)
    stack = synth.render(scene, lights, noise=0.002, seed=1)
    ball = synth.sphere_surface(90, 40)
    gauge = Gauge.from_sphere((90, 90), 44.5, 44.5, 40)
    gauge_stack = synth.render(ball, lights, noise=0.002, seed=2)
    mask = np.zeros(scene.mask.shape, bool)
    mask[10:50, 20:70] = scene.mask[10:50, 20:70]
    whole = reconstruct(stack, gauge_stack, gauge, mask=mask, read_noise=0.002, gain=0.0)
    rows, cols = np.nonzero(mask.any(axis=1))[0], np.nonzero(mask.any(axis=0))[0]
    box = np.s_[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
    cut = reconstruct(stack[:, box[0], box[1]], gauge_stack, gauge, mask=mask[box],
                      read_noise=0.002, gain=0.0)
    assert whole.normals.shape == (*mask.shape, 3)
    for name in ("normals", "albedo", "quality", "uncertainty", "reason", "dropped_lights"):
        np.testing.assert_array_equal(getattr(whole, name)[box], getattr(cut, name))
    outside = np.ones(mask.shape, bool)
    outside[box] = False
    assert (whole.reason[outside] == Reason.BACKGROUND).all()
    assert np.isnan(whole.normals[outside]).all() and not whole.solved[outside].any()
    assert whole.stats.pixels == mask.size
    assert sum(whole.stats.pixels_by_reason.values()) == mask.size
    assert whole.stats.pixels_by_reason[Reason.BACKGROUND.label] == (~mask).sum()


def test_model_scale_pixels_are_counted_from_the_whole_scenes_corner():
    from colorps.matching import model_scale_pixels

    mask = np.random.default_rng(3).random((60, 70)) < 0.8
    picked = model_scale_pixels(mask, step=3)
    np.testing.assert_array_equal(
        model_scale_pixels(mask[7:50, 11:64], step=3, first_row=7, first_col=11),
        picked[7:50, 11:64])


@pytest.mark.skipif(sys.version_info < (3, 11),
                    reason="before 3.11 a caller's stack keeps the arguments of a call")
@pytest.mark.parametrize("mode", ["colour", "mono"])
def test_a_handed_over_stack_is_let_go_for_the_matching(monkeypatch, mode):
    """Given its only reference, reconstruct frees the scene stack once the OVs
    exist in colour mode (their albedo is read from them), and keeps it in mono
    mode (the albedo needs every band): the same maps either way."""
    import weakref

    reconstruct_module = sys.modules["colorps.reconstruct"]
    lighting = synth.ring_lights(6, 45)
    scene = synth.smiley_surface(64)
    ball = synth.sphere_surface(101, 48)
    stack = synth.render(scene, lighting, noise=0.002, seed=1)
    gauge_stack = synth.render(ball, lighting, noise=0.002, seed=2)
    gauge = Gauge.from_sphere((101, 101), 50, 50, 48)
    kept = reconstruct(stack, gauge_stack, gauge, mask=scene.mask, mode=mode)
    alive_at_matching = []
    real_match = reconstruct_module.match_pixels

    def match_pixels(*args, **kwargs):
        alive_at_matching.append(handed_stack() is not None)
        return real_match(*args, **kwargs)

    monkeypatch.setattr(reconstruct_module, "match_pixels", match_pixels)
    handed, handed_stack = [stack], weakref.ref(stack)
    del stack
    result = reconstruct(handed.pop(), gauge_stack, gauge, mask=scene.mask, mode=mode)
    assert alive_at_matching == [mode == "mono"]
    for name in ("normals", "albedo", "quality", "uncertainty", "solved"):
        np.testing.assert_array_equal(getattr(result, name), getattr(kept, name), err_msg=name)


def _huge_pages_asked() -> bool:
    from numpy._core.multiarray import _set_madvise_hugepage

    now = _set_madvise_hugepage(False)
    _set_madvise_hugepage(now)
    return now


def test_reconstruct_runs_on_small_pages_and_puts_the_setting_back(monkeypatch):
    """numpy's huge-page requests (compaction stalls on many Linux machines) are off
    while reconstruct runs, and as they were after it, whatever they were."""
    from numpy._core.multiarray import _set_madvise_hugepage

    module = sys.modules["colorps.reconstruct"]  # (the package's name is the function)

    seen = []
    match = module.match_pixels

    def recording(*args, **kwargs):
        seen.append(_huge_pages_asked())
        return match(*args, **kwargs)

    monkeypatch.setattr(module, "match_pixels", recording)
    before = _set_madvise_hugepage(True)
    try:
        run(synth.ring_lights(6, 40))
        assert seen and not any(seen)
        assert _huge_pages_asked()
    finally:
        _set_madvise_hugepage(before)


def test_groups_prepared_in_threads_match_as_brute_force_does(monkeypatch):
    """Grids are built in threads, ahead of the lookups: the matches are still
    brute force's over each band-weight group's table, pixel for pixel."""
    import colorps.tables

    phase = 2 * np.pi * np.arange(8) / 8  # a coloured light each: bands of unlike SNR
    hue = 0.5 + 0.5 * np.cos(phase[:, None] - np.array([0.0, 2.0, 4.0]) * np.pi / 3)
    lighting = synth.ring_lights(8, 40, 0.05 + 0.95 * hue)
    scene = synth.smiley_surface(96)
    ball = synth.sphere_surface(72, 32)
    stacks = synth.render(scene, lighting, noise=0.01, seed=1), \
        synth.render(ball, lighting, noise=0.01, seed=2)
    gauge = Gauge.from_sphere((72, 72), 35.5, 35.5, 32)
    result = reconstruct(*stacks, gauge, mask=scene.mask, refine="none")
    assert sum(g.grid_n is not None for g in result.stats.grids) >= 3  # grids of groups
    monkeypatch.setattr(colorps.tables, "BRUTE_FORCE_PIXELS", 10 ** 9)
    brute = reconstruct(*stacks, gauge, mask=scene.mask, refine="none")
    assert all(g.grid_n is None for g in brute.stats.grids)
    np.testing.assert_array_equal(result.solved, brute.solved)
    np.testing.assert_array_equal(result.normals, brute.normals)
    np.testing.assert_array_equal(result.quality, brute.quality)
