"""Synthetic scenes and gauges with ground truth (tests, sample data, benchmarks).

Everything is orthographic, with distant lights, in the project's conventions:
pixel (x, y) = (column, row); camera space x right, y up, z towards the camera.
Pixel values are linear radiance on a 0..1 scale.

Lighting is given per image as a set of distant lights, each with a unit
direction (pointing from the surface towards the light) and a colour (one
intensity per band), so an image may be lit by one white light, one coloured
light, or several lights of different colours at once.

BRDFs (:mod:`colorps.finishes`): ``"lambert"`` and ``"oren-nayar"`` (the
qualitative Oren-Nayar model, a broad rough-diffuse lobe). Both are the albedo
of the band times one fixed shape, as gauge-based photometric stereo requires.
Attached shadows are modelled (cos < 0 gives 0); cast shadows of the relief, a
white highlight (Blinn-Phong, or the GGX microfacet lobe of physically based
renderers: ``render(cast_shadows=True, gloss=Gloss(...))``) and a one-bounce
interreflection can be added, with ground truth of which light the first two
affect (:func:`shadow_maps`, :func:`highlight_maps`).
"""

from __future__ import annotations

from dataclasses import astuple, dataclass
from typing import Literal

import numpy as np

from ._config import MIN_LIGHTS, MIN_RADIUS
from .errors import InputError
from .finishes import Gloss, gloss_shape, oren_nayar
from .geometry import sphere_normals
from .occlusion import shadow_maps, sky_visibility

__all__ = [
    "BRDFS",
    "FILE_FORMATS",
    "LIGHT_LAYOUTS",
    "Lighting",
    "SyntheticCapture",
    "SyntheticSurface",
    "highlight_maps",
    "mixed_lights",
    "render",
    "ring_lights",
    "shadow_maps",
    "sky_visibility",
    "smiley_surface",
    "sphere_surface",
    "synthetic_files",
    "write_synthetic",
]

#: Names of the reflectance models :func:`render` knows.
BRDFS = ("lambert", "oren-nayar")
#: One-bounce interreflection (:func:`render`): cells it is gathered on, at most
#: (4 times :data:`colorps.interreflection.BOUNCE_CELLS`, finer than the
#: estimate tested against it).
BOUNCE_CELLS = 16384


@dataclass(frozen=True)
class Lighting:
    """Distant lights of an m-image capture.

    Attributes
    ----------
    directions : (m, L, 3) ndarray of float64
        Unit vectors towards each of the L lights of each image (camera space).
    colours : (m, L, c) ndarray of float64
        Intensity of each light in each band (0 switches a light off).
    """

    directions: np.ndarray
    colours: np.ndarray

    @property
    def images(self) -> int:
        return self.directions.shape[0]

    @property
    def bands(self) -> int:
        return self.colours.shape[2]


@dataclass(frozen=True)
class SyntheticSurface:
    """A rendered-to-be surface with ground truth.

    Attributes
    ----------
    normals : (H, W, 3) ndarray of float64
        Camera-space unit normals (0 outside the mask).
    mask : (H, W) ndarray of bool
        Pixels on the surface.
    albedo : (H, W, c) ndarray of float64
        Intrinsic albedo per band (linear, 0..1).
    height : (H, W) ndarray of float64
        Height z in pixel units (NaN outside the mask).
    """

    normals: np.ndarray
    mask: np.ndarray
    albedo: np.ndarray
    height: np.ndarray


def ring_lights(m: int, theta_deg: float, colours=None, *, bands: int = 3,
                azimuth0_deg: float = 0.0) -> Lighting:
    """One distant light per image, at angle ``theta_deg`` from the view direction.

    Azimuths are evenly spaced around the view axis.

    Parameters
    ----------
    m : int
        Number of images (lights).
    theta_deg : float
        Angle between each light and the z axis (degrees).
    colours : (m, c) array_like, optional
        Colour of each light; white (all ones in ``bands`` bands) by default.
    bands : int, optional
        Number of bands of white lights.
    azimuth0_deg : float, optional
        Azimuth of the first light (degrees, from +x towards +y).
    """
    if m < 1:
        raise InputError(f"m: expected at least 1 light, got {m}")
    phi = np.deg2rad(azimuth0_deg) + 2 * np.pi * np.arange(m) / m
    theta = np.deg2rad(theta_deg)
    directions = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                           np.full(m, np.cos(theta))], axis=1)
    if colours is None:
        colours = np.ones((m, bands))
    colours = np.asarray(colours, dtype=np.float64)
    if colours.shape[0] != m or colours.ndim != 2:
        raise InputError(f"colours: expected shape ({m}, c), got {colours.shape}")
    return Lighting(directions[:, None, :], colours[:, None, :])


