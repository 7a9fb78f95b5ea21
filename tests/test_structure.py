"""Options, reasons, geometry and packaging: each concept has one home, and it holds."""

import dataclasses
import fnmatch
import tomllib
from pathlib import Path

import numpy as np
import pytest

import colorps
from colorps import InputError, Options, Reason, synth
from colorps.cli import build_parser
from colorps.geometry import angular_error, sphere_normals
from colorps.options import FLOAT_DARK_LEVEL, dark_threshold
from colorps.reasons import reason_counts, reason_picture
from colorps.sample import sample_folder

ROOT = Path(__file__).resolve().parent.parent


def cli_options(*extra):
    args = build_parser().parse_args(["reconstruct", "--scene", "s", "--gauge", "g",
                                      "--sphere", "auto", "--out", "o", *extra])
    return Options(**{f.name: getattr(args, f.name) for f in dataclasses.fields(Options)})


def test_cli_defaults_are_the_options_defaults():
    assert cli_options() == Options()


def test_cli_converts_every_option_text():
    got = cli_options("--mode", "mono", "--band", "2", "--colourspace", "Adobe RGB (1998)",
                      "--grid-n", "auto", "--threads", "1", "--dark-level", "0.001",
                      "--clip-level", "none", "--max-distance", "0.2", "--encoding", "srgb",
                      "--mesh", "obj", "--read-noise", "0.002", "--gain", "0",
                      "--no-band-weights", "--no-light-subsets", "--max-dropped-lights", "1",
                      "--max-residual", "none", "--memory-limit", "none")
    assert got == Options(mode="mono", band=2, colourspace="Adobe RGB (1998)",
                          grid_n="auto", threads=1, dark_level=0.001, clip_level=None,
                          max_distance=0.2, encoding="srgb", mesh="obj", read_noise=0.002,
                          gain=0.0, band_weights=False, light_subsets=False,
                          max_dropped_lights=1, max_residual=None, memory_limit_gib=None)
    assert cli_options("--mode", "mono", "--band", "luminance", "--grid-n", "7",
                       "--clip-level", "0.9", "--no-height", "--memory-limit",
                       "2.5").replace(mesh=None) == \
        Options(mode="mono", band="luminance", grid_n=7, clip_level=0.9, height=False,
                memory_limit_gib=2.5)


@pytest.mark.parametrize("field, value", [
    ("mode", "grey"), ("band", -1), ("band", "red"), ("grid_n", 0), ("grid_n", 2.5),
    ("threads", 0), ("threads", True), ("dark_level", 0.0), ("dark_level", "none"),
    ("clip_level", -1.0), ("clip_level", float("nan")), ("max_distance", 0),
    ("read_noise", -0.1), ("gain", "big"), ("max_dropped_lights", -1), ("max_residual", 0),
    ("encoding", "gamma"), ("mesh", "stl"), ("memory_limit_gib", "all"),
    ("memory_limit_gib", 0), ("band", 1), ("colourspace", "ITU-R BT.2020")])  # (colour mode)
def test_bad_option_names_its_field(field, value):
    with pytest.raises(InputError, match=f"^{field}: "):
        Options(**{field: value})


def test_options_replace_and_levels():
    with pytest.raises(InputError, match="unknown option"):
        Options().replace(maxdistance=1)
    with pytest.raises(InputError, match="mesh"):
        Options(height=False, mesh="ply")
    assert Options().with_levels(0.99, 0.002) == Options(clip_level=0.99, dark_level=0.002)
    assert Options(clip_level=None, dark_level=0.1).with_levels(0.99, 0.002) == \
        Options(clip_level=None, dark_level=0.1)
    assert dark_threshold(FLOAT_DARK_LEVEL, 9) == pytest.approx(3 * FLOAT_DARK_LEVEL)
    assert Options(mesh="both").mesh_kinds == ("ply", "obj") and Options().mesh_kinds == ()


def test_array_api_and_keyword_changes_agree():
    lights = synth.ring_lights(5, 40)
    scene, ball = synth.smiley_surface(48), synth.sphere_surface(90, 40)
    args = (synth.render(scene, lights, noise=0.01, seed=1), synth.render(ball, lights),
            colorps.Gauge.from_sphere((90, 90), 44.5, 44.5, 40))
    a = colorps.reconstruct(*args, Options(mode="mono", max_distance=0.05), mask=scene.mask)
    b = colorps.reconstruct(*args, mask=scene.mask, mode="mono", max_distance=0.05)
    np.testing.assert_array_equal(a.normals, b.normals)
    assert a.stats.mode == "mono" and a.stats.max_distance == 0.05
    assert a.stats.dark_threshold == pytest.approx(FLOAT_DARK_LEVEL * np.sqrt(5))
    with pytest.raises(ValueError, match="read-only"):
        a.normals[0, 0] = 0
    with pytest.raises(dataclasses.FrozenInstanceError):
        a.height = None
    z = np.zeros(scene.mask.shape)
    with_z = a.with_height(z, 0.5)
    assert with_z.height is not None and a.height is None
    assert with_z.stats.seconds.integration == 0.5 and a.stats.seconds.integration is None


