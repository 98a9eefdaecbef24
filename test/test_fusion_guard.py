"""The fusion's guard: evidence, decisions, and never worse than the single-view input."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from depth_fusion_ros.fusion.guard import DECISIONS, GuardConfig, MultiViewEvidence, assess
from depth_fusion_ros.fusion.pipeline import FusionConfig, fuse_keyframe
from depth_fusion_ros.fusion.scenes import planes_and_boxes

W, H = 120, 90


def _single(depth: np.ndarray, seed: int) -> np.ndarray:
    """A CNN-like single-view depth: wrong by region (a 3x3 grid of scales 0.75-1.3), right locally."""
    rng = np.random.default_rng(seed)
    factors = rng.uniform(0.75, 1.3, (3, 3))
    rows = np.minimum(np.arange(H) * 3 // H, 2)
    cols = np.minimum(np.arange(W) * 3 // W, 2)
    return (depth * factors[rows][:, cols]).astype(np.float32)


def _multi(depth: np.ndarray, seed: int, density: float, noise: float, region: np.ndarray | None = None):
    """Semi-dense multi-view depth on a random ``density`` of the pixels, log-normal ``noise``
    (independent per point: wrong matches) inside ``region`` (everywhere when None)."""
    rng = np.random.default_rng(seed + 100)
    m = np.full(depth.shape, np.nan, dtype=np.float32)
    pick = rng.random(depth.shape) < density
    values = depth * np.exp(rng.normal(0.0, 1.0, depth.shape) * noise)
    if region is not None:
        values = np.where(region, values, depth)
    m[pick] = values[pick]
    return m


def _mae(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.nanmean(np.abs(a - b)))


@pytest.fixture(scope='module')
def truth() -> np.ndarray:
    return planes_and_boxes(W, H, boxes=2, seed=4)


def test_consistent_points_keep_the_full_fusion(truth):
    single = _single(truth, 0)
    multi = _multi(truth, 0, density=0.08, noise=0.01)
    result = fuse_keyframe(single, multi, None, FusionConfig(mode='fast'))
    assert result.decision == 'full', result.decision_reason
    assert result.keyframe_confidence == 1.0 and result.fallback is None
    assert result.evidence['mv_noise'] < GuardConfig().max_mv_noise
    assert _mae(result.depth, truth) < 0.7 * _mae(single, truth)


def test_independent_wrong_matches_step_down_and_never_hurt(truth):
    single = _single(truth, 1)
    multi = _multi(truth, 1, density=0.01, noise=0.5)  # sparse, most points 20-80 % off, independently
    guarded = fuse_keyframe(single, multi, None, FusionConfig(mode='fast'))
    unguarded = fuse_keyframe(single, multi, None, FusionConfig(mode='fast', guard=False))
    assert DECISIONS.index(guarded.decision) >= DECISIONS.index('scale_only'), guarded.evidence
    assert guarded.evidence['effective_noise'] > GuardConfig().max_mv_noise
    assert _mae(guarded.depth, truth) <= _mae(single, truth)
    assert _mae(guarded.depth, truth) <= _mae(unguarded.depth, truth)
    assert float(np.nanmax(guarded.confidence)) <= guarded.keyframe_confidence < 1.0


def test_a_bad_region_is_dropped_and_the_rest_fused(truth):
    single = _single(truth, 2)
    bad = np.zeros(truth.shape, dtype=bool)
    bad[:, : W // 2] = True  # half of the image has wrong matches
    multi = _multi(truth, 2, density=0.08, noise=0.35, region=bad)
    # full_fraction 0.8: half the points inconsistent is below it (the default, 0.5, keeps
    # every point up to there: on the stress cases and TUM dropping fewer did better).
    guard = GuardConfig(full_fraction=0.8)
    result = fuse_keyframe(single, multi, None, FusionConfig(mode='fast'), guard_config=guard)
    assert result.decision == 'fewer_points', (result.decision, result.evidence)
    used = result.omega_mask
    assert used[bad].mean() < 0.5 * used[~bad].mean()
    assert _mae(result.depth, truth) < _mae(single, truth)


def test_too_few_points_is_the_single_view_depth_flagged(truth):
    single = _single(truth, 3)
    multi = _multi(truth, 3, density=0.0015, noise=0.0)
    result = fuse_keyframe(single, multi, None, FusionConfig(mode='fast', ransac_min_inliers=2))
    assert result.decision == 'single_view' and result.keyframe_confidence == 0.0
    np.testing.assert_array_equal(result.depth, single)
    assert not result.confidence.any()


def test_guard_off_and_given_omega_are_the_paper_fusion(truth):
    single = _single(truth, 4)
    multi = _multi(truth, 4, density=0.08, noise=0.35)
    off = fuse_keyframe(single, multi, None, FusionConfig(mode='fast', guard=False))
    # No guard evidence; only the certainty floor's share kept, the halo test's report (not
    # run here: no keyframe image) and the edge test's (edge_points.py), there either way.
    assert off.decision == 'full'
    assert set(off.evidence) == {
        'certainty', 'certainty_floor', 'halo_checked', 'n_halo', 'edge_share', 'edge_ratio', 'edge_explained'
    }  # fmt: skip
    assert off.evidence['edge_explained'] == 0.0, 'points spread over the image are left as they are'
    oracle = fuse_keyframe(single, multi, None, FusionConfig(mode='fast'), omega_mask=np.isfinite(multi))
    assert oracle.decision == 'full'


def test_parallax_evidence_removes_low_parallax_points(truth):
    single = _single(truth, 5)
    multi = _multi(truth, 5, density=0.08, noise=0.01)
    omega = np.isfinite(multi)
    rel = np.where(omega, 0.01, np.nan).astype(np.float32)
    rel[:, W // 2 :] = 0.5  # half the points have almost no parallax
    evidence = MultiViewEvidence(relative_std=rel)
    verdict = assess(single, multi, omega, int(omega.sum()), GuardConfig(), evidence)
    assert verdict.decision == 'fewer_points'
    assert not verdict.trusted[:, W // 2 :].any() and verdict.trusted[:, : W // 2].any()
    assert verdict.evidence['median_relative_std'] > 0


def test_points_about_as_far_off_as_the_single_view_are_not_trusted(truth):
    """A point whose std passes ``max_relative_std`` only by the single view's own error is
    trusted below ``single_error_share`` of that error: its std at three quarters of it is not
    trusted by default (the hand-held streams of docs/fusion.md were fused above their input
    at the whole of it), and is at ``single_error_share`` 1."""
    single = _single(truth, 6)
    multi = _multi(truth, 6, density=0.08, noise=0.01)
    omega = np.isfinite(multi)
    plain = assess(single, multi, omega, int(omega.sum()), GuardConfig(), None)
    single_error = plain.evidence['single_error']
    assert single_error > 0.1
    evidence = MultiViewEvidence(relative_std=np.where(omega, 0.75 * single_error, np.nan).astype(np.float32))
    for share, decision in ((GuardConfig().single_error_share, 'single_view'), (1.0, 'full')):
        config = GuardConfig(max_relative_std=0.05, single_error_share=share)
        verdict = assess(single, multi, omega, int(omega.sum()), config, evidence)
        assert verdict.decision == decision, (share, verdict.reason)
        assert verdict.evidence['precise_fraction'] == (0.0 if decision == 'single_view' else 1.0)


def test_corrections_do_not_reach_far_from_their_points(truth):
    # The single-view depth is 25 % too far on the left, 5 % too near on the right: unrelated
    # errors, as in two regions of a network's prediction.
    single = (truth * np.where(np.arange(W) < W // 2, 1.25, 0.95)[None, :]).astype(np.float32)
    multi = _multi(truth, 6, density=0.08, noise=0.01)
    multi[:, W // 3 :] = np.nan  # the points cover the left third only (weak texture elsewhere)
    reached = fuse_keyframe(single, multi, None, FusionConfig(mode='fast'))
    unlimited = fuse_keyframe(
        single, multi, None, FusionConfig(mode='fast'), guard_config=GuardConfig(reach=0.0)
    )
    assert reached.decision == 'full' and 0 < reached.evidence['coverage'] < 0.6
    far = np.s_[:, W - W // 6 :]  # more than reach x width from every point: the single-view depth
    np.testing.assert_allclose(reached.depth[far], single[far], rtol=0.02)
    near = np.s_[:, : W // 3]
    assert _mae(reached.depth[near], truth[near]) < 0.5 * _mae(single[near], truth[near])
    assert _mae(reached.depth, truth) < min(_mae(single, truth), _mae(unlimited.depth, truth))


def test_no_scale_from_untrusted_points(truth):
    single = _single(truth, 7)
    multi = _multi(truth, 7, density=0.08, noise=0.01) * np.float32(0.8)  # consistent, 20 % too near
    omega = np.isfinite(multi)
    evidence = MultiViewEvidence(relative_std=np.where(omega, 0.5, np.nan).astype(np.float32))  # no parallax
    result = fuse_keyframe(single, multi, None, FusionConfig(mode='fast'), evidence=evidence)
    assert result.decision == 'single_view' and 'scale untrusted' in result.decision_reason
    np.testing.assert_allclose(result.depth, single)
    assert result.keyframe_confidence == 0.0


def test_a_relative_source_with_untrusted_points_is_withheld(truth):
    """The same untrusted points with a relative source: there is no depth in metres to pass
    on, so the keyframe has none (NaN), flagged, instead of the rejected fit's numbers."""
    single = _single(truth, 7)
    multi = _multi(truth, 7, density=0.08, noise=0.01) * np.float32(0.8)
    omega = np.isfinite(multi)
    evidence = MultiViewEvidence(relative_std=np.where(omega, 0.5, np.nan).astype(np.float32))
    relative = 3.0 * single + 0.7  # affine in depth: what a relative model gives
    result = fuse_keyframe(
        relative, multi, None, FusionConfig(mode='fast'), 'relative_depth', evidence=evidence
    )
    assert result.decision == 'single_view' and result.fallback is None and result.withheld
    assert np.isnan(result.depth).all() and np.all(result.confidence == 0)
    assert 'scale untrusted' in result.decision_reason and 'withheld' in result.decision_reason
    trusted = fuse_keyframe(
        relative, multi / np.float32(0.8), None, FusionConfig(mode='fast'), 'relative_depth'
    )
    assert not trusted.withheld and np.isfinite(trusted.depth).mean() > 0.9


