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


@pytest.mark.parametrize(('power', 'expected'), [(1.0, 2.025), (2.0, 2.010)])
def test_confidence_power_weights_the_confident_depth_more(power, expected):
    """Weights 0.9 and 0.3 to the power: 2.025 m linearly, 2.010 m squared (0.81 against 0.09)."""
    tsdf = TorchTSDF(MapConfig(engine='torch', voxel_size=0.04, min_weight=0.0, confidence_power=power))
    tsdf.integrate(_wall(2.0), LOOK_DOWN_Z, CAMERA, confidence=np.full(_wall().shape, 0.9, np.float32))
    tsdf.integrate(_wall(2.1), LOOK_DOWN_Z, CAMERA, confidence=np.full(_wall().shape, 0.3, np.float32))
    assert abs(np.median(tsdf.mesh().vertices[:, 2]) - expected) < 0.004
    with pytest.raises(ValueError, match=r'map\.confidence_power'):
        MapConfig(confidence_power=0.0).validate()


@pytest.mark.parametrize(('depth_power', 'expected'), [(0.0, 1.050), (2.0, 1.018)])
def test_depth_power_weights_the_nearer_view_more(depth_power, expected):
    """The same wall seen at 1 m and, 10 cm off, at 2.1 m (equally confident): an unweighted
    mean puts it at 1.05 m, weights 1 / z^2 (1 against 0.227) at 1.018 m."""
    tsdf = TorchTSDF(MapConfig(engine='torch', voxel_size=0.04, min_weight=0.0, depth_power=depth_power))
    confident = np.full(_wall().shape, 0.9, np.float32)
    tsdf.integrate(_wall(1.0), LOOK_DOWN_Z, CAMERA, confidence=confident)
    back = np.eye(4)
    back[2, 3] = -1.0  # one metre further back
    tsdf.integrate(_wall(2.1), back, CAMERA, confidence=confident)
    v = tsdf.mesh().vertices
    middle = v[(np.abs(v[:, 0]) < 0.4) & (np.abs(v[:, 1]) < 0.3)]
    assert len(middle) > 100 and abs(np.median(middle[:, 2]) - expected) < 0.004
    with pytest.raises(ValueError, match=r'map\.depth_power'):
        MapConfig(depth_power=-1.0).validate()


def test_depth_range_and_nan_are_left_out():
    tsdf = TorchTSDF(MapConfig(engine='torch', max_depth=3.0))
    depth = _wall(4.0)
    depth[:, :40] = np.nan
    tsdf.integrate(depth, LOOK_DOWN_Z, CAMERA)
    assert tsdf.n_blocks == 0


def test_max_blocks_bounds_memory_and_evicts_the_farthest():
    config = MapConfig(engine='torch', voxel_size=0.04, max_blocks=60, archive=False)
    tsdf = TorchTSDF(config)
    poses = []
    for x in np.linspace(0.0, 6.0, 13):  # slide along a long wall: far more than 60 blocks
        T = np.eye(4)
        T[0, 3] = x
        poses.append(T)
        tsdf.integrate(_wall(1.5), T, CAMERA)
        assert tsdf.n_blocks <= 60
        assert tsdf.memory_bytes <= 60 * config.bytes_per_block + 60 * 3 * 8
    assert 0 < tsdf.lost_blocks <= tsdf.evicted_blocks  # no archive: dropped
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


def test_open3d_chosen_says_what_it_does_not_do(monkeypatch):
    """Open3D takes no per-pixel weights and has no archive: its line says both (as if installed)."""
    from depth_fusion_ros.mapping import engine

    monkeypatch.setattr(engine, 'open3d_available', lambda: None)
    open3d, note = engine._choose(MapConfig(engine='open3d'))
    assert open3d and 'no archive' in note and 'map.confidence_power and map.depth_power unused' in note
    plain = MapConfig(engine='open3d', confidence_power=1.0, depth_power=0.0, archive=False)
    _, note = engine._choose(plain)
    assert note == 'TSDF engine: open3d (VoxelBlockGrid) on cpu'


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


