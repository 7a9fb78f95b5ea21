"""What a run will need, loaded in a thread while it reads its images.

A new process pays, at its first numba kernel, for numba's own implementation
modules (its target context's refresh, which also imports scipy's BLAS: about
0.3 s on 2 cores), and, later in the run, for the scipy modules colorps imports
where it uses them (about 0.15 s). Both are Python work under the GIL, but while
they run the main thread mostly decodes images in OpenImageIO, which releases
it. Started at the top of :func:`colorps.pipeline.reconstruct_files`, this took
a 1 MP, 8-image ``colorps reconstruct`` from 4.86 to 4.68 s (median of 5,
docs/benchmarks.md). It changes no result: the same modules are loaded either
way, and numba's compiler lock orders the refresh before any kernel's loading.
"""

from __future__ import annotations

import importlib
import threading

__all__ = ["start_warm_up"]

#: Modules colorps imports where it uses them, in the order a run needs them:
#: the gauge's sphere, the noise model and the refinement (scipy.ndimage), the
#: noise model's fit (scipy.optimize).
LAZY_IMPORTS = ("scipy.ndimage", "scipy.optimize")


def start_warm_up() -> threading.Thread:
    """Start loading numba's implementation and the run's scipy modules in a
    daemon thread; returns the thread (nothing need wait for it)."""
    thread = threading.Thread(target=_warm_up, name="colorps-warm-up", daemon=True)
    thread.start()
    return thread


def _warm_up() -> None:
    try:
        from numba.core.registry import cpu_target

        cpu_target.target_context.refresh()
        for name in LAZY_IMPORTS:
            importlib.import_module(name)
    except Exception:  # (a head start only: the run loads these itself)
        pass