def test_weak_stage2_support_keeps_the_single_view_depth(truth):
    """Points that agree with each other but not with most of stage 1 (a biased subset
    surviving among wrong estimates) are not fused, nor is their scale used."""
    single = _single(truth, 6)
    rng = np.random.default_rng(7)
    multi = _multi(truth, 6, density=0.06, noise=0.0)
    wrong = np.isfinite(multi) & (rng.random(truth.shape) < 0.7)  # 70 % of the estimates far off
    # independent and far off (factor e^±0.5 to e^±1.6): no single fit explains them
    factor = np.exp(rng.choice([-1.0, 1.0], truth.shape) * rng.uniform(0.5, 1.6, truth.shape))
    multi[wrong] = (truth * factor)[wrong]
    guarded = fuse_keyframe(single, multi, None, FusionConfig(mode='fast'))
    assert guarded.evidence['inlier_ratio'] < GuardConfig().min_inlier_ratio, guarded.evidence
    assert guarded.decision == 'single_view' and 'stage 2 kept' in guarded.decision_reason
    np.testing.assert_array_equal(guarded.depth, single)
    assert guarded.keyframe_confidence == 0.0
    relaxed = fuse_keyframe(
        single, multi, None, FusionConfig(mode='fast'), guard_config=GuardConfig(min_inlier_ratio=0.0)
    )
    assert relaxed.decision != 'single_view' or 'stage 2 kept' not in relaxed.decision_reason


