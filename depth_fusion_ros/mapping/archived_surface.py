"""The surface of a bounded map's archived blocks, kept as points for the published cloud.

A map larger than ``map.max_blocks`` moves its farthest blocks to a disk archive
(:mod:`.block_archive`). The saved mesh and the map file read them back, but the published
cloud (nodes/map_points.py) was extracted from the blocks in memory only: the map around the
camera, the rest of the building gone from RViz. Extracting the whole map at every
publication would read the whole archive each time. So the surface of each archived block is
extracted once, when it is first seen archived (or archived again after it came back and
changed: :meth:`.BlockArchive.versions`), and its points are kept here; a block back in memory
is dropped from here (the blocks in memory are extracted at each publication, as before).

Surface nets take the corners of a block's cells on its +x, +y and +z faces from the
neighbouring blocks, so a block is extracted with its neighbours (archived or in memory) and
only the vertices of its own cells are kept: the points the whole map's mesh has there, a
block at a time. The blocks in memory are extracted with their archived neighbours too
(:func:`resident_surface`), so the cloud has no seam where the two meet. Bounded: past
``max_points`` every second point of every block is dropped (``thinned`` counts the halvings,
and the blocks that come later keep the same share), since the published cloud is cut to
``points_max`` points anyway.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from .block_surface import BlockGrid, block_mesh, block_mesh_cells
from .keys import SortedKeys, pack, unpack
from .surface import SurfaceMesh

#: The +1 neighbours whose voxels a block's cells on its upper faces read.
_UPPER = torch.tensor([(x, y, z) for x in (0, 1) for y in (0, 1) for z in (0, 1) if (x, y, z) != (0, 0, 0)])


@dataclass
class Pending:
    """What one publication reads under the map's lock: the archived blocks to extract now
    (``keys``, their archive writes) and every archived block the extraction reads (them, their
    archived neighbours, and the archived neighbours of the blocks in memory)."""

    keys: torch.Tensor  # (N,) packed keys of the archived blocks extracted now
    versions: list[int]
    read: BlockGrid  # the archived blocks read


@dataclass
class ArchivedSurface:
    """Surface points per archived block (see module)."""

    max_points: int
    #: packed key -> (archive write it was extracted from, xyz (P, 3) float32, rgb (P, 3) uint8)
    blocks: dict[int, tuple[int, np.ndarray, np.ndarray]] = field(default_factory=dict)
    #: Halvings of every block's points to stay within ``max_points``.
    thinned: int = 0
    points: int = 0
    #: The archive the points came from (another one: a rebuilt or cleared map, start over).
    source: object | None = None

    def plan(
        self,
        source: object,
        versions: dict[int, int],
        read: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor, torch.Tensor]] | None,
        resident: BlockGrid,
        limit: int,
    ) -> Pending | None:
        """Under the map's lock: forget the blocks no longer archived (or of another archive),
        and read up to ``limit`` archived blocks not extracted yet with what their extraction
        and that of the blocks in memory (``resident``) read (``read``: the archive's voxels of
        block coordinates). None: nothing archived."""
        if source is not self.source:
            self.blocks.clear()
            self.points, self.thinned, self.source = 0, 0, source
        for key in [k for k in self.blocks if k not in versions]:
            self._drop(key)
        if not versions or read is None:
            return None
        todo = [k for k, v in versions.items() if self.blocks.get(k, (None,))[0] != v][:limit]
        keys = torch.tensor(todo, dtype=torch.int64)
        archived = torch.tensor(list(versions), dtype=torch.int64)
        near = torch.cat((_upper(unpack(keys)), _upper(resident.coords.cpu())))
        near = near[torch.isin(near, archived) & ~torch.isin(near, keys)]
        every = unpack(torch.cat((keys, near)))
        grid = BlockGrid(every, *read(every), resident.block_size, resident.voxel_size, resident.min_weight)
        return Pending(keys, [versions[k] for k in todo], grid)

    def extract(self, pending: Pending, resident: BlockGrid) -> None:
        """Outside the lock: the surface of the pending archived blocks (their neighbours in
        memory taken from ``resident``, a copy of the blocks in memory), kept per block."""
        if pending.keys.numel() == 0:
            return
        mine = pending.read.coords[: pending.keys.numel()]
        rows, found = SortedKeys(pack(resident.coords.cpu())).lookup(_upper(mine))
        grid = _joined(pending.read, resident.rows(rows[found].unique().to(resident.coords.device)))
        mesh, owner = _vertices(grid)
        # The vertices grouped by their block in one sort (not a pass over all of them per block).
        order = np.argsort(owner, kind='stable')
        keys = pending.keys.numpy()
        grouped = owner[order]
        starts = np.searchsorted(grouped, keys, side='left')
        ends = np.searchsorted(grouped, keys, side='right')
        stride = 2**self.thinned
        for key, version, a, b in zip(keys.tolist(), pending.versions, starts, ends, strict=True):
            at = order[a:b:stride]
            self._drop(key)
            self.blocks[key] = (version, mesh.vertices[at], mesh.colours[at])
            self.points += len(at)
        while self.points > self.max_points:
            self._thin()

    def cloud(self) -> tuple[np.ndarray, np.ndarray]:
        """Every kept point: xyz (P, 3) float32 and rgb (P, 3) uint8."""
        if not self.blocks:
            return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.uint8)
        parts = list(self.blocks.values())
        return np.concatenate([p[1] for p in parts]), np.concatenate([p[2] for p in parts])

    def _drop(self, key: int) -> None:
        gone = self.blocks.pop(key, None)
        if gone is not None:
            self.points -= len(gone[1])

    def _thin(self) -> None:
        self.thinned += 1
        self.blocks = {k: (v, xyz[::2], rgb[::2]) for k, (v, xyz, rgb) in self.blocks.items()}
        self.points = sum(len(p[1]) for p in self.blocks.values())


def resident_surface(resident: BlockGrid, pending: Pending | None) -> SurfaceMesh:
    """The surface points of the blocks in memory, their cells on the faces toward archived
    blocks completed from those (read in ``pending``): the whole map's vertices there."""
    if pending is None or pending.read.coords.shape[0] == 0:
        return block_mesh(resident, triangles=False)
    border = torch.isin(pack(pending.read.coords.cpu()), _upper(resident.coords.cpu()))
    if not bool(border.any()):
        return block_mesh(resident, triangles=False)
    rows = torch.nonzero(border).squeeze(1).to(pending.read.coords.device)
    mesh, owner = _vertices(_joined(resident, pending.read.rows(rows)))
    keep = np.isin(owner, pack(resident.coords.cpu()).numpy())
    return SurfaceMesh(mesh.vertices[keep], np.zeros((0, 3), np.int64), mesh.colours[keep])


def _vertices(grid: BlockGrid) -> tuple[SurfaceMesh, np.ndarray]:
    """The surface vertices of ``grid`` and the packed key of the block each one's cell is in."""
    mesh, cells = block_mesh_cells(grid, triangles=False)
    return mesh, pack(torch.div(cells, grid.block_size, rounding_mode='floor')).numpy()


def _joined(a: BlockGrid, b: BlockGrid) -> BlockGrid:
    device = a.coords.device
    return a.extended(*(x.to(device) for x in (b.coords, b.tsdf, b.weight, b.colour)))


def _upper(coords: torch.Tensor) -> torch.Tensor:
    """Packed keys of the +1 neighbours of blocks ``coords`` (N, 3), each once."""
    return pack((coords[:, None, :] + _UPPER[None]).reshape(-1, 3)).unique()
