"""Files in, files out: the work behind ``colorps reconstruct``.

:func:`reconstruct_files` reads top to bottom, each step a call into its own module: check
the output folder (:mod:`colorps.outputs`), read the headers and plan the run
(:mod:`colorps.io`, :func:`colorps.memory.plan_tiles`), read the scene, resolve the
settings against the files (:func:`colorps.resolve.resolve`), make the gauge (photographed:
:meth:`colorps.Gauge.from_sphere`; rendered: :func:`colorps.virtual.virtual_gauge`), match
(:func:`colorps.reconstruct`, or :func:`colorps.tiles.reconstruct_tiled`), take out the
light a concave object bounces onto itself
(:func:`colorps.interreflection.without_interreflections`; a rendered gauge's finish fitted
again without it), try the gauge's lights when the scene's finish looks another
(:func:`colorps.gauge_finish.with_gauge_lights`; the bounced light then taken out again
with its shape and finish), integrate the height (:func:`colorps.integrate`) while the maps
are written (:func:`colorps.outputs.save_reconstruction`). Option values arrive converted
(:class:`~colorps.Options`); the command line only parses arguments.
"""

from __future__ import annotations

import dataclasses
import sys
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from . import __version__
from ._blas import one_blas_thread
from ._pages import small_pages
from .errors import InputError, LowSolvedWarning
from .falloff_trade import with_falloff_trade
from .figures import overview_step
from .gauge import Gauge, find_sphere, rim_margin
from .gauge_check import (
    as_linear,
    check_gauge,
    check_lights,
    finish_differs,
    finish_may_differ,
    judge_finish,
    lens_hint,
    noisier_scene,
    shows_finish,
    with_lens_bias,
)
from .gauge_finish import with_gauge_lights
from .hygiene import check_contents, check_exposures, check_names, check_stack_exposures
from .inputs import CaptureFiles
from .integrate import DEFAULT_TILE, integrate, weights_from_quality
from .interreflection import (
    PASSES_AGAIN,
    SceneSample,
    left_in,
    moved_by,
    with_bounce_left_in,
    with_scale_uncertainty,
    without_interreflections,
)
from .io import (
    check_stack_files,
    expand_paths,
    read_image,
    read_mask,
    read_stack,
    top_code,
    warn_lossy_stack,
)
from .light_axes import check_axes
from .lights import read_lights
from .memory import (
    TilePlan,
    check_input_size,
    kept_grids_mib,
    plan_tiles,
    release_freed_memory,
)
from .options import Options
from .outputs import TILED_EXR_SIDE, Exports, prepare_output_dir, save_reconstruction
from .pairing import (
    check_natural_order,
    check_shading_pairing,
    light_subspaces,
    pair_lights,
    pairing_record,
    shading_subspaces,
)
from .reconstruct import reconstruct
from .resolve import Resolved, StackModel, resolve
from .results import Reconstruction, RunClock, check_solved, say_low_solved
from .tables import GaugeTables
from .tiles import StackFiles, dask_client, reconstruct_tiled
from .virtual import (
    corrected,
    match_along_rays,
    matched_again,
    virtual_gauge,
    with_own_finish,
)

__all__ = ["reconstruct_files"]


