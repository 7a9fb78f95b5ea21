"""Where a ``colorps reconstruct`` run spends its time and memory, phase by phase.

Run ``python benchmarks/phases.py [--size 1024]``. It writes the synthetic
capture of ``benchmarks/end_to_end.py`` (8 half-float RGB EXR images, one
coloured light each, noise 0.005, 210 x 210 gauge images, the object mask),
then runs ``colorps reconstruct`` on it with default options, in this process,
with the pipeline's steps wrapped by timers, while a thread samples the
resident memory every 20 ms. It prints a markdown table: each phase's start
and duration (wall seconds from the start of the run) and the peak resident
memory while it ran, and how many cores it kept busy (process CPU seconds
over wall seconds, from the same samples). The height integration runs in a thread beside the
writing of the maps, so those two rows overlap in time.

Start-up (the interpreter and ``import colorps.cli``) is measured apart, in a
fresh process, as a user's run pays it.
"""

from __future__ import annotations

import argparse
import functools
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

#: (module, function, label) of the steps timed, in the order they run (each
#: patched in the module that calls it).
PHASES = (
    ("colorps.pipeline", "read_stack", "read images"),
    ("colorps.pipeline", "find_sphere", "find the gauge sphere"),
    ("colorps.reconstruct", "_setup", "signatures, noise model"),
    ("colorps.reconstruct", "match_pixels", "matching (tables, grids, lookups, subsets)"),
    ("colorps.reconstruct", "_refine", "sub-pixel refinement"),
    ("colorps.reconstruct", "_albedo", "albedo"),
    ("colorps.reconstruct", "_reasons", "reasons"),
    ("colorps.reconstruct", "_misfit_radius", "misfit radius"),
    ("colorps.pipeline", "integrate", "height integration (thread)"),
    ("colorps.outputs", "_write_folder", "write every file"),
    ("colorps.outputs", "write_viewer", "the viewer (within writing)"),
)
#: Resident memory is sampled this often (seconds).
SAMPLE_SECONDS = 0.02


def resident_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2 ** 20


class Recorder:
    """Phase intervals, and the resident memory sampled in a thread."""

    def __init__(self) -> None:
        self.t0 = time.perf_counter()
        self.spans: list[list] = []  # [label, start, stop]
        self.samples: list[tuple[float, float, float]] = []  # (wall s, MiB, CPU s)
        self._stop = threading.Event()
        threading.Thread(target=self._sample, daemon=True).start()

    def _sample(self) -> None:
        while not self._stop.is_set():
            cpu = os.times()
            self.samples.append((time.perf_counter() - self.t0, resident_mib(),
                                 cpu.user + cpu.system))
            time.sleep(SAMPLE_SECONDS)

    def wrap(self, module, name: str, label: str) -> None:
        function = getattr(module, name)

        @functools.wraps(function)
        def timed(*args, **kwargs):
            span = [label, time.perf_counter() - self.t0, None]
            self.spans.append(span)
            try:
                return function(*args, **kwargs)
            finally:
                span[2] = time.perf_counter() - self.t0

        setattr(module, name, timed)

    def peak(self, start: float, stop: float) -> float:
        """The largest sample within the phase, or one sampling period around it
        (a phase shorter than the period falls between samples)."""
        inside = [mib for t, mib, _ in self.samples
                  if start - SAMPLE_SECONDS <= t <= stop + SAMPLE_SECONDS]
        return max(inside) if inside else float("nan")

    def cores(self, start: float, stop: float) -> float:
        """Cores kept busy within the phase: the process's CPU seconds over the
        wall seconds between the samples nearest its start and stop."""
        first = min(self.samples, key=lambda sample: abs(sample[0] - start))
        last = min(self.samples, key=lambda sample: abs(sample[0] - stop))
        return (last[2] - first[2]) / (last[0] - first[0]) if last[0] > first[0] \
            else float("nan")

    def stop(self) -> None:
        self._stop.set()


def start_up_seconds() -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", "import colorps.cli"], check=True)
    return time.perf_counter() - t0


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=1024, help="pixels on a side")
    args = parser.parse_args(argv)
    import importlib

    from colorps.cli import main as colorps

    with tempfile.TemporaryDirectory() as tmp:
        capture = Path(tmp) / "capture"
        subprocess.run([sys.executable, "-m", "colorps.cli", "synth", "--out", str(capture),
                        "--size", str(args.size), "--lights", "colour", "--noise", "0.005",
                        "--gauge-radius", "100"], check=True, capture_output=True)
        start_up = start_up_seconds()
        recorder = Recorder()
        for module, name, label in PHASES:
            recorder.wrap(importlib.import_module(module), name, label)
        code = colorps(["reconstruct", "--scene", str(capture / "scene_*.exr"),
                        "--gauge", str(capture / "gauge_*.exr"), "--sphere", "auto",
                        "--mask", str(capture / "mask.png"), "--out", str(Path(tmp) / "out"),
                        "--quiet"])
        total = time.perf_counter() - recorder.t0
        recorder.stop()
    if code:
        raise SystemExit(f"colorps reconstruct failed (exit code {code})")
    print(f"\n{args.size} x {args.size}, 8 RGB images, 2 cores: start-up "
          f"(python -c 'import colorps.cli') {start_up:.2f} s, then the run {total:.2f} s, "
          f"peak {max(m for _, m, _ in recorder.samples):.0f} MiB resident\n")
    print("| phase | start s | seconds | peak MiB | cores busy |")
    print("|---|---|---|---|---|")
    for label, start, stop in recorder.spans:
        print(f"| {label} | {start:.2f} | {stop - start:.2f} | "
              f"{recorder.peak(start, stop):.0f} | {recorder.cores(start, stop):.1f} |")
    print(f"| the whole run | 0.00 | {total:.2f} | | {recorder.cores(0.0, total):.1f} |")


if __name__ == "__main__":
    main()
