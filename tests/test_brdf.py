"""The fitted finish of virtual gauges, and light masks wider than 64 images."""

import numpy as np
import pytest

from colorps import Gauge, InputError, Lights, Options, angular_error, light_masks, reconstruct
from colorps import synth
from colorps.brdf import BRDF, DIFFUSE_KNOTS
from colorps.brdf_fit import fit_brdf
from colorps.options import FLOAT_DARK_LEVEL
from colorps.resolve import StackModel, resolve
from colorps.virtual import fit_scene_brdf

#: A glossy finish: darker than cosine at grazing incidence, a sharp highlight
#: tinted by the albedo and stronger in blue than in red.
GLOSSY = BRDF(falloff=(0.85, 0.86, 0.88, 0.91, 0.95, 0.98, 1.0, 1.0),
              specular=(0.02, 0.03, 0.04), alpha=0.08)


@pytest.fixture(scope="module")
def lights():
    low = synth.ring_lights(8, 55.0)
    high = synth.ring_lights(8, 25.0, azimuth0_deg=22.5)
    directions = np.concatenate([low.directions[:, 0], high.directions[:, 0]])
    colours = np.random.default_rng(3).uniform(0.7, 1.0, (16, 3))
    return Lights(directions, colours)


def _render(surface, lights, brdf, noise=0.0, seed=0):
    stack = np.zeros((lights.images, *surface.mask.shape, 3), dtype=np.float32)
    values = brdf.shade(surface.normals[surface.mask], lights.directions, lights.intensities)
    stack[:, surface.mask] = values * surface.albedo[surface.mask][None]
    if noise:
        stack += np.random.default_rng(seed).normal(0.0, noise, stack.shape).astype(np.float32)
        np.maximum(stack, 0.0, out=stack)
    return stack


def test_lambert_shading_is_the_cosine(lights):
    normals = synth.sphere_surface(41, 18).normals.reshape(-1, 3)
    expected = np.maximum(normals @ lights.directions.T, 0.0).T[..., None] * \
        lights.intensities[:, None, :]
    np.testing.assert_allclose(BRDF.lambert().shade(normals, lights.directions,
                                                    lights.intensities), expected, atol=1e-12)
    assert BRDF.lambert().is_lambert and not GLOSSY.is_lambert


def test_fit_recovers_a_known_finish(lights):
    ball = synth.sphere_surface(61, 28, bands=3)
    inside = ball.mask
    rng = np.random.default_rng(1)
    albedo = rng.uniform(0.3, 0.9, (int(inside.sum()), 3))  # per-pixel colour
    observed = GLOSSY.shade(ball.normals[inside], lights.directions,
                            lights.intensities) * albedo[None]
    usable = observed > 1e-6
    fitted, rms = fit_brdf(observed, ball.normals[inside], lights.directions,
                           lights.intensities, usable)
    assert rms < 0.02
    np.testing.assert_allclose(fitted.falloff[1:], GLOSSY.falloff[1:], atol=0.03)
    np.testing.assert_allclose(fitted.specular, GLOSSY.specular, rtol=0.3)
    assert 0.06 <= fitted.alpha <= 0.11 and not fitted.white_highlight


def test_fit_recovers_a_rough_finish(lights):
    """An Oren-Nayar surface (sigma 0.3, rendered by colorps.finishes) at its true
    normals: the fit finds its roughness and leaves the falloff at Lambert."""
    from colorps.finishes import oren_nayar

    ball = synth.sphere_surface(61, 28, bands=3)
    normals = ball.normals[ball.mask]
    albedo = np.random.default_rng(2).uniform(0.3, 0.9, (len(normals), 3))
    shape = np.stack([oren_nayar(normals, d, 0.3) for d in lights.directions])
    observed = shape[..., None] * lights.intensities[:, None, :] * albedo[None]
    fitted, rms = fit_brdf(observed, normals, lights.directions, lights.intensities,
                           observed > 1e-6)
    assert fitted.roughness == 0.3 and rms < 1e-3
    # (the knot at cosine 0.1, lit in few measurements, within 0.03)
    np.testing.assert_allclose(fitted.falloff[1:], 1.0, atol=0.035)
    assert max(fitted.specular) < 1e-3
    assert BRDF.from_dict(fitted.as_dict()) == fitted


def test_fit_of_a_matte_finish_is_lambert(lights):
    ball = synth.sphere_surface(41, 18, bands=3)
    observed = BRDF.lambert().shade(ball.normals[ball.mask], lights.directions,
                                    lights.intensities) * 0.5
    fitted, rms = fit_brdf(observed, ball.normals[ball.mask], lights.directions,
                           lights.intensities, observed > 1e-6)
    assert rms < 1e-3
    np.testing.assert_allclose(fitted.falloff[1:], 1.0, atol=0.01)
    assert max(fitted.specular) < 1e-3 and fitted.roughness == 0.0


