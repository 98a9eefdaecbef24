"""Surface nets on the TSDF's blocks give the mesh the voxel-list extraction gives."""

from __future__ import annotations

import numpy as np
import pytest

from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence
from depth_fusion_ros.mapping.block_surface import block_mesh
from depth_fusion_ros.mapping.config import MapConfig
from depth_fusion_ros.mapping.surface import extract_mesh
from depth_fusion_ros.mapping.torch_tsdf import TorchTSDF


def _triangle_set(vertices: np.ndarray, triangles: np.ndarray) -> set:
    """Triangles as rotation-normalised triples of rounded vertex positions (order-free, orientation kept)."""
    out = set()
    for tri in np.round(vertices[triangles] * 1e5).astype(np.int64):
        rows = [tuple(p) for p in tri]
        k = rows.index(min(rows))
        out.add(tuple(rows[k:] + rows[:k]))
    return out


@pytest.mark.parametrize('block_size', [8, 5])
def test_block_mesh_equals_the_voxel_list_mesh(block_size):
    seq = render_sequence(SynthConfig(width=96, height=72, frames=6, seed=2))
    tsdf = TorchTSDF(MapConfig(voxel_size=0.05, block_size=block_size, engine='torch', consistency_span=0))
    rng = np.random.default_rng(0)
    for i, frame in enumerate(seq.frames):
        confidence = rng.uniform(0.0, 1.0, (72, 96)).astype(np.float32)  # some voxels under min_weight
        tsdf.integrate(seq.gt_depth_working(i), frame.pose, seq.camera, confidence=confidence, rgb=frame.rgb)
    reference = extract_mesh(tsdf.voxels())
    fast = block_mesh(tsdf.blocks())
    assert len(reference.vertices) > 500 and len(reference.triangles) > 500
    order_r = np.lexsort(reference.vertices.T)
    order_f = np.lexsort(fast.vertices.T)
    np.testing.assert_allclose(fast.vertices[order_f], reference.vertices[order_r], atol=1e-5)
    np.testing.assert_array_equal(fast.colours[order_f], reference.colours[order_r])
    assert _triangle_set(fast.vertices, fast.triangles) == _triangle_set(
        reference.vertices, reference.triangles
    )
    # The point cloud's extraction (map_points.py): the same vertices and colours, no triangles.
    points = block_mesh(tsdf.blocks(), triangles=False)
    np.testing.assert_array_equal(points.vertices, fast.vertices)
    np.testing.assert_array_equal(points.colours, fast.colours)
    assert points.triangles.shape == (0, 3)
