"""The second round of bad inputs: nothing silent, nothing left behind, memory bounded.

Each case runs the CLI (``main([...])`` or a subprocess) and checks the exit code,
the one-line message naming the file, and the output folder's bytes before/after.
"""

import json
import os
import shutil
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from colorps import synth
from colorps.cli import main
from tests.conftest import long_run_command
from colorps.io import read_image, write_image


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    folder = tmp_path_factory.mktemp("capture")
    info = synth.write_synthetic(folder, size=48, images=4, theta=40, gauge_radius=30)
    return folder, info


def args_for(capture, out, scene=None, gauge=None, *extra):
    folder, info = capture
    g = info["gauge_sphere"]
    return ["reconstruct", "--scene", scene or str(folder / "scene_*.exr"),
            "--gauge", gauge or str(folder / "gauge_*.exr"),
            "--sphere", f"{g['cx']},{g['cy']},{g['r']}", "--out", str(out), "--quiet", *extra]


def snapshot(folder: Path) -> dict:
    """Every file below ``folder`` with its bytes (hidden temporaries included)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


def one_line_error(capsys, *words):
    err = capsys.readouterr().err.strip()
    lines = [line for line in err.splitlines() if line.startswith("colorps: error:")]
    assert len(lines) == 1, err
    for word in words:
        assert word in lines[0], lines[0]
    return lines[0]


def copy_stack(capture, folder, rename=None, convert=None):
    """Copy the capture's images into ``folder`` (optionally converted per file)."""
    src, _ = capture
    folder.mkdir(exist_ok=True)
    for path in sorted(src.glob("*_0*.exr")):
        image, names = read_image(path)
        name = rename(path.name) if rename else path.name
        if convert:
            convert(folder / name, image, path.name)
        else:
            write_image(folder / name, image, channel_names=names, dtype="half")
    return folder


# ------------------------------------------------------------------ silent wrong data
def test_mixed_pixel_types_in_a_stack_are_refused(capture, tmp_path, capsys):
    mixed = copy_stack(capture, tmp_path / "mixed", convert=lambda p, im, n: write_image(
        p.with_suffix(".tif") if n == "scene_02.exr" else p, im if n != "scene_02.exr"
        else np.clip(im, 0, 1), dtype="uint16" if n == "scene_02.exr" else "half"))
    out = tmp_path / "out"
    code = main(args_for(capture, out, scene=f"{mixed}/scene_0*"))
    assert code == 1
    one_line_error(capsys, "scene_02.tif", "pixel type uint16", "scene_00.exr")
    assert not out.exists()


def test_saturated_16bit_gauge_with_exr_scene_is_not_silent(capture, tmp_path, capsys):
    """The gauge's own clip level applies to the gauge: its saturated pixels are
    clipped, and the run warns (or refuses) instead of matching garbage."""
    gauges = copy_stack(capture, tmp_path / "tif", rename=lambda n: n.replace(".exr", ".tif"),
                        convert=lambda p, im, n: write_image(p, np.clip(im * 4, 0, 1),
                                                             dtype="uint16"))
    out = tmp_path / "out"
    code = main(args_for(capture, out, gauge=f"{gauges}/gauge_*.tif"))
    err = capsys.readouterr().err
    assert code == 1 or "warning" in err, err
    if code == 0:
        import json
        report = json.loads((out / "report.json").read_text())
        assert report["gauge_levels"]["clip_level"] is not None
        assert report["statistics"]["warnings"]


# ------------------------------------------------------------------ runs that solve nothing
def test_mask_selecting_nothing_is_an_error(capture, tmp_path, capsys):
    empty = tmp_path / "empty.png"
    write_image(empty, np.zeros((48, 48)), dtype="uint8")
    out = tmp_path / "out"
    assert main(args_for(capture, out, None, None, "--mask", str(empty))) == 1
    one_line_error(capsys, "empty.png", "selects no pixel")
    assert not out.exists()


