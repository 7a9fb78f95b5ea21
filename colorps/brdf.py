"""The finish a virtual gauge is rendered with, fitted from the scene itself.

A virtual gauge (:meth:`colorps.Gauge.virtual`) has no photographs: its images
are rendered under the calibrated lights. The finish it assumes must be the
scene's, or every match is biased. :class:`BRDF` is an isotropic model with few
parameters, shared by every pixel (a gauge has one finish) while the albedo
varies per pixel and band. With the camera along +z, light k of direction l_k
and intensity E_kb in band b, a pixel of normal n and albedo a_b shows::

    I_kb = E_kb a_b ( g(n . l_k) R_k(n) (n . l_k) + s_b (shininess + 2) / 2 (n . h_k)^shininess (n . l_k) )

for n . l_k > 0 (0 otherwise: attached shadow), h_k the unit half vector of
l_k and the view. ``g`` is the diffuse falloff, piecewise linear in the
cosine of incidence over DIFFUSE_KNOTS with g(1) = 1: g = 1 everywhere is
Lambert, real matte and plastic finishes are darker at grazing incidence.
``R_k`` is the Oren-Nayar factor of a rough surface (roughness sigma, radians;
:func:`colorps.finishes.oren_nayar_factor`; 1 when sigma is 0), brighter where
light and view are on the same side: it depends on the view, which g cannot
follow. The last term is a normalised Blinn-Phong highlight of strength s_b
per band.

:func:`fit_brdf` fits g, sigma, s and shininess to a scene's observations at given
normals (an initial estimate from a Lambertian gauge, then from the fitted one:
:func:`colorps.virtual.fit_scene_brdf`): alternating least squares between the
per-pixel albedos and the shared,
non-negative parameters, on relative residuals with robust (Huber) weights so
that cast shadows and interreflections do not pull the fit, over grids of
shininess and roughness values.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import InputError
from .finishes import oren_nayar_factor

__all__ = ["BRDF", "DIFFUSE_KNOTS", "fit_brdf"]

# ---------------------------------------------------------------- tuning
#: Cosines of incidence at which the diffuse falloff g is a free value (linear
#: in between; g(1) = 1 fixes the scale the albedo carries).
DIFFUSE_KNOTS = (0.0, 0.1, 0.2, 0.3, 0.45, 0.6, 0.8, 1.0)
#: Shininess values tried (Blinn-Phong exponents; 10,000 is a highlight about
#: 1 degree wide), then SHININESS_STEPS halvings of the (logarithmic) step
#: around the best; each joint round (below) tries the best and its neighbours.
SHININESS_GRID = tuple(float(v) for v in np.geomspace(4.0, 10000.0, 10))
SHININESS_STEPS = 2
#: Oren-Nayar roughness values (radians; 0: smooth, Lambertian) tried at the
#: best shininess of each round: every other one in the first round, then the
#: best and its neighbours. (Refined between them, the fit slid along the valley
#: where a darker falloff stands in for roughness: Oren-Nayar 0.2 and 0.3
#: scenes fitted 0.16 and 0.29, falloffs 0.39 and 0.85 at grazing.)
ROUGHNESS_GRID = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)
#: Where a roughness between ROUGHNESS_GRID's values is sought
#: (:func:`refined_roughness`), to this many radians, and then the vertex of a
#: parabola through the values tried this close to the best.
ROUGHNESS_TOLERANCE = 0.01
ROUGHNESS_WINDOW = 0.03
#: A highlight peaking under this fraction of the diffuse albedo is too faint
#: for the view direction to matter (:attr:`BRDF.depends_on_view`).
VISIBLE_PEAK = 0.01
#: Observations whose cosine of incidence at the estimated normal is below this
#: are left out: attached-shadow boundaries are where normal errors matter most.
MIN_FIT_COSINE = 0.02
#: fit_brdf then refines the sample's normals under the fit and fits again,
#: JOINT_ROUNDS times (NORMAL_STEPS damped Gauss-Newton steps of at most
#: MAX_NORMAL_STEP radians, derivatives over NORMAL_EPS radians): normals
#: matched with a too-matte gauge are tilted to explain the highlights, and
#: fits at them alone underestimate the highlight.
JOINT_ROUNDS = 4
#: The falloff and the normals' tilt explain much the same shading, so fitting
#: them in turn creeps along that valley: each round's step of the normals is
#: taken OVER_RELAXATION times as long (successive over-relaxation). An
#: Oren-Nayar 0.3 scene matched first with a Lambertian gauge (normals 5.1
#: degrees off): after the 4 rounds, normals 1.48 degrees off and a falloff of
#: 0.52 at grazing with 1 (plain alternation), 0.26 and 1.06 (the truth: 1) with
#: 1.5; 2 overshoots (1.68), 3 diverges.
OVER_RELAXATION = 1.5
NORMAL_STEPS = 5
MAX_NORMAL_STEP = 0.1
NORMAL_EPS = 1e-4
#: Alternating least-squares rounds per shininess value, at most: they stop
#: when a round lowers the cost by less than FIT_TOLERANCE of it (by the 4th or
#: 5th round usually; later rounds changed it by under 1e-4, not the choice).
FIT_ROUNDS = 8
FIT_TOLERANCE = 1e-4
#: Huber threshold of the relative residuals, in robust standard deviations.
HUBER_K = 2.0
#: Weight of the prior pulling each falloff value towards Lambert (1), and of
#: the smoothness of the falloff (second differences), relative to the data.
PRIOR_WEIGHT = 1e-6
SMOOTHNESS_WEIGHT = 1e-4
#: The prior's weight in the rounds where fit_brdf holds the falloff at
#: Lambert's (its ``settle_rounds``): g = 1 to about 1e-6.
SETTLED_PRIOR_WEIGHT = 1e6


@dataclass(frozen=True)
class BRDF:
    """A shared isotropic finish: diffuse falloff and roughness, plus a Blinn-Phong highlight.

    Attributes
    ----------
    falloff : tuple of float
        g at :data:`DIFFUSE_KNOTS` (1 everywhere: Lambert).
    specular : tuple of float
        Highlight strength s_b per band (relative to the diffuse albedo), or
        one value for all bands; 0: no highlight.
    shininess : float
        Blinn-Phong exponent of the highlight.
    roughness : float
        Oren-Nayar sigma of the diffuse term (radians; 0: smooth).

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
    shininess: float = 100.0
    roughness: float = 0.0

    def __post_init__(self) -> None:
        falloff = tuple(float(v) for v in self.falloff)
        specular = tuple(float(v) for v in np.atleast_1d(self.specular))
        if len(falloff) != len(DIFFUSE_KNOTS):
            raise InputError(f"brdf: falloff needs {len(DIFFUSE_KNOTS)} values (at "
                             f"cosines {DIFFUSE_KNOTS}), got {len(falloff)}")
        values = np.array(falloff + specular + (float(self.shininess), float(self.roughness)))
        if not np.all(np.isfinite(values)) or np.any(values < 0) or self.shininess <= 0:
            raise InputError(f"brdf: falloff and specular must be finite and >= 0, "
                             f"shininess > 0; got {falloff}, {specular}, {self.shininess}")
        object.__setattr__(self, "falloff", falloff)
        object.__setattr__(self, "specular", specular)
        object.__setattr__(self, "shininess", float(self.shininess))
        object.__setattr__(self, "roughness", float(self.roughness))

    @classmethod
    def lambert(cls) -> BRDF:
        """The Lambertian finish (g = 1, no highlight)."""
        return cls()

    @property
    def highlight_peak(self) -> float:
        """The highlight's largest value relative to the diffuse albedo (at its
        centre, normal incidence): max(s) (shininess + 2) / 2."""
        return max(self.specular) * (self.shininess + 2.0) / 2.0

    @property
    def depends_on_view(self) -> bool:
        """Whether the view direction changes the shading by more than
        VISIBLE_PEAK of the diffuse albedo (a highlight, or a roughness)."""
        return self.roughness > 0.0 or self.highlight_peak > VISIBLE_PEAK

    @property
    def is_lambert(self) -> bool:
        return all(v == 1.0 for v in self.falloff) and not any(self.specular) and \
            self.roughness == 0.0

    def shade(self, normals: np.ndarray, directions: np.ndarray,
              intensities: np.ndarray, views: np.ndarray | None = None) -> np.ndarray:
        """Pixel values of unit-albedo surface points under distant lights.

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

        Returns
        -------
        (m, N, c) ndarray of float64
            Linear values (albedo 1).
        """
        normals = np.asarray(normals, dtype=np.float64)
        intensities = np.asarray(intensities, dtype=np.float64)
        bands = intensities.shape[1]
        specular = np.broadcast_to(self.specular, (bands,)) \
            if len(self.specular) == 1 else np.array(self.specular)
        if len(specular) != bands:
            raise InputError(f"brdf: specular has {len(specular)} bands but the lights {bands}")
        cosine, cos_half = _angles(normals, directions, views)
        diffuse = np.interp(cosine, DIFFUSE_KNOTS, self.falloff)
        diffuse *= cosine
        if self.roughness:
            diffuse *= oren_nayar_factor(normals, directions, self.roughness, views)
        lobe = _lobe(cosine, cos_half, self.shininess) if np.any(specular) else None
        del cosine, cos_half
        # A band at a time, into the result: no (m, N, c) temporaries (fresh
        # memory costs more than the arithmetic here).
        value = np.empty((*diffuse.shape, bands))
        for b in range(bands):
            band = value[..., b]
            if lobe is None:
                np.multiply(diffuse, intensities[:, b, None], out=band)
            else:
                np.multiply(lobe, specular[b], out=band)
                band += diffuse
                band *= intensities[:, b, None]
        return value

    def as_dict(self) -> dict:
        return dict(model="diffuse falloff x Oren-Nayar + Blinn-Phong",
                    falloff_knots=list(DIFFUSE_KNOTS), falloff=list(self.falloff),
                    specular=list(self.specular), shininess=self.shininess,
                    roughness=self.roughness)

    @classmethod
    def from_dict(cls, record: dict) -> BRDF:
        """The finish :meth:`as_dict` recorded (report.json's ``brdf``)."""
        if list(record.get("falloff_knots", DIFFUSE_KNOTS)) != list(DIFFUSE_KNOTS):
            raise InputError("brdf: its falloff is given at knots other than this "
                             f"colorps's {DIFFUSE_KNOTS}")
        return cls(tuple(record["falloff"]), tuple(record["specular"]),
                   float(record["shininess"]), float(record.get("roughness", 0.0)))


