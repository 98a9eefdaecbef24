"""map_node over real DDS: a loop closure's corrected trajectory rebuilds the map at the corrected poses."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from geometry_msgs.msg import TransformStamped
from map_geometry import room_surface_distance
from map_inputs import T0, MapInputs, call_save, make_room, map_node
from nav_msgs.msg import Path as PathMsg
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import TimeReference

from depth_fusion_ros.data import messages as m
from depth_fusion_ros.mapping import read_ply
from depth_fusion_ros.nodes.posing import (
    TOPIC_POSING_TIME,
    TOPIC_POSING_TRANSFORM,
    TOPIC_REPOSED_KEYFRAMES,
    posing_qos,
    reposed_msg,
    time_reference_msg,
    transform_msg,
)
from depth_fusion_ros.nodes.qos import latched_qos
from depth_fusion_ros.nodes.testing import RosHarness
from depth_fusion_ros.pose_corrections import Posing

pytestmark = pytest.mark.usefixtures('one_torch_thread')

K = m.RCLPY
STEP = 100_000_000  # keyframes 0.1 s apart, at frames 0, 2, 4, ...


@pytest.fixture(scope='module')
def room():
    return make_room()


def _drift(k: float) -> np.ndarray:
    """The pose source's drift at keyframe ``k``: 2.5 cm and 0.8 deg more each keyframe."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler('y', 0.8 * k, degrees=True).as_matrix()
    T[:3, 3] = (0.025 * k, 0.0, 0.01 * k)
    return T


def _path(poses: list[tuple[int, np.ndarray]], frame: str = 'world') -> PathMsg:
    msg = PathMsg()
    msg.header = m.header_msg(T0 + 10 * STEP, frame, kind=K)
    msg.poses = [m.pose_stamped_msg(T, m.header_msg(stamp, frame, kind=K), kind=K) for stamp, T in poses]
    return msg


def _map_from_told_poses(ros: RosHarness, seq, path, told, posings: int = 0) -> tuple:
    """map_node, and a publisher of corrected trajectories, after eight keyframes (frames 0, 2,
    ..., 14) were integrated at the poses ``told(k, true_pose)`` gives (once the node heard
    ``posings`` posing messages, when the test sent some)."""
    node = map_node(ros, save_path=str(path), points_rate=0.0, **{'map.engine': 'torch'})
    assert ros.wait_for(lambda: node.stats.snapshot().received.get('posing', 0) >= posings, 10.0)
    inputs = MapInputs(ros)
    fix = ros.publisher(PathMsg, '/camera/corrected_path')
    assert ros.wait_for_subscribers([fix])
    for k in range(8):
        stamp = T0 + k * STEP
        world = m.header_msg(stamp, 'world', kind=K)
        pose = m.pose_stamped_msg(told(k, seq.frames[2 * k].pose), world, kind=K)
        inputs.keyframe(seq, 2 * k, stamp, pose=pose)
    assert ros.wait_for(lambda: node.integrated == 8 and node.worker.idle(), 30.0), (
        node.stats.snapshot().summary()
    )
    return node, fix


def _saved_distances(ros: RosHarness, scene, path) -> np.ndarray:
    saved = call_save(ros)
    assert saved.success, saved.message
    return room_surface_distance(scene, read_ply(path).vertices.astype(np.float64))


