"""A gauge with no photographs: rendered under calibrated lights, with the scene's finish.

With a light file instead of gauge images (``--lights``) the gauge is
rendered (:meth:`colorps.Gauge.virtual`) under the calibrated lights. Its
finish must be the scene's, or every match is biased, so
:func:`fit_scene_brdf` fits it from the scene itself: match against a
Lambertian virtual gauge, fit a :class:`~colorps.brdf.BRDF` to a sample of
the scene at those normals (:func:`colorps.brdf.fit_brdf`), render, match,
fit again. The gauge is rendered for a view along the optical axis; through
a lens, :func:`view_corrected` turns a scene's measurements into those of
that view, under the fitted finish at the first match's normals, for a
second match. :func:`virtual_gauge` is the whole step for a run: the noise
measured on the scene where the options say "auto" (a rendered gauge has no
scatter to measure), the finish, the rendered gauge, and the settings that
describe it (:meth:`colorps.resolve.StackModel.rendered`). This module sits
above :mod:`colorps.gauge`, :mod:`colorps.brdf` and :func:`colorps.reconstruct`.
"""

from __future__ import annotations

import dataclasses
import sys
import warnings

import numpy as np

from ._blas import one_blas_thread
from ._pages import small_pages
from .brdf import BRDF, best_normals
from .brdf_fit import fit_brdf, refined_roughness, relative_weights, roughness_bracket
from .camera import Camera
from .errors import ColorPSWarning, InputError
from .gauge import DEFAULT_VIRTUAL_RADIUS, Gauge
from .lights import Lights
from .noise import estimate_noise, lit_measurements
from .options import Options
from .reconstruct import reconstruct
from .resolve import Resolved, StackModel, resolve

__all__ = ["corrected", "fit_scene_brdf", "match_along_rays", "matched_again", "rendered",
           "view_corrected", "virtual_gauge", "without_highlight"]

