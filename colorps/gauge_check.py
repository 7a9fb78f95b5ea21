"""Does the gauge look like a lit sphere, and the scene like its lights? Checks of
the images against what they should show, and the choice of their encoding.

Every gauge image, under one distant light, should shade its sphere like a
matte ball: I(q) = max(0, n(q) . L) with n(q) the sphere's normal at pixel q
and L the light (times the albedo). :func:`sphere_fit` fits L to each image by
least squares on the pixels it lights and gives the relative RMS residual.
A real matte gauge, decoded right, leaves a few percent (its finish is not
quite Lambertian); much more says the images are not of a lit sphere at that
place. Two mistakes show so:

* **the wrong images or place**: scene and gauge swapped, another object, a
  wrong ``--sphere``, a chrome ball: a residual over POOR_FIT
  (:func:`check_gauge` warns, naming the first gauge file);
* **the wrong encoding**: 8- or 16-bit files decoded as sRGB that are linear
  (or the other way): the fit of the other decoding is much better
  (under ENCODING_RATIO of this one's). Under ``--encoding auto`` the files
  are then read as linear (the record's ``decoded_as``, with a warning that
  says so); with an explicit ``--encoding`` the warning gives the one to use.

With calibrated lights and no gauge, :func:`check_lights` asks the same of the
scene: each pixel's measurements fitted as a matte surface under the known
lights (:func:`lights_fit`).
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .brdf import BRDF
from .camera import Camera
from .errors import CameraWarning, EncodingWarning, GaugeError, GaugeWarning
from .gauge import Gauge
from .geometry import angular_error, at_nearest_normal
from .lights import Lights
from .noise import NoiseModel, estimate_noise, lit_measurements

if TYPE_CHECKING:
    from .results import ReconstructionStats

__all__ = ["ENCODING_RATIO", "POOR_FIT", "as_linear", "check_gauge", "check_lights",
           "finish_differs", "finish_may_differ", "judge_finish", "lambertian_fit", "lens_bias",
           "lens_hint", "lights_fit", "noisier_scene", "shows_finish", "sphere_fit",
           "with_lens_bias"]

# ---------------------------------------------------------------- tuning
#: Relative RMS residual of the Lambertian sphere fit above which the gauge
#: images do not look like a lit sphere: synthetic matte, glossy (0.3) and rough
#: (Oren-Nayar 0.5) gauges left 0.01, 0.07 and 0.10; a smiley scene read as the
#: gauge (stacks swapped) 0.26.
POOR_FIT = 0.18
#: The other decoding fits better by at least this factor: the encoding is wrong.
ENCODING_RATIO = 0.5
#: A pixel takes part in an image's fit where the fitted light reaches it by at
#: least this fraction of its strength (the terminator is left out).
LIT_FRACTION = 0.1
#: Rounds of fitting the light and choosing the pixels it lights.
FIT_ROUNDS = 3
#: Scene pixels sampled for :func:`lights_fit`.
LIGHTS_FIT_PIXELS = 4000
#: :func:`finish_differs` holds when the scene matches the gauge at a median of
#: more than FINISH_HINT_SCALE noise units (the run's model scale: about 1 where
#: the gauge's finish is the scene's, 1.0-1.2 with bounced light; on the
#: real-shapes folds 3.9-4.1 for a rough scene against a Lambertian gauge or the
#: reverse, 9.0 for a glossy scene against a matte gauge, 6.1 for a glossy scene
#: and gauge, 1.2-1.3 for a varnished scene or gauge; 1.5-2.2 for a gauge only a
#: little rougher or smoother than the scene, Oren-Nayar 0.2 against 0.3, 0.15
#: against Lambert) while the gauge shades like a matte sphere, its
#: :func:`sphere_fit` under MATTE_FIT (Lambertian 0.003, rough 0.064, the GGX
#: coat of the glossy set 0.24; POOR_FIT is where it stops looking like a sphere).
FINISH_HINT_SCALE = 1.5
#: Above FINISH_ASK_SCALE (and up to FINISH_HINT_SCALE) a scene may be of another
#: finish, or only hold some bounced light (1.0-1.2): :func:`finish_may_differ`
#: holds, and the route fits the scene's own finish under the gauge's lights but
#: solves it again only where that finish shows one (:func:`shows_finish`). A
#: varnished scene on a matte gauge (1.2-1.3) was solved at 0.35 degrees median
#: with 39 % of its errors within the 68 % radius; through the route 0.12.
FINISH_ASK_SCALE = 1.2
MATTE_FIT = 0.1
#: A scene whose own pixel-to-pixel scatter (:func:`colorps.noise.estimate_noise`
#: on its masked pixels, as ``--lights`` runs measure it) has at least this many
#: times the sigma of the gauge's noise model, at the scene's median measurement,
#: is noisier than its gauge: its residuals in the gauge's noise units overstate
#: its misfit by as much, and :func:`finish_differs` divides the model scale by
#: it. A gauge path-traced without Monte Carlo noise (a lone sphere under
#: directional lights) against a scene that carries its bounced light's: 8.1-9.6
#: (Mitsuba 3, benchmarks/independent_renders.py), where the route of the gauge's
#: lights took a glossy pot from 0.82 to 3.16 degrees median. Scene and gauge of
#: one camera: about 1 (the textured sample, 1.04); under this factor, texture
#: the estimate takes for noise cannot hide another finish.
NOISIER_SCENE = 2.0
#: Measurements (at most) whose median is the scene's level for that comparison.
NOISE_LEVEL_SAMPLE = 100_000
#: The solution with the gauge's lights and the scene's own finish is taken when
#: its median residual (noise units) is under this fraction of the gauge's. On
#: the gauges a little off the scene's finish it was 0.53-0.80 of it, and the
#: normals 0.11-0.57 degrees off instead of 1.4-2.6 on all six; where the
#: finishes match, 1.0-1.7 (docs/benchmarks.md).
CLEARLY_BETTER = 0.85
#: A scene noisier than its gauge (NOISIER_SCENE) takes that solution when its
#: own fitted finish is one the gauge's match gets wrong (:func:`shows_finish`):
#: a highlight of at least NOISY_SCENE_HIGHLIGHT (the share of light it reflects
#: at normal incidence; clear coats 0.04) on the scene or on the gauge, a
#: roughness NOISY_SCENE_ROUGHNESS apart (radians), or a falloff
#: NOISY_SCENE_FALLOFF apart at some incidence (another coat's): its residuals
#: cannot tell. Mitsuba 3's textured pots with one bounce, 7.9-9.0 times
#: noisier than their gauges: under a GGX coat (0.067 fitted) 0.72 -> 0.52
#: degrees median, on a matte gauge 4.16 -> 2.85; matte (a lobe of 7e-6 fitted
#: to the noise) kept, 0.28 (0.37 had it been taken); matte on a coated gauge
#: 2.79 -> 0.46 (its finish had been compared with a matte gauge's).
NOISY_SCENE_HIGHLIGHT = 0.01
#: Roughnesses (Oren-Nayar sigma, radians) this far apart differ (the fit's grid
#: steps by 0.1).
NOISY_SCENE_ROUGHNESS = 0.05
#: Falloffs this far apart at some knot differ (a clear coat of alpha 0.3 takes
#: 0.33 at grazing, 0.05 at the cosine 0.6).
NOISY_SCENE_FALLOFF = 0.05
#: A matte gauge read without a camera is fitted again through pinholes of focal
#: lengths LENS_FOCAL_RADII times its radius (principal point at the image's
#: centre); when the best of them, inside that range, leaves under LENS_BETTER of
#: the orthographic reading's Lambertian residual, the images were taken through
#: a lens (warned). On LENS_PIXELS of the gauge's pixels within LENS_INNER of its
#: radius. A Mitsuba gauge seen at 3772 px: 0.0013 at 3800 px, 0.0106 orthographically.
LENS_FOCAL_RADII = np.geomspace(4.0, 400.0, 17)
LENS_BETTER = 0.25
LENS_PIXELS = 1500
LENS_INNER = 0.9


def sphere_fit(stack: np.ndarray, gauge: Gauge) -> float:
    """Median over the images of the relative RMS residual of a Lambertian fit.

    Parameters
    ----------
    stack : (m, Hg, Wg, c) ndarray
        Linear gauge images.
    gauge : Gauge
        Its geometry (the normals inside its mask).

    Returns
    -------
    float
        sqrt(sum r^2 / sum I^2) over the lit pixels of each image (I the bands'
        mean, r = I - n . L), the median over the images.
    """
    return _sphere_fit_pixels(np.asarray(stack)[:, gauge.mask], gauge.normals[gauge.mask])


def _sphere_fit_pixels(pixels: np.ndarray, normals: np.ndarray) -> float:
    """:func:`sphere_fit` of the gauge's (m, P, c) pixels at their (P, 3) normals:
    one light fitted per image."""
    return _lambert_residual(np.asarray(pixels, np.float64).mean(axis=-1), normals,
                             min_lit=10)


def lambertian_fit(values: np.ndarray, design: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each row of ``values`` (R, K) fitted as design @ x_r (``design`` (K, 3): the
    normals of a gauge's pixels, or the directions of the lights) by least
    squares on its lit entries, FIT_ROUNDS times, an entry lit where the fit
    gives it at least LIT_FRACTION of |x_r| (at first: of the row's largest
    value). Non-finite entries take no part. Returns x (R, 3) and the lit
    entries (R, K) of the last fit."""
    finite = np.isfinite(values)
    values = np.where(finite, values, 0.0)
    lit = finite & (values > LIT_FRACTION * values.max(axis=1, keepdims=True))
    x = np.zeros((len(values), 3))
    for _ in range(FIT_ROUNDS):
        weight = lit.astype(np.float64)
        normal = np.einsum("rk,ka,kb->rab", weight, design, design) + 1e-12 * np.eye(3)
        x = np.linalg.solve(normal, np.einsum("rk,ka,rk->ra", weight, design,
                                              values)[..., None])[..., 0]
        lit = finite & (x @ design.T > LIT_FRACTION * np.linalg.norm(x, axis=1, keepdims=True))
    return x, lit