def test_all_black_scene_is_an_error(capture, tmp_path, capsys):
    black = copy_stack(capture, tmp_path / "black",
                       convert=lambda p, im, n: write_image(p, im * 0, dtype="half"))
    out = tmp_path / "out"
    assert main(args_for(capture, out, scene=f"{black}/scene_*.exr")) == 1
    one_line_error(capsys, "scene_00.exr", "no pixel", "too dark")
    assert not out.exists()


def test_small_solved_fraction_warns_in_summary_and_report(capture, tmp_path, capsys):
    import json

    half = copy_stack(capture, tmp_path / "half", convert=lambda p, im, n: write_image(
        p, np.where(np.arange(48)[None, :, None] < 34, 0.0, im) if n.startswith("scene")
        else im, dtype="half"))
    out = tmp_path / "out"
    assert main(args_for(capture, out, scene=f"{half}/scene_*.exr")) == 0
    assert "only" in capsys.readouterr().err
    report = json.loads((out / "report.json").read_text())
    assert any("were solved" in w for w in report["statistics"]["warnings"])


@pytest.mark.parametrize("centre, warned", [((42, 42), False), ((46, 2), True)])
def test_a_mask_drawn_for_another_object(capture, tmp_path, capsys, centre, warned):
    """A mask drawn for another object (another capture's, a disc elsewhere): its
    pixels off this object are refused as too dark and counted in report.json, never
    given normals; the ones on it are right; when most are off, the run says so."""
    import json

    from colorps import angular_error

    folder, _ = capture
    scene_mask = read_image(folder / "mask.png")[0][..., 0] > 0.5
    truth = read_image(folder / "truth_normal.exr")[0]
    yy, xx = np.mgrid[:48, :48]
    wrong = (yy - centre[0]) ** 2 + (xx - centre[1]) ** 2 < 18 ** 2
    write_image(tmp_path / "wrong.png", np.repeat(wrong[..., None], 3, axis=2).astype(float),
                dtype="uint8")
    out = tmp_path / "out"
    assert main(args_for(capture, out, None, None, "--mask", str(tmp_path / "wrong.png"),
                         "--no-height")) == 0
    assert ("were solved (mostly 'too dark'" in capsys.readouterr().err) == warned
    normals = read_image(out / "normal.exr")[0]
    solved = np.isfinite(normals).all(axis=-1)
    off, on = wrong & ~scene_mask, wrong & scene_mask
    assert off.sum() > 100 and on.sum() > 50
    assert not solved[off].any()
    report = json.loads((out / "report.json").read_text())
    stats = report["statistics"]
    assert stats["pixels_by_reason"]["too dark"] == off.sum()
    assert stats["solved"] == solved.sum() == on.sum()
    assert stats["residual_median_noise_units"] == pytest.approx(
        stats["residual_median"] * stats["model_scale"])
    assert np.median(angular_error(normals[on], truth[on])) < 2.0


# ------------------------------------------------------------------ memory
def hostile_exr(path: Path, claims: int) -> None:
    """A small valid EXR whose header then claims ``claims`` x ``claims`` pixels."""
    write_image(path, np.zeros((8, 8, 3)), dtype="half")
    data = bytearray(path.read_bytes())
    for name in (b"dataWindow\0box2i\0", b"displayWindow\0box2i\0"):
        at = data.index(name) + len(name) + 4  # skip the attribute's size
        data[at:at + 16] = struct.pack("<4i", 0, 0, claims - 1, claims - 1)
    path.write_bytes(bytes(data))


