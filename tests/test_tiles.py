"""Tiled and Dask runs give the maps of one untiled run."""

import json

import numpy as np
import pytest

from colorps import Gauge, reconstruct, synth
from colorps.errors import InputError
from colorps.io import read_image, write_image
from colorps.memory import tile_rows
from colorps.tiles import StackFiles, reconstruct_tiled

MAPS = ("normals", "albedo", "quality", "uncertainty", "solved", "reason", "bands_used",
        "dropped_lights")


@pytest.fixture(scope="module")
def messy():
    """Oren-Nayar scene against a Lambertian gauge (model scale > 1), noise, cast
    shadows, a highlight and clipped colours: every step of a run has work."""
    hue = 0.5 + 0.5 * np.cos(2 * np.pi * np.arange(8)[:, None] / 8 - [0.0, 2.1, 4.2])
    lights = synth.ring_lights(8, 55, 0.2 + 0.8 * hue)
    surface = synth.smiley_surface(72, relief=0.2)
    scene = synth.render(surface, lights, brdf="oren-nayar", noise=0.004, seed=1,
                         cast_shadows=True, gloss=0.4)
    scene = np.minimum(scene * 1.6, 1.0)  # saturated colours clip in some images
    ball = synth.sphere_surface(91, 42)
    gauge_stack = synth.render(ball, lights, noise=0.004, seed=2)
    gauge = Gauge.from_sphere((91, 91), 45, 45, 42)
    mask = surface.mask.copy()
    mask[30:34, :] = False  # a tile border inside and outside the mask
    return scene.astype(np.float32), gauge_stack, gauge, mask


def assert_same(whole, tiled):
    for name in MAPS:
        assert np.array_equal(getattr(whole, name), getattr(tiled, name), equal_nan=True), name
    for name in ("solved", "pixels", "model_scale", "pixels_by_reason",
                 "solved_from_light_subset", "lights_dropped_per_pixel", "dropped_per_light",
                 "residual_median", "refined", "uncertainty_median"):
        assert getattr(whole.stats, name) == getattr(tiled.stats, name), name


def test_tiles_give_the_untiled_maps_and_statistics(messy):
    scene, gauge_stack, gauge, mask = messy
    whole = reconstruct(scene, gauge_stack, gauge, mask=mask)
    assert whole.stats.model_scale > 1.05  # a shared scale matters here
    assert whole.stats.solved_from_light_subset > 0
    assert (whole.reason[mask] != 0).any()  # some pixels unsolved, with reasons
    for tile in (7, 30, 200):
        assert_same(whole, reconstruct_tiled(scene, gauge_stack, gauge, tile=tile, mask=mask))


