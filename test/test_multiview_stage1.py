"""Stage 1 per multi-view method: the sweep's best fraction by score, every filter estimate."""

from __future__ import annotations

import numpy as np
import pytest

from depth_fusion_ros.camera import PinholeCamera
from depth_fusion_ros.multiview.filter_result import FilterResult
from depth_fusion_ros.multiview.semidense import MultiViewResult, empty_result
from depth_fusion_ros.multiview.stage1 import resolve_rule, stage1_mask


def _maps(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    depth = np.where(rng.random((30, 40)) < 0.3, rng.uniform(1, 3, (30, 40)), np.nan).astype(np.float32)
    score = np.where(np.isfinite(depth), rng.random((30, 40)), np.nan).astype(np.float32)
    return depth, score


def _result(cls: type, depth: np.ndarray, score: np.ndarray) -> MultiViewResult:
    """A result of class ``cls`` with these maps (every other map empty)."""
    empty = empty_result(PinholeCamera(40, 30, 30.0, 30.0, 19.5, 14.5))
    return cls(**{**vars(empty), 'depth': depth, 'score': score, 'candidates': np.isfinite(depth)})


def test_rules_resolve_by_method_and_fraction_keeps_the_best_scores():
    assert resolve_rule('auto', 'sweep') == 'fraction'
    assert resolve_rule('auto', 'filter') == 'all'
    assert resolve_rule('auto', None) == 'fraction'  # nothing announced yet: the paper's rule
    assert resolve_rule('all', 'sweep') == 'all'
    with pytest.raises(ValueError, match='stage1 must be one of auto, fraction, all'):
        resolve_rule('best', 'sweep')
    depth, score = _maps()
    valid = np.isfinite(depth)
    best = stage1_mask(depth, score, 'fraction', 0.25)
    assert best.sum() == round(0.25 * valid.sum())
    assert score[best].min() >= np.quantile(score[valid], 0.74)
    assert np.array_equal(stage1_mask(depth, score, 'all', 0.25), valid)


def test_a_filter_result_sends_every_estimate_and_a_sweep_result_its_best_quarter():
    depth, score = _maps(1)
    sweep = _result(MultiViewResult, depth, score)
    filt = _result(FilterResult, depth, score)
    assert (sweep.method, filt.method) == ('sweep', 'filter')
    assert np.array_equal(filt.stage1_mask(), np.isfinite(depth))
    assert np.array_equal(sweep.stage1_mask(), sweep.selected_mask(0.25))
    assert np.array_equal(filt.stage1_mask('fraction'), sweep.selected_mask(0.25))  # explicit rule wins