def test_fitted_virtual_gauge_beats_lambert_on_a_glossy_scene(lights):
    scene = synth.smiley_surface(96)
    stack = _render(scene, lights, GLOSSY, noise=0.002)
    options = Options(read_noise=0.002, gain=0.0)
    rendered = resolve(options, gauge=StackModel.rendered(FLOAT_DARK_LEVEL))

    def error(brdf):
        gauge = Gauge.virtual(lights, radius=60, bands=3, brdf=brdf)
        result = reconstruct(stack, gauge.stack, gauge, rendered, max_residual=None,
                             mask=scene.mask)
        solved = result.solved & scene.mask
        assert solved.sum() > 0.98 * scene.mask.sum()
        return float(np.mean(angular_error(result.normals[solved], scene.normals[solved])))

    brdf, history = fit_scene_brdf(stack, lights, options, mask=scene.mask, radius=60)
    # (the second fit's own residual as low as the first's, within 1 %)
    assert len(history) == 2 and history[-1]["rms_relative"] <= 1.01 * history[0]["rms_relative"]
    assert history[-1]["kept"]
    assert history[-1]["match_residual_median"] < history[0]["match_residual_median"]
    lambert, fitted, truth = error(BRDF.lambert()), error(brdf), error(GLOSSY)
    assert fitted < 0.5 * lambert
    assert fitted < truth + 0.4  # close to the gauge rendered with the true finish


def test_a_strong_ggx_coat_is_fitted_and_kept(lights, monkeypatch):
    """A finish rendered by another model (a white GGX microfacet coat of alpha
    0.3 over a coloured base, :mod:`colorps.finishes`): the fit is kept because
    it matches better in noise units (the run-scaled median is about 1 for every
    finish and once dropped every fit), and the normals are several times
    closer than a Lambertian virtual gauge's. Past FIT_MATCH_PIXELS masked
    pixels the fit's rounds match a random sample of them: 2,000 of the 7,000
    give a fit kept too, and normals as close."""
    import colorps.virtual as virtual
    from colorps.finishes import Gloss

    scene = synth.smiley_surface(96)
    lighting = synth.Lighting(lights.directions[:, None], lights.intensities[:, None])
    stack = synth.render(scene, lighting, gloss=Gloss(0.5, "ggx", alpha=0.3), noise=0.002)
    options = Options(read_noise=0.002, gain=0.0)
    brdf, history = fit_scene_brdf(stack, lights, options, mask=scene.mask, radius=60)
    assert history[-1]["kept"] and not brdf.is_lambert
    assert history[-1]["match_residual_median"] < 0.5 * history[0]["match_residual_median"]
    monkeypatch.setattr(virtual, "FIT_MATCH_PIXELS", 2000)
    assert scene.mask.sum() > 3 * 2000
    sampled, history = fit_scene_brdf(stack, lights, options, mask=scene.mask, radius=60)
    assert history[-1]["kept"] and not sampled.is_lambert
    rendered = resolve(options, gauge=StackModel.rendered(FLOAT_DARK_LEVEL))
    errors = {}
    for name, finish in (("lambert", BRDF.lambert()), ("fitted", brdf), ("sampled", sampled)):
        gauge = Gauge.virtual(lights, radius=60, bands=3, brdf=finish)
        result = reconstruct(stack, gauge.stack, gauge, rendered, mask=scene.mask)
        errors[name] = float(np.mean(angular_error(result.normals[scene.mask],
                                                   scene.normals[scene.mask])))
    assert errors["fitted"] < 0.35 * errors["lambert"], errors
    assert errors["sampled"] < errors["fitted"] + 0.1, errors


def test_a_coats_transmission_is_its_microfacet_btdfs_integral():
    """coat_transmission (an average over the coat's facets) against Walter et
    al.'s rough-dielectric BTDF summed over a fine grid of refracted directions."""
    from colorps.brdf import COAT_INDEX, FRESNEL_F0, coat_transmission

    alpha, steps = 0.4, 1000
    a2 = alpha * alpha
    depth = (np.arange(steps) + 0.5) / steps  # -z of the refracted ray
    turn = (np.arange(2 * steps) + 0.5) * np.pi / steps
    depth, turn = (a.ravel() for a in np.meshgrid(depth, turn, indexing="ij"))
    out = np.stack([np.sqrt(1 - depth ** 2) * np.cos(turn),
                    np.sqrt(1 - depth ** 2) * np.sin(turn), -depth], axis=1)

    def masking(cosine):
        return 2 * cosine / (cosine + np.sqrt(a2 + (1 - a2) * cosine ** 2))

    cosines = np.array([0.02, 0.2, 0.5, 0.8, 1.0])
    shares = []
    for cosine in cosines:
        light = np.array([np.sqrt(1 - cosine ** 2), 0.0, cosine])
        half = -(light + COAT_INDEX * out)
        half *= (np.sign(half[:, 2]) / np.linalg.norm(half, axis=1))[:, None]
        lh, oh = half @ light, np.einsum("ij,ij->i", out, half)
        facets = a2 / (np.pi * (half[:, 2] ** 2 * (a2 - 1) + 1) ** 2)
        crossing = 1 - FRESNEL_F0 - (1 - FRESNEL_F0) * (1 - np.clip(lh, 0, 1)) ** 5
        btdf = np.abs(lh * oh) / (cosine * depth) * COAT_INDEX ** 2 * crossing * \
            masking(cosine) * masking(depth) * facets / (lh + COAT_INDEX * oh) ** 2
        valid = (lh > 0) & (oh < 0)
        shares.append(np.where(valid, btdf * depth, 0.0).sum() * np.pi / steps ** 2)
    expected = np.array(shares) / shares[-1]
    got = coat_transmission(cosines, alpha)
    assert np.abs(got - expected).max() < 0.01, (got, expected)
    assert got[0] < 0.7  # a real loss at grazing incidence


