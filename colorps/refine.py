"""Normals finer than the gauge's pixels, and how certain they are.

The exact lookup returns a gauge pixel; its normal is only as fine as the
gauge's pixel grid (about 1 / (r cos theta) radians per pixel on a sphere of
radius r). :func:`refine_normals` fits, around the matched gauge pixel, a
quadratic model of every gauge measurement (and of the gauge normal) over its
5 x 5 neighbourhood (3 x 3 near the rim), and moves to the sub-pixel position whose modelled
observation vector explains the pixel's best (weighted by the noise model,
over the bands and lights the match used, measurements far outside the noise
down-weighted: ROBUST_LIMIT), by Gauss-Newton. At the edge of the usable
gauge the fit may go a few pixels past it on the outermost model
(EXTRAPOLATE): normals the gauge does not show. This works for any gauge given
as normals and a mask, not only for spheres.

The **uncertainty** is the radius (degrees) within which the true normal lies
with 68 % probability under the noise model: the offset's covariance
(J^T W J)^-1 from the Jacobian of the fit (each band's scale projected out of
it, so profiled out of the covariance), carried to the normal through the
normal's derivatives, scaled by the capture's model scale, taken as an
isotropic 2-D Gaussian (68 % radius = 1.515 sigma per axis). Beside it, the
**measured uncertainty** is the same radius from the sandwich covariance
(J^T W J)^-1 (J^T W diag(r^2) W J) (J^T W J)^-1 of the residuals r the fit
leaves (times n / (n - p) for the p fitted values), which grows where the
measurements depart from the gauge along the directions that move the normal.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from . import _refine_kernels
from .noise import NoiseModel

__all__ = [
    "RADIUS_68",
    "REFINE_METHODS",
    "Matched",
    "QuadraticModels",
    "Refinement",
    "misfit_radius",
    "noise_tables",
    "quadratic_models",
    "refine_normals",
]

#: Refinement methods of ``Options.refine``.
REFINE_METHODS = ("quadratic", "none")
#: Measurements the fit leaves more than this many noise units (times the
#: capture's model scale) from the gauge's are down-weighted (Huber: weight
#: limit / residual): a light whose cast shadow is too faint to be found (near
#: grazing incidence, a few noise units), a trace of a highlight. On deep folds
#: under 32 lights the normals of pixels with such a shadow went 0.26 -> 0.16
#: degrees (median), the others' stayed at 0.10; DiLiGenT Ball 1.13 -> 1.12.
ROBUST_LIMIT = 2.0
#: Pixels refined at a time: the kernel's per-pixel outputs (about 100 bytes
#: each) are allocated for a block, not for every pixel of a large scene.
REFINE_BLOCK = 2 ** 18
#: For an isotropic 2-D Gaussian with sigma per axis, 68 % of the mass lies
#: within this many sigma of the centre: sqrt(-2 ln(1 - 0.68)).
RADIUS_68 = float(np.sqrt(-2.0 * np.log(1.0 - 0.68)))
#: A residual counts as a misfit only where its square exceeds 1 by more than
#: this many of the noise's own standard deviations, sqrt(2 / dof): below it,
#: the noise alone explains it. With 0 the noise's own spread counted as misfit
#: (78 % of clean renders' errors within the radius); with 2, 66-70 %
#: (docs/benchmarks.md).
MISFIT_NOISE_SDS = 2.0


@dataclass(frozen=True)
class Refinement:
    """Refined matches of P pixels.

    Attributes
    ----------
    normals : (P, 3) ndarray of float32
        Refined unit normals (the table's where not refined).
    uncertainty : (P,) ndarray of float32
        68 % angular radius in degrees under the noise model (NaN where not
        refined).
    measured_uncertainty : (P,) ndarray of float32
        The same radius from the residuals the fit leaves (the sandwich
        covariance C M C, M their spread along the Jacobian): larger where the
        measurements disagree with the gauge more than the noise would, along
        the directions that move the normal (NaN where not refined or with no
        degrees of freedom left).
    offset : (P, 2) ndarray of float32
        Refined position in gauge pixels (columns, rows) relative to the
        matched gauge pixel (up to MAX_MOVES + EXTRAPOLATE pixels away).
    refined : (P,) ndarray of bool
        False where the gauge neighbourhood was incomplete (rim, holes).
    inlier_residual : (P,) ndarray of float32
        The fit's residual over its inliers: the root of their chi-square per
        degree of freedom, in noise units before the model scale (NaN where
        not refined or none is left). Unlike the match's residual it has no
        share for the table's pixel steps: the fit is continuous.
    outliers : (P, words) ndarray of uint64
        Light masks (:mod:`colorps.light_masks`) of the lights with a
        measurement the fit leaves more than ``outlier_z`` off.
    """

    normals: np.ndarray
    uncertainty: np.ndarray
    measured_uncertainty: np.ndarray
    offset: np.ndarray
    refined: np.ndarray
    inlier_residual: np.ndarray
    outliers: np.ndarray


class QuadraticModels(NamedTuple):
    """The gauge's local quadratic models (:func:`quadratic_models`)."""

    coef: np.ndarray
    ncoef: np.ndarray
    window: np.ndarray


def quadratic_models(values: np.ndarray, normals: np.ndarray, usable: np.ndarray,
                     needed: np.ndarray | None = None) -> QuadraticModels:
    """The local quadratic model of every gauge series around gauge pixels.

    Parameters
    ----------
    values : (Hg, Wg, S) ndarray
        S gauge measurement series (bands x lights).
    normals : (Hg, Wg, 3) ndarray
    usable : (Hg, Wg) ndarray of bool
    needed : (Hg, Wg) ndarray of bool, optional
        Pixels whose models are wanted (default: all).

    Returns
    -------
    QuadraticModels
    coef : (Hg, Wg, S, 6) float32, ncoef : (Hg, Wg, 3, 6) float32
        Coefficients of (1, u, v, u^2, uv, v^2), fitted by least squares over
        the largest window of ``_refine_kernels.HALVES`` whose pixels are all
        usable (0 elsewhere).
    window : (Hg, Wg) int8
        Half side of that window (0: none, or not needed).
    """
    from scipy.ndimage import binary_erosion

    hg, wg = usable.shape
    window = np.zeros((hg, wg), dtype=np.int8)
    for half in sorted(_refine_kernels.HALVES):  # wider windows overwrite narrower
        side = 2 * half + 1
        window[binary_erosion(usable, np.ones((side, side), bool), border_value=0)] = half
    if needed is not None:
        window[~needed] = 0
    models = []
    for series in (values, normals):
        series = np.ascontiguousarray(series, dtype=np.float32)
        coef = np.zeros((hg, wg, series.shape[2], 6), dtype=np.float32)
        for half in _refine_kernels.HALVES:
            ys, xs = np.nonzero(window == half)
            _refine_kernels.fit_quadratics(series, ys, xs, half,
                                           _refine_kernels.quadratic_fit_matrix(half), coef)
        models.append(coef)
    return QuadraticModels(models[0], models[1], window)


def noise_tables(scene: NoiseModel, gauge: NoiseModel) -> _refine_kernels.NoiseTables:
    """The kernel's description of two noise models (NoiseModel.kernel_args of each,
    stacked): (2, 3) (read^2, gain, pixel kind), the (Q,) levels 0..1 and the
    (2, Q) quantisation sigma at them (integer files; 0 for the others)."""
    from .noise import _quantisation_levels

    levels = _quantisation_levels()
    noise = np.zeros((2, 3))
    table = np.zeros((2, levels.size))
    for row, model in enumerate((scene, gauge)):
        read2, gain, kind, _, model_table = model.kernel_args()  # integer files: at levels
        noise[row] = (read2, gain, kind)
        if model.pixel_type == "int":
            table[row] = model_table
    return _refine_kernels.NoiseTables(noise, levels, table)


class Matched(NamedTuple):
    """Matched pixels to refine.

    Attributes
    ----------
    ys, xs : (P,) ndarray of int
        The pixels.
    rows : (P,) ndarray of int
        Flat index of each pixel's matched gauge pixel.
    bands : (P,) ndarray of uint8
        Bit k set: band k was matched.
    dropped : (P, words) ndarray of uint64
        Light masks (:mod:`colorps.light_masks`) of the lights left out of
        each match.
    """

    ys: np.ndarray
    xs: np.ndarray
    rows: np.ndarray
    bands: np.ndarray
    dropped: np.ndarray


def refine_normals(scene_ov: np.ndarray, gauge_ov: np.ndarray, gauge_normals: np.ndarray,
                   usable: np.ndarray, matched: Matched, scene_noise: NoiseModel,
                   gauge_noise: NoiseModel, *, model_scale: float = 1.0,
                   outlier_z: float = np.inf, threads: int | None = None) -> Refinement:
    """Refine matched normals continuously (see the module docstring).

    Parameters
    ----------
    scene_ov : (H, W, B, M) ndarray
        Scene observation vectors per band.
    gauge_ov : (Hg, Wg, B, M) ndarray
        Gauge observation vectors per band.
    gauge_normals : (Hg, Wg, 3) ndarray
    usable : (Hg, Wg) ndarray of bool, or QuadraticModels
        Gauge pixels whose measurements and normal may be used; or the
        :func:`quadratic_models` of every such pixel, fitted before (else they
        are fitted here, around the matched pixels only).
    matched : Matched
        The pixels to refine and their matches.
    scene_noise, gauge_noise : NoiseModel
        Weights are 1 / (sigma_S^2 + (|S_k| / |G_k|)^2 sigma_G^2).
    model_scale : float, optional
        The capture's model scale (uncertainties grow with it).
    outlier_z : float, optional
        A light with a measurement the robust fit leaves more than this many
        noise units (times the model scale) off is an outlier
        (``Refinement.outliers``; ``inlier_residual`` is over the others).
    threads : int, optional

    Returns
    -------
    Refinement
    """
    import numba
    from scipy.ndimage import binary_dilation

    from ._checks import resolve_threads

    hg, wg, b, m = gauge_ov.shape
    n = len(matched.rows)
    rows = np.asarray(matched.rows, dtype=np.int64)
    models = usable
    if not isinstance(models, QuadraticModels):
        # The fit may move MAX_MOVES pixels, from the matched pixel or, at the rim,
        # from its modelled neighbour: every model it may look at is fitted, so a
        # pixel's normal does not depend on what the others matched (tiles).
        near = np.zeros(hg * wg, dtype=bool)
        near[rows] = True
        reach = 2 * (_refine_kernels.MAX_MOVES + 1) + 1
        needed = binary_dilation(near.reshape(hg, wg), np.ones((reach, reach), bool))
        models = quadratic_models(gauge_ov.reshape(hg, wg, b * m), gauge_normals, usable,
                                  needed)
    coef, ncoef, window = models
    gauge = _refine_kernels.GaugeModel(coef, ncoef, window,
                                       np.ascontiguousarray(gauge_ov, dtype=np.float32))
    scene_ov = np.ascontiguousarray(scene_ov, dtype=np.float32)
    dropped = np.ascontiguousarray(matched.dropped, dtype=np.uint64).reshape(n, -1)
    tables = noise_tables(scene_noise, gauge_noise)
    result = Refinement(np.empty((n, 3), np.float32), np.empty(n, np.float32),
                        np.empty(n, np.float32), np.empty((n, 2), np.float32),
                        np.empty(n, bool), np.empty(n, np.float32), np.zeros_like(dropped))
    previous = numba.get_num_threads()
    numba.set_num_threads(resolve_threads(threads))
    try:
        for first in range(0, n, REFINE_BLOCK):  # bounded per-pixel scratch
            block = slice(first, min(first + REFINE_BLOCK, n))
            qy, qx = np.divmod(rows[block], wg)
            pixels = _refine_kernels.Pixels(
                scene_ov, np.asarray(matched.ys[block], np.int64),
                np.asarray(matched.xs[block], np.int64), qy, qx,
                np.asarray(matched.bands[block], np.uint8), dropped[block])
            part = _refine_block(gauge, pixels, tables, gauge_normals, model_scale,
                                 (ROBUST_LIMIT * model_scale, outlier_z * model_scale))
            for field in dataclasses.fields(Refinement):
                getattr(result, field.name)[block] = getattr(part, field.name)
    finally:
        numba.set_num_threads(previous)
    return result


def misfit_radius(unit_radius: np.ndarray, residual: np.ndarray,
                  dof: np.ndarray) -> np.ndarray:
    """How far the normal may be off where the gauge does not explain a pixel.

    A misfit the noise does not explain (bounced light, another finish, a
    varnish) shows in the residual only across the gauge's signatures; along
    them, where it moves the normal, it is not seen. Taken as large along as
    across, its size in noise units, sqrt((r^2 - 1) dof) (the part of the
    residual's chi-square beyond the noise's, less MISFIT_NOISE_SDS of the
    noise's own spread), moves the normal that many times the noise's sigma.

    Parameters
    ----------
    unit_radius : (P,) ndarray
        The noise's 68 % radius (degrees) for noise of one unit (before the
        capture's model scale).
    residual : (P,) ndarray
        r of :mod:`colorps.residuals`, before the capture's model scale (NaN:
        none, taken as explained).
    dof : (P,) ndarray of int
        Its degrees of freedom: bands matched x (lights used - 1).

    Returns
    -------
    (P,) ndarray
        Radius in degrees; 0 where the noise explains the residual.
    """
    # In place, a few (P,) arrays at a time (P: millions of pixels).
    dof = np.maximum(np.asarray(dof, dtype=np.float64), 1.0)
    excess = np.nan_to_num(np.asarray(residual, dtype=np.float64), nan=1.0)
    excess **= 2
    excess -= 1.0
    spread = np.divide(2.0, dof)
    np.sqrt(spread, out=spread)
    spread *= MISFIT_NOISE_SDS
    excess -= spread
    del spread
    np.maximum(excess, 0.0, out=excess)
    excess *= dof
    np.sqrt(excess, out=excess)
    excess *= unit_radius
    excess /= RADIUS_68
    return excess


def _refine_block(gauge, pixels, tables, gauge_normals: np.ndarray, model_scale: float,
                  limits: tuple[float, float]) -> Refinement:
    """Run the kernel on one block of pixels; their Refinement."""
    n, qy, qx = len(pixels.y), pixels.qy, pixels.qx
    out = _refine_kernels.Refined(y=qy.copy(), x=qx.copy(), u=np.zeros(n), v=np.zeros(n),
                                  normal=np.zeros((n, 3)), cov=np.full(n, np.nan),
                                  fit=np.full(n, np.nan), ok=np.zeros(n, dtype=bool),
                                  chi2=np.full(n, np.nan),
                                  outliers=np.zeros_like(pixels.dropped))
    _refine_kernels.refine(gauge, pixels, tables, *limits, out)
    out_y, out_x, out_u, out_v, out_normal, out_cov, out_fit, out_ok, out_chi2, outliers = out
    table_normals = gauge_normals[qy, qx]
    normals = np.where(out_ok[:, None], out_normal, table_normals)
    sigma = np.sqrt(np.maximum(out_cov / 2.0, 0.0)) * model_scale
    uncertainty = np.where(out_ok, np.degrees(RADIUS_68 * sigma), np.nan)
    measured = np.where(out_ok & np.isfinite(out_fit),
                        np.degrees(RADIUS_68 * np.sqrt(np.maximum(out_fit / 2.0, 0.0))), np.nan)
    # Offsets relative to the matched pixel (the fit may have moved).
    offset = np.stack([out_x - qx + out_u, out_y - qy + out_v], axis=1)
    offset = np.where(out_ok[:, None], offset, 0.0)
    inlier_residual = np.where(out_ok, np.sqrt(out_chi2), np.nan)
    return Refinement(normals, uncertainty, measured, offset, out_ok, inlier_residual, outliers)