def roughness_bracket(value: float) -> tuple[float, ...]:
    """``value`` and the values of ROUGHNESS_GRID on either side of it."""
    below = [v for v in ROUGHNESS_GRID if v < value][-1:]
    above = [v for v in ROUGHNESS_GRID if v > value][:1]
    return (*below, value, *above)


def refined_roughness(cost, start: float) -> float:
    """The roughness (radians) of least ``cost``, from ``start`` refined between
    the values of ROUGHNESS_GRID on either side of it.

    A bounded scalar minimisation to ROUGHNESS_TOLERANCE, then the vertex of a
    parabola fitted to every value tried within ROUGHNESS_WINDOW of the best:
    a median residual is a noisy cost at that scale (an Oren-Nayar 0.2 scene's
    least was at 0.206, the parabola's vertex at 0.203). ``cost`` maps a
    roughness to a float and is called on the value returned too.
    """
    from scipy.optimize import minimize_scalar

    tried = {start: cost(start)}

    def remembered(roughness: float) -> float:
        roughness = float(roughness)
        if roughness not in tried:
            tried[roughness] = cost(roughness)
        return tried[roughness]

    around = roughness_bracket(start)
    minimize_scalar(remembered, bounds=(around[0], around[-1]), method="bounded",
                    options=dict(xatol=ROUGHNESS_TOLERANCE))
    best = min(tried, key=tried.get)
    near = np.array([r for r in tried if abs(r - best) <= ROUGHNESS_WINDOW])
    if len(near) < 3:
        return best
    curve, slope, _ = np.polyfit(near, [tried[r] for r in near], 2)
    if curve <= 0:
        return best
    vertex = float(np.clip(-slope / (2 * curve), near.min(), near.max()))
    remembered(vertex)
    return vertex