def test_a_coat_the_held_finish_lacks_darkens_its_falloff_and_the_reverse():
    from colorps.brdf import coat_transmission

    coat = BRDF(specular=(0.05,), alpha=0.3, white_highlight=True)
    matte = BRDF(falloff=(0.9, 0.92, 0.94, 0.95, 0.97, 0.98, 1.0, 1.0))
    coated = coat.coat_adjusted(matte)
    expected = np.array(matte.falloff) * coat_transmission(DIFFUSE_KNOTS, 0.3)
    assert np.allclose(coated.falloff, expected) and coated.specular == coat.specular
    assert coat.coat_adjusted(coat) is None  # the held falloff has this coat's loss
    assert BRDF(specular=(0.05,), alpha=0.3).coat_adjusted(matte) is None  # tinted: no coat
    uncoated = matte.coat_adjusted(coated)  # a matte scene on a coated gauge: the reverse
    assert np.allclose(uncoated.falloff, matte.falloff) and not any(uncoated.specular)


def test_bad_brdf_values_are_refused():
    with pytest.raises(InputError, match="falloff needs 8 values"):
        BRDF(falloff=(1.0, 1.0))
    with pytest.raises(InputError, match="finite and >= 0"):
        BRDF(specular=(-0.1,))
    with pytest.raises(InputError, match="brdf: expected 'fitted' or 'lambert'"):
        Options(brdf="phong")
    assert len(DIFFUSE_KNOTS) == len(BRDF().falloff)


@pytest.mark.parametrize("m", [5, 64, 65, 96, 130])
def test_light_masks_round_trip(m):
    rng = np.random.default_rng(m)
    flags = rng.random((7, 3, m)) < 0.2
    masks = light_masks.from_bool(flags)
    assert masks.shape == (7, 3, light_masks.words(m)) and masks.dtype == np.uint64
    np.testing.assert_array_equal(light_masks.to_bool(masks, m), flags)
    np.testing.assert_array_equal(light_masks.count(masks), flags.sum(axis=-1))
    np.testing.assert_array_equal(light_masks.is_empty(masks), ~flags.any(axis=-1))
    picked = tuple(int(i) for i in np.flatnonzero(flags[2, 1]))
    assert light_masks.lights(masks[2, 1]) == picked
    np.testing.assert_array_equal(light_masks.of_lights(picked, m), masks[2, 1])


def test_many_sets_of_clipped_lights_do_not_make_a_table_each():
    """24 lights, the scene overexposed so that each pixel clips under its own
    few lights: hundreds of distinct clipped sets, solved by the per-pixel fit
    with those lights left out (the few it cannot solve: on a table of their own
    set), not by a table per set."""
    lighting = synth.ring_lights(24, 40.0)
    scene = synth.smiley_surface(64)
    ball = synth.sphere_surface(81, 38)
    stack = synth.render(scene, lighting, noise=0.001, seed=4) * 1.6  # the scene overexposed
    gauge_stack = synth.render(ball, lighting, noise=0.001, seed=5)
    clipped = (stack >= 1.0).any(axis=-1) & scene.mask  # (m, H, W)
    stack, gauge_stack = np.minimum(stack, 1.0), np.minimum(gauge_stack, 1.0)
    sets = {tuple(np.flatnonzero(clipped[:, y, x])) for y, x in zip(*np.nonzero(clipped.any(0)))}
    assert len(sets) > 100  # a table each made 243 tables (3.5 s)
    result = reconstruct(stack, gauge_stack, Gauge.from_sphere((81, 81), 40, 40, 38),
                         mask=scene.mask, clip_level=1.0, read_noise=0.001, gain=0.0)
    hit = clipped.any(axis=0)
    assert result.solved[hit].all()
    assert sum(1 for g in result.stats.grids if g.lights_dropped) < len(sets) / 4
    errors = angular_error(result.normals[hit], scene.normals[hit])
    assert np.median(errors) < 0.15 and errors.mean() < 0.6


def test_clipped_lights_past_64_images_are_dropped_not_refused():
    m = 72
    lighting = synth.ring_lights(m, 45.0)
    scene = synth.smiley_surface(48)
    ball = synth.sphere_surface(81, 38)
    stack = synth.render(scene, lighting)
    stack[68] *= 4.0  # image 68 saturates over much of the scene
    clipped = (stack[68] >= 1.0).all(axis=-1) & scene.mask
    assert clipped.sum() > 50
    stack = np.minimum(stack, 1.0)
    result = reconstruct(stack, synth.render(ball, lighting),
                         Gauge.from_sphere((81, 81), 40, 40, 38), mask=scene.mask,
                         clip_level=1.0, read_noise=0.001, gain=0.0)
    assert result.solved[clipped].all()
    dropped = light_masks.to_bool(result.dropped_lights[clipped], m)
    assert dropped[:, 68].all() and dropped.sum(axis=1).max() <= 2
    errors = angular_error(result.normals[clipped], scene.normals[clipped])
    assert np.median(errors) < 1.0


