"""The TSDF map saved to disk and loaded back (map_node's map_file): core, no ROS."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence
from depth_fusion_ros.mapping.config import MapConfig
from depth_fusion_ros.mapping.map_file import load_tsdf, save_tsdf
from depth_fusion_ros.mapping.torch_tsdf import TorchTSDF


@pytest.fixture(scope='module')
def saved_map(tmp_path_factory):
    seq = render_sequence(SynthConfig(width=96, height=72, frames=4, seed=4))
    tsdf = TorchTSDF(MapConfig(voxel_size=0.05, engine='torch'))
    for i, frame in enumerate(seq.frames):
        tsdf.integrate(seq.gt_depth_working(i), frame.pose, seq.camera, rgb=frame.rgb)
    path = tmp_path_factory.mktemp('map') / 'room.tsdf'
    assert save_tsdf(tsdf, path, 'world') == tsdf.n_blocks > 10
    return tsdf, path, seq


def test_a_saved_map_loads_back_the_same_and_takes_more_keyframes(saved_map):
    tsdf, path, seq = saved_map
    loaded = TorchTSDF(MapConfig(voxel_size=0.05, engine='torch'))
    assert load_tsdf(loaded, path) == 'world'
    assert loaded.n_blocks == tsdf.n_blocks
    a, b = tsdf.mesh(), loaded.mesh()
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.triangles, b.triangles)
    loaded.integrate(seq.gt_depth_working(0), seq.frames[0].pose, seq.camera)  # integration goes on
    assert loaded.integrated == 1 and loaded.n_blocks == tsdf.n_blocks


def test_a_map_file_that_does_not_fit_is_a_one_line_error(saved_map, tmp_path):
    _, path, _ = saved_map
    with pytest.raises(ValueError, match=r'5 cm voxels .* configured for 4 cm'):
        load_tsdf(TorchTSDF(MapConfig(voxel_size=0.04, engine='torch')), path)
    with pytest.raises(ValueError, match=r'more than map\.max_blocks=3 with map\.archive off'):
        load_tsdf(TorchTSDF(MapConfig(voxel_size=0.05, engine='torch', max_blocks=3, archive=False)), path)
    junk = tmp_path / 'junk.tsdf'
    junk.write_bytes(b'not a map')
    with pytest.raises(ValueError, match='not readable as a map'):
        load_tsdf(TorchTSDF(MapConfig(voxel_size=0.05, engine='torch')), junk)
    other = tmp_path / 'other.tsdf'
    torch.save({'weights': torch.zeros(3)}, other)
    with pytest.raises(ValueError, match='not a depth_fusion_ros TSDF map'):
        load_tsdf(TorchTSDF(MapConfig(voxel_size=0.05, engine='torch')), other)