def reconstruct_files(inputs: CaptureFiles, out, *, options: Options | None = None,
                      overwrite: bool = False, progress: bool = True,
                      scheduler=None) -> Reconstruction:
    """Read a capture, reconstruct, and write the output folder.

    Parameters
    ----------
    inputs : CaptureFiles
        The scene images, and the gauge images and sphere or a light file, the
        mask and the gauge's albedo (see :class:`colorps.inputs.CaptureFiles`).
    out : str or Path
        Output folder (see :mod:`colorps.outputs` for the files).
    options : Options, optional
        Settings (default ``Options()``); "auto" levels come from each stack's
        files (see :func:`colorps.resolve.resolve`).
    overwrite : bool, optional
        Replace existing results.
    progress : bool, optional
        Progress bars on reading and matching.
    scheduler : str or dask.distributed.Client, optional
        Run the scene's tiles (``options.tile``, default 256 rows when a
        scheduler is given) on a Dask cluster: a client, a scheduler address,
        or "local" for a local cluster started for this run.

    Returns
    -------
    Reconstruction
        With its height map when ``options.height``.

    Examples
    --------
    >>> import tempfile
    >>> from colorps.inputs import CaptureFiles
    >>> from colorps.pipeline import reconstruct_files
    >>> from colorps.sample import sample_folder
    >>> folder = sample_folder()
    >>> files = CaptureFiles(str(folder / "scene_*.exr"), gauge=str(folder / "gauge_*.exr"),
    ...                      mask=folder / "mask.png")
    >>> with tempfile.TemporaryDirectory() as out:
    ...     result = reconstruct_files(files, out, progress=False)
    >>> bool(result.solved.any()), result.height is not None
    (True, True)
    """
    with one_blas_thread(), small_pages():
        options = options or Options()
        clock = RunClock()
        clock.start("checking")
        prepare_output_dir(out, overwrite=overwrite)  # fail before the long work
        scene_paths = expand_paths(inputs.scene, name="scene")
        check_natural_order(scene_paths, inputs.scene, "scene")
        check_names(scene_paths, "scene")
        stacks = _Stacks(scene_paths, check_stack_files(scene_paths, name="scene"))
        plan = plan_tiles(stacks.shape, tile=options.tile,
                          memory_limit_gib=options.memory_limit_gib, scheduler=scheduler)
        options = options.replace(tile=plan.rows)
        check_input_size(stacks.scene_paths, stacks.scene_infos, options, plan,
                         light_file=inputs.lights is not None)
        stacks = _with_gauge_headers(stacks, inputs, options)
        inputs = inputs.with_exif_camera([*stacks.gauge_infos[:1], *stacks.scene_infos[:1]])
        mask = None
        if inputs.mask is not None:
            mask = read_mask(inputs.mask, stacks.shape[1:3])
            if not mask.any():
                raise InputError(f"{inputs.mask}: the mask selects no pixel (non-zero = solve)")
        clock.start("reading")
        scene, names = _read_scene(stacks, options, plan, progress)
        handed = [scene]
        del scene  # held by ``handed`` alone, so that the reconstruction can free it
        with warnings.catch_warnings():  # each pass says its share: the kept result's below
            warnings.simplefilter("ignore", LowSolvedWarning)
            result, preview, run, gauge, virtual, checked, bounced = _solved(
                handed, inputs, stacks, options, mask, plan, clock, scheduler, progress)
        say_low_solved(result)
        report = _report(inputs, stacks, run, plan, gauge, virtual, names, bounced)
        report["lights_check" if inputs.lights is not None else "gauge_check"] = checked
        report["matched_along_rays"] = plan.rows is None and _view_matters(inputs, virtual)
        report["run_seconds"] = clock  # taken when report.json is written, last
        clock.start("writing")
        result = _save(result, out, run.options, plan, report, names, preview, overwrite, progress)
        seconds = dataclasses.replace(result.stats.seconds, run=clock.as_dict()["total"])
        return dataclasses.replace(result, stats=dataclasses.replace(result.stats, seconds=seconds))


