"""Reflectance models of the synthetic renders (:func:`colorps.synth.render`).

Each function gives, for N surface points of unit normals seen along +z and
one distant light of unit direction ``light`` (from the surface towards the
light), the reflected radiance per unit irradiance at normal incidence: the
Lambertian value is the cosine of incidence, so a pixel of albedo a shows
``a * shape`` in every band. Unlit points (``n . l <= 0``) give 0.

=================  =====================================================
model              value
=================  =====================================================
Lambert            ``n . l``
Oren-Nayar         the qualitative model of rough diffuse surfaces,
                   roughness sigma in radians (0: Lambert)
Blinn-Phong gloss  ``strength (n . h)^shininess``, h the half vector
GGX gloss          ``pi f_s (n . l)``: the Cook-Torrance microfacet
                   lobe of physically based renderers, ``f_s = D F G /
                   (4 (n . l)(n . v))`` with the GGX (Trowbridge-Reitz)
                   distribution D of roughness alpha, Smith's
                   separable shadowing G and Schlick's Fresnel F of
                   reflectance ``strength`` at normal incidence (0.04
                   for common dielectrics: plastics, varnish, glaze)
=================  =====================================================

A gloss is white (the same in every band) and added to the diffuse term: a
dielectric coat over a coloured base, as plastics and painted or glazed
objects are rendered. The ``pi`` makes the GGX lobe comparable with the
diffuse term (a Lambertian BRDF a / pi reflects ``a (n . l)`` here).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from .errors import InputError

__all__ = ["GLOSS_MODELS", "Gloss", "gloss_shape", "oren_nayar", "oren_nayar_factor"]

#: Names of the highlight models :class:`Gloss` knows.
GLOSS_MODELS = ("blinn-phong", "ggx")
#: The view direction of every synthetic render (orthographic camera).
VIEW = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Gloss:
    """A white highlight added to the diffuse shading.

    Attributes
    ----------
    strength : float
        Blinn-Phong: the peak value; GGX: the Fresnel reflectance at normal
        incidence (F0; 0.04 for common dielectrics).
    model : {"blinn-phong", "ggx"}
    shininess : float
        Blinn-Phong exponent (60: a highlight about 15 degrees wide).
    alpha : float
        GGX roughness (0 < alpha <= 1; a renderer's "roughness" r is often
        alpha = r^2).
    """

    strength: float = 0.0
    model: Literal["blinn-phong", "ggx"] = "blinn-phong"
    shininess: float = 60.0
    alpha: float = 0.3

    def __post_init__(self) -> None:
        if self.model not in GLOSS_MODELS:
            raise InputError(f"gloss model: expected one of {GLOSS_MODELS}, got {self.model!r}")
        if not (self.strength >= 0 and self.shininess > 0 and 0 < self.alpha <= 1):
            raise InputError(f"gloss: strength >= 0, shininess > 0 and 0 < alpha <= 1 "
                             f"please; got {self.strength}, {self.shininess}, {self.alpha}")


def oren_nayar_factor(normals: np.ndarray, directions: np.ndarray, sigma: float,
                      views: np.ndarray | None = None) -> np.ndarray:
    """(m, N) Oren-Nayar factor ``A + B max(0, cos dphi) sin(alpha) tan(beta)`` of
    N unit normals under m light directions (1 everywhere when sigma is 0:
    Lambert). Multiply by the cosine of incidence for the shading. ``views``
    (N, 3): each point's unit direction towards the camera (default +z)."""
    normals = np.asarray(normals, dtype=np.float64)
    views = np.broadcast_to(VIEW if views is None else np.asarray(views, np.float64),
                            normals.shape)
    directions = np.atleast_2d(np.asarray(directions, dtype=np.float64))
    s2 = sigma ** 2
    a = 1.0 - 0.5 * s2 / (s2 + 0.33)
    b = 0.45 * s2 / (s2 + 0.09)
    if b == 0.0:
        return np.full((len(directions), len(normals)), a)
    cos_i = np.clip(directions @ normals.T, -1.0, 1.0)  # (m, N)
    cos_r = np.clip((normals * views).sum(axis=1), 0.0, 1.0)  # (N,)
    theta_i = np.arccos(cos_i)
    theta_r = np.arccos(cos_r)
    larger = np.maximum(theta_i, theta_r)
    smaller = np.minimum(theta_i, theta_r)
    # cos of the azimuth difference: light and view projected on the tangent plane.
    view_t = views - cos_r[:, None] * normals  # (N, 3)
    light_dot_view_t = directions @ view_t.T  # l . (v - (n.v) n) = l.v - (n.v)(n.l)
    light_t_norm = np.sqrt(np.maximum(1.0 - cos_i ** 2, 0.0))
    view_t_norm = np.sqrt(np.maximum(1.0 - cos_r ** 2, 0.0))
    norm = light_t_norm * view_t_norm
    cos_phi = np.where(norm > 1e-12, light_dot_view_t / np.maximum(norm, 1e-12), 0.0)
    return a + b * np.maximum(cos_phi, 0.0) * np.sin(larger) * np.tan(smaller)


def oren_nayar(normals: np.ndarray, light: np.ndarray, sigma: float) -> np.ndarray:
    """(N,) Oren-Nayar (qualitative model) shape times the cosine, view along +z."""
    lit = np.maximum(normals @ light, 0.0)
    return lit * oren_nayar_factor(normals, light, sigma)[0]


def gloss_shape(normals: np.ndarray, light: np.ndarray, gloss: Gloss,
                views: np.ndarray | None = None) -> np.ndarray:
    """(N,) radiance of the highlight of one light (0 where unlit); ``views`` (N, 3):
    each point's unit direction towards the camera (default +z)."""
    views = np.broadcast_to(VIEW if views is None else np.asarray(views, np.float64),
                            normals.shape)
    half = light + views
    half = half / np.linalg.norm(half, axis=-1, keepdims=True)
    cos_l = normals @ light
    cos_h = np.clip((normals * half).sum(axis=-1), 0.0, 1.0)
    lit = cos_l > 0
    if gloss.model == "blinn-phong":
        return np.where(lit, gloss.strength * cos_h ** gloss.shininess, 0.0)
    a2 = gloss.alpha ** 2
    cos_v = np.clip((normals * views).sum(axis=-1), 1e-6, 1.0)
    cos_l = np.clip(cos_l, 1e-6, 1.0)
    distribution = a2 / (np.pi * (cos_h ** 2 * (a2 - 1.0) + 1.0) ** 2)

    def smith(cosine):
        return 2.0 * cosine / (cosine + np.sqrt(a2 + (1.0 - a2) * cosine ** 2))

    cos_d = np.clip(half @ light, 0.0, 1.0)  # the same for every normal of one view
    fresnel = gloss.strength + (1.0 - gloss.strength) * (1.0 - cos_d) ** 5
    lobe = distribution * fresnel * smith(cos_l) * smith(cos_v) / (4.0 * cos_v)
    return np.where(lit, np.pi * lobe, 0.0)
