import numpy as np
import pytest

from colorps import compute_signatures, synth


def sphere_table(m, theta, colour, radius=40, seed=1):
    """Signature table of a Lambertian sphere gauge (mono: 1 band; colour: RGB lights)."""
    bands = 3 if colour else 1
    colours = np.random.default_rng(seed).uniform(0.2, 1.0, (m, 3)) if colour else None
    lights = synth.ring_lights(m, theta, colours, bands=bands)
    gauge = synth.sphere_surface(2 * radius + 4, radius, bands=bands)
    sig = compute_signatures(synth.render(gauge, lights), "colour")
    return sig.signatures[sig.valid & gauge.mask]


@pytest.fixture(scope="session")
def rng():
    return np.random.default_rng(12345)
