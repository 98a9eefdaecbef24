"""A compact sparse TSDF in torch: bounded voxel blocks, confidence-weighted integration.

Why our own: the library TSDF (Open3D) is an optional 300 MB install with a large dependency
tree and no per-pixel weights; this one is ~200 lines of torch, runs on CUDA wherever torch
does, and weights every pixel by the fused confidence (docs/mapping.md has the measurements).

Layout: voxel blocks of ``block_size``³ voxels, allocated where depth is observed. Block ``b``
holds rows ``b`` of ``tsdf``/``weight`` (``(capacity, block_size³)``) and ``colour``
(``(capacity, 3, block_size³)``, one plane per channel so the colour update is three
contiguous passes, not a stride-3 one); the block coordinates are looked up by binary search
in a sorted key table (:mod:`.keys`). Voxel ``i`` of the integer grid has its centre at
``i * voxel_size`` in the world frame.

Integration of one keyframe (projective TSDF, as KinectFusion / Open3D):

1. allocate the blocks around every observed surface point (``± truncation`` along the ray);
2. project the voxels of those blocks into the depth image (nearest pixel);
3. ``sdf = depth - z``; voxels with ``sdf > -truncation`` get ``tsdf = min(1, sdf/truncation)``
   averaged with weight = pixel confidence to ``confidence_power`` over its depth to
   ``depth_power`` (capped at ``max_weight``).

Cost (docs/mapping.md has the profile): on a CPU the per-element work is cheap and what costs
is the irregular work, so the voxels are gathered and written with ``index_select`` and
``scatter_`` (several times faster than advanced indexing, ``index_put_`` or ``index_copy_``
here, and free of their multi-thread slowdown), the image lookups go to a zero-bordered copy of
each image (a voxel outside the image, or behind the camera, reads the border: weight 0) so one
``nonzero`` picks the updated voxels, and the blocks a keyframe touches are deduplicated by
marking a dense grid over their bounding box, not by sorting. Every step is a torch op, the
same on CPU and CUDA.

Memory is bounded by ``max_blocks``: when a keyframe needs more blocks than are free, the
blocks farthest from its camera are evicted (counted in ``evicted_blocks``) to the disk archive
(:mod:`.block_archive`, ``archive``), which gives them back when a keyframe needs them again:
``mesh`` and ``whole_map`` are the whole map, archived blocks included.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F  # noqa: N812  (the conventional alias)

from ..camera import PinholeCamera
from ..true_indices import true_indices
from .block_archive import BlockArchive
from .block_surface import BlockGrid, block_mesh
from .config import MapConfig
from .keys import SortedKeys, pack, unpack
from .slab_surface import slab_mesh
from .surface import SurfaceMesh, VoxelSet

log = logging.getLogger(__name__)

#: Initial block capacity; doubled as needed up to ``max_blocks``.
INITIAL_CAPACITY = 256
#: Blocks moved to the archive at a time when a map larger than ``max_blocks`` is loaded
#: (10 MiB at 8³ voxels).
LOAD_CHUNK = 1024

#: An image as numpy (the node, the evaluation) or as a tensor already on the map's device
#: (the consistency test hands its masked depth over without a round trip through the host).
Image = np.ndarray | torch.Tensor


class TorchTSDF:
    """Sparse block TSDF on a torch device. ``integrate`` per keyframe, ``mesh`` to extract."""

    name = 'torch'
    #: ``integrate`` takes tensors on ``config.device`` as well as numpy (the consistency test
    #: hands its masked depth over as a tensor).
    accepts_tensors = True

    def __init__(self, config: MapConfig) -> None:
        self.config = config.validate()
        self.device = torch.device(config.device)
        self.voxel = float(config.voxel_size)
        self.trunc = float(config.truncation_m)
        n = config.block_size
        self.block_voxels = n**3
        local = torch.stack(
            torch.meshgrid(torch.arange(n), torch.arange(n), torch.arange(n), indexing='ij'), dim=-1
        )
        #: (block_size³, 3) voxel offsets inside a block.
        self.local = local.reshape(-1, 3).to(self.device)
        self._local_metric = self.local.to(torch.float32) * self.voxel
        self.n_blocks = 0
        self.evicted_blocks = 0
        #: Blocks keyframes needed beyond ``max_blocks`` on their own (left out of those keyframes).
        self.skipped_blocks = 0
        self.integrated = 0
        #: Where evicted blocks go (None: ``archive`` off, they are dropped).
        self.archive = (
            BlockArchive(self.block_voxels, config.archive_dir, config.archive_max_mb * 2**20)
            if config.archive
            else None
        )
        self._dropped = 0
        #: World position of the last keyframe's camera (saved with the map: a map larger than
        #: ``max_blocks`` is loaded around it).
        self.camera_position: np.ndarray | None = None
        self._allocate_storage(min(INITIAL_CAPACITY, config.max_blocks))
        self._index = SortedKeys(self.block_coords[:0].new_zeros((0,)))

    # --- storage ----------------------------------------------------------------------------------

    def _allocate_storage(self, capacity: int) -> None:
        dev, v = self.device, self.block_voxels
        self.block_coords = torch.zeros((capacity, 3), dtype=torch.int64, device=dev)
        self.tsdf = torch.ones((capacity, v), dtype=torch.float32, device=dev)
        self.weight = torch.zeros((capacity, v), dtype=torch.float32, device=dev)
        self.colour = torch.zeros((capacity, 3, v), dtype=torch.float32, device=dev)

    def _grow(self, needed: int) -> None:
        capacity = self.block_coords.shape[0]
        if needed <= capacity:
            return
        new_capacity = min(self.config.max_blocks, max(needed, 2 * capacity))
        old = (self.block_coords, self.tsdf, self.weight, self.colour)
        self._allocate_storage(new_capacity)
        n = self.n_blocks
        for dst, src in zip((self.block_coords, self.tsdf, self.weight, self.colour), old, strict=True):
            dst[:n] = src[:n]

    def _keep(self, rows: torch.Tensor) -> None:
        """Keep only blocks ``rows`` (compacted to the front), e.g. after an eviction."""
        k = rows.numel()
        for arr in (self.block_coords, self.tsdf, self.weight, self.colour):
            arr[:k] = arr[rows].clone()
        self.tsdf[k : self.n_blocks] = 1.0
        self.weight[k : self.n_blocks] = 0.0
        self.colour[k : self.n_blocks] = 0.0
        self.n_blocks = k

    def load_blocks(
        self,
        coords: torch.Tensor,
        tsdf: torch.Tensor,
        weight: torch.Tensor,
        colour: torch.Tensor,
        centre: np.ndarray | None = None,
    ) -> None:
        """Replace the map by these blocks (a saved map: mapping/map_file.py). More than
        ``max_blocks``: the ones nearest ``centre`` (the world origin by default) are held in
        memory and the rest go to the archive (``ValueError`` without one)."""
        n, v = int(coords.shape[0]), self.block_voxels
        shapes = (tuple(coords.shape), tuple(tsdf.shape), tuple(weight.shape), tuple(colour.shape))
        if shapes != ((n, 3), (n, v), (n, v), (n, 3, v)):
            raise ValueError(
                f'blocks do not match: coords {tuple(coords.shape)}, tsdf {tuple(tsdf.shape)}, '
                f'weight {tuple(weight.shape)}, colour {tuple(colour.shape)} for {v} voxels a block'
            )
        cap = self.config.max_blocks
        if n > cap and self.archive is None:
            raise ValueError(f'{n} blocks, more than max_blocks={cap} (and map.archive is off)')
        if self.archive is not None:
            self.archive.close()  # the map is replaced: what was archived goes with it
        if n > cap:
            where = torch.zeros(3) if centre is None else torch.as_tensor(centre, dtype=torch.float32)
            order = torch.argsort(self._block_distance(coords.cpu(), where))
            # The rest to the archive a part at a time: the blocks may be a map file's, read from
            # disk as they are indexed (mapping/map_file.py), and larger than memory.
            for rest in order[cap:].split(LOAD_CHUNK):
                rest = rest.sort().values  # rows in file order: the reads go forward
                self.archive.put(coords[rest], tsdf[rest], weight[rest], colour[rest])
            first = order[:cap]
            coords, tsdf, weight, colour, n = coords[first], tsdf[first], weight[first], colour[first], cap
        self._allocate_storage(max(n, min(INITIAL_CAPACITY, self.config.max_blocks)))
        dev = self.device
        self.block_coords[:n] = coords.to(dev, torch.int64)
        self.tsdf[:n] = tsdf.to(dev, torch.float32)
        self.weight[:n] = weight.to(dev, torch.float32)
        self.colour[:n] = colour.to(dev, torch.float32)
        self.n_blocks = n
        self._index = SortedKeys(pack(self.block_coords[:n]))

    @property
    def lost_blocks(self) -> int:
        """Evicted blocks that are gone: not archived (``archive`` off, the archive full, a disk error)."""
        return self._dropped + (self.archive.lost if self.archive is not None else 0)

    @property
    def archived_blocks(self) -> int:
        """Blocks held in the disk archive now."""
        return self.archive.n_blocks if self.archive is not None else 0

    @property
    def restored_blocks(self) -> int:
        """Blocks read back from the archive so far."""
        return self.archive.restored if self.archive is not None else 0

    def close(self) -> None:
        """Delete the archive (the map is being replaced or the node stops)."""
        if self.archive is not None:
            self.archive.close()

    @property
    def memory_bytes(self) -> int:
        """Bytes held by the voxel storage now (capacity, not only used blocks)."""
        return sum(
            a.element_size() * a.numel() for a in (self.block_coords, self.tsdf, self.weight, self.colour)
        )

    # --- integration ------------------------------------------------------------------------------

    def integrate(
        self,
        depth: Image,
        T_wc: np.ndarray,
        camera: PinholeCamera,
        confidence: Image | None = None,
        rgb: Image | None = None,
    ) -> int:
        """Fuse one depth image (z-depth, metres, NaN = none) seen from camera-to-world ``T_wc``.

        ``confidence`` weights each pixel (pixels below ``min_confidence`` are left out; ``None``:
        weight 1). Returns the number of voxels updated.
        """
        dev = self.device
        d = torch.as_tensor(depth, dtype=torch.float32, device=dev)
        if d.shape != (camera.height, camera.width):
            raise ValueError(f'depth is {d.shape[1]}x{d.shape[0]}, camera is {camera.width}x{camera.height}')
        w = self._pixel_weights(d, confidence)
        T = torch.as_tensor(np.asarray(T_wc, dtype=np.float64), device=dev).to(torch.float32)
        self.camera_position = np.asarray(T_wc, dtype=np.float64)[:3, 3].copy()
        rows = self._allocate(d, w, T, camera)
        self.integrated += 1
        if rows.numel() == 0:
            return 0
        colour = None
        if rgb is not None:
            # (3, H, W) planes, like the storage.
            colour = torch.as_tensor(rgb, device=dev).to(torch.float32).reshape((*d.shape, 3))
            colour = colour.permute(2, 0, 1)
        return self._update(rows, d, w, T, camera, colour)

    def _pixel_weights(self, d: torch.Tensor, confidence: Image | None) -> torch.Tensor:
        """Per-pixel integration weight: 0 where the pixel is not integrated.

        NaN and ±inf fail the depth range comparisons, so no separate finiteness test."""
        cfg = self.config
        valid = (d >= cfg.min_depth) & (d <= cfg.max_depth)
        if confidence is None:
            w = valid.to(torch.float32)
        else:
            c = torch.as_tensor(confidence, dtype=torch.float32, device=d.device)
            if c.shape != d.shape:
                raise ValueError(f'confidence is {tuple(c.shape)}, depth is {tuple(d.shape)}')
            c = torch.nan_to_num(c, nan=0.0).clamp_(0.0, 1.0)
            valid &= c >= cfg.min_confidence
            if cfg.confidence_power != 1.0:  # the weight follows the error more steeply (MapConfig)
                c.pow_(cfg.confidence_power)
            # c in [0, 1] times 0 or 1 is exact: the weight is c where valid and 0 elsewhere.
            w = c.mul_(valid)
        if cfg.depth_power != 0:  # a distance in metres: its error grows with the depth (MapConfig)
            w.div_(torch.where(valid, d, 1.0).clamp_(min=1e-3).pow_(cfg.depth_power))
        return w

    def _allocate(
        self, d: torch.Tensor, w: torch.Tensor, T: torch.Tensor, camera: PinholeCamera
    ) -> torch.Tensor:
        """Rows of the blocks this keyframe touches, allocating (and evicting) as needed."""
        s = self.config.allocation_stride
        ds, ws = d[::s, ::s], w[::s, ::s]
        vv, uu = _divmod(true_indices((ws > 0).reshape(-1)), ws.shape[1])
        if vv.numel() == 0:
            return torch.zeros(0, dtype=torch.int64, device=d.device)
        z = ds[vv, uu]
        x = ((uu * s).to(torch.float32) - camera.cx) / camera.fx
        y = ((vv * s).to(torch.float32) - camera.cy) / camera.fy
        rays = torch.stack((x, y, torch.ones_like(x)), dim=-1)
        steps = max(2, int(np.ceil(2 * self.trunc / (0.5 * self.config.block_m))) + 1)
        offsets = torch.linspace(-self.trunc, self.trunc, steps, device=d.device)
        zz = (z[:, None] + offsets[None]).clamp(min=1e-3)
        points = rays[:, None, :] * zz[..., None]  # camera frame
        world = points.reshape(-1, 3) @ T[:3, :3].T + T[:3, 3]
        blocks = torch.floor(world / self.config.block_m).to(torch.int64)
        keys = pack(_distinct(blocks))
        rows, found = self._index.lookup(keys)
        new_keys = keys[~found]
        if new_keys.numel():
            rows = self._insert(keys, found, rows, new_keys, T[:3, 3])
        return rows

    def _insert(
        self,
        keys: torch.Tensor,
        found: torch.Tensor,
        rows: torch.Tensor,
        new_keys: torch.Tensor,
        centre: torch.Tensor,
    ) -> torch.Tensor:
        """Add ``new_keys`` (evicting far blocks past ``max_blocks``); rows of all ``keys``.

        The blocks this keyframe touches are never the ones evicted for it (their observations
        would be skipped); a keyframe that needs more blocks than the map holds keeps the
        nearest and the rest are counted in ``skipped_blocks``."""
        cap = self.config.max_blocks
        new_coords = unpack(new_keys)
        touched = rows[found]
        room = cap - touched.numel()
        if new_coords.shape[0] > room:  # a single frame larger than the map: keep its nearest blocks
            dist = self._block_distance(new_coords, centre)
            new_coords = new_coords[torch.argsort(dist)[: max(room, 0)]]
            self.skipped_blocks += new_keys.numel() - new_coords.shape[0]
        overflow = self.n_blocks + new_coords.shape[0] - cap
        if overflow > 0:
            dist = self._block_distance(self.block_coords[: self.n_blocks], centre)
            dist[touched] = -1.0  # first in the order: kept
            order = torch.argsort(dist)
            self._evict(order[self.n_blocks - overflow :])
            self.evicted_blocks += int(overflow)
            self._keep(torch.sort(order[: self.n_blocks - overflow]).values)
        self._grow(self.n_blocks + new_coords.shape[0])
        start = self.n_blocks
        self.block_coords[start : start + new_coords.shape[0]] = new_coords
        self._restore(new_coords, start)
        self.n_blocks += new_coords.shape[0]
        self._index = SortedKeys(pack(self.block_coords[: self.n_blocks]))
        rows, found = self._index.lookup(keys)
        return rows[found]

    def _evict(self, rows: torch.Tensor) -> None:
        """Blocks ``rows`` (nearest first) leave memory: to the archive, or dropped without one."""
        if self.archive is None:
            self._dropped += int(rows.numel())
            return
        self.archive.put(
            self.block_coords.index_select(0, rows),
            self.tsdf.index_select(0, rows),
            self.weight.index_select(0, rows),
            self.colour.index_select(0, rows),
        )

    def _restore(self, coords: torch.Tensor, start: int) -> None:
        """The archived blocks among new blocks ``coords`` (rows from ``start``) come back."""
        if self.archive is None or self.archive.n_blocks == 0:
            return
        found, tsdf, weight, colour = self.archive.take(coords)
        if tsdf.shape[0] == 0:
            return
        rows = true_indices(found).to(self.device) + start
        self.tsdf.index_copy_(0, rows, tsdf.to(self.device))
        self.weight.index_copy_(0, rows, weight.to(self.device))
        self.colour.index_copy_(0, rows, colour.to(self.device))

    def _block_distance(self, coords: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
        centres = (coords.to(torch.float32) + 0.5) * self.config.block_m
        return torch.linalg.vector_norm(centres - centre, dim=-1)

    def _update(
        self,
        rows: torch.Tensor,
        d: torch.Tensor,
        w: torch.Tensor,
        T: torch.Tensor,
        camera: PinholeCamera,
        colour: torch.Tensor | None,
    ) -> int:
        R, t = T[:3, :3], T[:3, 3]
        width, height = camera.width, camera.height
        # Camera coordinates of every voxel of the blocks, per axis: rotated block origin plus
        # rotated local offset, broadcast (B, 1) + (1, V), instead of transforming B*V points.
        corners = self.block_coords.index_select(0, rows).to(torch.float32) * self.config.block_m
        origins = ((corners - t) @ R).T
        offsets = self._local_metric @ R
        z = (origins[2][:, None] + offsets[:, 2][None]).reshape(-1)
        # 1/z where z > 1e-6 (in front of the camera); behind it 1e6, finite, and sent to the
        # border pixel below.
        inv_z = torch.clamp(z, min=1e-6).reciprocal_()
        u = (origins[0][:, None] + offsets[:, 0][None]).reshape(-1).mul_(inv_z).mul_(camera.fx)
        v = (origins[1][:, None] + offsets[:, 1][None]).reshape(-1).mul_(inv_z).mul_(camera.fy)
        # u, v hold pixel + 0.5: inside the image iff in [0, size), and there the pixel is their
        # floor. Clamped to [-1, size] they index an image with a one-pixel zero border, where
        # everything outside lands; a voxel behind the camera is sent to the border pixel 0.
        # Column and row of the bordered image are small integers, exact in float32; the pixel
        # index is formed in int32, exact for any image size.
        front = torch.sub(z, 1e-6).sign_().clamp_(min=0.0)  # 1 in front of the camera, else 0
        px_col = u.add_(camera.cx + 0.5).floor_().clamp_(-1, width).add_(1).mul_(front).to(torch.int32)
        px_row = v.add_(camera.cy + 0.5).floor_().clamp_(-1, height).add_(1).mul_(front).to(torch.int32)
        pix = px_row.mul_(width + 2).add_(px_col)
        obs_w = _bordered(w).index_select(0, pix)
        sdf = _bordered(torch.nan_to_num(d, nan=0.0)).index_select(0, pix).sub_(z)
        idx = true_indices((obs_w > 0) & (sdf > -self.trunc))
        if idx.numel() == 0:
            return 0
        wi = obs_w.index_select(0, idx)
        obs = sdf.index_select(0, idx).div_(self.trunc).clamp_(max=1.0)
        V = self.block_voxels
        block, local = _divmod(idx, V)
        row = rows.index_select(0, block)
        flat = row * V + local  # into the flattened tsdf / weight storage
        tsdf, weight = self.tsdf.view(-1), self.weight.view(-1)
        w_old = weight.index_select(0, flat)
        w_new = w_old + wi
        tsdf.scatter_(0, flat, (tsdf.index_select(0, flat) * w_old + obs * wi) / w_new)
        weight.scatter_(0, flat, w_new.clamp(max=self.config.max_weight))
        if colour is not None:
            # One channel at a time: (n,) passes, which on a CPU are several times faster than
            # the (3, n) x (n,) broadcasts of all three at once.
            seen_pix = pix.index_select(0, idx)
            base = row * (3 * V) + local
            flat_c = self.colour.view(-1)
            for c in range(3):
                seen = _bordered(colour[c]).index_select(0, seen_pix)
                at = base + c * V if c else base
                flat_c.scatter_(0, at, (flat_c.index_select(0, at) * w_old + seen * wi) / w_new)
        return int(idx.numel())

    # --- extraction -------------------------------------------------------------------------------

    def voxels(self) -> VoxelSet:
        """Every observed voxel (weight ≥ ``min_weight``): integer coordinates, TSDF, colour."""
        n, b = self.config.block_size, self.n_blocks
        keep = self.weight[:b] >= max(self.config.min_weight, 1e-9)
        coords = self.block_coords[:b][:, None, :] * n + self.local[None]
        colour = self.colour[:b].transpose(1, 2)
        return VoxelSet(coords[keep], self.tsdf[:b][keep], colour[keep], self.voxel)

    def blocks(self) -> BlockGrid:
        """The used blocks as views of the storage (``.clone()`` for a copy integration cannot change)."""
        b, cfg = self.n_blocks, self.config
        return BlockGrid(
            self.block_coords[:b],
            self.tsdf[:b],
            self.weight[:b],
            self.colour[:b],
            cfg.block_size,
            self.voxel,
            cfg.min_weight,
        )

    def mesh(self) -> SurfaceMesh:
        """The zero level set of the whole map (archived blocks included) as a triangle mesh
        (surface nets on the blocks), world frame, metres. With blocks archived it is extracted
        in slabs of at most ``max_blocks`` blocks read back at a time (mapping/slab_surface.py),
        so saving a map larger than memory stays within about twice the cap."""
        if self.archive is None or self.archive.n_blocks == 0:
            return block_mesh(self.blocks())
        return slab_mesh(*self.whole_map(), self.config.max_blocks)

    def whole_map(self) -> tuple[torch.Tensor, Callable[[torch.Tensor], BlockGrid]]:
        """The coordinates of every block (CPU: those in memory, then the archived ones) and
        ``load(rows)``, the blocks of those rows as a :class:`BlockGrid` on the map's device,
        the archived ones read from disk: the whole map a part at a time (the slab mesh, the
        map file), never all of it in memory at once."""
        grid = self.blocks()
        n = self.n_blocks
        archived = self.archive.coords() if self.archive is not None else grid.coords.new_zeros((0, 3)).cpu()

        def load(rows: torch.Tensor) -> BlockGrid:
            mine = grid.rows(rows[rows < n].to(self.device))
            theirs = archived[rows[rows >= n] - n]
            if theirs.shape[0] == 0:
                return mine
            stored = (theirs, *self.archive.read(theirs))
            return mine.extended(*(a.to(self.device) for a in stored))

        return torch.cat((grid.coords.cpu(), archived)), load


def _bordered(image: torch.Tensor) -> torch.Tensor:
    """``(H, W)`` -> flattened ``(H + 2) * (W + 2)`` with a one-pixel border of zeros."""
    return F.pad(image, (1, 1, 1, 1)).view(-1)


def _divmod(index: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(index // n, index % n)`` for non-negative ``index``; shifts when ``n`` is a power of 2
    (the default 8³ blocks), as integer division is several times slower on a CPU."""
    if n & (n - 1) == 0:
        return index >> (n.bit_length() - 1), index & (n - 1)
    return torch.div(index, n, rounding_mode='floor'), index % n


