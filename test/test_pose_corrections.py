"""A corrected trajectory (loop closure) moves the poses: the map's kept keyframes and the
multi-view node's pose buffer (core, no ROS)."""

from __future__ import annotations

import mmap

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.mapping import keyframe_store
from depth_fusion_ros.mapping.config import MapConfig
from depth_fusion_ros.mapping.engine import make_engine
from depth_fusion_ros.mapping.keyframe_store import (
    KeyframeStore,
    PendingKeyframe,
    half_camera,
    mapped_bytes,
    rebuild,
)
from depth_fusion_ros.pose_buffer import PoseBuffer
from depth_fusion_ros.pose_corrections import (
    CorrectionLimits,
    Corrections,
    Posing,
    corrected_poses,
    corrected_segments,
    new_world_from,
)


def _pose(t, rotvec=(0.0, 0.0, 0.0)) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    T[:3, 3] = t
    return T


def _trajectory(stamps: np.ndarray) -> np.ndarray:
    """A smooth handheld-like path: 0.3 m/s along x, swaying in y, yawing slowly."""
    return np.stack([_pose((0.3 * s, 0.05 * np.sin(s), 0.0), (0.0, 0.1 * s, 0.0)) for s in stamps])


def _drift(stamps: np.ndarray) -> np.ndarray:
    """What a pose graph corrects: a drift that grows along the loop (2 cm and 0.6 deg a second)."""
    return np.stack([_pose((0.02 * s, -0.01 * s, 0.0), (0.0, 0.0, np.radians(0.6) * s)) for s in stamps])


def test_keyframes_between_the_paths_poses_get_the_interpolated_correction():
    """Our keyframes every 0.2 s, the SLAM's corrected keyframes every 0.5 s at other stamps."""
    ours = np.arange(0.0, 10.0, 0.2)
    truth = _trajectory(ours)
    drifted = _drift(ours) @ truth  # what was integrated
    slam = np.arange(0.05, 10.0, 0.5)
    fix = corrected_poses(ours, drifted, slam, _trajectory(slam))
    inside = (ours >= slam[0]) & (ours <= slam[-1])
    assert np.array_equal(fix.corrected, inside)
    err = np.linalg.norm(fix.poses[inside, :3, 3] - truth[inside, :3, 3], axis=1)
    before = np.linalg.norm(drifted[inside, :3, 3] - truth[inside, :3, 3], axis=1)
    assert before.max() > 0.15 and err.max() < 0.005, (before.max(), err.max())
    # outside the path's span: not moved (the newest are already in the corrected world)
    assert np.array_equal(fix.poses[~inside], drifted[~inside])


def _posed(stamps: np.ndarray, T_pose_cam: np.ndarray, offset: float, drift: bool = False) -> np.ndarray:
    """Camera poses as a multi-view node reads them: the pose source's trajectory at ``stamp +
    offset`` (with its drift when ``drift``), then ``T_pose_cam``."""
    told = _trajectory(stamps + offset)
    if drift:
        told = _drift(stamps + offset) @ told
    return told @ T_pose_cam


def test_a_path_that_restates_the_pose_source_keeps_the_posing_a_check_added():
    """A mount check turned the camera 1.75 deg and a time offset check read poses 30 ms late:
    the camera poses are not the pose source's. Its trajectory published unchanged moves nothing;
    corrected (a drift taken out), it moves each keyframe to the truth with the turn and the
    offset kept. Compared in the camera frame, as before, the same path moved every keyframe by
    the turn and lost it."""
    ours = np.arange(0.0, 6.0, 0.2)
    turn = _pose((0.0, 0.0, 0.0), (np.radians(1.75), 0.0, 0.0))
    mount = _pose((0.05, 0.0, 0.1), (0.0, 0.0, np.radians(90.0)))
    posing = Posing(mount @ turn, 0.03)
    truth = _posed(ours, posing.T_pose_cam, posing.offset)
    segments = np.zeros(len(ours), dtype=int)
    slam = np.arange(0.05, 6.0, 0.3)
    posings = [posing] * len(ours)
    same = corrected_segments(ours, truth, segments, 0, slam, _trajectory(slam), 1.0, posings)
    metres, degrees = same.moves(truth)
    assert same.corrected[5:-5].all() and metres.max() < 1e-3 and degrees.max() < 0.02, (
        metres.max(),
        degrees.max(),
    )
    drifted = _posed(ours, posing.T_pose_cam, posing.offset, drift=True)
    fix = corrected_segments(ours, drifted, segments, 0, slam, _trajectory(slam), 1.0, posings)
    inside = fix.corrected
    err_m, err_deg = Corrections(fix.poses[inside], inside[inside]).moves(truth[inside])
    assert inside[5:-5].all() and err_m.max() < 0.003 and err_deg.max() < 0.02, (err_m.max(), err_deg.max())
    # The camera poses against the path's poses with the configured mount alone (as before):
    # the unchanged path moves every keyframe by the turn.
    naive = corrected_poses(ours, truth, slam, _trajectory(slam) @ mount)
    assert naive.moves(truth)[1][5:-5].min() > 1.7