# ---------------------------------------------------------------- tuning
#: fit_scene_brdf fits this many times: at the normals of a Lambertian gauge,
#: then at those of the previous fit (on DiLiGenT Ball the mean error went
#: 2.71, 1.96, 1.37, 1.35 degrees after 0, 1, 2, 3 fits).
SCENE_FITS = 2
#: Under this share of what the first fit's finish gives it, a measurement is
#: cast shadow, out of :func:`without_highlight`'s second fit.
SHADOW_BELOW = 0.75
#: The first fit starts at a Lambertian gauge's normals, which a rough or coated
#: finish tilts by degrees: it holds the diffuse falloff at Lambert's for its
#: first SETTLE_ROUNDS rounds (:func:`colorps.brdf.fit_brdf`) while they settle;
#: the second starts at normals matched under the first and frees it at once.
#: Mean error, virtual gauge (SETTLE_ROUNDS 0 / 1 / 2 / 3): Oren-Nayar 0.3 folds
#: 4.41 / 1.47 / 0.21 / 0.18 degrees, DiLiGenT Ball 1.11 / 1.15 / 1.16 / 1.19
#: (where shading cannot tell the falloff from tilted normals, the free
#: falloff happened to be nearer), glossy and varnished folds unchanged.
SETTLE_ROUNDS = 2
#: Fewer images than this leave too few measurements per pixel to tell a
#: finish from tilted normals: the scene is taken as Lambertian.
MIN_FIT_IMAGES = 6
#: Pixels of the scene the fit uses (a fixed random sample of the solved ones).
#: 1500 against 2500: DiLiGenT Ball 1.13 against 1.15 degrees, the synthetic
#: glossy, rough and varnished sets as close or closer, the fits 35 % faster.
FIT_PIXELS = 1500
#: After its rounds the fit is compared, on the same sample of the scene, with
#: simpler finishes: its falloff set to Lambert's, and diffuse Oren-Nayar ones
#: (Lambert's falloff, no highlight) of its roughness and the grid's next ones.
#: The fit's own cost, over a sample at normals it refines, can settle where a
#: darker falloff stands in for tilted normals; the whole match then
#: prefers the simpler finish (an Oren-Nayar 0.2 scene, 8-bit under 48 lights:
#: fitted 0.95 noise units and 1.38 degrees, with Lambert's falloff 0.83 and
#: 0.20, also without the highlight 0.82 and 0.11, the true finish's numbers).
#: A simpler finish is taken only when its median residual is under SIMPLER_GAIN
#: of the fit's: on DiLiGenT Ball, whose falloff is real, Lambert's falloff
#: matched 1.28 against the fit's 1.29 and gave 1.82 degrees against 1.12 (and
#: Lambert itself, 1.28, 2.22 degrees: the match alone cannot tell these apart).
SIMPLER_GAIN = 0.95
#: The fit is kept when the scene matches it no more than this fraction worse
#: than a Lambertian gauge (a tie, within what a median over the sample
#: fixes, goes to the fit, which holds Lambert's finish): on a Lambertian scene
#: the fit chases the noise and matches 3-8 % worse, while DiLiGenT Ball, whose
#: falloff is real, matched its fits 0.1 % better or worse from run to run
#: (1.07 degrees mean kept, 2.22 dropped).
TIED_RESIDUALS = 0.01
#: The finishes are compared on this many of the fit's matched pixels at most (a
#: fixed random sample: a median residual to about 1 %, under SIMPLER_GAIN's 5 %).
CANDIDATE_PIXELS = 5000
#: The fit's rounds and the finishes' comparison match against gauges rendered
#: at this radius (pixels) at most: the refinement carries the normals between
#: the table's pixels, and a smaller table is much faster to search under many
#: lights. Against the run's radius (100) for the rounds: DiLiGenT Ball 1.115 /
#: 0.835 -> 1.086 / 0.770 degrees mean / median and its two rounds' matches
#: 2.6 -> 0.5 s each; the synthetic folds within 0.01 degrees (one-bounce set
#: 0.46 -> 0.29); Mitsuba's plastic pot 2.85 / 2.46 -> 2.81 / 2.40.
FIT_GAUGE_RADIUS = 50
#: The fit's rounds match at most this many pixels of the mask (a fixed random
#: sample; every pixel of smaller masks, as DiLiGenT's): the fit takes FIT_PIXELS
#: of them and compares median residuals, which a sample this size fixes to well
#: under 1 %. A 4 MP capture's two rounds took 20 s matching every pixel.
FIT_MATCH_PIXELS = 40_000
#: view_corrected and without_highlight take this many pixels at a time
#: (bounded temporaries).
VIEW_CHUNK = 2 ** 15


def virtual_gauge(scene: np.ndarray, lights: Lights, options: Options | Resolved, *,
                  mask=None, radius: float = DEFAULT_VIRTUAL_RADIUS, progress: bool = False,
                  camera: Camera | None = None, held_finish: BRDF | None = None
                  ) -> tuple[Gauge, Resolved, BRDF, list[dict] | None]:
    """The rendered gauge of a run with calibrated lights, and its settings.

    Parameters
    ----------
    scene : (m, H, W, c) ndarray
        Linear scene images, one per light.
    lights : Lights
    options : Options or Resolved
        The run's settings and how the scene is stored; "auto" read noise and
        gain are measured on the scene's pixel scatter (:func:`estimate_noise`),
        and ``options.brdf`` says whether the finish is fitted.
    mask : (H, W) array_like of bool, optional
        Scene pixels to fit the finish (and measure the noise) on.
    radius : float, optional
        Radius (pixels) of the rendered sphere.
    progress : bool, optional
        Say each finish fit's result on stderr.
    camera : Camera, optional
        The lens the scene was photographed through (:func:`fit_scene_brdf`).
    held_finish : BRDF, optional
        A gauge's finish, whose diffuse falloff the finish fit holds
        (:func:`fit_scene_brdf`).

    Returns
    -------
    gauge : Gauge
        With ``stack`` its rendered images.
    resolved : Resolved
        The run's settings with numbers for the noise, and the gauge as rendered.
    brdf : BRDF
        The finish the gauge is rendered with.
    history : list of dict or None
        Each finish fit (:func:`fit_scene_brdf`), None when not fitted.
    """
    with one_blas_thread(), small_pages():
        run = resolve(options)
        settings = run.options
        if "auto" in (settings.read_noise, settings.gain):
            fitted = estimate_noise(scene, lit_measurements(scene, mask), run.scene.noise)
            run = run.replace(
                read_noise=fitted.read if settings.read_noise == "auto" else settings.read_noise,
                gain=fitted.gain if settings.gain == "auto" else settings.gain)
        run = resolve(run, gauge=StackModel.rendered(run.options.dark_level))
        brdf, history = BRDF.lambert(), None
        if run.options.brdf == "fitted":
            brdf, history = fit_scene_brdf(scene, lights, run, mask=mask, radius=radius,
                                           progress=progress, camera=camera,
                                           held_finish=held_finish)
        return rendered(lights, brdf, radius, scene.shape[3]), run, brdf, history


