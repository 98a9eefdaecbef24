"""Each point's precision weight (fusion/precision.py, issue 11); the kernels' handling of it is
tested against the formulas in test_fusion_pipeline.py."""

from __future__ import annotations

import numpy as np
import pytest

from depth_fusion_ros.fusion.guard import MultiViewEvidence
from depth_fusion_ros.fusion.interpolation import interpolate
from depth_fusion_ros.fusion.pipeline import FusionConfig, fuse_keyframe
from depth_fusion_ros.fusion.precision import precision_weights
from depth_fusion_ros.fusion.scenes import make_scene


def test_precision_weights_halve_at_the_half_weight_and_switch_off() -> None:
    r = np.array([[0.0, 0.05, 0.1, np.nan, -1.0]], dtype=np.float32)
    c = precision_weights(r, 0.05)
    assert np.allclose(c[0, :3], [1.0, 0.5, 0.2])
    assert np.isnan(c[0, 3]) and np.isnan(c[0, 4])
    assert precision_weights(r, 0.0) is None and precision_weights(None, 0.05) is None
    with pytest.raises(ValueError, match='std_half_weight'):
        FusionConfig(std_half_weight=-0.1)
    with pytest.raises(ValueError, match='point_weight'):
        interpolate(np.ones((4, 4)), np.ones((4, 4)), np.ones((4, 4), bool), point_weight=np.zeros((4, 4)))


def test_imprecise_wrong_points_bend_the_depth_less() -> None:
    """Points whose multi-view depth is off by 8 % and whose std says so (relative std
    0.2) pull the fused depth less than exact points with a small std: with the precision
    weights the fused error drops, and without the std the fusion is the paper's."""
    sc = make_scene(80, 60, n_points=120, seed=3)
    rng = np.random.default_rng(3)
    omega = np.isfinite(sc.multi)
    bad = omega & (rng.random(sc.multi.shape) < 0.4)
    multi = np.where(bad, sc.multi * 1.08, sc.multi).astype(np.float32)
    std = np.where(bad, 0.2, 0.01).astype(np.float32) * multi
    cfg = FusionConfig(guard=False, ransac_threshold=0.5, std_half_weight=0.05)
    paper = fuse_keyframe(sc.single, multi, None, cfg)
    evidence = MultiViewEvidence.from_depth_std(multi, std)
    weighted = fuse_keyframe(sc.single, multi, None, cfg, evidence=evidence)
    unweighted = fuse_keyframe(
        sc.single, multi, None, FusionConfig(guard=False, ransac_threshold=0.5), evidence=evidence
    )
    runs = (('paper', paper), ('weighted', weighted), ('off', unweighted))
    err = {name: float(np.nanmean(np.abs(r.depth - sc.depth))) for name, r in runs}
    assert err['off'] == err['paper']
    assert err['weighted'] < 0.8 * err['paper'], err
