"""Large arrays on ordinary memory pages while colorps runs.

numpy asks Linux for transparent huge pages (``madvise(MADV_HUGEPAGE)``) for
every array over 4 MiB. Where the kernel then compacts memory to find them at
once (``/sys/kernel/mm/transparent_hugepage/defrag`` set to ``madvise``, the
default of Debian and Ubuntu), each such allocation can stall for
milliseconds, the longer the longer the machine has been up. colorps makes
many short-lived arrays of tens of MiB (grid tables, per-pixel temporaries):
on a 2-core VM a 1 MP, 8-image ``colorps reconstruct`` took 6.8-7.6 s with
huge pages and 5.4-5.7 s without (system time 2.3-2.8 s against 0.6-0.7 s),
and a 612 x 512 capture under 32 lights 29.7 s against 20.9 s; the same run's
grid builds varied 20-fold from one table to the next (docs/benchmarks.md).

The public entry points that run numba's kernels run their bodies ``with
small_pages():`` beside ``one_blas_thread()``. numpy's own switch is
``NUMPY_MADVISE_HUGEPAGE=0`` before it is imported; this does the same for a
while, in a process that imported numpy already, and puts back the setting
from before.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

try:  # numpy's switch (numpy/__init__.py calls it at import)
    from numpy._core.multiarray import _set_madvise_hugepage
except ImportError:  # pragma: no cover - a numpy without it: nothing to switch
    _set_madvise_hugepage = None

__all__ = ["small_pages"]


@contextlib.contextmanager
def small_pages() -> Iterator[None]:
    """A context in which numpy does not ask for huge pages for its arrays."""
    if _set_madvise_hugepage is None:  # pragma: no cover
        yield
        return
    before = _set_madvise_hugepage(False)
    try:
        yield
    finally:
        _set_madvise_hugepage(before)