def test_model_scale_from_a_lattice_of_pixels_tiled_or_not(messy, monkeypatch):
    """The scale is measured on every s-th row and column (s = 2 here): the same
    pixels, so the same scale and maps, whether or not the scene is tiled."""
    import sys

    from colorps.matching import measured_model_scale, model_scale_pixels
    from colorps.reconstruct import first_residuals

    matching = sys.modules["colorps.matching"]
    scene, gauge_stack, gauge, mask = messy
    monkeypatch.setattr(matching, "MODEL_SCALE_PIXELS", mask.sum() // 5)  # step 2
    picked = model_scale_pixels(mask)
    assert picked.sum() < mask.sum() / 3 and not picked[1::2].any()
    assert np.array_equal(model_scale_pixels(mask[7:], step=2, first_row=7), picked[7:])
    whole = reconstruct(scene, gauge_stack, gauge, mask=mask)
    first = first_residuals(scene, gauge_stack, gauge, mask=picked)
    assert whole.stats.model_scale == measured_model_scale(first)
    for tile in (7, 30):
        assert_same(whole, reconstruct_tiled(scene, gauge_stack, gauge, tile=tile, mask=mask))


def test_gauge_tables_build_each_grid_once_for_all_tiles(messy):
    import pickle

    from colorps.tables import GaugeTables

    scene, gauge_stack, gauge, mask = messy
    whole = reconstruct(scene, gauge_stack, gauge, mask=mask)
    tables = GaugeTables()
    pieces = [reconstruct(scene[:, a:b], gauge_stack, gauge, mask=mask[a:b],
                          model_scale=whole.stats.model_scale, tables=tables)
              for a, b in tile_rows(72, 24)]
    assert tables.reused > 0 and 0 < tables.bytes <= tables.max_bytes
    alone = [reconstruct(scene[:, a:b], gauge_stack, gauge, mask=mask[a:b],
                         model_scale=whole.stats.model_scale) for a, b in tile_rows(72, 24)]
    for kept, built in zip(pieces, alone):  # the same matches either way
        assert np.array_equal(kept.normals, built.normals, equal_nan=True)
    # Another gauge (here: the same sphere, other lights) is refused, by name.
    with pytest.raises(InputError, match="another gauge"):
        reconstruct(scene, gauge_stack[::-1], gauge, mask=mask, tables=tables)
    # Sent to a Dask worker it travels empty, keeping its fingerprint.
    copy = pickle.loads(pickle.dumps(tables))
    assert copy.bytes == 0 and copy.max_bytes == tables.max_bytes
    with pytest.raises(InputError, match="another gauge"):
        reconstruct(scene, gauge_stack[::-1], gauge, mask=mask, tables=copy)


def test_gauge_tables_prepare_the_gauge_once_for_every_solve(messy, monkeypatch):
    """Solves sharing one GaugeTables (the bounced light's passes) fit the gauge's
    noise and refinement models once, and give the maps each solve gives alone."""
    import sys

    from colorps.tables import GaugeTables

    module = sys.modules["colorps.reconstruct"]
    calls = []
    for name in ("estimate_noise", "quadratic_models"):
        def counted(*args, _original=getattr(module, name), _name=name, **kwargs):
            calls.append(_name)
            return _original(*args, **kwargs)
        monkeypatch.setattr(module, name, counted)
    scene, gauge_stack, gauge, mask = messy
    tables = GaugeTables()
    solves = [reconstruct(stack, gauge_stack, gauge, mask=mask, tables=tables)
              for stack in (scene, scene * np.float32(0.9))]
    assert sorted(calls) == ["estimate_noise", "quadratic_models"]
    for stack, kept in zip((scene, scene * np.float32(0.9)), solves):
        alone = reconstruct(stack, gauge_stack, gauge, mask=mask)
        for field in ("normals", "albedo", "quality", "uncertainty"):
            assert np.array_equal(getattr(kept, field), getattr(alone, field), equal_nan=True)
    # Another gauge stack is prepared again (and here refused: other lights).
    calls.clear()
    with pytest.raises(InputError, match="another gauge"):
        reconstruct(scene, np.ascontiguousarray(gauge_stack[::-1]), gauge, mask=mask,
                    tables=tables)
    assert calls == ["estimate_noise"]


def test_kept_grids_grow_with_the_memory_left():
    from colorps.memory import KEPT_GRIDS_SHARE, TABLE_CACHE_MIB, kept_grids_mib

    shape = (32, 512, 612, 3)
    assert kept_grids_mib(0.5, shape) == TABLE_CACHE_MIB  # nothing left: the tiles' cache
    more = kept_grids_mib(16.0, shape) - kept_grids_mib(8.0, shape)
    assert more == pytest.approx(KEPT_GRIDS_SHARE * 8 * 1024)
    assert kept_grids_mib(16.0, shape) > kept_grids_mib(16.0, (96, 512, 612, 3))


def test_each_tile_alone_would_scale_differently(messy):
    """Without the shared model scale, tiles would not reproduce the whole run."""
    scene, gauge_stack, gauge, mask = messy
    whole = reconstruct(scene, gauge_stack, gauge, mask=mask)
    top = reconstruct(scene[:, :20], gauge_stack, gauge, mask=mask[:20])
    assert top.stats.model_scale != whole.stats.model_scale


def test_tiles_read_from_files(messy, tmp_path):
    scene, gauge_stack, gauge, mask = messy
    paths = [write_image(tmp_path / f"s{k}.exr", image) for k, image in enumerate(scene)]
    files = StackFiles(tuple(paths), scene.shape)
    assert np.array_equal(files[:, 10:25], scene[:, 10:25])
    whole = reconstruct(scene, gauge_stack, gauge, mask=mask)
    tiled, preview = reconstruct_tiled(files, gauge_stack, gauge, tile=25, mask=mask,
                                       return_preview=True)
    assert_same(whole, tiled)
    np.testing.assert_allclose(preview, scene.mean(axis=0), rtol=1e-6, atol=1e-7)


def test_tiled_preview_is_the_mean_at_the_pixels_the_overview_draws(messy, monkeypatch):
    import colorps.figures as figures

    scene, gauge_stack, gauge, mask = messy
    monkeypatch.setattr(figures, "OVERVIEW_SIDE", 20)  # every 4th row and column
    assert figures.overview_step(scene.shape[1:3]) == 4
    _, preview = reconstruct_tiled(scene, gauge_stack, gauge, tile=25, mask=mask,
                                   return_preview=True)  # tiles start off the lattice
    np.testing.assert_allclose(preview, scene[:, ::4, ::4].mean(axis=0), rtol=1e-6,
                               atol=1e-7)


def test_tile_arguments_are_checked(messy):
    scene, gauge_stack, gauge, mask = messy
    assert tile_rows(10, 4) == [(0, 4), (4, 8), (8, 10)]
    with pytest.raises(InputError, match="tile"):
        reconstruct_tiled(scene, gauge_stack, gauge, tile=0)
    with pytest.raises(InputError, match="mask"):
        reconstruct_tiled(scene, gauge_stack, gauge, mask=mask[1:])


@pytest.mark.slow
def test_dask_local_cluster_gives_the_untiled_maps(messy, tmp_path):
    distributed = pytest.importorskip("dask.distributed")  # in the test extra
    scene, gauge_stack, gauge, mask = messy
    whole = reconstruct(scene, gauge_stack, gauge, mask=mask)
    paths = [write_image(tmp_path / f"s{k}.exr", image) for k, image in enumerate(scene)]
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        in_memory = reconstruct_tiled(scene, gauge_stack, gauge, tile=20, mask=mask,
                                      client=client)
        from_files = reconstruct_tiled(StackFiles(tuple(paths), scene.shape), gauge_stack,
                                       gauge, tile=20, mask=mask, client=client)
        assert len(client.scheduler_info()["workers"]) == 2
        # --memory-limit auto inside a worker: no more than the worker's own limit.
        from colorps.memory import available_memory_bytes

        worker_limit = min(w["memory_limit"] for w in client.scheduler_info()["workers"].values())
        assert 0 < client.submit(available_memory_bytes, pure=False).result() <= worker_limit
    assert_same(whole, in_memory)
    assert_same(whole, from_files)


def exr_tile_side(path) -> int:
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    side = inp.spec().tile_width
    inp.close()
    return side


def test_reconstruct_files_tiled_writes_the_untiled_results(messy, tmp_path):
    from colorps import Options
    from colorps.io import read_image
    from colorps.outputs import TILED_EXR_SIDE
    from colorps.inputs import CaptureFiles
    from colorps.pipeline import reconstruct_files

    scene, gauge_stack, gauge, mask = messy
    for k in range(len(scene)):
        write_image(tmp_path / f"scene_{k}.exr", scene[k])
        write_image(tmp_path / f"gauge_{k}.exr", gauge_stack[k])
    write_image(tmp_path / "mask.png", mask.astype(np.float32), dtype="uint8")
    files = CaptureFiles(str(tmp_path / "scene_*.exr"), gauge=str(tmp_path / "gauge_*.exr"),
                         sphere=(45, 45, 42), mask=tmp_path / "mask.png")
    # (An Oren-Nayar scene against its Lambertian gauge: a whole run would solve it
    # again through the gauge's lights, and without the light its relief bounces,
    # which a tiled run leaves to the user.)
    alike = dict(finish_check=False, interreflections=False)
    reconstruct_files(files, tmp_path / "whole", options=Options(**alike), progress=False)
    reconstruct_files(files, tmp_path / "tiled", options=Options(tile=16, **alike),
                      progress=False)
    for name in ("normal", "albedo", "quality", "uncertainty", "height", "lights"):
        whole = read_image(tmp_path / "whole" / f"{name}.exr")[0]
        tiled = read_image(tmp_path / "tiled" / f"{name}.exr")[0]
        assert np.array_equal(whole, tiled, equal_nan=True), name
        # The tiled run's maps are tiled files, the plain run's scanline files.
        assert exr_tile_side(tmp_path / "tiled" / f"{name}.exr") == TILED_EXR_SIDE, name
        assert exr_tile_side(tmp_path / "whole" / f"{name}.exr") == 0, name
    with pytest.raises(InputError, match="--tile"):
        reconstruct_files(files, tmp_path / "huge", options=Options(tile=16, max_input_gib=1e-6),
                          progress=False)


def test_memory_limit_chooses_the_tile_rows():
    from colorps.tables import TABLE_CACHE_MIB
    from colorps.memory import (BASE_MIB, MAP_BYTES, MIN_TILE_ROWS, TILE_FIXED_MIB,
                               WORKING_BYTES, rows_for_memory)

    shape = (8, 4096, 4096, 3)
    assert rows_for_memory(64.0, shape) is None  # fits whole
    rows = rows_for_memory(2.0, shape)  # 16 MP under 2 GiB: in tiles
    row_bytes = WORKING_BYTES * 4 * 8 * 3 * 4096
    fixed = (BASE_MIB + TILE_FIXED_MIB + TABLE_CACHE_MIB) * 2 ** 20 + MAP_BYTES * 4096 * 4096
    assert MIN_TILE_ROWS <= rows < 4096
    assert fixed + rows * row_bytes <= 2 * 2 ** 30 < fixed + (rows + 1) * row_bytes
    assert rows_for_memory(2.5, shape) > rows
    with pytest.raises(InputError, match="needs about .* GiB even in tiles of 16 rows"):
        rows_for_memory(1.0, shape)


def test_memory_limit_on_the_command_line(tmp_path, capsys):
    from colorps.cli import main

    data = tmp_path / "capture"
    synth.write_synthetic(data, size=48, images=6, noise=0.002)
    args = ["reconstruct", "--scene", str(data / "scene_*.exr"), "--gauge",
            str(data / "gauge_*.exr"), "--sphere", "auto", "--quiet"]
    assert main(args + ["--out", str(tmp_path / "small"), "--memory-limit", "0.1"]) == 1
    assert "--memory-limit 0.1 GiB" in capsys.readouterr().err
    assert not (tmp_path / "small").exists()
    assert main(args + ["--out", str(tmp_path / "ok"), "--memory-limit", "4"]) == 0
    report = json.loads((tmp_path / "ok" / "report.json").read_text())
    assert report["options"]["memory_limit_gib"] == 4 and report["options"]["tile"] is None
    # A limit just above 20 rows' worth tiles the run, with the untiled maps.
    from colorps.tables import TABLE_CACHE_MIB
    from colorps.memory import BASE_MIB, MAP_BYTES, TILE_FIXED_MIB, WORKING_BYTES

    limit = ((BASE_MIB + TILE_FIXED_MIB + TABLE_CACHE_MIB) * 2 ** 20 + MAP_BYTES * 48 * 48
             + 20.5 * WORKING_BYTES * 4 * 6 * 3 * 48) / 2 ** 30
    assert main(args + ["--out", str(tmp_path / "tiled"), "--memory-limit", repr(limit)]) == 0
    report = json.loads((tmp_path / "tiled" / "report.json").read_text())
    assert report["options"]["tile"] == 20
    assert np.array_equal(read_image(tmp_path / "tiled" / "normal.exr")[0],
                          read_image(tmp_path / "ok" / "normal.exr")[0], equal_nan=True)


def test_memory_limit_auto_tiles_a_capture_larger_than_the_memory(tmp_path, capsys,
                                                                   monkeypatch):
    import psutil

    import colorps.memory
    from colorps.cli import main
    from colorps.tables import TABLE_CACHE_MIB
    from colorps.memory import AUTO_MEMORY_FRACTION
    from colorps.memory import (BASE_MIB, MAP_BYTES, TILE_FIXED_MIB, WORKING_BYTES,
                               available_memory_bytes)

    assert 0 < available_memory_bytes() <= psutil.virtual_memory().total
    data = tmp_path / "capture"
    synth.write_synthetic(data, size=48, images=6, noise=0.002)
    args = ["reconstruct", "--scene", str(data / "scene_*.exr"), "--gauge",
            str(data / "gauge_*.exr"), "--sphere", "auto", "--quiet", "--no-height"]
    assert main(args + ["--out", str(tmp_path / "whole"), "--memory-limit", "none"]) == 0
    report = json.loads((tmp_path / "whole" / "report.json").read_text())
    assert report["options"]["tile"] is None and report["memory_limit_gib_used"] is None
    assert report["tiled_because"] is None
    # A machine with memory for 20 rows of this capture (the default is "auto").
    limit = ((BASE_MIB + TILE_FIXED_MIB + TABLE_CACHE_MIB) * 2 ** 20 + MAP_BYTES * 48 * 48
             + 20.5 * WORKING_BYTES * 4 * 6 * 3 * 48)
    monkeypatch.setattr(colorps.memory, "available_memory_bytes",
                        lambda: limit / AUTO_MEMORY_FRACTION)
    capsys.readouterr()
    loud = [a for a in args if a != "--quiet"]
    assert main(loud + ["--out", str(tmp_path / "auto")]) == 0
    report = json.loads((tmp_path / "auto" / "report.json").read_text())
    assert report["options"]["memory_limit_gib"] == "auto"
    assert report["options"]["tile"] == 20
    why = report["tiled_because"]
    assert why.startswith("--memory-limit auto (") and why.endswith(
        "is too small for the whole scene")
    assert f"colorps: the scene's 48 rows in tiles of 20 ({why})" in capsys.readouterr().err
    assert report["memory_limit_gib_used"] == pytest.approx(limit / 2 ** 30)
    for name in ("normal", "albedo"):
        assert np.array_equal(read_image(tmp_path / "auto" / f"{name}.exr")[0],
                              read_image(tmp_path / "whole" / f"{name}.exr")[0], equal_nan=True)
    # A machine too small even for 16-row tiles: refused before any output, saying why.
    monkeypatch.setattr(colorps.memory, "available_memory_bytes", lambda: 2 ** 28)
    assert main(args + ["--out", str(tmp_path / "small")]) == 1
    err = capsys.readouterr().err
    assert "--memory-limit auto (0.2 GiB: 80% of the 0.2 GiB available)" in err
    assert "needs about" in err
    assert not (tmp_path / "small").exists()


def _cgroup(folder, **files):
    folder.mkdir(parents=True, exist_ok=True)
    for name, text in files.items():
        (folder / name.replace("_", ".", 1)).write_text(text)


def test_cgroup_limits_bound_the_available_memory(tmp_path, monkeypatch):
    """A container's or cluster job's memory limit counts, at any level of its
    cgroup tree, in cgroup v2 and v1 alike; no limit leaves psutil's figure."""
    import colorps.memory
    from colorps.memory import available_memory_bytes, cgroup_available_bytes

    gib = 2 ** 30
    # v2, a SLURM-like nested job: the limit is set on the job, the step has none.
    v2 = tmp_path / "v2"
    _cgroup(v2, memory_max="max", memory_current=str(9 * gib), memory_stat="anon 1\n")
    _cgroup(v2 / "job_7", memory_max=str(4 * gib), memory_current=str(gib),
            memory_stat=f"anon {gib}\nfile {gib // 2 + 5}\nshmem 5\n")
    _cgroup(v2 / "job_7" / "step_0", memory_max="max", memory_current=str(gib),
            memory_stat="file 0\n")
    assert cgroup_available_bytes(v2, "0::/job_7/step_0\n") == 3.5 * gib
    # v1 (memory controller in its own hierarchy); the root's "unlimited" is no limit.
    v1 = tmp_path / "v1"
    _cgroup(v1 / "memory", memory_limit_in_bytes="9223372036854771712",
            memory_usage_in_bytes=str(gib), memory_stat="total_cache 0\n")
    _cgroup(v1 / "memory" / "docker" / "abc", memory_limit_in_bytes=str(2 * gib),
            memory_usage_in_bytes=str(3 * gib // 2),
            memory_stat=f"cache 9\ntotal_cache {gib // 2}\ntotal_shmem {gib // 4}\n")
    membership = "9:pids:/docker/abc\n4:memory:/docker/abc\n1:cpu:/\n"
    assert cgroup_available_bytes(v1, membership) == 0.75 * gib
    # Inside the container the host's path is not there: its own root is the group.
    inside = tmp_path / "inside"
    _cgroup(inside, memory_max=str(gib), memory_current=str(gib // 4),
            memory_stat="file 0\n")
    assert cgroup_available_bytes(inside, "0::/docker/abc\n") == 0.75 * gib
    # No limit anywhere, no cgroup files, unreadable values: no cgroup figure.
    assert cgroup_available_bytes(v2, "0::/\n") is None
    assert cgroup_available_bytes(tmp_path / "none", "0::/x\n4:memory:/x\n") is None
    _cgroup(inside, memory_current="garbage")
    assert cgroup_available_bytes(inside, "0::/\n") is None
    # The least of psutil's and the cgroups' figure is what "auto" plans with.
    monkeypatch.setattr(colorps.memory, "cgroup_available_bytes", lambda: 2 ** 20)
    assert available_memory_bytes() == 2 ** 20
