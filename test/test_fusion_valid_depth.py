"""The fused depth is positive-finite or NaN on every path, fallbacks included (core and over DDS)."""

from __future__ import annotations

import numpy as np
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.data import messages as m
from depth_fusion_ros.fusion.pipeline import FusionConfig, fuse_keyframe
from depth_fusion_ros.fusion.scenes import make_scene
from depth_fusion_ros.fusion.valid_depth import sanitize_depth
from depth_fusion_ros.nodes.fusion_node import FusionNode
from depth_fusion_ros.nodes.testing import RosHarness


def _poisoned_single(h: int = 30, w: int = 40) -> np.ndarray:
    """A single-view map with the codes a network or driver may emit: -1, 0, +inf, -inf, NaN."""
    s = np.full((h, w), 2.0, np.float32)
    s[0, :5] = -1.0
    s[1, :5] = np.inf
    s[2, :5] = -np.inf
    s[3, :5] = 0.0
    s[4, :5] = np.nan
    return s


def _assert_valid(depth: np.ndarray) -> None:
    finite = depth[np.isfinite(depth)]
    assert not np.isinf(depth).any(), 'inf in the fused depth'
    assert np.all(finite > 0), 'non-positive depth in the fused depth'


def test_sanitize_depth_counts_and_removes_invalid_values() -> None:
    out, count = sanitize_depth(_poisoned_single())
    assert count == 20  # -1, +inf, -inf, 0 (NaN already NaN is not counted)
    assert np.isnan(out[:5, :5]).all() and np.all(out[5:] == 2.0)


def test_every_fallback_output_is_finite_or_nan() -> None:
    s = _poisoned_single()
    sc = make_scene(40, 30, n_points=200)
    nan = np.full((30, 40), np.nan, np.float32)
    rng = np.random.default_rng(0)
    junk = np.where(np.isfinite(sc.multi), rng.uniform(1, 9, (30, 40)), np.nan).astype(np.float32)
    strict = FusionConfig(ransac_threshold=0.005, ransac_min_inliers=50)
    cases = {
        'no_consensus': fuse_keyframe(s, junk, None, strict),
        'too_few_points': fuse_keyframe(s, nan, None),
        'empty_omega': fuse_keyframe(s, sc.multi, None, omega_mask=np.zeros((30, 40), bool)),
    }
    for reason, res in cases.items():
        assert res.fallback == reason
        _assert_valid(res.depth)
        assert np.isnan(res.depth[:5, :5]).all() and np.all(res.depth[5:] == 2.0)
    # the fused (non-fallback) path too, with the same poisoned pixels
    ok = fuse_keyframe(s, np.where(np.isfinite(sc.multi), 2.0, np.nan).astype(np.float32), None)
    _assert_valid(ok.depth)


def test_fusion_node_never_publishes_inf_from_a_poisoned_single_view() -> None:
    """A keyframe whose single-view depth holds -1 and +inf and no multi-view points (the
    no-consensus fallback) is published over DDS with NaN there, never inf or negative."""
    cam = PinholeCamera(40, 30, 30.0, 30.0, 19.5, 14.5)
    single = _poisoned_single()
    mv = np.full((30, 40), np.nan, np.float32)
    with RosHarness() as ros:
        node = ros.add(
            FusionNode(
                context=ros.context,
                parameter_overrides=[Parameter('fusion.compile_kernel', value=False)],
            )
        )
        out = ros.collect(Image, '/depth_fusion/fused/depth')
        pubs = {
            'info': ros.publisher(CameraInfo, '/depth_fusion/keyframe/camera_info'),
            'mv': ros.publisher(Image, '/depth_fusion/multi_view/depth'),
            'score': ros.publisher(Image, '/depth_fusion/multi_view/score'),
            'single': ros.publisher(Image, '/depth_fusion/single_view/depth'),
        }
        assert ros.wait_for_subscribers(list(pubs.values()))
        header = m.header_msg(1_000_000_000, 'camera', kind=m.RCLPY)
        pubs['info'].publish(m.camera_info_msg(cam, header, kind=m.RCLPY))
        pubs['mv'].publish(m.depth_image_msg(mv, header, kind=m.RCLPY))
        pubs['score'].publish(m.image_msg(mv, '32FC1', header, kind=m.RCLPY))
        pubs['single'].publish(m.depth_image_msg(single, header, kind=m.RCLPY))
        assert ros.wait_for(lambda: len(out) == 1)
        depth = m.image_to_numpy(out[0])
        _assert_valid(depth)
        assert np.isnan(depth[:5, :5]).all() and np.all(depth[5:] == 2.0)
        assert any(k.startswith('fallback_') for k in node.stats.snapshot().noted)
