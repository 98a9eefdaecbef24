"""The mesh of a map too large for memory, extracted slab by slab along x.

Why: with the disk archive (:mod:`.block_archive`) a map can hold far more blocks than
``max_blocks`` keeps in memory, up to ``archive_max_mb`` (4 GiB). Reading all of it back to
extract the saved mesh at once would take that much memory on the robot that bounded its map
for a reason. So the mesh is extracted in slabs of whole x-layers of blocks holding at most
``max_blocks`` blocks each, each with one extra layer on both sides, and the parts are joined.

Why the parts join exactly (surface nets on blocks, :mod:`.block_surface`):

* A cell's vertex needs its block and the neighbours on the + side. A slab's own layers and
  the layer before it (whose + neighbours are the slab's first layer, or the layer itself) are
  complete, so every vertex a kept triangle uses is computed as in the whole map.
* A triangle comes from a voxel edge in one block, and its cells lie in that block's x-layer or
  the one before; whichever three of the quad's four cells a triangle takes, one is in the
  edge's own layer. So the largest x-layer among a triangle's cells is its edge's layer: a
  slab keeps the triangles whose largest layer is its own, and each triangle is kept once.
* A vertex is named by its cell (integer voxel coordinates), the same in every slab, and is
  kept by the slab that owns its layer; triangles are joined by those names.

A test compares the result with :func:`.block_surface.block_mesh` of the whole map.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from .block_surface import BlockGrid, block_mesh, block_mesh_cells
from .keys import pack
from .surface import SurfaceMesh, empty_mesh


def slab_mesh(
    coords: torch.Tensor, load: Callable[[torch.Tensor], BlockGrid], max_blocks: int
) -> SurfaceMesh:
    """Surface nets of the blocks at ``coords`` ((B, 3) block coordinates, CPU), reading them
    with ``load(rows)`` (a :class:`BlockGrid` of those rows of ``coords``) a slab at a time, at
    most ``max_blocks`` own blocks a slab (whole x-layers: a layer larger than that is a slab
    of its own)."""
    if coords.shape[0] == 0:
        return empty_mesh()
    layers = coords[:, 0]
    values, counts = torch.unique(layers, return_counts=True)
    slabs = _slabs(values.tolist(), counts.tolist(), max_blocks)
    if len(slabs) == 1:
        return block_mesh(load(torch.arange(coords.shape[0])))
    parts = [_part(coords, load, layers, lo, hi) for lo, hi in slabs]
    return _join(parts)


def _slabs(values: list[int], counts: list[int], max_blocks: int) -> list[tuple[int, int]]:
    """Consecutive x-layer ranges ``[lo, hi)`` of at most ``max_blocks`` blocks (or one layer)."""
    slabs, start, total = [], values[0], 0
    for value, count in zip(values, counts, strict=True):
        if total and total + count > max_blocks:
            slabs.append((start, value))
            start, total = value, 0
        total += count
    slabs.append((start, values[-1] + 1))
    return slabs


def _part(
    coords: torch.Tensor, load: Callable[[torch.Tensor], BlockGrid], layers: torch.Tensor, lo: int, hi: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One slab: its own vertices (their cell keys, positions, colours) and its triangles as
    cell keys."""
    rows = torch.nonzero((layers >= lo - 1) & (layers <= hi)).squeeze(1)
    grid = load(rows)
    mesh, cells = block_mesh_cells(grid)
    if mesh.is_empty:
        return np.zeros(0, np.int64), mesh.vertices, mesh.colours, np.zeros((0, 3), np.int64)
    layer = torch.div(cells[:, 0], grid.block_size, rounding_mode='floor').numpy()
    keys = pack(cells).numpy()
    own = (layer >= lo) & (layer < hi)
    tri = mesh.triangles
    tri_layer = layer[tri].max(axis=1) if len(tri) else np.zeros(0, np.int64)
    kept = tri[(tri_layer >= lo) & (tri_layer < hi)]
    return keys[own], mesh.vertices[own], mesh.colours[own], keys[kept]


def _join(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]) -> SurfaceMesh:
    keys = np.concatenate([p[0] for p in parts])
    if keys.size == 0:
        return empty_mesh()
    vertices = np.concatenate([p[1] for p in parts])
    colours = np.concatenate([p[2] for p in parts])
    order = np.argsort(keys, kind='stable')
    sorted_keys = keys[order]
    tri_keys = np.concatenate([p[3] for p in parts])
    at = np.searchsorted(sorted_keys, tri_keys)
    triangles = order[np.minimum(at, len(order) - 1)].astype(np.int64)
    return SurfaceMesh(vertices, triangles.reshape(-1, 3), colours)
