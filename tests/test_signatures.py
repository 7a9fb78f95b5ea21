import colour
import numpy as np
import pytest

from colorps import InputError, compute_signatures, light_masks, luminance
from colorps.signatures import NEGATIVE_NOISE


def test_colour_layout_is_band_major(rng):
    stack = rng.uniform(0.1, 1.0, (5, 4, 6, 3)).astype(np.float32)
    sig = compute_signatures(stack, "colour")
    assert sig.signatures.shape == (4, 6, 15) and sig.bands == 3 and sig.images == 5
    for band in range(3):
        ov = stack[:, 2, 3, band]
        np.testing.assert_allclose(sig.signatures[2, 3, 5 * band:5 * band + 5],
                                   ov / np.linalg.norm(ov), rtol=1e-6)
        np.testing.assert_allclose(sig.norms[2, 3, band], np.linalg.norm(ov), rtol=1e-6)
    blocks = sig.signatures.reshape(4, 6, 3, 5)
    np.testing.assert_allclose(np.linalg.norm(blocks, axis=-1), 1.0, rtol=1e-6)
    assert sig.valid.all()


def test_invalid_pixels_are_masked_not_nan(rng):
    stack = rng.uniform(0.1, 1.0, (4, 3, 3, 3)).astype(np.float32)
    stack[:, 0, 0, 1] = 0.0          # one band dark
    stack[:, 1, 1, :] = 0.0          # all dark
    stack[2, 2, 2, 0] = np.nan       # non-finite measurement
    stack[:, 0, 2, 2] = 1e-6         # below min_norm
    sig = compute_signatures(stack, "colour")
    assert np.isfinite(sig.signatures).all()
    expected = np.ones((3, 3), bool)
    expected[0, 0] = expected[1, 1] = expected[2, 2] = expected[0, 2] = False
    np.testing.assert_array_equal(sig.valid, expected)
    assert sig.band_valid[0, 0].tolist() == [True, False, True]
    blocks = sig.signatures.reshape(3, 3, 3, 4)
    assert (blocks[~sig.band_valid] == 0).all()  # invalid band blocks are zero
    np.testing.assert_allclose(np.linalg.norm(blocks[sig.band_valid], axis=-1), 1, rtol=1e-6)
    assert np.isfinite(sig.norms).all()
    assert sig.band_dark[0, 0, 1] and sig.band_dark[1, 1].all() and sig.band_dark[0, 2, 2]
    assert sig.band_invalid_value[2, 2].tolist() == [True, False, False]


def test_clipped_and_negative_measurements(rng):
    stack = rng.uniform(0.1, 0.5, (4, 2, 2, 3)).astype(np.float32)
    stack[1, 0, 0, 0] = 1.0   # saturated red in one image
    stack[2, 1, 1, 2] = -0.2  # negative blue
    sig = compute_signatures(stack, "colour", clip_level=0.99)
    assert sig.band_clipped[0, 0].tolist() == [True, False, False]
    assert sig.band_invalid_value[1, 1].tolist() == [False, False, True]
    assert sig.valid.sum() == 2
    unclipped = compute_signatures(stack, "colour")  # no clip level: nothing clipped
    assert unclipped.band_valid[0, 0].all()
    mono = compute_signatures(stack, "mono", clip_level=0.99)  # luminance mixes bands
    assert not mono.valid[0, 0] and not mono.valid[1, 1] and mono.band_clipped[0, 0, 0]
    green = compute_signatures(stack, "mono", band=1, clip_level=0.99)
    assert green.valid.all()
    with pytest.raises(InputError, match="clip_level"):
        compute_signatures(stack, clip_level=0)


def test_negative_noise_around_a_dark_measurement_is_kept(rng):
    """Linear files with the black level taken off, and renders with noise added,
    hold small negative values where a light does not reach: they are data
    (kept as measured), not invalid; a value far below zero is not noise."""
    stack = rng.uniform(0.2, 0.8, (6, 3, 3, 3)).astype(np.float32)
    stack[2, 0, 0, 0] = -0.01                            # noise around a shadow
    stack[3, 0, 0, 1] = -0.9 * NEGATIVE_NOISE * np.delete(stack[:, 0, 0, 1], 3).max()
    stack[4, 1, 1, 2] = -1.1 * NEGATIVE_NOISE * stack[:, 1, 1, 2].max()  # beyond
    sig = compute_signatures(stack, "colour")
    assert sig.band_valid[0, 0].all() and sig.ov[0, 0, 0, 2] == np.float32(-0.01)
    assert sig.band_invalid_value[1, 1].tolist() == [False, False, True]
    assert light_masks.to_bool(sig.invalid_lights[1, 1], 6).tolist() == \
        [False, False, False, False, True, False]
    assert sig.valid.sum() == 8
    np.testing.assert_allclose(np.linalg.norm(sig.signatures[0, 0].reshape(3, 6), axis=1), 1,
                               rtol=1e-6)