def _shade(normals: np.ndarray, light: np.ndarray, brdf: str, roughness: float) -> np.ndarray:
    """BRDF shape times cosine for one light, view along +z (values >= 0)."""
    if brdf == "lambert":
        return np.maximum(normals @ light, 0.0)
    return oren_nayar(normals, light, roughness)


def render(surface: SyntheticSurface, lighting: Lighting, *,
           brdf: Literal["lambert", "oren-nayar"] = "lambert", roughness: float = 0.5,
           noise: float = 0.0, seed: int | None = 0, cast_shadows: bool = False,
           gloss: float | Gloss = 0.0, interreflection: float = 0.0) -> np.ndarray:
    """Render an image stack of a surface.

    Parameters
    ----------
    surface : SyntheticSurface
    lighting : Lighting
        Its band count must match the surface albedo's.
    brdf : {"lambert", "oren-nayar"}, optional
    roughness : float, optional
        Oren-Nayar roughness sigma (radians).
    noise : float, optional
        Standard deviation of additive Gaussian noise (0..1 scale); results are
        clipped at 0.
    seed : int, optional
        Noise seed.
    cast_shadows : bool, optional
        Lights blocked by the relief itself (:func:`shadow_maps`) do not
        reach a pixel.
    gloss : float or Gloss, optional
        A white highlight added to the diffuse shading (a dielectric coat,
        :class:`colorps.finishes.Gloss`; a number is the peak of a Blinn-Phong
        highlight of shininess 60): a finish a matte gauge does not share
        (:func:`highlight_maps`).
    interreflection : float, optional
        Strength of a one-bounce interreflection (0: none; 1: physical, a
        matte surface's): each pixel also reflects the direct light of every
        patch of the relief it sees, ``interreflection * albedo * sum(L_q
        cos cos A_q / (pi r^2))`` (:mod:`colorps.bounce` on the true relief,
        on up to BOUNCE_CELLS cells): light bounced inside folds, none on
        open, convex parts.

    Returns
    -------
    (m, H, W, c) ndarray of float32
        Linear pixel values; 0 outside the surface mask.
    """
    if brdf not in BRDFS:
        raise InputError(f"brdf: expected one of {BRDFS}, got {brdf!r}")
    c = surface.albedo.shape[-1]
    if lighting.bands != c:
        raise InputError(f"lighting has {lighting.bands} bands but the albedo has {c}")
    m = lighting.images
    h, w = surface.mask.shape
    stack = np.zeros((m, h, w, c), dtype=np.float64)
    n = surface.normals[surface.mask]
    alb = surface.albedo[surface.mask]
    blocked = shadow_maps(surface, lighting) if cast_shadows else None
    gloss = gloss if isinstance(gloss, Gloss) else Gloss(float(gloss))
    for k in range(m):
        value = np.zeros_like(alb)
        for index, (light, colour) in enumerate(zip(lighting.directions[k],
                                                    lighting.colours[k])):
            shade = _shade(n, light, brdf, roughness)[:, None] * alb
            if gloss.strength > 0:
                shade = shade + gloss_shape(n, light, gloss)[:, None]
            if blocked is not None:
                shade = np.where(blocked[k, index][surface.mask][:, None], 0.0, shade)
            value += shade * colour[None, :]
        stack[k][surface.mask] = value
    if interreflection > 0:
        stack += interreflection * _bounced(surface, stack)
    if noise > 0:
        rng = np.random.default_rng(seed)
        stack += rng.normal(0.0, noise, size=stack.shape)
        np.maximum(stack, 0.0, out=stack)
    return stack.astype(np.float32)