def _lambert_residual(values: np.ndarray, design: np.ndarray, min_lit: int) -> float:
    """Median over the rows of ``values`` (R, K) of the relative RMS residual of
    their :func:`lambertian_fit`; rows with fewer than ``min_lit`` lit entries
    do not count. The residual is sqrt(sum r^2 / sum I^2) over the lit entries;
    NaN when no row counts."""
    x, lit = lambertian_fit(values, design)
    values = np.where(np.isfinite(values), values, 0.0)
    enough = lit.sum(axis=1) >= min_lit
    if not enough.any():
        return float("nan")
    r2 = np.where(lit, (values - x @ design.T) ** 2, 0.0).sum(axis=1)
    i2 = np.where(lit, values ** 2, 0.0).sum(axis=1)
    return float(np.median(np.sqrt(r2[enough] / np.maximum(i2[enough], 1e-30))))


def lights_fit(scene: np.ndarray, lights: Lights, mask: np.ndarray | None = None,
               seed: int = 0) -> float:
    """Median relative RMS residual of Lambertian fits of scene pixels to known lights.

    Each of up to LIGHTS_FIT_PIXELS pixels (inside ``mask``) is fitted as
    I_j = L_j . b (the bands' mean over each light's mean intensity; b the
    albedo times the normal) by least squares on the lights that reach it
    (FIT_ROUNDS rounds, as :func:`sphere_fit`).

    Parameters
    ----------
    scene : (m, H, W, c) ndarray
        Linear scene images, one per light.
    lights : Lights
    mask : (H, W) ndarray of bool, optional
    seed : int, optional
        Of the pixel sample.

    Returns
    -------
    float
        NaN when no pixel has 4 lit measurements.
    """
    return _lights_fit_pixels(_sample(scene, mask, seed), lights)