def test_a_box_is_read_in_place_as_its_slice_would_be(rng):
    """``box`` gives the signatures of a box of the stack, bit for bit those of
    the box cut out, without a copy; invalid measurements are flagged per light."""
    stack = rng.uniform(0.0, 1.0, (6, 9, 11, 3)).astype(np.float32)
    stack[2, 4, 5, 1] = np.nan
    stack[4, 4, 5, 0] = -1.0
    stack[1, 6, 3, :] = 2.0
    box = (slice(2, 8), slice(1, 10))
    whole = compute_signatures(stack, "colour", clip_level=1.5, box=box)
    cut = compute_signatures(np.ascontiguousarray(stack[:, box[0], box[1]]), "colour",
                             clip_level=1.5)
    for name in ("ov", "norms", "band_valid", "band_invalid_value", "band_clipped",
                 "band_dark", "clipped_lights", "invalid_lights"):
        np.testing.assert_array_equal(getattr(whole, name), getattr(cut, name), err_msg=name)
    assert int(whole.invalid_lights[2, 4, 0]) == (1 << 2) | (1 << 4)
    assert int(whole.clipped_lights[4, 2, 0]) == 1 << 1
    assert not whole.invalid_lights[whole.band_invalid_value.sum(-1) == 0].any()
    with pytest.raises(InputError, match="step 1"):
        compute_signatures(stack, box=(slice(0, 9, 2), slice(None)))


def test_mono_luminance_matches_colour_science(rng):
    stack = rng.uniform(0.0, 1.0, (3, 5, 5, 3)).astype(np.float32)
    y = colour.RGB_to_XYZ(stack.astype(np.float64), colour.RGB_COLOURSPACES["sRGB"],
                          apply_cctf_decoding=False)[..., 1]
    np.testing.assert_allclose(luminance(stack), y, rtol=1e-5, atol=1e-7)
    sig = compute_signatures(stack, "mono")
    ov = y[:, 1, 2]
    np.testing.assert_allclose(sig.signatures[1, 2], ov / np.linalg.norm(ov), rtol=1e-5)
    assert sig.bands == 1 and sig.signatures.shape == (5, 5, 3)
    wide = compute_signatures(stack, "mono", colourspace="ITU-R BT.2020")
    assert not np.allclose(wide.norms, sig.norms)


def test_mono_channel_and_single_band(rng):
    stack = rng.uniform(0.1, 1.0, (4, 2, 2, 3)).astype(np.float32)
    sig = compute_signatures(stack, "mono", band=2)
    ov = stack[:, 0, 1, 2]
    np.testing.assert_allclose(sig.signatures[0, 1], ov / np.linalg.norm(ov), rtol=1e-6)
    grey = compute_signatures(stack[..., 0], "mono")  # (m, H, W) stack
    assert grey.signatures.shape == (2, 2, 4)


@pytest.mark.parametrize("kwargs, message", [
    (dict(mode="rgb"), "mode"),
    (dict(mode="mono", band=3), "band"),
    (dict(mode="mono", band="green"), "band"),
    (dict(mode="mono", colourspace="nope"), "colourspace"),
    (dict(min_norm=-1.0), "min_norm"),
])
def test_bad_arguments(kwargs, message):
    with pytest.raises(InputError, match=message):
        compute_signatures(np.ones((3, 2, 2, 3), np.float32), **kwargs)


def test_bad_stacks():
    with pytest.raises(InputError, match="shape"):
        compute_signatures(np.ones((3, 2)))
    with pytest.raises(InputError, match="empty"):
        compute_signatures(np.ones((0, 2, 2, 3)))


def test_table_resolution_matches_brute_force():
    from colorps.residuals import table_resolution

    rng = np.random.default_rng(4)
    sig = rng.normal(size=(9, 11, 2, 5)).astype(np.float32)
    usable = rng.random((9, 11)) < 0.7
    expected = np.zeros((9, 11, 2))
    for y in range(9):
        for x in range(11):
            steps = [((sig[y, x] - sig[ny, nx]).astype(np.float64) ** 2).sum(axis=-1)
                     for ny, nx in ((y - 1, x), (y + 1, x), (y, x - 1), (y, x + 1))
                     if 0 <= ny < 9 and 0 <= nx < 11 and usable[y, x] and usable[ny, nx]]
            if steps:
                expected[y, x] = np.mean(steps, axis=0)
    np.testing.assert_allclose(table_resolution(sig, usable), expected, rtol=1e-6)


def test_table_resolution_of_ovs_over_a_light_subset_is_that_of_their_unit_signatures():
    from colorps.residuals import table_resolution

    rng = np.random.default_rng(5)
    ov = rng.random((9, 11, 2, 6)).astype(np.float32)
    ov[2, 3, 1] = 0.0  # a zero OV stays zero
    usable = rng.random((9, 11)) < 0.7
    lights = [0, 2, 3, 5]
    sub = ov[..., lights].astype(np.float64)
    norm2 = (sub ** 2).sum(axis=-1)
    unit = np.divide(sub, np.sqrt(norm2)[..., None], out=np.zeros_like(sub),
                     where=norm2[..., None] > 0).astype(np.float32)
    rows = np.array([0, 14, 25, 98])
    out = np.zeros((99, 2))
    got = table_resolution(ov, usable, rows, out, lights=lights, norm2=norm2)
    np.testing.assert_allclose(got[rows], table_resolution(unit, usable)
                               .reshape(-1, 2)[rows], rtol=1e-5, atol=1e-12)
    assert not got[np.setdiff1d(np.arange(99), rows)].any()  # only ``rows`` written