def _bounced(surface: SyntheticSurface, direct: np.ndarray) -> np.ndarray:
    """The one-bounce term of :func:`render` (strength 1), (m, H, W, c): the
    direct light every other visible patch of the relief reflects, gathered
    by form factors on the true relief (:mod:`colorps.bounce`)."""
    from colorps.bounce import bounced_light, cell_grid, cell_heights, gather

    grid = cell_grid(surface.normals, surface.mask, BOUNCE_CELLS)
    height = cell_heights(grid, surface.height, surface.mask)
    bounced = gather(grid, height, direct, surface.mask, surface.albedo)
    return bounced_light(bounced, surface.albedo, surface.mask.shape).astype(direct.dtype)


def highlight_maps(surface: SyntheticSurface, lighting: Lighting, *, gloss: float | Gloss,
                   level: float = 0.01) -> np.ndarray:
    """Where the highlight of :func:`render` adds more than ``level``: (m, L, H, W)."""
    gloss = gloss if isinstance(gloss, Gloss) else Gloss(float(gloss))
    out = np.zeros(lighting.directions.shape[:2] + surface.mask.shape, dtype=bool)
    n = surface.normals[surface.mask]
    for k in range(lighting.images):
        for index, light in enumerate(lighting.directions[k]):
            out[k, index][surface.mask] = gloss_shape(n, light, gloss) > level
    return out


def sphere_surface(size: int | tuple[int, int], radius: float, centre=None,
                   albedo=1.0, *, bands: int = 3) -> SyntheticSurface:
    """A sphere seen orthographically (the usual gauge).

    Parameters
    ----------
    size : int or (H, W)
        Image size in pixels.
    radius : float
        Sphere radius r in pixels.
    centre : (cx, cy), optional
        Centre in pixel coordinates (default: image centre).
    albedo : float or (c,) array_like
        Uniform albedo (per band).

    Notes
    -----
    Normals from :func:`colorps.geometry.sphere_normals` inside the disk.
    """
    h, w = (size, size) if np.isscalar(size) else size
    if centre is None:
        centre = ((w - 1) / 2.0, (h - 1) / 2.0)
    cx, cy = centre
    n, rho = sphere_normals((h, w), cx, cy, radius)
    mask = rho < 1.0
    normals = np.where(mask[..., None], n, 0.0)
    nz = normals[..., 2]
    alb = np.broadcast_to(np.asarray(albedo, dtype=np.float64), (bands,))
    albedo_map = np.where(mask[..., None], alb, 0.0)
    height = np.where(mask, radius * nz, np.nan)
    return SyntheticSurface(normals, mask, albedo_map, height)


def _smiley_slopes(X, Y, relief):
    """Height f(X, Y) and its gradient, in units of the face radius."""
    base2 = np.clip(1.0 - X * X - Y * Y, 1e-12, None)
    f = np.sqrt(base2)
    fx = -X / f
    fy = -Y / f
    # Convex eyes: Gaussian bumps.
    s = 0.09
    for ex in (-0.33, 0.33):
        g = relief * np.exp(-((X - ex) ** 2 + (Y - 0.28) ** 2) / (2 * s * s))
        f = f + g
        fx = fx - g * (X - ex) / (s * s)
        fy = fy - g * (Y - 0.28) / (s * s)
    # Concave mouth: a Gaussian groove along the smile curve Y = -0.42 + 0.7 X^2.
    c = -0.42 + 0.7 * X * X
    dc = 1.4 * X
    sm, wm = 0.07, 0.3
    g = -0.8 * relief * np.exp(-((Y - c) ** 2) / (2 * sm * sm) - X * X / (2 * wm * wm))
    f = f + g
    fx = fx + g * ((Y - c) * dc / (sm * sm) - X / (wm * wm))
    fy = fy + g * (-(Y - c) / (sm * sm))
    return f, fx, fy