def _sample(scene: np.ndarray, mask, seed: int = 0) -> np.ndarray:
    """Up to LIGHTS_FIT_PIXELS pixels of the scene inside ``mask``: (m, P, c)."""
    _m, h, w, _c = scene.shape
    inside = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    ys, xs = np.nonzero(inside)
    if len(ys) > LIGHTS_FIT_PIXELS:
        pick = np.sort(np.random.default_rng(seed).choice(len(ys), LIGHTS_FIT_PIXELS,
                                                          replace=False))
        ys, xs = ys[pick], xs[pick]
    return np.asarray(scene[:, ys, xs])


def _lights_fit_pixels(pixels: np.ndarray, lights: Lights) -> float:
    """:func:`lights_fit` of (m, P, c) scene pixels: one albedo-scaled normal
    fitted per pixel."""
    strength = lights.intensities.mean(axis=1)  # (m,)
    values = np.asarray(pixels, np.float64).mean(axis=-1).T / strength  # (P, m)
    return _lambert_residual(values, lights.directions, min_lit=4)


def linear_codes(values: np.ndarray, top_code: int) -> np.ndarray:
    """What integer files decoded as sRGB hold read as linear: their codes over
    ``top_code``, recovered exactly (colour-science's sRGB encoding, rounded to
    the codes) and scaled as OpenImageIO reads them (times the float32 of
    1 / top_code), so that the values are those of a linear read bit for bit."""
    import colour

    codes = colour.cctf_encoding(np.clip(np.asarray(values, np.float64), 0, 1),
                                 function="sRGB")
    return np.rint(codes * top_code).astype(np.float32) * np.float32(1.0 / top_code)


