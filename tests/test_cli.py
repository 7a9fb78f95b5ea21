import json
import subprocess
import sys

import pytest

from colorps import __version__, angular_error
from colorps.cli import main
from colorps.io import read_image, write_image
from colorps.outputs import HEIGHT_FILES, OUTPUT_FILES
from colorps.synth import write_synthetic


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    folder = tmp_path_factory.mktemp("sample")
    info = write_synthetic(folder, size=64, images=5, theta=40, gauge_radius=45)
    return folder, info


def args_for(sample, out, *extra, sphere=None):
    folder, info = sample
    g = info["gauge_sphere"]
    return ["reconstruct", "--scene", str(folder / "scene_*.exr"),
            "--gauge", str(folder / "gauge_*.exr"),
            "--sphere", sphere or f"{g['cx']},{g['cy']},{g['r']}",
            "--out", str(out), "--quiet", *extra]


def test_reconstruct_writes_every_output(sample, tmp_path):
    out = tmp_path / "out"
    assert main(args_for(sample, out, "--mask", str(sample[0] / "mask.png"))) == 0
    defaults = OUTPUT_FILES + HEIGHT_FILES
    assert sorted(p.name for p in out.iterdir()) == sorted(defaults)
    normals, names = read_image(out / "normal.exr")
    assert names == ["X", "Y", "Z"] and normals.shape == (64, 64, 3)
    truth, _ = read_image(sample[0] / "truth_normal.exr")
    mask = read_image(sample[0] / "mask.png", "linear")[0][..., 0] > 0.5
    err = angular_error(normals[mask], truth[mask])
    assert err.mean() < 1.0
    albedo, albedo_names = read_image(out / "albedo.exr")
    assert albedo_names == ["R", "G", "B"]
    report = json.loads((out / "report.json").read_text())
    assert report["statistics"]["solved"] == mask.sum()
    assert report["options"]["mode"] == "colour" and report["statistics"]["grid_n"] > 1
    assert read_image(out / "normal.png", "linear")[0].shape == (64, 64, 3)
    assert sorted(p.name for p in (out / "viewer").iterdir()) == ["level0.js"]
    assert sorted(report["files"]) == sorted(p.name for p in out.iterdir())  # what is there


def test_auto_sphere_mono_and_options(sample, tmp_path):
    out = tmp_path / "auto"
    code = main(args_for(sample, out, "--mode", "mono", "--threads", "1", "--grid-n", "50",
                         "--gauge-albedo", "1,1,1", sphere="auto"))
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    assert report["sphere_found_automatically"]
    assert abs(report["sphere"]["r"] - sample[1]["gauge_sphere"]["r"]) < 1.0
    assert report["statistics"]["grid_n"] == 50


def test_list_file_input(sample, tmp_path):
    folder, _ = sample
    listing = tmp_path / "scene.txt"
    listing.write_text("\n".join(str(p) for p in sorted(folder.glob("scene_*.exr"))))
    args = args_for(sample, tmp_path / "o")
    args[args.index("--scene") + 1] = "@" + str(listing)
    assert main(args) == 0


@pytest.mark.parametrize("mutate, message", [
    (lambda a, s: a.__setitem__(a.index("--scene") + 1, str(s / "nothing_*.exr")),
     "matches no file"),
    (lambda a, s: a.__setitem__(a.index("--gauge") + 1, str(s / "gauge_0[0-2].exr")),
     "scene has 5 images but the gauge 3"),
    (lambda a, s: a.__setitem__(a.index("--sphere") + 1, "30,30,500"), "partly outside"),
    (lambda a, s: a.__setitem__(a.index("--sphere") + 1, "1000,1000,50"),  # (off the images:
     "partly outside"),  # the rim's measure had found no pixel to sample)
    (lambda a, s: a.__setitem__(a.index("--scene") + 1, str(s / "missing.exr")),
     "missing.exr: no such file"),
])
def test_bad_input_exits_nonzero_with_one_line(sample, tmp_path, capsys, mutate, message):
    out = tmp_path / "bad"
    args = args_for(sample, out)
    mutate(args, sample[0])
    assert main(args) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("colorps: error:") and message in err and "\n" not in err
    assert not out.exists()  # nothing created, not even the folder