def test_a_keyframe_at_a_path_stamp_takes_the_paths_pose_and_an_unchanged_path_moves_nothing():
    ours = np.arange(0.0, 4.0, 0.25)
    poses = _trajectory(ours)
    fix = corrected_poses(ours, poses, ours[::3], poses[::3])
    metres, degrees = fix.moves(poses)
    assert fix.corrected[: 3 * (len(ours[::3]) - 1) + 1].all()
    assert metres.max() < 1e-9 and degrees.max() < 1e-6
    moved = poses[::3].copy()
    moved[:, 0, 3] += 0.1
    fix = corrected_poses(ours, poses, ours[::3][::-1], moved[::-1])  # any order
    assert np.allclose(fix.poses[::3][: len(moved)], moved)


def test_no_old_pose_is_interpolated_across_a_gap_longer_than_max_gap():
    ours = np.array([0.0, 0.2, 0.4, 5.0, 5.2])
    poses = _trajectory(ours)
    slam = np.array([2.0])  # falls in the 4.6 s gap: nothing known there
    fix = corrected_poses(ours, poses, slam, _trajectory(slam) @ _pose((1.0, 0, 0)), max_gap=2.0)
    assert not fix.corrected.any()


def test_pose_buffer_takes_the_correction_and_the_step_it_removes_is_no_jump():
    """Poses in the old world up to 2 s, in the corrected world after (a 30 cm step: a jump);
    the corrected trajectory moves the old ones, and the jump mark goes with the step."""
    from depth_fusion_ros.pose_jumps import PoseJumpLimits

    stamps = np.arange(0.0, 3.0, 0.1)
    truth = _trajectory(stamps)
    step = _pose((0.3, 0.0, 0.0), (0.0, 0.05, 0.0))
    buffer = PoseBuffer(100, 0.5, PoseJumpLimits(1.0, 90.0))
    jumps = [buffer.insert(s, T if s < 2.0 else step @ T) for s, T in zip(stamps, truth, strict=True)]
    assert sum(j is not None for j in jumps) == 1
    assert buffer.lookup(1.95).key == 'pose_jump'
    moved = buffer.correct(stamps[stamps < 2.0][::4], (step @ truth[stamps < 2.0])[::4], max_gap=1.0)
    assert moved is not None and moved[0] > 0.25
    assert buffer.lookup(1.95).pose is not None  # no step left to interpolate across
    np.testing.assert_allclose(buffer.lookup(1.0).pose, step @ truth[10], atol=1e-6)
    assert buffer.correct(np.array([10.0]), truth[:1], max_gap=1.0) is None  # covers nothing


def _room_keyframe(i: int, camera: PinholeCamera) -> tuple[np.ndarray, np.ndarray]:
    """A camera 2 m in front of a wall (z = 2 in the world), sliding along x."""
    depth = np.full((camera.height, camera.width), 2.0, np.float32)
    return depth, _pose((0.05 * i, 0.0, 0.0))


def _mapping(array: np.ndarray) -> mmap.mmap | None:
    """The anonymous mapping an array's memory belongs to (None: the heap)."""
    while array is not None and not isinstance(array, mmap.mmap):
        array = array.base.obj if isinstance(array.base, memoryview) else array.base
    return array


def test_store_keeps_half_resolution_thins_with_age_and_splits_segments():
    camera = PinholeCamera(64, 48, 60.0, 60.0, 31.5, 23.5)
    store = KeyframeStore(max_bytes=8 * KeyframeStore.keyframe_bytes(camera))
    for i in range(20):
        depth, T = _room_keyframe(i, camera)
        store.add(
            0.1 * i, depth, T, camera, np.full(depth.shape, 0.5, np.float32), np.zeros((48, 64, 3), np.uint8)
        )
    assert len(store.entries) <= 8 and store.thinned == 20 - len(store.entries)
    assert store.entries[-1].seq == 19 and store.entries[0].seq == 0  # the whole run, denser at the end
    e = store.entries[-1]
    assert e.depth.shape == (24, 32) and e.depth.dtype == np.float16
    assert e.camera == half_camera(camera) and e.camera.cx == pytest.approx(15.75)
    # What it holds is counted in whole pages: each keyframe's images share one mapping of their own.
    assert store.memory_bytes == len(store.entries) * mapped_bytes(24 * 32 * 6) == len(store.entries) * 8192
    assert store.memory_bytes <= store.max_bytes
    assert all(_mapping(a) is _mapping(e.depth) is not None for a in (e.confidence, e.rgb))
    assert e.confidence[0, 0] == round(0.5 * 255) and not e.rgb.any()
    store.add(0.5, *_room_keyframe(0, camera), camera)  # stamps went back: a restarted stream
    assert store.entries[-1].segment == 1
    store.new_segment()
    store.add(0.6, *_room_keyframe(1, camera), camera)
    assert store.entries[-1].segment == 2
    # Past MAX_MAPPED_ENTRIES (the process's mappings are a limited resource) they go on the heap.
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(keyframe_store, 'MAX_MAPPED_ENTRIES', len(store.entries))
        heap = store.add(9.0, *_room_keyframe(3, camera), camera, np.full(depth.shape, 0.5, np.float32))
    assert _mapping(heap.depth) is None and heap.confidence[0, 0] == round(0.5 * 255)


