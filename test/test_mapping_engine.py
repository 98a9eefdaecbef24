"""The TSDF engines without ROS: geometry of the extracted surface, weighting, bounds, PLY."""

from __future__ import annotations

import numpy as np
import pytest
from map_geometry import room_surface_distance

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.data.synthetic import SynthConfig, build_world, render_sequence
from depth_fusion_ros.mapping import MapConfig, make_map, read_ply, write_ply
from depth_fusion_ros.mapping.engine import make_map as make_map_direct
from depth_fusion_ros.mapping.open3d_tsdf import open3d_available
from depth_fusion_ros.mapping.torch_tsdf import TorchTSDF

pytestmark = pytest.mark.usefixtures('one_torch_thread')

CAMERA = PinholeCamera(160, 120, 131.25, 131.25, 79.5, 59.5)
LOOK_DOWN_Z = np.eye(4)


def _wall(distance: float = 2.0) -> np.ndarray:
    """Depth of a fronto-parallel wall ``distance`` m in front of the camera."""
    return np.full((CAMERA.height, CAMERA.width), distance, np.float32)


@pytest.fixture(scope='module')
def room():
    cfg = SynthConfig(width=160, height=120, frames=16, seed=5)
    return build_world(cfg)[0], render_sequence(cfg)


def test_flat_wall_is_extracted_at_its_depth_facing_the_camera():
    tsdf = TorchTSDF(MapConfig(engine='torch', voxel_size=0.04))
    for _ in range(2):
        tsdf.integrate(_wall(2.0), LOOK_DOWN_Z, CAMERA)
    mesh = tsdf.mesh()
    assert len(mesh.vertices) > 500 and len(mesh.triangles) > 500
    assert np.abs(mesh.vertices[:, 2] - 2.0).max() < 0.01
    p = mesh.vertices[mesh.triangles]
    normals = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert (normals[:, 2] < 0).mean() > 0.99  # towards the camera (free space)


def test_synthetic_room_mesh_lies_on_the_known_geometry(room):
    scene, seq = room
    tsdf = TorchTSDF(MapConfig(engine='torch', voxel_size=0.04))
    for i in range(0, len(seq), 2):
        tsdf.integrate(seq.gt_depth_working(i), seq.frames[i].pose, seq.camera, rgb=seq.frames[i].rgb)
    mesh = tsdf.mesh()
    dist = room_surface_distance(scene, mesh.vertices.astype(np.float64))
    assert len(dist) > 2000
    assert np.median(dist) < 0.01 and np.percentile(dist, 95) < 0.03
    assert mesh.colours.std() > 5  # coloured by the images, not a constant


def test_confidence_weights_and_threshold():
    config = MapConfig(engine='torch', voxel_size=0.04, min_confidence=0.3, min_weight=0.0)
    tsdf = TorchTSDF(config)
    low = np.full(_wall().shape, 0.1, np.float32)
    tsdf.integrate(_wall(2.0), LOOK_DOWN_Z, CAMERA, confidence=low)
    assert tsdf.n_blocks == 0 and tsdf.mesh().is_empty  # below the threshold: nothing integrated
    # A confident wall at 2.0 m and a weak one at 2.2 m: the surface sits nearer the confident one.
    tsdf.integrate(_wall(2.0), LOOK_DOWN_Z, CAMERA, confidence=np.full(_wall().shape, 0.9, np.float32))
    tsdf.integrate(_wall(2.1), LOOK_DOWN_Z, CAMERA, confidence=np.full(_wall().shape, 0.3, np.float32))
    z = np.median(tsdf.mesh().vertices[:, 2])
    assert 2.0 < z < 2.04  # 0.9:0.3 weighting puts it at 2.025, an unweighted mean at 2.05


def test_depth_range_and_nan_are_left_out():
    tsdf = TorchTSDF(MapConfig(engine='torch', max_depth=3.0))
    depth = _wall(4.0)
    depth[:, :40] = np.nan
    tsdf.integrate(depth, LOOK_DOWN_Z, CAMERA)
    assert tsdf.n_blocks == 0


def test_max_blocks_bounds_memory_and_evicts_the_farthest():
    config = MapConfig(engine='torch', voxel_size=0.04, max_blocks=60)
    tsdf = TorchTSDF(config)
    poses = []
    for x in np.linspace(0.0, 6.0, 13):  # slide along a long wall: far more than 60 blocks
        T = np.eye(4)
        T[0, 3] = x
        poses.append(T)
        tsdf.integrate(_wall(1.5), T, CAMERA)
        assert tsdf.n_blocks <= 60
        assert tsdf.memory_bytes <= 60 * config.bytes_per_block + 60 * 3 * 8
    assert tsdf.evicted_blocks > 0
    vertices = tsdf.mesh().vertices
    assert np.abs(vertices[:, 0] - 6.0).min() < 0.5 and vertices[:, 0].min() > 3.0  # the old end went


def test_wrong_sizes_and_bad_config_are_refused():
    tsdf = TorchTSDF(MapConfig(engine='torch'))
    with pytest.raises(ValueError, match='camera is 160x120'):
        tsdf.integrate(np.ones((10, 10), np.float32), LOOK_DOWN_Z, CAMERA)
    with pytest.raises(ValueError, match='confidence'):
        tsdf.integrate(_wall(), LOOK_DOWN_Z, CAMERA, confidence=np.ones((3, 3), np.float32))
    with pytest.raises(ValueError, match=r'map\.voxel_size'):
        MapConfig(voxel_size=0).validate()
    with pytest.raises(ValueError, match=r'map\.engine'):
        MapConfig(engine='nvblox').validate()


def test_engine_choice_says_what_it_picked():
    engine, note = make_map_direct(MapConfig(engine='torch'))
    assert engine.name == 'torch' and 'torch' in note
    engine, note = make_map(MapConfig(engine='open3d'))
    if open3d_available() is None:
        assert engine.name == 'open3d'
    else:
        assert engine.name == 'torch' and 'falling back to torch' in note and '\n' not in note


def test_ply_round_trip(tmp_path, room):
    _, seq = room
    tsdf = TorchTSDF(MapConfig(engine='torch'))
    tsdf.integrate(seq.gt_depth_working(0), seq.frames[0].pose, seq.camera, rgb=seq.frames[0].rgb)
    mesh = tsdf.mesh()
    back = read_ply(write_ply(tmp_path / 'm.ply', mesh))
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(back.triangles, mesh.triangles)
    np.testing.assert_array_equal(back.colours, mesh.colours)
    assert back.triangles.max() < len(back.vertices)
    with pytest.raises(ValueError, match=r'\.ply'):
        write_ply(tmp_path / 'm.obj', mesh)


@pytest.mark.skipif(open3d_available() is not None, reason='Open3D is not installed (optional engine)')
def test_open3d_engine_agrees_with_torch(room):
    scene, seq = room
    o3d_map, _ = make_map(MapConfig(engine='open3d'))
    for i in range(0, len(seq), 4):
        o3d_map.integrate(seq.gt_depth_working(i), seq.frames[i].pose, seq.camera, rgb=seq.frames[i].rgb)
    dist = room_surface_distance(scene, o3d_map.mesh().vertices.astype(np.float64))
    assert np.median(dist) < 0.01
