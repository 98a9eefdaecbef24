"""Evaluation methods multi_view, multi_view_selected and tv on the synthetic room sequence.

The default method is the temporal filter (checked here); the sweep-specific checks pin
``multi_view.method=sweep`` so that the paper's method stays covered. The filter's own
accuracy is in test_multiview_filter.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from depth_fusion_ros.evaluation.context import EvalOptions, KeyframeContext
from depth_fusion_ros.evaluation.harness import evaluate_sequence
from depth_fusion_ros.evaluation.methods.multi_view import (
    DEFAULT_METHOD,
    multi_view_method,
    multi_view_result,
    neighbour_indices,
)
from depth_fusion_ros.evaluation.registry import get_method
from depth_fusion_ros.metrics import high_gradient_mask

pytestmark = pytest.mark.usefixtures('one_torch_thread')

#: ``--set multi_view.method=sweep``: the paper's sweep (the default is the filter).
SWEEP = {'method': 'sweep'}


def test_methods_are_registered_with_their_kind():
    assert get_method('multi_view').sparse
    assert get_method('multi_view_selected').sparse
    assert not get_method('tv').sparse


def test_semi_dense_methods_on_the_synthetic_room(synthetic_sequence):
    options = EvalOptions(frames=24, stride=12, params={'multi_view': SWEEP})
    result = evaluate_sequence(
        synthetic_sequence, ['multi_view', 'multi_view_selected'], options, show_progress=False
    )
    everything = result.records['multi_view'].to_json()
    selected = result.records['multi_view_selected'].to_json()
    assert everything['density'] > 0.05
    assert 0.01 < selected['density'] < everything['density']
    assert 0.5 * everything['density'] < everything['good_density'] <= everything['density']
    assert selected['median_abs_rel'] < 0.02
    assert selected['n_selected'] > 0


def test_selected_row_scores_the_points_the_fusion_takes(synthetic_sequence):
    """``multi_view_selected`` follows ``fusion.stage1_fraction`` (one mask with stage 1 of
    ``fused``), and ``multi_view.select_fraction`` is the same setting seen from the other side."""
    from depth_fusion_ros.evaluation.methods.fusion import _stage1, fusion_settings

    counts = {}
    for stage, key in (('fusion', 'stage1_fraction'), ('multi_view', 'select_fraction')):
        for fraction in (0.25, 0.5):
            params = {'multi_view': dict(SWEEP)}
            params.setdefault(stage, {})[key] = fraction
            options = EvalOptions(frames=24, stride=12, params=params)
            ctx = KeyframeContext(synthetic_sequence, 12, options, {})
            selected = get_method('multi_view_selected').fn(ctx)
            mask = _stage1(ctx, multi_view_result(ctx), fusion_settings(ctx)[1])
            assert selected.extras['n_selected'] == mask.sum() > 0
            counts[stage, fraction] = int(mask.sum())
    for stage in ('fusion', 'multi_view'):
        assert counts[stage, 0.5] == pytest.approx(2 * counts[stage, 0.25], abs=1)


def test_result_and_neighbours_are_shared_and_options_honoured(synthetic_sequence):
    shared: dict = {}
    options = EvalOptions(
        neighbour_mode='online', num_neighbours=2, params={'multi_view': {**SWEEP, 'num_samples': 40}}
    )
    ctx = KeyframeContext(synthetic_sequence, 10, options, shared)
    indices = neighbour_indices(ctx)
    assert len(indices) == 2 and all(i < 10 for i in indices)
    result = multi_view_result(ctx)
    assert multi_view_result(ctx) is result
    assert result.neighbours == tuple(indices)
    # A second keyframe context of the same run reuses the neighbour table.
    assert any(key.startswith('multi_view:neighbours:online:2') for key in shared)
    # The first keyframe has no past frame online: an all-NaN estimate, not an error.
    first = multi_view_result(KeyframeContext(synthetic_sequence, 0, options, shared))
    assert not np.isfinite(first.depth).any()


def test_the_default_method_is_the_filter(synthetic_sequence):
    """No ``multi_view.method``: the temporal filter, whose stage 1 passes every estimate on."""
    ctx = KeyframeContext(synthetic_sequence, 12, EvalOptions(frames=24, stride=12), {})
    assert DEFAULT_METHOD == multi_view_method(ctx) == 'filter'
    result = multi_view_result(ctx)
    assert result.method == 'filter' and result.valid.mean() > 0.05
    selected = get_method('multi_view_selected').fn(ctx)
    assert selected.extras['n_selected'] == result.valid.sum()
    sweep = KeyframeContext(synthetic_sequence, 12, EvalOptions(params={'multi_view': SWEEP}), {})
    assert multi_view_method(sweep) == 'sweep' and multi_view_result(sweep).method == 'sweep'


def test_unknown_or_mistyped_override_is_reported(synthetic_sequence):
    for params, message in (
        ({'multi_view': {'num_sample': 40}}, 'unknown parameter multi_view.num_sample'),
        ({'multi_view': {'num_samples': 'many'}}, 'multi_view.num_samples: expected an integer'),
        ({'neighbours': {'window': 0}}, 'neighbours.window must be >= 1'),
    ):
        ctx = KeyframeContext(synthetic_sequence, 5, EvalOptions(params=params), {})
        with pytest.raises(ValueError, match=message):
            get_method('multi_view').fn(ctx)


def test_tv_method_is_dense(synthetic_sequence):
    options = EvalOptions(params={'tv': {'edge_alpha': 10.0}})  # an override goes through
    ctx = KeyframeContext(synthetic_sequence, 12, options, {})
    out = get_method('tv').fn(ctx)
    gt = ctx.gt_depth_working
    assert out.depth.shape == gt.shape and np.all(np.isfinite(out.depth))
    # TV is reliable on image edges only (the paper's point): score it there.
    edges = high_gradient_mask(ctx.frame.gray) & np.isfinite(gt)
    assert np.median(np.abs(out.depth[edges] - gt[edges]) / gt[edges]) < 0.15