def smiley_surface(size: int | tuple[int, int] = 256, *, radius: float | None = None,
                   relief: float = 0.12, coloured: bool = True, bands: int = 3,
                   rim: float = 0.97) -> SyntheticSurface:
    """The paper's test scene: a hemispherical smiley mask.

    Convex eyes and a concave mouth in low relief on a hemisphere, with (by
    default) a coloured albedo map that has saturated regions.

    Parameters
    ----------
    size : int or (H, W)
        Image size in pixels.
    radius : float, optional
        Face radius in pixels (default: 0.47 of the smaller image side).
    relief : float, optional
        Height of the eyes (the mouth is 0.8 of it deep), in face radii.
    coloured : bool, optional
        Coloured albedo (a skin-like base, saturated blue eyes, saturated red
        mouth, a green band across the forehead) instead of uniform grey 0.7.
    bands : int, optional
        Number of albedo bands (the colour map needs 3).
    rim : float, optional
        Keep pixels within this fraction of the radius (steep rim excluded).
    """
    h, w = (size, size) if np.isscalar(size) else size
    radius = 0.47 * min(h, w) if radius is None else radius
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    X = (x - cx) / radius
    Y = -(y - cy) / radius
    mask = rim * rim > X * X + Y * Y
    f, fx, fy = _smiley_slopes(X, Y, relief)
    n = np.stack([-fx, -fy, np.ones_like(f)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    normals = np.where(mask[..., None], n, 0.0)
    height = np.where(mask, radius * f, np.nan)
    if coloured:
        if bands != 3:
            raise InputError("coloured smiley albedo needs bands=3")
        alb = np.empty((h, w, 3))
        alb[:] = (0.80, 0.55, 0.40)
        eyes = np.minimum((X + 0.33) ** 2, (X - 0.33) ** 2) + (Y - 0.28) ** 2 < 0.12 ** 2
        mouth = (np.abs(Y - (-0.42 + 0.7 * X * X)) < 0.09) & (np.abs(X) < 0.5)
        band = np.abs(Y - 0.62) < 0.06
        alb[eyes] = (0.06, 0.12, 0.85)
        alb[mouth] = (0.85, 0.06, 0.05)
        alb[band] = (0.10, 0.70, 0.15)
    else:
        alb = np.full((h, w, bands), 0.7)
    albedo = np.where(mask[..., None], alb, 0.0)
    return SyntheticSurface(normals, mask, albedo, height)


def mixed_lights(m: int, theta_deg: float = 45.0) -> Lighting:
    """Two lights of different colours per image, 2m distinct directions.

    Each image is lit at once by a warm light (1, 0.5, 0.05) at ``theta_deg``
    from the view axis and a cool light (0.05, 0.5, 1) at ``theta_deg / 2``,
    from azimuths evenly spaced over the 2m lights; warm and cool swap from
    image to image. Colour mode separates the lights by band, mono mode cannot.

    Notes
    -----
    With m = 2 each band's signature is a ratio of two values, so the normal is
    fixed by three ratios. Symmetric layouts make them ambiguous: four lights at
    one elevation and azimuths 0, 90, 180, 270 degrees give every normal with
    nx = -ny the same three ratios. Alternating elevations break that symmetry.
    """
    phi = 2 * np.pi * np.arange(2 * m) / (2 * m)
    theta = np.deg2rad(np.where(np.arange(2 * m) % 2 == 0, theta_deg, theta_deg / 2))
    ring = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                     np.cos(theta)], axis=1)
    directions = np.stack([ring[0::2], ring[1::2]], axis=1)
    warm, cool = (1.0, 0.5, 0.05), (0.05, 0.5, 1.0)
    colours = np.array([[warm, cool] if k % 2 == 0 else [cool, warm] for k in range(m)])
    return Lighting(directions, colours)


#: Smallest scene side (pixels) ``colorps synth`` renders: the smiley's
#: features take a few pixels each.
MIN_SYNTH_SIZE = 16
#: Memory (bytes) rendering takes per value of the scene's and gauge's stacks
#: (float64 images and their temporaries: 16 measured at 64-1024 px, 8 lights).
SYNTH_BYTES_PER_VALUE = 16
#: Light layouts of :func:`write_synthetic` (``colorps synth --lights``).
LIGHT_LAYOUTS = ("white", "colour", "mixed", "one-sided")
#: File formats of :func:`write_synthetic`: linear half-float EXR, or 8-bit sRGB PNG.
FILE_FORMATS = ("exr", "png8")