def test_rebuild_at_corrected_poses_puts_the_wall_back_where_it_is():
    """Keyframes of a wall at z = 2 m integrated with a 10 cm error in z from keyframe 5 on:
    the map holds two walls. The corrected trajectory moves them back; the rebuilt map has one."""
    camera = PinholeCamera(80, 60, 70.0, 70.0, 39.5, 29.5)
    config = MapConfig(voxel_size=0.02, engine='torch', consistency_span=0)
    store = KeyframeStore(max_bytes=2**20)
    stamps, truth = [], []
    for i in range(10):
        depth, T = _room_keyframe(i, camera)
        wrong = T.copy()
        if i >= 5:
            wrong[2, 3] += 0.10
        store.add(0.2 * i, depth, wrong, camera, None, None)
        stamps.append(0.2 * i)
        truth.append(T)

    def wall_spread(engine) -> tuple[float, float]:
        z = engine.mesh().vertices[:, 2]
        return float(np.percentile(z, 5)), float(np.percentile(z, 95))

    before, _ = make_engine(config)
    rebuild(before, store.entries)
    lo, hi = wall_spread(before)
    assert hi - lo > 0.08  # two walls, 10 cm apart
    summary = store.correct(np.array(stamps), np.stack(truth), CorrectionLimits(), Posing(np.eye(4)))
    assert summary.corrected == 10 and summary.moved == 5 and summary.largest_m == pytest.approx(0.10)
    after, _ = make_engine(config)
    assert rebuild(after, store.entries) == 10
    lo, hi = wall_spread(after)
    assert hi - lo < 0.03 and abs(0.5 * (lo + hi) - 2.0) < 0.02


def test_the_newest_stored_keyframes_are_corrected_up_to_the_pending_ones():
    """The map stores a keyframe only once the consistency test integrated it, a few keyframes
    after it came; a SLAM's path reaches the newest pose. Compared with the stored keyframes
    alone, the path's poses after the newest stored one had no old pose to be compared with,
    so the newest stored keyframes were left in the old world (the last one 13 cm off here).
    With the pending keyframes given, every stored keyframe is corrected, and so are they."""
    camera = PinholeCamera(32, 24, 30.0, 30.0, 15.5, 11.5)
    ours = np.arange(0.0, 1.6, 0.2)  # eight keyframes, the last two pending
    truth = _trajectory(ours)
    drifted = _drift(ours * 5.0) @ truth
    store = KeyframeStore(max_bytes=2**20)
    for t, T in zip(ours[:6], drifted[:6], strict=True):
        store.add(t, np.full((24, 32), 2.0, np.float32), T, camera)
    slam = ours[:-1] + 0.1  # the SLAM's own keyframes, between ours, up to the newest
    pending = [PendingKeyframe(t, T, store.segment) for t, T in zip(ours[6:], drifted[6:], strict=True)]
    alone = KeyframeStore(max_bytes=2**20)
    for e in store.entries:
        alone.add(e.stamp, np.full((24, 32), 2.0, np.float32), e.T_wc, camera)
    alone.correct(slam, _trajectory(slam), CorrectionLimits(), Posing(np.eye(4)))
    summary = store.correct(slam, _trajectory(slam), CorrectionLimits(), Posing(np.eye(4)), pending)
    stored = np.stack([e.T_wc for e in store.entries])
    err = np.linalg.norm(stored[:, :3, 3] - truth[:6, :3, 3], axis=1)
    assert summary.corrected == 5 and err[1:].max() < 0.01, err  # the first is before the path
    before = np.linalg.norm(alone.entries[-1].T_wc[:3, 3] - truth[5, :3, 3])
    assert before > 0.1, before
    assert summary.others is not None
    pending_err = np.linalg.norm(summary.others[:, :3, 3] - truth[6:, :3, 3], axis=1)
    assert pending_err[0] < 0.01, pending_err  # the newest is after the path's last pose: as it was


def test_the_corrected_world_starts_at_the_paths_stamp_unless_it_says_nothing_new():
    # Stamp 9 after the newest posed image 7, path to 6: an image 8 still to come is old world.
    assert new_world_from(9.0, 6.0, 7.0) == 9.0
    # Unset, not after what is posed, or a path reaching past it: the next posed image.
    assert new_world_from(0.0, 6.0, 7.0) is None
    assert new_world_from(7.0, 6.0, 7.0) is None
    assert new_world_from(9.0, 8.0, 7.0) is None
    assert new_world_from(9.0, 6.0, None) is None
