"""The TSDF of Open3D (``open3d.t.geometry.VoxelBlockGrid``) behind the engine interface.

Optional: Open3D is not installed by the README (300+ MB, a large dependency tree and a
system ``libusb``; docs/mapping.md has the measurements). When it is importable, ``engine:
open3d`` (or ``auto``) uses it. Differences from the torch engine, said plainly:

* Open3D integrates every valid pixel with weight 1: the confidence only *selects* pixels
  (``min_confidence``), it does not weight them;
* memory is bounded by erasing the blocks farthest from the camera once the hash map holds
  more than ``max_blocks`` (the same rule as the torch engine).
"""

from __future__ import annotations

import numpy as np

from ..camera import PinholeCamera
from .config import MapConfig
from .surface import SurfaceMesh, empty_mesh


def open3d_available() -> str | None:
    """``None`` when Open3D imports, else why not (one line)."""
    try:
        import open3d  # noqa: F401
    except Exception as exc:  # ImportError, or a missing system library (OSError)
        return f'{type(exc).__name__}: {exc}'
    return None


class Open3DTSDF:
    """Same interface as :class:`~.torch_tsdf.TorchTSDF`, backed by Open3D's VoxelBlockGrid."""

    name = 'open3d'

    def __init__(self, config: MapConfig) -> None:
        import open3d as o3d
        import open3d.core as o3c

        self.o3d, self.o3c = o3d, o3c
        self.config = config.validate()
        device = 'CUDA:' + (config.device.split(':')[1] if ':' in config.device else '0')
        self.device = o3c.Device(device if config.device.startswith('cuda') else 'CPU:0')
        self.grid = o3d.t.geometry.VoxelBlockGrid(
            attr_names=('tsdf', 'weight', 'color'),
            attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
            attr_channels=((1), (1), (3)),
            voxel_size=float(config.voxel_size),
            block_resolution=int(config.block_size),
            block_count=int(config.max_blocks),
            device=self.device,
        )
        self.evicted_blocks = 0
        self.integrated = 0
        #: No disk archive here: every evicted block is lost (the engine's start line says so).
        self.archive = None
        self.skipped_blocks = 0
        self.camera_position: np.ndarray | None = None

    @property
    def lost_blocks(self) -> int:
        return self.evicted_blocks

    archived_blocks = 0
    restored_blocks = 0

    def close(self) -> None:
        """Nothing outside memory to release (the torch engine deletes its archive here)."""

    @property
    def n_blocks(self) -> int:
        return int(self.grid.hashmap().size())

    @property
    def memory_bytes(self) -> int:
        return int(self.grid.hashmap().capacity()) * self.config.bytes_per_block

    def integrate(
        self,
        depth: np.ndarray,
        T_wc: np.ndarray,
        camera: PinholeCamera,
        confidence: np.ndarray | None = None,
        rgb: np.ndarray | None = None,
    ) -> int:
        o3d, o3c, cfg = self.o3d, self.o3c, self.config
        d = np.array(depth, dtype=np.float32)
        if d.shape != (camera.height, camera.width):
            raise ValueError(f'depth is {d.shape[1]}x{d.shape[0]}, camera is {camera.width}x{camera.height}')
        keep = np.isfinite(d) & (d >= cfg.min_depth) & (d <= cfg.max_depth)
        if confidence is not None:
            keep &= np.nan_to_num(np.asarray(confidence, np.float32)) >= max(cfg.min_confidence, 1e-6)
        d[~keep] = 0.0
        self.integrated += 1
        if not keep.any():
            return 0
        depth_img = o3d.t.geometry.Image(o3c.Tensor(d, device=self.device))
        intrinsic = o3c.Tensor(camera.K.astype(np.float64))
        extrinsic = o3c.Tensor(np.linalg.inv(np.asarray(T_wc, np.float64)))
        blocks = self.grid.compute_unique_block_coordinates(
            depth_img,
            intrinsic,
            extrinsic,
            1.0,
            float(cfg.max_depth),
            float(cfg.truncation_m / cfg.voxel_size),
        )
        colour = np.zeros((*d.shape, 3), np.float32) if rgb is None else np.asarray(rgb, np.float32)
        colour_img = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(colour), device=self.device))
        self.grid.integrate(
            blocks, depth_img, colour_img, intrinsic, intrinsic, extrinsic, 1.0, float(cfg.max_depth),
            float(cfg.truncation_m / cfg.voxel_size),
        )  # fmt: skip
        self._bound(np.asarray(T_wc)[:3, 3])
        return int(keep.sum())

    def _bound(self, centre: np.ndarray) -> None:
        """Erase the blocks farthest from ``centre`` while more than ``max_blocks`` are held."""
        hashmap = self.grid.hashmap()
        over = int(hashmap.size()) - self.config.max_blocks
        if over <= 0:
            return
        keys = hashmap.key_tensor()[hashmap.active_buf_indices().to(self.o3c.int64)].cpu().numpy()
        centres = (keys.astype(np.float64) + 0.5) * self.config.block_m
        far = np.argsort(-np.linalg.norm(centres - centre, axis=1))[:over]
        hashmap.erase(self.o3c.Tensor(keys[far], device=self.device))
        self.evicted_blocks += over

    def mesh(self) -> SurfaceMesh:
        """Open3D's marching cubes of the grid (``min_weight`` as its weight threshold)."""
        if self.n_blocks == 0:
            return empty_mesh()
        mesh = self.grid.extract_triangle_mesh(weight_threshold=float(self.config.min_weight))
        vertices = mesh.vertex.positions.cpu().numpy().astype(np.float32)
        if len(vertices) == 0:
            return empty_mesh()
        colours = mesh.vertex.colors.cpu().numpy() if 'colors' in mesh.vertex else np.zeros_like(vertices)
        return SurfaceMesh(
            vertices,
            mesh.triangle.indices.cpu().numpy().astype(np.int64),
            np.clip(np.round(colours), 0, 255).astype(np.uint8),
        )