def _distinct(cells: torch.Tensor) -> torch.Tensor:
    """The distinct rows of ``(N, 3)`` integer ``cells``, in :func:`pack` order (x, y, z).

    They are marked in a dense grid over their bounding box and read back with one
    ``nonzero``: a keyframe's ~15 k allocation points fall in a few hundred blocks, and its
    box is bounded by ``max_depth`` (about 40³ blocks at 6 m), so this is cheaper than the
    sort that ``unique`` does. A box with far more cells than points falls back to ``unique``
    so the grid's memory stays bounded whatever the configuration."""
    lo = cells.amin(dim=0)
    local = cells - lo
    ext = local.amax(dim=0) + 1
    nx, ny, nz = ext.tolist()  # one device sync
    if nx * ny * nz > max(1 << 20, 64 * cells.shape[0]):  # a sparse spread (a far max_depth, fine voxels)
        return torch.unique(cells, dim=0)  # rows in lexicographic order = pack order
    linear = (local[:, 0] * ny + local[:, 1]) * nz + local[:, 2]
    marks = torch.zeros(nx * ny * nz, dtype=torch.bool, device=cells.device)
    marks.scatter_(0, linear, True)
    at = true_indices(marks)
    x, rest = torch.div(at, ny * nz, rounding_mode='floor'), at % (ny * nz)
    return torch.stack((x, torch.div(rest, nz, rounding_mode='floor'), rest % nz), dim=-1) + lo
