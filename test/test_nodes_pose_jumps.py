"""multi_view_node over real DDS when the pose source relocalises mid-stream.

A SLAM that relocalises or closes a loop moves every later pose by its correction: the
poses after it are right among themselves, wrong against the ones before. The node must not
let a neighbour or a filter estimate cross that step.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from nav_msgs.msg import Path as PathMsg
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import Image
from test_nodes_multi_view import _Camera, _mv_node, _stamps
from test_nodes_multi_view_filter import EVERY_FRAME

from depth_fusion_ros.data import messages as m
from depth_fusion_ros.geometry import make_pose
from depth_fusion_ros.nodes.testing import RosHarness

pytestmark = pytest.mark.usefixtures('one_torch_thread')

K = m.RCLPY
#: The frame whose pose is the first after the relocalisation.
JUMP_AT = 9
#: The correction: 0.4 m and 6 degrees, as a loop closure after a short drift could give.
CORRECTION = make_pose([0.3, -0.2, 0.2], Rotation.from_euler('y', 6, degrees=True).as_quat())


def _relocalised(poses: list[np.ndarray], correction: np.ndarray = CORRECTION) -> list[np.ndarray]:
    return [T if i < JUMP_AT else correction @ T for i, T in enumerate(poses)]


def _corrected_path(poses: list[np.ndarray], stamps: list[int], correction: np.ndarray) -> PathMsg:
    """What the SLAM publishes when it closes the loop: its keyframes (every third frame) before
    the correction, in the corrected world."""
    msg = PathMsg()
    msg.header = m.header_msg(stamps[JUMP_AT], 'world', kind=K)
    msg.poses = [
        m.pose_stamped_msg(correction @ poses[i], m.header_msg(stamps[i], 'world', kind=K), kind=K)
        for i in range(0, JUMP_AT, 3)
    ]
    return msg


def _play(
    seq,
    detect: bool,
    correction: np.ndarray = CORRECTION,
    with_path: bool = False,
    path_before_image: int = JUMP_AT,
    **extra,
) -> tuple[list, object, dict]:
    """``path_before_image``: the image the path is taken before (``JUMP_AT - 1``: an image of
    the old world whose callback comes after the path's, as two topics allow; its pose and the
    first corrected one are published before the path)."""
    stamps = [m.sec_to_ns(s) for s in seq.stamps]
    truth = [f.pose for f in seq.frames]
    poses = _relocalised(truth, correction)
    limits = {} if detect else {'max_pose_speed': 0.0, 'max_pose_angular_speed': 0.0}
    with RosHarness() as ros:
        node = _mv_node(ros, **EVERY_FRAME, **limits, **extra)
        depth_msgs = ros.collect(Image, '/depth_fusion/multi_view/depth')
        cam = _Camera(ros)
        path = ros.publisher(PathMsg, '/camera/corrected_path')
        assert ros.wait_for_subscribers([path])
        for i, frame in enumerate(seq.frames):
            if not (with_path and i == JUMP_AT > path_before_image):  # (published already)
                cam.publish_pose(poses[i], stamps[i])
            if with_path and i == path_before_image:
                if i < JUMP_AT:
                    cam.publish_pose(poses[JUMP_AT], stamps[JUMP_AT])
                # The loop closed: the first corrected pose, then the path.
                time.sleep(0.05)
                path.publish(_corrected_path(truth, stamps, correction))
                # The path is taken before the next image (two topics keep no order between them:
                # under load image 9 was once posed first, and the filter ran across the
                # correction, 2 of 4 runs beside three busy loops). No assert: the test asserts it.
                ros.wait_for(lambda: node.stats.snapshot().noted.get('pose_correction') == 1, 10.0)
            cam.publish_image(frame.rgb, stamps[i], seq.camera)
            time.sleep(0.02)
        feed = node.filter_feed
        assert feed is None or ros.wait_for(lambda: feed.fed == len(seq.frames), 60.0)
        assert ros.wait_for(lambda: (feed is None or feed.idle()) and node.worker.idle(), 60.0)
        time.sleep(0.3)
        snap = node.stats.snapshot()
    index = {s: i for i, s in enumerate(stamps)}
    return [(index[s], msg) for s, msg in zip(_stamps(depth_msgs), depth_msgs, strict=True)], snap, stamps


def _abs_rel(seq, k: int, msg) -> tuple[float, float]:
    depth, gt = m.image_to_numpy(msg), seq.frames[k].depth
    valid = np.isfinite(depth) & np.isfinite(gt)
    return float(np.median(np.abs(depth[valid] - gt[valid]) / gt[valid])), float(valid.mean())


def test_a_relocalisation_starts_the_frame_history_and_filter_over(synthetic_sequence):
    seq = synthetic_sequence
    published, snap, _ = _play(seq, detect=True)
    assert snap.noted.get('pose_jump') == 1, snap.summary()
    assert snap.dropped == {}, snap.summary()  # images share the poses' stamps: nothing inside the jump
    after = [(k, msg) for k, msg in published if k >= JUMP_AT]
    assert after, f'no keyframe after the jump: {[k for k, _ in published]}'
    for k, msg in published:
        error, density = _abs_rel(seq, k, msg)
        assert error < 0.02 and density > 0.03, f'keyframe {k}: AbsRel {error:.3f}, density {density:.3f}'


def test_without_the_check_the_filter_carries_estimates_across_the_jump(synthetic_sequence):
    """The failure the check prevents, reproduced: the first keyframe after the jump gets the
    estimates propagated through the wrong relative pose (5 % off in the median on this
    sequence, against 1 % on either side of it with the check)."""
    published, snap, _ = _play(synthetic_sequence, detect=False)
    assert 'pose_jump' not in snap.noted
    first_after = next((k, msg) for k, msg in published if k >= JUMP_AT)
    error, _ = _abs_rel(synthetic_sequence, *first_after)
    assert error > 0.03, f'keyframe {first_after[0]}: AbsRel {error:.3f}'


#: A loop closure's correction under the jump limits (6 cm and 2 degrees between two frames at
#: 30 Hz is 1.8 m/s and 60 deg/s): the poses alone cannot tell it from motion.
SMALL = make_pose([0.06, -0.03, 0.03], Rotation.from_euler('y', 2, degrees=True).as_quat())


def test_a_corrected_trajectory_starts_the_filter_over_where_the_jump_test_cannot_see(synthetic_sequence):
    """The SLAM says it corrected (its trajectory on camera/corrected_path): the buffered poses
    move with it and the filter starts over, so the first keyframe after it is as accurate as
    the others. Without the path the same correction goes unseen and that keyframe is worse."""
    seq = synthetic_sequence
    published, snap, _ = _play(seq, detect=True, correction=SMALL, with_path=True)
    assert snap.noted.get('pose_correction') == 1 and 'pose_jump' not in snap.noted, snap.summary()
    assert snap.dropped == {}, snap.summary()
    errors = {k: _abs_rel(seq, k, msg)[0] for k, msg in published}
    assert any(k >= JUMP_AT for k in errors), errors
    assert max(errors.values()) < 0.0125, errors
    unseen, snap, _ = _play(seq, detect=True, correction=SMALL)
    assert 'pose_jump' not in snap.noted and 'pose_correction' not in snap.noted, snap.summary()
    first_after = next((k, msg) for k, msg in unseen if k >= JUMP_AT)
    assert _abs_rel(seq, *first_after)[0] > 0.014, first_after[0]


def test_an_old_world_image_taken_after_the_path_stays_in_the_old_world(synthetic_sequence):
    """The image before the correction comes after the path (its callback was queued behind
    the path's): it was posed at the old pose, so it joins the frames before it, and the new
    world starts at the path's stamp. Taken as the first frame of the new world, it was a
    neighbour of the next keyframe at its old pose (1.96 % off in the median; 1 of 3 runs
    under load before this was fixed)."""
    seq = synthetic_sequence
    published, snap, _ = _play(
        seq, detect=True, correction=SMALL, with_path=True, path_before_image=JUMP_AT - 1
    )
    assert snap.noted.get('pose_correction') == 1 and 'pose_jump' not in snap.noted, snap.summary()
    assert snap.dropped == {}, snap.summary()
    errors = {k: _abs_rel(seq, k, msg)[0] for k, msg in published}
    assert any(k >= JUMP_AT for k in errors), errors
    assert max(errors.values()) < 0.0125, errors
