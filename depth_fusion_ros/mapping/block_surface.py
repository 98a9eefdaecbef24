"""Surface nets straight on the TSDF's voxel blocks: the mesh of :mod:`.surface`, 10x faster.

:func:`.surface.extract_mesh` takes the observed voxels as a flat list and finds each cell's
eight corners and each quad's four cells by binary search in a sorted key table: 16 lookups
a voxel, and most of the time (``aten::searchsorted`` and the gathers: about 0.35 ms a block
on 2 CPU cores, seconds for a large map). The TSDF stores its voxels in dense blocks of
``n^3`` (``torch_tsdf.py``), so here every corner is a neighbour in the same dense array: each
block is padded with the faces, edges and corner of its seven neighbours on the + side (a
lookup per *block*, not per voxel), the cells are slices of that array, and the quads read the
cell numbers of the block and of its seven neighbours on the - side. Same cells, same
vertices, same quads as :func:`.surface.extract_mesh` (a test checks it), in another order.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import torch

from .keys import SortedKeys, pack
from .surface import TRUNCATED, SurfaceMesh, edge_vertices, empty_mesh, two_triangles


@dataclass
class BlockGrid:
    """The blocks of a TSDF (a copy or a view): what :func:`block_mesh` needs."""

    coords: torch.Tensor  # (B, 3) int64 block coordinates
    tsdf: torch.Tensor  # (B, n^3) float32, local index x n^2 + y n + z
    weight: torch.Tensor  # (B, n^3) float32
    colour: torch.Tensor  # (B, 3, n^3) float32 in [0, 255]
    block_size: int
    voxel_size: float
    min_weight: float

    def rows(self, rows: torch.Tensor) -> BlockGrid:
        """The blocks ``rows`` (a loader of :func:`.slab_surface.slab_mesh` over blocks in memory)."""
        return self._with(*(a[rows] for a in self._arrays()))

    def extended(
        self, coords: torch.Tensor, tsdf: torch.Tensor, weight: torch.Tensor, colour: torch.Tensor
    ) -> BlockGrid:
        """These blocks followed by more (e.g. read back from the map's disk archive)."""
        more = (coords, tsdf, weight, colour)
        return self._with(*(torch.cat((a, b)) for a, b in zip(self._arrays(), more, strict=True)))

    def clone(self) -> BlockGrid:
        """A copy that the map's later integrations cannot change (map_node takes it under its lock)."""
        return self._with(*(a.clone() for a in self._arrays()))

    def _arrays(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        return self.coords, self.tsdf, self.weight, self.colour

    def _with(self, *arrays: torch.Tensor) -> BlockGrid:
        return BlockGrid(*arrays, self.block_size, self.voxel_size, self.min_weight)


def _neighbour_rows(index: SortedKeys, coords: torch.Tensor, offset: tuple[int, int, int]) -> torch.Tensor:
    """Row of each block's neighbour at ``offset`` (in blocks), -1 where there is none."""
    if offset == (0, 0, 0):
        return torch.arange(coords.shape[0], device=coords.device)
    rows, found = index.lookup(pack(coords + torch.tensor(offset, device=coords.device)))
    return torch.where(found, rows, -1)


Step = tuple[int, int, int]


def _neighbours(index: SortedKeys, coords: torch.Tensor, side: int) -> dict[Step, torch.Tensor]:
    """:func:`_neighbour_rows` of the seven neighbours (and the block itself) on the ``side``
    (+1 or -1) of every axis: looked up once, shared by every array padded on that side."""
    return {step: _neighbour_rows(index, coords, step) for step in itertools.product((0, side), repeat=3)}


def _padded(
    values: torch.Tensor, neighbours: dict[Step, torch.Tensor], n: int, side: int, fill: float
) -> torch.Tensor:
    """``values`` (B, n, n, n) with one more layer on the ``side`` (+1 or -1) of every axis,
    taken from the neighbour blocks there (``neighbours``, :func:`_neighbours` of that side;
    ``fill`` where there is none): (B, n+1, n+1, n+1)."""
    b = values.shape[0]
    out = torch.full((b, n + 1, n + 1, n + 1), fill, dtype=values.dtype, device=values.device)
    for step, rows in neighbours.items():
        # Along an axis: the block itself fills n layers; the neighbour, its nearest layer.
        if side > 0:
            dst = tuple(slice(0, n) if s == 0 else slice(n, n + 1) for s in step)
            src = tuple(slice(0, n) if s == 0 else slice(0, 1) for s in step)
        else:
            dst = tuple(slice(1, n + 1) if s == 0 else slice(0, 1) for s in step)
            src = tuple(slice(0, n) if s == 0 else slice(n - 1, n) for s in step)
        ok = rows >= 0
        slab = values[(slice(None), *src)].index_select(0, rows.clamp(min=0))
        shape = (b,) + (1,) * 3
        out[(slice(None), *dst)] = torch.where(ok.view(shape), slab, torch.full_like(slab, fill))
    return out


def block_mesh(grid: BlockGrid, triangles: bool = True) -> SurfaceMesh:
    """Surface-nets mesh of the blocks (voxels with ``min_weight`` or more, ``|tsdf| <`` 0.999).

    ``triangles=False``: the vertices and their colours only (no triangles), for a point cloud
    of the surface (nodes/map_points.py): a quarter of the work less."""
    return block_mesh_cells(grid, triangles)[0]


def block_mesh_cells(grid: BlockGrid, triangles: bool = True) -> tuple[SurfaceMesh, torch.Tensor]:
    """:func:`block_mesh` and the cell of each vertex: the integer voxel coordinates of its
    cell's min corner, (V, 3) int64 (a vertex's identity across extractions of parts of a map,
    mapping/slab_surface.py)."""
    n, dev = grid.block_size, grid.coords.device
    b = grid.coords.shape[0]
    none = torch.zeros((0, 3), dtype=torch.int64)
    if b == 0:
        return empty_mesh(), none
    usable = (grid.weight >= max(grid.min_weight, 1e-9)) & (grid.tsdf.abs() < TRUNCATED)
    t = torch.where(usable, grid.tsdf, math.nan).view(b, n, n, n)
    index = SortedKeys(pack(grid.coords))
    plus = _neighbours(index, grid.coords, +1)
    tp = _padded(t, plus, n, +1, math.nan)  # corners at +1 come from the neighbours
    # Where each padded voxel's colour lives in the storage (row * n^3 + local; -1: none).
    flat = torch.arange(b * n**3, device=dev, dtype=torch.int64).view(b, n, n, n)
    source = _padded(flat, plus, n, +1, -1)
    code = _codes(tp)
    cell, corner_at = _cells(code, n)
    cells = torch.nonzero(cell)  # (C, 4): block, x, y, z (min corner)
    if cells.shape[0] == 0:
        return empty_mesh(), none
    m = n + 1
    base = ((cells[:, 0] * m + cells[:, 1]) * m + cells[:, 2]) * m + cells[:, 3]
    at = base[:, None] + corner_at[None]  # (C, 8) into the padded arrays
    corner_t = tp.view(-1).index_select(0, at.view(-1)).view(at.shape)
    corner_src = source.view(-1).index_select(0, at.view(-1)).view(at.shape)
    local, colours = _vertices(corner_t, corner_src, grid.colour, n)
    voxel = grid.coords[cells[:, 0]] * n + cells[:, 1:]
    vertices = voxel.to(torch.float32) + local
    if triangles:
        ids = torch.full((b, n, n, n), -1, dtype=torch.int64, device=dev)
        ids[cell] = torch.arange(cells.shape[0], device=dev)
        minus = _neighbours(index, grid.coords, -1)
        faces = _quads(tp, code, _padded(ids, minus, n, -1, -1), n, vertices)
    else:
        faces = torch.zeros((0, 3), dtype=torch.int64, device=dev)
    mesh = SurfaceMesh(
        (vertices * grid.voxel_size).cpu().numpy().astype('float32'),
        faces.cpu().numpy().astype('int64'),
        colours.round().clamp(0, 255).to(torch.uint8).cpu().numpy(),
    )
    return mesh, voxel.cpu()


def _corner_offsets(n: int, device: torch.device) -> torch.Tensor:
    """The 8 corners of a cell as offsets into a flattened (n+1)^3 padded block, in the
    corner order of :mod:`.surface` (x fastest: 000, 100, 010, 110, 001, ...)."""
    m = n + 1
    return torch.tensor(
        [dx * m * m + dy * m + dz for dz in (0, 1) for dy in (0, 1) for dx in (0, 1)], device=device
    )


def _codes(tp: torch.Tensor) -> torch.Tensor:
    """One byte a padded voxel: 1 positive, 0 negative, 16 unusable. A sum over up to eight
    voxels is then below 16 only when all are usable, and counts the positive ones: the
    cell and edge tests are byte additions instead of float comparisons over every corner."""
    code = (tp >= 0).to(torch.uint8)
    return code.masked_fill_(torch.isnan(tp), 16)


def _cells(code: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Which cells (min corner in the block) have eight usable corners of both signs."""
    total = None
    for dz, dy, dx in itertools.product((0, 1), repeat=3):
        c = code[:, dx : dx + n, dy : dy + n, dz : dz + n]
        total = c.clone() if total is None else total.add_(c)
    return (total > 0) & (total < 8), _corner_offsets(n, code.device)


def _vertices(
    corner_t: torch.Tensor, corner_src: torch.Tensor, colour: torch.Tensor, n: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Vertex of each cell and its colour (:func:`.surface.edge_vertices`), the corners'
    colours read from the storage through their source index (row * n^3 + local)."""
    v = n**3
    src = corner_src.clamp(min=0)  # every corner of a cell is usable, so it has a source
    flat = colour.reshape(-1)
    red = (src // v) * (3 * v) + src % v
    rgb = torch.stack(
        [flat.index_select(0, (red + c * v).view(-1)).view(src.shape) for c in range(3)], dim=-1
    )
    return edge_vertices(corner_t, rgb)


def _shifted(tp: torch.Tensor, n: int, axis: int) -> torch.Tensor:
    """The voxel one step along ``axis`` from each of the block's own (B, n, n, n)."""
    at = [slice(0, n)] * 3
    at[axis] = slice(1, n + 1)
    return tp[(slice(None), *at)]


def _around(ids: torch.Tensor, e: torch.Tensor, axis: int) -> torch.Tensor:
    """The four cells around the edge from voxel ``e`` (E, 4: block, x, y, z) along ``axis``:
    those at ``v``, ``v - e_b``, ``v - e_b - e_c`` and ``v - e_c`` (E, 4), from ``ids``."""
    b, c = (axis + 1) % 3, (axis + 2) % 3
    blk, p = e[:, 0], [e[:, 1] + 1, e[:, 2] + 1, e[:, 3] + 1]  # ids' index 0 is local -1
    quad = []
    for db, dc in ((0, 0), (1, 0), (1, 1), (0, 1)):
        q = list(p)
        q[b] = q[b] - db
        q[c] = q[c] - dc
        quad.append(ids[blk, q[0], q[1], q[2]])
    return torch.stack(quad, dim=1)


def _quads(
    tp: torch.Tensor, code: torch.Tensor, ids: torch.Tensor, n: int, vertices: torch.Tensor
) -> torch.Tensor:
    """Two triangles for every sign-changing voxel edge whose four cells all have a vertex.

    ``ids`` (B, n+1, n+1, n+1): the vertex of each cell, index 0 along an axis being the
    neighbour's last layer (local -1)."""
    own = code[:, :n, :n, :n]
    triangles = []
    for axis in range(3):
        far = _shifted(tp, n, axis)
        edge = torch.add(own, _shifted(code, n, axis)) == 1  # both usable, one positive
        e = torch.nonzero(edge)  # (E, 4)
        if e.shape[0] == 0:
            continue
        quad = _around(ids, e, axis)
        ok = (quad >= 0).all(dim=1)
        towards_plus = far[e[:, 0], e[:, 1], e[:, 2], e[:, 3]][ok] >= 0
        triangles.append(two_triangles(quad[ok], towards_plus, axis, vertices))
    if not triangles:
        return torch.zeros((0, 3), dtype=torch.int64, device=tp.device)
    return torch.cat(triangles)
