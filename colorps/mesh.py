"""Triangle meshes of height fields, written with trimesh (PLY binary, OBJ)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import InputError, OutputError
from .figures import as_rgb
from .interrupts import interrupts_kept
from .io import atomic_target, srgb_encode

__all__ = ["MESH_FORMATS", "height_mesh", "write_mesh"]

#: Mesh file formats (extensions) that :func:`write_mesh` writes.
MESH_FORMATS = ("ply", "obj")


def height_mesh(height, colours=None):
    """A triangle mesh of a height field, one vertex per pixel inside.

    Vertices are (x, -y, z): columns to the right, rows *up* (so the mesh is
    upright like the camera-space normals), height towards the viewer, all in
    pixel units. Every 2 x 2 block of pixels inside gives two triangles (one
    when only three of its pixels are inside).

    Parameters
    ----------
    height : (H, W) array_like
        Height in pixels, NaN outside.
    colours : (H, W, c) array_like, optional
        Linear albedo; stored sRGB-encoded as 8-bit vertex colours.

    Returns
    -------
    trimesh.Trimesh
    """
    z = np.asarray(height, dtype=np.float64)
    if z.ndim != 2:
        raise InputError(f"height: expected an (H, W) map, got shape {z.shape}")
    inside = np.isfinite(z)
    if inside.sum() < 3:
        raise InputError("height: fewer than 3 pixels inside; nothing to mesh")
    h, w = z.shape
    index = np.full((h, w), -1, dtype=np.int64)
    index[inside] = np.arange(inside.sum())
    rows, cols = np.nonzero(inside)
    vertices = np.stack([cols, -rows, z[inside]], axis=1).astype(np.float64)
    a, b = index[:-1, :-1], index[:-1, 1:]
    c, d = index[1:, :-1], index[1:, 1:]
    faces = []
    full = (a >= 0) & (b >= 0) & (c >= 0) & (d >= 0)
    # Counter-clockwise seen from +z with rows pointing down the image.
    faces.append(np.stack([a[full], c[full], b[full]], axis=1))
    faces.append(np.stack([b[full], c[full], d[full]], axis=1))
    for p, q, r in ((a, c, b), (b, c, d), (a, d, b), (a, c, d)):
        three = ~full & (p >= 0) & (q >= 0) & (r >= 0)
        faces.append(np.stack([p[three], q[three], r[three]], axis=1))
        full = full | three
    faces = np.concatenate(faces)
    vertex_colors = None
    if colours is not None:
        col = as_rgb(np.asarray(colours, dtype=np.float64)[inside])
        vertex_colors = np.round(srgb_encode(col) * 255).astype(np.uint8)
    with interrupts_kept():  # trimesh's "except BaseException" can swallow a Ctrl-C
        import trimesh

        return trimesh.Trimesh(vertices=vertices, faces=faces, vertex_colors=vertex_colors,
                               process=False)


def write_mesh(mesh, path) -> Path:
    """Write a mesh atomically; the format (binary PLY or OBJ) follows the extension."""
    path = Path(path)
    kind = path.suffix.lower().lstrip(".")
    if kind not in MESH_FORMATS:
        raise InputError(f"{path}: mesh format must be one of {MESH_FORMATS}")
    with interrupts_kept():
        data = mesh.export(file_type=kind, **({"encoding": "binary"} if kind == "ply" else
                                             {"include_color": True}))
    try:
        with atomic_target(path) as tmp:
            tmp.write_bytes(data if isinstance(data, bytes) else data.encode())
    except OSError as exc:
        raise OutputError(f"{path}: cannot write mesh ({exc.strerror})") from None
    return path