def as_linear(stack: np.ndarray, paths, info, name: str) -> np.ndarray:
    """A stack of integer files read as sRGB, as a linear read gives it, bit for bit:
    8- and 16-bit codes recoded in place (:func:`colorps.transfer.recode`, faster than
    decoding the files again), other integer types read again. ``info``: the first
    file's :class:`~colorps.io.ImageInfo`; ``name``: the stack's, for errors."""
    from .io import read_stack, top_code
    from .transfer import TABLE_TYPES, recode

    if info.pixel_type not in TABLE_TYPES:
        return read_stack(paths, "linear", name=name, warn_lossy=False)[0]
    recode(stack, top_code(info), "srgb", "linear")
    return stack


def _encoding_verdict(fit, stack, fitted: float, encoding: str, top_code: int | None,
                      first_file: Path, what: str) -> dict:
    """The other decoding's fit, and whether to read the files the other way."""
    record = dict(other_encoding_residual=None, decoded_as=None)
    if top_code is None and encoding != "srgb":
        return record  # (floating-point files are linear unless told otherwise)
    import colour

    from .io import srgb_decode

    read_as_srgb = encoding in ("auto", "srgb")
    if top_code is None:  # floating-point files told to be sRGB: as stored (unclipped)
        other = colour.cctf_encoding(np.maximum(np.asarray(stack, np.float64), 0.0), "sRGB")
    else:
        other = linear_codes(stack, top_code) if read_as_srgb else \
            srgb_decode(np.clip(stack, 0, 1))
    other_fit = fit(other)
    record["other_encoding_residual"] = other_fit
    if not other_fit < ENCODING_RATIO * fitted:
        return record
    this, that = ("sRGB", "linear") if read_as_srgb else ("linear", "sRGB")
    told = (f"{first_file}: {what} fits far better read as {that} (relative residual "
            f"{other_fit:.3f}) than as {this} ({fitted:.3f})")
    if encoding == "auto":
        record["decoded_as"] = "linear"
        warnings.warn(f"{told}: the files are read as linear (--encoding auto); pass "
                      "--encoding srgb to read them as sRGB anyway", EncodingWarning,
                      stacklevel=4)
    else:
        flag = that.lower()
        warnings.warn(f"{told}: the files are probably {flag}; pass --encoding {flag}",
                      EncodingWarning, stacklevel=4)
    return record