def _solved(handed: list, inputs: CaptureFiles, stacks: _Stacks, options: Options, mask,
            plan: TilePlan, clock: RunClock, scheduler, progress: bool):
    """The gauge (read, or rendered for a light file) and the scene (``handed``'s
    one stack, let go of) solved with it, with every pass the run takes:
    (the result kept, its preview, the run's settings, the gauge, the virtual
    gauge's finish and fits, the gauge or lights check, the bounced light's record)."""
    scene = handed.pop()
    clock.start("gauge")
    run = resolve(options, scene=StackModel.of_file(stacks.scene_infos[0], options.encoding),
                  gauge=None if inputs.lights is not None else
                  StackModel.of_file(stacks.gauge_infos[0], options.encoding))
    gauge, gauge_stack, run, virtual, checked, scene = _make_gauge(inputs, stacks, scene, run,
                                                                   mask, progress)
    clock.start("reconstruct")
    along_rays = plan.rows is None and _view_matters(inputs, virtual)  # (no fit in tiles)
    view = (stacks.light_set, virtual, inputs.camera) if along_rays else None
    tables = _solves_tables(run, stacks.shape)
    sample = SceneSample.of(scene) if plan.rows is None and view is None and \
        run.options.interreflections else None  # the bounced light's first look
    if plan.rows is not None:
        with dask_client(scheduler) as client:
            result, preview = reconstruct_tiled(
                scene, gauge_stack, gauge, run, tile=plan.rows, mask=mask, client=client,
                progress=progress, return_preview=True)
        del scene  # not needed past here: free it for integration and writing
    else:
        handed = [scene]
        del scene  # held by ``handed`` alone, so that the reconstruction can free it
        result, preview = _reconstruct_whole(handed, gauge_stack, gauge, run, mask, view,
                                             progress, tables)
    check_solved(result, stacks.scene_paths, stacks.gauge_paths, inputs.mask)
    checked = _with_axes(checked, result, inputs)
    read_again = None if plan.rows is not None else \
        (lambda: _read_scene(stacks, run.options, plan, progress, True)[0])  # (tiled: none)
    result, solved_from, bounced, moved = _without_interreflections(
        result, read_again, gauge_stack, gauge, run, mask, view, progress, tables, sample)
    del tables, sample  # (the grids, the sample)
    corrected = result
    if virtual is not None and solved_from is not None:  # its finish fitted again
        result, run, virtual = with_own_finish(  # (seen along the axis if along_rays)
            solved_from, stacks.light_set, run, mask=mask, radius=inputs.virtual_radius,
            camera=None if along_rays else inputs.camera, progress=progress)
    lights = stacks.light_set  # (the gauge's, measured, when the finish route is taken)
    if inputs.lights is None and run.options.finish_check and \
            finish_may_differ(result.stats.model_scale, checked):
        if solved_from is None and read_again is not None:  # (a tiled run's: not tried)
            solved_from = read_again()
        result, run, virtual, lights = _with_gauge_lights(
            result, stacks, gauge_stack, gauge, run, mask, inputs, checked, progress,
            solved_from)
        if virtual is not None and bounced.get("passes"):
            result, run, virtual = _bounced_again(result, run, virtual, lights, read_again,
                                                  mask, inputs, progress, bounced)
    if moved is not None and result is not corrected:  # solved again: the scale's radius
        result = with_scale_uncertainty(result, moved)
    del solved_from, corrected, moved
    result = with_bounce_left_in(result, bounced)  # (when no pass took it out)
    result = with_lens_bias(result, gauge, checked)  # a lens read orthographically
    result = with_falloff_trade(result, virtual, lights, inputs.virtual_radius, checked)
    return result, preview, run, gauge, virtual, checked, bounced


@dataclass(frozen=True)
class _Stacks:
    """The files of a capture's stacks and their headers, checked (private)."""

    scene_paths: list
    scene_infos: list
    gauge_paths: list = dataclasses.field(default_factory=list)
    gauge_infos: list = dataclasses.field(default_factory=list)
    light_set: object = None  # Lights, with a light file
    exposures: np.ndarray | None = None

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """(m, H, W, c) of the scene."""
        info = self.scene_infos[0]
        return len(self.scene_paths), info.height, info.width, info.channels


def _with_gauge_headers(stacks: _Stacks, inputs: CaptureFiles, options: Options) -> _Stacks:
    """The scene's stacks with the gauge's headers or the light file, checked
    against the scene's, before any pixel is read."""
    scene_paths, scene_infos = stacks.scene_paths, stacks.scene_infos
    if inputs.lights is not None:
        light_set = read_lights(inputs.lights, inputs.light_intensities,
                                images=len(scene_paths))
        light_set = pair_lights(light_set, scene_paths, inputs.lights)
        bands = light_set.intensities.shape[1]
        if bands not in (1, scene_infos[0].channels):
            source = inputs.light_intensities or inputs.lights
            raise InputError(f"{source}: the intensities have {bands} values per light but "
                             f"{scene_paths[0]} has {scene_infos[0].channels} channel(s); give "
                             "one value or one per channel")
        check_stack_exposures(scene_infos)
        return dataclasses.replace(stacks, light_set=light_set)
    gauge_paths = expand_paths(inputs.gauge, name="gauge")
    check_natural_order(gauge_paths, inputs.gauge, "gauge")
    check_names(gauge_paths, "gauge")
    if len(scene_paths) != len(gauge_paths):
        raise InputError(f"the scene has {len(scene_paths)} images but the gauge "
                         f"{len(gauge_paths)}; they are paired in order")
    gauge_infos = check_stack_files(gauge_paths, name="gauge",
                                    max_bytes=options.max_input_gib * 2 ** 30)
    if gauge_infos[0].channels != scene_infos[0].channels:
        raise InputError(f"{gauge_paths[0]}: has {gauge_infos[0].channels} channel(s) but "
                         f"{scene_paths[0]} has {scene_infos[0].channels}")
    return dataclasses.replace(stacks, gauge_paths=gauge_paths, gauge_infos=gauge_infos,
                               exposures=check_exposures(scene_infos, gauge_infos))