def test_hostile_header_refused_before_decoding(capture, tmp_path):
    folder = copy_stack(capture, tmp_path / "hostile")
    hostile_exr(folder / "scene_01.exr", 20000)
    out = tmp_path / "out"
    # The child's own peak (VmHWM: ru_maxrss would carry over the forking pytest's).
    code = ("import re, sys; from colorps.cli import main; "
            f"rc = main({args_for(capture, out, scene=str(folder / 'scene_*.exr'))!r}); "
            "print(re.search(r'VmHWM:\\s*(\\d+)', open('/proc/self/status').read())[1]); "
            "sys.exit(rc)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 1, proc.stderr
    assert proc.stderr.count("\n") == 1 and "scene_01.exr: " in proc.stderr
    assert "size 20000x20000" in proc.stderr or "header" in proc.stderr
    peak_mb = int(proc.stdout.split()[-1]) / 1024
    assert peak_mb < 1000, peak_mb  # the header claims 4.8 GB of float32 pixels
    assert not out.exists()


def test_stack_too_large_for_the_limit(capture, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(args_for(capture, out, None, None, "--max-input-gib", "0.0001")) == 1
    one_line_error(capsys, "scene_00.exr", "GiB", "--max-input-gib")


def test_absurd_grid_size_is_refused(capture, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(args_for(capture, out, None, None, "--grid-n", "1000000")) == 1
    one_line_error(capsys, "far too fine", "at most N")
    assert not out.exists()


# ------------------------------------------------------------------ tracebacks
@pytest.mark.parametrize("kind", ["noise", "tiny"])
def test_auto_sphere_without_a_sphere(capture, tmp_path, capsys, kind):
    rng = np.random.default_rng(0)
    size = 1 if kind == "tiny" else 64
    folder = tmp_path / kind
    folder.mkdir()
    for k in range(4):
        write_image(folder / f"gauge_{k}.exr", rng.random((size, size, 3)), dtype="half")
    args = args_for(capture, tmp_path / "out", gauge=str(folder / "gauge_*.exr"))
    args[args.index("--sphere") + 1] = "auto"
    if kind == "tiny":
        args[args.index("--scene") + 1] = str(folder / "gauge_*.exr")
    assert main(args) == 1
    one_line_error(capsys, "sphere auto")


def test_one_pixel_scene(capture, tmp_path):
    folder = copy_stack(capture, tmp_path / "one", convert=lambda p, im, n: write_image(
        p, im[24:25, 24:25] if n.startswith("scene") else im, dtype="half"))
    out = tmp_path / "out"
    assert main(args_for(capture, out, scene=f"{folder}/scene_*.exr")) == 0
    assert read_image(out / "relief.png")[0].shape[:2] == (1, 1)


# ------------------------------------------------------------------ files left behind
def test_disk_full_leaves_nothing_and_names_the_folder(capture, tmp_path, capsys,
                                                       monkeypatch):
    import errno

    import colorps.outputs as outputs

    real = outputs.write_image
    calls = []

    def full_disk(path, *a, **k):
        calls.append(path)
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, *a, **k)

    monkeypatch.setattr(outputs, "write_image", full_disk)
    out = tmp_path / "new" / "deeper" / "out"
    assert main(args_for(capture, out)) == 1
    line = one_line_error(capsys, str(out), "No space left on device")
    assert ".colorps-" not in line
    assert list(tmp_path.iterdir()) == []  # not the folder, not its parents


def test_failed_integration_leaves_old_results_byte_identical(capture, tmp_path, capsys,
                                                              monkeypatch):
    # The height is integrated in a thread while the maps are written: its
    # failure must still fail the whole write, after some maps were written.
    import colorps.outputs as outputs
    from colorps.errors import InputError

    out = tmp_path / "out"
    assert main(args_for(capture, out)) == 0
    before = snapshot(tmp_path)
    written = []
    real_write = outputs.write_image
    monkeypatch.setattr(outputs, "write_image",
                        lambda path, *a, **k: written.append(path) or real_write(path, *a, **k))

    def failing(*args, **kwargs):
        raise InputError("weights: must be finite and >= 0 inside the mask")

    monkeypatch.setattr(sys.modules["colorps.pipeline"], "integrate", failing)
    assert main(args_for(capture, out, None, None, "--overwrite")) == 1
    one_line_error(capsys, "weights: must be finite")
    assert any(p.name == "normal.exr" for p in written)  # the maps went first
    assert snapshot(tmp_path) == before


def test_overwrite_swaps_the_whole_folder(capture, tmp_path):
    out = tmp_path / "out"
    assert main(args_for(capture, out)) == 0
    first = snapshot(out)
    assert main(args_for(capture, out, None, None, "--overwrite", "--mode", "mono")) == 0
    second = snapshot(out)
    assert set(first) == set(second) and first["report.json"] != second["report.json"]
    assert [p.name for p in tmp_path.iterdir()] == ["out"]  # no temporaries beside it
    (out / "notes.txt").write_text("mine")  # a user's file is kept
    assert main(args_for(capture, out, None, None, "--overwrite")) == 0
    assert (out / "notes.txt").read_text() == "mine"


def test_failed_overwrite_leaves_old_results_byte_identical(capture, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(args_for(capture, out)) == 0
    before = snapshot(tmp_path)
    assert main(args_for(capture, out, str(tmp_path / "missing_*.exr"), None,
                         "--overwrite")) == 1
    one_line_error(capsys, "matches no file")
    assert snapshot(tmp_path) == before


def test_sigterm_leaves_no_temporaries(tmp_path):
    cmd, out = long_run_command(tmp_path)
    codes = []
    for delay in (2.0, 4.0):
        proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)
        time.sleep(delay)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
        codes.append(proc.returncode)
        hidden = [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]
        assert hidden == []
        # 143: caught by colorps. -SIGTERM: Python's default, before colorps set
        # its handler (importing) or after it restored it (exiting, results written).
        assert proc.returncode in (0, 143, -signal.SIGTERM), (proc.returncode, err)
        if proc.returncode == 143:
            assert "terminated" in err and not out.exists(), err
        elif out.exists():
            assert (out / "report.json").exists() and (out / "normal.exr").exists(), err
            shutil.rmtree(out)
    assert 143 in codes, codes


# ------------------------------------------------------------------ details users notice
def test_result_files_follow_the_umask(capture, tmp_path):
    old = os.umask(0o022)
    try:
        out = tmp_path / "out"
        assert main(args_for(capture, out)) == 0
    finally:
        os.umask(old)
    assert (out.stat().st_mode & 0o777) == 0o755
    for path in out.rglob("*"):
        assert (path.stat().st_mode & 0o777) == (0o755 if path.is_dir() else 0o644), path


def test_existing_file_with_glob_characters(capture, tmp_path):
    folder = copy_stack(capture, tmp_path / "odd",
                        rename=lambda n: n.replace("scene_", "shot [").replace(".exr", "].exr"))
    scenes = sorted(str(p) for p in folder.glob("shot*"))
    assert scenes and "[" in scenes[0]
    out = tmp_path / "out"
    folder_, info = capture
    g = info["gauge_sphere"]
    assert main(["reconstruct", "--scene", *scenes, "--gauge", str(folder_ / "gauge_*.exr"),
                 "--sphere", f"{g['cx']},{g['cy']},{g['r']}", "--out", str(out),
                 "--quiet"]) == 0


def test_integrate_refuses_what_is_not_a_normal_map(capture, tmp_path, capsys):
    folder, _ = capture
    out = tmp_path / "z.exr"
    assert main(["integrate", str(folder / "scene_00.exr"), "--out", str(out)]) == 1
    one_line_error(capsys, "scene_00.exr", "not a normal map")
    nan = tmp_path / "nan.exr"
    write_image(nan, np.full((8, 8, 3), np.nan))
    with _no_warnings():  # numpy's all-NaN warning must not leak out
        assert main(["integrate", str(nan), "--out", str(out)]) == 1
    one_line_error(capsys, "nan.exr", "no finite normal")
    assert not out.exists()


class _no_warnings:
    """Fail when the block issues any warning."""

    def __enter__(self):
        import warnings
        self._catch = warnings.catch_warnings(record=True)
        self.caught = self._catch.__enter__()
        warnings.simplefilter("always")

    def __exit__(self, *exc):
        self._catch.__exit__(*exc)
        assert not self.caught, [str(w.message) for w in self.caught]


def copy_with_exposure(src, dst, time, f_number=8.0, scale=1.0):
    """An image as a camera would have saved it: its EXIF exposure in the header
    (and, with ``scale``, pixels as bright as that exposure makes them)."""
    import OpenImageIO as oiio

    buf = oiio.ImageBuf(str(src))
    if scale != 1.0:
        buf = oiio.ImageBufAlgo.mul(buf, scale)
    buf.specmod().attribute("ExposureTime", float(time))
    buf.specmod().attribute("FNumber", float(f_number))
    assert buf.write(str(dst), "half"), buf.geterror()


def test_exposures_of_scene_and_gauge_are_checked(capture, tmp_path, capsys):
    """EXIF exposures that differ between a light's scene and gauge photos bias the
    normals, and a uniform difference scales the albedo: both are said, with numbers."""
    folder, info = capture

    def run(name, scene_times, gauge_times, scale=1.0):
        data = tmp_path / name
        data.mkdir()
        for k, (ts, tg) in enumerate(zip(scene_times, gauge_times)):
            copy_with_exposure(folder / f"scene_{k:02d}.exr", data / f"scene_{k:02d}.exr", ts,
                               scale=scale)
            copy_with_exposure(folder / f"gauge_{k:02d}.exr", data / f"gauge_{k:02d}.exr", tg)
        out = tmp_path / f"out_{name}"
        assert main(args_for(capture, out, str(data / "scene_*.exr"),
                             str(data / "gauge_*.exr"), "--no-height")) == 0
        report = json.loads((out / "report.json").read_text())
        return report["exposure_scene_over_gauge"], capsys.readouterr().err, out

    same = [1 / 125] * 4
    ratios, err, alike = run("alike", same, same)
    assert ratios == [1.0] * 4 and "exposed" not in err
    ratios, err, _ = run("one_light", same, [1 / 125, 1 / 125, 1 / 60, 1 / 125])
    assert ratios[2] == pytest.approx(60 / 125) and ratios[0] == 1.0
    assert "warning" in err and "scene_02.exr" in err and "different lights" in err
    # The whole scene exposed 2x: its pixels 2x brighter, and the albedo with them.
    ratios, err, twice = run("twice", [2 / 125] * 4, same, scale=2.0)
    assert ratios == pytest.approx([2.0] * 4)
    assert "exposed 2x the gauge" in err and "multiplied by 2" in err
    base, _ = read_image(alike / "albedo.exr")
    doubled, _ = read_image(twice / "albedo.exr")
    assert np.nanmedian(doubled / base) == pytest.approx(2.0, rel=0.01)
    # No EXIF (synthetic EXR): nothing to compare.
    assert main(args_for(capture, tmp_path / "plain", None, None, "--no-height")) == 0
    report = json.loads((tmp_path / "plain" / "report.json").read_text())
    assert report["exposure_scene_over_gauge"] is None


def test_unequal_exposures_within_a_light_file_run_are_warned_about(capture, tmp_path,
                                                                   capsys):
    """With calibrated lights no gauge photo cancels an image's exposure: one image
    exposed 2x the others is named, with its place in the stack."""
    from colorps import Lights, write_lights

    folder, info = capture
    lights = tmp_path / "lights.txt"
    write_lights(Lights(np.array(info["light_directions"])[:, 0],
                        np.array(info["light_colours"])[:, 0]), lights)
    data = tmp_path / "data"
    data.mkdir()
    for k, time_s in enumerate([1 / 125, 1 / 125, 2 / 125, 1 / 125]):
        copy_with_exposure(folder / f"scene_{k:02d}.exr", data / f"scene_{k:02d}.exr", time_s)
    command = ["reconstruct", "--scene", str(data / "scene_*.exr"), "--lights", str(lights),
               "--brdf", "lambert", "--out", str(tmp_path / "o"), "--quiet", "--no-height"]
    assert main(command) == 0
    err = capsys.readouterr().err
    assert "scene_02.exr (image 3 of 4): exposed 2x the scene's usual exposure" in err
    for k in range(4):  # alike: nothing said
        copy_with_exposure(folder / f"scene_{k:02d}.exr", data / f"scene_{k:02d}.exr", 1 / 125)
    assert main(command[:-4] + ["--out", str(tmp_path / "o2"), "--quiet", "--no-height"]) == 0
    assert "exposed" not in capsys.readouterr().err


@pytest.mark.parametrize("stack", ["scene", "gauge"])
def test_a_file_given_twice_is_refused_naming_it(capture, tmp_path, capsys, stack):
    """A stack that lists one image twice (a typo in a list file, a glob and a
    path that overlap) is refused before any work, naming the file and both
    positions; nothing is written."""
    folder, _ = capture
    listed = [folder / f"{stack}_0{k}.exr" for k in (0, 1, 2)]
    listed.insert(2, Path(str(folder) + "/./" + f"{stack}_01.exr"))  # the same file
    (tmp_path / "list.txt").write_text("\n".join(str(p) for p in listed))
    out = tmp_path / "out"
    given = {stack: "@" + str(tmp_path / "list.txt")}
    assert main(args_for(capture, out, given.get("scene"), given.get("gauge"))) == 1
    line = one_line_error(capsys, f"{stack}_01.exr", f"given twice in the {stack} stack",
                          "images 2 and 3 of 4")
    assert "Traceback" not in line
    assert not out.exists()


def test_empty_out_is_refused_before_any_work(capture, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    before = snapshot(tmp_path)
    assert main(args_for(capture, "")) == 1
    one_line_error(capsys, "--out is empty")
    assert snapshot(tmp_path) == before


def test_out_dot_writes_into_the_users_own_folder(capture, tmp_path, monkeypatch):
    """``--out .``: the folder the user stands in keeps its identity, its mode and
    its other files; the results are written into it (twice, with --overwrite)."""
    work = tmp_path / "work"
    work.mkdir()
    os.chmod(work, 0o750)
    (work / "notes.txt").write_text("mine")
    monkeypatch.chdir(work)
    inode = work.stat().st_ino
    assert main(args_for(capture, ".")) == 0
    assert main(args_for(capture, ".", None, None, "--overwrite")) == 0
    assert work.stat().st_ino == inode and (work.stat().st_mode & 0o777) == 0o750
    assert (work / "notes.txt").read_text() == "mine"
    assert (work / "normal.exr").exists()
    assert not [p for p in work.iterdir() if p.name.startswith(".")]  # no temporaries
    assert Path.cwd() == work


def test_out_symlink_stays_a_link(capture, tmp_path):
    """A results folder reached through a symbolic link (a mounted volume's path, a
    shared folder) is written through the link, which stays one."""
    real = tmp_path / "real"
    link = tmp_path / "link"
    assert main(args_for(capture, real)) == 0
    link.symlink_to(real, target_is_directory=True)
    stamp = (real / "report.json").stat().st_mtime_ns
    assert main(args_for(capture, link, None, None, "--overwrite")) == 0
    assert link.is_symlink() and real.is_dir() and not real.is_symlink()
    assert (real / "report.json").stat().st_mtime_ns != stamp


@pytest.mark.parametrize("stack", ["scene", "gauge"])
def test_a_mask_in_the_stack_is_named_with_its_position(capture, tmp_path, capsys, stack):
    """A glob that picks up a mask file: refused by its name before any pixel is read,
    or, named like a photograph, by its two values; the message names the file and
    its position, and nothing is written."""
    folder, _ = capture
    for kind in ("scene", "gauge"):
        for k in range(4):
            shutil.copy(folder / f"{kind}_{k:02d}.exr", tmp_path / f"{kind}_{k:02d}.exr")
    mask = read_image(folder / "mask.png")[0][..., :1]
    out = tmp_path / "out"
    # By name: cat.mask.exr sorts after the photographs.
    write_image(tmp_path / f"{stack}_zz.mask.exr", np.repeat(mask, 3, axis=2), dtype="half")
    pattern = str(tmp_path / f"{stack}_*.exr")
    given = {stack: pattern}
    code = main(args_for(capture, out, given.get("scene"), given.get("gauge")))
    assert code == 1
    one_line_error(capsys, f"{stack}_zz.mask.exr", "image 5 of the 5", "looks like a mask")
    assert not out.exists()
    # By content: the same mask named like a photograph (and sized like the stack).
    (tmp_path / f"{stack}_zz.mask.exr").rename(tmp_path / f"{stack}_04.exr")
    size = read_image(tmp_path / f"{stack}_00.exr")[0].shape[:2]
    binary = np.zeros(size + (3,), np.float32)
    binary[size[0] // 4:size[0] // 2, size[1] // 4:size[1] // 2] = 1.0
    write_image(tmp_path / f"{stack}_04.exr", binary, dtype="half")
    other = "gauge" if stack == "scene" else "scene"  # five images on both sides
    shutil.copy(tmp_path / f"{other}_00.exr", tmp_path / f"{other}_04.exr")
    given = {"scene": str(tmp_path / "scene_*.exr"), "gauge": str(tmp_path / "gauge_*.exr")}
    assert main(args_for(capture, out, given.get("scene"), given.get("gauge"))) == 1
    one_line_error(capsys, f"{stack}_04.exr", "image 5 of the 5", "only 2 values (0 and 1)")
    assert not out.exists()


@pytest.mark.parametrize("stack", ["scene", "gauge"])
def test_a_file_copied_over_another_is_warned_about_once(capture, tmp_path, capsys, stack):
    """Two images of a stack holding the same pixels (under two lights they cannot):
    one warning naming both files and their positions; the run still finishes."""
    folder, _ = capture
    for kind in ("scene", "gauge"):
        for k in range(4):
            shutil.copy(folder / f"{kind}_{k:02d}.exr", tmp_path / f"{kind}_{k:02d}.exr")
    shutil.copy(folder / f"{stack}_01.exr", tmp_path / f"{stack}_02.exr")
    assert main(args_for(capture, tmp_path / "out", str(tmp_path / "scene_*.exr"),
                         str(tmp_path / "gauge_*.exr"), "--no-height")) == 0
    said = [line for line in capsys.readouterr().err.splitlines() if "same pixels" in line]
    assert len(said) == 1, said
    assert f"{stack}_02.exr: image 3 of the 4 {stack} images holds the same pixels as " \
           f"image 2, {tmp_path / f'{stack}_01.exr'}" in said[0]
    assert main(args_for(capture, tmp_path / "clean", None, None, "--no-height")) == 0
    assert "same pixels" not in capsys.readouterr().err


def test_swapped_stacks_and_the_wrong_encoding_are_warned_about(capture, tmp_path, capsys):
    """The gauge's shading is fitted as a lit sphere at its place: scene and gauge
    swapped fit badly; 8-bit files decoded the wrong way fit far better the other
    way: under --encoding auto they are then read as linear (and the warning says
    so), with an explicit --encoding the warning says which to pass. report.json
    records both fits and the choice."""
    from colorps import angular_error
    from colorps.io import srgb_encode

    folder, info = capture
    g = info["gauge_sphere"]
    out = tmp_path / "swapped"
    assert main(["reconstruct", "--scene", str(folder / "gauge_*.exr"), "--gauge",
                 str(folder / "scene_*.exr"), "--sphere", "23.5,23.5,22", "--out", str(out),
                 "--quiet", "--no-height"]) == 0
    assert "scene and gauge are not swapped" in capsys.readouterr().err
    # The capture as 8-bit files: linear codes (a camera's linear PNG), and sRGB codes.
    for kind in ("scene", "gauge"):
        for k in range(4):
            image = read_image(folder / f"{kind}_{k:02d}.exr")[0]
            write_image(tmp_path / f"lin_{kind}_{k}.png", image, dtype="uint8")
            write_image(tmp_path / f"srgb_{kind}_{k}.png", srgb_encode(image), dtype="uint8")
    sphere = f"{g['cx']},{g['cy']},{g['r']}"
    truth = read_image(folder / "truth_normal.exr")[0]
    cases = (("lin", "auto", "read as linear (--encoding auto)", "linear"),
             ("srgb", "linear", "pass --encoding srgb", None), ("srgb", "auto", None, None),
             ("lin", "linear", None, None))
    errors = {}
    for prefix, encoding, said, decoded_as in cases:
        out = tmp_path / f"{prefix}-{encoding}"
        assert main(["reconstruct", "--scene", str(tmp_path / f"{prefix}_scene_*.png"),
                     "--gauge", str(tmp_path / f"{prefix}_gauge_*.png"), "--sphere", sphere,
                     "--encoding", encoding, "--out", str(out), "--quiet", "--no-height",
                     "--max-residual", "none"]) == 0
        err = capsys.readouterr().err
        assert (said in err) if said else ("--encoding" not in err), err
        report = json.loads((out / "report.json").read_text())
        check = report["gauge_check"]
        assert check["sphere_fit_residual"] > 0 and check["other_encoding_residual"] > 0
        assert check["decoded_as"] == decoded_as
        assert report["options"]["encoding"] == (decoded_as or encoding)
        normals = read_image(out / "normal.exr")[0]
        solved = np.isfinite(normals).all(axis=-1)
        errors[prefix, encoding] = float(np.mean(angular_error(normals[solved],
                                                               truth[solved])))
    # Read as linear by itself, the linear set is as good as when told so.
    assert errors["lin", "auto"] == pytest.approx(errors["lin", "linear"], abs=1e-6)
    assert errors["lin", "auto"] < 3.0


def test_float_files_told_to_be_srgb_are_warned_about_when_linear_fits(capture, tmp_path,
                                                                        capsys):
    """Floating-point files are linear unless --encoding srgb says otherwise; told
    so, the gauge's fit is compared with the values as stored, and the warning
    says to pass --encoding linear when those fit far better (as they do here)."""
    out = tmp_path / "told-srgb"
    assert main(args_for(capture, out, None, None, "--encoding", "srgb", "--no-height")) == 0
    err = capsys.readouterr().err
    assert "gauge_00.exr" in err and "pass --encoding linear" in err, err
    check = json.loads((out / "report.json").read_text())["gauge_check"]
    assert check["other_encoding_residual"] < 0.5 * check["sphere_fit_residual"]
    assert main(args_for(capture, tmp_path / "as-stored", None, None, "--no-height")) == 0
    assert "--encoding" not in capsys.readouterr().err
    check = json.loads((tmp_path / "as-stored" / "report.json").read_text())["gauge_check"]
    assert check["other_encoding_residual"] is None


def test_light_file_runs_choose_the_encoding_the_lights_explain(tmp_path, capsys):
    """With calibrated lights, 8-bit linear files are found so from the scene's fit
    to its lights: read as linear under auto (as good as when told), warned about
    when --encoding srgb is forced."""
    from colorps import Lights, angular_error, write_lights

    info = synth.write_synthetic(tmp_path / "cap", size=64, images=8, theta=40)
    lights = tmp_path / "lights.txt"
    write_lights(Lights(np.array(info["light_directions"])[:, 0],
                        np.array(info["light_colours"])[:, 0]), lights)
    for k in range(8):
        image = read_image(tmp_path / "cap" / f"scene_{k:02d}.exr")[0]
        write_image(tmp_path / f"lin_{k}.png", image, dtype="uint8")
    truth = read_image(tmp_path / "cap" / "truth_normal.exr")[0]
    errors = {}
    for encoding, said in (("auto", "read as linear (--encoding auto)"),
                           ("linear", None), ("srgb", "pass --encoding linear")):
        out = tmp_path / encoding
        assert main(["reconstruct", "--scene", str(tmp_path / "lin_*.png"), "--lights",
                     str(lights), "--mask", str(tmp_path / "cap" / "mask.png"), "--encoding",
                     encoding, "--out", str(out), "--quiet", "--no-height"]) == 0
        err = capsys.readouterr().err
        assert (said in err) if said else ("--encoding" not in err), err
        check = json.loads((out / "report.json").read_text())["lights_check"]
        assert check["decoded_as"] == ("linear" if encoding == "auto" else None)
        normals = read_image(out / "normal.exr")[0]
        solved = np.isfinite(normals).all(axis=-1)
        errors[encoding] = float(np.mean(angular_error(normals[solved], truth[solved])))
    assert errors["auto"] == pytest.approx(errors["linear"], abs=1e-6)
    assert errors["srgb"] > errors["linear"] + 2.0