def test_scene_fit_without_matches_says_why(lights):
    dark = np.zeros((lights.images, 16, 16, 3), dtype=np.float32)
    with pytest.raises(InputError, match="no scene pixel matched the virtual gauge"):
        fit_scene_brdf(dark, lights, Options(read_noise=0.001, gain=0.0), radius=20)


def test_too_few_images_stay_lambertian(lights):
    few = Lights(lights.directions[:4], lights.intensities[:4])
    scene = synth.smiley_surface(48)
    stack = _render(scene, few, GLOSSY)
    with pytest.warns(UserWarning, match="4 images are too few"):
        brdf, history = fit_scene_brdf(stack, few, Options(read_noise=0.001, gain=0.0),
                                       mask=scene.mask, radius=30)
    assert brdf.is_lambert and history == []


def test_lights_exr_holds_every_image_exactly(tmp_path):
    from colorps.io import read_image
    from colorps.outputs import _write_light_channels

    m = 40
    flags = np.random.default_rng(7).random((5, 6, m)) < 0.3
    _write_light_channels(tmp_path / "lights.exr", light_masks.from_bool(flags), m)
    channels, names = read_image(tmp_path / "lights.exr")
    assert names == ["L0-15", "L16-31", "L32-39"]
    bits = channels.astype(np.int64)
    back = np.concatenate([(bits[..., j:j + 1] >> np.arange(16)) & 1 for j in range(3)],
                          axis=-1)[..., :m]
    np.testing.assert_array_equal(back.astype(bool), flags)


@pytest.mark.parametrize("white", [False, True])
def test_compiled_fit_passes_are_the_plain_formulas(white):
    """The BRDF fit's compiled passes against their numpy statement, for a highlight
    tinted by the albedo and for a white one."""
    from colorps import _brdf_kernels as kernels

    rng = np.random.default_rng(7)
    m, n, c, k = 9, 300, 3, len(DIFFUSE_KNOTS)  # more pixels than one chunk
    obs = rng.uniform(0, 1, (m, n, c))
    weight = np.where(rng.uniform(size=(m, n, c)) < 0.2, 0.0, rng.uniform(0.5, 2, (m, n, c)))
    # The diffuse hats times a per-measurement factor (Oren-Nayar's): two
    # neighbouring knots of K at most are not zero, and none under no light.
    from colorps.brdf_fit import _hats
    cosine = np.clip(rng.uniform(-0.3, 1, (m, n)), 0, 1)
    basis = _hats(cosine) * rng.uniform(0.5, 1.5, (m, n, 1))
    lobe = rng.uniform(0, 1, (m, n))
    falloff, specular = rng.uniform(0.5, 1, k), rng.uniform(0, 0.1, c)
    robust = rng.uniform(0.2, 1, (m, n, c))
    diffuse = (basis @ falloff)[..., None]
    highlight = lobe[..., None] * specular
    wr = weight * robust
    albedo = np.empty((n, c))
    data = dict(obs=obs, weight=weight, basis=basis, lobe=lobe, falloff=falloff,
                specular=specular, white=white)
    kernels.fit_albedo(robust=robust, albedo=albedo, **data)
    shape, target = (diffuse, obs - highlight) if white else (diffuse + highlight, obs)
    assert np.allclose(albedo, (wr * shape * target).sum(0) / (wr * shape ** 2).sum(0))
    tint = 1.0 if white else albedo
    model = albedo * diffuse + tint * highlight
    relative = np.empty_like(obs)
    kernels.relative_residuals(albedo=albedo, out=relative, **data)
    expected_relative = (obs - model) * np.sqrt(weight)
    assert np.allclose(relative, expected_relative)
    threshold = np.median(np.abs(expected_relative[weight > 0]))
    normal, right = np.empty((k - 1 + c,) * 2), np.empty(k - 1 + c)
    loss, total = kernels.huber_normal_equations(robust=robust, albedo=albedo,
                                                 threshold=threshold, normal=normal,
                                                 right=right, **data)
    size = np.abs(expected_relative)
    factor = np.where(size <= threshold, 1.0, threshold / np.maximum(size, 1e-30))
    assert np.allclose(robust, factor)
    assert np.isclose(loss, np.where(size <= threshold, size ** 2,
                                     2 * threshold * size - threshold ** 2).sum())
    # Least squares in x = (falloff[:-1], specular), albedo fixed: rows of the design.
    w = weight * factor
    assert np.isclose(total, w.sum())
    design = np.concatenate([np.repeat(basis[..., None, :-1], c, axis=2) * albedo[..., None],
                             np.eye(c)[None, None] * (lobe[..., None, None] *
                                                      np.broadcast_to(tint, (n, c))[..., None])],
                            axis=-1)
    target = obs - basis[..., -1:] * albedo
    rows, ws = design.reshape(-1, k - 1 + c), w.reshape(-1)
    assert np.allclose(normal, (rows * ws[:, None]).T @ rows)
    assert np.allclose(right, (rows * ws[:, None]).T @ target.reshape(-1))