def _read_scene(stacks: _Stacks, options: Options, plan: TilePlan, progress: bool,
                again: bool = False):
    """The scene stack (in its files if tiled), its channel names; ``again``: read before."""
    if plan.rows is None:
        scene, names = read_stack(stacks.scene_paths, options.encoding, name="scene",
                                  progress=progress, warn_lossy=not again)
        if not again:  # (checked, and warned of, on the first read)
            check_contents(scene, stacks.scene_paths, "scene")
        return scene, names
    _m, h, _w, _c = stacks.shape
    if progress:  # a tiled run is slower: say why it is tiled
        from tqdm import tqdm

        tqdm.write(f"colorps: the scene's {h} rows in tiles of {plan.rows} ({plan.why})",
                   file=sys.stderr)
    warn_lossy_stack(stacks.scene_infos, "scene")
    scene = StackFiles(tuple(stacks.scene_paths), stacks.shape, options.encoding)
    return scene, read_image(stacks.scene_paths[0], options.encoding, rows=(0, 1),
                             warn_lossy=False)[1]


def _reconstruct_whole(handed: list, gauge_stack, gauge: Gauge, run: Resolved, mask, view,
                       progress: bool, tables: GaugeTables) -> tuple[Reconstruction, np.ndarray]:
    """Reconstruct the scene stack ``handed`` holds (its only reference) untiled;
    the result and the overview's preview of the scene.

    Without ``view`` the stack goes to :func:`reconstruct` as its only
    reference, which lets it go once it has the observation vectors. With it
    (the light file's lights, the virtual gauge's finish and fits, the camera:
    a finish that has the scene matched again) the scene is matched once more,
    corrected (:func:`virtual.match_along_rays`)."""
    step = overview_step(handed[0].shape[1:3])
    if view is None:
        preview = handed[0][:, ::step, ::step].mean(axis=0)  # what the overview draws
        return reconstruct(handed.pop(), gauge_stack, gauge, run, mask=mask,
                           progress=progress, tables=tables), preview
    light_set, virtual, camera = view
    result, scene = match_along_rays(handed.pop(), gauge, run, light_set, virtual[0], camera,
                                     mask=mask, progress=progress)
    return result, scene[:, ::step, ::step].mean(axis=0)


#: Why a run matched again under its finish keeps the light it bounces onto itself.
_MATCHED_AGAIN = "a run matched again under its finish (its white highlight out, or along " \
    "the camera's rays)"


def _view_matters(inputs: CaptureFiles, virtual) -> bool:
    """A virtual gauge whose fitted finish has the scene matched again
    (:func:`virtual.matched_again`)."""
    return virtual is not None and matched_again(virtual[0], inputs.camera)