def with_own_finish(scene: np.ndarray, lights: Lights, run: Resolved, *, mask=None,
                    radius: float = DEFAULT_VIRTUAL_RADIUS, camera: Camera | None = None,
                    progress: bool = False, held_finish: BRDF | None = None,
                    wanted=None):
    """The scene solved with a virtual gauge under ``lights`` of its own fitted
    finish (:func:`virtual_gauge`, :func:`match_along_rays`): for another gauge's
    lights, or for measurements whose bounced light was taken out
    (:mod:`colorps.interreflection`: a finish fitted with it in takes some of
    it for its falloff and highlight), ``held_finish``'s falloff held as
    :func:`fit_scene_brdf` says. Returns (the
    :class:`~colorps.Reconstruction`, its settings, (the finish, its fits)); the
    first two are None when ``wanted`` (a predicate on the fitted finish) says
    the scene need not be matched with it."""
    virtual, settings, brdf, fits = virtual_gauge(scene, lights, run, mask=mask,
                                                  radius=radius, progress=progress,
                                                  camera=camera, held_finish=held_finish)
    if wanted is not None and not wanted(brdf):
        return None, None, (brdf, fits)
    result, _ = match_along_rays(scene, virtual, settings, lights, brdf, camera, mask=mask,
                                 progress=progress)
    return result, settings, (brdf, fits)


def match_along_rays(scene: np.ndarray, gauge: Gauge, run: Resolved, lights: Lights,
                     brdf: BRDF, camera: Camera | None, *, mask=None, progress: bool = False):
    """Reconstruct ``scene`` against a virtual ``gauge`` rendered with ``brdf``
    (its diffuse part, for a white highlight: :func:`rendered`) under
    ``lights``, then, where the finish asks for it (:func:`matched_again`), once
    more with the scene :func:`corrected` (in place). Returns (the
    :class:`~colorps.Reconstruction`, the scene as last matched)."""
    result = reconstruct(scene, gauge.stack, gauge, run, mask=mask, progress=progress)
    if not matched_again(brdf, camera):
        return result, scene
    if progress:
        along = "each pixel seen along its own ray"
        why = (f"the white highlight taken out{', ' + along if camera is not None else ''}"
               if brdf.has_white_highlight else
               f"{along} (--camera and a finish that depends on the view)")
        print(f"matching again, {why}", file=sys.stderr)
    scene = corrected(scene, result, lights, brdf, camera, run)
    return reconstruct(scene, gauge.stack, gauge, run, mask=mask, progress=progress), scene


def matched_again(brdf: BRDF, camera: Camera | None) -> bool:
    """Whether a scene of finish ``brdf`` is matched a second time, corrected
    (:func:`corrected`): a white highlight, or a finish that depends on the view
    seen through a lens."""
    return brdf.has_white_highlight or (camera is not None and brdf.depends_on_view)