def test_points_noisy_from_weak_geometry_are_not_trusted_nor_their_scale(truth):
    """Points scattered by 10 % each around their neighbours *and* 40 % too near together (the
    weak geometry of a SLAM keyframe under rotation with a wrong focal length: docs/fusion.md)
    pass the local test and the averaged noise; ``max_point_noise`` keeps the single view."""
    single = _single(truth, 8)
    multi = _multi(truth, 8, density=0.08, noise=0.1) * np.float32(0.6)
    guarded = fuse_keyframe(single, multi, None, FusionConfig(mode='fast'))
    assert guarded.evidence['mv_noise'] > GuardConfig().max_point_noise, guarded.evidence
    assert guarded.evidence['effective_noise'] < GuardConfig().max_mv_noise
    assert guarded.decision == 'single_view' and 'point noise' in guarded.decision_reason
    np.testing.assert_array_equal(guarded.depth, single)
    relaxed = fuse_keyframe(
        single, multi, None, FusionConfig(mode='fast'), guard_config=GuardConfig(max_point_noise=1.0)
    )
    assert relaxed.decision == 'full'
    assert _mae(relaxed.depth, truth) > 1.2 * _mae(single, truth)


@pytest.mark.parametrize(
    ('field', 'value'),
    [
        ('local_tolerance', 0.0),
        ('full_fraction', 1.5),
        ('min_trusted_points', 0),
        ('reach', -1.0),
        ('min_inlier_ratio', 1.2),
        ('single_error_share', 1.5),
        ('max_point_noise', 0.0),
    ],
)
def test_bad_thresholds_raise(field, value):
    with pytest.raises(ValueError, match=f'guard.{field}'):
        GuardConfig(**{field: value})


