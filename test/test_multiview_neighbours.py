"""Neighbour selection: parallax, overlap, rotation, online/offline windows, bad poses."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.geometry import PoseError, make_pose
from depth_fusion_ros.multiview.neighbours import (
    NeighbourConfig,
    neighbour_table,
    overlap_fraction,
    select_neighbours,
)

CAMERA = PinholeCamera(320, 240, 260.0, 260.0, 159.5, 119.5)


def sideways_track(count: int, step: float = 0.02) -> np.ndarray:
    """Camera moving along x by ``step`` m per frame, looking along +z."""
    poses = np.tile(np.eye(4), (count, 1, 1))
    poses[:, 0, 3] = np.arange(count) * step
    return poses


def yaw(degrees: float, t: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    half = np.radians(degrees) / 2
    return make_pose(t, (0.0, np.sin(half), 0.0, np.cos(half)))


def test_online_uses_past_frames_only_and_prefers_target_parallax():
    poses = sideways_track(40)
    chosen = select_neighbours(poses, 20, 4, 'online', CAMERA)
    assert len(chosen) == 4
    assert all(i < 20 for i in chosen)
    # Target baseline 0.08 * 1.5 m = 12 cm = 6 frames back; the best one is chosen first.
    assert chosen[0] == 14
    # Spread: no two chosen frames closer than half the target baseline (3 frames).
    gaps = np.diff(sorted(chosen))
    assert np.all(gaps >= 3)


def test_offline_uses_both_sides():
    poses = sideways_track(40)
    chosen = select_neighbours(poses, 20, 4, 'offline', CAMERA)
    assert len(chosen) == 4
    assert any(i < 20 for i in chosen) and any(i > 20 for i in chosen)
    assert 20 not in chosen


def test_first_frame_online_has_no_neighbour():
    assert select_neighbours(sideways_track(5), 0, 4, 'online', CAMERA) == []


def test_non_overlapping_and_rotated_frames_are_rejected():
    poses = np.stack(
        [
            np.eye(4),  # keyframe
            make_pose((0.1, 0.0, 0.0), (0, 0, 0, 1)),  # good: 10 cm sideways
            yaw(180.0, (0.05, 0.0, 0.0)),  # looks backwards: no overlap
            make_pose((4.0, 0.0, 0.0), (0, 0, 0, 1)),  # 4 m sideways: no overlap
            yaw(45.0, (0.1, 0.0, 0.0)),  # too much rotation
        ]
    )
    assert overlap_fraction(np.linalg.inv(poses[2]) @ poses[0], CAMERA, 1.5) == 0.0
    assert overlap_fraction(np.linalg.inv(poses[3]) @ poses[0], CAMERA, 1.5) == 0.0
    config = NeighbourConfig(max_parallax=10.0)  # let the 4 m frame fail on overlap alone
    assert select_neighbours(poses, 0, 4, 'offline', CAMERA, config) == [1]


def test_zero_baseline_frames_only_with_a_warning(caplog):
    poses = np.stack([np.eye(4), yaw(2.0), yaw(-3.0), yaw(4.0)])
    with caplog.at_level(logging.WARNING, logger='depth_fusion_ros.multiview.neighbours'):
        chosen = select_neighbours(poses, 0, 2, 'offline', CAMERA)
    assert len(chosen) == 2
    assert 'zero baseline' in caplog.text
    # A node routes the warning to its own throttled counter instead of the logger.
    caplog.clear()
    said: list[str] = []
    with caplog.at_level(logging.WARNING, logger='depth_fusion_ros.multiview.neighbours'):
        assert select_neighbours(poses, 0, 2, 'offline', CAMERA, warn=said.append) == chosen
    assert len(said) == 1 and 'zero baseline' in said[0] and not caplog.text


def test_zero_baseline_frames_do_not_displace_real_parallax(caplog):
    poses = np.stack([np.eye(4), yaw(2.0), make_pose((0.1, 0.0, 0.0), (0, 0, 0, 1))])
    with caplog.at_level(logging.WARNING, logger='depth_fusion_ros.multiview.neighbours'):
        chosen = select_neighbours(poses, 0, 2, 'offline', CAMERA)
    assert chosen == [2, 1]  # the translated frame first; the rotation only fills up
    assert 'zero baseline' not in caplog.text


def test_bad_poses_and_arguments_raise_clear_errors():
    poses = sideways_track(6)
    poses[3, 0, 0] = np.nan
    with pytest.raises(PoseError, match='pose of frame 3: contains NaN'):
        select_neighbours(poses, 5, 4, 'online', CAMERA)
    skewed = sideways_track(6)
    skewed[2, :3, :3] *= 1.5
    with pytest.raises(PoseError, match='pose of frame 2: rotation is not orthonormal'):
        select_neighbours(skewed, 0, 4, 'offline', CAMERA)
    with pytest.raises(ValueError, match='neighbour mode'):
        select_neighbours(sideways_track(6), 2, 4, 'sideways', CAMERA)
    with pytest.raises(ValueError, match='keyframe index 9'):
        select_neighbours(sideways_track(6), 9, 4, 'online', CAMERA)
    with pytest.raises(ValueError, match=r'poses must be \(N, 4, 4\)'):
        select_neighbours(np.eye(4), 0, 4, 'online', CAMERA)


def test_table_covers_every_keyframe():
    table = neighbour_table(sideways_track(12), 2, 'online', CAMERA)
    assert sorted(table) == list(range(12))
    assert table[0] == []
    assert all(len(v) == 2 for k, v in table.items() if k >= 2)


def test_batched_candidates_match_one_by_one():
    """``describe_candidates`` describes the whole window in one batch; each candidate equals
    its own relative pose's parallax, rotation and lattice overlap."""
    from depth_fusion_ros.geometry import relative_pose, rotation_angle
    from depth_fusion_ros.multiview.neighbours import describe_candidates

    rng = np.random.default_rng(5)
    angles, shifts = rng.uniform(-40, 40, 31), rng.normal(0, 0.3, (31, 3))
    poses = np.stack([yaw(a, tuple(t)) for a, t in zip(angles, shifts, strict=True)])
    config = NeighbourConfig()
    described = describe_candidates(poses, 30, list(range(30)), CAMERA, config)
    for c in described:
        T_ok = relative_pose(poses[30], poses[c.index])
        assert c.overlap == overlap_fraction(T_ok, CAMERA, config.scene_depth)
        assert c.rotation_deg == pytest.approx(np.degrees(rotation_angle(T_ok[:3, :3])), abs=1e-9)
        baseline = np.linalg.norm(poses[c.index][:3, 3] - poses[30][:3, 3])
        assert c.parallax == pytest.approx(baseline / config.scene_depth, rel=1e-12)
    assert {round(c.overlap, 3) for c in described} != {1.0}  # the window mixes seen and unseen frames
