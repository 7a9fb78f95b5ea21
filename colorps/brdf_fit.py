"""The fit of a :class:`~colorps.brdf.BRDF` to a scene's observations.

:func:`fit_brdf` fits g, sigma, s, alpha and which highlight to a scene's
observations at given normals (an initial estimate from a Lambertian gauge,
then from the fitted one: :func:`colorps.virtual.fit_scene_brdf`): alternating
least squares between the per-pixel albedos and the shared, non-negative
parameters, on relative residuals with robust (Huber) weights so that cast
shadows and interreflections do not pull the fit, over grids of alpha and
roughness values.
"""

from __future__ import annotations

import numpy as np

from .brdf import BRDF, DIFFUSE_KNOTS, best_normals, ggx_lobe, shading_angles
from .errors import InputError
from .finishes import oren_nayar_factor

__all__ = ["ALPHA_GRID", "ROUGHNESS_GRID", "fit_brdf", "refined_roughness",
           "relative_weights", "roughness_bracket"]

# ---------------------------------------------------------------- tuning
#: GGX roughness values tried (alpha; 0.014 is a highlight about 1 degree
#: wide, 0.6 one spread over most of the sphere), then ALPHA_STEPS halvings of
#: the (logarithmic) step around the best; each joint round (below) tries the
#: best and its neighbours.
ALPHA_GRID = tuple(float(v) for v in np.geomspace(0.6, 0.014, 10))
ALPHA_STEPS = 2
#: A white highlight is fitted with alpha up to this: broader, it is nearly a
#: diffuse term of its own, and took up the light a concave object bounces onto
#: itself (folds under a one-bounce interreflection: a white lobe of alpha 0.54,
#: 6.2 degrees mean against 0.29 for the tinted fit, which the bounced light
#: taken out then corrects). Clear coats of plastics, paints and glazes are
#: below it (renderers' roughness up to 0.63).
WHITE_MAX_ALPHA = 0.4
#: Oren-Nayar roughness values (radians; 0: smooth, Lambertian) tried at the
#: best alpha of each round: every other one in the first round, then the
#: best and its neighbours. (Refined between them, the fit slid along the valley
#: where a darker falloff stands in for roughness: Oren-Nayar 0.2 and 0.3
#: scenes fitted 0.16 and 0.29, falloffs 0.39 and 0.85 at grazing.)
ROUGHNESS_GRID = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)
#: Where a roughness between ROUGHNESS_GRID's values is sought
#: (:func:`refined_roughness`), to this many radians, and then the vertex of a
#: parabola through the values tried this close to the best.
ROUGHNESS_TOLERANCE = 0.01
ROUGHNESS_WINDOW = 0.03
#: Observations whose cosine of incidence at the estimated normal is below this
#: are left out: attached-shadow boundaries are where normal errors matter most.
MIN_FIT_COSINE = 0.02
#: fit_brdf then refines the sample's normals under the fit
#: (:func:`colorps.brdf.best_normals`) and fits again, JOINT_ROUNDS times: normals
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
#: Alternating least-squares rounds per alpha value, at most: they stop
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


def _hats(cosine: np.ndarray) -> np.ndarray:
    """(..., K) piecewise-linear basis over DIFFUSE_KNOTS, times the cosine."""
    knots = np.array(DIFFUSE_KNOTS)
    basis = np.empty((*cosine.shape, len(knots)))
    for j, _knot in enumerate(knots):
        unit = np.zeros(len(knots))
        unit[j] = 1.0
        basis[..., j] = np.interp(cosine, knots, unit)
    return basis * cosine[..., None]