def _make_gauge(inputs: CaptureFiles, stacks: _Stacks, scene, run: Resolved, mask,
                progress: bool):
    """(gauge, its stack, the settings with it, the virtual gauge's finish and fits or
    None, the images' check, the scene): photographed, or rendered under the light
    file. The check may find that integer files fit far better read as linear;
    under --encoding auto the scene and gauge are then read so (the settings and
    the scene returned are those)."""
    encoding = run.options.encoding
    if stacks.light_set is not None:
        checked = None
        if isinstance(scene, np.ndarray):  # (a tiled run's scene stays in its files)
            checked = check_lights(scene, stacks.light_set, mask, stacks.scene_paths[0],
                                   encoding, top_code(stacks.scene_infos[0]))
            if checked["decoded_as"]:
                scene, run = _read_as_linear(scene, stacks, run)
            checked["pairing"] = check_shading_pairing(
                scene, mask, light_subspaces(stacks.light_set, scene.shape[-1]),
                inputs.lights, "the light file")
        gauge, run, brdf, fits = virtual_gauge(scene, stacks.light_set, run, mask=mask,
                                               radius=inputs.virtual_radius,
                                               progress=progress, camera=inputs.camera)
        return gauge, gauge.stack, run, (brdf, fits), checked, scene
    gauge_stack, _ = read_stack(stacks.gauge_paths, encoding, name="gauge", progress=progress)
    check_contents(gauge_stack, stacks.gauge_paths, "gauge")
    if inputs.sphere == "auto":  # in the scene's own frame: looked for outside the object
        same_frame = list(stacks.gauge_paths) == list(stacks.scene_paths)
        sphere = find_sphere(gauge_stack, inputs.camera,
                             exclude=mask if same_frame else None)
    else:
        sphere = tuple(inputs.sphere)

    def photographed(images):  # its rim margin measured on the images as read
        return Gauge.from_sphere(images.shape[1:3], *sphere, albedo=inputs.gauge_albedo,
                                 camera=inputs.camera,
                                 rim_margin=rim_margin(images, sphere, inputs.camera))

    gauge = photographed(gauge_stack)
    checked = check_gauge(gauge_stack, gauge, stacks.gauge_paths[0], encoding,
                          top_code(stacks.gauge_infos[0]))
    if inputs.camera is None:  # read orthographically: does it shade as through a lens?
        checked["lens_fit"] = lens_hint(gauge_stack, gauge, stacks.gauge_paths[0])
    if checked["decoded_as"]:
        gauge_stack = as_linear(gauge_stack, stacks.gauge_paths, stacks.gauge_infos[0], "gauge")
        gauge = photographed(gauge_stack)
        scene, run = _read_as_linear(scene, stacks, run)
    if isinstance(scene, np.ndarray):  # (a tiled run's scene stays in its files)
        checked["pairing"] = check_shading_pairing(
            scene, mask, shading_subspaces(gauge_stack, gauge.mask)[0], stacks.gauge_paths[0],
            "the gauge")
    return gauge, gauge_stack, run, None, checked, scene


def _with_axes(checked: dict | None, result: Reconstruction, inputs: CaptureFiles):
    """The lights check of a run with a light file, with whether its axes look
    mirrored, swapped or turned (:func:`light_axes.check_axes`, on the first solve's
    normals)."""
    if inputs.lights is None:
        return checked
    return {**(checked or {}), "axes": check_axes(result.normals, result.solved, inputs.lights)}


def _read_as_linear(scene, stacks: _Stacks, run: Resolved):
    """The scene and settings of a run whose integer files, read as sRGB, are linear."""
    options = run.requested.replace(encoding="linear")  # levels still "auto" if asked
    if isinstance(scene, StackFiles):
        scene = StackFiles(scene.paths, scene.shape, "linear")
    elif top_code(stacks.scene_infos[0]) is not None:
        scene = as_linear(scene, stacks.scene_paths, stacks.scene_infos[0], "scene")
    return scene, resolve(options, scene=StackModel.of_file(stacks.scene_infos[0], "linear"),
                          gauge=None if stacks.light_set is not None else
                          StackModel.of_file(stacks.gauge_infos[0], "linear"))


def _report(inputs: CaptureFiles, stacks: _Stacks, run: Resolved, plan: TilePlan,
            gauge: Gauge, virtual, names, interreflections: dict) -> dict:
    """What report.json says of the run's inputs, settings and bounced light."""
    brdf, fits = virtual if virtual is not None else (None, None)
    clip, dark = run.gauge_levels
    return dict(
        colorps_version=__version__, scene=[str(p) for p in stacks.scene_paths],
        gauge=[str(p) for p in stacks.gauge_paths],
        sphere=dict(zip(("cx", "cy", "r", "rim_margin"), (*gauge.sphere, gauge.rim_margin))),
        sphere_found_automatically=inputs.sphere == "auto",
        camera=None if inputs.camera is None else inputs.camera.as_dict(),
        lights=None if inputs.lights is None else str(inputs.lights),
        light_intensities=(None if inputs.light_intensities is None
                           else str(inputs.light_intensities)),
        virtual_gauge=inputs.lights is not None, gauge_albedo=inputs.gauge_albedo,
        brdf=None if brdf is None else brdf.as_dict(), brdf_fits=fits,
        mask=None if inputs.mask is None else str(inputs.mask), channels=names,
        options=run.options.as_dict(), memory_limit_gib_used=plan.limit_gib,
        tiled_because=plan.why,
        exposure_scene_over_gauge=None if stacks.exposures is None else stacks.exposures.tolist(),
        gauge_levels=dict(clip_level=clip, dark_level=dark), interreflections=interreflections,
        pairing=pairing_record(stacks.scene_paths, stacks.gauge_paths, stacks.light_set))