def corrected(scene: np.ndarray, result, lights: Lights, brdf: BRDF, camera: Camera | None,
              run: Resolved) -> np.ndarray:
    """``scene`` (in place) as the virtual gauge of ``brdf`` shows it, from a first
    match ``result``: without its white highlight (:func:`without_highlight`), or
    seen along the axis (:func:`view_corrected`); as it is when neither applies."""
    if brdf.has_white_highlight:
        return without_highlight(scene, result, lights, brdf, camera, run.options.dark_level,
                                 run.options.clip_level)
    if camera is not None and brdf.depends_on_view:
        return view_corrected(scene, result, lights, brdf, camera, run.options.clip_level)
    return scene


def rendered(lights: Lights, brdf: BRDF, radius: float, bands: int) -> Gauge:
    """The virtual gauge of a finish: rendered with it, or with its diffuse part
    when its highlight is white (the scene is matched without it)."""
    return Gauge.virtual(lights, radius=radius, bands=bands,
                         brdf=brdf.diffuse if brdf.has_white_highlight else brdf)


def fit_scene_brdf(scene, lights: Lights, options: Options | Resolved | None = None, *,
                   mask=None, radius: float = DEFAULT_VIRTUAL_RADIUS, fits: int = SCENE_FITS,
                   progress: bool = False, camera: Camera | None = None,
                   held_finish: BRDF | None = None) -> tuple[BRDF, list[dict]]:
    """Fit the scene's finish from its own images, for a virtual gauge.

    Starting from a Lambertian virtual gauge, the scene is matched (light
    subsets off and nothing refused: a quick, complete estimate), a
    :class:`BRDF` is fitted (:func:`fit_brdf`) to FIT_PIXELS of its solved
    pixels at their estimated normals, the gauge is rendered with it, and the
    scene matched again; ``fits`` times in all (on FIT_MATCH_PIXELS of the
    mask's pixels at most, a fixed random sample). The fit is kept only when the
    scene matches the gauge rendered with it better (lower median residual in
    noise units, before the run's model scale, TIED_RESIDUALS counting as a
    tie) than the Lambertian one (the last round's ``kept``); otherwise the
    result is Lambert, as it is with fewer than MIN_FIT_IMAGES images (with a
    warning). A kept fit is then matched with
    the simpler finishes of :data:`SIMPLER_GAIN`, one of which replaces it where
    clearly better (the last round's ``candidates``: what each matched). The
    plain Oren-Nayar ones are the fit's roughness and the grid's values on
    either side, and, photographed without a lens, the roughness between them
    that the scene matches best (:func:`colorps.brdf_fit.refined_roughness`): the
    fit's own roughness is one of the grid's, and a scene between them had it
    take a darker falloff instead (Oren-Nayar 0.15 fitted at 0.1 with a
    falloff of 0.18 at grazing: 2.3 degrees off; the plain 0.153, 0.12).

    Parameters
    ----------
    scene : (m, H, W, c) array_like
        Linear scene images.
    lights : Lights
        The calibrated lights, one per image.
    options : Options or Resolved, optional
        The run's settings, with numbers for ``read_noise`` and ``gain`` (a
        rendered gauge has no noise to fit them to); a Resolved also says how
        the scene is stored (see :func:`colorps.reconstruct`).
    mask : optional
        As for :func:`colorps.reconstruct`.
    radius : float, optional
        Radius (pixels) of the rendered gauge sphere (FIT_GAUGE_RADIUS at most).
    fits : int, optional
        Rounds of matching and fitting.
    progress : bool, optional
        Say each round's result on stderr.
    camera : Camera, optional
        The lens the scene was photographed through. The finishes are compared
        by matches against gauges seen along the axis, which a rougher finish
        than the scene's fits better through a lens (a smiley of roughness 0.3
        seen with rays up to 11 degrees off the axis matched 0.337 best, and
        its normals came out 0.64 degrees off against 0.49 at 0.3): with one,
        the plain finishes' roughness is only taken from the grid.
    held_finish : BRDF, optional
        A finish whose diffuse falloff every round holds, the rest fitted: a
        gauge's (:func:`colorps.gauge_finish.with_gauge_lights`). Fitted on the
        scene's estimated normals, the falloff trades with their tilt (a
        Mitsuba plastic pot: its fit at the true normals 0.68 at grazing, at
        the matched ones 1.14, and the normals 1.01 degrees off, leaning away
        from the view). The scene is also matched with that falloff carried
        over to its own clear coat (:meth:`BRDF.coat_adjusted`: a white
        highlight the held finish has not, or the reverse), a candidate like
        the simpler ones: a plastic pot on a matte gauge, 2.85 -> 0.99 degrees
        median.

    Returns
    -------
    (BRDF, list of dict)
        The last fit, and per round the median match residual of the gauge it
        started from, the fit's RMS relative residual and its parameters.
    """
    with one_blas_thread(), small_pages():
        run = resolve(options)
        run = resolve(run, gauge=StackModel.rendered(run.options.dark_level))
        quick = run.replace(light_subsets=False, max_residual=None, max_distance=None, tile=None)
        data = np.asarray(scene, dtype=np.float32)
        m, _, _, _c = data.shape
        brdf = BRDF.lambert()
        history = []
        if m < MIN_FIT_IMAGES:
            warnings.warn(f"brdf: {m} images are too few to fit a finish (need "
                          f"{MIN_FIT_IMAGES}); the virtual gauge is Lambertian", ColorPSWarning,
                          stacklevel=2)
            return brdf, history
        rng = np.random.default_rng(0)
        shape = data.shape[1:3]
        data, mask, (rows, cols) = _match_sample(data, mask, rng)
        views = None if camera is None else -camera.rays(cols, rows, shape)
        if progress:
            print(f"brdf: fitting the scene's finish ({fits} rounds of matching and fitting)",
                  file=sys.stderr)
        radius = min(radius, FIT_GAUGE_RADIUS)
        for round_ in range(fits):
            brdf, record = _fit_round(data, lights, brdf, quick, mask, radius, rng,
                                      SETTLE_ROUNDS if round_ == 0 else 0,
                                      None if held_finish is None else held_finish.falloff,
                                      views)
            history.append(dict(round=round_ + 1, **record))
            if progress:
                print(f"brdf fit {round_ + 1}/{fits}: {record['pixels']} pixels, RMS relative "
                      f"residual {record['rms_relative']:.4f}, highlight "
                      f"{max(brdf.specular):.4f} "
                      f"({'white' if brdf.white_highlight else 'tinted'}), alpha "
                      f"{brdf.alpha:.3f}, roughness "
                      f"{brdf.roughness:.1f} rad (the scene matched the gauge before it at "
                      f"{record['match_residual_median']:.2f} noise units)", file=sys.stderr)
        start, fitted = history[0]["match_residual_median"], history[-1]["match_residual_median"]
        kept = len(history) == 1 or fitted < (1.0 + TIED_RESIDUALS) * start
        history[-1]["kept"] = kept
        if not kept:
            # Not a warning: on a Lambertian scene the fit chases the noise and
            # matches a few per cent worse (3-8 % on the synthetic sets), and
            # Lambert is then the right answer.
            if progress:
                print(f"brdf: the fitted finish matched the scene no better than a Lambertian "
                      f"one (median residual {fitted:.2f} vs {start:.2f} noise units): dropped, "
                      "the virtual gauge is Lambertian", file=sys.stderr)
            return BRDF.lambert(), history
        data, mask, _ = _match_sample(data, mask, rng, CANDIDATE_PIXELS)
        scored: dict[BRDF, float] = {}

        def score(finish: BRDF) -> float:  # the scene's median match residual, once each
            if finish not in scored:
                scored[finish] = _match_residual(data, lights, finish, quick, mask, radius)
            return scored[finish]

        for finish in _simpler_finishes(brdf, held_finish):
            score(finish)
        plain = {f.roughness: value for f, value in scored.items()
                 if f == BRDF(roughness=f.roughness)}
        if plain and camera is None:
            refined_roughness(lambda roughness: score(BRDF(roughness=roughness)),
                              min(plain, key=plain.get))
        chosen = min((f for f in scored if f == brdf or scored[f] < SIMPLER_GAIN * scored[brdf]),
                     key=scored.get)
        history[-1]["candidates"] = [dict(match_residual_median=value, **finish.as_dict())
                                     for finish, value in scored.items()]
        if progress and chosen != brdf:
            print(f"brdf: another finish matched the scene clearly better than the fitted "
                  f"one (median residual {scored[chosen]:.2f} vs {scored[brdf]:.2f} noise units)"
                  f": falloff {chosen.falloff[0]:.2f} at grazing incidence, highlight "
                  f"{max(chosen.specular):.4f}", file=sys.stderr)
        return chosen, history


