"""A compact sparse TSDF in torch: bounded voxel blocks, confidence-weighted integration.

Why our own: the library TSDF (Open3D) is an optional 300 MB install with a large dependency
tree and no per-pixel weights; this one is ~200 lines of torch, runs on CUDA wherever torch
does, and weights every pixel by the fused confidence (docs/mapping.md has the measurements).

Layout: voxel blocks of ``block_size``³ voxels, allocated where depth is observed. Block ``b``
holds rows ``b`` of ``tsdf``/``weight`` (``(capacity, block_size³)``) and ``colour``
(``(capacity, block_size³, 3)``); the block coordinates are looked up by binary search in a
sorted key table (:mod:`.keys`). Voxel ``i`` of the integer grid has its centre at
``i * voxel_size`` in the world frame.

Integration of one keyframe (projective TSDF, as KinectFusion / Open3D):

1. allocate the blocks around every observed surface point (``± truncation`` along the ray);
2. project the voxels of those blocks into the depth image (nearest pixel);
3. ``sdf = depth - z``; voxels with ``sdf > -truncation`` get ``tsdf = min(1, sdf/truncation)``
   averaged with weight = pixel confidence (capped at ``max_weight``).

Memory is bounded by ``max_blocks``: when a keyframe needs more blocks than are free, the
blocks farthest from its camera are evicted (counted in ``evicted_blocks``).
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from ..camera import PinholeCamera
from .config import MapConfig
from .keys import SortedKeys, pack
from .surface import SurfaceMesh, VoxelSet, extract_mesh

log = logging.getLogger(__name__)

#: Initial block capacity; doubled as needed up to ``max_blocks``.
INITIAL_CAPACITY = 256


class TorchTSDF:
    """Sparse block TSDF on a torch device. ``integrate`` per keyframe, ``mesh`` to extract."""

    name = 'torch'

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
        self.integrated = 0
        self._allocate_storage(min(INITIAL_CAPACITY, config.max_blocks))
        self._index = SortedKeys(self.block_coords[:0].new_zeros((0,)))

    # --- storage ----------------------------------------------------------------------------------

    def _allocate_storage(self, capacity: int) -> None:
        dev, v = self.device, self.block_voxels
        self.block_coords = torch.zeros((capacity, 3), dtype=torch.int64, device=dev)
        self.tsdf = torch.ones((capacity, v), dtype=torch.float32, device=dev)
        self.weight = torch.zeros((capacity, v), dtype=torch.float32, device=dev)
        self.colour = torch.zeros((capacity, v, 3), dtype=torch.float32, device=dev)

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

    @property
    def memory_bytes(self) -> int:
        """Bytes held by the voxel storage now (capacity, not only used blocks)."""
        return sum(
            a.element_size() * a.numel() for a in (self.block_coords, self.tsdf, self.weight, self.colour)
        )

    # --- integration ------------------------------------------------------------------------------

    def integrate(
        self,
        depth: np.ndarray,
        T_wc: np.ndarray,
        camera: PinholeCamera,
        confidence: np.ndarray | None = None,
        rgb: np.ndarray | None = None,
    ) -> int:
        """Fuse one depth image (z-depth, metres, NaN = none) seen from camera-to-world ``T_wc``.

        ``confidence`` weights each pixel (pixels below ``min_confidence`` are left out; ``None``:
        weight 1). Returns the number of voxels updated.
        """
        dev = self.device
        d = torch.as_tensor(np.asarray(depth, dtype=np.float32), device=dev)
        if d.shape != (camera.height, camera.width):
            raise ValueError(f'depth is {d.shape[1]}x{d.shape[0]}, camera is {camera.width}x{camera.height}')
        w = self._pixel_weights(d, confidence)
        T = torch.as_tensor(np.asarray(T_wc, dtype=np.float64), device=dev).to(torch.float32)
        rows = self._allocate(d, w, T, camera)
        self.integrated += 1
        if rows.numel() == 0:
            return 0
        colour = None
        if rgb is not None:
            colour = torch.as_tensor(np.asarray(rgb), device=dev).to(torch.float32).reshape(-1, 3)
        return self._update(rows, d, w, T, camera, colour)

    def _pixel_weights(self, d: torch.Tensor, confidence: np.ndarray | None) -> torch.Tensor:
        """Per-pixel integration weight: 0 where the pixel is not integrated."""
        cfg = self.config
        valid = torch.isfinite(d) & (d >= cfg.min_depth) & (d <= cfg.max_depth)
        if confidence is None:
            return valid.to(torch.float32)
        c = torch.as_tensor(np.asarray(confidence, dtype=np.float32), device=d.device)
        if c.shape != d.shape:
            raise ValueError(f'confidence is {tuple(c.shape)}, depth is {tuple(d.shape)}')
        c = torch.nan_to_num(c, nan=0.0).clamp_(0.0, 1.0)
        valid &= c >= cfg.min_confidence
        return torch.where(valid & (c > 0), c, torch.zeros_like(c))

    def _allocate(
        self, d: torch.Tensor, w: torch.Tensor, T: torch.Tensor, camera: PinholeCamera
    ) -> torch.Tensor:
        """Rows of the blocks this keyframe touches, allocating (and evicting) as needed."""
        s = self.config.allocation_stride
        ds, ws = d[::s, ::s], w[::s, ::s]
        vv, uu = torch.nonzero(ws > 0, as_tuple=True)
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
        keys = torch.unique(pack(blocks))
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
        """Add ``new_keys`` (evicting far blocks past ``max_blocks``); rows of all ``keys``."""
        from .keys import unpack

        cap = self.config.max_blocks
        new_coords = unpack(new_keys)
        if new_coords.shape[0] > cap:  # a single frame larger than the map: keep its nearest blocks
            dist = self._block_distance(new_coords, centre)
            new_coords = new_coords[torch.argsort(dist)[:cap]]
            self.evicted_blocks += new_keys.numel() - cap
        overflow = self.n_blocks + new_coords.shape[0] - cap
        if overflow > 0:
            dist = self._block_distance(self.block_coords[: self.n_blocks], centre)
            keep = torch.argsort(dist)[: self.n_blocks - overflow]
            self.evicted_blocks += int(overflow)
            self._keep(torch.sort(keep).values)
        self._grow(self.n_blocks + new_coords.shape[0])
        start = self.n_blocks
        self.block_coords[start : start + new_coords.shape[0]] = new_coords
        self.n_blocks += new_coords.shape[0]
        self._index = SortedKeys(pack(self.block_coords[: self.n_blocks]))
        rows, found = self._index.lookup(keys)
        return rows[found]

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
        # Camera coordinates of every voxel of the blocks, per axis: rotated block origin plus
        # rotated local offset, broadcast (B, 1) + (1, V), instead of transforming B*V points.
        origins = ((self.block_coords[rows].to(torch.float32) * self.config.block_m - t) @ R).T
        offsets = self._local_metric @ R
        z = (origins[2][:, None] + offsets[:, 2][None]).reshape(-1)
        front = z > 1e-6
        inv_z = 1.0 / torch.where(front, z, torch.ones_like(z))
        u = (
            (origins[0][:, None] + offsets[:, 0][None])
            .reshape(-1)
            .mul_(inv_z)
            .mul_(camera.fx)
            .add_(camera.cx + 0.5)
        )
        v = (
            (origins[1][:, None] + offsets[:, 1][None])
            .reshape(-1)
            .mul_(inv_z)
            .mul_(camera.fy)
            .add_(camera.cy + 0.5)
        )
        # u, v hold pixel + 0.5: inside the image iff in [0, size).
        inside = front & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
        cand = torch.nonzero(inside, as_tuple=True)[0]
        pix = v[cand].to(torch.int64) * camera.width + u[cand].to(torch.int64)  # truncation = floor here
        obs_w = w.reshape(-1)[pix]
        sdf = torch.nan_to_num(d.reshape(-1)[pix], nan=0.0) - z[cand]
        upd = (obs_w > 0) & (sdf > -self.trunc)
        keep = torch.nonzero(upd, as_tuple=True)[0]
        if keep.numel() == 0:
            return 0
        local_idx = cand[keep]
        pix, wi = pix[keep], obs_w[keep]
        obs = (sdf[keep] / self.trunc).clamp(max=1.0)
        V = self.block_voxels
        flat = rows[local_idx // V] * V + local_idx % V  # into the flattened storage
        tsdf, weight = self.tsdf.view(-1), self.weight.view(-1)
        w_old = weight[flat]
        w_new = w_old + wi
        tsdf[flat] = (tsdf[flat] * w_old + obs * wi) / w_new
        weight[flat] = w_new.clamp(max=self.config.max_weight)
        if colour is not None:
            flat_c = self.colour.view(-1, 3)
            flat_c[flat] = (flat_c[flat] * w_old[:, None] + colour[pix] * wi[:, None]) / w_new[:, None]
        return int(flat.numel())

    # --- extraction -------------------------------------------------------------------------------

    def voxels(self) -> VoxelSet:
        """Every observed voxel (weight ≥ ``min_weight``): integer coordinates, TSDF, colour."""
        n, b = self.config.block_size, self.n_blocks
        keep = self.weight[:b] >= max(self.config.min_weight, 1e-9)
        coords = self.block_coords[:b][:, None, :] * n + self.local[None]
        return VoxelSet(coords[keep], self.tsdf[:b][keep], self.colour[:b][keep], self.voxel)

    def mesh(self) -> SurfaceMesh:
        """The zero level set as a triangle mesh (surface nets), world frame, metres."""
        return extract_mesh(self.voxels())
