"""How the map's surface extraction scales with the number of voxel blocks (figures, no assertions).

    python scripts/diag/map_extraction.py

A synthetic room (30 keyframes at 320x240, exact depth) integrated at 4, 2 and 1 cm voxels,
so the same surface spans more and more blocks; prints the blocks, the observed voxels, the
time of ``blocks().clone()`` (the copy map_node takes under its lock), of the mesh extraction
on the blocks (mapping/block_surface.py: ``TorchTSDF.mesh``, and what nodes/map_points.py
does outside the lock) and of the voxel-list extraction it replaced (mapping/surface.py).
Measured 2026-11-29 on 2 cores: 588 blocks 66 ms (voxel list 121 ms), 1898 blocks 252 ms
(471 ms), 6601 blocks 987 ms (2280 ms).
"""

from __future__ import annotations

import time

import numpy as np

from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence
from depth_fusion_ros.mapping.config import MapConfig
from depth_fusion_ros.mapping.engine import make_engine
from depth_fusion_ros.mapping.surface import extract_mesh


def main() -> None:
    seq = render_sequence(SynthConfig(width=320, height=240, frames=30, seed=1))
    confidence = np.full((240, 320), 0.8, np.float32)
    for voxel in (0.04, 0.02, 0.01):
        engine, _ = make_engine(MapConfig(voxel_size=voxel, engine='torch', max_blocks=100000))
        for i, frame in enumerate(seq.frames):
            engine.integrate(
                seq.gt_depth_working(i), frame.pose, seq.camera, confidence=confidence, rgb=frame.rgb
            )
        t0 = time.perf_counter()
        engine.blocks().clone()
        copy = time.perf_counter() - t0
        t0 = time.perf_counter()
        mesh = engine.mesh()
        whole = time.perf_counter() - t0
        t0 = time.perf_counter()
        voxels = engine.voxels()
        extract_mesh(voxels)
        listed = time.perf_counter() - t0
        print(
            f'{voxel * 100:g} cm voxels: {engine.n_blocks} blocks, {len(voxels.tsdf)} voxels, '
            f'copy {copy * 1e3:.0f} ms, mesh {whole * 1e3:.0f} ms ({whole / engine.n_blocks * 1e3:.2f} ms '
            f'a block; voxel list {listed * 1e3:.0f} ms), {len(mesh.vertices)} vertices'
        )


if __name__ == '__main__':
    main()