@pytest.mark.parametrize("option, value", [
    ("--sphere", "1,2"), ("--sphere", "a,b,c"), ("--gauge-albedo", "0"),
    ("--gauge-albedo", "x"), ("--gauge-albedo", "80"), ("--threads", "0"), ("--grid-n", "-2"), ("--mode", "rgb"),
])
def test_malformed_options_are_usage_errors(sample, tmp_path, capsys, option, value):
    args = args_for(sample, tmp_path / "o")
    if option in args:
        args[args.index(option) + 1] = value
    else:
        args += [option, value]
    with pytest.raises(SystemExit) as exit_info:
        main(args)
    assert exit_info.value.code == 2
    assert option in capsys.readouterr().err


def test_existing_results_need_overwrite(sample, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(args_for(sample, out)) == 0
    before = (out / "normal.exr").read_bytes()
    assert main(args_for(sample, out)) == 1
    assert "--overwrite" in capsys.readouterr().err
    assert (out / "normal.exr").read_bytes() == before
    assert main(args_for(sample, out, "--overwrite")) == 0


def test_output_path_is_a_file(sample, tmp_path, capsys):
    target = tmp_path / "file"
    target.write_text("x")
    assert main(args_for(sample, target)) == 1
    assert "not a folder" in capsys.readouterr().err


def test_mismatched_image_sizes_name_the_file(sample, tmp_path, capsys):
    folder, _ = sample
    odd = tmp_path / "odd"
    odd.mkdir()
    for k, path in enumerate(sorted(folder.glob("scene_*.exr"))):
        image, _ = read_image(path)
        write_image(odd / path.name, image[:60] if k == 3 else image)
    args = args_for(sample, tmp_path / "o")
    args[args.index("--scene") + 1] = str(odd / "scene_*.exr")
    assert main(args) == 1
    assert "scene_03.exr (image 4 of 5 of the scene): size 64x60" in capsys.readouterr().err


def test_synth_and_demo(tmp_path, capsys):
    data = tmp_path / "data"
    assert main(["synth", "--out", str(data), "--size", "48", "--images", "4",
                 "--gauge-radius", "40", "--lights", "mixed"]) == 0
    assert (data / "truth_height.exr").exists()
    assert (data / "sample.json").exists() and len(list(data.glob("scene_*.exr"))) == 4
    assert main(["demo", "--data", str(data), "--out", str(tmp_path / "demo")]) == 0
    printed = capsys.readouterr().out
    assert "normal error (deg): mean" in printed and "height RMS error" in printed
    assert main(["demo", "--data", str(tmp_path / "none"), "--out", str(tmp_path / "d")]) == 1


@pytest.mark.parametrize("option, value, message", [
    ("--images", "2", "images: expected at least 3"), ("--theta", "95", "theta: expected 0"),
    ("--noise", "-0.1", "noise: expected a sigma"), ("--size", "8", "size: expected at least"),
    ("--gauge-radius", "4", "gauge_radius: expected at least")])
def test_synth_refuses_what_it_cannot_render(tmp_path, capsys, option, value, message):
    assert main(["synth", "--out", str(tmp_path / "data"), option, value]) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("colorps: error:") and message in err and "\n" not in err
    assert not (tmp_path / "data").exists()


def test_synth_needs_the_memory_it_renders_in(tmp_path, capsys, monkeypatch):
    """A gauge too large for the memory available is refused before any rendering
    (a 5000 px radius had the process killed), naming both sizes."""
    from colorps import memory

    monkeypatch.setattr(memory, "available_memory_bytes", lambda: 2 ** 30)
    assert main(["synth", "--out", str(tmp_path / "data"), "--gauge-radius", "1000"]) == 1
    assert "need about 1.5 GiB to render; 1.0 GiB is available" in capsys.readouterr().err
    assert not (tmp_path / "data").exists()


def test_synth_replaces_an_earlier_capture_only_when_told_and_whole(tmp_path, capsys):
    """An earlier capture is kept without --overwrite; with it, a capture of fewer
    images leaves none of the earlier images behind (a glob would mix them in),
    and a user's own files beside it stay."""
    data = tmp_path / "data"
    small = ["--size", "32", "--gauge-radius", "12"]
    assert main(["synth", "--out", str(data), *small, "--images", "6"]) == 0
    (data / "notes.txt").write_text("mine")
    before = {p.name: p.read_bytes() for p in data.iterdir()}
    assert main(["synth", "--out", str(data), *small, "--images", "3"]) == 1
    assert "use --overwrite" in capsys.readouterr().err
    assert {p.name: p.read_bytes() for p in data.iterdir()} == before
    assert main(["synth", "--out", str(data), *small, "--images", "3", "--overwrite"]) == 0
    assert sorted(p.name for p in data.glob("scene_*")) == [f"scene_{k:02d}.exr" for k in range(3)]
    assert len(list(data.glob("gauge_*"))) == 3 and (data / "notes.txt").read_text() == "mine"
    assert json.loads((data / "sample.json").read_text())["images"] == 3


def test_console_script_version_and_help():
    version = subprocess.run([sys.executable, "-m", "colorps.cli", "--version"],
                             capture_output=True, text=True)
    assert version.returncode == 0 and __version__ in version.stdout
    helptext = subprocess.run([sys.executable, "-m", "colorps.cli", "reconstruct", "--help"],
                              capture_output=True, text=True).stdout
    helptext = " ".join(helptext.split())
    assert "--sphere" in helptext and "(default: colour)" in helptext
    assert "default: None" not in helptext and "default: True" not in helptext
    bad = subprocess.run([sys.executable, "-m", "colorps.cli", "reconstruct"],
                         capture_output=True, text=True)
    assert bad.returncode == 2


def test_the_command_ends_with_its_exit_code_and_all_it_printed(tmp_path):
    """``python -m colorps`` (the console script's entry) ends the process without
    the interpreter's teardown: its output, piped, is all there, and its exit code
    is the command's."""
    wrote = subprocess.run([sys.executable, "-m", "colorps", "synth", "--out",
                            str(tmp_path / "capture"), "--size", "32", "--gauge-radius", "12"],
                           capture_output=True, text=True)
    assert wrote.returncode == 0, wrote.stderr
    assert wrote.stdout.endswith(f"wrote a synthetic stack with ground truth to "
                                 f"{tmp_path / 'capture'}/\n")
    failed = subprocess.run([sys.executable, "-m", "colorps", "reconstruct", "--scene",
                             str(tmp_path / "none_*.exr"), "--gauge", "g", "--sphere", "auto",
                             "--out", str(tmp_path / "out")], capture_output=True, text=True)
    assert failed.returncode == 1 and "matches no file" in failed.stderr
    assert not (tmp_path / "out").exists()


def test_bundled_demo_runs(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "demo")]) == 0
    assert "pixels solved" in capsys.readouterr().out


