"""The mesh of a map extracted slab by slab (saving a map larger than memory) is the whole
map's mesh: the same vertices with the same colours, the same triangles."""

from __future__ import annotations

import numpy as np
import pytest

from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence
from depth_fusion_ros.mapping.block_surface import block_mesh
from depth_fusion_ros.mapping.config import MapConfig
from depth_fusion_ros.mapping.slab_surface import slab_mesh
from depth_fusion_ros.mapping.torch_tsdf import TorchTSDF

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _canonical(mesh) -> tuple[dict, set]:
    """Vertex position -> colour, and each triangle as its sorted vertex positions (the meshes
    number their vertices in different orders)."""
    positions = [tuple(p) for p in np.round(mesh.vertices.astype(np.float64), 6)]
    colour = {p: tuple(c) for p, c in zip(positions, mesh.colours.tolist(), strict=True)}
    triangles = {tuple(sorted(positions[i] for i in t)) for t in mesh.triangles}
    return colour, triangles


@pytest.mark.parametrize('max_blocks', [8, 37, 100_000])
def test_slabs_join_into_the_whole_mesh(max_blocks):
    seq = render_sequence(SynthConfig(width=160, height=120, frames=16, seed=7))
    tsdf = TorchTSDF(MapConfig(engine='torch', voxel_size=0.04))
    for i in range(0, 16, 2):
        tsdf.integrate(seq.gt_depth_working(i), seq.frames[i].pose, seq.camera, rgb=seq.frames[i].rgb)
    grid = tsdf.blocks()

    whole, slabs = block_mesh(grid), slab_mesh(grid.coords, grid.rows, max_blocks)
    assert len(whole.triangles) > 10_000
    assert len(slabs.vertices) == len(whole.vertices) and len(slabs.triangles) == len(whole.triangles)
    assert _canonical(slabs) == _canonical(whole)