def check_lights(scene: np.ndarray, lights: Lights, mask, first_file: Path, encoding: str,
                 top_code: int | None) -> dict:
    """Fit the scene to its lights (:func:`lights_fit`) as decoded and the other
    way; warn, or under "auto" choose linear, as :func:`check_gauge` does.

    Returns what report.json records: ``lights_fit_residual``,
    ``other_encoding_residual`` and ``decoded_as`` ("linear" when the files are
    to be read so, else None).
    """
    pixels = _sample(scene, mask)  # both decodings of the same pixels, not the stack

    def fit(values):
        return _lights_fit_pixels(values, lights)

    fitted = fit(pixels)
    return dict(lights_fit_residual=fitted,
                **_encoding_verdict(fit, pixels, fitted, encoding, top_code, first_file,
                                    "the scene's shading under the lights"))


def check_gauge(stack: np.ndarray, gauge: Gauge, first_file: Path, encoding: str,
                top_code: int | None) -> dict:
    """Warn when the gauge images do not look like a lit sphere; compare the other
    decoding of integer files, and under "auto" choose linear when it fits far
    better. Returns what report.json records.

    Parameters
    ----------
    stack : (m, Hg, Wg, c) ndarray
        The gauge images as decoded.
    gauge : Gauge
    first_file : Path
        The first gauge file, for messages.
    encoding : {"auto", "linear", "srgb"}
        How the files were decoded ("auto": sRGB for integer files).
    top_code : int or None
        The files' largest code (255 for 8-bit); None for floating-point files
        (linear: no encoding question, unless ``encoding`` is "srgb").

    Returns
    -------
    dict
        ``sphere_fit_residual``, ``other_encoding_residual`` and
        ``decoded_as`` ("linear" when the files are to be read so, else None).
    """
    pixels = np.asarray(stack)[:, gauge.mask]  # (m, P, c): the sphere's pixels only
    normals = gauge.normals[gauge.mask]

    def fit(values):
        return _sphere_fit_pixels(values, normals)

    fitted = fit(pixels)
    record = dict(sphere_fit_residual=fitted,
                  **_encoding_verdict(fit, pixels, fitted, encoding, top_code, first_file,
                                      "the gauge's shading of a lit sphere"))
    other = record["other_encoding_residual"]
    best = fitted if other is None else min(fitted, other)
    if best > POOR_FIT:
        warnings.warn(
            f"{first_file}: the gauge images do not look like a matte sphere lit from one "
            f"direction at the given place (relative residual of a Lambertian fit "
            f"{best:.2f}; matte gauges leave about 0.1 or less): check that scene and gauge "
            "are not swapped, --sphere, and that the gauge is not a mirror ball",
            GaugeWarning, stacklevel=3)
    return record