def test_white_strength_is_the_least_squares_with_the_albedos():
    """The white highlight's one strength, each pixel's albedo fitted beside it:
    against a brute-force least squares over (every albedo, the strength)."""
    from colorps import _brdf_kernels as kernels
    from colorps.brdf_fit import _hats

    rng = np.random.default_rng(8)
    m, n, c, k = 7, 150, 2, len(DIFFUSE_KNOTS)
    basis = _hats(np.clip(rng.uniform(-0.2, 1, (m, n)), 0, 1))
    lobe = rng.uniform(0, 1, (m, n))
    falloff = rng.uniform(0.5, 1, k)
    obs = rng.uniform(0, 1, (m, n, c))
    weight = rng.uniform(0.5, 2, (m, n, c))
    robust = rng.uniform(0.2, 1, (m, n, c))
    specular = np.zeros(c)
    kernels.white_strength(obs=obs, weight=weight, robust=robust, basis=basis, lobe=lobe,
                           falloff=falloff, specular=specular)
    # Unknowns: the n * c albedos, then the strength; rows: every measurement.
    diffuse = basis @ falloff  # (m, n)
    rows = np.zeros((m, n, c, n * c + 1))
    for p in range(n):
        for b in range(c):
            rows[:, p, b, p * c + b] = diffuse[:, p]
    rows[..., -1] = lobe[..., None]
    root = np.sqrt(weight * robust).reshape(-1, 1)
    solution = np.linalg.lstsq(rows.reshape(-1, n * c + 1) * root,
                               obs.reshape(-1, 1) * root, rcond=None)[0]
    np.testing.assert_allclose(specular, max(solution[-1, 0], 0.0), rtol=1e-9)


def test_a_dropped_finish_is_said(lights, monkeypatch, capsys):
    """A fit that matches no better than Lambert is dropped, and the console says so."""
    import colorps.virtual as virtual

    rounds = iter([1.00, 1.01])  # the median residual of each round's starting gauge

    def fake_round(data, lights, brdf, quick, mask, radius, rng, settle_rounds, *held):
        return BRDF(specular=(0.1,), alpha=0.3), dict(pixels=1, rms_relative=0.1,
                                                      match_residual_median=next(rounds))

    monkeypatch.setattr(virtual, "_fit_round", fake_round)
    stack = np.ones((len(lights.directions), 4, 4, 1), dtype=np.float32)
    brdf, history = fit_scene_brdf(stack, lights, Options(read_noise=0.001, gain=0.0),
                                   fits=2, progress=True)
    err = capsys.readouterr().err
    assert brdf == BRDF.lambert() and history[-1]["kept"] is False
    assert "dropped" in err and "1.01 vs 1.00" in err


def test_a_rough_scene_is_fitted_from_a_lambertian_start(lights, monkeypatch):
    """An Oren-Nayar scene (sigma 0.3) matched first against a Lambertian gauge
    has normals tilted by degrees; a falloff fitted at them takes up the tilt
    and the fit stays near it (sigma 0.2, 2.7 degrees mean error here). Holding
    the falloff at Lambert's in the first fit's first rounds finds the
    roughness: 0.57 degrees (the true finish: 0.12; the second fit's free
    falloff takes up part of the tilt again)."""
    import colorps.virtual as virtual

    scene = synth.smiley_surface(96)
    stack = synth.render(scene, lights.as_lighting(3), brdf="oren-nayar", roughness=0.3,
                         noise=0.002, seed=1)
    options = Options(read_noise=0.002, gain=0.0)
    rendered = resolve(options, gauge=StackModel.rendered(FLOAT_DARK_LEVEL))

    def error(brdf):
        gauge = Gauge.virtual(lights, radius=60, bands=3, brdf=brdf)
        result = reconstruct(stack, gauge.stack, gauge, rendered, mask=scene.mask)
        solved = result.solved & scene.mask
        return float(np.mean(angular_error(result.normals[solved], scene.normals[solved])))

    # (The simpler finishes compared after the fit would rescue the free one too:
    # left out here, to see the settling alone.)
    monkeypatch.setattr(virtual, "_simpler_finishes", lambda brdf, held=None: [brdf])
    settled, _ = fit_scene_brdf(stack, lights, options, mask=scene.mask, radius=60)
    monkeypatch.setattr(virtual, "SETTLE_ROUNDS", 0)
    free, _ = fit_scene_brdf(stack, lights, options, mask=scene.mask, radius=60)
    assert settled.roughness == 0.3 and free.roughness != 0.3
    assert error(settled) < 0.3 * error(free)
    monkeypatch.undo()
    monkeypatch.setattr(virtual, "SETTLE_ROUNDS", 0)
    rescued, _ = fit_scene_brdf(stack, lights, options, mask=scene.mask, radius=60)
    assert abs(rescued.roughness - 0.3) < 0.01 and error(rescued) < 0.3 * error(free)