def _simpler_finishes(brdf: BRDF, held: BRDF | None = None) -> list[BRDF]:
    """The fitted finish and the others :func:`fit_scene_brdf` compares it with
    (SIMPLER_GAIN; not Lambert itself, which the kept fit already beat): simpler
    ones, and the held falloff carried over to the fit's coat
    (:meth:`BRDF.coat_adjusted`)."""
    flat = dataclasses.replace(brdf, falloff=BRDF.lambert().falloff)
    plain = [BRDF(roughness=r) for r in roughness_bracket(brdf.roughness)]
    coated = [] if held is None else [brdf.coat_adjusted(held)]
    return list(dict.fromkeys(f for f in (brdf, flat, *plain, *coated)
                              if f is not None and not f.is_lambert))


def _matched(data: np.ndarray, lights: Lights, brdf: BRDF, quick: Resolved, mask,
             radius: float):
    """The scene matched against the gauge of ``radius`` rendered with ``brdf``
    (:func:`match_along_rays`, along the axis: on a copy of ``data``)."""
    gauge = rendered(lights, brdf, radius, data.shape[-1])
    if not brdf.has_white_highlight:
        return reconstruct(data, gauge.stack, gauge, quick, mask=mask)
    return match_along_rays(data.copy(), gauge, quick, lights, brdf, None, mask=mask)[0]