def lens_hint(stack: np.ndarray, gauge: Gauge, first_file: Path) -> dict | None:
    """Whether a gauge read orthographically shades as if seen through a lens.

    Its Lambertian fit (:func:`sphere_fit`) is tried again with the normals of
    pinholes of LENS_FOCAL_RADII times its radius; warns (CameraWarning) when
    the best leaves under LENS_BETTER of the orthographic residual. A glossy or
    rough gauge's shading does not tell a lens (its highlights or its falloff
    move the best focal length), so only a matte one is asked (MATTE_FIT).

    Parameters
    ----------
    stack : (m, Hg, Wg, c) ndarray
        Linear gauge images.
    gauge : Gauge
        The sphere as read (orthographically).
    first_file : Path
        The first gauge file, for messages.

    Returns
    -------
    dict or None
        ``focal_px``, ``residual`` and ``orthographic_residual``, and when it
        warns ``normals_off_deg`` (the median of :func:`lens_bias` on the
        sphere); None for a gauge that is not a matte sphere.
    """
    if gauge.sphere is None:
        return None
    cx, cy, r = gauge.sphere
    ys, xs = np.nonzero(gauge.mask)
    inner = np.flatnonzero(np.hypot(xs - cx, ys - cy) < LENS_INNER * r)
    inner = inner[np.linspace(0, inner.size - 1, min(LENS_PIXELS, inner.size)).astype(int)]
    ys, xs = ys[inner], xs[inner]
    pixels = np.asarray(stack)[:, ys, xs]
    orthographic = _sphere_fit_pixels(pixels, gauge.normals[ys, xs])
    if not orthographic < MATTE_FIT:
        return None
    fits = np.full(LENS_FOCAL_RADII.size, np.nan)
    for k, focal in enumerate(LENS_FOCAL_RADII):
        normals = _through_lens(gauge, focal * r, ys, xs)
        if normals is not None:  # (else a sphere that lens would not show whole)
            fits[k] = _sphere_fit_pixels(pixels, normals)
    if not np.isfinite(fits).any():
        return None
    best = int(np.nanargmin(fits))
    inside = 0 < best < len(fits) - 1
    step = 0.0  # a parabola through the best and its neighbours, in log focal length
    if inside and fits[best - 1] - 2 * fits[best] + fits[best + 1] > 0:
        a, b, c = fits[best - 1:best + 2]
        step = float(np.clip(0.5 * (a - c) / (a - 2 * b + c), -1.0, 1.0))
    focal = LENS_FOCAL_RADII[best] * (LENS_FOCAL_RADII[1] / LENS_FOCAL_RADII[0]) ** step
    record = dict(focal_px=float(focal * r), residual=float(fits[best]),
                  orthographic_residual=float(orthographic))
    if inside and fits[best] < LENS_BETTER * orthographic:
        record["normals_off_deg"] = float(np.median(lens_bias(gauge, record["focal_px"],
                                                              gauge.normals[ys, xs])))
        warnings.warn(
            f"{first_file}: the gauge shades as a matte sphere seen through a lens of focal "
            f"length about {record['focal_px']:.0f} px (its Lambertian fit leaves "
            f"{fits[best]:.4f} then, {orthographic:.4f} read orthographically, with the "
            "principal point at the image's centre): without --camera its normals are read "
            f"as if seen from infinitely far, {record['normals_off_deg']:.2f} degrees off "
            "(each normal's uncertainty takes that in); give the camera's K.txt, or "
            f"--camera {record['focal_px']:.0f} for this estimate (its principal point at "
            "the image's centre)", CameraWarning, stacklevel=3)
    return record


def lens_bias(gauge: Gauge, focal_px: float, normals: np.ndarray) -> np.ndarray:
    """How far (degrees) normals matched on ``gauge`` read orthographically are off
    if it was seen through a pinhole of ``focal_px`` (principal point at the
    image's centre): at each of ``normals`` (..., 3; NaN where not solved), the
    angle between the orthographic normal and the lens's at the gauge pixel of
    the nearest orthographic normal (on a LENS_PIXELS sample of the sphere)."""
    ys, xs = np.nonzero(gauge.mask)
    pick = np.linspace(0, ys.size - 1, min(LENS_PIXELS, ys.size)).astype(int)
    ys, xs = ys[pick], xs[pick]
    through = _through_lens(gauge, focal_px, ys, xs)
    seen = (through != 0).any(axis=1)
    ys, xs, off = ys[seen], xs[seen], angular_error(through[seen], gauge.normals[ys[seen],
                                                                                 xs[seen]])
    return at_nearest_normal(gauge.normals[ys, xs], off, normals)


def with_lens_bias(result, gauge: Gauge, record: dict):
    """``result`` (a :class:`~colorps.Reconstruction` matched on ``gauge`` read
    orthographically) with :func:`lens_bias` added to its 68 % radii where
    :func:`lens_hint` found a lens (``record``'s ``lens_fit`` has
    ``normals_off_deg``): the bias through a lens one step of LENS_FOCAL_RADII
    shorter than the one found (the fit's bracket: the bias goes as one over the
    focal length, and the errors of a lens read orthographically are that bias
    to within a few per cent); else ``result`` as it is."""
    lens_fit = record.get("lens_fit") or {}
    if "normals_off_deg" not in lens_fit:
        return result
    shortest = lens_fit["focal_px"] * LENS_FOCAL_RADII[0] / LENS_FOCAL_RADII[1]
    return result.with_uncertainty_added(lens_bias(gauge, shortest, result.normals))