def test_channel_mismatch_across_stacks_and_small_radius(sample, tmp_path, capsys):
    folder, _ = sample
    grey = tmp_path / "grey"
    grey.mkdir()
    for path in sorted(folder.glob("gauge_*.exr")):
        write_image(grey / path.name, read_image(path)[0][..., :1])
    args = args_for(sample, tmp_path / "o")
    args[args.index("--gauge") + 1] = str(grey / "gauge_*.exr")
    assert main(args) == 1
    err = capsys.readouterr().err
    assert "gauge_00.exr: has 1 channel(s) but" in err and "scene_00.exr has 3" in err
    args = args_for(sample, tmp_path / "o", sphere="50,50,4")
    assert main(args) == 1
    assert "too small" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def _uncached_kernel(module: str):
    """A new numba kernel that claims to live in ``module`` (never in numba's cache)."""
    import numba

    namespace = {"__name__": module}
    exec("def kernel(x):\n    return x + 1\n", namespace)
    return numba.njit(namespace["kernel"])


def test_first_compile_of_a_colorps_kernel_is_announced_once(capsys):
    from colorps.cli import COMPILE_NOTICE, _compile_notice

    with _compile_notice():
        assert _uncached_kernel("colorps._notice_test")(1) == 2
        assert _uncached_kernel("colorps._notice_test")(2.0) == 3.0  # a second compile
    assert capsys.readouterr().err.count(COMPILE_NOTICE) == 1
    with _compile_notice():
        _uncached_kernel("elsewhere")(1)  # not colorps': no notice
    with _compile_notice(enabled=False):  # --quiet
        _uncached_kernel("colorps._notice_test")(1)
    assert COMPILE_NOTICE not in capsys.readouterr().err
    _uncached_kernel("colorps._notice_test")(1)  # outside the context: no listener left
    assert COMPILE_NOTICE not in capsys.readouterr().err


