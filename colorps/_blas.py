"""BLAS held to one thread while colorps runs.

numpy's BLAS (OpenBLAS in the wheels) starts a thread per core for a large
matrix product, and its threads keep spinning for a while after the call
returns (a busy wait, for the next call). colorps's heavy work runs in numba's
own parallel kernels right after such products (a grid's principal axes, a
finish fit's normal equations), and the spinning threads took the cores from
them: at 1 MP, 8 RGB images on 2 cores, the grid lookups ran 1.5-2x slower and
the whole ``colorps reconstruct`` 5.7-6.8 s instead of 4.8 s; DiLiGenT Ball
with ``--lights`` 23.1 s instead of 18.2 s (docs/benchmarks.md). The products
themselves are small enough that one thread loses nothing measurable.

The public entry points that run numba's kernels (``reconstruct_files``,
``reconstruct``, ``virtual_gauge``, ``fit_scene_brdf``) run their bodies
``with one_blas_thread():``. Not as a decorator: a wrapper's frame would hold
the arguments for the whole call, and ``reconstruct`` lets the scene stack go
once it has the observation vectors (when its caller holds no reference).
"""

from __future__ import annotations

from threadpoolctl import threadpool_limits

__all__ = ["one_blas_thread"]


def one_blas_thread() -> threadpool_limits:
    """A context in which every BLAS library runs one thread (threadpoolctl); the
    limits from before are back when it ends."""
    return threadpool_limits(limits=1, user_api="blas")