def _through_lens(gauge: Gauge, focal_px: float, ys: np.ndarray,
                  xs: np.ndarray) -> np.ndarray | None:
    """The (P, 3) normals at pixels (``ys``, ``xs``) of ``gauge``'s sphere seen
    through a pinhole of ``focal_px`` with the principal point at its image's
    centre (zero off that sphere); None where that lens would not show it whole."""
    cx, cy, r = gauge.sphere
    h, w = gauge.mask.shape
    y0, x0 = max(0, int(cy - r) - 2), max(0, int(cx - r) - 2)
    box = (min(h, int(cy + r) + 3) - y0, min(w, int(cx + r) + 3) - x0)  # the sphere's alone
    camera = Camera(focal_px, focal_px, (w - 1) / 2 - x0, (h - 1) / 2 - y0)
    try:
        seen = Gauge.from_sphere(box, cx - x0, cy - y0, r, camera=camera)
    except GaugeError:
        return None
    return seen.normals[ys - y0, xs - x0]


def finish_differs(model_scale: float, record: dict, above: float = FINISH_HINT_SCALE) -> bool:
    """A gauge-mode run that looks like a scene of another finish than its matte
    gauge's: its model scale over ``above`` (FINISH_HINT_SCALE), the gauge under
    MATTE_FIT; ``record`` is :func:`check_gauge`'s, with the scene's
    ``scene_noise_over_gauge`` once :func:`noisier_scene` measured it
    (NOISIER_SCENE), and not when its images look out of step with the gauge's."""
    if record.get("pairing", {}).get("looks_out_of_step"):
        return False  # images and gauge out of step: not a finish to fit
    fit = record.get("sphere_fit_residual")
    noisier = record.get("scene_noise_over_gauge") or 1.0
    if noisier >= NOISIER_SCENE:
        model_scale /= noisier
    return bool(model_scale > above and fit is not None and fit < MATTE_FIT)


def finish_may_differ(model_scale: float, record: dict) -> bool:
    """:func:`finish_differs` from FINISH_ASK_SCALE up: a scene whose own fitted
    finish is to be asked (:func:`shows_finish`) before it is solved again."""
    return finish_differs(model_scale, record, FINISH_ASK_SCALE)


