"""The stream's scale between a metric single view and the points (fusion/stream_scale.py)."""

from __future__ import annotations

import numpy as np
import pytest

from depth_fusion_ros.fusion.pipeline import FusionConfig, fuse_keyframe
from depth_fusion_ros.fusion.scenes import make_scene
from depth_fusion_ros.fusion.stream_scale import StreamScale, StreamScaleConfig, keyframe_factor

H, W = 60, 80


def _keyframe(factor: float, seed: int = 0, noise: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """A single view and points at ``factor`` of it, with 3 % noise, on a fifth of the pixels."""
    rng = np.random.default_rng(seed)
    single = rng.uniform(1.0, 4.0, (H, W)).astype(np.float32)
    mv = np.full((H, W), np.nan, np.float32)
    points = rng.random((H, W)) < 0.2
    mv[points] = single[points] * factor * np.exp(rng.normal(0.0, noise, points.sum()))
    return single, mv


def test_a_keyframe_factor_is_the_median_ratio_and_needs_one_consensus():
    config = StreamScaleConfig()
    single, mv = _keyframe(0.4)
    assert keyframe_factor(single, mv, None, config) == pytest.approx(0.4, rel=0.01)
    # Three clusters at 0.2, 1 and 5 times: no factor most points agree on.
    rng = np.random.default_rng(1)
    spread = mv * rng.choice([0.5, 2.5, 12.5], size=mv.shape).astype(np.float32)
    assert keyframe_factor(single, spread, None, config) is None
    # Too few points (a stage-1 mask keeping 50).
    keep = np.zeros((H, W), bool)
    keep.ravel()[np.flatnonzero(np.isfinite(mv))[:50]] = True
    assert keyframe_factor(single, mv, keep, config) is None


def test_the_factor_is_taken_once_three_keyframes_agree_and_then_follows_the_window():
    scale = StreamScale()
    found = [scale.observe(*_keyframe(0.35, seed), None, stamp=seed) for seed in range(3)]
    assert found == [False, False, True]
    assert scale.factor == pytest.approx(0.35, rel=0.02)
    assert 'monocular SLAM' in scale.describe() and '0.35' in scale.describe()
    # A network adapting to the points moves the factor back towards 1, smoothly.
    for seed in range(3, 8):
        assert not scale.observe(*_keyframe(0.9, seed), None, stamp=seed)
    assert scale.factor == pytest.approx(0.9, rel=0.02)


def test_a_scale_about_right_or_points_that_disagree_change_nothing():
    near_one = StreamScale()
    for seed in range(6):
        near_one.observe(*_keyframe(0.75 if seed % 2 else 1.3, seed), None, stamp=seed)
    assert near_one.factor == 1.0 and not near_one.disagrees
    scattered = StreamScale()
    for seed, factor in enumerate([0.2, 0.5, 0.2, 0.5, 0.9, 0.2]):
        scattered.observe(*_keyframe(factor, seed), None, stamp=seed)
    assert scattered.factor == 1.0 and not scattered.disagrees


def test_warn_notes_without_scaling_off_does_nothing_and_a_new_stream_starts_over():
    warn = StreamScale(StreamScaleConfig(mode='warn'))
    assert [warn.observe(*_keyframe(3.0, s), None, stamp=s) for s in range(3)] == [False, False, True]
    assert warn.factor == 1.0 and 'not corrected' in warn.describe()
    assert StreamScaleConfig(mode=False).mode == 'off'  # an unquoted YAML off
    off = StreamScale(StreamScaleConfig(mode='off'))
    assert not any(off.observe(*_keyframe(3.0, s), None, stamp=s) for s in range(5))
    scale = StreamScale()
    for s in range(3):
        scale.observe(*_keyframe(3.0, s), None, stamp=10 + s)
    assert scale.factor == pytest.approx(3.0, rel=0.02)
    scale.observe(*_keyframe(1.0, 9), None, stamp=0)  # stamps went back: a new stream
    assert scale.factor == 1.0 and len(scale.factors) == 1


@pytest.mark.parametrize(
    'change',
    [
        {'mode': 'fix'},
        {'window': 2, 'min_keyframes': 3},
        {'engage_ratio': 1.0},
        {'max_spread': 0.0},
        {'min_share': 2},
        {'max_jump': 1.0},
        {'max_jump': float('inf')},
    ],
)
def test_bad_settings_are_refused_by_name(change):
    with pytest.raises(ValueError, match='stream_scale'):
        StreamScaleConfig(**change)


def test_the_single_view_scaled_into_the_points_unit_fuses_like_a_metric_pair():
    """What the node does with the factor: the scene's points at 0.3x, the single view scaled
    by the factor, fused as if both were in one unit (before: stage 2 found no plausible scale)."""
    scene = make_scene(W, H, n_points=W * H // 20, scale=1.0, offset=0.1, seed=3)
    mv = (scene.multi * 0.3).astype(np.float32)
    config = FusionConfig(mode='fast')
    before = fuse_keyframe(scene.single, mv, None, config)
    assert before.decision == 'single_view'
    factor = keyframe_factor(scene.single, mv, None, StreamScaleConfig(min_points=50))
    after = fuse_keyframe(scene.single * np.float32(factor), mv, None, config)
    assert after.decision in ('full', 'fewer_points')
    truth = 0.3 * scene.depth
    error_after = np.nanmean(np.abs(after.depth - truth))
    error_scaled_single = np.nanmean(np.abs(scene.single * factor - truth))
    assert error_after < error_scaled_single


def test_a_keyframe_whose_points_leave_the_stream_keeps_its_single_view():
    """Points consistent among themselves and 2.3x off the stream's ratio (on a SLAM keyframe
    stream: a match a wave along the line, kept by frames at equal baselines; docs/fusion.md "A
    keyframe off the stream") are not fused, the keyframes around it are, and a stream whose
    ratio really moves is fused again at its new level after three keyframes."""
    scene = make_scene(W, H, n_points=W * H // 20, scale=1.0, offset=0.1, seed=3)
    config = FusionConfig(mode='fast')

    def fuse(stream: StreamScale, factor: float, stamp: int):
        mv = (scene.multi * factor).astype(np.float32)
        return fuse_keyframe(scene.single, mv, None, config, stream_scale=stream, stamp=stamp)

    stream = StreamScale(StreamScaleConfig(min_points=50))
    assert all(fuse(stream, 1.25, t).decision in ('full', 'fewer_points') for t in range(4))
    off = fuse(stream, 0.55, 4)
    assert off.decision == 'single_view' and off.decision_reason.startswith('scale_jump')
    assert '2.27x off' in off.decision_reason and off.keyframe_confidence == 0.0
    assert off.evidence['scale_jump'] == pytest.approx(np.log(0.55 / 1.25), abs=0.02)
    kept = np.isfinite(scene.single)
    assert np.allclose(off.depth[kept], scene.single[kept])
    # The same keyframe without the check is fused at the points' scale.
    unchecked = StreamScale(StreamScaleConfig(min_points=50, max_jump=0.0))
    for t in range(4):
        fuse(unchecked, 1.25, t)
    assert fuse(unchecked, 0.55, 4).decision in ('full', 'fewer_points')
    # Back on the stream: fused; a ratio that stays at its new level: fused from the third on.
    assert fuse(stream, 1.25, 5).decision in ('full', 'fewer_points')
    moved = [fuse(stream, 0.55, t) for t in (6, 7, 8)]
    assert [r.decision_reason.startswith('scale_jump') for r in moved] == [True, True, False]
    assert moved[2].decision in ('full', 'fewer_points')
    # Another sequence played into the running node, with later stamps: not judged against the
    # last one's keyframes until three of its own have come.
    other = [fuse(stream, 1.3, t) for t in (100, 101, 102, 103)]
    assert not any(r.decision_reason.startswith('scale_jump') for r in other)
    assert [('scale_jump' in r.evidence) for r in other] == [False, False, False, True]
    assert other[3].decision in ('full', 'fewer_points')
    # stream_scale.mode off still judges the keyframes (it only stops the scaling).
    judged = StreamScale(StreamScaleConfig(mode='off', min_points=50))
    for t, factor in enumerate((1.0, 1.0, 1.0, 0.4)):
        judged.observe(*_keyframe(factor, t), None, stamp=t)
    assert judged.jumped and judged.factor == 1.0


class _Context:
    """What ``evaluation.methods.fusion.sequence_scale`` reads of a keyframe context."""

    def __init__(self, shared: dict, params: dict | None = None) -> None:
        self.shared, self.params = shared, params or {}

    def shared_cached(self, key, factory):
        if key not in self.shared:
            self.shared[key] = factory()
        return self.shared[key]

    def stage_params(self, stage):
        return self.params.get(stage, {})


def _fused(single, mv, kind, scale, index):
    return fuse_keyframe(single, mv, None, FusionConfig(mode='fast'), kind, stream_scale=scale, stamp=index)


def test_evaluate_takes_each_keyframe_once_per_source_and_leaves_relative_sources_alone():
    """``evaluate`` fuses each keyframe once per method, all with the sequence's stream scale of
    their single-view source: a keyframe fused twice is taken once, and the single view each
    fusion starts from is the scaled one."""
    from depth_fusion_ros.evaluation.methods.fusion import sequence_scale

    shared: dict = {}
    factors = []
    for index in range(4):
        single, mv = _keyframe(0.3, index)
        for _ in range(2):  # two methods fuse the same keyframe: one observation
            result = _fused(
                single, mv, 'metric_depth', sequence_scale(_Context(shared), 'single_view'), index
            )
        factor = result.evidence['stream_scale']
        factors.append(factor)
        assert np.allclose(result.single_aligned, single * np.float32(factor))
    assert factors[:2] == [1.0, 1.0] and factors[2] == pytest.approx(0.3, rel=0.02)
    assert len(shared['stream_scale:single_view'].factors) == 4
    single, mv = _keyframe(0.3, 9)
    inverse = _fused(1.0 / single, mv, 'inverse_depth', sequence_scale(_Context(shared), 'single_view'), 9)
    assert inverse.evidence['stream_scale'] == 1.0
    assert 'scale_jump' not in inverse.evidence  # not observed: no jump of the metric keyframes
    warned: dict = {}
    for index in range(4):
        single, mv = _keyframe(0.3, index)
        context = _Context(warned, {'stream_scale': {'mode': 'warn'}})
        assert (
            _fused(single, mv, 'metric_depth', sequence_scale(context, 'single_view'), index).evidence[
                'stream_scale'
            ]
            == 1.0
        )
    assert warned['stream_scale:single_view'].disagrees