def _match_residual(data: np.ndarray, lights: Lights, brdf: BRDF, quick: Resolved, mask,
                    radius: float) -> float:
    """Median residual (noise units, before the run's model scale) of the scene
    matched against the gauge rendered with ``brdf`` (the table's matches: without
    light subsets the refinement leaves them as they are, and is not run)."""
    return _matched(data, lights, brdf, quick.replace(refine="none"), mask,
                    radius).stats.residual_median_noise_units


def _match_sample(data: np.ndarray, mask, rng: np.random.Generator,
                  size: int = FIT_MATCH_PIXELS):
    """The scene and mask the fit's rounds match: the masked pixels (up to
    ``size`` of them, a random sample past it) packed into a one-row stack (their
    neighbours play no part in the fit; a white highlight's matches copy it), and
    where each pixel of it was ((ys, xs) of ``data``'s pixels, each (H', W'))."""
    chosen = np.ones(data.shape[1:3], bool) if mask is None else np.asarray(mask, bool)
    ys, xs = np.nonzero(chosen)
    if len(ys) > size:
        pick = np.sort(rng.choice(len(ys), size, replace=False))
        ys, xs = ys[pick], xs[pick]
    elif mask is None:
        return data, mask, np.indices(data.shape[1:3])
    return np.ascontiguousarray(data[:, ys, xs][:, None]), None, (ys[None], xs[None])


