"""The confidence's agreement factor (fusion/agreement.py): points that disagree lower it."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import spearmanr

from depth_fusion_ros.fusion.agreement import agreement, offset_spread
from depth_fusion_ros.fusion.interpolation import confidence_from_support
from depth_fusion_ros.fusion.pipeline import FusionConfig, fuse_keyframe


def _grid_points(shape: tuple[int, int], step: int) -> np.ndarray:
    points = np.zeros(shape, bool)
    points[step // 2 :: step, step // 2 :: step] = True
    return points


def test_spread_is_zero_where_points_agree_and_their_scatter_where_they_do_not() -> None:
    shape = (60, 80)
    points = _grid_points(shape, 4)
    offsets = np.full(shape, 0.3, np.float32)
    assert np.abs(offset_spread(offsets, points, 8.0)).max() < 1e-5
    # alternating +-0.2 m: the standard deviation of the window is 0.2 m away from the border
    checker = np.where((np.indices(shape).sum(axis=0) // 4) % 2 == 0, 0.2, -0.2).astype(np.float32)
    spread = offset_spread(checker, points, 8.0)
    assert spread[20:40, 20:60] == pytest.approx(0.2, abs=0.02)


def test_a_pixel_with_no_point_in_reach_keeps_its_support_confidence() -> None:
    shape = (60, 200)
    points = np.zeros(shape, bool)
    points[30, 5] = points[32, 7] = True
    offsets = np.where(points, np.float32(0.1), np.nan).astype(np.float32)
    offsets[32, 7] = -0.5
    spread = offset_spread(offsets, points, 4.0)
    assert spread[31, 6] > 0.1 and spread[30, 190] == 0.0
    assert np.isfinite(spread).all()


def test_tau_zero_is_the_support_confidence_alone() -> None:
    rng = np.random.default_rng(1)
    s = np.full((40, 60), 2.0, np.float32)
    m = np.where(rng.random(s.shape) < 0.05, 2.0 + rng.normal(0, 0.2, s.shape), np.nan).astype(np.float32)
    omega = np.isfinite(m)
    off = fuse_keyframe(s, m, None, FusionConfig(agreement_tau=0.0), omega_mask=omega)
    interp_conf = off.confidence
    on = fuse_keyframe(s, m, None, FusionConfig(), omega_mask=omega)
    assert np.array_equal(on.depth, off.depth)  # the depth does not change, only its confidence
    assert np.all(on.confidence <= interp_conf + 1e-7) and on.confidence.mean() < interp_conf.mean()
    assert np.all(agreement(on.depth, s, m, omega, 8.0, 0.0) == 1.0)
    assert confidence_from_support(np.zeros((1, 1)), 15.0)[0, 0] == 1.0


def test_the_confidence_ranks_the_error_where_the_points_of_one_region_disagree() -> None:
    """Left half: exact points; right half: every other point a wrong match 40 % too far. The
    fused depth is wrong on the right; the support confidence alone (every pixel has points
    as near) did not say so, the agreement factor does."""
    truth = np.full((60, 120), 2.0, np.float32)
    single = (0.8 * truth + 0.3).astype(np.float32)
    points = _grid_points(truth.shape, 3)
    wrong = points & (np.arange(120)[None, :] >= 60) & (np.indices(truth.shape).sum(axis=0) % 2 == 0)
    m = np.where(points, truth * np.where(wrong, 1.4, 1.0), np.nan).astype(np.float32)
    inner = (slice(5, -5), slice(10, 110))

    def fused(tau: float) -> tuple[np.ndarray, float]:
        res = fuse_keyframe(
            single, m, None, FusionConfig(weights='w1', guard=False, agreement_tau=tau), omega_mask=points
        )
        err = np.abs(res.depth - truth) / truth
        return res.confidence, spearmanr(res.confidence[inner].ravel(), -err[inner].ravel())[0]

    confidence, rank = fused(0.05)
    _, rank_before = fused(0.0)
    assert np.median(confidence[5:-5, 70:110]) < 0.3 * np.median(confidence[5:-5, 10:50])
    assert rank > 0.5 and rank > rank_before + 0.3


@pytest.mark.parametrize('field, value', [('agreement_tau', -0.1), ('agreement_sigma', 0.0)])
def test_bad_agreement_parameters_raise(field: str, value: float) -> None:
    with pytest.raises(ValueError, match=field):
        FusionConfig(**{field: value})