def _half_vectors(directions: np.ndarray) -> np.ndarray:
    half = np.asarray(directions, dtype=np.float64) + np.array([0.0, 0.0, 1.0])
    return half / np.linalg.norm(half, axis=1, keepdims=True)


def _angles(normals: np.ndarray, directions: np.ndarray, views: np.ndarray | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """(m, N) cosines of incidence (0 when unlit) and of the half-vector angle,
    for a view along +z or each point's ``views`` (N, 3)."""
    directions = np.asarray(directions, dtype=np.float64)
    cosine = np.maximum(normals @ directions.T, 0.0).T
    if views is None:
        cos_half = np.clip(normals @ _half_vectors(directions).T, 0.0, 1.0).T
        return cosine, cos_half
    cos_half = np.empty_like(cosine)
    for k, light in enumerate(directions):  # (N, 3) half vectors a light at a time
        half = light + np.asarray(views, dtype=np.float64)
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        cos_half[k] = np.clip((normals * half).sum(axis=1), 0.0, 1.0)
    return cosine, cos_half


def _lobe(cosine: np.ndarray, cos_half: np.ndarray, shininess: float) -> np.ndarray:
    """(m, N) normalised Blinn-Phong lobe times the cosine of incidence."""
    return (shininess + 2.0) / 2.0 * cos_half ** shininess * cosine


def _hats(cosine: np.ndarray) -> np.ndarray:
    """(..., K) piecewise-linear basis over DIFFUSE_KNOTS, times the cosine."""
    knots = np.array(DIFFUSE_KNOTS)
    basis = np.empty((*cosine.shape, len(knots)))
    for j, _knot in enumerate(knots):
        unit = np.zeros(len(knots))
        unit[j] = 1.0
        basis[..., j] = np.interp(cosine, knots, unit)
    return basis * cosine[..., None]


def fit_brdf(observations: np.ndarray, normals: np.ndarray, directions: np.ndarray,
             intensities: np.ndarray, usable: np.ndarray, *, settle_rounds: int = 0
             ) -> tuple[BRDF, float]:
    """Fit a :class:`BRDF` to observations of pixels at known (estimated) normals.

    The falloff g and the normals' tilt can explain much the same shading: a
    falloff fitted at normals of another finish's match takes up their error,
    and the joint rounds then stay near them. With ``settle_rounds`` the first
    rounds hold g at Lambert's (g = 1), fitting the roughness and the highlight
    alone, while the normals settle; the rest free it.

    Parameters
    ----------
    observations : (m, N, c) ndarray
        Linear values of N pixels in m images.
    normals : (N, 3) ndarray
        Their unit normals (an estimate).
    directions, intensities : (m, 3), (m, c) ndarray
        The lights.
    usable : (m, N, c) ndarray of bool
        Measurements to fit (not clipped, not dark, finite).
    settle_rounds : int, optional
        Rounds (of 1 + JOINT_ROUNDS) that hold the falloff at Lambert's.

    Returns
    -------
    (BRDF, float)
        The fit and its robust RMS relative residual.

    Raises
    ------
    InputError
        When too few usable measurements are lit.
    """
    obs = np.asarray(observations, dtype=np.float64)
    _m, _n_pixels, c = obs.shape
    lit = np.maximum(normals @ directions.T, 0.0).T  # (m, N) at the given normals
    use = np.asarray(usable, dtype=bool) & (lit >= MIN_FIT_COSINE)[..., None]
    obs = np.where(use, obs / intensities[:, None, :], 0.0)
    if use.sum() < 10 * (len(DIFFUSE_KNOTS) + c + 1):
        raise InputError(f"brdf fit: only {int(use.sum())} usable lit measurements")
    # Relative weights: each pixel and band counts alike whatever its albedo.
    scale = np.sqrt((obs ** 2).sum(axis=0))  # (N, c)
    base_weight = np.where(use, 1.0 / np.maximum(scale, 1e-12) ** 2, 0.0)
    normals = np.array(normals, dtype=np.float64)
    grid = SHININESS_GRID
    step = np.log(SHININESS_GRID[1] / SHININESS_GRID[0])
    brdf = BRDF.lambert()  # round 0 fits at the given normals; later rounds refine them
    roughness_grid = ROUGHNESS_GRID[::2]  # every other value first, then neighbours
    for round_ in range(1 + JOINT_ROUNDS):
        if round_:
            normals = _relaxed_normals(obs, base_weight, normals, brdf, directions)
        cosine, cos_half = _angles(normals, directions)  # one round's normals
        hats = _hats(cosine)  # (m, N, K)
        fits = {}

        prior = SETTLED_PRIOR_WEIGHT if round_ < settle_rounds else PRIOR_WEIGHT

        def fit_at(shininess, roughness, fits=fits, hats=hats, cosine=cosine,
                   cos_half=cos_half, normals=normals, prior=prior):  # this round's, bound now
            if (shininess, roughness) not in fits:
                basis = hats if roughness == 0.0 else \
                    hats * oren_nayar_factor(normals, directions, roughness)[..., None]
                fits[shininess, roughness] = _fit_at(obs, base_weight, basis,
                                                     _lobe(cosine, cos_half, shininess), prior)
            return fits[shininess, roughness][2]

        roughness = brdf.roughness
        shininess = min(grid, key=lambda v: fit_at(v, roughness))
        for _ in range(SHININESS_STEPS if round_ == 0 else 0):
            step /= 2.0
            shininess = min((shininess * np.exp(-step), shininess, shininess * np.exp(step)),
                            key=lambda v: fit_at(v, roughness))
        roughness = min(roughness_grid, key=lambda v: fit_at(shininess, v))
        # Later rounds try this round's best and its neighbours at the last step.
        grid = (shininess * np.exp(-step), shininess, shininess * np.exp(step))
        roughness_grid = roughness_bracket(roughness)
        falloff, specular, cost = fits[shininess, roughness]
        brdf = BRDF(tuple(falloff), tuple(specular), shininess, roughness)
    if not np.any(brdf.specular):
        brdf = BRDF(brdf.falloff, brdf.specular, roughness=brdf.roughness)
    return brdf, float(np.sqrt(cost))


def _relaxed_normals(obs, weight, normals, brdf: BRDF, directions) -> np.ndarray:
    """The sample's normals refined under ``brdf``, their step over-relaxed
    (OVER_RELAXATION)."""
    refined = _refine_normals(obs, weight, normals, brdf, directions)
    moved = normals + OVER_RELAXATION * (refined - normals)
    return moved / np.linalg.norm(moved, axis=1, keepdims=True)


def _refine_normals(obs, weight, normals, brdf: BRDF, directions) -> np.ndarray:
    """Normals that explain the observations best under ``brdf`` (damped
    Gauss-Newton on two tangent angles per pixel, albedos projected out)."""
    m, n_pixels, c = obs.shape
    ones = np.ones((m, c))
    # Tangent basis of each normal.
    helper = np.where(np.abs(normals[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(normals, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(normals, t1)
    root = np.sqrt(weight)

    def residual(n):
        model = brdf.shade(n, directions, ones)
        albedo = (weight * model * obs).sum(0) / np.maximum((weight * model ** 2).sum(0),
                                                            1e-30)
        return ((obs - albedo[None] * model) * root).transpose(1, 0, 2) \
            .reshape(n_pixels, -1)

    def moved(du, dv):
        n = normals + du[:, None] * t1 + dv[:, None] * t2
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        n[:, 2] = np.maximum(n[:, 2], 0.0)  # stay facing the camera
        return n / np.linalg.norm(n, axis=1, keepdims=True)

    u = np.zeros(n_pixels)
    v = np.zeros(n_pixels)
    damping = np.full(n_pixels, 1e-3)
    current = residual(moved(u, v))
    cost = (current ** 2).sum(1)
    for _ in range(NORMAL_STEPS):
        ju = (residual(moved(u + NORMAL_EPS, v)) - current) / NORMAL_EPS
        jv = (residual(moved(u, v + NORMAL_EPS)) - current) / NORMAL_EPS
        a, b, d = (ju * ju).sum(1), (ju * jv).sum(1), (jv * jv).sum(1)
        gu, gv = (ju * current).sum(1), (jv * current).sum(1)
        a_d, d_d = a * (1 + damping), d * (1 + damping)
        det = np.maximum(a_d * d_d - b * b, 1e-30)
        du = np.clip(-(d_d * gu - b * gv) / det, -MAX_NORMAL_STEP, MAX_NORMAL_STEP)
        dv = np.clip(-(a_d * gv - b * gu) / det, -MAX_NORMAL_STEP, MAX_NORMAL_STEP)
        trial = residual(moved(u + du, v + dv))
        trial_cost = (trial ** 2).sum(1)
        better = trial_cost < cost
        u, v = np.where(better, u + du, u), np.where(better, v + dv, v)
        current = np.where(better[:, None], trial, current)
        cost = np.where(better, trial_cost, cost)
        damping = np.where(better, damping / 3.0, damping * 10.0)
    return moved(u, v)


def _fit_at(obs, base_weight, diffuse_basis, lobe, prior_weight):
    """Alternating least squares at one shininess: (falloff, specular, cost).

    ``prior_weight`` is the pull of the falloff towards Lambert's (PRIOR_WEIGHT,
    or SETTLED_PRIOR_WEIGHT to hold it there).

    The cost is the mean Huber loss of the relative residuals, with the
    threshold taken from the Lambertian start (the same for every shininess).
    Each round's passes over the measurements are compiled
    (:mod:`colorps._brdf_kernels`); the small normal equations are solved here.
    """
    from scipy.optimize import nnls

    from . import _brdf_kernels as kernels

    _m, n_pixels, c = obs.shape
    k = diffuse_basis.shape[-1]
    obs, base_weight, diffuse_basis, lobe = (np.ascontiguousarray(a, dtype=np.float64) for a in
                                             (obs, base_weight, diffuse_basis, lobe))
    falloff = np.ones(k)
    specular = np.zeros(c)
    robust = np.ones_like(obs)
    albedo = np.empty((n_pixels, c))
    normal = np.empty((k - 1 + c, k - 1 + c))
    right = np.empty(k - 1 + c)
    # Prior rows: falloff towards 1 and smooth (second differences).
    prior = np.eye(k - 1, k - 1 + c)
    second = np.zeros((k - 3, k - 1 + c))
    for j in range(k - 3):
        second[j, j:j + 3] = (1.0, -2.0, 1.0)
    regulariser = prior_weight * prior.T @ prior + SMOOTHNESS_WEIGHT * second.T @ second
    pull = prior_weight * prior.T @ np.ones(k - 1)
    measured = np.count_nonzero(base_weight)
    data = dict(obs=obs, weight=base_weight, basis=diffuse_basis, lobe=lobe)
    kernels.fit_albedo(robust=robust, falloff=falloff, specular=specular, albedo=albedo,
                       **data)
    relative = np.empty_like(obs)
    kernels.relative_residuals(falloff=falloff, specular=specular, albedo=albedo,
                               out=relative, **data)
    threshold = HUBER_K * 1.4826 * np.median(np.abs(relative[base_weight > 0])) + 1e-12
    del relative
    cost = np.inf
    for round_ in range(FIT_ROUNDS + 1):
        if round_:
            kernels.fit_albedo(robust=robust, falloff=falloff, specular=specular,
                               albedo=albedo, **data)
        # Huber factors and loss at this fit; the next fit's normal equations,
        # linear in (falloff[:-1], specular) given the albedo.
        loss, total = kernels.huber_normal_equations(
            robust=robust, falloff=falloff, specular=specular, albedo=albedo,
            threshold=threshold, normal=normal, right=right, **data)
        converged = loss / measured > (1.0 - FIT_TOLERANCE) * cost
        cost = loss / measured
        if round_ == FIT_ROUNDS or converged:
            break
        normal /= total
        right /= total
        level = np.trace(normal) / len(normal)
        normal += level * regulariser
        right += level * pull
        upper = np.linalg.cholesky(normal).T
        solution, _residual = nnls(upper, np.linalg.solve(upper.T, right))
        falloff = np.append(solution[:k - 1], 1.0)
        specular = solution[k - 1:]
    return falloff, specular, cost
