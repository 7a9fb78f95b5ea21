"""colorps batch: capture folders and manifests, in process and on a Dask cluster."""

import json
import re

import numpy as np
import pytest

from colorps import InputError, Lights, Options, synth, write_lights
from colorps.batch import CaptureSpec, find_capture, read_manifest, run_batch
from colorps.cli import main
from colorps.io import read_image
from colorps.pipeline import reconstruct_files

OPTIONS = Options(height=False)


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """Two gauge captures and one light-file capture, as folders."""
    root = tmp_path_factory.mktemp("captures")
    synth.write_synthetic(root / "matte", size=48, images=6, theta=40, noise=0.002)
    synth.write_synthetic(root / "colour", size=40, images=6, theta=45, lights="colour",
                          noise=0.002, seed=3)
    info = synth.write_synthetic(root / "lit", size=40, images=6, theta=40, noise=0.002,
                                 seed=5)
    for gauge in (root / "lit").glob("gauge_*"):
        gauge.unlink()
    write_lights(Lights(np.array(info["light_directions"])[:, 0],
                        np.array(info["light_colours"])[:, 0]), root / "lit" / "lights.txt")
    return root


def test_folders_follow_the_convention(captures):
    matte = find_capture(captures / "matte")
    assert matte.gauge and matte.sphere == "auto" and matte.mask.endswith("mask.png")
    lit = find_capture(captures / "lit")
    assert lit.gauge is None and lit.lights.endswith("lights.txt")
    with pytest.raises(InputError, match="is not a capture folder"):
        find_capture(captures / "missing")
    with pytest.raises(InputError, match="no scene_\\* images"):
        find_capture(captures)


def test_batch_gives_each_capture_its_own_run(captures, tmp_path):
    specs = [find_capture(captures / name) for name in ("matte", "colour", "lit")]
    outcomes = run_batch(specs, tmp_path / "out", OPTIONS, progress=False)
    assert [o.name for o in outcomes] == ["matte", "colour", "lit"]
    assert all(o.ok and o.solved > 0 for o in outcomes)
    summary = json.loads((tmp_path / "out" / "batch.json").read_text())
    assert [c["solved"] for c in summary["captures"]] == [o.solved for o in outcomes]
    for spec in specs:  # the same maps as one `colorps reconstruct` each
        alone = reconstruct_files(spec.files, tmp_path / spec.name, options=OPTIONS,
                                  progress=False)
        batch_normals = read_image(tmp_path / "out" / spec.name / "normal.exr")[0]
        assert np.array_equal(batch_normals, alone.normals, equal_nan=True)


def test_a_failing_capture_does_not_stop_the_others(captures, tmp_path, capsys):
    manifest = tmp_path / "batch.json"
    manifest.write_text(json.dumps([
        {"name": "good", "scene": str(captures / "matte" / "scene_*.exr"),
         "gauge": str(captures / "matte" / "gauge_*.exr")},
        {"name": "short", "scene": str(captures / "matte" / "scene_*.exr"),
         "gauge": str(captures / "matte" / "gauge_0[0-3].exr")}]))
    out = tmp_path / "out"
    assert main(["batch", "--manifest", str(manifest), "--out", str(out), "--no-height",
                 "--quiet"]) == 1
    assert "short: the scene has 6 images but the gauge 4" in capsys.readouterr().err
    assert (out / "good" / "normal.exr").is_file() and not (out / "short").exists()
    summary = json.loads((out / "batch.json").read_text())
    assert [c["ok"] for c in summary["captures"]] == [True, False]
    # batch.json is a result too: a second run does not replace it silently.
    assert main(["batch", "--manifest", str(manifest), "--out", str(out), "--quiet"]) == 1
    assert "already exists" in capsys.readouterr().err