def test_reasons_are_one_enum():
    assert [int(r) for r in Reason] == list(range(8))
    assert len({r.label for r in Reason}) == len({r.colour for r in Reason}) == 8
    codes = np.array([[0, 1, 2, 3, 7], [4, 5, 6, 6, 7]], dtype=np.uint8)
    picture = reason_picture(codes)
    for r in Reason:
        np.testing.assert_allclose(picture[codes == r][0] * 255, r.colour, atol=1e-4)
    assert reason_counts(codes) == {r.label: 2 if r in (6, 7) else 1 for r in Reason}


def test_sphere_normals_and_angular_error():
    normals, rho = sphere_normals((41, 41), 20.0, 20.0, 15.0)
    inside = rho < 1
    np.testing.assert_allclose(np.linalg.norm(normals[inside], axis=-1), 1, atol=1e-12)
    assert normals[20, 35].tolist() == [1.0, -0.0, 0.0]        # right rim: +x
    assert normals[5, 20].tolist() == [0.0, 1.0, 0.0]          # top rim: +y (y up)
    a = np.array([[1.0, 0, 0], [0, 0, 1], [0, 1, 0]])
    b = np.array([[0, 1.0, 0], [0, 0, 1], [0, -1, 0]])
    np.testing.assert_allclose(angular_error(a, b), [90, 0, 180])
    tilt = np.array([np.sin(0.1), 0, np.cos(0.1)])
    assert angular_error(tilt, [0, 0, 1]) == pytest.approx(np.degrees(0.1))
    assert np.isnan(angular_error([np.nan, 0, 1], [0, 0, 1]))