@dataclass(frozen=True)
class SyntheticCapture:
    """What :func:`write_synthetic` renders (``colorps synth`` flags of the same names).

    Attributes
    ----------
    size : int
        Scene side (pixels).
    images : int
        Number of images m (one light each).
    theta : float
        Light angle from the view axis (degrees).
    lights : {"white", "colour", "mixed", "one-sided"}
    brdf : {"lambert", "oren-nayar"}
    noise : float
        Gaussian noise sigma (0..1 scale).
    gauge_radius : float
        Gauge sphere radius (pixels).
    seed : int
    relief : float
        Height of the eyes in face radii (the mouth is 0.8 of it deep).
    cast_shadows : bool
        The relief casts shadows.
    gloss : float
        Strength of a white highlight the matte gauge does not share.
    file_format : {"exr", "png8"}
    """

    size: int = 256
    images: int = 8
    theta: float = 45.0
    lights: Literal["white", "colour", "mixed", "one-sided"] = "white"
    brdf: Literal["lambert", "oren-nayar"] = "lambert"
    noise: float = 0.0
    gauge_radius: float = 100.0
    seed: int = 0
    relief: float = 0.12
    cast_shadows: bool = False
    gloss: float = 0.0
    file_format: Literal["exr", "png8"] = "exr"

    def __post_init__(self) -> None:
        for name, bad, expected in (
                ("size", not self.size >= MIN_SYNTH_SIZE, f"at least {MIN_SYNTH_SIZE} px"),
                ("images", not self.images >= MIN_LIGHTS, f"at least {MIN_LIGHTS} (one light "
                                                           "each; fewer fix no normal)"),
                ("theta", not 0.0 <= self.theta < 90.0, "0 to under 90 degrees"),
                ("noise", not self.noise >= 0.0, "a sigma of at least 0"),
                ("gauge_radius", not self.gauge_radius >= MIN_RADIUS,
                 f"at least {MIN_RADIUS:g} px"),
                ("relief", not self.relief >= 0.0, "at least 0"),
                ("gloss", not self.gloss >= 0.0, "at least 0")):
            if bad:
                raise InputError(f"{name}: expected {expected}, got {getattr(self, name)!r}")
        if self.lights not in LIGHT_LAYOUTS:
            raise InputError(f"lights: expected one of {LIGHT_LAYOUTS}, got {self.lights!r}")
        if self.file_format not in FILE_FORMATS:
            raise InputError(f"file_format: expected one of {FILE_FORMATS}, "
                             f"got {self.file_format!r}")

    def bytes_needed(self) -> int:
        """About how much memory rendering it takes (SYNTH_BYTES_PER_VALUE a value of
        the scene's and the gauge's stacks)."""
        gauge_side = _gauge_side(self.gauge_radius)
        return int(SYNTH_BYTES_PER_VALUE * 3 * self.images *
                   (self.size ** 2 + gauge_side ** 2))


def _gauge_side(gauge_radius: float) -> int:
    """Side (pixels) of the gauge's images: its sphere and 5 px around."""
    return int(np.ceil(2 * gauge_radius + 10))


def write_synthetic(out_dir, **settings) -> dict:
    """Render a smiley scene and a sphere gauge to image stacks with ground truth.

    ``settings`` are fields of :class:`SyntheticCapture` (its defaults for the rest).

    Writes ``scene_NN`` and ``gauge_NN`` images (``file_format`` "exr": half
    float, linear RGB; "png8": 8-bit sRGB PNG, as a camera's JPEG or PNG would
    be), ``mask.png`` (the object mask a user would draw, for ``--mask``),
    ``truth_normal.exr``, ``truth_albedo.exr``, ``truth_height.exr`` (pixels,
    NaN outside), ``truth_mask.png``, ``truth_shadows.png`` (with
    ``cast_shadows``: bit i set where light i is blocked, as 8-bit codes for up
    to 8 images) and ``sample.json`` (every parameter, the light directions and
    colours, and the gauge sphere geometry) into ``out_dir`` (made when
    missing; files of those names replaced). ``colorps synth`` writes the
    same files all together or not at all
    (:func:`colorps.sample.write_synthetic_folder`).

    Lights: "white" ring lights at ``theta`` from the view axis; "colour" one
    coloured light per image; "mixed" two colours per image; "one-sided" white
    lights over half the azimuths only (0-180 degrees: the lower rim of the
    sphere stays dark in every image, as in many real captures).

    Returns
    -------
    dict
        The content of sample.json.
    """
    from pathlib import Path

    try:
        capture = SyntheticCapture(**settings)
    except TypeError as error:
        raise InputError(f"write_synthetic: {error}") from None
    files, info = synthetic_files(capture)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name, write in files.items():
        write(out / name)
    return info


