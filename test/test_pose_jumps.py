"""Pose jumps (a SLAM relocalising): found by speed, nothing interpolated across them."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from depth_fusion_ros.geometry import make_pose
from depth_fusion_ros.pose_buffer import PoseBuffer
from depth_fusion_ros.pose_jumps import PoseJumpLimits, find_jump

IDENTITY_Q = [0, 0, 0, 1]


def _pose(x: float, yaw_deg: float = 0.0) -> np.ndarray:
    return make_pose([x, 0, 0], Rotation.from_euler('z', yaw_deg, degrees=True).as_quat())


def test_a_step_faster_than_the_limits_is_a_jump_and_noise_is_not():
    limits = PoseJumpLimits()  # 5 m/s, 360 deg/s, 2 cm and 2 deg of slack
    dt = 1 / 30
    assert find_jump(limits, 0.0, _pose(0.0), dt, _pose(0.15)) is None  # 4.5 m/s: a fast hand
    jump = find_jump(limits, 0.0, _pose(0.0), dt, _pose(0.3))
    assert jump is not None and jump.distance_m == pytest.approx(0.3) and jump.after == dt
    assert '0.30 m' in jump.describe(limits) and '5 m/s' in jump.describe(limits)
    assert find_jump(limits, 0.0, _pose(0.0), dt, _pose(0.0, 11.0)) is None  # 330 deg/s
    assert find_jump(limits, 0.0, _pose(0.0), dt, _pose(0.0, 20.0)) is not None
    # 200 Hz poses 5 mm apart: within the noise slack, not a 1 m/s "speed" over 5 ms
    assert find_jump(limits, 0.0, _pose(0.0), 0.005, _pose(0.015)) is None
    # either order; the limits off, or one of them off
    assert find_jump(limits, dt, _pose(0.3), 0.0, _pose(0.0)).before == 0.0
    assert find_jump(PoseJumpLimits(0.0, 0.0), 0.0, _pose(0.0), dt, _pose(5.0)) is None
    assert find_jump(PoseJumpLimits(0.0, 360.0), 0.0, _pose(0.0), dt, _pose(5.0)) is None
    with pytest.raises(ValueError, match='max_speed'):
        PoseJumpLimits(max_speed=-1.0)


def test_the_buffer_interpolates_on_each_side_of_a_jump_but_not_across_it():
    buf = PoseBuffer(capacity=100, max_gap=0.5, jump_limits=PoseJumpLimits())
    dt = 1 / 30
    jumps = [buf.insert(i * dt, _pose(0.01 * i)) for i in range(5)]
    assert jumps == [None] * 5
    # the SLAM relocalised between poses 4 and 5: everything after is 0.5 m away
    jump = buf.insert(5 * dt, _pose(0.05 + 0.5))
    assert jump is not None and jump.before == pytest.approx(4 * dt)
    assert buf.insert(6 * dt, _pose(0.06 + 0.5)) is None
    assert np.allclose(buf.lookup(3.5 * dt).pose[:3, 3], [0.035, 0, 0])
    assert np.allclose(buf.lookup(5.5 * dt).pose[:3, 3], [0.555, 0, 0])
    inside = buf.lookup(4.5 * dt)
    assert inside.pose is None and inside.key == 'pose_jump' and 'jump' in inside.reason
    assert np.allclose(buf.lookup(5 * dt).pose[:3, 3], [0.55, 0, 0])  # the pose after it, exactly
    # a gap keeps its own key
    buf.insert(2.0, _pose(0.56))
    assert buf.lookup(1.0).key == 'pose_gap'


def test_a_pose_placed_between_the_two_sides_moves_the_jump():
    """Out of order: a late pose inside the jumped interval takes the step on one side."""
    buf = PoseBuffer(capacity=100, max_gap=0.5, jump_limits=PoseJumpLimits())
    buf.insert(0.0, _pose(0.0))
    assert buf.insert(0.1, _pose(1.0)) is not None  # 10 m/s
    late = buf.insert(0.05, _pose(0.01))  # near the first: the step is now after it
    assert late is not None and late.before == pytest.approx(0.05) and late.after == pytest.approx(0.1)
    assert buf.lookup(0.02).pose is not None  # between 0.0 and 0.05: no jump there any more
    assert buf.lookup(0.07).key == 'pose_jump'


def test_jumps_leave_the_buffer_with_their_poses():
    buf = PoseBuffer(capacity=3, max_gap=0.5, jump_limits=PoseJumpLimits())
    buf.insert(0.0, _pose(0.0))
    buf.insert(0.1, _pose(2.0))
    for t in (0.2, 0.3, 0.4):
        buf.insert(t, _pose(2.0 + t))
    assert buf.span == (0.2, 0.4) and buf.lookup(0.25).pose is not None
    buf.clear()
    assert buf.lookup(0.25).pose is None and buf.lookup(0.25).key == 'pose_gap'


def test_reread_gives_the_poses_at_a_corrected_offset_but_not_across_a_jump_or_past_the_buffer():
    """A time offset corrected from 0 to +20 ms: the frames posed before are read again 20 ms
    later; one whose two times straddle a jump (its new pose is in another world) or the
    buffer's end gets none."""
    buf = PoseBuffer(capacity=100, max_gap=0.5, jump_limits=PoseJumpLimits())
    dt = 1 / 30
    for i in range(10):
        buf.insert(i * dt, _pose(0.01 * i + (0.5 if i >= 6 else 0.0)))  # relocalised between 5 and 6
    stamps = [1 * dt, 3 * dt, 5.5 * dt, 9 * dt - 0.01]
    poses = buf.reread(stamps, 0.0, 0.02)
    assert np.allclose(poses[0][:3, 3], [0.01 + 0.006, 0, 0])  # 0.3 m/s for 20 ms later
    assert np.allclose(poses[1][:3, 3], [0.03 + 0.006, 0, 0])
    assert poses[2] is None  # 5.5 dt was posed inside the jump: none then, none now
    assert poses[3] is None  # 20 ms later is past the newest pose
    assert buf.reread([5 * dt - 0.01], 0.0, 0.02) == [None]  # before the jump, then after it
