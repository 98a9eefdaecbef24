"""map_node over real DDS: a synthetic room integrated keyframe by keyframe, saved and checked."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped
from map_geometry import room_surface_distance
from map_inputs import FRAME, T0, MapInputs, call, call_save, make_room, map_node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image, PointCloud2

from depth_fusion_ros.data import messages as m
from depth_fusion_ros.mapping import MapConfig, make_map, read_ply
from depth_fusion_ros.mapping.block_surface import block_mesh
from depth_fusion_ros.nodes.map_node import MapNode
from depth_fusion_ros.nodes.testing import RosHarness

pytestmark = pytest.mark.usefixtures('one_torch_thread')

K = m.RCLPY


@pytest.fixture(scope='module')
def room():
    return make_room()


def test_integrates_a_synthetic_room_and_saves_a_mesh_on_its_geometry(room, tmp_path):
    scene, seq = room
    path = tmp_path / 'room.ply'
    with RosHarness() as ros:
        node = map_node(ros, save_path=str(path), points_rate=5.0, **{'map.engine': 'torch'})
        clouds = ros.collect(PointCloud2, '/depth_fusion/map/points')
        empty = call_save(ros)
        assert not empty.success and 'empty' in empty.message and not path.exists()
        inputs = MapInputs(ros)
        stamps = [T0 + k * 100_000_000 for k in range(8)]
        for k, stamp in enumerate(stamps):
            inputs.keyframe(seq, 2 * k, stamp)
        assert ros.wait_for(lambda: node.integrated == 8, 30.0), node.stats.snapshot().summary()
        assert ros.wait_for(lambda: len(clouds) > 0, 10.0)
        saved = call_save(ros)
        assert saved.success, saved.message
        assert '8 keyframes' in saved.message
    mesh = read_ply(path)
    dist = room_surface_distance(scene, mesh.vertices.astype(np.float64))
    assert len(mesh.triangles) > 1000
    assert np.median(dist) < 0.015 and np.percentile(dist, 90) < 0.04
    cloud = clouds[-1]
    assert cloud.header.frame_id == 'world'
    xyz = m.pointcloud2_to_numpy(cloud)
    assert 'rgb' in xyz or 'rgb' in {f.name for f in cloud.fields}


def test_pairs_by_stamp_drops_incomplete_and_bad_keyframes_and_saves_on_shutdown(room, tmp_path):
    _, seq = room
    path = tmp_path / 'shutdown.ply'
    with RosHarness() as ros:
        node = map_node(ros, save_path=str(path), save_on_shutdown=True, points_rate=0.0)
        inputs = MapInputs(ros)
        inputs.keyframe(seq, 0, T0, skip=('pose',))  # the pose of this keyframe never comes
        bad = m.pose_stamped_msg(seq.frames[2].pose, m.header_msg(T0 + 10**8, 'world', kind=K), kind=K)
        bad.pose.orientation.w = float('nan')
        inputs.keyframe(seq, 2, T0 + 10**8, pose=bad)  # unusable pose: dropped, node goes on
        inputs.keyframe(seq, 4, T0 + 2 * 10**8)
        assert ros.wait_for(lambda: node.integrated == 1, 30.0), node.stats.snapshot().summary()
        dropped = node.stats.snapshot().dropped
        assert dropped.get('bad_pose') == 1
        assert dropped.get('unpaired', 0) == 2  # keyframes 0 and 1 will never get their pose
    assert path.exists() and len(read_ply(path).vertices) > 100


@pytest.mark.parametrize('clear', [False, True])
def test_a_keyframe_pose_jump_is_noted_and_clears_the_map_when_asked(room, clear):
    """A relocalised pose source: the keyframes after it are 1 m away from where the map put
    the ones before. Noted either way; with ``clear_on_pose_jump`` the map starts again."""
    _, seq = room
    with RosHarness() as ros:
        node = map_node(ros, points_rate=0.0, clear_on_pose_jump=clear, **{'map.consistency_span': 0})
        inputs = MapInputs(ros)
        shift = np.eye(4)
        shift[0, 3] = 1.0
        for k in range(6):
            stamp = T0 + k * 100_000_000
            T = seq.frames[k].pose if k < 3 else shift @ seq.frames[k].pose
            world = m.header_msg(stamp, 'world', kind=K)
            inputs.keyframe(seq, k, stamp, pose=m.pose_stamped_msg(T, world, kind=K))
        integrated = 3 if clear else 6
        assert ros.wait_for(lambda: node.integrated == integrated and node.worker.idle(), 30.0), (
            node.stats.snapshot().summary()
        )
        snap = node.stats.snapshot()
        assert snap.noted.get('pose_jump') == 1 and snap.dropped == {}, snap.summary()
        cleared = call(ros, '/map_node/clear_map')
        assert cleared.success and f'{integrated} keyframes' in cleared.message
        assert node.integrated == 0 and node.extract()[0].is_empty


def test_a_young_map_follows_the_pose_sources_frame_and_an_established_one_keeps_its_own(room):
    """One stray keyframe posed in 'map' must not lock the map out of the pose source's frame
    for good: after three keyframes in a row posed in 'world', the young map starts over there
    (noted ``world_frame_changed``). A map of three keyframes keeps its frame: keyframes posed
    in another are dropped (``frame_mismatch``) however many come, and after ~/clear_map the
    next keyframe sets the frame again."""
    _, seq = room
    with RosHarness() as ros:
        node = map_node(ros, points_rate=0.0, **{'map.consistency_span': 0})
        inputs = MapInputs(ros)

        def send(k: int, frame: str) -> None:
            stamp = T0 + k * 100_000_000
            pose = m.pose_stamped_msg(seq.frames[k].pose, m.header_msg(stamp, frame, kind=K), kind=K)
            inputs.keyframe(seq, k, stamp, pose=pose)

        def settled(integrated: int, mismatched: int) -> bool:
            snap = node.stats.snapshot()
            done = node.integrated == integrated and snap.dropped.get('frame_mismatch', 0) == mismatched
            return done and node.worker.idle()

        send(0, 'map')  # a stray pose in another node's frame comes first
        assert ros.wait_for(lambda: settled(1, 0), 30.0), node.stats.snapshot().summary()
        for k in range(1, 6):
            send(k, 'world')
        assert ros.wait_for(lambda: settled(3, 2), 30.0), node.stats.snapshot().summary()
        assert node.stats.snapshot().noted.get('world_frame_changed') == 1
        assert node.extract()[1] == 'world'

        for k in range(6, 10):  # an established map: another frame is refused, however long
            send(k, 'odom')
        assert ros.wait_for(lambda: settled(3, 6), 30.0), node.stats.snapshot().summary()
        assert node.stats.snapshot().noted.get('world_frame_changed') == 1 and node.extract()[1] == 'world'
        cleared = call(ros, '/map_node/clear_map')
        assert cleared.success and '3 keyframes' in cleared.message
        send(10, 'odom')
        assert ros.wait_for(lambda: settled(1, 6), 30.0), node.stats.snapshot().summary()
        assert node.extract()[1] == 'odom'


def test_bad_parameters_fail_at_start():
    with RosHarness() as ros:
        with pytest.raises(ValueError, match='save_path'):
            MapNode(context=ros.context, parameter_overrides=[Parameter('save_path', value='map.obj')])
        with pytest.raises(ValueError, match=r'map\.engine'):
            MapNode(context=ros.context, parameter_overrides=[Parameter('map.engine', value='nvblox')])
        with pytest.raises(ValueError, match='camera_from_pose_frame'):
            bad = Parameter('camera_from_pose_frame', value=[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 2.0])
            MapNode(context=ros.context, parameter_overrides=[bad])


def test_multi_view_node_publishes_each_keyframe_pose_with_its_stamp(room):
    """What the map node pairs on: the keyframe's interpolated pose, stamped like its image."""
    from depth_fusion_ros.nodes.multi_view_node import MultiViewNode

    _, seq = room
    with RosHarness() as ros:
        params = [Parameter('keyframe_every', value=3), Parameter('queue_size', value=8)]
        params.append(Parameter('filter.max_lag_frames', value=0))  # every frame, as a paced replay
        params.append(Parameter('filter.max_update_rate', value=0.0))
        ros.add(MultiViewNode(context=ros.context, parameter_overrides=params))
        poses = ros.collect(PoseStamped, '/depth_fusion/keyframe/pose')
        keyframes = ros.collect(Image, '/depth_fusion/keyframe/image')
        image = ros.publisher(Image, '/camera/rgb/image_color')
        info = ros.publisher(CameraInfo, '/camera/rgb/camera_info')
        pose = ros.publisher(PoseStamped, '/camera/pose')
        assert ros.wait_for_subscribers([image, info, pose])
        stamps = [T0 + k * 33_000_000 for k in range(8)]
        for k, stamp in enumerate(stamps):
            pose.publish(m.pose_stamped_msg(seq.frames[k].pose, m.header_msg(stamp, 'world', kind=K), kind=K))
            header = m.header_msg(stamp, FRAME, kind=K)
            info.publish(m.camera_info_msg(seq.camera, header, kind=K))
            image.publish(m.rgb_image_msg(seq.frames[k].rgb, header, kind=K))
        assert ros.wait_for(lambda: len(poses) == 2 and len(keyframes) == 2, 20.0)
    assert [m.stamp_to_ns(p.header.stamp) for p in poses] == [stamps[3], stamps[6]]
    assert [m.stamp_to_ns(k.header.stamp) for k in keyframes] == [stamps[3], stamps[6]]
    assert all(p.header.frame_id == 'world' for p in poses)
    np.testing.assert_allclose(m.pose_stamped_to_matrix(poses[0]), seq.frames[3].pose, atol=1e-6)


