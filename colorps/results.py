"""What a reconstruction returns: the maps, and the statistics of the run.

:class:`Reconstruction` holds the per-pixel maps and a
:class:`ReconstructionStats`; :func:`run_statistics` builds the statistics of
one run from its matches and maps, and :func:`combine_statistics` joins those
of the tiles of one capture (:mod:`colorps.tiles`) into the statistics of the
whole. Both are built here only, so report.json reads the same for a tiled and
an untiled run.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections import Counter
from dataclasses import dataclass

import numpy as np

from . import light_masks
from .errors import InputError, LowSolvedWarning
from .matching import Matches, MatchGroup
from .reasons import Reason, reason_counts

__all__ = [
    "LOW_SOLVED_FRACTION",
    "MAX_UNCERTAINTY",
    "Reconstruction",
    "ReconstructionStats",
    "RunClock",
    "Timings",
    "check_solved",
    "combine_statistics",
    "default_band_names",
    "low_solved_message",
    "run_statistics",
    "say_low_solved",
]

#: Below this fraction of the masked pixels solved, a LowSolvedWarning is raised.
LOW_SOLVED_FRACTION = 0.5
#: The largest 68 % radius (degrees) a normal is given: no direction is further
#: off. A fit gone past the gauge's rim, where the gauge's signatures no longer
#: change, had radii of 1e11 degrees.
MAX_UNCERTAINTY = 180.0


@dataclass(frozen=True)
class Timings:
    """Seconds spent per stage (wall clock).

    ``total`` is :func:`colorps.reconstruct`'s; ``integration`` the height's,
    and ``run`` the whole run's from reading the files to writing the last
    (:func:`colorps.pipeline.reconstruct_files`; its phases are in
    report.json's ``run_seconds``), when there were such stages.
    """

    signatures: float
    grid: float
    lookup: float
    refine: float
    total: float
    integration: float | None = None
    run: float | None = None


class RunClock:
    """Wall-clock seconds of a run's phases, one after the other.

    ``start(phase)`` ends the phase under way and starts the next;
    :meth:`as_dict` gives every phase so far, the one under way up to the
    call, and the total since the clock was made: report.json, written last,
    takes it then, so it counts every phase before it.

    Examples
    --------
    >>> clock = RunClock()
    >>> clock.start("reading"); clock.start("writing")
    >>> sorted(clock.as_dict())
    ['reading', 'total', 'writing']
    """

    def __init__(self) -> None:
        self._started = time.perf_counter()
        self._seconds: dict[str, float] = {}
        self._phase: tuple[str, float] | None = None

    def start(self, phase: str) -> None:
        now = time.perf_counter()
        if self._phase is not None:
            name, since = self._phase
            self._seconds[name] = self._seconds.get(name, 0.0) + now - since
        self._phase = (phase, now)

    def as_dict(self) -> dict[str, float]:
        now = time.perf_counter()
        seconds = dict(self._seconds)
        if self._phase is not None:
            name, since = self._phase
            seconds[name] = seconds.get(name, 0.0) + now - since
        return {**seconds, "total": now - self._started}


@dataclass(frozen=True)
class ReconstructionStats:
    """What a reconstruction did (written to report.json as ``statistics``).

    Attributes
    ----------
    images, bands : int
        m, and the number c of input bands.
    mode : str
    signature_dims : int
        Dimension D of the full signature (B m).
    table_size : int
        Gauge pixels with every band usable (the full table |T|).
    grid_n : int or None
        N of the full-signature grid (None when no pixel used it).
    grids : tuple of MatchGroup
        Every table built, full signature first.
    buckets_per_lookup, tests_per_lookup : float
        Mean buckets examined (b) and full distances computed (d) per lookup.
    pixels, solved, solved_from_band_subset, solved_from_light_subset : int
    lights_dropped_per_pixel : dict of str to int
        Solved pixels by number of lights dropped ("0", "1", ...).
    dropped_per_light : list of dict
        Per light: solved pixels that dropped it as darker than the match
        (cast shadow) and as brighter (highlight, interreflection).
    pixels_by_reason : dict of str to int
        Keyed by :attr:`Reason.label`.
    clip_level : float or None
    dark_level : float
        Resolved levels (linear); ``dark_threshold`` = dark_level sqrt(m).
    dark_threshold : float
    noise : dict
        The noise model (:class:`~colorps.noise.NoiseModel`).
    model_scale : float
        Median residual of the first matches when above 1 (model mismatch
        every pixel shares); residuals are divided by it.
    residual_median, residual_p95 : float or None
        Of the matched pixels' ``quality``; ``as_dict`` adds
        ``residual_median_noise_units``, the median before the model scale.
    max_residual, max_distance : float or None
    gauge_usable_fraction : float
        Fraction of the gauge mask with every band usable.
    gauge_spikes_replaced : int
        Isolated spikes in a photographed gauge's images replaced by their
        neighbours' median (:mod:`colorps.spikes`).
    warnings : tuple of str
        What the run warned about (also issued as Python warnings).
    refined : int
        Solved pixels whose normal was refined past the gauge's pixel grid.
    uncertainty_median, uncertainty_p95 : float or None
        Of the refined pixels' 68 % angular uncertainty (degrees).
    seconds : Timings
    """

    images: int
    bands: int
    mode: str
    signature_dims: int
    table_size: int
    grid_n: int | None
    grids: tuple[MatchGroup, ...]
    buckets_per_lookup: float
    tests_per_lookup: float
    pixels: int
    solved: int
    solved_from_band_subset: int
    solved_from_light_subset: int
    lights_dropped_per_pixel: dict
    dropped_per_light: list
    pixels_by_reason: dict
    clip_level: float | None
    dark_level: float
    dark_threshold: float
    noise: dict
    model_scale: float
    residual_median: float | None
    residual_p95: float | None
    max_residual: float | None
    max_distance: float | None
    gauge_usable_fraction: float
    gauge_spikes_replaced: int
    warnings: tuple[str, ...]
    refined: int
    uncertainty_median: float | None
    uncertainty_p95: float | None
    seconds: Timings

    @property
    def residual_median_noise_units(self) -> float | None:
        """The median residual before the run's model scale (which brings every
        run's median to about 1): how well the gauge explains the scene."""
        return None if self.residual_median is None else \
            self.residual_median * self.model_scale

    def as_dict(self) -> dict:
        """Nested plain dicts and lists (JSON-ready), with
        ``residual_median_noise_units``."""
        return {**dataclasses.asdict(self),
                "residual_median_noise_units": self.residual_median_noise_units}


@dataclass(frozen=True)
class Reconstruction:
    """Result of :func:`colorps.reconstruct` (frozen; its arrays are read-only).

    Attributes
    ----------
    normals : (H, W, 3) ndarray of float32
        Camera-space unit normals (x right, y up, z towards the camera); NaN
        where not solved.
    albedo : (H, W, c) ndarray of float32
        Intrinsic albedo per input band (linear, relative to the gauge albedo);
        NaN where not solved, and in a band whose usable measurements cannot
        fix its scale (e.g. every lit measurement clipped).
    quality : (H, W) ndarray of float32
        Residual of the match in units of its expected value under the noise
        model (:mod:`colorps.residuals`): about 1 where the gauge explains
        the pixel, far above for cast shadows, highlights or other materials.
        NaN where no match was attempted.
    uncertainty : (H, W) ndarray of float32
        68 % angular radius of the refined normal, degrees: the noise's
        (:mod:`colorps.refine`) times the match residual where that exceeds 1
        (a pixel the gauge explains worse than the noise is less certain); NaN
        where not solved or not refined.
    solved : (H, W) ndarray of bool
    reason : (H, W) ndarray of uint8
        Why a pixel is not solved: a :class:`~colorps.Reason` code.
    bands_used : (H, W) ndarray of uint8
        Bit k set when band k of the signature was matched (colour mode falls
        back to the valid bands of a pixel).
    dropped_lights : (H, W, words) ndarray of uint64
        Light masks (:mod:`colorps.light_masks`: image i is bit i % 64 of
        word i // 64) of the lights left out of each pixel's match (a cast
        shadow or highlight there); see :attr:`lights_dropped_count`.
    stats : ReconstructionStats
    height : (H, W) ndarray or None
        Height map (pixels), when integrated: see :meth:`with_height`.
    """

    normals: np.ndarray
    albedo: np.ndarray
    quality: np.ndarray
    uncertainty: np.ndarray
    solved: np.ndarray
    reason: np.ndarray
    bands_used: np.ndarray
    dropped_lights: np.ndarray
    stats: ReconstructionStats
    height: np.ndarray | None = None

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                value.flags.writeable = False

    @property
    def lights_dropped_count(self) -> np.ndarray:
        """(H, W) uint8 number of lights dropped from each pixel's match."""
        return light_masks.count(self.dropped_lights).astype(np.uint8)

    def with_uncertainty_added(self, radius, *, bias: bool = False) -> Reconstruction:
        """A copy whose 68 % radii (degrees) have ``radius`` (degrees, a scalar or
        an (H, W) map: an error this result's own fit cannot see) added in
        quadrature (a scatter), or added to them (``bias``: an offset of up to
        ``radius`` in one direction), at most MAX_UNCERTAINTY, their median and
        p95 in ``stats`` again."""
        widened = (self.uncertainty + radius if bias else
                   np.sqrt(self.uncertainty ** 2 + np.square(radius))).astype(np.float32)
        np.minimum(widened, MAX_UNCERTAINTY, out=widened)
        inside = widened[self.solved & np.isfinite(widened)]
        stats = dataclasses.replace(self.stats, uncertainty_median=_median(inside),
                                    uncertainty_p95=_percentile(inside, 95))
        return dataclasses.replace(self, uncertainty=widened, stats=stats)

    def with_height(self, height: np.ndarray, seconds: float | None = None
                    ) -> Reconstruction:
        """A copy with a height map (and the seconds its integration took)."""
        timings = dataclasses.replace(self.stats.seconds, integration=seconds)
        stats = dataclasses.replace(self.stats, seconds=timings)
        return dataclasses.replace(self, height=np.asarray(height),
                                   stats=stats)


def run_statistics(matches: Matches, solved: np.ndarray, reason: np.ndarray,
                   uncertainty: np.ndarray, **given) -> ReconstructionStats:
    """The statistics of one run, from its matches and maps.

    Parameters
    ----------
    matches : Matches
        Every pixel's match (:func:`colorps.matching.match_pixels`).
    solved, reason, uncertainty : (H, W) ndarray
        The run's maps (see :class:`Reconstruction`).
    **given
        The fields of :class:`ReconstructionStats` that the run states as they
        are (images, bands, mode, levels, noise, table size, warnings, seconds...).
    """
    m = given["images"]
    n_bands = given["signature_dims"] // m
    matched = matches.row >= 0
    n_matched = int(np.count_nonzero(matched))
    full = (1 << n_bands) - 1
    full_grid = [g for g in matches.groups if g.bands == tuple(range(n_bands))
                 and g.lights_dropped == () and g.grid_n is not None]
    q = matches.quality[matched]
    dropped = light_masks.to_bool(matches.dropped[solved], m)
    brighter = light_masks.to_bool(matches.brighter[solved], m)
    return ReconstructionStats(
        grid_n=full_grid[0].grid_n if full_grid else None, grids=matches.groups,
        buckets_per_lookup=matches.buckets / n_matched if n_matched else 0.0,
        tests_per_lookup=matches.tests / n_matched if n_matched else 0.0,
        pixels=solved.size, solved=int(solved.sum()),
        solved_from_band_subset=int((solved & (matches.bands_used != full)).sum()),
        solved_from_light_subset=int((solved & ~light_masks.is_empty(matches.dropped)).sum()),
        lights_dropped_per_pixel=_histogram(light_masks.count(matches.dropped[solved])),
        dropped_per_light=[dict(light=i, darker=int((dropped[:, i] & ~brighter[:, i]).sum()),
                                brighter=int(brighter[:, i].sum())) for i in range(m)],
        pixels_by_reason=reason_counts(reason), model_scale=matches.model_scale,
        residual_median=_median(q), residual_p95=_percentile(q, 95),
        refined=int(np.isfinite(uncertainty).sum()),
        uncertainty_median=_median(uncertainty[solved]),
        uncertainty_p95=_percentile(uncertainty[solved], 95), **given)


def combine_statistics(tiles: list[ReconstructionStats], matched: list[int],
                       maps: dict, mask: np.ndarray, said: list, seconds: float
                       ) -> ReconstructionStats:
    """The statistics of a capture run in tiles, from those of its tiles.

    Parameters
    ----------
    tiles : list of ReconstructionStats
        Of the tiles, top to bottom.
    matched : list of int
        Pixels each tile matched (the weights of its per-lookup means).
    maps : dict of str to ndarray
        The whole capture's maps, by :class:`Reconstruction` field name.
    mask : (H, W) ndarray of bool
        The pixels the capture was asked to solve.
    said : list of (category, str)
        The tiles' warnings, each once; issued again here, with the whole
        capture's low-solved warning.
    seconds : float
        Wall-clock seconds of the whole run.
    """
    first = tiles[0]

    def total(name):
        return sum(getattr(t, name) for t in tiles)

    def counts(name):  # summed dicts, keys in the first tile's order, zeros kept
        out = {}
        for t in tiles:
            for key, value in getattr(t, name).items():
                out[key] = out.get(key, 0) + int(value)
        return out

    def per_lookup(name):
        weight = sum(matched)
        return (sum(getattr(t, name) * n for t, n in zip(tiles, matched)) / weight
                if weight else 0.0)

    groups = Counter()
    for t in tiles:
        for g in t.grids:
            groups[dataclasses.replace(g, pixels=0)] += g.pixels
    grids = tuple(sorted((dataclasses.replace(g, pixels=n) for g, n in groups.items()),
                         key=lambda g: -g.pixels))
    warnings_said = [text for _, text in said]
    for category, text in said:
        warnings.warn(text, category, stacklevel=3)
    message = low_solved_message(maps["reason"], mask, maps["solved"])
    if message:
        warnings_said.append(message)
        warnings.warn(message, LowSolvedWarning, stacklevel=3)
    q = maps["quality"][np.isfinite(maps["quality"])]
    refined = maps["uncertainty"][maps["solved"]]
    timing = Timings(**{f.name: sum(getattr(t.seconds, f.name) or 0.0 for t in tiles)
                        for f in dataclasses.fields(Timings)})
    return dataclasses.replace(
        first, grid_n=next((t.grid_n for t in tiles if t.grid_n), None),
        grids=grids, buckets_per_lookup=per_lookup("buckets_per_lookup"),
        tests_per_lookup=per_lookup("tests_per_lookup"), pixels=total("pixels"),
        solved=total("solved"), solved_from_band_subset=total("solved_from_band_subset"),
        solved_from_light_subset=total("solved_from_light_subset"),
        lights_dropped_per_pixel=counts("lights_dropped_per_pixel"),
        dropped_per_light=[dict(light=i, darker=sum(t.dropped_per_light[i]["darker"]
                                                    for t in tiles),
                                brighter=sum(t.dropped_per_light[i]["brighter"]
                                             for t in tiles))
                           for i in range(first.images)],
        pixels_by_reason=counts("pixels_by_reason"),
        residual_median=_median(q), residual_p95=_percentile(q, 95),
        warnings=tuple(warnings_said), refined=total("refined"),
        uncertainty_median=_median(refined), uncertainty_p95=_percentile(refined, 95),
        seconds=dataclasses.replace(timing, total=seconds, integration=None))


def default_band_names(bands: int) -> list[str]:
    """The names of an albedo's bands when the input's are not known: Y for one,
    R, G, B for three, else B0, B1, ...

    Examples
    --------
    >>> default_band_names(3), default_band_names(2)
    (['R', 'G', 'B'], ['B0', 'B1'])
    """
    return {1: ["Y"], 3: ["R", "G", "B"]}.get(bands, [f"B{k}" for k in range(bands)])


def low_solved_message(reason: np.ndarray, mask: np.ndarray, solved: np.ndarray
                       ) -> str | None:
    """What to warn when under LOW_SOLVED_FRACTION of the mask was solved (else None)."""
    n_masked = int(mask.sum())
    if not (n_masked and 0 < solved.sum() < LOW_SOLVED_FRACTION * n_masked):
        return None
    counts = reason_counts(reason[mask & ~solved])
    worst = max(counts, key=counts.get)
    hint = ("; a background dark under every light is left out by a mask"
            if worst == Reason.TOO_DARK.label else "")
    return (f"only {solved.sum() / n_masked:.0%} of the {n_masked} masked pixels were "
            f"solved (mostly '{worst}': {counts[worst]} pixels{hint})")


def say_low_solved(result: Reconstruction) -> None:
    """Warn (LowSolvedWarning) when under LOW_SOLVED_FRACTION of ``result``'s
    mask (its pixels not labelled background) was solved: once for a run's
    kept result, whose samples, probes and passes would each say their own."""
    message = low_solved_message(result.reason, result.reason != Reason.BACKGROUND,
                                 result.solved)
    if message:
        warnings.warn(message, LowSolvedWarning, stacklevel=2)


def check_solved(result: Reconstruction, scene_paths, gauge_paths, mask_path) -> None:
    """Refuse a run that solved nothing (InputError), saying why: its files, and
    the most common reason of its unsolved pixels."""
    stats = result.stats
    if stats.solved:
        return
    reasons = {k: v for k, v in stats.pixels_by_reason.items() if v and k != "background"}
    if stats.table_size == 0 and gauge_paths:
        raise InputError(f"{gauge_paths[0]}: no gauge pixel has every band usable "
                         "(clipped, too dark or invalid), so nothing can be matched; check "
                         "the gauge images and --sphere")
    worst = max(reasons, key=reasons.get) if reasons else "background"
    where = f"mask {mask_path}" if mask_path else "the scene"
    raise InputError(f"{scene_paths[0]}: no pixel of {where} could be solved (mostly "
                     f"'{worst}': {reasons.get(worst, 0)} pixels); see --dark-level, "
                     "--clip-level and --max-residual")


def _median(values: np.ndarray) -> float | None:
    finite = values[np.isfinite(values)]
    return float(np.median(finite)) if finite.size else None


def _percentile(values: np.ndarray, q: float) -> float | None:
    finite = values[np.isfinite(values)]
    return float(np.percentile(finite, q)) if finite.size else None


def _histogram(counts: np.ndarray) -> dict:
    """{"0": pixels with 0, "1": with 1, ...} of an integer count per pixel."""
    return {str(k): int(v) for k, v in enumerate(np.bincount(counts, minlength=1))}