def test_angular_error_keeps_its_precision_at_small_angles(rng):
    """Identical float32 normals are 0 degrees apart (arccos of their dot product
    had given up to 0.026), and angles of 1e-5 to 1e-1 degrees come out as the
    chord formula 2 asin(|a - b| / 2) gives them, for vectors of any length."""
    normals = rng.normal(size=(100_000, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    assert angular_error(normals, normals).max() == 0.0
    a = rng.normal(size=(1000, 3))
    a /= np.linalg.norm(a, axis=-1, keepdims=True)
    axis = np.cross(a, rng.normal(size=(1000, 3)))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    angle = np.radians(10.0 ** rng.uniform(-5, -1, 1000))
    b = a * np.cos(angle)[:, None] + np.cross(axis, a) * np.sin(angle)[:, None]
    chord = np.degrees(2 * np.arcsin(np.linalg.norm(a - b, axis=-1) / 2))
    np.testing.assert_allclose(angular_error(3.0 * a, 0.5 * b), chord, rtol=1e-6)
    np.testing.assert_allclose(chord, np.degrees(angle), rtol=1e-6)


def test_gauge_and_synthetic_sphere_share_the_formula():
    gauge = colorps.Gauge.from_sphere((60, 60), 29.5, 29.5, 25)
    ball = synth.sphere_surface(60, 25)
    np.testing.assert_allclose(gauge.normals[gauge.mask], ball.normals[gauge.mask], atol=1e-6)


def test_every_sample_file_is_package_data():
    """``pip install .`` ships the demo's sample: every file matches a package-data glob."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    globs = config["tool"]["setuptools"]["package-data"]["colorps.sample"]
    assert "colorps.sample" in config["tool"]["setuptools"]["packages"]
    files = [p.name for p in sample_folder().iterdir() if p.is_file() and p.suffix != ".py"]
    assert len(files) >= 20
    unshipped = [f for f in files if not any(fnmatch.fnmatch(f, g) for g in globs)]
    assert not unshipped


def test_demo_runs_from_any_folder(tmp_path, monkeypatch, capsys):
    from colorps.cli import main

    monkeypatch.chdir(tmp_path)
    assert main(["demo", "--out", "demo-out"]) == 0
    text = capsys.readouterr().out
    assert "42804 of 42804 scene pixels solved" in text
    median = float(text.split("median ")[1].split(",")[0])
    assert median < 0.5  # degrees, against the sample's ground truth
    assert (tmp_path / "demo-out" / "normal.exr").exists()


# ---------------------------------------------------------------- the house
def _package_modules():
    """{module name: path} of every colorps module."""
    package = ROOT / "colorps"
    found = {}
    for path in sorted(package.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        found[name] = path
    return found


def _imports(modules):
    """{module: set of colorps modules it imports}, at any depth of its code
    (function-level imports count: a circle through them is still a circle)."""
    import ast

    graph = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        graph[name] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level:
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
                for candidate in [target] + [f"{target}.{a.name}" for a in node.names]:
                    if candidate in modules and candidate not in (name, "colorps"):
                        graph[name].add(candidate)
    return graph


def test_no_import_circle():
    """Every module can be read after the ones it imports: the graph has no cycle."""
    graph = _imports(_package_modules())
    done, path = set(), []

    def visit(module):
        if module in path:
            raise AssertionError("import circle: " + " -> ".join(path[path.index(module):]
                                                                 + [module]))
        if module in done:
            return
        path.append(module)
        for target in sorted(graph[module]):
            visit(target)
        path.pop()
        done.add(module)

    for module in sorted(graph):
        visit(module)


#: Compiled kernels (private ``_*_kernels.py``) are exempt: their data are
#: grouped in named tuples at the public entry points, their inner functions
#: take scalars for speed. So is the CLI's argument parser.
EXEMPT_FUNCTIONS = {"colorps.cli.build_parser", "colorps.cli._add_options"}
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80  # of code: the docstring does not count
MAX_PARAMETERS = 10


def _is_kernel_module(name):
    return name.rsplit(".", 1)[-1].endswith("_kernels")


def test_modules_and_functions_stay_small():
    import ast

    too_long, too_many = [], []
    for name, path in _package_modules().items():
        if _is_kernel_module(name):
            continue
        text = path.read_text()
        if len(text.splitlines()) > MAX_MODULE_LINES:
            too_long.append(f"{name}: {len(text.splitlines())} lines")
        for node in ast.walk(ast.parse(text)):
            if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            if f"{name}.{node.name}" in EXEMPT_FUNCTIONS:
                continue
            first = node.body[0]
            docstring = (first.end_lineno - first.lineno + 1
                         if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant)
                         and isinstance(first.value.value, str) else 0)
            lines = node.end_lineno - node.lineno + 1 - docstring
            args = node.args
            count = (len(args.posonlyargs) + len(args.args) + len(args.kwonlyargs)
                     + bool(args.vararg) + bool(args.kwarg))
            if args.args and args.args[0].arg in ("self", "cls"):
                count -= 1
            if lines > MAX_FUNCTION_LINES:
                too_long.append(f"{name}.{node.name}: {lines} lines of code")
            if count > MAX_PARAMETERS:
                too_many.append(f"{name}.{node.name}: {count} parameters")
    assert not too_long and not too_many, too_long + too_many


def test_every_warning_is_a_colorps_warning():
    """One base class: ``warnings.simplefilter("ignore", ColorPSWarning)`` silences
    all of colorps's warnings and none of anyone else's."""
    import ast

    offenders = []
    for name, path in _package_modules().items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ClassDef) and any(
                    getattr(base, "id", "").endswith("Warning") for base in node.bases):
                cls = getattr(__import__(name, fromlist=["_"]), node.name)
                if not issubclass(cls, colorps.ColorPSWarning):
                    offenders.append(f"{name}.{node.name}")
            if isinstance(node, ast.Call) and getattr(node.func, "attr", "") == "warn":
                category = node.args[1] if len(node.args) > 1 else None
                if isinstance(category, ast.Name) and category.id in ("UserWarning",
                                                                      "RuntimeWarning"):
                    offenders.append(f"{name}: warns with {category.id}")
    assert not offenders, offenders


def test_the_package_is_ruff_clean():
    """``ruff check colorps`` with the rules of pyproject.toml ([tool.ruff.lint]:
    numpy docstrings for the public API among them) finds nothing."""
    import shutil
    import subprocess
    import sys

    ruff = shutil.which("ruff", path=str(Path(sys.executable).parent)) or shutil.which("ruff")
    if ruff is None:
        pytest.skip("ruff is not installed (pip install -e '.[test]' brings it)")
    found = subprocess.run([ruff, "check", "--no-cache", "colorps"], cwd=ROOT,
                           capture_output=True, text=True)
    assert found.returncode == 0, found.stdout[-3000:]
