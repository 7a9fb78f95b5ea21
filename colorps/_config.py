"""Settings shared by several modules (private): each is stated here once.

``FASTMATH`` is read when numba compiles a kernel. numba's on-disk cache
watches only each kernel's own source file, so after changing it, clear the
``__pycache__`` of colorps (or touch the kernel files), or cached kernels keep
the old flags.
"""

#: LLVM fast-math flags of the compiled kernels (grid lookups, refinement).
#: Reassociation lets LLVM vectorise the dot products; its rounding changes are
#: orders of magnitude below the pruning margins and the noise. No flags that
#: assume finite values: inputs are checked, but inf is used as "no entry yet".
FASTMATH = {"reassoc", "contract"}
#: ``grid_n="auto"`` times its candidate grids on at most this many of the
#: queries (a regular sample of a group's, then a random one of those).
AUTO_N_SAMPLE = 4000
#: Fewest lights a pixel may be matched on (light subsets, shadows): three
#: directions fix a normal.
MIN_LIGHTS = 3
#: Smallest usable gauge sphere radius (pixels).
MIN_RADIUS = 8.0
