"""The fusion's evaluation methods on a small synthetic sequence (exact ground truth and poses)."""

from __future__ import annotations

import numpy as np
import pytest

from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence
from depth_fusion_ros.evaluation.context import EvalOptions, KeyframeContext
from depth_fusion_ros.evaluation.methods.fusion import consistency_settings, fusion_settings, oracle_mask
from depth_fusion_ros.evaluation.methods.single_view import single_view_prediction
from depth_fusion_ros.evaluation.registry import available_methods, get_method

FUSION_METHODS = ('fused', 'fused_fast', 'fused_oracle', 'fused_w1', 'fused_w1w2', 'fused_consistent')


@pytest.fixture(scope='module')
def sequence():
    return render_sequence(SynthConfig(width=96, height=72, frames=6, parallax='high', seed=5))


def _context(sequence, **params) -> KeyframeContext:
    options = EvalOptions(single_view='simulated', params={'fusion': {'compile_kernel': False, **params}})
    return KeyframeContext(sequence, 2, options, {})


def test_every_fusion_method_is_registered() -> None:
    assert set(FUSION_METHODS) <= set(available_methods())


def test_methods_fuse_a_keyframe_and_report_their_counts(sequence) -> None:
    ctx = _context(sequence)
    outputs = {name: get_method(name).fn(ctx) for name in FUSION_METHODS}
    single = single_view_prediction(ctx).depth
    for name, out in outputs.items():
        assert out.depth.shape == single.shape
        assert np.array_equal(np.isfinite(out.depth), np.isfinite(single)), name
        assert {'n_stage1', 'n_omega', 'fallback'} <= set(out.extras), name
    auto = outputs['fused'].extras
    assert auto['n_omega'] <= auto['n_stage1'] and auto['fallback'] in (0.0, 1.0)
    gt = ctx.gt_depth_working
    oracle = outputs['fused_oracle']
    assert oracle.extras['fallback'] == 0.0 and oracle.extras['n_omega'] > 0
    # The oracle points are within 10 cm of the truth and bend the prior towards it.
    valid = np.isfinite(gt) & (gt > 0)
    err_single = np.abs(single - gt)[valid].mean()
    assert np.abs(oracle.depth - gt)[valid].mean() < err_single


def test_stage_parameters_are_honoured_and_checked(sequence) -> None:
    config, extra = fusion_settings(_context(sequence, mode='fast', stage1_fraction=0.5, sigma1=9))
    assert config.mode == 'fast' and config.sigma1 == 9 and extra['stage1_fraction'] == 0.5
    forced, _ = fusion_settings(_context(sequence, weights='w1'), weights='all')
    assert forced.weights == 'all'  # the method's own setting wins
    with pytest.raises(ValueError, match='sigma4'):
        fusion_settings(_context(sequence, sigma4=1.0))


def test_oracle_mask_keeps_points_within_the_threshold() -> None:
    gt = np.array([[1.0, 2.0, np.nan, 0.0]], np.float32)
    mv = np.array([[1.05, 2.5, 1.0, 1.0]], np.float32)
    assert oracle_mask(mv, gt, 0.1).tolist() == [[True, False, False, False]]
    with pytest.raises(ValueError, match='ground-truth'):
        oracle_mask(mv, None, 0.1)


def test_consistency_parameters_are_honoured_and_checked(sequence) -> None:
    options = EvalOptions(
        single_view='simulated', params={'consistency': {'tolerance': 0.05, 'candidates': 'all'}}
    )
    config = consistency_settings(KeyframeContext(sequence, 2, options, {}))
    assert config.tolerance == 0.05 and config.candidates == 'all' and not config.enabled
    bad = EvalOptions(single_view='simulated', params={'consistency': {'tolerence': 0.05}})
    with pytest.raises(ValueError, match=r'consistency\.tolerence'):
        consistency_settings(KeyframeContext(sequence, 2, bad, {}))
