import os
import sys

if "PYTEST_XDIST_WORKER" in os.environ:  # (before numba is imported)
    # Test processes share the cores (pyproject's -n auto): numba's threads wait
    # asleep, not spinning, and each process keeps at least 2 (races still show).
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    _workers = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
    os.environ.setdefault("NUMBA_NUM_THREADS", str(max(2, (os.cpu_count() or 2) // _workers)))

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from colorps import compute_signatures, synth  # noqa: E402


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


def long_run_command(folder):
    """A CLI run of several seconds (700 px scene, r = 150 gauge) and its output folder."""
    data = folder / "big"
    synth.write_synthetic(data, size=700, images=8, gauge_radius=150)
    out = folder / "out"
    return [sys.executable, "-m", "colorps.cli", "reconstruct", "--scene",
            str(data / "scene_*.exr"), "--gauge", str(data / "gauge_*.exr"), "--sphere", "auto",
            "--out", str(out), "--quiet", "--mesh", "both"], out
