"""Relative single-view models made metric by the fusion: the per-keyframe fit in the model's
own space (fusion/alignment.py) and the ``simulated_relative`` source."""

from __future__ import annotations

import numpy as np
import pytest

from depth_fusion_ros.fusion.alignment import apply_alignment, fit_alignment, fit_space
from depth_fusion_ros.fusion.pipeline import FusionConfig, fuse_keyframe
from depth_fusion_ros.fusion.selection import LinearFit
from depth_fusion_ros.singleview.simulated import to_relative_inverse

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def _points(n: int = 400, outliers: float = 0.2, seed: int = 0):
    """Metric depths m at n points, a disparity model's output s = 0.3 / m + 0.8 there, and a
    fraction of wrong multi-view matches."""
    rng = np.random.default_rng(seed)
    m_true = rng.uniform(0.5, 5.0, n)
    s = 0.3 / m_true + 0.8
    m = m_true * (1 + rng.normal(0, 0.01, n))
    bad = rng.random(n) < outliers
    m[bad] = rng.uniform(0.3, 8.0, int(bad.sum()))
    return s, m, bad


def test_disparity_fit_is_in_inverse_depth_space_and_ignores_wrong_matches():
    s, m, bad = _points()
    fit = fit_alignment(s, m, 'inverse_depth', FusionConfig(ransac_threshold=0.05))
    assert fit.ok and fit.inverse and fit_space('inverse_depth') == 'inverse_depth'
    # 1/m = (s - 0.8) / 0.3  ->  a = 1/0.3, b = -0.8/0.3
    assert fit.a == pytest.approx(1 / 0.3, rel=0.02) and fit.b == pytest.approx(-0.8 / 0.3, rel=0.02)
    assert fit.inliers[~bad].mean() > 0.95 and fit.inliers[bad].mean() < 0.2
    relative = fit_alignment(s, m, 'relative_depth', FusionConfig(ransac_threshold=0.05))
    assert not relative.inverse  # relative depth is fitted in depth space


def test_non_positive_aligned_depth_is_nan_and_counted():
    fit = LinearFit(a=2.0, b=-1.0, inverse=True, inliers=np.ones(1, bool), ok=True, max_depth=4.0)
    s = np.array([[1.0, 0.5, 0.2], [np.nan, 0.5001, 3.0]], dtype=np.float32)
    out = apply_alignment(s, fit)
    assert out.n_nonpositive == 2  # 2·0.5 − 1 = 0 and 2·0.2 − 1 < 0: beyond infinity
    assert np.isnan(out.depth[0, 1]) and np.isnan(out.depth[0, 2]) and np.isnan(out.depth[1, 0])
    assert out.depth[0, 0] == pytest.approx(1.0)
    assert out.depth[1, 1] == pytest.approx(40.0)  # tiny positive inverse depth: 10 x the farthest inlier
    assert out.depth[1, 2] == pytest.approx(0.2)
    depth_fit = LinearFit(a=1.0, b=-1.0, inverse=False, inliers=np.ones(1, bool), ok=True)
    assert apply_alignment(np.array([0.5, 2.0]), depth_fit).n_nonpositive == 1


def test_relative_inverse_is_an_affine_map_of_inverse_depth_seeded_per_keyframe():
    depth = np.random.default_rng(1).uniform(0.5, 4.0, (24, 32)).astype(np.float32)
    a, b, c = (to_relative_inverse(depth, seed=(0, k)) for k in (3, 3, 4))
    np.testing.assert_array_equal(a.inverse, b.inverse)
    assert (a.scale, a.shift) != (c.scale, c.shift)
    assert a.scale > 0 and a.shift >= 0
    np.testing.assert_allclose(a.inverse, a.scale / depth + a.shift, rtol=1e-5)


def test_fusion_of_an_inverse_depth_model_matches_the_metric_one_and_reports_nonpositive():
    from depth_fusion_ros.fusion.scenes import make_scene

    scene = make_scene(96, 72, n_points=300, offset=0.0, seed=2)  # single-view = 0.8 x depth
    metric = fuse_keyframe(scene.single, scene.multi, None, FusionConfig(align_scale=True))
    rel = to_relative_inverse(scene.single, seed=5)
    inverse = fuse_keyframe(rel.inverse, scene.multi, None, FusionConfig(), output_kind='inverse_depth')
    assert inverse.fallback is None and inverse.n_nonpositive == 0
    mae = lambda d: float(np.nanmean(np.abs(d - scene.depth)))  # noqa: E731
    assert mae(inverse.depth) <= 1.1 * mae(metric.depth) + 1e-3
    # the network puts a corner "beyond infinity" (disparity below the shift): NaN there, counted
    beyond = rel.inverse.copy()
    beyond[:10, :10] = rel.shift - 1.0
    far = fuse_keyframe(beyond, scene.multi, None, FusionConfig(), output_kind='inverse_depth')
    assert far.fallback is None and far.n_nonpositive == 100
    assert np.isnan(far.depth[:10, :10]).all() and int(np.isnan(far.depth).sum()) == 100


def test_simulated_relative_is_made_metric_by_the_fusion_on_synthetic_rooms(synthetic_sequence):
    """The issue's property on synthetic rooms: a disparity-like source with a random scale and
    shift per keyframe, once aligned and fused, is metric and better than the metric prior it
    came from, and within the issue's 10 % of the metric prior's own fused MAE (0.77x here
    since the inverse fit's RANSAC was fixed, 0.90x before; docs/fusion.md).

    The two sources share the keyframe's multi-view result, not its fusion: the fusion is
    cached per keyframe under one key, and a shared cache once scored the metric fusion twice.

    With the paper's sweep (pinned): the property is the alignment's, and the default
    filter's 20k points per keyframe make the six exact fusions 8x slower (49 s against 6 s
    on 2026-11-25; the assertions held with the filter too). In the fast mode (the node's), as
    the alignment is the same in both: 9.7 s against 21.4 s exact, the three means 0.459 / 0.351
    / 0.698 m against 0.464 / 0.352 / 0.698 (2026-12-01)."""
    from depth_fusion_ros.evaluation.context import EvalOptions, KeyframeContext
    from depth_fusion_ros.evaluation.methods.fusion import fused_automatic

    maes: dict[str, list[float]] = {'simulated': [], 'simulated_relative': [], 'prior': []}
    for index in (4, 12, 20):
        memo: dict | None = None
        for source in ('simulated', 'simulated_relative'):
            options = EvalOptions(
                frames=24,
                single_view=source,
                params={
                    'fusion': {'compile_kernel': False, 'mode': 'fast'},
                    'multi_view': {'method': 'sweep'},
                },
            )
            ctx = KeyframeContext(synthetic_sequence, index, options, {})
            if memo is not None:  # the same keyframe: the multi-view result is computed once
                ctx._memo = {key: value for key, value in memo.items() if not key.startswith('fusion:')}
            memo = ctx._memo
            out = fused_automatic(ctx)
            gt = ctx.gt_depth_working
            valid = np.isfinite(gt) & (gt > 0)
            assert np.isfinite(out.depth[valid]).mean() > 0.99 and out.extras['fallback'] == 0
            maes[source].append(float(np.abs(out.depth - gt)[valid].mean()))
        prior = ctx.cached('single_view:simulated', lambda: None).depth
        maes['prior'].append(float(np.abs(prior - gt)[valid].mean()))
    sim, rel, prior = (float(np.mean(maes[k])) for k in ('simulated', 'simulated_relative', 'prior'))
    assert rel < prior, (rel, prior)
    assert rel <= 1.1 * sim, (sim, rel)
