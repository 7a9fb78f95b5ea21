"""Pinhole cameras: the gauge sphere's normals from the true rays, and the files
that give a camera."""

import json
import warnings

import numpy as np
import pytest

from colorps import Gauge, InputError, angular_error, reconstruct, synth
from colorps.camera import Camera, read_camera
from colorps.geometry import sphere_normals


def project(points, camera, shape):
    """Pixel coordinates of camera-space points (forward pinhole projection)."""
    px, py = camera.principal(shape)
    return (px + camera.fx * points[:, 0] / -points[:, 2],
            py - camera.fy * points[:, 1] / -points[:, 2])


def sphere_in_view(camera, shape, centre, radius):
    """(cx, cy, r) of the circle a fitted silhouette gives, and a 3-D sphere."""
    c = np.asarray(centre, np.float64)
    angles = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    # The silhouette: tangent points of the cone from the camera to the sphere.
    axis = c / np.linalg.norm(c)
    u = np.cross(axis, [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    dist = np.linalg.norm(c)
    tangent = np.sqrt(dist ** 2 - radius ** 2)
    sin_a = radius / dist
    ring = c - axis * radius * sin_a + radius * np.sqrt(1 - sin_a ** 2) * (
        np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * v)
    assert np.allclose(np.linalg.norm(ring, axis=1), tangent)
    x, y = project(ring, camera, shape)
    a = np.column_stack([x, y, np.ones_like(x)])
    sol = np.linalg.lstsq(a, x * x + y * y, rcond=None)[0]
    cx, cy = sol[0] / 2, sol[1] / 2
    return cx, cy, float(np.sqrt(sol[2] + cx * cx + cy * cy))


@pytest.mark.parametrize("centre, limit", [((0.0, 0.0, -10.0), 1e-4),
                                           ((1.2, -0.8, -10.0), 0.02),
                                           ((-1.5, 1.0, -9.0), 0.05),
                                           ((2.5, -1.5, -9.0), 0.1)])
def test_pinhole_sphere_normals_match_the_projected_sphere(centre, limit):
    """Points of a sphere projected forward land on pixel coordinates whose computed
    normal is theirs, from the circle fitted to the silhouette (an ellipse off
    axis): median error within ``limit`` degrees at 0, 8, 11 and 18 degrees off
    axis (the circle stands for the ellipse less well the farther off axis it
    is); orthographic normals are degrees off."""
    from colorps.geometry import _pinhole_sphere_normals

    camera = Camera(500.0, 500.0, 160.0, 120.0)
    shape = (240, 320)
    cx, cy, r = sphere_in_view(camera, shape, centre, 1.0)
    rng = np.random.default_rng(0)
    n = rng.normal(size=(4000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    points = np.asarray(centre) + n
    to_camera = -points / np.linalg.norm(points, axis=1, keepdims=True)
    visible = (n * to_camera).sum(axis=1) > 0.05
    x, y = project(points[visible], camera, shape)
    got, rho = _pinhole_sphere_normals(x, y, cx, cy, r, camera, shape)
    error = angular_error(got, n[visible])
    assert np.median(error) < limit and np.percentile(error, 99) < 15 * limit + 1e-4
    assert (rho < 1).all()
    # The whole-image field agrees at pixel centres, and orthographic normals of
    # the same circle do not.
    normals, _ = sphere_normals(shape, cx, cy, r, camera)
    ortho, _ = sphere_normals(shape, cx, cy, r)
    iy, ix = np.round(y).astype(int), np.round(x).astype(int)
    keep = (iy >= 0) & (iy < shape[0]) & (ix >= 0) & (ix < shape[1])
    iy, ix = iy[keep], ix[keep]
    exact, _ = _pinhole_sphere_normals(ix.astype(float), iy.astype(float), cx, cy, r, camera,
                                       shape)
    inside = np.linalg.norm(exact, axis=1) > 0
    np.testing.assert_allclose(normals[iy, ix][inside], exact[inside], atol=1e-12)
    assert np.median(angular_error(ortho[iy, ix][inside], exact[inside])) > 2.0


def test_without_a_camera_the_gauge_is_orthographic():
    a = Gauge.from_sphere((60, 60), 29.5, 29.5, 25)
    b = Gauge.from_sphere((60, 60), 29.5, 29.5, 25, camera=None)
    np.testing.assert_array_equal(a.normals, b.normals)


def render_sphere(camera, shape, centre, lights, albedo=0.7):
    """A Lambertian sphere rendered by ray casting (its own code, not sphere_normals)."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    d = camera.rays(x, y, shape)
    c = np.asarray(centre, np.float64)
    b = d @ c
    disc = b * b - (c @ c - 1.0)
    hit = disc > 0
    t = b - np.sqrt(np.where(hit, disc, 0.0))
    normals = np.where(hit[..., None], t[..., None] * d - c, 0.0)
    shading = np.clip(np.einsum("hwk,mk->mhw", normals, lights), 0, None) * albedo
    stack = np.repeat(np.where(hit, shading, 0.0)[..., None], 3, axis=-1)
    return stack.astype(np.float32), normals, hit


def test_a_pinhole_gauge_removes_the_perspective_error():
    """Scene and gauge spheres off axis under a short lens: with the camera the
    normals are right to a fraction of a degree; read orthographically, they are
    degrees off."""
    camera = Camera(400.0, 400.0)
    shape = (200, 260)
    theta = np.radians(35)
    phi = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    lights = np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                              np.full(8, np.cos(theta))])
    gauge_stack, _, gauge_hit = render_sphere(camera, shape, (-1.3, 0.5, -9.0), lights)
    scene_stack, truth, scene_hit = render_sphere(camera, shape, (1.5, -0.4, -9.5), lights)
    cx, cy, r = sphere_in_view(camera, shape, (-1.3, 0.5, -9.0), 1.0)
    mask = scene_hit & (truth[..., 2] > 0.3)
    errors = {}
    for name, cam in (("pinhole", camera), ("orthographic", None)):
        gauge = Gauge.from_sphere(shape, cx, cy, r, camera=cam)
        result = reconstruct(scene_stack, gauge_stack, gauge, mask=mask, max_residual=None)
        errors[name] = angular_error(result.normals[mask], truth[mask])
    assert np.median(errors["pinhole"]) < 0.1
    assert np.median(errors["orthographic"]) > 1.0 > 10 * np.median(errors["pinhole"])


@pytest.mark.parametrize("text, expected", [
    ("3700", Camera(3700.0, 3700.0)),
    ("K.txt", Camera(3772.1, 3759.7, 244.9, 256.9)),
    ("cam.json", Camera(800.0, 810.0, 320.0, 240.0)),
    ("k.json", Camera(3772.1, 3759.7, 244.9, 256.9)),
])
def test_camera_files(tmp_path, monkeypatch, text, expected):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "K.txt").write_text("3772.1 0 244.9\n0 3759.7 256.9\n0 0 1\n")
    (tmp_path / "cam.json").write_text(json.dumps(dict(fx=800, fy=810, px=320, py=240)))
    (tmp_path / "k.json").write_text(json.dumps(
        dict(K=[[3772.1, 0, 244.9], [0, 3759.7, 256.9], [0, 0, 1]])))
    assert read_camera(text) == expected
    assert read_camera(None) is None and read_camera("orthographic") is None


@pytest.mark.parametrize("content, message", [
    ("1 2 3\n4 5 6\n", "3 x 3"),
    ("3772 5 244\n0 3759 256\n0 0 1\n", "no skew"),
    ("a b c\n", "numbers"),
])
def test_bad_camera_files_name_the_file(tmp_path, content, message):
    path = tmp_path / "K.txt"
    path.write_text(content)
    with pytest.raises(InputError, match=f"K.txt.*{message}"):
        read_camera(path)
    with pytest.raises(InputError, match="no such camera file"):
        read_camera(tmp_path / "missing.txt")
    with pytest.raises(InputError, match="focal length > 0"):
        read_camera("-5")


def test_cli_camera_from_k_txt_is_used_and_recorded(tmp_path, capsys):
    """``--camera K.txt``: the run's normals have no perspective error, and
    report.json says which camera; a bad camera file is a one-line error naming it."""
    from colorps.cli import main
    from colorps.io import read_image, write_image

    camera = Camera(400.0, 400.0, 129.5, 99.5)
    shape = (200, 260)
    phi = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    lights = np.column_stack([0.57 * np.cos(phi), 0.57 * np.sin(phi), np.full(8, 0.82)])
    gauge_stack, _, _ = render_sphere(camera, shape, (-1.3, 0.5, -9.0), lights)
    scene_stack, truth, hit = render_sphere(camera, shape, (1.5, -0.4, -9.5), lights)
    for k in range(8):
        write_image(tmp_path / f"scene_{k}.exr", scene_stack[k])
        write_image(tmp_path / f"gauge_{k}.exr", gauge_stack[k])
    mask = hit & (truth[..., 2] > 0.3)
    write_image(tmp_path / "mask.png", mask.astype(np.float32), dtype="uint8")
    (tmp_path / "K.txt").write_text("400 0 129.5\n0 400 99.5\n0 0 1\n")
    cx, cy, r = sphere_in_view(camera, shape, (-1.3, 0.5, -9.0), 1.0)
    args = ["reconstruct", "--scene", str(tmp_path / "scene_*.exr"), "--gauge",
            str(tmp_path / "gauge_*.exr"), "--sphere", f"{cx},{cy},{r}", "--mask",
            str(tmp_path / "mask.png"), "--quiet", "--no-height", "--max-residual", "none"]
    assert main(args + ["--out", str(tmp_path / "out"), "--camera",
                        str(tmp_path / "K.txt")]) == 0
    normals = read_image(tmp_path / "out" / "normal.exr")[0]
    assert np.median(angular_error(normals[mask], truth[mask])) < 0.1
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["camera"] == dict(model="pinhole", fx=400.0, fy=400.0, px=129.5, py=99.5)
    (tmp_path / "bad.txt").write_text("1 2\n")
    with pytest.raises(SystemExit) as exit_:
        main(args + ["--out", str(tmp_path / "bad"), "--camera", str(tmp_path / "bad.txt")])
    assert exit_.value.code == 2
    assert "bad.txt" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_a_lens_left_out_widens_every_normals_uncertainty(tmp_path, capsys):
    """The same capture read without its camera: every normal is off by about the
    angle between the orthographic and the true normal of the gauge pixel it matched
    (here 2-13 degrees). The lens hint finds the focal length (417 px for 400),
    warns with the median bias (``normals_off_deg``), and adds each pixel's to its
    68 % radius (through a lens a step shorter): the radii then hold most errors and
    rank them (the noise's alone held almost none)."""
    from colorps.cli import main
    from colorps.io import read_image, write_image

    camera = Camera(400.0, 400.0)
    shape = (200, 260)
    phi = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    lights = np.column_stack([0.57 * np.cos(phi), 0.57 * np.sin(phi), np.full(8, 0.82)])
    rng = np.random.default_rng(2)
    gauge_stack, _, _ = render_sphere(camera, shape, (-1.3, 0.5, -9.0), lights)
    scene_stack, truth, hit = render_sphere(camera, shape, (1.5, -0.4, -9.5), lights)
    for k in range(8):
        write_image(tmp_path / f"scene_{k}.exr", scene_stack[k] + rng.normal(
            0, 0.002, scene_stack[k].shape).astype(np.float32))
        write_image(tmp_path / f"gauge_{k}.exr", gauge_stack[k] + rng.normal(
            0, 0.002, gauge_stack[k].shape).astype(np.float32))
    mask = hit & (truth[..., 2] > 0.3)
    write_image(tmp_path / "mask.png", mask.astype(np.float32), dtype="uint8")
    cx, cy, r = sphere_in_view(camera, shape, (-1.3, 0.5, -9.0), 1.0)
    assert main(["reconstruct", "--scene", str(tmp_path / "scene_*.exr"), "--gauge",
                 str(tmp_path / "gauge_*.exr"), "--sphere", f"{cx},{cy},{r}", "--mask",
                 str(tmp_path / "mask.png"), "--quiet", "--no-height", "--no-finish-check",
                 "--out", str(tmp_path / "out")]) == 0
    assert "degrees off (each normal's uncertainty takes that in)" in capsys.readouterr().err
    normals = read_image(tmp_path / "out" / "normal.exr")[0]
    radius = read_image(tmp_path / "out" / "uncertainty.exr")[0][..., 0]
    solved = mask & np.isfinite(radius)
    errors = angular_error(normals[solved], truth[solved])
    off = json.loads((tmp_path / "out" / "report.json").read_text())["gauge_check"][
        "lens_fit"]["normals_off_deg"]
    assert np.median(errors) > 2.0
    assert off == pytest.approx(np.median(errors), rel=0.3)
    assert np.mean(errors <= radius[solved]) > 0.9  # a bias, not a scatter: held
    assert np.corrcoef(errors, radius[solved])[0, 1] > 0.8  # the worst ranked worst


def test_camera_with_a_light_file_matches_again_along_each_ray(tmp_path, capsys):
    """--lights renders the gauge for a view along the optical axis: with a fitted
    highlight (which depends on the view) and a camera, the run matches again
    along each pixel's ray, and says so; with a matte finish it has no need."""
    from colorps import synth
    from colorps.cli import main
    from colorps.finishes import Gloss
    from colorps.io import write_image

    lights = synth.ring_lights(8, 40.0)
    scene = synth.smiley_surface(56)
    for name, gloss in (("glossy", Gloss(0.5, "ggx", alpha=0.3)), ("matte", 0.0)):
        folder = tmp_path / name
        folder.mkdir()
        stack = synth.render(scene, lights, gloss=gloss, noise=0.002)
        for k, image in enumerate(stack):
            write_image(folder / f"scene_{k:02d}.exr", image, channel_names=["R", "G", "B"])
        np.savetxt(folder / "lights.txt", lights.directions[:, 0])
        write_image(folder / "mask.png", scene.mask.astype(np.float32), dtype="uint8")
        capsys.readouterr()
        assert main(["reconstruct", "--scene", str(folder / "scene_*.exr"), "--lights",
                     str(folder / "lights.txt"), "--mask", str(folder / "mask.png"),
                     "--camera", "200", "--out", str(folder / "out")]) == 0
        said = capsys.readouterr().err
        assert ("each pixel seen along its own ray" in said) == (name == "glossy"), said
        report = json.loads((folder / "out" / "report.json").read_text())
        assert report["matched_along_rays"] == (name == "glossy")


def test_a_view_dependent_finish_is_matched_along_each_pixels_ray():
    """A glossy scene seen through a wide lens (rays up to 15 degrees off the
    axis), shaded by the finish the virtual gauge is rendered with but for each
    pixel's own view: matched again after view_corrected, the normals lose the
    perspective's error; with the rays along the axis nothing changes."""
    from colorps import Gauge, Lights, reconstruct, synth
    from colorps.brdf import BRDF
    from colorps.virtual import view_corrected

    lighting = synth.ring_lights(12, 40.0)
    lights = Lights(lighting.directions[:, 0], lighting.colours[:, 0])
    scene = synth.smiley_surface(80)
    brdf = BRDF(specular=(0.3,), alpha=0.3)  # a broad highlight: many lights
    camera = Camera(150.0, 150.0)
    ys, xs = np.nonzero(scene.mask)
    views = -camera.rays(xs, ys, scene.mask.shape)
    stack = np.zeros((12, 80, 80, 3), np.float32)
    stack[:, ys, xs] = brdf.shade(scene.normals[ys, xs], lights.directions,
                                  lights.intensities, views) * scene.albedo[ys, xs][None]
    gauge = Gauge.virtual(lights, radius=60, bands=3, brdf=brdf)
    settings = dict(mask=scene.mask, read_noise=0.001, gain=0.0)
    first = reconstruct(stack, gauge.stack, gauge, **settings)
    again = reconstruct(view_corrected(stack.copy(), first, lights, brdf, camera),
                        gauge.stack, gauge, **settings)
    solved = scene.mask & first.solved & again.solved
    before = np.median(angular_error(first.normals[solved], scene.normals[solved]))
    after = np.median(angular_error(again.normals[solved], scene.normals[solved]))
    assert after < 0.4 * before, (before, after)
    on_axis = view_corrected(stack.copy(), first, lights, brdf, Camera(1e9, 1e9))
    np.testing.assert_allclose(on_axis, stack, atol=1e-6)


def test_sphere_auto_through_a_lens_fits_the_cone_of_rays():
    """A sphere 2.5 radii off the axis at a focal length of 8 radii, lit by a
    dome of lights and stored in 8 bits: its image is an ellipse, and the circle
    fitted to its lit arc is pixels off. Given the camera, find_sphere fits the
    cone of rays through the edge and returns the circle that stands for it."""
    from colorps import find_sphere, synth
    from colorps.io import srgb_decode, srgb_encode
    from colorps.shapes import dome_lights

    radius, side = 60, 130
    centre = (side - 1) / 2
    camera = Camera(8 * radius, 8 * radius, centre - 2.5 * radius, centre)
    sphere = Gauge.from_sphere((side, side), centre, centre, radius, rim_margin=0.0,
                               camera=camera)
    ball = synth.SyntheticSurface(normals=np.where(sphere.mask[..., None], sphere.normals, 0.0),
                                  mask=sphere.mask, albedo=np.ones((side, side, 3)),
                                  height=np.zeros((side, side)))
    stack = synth.render(ball, dome_lights(32), noise=0.003, seed=2)
    stack = srgb_decode(np.round(srgb_encode(np.clip(stack, 0, 1)) * 255) / 255)
    found = np.array(find_sphere(stack, camera))
    assert np.abs(found - (centre, centre, radius)).max() < 0.15
    plain = np.array(find_sphere(stack))
    assert np.abs(plain - (centre, centre, radius)).max() > 1.0


def write_tiff_with_exif(path, image, **tags):
    """A float32 TIFF (linear) whose header carries EXIF ``tags``."""
    import OpenImageIO as oiio

    image = np.ascontiguousarray(np.atleast_3d(image), dtype=np.float32)
    spec = oiio.ImageSpec(image.shape[1], image.shape[0], image.shape[2], oiio.FLOAT)
    for name, value in tags.items():
        spec.attribute(f"Exif:{name}", value)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec) and out.write_image(image)
    out.close()
    return path


@pytest.mark.parametrize("tags, focal", [
    (dict(FocalLength=20.0, FocalPlaneXResolution=200.0, FocalPlaneResolutionUnit=3), 400.0),
    (dict(FocalLength=20.0, FocalPlaneXResolution=508.0, FocalPlaneResolutionUnit=2,
          PixelXDimension=520, PixelYDimension=400), 200.0),  # resized to half after the shot
    (dict(FocalLength=20.0, FocalPlaneXResolution=200.0, FocalPlaneResolutionUnit=3,
          PixelXDimension=600, PixelYDimension=400), None),  # a 3:2 shot cropped to 13:10
    (dict(FocalLengthIn35mmFilm=50), 50 * np.hypot(260, 200) / np.hypot(36, 24)),
    (dict(FocalLength=20.0), None),  # no sensor size: no camera
    (dict(FocalLengthIn35mmFilm=1), None),  # 0.4 % of the diagonal: not a lens
    ({}, None),
])
def test_exif_camera(tmp_path, tags, focal):
    from colorps.camera import exif_camera

    camera = exif_camera(write_tiff_with_exif(tmp_path / "a.tif", np.zeros((200, 260)),
                                              **tags))
    if focal is None:
        assert camera is None
    else:
        assert camera.fx == camera.fy == pytest.approx(focal, rel=1e-6)
        assert camera.px is None and "EXIF of a.tif" in camera.source


def test_cli_camera_from_the_images_exif(tmp_path, capsys):
    """Without --camera, photographs whose EXIF records the lens and sensor are
    read through that camera (a CameraWarning and report.json say so); with
    --camera orthographic they are not."""
    from colorps.cli import main
    from colorps.io import read_image, write_image

    camera = Camera(400.0, 400.0)
    shape = (200, 260)
    phi = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    lights = np.column_stack([0.57 * np.cos(phi), 0.57 * np.sin(phi), np.full(8, 0.82)])
    gauge_stack, _, _ = render_sphere(camera, shape, (-1.3, 0.5, -9.0), lights)
    scene_stack, truth, hit = render_sphere(camera, shape, (1.5, -0.4, -9.5), lights)
    lens = dict(FocalLength=20.0, FocalPlaneXResolution=200.0, FocalPlaneResolutionUnit=3)
    for k in range(8):
        write_tiff_with_exif(tmp_path / f"scene_{k}.tif", scene_stack[k], **lens)
        write_tiff_with_exif(tmp_path / f"gauge_{k}.tif", gauge_stack[k], **lens)
    mask = hit & (truth[..., 2] > 0.3)
    write_image(tmp_path / "mask.png", mask.astype(np.float32), dtype="uint8")
    cx, cy, r = sphere_in_view(camera, shape, (-1.3, 0.5, -9.0), 1.0)
    args = ["reconstruct", "--scene", str(tmp_path / "scene_*.tif"), "--gauge",
            str(tmp_path / "gauge_*.tif"), "--sphere", f"{cx},{cy},{r}", "--mask",
            str(tmp_path / "mask.png"), "--quiet", "--no-height", "--max-residual", "none"]
    errors = {}
    for name, extra in (("exif", []), ("orthographic", ["--camera", "orthographic"])):
        assert main(args + ["--out", str(tmp_path / name)] + extra) == 0
        said = capsys.readouterr().err
        assert ("a focal length of 400 px (EXIF of gauge_0.tif" in said) == (name == "exif")
        normals = read_image(tmp_path / name / "normal.exr")[0]
        errors[name] = np.median(angular_error(normals[mask], truth[mask]))
        report = json.loads((tmp_path / name / "report.json").read_text())
        if name == "exif":
            assert report["camera"]["fx"] == pytest.approx(400.0)
            assert "FocalLength 20 mm" in report["camera"]["source"]
        else:
            assert report["camera"] is None
    assert errors["exif"] < 0.1 and errors["orthographic"] > 1.0


def test_no_exif_camera_for_stacks_of_different_sizes(tmp_path):
    """A gauge cropped out of the photographs (another size than the scene's) has
    no known principal point: the run stays orthographic."""
    from colorps.inputs import CaptureFiles
    from colorps.io import read_info

    lens = dict(FocalLength=20.0, FocalPlaneXResolution=200.0, FocalPlaneResolutionUnit=3)
    scene = read_info(write_tiff_with_exif(tmp_path / "s.tif", np.zeros((200, 260)), **lens))
    gauge = read_info(write_tiff_with_exif(tmp_path / "g.tif", np.zeros((90, 90)), **lens))
    files = CaptureFiles("s.tif", gauge="g.tif")
    assert files.camera == "auto"
    assert files.with_exif_camera([gauge, scene]).camera is None
    with pytest.warns(UserWarning, match="focal length of 400 px"):
        assert files.with_exif_camera([scene]).camera.fx == pytest.approx(400.0)
    assert CaptureFiles("s.tif", gauge="g.tif", camera="orthographic").camera is None
    with pytest.raises(InputError, match="camera"):
        CaptureFiles("s.tif", gauge="g.tif", camera="fisheye")


def test_a_lens_is_told_from_a_matte_gauges_shading(tmp_path):
    """A matte gauge photographed through a lens and read without --camera: its
    Lambertian fit is far tighter through a pinhole of the true focal length, so
    colorps warns with that focal length (within 5 %); read from an orthographic
    render it stays quiet. Point-sampled ray casts (render_sphere), noise 0.002."""
    from colorps import find_sphere
    from colorps.errors import CameraWarning
    from colorps.gauge_check import lens_hint

    shape = (200, 260)
    rng = np.random.default_rng(5)
    theta, phi = np.radians(np.linspace(10, 45, 12)), np.linspace(0, 6 * np.pi, 12)
    lights = np.column_stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                              np.cos(theta)])
    camera = Camera(900.0, 900.0)
    stack, _, _ = render_sphere(camera, shape, (0.8, 0.2, -16.0), lights)
    stack += rng.normal(0, 0.002, stack.shape).astype(np.float32)
    circle = find_sphere(stack)
    gauge = Gauge.from_sphere(shape, *circle)
    with pytest.warns(CameraWarning, match="through a lens of focal length about") as said:
        record = lens_hint(stack, gauge, tmp_path / "gauge_0.exr")
    assert record["focal_px"] == pytest.approx(900.0, rel=0.05)
    assert f"--camera {record['focal_px']:.0f} for this estimate" in str(said[0].message)
    assert record["residual"] < 0.25 * record["orthographic_residual"]

    flat = synth.render(synth.sphere_surface(shape, circle[2], centre=circle[:2]),
                        synth.ring_lights(8, 35), noise=0.002, seed=3)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CameraWarning)
        record = lens_hint(flat, Gauge.from_sphere(shape, *circle), tmp_path / "gauge_0.exr")
    assert record["focal_px"] > 20 * circle[2]
