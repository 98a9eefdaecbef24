"""The zero level set of a sparse TSDF as a triangle mesh, by naive surface nets (vectorised).

Why surface nets and not marching cubes: it needs no 256-case triangle table, is a few
vectorised lookups on torch (CPU or CUDA), and gives a watertight-where-observed mesh with one
vertex per surface cell. A *cell* is the cube whose corners are voxels ``v + {0,1}³``. A cell
whose eight corners are observed and not truncated, and whose corner TSDF values change sign,
gets one vertex: the mean of the zero crossings on its sign-changing edges (linear
interpolation). Every voxel edge with a sign change is shared by four cells; their four
vertices make a quad (two triangles), oriented so the normal points to positive TSDF (free
space, towards the cameras that saw it).

Truncated values (|tsdf| = 1) carry no position, and a sign change between them is the back
of an observed surface or an occlusion edge, not a surface: such corners make no cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .keys import SortedKeys, pack

#: |tsdf| at or above this counts as truncated (no surface position).
TRUNCATED = 0.999

_CORNERS = torch.tensor(
    [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]]
)
#: The 12 cube edges as pairs of corner indices into ``_CORNERS``.
_EDGES = torch.tensor(
    [[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]]
)


@dataclass
class VoxelSet:
    """Observed voxels of a map: integer grid coordinates (voxel centre = coords * voxel_size)."""

    coords: torch.Tensor  # (N, 3) int64
    tsdf: torch.Tensor  # (N,) float32 in [-1, 1]
    colour: torch.Tensor  # (N, 3) float32 in [0, 255]
    voxel_size: float


@dataclass
class SurfaceMesh:
    """A triangle mesh in the world frame (numpy, metres); ``colours`` uint8 RGB per vertex."""

    vertices: np.ndarray  # (V, 3) float32
    triangles: np.ndarray  # (T, 3) int64
    colours: np.ndarray  # (V, 3) uint8

    @property
    def is_empty(self) -> bool:
        return len(self.vertices) == 0


def empty_mesh() -> SurfaceMesh:
    return SurfaceMesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int64), np.zeros((0, 3), np.uint8))


def extract_mesh(voxels: VoxelSet) -> SurfaceMesh:
    """Surface-nets mesh of ``voxels`` (see the module docstring)."""
    t = voxels.tsdf
    usable = t.abs() < TRUNCATED
    coords, t, colour = voxels.coords[usable], t[usable], voxels.colour[usable]
    if coords.shape[0] < 8:
        return empty_mesh()
    dev = coords.device
    index = SortedKeys(pack(coords))
    corners = _CORNERS.to(dev)
    # Cells: one per usable voxel taken as the cell's minimum corner.
    rows, found = index.lookup(pack(coords[:, None, :] + corners[None]))  # (N, 8)
    complete = found.all(dim=1)
    ct = t[rows]  # (N, 8) corner TSDF
    positive = ct >= 0
    cell = complete & positive.any(dim=1) & (~positive).any(dim=1)
    cell_ids = torch.nonzero(cell, as_tuple=True)[0]
    if cell_ids.numel() == 0:
        return empty_mesh()
    vertices, colours = _cell_vertices(coords, t, colour, rows[cell_ids], corners)
    triangles = _quads(coords, t, cell_ids, index, vertices)
    return SurfaceMesh(
        (vertices * voxels.voxel_size).cpu().numpy().astype(np.float32),
        triangles.cpu().numpy().astype(np.int64),
        colours.round().clamp(0, 255).to(torch.uint8).cpu().numpy(),
    )


def _cell_vertices(
    coords: torch.Tensor, t: torch.Tensor, colour: torch.Tensor, rows: torch.Tensor, corners: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Vertex of each cell (voxel units): its corners gathered, then :func:`edge_vertices`."""
    local, colours = edge_vertices(t[rows], colour[rows])
    return coords[rows[:, 0]].to(torch.float32) + local, colours


