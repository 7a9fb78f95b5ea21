"""Height-map integration: time and peak memory for about 1 megapixel.

Run ``python benchmarks/integration.py``. Each case runs in a fresh process so
that its peak resident memory (ru_maxrss) is its own; the input normals are
made before the baseline is read, so the reported peak is the solver's extra
memory. Times are the best of 3 runs.

Cases: the smiley mask (disk-shaped, about 1.0 MP inside a 1237^2 image), a
two-part non-rectangular mask of the same size, and a full 1024^2 rectangle
with both the Poisson and the DCT solver.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import time

import numpy as np


def case_inputs(name: str):
    from colorps import synth

    if name == "smiley":
        s = synth.smiley_surface(1237)
        return s.normals, s.mask
    if name == "two-part":
        s = synth.smiley_surface(1237)
        mask = s.mask.copy()
        mask[:, 610:630] = False  # cut the face into two separate parts
        return s.normals, mask
    if name == "rectangle":
        s = synth.sphere_surface(1024, 1500)  # a sphere cap covering the image
        return s.normals, None
    raise ValueError(name)


def worker(name: str, method: str) -> dict:
    from colorps import integrate

    normals, mask = case_inputs(name)
    pixels = int(mask.sum()) if mask is not None else normals.shape[0] * normals.shape[1]
    integrate(normals[:64, :64], None if mask is None else mask[:64, :64], method=method)
    base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        integrate(normals, mask, method=method)
        times.append(time.perf_counter() - t0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return dict(case=name, method=method, pixels=pixels, seconds=min(times),
                extra_peak_mb=(peak - base) / 1024)


def main() -> None:
    if len(sys.argv) == 4 and sys.argv[1] == "--worker":
        print(json.dumps(worker(sys.argv[2], sys.argv[3])))
        return
    import numba

    print(f"Machine: {os.cpu_count()} logical cores, numpy {np.__version__}, "
          f"numba {numba.__version__}\n")
    print("| case | method | pixels | seconds (best of 3) | extra peak memory (MB) |")
    print("|---|---|---|---|---|")
    for name, method in (("smiley", "poisson"), ("two-part", "poisson"),
                         ("rectangle", "poisson"), ("rectangle", "dct")):
        out = subprocess.run([sys.executable, __file__, "--worker", name, method],
                             capture_output=True, text=True, check=True)
        r = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"| {r['case']} | {r['method']} | {r['pixels']:,} | {r['seconds']:.2f} "
              f"| {r['extra_peak_mb']:.0f} |", flush=True)


if __name__ == "__main__":
    main()
