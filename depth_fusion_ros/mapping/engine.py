"""Picks the TSDF engine: ``torch`` (always there), ``open3d`` (optional), or ``auto``.

``make_map(config)`` returns the engine and one line saying what was chosen and why, which
the node logs at start: a missing optional engine is a fallback that is said, never silent.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from ..camera import PinholeCamera
from ..torch_device import resolve_device
from .config import MapConfig
from .consistency import ConsistentMap
from .open3d_tsdf import Open3DTSDF, open3d_available
from .surface import SurfaceMesh
from .torch_tsdf import TorchTSDF


class TSDFMap(Protocol):
    """What every engine offers."""

    name: str
    config: MapConfig
    evicted_blocks: int
    #: Blocks a keyframe needed beyond ``max_blocks`` on its own (left out of it).
    skipped_blocks: int
    integrated: int
    #: The disk archive of evicted blocks (mapping/block_archive.py), or None.
    archive: object | None
    camera_position: np.ndarray | None

    @property
    def lost_blocks(self) -> int: ...

    @property
    def archived_blocks(self) -> int: ...

    @property
    def restored_blocks(self) -> int: ...

    def close(self) -> None: ...

    @property
    def n_blocks(self) -> int: ...

    @property
    def memory_bytes(self) -> int: ...

    def integrate(
        self,
        depth: np.ndarray,
        T_wc: np.ndarray,
        camera: PinholeCamera,
        confidence: np.ndarray | None = None,
        rgb: np.ndarray | None = None,
    ) -> int: ...

    def mesh(self) -> SurfaceMesh: ...


def make_map(config: MapConfig) -> tuple[ConsistentMap, str]:
    """The engine ``config.engine`` asks for (or the torch engine with the reason it fell
    back), behind the multi-keyframe consistency test (``consistency_span`` 0: none)."""
    engine, note = make_engine(config)
    return ConsistentMap(engine, config), note


def make_engine(config: MapConfig) -> tuple[TSDFMap, str]:
    """The bare engine (no consistency test) and the line saying which: also what a rebuild
    at corrected poses integrates into (mapping/keyframe_store.py). The device is checked
    once the engine is chosen: Open3D's own CUDA needs no CUDA in torch."""
    config.validate()
    open3d, note = _choose(config)
    if open3d:
        if config.device.startswith('cuda') and not _open3d_cuda():
            raise ValueError(
                f'device {config.device!r} requested but this Open3D has no CUDA (map.engine open3d)'
            )
        if not config.device.startswith('cuda'):
            resolve_device(config.device)  # a typo
        return Open3DTSDF(config), note
    resolve_device(config.device)
    return TorchTSDF(config), note


def _choose(config: MapConfig) -> tuple[bool, str]:
    """(whether Open3D is the engine, the line saying which and why)."""
    wanted = config.engine
    if wanted == 'torch':
        return False, f'TSDF engine: torch on {config.device}'
    missing = open3d_available()
    if wanted == 'auto' and missing is None and config.device.startswith('cuda') and not _open3d_cuda():
        return False, f'TSDF engine: torch on {config.device} (auto; this Open3D has no CUDA)'
    if missing is None:
        archive = '; no archive: blocks evicted past map.max_blocks are lost' if config.archive else ''
        # Its integration takes no per-pixel weights: the confidence only selects (min_confidence).
        unused = config.confidence_power != 1 or config.depth_power != 0
        weights = '; every pixel weighs 1 (map.confidence_power and map.depth_power unused)' if unused else ''
        return True, f'TSDF engine: open3d (VoxelBlockGrid) on {config.device}{archive}{weights}'
    if wanted == 'auto':
        return False, f'TSDF engine: torch on {config.device} (auto; Open3D not installed)'
    return False, f'TSDF engine: open3d unavailable ({missing}); falling back to torch'


def _open3d_cuda() -> bool:
    import open3d.core as o3c

    return bool(o3c.cuda.is_available())