def synthetic_files(capture: SyntheticCapture) -> tuple[dict, dict]:
    """The files :func:`write_synthetic` writes of ``capture``, rendered:
    ``{name: write(path)}``, and the content of sample.json."""
    import json

    from .io import srgb_encode, write_image

    (size, images, theta, lights, brdf, noise, gauge_radius, seed, relief, cast_shadows, gloss,
     file_format) = astuple(capture)
    if lights == "white":
        lighting = ring_lights(images, theta)
    elif lights == "colour":
        phase = 2 * np.pi * np.arange(images) / images
        hue = 0.5 + 0.5 * np.cos(phase[:, None] - np.array([0.0, 2.0, 4.0]) * np.pi / 3)
        lighting = ring_lights(images, theta, 0.1 + 0.9 * hue)
    elif lights == "mixed":
        lighting = mixed_lights(images, theta)
    else:  # "one-sided"
        phi = np.linspace(0.0, np.pi, images)
        t = np.deg2rad(theta)
        dirs = np.stack([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi),
                         np.full(images, np.cos(t))], axis=1)
        lighting = Lighting(dirs[:, None, :], np.ones((images, 1, 3)))
    scene = smiley_surface(size, relief=relief)
    gsize = _gauge_side(gauge_radius)
    gauge = sphere_surface(gsize, gauge_radius)
    scene_stack = render(scene, lighting, brdf=brdf, noise=noise, seed=seed,
                         cast_shadows=cast_shadows, gloss=gloss)
    gauge_stack = render(gauge, lighting, brdf=brdf, noise=noise, seed=seed + 1)
    files = {}
    for k in range(images):
        for name, stack in (("scene", scene_stack), ("gauge", gauge_stack)):
            if file_format == "exr":
                files[f"{name}_{k:02d}.exr"] = lambda path, image=stack[k]: write_image(
                    path, image, dtype="half", channel_names=["R", "G", "B"])
            else:
                files[f"{name}_{k:02d}.png"] = lambda path, image=stack[k]: write_image(
                    path, srgb_encode(image), dtype="uint8")
    normals = np.where(scene.mask[..., None], scene.normals, np.nan)
    albedo = np.where(scene.mask[..., None], scene.albedo, np.nan)
    mask = scene.mask.astype(np.float32)
    files.update({
        "truth_normal.exr": lambda path: write_image(path, normals, channel_names=["X", "Y", "Z"]),
        "truth_albedo.exr": lambda path: write_image(path, albedo, channel_names=["R", "G", "B"]),
        "truth_mask.png": lambda path: write_image(path, mask, dtype="uint8"),
        "truth_height.exr": lambda path: write_image(path, scene.height, channel_names=["Z"]),
        "mask.png": lambda path: write_image(path, mask, dtype="uint8")})
    if cast_shadows and images <= 8:
        blocked = shadow_maps(scene, lighting).any(axis=1)
        code = (blocked * (1 << np.arange(images))[:, None, None]).sum(axis=0)
        files["truth_shadows.png"] = lambda path: write_image(path, code / 255.0, dtype="uint8")
    centre = (gsize - 1) / 2.0
    info = dict(
        made_by="colorps synth", size=size, images=images, theta_deg=theta, lights=lights,
        brdf=brdf, noise=noise, seed=seed, relief=relief, cast_shadows=cast_shadows,
        gloss=gloss, file_format=file_format, gauge_albedo=1.0,
        gauge_sphere=dict(cx=centre, cy=centre, r=gauge_radius),
        light_directions=lighting.directions.tolist(), light_colours=lighting.colours.tolist(),
    )
    files["sample.json"] = lambda path: path.write_text(json.dumps(info, indent=1))
    return files, info