def test_summary_gives_the_residual_before_the_run_scale(sample, tmp_path, capsys):
    """The run's median residual is about 1 by construction when a scale is fitted;
    the summary also gives it in noise units (times the model scale), and the
    median 68 % radius, as in report.json."""
    out = tmp_path / "out"
    args = [a for a in args_for(sample, out, "--no-height") if a != "--quiet"]
    assert main(args) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    stats = json.loads((out / "report.json").read_text())["statistics"]
    absolute = stats["residual_median"] * stats["model_scale"]
    assert f"{absolute:.2f} in noise units before the model scale " \
           f"{stats['model_scale']:.2f}" in line
    assert f"68 % radius median {stats['uncertainty_median']:.2f} deg" in line


def test_report_times_every_phase_and_writing_shows_progress(sample, tmp_path, capsys):
    out = tmp_path / "timed"
    assert main([a for a in args_for(sample, out) if a != "--quiet"]) == 0
    captured = capsys.readouterr()
    assert "writing" in captured.err  # the files' progress bar
    assert "s in all" in captured.out
    report = json.loads((out / "report.json").read_text())
    run = report["run_seconds"]
    assert {"checking", "reading", "gauge", "reconstruct", "writing", "total"} <= set(run)
    phases = sum(v for k, v in run.items() if k != "total")
    assert phases <= run["total"] + 1e-6 and phases > 0.9 * run["total"]
    assert run["reconstruct"] >= report["statistics"]["seconds"]["total"] - 0.05
    assert run["writing"] >= report["statistics"]["seconds"]["integration"] - 0.05


def test_a_gauge_in_the_scenes_own_frame(sample, tmp_path, capsys):
    """Scene and gauge in one photograph per light: --scene and --gauge name the
    same files, and --sphere auto looks for the sphere outside --mask (the
    object). The normals are those of the gauge photographed apart; without the
    mask the two bright regions are refused, and the message says what to give."""
    import numpy as np

    folder, info = sample
    frames = tmp_path / "frames"
    frames.mkdir()
    mask = read_image(folder / "mask.png", "linear")[0][..., 0] > 0.5
    scenes = sorted(folder.glob("scene_*.exr"))
    for k, (scene_path, gauge_path) in enumerate(zip(scenes, sorted(folder.glob("gauge_*.exr")))):
        scene, gauge = read_image(scene_path)[0], read_image(gauge_path)[0]
        frame = np.zeros((max(len(scene), len(gauge)), scene.shape[1] + gauge.shape[1], 3),
                         np.float32)
        frame[:len(scene), :scene.shape[1]] = scene
        frame[:len(gauge), scene.shape[1]:] = gauge
        write_image(frames / f"photo_{k}.exr", frame)
    whole_mask = np.zeros(frame.shape[:2], np.float32)
    whole_mask[:mask.shape[0], :mask.shape[1]] = mask
    write_image(frames / "mask.png", whole_mask, dtype="uint8")
    photos = str(frames / "photo_*.exr")
    common = ["reconstruct", "--scene", photos, "--gauge", photos, "--sphere", "auto",
              "--quiet", "--no-height"]
    assert main([*common, "--out", str(tmp_path / "unmasked")]) != 0
    assert "--mask of the object" in capsys.readouterr().err
    assert main([*common, "--mask", str(frames / "mask.png"), "--out",
                 str(tmp_path / "framed")]) == 0
    assert main(args_for(sample, tmp_path / "apart", "--mask", str(folder / "mask.png"),
                         "--no-height")) == 0
    report = json.loads((tmp_path / "framed" / "report.json").read_text())
    g = info["gauge_sphere"]
    assert abs(report["sphere"]["cx"] - (g["cx"] + mask.shape[1])) < 0.5
    assert abs(report["sphere"]["cy"] - g["cy"]) < 0.5 and abs(report["sphere"]["r"] - g["r"]) < 1
    framed = read_image(tmp_path / "framed" / "normal.exr")[0][:mask.shape[0], :mask.shape[1]]
    apart = read_image(tmp_path / "apart" / "normal.exr")[0]
    truth = read_image(folder / "truth_normal.exr")[0]
    errors = [float(np.mean(angular_error(n[mask], truth[mask]))) for n in (framed, apart)]
    assert errors[0] < 1.2 * errors[1] + 0.05, errors
