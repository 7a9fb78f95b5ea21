"""The reflectance models of the synthetic renders (colorps.finishes)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from colorps import InputError
from colorps.finishes import Gloss, gloss_shape, oren_nayar, oren_nayar_factor


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@pytest.fixture(scope="module")
def normals():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(400, 3))
    n[:, 2] = np.abs(n[:, 2]) + 0.3
    return _unit(n)


def _ggx_by_hand(n, light, view, f0, alpha):
    """Cook-Torrance with GGX, Smith and Schlick, one point at a time, times pi cos."""
    out = []
    for normal in n:
        cos_l, cos_v = normal @ light, normal @ view
        if cos_l <= 0:
            out.append(0.0)
            continue
        half = _unit(light + view)
        cos_h = normal @ half
        d = alpha ** 2 / (np.pi * ((alpha ** 2 - 1) * cos_h ** 2 + 1) ** 2)

        def g1(c):
            return 2 * c / (c + np.sqrt(alpha ** 2 + (1 - alpha ** 2) * c * c))

        fresnel = f0 + (1 - f0) * (1 - light @ half) ** 5
        out.append(np.pi * d * fresnel * g1(cos_l) * g1(cos_v) / (4 * cos_l * cos_v) * cos_l)
    return np.array(out)


@pytest.mark.parametrize("alpha", [0.1, 0.3, 0.6])
def test_ggx_lobe_is_cook_torrance(normals, alpha):
    light = _unit([0.4, -0.2, 0.9])
    shape = gloss_shape(normals, light, Gloss(0.04, "ggx", alpha=alpha))
    expected = _ggx_by_hand(normals, light, np.array([0.0, 0.0, 1.0]), 0.04, alpha)
    np.testing.assert_allclose(shape, expected, rtol=1e-9, atol=1e-12)


def test_per_pixel_views(normals):
    """Views along +z are the default; each pixel's own view is used, and turning
    normals, light and view together changes nothing (the models are isotropic)."""
    light = _unit([0.3, 0.5, 0.8])
    views = _unit(np.column_stack([np.linspace(-0.2, 0.2, len(normals)),
                                   np.linspace(0.15, -0.1, len(normals)),
                                   np.ones(len(normals))]))
    gloss = Gloss(0.5, "ggx", alpha=0.3)
    plus_z = np.tile([0.0, 0.0, 1.0], (len(normals), 1))
    np.testing.assert_array_equal(gloss_shape(normals, light, gloss, plus_z),
                                  gloss_shape(normals, light, gloss))
    by_hand = [_ggx_by_hand(n[None], light, v, 0.5, 0.3)[0] for n, v in zip(normals, views)]
    np.testing.assert_allclose(gloss_shape(normals, light, gloss, views), by_hand, rtol=1e-9)
    turn = Rotation.from_euler("xyz", [12.0, -7.0, 30.0], degrees=True).as_matrix()
    for model in (lambda n, l, v: gloss_shape(n, l, gloss, v),
                  lambda n, l, v: oren_nayar_factor(n, l, 0.4, v)[0]):
        np.testing.assert_allclose(model(normals @ turn.T, turn @ light, views @ turn.T),
                                   model(normals, light, views), rtol=1e-9, atol=1e-12)


def test_oren_nayar_is_lambert_when_smooth_and_brighter_back_towards_the_light(normals):
    light = _unit([0.6, 0.0, 0.8])
    np.testing.assert_allclose(oren_nayar(normals, light, 0.0),
                               np.maximum(normals @ light, 0.0), atol=1e-12)
    # A point tilted towards the light and the view: retro-reflection lifts it
    # above the smooth model's A (the factor of points facing the view).
    tilted = _unit([[0.7, 0.0, 0.7]])
    assert oren_nayar_factor(tilted, light, 0.4)[0, 0] > oren_nayar_factor(
        np.array([[0.0, 0.0, 1.0]]), light, 0.4)[0, 0]


def test_bad_gloss_is_refused():
    with pytest.raises(InputError, match="gloss model"):
        Gloss(0.1, "phong")
    with pytest.raises(InputError, match="0 < alpha <= 1"):
        Gloss(0.1, "ggx", alpha=0.0)