def test_a_corrected_trajectory_rebuilds_the_map_at_the_corrected_poses(room, tmp_path):
    """Eight keyframes integrated at drifting poses (up to 17 cm and 5.6 deg off) smear the room;
    the SLAM's corrected trajectory, at its own stamps (between ours) and ours, puts it back."""
    scene, seq = room
    path = tmp_path / 'room.ply'
    with RosHarness() as ros:
        node, fix = _map_from_told_poses(ros, seq, path, lambda k, T: _drift(k) @ T)
        smeared = _saved_distances(ros, scene, path)
        # The SLAM's keyframes: the frames between ours (odd frames, 50 ms after ours), and our last.
        slam = [(T0 + k * STEP + STEP // 2, seq.frames[2 * k + 1].pose) for k in range(7)]
        slam.append((T0 + 7 * STEP, seq.frames[14].pose))
        fix.publish(_path(slam, frame='map'))  # another world frame: refused, the map untouched
        assert ros.wait_for(lambda: node.stats.snapshot().dropped.get('frame_mismatch') == 1, 10.0)
        with_bad = _path(slam)
        with_bad.poses[3].pose.orientation.w = float('nan')  # one unusable pose: dropped, the rest used
        fix.publish(with_bad)
        assert ros.wait_for(lambda: node.corrector.rebuilds == 1 and not node.corrector.busy(), 60.0), (
            node.stats.snapshot().summary()
        )
        assert node.stats.snapshot().dropped.get('bad_pose') == 1
        corrected = _saved_distances(ros, scene, path)
        fix.publish(_path(slam))  # the same trajectory again: nothing moves, no rebuild
        assert ros.wait_for(lambda: node.stats.snapshot().published.get('corrections') == 2, 10.0)
        assert node.corrector.rebuilds == 1 and not node.corrector.busy()
        diagnostics = node.diagnostic_extra()
    assert np.percentile(smeared, 90) > 0.06, np.percentile(smeared, 90)
    assert np.median(corrected) < 0.008 and np.percentile(corrected, 90) < 0.02, (
        np.median(corrected),
        np.percentile(corrected, 90),
    )
    assert diagnostics['keyframes kept for a rebuild'] == 8
    assert diagnostics['rebuilds at corrected poses'] == 1


def test_a_relocalisation_with_its_corrected_trajectory_brings_the_old_keyframes_into_the_new_world(
    room, tmp_path
):
    """The pose source jumps 0.8 m at keyframe 4 (a pose jump: noted) and then publishes the
    corrected trajectory of its keyframes 0-2. Keyframe 3, after the path's end but before the
    jump, is in the old world too and takes the last correction: the whole map ends up in the
    new world, where the saved mesh lies on the room moved by the correction."""
    scene, seq = room
    path = tmp_path / 'room.ply'
    shift = np.eye(4)
    shift[:3, 3] = (0.8, 0.0, -0.3)
    with RosHarness() as ros:
        node, fix = _map_from_told_poses(ros, seq, path, lambda k, T: T if k < 4 else shift @ T)
        fix.publish(_path([(T0 + k * STEP, shift @ seq.frames[2 * k].pose) for k in range(3)]))
        assert ros.wait_for(lambda: node.corrector.rebuilds == 1 and not node.corrector.busy(), 60.0), (
            node.stats.snapshot().summary()
        )
        assert node.stats.snapshot().noted.get('pose_jump') == 1
        moved_scene = _shifted_scene(scene, shift[:3, 3])
        dist = _saved_distances(ros, moved_scene, path)
    assert np.median(dist) < 0.01 and np.percentile(dist, 90) < 0.03, (
        np.median(dist),
        np.percentile(dist, 90),
    )


def _shifted_scene(scene, offset: np.ndarray):
    """The synthetic room moved by ``offset`` (its boxes' centres): where a map in the corrected
    world should lie."""
    return dataclasses.replace(scene, centres=scene.centres + offset)


def test_a_corrected_trajectory_after_a_restart_moves_the_map_the_earlier_run_saved(room, tmp_path):
    """A robot maps at drifting poses and stops (map_file written with the keyframes it kept);
    the next map_node loads it, and the SLAM's corrected trajectory of the earlier keyframes
    rebuilds it at the corrected poses: the saved mesh then lies on the room."""
    scene, seq = room
    map_file = tmp_path / 'room.tsdf'
    with RosHarness() as ros:
        node = map_node(ros, map_file=str(map_file), save_path=str(tmp_path / 'a.ply'), points_rate=0.0)
        inputs = MapInputs(ros)
        for k in range(8):
            world = m.header_msg(T0 + k * STEP, 'world', kind=K)
            pose = m.pose_stamped_msg(_drift(k) @ seq.frames[2 * k].pose, world, kind=K)
            inputs.keyframe(seq, 2 * k, T0 + k * STEP, pose=pose)
        assert ros.wait_for(lambda: node.integrated == 8 and node.worker.idle(), 30.0)
        smeared = _saved_distances(ros, scene, tmp_path / 'a.ply')
    with RosHarness() as ros:
        path = tmp_path / 'b.ply'
        node = map_node(ros, map_file=str(map_file), save_path=str(path), points_rate=0.0)
        assert len(node.corrector.store.entries) == 8 and node.corrector.base is None
        fix = ros.publisher(PathMsg, '/camera/corrected_path')
        assert ros.wait_for_subscribers([fix])
        fix.publish(_path([(T0 + k * STEP, seq.frames[2 * k].pose) for k in range(8)]))
        assert ros.wait_for(lambda: node.corrector.rebuilds == 1 and not node.corrector.busy(), 60.0), (
            node.stats.snapshot().summary()
        )
        corrected = _saved_distances(ros, scene, path)
    assert np.percentile(smeared, 90) > 0.06
    assert np.median(corrected) < 0.01 and np.percentile(corrected, 90) < 0.025, (
        np.median(corrected),
        np.percentile(corrected, 90),
    )


def test_the_rebuild_compares_each_keyframe_through_the_posing_multi_view_node_said(room, tmp_path):
    """multi_view_node turned the camera 2 deg (a mount check) and reads poses 30 ms after the
    image stamps, and says so on the posing topics. The SLAM's trajectory restated as it was
    moves nothing (compared in the camera frame with the configured mount alone, it moved every
    keyframe by the turn and a rebuild dropped it); with the drift taken out, the rebuilt map
    lies on the room, turn and offset kept."""
    scene, seq = room
    path = tmp_path / 'room.ply'
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler('x', 2.0, degrees=True).as_matrix()
    mount = np.eye(4)
    mount[:3, :3] = Rotation.from_euler('z', 90.0, degrees=True).as_matrix()
    mount[:3, 3] = (0.05, 0.0, 0.1)
    posing = Posing(mount @ turn, 0.03)
    offset_ns = 30_000_000
    with RosHarness() as ros:
        said = ros.publisher(TransformStamped, '/' + TOPIC_POSING_TRANSFORM, latched_qos())
        said_time = ros.publisher(TimeReference, '/' + TOPIC_POSING_TIME, latched_qos())
        said.publish(transform_msg(posing, T0, 'camera', kind=K))
        said_time.publish(time_reference_msg(posing, T0, 'test', kind=K))
        node, fix = _map_from_told_poses(ros, seq, path, lambda k, T: _drift(k) @ T, posings=2)
        assert all(e.posing is not None for e in node.corrector.store.entries)
        body = np.linalg.inv(posing.T_pose_cam)
        told = [(T0 + k * STEP + offset_ns, _drift(k) @ seq.frames[2 * k].pose @ body) for k in range(8)]
        fix.publish(_path(told))  # the pose source's poses as they were: nothing moves
        assert ros.wait_for(lambda: node.stats.snapshot().published.get('corrections') == 1, 10.0)
        assert node.corrector.rebuilds == 0 and not node.corrector.busy(), node.stats.snapshot().summary()
        slam = [(T0 + k * STEP + STEP // 2 + offset_ns, seq.frames[2 * k + 1].pose @ body) for k in range(7)]
        slam.append((T0 + 7 * STEP + offset_ns, seq.frames[14].pose @ body))
        fix.publish(_path(slam))
        assert ros.wait_for(lambda: node.corrector.rebuilds == 1 and not node.corrector.busy(), 60.0), (
            node.stats.snapshot().summary()
        )
        dist = _saved_distances(ros, scene, path)
        bad = transform_msg(posing, T0 + 9 * STEP, 'camera', kind=K)
        bad.transform.rotation.w = float('nan')  # not a rotation: dropped, counted, the posing kept
        said.publish(bad)
        assert ros.wait_for(lambda: node.stats.snapshot().dropped.get('bad_posing') == 1, 10.0)
        assert node.corrector.posings.latest is not None and len(node.corrector.posings.transforms) == 1
        assert node.corrector.rebuilds == 1
    assert np.median(dist) < 0.008 and np.percentile(dist, 90) < 0.02, (
        np.median(dist),
        np.percentile(dist, 90),
    )


def test_a_mount_turn_multi_view_node_takes_re_poses_the_keyframes_mapped_before_it(room, tmp_path):
    """multi_view_node's mount check finds the camera turned 2 deg only after a stretch of the
    run: the keyframes before were posed without the turn. The map node hears the new posing,
    re-poses the keyframes it kept (and one in flight, posed before the turn and arriving after
    it) and rebuilds: the map lies on the room, where those keyframes had smeared it."""
    scene, seq = room
    path = tmp_path / 'room.ply'
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler('x', 2.0, degrees=True).as_matrix()
    told, found = Posing(np.eye(4)), Posing(turn)
    unturned = np.linalg.inv(turn)
    with RosHarness() as ros:
        said = ros.publisher(TransformStamped, '/' + TOPIC_POSING_TRANSFORM, latched_qos())
        said.publish(transform_msg(told, T0, 'camera', kind=K))
        node = map_node(ros, save_path=str(path), points_rate=0.0, **{'map.engine': 'torch'})
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('posing', 0) == 1, 10.0)
        inputs = MapInputs(ros)

        def keyframe(k: int, T: np.ndarray) -> None:
            pose = m.pose_stamped_msg(T, m.header_msg(T0 + k * STEP, 'world', kind=K), kind=K)
            inputs.keyframe(seq, 2 * k, T0 + k * STEP, pose=pose)

        for k in range(3):  # posed without the turn: the true pose turned back
            keyframe(k, seq.frames[2 * k].pose @ unturned)
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('depth', 0) == 3, 10.0)
        said.publish(transform_msg(found, T0 + 3 * STEP + STEP // 2, 'camera', kind=K))
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('posing', 0) == 2, 10.0)
        keyframe(3, seq.frames[6].pose @ unturned)  # in flight: posed before the turn, here after it
        for k in range(4, 8):
            keyframe(k, seq.frames[2 * k].pose)
        assert ros.wait_for(
            lambda: node.integrated == 8 and node.worker.idle() and not node.corrector.busy(), 30.0
        )
        assert all(
            e.posing is not None and np.allclose(e.posing.T_pose_cam, turn)
            for e in node.corrector.store.entries
        )
        dist = _saved_distances(ros, scene, path)
        rebuilds = node.corrector.rebuilds
    assert rebuilds <= 1
    assert np.median(dist) < 0.008 and np.percentile(dist, 90) < 0.02, (
        np.median(dist),
        np.percentile(dist, 90),
    )


def test_a_map_node_started_after_a_mount_turn_hears_the_posing_before_it(room, tmp_path):
    """The posing topics keep the last posings, not only the newest: a map_node started after
    multi_view_node turned the camera hears the posing before the turn too, so keyframes posed
    before it and still in flight are re-posed in the turn (with the newest posing alone, they
    were taken as posed in it and mapped 2 deg off)."""
    scene, seq = room
    path = tmp_path / 'room.ply'
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler('x', 2.0, degrees=True).as_matrix()
    unturned = np.linalg.inv(turn)
    with RosHarness() as ros:
        said = ros.publisher(TransformStamped, '/' + TOPIC_POSING_TRANSFORM, posing_qos())
        said.publish(transform_msg(Posing(np.eye(4)), T0, 'camera', kind=K))
        said.publish(transform_msg(Posing(turn), T0 + 3 * STEP + STEP // 2, 'camera', kind=K))
        node = map_node(ros, save_path=str(path), points_rate=0.0, **{'map.engine': 'torch'})
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('posing', 0) == 2, 10.0)
        assert [stamp for stamp, _ in node.corrector.posings.transforms] == [T0, T0 + 3 * STEP + STEP // 2]
        inputs = MapInputs(ros)
        for k in range(8):  # 0-2 posed before the turn (the true pose turned back), in flight
            T = seq.frames[2 * k].pose @ (unturned if k < 3 else np.eye(4))
            pose = m.pose_stamped_msg(T, m.header_msg(T0 + k * STEP, 'world', kind=K), kind=K)
            inputs.keyframe(seq, 2 * k, T0 + k * STEP, pose=pose)
        assert ros.wait_for(lambda: node.integrated == 8 and node.worker.idle(), 30.0), (
            node.stats.snapshot().summary()
        )
        entries = {round(e.stamp, 3): e.T_wc for e in node.corrector.store.entries}
        dist = _saved_distances(ros, scene, path)
    early = {k: round((T0 + k * STEP) / 1e9, 3) for k in range(3)}
    early = {k: entries[stamp] for k, stamp in early.items() if stamp in entries}
    assert early, sorted(entries)
    for k, T_wc in early.items():
        np.testing.assert_allclose(T_wc, seq.frames[2 * k].pose, atol=1e-6)
    assert np.median(dist) < 0.008 and np.percentile(dist, 90) < 0.02, (
        np.median(dist),
        np.percentile(dist, 90),
    )


def test_a_time_offset_correction_re_poses_the_keyframes_mapped_before_it(room, tmp_path):
    """multi_view_node read the poses 50 ms late until its time offset check corrected it; it
    then reads the keyframes before again at the corrected offset and publishes them
    (``reposed_keyframes``, here before the ``pose_time`` of the posing it belongs to). The map
    node moves the kept keyframes, those in the consistency window and one still in flight,
    rebuilds, and keeps them at the corrected offset: the map lies on the room."""
    scene, seq = room
    path = tmp_path / 'room.ply'
    corrected_from = T0 + 4 * STEP + STEP // 2
    with RosHarness() as ros:
        said_time = ros.publisher(TimeReference, '/' + TOPIC_POSING_TIME, posing_qos())
        reposed = ros.publisher(PathMsg, '/' + TOPIC_REPOSED_KEYFRAMES, posing_qos())
        said_time.publish(time_reference_msg(Posing(np.eye(4), 0.05), T0, 'test', kind=K))
        node = map_node(ros, save_path=str(path), points_rate=0.0, **{'map.engine': 'torch'})
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('posing', 0) == 1, 10.0)
        inputs = MapInputs(ros)

        def keyframe(k: int, T: np.ndarray, skip: tuple[str, ...] = ()) -> None:
            pose = m.pose_stamped_msg(T, m.header_msg(T0 + k * STEP, 'world', kind=K), kind=K)
            inputs.keyframe(seq, 2 * k, T0 + k * STEP, skip=skip, pose=pose)

        for k in range(4):  # posed 50 ms late: at the next frame's pose
            keyframe(k, seq.frames[2 * k + 1].pose)
        keyframe(4, seq.frames[9].pose, skip=('depth',))  # in flight: its depth comes after the correction
        assert ros.wait_for(
            lambda: (
                node.stats.snapshot().received.get('depth', 0) == 4
                and node.worker.idle()
                and len(node.corrector.store.entries) >= 1
            ),
            30.0,
        ), node.stats.snapshot().summary()
        kept_before = len(node.corrector.store.entries)
        poses = [(T0 + k * STEP, seq.frames[2 * k].pose) for k in range(5)]  # read again in sync
        reposed.publish(reposed_msg(corrected_from, 'world', poses, kind=K))
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('reposed_keyframes', 0) == 1, 10.0)
        assert node.corrector.rebuilds == 0  # its posing's pose_time not heard yet: waits for it
        said_time.publish(time_reference_msg(Posing(np.eye(4), 0.0), corrected_from, 'test', kind=K))
        assert ros.wait_for(lambda: node.stats.snapshot().published.get('reposings', 0) == 1, 10.0)
        keyframe(4, seq.frames[9].pose, skip=('image', 'info', 'confidence', 'pose'))
        for k in range(5, 8):
            keyframe(k, seq.frames[2 * k].pose)
        assert ros.wait_for(
            lambda: node.integrated == 8 and node.worker.idle() and not node.corrector.busy(), 30.0
        ), node.stats.snapshot().summary()
        entries = {e.stamp: e for e in node.corrector.store.entries}
        dist = _saved_distances(ros, scene, path)
        rebuilds = node.corrector.rebuilds
    assert kept_before >= 1 and rebuilds == 1
    for k in range(5):
        e = entries.get(m.ns_to_sec(T0 + k * STEP))
        if e is not None:
            np.testing.assert_allclose(e.T_wc, seq.frames[2 * k].pose, atol=1e-6)
            assert e.posing.offset == 0.0
    # 1.4 mm and 4.1 mm; with the keyframes left where they were mapped, 6.4 mm and 17.6 mm.
    assert np.median(dist) < 0.004 and np.percentile(dist, 90) < 0.01, (
        np.median(dist),
        np.percentile(dist, 90),
    )


def test_a_time_offset_correction_with_no_keyframes_kept_moves_the_rest_and_counts_what_stays(room, tmp_path):
    """reintegration_max_mb 0 keeps no keyframe to rebuild from: the keyframes integrated before
    the correction stay where they were mapped, counted and said; those still in the consistency
    window and in flight move. Re-read poses for a posing no pose_time said are dropped, counted,
    when the next ones come."""
    _, seq = room
    corrected_from = T0 + 4 * STEP + STEP // 2
    with RosHarness() as ros:
        said_time = ros.publisher(TimeReference, '/' + TOPIC_POSING_TIME, posing_qos())
        reposed = ros.publisher(PathMsg, '/' + TOPIC_REPOSED_KEYFRAMES, posing_qos())
        said_time.publish(time_reference_msg(Posing(np.eye(4), 0.05), T0, 'test', kind=K))
        node = map_node(ros, points_rate=0.0, reintegration_max_mb=0.0, **{'map.engine': 'torch'})
        assert ros.wait_for(lambda: node.stats.snapshot().received.get('posing', 0) == 1, 10.0)
        inputs = MapInputs(ros)
        for k in range(4):
            pose = m.pose_stamped_msg(
                seq.frames[2 * k + 1].pose, m.header_msg(T0 + k * STEP, 'world', kind=K), kind=K
            )
            inputs.keyframe(seq, 2 * k, T0 + k * STEP, pose=pose)
        # All four taken into the map (a depth received is not yet a keyframe paired and handed
        # to the worker: an idle worker then, with the fourth still to come, read one less).
        assert ros.wait_for(lambda: node.integrated == 4 and node.worker.idle(), 30.0)
        waiting = len(node.map.waiting_keys())
        poses = [(T0 + k * STEP, seq.frames[2 * k].pose) for k in range(5)]  # 4: not come yet
        reposed.publish(reposed_msg(T0 + 99 * STEP, 'world', poses, kind=K))  # no pose_time says it
        reposed.publish(reposed_msg(corrected_from, 'world', poses, kind=K))
        said_time.publish(time_reference_msg(Posing(np.eye(4), 0.0), corrected_from, 'test', kind=K))
        assert ros.wait_for(lambda: node.stats.snapshot().published.get('reposings', 0) == 1, 10.0)
        moved = {float(key): T for key, T in node.map.window_keyframes() if key in node.map.waiting_keys()}
        extra = node.diagnostic_extra()
        dropped = node.stats.snapshot().dropped
    assert dropped == {'reposed_unmatched': 1}, dropped  # replaced by the one its pose_time said
    integrated = 4 - waiting
    assert integrated >= 1 and node.corrector.rebuilds == 0
    assert extra['keyframes integrated and not kept at a time offset correction'] == integrated
    assert extra['keyframes re-read at a corrected time offset'] == waiting + 1  # + the one in flight
    assert len(moved) == waiting >= 1
    for stamp, T in moved.items():
        k = round((stamp - T0 / 1e9) / (STEP / 1e9))
        np.testing.assert_allclose(T, seq.frames[2 * k].pose, atol=1e-6)
