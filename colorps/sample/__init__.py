"""The bundled sample capture with ground truth, ``colorps demo`` which reads it, and
``colorps synth``'s folders of captures like it.

The files of this folder (see its README.md) are installed with the package,
so the demo runs from any install and any working folder.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import InputError
from ..geometry import angular_error
from ..options import Options

if TYPE_CHECKING:
    from ..synth import SyntheticCapture

__all__ = ["DemoReport", "run_demo", "sample_folder", "write_synthetic_folder"]


def sample_folder() -> Path:
    """The installed folder holding the sample's files."""
    return Path(str(resources.files(__name__)))


@dataclass(frozen=True)
class DemoReport:
    """Accuracy of a demo run against the sample's ground truth.

    Attributes
    ----------
    solved, pixels : int
        Object pixels solved, of all object pixels of the truth mask.
    normal_error_deg : (mean, median, 95th percentile), degrees
    albedo_error : tuple of float
        Median relative albedo error per band.
    height_rms_px, relief_px : float or None
        RMS height error (zero-mean over the solved pixels) and the true
        relief depth, pixels; None without a height map.
    """

    solved: int
    pixels: int
    normal_error_deg: tuple[float, float, float]
    albedo_error: tuple[float, ...]
    height_rms_px: float | None
    relief_px: float | None

    def lines(self, mode: str, out) -> list[str]:
        """The demo's printed summary."""
        mean, median, p95 = self.normal_error_deg
        text = [f"colorps demo ({mode} mode): {self.solved} of {self.pixels} scene pixels "
                "solved",
                f"  normal error (deg): mean {mean:.3f}, median {median:.3f}, "
                f"95th percentile {p95:.3f}",
                "  albedo relative error, median per band: "
                + ", ".join(f"{e:.2%}" for e in self.albedo_error)]
        if self.height_rms_px is not None:
            text.append(f"  height RMS error {self.height_rms_px:.2f} px "
                        f"({self.height_rms_px / self.relief_px:.2%} of the "
                        f"{self.relief_px:.1f} px relief)")
        text.append(f"  outputs in {out}/ (normal.exr, albedo.exr, quality.exr, "
                    "report.json, ...)")
        text.append(f"  look at them: colorps view {out}  (or open {out}/index.html)")
        return text


def run_demo(out, data=None, mode: str = "colour", overwrite: bool = False, *,
             progress: bool = True, options: Options | None = None):
    """Reconstruct a sample capture and measure it against its ground truth.

    Parameters
    ----------
    out : str or Path
        Output folder.
    data : str or Path, optional
        A folder made by ``colorps synth`` (default: the bundled sample).
    mode : {"colour", "mono"}
    overwrite, progress : bool
    options : Options, optional
        Settings (default ``Options(mode=mode)``).

    Returns
    -------
    (Reconstruction, DemoReport)
    """
    from ..inputs import CaptureFiles
    from ..io import read_image, read_mask
    from ..pipeline import reconstruct_files

    folder = Path(data) if data is not None else sample_folder()
    info_path = folder / "sample.json"
    if not info_path.exists():
        raise InputError(f"{info_path}: not a sample folder (make one with "
                         "'colorps synth --out DIR')")
    info = json.loads(info_path.read_text())
    g = info["gauge_sphere"]
    mask = folder / "mask.png"
    ext = {"exr": "exr", "png8": "png"}[info.get("file_format", "exr")]
    inputs = CaptureFiles(str(folder / f"scene_*.{ext}"), gauge=str(folder / f"gauge_*.{ext}"),
                          sphere=(g["cx"], g["cy"], g["r"]), gauge_albedo=info["gauge_albedo"],
                          mask=mask if mask.exists() else None)
    result = reconstruct_files(inputs, out, options=options or Options(mode=mode),
                               overwrite=overwrite, progress=progress)
    truth_n, _ = read_image(folder / "truth_normal.exr")
    truth_a, _ = read_image(folder / "truth_albedo.exr")
    truth_mask = read_mask(folder / "truth_mask.png", truth_n.shape[:2])
    ok = truth_mask & result.solved
    err = angular_error(result.normals[ok], truth_n[ok])
    rel = np.abs(result.albedo[ok] / truth_a[ok] - 1)
    rms = relief = None
    truth_height = folder / "truth_height.exr"
    if result.height is not None and truth_height.exists():
        z_true = read_image(truth_height)[0][..., 0]
        both = ok & np.isfinite(result.height)
        diff = (result.height[both] - result.height[both].mean()) - \
            (z_true[both] - z_true[both].mean())
        rms = float(np.sqrt(np.mean(diff ** 2)))
        relief = float(np.ptp(z_true[both]))
    report = DemoReport(
        solved=int(ok.sum()), pixels=int(truth_mask.sum()),
        normal_error_deg=(float(err.mean()), float(np.median(err)),
                          float(np.percentile(err, 95))),
        albedo_error=tuple(float(np.median(rel[:, k])) for k in range(rel.shape[1])),
        height_rms_px=rms, relief_px=relief)
    return result, report


def write_synthetic_folder(out: str | Path, capture: SyntheticCapture,
                           overwrite: bool = False) -> dict:
    """``colorps synth``: render ``capture`` (a :class:`colorps.synth.SyntheticCapture`)
    and write its files (:func:`colorps.synth.write_synthetic`) into ``out``, all
    together or not at all (:func:`colorps.outputs.write_folder`).

    Raises
    ------
    OutputError
        ``out`` is not a folder to write, or already holds such files and not
        ``overwrite``, before anything is rendered.
    InputError
        Rendering it would need more memory than is available.

    Returns
    -------
    dict
        The content of its sample.json.
    """
    from ..memory import available_memory_bytes
    from ..outputs import prepare_output_dir, write_folder
    from ..synth import synthetic_files

    prepare_output_dir(out, overwrite=overwrite, files=["sample.json", "mask.png"])
    needed, available = capture.bytes_needed(), available_memory_bytes()
    if needed > available:
        raise InputError(f"synth: a {capture.size} px scene and a gauge of radius "
                         f"{capture.gauge_radius:g} px under {capture.images} lights need "
                         f"about {needed / 2 ** 30:.1f} GiB to render; "
                         f"{available / 2 ** 30:.1f} GiB is available")
    files, info = synthetic_files(capture)
    write_folder(out, files, overwrite=overwrite, replaces=_earlier_capture(out))
    return info


#: The files of a folder ``colorps synth`` wrote.
_CAPTURE_FILE = re.compile(r"(scene|gauge)_\d+\.(exr|png)|truth_\w+\.(exr|png)|mask\.png|"
                           r"sample\.json")


def _earlier_capture(out):
    """``replaces(name)`` of :func:`colorps.outputs.write_folder` for a folder holding
    an earlier ``colorps synth`` capture (its sample.json says so): its files, all
    of them replaced (a capture of more images leaves none behind); else None."""
    try:
        made = json.loads((Path(out) / "sample.json").read_text()).get("made_by")
    except (OSError, ValueError, AttributeError):
        return None
    return (lambda name: _CAPTURE_FILE.fullmatch(name) is not None) \
        if made == "colorps synth" else None