def test_over_relaxed_rounds_leave_the_falloff_tilt_valley(lights, monkeypatch):
    """An Oren-Nayar scene (sigma 0.3) at the normals a Lambertian gauge matches
    (4 degrees off): fitting the finish and refining the normals in turn creeps
    along the valley where a darker falloff at grazing stands in for tilted
    normals (falloff 0.49 at grazing, 0.97 degrees mean error with plain steps).
    Over-relaxed steps reach the true finish (falloff 1, sigma 0.3) and its
    normals (0.12 degrees, what the true finish gives)."""
    import colorps.brdf_fit as brdf_module

    scene = synth.smiley_surface(96)
    stack = synth.render(scene, lights.as_lighting(3), brdf="oren-nayar", roughness=0.3,
                         noise=0.002, seed=1)
    rendered = resolve(Options(read_noise=0.002, gain=0.0),
                       gauge=StackModel.rendered(FLOAT_DARK_LEVEL))
    quick = rendered.replace(light_subsets=False, max_residual=None, max_distance=None)
    lambert = Gauge.virtual(lights, radius=60, bands=3)
    start = reconstruct(stack, lambert.stack, lambert, quick, mask=scene.mask)
    ys, xs = np.nonzero(start.solved & scene.mask)
    observed = stack[:, ys, xs, :].astype(np.float64)
    normals = start.normals[ys, xs].astype(np.float64)
    assert np.mean(angular_error(normals, scene.normals[ys, xs])) > 3.0

    def fitted_and_error():
        brdf, _ = fit_brdf(observed, normals, lights.directions, lights.intensities,
                           observed > 1e-6, settle_rounds=2)
        gauge = Gauge.virtual(lights, radius=60, bands=3, brdf=brdf)
        result = reconstruct(stack, gauge.stack, gauge, rendered, mask=scene.mask)
        solved = result.solved & scene.mask
        return brdf, float(np.mean(angular_error(result.normals[solved],
                                                 scene.normals[solved])))

    relaxed, relaxed_error = fitted_and_error()
    monkeypatch.setattr(brdf_module, "OVER_RELAXATION", 1.0)
    plain, plain_error = fitted_and_error()
    assert relaxed.roughness == 0.3
    np.testing.assert_allclose(relaxed.falloff, 1.0, atol=0.05)
    assert plain.falloff[0] < 0.7  # the valley
    assert relaxed_error < 0.2 < 0.5 < plain_error


@pytest.mark.parametrize("flat, chosen", [(0.80, "flat"), (0.97, "fitted")])
def test_a_simpler_finish_replaces_the_fit_only_where_clearly_better(lights, monkeypatch,
                                                                     flat, chosen):
    """A kept fit is matched again with its falloff set to Lambert's and without its
    highlight; one of those replaces it where the scene matches it under
    SIMPLER_GAIN of the fit's residual (an Oren-Nayar 0.2 scene: 0.95 -> 0.82
    noise units, 1.38 -> 0.11 degrees), not where about as well (DiLiGenT Ball,
    whose darker falloff is real: 1.29 against 1.28)."""
    import colorps.virtual as virtual

    fitted = BRDF(falloff=(0.5, 0.8, 0.9, 0.95, 1.0, 1.0, 1.0, 1.0), specular=(0.01,),
                  alpha=0.3, roughness=0.2)
    rounds = iter([2.0, 1.0])  # Lambert's, then the first fit's: the fit is kept

    def fake_round(data, lights, brdf, quick, mask, radius, rng, settle_rounds, *held):
        return fitted, dict(pixels=1, rms_relative=0.1, match_residual_median=next(rounds))

    def fake_match(data, lights, brdf, quick, mask, radius):
        if brdf == fitted:
            return 1.0
        return flat if any(brdf.specular) else flat + 0.01  # the flat one with its highlight

    monkeypatch.setattr(virtual, "_fit_round", fake_round)
    monkeypatch.setattr(virtual, "_match_residual", fake_match)
    stack = np.ones((len(lights.directions), 4, 4, 1), dtype=np.float32)
    brdf, history = fit_scene_brdf(stack, lights, Options(read_noise=0.001, gain=0.0),
                                   fits=2)
    # The fit, its flat falloff, plain finishes at 3 roughnesses of the grid and,
    # all matching alike here, the ones tried between them.
    assert history[-1]["kept"] and len(history[-1]["candidates"]) >= 5
    if chosen == "flat":
        assert brdf.falloff == BRDF.lambert().falloff and brdf.specular == fitted.specular
        assert brdf.roughness == fitted.roughness
    else:
        assert brdf == fitted