@pytest.mark.parametrize("content, message", [
    ("{}", "non-empty JSON list"),
    ("[1]", "entry 1 is not an object"),
    ('[{"name": "a"}]', "needs 'name' and 'scene'"),
    ('[{"name": "a", "scene": "x", "gauge": "y", "colour": 1}]', "unknown key"),
    ('[{"name": "a", "scene": "x"}]', "either gauge images or a light file"),
    ('[{"name": "a", "scene": "x", "gauge": "y"}, {"name": "a", "scene": "x", '
     '"lights": "l.txt"}]', "two captures are named 'a'"),
    ('[{"name": "../up", "scene": "x", "gauge": "y"}]', "plain folder name"),
    ("[", "not JSON"),
])
def test_bad_manifests_are_refused(tmp_path, content, message):
    path = tmp_path / "manifest.json"
    path.write_text(content)
    with pytest.raises(InputError, match=message):
        read_manifest(path)


def test_manifest_paths_are_relative_to_it(tmp_path):
    path = tmp_path / "sub" / "manifest.json"
    path.parent.mkdir()
    path.write_text('[{"name": "a", "scene": "s/*.exr", "lights": "@l.txt", '
                    '"sphere": [1, 2, 3], "gauge": null}]')
    spec = read_manifest(path)[0]
    assert spec == CaptureSpec(name="a", scene=[str(path.parent / "s/*.exr")],
                               lights="@" + str(path.parent / "l.txt"), sphere=(1.0, 2.0, 3.0))


def test_dask_batch_gives_the_in_process_results(captures, tmp_path):
    import distributed  # in the test extra
    specs = [find_capture(captures / name) for name in ("matte", "colour")]
    local = run_batch(specs, tmp_path / "local", OPTIONS, progress=False)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        remote = run_batch(specs, tmp_path / "dask", OPTIONS, client=client, progress=False)
    assert [o.solved for o in remote] == [o.solved for o in local]
    for spec in specs:
        a = read_image(tmp_path / "local" / spec.name / "normal.exr")[0]
        b = read_image(tmp_path / "dask" / spec.name / "normal.exr")[0]
        assert np.array_equal(a, b, equal_nan=True)


@pytest.mark.parametrize("command", ["batch", "reconstruct"])
def test_a_scheduler_address_dask_cannot_read_is_one_line(captures, tmp_path, capsys, command):
    """``--scheduler http://...`` (a dashboard's address, not the scheduler's) ended in
    a traceback: now exit 1 with one line saying what to give, and nothing written."""
    from colorps.cli import main

    matte = captures / "matte"
    out = tmp_path / "out"
    args = ([str(matte)] if command == "batch" else
            ["--scene", str(matte / "scene_*.exr"), "--gauge", str(matte / "gauge_*.exr"),
             "--sphere", "auto"])
    assert main([command, *args, "--out", str(out), "--quiet",
                 "--scheduler", "http://127.0.0.1:8787"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a Dask scheduler address" in err[0]
    assert "tcp://HOST:8786" in err[0] and "Traceback" not in err[0]
    assert not out.exists()


def test_any_readable_format_and_mask_name(tmp_path):
    """TGA and HDR captures with a mask.tif are found; another suffix is not an image."""
    from colorps.io import write_image

    folder = tmp_path / "tga"
    folder.mkdir()
    for k in range(4):
        write_image(folder / f"scene_{k}.tga", np.full((8, 8, 3), 0.5), dtype="uint8")
        write_image(folder / f"gauge_{k}.hdr", np.full((8, 8, 3), 0.5))
    write_image(folder / "mask.tif", np.ones((8, 8)), dtype="uint8")
    (folder / "scene_notes.txt").write_text("not an image")
    spec = find_capture(folder)
    assert spec.scene == [str(folder / "scene_*.tga")]
    assert spec.gauge == [str(folder / "gauge_*.hdr")] and spec.mask.endswith("mask.tif")
    write_image(folder / "mask.png", np.ones((8, 8)), dtype="uint8")
    with pytest.raises(InputError, match=re.escape("several masks (mask.png, mask.tif)")):
        find_capture(folder)
    odd = tmp_path / "odd"
    odd.mkdir()
    (odd / "scene_1.xyz").write_text("?")
    with pytest.raises(InputError, match=re.escape("scene_* files found are .xyz: not images")):
        find_capture(odd)