def noisier_scene(scene: np.ndarray, mask: np.ndarray | None, stats: ReconstructionStats,
                  record: dict) -> bool:
    """Whether a run that :func:`finish_differs` flags (its ``stats``)
    may be only a scene noisier than its gauge (NOISIER_SCENE): the (m, H, W, c)
    ``scene``'s own noise sigma over the run's (the gauge's) at the scene's median
    measurement, added to ``record`` as ``scene_noise_over_gauge``. Its residuals
    then cannot tell another finish from the noise (:func:`judge_finish`)."""
    model_scale = stats.model_scale
    usable = lit_measurements(scene, mask)
    gauge_noise = NoiseModel(**stats.noise)
    own = estimate_noise(scene, usable, gauge_noise)
    picked = np.flatnonzero(usable)
    picked = picked[::max(1, picked.size // NOISE_LEVEL_SAMPLE)]
    level = float(np.median(scene.reshape(-1, scene.shape[3])[picked]))
    ratio = record["scene_noise_over_gauge"] = float(own.sigma(level) / gauge_noise.sigma(level))
    return ratio >= NOISIER_SCENE and not finish_differs(model_scale, record)


def judge_finish(record: dict, first_file: Path, *, noisier: float | None = None,
                 finish=None, gauge_finish=None) -> bool:
    """Whether a run whose scene the matte gauge explained poorly takes the
    solution with the gauge's lights and the scene's own finish (``finish``, a
    :class:`~colorps.brdf.BRDF`): its median residual is under CLEARLY_BETTER of
    the gauge's (both in ``record``, noise units; ``taken`` is added). When the
    scene is ``noisier`` than its gauge (that many times: :func:`noisier_scene`;
    the warning then names the scene's ``first_file``) its residuals
    cannot tell: it is taken when that finish differs from the gauge's own
    (``gauge_finish``; :func:`shows_finish`). Warns of what was done. A run
    that could not try it (``residual_with_gauge_lights`` None: a tiled run) is
    told how to, by hand."""
    gauge, own = record["residual_with_gauge"], record["residual_with_gauge_lights"]
    if noisier is not None:
        record["taken"] = bool(own is not None and finish is not None and
                               shows_finish(finish, gauge_finish))
        _say_noisier(record, noisier, first_file)
        return record["taken"]
    record["taken"] = bool(own is not None and own < CLEARLY_BETTER * gauge)
    seen = (f"the scene matches the gauge at {gauge:.1f} noise units (median; about 1 "
            "where the gauge explains it), though the gauge shades like a matte sphere")
    if own is None:
        why = f"could not ({record['failed']})" if "failed" in record else \
            "does not try it itself in a tiled run"
        said = (f"{seen}: if the scene's finish differs from the gauge's, every normal is "
                f"biased alike. The way out, lights measured on the gauge, {why}: by hand, "
                "colorps calibrate-lights 'GAUGE_IMAGES' --sphere ... --matte --out "
                "lights.json (with this run's --camera, and its --gauge-albedo as --albedo), "
                "then reconstruct with --lights lights.json, which fits the scene's own "
                "finish")
    elif record["taken"]:
        said = (f"{seen}: its finish is not the scene's. Solved instead with the lights "
                "measured on the gauge and the scene's own fitted finish (as calibrate-"
                f"lights --matte and --lights would), which matches at {own:.1f}; "
                "report.json's gauge_check.finish says so")
    else:
        said = (f"{seen}; the lights measured on it with the scene's own fitted finish did "
                f"no better ({own:.1f}), so the gauge's result is kept. Something else "
                "departs from the gauge: lights near the object, bounced light, or scene "
                "and gauge lit or exposed differently")
    warnings.warn(f"{first_file}: {said}", GaugeWarning, stacklevel=3)
    return record["taken"]


def shows_finish(finish, gauge_finish=None) -> bool:
    """Whether a scene's fitted finish (a :class:`~colorps.brdf.BRDF`) is one its
    gauge's match gets wrong, its residuals aside: it or the gauge's own
    (``gauge_finish``, fitted at its known normals; default a matte one) has a
    highlight of NOISY_SCENE_HIGHLIGHT (a grey gauge's signatures cannot hold a
    white highlight on coloured patches, whatever its own finish), or their
    roughnesses are NOISY_SCENE_ROUGHNESS apart, or their falloffs
    NOISY_SCENE_FALLOFF apart at some incidence."""
    gauge_finish = gauge_finish or BRDF.lambert()
    falloff_apart = np.abs(np.subtract(finish.falloff, gauge_finish.falloff)).max()
    return (max(*finish.specular, *gauge_finish.specular) >= NOISY_SCENE_HIGHLIGHT
            or abs(finish.roughness - gauge_finish.roughness) >= NOISY_SCENE_ROUGHNESS
            or falloff_apart >= NOISY_SCENE_FALLOFF)


def _say_noisier(record: dict, ratio: float, first_file: Path) -> None:
    """Warn of a scene noisier than its gauge, and of what :func:`judge_finish` did."""
    said = (f"the scene matches the gauge at {record['residual_with_gauge']:.1f} noise "
            "units (median; about 1 where the gauge explains it), but its own pixel-to-pixel "
            f"scatter is {ratio:.1f} times the gauge's noise, which "
            "explains it: the scene is noisier than its gauge (a gauge rendered without the "
            "scene's Monte Carlo noise, or photographed at a lower ISO)")
    if record["taken"]:
        said += (", so its residuals cannot tell its finish from the gauge's; but a "
                 "highlight on either, or its own fitted finish's roughness or falloff, "
                 "differs from what the gauge's match assumes. Solved instead with the "
                 "lights measured on the "
                 "gauge and that finish; report.json's gauge_check.finish says so")
    else:
        why = "could not be fitted" if "failed" in record else "is the matte gauge's"
        said += (f", not of another finish (its own fitted finish {why}): the gauge's result "
                 "is kept. Residuals and quality.exr are in the gauge's noise units; "
                 "report.json's gauge_check.scene_noise_over_gauge says so")
    warnings.warn(f"{first_file}: {said}", GaugeWarning, stacklevel=4)