@pytest.mark.parametrize("camera", [None, "lens"])
def test_a_plain_finish_between_the_grids_values_is_found(lights, monkeypatch, camera):
    """The fit's roughness is one of the grid's; a scene between them (Oren-Nayar
    0.15) had the fit take 0.1 and a darker falloff instead, 2.3 degrees off.
    The plain finishes are then also tried between the grid's values around the
    best of them, and the one the scene matches best replaces the fit where it
    is clearly better; through a lens (whose matches along the axis favour a
    rougher finish) only the grid's values are tried."""
    import colorps.virtual as virtual
    from colorps.camera import Camera

    fitted = BRDF(falloff=(0.2, 0.6, 0.9, 0.95, 1.0, 1.0, 1.0, 1.0), roughness=0.1)
    rounds = iter([2.0, 1.0])
    tried = []

    def fake_round(data, lights, brdf, quick, mask, radius, rng, settle_rounds, *held):
        return fitted, dict(pixels=1, rms_relative=0.1, match_residual_median=next(rounds))

    def fake_match(data, lights, brdf, quick, mask, radius):
        if brdf == fitted or brdf.falloff != BRDF.lambert().falloff:
            return 1.0
        tried.append(brdf.roughness)  # the scene's roughness is 0.153
        return 0.9 + 8.0 * (brdf.roughness - 0.153) ** 2 + 0.001 * np.sin(900 * brdf.roughness)

    monkeypatch.setattr(virtual, "_fit_round", fake_round)
    monkeypatch.setattr(virtual, "_match_residual", fake_match)
    stack = np.ones((len(lights.directions), 4, 4, 1), dtype=np.float32)
    brdf, _ = fit_scene_brdf(stack, lights, Options(read_noise=0.001, gain=0.0), fits=2,
                             camera=None if camera is None else Camera(300.0, 300.0))
    assert brdf.falloff == BRDF.lambert().falloff and not any(brdf.specular)
    if camera is None:
        assert abs(brdf.roughness - 0.153) < 0.005
        assert len(tried) <= 16  # a few matches, not a scan
    else:
        assert brdf.roughness == 0.2 and set(tried) == {0.1, 0.2}  # (0: Lambert, beaten)


def test_a_finish_is_scored_by_its_matches_with_or_without_refinement(lights):
    """The fit scores candidate finishes by the scene's median match residual; its
    quick matches use no light subsets, so the refinement changes no match, and
    the score is taken without it: the same number."""
    from colorps.virtual import _match_residual, _matched

    scene = synth.smiley_surface(64)
    stack = _render(scene, lights, GLOSSY, noise=0.002)
    quick = resolve(Options(read_noise=0.002, gain=0.0), gauge=StackModel.rendered(
        FLOAT_DARK_LEVEL)).replace(light_subsets=False, max_residual=None, max_distance=None)
    refined = _matched(stack, lights, BRDF.lambert(), quick, scene.mask, 40)
    assert refined.stats.refined > 0
    assert _match_residual(stack, lights, BRDF.lambert(), quick, scene.mask, 40) == \
        refined.stats.residual_median_noise_units


def test_ggx_lobe_is_the_renderers_coat():
    """The fitted finish's highlight is the GGX coat colorps.synth renders (its
    Fresnel factor relative to FRESNEL_F0), along the axis and along other views."""
    from colorps.brdf import FRESNEL_F0, ggx_lobe, shading_angles
    from colorps.finishes import Gloss, gloss_shape

    rng = np.random.default_rng(11)
    normals = rng.normal(size=(500, 3)) + [0, 0, 2.0]
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    directions = rng.normal(size=(6, 3)) + [0, 0, 1.5]
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    views = rng.normal(size=(500, 3)) * 0.1 + [0, 0, 1.0]
    views /= np.linalg.norm(views, axis=1, keepdims=True)
    for alpha in (0.05, 0.3):
        for seen in (None, views):
            lobe = ggx_lobe(shading_angles(normals, directions, seen), alpha)
            coat = np.stack([gloss_shape(normals, light, Gloss(FRESNEL_F0, "ggx", alpha=alpha),
                                         seen) for light in directions])
            # (the renderer clips the cosines at 1e-6: a relative 1e-4 at grazing)
            np.testing.assert_allclose(lobe * FRESNEL_F0, coat, rtol=1e-4, atol=1e-12)
    assert np.isclose(BRDF(specular=(0.2,), alpha=0.25).highlight_peak, 0.2 / (4 * 0.25 ** 2))