def edge_vertices(corner_t: torch.Tensor, corner_rgb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each cell's vertex (voxel units from its minimum corner) and colour from its eight
    corners' TSDF (C, 8) and colour (C, 8, 3), in ``_CORNERS`` order: the mean zero crossing of
    its sign-changing edges, the colour interpolated alike (also mapping/block_surface.py)."""
    dev = corner_t.device
    edges, corners = _EDGES.to(dev), _CORNERS.to(dev)
    ta, tb = corner_t[:, edges[:, 0]], corner_t[:, edges[:, 1]]  # (C, 12)
    crossing = (ta >= 0) != (tb >= 0)
    frac = torch.where(crossing, ta / (ta - tb).where(crossing, torch.ones_like(ta)), torch.zeros_like(ta))
    pa = corners[edges[:, 0]].to(torch.float32)  # (12, 3)
    pb = corners[edges[:, 1]].to(torch.float32)
    points = pa[None] + frac[..., None] * (pb - pa)[None]  # (C, 12, 3)
    count = crossing.sum(dim=1, keepdim=True).clamp(min=1).to(torch.float32)
    local = (points * crossing[..., None]).sum(dim=1) / count
    ca, cb = corner_rgb[:, edges[:, 0]], corner_rgb[:, edges[:, 1]]  # (C, 12, 3)
    cmix = ca + frac[..., None] * (cb - ca)
    colours = (cmix * crossing[..., None]).sum(dim=1) / count
    return local, colours


def two_triangles(
    quad: torch.Tensor, towards_plus: torch.Tensor, axis: int, vertices: torch.Tensor
) -> torch.Tensor:
    """The two triangles of each quad (four vertex indices around a sign-changing edge along
    ``axis``), oriented towards positive TSDF when ``towards_plus`` (also block_surface.py)."""
    tri = torch.cat((quad[:, [0, 1, 2]], quad[:, [0, 2, 3]]), dim=0)
    return _orient(tri, torch.cat((towards_plus, towards_plus)), axis, vertices)


def _quads(
    coords: torch.Tensor, t: torch.Tensor, cell_ids: torch.Tensor, index: SortedKeys, vertices: torch.Tensor
) -> torch.Tensor:
    """Triangles (indices into the cell vertices) for every sign-changing voxel edge."""
    dev = coords.device
    cells = SortedKeys(pack(coords[cell_ids]))
    triangles = []
    for axis in range(3):
        b, c = (axis + 1) % 3, (axis + 2) % 3
        step = torch.zeros(3, dtype=torch.int64, device=dev)
        step[axis] = 1
        rows, found = index.lookup(pack(coords + step))
        ta, tb = t, t[rows]
        edge = found & ((ta >= 0) != (tb >= 0))
        e = torch.nonzero(edge, as_tuple=True)[0]
        if e.numel() == 0:
            continue
        eb = torch.zeros(3, dtype=torch.int64, device=dev)
        eb[b] = 1
        ec = torch.zeros(3, dtype=torch.int64, device=dev)
        ec[c] = 1
        base = coords[e]
        around = torch.stack((base, base - eb, base - eb - ec, base - ec), dim=1)  # (E, 4, 3)
        quad, ok = cells.lookup(pack(around))
        ok = ok.all(dim=1)
        quad = quad[ok]
        # Normal towards positive TSDF: +axis when the far end is the positive one.
        triangles.append(two_triangles(quad, tb[e][ok] >= 0, axis, vertices))
    if not triangles:
        return torch.zeros((0, 3), dtype=torch.int64, device=dev)
    return torch.cat(triangles)


def _orient(tri: torch.Tensor, towards_plus: torch.Tensor, axis: int, vertices: torch.Tensor) -> torch.Tensor:
    """Reorder each triangle so its normal's ``axis`` component has the wanted sign."""
    p = vertices[tri]
    normal = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    wrong = (normal[:, axis] >= 0) != towards_plus
    return torch.where(wrong[:, None], tri[:, [0, 2, 1]], tri)


def surface_points(mesh: SurfaceMesh) -> tuple[np.ndarray, np.ndarray]:
    """Points and colours of the surface (the mesh vertices: about one per surface voxel)."""
    return mesh.vertices, mesh.colours