def _local_deviation_loop(points, residual, radius, min_neighbours, max_neighbours=None):
    """The per-point loop ``guard._local_deviation`` replaced: the reference it must match
    (the nearest ``max_neighbours`` within the radius, equidistant ones in index order; every
    one when None)."""
    neighbours = cKDTree(points).query_ball_point(points, r=radius)  # each list in index order
    out = np.full(len(points), np.nan)
    counts = np.zeros(len(points))
    for i, idx in enumerate(neighbours):
        others = np.array([j for j in idx if j != i], dtype=int)
        counts[i] = len(others)
        if max_neighbours is not None:
            order = np.argsort(np.hypot(*(points[others] - points[i]).T), kind='stable')
            others = others[order[:max_neighbours]]
        if len(others) >= min_neighbours:
            out[i] = abs(residual[i] - np.median(residual[others]))
    return out, float(np.median(counts))


def _pixels(rng, density, shape=(60, 80)):
    rows, cols = np.nonzero(rng.random(shape) < density)  # row-major, as Ω's points
    return cols, rows


@pytest.mark.parametrize('density', [0.02, 0.4])
@pytest.mark.parametrize('max_neighbours', [500, 16, 3])
def test_local_deviation_is_the_per_point_median_exactly(density, max_neighbours):
    """Vectorised, the same numbers as the loop on pixel points (sparse and isolated ones,
    dense ones, even and odd counts, tied residuals), with a cap above every point's neighbour
    count and below it: then equidistant neighbours (rings of up to 16 pixels) count in index
    order, whichever order the k-d tree returned them in."""
    from depth_fusion_ros.fusion import guard

    rng = np.random.default_rng(7)
    cols, rows = _pixels(rng, density)
    points = np.stack((cols, rows), axis=1).astype(np.float64)
    residual = rng.normal(0.0, 0.2, len(points))
    residual[::7] = residual[0]  # ties: the median must not depend on their order
    expected = _local_deviation_loop(points, residual, 12.0, 2, max_neighbours)
    got = guard._local_deviation(cols, rows, residual, 12.0, 2, max_neighbours)
    np.testing.assert_array_equal(got[0], expected[0])
    assert got[1] == expected[1]
    assert np.isfinite(got[0]).any()
    empty = guard._local_deviation(np.zeros(0, int), np.zeros(0, int), np.zeros(0), 12.0, 2, 32)
    assert empty[0].shape == (0,) and empty[1] == 0.0


@pytest.mark.parametrize('radius', [12.0, 7.5, 3.0])
def test_the_grid_search_gives_the_tree_search_numbers(radius):
    """The GPU's search (every offset in one gather) and the CPU's (a k-d tree, its last ring
    read in order; row spans for the support) give the same medians and counts, here both on
    the CPU."""
    from depth_fusion_ros.fusion import neighbour_median as nm

    rng = np.random.default_rng(5)
    for density in (0.05, 0.3, 0.9):
        cols, rows = _pixels(rng, density, (90, 120))
        values = rng.normal(0.0, 1.0, len(cols))
        tree = nm.nearest_median(cols, rows, values, radius, 16, 'cpu', support_step=3)
        grid = nm.grid_median(cols, rows, values, radius, 16, torch.device('cpu'), support_step=3)
        for got, expected in zip(grid, tree, strict=True):
            np.testing.assert_array_equal(got, expected)


@pytest.mark.parametrize('radius', [12.0, 7.5, 3.0])
@pytest.mark.parametrize('max_neighbours', [16, 3, 1])
def test_the_native_ring_walk_gives_the_tree_search_numbers(radius, max_neighbours):
    """The CPU's kernel (``ring_median.c``: each point walks the ring offsets and stops at the
    k-th neighbour) and the k-d tree give the same medians, bit for bit, and the same counts;
    ties among the values, sparse and dense points."""
    from depth_fusion_ros import native_build
    from depth_fusion_ros.fusion import neighbour_median as nm

    if nm._ring_median_library() is None:
        pytest.skip(f'the native kernel cannot run here: {native_build.unavailable() or "it did not build"}')
    rng = np.random.default_rng(11)
    for density in (0.01, 0.05, 0.3, 0.9):
        cols, rows = _pixels(rng, density, (90, 120))
        values = rng.normal(0.0, 1.0, len(cols))
        values[::5] = values[0]
        native = nm.native_median(cols, rows, values, radius, max_neighbours)
        assert native is not None
        tree = nm.tree_median(cols, rows, values, radius, max_neighbours)
        np.testing.assert_array_equal(native[0], tree[0])
        np.testing.assert_array_equal(native[1], tree[1])
    assert nm.native_median(cols, rows, values, radius, 500) is None  # beyond the kernel's 256: the tree
    values[3] = np.nan
    assert nm.native_median(cols, rows, values, radius, max_neighbours) is None


