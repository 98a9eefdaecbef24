"""The points' global scale weighed against the single view's by the std the points share
(``fusion/shared_scale.py``): the weight, the points it moves, and a keyframe whose points are
all biased together (an unverified focal length under rotation), fused with and without it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from depth_fusion_ros.fusion.guard import GuardConfig, MultiViewEvidence
from depth_fusion_ros.fusion.pipeline import FusionConfig, fuse_keyframe
from depth_fusion_ros.fusion.shared_scale import points_factor, scale_weight, weighed_points

W, H = 160, 120


def test_the_weight_is_the_single_views_share_of_the_scales_variance():
    # nothing shared, or nothing known: the points' scale in full
    assert scale_weight(0.1, 0.0, 0.8) == 1.0
    assert scale_weight(float('nan'), 0.16, 0.8) == 1.0
    assert scale_weight(0.1, float('nan'), 0.8) == 1.0
    assert scale_weight(0.1, 0.16, float('nan')) == 1.0
    # the handheld stream of seed 311 with camera_info 5 % short: e 0.10, b 0.16, the points 16 %
    # nearer than the network; the disagreement is within what b explains, so e sets n
    c = math.log(0.84)
    assert c * c - 0.16**2 < 0.1**2
    assert scale_weight(0.1, 0.16, 0.84) == pytest.approx(0.01 / (0.01 + 0.16**2))
    # a network three times too far (the shipped one on TUM fr1_xyz): the disagreement is not
    # the points' bias, and their scale is taken nearly in full
    assert scale_weight(0.1, 0.05, 1 / 3) > 0.99
    # a shape the points cannot fault and a disagreement their bias explains: the single view's scale
    assert scale_weight(0.0, 0.2, 1.05) == 0.0
    # more shared std, less of the points' scale
    weights = [scale_weight(0.1, b, 0.9) for b in (0.02, 0.05, 0.1, 0.2)]
    assert weights == sorted(weights, reverse=True) and weights[0] > 0.95


def test_the_points_move_by_what_the_weight_leaves_of_their_scale():
    m = np.array([[1.0, np.nan], [2.0, 4.0]], dtype=np.float32)
    assert points_factor(0.8, 1.0) == 1.0 and points_factor(float('nan'), 0.5) == 1.0
    assert weighed_points(m, points_factor(0.8, 1.0)) is m
    np.testing.assert_allclose(weighed_points(m, points_factor(0.8, 0.0)), m / 0.8, rtol=1e-6)
    np.testing.assert_allclose(weighed_points(m, points_factor(0.8, 0.5)), m / math.sqrt(0.8), rtol=1e-6)
    assert weighed_points(m, points_factor(0.8, 0.5)).dtype == np.float32


def _keyframe(shared: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, MultiViewEvidence]:
    """A room-like depth; a single view 2 % too far with a smooth 6 % shape error; points on 5 %
    of the pixels, all 14 % too near (a shared bias) with 1 % noise of their own; their std
    says so: 1 % of matching noise and ``shared`` in common."""
    rng = np.random.default_rng(5)
    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    gt = (2.0 + 1.2 * u / W + 0.5 * np.sin(v / 17.0)).astype(np.float32)
    box = (u > 50) & (u < 100) & (v > 30) & (v < 80)
    gt[box] = 1.4
    single = (gt * 1.02 * np.exp(0.06 * np.sin(u / 23.0 + v / 31.0))).astype(np.float32)
    mv = np.full((H, W), np.nan, np.float32)
    pick = rng.choice(gt.size, size=int(0.05 * gt.size), replace=False)
    mv.ravel()[pick] = gt.ravel()[pick] * np.exp(-0.14 + 0.01 * rng.standard_normal(pick.size))
    std = np.where(np.isfinite(mv), mv * math.hypot(0.01, shared), np.nan).astype(np.float32)
    bias = np.where(np.isfinite(mv), mv * shared, np.nan).astype(np.float32)
    return gt, single, mv, MultiViewEvidence.from_depth_std(mv, std, bias_std=bias)


def _fuse(single, mv, evidence, on: bool):
    config = FusionConfig(mode='fast', compile_kernel=False, halo_min_step=0.0)
    guard = GuardConfig(shared_scale=on)
    return fuse_keyframe(single, mv, None, config, guard_config=guard, evidence=evidence)


def _mae(depth: np.ndarray, gt: np.ndarray) -> float:
    return float(np.nanmean(np.abs(depth - gt)))


def test_a_keyframe_whose_points_share_a_bias_keeps_the_single_views_scale():
    gt, single, mv, evidence = _keyframe(0.14)
    taken, weighed = _fuse(single, mv, evidence, False), _fuse(single, mv, evidence, True)
    assert weighed.decision in ('full', 'fewer_points'), weighed.decision_reason
    assert weighed.evidence['shared_std'] == pytest.approx(0.14, rel=1e-3)
    assert weighed.evidence['scale_weight'] < 0.4
    # all of the points' scale makes the keyframe worse than its input; weighed, it is not
    assert _mae(taken.depth, gt) > _mae(single, gt)
    assert _mae(weighed.depth, gt) < _mae(single, gt) < _mae(taken.depth, gt)


def test_points_that_share_nothing_are_fused_as_before_to_the_bit():
    gt, single, mv, evidence = _keyframe(0.0)
    taken, weighed = _fuse(single, mv, evidence, False), _fuse(single, mv, evidence, True)
    assert weighed.evidence['shared_std'] == 0.0 and weighed.evidence['scale_weight'] == 1.0
    np.testing.assert_array_equal(weighed.depth, taken.depth)
    # the points' scale in full: the fused depth follows the points, 14 % near
    assert _mae(weighed.depth, gt) > _mae(single, gt)
