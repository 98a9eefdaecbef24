"""Poses read along a cubic through their samples (``pose_curve.py``): through every sample,
far closer than straight lines to a curved motion between them, invalid outside, and the
linear reading where there are too few samples for a curve."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from depth_fusion_ros.geometry import interpolate_poses
from depth_fusion_ros.pose_curve import interpolate_poses_cubic


def _hand(t: np.ndarray) -> np.ndarray:
    """A walk at 0.3 m/s with a 2-3 Hz shake of 1 cm and 0.6 deg: camera-to-world poses at ``t``."""
    P = np.repeat(np.eye(4)[None], len(t), axis=0)
    P[:, :3, 3] = np.stack([0.01 * np.sin(4 * np.pi * t), 0.01 * np.cos(6 * np.pi * t), 0.3 * t], axis=1)
    turn = np.stack([0.01 * np.sin(5 * np.pi * t), 0.2 * t, 0.01 * np.cos(3 * np.pi * t)], axis=1)
    P[:, :3, :3] = Rotation.from_rotvec(turn).as_matrix()
    return P


def _errors(A: np.ndarray, B: np.ndarray) -> tuple[float, float]:
    """Median translation (m) and rotation (rad) differences."""
    moved = np.linalg.norm(A[:, :3, 3] - B[:, :3, 3], axis=1)
    turned = Rotation.from_matrix(np.transpose(A[:, :3, :3], (0, 2, 1)) @ B[:, :3, :3]).magnitude()
    return float(np.median(moved)), float(np.median(turned))


def test_the_cubic_passes_through_the_samples_and_follows_a_shaking_hand():
    rng = np.random.default_rng(0)
    stamps = np.cumsum(rng.uniform(0.028, 0.038, 60))  # a 30 Hz stream with jitter
    poses = _hand(stamps)
    through, ok = interpolate_poses_cubic(stamps, poses, stamps)
    assert ok.all() and np.allclose(through, poses, atol=1e-9)
    between = stamps[:-1] + 0.4 * np.diff(stamps)
    truth = _hand(between)
    cubic = _errors(interpolate_poses_cubic(stamps, poses, between)[0], truth)
    linear = _errors(interpolate_poses(stamps, poses, between)[0], truth)
    assert cubic[0] < linear[0] / 5 and cubic[1] < linear[1] / 5, (cubic, linear)


def test_outside_the_samples_is_invalid_and_two_samples_are_a_line():
    stamps = np.array([0.0, 0.1, 0.2, 0.3])
    poses = _hand(stamps)
    out, ok = interpolate_poses_cubic(stamps, poses, np.array([-0.01, 0.15, 0.31]))
    assert ok.tolist() == [False, True, False] and np.isnan(out[0]).all() and np.isfinite(out[1]).all()
    two, _ = interpolate_poses_cubic(stamps[:2], poses[:2], np.array([0.05]))
    line, _ = interpolate_poses(stamps[:2], poses[:2], np.array([0.05]))
    assert np.allclose(two, line)