def _save(result: Reconstruction, out, options: Options, plan: TilePlan, report: dict,
          names, preview, overwrite: bool, progress: bool) -> Reconstruction:
    """Integrate the height and write every output file; the result with its height.

    A tiled run integrates first, in tiles (memory is what counts); an untiled
    run integrates in a thread while the maps are written (the solver and
    OpenImageIO's writers release the GIL): the two overlap."""
    tiled = plan.rows is not None
    release_freed_memory()  # the reconstruction's temporaries, before the writers'

    def with_height(result: Reconstruction) -> Reconstruction:
        t0 = time.perf_counter()
        height = integrate(result.normals, result.solved,
                           weights=weights_from_quality(result.quality),
                           tile=DEFAULT_TILE if tiled else None)
        if tiled:
            release_freed_memory()
        return result.with_height(height, time.perf_counter() - t0)

    if options.height and tiled:
        result = with_height(result)
    with ThreadPoolExecutor(max_workers=1) as pool:
        finished = pool.submit(with_height, result) \
            if options.height and result.height is None else None
        exports = Exports(mesh=options.mesh_kinds, normal_convention=options.normal_convention,
                          viewer=options.viewer, exr_tile=TILED_EXR_SIDE if tiled else None)
        save_reconstruction(result, out, channel_names=names, scene_preview=preview,
                            report=report, exports=exports, overwrite=overwrite,
                            finished=finished, progress=progress)
    return result if finished is None else finished.result()


def _solves_tables(run: Resolved, shape: tuple[int, int, int, int]) -> GaugeTables:
    """The gauge's side and grids for every untiled solve of a run: its grids kept
    within the memory model (:func:`memory.kept_grids_mib`) when the bounced
    light's passes may match with them again (a 612 x 512 capture under 32
    lights: 25 -> 21 s), else none."""
    return GaugeTables(kept_grids_mib(run.options.memory_limit_gib, shape)
                       if run.options.interreflections else 0)


def _without_interreflections(result, read_again, gauge_stack, gauge: Gauge, run: Resolved,
                              mask, view, progress: bool, tables: GaugeTables,
                              sample: SceneSample | None):
    """The result solved again without the light a concave object bounces onto itself
    (:func:`interreflection.without_interreflections`, the scene read again, by
    ``read_again()``, only then; None: a tiled run's, left in), the measurements
    it was solved from (None: as read), report.json's record,
    and how far taking it out moved each normal (:func:`interreflection.moved_by`;
    None: not taken out), for a result solved again from those measurements.
    ``view``: None, or (lights, finish and fits, camera) of a run matched again
    under its finish (:func:`virtual.matched_again`), whose scene is read as
    that match saw it (:func:`virtual.corrected`, at ``result``'s normals).
    ``sample``: of the scene as read, looked at before it is read again."""
    if not run.options.interreflections:
        return result, None, dict(skipped="--no-interreflections"), None
    if read_again is None:
        return result, None, left_in(
            result, "a tiled run", " (untiled, without --tile and with enough "
            "--memory-limit, that light is taken out)"), None

    def read_scene():
        scene = read_again()
        if view is None:
            return scene
        lights, virtual, camera = view
        return corrected(scene, result, lights, virtual[0], camera, run)

    corrected_result, solved_from, record = without_interreflections(
        read_scene, result, _solve_with(gauge_stack, gauge, run, mask, progress, tables), gauge,
        gauge_stack, sample=sample, progress=progress)
    return corrected_result, solved_from, record, \
        None if solved_from is None else moved_by(corrected_result, result)


def _solve_with(gauge_stack, gauge: Gauge, run: Resolved, mask, progress: bool,
                tables: GaugeTables):
    """The run's solve against ``gauge`` as :func:`interreflection.without_interreflections`
    calls it: ``solve(stack, pixels, model_scale)``, ``pixels`` None for ``mask``; the
    gauge's side and grids kept in ``tables`` for every solve."""
    return lambda stack, pixels, scale: reconstruct(
        stack, gauge_stack, gauge, run, model_scale=scale, progress=progress,
        mask=mask if pixels is None else pixels, tables=tables)