def test_map_settings_of_a_graph_run(tmp_path):
    from depth_fusion_ros.nodes.graph import RunOptions
    from depth_fusion_ros.nodes.graph.param_merge import map_overrides
    from depth_fusion_ros.nodes.map_node import PARAMETERS

    params = map_overrides(RunOptions(bag=tmp_path, save_map=tmp_path / 'map.ply', device='cpu'))
    assert params['save_on_shutdown'] is True and params['save_path'].endswith('map.ply')
    declared = {spec.name: spec for spec in PARAMETERS} | {
        'queue_policy': None,
        'queue_size': None,
        'qos_depth': None,
    }
    assert set(params) <= set(declared)
    assert 'save_path' not in map_overrides(RunOptions(bag=tmp_path, map=True, realtime=True))
    with pytest.raises(ValueError, match='ply'):
        map_overrides(RunOptions(bag=tmp_path, save_map=Path('map.obj')))


def test_the_surface_is_extracted_outside_the_maps_lock_and_a_slow_one_is_published_less_often(
    room, monkeypatch
):
    """Extracting a large map takes seconds (0.35 ms a block): it must not hold the lock that
    integration needs, and it may take at most a quarter of a core (``points_throttled``)."""
    from depth_fusion_ros.nodes import map_points

    _, seq = room
    lock_free, real_extract = [], map_points.block_mesh

    def slow_extract(blocks, **options):
        lock_free.append(node._lock.acquire(timeout=0))  # integration could take it meanwhile
        if lock_free[-1]:
            node._lock.release()
        time.sleep(0.3)
        return real_extract(blocks, **options)

    monkeypatch.setattr(map_points, 'block_mesh', slow_extract)
    with RosHarness() as ros:
        node = map_node(ros, points_rate=20.0, **{'map.consistency_span': 0})
        clouds = ros.collect(PointCloud2, '/depth_fusion/map/points')
        inputs = MapInputs(ros)
        for k in range(4):
            inputs.keyframe(seq, 2 * k, T0 + k * 100_000_000)
            time.sleep(0.1)
        assert ros.wait_for(lambda: node.integrated == 4 and len(clouds) > 0, 30.0), (
            node.stats.snapshot().summary()
        )
        assert ros.wait_for(lambda: node.stats.snapshot().noted.get('points_throttled', 0) > 0, 10.0)
        node.points.wait(5.0)
    assert lock_free and all(lock_free)
    assert node.points.last_seconds >= 0.3