def _reference_update(tsdf: TorchTSDF, depth, weights, rgb, T_wc, camera) -> tuple:
    """Per voxel, in float64 numpy: the projective TSDF update the engine's docstring states
    (nearest pixel, ``sdf = depth - z``, kept where ``sdf > -truncation`` and the pixel has
    weight), from an empty map: expected (tsdf, weight, colour) of every allocated voxel."""
    b, n = tsdf.n_blocks, tsdf.config.block_size
    coords = (tsdf.block_coords[:b, None, :] * n + tsdf.local[None]).reshape(-1, 3).numpy()
    world = coords * tsdf.voxel
    cam = (world - T_wc[:3, 3]) @ T_wc[:3, :3]
    z = cam[:, 2]
    with np.errstate(divide='ignore', invalid='ignore'):
        u = np.floor(cam[:, 0] / z * camera.fx + camera.cx + 0.5)
        v = np.floor(cam[:, 1] / z * camera.fy + camera.cy + 0.5)
    inside = (z > 1e-6) & (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    pix = np.where(inside, v * camera.width + u, 0).astype(np.int64)
    obs_w = np.where(inside, weights.reshape(-1)[pix], 0.0)
    sdf = np.nan_to_num(depth.reshape(-1)[pix], nan=0.0) - z
    upd = (obs_w > 0) & (sdf > -tsdf.trunc)
    t = np.where(upd, np.minimum(1.0, sdf / tsdf.trunc), 1.0)
    c = np.where(upd[:, None], rgb.reshape(-1, 3)[pix].astype(np.float64), 0.0)
    return upd, t, np.where(upd, obs_w, 0.0), c, z


def test_integration_matches_the_per_voxel_formula_at_image_edges_and_behind_the_camera():
    """A wall at 0.25 m, tilted camera, NaN holes and varying confidence: the blocks reach
    behind the camera and past every image edge, where the vectorised lookups must read
    nothing (the bordered image, the voxels behind sent to its corner)."""
    rng = np.random.default_rng(3)
    camera = PinholeCamera(48, 36, 40.0, 40.0, 23.5, 17.5)
    depth = np.full((36, 48), 0.25, np.float32) + rng.uniform(0, 0.3, (36, 48)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.1] = np.nan
    confidence = rng.uniform(0.0, 1.0, depth.shape).astype(np.float32)
    rgb = rng.integers(0, 256, (36, 48, 3), dtype=np.uint8)
    angle = 0.3
    T = np.eye(4)
    T[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    T[:3, 3] = [0.1, -0.05, 0.02]
    tsdf = TorchTSDF(MapConfig(engine='torch', voxel_size=0.05, min_depth=0.1, min_weight=0.0))
    updated = tsdf.integrate(depth, T, camera, confidence=confidence, rgb=rgb)
    # The weight is the confidence to the default power, 2, over the depth to its default, 2.
    weights = np.where((depth >= 0.1) & (depth <= 6.0), confidence.astype(np.float64) ** 2, 0.0)
    weights /= np.where(np.isfinite(depth), depth.astype(np.float64), 1.0) ** 2
    upd, t, w, c, z = _reference_update(tsdf, depth, weights, rgb, T, camera)
    b = tsdf.n_blocks
    got_w = tsdf.weight[:b].reshape(-1).numpy()
    assert updated == upd.sum() > 300 and (~upd).sum() > 3000
    assert (z < 0).any() and (z > 0).any()  # some allocated voxels are behind the camera
    np.testing.assert_array_equal(got_w > 0, upd)
    np.testing.assert_allclose(got_w, w, atol=1e-6)
    np.testing.assert_allclose(tsdf.tsdf[:b].reshape(-1).numpy(), t, atol=1e-5)
    np.testing.assert_allclose(tsdf.colour[:b].transpose(1, 2).reshape(-1, 3).numpy(), c, atol=1e-3)


def test_block_deduplication_gives_the_distinct_cells_in_key_order():
    import torch

    from depth_fusion_ros.mapping.keys import pack
    from depth_fusion_ros.mapping.torch_tsdf import _distinct

    generator = torch.Generator().manual_seed(0)
    cells = torch.randint(-30, 30, (5000, 3), generator=generator) * torch.tensor([1, 2, 1])
    got = _distinct(cells)
    want = torch.unique(cells, dim=0)
    assert torch.equal(pack(got), torch.sort(pack(want)).values)
    assert torch.equal(_distinct(cells[:1]), cells[:1])
    wide = cells * 40  # a box of 2400³ cells: the sort fallback, same answer
    assert torch.equal(pack(_distinct(wide)), torch.sort(pack(torch.unique(wide, dim=0))).values)
