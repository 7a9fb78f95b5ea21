"""The finish a virtual gauge is rendered with, fitted from the scene itself.

A virtual gauge (:meth:`colorps.Gauge.virtual`) has no photographs: its images
are rendered under the calibrated lights. The finish it assumes must be the
scene's, or every match is biased. :class:`BRDF` is an isotropic model with few
parameters, shared by every pixel (a gauge has one finish) while the albedo
varies per pixel and band. With the camera along +z, light k of direction l_k
and intensity E_kb in band b, a pixel of normal n and albedo a_b shows::

    I_kb = E_kb ( a_b g(n . l_k) R_k(n) (n . l_k) + h_b G_k(n) )

for n . l_k > 0 (0 otherwise: attached shadow). ``g`` is the diffuse falloff,
piecewise linear in the cosine of incidence over DIFFUSE_KNOTS with g(1) = 1:
g = 1 everywhere is Lambert, real matte and plastic finishes are darker at
grazing incidence (a coat lets less light in and out there). ``R_k`` is the
Oren-Nayar factor of a rough surface (roughness sigma, radians;
:func:`colorps.finishes.oren_nayar_factor`; 1 when sigma is 0), brighter where
light and view are on the same side: it depends on the view, which g cannot
follow. ``G_k`` is the microfacet highlight of physically based renderers
(:func:`ggx_lobe`: GGX distribution of roughness alpha, Smith shadowing,
Schlick's Fresnel of a dielectric, over 4 (n . v)), of strength h_b per band:

* a **white** highlight (``white_highlight``): h_b = s_b whatever the albedo,
  the lights' own colour reflected by a clear coat over a coloured base
  (plastics, paints, glazes; the dichromatic model);
* a **tinted** one: h_b = s_b a_b, relative to the albedo (a metal, or a
  uniformly coloured object, where the two are one).

A white highlight on a textured object is a different share of each pixel's
light in each band, which one table of signatures cannot hold: its scenes are
matched against the diffuse part alone once their highlight is taken out
(:func:`colorps.virtual.without_highlight`).

:func:`best_normals` finds the normals that explain given observations best
under a finish (the albedos projected out), and :mod:`colorps.brdf_fit` fits
the finish itself.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from .errors import InputError
from .finishes import oren_nayar_factor

__all__ = ["BRDF", "DIFFUSE_KNOTS", "best_normals", "coat_transmission", "ggx_lobe",
           "shading_angles"]

# ---------------------------------------------------------------- tuning
#: Cosines of incidence at which the diffuse falloff g is a free value (linear
#: in between; g(1) = 1 fixes the scale the albedo carries).
DIFFUSE_KNOTS = (0.0, 0.1, 0.2, 0.3, 0.45, 0.6, 0.8, 1.0)
#: The highlight's Fresnel factor is Schlick's for this reflectance at normal
#: incidence (a clear dielectric of index 1.5: plastics, varnish, glaze),
#: relative to it: 1 at normal incidence, rising towards grazing.
FRESNEL_F0 = 0.04
#: The refractive index of that dielectric: (1 + sqrt(F0)) / (1 - sqrt(F0)).
COAT_INDEX = (1.0 + FRESNEL_F0 ** 0.5) / (1.0 - FRESNEL_F0 ** 0.5)
#: A highlight peaking under this fraction of the diffuse albedo is too faint
#: for the view direction to matter (:attr:`BRDF.depends_on_view`).
VISIBLE_PEAK = 0.01
#: coat_transmission averages over COAT_STEPS shares of the coat's facet
#: normals by twice as many azimuths (within 0.003 of a grid twice as fine).
COAT_STEPS = 256
#: best_normals takes NORMAL_STEPS damped Gauss-Newton steps of at most
#: MAX_NORMAL_STEP radians, derivatives over NORMAL_EPS radians.
NORMAL_STEPS = 5
MAX_NORMAL_STEP = 0.1
NORMAL_EPS = 1e-4


@dataclass(frozen=True)
class BRDF:
    """A shared isotropic finish: diffuse falloff and roughness, plus a GGX highlight.

    Attributes
    ----------
    falloff : tuple of float
        g at :data:`DIFFUSE_KNOTS` (1 everywhere: Lambert).
    specular : tuple of float
        Highlight strength s_b per band, or one value for all bands; 0: no
        highlight.
    alpha : float
        GGX roughness of the highlight (0 < alpha <= 1; a renderer's
        "roughness" r is often alpha = r^2).
    roughness : float
        Oren-Nayar sigma of the diffuse term (radians; 0: smooth).
    white_highlight : bool
        Whether the highlight is the lights' colour whatever the albedo (s_b
        absolute, a clear coat) or tinted by it (s_b relative to a_b).

    Examples
    --------
    >>> from colorps.brdf import BRDF
    >>> import numpy as np
    >>> BRDF.lambert().shade(np.array([[0.0, 0.0, 1.0]]), np.array([[0.6, 0.0, 0.8]]),
    ...                      np.ones((1, 1))).round(3).tolist()
    [[[0.8]]]
    """

    falloff: tuple[float, ...] = field(default=tuple(1.0 for _ in DIFFUSE_KNOTS))
    specular: tuple[float, ...] = (0.0,)
    alpha: float = 0.3
    roughness: float = 0.0
    white_highlight: bool = False

    def __post_init__(self) -> None:
        falloff = tuple(float(v) for v in self.falloff)
        specular = tuple(float(v) for v in np.atleast_1d(self.specular))
        if len(falloff) != len(DIFFUSE_KNOTS):
            raise InputError(f"brdf: falloff needs {len(DIFFUSE_KNOTS)} values (at "
                             f"cosines {DIFFUSE_KNOTS}), got {len(falloff)}")
        values = np.array(falloff + specular + (float(self.alpha), float(self.roughness)))
        if not np.all(np.isfinite(values)) or np.any(values < 0) or \
                not 0 < self.alpha <= 1:
            raise InputError(f"brdf: falloff and specular must be finite and >= 0, "
                             f"0 < alpha <= 1; got {falloff}, {specular}, {self.alpha}")
        object.__setattr__(self, "falloff", falloff)
        object.__setattr__(self, "specular", specular)
        object.__setattr__(self, "alpha", float(self.alpha))
        object.__setattr__(self, "roughness", float(self.roughness))
        object.__setattr__(self, "white_highlight", bool(self.white_highlight))

    @classmethod
    def lambert(cls) -> BRDF:
        """The Lambertian finish (g = 1, no highlight)."""
        return cls()

    @property
    def highlight_peak(self) -> float:
        """The highlight's largest value relative to a diffuse albedo of 1 (at its
        centre, normal incidence): max(s) / (4 alpha^2)."""
        return max(self.specular) / (4.0 * self.alpha ** 2)

    @property
    def depends_on_view(self) -> bool:
        """Whether the view direction changes the shading by more than
        VISIBLE_PEAK of the diffuse albedo (a highlight, or a roughness)."""
        return self.roughness > 0.0 or self.highlight_peak > VISIBLE_PEAK

    @property
    def has_white_highlight(self) -> bool:
        """A white highlight bright enough to matter (VISIBLE_PEAK)."""
        return self.white_highlight and self.highlight_peak > VISIBLE_PEAK

    @property
    def is_lambert(self) -> bool:
        return all(v == 1.0 for v in self.falloff) and not any(self.specular) and \
            self.roughness == 0.0

    @property
    def diffuse(self) -> BRDF:
        """The finish without its highlight."""
        return BRDF(self.falloff, roughness=self.roughness)

    def coat_adjusted(self, held: BRDF) -> BRDF | None:
        """The finish with ``held``'s falloff carried over to its own clear coat.

        ``held``'s falloff (a gauge's, measured at its known normals) times the
        share of light this finish's coat lets into its base at each incidence,
        over the share ``held``'s coat lets in (:func:`coat_transmission`): a
        matte gauge's falloff darkened towards grazing for a coated scene, a
        coated gauge's brightened for a matte one. This finish has a coat when
        its highlight is white (a tinted one is a metal's); ``held``, a gauge of
        one albedo on which the two look alike, when it has a visible highlight.
        None when the two coats let in the same light, within VISIBLE_PEAK.
        """
        knots = np.array(DIFFUSE_KNOTS)
        let_in = np.ones(len(knots))
        if self.has_white_highlight:
            let_in *= coat_transmission(knots, self.alpha)
        if held.highlight_peak > VISIBLE_PEAK:
            let_in /= coat_transmission(knots, held.alpha)
        if np.abs(let_in - 1.0).max() < VISIBLE_PEAK:
            return None
        return replace(self, falloff=tuple(np.asarray(held.falloff) * let_in))

    def bands(self, count: int) -> np.ndarray:
        """(count,) highlight strength per band."""
        if len(self.specular) == 1:
            return np.full(count, self.specular[0])
        if len(self.specular) != count:
            raise InputError(f"brdf: specular has {len(self.specular)} bands but the "
                             f"lights {count}")
        return np.array(self.specular)

    def parts(self, normals: np.ndarray, directions: np.ndarray,
              views: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
        """(m, N) diffuse shading g R (n . l) and highlight lobe G of unit lights
        (the lobe None without a highlight); ``views`` as for :meth:`shade`."""
        normals = np.asarray(normals, dtype=np.float64)
        angles = shading_angles(normals, directions, views)
        diffuse = np.interp(angles[0], DIFFUSE_KNOTS, self.falloff)
        diffuse *= angles[0]
        if self.roughness:
            diffuse *= oren_nayar_factor(normals, directions, self.roughness, views)
        return diffuse, ggx_lobe(angles, self.alpha) if any(self.specular) else None

    def shade(self, normals: np.ndarray, directions: np.ndarray,
              intensities: np.ndarray, views: np.ndarray | None = None,
              albedo: np.ndarray | None = None) -> np.ndarray:
        """Pixel values of surface points under distant lights.

        Parameters
        ----------
        normals : (N, 3) ndarray
            Unit normals, camera space.
        directions : (m, 3) ndarray
            Unit directions towards the lights.
        intensities : (m, c) ndarray
            Light intensity per band (linear).
        views : (N, 3) ndarray, optional
            Each point's unit direction towards the camera (default +z, a view
            along the optical axis).
        albedo : (N, c) ndarray, optional
            Each point's diffuse albedo (default 1).

        Returns
        -------
        (m, N, c) ndarray of float64
            Linear values.
        """
        intensities = np.asarray(intensities, dtype=np.float64)
        bands = intensities.shape[1]
        specular = self.bands(bands)
        diffuse, lobe = self.parts(normals, directions, views)
        # A band at a time, into the result: no (m, N, c) temporaries (fresh
        # memory costs more than the arithmetic here).
        value = np.empty((*diffuse.shape, bands))
        for b in range(bands):
            band = value[..., b]
            np.copyto(band, diffuse)
            if albedo is not None:
                band *= albedo[None, :, b]
            if lobe is not None:
                tint = 1.0 if albedo is None or self.white_highlight else albedo[None, :, b]
                band += lobe * (specular[b] * tint)
            band *= intensities[:, b, None]
        return value

    def never_brighter_towards_grazing(self) -> BRDF:
        """The same finish with the nearest falloff (least squares at the knots,
        scipy's isotonic regression) that never rises as the light's cosine
        falls, 1 at normal incidence: what a diffuse base gives under a coat
        that lets less light in towards grazing, or bare. A fitted falloff that
        rises towards grazing is, as often, the normals' tilt traded for it
        (:mod:`colorps.falloff_trade`).

        Examples
        --------
        >>> from colorps.brdf import BRDF
        >>> fitted = BRDF(falloff=(1.2, 0.9, 0.9, 0.9, 0.95, 1.0, 1.0, 1.0))
        >>> [round(g, 3) for g in fitted.never_brighter_towards_grazing().falloff]
        [0.97, 0.97, 0.97, 0.97, 0.97, 1.0, 1.0, 1.0]
        """
        from scipy.optimize import isotonic_regression

        falloff = isotonic_regression(np.asarray(self.falloff), increasing=True).x
        return replace(self, falloff=tuple(falloff / falloff[-1]))

    def as_dict(self) -> dict:
        return dict(model="diffuse falloff x Oren-Nayar + GGX",
                    falloff_knots=list(DIFFUSE_KNOTS), falloff=list(self.falloff),
                    specular=list(self.specular), alpha=self.alpha,
                    roughness=self.roughness, white_highlight=self.white_highlight,
                    fresnel_f0=FRESNEL_F0)

    @classmethod
    def from_dict(cls, record: dict) -> BRDF:
        """The finish :meth:`as_dict` recorded (report.json's ``brdf``). A record of
        colorps 0.2's Blinn-Phong highlight (``shininess`` s) is read as the GGX
        one of the same peak, alpha = sqrt(2 / (s + 2)), tinted."""
        if list(record.get("falloff_knots", DIFFUSE_KNOTS)) != list(DIFFUSE_KNOTS):
            raise InputError("brdf: its falloff is given at knots other than this "
                             f"colorps's {DIFFUSE_KNOTS}")
        alpha = record["alpha"] if "alpha" in record else \
            float(np.sqrt(2.0 / (float(record["shininess"]) + 2.0)))
        return cls(tuple(record["falloff"]), tuple(record["specular"]), float(alpha),
                   float(record.get("roughness", 0.0)),
                   bool(record.get("white_highlight", False)))


def _half_vectors(directions: np.ndarray) -> np.ndarray:
    half = np.asarray(directions, dtype=np.float64) + np.array([0.0, 0.0, 1.0])
    return half / np.linalg.norm(half, axis=1, keepdims=True)


def shading_angles(normals: np.ndarray, directions: np.ndarray,
                   views: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cosines of incidence (m, N; 0 when unlit), of the half vector's angle to
    the normal (m, N), of the view's (N,) and of the half vector's to the light
    ((m, 1), or (m, N) with ``views``), for a view along +z or each point's
    ``views`` (N, 3)."""
    directions = np.asarray(directions, dtype=np.float64)
    cosine = np.maximum(normals @ directions.T, 0.0).T
    if views is None:
        half = _half_vectors(directions)
        cos_half = np.clip(normals @ half.T, 0.0, 1.0).T
        cos_diff = np.clip((half * directions).sum(axis=1), 0.0, 1.0)[:, None]
        return cosine, cos_half, np.clip(normals[:, 2], 0.0, 1.0), cos_diff
    views = np.asarray(views, dtype=np.float64)
    cos_half = np.empty_like(cosine)
    cos_diff = np.empty_like(cosine)
    for k, light in enumerate(directions):  # (N, 3) half vectors a light at a time
        half = light + views
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        cos_half[k] = np.clip((normals * half).sum(axis=1), 0.0, 1.0)
        cos_diff[k] = np.clip(half @ light, 0.0, 1.0)
    return cosine, cos_half, np.clip((normals * views).sum(axis=1), 0.0, 1.0), cos_diff


def ggx_lobe(angles: tuple, alpha: float) -> np.ndarray:
    """(m, N) microfacet highlight of unit lights: ``pi D F G / (4 (n . v))``.

    That is pi times the radiance of the BRDF D F G / (4 (n . l)(n . v)) under a
    light of unit irradiance at normal incidence (the pi makes it comparable
    with the diffuse term: a Lambertian BRDF a / pi gives a (n . l)), with the
    GGX (Trowbridge-Reitz) distribution D of roughness
    ``alpha``, Smith's separable shadowing G and Schlick's Fresnel factor F of
    reflectance FRESNEL_F0, relative to it. At normal incidence it peaks at
    1 / (4 alpha^2). ``angles`` is :func:`shading_angles`'s.
    """
    cosine, cos_half, cos_view, cos_diff = angles
    a2 = alpha * alpha
    lobe = cos_half ** 2
    lobe *= a2 - 1.0
    lobe += 1.0
    np.square(lobe, out=lobe)
    np.divide(a2, lobe, out=lobe)  # pi D
    lobe *= 1.0 + (1.0 / FRESNEL_F0 - 1.0) * (1.0 - cos_diff) ** 5
    # Smith's G1 of the light (0 where unlit), and G1 of the view over 4 (n . v)
    # in a form without 0 / 0 at grazing.
    lobe *= 2.0 * cosine / (cosine + np.sqrt(a2 + (1.0 - a2) * cosine ** 2))
    lobe /= 2.0 * (cos_view + np.sqrt(a2 + (1.0 - a2) * cos_view ** 2))
    return lobe


def coat_transmission(cosines, alpha: float) -> np.ndarray:
    """Share of a light that crosses a clear coat into its base, relative to
    normal incidence.

    A clear dielectric coat (the one whose highlight :func:`ggx_lobe` draws:
    GGX roughness ``alpha``, Fresnel reflectance FRESNEL_F0 at normal
    incidence, index COAT_INDEX) reflects part of each light and refracts the
    rest into the diffuse base beneath, where its rough surface also shadows
    some of the refracted light. This is that single-scattering transmission
    (the microfacet model of Walter et al. 2007: over the facets the light
    sees, Schlick's Fresnel transmission times the Smith masking of the
    refracted ray) at each cosine of incidence, over its value at normal
    incidence: as Mitsuba 3's ``roughplastic`` weights its base (within 0.01
    of its table at alpha 0.3). A coated finish's diffuse falloff is the
    uncoated one times this; a renderer that weights its layers by the view
    alone has none of it.

    Parameters
    ----------
    cosines : array_like
        Cosines of incidence (0 to 1).
    alpha : float
        The coat's GGX roughness.

    Returns
    -------
    ndarray of float64
        1 at normal incidence, falling towards grazing.

    Examples
    --------
    >>> from colorps.brdf import coat_transmission
    >>> coat_transmission([0.0, 0.5, 1.0], 0.3).round(2).tolist()
    [0.67, 0.93, 1.0]
    """
    cosines = np.asarray(cosines, dtype=np.float64)
    a2 = alpha * alpha
    # Facet normals m on a grid of equal shares of D(m) (n . m), the GGX
    # sampling map: the transmission is the mean of
    # (1 - F) G1(l) G1(t) (l . m) / ((n . l)(n . m)), t the refracted ray.
    share = (np.arange(COAT_STEPS) + 0.5) / COAT_STEPS
    cos_facet = np.sqrt((1.0 - share) / (1.0 + (a2 - 1.0) * share))[:, None]
    turn = (np.arange(2 * COAT_STEPS) + 0.5) * np.pi / COAT_STEPS
    sin_facet = np.sqrt(1.0 - cos_facet ** 2)
    facets = np.stack(np.broadcast_arrays(sin_facet * np.cos(turn), sin_facet * np.sin(turn),
                                          cos_facet), axis=-1).reshape(-1, 3)

    def smith(cosine):  # G1(cosine) / cosine, finite at grazing
        return 2.0 / (cosine + np.sqrt(a2 + (1.0 - a2) * cosine ** 2))

    def let_in(cosine):
        light = np.array([np.sqrt(max(0.0, 1.0 - cosine ** 2)), 0.0, cosine])
        l_dot_m = np.maximum(facets @ light, 0.0)
        cos_refracted = np.sqrt(1.0 - (1.0 - l_dot_m ** 2) / COAT_INDEX ** 2)
        # -z of the refracted ray -l / eta + (l.m / eta - cos_refracted) m
        depth = light[2] / COAT_INDEX - (l_dot_m / COAT_INDEX - cos_refracted) * facets[:, 2]
        crossing = 1.0 - FRESNEL_F0 - (1.0 - FRESNEL_F0) * (1.0 - l_dot_m) ** 5
        value = crossing * smith(cosine) * smith(np.maximum(depth, 0.0)) * \
            np.maximum(depth, 0.0) * l_dot_m / facets[:, 2]
        return float(np.where((l_dot_m > 0.0) & (depth > 0.0), value, 0.0).mean())

    shares = np.array([let_in(float(c)) for c in cosines.ravel()])
    return (shares / let_in(1.0)).reshape(cosines.shape)


def best_normals(obs: np.ndarray, weight: np.ndarray, normals: np.ndarray, brdf: BRDF,
                 directions: np.ndarray, views: np.ndarray | None = None) -> np.ndarray:
    """The normals that explain observations best under a finish.

    Damped Gauss-Newton on two tangent angles per pixel (NORMAL_STEPS steps),
    each pixel's albedo in every band projected out.

    Parameters
    ----------
    obs : (m, N, c) ndarray
        Observations of N pixels per unit light (divided by the intensities).
    weight : (m, N, c) ndarray
        Each measurement's least-squares weight (0: left out).
    normals : (N, 3) ndarray
        Unit normals to start from.
    brdf : BRDF
    directions : (m, 3) ndarray
        Unit directions towards the lights.
    views : (N, 3) ndarray, optional
        As for :meth:`BRDF.shade`.

    Returns
    -------
    (N, 3) ndarray
        Unit normals, facing the camera.
    """
    from . import _normal_kernels

    _m, n_pixels, c = obs.shape
    if views is None:
        views = np.broadcast_to([0.0, 0.0, 1.0], (n_pixels, 3))
    out = np.array(normals, dtype=np.float64)
    _normal_kernels.best_normals(
        obs=np.ascontiguousarray(obs, dtype=np.float64),
        weight=np.ascontiguousarray(weight, dtype=np.float64), normals=out,
        views=np.ascontiguousarray(views, dtype=np.float64),
        directions=np.ascontiguousarray(directions, dtype=np.float64),
        knots=np.array(DIFFUSE_KNOTS), falloff=np.array(brdf.falloff),
        specular=brdf.bands(c).astype(np.float64), alpha=brdf.alpha, roughness=brdf.roughness,
        white=brdf.white_highlight, fresnel_f0=FRESNEL_F0, steps=NORMAL_STEPS,
        max_step=MAX_NORMAL_STEP, eps=NORMAL_EPS)
    return out