def test_a_map_file_keeps_the_map_across_a_restart(room, tmp_path):
    """map_file: written beside the mesh by ~/save_map, loaded by the next map_node, which
    serves and extends it; a file it cannot use stops the node at start with one line."""
    scene, seq = room
    map_file = tmp_path / 'room.tsdf'
    with RosHarness() as ros:
        node = map_node(ros, save_path=str(tmp_path / 'a.ply'), map_file=str(map_file), points_rate=0.0)
        inputs = MapInputs(ros)
        for k in range(4):
            inputs.keyframe(seq, 2 * k, T0 + k * 100_000_000)
        assert ros.wait_for(lambda: node.integrated == 4 and node.worker.idle(), 30.0)
        saved = call_save(ros)
        assert saved.success and f'map written to {map_file}' in saved.message, saved.message
        blocks = node.map.n_blocks
    assert map_file.exists()
    with RosHarness() as ros:
        node = map_node(ros, save_path=str(tmp_path / 'b.ply'), map_file=str(map_file), points_rate=0.0)
        assert node.map.n_blocks == blocks and node.integrated == 0
        saved = call_save(ros)  # the loaded map, before any keyframe
        assert saved.success, saved.message
        # The file carried the keyframes the map kept: a rebuild at corrected poses integrates
        # them (at half resolution, so a few blocks fewer), nothing is fixed.
        assert len(node.corrector.store.entries) == 4 and node.corrector.base is None
        node.corrector.start_rebuild()
        assert ros.wait_for(lambda: node.corrector.rebuilds == 1 and not node.corrector.busy(), 30.0)
        assert 0.8 * blocks < node.map.n_blocks <= blocks
    dist = room_surface_distance(scene, read_ply(tmp_path / 'b.ply').vertices.astype(np.float64))
    assert np.median(dist) < 0.015
    with RosHarness() as ros, pytest.raises(ValueError, match=r'map_node: map file .*room.tsdf: 4 cm voxels'):
        map_node(ros, map_file=str(map_file), **{'map.voxel_size': 0.05})


