"""Isolated spikes (fireflies, hot pixels) in a gauge's and a scene's images."""

import importlib
import warnings

import numpy as np
import pytest

from colorps import Gauge, angular_error, reconstruct, synth
from colorps.errors import GaugeWarning
from colorps.finishes import Gloss
from colorps.shapes import dome_lights, folds_surface
from colorps.spikes import replace_spikes


def spiked(stack, rate, seed):
    """``stack`` with ``rate`` of its (image, pixel) measurements 3 to 30 times
    brighter plus 0.05, as a path tracer's fireflies; and where."""
    rng = np.random.default_rng(seed)
    hit = rng.random(stack.shape[:3]) < rate
    gain = rng.uniform(3.0, 30.0, stack.shape[:3])
    out = stack.copy()
    out[hit] = out[hit] * gain[hit][:, None] + 0.05
    return out, hit


@pytest.fixture(scope="module")
def gauge_capture():
    lights = dome_lights(32)
    gauge = Gauge.from_sphere((90, 90), 44.5, 44.5, 40)
    ball = synth.sphere_surface(90, 40)
    plain = synth.render(ball, lights, noise=0.003, seed=2)
    glossy = synth.render(ball, lights, noise=0.003, seed=2, gloss=Gloss(0.5, "ggx", alpha=0.3))
    return lights, gauge, plain, glossy


def test_spikes_are_found_and_nothing_else(gauge_capture):
    """Most fireflies on the sphere are replaced by their neighbours' median;
    a clean gauge, matte or glossy, comes back as it is (the same array)."""
    _, gauge, plain, glossy = gauge_capture
    for clean in (plain, glossy):
        same, count = replace_spikes(clean, gauge.mask)
        assert count == 0 and same is clean
    images, hit = spiked(plain, 0.01, 3)
    repaired, count = replace_spikes(images, gauge.mask)
    changed = (repaired != images).any(axis=-1)
    inside = hit[:, gauge.mask]
    assert count > 0 and not (changed[:, gauge.mask] & ~inside).any()  # nothing else
    assert (changed[:, gauge.mask] & inside).sum() > 0.8 * inside.sum()
    back = np.abs(repaired - plain)[changed & hit & gauge.mask].max(axis=-1)
    assert np.mean(back < 0.05) > 0.95  # the shading back (but next to another spike)
    assert np.array_equal(images[:, ~gauge.mask], repaired[:, ~gauge.mask])


def test_fireflies_in_gauge_and_scene(gauge_capture, monkeypatch):
    """1 % of the measurements of the gauge and of the scene spiked: the run
    replaces the gauge's (and says so) and leaves the scene's out of each
    pixel's first guess; it had come out several degrees off."""
    lights, gauge, plain, _ = gauge_capture
    scene = folds_surface(96)
    stack = synth.render(scene, lights, noise=0.003, seed=1, cast_shadows=True)
    scene_spiked, _ = spiked(stack, 0.01, 1)
    gauge_spiked, _ = spiked(plain, 0.01, 2)

    def error(scene_stack, gauge_stack):
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            result = reconstruct(scene_stack, gauge_stack, gauge, mask=scene.mask)
        errors = np.where(result.solved, angular_error(result.normals, scene.normals), 90.0)
        return float(errors[scene.mask].mean()), result, said

    clean, _, _ = error(stack, plain)
    fixed, result, said = error(scene_spiked, gauge_spiked)
    assert fixed < 2.0 * clean + 0.1, (fixed, clean)
    assert result.stats.gauge_spikes_replaced > 0
    assert any(issubclass(w.category, GaugeWarning) and "spikes" in str(w.message)
               for w in said)
    shadows = importlib.import_module("colorps.shadows")
    monkeypatch.setattr(shadows, "SPIKE_LIMIT", np.inf)
    monkeypatch.setattr(shadows, "BRIGHT_RANK", 1)
    reconstruct_module = importlib.import_module("colorps.reconstruct")
    monkeypatch.setattr(reconstruct_module, "replace_spikes", lambda stack, mask: (stack, 0))
    before, _, _ = error(scene_spiked, gauge_spiked)
    assert before > 3.0 * fixed + 1.0, (before, fixed)


def test_neighbour_medians_against_brute_force():
    """The kernel's median of each measurement's 8 neighbours (the border's
    nearest pixels standing in beyond it) against numpy's."""
    from colorps import _spike_kernels

    values = np.random.default_rng(0).random((2, 7, 9, 2)).astype(np.float32)
    out = np.empty_like(values)
    _spike_kernels.neighbour_medians(values, out)
    padded = np.pad(values, ((0, 0), (1, 1), (1, 1), (0, 0)), mode="edge")
    for y in range(7):
        for x in range(9):
            ring = np.delete(padded[:, y:y + 3, x:x + 3].reshape(2, 9, 2), 4, axis=1)
            np.testing.assert_allclose(out[:, y, x], np.median(ring, axis=1), rtol=1e-6)
