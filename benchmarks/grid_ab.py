"""Same-process A/B timing of the bucket grid against an earlier git revision.

Run ``python benchmarks/grid_ab.py REV`` from a source checkout: it exports
``colorps/`` at REV into a temporary folder as the package ``colorps_ref``,
builds both grids on the same tables and times both on the same queries,
alternating old and new ``--rounds`` times (best and median per case), so
machine load hits both alike. Every result of both is checked against the
other (same nearest distance). Cases follow Table 1 (sphere gauge |T| about
10,000, smiley queries in the pipeline's tile order): mono m = 3 and colour
m = 5 and 30 at theta 10 and 45, with noise sigma 0.005.
"""

from __future__ import annotations

import argparse
import importlib
import io
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from colorps import BucketGrid, compute_signatures, synth  # noqa: E402
from colorps.matching import _tile_order  # noqa: E402


def reference_package(rev: str, folder: Path):
    """Import colorps/ of ``rev`` as the package colorps_ref."""
    blob = subprocess.run(["git", "-C", str(ROOT), "archive", rev, "colorps"],
                          check=True, capture_output=True).stdout
    with tarfile.open(fileobj=io.BytesIO(blob)) as tar:
        tar.extractall(folder, filter="data")
    (folder / "colorps").rename(folder / "colorps_ref")
    sys.path.insert(0, str(folder))
    return importlib.import_module("colorps_ref")


def case(m: int, theta: float, colour: bool, size: int, noise: float, seed: int = 0):
    """(table, queries) like Table 1: sphere gauge r = 57 px, smiley scene queries."""
    rng = np.random.default_rng(seed)
    bands = 3 if colour else 1
    colours = rng.uniform(0.2, 1.0, (m, 3)) if colour else None
    lights = synth.ring_lights(m, theta, colours, bands=bands)
    gauge = synth.sphere_surface(2 * 57 + 6, 57, bands=bands)
    g = compute_signatures(synth.render(gauge, lights), "colour")
    table = g.signatures[g.valid & gauge.mask]
    scene = synth.smiley_surface(size, coloured=colour, bands=bands)
    s = compute_signatures(synth.render(scene, lights, noise=noise, seed=seed), "colour")
    ys, xs = _tile_order(scene.mask & s.valid)
    return np.ascontiguousarray(table), np.ascontiguousarray(s.signatures[ys, xs])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("rev", help="git revision to compare with (e.g. HEAD~3)")
    parser.add_argument("--size", type=int, default=600, help="scene size (px)")
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--threads", type=int, default=None)
    parser.add_argument("--noise", type=float, default=0.005)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        ref = reference_package(args.rev, Path(tmp))
        print(f"grid A/B: reference {args.rev} vs working tree; scene {args.size} px, "
              f"noise {args.noise}, best / median of {args.rounds} alternating rounds\n")
        print("| case | D | queries | ref ns | new ns | new / ref (best) | (median) |")
        print("|---|---|---|---|---|---|---|")
        for m, colour in ((3, False), (5, True), (30, True)):
            for theta in (10, 45):
                table, queries = case(m, theta, colour, args.size, args.noise)
                grids = {"ref": ref.BucketGrid(table), "new": BucketGrid(table)}
                results, times = {}, {k: [] for k in grids}
                for name, grid in grids.items():
                    results[name] = grid.query(queries, threads=args.threads)
                if not np.allclose(results["ref"][1], results["new"][1], rtol=1e-6,
                                   atol=1e-7):
                    raise SystemExit(f"m={m} theta={theta}: distances differ")
                for _ in range(args.rounds):
                    for name, grid in grids.items():
                        t0 = time.perf_counter()
                        grid.query(queries, threads=args.threads)
                        times[name].append((time.perf_counter() - t0) / len(queries) * 1e9)
                best = {k: min(v) for k, v in times.items()}
                med = {k: float(np.median(v)) for k, v in times.items()}
                label = f"{'colour' if colour else 'mono'} m={m} theta={theta}"
                print(f"| {label} | {table.shape[1]} | {len(queries)} | {best['ref']:.0f} | "
                      f"{best['new']:.0f} | {best['new'] / best['ref']:.3f} | "
                      f"{med['new'] / med['ref']:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
