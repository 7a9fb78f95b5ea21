"""The memory a run needs, and the tiles that keep it within a limit.

A run holds the scene stack, its working arrays and the whole-image maps; a
scene too large for the memory available runs in bands of rows
(:mod:`colorps.tiles`). :func:`plan_tiles` decides, before any pixel is read,
whether a capture is tiled, in how many rows, and why; it reads the limit
(:func:`memory_limit`: a number, or "auto" from what this process may use,
:func:`available_memory_bytes`, within a container's or job's cgroup limit)
and the memory model (:func:`rows_for_memory`, constants measured below).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from .errors import InputError
from .io import check_decoded_size
from .tables import TABLE_CACHE_MIB

__all__ = [
    "AUTO_MEMORY_FRACTION",
    "DEFAULT_TILE_ROWS",
    "KEPT_GRIDS_SHARE",
    "TilePlan",
    "available_memory_bytes",
    "cgroup_available_bytes",
    "check_input_size",
    "kept_grids_mib",
    "memory_limit",
    "plan_tiles",
    "release_freed_memory",
    "rows_for_memory",
    "tile_rows",
]

#: Share of the memory available at the start of a run that an "auto"
#: ``memory_limit_gib`` lets it use (the rest for the system, other programs
#: and the memory model's error).
AUTO_MEMORY_FRACTION = 0.8
#: Rows per tile when none are given: about 64 MiB of float32 per tile for 8 RGB
#: images of 4096 columns.
DEFAULT_TILE_ROWS = 256

# ---------------------------------------------------------------- memory model
#: Peak memory of a tiled run, measured at 4 and 16 MP (2026-12-02): BASE_MIB
#: for the interpreter, libraries and gauge; while the tiles run, MAP_BYTES per
#: scene pixel for the maps and preview gathered so far, plus TILE_FIXED_MIB and
#: WORKING_BYTES per byte of the tile's float32 input (6.2 measured; 8 leaves a
#: margin); after them FINISH_BYTES per pixel for the integration and the files
#: written (102 measured). A tile has at least MIN_TILE_ROWS rows. An untiled run
#: is the same with the whole scene as its one tile. The grids kept for the
#: tiles (tables.TABLE_CACHE_MIB) come on top while the tiles run.
BASE_MIB = 250
MAP_BYTES = 60
TILE_FIXED_MIB = 300
WORKING_BYTES = 8.0
FINISH_BYTES = 110
MIN_TILE_ROWS = 16
#: An untiled run that solves its scene again and again (the bounced light's
#: passes) keeps the grids of its tables for every solve within this share of
#: what the memory model leaves under the limit (:func:`kept_grids_mib`): 32
#: RGB images of a 40,000-pixel gauge make grids of 42 MiB, 34 of them.
KEPT_GRIDS_SHARE = 0.5


#: Where Linux mounts the control groups whose memory limits a container or a
#: cluster job (Docker, Kubernetes, SLURM) runs under; /proc/meminfo, which
#: psutil reads, knows nothing of them.
CGROUP_ROOT = Path("/sys/fs/cgroup")
#: A cgroup v1 memory limit at or above this many bytes means "no limit".
CGROUP_UNLIMITED = 2 ** 60


def available_memory_bytes() -> int:
    """Memory this process can use now, in bytes.

    The least of: the system's available memory
    (``psutil.virtual_memory().available``: free memory plus caches the system
    can drop), what the control groups the process runs in leave it
    (:func:`cgroup_available_bytes`: a container's or a cluster job's memory
    limit), and inside a Dask worker the worker's own memory limit.
    """
    import sys

    import psutil

    available = psutil.virtual_memory().available
    in_cgroup = cgroup_available_bytes()
    if in_cgroup is not None:
        available = min(available, in_cgroup)
    if "distributed" in sys.modules:  # only a process that uses Dask can be a worker
        from distributed import get_worker

        try:
            worker_limit = get_worker().memory_manager.memory_limit
        except ValueError:  # not in a worker
            worker_limit = None
        if worker_limit:
            available = min(available, int(worker_limit))
    return int(available)


def cgroup_available_bytes(root: Path = CGROUP_ROOT,
                           membership: str | None = None) -> int | None:
    """What the memory limits of this process's control groups leave it, in bytes.

    For the process's cgroup and each of its ancestors that sets a memory
    limit: the limit, less the memory charged to the group, plus the group's
    file cache other than shared memory (which the kernel reclaims before it
    kills, and which psutil's figure counts as available too). The least
    of them; None where no group sets a limit, or on systems without cgroups.

    Parameters
    ----------
    root : Path
        Mount point of the cgroup file systems: cgroup v2 unified at ``root``,
        v1's memory controller at ``root/memory``.
    membership : str, optional
        The text of ``/proc/self/cgroup`` (read from there when None).
    """
    try:
        if membership is None:
            membership = Path("/proc/self/cgroup").read_text()
    except OSError:
        return None
    found = []
    for line in membership.splitlines():
        number, _, rest = line.partition(":")
        controllers, _, group = rest.partition(":")
        if number == "0" and controllers == "":  # cgroup v2
            files = root, "memory.max", "memory.current", ("file", "shmem")
        elif "memory" in controllers.split(","):  # cgroup v1
            files = root / "memory", "memory.limit_in_bytes", "memory.usage_in_bytes", \
                ("total_cache", "total_shmem")
        else:
            continue
        left = _cgroup_tree_available(*files, group.strip().lstrip("/"))
        if left is not None:
            found.append(left)
    return min(found) if found else None


def _cgroup_tree_available(mount: Path, limit_file: str, usage_file: str,
                           cache_keys: tuple[str, str], group: str) -> int | None:
    """The least memory left by the limits of ``group`` and its ancestors under
    ``mount``. Inside a container the group path names the host's hierarchy,
    which the container sees as its ``mount``: then the mount itself is read."""
    folder = mount / group if group and (mount / group).is_dir() else mount
    least = None
    while True:
        try:
            text = (folder / limit_file).read_text().strip()
            limit = None if text == "max" else int(text)
            if limit is not None and limit < CGROUP_UNLIMITED:
                usage = int((folder / usage_file).read_text())
                stat = dict(row.split(" ", 1) for row in
                            (folder / "memory.stat").read_text().splitlines() if " " in row)
                cache, shared = (int(stat.get(key, 0)) for key in cache_keys)
                left = max(limit - usage + max(cache - shared, 0), 0)
                least = left if least is None else min(least, left)
        except (OSError, ValueError):
            pass
        if folder == mount or mount not in folder.parents:
            return least
        folder = folder.parent


def memory_limit(setting: float | str | None) -> tuple[float | None, str]:
    """The memory limit in GiB that ``Options.memory_limit_gib`` means now.

    Returns
    -------
    limit_gib : float or None
        The number given; for "auto", ``AUTO_MEMORY_FRACTION`` of
        :func:`available_memory_bytes`; None for no limit.
    source : str
        How an error message names the limit (``--memory-limit 2 GiB``, or
        the automatic limit with the memory it was taken from).
    """
    if setting is None:
        return None, "no memory limit"
    if setting == "auto":
        available = available_memory_bytes() / 2 ** 30
        limit = AUTO_MEMORY_FRACTION * available
        return limit, (f"--memory-limit auto ({limit:.1f} GiB: {AUTO_MEMORY_FRACTION:.0%} of "
                       f"the {available:.1f} GiB available)")
    return float(setting), f"--memory-limit {setting:g} GiB"


def rows_for_memory(limit_gib: float, shape: tuple[int, int, int, int], *,
                    source: str | None = None) -> int | None:
    """Rows per tile that keep a run of an (m, H, W, c) scene under ``limit_gib``.

    Returns
    -------
    int or None
        None when the whole scene fits untiled.

    Raises
    ------
    InputError
        When even MIN_TILE_ROWS rows would not fit, saying how much is needed
        (and naming the limit as ``source``, default ``--memory-limit ...``).
    """
    source = source or f"--memory-limit {limit_gib:g} GiB"
    m, h, w, c = shape
    mib = 2 ** 20
    limit = limit_gib * 2 ** 30
    finish = BASE_MIB * mib + FINISH_BYTES * h * w
    budget = limit - (BASE_MIB + TILE_FIXED_MIB + TABLE_CACHE_MIB) * mib - MAP_BYTES * h * w
    row_bytes = WORKING_BYTES * 4 * m * c * w
    if finish <= limit and budget >= row_bytes * h:
        return None
    rows = int(budget // row_bytes) if budget > 0 else 0
    if finish > limit or rows < MIN_TILE_ROWS:
        need = max(finish, limit - budget + row_bytes * MIN_TILE_ROWS) / 2 ** 30
        raise InputError(f"{source}: a {w}x{h} capture of {m} "
                         f"images needs about {need:.1f} GiB even in tiles of "
                         f"{MIN_TILE_ROWS} rows (its whole-image maps, height "
                         f"integration and outputs take {finish / 2 ** 30:.1f} GiB)")
    return rows


def kept_grids_mib(limit_gib: float | str | None, shape: tuple[int, int, int, int]) -> float:
    """MiB of grids an untiled run of an (m, H, W, c) scene may keep for its
    solves: TABLE_CACHE_MIB, plus KEPT_GRIDS_SHARE of what the memory model
    leaves under the limit (:func:`memory_limit` of ``limit_gib``; with none,
    of the memory "auto" would give)."""
    limit, _ = memory_limit("auto" if limit_gib is None else limit_gib)
    m, h, w, c = shape
    used = (BASE_MIB + TILE_FIXED_MIB + TABLE_CACHE_MIB) * 2 ** 20 + \
        (MAP_BYTES + WORKING_BYTES * 4 * m * c) * h * w
    return TABLE_CACHE_MIB + KEPT_GRIDS_SHARE * max(0.0, limit * 2 ** 30 - used) / 2 ** 20


@dataclass(frozen=True)
class TilePlan:
    """Whether and how a capture is tiled (see :func:`plan_tiles`).

    Attributes
    ----------
    rows : int or None
        Rows per tile; None for one untiled run.
    why : str or None
        Why it is tiled, as the console and report.json say it.
    limit_gib : float or None
        The memory limit in force (GiB), None for none.
    """

    rows: int | None
    why: str | None
    limit_gib: float | None


def plan_tiles(shape: tuple[int, int, int, int], *, tile: int | None = None,
               memory_limit_gib: float | str | None = "auto",
               scheduler=None) -> TilePlan:
    """Decide how an (m, H, W, c) scene runs: whole, or in tiles of how many rows.

    ``tile`` rows when given; else tiles when the memory limit
    (:func:`memory_limit` of ``memory_limit_gib``) is too small for the whole
    scene (:func:`rows_for_memory`); else, with a Dask ``scheduler``,
    :data:`DEFAULT_TILE_ROWS` (tiles are its tasks); else untiled.
    """
    limit_gib, source = memory_limit(memory_limit_gib)
    if tile is not None:
        return TilePlan(tile, f"--tile {tile}", limit_gib)
    if limit_gib is not None:
        rows = rows_for_memory(limit_gib, shape, source=source)
        if rows is not None:
            return TilePlan(rows, f"{source} is too small for the whole scene", limit_gib)
    if scheduler is not None:
        return TilePlan(DEFAULT_TILE_ROWS, "--scheduler: tiles are its tasks", limit_gib)
    return TilePlan(None, None, limit_gib)


def tile_rows(height: int, tile: int) -> list[tuple[int, int]]:
    """(start, stop) row ranges of ``tile`` rows covering ``height`` rows."""
    if tile < 1:
        raise InputError(f"tile: expected at least 1 row, got {tile}")
    return [(start, min(start + tile, height)) for start in range(0, height, tile)]


def release_freed_memory() -> None:
    """Give memory that numpy has freed back to the system (glibc ``malloc_trim``).

    glibc keeps freed blocks of a few MiB on its heap for reuse: after a tile's
    temporaries are freed the process stays that much larger (57 bytes per
    pixel of a 4 MP run, measured). A no-op where the C library has no
    ``malloc_trim``.
    """
    import ctypes
    import ctypes.util

    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.malloc_trim(0)
    except (OSError, AttributeError):
        pass


def check_input_size(scene_paths, scene_infos, options, plan: TilePlan, *,
                     light_file: bool) -> None:
    """Refuse a scene that would not fit in ``options.max_input_gib`` (GiB) whole
    or a tile at a time (``plan``), or a tiled run that cannot fit its noise or
    finish on the whole scene (``light_file``: a virtual-gauge run)."""
    limit = options.max_input_gib * 2 ** 30
    if plan.rows is None:
        check_decoded_size(scene_infos, limit, name="scene")
        return
    m, info = len(scene_paths), scene_infos[0]
    tile_bytes = 4 * m * info.channels * info.width * min(plan.rows, info.height)
    if tile_bytes > limit:  # one tile's stack is held at a time
        raise InputError(f"{scene_paths[0]}: a tile of {plan.rows} rows of "
                         f"{m} images takes {tile_bytes / 2 ** 30:.1f} GiB, more than "
                         f"--max-input-gib {options.max_input_gib:g}; use fewer rows (--tile)")
    if light_file and "auto" in (options.read_noise, options.gain):
        raise InputError(f"a tiled run ({plan.why}) with --lights needs --read-noise and "
                         "--gain: the noise of a virtual-gauge run is fitted to the whole "
                         "scene at once")
    if light_file and options.brdf == "fitted":
        raise InputError(f"a tiled run ({plan.why}) with --lights needs --brdf lambert: the "
                         "finish of a virtual-gauge run is fitted to the whole scene at once")