def _fit_round(data: np.ndarray, lights: Lights, brdf: BRDF, quick: Resolved, mask,
               radius: float, rng: np.random.Generator, settle_rounds: int,
               held_falloff: tuple | None, views: np.ndarray | None) -> tuple[BRDF, dict]:
    """Match the scene against the gauge rendered with ``brdf``; fit a finish to a
    sample of the solved pixels at their normals (``settle_rounds``,
    ``held_falloff`` and ``views``, each pixel's of ``data`` through a lens, as
    :func:`colorps.brdf.fit_brdf` takes them). Returns it and what to record."""
    c = data.shape[-1]
    result = _matched(data, lights, brdf, quick, mask, radius)
    ys, xs = np.nonzero(result.solved)
    if not len(ys):
        raise InputError("brdf fit: no scene pixel matched the virtual gauge; check "
                         "the light file and the mask (or use --brdf lambert)")
    if len(ys) > FIT_PIXELS:
        pick = np.sort(rng.choice(len(ys), FIT_PIXELS, replace=False))
        ys, xs = ys[pick], xs[pick]
    settings = quick.options
    observed = data[:, ys, xs, :].astype(np.float64)
    usable = _usable(observed, settings.dark_level, settings.clip_level)
    colours = lights.as_lighting(c).colours[:, 0, :]  # (m, c), checked against the bands
    fitted, rms = fit_brdf(observed, result.normals[ys, xs].astype(np.float64),
                           lights.directions, colours, usable, settle_rounds=settle_rounds,
                           held_falloff=held_falloff,
                           views=None if views is None else views[ys, xs])
    return fitted, dict(pixels=len(ys),
                        # Not run-scaled: scaled, every finish's median is about 1.
                        match_residual_median=result.stats.residual_median_noise_units,
                        rms_relative=rms, **fitted.as_dict())


def view_corrected(scene: np.ndarray, result, lights: Lights, brdf: BRDF, camera,
                   clip_level: float | None = None) -> np.ndarray:
    """The scene as seen along the optical axis, for a finish that depends on the view.

    A virtual gauge is rendered for a view along +z, but through a lens each
    pixel sees the object along its own ray, and a highlight or a roughness
    shades it differently. Each solved pixel's measurements get the change
    from its view to +z under ``brdf``, at its normal and albedo of ``result``:
    ``albedo * (shade(n, l, +z) - shade(n, l, view))``. Matching the corrected
    scene again takes the perspective out of the match (a glossy scene seen
    up to 5.4 degrees off the axis: 1.60 -> 1.41 degrees mean, the
    orthographic capture's 1.42). Clipped measurements are left as they are.

    Parameters
    ----------
    scene : (m, H, W, c) ndarray of float32
        Linear scene images: corrected in place, and returned.
    result : Reconstruction
        The first match against the gauge rendered with ``brdf``.
    lights : Lights
    brdf : BRDF
    camera : Camera
        The scene's pinhole camera (:mod:`colorps.camera`).
    clip_level : float, optional
        Measurements at or above it are clipped.

    Returns
    -------
    ndarray
        ``scene``.
    """
    _m, height, width, c = scene.shape
    intensities = lights.as_lighting(c).colours[:, 0, :]
    for y, x in _solved_chunks(result):
        normals = result.normals[y, x].astype(np.float64)
        views = -camera.rays(x, y, (height, width))
        values = scene[:, y, x, :]
        change = _view_change(brdf, normals, lights.directions, intensities, views,
                              result.albedo[y, x])
        scene[:, y, x, :] = _clipped_kept(values, values + change, clip_level)
    return scene