def relative_weights(observations: np.ndarray, normals: np.ndarray, directions: np.ndarray,
                     intensities: np.ndarray, usable: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Observations per unit light, and their least-squares weights relative to
    each pixel's scale in each band (every pixel and band counts alike whatever
    its albedo): 0 for the measurements not ``usable`` or lit under
    MIN_FIT_COSINE at ``normals`` (their observations read 0).

    Parameters
    ----------
    observations, usable : (m, N, c) ndarray
        Linear values of N pixels in m images, and which to use.
    normals : (N, 3) ndarray
        Their unit normals (an estimate).
    directions, intensities : (m, 3), (m, c) ndarray
        The lights.

    Returns
    -------
    (obs, weight) : (m, N, c) ndarrays of float64
    """
    lit = np.asarray(normals, dtype=np.float64) @ np.asarray(directions).T >= MIN_FIT_COSINE
    use = np.asarray(usable, dtype=bool) & lit.T[..., None]
    obs = np.where(use, np.asarray(observations, dtype=np.float64) /
                   np.asarray(intensities, dtype=np.float64)[:, None, :], 0.0)
    scale = np.sqrt((obs ** 2).sum(axis=0))  # (N, c)
    return obs, np.where(use, 1.0 / np.maximum(scale, 1e-12) ** 2, 0.0)


def fit_brdf(observations: np.ndarray, normals: np.ndarray, directions: np.ndarray,
             intensities: np.ndarray, usable: np.ndarray, *, settle_rounds: int = 0,
             held_falloff: tuple | None = None, known_normals: bool = False,
             views: np.ndarray | None = None) -> tuple[BRDF, float]:
    """Fit a :class:`BRDF` to observations of pixels at known (estimated) normals.

    The falloff g and the normals' tilt can explain much the same shading: a
    falloff fitted at normals of another finish's match takes up their error,
    and the joint rounds then stay near them. With ``settle_rounds`` the first
    rounds hold g at Lambert's (g = 1), fitting the roughness and the highlight
    alone, while the normals settle; the rest free it. The first round fits a
    highlight tinted by the albedo and a white one (alpha up to
    WHITE_MAX_ALPHA), and the rounds after it keep the one of lower cost.

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
    held_falloff : tuple of float, optional
        A falloff (at DIFFUSE_KNOTS) held through every round instead: a
        gauge's of the same finish (:mod:`colorps.gauge_finish`), where the
        normals are estimates and the falloff would otherwise trade with their
        tilt.
    known_normals : bool, optional
        The normals are known (a gauge's): not refined between rounds.
    views : (N, 3) ndarray, optional
        Each pixel's unit direction towards the camera (default +z).

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
    obs, base_weight = relative_weights(obs, normals, directions, intensities, usable)
    used = np.count_nonzero(base_weight)
    if used < 10 * (len(DIFFUSE_KNOTS) + c + 1):
        raise InputError(f"brdf fit: only {used} usable lit measurements")
    normals = np.array(normals, dtype=np.float64)
    grid = ALPHA_GRID
    step = np.log(ALPHA_GRID[0] / ALPHA_GRID[1])
    brdf = BRDF.lambert()  # round 0 fits at the given normals; later rounds refine them
    roughness_grid = ROUGHNESS_GRID[::2]  # every other value first, then neighbours
    kinds = (False, True)  # tinted and white highlights: the better one is kept
    held = held_falloff is not None
    centre = np.asarray(held_falloff if held else BRDF.lambert().falloff, dtype=np.float64)
    for round_ in range(1 + JOINT_ROUNDS):
        if round_ and not known_normals:
            normals = _relaxed_normals(obs, base_weight, normals, brdf, directions, views)
        angles = shading_angles(normals, directions, views)  # one round's normals
        hats = _hats(angles[0])  # (m, N, K)
        fits = {}

        prior = (SETTLED_PRIOR_WEIGHT if held or round_ < settle_rounds else PRIOR_WEIGHT,
                 centre)

        def basis_at(roughness, hats=hats, normals=normals):
            return hats if roughness == 0.0 else \
                hats * oren_nayar_factor(normals, directions, roughness, views)[..., None]

        # One robust threshold for every fit of the round (their costs compared):
        # from Lambert's residuals. (One per roughness, from its own Lambertian
        # start, scored the roughnesses on different scales: Oren-Nayar 0.3 folds
        # 0.26 against 0.14 degrees in virtual mode.)
        threshold = _huber_threshold(obs, base_weight, hats, np.zeros(obs.shape[:2]), False,
                                     centre, np.zeros(c))

        def fit_at(alpha, roughness, white, fits=fits, angles=angles, prior=prior,
                   threshold=threshold):  # this round's, bound now
            if white and alpha > WHITE_MAX_ALPHA:
                return np.inf
            if (alpha, roughness, white) not in fits:
                fits[alpha, roughness, white] = _fit_at(
                    obs, base_weight, basis_at(roughness), ggx_lobe(angles, alpha), prior,
                    white, threshold)
            return fits[alpha, roughness, white][2]

        roughness = brdf.roughness
        best = {}
        for white in kinds:
            alpha = min(grid, key=lambda v: fit_at(v, roughness, white))
            halving = step
            for _ in range(ALPHA_STEPS if round_ == 0 else 0):
                halving /= 2.0
                alpha = min((alpha * np.exp(-halving), alpha, alpha * np.exp(halving)),
                            key=lambda v: fit_at(v, roughness, white))
            best[white] = alpha
        white = min(kinds, key=lambda kind: fit_at(best[kind], roughness, kind))
        alpha = best[white]
        if round_ == 0:
            step /= 2.0 ** ALPHA_STEPS
            kinds = (white,)
        roughness = min(roughness_grid, key=lambda v: fit_at(alpha, v, white))
        # Later rounds try this round's best and its neighbours at the last step.
        grid = tuple(float(min(v, 1.0)) for v in
                     (alpha * np.exp(-step), alpha, alpha * np.exp(step)))
        roughness_grid = roughness_bracket(roughness)
        falloff, specular, cost = fits[alpha, roughness, white]
        brdf = BRDF(tuple(falloff), tuple(specular), alpha, roughness, white)
    if not np.any(brdf.specular):
        brdf = brdf.diffuse
    return brdf, float(np.sqrt(cost))


def _relaxed_normals(obs, weight, normals, brdf: BRDF, directions, views) -> np.ndarray:
    """The sample's normals refined under ``brdf``, their step over-relaxed
    (OVER_RELAXATION)."""
    refined = best_normals(obs, weight, normals, brdf, directions, views)
    moved = normals + OVER_RELAXATION * (refined - normals)
    return moved / np.linalg.norm(moved, axis=1, keepdims=True)


def _huber_threshold(obs, base_weight, diffuse_basis, lobe, white, falloff, specular):
    """HUBER_K robust standard deviations of the relative residuals of a finish
    (falloff, specular), each pixel's albedo fitted."""
    from . import _brdf_kernels as kernels

    data = dict(obs=obs, weight=base_weight, basis=np.ascontiguousarray(diffuse_basis),
                lobe=np.ascontiguousarray(lobe, dtype=np.float64), white=white,
                falloff=np.asarray(falloff, dtype=np.float64),
                specular=np.asarray(specular, dtype=np.float64))
    albedo = np.empty(obs.shape[1:])
    kernels.fit_albedo(robust=np.ones_like(obs), albedo=albedo, **data)
    relative = np.empty_like(obs)
    kernels.relative_residuals(albedo=albedo, out=relative, **data)
    return HUBER_K * 1.4826 * float(np.median(np.abs(relative[base_weight > 0]))) + 1e-12


def _fit_at(obs, base_weight, diffuse_basis, lobe, prior, white, threshold):
    """Alternating least squares at one alpha: (falloff, specular, cost).

    ``white``: the highlight is absolute, else relative to the albedo.
    ``prior`` is (the pull of the falloff towards a centre: PRIOR_WEIGHT, or
    SETTLED_PRIOR_WEIGHT to hold it there; that centre, at DIFFUSE_KNOTS:
    Lambert's or a held one).

    The cost is the mean Huber loss of the relative residuals beyond
    ``threshold`` (:func:`_huber_threshold`; the same for every fit of a round).
    Each round's passes over the measurements are compiled
    (:mod:`colorps._brdf_kernels`); the small normal equations are solved here.
    """
    from scipy.optimize import nnls

    from . import _brdf_kernels as kernels

    _m, n_pixels, c = obs.shape
    k = diffuse_basis.shape[-1]
    obs, base_weight, diffuse_basis, lobe = (np.ascontiguousarray(a, dtype=np.float64) for a in
                                             (obs, base_weight, diffuse_basis, lobe))
    prior_weight, centre = prior
    falloff = np.array(centre, dtype=np.float64)
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
    pull = prior_weight * prior.T @ centre[:-1]
    measured = np.count_nonzero(base_weight)
    data = dict(obs=obs, weight=base_weight, basis=diffuse_basis, lobe=lobe, white=white)
    kernels.fit_albedo(robust=robust, falloff=falloff, specular=specular, albedo=albedo,
                       **data)
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
        if white:
            kernels.white_strength(obs=obs, weight=base_weight, robust=robust,
                                   basis=diffuse_basis, lobe=lobe, falloff=falloff,
                                   specular=specular)
    return falloff, specular, cost