def test_a_bounded_map_archives_what_it_evicts_and_saves_the_whole_map(room, tmp_path):
    """map.max_blocks below what the room needs (each keyframe sees ~400 of its ~510 blocks): the
    evicted blocks go to the disk archive and come back, so the saved mesh is the mesh of the
    same keyframes mapped without a cap; beside it, a node with map.archive off counts the
    blocks it loses. The archive's directory goes with the node."""
    _, seq = room
    archive = tmp_path / 'archive'
    cap = {'map.engine': 'torch', 'map.max_blocks': 450}
    with RosHarness() as ros:
        node = map_node(
            ros,
            save_path=str(tmp_path / 'bounded.ply'),
            points_rate=0.0,
            **cap,
            **{'map.archive_dir': str(archive)},
        )
        off = ros.add(
            MapNode(
                'map_off',
                context=ros.context,
                parameter_overrides=[
                    Parameter(k, value=v)
                    for k, v in {'queue_size': 16, 'points_rate': 0.0, 'map.archive': False, **cap}.items()
                ],
            )
        )
        inputs = MapInputs(ros)
        for k in range(8):
            inputs.keyframe(seq, 2 * k, T0 + k * 100_000_000)
        both = lambda: node.integrated == off.integrated == 8 and node.worker.idle() and off.worker.idle()  # noqa: E731
        assert ros.wait_for(both, 30.0), node.stats.snapshot().summary()
        saved = call_save(ros)
        assert saved.success, saved.message
        diagnostics = node.diagnostic_extra()
        assert diagnostics['blocks evicted'] > 0 and diagnostics['blocks archived on disk'] > 0
        assert diagnostics['blocks lost'] == diagnostics['blocks keyframes needed beyond the cap'] == 0
        assert diagnostics['blocks'] <= 450 and any(archive.iterdir())
        lost = off.diagnostic_extra()['blocks lost']
        assert lost > 0 and off.stats.snapshot().dropped.get('blocks_lost', 0) == lost
        # The published cloud holds the archived blocks' surface too (mapping/archived_surface.py).
        cloud, _ = node.points._surface()
        archived = node.diagnostic_extra()['archived blocks in the published cloud']
        resident = block_mesh(node.map.engine.blocks(), triangles=False).vertices
    assert not any(archive.iterdir())  # deleted with the node
    uncapped, _ = make_map(MapConfig(engine='torch'))
    for k in range(8):
        depth = seq.gt_depth_working(2 * k)
        confidence = np.full(depth.shape, 0.8, np.float32)
        uncapped.integrate(
            depth, seq.frames[2 * k].pose, seq.camera, confidence=confidence, rgb=seq.frames[2 * k].rgb
        )
    uncapped.flush()
    expected, got = uncapped.mesh().vertices, read_ply(tmp_path / 'bounded.ply').vertices
    assert uncapped.n_blocks > 450 and len(got) == len(expected) > 5000
    np.testing.assert_allclose(
        got[np.lexsort(got.T[::-1])], expected[np.lexsort(expected.T[::-1])], atol=1e-6
    )
    assert archived == diagnostics['blocks archived on disk'] and len(cloud.vertices) > len(resident)
    in_mesh = {tuple(v) for v in np.round(got.astype(np.float64), 4)}
    on = sum(tuple(v) in in_mesh for v in np.round(cloud.vertices.astype(np.float64), 4))
    assert on == len(cloud.vertices) == len(got), (on, len(cloud.vertices), len(got))  # the whole map's


def test_an_archive_directory_that_cannot_be_written_is_said_at_start(tmp_path):
    """One warning line at start (the archive is made only when the map first evicts, so the
    node still starts: the blocks it would evict are then counted as lost)."""
    blocker = tmp_path / 'a_file'
    blocker.write_text('not a directory')
    with RosHarness() as ros:
        node = map_node(
            ros, points_rate=0.0, **{'map.engine': 'torch', 'map.archive_dir': str(blocker / 'x')}
        )
        assert node.map.engine.archive is not None
    from depth_fusion_ros.nodes.map_node import _writable

    assert not _writable(blocker / 'x') and _writable(tmp_path / 'new' / 'dir')