def test_a_white_highlight_does_not_scale_with_the_albedo(lights):
    normals = np.array([[0.0, 0.0, 1.0], [0.3, 0.1, 0.95]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    albedo = np.array([[0.2, 0.5, 0.9], [0.7, 0.1, 0.4]])
    for white in (False, True):
        brdf = BRDF(specular=(0.05,), alpha=0.2, white_highlight=white)
        diffuse, lobe = brdf.parts(normals, lights.directions)
        tint = 1.0 if white else albedo[None]
        expected = (albedo[None] * diffuse[..., None] + tint * 0.05 * lobe[..., None]) * \
            lights.intensities[:, None, :]
        np.testing.assert_allclose(brdf.shade(normals, lights.directions, lights.intensities,
                                              albedo=albedo), expected, rtol=1e-12)
        assert BRDF.from_dict(brdf.as_dict()) == brdf
    assert not BRDF(specular=(0.05,), alpha=0.2, white_highlight=True).diffuse.has_white_highlight


def test_a_blinn_phong_record_of_colorps_0_2_is_read():
    record = dict(falloff_knots=list(DIFFUSE_KNOTS), falloff=[1.0] * len(DIFFUSE_KNOTS),
                  specular=[0.02], shininess=98.0, roughness=0.0)
    brdf = BRDF.from_dict(record)
    assert np.isclose(brdf.alpha, np.sqrt(2 / 100)) and not brdf.white_highlight


@pytest.mark.parametrize("white, roughness, seen", [(False, 0.0, False), (True, 0.0, False),
                                                    (True, 0.3, True)])
def test_best_normals_find_the_true_normals(lights, white, roughness, seen):
    """Noise-free pixels of a finish (tinted or white highlight, smooth or rough,
    along the axis or along their own rays), from normals 3 degrees off: the
    compiled per-pixel fit comes back to the truth."""
    from colorps.brdf import best_normals

    rng = np.random.default_rng(5)
    truth = rng.normal(size=(400, 3)) * 0.35 + [0, 0, 1.0]
    truth /= np.linalg.norm(truth, axis=1, keepdims=True)
    albedo = rng.uniform(0.05, 0.9, (400, 3))  # saturated colours too
    views = None
    if seen:
        views = rng.normal(size=(400, 3)) * 0.05 + [0, 0, 1.0]
        views /= np.linalg.norm(views, axis=1, keepdims=True)
    brdf = BRDF(falloff=(0.6, 0.7, 0.78, 0.85, 0.9, 0.95, 0.98, 1.0), specular=(0.04,),
                alpha=0.25, roughness=roughness, white_highlight=white)
    observed = brdf.shade(truth, lights.directions, np.ones_like(lights.intensities), views,
                          albedo=albedo)
    tilt = rng.normal(size=(400, 3))
    tilt -= (tilt * truth).sum(1, keepdims=True) * truth
    start = truth + np.radians(3.0) * tilt / np.linalg.norm(tilt, axis=1, keepdims=True)
    start /= np.linalg.norm(start, axis=1, keepdims=True)
    lit = (truth @ lights.directions.T).T[..., None] > 0.02
    weight = np.broadcast_to(lit, observed.shape) / np.maximum(
        np.sqrt((observed ** 2).sum(0)), 1e-12) ** 2
    found = best_normals(observed, weight, start, brdf, lights.directions, views)
    assert np.median(angular_error(start, truth)) > 2.9
    assert np.percentile(angular_error(found, truth), 95) < 0.01


def test_the_fit_tells_a_white_highlight_from_a_tinted_one(lights):
    """A textured sphere under a clear coat (the highlight the lights' colour,
    whatever the albedo) and one whose highlight takes the albedo's colour: the
    fit at the true normals says which, with the coat's strength and roughness."""
    ball = synth.sphere_surface(61, 28, bands=3)
    normals = ball.normals[ball.mask]
    albedo = np.random.default_rng(4).uniform(0.05, 0.9, (len(normals), 3))
    for white in (True, False):
        truth = BRDF(specular=(0.04,) if white else (0.08,), alpha=0.25, white_highlight=white)
        observed = truth.shade(normals, lights.directions, lights.intensities, albedo=albedo)
        fitted, rms = fit_brdf(observed, normals, lights.directions, lights.intensities,
                               observed > 1e-6)
        assert fitted.white_highlight == white and rms < 0.01
        np.testing.assert_allclose(fitted.specular, truth.bands(3), rtol=0.3)
        assert 0.2 <= fitted.alpha <= 0.3


def test_a_clear_coat_on_a_coloured_scene_is_matched_without_its_highlight(lights):
    """The smiley's saturated colours under a white GGX coat (colorps.synth's, as
    plastics and glazes are rendered): the fit finds a white highlight, and the
    scene matched with it taken out (match_along_rays) comes back at a fifth of
    a Lambertian gauge's error, its albedo the base colour's, not the coat's."""
    from colorps.finishes import Gloss
    from colorps.virtual import match_along_rays, virtual_gauge

    scene = synth.smiley_surface(96)
    stack = synth.render(scene, lights.as_lighting(3), gloss=Gloss(0.1, "ggx", alpha=0.25),
                         noise=0.002, seed=1)
    gauge, run, brdf, _ = virtual_gauge(stack, lights, Options(read_noise=0.002, gain=0.0),
                                        mask=scene.mask)
    assert brdf.white_highlight and 0.2 <= brdf.alpha <= 0.3
    np.testing.assert_allclose(brdf.specular, 0.1, rtol=0.15)
    result, _ = match_along_rays(stack.copy(), gauge, run, lights, brdf, None, mask=scene.mask)
    solved = result.solved & scene.mask
    assert solved.sum() >= 0.995 * scene.mask.sum()
    error = angular_error(result.normals[solved], scene.normals[solved])
    lambert = Gauge.virtual(lights, radius=100, bands=3)
    plain = reconstruct(stack, lambert.stack, lambert, run, mask=scene.mask)
    plain_error = angular_error(plain.normals[plain.solved & scene.mask],
                                scene.normals[plain.solved & scene.mask])
    assert error.mean() < 0.3 and error.mean() < 0.2 * plain_error.mean()
    albedo_error = np.abs(result.albedo[solved] / scene.albedo[solved] - 1)
    assert np.percentile(albedo_error, 95) < 0.05