def without_highlight(scene: np.ndarray, result, lights: Lights, brdf: BRDF,
                      camera: Camera | None, dark_level: float,
                      clip_level: float | None = None) -> np.ndarray:
    """The scene without the white highlight of its finish, to match its diffuse part.

    A white highlight (:attr:`BRDF.white_highlight`, a clear coat) is the same
    light in every band whatever the albedo, so on a coloured or textured
    object it is a different share of each pixel's signature, which no one
    gauge table holds. Each solved pixel's normal is found instead by a
    per-pixel fit of the whole finish, highlight and albedos included
    (:func:`colorps.brdf.best_normals`, from its normal in ``result``, on its
    measurements that are neither dark nor clipped, weighted as the finish's fit
    weighs them: :func:`colorps.brdf_fit.relative_weights`), and the highlight
    at that normal is taken out of its measurements (through a lens, ``camera``, seen along its own
    ray, the diffuse part's change from that view to the axis as in
    :func:`view_corrected`). The fit is run twice, the second time without the
    measurements under SHADOW_BELOW of what the first one's finish gives them
    (cast shadows: on glossy folds 3.48 -> 1.52 degrees mean for the fitted
    normals). Clipped measurements are left as they are.

    Parameters
    ----------
    scene : (m, H, W, c) ndarray of float32
        Linear scene images: corrected in place, and returned.
    result : Reconstruction
        A match against the diffuse part of ``brdf``.
    lights : Lights
    brdf : BRDF
    camera : Camera or None
    dark_level : float
        Measurements at or under it are not fitted.
    clip_level : float, optional
        Measurements at or above it are clipped.

    Returns
    -------
    ndarray
        ``scene``.
    """
    _m, height, width, c = scene.shape
    intensities = lights.as_lighting(c).colours[:, 0, :]
    specular = brdf.bands(c)
    for y, x in _solved_chunks(result):
        views = None if camera is None else -camera.rays(x, y, (height, width))
        values = scene[:, y, x, :]
        normals = result.normals[y, x].astype(np.float64)
        observed, weight = relative_weights(values, normals, lights.directions, intensities,
                                            _usable(values, dark_level, clip_level))
        normals = best_normals(observed, weight, normals, brdf, lights.directions, views)
        # Cast shadows, which the finish cannot explain, out; fitted again.
        weight[observed < SHADOW_BELOW * _modelled(observed, weight, normals, brdf,
                                                   lights.directions, views)] = 0.0
        normals = best_normals(observed, weight, normals, brdf, lights.directions, views)
        _diffuse, lobe = brdf.parts(normals, lights.directions, views)
        corrected = values - lobe[..., None] * specular * intensities[:, None, :]
        if views is not None and brdf.roughness:
            corrected += _view_change(brdf.diffuse, normals, lights.directions, intensities,
                                      views, result.albedo[y, x])
        scene[:, y, x, :] = _clipped_kept(values, corrected, clip_level)
    return scene


def _usable(values: np.ndarray, dark_level: float, clip_level: float | None) -> np.ndarray:
    """Measurements a fit uses: finite, above ``dark_level``, under ``clip_level``."""
    usable = np.isfinite(values) & (values > dark_level)
    if clip_level is not None:
        usable &= values < clip_level
    return usable


def _view_change(brdf: BRDF, normals: np.ndarray, directions: np.ndarray,
                 intensities: np.ndarray, views: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """(m, N, c) what seeing N points of ``albedo`` along the axis instead of along
    ``views`` adds to their values under ``brdf`` (a band without albedo: nothing)."""
    change = brdf.shade(normals, directions, intensities) - \
        brdf.shade(normals, directions, intensities, views)
    return change * np.nan_to_num(albedo, nan=0.0)[None]


def _clipped_kept(values: np.ndarray, corrected: np.ndarray,
                  clip_level: float | None) -> np.ndarray:
    """``corrected`` at least 0, the clipped ``values`` as they were."""
    corrected = np.maximum(corrected, 0.0)
    return corrected if clip_level is None else np.where(values >= clip_level, values,
                                                         corrected)


def _solved_chunks(result):
    """(rows, columns) of ``result``'s solved pixels, VIEW_CHUNK at a time."""
    ys, xs = np.nonzero(result.solved)
    for first in range(0, len(ys), VIEW_CHUNK):
        yield ys[first:first + VIEW_CHUNK], xs[first:first + VIEW_CHUNK]


def _modelled(observed: np.ndarray, weight: np.ndarray, normals: np.ndarray, brdf: BRDF,
              directions: np.ndarray, views) -> np.ndarray:
    """(m, N, c) what ``brdf`` gives at ``normals`` per unit light, each pixel's
    albedo in every band fitted to the ``observed`` (weighted) beside its highlight."""
    diffuse, lobe = brdf.parts(normals, directions, views)
    highlight = lobe[..., None] * brdf.bands(observed.shape[-1])
    shape = diffuse[..., None]
    albedo = (weight * shape * (observed - highlight)).sum(0) / \
        np.maximum((weight * shape ** 2).sum(0), 1e-30)
    return albedo[None] * shape + highlight
