import json

import numpy as np
import pytest
import trimesh

from colorps import InputError, integrate, synth, weights_from_quality
from colorps.cli import main
from colorps.figures import shaded_relief
from colorps.integrate import slopes
from colorps.io import read_image
from colorps.mesh import height_mesh, write_mesh


def analytic_surface(size=160):
    """Two separate parts: a Gaussian bump (disk mask) and a tilted ripple (ring)."""
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    bump_mask = np.hypot(x - 45, y - 50) < 35
    ring = (np.hypot(x - 112, y - 105) < 40) & (np.hypot(x - 112, y - 105) > 12)
    z = np.where(bump_mask, 25 * np.exp(-((x - 45) ** 2 + (y - 50) ** 2) / 400), 0.0)
    z = np.where(ring, 0.3 * x - 0.2 * y + 6 * np.sin(x / 7) * np.cos(y / 9), z)
    # Analytic derivatives: dz/dx, dz/drow.
    g = 25 * np.exp(-((x - 45) ** 2 + (y - 50) ** 2) / 400)
    zx = np.where(bump_mask, -g * (x - 45) / 200, 0.3 + 6 / 7 * np.cos(x / 7) * np.cos(y / 9))
    zr = np.where(bump_mask, -g * (y - 50) / 200, -0.2 - 6 / 9 * np.sin(x / 7) * np.sin(y / 9))
    # Normal from slopes (x right, y up): n ~ (-dz/dx, -dz/dy, 1), dz/dy = -dz/drow.
    n = np.stack([-zx, zr, np.ones_like(zx)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    mask = bump_mask | ring
    return n, mask, np.where(mask, z, np.nan), (bump_mask, ring)


def rms_error_fraction(z, truth, parts):
    """RMS height error per part (offsets removed) as a fraction of its depth."""
    worst = 0.0
    for part in parts:
        err = (z[part] - z[part].mean()) - (truth[part] - truth[part].mean())
        depth = truth[part].max() - truth[part].min()
        worst = max(worst, np.sqrt(np.mean(err ** 2)) / depth)
    return worst


def test_slopes_follow_conventions():
    n = np.array([[[0.6, 0.0, 0.8], [0.0, 0.6, 0.8]]])
    gx, grow = slopes(n)
    # Facing right: height falls to the right; facing up: height rises downwards.
    np.testing.assert_allclose(gx[0], [-0.75, 0.0])
    np.testing.assert_allclose(grow[0], [0.0, 0.75])


def test_smiley_and_sphere_cap_from_exact_normals():
    for surface in (synth.smiley_surface(200), synth.sphere_surface(200, 140)):
        z = integrate(surface.normals, surface.mask)
        assert rms_error_fraction(z, surface.height, [surface.mask]) <= 0.01
        assert np.isnan(z[~surface.mask]).all()
        assert abs(np.nanmean(z)) < 1e-6  # the documented zero-mean offset


def test_non_rectangular_two_part_mask():
    normals, mask, truth, parts = analytic_surface()
    z = integrate(normals, mask)
    assert rms_error_fraction(z, truth, parts) <= 0.01
    for part in parts:
        assert abs(z[part].mean()) < 1e-6


def test_dct_equals_poisson_on_a_rectangle():
    surface = synth.sphere_surface(120, 200)  # the cap fills the whole image
    assert surface.mask.all()
    dct = integrate(surface.normals, method="dct")
    poisson = integrate(surface.normals, method="poisson")
    np.testing.assert_allclose(dct, poisson, atol=1e-3)
    assert rms_error_fraction(dct, surface.height, [surface.mask]) <= 0.01
    with pytest.raises(InputError, match="full rectangle"):
        integrate(surface.normals, surface.mask & (np.arange(120) > 3), method="dct")


def test_weights_keep_bad_normals_from_spreading():
    surface = synth.smiley_surface(160)
    bad = surface.normals.copy()
    corrupt = np.zeros(surface.mask.shape, bool)
    corrupt[60:75, 60:110] = True
    bad[corrupt & surface.mask] = [0.7, 0.0, 0.714]  # a wrong, steep normal
    plain = integrate(bad, surface.mask)
    weights = np.where(corrupt, 1e-4, 1.0)
    weighted = integrate(bad, surface.mask, weights=weights)
    good = surface.mask & ~corrupt
    err_plain = rms_error_fraction(np.where(good, plain, np.nan), surface.height, [good])
    err_weighted = rms_error_fraction(np.where(good, weighted, np.nan), surface.height, [good])
    assert err_weighted < 0.5 * err_plain


def test_weights_from_quality():
    q = np.array([[0.0, 0.01, np.nan], [0.02, 0.03, 1.0]])
    w = weights_from_quality(q, scale=0.02)
    assert w[0, 2] == 0 and w[0, 0] == 1 and w[1, 0] == pytest.approx(0.5)
    assert np.all(np.diff([w[0, 0], w[0, 1], w[1, 0], w[1, 1], w[1, 2]]) < 0)


def test_grazing_and_bad_inputs():
    n = np.zeros((4, 4, 3))
    n[..., 0] = 1.0  # nz = 0 everywhere: slopes are clamped, result finite
    assert np.isfinite(integrate(n)).all()
    with pytest.raises(InputError, match="normals"):
        integrate(np.zeros((4, 4)))
    with pytest.raises(InputError, match="mask"):
        integrate(n, np.ones((3, 3), bool))
    with pytest.raises(InputError, match="weights"):
        integrate(n, weights=-np.ones((4, 4)))
    with pytest.raises(InputError, match="method"):
        integrate(n, method="fft")
    assert np.isnan(integrate(n, np.zeros((4, 4), bool))).all()


def test_mesh_and_relief(tmp_path):
    surface = synth.smiley_surface(64)
    z = integrate(surface.normals, surface.mask)
    mesh = height_mesh(z, surface.albedo)
    assert len(mesh.vertices) == surface.mask.sum()
    assert mesh.face_normals[:, 2].mean() > 0.5  # faces look towards the camera (+z)
    for kind in ("ply", "obj"):
        path = write_mesh(mesh, tmp_path / f"m.{kind}")
        back = trimesh.load(path, process=False)
        assert len(back.vertices) == len(mesh.vertices) and len(back.faces) == len(mesh.faces)
    assert trimesh.load(tmp_path / "m.ply").visual.vertex_colors.shape[0] == len(mesh.vertices)
    with pytest.raises(InputError, match="mesh format"):
        write_mesh(mesh, tmp_path / "m.stl")
    relief = shaded_relief(z)
    assert relief.shape == z.shape and relief[~surface.mask].max() == 0
    # Lit from the upper left: the upper-left of the dome is brighter than the lower-right.
    assert relief[20, 20] > relief[44, 44]


def test_reconstruct_writes_height_and_cli_integrate(tmp_path, capsys):
    data = tmp_path / "data"
    synth.write_synthetic(data, size=64, images=5, gauge_radius=45)
    info = json.loads((data / "sample.json").read_text())
    g = info["gauge_sphere"]
    out = tmp_path / "out"
    args = ["reconstruct", "--scene", str(data / "scene_*.exr"), "--gauge",
            str(data / "gauge_*.exr"), "--sphere", f"{g['cx']},{g['cy']},{g['r']}",
            "--mask", str(data / "mask.png"), "--out", str(out), "--quiet", "--mesh", "both"]
    assert main(args) == 0
    for name in ("height.exr", "relief.png", "overview.png", "mesh.ply", "mesh.obj"):
        assert (out / name).exists(), name
    height, _ = read_image(out / "height.exr")
    truth = synth.smiley_surface(64)
    err = rms_error_fraction(height[..., 0], truth.height, [truth.mask])
    assert err < 0.03  # from reconstructed normals
    assert main(["integrate", str(out / "normal.exr"), "--out", str(tmp_path / "h.exr"),
                 "--mask", str(data / "mask.png"), "--weights", str(out / "quality.exr")]) == 0
    assert "relief depth" in capsys.readouterr().out
    assert main(["integrate", str(out / "normal.exr"), "--out", str(tmp_path / "h.exr")]) == 1
    assert "--overwrite" in capsys.readouterr().err
    plain = tmp_path / "plain"
    assert main(args[:-3] + ["--out", str(plain), "--no-height"]) == 0
    assert not (plain / "height.exr").exists()


def test_tiled_integration_stays_close_to_one_solve():
    from colorps import synth

    scene = synth.smiley_surface(300)
    mask = scene.mask.copy()
    mask[140:150, :] = False          # two parts, and a hole
    mask[60:70, 100:120] = False
    rng = np.random.default_rng(2)
    weights = rng.uniform(0.2, 1.0, mask.shape)
    normals = np.where(mask[..., None], scene.normals, np.nan)
    whole = integrate(normals, mask, weights=weights)
    tiled = integrate(normals, mask, weights=weights, tile=64)
    assert np.array_equal(np.isfinite(whole), np.isfinite(tiled))
    depth = np.nanmax(whole) - np.nanmin(whole)
    diff = np.abs(whole - tiled)[mask]
    assert np.sqrt(np.mean(diff ** 2)) < 1e-3 * depth  # the stated tolerance
    assert diff.max() < 5e-3 * depth
    # One tile covering the image is the plain solve.
    np.testing.assert_array_equal(integrate(normals, mask, weights=weights, tile=300), whole)
    with pytest.raises(InputError, match="tile"):
        integrate(normals, mask, tile=4)
    with pytest.raises(InputError, match="only method 'poisson'"):
        integrate(scene.normals, method="dct", tile=64)


# ------------------------------------------------- multigrid against pyamg's AMG
def _components(mask, weights):
    """Labels of the pixels linked by pairs of positive weight (the parts whose
    height offsets the normals cannot fix)."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    w = np.ones(mask.shape) if weights is None else weights
    index = np.arange(mask.size).reshape(mask.shape)
    pairs = []
    for a, b, wa, wb, both in ((index[:, :-1], index[:, 1:], w[:, :-1], w[:, 1:],
                                mask[:, :-1] & mask[:, 1:]),
                               (index[:-1], index[1:], w[:-1], w[1:], mask[:-1] & mask[1:])):
        keep = both & (np.minimum(wa, wb) > 0)
        pairs.append((a[keep], b[keep]))
    a = np.concatenate([p[0] for p in pairs])
    b = np.concatenate([p[1] for p in pairs])
    graph = sp.coo_matrix((np.ones(a.size), (a, b)), shape=(mask.size, mask.size))
    return connected_components(graph, directed=False)[1].reshape(mask.shape)


def _mg_and_amg(mask, weights=None, anchor=None, seed=0, tol=1e-10):
    """Heights of both solvers on random slopes, each part shifted to zero mean."""
    from colorps.integrate import _integrate_poisson, _integrate_poisson_amg

    rng = np.random.default_rng(seed)
    gx, grow = rng.normal(0, 1, mask.shape), rng.normal(0, 1, mask.shape)
    labels = _components(mask, weights)
    out = []
    for solver in (_integrate_poisson, _integrate_poisson_amg):
        z = np.full(mask.shape, np.nan)
        z[mask] = solver(gx, grow, mask, weights, tol, anchor)
        for part in np.unique(labels[mask]):
            pixels = labels == part
            if anchor is None or not np.isfinite(anchor[pixels & mask]).any():
                z[pixels] -= z[pixels].mean()  # a free offset
        out.append(z)
    return out


@pytest.mark.parametrize("shape", [(1, 1), (1, 7), (9, 1), (2, 2), (17, 33), (64, 65)])
def test_multigrid_matches_amg_on_rectangles_of_any_size(shape):
    mg, amg = _mg_and_amg(np.ones(shape, dtype=bool))
    np.testing.assert_allclose(mg, amg, atol=1e-4)


def test_multigrid_matches_amg_on_holes_parts_weights_and_anchors():
    from scipy import ndimage

    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:150, 0:201]
    mask = ((x - 70) ** 2 + (y - 75) ** 2 < 60 ** 2) | ((x > 150) & (y > 20) & (y < 140))
    mask &= ~ndimage.binary_dilation(rng.random(mask.shape) < 0.002, iterations=3)
    mask[5, 5] = mask[5, 7] = True  # lone pixels: parts of their own
    assert ndimage.label(mask)[1] >= 4
    mg, amg = _mg_and_amg(mask)
    np.testing.assert_allclose(mg, amg, atol=1e-4)
    weights = rng.gamma(1.0, 1.0, mask.shape) * (rng.random(mask.shape) > 0.05)  # some 0
    mg, amg = _mg_and_amg(mask, weights)
    # A pixel whose every pair has weight 0 has no height information: the
    # multigrid keeps it at 0, the AMG anywhere its tolerance allows.
    coupled = np.zeros(mask.shape, dtype=bool)
    pair_x = mask[:, :-1] & mask[:, 1:] & (np.minimum(weights[:, :-1], weights[:, 1:]) > 0)
    pair_y = mask[:-1] & mask[1:] & (np.minimum(weights[:-1], weights[1:]) > 0)
    coupled[:, :-1] |= pair_x
    coupled[:, 1:] |= pair_x
    coupled[:-1] |= pair_y
    coupled[1:] |= pair_y
    np.testing.assert_allclose(mg[coupled], amg[coupled], atol=1e-4)
    anchor = np.full(mask.shape, np.nan)
    anchor[:, 0] = anchor[:, -1] = 2.5
    anchor[0, :] = -1.0
    mg, amg = _mg_and_amg(mask, weights, anchor)
    np.testing.assert_allclose(mg[coupled], amg[coupled], atol=1e-4)


def test_multigrid_solves_the_system_it_is_given():
    """The residual of the returned heights is within the tolerance asked for."""
    from colorps._mg_kernels import residual
    from colorps.integrate import _grid_equations
    from colorps.multigrid import solve

    y, x = np.mgrid[0:300, 0:257]
    mask = (x - 128) ** 2 + (y - 150) ** 2 < 120 ** 2
    rng = np.random.default_rng(0)
    system, rhs = _grid_equations(rng.normal(0, 1, mask.shape), rng.normal(0, 1, mask.shape),
                                  mask, None, None)
    for tol in (1e-4, 1e-8):
        u, iterations = solve(system, rhs, tol=tol)
        r = np.empty_like(u)
        residual(u, rhs, system.east, system.south, system.diag, r)
        assert np.linalg.norm(r) <= tol * np.linalg.norm(rhs)
        assert iterations < 40 and (u[~mask] == 0).all()