def _with_gauge_lights(result, stacks: _Stacks, gauge_stack, gauge: Gauge, run: Resolved,
                       mask, inputs: CaptureFiles, checked: dict, progress: bool, scene):
    """A run whose gauge explains its scene poorly, solved again with the gauge's lights
    and the scene's own finish (:func:`gauge_finish.with_gauge_lights`; a scene noisier
    than its gauge, or matched only a little worse, matched with it only when that
    :func:`gauge_check.shows_finish`), kept as :func:`gauge_check.judge_finish` says
    (recorded in ``checked``). ``scene``: what ``result`` was solved from (None: a tiled
    run's, not tried). Returns (result, settings, finish and fits or None, lights or None)."""
    noisier = scene is not None and noisier_scene(scene, mask, result.stats, checked)
    asked = not finish_differs(result.stats.model_scale, checked)  # its finish asked first
    record = checked["finish"] = dict(
        residual_with_gauge=result.stats.residual_median_noise_units,
        residual_with_gauge_lights=None, brdf=None, asked_first=asked)
    try:  # the gauge's lights may not be measurable (a small or one-sided sphere)
        if scene is not None:
            other, other_run, finish, lights, own = with_gauge_lights(
                scene, gauge_stack, gauge, run, mask=mask, radius=inputs.virtual_radius,
                camera=inputs.camera, progress=progress,
                wanted=shows_finish if noisier or asked else None)
            record.update(brdf=finish[0].as_dict(), gauge_brdf=own.as_dict())
            if other is not None:
                record["residual_with_gauge_lights"] = other.stats.residual_median_noise_units
    except InputError as error:
        record["failed"] = str(error)
    if asked and not noisier and record["residual_with_gauge_lights"] is None:
        record["taken"] = False  # its finish is the gauge's, or not tried: nothing to say
    elif judge_finish(record, stacks.scene_paths[0] if noisier else stacks.gauge_paths[0],
                      noisier=checked["scene_noise_over_gauge"] if noisier else None,
                      finish=finish[0] if record["brdf"] else None,
                      gauge_finish=own if record["brdf"] else None):
        return other, other_run, finish, lights
    return result, run, None, None


def _bounced_again(result, run: Resolved, finish, lights, read_scene, mask,
                   inputs: CaptureFiles, progress: bool, bounced: dict):
    """The gauge's lights' result (``finish``: the scene's own) solved again, the bounced
    light estimated from its shape (another finish's normals had given it another),
    scaled against that finish, taken out of the measurements as read (``read_scene()``),
    the finish fitted again (:func:`virtual.with_own_finish`); kept when it explains the
    scene at least as well. Returns (result, settings, finish and its fits); its record
    is ``bounced``'s ``with_scene_finish``."""
    if _view_matters(inputs, finish):
        bounced["with_scene_finish"] = dict(skipped=_MATCHED_AGAIN)
        return result, run, finish
    virtual = Gauge.virtual(lights, radius=inputs.virtual_radius, bands=result.albedo.shape[-1],
                            brdf=finish[0])
    tables = GaugeTables(kept_grids_mib(run.options.memory_limit_gib,
                                        (len(virtual.stack), *result.albedo.shape)))
    _, corrected, record = without_interreflections(
        read_scene, result, _solve_with(virtual.stack, virtual, run, mask, progress, tables),
        virtual, virtual.stack, passes=PASSES_AGAIN, solved_as_read=False, progress=progress)
    bounced["with_scene_finish"] = record
    if corrected is None:
        return result, run, finish
    try:
        again = with_own_finish(corrected, lights, run, mask=mask, radius=inputs.virtual_radius,
                                camera=inputs.camera, progress=progress,
                                held_finish=finish[0])
    except InputError as error:  # (a finish fit short of lit measurements)
        record.update(kept=False, failed=str(error))
        return result, run, finish
    del corrected
    record["kept"] = bool(again[0].stats.residual_median_noise_units
                          <= result.stats.residual_median_noise_units)
    return again if record["kept"] else (result, run, finish)