def test_local_deviation_counts_every_neighbour_for_the_support():
    """Dense points (the filter's): the support counts all neighbours within the radius, not
    the ``max_neighbours`` of the median (a strided sample beyond SUPPORT_SAMPLE points)."""
    from depth_fusion_ros.fusion import guard

    rng = np.random.default_rng(3)
    cols, rows = _pixels(rng, 0.3, (60, 60))
    _, support = guard._local_deviation(cols, rows, np.zeros(len(cols)), 12.0, 2, max_neighbours=16)
    points = np.stack((cols, rows), axis=1).astype(float)
    assert support == _local_deviation_loop(points, np.zeros(len(cols)), 12.0, 2)[1]
    assert support > 16
    cols, rows = _pixels(rng, 0.5, (120, 220))
    assert len(cols) > 3 * guard.SUPPORT_SAMPLE
    _, support = guard._local_deviation(cols, rows, np.zeros(len(cols)), 12.0, 2, max_neighbours=8)
    many = np.stack((cols, rows), axis=1).astype(float)
    exact = np.median(cKDTree(many).query_ball_point(many, r=12.0, return_length=True) - 1)
    assert abs(support - exact) <= 0.05 * exact


@pytest.mark.parametrize('case', ['consistent', 'bad_region', 'wrong_matches'])
def test_a_sampled_guard_decides_as_the_full_one(truth, case):
    """With ``max_points`` the guard checks 2 x max_points of Ω (pipeline.GUARD_SAMPLE_FACTOR):
    the same decision as checking every point, counts scaled to all of Ω, trust only in the sample."""
    single = _single(truth, 5)
    bad = np.zeros(truth.shape, dtype=bool)
    bad[:, : W // 2] = True
    density, noise, region = {
        'consistent': (0.3, 0.01, None),
        'bad_region': (0.3, 0.35, bad),
        'wrong_matches': (0.3, 0.5, None),
    }[case]
    multi = _multi(truth, 5, density=density, noise=noise, region=region)
    omega = np.isfinite(multi)
    guard = GuardConfig(full_fraction=0.8)
    full = assess(single, multi, omega, int(omega.sum()), guard)
    sampled = assess(single, multi, omega, int(omega.sum()), guard, sample=800, seed=3)
    assert sampled.decision == full.decision, (sampled.evidence, full.evidence)
    assert sampled.evidence['n_checked'] == 800 and full.evidence['n_checked'] == omega.sum()
    assert sampled.evidence['inlier_ratio'] == full.evidence['inlier_ratio']
    assert abs(sampled.evidence['trusted_fraction'] - full.evidence['trusted_fraction']) < 0.08
    n_omega = int(omega.sum())
    assert abs(sampled.evidence['n_trusted'] - full.evidence['n_trusted']) < 0.08 * n_omega
    if sampled.decision == 'fewer_points':
        assert sampled.trusted.sum() <= 800 and not (sampled.trusted & ~omega).any()
    capped = fuse_keyframe(single, multi, None, FusionConfig(mode='fast', max_points=400), guard_config=guard)
    assert capped.decision == full.decision and capped.evidence['n_checked'] <= 800


@pytest.mark.parametrize('radius', [12.0, 7.5, 3.0, 0.5])
def test_grid_counts_are_the_ball_query_counts_on_pixels(radius):
    """The support's row-span counts equal the k-d tree's ball counts on pixel positions
    (duplicates, points on the border, a sample of them), and decline anything else."""
    from depth_fusion_ros.fusion import neighbour_median

    rng = np.random.default_rng(11)
    rows, cols = np.nonzero(rng.random((50, 70)) < 0.3)
    points = np.stack((cols, rows), axis=1).astype(np.float64)
    points = np.concatenate((points, points[:9], [[0.0, 0.0], [69.0, 49.0]]))
    sample = points[::3]
    expected = cKDTree(points).query_ball_point(sample, r=radius, return_length=True)
    np.testing.assert_array_equal(neighbour_median.grid_counts(points, sample, radius), expected)
    for off_grid in (0.25, -1.0):
        with pytest.raises(ValueError, match='non-negative integer'):
            neighbour_median.grid_counts(points + off_grid, sample + off_grid, radius)
